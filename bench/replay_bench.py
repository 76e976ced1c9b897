"""``magnav-ins replay`` figures: accuracy on a simulated flight log over the Osborne map, throughput on real PX4 logs.

Simulated: 90 s east at 40 m/s and 400 m over the Osborne mine anomaly (``builtin:osborne-magnetic``), tactical IMU
errors (seed 7), magnetometer = IGRF (2020-06-01) scaled by the map's anomaly + 1 nT noise, written as a MAVLink
tlog (HIGHRES_IMU 25 Hz, ATTITUDE and GLOBAL_POSITION_INT 5 Hz); replayed with ``--init`` 68 m off (44 m N, 52 m E),
readings every 0.5 s, MLR windows of 30 readings every 10, for each fuser. Real: the two PX4 ULogs of
``../shared/data/px4_ulog`` (off any shipped map) for throughput (CPU s per IMU sample, pipeline sample by sample).

Usage: ``python bench/replay_bench.py [--json]``.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np

from magnav_ins.core.frames import C_nb_from_q, euler_from_q_nb, horizontal_error_m, meters_to_latlon
from magnav_ins.maps.builtin import load_map
from magnav_ins.mavlink.bridge import ScalarAnomalyModel
from magnav_ins.mavlink.replay import read_log, replay

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
DATE = "2020-06-01"
T0 = 100.0
INIT = (math.radians(-21.7996), math.radians(140.7205), 400.0, math.radians(90.0))


def simulated_tlog(path: Path):
    from magnav_ins.ins import imu_models
    from magnav_ins.ins.simulate import great_circle, ideal_imu
    from magnav_ins.maps.reference import igrf_ned
    from magnav_ins.mavlink.link import AttitudeMessage, ImuMessage, PositionMessage, write_tlog

    fmap = load_map("builtin:osborne-magnetic")
    lat0, lon0 = math.radians(-21.80), math.radians(140.72)
    dlat, dlon = meters_to_latlon(0.0, 40.0 * 90.0, lat0, 0.0)
    truth = great_circle(lat0, lon0, lat0 + float(dlat), lon0 + float(dlon), 400.0, 40.0, 25.0)
    rng = np.random.default_rng(7)
    imu, _ = imu_models.corrupt(ideal_imu(truth), imu_models.get_grade("tactical"), rng)
    anomaly = np.asarray(fmap.value(truth.lat, truth.lon, truth.h), float)
    b_n = igrf_ned(truth.lat, truth.lon, truth.h, DATE)
    b_n = b_n * (1.0 + anomaly / np.linalg.norm(b_n, axis=1))[:, None]
    mag_b = np.einsum("nji,nj->ni", C_nb_from_q(truth.q_nb), b_n) + rng.normal(0.0, 1.0, b_n.shape)
    roll, pitch, yaw = euler_from_q_nb(truth.q_nb)
    msgs = []
    for k in range(len(truth)):
        t = float(truth.t[k]) + T0
        msgs.append(ImuMessage(t, imu.gyro_b[k], imu.accel_b[k], mag_b[k], "HIGHRES_IMU", 1, 1))
        if k % 5 == 0:
            msgs.append(AttitudeMessage(t, float(roll[k]), float(pitch[k]), float(yaw[k]), 1, 1))
            msgs.append(
                PositionMessage(t, float(truth.lat[k]), float(truth.lon[k]), float(truth.h[k]), truth.v_n[k], 1, 1)
            )
    write_tlog(path, msgs)
    return truth, fmap


def _timed(fn):
    w, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w, time.process_time() - c


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON line")
    args = ap.parse_args()
    result: dict = {"simulated": {}, "px4": {}}
    with tempfile.TemporaryDirectory() as d:
        tlog = Path(d) / "sim.tlog"
        truth, fmap = simulated_tlog(tlog)
        rec = read_log(tlog)
        for fusion in ("ukf", "graph", "free_inertial"):
            res, wall, cpu = _timed(
                lambda fusion=fusion: replay(
                    rec, fmap, init=INIT, field_model=ScalarAnomalyModel(DATE), reading_interval_s=0.5,
                    output_dt=1.0, fusion=fusion, matcher="mlr",
                )
            )  # fmt: skip
            t = res.t - T0
            err = horizontal_error_m(
                np.array([n.lat for n in res.navs]), np.array([n.lon for n in res.navs]),
                np.interp(t, truth.t, truth.lat), np.interp(t, truth.t, truth.lon),
            )  # fmt: skip
            s = res.summary()
            result["simulated"][fusion] = {
                "rms_m": round(float(np.sqrt(np.mean(err**2))), 2),
                "final_m": round(float(err[-1]), 2),
                "rms_last_30s_m": round(float(np.sqrt(np.mean(err[t >= t[-1] - 30] ** 2))), 2),
                "fix_attempts": s["fix_attempts"],
                "fixes_issued": s["fixes_issued"],
                "fixes_accepted": s["fixes_accepted"],
                "cpu_us_per_imu_sample": round(1e6 * cpu / res.imu_samples, 1),
                "wall_s": round(wall, 2),
            }
    if SHARED.is_dir():
        for name, init in (
            ("sample_log_small.ulg", None),
            ("sample.ulg", (math.radians(47.4), math.radians(8.5), 500.0, 0.0)),
        ):
            rec = read_log(SHARED / "px4_ulog" / name)
            res, wall, cpu = _timed(
                lambda rec=rec, init=init: replay(
                    rec, load_map("builtin:osborne-magnetic"), init=init, field_model=ScalarAnomalyModel(DATE)
                )
            )
            s = res.summary()
            result["px4"][name] = {
                "imu_samples": res.imu_samples,
                "duration_s": round(res.duration_s, 1),
                "fix_attempts": s["fix_attempts"],
                "no_fix_reasons": s["no_fix_reasons"],
                "gnss_error_max_m": round(s["gnss_error_m"]["max"], 2) if "gnss_error_m" in s else None,
                "cpu_us_per_imu_sample": round(1e6 * cpu / res.imu_samples, 1),
                "wall_s": round(wall, 2),
            }
    if args.json:
        print(json.dumps(result))
    else:
        print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
