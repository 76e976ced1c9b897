"""Likelihood map matchers: maximum likelihood (ML), maximum likelihood ratio (MLR), aggregate bin likelihood (ABL).

Sources: Shockley 2012 (seed 003) sec. 4.3.1-4.3.3 and measurement composition sec. 4.4-4.6; Raquet, Shockley &
Fisher (seed 000) eq. 1. The Gaussian likelihood of the readings ``z_k`` against the map ``m`` at a hypothesised
position is (003 eq. 2.49-2.52, 000 eq. 1, beta dropped, log space)::

    log L(p) = -1/(2 s^2) sum_k || z_k - m(x_k + p) ||^2 ,   s^2 = sigma_reading^2 + sigma_map^2

where ``x_k`` are the INS-indicated positions of the readings relative to the last one and ``p`` is the
hypothesised position of the last reading: a section of readings is slid rigidly over the map (the INS is trusted
over the short section, 003 sec. 4.5). Options: ``demean`` (subtract the section mean from readings and map
profile, removes a constant bias, 003 sec. 4.6) and ``difference`` (successive differences, s^2 -> 2 s^2).

* ML picks the largest likelihood.
* MLR divides it by the largest likelihood at least ``min_distance_m`` away and issues a fix only when the ratio
  exceeds ``ratio_threshold`` (003 sec. 4.3.2: 20 m and 2). Shockley compares every reading with the whole map;
  inside a search window that holds no candidate ``min_distance_m`` from the peak (a prior 1-sigma of a few metres
  gives a window of +-5 m) the ratio is infinite and MLR issues exactly the ML fixes: use ``search_window=False``
  (or a prior wide enough) for the ratio test to act.
* ABL normalises the likelihoods to sum to one, requires a normalised peak above ``peak_threshold`` and chooses
  the bin holding the largest normalised mass (003 sec. 4.3.3; the thesis gives no values, ours are defaults to
  tune). On a road map the bin is ``bin_size_m`` long and slides along the map's sequence of points (one road, one
  travel direction; the fix is the bin's point nearest its likelihood-weighted centre); on a grid it is a square
  of side ``bin_size_m`` centred on each node.

The scan runs over a search window around the prior (the thesis' suggested improvement; ``search_window=True``,
half-width ``window_sigma`` times the prior 1-sigma, widened up to ``window_growth`` times by 2 while the
likelihood's peak region reaches its edge) or over the whole grid map (``search_window=False``).

Level offset (issue 13; ``level_sigma``). Readings and map may differ by a constant level ``b`` over the section
(the map's levelling, diurnal variation, the platform's own field: Osborne's tie lines sit 17-30 nT below its flight
lines), which is not a per-node map error. It is marginalised with the prior ``b ~ N(0, sigma_b^2)``,
``sigma_b`` the map's level prior (:func:`~.map_error.resolve_level`: ``metadata["level_sigma"]``, else 10 % of the
map's std; the option overrides it, 0 = absolute levels as in the thesis): by Sherman-Morrison the scan's
``r' (s^2 I + sigma_b^2 1 1')^-1 r`` is ``|r - gamma mean(r)|^2 / s^2`` with ``gamma = 1 - sqrt(s^2 / (s^2 + K
sigma_b^2))`` (:func:`~.map_error.level_fraction`), so the scan removes that fraction of the section mean from
readings and map profile (``demean`` is ``gamma = 1``, a diffuse level; with ``demean`` or ``difference`` there is
no level term, nothing is counted twice); the honest covariance below has ``sigma_b^2 1 1'`` in the section
covariance and ``T = I - gamma / K 1 1'`` as the scan's transform. A single reading gets ``sigma_b^2`` as variance.

What the fix covariance contains (issue 13; :mod:`.map_error`). The scan's likelihood uses the variance
``sigma_reading^2 + sigma_map^2`` (the map's error layer at the section, or ``map_sigma``, or the stated default)
plus the node error ``|grad|^2 step^2 / 12``, as if the readings were independent. With ``map_gradient_error_m``
``c`` (m, 0 by default) the map error at each reading is ``sqrt(sigma_map^2 + (c |grad m|)^2)``: a map gridded from
other or fewer lines than the field puts its features a few metres off, an error that follows the gradient (the SITL's
world against ``builtin:osborne-magnetic``: :mod:`magnav_ins.mavlink.sitl_flight`); in the scan's variance with the
section's mean ``|grad|^2`` at the INS positions, in the honest covariance with the gradient at the fix. They are not: the map error is
correlated over its correlation length, and the INS track the section is slid along drifts. So before its
moments are taken the surface is divided by a temperature: the sandwich factor (White 1982) of the section's full
residual covariance ``sigma_s^2 I + D C D + node error + sigma_b^2 1 1' + G P_drift G'`` (map error correlation ``C``, INS drift
over the section from the growth of the window's covariances, :func:`ins_drift_rate`) against the scan's
diagonal one, times the section's misfit chi-square per degree of freedom when that exceeds its 99 % quantile (the
residuals at the fix are larger than the model says), times ``K / new readings`` when the window shares readings
with the previous fix's window (``count_overlap``: each reading's evidence is issued once). The fix covariance is
then the second moment of the tempered likelihood about the fix (it covers every mode it holds) plus the grid
quantisation ``step^2/12`` and ``min_fix_sigma_m^2`` (0 by default; the old knob for what the likelihood cannot
see). ``honest=False`` skips the temperature (the thesis' likelihood).

Off the map (``off_map = "unknown"``; the default ``"impossible"`` leaves candidates without map values out, so
near the map's edge the best candidate is on the edge even when the vehicle has left the map): every scanned node
without map values holds the hypothesis "the field here is unknown", with the likelihood of the section under the
map's own field statistics (:func:`~.map_error.off_map_loglik`); when those nodes hold more than
``max_off_map_mass`` of the (untempered) likelihood, "no fix: off the map".

"No fix" (with the reason) for: NaN readings, off the map, a flat map (feature variability, Wang eq. 14, below
``min_variability`` times the sensor sigma), an ambiguous likelihood (its 99.9 % region falls into several parts and
those other than the best one's hold more than ``ambiguity_mass``; the reason gives the mass and the distance), a
likelihood whose peak region reaches scanned positions without map values ("map edge": cut off by the map's edge,
its peak pushed inwards and its spread too small; a wider window cannot help; with ``edge_fix`` the likelihood times
the prior is used when that stays off the map's edge), a likelihood that still reaches the edge of the widened search window (with ``edge_fix``: only when even the
likelihood times the prior does, or it holds no information; else the fix in the directions it does hold,
:meth:`LikelihoodMatcher.prior_fix`), a likelihood spread wider than
``max_fix_sigma_m``, an MLR ratio or ABL peak below threshold.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from ...core.errors import ConfigError
from ...core.protocols import FieldMap, MatchWindow
from ...core.types import EDGE_REASON, Fix
from ._kernels import grid_far_max, grid_moments, grid_scan1, grid_variability, section_loglik
from ._local import (
    MapFrame,
    WorkFrame,
    feature_variability,
    make_frame,
    map_components,
    moments_about,
    native_gradient_rms,
    sigma_window,
    spacing_of,
    window_axes,
)
from .map_error import (
    LevelModel,
    MapErrorModel,
    drift_covariance,
    level_fraction,
    misfit_factor,
    off_map_loglik,
    resolve_level,
    resolve_map_error,
    section_covariance,
    section_transform,
    temperature_and_topup,
    whitened_misfit,
)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Surface:
    """A log-likelihood surface over candidate positions (north/east metres in ``frame``).

    ``logl`` (M,) with ``-inf`` where the map is off. For a grid (``shape = (ni, nj)``), ``n`` and ``e`` are the
    grid's axes (ni,), (nj,) and ``logl`` is the flattened (ni, nj) surface; for scattered candidates
    (``shape = None``, road maps) ``n``, ``e`` (M,) are the candidate positions. ``step`` the grid spacing m;
    ``variability`` the map feature variability (unit^2) of the window; ``sigma2`` the likelihood variance used
    (unit^2); ``half`` the window half-widths (m). Road maps also give each candidate its position ``along`` the
    map's sequence of points (m; segments offset far apart so no bin spans two roads) and its travel direction
    ``lane`` (0 forward, 1 reversed): ABL's bins slide along the map's sequence of points (003 sec. 4.3.3)."""

    frame: WorkFrame
    logl: FloatArray
    n: FloatArray
    e: FloatArray
    shape: tuple[int, int] | None
    step: float
    variability: float
    sigma2: float
    half: tuple[float, float] = (np.inf, np.inf)
    k_max: int = -1
    along: FloatArray | None = None
    lane: NDArray[np.int64] | None = None
    section: Section | None = None
    grow: float = 1.0
    off_loglik: float = float("nan")
    prior_cov: FloatArray | None = None  # (2, 2) m^2, the INS covariance at the last reading (the issuing rule)


#: the "no fix" reason when the likelihood's peak region reaches scanned nodes without map values (the map's edge)
MAP_EDGE_REASON = (
    "map edge: the likelihood's peak region reaches positions without map values, so it is cut off there (its "
    "peak and spread are not the readings')"
)


@dataclass(frozen=True)
class Section:
    """The section a surface was scanned with, for the honest covariance (:meth:`LikelihoodMatcher.decide`):
    INS positions ``dn``, ``de`` (K,) m relative to the last reading in the surface's frame, readings ``z``
    (K, c), the height of the last reading ``h_last`` (m or None), the sensor 1-sigma ``sigma_sensor`` and the scan's
    per-reading variance before node error and differencing ``s2_base`` (sensor + mean map error, unit^2), and
    where the map error came from (``error``)."""

    dn: FloatArray
    de: FloatArray
    z: FloatArray
    h_last: float | None
    sigma_sensor: float
    s2_base: float
    error: MapErrorModel
    t: FloatArray | None = None
    drift_mps: FloatArray | None = None
    tau: FloatArray | None = None
    level: LevelModel | None = None
    level_frac: float = 0.0

    @property
    def level_var(self) -> float:
        """Variance (unit^2) of the section's constant level offset (0 without the level term)."""
        return 0.0 if self.level is None else float(self.level.sigma) ** 2


