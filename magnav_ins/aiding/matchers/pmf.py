"""Point-mass filter: recursive Bayesian estimation of the horizontal position on a grid (Bergman, Ljung &
Gustafsson 1999, "Terrain navigation using Bayesian statistics", IEEE Control Systems 19(3), 33-40; Bergman 1999,
PhD thesis, Linkoping, ch. 5).

The density of the INS position error is held as point masses on a regular grid of offsets ``d`` from the INS
position (the grid rides with the INS: Bergman's time update moves the masses by the INS displacement ``u_t``):

* initiation: the grid spans ``gate_sigma`` prior sigmas about the INS position with ``grid_points`` nodes a side;
  the masses are uniform over the gate (``use_prior=False``, a diffuse prior: the fix is then the readings'
  evidence alone and the fuser can add it to the INS without counting the INS twice) or the INS Gaussian
  (``use_prior=True``, Bergman's recursion from the prior);
* time update: convolution with the INS drift since the last update, ``N(0, q I)`` with ``q`` the growth of the
  INS position variance (plus ``drift_sigma^2 dt``), done as a Gaussian filter on the grid with the density beyond
  the border taken as the border's (the diffuse prior continues outside the grid); the grid is widened (masses
  interpolated, the border density continued) when the INS sigma outgrows it;
* systematic drift (ours, issue 16; ``systematic_drift=True``, default): the INS position error moves by its
  velocity error, which holds over a 30-reading recursion (a stretched or turned track), not as the random walk of
  the time update. Its size since initiation is at most ``S_k = sum_j (sigma_v,j-1 + sigma_v,j) dt_j / 2`` (1
  sigma, m: Minkowski's bound of the std of the integrated velocity error, reached by a fully correlated one;
  ``sigma_v`` the INS horizontal velocity sigma, root of half the trace of the prior's velocity covariance). It
  enters twice: the misfit test below takes ``S_T - S_t`` as the drift since reading ``t`` (not the growth of the
  position variance, which also holds the position error's correlation with the later drift and overstates it:
  10 km against 6 km over a tactical recursion), and the fix's covariance gets ``lag^2 I``, the posterior's lag
  behind such a drift: ``lag <- (1 - K) (lag + ds)`` per reading, ``ds`` the step of ``S``, ``K = 1 - V+ / V-``
  the update's shrinkage of the masses' variance (half trace); a filter that keeps all its readings (``K = 1 /
  k``) lags by ``S_T - mean S`` (the readings' centre), one that forgets them fast (large ``q``) hardly lags.
  On a synthetic map with the INS velocity error held over the recursion (0.5-2 m/s) and the time update's ``q``
  set to that drift's steps, the unscaled fixes had a NEES of 3-7 and with ``lag^2`` 1.8-2.3 (that time update
  was not kept: with the tactical IMU on QLD West the real deformation outgrew it and 3 of 10 runs diverged);
* measurement update: ``w(d) <- w(d) N(z; m(x_ins + d), s^2 + |grad m|^2 D^2 / 12)`` (``s^2`` sensor + map error,
  :mod:`._batch`; ``D`` the grid spacing, each node standing for its cell);
* output (:meth:`PointMassFilter.to_fix`): the posterior mean and covariance (second moment plus ``D^2 / 12``) at
  the INS position plus the mean offset, the covariance scaled by ``max(1, chi2)`` (plus ``lag^2 I`` above),
  ``chi2`` the mean normalised misfit of the readings at their INS positions moved by the mean offset, their
  variance holding the INS drift since each reading through the local gradient (ours, as ICCP's scaling; issue 16:
  with the tactical IMU on QLD West the INS deforms by kilometres within a 30-reading recursion, the riding grid's
  drift model misses it, and the unscaled fixes had a NEES of 1,825 mean, 17 median over 10 runs; scaled: 209 /
  13).
* grid: ``grid_points`` nodes a side, more (up to ``max_grid_points``) where the gate needs them to keep the
  spacing at most ``max_spacing_fraction`` of the map's node spacing (:meth:`PointMassFilter._refine`). With ``restart=True`` (default) the filter is re-initiated at the next
  reading, so consecutive fixes are built from disjoint readings and are independent (the fuser takes them as
  such); ``restart=False`` keeps Bergman's full recursion (each fix then repeats all the earlier evidence: only
  for a free-running PMF, not for fusing).

No fix: "off the map" (no map values under the grid), "flat map" when the fix adds no information over the prior
beyond the grid's own (:func:`._batch.adds_information`), "at the edge" when more than ``edge_mass`` of the posterior sits on the grid's
border (the truth may be outside the grid), "diverged" when the readings' misfit at the mean offset (``chi2`` above)
fails the chi-square test at false-alarm rate ``misfit_alpha`` (:func:`._batch.misfit_threshold`: 1.99 per reading
for 30) or exceeds ``max_chi2``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from ...core.errors import ConfigError
from ...core.protocols import FieldMap
from ...core.types import FieldReadings, Fix, NavEstimate
from ._batch import adds_information, information_refusal, local_gradient2, misfit_threshold
from ._local import make_frame, map_components, sigma_window, spacing_of
from .map_error import resolve_map_error

FloatArray = NDArray[np.float64]


def velocity_sigma(prior: NavEstimate) -> float:
    """Horizontal velocity sigma (m/s) of ``prior``: root of half the trace of its north/east velocity covariance;
    NaN when its layout has no velocity or the value is not finite."""
    try:
        s = prior.layout["vel"]
    except (KeyError, TypeError):
        return float("nan")
    P = np.asarray(prior.P, float)
    if P.ndim != 2 or P.shape[0] < s.start + 2:
        return float("nan")
    v = 0.5 * (P[s.start, s.start] + P[s.start + 1, s.start + 1])
    return float(np.sqrt(v)) if np.isfinite(v) and v >= 0 else float("nan")


def _axis(half: float, target: float, n_min: int, n_max: int) -> FloatArray:
    """Symmetric axis ``[-half, half]`` m with spacing at most ``target`` m where ``n_max`` nodes allow it (at
    least ``n_min`` nodes; odd counts, so 0 is a node)."""
    k = int(np.ceil(half / target))
    k = int(np.clip(k, n_min // 2, n_max // 2))
    return np.linspace(-half, half, 2 * k + 1)


def _spread(w: FloatArray, an: FloatArray, ae: FloatArray) -> float:
    """Half the trace of the covariance (m^2) of the masses ``w`` on the axes ``an``, ``ae`` (m)."""
    pn, pe = w.sum(axis=1), w.sum(axis=0)
    mn, me = float(pn @ an), float(pe @ ae)
    return 0.5 * (float(pn @ (an - mn) ** 2) + float(pe @ (ae - me) ** 2))


@dataclass
class PMFState:
    """The point masses: INS position ``lat``, ``lon`` rad, ``h`` m at time ``t`` s and its horizontal covariance
    ``cov_ne`` (m^2) at the last time update; offset axes ``an``, ``ae`` (m, north / east of the INS position);
    normalised masses ``w`` (len(an), len(ae)); ``updates`` readings absorbed since initiation; the last ``fix``;
    ``restart`` re-initiate at the next time update; ``frame`` the working frame of the last update; ``hist`` per
    reading (INS lat, lon, reading, its variance, INS position variance); ``sigma_v`` the INS velocity sigma m/s at
    ``t``; ``drift`` the systematic drift bound ``S`` (m) since initiation and ``hist_drift`` its value at each
    reading; ``lag`` the posterior's lag behind that drift (m) and ``lag_step`` the drift since the last reading
    (module docstring)."""

    t: float
    lat: float
    lon: float
    h: float
    cov_ne: FloatArray
    an: FloatArray
    ae: FloatArray
    w: FloatArray
    updates: int = 0
    fix: Fix | None = None
    restart: bool = False
    off_map: bool = False
    frame: Any = None
    hist: list[tuple[float, float, FloatArray, float, float]] = field(default_factory=list)
    sigma_v: float = float("nan")
    drift: float = 0.0
    hist_drift: list[float] = field(default_factory=list)
    lag: float = 0.0
    lag_step: float = 0.0


@dataclass
class PointMassFilter:
    """Point-mass filter (module docstring). Recursive: ``initiate``, ``predict``, ``update``, ``to_fix``.

    ``grid_points`` nodes a side; ``gate_sigma`` grid half-width in prior sigmas (at least ``window_floor_m``);
    ``drift_sigma`` extra random walk of the INS position (m/sqrt(s)); ``systematic_drift`` the misfit's drift and
    the lag term from the INS velocity sigma (module docstring; else the misfit takes the growth of the position
    variance and there is no lag term); ``use_prior``; ``restart``;
    ``map_sigma`` / ``correlation_m`` override the map's error; ``edge_mass`` the border-mass cut-off;
    ``max_spacing_fraction`` the largest grid spacing as a fraction of the map's node spacing (more nodes a side
    than ``grid_points`` where the gate needs them, at most ``max_grid_points``); ``misfit_alpha`` the false-alarm
    rate of the misfit's chi-square test and ``max_chi2`` a cap on its threshold: above either the fix is
    "diverged" (as TERCOM's)."""

    grid_points: int = 81
    gate_sigma: float = 4.0
    window_floor_m: float = 10.0
    drift_sigma: float = 0.0
    systematic_drift: bool = True
    use_prior: bool = False
    restart: bool = True
    map_sigma: float | None = None
    correlation_m: float | None = None
    edge_mass: float = 0.05
    max_spacing_fraction: float = 0.5
    max_grid_points: int = 401
    max_chi2: float = 9.0
    misfit_alpha: float = 1e-3
    name: str = "pmf"

    def __post_init__(self) -> None:
        if not (isinstance(self.grid_points, int) and self.grid_points >= 5):
            raise ConfigError(f"pmf 'grid_points': expected an integer >= 5, got {self.grid_points!r}")
        if not self.gate_sigma > 0:
            raise ConfigError(f"pmf 'gate_sigma': expected > 0, got {self.gate_sigma!r}")
        if not (np.isfinite(self.drift_sigma) and self.drift_sigma >= 0):
            raise ConfigError(f"pmf 'drift_sigma': expected >= 0 m/sqrt(s), got {self.drift_sigma!r}")
        if not 0 < self.misfit_alpha < 1:
            raise ConfigError(f"pmf 'misfit_alpha': expected 0 < misfit_alpha < 1, got {self.misfit_alpha!r}")
        if not 0 < self.edge_mass < 1:
            raise ConfigError(f"pmf 'edge_mass': expected 0 < edge_mass < 1, got {self.edge_mass!r}")

    # ------------------------------------------------------------------ recursion
    def initiate(self, prior: NavEstimate, rng: np.random.Generator | None = None) -> PMFState:  # noqa: ARG002
        """Point masses over the gate of ``prior`` (uniform, or its Gaussian with ``use_prior``)."""
        nav = prior.nav
        cov = np.array(prior.cov_ne, dtype=float)
        hn, he = sigma_window(cov, self.gate_sigma, self.window_floor_m)
        if not (np.isfinite(hn) and np.isfinite(he)):
            hn = he = self.window_floor_m
        k = self.grid_points // 2
        an, ae = np.linspace(-hn, hn, 2 * k + 1), np.linspace(-he, he, 2 * k + 1)
        if self.use_prior and np.all(np.isfinite(cov)) and np.linalg.det(cov) > 0:
            GN, GE = np.meshgrid(an, ae, indexing="ij")
            ci = np.linalg.inv(cov)
            w = np.exp(-0.5 * (ci[0, 0] * GN**2 + 2 * ci[0, 1] * GN * GE + ci[1, 1] * GE**2))
        else:
            w = np.ones((an.size, ae.size))
        return PMFState(float(nav.t), float(nav.lat), float(nav.lon), float(nav.h), cov, an, ae, w / w.sum(),
                        sigma_v=velocity_sigma(prior))  # fmt: skip

    def predict(self, state: PMFState, prior: NavEstimate) -> PMFState:
        """Time update to the INS estimate ``prior``: the masses ride with the INS and spread by its drift."""
        if state.restart:
            return self.initiate(prior)
        nav = prior.nav
        cov = np.array(prior.cov_ne, dtype=float)
        v0 = 0.5 * float(np.trace(state.cov_ne))
        v1 = 0.5 * float(np.trace(cov))
        dt = max(float(nav.t) - state.t, 0.0)
        q = max(v1 - v0, 0.0) + self.drift_sigma**2 * dt if np.isfinite(v1 - v0) else 0.0
        sigma_v = velocity_sigma(prior)
        ds = 0.5 * (state.sigma_v + sigma_v) * dt  # drift of a velocity error held over the step (1 sigma, m)
        ds = ds if np.isfinite(ds) else 0.0
        an, ae, w = state.an, state.ae, state.w
        hn, he = sigma_window(cov, self.gate_sigma, self.window_floor_m)
        if np.isfinite(hn) and (hn > 1.2 * an[-1] or he > 1.2 * ae[-1]):  # the INS sigma outgrew the grid: widen
            # keep the spacing (more nodes, up to max_grid_points) so a refined grid stays refined
            bn = _axis(max(hn, an[-1]), float(an[1] - an[0]), an.size, max(self.max_grid_points, an.size))
            be = _axis(max(he, ae[-1]), float(ae[1] - ae[0]), ae.size, max(self.max_grid_points, ae.size))
            BN, BE = np.meshgrid(bn, be, indexing="ij")
            fi = (BN - an[0]) / (an[1] - an[0])
            fj = (BE - ae[0]) / (ae[1] - ae[0])
            dens = w / ((an[1] - an[0]) * (ae[1] - ae[0]))
            w = ndimage.map_coordinates(dens, [fi, fj], order=1, mode="nearest")  # the flat prior continues
            w = w * (bn[1] - bn[0]) * (be[1] - be[0])
            an, ae = bn, be
        if q > 0:
            sn, se = np.sqrt(q) / (an[1] - an[0]), np.sqrt(q) / (ae[1] - ae[0])
            if max(sn, se) > 0.05:
                # "nearest": the density beyond the border is taken as the border's (a flat prior continues there);
                # an absorbing border would drain mass from the edges at every step and, renormalised, pile it up
                # about the INS position: a spurious prior that pulls every fix back onto the INS
                w = ndimage.gaussian_filter(w, sigma=(sn, se), mode="nearest", truncate=4.0)
        tot = float(w.sum())
        w = w / tot if tot > 0 else np.full_like(w, 1.0 / w.size)
        return PMFState(float(nav.t), float(nav.lat), float(nav.lon), float(nav.h), cov, an, ae, w, state.updates,
                        state.fix, False, state.off_map, state.frame, state.hist, sigma_v, state.drift + ds,
                        state.hist_drift, state.lag, state.lag_step + ds)  # fmt: skip

    def update(self, state: PMFState, readings: FieldReadings, fmap: FieldMap) -> PMFState:
        """Measurement update with the last reading of ``readings``."""
        if len(readings) == 0:
            return state
        z = np.asarray(readings.value, float).reshape(len(readings), -1)[-1]
        if z.size != map_components(fmap) or not np.all(np.isfinite(z)):
            state.fix = Fix.no_fix(float(readings.t[-1]), "reading is NaN or has the wrong components", self.name)
            return state
        if state.updates == 0:
            self._refine(state, fmap)
        frame = make_frame(fmap, state.lat, state.lon)
        GN, GE = np.meshgrid(state.an, state.ae, indexing="ij")
        m = frame.sample(GN.ravel(), GE.ravel()).reshape(GN.shape + (-1,))
        me = resolve_map_error(fmap, self.map_sigma, self.correlation_m)
        s_map = float(np.nan_to_num(me.sigma_at(np.array([state.lat]), np.array([state.lon]))[0]))
        dn, de = float(state.an[1] - state.an[0]), float(state.ae[1] - state.ae[0])
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN grid off the map: handled below
            g2 = np.nanmean(np.sum(np.gradient(m, dn, axis=0) ** 2 + np.gradient(m, de, axis=1) ** 2, axis=-1))
        v = float(readings.sigma) ** 2 + s_map**2 + (float(g2) if np.isfinite(g2) else 0.0) * (dn * dn + de * de) / 12
        ll = -0.5 * np.sum((m - z) ** 2, axis=-1) / v
        finite = np.isfinite(ll)
        if not np.any(finite):
            state.off_map = True
            state.fix = Fix.no_fix(float(readings.t[-1]), "off the map: no map values under the grid", self.name)
            return state
        ll = np.where(finite, ll, -np.inf)
        w = state.w * np.exp(ll - np.max(ll[finite]))
        tot = float(w.sum())
        if not tot > 0:  # the reading contradicts every mass: keep the prior, say so
            state.fix = Fix.no_fix(float(readings.t[-1]), "diverged: the reading fits no point mass", self.name)
            return state
        w = w / tot
        v0, v1 = _spread(state.w, state.an, state.ae), _spread(w, state.an, state.ae)
        gain = float(np.clip(1.0 - v1 / v0, 0.0, 1.0)) if v0 > 0 else 1.0
        state.lag = (1.0 - gain) * (state.lag + state.lag_step)  # the lag behind a systematic drift (1 sigma, m)
        state.lag_step = 0.0
        state.w = w
        state.frame = frame
        state.t = float(readings.t[-1])
        state.updates += 1
        state.fix = None
        var_ins = 0.5 * float(np.trace(state.cov_ne)) if np.all(np.isfinite(state.cov_ne)) else float("nan")
        state.hist.append((state.lat, state.lon, np.asarray(z, float), v, var_ins))
        state.hist_drift.append(state.drift)
        return state

    def _refine(self, state: PMFState, fmap: FieldMap) -> None:
        """Before the first reading: finer axes when the grid's spacing exceeds ``max_spacing_fraction`` of the
        map's node spacing (the masses resampled; before any reading they are the prior, smooth on the grid).

        Why (issue 16): with the tactical IMU on QLD West the gate of 4 prior sigmas spans 100-160 km and 81 nodes
        a side put them 1.5-4 km apart on a 0.9 km map: the likelihood sampled that coarsely aliases (the node
        nearest the truth misfits by several mGal, some node far away fits by chance), and a third of the issued
        fixes sat 20-90 km off with sigmas of 1-15 km (fix NEES mean 2,058)."""
        target = self.max_spacing_fraction * spacing_of(fmap, float("inf"))
        an, ae = state.an, state.ae
        if not np.isfinite(target) or target <= 0:
            return
        dn, de = float(an[1] - an[0]), float(ae[1] - ae[0])
        if max(dn, de) <= target:
            return
        bn = _axis(float(an[-1]), target, an.size, self.max_grid_points)
        be = _axis(float(ae[-1]), target, ae.size, self.max_grid_points)
        BN, BE = np.meshgrid(bn, be, indexing="ij")
        dens = state.w / (dn * de)
        w = ndimage.map_coordinates(dens, [(BN - an[0]) / dn, (BE - ae[0]) / de], order=1, mode="nearest")
        tot = float(w.sum())
        state.an, state.ae = bn, be
        state.w = w / tot if tot > 0 else np.full(w.shape, 1.0 / w.size)

    def _misfit(self, state: PMFState, mn: float, me_: float, h: float) -> float:
        """Mean normalised misfit ``(z_t - m(x_t + d))^2 / v_t`` of the readings since initiation at their INS
        positions ``x_t`` moved by the posterior mean offset ``d`` = (``mn``, ``me_``) m, ``v_t`` the update's
        variance plus ``|grad m|^2 r_t^2``, ``r_t`` the INS drift since reading t (the offset a rigid shift cannot
        hold): ``S_T - S_t`` with the systematic drift model, else ``sqrt(V_T - V_t)``, ``V`` half the trace of the
        INS position covariance m^2. 1 with fewer than 2 readings or no map values."""
        if len(state.hist) < 2 or state.frame is None:
            return 1.0
        lat = np.array([r[0] for r in state.hist])
        lon = np.array([r[1] for r in state.hist])
        z = np.array([r[2] for r in state.hist]).reshape(lat.size, -1)
        v = np.array([r[3] for r in state.hist])
        n, e = state.frame.to_ne(lat, lon)
        n, e = np.asarray(n, float) + mn, np.asarray(e, float) + me_
        m = state.frame.sample(n, e).reshape(lat.size, -1)
        g2 = local_gradient2(state.frame, n, e, max(h, 0.5))
        if self.systematic_drift and len(state.hist_drift) == lat.size:
            S = np.array(state.hist_drift)
            drift2 = (S[-1] - S) ** 2
        else:
            var = np.array([r[4] for r in state.hist])
            drift2 = np.nan_to_num(np.maximum(var[-1] - var, 0.0))
        r2 = np.sum((z - m) ** 2, axis=1) / (v + g2 * drift2)
        r2 = r2[np.isfinite(r2)]
        return float(np.mean(r2)) if r2.size >= 2 else 1.0

    def _deformation_cover(self, state: PMFState) -> float:
        """Variance (m^2, per axis) of the posterior's lag behind a systematic INS drift: ``lag^2`` (module
        docstring); 0 without ``systematic_drift``."""
        if not self.systematic_drift or not np.isfinite(state.lag):
            return 0.0
        return float(state.lag) ** 2

    def to_fix(self, state: PMFState) -> Fix:
        """The posterior mean and covariance as a fix at the INS position plus the mean offset."""
        fix = self._fix(state)
        if self.restart:
            state.restart = True
        return fix

    def _fix(self, state: PMFState) -> Fix:
        t = state.t
        if state.fix is not None and not state.fix.available:
            return state.fix
        if state.updates == 0:
            return Fix.no_fix(t, "no reading since the last fix", self.name)
        w = state.w
        GN, GE = np.meshgrid(state.an, state.ae, indexing="ij")
        mn, me_ = float(np.sum(w * GN)), float(np.sum(w * GE))
        dn, de = GN - mn, GE - me_
        Dn, De = float(state.an[1] - state.an[0]), float(state.ae[1] - state.ae[0])
        C = np.array([[np.sum(w * dn * dn), np.sum(w * dn * de)], [np.sum(w * dn * de), np.sum(w * de * de)]])
        C = C + np.diag([Dn * Dn, De * De]) / 12.0
        chi2 = self._misfit(state, mn, me_, 0.5 * min(Dn, De))
        limit = min(self.max_chi2, misfit_threshold(len(state.hist), self.misfit_alpha))
        if chi2 > limit:
            return Fix.no_fix(
                t,
                f"diverged: readings disagree with the map at the mean offset (chi2 per reading {chi2:.3g} above "
                f"{limit:.3g})",
                self.name,
                chi2,
            )
        C = C * max(1.0, chi2) + np.eye(2) * self._deformation_cover(state)
        gate = (0.5 * float(state.an[-1] - state.an[0]), 0.5 * float(state.ae[-1] - state.ae[0]))
        if not adds_information(C, state.cov_ne, gate):  # C holds the grid's own (diffuse) information
            return information_refusal(t, C, state.cov_ne, self.name, float(state.updates), gate)
        edge = float(w[0].sum() + w[-1].sum() + w[1:-1, 0].sum() + w[1:-1, -1].sum())
        if edge > self.edge_mass:
            return Fix.no_fix(
                t, f"at the edge: {edge:.0%} of the posterior on the grid's border (truth may be outside)", self.name
            )
        lat, lon = state.frame.to_latlon(mn, me_)
        return Fix(t, float(lat), float(lon), 0.5 * (C + C.T), True, "", float(state.updates), self.name)
