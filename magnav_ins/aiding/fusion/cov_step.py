"""One covariance step of the 15-state INS error model, compiled: ``(Phi, Qd)`` over ``dt`` s.

The same model and formulas as :func:`magnav_ins.ins.error_model.system_matrices` (Groves 2013 eq. 14.63-14.71 in
NED metres; noise ``[w_a, w_g, w_ba, w_bg]``, ``Qc = diag(VRW^2, ARW^2, 2 sigma_a^2 / tau_a, 2 sigma_g^2 / tau_g)``)
with the step's attitude-dependent blocks averaged as in :func:`.common.step_matrices` (``-mean(C_nb)`` for the bias
columns, ``-[mean(f_n) x]`` for the tilt column), discretised by Van Loan (``B = exp([[-F, G Qc G^T], [0, F^T]] dt)``,
``Phi = B22^T``, ``Qd = Phi B12``) with the product-only matrix exponential of :func:`.common._expm` (scaling and
squaring of a Taylor polynomial, Moler & Van Loan 2003 method 3), on the blocks of the block-triangular ``A``.

Why compiled: a fuser takes a covariance step at every reading and output (10-15 per second in the bridge and the
replay); in Python the ~60 small numpy operations of building ``F`` and the 30x30 exponential cost ~0.3 ms per step,
more than the whole strapdown mechanisation between steps. The tests hold these matrices equal to the Python
path's (:func:`.common.step_matrices` with the optional states, which stays in Python) to rounding.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit

from ...core.frames import WGS84_A, WGS84_E2, WGS84_F, WGS84_GAMMA_E, WGS84_K, WGS84_M, WGS84_OMEGA_E
from ...core.types import FloatArray

_A = WGS84_A
_E2 = WGS84_E2
_W = WGS84_OMEGA_E


@njit(cache=True)
def _skew(v0: float, v1: float, v2: float) -> FloatArray:
    out = np.zeros((3, 3))
    out[0, 1], out[0, 2] = -v2, v1
    out[1, 0], out[1, 2] = v2, -v0
    out[2, 0], out[2, 1] = -v1, v0
    return out


@njit(cache=True)
def _expm(A: FloatArray, order: int) -> FloatArray:
    """:func:`.common._expm`, compiled."""
    norm = np.abs(A).sum(axis=0).max()
    s = 0
    if norm > 0.25:
        s = max(0, int(math.ceil(math.log2(norm / 0.25))))
    M = A / (2.0**s)
    n = A.shape[0]
    E = np.eye(n)
    term = np.eye(n)
    for k in range(1, order + 1):
        term = (term @ M) / k
        E = E + term
    for _ in range(s):
        E = E @ E
    return E


@njit(cache=True)
def _step_15(
    lat: float,
    h: float,
    v: FloatArray,
    C: FloatArray,
    C_mean: FloatArray,
    fn_mean: FloatArray,
    averaged: bool,
    inv_tau_a: float,
    inv_tau_g: float,
    qc: FloatArray,
    dt: float,
) -> tuple[FloatArray, FloatArray]:
    vn, ve, vd = v[0], v[1], v[2]
    sl = math.sin(lat)
    cl = math.cos(lat)
    s2 = sl**2
    den = 1.0 - _E2 * s2
    r_e = _A / math.sqrt(den)
    r_n = _A * (1.0 - _E2) / den**1.5
    rn, re = r_n + h, r_e + h
    tl = sl / cl
    w_ie = np.array([_W * cl, 0.0, -_W * sl])
    w_en = np.array([ve / re, -vn / rn, -ve * math.tan(lat) / re])
    w_in = w_ie + w_en

    dwie_dp = np.zeros((3, 3))
    dwie_dp[0, 0] = -_W * sl / rn
    dwie_dp[2, 0] = -_W * cl / rn
    dwen_dp = np.zeros((3, 3))
    dwen_dp[2, 0] = -ve / (cl * cl) / re / rn
    dwen_dp[0, 2] = ve / re**2
    dwen_dp[1, 2] = -vn / rn**2
    dwen_dp[2, 2] = -ve * tl / re**2
    dwen_dv = np.zeros((3, 3))
    dwen_dv[0, 1] = 1.0 / re
    dwen_dv[1, 0] = -1.0 / rn
    dwen_dv[2, 1] = -tl / re

    F = np.zeros((15, 15))
    for i in range(3):
        F[i, 3 + i] = 1.0
    F[0, 0] = -vd / rn
    F[0, 2] = vn / rn
    F[1, 0] = ve * tl / rn
    F[1, 1] = -vd / re - vn * tl / rn
    F[1, 2] = ve / re
    Wv = 2.0 * w_ie + w_en
    sv = _skew(vn, ve, vd)
    F[3:6, 0:3] = sv @ (2.0 * dwie_dp + dwen_dp)
    g0 = WGS84_GAMMA_E * (1.0 + WGS84_K * s2) / math.sqrt(1.0 - _E2 * s2)
    dgd_dh = g0 * (-2.0 / _A * (1.0 + WGS84_F + WGS84_M - 2.0 * WGS84_F * math.sin(lat) ** 2) + 6.0 * h / _A**2)
    F[5, 2] += -dgd_dh
    F[3, 2] += 8.08e-9 * math.sin(2.0 * lat)
    F[3:6, 3:6] = -_skew(Wv[0], Wv[1], Wv[2]) + sv @ dwen_dv
    # f_b = 0 at the step's end point: the tilt column and the bias columns come from the step averages
    F[3:6, 9:12] = -C
    F[6:9, 0:3] = -(dwie_dp + dwen_dp)
    F[6:9, 3:6] = -dwen_dv
    F[6:9, 6:9] = -_skew(w_in[0], w_in[1], w_in[2])
    F[6:9, 12:15] = -C
    for i in range(3):
        F[9 + i, 9 + i] = -inv_tau_a
        F[12 + i, 12 + i] = -inv_tau_g
    if averaged:
        F[3:6, 6:9] = -_skew(fn_mean[0], fn_mean[1], fn_mean[2])
        F[3:6, 9:12] = -C_mean
        F[6:9, 12:15] = -C_mean

    G = np.zeros((15, 12))
    G[3:6, 0:3] = C
    G[6:9, 3:6] = C
    for i in range(3):
        G[9 + i, 6 + i] = 1.0
        G[12 + i, 9 + i] = 1.0
    Qc = np.zeros((12, 12))
    for i in range(12):
        Qc[i, i] = qc[i]

    return _van_loan(F, G @ Qc @ G.T, dt, 10)


@njit(cache=True)
def _van_loan(F: FloatArray, GQG: FloatArray, dt: float, order: int) -> tuple[FloatArray, FloatArray]:
    """``(Phi, Qd)`` from ``B = exp(A dt)``, ``A = [[-F, G Qc G^T], [0, F^T]]``, by :func:`_expm`'s scaling and
    squaring of a Taylor polynomial carried out on the 15x15 blocks: ``A`` and all its powers are block upper
    triangular, so each product needs four block products instead of the eight of the 30x30 one (the same
    numbers to rounding)."""
    M11 = -F * dt
    M12 = GQG * dt
    M22 = np.ascontiguousarray(F.T) * dt
    norm = 0.0  # 1-norm of A dt: the largest column sum, columns of [M11; 0] and [M12; M22]
    n = F.shape[0]
    for j in range(n):
        c1 = 0.0
        c2 = 0.0
        for i in range(n):
            c1 += abs(M11[i, j])
            c2 += abs(M12[i, j]) + abs(M22[i, j])
        norm = max(norm, c1, c2)
    s = 0
    if norm > 0.25:
        s = max(0, int(math.ceil(math.log2(norm / 0.25))))
    sc = 2.0**s
    M11, M12, M22 = M11 / sc, M12 / sc, M22 / sc
    E11, E12, E22 = np.eye(n), np.zeros((n, n)), np.eye(n)
    T11, T12, T22 = np.eye(n), np.zeros((n, n)), np.eye(n)
    for k in range(1, order + 1):
        T11, T12, T22 = (T11 @ M11) / k, (T11 @ M12 + T12 @ M22) / k, (T22 @ M22) / k
        E11, E12, E22 = E11 + T11, E12 + T12, E22 + T22
    for _ in range(s):
        E11, E12, E22 = E11 @ E11, E11 @ E12 + E12 @ E22, E22 @ E22
    Phi = np.ascontiguousarray(E22.T)
    Qd = Phi @ E12
    return Phi, 0.5 * (Qd + Qd.T)


def noise_constants(noise: object) -> tuple[float, float, FloatArray]:
    """``(1 / tau_a, 1 / tau_g, diag(Qc))`` of an :class:`.common.ImuNoise` (or an ImuGrade), as
    :func:`magnav_ins.ins.error_model.system_matrices` reads them (0 for a random-constant bias)."""
    from ...ins.error_model import bias_psd

    tau_a, tau_g = float(noise.accel_bias_tau), float(noise.gyro_bias_tau)  # type: ignore[attr-defined]
    qc = np.concatenate([noise.arr("vrw") ** 2, noise.arr("arw") ** 2, bias_psd(noise, "accel"),  # type: ignore[attr-defined]
                         bias_psd(noise, "gyro")])  # fmt: skip
    return (1.0 / tau_a if math.isfinite(tau_a) else 0.0), (1.0 / tau_g if math.isfinite(tau_g) else 0.0), qc


@functools.lru_cache(maxsize=64)
def noise_constants_cached(noise: object) -> tuple[float, float, FloatArray]:
    """:func:`noise_constants` of a hashable (immutable) noise object, computed once."""
    out = noise_constants(noise)
    out[2].setflags(write=False)
    return out


def step_matrices_15(
    lat: float,
    h: float,
    v_n: FloatArray,
    C_end: FloatArray,
    C_sum: FloatArray,
    fn_sum: FloatArray,
    sum_dt: float,
    dt: float,
    constants: tuple[float, float, FloatArray],
) -> tuple[FloatArray, FloatArray]:
    """``(Phi, Qd)`` (15,15) of one step of ``dt`` s ending at (``lat`` rad, ``h`` m, ``v_n`` m/s NED, attitude
    ``C_end``), with the step integrals ``C_sum``, ``fn_sum`` over ``sum_dt`` s (module docstring); ``constants``
    from :func:`noise_constants`."""
    averaged = sum_dt > 0
    C_mean = C_sum / sum_dt if averaged else C_end
    fn_mean = fn_sum / sum_dt if averaged else np.zeros(3)
    inv_a, inv_g, qc = constants
    return _step_15(float(lat), float(h), np.ascontiguousarray(v_n, dtype=float), np.ascontiguousarray(C_end),
                    np.ascontiguousarray(C_mean), np.ascontiguousarray(fn_mean), bool(averaged), inv_a, inv_g, qc,
                    float(dt))  # fmt: skip
