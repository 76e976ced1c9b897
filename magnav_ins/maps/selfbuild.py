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
  Readings may carry weights (``weights = 1 / variance``: West's 1979 weighted form of the same update,
  ``W = W_a + W_b``, ``mean = mean_a + delta W_b / W``, ``M2 = M2_a + M2_b + delta^2 W_a W_b / W``); the variance of
  a node's weighted mean is then ``1 / W`` (:meth:`BuiltMap.variance_of_mean`). Each node also keeps the time of
  its latest reading.
* :func:`amalgamate` keeps, per node, the contribution with the smaller variance of the mean (or more readings), or
  (``by="current"``) combines the contributions by inverse variance after ageing each one: the field is taken to
  drift as a random walk of ``change_rate`` (unit^2/s) since the contribution's latest reading, so the most current
  readings weigh most (Raquet et al., seed 000 sec. 4.0: "preferring the most current").
* :class:`OnlineMapBuilder` builds the map a vehicle navigates on during the same run (seed 000 sec. 2.1, seed 003
  sec. 6.2): a reading goes in only where the vehicle's position is trusted (its horizontal 1-sigma at most
  ``trust_sigma_m``, e.g. with GNSS or after a good fix), weighted by ``1 / (sigma_reading^2 + g^2 sigma_pos^2)``
  (``g`` the field's RMS horizontal gradient: a position error ``sigma_pos`` misplaces the reading by that much
  field); the map it hands out carries its own error layer (the variance of each node's mean).
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
    weight: FloatArray | None = None
    last_t: FloatArray | None = None

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
        readings). NaN where the node has no reading. Readings added with ``weights`` (inverse variances): ``1 / W``
        instead, unless ``reading_sigma`` is given."""
        if reading_sigma is None and self.weight is not None:
            with np.errstate(invalid="ignore", divide="ignore"):
                vm = np.where(self.count > 0, 1.0 / self.weight, np.nan)
            return vm if self.variance.ndim == 2 else np.repeat(vm[:, :, None], self.variance.shape[2], axis=2)
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
        self._w = np.zeros((ny, nx))  # sum of weights (= count for unit weights)
        self._weighted = False
        self.last_t = np.full((ny, nx), np.nan)
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

    def add(
        self,
        lat: ArrayLike,
        lon: ArrayLike,
        values: ArrayLike,
        *,
        weights: ArrayLike | None = None,
        t: ArrayLike | float | None = None,
    ) -> int:
        """Add readings taken at known positions (rad); ``values`` (N,) or (N, 3) in the map's unit; ``weights``
        (N,) > 0, e.g. ``1 / variance`` (unit^-2; default 1 each: plain means); ``t`` the readings' time (s; a
        scalar or (N,)) for the nodes' latest-reading time. Readings off the grid, with a NaN or a weight <= 0 are
        skipped. Returns the number of readings used."""
        v = np.asarray(values, float).reshape(-1, self._c)
        idx = self.node_index(lat, lon)
        if idx.size != v.shape[0]:
            raise InputError(f"add: {idx.size} positions but {v.shape[0]} readings of {self._c} component(s)")
        w = np.ones(idx.size) if weights is None else np.broadcast_to(np.asarray(weights, float), idx.shape).copy()
        tt = None if t is None else np.broadcast_to(np.asarray(t, float), idx.shape)
        use = (idx >= 0) & np.all(np.isfinite(v), axis=1) & np.isfinite(w) & (w > 0)
        idx, v, w = idx[use], v[use], w[use]
        if idx.size == 0:
            return 0
        if weights is not None:
            self._weighted = True
        size = self.count.size
        n_b = np.bincount(idx, minlength=size)
        w_b = np.bincount(idx, weights=w, minlength=size).astype(float)
        hit = n_b > 0
        mean_b = np.zeros((size, self._c))
        m2_b = np.zeros((size, self._c))
        for c in range(self._c):
            mean_b[hit, c] = np.bincount(idx, weights=w * v[:, c], minlength=size)[hit] / w_b[hit]
            dev = v[:, c] - mean_b[idx, c]
            m2_b[:, c] = np.bincount(idx, weights=w * dev * dev, minlength=size)
        self._merge(n_b.astype(np.int64), mean_b, m2_b, w_b)
        if tt is not None:
            lt = self.last_t.reshape(-1)
            np.fmax.at(lt, idx, tt[use])
        return int(idx.size)

    def add_readings(self, readings: FieldReadings, lat: ArrayLike, lon: ArrayLike) -> int:
        """:meth:`add` for a :class:`FieldReadings` batch whose positions (rad) are known; the kinds must match."""
        if readings.kind is not self.kind:
            raise InputError(f"add_readings: readings are {readings.kind.value}, the map is {self.kind.value}")
        return self.add(lat, lon, readings.value)

    def _merge(
        self, n_b: NDArray[np.int64], mean_b: FloatArray, m2_b: FloatArray, w_b: FloatArray | None = None
    ) -> None:
        n_a = self.count.reshape(-1)
        w_a = self._w.reshape(-1)
        w_b = n_b.astype(float) if w_b is None else w_b
        mean_a = self._mean.reshape(-1, self._c)
        m2_a = self._m2.reshape(-1, self._c)
        hit = n_b > 0
        W = w_a[hit] + w_b[hit]
        delta = mean_b[hit] - mean_a[hit]
        frac_b = (w_b[hit] / W)[:, None]
        mean_a[hit] = mean_a[hit] + delta * frac_b
        m2_a[hit] = m2_a[hit] + m2_b[hit] + delta**2 * (w_a[hit] * frac_b[:, 0])[:, None]
        n_a[hit] = n_a[hit] + n_b[hit]
        w_a[hit] = W

    def merge(self, other: MapAccumulator) -> None:
        """Fold in another user's accumulator on the same grid (exact: as if its readings had been added here)."""
        if other.shape != self.shape or other.kind is not self.kind or other._grid.frame != self._grid.frame:
            raise MapError(f"merge: accumulators differ in grid or kind ({other.shape} vs {self.shape})")
        if not all(np.array_equal(a, b) for a, b in zip(other._grid.axes, self._grid.axes, strict=True)):
            raise MapError("merge: accumulators have different grid axes")
        self._merge(
            other.count.reshape(-1).copy(),
            other._mean.reshape(-1, self._c),
            other._m2.reshape(-1, self._c),
            other._w.reshape(-1).copy(),
        )
        self._weighted = self._weighted or other._weighted
        np.fmax(self.last_t, other.last_t, out=self.last_t)

    def mean(self) -> FloatArray:
        """Per-node mean, (ny, nx) or (ny, nx, 3); NaN where no reading."""
        m = np.where(self.count[:, :, None] > 0, self._mean, np.nan)
        return m[:, :, 0] if self._c == 1 else m

    def variance(self) -> FloatArray:
        """Per-node sample variance (ddof = 1; with weights the reliability-weighted ``M2 / (W - W2 / W)`` is not
        kept, so ``M2 / W * n / (n - 1)``), unit^2; NaN below two readings."""
        cnt = self.count[:, :, None]
        w = self._w[:, :, None]
        with np.errstate(invalid="ignore", divide="ignore"):
            var = np.where(cnt > 1, self._m2 / w * cnt / (cnt - 1), np.nan)
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
        weight = np.where(low, 0.0, self._w) if self._weighted else None
        return BuiltMap(gm, var, self.count.copy(), weight, np.where(low, np.nan, self.last_t))


