"""The real-data integrity suite (issue 13): every estimator with default matcher and fuser settings, flown over
real survey lines with their own recorded readings, matched against maps gridded without those lines.

Groups (each case is one survey line at one speed; every case runs ``--seeds`` Monte Carlo runs, each with its own
IMU errors, initial errors and sensor noise, from a seed derived from the case's name):

* ``osborne_tactical``, ``osborne_navigation``: the 22 tie lines of ``builtin:osborne-tie-lines`` (1990 Osborne
  survey, Queensland) against ``builtin:osborne-magnetic`` (gridded from the east-west flight lines only), at 50,
  65 and 80 m/s, with a tactical (HG-1700 class) and a navigation-grade (H764-G class) IMU.
* ``rio``: the 9 east-west tie lines (``TIE``) of the 1978 Rio de Janeiro survey
  (``../shared/data/rio_magnetic/rio-magnetic.csv.xz``, CC-BY-NC-4.0: benchmark only, never shipped) against a map
  gridded from its 128 north-south flight lines (``LINE``) only, at the same speeds, tactical IMU. Skipped, with
  the reason in the output, when ``../shared/data`` is absent or the survey cannot be read.

Estimators (the same for every case; no setting tuned per case): ``ml+ukf``, ``pmht+ukf``, ``particle_ins+ukf``,
``ml+graph`` (``bayes_grid+ukf`` needs a vector map; both surveys are scalar total-field). Matchers and fusers take
their defaults; the study set-up is stated once here: readings every 0.5 s with 1 nT noise added to the real
readings, the IMU at 20 Hz, the vertical channel held at the survey height (a barometer's job), batch windows of
``WINDOW`` readings matched every ``WINDOW`` readings (non-overlapping sections, so the fixes are as independent as
the map error lets them be), a recursive matcher asked for a fix as often, PMHT on its own default batch.

Per case and estimator it prints (stderr with ``--json``) RMS, max, NEES, fix NEES, HPL exceedance, availability,
divergence and the free-inertial RMS; ``--json`` prints one line on stdout:
``{"groups": {"osborne_tactical": {ESTIMATOR: {...}}, "osborne_navigation": {...}, "rio": {...}}}`` with, per
estimator, the ``metrics.json`` keys ``rms_horizontal_m``, ``nees_mean``, ``fix_nees_mean``, ``hpl_exceedance``,
``divergence_rate`` (and ``max_horizontal_m``, ``availability``, ``hpl_median_m``, ``runs``) plus
``free_rms_horizontal_m``, pooled over the group's cases and runs.

    python bench/realdata.py --json [--quick] [--jobs 2] [--seeds 2]

``--quick``: four Osborne lines at 65 m/s, one seed, both grades, two Rio lines (the CI subset).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import zlib
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"
RIO_SURVEY = SHARED_DATA / "rio_magnetic" / "rio-magnetic.csv.xz"

OSBORNE_SURVEY = "builtin:osborne-tie-lines"
OSBORNE_MAP = "builtin:osborne-magnetic"
SPEEDS_MPS = (50.0, 65.0, 80.0)
IMU_RATE_HZ = 20.0
READING_INTERVAL_S = 0.5
READING_NOISE_NT = 1.0
#: readings per batch-matcher section and between fix attempts (30 s)
WINDOW = 60
#: Rio map node spacing (m): flight lines 1 km apart, ~100 m along-track
RIO_SPACING_M = 250.0
#: Rio readings every 1 s (the survey sampled every ~100 m; faster readings would only interpolate it)
RIO_READING_INTERVAL_S = 1.0

ESTIMATORS: tuple[dict[str, Any], ...] = (
    {"name": "ml+ukf", "matcher": {"kind": "ml"}, "fusion": {"kind": "ukf"}, "window": WINDOW, "match_every": WINDOW},
    {"name": "pmht+ukf", "matcher": {"kind": "pmht"}, "fusion": {"kind": "ukf"}},
    {"name": "particle_ins+ukf", "matcher": {"kind": "particle_ins"}, "fusion": {"kind": "ukf"},
     "match_every": WINDOW},
    {"name": "ml+graph", "matcher": {"kind": "ml"}, "fusion": {"kind": "graph"}, "window": WINDOW,
     "match_every": WINDOW},
)  # fmt: skip

#: the keys of each estimator in the --json line (metrics.json's, plus free_rms_horizontal_m)
JSON_KEYS = (
    "rms_horizontal_m",
    "max_horizontal_m",
    "nees_mean",
    "fix_nees_mean",
    "hpl_exceedance",
    "hpl_median_m",
    "availability",
    "divergence_rate",
)


@dataclass(frozen=True)
class Case:
    """One survey line flown at one speed with one IMU grade; ``map_keys`` / ``trajectory_keys``: further
    ``[map]`` / ``[trajectory]`` keys (column mapping, line types, grid spacing)."""

    group: str
    survey: str
    map_path: str
    line: int
    speed_mps: float
    grade: str
    reading_interval_s: float = READING_INTERVAL_S
    map_keys: tuple[tuple[str, Any], ...] = ()
    trajectory_keys: tuple[tuple[str, Any], ...] = ()

    @property
    def name(self) -> str:
        return f"{self.group}:{self.line}@{self.speed_mps:g}"

    @property
    def seed(self) -> int:
        return zlib.crc32(self.name.encode("utf-8"))

    def scenario(self, estimators: tuple[dict[str, Any], ...]):
        from magnav_ins.studies.scenario import scenario_from_dict

        data = {
            "name": self.name,
            "seed": self.seed,
            "trajectory": {"kind": "survey_line", "survey": self.survey, "line": self.line,
                           "speed_mps": self.speed_mps, **dict(self.trajectory_keys)},
            "imu": {"grade": self.grade, "rate_hz": IMU_RATE_HZ},
            "map": {"path": self.map_path, "kind": "total_field_anomaly_nt", **dict(self.map_keys)},
            "sensor": {"kind": "scalar_magnetometer", "source": "survey", "sigma": READING_NOISE_NT,
                       "interval_s": self.reading_interval_s},
            "estimator": [dict(e) for e in estimators],
        }  # fmt: skip
        return scenario_from_dict(data)


def osborne_lines() -> list[int]:
    """The 22 tie-line numbers of the shipped Osborne tie-line survey."""
    from magnav_ins.maps.builtin import load_survey_lines

    return [int(x) for x in load_survey_lines(OSBORNE_SURVEY).line_ids()]


#: the Rio survey read as downloaded (h14's column mapping): our name -> the file's column
RIO_COLUMNS = {"height_ellipsoidal_m": "height_ell_m", "line": "line_number"}
#: a tie line shorter than this is a stub at the survey's edge (9-29 readings), left out (m)
RIO_MIN_LINE_M = 20e3


def rio_cases(quick: bool) -> tuple[list[Case], str]:
    """The Rio cases (the long tie lines, tactical IMU), or none and the reason."""
    if not RIO_SURVEY.is_file():
        return [], f"{RIO_SURVEY.name} not found (../shared/data is not beside the project)"
    from magnav_ins.core.frames import latlon_to_meters
    from magnav_ins.maps import io as maps_io

    s = maps_io.read_survey(RIO_SURVEY, columns=RIO_COLUMNS).of_type("TIE")
    lines = []
    for ln in s.line_ids():
        m = s.line == ln
        dn, de = latlon_to_meters(s.lat[m].max() - s.lat[m].min(), s.lon[m].max() - s.lon[m].min(), s.lat[m].mean())
        if np.hypot(dn, de) >= RIO_MIN_LINE_M:
            lines.append(int(ln))
    map_keys = (("columns", RIO_COLUMNS), ("line_type", "LINE"), ("grid_spacing_m", RIO_SPACING_M))
    traj_keys = (("columns", RIO_COLUMNS), ("line_type", "TIE"))
    speeds = (65.0,) if quick else SPEEDS_MPS
    if quick:
        lines = lines[:2]
    cases = [
        Case("rio", str(RIO_SURVEY), str(RIO_SURVEY), ln, v, "tactical", RIO_READING_INTERVAL_S, map_keys, traj_keys)
        for ln in lines
        for v in speeds
    ]
    return cases, ""


def all_cases(quick: bool) -> tuple[list[Case], dict[str, str]]:
    lines = osborne_lines()
    speeds = (65.0,) if quick else SPEEDS_MPS
    if quick:
        lines = [lines[i] for i in np.linspace(0, len(lines) - 1, 4).round().astype(int)]
    cases = [
        Case(f"osborne_{grade}", OSBORNE_SURVEY, OSBORNE_MAP, ln, v, grade)
        for grade in ("tactical", "navigation")
        for ln in lines
        for v in speeds
    ]
    rio, why = rio_cases(quick)
    return cases + rio, ({"rio": why} if why else {})


def run_case(case: Case, seeds: int) -> tuple[Case, list[Any], float]:
    """All runs of one case in this process (the truth and the map are built once); returns their summaries."""
    from magnav_ins.studies import runner
    from magnav_ins.studies.model import PipelineModel

    t0 = time.perf_counter()
    model = PipelineModel(case.scenario(ESTIMATORS))
    out = runner.execute(model, seeds, case.seed, jobs=1, quiet=True)
    return case, out, time.perf_counter() - t0


def pooled(summaries: list[Any]) -> dict[str, Any]:
    """Each estimator's metrics over the given run summaries (different cases pooled), plus the free-inertial RMS."""
    from magnav_ins.studies import metrics as M
    from magnav_ins.studies.scenario import FREE_INERTIAL

    out: dict[str, Any] = {}
    free = M.aggregate([s.estimators[FREE_INERTIAL].metrics for s in summaries], None, FREE_INERTIAL)
    for name in (e["name"] for e in ESTIMATORS):
        es = [s.estimators[name] for s in summaries]
        m = M.aggregate([e.metrics for e in es], es[0].matcher, es[0].fusion)
        row = {k: m[k] for k in JSON_KEYS}
        row["runs"] = len(es)
        row["free_rms_horizontal_m"] = free["rms_horizontal_m"]
        out[name] = row
    return out


