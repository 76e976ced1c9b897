"""``GridMap``: a geophysical field on a regular 2-D grid (geodetic lat/lon or a local northing/easting frame).

Conventions
-----------
* Geodetic frame (``frame="geodetic"``): axes ``lat`` (ny,) and ``lon`` (nx,) in rad, strictly increasing, regular.
* Local frame (``frame="local"``): axes ``northing`` (ny,) and ``easting`` (nx,) in metres of the local tangent plane
  (NED north/east) about ``origin = (lat0, lon0, h0)`` (rad, rad, m). ``crs`` is a free-text label (e.g. a UTM zone)
  kept for provenance; the conversion used is always the tangent plane of :func:`magnav_ins.core.frames.geodetic_to_ned`.
* Projected frame (``frame="projected"``): axes northing (ny,) and easting (nx,) in metres of the projected CRS
  ``crs`` (an EPSG code, PROJ string or WKT: a UTM zone, Mercator, ...), used in that CRS: queries in WGS-84
  latitude/longitude are transformed on the fly and gradients are given in metres of true north/east at the query
  point (:mod:`magnav_ins.maps.projection`, the only pyproj user). ``origin`` (default: the grid centre) is the
  tangent point of :meth:`to_local` / :meth:`value_ne`.
* ``values`` (ny, nx) for scalar kinds, (ny, nx, 3) NED components for ``vector_field_nt``; NaN = no data.
* Queries (:meth:`GridMap.value`, :meth:`GridMap.gradient_ne`, :meth:`GridMap.covers`) take latitude and longitude in
  rad for every frame; :meth:`GridMap.value_ne` takes northing/easting in metres of the map's own local plane
  (:meth:`to_local` / :meth:`from_local`), for scans on the native grid.

Altitude
--------
A grid holds the field on one surface: a constant ellipsoidal height ``altitude_m`` or a draped surface
(an (ny, nx) array of heights). :meth:`value` does **not** move the field to the query height ``h``: ``h`` is accepted
for interface uniformity and ignored, unless the map was built with ``altitude_tolerance_m`` set, in which case a
query whose ``h`` differs from the map surface by more than that tolerance raises :class:`MapError`.
To use a map at another altitude, upward-continue it first (``magnav_ins.maps.continuation``).

Map error layer
---------------
A map may carry its own prediction error (DESIGN "Integrity"): ``error_sigma``, the 1-sigma difference between the
map and the true field at each node (same unit, same nodes; larger between survey lines and far from data), and
``error_correlation_m``, the correlation length (m) of that error: two points closer than it see nearly the same
map error, so readings inside one correlation length are not independent evidence against the map.
:meth:`GridMap.error_sigma_at` interpolates the layer; :attr:`GridMap.has_error_layer` says whether there is one
(a map from elsewhere may not have it; the matchers then use their own stated default). Gridding a survey
(:mod:`magnav_ins.maps.build`) estimates the layer by spatial cross-validation; ``error_source`` says how it was made.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core.errors import MapError
from ..core.frames import radii_of_curvature
from ..core.types import FieldKind
from . import interp
from .projection import Projection
from .tangent import geodetic_to_tangent, tangent_to_geodetic

FloatArray = NDArray[np.float64]
Frame = Literal["geodetic", "local", "projected"]
Method = Literal["bilinear", "bicubic"]

_TWO_PI = 2.0 * np.pi


def _regular_axis(name: str, axis: ArrayLike) -> tuple[FloatArray, float, float]:
    a = np.asarray(axis, dtype=float)
    if a.ndim != 1 or a.size < 2:
        raise MapError(f"GridMap axis '{name}': expected a 1-D array of at least 2 nodes, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise MapError(f"GridMap axis '{name}': contains NaN or infinite coordinates")
    d = np.diff(a)
    if not np.all(d > 0):
        raise MapError(f"GridMap axis '{name}': must be strictly increasing (flip the grid before building the map)")
    step = (a[-1] - a[0]) / (a.size - 1)
    if np.max(np.abs(d - step)) > 1e-6 * abs(step):
        raise MapError(
            f"GridMap axis '{name}': spacing is not regular (steps {d.min():.9g} .. {d.max():.9g}); resample first"
        )
    return a, float(a[0]), float(step)


class GridMap:
    """A scalar or NED-vector field on a regular grid; implements the :class:`~magnav_ins.core.protocols.FieldMap`
    protocol. See the module docstring for frames, units and the altitude rule.

    Parameters
    ----------
    northing_axis_or_lat, easting_axis_or_lon
        Axes: latitude/longitude in rad (geodetic) or northing/easting in m (local), strictly increasing, regular.
    values
        (ny, nx) or (ny, nx, 3) in ``kind``'s unit (nT or mGal); NaN marks missing data.
    kind
        What the map measures (:class:`FieldKind`), which fixes its unit.
    frame
        ``"geodetic"``, ``"local"`` or ``"projected"`` (then ``crs`` is required and is the projection).
    altitude_m
        Ellipsoidal height of the map surface (m): a float, or an (ny, nx) draped surface.
    datum
        Geodetic datum label (only ``"WGS84"`` is supported for conversions).
    origin
        ``(lat0, lon0, h0)`` (rad, rad, m) of a local frame's tangent plane; for a geodetic map, optional (default:
        the grid centre at the mean altitude) and only used by :meth:`to_local` / :meth:`value_ne`.
    crs
        Free-text CRS label, kept for provenance; for ``frame="projected"`` the projected CRS itself (anything
        ``pyproj.CRS.from_user_input`` reads: ``"EPSG:32613"``, a PROJ string, WKT).
    altitude_tolerance_m
        If set, queries with ``h`` farther than this from the map surface raise :class:`MapError`.
    error_sigma
        Optional map error layer: 1-sigma prediction error in ``kind``'s unit, a float (uniform) or (ny, nx);
        for vector maps one sigma per node applies to each component. NaN nodes take the layer's largest value.
    error_correlation_m
        Correlation length (m) of the map error; required with ``error_sigma``.
    error_source
        Free text saying how the error layer was obtained (e.g. "block k-fold cross-validation, 5 folds").
    """

    def __init__(
        self,
        northing_axis_or_lat: ArrayLike,
        easting_axis_or_lon: ArrayLike,
        values: ArrayLike,
        *,
        kind: FieldKind | str,
        frame: Frame,
        altitude_m: float | ArrayLike,
        datum: str = "WGS84",
        origin: tuple[float, float, float] | None = None,
        crs: str | None = None,
        name: str = "",
        metadata: Mapping[str, Any] | None = None,
        altitude_tolerance_m: float | None = None,
        error_sigma: float | ArrayLike | None = None,
        error_correlation_m: float | None = None,
        error_source: str = "",
    ) -> None:
        try:
            self.kind = FieldKind(kind)
        except ValueError:
            raise MapError(f"GridMap: unknown kind {kind!r}; expected one of {[k.value for k in FieldKind]}") from None
        if frame not in ("geodetic", "local", "projected"):
            raise MapError(f"GridMap: frame must be 'geodetic', 'local' or 'projected', got {frame!r}")
        if str(datum).upper().replace("-", "").replace(" ", "") != "WGS84":
            raise MapError(f"GridMap: datum {datum!r} is not supported; expected 'WGS84' (reproject the map first)")
        self.frame: Frame = frame
        self.datum = "WGS84"
        self.crs = crs
        self.name = name
        self.metadata: dict[str, Any] = dict(metadata or {})
        self.altitude_tolerance_m = altitude_tolerance_m
        self.projection: Projection | None = None
        if frame == "projected":
            if not crs:
                raise MapError(f"GridMap '{name}': a projected frame needs crs= (EPSG code, PROJ string or WKT)")
            self.projection = Projection(crs, where=f"GridMap '{name}' crs")
        ynames = ("lat", "lon") if frame == "geodetic" else ("northing", "easting")
        self._y, self._y0, self._dy = _regular_axis(ynames[0], northing_axis_or_lat)
        self._x, self._x0, self._dx = _regular_axis(ynames[1], easting_axis_or_lon)
        ny, nx = self._y.size, self._x.size
        if frame == "geodetic":
            if self._y[0] < -np.pi / 2 - 1e-12 or self._y[-1] > np.pi / 2 + 1e-12:
                raise MapError(
                    "GridMap: latitude axis outside [-pi/2, pi/2] rad (degrees given where radians were expected?)"
                )
            if self._x[-1] - self._x[0] > _TWO_PI + 1e-9:
                raise MapError("GridMap: longitude axis spans more than 2 pi rad (degrees given instead of radians?)")
        v = np.asarray(values, dtype=float)
        ncomp = self.kind.components
        expect = (ny, nx) if ncomp == 1 else (ny, nx, 3)
        if v.shape != expect:
            raise MapError(
                f"GridMap '{name}': values have shape {v.shape}, expected {expect} for kind {self.kind.value}"
            )
        if not np.any(np.isfinite(v)):
            raise MapError(f"GridMap '{name}': every value is NaN (an empty map)")
        v = np.where(np.isfinite(v), v, np.nan)
        self._v3 = np.ascontiguousarray(v.reshape(ny, nx, ncomp))
        # scalar fast path: a C-contiguous (ny, nx) view of the same memory
        self._v2 = self._v3.reshape(ny, nx) if ncomp == 1 else None
        alt = np.asarray(altitude_m, dtype=float)
        if alt.ndim == 0:
            if not np.isfinite(alt):
                raise MapError(f"GridMap '{name}': altitude_m must be finite, got {float(alt)}")
            self.altitude_m: float | FloatArray = float(alt)
            self._alt3 = None
        else:
            if alt.shape != (ny, nx):
                raise MapError(f"GridMap '{name}': draped altitude_m has shape {alt.shape}, expected {(ny, nx)}")
            self.altitude_m = alt
            self._alt3 = np.ascontiguousarray(alt.reshape(ny, nx, 1))
        h_ref = float(np.nanmean(alt))
        if frame == "local":
            if origin is None:
                raise MapError(f"GridMap '{name}': a local frame needs origin=(lat0, lon0, h0) in rad, rad, m")
            self.origin: tuple[float, float, float] = tuple(float(o) for o in origin)  # type: ignore[assignment]
        elif origin is not None:
            self.origin = tuple(float(o) for o in origin)  # type: ignore[assignment]
        elif frame == "projected":
            la0, lo0 = self.projection.inverse(0.5 * (self._x[0] + self._x[-1]), 0.5 * (self._y[0] + self._y[-1]))  # type: ignore[union-attr]
            if not (np.isfinite(la0) and np.isfinite(lo0)):
                raise MapError(f"GridMap '{name}': the grid centre is outside the projection {crs!r}")
            self.origin = (float(la0), float(lo0), h_ref)
        else:
            self.origin = (0.5 * (self._y[0] + self._y[-1]), 0.5 * (self._x[0] + self._x[-1]), h_ref)
        self._h_ref = h_ref
        self._period = _TWO_PI if frame == "geodetic" else 0.0
        self._err2: FloatArray | None = None
        self.error_correlation_m: float | None = None
        self.error_source = ""
        if error_sigma is not None:
            self._set_error_layer(error_sigma, error_correlation_m, error_source)
        elif error_correlation_m is not None:
            raise MapError(f"GridMap '{name}': error_correlation_m given without error_sigma")

    def _set_error_layer(self, sigma: float | ArrayLike, correlation_m: float | None, source: str) -> None:
        ny, nx = self.shape
        e = np.asarray(sigma, dtype=float)
        if e.ndim == 0:
            e = np.full((ny, nx), float(e))
        if e.shape != (ny, nx):
            raise MapError(f"GridMap '{self.name}': error_sigma has shape {e.shape}, expected {(ny, nx)} or a scalar")
        finite = e[np.isfinite(e)]
        if finite.size == 0 or np.any(finite < 0):
            raise MapError(f"GridMap '{self.name}': error_sigma must be >= 0 with at least one finite node")
        if correlation_m is None or not np.isfinite(correlation_m) or correlation_m <= 0:
            raise MapError(
                f"GridMap '{self.name}': an error layer needs error_correlation_m > 0 (m), got {correlation_m!r}"
            )
        e = np.where(np.isfinite(e), e, float(finite.max()))
        self._err2 = np.ascontiguousarray(e)
        self.error_correlation_m = float(correlation_m)
        self.error_source = str(source)

    # ------------------------------------------------------------------ description
    @property
    def unit(self) -> str:
        """Unit of the values (``"nT"`` or ``"mGal"``)."""
        return self.kind.unit

    @property
    def shape(self) -> tuple[int, int]:
        """(ny, nx)."""
        return (self._y.size, self._x.size)

    @property
    def values(self) -> FloatArray:
        """The grid values, (ny, nx) or (ny, nx, 3) (a read-only view)."""
        v = self._v3 if self.kind.components == 3 else self._v3[:, :, 0]
        v = v.view()
        v.flags.writeable = False
        return v

    @property
    def lat(self) -> FloatArray:
        """Latitude axis (rad) of a geodetic map."""
        self._need("geodetic", "lat")
        return self._y.copy()

    @property
    def lon(self) -> FloatArray:
        """Longitude axis (rad) of a geodetic map."""
        self._need("geodetic", "lon")
        return self._x.copy()

    @property
    def northing(self) -> FloatArray:
        """Northing axis (m) of a local map."""
        self._need("local", "northing")
        return self._y.copy()

    @property
    def easting(self) -> FloatArray:
        """Easting axis (m) of a local map."""
        self._need("local", "easting")
        return self._x.copy()

    @property
    def axes(self) -> tuple[FloatArray, FloatArray]:
        """(y axis, x axis) in the frame's units: (lat, lon) rad or (northing, easting) m."""
        return self._y.copy(), self._x.copy()

    def _need(self, frame: str, what: str) -> None:
        if self.frame != frame:
            raise MapError(f"GridMap '{self.name}': '{what}' exists only for {frame} maps; this map is {self.frame}")

    @property
    def region(self) -> tuple[float, float, float, float]:
        """Bounds ``(west, east, south, north)`` in the frame's axis units (rad or m), verde's order."""
        return (float(self._x[0]), float(self._x[-1]), float(self._y[0]), float(self._y[-1]))

    @property
    def bounds_latlon(self) -> tuple[float, float, float, float]:
        """Geodetic bounding box ``(lat_min, lat_max, lon_min, lon_max)`` in rad (corners of a local map)."""
        if self.frame == "geodetic":
            return (float(self._y[0]), float(self._y[-1]), float(self._x[0]), float(self._x[-1]))
        if self.frame == "projected":  # the edges, sampled: a projected rectangle is curved in lat/lon
            t = np.linspace(0.0, 1.0, 65)
            y0, y1, x0, x1 = self._y[0], self._y[-1], self._x[0], self._x[-1]
            ee = np.r_[x0 + t * (x1 - x0), x0 + t * (x1 - x0), np.full(65, x0), np.full(65, x1)]
            nn = np.r_[np.full(65, y0), np.full(65, y1), y0 + t * (y1 - y0), y0 + t * (y1 - y0)]
            la, lo = self.projection.inverse(ee, nn)  # type: ignore[union-attr]
            return (float(np.nanmin(la)), float(np.nanmax(la)), float(np.nanmin(lo)), float(np.nanmax(lo)))
        nn, ee = np.meshgrid(self._y[[0, -1]], self._x[[0, -1]], indexing="ij")
        la, lo = self.from_local(nn.ravel(), ee.ravel())
        return (float(la.min()), float(la.max()), float(lo.min()), float(lo.max()))

    @property
    def spacing_m(self) -> tuple[float, float]:
        """Approximate node spacing (north, east) in metres (at the grid centre for geodetic maps)."""
        if self.frame == "local":
            return (self._dy, self._dx)
        if self.frame == "projected":  # projected metres per ground metre at the origin (the grid centre)
            J = self.projection.jacobian(self.origin[0], self.origin[1])[0]  # type: ignore[union-attr]
            # ground length of one node step along each grid axis: the inverse Jacobian's columns
            Jinv = np.linalg.inv(J)  # (north, east) ground m per (easting, northing) projected m
            return (float(self._dy * np.hypot(*Jinv[:, 1])), float(self._dx * np.hypot(*Jinv[:, 0])))
        lat_c = 0.5 * (self._y[0] + self._y[-1])
        r_n, r_e = radii_of_curvature(lat_c)
        return (float(self._dy * (r_n + self._h_ref)), float(self._dx * (r_e + self._h_ref) * np.cos(lat_c)))

    @property
    def has_error_layer(self) -> bool:
        """True when the map carries a prediction-error layer (module docstring, "Map error layer")."""
        return self._err2 is not None

    @property
    def error_sigma(self) -> FloatArray | None:
        """The error layer (ny, nx), 1-sigma in the map's unit (a read-only view), or None."""
        if self._err2 is None:
            return None
        v = self._err2.view()
        v.flags.writeable = False
        return v

    def error_sigma_at(self, lat: ArrayLike, lon: ArrayLike) -> FloatArray:
        """Map error 1-sigma (map unit) at ``(lat, lon)`` rad, bilinear between nodes, shape ``lat.shape``.

        NaN off the grid, and everywhere when the map has no error layer (:attr:`has_error_layer`)."""
        yq, xq, shape = self._query_axes(lat, lon)
        if self._err2 is None:
            out = np.full(yq.shape, np.nan)
        else:
            out = interp.bilinear_scalar(self._err2, self._y0, self._dy, self._x0, self._dx, yq, xq, self._period)
        return out.reshape(shape) if shape else out.reshape(())

    def error_sigma_ne(self, northing: ArrayLike, easting: ArrayLike) -> FloatArray:
        """As :meth:`error_sigma_at`, at local-plane (northing, easting) m about :attr:`origin`."""
        n, e = np.broadcast_arrays(np.asarray(northing, dtype=float), np.asarray(easting, dtype=float))
        shape = n.shape
        if self._err2 is None:
            return np.full(shape, np.nan)
        yq, xq = self._ne_axes(n, e)
        out = interp.bilinear_scalar(self._err2, self._y0, self._dy, self._x0, self._dx, yq, xq, self._period)
        return out.reshape(shape)

    def with_error_layer(
        self, error_sigma: float | ArrayLike | None, correlation_m: float | None = None, source: str = ""
    ) -> GridMap:
        """A copy of this map carrying another error layer (``None`` removes it)."""
        out = self.with_values(self.values)
        out._err2 = None
        out.error_correlation_m = None
        out.error_source = ""
        if error_sigma is not None:
            out._set_error_layer(error_sigma, correlation_m, source)
        return out

    def __repr__(self) -> str:
        dn, de = self.spacing_m
        alt = f"{self.altitude_m:.1f} m" if np.ndim(self.altitude_m) == 0 else "draped"
        return (
            f"GridMap(name={self.name!r}, kind={self.kind.value}, frame={self.frame}, shape={self.shape}, "
            f"spacing~({dn:.1f} m, {de:.1f} m), altitude={alt}"
            + (
                f", error layer median {float(np.median(self._err2)):.3g} {self.unit}, "
                f"correlation {self.error_correlation_m:.0f} m)"
                if self._err2 is not None
                else ")"
            )
        )

    # ------------------------------------------------------------------ frame helpers
    def to_local(self, lat: ArrayLike, lon: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Geodetic (rad) to the map's local tangent plane (northing, easting) in m about :attr:`origin`: the
        north/east components of :func:`magnav_ins.core.frames.geodetic_to_ned` for the point ``(lat, lon, h0)``
        (compiled twin in :mod:`magnav_ins.maps.tangent`)."""
        la, lo = np.broadcast_arrays(np.asarray(lat, float), np.asarray(lon, float))
        n, e = geodetic_to_tangent(np.ascontiguousarray(la.ravel()), np.ascontiguousarray(lo.ravel()), *self.origin)
        return n.reshape(la.shape), e.reshape(la.shape)

    def from_local(self, northing: ArrayLike, easting: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Local (northing, easting) m about :attr:`origin` to geodetic (lat, lon) rad: the exact inverse of
        :meth:`to_local` (the point of height ``h0`` with those tangent-plane coordinates)."""
        n, e = np.broadcast_arrays(np.asarray(northing, float), np.asarray(easting, float))
        la, lo = tangent_to_geodetic(np.ascontiguousarray(n.ravel()), np.ascontiguousarray(e.ravel()), *self.origin)
        return la.reshape(n.shape), lo.reshape(n.shape)

    def _query_axes(self, lat: ArrayLike, lon: ArrayLike) -> tuple[FloatArray, FloatArray, tuple[int, ...]]:
        la = np.asarray(lat, dtype=float)
        lo = np.asarray(lon, dtype=float)
        la, lo = np.broadcast_arrays(la, lo)
        shape = la.shape
        if self.frame == "geodetic":
            return np.ascontiguousarray(la.ravel()), np.ascontiguousarray(lo.ravel()), shape
        if self.frame == "projected":
            e, n = self.projection.forward(la.ravel(), lo.ravel())  # type: ignore[union-attr]
            return np.ascontiguousarray(n), np.ascontiguousarray(e), shape
        n, e = self.to_local(la.ravel(), lo.ravel())
        return np.ascontiguousarray(n), np.ascontiguousarray(e), shape

    def _ne_axes(self, n: FloatArray, e: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Grid axes (y, x) of local-plane (northing, easting) m about :attr:`origin`."""
        if self.frame == "local":
            return np.ascontiguousarray(n.ravel()), np.ascontiguousarray(e.ravel())
        la, lo = self.from_local(n.ravel(), e.ravel())
        if self.frame == "projected":
            pe, pn = self.projection.forward(la, lo)  # type: ignore[union-attr]
            return np.ascontiguousarray(pn), np.ascontiguousarray(pe)
        return la, lo

    def _check_h(self, yq: FloatArray, xq: FloatArray, h: ArrayLike | None) -> None:
        if h is None or self.altitude_tolerance_m is None:
            return
        if self._alt3 is None:
            surf = np.full(yq.shape, float(self.altitude_m))
        else:
            surf = interp.bilinear(self._alt3, self._y0, self._dy, self._x0, self._dx, yq, xq, self._period)[:, 0]
        dh = np.abs(np.broadcast_to(np.asarray(h, float).ravel(), yq.shape) - surf)
        bad = np.nanmax(dh) if dh.size else 0.0
        if bad > self.altitude_tolerance_m:
            raise MapError(
                f"GridMap '{self.name}': query height differs from the map surface by {bad:.1f} m "
                f"(> altitude_tolerance_m = {self.altitude_tolerance_m} m); upward-continue the map "
                "(magnav_ins.maps.continuation) to the flight altitude"
            )

    def _shape_out(self, out: FloatArray, shape: tuple[int, ...], tail: tuple[int, ...]) -> FloatArray:
        if self.kind.components == 1:
            out = out[:, 0]
            return out.reshape(shape + tail) if shape else out.reshape(tail)
        return out.reshape(shape + (3,) + tail)

    # ------------------------------------------------------------------ queries
    def value(
        self, lat: ArrayLike, lon: ArrayLike, h: ArrayLike | None = None, method: Method = "bilinear"
    ) -> FloatArray:
        """Interpolated field at ``(lat, lon)`` rad, shape ``lat.shape`` (scalar kinds) or ``lat.shape + (3,)``.

        NaN off the map or where a node of the interpolation stencil is NaN. ``h`` is ignored (see module docstring)
        unless ``altitude_tolerance_m`` is set. ``method``: ``"bilinear"`` or ``"bicubic"`` (Keys cubic convolution).
        """
        yq, xq, shape = self._query_axes(lat, lon)
        self._check_h(yq, xq, h)
        return self._shape_out(self._kernel(method, False)(yq, xq), shape, ())

    def value_ne(self, northing: ArrayLike, easting: ArrayLike, method: Method = "bilinear") -> FloatArray:
        """Field at local-plane (northing, easting) m about :attr:`origin`; for a local map this reads the native
        grid directly (no geodetic conversion), which makes candidate scans cheap."""
        n = np.asarray(northing, dtype=float)
        e = np.asarray(easting, dtype=float)
        n, e = np.broadcast_arrays(n, e)
        shape = n.shape
        yq, xq = self._ne_axes(n, e)
        return self._shape_out(self._kernel(method, False)(yq, xq), shape, ())

    def gradient_ne(
        self, lat: ArrayLike, lon: ArrayLike, h: ArrayLike | None = None, method: Method = "bilinear"
    ) -> FloatArray:
        """Analytic gradient of the interpolant, (d/dnorth, d/deast) in unit per metre: shape ``(N, 2)`` (scalar)
        or ``(N, 3, 2)`` (vector). For geodetic maps the angular derivatives are scaled by ``1 / (R_N + h_map)``
        and ``1 / ((R_E + h_map) cos lat)`` (Groves eq. 2.105-2.106); local maps are already in metres."""
        yq, xq, shape = self._query_axes(lat, lon)
        self._check_h(yq, xq, h)
        g = self._kernel(method, True)(yq, xq)
        if self.frame == "geodetic":
            r_n, r_e = radii_of_curvature(yq)
            g[:, :, 0] /= (r_n + self._h_ref)[:, None]
            g[:, :, 1] /= ((r_e + self._h_ref) * np.cos(yq))[:, None]
        elif self.frame == "projected":
            # chain rule: d/dnorth = dv/dE dE/dnorth + dv/dN dN/dnorth (J rows easting, northing; columns north, east)
            la, lo = np.broadcast_arrays(np.asarray(lat, float), np.asarray(lon, float))
            J = self.projection.jacobian(la.ravel(), lo.ravel())  # type: ignore[union-attr]
            gn, ge = g[:, :, 0].copy(), g[:, :, 1].copy()  # per projected northing / easting metre
            g[:, :, 0] = ge * J[:, 0, 0][:, None] + gn * J[:, 1, 0][:, None]
            g[:, :, 1] = ge * J[:, 0, 1][:, None] + gn * J[:, 1, 1][:, None]
        else:
            g = self._rotate_local_gradient(g, yq, xq)
        return self._shape_out(g, shape, (2,))

    def _rotate_local_gradient(self, g: FloatArray, yq: FloatArray, xq: FloatArray) -> FloatArray:
        # The local plane's north differs from the query point's north by the meridian convergence
        # (lon - lon0) sin(lat0); below ~1e-3 rad within 10 km of the origin. Rotate to the point's own N/E axes.
        lat0, lon0, _ = self.origin
        la, lo = self.from_local(yq, xq)
        gamma = (lo - lon0) * np.sin(lat0)
        c, s = np.cos(gamma), np.sin(gamma)
        gn, ge = g[:, :, 0].copy(), g[:, :, 1].copy()
        # local-plane axes expressed in the point's N/E frame are rotated by -gamma
        g[:, :, 0] = c[:, None] * gn - s[:, None] * ge
        g[:, :, 1] = s[:, None] * gn + c[:, None] * ge
        return g

    def covers(self, lat: ArrayLike, lon: ArrayLike) -> NDArray[np.bool_]:
        """True where the map has a finite bilinear value (inside the grid, no NaN in the cell)."""
        v = self.value(lat, lon)
        if self.kind.components == 3:
            return np.all(np.isfinite(v), axis=-1)
        return np.isfinite(v)

    def _kernel(self, method: str, gradient: bool):
        if method == "bilinear":
            fn = interp.bilinear_gradient if gradient else interp.bilinear
        elif method == "bicubic":
            fn = interp.bicubic_gradient if gradient else interp.bicubic
        else:
            raise MapError(f"GridMap: unknown interpolation method {method!r}; expected 'bilinear' or 'bicubic'")
        v3, y0, dy, x0, dx, per = self._v3, self._y0, self._dy, self._x0, self._dx, self._period
        if method == "bilinear" and not gradient and v3.shape[2] == 1:
            v2 = self._v2

            def run_scalar(yq: FloatArray, xq: FloatArray) -> FloatArray:
                return interp.bilinear_scalar(v2, y0, dy, x0, dx, yq, xq, per)[:, None]

            return run_scalar

        def run(yq: FloatArray, xq: FloatArray) -> FloatArray:
            return fn(v3, y0, dy, x0, dx, yq, xq, per)

        return run

    # ------------------------------------------------------------------ derived maps
    def with_values(
        self, values: ArrayLike, *, name: str | None = None, kind: FieldKind | str | None = None
    ) -> GridMap:
        """A copy of this map (same axes, frame, altitude, metadata, error layer) holding other values.

        The error layer is kept as it is: if the new values are not the same field (a derived map), remove or
        replace it with :meth:`with_error_layer`."""
        return GridMap(
            self._y,
            self._x,
            values,
            kind=kind if kind is not None else self.kind,
            frame=self.frame,
            altitude_m=self.altitude_m,
            datum=self.datum,
            origin=self.origin,
            crs=self.crs,
            name=self.name if name is None else name,
            metadata=self.metadata,
            altitude_tolerance_m=self.altitude_tolerance_m,
            error_sigma=self._err2,
            error_correlation_m=self.error_correlation_m,
            error_source=self.error_source,
        )

    def node_latlon(self) -> tuple[FloatArray, FloatArray]:
        """Latitude and longitude (rad) of every node, each (ny, nx)."""
        if self.frame == "geodetic":
            lat, lon = np.meshgrid(self._y, self._x, indexing="ij")
            return lat, lon
        n, e = np.meshgrid(self._y, self._x, indexing="ij")
        if self.frame == "projected":
            return self.projection.inverse(e, n)  # type: ignore[union-attr]
        return self.from_local(n, e)