def _pick(arrays: Sequence[NDArray[Any]], best: NDArray[np.intp]) -> NDArray[Any]:
    stack = np.stack(arrays)  # (M, ny, nx[, c])
    idx = best.reshape((1,) + best.shape + (1,) * (stack.ndim - 3))
    return np.take_along_axis(stack, idx, axis=0)[0]


def amalgamate(
    maps: Sequence[BuiltMap],
    *,
    by: Literal["variance", "count", "current"] = "variance",
    reading_sigma: Sequence[float | None] | None = None,
    change_rate: float | None = None,
    t_now: float | None = None,
) -> BuiltMap:
    """Combine maps on one grid keeping, per node, the better contribution (Shockley 003 sec. 6.2): the one whose
    mean has the smaller variance (``by="variance"``: ``sigma^2 / count`` with each map's ``reading_sigma`` if
    given, else its pooled reading variance, :attr:`BuiltMap.pooled_variance`) or the most readings
    (``by="count"``). A node only one map covers takes it. ``by="current"``: every contribution's variance of the
    mean is aged by ``change_rate`` (unit^2/s, the field's random-walk rate) times ``t_now - last_t`` (its latest
    reading there; ``t_now`` defaults to the latest of all), and the node is their inverse-variance weighted mean,
    of variance ``1 / sum(1 / var_i)`` (the Kalman combination of observations of a random walk made at other
    times); the result carries that as its weights."""
    if not maps:
        raise InputError("amalgamate: no maps given")
    ref = maps[0].mean
    for m in maps[1:]:
        if m.mean.shape != ref.shape or m.mean.kind is not ref.kind or m.mean.frame != ref.frame:
            raise MapError(f"amalgamate: map {m.mean.name!r} is not on the grid of {ref.name!r}")
        if not all(np.allclose(a, b) for a, b in zip(m.mean.axes, ref.axes, strict=True)):
            raise MapError(f"amalgamate: map {m.mean.name!r} has other grid axes than {ref.name!r}")
    if by not in ("variance", "count", "current"):
        raise InputError(f"amalgamate: by must be 'variance', 'count' or 'current', got {by!r}")
    sigmas = [None] * len(maps) if reading_sigma is None else list(reading_sigma)
    if len(sigmas) != len(maps):
        raise InputError(f"amalgamate: {len(sigmas)} reading_sigma values for {len(maps)} maps")
    if by == "current":
        return _amalgamate_current(maps, sigmas, change_rate, t_now)
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


