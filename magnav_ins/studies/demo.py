"""The demo: a tactical-grade INS flies a real Osborne tie line, aided by matching that line's REAL magnetometer
readings against the shipped map, next to the same INS left free.

Everything real that can be: the map is ``builtin:osborne-magnetic`` (gridded at 100 m from the 1990 survey's
east-west flight lines only), the readings are those recorded along tie line ``line`` of
``builtin:osborne-tie-lines`` (flown north-south, never used by the map, so they test it independently, with
their real noise, levelling and map errors), and the trajectory is that line's own track and heights. The survey
has no time column, so the line is flown at ``speed_mps`` (:func:`magnav_ins.ins.simulate.survey_line`) and the
recorded readings are resampled to the reading times by along-line position
(nearest survey sample by along-line position, :mod:`.model`). Simulated: the ideal IMU of that flight
(:func:`~magnav_ins.ins.simulate.ideal_imu`), the IMU errors of ``grade`` and the initial INS errors (DESIGN.md
``[init]`` defaults), drawn from ``seed``.

The aided and the free-inertial runs get the SAME corrupted IMU samples and the SAME perturbed initial state; both
run through :class:`magnav_ins.pipeline.Pipeline` with the same INS core (the free one with the ``free_inertial``
fuser and no matcher), so the only difference is the map aiding. Both hold the vertical channel at the truth's
initial height (a barometric aid, as in :mod:`.model`).

Seeds: ``child(SeedSequence(seed), 0)`` draws the IMU errors, ``child(., 1)`` the initial errors, ``child(., 2)``
a randomised matcher (as :mod:`.model` does for a study run).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from ..core.errors import ConfigError, InputError
from ..core.frames import horizontal_error_m
from ..core.types import LAYOUT_15, FieldKind, FieldReadings, NavEstimate
from ..core.units import DEG_TO_RAD
from .runner import EstimatorOutput, RunOutput, runs_dataset, study_metrics, summarise_run
from .scenario import FREE_INERTIAL, InitConfig

#: the map and the survey the demo flies (shipped with the package)
DEMO_MAP = "builtin:osborne-magnetic"
DEMO_SURVEY = "builtin:osborne-tie-lines"


@dataclass(frozen=True)
class DemoConfig:
    """Demo parameters (SI). ``line``: tie line id in :data:`DEMO_SURVEY`; ``speed_mps``: ground speed flown;
    ``duration_s``: fly only the first part of the line (None: all of it); ``grade``: IMU grade; ``imu_rate_hz``;
    ``reading_interval_s``: magnetometer reading period; ``reading_sigma_nt``: the magnetometer's noise 1-sigma
    (nT; the readings are real, their noise is below 1 nT; the map's error comes from the map's error layer);
    ``matcher``: matcher config (:func:`magnav_ins.aiding.matchers.registry.build_matcher`; its defaults, no
    option tuned: ``particle_ins``, the best estimator on the Osborne groups of the real-data suite,
    :mod:`.suite`); ``fusion``: fuser kind; ``window``, ``match_every``: readings per match window and between
    match attempts (:class:`magnav_ins.pipeline.Pipeline`; a fix attempt every 30 s, as the suite asks a recursive
    matcher); ``init``: 1-sigma initial INS errors; ``seed``.
    ``waypoint_tolerance_m``: how far the flown polyline may deviate from the surveyed track (RDP simplification
    in :func:`~magnav_ins.ins.simulate.survey_line`)."""

    line: int = 10152
    speed_mps: float = 60.0
    duration_s: float | None = None
    grade: str = "tactical"
    imu_rate_hz: float = 50.0
    reading_interval_s: float = 0.5
    reading_sigma_nt: float = 1.0
    matcher: dict[str, Any] = field(default_factory=lambda: {"kind": "particle_ins"})
    fusion: str = "ukf"
    window: int = 1
    match_every: int = 60
    init: InitConfig = field(default_factory=InitConfig)
    seed: int = 1990
    waypoint_tolerance_m: float = 25.0

    @property
    def estimator_name(self) -> str:
        return f"{self.matcher['kind']}+{self.fusion}"


@dataclass
class DemoResult:
    """What :func:`run_demo` produced: ``summary`` (the ``summary.json`` document), the study ``dataset``
    (:func:`~magnav_ins.studies.runner.runs_dataset`, one run, the aided estimator and ``free_inertial``) and
    the map (for the track figure)."""

    summary: dict[str, Any]
    dataset: Any
    fmap: Any


def _line_points(line: int) -> dict[str, np.ndarray]:
    from ..maps.builtin import load_survey_lines

    s = load_survey_lines(DEMO_SURVEY)
    m = s.line == int(line)
    if m.sum() < 2:
        ids = ", ".join(str(i) for i in s.line_ids())
        raise InputError(f"{DEMO_SURVEY}: no tie line {line}; the tie lines are {ids}")
    return {"lat": s.lat[m], "lon": s.lon[m], "h": s.h[m], "value": s.value[m]}


def _truth(cfg: DemoConfig, pts: dict[str, np.ndarray]):
    from ..ins import simulate

    truth = simulate.survey_line(
        pts["lat"], pts["lon"], pts["h"], cfg.speed_mps, cfg.imu_rate_hz, tolerance_m=cfg.waypoint_tolerance_m
    )
    if cfg.duration_s is not None:
        if not cfg.duration_s > 0:
            raise ConfigError(f"demo: duration_s must be > 0 s, got {cfg.duration_s!r}")
        n = int(np.searchsorted(truth.t, truth.t[0] + cfg.duration_s, side="right"))
        truth = truth.slice(0, max(n, 2))
    return truth


def run_demo(cfg: DemoConfig | None = None) -> DemoResult:
    """Run the demo (module docstring) and return its summary, dataset and map. Nothing is written."""
    from ..aiding.fusion import ImuNoise, make_fuser
    from ..aiding.matchers.metrics import no_fix_reasons
    from ..aiding.matchers.registry import build_matcher
    from ..ins import imu_models, simulate
    from ..ins.error_model import initial_covariance
    from ..maps.builtin import load_builtin_map
    from ..pipeline import Pipeline
    from .model import _resample_along_line as resample_along_line
    from .model import child, perturbed_init

    cfg = cfg or DemoConfig()
    t_start = time.perf_counter()
    fmap = load_builtin_map(DEMO_MAP)
    pts = _line_points(cfg.line)
    truth = _truth(cfg, pts)
    grade = imu_models.get_grade(cfg.grade)
    ss = np.random.SeedSequence(cfg.seed)
    imu, _ = imu_models.corrupt(simulate.ideal_imu(truth), grade, np.random.default_rng(child(ss, 0)))
    init = perturbed_init(SimpleNamespace(init=cfg.init), truth, np.random.default_rng(child(ss, 1)))
    # the line's real readings at the reading times (along-line resampling), no noise added
    t_r = np.arange(truth.t[0] + cfg.reading_interval_s, truth.t[-1] + 1e-9, cfg.reading_interval_s)
    lat_r = np.interp(t_r, truth.t, truth.lat)
    lon_r = np.interp(t_r, truth.t, truth.lon)
    readings = FieldReadings(
        t_r, resample_along_line(pts, lat_r, lon_r), cfg.reading_sigma_nt, FieldKind.TOTAL_FIELD_ANOMALY_NT
    )
    ic = cfg.init
    P0 = initial_covariance(
        grade, ic.position_sigma_m, ic.velocity_sigma_mps, np.asarray(ic.attitude_sigma_deg) * DEG_TO_RAD
    )
    noise = ImuNoise.from_grade(grade)
    hold = float(truth.h[0])
    t_setup = time.perf_counter() - t_start

    def fly(kind: str, matcher: Any) -> Any:
        fuser = make_fuser(kind, NavEstimate(init, P0, LAYOUT_15), noise, altitude_hold=hold)
        pipe = Pipeline(
            fuser,
            matcher,
            fmap if matcher is not None else None,
            window=cfg.window,
            match_every=cfg.match_every,
            rng=np.random.default_rng(child(ss, 2)),
        )
        return pipe.run(imu, readings if matcher is not None else None, output_dt=1.0)

    t0 = time.perf_counter()
    aided = fly(cfg.fusion, build_matcher(cfg.matcher))
    t_aided = time.perf_counter() - t0
    free = fly("free_inertial", None)

    name = cfg.estimator_name
    outs = []
    for nm, res, mk, fk in ((name, aided, cfg.matcher["kind"], cfg.fusion), (FREE_INERTIAL, free, None, FREE_INERTIAL)):
        nav = res.trajectory
        fixes = list(res.fixes)
        outs.append(
            EstimatorOutput(
                nm,
                mk,
                fk,
                nav.lat,
                nav.lon,
                np.asarray(res.P)[:, 0:2, 0:2],
                np.array([f.t for f in fixes], float),
                np.array([f.lat for f in fixes], float),
                np.array([f.lon for f in fixes], float),
                np.array([f.cov_ne for f in fixes], float).reshape(-1, 2, 2),
                np.array([f.available for f in fixes], bool),
                hpl_m=np.asarray(res.hpl_m, float) if len(res.hpl_m) == len(nav.t) else None,
            )
        )
    t_out = aided.trajectory.t
    run = RunOutput(t_out, np.interp(t_out, truth.t, truth.lat), np.interp(t_out, truth.t, truth.lon), tuple(outs))
    summ = summarise_run(0, run)
    wall = time.perf_counter() - t_start
    doc = study_metrics([summ], cfg.seed, wall, f"demo: Osborne tie line {cfg.line}")
    est = doc["estimators"][name]
    fi = doc["free_inertial"]
    accepted = sum(1 for inn in aided.innovations if inn.accepted)
    # honesty check: until the first accepted fix the aided INS must be the free INS, sample for sample
    t_first = min((inn.t for inn in aided.innovations if inn.accepted), default=np.inf)
    before = t_out < t_first - 1e-9
    same = horizontal_error_m(
        aided.trajectory.lat[before],
        aided.trajectory.lon[before],
        free.trajectory.lat[before],
        free.trajectory.lon[before],
    )
    e_aid = summ.estimators[name].metrics.e
    e_free = summ.estimators[FREE_INERTIAL].metrics.e
    cfg_doc = asdict(cfg)
    summary: dict[str, Any] = {
        "rms_horizontal_m": est["rms_horizontal_m"],
        "free_inertial_rms_horizontal_m": fi["rms_horizontal_m"],
        "max_horizontal_m": est["max_horizontal_m"],
        "final_horizontal_m": est["final_horizontal_m"],
        "free_inertial_max_horizontal_m": fi["max_horizontal_m"],
        "free_inertial_final_horizontal_m": fi["final_horizontal_m"],
        "improvement_factor": float(fi["rms_horizontal_m"] / est["rms_horizontal_m"]),
        "fixes_issued": est["fixes_issued"],
        "fixes_accepted": int(accepted),
        "fix_attempts": est["fix_attempts"],
        "fix_error_median_m": _median(summ.estimators[name].metrics.fix_errors_m),
        "fix_error_rms_m": _rms(summ.estimators[name].metrics.fix_errors_m),
        "nees_mean": est["nees_mean"],
        "fix_nees_mean": est["fix_nees_mean"],
        "hpl_median_m": est["hpl_median_m"],
        "hpl_exceedance": est["hpl_exceedance"],
        "integrity_risk": float(aided.integrity_risk),
        "free_inertial_nees_mean": fi["nees_mean"],
        "first_fix_accepted_s": float(t_first - truth.t[0]) if np.isfinite(t_first) else None,
        "aided_minus_free_before_first_fix_m": float(same.max()) if same.size else 0.0,
        "no_fix_reasons": no_fix_reasons(aided.fixes),
        "rejected_fix_reasons": _rejections(aided.innovations),
        "matcher": cfg.matcher,
        "fusion": cfg.fusion,
        "grade": cfg.grade,
        "line": int(cfg.line),
        "map": DEMO_MAP,
        "survey": DEMO_SURVEY,
        "speed_mps": cfg.speed_mps,
        "duration_s": float(truth.t[-1] - truth.t[0]),
        "distance_km": float(cfg.speed_mps * (truth.t[-1] - truth.t[0]) / 1000.0),
        "readings": len(readings),
        "reading_interval_s": cfg.reading_interval_s,
        "aided_mean_over_last_quarter_m": float(np.mean(e_aid[3 * len(e_aid) // 4 :])),
        "free_inertial_mean_over_last_quarter_m": float(np.mean(e_free[3 * len(e_free) // 4 :])),
        "seed": int(cfg.seed),
        "config": {k: v for k, v in cfg_doc.items() if k not in ("matcher",)},
        "setup_s": float(t_setup),
        "aided_run_s": float(t_aided),
        "wall_s": float(wall),
    }
    return DemoResult(summary, runs_dataset([summ], doc["name"]), fmap)


def _rejections(innovations: list[Any]) -> dict[str, int]:
    """Count of the fuser's reasons for rejecting issued fixes (the text before the first number)."""
    out: dict[str, int] = {}
    for inn in innovations:
        if not inn.accepted and not inn.reason.startswith("no fix"):
            key = inn.reason.split(" ")[0] if inn.reason else "unspecified"
            out[key] = out.get(key, 0) + 1
    return out