@dataclass
class LikelihoodMatcher:
    """ML / MLR / ABL matcher over a :class:`~magnav_ins.core.protocols.FieldMap` (see the module docstring).

    Parameters (SI; field values in the map's unit): ``method`` "ml" | "mlr" | "abl"; ``ratio_threshold`` and
    ``min_distance_m`` (MLR); ``bin_size_m`` and ``peak_threshold`` (ABL); ``demean``, ``difference`` (section
    composition); ``search_window`` and ``window_sigma`` (search window = ``window_sigma`` prior sigmas, at least
    ``window_floor_m`` and ``window_floor_cells`` map cells: a window narrower than a cell holds too few nodes for
    the flat-map test and for the likelihood's peak, which is never much narrower than a cell of a smooth map, to
    fit in it); ``resolution_m`` scan step (default: the map spacing); ``map_sigma`` map error 1-sigma overriding the map's error layer (0 = from the map: its layer, else the default of :mod:`.map_error`); ``distance_step_m`` re-samples the section every that many metres of
    INS-travelled distance before matching (Shockley's distance-sampled readings; ``None`` = as recorded); ``quantisation``: with the default resolution the scan step is refined (by
    bilinear interpolation) until the RMS map gradient times the step is at most this many reading sigmas, and the
    remaining node error ``|grad|^2 step^2 / 12`` is added to the likelihood variance (0 = native grid only);
    ``min_variability`` flat-map cut-off in units of s; ``max_fix_sigma_m`` largest accepted fix 1-sigma (default
    a quarter of the window half-width); ``min_fix_sigma_m`` a 1-sigma (m) added in quadrature to the fix
    covariance for what the likelihood cannot see: map registration and resolution errors, and the shape error of
    the INS-indicated track over the section (with real readings against a gridded survey the likelihood curvature
    alone gave fix sigmas under 1 m for fixes 200-400 m off; 0 = none); ``max_nodes`` cap on scanned nodes;
    ``map_correlation_m`` overrides the map's error correlation length (m); ``honest`` applies the temperature;
    ``ambiguity_mass`` (0.05; 1 = off); ``count_overlap``; ``track_error`` (INS drift in the section covariance);
    ``window_growth`` (widenings of the search window); ``edge_fix`` (on by default since 2026-12) and ``edge_fix_sigma_m`` (m): when the
    likelihood still reaches the edge of the widest window, the fix it holds with the prior (:meth:`prior_fix`)
    rather than none; ``off_map`` "impossible" | "unknown" and
    ``max_off_map_mass``; ``level_sigma`` the level offset's prior 1-sigma (None = the map's, 0 = none);
    ``map_gradient_error_m`` the map error per unit field gradient (m; 0 = none) (module docstring). A window whose
    INS track is shorter than a map cell (a hovering or landing vehicle) never reaches the matcher
    (:class:`~magnav_ins.pipeline.Pipeline`'s ``min_section_m``). The module docstring says what the covariance contains.

    The matcher remembers the time of the last reading of its last issued fix (``count_overlap``): one instance
    serves one stream of windows (a window whose last reading is not newer starts a new stream)."""

    method: str = "ml"
    ratio_threshold: float = 2.0
    min_distance_m: float = 20.0
    bin_size_m: float = 5.0
    peak_threshold: float = 0.0
    demean: bool = False
    difference: bool = False
    search_window: bool = True
    window_sigma: float = 4.0
    window_floor_m: float = 5.0
    window_floor_cells: float = 0.0
    resolution_m: float | None = None
    map_sigma: float = 0.0
    min_variability: float = 1.0
    max_fix_sigma_m: float | None = None
    min_fix_sigma_m: float = 0.0
    max_nodes: int = 2_000_000
    quantisation: float = 1.0
    distance_step_m: float | None = None
    both_directions: bool = True
    track_sigma_m: float = 1.0
    map_correlation_m: float | None = None
    honest: bool = True
    ambiguity_mass: float = 0.05
    count_overlap: bool = True
    track_error: bool = True
    window_growth: int = 2
    edge_fix: bool = True
    edge_fix_sigma_m: float = 10_000.0
    off_map: str = "impossible"
    max_off_map_mass: float = 0.5
    level_sigma: float | None = None
    map_gradient_error_m: float = 0.0
    name: str = ""
    _last_fix_t: float = field(default=-np.inf, init=False, repr=False, compare=False)

    METHODS: ClassVar[tuple[str, ...]] = ("ml", "mlr", "abl")

    def __post_init__(self) -> None:
        if self.method not in self.METHODS:
            raise ConfigError(f"likelihood matcher 'method': expected one of {self.METHODS}, got {self.method!r}")
        for key in ("ratio_threshold", "window_sigma", "bin_size_m"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"likelihood matcher '{key}': expected > 0, got {getattr(self, key)!r}")
        if (
            min(
                self.min_distance_m,
                self.map_sigma,
                self.min_variability,
                self.peak_threshold,
                self.min_fix_sigma_m,
                self.window_floor_cells,
                self.map_gradient_error_m,
            )
            < 0
        ):
            raise ConfigError(
                "likelihood matcher: min_distance_m, map_sigma, min_variability, peak_threshold, min_fix_sigma_m, "
                "window_floor_cells, map_gradient_error_m >= 0"
            )
        if not self.edge_fix_sigma_m > 0:
            raise ConfigError(f"likelihood matcher 'edge_fix_sigma_m': expected > 0, got {self.edge_fix_sigma_m!r}")
        if self.level_sigma is not None and not self.level_sigma >= 0:
            raise ConfigError(f"likelihood matcher 'level_sigma': expected >= 0 or None, got {self.level_sigma!r}")
        if self.off_map not in ("impossible", "unknown"):
            raise ConfigError(f"likelihood matcher 'off_map': expected 'impossible' or 'unknown', got {self.off_map!r}")
        if not self.name:
            self.name = self.method

    # ------------------------------------------------------------------ surface
    def surface(self, window: MatchWindow, fmap: FieldMap, grow: float = 1.0) -> Surface | str:
        """The log-likelihood surface for ``window`` on ``fmap``, or the reason there is none; ``grow`` widens the
        search window by that factor."""
        rd = window.readings
        z = np.asarray(rd.value, dtype=float)
        ncomp = map_components(fmap)
        z = z.reshape(len(z), -1)
        if z.shape[1] != ncomp:
            return f"reading has {z.shape[1]} components, map has {ncomp}"
        good = np.all(np.isfinite(z), axis=1) & np.isfinite(window.lat) & np.isfinite(window.lon)
        if not np.any(good):
            return "no finite readings (NaN)"
        z = z[good]
        lat, lon = np.asarray(window.lat)[good], np.asarray(window.lon)[good]
        h = np.asarray(window.h, dtype=float)[good]
        h_last = float(h[-1]) if np.isfinite(h[-1]) else None
        frame = make_frame(fmap, float(lat[-1]), float(lon[-1]))
        dn, de = frame.to_ne(lat, lon)
        if self.distance_step_m is not None and len(z) > 1:
            dn, de, z = distance_sample(dn, de, z, self.distance_step_m)
        step0 = self.resolution_m if self.resolution_m else spacing_of(fmap, 1.0)
        cov = np.asarray(window.cov_ne, dtype=float)
        cov_last = cov[-1] if cov.ndim == 3 else cov
        if self.search_window:
            floor = max(self.window_floor_m, self.window_floor_cells * spacing_of(fmap, 0.0))
            half_n, half_e = sigma_window(cov_last, self.window_sigma * grow, floor * grow)
            if not np.isfinite(half_n):
                return "prior covariance not finite"
        else:
            extent = (np.inf, np.inf) if _is_track(fmap) else _map_half_extent(fmap, frame)
            if extent is None:
                return "search_window=False needs a grid map with known extent"
            half_n, half_e = extent
        nz = len(z)
        err = resolve_map_error(fmap, self.map_sigma, self.map_correlation_m)
        sm = err.sigma_at(lat, lon)
        if self.map_gradient_error_m > 0:  # the map error that follows the field's gradient (module docstring)
            sm = self._gradient_error(sm, _map_gradient2(fmap, lat, lon))
        s2_base = float(rd.sigma) ** 2 + float(np.mean(sm**2))  # sensor + map error variance (map_error.py)
        t_sec = np.asarray(rd.t, dtype=float)[good]
        drift = ins_drift_rate(t_sec, cov[good] if cov.ndim == 3 else None) if self.track_error else np.zeros(2)
        tau = _section_times(t_sec, dn, de) if self.track_error else None
        # the level offset (module docstring): none when the section is differenced (it cancels) or demeaned
        lvl = None if ((self.difference and nz > 1) or self.demean) else resolve_level(fmap, self.level_sigma)
        lv = 0.0 if lvl is None else float(lvl.sigma) ** 2
        sec = Section(dn, de, z, h_last, float(rd.sigma), s2_base, err, t_sec, drift, tau, lvl)
        if _is_track(fmap):
            frac = 1.0 if self.demean else level_fraction(lv, s2_base, nz)
            out = self._track_surface(fmap, frame, z, dn, de, half_n, half_e, s2_base, frac)
            return out if isinstance(out, str) else replace(out, section=replace(sec, level_frac=frac))
        s2 = s2_base
        native = frame.native(-half_n, half_n, -half_e, half_e) if self.resolution_m is None else None
        g_rms = _gradient_rms(native, fmap, window)
        if native is not None and self.quantisation > 0 and np.isfinite(g_rms) and g_rms > 0:
            fine = self.quantisation * np.sqrt(s2) / g_rms  # scan step keeping the node error below the noise
            sp = [float(a[1] - a[0]) for a in native[:2] if a.size > 1]
            if sp and fine < 0.99 * min(sp):
                native, step0 = None, fine
        if native is None and self.resolution_m is None:  # no native local grid (geodetic map): interpolate
            options = [step0, min(half_n, half_e) / 10.0]
            if self.quantisation > 0 and np.isfinite(g_rms) and g_rms > 0:
                options.append(self.quantisation * np.sqrt(s2) / g_rms)
            step0 = min(options)
        if native is not None:
            n_ax, e_ax, v_last = native
            stride = int(np.ceil(np.sqrt(n_ax.size * e_ax.size * nz / self.max_nodes)))
            if stride > 1:
                n_ax, e_ax, v_last = n_ax[::stride], e_ax[::stride], v_last[::stride, ::stride]
            steps = [float(a[1] - a[0]) for a in (n_ax, e_ax) if a.size > 1]
            step = float(np.mean(steps)) if steps else step0
            v_last = np.ascontiguousarray(v_last, dtype=float)
            if np.isfinite(g_rms):  # value error of the nearest node: |grad|^2 step^2 / 12
                s2 = s2 + g_rms**2 * step**2 / 12.0
            ic, jc = int(np.argmin(np.abs(n_ax))), int(np.argmin(np.abs(e_ax)))
            if nz == 1 and not (self.demean or self.difference):  # the fast path: one compiled pass
                s2 = s2 + lv  # one reading: its level offset is more variance
                l2, kmax, variability = grid_scan1(v_last, np.ascontiguousarray(z[0]), s2, ic, jc)
                return Surface(
                    frame, l2.ravel(), n_ax, e_ax, l2.shape, step, float(variability), s2, (half_n, half_e), int(kmax),
                    section=sec,
                )  # fmt: skip
            variability = float(grid_variability(v_last, ic, jc))
            gn, ge = np.meshgrid(n_ax, e_ax, indexing="ij")
            m_last = v_last.reshape(1, gn.size, ncomp)
            if nz > 1:
                m_prev = frame.sample(dn[:-1, None, None] + gn[None], de[:-1, None, None] + ge[None], h_last)
                m = np.concatenate([m_prev.reshape(nz - 1, gn.size, ncomp), m_last], axis=0)
            else:
                m = m_last
        else:
            n_ax, e_ax, step = window_axes(half_n, half_e, step0, max(self.max_nodes // max(nz, 1), 9))
            grid = _local_grid(fmap, frame)
            if grid is not None:  # compiled section scan with bilinear reads on the local grid
                if np.isfinite(g_rms):
                    s2 = s2 + g_rms**2 * step**2 / 12.0
                v3, y0, dy, x0, dx = grid
                pos = np.column_stack([dn + frame.n0, de + frame.e0])  # type: ignore[union-attr]
                s2r = 2.0 * s2 if (self.difference and nz > 1) else s2
                frac = 1.0 if self.demean else level_fraction(lv, s2, nz)
                if nz == 1:
                    s2r = s2r + lv
                l2 = section_loglik(
                    v3, y0, dy, x0, dx, pos, np.ascontiguousarray(z), n_ax, e_ax, s2r, frac, self.difference
                )
                last = frame.sample(*np.meshgrid(n_ax, e_ax, indexing="ij"), h_last)
                last = np.ascontiguousarray(last.reshape(n_ax.size, e_ax.size, ncomp))
                ic, jc = int(np.argmin(np.abs(n_ax))), int(np.argmin(np.abs(e_ax)))
                variability = float(grid_variability(last, ic, jc))
                return Surface(
                    frame, l2.ravel(), n_ax, e_ax, l2.shape, step, variability, s2r, (half_n, half_e),
                    section=replace(sec, level_frac=frac),
                )  # fmt: skip
            gn, ge = np.meshgrid(n_ax, e_ax, indexing="ij")
            m = frame.sample(dn[:, None, None] + gn[None], de[:, None, None] + ge[None], h_last)
            m = m.reshape(nz, gn.size, ncomp)
            if np.isfinite(g_rms):  # value error of the nearest node: |grad|^2 step^2 / 12
                s2 = s2 + g_rms**2 * step**2 / 12.0
            ic, jc = int(np.argmin(np.abs(n_ax))), int(np.argmin(np.abs(e_ax)))
            variability = float(grid_variability(np.ascontiguousarray(m[-1].reshape(gn.shape + (ncomp,))), ic, jc))
        frac = 1.0 if self.demean else level_fraction(lv, s2, nz)
        if nz == 1:
            s2 = s2 + lv
        zz, mm = z[:, None, :], m
        if self.difference and len(z) > 1:
            zz, mm = np.diff(zz, axis=0), np.diff(mm, axis=0)
            s2 = 2.0 * s2
        if frac > 0 and len(zz) > 1:
            zz = zz - frac * zz.mean(axis=0, keepdims=True)
            mm = mm - frac * mm.mean(axis=0, keepdims=True)
        logl = -0.5 * np.sum((zz - mm) ** 2, axis=(0, 2)) / s2
        logl = np.where(np.isfinite(logl), logl, -np.inf)
        sec = replace(sec, level_frac=frac)
        return Surface(frame, logl, n_ax, e_ax, gn.shape, step, variability, s2, (half_n, half_e), section=sec)

    def _track_surface(
        self,
        fmap: FieldMap,
        frame: WorkFrame,
        z: FloatArray,
        dn: FloatArray,
        de: FloatArray,
        half_n: float,
        half_e: float,
        s2_base: float,
        level_frac: float = 0.0,
    ) -> Surface | str:
        """Likelihood at the points of a road map (Shockley 003 sec. 4.3-4.5): the section of readings is slid
        along the road; reading k sits ``d_k`` metres (INS-travelled distance to the last reading) before the
        candidate point, on the same segment (both travel directions when ``both_directions``)."""
        tn, te = frame.to_ne(fmap.lat, fmap.lon)  # type: ignore[attr-defined]
        sel = np.flatnonzero((np.abs(tn) <= half_n) & (np.abs(te) <= half_e))
        if sel.size == 0:
            return "off the map: no road points in the search window"
        vals = np.asarray(fmap.values, float).reshape(len(tn), -1)  # type: ignore[attr-defined]
        seg_run = np.cumsum(np.r_[True, np.diff(fmap.segment_id) != 0]) - 1  # type: ignore[attr-defined]
        s_at = np.asarray(fmap.along_track_m, float)  # type: ignore[attr-defined]
        big = 10.0 * (float(np.max(s_at)) + 1.0)
        s_glob = s_at + seg_run * big
        step_d = np.hypot(np.diff(dn), np.diff(de))
        d_back = np.concatenate([np.cumsum(step_d[::-1])[::-1], [0.0]])  # distance from reading k to the last
        dirs = (1.0, -1.0) if self.both_directions else (1.0,)
        nz = len(z)
        ms = []
        for sgn in dirs:
            target = s_glob[sel][None, :] - sgn * d_back[:, None]  # (nz, M)
            run = seg_run[sel][None, :]
            lo = np.clip(np.searchsorted(s_glob, target, "right") - 1, 0, len(s_glob) - 1)
            hi = np.clip(lo + 1, 0, len(s_glob) - 1)
            ok = (seg_run[lo] == run) & (seg_run[hi] == run) & (target >= s_glob[lo]) & (target <= s_glob[hi])
            span = np.where(hi > lo, s_glob[hi] - s_glob[lo], 1.0)
            f = np.clip((target - s_glob[lo]) / span, 0.0, 1.0)[..., None]
            m = (1.0 - f) * vals[lo] + f * vals[hi]
            m[~ok] = np.nan
            ms.append(m)
        m = np.concatenate(ms, axis=1)  # (nz, M * ndirs, c)
        cn = np.tile(tn[sel], len(dirs))
        ce = np.tile(te[sel], len(dirs))
        s2 = s2_base
        k0 = int(np.argmin(tn[sel] ** 2 + te[sel] ** 2))
        center = vals[sel][k0]
        variability = feature_variability(vals[sel], center) if np.all(np.isfinite(center)) else 0.0
        zz, mm = z[:, None, :], m
        if self.difference and nz > 1:
            zz, mm = np.diff(zz, axis=0), np.diff(mm, axis=0)
            s2 = 2.0 * s2
        if level_frac > 0 and len(zz) > 1:
            zz = zz - level_frac * zz.mean(axis=0, keepdims=True)
            mm = mm - level_frac * mm.mean(axis=0, keepdims=True)
        logl = -0.5 * np.sum((zz - mm) ** 2, axis=(0, 2)) / s2
        logl = np.where(np.isfinite(logl), logl, -np.inf)
        step = float(np.median(np.diff(s_at)[np.diff(seg_run) == 0])) if len(s_at) > 1 else 1.0
        along = np.tile(s_glob[sel], len(dirs))
        lane = np.repeat(np.arange(len(dirs), dtype=np.int64), sel.size)
        return Surface(frame, logl, cn, ce, None, step, variability, s2, (half_n, half_e), -1, along, lane)

    # ------------------------------------------------------------------ decision
    def match(self, window: MatchWindow, fmap: FieldMap) -> Fix:
        """A :class:`Fix` at the time of the window's last reading, or a "no fix" with the reason."""
        t = float(window.readings.t[-1]) if len(window.readings) else float("nan")
        cov_w = np.asarray(window.cov_ne, dtype=float)
        prior_cov = cov_w[-1] if cov_w.ndim == 3 else cov_w
        try:
            grow = 1.0
            for _ in range(self.window_growth + 1):  # widen the window while the likelihood reaches its edge
                surf = self.surface(window, fmap, grow)
                if isinstance(surf, str):
                    return Fix.no_fix(t, surf, self.name)
                surf = replace(surf, grow=grow, prior_cov=prior_cov)
                if self.off_map == "unknown" and surf.section is not None:
                    off = off_map_loglik(surf.section.z, fmap, surf.section.s2_base)
                    surf = replace(surf, off_loglik=off)
                fix = self.decide(surf, t)
                if fix.reason.startswith(MAP_EDGE_REASON):
                    break  # a wider window cannot help; the prior may still keep the fix off the map's edge
                if not fix.reason.startswith(EDGE_REASON):
                    return fix
                grow *= 2.0
            if self.edge_fix:
                partial = self.prior_fix(surf, t, prior_cov)
                if partial is not None:
                    return partial
            return fix
        except (ValueError, FloatingPointError) as exc:  # data problems never escape as exceptions
            return Fix.no_fix(t, f"map lookup failed: {exc}", self.name)

    def decide(self, surf: Surface, t: float) -> Fix:
        """Apply ML / MLR / ABL to a surface, with the honest temperature and the ambiguity test (class
        docstring)."""
        logl = surf.logl
        k = surf.k_max if surf.k_max >= 0 else int(np.argmax(logl))
        if not np.isfinite(logl[k]):
            return Fix.no_fix(t, "off the map: no map values in the search window", self.name)
        s2_flat = _flat_sigma2(surf, self.difference)
        if surf.variability < (self.min_variability**2) * s2_flat:
            return Fix.no_fix(
                t,
                f"flat map: feature variability {np.sqrt(surf.variability):.3g} below "
                f"{self.min_variability:g} x reading sigma {np.sqrt(s2_flat):.3g}",
                self.name,
            )
        grid = surf.shape is not None
        if np.isfinite(surf.off_loglik):  # off_map = "unknown": nodes without map values hold the field's prior
            n_off = int(np.sum(~np.isfinite(logl)))
            if n_off:
                on = logl[np.isfinite(logl)]
                top = max(float(on.max()), surf.off_loglik)
                w_on = float(np.sum(np.exp(on - top)))
                w_off = n_off * float(np.exp(surf.off_loglik - top))
                mass_off = w_off / (w_on + w_off)
                if mass_off > self.max_off_map_mass:
                    return Fix.no_fix(
                        t,
                        f"off the map: {100 * mass_off:.0f} % of the likelihood lies where the map has no values",
                        self.name,
                    )
        if grid:
            ki, kj = divmod(k, surf.shape[1])  # type: ignore[index]
            n_fix, e_fix = float(surf.n[ki]), float(surf.e[kj])
        else:
            n_fix, e_fix = float(surf.n[k]), float(surf.e[k])
        temp, topup = self._tempering(surf, n_fix, e_fix, grid)
        logl = (logl - float(logl[k])) / temp  # tempered: the peak is 0
        lmax = 0.0
        if grid:
            l2 = logl.reshape(surf.shape)
            pk, snn, sne, see, _ = grid_moments(l2, surf.n, surf.e, lmax, n_fix, e_fix)
            p = None
            about = (n_fix, e_fix)
            if _touches_map_edge(l2, ki, kj):
                return Fix.no_fix(t, MAP_EDGE_REASON, self.name)
            if self.search_window and _reaches_edge(l2, ki, kj):
                return Fix.no_fix(t, f"{EDGE_REASON} (the prior may be too confident)", self.name)
            if self.ambiguity_mass < 1.0:
                amb = _ambiguity(l2, surf.n, surf.e, ki, kj)
                if amb[0] > self.ambiguity_mass:
                    return Fix.no_fix(
                        t,
                        f"ambiguous: {amb[1]} likelihood peaks in the search window, {100 * amb[0]:.0f} % of the "
                        f"likelihood off the best one (nearest {amb[2]:.0f} m away)",
                        self.name,
                        float(pk),
                    )
        else:
            p = np.exp(logl - lmax)
            p /= p.sum()
            pk = float(p[k])
        score = float(pk)
        if self.method == "mlr":
            if grid:
                l_far = float(grid_far_max(l2, surf.n, surf.e, n_fix, e_fix, self.min_distance_m**2))
            else:
                far = np.isfinite(logl) & ((surf.n - n_fix) ** 2 + (surf.e - e_fix) ** 2 >= self.min_distance_m**2)
                l_far = float(logl[far].max()) if np.any(far) else -np.inf
            log_ratio = lmax - l_far
            score = float(np.exp(min(log_ratio, 700.0)))
            if log_ratio < np.log(self.ratio_threshold):
                return Fix.no_fix(
                    t, f"ambiguous: likelihood ratio {score:.3g} below {self.ratio_threshold:g}", self.name, score
                )
        elif self.method == "abl":
            if pk < self.peak_threshold:
                return Fix.no_fix(
                    t, f"no distinct peak: normalised peak {pk:.3g} below {self.peak_threshold:g}", self.name, pk
                )
            if p is None:
                p = np.exp(logl - lmax)
                p /= p.sum()
            if not grid and surf.along is not None and surf.lane is not None:
                kb, score = _road_bin(p, surf.along, surf.lane, self.bin_size_m)
                n_fix, e_fix = float(surf.n[kb]), float(surf.e[kb])
            else:
                mass = _bin_mass(p, surf, self.bin_size_m)
                kb = int(np.argmax(mass))
                score = float(mass[kb])
                if grid:
                    bi, bj = divmod(kb, surf.shape[1])  # type: ignore[index]
                    n_fix, e_fix = float(surf.n[bi]), float(surf.e[bj])
                else:
                    n_fix, e_fix = float(surf.n[kb]), float(surf.e[kb])
        if grid:
            if about != (n_fix, e_fix):  # ABL moved the fix off the peak
                _, snn, sne, see, _ = grid_moments(l2, surf.n, surf.e, lmax, n_fix, e_fix)
            cov = np.array([[snn, sne], [sne, see]])
        else:
            cov = moments_about(p, surf.n, surf.e, n_fix, e_fix)
        cov = cov + topup + np.eye(2) * surf.step**2 / 12.0
        if not grid:  # road map: the vehicle is somewhere across the road
            cov = cov + np.eye(2) * self.track_sigma_m**2
        cov = cov + np.eye(2) * self.min_fix_sigma_m**2
        refusal = self._too_spread(surf, cov, t, score, grid)
        if refusal is not None:
            return refusal
        self._issued(surf)
        lat, lon = surf.frame.to_latlon(n_fix, e_fix)
        return Fix(t, float(lat), float(lon), cov, True, "", score, self.name)

    def prior_fix(self, surf: Surface, t: float, prior_cov: FloatArray) -> Fix | None:
        """The fix a likelihood that reaches the edge of the widest search window still holds (``edge_fix``), or
        None: the tempered likelihood times the prior ``N(0, prior_cov)`` (north/east m^2, centred on the INS
        position of the last reading, the frame's origin; the window spans ``window_sigma * 2**window_growth``
        prior sigmas, so the product is inside it) has moments ``mu, C``; the likelihood's own information is
        ``L = C^-1 - prior_cov^-1`` and the fix is ``L^-1 C^-1 mu`` with covariance ``L^-1`` in the directions where
        ``L`` holds more than ``1 / edge_fix_sigma_m^2``. In the others (along a track over a smooth map) the fix
        says nothing: it sits at the prior's mean (no innovation) with a 1-sigma of ``edge_fix_sigma_m``. So a
        section that fixes the cross-track position but not the along-track one gives a cross-track fix rather than
        nothing. None when the product is still at the window's edge or the map's, ambiguous, or holds no
        information. Also used for a likelihood cut off by the map's edge (the product, kept off that edge by the
        prior, is not cut off)."""
        if surf.shape is None or not self.search_window:
            return None
        P = np.asarray(prior_cov, dtype=float).reshape(2, 2)
        if not np.all(np.isfinite(P)) or np.linalg.det(P) <= 0.0:
            return None
        logl = surf.logl
        k = surf.k_max if surf.k_max >= 0 else int(np.argmax(logl))
        if not np.isfinite(logl[k]):
            return None
        ki, kj = divmod(k, surf.shape[1])
        temp, topup = self._tempering(surf, float(surf.n[ki]), float(surf.e[kj]), True)
        gn, ge = np.meshgrid(surf.n, surf.e, indexing="ij")
        Pi = np.linalg.inv(P)
        lp = (logl.reshape(surf.shape) - float(logl[k])) / temp
        lp = lp - 0.5 * (Pi[0, 0] * gn**2 + 2.0 * Pi[0, 1] * gn * ge + Pi[1, 1] * ge**2)
        lp = np.where(np.isfinite(lp), lp, -np.inf)
        pi_, pj_ = divmod(int(np.argmax(lp)), surf.shape[1])
        lp = lp - float(lp[pi_, pj_])
        if _reaches_edge(lp, pi_, pj_) or _touches_map_edge(lp, pi_, pj_):
            return None
        if self.ambiguity_mass < 1.0 and _ambiguity(lp, surf.n, surf.e, pi_, pj_)[0] > self.ambiguity_mass:
            return None
        w = np.exp(lp)
        w /= w.sum()
        mu = np.array([float(np.sum(w * gn)), float(np.sum(w * ge))])
        C = moments_about(w, gn, ge, mu[0], mu[1]) + np.eye(2) * surf.step**2 / 12.0
        Ci = np.linalg.inv(C)
        L = Ci - Pi
        lam, V = np.linalg.eigh(0.5 * (L + L.T))
        lam_min = 1.0 / self.edge_fix_sigma_m**2
        if lam[-1] <= lam_min:
            return None
        y = V.T @ (Ci @ mu)
        strong = lam > lam_min
        z = V @ np.where(strong, y / np.where(strong, lam, 1.0), 0.0)
        R = V @ np.diag(np.where(strong, 1.0 / np.where(strong, lam, 1.0), self.edge_fix_sigma_m**2)) @ V.T
        R = R + topup + np.eye(2) * (surf.step**2 / 12.0 + self.min_fix_sigma_m**2)
        if self._too_spread(replace(surf, prior_cov=P), R, t, float("nan"), True) is not None:
            return None
        self._issued(surf)
        lat, lon = surf.frame.to_latlon(float(z[0]), float(z[1]))
        return Fix(t, float(lat), float(lon), R, True, "", float("nan"), self.name)

    def _too_spread(self, surf: Surface, cov: FloatArray, t: float, score: float, grid: bool) -> Fix | None:
        """The issuing rule: "likelihood too spread" (no fix) or None (issue). With ``max_fix_sigma_m`` set, the fix's
        1-sigma in its better direction (in a grid search window; else its worse) must be at most that. By default,
        in a search window with the INS covariance known, the rule of the batch matchers (issue 16,
        :func:`._batch.adds_information`): issued when fusing it would shrink the prior's covariance by at least
        5 % in some direction beyond the window's own information (the window is the prior's). Until 2026-12 the
        default was a 1-sigma at most a quarter of the first window's half-width (one prior sigma), i.e. at least
        half the prior's information: on the Osborne tie lines it refused fixes that halved the error of a
        tactical INS (a fix sigma of 1.5 prior sigmas adds 30 % of the prior's information). Otherwise (whole-map
        scan, road maps, no prior) the old quarter of the window half-width."""
        from ._batch import MIN_INFORMATION_RATIO, information_ratio

        P = surf.prior_cov
        if self.max_fix_sigma_m is None and grid and self.search_window and P is not None and np.all(np.isfinite(P)):
            r = information_ratio(cov, np.asarray(P, dtype=float).reshape(2, 2), np.asarray(surf.half, dtype=float))
            if r >= MIN_INFORMATION_RATIO:
                return None
            sf = np.sqrt(np.maximum(np.linalg.eigvalsh(cov), 0.0))
            return Fix.no_fix(
                t,
                f"likelihood too spread: the fix adds no information over the prior (information ratio {r:.2g} < "
                f"{MIN_INFORMATION_RATIO:g}; fix sigmas {sf[0]:.3g} / {sf[-1]:.3g} m)",
                self.name,
                score,
            )
        max_sig = self.max_fix_sigma_m
        if max_sig is None:
            max_sig = 0.25 * min(surf.half) / surf.grow
        sig = float(np.sqrt(np.linalg.eigvalsh(cov)[0 if (grid and self.search_window) else -1]))
        if sig > max_sig:  # in a search window: the fix must say something in its better direction
            return Fix.no_fix(
                t, f"likelihood too spread: fix sigma {sig:.3g} m above {max_sig:.3g} m", self.name, score
            )
        return None

    # ------------------------------------------------------------------ honesty
    def temperature(self, surf: Surface, n_fix: float, e_fix: float) -> float:
        """The factor (>= 1) the scan's log-likelihood is divided by before its moments are taken (:meth:`honesty`)."""
        return self.honesty(surf, n_fix, e_fix)[0]

    def honesty(self, surf: Surface, n_fix: float, e_fix: float) -> tuple[float, FloatArray]:
        """(temperature, top-up covariance m^2) of the fix at ``(n_fix, e_fix)`` (module docstring): the
        sandwich of the correlated section covariance against the scan's diagonal one, as a scalar temperature
        (the geometric mean of its two directions, :func:`~.map_error.temperature_and_topup`) and the covariance
        that must still be added so that the fix covers the sandwich in the weaker direction; both scaled by the
        section's misfit per degree of freedom when its chi-square exceeds the 99 % quantile."""
        sec = surf.section
        if sec is None or sec.dn.size == 0:
            return 1.0, np.zeros((2, 2))
        frame = surf.frame
        pn, pe = sec.dn + n_fix, sec.de + e_fix
        k = pn.size
        c = sec.z.shape[1]
        h = max(float(surf.step), 1e-3)
        m0 = np.asarray(frame.sample(pn, pe, sec.h_last), float).reshape(k, c)
        jac = np.empty((k, c, 2))
        jac[:, :, 0] = (
            np.asarray(frame.sample(pn + h, pe, sec.h_last), float).reshape(k, c)
            - np.asarray(frame.sample(pn - h, pe, sec.h_last), float).reshape(k, c)
        ) / (2 * h)
        jac[:, :, 1] = (
            np.asarray(frame.sample(pn, pe + h, sec.h_last), float).reshape(k, c)
            - np.asarray(frame.sample(pn, pe - h, sec.h_last), float).reshape(k, c)
        ) / (2 * h)
        jac = np.nan_to_num(jac, nan=0.0, posinf=0.0, neginf=0.0)
        lat, lon = frame.to_latlon(pn, pe)
        sm = self._gradient_error(sec.error.sigma_at(lat, lon), np.sum(jac**2, axis=2).mean(axis=1))
        diff = self.difference and k > 1
        lv = sec.level_var
        node_var = max(surf.sigma2 / (2.0 if diff else 1.0) - sec.s2_base - (lv if k == 1 else 0.0), 0.0)
        sigma = section_covariance(pn, pe, sm, sec.sigma_sensor, sec.error.correlation_m)
        sigma[np.diag_indices(k)] += node_var
        sigma += lv  # the level offset, sigma_b^2 1 1' (module docstring)
        if sec.drift_mps is not None and sec.tau is not None and sec.tau.size == k:
            sigma += drift_covariance(jac, sec.tau, sec.drift_mps)  # INS drift over the section
        tr = section_transform(k, self.demean, self.difference, sec.level_frac)
        kappa, topup = temperature_and_topup(jac, sigma, surf.sigma2, tr)
        resid = sec.z - m0
        phi = 1.0
        if np.all(np.isfinite(resid)):
            chi2, dof = whitened_misfit(resid, sigma, tr)
            phi = misfit_factor(chi2, dof)
        return float(kappa * phi), topup * phi

    def _tempering(self, surf: Surface, n_fix: float, e_fix: float, grid: bool) -> tuple[float, FloatArray]:
        """The temperature (>= 1) the scan's log-likelihood is divided by and the covariance top-up (m^2) for a fix
        at ``(n_fix, e_fix)``: :meth:`honesty` on a grid scan (1 and none otherwise or without ``honest``), both
        scaled by :meth:`_overlap_factor`."""
        temp, topup = self.honesty(surf, n_fix, e_fix) if (grid and self.honest) else (1.0, np.zeros((2, 2)))
        overlap = self._overlap_factor(surf)
        return temp * overlap, topup * overlap

    def _overlap_factor(self, surf: Surface) -> float:
        """``K / (readings newer than the last issued fix)`` when this window shares readings with the window of
        the previous fix this matcher issued on the same stream (``match_every < window``), else 1."""
        sec = surf.section
        if not self.count_overlap or sec is None or sec.t is None or sec.t.size == 0:
            return 1.0
        t = sec.t
        last = self._last_fix_t
        if not (np.isfinite(last) and t[-1] > last and t[0] <= last):
            return 1.0
        new = int(np.sum(t > last))
        return float(t.size) / max(new, 1)

    def _gradient_error(self, sigma_map: FloatArray, grad2: FloatArray) -> FloatArray:
        """Per-reading map error 1-sigma (map unit) with the gradient term: ``sqrt(sigma_map^2 + (c |grad|)^2)``,
        ``c = map_gradient_error_m``, ``grad2`` (K,) the squared map gradient (unit^2/m^2) at the readings (module
        docstring); ``sigma_map`` unchanged when ``c`` is 0."""
        if not self.map_gradient_error_m > 0:
            return sigma_map
        g2 = np.nan_to_num(np.asarray(grad2, dtype=float), nan=0.0, posinf=0.0)
        return np.sqrt(np.asarray(sigma_map, dtype=float) ** 2 + self.map_gradient_error_m**2 * g2)

    def _issued(self, surf: Surface) -> None:
        sec = surf.section
        if sec is not None and sec.t is not None and sec.t.size:
            self._last_fix_t = float(sec.t[-1])


def _flat_sigma2(surf: Surface, difference: bool) -> float:
    """The variance the flat-map test compares the map's feature variability with: the scan's, without the map
    error (a map with large errors is not flat; what it is worth is the temperature's business)."""
    sec = surf.section
    if sec is None:
        return float(surf.sigma2)
    map_var = max(sec.s2_base - sec.sigma_sensor**2, 0.0) + (sec.level_var if sec.dn.size == 1 else 0.0)
    k = 2.0 if (difference and sec.dn.size > 1) else 1.0
    return max(float(surf.sigma2) - k * map_var, k * sec.sigma_sensor**2)


#: a peak's region: where the (tempered) log-likelihood is within this of its maximum, the 99.9 % region of a
#: 2-D Gaussian (chi-square 2 dof quantile 13.8, halved)
HPD_LOG_DROP = 0.5 * 13.8155


def _ambiguity(l2: FloatArray, n_ax: FloatArray, e_ax: FloatArray, ki: int, kj: int) -> tuple[float, int, float]:
    """Multi-modality of a tempered log-likelihood grid ``l2`` (peak 0 at node ``(ki, kj)``): the region where it
    is within :data:`HPD_LOG_DROP` of the peak, split into 8-connected parts. Returns (normalised likelihood mass
    in the parts other than the peak's, number of parts, distance m from the peak to the nearest node of another
    part; inf if none)."""
    mask = l2 >= -HPD_LOG_DROP
    lab, count = ndimage.label(mask, structure=np.ones((3, 3), dtype=bool))
    if count <= 1:
        return 0.0, int(count), float("inf")
    p = np.exp(np.where(np.isfinite(l2), l2, -np.inf))
    tot = float(p.sum())
    main = lab[ki, kj]
    other = (lab > 0) & (lab != main)
    mass = float(p[other].sum() / tot) if tot > 0 else 0.0
    oi, oj = np.nonzero(other)
    d = float(np.min(np.hypot(n_ax[oi] - n_ax[ki], e_ax[oj] - e_ax[kj]))) if oi.size else float("inf")
    return mass, int(count), d


def _reaches_edge(l2: FloatArray, ki: int, kj: int) -> bool:
    """True when the peak's region (as in :func:`_ambiguity`) touches the border of the scanned window: the
    likelihood goes on beyond it and its moments would be truncated."""
    mask = l2 >= -HPD_LOG_DROP
    lab, _ = ndimage.label(mask, structure=np.ones((3, 3), dtype=bool))
    main = lab[ki, kj]
    if main == 0:
        return False
    border = np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]])
    return bool(np.any(border == main))


