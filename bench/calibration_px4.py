"""Full-ellipsoid calibration of the magnetometer in a real PX4 log (pyulog's ``test/sample.ulg``, AUAV-X21, 2016).

``sensor_combined.magnetometer_ga[0..2]`` (gauss -> nT), de-duplicated on the magnetometer's own timestamp
(``timestamp + magnetometer_timestamp_relative``; the topic repeats the last reading at the 248 Hz IMU rate).

Site: the log has no GPS (``vehicle_local_position.ref_lat = 0``) and no UTC time. We assume Zurich, PX4's
development home (47.397742 N, 8.545594 E, 488 m, PX4's default SITL home) on 2016-12-01 (the log was committed to
pyulog on 2016-12-02). The reference only sets the scale of the calibrated ``|B|``; the before/after spread of
``|B|`` is what the calibration changes. (Check: the mean measured ``|B|`` is within 1 % of IGRF there.)

Reported: the attitude coverage of the log, the full-ellipsoid attempt through :func:`calibrate` (refused when
coverage is insufficient, with the reason), the same fit forced through (what the refusal protects against), and
``|B|`` spread (std, max - min) before and after, next to the noise floor (``|B|`` std while at rest).

    python bench/calibration_px4.py [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from magnav_ins.aiding.calibration import MagnitudeStats, calibrate, fit_quadric
from magnav_ins.core.errors import InputError
from magnav_ins.core.units import DEG_TO_RAD, NT_PER_GAUSS, RAD_TO_DEG
from magnav_ins.maps.reference import igrf_ned
from magnav_ins.mavlink.ulog import read_ulog_topic

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
LOG = DATA / "px4_ulog" / "sample.ulg"
SITE = {"name": "Zurich (PX4 default home)", "lat_deg": 47.397742, "lon_deg": 8.545594, "alt_m": 488.0}
DATE = "2016-12-01"
REST_GYRO_RAD_S = 0.05


def load_mag(path: Path = LOG) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(t [s], m_nt (N, 3), gyro (N, 3) rad/s)`` with one row per magnetometer sample."""
    mag_f = [f"magnetometer_ga[{i}]" for i in range(3)]
    gyr_f = [f"gyro_rad[{i}]" for i in range(3)]
    d = read_ulog_topic(path, "sensor_combined", ["magnetometer_timestamp_relative", *mag_f, *gyr_f])
    t = d["t"] + d["magnetometer_timestamp_relative"] * 1e-6
    _, idx = np.unique(np.round(t * 1e6), return_index=True)
    m = np.column_stack([d[f] for f in mag_f])[idx] * NT_PER_GAUSS
    g = np.column_stack([d[f] for f in gyr_f])[idx]
    return t[idx], m, g


def coverage(m: np.ndarray) -> dict:
    u = m / np.linalg.norm(m, axis=1)[:, None]
    mu = u.mean(axis=0)
    mu /= np.linalg.norm(mu)
    ang = np.arccos(np.clip(u @ mu, -1.0, 1.0)) * RAD_TO_DEG
    sv = np.linalg.svd(m - m.mean(axis=0), compute_uv=False) / math.sqrt(len(m))
    return {
        "max_angle_from_mean_deg": float(ang.max()),
        "p99_angle_deg": float(np.percentile(ang, 99)),
        "principal_spread_nt": sv.tolist(),
    }


def _stats(s: MagnitudeStats) -> dict:
    return {"mean_nt": s.mean_nt, "std_nt": s.std_nt, "span_nt": s.span_nt, "rms_vs_igrf_nt": s.rms_error_nt}


