"""``TrackMap``: a field recorded at ordered points along roads or survey lines (Shockley 2012, seed 003, ch. IV).

Shockley's ground-vehicle maps are *distance sampled*: readings along each road are resampled to a fixed step
(0.5-3 m; 1 m in most of his results, sec. 4.4) by linear interpolation along the driven polyline, so that a map
location is a distance along a road, not a time. A matcher then compares readings with the map at its points
(the likelihood of 003 eqs. 2.49-2.52 evaluated at every map location), and the MagNavigate particle filter
penalises particles by their distance to the nearest map location (003 sec. 5.2, sigma = 6 m).

Conventions
-----------
* Points: geodetic ``lat``, ``lon`` (rad), ellipsoidal ``h`` (m), ``values`` (N,) or (N, 3) NED in ``kind``'s unit.
* ``segment_id`` (N,) ints split the points into polylines (a road network); a segment is a maximal run of equal
  ids, its points ordered along the road. Along-track distance ``s`` restarts at 0 on each segment.
* Geometry (distances, headings, the k-d tree) lives in the local tangent plane (NED north/east, m) about
  ``origin`` (default: the first point), as :func:`magnav_ins.core.frames.geodetic_to_ned` defines it; accurate to
  well under a metre over a few tens of km.
* :class:`~magnav_ins.core.protocols.FieldMap`: :meth:`TrackMap.value` is the value of the nearest point (NaN
  farther than ``max_distance_m``); :meth:`TrackMap.gradient_ne` is the along-track derivative ``df/ds`` at that
  point times the unit heading vector (the only horizontal derivative a track observes); :meth:`TrackMap.covers`
  is "within ``max_distance_m`` of a point".

Body-frame vector maps (Shockley 003 sec. 4.1, 4.2): a strapdown three-axis magnetometer reads the field in the
vehicle's (level) body frame, ``B_b = C_bn(psi) B_n`` (:func:`ned_to_body`), so the same road read in the other
direction, or at another heading, reads differently (``x`` and ``y`` change sign when driving the other way).
Either the map holds the field per direction of travel (:meth:`TrackMap.directional`: a body-frame map for driving
each road forwards or backwards), or it is kept in the navigation frame and the readings are rotated with the
vehicle's attitude (:func:`body_to_ned`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from ..core.errors import InputError, MapError
from ..core.frames import geodetic_to_ned
from ..core.types import FieldKind, FieldReadings

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


class TrackMap:
    """A field along ordered points (module docstring). Implements the ``FieldMap`` protocol.

    Parameters
    ----------
    lat, lon
        (N,) geodetic position of each point, rad.
    h
        (N,) or scalar ellipsoidal height, m.
    values
        (N,) scalar or (N, 3) NED components, in ``kind``'s unit; NaN allowed (a gap).
    kind
        :class:`FieldKind` of the values.
    segment_id
        Optional (N,) integers: runs of equal ids are separate polylines (roads).
    max_distance_m
        Queries farther than this from every point are off the map (NaN value, ``covers`` False).
    origin
        ``(lat0, lon0, h0)`` of the local plane used for geometry (default: the first point).
    """

    def __init__(
        self,
        lat: ArrayLike,
        lon: ArrayLike,
        h: ArrayLike,
        values: ArrayLike,
        *,
        kind: FieldKind | str,
        segment_id: ArrayLike | None = None,
        max_distance_m: float = 5.0,
        origin: tuple[float, float, float] | None = None,
        name: str = "",
        metadata: Mapping[str, Any] | None = None,
    ) -> None:
        try:
            self.kind = FieldKind(kind)
        except ValueError:
            raise MapError(f"TrackMap: unknown kind {kind!r}; expected one of {[k.value for k in FieldKind]}") from None
        self.name = name
        self.metadata: dict[str, Any] = dict(metadata or {})
        lat_a = np.atleast_1d(np.asarray(lat, float))
        lon_a = np.atleast_1d(np.asarray(lon, float))
        n = lat_a.size
        if lat_a.ndim != 1 or lon_a.shape != lat_a.shape or n < 1:
            raise MapError(
                f"TrackMap '{name}': lat and lon must be 1-D of equal length, got {lat_a.shape}, {lon_a.shape}"
            )
        if not (np.all(np.isfinite(lat_a)) and np.all(np.isfinite(lon_a))):
            raise MapError(f"TrackMap '{name}': lat/lon contain NaN or infinite values")
        if np.any(np.abs(lat_a) > np.pi / 2 + 1e-12):
            raise MapError(f"TrackMap '{name}': latitude outside [-pi/2, pi/2] rad (degrees given instead of radians?)")
        h_a = np.broadcast_to(np.asarray(h, float), lat_a.shape).astype(float)
        v = np.asarray(values, float)
        expect = (n,) if self.kind.components == 1 else (n, 3)
        if v.shape != expect:
            raise MapError(
                f"TrackMap '{name}': values have shape {v.shape}, expected {expect} for kind {self.kind.value}"
            )
        seg = np.zeros(n, dtype=np.int64) if segment_id is None else np.asarray(segment_id).astype(np.int64)
        if seg.shape != (n,):
            raise MapError(f"TrackMap '{name}': segment_id has shape {seg.shape}, expected {(n,)}")
        md = float(max_distance_m)
        if not md > 0.0:
            raise MapError(f"TrackMap '{name}': max_distance_m must be > 0, got {max_distance_m!r}")
        self.max_distance_m = md
        self.lat, self.lon, self.h, self.values, self.segment_id = lat_a, lon_a, h_a, v, seg
        self.origin: tuple[float, float, float] = (
            (float(lat_a[0]), float(lon_a[0]), float(h_a[0])) if origin is None else tuple(map(float, origin))  # type: ignore[assignment]
        )
        r = self._to_local(lat_a, lon_a)
        self.northing, self.easting = r[:, 0], r[:, 1]
        # segment runs
        new = np.ones(n, dtype=bool)
        new[1:] = seg[1:] != seg[:-1]
        self._run = np.cumsum(new) - 1  # run index per point
        self._first = new
        self._last = np.append(new[1:], True)
        step = np.hypot(np.diff(self.northing), np.diff(self.easting))
        same = ~new[1:]
        if np.any(same & (step <= 0.0)):
            k = int(np.flatnonzero(same & (step <= 0.0))[0])
            raise MapError(f"TrackMap '{name}': points {k} and {k + 1} coincide; drop repeated points first")
        ds = np.where(same, step, 0.0)
        s = np.concatenate([[0.0], np.cumsum(ds)])
        run_start_s = s[new][self._run]
        self.along_track_m: FloatArray = s - run_start_s
        self._s_global = s
        self.heading = self._heading()
        self._tree = cKDTree(np.column_stack([self.northing, self.easting]))
        self._grad: FloatArray | None = None

    @classmethod
    def from_readings(
        cls,
        readings: FieldReadings,
        lat: ArrayLike,
        lon: ArrayLike,
        h: ArrayLike,
        *,
        segment_id: ArrayLike | None = None,
        step_m: float | None = None,
        max_distance_m: float = 5.0,
        name: str = "",
    ) -> TrackMap:
        """A track map from readings taken at known positions (rad, m) along a drive: readings at the position of
        the previous one (a stop) are dropped, then, with ``step_m``, the track is distance-sampled (Shockley 003
        sec. 4.2.3: a 0.5 m distance map was 85 % smaller than the 50 Hz time map)."""
        lat_a, lon_a = np.atleast_1d(np.asarray(lat, float)), np.atleast_1d(np.asarray(lon, float))
        if lat_a.shape != (len(readings),) or lon_a.shape != lat_a.shape:
            raise InputError(f"from_readings: {len(readings)} readings but positions of shape {lat_a.shape}")
        h_a = np.broadcast_to(np.asarray(h, float), lat_a.shape)
        seg = np.zeros(lat_a.size, np.int64) if segment_id is None else np.asarray(segment_id).astype(np.int64)
        keep = np.ones(lat_a.size, dtype=bool)
        keep[1:] = (lat_a[1:] != lat_a[:-1]) | (lon_a[1:] != lon_a[:-1]) | (seg[1:] != seg[:-1])
        tm = cls(
            lat_a[keep],
            lon_a[keep],
            h_a[keep],
            readings.value[keep],
            kind=readings.kind,
            segment_id=seg[keep],
            max_distance_m=max_distance_m,
            name=name,
            metadata={"reading_sigma": readings.sigma},
        )
        return tm if step_m is None else tm.resample(step_m)

    # ------------------------------------------------------------------ geometry
    def __len__(self) -> int:
        return self.lat.size

    def __repr__(self) -> str:
        return (
            f"TrackMap(name={self.name!r}, kind={self.kind.value}, points={len(self)}, "
            f"segments={self.n_segments}, length={self.total_length_m:.1f} m)"
        )

    @property
    def unit(self) -> str:
        return self.kind.unit

    @property
    def n_segments(self) -> int:
        return int(self._run[-1]) + 1

    @property
    def run_index(self) -> NDArray[np.int64]:
        """(N,) 0-based index of each point's segment run, in order of appearance (non-decreasing)."""
        return self._run.copy()

    @property
    def total_length_m(self) -> float:
        """Sum of the segment lengths (m)."""
        return float(np.sum(self.along_track_m[self._last]))

    def _to_local(self, lat: FloatArray, lon: FloatArray) -> FloatArray:
        lat0, lon0, h0 = self.origin
        return geodetic_to_ned(lat, lon, h0, lat0, lon0, h0).reshape(-1, 3)

    def to_local(self, lat: ArrayLike, lon: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Geodetic (rad) to the track's local plane (northing, easting), m."""
        r = self._to_local(np.ravel(np.asarray(lat, float)), np.ravel(np.asarray(lon, float)))
        return r[:, 0], r[:, 1]

    def _neighbour_slope(self, q: FloatArray) -> FloatArray:
        """d q / d s at each point within its segment: central differences inside, one-sided at ends, 0 alone."""
        n = len(self)
        q2 = q.reshape(n, -1)
        s = self._s_global
        i = np.arange(n)
        lo = np.where(self._first, i, i - 1)
        hi = np.where(self._last, i, i + 1)
        ds = s[hi] - s[lo]
        with np.errstate(invalid="ignore", divide="ignore"):
            out = (q2[hi] - q2[lo]) / ds[:, None]
        out[ds == 0.0] = 0.0
        return out.reshape(q.shape)

    def _heading(self) -> FloatArray:
        dn = self._neighbour_slope(self.northing)
        de = self._neighbour_slope(self.easting)
        return np.arctan2(de, dn)

    # ------------------------------------------------------------------ queries
    def nearest(self, lat: ArrayLike, lon: ArrayLike) -> tuple[IntArray, FloatArray, FloatArray]:
        """Nearest track point to each query (rad): ``(index, distance_m, along_track_m)``, each (M,).

        No distance limit here (``covers``/``value`` apply ``max_distance_m``)."""
        qn, qe = self.to_local(lat, lon)
        dist, idx = self._tree.query(np.column_stack([qn, qe]), k=1)
        idx = np.asarray(idx, dtype=np.int64)
        return idx, np.asarray(dist, float), self.along_track_m[idx]

    def nearest_ne(self, northing: ArrayLike, easting: ArrayLike) -> tuple[IntArray, FloatArray]:
        """Nearest point to local-plane queries (m): ``(index, distance_m)``; cheap for candidate scans."""
        n, e = np.broadcast_arrays(np.ravel(np.asarray(northing, float)), np.ravel(np.asarray(easting, float)))
        dist, idx = self._tree.query(np.column_stack([n, e]), k=1)
        return np.asarray(idx, dtype=np.int64), np.asarray(dist, float)

    def _masked(self, per_point: FloatArray, lat: ArrayLike, lon: ArrayLike) -> FloatArray:
        idx, dist, _ = self.nearest(lat, lon)
        out = per_point[idx].astype(float, copy=True)
        out[dist > self.max_distance_m] = np.nan
        return out

    def value(self, lat: ArrayLike, lon: ArrayLike, h: ArrayLike | None = None) -> FloatArray:
        """Value of the nearest point, (M,) or (M, 3); NaN farther than ``max_distance_m``. ``h`` is ignored."""
        return self._masked(self.values, lat, lon)

    def gradient_ne(self, lat: ArrayLike, lon: ArrayLike, h: ArrayLike | None = None) -> FloatArray:
        """Along-track derivative at the nearest point projected on north/east, unit per metre: (M, 2) or
        (M, 3, 2); NaN off the map. The cross-track derivative is unobserved and reported as 0."""
        if self._grad is None:  # per-point gradients, computed once
            dfds = self._neighbour_slope(self.values)
            u = np.column_stack([np.cos(self.heading), np.sin(self.heading)])
            self._grad = dfds[:, None] * u if dfds.ndim == 1 else dfds[:, :, None] * u[:, None, :]
        return self._masked(self._grad, lat, lon)

    def covers(self, lat: ArrayLike, lon: ArrayLike) -> NDArray[np.bool_]:
        """True within ``max_distance_m`` of a point whose value is finite."""
        v = self.value(lat, lon)
        return np.all(np.isfinite(v), axis=-1) if v.ndim == 2 else np.isfinite(v)

    def segment(self, k: int) -> slice:
        """Index slice of segment run ``k`` (0-based, in order of appearance)."""
        idx = np.flatnonzero(self._run == k)
        if idx.size == 0:
            raise MapError(f"TrackMap '{self.name}': no segment {k}; it has {self.n_segments}")
        return slice(int(idx[0]), int(idx[-1]) + 1)

    def directional(self, reverse: bool = False) -> TrackMap:
        """A body-frame map of this NED vector track for driving every segment forwards (its point order) or, with
        ``reverse``, backwards (points reversed within each segment, heading + pi): the values a level strapdown
        magnetometer reads there in that direction (:func:`ned_to_body`). Shockley's per-direction road maps."""
        if self.kind.components != 3:
            raise MapError(
                f"TrackMap '{self.name}': a body-frame map needs vector values, the map holds {self.kind.value}"
            )
        order = np.arange(len(self))
        if reverse:
            order = np.concatenate([np.arange(len(self))[self.segment(k)][::-1] for k in range(self.n_segments)])
        psi = self.heading[order] + (np.pi if reverse else 0.0)
        return TrackMap(
            self.lat[order],
            self.lon[order],
            self.h[order],
            ned_to_body(self.values[order], psi),
            kind=self.kind,
            segment_id=self.segment_id[order],
            max_distance_m=self.max_distance_m,
            origin=self.origin,
            name=f"{self.name} (body frame, {'reverse' if reverse else 'forward'})",
            metadata={**self.metadata, "frame": "body", "direction": "reverse" if reverse else "forward"},
        )

    # ------------------------------------------------------------------ resampling
    def resample(self, step_m: float) -> TrackMap:
        """Distance-sampled copy (Shockley 003 sec. 4.4): on every segment, points every ``step_m`` metres of
        along-track distance from 0, with lat, lon, h and values linearly interpolated along the polyline."""
        step = float(step_m)
        if not np.isfinite(step) or step <= 0.0:
            raise InputError(f"step_m: expected a positive distance in metres, got {step_m!r}")
        cols = [self.lat, self.lon, self.h, *np.atleast_2d(self.values.T)]
        out_cols: list[list[FloatArray]] = [[] for _ in cols]
        out_seg: list[IntArray] = []
        for k in range(self.n_segments):
            sl = self.segment(k)
            s = self.along_track_m[sl]
            s_new = np.arange(0.0, s[-1] + 1e-9 * max(1.0, s[-1]), step)
            for c, col in enumerate(cols):
                out_cols[c].append(np.interp(s_new, s, col[sl]))
            out_seg.append(np.full(s_new.size, self.segment_id[sl][0], dtype=np.int64))
        arr = [np.concatenate(c) for c in out_cols]
        values = arr[3] if self.kind.components == 1 else np.column_stack(arr[3:])
        return TrackMap(
            arr[0],
            arr[1],
            arr[2],
            values,
            kind=self.kind,
            segment_id=np.concatenate(out_seg),
            max_distance_m=self.max_distance_m,
            origin=self.origin,
            name=self.name,
            metadata={**self.metadata, "resample_step_m": step},
        )


def ned_to_body(values_ned: ArrayLike, heading: ArrayLike) -> FloatArray:
    """Level body-frame (FRD) components of NED vectors for a vehicle heading ``heading`` (rad, clockwise from
    north): ``x = cos psi N + sin psi E``, ``y = -sin psi N + cos psi E``, ``z = D``; (N, 3) in, (N, 3) out."""
    v = np.atleast_2d(np.asarray(values_ned, float))
    psi = np.broadcast_to(np.asarray(heading, float), v.shape[:1])
    c, s = np.cos(psi), np.sin(psi)
    return np.column_stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1], v[:, 2]])