def _amalgamate_current(
    maps: Sequence[BuiltMap], sigmas: Sequence[float | None], change_rate: float | None, t_now: float | None
) -> BuiltMap:
    if change_rate is None or not (np.isfinite(change_rate) and change_rate >= 0):
        raise InputError(f"amalgamate by='current': change_rate must be >= 0 (unit^2/s), got {change_rate!r}")
    if any(m.last_t is None or not np.any(np.isfinite(m.last_t)) for m in maps):
        raise InputError("amalgamate by='current': every map needs its readings' times (MapAccumulator.add(t=...))")
    ref = maps[0].mean
    if t_now is None:
        t_now = float(max(np.nanmax(m.last_t) for m in maps))  # type: ignore[arg-type]
    c = ref.kind.components
    num = np.zeros(ref.shape + (c,))
    info = np.zeros(ref.shape)
    last = np.full(ref.shape, np.nan)
    cnt = np.zeros(ref.shape, dtype=np.int64)
    for m, sig in zip(maps, sigmas, strict=True):
        vals = np.asarray(m.mean.values, float).reshape(ref.shape + (c,))
        vm = m.variance_of_mean(sig)
        vm = vm if vm.ndim == 2 else np.mean(vm, axis=-1)
        age = np.maximum(t_now - m.last_t, 0.0)  # type: ignore[operator]
        var = vm + change_rate * age
        ok = np.all(np.isfinite(vals), axis=-1) & np.isfinite(var) & (var > 0)
        w = np.where(ok, 1.0 / np.where(ok, var, 1.0), 0.0)
        num += w[:, :, None] * np.nan_to_num(vals)
        info += w
        last = np.fmax(last, np.where(ok, m.last_t, np.nan))  # type: ignore[arg-type]
        cnt += np.where(ok, m.count, 0)
    has = info > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(has[:, :, None], num / info[:, :, None], np.nan)
    y, x = ref.axes
    gm = GridMap(
        y,
        x,
        mean[:, :, 0] if c == 1 else mean,
        kind=ref.kind,
        frame=ref.frame,
        altitude_m=ref.altitude_m,
        origin=ref.origin,
        name=f"amalgamation of {len(maps)} maps (most current preferred)",
        metadata={"source": "amalgamated", "rule": "current", "change_rate": float(change_rate)},
    )
    var = np.full(maps[0].variance.shape, np.nan)
    return BuiltMap(gm, var, cnt, np.where(has, info, 0.0), last)


