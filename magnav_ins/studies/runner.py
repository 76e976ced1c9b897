"""Monte Carlo runner: N runs of a study model, serial, in local processes, or on a Dask cluster, with identical
results whatever the parallelism.

Seeds. Run ``i`` gets ``numpy.random.SeedSequence(seed).spawn(runs)[i]``; everything random in that run (IMU
errors, initial INS errors, sensor noise, and any randomised estimator) is drawn from it by the model, so the
results depend on ``seed`` and ``runs`` only, never on ``jobs`` or the scheduler.

A *study model* (:class:`StudyModel`) turns one seed sequence into a :class:`RunOutput`: the truth and every
estimator's track on one common time base, the free-inertial baseline among them under the name
``free_inertial``. :class:`magnav_ins.studies.model.PipelineModel` builds it from a scenario; tests use small
stand-ins. Workers summarise their run (:func:`summarise_run`) so only compact float32 arrays travel back.

Outputs (every file through :mod:`magnav_ins.core.atomic`; written only after all runs succeeded): ``metrics.json``
(keys in ``shared/DESIGN.md`` and :mod:`.metrics`), ``runs.nc`` (per-run north/east errors, horizontal 1-sigma and
fixes, float32, decimated to at most ``max_samples`` samples, plus the truth track in float64), ``report.md`` and
PNG figures.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from ..core.atomic import atomic_path, check_output_dir, write_text_atomic
from ..core.errors import ConfigError, OutputError
from ..core.signals import deferred
from ..core.units import RAD_TO_DEG
from . import metrics as M
from .scenario import FREE_INERTIAL

#: at most this many samples per run are kept in ``runs.nc`` and used for the error statistics
DEFAULT_MAX_SAMPLES = 4000


# ------------------------------------------------------------------------------------------------ run outputs
@dataclass(frozen=True)
class EstimatorOutput:
    """One estimator's result in one run, on the run's time base ``RunOutput.t``.

    ``lat``, ``lon`` (N,) rad; ``cov_ne`` (N,2,2) m^2 horizontal covariance or None (free inertial without a
    filter). Fixes: ``fix_t`` (K,) s, ``fix_lat``, ``fix_lon`` (K,) rad (NaN for "no fix"), ``fix_cov_ne``
    (K,2,2) m^2, ``fix_available`` (K,) bool, ``fix_reason`` (K,) the reason of each "no fix" ("" for a fix); one
    entry per fix attempt. ``fix_accepted`` (K,) bool: whether the fuser applied each fix (empty when unknown).
    """

    name: str
    matcher: str | None
    fusion: str
    lat: NDArray[np.float64]
    lon: NDArray[np.float64]
    cov_ne: NDArray[np.float64] | None = None
    fix_t: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    fix_lat: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    fix_lon: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    fix_cov_ne: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2, 2)))
    fix_available: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    fix_reason: tuple[str, ...] = ()
    fix_accepted: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    hpl_m: NDArray[np.float64] | None = None  # (N,) horizontal protection level, m (None: none given)


@dataclass(frozen=True)
class RunOutput:
    """One Monte Carlo run: time base ``t`` (N,) s, truth ``lat_true``, ``lon_true`` (N,) rad, and the estimators
    (the free-inertial baseline named ``free_inertial`` must be among them)."""

    t: NDArray[np.float64]
    lat_true: NDArray[np.float64]
    lon_true: NDArray[np.float64]
    estimators: tuple[EstimatorOutput, ...]


class StudyModel(Protocol):
    """What the runner needs from a study: a name, the estimator names in order, and one run per seed."""

    name: str

    def estimator_names(self) -> tuple[str, ...]: ...

    def run(self, seed: np.random.SeedSequence) -> RunOutput: ...


# ------------------------------------------------------------------------------------------------ summaries
@dataclass
class EstimatorSummary:
    """Compact per-run record of one estimator: metrics inputs and float32 arrays for ``runs.nc``."""

    matcher: str | None
    fusion: str
    metrics: M.RunMetrics
    err_n: NDArray[np.float32]
    err_e: NDArray[np.float32]
    sigma_n: NDArray[np.float32]
    sigma_e: NDArray[np.float32]
    corr_ne: NDArray[np.float32]
    fix_t: NDArray[np.float64]
    fix_err_n: NDArray[np.float32]
    fix_err_e: NDArray[np.float32]
    fix_sigma_n: NDArray[np.float32]
    fix_sigma_e: NDArray[np.float32]
    fix_corr_ne: NDArray[np.float32]
    fix_available: NDArray[np.bool_]
    no_fix_reasons: dict[str, int] = field(default_factory=dict)
    hpl: NDArray[np.float32] | None = None


def reason_category(reason: str) -> str:
    """The class of a "no fix" reason: the text before its first colon (``"flat map"``, ``"diverged"``,
    ``"off the map"``, ...), as :func:`magnav_ins.aiding.matchers.metrics.no_fix_reasons` counts them."""
    return reason.split(":", 1)[0].strip() or "unspecified"


@dataclass
class RunSummary:
    index: int
    t: NDArray[np.float64]
    lat_true: NDArray[np.float64]
    lon_true: NDArray[np.float64]
    estimators: dict[str, EstimatorSummary]
    wall_s: float


def _cov_parts(cov: NDArray[np.float64] | None, n: int) -> tuple[NDArray, NDArray, NDArray]:
    if cov is None or len(cov) == 0:
        nan = np.full(n, np.nan, np.float32)
        return nan, nan, nan
    cov = np.asarray(cov, float)
    sn = np.sqrt(np.maximum(cov[:, 0, 0], 0.0))
    se = np.sqrt(np.maximum(cov[:, 1, 1], 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = cov[:, 0, 1] / (sn * se)
    return sn.astype(np.float32), se.astype(np.float32), rho.astype(np.float32)


def summarise_run(
    index: int, out: RunOutput, max_samples: int = DEFAULT_MAX_SAMPLES, wall_s: float = 0.0
) -> RunSummary:
    """Errors, NEES, fix errors and divergence of every estimator in one run (decimated to ``max_samples``)."""
    n = len(out.t)
    step = max(1, int(np.ceil(n / max_samples)))
    sel = np.arange(0, n, step)
    if sel[-1] != n - 1:
        sel = np.append(sel, n - 1)  # keep the final sample for final_horizontal_m
    t = np.asarray(out.t, float)[sel]
    lat_t = np.asarray(out.lat_true, float)[sel]
    lon_t = np.asarray(out.lon_true, float)[sel]
    names = [e.name for e in out.estimators]
    if FREE_INERTIAL not in names:
        raise ValueError(f"RunOutput must contain the {FREE_INERTIAL!r} baseline, got {names}")
    errs: dict[str, tuple[NDArray, NDArray, NDArray]] = {}
    for est in out.estimators:
        dn, de = M.ne_errors(np.asarray(est.lat)[sel], np.asarray(est.lon)[sel], lat_t, lon_t)
        errs[est.name] = (dn, de, np.hypot(dn, de))
    e_free = errs[FREE_INERTIAL][2]
    res: dict[str, EstimatorSummary] = {}
    for est in out.estimators:
        dn, de, e = errs[est.name]
        cov = None if est.cov_ne is None else np.asarray(est.cov_ne, float)[sel]
        nees = M.nees_ne(dn, de, cov) if cov is not None else np.full(len(sel), np.nan)
        fix_avail = np.asarray(est.fix_available, bool)
        fix_t = np.asarray(est.fix_t, float)
        if len(fix_t):
            lat_f = np.interp(fix_t, out.t, out.lat_true)
            lon_f = np.interp(fix_t, out.t, np.unwrap(out.lon_true))
            fdn, fde = M.ne_errors(est.fix_lat, est.fix_lon, lat_f, lon_f)
            fdn = np.where(fix_avail, fdn, np.nan)
            fde = np.where(fix_avail, fde, np.nan)
        else:
            fdn = fde = np.zeros(0)
        fsn, fse, frho = _cov_parts(np.asarray(est.fix_cov_ne, float), len(fix_t))
        hpl = None if est.hpl_m is None else np.asarray(est.hpl_m, float)[sel]
        fix_nees = M.nees_ne(fdn, fde, np.asarray(est.fix_cov_ne, float))[fix_avail] if len(fix_t) else np.zeros(0)
        rm = M.RunMetrics(
            e=e,
            nees=nees,
            fix_errors_m=np.hypot(fdn, fde)[fix_avail] if len(fix_t) else np.zeros(0),
            fix_attempts=len(fix_t),
            divergent=M.is_divergent(e, e_free),
            first_fix_index=M.first_fix_index(t, fix_t, np.asarray(est.fix_accepted, bool)),
            hpl_m=hpl if hpl is not None else np.full(len(sel), np.nan),
            fix_nees=fix_nees,
        )
        sn, se, rho = _cov_parts(cov, len(sel))
        reasons: dict[str, int] = {}
        for a, why in zip(fix_avail, est.fix_reason, strict=False):
            if not a:
                c = reason_category(why)
                reasons[c] = reasons.get(c, 0) + 1
        res[est.name] = EstimatorSummary(
            est.matcher, est.fusion, rm, dn.astype(np.float32), de.astype(np.float32), sn, se, rho,
            fix_t, fdn.astype(np.float32), fde.astype(np.float32), fsn, fse, frho, fix_avail, reasons,
            None if hpl is None else hpl.astype(np.float32),
        )  # fmt: skip
    return RunSummary(index, t, lat_t, lon_t, res, wall_s)


def _run_task(model: StudyModel, index: int, seed: np.random.SeedSequence, max_samples: int) -> RunSummary:
    """One run in a worker (module-level so it pickles)."""
    t0 = time.perf_counter()
    out = model.run(seed)
    return summarise_run(index, out, max_samples, time.perf_counter() - t0)


def _run_chunk(
    model: StudyModel, first: int, seeds: Sequence[np.random.SeedSequence], max_samples: int
) -> list[RunSummary]:
    """Runs ``first, first + 1, ...`` one after the other in one worker (module-level so it pickles)."""
    return [_run_task(model, first + k, ss, max_samples) for k, ss in enumerate(seeds)]


# ------------------------------------------------------------------------------------------------ execution
def run_seeds(seed: int, runs: int) -> list[np.random.SeedSequence]:
    """The per-run seed sequences: ``SeedSequence(seed).spawn(runs)``."""
    return np.random.SeedSequence(seed).spawn(runs)


def execute(
    model: StudyModel,
    runs: int,
    seed: int,
    jobs: int = 1,
    scheduler: str | Any | None = None,
    quiet: bool = True,
    max_samples: int = DEFAULT_MAX_SAMPLES,
    chunk: int = 1,
) -> list[RunSummary]:
    """Run ``runs`` Monte Carlo runs of ``model`` and return their summaries in run order.

    ``jobs`` > 1 uses a :class:`~concurrent.futures.ProcessPoolExecutor`, handing each worker ``chunk``
    consecutive runs at a time (a model whose consecutive runs share a set-up memoised per process, as the suite's
    runs of one case, then builds it once, not once per worker; the results do not depend on ``chunk``);
    ``scheduler`` (an address ``tcp://HOST:PORT`` or a ``dask.distributed.Client``) runs them on a Dask cluster
    instead. A progress bar (tqdm) is shown unless ``quiet``.
    """
    if runs < 1:
        raise ConfigError(f"runs must be >= 1, got {runs}")
    if jobs < 1:
        raise ConfigError(f"jobs must be >= 1, got {jobs}")
    if chunk < 1:
        raise ConfigError(f"chunk must be >= 1, got {chunk}")
    seeds = run_seeds(seed, runs)
    from tqdm.auto import tqdm

    bar = tqdm(total=runs, desc=model.name, unit="run", disable=quiet)
    results: list[RunSummary | None] = [None] * runs
    try:
        if scheduler is not None:
            _execute_dask(model, seeds, scheduler, max_samples, results, bar.update)
        elif jobs == 1:
            for i, ss in enumerate(seeds):
                results[i] = _run_task(model, i, ss, max_samples)
                bar.update(1)
        else:
            _execute_pool(model, seeds, jobs, max_samples, results, bar.update, chunk)
    finally:
        bar.close()
    return [r for r in results if r is not None]


def _execute_pool(
    model: StudyModel,
    seeds: Sequence[np.random.SeedSequence],
    jobs: int,
    max_samples: int,
    results: list[RunSummary | None],
    progress: Callable[[int], Any],
    chunk: int = 1,
) -> None:
    """The runs in ``jobs`` local worker processes, ``chunk`` consecutive runs per task. Workers ignore SIGINT and die with their parent
    (:func:`magnav_ins.core.signals.worker_init`); on any exception here (Ctrl-C, SIGTERM, a failed run) the queued
    runs are cancelled and the workers are terminated at once, not waited for: nothing is left running."""
    import os

    from ..core.signals import worker_init

    pool = ProcessPoolExecutor(max_workers=jobs, initializer=worker_init, initargs=(os.getpid(),))
    try:
        futs = {
            pool.submit(_run_chunk, model, i, seeds[i : i + chunk], max_samples): i for i in range(0, len(seeds), chunk)
        }
        for fut in as_completed(futs):
            done = fut.result()
            results[futs[fut] : futs[fut] + len(done)] = done
            progress(len(done))
    except BrokenProcessPool as exc:
        _stop_pool(pool)
        raise RuntimeError(
            "a worker process died during a Monte Carlo run (killed by the OS, e.g. out of memory); "
            "nothing was written - retry with fewer --jobs"
        ) from exc
    except BaseException:
        _stop_pool(pool)
        raise
    pool.shutdown(wait=True)


#: seconds given to closing the connection to a Dask scheduler
_DASK_CLOSE_S = 3.0
#: seconds a terminated worker gets to exit before it is killed
_WORKER_STOP_S = 2.0


def _stop_pool(pool: ProcessPoolExecutor) -> None:
    """Cancel what is queued and end every worker now: SIGTERM, then SIGKILL after ``_WORKER_STOP_S``.
    (:class:`ProcessPoolExecutor` has no public way to stop running tasks; its ``_processes`` map is read once.)"""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        if p.is_alive():
            p.terminate()
    deadline = time.monotonic() + _WORKER_STOP_S
    for p in procs:
        p.join(max(0.0, deadline - time.monotonic()))
        if p.is_alive():
            p.kill()
            p.join(1.0)
    # let the pool's manager thread see its dead workers and close its wake-up pipe now: left running, it raced
    # Python's exit hook on CPython 3.11 ("Exception ignored ... OSError: Bad file descriptor" after a SIGTERM;
    # python/cpython gh-125451)
    manager = getattr(pool, "_executor_manager_thread", None)
    if manager is not None:
        manager.join(_WORKER_STOP_S)


def _execute_dask(
    model: StudyModel,
    seeds: Sequence[np.random.SeedSequence],
    scheduler: str | Any,
    max_samples: int,
    results: list[RunSummary | None],
    progress: Callable[[int], Any],
) -> None:
    from dask.distributed import Client
    from dask.distributed import as_completed as dask_completed

    own = isinstance(scheduler, str)
    try:
        client = Client(scheduler) if own else scheduler
    except OSError as exc:
        raise ConfigError(f"--scheduler {scheduler}: cannot connect to the Dask scheduler ({exc})") from None
    futs: list[Any] = []
    try:
        # hash=False: a key of this study's own; the default content hash gives two studies of one model on one
        # cluster the same key, the likely cause (not proven) of the second study's runs being cancelled with "lost
        # dependencies", seen once in the test suite under load
        [model_f] = client.scatter([model], broadcast=True, hash=False)
        futs = [client.submit(_run_task, model_f, i, ss, max_samples, pure=False) for i, ss in enumerate(seeds)]
        index = {f.key: i for i, f in enumerate(futs)}
        for fut in dask_completed(futs):
            results[index[fut.key]] = fut.result()
            progress(1)
    except BaseException:
        # Ctrl-C, SIGTERM or a failed run: withdraw every run from the cluster (queued ones never start; a running
        # one finishes on its worker and is discarded), so the cluster is free for the next study
        if futs:
            with contextlib.suppress(Exception):
                client.cancel(futs, force=True)
        raise
    finally:
        if own:
            with contextlib.suppress(Exception):
                client.close(timeout=_DASK_CLOSE_S)


# ------------------------------------------------------------------------------------------------ aggregation
def fix_warnings(doc: dict[str, Any]) -> list[str]:
    """One line per estimator with a matcher that never got a fix: no attempt at all, or attempts that all ended
    in "no fix" (with their counted reasons, as the replay summary gives them)."""
    out: list[str] = []
    for name, m in doc["estimators"].items():
        if m.get("matcher") is None:
            continue
        attempts, issued = m.get("fix_attempts", 0), m.get("fixes_issued", 0)
        if attempts == 0:
            out.append(
                f"estimator {name!r}: no fix attempt in {doc['runs']} run(s) (no reading on the map, or fewer "
                "readings than the matcher's window): it ran unaided"
            )
        elif issued == 0:
            counts = sorted((m.get("no_fix_reasons") or {}).items(), key=lambda rn: -rn[1])
            why = "; ".join(f"{r} x{n}" for r, n in counts) or "no reason given"
            out.append(f"estimator {name!r}: 0 of {attempts} fix attempts gave a fix ({why}): it ran unaided")
    return out


def study_metrics(
    summaries: list[RunSummary], seed: int, wall_s: float, name: str = "", warnings: Sequence[str] = ()
) -> dict[str, Any]:
    """The ``metrics.json`` document (see :mod:`.metrics` for the definitions). ``warnings``: lines found before
    the runs (e.g. a trajectory that never crosses the map); :func:`fix_warnings` adds its own."""
    names = list(summaries[0].estimators)
    doc: dict[str, Any] = {
        "name": name,
        "runs": len(summaries),
        "seed": int(seed),
        "wall_s": float(wall_s),
        "estimators": {},
        "free_inertial": None,
    }
    for nm in names:
        es = [s.estimators[nm] for s in summaries]
        entry = M.aggregate([e.metrics for e in es], es[0].matcher, es[0].fusion)
        counts: dict[str, int] = {}
        for e in es:  # how often each "no fix" reason occurred, over all runs (issue 16)
            for c, k in e.no_fix_reasons.items():
                counts[c] = counts.get(c, 0) + k
        entry["no_fix_reasons"] = dict(sorted(counts.items()))
        if nm == FREE_INERTIAL:
            doc["free_inertial"] = entry
        else:
            doc["estimators"][nm] = entry
    doc["warnings"] = [*warnings, *fix_warnings(doc)]
    return doc


def runs_dataset(summaries: list[RunSummary], scenario_name: str = ""):
    """Per-run tracks as an :class:`xarray.Dataset` (float32 errors on the decimated time base; truth float64)."""
    import xarray as xr

    names = list(summaries[0].estimators)
    s0 = summaries[0]
    R, E = len(summaries), len(names)
    K = max((len(s.estimators[n].fix_t) for s in summaries for n in names), default=0)

    def stack(attr: str, dtype=np.float32) -> NDArray:
        return np.stack([np.stack([getattr(s.estimators[n], attr) for n in names]) for s in summaries]).astype(dtype)

    def stack_fix(attr: str, fill: Any, dtype: Any) -> NDArray:
        arr = np.full((R, E, K), fill, dtype=dtype)
        for i, s in enumerate(summaries):
            for j, n in enumerate(names):
                v = getattr(s.estimators[n], attr)
                arr[i, j, : len(v)] = v
        return arr

    def stack_hpl() -> NDArray:
        nan = np.full(len(s0.t), np.nan, np.float32)
        return np.stack(
            [np.stack([nan if (h := s.estimators[n].hpl) is None else h for n in names]) for s in summaries]
        )

    dims = ("run", "estimator", "time")
    fdims = ("run", "estimator", "fix")
    ds = xr.Dataset(
        {
            "err_north_m": (dims, stack("err_n")),
            "err_east_m": (dims, stack("err_e")),
            "sigma_north_m": (dims, stack("sigma_n")),
            "sigma_east_m": (dims, stack("sigma_e")),
            "corr_ne": (dims, stack("corr_ne")),
            "truth_lat_deg": (("time",), s0.lat_true * RAD_TO_DEG),
            "truth_lon_deg": (("time",), s0.lon_true * RAD_TO_DEG),
            "fix_t_s": (fdims, stack_fix("fix_t", np.nan, np.float64)),
            "fix_err_north_m": (fdims, stack_fix("fix_err_n", np.nan, np.float32)),
            "fix_err_east_m": (fdims, stack_fix("fix_err_e", np.nan, np.float32)),
            "fix_sigma_north_m": (fdims, stack_fix("fix_sigma_n", np.nan, np.float32)),
            "fix_sigma_east_m": (fdims, stack_fix("fix_sigma_e", np.nan, np.float32)),
            "fix_corr_ne": (fdims, stack_fix("fix_corr_ne", np.nan, np.float32)),
            "fix_available": (fdims, stack_fix("fix_available", 0, np.int8)),
            "hpl_m": (dims, stack_hpl()),
            "divergent": (
                ("run", "estimator"),
                np.array([[s.estimators[n].metrics.divergent for n in names] for s in summaries], np.int8),
            ),
        },
        coords={
            "run": np.array([s.index for s in summaries]),
            "estimator": np.array(names, dtype=object),
            "time": ("time", s0.t, {"units": "s"}),
        },
        attrs={"title": f"magnav-ins run: {scenario_name}", "conventions": "errors are estimate minus truth, NED"},
    )
    for v in (
        "err_north_m",
        "err_east_m",
        "sigma_north_m",
        "sigma_east_m",
        "fix_err_north_m",
        "fix_err_east_m",
        "hpl_m",
    ):
        ds[v].attrs["units"] = "m"
    ds["hpl_m"].attrs["long_name"] = "horizontal protection level at the fuser's integrity risk (default 1e-3)"
    return ds


def write_outputs(
    out_dir: str | Path,
    summaries: list[RunSummary],
    doc: dict[str, Any],
    plots: bool = True,
    fmap: Any = None,
    command: str | None = None,
) -> list[Path]:
    """Write ``metrics.json``, ``runs.nc``, ``report.md`` and figures into ``out_dir``. Everything is first
    written into a hidden staging folder inside ``out_dir`` and moved into place only when all of it succeeded
    (``metrics.json`` last), so an error leaves no partial set of outputs. Returns the paths written."""
    import os
    import shutil
    import tempfile

    from . import plots as P
    from . import reports

    out = check_output_dir(out_dir, option=None)
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=".staging-", dir=out))
    except OSError as exc:
        raise OutputError(f"{out}: cannot create the output folder ({exc.strerror or exc})") from None
    ok = False
    try:
        ds = runs_dataset(summaries, doc.get("name", ""))
        with atomic_path(stage / "runs.nc") as tmp:
            ds.to_netcdf(tmp, engine="netcdf4")
        figures = P.study_figures(ds, stage, fmap=fmap) if plots else []
        write_text_atomic(stage / "report.md", reports.markdown_report(doc, [f.name for f in figures], command))
        write_text_atomic(stage / "metrics.json", json.dumps(doc, indent=2, allow_nan=False) + "\n")
        names = ["runs.nc", *(f.name for f in figures), "report.md", "metrics.json"]  # metrics.json last
        written = []
        with deferred():  # a signal lands before or after the whole set is moved into place, not half-way
            for name in names:
                os.chmod(stage / name, 0o644)
                os.replace(stage / name, out / name)
                written.append(out / name)
        ok = True
        return written
    finally:
        shutil.rmtree(stage, ignore_errors=True)
        if created and not ok:
            with contextlib.suppress(OSError):
                out.rmdir()  # only if empty: the folder this call made for outputs that never came


def run_study(
    model: StudyModel,
    runs: int,
    seed: int,
    out_dir: str | Path | None = None,
    jobs: int = 1,
    scheduler: str | Any | None = None,
    quiet: bool = True,
    plots: bool = True,
    fmap: Any = None,
    max_samples: int = DEFAULT_MAX_SAMPLES,
    command: str | None = None,
    warnings: Sequence[str] = (),
) -> dict[str, Any]:
    """Execute the study and (if ``out_dir``) write its outputs. Returns the ``metrics.json`` document (with
    ``warnings``: the given lines and :func:`fix_warnings`)."""
    t0 = time.perf_counter()
    summaries = execute(model, runs, seed, jobs, scheduler, quiet, max_samples)
    doc = study_metrics(summaries, seed, time.perf_counter() - t0, model.name, warnings)
    bound = getattr(model, "crlb_metrics", None)
    if callable(bound):  # the flight's posterior CRLB, the limit column of the comparisons (studies.crlb)
        doc.update(bound())
    if out_dir is not None:
        write_outputs(out_dir, summaries, doc, plots=plots, fmap=fmap, command=command)
    return doc
