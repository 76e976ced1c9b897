"""Information content of maps and the accuracy/speed of the map tools (maps.variability, maps.continuation).

1. Wang et al. (2022) route, Melbourne [-38, 144.5] -> Sydney [-35, 150] at 22 m/s, on the real EIGEN-6C4 gravity
   disturbance at 10 km (``builtin:eigen6c4-australia-se``, a straight lat/lon line): feature
   variability C_i along the route (Wang eq. 14; Wang Fig. 4 shows it small during the first hour) and the
   Cramér-Rao bounds for a 1 mGal gravimeter every 10 s (one reading; a T = 30 batch).
2. Storms' hallway (synthetic, maps.synthetic.hallway_map): single-reading CRLB of a 3-axis reading with
   sigma = 1 mG (Storms Table 4.1), next to his reported < 0.3 m RMS.
3. FFT upward continuation of a point-dipole anomaly 0 -> 200 m against the analytic field; time per 1024^2 grid;
   side by side with harmonica.upward_continuation (when installed).
4. Self-building: readings at known positions accumulated per node; map error against sigma / sqrt(count).
5. Speed of the feature-variability raster on 2000 x 2000 nodes.

Run: ``python bench/maps_information.py [--json]`` (prints one JSON line with --json).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from magnav_ins.core.frames import horizontal_error_m
from magnav_ins.core.units import DEG_TO_RAD, NT_PER_MILLIGAUSS
from magnav_ins.maps import synthetic as syn
from magnav_ins.maps import variability as var
from magnav_ins.maps.continuation import upward_continue_array


def wang_route() -> dict[str, float]:
    from magnav_ins.maps.io import load_map

    gm = load_map("builtin:eigen6c4-australia-se")  # EIGEN-6C4 disturbance at 10 km (shipped, from shared/data)
    # route: 22 m/s, a reading every 10 s
    start, end = np.array([-38.0, 144.5]) * DEG_TO_RAD, np.array([-35.0, 150.0]) * DEG_TO_RAD
    length = float(horizontal_error_m(end[0], end[1], start[0], start[1]))
    n = int(length / (22.0 * 10.0)) + 1
    f = np.linspace(0.0, 1.0, n)
    r_lat, r_lon = start[0] + f * (end[0] - start[0]), start[1] + f * (end[1] - start[1])
    t_h = f * length / 22.0 / 3600.0
    c_i = var.feature_variability_track(gm, r_lat, r_lon, window_m=60_000.0, step_m=5_000.0)
    along, batch = var.crlb_track(gm, r_lat, r_lon, sigma=1.0, window=30)
    first = t_h <= 1.0
    return {
        "route_km": length / 1e3,
        "grid_spacing_km": float(np.mean(gm.spacing_m)) / 1e3,
        "ci_median_first_hour_mgal2": float(np.nanmedian(c_i[first])),
        "ci_median_rest_mgal2": float(np.nanmedian(c_i[~first])),
        "crlb_one_reading_median_m": float(np.nanmedian(along)),
        "crlb_T30_semi_minor_median_m": float(np.nanmedian(batch.semi_minor_m[30:])),
        "crlb_T30_semi_major_median_m": float(np.nanmedian(batch.semi_major_m[30:])),
    }


def osborne() -> dict[str, float]:
    from magnav_ins.maps.io import load_map

    m = load_map("builtin:osborne-magnetic")
    r = var.crlb_raster(m, 1.0, window_m=1000.0)
    return {
        "grid_spacing_m": float(m.spacing_m[0]),
        "crlb_one_reading_median_m": float(np.nanmedian(r["along_gradient"])),
        "crlb_1km_window_semi_major_median_m": float(np.nanmedian(r["semi_major"])),
        "ci_1km_median_nt2": float(np.nanmedian(var.feature_variability(m, 1000.0).values)),
    }


def hallway() -> dict[str, float]:
    m = syn.hallway_map(np.random.default_rng(0))
    sigma = 1.0 * NT_PER_MILLIGAUSS  # Storms Table 4.1
    r = var.crlb_raster(m, sigma, window_m=1.5)
    c = var.feature_variability(m, 1.5).values
    return {
        "crlb_one_reading_median_m": float(np.nanmedian(r["along_gradient"])),
        "crlb_one_reading_p90_m": float(np.nanpercentile(r["along_gradient"], 90)),
        "ci_median_mg2": float(np.nanmedian(c)) / NT_PER_MILLIGAUSS**2,
        "storms_reported_rms_m": 0.3,
    }


def continuation() -> dict[str, float]:
    d = 25.0
    ax = np.arange(-512, 512) * d
    nn, ee = np.meshgrid(ax, ax, indexing="ij")
    b_hat = syn.direction_ned(60.0 * DEG_TO_RAD, 10.0 * DEG_TO_RAD)

    def field(h: float) -> np.ndarray:
        pts = np.stack([nn.ravel(), ee.ravel(), np.full(nn.size, -h)], axis=-1)
        return syn.dipole_total_field_anomaly(pts, [0.0, 0.0, 300.0], 1e8 * b_hat, b_hat).reshape(nn.shape)

    t0, t200 = field(0.0), field(200.0)
    tic = time.perf_counter()
    cont = upward_continue_array(t0, (d, d), 200.0)
    wall = time.perf_counter() - tic
    inner = (np.abs(nn) < 6000) & (np.abs(ee) < 6000)
    err = cont - t200
    out = {
        "grid": 1024,
        "signal_ptp_nt": float(np.ptp(t200)),
        "rms_error_inner_nt": float(np.sqrt(np.mean(err[inner] ** 2))),
        "max_error_nt": float(np.max(np.abs(err))),
        "wall_s": wall,
    }
    try:  # peer: harmonica.upward_continuation with xrft zero padding (its documented recipe), demeaned
        import warnings

        import harmonica as hm
        import xarray as xr
        import xrft
    except ImportError:
        return out
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tic = time.perf_counter()
        g = xr.DataArray(t0 - t0.mean(), coords={"northing": ax, "easting": ax}, dims=("northing", "easting"))
        pad = {"northing": ax.size // 2, "easting": ax.size // 2}
        peer = xrft.unpad(hm.upward_continuation(xrft.pad(g, pad), 200.0), pad).values + t0.mean()
        out["harmonica_wall_s"] = time.perf_counter() - tic
    perr = peer - t200
    out["harmonica_rms_error_inner_nt"] = float(np.sqrt(np.mean(perr[inner] ** 2)))
    out["harmonica_max_error_nt"] = float(np.max(np.abs(perr)))
    return out


def self_building() -> dict[str, float]:
    """Readings at known positions (sigma = 1 mG, 3-axis) accumulated on the hallway grid, ~12 per node."""
    from magnav_ins.maps.selfbuild import MapAccumulator

    rng = np.random.default_rng(3)
    hall = syn.hallway_map(rng)
    inside = np.argwhere(np.isfinite(hall.values[..., 0]))
    pick = inside[rng.integers(0, len(inside), 12 * len(inside))]
    north, east = hall.axes
    lat, lon = hall.from_local(north[pick[:, 0]], east[pick[:, 1]])
    sigma = 1.0 * NT_PER_MILLIGAUSS
    z = hall.values[pick[:, 0], pick[:, 1]] + sigma * rng.standard_normal((len(pick), 3))
    acc = MapAccumulator.like(hall)
    tic = time.perf_counter()
    acc.add(lat, lon, z)
    wall = time.perf_counter() - tic
    built = acc.result()
    err = built.mean.values - hall.values
    out: dict[str, float] = {"readings": float(len(pick)), "add_wall_s": wall}
    for n in (8, 12, 16):
        cells = built.count == n
        out[f"rms_error_count{n}_over_sigma"] = float(np.sqrt(np.mean(err[cells] ** 2)) / sigma)
        out[f"expected_count{n}_over_sigma"] = 1.0 / np.sqrt(n)
    return out


def variability_speed() -> dict[str, float]:
    rng = np.random.default_rng(1)
    v = syn.gaussian_random_field((2000, 2000), 10.0, 100.0, 5.0, rng)
    tic = time.perf_counter()
    var.feature_variability_array(v, (10.0, 10.0), 500.0)
    return {"cells": 4_000_000, "window_cells": 51 * 51, "wall_s": time.perf_counter() - tic}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", action="store_true", help="print one JSON line")
    a = p.parse_args(argv)
    out = {
        "wang_route_eigen6c4": wang_route(),
        "osborne_magnetic_sigma_1nt": osborne(),
        "storms_hallway": hallway(),
        "upward_continuation_dipole": continuation(),
        "self_building_hallway": self_building(),
        "feature_variability_raster": variability_speed(),
    }
    if a.json:
        print(json.dumps(out))
    else:
        for k, v in out.items():
            print(k)
            for kk, vv in (v or {"(data absent)": ""}).items():
                print(f"  {kk:<34} {vv:.4g}" if isinstance(vv, float) else f"  {kk:<34} {vv}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
