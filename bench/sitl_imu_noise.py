"""The ArduCopter SITL's IMU at rest: what the bridge's filter should assume for it (``bench/sitl_flight.py``'s grade).

Starts the SITL (``../shared/tools/ardupilot-sitl``, ``copter.parm``, ``SIM_DRIFT_SPEED=0``) at the flight's home, asks
for HIGHRES_IMU at 100 Hz and records ``--seconds`` of it on the ground. One JSON line: per-axis mean and standard
deviation of the gyro (rad/s) and accelerometer (m/s^2) samples, the white-noise densities (ARW rad/sqrt(s) and VRW
m/s/sqrt(s)) from the Allan deviation at 0.1-1 s (``*_allan``, :mod:`magnav_ins.ins.allan`; what the filter needs) and
from std x sqrt(dt) (``arw_rad_sqrt_s``, ``vrw_mps_sqrt_s``: low, the samples are filtered at 20 Hz before they are
sent), and the accelerometer scale error on the vertical axis (|mean z| / 9.80665 - 1). Use ``--seconds 60`` or more
for the Allan figures.

Usage: ``python bench/sitl_imu_noise.py [--seconds 20]``
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from magnav_ins.ins.allan import white_noise_density
from magnav_ins.mavlink.link import ImuMessage
from magnav_ins.mavlink.sitl import GroundStation, Sitl, sitl_dir

G = 9.80665


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--home", default="-21.94,140.76")
    a = ap.parse_args()
    if sitl_dir() is None:
        raise SystemExit("../shared/tools/ardupilot-sitl is not beside the project")
    lat, lon = (float(x) for x in a.home.split(","))
    with Sitl((lat, lon, 380.0, 0.0), params={"SIM_DRIFT_SPEED": 0}) as s:
        gcs = GroundStation(s.gcs_url)
        try:
            gcs.link.request_message_interval("HIGHRES_IMU", 100.0, 1, 1)
            t, g, f = [], [], []
            t_end = time.monotonic() + a.seconds + 5.0
            while time.monotonic() < t_end:
                for m in gcs.link.recv(0.05):
                    if isinstance(m, ImuMessage) and m.source == "HIGHRES_IMU":
                        t.append(m.t)
                        g.append(m.gyro_b)
                        f.append(m.accel_b)
        finally:
            gcs.close()
    t, g, f = np.array(t), np.array(g)[50:], np.array(f)[50:]  # the first half second: the streams settling
    dt = float(np.median(np.diff(t)))
    out = {
        "samples": len(g),
        "rate_hz": round(1.0 / dt, 2),
        "gyro_mean_rad_s": g.mean(0).tolist(),
        "gyro_std_rad_s": g.std(0).tolist(),
        "accel_mean_mps2": f.mean(0).tolist(),
        "accel_std_mps2": f.std(0).tolist(),
        "arw_rad_sqrt_s": (g.std(0) * np.sqrt(dt)).tolist(),
        "vrw_mps_sqrt_s": (f.std(0) * np.sqrt(dt)).tolist(),
        "arw_allan_rad_sqrt_s": white_noise_density(g, dt).tolist(),
        "vrw_allan_mps_sqrt_s": white_noise_density(f, dt).tolist(),
        "accel_scale_z": float(abs(f[:, 2].mean()) / G - 1.0),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