def _touches_map_edge(l2: FloatArray, ki: int, kj: int) -> bool:
    """True when the peak's region (as in :func:`_ambiguity`) borders a scanned node without a likelihood (a
    hypothesis that puts some reading where the map has no values: ``-inf`` with ``off_map = "impossible"``). The
    likelihood is then cut off at the map's edge, not by the readings: beyond it the readings may fit as well or
    better, so the peak is pushed away from the edge and the moments are too small. On the Osborne tie lines, which
    begin at the map's edge, the first ML fix of a tactical run was 50-120 m off towards the map's inside with
    sigmas of 10-18 m (fix NEES 24-70, 4 of 9 fixes whose section came within 300 m of the edge; 1.2 elsewhere),
    and the filter took it as a tilt and velocity error (10149 at 65 m/s: 1.7 km RMS against 0.4 km free inertial)."""
    region = _peak_region(l2, ki, kj)
    if region is None:
        return False
    near = ndimage.binary_dilation(region, structure=np.ones((3, 3), dtype=bool))
    return bool(np.any(near & ~np.isfinite(l2)))


def _peak_region(l2: FloatArray, ki: int, kj: int) -> NDArray[np.bool_] | None:
    """The 8-connected part of ``l2 >= -HPD_LOG_DROP`` holding node ``(ki, kj)`` (None if that node is outside)."""
    lab, _ = ndimage.label(l2 >= -HPD_LOG_DROP, structure=np.ones((3, 3), dtype=bool))
    main = lab[ki, kj]
    return None if main == 0 else lab == main


