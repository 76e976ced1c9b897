"""Storms' Bayes grid matcher (Storms 2009, seed 004, sec. 2.3.2.4 and 3.4).

At each update:

1. Prior (eq. 3.5): the discrete bivariate Gaussian of the propagated mean and covariance (here the estimate handed
   to :meth:`BayesGridMatcher.predict`: the INS + UKF's, or Storms' own 2-D constant-velocity Kalman filter,
   :mod:`magnav_ins.aiding.fusion.cv_kf`) on the map grid nodes of a window of ``window_sigma`` prior sigmas.
2. Likelihood (eq. 3.6): ``L = exp(-sum_k (y_k - h_k(x))^2 / (2 s^2))`` over the 3 field components (or the
   scalar), ``s^2 = sigma_reading^2 + sigma_map(x)^2`` (log space). The map error ``sigma_map`` comes from
   :func:`~magnav_ins.aiding.matchers.map_error.resolve_map_error`: the ``map_sigma`` option (> 0), else the map's
   error layer at each node, else that module's stated default; ``map_sigma = 0`` states the map exact (a
   simulation whose readings are drawn from the map itself).
3. Posterior = prior x likelihood (eq. 2.19); its peak (MAP) is the position measurement (sec. 3.4.2.3).
4. R, the fix covariance. ``covariance`` says which rule:

   * ``"storms"`` (default; sec. 3.4.2.4): through the posterior peak, lay a line of grid points along north
     (Storms' X) and one along east (Y); evaluate the *likelihood* (eq. 3.6) alone on each line, normalise each to a
     pdf, find the points leaving ``tail`` (~16 %) in each tail and average their distances to that pdf's *mean*
     -> ``sigma_N``, ``sigma_E``; ``R = diag(sigma_N^2, sigma_E^2)``. The likelihood, not the posterior: the
     posterior contains the filter's own prior, so an R from it would be correlated with the filter and the prior
     counted twice (Storms' reason for the rule).
   * ``"posterior"``: the posterior's full second moment about its peak (the prior counted twice, as said; kept
     for comparison: on the Storms hallway it gives fix NEES ~3.4 where the likelihood rule gives ~1.9).
   * ``"spread"``: the 16 % tail points of the slices (of the likelihood, or with ``spread_of="posterior"`` of the
     posterior), their distances measured to the *peak* (this module's reading of sec. 3.4.2.4 before 2026-12-01).

   ``line_extent`` says how far the lines run: ``"window"`` (the whole prior window, as first implemented) or
   ``"lobe"`` (out to the likelihood's first minimum on each side of the peak: the fix's own lobe). Storms does not
   say; over the window a line through the peak also runs through the likelihood's other peaks on it, so with
   ``cover_rivals`` those are counted twice (in the line and again as rivals): ``"lobe"`` counts each once
   (own lobe spread + the rivals' second moment; ``tests/test_storms.py``, two wells of known share).
   ``fix_at``: ``"posterior"`` (Storms: the fix is the posterior peak) or ``"likelihood"`` (the prior picks the
   peak, the fix is the likelihood's own local maximum reached from it by steepest ascent): R describes the
   likelihood alone, so the fix it goes with is then the likelihood's too, not pulled towards the prior, whose
   information the filter adds itself.

   The grid quantisation ``step^2 / 12`` is added to each, except to Storms' rule with ``"lobe"`` lines when the
   likelihood holds the node error (below): ``s^2`` then has ``|grad|^2 step^2 / 12``, which widens the lobe by at
   least ``step^2 / 12`` in each direction, so it is in R once already. What R contains: the sensor noise and the map error
   (through the likelihood's ``s^2``), the spread of the likelihood along the two lines through the peak, and the
   node quantisation; not the map error's correlation between successive fixes (a fix every 1.5 s at 0.5 m/s
   reads the map 0.75 m further on).
Map resolution: where the RMS map gradient times the node spacing exceeds ``quantisation`` reading sigmas, the
window is resampled (bilinear) at a finer step (at most ``max_refine`` times finer), and the remaining node error
``|grad|^2 step^2 / 12`` is added to the likelihood variance.

Guards (ours, after Storms' sec. 4.3.3 suggestions; ``guards = false`` switches them off for his algorithm as
published): several separated posterior peaks inside the prior region (a second local maximum at least
``min_peak_separation_m`` away holding at least ``peak_ratio`` of the peak density, inside the
``prior_region_sigma`` ellipse) -> "no fix, ambiguous"; less than ``min_peak_mass`` of the posterior inside the
fix's own ``peak_mass_sigma`` ellipse (R does not describe the posterior: it is spread over other modes) -> "no
fix, ambiguous"; a reading residual at the peak above ``max_residual_sigma`` s per component (chi-square) -> "no
fix, large residual". Storms' own suggestions (sec. 4.3.3), each an option: ``max_jump_m`` ignores a peak more
than that many metres from the estimate ("residual monitoring ... so many meters away from the estimate"), and
``cover_rivals`` keeps the fix but widens R to cover the other peaks (R plus the peaks' second moment about the fix,
each weighted by its share of the peaks' density) instead of refusing it: with ``rivals_of = "posterior"`` the
posterior's other peaks in the prior region (those the ambiguity guard refuses), with ``"likelihood"`` the
likelihood's own peaks anywhere in the window holding at least ``peak_ratio`` of its maximum. The second is the one
that acts when the filter's prior is wrong and too sure of itself (Storms' filter through the turn without the turn
command): the prior then suppresses the true peak in the posterior, and only the likelihood still shows it.

Residual monitoring with a wider search (``research_residual_sigma``, off by default; Storms sec. 4.3.3 and 4.5.1
recommend "residual monitoring, likelihood thresholding"): a fix whose reading residual at the peak exceeds that many
sigmas per component is not where the vehicle is: the filter's prior is wrong and too sure of itself (Storms' filter
after a turn its model did not expect, or after a run of wrong peaks). The grid is searched again with the prior's
covariance scaled by ``research_factor^2`` (up to ``research_steps`` times; the guards on for these searches, so a
re-acquisition must be unambiguous) and the first fix whose residual passes is issued; if none, "no fix: large
residual". The filter then gets a fix far from its prior and moves to it.

Off the map (``off_map``): ``"impossible"`` (default) gives nodes without map values zero likelihood, so the
posterior is forced onto the mapped nodes even when the vehicle has left the map (the peak then sits on the map's
edge); ``"unknown"`` gives them the likelihood of the reading under the map's own field statistics
(:func:`~.map_error.off_map_loglik`: the field there is unknown), so leaving the map shows as posterior mass where
the map has no values: more than ``max_off_map_mass`` of it, or the peak there, gives "no fix: off the map", less
widens Storms' likelihood lines (R). Always: off the map, flat map (feature variability, Wang eq. 14), NaN reading -> "no fix"
with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

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
from .map_error import off_map_loglik, resolve_map_error

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
    """Average distance from ``x_peak`` of the points leaving ``tail`` in each tail of the 1-D ``pdf`` sampled at
    ``x`` (linear interpolation of the cumulative sum at cell centres); NaN for an empty pdf."""
    p = np.where(np.isfinite(pdf), pdf, 0.0)
    tot = p.sum()
    if tot <= 0:
        return float("nan")
    cdf = np.cumsum(p) / tot - 0.5 * p / tot
    lo = float(np.interp(tail, cdf, x))
    hi = float(np.interp(1.0 - tail, cdf, x))
    return 0.5 * (abs(x_peak - lo) + abs(hi - x_peak))


def own_lobe(line: FloatArray, k: int) -> slice:
    """The index range of the lobe of the 1-D ``line`` (values >= 0) that holds index ``k``: out to the nearest
    local minimum (or zero) on each side of ``k``, inclusive; the line's ends when there is none."""
    v = np.where(np.isfinite(line), line, 0.0)
    lo = k
    while lo > 0 and (lo == k or not (v[lo] <= 0.0 or (v[lo - 1] > v[lo] and v[lo + 1] >= v[lo]))):
        lo -= 1
    hi = k
    while hi < len(v) - 1 and (hi == k or not (v[hi] <= 0.0 or (v[hi + 1] > v[hi] and v[hi - 1] >= v[hi]))):
        hi += 1
    return slice(lo, hi + 1)


