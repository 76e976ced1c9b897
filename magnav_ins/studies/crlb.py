"""The posterior Cramér-Rao bound of a study's flight: the limit column of the gravity comparison tables (issue 16).

For the scenario's truth trajectory, IMU grade, initial INS errors, reading times, reading noise and map, the INS
error state (LAYOUT_15) evolves linearly (:func:`magnav_ins.ins.error_model.system_matrices` along the truth,
discretised over each step by :func:`~magnav_ins.ins.error_model.discretize`) and each reading ``z = m(p) + v``,
``v ~ N(0, sigma^2)``, carries the Fisher information ``g g^T / sigma^2`` about the position error, ``g`` the map
gradient (:meth:`GridMap.gradient_ne`, the gradient of the interpolant the readings are drawn from) at the true
position. Because the truth is deterministic, this information needs no expectation over the state.
:func:`magnav_ins.maps.variability.posterior_crlb` runs the recursion (Tichavsky et al. 1998; Bergman 1999 ch. 4);
no estimator using these readings and this INS can have a smaller mean-square error (to first order). The vertical
channel is held as the studies hold it (down position and velocity frozen).

The suite's real readings (issue 13) follow ``z = m(p) + c + b(p) + v``: ``c`` an unknown level of the whole
flight, ``b`` the map's error (1-sigma from its error layer, correlated along track over ``ell``), ``v`` the sensor
noise. :func:`flight_crlb` with ``map_error`` counts ``b`` in each reading's variance (``sigma^2 + sigma_map(p)^2``)
and weighs each reading by ``min(1, ds / ell)`` (``ds`` its distance from the previous reading): readings inside one
correlation length are counted by their effective number. That weighting is an approximation of the correlated
model, not its exact information: the matchers' own effective count of a long section (``K^2 / sum C``,
:func:`magnav_ins.aiding.matchers.map_error.effective_count`) is ``ds / (sqrt(pi) ell)`` per reading, 1.8 times
less, so the approximation leans optimistic, as a lower bound should; it ignores the information that differences of
readings within one ``ell`` carry where the gradient changes faster than the map error (that would lower the bound).
With ``level_sigma`` > 0 the level ``c`` is one more state (constant, prior ``N(0, level_sigma^2)``, the matchers'
prior), so its Fisher information is projected out exactly rather than assumed known.

``metrics.json`` gets ``crlb_rms_horizontal_m`` (the RMS over the flight of ``sqrt(P_NN + P_EE)``, comparable with
``rms_horizontal_m``) and ``crlb_final_horizontal_m`` (at the end).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: longest covariance step of the bound (s); readings fall on step ends
CRLB_STEP_S = 10.0
#: states held by the altitude hold (down position and velocity), as the studies hold them
HOLD = (2, 5)


def flight_crlb(
    sc: Any,
    truth: Any,
    imu: Any,
    fmap: Any,
    step_s: float = CRLB_STEP_S,
    *,
    map_error: Any = None,
    level_sigma: float = 0.0,
    count_correlation: bool = True,
    readings: bool = True,
) -> tuple[FloatArray, FloatArray]:
    """The bound along the flight: times ``t`` (K+1,) s and horizontal ``sqrt(P_NN + P_EE)`` (K+1,) m.

    ``sc`` a :class:`~magnav_ins.studies.scenario.Scenario`, ``truth`` its truth trajectory, ``imu`` the ideal IMU
    along it (specific force for ``F``), ``fmap`` its map. Readings every ``sc.sensor.interval_s`` from
    ``interval_s`` on (as :func:`magnav_ins.studies.model.simulate_readings`), only where the map covers the truth.

    The reading model (module docstring): ``map_error`` a
    :class:`~magnav_ins.aiding.matchers.map_error.MapErrorModel` (its ``sigma_at`` at the true position is added
    to the sensor variance, and with ``count_correlation`` each reading is weighed by ``min(1, ds / ell)``);
    ``level_sigma`` (map unit) > 0: an unknown level with that prior, carried as a state (0: the level known).
    ``readings=False``: no reading at all, the free-inertial covariance along the same steps."""
    from ..maps.variability import posterior_crlb

    edges, P0, Phi, Q, J = flight_system(
        sc, truth, imu, fmap, step_s, map_error=map_error, level_sigma=level_sigma,
        count_correlation=count_correlation, readings=readings,
    )  # fmt: skip
    P = posterior_crlb(P0, Phi, Q, J, hold=HOLD)
    return edges, np.sqrt(P[:, 0, 0] + P[:, 1, 1])


def flight_system(
    sc: Any,
    truth: Any,
    imu: Any,
    fmap: Any,
    step_s: float = CRLB_STEP_S,
    *,
    map_error: Any = None,
    level_sigma: float = 0.0,
    count_correlation: bool = True,
    readings: bool = True,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """The linear(ised) system behind :func:`flight_crlb` (same arguments): step ends ``edges`` (K+1,) s, the prior
    ``P0`` (n, n), ``Phi`` and ``Q`` (K, n, n) over each step and the readings' Fisher information ``J`` (K, n, n)
    added at each step's end; ``n`` = 15 (LAYOUT_15) plus one level state per field component with ``level_sigma``
    > 0. States :data:`HOLD` are held by the mechanisation."""
    from scipy.spatial.transform import Rotation

    from ..core.frames import latlon_to_meters
    from ..ins.error_model import discretize, system_matrices
    from ..ins.imu_models import get_grade
    from ..maps.variability import fisher_information_ne
    from .model import initial_estimate

    grade = get_grade(sc.imu.grade)
    P0 = np.asarray(initial_estimate(sc, truth.at(0)).P, float)
    t0, t1 = float(truth.t[0]), float(truth.t[-1])
    s = sc.sensor
    t_read = np.arange(t0 + s.interval_s, t1 + 1e-9, s.interval_s)
    # step ends: every reading time, and at most step_s apart
    edges = [t0]
    for tr in np.append(t_read, t1):
        while tr - edges[-1] > step_s + 1e-9:
            edges.append(edges[-1] + step_s)
        if tr > edges[-1] + 1e-9:
            edges.append(float(tr))
    edges = np.asarray(edges)
    C_all = Rotation.from_quat(truth.q_nb).as_matrix()
    K = len(edges) - 1
    lat = np.interp(t_read, truth.t, truth.lat)
    lon = np.interp(t_read, truth.t, truth.lon)
    g = np.asarray(fmap.gradient_ne(lat, lon), float)
    g = g.reshape(len(t_read), -1, 2) if g.ndim == 3 else g.reshape(len(t_read), 1, 2)
    nc = g.shape[1]  # field components: one level state each
    nl = nc if level_sigma > 0 else 0
    n = 15 + nl
    Phi = np.zeros((K, n, n))
    Q = np.zeros((K, n, n))
    J = np.zeros((K, n, n))
    Phi[:, 15:, 15:] = np.eye(nl)  # a constant level
    for k in range(K):
        i = min(int(np.searchsorted(truth.t, edges[k])), len(truth.t) - 1)
        j = min(int(np.searchsorted(imu.t, edges[k], side="right")), len(imu.t) - 1)
        F, G, Qc = system_matrices(truth.lat[i], truth.h[i], truth.v_n[i], C_all[i], imu.accel_b[j], grade)
        Phi[k, :15, :15], Q[k, :15, :15] = discretize(F, G, Qc, float(edges[k + 1] - edges[k]))
    if nl:
        P0 = np.block([[P0, np.zeros((15, nl))], [np.zeros((nl, 15)), float(level_sigma) ** 2 * np.eye(nl)]])
    if readings:
        at = np.searchsorted(edges, t_read - 1e-9) - 1  # step whose end is the reading
        ok = (at >= 0) & (np.abs(edges[np.clip(at + 1, 0, K)] - t_read) < 1e-6)
        good = ok & np.all(np.isfinite(g), axis=(1, 2)) & np.asarray(fmap.covers(lat, lon))
        sigma = np.full(len(t_read), float(s.sigma))
        weight = np.ones(len(t_read))
        if map_error is not None:
            sm = np.asarray(map_error.sigma_at(lat, lon), float)
            sigma = np.sqrt(sigma**2 + np.where(np.isfinite(sm), sm, 0.0) ** 2)
            ell = float(map_error.correlation_m)
            if count_correlation and np.isfinite(ell) and ell > 0 and len(t_read) > 1:
                dn, de = latlon_to_meters(np.diff(lat), np.diff(lon), lat[1:])
                ds = np.hypot(dn, de)
                weight = np.minimum(1.0, np.append(ds[:1], ds) / ell)
        gg = np.where(np.isfinite(g), g, 0.0)
        info = fisher_information_ne(gg if nc > 1 else gg[:, 0, :], sigma, weight, level=nl > 0)
        idx = [0, 1, *range(15, n)]
        for r in np.flatnonzero(good):
            J[at[r]][np.ix_(idx, idx)] += info[r]
    return edges, P0, Phi, Q, J


def crlb_metrics(t: FloatArray, sigma_h: FloatArray) -> dict[str, float]:
    """``crlb_rms_horizontal_m`` (time-weighted RMS over the flight) and ``crlb_final_horizontal_m`` (m)."""
    dt = np.diff(t)
    mid2 = 0.5 * (sigma_h[1:] ** 2 + sigma_h[:-1] ** 2)
    rms = float(np.sqrt(np.sum(mid2 * dt) / np.sum(dt))) if dt.size else float(sigma_h[-1])
    return {"crlb_rms_horizontal_m": rms, "crlb_final_horizontal_m": float(sigma_h[-1])}


def bound_monte_carlo(
    P0: FloatArray,
    Phi: FloatArray,
    Q: FloatArray,
    J: FloatArray,
    runs: int,
    rng: np.random.Generator,
    hold: tuple[int, ...] = HOLD,
) -> tuple[FloatArray, FloatArray]:
    """Runs of the estimator that attains the bound: the Kalman filter of the linear-Gaussian system that
    :func:`flight_system` describes (its covariance is :func:`~magnav_ins.maps.variability.posterior_crlb`'s),
    with the free INS of the same draw beside it, for Wang's test on the same draws as the suite makes it.

    Each run draws the initial error ``x0 ~ N(0, P0)``, the process noise of every step and the readings' noise;
    ``J``'s eigen-decomposition gives readings ``u^T x + v``, ``v ~ N(0, 1 / lambda)`` with the same information.
    The free INS's error is ``x`` (never corrected), the filter's ``x - x_hat``. Held states (``hold``) have their
    variance kept and their correlations dropped each step, as in ``posterior_crlb``: their effect enters the other
    states as independent noise each step. Returns the horizontal errors (m), filter and free, each (runs, K+1)."""
    n = P0.shape[0]
    free_i = [i for i in range(n) if i not in hold]
    hold_l = list(hold)
    P = np.asarray(P0, float)[np.ix_(free_i, free_i)].copy()
    P_hh = np.asarray(P0, float)[np.ix_(hold_l, hold_l)] if hold_l else None
    L0 = np.linalg.cholesky(P + 1e-18 * np.eye(len(free_i)))
    x = rng.standard_normal((runs, len(free_i))) @ L0.T
    e = x.copy()
    K = Phi.shape[0]
    err = np.empty((runs, K + 1))
    fre = np.empty((runs, K + 1))
    err[:, 0] = np.hypot(e[:, 0], e[:, 1])
    fre[:, 0] = err[:, 0]
    for k in range(K):
        F = Phi[k][np.ix_(free_i, free_i)]
        Qk = Q[k][np.ix_(free_i, free_i)]
        if hold_l:
            Fh = Phi[k][np.ix_(free_i, hold_l)]
            Qk = Qk + Fh @ P_hh @ Fh.T
        Qk = 0.5 * (Qk + Qk.T)
        w, V = np.linalg.eigh(Qk)
        noise = (rng.standard_normal((runs, len(free_i))) * np.sqrt(np.maximum(w, 0.0))) @ V.T
        x = x @ F.T + noise
        e = e @ F.T + noise
        P = F @ P @ F.T + Qk
        Jf = J[k][np.ix_(free_i, free_i)]
        if np.any(Jf):
            lam, U = np.linalg.eigh(0.5 * (Jf + Jf.T))
            keep = lam > 1e-12 * max(float(lam.max()), 1e-300)
            H, lam = U[:, keep].T, lam[keep]
            S = H @ P @ H.T + np.diag(1.0 / lam)
            G = np.linalg.solve(S, H @ P).T  # gain P H^T S^-1
            v = rng.standard_normal((runs, len(lam))) / np.sqrt(lam)
            e = e - (e @ H.T + v) @ G.T
            IKH = np.eye(len(free_i)) - G @ H
            P = IKH @ P @ IKH.T + G @ np.diag(1.0 / lam) @ G.T
        err[:, k + 1] = np.hypot(e[:, 0], e[:, 1])
        fre[:, k + 1] = np.hypot(x[:, 0], x[:, 1])
    return err, fre
