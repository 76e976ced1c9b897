"""The real-data integrity suite (issue 13): every estimator with default matcher and fuser settings, flown over
real survey lines with their own recorded readings, matched against maps gridded without those lines.

Groups (a *case* is one survey line flown at one speed with one IMU grade):

* ``osborne_tactical``, ``osborne_navigation``: the 22 tie lines of ``builtin:osborne-tie-lines`` (the 1990
  Osborne survey, Queensland) against ``builtin:osborne-magnetic`` (gridded from the east-west flight lines only),
  at 50, 65 and 80 m/s, with a tactical (HG-1700 class) and a navigation-grade (H764-G class) IMU.
* ``rio``: the long east-west tie lines (``TIE``, the stubs under 20 km at the survey's edge left out) of the 1978
  Rio de Janeiro survey (``../shared/data/rio_magnetic/rio-magnetic.csv.xz``, CC-BY-NC-4.0: studies only, never
  shipped) against a grid of its 128 north-south flight lines (``LINE``) only, read through the survey column
  mapping, at the same speeds, tactical IMU. The survey's other tie lines, not the one flown, measure the map's
  error between line sets at their crossovers (the map's error layer, :mod:`magnav_ins.maps.error_layer`
  "Crossovers"; never gridded): the line flown is used for nothing in the map. Skipped, with the reason, when the
  file is not there.

Estimators (:data:`ESTIMATORS`, the same for every case, nothing tuned per case): ``ml+ukf``, ``pmht+ukf``,
``particle_ins+ukf``, ``ml+graph``; ``bayes_grid+ukf`` needs a vector map and both surveys are scalar total field.
Matchers and fusers take their defaults. The set-up, stated once: 1 nT noise added to the real readings, taken
every second (50-80 m apart: about two per correlation length of the Osborne map error; Rio's survey is sampled
every ~100 m), the IMU at 10 Hz (straight lines: coning is negligible), estimates reported at :data:`OUTPUT_SAMPLES`
epochs per run,
the vertical channel held at the survey height (a barometer's job, as in every study), batch sections of
:data:`WINDOW` readings matched every :data:`WINDOW` readings (non-overlapping sections, so the fixes are as
independent as the map error lets them be), a recursive matcher asked for a fix every :data:`RECURSIVE_EVERY`
readings (its increment holds every reading since its last issued fix, so asking more often splits no evidence),
PMHT on its own default batch.

Each case runs ``seeds`` Monte Carlo runs (default :data:`DEFAULT_SEEDS`), with IMU errors, initial errors and sensor noise drawn from
the run's seed; the runs of all cases are one study for :func:`magnav_ins.studies.runner.execute` (so ``--jobs``,
Dask and the signal handling are the runner's), run ``i`` being case ``i // seeds``. Results are the
``metrics.json`` figures (:mod:`.metrics`) pooled over each group's cases and runs, plus the free-inertial RMS.

Beside them, each case's information bound (:func:`case_bound`, :mod:`.crlb`): the posterior Cramér-Rao bound of the
readings' model ``z = m(p) + c + b(p) + v`` (map error layer in the variance, readings counted by their effective
number along its correlation length, the level ``c`` unknown), the free INS's covariance along the same flight, and
whether Wang's test flags the bound itself; :func:`suite_bounds` gives them without flying anything.
"""

from __future__ import annotations

import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..core.errors import ConfigError
from .runner import RunOutput, RunSummary
from .scenario import FREE_INERTIAL

OSBORNE_SURVEY = "builtin:osborne-tie-lines"
OSBORNE_MAP = "builtin:osborne-magnetic"
#: where the project keeps the Rio survey (relative to the project folder, as ``../shared/data``)
RIO_SURVEY_DEFAULT = Path("..") / "shared" / "data" / "rio_magnetic" / "rio-magnetic.csv.xz"
#: the Rio survey as downloaded: our column name -> the file's
RIO_COLUMNS = {"height_ellipsoidal_m": "height_ell_m", "line": "line_number"}
#: Rio tie lines shorter than this are stubs at the survey's edge (9-29 readings), left out (m)
RIO_MIN_LINE_M = 20e3
#: Rio map node spacing (m): flight lines 1 km apart, readings ~100 m apart along them
RIO_SPACING_M = 250.0
RIO_READING_INTERVAL_S = 1.0

