"""Map projections through pyproj (the only pyproj import of the package).

A grid distributed in a projected CRS (a UTM zone, Mercator, an Albers or Lambert grid; EPSG code, PROJ string or WKT)
is used in its own CRS (:class:`~magnav_ins.maps.grid.GridMap` ``frame="projected"``): a query at WGS-84 latitude and
longitude is transformed to the grid's easting/northing on the fly (:meth:`Projection.forward`, pyproj's
``Transformer`` from EPSG:4326, with the datum shift pyproj chooses - its description is :attr:`Projection.transform`),
and gradients are turned into metres of true north and east at the query point with the projection's Jacobian
(:meth:`Projection.jacobian`: d(easting, northing) / d(north, east) by central differences of 1 m on the ellipsoid,
which holds the scale factor and the meridian convergence of any projection, conformal or not; Snyder 1987,
*Map Projections - A Working Manual*, USGS PP 1395, eq. 4-2 to 4-7).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core.errors import MapError
from ..core.frames import meters_to_latlon
from ..core.units import DEG_TO_RAD, RAD_TO_DEG

FloatArray = NDArray[np.float64]

#: datums whose geographic coordinates are WGS-84's to better than ~2 m (ITRF realisations, GRS80 continental
#: datums); a geographic grid on any other datum is refused unless the user states ``datum="WGS84"``
WGS84_COMPATIBLE_DATUMS = ("WGS84", "WGS 84", "WORLD GEODETIC SYSTEM 1984", "GDA94", "GDA2020", "ITRF", "ETRS89",
                           "NAD83", "NORTH AMERICAN DATUM 1983", "GEOCENTRIC DATUM OF AUSTRALIA", "SIRGAS")  # fmt: skip
_STEP_M = 1.0


def _crs(spec: Any, where: str) -> Any:
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        return CRS.from_user_input(spec)
    except CRSError as exc:
        raise MapError(
            f"{where}: {str(spec)[:80]!r} is not a coordinate reference system pyproj knows ({exc})"
        ) from None


def describe_crs(spec: Any, where: str = "crs") -> dict[str, Any]:
    """Name, whether geographic, datum name, WKT and linear unit (m per unit, projected only) of a CRS."""
    c = _crs(spec, where)
    out: dict[str, Any] = {
        "name": c.name,
        "geographic": bool(c.is_geographic),
        "datum": c.datum.name if c.datum is not None else "",
        "wkt": c.to_wkt(),
    }
    if not c.is_geographic:
        ax = c.axis_info[0] if c.axis_info else None
        out["unit_m"] = float(ax.unit_conversion_factor) if ax is not None else 1.0
    return out


def datum_is_wgs84_compatible(datum_name: str) -> bool:
    """True when geographic coordinates on ``datum_name`` are WGS-84's to within ~2 m (:data:`WGS84_COMPATIBLE_DATUMS`)."""
    d = datum_name.upper().replace("_", " ")
    return any(k in d for k in WGS84_COMPATIBLE_DATUMS)


class Projection:
    """A projected CRS (anything ``pyproj.CRS.from_user_input`` reads) with transforms from and to WGS-84.

    ``forward(lat, lon)`` (rad) -> ``(easting, northing)`` in the CRS's metres; ``inverse`` the other way;
    :meth:`jacobian` the local derivatives. Picklable (rebuilt from its WKT)."""

    def __init__(self, crs: Any, where: str = "crs") -> None:
        c = _crs(crs, where)
        if c.is_geographic:
            raise MapError(f"{where}: {c.name!r} is a geographic (latitude/longitude) CRS, not a projection")
        info = describe_crs(c, where)
        if abs(info["unit_m"] - 1.0) > 1e-12:
            raise MapError(
                f"{where}: {c.name!r} has axes in units of {info['unit_m']} m; only metre grids are supported"
            )
        self.wkt: str = c.to_wkt()
        self.name: str = c.name
        self.datum: str = info["datum"]
        self._build()

    def _build(self) -> None:
        from pyproj import Transformer

        self._fwd = Transformer.from_crs("EPSG:4326", self.wkt, always_xy=True)
        self._inv = Transformer.from_crs(self.wkt, "EPSG:4326", always_xy=True)
        self.transform: str = str(self._fwd.description)

    def __getstate__(self) -> dict[str, Any]:
        return {"wkt": self.wkt, "name": self.name, "datum": self.datum}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._build()

    def forward(self, lat: ArrayLike, lon: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """WGS-84 ``lat``, ``lon`` (rad) -> ``(easting, northing)`` (m), shapes of the broadcast inputs."""
        la, lo = np.broadcast_arrays(np.asarray(lat, float), np.asarray(lon, float))
        e, n = self._fwd.transform(lo * RAD_TO_DEG, la * RAD_TO_DEG)
        e, n = np.asarray(e, dtype=float), np.asarray(n, dtype=float)
        bad = ~(np.isfinite(e) & np.isfinite(n))
        if bad.any():  # pyproj returns inf outside the projection's domain
            e, n = np.where(bad, np.nan, e), np.where(bad, np.nan, n)
        return e.reshape(la.shape), n.reshape(la.shape)

    def inverse(self, easting: ArrayLike, northing: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """``(easting, northing)`` (m) -> WGS-84 ``(lat, lon)`` (rad)."""
        e, n = np.broadcast_arrays(np.asarray(easting, float), np.asarray(northing, float))
        lo, la = self._inv.transform(e, n)
        return (np.asarray(la, float) * DEG_TO_RAD).reshape(e.shape), (np.asarray(lo, float) * DEG_TO_RAD).reshape(
            e.shape
        )

    def jacobian(self, lat: ArrayLike, lon: ArrayLike) -> FloatArray:
        """d(easting, northing) / d(north, east) at ``lat``, ``lon`` (rad): shape (N, 2, 2), rows (easting,
        northing), columns (north, east), dimensionless (projected m per ground m)."""
        la = np.atleast_1d(np.asarray(lat, float)).ravel()
        lo = np.atleast_1d(np.asarray(lon, float)).ravel()
        h = np.zeros_like(la)
        out = np.empty((la.size, 2, 2))
        for col, (dn, de) in enumerate(((_STEP_M, 0.0), (0.0, _STEP_M))):
            dlat, dlon = meters_to_latlon(np.full_like(la, dn), np.full_like(la, de), la, h)
            e1, n1 = self.forward(la + dlat, lo + dlon)
            e0, n0 = self.forward(la - dlat, lo - dlon)
            out[:, 0, col] = (e1 - e0) / (2 * _STEP_M)
            out[:, 1, col] = (n1 - n0) / (2 * _STEP_M)
        return out
