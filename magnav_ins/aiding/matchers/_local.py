"""Local north/east working frame and map sampling shared by the matchers.

Every matcher works in metres north/east of an origin (usually the INS position at the window's last reading):
``n = (lat - lat0) (R_N + h0)``, ``e = wrap(lon - lon0) (R_E + h0) cos(lat)`` with the cosine taken at each point's
own latitude, so that :meth:`LocalFrame.to_ne` and :meth:`LocalFrame.to_latlon` are exact inverses. Over the few
kilometres a search window spans this differs from a true tangent plane by well under a metre per kilometre.

Map access goes through the :class:`~magnav_ins.core.protocols.FieldMap` protocol (``value(lat, lon, h)``), with a
fast path for grid maps that expose their native nodes (``values`` with ``to_local`` / ``value_ne``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...core.frames import radii_of_curvature, wrap_angle
from ...core.protocols import FieldMap

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class LocalFrame:
    """North/east metres about ``(lat0, lon0)`` rad at height ``h0`` m (see the module docstring)."""

    lat0: float
    lon0: float
    h0: float = 0.0

    @property
    def _radii(self) -> tuple[float, float]:
        r_n, r_e = radii_of_curvature(self.lat0)
        return float(r_n) + self.h0, float(r_e) + self.h0

    def to_ne(self, lat: ArrayLike, lon: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Latitude/longitude (rad) -> north, east (m)."""
        rn, re = self._radii
        lat = np.asarray(lat, dtype=float)
        n = (lat - self.lat0) * rn
        e = wrap_angle(np.asarray(lon, dtype=float) - self.lon0) * re * np.cos(lat)
        return n, e

    def to_latlon(self, n: ArrayLike, e: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """North, east (m) -> latitude/longitude (rad)."""
        rn, re = self._radii
        lat = self.lat0 + np.asarray(n, dtype=float) / rn
        lon = self.lon0 + np.asarray(e, dtype=float) / (re * np.cos(lat))
        return lat, lon


def sample_map(fmap: FieldMap, frame: LocalFrame, n: ArrayLike, e: ArrayLike, h: float | None) -> FloatArray:
    """Map values at local points ``(n, e)`` m; shape ``n.shape`` (scalar maps) or ``n.shape + (3,)``; NaN off map."""
    n = np.asarray(n, dtype=float)
    e = np.broadcast_to(np.asarray(e, dtype=float), n.shape)
    lat, lon = frame.to_latlon(n.ravel(), e.ravel())
    vals = np.asarray(fmap.value(lat, lon, None if h is None else np.full(lat.shape, h)), dtype=float)
    return vals.reshape(n.shape + vals.shape[1:])


class MapFrame:
    """Working frame = a grid map's own local plane (``to_local`` / ``from_local`` / ``value_ne``), shifted so that
    ``(lat0, lon0)`` is at north = east = 0. Scans then read the native grid without geodetic conversions."""

    def __init__(self, fmap: FieldMap, lat0: float, lon0: float) -> None:
        self.fmap = fmap
        n0, e0 = fmap.to_local(np.array([lat0]), np.array([lon0]))  # type: ignore[attr-defined]
        self.n0, self.e0 = float(np.ravel(n0)[0]), float(np.ravel(e0)[0])
        self.lat0, self.lon0 = float(lat0), float(lon0)

    def to_ne(self, lat: ArrayLike, lon: ArrayLike) -> tuple[FloatArray, FloatArray]:
        lat = np.asarray(lat, dtype=float)
        n, e = self.fmap.to_local(lat.ravel(), np.asarray(lon, dtype=float).ravel())  # type: ignore[attr-defined]
        return (np.asarray(n) - self.n0).reshape(lat.shape), (np.asarray(e) - self.e0).reshape(lat.shape)

    def to_latlon(self, n: ArrayLike, e: ArrayLike) -> tuple[FloatArray, FloatArray]:
        n = np.asarray(n, dtype=float)
        lat, lon = self.fmap.from_local(n.ravel() + self.n0, np.asarray(e, dtype=float).ravel() + self.e0)  # type: ignore[attr-defined]
        return np.asarray(lat).reshape(n.shape), np.asarray(lon).reshape(n.shape)

    def sample(self, n: ArrayLike, e: ArrayLike, h: float | None = None) -> FloatArray:
        n = np.asarray(n, dtype=float)
        e = np.broadcast_to(np.asarray(e, dtype=float), n.shape)
        vals = np.asarray(self.fmap.value_ne(n.ravel() + self.n0, e.ravel() + self.e0), dtype=float)  # type: ignore[attr-defined]
        return vals.reshape(n.shape + vals.shape[1:])

    def native(
        self, n_lo: float, n_hi: float, e_lo: float, e_hi: float
    ) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """Native nodes of a local-frame grid inside the box (frame metres): (north axis, east axis,
        values (ni, nj, c)), or None when the map is not a local grid or the box misses it."""
        if getattr(self.fmap, "frame", None) != "local" or not hasattr(self.fmap, "axes"):
            return None
        ya, xa = self.fmap.axes  # type: ignore[attr-defined]
        ya = ya - self.n0
        xa = xa - self.e0
        i0, i1 = np.searchsorted(ya, n_lo, "left"), np.searchsorted(ya, n_hi, "right")
        j0, j1 = np.searchsorted(xa, e_lo, "left"), np.searchsorted(xa, e_hi, "right")
        if i1 <= i0 or j1 <= j0:
            return None
        v = np.asarray(self.fmap.values)  # type: ignore[attr-defined]
        v = v.reshape(v.shape[0], v.shape[1], -1)[i0:i1, j0:j1]
        return ya[i0:i1], xa[j0:j1], v


class GenericFrame:
    """:class:`LocalFrame` bound to a map: samples through ``fmap.value(lat, lon, h)`` (any FieldMap)."""

    def __init__(self, fmap: FieldMap, lat0: float, lon0: float, h0: float = 0.0) -> None:
        self.fmap = fmap
        self.local = LocalFrame(float(lat0), float(lon0), float(h0))

    def to_ne(self, lat: ArrayLike, lon: ArrayLike) -> tuple[FloatArray, FloatArray]:
        return self.local.to_ne(lat, lon)

    def to_latlon(self, n: ArrayLike, e: ArrayLike) -> tuple[FloatArray, FloatArray]:
        return self.local.to_latlon(n, e)

    def sample(self, n: ArrayLike, e: ArrayLike, h: float | None = None) -> FloatArray:
        return sample_map(self.fmap, self.local, n, e, h)

    def native(self, *args: float) -> None:
        return None


WorkFrame = MapFrame | GenericFrame


def make_frame(fmap: FieldMap, lat0: float, lon0: float) -> WorkFrame:
    """The working frame for ``fmap`` about ``(lat0, lon0)`` rad: the map's own plane when it has one."""
    if hasattr(fmap, "value_ne") and hasattr(fmap, "to_local") and hasattr(fmap, "from_local"):
        return MapFrame(fmap, lat0, lon0)
    return GenericFrame(fmap, lat0, lon0)


def map_components(fmap: FieldMap) -> int:
    """1 for scalar maps, 3 for vector maps."""
    kind = getattr(fmap, "kind", None)
    return int(getattr(kind, "components", 1))


def spacing_of(fmap: FieldMap, default: float) -> float:
    """The map's grid spacing (m) if it says so, else ``default``."""
    sp = getattr(fmap, "spacing_m", None)
    if sp is None:
        return float(default)
    sp = sp() if callable(sp) else sp
    arr = np.atleast_1d(np.asarray(sp, dtype=float))
    arr = arr[np.isfinite(arr) & (arr > 0)]
    return float(arr.min()) if arr.size else float(default)


def window_axes(half_n: float, half_e: float, step: float, max_nodes: int) -> tuple[FloatArray, FloatArray, float]:
    """Symmetric offset axes ``[-half, half]`` with spacing ``step`` (coarsened so the grid has at most
    ``max_nodes`` nodes). Returns (north offsets, east offsets, the step used)."""
    step = float(step)
    while (2 * np.ceil(half_n / step) + 1) * (2 * np.ceil(half_e / step) + 1) > max_nodes:
        step *= 1.25
    kn = int(np.ceil(half_n / step))
    ke = int(np.ceil(half_e / step))
    return np.arange(-kn, kn + 1) * step, np.arange(-ke, ke + 1) * step, step


def feature_variability(values: ArrayLike, center: ArrayLike) -> float:
    """Map feature variability (Wang et al. 2022, eq. 14): mean squared difference between the map value at the
    centre pixel and every other finite value of the search window, in the map's unit squared (summed over
    components for vector maps)."""
    c = np.atleast_1d(np.asarray(center, dtype=float)).ravel()
    v = np.asarray(values, dtype=float).reshape(-1, c.size)
    d = np.sum((v - c) ** 2, axis=1)
    d = d[np.isfinite(d)]
    d = d[d > 0]
    return float(d.mean()) if d.size else 0.0


def moments_about(p: FloatArray, n: FloatArray, e: FloatArray, n0: float, e0: float) -> FloatArray:
    """Second moment (m^2, north/east) of the normalised weights ``p`` at points ``(n, e)`` about ``(n0, e0)``."""
    dn = n - n0
    de = e - e0
    return np.array(
        [[np.sum(p * dn * dn), np.sum(p * dn * de)], [np.sum(p * dn * de), np.sum(p * de * de)]], dtype=float
    )


def sigma_window(cov_ne: FloatArray, n_sigma: float, floor: float) -> tuple[float, float]:
    """Half-widths (north, east) m of the box holding the ``n_sigma`` ellipse of ``cov_ne``, at least ``floor``."""
    c = np.asarray(cov_ne, dtype=float)
    if not np.all(np.isfinite(c)):
        return float("nan"), float("nan")
    return max(n_sigma * float(np.sqrt(max(c[0, 0], 0.0))), floor), max(
        n_sigma * float(np.sqrt(max(c[1, 1], 0.0))), floor
    )


def native_gradient_rms(native: tuple[FloatArray, FloatArray, FloatArray] | None) -> float:
    """RMS horizontal gradient magnitude (unit/m, summed over components) of native grid nodes
    ``(north axis, east axis, values (ni, nj, c))`` by forward differences; NaN when unavailable."""
    if native is None:
        return float("nan")
    n_ax, e_ax, v = native
    if n_ax.size < 2 or e_ax.size < 2:
        return float("nan")
    from ._kernels import grid_gradient_rms

    k = max(1, int(np.sqrt(n_ax.size * e_ax.size / 40_000)))  # a statistic: 40k nodes are plenty
    if k > 1 and min(n_ax.size, e_ax.size) > 2 * k:
        n_ax, e_ax, v = n_ax[::k], e_ax[::k], v[::k, ::k]
    dn, de = float(n_ax[1] - n_ax[0]), float(e_ax[1] - e_ax[0])
    return float(grid_gradient_rms(np.ascontiguousarray(v, dtype=float), dn, de))
