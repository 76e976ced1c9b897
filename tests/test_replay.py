"""``magnav-ins replay``: recordings (tlog, ULog, CSV) through the bridge's online pipeline.

Truth comes from a simulated flight over ``builtin:osborne-magnetic`` (tactical IMU errors, the map's anomaly plus
the IGRF as the magnetometer vector), written as a MAVLink tlog with :func:`link.write_tlog`, as a ULog with the
small writer below (independent of pyulog's), and as a CSV; and from the real PX4 logs in ``../shared/data``.
"""

from __future__ import annotations

import json
import math
import re
import struct
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from magnav_ins.cli import main
from magnav_ins.core.errors import ConfigError, InputError
from magnav_ins.core.frames import C_nb_from_q, euler_from_q_nb, horizontal_error_m, meters_to_latlon
from magnav_ins.core.units import NT_PER_GAUSS
from magnav_ins.mavlink.replay import LogRecording, _reason_key, initial_state, read_log

DATE = "2020-06-01"
T0 = 100.0  #: log clock at the start of the simulated flight, s
RATE_HZ = 25.0
DURATION_S = 90.0
SPEED_MPS = 40.0
LAT0, LON0, H0 = math.radians(-21.80), math.radians(140.72), 400.0  # over the Osborne mine anomaly, heading east
MAP = "builtin:osborne-magnetic"
#: --init 44 m north and 52 m east of the true start, true heading (east)
INIT = "-21.7996,140.7205,400,90"


# ----------------------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """Truth, corrupted tactical IMU, body magnetometer (nT), written as a tlog."""
    from magnav_ins.ins import imu_models
    from magnav_ins.ins.simulate import great_circle, ideal_imu
    from magnav_ins.maps.builtin import load_map
    from magnav_ins.maps.reference import igrf_ned
    from magnav_ins.mavlink.link import AttitudeMessage, ImuMessage, PositionMessage, write_tlog

    d = tmp_path_factory.mktemp("replay")
    fmap = load_map(MAP)
    dlat, dlon = meters_to_latlon(0.0, SPEED_MPS * DURATION_S, LAT0, 0.0)
    truth = great_circle(LAT0, LON0, LAT0 + float(dlat), LON0 + float(dlon), H0, SPEED_MPS, RATE_HZ)
    rng = np.random.default_rng(7)
    imu, _ = imu_models.corrupt(ideal_imu(truth), imu_models.get_grade("tactical"), rng)
    anomaly = np.asarray(fmap.value(truth.lat, truth.lon, truth.h), float)
    b_n = igrf_ned(truth.lat, truth.lon, truth.h, DATE)
    b_n = b_n * (1.0 + anomaly / np.linalg.norm(b_n, axis=1))[:, None]  # |B| = F + anomaly (anomaly along B)
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
    tlog = d / "sim.tlog"
    write_tlog(tlog, msgs)
    return {"dir": d, "truth": truth, "imu": imu, "mag_b": mag_b, "tlog": tlog, "anomaly": anomaly}


def _cli(capsys, *argv) -> tuple[int, str, str]:
    rc = main(["replay", *map(str, argv)])
    out, err = capsys.readouterr()
    return rc, out, err


def _read_traj(path: Path) -> dict[str, np.ndarray]:
    header = path.read_text().splitlines()[0].split(",")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return {name: data[:, i] for i, name in enumerate(header)}


def _truth_error(sim, traj) -> np.ndarray:
    truth = sim["truth"]
    t = traj["t"] - T0
    lat_t, lon_t = np.interp(t, truth.t, truth.lat), np.interp(t, truth.t, truth.lon)
    return horizontal_error_m(np.radians(traj["lat_deg"]), np.radians(traj["lon_deg"]), lat_t, lon_t)


# ------------------------------------------------------------------------------------- a ULog writer for tests
_ULOG_TYPES = {"uint64_t": "Q", "int32_t": "i", "uint8_t": "B", "float": "f"}


def write_ulog(path: Path, topics: dict) -> None:
    """A minimal ULog (file format spec: header, flag bits, formats, subscriptions, data sorted by time).

    ``topics``: name -> (fields [(c type, name, array size)], {field: values (N,) or (N, size)}); ``timestamp``
    (uint64 us) first."""
    out = bytearray(b"ULog\x01\x12\x35" + bytes([1]) + struct.pack("<Q", 0))

    def message(kind: str, payload: bytes) -> None:
        out.extend(struct.pack("<HB", len(payload), ord(kind)) + payload)

    message("B", bytes(40))
    for name, (fields, _) in topics.items():
        message("F", (name + ":" + "".join(f"{t}[{n}] {f};" if n > 1 else f"{t} {f};" for t, f, n in fields)).encode())
    items = []
    for msg_id, (name, (fields, data)) in enumerate(topics.items()):
        message("A", struct.pack("<BH", 0, msg_id) + name.encode())
        fmt = "<H" + "".join(_ULOG_TYPES[t] * n for t, _, n in fields)
        for i in range(len(data["timestamp"])):
            vals: list = []
            for t, f, _n in fields:
                cast = int if _ULOG_TYPES[t] in "QiB" else float
                vals += [cast(x) for x in np.asarray(data[f][i]).reshape(-1)]
            items.append((int(data["timestamp"][i]), msg_id, struct.pack(fmt, msg_id, *vals)))
    for _, _, payload in sorted(items, key=lambda x: (x[0], x[1])):
        message("D", payload)
    path.write_bytes(bytes(out))


def _sensor_combined(t_us, gyro, accel):
    return (
        [("uint64_t", "timestamp", 1), ("float", "gyro_rad", 3), ("float", "accelerometer_m_s2", 3)],
        {"timestamp": t_us, "gyro_rad": gyro, "accelerometer_m_s2": accel},
    )


def _sim_ulog(sim, path: Path, seconds: float) -> None:
    """The simulated flight as a PX4 ULog: sensor_combined, vehicle_magnetometer (gauss), vehicle_gps_position
    (degE7, mm), vehicle_attitude (scalar-first quaternion)."""
    truth, imu = sim["truth"], sim["imu"]
    n = int(seconds * RATE_HZ) + 1
    t_us = np.round((truth.t[:n] + T0) * 1e6).astype(np.int64)
    g = slice(0, n, 5)
    q_wxyz = truth.q_nb[g][:, [3, 0, 1, 2]]
    write_ulog(
        path,
        {
            "sensor_combined": _sensor_combined(t_us, imu.gyro_b[:n], imu.accel_b[:n]),
            "vehicle_magnetometer": (
                [("uint64_t", "timestamp", 1), ("float", "magnetometer_ga", 3)],
                {"timestamp": t_us, "magnetometer_ga": sim["mag_b"][:n] / NT_PER_GAUSS},
            ),
            "vehicle_gps_position": (
                [
                    ("uint64_t", "timestamp", 1),
                    ("uint64_t", "time_utc_usec", 1),
                    ("int32_t", "lat", 1),
                    ("int32_t", "lon", 1),
                    ("int32_t", "alt", 1),
                    ("int32_t", "alt_ellipsoid", 1),
                    ("float", "vel_n_m_s", 1),
                    ("float", "vel_e_m_s", 1),
                    ("float", "vel_d_m_s", 1),
                    ("uint8_t", "fix_type", 1),
                ],
                {
                    "timestamp": t_us[g],
                    "time_utc_usec": np.full(len(t_us[g]), 1591012800 * 10**6),  # 2020-06-01T12:00Z
                    "lat": np.round(np.degrees(truth.lat[g]) * 1e7),
                    "lon": np.round(np.degrees(truth.lon[g]) * 1e7),
                    "alt": np.round(truth.h[g] * 1e3) - 40_000,  # MSL: a 40 m geoid, not used when alt_ellipsoid exists
                    "alt_ellipsoid": np.round(truth.h[g] * 1e3),
                    "vel_n_m_s": truth.v_n[g, 0],
                    "vel_e_m_s": truth.v_n[g, 1],
                    "vel_d_m_s": truth.v_n[g, 2],
                    "fix_type": np.full(len(t_us[g]), 3),
                },
            ),
            "vehicle_attitude": (
                [("uint64_t", "timestamp", 1), ("float", "q", 4)],
                {"timestamp": t_us[g], "q": q_wxyz},
            ),
        },
    )


