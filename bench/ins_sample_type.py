"""Instantaneous IMU samples through ``magnav-ins ins integrate`` against pyins, on pyins's own ``sensor_type="rate"``.

pyins (``python-ins``) simulates ``--minutes`` of 100 Hz sine-velocity motion at sea level
(``pyins.sim.generate_sine_velocity_motion``, as in ``bench/ins_vs_pyins.py``) and outputs the rates AT each sample
time (instantaneous samples, as ArduPilot's HIGHRES_IMU and most MEMS logs carry them), not interval means. The
command-line integrator is run on that CSV with ``--sample-type instantaneous`` (the trapezoid turns them into
interval means) and with ``--sample-type mean`` (the samples taken as means: a half-sample lag), and pyins integrates
the same data its own way (``compute_increments_from_imu(imu, "rate")``). One JSON line: the largest horizontal error
against pyins's reference trajectory of each (m), and the ratio ours / pyins.

Usage: ``python bench/ins_sample_type.py [--minutes 60]``
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from magnav_ins.cli import main as cli_main
from magnav_ins.core.frames import horizontal_error_m


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=60.0)
    a = ap.parse_args()
    from pyins import sim
    from pyins import strapdown as pyins_strapdown

    ref, imu = sim.generate_sine_velocity_motion(
        0.01, a.minutes * 60.0, [55.0, 37.0, 0.0], [5.0, -3.0, 0.0], velocity_change_amplitude=[1.0, 1.0, 0.0],
        sensor_type="rate",
    )  # fmt: skip
    lat_t, lon_t = np.deg2rad(ref.lat.to_numpy()), np.deg2rad(ref.lon.to_numpy())
    t0 = time.perf_counter()
    theirs = pyins_strapdown.Integrator(ref.iloc[0], True).integrate(
        pyins_strapdown.compute_increments_from_imu(imu, "rate")
    )
    pyins_s = time.perf_counter() - t0
    n = len(theirs)
    out: dict = {"minutes": a.minutes, "samples": len(imu)}
    out["pyins_max_horizontal_m"] = float(
        horizontal_error_m(
            np.deg2rad(theirs.lat.to_numpy()), np.deg2rad(theirs.lon.to_numpy()), lat_t[:n], lon_t[:n]
        ).max()
    )
    with tempfile.TemporaryDirectory() as d:
        t = imu.index.to_numpy(dtype=float)
        df = pd.DataFrame(imu.to_numpy(), columns=["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"])
        df.insert(0, "t", t)
        path = Path(d) / "imu.csv"
        df.to_csv(path, index=False, float_format="%.17g")
        r0 = ref.iloc[0]
        init = Path(d) / "init.json"
        init.write_text(
            json.dumps(
                {"t": float(t[0]), "lat_deg": float(r0.lat), "lon_deg": float(r0.lon), "h_m": float(r0.alt),
                 "v_n": [float(r0.VN), float(r0.VE), float(r0.VD)], "roll_deg": float(r0.roll),
                 "pitch_deg": float(r0.pitch), "yaw_deg": float(r0.heading)}
            )
        )  # fmt: skip
        for sample_type in ("instantaneous", "mean"):
            traj = Path(d) / f"traj_{sample_type}.csv"
            t0 = time.perf_counter()
            argv = [
                "ins",
                "integrate",
                str(path),
                "--init",
                str(init),
                "--out",
                str(traj),
                "--sample-type",
                sample_type,
            ]
            if cli_main(argv) != 0:
                raise SystemExit(f"magnav-ins ins integrate --sample-type {sample_type} failed")
            o = pd.read_csv(traj)
            e = horizontal_error_m(np.deg2rad(o.lat_deg.to_numpy()), np.deg2rad(o.lon_deg.to_numpy()), lat_t, lon_t)
            out[f"{sample_type}_max_horizontal_m"] = float(e.max())
            out[f"{sample_type}_cli_s"] = round(time.perf_counter() - t0, 1)
    out["instantaneous_over_pyins"] = round(out["instantaneous_max_horizontal_m"] / out["pyins_max_horizontal_m"], 3)
    out["mean_over_pyins"] = round(out["mean_max_horizontal_m"] / out["pyins_max_horizontal_m"], 1)
    out["pyins_s"] = round(pyins_s, 1)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
