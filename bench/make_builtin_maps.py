"""Regenerate the maps and the survey shipped in ``magnav_ins/data`` from ``../shared/data`` (reproducible provenance).

    python bench/make_builtin_maps.py [--json]

* ``osborne-magnetic.nc``: Osborne airborne magnetics (Fatiando a Terra / Geoscience Australia, CC-BY-4.0), heights
  made ellipsoidal with the EIGEN-6C4 geoid (h = H + N), gridded at 100 m from the east-west flight lines only
  (the 22 north-south tie lines, found by line azimuth, are excluded), float32, compressed.
* ``osborne-tie-lines.csv.xz``: the tie lines' real readings (line, lat, lon, ellipsoidal height, anomaly).
* ``eigen6c4-geoid-10arcmin.nc``: the EIGEN-6C4 geoid (Fatiando a Terra / GFZ ICGEM, CC-BY-4.0), global 10' grid,
  int16 in 0.1 m as published, without the duplicated 180 deg column (:mod:`magnav_ins.maps.geoid`).
* ``eigen6c4-australia-se.nc``: EIGEN-6C4 full gravity at 10 km (Fatiando a Terra / GFZ ICGEM, CC-BY-4.0) minus WGS-84
  normal gravity at 10 km = gravity disturbance (mGal), lat -40..-32, lon 142..153 deg.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd
import xarray as xr

from magnav_ins.core.atomic import atomic_path
from magnav_ins.core.types import FieldKind
from magnav_ins.core.units import DEG_TO_RAD, MPS2_TO_MGAL
from magnav_ins.ins.earth import normal_gravity
from magnav_ins.maps import geoid
from magnav_ins.maps.build import cross_lines, grid_survey, tie_line_misfit
from magnav_ins.maps.geoid import GEOID_FILE
from magnav_ins.maps.grid import GridMap
from magnav_ins.maps.io import read_survey, write_map

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "fatiando"
OUT = ROOT / "magnav_ins" / "data"
OSBORNE_SPACING_M = 100.0
SE_AUS_REGION_DEG = (-40.0, -32.0, 142.0, 153.0)  # lat_min, lat_max, lon_min, lon_max
EIGEN_HEIGHT_M = 10_000.0


def make_geoid() -> dict:
    """The shipped geoid: the published int16 (0.1 m) grid, the duplicated lon = 180 deg column dropped."""
    ds = xr.open_dataset(SHARED / "earth-geoid-10arcmin.nc", mask_and_scale=False)
    raw = np.asarray(ds.geoid.values)
    if raw.dtype != np.int16 or float(ds.geoid.attrs["scale_factor"]) != 0.1 or np.any(raw[:, 0] != raw[:, -1]):
        raise SystemExit("earth-geoid-10arcmin.nc: unexpected encoding (expected int16 x 0.1 m, lon -180..180)")
    attrs = {
        "units": "m",
        "scale_factor": 0.1,
        "long_name": "geoid height above the WGS84 ellipsoid (EIGEN-6C4, degree 720, tide-free)",
        "standard_name": "geoid_height_above_reference_ellipsoid",
    }
    out = xr.Dataset(
        {"geoid": (("latitude", "longitude"), raw[:, :-1], attrs)},
        coords={
            "latitude": ("latitude", np.asarray(ds.latitude.values, float), {"units": "degrees_north"}),
            "longitude": ("longitude", np.asarray(ds.longitude.values[:-1], float), {"units": "degrees_east"}),
        },
        attrs={
            "Conventions": "CF-1.8",
            "title": "EIGEN-6C4 geoid height above WGS84, 10 arc-minute grid",
            "source": "Fatiando a Terra earth-geoid-10arcmin v1 (EIGEN-6C4, GFZ/ICGEM, doi:10.5880/icgem.2015.1)",
            "license": "CC-BY-4.0",
            "made_by": "bench/make_builtin_maps.py",
        },
    )
    path = OUT / GEOID_FILE
    with atomic_path(path) as tmp:
        out.to_netcdf(tmp, encoding={"geoid": {"zlib": True, "complevel": 9, "shuffle": True, "dtype": "int16"}})
        tmp.chmod(0o644)
    geoid._grid.cache_clear()
    return {"geoid_shape": list(raw[:, :-1].shape), "geoid_bytes": path.stat().st_size}


def make_osborne() -> dict:
    t0 = time.perf_counter()
    survey = read_survey(SHARED / "osborne-magnetic.csv.xz")  # orthometric heights through the shipped geoid
    ties = cross_lines(survey)
    tie_survey = survey.select(np.isin(survey.line, ties))
    # the tie lines are not gridded; their crossovers with the flight lines measure the error between line sets
    fmap = grid_survey(survey, OSBORNE_SPACING_M, exclude_lines=ties, name="osborne-magnetic", check_lines=tie_survey)
    fmap.metadata.update(
        {
            "source": "Fatiando a Terra osborne-magnetic v1 (Geoscience Australia MIM P1029, 1990), CC-BY-4.0",
            "tie_lines_excluded": ties,
            "heights": "ellipsoidal = orthometric + EIGEN-6C4 geoid (10' grid)",
            "made_by": "bench/make_builtin_maps.py",
        }
    )
    write_map(fmap, OUT / "osborne-magnetic.nc", dtype="float32")
    m = np.isin(survey.line, ties)
    df = pd.DataFrame(
        {
            "flight_line": survey.line[m],
            "latitude": np.round(np.rad2deg(survey.lat[m]), 6),
            "longitude": np.round(np.rad2deg(survey.lon[m]), 6),
            "height_ellipsoidal_m": np.round(survey.h[m], 1),
            "total_field_anomaly_nt": survey.value[m],
        }
    )
    with atomic_path(OUT / "osborne-tie-lines.csv.xz") as tmp:
        df.to_csv(tmp, index=False, compression="xz")
        tmp.chmod(0o644)
    mis = tie_line_misfit(fmap, survey, ties)
    n = sum(v["n"] for v in mis.values())
    tie = survey.select(m)
    r = fmap.value(tie.lat, tie.lon) - tie.value
    z = r / fmap.error_sigma_at(tie.lat, tie.lon)
    ok = np.isfinite(z)
    return {
        "osborne_tie_z_rms": float(np.sqrt(np.mean(z[ok] ** 2))),
        "osborne_tie_z_rms_demeaned": float(np.sqrt(np.mean(((r[ok] - r[ok].mean()) / (r[ok] / z[ok])) ** 2))),
        "osborne_error_sigma_median_nt": float(np.median(fmap.error_sigma)),
        "osborne_error_correlation_m": float(fmap.error_correlation_m),
        "osborne_shape": list(fmap.shape),
        "osborne_tie_lines": ties,
        "osborne_tie_rms_nt": float(np.sqrt(sum(v["rms"] ** 2 * v["n"] for v in mis.values()) / n)),
        "osborne_bytes": (OUT / "osborne-magnetic.nc").stat().st_size,
        "tie_lines_bytes": (OUT / "osborne-tie-lines.csv.xz").stat().st_size,
        "osborne_wall_s": time.perf_counter() - t0,
    }


def eigen_error_vs_sandwell_smith() -> dict:
    """The EIGEN-6C4 10' disturbance at 10 km against an independent grid: Sandwell & Smith's 2' marine free-air
    anomaly (Gulf of Alaska, ``../shared/data/marine_gravity/AK_gulf_grav.nc``, satellite altimetry) continued up to
    10 km (FFT, :mod:`magnav_ins.maps.continuation`) and made a disturbance (dg = Dg + 0.3086 N, N from the shipped
    geoid); EIGEN-6C4 bilinear from its 10' nodes, as the shipped map is used. 25 nodes (~50-90 km) of each edge are
    left out (continuation edge effects). Returns the RMS (the stated error layer) and the e-folding length of the
    difference's autocorrelation (its correlation length)."""
    from magnav_ins.core.frames import radii_of_curvature
    from magnav_ins.maps.continuation import upward_continue_array
    from magnav_ins.maps.geoid import geoid_undulation

    ss = xr.load_dataset(SHARED.parent / "marine_gravity" / "AK_gulf_grav.nc")
    lat, lon = np.asarray(ss.lat.values, float), np.asarray(ss.lon.values, float)
    z = np.asarray(ss.z.values, float)  # mGal (free-air anomaly at sea level; the file states no unit)
    lat_c = np.deg2rad(lat.mean())
    r_n, r_e = radii_of_curvature(lat_c)
    dn, de = np.deg2rad(lat[1] - lat[0]) * r_n, np.deg2rad(lon[1] - lon[0]) * r_e * np.cos(lat_c)
    la, lo = np.meshgrid(np.deg2rad(lat), np.deg2rad(lon), indexing="ij")
    ss_dist = upward_continue_array(z, (dn, de), EIGEN_HEIGHT_M) + 0.3086 * geoid_undulation(la, lo)
    g = xr.load_dataset(SHARED / "earth-gravity-10arcmin.nc").gravity
    eg = g.interp(latitude=xr.DataArray(lat, dims="y"), longitude=xr.DataArray(lon, dims="x")).values
    eg_dist = eg - normal_gravity(la, EIGEN_HEIGHT_M) * MPS2_TO_MGAL
    d = (eg_dist - ss_dist)[25:-25, 25:-25]
    d0 = d - d.mean()
    ac = np.fft.irfft2(np.abs(np.fft.rfft2(d0, s=(2 * d.shape[0], 2 * d.shape[1]))) ** 2)[: d.shape[0], : d.shape[1]]
    ac /= ac[0, 0]
    # e-folding lag along each axis, in metres, averaged
    lens = []
    for prof, step in ((ac[:, 0], dn), (ac[0, :], de)):
        k = int(np.argmax(prof < np.exp(-1.0)))
        lens.append(step * (k - 1 + (prof[k - 1] - np.exp(-1.0)) / (prof[k - 1] - prof[k])))
    return {
        "eigen_vs_ss_rms_mgal": float(np.sqrt(np.mean(d**2))),
        "eigen_vs_ss_mean_mgal": float(d.mean()),
        "eigen_vs_ss_std_mgal": float(d.std()),
        "eigen_signal_std_mgal": float(eg_dist[25:-25, 25:-25].std()),
        "eigen_vs_ss_correlation_m": float(np.mean(lens)),
        "eigen_vs_ss_points": int(d.size),
    }


