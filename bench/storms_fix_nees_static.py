"""Storms' Bayes grid fix covariance checked without a filter: which part of R is conservative.

On the Storms scenarios' synthetic hallway map (``examples/scenarios/storms_hallway.toml``: seed 41, 42 m + 17 m), the
truth is drawn uniformly along the main hallway (2-38 m north, within 0.6 m of the centre line), the reading is the
map there plus 1 mG per axis, and the prior is N(truth + e, sp^2 I) with e ~ N(0, sp^2 I): an honest prior of sigma
``sp``. One Bayes grid update per trial (no guards, the map stated exact), and per prior sigma the fixes' NEES (2-D,
each fix's error against its own R; 2 = consistent), the RMS of the fixes' errors and of R's sigmas, over the fixes
within 0.5 m of the truth (the right lobe) and over all. ``--matcher`` lays options over the matcher's.

    python bench/storms_fix_nees_static.py
    python bench/storms_fix_nees_static.py --matcher '{"line_extent": "lobe", "fix_at": "likelihood"}'
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np


def run(matcher: dict, prior_sigmas: list[float], trials: int, seed: int) -> list[dict]:
    from magnav_ins.aiding.matchers import BayesGridMatcher
    from magnav_ins.core.types import FieldKind, FieldReadings, NavEstimate, NavState
    from magnav_ins.maps import synthetic

    origin = (np.radians(39.78), np.radians(-84.08), 0.0)
    fmap = synthetic.hallway_map(np.random.default_rng(41), origin=origin, main_length_m=42.0, side_length_m=17.0)
    rng = np.random.default_rng(seed)
    out = []
    for sp in prior_sigmas:
        bg = BayesGridMatcher(**{"map_sigma": 0.0, "guards": False, **matcher})
        q, err, sig = [], [], []
        for _ in range(trials):
            truth = np.array([rng.uniform(2.0, 38.0), 1.143 + rng.uniform(-0.6, 0.6)])
            lat, lon = fmap.from_local(truth[:1], truth[1:])
            z = fmap.value(lat, lon)[0] + rng.normal(0.0, 100.0, 3)
            pn, pe = truth + rng.normal(0.0, sp, 2)
            plat, plon = fmap.from_local(np.array([pn]), np.array([pe]))
            P = np.eye(15) * 1e-4
            P[:2, :2] = np.eye(2) * sp**2
            nav = NavState(0.0, float(plat[0]), float(plon[0]), 0.0, np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))
            st = bg.initiate(NavEstimate(nav, P))
            fix = bg.to_fix(
                bg.update(st, FieldReadings(np.array([0.0]), z[None], 100.0, FieldKind.VECTOR_FIELD_NT), fmap)
            )
            if not fix.available:
                continue
            fn, fe = fmap.to_local(np.array([fix.lat]), np.array([fix.lon]))
            d = np.array([float(np.ravel(fn)[0]), float(np.ravel(fe)[0])]) - truth
            R = np.asarray(fix.cov_ne)
            q.append(float(d @ np.linalg.solve(R, d)))
            err.append(d)
            sig.append(np.sqrt(np.diag(R)))
        q_a, e_a, s_a = np.array(q), np.array(err), np.array(sig)
        right = np.hypot(*e_a.T) <= 0.5
        out.append(
            {
                "prior_sigma_m": sp,
                "fixes": int(len(q_a)),
                "fix_nees_mean": float(q_a.mean()),
                "fix_nees_median": float(np.median(q_a)),
                "wrong_lobe": int((~right).sum()),
                "fix_nees_mean_right_lobe": float(q_a[right].mean()),
                "error_rms_ne_right_lobe_m": np.sqrt((e_a[right] ** 2).mean(0)).round(4).tolist(),
                "r_sigma_rms_ne_right_lobe_m": np.sqrt((s_a[right] ** 2).mean(0)).round(4).tolist(),
            }
        )
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--matcher", type=json.loads, default={}, help="JSON object laid over the matcher's options")
    ap.add_argument("--prior-sigmas", type=float, nargs="*", default=[0.1, 0.2, 0.5])
    ap.add_argument("--trials", type=int, default=300)
    ap.add_argument("--seed", type=int, default=5)
    args = ap.parse_args(argv)
    for row in run(args.matcher, args.prior_sigmas, args.trials, args.seed):
        print(json.dumps({"matcher": args.matcher, **row}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
