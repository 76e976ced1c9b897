"""Strapdown mechanisation: magnav_ins vs pyins on the same IMU samples, in one process.

pyins (``python-ins``) simulates 1 h of 100 Hz motion (``pyins.sim.generate_sine_velocity_motion``, the scenario of
pyins's own ``test_integrate_sine_velocity`` but at sea level: at height the two gravity models differ, pyins's normal
gravity has no north component while ours has the -8.08e-9 h sin(2 lat) m/s^2 deflection) and generates exact
increment-type IMU samples (angle and velocity increments over each interval, first sample duplicated). The SAME
samples go to pyins's ``compute_increments_from_imu`` + ``strapdown.Integrator`` and to our
:func:`magnav_ins.ins.strapdown.integrate`; both are compared with pyins's reference trajectory. Both vertical
channels are free.

Prints ONE JSON line with ``--json``: throughput (warm, compile excluded; pyins timed end to end from the IMU frame,
as its API requires, and its numba kernel alone), maximum horizontal and vertical errors, compile time, and the
throughput of :func:`integrate_batch` over many runs.

Run: ``python bench/ins_vs_pyins.py --json``
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def _pyins_run(pyins_strapdown, ref, imu):
    inc = pyins_strapdown.compute_increments_from_imu(imu, "increment")
    integ = pyins_strapdown.Integrator(ref.iloc[0], True)
    return integ.integrate(inc)


def _altitude_scenario(duration: float) -> dict[str, float]:
    """pyins's own test scenario (1500 m, descending 0.2 m/s, 1 m/s sine on all axes). Here the two normal-gravity
    models differ (pyins: Somigliana x (1 - 2h/a), no north component; ours: Groves eq. 2.139-2.140 with the
    -8.08e-9 h sin(2 lat) north deflection), so our raw error measures that model difference. Adding
    ``C_bn (g_pyins - g_ours) dt`` to our velocity increments (on the truth path) aligns the models and leaves the
    integration error alone."""
    from pyins import earth as pyins_earth
    from pyins import sim
    from pyins import strapdown as pyins_strapdown

    from magnav_ins.core.frames import C_nb_from_q, horizontal_error_m, q_nb_from_euler
    from magnav_ins.core.types import ImuIncrements, NavState
    from magnav_ins.ins import earth, strapdown

    ref, imu = sim.generate_sine_velocity_motion(
        0.01, duration, [55.0, 37.0, 1500.0], [5.0, -3.0, 0.2], velocity_change_amplitude=1.0, sensor_type="increment"
    )
    t = imu.index.to_numpy(dtype=float)
    r0 = ref.iloc[0]
    rph = np.deg2rad(ref[["roll", "pitch", "heading"]].to_numpy())
    init = NavState(
        float(t[0]), np.deg2rad(r0.lat), np.deg2rad(r0.lon), float(r0.alt), r0[["VN", "VE", "VD"]].to_numpy(float),
        q_nb_from_euler(*rph[0]),
    )  # fmt: skip
    lat, lon, h = np.deg2rad(ref.lat.to_numpy()), np.deg2rad(ref.lon.to_numpy()), ref.alt.to_numpy()
    dtheta = imu[["gyro_x", "gyro_y", "gyro_z"]].to_numpy()
    dv = imu[["accel_x", "accel_y", "accel_z"]].to_numpy()
    raw = strapdown.integrate(init, ImuIncrements(t, dtheta, dv))
    dg_n = pyins_earth.gravity_n(ref.lat.to_numpy(), h) - earth.gravity_n(lat, h)
    C_nb = C_nb_from_q(q_nb_from_euler(*rph.T))
    dts = np.diff(t, prepend=t[0] - 0.01)[:, None]
    aligned = strapdown.integrate(init, ImuIncrements(t, dtheta, dv + np.einsum("kji,kj->ki", C_nb, dg_n) * dts))
    theirs = pyins_strapdown.Integrator(ref.iloc[0], True).integrate(
        pyins_strapdown.compute_increments_from_imu(imu, "increment")
    )
    e_p = horizontal_error_m(np.deg2rad(theirs.lat.to_numpy()), np.deg2rad(theirs.lon.to_numpy()), lat, lon)
    return {
        "alt1500_ours_raw_max_error_m": float(f"{horizontal_error_m(raw.lat, raw.lon, lat, lon).max():.4g}"),
        "alt1500_ours_gravity_aligned_max_error_m": float(
            f"{horizontal_error_m(aligned.lat, aligned.lon, lat, lon).max():.4g}"
        ),
        "alt1500_pyins_max_error_m": float(f"{e_p.max():.4g}"),
        "alt1500_ours_gravity_aligned_max_vertical_error_m": float(f"{np.abs(aligned.h - h).max():.4g}"),
        "alt1500_pyins_max_vertical_error_m": float(f"{np.abs(theirs.alt.to_numpy() - h).max():.4g}"),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON line only")
    ap.add_argument("--duration", type=float, default=3600.0, help="simulated time, s (default 3600)")
    ap.add_argument(
        "--no-altitude", dest="altitude", action="store_false", help="skip the 1500 m scenario (gravity-model study)"
    )
    ap.add_argument("--runs", type=int, default=16, help="runs for the batch-kernel throughput (default 16)")
    args = ap.parse_args(argv)

    from pyins import sim
    from pyins import strapdown as pyins_strapdown

    from magnav_ins.core.frames import horizontal_error_m, q_nb_from_euler
    from magnav_ins.core.types import ImuIncrements, NavState
    from magnav_ins.ins import strapdown

    dt = 0.01
    t_gen = time.perf_counter()
    ref, imu = sim.generate_sine_velocity_motion(
        dt, args.duration, [55.0, 37.0, 0.0], [5.0, -3.0, 0.0], velocity_change_amplitude=[1.0, 1.0, 0.0],
        sensor_type="increment",
    )  # fmt: skip
    gen_s = time.perf_counter() - t_gen
    t = imu.index.to_numpy(dtype=float)
    n = len(t)
    dtheta = imu[["gyro_x", "gyro_y", "gyro_z"]].to_numpy()
    dv = imu[["accel_x", "accel_y", "accel_z"]].to_numpy()
    r0 = ref.iloc[0]
    init = NavState(
        float(t[0]), np.deg2rad(r0.lat), np.deg2rad(r0.lon), float(r0.alt), r0[["VN", "VE", "VD"]].to_numpy(float),
        q_nb_from_euler(*np.deg2rad(r0[["roll", "pitch", "heading"]].to_numpy(float))),
    )  # fmt: skip
    inc = ImuIncrements(t, dtheta, dv)

    # --- ours: compile, then warm timing ---------------------------------------------------------------------
    tc = time.perf_counter()
    strapdown.integrate(init, ImuIncrements(t[:3], dtheta[:3], dv[:3]))
    compile_s = time.perf_counter() - tc
    best = np.inf
    for _ in range(3):
        t1 = time.perf_counter()
        ours = strapdown.integrate(init, inc)
        best = min(best, time.perf_counter() - t1)
    ours_rate = (n - 1) / best

    # --- pyins: warm (its kernel compiles on first use), end to end and kernel only --------------------------
    _pyins_run(pyins_strapdown, ref.iloc[:10], imu.iloc[:10])
    best_p = np.inf
    for _ in range(2):
        t1 = time.perf_counter()
        theirs = _pyins_run(pyins_strapdown, ref, imu)
        best_p = min(best_p, time.perf_counter() - t1)
    pyins_rate = (n - 1) / best_p
    incr = pyins_strapdown.compute_increments_from_imu(imu, "increment")
    integ = pyins_strapdown.Integrator(ref.iloc[0], True)
    t1 = time.perf_counter()
    integ._integrate(incr, "predict")
    pyins_kernel_rate = (n - 1) / (time.perf_counter() - t1)

    lat_true = np.deg2rad(ref.lat.to_numpy())
    lon_true = np.deg2rad(ref.lon.to_numpy())
    e_ours = horizontal_error_m(ours.lat, ours.lon, lat_true, lon_true)
    e_pyins = horizontal_error_m(
        np.deg2rad(theirs.lat.to_numpy()), np.deg2rad(theirs.lon.to_numpy()), lat_true, lon_true
    )
    v_ours = np.abs(ours.h - ref.alt.to_numpy()).max()
    v_pyins = np.abs(theirs.alt.to_numpy() - ref.alt.to_numpy()).max()

    # --- batch kernel: R runs of the same motion as mean rates (increment / dt), parallel over runs -----------
    r_runs = args.runs
    m = min(n, 60_000)
    rates_g = np.empty((r_runs, m, 3))
    rates_a = np.empty((r_runs, m, 3))
    dts = np.diff(t[:m], prepend=t[0] - dt)[:, None]
    rates_g[:] = dtheta[:m] / dts
    rates_a[:] = dv[:m] / dts
    args_b = (
        t[:m], rates_g, rates_a, np.full(r_runs, init.lat), np.full(r_runs, init.lon), np.full(r_runs, init.h),
        np.tile(init.v_n, (r_runs, 1)), np.tile(init.q_nb, (r_runs, 1)),
    )  # fmt: skip
    strapdown.integrate_batch(*(a[:3] if i == 0 else a[:, :3] if i < 3 else a for i, a in enumerate(args_b)))
    t1 = time.perf_counter()
    batch = strapdown.integrate_batch(*args_b, decimate=100)
    batch_rate = r_runs * (m - 1) / (time.perf_counter() - t1)
    # the batch kernel reproduces the single-run integration of the same samples as rates
    single = strapdown.integrate(init, ImuIncrements(t[:m], dtheta[:m], dv[:m]))
    batch_vs_single = float(np.abs(batch.lat[0] - single.lat[::100]).max() * 6.4e6)

    # --- streaming stepper: per-call cost (what the UKF and the MAVLink bridge pay per sample) ------------------
    stepper = strapdown.StrapdownStepper(init)
    k_steps = min(n - 1, 100_000)
    rows_t = t[1 : k_steps + 1].tolist()
    rows_a = [np.ascontiguousarray(r) for r in dtheta[1 : k_steps + 1]]
    rows_b = [np.ascontiguousarray(r) for r in dv[1 : k_steps + 1]]
    step = stepper.step_increment
    t1 = time.perf_counter()
    for tk, a, b in zip(rows_t, rows_a, rows_b, strict=True):
        step(tk, a, b)
    stepper_us = (time.perf_counter() - t1) / k_steps * 1e6

    alt = _altitude_scenario(args.duration) if args.altitude else {}

    fig = {
        "duration_s": float(t[-1] - t[0]),
        "samples": int(n),
        "ours_msamples_per_s": round(ours_rate / 1e6, 3),
        "pyins_msamples_per_s": round(pyins_rate / 1e6, 3),
        "pyins_kernel_msamples_per_s": round(pyins_kernel_rate / 1e6, 3),
        "speed_ratio": round(ours_rate / pyins_rate, 2),
        "ours_max_error_m": float(f"{e_ours.max():.4g}"),
        "pyins_max_error_m": float(f"{e_pyins.max():.4g}"),
        "ours_max_vertical_error_m": float(f"{v_ours:.4g}"),
        "pyins_max_vertical_error_m": float(f"{v_pyins:.4g}"),
        "ours_compile_s": round(compile_s, 2),
        "stepper_us_per_call": round(stepper_us, 2),
        "batch_runs": r_runs,
        "batch_samples_per_run": int(m),
        "batch_msamples_per_s": round(batch_rate / 1e6, 3),
        "batch_vs_single_m": float(f"{batch_vs_single:.3g}"),
        "pyins_generate_s": round(gen_s, 1),
        **alt,
    }
    if args.json:
        print(json.dumps(fig))
    else:
        for k, v in fig.items():
            print(f"{k:32s} {v}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