def ins_drift_rate(t: FloatArray, cov_ne: FloatArray | None) -> FloatArray:
    """Per-axis (north, east) rate m/s at which the INS position 1-sigma grew within a window, from the fuser's
    covariance at each reading (``cov_ne`` (K, 2, 2) m^2 at times ``t`` (K,) s): the largest
    ``d sqrt(P_aa) / dt`` between successive readings. ``|d sigma_p / dt| = |P_pv| / sigma_p <= sigma_v``, so it is
    a lower bound of the INS velocity error 1-sigma, tight once the position error is velocity-driven; zeros when
    unknown."""
    if cov_ne is None or len(t) < 2:
        return np.zeros(2)
    sd = np.sqrt(np.maximum(np.stack([cov_ne[:, 0, 0], cov_ne[:, 1, 1]], axis=1), 0.0))
    dt = np.diff(np.asarray(t, float))
    ok = dt > 0
    if not np.any(ok):
        return np.zeros(2)
    rate = np.diff(sd, axis=0)[ok] / dt[ok, None]
    rate = np.where(np.isfinite(rate), rate, 0.0)
    return np.maximum(rate.max(axis=0), 0.0)


def _section_times(t: FloatArray, dn: FloatArray, de: FloatArray) -> FloatArray | None:
    """Time (s, <= 0) of each section reading relative to the last; for a distance-resampled section (other
    length than ``t``) the times are taken proportional to the travelled distance."""
    if dn.size == t.size:
        return t - t[-1]
    if dn.size < 2 or t.size < 2:
        return None
    s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(dn), np.diff(de)))])
    return (s - s[-1]) / max(s[-1], 1e-9) * (t[-1] - t[0])


