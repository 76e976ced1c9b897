"""Storms (2009, seed 004) sec. 4.5, Table 4.2: the leader-follower experiment, 3 vs 4 leader sensors, with and
without the follower's position reset (:mod:`magnav_ins.studies.leader_follower`).

The hallway is the synthetic Storms-like map of ``examples/scenarios/storms_hallway.toml`` (the same seed and
lengths), the route its centre lines. Prints the table beside Storms' (50 runs per row):

    python bench/leader_follower.py --runs 50
    python bench/leader_follower.py --runs 50 --json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: Storms Table 4.2 (50 runs each): completed, successful, past the turn, not making the turn
STORMS_TABLE_4_2 = {
    (3, False): (0, 0, 0, 50),
    (3, True): (2, 18, 33, 17),
    (4, False): (9, 18, 38, 12),
    (4, True): (23, 36, 41, 9),
}
ROUTE = np.array([[0.0, 1.143], [40.767, 1.143], [40.767, 17.5]])


def hallway(centre_fraction: float = 1.0, quiet: tuple[float, float] | None = None):
    from magnav_ins.maps.synthetic import hallway_map

    origin = (np.radians(39.78), np.radians(-84.08), 0.0)
    return hallway_map(np.random.default_rng(41), origin=origin, main_length_m=42.0, side_length_m=17.0,
                       centre_fraction=centre_fraction, quiet_side_m=quiet)  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    from magnav_ins.studies.leader_follower import LeaderFollowerConfig, run_follower, table_4_2

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--seed", type=int, default=2009)
    ap.add_argument("--centre-fraction", type=float, default=1.0, help="map variation at the centre line (0-1)")
    ap.add_argument("--quiet", type=float, nargs=2, default=None, help="a quiet stretch of the side hallway (m)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    fmap = hallway(args.centre_fraction, None if args.quiet is None else tuple(args.quiet))
    rows = []
    for (sensors, reset), storms in STORMS_TABLE_4_2.items():
        cfg = LeaderFollowerConfig(sensors=sensors, position_reset=reset)
        outs = [
            run_follower(cfg, fmap, ROUTE, ROUTE[1], np.random.default_rng([args.seed, sensors, int(reset), r]))
            for r in range(args.runs)
        ]
        tab = table_4_2(outs, cfg)
        good = [o.cross_rms_m for o in outs if o.side_m >= cfg.successful_m]
        rows.append(
            {
                "sensors": sensors,
                "position_reset": reset,
                **tab,
                "resets_mean": float(np.mean([o.resets for o in outs])),
                "fix_availability": sum(o.fixes for o in outs) / max(1, sum(o.attempts for o in outs)),
                "cross_track_rms_successful_m": float(np.median(good)) if good else None,
                "storms": dict(zip(("completed", "successful", "past_turn", "not_making_turn"), storms, strict=True)),
            }
        )
    wall = time.perf_counter() - t0
    if args.json:
        print(json.dumps({"leader_follower": rows, "wall_s": wall}, separators=(",", ":")))
        return 0
    print("| leader sensors, follower reset | completed (>= 16 m) | successful (>= 10 m) | past the turn "
          "| not making the turn | cross-track RMS of successful runs | Storms Table 4.2 (50 runs) |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---|")
    for r in rows:
        s = r["storms"]
        n = r["runs"]
        xt = "-" if r["cross_track_rms_successful_m"] is None else f"{r['cross_track_rms_successful_m']:.2f} m"
        print(
            f"| {r['sensors']}, {'reset' if r['position_reset'] else 'no reset'} | {r['completed']} / {n} "
            f"| {r['successful']} / {n} | {r['past_turn']} / {n} | {r['not_making_turn']} / {n} | {xt} "
            f"| {s['completed']} / {s['successful']} / {s['past_turn']} / {s['not_making_turn']} |"
        )
    print(f"\n({wall:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