def climb(surface: FloatArray, start: tuple[int, ...]) -> tuple[int, int]:
    """The local maximum of the 2-D ``surface`` reached from index ``start`` by steepest ascent over the 8
    neighbours (NaN / -inf cells are never entered)."""
    i, j = int(start[0]), int(start[1])
    v = np.where(np.isfinite(surface), surface, -np.inf)
    ni, nj = v.shape
    while True:
        i0, i1, j0, j1 = max(i - 1, 0), min(i + 2, ni), max(j - 1, 0), min(j + 2, nj)
        block = v[i0:i1, j0:j1]
        k = np.unravel_index(int(np.argmax(block)), block.shape)
        bi, bj = i0 + int(k[0]), j0 + int(k[1])
        if block[k] <= v[i, j] or (bi, bj) == (i, j):
            return i, j
        i, j = bi, bj


def storms_sigma(pdf: FloatArray, x: FloatArray, tail: float = 0.16) -> float:
    """Storms' 1-sigma of an experimental pdf (sec. 3.4.2.4): the line of values ``pdf`` (any scale; normalised
    here) at the points ``x`` (m), the points leaving ``tail`` in each tail found, and their distances to the pdf's
    *mean* averaged. For a Gaussian this is its sigma when ``tail`` = 0.1587. NaN for an empty pdf."""
    p = np.where(np.isfinite(pdf), pdf, 0.0)
    tot = p.sum()
    if tot <= 0:
        return float("nan")
    mean = float(np.sum(p * x) / tot)
    return _tail_sigma(p, x, mean, tail)


