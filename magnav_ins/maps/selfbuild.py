"""Self-building maps: accumulate readings taken where position is known, merge contributions, amalgamate maps,
and build a leader's map for a follower.

Sources: Raquet, Shockley & Fisher (seed 000) sec. 2.1-2.2 and 4.0 - world models built from the readings of users
who know where they are (GPS available), used by those who do not, with many users contributing; Shockley (seed 003)
sec. 6.2 - map amalgamation "ensuring the best measurements are kept"; Storms (seed 004) sec. 3.5.1 - the leader's
readings are gridded at the leader's *estimated* positions with ``griddata`` for the follower.

* :class:`MapAccumulator` keeps, per grid node, the count, mean and sum of squared deviations (M2) of the readings
  assigned to it (nearest node), updated in batches: batch statistics with :func:`numpy.bincount`, merged into the
  running ones by Chan, Golub & LeVeque's pairwise update (1979; Welford's update for one reading)
  ``n = n_a + n_b``, ``delta = mean_b - mean_a``, ``mean = mean_a + delta n_b / n``,
  ``M2 = M2_a + M2_b + delta^2 n_a n_b / n``. Two accumulators on one grid merge the same way (several users).
  Time-delineated maps are one accumulator per time span.
* :func:`amalgamate` keeps, per node, the contribution with the smaller variance of the mean (or more readings).
* :func:`leader_follower_map` grids scattered readings (``scipy.interpolate.griddata``, linear) and blanks nodes
  farther than ``max_distance_m`` from every reading (the convex hull of an L-shaped route covers the empty corner).
* :func:`path_map` grids readings along a path (a walk) by kernel regression, for maps of a route rather than an
  area (the Kok walks, ``bench/kok_walks.py``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import griddata
from scipy.spatial import cKDTree

from ..core.errors import InputError, MapError
from ..core.frames import geodetic_to_ned
from ..core.types import FieldKind, FieldReadings
from .grid import GridMap

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class BuiltMap:
    """A map built from readings: ``mean`` (a :class:`GridMap`, NaN where ``count < min_count``), the per-node
    sample ``variance`` of the readings ((ny, nx) or (ny, nx, 3), unit^2, NaN below 2 readings) and ``count``
    ((ny, nx) ints)."""

    mean: GridMap
    variance: FloatArray
    count: NDArray[np.int64]

    @property
    def pooled_variance(self) -> FloatArray:
        """Reading variance pooled over all nodes with two or more readings, ``sum M2 / sum (n - 1)`` (unit^2;
        per component for vector maps): one noise level per contributor, far steadier than any node's own."""
        var = self.variance if self.variance.ndim == 3 else self.variance[:, :, None]
        dof = np.where(self.count >= 2, self.count - 1, 0)[:, :, None]
        m2 = np.where(dof > 0, np.nan_to_num(var) * dof, 0.0)
        total = dof.sum(axis=(0, 1))
        with np.errstate(invalid="ignore", divide="ignore"):
            pooled = np.where(total > 0, m2.sum(axis=(0, 1)) / total, np.nan)
        return pooled if self.variance.ndim == 3 else pooled[0]

    def variance_of_mean(self, reading_sigma: float | None = None, pooled: bool = True) -> FloatArray:
        """Variance of each node's mean (unit^2), ``sigma^2 / count`` with ``sigma^2`` the given ``reading_sigma``,
        else the :attr:`pooled_variance` (``pooled=True``), else each node's own sample variance (NaN below two
        readings). NaN where the node has no reading."""
        if reading_sigma is not None:
            var = np.broadcast_to(float(reading_sigma) ** 2, self.variance.shape)
        elif pooled:
            var = np.broadcast_to(self.pooled_variance, self.variance.shape)
        else:
            var = self.variance
        cnt = self.count if self.variance.ndim == 2 else self.count[:, :, None]
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(cnt > 0, var / cnt, np.nan)


