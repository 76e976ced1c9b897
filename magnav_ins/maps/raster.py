"""Raster grids through GDAL (rasterio; the only rasterio import of the package): GeoTIFF, ER Mapper (``.ers``
header + raw body, Geoscience Australia's traditional format), Geosoft GXF and anything else GDAL opens.

:func:`read_raster` returns band 1 as float64 with the raster's no-data value (GeoTIFF ``nodata``, ERS
``NullCellValue``, GXF's dummy) as NaN, the node coordinates (pixel centres, GDAL's geotransform; rotated rasters are
refused), the CRS as WKT (None when the file has none) and the band's unit if GDAL reports one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..core.errors import MapError

FloatArray = NDArray[np.float64]
#: file suffixes read through GDAL
RASTER_SUFFIXES = (".tif", ".tiff", ".gtiff", ".ers", ".gxf", ".img", ".asc", ".vrt")


@dataclass(frozen=True)
class RasterBand:
    """One band: ``values`` (ny, nx) float64, NaN = no data, rows from the first (top) row of the file;
    ``y`` (ny,) and ``x`` (nx,) pixel-centre coordinates in the CRS's units (degrees or metres), as stored (``y``
    usually decreasing); ``crs_wkt``; ``unit`` (GDAL's band unit, or None); ``driver``; ``nodata``."""

    values: FloatArray
    y: FloatArray
    x: FloatArray
    crs_wkt: str | None
    geographic: bool
    unit: str | None
    driver: str
    nodata: float | None
    description: str


def ers_for(path: Path) -> Path | None:
    """The ``.ers`` header of an ER Mapper raw body given without its header (``QLDWestGravity`` beside
    ``QLDWestGravity.ers``), else None."""
    hdr = path.with_name(path.name + ".ers")
    return hdr if path.suffix == "" and hdr.is_file() else None


def read_raster(path: str | Path) -> RasterBand:
    """Band 1 of a GDAL raster (module docstring). Raises :class:`MapError` naming the file when GDAL cannot read
    it or its geotransform is rotated."""
    import rasterio
    from rasterio.errors import RasterioIOError

    p = Path(path)
    try:
        with rasterio.open(p) as ds:
            if ds.count < 1:
                raise MapError(f"{p}: the raster has no band")
            t = ds.transform
            if abs(t.b) > 0 or abs(t.d) > 0:
                raise MapError(f"{p}: rotated rasters are not supported (geotransform {tuple(t)[:6]})")
            band = ds.read(1, masked=True)
            values = np.ma.filled(band.astype(np.float64), np.nan)
            ny, nx = values.shape
            x = t.c + (np.arange(nx) + 0.5) * t.a
            y = t.f + (np.arange(ny) + 0.5) * t.e
            crs = ds.crs
            unit = ds.units[0] if ds.units and ds.units[0] else None
            return RasterBand(
                values,
                np.asarray(y, float),
                np.asarray(x, float),
                crs.to_wkt() if crs is not None else None,
                bool(crs.is_geographic) if crs is not None else False,
                unit,
                ds.driver,
                None if ds.nodata is None else float(ds.nodata),
                (ds.descriptions[0] or "") if ds.descriptions else "",
            )
    except RasterioIOError as exc:
        raise MapError(f"{p}: cannot be read by GDAL ({exc})") from None