def run() -> dict:
    t, m, g = load_mag()
    lat, lon = SITE["lat_deg"] * DEG_TO_RAD, SITE["lon_deg"] * DEG_TO_RAD
    field = np.asarray(igrf_ned(lat, lon, SITE["alt_m"], DATE), float).reshape(3)
    total = float(np.linalg.norm(field))
    rest = np.linalg.norm(g, axis=1) < REST_GYRO_RAD_S
    mag = np.linalg.norm(m, axis=1)
    out: dict = {
        "log": "px4_ulog/sample.ulg",
        "samples": int(len(m)),
        "duration_s": float(t[-1] - t[0]),
        "site": {**SITE, "date": DATE},
        "igrf_total_nt": total,
        "igrf_ned_nt": field.tolist(),
        "mean_measured_over_igrf": float(mag.mean() / total),
        "coverage": coverage(m),
        "fraction_at_rest": float(rest.mean()),
        "noise_floor_std_at_rest_nt": float(mag[rest].std()),
        "before": _stats(MagnitudeStats.of(m, total)),
    }
    try:
        cal = calibrate(m, "ellipsoid", field, lat=lat, lon=lon, alt=SITE["alt_m"], date=DATE, source="sample.ulg")
        out["ellipsoid"] = {"accepted": True, "after": _stats(cal.after), "A": cal.A.tolist(), "b_nt": cal.b.tolist()}
    except InputError as exc:
        out["ellipsoid"] = {"accepted": False, "reason": str(exc)}
    forced = {}
    for name, pub in (("robust", False), ("as_printed_k0", True)):
        try:
            q = fit_quadric(m, total, published=pub)
            after = MagnitudeStats.of((m - q.b) @ q.A.T, total)
            forced[name] = {
                "after": _stats(after),
                "std_ratio_before_over_after": out["before"]["std_nt"] / after.std_nt,
                "condition": q.condition,
                "A_eigenvalues": np.linalg.eigvalsh(q.A).tolist(),
            }
        except InputError as exc:
            forced[name] = {"error": str(exc)}
    out["ellipsoid_forced"] = forced
    # the smallest model the log might support: hard iron only (bias, sphere of IGRF radius), for comparison
    sol = least_squares(lambda b: np.linalg.norm(m - b, axis=1) - total, np.zeros(3))
    hard = MagnitudeStats.of(m - sol.x, total)
    out["hard_iron_only"] = {
        "b_nt": sol.x.tolist(),
        "after": _stats(hard),
        "std_ratio_before_over_after": out["before"]["std_nt"] / hard.std_nt,
    }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON line")
    args = ap.parse_args(argv)
    if not LOG.is_file():
        print(f"missing {LOG.name}: put the shared data beside the project", file=sys.stderr)
        return 1
    res = run()
    if args.json:
        print(json.dumps(res))
        return 0
    b = res["before"]
    print(
        f"{res['samples']} magnetometer samples over {res['duration_s']:.1f} s; {100 * res['fraction_at_rest']:.1f} % at rest"
    )
    print(f"site {res['site']['name']} {res['site']['date']}: IGRF |B| = {res['igrf_total_nt']:.0f} nT")
    print(f"mean measured |B| / IGRF = {res['mean_measured_over_igrf']:.4f}")
    print(f"coverage: max {res['coverage']['max_angle_from_mean_deg']:.1f} deg from the mean field direction")
    print(
        f"before: std {b['std_nt']:.0f} nT, max-min {b['span_nt']:.0f} nT; at-rest noise floor std {res['noise_floor_std_at_rest_nt']:.0f} nT"
    )
    e = res["ellipsoid"]
    print("ellipsoid:", "accepted" if e["accepted"] else f"refused: {e['reason']}")
    for name, f in res["ellipsoid_forced"].items():
        if "after" in f:
            a = f["after"]
            print(
                f"forced ({name}): std {a['std_nt']:.0f} nT, max-min {a['span_nt']:.0f} nT, ratio {f['std_ratio_before_over_after']:.2f}"
            )
        else:
            print(f"forced ({name}): {f['error']}")
    h = res["hard_iron_only"]
    print(
        f"hard iron only (3 parameters): std {h['after']['std_nt']:.0f} nT, max-min {h['after']['span_nt']:.0f} nT, "
        f"ratio {h['std_ratio_before_over_after']:.3f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