#: the fix-covariance rules of :class:`BayesGridMatcher` (module docstring, step 4)
COVARIANCE_RULES = ("storms", "posterior", "spread")


@dataclass
class BayesGridMatcher:
    """Bayes grid matcher (module docstring). Recursive: ``initiate``, ``predict``, ``update``, ``to_fix``."""

    window_sigma: float = 4.0
    window_floor_m: float = 1.0
    resolution_m: float | None = None
    map_sigma: float | None = None
    map_correlation_m: float | None = None
    tail: float = 0.16
    spread_of: str = "likelihood"
    covariance: str = "storms"
    prior_region_sigma: float = 2.0
    peak_ratio: float = 0.5
    min_peak_separation_m: float | None = None
    max_residual_sigma: float = 4.0
    min_peak_mass: float = 0.5
    peak_mass_sigma: float = 3.0
    guards: bool = True
    cover_rivals: bool = False
    max_jump_m: float | None = None
    off_map: str = "impossible"
    max_off_map_mass: float = 0.5
    rivals_of: str = "posterior"
    line_extent: str = "window"
    fix_at: str = "posterior"
    research_residual_sigma: float | None = None
    research_factor: float = 4.0
    research_steps: int = 2
    min_variability: float = 0.5
    max_nodes: int = 1_000_000
    quantisation: float = 1.0
    max_refine: float = 4.0
    name: str = "bayes_grid"

    def __post_init__(self) -> None:
        if self.spread_of not in ("likelihood", "posterior"):
            raise ConfigError(f"bayes_grid 'spread_of': expected 'likelihood' or 'posterior', got {self.spread_of!r}")
        if self.rivals_of not in ("posterior", "likelihood"):
            raise ConfigError(f"bayes_grid 'rivals_of': expected 'posterior' or 'likelihood', got {self.rivals_of!r}")
        if self.research_residual_sigma is not None and not self.research_residual_sigma > 0:
            raise ConfigError(
                f"bayes_grid 'research_residual_sigma': expected > 0 or unset, got {self.research_residual_sigma!r}"
            )
        if not (self.research_factor > 1 and int(self.research_steps) >= 1):
            raise ConfigError(
                f"bayes_grid 'research_factor' / 'research_steps': expected > 1 / >= 1, got "
                f"{self.research_factor!r} / {self.research_steps!r}"
            )
        if self.fix_at not in ("posterior", "likelihood"):
            raise ConfigError(f"bayes_grid 'fix_at': expected 'posterior' or 'likelihood', got {self.fix_at!r}")
        if self.line_extent not in ("window", "lobe"):
            raise ConfigError(f"bayes_grid 'line_extent': expected 'window' or 'lobe', got {self.line_extent!r}")
        if self.off_map not in ("impossible", "unknown"):
            raise ConfigError(f"bayes_grid 'off_map': expected 'impossible' or 'unknown', got {self.off_map!r}")
        if self.covariance not in COVARIANCE_RULES:
            raise ConfigError(
                f"bayes_grid 'covariance': expected one of {', '.join(COVARIANCE_RULES)}, got {self.covariance!r}"
            )
        if self.map_sigma is not None and not (np.isfinite(self.map_sigma) and self.map_sigma >= 0):
            raise ConfigError(f"bayes_grid 'map_sigma': expected >= 0 (map unit) or unset, got {self.map_sigma!r}")
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
                if self.research_residual_sigma is not None:
                    fix, extra = self._research(state, readings, fmap, fix, extra)
            except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
                fix, extra = Fix.no_fix(float(readings.t[-1]), f"map lookup failed: {exc}", self.name), {}
            state = BayesGridState(state.t, state.lat, state.lon, state.h, state.cov_ne, fix, extra)
            return state
        return BayesGridState(state.t, state.lat, state.lon, state.h, state.cov_ne, fix)

    def to_fix(self, state: BayesGridState) -> Fix:
        """The last fix (a "no fix" before the first update)."""
        return state.fix if state.fix is not None else Fix.no_fix(state.t, "no update yet", self.name)

    def _research(
        self, state: BayesGridState, readings: FieldReadings, fmap: FieldMap, fix: Fix, extra: dict[str, float]
    ) -> tuple[Fix, dict[str, float]]:
        """Residual monitoring with a wider search (Storms sec. 4.3.3 / 4.5.1: "residual monitoring, likelihood
        thresholding"): a fix whose reading residual at the peak exceeds ``research_residual_sigma`` per component
        says the vehicle is not in the prior's region (the filter's prior is wrong and too sure: a turn its model
        did not expect). The grid is then searched again with the prior's covariance scaled by
        ``research_factor^2``, up to ``research_steps`` times, and the first fix whose residual passes is issued;
        if none passes, "no fix: large residual"."""
        lim = float(self.research_residual_sigma)  # type: ignore[arg-type]
        if not fix.available or extra.get("residual_sigma", 0.0) <= lim:
            return fix, extra
        res = extra.get("residual_sigma", float("nan"))
        strict = replace(self, guards=True, research_residual_sigma=None)  # a re-acquisition must be unambiguous
        for k in range(1, self.research_steps + 1):
            wide = BayesGridState(
                state.t, state.lat, state.lon, state.h, state.cov_ne * self.research_factor ** (2 * k), state.fix
            )
            f2, x2 = strict._posterior_fix(wide, readings, fmap)
            if f2.available and x2.get("residual_sigma", np.inf) <= lim:
                return f2, {**x2, "research": float(k)}
        return Fix.no_fix(
            float(readings.t[-1]), f"large residual: {res:.3g} sigma per component, none within {lim:g} in a "
            f"{self.research_factor ** self.research_steps:g}x wider search", self.name,
        ), extra  # fmt: skip

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
        # map_sigma = 0: the map is stated exact (a study whose readings are drawn from this very map)
        map_err = None if self.map_sigma == 0.0 else resolve_map_error(fmap, self.map_sigma, self.map_correlation_m)
        s2 = float(readings.sigma) ** 2
        if map_err is not None and map_err.source != "layer":  # uniform (option or default): known beforehand
            s2 = s2 + map_err.uniform_sigma**2
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
        if map_err is not None and map_err.source == "layer":  # the layer's sigma at every node of the window
            s2 = s2 + map_err.sigma_at(*frame.to_latlon(gn, ge)) ** 2
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
        s2_c = float(np.median(s2)) if np.ndim(s2) else float(s2)
        if variability < self.min_variability**2 * s2_c:
            return Fix.no_fix(
                t,
                f"flat map: feature variability {np.sqrt(variability):.3g} below {self.min_variability:g} x "
                f"reading sigma {np.sqrt(s2_c):.3g}",
                self.name,
            ), {}
        ci = np.linalg.inv(cov)
        d2 = ci[0, 0] * gn**2 + 2 * ci[0, 1] * gn * ge + ci[1, 1] * ge**2
        logprior = -0.5 * d2  # eq. 3.5 (normalisation cancels)
        off = ~finite
        if self.off_map == "unknown" and np.any(off):  # the field where the map has none: the map's statistics
            loglik = np.where(finite, loglik, off_map_loglik(z[None], fmap, float(np.median(s2))))
        else:
            loglik = np.where(finite, loglik, -np.inf)
        logpost = logprior + loglik
        kp = np.unravel_index(int(np.argmax(logpost)), logpost.shape)
        post = np.exp(logpost - logpost[kp])
        post /= post.sum()
        n_fix, e_fix = float(gn[kp]), float(ge[kp])
        if self.off_map == "unknown" and np.any(off):
            mass_off = float(post[off].sum())
            if off[kp] or mass_off > self.max_off_map_mass:
                return Fix.no_fix(
                    t,
                    f"off the map: {100 * mass_off:.0f} % of the posterior lies where the map has no values",
                    self.name,
                ), {"off_map_mass": mass_off}
        # guard: residual at the peak
        res2 = float(np.sum((m[kp] - z) ** 2) / (s2[kp] if np.ndim(s2) else s2))
        if self.guards and res2 > ncomp * self.max_residual_sigma**2:
            return Fix.no_fix(t, f"large residual: {np.sqrt(res2 / ncomp):.3g} sigma per component", self.name), {}
        # guard: several peaks inside the prior region
        sep = self.min_peak_separation_m if self.min_peak_separation_m is not None else 4.0 * step
        local_max = (post == ndimage.maximum_filter(post, size=3, mode="constant", cval=0.0)) & (
            post >= self.peak_ratio * post[kp]
        )
        inside = d2 <= self.prior_region_sigma**2
        far = (gn - n_fix) ** 2 + (ge - e_fix) ** 2 >= sep**2
        rivals = local_max & inside & far
        if self.max_jump_m is not None and np.hypot(n_fix, e_fix) > self.max_jump_m:  # Storms' residual monitoring
            return Fix.no_fix(
                t, f"large residual: the peak lies {np.hypot(n_fix, e_fix):.2f} m from the estimate (> "
                f"{self.max_jump_m:g} m)", self.name,
            ), {}  # fmt: skip
        if self.guards and not self.cover_rivals and np.any(rivals):
            ratio = float(post[rivals].max() / post[kp])
            return Fix.no_fix(
                t, f"ambiguous: {int(rivals.sum())} other peak(s) in the prior region (ratio {ratio:.2f})", self.name
            ), {"peaks": float(rivals.sum() + 1)}
        if self.fix_at == "likelihood":  # the prior picked the peak, the likelihood alone places the fix on it
            kp = climb(loglik, kp)
            n_fix, e_fix = float(gn[kp]), float(ge[kp])
            far = (gn - n_fix) ** 2 + (ge - e_fix) ** 2 >= sep**2
        if self.covariance == "storms":  # sec. 3.4.2.4: the likelihood alone on the lines through the peak
            lik = np.exp(loglik - loglik[kp])
            ln, le = lik[:, kp[1]], lik[kp[0], :]
            sn, se = (own_lobe(ln, kp[0]), own_lobe(le, kp[1])) if self.line_extent == "lobe" else (slice(None),) * 2
            sig_n = storms_sigma(ln[sn], n_ax[sn], self.tail)
            sig_e = storms_sigma(le[se], e_ax[se], self.tail)
            R = np.diag([sig_n**2, sig_e**2])
        elif self.covariance == "posterior":
            dn, de = gn - n_fix, ge - e_fix
            R = np.array(
                [[np.sum(post * dn * dn), np.sum(post * dn * de)], [np.sum(post * dn * de), np.sum(post * de * de)]]
            )
        else:
            src = post if self.spread_of == "posterior" else np.exp(loglik - loglik[kp])
            sig_n = _tail_sigma(src[:, kp[1]], n_ax, n_fix, self.tail)
            sig_e = _tail_sigma(src[kp[0], :], e_ax, e_fix, self.tail)
            R = np.diag([sig_n**2, sig_e**2])
        node_in_lik = np.isfinite(g_rms) and g_rms > 0
        if not (self.line_extent == "lobe" and self.covariance == "storms" and node_in_lik):
            R = R + np.eye(2) * step**2 / 12.0  # (the lobe of a likelihood holding the node error has it already)
        if self.cover_rivals and self.rivals_of == "likelihood":  # the likelihood's own peaks in the window
            lk = np.exp(loglik - np.max(loglik))
            lmax = (lk == ndimage.maximum_filter(lk, size=3, mode="constant", cval=0.0)) & (lk >= self.peak_ratio)
            rivals = lmax & far
            dens, dens_fix = lk[rivals], float(lk[kp])
        else:
            dens, dens_fix = post[rivals], float(post[kp])
        if self.cover_rivals and np.any(rivals):  # R covers the other peaks: the modes' second moment about the fix
            w = dens / (dens_fix + dens.sum())
            d = np.column_stack([gn[rivals] - n_fix, ge[rivals] - e_fix])
            R = R + (d * w[:, None]).T @ d
        if not np.all(np.isfinite(R)):
            return Fix.no_fix(t, "posterior spread not finite", self.name), {}
        # the posterior mass the fix's own covariance accounts for: inside its k-sigma ellipse about the peak
        dn, de = gn - n_fix, ge - e_fix
        ri = np.linalg.inv(R)
        own = ri[0, 0] * dn**2 + 2 * ri[0, 1] * dn * de + ri[1, 1] * de**2 <= self.peak_mass_sigma**2
        mass = float(post[own].sum())
        extra = {"residual_sigma": np.sqrt(res2 / ncomp), "peak_mass": mass}
        if self.guards and mass < self.min_peak_mass:
            return Fix.no_fix(
                t,
                f"ambiguous: the fix's {self.peak_mass_sigma:g}-sigma ellipse holds {mass:.2f} of the posterior "
                f"(< {self.min_peak_mass:g})",
                self.name,
            ), extra
        lat, lon = frame.to_latlon(n_fix, e_fix)
        score = float(post[kp])
        return Fix(t, float(lat), float(lon), R, True, "", score, self.name), extra