GROUPS = ("osborne_tactical", "osborne_navigation", "rio")
SPEEDS_MPS = (50.0, 65.0, 80.0)
QUICK_SPEEDS_MPS = (65.0,)
IMU_RATE_HZ = 10.0
#: one reading a second: 50-80 m apart, about two per correlation length of the map error (~150 m at Osborne)
READING_INTERVAL_S = 1.0
READING_NOISE_NT = 1.0
#: readings per batch-matcher section and between its fix attempts (60 s: 3-4.8 km, about 15-25 correlation lengths
#: of the Osborne map error; 30-reading sections held too little evidence for a fix on most of the Osborne tie lines:
#: ML availability 25 % tactical / 15 % navigation, against 40 % / 35 % with 60 on the same lines and seed)
WINDOW = 60
#: readings between a recursive matcher's fix attempts (30 s)
RECURSIVE_EVERY = 30
#: output epochs per run (every 4-12 s): each costs the fusers a covariance (the graph a marginal); the NEES and HPL
#: statistics pool them over all runs of a group (a few thousand epochs)
OUTPUT_SAMPLES = 100
#: Monte Carlo runs per case (seeds derived from the run index, not chosen)
DEFAULT_SEEDS = 2

ESTIMATORS: tuple[dict[str, Any], ...] = (
    {"name": "ml+ukf", "matcher": {"kind": "ml"}, "fusion": {"kind": "ukf"}, "window": WINDOW, "match_every": WINDOW},
    {"name": "pmht+ukf", "matcher": {"kind": "pmht"}, "fusion": {"kind": "ukf"}},
    {"name": "particle_ins+ukf", "matcher": {"kind": "particle_ins"}, "fusion": {"kind": "ukf"},
     "match_every": RECURSIVE_EVERY},
    {"name": "ml+graph", "matcher": {"kind": "ml"}, "fusion": {"kind": "graph"}, "window": WINDOW,
     "match_every": WINDOW},
)  # fmt: skip

#: the figures kept per estimator (``metrics.json`` keys) besides ``free_rms_horizontal_m`` and ``runs``
KEYS = (
    "rms_horizontal_m",
    "max_horizontal_m",
    "nees_mean",
    "fix_nees_mean",
    "hpl_exceedance",
    "hpl_median_m",
    "availability",
    "divergence_rate",
    "nees_divergence_rate",
)


@dataclass(frozen=True)
class Case:
    """One survey line flown at ``speed_mps`` with IMU ``grade``; ``map_keys`` / ``trajectory_keys``: further
    ``[map]`` / ``[trajectory]`` scenario keys (column mapping, line types, grid spacing)."""

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

    def scenario(self, estimators: tuple[dict[str, Any], ...] = ESTIMATORS):
        """The case as a validated :class:`~magnav_ins.studies.scenario.Scenario`."""
        from .scenario import scenario_from_dict

        data = {
            "name": self.name,
            "seed": zlib.crc32(self.name.encode("utf-8")),
            "trajectory": {"kind": "survey_line", "survey": self.survey, "line": self.line,
                           "speed_mps": self.speed_mps, **dict(self.trajectory_keys)},
            "imu": {"grade": self.grade, "rate_hz": IMU_RATE_HZ},
            "map": {"path": self.map_path, "kind": "total_field_anomaly_nt",
                    **{k: list(v) if isinstance(v, tuple) else v for k, v in self.map_keys}},
            "sensor": {"kind": "scalar_magnetometer", "source": "survey", "sigma": READING_NOISE_NT,
                       "interval_s": self.reading_interval_s},
            "estimator": [dict(e) for e in estimators],
        }  # fmt: skip
        return scenario_from_dict(data)


