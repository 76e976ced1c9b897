"""The free-inertial fuser over a run of IMU samples in one compiled call, with an estimate after chosen samples.

:func:`free_run` is :meth:`.common.InertialCore.propagate` (the strapdown stepper with the attitude integrals of the
covariance step, :func:`magnav_ins.ins.strapdown._stepper_run_sums`) followed by :meth:`.common.InertialCore.estimate`
after each chosen sample, for the 15-state filter without optional states: every covariance step where the Python
path takes one (where a step of ``cov_step_s`` s ends, and at each estimate), with the same matrices
(:func:`.cov_step._step_15` from the step's attitude integrals), the same prediction ``Phi P Phi^T + Qd``, the same
:func:`.common.symmetrise` (with ``floor = 0``) and the same altitude-hold freeze of the down states.

Why: the log replay of the free-inertial baseline records an estimate every 0.2 s, and each estimate through the
Python objects (the batch push, a ``NavState``, a ``NavEstimate``, the covariance step's wrappers, the checkpoint
kept for rewinds) cost ~0.4 ms, more than 10x the mechanisation of the 80 samples (400 Hz) between two of them: a
1 M-row log replayed at ~100-140 k samples/s; in one call ~1 M samples/s. The free-inertial fuser never rewinds
(it applies no fix), so no checkpoint is kept here. The same numbers as the Python path to rounding (the matrix
products go through the BLAS numba links, whose summation order may differ in the last bit; the replay test holds
them to 1e-12 relative and measures them bit for bit).

Units: as :mod:`.common` (SI, NED, body FRD, positions rad and ellipsoidal metres).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ...core.types import FloatArray
from ...ins.strapdown import _H, _LAT, _NX, _Q, _V, _dcm_into, _stepper_run_sums
from .cov_step import _step_15

#: columns of the rows :func:`free_run` writes: t, lat, lon, h, v_n (3), q_nb (4, unit), P_nn, P_ne, P_ee
ROW_COLUMNS = ("t", "lat", "lon", "h", "vn", "ve", "vd", "qx", "qy", "qz", "qw", "P_nn", "P_ne", "P_ee")


@njit(cache=True)
def _positive_definite_where_live(C: FloatArray, live: np.ndarray) -> bool:
    """:func:`.common._positive_definite_where_live`: the dead states (no variance) exactly uncorrelated zeros, and
    a Cholesky factor of the live block exists (every pivot > 0, as LAPACK's ``potrf`` asks)."""
    n = C.shape[0]
    for i in range(n):
        if not live[i]:
            for j in range(n):
                if C[i, j] != 0.0 or C[j, i] != 0.0:
                    return False
    idx = np.flatnonzero(live)
    m = idx.shape[0]
    L = np.zeros((m, m))
    for j in range(m):
        s = C[idx[j], idx[j]]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not (s > 0.0):
            return False
        L[j, j] = math.sqrt(s)
        for i in range(j + 1, m):
            s = C[idx[i], idx[j]]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / L[j, j]
    return True


@njit(cache=True)
def symmetrise0(P: FloatArray) -> FloatArray:
    """:func:`.common.symmetrise` with ``floor = 0``: ``(P + P^T)/2``, its eigenvalues clipped at 0 on the
    correlation-scaled matrix when it is not positive semi-definite."""
    P = 0.5 * (P + P.T)
    n = P.shape[0]
    sd = np.empty(n)
    live = np.empty(n, dtype=np.bool_)
    for i in range(n):
        live[i] = P[i, i] > 0.0
        sd[i] = math.sqrt(P[i, i]) if live[i] else 1.0
    C = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            C[i, j] = P[i, j] / (sd[i] * sd[j])
    if _positive_definite_where_live(C, live):
        return P
    w, V = np.linalg.eigh(C)
    if w.min() >= 0.0:
        return P
    W = V * np.maximum(w, 0.0)
    out = W @ V.T
    for i in range(n):
        for j in range(n):
            out[i, j] *= sd[i] * sd[j]
    return out


@njit(cache=True)
def _cov_step(
    s: FloatArray,
    C_sum: FloatArray,
    fn_sum: FloatArray,
    Cf_sum: FloatArray,
    Cw_sum: FloatArray,
    acc: FloatArray,
    t_cov: FloatArray,
    P: FloatArray,
    held: bool,
    inv_tau_a: float,
    inv_tau_g: float,
    qc: FloatArray,
) -> None:
    """:meth:`.common.InertialCore._advance_cov` without the checkpoint: ``P`` (15,15) from ``t_cov[0]`` to the
    stepper time ``s[0]`` (nothing when not later), the step integrals cleared, ``t_cov[0]`` moved."""
    dt = s[0] - t_cov[0]
    if dt <= 0.0:
        return
    x = s[1 : 1 + _NX]
    q = x[_Q : _Q + 4] / math.sqrt(
        np.dot(x[_Q : _Q + 4], x[_Q : _Q + 4])
    )  # the NavState the Python path builds normalises it
    C_end = np.empty((3, 3))
    _dcm_into(q, C_end)
    sum_dt = acc[0]
    averaged = sum_dt > 0
    C_mean = C_sum / sum_dt if averaged else C_end.copy()
    fn_mean = fn_sum / sum_dt if averaged else np.zeros(3)
    v = x[_V : _V + 3].copy()
    Phi, Qd = _step_15(x[_LAT], x[_H], v, C_end, C_mean, fn_mean, averaged, inv_tau_a, inv_tau_g, qc, dt)
    h2, h5 = P[2, 2], P[5, 5]
    Pn = symmetrise0(Phi @ P @ np.ascontiguousarray(Phi.T) + Qd)
    if held:  # the INS holds the altitude: no down error growth (as _advance_cov)
        for i in range(Pn.shape[0]):
            Pn[2, i] = Pn[i, 2] = Pn[5, i] = Pn[i, 5] = 0.0
        Pn[2, 2], Pn[5, 5] = h2, h5
    P[:, :] = Pn
    t_cov[0] = s[0]
    C_sum[:, :] = 0.0
    fn_sum[:] = 0.0
    Cf_sum[:, :] = 0.0
    Cw_sum[:, :] = 0.0
    acc[:] = 0.0


@njit(cache=True)
def free_run(
    s: FloatArray,
    t: FloatArray,
    w: FloatArray,
    f: FloatArray,
    coning_sculling: bool,
    holds: FloatArray,
    C_sum: FloatArray,
    fn_sum: FloatArray,
    Cf_sum: FloatArray,
    Cw_sum: FloatArray,
    C_prev: FloatArray,
    acc: FloatArray,
    t_cov: FloatArray,
    cov_step_s: float,
    P: FloatArray,
    held: bool,
    inv_tau_a: float,
    inv_tau_g: float,
    qc: FloatArray,
    out_idx: np.ndarray,
    rows: FloatArray,
) -> int:
    """Rate samples ``t`` (m,) s, ``w`` rad/s, ``f`` m/s^2 (m,3) (bias-corrected) through the stepper work vector
    ``s`` with the attitude integrals (``C_sum`` ... ``acc``, :class:`magnav_ins.ins.strapdown.AttitudeSums`) and
    the covariance ``P`` (15,15) as of ``t_cov[0]``, all updated in place; after sample ``out_idx[o]`` (increasing)
    the estimate goes to ``rows[o]`` (:data:`ROW_COLUMNS`). ``holds`` (m,): the altitude hold of each sample (NaN:
    free); ``held``: the fuser holds the altitude (the down states frozen in ``P``). Returns the number of samples
    done (m), or ``-(k + 1)`` when sample ``k`` does not advance the time."""
    m = t.shape[0]
    q_out = np.empty((m, 4))
    n_out = out_idx.shape[0]
    i = 0
    o = 0
    while i < m:
        end = out_idx[o] + 1 if o < n_out else m
        j = i
        while j < end:  # InertialCore._run over samples i..end-1 (one push)
            n = _stepper_run_sums(s, t[j:end], w[j:end], f[j:end], coning_sculling, holds[j:end], C_sum, fn_sum,
                                  Cf_sum, Cw_sum, C_prev, acc, t_cov[0], cov_step_s, False, q_out[j:end])  # fmt: skip
            if n < 0:
                return -(j + (-n - 1)) - 1
            j += n
            if j < end or t[end - 1] - t_cov[0] >= cov_step_s - 1e-9:
                _cov_step(s, C_sum, fn_sum, Cf_sum, Cw_sum, acc, t_cov, P, held, inv_tau_a, inv_tau_g, qc)
        if o < n_out:  # InertialCore.estimate
            _cov_step(s, C_sum, fn_sum, Cf_sum, Cw_sum, acc, t_cov, P, held, inv_tau_a, inv_tau_g, qc)
            x = s[1 : 1 + _NX]
            r = rows[o]
            r[0] = s[0]
            for k in range(_Q):
                r[1 + k] = x[k]
            nq = math.sqrt(np.dot(x[_Q : _Q + 4], x[_Q : _Q + 4]))
            for k in range(4):
                r[1 + _Q + k] = x[_Q + k] / nq
            r[11], r[12], r[13] = P[0, 0], 0.5 * (P[0, 1] + P[1, 0]), P[1, 1]
            o += 1
        i = end
    return m