class MapAccumulator:
    """Running per-node statistics of readings on a fixed grid (module docstring). Build with :meth:`like` from a
    template :class:`GridMap` (its axes, frame, origin, altitude and kind) or with the same arguments as GridMap
    minus ``values``."""

    def __init__(
        self,
        northing_axis_or_lat: ArrayLike,
        easting_axis_or_lon: ArrayLike,
        *,
        kind: FieldKind | str,
        frame: Literal["geodetic", "local"],
        altitude_m: float,
        origin: tuple[float, float, float] | None = None,
        name: str = "self-built map",
    ) -> None:
        ny, nx = np.size(northing_axis_or_lat), np.size(easting_axis_or_lon)
        kind = FieldKind(kind)
        # a template GridMap validates the axes/frame/origin once and gives us the node lookup
        probe = np.zeros((ny, nx) if kind.components == 1 else (ny, nx, 3))
        self._grid = GridMap(
            northing_axis_or_lat,
            easting_axis_or_lon,
            probe,
            kind=kind,
            frame=frame,
            altitude_m=altitude_m,
            origin=origin,
            name=name,
        )
        self.kind = kind
        self.name = name
        self._c = kind.components
        self.count = np.zeros((ny, nx), dtype=np.int64)
        self._mean = np.zeros((ny, nx, self._c))
        self._m2 = np.zeros((ny, nx, self._c))

    @classmethod
    def like(cls, template: GridMap, name: str | None = None) -> MapAccumulator:
        """An empty accumulator on the grid of ``template``."""
        y, x = template.axes
        if np.ndim(template.altitude_m) != 0:
            raise MapError(f"map {template.name!r}: draped altitude not supported for self-building")
        return cls(
            y,
            x,
            kind=template.kind,
            frame=template.frame,
            altitude_m=float(template.altitude_m),
            origin=template.origin,
            name=template.name if name is None else name,
        )

    @property
    def shape(self) -> tuple[int, int]:
        return self._grid.shape

    def node_index(self, lat: ArrayLike, lon: ArrayLike) -> NDArray[np.int64]:
        """Flat index of the nearest node to each position (rad); -1 outside the grid (beyond half a cell)."""
        la, lo = np.ravel(np.asarray(lat, float)), np.ravel(np.asarray(lon, float))
        y, x = self._grid.axes
        if self._grid.frame == "local":
            qy, qx = self._grid.to_local(la, lo)
        else:
            qy, qx = la, (lo - x[0]) % (2 * np.pi) + x[0]
        dy, dx = y[1] - y[0], x[1] - x[0]
        iy = np.rint((qy - y[0]) / dy)
        ix = np.rint((qx - x[0]) / dx)
        ok = (iy >= 0) & (iy < y.size) & (ix >= 0) & (ix < x.size) & np.isfinite(iy) & np.isfinite(ix)
        idx = np.full(la.shape, -1, dtype=np.int64)
        idx[ok] = iy[ok].astype(np.int64) * x.size + ix[ok].astype(np.int64)
        return idx

    def add(self, lat: ArrayLike, lon: ArrayLike, values: ArrayLike) -> int:
        """Add readings taken at known positions (rad); ``values`` (N,) or (N, 3) in the map's unit. Readings off
        the grid or with a NaN are skipped. Returns the number of readings used."""
        v = np.asarray(values, float).reshape(-1, self._c)
        idx = self.node_index(lat, lon)
        if idx.size != v.shape[0]:
            raise InputError(f"add: {idx.size} positions but {v.shape[0]} readings of {self._c} component(s)")
        use = (idx >= 0) & np.all(np.isfinite(v), axis=1)
        idx, v = idx[use], v[use]
        if idx.size == 0:
            return 0
        size = self.count.size
        n_b = np.bincount(idx, minlength=size).astype(float)
        hit = n_b > 0
        mean_b = np.zeros((size, self._c))
        m2_b = np.zeros((size, self._c))
        for c in range(self._c):
            mean_b[hit, c] = np.bincount(idx, weights=v[:, c], minlength=size)[hit] / n_b[hit]
            dev = v[:, c] - mean_b[idx, c]
            m2_b[:, c] = np.bincount(idx, weights=dev * dev, minlength=size)
        self._merge(n_b.astype(np.int64), mean_b, m2_b)
        return int(idx.size)

    def add_readings(self, readings: FieldReadings, lat: ArrayLike, lon: ArrayLike) -> int:
        """:meth:`add` for a :class:`FieldReadings` batch whose positions (rad) are known; the kinds must match."""
        if readings.kind is not self.kind:
            raise InputError(f"add_readings: readings are {readings.kind.value}, the map is {self.kind.value}")
        return self.add(lat, lon, readings.value)

    def _merge(self, n_b: NDArray[np.int64], mean_b: FloatArray, m2_b: FloatArray) -> None:
        n_a = self.count.reshape(-1)
        mean_a = self._mean.reshape(-1, self._c)
        m2_a = self._m2.reshape(-1, self._c)
        hit = n_b > 0
        n = n_a[hit] + n_b[hit]
        delta = mean_b[hit] - mean_a[hit]
        frac_b = (n_b[hit] / n)[:, None]
        mean_a[hit] = mean_a[hit] + delta * frac_b
        m2_a[hit] = m2_a[hit] + m2_b[hit] + delta**2 * (n_a[hit] * frac_b[:, 0])[:, None]
        n_a[hit] = n

    def merge(self, other: MapAccumulator) -> None:
        """Fold in another user's accumulator on the same grid (exact: as if its readings had been added here)."""
        if other.shape != self.shape or other.kind is not self.kind or other._grid.frame != self._grid.frame:
            raise MapError(f"merge: accumulators differ in grid or kind ({other.shape} vs {self.shape})")
        if not all(np.array_equal(a, b) for a, b in zip(other._grid.axes, self._grid.axes, strict=True)):
            raise MapError("merge: accumulators have different grid axes")
        self._merge(other.count.reshape(-1).copy(), other._mean.reshape(-1, self._c), other._m2.reshape(-1, self._c))

    def mean(self) -> FloatArray:
        """Per-node mean, (ny, nx) or (ny, nx, 3); NaN where no reading."""
        m = np.where(self.count[:, :, None] > 0, self._mean, np.nan)
        return m[:, :, 0] if self._c == 1 else m

    def variance(self) -> FloatArray:
        """Per-node sample variance (ddof = 1), unit^2; NaN below two readings."""
        cnt = self.count[:, :, None]
        with np.errstate(invalid="ignore", divide="ignore"):
            var = np.where(cnt > 1, self._m2 / (cnt - 1), np.nan)
        return var[:, :, 0] if self._c == 1 else var

    def result(self, min_count: int = 1, metadata: dict[str, Any] | None = None) -> BuiltMap:
        """The map so far as a :class:`BuiltMap`; nodes with fewer than ``min_count`` readings are NaN."""
        if not np.any(self.count >= min_count):
            raise MapError(f"map {self.name!r}: no node has {min_count} reading(s) yet")
        m = self.mean()
        low = self.count < min_count
        m[low] = np.nan
        g = self._grid
        y, x = g.axes
        gm = GridMap(
            y,
            x,
            m,
            kind=self.kind,
            frame=g.frame,
            altitude_m=g.altitude_m,
            origin=g.origin,
            name=self.name,
            metadata={"source": "self-built", "readings": int(self.count.sum()), **(metadata or {})},
        )
        var = self.variance()
        var[low] = np.nan
        return BuiltMap(gm, var, self.count.copy())