# ------------------------------------------------------------------------------------------------- tests
def test_tlog_round_trip(sim):
    """write_tlog -> read_log returns the SI samples (float32 precision of HIGHRES_IMU, degE7 of positions)."""
    rec = read_log(sim["tlog"])
    truth, imu = sim["truth"], sim["imu"]
    assert rec.fmt == "tlog" and rec.sources["imu"] == "HIGHRES_IMU"
    np.testing.assert_allclose(rec.imu.t, truth.t + T0, atol=1e-6)
    np.testing.assert_allclose(rec.imu.gyro_b, imu.gyro_b, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(rec.imu.accel_b, imu.accel_b, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(rec.mag_b_nt, sim["mag_b"], rtol=1e-6, atol=0.01)  # ArduPilot's mG x 1000 in float32
    np.testing.assert_allclose(rec.gnss.lat, truth.lat[::5], atol=math.radians(1e-7))
    np.testing.assert_allclose(rec.gnss.v_n, truth.v_n[::5], atol=0.006)
    dq = Rotation.from_quat(rec.attitude.q_nb).inv() * Rotation.from_quat(truth.q_nb[::5])
    assert np.max(dq.magnitude()) < 1e-6


def test_tlog_replay_issues_fixes_and_beats_free_inertial(sim, capsys):
    """Over the map, from a 68 m initial error: fixes are issued and accepted and the fused track is much closer
    to the truth than the same INS unaided (batch strapdown from the same initial state)."""
    from magnav_ins.ins.strapdown import integrate
    from magnav_ins.maps.builtin import load_map
    from magnav_ins.maps.io import write_map

    out, js = sim["dir"] / "traj.csv", sim["dir"] / "summary.json"
    # the emulator draws the readings from the map itself: tell the matcher the map is exact (a zero error layer),
    # else it adds the default map error of a map that does not know its own (map_error.py) and finds no fix here
    exact = sim["dir"] / "exact.nc"
    write_map(load_map(MAP).with_error_layer(0.0, 150.0, "the emulator's readings come from this map"), exact)
    rc, stdout, _ = _cli(
        capsys, sim["tlog"], "--map", exact, f"--init={INIT}", "--date", DATE, "--reading-interval", 0.5,
        "--output-interval", 1.0, "--out", out, "--summary-json", js,
    )  # fmt: skip
    assert rc == 0
    s = json.loads(js.read_text())
    # (honest fixes: sections of this 90 s flight that are ambiguous or reach the window edge give none)
    assert s["fixes_issued"] >= 2 and s["fixes_accepted"] >= 2, json.dumps(s)[:3000]
    assert s["init"] == "--init" and s["map_covers_start"] is True
    traj = _read_traj(out)
    assert list(traj) == ["t", "lat_deg", "lon_deg", "h_m", "vn", "ve", "vd", "roll_deg", "pitch_deg", "yaw_deg",
                          "sigma_n_m", "sigma_e_m", "hpl_m"]  # fmt: skip
    err = _truth_error(sim, traj)
    assert err[0] == pytest.approx(68.0, abs=1.0)  # the --init offset
    # the summary's error against the log's GNSS is the error against the truth (GNSS = truth to 1e-7 deg)
    assert s["gnss_error_m"]["rms"] == pytest.approx(float(np.sqrt(np.mean(err**2))), abs=0.05)
    rec = read_log(sim["tlog"])
    nav0, k0, _ = initial_state(rec, (math.radians(-21.7996), math.radians(140.7205), 400.0, math.radians(90.0)))
    free = integrate(nav0, rec.imu.slice(k0, len(rec.imu)), altitude_hold=400.0)
    err_free = horizontal_error_m(
        np.interp(traj["t"], free.t, free.lat), np.interp(traj["t"], free.t, free.lon),
        np.interp(traj["t"] - T0, sim["truth"].t, sim["truth"].lat),
        np.interp(traj["t"] - T0, sim["truth"].t, sim["truth"].lon),
    )  # fmt: skip
    rms, rms_free = float(np.sqrt(np.mean(err**2))), float(np.sqrt(np.mean(err_free**2)))
    assert rms < 0.7 * rms_free, (rms, rms_free)
    assert np.mean(err[-30:]) < 0.6 * np.mean(err_free[-30:])  # 2-3 honest fixes in 90 s (was 0.5 with 5 or more)
    assert "horizontal error vs the log's GNSS" in stdout and "fixes:" in stdout


def test_csv_free_inertial_equals_batch_strapdown(sim, tmp_path, capsys):
    """The online path (pipeline + free-inertial fuser, sample by sample) reproduces the batch mechanisation."""
    from magnav_ins.ins.strapdown import integrate

    n = int(20 * RATE_HZ) + 1
    rec = read_log(sim["tlog"])
    csv = tmp_path / "rec.csv"
    cols = np.column_stack([rec.imu.t[:n], rec.imu.gyro_b[:n], rec.imu.accel_b[:n], rec.mag_b_nt[:n]])
    np.savetxt(csv, cols, delimiter=",", fmt="%.17g", comments="",
               header="t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z,mag_x,mag_y,mag_z")  # fmt: skip
    out = tmp_path / "traj.csv"
    rc, stdout, _ = _cli(capsys, csv, "--map", MAP, f"--init={INIT}", "--date", DATE, "--fusion", "free_inertial",
                         "--output-interval", 1.0, "--out", out)  # fmt: skip
    assert rc == 0 and "horizontal error" not in stdout  # a CSV holds no GNSS
    traj = _read_traj(out)
    rec_csv = read_log(csv)
    init = (math.radians(-21.7996), math.radians(140.7205), 400.0, math.radians(90.0))
    nav0, _, _ = initial_state(rec_csv, init)
    assert np.allclose(nav0.v_n, 0.0)  # no GNSS, no attitude: at rest, levelled from the specific force
    free = integrate(nav0, rec_csv.imu, altitude_hold=400.0)
    d = horizontal_error_m(np.radians(traj["lat_deg"]), np.radians(traj["lon_deg"]),
                           np.interp(traj["t"], free.t, free.lat), np.interp(traj["t"], free.t, free.lon))  # fmt: skip
    assert np.max(d) < 0.01  # same mechanisation, same samples (the output times are sample times)
    assert np.all(np.diff(traj["sigma_n_m"]) >= -1e-9)  # unaided: the covariance only grows


def test_off_map_replays_with_no_fix_reasons(sim, tmp_path, capsys):
    """Far from any map the INS still runs; every fix attempt is a "no fix" saying off the map."""
    js = tmp_path / "s.json"
    rc, stdout, _ = _cli(capsys, sim["tlog"], "--map", MAP, "--init=63.4,10.4,100,90", "--date", DATE,
                         "--duration", 12, "--reading-interval", 0.2, "--summary-json", js)  # fmt: skip
    assert rc == 0
    s = json.loads(js.read_text())
    assert s["fix_attempts"] >= 2 and s["fixes_issued"] == 0
    assert list(s["no_fix_reasons"]) == ["off the map"]
    assert s["map_covers_start"] is False and "does not cover the start position" in stdout


def test_synthetic_ulog_init_from_log(sim, tmp_path, capsys):
    """A ULog's scalar-first quaternion, degE7/mm GNSS (alt_ellipsoid preferred) and gauss magnetometer arrive
    as our SI state: the first output row is the truth."""
    ulg = tmp_path / "sim.ulg"
    _sim_ulog(sim, ulg, 8.0)
    out = tmp_path / "traj.csv"
    rc, stdout, _ = _cli(capsys, ulg, "--map", MAP, "--out", out, "--output-interval", 1.0)
    assert rc == 0
    assert "IGRF date 2020-06-01 (GNSS time in the log)" in stdout
    assert "init from log (vehicle_gps_position + vehicle_attitude)" in stdout
    traj = _read_traj(out)
    truth = sim["truth"]
    roll, pitch, yaw = (math.degrees(float(x)) for x in euler_from_q_nb(truth.q_nb[0]))
    assert traj["t"][0] == pytest.approx(T0)
    assert (traj["roll_deg"][0], traj["pitch_deg"][0], traj["yaw_deg"][0]) == pytest.approx(
        (roll, pitch, yaw), abs=1e-4
    )
    assert traj["h_m"][0] == pytest.approx(H0, abs=1e-3)
    assert traj["lat_deg"][0] == pytest.approx(math.degrees(LAT0), abs=2e-7)
    assert traj["ve"][0] == pytest.approx(SPEED_MPS, abs=1e-4)
    rec = read_log(ulg)
    np.testing.assert_allclose(rec.mag_b_nt, sim["mag_b"][: len(rec.mag_t)], rtol=1e-6, atol=0.01)


def test_reason_key_groups_numbers():
    assert _reason_key("NIS 28.1 above gate 18.4 (2 dof)") == _reason_key("NIS 785.3 above gate 18.4 (2 dof)")
    assert _reason_key("off the map: no map values in the search window") == "off the map"


# -------------------------------------------------------------------------------------------- bad input
def _assert_fails(capsys, tmp_path, log, *extra, match: str) -> str:
    out = tmp_path / "never.csv"
    rc, _, err = _cli(capsys, log, "--map", MAP, "--out", out, *extra)
    assert rc == 2, err
    assert err.startswith("magnav-ins: error:") and len(err.strip().splitlines()) == 1
    assert match in err, err
    assert not out.exists()
    return err


def test_not_a_log(tmp_path, capsys):
    p = tmp_path / "notes.bin"
    p.write_bytes(b"\x00\x01hello, this is not a flight log\n")
    _assert_fails(capsys, tmp_path, p, match="not a recording")
    junk = tmp_path / "junk.tlog"
    junk.write_bytes(np.random.default_rng(3).integers(0, 256, 4000, dtype=np.uint8).tobytes())
    _assert_fails(capsys, tmp_path, junk, match="no IMU messages")
    _assert_fails(capsys, tmp_path, tmp_path / "missing.ulg", match="no such log file")


def test_ulog_without_sensor_combined_or_init(tmp_path, capsys):
    t = np.arange(50) * 4000 + 10**6
    att = ([("uint64_t", "timestamp", 1), ("float", "q", 4)], {"timestamp": t, "q": np.tile([1.0, 0, 0, 0], (50, 1))})
    p = tmp_path / "att_only.ulg"
    write_ulog(p, {"vehicle_attitude": att})
    err = _assert_fails(capsys, tmp_path, p, match="no topic 'sensor_combined'")
    assert "att_only.ulg" in err
    p2 = tmp_path / "imu_only.ulg"
    write_ulog(p2, {"sensor_combined": _sensor_combined(t, np.zeros((50, 3)), np.tile([0, 0, -9.8], (50, 1)))})
    err = _assert_fails(capsys, tmp_path, p2, match="add --init LAT_DEG,LON_DEG,ALT_M,YAW_DEG")
    assert "vehicle_gps_position" in err and "vehicle_attitude" in err


def test_nan_and_backward_time_are_named(tmp_path, capsys):
    t = np.arange(50) * 4000 + 10**6
    gyro = np.zeros((50, 3))
    gyro[6, 1] = np.nan
    p = tmp_path / "nan.ulg"
    write_ulog(p, {"sensor_combined": _sensor_combined(t, gyro, np.tile([0, 0, -9.8], (50, 1)))})
    _assert_fails(capsys, tmp_path, p, "--init=1,2,3,4", match="topic 'sensor_combined' row 7")
    header = "t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n"
    back = tmp_path / "back.csv"
    back.write_text(header + "0.00,0,0,0,0,0,-9.8\n0.01,0,0,0,0,0,-9.8\n0.005,0,0,0,0,0,-9.8\n")
    err = _assert_fails(capsys, tmp_path, back, "--init=1,2,3,4", match="row 3")
    assert "back.csv" in err and "backwards" in err
    nan = tmp_path / "nan.csv"
    nan.write_text(header + "0.00,0,0,0,0,0,-9.8\n0.01,0,0,0,0,0,-9.8\n0.02,0,0,0,0,0,-9.8\n0.03,0,nan,0,0,0,-9.8\n")
    _assert_fails(capsys, tmp_path, nan, "--init=1,2,3,4", match="row 4 column 'gyro_y'")


def test_tlog_time_going_back(tmp_path, capsys):
    from magnav_ins.mavlink.link import ImuMessage, write_tlog

    f = np.array([0.0, 0.0, -9.8])
    times = [1.00, 1.01, 1.02, 1.015, 1.03]
    p = tmp_path / "back.tlog"
    write_tlog(p, [ImuMessage(t, np.zeros(3), f, None, "HIGHRES_IMU", 1, 1) for t in times])
    _assert_fails(capsys, tmp_path, p, "--init=1,2,3,4", match="message HIGHRES_IMU row 4")


def test_tlog_duplicates_dropped_as_the_bridge_does(tmp_path, capsys):
    """A message logged twice is dropped (the bridge drops duplicate timestamps); the same time with different
    values is an error."""
    from magnav_ins.mavlink.link import ImuMessage, write_tlog

    f = np.array([0.0, 0.0, -9.8])
    msgs = [ImuMessage(1.0 + 0.01 * k, np.zeros(3), f, None, "HIGHRES_IMU", 1, 1) for k in range(5)]
    p = tmp_path / "dup.tlog"
    write_tlog(p, [*msgs[:3], msgs[2], *msgs[3:]])
    rec = read_log(p)
    assert len(rec.imu) == 5 and rec.notes == ("1 duplicated HIGHRES_IMU messages dropped (as the bridge drops them)",)
    clash = ImuMessage(1.02, np.ones(3), f, None, "HIGHRES_IMU", 1, 1)
    write_tlog(p, [*msgs[:3], clash, *msgs[3:]])
    _assert_fails(capsys, tmp_path, p, "--init=1,2,3,4", match="message HIGHRES_IMU row 4")


def test_bad_options(sim, tmp_path, capsys):
    _assert_fails(capsys, tmp_path, sim["tlog"], "--init=1,2,3", match="--init")
    _assert_fails(capsys, tmp_path, sim["tlog"], "--date", "June", match="--date")
    bare = LogRecording(Path("bare.csv"), "csv", read_log(sim["tlog"]).imu, np.zeros(0), np.zeros((0, 3)))
    with pytest.raises(ConfigError, match="add --init"):
        initial_state(bare)


# ------------------------------------------------------------------------------------------- real PX4 logs
@pytest.mark.shared_data
def test_px4_small_log_replays_off_map(shared_data, tmp_path, capsys):
    """sample_log_small.ulg: stationary in Norway (no shipped map there). Initialised from its GPS and attitude;
    every fix attempt is "section too short" (the vehicle does not move: no window is matched, on or off the map);
    the replay says the map does not cover the log; the INS stays within metres of the GPS over the 6.5 s."""
    from magnav_ins.mavlink.ulog import read_ulog_topic

    log = shared_data / "px4_ulog" / "sample_log_small.ulg"
    out, js = tmp_path / "traj.csv", tmp_path / "s.json"
    rc, stdout, _ = _cli(capsys, log, "--map", MAP, "--out", out, "--summary-json", js)
    assert rc == 0
    s = json.loads(js.read_text())
    assert s["fix_attempts"] >= 1 and s["fixes_issued"] == 0 and list(s["no_fix_reasons"]) == ["section too short"]
    assert s["duration_s"] > 6.0 and s["readings"] > 20
    assert s["gnss_error_m"]["max"] < 5.0
    assert "section too short" in stdout and "does not cover" in stdout
    traj = _read_traj(out)
    gps = read_ulog_topic(log, "vehicle_gps_position", ["lat", "lon"])
    assert traj["lat_deg"][0] == pytest.approx(np.interp(traj["t"][0], gps["t"], gps["lat"]) / 1e7, abs=1e-7)
    att = read_ulog_topic(log, "vehicle_attitude", [f"q[{i}]" for i in range(4)])
    k = int(np.argmin(abs(att["t"] - traj["t"][0])))
    q = np.array([att[f"q[{i}]"][k] for i in range(4)])
    ypr = Rotation.from_quat(q, scalar_first=True).as_euler("ZYX", degrees=True)
    assert (traj["yaw_deg"][0], traj["pitch_deg"][0], traj["roll_deg"][0]) == pytest.approx(tuple(ypr), abs=1e-3)


@pytest.mark.shared_data
def test_px4_hand_rotations_follow_autopilot_attitude(shared_data, capsys):
    """sample.ulg (no GPS, hand rotations): needs --init; with it, the INS attitude from the raw gyros follows
    PX4's own estimate through a 16 deg rotation to within 3 deg over 6 s (a frame or quaternion-order mistake would be
    off by tens of degrees)."""
    from magnav_ins.mavlink.replay import replay
    from magnav_ins.mavlink.ulog import read_ulog_topic

    log = shared_data / "px4_ulog" / "sample.ulg"
    rc, _, err = _cli(capsys, log, "--map", MAP)
    assert rc == 2 and "no GNSS position (vehicle_gps_position)" in err and "add --init" in err
    rec = read_log(log)
    assert rec.sources["mag"] == "sensor_combined" and 0.2e5 < np.median(np.linalg.norm(rec.mag_b_nt, axis=1)) < 0.7e5
    att = read_ulog_topic(log, "vehicle_attitude", [f"q[{i}]" for i in range(4)])
    R_px4 = Rotation.from_quat(np.column_stack([att[f"q[{i}]"] for i in range(4)]), scalar_first=True)
    yaw0 = float(R_px4[0].as_euler("ZYX")[0])
    res = replay(rec, None, init=(math.radians(47.4), math.radians(8.5), 500.0, yaw0), output_dt=0.25,
                 duration_s=6.0, fusion="free_inertial", matcher="none")  # fmt: skip
    ang_ours, ang_px4 = [], []
    for t, nav in zip(res.t, res.navs, strict=True):
        k = int(np.argmin(abs(att["t"] - t)))
        ang_ours.append((R_px4[k].inv() * Rotation.from_quat(nav.q_nb)).magnitude())
        ang_px4.append((R_px4[0].inv() * R_px4[k]).magnitude())
    assert math.degrees(max(ang_px4)) > 10.0
    assert math.degrees(max(ang_ours)) < 3.0  # raw MEMS gyro bias (~0.2 deg/s, PX4 estimates it, we do not)
    assert res.imu_samples > 1000 and not res.fixes


# ------------------------------------------------------------------------------------------- barometer
def _climbing_tlog(path: Path, *, pressure: bool) -> tuple:
    """70 s at 20 m/s over the Osborne map, +100 m between 5 s and 65 s, as a tlog (HIGHRES_IMU 50 Hz, ATTITUDE and
    GLOBAL_POSITION_INT 5 Hz, SCALED_PRESSURE 25 Hz from the ISA pressure of the truth height + 2 Pa noise)."""
    from magnav_ins.core.atmosphere import isa_pressure_pa
    from magnav_ins.maps.builtin import load_map
    from magnav_ins.mavlink.emulator import flight_over_map
    from magnav_ins.mavlink.link import AttitudeMessage, ImuMessage, PositionMessage, PressureMessage, write_tlog

    fmap = load_map(MAP)
    f = flight_over_map(fmap, start=(LAT0, LON0), heading=math.radians(90), speed_mps=20.0, duration_s=70.0,
                        rate_hz=50.0, altitude_m=H0, seed=4, date=DATE, climb_m=100.0, climb_window_s=(5.0, 65.0))  # fmt: skip
    tr = f.truth
    roll, pitch, yaw = euler_from_q_nb(tr.q_nb)
    p = np.asarray(isa_pressure_pa(tr.h)) + np.random.default_rng(2).normal(0.0, 2.0, len(tr))
    msgs: list = []
    for k in range(len(tr)):
        t = float(tr.t[k]) + T0
        msgs.append(ImuMessage(t, f.imu.gyro_b[k], f.imu.accel_b[k], f.mag_b_nt[k], "HIGHRES_IMU", 1, 1))
        if k % 10 == 0:
            msgs.append(AttitudeMessage(t, float(roll[k]), float(pitch[k]), float(yaw[k]), 1, 1))
            msgs.append(PositionMessage(t, float(tr.lat[k]), float(tr.lon[k]), float(tr.h[k]), tr.v_n[k], 1, 1))
        if pressure and k % 2 == 0:
            msgs.append(PressureMessage(t, float(p[k]), 15.0, 1, 1))
    write_tlog(path, msgs)
    return fmap, f


def test_tlog_replay_height_follows_the_barometer_in_a_climb(tmp_path):
    """The same recording replayed with and without its SCALED_PRESSURE: with it the height tracks the 100 m climb
    within 1 m (measured max 0.2 m); without it (and with ``baro=False``) it stays at the start height."""
    from magnav_ins.mavlink.bridge import ScalarAnomalyModel
    from magnav_ins.mavlink.replay import replay

    fmap, f = _climbing_tlog(tmp_path / "climb.tlog", pressure=True)
    rec = read_log(tmp_path / "climb.tlog")
    assert rec.sources["baro"] == "SCALED_PRESSURE" and len(rec.baro_t) == (len(f.truth) + 1) // 2
    model = ScalarAnomalyModel(DATE)
    errs = {}
    for baro in (True, False):
        res = replay(rec, fmap, field_model=model, output_dt=0.5, baro=baro, matcher="none")
        h = np.array([n.h for n in res.navs])
        errs[baro] = h - np.interp(res.t - T0, f.truth.t, f.truth.h)
        assert res.summary()["baro"]["used"] is baro
    assert np.abs(errs[True]).max() < 1.0, np.abs(errs[True]).max()
    assert errs[False][-1] == pytest.approx(-100.0, abs=0.5)
    s = replay(rec, fmap, field_model=model, output_dt=1.0, duration_s=5.0, matcher="none").summary()["baro"]
    assert s["samples"] > 100 and s["rejected"] == 0 and s["state"] == "active"


def test_csv_and_ulog_pressure_columns(sim, tmp_path):
    """CSV ``pressure_pa`` (blank = no sample; text -> error naming row and column) and ULog ``sensor_baro`` in hPa
    (PX4 before v1.14) read as Pa."""
    from magnav_ins.core.errors import InputError

    imu = sim["imu"]
    n = 50
    rows = ["t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z,pressure_pa"]
    for k in range(n):
        p = "" if k % 2 else f"{96000.0 + k:.1f}"
        rows.append(",".join(f"{x:.9g}" for x in (imu.t[k], *imu.gyro_b[k], *imu.accel_b[k])) + "," + p)
    (tmp_path / "a.csv").write_text("\n".join(rows) + "\n")
    rec = read_log(tmp_path / "a.csv")
    assert rec.sources["baro"] == "CSV" and len(rec.baro_t) == n // 2
    np.testing.assert_allclose(rec.baro_pa, 96000.0 + np.arange(0, n, 2))
    np.testing.assert_allclose(rec.baro_t, imu.t[0:n:2])
    rows[7] = rows[7].rsplit(",", 1)[0] + ",high"
    (tmp_path / "b.csv").write_text("\n".join(rows) + "\n")
    with pytest.raises(InputError, match="row 7 column 'pressure_pa': not a number"):
        read_log(tmp_path / "b.csv")
    t_us = np.round((imu.t[:n] + T0) * 1e6).astype(np.int64)
    write_ulog(
        tmp_path / "b.ulg",
        {
            "sensor_combined": _sensor_combined(t_us, imu.gyro_b[:n], imu.accel_b[:n]),
            "sensor_baro": (
                [("uint64_t", "timestamp", 1), ("float", "pressure", 1)],
                {"timestamp": t_us[::5], "pressure": np.full(len(t_us[::5]), 1002.5)},
            ),
        },
    )
    rec = read_log(tmp_path / "b.ulg")
    assert rec.sources["baro"] == "sensor_baro"
    np.testing.assert_allclose(rec.baro_pa, 100250.0, atol=0.01)


@pytest.mark.shared_data
def test_px4_small_log_height_follows_its_barometer(shared_data):
    """sample_log_small.ulg (stationary, vehicle_air_data at 18 Hz): our ISA pressure altitude of PX4's logged
    pressure equals PX4's own ``baro_alt_meter`` (a peer implementation) to 2 cm; the replayed height stays at the
    GNSS start height plus the logged baro-altitude change, within 0.3 m (the log's baro altitude noise is 0.11 m
    per sample), and moves with it."""
    from magnav_ins.core.atmosphere import pressure_altitude_m
    from magnav_ins.mavlink.replay import replay
    from magnav_ins.mavlink.ulog import read_ulog_topic

    log = shared_data / "px4_ulog" / "sample_log_small.ulg"
    air = read_ulog_topic(log, "vehicle_air_data", ["baro_alt_meter", "baro_pressure_pa"])
    np.testing.assert_allclose(pressure_altitude_m(air["baro_pressure_pa"]), air["baro_alt_meter"], atol=0.02)
    rec = read_log(log)
    assert rec.sources["baro"] == "vehicle_air_data" and len(rec.baro_t) == len(air["t"])
    res = replay(rec, None, fusion="free_inertial", matcher="none", output_dt=0.1)
    assert res.baro is not None and res.baro["used"] and res.baro["samples"] == len(air["t"])
    h = np.array([n.h for n in res.navs])

    def baro_1s(t: float) -> float:  # the logged baro altitude averaged over 1 s around t
        near = np.abs(air["t"] - t) <= 0.5
        return float(air["baro_alt_meter"][near].mean())

    expected = h[0] + np.array([baro_1s(t) for t in res.t]) - baro_1s(res.t[0])
    assert np.abs(h - expected).max() < 0.3
    # the vehicle sits still, so "follows" can only mean the height moves with the baro noise (0.15 m peak to peak
    # after 1 s averaging): measured correlation 0.68; a held height would have none
    assert np.corrcoef(h[5:], expected[5:])[0, 1] > 0.5
    assert h[0] == pytest.approx(float(np.interp(res.t[0], rec.gnss.t, rec.gnss.h)))


# ------------------------------------------------------------------------------------------------ IMU gaps
GAP_S = 3600.0  #: a one-hour jump in the log's clock
GAP_AT_S = 45.0  #: ... after this many seconds of the simulated flight


def _gapped_csv(sim, path: Path) -> int:
    """The simulated flight as a CSV whose clock jumps by GAP_S after GAP_AT_S (the samples themselves continue:
    the vehicle did not move during the "gap"); returns the 0-based index of the first sample after the jump."""
    truth, imu = sim["truth"], sim["imu"]
    k_gap = int(GAP_AT_S * RATE_HZ) + 1
    t = truth.t + T0
    t = np.where(np.arange(len(t)) >= k_gap, t + GAP_S, t)
    cols = np.column_stack([t, imu.gyro_b, imu.accel_b, sim["mag_b"]])
    np.savetxt(path, cols, delimiter=",", fmt="%.17g", comments="",
               header="t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z,mag_x,mag_y,mag_z")  # fmt: skip
    return k_gap


def _gapped_tlog(sim, path: Path) -> int:
    """The simulated tlog (IMU, attitude, GNSS) with the clock jump of :func:`_gapped_csv`."""
    from magnav_ins.mavlink.link import AttitudeMessage, ImuMessage, PositionMessage, write_tlog

    truth, imu = sim["truth"], sim["imu"]
    k_gap = int(GAP_AT_S * RATE_HZ) + 1
    roll, pitch, yaw = euler_from_q_nb(truth.q_nb)
    msgs: list = []
    for k in range(len(truth)):
        t = float(truth.t[k]) + T0 + (GAP_S if k >= k_gap else 0.0)
        msgs.append(ImuMessage(t, imu.gyro_b[k], imu.accel_b[k], sim["mag_b"][k], "HIGHRES_IMU", 1, 1))
        if k % 5 == 0:
            msgs.append(AttitudeMessage(t, float(roll[k]), float(pitch[k]), float(yaw[k]), 1, 1))
            msgs.append(
                PositionMessage(t, float(truth.lat[k]), float(truth.lon[k]), float(truth.h[k]), truth.v_n[k], 1, 1)
            )
    write_tlog(path, msgs)
    return k_gap


def test_an_hour_gap_restarts_the_ins_instead_of_integrating_across(sim, tmp_path, capsys):
    """Item 7 of issue 18: a 1 h jump in ``t`` was integrated across (the vehicle moved ~7,800 km, exit 0). Now, as
    the bridge: the INS restarts at the sample after the gap from its last estimate, the position sigma grown by
    speed x gap, the summary says so (row and times); the track is continuous, and on a tlog (with GNSS) its error
    against the truth (the samples continue where they stopped) stays that of the flight without the jump."""
    for kind in ("csv", "tlog"):
        log = tmp_path / f"gap.{kind}"
        k_gap = _gapped_csv(sim, log) if kind == "csv" else _gapped_tlog(sim, log)
        out, js = tmp_path / f"traj_{kind}.csv", tmp_path / f"s_{kind}.json"
        rc, stdout, err = _cli(capsys, log, "--map", MAP, f"--init={INIT}", "--date", DATE, "--fusion",
                               "free_inertial", "--output-interval", 1.0, "--out", out, "--summary-json", js)  # fmt: skip
        assert rc == 0, err
        g = json.loads(js.read_text())["imu_gaps"]
        assert g["count"] == 1 and g["longest"]["row"] == k_gap + 1
        t_before, t_after = T0 + sim["truth"].t[k_gap - 1], T0 + sim["truth"].t[k_gap] + GAP_S
        assert g["longest"]["t_before"] == pytest.approx(t_before, abs=1e-5)
        assert g["longest"]["t_after"] == pytest.approx(t_after, abs=1e-5)
        assert f"row {k_gap + 1}" in stdout and f"t={t_before:.3f} -> {t_after:.3f} s" in stdout
        assert "never integrated across" in stdout and "INS restarted" in stdout
        traj = _read_traj(out)
        step = horizontal_error_m(np.radians(traj["lat_deg"][1:]), np.radians(traj["lon_deg"][1:]),
                                  np.radians(traj["lat_deg"][:-1]), np.radians(traj["lon_deg"][:-1]))  # fmt: skip
        assert step.max() < 2.0 * SPEED_MPS * 1.0 + 5.0  # no jump: at most the distance flown in an output interval
        after = traj["t"] >= t_after - 1e-6
        i = int(np.argmax(after))
        speed = math.hypot(traj["vn"][i - 1], traj["ve"][i - 1])
        assert traj["sigma_n_m"][i] >= traj["sigma_n_m"][i - 1] + 0.99 * speed * GAP_S  # grown by speed x gap
        assert traj["t"][i] == pytest.approx(t_after, abs=1e-5)
        if kind == "tlog":  # the INS knew its velocity (GNSS): 40 m/s x 1 h of sigma, and it stayed on the truth
            assert speed == pytest.approx(SPEED_MPS, rel=0.02)
            t_truth = np.where(after, traj["t"] - GAP_S, traj["t"]) - T0
            lat_t = np.interp(t_truth, sim["truth"].t, sim["truth"].lat)
            lon_t = np.interp(t_truth, sim["truth"].t, sim["truth"].lon)
            e = horizontal_error_m(np.radians(traj["lat_deg"]), np.radians(traj["lon_deg"]), lat_t, lon_t)
            assert e.max() < 500.0, e.max()  # tactical INS, 90 s, 68 m start error (integrated across: ~1.4e5 m)


def test_gap_refused_with_on_gap_stop_and_in_tlog_and_ulog(sim, tmp_path, capsys):
    """``--on-gap stop`` refuses the log before replaying it (one line naming the row and the times, exit 2, no
    output); a tlog and a ULog with the same jump restart like the CSV (the check is on the IMU stream)."""
    from magnav_ins.mavlink.link import ImuMessage, write_tlog
    from magnav_ins.mavlink.replay import replay

    csv = tmp_path / "gap.csv"
    k_gap = _gapped_csv(sim, csv)
    err = _assert_fails(
        capsys, tmp_path, csv, f"--init={INIT}", "--on-gap", "stop", match=f"row {k_gap + 1}: IMU gap of 3600.04 s"
    )
    assert "longer than --max-gap 0.5 s" in err and "--on-gap restart" in err
    _assert_fails(capsys, tmp_path, csv, f"--init={INIT}", "--max-gap", "-1", match="--max-gap")
    from magnav_ins.commands.replay import MAX_GAP_S as cli_default
    from magnav_ins.mavlink.bridge import BridgeConfig
    from magnav_ins.mavlink.online import MAX_GAP_S

    assert cli_default == MAX_GAP_S == BridgeConfig.max_gap_s  # the replay bridges what the bridge bridges
    truth, imu = sim["truth"], sim["imu"]
    t = truth.t + T0 + np.where(np.arange(len(truth)) >= k_gap, GAP_S, 0.0)
    tlog = tmp_path / "gap.tlog"
    write_tlog(tlog, [ImuMessage(float(t[k]), imu.gyro_b[k], imu.accel_b[k], sim["mag_b"][k], "HIGHRES_IMU", 1, 1)
                      for k in range(len(t))])  # fmt: skip
    ulg = tmp_path / "gap.ulg"
    write_ulog(ulg, {"sensor_combined": _sensor_combined(np.round(t * 1e6).astype(np.int64), imu.gyro_b, imu.accel_b)})
    init = (math.radians(-21.7996), math.radians(140.7205), 400.0, math.radians(90.0))
    for path in (tlog, ulg):
        rec = read_log(path)
        res = replay(rec, None, init=init, fusion="free_inertial", matcher="none", output_dt=1.0)
        assert len(res.gaps) == 1 and res.gaps[0]["row"] == k_gap + 1, path
        assert res.gaps[0]["gap_s"] == pytest.approx(GAP_S + 1.0 / RATE_HZ, abs=1e-3)
        assert res.summary()["imu_gaps"]["count"] == 1
        assert np.max(np.abs(np.diff(res.trajectory.lat))) < 1e-4  # no 7,800 km step (1e-4 rad = 640 m)
        with pytest.raises(InputError, match=f"row {k_gap + 1}: IMU gap"):
            replay(rec, None, init=init, fusion="free_inertial", matcher="none", on_gap="stop")
        # a short gap (two samples missing, 0.12 s) is bridged: integrated, no restart
        short = read_log(path)
        res = replay(short, None, init=init, fusion="free_inertial", matcher="none", duration_s=40.0)
        assert res.gaps == ()


def test_batched_replay_equals_sample_by_sample(sim):
    """The replay feeds runs of samples between events to the pipeline in one call; the result is the same as the
    bridge's way, sample by sample (every output bit for bit), for the UKF with fixes and for the free INS."""
    from magnav_ins.maps.builtin import load_map
    from magnav_ins.mavlink.bridge import ScalarAnomalyModel
    from magnav_ins.mavlink.replay import make_online_pipeline, replay

    rec = read_log(sim["tlog"])
    fmap = load_map(MAP).with_error_layer(0.0, 150.0, "the readings come from this map")  # fixes get accepted
    init = (math.radians(-21.7996), math.radians(140.7205), 400.0, math.radians(90.0))

    class OneByOne:
        """The pipeline with its batch input replaced by sample-by-sample push_imu (the bridge's feed)."""

        can_push_outputs = False  # not the free-inertial path in one call either

        def __init__(self, pipe) -> None:  # noqa: ANN001
            self.p = pipe

        def __getattr__(self, name: str):  # noqa: ANN204
            return getattr(self.p, name)

        def push_imu_batch(self, t, w, f, *, altitude_hold=None, attitudes=False):  # noqa: ANN001, ANN202, ARG002
            for k in range(len(t)):
                self.p.push_imu(float(t[k]), w[k], f[k])

    for fusion in ("ukf", "free_inertial"):
        kw = {"fusion": fusion, "matcher": "mlr", "attitude_sigma_rad": (0.01, 0.01, 0.05)}
        runs = []
        for wrap in (False, True):

            def factory(nav, sigma, wrap=wrap, kw=kw):  # noqa: ANN001, ANN202
                p = make_online_pipeline(nav, sigma, fmap, **kw)
                return OneByOne(p) if wrap else p

            runs.append(replay(rec, fmap, init=init, field_model=ScalarAnomalyModel(DATE), reading_interval_s=0.5,
                               output_dt=1.0, pipeline_factory=factory))  # fmt: skip
        a, b = runs
        assert len(a.t) == len(b.t) > 80
        for x, y in ((a.trajectory.lat, b.trajectory.lat), (a.trajectory.v_n, b.trajectory.v_n),
                     (a.trajectory.q_nb, b.trajectory.q_nb), (a.sigma_ne, b.sigma_ne), (a.hpl_m, b.hpl_m)):  # fmt: skip
            np.testing.assert_array_equal(x, y)
        assert [f.available for f in a.fixes] == [f.available for f in b.fixes]
        if fusion == "ukf":
            assert sum(i.accepted for i in a.innovations) >= 1


@pytest.mark.parametrize(("output_dt", "chunk"), [(0.2, None), (2.5, 37)])
def test_free_inertial_fast_path_equals_sample_by_sample_across_a_gap(sim, tmp_path, monkeypatch, output_dt, chunk):
    """The free-inertial replay mechanises the samples between two gaps in compiled chunks with the output samples
    marked (:meth:`.online.OnlinePipeline.push_imu_outputs`); the sample-by-sample feed of the bridge (``push_imu``
    and ``estimate`` at each output) gives the same trajectory, sigmas, protection levels and summary, across a
    2 s gap that restarts the INS (``--max-gap 0.5``). Tolerance 1e-12 relative (the compiled covariance product
    may sum in another order than numpy's BLAS; measured: bit for bit). ``output_dt`` 2.5 s puts covariance steps
    (every 1 s) between outputs; ``chunk`` 37 splits the runs between outputs and gaps into many calls."""
    from magnav_ins.mavlink import replay as replay_mod
    from magnav_ins.mavlink.bridge import ScalarAnomalyModel
    from magnav_ins.mavlink.replay import make_online_pipeline, replay

    truth, imu = sim["truth"], sim["imu"]
    k_gap = int(30.0 * RATE_HZ) + 1
    t = truth.t + T0 + np.where(np.arange(len(truth)) >= k_gap, 2.0, 0.0)
    t = t + np.where(np.arange(len(t)) % 7 == 3, 0.004, 0.0)  # uneven sample intervals
    log = tmp_path / "gap2s.csv"
    np.savetxt(log, np.column_stack([t, imu.gyro_b, imu.accel_b, sim["mag_b"]]), delimiter=",", fmt="%.17g",
               comments="", header="t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z,mag_x,mag_y,mag_z")  # fmt: skip
    rec = read_log(log)
    init = (math.radians(-21.7996), math.radians(140.7205), 400.0, math.radians(90.0))
    if chunk is not None:
        monkeypatch.setattr(replay_mod, "FAST_CHUNK", chunk)
    calls = []

    class Counted:
        def __init__(self, pipe, one_by_one: bool) -> None:  # noqa: ANN001
            self.p, self.one = pipe, one_by_one

        def __getattr__(self, name: str):  # noqa: ANN204
            return getattr(self.p, name)

        @property
        def can_push_outputs(self) -> bool:
            return not self.one and self.p.can_push_outputs

        def push_imu_outputs(self, *args):  # noqa: ANN002, ANN202
            calls.append(len(args[0]))
            return self.p.push_imu_outputs(*args)

        def push_imu_batch(self, t, w, f, *, altitude_hold=None, attitudes=False):  # noqa: ANN001, ANN202, ARG002
            assert self.one, "the fast path must take every sample"
            for k in range(len(t)):
                self.p.push_imu(float(t[k]), w[k], f[k])

    runs = []
    for one in (False, True):

        def factory(nav, sigma, one=one):  # noqa: ANN001, ANN202
            return Counted(make_online_pipeline(nav, sigma, None, fusion="free_inertial", matcher="none"), one)

        runs.append(replay(rec, None, init=init, field_model=ScalarAnomalyModel(DATE), output_dt=output_dt,
                           max_gap_s=0.5, pipeline_factory=factory))  # fmt: skip
    fast, slow = runs
    assert sum(calls) == len(t) - 2  # every sample but the first (the start) and the one after the gap (restart)
    assert len(calls) >= (2 if chunk is None else len(t) // chunk)
    assert len(fast.gaps) == 1 and fast.gaps[0]["row"] == k_gap + 1
    assert len(fast.t) == len(slow.t) > 90.0 / output_dt
    np.testing.assert_array_equal(fast.t, slow.t)
    tf, ts = fast.trajectory, slow.trajectory
    for x, y in ((tf.lat, ts.lat), (tf.lon, ts.lon), (tf.h, ts.h), (tf.v_n, ts.v_n), (tf.q_nb, ts.q_nb),
                 (fast.sigma_ne, slow.sigma_ne), (fast.hpl_m, slow.hpl_m)):  # fmt: skip
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=0.0)
    assert fast.summary() == slow.summary()
    # the INS ran free (its sigma grows) and restarted at the sample after the gap with the grown sigma
    assert fast.sigma_ne[-1, 0] > 1.5 * fast.sigma_ne[0, 0]
    i = int(np.argmax(fast.t >= t[k_gap] - 1e-9))
    assert fast.sigma_ne[i, 0] >= fast.sigma_ne[i - 1, 0] and np.all(np.diff(fast.t) > 0)


def test_csv_parsed_without_pandas_same_numbers(sim, tmp_path):
    """A plain numeric CSV is parsed straight into one float64 array (no pandas table and copy: 160 MB less at
    1 M rows); the numbers are pandas' own, with comment lines, a blank line and an extra text column. A pressure
    column or a bad value goes through pandas (which names the row and column)."""
    import pandas as pd

    from magnav_ins.mavlink.replay import _read_csv_numbers

    imu, n = sim["imu"], 400
    cols = np.column_stack([sim["truth"].t[:n] + T0, imu.gyro_b[:n], imu.accel_b[:n], sim["mag_b"][:n]])
    body = "\n".join(
        ",".join([f"{cols[k, 0]:.5f}", *(f"{x:.9e}" for x in cols[k, 1:7]), *(f"{x:.2f}" for x in cols[k, 7:])])
        + ",note"
        for k in range(n)
    )
    p = tmp_path / "plain.csv"
    p.write_text("# recorded by a test\n t ,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z,mag_x,mag_y,mag_z,remark\n"
                 + body.replace("\n", "\n# a comment line\n", 1) + "\n\n")  # fmt: skip
    fast = _read_csv_numbers(p)
    assert fast is not None and fast[1]
    ref = pd.read_csv(p, comment="#")
    ref.columns = [c.strip() for c in ref.columns]
    want = ["t", "gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z", "mag_x", "mag_y", "mag_z"]
    np.testing.assert_array_equal(fast[0], ref[want].to_numpy(float))
    rec = read_log(p)
    np.testing.assert_array_equal(rec.imu.gyro_b, fast[0][:, 1:4])
    np.testing.assert_array_equal(rec.mag_b_nt, fast[0][:, 7:10])
    bad = tmp_path / "bad.csv"
    bad.write_text(p.read_text().replace(f"{cols[5, 0]:.5f},", f"{cols[5, 0]:.5f},x", 1))
    assert _read_csv_numbers(bad) is None
    with pytest.raises(InputError, match="column 'gyro_x': not a number"):
        read_log(bad)
    baro = tmp_path / "baro.csv"
    baro.write_text("t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z,pressure_pa\n" + "\n".join(
        f"{T0 + 0.04 * k:.2f},0,0,0,0,0,-9.8,{'' if k % 2 else 96000.0}" for k in range(10)))  # fmt: skip
    assert _read_csv_numbers(baro) is None
    assert len(read_log(baro).baro_pa) == 5


def test_free_inertial_csv_replay_imports_no_heavy_libraries(sim, tmp_path):
    """The free-inertial replay of a CSV over one of this project's NetCDF maps imports neither xarray, pandas,
    pymavlink, scipy.stats nor scipy.signal (~130 MB of a 1 M-row replay's memory: the < 300 MB target)."""
    import subprocess
    import sys

    log = tmp_path / "short.csv"
    _gapped_csv(sim, log)
    code = (
        "import sys, json\nfrom magnav_ins.cli import main\n"
        f"rc = main(['replay', {str(log)!r}, '--map', {MAP!r}, '--init={INIT}', '--fusion', 'free_inertial', "
        f"'--date', {DATE!r}, '--quiet', '--out', {str(tmp_path / 'o.csv')!r}])\n"
        "print(json.dumps([rc, sorted(m for m in sys.modules if m.split('.')[0] in "
        "('xarray', 'pandas', 'pymavlink') or m in ('scipy.stats', 'scipy.signal'))]))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True)
    rc, heavy = json.loads(out.stdout.splitlines()[-1])
    assert rc == 0 and heavy == [], heavy
    assert len(_read_traj(tmp_path / "o.csv")["t"]) > 80


# ------------------------------------------------------------------------------------------ streamed CSV
def _sim_csv(sim, path: Path, *, gap: bool = False) -> None:
    """The simulated flight as a replay CSV (a comment line and a blank line in the middle; with ``gap``, the
    clock jump of :func:`_gapped_csv`)."""
    if gap:
        _gapped_csv(sim, path)
        return
    cols = np.column_stack([sim["truth"].t + T0, sim["imu"].gyro_b, sim["imu"].accel_b, sim["mag_b"]])
    lines = [",".join(f"{x:.17g}" for x in row) for row in cols]
    lines.insert(1500, "# a comment between the rows")
    lines.insert(1700, "")
    path.write_text("t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z,mag_x,mag_y,mag_z\n" + "\n".join(lines) + "\n")


def test_streamed_csv_replays_bit_for_bit_as_read_whole(sim, tmp_path):
    """A CSV read chunk by chunk (open_log, 997 lines a chunk: chunk ends fall on outputs, readings, a comment, the
    gap) gives the trajectory, fix attempts and gap restarts of the same CSV read whole, bit for bit, for the UKF
    (readings every 0.5 s, MLR attempts) and for the free INS; so does a --duration that ends in a later chunk."""
    from magnav_ins.maps.builtin import load_map
    from magnav_ins.mavlink.bridge import ScalarAnomalyModel
    from magnav_ins.mavlink.replay import open_log, replay

    fmap = load_map(MAP).with_error_layer(0.0, 150.0, "the readings come from this map")  # fixes get accepted
    init = (math.radians(-21.7996), math.radians(140.7205), 400.0, math.radians(90.0))
    for gap in (False, True):
        csv = tmp_path / f"rec_{gap}.csv"
        _sim_csv(sim, csv, gap=gap)
        for fusion, duration in (("ukf", None), ("free_inertial", None), ("ukf", 61.3)):
            runs = []
            for rec in (read_log(csv), open_log(csv, chunk_rows=997)):
                runs.append(replay(rec, fmap, init=init, field_model=ScalarAnomalyModel(DATE), reading_interval_s=0.5,
                                   output_dt=0.2, fusion=fusion, matcher="mlr", duration_s=duration))  # fmt: skip
            whole, streamed = runs
            assert streamed.imu_samples == whole.imu_samples and streamed.duration_s == whole.duration_s
            assert len(whole.t) > 200
            for x, y in ((whole.t, streamed.t), (whole.trajectory.lat, streamed.trajectory.lat),
                         (whole.trajectory.lon, streamed.trajectory.lon), (whole.trajectory.v_n, streamed.trajectory.v_n),
                         (whole.trajectory.q_nb, streamed.trajectory.q_nb), (whole.sigma_ne, streamed.sigma_ne),
                         (whole.hpl_m, streamed.hpl_m)):  # fmt: skip
                np.testing.assert_array_equal(x, y)
            assert [(f.t, f.available, f.reason) for f in whole.fixes] == [
                (f.t, f.available, f.reason) for f in streamed.fixes
            ]
            assert streamed.readings == whole.readings and streamed.gaps == whole.gaps
            if duration is None:  # its chunks are read: a second replay of the same recording is refused
                with pytest.raises(ConfigError, match="replays once"):
                    replay(rec, fmap, init=init, fusion=fusion, matcher="mlr")
            assert len(whole.gaps) == (1 if gap and duration is None else 0)
            if fusion == "ukf":  # the matcher ran (no fix is accepted on this CSV: see the README's replay table)
                assert len(whole.fixes) >= 5


def test_streamed_csv_names_a_bad_row_deep_in_a_later_chunk(sim, tmp_path, capsys, monkeypatch):
    """A bad value, a NaN and a time going back far into the file (in the 4th or 5th chunk of 500 lines, after a
    comment line that is no row) are named with the row the whole-file reader gives (1-based data row) and the
    column, one line, exit 2, no output."""
    import magnav_ins.mavlink.replay as replay_mod

    monkeypatch.setattr(replay_mod, "CSV_CHUNK_ROWS", 500)
    monkeypatch.setattr(replay_mod.open_log, "__kwdefaults__", {"geoid_height_m": 0.0, "chunk_rows": 500})
    good = tmp_path / "good.csv"
    _sim_csv(sim, good)
    lines = good.read_text().splitlines()
    # lines[0] header, lines[1500] the comment, lines[1700] blank: data row r is lines[r] up to 1499, then lines[r+1]
    # up to 1698, then lines[r + 2]
    for name, row, edit, match in (
        ("word", 1877, lambda f: f[:5] + ["oops"] + f[6:], "row 1877 column 'accel_y': not a number: 'oops'"),
        ("nan", 2100, lambda f: f[:8] + ["nan"] + f[9:], "row 2100 column 'mag_y': non-finite value nan"),
        ("back", 1999, lambda f: ["100.0"] + f[1:], "CSV row 1999: time goes backwards or repeats: t=100.0 s"),
    ):
        li = lines.copy()
        i = row + 2
        li[i] = ",".join(edit(li[i].split(",")))
        bad = tmp_path / f"{name}.csv"
        bad.write_text("\n".join(li) + "\n")
        with pytest.raises(InputError, match=re.escape(f"{bad}: {match}")):
            read_log(bad)  # the whole-file reader says the same
        assert replay_mod.open_log(bad).rest is not None  # the first chunk is fine: streamed
        err = _assert_fails(capsys, tmp_path, bad, f"--init={INIT}", "--date", DATE, "--fusion", "ukf", match=match)
        assert f"{bad}: " in err


def test_ukf_csv_replay_imports_no_scipy_stats(sim, tmp_path):
    """A UKF replay of a CSV imports no scipy.stats (filterpy's modules get a lazy ``filterpy.stats.logpdf``, ~30 MB
    of a 1 M-row replay's memory), and filterpy's own logpdf still gives scipy's numbers, the real module loaded at
    its first call."""
    import subprocess
    import sys

    log = tmp_path / "short.csv"
    _sim_csv(sim, log)
    code = (
        "import sys, json\nimport numpy as np\nfrom magnav_ins.cli import main\n"
        f"rc = main(['replay', {str(log)!r}, '--map', {MAP!r}, '--init={INIT}', '--fusion', 'ukf', "
        f"'--date', {DATE!r}, '--quiet', '--reading-interval', '0.5', '--out', {str(tmp_path / 'o.csv')!r}])\n"
        "before = 'scipy.stats' in sys.modules\n"
        "from filterpy.kalman import UKF\n"
        "x, m, P = np.array([1.0, -2.0]), np.array([0.5, 0.0]), np.array([[2.0, 0.3], [0.3, 1.0]])\n"
        "lazy = float(UKF.logpdf(x, m, P))\n"
        "from scipy.stats import multivariate_normal\n"
        "print(json.dumps([rc, before, lazy, float(multivariate_normal.logpdf(x, m, P))]))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True)
    rc, stats_before, lazy, real = json.loads(out.stdout.splitlines()[-1])
    assert rc == 0 and not stats_before
    assert lazy == pytest.approx(real, rel=1e-12)
    assert len(_read_traj(tmp_path / "o.csv")["t"]) > 80
