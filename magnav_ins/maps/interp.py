"""Compiled interpolation kernels on regular 2-D grids (numba): bilinear and bicubic (Keys cubic convolution).

The kernels work in *axis units* (rad for geodetic grids, m for local grids) on a grid whose nodes are
``y_k = y0 + k * dy`` (k = 0..ny-1, the northing / latitude axis) and ``x_j = x0 + j * dx`` (j = 0..nx-1, the easting /
longitude axis). Values are ``(ny, nx, c)`` float64 with ``c`` components (1 for scalar maps, 3 for NED vector maps).

* Bilinear: exact for fields ``a + b*y + c*x + d*x*y``; its gradient is the analytic derivative inside the cell.
* Bicubic: Keys (1981) cubic convolution with ``a = -1/2`` (Keys, *Cubic convolution interpolation for digital
  image processing*, IEEE TASSP 29(6), eq. 15), third-order accurate: exact for every polynomial of degree <= 2 in
  each axis. At the grid edges the missing node is Keys' boundary extrapolation ``f[-1] = 3 f[0] - 3 f[1] + f[2]``
  (Keys eq. 25), which keeps the exactness for quadratics up to the border.

A query outside ``[y0, y0 + (ny-1) dy] x [x0, x0 + (nx-1) dx]`` gives NaN, as does a query whose stencil (the 2 x 2
bilinear cell, or the 4 x 4 bicubic stencil) holds a NaN node. ``period`` > 0 wraps the x offset into
``[0, period)`` (longitude, ``2 pi``); 0 disables wrapping.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

_NAN = np.nan
_EDGE = 1e-9  # grid-index tolerance at the edges: a query on the last node is not lost to rounding


@nb.njit(cache=True, inline="always")
def _cell(q: float, q0: float, dq: float, n: int, period: float) -> tuple[int, float]:
    """Cell index ``i`` in ``[0, n-2]`` and fraction ``t`` in ``[0, 1]``; ``i = -1`` when outside the axis."""
    d = q - q0
    if period > 0.0 and (d < 0.0 or d >= period):
        d = d - period * np.floor(d / period)
    f = d / dq
    if not (f >= -_EDGE and f <= n - 1 + _EDGE):  # also catches NaN
        return -1, 0.0
    f = min(max(f, 0.0), n - 1.0)
    i = int(f)
    if i > n - 2:
        i = n - 2
    return i, f - i


@nb.njit(cache=True)
def bilinear(
    values: NDArray[np.float64],
    y0: float,
    dy: float,
    x0: float,
    dx: float,
    yq: NDArray[np.float64],
    xq: NDArray[np.float64],
    period: float,
) -> NDArray[np.float64]:
    """Bilinear values at the query points, shape ``(N, c)``; NaN off the grid or next to a NaN node."""
    ny, nx, c = values.shape
    n = yq.shape[0]
    out = np.empty((n, c))
    for k in range(n):
        i, ty = _cell(yq[k], y0, dy, ny, 0.0)
        j, tx = _cell(xq[k], x0, dx, nx, period)
        if i < 0 or j < 0:
            for m in range(c):
                out[k, m] = _NAN
            continue
        w00 = (1.0 - ty) * (1.0 - tx)
        w01 = (1.0 - ty) * tx
        w10 = ty * (1.0 - tx)
        w11 = ty * tx
        for m in range(c):
            out[k, m] = (
                w00 * values[i, j, m]
                + w01 * values[i, j + 1, m]
                + w10 * values[i + 1, j, m]
                + w11 * values[i + 1, j + 1, m]
            )
    return out


@nb.njit(cache=True)
def bilinear_scalar(
    values: NDArray[np.float64],
    y0: float,
    dy: float,
    x0: float,
    dx: float,
    yq: NDArray[np.float64],
    xq: NDArray[np.float64],
    period: float,
) -> NDArray[np.float64]:
    """:func:`bilinear` for a scalar grid ``values`` (ny, nx): the hot path of map queries, shape ``(N,)``."""
    ny, nx = values.shape
    n = yq.shape[0]
    out = np.empty(n)
    idy = 1.0 / dy
    idx = 1.0 / dx
    ymax = ny - 1.0
    xmax = nx - 1.0
    for k in range(n):
        fy = (yq[k] - y0) * idy
        d = xq[k] - x0
        if period > 0.0 and (d < 0.0 or d >= period):
            d -= period * np.floor(d / period)
        fx = d * idx
        if not (fy >= -_EDGE and fy <= ymax + _EDGE and fx >= -_EDGE and fx <= xmax + _EDGE):
            out[k] = _NAN
            continue
        fy = min(max(fy, 0.0), ymax)
        fx = min(max(fx, 0.0), xmax)
        i = min(int(fy), ny - 2)
        j = min(int(fx), nx - 2)
        ty = fy - i
        tx = fx - j
        a = values[i, j] + tx * (values[i, j + 1] - values[i, j])
        b = values[i + 1, j] + tx * (values[i + 1, j + 1] - values[i + 1, j])
        out[k] = a + ty * (b - a)
    return out


@nb.njit(cache=True)
def bilinear_gradient(
    values: NDArray[np.float64],
    y0: float,
    dy: float,
    x0: float,
    dx: float,
    yq: NDArray[np.float64],
    xq: NDArray[np.float64],
    period: float,
) -> NDArray[np.float64]:
    """Analytic gradient of the bilinear interpolant, shape ``(N, c, 2)`` = (d/dy, d/dx) per axis unit."""
    ny, nx, c = values.shape
    n = yq.shape[0]
    out = np.empty((n, c, 2))
    for k in range(n):
        i, ty = _cell(yq[k], y0, dy, ny, 0.0)
        j, tx = _cell(xq[k], x0, dx, nx, period)
        if i < 0 or j < 0:
            for m in range(c):
                out[k, m, 0] = _NAN
                out[k, m, 1] = _NAN
            continue
        for m in range(c):
            f00 = values[i, j, m]
            f01 = values[i, j + 1, m]
            f10 = values[i + 1, j, m]
            f11 = values[i + 1, j + 1, m]
            out[k, m, 0] = ((1.0 - tx) * (f10 - f00) + tx * (f11 - f01)) / dy
            out[k, m, 1] = ((1.0 - ty) * (f01 - f00) + ty * (f11 - f10)) / dx
    return out


@nb.njit(cache=True, inline="always")
def _keys(t: float, deriv: bool) -> tuple[float, float, float, float]:
    """Keys (a = -1/2) weights (or their t-derivatives) for nodes -1, 0, 1, 2 at fraction t."""
    t2 = t * t
    if deriv:
        return (
            0.5 * (-3.0 * t2 + 4.0 * t - 1.0),
            0.5 * (9.0 * t2 - 10.0 * t),
            0.5 * (-9.0 * t2 + 8.0 * t + 1.0),
            0.5 * (3.0 * t2 - 2.0 * t),
        )
    t3 = t2 * t
    return (
        0.5 * (-t3 + 2.0 * t2 - t),
        0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
        0.5 * (-3.0 * t3 + 4.0 * t2 + t),
        0.5 * (t3 - t2),
    )


@nb.njit(cache=True)
def _axis_weights(i: int, t: float, n: int, deriv: bool, w: NDArray[np.float64]) -> int:
    """Fill ``w`` (4,) with weights on nodes ``start .. start+3`` (those past ``n`` are 0); return ``start``.

    Ghost nodes outside the axis use Keys' cubic boundary extrapolation; a 2-node axis falls back to linear.
    """
    w[:] = 0.0
    if n == 2:
        if deriv:
            w[0] = -1.0
            w[1] = 1.0
        else:
            w[0] = 1.0 - t
            w[1] = t
        return 0
    m = 4 if n >= 4 else 3
    start = i - 1
    if start < 0:
        start = 0
    if start > n - m:
        start = n - m
    k = _keys(t, deriv)
    for s in range(4):
        node = i - 1 + s
        kk = k[s]
        if node < 0:
            w[0 - start] += 3.0 * kk
            w[1 - start] -= 3.0 * kk
            w[2 - start] += kk
        elif node > n - 1:
            w[n - 1 - start] += 3.0 * kk
            w[n - 2 - start] -= 3.0 * kk
            w[n - 3 - start] += kk
        else:
            w[node - start] += kk
    return start


@nb.njit(cache=True)
def _bicubic_core(
    values: NDArray[np.float64],
    y0: float,
    dy: float,
    x0: float,
    dx: float,
    yq: NDArray[np.float64],
    xq: NDArray[np.float64],
    period: float,
    gradient: bool,
) -> NDArray[np.float64]:
    ny, nx, c = values.shape
    n = yq.shape[0]
    nout = 3 if gradient else 1
    out = np.empty((n, c, nout))
    wy = np.empty(4)
    wx = np.empty(4)
    dwy = np.empty(4)
    dwx = np.empty(4)
    my = min(ny, 4)
    mx = min(nx, 4)
    for k in range(n):
        i, ty = _cell(yq[k], y0, dy, ny, 0.0)
        j, tx = _cell(xq[k], x0, dx, nx, period)
        if i < 0 or j < 0:
            for m in range(c):
                for o in range(nout):
                    out[k, m, o] = _NAN
            continue
        sy = _axis_weights(i, ty, ny, False, wy)
        sx = _axis_weights(j, tx, nx, False, wx)
        if gradient:
            _axis_weights(i, ty, ny, True, dwy)
            _axis_weights(j, tx, nx, True, dwx)
        for m in range(c):
            acc = 0.0
            gy = 0.0
            gx = 0.0
            for a in range(my):
                if wy[a] == 0.0 and (not gradient or dwy[a] == 0.0):
                    continue  # node not in the stencil (a missing value there must not poison the result)
                for b in range(mx):
                    if wx[b] == 0.0 and (not gradient or dwx[b] == 0.0):
                        continue
                    f = values[sy + a, sx + b, m]
                    acc += wy[a] * wx[b] * f
                    if gradient:
                        gy += dwy[a] * wx[b] * f
                        gx += wy[a] * dwx[b] * f
            out[k, m, 0] = acc
            if gradient:
                out[k, m, 1] = gy / dy
                out[k, m, 2] = gx / dx
    return out


def bicubic(
    values: NDArray[np.float64],
    y0: float,
    dy: float,
    x0: float,
    dx: float,
    yq: NDArray[np.float64],
    xq: NDArray[np.float64],
    period: float,
) -> NDArray[np.float64]:
    """Keys bicubic values at the query points, shape ``(N, c)``."""
    return _bicubic_core(values, y0, dy, x0, dx, yq, xq, period, False)[:, :, 0]


def bicubic_gradient(
    values: NDArray[np.float64],
    y0: float,
    dy: float,
    x0: float,
    dx: float,
    yq: NDArray[np.float64],
    xq: NDArray[np.float64],
    period: float,
) -> NDArray[np.float64]:
    """Analytic gradient of the Keys bicubic interpolant, shape ``(N, c, 2)`` = (d/dy, d/dx) per axis unit."""
    return _bicubic_core(values, y0, dy, x0, dx, yq, xq, period, True)[:, :, 1:]