def _pick(arrays: Sequence[NDArray[Any]], best: NDArray[np.intp]) -> NDArray[Any]:
    stack = np.stack(arrays)  # (M, ny, nx[, c])
    idx = best.reshape((1,) + best.shape + (1,) * (stack.ndim - 3))
    return np.take_along_axis(stack, idx, axis=0)[0]


def amalgamate(
    maps: Sequence[BuiltMap],
    *,
    by: Literal["variance", "count"] = "variance",
    reading_sigma: Sequence[float | None] | None = None,
) -> BuiltMap:
    """Combine maps on one grid keeping, per node, the better contribution (Shockley 003 sec. 6.2): the one whose
    mean has the smaller variance (``by="variance"``: ``sigma^2 / count`` with each map's ``reading_sigma`` if
    given, else its pooled reading variance, :attr:`BuiltMap.pooled_variance`) or the most readings
    (``by="count"``). A node only one map covers takes it."""
    if not maps:
        raise InputError("amalgamate: no maps given")
    ref = maps[0].mean
    for m in maps[1:]:
        if m.mean.shape != ref.shape or m.mean.kind is not ref.kind or m.mean.frame != ref.frame:
            raise MapError(f"amalgamate: map {m.mean.name!r} is not on the grid of {ref.name!r}")
        if not all(np.allclose(a, b) for a, b in zip(m.mean.axes, ref.axes, strict=True)):
            raise MapError(f"amalgamate: map {m.mean.name!r} has other grid axes than {ref.name!r}")
    if by not in ("variance", "count"):
        raise InputError(f"amalgamate: by must be 'variance' or 'count', got {by!r}")
    sigmas = [None] * len(maps) if reading_sigma is None else list(reading_sigma)
    if len(sigmas) != len(maps):
        raise InputError(f"amalgamate: {len(sigmas)} reading_sigma values for {len(maps)} maps")
    scores = []
    for m, sig in zip(maps, sigmas, strict=True):
        has = np.all(np.isfinite(m.mean.values.reshape(ref.shape + (-1,))), axis=-1)
        if by == "count":
            s = -m.count.astype(float)
        else:
            vm = m.variance_of_mean(sig)
            s = vm if vm.ndim == 2 else np.sum(vm, axis=-1)
            s = np.where(np.isfinite(s), s, np.inf)
        scores.append(np.where(has, s, np.nan))
    stack = np.stack(scores)  # (M, ny, nx)
    any_has = np.any(np.isfinite(stack), axis=0)
    best = np.argmin(np.where(np.isfinite(stack), stack, np.inf), axis=0)
    mean = _pick([m.mean.values for m in maps], best)
    var = _pick([m.variance for m in maps], best)
    cnt = _pick([m.count for m in maps], best)
    mean = np.where(any_has if mean.ndim == 2 else any_has[:, :, None], mean, np.nan)
    y, x = ref.axes
    gm = GridMap(
        y,
        x,
        mean,
        kind=ref.kind,
        frame=ref.frame,
        altitude_m=ref.altitude_m,
        origin=ref.origin,
        name=f"amalgamation of {len(maps)} maps",
        metadata={"source": "amalgamated", "rule": by},
    )
    return BuiltMap(gm, var, np.where(any_has, cnt, 0))