def _bin_mass(p: FloatArray, surf: Surface, bin_size_m: float) -> FloatArray:
    """Sum of normalised likelihood in a square bin of side ``bin_size_m`` centred on each candidate."""
    if surf.shape is not None:
        w = max(int(round(bin_size_m / surf.step)), 1)
        grid = p.reshape(surf.shape)
        return (ndimage.uniform_filter(grid, size=w, mode="constant") * w * w).ravel()
    from scipy.spatial import cKDTree

    pts = np.column_stack([surf.n, surf.e])
    tree = cKDTree(pts)
    groups = tree.query_ball_point(pts, r=bin_size_m / 2.0)
    return np.array([p[g].sum() for g in groups])


def _road_bin(p: FloatArray, along: FloatArray, lane: NDArray[np.int64], bin_size_m: float) -> tuple[int, float]:
    """ABL on a road map (Shockley 003 sec. 4.3.3): a bin of length ``bin_size_m`` (m) slides along the map's
    sequence of points (same road, same travel direction); the bin holding the most normalised likelihood ``p`` wins.
    The fix is the point of that bin nearest to the bin's likelihood-weighted centre along the road (so a lone sharp
    peak is not moved by up to half a bin to whichever overlapping bin happens to hold a little more mass).
    Returns (index of the fix candidate, mass of the winning bin)."""
    span = float(np.max(along) - np.min(along)) + 10.0 * bin_size_m + 1.0
    coord = along - np.min(along) + lane * span  # one line: lanes never share a bin
    order = np.argsort(coord, kind="stable")
    c, q = coord[order], p[order]
    cum = np.concatenate([[0.0], np.cumsum(q)])
    half = 0.5 * bin_size_m
    lo = np.searchsorted(c, c - half - 1e-9, "left")
    hi = np.searchsorted(c, c + half + 1e-9, "right")
    mass = cum[hi] - cum[lo]
    b = int(np.argmax(mass))
    inside = slice(int(lo[b]), int(hi[b]))
    w = q[inside]
    centre = float(np.sum(w * c[inside]) / np.sum(w)) if np.sum(w) > 0 else float(c[b])
    k = int(lo[b]) + int(np.argmin(np.abs(c[inside] - centre)))
    return int(order[k]), float(mass[b])