def body_to_ned(values_body: ArrayLike, heading: ArrayLike) -> FloatArray:
    """The inverse of :func:`ned_to_body`: level body-frame readings (N, 3) to NED with the heading applied."""
    v = np.atleast_2d(np.asarray(values_body, float))
    psi = np.broadcast_to(np.asarray(heading, float), v.shape[:1])
    c, s = np.cos(psi), np.sin(psi)
    return np.column_stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]])


def road_network_from_grid(
    grid: Any,
    street_northings_m: Sequence[float],
    street_eastings_m: Sequence[float],
    step_m: float = 1.0,
    *,
    max_distance_m: float = 5.0,
    name: str = "road network",
) -> TrackMap:
    """A grid of straight streets sampled every ``step_m`` metres from a local-frame ``GridMap``: east-west streets
    at each northing of ``street_northings_m`` and north-south streets at each easting of ``street_eastings_m``
    (m, in the grid's local plane), each street its own segment spanning the grid. For tests and scenarios."""
    if getattr(grid, "frame", None) != "local":
        raise MapError("road_network_from_grid: expected a local-frame GridMap (northing/easting in metres)")
    west, east, south, north = grid.region
    step = float(step_m)
    if not step > 0.0:
        raise InputError(f"step_m: expected > 0, got {step_m!r}")
    ns: list[FloatArray] = []
    es: list[FloatArray] = []
    segs: list[IntArray] = []
    k = 0
    for n0 in street_northings_m:
        e = np.arange(west, east + 1e-9, step)
        ns.append(np.full(e.size, float(n0)))
        es.append(e)
        segs.append(np.full(e.size, k, dtype=np.int64))
        k += 1
    for e0 in street_eastings_m:
        n = np.arange(south, north + 1e-9, step)
        ns.append(n)
        es.append(np.full(n.size, float(e0)))
        segs.append(np.full(n.size, k, dtype=np.int64))
        k += 1
    if k == 0:
        raise InputError("road_network_from_grid: no streets given")
    n_all, e_all = np.concatenate(ns), np.concatenate(es)
    values = grid.value_ne(n_all, e_all)
    lat, lon = grid.from_local(n_all, e_all)
    return TrackMap(
        lat,
        lon,
        grid.origin[2],
        values,
        kind=grid.kind,
        segment_id=np.concatenate(segs),
        max_distance_m=max_distance_m,
        origin=grid.origin,
        name=name,
        metadata={"source": f"sampled from {grid.name!r}", "step_m": step},
    )
