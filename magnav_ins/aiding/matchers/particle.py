"""Particle filters: MagNavigate (Shockley 2012, seed 003, ch. V; Raquet, Shockley & Fisher, seed 000, sec. 3.3)
and an INS-driven variant, with a likelihood that knows the map's error and fixes that carry only new information.

State per particle, in metres north/east of a :class:`~._local.LocalFrame` about the prior the cloud was drawn from:

* ``dynamics="gauss_markov"`` (MagNavigate): position, velocity and acceleration per axis; the acceleration is a
  first-order Gauss-Markov process ``da/dt = -a / tau + w`` with ``tau = 2 s`` and steady-state ``sigma = 5 m/s^2``
  (003 sec. 5.1), discretised exactly for ``a`` and by the trapezoid for ``v``, ``p`` (sub-steps of at most
  ``tau / 4``).
* ``dynamics="ins"``: particles move with the INS displacement between predictions (the trapezoid of the INS
  velocities of the priors handed to :meth:`ParticleFilter.predict`; velocities rather than positions so that a
  fuser's position corrections between two predictions do not move the cloud again) plus each particle's own INS
  velocity error ``dv`` (drawn with the position from the prior's joint position / velocity covariance, constant
  between fixes: over tens of seconds the INS velocity error is a bias, not white noise) plus a random walk
  ``ins_sigma`` m/sqrt(s).

Initialisation: ``n_particles`` (500) from the prior's covariance (``init="gaussian"``, the default: the cloud
must cover where the fuser thinks it may be), or uniform in a disc of ``init_radius_m`` (50 m) about the prior
position as in the thesis (``init="disc"``, 003 sec. 5.1). The particles' velocity is the prior's, or zero with
``start_at_rest`` (the thesis: "with zero velocity and acceleration"; the cloud's moments without readings then
start at rest too). A Gaussian draw is moment-matched (shifted and scaled so
that its sample mean and covariance are exactly the prior's), so that the fix below is not made of sampling noise.
Road penalisation (003 sec. 5.2): with a ``road`` map (anything with ``nearest(lat, lon) -> (idx, dist, s)``, e.g.
:class:`~magnav_ins.maps.track.TrackMap`), every prediction multiplies the weights by
``N(d; 0, road_sigma_m^2)`` of the distance to the nearest road point (6 m), a likelihood of its own: the cloud is
resampled after it when its effective sample size falls below half the particles (without that, a cloud whose reading updates are skipped, e.g. off the map,
degenerates to one particle).

Measurement update (``measurement="field"``). A reading is ``z = m(x) + c + b(x) + v``: the map at the particle,
an unknown level offset ``c`` between readings and map (levelling, diurnal variation, the platform's own field:
the tie lines of the Osborne survey sit 17-30 nT off its flight lines), the map error ``b`` and the sensor noise
``v`` (``readings.sigma``). The map error has the 1-sigma of the map's error layer where the cloud is (its weighted
mean over the particles, one value per reading for the whole cloud: a variance per particle would make the
likelihood's normalisation reward the particles where the layer is small, near the survey's lines, whatever the
readings say), or ``map_sigma``, or the stated default (:func:`~.map_error.resolve_map_error`), and is correlated
along the track:
each particle carries a two-state Kalman filter for ``(c, b)`` (Rao-Blackwellised: the weights use the marginal
likelihood ``N(z - m(x); c_hat + b_hat, S)``), with ``b`` a first-order Gauss-Markov process in the distance the
particle moved (:func:`~.map_error.markov_coefficient`: readings inside one correlation length share their map
error and are not counted as independent evidence). ``level_sigma``: None (default) = the level is unknown (a
diffuse prior, the recursive form of a likelihood matcher's ``demean``), 0 = no offset, else its 1-sigma. The first
reading after an initiation then only sets the level. ``measurement="fix"`` runs ``fix_matcher`` (ML by default)
on the reading with the particle cloud as prior and weights by ``N(z = [pN, pE]; p, R)``.

SIR: systematic resampling when the effective sample size ``1 / sum w^2`` drops below
``resample_threshold * n_particles`` (default 0.5; 1.0 = every update, as in the thesis), with roughening
(``roughening``: a Gaussian kernel of Silverman's bandwidth ``h`` and Liu-West shrinkage ``a = sqrt(1 - h^2)``
towards the mean, which keeps the cloud's mean and covariance; the covariance gets a floor ``roughen_min_m^2``)
against sample impoverishment when the likelihood is much sharper than the cloud.

Output (:meth:`ParticleFilter.to_fix`).

* ``fix_output="increment"`` (default): the information the readings added since the cloud was drawn, as an
  equivalent measurement of the current position (the "tracklet" of distributed tracking; Drummond 1997): with the
  cloud's weighted moments ``(mu, P)`` and the moments ``(mu0, P0)`` the cloud would have without any reading (the
  prior's Gaussian, propagated by the same linear dynamics), ``R = (P^-1 - P0^-1)^-1``,
  ``z = R (P^-1 mu - P0^-1 mu0)``. A fuser can take it as an independent measurement: the prior it came from is
  divided out. After a fix is issued the next :meth:`ParticleFilter.predict` draws a new cloud from the fuser's
  estimate (which holds the fix if the fuser accepted it), so no reading is ever reported twice. Feeding the
  cloud's posterior itself to a fuser at every reading (what this filter did before) counts the prior and every
  earlier reading again at each fix: on the Osborne tie line 10152 (tactical IMU, real readings) that took the
  filter to 28 km error with 1 m sigmas.
* ``fix_output="posterior"``: the cloud's weighted mean and covariance at every request, the thesis' stand-alone
  navigator (Shockley 003 sec. 5.1: "the navigation solutions presented here are the weighted particle mean at each
  epoch"; the cloud is never re-drawn). This is a navigation solution, not a measurement for another filter (it
  holds the prior and every earlier reading): pair it with the ``solution`` fuser
  (:mod:`magnav_ins.aiding.fusion.solution`), which reports it as the estimate. It is issued also after an update
  that was skipped (off the map, flat map, NaN reading: the predicted cloud is then the solution) and when the cloud
  is multi-modal (its covariance then spans the modes); only a collapsed cloud gives "no fix".

"No fix" in the increment mode (with the reason, and the cloud is kept) when the last update was off the map, on a flat map (the feature
variability, Wang eq. 14, of a 9 x 9 stencil of half-width ``max(2 sigma_cloud, flat_window_m)`` about the cloud
mean below ``min_variability`` sensor sigmas) or had a NaN reading; when the cloud is not unimodal (more than
``ambiguity_mass`` of its weight more than 3 sigma, Mahalanobis, from its mean: a Gaussian has 1.1 %); and in the
increment mode when the readings did not add information in both directions (``P^-1 - P0^-1`` not positive
definite) or the fix 1-sigma would exceed ``max_fix_sigma_m`` (default: twice the prior's own 1-sigma).

The fix covariance contains: sensor noise, the map error (variance and along-track correlation), the unknown level,
the INS velocity error and random walk over the time since the cloud was drawn (all through the particles'
weights), the cloud's shape (multi-modality beyond the ambiguity limit gives no fix), the readings' rival modes in the prior
region ("Rival modes" below), the readings' forecast misfit
(the covariance scaled by the NIS per reading when it exceeds its 99 % quantile), and a floor: the increment is never
tighter than the Cramer-Rao bound of its readings (:func:`_fisher_bound`: the map gradients along the cloud's track,
the level projected out, the correlated map error counted by the effective number of readings). The cloud's
weighted moments alone were up to 5x tighter than that bound on a featureless stretch of the Rio tie lines.

Rival modes (increment mode, INS dynamics; ``rival_grid`` nodes a side, default 101, 0 = off; ``rival_peak_ratio``,
default ``RIVAL_PEAK_RATIO`` = 0.01). Resampling keeps the cloud where the prior and the readings agree best and
forgets every other place the readings fit: on a nearly one-dimensional field (the Rio tie lines) a cloud spread
km along the track by the INS velocity error settled on a wrong along-track mode 5-9 km off and reported it with a
0.6-3.3 km sigma (fix NEES 38-93). At each fix attempt the readings since the cloud was drawn (at most
``RIVAL_MAX_READINGS``, evenly thinned, each variance scaled by the thinning) are matched as a rigid track (the
cloud's prior mean at each reading) against a grid of offsets along the principal axes of the cloud's current prior
position covariance, out to the prior-consistency radius (its 99.9 % region): a Gaussian likelihood with the level
of each component marginalised and, per reading, variance = sensor + map error counted ``ell / ds`` times (readings
within one correlation length share their map error) + the misfit of the INS velocity error between the reading
and the fix (``|g|^2 tr(P_vv) dt^2 / 2``, ``P_vv`` the cloud's velocity covariance without its inflation: the
particles' tracks are rigid only up to it), times the cloud's prior (as bayes_grid's ``rivals_of = "posterior"``:
a mode the prior all but excludes is no rival). Its local maxima at least 3 increment sigmas (and two nodes) away
holding at least ``rival_peak_ratio`` of the best density are the rivals: their second moment about the increment,
each weighted by its share of the peaks' density (:func:`._batch.rival_moment`, as ICCP's and TERCOM's
``cover_rivals``); and since a wrong mode need not be a separate peak (on Rio 9180 the truth sat 4-8 km along the
line on the same broad hill as the fix, 0.2-1.1 nats below its top), the second moment about the increment of the
grid posterior's mass more than 3 increment sigmas away. The increment's covariance gets the larger of the two
(their Loewner maximum). A fix whose cover takes it beyond ``max_fix_sigma_m`` is a "no fix"; with rival peaks its
reason starts with "ambiguous: N rival mode(s)". A cloud whose increment already spans the posterior is unchanged.
On a field that repeats every 40 m along the track (``tests/test_matchers_map_error.py``) without the check 12 of
24 issued fixes sat a period or more off, mean NEES 7,069; with it 16 were issued (8 a period or more off,
covered), NEES 1.2 (rival peaks only: 17, NEES 2.6; rivals of the likelihood alone, without the prior: 7, NEES 1.7).

Map faults (increment mode; ``fault_window`` readings, default 20, 0 = off; ``fault_probability``, default 0.999).
Where the map is wrong over a stretch (Rio tie line 9160: up to 500 nT off over ~2 km, 1.7-9x its error layer) the
readings pull the cloud to wherever the map happens to fit them, and the increment passes every check above: its
misfit over all its readings is diluted by the good ones, the wrong place is within the prior's 99.9 % region, the
cloud is unimodal there. While the cloud is still being pulled, though, the readings miss its forecast: the
predictive NIS of each reading (the cloud's mixture forecast, the statistic of the misfit rule) summed over the last
``fault_window`` readings is chi-square with as many degrees of freedom when the model holds (it is conservative:
the mixture forecast is wider than a Gaussian's, 0.01-0.15 per reading on the Rio tie lines) and jumped to 2-26 per
reading (15 s means) inside 9160's fault zones. Above its ``fault_probability`` quantile the cloud is condemned: it
is re-drawn from the fuser's estimate at the next prediction (the readings it holds, good and bad, are never
reported), and the next :meth:`ParticleFilter.to_fix` is a "no fix" whose reason starts with "map fault"
(``ParticleState.faults`` counts them). It cannot see a fault the cloud fits from the start (a wrong place that
matches the corrupted readings as well as the right one matches good ones): there the fix stays wrong (Rio 9180 and
9220, README "real-data suite").

Sparse draws (increment mode). Where the prior is kilometres wide (a tactical INS after minutes without a fix) and
the readings' likelihood tens of metres wide, the draws sample the likelihood's peaks sparsely: each peak's weight
is that of the draw that happened to land nearest to it, several peaks fit, and within a few resamplings the cloud
sits on one of them - unimodal, its increment tight, as likely the wrong peak as the right one (the resampling's
Liu-West kernel helps: on a multi-modal cloud its covariance is the spread between the modes, so each resampling
scatters the copies off them). A fix right after an attempt refused as "not unimodal" was exactly that (Osborne tie
line 5817 at 50 m/s, tactical, run 0: 3.6 km off with 210 / 670 m sigmas, NEES 36, after 14 resamplings in 30
readings; the same run with 5,000 particles issued no such fix and had NEES 1.0 instead of 6.6). Each particle
carries the draw it descends from (``ParticleState.anc``); the cloud's weight then rests on few draws (the
ancestral effective sample size ``1 / sum_a W_a^2``, :func:`ancestral_ess`: 2-7 of 500 for such fixes on the
Osborne tie lines). Below ``min_draws`` (default :data:`MIN_DRAWS_INS` for ``dynamics="ins"``, 0 = off for the
Gauss-Markov filter, whose particles re-explore by their own acceleration noise between readings while INS-driven
ones move rigidly with the INS) the attempt is "unresolved" and the cloud condemned - where the prior (largest
1-sigma) is wider than :data:`SPARSE_PRIOR_ELLS` correlation lengths of the map error: a narrower prior has no room
for two places the readings fit independently, and there a cloud on few draws is a sharp likelihood well sampled
(the synthetic flights of the matcher tests, 15 m priors over 21-35 m correlation lengths: honest fixes, 60 % of
them refused without this condition; the Osborne failures above: priors 1.4-9.5 correlation lengths wide). On a map that repeats itself
every 600 m (``tests/test_particle_ambiguity.py``, 30 flights, 3 attempts each) the filter then issues no fix that
picks one copy; without it, 68 of 90 attempts did.

Re-draws. A condemned cloud (too few draws, sub-clouds apart, a map fault) is re-drawn at the next prediction with
twice the particles of the last one (at most ``max_particle_factor`` times ``n_particles``), back to
``n_particles`` after the next issued fix: a prior too wide for its draws gets more of them. After ``j`` map faults
in a row the prior is also widened by ``2^j`` (at most ``max_lost_inflation``): when every cloud drawn from the
fuser's estimate misses its readings, the fuser has lost track and another cloud from the same prior cannot find
the truth (Osborne 10156 at 50 m/s, tactical: the monitor condemned cloud after cloud drawn 3-5 km from the truth).
The increment divides out the prior the cloud was drawn from, so a wider draw gives a weaker fix, not a biased one.

Sub-clouds (``subclouds``, default 1 = off). The cloud as ``S`` independent clouds (the descendants of draws ``k``,
``k + S``, ...), each resampled and roughened on its own and weighted equally; an attempt whose sub-clouds settled
further apart than chi-square(2) 99.9 % in the sum of their covariances is "ambiguous" and the cloud condemned.
Where several places fit, the sub-clouds find different ones unless all pick the same (chance ``sum p_i^S``). On
the 600 m repeating map 2 sub-clouds issued 7 one-copy fixes in 90 attempts, 3 none; on the Osborne tactical group
(suite, 132 runs) 2-4 sub-clouds gave NEES 3.0-3.2 against 2.5 with ``min_draws``, and 3 failed the Gauss-Markov
filter's synthetic honesty test (NEES 3.9: 167 particles a sub-cloud are too few).
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
from ..gating import chi2_threshold
from ._batch import RIVAL_PEAK_RATIO, loewner_max, rival_moment
from ._local import LocalFrame, feature_variability, map_components, sample_map
from .map_error import INTEGRAL_SCALE, MapErrorModel, markov_coefficient, misfit_factor, resolve_map_error

FloatArray = NDArray[np.float64]

#: chi-square (2 dof) of the 3-sigma Mahalanobis radius used by the cloud's unimodality test; a Gaussian cloud
#: holds exp(-9/2) = 1.1 % of its weight beyond it
_CLOUD_TAIL_CHI2 = 9.0
#: an increment is issued only if the cloud's mean and the increment are within the 99.9 % region (chi-square 2 dof)
#: of the prior the cloud was drawn from: otherwise the likelihood peaks where there are no particles
_PRIOR_CONSISTENCY_CHI2 = 13.8155
#: nodes a side of the rival-mode grid (``rival_grid``, INS dynamics): 101 spans a 25 km prior region (Rio's
#: tactical priors after 10 minutes) at 250 m, the Rio map's node spacing
RIVAL_GRID = 101
#: at most this many readings (evenly thinned, their variances scaled to keep the total information) enter the
#: rival check: ~0.05 s of map lookups per fix attempt on a 101 x 101 grid
RIVAL_MAX_READINGS = 100
#: the default ``min_draws`` of INS-driven particles (module docstring, "Sparse draws")
MIN_DRAWS_INS = 10.0
#: the sparse-draws rule holds where the cloud's prior is wider than this many correlation lengths of the map error
SPARSE_PRIOR_ELLS = 2.0
#: the cloud's sub-clouds disagree (no fix, re-drawn) when two means are further apart than this Mahalanobis^2
#: (chi-square 2 dof, 99.9 %) in the sum of their covariances
_SUBCLOUD_CHI2 = 13.8155
#: after the road penalty the cloud is resampled when its effective sample size drops below this fraction (at most
#: ``resample_threshold``): a likelihood applied at every prediction would otherwise, resampled each time, wear the
#: cloud down to a few particles between readings
_ROAD_RESAMPLE = 0.5


@dataclass(frozen=True)
class RivalTrack:
    """The readings since the cloud was drawn, for the rival-mode check (module docstring, "Rival modes"): ``t0``
    s the time the cloud was drawn; per reading its time ``t`` s, value ``z`` (c,), its variance ``var`` (map
    unit^2: sensor + map error) in the rigid-offset likelihood, the squared map gradient ``g2`` (unit^2/m^2) at the
    cloud and the cloud's prior mean ``centre`` (2,) m north/east of the cloud's frame then; ``fmap`` the map they
    were weighted against."""

    t0: float
    t: tuple[float, ...] = ()
    z: tuple[FloatArray, ...] = ()
    var: tuple[float, ...] = ()
    g2: tuple[float, ...] = ()
    centre: tuple[FloatArray, ...] = ()
    fmap: Any = None

    def add(self, t: float, z: FloatArray, var: float, g2: float, centre: FloatArray, fmap: FieldMap) -> RivalTrack:
        return RivalTrack(
            self.t0, (*self.t, t), (*self.z, z), (*self.var, var), (*self.g2, g2), (*self.centre, centre), fmap
        )


@dataclass
class ParticleState:
    """Particles in metres north/east of ``frame``'s origin: ``pos``, ``vel``, ``acc`` (M, 2), the INS velocity
    error ``dv`` (M, 2) (``dynamics="ins"``), log weights ``logw`` (M,) (normalised), time ``t`` s, height ``h`` m,
    the INS position of the last prior ``ins_ne`` (2,), the effective sample size ``neff``, the random generator
    ``rng``, the reason of the last rejected update (``""`` if it was used); ``recent_nis`` the forecast NIS and
    its degrees of freedom of the last readings (the map-fault monitor's window), ``fault`` a detected map fault
    not yet reported by :meth:`ParticleFilter.to_fix`, ``faults`` their count; ``anc`` (M,) the draw each particle
    descends from (its sub-cloud is ``anc % subclouds``), ``redraws`` the clouds condemned in a row and ``lost`` the
    map faults in a row since the last issued fix (module docstring, "Re-draws").

    Per particle and field component, the level / map-error filter: means ``lev`` and ``err`` (M, c) and
    covariance ``p_ll``, ``p_le``, ``p_ee`` (M, c); ``lev_set`` False until the first reading has set an unknown
    level. ``prior_mean`` (d,) and ``prior_cov`` (d, d) are the cloud's moments without readings (the linear
    state: ``[pN, pE, dvN, dvE]`` for INS dynamics, ``[pN, vN, aN, pE, vE, aE]`` for Gauss-Markov); ``issued`` is
    set by :meth:`ParticleFilter.to_fix` when it issues an increment (the next prediction re-draws the cloud)."""

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
    dv: FloatArray | None = None
    lev: FloatArray | None = None
    err: FloatArray | None = None
    p_ll: FloatArray | None = None
    p_le: FloatArray | None = None
    p_ee: FloatArray | None = None
    lev_set: bool = False
    prior_mean: FloatArray | None = None
    prior_cov: FloatArray | None = None
    issued: bool = False
    readings: int = 0
    p_vv: FloatArray | None = None
    fisher: FloatArray | None = None
    recent_nis: tuple[tuple[float, float], ...] = ()
    fault: str = ""
    faults: int = 0
    rivals: RivalTrack | None = None
    anc: NDArray[np.int64] | None = None
    redraws: int = 0
    lost: int = 0


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


def _moment_match(x: FloatArray, mean: FloatArray, cov: FloatArray) -> FloatArray:
    """Affine transform of the sample ``x`` (M, d) so that its mean and (1/M) covariance are exactly ``mean``,
    ``cov`` (d, d)."""
    d = x - x.mean(axis=0)
    s = d.T @ d / len(x)
    try:
        ls = np.linalg.cholesky(s)
        lc = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        return x
    return mean + (lc @ np.linalg.solve(ls, d.T)).T


def _loewner_max(a: FloatArray, b: FloatArray) -> FloatArray:
    """:func:`._batch.loewner_max` of two covariances (2, 2), either of which may be zero (no rivals, no far
    mass): then the other."""
    if float(np.trace(b)) <= 0:
        return a
    if float(np.trace(a)) <= 0:
        return b
    return loewner_max(a, b)


def _psd_part(a: FloatArray) -> FloatArray:
    """The positive semi-definite part of a symmetric matrix (negative eigenvalues set to 0)."""
    a = 0.5 * (a + a.T)
    w, v = np.linalg.eigh(a)
    return (v * np.maximum(w, 0.0)) @ v.T


def _fisher_step(
    state: ParticleState,
    fmap: FieldMap,
    lat: FloatArray,
    lon: FloatArray,
    w: FloatArray,
    sm2: FloatArray,
    s2v: float,
    ell_m: float,
) -> FloatArray | None:
    """The Fisher information sums of the readings since the cloud was drawn, with this reading added:
    ``[readings, sum g (2), sum g g' (2x2 flattened), distance m, ell m, sum sigma_map^2, sigma_sensor^2]`` (11,),
    ``g`` the map gradient (unit/m, north/east; components summed) averaged over the cloud with its weights ``w``
    (M,) at the particles ``lat``, ``lon`` (rad), ``sm2`` (M,) the map error variance there. None for a map without
    gradients (a road map's points)."""
    grad = getattr(fmap, "gradient_ne", None)
    if grad is None:
        return None
    try:
        g = np.asarray(grad(lat, lon), float)
    except (ValueError, TypeError):
        return None
    g = g.reshape(len(lat), -1, 2)
    ok = np.all(np.isfinite(g), axis=(1, 2)) & np.isfinite(sm2)
    if not np.any(ok):
        return state.fisher
    wk = w[ok] / max(float(w[ok].sum()), 1e-300)
    f = np.zeros(11) if state.fisher is None else state.fisher.copy()
    f[0] += 1.0
    f[1:3] += np.einsum("m,mci->i", wk, g[ok])
    f[3:7] += np.einsum("m,mci,mcj->ij", wk, g[ok], g[ok]).ravel()
    f[7] += float(state.extra.get("moved_m", 0.0)) if state.fisher is not None else 0.0
    f[8] = ell_m
    f[9] += float(wk @ sm2[ok])
    f[10] = s2v
    return f


def _fisher_bound(fisher: FloatArray | None, level_unknown: bool) -> FloatArray | None:
    """Fisher information (2, 2) m^-2 about the position of the readings since the cloud was drawn, from
    :func:`_fisher_step`'s sums: ``(sum g g' - [level unknown] (sum g)(sum g)' / n) / s2`` with the per-reading
    variance ``s2 = sigma_sensor^2 + mean sigma_map^2 n / n_eff``: the map error is correlated over its correlation
    length ``ell``, so ``n`` readings spread over a distance ``D`` hold at most ``n_eff = 1 + D / (ell sqrt(pi) /
    2)`` independent map errors (as :func:`~.map_error.markov_coefficient` counts them). Its inverse is the
    Cramer-Rao bound of a position estimated from these readings (no unbiased estimate has a smaller covariance),
    with the correlated map error counted by the effective number of readings (exact for a constant gradient, the
    same count as :func:`~.map_error.effective_count`); None when unknown."""
    if fisher is None or fisher[0] < 1:
        return None
    n = float(fisher[0])
    j = fisher[3:7].reshape(2, 2).copy()
    if level_unknown:
        j -= np.outer(fisher[1:3], fisher[1:3]) / n
    n_eff = n
    if np.isfinite(fisher[8]) and fisher[8] > 0:
        n_eff = min(n, 1.0 + float(fisher[7]) / (INTEGRAL_SCALE * float(fisher[8])))
    s2 = float(fisher[10]) + float(fisher[9]) / n * n / max(n_eff, 1.0)
    return _psd_part(j / s2)


def _cramer_rao_floor(r: FloatArray, fisher: FloatArray | None) -> FloatArray:
    """``r`` (2, 2) m^2 raised, direction by direction, to at least the Cramer-Rao bound ``fisher^-1``: in the
    coordinates where ``r`` is the identity, the information ``fisher`` becomes ``M``; the fix's information (the
    identity) is capped at ``M``'s eigenvalues. A direction the readings cannot inform (eigenvalue 0) gets a
    variance 1e12 times its own (the fix then fails its sigma test)."""
    if fisher is None:
        return r
    w, v = np.linalg.eigh(0.5 * (r + r.T))
    if np.any(w <= 0):
        return r
    half = (v * np.sqrt(w)) @ v.T  # r^(1/2)
    mu, u = np.linalg.eigh(half @ fisher @ half)
    cap = np.clip(mu, 1e-12, 1.0)
    out = half @ (u / cap) @ u.T @ half
    return 0.5 * (out + out.T)


def _gm_transition(h: float, tau: float, sigma: float) -> tuple[FloatArray, FloatArray]:
    """One Gauss-Markov sub-step of length ``h`` (s) as the particles take it, per axis on ``[p, v, a]``:
    ``a' = phi a + w``, ``p' = p + v h + (2 a + a') h^2 / 6``, ``v' = v + (a + a') h / 2`` with
    ``phi = exp(-h / tau)``, ``w ~ N(0, sigma^2 (1 - phi^2))``. Returns (F (3, 3), Q (3, 3))."""
    phi = np.exp(-h / tau)
    sd = sigma * np.sqrt(1.0 - phi**2)
    f = np.array([[1.0, h, (2.0 + phi) * h * h / 6.0], [0.0, 1.0, (1.0 + phi) * h / 2.0], [0.0, 0.0, phi]])
    g = np.array([h * h / 6.0, h / 2.0, 1.0]) * sd
    return f, np.outer(g, g)


@dataclass
class ParticleFilter:
    """MagNavigate / INS-driven particle filter (module docstring).

    Parameters (SI; field values in the map's unit): ``n_particles``; ``dynamics`` "gauss_markov" | "ins";
    ``tau_s``, ``accel_sigma`` (Gauss-Markov acceleration); ``ins_sigma`` INS random walk (m/sqrt(s));
    ``ins_velocity`` draw each particle's INS velocity error from the prior's covariance; ``init`` "gaussian" |
    "disc" and ``init_radius_m``; ``road``, ``road_sigma_m``; ``measurement`` "field" | "fix" and
    ``fix_matcher``; ``map_sigma`` (map error 1-sigma overriding the map's layer; 0 = from the map) and
    ``map_correlation_m`` (overrides the map's correlation length); ``level_sigma`` (None = unknown level);
    ``resample_threshold``, ``roughening``, ``roughen_min_m``; ``min_variability`` and ``flat_window_m`` (flat-map
    test); ``fix_output`` "increment" | "posterior"; ``ambiguity_mass``; ``max_fix_sigma_m``; ``start_at_rest``
    (particles start with zero velocity); ``fault_window`` (readings, 0 = off) and ``fault_probability``: the
    map-fault monitor (module docstring, "Map faults"); ``rival_grid`` (nodes a side; None = 101 with INS dynamics,
    0 = off, the Gauss-Markov default) and ``rival_peak_ratio``: the rival-mode check ("Rival modes");
    ``subclouds`` (1 = off), ``max_particle_factor``, ``max_lost_inflation``, ``min_draws`` (0 = off): module
    docstring, "Sub-clouds" and "Re-draws"."""

    n_particles: int = 500
    dynamics: str = "gauss_markov"
    tau_s: float = 2.0
    accel_sigma: float = 5.0
    ins_sigma: float = 0.5
    ins_velocity: bool = True
    init: str = "gaussian"
    init_radius_m: float = 50.0
    road: Any = None
    road_sigma_m: float = 6.0
    measurement: str = "field"
    fix_matcher: Any = None
    map_sigma: float = 0.0
    map_correlation_m: float | None = None
    level_sigma: float | None = None
    resample_threshold: float = 0.5
    min_variability: float = 0.5
    flat_window_m: float = 10.0
    roughening: bool = True
    roughen_min_m: float = 0.1
    fix_output: str = "increment"
    ambiguity_mass: float = 0.05
    max_fix_sigma_m: float | None = None
    prior_inflation: float = 1.5
    start_at_rest: bool = False
    fault_window: int = 20
    fault_probability: float = 0.999
    rival_grid: int | None = None
    rival_peak_ratio: float = RIVAL_PEAK_RATIO
    max_particle_factor: int = 8
    subclouds: int = 1
    min_draws: float | None = None
    max_lost_inflation: float = 8.0
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
        if self.fix_output not in ("increment", "posterior"):
            raise ConfigError(f"particle 'fix_output': expected 'increment' or 'posterior', got {self.fix_output!r}")
        if not 0.0 <= self.resample_threshold <= 1.0:
            raise ConfigError(f"particle 'resample_threshold': expected 0..1, got {self.resample_threshold!r}")
        for key in ("tau_s", "accel_sigma", "ins_sigma", "init_radius_m", "road_sigma_m", "prior_inflation"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"particle '{key}': expected > 0, got {getattr(self, key)!r}")
        if self.map_sigma < 0 or (self.level_sigma is not None and self.level_sigma < 0):
            raise ConfigError("particle: map_sigma and level_sigma must be >= 0")
        if not 0.0 < self.ambiguity_mass <= 1.0:
            raise ConfigError(f"particle 'ambiguity_mass': expected 0 < x <= 1, got {self.ambiguity_mass!r}")
        if not (isinstance(self.fault_window, int | np.integer) and self.fault_window >= 0):
            raise ConfigError(f"particle 'fault_window': expected an integer >= 0, got {self.fault_window!r}")
        chi2_threshold(1, self.fault_probability)  # validates the probability (a clear error)
        if self.rival_grid is None:  # the INS-driven cloud's tracks are the INS track's, rigid up to its velocity error
            self.rival_grid = RIVAL_GRID if self.dynamics == "ins" else 0
        if isinstance(self.rival_grid, float) and self.rival_grid.is_integer():  # a TOML / JSON number
            self.rival_grid = int(self.rival_grid)
        if not (isinstance(self.rival_grid, int | np.integer) and (self.rival_grid == 0 or self.rival_grid >= 5)):
            raise ConfigError(f"particle 'rival_grid': expected 0 (off) or an integer >= 5, got {self.rival_grid!r}")
        if not 0.0 < self.rival_peak_ratio <= 1.0:
            raise ConfigError(f"particle 'rival_peak_ratio': expected 0 < x <= 1, got {self.rival_peak_ratio!r}")
        if not (isinstance(self.max_particle_factor, int | np.integer) and self.max_particle_factor >= 1):
            raise ConfigError(
                f"particle 'max_particle_factor': expected an integer >= 1, got {self.max_particle_factor!r}"
            )
        if not (isinstance(self.subclouds, int | np.integer) and 1 <= self.subclouds <= self.n_particles // 2):
            raise ConfigError(
                f"particle 'subclouds': expected an integer from 1 to n_particles / 2, got {self.subclouds!r}"
            )
        if self.min_draws is None:  # module docstring, "Sparse draws"
            self.min_draws = MIN_DRAWS_INS if self.dynamics == "ins" else 0.0
        if not self.min_draws >= 0:
            raise ConfigError(f"particle 'min_draws': expected >= 0, got {self.min_draws!r}")
        if not self.max_lost_inflation >= 1:
            raise ConfigError(f"particle 'max_lost_inflation': expected >= 1, got {self.max_lost_inflation!r}")
        if self.measurement == "fix" and self.fix_matcher is None:
            from .likelihood import LikelihoodMatcher

            self.fix_matcher = LikelihoodMatcher(method="ml")

    # ------------------------------------------------------------------ recursion
    def initiate(self, prior: NavEstimate, rng: np.random.Generator) -> ParticleState:
        """A cloud about the prior position (the prior covariance, or a disc of ``init_radius_m``), with its
        moments without readings (``prior_mean``, ``prior_cov``) for the increment."""
        return self._draw(prior, rng, 0, 0)

    def _draw(self, prior: NavEstimate, rng: np.random.Generator, redraws: int, lost: int) -> ParticleState:
        """:meth:`initiate` after ``redraws`` clouds in a row were condemned without issuing a fix (their draws
        too sparse for the readings, module docstring "Re-draws"): ``n_particles`` times ``2^redraws`` (at most
        ``max_particle_factor``), and after ``lost`` map faults in a row the prior widened by ``2^lost`` (at most
        ``max_lost_inflation``)."""
        nav = prior.nav
        frame = LocalFrame(float(nav.lat), float(nav.lon), 0.0)
        m = self.n_particles * min(2**redraws, self.max_particle_factor)
        P = np.asarray(prior.P, float)
        ps, vs = prior.layout["pos"], prior.layout["vel"]
        ip = [ps.start, ps.start + 1]
        iv = [vs.start, vs.start + 1]
        k2 = (self.prior_inflation * min(2.0**lost, self.max_lost_inflation)) ** 2
        c_pp = 0.5 * (P[np.ix_(ip, ip)] + P[np.ix_(ip, ip)].T) * k2
        c_vv = 0.5 * (P[np.ix_(iv, iv)] + P[np.ix_(iv, iv)].T)
        c_pv = P[np.ix_(ip, iv)] * k2
        vv_now = c_vv.copy()
        c_vv = c_vv * k2
        v0 = np.zeros(2) if self.start_at_rest else np.asarray(nav.v_n, float)[:2]
        if self.init == "disc":
            r = self.init_radius_m * np.sqrt(rng.uniform(size=m))
            a = rng.uniform(0.0, 2 * np.pi, size=m)
            pos = np.column_stack([r * np.cos(a), r * np.sin(a)])
            c_pp, c_pv = np.eye(2) * self.init_radius_m**2 / 4.0, np.zeros((2, 2))
        else:
            pos = None
        want_dv = self.dynamics == "ins" and self.ins_velocity
        if self.dynamics == "ins":
            cov4 = np.zeros((4, 4))
            cov4[:2, :2] = c_pp
            if want_dv:
                cov4[:2, 2:], cov4[2:, :2], cov4[2:, 2:] = c_pv, c_pv.T, c_vv
            if pos is None:
                x = rng.multivariate_normal(np.zeros(4), cov4, size=m, method="eigh")
                x = _moment_match(x, np.zeros(4), cov4 + np.eye(4) * 1e-12) if m > 8 else x
                pos, dv = x[:, :2], x[:, 2:]
            else:
                dv = rng.multivariate_normal(np.zeros(2), c_vv, size=m, method="eigh") if want_dv else np.zeros((m, 2))
            if not want_dv:
                dv = np.zeros((m, 2))
            prior_mean, prior_cov = np.zeros(4), cov4
            vel = np.tile(v0, (m, 1))
        else:
            cov6 = np.zeros((6, 6))  # [pN, vN, aN, pE, vE, aE]
            cov6[np.ix_([0, 3], [0, 3])] = c_pp
            if pos is None:
                pos = rng.multivariate_normal(np.zeros(2), c_pp, size=m, method="eigh")
                pos = _moment_match(pos, np.zeros(2), c_pp + np.eye(2) * 1e-12) if m > 4 else pos
            vel = np.tile(v0, (m, 1))
            dv = np.zeros((m, 2))
            prior_mean = np.array([0.0, v0[0], 0.0, 0.0, v0[1], 0.0])
            prior_cov = cov6
        acc = np.zeros((m, 2))
        logw = np.full(m, -np.log(m))
        st = ParticleState(float(nav.t), frame, float(nav.h), pos, vel, acc, logw, np.zeros(2), float(m), rng)
        st.dv = dv
        st.prior_mean, st.prior_cov = prior_mean, prior_cov
        st.p_vv = vv_now
        if self.init == "gaussian" and self.rival_grid and self.fix_output == "increment":
            st.rivals = RivalTrack(float(nav.t))
        st.anc = np.arange(m)
        st.redraws, st.lost = redraws, lost
        return st

    def _rival_track(
        self,
        state: ParticleState,
        fmap: FieldMap,
        z: FloatArray,
        fisher: FloatArray | None,
        s2v: float,
        sm2: float,
        err: MapErrorModel,
    ) -> RivalTrack | None:
        """The track with the reading ``z`` (c,) added at the cloud's prior mean: its variance is sensor ``s2v`` +
        map error ``sm2`` counted ``ell / ds`` times (readings ``ds`` apart within one correlation length ``ell``
        share their map error, as :func:`._batch.reading_variance`); ``|g|^2`` from the Fisher sums ``fisher``."""
        g = state.rivals
        if g is None or state.prior_mean is None:
            return g
        ell, ds = float(err.correlation_m), float(state.extra.get("moved_m", 0.0))
        temper = float(np.clip(ell / ds, 1.0, None)) if (np.isfinite(ell) and ell > 0 and ds > 0) else 1.0
        var = s2v + temper * sm2
        if not (np.isfinite(var) and var > 0):
            return g
        g2 = 0.0
        if fisher is not None:
            old = state.fisher[3:7] if state.fisher is not None else np.zeros(4)
            g2 = max(float(fisher[3] - old[0] + fisher[6] - old[3]), 0.0)  # |g|^2 of this reading
        ip = [0, 1] if self.dynamics == "ins" else [0, 3]
        return g.add(
            state.t, np.asarray(z, float).copy(), float(var), g2, np.asarray(state.prior_mean[ip]).copy(), fmap
        )

    def _rival_cover(
        self, state: ParticleState, d_fix: FloatArray, r: FloatArray, p0: FloatArray
    ) -> tuple[FloatArray, int]:
        """Covariance (2, 2) m^2 covering the rival modes of the readings' rigid-offset likelihood about the
        increment's offset ``d_fix`` (2,) m from the prior mean, and how many there are (module docstring, "Rival
        modes"). The offsets form a ``rival_grid`` x ``rival_grid`` grid along the principal axes of the cloud's
        prior position covariance ``p0`` (2, 2) m^2, out to the prior-consistency radius (its 99.9 % region); the
        level of each component is marginalised; a node off the map for some readings counts its others (its
        chi-square scaled up), one off for more than half is out. Rivals (:func:`._batch.rival_moment`, in the
        grid's axes, rotated back) are at least 3 increment sigmas (``r`` (2, 2) m^2) and two nodes away."""
        g = state.rivals
        if g is None or len(g.z) < 2 or g.fmap is None:
            return np.zeros((2, 2)), 0
        fmap = g.fmap
        lam, axes = np.linalg.eigh(0.5 * (p0 + p0.T))
        if not (np.all(np.isfinite(lam)) and lam[0] > 0):
            return np.zeros((2, 2)), 0
        half = np.sqrt(_PRIOR_CONSISTENCY_CHI2 * lam)
        k = int(self.rival_grid) // 2  # type: ignore[arg-type]
        a, b = np.linspace(-half[0], half[0], 2 * k + 1), np.linspace(-half[1], half[1], 2 * k + 1)
        A, B = np.meshgrid(a, b, indexing="ij")
        ab = np.column_stack([A.ravel(), B.ravel()])
        off = ab @ axes.T  # (K, 2) north/east
        T = len(g.z)
        sel = np.unique(np.linspace(0, T - 1, min(T, RIVAL_MAX_READINGS)).round().astype(int))
        thin = T / len(sel)  # each kept reading stands for this many: its variance scaled to keep the information
        tr_vv = 0.0  # the INS velocity error (the cloud's, without its inflation): the tracks are rigid up to it
        if self.dynamics == "ins" and state.prior_cov is not None:
            tr_vv = float(np.trace(state.prior_cov[2:4, 2:4])) / self.prior_inflation**2
        kk, c = len(off), np.size(g.z[0])
        s1, s2, w = np.zeros((kk, c)), np.zeros((kk, c)), np.zeros((kk, c))
        n_ok = np.zeros(kk)
        for i in sel:
            nodes = off + g.centre[i]
            m = sample_map(fmap, state.frame, nodes[:, 0], nodes[:, 1], None).reshape(kk, -1)
            ok = np.all(np.isfinite(m), axis=1)
            v = (g.var[i] + g.g2[i] * tr_vv * 0.5 * (state.t - g.t[i]) ** 2) * thin
            res = np.where(ok[:, None], g.z[i][None, :] - m, 0.0)
            s1 += res / v
            s2 += res * res / v
            w += ok[:, None] / v
            n_ok += ok
        good = n_ok > 0.5 * len(sel)
        ll = -0.5 * np.sum(s2 - s1**2 / np.where(w > 0, w, 1.0), axis=1) * len(sel) / np.maximum(n_ok, 1.0)
        ll = ll - 0.5 * np.einsum("ki,ij,kj->k", off, np.linalg.inv(p0), off)  # rivals of the posterior
        ll = np.where(good, ll, -np.inf)
        ab_fix = axes.T @ np.asarray(d_fix, float)
        spacing = (float(a[1] - a[0]), float(b[1] - b[0]))
        sep = max(3.0 * float(np.sqrt(np.max(np.linalg.eigvalsh(r)))), 2.0 * max(spacing))
        mom, n = rival_moment(ll, ab[:, 0] - ab_fix[0], ab[:, 1] - ab_fix[1], spacing, sep, self.rival_peak_ratio)
        mom = axes @ mom @ axes.T
        if np.any(np.isfinite(ll)):  # the posterior's mass beyond 3 increment sigmas (one broad hill, not peaks)
            lk = np.exp(ll - np.max(ll))
            d = (ab - ab_fix) @ axes.T
            far = np.einsum("ki,ij,kj->k", d, np.linalg.inv(r), d) > _CLOUD_TAIL_CHI2
            wk = lk[far] / lk.sum()
            mom = _loewner_max(mom, (d[far] * wk[:, None]).T @ d[far])
        return mom, n

    def predict(self, state: ParticleState, prior: NavEstimate) -> ParticleState:
        """Move the particles to the prior's time (GM dynamics or the INS increment) and penalise off-road ones.
        After an increment was issued (:meth:`to_fix`), draw a new cloud from ``prior`` instead."""
        if state.issued and self.fix_output == "increment":
            fresh = self._draw(prior, state.rng, state.redraws, state.lost)
            fresh.fault, fresh.faults = state.fault, state.faults  # a map fault is reported by the next to_fix
            return fresh
        rng = state.rng
        nav = prior.nav
        dt = float(nav.t) - state.t
        pos, vel, acc = state.pos.copy(), state.vel.copy(), state.acc.copy()
        dv = state.dv if state.dv is not None else np.zeros_like(pos)
        ins_n, ins_e = state.frame.to_ne(nav.lat, nav.lon)
        ins_ne = np.array([float(ins_n), float(ins_e)])
        m = len(pos)
        iv = [prior.layout["vel"].start, prior.layout["vel"].start + 1]
        p_vv_now = np.asarray(prior.P, float)[np.ix_(iv, iv)]
        mean0 = None if state.prior_mean is None else state.prior_mean.copy()
        cov0 = None if state.prior_cov is None else state.prior_cov.copy()
        if dt > 0:
            if self.dynamics == "gauss_markov":
                nsub = max(1, int(np.ceil(dt / (0.25 * self.tau_s))))
                h = dt / nsub
                phi = np.exp(-h / self.tau_s)
                sd = self.accel_sigma * np.sqrt(1.0 - phi**2)
                f3, q3 = _gm_transition(h, self.tau_s, self.accel_sigma)
                f6 = np.kron(np.eye(2), f3)
                q6 = np.kron(np.eye(2), q3)
                for _ in range(nsub):
                    a_new = phi * acc + sd * rng.standard_normal((m, 2))
                    pos += vel * h + (2.0 * acc + a_new) * h * h / 6.0
                    vel += 0.5 * (acc + a_new) * h
                    acc = a_new
                    if mean0 is not None and cov0 is not None:
                        mean0 = f6 @ mean0
                        cov0 = f6 @ cov0 @ f6.T + q6
            else:
                v_now = np.asarray(nav.v_n, float)[:2]
                step = 0.5 * (state.vel.mean(axis=0) + v_now) * dt  # trapezoid of the INS velocity
                q_v = np.zeros((2, 2))
                if self.ins_velocity and state.p_vv is not None:  # the fuser's velocity covariance growth
                    q_v = _psd_part(p_vv_now - state.p_vv) * self.prior_inflation**2
                dv_new = dv + rng.multivariate_normal(np.zeros(2), q_v, size=m, method="eigh") if q_v.any() else dv
                pos += step + 0.5 * (dv + dv_new) * dt + self.ins_sigma * np.sqrt(dt) * rng.standard_normal((m, 2))
                dv = dv_new
                vel[:] = v_now
                if mean0 is not None and cov0 is not None:
                    f4 = np.eye(4)
                    f4[0, 2] = f4[1, 3] = dt
                    mean0 = f4 @ mean0
                    mean0[:2] += step
                    cov0 = f4 @ cov0 @ f4.T
                    g = np.vstack([0.5 * dt * np.eye(2), np.eye(2)])  # dv increment: half into the position
                    cov0 = cov0 + g @ q_v @ g.T
                    cov0[0, 0] += self.ins_sigma**2 * dt
                    cov0[1, 1] += self.ins_sigma**2 * dt
        logw = state.logw.copy()
        if self.road is not None:
            lat, lon = state.frame.to_latlon(pos[:, 0], pos[:, 1])
            _, dist, _ = self.road.nearest(lat, lon)
            logw += -0.5 * (np.asarray(dist, float) / self.road_sigma_m) ** 2
            logw = _balance(_normalise(logw), _subclouds(state, self.subclouds))
        st = replace(
            state, t=float(nav.t), h=float(nav.h), pos=pos, vel=vel, acc=acc, logw=logw, ins_ne=ins_ne,
            prior_mean=mean0, prior_cov=cov0, issued=False, dv=dv, p_vv=p_vv_now,
        )  # fmt: skip
        st.extra = dict(state.extra)
        st.extra["moved_m"] = st.extra.get("moved_m", 0.0) + float(np.hypot(*np.mean(pos - state.pos, axis=0)))
        return self._maybe_resample(st, rng, force_check=self.road is not None, threshold=_ROAD_RESAMPLE)

    def update(self, state: ParticleState, readings: FieldReadings, fmap: FieldMap) -> ParticleState:
        """Weight by the last reading (``"field"``) or by a fix from ``fix_matcher`` (``"fix"``); SIR resampling."""
        rng = state.rng
        if len(readings) == 0:
            return replace(state, reason="no reading")
        try:
            if self.measurement == "field":
                out = self._field_update(state, readings, fmap)
                if isinstance(out[0], str):
                    return replace(state, reason=out[0])
                loglik, st = out  # type: ignore[misc]
            else:
                loglik, reason = self._fix_loglik(state, readings, fmap)
                if loglik is None:
                    return replace(state, reason=reason)
                st = state
        except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
            return replace(state, reason=f"map lookup failed: {exc}")
        logw = _balance(_normalise(st.logw + loglik), _subclouds(st, self.subclouds))
        st = replace(st, logw=logw, reason="", readings=st.readings + 1)
        return self._maybe_resample(self._fault_check(st), rng, force_check=True)

    def _fault_check(self, state: ParticleState) -> ParticleState:
        """The map-fault monitor (module docstring, "Map faults"): when the forecast NIS of the last
        ``fault_window`` readings sums above its chi-square ``fault_probability`` quantile, the cloud is condemned
        (increment mode: re-drawn from the fuser's estimate at the next prediction, its readings never reported);
        the fault is recorded in ``fault`` for :meth:`to_fix` to report."""
        w = self.fault_window
        if w < 1 or self.fix_output != "increment" or len(state.recent_nis) < w or state.issued:
            return state
        chi2 = float(sum(x[0] for x in state.recent_nis[-w:]))
        dof = int(round(sum(x[1] for x in state.recent_nis[-w:])))
        thr = chi2_threshold(max(dof, 1), self.fault_probability)
        if chi2 <= thr:
            return state
        reason = (
            f"map fault: the last {w} readings missed the cloud's forecast (NIS {chi2:.1f} above {thr:.1f}, "
            f"{dof} dof) at t = {state.t:.0f} s; the cloud's {state.readings} readings were dropped"
        )
        return replace(
            state, fault=reason, faults=state.faults + 1, issued=True, redraws=state.redraws + 1, lost=state.lost + 1
        )

    def to_fix(self, state: ParticleState) -> Fix:
        """The increment since the cloud was drawn, or the cloud's weighted mean and covariance
        (``fix_output``); "no fix" with the reason otherwise (module docstring)."""
        if state.fault and self.fix_output == "increment":
            reason, state.fault = state.fault, ""  # reported once
            return Fix.no_fix(state.t, reason, self.name, state.neff)
        if state.reason and self.fix_output != "posterior":
            return Fix.no_fix(state.t, state.reason, self.name)
        w = np.exp(state.logw)
        mean = w @ state.pos
        d = state.pos - mean
        cov = (d * w[:, None]).T @ d
        cov = 0.5 * (cov + cov.T)
        try:
            ci = np.linalg.inv(cov)
        except np.linalg.LinAlgError:
            return Fix.no_fix(state.t, "particle cloud collapsed (singular covariance)", self.name)
        if self.fix_output == "posterior":  # the navigator's solution (module docstring)
            lat, lon = state.frame.to_latlon(mean[0], mean[1])
            return Fix(state.t, float(lat), float(lon), cov, True, "", state.neff, self.name)
        m2 = np.einsum("ij,jk,ik->i", d, ci, d)
        tail = float(w[m2 > _CLOUD_TAIL_CHI2].sum())
        if tail > self.ambiguity_mass:
            return Fix.no_fix(
                state.t,
                f"ambiguous: particle cloud not unimodal ({100 * tail:.0f} % of the weight beyond 3 sigma)",
                self.name,
                state.neff,
            )
        if state.prior_cov is None:
            lat, lon = state.frame.to_latlon(mean[0], mean[1])
            return Fix(state.t, float(lat), float(lon), cov, True, "", state.neff, self.name)
        draws = ancestral_ess(state)
        if draws < self.min_draws and _room_for_rivals(state, self.dynamics):  # module docstring, "Sparse draws"
            state.issued = True  # condemned: re-drawn, with more particles, at the next prediction
            state.redraws += 1
            return Fix.no_fix(
                state.t,
                f"unresolved: the cloud's weight rests on {draws:.1f} of its {len(w)} draws (below {self.min_draws:g}): "
                "the readings' peak is narrower than the cloud's sampling of its prior, a place between the draws "
                f"may fit better; re-drawn with {self.n_particles * min(2**state.redraws, self.max_particle_factor)} "
                "particles",
                self.name,
                state.neff,
            )
        split, dist = subcloud_disagreement(state, self.subclouds)
        if split > _SUBCLOUD_CHI2:  # module docstring, "Sub-clouds"
            state.issued = True  # condemned: re-drawn, with more particles, at the next prediction
            state.redraws += 1
            return Fix.no_fix(
                state.t,
                f"ambiguous: the cloud's sub-clouds settled {dist:.0f} m apart (Mahalanobis^2 {split:.1f} above "
                f"{_SUBCLOUD_CHI2:.1f}): the readings fit more than one place and the draws found different ones; "
                f"re-drawn with {self.n_particles * min(2**state.redraws, self.max_particle_factor)} particles",
                self.name,
                state.neff,
            )
        ip = [0, 1] if self.dynamics == "ins" else [0, 3]
        mu0 = state.prior_mean[ip]  # type: ignore[index]
        p0 = state.prior_cov[np.ix_(ip, ip)]
        p0 = 0.5 * (p0 + p0.T)
        try:
            y = ci - np.linalg.inv(p0)
        except np.linalg.LinAlgError:
            return Fix.no_fix(state.t, "prior covariance singular", self.name)
        lam = np.linalg.eigvalsh(y)
        if lam[0] <= 0:
            return Fix.no_fix(
                state.t,
                "too little new information: the readings since the last fix did not narrow the cloud in every "
                f"direction ({state.readings} readings)",
                self.name,
                state.neff,
            )
        r = np.linalg.inv(y)
        r = 0.5 * (r + r.T)
        z = r @ (ci @ mean - np.linalg.solve(p0, mu0))
        n_nis = float(state.extra.get("nis_n", 0.0))
        nis = float(state.extra.get("nis_sum", 0.0))
        r = r * misfit_factor(nis, n_nis)  # the readings missed their forecasts by more than the model allows
        r = _cramer_rao_floor(r, _fisher_bound(state.fisher, self.level_sigma is None))
        cover, n_rivals = self._rival_cover(state, z - mu0, r, p0)
        r = r + cover  # the readings fit elsewhere in the prior region too: the fix's covariance says so
        sig = float(np.sqrt(np.linalg.eigvalsh(r)[-1]))
        max_sig = (
            self.max_fix_sigma_m
            if self.max_fix_sigma_m is not None
            else 2.0 * float(np.sqrt(np.linalg.eigvalsh(p0)[-1]))
        )
        if sig > max_sig:
            why = (
                f"ambiguous: {n_rivals} rival mode(s) of the readings' likelihood in the prior region; covering them"
                if n_rivals
                else "too little new information:"
            )
            return Fix.no_fix(
                state.t,
                f"{why} fix sigma {sig:.3g} m above {max_sig:.3g} m ({state.readings} readings)",
                self.name,
                state.neff,
            )
        d_mu = mean - mu0
        d_z = z - mu0
        m_mu = float(d_mu @ np.linalg.solve(p0, d_mu))
        m_z = float(d_z @ np.linalg.solve(p0 + r, d_z))
        if max(m_mu, m_z) > _PRIOR_CONSISTENCY_CHI2:
            return Fix.no_fix(
                state.t,
                "inconsistent with the prior: the readings pull the cloud "
                f"{np.sqrt(m_mu):.1f} prior sigmas away (increment {np.sqrt(m_z):.1f} sigmas): the likelihood peaks "
                "beyond the particles, or the prior is too confident",
                self.name,
                state.neff,
            )
        lat, lon = state.frame.to_latlon(z[0], z[1])
        state.issued = True  # the next prediction draws a new cloud from the fuser's estimate
        state.redraws, state.lost = 0, 0
        return Fix(state.t, float(lat), float(lon), r, True, "", state.neff, self.name)

    # ------------------------------------------------------------------ internals
    def _error_model(self, fmap: FieldMap) -> MapErrorModel:
        return resolve_map_error(fmap, self.map_sigma, self.map_correlation_m)

    def _field_update(
        self, state: ParticleState, readings: FieldReadings, fmap: FieldMap
    ) -> tuple[FloatArray, ParticleState] | tuple[str, None]:
        z = np.asarray(readings.value, float).reshape(len(readings), -1)[-1]
        ncomp = map_components(fmap)
        if z.size != ncomp:
            return f"reading has {z.size} components, map has {ncomp}", None
        if not np.all(np.isfinite(z)):
            return "reading is NaN", None
        mp = len(state.pos)
        m = sample_map(fmap, state.frame, state.pos[:, 0], state.pos[:, 1], None).reshape(mp, ncomp)
        ok = np.all(np.isfinite(m), axis=1)
        if not np.any(ok):
            return "off the map: no particle on the map", None
        s2v = float(readings.sigma) ** 2
        w = np.exp(state.logw)
        mean = w @ state.pos
        sd = float(np.sqrt(np.sum(w @ (state.pos - mean) ** 2)))
        r = max(2.0 * sd, self.flat_window_m)
        g = np.linspace(-r, r, 9)
        gn, ge = np.meshgrid(mean[0] + g, mean[1] + g, indexing="ij")
        stencil = sample_map(fmap, state.frame, gn.ravel(), ge.ravel(), None).reshape(gn.size, ncomp)
        centre = stencil[gn.size // 2]
        spread = feature_variability(stencil, centre) if np.all(np.isfinite(centre)) else np.inf
        if spread < self.min_variability**2 * s2v:  # Wang eq. 14 about the cloud mean
            return (
                f"flat map: feature variability {np.sqrt(spread):.3g} about the particle mean below "
                f"{self.min_variability:g} x reading sigma {np.sqrt(s2v):.3g}"
            ), None
        err = self._error_model(fmap)
        lat, lon = state.frame.to_latlon(state.pos[:, 0], state.pos[:, 1])
        w = np.exp(state.logw)
        sm2 = err.sigma_at(lat, lon) ** 2  # (M,)
        sm2 = np.where(np.isfinite(sm2), sm2, 0.0)
        # one map-error variance for the whole cloud (its weighted mean where the cloud is): with a variance per
        # particle the likelihood's normalisation, prod_k S_k(x)^-1/2, rewards positions where the error layer is
        # small (near the survey's lines) whatever the readings say - on Rio, where flight lines are 1 km apart,
        # that alone gave confident along-track fixes hundreds of metres off on a featureless stretch
        sm2 = np.full(len(sm2), float(w @ sm2))
        fisher = _fisher_step(state, fmap, lat, lon, w, sm2, s2v, err.correlation_m)
        rivals = self._rival_track(state, fmap, z, fisher, s2v, float(sm2[0]), err)
        sm2 = sm2[:, None] * np.ones((1, ncomp))
        st = self._level_error_predict(state, sm2, err.correlation_m, ncomp)
        resid = np.where(ok[:, None], z[None, :] - m, 0.0)  # (M, c)
        loglik, st = self._level_error_update(st, resid, s2v)
        st = replace(st, fisher=fisher, rivals=rivals)
        loglik = np.where(ok, loglik, -np.inf)
        return loglik, st

    def _level_error_predict(self, state: ParticleState, sm2: FloatArray, ell: float, ncomp: int) -> ParticleState:
        """Carry the per-particle level / map-error filter to the particles' new positions (module docstring)."""
        mp = len(state.pos)
        if state.err is None or state.err.shape != (mp, ncomp):
            p_ll = np.full((mp, ncomp), 0.0 if self.level_sigma is None else float(self.level_sigma) ** 2)
            return replace(
                state, lev=np.zeros((mp, ncomp)), err=np.zeros((mp, ncomp)), p_ll=p_ll,
                p_le=np.zeros((mp, ncomp)), p_ee=sm2.copy(), lev_set=self.level_sigma is not None,
                extra={**state.extra, "moved_m": 0.0},
            )  # fmt: skip
        moved = float(state.extra.get("moved_m", 0.0))
        rho = float(markov_coefficient(moved, ell))
        st = replace(
            state, err=rho * state.err, p_le=rho * state.p_le, p_ee=rho**2 * state.p_ee + (1.0 - rho**2) * sm2,
            extra={**state.extra, "moved_m": 0.0},
        )  # fmt: skip
        return st

    def _level_error_update(
        self, state: ParticleState, resid: FloatArray, s2v: float
    ) -> tuple[FloatArray, ParticleState]:
        """Kalman update of ``(c, b)`` per particle and component with ``resid = z - m(x)``; returns the marginal
        log-likelihood per particle (summed over components) and the updated state."""
        lev, err = state.lev, state.err
        p_ll, p_le, p_ee = state.p_ll, state.p_le, state.p_ee
        assert lev is not None and err is not None and p_ll is not None and p_le is not None and p_ee is not None
        if not state.lev_set:  # diffuse level: the first reading sets it and says nothing about position
            lev = resid - err
            p_ll = p_ee + s2v
            p_le = -p_ee.copy()
            return np.zeros(len(resid)), replace(state, lev=lev, p_ll=p_ll, p_le=p_le, lev_set=True)
        nu = resid - lev - err
        s = p_ll + 2.0 * p_le + p_ee + s2v
        k_l = (p_ll + p_le) / s
        k_e = (p_le + p_ee) / s
        loglik = -0.5 * np.sum(nu**2 / s + np.log(s), axis=1)
        w = np.exp(state.logw)  # the predictive check: the cloud's mixture forecast of the reading
        nu_bar = w @ nu
        var = w @ (s + (nu - nu_bar) ** 2)
        nis = float(np.sum(nu_bar**2 / var))
        extra = {**state.extra, "nis_sum": state.extra.get("nis_sum", 0.0) + nis}
        extra["nis_n"] = state.extra.get("nis_n", 0.0) + nu.shape[1]
        keep = self.fault_window - 1  # the monitor's window (the readings before this one)
        recent = (*(state.recent_nis[-keep:] if keep > 0 else ()), (nis, float(nu.shape[1])))
        lev = lev + k_l * nu
        err = err + k_e * nu
        p_ll_n = p_ll - k_l * k_l * s
        p_le_n = p_le - k_l * k_e * s
        p_ee_n = p_ee - k_e * k_e * s
        return loglik, replace(
            state, lev=lev, err=err, p_ll=p_ll_n, p_le=p_le_n, p_ee=p_ee_n, extra=extra, recent_nis=recent
        )

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
        self, state: ParticleState, rng: np.random.Generator, force_check: bool = False, threshold: float | None = None
    ) -> ParticleState:
        """SIR resampling (with roughening), each sub-cloud on its own (module docstring, "Sub-clouds"): one
        whose effective sample size is below the threshold is resampled within itself and keeps its mass."""
        w = np.exp(state.logw)
        neff = float(1.0 / np.sum(w * w))
        m = len(w)
        thr = self.resample_threshold if threshold is None else min(threshold, self.resample_threshold)
        if not force_check:
            return replace(state, neff=neff)
        idx = np.arange(m)
        pos = state.pos.copy()
        logw = state.logw.copy()
        done = False
        for grp in _subclouds(state, self.subclouds):
            lw = state.logw[grp]
            top = float(np.max(lw)) if len(grp) else -np.inf
            if not np.isfinite(top):  # a sub-cloud without weight (all off the map) stays as it is
                continue
            wg = np.exp(lw - top)
            tot = float(wg.sum())
            wg = wg / tot
            mg = len(grp)
            if float(1.0 / np.sum(wg * wg)) >= thr * mg - 1e-9:
                continue
            done = True
            loc = _systematic_resample(wg, float(rng.uniform()))
            idx[grp] = grp[loc]
            pg = state.pos[grp][loc]
            if self.roughening:  # regularised resampling with Liu-West shrinkage: keeps the mean and covariance
                mean = wg @ state.pos[grp]
                d = state.pos[grp] - mean
                cov = (d * wg[:, None]).T @ d + np.eye(2) * self.roughen_min_m**2
                h2 = (4.0 / (mg * 4.0)) ** (2.0 / 6.0)  # Silverman bandwidth^2 for d = 2
                a = np.sqrt(1.0 - h2)
                jitter = rng.multivariate_normal(np.zeros(2), h2 * cov, size=mg)
                pg = mean + a * (pg - mean) + jitter
            pos[grp] = pg
            logw[grp] = top + np.log(tot) - np.log(mg)  # the sub-cloud keeps its mass
        if not done:
            return replace(state, neff=neff)
        sel = {k: (None if getattr(state, k) is None else getattr(state, k)[idx]) for k in _PER_PARTICLE}
        return replace(
            state,
            pos=pos,
            vel=state.vel[idx],
            acc=state.acc[idx],
            dv=None if state.dv is None else state.dv[idx],
            logw=_normalise(logw),
            neff=neff,
            resampled=state.resampled + 1,
            anc=None if state.anc is None else state.anc[idx],
            **sel,
        )


def _subclouds(state: ParticleState, split: int = 2) -> list[NDArray[np.int64]]:
    """The particle indices of the cloud's ``split`` sub-clouds (sub-cloud ``k``: the descendants of draws ``k``,
    ``k + split``, ...; module docstring, "Sub-clouds"), or of the whole cloud when its draws are unknown or
    ``split`` < 2."""
    if state.anc is None or split < 2:
        return [np.arange(len(state.logw))]
    return [np.flatnonzero(state.anc % split == k) for k in range(split)]


def _room_for_rivals(state: ParticleState, dynamics: str) -> bool:
    """Whether the prior the cloud was drawn from is wider (largest 1-sigma) than :data:`SPARSE_PRIOR_ELLS`
    correlation lengths of the map error (module docstring, "Sparse draws"); True when either is unknown."""
    if state.prior_cov is None or state.fisher is None or not np.isfinite(state.fisher[8]):
        return True
    ip = [0, 1] if dynamics == "ins" else [0, 3]
    p0 = state.prior_cov[np.ix_(ip, ip)]
    return float(np.sqrt(max(np.linalg.eigvalsh(0.5 * (p0 + p0.T))[-1], 0.0))) > SPARSE_PRIOR_ELLS * state.fisher[8]


def ancestral_ess(state: ParticleState) -> float:
    """The effective number of the cloud's original draws its weight rests on: ``1 / sum_a W_a^2`` with ``W_a``
    the weight of the particles descended (through resampling) from draw ``a``; the particle count when unknown."""
    w = np.exp(state.logw)
    if state.anc is None:
        return float(len(w))
    wa = np.bincount(state.anc, weights=w)
    return float(1.0 / np.sum(wa * wa))


def _balance(logw: FloatArray, groups: list[NDArray[np.int64]]) -> FloatArray:
    """Log weights with each group's total set to ``1 / len(groups)`` (a group with no weight is left at zero):
    the sub-clouds are estimates of the same posterior, averaged (module docstring, "Sub-clouds")."""
    if len(groups) < 2:
        return logw
    out = logw.copy()
    for grp in groups:
        lw = logw[grp]
        top = float(np.max(lw)) if len(grp) else -np.inf
        if np.isfinite(top):
            out[grp] = lw - top - np.log(np.sum(np.exp(lw - top))) - np.log(len(groups))
    return _normalise(out)


def subcloud_disagreement(state: ParticleState, split: int = 2) -> tuple[float, float]:
    """The largest Mahalanobis distance^2 ``d' (P_a + P_b)^-1 d`` between the weighted means of two of the
    cloud's sub-clouds (``d`` their difference, ``P_a``, ``P_b`` their weighted covariances, each sub-cloud's
    weights normalised on their own) and that pair's distance ``|d|`` (m); ``(0, 0)`` without sub-clouds."""
    groups = _subclouds(state, split)
    if len(groups) < 2 or min(len(g) for g in groups) < 2:
        return 0.0, 0.0
    mom = []
    for grp in groups:
        lw = state.logw[grp]
        if not np.isfinite(np.max(lw)):
            return 0.0, 0.0
        wg = np.exp(lw - np.max(lw))
        wg = wg / wg.sum()
        mu = wg @ state.pos[grp]
        d = state.pos[grp] - mu
        mom.append((mu, (d * wg[:, None]).T @ d))
    worst = (0.0, 0.0)
    for a in range(len(mom)):
        for b in range(a + 1, len(mom)):
            dm = mom[a][0] - mom[b][0]
            s = mom[a][1] + mom[b][1] + np.eye(2) * 1e-6
            worst = max(worst, (float(dm @ np.linalg.solve(s, dm)), float(np.hypot(*dm))))
    return worst


#: per-particle arrays of the level / map-error filter, resampled with the particles
_PER_PARTICLE = ("lev", "err", "p_ll", "p_le", "p_ee")
