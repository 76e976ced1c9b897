"""Combining maps: a fine survey grid over a coarse regional one, with a blended edge and both error layers.

As MagNav.jl's ``map_combine(mapS, mapS_fallback)`` (``src/map_functions.jl``): the fallback (coarse) map is
continued up to the fine map's altitude when it lies below it (FFT, :mod:`magnav_ins.maps.continuation`; a coarse map
above the fine one is not continued down - that is unstable - and the height difference is recorded), both are
sampled on one WGS-84 latitude/longitude grid at the fine map's node spacing over the fine map's extent widened by
``margin`` (MagNav: 10 % of each side), and the fine map fills the grid where it has data. Beyond MagNav:

* The edge is blended, not cut: the fine map's weight ``w`` falls from 1 to 0 over ``blend_m`` metres inside its own
  edge (raised cosine of the distance to its nearest no-data node, ``scipy.ndimage.distance_transform_edt``), and
  the value is ``w fine + (1 - w) coarse``.
* The coarse map is levelled onto the fine one (``level=True``): their mean difference where both have data, often
  a different regional field or IGRF removed, is added to the coarse map and recorded.
* The error layer is the blend's: ``sigma^2 = w^2 sigma_fine^2 + (1 - w)^2 sigma_coarse^2`` (independent errors of
  the two surveys), when both maps carry a layer; the correlation length is the longer of the two (the cautious
  choice for matchers, which count correlated readings once per correlation length).
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import NDArray

from ..core.errors import MapError
from ..core.frames import meters_to_latlon
from .continuation import upward_continue
from .grid import GridMap

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)

#: MagNav.jl's default widening of the fine map's extent (get_lim(xx, 0.1)): 10 % of its size on each side
DEFAULT_MARGIN_FRACTION = 0.1


def _mean_alt(m: GridMap) -> float:
    return float(np.nanmean(np.asarray(m.altitude_m, dtype=float)))


def combine_maps(
    fine: GridMap,
    coarse: GridMap,
    *,
    margin_m: float | None = None,
    blend_m: float | None = None,
    level: bool = True,
    name: str = "",
) -> GridMap:
    """``fine`` over ``coarse`` (module docstring) on a geodetic grid. ``margin_m`` (m) widens the fine map's extent
    (default 10 % of its size), ``blend_m`` (m) is the width of the blended edge (default 5 of the fine map's node
    spacings). The maps must measure the same kind."""
    if fine.kind is not coarse.kind:
        raise MapError(f"combine: {fine.name!r} holds {fine.kind.value} but {coarse.name!r} holds {coarse.kind.value}")
    if fine.kind.components != 1:
        raise MapError("combine: vector maps are not supported")
    dn, de = fine.spacing_m
    step = float(min(dn, de))
    blend = 5.0 * step if blend_m is None else float(blend_m)
    if not (np.isfinite(blend) and blend >= 0):
        raise MapError(f"combine: blend_m must be >= 0 m, got {blend_m!r}")
    h_f, h_c = _mean_alt(fine), _mean_alt(coarse)
    meta: dict[str, object] = {"combined_from": [fine.name, coarse.name], "blend_m": blend}
    if h_c < h_f - 1.0:
        coarse = upward_continue(coarse, h_f)
        meta["coarse_continued_m"] = [h_c, h_f]
    elif h_c > h_f + 1.0:
        log.info("combine: %s is %.0f m above %s; not continued down", coarse.name, h_c - h_f, fine.name)
        meta["coarse_height_above_fine_m"] = h_c - h_f
    lat0, lat1, lon0, lon1 = fine.bounds_latlon
    lat_c = 0.5 * (lat0 + lat1)
    if margin_m is None:
        m_lat, m_lon = DEFAULT_MARGIN_FRACTION * (lat1 - lat0), DEFAULT_MARGIN_FRACTION * (lon1 - lon0)
    else:
        m_lat, m_lon = meters_to_latlon(float(margin_m), float(margin_m), lat_c)
    c0, c1, c2, c3 = coarse.bounds_latlon
    lat_a, lat_b = max(lat0 - m_lat, c0), min(lat1 + m_lat, c1)
    lon_a, lon_b = max(lon0 - m_lon, c2), min(lon1 + m_lon, c3)
    if lat_b <= lat_a or lon_b <= lon_a:
        raise MapError(f"combine: {coarse.name!r} does not cover the area of {fine.name!r}")
    dlat, dlon = meters_to_latlon(step, step, lat_c)
    lat = np.arange(lat_a, lat_b + 1e-12, float(dlat))
    lon = np.arange(lon_a, lon_b + 1e-12, float(dlon))
    if lat.size < 2 or lon.size < 2:
        raise MapError("combine: the combined area is smaller than two nodes")
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    vf = np.asarray(fine.value(la, lo), dtype=float)
    vc = np.asarray(coarse.value(la, lo), dtype=float)
    both = np.isfinite(vf) & np.isfinite(vc)
    if level and both.any():
        offset = float(np.mean(vf[both] - vc[both]))
        vc = vc + offset
        meta["coarse_levelled_by"] = offset
    w = _edge_weight(np.isfinite(vf), step, blend)
    vals = np.where(np.isfinite(vf), w * np.nan_to_num(vf) + (1.0 - w) * vc, vc)
    vals = np.where(np.isfinite(vf) & ~np.isfinite(vc), vf, vals)
    meta["fine_fraction"] = float(np.mean(w > 0))
    err = corr = None
    source = ""
    if fine.has_error_layer and coarse.has_error_layer:
        sf = np.asarray(fine.error_sigma_at(la, lo), dtype=float)
        sc = np.asarray(coarse.error_sigma_at(la, lo), dtype=float)
        sc = np.where(np.isfinite(sc), sc, float(np.nanmax(coarse.error_sigma)))
        sf = np.where(np.isfinite(sf), sf, sc)
        err = np.sqrt((w * sf) ** 2 + ((1.0 - w) * sc) ** 2)
        corr = max(float(fine.error_correlation_m), float(coarse.error_correlation_m))  # type: ignore[arg-type]
        source = f"blend of the error layers of {fine.name!r} ({fine.error_source}) and {coarse.name!r} ({coarse.error_source})"
    else:
        meta["error_layer"] = "none: both maps need one to combine them"
    return GridMap(lat, lon, vals, kind=fine.kind, frame="geodetic", altitude_m=h_f,
                   name=name or f"{fine.name} over {coarse.name}", metadata=meta, error_sigma=err,
                   error_correlation_m=corr, error_source=source)  # fmt: skip


def _edge_weight(covered: NDArray[np.bool_], step_m: float, blend_m: float) -> FloatArray:
    """Weight of the fine map: 0 where it has no data, rising as a raised cosine to 1 at ``blend_m`` (m) from its
    nearest no-data node (or the grid's border) - distances on the output grid of node step ``step_m``."""
    from scipy.ndimage import distance_transform_edt

    if blend_m <= 0:
        return covered.astype(float)
    padded = np.pad(covered, 1, constant_values=False)  # the grid's border counts as no data
    d = distance_transform_edt(padded)[1:-1, 1:-1] * step_m
    t = np.clip(d / blend_m, 0.0, 1.0)
    return np.where(covered, 0.5 - 0.5 * np.cos(np.pi * t), 0.0)