def _local_grid(fmap: FieldMap, frame: WorkFrame) -> tuple[FloatArray, float, float, float, float] | None:
    """(values (ny, nx, c), n0, dn, e0, de) of a local-frame grid map read through a :class:`MapFrame`, else None."""
    if not isinstance(frame, MapFrame) or getattr(fmap, "frame", None) != "local" or not hasattr(fmap, "axes"):
        return None
    ya, xa = fmap.axes  # type: ignore[attr-defined]
    if ya.size < 2 or xa.size < 2:
        return None
    v = np.asarray(fmap.values, dtype=float)  # type: ignore[attr-defined]
    v3 = np.ascontiguousarray(v.reshape(v.shape[0], v.shape[1], -1))
    return v3, float(ya[0]), float(ya[1] - ya[0]), float(xa[0]), float(xa[1] - xa[0])


def distance_sample(
    dn: FloatArray, de: FloatArray, z: FloatArray, step_m: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Distance-sampled section (Shockley 003 sec. 4.4): readings ``z`` (N, c) at INS positions ``(dn, de)`` m
    re-interpolated every ``step_m`` metres of travelled distance, counted back from the last reading (which is
    kept). Readings taken while standing still collapse to one. Returns the new positions and readings."""
    seg = np.hypot(np.diff(dn), np.diff(de))
    s = np.concatenate([[0.0], np.cumsum(seg)])
    keep = np.concatenate([[True], seg > 1e-9])
    s, dn, de, z = s[keep], dn[keep], de[keep], z[keep]
    if s.size < 2:
        return dn[-1:], de[-1:], z[-1:]
    s_new = s[-1] - np.arange(0.0, s[-1] + 1e-9, step_m)[::-1]
    zi = np.column_stack([np.interp(s_new, s, z[:, c]) for c in range(z.shape[1])])
    return np.interp(s_new, s, dn), np.interp(s_new, s, de), zi


def _gradient_rms(
    native: tuple[FloatArray, FloatArray, FloatArray] | None, fmap: FieldMap, window: MatchWindow
) -> float:
    """RMS horizontal gradient magnitude (unit/m) of the window's native nodes, or of the map at the INS
    positions when the map has no native local grid."""
    if native is not None:
        return native_gradient_rms(native)
    try:
        g = np.asarray(fmap.gradient_ne(window.lat, window.lon), float)
    except (ValueError, AttributeError):
        return float("nan")
    g2 = np.sum(g.reshape(len(g), -1) ** 2, axis=1)
    g2 = g2[np.isfinite(g2)]
    return float(np.sqrt(g2.mean())) if g2.size else float("nan")


def _map_gradient2(fmap: FieldMap, lat: FloatArray, lon: FloatArray) -> FloatArray:
    """Squared horizontal map gradient (unit^2/m^2, mean over the field's components) at ``(lat, lon)`` rad (K,);
    0 where the map has none (NaN, off the map, no ``gradient_ne``)."""
    try:
        g = np.asarray(fmap.gradient_ne(lat, lon), float)  # type: ignore[attr-defined]
    except (ValueError, AttributeError, TypeError):
        return np.zeros(np.size(lat))
    g2 = np.sum(g.reshape(np.size(lat), -1, 2) ** 2, axis=2).mean(axis=1)
    return np.nan_to_num(g2, nan=0.0, posinf=0.0)


def _is_track(fmap: FieldMap) -> bool:
    return hasattr(fmap, "along_track_m") and hasattr(fmap, "segment_id") and hasattr(fmap, "nearest_ne")


def _map_half_extent(fmap: FieldMap, frame: WorkFrame) -> tuple[float, float] | None:
    """Half-extent (m) of a window about the frame origin that covers the whole map, if the map knows its extent."""
    bounds = getattr(fmap, "bounds_latlon", None)
    if bounds is None:
        return None
    lat_min, lat_max, lon_min, lon_max = (float(b) for b in (bounds() if callable(bounds) else bounds))
    n, e = frame.to_ne(np.array([lat_min, lat_min, lat_max, lat_max]), np.array([lon_min, lon_max, lon_min, lon_max]))
    return float(np.max(np.abs(n))), float(np.max(np.abs(e)))


def ML(**kw: object) -> LikelihoodMatcher:
    """Maximum likelihood matcher (Shockley 003 sec. 4.3.1)."""
    return LikelihoodMatcher(method="ml", **kw)  # type: ignore[arg-type]


def MLR(**kw: object) -> LikelihoodMatcher:
    """Maximum likelihood ratio matcher (Shockley 003 sec. 4.3.2)."""
    return LikelihoodMatcher(method="mlr", **kw)  # type: ignore[arg-type]


def ABL(**kw: object) -> LikelihoodMatcher:
    """Aggregate bin likelihood matcher (Shockley 003 sec. 4.3.3)."""
    return LikelihoodMatcher(method="abl", **kw)  # type: ignore[arg-type]