def osborne_cases(quick: bool) -> list[Case]:
    """Every Osborne tie line (``quick``: four spread over the survey) at each speed, for both grades."""
    from ..maps.builtin import load_survey_lines

    lines = [int(x) for x in load_survey_lines(OSBORNE_SURVEY).line_ids()]
    if quick:
        lines = [lines[i] for i in np.linspace(0, len(lines) - 1, 4).round().astype(int)]
    speeds = QUICK_SPEEDS_MPS if quick else SPEEDS_MPS
    return [
        Case(f"osborne_{grade}", OSBORNE_SURVEY, OSBORNE_MAP, ln, v, grade)
        for grade in ("tactical", "navigation")
        for ln in lines
        for v in speeds
    ]


def rio_cases(survey: Path, quick: bool) -> tuple[list[Case], str]:
    """The Rio cases (the long tie lines; ``quick``: two) or none and the reason."""
    if not survey.is_file():
        return [], f"{survey}: not found (the Rio survey lives in ../shared/data beside the project)"
    from ..core.frames import latlon_to_meters
    from ..maps import io as maps_io

    s = maps_io.read_survey(survey, columns=RIO_COLUMNS).of_type("TIE")
    lines = []
    for ln in s.line_ids():
        m = s.line == ln
        dn, de = latlon_to_meters(np.ptp(s.lat[m]), np.ptp(s.lon[m]), float(np.mean(s.lat[m])))
        if np.hypot(dn, de) >= RIO_MIN_LINE_M:
            lines.append(int(ln))
    if quick:
        lines = lines[:2]
    map_keys = (("columns", RIO_COLUMNS), ("line_type", "LINE"), ("grid_spacing_m", RIO_SPACING_M))
    traj_keys = (("columns", RIO_COLUMNS), ("line_type", "TIE"))
    speeds = QUICK_SPEEDS_MPS if quick else SPEEDS_MPS
    path = str(survey.resolve())
    return [
        Case("rio", path, path, ln, v, "tactical", RIO_READING_INTERVAL_S, (*map_keys, ("exclude_lines", (ln,))),
             traj_keys)
        for ln in lines
        for v in speeds
    ], ""  # fmt: skip


