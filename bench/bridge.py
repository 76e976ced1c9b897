"""Bridge throughput and latency: an emulated autopilot streams HIGHRES_IMU at 400 Hz (with magnetometer) over UDP
loopback while the bridge runs INS + matcher + UKF and sends GPS_INPUT / GLOBAL_POSITION_SENSOR at 5 Hz.

Prints one JSON line (``--json``) with: IMU messages sent and processed, the fraction kept up with, gaps seen,
median / p95 latency from the arrival of the newest IMU sample an output includes to the output's send (ms), the
bridge thread's CPU use (fraction of one core), outputs per second, and the horizontal error of its healthy outputs.

    python bench/bridge.py --json [--rate 400] [--seconds 20] [--matcher mlr] [--fusion ukf]
"""

from __future__ import annotations

import argparse
import json
import math
import socket
import time

import numpy as np

from magnav_ins.core.frames import horizontal_error_m
from magnav_ins.maps.builtin import load_map
from magnav_ins.mavlink.bridge import Bridge, BridgeConfig, ScalarAnomalyModel
from magnav_ins.mavlink.emulator import AutopilotEmulator, flight_over_map
from magnav_ins.mavlink.link import MavLink
from magnav_ins.mavlink.replay import make_online_pipeline


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--rate", type=float, default=400.0, help="HIGHRES_IMU rate, Hz")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--matcher", default="mlr")
    ap.add_argument("--fusion", default="ukf")
    ap.add_argument("--reading-interval", type=float, default=0.1)
    args = ap.parse_args()

    fmap = load_map("builtin:osborne-magnetic")
    flight = flight_over_map(
        fmap,
        start=(math.radians(-21.93), math.radians(140.62)),
        heading=math.radians(80),
        speed_mps=60.0,
        duration_s=args.seconds + 10.0,
        rate_hz=args.rate,
        altitude_m=400.0,
        seed=1,
    )
    port = free_udp_port()
    link = MavLink(f"udpin:127.0.0.1:{port}", source_system=1, peer_system=1, peer_component=1)
    config = BridgeConfig(
        output="global_position_sensor",
        output_rate_hz=5.0,
        imu_rate_hz=args.rate,
        reading_interval_s=args.reading_interval,
        init_sigma_m=10.0,
    )

    def factory(nav0, sigma_m):
        return make_online_pipeline(nav0, sigma_m, fmap, grade="tactical", matcher=args.matcher, fusion=args.fusion)

    bridge = Bridge(link, config, factory, ScalarAnomalyModel(flight.date))
    # warm the compiled kernels and the matcher once, outside the measurement
    warm = factory(flight.truth.at(0), 10.0)
    for k in range(1, 50):
        warm.push_imu(flight.imu.t[k], flight.imu.gyro_b[k], flight.imu.accel_b[k])
    autopilot = MavLink(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    emu = AutopilotEmulator(autopilot, flight.truth, flight.imu, flight.mag_b_nt).start()
    wall0 = time.monotonic()
    cpu0 = time.thread_time()
    bridge.run(duration_s=args.seconds)
    cpu = time.thread_time() - cpu0
    wall = time.monotonic() - wall0
    rec = emu.stop()
    time.sleep(0.1)

    outs = [o for o in rec.outputs if o.healthy]
    t = np.array([o.fields["time_usec"] * 1e-6 for o in outs])
    err = (
        horizontal_error_m(
            [o.lat for o in outs],
            [o.lon for o in outs],
            np.interp(t, flight.truth.t, flight.truth.lat),
            np.interp(t, flight.truth.t, flight.truth.lon),
        )
        if outs
        else np.array([np.nan])
    )
    lat_ms = np.array(bridge.latencies_s) * 1e3
    h = bridge.health
    result = {
        "imu_rate_hz": args.rate,
        "seconds": round(wall, 2),
        "imu_sent": rec.imu_sent,
        "imu_processed": h.imu_samples,
        "kept_up_fraction": round(h.imu_samples / max(rec.imu_sent, 1), 4),
        "imu_gaps": h.imu_gaps,
        "readings": h.readings,
        "outputs_per_s": round(h.outputs_sent / wall, 2),
        "latency_median_ms": round(float(np.median(lat_ms)), 3) if len(lat_ms) else None,
        "latency_p95_ms": round(float(np.percentile(lat_ms, 95)), 3) if len(lat_ms) else None,
        "cpu_fraction_of_one_core": round(cpu / wall, 3),
        "healthy_outputs": len(outs),
        "rms_horizontal_m": round(float(np.sqrt(np.mean(err**2))), 2),
        "matcher": args.matcher,
        "fusion": args.fusion,
        "link": link.stats.as_dict(),
    }
    link.close()
    autopilot.close()
    if args.json:
        print(json.dumps(result))
    else:
        for k, v in result.items():
            print(f"{k:28s} {v}")


if __name__ == "__main__":
    main()
