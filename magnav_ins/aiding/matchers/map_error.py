"""The map's own prediction error as the matchers see it (DESIGN "Integrity").

A reading ``z`` at the true position ``x`` differs from the map prediction ``m(x)`` by the sensor noise *and* the
map error: ``z - m(x) = v_sensor + e_map(x)``, so every matcher's likelihood uses the variance
``sigma_sensor^2 + sigma_map(x)^2``. The map error is spatially correlated: readings closer together than its
correlation length ``ell`` share most of their map error and are not independent evidence.

Where the map error comes from (:func:`resolve_map_error`), in this order: a matcher's explicit ``map_sigma``
option (the user's number, kept for old scenarios), the map's error layer (:attr:`GridMap.has_error_layer`,
estimated by cross-validation when a survey is gridded), else the stated default below for a map that does not
know its error.

The default (a map from elsewhere, no layer): 1-sigma ``DEFAULT_ERROR_FRACTION_OF_STD`` (10 %) of the map's own
standard deviation, uniform, correlated over ``DEFAULT_CORRELATION_NODES`` (2) node spacings. Evidence: the 22
Osborne tie lines (``builtin:osborne-tie-lines``, never used by ``builtin:osborne-magnetic``) differ from that map
by 4-48 nT RMS after removing each line's mean (all lines: 30 nT; the map's standard deviation is 302 nT, so 10 %),
and their along-line autocorrelation follows the Gaussian kernel below with ``ell`` = 210 m = 2 node spacings
(measured 0.75 at 100 m, 0.39 at 200 m, 0.06 at 350 m; the kernel gives 0.80, 0.40, 0.06). A map that is not a grid (a road map's points, :class:`~magnav_ins.maps.track.TrackMap`)
is sampled where it was measured, not interpolated: without ``map_sigma`` it is taken as exact. It is one
survey's figure, not a law: a map whose error is known
should carry a layer, or the matcher should be given ``map_sigma``.

Level offset (:func:`resolve_level`, :func:`level_fraction`). Besides the per-node error, a flight's readings may
sit a constant level off the map (the survey's levelling against the flight, diurnal variation, the platform's own
field): Osborne's tie lines are 17-30 nT (mean -24 nT) below its flight lines' levelling. That is not a random
per-node error: counted as one (in the error layer's inflation, as until 2026-12) it makes a matcher over-cautious
about the field's shape and over-confident about its level. The batch matchers marginalise it per section with the
prior ``N(0, sigma_b^2)`` (ML / MLR / ABL, PMHT); the particle filters carry it as a state with a diffuse prior
(``level_sigma``); ``bayes_grid`` (one reading per fix) has no level term: a level shared by successive fixes is
not a per-fix variance, and would need a level state in the fuser. ``sigma_b`` is the map's ``metadata["level_sigma"]`` (e.g. from a survey's tie-line crossovers),
else :data:`DEFAULT_LEVEL_FRACTION_OF_STD` of the map's std.

Correlation model. The map error is a zero-mean Gaussian process with the squared-exponential correlation
``rho(d) = exp(-(d / ell)^2)``: the correlation length ``ell`` (``GridMap.error_correlation_m``) is the lag where
the correlation has fallen to 1/e, as :mod:`magnav_ins.maps.error_layer` measures it from the cross-validation
residuals. :func:`magnav_ins.maps.synthetic.gaussian_random_field` draws this kernel with its length scale
``l = ell / sqrt(2)`` (its correlation is ``exp(-r^2 / (2 l^2))``). For a section of
``K`` readings at positions ``(n_k, e_k)`` the residuals ``z_k - m(x_k)`` then have the covariance (the "full
covariance" of a section)::

    Sigma = sigma_s^2 I + D C D,   C_ij = rho(|x_i - x_j|),   D = diag(sigma_map(x_k))

:func:`section_covariance` builds it; :func:`sandwich_covariance` gives the covariance of a position estimated
from a likelihood that *assumed* independent readings (the scan's cheap diagonal likelihood) when the residuals
really have ``Sigma`` (the "sandwich" ``A^-1 B A^-1`` of a misspecified least-squares fit, linearised at the
estimate; White 1982, eq. 2.5 / the robust covariance of quasi-likelihood); :func:`likelihood_temperature` turns
it into the factor by which that likelihood's log must be divided to be honest; :func:`effective_count` is the
number of independent readings a correlated section is worth. Recursive filters, which take one reading at a time,
use the first-order Markov approximation :func:`markov_coefficient` with the same integral scale.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import gammaincinv

from ...core.protocols import FieldMap

FloatArray = NDArray[np.float64]

#: A map without an error layer: 1-sigma map error = this fraction of the map's standard deviation ...
DEFAULT_ERROR_FRACTION_OF_STD = 0.10
#: ... with a correlation length of this many node spacings (module docstring: the Osborne tie lines give 210 m on
#: a 100 m grid).
DEFAULT_CORRELATION_NODES = 2.0
#: integral scale of the correlation, in units of ``ell``: int_0^inf exp(-(d / ell)^2) dd = ell sqrt(pi) / 2
INTEGRAL_SCALE = float(np.sqrt(np.pi) / 2.0)


@dataclass(frozen=True)
class MapErrorModel:
    """Where the matcher's map error comes from: ``source`` is ``"option"``, ``"layer"`` or ``"default"``.

    ``uniform_sigma`` (map unit) is set for ``option`` / ``default``; for ``layer`` the sigma varies by position
    (:meth:`sigma_at`). ``correlation_m`` is the error's correlation length ``ell`` (m) of the kernel in the module
    docstring; NaN when unknown (then readings are taken as uncorrelated)."""

    source: str
    uniform_sigma: float
    correlation_m: float
    fmap: FieldMap | None = None

    def sigma_at(self, lat: ArrayLike, lon: ArrayLike) -> FloatArray:
        """1-sigma map error (map unit) at ``(lat, lon)`` rad, shape of the broadcast inputs; off the map the
        layer's value is NaN and is replaced by the layer's largest value (the most cautious)."""
        la, lo = np.broadcast_arrays(np.asarray(lat, dtype=float), np.asarray(lon, dtype=float))
        if self.source != "layer":
            return np.full(la.shape, self.uniform_sigma)
        s = np.asarray(self.fmap.error_sigma_at(la, lo), dtype=float)  # type: ignore[union-attr]
        if np.any(~np.isfinite(s)):
            s = np.where(np.isfinite(s), s, float(np.nanmax(self.fmap.error_sigma)))  # type: ignore[union-attr]
        return s

    def describe(self) -> str:
        """One line for reasons and logs: where the map error came from and its size."""
        ell = f"{self.correlation_m:.0f} m" if np.isfinite(self.correlation_m) else "unknown"
        if self.source == "layer":
            return f"map error from the map's layer, correlation {ell}"
        return f"map error {self.uniform_sigma:.3g} ({self.source}), correlation {ell}"


def _default_for(fmap: FieldMap) -> tuple[float, float]:
    if getattr(fmap, "spacing_m", None) is None:  # not a grid (a road map's points): sampled, not interpolated
        return 0.0, float("nan")
    vals = np.asarray(getattr(fmap, "values", np.array([np.nan])), dtype=float)
    std = float(np.nanstd(vals)) if np.any(np.isfinite(vals)) else float("nan")
    spacing = getattr(fmap, "spacing_m", None)
    corr = DEFAULT_CORRELATION_NODES * float(np.mean(spacing)) if spacing is not None else float("nan")
    return DEFAULT_ERROR_FRACTION_OF_STD * std, corr


def resolve_map_error(
    fmap: FieldMap, map_sigma: float | None = None, correlation_m: float | None = None
) -> MapErrorModel:
    """The map error a matcher should use (module docstring): ``map_sigma`` (map unit, > 0) overrides the map's
    layer; ``correlation_m`` (m, > 0) overrides the correlation length."""
    if correlation_m is not None and not correlation_m > 0:
        correlation_m = None
    if map_sigma is not None and map_sigma > 0:
        corr = correlation_m if correlation_m is not None else getattr(fmap, "error_correlation_m", None)
        if corr is None:
            corr = _default_for(fmap)[1]
        return MapErrorModel("option", float(map_sigma), float(corr))
    if getattr(fmap, "has_error_layer", False):
        corr = correlation_m if correlation_m is not None else fmap.error_correlation_m  # type: ignore[attr-defined]
        return MapErrorModel("layer", float("nan"), float(corr), fmap)
    sig, corr = _default_for(fmap)
    return MapErrorModel("default", sig, float(correlation_m) if correlation_m is not None else corr)


# ------------------------------------------------------------------------------------------------ level
#: A map that states no level uncertainty (``metadata["level_sigma"]``): the 1-sigma of the constant offset between
#: a flight's readings and the map is this fraction of the map's standard deviation (the same rule as the default
#: map error; a magnetic anomaly map with a 100-300 nT spread gives 10-30 nT, the size of the Osborne tie lines'
#: 17-30 nT offsets from the map's levelling).
DEFAULT_LEVEL_FRACTION_OF_STD = 0.10


@dataclass(frozen=True)
class LevelModel:
    """The prior of the constant level offset ``b`` between a section's readings and the map (the map's levelling,
    diurnal variation, the platform's residual field): ``b ~ N(0, sigma^2)``, ``sigma`` in the map unit (0 = no
    offset, the old absolute-level likelihood), one value per field component; ``source`` says where it came
    from (``"option"``, ``"map"`` or ``"default"``) and ``detail`` how the map derived it."""

    sigma: float
    source: str
    detail: str = ""

    def describe(self) -> str:
        """One line for reasons and logs."""
        return f"level offset 1-sigma {self.sigma:.3g} ({self.source}{': ' + self.detail if self.detail else ''})"


def resolve_level(fmap: FieldMap, level_sigma: float | None = None) -> LevelModel:
    """The level-offset prior a matcher should use: ``level_sigma`` (map unit, >= 0; 0 switches the level term
    off) overrides the map's own (``fmap.metadata["level_sigma"]``, stated when gridding,
    :func:`magnav_ins.maps.build.grid_survey`, or by the user), else the stated default:
    :data:`DEFAULT_LEVEL_FRACTION_OF_STD` of the map's standard deviation (what a new flight may add: diurnal
    variation, its platform's field), or the survey's own crossover level differences
    (``metadata["level_crossover"]``, :func:`magnav_ins.maps.build.crossover_level_sigma`) when larger; 0 for a map
    that is not a grid."""
    if level_sigma is not None:
        return LevelModel(float(level_sigma), "option")
    meta = getattr(fmap, "metadata", None) or {}
    val = meta.get("level_sigma") if isinstance(meta, dict) else None
    if isinstance(val, (int, float)) and np.isfinite(val) and val >= 0:
        return LevelModel(float(val), "map", str(meta.get("level_sigma_source", "")))
    if getattr(fmap, "spacing_m", None) is None:
        return LevelModel(0.0, "default", "not a grid")
    vals = np.asarray(getattr(fmap, "values", np.array([np.nan])), dtype=float)
    std = float(np.nanstd(vals)) if np.any(np.isfinite(vals)) else 0.0
    xo = meta.get("level_crossover") if isinstance(meta, dict) else None
    xo_rms = float(xo.get("rms", 0.0)) if isinstance(xo, dict) else 0.0
    if np.isfinite(xo_rms) and xo_rms > DEFAULT_LEVEL_FRACTION_OF_STD * std:
        return LevelModel(xo_rms, "default", f"the survey's crossover level differences ({xo.get('lines')} lines)")
    return LevelModel(
        DEFAULT_LEVEL_FRACTION_OF_STD * std, "default", f"{DEFAULT_LEVEL_FRACTION_OF_STD:g} x the map's std"
    )


def level_fraction(level_var: float, s2: float, k: int) -> float:
    """The fraction ``gamma`` of the section mean that a likelihood over ``k`` residuals of working variance ``s2``
    subtracts when it marginalises a level offset of variance ``level_var``: with ``Sigma = s2 I + level_var 1 1'``,
    ``r' Sigma^-1 r = |r - gamma mean(r) 1|^2 / s2`` (Sherman-Morrison) for ``gamma = 1 - sqrt(s2 / (s2 + k
    level_var))``. 0 without a level (or one reading: then the level is only more variance), 1 for a diffuse one
    (``demean``)."""
    if k < 2 or not level_var > 0:
        return 0.0
    if not np.isfinite(level_var):
        return 1.0
    return float(1.0 - np.sqrt(s2 / (s2 + k * level_var)))


# ------------------------------------------------------------------------------------------------ correlation
def correlation(d_m: ArrayLike, ell_m: float) -> FloatArray:
    """Map-error correlation ``exp(-(d / ell)^2)`` at distance ``d_m`` (m); with an unknown (NaN) or zero
    ``ell_m`` the errors are uncorrelated (1 at d = 0, else 0)."""
    d = np.asarray(d_m, dtype=float)
    if not (np.isfinite(ell_m) and ell_m > 0):
        return (d == 0.0).astype(float)
    return np.exp(-((d / ell_m) ** 2))


def correlation_matrix(n: ArrayLike, e: ArrayLike, ell_m: float) -> FloatArray:
    """``C_ij = rho(|x_i - x_j|)`` (K, K) for points at north ``n``, east ``e`` (K,) m."""
    n = np.asarray(n, dtype=float).ravel()
    e = np.asarray(e, dtype=float).ravel()
    d = np.hypot(n[:, None] - n[None, :], e[:, None] - e[None, :])
    return correlation(d, ell_m)


def section_covariance(
    n: ArrayLike, e: ArrayLike, sigma_map: ArrayLike, sigma_sensor: float, ell_m: float
) -> FloatArray:
    """Covariance (K, K), map unit squared, of the residuals ``z_k - m(x_k)`` of a section of readings at
    ``(n, e)`` m: ``sigma_sensor^2 I + D C D`` with ``D = diag(sigma_map)`` (module docstring)."""
    s = np.broadcast_to(np.asarray(sigma_map, dtype=float).ravel(), (np.size(n),))
    c = correlation_matrix(n, e, ell_m)
    return float(sigma_sensor) ** 2 * np.eye(len(s)) + s[:, None] * c * s[None, :]


def effective_count(n: ArrayLike, e: ArrayLike, ell_m: float) -> float:
    """Number of independent readings a section at ``(n, e)`` m is worth for estimating a common offset:
    ``K^2 / sum_ij C_ij`` (1 for readings on top of each other, K for readings much farther apart than ``ell``)."""
    c = correlation_matrix(n, e, ell_m)
    return float(c.shape[0] ** 2 / np.sum(c)) if c.size else 0.0


def markov_coefficient(ds_m: ArrayLike, ell_m: float) -> FloatArray:
    """Correlation between successive readings ``ds_m`` (m) apart in a first-order Gauss-Markov approximation of
    the map error along a track, ``exp(-ds / L)`` with ``L = ell sqrt(pi) / 2`` so that its integral scale equals the
    squared-exponential kernel's (a long section is then worth the same number of independent readings). 0 when
    ``ell`` is unknown."""
    ds = np.abs(np.asarray(ds_m, dtype=float))
    if not (np.isfinite(ell_m) and ell_m > 0):
        return np.zeros_like(ds)
    return np.exp(-ds / (INTEGRAL_SCALE * ell_m))


# ------------------------------------------------------------------------------------------------ sandwich
def section_transform(k: int, demean: bool, difference: bool, level: float = 0.0) -> FloatArray:
    """The linear map ``T`` a likelihood matcher applies to a section's residuals: successive differences
    ``(K-1, K)`` if ``difference``, then the removal of the mean if ``demean``, or of the fraction ``level`` of it
    (:func:`level_fraction`: the marginalised level offset; ``T' T = Sigma_level^-1 s2``), identity otherwise."""
    t = np.eye(k)
    if difference and k > 1:
        t = np.diff(t, axis=0)
    frac = 1.0 if demean else float(level)
    if frac > 0 and t.shape[0] > 1:
        t = t - frac * t.mean(axis=0, keepdims=True)
    return t


def sandwich_covariance(jac: ArrayLike, sigma: ArrayLike, transform: ArrayLike | None = None) -> FloatArray:
    """Covariance (2, 2) m^2 of the offset that minimises ``|T (z - m(x + p))|^2`` when the residuals have the
    covariance ``sigma`` (K, K): ``A^-1 B A^-1`` with ``A = J' T' T J``, ``B = J' T' (T Sigma T') T J``, ``J``
    (K, 2) or (K, c, 2) the map gradient (unit/m, north/east) at the readings (components independent, each with
    ``sigma``), linearised at the estimate. Infinite when the section does not constrain both directions."""
    j = np.asarray(jac, dtype=float)
    j = j.reshape(j.shape[0], -1, 2)
    s = np.asarray(sigma, dtype=float)
    t = np.eye(j.shape[0]) if transform is None else np.asarray(transform, dtype=float)
    tst = t @ s @ t.T
    a = np.zeros((2, 2))
    b = np.zeros((2, 2))
    for c in range(j.shape[1]):
        tj = t @ j[:, c, :]
        a += tj.T @ tj
        b += tj.T @ tst @ tj
    if not np.all(np.isfinite(a)) or np.linalg.cond(a) > 1e12:
        return np.full((2, 2), np.inf)
    ai = np.linalg.inv(a)
    out = ai @ b @ ai
    return 0.5 * (out + out.T)


def likelihood_temperature(
    jac: ArrayLike, sigma: ArrayLike, s2_assumed: float, transform: ArrayLike | None = None
) -> float:
    """How much a likelihood that assumed independent residuals of variance ``s2_assumed`` over-states its
    information: the largest eigenvalue of ``(s2 A^-1)^-1 (A^-1 B A^-1)`` (:func:`sandwich_covariance`), i.e. the
    factor by which its covariance ``s2 A^-1`` must grow to cover the sandwich in every direction. Dividing the
    log-likelihood by it gives a surface whose curvature is the honest one at the peak. At least 1; 1 when the
    section does not constrain both directions (nothing to say)."""
    j = np.asarray(jac, dtype=float)
    j = j.reshape(j.shape[0], -1, 2)
    t = np.eye(j.shape[0]) if transform is None else np.asarray(transform, dtype=float)
    a = np.zeros((2, 2))
    for c in range(j.shape[1]):
        tj = t @ j[:, c, :]
        a += tj.T @ tj
    sw = sandwich_covariance(j, sigma, t)
    if not np.all(np.isfinite(sw)):
        return 1.0
    # generalised eigenproblem sw v = lam (s2 A^-1) v  <=>  lam = eig(A sw) / s2
    lam = np.linalg.eigvals(a @ sw).real / float(s2_assumed)
    return float(max(1.0, np.max(lam)))


def temperature_and_topup(
    jac: ArrayLike, sigma: ArrayLike, s2_assumed: float, transform: ArrayLike | None = None
) -> tuple[float, FloatArray]:
    """A scalar temperature for a likelihood surface and the covariance to add to its moments so that they cover
    the sandwich in every direction, without over-tempering the well-determined one: the geometric mean
    ``sqrt(lam_min lam_max)`` (at least 1) of the eigenvalues of :func:`likelihood_temperature`'s problem, and
    the positive semi-definite part of ``sandwich - temperature s2 A^-1`` (m^2). (1, 0) when the section does not
    constrain both directions."""
    j = np.asarray(jac, dtype=float)
    j = j.reshape(j.shape[0], -1, 2)
    t = np.eye(j.shape[0]) if transform is None else np.asarray(transform, dtype=float)
    a = np.zeros((2, 2))
    for c in range(j.shape[1]):
        tj = t @ j[:, c, :]
        a += tj.T @ tj
    sw = sandwich_covariance(j, sigma, t)
    if not np.all(np.isfinite(sw)):
        return 1.0, np.zeros((2, 2))
    lam = np.linalg.eigvals(a @ sw).real / float(s2_assumed)
    temp = float(max(1.0, np.sqrt(max(float(np.min(lam)), 0.0) * float(np.max(lam)))))
    d = sw - temp * float(s2_assumed) * np.linalg.inv(a)
    w, v = np.linalg.eigh(0.5 * (d + d.T))
    return temp, (v * np.maximum(w, 0.0)) @ v.T


def whitened_misfit(residual: ArrayLike, sigma: ArrayLike, transform: ArrayLike | None = None) -> tuple[float, int]:
    """``(chi2, dof)`` of a section's residuals (K,) or (K, c) at the estimate under the covariance ``sigma``
    (K, K) per component, after the matcher's transform ``T``: ``r' T' (T Sigma T')^+ T r`` with the pseudo-inverse
    over the rank of ``T Sigma T'``; ``dof`` = that rank times the components, minus the 2 fitted offsets."""
    r = np.asarray(residual, dtype=float)
    r = r.reshape(r.shape[0], -1)
    t = np.eye(r.shape[0]) if transform is None else np.asarray(transform, dtype=float)
    w, v = np.linalg.eigh(t @ np.asarray(sigma, dtype=float) @ t.T)
    keep = w > 1e-10 * max(float(np.max(w)), 1e-300)
    proj = v[:, keep].T @ (t @ r)  # (rank, c)
    chi2 = float(np.sum(proj**2 / w[keep][:, None]))
    return chi2, int(keep.sum() * r.shape[1]) - 2


#: a section's misfit scales its covariance only when its chi-square exceeds this quantile (a model that
#: under-states the residuals, not a chance fluctuation of a right one); shared by every matcher
MISFIT_PROBABILITY = 0.99


def misfit_factor(chi2: float, dof: float) -> float:
    """``chi2 / dof`` when the chi-square ``chi2`` with ``dof`` degrees of freedom exceeds its
    :data:`MISFIT_PROBABILITY` quantile (the readings misfit by more than the model allows: the covariance is to
    grow by that factor), else 1."""
    if dof > 0 and np.isfinite(chi2) and chi2 > float(2.0 * gammaincinv(dof / 2.0, MISFIT_PROBABILITY)):  # chi2.ppf
        return float(chi2 / dof)
    return 1.0


def drift_covariance(jac: ArrayLike, tau: ArrayLike, drift_mps: ArrayLike) -> FloatArray:
    """Covariance (K, K) of a section's readings from the INS's velocity drift over it: ``delta p_k = dv (t_k - t_K)``
    per axis, rank one per axis, ``sum_a g_a g_a'`` with ``g_a = (sum_c jac[:, c, a]) tau drift_mps[a]``; ``jac``
    (K, c, 2) field per metre, ``tau`` (K,) s the reading times less the last's, ``drift_mps`` (2,) m/s 1-sigma."""
    j = np.asarray(jac, dtype=float)
    t = np.asarray(tau, dtype=float)
    out = np.zeros((j.shape[0], j.shape[0]))
    for a in range(2):
        g = j[:, :, a].sum(axis=1) * t * float(np.asarray(drift_mps, dtype=float)[a])
        out += np.outer(g, g)
    return out


# ------------------------------------------------------------------------------------------------ variogram
@dataclass(frozen=True)
class FieldVariogram:
    """The map's own field as a stationary isotropic process (for a track moved by an unknown drift): semivariogram
    ``gamma(h) = E |m(x + h) - m(x)|^2 / 2`` (map unit^2, summed over components) at lags ``lags_m`` (m, from 0),
    and the field's variance ``variance`` (map unit^2, summed over components) over the map."""

    lags_m: FloatArray
    gamma: FloatArray
    variance: float

    def at(self, h_m: ArrayLike) -> FloatArray:
        """``gamma`` at lags ``h_m`` (m; linear between the tabulated lags, the last value beyond them)."""
        return np.interp(np.abs(np.asarray(h_m, dtype=float)), self.lags_m, self.gamma)

    def correlation(self, h_m: ArrayLike) -> FloatArray:
        """The field's correlation at lags ``h_m`` (m): ``max(0, 1 - gamma(h) / variance)``."""
        if not self.variance > 0:
            return (np.asarray(h_m, dtype=float) == 0.0).astype(float)
        return np.clip(1.0 - self.at(h_m) / self.variance, 0.0, 1.0)

    def drift_variance(self, sigma_m: ArrayLike) -> FloatArray:
        """``E |m(x + delta) - m(x)|^2 = E 2 gamma(|delta|)`` (map unit^2) for a horizontal displacement
        ``delta ~ N(0, sigma^2 I)`` (``sigma_m`` m, any shape): the mean over 32 quantiles of the Rayleigh
        distribution of ``|delta|``."""
        s = np.asarray(sigma_m, dtype=float)
        u = np.sqrt(-2.0 * np.log(1.0 - (np.arange(32) + 0.5) / 32.0))  # unit Rayleigh quantiles
        return np.mean(2.0 * self.at(s[..., None] * u), axis=-1)


#: the variogram's lags: this many node counts from 1 to half the axis, geometrically spaced ...
VARIOGRAM_LAGS = 48
#: ... over at most about this many grid lines per axis (every k-th line of a larger grid)
VARIOGRAM_LINES = 512


def field_variogram(fmap: FieldMap) -> FieldVariogram | None:
    """The semivariogram of the map's node values (:class:`FieldVariogram`) from the differences of nodes ``k``
    apart along each grid axis (:data:`VARIOGRAM_LAGS` values of ``k`` from 1 to half the axis, geometrically
    spaced, over at most about :data:`VARIOGRAM_LINES` lines; lags ``k`` times the axis spacing ``spacing_m``, m),
    the two axes interpolated onto one lag axis and averaged, made non-decreasing (the larger, cautious value where a
    periodic field's variogram dips). None for a map that is not a grid (no ``values`` /
    ``spacing_m``). Cached on the map object."""
    cached = getattr(fmap, "_field_variogram", None)
    if cached is not None:
        return cached
    sp = getattr(fmap, "spacing_m", None)
    vals = getattr(fmap, "values", None)
    if sp is None or vals is None:
        return None
    sp = np.asarray(sp() if callable(sp) else sp, dtype=float).ravel()
    v = np.asarray(vals, dtype=float)
    v = v.reshape(v.shape[0], v.shape[1], -1) if v.ndim >= 2 else None  # type: ignore[assignment]
    if v is None or sp.size < 2 or not np.all(np.isfinite(sp) & (sp > 0)) or min(v.shape[:2]) < 3:
        return None
    curves = []
    for axis in (0, 1):
        n = v.shape[axis]
        ks = np.unique(np.round(np.geomspace(1, max(n // 2, 1), VARIOGRAM_LAGS)).astype(int))
        stride = max(1, v.shape[1 - axis] // VARIOGRAM_LINES)  # a subset of the lines across a large grid
        sub = v[:, ::stride] if axis == 0 else v[::stride, :]
        g = [0.0]
        for k in ks:
            d = (sub[k:] - sub[:-k]) if axis == 0 else (sub[:, k:] - sub[:, :-k])
            d2 = np.sum(d**2, axis=-1)
            g.append(0.5 * float(np.nanmean(d2)) if np.any(np.isfinite(d2)) else np.nan)
        curves.append((np.concatenate([[0.0], ks * sp[axis]]), np.asarray(g)))
    lags = np.unique(np.concatenate([c[0] for c in curves]))
    lags = lags[lags <= min(c[0][-1] for c in curves)]
    gam = np.nanmean([np.interp(lags, c[0], c[1]) for c in curves], axis=0)
    flat = v.reshape(-1, v.shape[-1])
    flat = flat[np.all(np.isfinite(flat), axis=1)]
    var = float(np.sum(np.var(flat, axis=0))) if len(flat) else float("nan")
    if not (np.all(np.isfinite(gam)) and np.isfinite(var)):
        return None
    out = FieldVariogram(lags, np.maximum.accumulate(gam), var)
    try:
        object.__setattr__(fmap, "_field_variogram", out)
    except (AttributeError, TypeError):
        pass
    return out


# ------------------------------------------------------------------------------------------------ off the map
def field_statistics(fmap: FieldMap) -> tuple[FloatArray, FloatArray]:
    """Mean and variance per component (map unit, unit^2) of the field over the map's finite values: what a
    reading is expected to be where the map has no value (the field's prior). Cached on the map object."""
    cached = getattr(fmap, "_field_statistics", None)
    if cached is not None:
        return cached
    v = np.asarray(fmap.values, dtype=float)
    ncomp = int(getattr(getattr(fmap, "kind", None), "components", 1) or 1)
    v = v.reshape(-1, ncomp)
    v = v[np.all(np.isfinite(v), axis=1)]
    out = (v.mean(axis=0), v.var(axis=0)) if len(v) else (np.zeros(ncomp), np.full(ncomp, np.inf))
    try:
        object.__setattr__(fmap, "_field_statistics", out)
    except (AttributeError, TypeError):
        pass
    return out


def off_map_loglik(z: ArrayLike, fmap: FieldMap, s2: ArrayLike) -> float:
    """Log-likelihood of the readings ``z`` (K, c) at a place where the map has no value, relative to the scale of
    an on-map likelihood ``-1/2 sum (z - m)^2 / s2``: the field there is unknown and drawn from the map's own field
    statistics (:func:`field_statistics`), ``z_k ~ N(mu, var + s2)`` independently, so

        log L_off = -1/2 sum_k sum_c [ (z - mu)^2 / (var + s2) + log((var + s2) / s2) ].

    A matcher compares it with its on-map candidates (the hypothesis "the vehicle is off the map" has this
    likelihood at every node without map values) to know when the vehicle has left its map (issue 15)."""
    mu, var = field_statistics(fmap)
    zz = np.asarray(z, dtype=float).reshape(-1, mu.size)
    s = np.asarray(s2, dtype=float)
    tot = var[None, :] + s
    return float(-0.5 * np.sum((zz - mu) ** 2 / tot + np.log(tot / s)))