def _fmt(x: Any, pct: bool = False) -> str:
    if x is None:
        return "-"
    return f"{100 * x:.1f}%" if pct else (f"{x:.3g}" if abs(x) >= 1e4 else f"{x:.1f}")


def case_lines(case: Case, metrics: dict[str, Any]) -> list[str]:
    rows = []
    for name, m in metrics.items():
        rows.append(
            f"{case.group:20s} {case.line:6d} {case.speed_mps:4.0f} {name:18s} {_fmt(m['rms_horizontal_m']):>8s} "
            f"{_fmt(m['max_horizontal_m']):>8s} {_fmt(m['nees_mean']):>6s} {_fmt(m['fix_nees_mean']):>6s} "
            f"{_fmt(m['hpl_exceedance'], True):>6s} {_fmt(m['availability'], True):>6s} "
            f"{_fmt(m['divergence_rate'], True):>6s} {_fmt(m['free_rms_horizontal_m']):>8s}"
        )
    return rows


HEADER = (
    f"{'group':20s} {'line':>6s} {'v':>4s} {'estimator':18s} {'RMS':>8s} {'max':>8s} {'NEES':>6s} {'fNEES':>6s} "
    f"{'HPLexc':>6s} {'avail':>6s} {'div':>6s} {'free':>8s}"
)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--json", action="store_true", help="print the group figures as one JSON line on stdout")
    p.add_argument("--quick", action="store_true", help="the CI subset (under 3 minutes on 2 cores)")
    p.add_argument("--seeds", type=int, default=None, help="Monte Carlo runs per case (default 2; --quick 1)")
    p.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    p.add_argument("--only", default=None, help="comma-separated groups to run (default all)")
    args = p.parse_args(argv)
    seeds = args.seeds if args.seeds is not None else (1 if args.quick else 2)
    t0 = time.perf_counter()
    cases, skipped = all_cases(args.quick)
    if args.only:
        keep = set(args.only.split(","))
        cases = [c for c in cases if c.group in keep]
    log = sys.stderr if args.json else sys.stdout
    print(HEADER, file=log, flush=True)
    by_group: dict[str, list[Any]] = {}
    case_wall: list[float] = []
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futs = [pool.submit(run_case, c, seeds) for c in cases]
        for fut in as_completed(futs):
            case, summaries, wall = fut.result()
            case_wall.append(wall)
            by_group.setdefault(case.group, []).extend(summaries)
            for line in case_lines(case, pooled(summaries)):
                print(line, file=log, flush=True)
    groups: dict[str, Any] = {}
    for g in ("osborne_tactical", "osborne_navigation", "rio"):
        if g in by_group:
            groups[g] = pooled(by_group[g])
        else:
            groups[g] = {"skipped": skipped.get(g, "not run")}
    wall = time.perf_counter() - t0
    print(
        f"{len(cases)} cases x {seeds} runs in {wall:.0f} s with {args.jobs} jobs "
        f"(case wall median {np.median(case_wall) if case_wall else 0:.0f} s)",
        file=log,
    )
    for g, rows in groups.items():
        print(f"\n{g}:", file=log)
        for name, m in rows.items():
            print(f"  {name:18s} {m}", file=log)
    if args.json:
        print(json.dumps({"groups": groups}, allow_nan=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
