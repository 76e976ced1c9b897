"""Study metrics: horizontal error series, NEES, fix statistics, the divergence test, aggregation over runs.

Definitions (they are what ``metrics.json`` reports; see ``shared/DESIGN.md``):

* Horizontal error e_k (m): distance between estimate and truth at sample k
  (:func:`magnav_ins.core.frames.horizontal_error_m`).
* ``rms_horizontal_m`` = sqrt(mean over runs and samples of e^2); ``mean_horizontal_m`` = mean of e over runs and
  samples; ``max_horizontal_m`` = max over runs and samples; ``final_horizontal_m`` = RMS over runs of e at the last
  sample. All runs count, divergent ones included.
* NEES: horizontal (2-D) normalised estimation error squared d_k^T P_ne,k^-1 d_k with d the north/east error and
  P_ne the filter's horizontal covariance; ``nees_mean`` is its mean over runs and samples (2 for a consistent
  filter; Bar-Shalom's NEES restricted to the horizontal position).
* ``availability`` = fixes issued / fix attempts (Shockley sec. 4.3.2), pooled over runs.
* ``fix_nees_mean``: mean over the issued fixes of their 2-D NEES against the truth, ``d^T R^-1 d`` with ``d`` the
  fix's north/east error and ``R`` its own covariance (2 when the matcher's covariances are honest).
* Protection level (the fuser's horizontal protection level ``hpl_m`` at its integrity risk, default 1e-3 per
  epoch; :mod:`magnav_ins.aiding.fusion.integrity`): ``hpl_median_m`` its median over runs and samples,
  ``hpl_exceedance`` the fraction of samples where the true horizontal error exceeds it (at most the integrity
  risk when the protection level keeps its promise).
* Fix error bins (Shockley Figs. 4.8-4.19): fractions of issued fixes whose error is < 3 m, 3-10 m, 10-20 m,
  >= 20 m; ``fix_within_3m_fraction`` is the first bin.
* Divergence (Wang et al. 2022 sec. 4.3: "RMS position error becomes increasingly large over time without
  apparent bound"). Stated test, :func:`is_divergent`: a run diverges when, over the last quarter of the run, its
  mean horizontal error is more than ``growth`` (2) times its mean error over the second quarter (the error keeps
  growing instead of settling) AND more than ``fraction_of_free`` (0.5) times the free-inertial mean error of the
  same run over the same last quarter (the aiding has lost at least half of its benefit). The free-inertial
  baseline itself is tested against itself, so it "diverges" whenever its error doubles between the quarters.
  ``divergence_rate`` is the fraction of runs that diverge. It is a test of the *error*, as the gravity-matching
  literature uses it (issue 16's studies compare against Wang's tables with it); it also flags an aided run that
  simply received no fix late and follows free inertial with an honestly growing covariance.
* Filter divergence (the estimation-theory sense, Bar-Shalom et al. 2001 sec. 5.4: the error leaves the covariance
  the filter claims), :func:`is_nees_divergent`: a run diverges when its mean horizontal NEES over the last quarter
  of the run exceeds :data:`NEES_DIVERGENCE_BOUND`, the 99 % point of chi-square with 2 degrees of freedom (9.21):
  a consistent filter's NEES is chi-square(2) at each epoch, and its mean over correlated epochs exceeds that point
  less often than one epoch does, so at most 1 % of consistent runs are flagged, while a run whose error grows
  with a covariance that grows as fast is not. ``nees_divergence_rate`` is the fraction of the runs with a
  covariance that diverge so (``null`` without any).

* ``rms_after_first_fix_m``: the ensemble horizontal RMS from each run's first accepted fix on (the samples at or
  after the time the fuser first applied a fix, pooled over the runs that had one; Storms 2009 Figs. 4.12-4.13 plot
  the ensemble RMS "once the initial positioning error is resolved"); ``null`` when no run accepted a fix.

Besides DESIGN.md's keys each entry holds ``fix_error_bins`` (the four bins above), ``fix_within_3m_fraction``,
``fix_attempts``, ``fixes_issued``, ``no_fix_reasons`` (how often each class of "no fix" reason occurred over all
runs, the text before the reason's first colon: "flat map", "diverged", ...; added by :mod:`.runner`) and
``non_finite_fraction`` (share of error samples that were not finite: an
estimator that blew up). Undefined values (no fixes, no covariance) are ``null``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core.frames import horizontal_error_m, latlon_to_meters, wrap_angle

FIX_BIN_EDGES_M = (3.0, 10.0, 20.0)
FIX_BIN_NAMES = ("lt_3m", "3_to_10m", "10_to_20m", "ge_20m")
DIVERGENCE_GROWTH = 2.0
DIVERGENCE_FRACTION_OF_FREE = 0.5
#: chi-square(2) 99 % point, -2 ln(0.01): the filter-divergence bound on a run's last-quarter mean horizontal NEES
NEES_DIVERGENCE_BOUND = float(-2.0 * np.log(0.01))


def horizontal_errors(lat: ArrayLike, lon: ArrayLike, lat_true: ArrayLike, lon_true: ArrayLike) -> NDArray[np.float64]:
    """Horizontal error (m) per sample between estimate and truth (rad)."""
    return horizontal_error_m(lat, lon, lat_true, lon_true)


def ne_errors(
    lat: ArrayLike, lon: ArrayLike, lat_true: ArrayLike, lon_true: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """North and east errors (m), estimate minus truth (rad inputs), local-tangent approximation."""
    lat_true = np.asarray(lat_true, float)
    dn, de = latlon_to_meters(np.asarray(lat) - lat_true, wrap_angle(np.asarray(lon) - lon_true), lat_true)
    return np.asarray(dn, float), np.asarray(de, float)


def nees_ne(d_n: ArrayLike, d_e: ArrayLike, cov_ne: ArrayLike) -> NDArray[np.float64]:
    """Horizontal NEES d^T P^-1 d per sample: ``d_n``, ``d_e`` (N,) m, ``cov_ne`` (N,2,2) m^2. NaN where P is
    not positive definite or missing."""
    d = np.stack([np.asarray(d_n, float), np.asarray(d_e, float)], axis=-1)
    P = np.asarray(cov_ne, float)
    a, b, c = P[..., 0, 0], 0.5 * (P[..., 0, 1] + P[..., 1, 0]), P[..., 1, 1]
    det = a * c - b * b
    ok = (a > 0) & (det > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        q = (c * d[..., 0] ** 2 - 2 * b * d[..., 0] * d[..., 1] + a * d[..., 1] ** 2) / det
    return np.where(ok, q, np.nan)


def sigma_h_m(cov_ne: ArrayLike) -> NDArray[np.float64]:
    """Horizontal 1-sigma (m): sqrt(trace(P_ne)) per sample (DRMS)."""
    P = np.asarray(cov_ne, float)
    return np.sqrt(np.maximum(P[..., 0, 0] + P[..., 1, 1], 0.0))


def quarter_means(e: ArrayLike) -> NDArray[np.float64]:
    """Mean of ``e`` over each quarter of its samples (4,), ignoring NaN."""
    e = np.asarray(e, float)
    parts = np.array_split(e, 4)
    return np.array([np.nanmean(p) if np.isfinite(p).any() else np.nan for p in parts])


def is_divergent(
    e: ArrayLike,
    e_free: ArrayLike,
    growth: float = DIVERGENCE_GROWTH,
    fraction_of_free: float = DIVERGENCE_FRACTION_OF_FREE,
) -> bool:
    """The divergence test of the module docstring: ``e`` the run's horizontal error series (m), ``e_free`` the
    free-inertial error of the same run on the same samples (m). A run with non-finite errors (the estimator
    blew up) is divergent."""
    e = np.asarray(e, float)
    if e.size < 4:
        return False
    if not np.all(np.isfinite(e)):
        return True
    q = quarter_means(e)
    qf = quarter_means(e_free)
    return bool(q[3] > growth * q[1] and q[3] > fraction_of_free * qf[3])


def is_nees_divergent(nees: ArrayLike, bound: float = NEES_DIVERGENCE_BOUND) -> bool | None:
    """Filter divergence (module docstring): the run's mean horizontal NEES ``nees`` (per sample, NaN without a
    covariance) over its last quarter exceeds ``bound``; None when the last quarter has no finite NEES."""
    q = np.array_split(np.asarray(nees, float), 4)[-1] if np.size(nees) >= 4 else np.zeros(0)
    q = q[np.isfinite(q)]
    return bool(np.mean(q) > bound) if q.size else None


def fix_error_bins(fix_errors_m: ArrayLike) -> dict[str, float]:
    """Fractions of fixes per error bin (< 3, 3-10, 10-20, >= 20 m); NaN fractions when there are no fixes."""
    e = np.asarray(fix_errors_m, float)
    e = e[np.isfinite(e)]
    if e.size == 0:
        return dict.fromkeys(FIX_BIN_NAMES, float("nan"))
    idx = np.searchsorted(np.asarray(FIX_BIN_EDGES_M), e, side="right")
    counts = np.bincount(idx, minlength=len(FIX_BIN_NAMES))
    return {n: float(c) / e.size for n, c in zip(FIX_BIN_NAMES, counts, strict=True)}


@dataclass
class RunMetrics:
    """One estimator in one run: the error series (m) on the study's common time base, the filter's horizontal
    NEES series (NaN without covariance), fix errors (m) of issued fixes, fix attempts, and the divergence flag."""

    e: NDArray[np.float64]
    nees: NDArray[np.float64]
    fix_errors_m: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    fix_attempts: int = 0
    divergent: bool = False
    first_fix_index: int | None = None
    hpl_m: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))  # per sample (NaN: none), m
    fix_nees: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))  # per issued fix


def first_fix_index(t: ArrayLike, fix_t: ArrayLike, fix_accepted: ArrayLike) -> int | None:
    """Index of the first sample of the time base ``t`` (s) at or after the first accepted fix (``fix_t`` s with
    ``fix_accepted`` flags); None when no fix was accepted or the flags are unknown (empty)."""
    ft = np.asarray(fix_t, float)
    ok = np.asarray(fix_accepted, bool)
    if ok.size == 0 or ok.size != ft.size or not ok.any():
        return None
    k = int(np.searchsorted(np.asarray(t, float), float(ft[ok].min()) - 1e-9, side="left"))
    return k if k < len(np.asarray(t)) else None


def hpl_statistics(e: ArrayLike, hpl: ArrayLike) -> tuple[float | None, float | None]:
    """``(median HPL, fraction of samples where e > HPL)`` over the samples with a finite HPL (m); a non-finite
    error (an estimator that blew up) counts as an exceedance. ``(None, None)`` without any HPL."""
    e = np.asarray(e, float).reshape(-1)
    h = np.asarray(hpl, float).reshape(-1)
    ok = np.isfinite(h)
    if h.size != e.size or not ok.any():
        return None, None
    with np.errstate(invalid="ignore"):
        over = ~np.isfinite(e[ok]) | (e[ok] > h[ok])
    return float(np.median(h[ok])), float(np.mean(over))


def aggregate(runs: list[RunMetrics], matcher: str | None, fusion: str) -> dict[str, Any]:
    """Pool one estimator's runs into the ``metrics.json`` entry (keys as in ``shared/DESIGN.md``). The runs may
    have different lengths (runs of several cases pooled, as the real-data suite does)."""
    E = np.concatenate([r.e for r in runs]) if runs else np.zeros(0)  # runs may differ in length (pooled cases)
    fin = np.isfinite(E)
    e_all = E[fin]
    nees = np.concatenate([r.nees for r in runs]) if runs else np.zeros(0)
    nees = nees[np.isfinite(nees)]
    fix_e = np.concatenate([r.fix_errors_m for r in runs]) if runs else np.zeros(0)
    attempts = sum(r.fix_attempts for r in runs)
    issued = int(np.isfinite(fix_e).sum())
    bins = fix_error_bins(fix_e)
    final = np.array([r.e[-1] if r.e.size else np.nan for r in runs])
    hpl_med, hpl_exc = hpl_statistics(E, np.concatenate([_as_len(r.hpl_m, r.e.size) for r in runs]) if runs else E)
    fix_nees = np.concatenate([r.fix_nees for r in runs]) if runs else np.zeros(0)
    fix_nees = fix_nees[np.isfinite(fix_nees)]
    out: dict[str, Any] = {
        "matcher": matcher,
        "fusion": fusion,
        "rms_horizontal_m": _f(np.sqrt(np.mean(e_all**2))) if e_all.size else None,
        "mean_horizontal_m": _f(np.mean(e_all)) if e_all.size else None,
        "max_horizontal_m": _f(np.max(e_all)) if e_all.size else None,
        "final_horizontal_m": _f(np.sqrt(np.nanmean(final**2))) if np.isfinite(final).any() else None,
        "divergence_rate": float(np.mean([r.divergent for r in runs])) if runs else None,
        "nees_divergence_rate": _nees_divergence_rate(runs),
        "availability": (issued / attempts) if attempts else None,
        "fix_attempts": int(attempts),
        "fixes_issued": issued,
        "nees_mean": _f(np.mean(nees)) if nees.size else None,
        "fix_nees_mean": _f(np.mean(fix_nees)) if fix_nees.size else None,
        "hpl_median_m": None if hpl_med is None else _f(hpl_med),
        "hpl_exceedance": hpl_exc,
        "fix_error_bins": {k: _f(v) for k, v in bins.items()},
        "fix_within_3m_fraction": _f(bins["lt_3m"]),
        "non_finite_fraction": float(1.0 - fin.mean()) if E.size else 0.0,
        "rms_after_first_fix_m": _rms_after_first_fix(runs),
    }
    return out


def _nees_divergence_rate(runs: list[RunMetrics]) -> float | None:
    """``nees_divergence_rate`` (module docstring): over the runs with a last-quarter NEES."""
    flags = [f for f in (is_nees_divergent(r.nees) for r in runs) if f is not None]
    return float(np.mean(flags)) if flags else None


def _rms_after_first_fix(runs: list[RunMetrics]) -> float | None:
    """``rms_after_first_fix_m`` (module docstring)."""
    parts = [r.e[r.first_fix_index :] for r in runs if r.first_fix_index is not None]
    e = np.concatenate(parts) if parts else np.zeros(0)
    e = e[np.isfinite(e)]
    return _f(np.sqrt(np.mean(e**2))) if e.size else None


def _as_len(a: NDArray[np.float64], n: int) -> NDArray[np.float64]:
    """``a`` if it has ``n`` samples, else NaNs (a run without a protection level)."""
    a = np.asarray(a, float)
    return a if a.size == n else np.full(n, np.nan)


def _f(x: Any) -> float | None:
    """JSON-safe float: NaN/inf -> None."""
    x = float(x)
    return x if np.isfinite(x) else None
