"""``magnav-ins replay`` figures: accuracy on a simulated flight log over the Osborne map, throughput and memory on a
1 M-row recording, and throughput on the real PX4 logs.

Accuracy (``simulated``): 90 s east at 40 m/s and 400 m over the Osborne mine anomaly (``builtin:osborne-magnetic``),
tactical IMU errors (seed 7), magnetometer = IGRF (2020-06-01) scaled by the map's anomaly + 1 nT noise, written as a
MAVLink tlog (HIGHRES_IMU 25 Hz, ATTITUDE and GLOBAL_POSITION_INT 5 Hz); replayed with ``--init`` 68 m off (44 m N,
52 m E), readings every 0.5 s, MLR windows of 30 readings every 10, for each fuser. The readings are drawn from the
map itself (+ 1 nT), so the map is given as exact (error layer 0, level offset 0), as in the throughput part; the row
``ukf_shipped_error_layer`` replays the same log against the map with its own error layer (Osborne: median 26 nT,
200 m correlation), where a 30-reading window (600 m) holds about three independent looks and the likelihood is wider
than the UKF's search window: no fix is issued, the honest answer for a map with that error.

Throughput (``throughput``): a racetrack (16 x 8 km legs, 40 m/s, 400 m) over the same map, tactical IMU (seed 7)
at ``--rate`` Hz (default 400, a PX4-class IMU) for ``--rows`` samples (default 1,000,000: 41.7 min), magnetometer
as above on every row, written as a CSV into a temporary folder (streamed by the replay, 16,384 lines at a time: its replay loop includes
parsing the later chunks); each fuser replays it in its own process
(``magnav-ins replay LOG --map MAP --init ... --fusion F --reading-interval 0.5 --out TRAJ.csv --quiet``: readings
every 0.5 s, MLR windows of 30 readings (15 s, 600 m: the default 0.1 s gives 120 m windows, too short to tell places
apart on this 100 m grid: every attempt "ambiguous"), outputs every 0.2 s). The map's error layer is set to zero (the readings come from the map itself,
as in the replay tests), so fixes are accepted and the UKF's search windows stay as in an aided flight. Reported:
samples/s of the replay loop (CPU time of ``replay()``, as the command prints it), the whole command's CPU and wall
time (start-up, reading the CSV, writing the trajectory included) and its peak memory (``ru_maxrss`` of the replay
process, by ``os.wait4``). Targets (issue 18): free inertial >= 200 k samples/s, UKF >= 10 k samples/s, < 300 MB.

PX4 (``px4``): the two ULogs of ``../shared/data/px4_ulog`` (off any shipped map), CPU per IMU sample.

Usage: ``nice -n 10 python bench/replay_bench.py [--json] [--rows N] [--rate HZ] [--fusers ukf,free_inertial]``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
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
#: the racetrack's start (south-west corner, heading east) and legs (north, east m)
TRACK_START = (-21.86, 140.62)
TRACK_CORNERS = ((0.0, 0.0), (0.0, 16000.0), (8000.0, 16000.0), (8000.0, 0.0))
SPEED_MPS = 40.0


def _magnetometer(fmap, truth, rng: np.random.Generator, decimate: int = 1) -> np.ndarray:  # noqa: ANN001
    """Body-frame magnetometer (nT): IGRF scaled by the map's anomaly (|B| = F + anomaly) + 1 nT noise; the IGRF
    evaluated every ``decimate`` samples and interpolated in time (it changes by nT per km)."""
    from magnav_ins.maps.reference import igrf_ned

    anomaly = np.nan_to_num(np.asarray(fmap.value(truth.lat, truth.lon, truth.h), float))
    d = slice(None, None, decimate)
    b_d = igrf_ned(truth.lat[d], truth.lon[d], truth.h[d], DATE)
    b_n = np.column_stack([np.interp(truth.t, truth.t[d], b_d[:, i]) for i in range(3)])
    b_n *= (1.0 + anomaly / np.linalg.norm(b_n, axis=1))[:, None]
    return np.einsum("nji,nj->ni", C_nb_from_q(truth.q_nb), b_n) + rng.normal(0.0, 1.0, b_n.shape)


def simulated_tlog(path: Path):
    from magnav_ins.ins import imu_models
    from magnav_ins.ins.simulate import great_circle, ideal_imu
    from magnav_ins.mavlink.link import AttitudeMessage, ImuMessage, PositionMessage, write_tlog

    fmap = load_map("builtin:osborne-magnetic")
    lat0, lon0 = math.radians(-21.80), math.radians(140.72)
    dlat, dlon = meters_to_latlon(0.0, 40.0 * 90.0, lat0, 0.0)
    truth = great_circle(lat0, lon0, lat0 + float(dlat), lon0 + float(dlon), 400.0, 40.0, 25.0)
    rng = np.random.default_rng(7)
    imu, _ = imu_models.corrupt(ideal_imu(truth), imu_models.get_grade("tactical"), rng)
    mag_b = _magnetometer(fmap, truth, rng)
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


def _take_off_run(lat0: float, lon0: float, rate_hz: float, still_s: float = 10.0, accel_mps2: float = 2.0):
    """At rest heading east for ``still_s`` s, then east at ``accel_mps2`` up to :data:`SPEED_MPS`, level, at 400 m
    (a CSV recording holds no GNSS: the replay starts at rest, levelled from the specific force)."""
    from magnav_ins.core.frames import q_nb_from_euler
    from magnav_ins.core.types import NavTrajectory

    t_acc = SPEED_MPS / accel_mps2
    t = np.arange(0.0, still_s + t_acc + 0.5 / rate_hz, 1.0 / rate_hz)
    ta = np.clip(t - still_s, 0.0, t_acc)
    east = 0.5 * accel_mps2 * ta**2
    dlat, dlon = meters_to_latlon(np.zeros_like(east), east, lat0, 400.0)
    v = np.column_stack([np.zeros_like(t), accel_mps2 * ta, np.zeros_like(t)])
    q = np.tile(np.asarray(q_nb_from_euler(0.0, 0.0, math.pi / 2)).reshape(4), (len(t), 1))
    return NavTrajectory(t, lat0 + dlat, lon0 + dlon, np.full(len(t), 400.0), v, q)


def racetrack_csv(path: Path, rows: int, rate_hz: float, seed: int = 7) -> None:
    """The throughput recording (module docstring) as a replay CSV (``t,gyro_*,accel_*,mag_*``): a take-off run
    (:func:`_take_off_run`), then laps of the racetrack."""
    from magnav_ins.core.types import NavTrajectory
    from magnav_ins.ins import imu_models
    from magnav_ins.ins.simulate import ideal_imu, waypoints

    fmap = load_map("builtin:osborne-magnetic")
    lat0, lon0 = (math.radians(x) for x in TRACK_START)
    run = _take_off_run(lat0, lon0, rate_hz)
    duration = rows / rate_hz
    lap_s = 2.0 * (16000.0 + 8000.0) / SPEED_MPS
    pts = [(float(run.lat[-1]), float(run.lon[-1]), 400.0)]
    for _ in range(int(duration / lap_s) + 2):
        for n, e in TRACK_CORNERS[1:] + TRACK_CORNERS[:1]:
            dlat, dlon = meters_to_latlon(n, e, lat0, 400.0)
            pts.append((lat0 + float(dlat), lon0 + float(dlon), 400.0))
    laps = waypoints(np.array(pts), SPEED_MPS, rate_hz)
    tr = [run, laps]
    cat = {k: np.concatenate([getattr(run, k), getattr(laps, k)[1:]]) for k in ("lat", "lon", "h", "v_n", "q_nb")}
    t = np.concatenate([run.t, laps.t[1:] + run.t[-1]])
    n = min(rows, len(t))
    truth = NavTrajectory(t[:n], *(cat[k][:n] for k in ("lat", "lon", "h", "v_n", "q_nb")))
    del tr, cat
    rng = np.random.default_rng(seed)
    imu, _ = imu_models.corrupt(ideal_imu(truth), imu_models.get_grade("tactical"), rng)
    mag = _magnetometer(fmap, truth, rng, decimate=int(rate_hz))
    with path.open("w") as fh:
        fh.write("t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z,mag_x,mag_y,mag_z\n")
        np.savetxt(fh, np.column_stack([truth.t + T0, imu.gyro_b, imu.accel_b, mag]), delimiter=",",
                   fmt=["%.5f"] + ["%.9e"] * 6 + ["%.2f"] * 3)  # fmt: skip


#: runs the command and writes its own peak resident memory (VmHWM of this process's address space: ru_maxrss of a
#: child keeps the parent's high-water mark across fork + exec, so it would count the bench's own arrays)
_CHILD = """
import json, sys
from magnav_ins.cli import main
rc = main(sys.argv[2:])
hwm = [l for l in open('/proc/self/status') if l.startswith('VmHWM')][0].split()[1]
open(sys.argv[1], 'w').write(json.dumps({'rc': rc, 'vmhwm_kb': int(hwm)}))
sys.exit(rc)
"""


def _replay_process(log: Path, map_path: Path, fusion: str, out: Path, summary: Path) -> dict:
    """One ``magnav-ins replay`` in its own process: its CPU and wall time (os.wait4) and peak memory (VmHWM)."""
    init = f"{TRACK_START[0]},{TRACK_START[1]},400,90"
    mem = summary.with_suffix(".mem.json")
    cmd = [sys.executable, "-c", _CHILD, str(mem), "replay", str(log), "--map", str(map_path), f"--init={init}",
           "--fusion", fusion, "--date", DATE, "--reading-interval", "0.5", "--out", str(out), "--summary-json",
           str(summary), "--quiet"]  # fmt: skip
    w0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _, status, ru = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - w0
    stdout, stderr = proc.stdout.read().decode(), proc.stderr.read().decode()
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"replay {fusion} failed: {stderr[-2000:]}")
    s = json.loads(summary.read_text())
    return {
        "imu_samples": s["imu_samples"],
        "duration_s": round(s["duration_s"], 1),
        "replay_cpu_s": round(s["replay_cpu_s"], 2),
        "samples_per_s": round(s["imu_samples"] / s["replay_cpu_s"]),
        "command_cpu_s": round(ru.ru_utime + ru.ru_stime, 2),
        "command_wall_s": round(wall, 2),
        "peak_rss_mb": round(json.loads(mem.read_text())["vmhwm_kb"] / 1024.0, 1),
        "readings": s["readings"],
        "fix_attempts": s["fix_attempts"],
        "fixes_issued": s["fixes_issued"],
        "fixes_accepted": s["fixes_accepted"],
        "no_fix_reasons": s["no_fix_reasons"],
        "output_rows": len(out.read_text().splitlines()) - 1,
        "stdout_lines": len(stdout.splitlines()),
    }


def throughput(rows: int, rate_hz: float, fusers: list[str]) -> dict:
    from magnav_ins.maps.io import write_map

    with tempfile.TemporaryDirectory() as d:
        log, exact = Path(d) / "racetrack.csv", Path(d) / "osborne-exact.nc"
        t0 = time.perf_counter()
        racetrack_csv(log, rows, rate_hz)
        gen_s = time.perf_counter() - t0
        write_map(load_map("builtin:osborne-magnetic").with_error_layer(0.0, 150.0, "readings drawn from this map"),
                  exact)  # fmt: skip
        out: dict = {"rows": rows, "rate_hz": rate_hz, "csv_mb": round(log.stat().st_size / 2**20, 1),
                     "generate_s": round(gen_s, 1)}  # fmt: skip
        for fusion in fusers:
            out[fusion] = _replay_process(log, exact, fusion, Path(d) / f"{fusion}.csv", Path(d) / f"{fusion}.json")
    return out


def _timed(fn):
    w, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w, time.process_time() - c


def accuracy() -> dict:
    result: dict = {}
    with tempfile.TemporaryDirectory() as d:
        tlog = Path(d) / "sim.tlog"
        truth, shipped = simulated_tlog(tlog)
        rec = read_log(tlog)
        # the readings are drawn from the map (+ 1 nT): the map is exact for them (no error, no level offset)
        exact = shipped.with_error_layer(0.0, 150.0, "readings drawn from this map")
        exact.metadata.update(level_sigma=0.0, level_sigma_source="readings drawn from this map")
        runs = [("ukf", "ukf", exact), ("graph", "graph", exact), ("free_inertial", "free_inertial", exact),
                ("ukf_shipped_error_layer", "ukf", shipped)]  # fmt: skip
        for name, fusion, fmap in runs:
            res, wall, cpu = _timed(
                lambda fusion=fusion, fmap=fmap: replay(
                    rec, fmap, init=INIT, field_model=ScalarAnomalyModel(DATE), reading_interval_s=0.5,
                    output_dt=1.0, fusion=fusion, matcher="mlr",
                )
            )  # fmt: skip
            t = res.t - T0
            err = horizontal_error_m(
                res.trajectory.lat,
                res.trajectory.lon,
                np.interp(t, truth.t, truth.lat),
                np.interp(t, truth.t, truth.lon),
            )
            s = res.summary()
            result[name] = {
                "rms_m": round(float(np.sqrt(np.mean(err**2))), 2),
                "final_m": round(float(err[-1]), 2),
                "rms_last_30s_m": round(float(np.sqrt(np.mean(err[t >= t[-1] - 30] ** 2))), 2),
                "fix_attempts": s["fix_attempts"],
                "fixes_issued": s["fixes_issued"],
                "fixes_accepted": s["fixes_accepted"],
                "no_fix_reasons": s["no_fix_reasons"],
                "cpu_us_per_imu_sample": round(1e6 * cpu / res.imu_samples, 1),
                "wall_s": round(wall, 2),
            }
    return result


def px4() -> dict:
    result: dict = {}
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
        result[name] = {
            "imu_samples": res.imu_samples,
            "duration_s": round(res.duration_s, 1),
            "fix_attempts": s["fix_attempts"],
            "no_fix_reasons": s["no_fix_reasons"],
            "gnss_error_max_m": round(s["gnss_error_m"]["max"], 2) if "gnss_error_m" in s else None,
            "cpu_us_per_imu_sample": round(1e6 * cpu / res.imu_samples, 1),
            "wall_s": round(wall, 2),
        }
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON line")
    ap.add_argument("--rows", type=int, default=1_000_000, help="rows of the throughput recording (default 1e6)")
    ap.add_argument("--rate", type=float, default=400.0, help="its IMU rate, Hz (default 400)")
    ap.add_argument("--fusers", default="free_inertial,ukf", help="fusers timed on it (default free_inertial,ukf)")
    ap.add_argument("--only", choices=["throughput", "accuracy", "px4"], default=None, help="one part only")
    args = ap.parse_args()
    result: dict = {}
    if args.only in (None, "throughput"):
        result["throughput"] = throughput(args.rows, args.rate, args.fusers.split(","))
    if args.only in (None, "accuracy"):
        result["simulated"] = accuracy()
    if args.only in (None, "px4") and SHARED.is_dir():
        result["px4"] = px4()
    print(json.dumps(result) if args.json else json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
