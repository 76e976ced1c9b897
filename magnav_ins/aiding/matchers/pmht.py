"""PMHT-MM: probabilistic multiple hypotheses map matching (Wang et al. 2022, seed 001, sec. 3).

For a batch of ``T`` scans (field readings ``s_t`` with INS-indicated positions ``x^s_t`` and covariances
``Sigma^s_t``):

1. Map lookup (eq. 1-2): in a gated rectangle of ``gate_sigma`` prior sigmas about ``x^s_t``, up to ``n``
   candidate grid nodes whose map values are closest to ``s_t`` (and, with ``value_gate``, within that many
   ``s`` of it). Each candidate ``z_j`` gets an isotropic location variance ``R_j = step^2/12 + (s / |grad m|)^2``
   (capped at the window half-width squared): the width of the level-set band it stands for.
2. EM (eq. 8-13): E-step = PDA per scan (eq. 3-5, with eq. 10's likelihood about the current state estimate
   ``x_t^(i)``): ``w_j ~ N(z_j; H x_t^(i), R_j) N(s_t; m(z_j), s^2)`` (the second factor, the reading likelihood of
   the candidate, is ours), ``z_bar = sum w_j z_j``, ``R_bar = sum w_j R_j`` (eq. 5) plus the spread
   ``sum w_j (z_j - z_bar)(z_j - z_bar)'`` (``pda_spread``, as in standard PDA). M-step = forward Kalman filter
   (eq. 12) + RTS smoother (eq. 13). Stop when ``max_t |x_t^(i+1) - x_t^(i)| <= tolerance_m`` or after
   ``iterations``.
3. Kinematics within the batch (eq. 6-7): ``"cv"`` constant velocity ``[n, e, v_n, v_e]`` with white acceleration
   ``accel_sigma``; or ``"ins"``: position only, moved by the INS displacement between scans plus a random walk
   ``ins_drift_sigma`` m/sqrt(s) (the INS is far better than CV over a batch when the vehicle turns); with
   ``adaptive_drift`` (ours) the random-walk step variance is at least the growth of the INS position variance
   between the two scans, ``sigma_{t+1}^2 - sigma_t^2`` (a tactical IMU drifts kilometres within a 300 s batch; a
   fixed 0.05 m/sqrt(s) made the batch rigid; until 2026-12 the step was the growth of the sigma,
   ``(sigma_{t+1} - sigma_t)^2``, about ``T`` times too small over a batch).
4. Output: ``mode="standard"`` one fix at the last scan (smoothed state, covariance ``P_T|T``); ``"retrodiction"``
   a fix per scan with their joint covariance (:meth:`PMHTMatcher.match_batch`, fused by the pipeline as one
   correlated measurement, ``Fuser.correct_batch``; :meth:`PMHTMatcher.match_all` gives the smoothed states). The
   fix covariance is weighted by the map feature variability (eq. 14) ``C``: multiplied by
   ``max(1, variability_ref / (C / s^2))``; aiding stops (no fix, "flat map") where ``sqrt(C) < min_variability * s``
   (off by default: ``min_variability = 0``). ``C`` is the mean over the batch, over the gate box of each scan, or
   (``variability_window_m``, Wang's "fixed search window template") over a square window of that size about each
   scan.

Reading variance: ``s^2`` = the gravimeter's variance plus the map's error (``map_error.resolve_map_error``: the
``map_sigma`` option, else the map's error layer, else the stated default), the map-error part counted once per
correlation length along the track (:mod:`._batch`).

Level offset (issue 13; ``level_sigma``, as the likelihood matchers'): the readings may sit a constant level ``b``
off the map (its levelling, diurnal variation, the platform's field), ``b ~ N(0, sigma_b^2)`` with ``sigma_b`` the
map's level prior (:func:`~.map_error.resolve_level`: ``metadata["level_sigma"]``, else 10 % of the map's std; 0 =
absolute levels, as published). After the EM the level is estimated along the smoothed track (the GLS mean of
``z_t - m(x_t)`` under the prior); when it exceeds ``LEVEL_REPASS`` reading sigmas the batch is run again on the
readings less that level (candidates are picked by value, so an offset moves them). The profile check uses the
readings less their level; the rigid-offset likelihood of the ambiguity floor marginalises the level (exact for
its diagonal variances); the Cramer-Rao floor has it in its section covariance.

Issuing rule (issue 16): a fix is issued whenever fusing it would shrink the INS prior's covariance (its information
beyond the gate's own at least 5 % of the prior's in some direction, :func:`._batch.adds_information`); it is
"flat map" only when it adds no information. A retrodiction batch is
issued or refused as a whole, by its last scan.

The ``wang`` preset (``build_matcher({"kind": "pmht", "preset": "wang", ...})``, :attr:`PMHTMatcher.PRESETS`):
PMHT-MM as published - CV kinematics (eq. 6-7), the INS covariance as the EM's prior (eq. 11), candidates weighted by
their distance to the prediction only (eq. 3, 10), eq. 5's variance without the PDA spread, no clutter hypothesis,
no value gate, none of the covariance floors or divergence checks below; eq. 14 over a fixed 5 km window (Wang's
window size) weights the covariance by ``max(1, 1 / (C / s^2))`` and stops the aiding where
``sqrt(C) < s / 4``. Wang gives neither number: the weighting reference (C = s^2) and the stop threshold are ours.

Fix covariance (ours): the EM's smoothed covariance ``P_k|T`` describes the mode the EM climbed only and is far
too small on smooth maps (fix NEES 10-20 at 1 mGal, 100-1000 with the tactical IMU on the EIGEN-6C4 10' gravity
grid). Three terms, combined by the Loewner maximum (in the basis that whitens one, the larger eigenvalue of each
pair: no double counting), never by a sum:

* ``variance_factor``: ``P`` times ``max(1, mean NIS / 2)``;
* ``crlb_floor``: the Cramer-Rao bound ``J^-1`` of a common position offset over the batch,
  ``J = sum_t G_t' G_t / s^2`` with the map gradient ``G_t`` along the estimated track, the level projected out,
  ``J - (sum G)(sum G)' / (s^2 (T + s^2 / sigma_b^2))``; with ``full_covariance`` (off by default)
  ``J = G' Sigma^-1 G`` under the batch's full residual covariance ``Sigma = sigma_s^2 I + D C D + node error +
  sigma_b^2 1 1'`` (the map error's correlation and the level, :mod:`.map_error`), divided by the readings' misfit
  chi-square per degree of freedom along the track when that exceeds its 99 % quantile (as ML's honesty). Measured
  on the quick real-data suite (2026-12-02) it issued more fixes and was more over-confident than the default
  (Osborne navigation NEES 8.2 against 6.0, Rio 48 against 21): the count of ``s^2`` above, one map error per
  correlation length, is the more cautious of the two, and neither covers PMHT's real-data bias;
* ``ambiguity_floor``: the spread of the batch likelihood of a rigid offset of the INS track over the whole gate
  (``ambiguity_grid`` offsets a side, :meth:`PMHTMatcher._ambiguity`), used where at most ``ambiguity_mass`` of it
  lies within 1.5 grid cells of the fix: by default (1.0) always, as ML's covariance is its tempered likelihood's
  spread (until 2026-12 0.9: only where ambiguous). On the 10' gravity grid and on real magnetic readings the
  likelihood is nearly always ambiguous (0.0-0.3 of the mass near the fix) and the term is what covers a wrong mode
  or a long along-track ridge; on synthetic maps with a correlated map error it is mostly concentrated, and there
  the EM's covariance and the Cramer-Rao bound alone were over-confident (a 100 nT field of 150 m length scale with a
  10 nT error layer, 30 batches: fix NEES 15.6 against 1.6 with the term, RMS 20 against 11 m). Where it is used,
  the fix is the readings' own estimate from that likelihood (below), not the EM's mode.

What the readings' batch likelihood contains (issue 13, ``temper``, on by default): the rigid-offset likelihood
assumes independent residuals of variance ``s^2 + |grad m|^2 (cell^2 / 12 + r_t^2)`` and the marginalised level;
it is divided by a temperature, as ML's (:mod:`.likelihood`, "What the fix covariance contains"): the sandwich
factor of the batch's full residual covariance (sensor noise, the map error with its correlation over its
correlation length, the offset cell, the level ``sigma_b^2 1 1'`` and the INS's deformation within the batch as a
velocity error, :func:`.likelihood.ins_drift_rate`) against the assumed one, times the residuals' misfit
chi-square per degree of freedom at the best offset when it exceeds its 99 % quantile; the sandwich's top-up is
added to its moments (:meth:`PMHTMatcher._temperature`).

De-prior (``ambiguity_deprior`` and ``deprior_location``, on by default since 2026-12). The offset likelihood lives
on a gate centred on the INS position, so its posterior (flat prior over the gate) holds the gate's information
too, ``B^-1 = diag(3 / h_n^2, 3 / h_e^2)``, and its mean is pulled towards the INS. Fused by the filter as an
independent measurement, that share of the INS error came back as evidence, fix after fix: on the real Osborne
tie lines the issued fixes' errors followed the INS error (cosine 0.9-1.0 along the weakly observed,
cross-track direction) while their covariance along it was the gate's own width, and the filter's NEES reached
5-16. The fix is therefore the readings' own estimate: the gate's information is taken out of the covariance,
``C_r = (C^-1 - B^-1)^-1``, and out of the location, ``x_ins + C_r C^-1 mu`` (``mu`` the posterior mean offset;
:meth:`PMHTMatcher._deprior_estimate`; directions that carry almost nothing stay put with a wide variance),
Loewner-maximised with the Cramer-Rao floor. The location is de-priored only where the tempered likelihood has one
mode in the gate (local maxima holding at least ``RIVAL_PEAK_RATIO`` of the best density, as ``rival_cover``): with
several modes the Gaussian algebra does not hold (on the EIGEN-6C4 10' grid, Melbourne -> Sydney, 5 runs, it
gave fix NEES 4.3 and 1,656 m mean against 1.4 and 1,114 m with the guard) and the fix stays at the EM's mode with
the de-priored spread about it. The EM is started at the likelihood's best offset
(``em_start = "likelihood"``; ``"ins"`` as published): started at the INS it stopped at a local optimum next to it
(tie line 10152: fixes 400-700 m off where the offset likelihood's mean was 30-100 m off). ``adds_information``
then compares the fix with the prior without the gate term (the fix no longer holds the gate's information).

Off the map (``off_map``, issue 13; default ``"holes"``). A rigid offset whose track crosses a hole in the map
(nodes without a value inside the map's extent, its geodetic bounding box: gaps between flight lines) is not
impossible there: each such reading has the likelihood of a field that is unknown there, drawn from the map's own
field statistics, ``N(z; mu, var + v_t)`` (:func:`~.map_error.field_statistics`, as the likelihood matchers'
``off_map = "unknown"``), and the level is marginalised over the readings that have a map value. Beyond the map's
extent an offset stays impossible (the vehicle is taken to fly over its map); ``"unknown"`` treats that region as
a hole too, ``"impossible"`` (until 2026-12) every place without a value. With ``"impossible"`` a batch whose true
track crossed a hole was matched to some other place with a confident covariance: on the Rio tie lines (the map
gridded from the flight lines has 2-2.5 km holes on every long tie line), suite seeds of ``--only rio``, every fix
with NEES above 9 had part of its true track off the map (fix NEES 19.4 mean there against 0.23 elsewhere).
``"holes"``: the group's NEES 3.1 -> 2.0, fix NEES 2.5 -> 0.3, no run filter-diverged (6.7 %), RMS 2,955 -> 3,195 m;
on the full suite's Rio seeds RMS 3,847 -> 3,593 m, NEES 3.4 -> 3.1. ``"unknown"`` gave the same NEES but cost
accuracy wherever the gate reaches beyond the map's edge (Rio full-suite seeds 4,207 m; Osborne's edge tie line 5816
at 50 m/s 1,208 -> 1,768 m; QLD West with the tactical IMU, 8 runs, 31 -> 37 km) without making those cases more
honest; ``"holes"`` leaves them as they were. ``tests/test_pmht_offmap.py``: a batch over a hole, fix NEES 408 ->
1.6.

Search gate (``edge_check``, off by default; ``gate_growth``). With ``edge_check`` a fix whose best peak's 99.9 %
region runs out of the gate through a border along which the fix claims to know more than the gate's half-width
(:func:`._batch.truncated_sides`) is re-run with the gate widened by 2 up to ``gate_growth`` times, and at the widest
gate gets no more information along that border's normal than ``1 / h^2``. Tried on Rio (issue 13) and not made the
default: the tempered likelihood's 99.9 % region touches the 3-sigma gate's border in nearly every batch there, and
the rule cost accuracy (full-suite seeds: RMS 3,847 -> 5,175 m, availability 53 -> 33 %) for its honesty (NEES
3.4 -> 2.0); with the region cut to 0.5 nat below the peak (the likelihood's top reaching the border) availability
was still 34 %, RMS 5,049 m.
The gate's width, :data:`GATE_SIGMA` = 3.48 prior sigmas per axis: the smallest box that holds a 2-D Gaussian
truth with probability ``1 - DEFAULT_INTEGRITY_RISK`` (1e-3, the protection level's) whatever its correlation
(Sidak: a box of ``a`` sigmas misses at most ``1 - (2 Phi(a) - 1)^2``, equality for uncorrelated axes). The
3-sigma box used before misses up to 5.4e-3: on Rio the truth left it in a map-fault zone (9160 at 65 m/s, case
NEES 21.8 -> 3.4; suite's Rio NEES 3.13 -> 1.86), and a fix that cannot see the truth promises what the fuser's
protection level does not cover. Cost, measured on five seed sets (README, "PMHT's gate at the integrity risk"):
RMS +5.2 / +4.0 / +0.6 % on the three Rio sets, -4.9 % Osborne tactical, +2.6 % navigation, each inside its paired
bootstrap's 5-95 % band; 3.72 (the box of the ``K = sqrt(-2 ln 1e-3)`` ellipse) costs more.

Variances are capped at ``(10 max h)^2``; with ``partial_fixes = False`` a fix is also refused when its sigma
exceeds the gate half-width in any direction (a fix along a straight line over a smooth map fixes the cross-track
position only, and is issued by default).

Departure from the paper, stated: by default (``use_prior=False``) the position prior of the forward filter is
diffuse (the INS prior only centres the gates and starts the EM), so the fix is independent of the INS and can be
fused without counting the INS twice; ``use_prior=True`` uses the INS covariance as in eq. 11.
Divergence: a fix whose estimate leaves the gated window, whose mean pseudo-measurement NIS exceeds ``max_nis``,
or whose readings disagree with the map sampled along the estimated track (mean chi-square per reading, with the
noise, half the node spacing and the position variance through the local gradient, above ``max_profile_chi2``;
about 0.3-0.7 when right, 50-200 when the true cells were outside the gates in our tests) is a "no fix" with
reason "diverged"; the mean NIS is the fix ``score``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.special import ndtri

from ...core.errors import ConfigError
from ...core.protocols import FieldMap, MatchWindow
from ...core.types import DEFAULT_INTEGRITY_RISK, EDGE_REASON, Fix
from ...maps.variability import feature_variability_track
from ._batch import (
    RIVAL_PEAK_RATIO,
    adds_information,
    edge_normals,
    information_refusal,
    loewner_max,
    reading_variance,
    truncated_sides,
)
from ._local import WorkFrame, make_frame, map_components, sigma_window, spacing_of, window_axes
from .likelihood import ins_drift_rate
from .map_error import (
    drift_covariance,
    field_statistics,
    misfit_factor,
    resolve_level,
    resolve_map_error,
    section_covariance,
    temperature_and_topup,
    whitened_misfit,
)

FloatArray = NDArray[np.float64]


# ---------------------------------------------------------------------------------------------- compiled kernels
@nb.njit(cache=True)
def _lookup_native(
    values: FloatArray,
    y_axis0: float,
    dy: float,
    x_axis0: float,
    dx: float,
    boxes: NDArray[np.int64],
    z: FloatArray,
    n_cand: int,
    s2: float,
    value_gate2: float,
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.int64], FloatArray]:
    """Top-``n_cand`` nodes per scan by squared value distance inside ``boxes`` (T, 4) = (i0, i1, j0, j1).

    Returns candidates (T, n, 2) frame north/east, squared value distances (T, n), squared gradient norms (T, n),
    counts (T,), feature variability (T,) (eq. 14 about the box centre node)."""
    T = boxes.shape[0]
    ny, nx, c = values.shape
    cand = np.full((T, n_cand, 2), np.nan)
    dist = np.full((T, n_cand), np.inf)
    grad2 = np.zeros((T, n_cand))
    counts = np.zeros(T, dtype=np.int64)
    var = np.zeros(T)
    bi = np.zeros(n_cand, dtype=np.int64)
    bj = np.zeros(n_cand, dtype=np.int64)
    for t in range(T):
        i0, i1, j0, j1 = boxes[t, 0], boxes[t, 1], boxes[t, 2], boxes[t, 3]
        if i1 <= i0 or j1 <= j0 or not np.isfinite(z[t, 0]):
            continue
        cnt = 0
        ic = (i0 + i1 - 1) // 2
        jc = (j0 + j1 - 1) // 2
        sv = 0.0
        nv = 0
        centre_ok = True
        for m in range(c):
            if not np.isfinite(values[ic, jc, m]):
                centre_ok = False
        for i in range(i0, i1):
            for j in range(j0, j1):
                d = 0.0
                for m in range(c):
                    r = values[i, j, m] - z[t, m]
                    d += r * r
                if not np.isfinite(d):
                    continue
                if centre_ok:
                    dv = 0.0
                    for m in range(c):
                        q = values[i, j, m] - values[ic, jc, m]
                        dv += q * q
                    if dv > 0.0:
                        sv += dv
                        nv += 1
                if d > value_gate2 * s2:
                    continue
                if cnt < n_cand:
                    k = cnt
                    cnt += 1
                elif d < dist[t, n_cand - 1]:
                    k = n_cand - 1
                else:
                    continue
                while k > 0 and dist[t, k - 1] > d:  # insertion into the sorted buffer
                    dist[t, k] = dist[t, k - 1]
                    bi[k] = bi[k - 1]
                    bj[k] = bj[k - 1]
                    k -= 1
                dist[t, k] = d
                bi[k] = i
                bj[k] = j
        counts[t] = cnt
        var[t] = sv / nv if nv > 0 else 0.0
        for k in range(cnt):
            i, j = bi[k], bj[k]
            cand[t, k, 0] = y_axis0 + i * dy
            cand[t, k, 1] = x_axis0 + j * dx
            ia, ib = max(i - 1, 0), min(i + 1, ny - 1)
            ja, jb = max(j - 1, 0), min(j + 1, nx - 1)
            g2 = 0.0
            for m in range(c):
                gn = (values[ib, j, m] - values[ia, j, m]) / ((ib - ia) * dy) if ib > ia else 0.0
                ge = (values[i, jb, m] - values[i, ja, m]) / ((jb - ja) * dx) if jb > ja else 0.0
                if np.isfinite(gn) and np.isfinite(ge):
                    g2 += gn * gn + ge * ge
            grad2[t, k] = g2
    return cand, dist, grad2, counts, var


@nb.njit(cache=True)
def _inv2(a: FloatArray) -> tuple[FloatArray, float]:
    det = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
    out = np.empty((2, 2))
    out[0, 0] = a[1, 1] / det
    out[1, 1] = a[0, 0] / det
    out[0, 1] = -a[0, 1] / det
    out[1, 0] = -a[1, 0] / det
    return out, det


@nb.njit(cache=True)
def _em(
    cand: FloatArray,
    cand_r2: FloatArray,
    cand_logv: FloatArray,
    logb: FloatArray,
    counts: NDArray[np.int64],
    F: FloatArray,
    Q: FloatArray,
    u: FloatArray,
    x0: FloatArray,
    P0: FloatArray,
    X: FloatArray,
    pvar0: FloatArray,
    iterations: int,
    tol: float,
    spread: bool,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, int]:
    """EM of PMHT-MM (eq. 8-13). ``X`` (T, d) initial state sequence, modified copy returned with smoothed
    covariances (T, d, d), pseudo-measurements (T, 2) and their covariances (T, 2, 2), and the iterations run."""
    T, n, _ = cand.shape
    d = x0.shape[0]
    X = X.copy()
    zbar = np.full((T, 2), np.nan)
    Rbar = np.full((T, 2, 2), np.nan)
    xf = np.zeros((T, d))
    Pf = np.zeros((T, d, d))
    xp = np.zeros((T, d))
    Pp = np.zeros((T, d, d))
    Ps = np.zeros((T, d, d))
    w = np.zeros(n)
    pvar = pvar0.copy()
    it_used = 0
    for it in range(iterations):
        it_used = it + 1
        # E-step: PDA per scan about the current estimate (eq. 3-5, 10)
        for t in range(T):
            c = counts[t]
            if c == 0:
                zbar[t, 0] = np.nan
                continue
            best = logb[t]
            for k in range(c):
                dn = cand[t, k, 0] - X[t, 0]
                de = cand[t, k, 1] - X[t, 1]
                r2 = cand_r2[t, k] + pvar[t]  # eq. 10 about the current estimate, widened by its uncertainty
                w[k] = -0.5 * (dn * dn + de * de) / r2 - np.log(2.0 * np.pi * r2) + cand_logv[t, k]
                if w[k] > best:
                    best = w[k]
            sw = np.exp(logb[t] - best)  # the "no candidate is the platform" hypothesis (clutter)
            for k in range(c):
                w[k] = np.exp(w[k] - best)
                sw += w[k]
            mass = 0.0
            for k in range(c):
                w[k] /= sw
                mass += w[k]
            if mass < 1e-9:
                zbar[t, 0] = np.nan
                continue
            zn = 0.0
            ze = 0.0
            rr = 0.0
            for k in range(c):
                zn += w[k] * cand[t, k, 0]
                ze += w[k] * cand[t, k, 1]
                rr += w[k] * cand_r2[t, k]
            zn /= mass
            ze /= mass
            rr /= mass
            snn = 0.0
            see = 0.0
            sne = 0.0
            if spread:
                for k in range(c):
                    an = cand[t, k, 0] - zn
                    ae = cand[t, k, 1] - ze
                    snn += w[k] * an * an / mass
                    see += w[k] * ae * ae / mass
                    sne += w[k] * an * ae / mass
            # PMHT synthetic measurement: covariance divided by the association mass (Streit & Luginbuhl)
            zbar[t, 0] = zn
            zbar[t, 1] = ze
            Rbar[t, 0, 0] = (rr + snn) / mass
            Rbar[t, 1, 1] = (rr + see) / mass
            Rbar[t, 0, 1] = sne / mass
            Rbar[t, 1, 0] = sne / mass
        # M-step: forward Kalman filter (eq. 12) with H = [I 0]
        for t in range(T):
            if t == 0:
                xp[0] = x0
                Pp[0] = P0
            else:
                xp[t] = F[t - 1] @ xf[t - 1] + u[t - 1]
                Pp[t] = F[t - 1] @ Pf[t - 1] @ F[t - 1].T + Q[t - 1]
            if np.isfinite(zbar[t, 0]):
                S = Pp[t, :2, :2] + Rbar[t]
                Si, _ = _inv2(S)
                K = np.ascontiguousarray(Pp[t, :, :2]) @ Si
                innov = zbar[t] - xp[t, :2]
                xf[t] = xp[t] + K @ innov
                Pf[t] = Pp[t] - K @ np.ascontiguousarray(Pp[t, :2, :])
                Pf[t] = 0.5 * (Pf[t] + Pf[t].T)
            else:
                xf[t] = xp[t]
                Pf[t] = Pp[t]
        # RTS smoother (eq. 13)
        Xn = np.empty_like(X)
        Xn[T - 1] = xf[T - 1]
        Ps[T - 1] = Pf[T - 1]
        for t in range(T - 2, -1, -1):
            G = Pf[t] @ F[t].T @ np.linalg.inv(Pp[t + 1])
            Xn[t] = xf[t] + G @ (Xn[t + 1] - xp[t + 1])
            Ps[t] = Pf[t] + G @ (Ps[t + 1] - Pp[t + 1]) @ G.T
        change = 0.0
        for t in range(T):
            dn = Xn[t, 0] - X[t, 0]
            de = Xn[t, 1] - X[t, 1]
            dd = np.sqrt(dn * dn + de * de)
            if dd > change:
                change = dd
        X = Xn
        for t in range(T):
            pvar[t] = 0.5 * (Ps[t, 0, 0] + Ps[t, 1, 1])
        if change <= tol:
            break
    return X, Ps, zbar, Rbar, it_used


#: the search gate's half-width in prior sigmas per axis (module docstring, "Search gate"): the smallest box that
#: holds a 2-D Gaussian truth with probability 1 - DEFAULT_INTEGRITY_RISK whatever its correlation (3.48 for 1e-3)
GATE_SIGMA = float(ndtri((1.0 + math.sqrt(1.0 - DEFAULT_INTEGRITY_RISK)) / 2.0))

# ---------------------------------------------------------------------------------------------- matcher
#: the batch is run again on the readings less their estimated level when that level exceeds this many reading
#: sigmas ``s`` (module docstring, "Level offset")
LEVEL_REPASS = 0.25
#: a direction whose readings add less than this share of the gate-posterior's information is taken at this share by
#: the de-prior (:meth:`PMHTMatcher._deprior_estimate`): at most 50 x the variance and the extrapolation
DEPRIOR_MIN_RATIO = 0.02
_SIDE_NAMES = {(-1, 0): "south", (1, 0): "north", (0, -1): "west", (0, 1): "east"}


@dataclass
class PMHTResult:
    """Everything one PMHT-MM batch produced (frame metres): smoothed states ``X`` (T, d) and covariances
    ``P`` (T, d, d), pseudo-measurements ``zbar`` (T, 2), ``Rbar`` (T, 2, 2), candidate counts (T,), iterations
    run, mean feature variability (unit^2), mean NIS, the frame and the scan times."""

    X: FloatArray
    P: FloatArray
    zbar: FloatArray
    Rbar: FloatArray
    counts: NDArray[np.int64]
    iterations: int
    variability: float
    nis: float
    frame: WorkFrame
    t: FloatArray
    x_ins: FloatArray
    half: FloatArray
    sigma2: float
    profile_chi2: float
    fisher: FloatArray
    ambiguity: tuple[FloatArray, FloatArray, FloatArray, FloatArray, int, FloatArray] | None = None
    cov_prior: FloatArray | None = None
    level: FloatArray | None = None


@dataclass
class PMHTMatcher:
    """PMHT-MM batch matcher (module docstring). Parameters in SI; ``batch`` T, ``candidates`` n, ``iterations``,
    ``tolerance_m``; ``gate_sigma`` window half-width in prior sigmas (at least ``window_floor_m``);
    ``value_gate`` (multiples of s, ``None`` = no value gate); ``kinematics`` "cv" | "ins"; ``accel_sigma`` m/s^2;
    ``ins_drift_sigma`` m/sqrt(s); ``velocity_sigma`` m/s prior on the CV velocity; ``use_prior``; ``pda_spread``;
    ``map_sigma``; ``min_variability``, ``variability_ref`` (eq. 14 cut-off and weighting); ``max_nis``;
    ``mode`` "standard" | "retrodiction"; ``resolution_m`` scan step for maps without a native local grid
    (coarsened so a scan reads at most ``max_scan_nodes`` map values); ``variance_factor``, ``crlb_floor``,
    ``ambiguity_floor`` (``ambiguity_grid``, ``ambiguity_mass``, ``ambiguity_deprior``, ``deprior_location``,
    ``temper``), ``em_start`` ("likelihood" | "ins") and ``partial_fixes``: the fix covariance terms of the module
    docstring; ``off_map`` ("holes" | "unknown" | "impossible"), ``edge_check`` and ``gate_growth``: module
    docstring, "Off the map" and "Search gate"."""

    batch: int = 30
    candidates: int = 20
    iterations: int = 15
    tolerance_m: float = 0.01
    gate_sigma: float = GATE_SIGMA
    window_floor_m: float = 10.0
    value_gate: float | None = 3.0
    kinematics: str = "ins"
    accel_sigma: float = 0.05
    ins_drift_sigma: float = 0.05
    velocity_sigma: float = 0.5
    use_prior: bool = False
    pda_spread: bool = True
    map_sigma: float | None = None
    correlation_m: float | None = None
    min_variability: float = 0.0
    variability_ref: float = 0.0
    variability_window_m: float | None = None
    reading_weight: bool = True
    max_nis: float = 20.0
    max_profile_chi2: float = 9.0
    mode: str = "standard"
    resolution_m: float | None = None
    candidate_floor_m: float | None = None
    variance_factor: bool = True
    detection_prob: float = 0.9
    crlb_floor: bool = True
    partial_fixes: bool = True
    ambiguity_floor: bool = True
    ambiguity_grid: int = 41
    ambiguity_mass: float = 1.0
    ambiguity_deprior: bool = True
    adaptive_drift: bool = True
    max_scan_nodes: int = 4096
    level_sigma: float | None = None
    full_covariance: bool = False
    em_start: str = "likelihood"
    deprior_location: bool = True
    temper: bool = True
    edge_check: bool = False
    off_map: str = "holes"
    gate_growth: int = 2
    preset: str = ""
    name: str = "pmht"

    #: named sets of defaults (``build_matcher({"kind": "pmht", "preset": "wang", ...})``; explicit keys win):
    #: ``wang`` is PMHT-MM as Wang et al. (2022) publish it (module docstring, "The wang preset")
    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        "wang": {
            "gate_sigma": 3.0,  # the paper gives no width; 3 sigmas, the default before GATE_SIGMA
            "kinematics": "cv",
            "use_prior": True,
            "pda_spread": False,
            "detection_prob": 1.0,
            "reading_weight": False,
            "value_gate": None,
            "variance_factor": False,
            "crlb_floor": False,
            "ambiguity_floor": False,
            "variability_window_m": 5000.0,
            "min_variability": 0.25,
            "variability_ref": 1.0,
            "max_profile_chi2": float("inf"),
            "max_nis": float("inf"),
            "level_sigma": 0.0,
        }
    }

    def __post_init__(self) -> None:
        for key in ("batch", "candidates", "iterations"):
            v = getattr(self, key)
            if not (isinstance(v, int | np.integer) and v >= 1):
                raise ConfigError(f"pmht '{key}': expected a positive integer, got {v!r}")
        if self.batch < 2:
            raise ConfigError(f"pmht 'batch': expected T >= 2 scans, got {self.batch}")
        if self.kinematics not in ("cv", "ins"):
            raise ConfigError(f"pmht 'kinematics': expected 'cv' or 'ins', got {self.kinematics!r}")
        if self.preset and self.preset not in self.PRESETS:
            raise ConfigError(f"pmht 'preset': expected one of {sorted(self.PRESETS)}, got {self.preset!r}")
        if self.variability_window_m is not None and not self.variability_window_m > 0:
            raise ConfigError(f"pmht 'variability_window_m': expected > 0 m, got {self.variability_window_m!r}")
        if self.off_map not in ("unknown", "holes", "impossible"):
            raise ConfigError(f"pmht 'off_map': expected 'unknown', 'holes' or 'impossible', got {self.off_map!r}")
        if self.em_start not in ("ins", "likelihood"):
            raise ConfigError(f"pmht 'em_start': expected 'ins' or 'likelihood', got {self.em_start!r}")
        if self.mode not in ("standard", "retrodiction"):
            raise ConfigError(f"pmht 'mode': expected 'standard' or 'retrodiction', got {self.mode!r}")
        for key in ("gate_sigma", "accel_sigma", "ins_drift_sigma", "velocity_sigma", "max_nis"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"pmht '{key}': expected > 0, got {getattr(self, key)!r}")
        if self.level_sigma is not None and not self.level_sigma >= 0:
            raise ConfigError(f"pmht 'level_sigma': expected >= 0 or None, got {self.level_sigma!r}")

    # ------------------------------------------------------------------ lookup
    def _lookup(
        self, frame: WorkFrame, fmap: FieldMap, x_ins: FloatArray, half: FloatArray, z: FloatArray, s2: float
    ) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.int64], FloatArray, float]:
        T = len(z)
        vg2 = np.inf if self.value_gate is None else float(self.value_gate) ** 2
        full = None
        if self.resolution_m is None:
            lo_n, hi_n = np.nanmin(x_ins[:, 0] - half[:, 0]), np.nanmax(x_ins[:, 0] + half[:, 0])
            lo_e, hi_e = np.nanmin(x_ins[:, 1] - half[:, 1]), np.nanmax(x_ins[:, 1] + half[:, 1])
            full = frame.native(lo_n, hi_n, lo_e, hi_e)
        if full is not None and (full[0].size < 2 or full[1].size < 2):
            full = None
        if full is not None:  # gates narrower than a few nodes: interpolate instead (generic path)
            dy, dx = float(full[0][1] - full[0][0]), float(full[1][1] - full[1][0])
            if float(np.min((2 * half[:, 0] / dy + 1) * (2 * half[:, 1] / dx + 1))) < 9.0:
                full = None
        if full is not None:
            ya, xa, vals = full
            boxes = np.empty((T, 4), dtype=np.int64)
            boxes[:, 0] = np.searchsorted(ya, x_ins[:, 0] - half[:, 0], "left")
            boxes[:, 1] = np.searchsorted(ya, x_ins[:, 0] + half[:, 0], "right")
            boxes[:, 2] = np.searchsorted(xa, x_ins[:, 1] - half[:, 1], "left")
            boxes[:, 3] = np.searchsorted(xa, x_ins[:, 1] + half[:, 1], "right")
            cand, dist, grad2, counts, var = _lookup_native(
                np.ascontiguousarray(vals), float(ya[0]), dy, float(xa[0]), dx, boxes, z, self.candidates, s2, vg2
            )
            return cand, dist, grad2, counts, var, 0.5 * (dy + dx)
        step = self.resolution_m or min(spacing_of(fmap, 1.0), float(np.min(half)) / 10.0)
        cand = np.full((T, self.candidates, 2), np.nan)
        dist = np.full((T, self.candidates), np.inf)
        grad2 = np.zeros((T, self.candidates))
        counts = np.zeros(T, dtype=np.int64)
        var = np.zeros(T)
        step_used = step
        for t in range(T):
            if not np.all(np.isfinite(z[t])):
                continue
            # at most max_scan_nodes samples per scan: an elongated gate (one short side) would otherwise be
            # scanned at a tenth of its short side along its long side (10^4-10^5 map reads per scan)
            an, ae, st = window_axes(half[t, 0], half[t, 1], step, self.max_scan_nodes)
            step_used = max(step_used, st)
            gn, ge = np.meshgrid(an, ae, indexing="ij")
            pn, pe = x_ins[t, 0] + gn.ravel(), x_ins[t, 1] + ge.ravel()
            v = frame.sample(pn, pe).reshape(pn.size, -1)
            centre = v[(gn.size - 1) // 2]
            dv = np.sum((v - centre) ** 2, axis=1)
            dv = dv[np.isfinite(dv) & (dv > 0)]
            var[t] = dv.mean() if dv.size else 0.0
            d = np.sum((v - z[t]) ** 2, axis=1)
            ok = np.flatnonzero(np.isfinite(d) & (d <= vg2 * s2))
            if ok.size == 0:
                continue
            sel = ok[np.argsort(d[ok])[: self.candidates]]
            c = sel.size
            counts[t] = c
            cand[t, :c, 0], cand[t, :c, 1], dist[t, :c] = pn[sel], pe[sel], d[sel]
            vn = frame.sample(pn[sel] + st, pe[sel]).reshape(c, -1) - frame.sample(pn[sel] - st, pe[sel]).reshape(c, -1)
            ve = frame.sample(pn[sel], pe[sel] + st).reshape(c, -1) - frame.sample(pn[sel], pe[sel] - st).reshape(c, -1)
            grad2[t, :c] = np.nan_to_num(np.sum(vn**2 + ve**2, axis=1) / (2 * st) ** 2)
        return cand, dist, grad2, counts, var, step_used

    # ------------------------------------------------------------------ batch
    def run(self, window: MatchWindow, fmap: FieldMap, grow: float = 1.0) -> PMHTResult | str:
        """Run one batch (the window's last ``batch`` readings) with the search gate ``grow`` times its
        ``gate_sigma`` width; the result, or the reason there is none. With a level prior (module docstring, "Level
        offset") the batch is run a second time on the readings less the level estimated along the first run's
        track."""
        lv = float(resolve_level(fmap, self.level_sigma).sigma) ** 2
        res = self._run(window, fmap, lv, None, grow)
        if isinstance(res, str) or res.level is None or not np.all(np.isfinite(res.level)):
            return res
        if float(np.max(np.abs(res.level))) <= LEVEL_REPASS * np.sqrt(res.sigma2):
            return res  # a level this small hardly changes the candidates' weights
        res2 = self._run(window, fmap, lv, res.level, grow)
        return res if isinstance(res2, str) else res2

    def _run(
        self, window: MatchWindow, fmap: FieldMap, lv: float, offset: FloatArray | None, grow: float = 1.0
    ) -> PMHTResult | str:
        """One batch with the level prior variance ``lv`` (unit^2), the readings less ``offset`` (c,) if given, the
        gate ``grow`` times ``gate_sigma`` prior sigmas wide."""
        rd = window.readings
        T = min(self.batch, len(rd))
        if T < 2:
            return f"need at least 2 scans, got {T}"
        sl = slice(len(rd) - T, len(rd))
        ncomp = map_components(fmap)
        z = np.asarray(rd.value, dtype=float)[sl].reshape(T, -1)
        if z.shape[1] != ncomp:
            return f"reading has {z.shape[1]} components, map has {ncomp}"
        base = np.zeros(ncomp) if offset is None else np.asarray(offset, float).reshape(ncomp)
        z = z - base
        lat, lon = np.asarray(window.lat, float)[sl], np.asarray(window.lon, float)[sl]
        if not (np.all(np.isfinite(lat)) and np.all(np.isfinite(lon))):
            return "INS positions not finite"
        good = np.all(np.isfinite(z), axis=1)
        if good.sum() < 2:
            return "fewer than 2 finite readings (NaN)"
        tt = np.asarray(rd.t, float)[sl]
        frame = make_frame(fmap, float(lat[-1]), float(lon[-1]))
        dn, de = frame.to_ne(lat, lon)
        x_ins = np.column_stack([dn, de])
        cov = np.asarray(window.cov_ne, float)[sl]
        s2_t, _ = reading_variance(fmap, lat, lon, x_ins, float(rd.sigma), self.map_sigma, self.correlation_m)
        s2 = float(np.mean(s2_t))  # sensor + map error (map_error via _batch.reading_variance)
        half = np.array([sigma_window(c, self.gate_sigma * grow, self.window_floor_m) for c in cov])
        if not np.all(np.isfinite(half)):
            return "prior covariance not finite"
        # INS drift within the batch (adaptive_drift): the position variance the INS adds between scans, and the
        # drift of each scan relative to the last one
        # the variance the INS adds between scans (m^2): a drift with independent increments has
        # Var(dp_t - dp_T) = sigma_T^2 - sigma_t^2 (not (sigma_T - sigma_t)^2, which is far smaller)
        var_ins = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
        step_growth2 = np.maximum(np.diff(var_ins), 0.0)
        rel_drift = np.sqrt(np.append(np.cumsum(step_growth2[::-1])[::-1], 0.0)) if self.adaptive_drift else np.zeros(T)
        cand, dist, grad2, counts, var, step = self._lookup(frame, fmap, x_ins, half, z, s2)
        counts = np.where(good, counts, 0)
        if np.sum(counts > 0) < 2:
            return "off the map: fewer than 2 scans with map candidates in their windows"
        if self.variability_window_m is not None:  # Wang's fixed search-window template about each scan (eq. 14)
            w_m = float(self.variability_window_m)
            cv = feature_variability_track(fmap, lat[good], lon[good], w_m, step_m=w_m / 20.0)
            variability = float(np.nanmean(cv)) if np.any(np.isfinite(cv)) else 0.0
        else:
            variability = float(np.mean(var[counts > 0]))
        if variability < self.min_variability**2 * s2:
            return (
                f"flat map: feature variability {np.sqrt(variability):.3g} below {self.min_variability:g} x "
                f"reading sigma {np.sqrt(s2):.3g}"
            )
        hmax2 = np.max(half, axis=1) ** 2
        r2 = (self.candidate_floor_m or 0.5 * step) ** 2 + np.minimum(s2 / np.maximum(grad2, 1e-300), hmax2[:, None])
        logv = -0.5 * np.where(np.isfinite(dist), dist, 0.0) / s2
        if not self.reading_weight:  # Wang's eq. 3: the candidates weighted by their distance to the prior only
            logv = np.zeros_like(logv)
        pd = self.detection_prob
        logb = np.log((1.0 - pd) / pd) - np.log(4.0 * half[:, 0] * half[:, 1]) if pd < 1.0 else np.full(T, -np.inf)
        v_ne = np.asarray(window.v_ne, float)[sl]
        dts = np.diff(tt)
        if self.kinematics == "cv":
            d = 4
            F = np.tile(np.eye(4), (T - 1, 1, 1))
            F[:, 0, 2] = F[:, 1, 3] = dts
            q = self.accel_sigma**2
            Q = np.zeros((T - 1, 4, 4))
            for a, b in ((0, 2), (1, 3)):
                Q[:, a, a] = q * dts**3 / 3
                Q[:, a, b] = Q[:, b, a] = q * dts**2 / 2
                Q[:, b, b] = q * dts
            u = np.zeros((T - 1, 4))
            X0 = np.column_stack([x_ins, np.where(np.isfinite(v_ne), v_ne, 0.0)])
        else:
            d = 2
            F = np.tile(np.eye(2), (T - 1, 1, 1))
            q = self.ins_drift_sigma**2 * dts
            if self.adaptive_drift:  # the INS's own drift between scans: the growth of its position variance
                q = np.maximum(q, step_growth2)
            Q = np.eye(2)[None] * q[:, None, None]
            u = np.diff(x_ins, axis=0)
            X0 = x_ins.copy()
        g_ok = np.isfinite(dist)
        g2 = np.sum(np.where(g_ok, grad2, 0.0), axis=1) / np.maximum(np.sum(g_ok, axis=1), 1)
        honesty = (fmap, float(rd.sigma), step, tt - tt[-1], ins_drift_rate(tt, cov)) if self.temper else None
        amb = (
            self._ambiguity(
                frame, z + base, good, x_ins, half, g2, s2, rel_drift, lv, honesty, self._field(fmap, frame)
            )
            if self.ambiguity_floor
            else None
        )
        if amb is not None and self.em_start == "likelihood":  # start the EM at the batch's best rigid offset
            X0[:, :2] = X0[:, :2] + amb[0][int(np.argmax(amb[1]))]
        P0 = np.zeros((d, d))
        if self.use_prior:
            P0[:2, :2] = cov[0]
        else:
            P0[:2, :2] = np.eye(2) * 1e4 * float(np.max(half)) ** 2
        if d == 4:
            P0[2, 2] = P0[3, 3] = self.velocity_sigma**2
        X, P, zbar, Rbar, its = _em(
            cand,
            r2,
            logv,
            logb,
            counts.astype(np.int64),
            F,
            Q,
            u,
            X0[0].copy(),
            P0,
            X0,
            0.5 * (cov[:, 0, 0] + cov[:, 1, 1]),
            self.iterations,
            self.tolerance_m,
            self.pda_spread,
        )
        ok = np.isfinite(zbar[:, 0])
        res = zbar[ok] - X[ok, :2]
        nis = float(np.mean([r @ np.linalg.solve(R, r) for r, R in zip(res, Rbar[ok], strict=True)]))
        # profile check: the readings against the map along the estimated track (value residual normalised by
        # the noise, the node error and the position uncertainty through the local gradient)
        m_est = frame.sample(X[:, 0], X[:, 1]).reshape(T, -1)
        pos_var = 0.5 * (P[:, 0, 0] + P[:, 1, 1])
        var_t = s2 + g2 * (pos_var + (0.5 * step) ** 2)
        resid = z - m_est
        r_ok = good & np.all(np.isfinite(resid), axis=1)
        level = None
        if lv > 0 and r_ok.sum() >= 2:  # the level along the track: the marginalised level's mean (GLS)
            w = 1.0 / var_t[r_ok]
            step_b = np.sum(resid[r_ok] * w[:, None], axis=0) / (np.sum(w) + 1.0 / lv)
            level = base + step_b
            resid = resid - step_b  # the profile check on the readings less their level
        chi = np.sum(resid**2, axis=1) / var_t
        chi = chi[good & np.isfinite(chi)]
        profile = float(np.mean(chi) / z.shape[1]) if chi.size else float("nan")
        # Cramer-Rao bound of a common position offset over the batch: J = sum_t G_t' G_t / s^2 with the map
        # gradient G_t at the estimated track (central differences); the fix covariance may not be smaller
        hstep = max(0.5 * step, 0.5)
        gn_ = (frame.sample(X[:, 0] + hstep, X[:, 1]) - frame.sample(X[:, 0] - hstep, X[:, 1])).reshape(T, -1)
        ge_ = (frame.sample(X[:, 0], X[:, 1] + hstep) - frame.sample(X[:, 0], X[:, 1] - hstep)).reshape(T, -1)
        G = np.stack([gn_, ge_], axis=-1) / (2 * hstep)  # (T, c, 2)
        rows = good & np.all(np.isfinite(G), axis=(1, 2))
        if self.full_covariance and rows.sum() >= 3:
            J = self._section_fisher(fmap, frame, X[rows, :2], G[rows], z[rows] + base - m_est[rows], g2[rows],
                                     step, float(rd.sigma), lv)  # fmt: skip
        else:
            G = G[rows]
            J = np.einsum("tci,tcj->ij", G, G) / s2
            if lv > 0 and len(G):  # the level projected out: (sum G G' - (sum G)(sum G)' / (T + s2 / lv)) / s2
                gs = G.sum(axis=0)  # (c, 2)
                J = J - np.einsum("ci,cj->ij", gs, gs) / (s2 * (len(G) + s2 / lv))
        return PMHTResult(
            X, P, zbar, Rbar, counts, int(its), variability, nis, frame, tt, x_ins, half, s2, profile, J, amb, cov,
            level,
        )  # fmt: skip

    def _section_fisher(
        self,
        fmap: FieldMap,
        frame: WorkFrame,
        x: FloatArray,
        G: FloatArray,
        resid: FloatArray,
        g2: FloatArray,
        step: float,
        sensor_sigma: float,
        lv: float,
    ) -> FloatArray:
        """Fisher information (2, 2) 1/m^2 of a rigid offset of the estimated track ``x`` (K, 2) frame m under the
        batch's full residual covariance (module docstring, "Fix covariance"): ``J = sum_c G_c' Sigma^-1 G_c`` with
        ``Sigma = sigma_s^2 I + D C D + node error + level 1 1'`` (the map error's correlation ``C`` and 1-sigma
        ``D`` from :func:`~.map_error.resolve_map_error`, the level prior variance ``lv``), ``G`` (K, c, 2) the map
        gradient along the track; divided by the readings' misfit chi-square per degree of freedom (``resid`` (K, c)
        = reading - map along the track, level included) when it exceeds its 99 % quantile."""
        err = resolve_map_error(fmap, self.map_sigma, self.correlation_m)
        la, lo = frame.to_latlon(x[:, 0], x[:, 1])
        sm = np.asarray(err.sigma_at(la, lo), float)
        sm = np.where(np.isfinite(sm), sm, 0.0)
        sig = section_covariance(x[:, 0], x[:, 1], sm, sensor_sigma, err.correlation_m)
        sig[np.diag_indices(len(x))] += g2 * (0.5 * step) ** 2
        sig += lv
        si = np.linalg.inv(sig)
        J = np.einsum("tci,ts,scj->ij", G, si, G)
        chi2, dof = whitened_misfit(resid, sig)
        J = J / misfit_factor(chi2, dof)
        return 0.5 * (J + J.T)

    def _ambiguity(
        self,
        frame: WorkFrame,
        z: FloatArray,
        good: NDArray[np.bool_],
        x_ins: FloatArray,
        half: FloatArray,
        g2: FloatArray,
        s2: float,
        rel_drift: FloatArray,
        lv: float = 0.0,
        honesty: tuple[FieldMap, float, float, FloatArray, FloatArray] | None = None,
        field: tuple[FloatArray, FloatArray, Any] | None = None,
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, int, FloatArray] | None:
        """Batch likelihood of a rigid offset of the INS track over the gate: offsets ``(K, 2)`` m, normalised
        weights ``(K,)``, the grid spacing ``(D_n, D_e)`` m, the tempering's top-up (2, 2) m^2, the number of modes
        and the outward normals (J, 2) of the gate borders the best peak's 99.9 % region touches
        (:func:`._batch.edge_normals`; module docstring, "Search gate") (``None`` where no offset has a finite
        likelihood).

        The likelihood of a rigid offset ``d`` of the INS track, ``p(d) ~ prod_t N(z_t; m(x_t + d), v_t)``, on
        ``ambiguity_grid`` offsets a side spanning the last scan's gate (``|d_n| <= h_n``, ``|d_e| <= h_e``, spacing
        ``D_n``, ``D_e``), with ``v_t = s^2 + |grad m|_t^2 ((D_n^2 + D_e^2) / 12 + r_t^2)`` (the offset cell through
        the local gradient: the grid point stands for its cell; ``r_t`` the INS drift of scan ``t`` relative to the
        last scan, ``rel_drift``, zero without ``adaptive_drift``). :meth:`_ambiguity_cov` turns it into a
        covariance about a smoothed position.

        The EM's smoothed covariance and the Cramer-Rao bound describe the mode the EM climbed only; on a smooth map
        with repeated features (the 10' gravity grid) the likelihood has several modes or a long ridge within the
        gate, and the fix error is that spread."""
        m = max(int(self.ambiguity_grid), 3)
        hn, he = float(half[-1, 0]), float(half[-1, 1])
        on, oe = np.linspace(-hn, hn, m), np.linspace(-he, he, m)
        dn, de = 2 * hn / (m - 1), 2 * he / (m - 1)
        ON, OE = np.meshgrid(on, oe, indexing="ij")
        ON, OE = ON.ravel(), OE.ravel()
        ll = np.zeros(ON.size)
        cell2 = (dn * dn + de * de) / 12.0
        s_r = np.zeros((ON.size, z.shape[1]))  # sum r / var per offset and component (the level's evidence)
        s_w = np.zeros(ON.size)  # sum 1 / var per offset over the readings with a map value there
        for t in np.flatnonzero(good):
            v = frame.sample(x_ins[t, 0] + ON, x_ins[t, 1] + OE).reshape(ON.size, -1)
            var_t = s2 + g2[t] * (cell2 + rel_drift[t] ** 2)
            r2 = np.sum((v - z[t]) ** 2, axis=1) / var_t
            fin = np.isfinite(r2)
            off: float | FloatArray = -np.inf  # off the map impossible
            if field is not None:  # off the map: the field there unknown, drawn from the map's own statistics
                tot = field[1] + var_t
                off = -0.5 * float(np.sum((z[t] - field[0]) ** 2 / tot + np.log(tot / var_t)))
                if field[2] is not None and not np.all(fin):  # "holes": beyond the map's extent impossible
                    inside = np.ones(ON.size, dtype=bool)
                    inside[~fin] = field[2](x_ins[t, 0] + ON[~fin], x_ins[t, 1] + OE[~fin])
                    off = np.where(inside, off, -np.inf)
            ll += np.where(fin, -0.5 * r2, off)
            s_r += np.where(fin[:, None], (z[t] - v) / var_t, 0.0)
            s_w += np.where(fin, 1.0 / var_t, 0.0)
        if lv > 0:  # the level offset marginalised per offset (Sherman-Morrison with the diagonal variances), with
            # its normalisation (constant over the offsets unless some readings lie off the map at some of them)
            gain = np.sum(s_r**2, axis=1) / (s_w + 1.0 / lv) - z.shape[1] * np.log1p(lv * s_w)
            ll = ll + 0.5 * np.where(np.isfinite(gain), gain, 0.0)
        if not np.any(np.isfinite(ll)):
            return None
        topup = np.zeros((2, 2))
        if honesty is not None:  # temper the surface as ML does (module docstring, "Fix covariance")
            kb = int(np.nanargmax(np.where(np.isfinite(ll), ll, -np.inf)))
            temp, topup = self._temperature(
                frame, z, good, x_ins + np.array([ON[kb], OE[kb]]), g2, s2, cell2, rel_drift, lv, *honesty
            )
            ll = ll / temp
        p = np.exp(ll - np.max(ll))
        grid = np.where(np.isfinite(p), p, 0.0).reshape(m, m)
        peaks = (grid == ndimage.maximum_filter(grid, size=3, mode="constant", cval=0.0)) & (grid >= RIVAL_PEAK_RATIO)
        edges = edge_normals(np.where(np.isfinite(ll), ll, -np.inf).reshape(m, m), int(np.argmax(grid)))
        keep = p > 1e-12 * p.sum()
        out = np.column_stack([ON[keep], OE[keep]]), p[keep] / p[keep].sum(), np.array([dn, de]), topup
        return (*out, int(peaks.sum()), edges)

    def _temperature(
        self,
        frame: WorkFrame,
        z: FloatArray,
        good: NDArray[np.bool_],
        y: FloatArray,
        g2: FloatArray,
        s2: float,
        cell2: float,
        rel_drift: FloatArray,
        lv: float,
        fmap: FieldMap,
        sensor_sigma: float,
        step: float,
        tau: FloatArray,
        drift_mps: FloatArray,
    ) -> tuple[float, FloatArray]:
        """``(temperature, top-up (2, 2) m^2)`` of the rigid-offset likelihood of :meth:`_ambiguity`, evaluated on
        the track ``y`` (T, 2) frame m at its best offset: ML's honesty (:meth:`.likelihood.LikelihoodMatcher.honesty`)
        for PMHT's batch. The likelihood assumed the residuals independent with variances ``v_t = s^2 + |grad m|_t^2
        (cell^2 / 12 + r_t^2)`` plus the level, ``A = diag(v) + sigma_b^2 1 1'``; their covariance is ``Sigma =
        sigma_s^2 I + D C D + diag(|grad m|^2 cell^2 / 12) + sigma_b^2 1 1' + W`` (the map error's correlation
        ``C``, :func:`~.map_error.section_covariance`, and the INS's deformation within the batch as the random walk
        of the EM's kinematics: scans ``t``, ``s`` share ``min(r_t^2, r_s^2)`` per axis, ``W_ts = G_t . G_s
        min(r_t^2, r_s^2)``). The temperature is the sandwich's (:func:`~.map_error.temperature_and_topup`, in the
        basis that whitens ``A``) times the residuals' misfit chi-square per degree of freedom under ``Sigma`` when
        that exceeds its 99 % quantile; the top-up is scaled by the same misfit factor."""
        idx = np.flatnonzero(good)
        yy = y[idx]
        k = idx.size
        if k < 3:
            return 1.0, np.zeros((2, 2))
        h = max(0.5 * float(step), 0.5)
        c = z.shape[1]
        m0 = np.asarray(frame.sample(yy[:, 0], yy[:, 1]), float).reshape(k, c)
        jac = np.empty((k, c, 2))
        jac[:, :, 0] = (frame.sample(yy[:, 0] + h, yy[:, 1]) - frame.sample(yy[:, 0] - h, yy[:, 1])).reshape(k, c)
        jac[:, :, 1] = (frame.sample(yy[:, 0], yy[:, 1] + h) - frame.sample(yy[:, 0], yy[:, 1] - h)).reshape(k, c)
        jac = np.nan_to_num(jac / (2 * h), nan=0.0, posinf=0.0, neginf=0.0)
        resid = z[idx] - m0
        if not np.all(np.isfinite(resid)):
            return 1.0, np.zeros((2, 2))
        err = resolve_map_error(fmap, self.map_sigma, self.correlation_m)
        la, lo = frame.to_latlon(yy[:, 0], yy[:, 1])
        sm = np.asarray(err.sigma_at(la, lo), float)
        sm = np.where(np.isfinite(sm), sm, 0.0)
        sigma = section_covariance(yy[:, 0], yy[:, 1], sm, sensor_sigma, err.correlation_m)
        sigma[np.diag_indices(k)] += g2[idx] * cell2
        sigma += lv
        r2 = rel_drift[idx] ** 2
        sigma += drift_covariance(jac, tau[idx], drift_mps)  # the INS's deformation within the batch
        assumed = np.diag(s2 + g2[idx] * (cell2 + r2)) + lv
        try:
            tr = np.linalg.inv(np.linalg.cholesky(assumed))  # T' T = A^-1
        except np.linalg.LinAlgError:
            return 1.0, np.zeros((2, 2))
        temp, topup = temperature_and_topup(jac, sigma, 1.0, tr)
        chi2, dof = whitened_misfit(resid, sigma)
        phi = misfit_factor(chi2, dof)
        return float(temp * phi), topup * phi

    def _field(self, fmap: FieldMap, frame: WorkFrame) -> tuple[FloatArray, FloatArray, Any] | None:
        """The field's prior ``(mean, variance, inside)`` per component where the map has no value (``off_map``
        "unknown" or "holes", :func:`~.map_error.field_statistics`; ``inside(n, e)`` (frame m) -> bool: within the
        map's geodetic bounding box, for "holes", else None), or None ("impossible", or a map without values)."""
        if self.off_map == "impossible":
            return None
        try:
            mu, var = field_statistics(fmap)
        except (AttributeError, TypeError, ValueError):
            return None
        mu, var = np.asarray(mu, float), np.asarray(var, float)
        if not (np.all(np.isfinite(mu)) and np.all(np.isfinite(var))):
            return None
        inside = None
        box = getattr(fmap, "bounds_latlon", None)
        if self.off_map == "holes" and box is None:
            return None  # no extent to tell a hole from beyond the map: every place without a value impossible
        if self.off_map == "holes":
            la0, la1, lo0, lo1 = (float(b) for b in box)

            def inside(n: FloatArray, e: FloatArray) -> NDArray[np.bool_]:
                la, lo = frame.to_latlon(n, e)
                return (la >= la0) & (la <= la1) & (lo >= lo0) & (lo <= lo1)

        return mu, var, inside

    def _ambiguity_cov(self, res: PMHTResult, k: int) -> tuple[FloatArray, float] | None:
        """``(C, near)`` from the rigid-offset likelihood of :meth:`_ambiguity` at scan ``k``: ``C`` (2, 2) m^2 the
        second moment of the offset posterior (flat prior over the gate) about the smoothed position ``X_k`` (each
        grid point a uniform cell, ``+ D^2/12`` per axis); with ``ambiguity_deprior`` the gate's own information is
        removed, ``C = (C_post^-1 - B^-1)^-1`` with ``B = diag(h_n^2, h_e^2) / 3`` the variance of the flat prior
        (directions where the likelihood adds less than that get ``(10 max h)^2``); :meth:`_fix` uses
        :meth:`_deprior_estimate` instead when ``deprior_location`` is on (the default). History: with the
        covariance de-priored but the fix at the EM's mode (2026-11), on the EIGEN-6C4 scenarios (5 runs, T = 15 /
        30) the fixes were more conservative (1 mGal fix NEES 0.4 / 0.8) and the mean errors larger (1 mGal 1303 /
        1416 m against 1295 / 1358 m; tactical 30.6 / 34.0 km against 24.9 / 26.6 km). ``near`` is
        the posterior mass within one and a half cells of ``X_k`` (the 3 x 3 cells about the EM's mode: 1 where the
        likelihood is unambiguous at the grid's resolution)."""
        if res.ambiguity is None:
            return None
        off, p, D, topup = res.ambiguity[:4]
        hn, he = float(res.half[-1, 0]), float(res.half[-1, 1])
        a = res.x_ins[k] + off - res.X[k, :2]
        near = float(np.sum(p[np.all(np.abs(a) <= 1.5 * D, axis=1)]))
        C = np.einsum("k,ki,kj->ij", p, a, a) + np.diag(D**2) / 12.0 + topup
        if not self.ambiguity_deprior:
            return C, near
        big = (10.0 * max(hn, he)) ** 2
        info = np.linalg.inv(C) - np.diag([3.0 / hn**2, 3.0 / he**2])
        ev, V = np.linalg.eigh(0.5 * (info + info.T))
        return (V / np.maximum(ev, 1.0 / big)) @ V.T, near

    def _deprior_estimate(self, res: PMHTResult, k: int, big: float) -> tuple[FloatArray, FloatArray] | None:
        """The readings' own estimate of scan ``k``'s position and its covariance, from the rigid-offset likelihood
        of :meth:`_ambiguity` with the gate's information taken out of *both* (module docstring, "Fix
        covariance"): with the posterior mean ``mu`` (offset from the INS) and covariance ``C`` over the gate
        (flat prior, variance ``B = diag(h_n^2, h_e^2) / 3``), the readings' information is ``C^-1 - B^-1`` and
        their estimate ``x_ins + (C^-1 - B^-1)^-1 C^-1 mu`` (the Gaussian posterior's algebra run backwards). A
        posterior mean is pulled towards the gate's centre, the INS, by ``C B^-1``: fused as independent, that
        share of the INS error came back as if it were evidence. In whitened coordinates (``C = L L'``) each
        direction whose information ratio ``lambda`` (eigenvalue of ``I - L' B^-1 L``) is below
        ``DEPRIOR_MIN_RATIO`` (also below zero, where the top-up makes the spread wider than the gate's) is taken at
        that ratio: its location extrapolated ``1 / DEPRIOR_MIN_RATIO`` times, its variance ``C /
        DEPRIOR_MIN_RATIO``. Tried (issue 13) and not kept: leaving such a direction at the posterior mean (the
        gate's pull towards the INS back in): Osborne tactical group 462 -> 482 m, edge line 5817 at 50 m/s fix NEES
        1.7 -> 10.9, Rio (``--only rio`` seeds) fix NEES 0.2 -> 1.0. Variances capped at ``big``."""
        if res.ambiguity is None or res.ambiguity[4] != 1:
            return None  # no likelihood, or several modes: the Gaussian algebra does not hold
        off, p, D, topup = res.ambiguity[:4]
        mu = p @ off
        a = off - mu
        C = np.einsum("k,ki,kj->ij", p, a, a) + np.diag(D**2) / 12.0 + topup
        try:
            L = np.linalg.cholesky(0.5 * (C + C.T))
        except np.linalg.LinAlgError:
            return None
        hn, he = float(res.half[-1, 0]), float(res.half[-1, 1])
        M = np.eye(2) - L.T @ np.diag([3.0 / hn**2, 3.0 / he**2]) @ L
        lam, W = np.linalg.eigh(0.5 * (M + M.T))
        g = 1.0 / np.maximum(lam, DEPRIOR_MIN_RATIO)
        x_w = W @ (g * (W.T @ np.linalg.solve(L, mu)))
        C_r = L @ ((W * g) @ W.T) @ L.T
        ev, V = np.linalg.eigh(0.5 * (C_r + C_r.T))
        C_r = (V * np.minimum(ev, big)) @ V.T
        return res.x_ins[k] + L @ x_w, C_r

    def _fix(self, res: PMHTResult, k: int, check_information: bool = True, widest: bool = True) -> Fix:
        t = float(res.t[k])
        xk = res.X[k, :2]
        if np.any(np.abs(xk - res.x_ins[k]) > res.half[k]) or not np.all(np.isfinite(xk)):
            return Fix.no_fix(t, "diverged: the estimate left the gated search window", self.name, res.nis)
        if res.profile_chi2 > self.max_profile_chi2:
            return Fix.no_fix(
                t,
                f"diverged: readings disagree with the map along the estimated track (chi2 per reading "
                f"{res.profile_chi2:.3g} above {self.max_profile_chi2:g})",
                self.name,
                res.nis,
            )
        if res.nis > self.max_nis:
            return Fix.no_fix(
                t, f"diverged: mean pseudo-measurement NIS {res.nis:.3g} above {self.max_nis:g}", self.name, res.nis
            )
        cov = 0.5 * (res.P[k, :2, :2] + res.P[k, :2, :2].T)
        if self.variance_factor:  # a-posteriori variance factor: mean NIS per 2-D pseudo-measurement / 2
            cov = cov * max(1.0, res.nis / 2.0)
        big = (10.0 * float(np.max(res.half[k]))) ** 2
        if self.crlb_floor:  # never claim more than the CRLB: the Loewner maximum of cov and J^-1 (J may be singular)
            cov = loewner_max(cov, res.fisher, big, information=True)
        amb = self._ambiguity_cov(res, k) if self.ambiguity_floor else None
        if amb is not None and amb[1] <= self.ambiguity_mass:
            # the batch likelihood is ambiguous within the gate (mass away from the EM's mode): cover its spread
            dep = self._deprior_estimate(res, k, big) if (self.ambiguity_deprior and self.deprior_location) else None
            if dep is not None:  # the readings' own estimate, not the EM's mode (module docstring)
                xk, cov_r = dep
                cov = loewner_max(cov_r, res.fisher, big, information=True) if self.crlb_floor else cov_r
            else:
                cov = loewner_max(cov, amb[0], big)
        ev, V = np.linalg.eigh(0.5 * (cov + cov.T))
        ev = np.minimum(ev, big)
        cov = (V * ev) @ V.T
        if self.variability_ref > 0:  # eq. 14 weighting: inflate where C / s^2 is below the reference
            cov = cov * max(1.0, self.variability_ref / max(res.variability / res.sigma2, 1e-300))
        if self.edge_check and res.ambiguity is not None and len(res.ambiguity[5]):
            # the likelihood's 99.9 % region runs out of the gate: the fix may not claim what lies beyond the border
            cut = truncated_sides(res.ambiguity[5], cov, res.half[-1])
            if len(cut) and widest:  # no wider gate: the fix claims no more along n than the gate's half-width
                for nrm in cut:
                    cov = loewner_max(cov, float(nrm @ res.half[-1]) ** 2 * np.outer(nrm, nrm), big)
            elif len(cut):
                sides = ", ".join(_SIDE_NAMES[(int(a), int(b))] for a, b in cut)
                return Fix.no_fix(
                    t,
                    f"{EDGE_REASON} ({sides}; gate half-widths {res.half[-1, 0]:.0f} / {res.half[-1, 1]:.0f} m: the "
                    f"prior may be too confident)",
                    self.name,
                    res.nis,
                )
        # the ambiguity term is the offset likelihood over this gate: its own information out (already out of the
        # covariance with ambiguity_deprior: every term is then the readings' own)
        gate = None if (self.ambiguity_floor and self.ambiguity_deprior) else res.half[-1]
        if check_information and res.cov_prior is not None and not adds_information(cov, res.cov_prior[k], gate):
            return information_refusal(t, cov, res.cov_prior[k], self.name, res.nis, gate)
        sig = float(np.sqrt(ev[-1]))
        if not self.partial_fixes and sig > float(np.max(res.half[k])):
            return Fix.no_fix(
                t,
                f"flat map: fix sigma {sig:.3g} m exceeds the gate half-width {float(np.max(res.half[k])):.3g} m",
                self.name,
                res.nis,
            )
        lat, lon = res.frame.to_latlon(xk[0], xk[1])
        return Fix(t, float(lat), float(lon), cov, True, "", res.nis, self.name)

    def match(self, window: MatchWindow, fmap: FieldMap) -> Fix:
        """Standard mode: one fix at the last scan of the batch (or a "no fix" with the reason)."""
        return self._solve(window, fmap)[1]

    def match_batch(self, window: MatchWindow, fmap: FieldMap) -> tuple[list[Fix], FloatArray]:
        """Retrodiction mode for fusing (Wang sec. 3.3): a fix per scan of the batch and the joint covariance
        (2J, 2J) m^2 of the J available ones (north/east per fix, in time order), for ``Fuser.correct_batch``.

        What is fused is the readings' evidence only. The EM's smoothed states are not: their relative geometry is
        the INS track itself (the batch moves with the INS displacement, its random walk is the INS's own variance
        growth), so fusing them would give the fuser back its own INS information about the motion within the batch
        as if it were new (tried: Melbourne -> Sydney, filter NEES 351). Instead the fixes are the final PDA
        pseudo-measurements ``zbar_k`` (eq. 4) with their covariances ``Rbar_k`` (eq. 5), independent across scans
        given the associations, plus one common-mode term ``E`` shared by every scan: the part of the standard-mode
        fix covariance (with its floors: variance factor, Cramer-Rao, ambiguity, eq. 14) that a rigid offset
        estimated from the pseudo-measurements alone does not cover (its positive part).
        Joint: ``blockdiag(f Rbar_k) + W + 1 1^T (x) E`` with ``f = max(1, mean NIS / 2)`` (the standard fix's
        variance factor) and ``W`` the INS's deformation within the batch relative to its last scan (a random walk
        with the INS's variance growth: scans ``j``, ``k`` share ``r_max(j,k)^2`` per axis; PDA pulls each
        pseudo-measurement towards the smoothed track, which follows the INS's shape; without ``W`` the NEES per fix
        was 3.9 on a synthetic map, 1.5 with it); ``E`` then tops up the generalised-least-squares covariance of the
        batch's common position to the standard-mode fix covariance. The batch is issued or refused as a whole, by
        the standard-mode rules at its last scan (information over the prior, divergence checks)."""
        res, last = self._solve(window, fmap)
        if isinstance(res, str):
            T = min(self.batch, len(window.readings))
            return [Fix.no_fix(float(t), res, self.name) for t in window.readings.t[len(window.readings) - T :]], (
                np.zeros((0, 0))
            )
        if not last.available:
            return [Fix.no_fix(float(t), last.reason, self.name, last.score) for t in res.t], np.zeros((0, 0))
        ok = [
            k
            for k in range(len(res.t))
            if np.all(np.isfinite(res.zbar[k])) and np.all(np.isfinite(res.Rbar[k])) and np.linalg.det(res.Rbar[k]) > 0
        ]
        if len(ok) < 2:
            reason = f"diverged: only {len(ok)} scans with a pseudo-measurement"
            return [Fix.no_fix(float(t), reason, self.name, res.nis) for t in res.t], np.zeros((0, 0))
        # the pseudo-measurements' covariances with the standard fix's a-posteriori variance factor (their scatter
        # about the smoothed track, mean NIS / 2 per 2-D scan): without it the per-scan part was over-confident
        # (synthetic gravity map, 40 batches: NEES per fix 3.9)
        vf = max(1.0, res.nis / 2.0) if self.variance_factor else 1.0
        Rk = {k: vf * 0.5 * (res.Rbar[k] + res.Rbar[k].T) for k in ok}
        J = len(ok)
        # the INS's deformation within the batch, relative to the last scan (a random walk: scans j and k share the
        # increments after the later of them, variance r_max(j,k)^2 per axis); PDA pulls each pseudo-measurement
        # towards the smoothed track along its level line, so this part of the INS error stays in the fixes
        # (synthetic map, 40 batches: NEES per fix 3.9 without this term)
        W = np.zeros((2 * J, 2 * J))
        if self.adaptive_drift and res.cov_prior is not None:
            var_ins = 0.5 * (res.cov_prior[:, 0, 0] + res.cov_prior[:, 1, 1])
            g2 = np.maximum(np.diff(var_ins), 0.0)
            r2 = np.append(np.cumsum(g2[::-1])[::-1], 0.0)[ok]
            W = np.kron(r2[np.maximum.outer(np.arange(J), np.arange(J))], np.eye(2))
        joint = W.copy()
        for i, k in enumerate(ok):
            joint[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] += Rk[k]
        H = np.tile(np.eye(2), (J, 1))
        C_pm = np.linalg.inv(H.T @ np.linalg.solve(joint, H))
        ev, V = np.linalg.eigh(0.5 * (last.cov_ne - C_pm + (last.cov_ne - C_pm).T))
        E = (V * np.maximum(ev, 0.0)) @ V.T
        fixes: list[Fix] = []
        joint += np.kron(np.ones((J, J)), E)
        for k in range(len(res.t)):
            if k in ok:
                lat, lon = res.frame.to_latlon(res.zbar[k, 0], res.zbar[k, 1])
                i = ok.index(k)
                C = joint[2 * i : 2 * i + 2, 2 * i : 2 * i + 2].copy()
                fixes.append(Fix(float(res.t[k]), float(lat), float(lon), C, True, "", res.nis, self.name))
            else:
                fixes.append(Fix.no_fix(float(res.t[k]), "no map candidate at this scan", self.name, res.nis))
        return fixes, 0.5 * (joint + joint.T)

    def match_all(self, window: MatchWindow, fmap: FieldMap) -> list[Fix]:
        """Retrodiction mode: a fix per scan of the batch (smoothed states and covariances)."""
        res = self._solve(window, fmap)[0]
        if isinstance(res, str):
            T = min(self.batch, len(window.readings))
            return [Fix.no_fix(float(t), res, self.name) for t in window.readings.t[len(window.readings) - T :]]
        return [self._fix(res, k) for k in range(len(res.t))]

    def _solve(self, window: MatchWindow, fmap: FieldMap) -> tuple[PMHTResult | str, Fix]:
        """The batch and its fix at the last scan, the gate widened by 2 up to ``gate_growth`` times while the fix
        is truncated by the gate's border (module docstring, "Search gate"); the last fix says so if it still is."""
        t = float(window.readings.t[-1]) if len(window.readings) else float("nan")
        grow = 1.0
        n_grow = max(int(self.gate_growth), 0)
        for i in range(n_grow + 1):
            res = self._run_safe(window, fmap, grow)
            if isinstance(res, str):
                return res, Fix.no_fix(t, res, self.name)
            fix = self._fix(res, len(res.t) - 1, widest=i == n_grow)
            if not fix.reason.startswith(EDGE_REASON):
                break
            grow *= 2.0
        return res, fix

    def _run_safe(self, window: MatchWindow, fmap: FieldMap, grow: float = 1.0) -> PMHTResult | str:
        try:
            res = self.run(window, fmap, grow)
        except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
            return f"PMHT failed on the data: {exc}"
        return res