def _median(x: np.ndarray) -> float | None:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(np.median(x)) if x.size else None


def _rms(x: np.ndarray) -> float | None:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if x.size else None


def summary_table(summary: dict[str, Any]) -> str:
    """The demo's printed table: aided vs free inertial (horizontal RMS, max, final; fixes)."""
    name = f"{summary['matcher']['kind']}+{summary['fusion']}"
    rows = [
        ("", name, "free inertial"),
        ("horizontal RMS (m)", _m(summary["rms_horizontal_m"]), _m(summary["free_inertial_rms_horizontal_m"])),
        ("horizontal max (m)", _m(summary["max_horizontal_m"]), _m(summary["free_inertial_max_horizontal_m"])),
        ("final error (m)", _m(summary["final_horizontal_m"]), _m(summary["free_inertial_final_horizontal_m"])),
        ("NEES (2-D, 2 when honest)", _m(summary["nees_mean"], 2), _m(summary.get("free_inertial_nees_mean"), 2)),
        (
            f"HPL median (m, risk {summary.get('integrity_risk', 1e-3):g})",
            _m(summary.get("hpl_median_m")),
            "-",
        ),
        ("HPL exceeded", _pct(summary.get("hpl_exceedance")), "-"),
        ("fixes issued / attempts", f"{summary['fixes_issued']} / {summary['fix_attempts']}", "-"),
        ("fixes accepted by the filter", str(summary["fixes_accepted"]), "-"),
    ]
    w0 = max(len(r[0]) for r in rows)
    w1 = max(len(r[1]) for r in rows)
    w2 = max(len(r[2]) for r in rows)
    lines = [f"{a:<{w0}}  {b:>{w1}}  {c:>{w2}}" for a, b, c in rows]
    lines.insert(1, "-" * len(lines[0]))
    head = (
        f"Osborne tie line {summary['line']} ({summary['distance_km']:.1f} km, {summary['duration_s']:.0f} s at "
        f"{summary['speed_mps']:g} m/s), {summary['grade']} IMU, real readings vs {summary['map']}, seed "
        f"{summary['seed']}"
    )
    tail = f"improvement factor (free RMS / aided RMS): {summary['improvement_factor']:.1f}x"
    return "\n".join([head, *lines, tail])


def _m(x: float | None, digits: int = 1) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100.0 * x:.1f} %"


def write_demo(result: DemoResult, out_dir: str | Path, t_start: float | None = None) -> list[Path]:
    """Write ``summary.json``, ``track.png`` and ``error_vs_time.png`` into ``out_dir`` (each atomically;
    ``summary.json`` last). With ``t_start`` (a :func:`time.perf_counter` reading), ``wall_s`` becomes the time
    from then until the figures are written. Returns the paths."""
    import json

    from ..core.atomic import write_text_atomic
    from . import plots

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [
        plots.plot_track(result.dataset, out / "track.png", fmap=result.fmap),
        plots.plot_error_vs_time(result.dataset, out / "error_vs_time.png"),
    ]
    if t_start is not None:
        result.summary["wall_s"] = float(time.perf_counter() - t_start)
    p = out / "summary.json"
    write_text_atomic(p, json.dumps(result.summary, indent=2, allow_nan=False) + "\n")
    return [*paths, p]
