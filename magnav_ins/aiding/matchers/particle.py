"""Particle filters: MagNavigate (Shockley 2012, seed 003, ch. V; Raquet, Shockley & Fisher, seed 000, sec. 3.3)
and an INS-driven variant.

State per particle, in metres north/east of the initial position (a :class:`~._local.LocalFrame`):

* ``dynamics="gauss_markov"`` (MagNavigate): position, velocity and acceleration per axis; the acceleration is a
  first-order Gauss-Markov process ``da/dt = -a / tau + w`` with ``tau = 2 s`` and steady-state ``sigma = 5 m/s^2``
  (003 sec. 5.1), discretised exactly for ``a`` and by the trapezoid for ``v``, ``p`` (sub-steps of at most
  ``tau / 4``).
* ``dynamics="ins"``: particles move with the INS displacement between predictions (the trapezoid of the INS
  velocities of the priors handed to :meth:`ParticleFilter.predict`; velocities rather than positions so that a
  fuser's position corrections between two predictions do not move the cloud again) plus a random walk
  ``ins_sigma`` m/sqrt(s).

Initialisation: ``n_particles`` (500) uniform in a disc of ``init_radius_m`` (50 m) about the prior position
(003 sec. 5.1), or Gaussian from the prior covariance (``init="gaussian"``).
Road penalisation (003 sec. 5.2): with a ``road`` map (anything with ``nearest(lat, lon) -> (idx, dist, s)``, e.g.
:class:`~magnav_ins.maps.track.TrackMap`), every prediction multiplies the weights by
``N(d; 0, road_sigma_m^2)`` of the distance to the nearest road point (6 m).
Measurement update: ``measurement="field"`` weights by the Gaussian likelihood of the reading (scalar or 3-axis,
``z = [Bx, By, Bz]``) at each particle; ``"fix"`` runs ``fix_matcher`` (ML by default) on the reading with the
particle cloud as prior and weights by ``N(z = [pN, pE]; p, R)``. SIR: systematic resampling when the effective
sample size ``1 / sum w^2`` drops below ``resample_threshold * n_particles`` (default 0.5; 1.0 = every update, as
in the thesis), with roughening (``roughening``: a Gaussian kernel of Silverman's bandwidth ``h`` and Liu-West
shrinkage ``a = sqrt(1 - h^2)`` towards the mean, which keeps the cloud's mean and covariance; the covariance gets a
floor ``roughen_min_m^2``) against sample impoverishment when the likelihood is much sharper than the cloud.
Output: weighted mean and covariance -> :class:`Fix` ("no fix" when the last update was off the map, on a flat
map (the feature variability, Wang eq. 14, of a 9 x 9 stencil of half-width ``max(2 sigma_cloud, flat_window_m)``
about the cloud mean below ``min_variability`` reading sigmas) or had a NaN reading).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numba as nb
import numpy as np
from numpy.typing import NDArray

from ...core.errors import ConfigError
from ...core.protocols import FieldMap, MatchWindow
from ...core.types import FieldReadings, Fix, NavEstimate
from ._local import LocalFrame, feature_variability, map_components, sample_map

FloatArray = NDArray[np.float64]


@dataclass
class ParticleState:
    """Particles in metres north/east of ``frame``'s origin: ``pos``, ``vel``, ``acc`` (M, 2), log weights
    ``logw`` (M,) (normalised), time ``t`` s, height ``h`` m, the INS position of the last prior ``ins_ne`` (2,),
    the effective sample size ``neff``, the random generator ``rng`` driving the process noise, the reason of the last rejected update (``""`` if it was used)."""

    t: float
    frame: LocalFrame
    h: float
    pos: FloatArray
    vel: FloatArray
    acc: FloatArray
    logw: FloatArray
    ins_ne: FloatArray
    neff: float
    rng: np.random.Generator
    reason: str = "no update yet"
    resampled: int = 0
    extra: dict[str, float] = field(default_factory=dict)


@nb.njit(cache=True)
def _systematic_resample(w: FloatArray, u0: float) -> NDArray[np.int64]:
    """Systematic resampling indices for normalised weights ``w`` and one uniform ``u0`` in [0, 1)."""
    m = w.shape[0]
    idx = np.empty(m, dtype=np.int64)
    c = w[0]
    j = 0
    for i in range(m):
        u = (u0 + i) / m
        while u > c and j < m - 1:
            j += 1
            c += w[j]
        idx[i] = j
    return idx


def _normalise(logw: FloatArray) -> FloatArray:
    mx = np.max(logw)
    w = np.exp(logw - mx)
    return logw - mx - np.log(w.sum())


@dataclass
class ParticleFilter:
    """MagNavigate / INS-driven particle filter (module docstring)."""

    n_particles: int = 500
    dynamics: str = "gauss_markov"
    tau_s: float = 2.0
    accel_sigma: float = 5.0
    ins_sigma: float = 0.5
    init: str = "disc"
    init_radius_m: float = 50.0
    road: Any = None
    road_sigma_m: float = 6.0
    measurement: str = "field"
    fix_matcher: Any = None
    map_sigma: float = 0.0
    resample_threshold: float = 0.5
    min_variability: float = 0.5
    flat_window_m: float = 10.0
    roughening: bool = True
    roughen_min_m: float = 0.1
    name: str = "particle"

    def __post_init__(self) -> None:
        if not (isinstance(self.n_particles, int | np.integer) and self.n_particles >= 2):
            raise ConfigError(f"particle 'n_particles': expected an integer >= 2, got {self.n_particles!r}")
        if self.dynamics not in ("gauss_markov", "ins"):
            raise ConfigError(f"particle 'dynamics': expected 'gauss_markov' or 'ins', got {self.dynamics!r}")
        if self.init not in ("disc", "gaussian"):
            raise ConfigError(f"particle 'init': expected 'disc' or 'gaussian', got {self.init!r}")
        if self.measurement not in ("field", "fix"):
            raise ConfigError(f"particle 'measurement': expected 'field' or 'fix', got {self.measurement!r}")
        if not 0.0 <= self.resample_threshold <= 1.0:
            raise ConfigError(f"particle 'resample_threshold': expected 0..1, got {self.resample_threshold!r}")
        for key in ("tau_s", "accel_sigma", "ins_sigma", "init_radius_m", "road_sigma_m"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"particle '{key}': expected > 0, got {getattr(self, key)!r}")
        if self.measurement == "fix" and self.fix_matcher is None:
            from .likelihood import LikelihoodMatcher

            self.fix_matcher = LikelihoodMatcher(method="ml")

    # ------------------------------------------------------------------ recursion
    def initiate(self, prior: NavEstimate, rng: np.random.Generator) -> ParticleState:
        """Particles about the prior position (disc of ``init_radius_m`` or the prior covariance)."""
        nav = prior.nav
        frame = LocalFrame(float(nav.lat), float(nav.lon), 0.0)
        m = self.n_particles
        if self.init == "disc":
            r = self.init_radius_m * np.sqrt(rng.uniform(size=m))
            a = rng.uniform(0.0, 2 * np.pi, size=m)
            pos = np.column_stack([r * np.cos(a), r * np.sin(a)])
        else:
            pos = rng.multivariate_normal(np.zeros(2), np.asarray(prior.cov_ne, float), size=m)
        v0 = np.asarray(nav.v_n, float)[:2]
        vel = np.tile(v0, (m, 1))
        acc = np.zeros((m, 2))
        logw = np.full(m, -np.log(m))
        return ParticleState(float(nav.t), frame, float(nav.h), pos, vel, acc, logw, np.zeros(2), float(m), rng)

    def predict(self, state: ParticleState, prior: NavEstimate) -> ParticleState:
        """Move the particles to the prior's time (GM dynamics or the INS increment) and penalise off-road ones."""
        rng = state.rng
        nav = prior.nav
        dt = float(nav.t) - state.t
        pos, vel, acc = state.pos.copy(), state.vel.copy(), state.acc.copy()
        ins_n, ins_e = state.frame.to_ne(nav.lat, nav.lon)
        ins_ne = np.array([float(ins_n), float(ins_e)])
        m = len(pos)
        if dt > 0:
            if self.dynamics == "gauss_markov":
                nsub = max(1, int(np.ceil(dt / (0.25 * self.tau_s))))
                h = dt / nsub
                phi = np.exp(-h / self.tau_s)
                sd = self.accel_sigma * np.sqrt(1.0 - phi**2)
                for _ in range(nsub):
                    a_new = phi * acc + sd * rng.standard_normal((m, 2))
                    pos += vel * h + (2.0 * acc + a_new) * h * h / 6.0
                    vel += 0.5 * (acc + a_new) * h
                    acc = a_new
            else:
                v_now = np.asarray(nav.v_n, float)[:2]
                step = 0.5 * (state.vel.mean(axis=0) + v_now) * dt  # trapezoid of the INS velocity
                pos += step + self.ins_sigma * np.sqrt(dt) * rng.standard_normal((m, 2))
                vel[:] = v_now
        logw = state.logw.copy()
        if self.road is not None:
            lat, lon = state.frame.to_latlon(pos[:, 0], pos[:, 1])
            _, dist, _ = self.road.nearest(lat, lon)
            logw += -0.5 * (np.asarray(dist, float) / self.road_sigma_m) ** 2
            logw = _normalise(logw)
        st = replace(state, t=float(nav.t), h=float(nav.h), pos=pos, vel=vel, acc=acc, logw=logw, ins_ne=ins_ne)
        return self._maybe_resample(st, rng)

    def update(self, state: ParticleState, readings: FieldReadings, fmap: FieldMap) -> ParticleState:
        """Weight by the last reading (``"field"``) or by a fix from ``fix_matcher`` (``"fix"``); SIR resampling."""
        rng = state.rng
        if len(readings) == 0:
            return replace(state, reason="no reading")
        try:
            if self.measurement == "field":
                loglik, reason = self._field_loglik(state, readings, fmap)
            else:
                loglik, reason = self._fix_loglik(state, readings, fmap)
        except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
            loglik, reason = None, f"map lookup failed: {exc}"
        if loglik is None:
            return replace(state, reason=reason)
        logw = _normalise(state.logw + loglik)
        return self._maybe_resample(replace(state, logw=logw, reason=""), rng, force_check=True)

    def to_fix(self, state: ParticleState) -> Fix:
        """Weighted mean and covariance of the particles, or "no fix" with the reason of the last update."""
        if state.reason:
            return Fix.no_fix(state.t, state.reason, self.name)
        w = np.exp(state.logw)
        mean = w @ state.pos
        d = state.pos - mean
        cov = (d * w[:, None]).T @ d
        lat, lon = state.frame.to_latlon(mean[0], mean[1])
        return Fix(state.t, float(lat), float(lon), cov, True, "", state.neff, self.name)

    # ------------------------------------------------------------------ internals
    def _field_loglik(
        self, state: ParticleState, readings: FieldReadings, fmap: FieldMap
    ) -> tuple[FloatArray | None, str]:
        z = np.asarray(readings.value, float).reshape(len(readings), -1)[-1]
        ncomp = map_components(fmap)
        if z.size != ncomp:
            return None, f"reading has {z.size} components, map has {ncomp}"
        if not np.all(np.isfinite(z)):
            return None, "reading is NaN"
        m = sample_map(fmap, state.frame, state.pos[:, 0], state.pos[:, 1], None).reshape(len(state.pos), ncomp)
        ok = np.all(np.isfinite(m), axis=1)
        if not np.any(ok):
            return None, "off the map: no particle on the map"
        s2 = float(readings.sigma) ** 2 + self.map_sigma**2
        w = np.exp(state.logw)
        mean = w @ state.pos
        sd = float(np.sqrt(np.sum(w @ (state.pos - mean) ** 2)))
        r = max(2.0 * sd, self.flat_window_m)
        g = np.linspace(-r, r, 9)
        gn, ge = np.meshgrid(mean[0] + g, mean[1] + g, indexing="ij")
        stencil = sample_map(fmap, state.frame, gn.ravel(), ge.ravel(), None).reshape(gn.size, ncomp)
        centre = stencil[gn.size // 2]
        spread = feature_variability(stencil, centre) if np.all(np.isfinite(centre)) else np.inf
        if spread < self.min_variability**2 * s2:  # Wang eq. 14 about the cloud mean
            return None, (
                f"flat map: feature variability {np.sqrt(spread):.3g} about the particle mean below "
                f"{self.min_variability:g} x reading sigma {np.sqrt(s2):.3g}"
            )
        loglik = np.full(len(m), -np.inf)
        loglik[ok] = -0.5 * np.sum((m[ok] - z) ** 2, axis=1) / s2
        return loglik, ""

    def _fix_loglik(
        self, state: ParticleState, readings: FieldReadings, fmap: FieldMap
    ) -> tuple[FloatArray | None, str]:
        w = np.exp(state.logw)
        mean = w @ state.pos
        d = state.pos - mean
        cov = (d * w[:, None]).T @ d + np.eye(2) * 1e-6
        rd = FieldReadings(readings.t[-1:], readings.value[-1:], readings.sigma, readings.kind)
        lat, lon = state.frame.to_latlon(np.array([mean[0]]), np.array([mean[1]]))
        win = MatchWindow(rd, lat, lon, np.array([state.h]), cov[None], (w @ state.vel)[None])
        fix = self.fix_matcher.match(win, fmap)
        if not fix.available:
            return None, fix.reason
        fn, fe = state.frame.to_ne(fix.lat, fix.lon)
        r = state.pos - np.array([float(fn), float(fe)])
        ri = np.linalg.inv(np.asarray(fix.cov_ne, float))
        return -0.5 * np.einsum("ij,jk,ik->i", r, ri, r), ""

    def _maybe_resample(
        self, state: ParticleState, rng: np.random.Generator, force_check: bool = False
    ) -> ParticleState:
        w = np.exp(state.logw)
        neff = float(1.0 / np.sum(w * w))
        m = len(w)
        if force_check and neff < self.resample_threshold * m + 1e-9:
            idx = _systematic_resample(w, float(rng.uniform()))
            pos = state.pos[idx]
            if self.roughening:  # regularised resampling with Liu-West shrinkage: keeps the mean and covariance
                mean = w @ state.pos
                d = state.pos - mean
                cov = (d * w[:, None]).T @ d + np.eye(2) * self.roughen_min_m**2
                h2 = (4.0 / (m * 4.0)) ** (2.0 / 6.0)  # Silverman bandwidth^2 for d = 2
                a = np.sqrt(1.0 - h2)
                jitter = rng.multivariate_normal(np.zeros(2), h2 * cov, size=m)
                pos = mean + a * (pos - mean) + jitter
            return replace(
                state,
                pos=pos,
                vel=state.vel[idx],
                acc=state.acc[idx],
                logw=np.full(m, -np.log(m)),
                neff=neff,
                resampled=state.resampled + 1,
            )
        return replace(state, neff=neff)