@dataclass(frozen=True)
class SuiteModel:
    """A :class:`~magnav_ins.studies.runner.StudyModel` over many cases: run ``i`` is run ``i % seeds`` of case
    ``i // seeds`` (its seed the runner's ``i``-th spawned sequence); every case has the same estimators."""

    cases: tuple[Case, ...]
    seeds: int = 1
    name: str = "realdata suite"
    estimators: tuple[dict[str, Any], ...] = ESTIMATORS
    _models: dict[int, Any] = field(default_factory=dict, compare=False, repr=False)

    def estimator_names(self) -> tuple[str, ...]:
        return (*(e["name"] for e in self.estimators), FREE_INERTIAL)

    def case_of(self, index: int) -> Case:
        return self.cases[index // self.seeds]

    def run(self, seed: np.random.SeedSequence) -> RunOutput:
        from .model import PipelineModel

        index = int(seed.spawn_key[-1])
        k = index // self.seeds
        if k not in self._models:  # a worker keeps the models of its cases (truth and map memoised by model.py)
            self._models[k] = PipelineModel(self.cases[k].scenario(self.estimators), max_samples=OUTPUT_SAMPLES)
        return self._models[k].run(seed)


def median_run_rms(runs: list[Any]) -> float | None:
    """The median over runs of each run's horizontal RMS error (m; runs of any cases, each over its own finite
    samples): the issue's "median RMS" of a group, which one long bad run cannot move as it moves the pooled RMS.
    None when no run has a finite error."""
    per_run = [float(np.sqrt(np.mean(e[np.isfinite(e)] ** 2))) for e in (np.asarray(r.e, float) for r in runs)
               if np.isfinite(e).any()]  # fmt: skip
    return float(np.median(per_run)) if per_run else None


def pooled(
    summaries: list[RunSummary], estimators: tuple[dict[str, Any], ...] = ESTIMATORS
) -> dict[str, dict[str, Any]]:
    """Each estimator's figures (:data:`KEYS`) over ``summaries`` (runs of any cases), with ``runs``, the median
    of the runs' RMS (:func:`median_run_rms`) as ``median_run_rms_horizontal_m`` and the free-inertial baseline's
    RMS as ``free_rms_horizontal_m``; ``estimators`` the ones the runs flew."""
    from . import metrics as M

    free = M.aggregate([s.estimators[FREE_INERTIAL].metrics for s in summaries], None, FREE_INERTIAL)
    out: dict[str, dict[str, Any]] = {}
    for name in (e["name"] for e in estimators):
        es = [s.estimators[name] for s in summaries]
        m = M.aggregate([e.metrics for e in es], es[0].matcher, es[0].fusion)
        out[name] = {
            **{k: m[k] for k in KEYS},
            "median_run_rms_horizontal_m": median_run_rms([e.metrics for e in es]),
            "runs": len(es),
            "free_rms_horizontal_m": free["rms_horizontal_m"],
        }
    return out


# ------------------------------------------------------------------------------------------------ the bound
def case_bound(case: Case, count_correlation: bool = True, draws: int = 0) -> dict[str, Any]:
    """The information bound of one case (:func:`magnav_ins.studies.crlb.flight_crlb` with the suite's reading
    model ``z = m(p) + c + b(p) + v``: the map's error layer at the true position added to the 1 nT sensor variance,
    readings weighed by ``min(1, ds / ell)``, the level ``c`` a state with the matchers' prior), next to the free
    INS's covariance along the same steps, both on the run's output samples (:data:`OUTPUT_SAMPLES`).

    Returns ``t`` (s), ``crlb`` and ``free`` (``sqrt(P_NN + P_EE)``, m, per sample), ``crlb_rms`` / ``free_rms``
    (RMS over the samples, m), the quarter means ``crlb_q2``, ``crlb_q4``, ``free_q2``, ``free_q4`` (m) and
    ``crlb_wang`` / ``free_wang``: whether Wang's two conditions (:func:`magnav_ins.studies.metrics.is_divergent`)
    hold for an error following the bound (or the free covariance, tested against itself). ``count_correlation``:
    False counts every reading as independent (no correlation weighting; a still lower bound). ``draws`` > 0 adds
    ``crlb_wang_mc`` and ``free_wang_mc``: the share of that many runs of the estimator attaining the bound
    (:func:`magnav_ins.studies.crlb.bound_monte_carlo`, seeded from the case name) that Wang's test flags against
    the free INS of the same draw, and of the free INS against itself."""
    from ..aiding.matchers.map_error import resolve_level, resolve_map_error
    from . import metrics as M
    from .crlb import flight_crlb
    from .model import PipelineModel, output_dt

    model = PipelineModel(case.scenario(ESTIMATORS[:1]), max_samples=OUTPUT_SAMPLES)
    sc, sh = model.scenario, model.shared()
    truth, fmap = sh["truth"], sh["map"]
    dt_out = output_dt(sc, truth, OUTPUT_SAMPLES)
    sel = np.unique(
        np.append(np.searchsorted(truth.t, np.arange(truth.t[0], truth.t[-1] + 1e-9, dt_out) - 1e-6), len(truth.t) - 1)
    )  # the samples of PipelineModel.run
    t_out = truth.t[sel]
    me = resolve_map_error(fmap)
    te, b = flight_crlb(
        sc, truth, sh["imu"], fmap, map_error=me, level_sigma=resolve_level(fmap).sigma,
        count_correlation=count_correlation,
    )  # fmt: skip
    _, f = flight_crlb(sc, truth, sh["imu"], fmap, readings=False)
    crlb = np.sqrt(np.interp(t_out, te, b**2))
    free = np.sqrt(np.interp(t_out, te, f**2))
    qb, qf = M.quarter_means(crlb), M.quarter_means(free)
    mc: dict[str, float] = {}
    if draws > 0:
        from .crlb import bound_monte_carlo, flight_system

        _, P0, Phi, Q, J = flight_system(
            sc, truth, sh["imu"], fmap, map_error=me, level_sigma=resolve_level(fmap).sigma,
            count_correlation=count_correlation,
        )  # fmt: skip
        err, fre = bound_monte_carlo(P0, Phi, Q, J, draws, np.random.default_rng(zlib.crc32(case.name.encode())))
        at = np.clip(np.searchsorted(te, t_out - 1e-6), 0, len(te) - 1)  # the step end at (or just after) a sample
        mc = {
            "crlb_wang_mc": float(np.mean([M.is_divergent(a[at], z[at]) for a, z in zip(err, fre, strict=True)])),
            "free_wang_mc": float(np.mean([M.is_divergent(z[at], z[at]) for z in fre])),
        }
    return {
        **mc,
        "t": t_out,
        "crlb": crlb,
        "free": free,
        "crlb_rms": float(np.sqrt(np.mean(crlb**2))),
        "free_rms": float(np.sqrt(np.mean(free**2))),
        "crlb_q2": float(qb[1]),
        "crlb_q4": float(qb[3]),
        "free_q2": float(qf[1]),
        "free_q4": float(qf[3]),
        "crlb_wang": M.is_divergent(crlb, free),
        "free_wang": M.is_divergent(free, free),
    }


def pooled_bound(bounds: list[dict[str, Any]]) -> dict[str, float]:
    """A group's bound figures from :func:`case_bound` results, pooled as the suite pools the RMS (every case has
    the same runs and samples): ``crlb_rms_horizontal_m`` and ``crlb_free_rms_horizontal_m`` (the free INS's
    expected RMS from its covariance), m; ``crlb_wang_rate`` and ``crlb_free_wang_rate`` (share of cases)."""
    if not bounds:
        return {}
    return {
        "crlb_rms_horizontal_m": float(np.sqrt(np.mean([np.mean(b["crlb"] ** 2) for b in bounds]))),
        "crlb_free_rms_horizontal_m": float(np.sqrt(np.mean([np.mean(b["free"] ** 2) for b in bounds]))),
        "crlb_wang_rate": float(np.mean([b["crlb_wang"] for b in bounds])),
        "crlb_free_wang_rate": float(np.mean([b["free_wang"] for b in bounds])),
    }


def suite_bounds(
    *,
    quick: bool = False,
    only: tuple[str, ...] | None = None,
    rio_survey: Path = RIO_SURVEY_DEFAULT,
    draws: int = 200,
    count_correlation: bool = True,
) -> tuple[dict[str, Any], str]:
    """The information bound of the suite's cases without flying them (:func:`case_bound` per case, ``draws`` runs
    at the bound each): per group :func:`pooled_bound`'s keys plus ``free_over_crlb`` (the free INS's expected RMS
    over the bound's: the most any estimator can gain), ``crlb_wang_mc_rate`` / ``free_wang_mc_rate`` (share of the
    runs at the bound / of the free INS that Wang's test flags) and ``cases``; and a text table per case and group."""
    wanted = tuple(GROUPS if not only else only)
    unknown = [g for g in wanted if g not in GROUPS]
    if unknown:
        raise ConfigError(f"unknown suite group(s) {unknown}; expected some of {', '.join(GROUPS)}")
    cases = [c for c in osborne_cases(quick) if c.group in wanted]
    if "rio" in wanted:
        cases += rio_cases(Path(rio_survey), quick)[0]
    bounds = [case_bound(c, count_correlation, draws) for c in cases]
    head = (
        f"{'case':28s} {'T (s)':>6s} {'CRLB':>8s} {'free':>8s} {'free/CRLB':>9s} {'Wang(bound)':>11s} {'Wang MC':>8s}"
    )
    lines = [head]
    for c, b in zip(cases, bounds, strict=True):
        mc = f"{100 * b['crlb_wang_mc']:.0f}%" if "crlb_wang_mc" in b else "-"
        lines.append(
            f"{c.name:28s} {b['t'][-1] - b['t'][0]:6.0f} {b['crlb_rms']:8.1f} {b['free_rms']:8.1f} "
            f"{b['free_rms'] / b['crlb_rms']:9.1f} {'yes' if b['crlb_wang'] else 'no':>11s} {mc:>8s}"
        )
    groups: dict[str, Any] = {}
    lines += [
        "",
        f"{'group':28s} {'cases':>6s} {'CRLB':>8s} {'free':>8s} {'free/CRLB':>9s} {'Wang(bound)':>11s} {'Wang MC':>8s} {'free MC':>8s}",
    ]
    for g in wanted:
        bs = [b for c, b in zip(cases, bounds, strict=True) if c.group == g]
        if not bs:
            continue
        m = pooled_bound(bs)
        m["free_over_crlb"] = m["crlb_free_rms_horizontal_m"] / m["crlb_rms_horizontal_m"]
        if draws > 0:
            m["crlb_wang_mc_rate"] = float(np.mean([b["crlb_wang_mc"] for b in bs]))
            m["free_wang_mc_rate"] = float(np.mean([b["free_wang_mc"] for b in bs]))
        m["cases"] = len(bs)
        groups[g] = m
        mc = f"{100 * m['crlb_wang_mc_rate']:7.1f}% {100 * m['free_wang_mc_rate']:7.1f}%" if draws > 0 else ""
        lines.append(
            f"{g:28s} {len(bs):6d} {m['crlb_rms_horizontal_m']:8.1f} {m['crlb_free_rms_horizontal_m']:8.1f} "
            f"{m['free_over_crlb']:9.1f} {100 * m['crlb_wang_rate']:10.1f}% {mc}"
        )
    return groups, "\n".join(lines)


@dataclass
class SuiteResult:
    """``groups``: per group the pooled figures per estimator, or ``{"skipped": reason}``; ``cases``: per case
    (name -> ``(Case, figures)``); ``wall_s``; ``runs``."""

    groups: dict[str, Any]
    cases: list[tuple[Case, dict[str, dict[str, Any]]]]
    wall_s: float
    runs: int


def run_suite(
    *,
    quick: bool = False,
    seeds: int = DEFAULT_SEEDS,
    jobs: int = 1,
    only: tuple[str, ...] | None = None,
    rio_survey: Path = RIO_SURVEY_DEFAULT,
    scheduler: Any = None,
    quiet: bool = True,
    estimators: tuple[str, ...] | None = None,
    cases: list[Case] | None = None,
    bound: bool = True,
) -> SuiteResult:
    """Run the suite (module docstring); ``only`` limits it to some groups, ``estimators`` to some of
    :data:`ESTIMATORS` (by name; the others are not flown, their settings unchanged); ``cases`` replaces the
    suite's own cases (e.g. those used for no choice, as the README's verification table). ``bound``: add each
    case's information bound (:func:`case_bound`, a fraction of a second per case) to every estimator's figures
    (:func:`pooled_bound`'s keys, ``crlb_rms_horizontal_m`` among them)."""
    if seeds < 1:
        raise ConfigError(f"--seeds must be >= 1, got {seeds}")
    known = [e["name"] for e in ESTIMATORS]
    bad = [e for e in (estimators or ()) if e not in known]
    if bad:
        raise ConfigError(f"unknown suite estimator(s) {bad}; expected some of {', '.join(known)}")
    ests = tuple(e for e in ESTIMATORS if not estimators or e["name"] in estimators)
    wanted = tuple(GROUPS if not only else only)
    unknown = [g for g in wanted if g not in GROUPS]
    if unknown:
        raise ConfigError(f"unknown suite group(s) {unknown}; expected some of {', '.join(GROUPS)}")
    from .runner import execute

    t0 = time.perf_counter()
    skipped: dict[str, str] = {}
    if cases is not None:
        cases = [c for c in cases if c.group in wanted]
    else:
        cases = [c for c in osborne_cases(quick) if c.group in wanted]
        if "rio" in wanted:
            rio, why = rio_cases(Path(rio_survey), quick)
            cases += rio
            if why:
                skipped["rio"] = why
    for g in GROUPS:
        if g not in wanted:
            skipped[g] = "not asked for"
    model = SuiteModel(tuple(cases), seeds, estimators=ests)
    # a worker takes a case's runs together: its truth and map are built once, not in each worker (same results)
    summaries = (
        execute(model, len(cases) * seeds, 0, jobs=jobs, scheduler=scheduler, quiet=quiet, chunk=seeds) if cases else []
    )
    per_case = [
        (c, pooled(summaries[k * seeds : (k + 1) * seeds], ests)) for k, c in enumerate(cases)
    ]  # runs are returned in order
    bounds = [case_bound(c) for c in cases] if bound else []
    for (_, figs), b in zip(per_case, bounds, strict=False):
        for m in figs.values():
            m.update(pooled_bound([b]))
    groups: dict[str, Any] = {}
    for g in GROUPS:
        runs = [s for k, c in enumerate(cases) if c.group == g for s in summaries[k * seeds : (k + 1) * seeds]]
        groups[g] = pooled(runs, ests) if runs else {"skipped": skipped.get(g, "no case")}
        if runs and bounds:  # the information bound of the group's cases, beside each estimator's RMS
            gb = pooled_bound([b for b, c in zip(bounds, cases, strict=True) if c.group == g])
            for m in groups[g].values():
                m.update(gb)
    return SuiteResult(groups, per_case, time.perf_counter() - t0, len(summaries))


def _fmt(x: Any, pct: bool = False) -> str:
    if x is None:
        return "-"
    if pct:
        return f"{100.0 * float(x):.1f}%"
    x = float(x)
    return f"{x:.3g}" if abs(x) >= 1e4 else f"{x:.1f}"


TABLE_HEADER = (
    f"{'case':28s} {'estimator':17s} {'RMS':>8s} {'medRMS':>8s} {'max':>8s} {'NEES':>7s} {'fixNEES':>8s} {'HPLexc':>7s} "
    f"{'avail':>6s} {'div':>6s} {'divNEES':>7s} {'free':>8s} {'xCRLB':>6s}"
)


def _x_crlb(m: dict[str, Any]) -> str:
    """The estimator's RMS in units of the information bound's (``-`` without the bound)."""
    b = m.get("crlb_rms_horizontal_m")
    return "-" if not b or m.get("rms_horizontal_m") is None else f"{float(m['rms_horizontal_m']) / b:.1f}"


def table_rows(name: str, figures: dict[str, dict[str, Any]]) -> list[str]:
    """Text rows of one case or group: RMS, median run RMS, max, NEES, fix NEES, HPL exceedance, availability,
    divergence (Wang's error-growth test and the filter's NEES test, :mod:`.metrics`), free RMS per estimator, and
    the RMS in units of the information bound's (``xCRLB``, :func:`case_bound`)."""
    return [
        f"{name:28s} {est:17s} {_fmt(m['rms_horizontal_m']):>8s} "
        f"{_fmt(m.get('median_run_rms_horizontal_m')):>8s} {_fmt(m['max_horizontal_m']):>8s} "
        f"{_fmt(m['nees_mean']):>7s} {_fmt(m['fix_nees_mean']):>8s} {_fmt(m['hpl_exceedance'], True):>7s} "
        f"{_fmt(m['availability'], True):>6s} {_fmt(m['divergence_rate'], True):>6s} "
        f"{_fmt(m['nees_divergence_rate'], True):>7s} {_fmt(m['free_rms_horizontal_m']):>8s} {_x_crlb(m):>6s}"
        for est, m in figures.items()
    ]


def report(result: SuiteResult) -> str:
    """The per-case and per-group tables as text."""
    lines = [TABLE_HEADER]
    for c, figs in result.cases:
        lines += table_rows(c.name, figs)
    lines += ["", TABLE_HEADER]
    for g, figs in result.groups.items():
        if "skipped" in figs:
            lines.append(f"{g:28s} skipped: {figs['skipped']}")
        else:
            lines += table_rows(g, figs)
    lines.append(f"\n{len(result.cases)} cases, {result.runs} runs, {result.wall_s:.0f} s")
    return "\n".join(lines)