def sensor_positions(
    lat: ArrayLike,
    lon: ArrayLike,
    heading: ArrayLike,
    offsets_fr_m: ArrayLike,
    origin: tuple[float, float, float],
) -> tuple[FloatArray, FloatArray]:
    """Local-plane (northing, easting) m, each (N, S), of S sensors mounted at body offsets ``offsets_fr_m``
    ((S, 2): forward, right in m) on a vehicle at ``lat``, ``lon`` (rad) with ``heading`` (rad, clockwise from north)."""
    lat0, lon0, h0 = origin
    r = geodetic_to_ned(np.asarray(lat, float), np.asarray(lon, float), h0, lat0, lon0, h0).reshape(-1, 3)
    off = np.asarray(offsets_fr_m, float).reshape(-1, 2)
    psi = np.asarray(heading, float).reshape(-1, 1)
    c, s = np.cos(psi), np.sin(psi)
    n = r[:, :1] + c * off[None, :, 0] - s * off[None, :, 1]
    e = r[:, 1:2] + s * off[None, :, 0] + c * off[None, :, 1]
    return n, e


def leader_follower_map(
    northing_m: ArrayLike,
    easting_m: ArrayLike,
    values: ArrayLike,
    *,
    kind: FieldKind | str,
    spacing_m: float,
    origin: tuple[float, float, float],
    max_distance_m: float | None = None,
    name: str = "leader map",
) -> GridMap:
    """Grid a leader's scattered readings (Storms 004 sec. 3.5.1) into a local-frame :class:`GridMap`.

    ``northing_m``, ``easting_m`` (any shape, m, local plane about ``origin``) are where the leader *estimates* each
    reading was taken (e.g. from :func:`sensor_positions`); ``values`` the readings (same shape, or that shape + (3,)
    for a vector map). Linear interpolation on a grid of ``spacing_m`` covering the readings; nodes farther than
    ``max_distance_m`` from every reading are NaN (default: 1.5 times the larger of ``spacing_m`` and the median
    distance between neighbouring readings)."""
    kind = FieldKind(kind)
    n = np.ravel(np.asarray(northing_m, float))
    e = np.ravel(np.asarray(easting_m, float))
    v = np.asarray(values, float).reshape(n.size, -1)
    if v.shape[1] != kind.components:
        raise InputError(
            f"leader_follower_map: {v.shape[1]} component(s) per reading, kind {kind.value} needs {kind.components}"
        )
    ok = np.isfinite(n) & np.isfinite(e) & np.all(np.isfinite(v), axis=1)
    if ok.sum() < 3:
        raise InputError(f"leader_follower_map: need at least 3 finite readings, got {int(ok.sum())}")
    n, e, v = n[ok], e[ok], v[ok]
    d = float(spacing_m)
    if not d > 0:
        raise InputError(f"spacing_m: expected > 0, got {spacing_m!r}")
    ax_n = np.arange(np.floor(n.min() / d) * d, n.max() + d, d)
    ax_e = np.arange(np.floor(e.min() / d) * d, e.max() + d, d)
    nn, ee = np.meshgrid(ax_n, ax_e, indexing="ij")
    grid = griddata(np.column_stack([n, e]), v, (nn, ee), method="linear")  # (ny, nx, c)
    tree = cKDTree(np.column_stack([n, e]))
    if max_distance_m is None:
        nn_dist, _ = tree.query(np.column_stack([n, e]), k=2)
        max_distance_m = 1.5 * max(d, float(np.median(nn_dist[:, 1])))
    dist, _ = tree.query(np.column_stack([nn.ravel(), ee.ravel()]), k=1)
    far = dist.reshape(nn.shape) > float(max_distance_m)
    grid[far] = np.nan
    return GridMap(
        ax_n,
        ax_e,
        grid[:, :, 0] if kind.components == 1 else grid,
        kind=kind,
        frame="local",
        altitude_m=origin[2],
        origin=origin,
        name=name,
        metadata={"source": "leader readings gridded (griddata linear)", "readings": int(n.size)},
    )