def make_eigen() -> dict:
    ds = xr.load_dataset(SHARED / "earth-gravity-10arcmin.nc")
    la0, la1, lo0, lo1 = SE_AUS_REGION_DEG
    sub = ds.sel(latitude=slice(la0, la1), longitude=slice(lo0, lo1))
    h = np.asarray(sub.height.values, dtype=float)
    if not np.allclose(h, EIGEN_HEIGHT_M):
        raise SystemExit(f"unexpected EIGEN-6C4 grid height {h.min()}..{h.max()} m")
    lat = np.asarray(sub.latitude.values) * DEG_TO_RAD
    lon = np.asarray(sub.longitude.values) * DEG_TO_RAD
    g = np.asarray(sub.gravity.values, dtype=float)  # mGal, full gravity
    la, _ = np.meshgrid(lat, lon, indexing="ij")
    dist = g - normal_gravity(la, EIGEN_HEIGHT_M) * MPS2_TO_MGAL
    check = eigen_error_vs_sandwell_smith()
    sigma = round(check["eigen_vs_ss_rms_mgal"], 1)
    corr = round(check["eigen_vs_ss_correlation_m"], -3)
    fmap = GridMap(
        lat,
        lon,
        dist,
        kind=FieldKind.GRAVITY_DISTURBANCE_MGAL,
        frame="geodetic",
        altitude_m=EIGEN_HEIGHT_M,
        name="eigen6c4-australia-se",
        metadata={
            "source": "Fatiando a Terra earth-gravity-10arcmin v1 (EIGEN-6C4, GFZ/ICGEM, doi:10.5880/icgem.2015.1), "
            "CC-BY-4.0",
            "method": "EIGEN-6C4 gravity at 10 km minus WGS-84 normal gravity at 10 km (magnav_ins.ins.earth)",
            "made_by": "bench/make_builtin_maps.py",
            "error_layer": {key: round(v, 4) for key, v in check.items()},
        },
        error_sigma=sigma,
        error_correlation_m=corr,
        error_source=(
            f"uniform {sigma} mGal, correlation {corr:.0f} m: RMS difference at 10 km against an independent grid "
            "(Sandwell & Smith 2' marine free-air gravity, Gulf of Alaska, upward-continued; bench/make_builtin_maps.py)"
        ),
    )
    write_map(fmap, OUT / "eigen6c4-australia-se.nc", dtype="float32")
    return {
        **check,
        "eigen_shape": list(fmap.shape),
        "eigen_range_mgal": [float(np.min(dist)), float(np.max(dist))],
        "eigen_bytes": (OUT / "eigen6c4-australia-se.nc").stat().st_size,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", action="store_true", help="print one JSON line")
    ap.add_argument("--only", choices=["osborne"], default=None, help="remake only the Osborne map and tie lines")
    args = ap.parse_args()
    if not SHARED.is_dir():
        raise SystemExit(f"{SHARED} not found: ../shared/data must sit beside the project")
    if args.only == "osborne":
        res = make_osborne()
    else:
        res = {**make_geoid(), **make_eigen(), **make_osborne()}
    print(json.dumps(res) if args.json else json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
