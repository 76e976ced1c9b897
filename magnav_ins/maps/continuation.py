"""Upward continuation of gridded potential-field maps by FFT.

A field that is harmonic above its sources (a gravity disturbance, a total-field anomaly, each NED component of a
magnetic anomaly) observed on a horizontal plane is carried ``dz`` metres higher by multiplying its 2-D spectrum by
``exp(-|k| dz)`` (|k| in rad/m; Blakely, *Potential Theory in Gravity and Magnetic Applications*, 1995, eq. 12.6).
The grid must be regular in metres; a geodetic grid is treated as locally flat with the spacing at its centre.

Edge effects: the grid is demeaned, extended by mirror reflection (so the periodic extension the FFT assumes is
continuous) and the extension is cosine-tapered to zero; NaN nodes are filled with the mean before and restored
after. A field whose integral over the plane is not zero (a point mass) keeps a small constant error, as the
grid cannot resolve its zero-wavenumber decay (0.5 % of the peak for a 6 km grid over a 400 m deep mass); dipole
fields integrate to zero and continue to 1e-4 of their range. Continuation only smooths, so it is stable for any ``dz >= 0``; downward continuation is refused.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..core.errors import InputError, MapError
from .grid import GridMap

FloatArray = NDArray[np.float64]


def _taper(n_pad: int, n: int) -> FloatArray:
    """1-D weights of length ``n + 2 n_pad``: 1 on the data, a half-cosine from 1 to 0 across each pad."""
    w = np.ones(n + 2 * n_pad)
    if n_pad > 0:
        ramp = 0.5 * (1.0 - np.cos(np.pi * np.arange(n_pad) / n_pad))  # 0 .. ~1
        w[:n_pad] = ramp
        w[-n_pad:] = ramp[::-1]
    return w


def upward_continue_array(
    values: NDArray[np.float64], spacing_m: tuple[float, float], dz_m: float, pad_fraction: float = 0.5
) -> FloatArray:
    """Continue a grid ``values`` ((ny, nx) or (ny, nx, c) with c independent components) observed on a plane
    upward by ``dz_m`` (m, >= 0). ``spacing_m`` = ``(d_north, d_east)`` in m; ``pad_fraction`` of each axis length
    is added on each side (mirror + taper). NaN nodes stay NaN."""
    dz = float(dz_m)
    if not np.isfinite(dz) or dz < 0.0:
        raise InputError(f"dz_m: expected a height increase >= 0 m (downward continuation is unstable), got {dz_m!r}")
    v = np.asarray(values, float)
    scalar = v.ndim == 2
    if scalar:
        v = v[:, :, None]
    if v.ndim != 3:
        raise InputError(f"values: expected shape (ny, nx) or (ny, nx, c), got {np.shape(values)}")
    ny, nx, nc = v.shape
    dn, de = (float(spacing_m[0]), float(spacing_m[1]))
    if dz == 0.0:
        return v[:, :, 0].copy() if scalar else v.copy()
    pn = min(int(np.ceil(pad_fraction * ny)), ny - 1)
    pe = min(int(np.ceil(pad_fraction * nx)), nx - 1)
    w = _taper(pn, ny)[:, None] * _taper(pe, nx)[None, :]
    my, mx = ny + 2 * pn, nx + 2 * pe
    k = np.hypot(2.0 * np.pi * np.fft.fftfreq(my, d=dn)[:, None], 2.0 * np.pi * np.fft.rfftfreq(mx, d=de)[None, :])
    filt = np.exp(-k * dz)
    out = np.empty_like(v)
    for c in range(nc):
        comp = v[:, :, c]
        nan = ~np.isfinite(comp)
        if nan.all():
            raise MapError("upward continuation: a component has no finite value")
        mean = float(np.mean(comp[~nan]))
        filled = np.where(nan, mean, comp) - mean
        padded = np.pad(filled, ((pn, pn), (pe, pe)), mode="reflect") * w
        cont = np.fft.irfft2(np.fft.rfft2(padded) * filt, s=(my, mx))[pn : pn + ny, pe : pe + nx] + mean
        cont[nan] = np.nan
        out[:, :, c] = cont
    return out[:, :, 0] if scalar else out


def upward_continue(fmap: GridMap, altitude_m: float, pad_fraction: float = 0.5) -> GridMap:
    """A copy of ``fmap`` continued from its altitude up to ``altitude_m`` (m, same reference as the map's
    ``altitude_m``). Works on local grids (spacing in m) and on geodetic grids (flat-Earth spacing at the centre)."""
    if np.ndim(fmap.altitude_m) != 0:
        raise MapError(f"map {fmap.name!r}: draped (non-planar) surface; FFT continuation needs a constant altitude")
    dz = float(altitude_m) - float(fmap.altitude_m)
    values = upward_continue_array(fmap.values, fmap.spacing_m, dz, pad_fraction=pad_fraction)
    y, x = fmap.axes
    return GridMap(
        y,
        x,
        values,
        kind=fmap.kind,
        frame=fmap.frame,
        altitude_m=float(altitude_m),
        datum=fmap.datum,
        origin=fmap.origin,
        crs=fmap.crs,
        name=fmap.name,
        metadata={**fmap.metadata, "upward_continued_from_m": float(fmap.altitude_m)},
    )
