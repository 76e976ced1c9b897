"""Compiled (numba) kernels for likelihood scans over regular grids of candidate positions.

Grids are given by their north axis ``n_ax`` (ni,) and east axis ``e_ax`` (nj,) in metres of the matcher's working
frame, and values / log-likelihoods as ``(ni, nj[, c])`` arrays. ``-inf`` log-likelihood marks nodes off the map.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@nb.njit(cache=True)
def grid_loglik(values: FloatArray, z: FloatArray, s2: float) -> FloatArray:
    """``-|z - m|^2 / (2 s2)`` at every node of ``values`` (ni, nj, c); ``-inf`` where a component is NaN."""
    ni, nj, c = values.shape
    out = np.empty((ni, nj))
    for i in range(ni):
        for j in range(nj):
            acc = 0.0
            for m in range(c):
                r = z[m] - values[i, j, m]
                acc += r * r
            out[i, j] = -0.5 * acc / s2 if np.isfinite(acc) else -np.inf
    return out


@nb.njit(cache=True, nogil=True)
def grid_scan1(values: FloatArray, z: FloatArray, s2: float, ic: int, jc: int) -> tuple[FloatArray, int, float]:
    """One pass for a single reading: log-likelihood grid (as :func:`grid_loglik`), the flat index of its maximum,
    and the feature variability about node ``(ic, jc)`` (as :func:`grid_variability`, which it calls when the
    centre node is NaN)."""
    ni, nj, c = values.shape
    out = np.empty((ni, nj))
    centre_ok = True
    for m in range(c):
        if not np.isfinite(values[ic, jc, m]):
            centre_ok = False
    best = -np.inf
    kbest = 0
    sv = 0.0
    nv = 0
    for i in range(ni):
        for j in range(nj):
            acc = 0.0
            dv = 0.0
            for m in range(c):
                v = values[i, j, m]
                r = z[m] - v
                acc += r * r
                if centre_ok:
                    q = v - values[ic, jc, m]
                    dv += q * q
            lv = -0.5 * acc / s2 if np.isfinite(acc) else -np.inf
            out[i, j] = lv
            if lv > best:
                best = lv
                kbest = i * nj + j
            if centre_ok and np.isfinite(dv) and dv > 0.0:
                sv += dv
                nv += 1
    if centre_ok:
        var = sv / nv if nv > 0 else 0.0
    else:
        var = grid_variability(values, ic, jc)
    return out, kbest, var


@nb.njit(cache=True)
def grid_moments(
    logl: FloatArray, n_ax: FloatArray, e_ax: FloatArray, lmax: float, n0: float, e0: float
) -> tuple[float, float, float, float, float]:
    """Normalised-likelihood statistics: (peak normalised mass, S_nn, S_ne, S_ee) about ``(n0, e0)`` and the
    normaliser ``sum exp(logl - lmax)``."""
    ni, nj = logl.shape
    tot = 0.0
    snn = 0.0
    sne = 0.0
    see = 0.0
    for i in range(ni):
        dn = n_ax[i] - n0
        for j in range(nj):
            d = logl[i, j] - lmax
            if d < -46.0:  # p < 1e-20: negligible (also skips -inf)
                continue
            p = np.exp(d)
            de = e_ax[j] - e0
            tot += p
            snn += p * dn * dn
            sne += p * dn * de
            see += p * de * de
    return 1.0 / tot, snn / tot, sne / tot, see / tot, tot


@nb.njit(cache=True)
def grid_far_max(logl: FloatArray, n_ax: FloatArray, e_ax: FloatArray, n0: float, e0: float, dmin2: float) -> float:
    """Largest log-likelihood at nodes at least ``sqrt(dmin2)`` from ``(n0, e0)`` (``-inf`` if none)."""
    ni, nj = logl.shape
    best = -np.inf
    for i in range(ni):
        dn = n_ax[i] - n0
        for j in range(nj):
            de = e_ax[j] - e0
            if dn * dn + de * de >= dmin2 and logl[i, j] > best:
                best = logl[i, j]
    return best


@nb.njit(cache=True)
def grid_variability(values: FloatArray, ic: int, jc: int) -> float:
    """Wang eq. 14 about node ``(ic, jc)``: mean of ``|m_ij - m_c|^2`` over the other finite nodes; if the centre
    is NaN, twice the summed component variance of the finite nodes (the same expectation)."""
    ni, nj, c = values.shape
    centre_ok = True
    for m in range(c):
        if not np.isfinite(values[ic, jc, m]):
            centre_ok = False
    s = 0.0
    cnt = 0
    if centre_ok:
        for i in range(ni):
            for j in range(nj):
                d = 0.0
                for m in range(c):
                    q = values[i, j, m] - values[ic, jc, m]
                    d += q * q
                if np.isfinite(d) and d > 0.0:
                    s += d
                    cnt += 1
        return s / cnt if cnt > 0 else 0.0
    out = 0.0
    for m in range(c):
        s1 = 0.0
        s2 = 0.0
        cnt = 0
        for i in range(ni):
            for j in range(nj):
                v = values[i, j, m]
                if np.isfinite(v):
                    s1 += v
                    s2 += v * v
                    cnt += 1
        if cnt > 1:
            mu = s1 / cnt
            out += 2.0 * (s2 / cnt - mu * mu)
    return out


@nb.njit(cache=True)
def grid_gradient_rms(values: FloatArray, dn: float, de: float) -> float:
    """RMS horizontal gradient magnitude (unit/m, summed over components) by forward differences; NaN if none."""
    ni, nj, c = values.shape
    sn = 0.0
    cn = 0
    se = 0.0
    ce = 0
    for i in range(ni):
        for j in range(nj):
            if i + 1 < ni:
                d = 0.0
                for m in range(c):
                    q = (values[i + 1, j, m] - values[i, j, m]) / dn
                    d += q * q
                if np.isfinite(d):
                    sn += d
                    cn += 1
            if j + 1 < nj:
                d = 0.0
                for m in range(c):
                    q = (values[i, j + 1, m] - values[i, j, m]) / de
                    d += q * q
                if np.isfinite(d):
                    se += d
                    ce += 1
    if cn == 0 or ce == 0:
        return np.nan
    return np.sqrt(sn / cn + se / ce)


@nb.njit(cache=True, nogil=True)  # the bridge scans in a worker thread: let the IMU loop run meanwhile
def section_loglik(
    values: FloatArray,
    y0: float,
    dy: float,
    x0: float,
    dx: float,
    pos: FloatArray,
    z: FloatArray,
    n_ax: FloatArray,
    e_ax: FloatArray,
    s2: float,
    demean: float,
    difference: bool,
) -> FloatArray:
    """Log-likelihood of a section of readings slid rigidly over a local grid (Shockley sec. 4.5), bilinear map
    values read straight from the grid ``values`` (ny, nx, c) with axes ``y0 + i dy`` (north), ``x0 + j dx``
    (east). ``pos`` (nz, 2) are the readings' INS positions in the grid's axes, ``z`` (nz, c) the readings; the
    candidate offsets are ``n_ax`` x ``e_ax``. ``difference`` uses successive differences, ``demean`` removes that
    fraction of the section means (in that order; 1 = all, a marginalised level offset is less, ``map_error.level_fraction``); ``s2`` is the variance of the (differenced) residual. ``-inf`` off the grid."""
    ny, nx, c = values.shape
    nz = pos.shape[0]
    ni, nj = n_ax.shape[0], e_ax.shape[0]
    out = np.empty((ni, nj))
    buf = np.empty((nz, c))
    res = np.empty((nz, c))
    for a in range(ni):
        for b in range(nj):
            ok = True
            for k in range(nz):
                fy = (pos[k, 0] + n_ax[a] - y0) / dy
                fx = (pos[k, 1] + e_ax[b] - x0) / dx
                if not (fy >= 0.0 and fy <= ny - 1 and fx >= 0.0 and fx <= nx - 1):
                    ok = False
                    break
                i = min(int(fy), ny - 2)
                j = min(int(fx), nx - 2)
                ty = fy - i
                tx = fx - j
                for m in range(c):
                    v = (
                        (1.0 - ty) * (1.0 - tx) * values[i, j, m]
                        + (1.0 - ty) * tx * values[i, j + 1, m]
                        + ty * (1.0 - tx) * values[i + 1, j, m]
                        + ty * tx * values[i + 1, j + 1, m]
                    )
                    buf[k, m] = v
                    res[k, m] = z[k, m] - v
            if not ok:
                out[a, b] = -np.inf
                continue
            n_use = nz
            if difference and nz > 1:
                for k in range(nz - 1):
                    for m in range(c):
                        res[k, m] = res[k + 1, m] - res[k, m]
                n_use = nz - 1
            if demean > 0.0 and n_use > 1:
                for m in range(c):
                    mu = 0.0
                    for k in range(n_use):
                        mu += res[k, m]
                    mu = demean * mu / n_use
                    for k in range(n_use):
                        res[k, m] -= mu
            acc = 0.0
            for k in range(n_use):
                for m in range(c):
                    acc += res[k, m] * res[k, m]
            out[a, b] = -0.5 * acc / s2 if np.isfinite(acc) else -np.inf
    return out
