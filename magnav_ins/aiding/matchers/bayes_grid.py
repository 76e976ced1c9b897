"""Storms' Bayes grid matcher (Storms 2009, seed 004, sec. 2.3.2.4 and 3.4).

At each update:

1. Prior (eq. 3.5): the discrete bivariate Gaussian of the propagated mean and covariance (here the INS estimate
   handed to :meth:`BayesGridMatcher.predict`) on the map grid nodes of a window of ``window_sigma`` prior sigmas.
2. Likelihood (eq. 3.6): ``L = exp(-sum_k (y_k - h_k(x))^2 / (2 s^2))`` over the 3 field components (or the
   scalar), ``s^2 = sigma_reading^2 + map_sigma^2`` (log space).
3. Posterior = prior x likelihood (eq. 2.19); its peak (MAP) is the position measurement.
4. R (sec. 3.4.2.4, ``covariance="spread"``): through the peak, along north and along east, the normalised slice
   is treated as a pdf; the points leaving ``tail`` (~16 %) in each tail are found and their distances to the peak
   averaged -> ``sigma_N``, ``sigma_E``; ``R = diag(sigma_N^2, sigma_E^2)``. The thesis computes the slices from
   the likelihood (eq. 3.6) to keep R uncorrelated with the filter's prior (``spread_of="likelihood"``, default);
   ``"posterior"`` uses the posterior slices. The default ``covariance="posterior"`` reports instead the full
   posterior second moment about the peak: the slices only see the peak they cross, so when a second peak wins
   the published R is far too small (fix NEES mean ~13 against ~1.5 on our random 3-axis maps, 100 trials).
   The grid quantisation ``step^2 / 12`` is added to either.
Map resolution: where the RMS map gradient times the node spacing exceeds ``quantisation`` reading sigmas, the
window is resampled (bilinear) at a finer step (at most ``max_refine`` times finer), and the remaining node error
``|grad|^2 step^2 / 12`` is added to the likelihood variance.

Guards (Storms sec. 4.5 suggestions): several separated posterior peaks inside the prior region (a second local
maximum at least ``min_peak_separation_m`` away holding at least ``peak_ratio`` of the peak density, inside the
``prior_region_sigma`` ellipse) -> "no fix, ambiguous"; a reading residual at the peak above
``max_residual_sigma`` s per component (chi-square) -> "no fix, large residual"; off the map, flat map (feature
variability, Wang eq. 14), NaN reading -> "no fix" with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from ...core.errors import ConfigError
from ...core.protocols import FieldMap
from ...core.types import FieldReadings, Fix, NavEstimate
from ._local import (
    feature_variability,
    make_frame,
    map_components,
    native_gradient_rms,
    sigma_window,
    spacing_of,
    window_axes,
)

FloatArray = NDArray[np.float64]


@dataclass
class BayesGridState:
    """Prior of the next update: time ``t`` s, position ``lat``, ``lon`` rad, ``h`` m, ``cov_ne`` (2, 2) m^2,
    and the last fix produced (``None`` before the first update)."""

    t: float
    lat: float
    lon: float
    h: float
    cov_ne: FloatArray
    fix: Fix | None = None
    extra: dict[str, float] = field(default_factory=dict)


def _tail_sigma(pdf: FloatArray, x: FloatArray, x_peak: float, tail: float) -> float:
    """Storms' R (sec. 3.4.2.4): average distance from ``x_peak`` of the points leaving ``tail`` in each tail of
    the 1-D ``pdf`` sampled at ``x`` (linear interpolation of the cumulative sum at cell centres)."""
    p = np.where(np.isfinite(pdf), pdf, 0.0)
    tot = p.sum()
    if tot <= 0:
        return float("nan")
    cdf = np.cumsum(p) / tot - 0.5 * p / tot
    lo = float(np.interp(tail, cdf, x))
    hi = float(np.interp(1.0 - tail, cdf, x))
    return 0.5 * (abs(x_peak - lo) + abs(hi - x_peak))


@dataclass
class BayesGridMatcher:
    """Bayes grid matcher (module docstring). Recursive: ``initiate``, ``predict``, ``update``, ``to_fix``."""

    window_sigma: float = 4.0
    window_floor_m: float = 1.0
    resolution_m: float | None = None
    map_sigma: float = 0.0
    tail: float = 0.16
    spread_of: str = "likelihood"
    covariance: str = "posterior"
    prior_region_sigma: float = 2.0
    peak_ratio: float = 0.5
    min_peak_separation_m: float | None = None
    max_residual_sigma: float = 4.0
    min_variability: float = 0.5
    max_nodes: int = 1_000_000
    quantisation: float = 1.0
    max_refine: float = 4.0
    name: str = "bayes_grid"

    def __post_init__(self) -> None:
        if self.spread_of not in ("likelihood", "posterior"):
            raise ConfigError(f"bayes_grid 'spread_of': expected 'likelihood' or 'posterior', got {self.spread_of!r}")
        if self.covariance not in ("spread", "posterior"):
            raise ConfigError(f"bayes_grid 'covariance': expected 'spread' or 'posterior', got {self.covariance!r}")
        if not 0.0 < self.tail < 0.5:
            raise ConfigError(f"bayes_grid 'tail': expected 0 < tail < 0.5, got {self.tail!r}")
        for key in ("window_sigma", "prior_region_sigma", "max_residual_sigma"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"bayes_grid '{key}': expected > 0, got {getattr(self, key)!r}")

    # ------------------------------------------------------------------ recursion
    def initiate(self, prior: NavEstimate, rng: np.random.Generator | None = None) -> BayesGridState:
        """State from the prior navigation estimate (position and horizontal covariance)."""
        nav = prior.nav
        return BayesGridState(float(nav.t), float(nav.lat), float(nav.lon), float(nav.h), np.array(prior.cov_ne))

    def predict(self, state: BayesGridState, prior: NavEstimate) -> BayesGridState:
        """The propagated prior is the INS estimate (Storms' KF prediction, here done by the fuser)."""
        nav = prior.nav
        return BayesGridState(
            float(nav.t), float(nav.lat), float(nav.lon), float(nav.h), np.array(prior.cov_ne), state.fix
        )

    def update(self, state: BayesGridState, readings: FieldReadings, fmap: FieldMap) -> BayesGridState:
        """Posterior on the grid with the last reading; the new state carries the fix (or "no fix")."""
        if len(readings) == 0:
            fix = Fix.no_fix(state.t, "no reading", self.name)
        else:
            try:
                fix, extra = self._posterior_fix(state, readings, fmap)
            except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
                fix, extra = Fix.no_fix(float(readings.t[-1]), f"map lookup failed: {exc}", self.name), {}
            state = BayesGridState(state.t, state.lat, state.lon, state.h, state.cov_ne, fix, extra)
            return state
        return BayesGridState(state.t, state.lat, state.lon, state.h, state.cov_ne, fix)

    def to_fix(self, state: BayesGridState) -> Fix:
        """The last fix (a "no fix" before the first update)."""
        return state.fix if state.fix is not None else Fix.no_fix(state.t, "no update yet", self.name)

    # ------------------------------------------------------------------ the grid
    def _posterior_fix(
        self, state: BayesGridState, readings: FieldReadings, fmap: FieldMap
    ) -> tuple[Fix, dict[str, float]]:
        t = float(readings.t[-1])
        z = np.asarray(readings.value, float).reshape(len(readings), -1)[-1]
        ncomp = map_components(fmap)
        if z.size != ncomp:
            return Fix.no_fix(t, f"reading has {z.size} components, map has {ncomp}", self.name), {}
        if not np.all(np.isfinite(z)):
            return Fix.no_fix(t, "reading is NaN", self.name), {}
        cov = np.asarray(state.cov_ne, float)
        if not (np.all(np.isfinite(cov)) and np.isfinite(state.lat) and np.isfinite(state.lon)):
            return Fix.no_fix(t, "prior not finite", self.name), {}
        frame = make_frame(fmap, state.lat, state.lon)
        step0 = self.resolution_m or spacing_of(fmap, 0.5)
        half_n, half_e = sigma_window(cov, self.window_sigma, self.window_floor_m)
        native = frame.native(-half_n, half_n, -half_e, half_e) if self.resolution_m is None else None
        s2 = float(readings.sigma) ** 2 + self.map_sigma**2
        g_rms = native_gradient_rms(native)
        if native is not None and self.quantisation > 0 and np.isfinite(g_rms) and g_rms > 0:
            sp = min(float(native[0][1] - native[0][0]), float(native[1][1] - native[1][0]))
            fine = max(self.quantisation * np.sqrt(s2) / g_rms, sp / self.max_refine)
            if fine < 0.99 * sp:  # interpolate the map (Storms sec. 3.2) so the node error stays near the noise
                native, step0 = None, fine
        if native is None and self.resolution_m is None:  # no native local grid (geodetic map): interpolate
            step0 = min(step0, min(half_n, half_e) / 10.0)
        if native is not None and native[0].size >= 3 and native[1].size >= 3:
            n_ax, e_ax, v = native
            step = 0.5 * (float(n_ax[1] - n_ax[0]) + float(e_ax[1] - e_ax[0]))
            gn, ge = np.meshgrid(n_ax, e_ax, indexing="ij")
            m = v.reshape(gn.shape + (ncomp,))
        else:
            n_ax, e_ax, step = window_axes(half_n, half_e, step0, self.max_nodes)
            gn, ge = np.meshgrid(n_ax, e_ax, indexing="ij")
            m = frame.sample(gn, ge, state.h).reshape(gn.shape + (ncomp,))
        if np.isfinite(g_rms):  # value error of the nearest node: |grad|^2 step^2 / 12
            s2 = s2 + g_rms**2 * step**2 / 12.0
        loglik = -0.5 * np.sum((m - z) ** 2, axis=-1) / s2
        finite = np.isfinite(loglik)
        if not np.any(finite):
            return Fix.no_fix(t, "off the map: no map values in the prior window", self.name), {}
        k_c = np.unravel_index(int(np.argmin(gn**2 + ge**2)), gn.shape)
        centre = m[k_c]
        if np.all(np.isfinite(centre)):
            variability = feature_variability(m, centre)
        else:
            variability = 2.0 * float(np.sum(np.nan_to_num(np.nanvar(m.reshape(-1, ncomp), axis=0))))
        if variability < self.min_variability**2 * s2:
            return Fix.no_fix(
                t,
                f"flat map: feature variability {np.sqrt(variability):.3g} below {self.min_variability:g} x "
                f"reading sigma {np.sqrt(s2):.3g}",
                self.name,
            ), {}
        ci = np.linalg.inv(cov)
        d2 = ci[0, 0] * gn**2 + 2 * ci[0, 1] * gn * ge + ci[1, 1] * ge**2
        logprior = -0.5 * d2  # eq. 3.5 (normalisation cancels)
        loglik = np.where(finite, loglik, -np.inf)
        logpost = logprior + loglik
        kp = np.unravel_index(int(np.argmax(logpost)), logpost.shape)
        post = np.exp(logpost - logpost[kp])
        post /= post.sum()
        n_fix, e_fix = float(gn[kp]), float(ge[kp])
        # guard: residual at the peak
        res2 = float(np.sum((m[kp] - z) ** 2) / s2)
        if res2 > ncomp * self.max_residual_sigma**2:
            return Fix.no_fix(t, f"large residual: {np.sqrt(res2 / ncomp):.3g} sigma per component", self.name), {}
        # guard: several peaks inside the prior region
        sep = self.min_peak_separation_m if self.min_peak_separation_m is not None else 4.0 * step
        local_max = (post == ndimage.maximum_filter(post, size=3, mode="constant", cval=0.0)) & (
            post >= self.peak_ratio * post[kp]
        )
        inside = d2 <= self.prior_region_sigma**2
        far = (gn - n_fix) ** 2 + (ge - e_fix) ** 2 >= sep**2
        rivals = local_max & inside & far
        if np.any(rivals):
            ratio = float(post[rivals].max() / post[kp])
            return Fix.no_fix(
                t, f"ambiguous: {int(rivals.sum())} other peak(s) in the prior region (ratio {ratio:.2f})", self.name
            ), {"peaks": float(rivals.sum() + 1)}
        if self.covariance == "posterior":
            dn, de = gn - n_fix, ge - e_fix
            R = np.array(
                [[np.sum(post * dn * dn), np.sum(post * dn * de)], [np.sum(post * dn * de), np.sum(post * de * de)]]
            )
        else:
            src = post if self.spread_of == "posterior" else np.exp(loglik - loglik[kp])
            sig_n = _tail_sigma(src[:, kp[1]], n_ax, n_fix, self.tail)
            sig_e = _tail_sigma(src[kp[0], :], e_ax, e_fix, self.tail)
            R = np.diag([sig_n**2, sig_e**2])
        R = R + np.eye(2) * step**2 / 12.0
        if not np.all(np.isfinite(R)):
            return Fix.no_fix(t, "posterior spread not finite", self.name), {}
        lat, lon = frame.to_latlon(n_fix, e_fix)
        score = float(post[kp])
        return Fix(t, float(lat), float(lon), R, True, "", score, self.name), {"residual_sigma": np.sqrt(res2 / ncomp)}