class OnlineMapBuilder:
    """The map a vehicle builds while it navigates (module docstring). ``template``: the grid to build on (its axes,
    frame, origin, kind; its values are not used); ``reading_sigma``: the sensor's 1-sigma (map unit);
    ``gradient_rms``: the field's RMS horizontal gradient (unit/m) for the position-error term;
    ``trust_sigma_m``: largest horizontal 1-sigma (m) at which a reading is taken in; ``correlation_m``: the map
    error's correlation length reported with its error layer (default two node spacings)."""

    def __init__(
        self,
        template: GridMap,
        reading_sigma: float,
        gradient_rms: float,
        trust_sigma_m: float,
        correlation_m: float | None = None,
        name: str = "self-built (online)",
    ) -> None:
        for key, v in (("reading_sigma", reading_sigma), ("trust_sigma_m", trust_sigma_m)):
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"OnlineMapBuilder: {key} must be > 0, got {v!r}")
        if not (np.isfinite(gradient_rms) and gradient_rms >= 0):
            raise InputError(f"OnlineMapBuilder: gradient_rms must be >= 0, got {gradient_rms!r}")
        self.acc = MapAccumulator.like(template, name)
        self.reading_sigma = float(reading_sigma)
        self.gradient_rms = float(gradient_rms)
        self.trust_sigma_m = float(trust_sigma_m)
        sp = np.atleast_1d(np.asarray(template.spacing_m, float)) if hasattr(template, "spacing_m") else [1.0]
        self.correlation_m = float(correlation_m) if correlation_m is not None else 2.0 * float(np.mean(sp))
        self.offered = 0
        self.taken = 0
        self._cache: GridMap | None = None

    def offer(self, lat: ArrayLike, lon: ArrayLike, values: ArrayLike, pos_cov_ne: ArrayLike, t: float) -> int:
        """Readings (N,) or (N, 3) at estimated positions ``lat``, ``lon`` (rad) whose horizontal covariance is
        ``pos_cov_ne`` (2, 2) m^2 (one estimate for all, e.g. the sensors of one bar); taken only when its largest
        1-sigma is at most ``trust_sigma_m``. Returns how many were taken."""
        la = np.atleast_1d(np.asarray(lat, float))
        self.offered += la.size
        P = np.asarray(pos_cov_ne, float)
        if P.shape != (2, 2) or not np.all(np.isfinite(P)):
            return 0
        s2 = float(np.max(np.linalg.eigvalsh(0.5 * (P + P.T))))
        if s2 > self.trust_sigma_m**2:
            return 0
        w = 1.0 / (self.reading_sigma**2 + self.gradient_rms**2 * s2)
        n = self.acc.add(la, lon, values, weights=np.full(la.size, w), t=t)
        self.taken += n
        if n:
            self._cache = None
        return n

    def current_map(self) -> GridMap | None:
        """The map built so far with its error layer (1-sigma of each node's mean; the layer's largest value where
        there is no reading yet: the layer must be finite where values are), or None before the first reading."""
        if self._cache is None and self.acc.count.any():
            built = self.acc.result()
            vm = np.atleast_3d(built.variance_of_mean())
            with np.errstate(invalid="ignore"):
                sig = np.sqrt(np.mean(vm, axis=-1))  # NaN where the node has no reading
            sig = np.where(np.isfinite(sig), sig, np.nanmax(sig))
            self._cache = built.mean.with_error_layer(sig, self.correlation_m, "online self-built: 1/sqrt(W)")
        return self._cache


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