def path_map(
    northing_m: ArrayLike,
    easting_m: ArrayLike,
    values: ArrayLike,
    *,
    kind: FieldKind | str,
    spacing_m: float,
    origin: tuple[float, float, float],
    length_scale_m: float,
    max_distance_m: float,
    name: str = "path map",
) -> GridMap:
    """Grid readings taken along a path (a walk, a drive: a one-dimensional set of points) into a local-frame
    :class:`GridMap` by Gaussian kernel regression (Nadaraya-Watson): each node is the mean of the readings within
    ``3 length_scale_m`` weighted by ``exp(-d^2 / (2 length_scale_m^2))``; nodes farther than ``max_distance_m``
    from every reading are NaN. Unlike triangulation (:func:`leader_follower_map`), which joins distant parts of a
    looping path across its interior, this only spreads each reading over its neighbourhood: across the path the
    map is the nearby readings' mean (the field there was never sampled).

    ``northing_m``, ``easting_m`` (N,) m in the local plane about ``origin`` (rad, rad, m); ``values`` (N,) or
    (N, 3) in ``kind``'s unit."""
    from scipy.spatial import cKDTree as _Tree

    kind = FieldKind(kind)
    n = np.ravel(np.asarray(northing_m, float))
    e = np.ravel(np.asarray(easting_m, float))
    v = np.asarray(values, float).reshape(n.size, -1)
    if v.shape[1] != kind.components:
        raise InputError(f"path_map: {v.shape[1]} component(s) per reading, kind {kind.value} needs {kind.components}")
    for key, x in (("spacing_m", spacing_m), ("length_scale_m", length_scale_m), ("max_distance_m", max_distance_m)):
        if not (np.isfinite(x) and x > 0):
            raise InputError(f"path_map: {key} must be > 0, got {x!r}")
    ok = np.isfinite(n) & np.isfinite(e) & np.all(np.isfinite(v), axis=1)
    if ok.sum() < 2:
        raise InputError(f"path_map: need at least 2 finite readings, got {int(ok.sum())}")
    n, e, v = n[ok], e[ok], v[ok]
    d = float(spacing_m)
    pad = float(max_distance_m)
    ax_n = np.arange(np.floor((n.min() - pad) / d) * d, n.max() + pad + d, d)
    ax_e = np.arange(np.floor((e.min() - pad) / d) * d, e.max() + pad + d, d)
    nn, ee = np.meshgrid(ax_n, ax_e, indexing="ij")
    nodes = np.column_stack([nn.ravel(), ee.ravel()])
    tree = _Tree(np.column_stack([n, e]))
    dist, _ = tree.query(nodes, k=1)
    out = np.full((nodes.shape[0], v.shape[1]), np.nan)
    near = np.flatnonzero(dist <= max_distance_m)
    radius = max(3.0 * float(length_scale_m), float(max_distance_m))
    for k, idx in zip(near, tree.query_ball_point(nodes[near], radius), strict=True):
        j = np.asarray(idx, dtype=np.int64)
        w = np.exp(-0.5 * ((n[j] - nodes[k, 0]) ** 2 + (e[j] - nodes[k, 1]) ** 2) / length_scale_m**2)
        if w.sum() > 0:
            out[k] = w @ v[j] / w.sum()
    grid = out.reshape(nn.shape + (v.shape[1],))
    return GridMap(
        ax_n,
        ax_e,
        grid[:, :, 0] if kind.components == 1 else grid,
        kind=kind,
        frame="local",
        altitude_m=origin[2],
        origin=origin,
        name=name,
        metadata={
            "source": f"readings along a path, Gaussian kernel {length_scale_m:g} m",
            "readings": int(n.size),
            "max_distance_m": float(max_distance_m),
        },
    )
