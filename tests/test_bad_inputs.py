"""Bad input to every command, table-driven (issue 18): missing, empty, binary-junk and folder files, bad values,
out-of-range keys, implausible values, unwritable outputs. Each case runs through the real dispatcher and must
end with exit status 2, exactly one line on stderr (``magnav-ins: error: ...``) naming the file / row / key /
option, and no output (nor ``.part`` file) left behind.

Further rows for ``replay`` and ``bridge`` (log formats, messages of each topic, the link) are in their own tests
(``tests/test_replay.py``, ``tests/test_mavlink_*.py``)."""

from __future__ import annotations

import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from magnav_ins.cli import main

TINY = """\
name = "tiny"
seed = 1
runs = 1

[trajectory]
kind = "great_circle"
start = [-35.0, 149.0]
end = [-35.0, 149.1]
altitude_m = 500.0
speed_mps = 50.0
duration_s = 20.0

[imu]
grade = "tactical"
rate_hz = 10.0
"""

#: a scenario on a map of full gravity (978,000 mGal) given as a "gravity disturbance"
FULL_GRAVITY = """\
name = "full_gravity"
[trajectory]
kind = "great_circle"
start = [-35.0, 149.0]
end = [-35.0, 149.1]
altitude_m = 500.0
speed_mps = 50.0
duration_s = 20.0
[imu]
grade = "tactical"
rate_hz = 10.0
[map]
path = "fullg.nc"
kind = "gravity_disturbance_mgal"
[sensor]
kind = "gravimeter"
sigma = 1.0
interval_s = 1.0
[[estimator]]
name = "ml+ukf"
matcher = { kind = "ml" }
fusion = { kind = "ukf" }
"""

INIT = {"t": 0.0, "lat_deg": 40.0, "lon_deg": -84.0, "h_m": 200.0, "v_n": [0, 0, 0], "roll_deg": 0.0,
        "pitch_deg": 0.0, "yaw_deg": 0.0}  # fmt: skip
IMU_HEADER = "t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n"


def _imu_rows(n: int = 200, gyro_y=None, accel_z: float = -9.8) -> str:
    rows = [IMU_HEADER]
    for k in range(n):
        gy = gyro_y(k) if gyro_y else 0.0
        rows.append(f"{k / 100:.2f},0,{gy},0,0,0,{accel_z}\n")
    return "".join(rows)


def _level_circle_nt(scale: float = 1.0) -> str:
    """Readings of a level 360-degree turn near Canberra (|B| about 58,000 nT), in nT times ``scale``."""
    h = np.linspace(0.0, 2 * np.pi, 240)
    b = np.column_stack([24000 * np.cos(h) + 300, -24000 * np.sin(h) - 200, -52000 + 0 * h]) * scale
    return "t,mx,my,mz\n" + "".join(f"{k * 0.1:.1f},{x:.6g},{y:.6g},{z:.6g}\n" for k, (x, y, z) in enumerate(b))


@pytest.fixture
def work(tmp_path, monkeypatch):
    """A folder with the files the cases refer to; the cases run inside it."""
    rng = np.random.default_rng(18)
    (tmp_path / "junk.bin").write_bytes(rng.integers(0, 256, 3000, dtype=np.uint8).tobytes())
    (tmp_path / "empty").write_bytes(b"")
    (tmp_path / "adir").mkdir()
    (tmp_path / "afile").write_text("not a folder\n")
    (tmp_path / "tiny.toml").write_text(TINY)
    (tmp_path / "init.json").write_text(json.dumps(INIT))
    (tmp_path / "imu.csv").write_text(_imu_rows())
    (tmp_path / "imu_gyro_1e6.csv").write_text(_imu_rows(gyro_y=lambda k: 1e6 if k == 120 else 0.0))
    (tmp_path / "imu_in_g.csv").write_text(_imu_rows(accel_z=-1.0))
    (tmp_path / "imu_nan.csv").write_text(_imu_rows().replace("\n0.42,0,0.0,", "\n0.42,0,nan,"))
    (tmp_path / "imu_gap.csv").write_text(
        IMU_HEADER + "".join(f"{k / 100 + (3600.0 if k >= 100 else 0.0):.2f},0,0,0,0,0,-9.8\n" for k in range(200))
    )
    (tmp_path / "cal_nt.csv").write_text(_level_circle_nt())
    (tmp_path / "cal_gauss.csv").write_text(_level_circle_nt(1e-5))
    (tmp_path / "points.csv").write_text("lat_deg,lon_deg\n-21.0,140.7\n")
    (tmp_path / "points_bad.csv").write_text("lat_deg,lon_deg\n-21.0,140.7\n210.0,140.7\n")
    (tmp_path / "full_gravity.toml").write_text(FULL_GRAVITY)
    _utm_grid(tmp_path / "utm.nc")
    _full_gravity_map(tmp_path / "fullg.nc")
    for name, text in (
        ("rate_1e9.toml", TINY.replace("rate_hz = 10.0", "rate_hz = 1e9")),
        ("rate_1e-3.toml", TINY.replace("rate_hz = 10.0", "rate_hz = 0.001")),
        ("unknown_key.toml", TINY.replace("speed_mps = 50.0", "speed_mps = 50.0\nsped_kts = 97")),
        ("syntax.toml", TINY.replace("runs = 1", "runs = = 1")),
        ("nul.toml", TINY.replace("seed = 1", "seed = 1\x00")),
    ):
        (tmp_path / name).write_text(text)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _full_gravity_map(path: Path) -> None:
    from magnav_ins.core.types import FieldKind
    from magnav_ins.core.units import DEG_TO_RAD
    from magnav_ins.maps.grid import GridMap
    from magnav_ins.maps.io import write_map

    lat = np.linspace(-35.5, -34.5, 21) * DEG_TO_RAD
    lon = np.linspace(148.5, 149.5, 21) * DEG_TO_RAD
    values = 979_700.0 + 30.0 * np.sin(np.arange(21))[:, None] * np.cos(np.arange(21))[None, :]
    write_map(
        GridMap(lat, lon, values, kind=FieldKind.GRAVITY_DISTURBANCE_MGAL, frame="geodetic", altitude_m=500.0), path
    )


def _utm_grid(path: Path) -> None:
    """A grid in UTM zone 54S metres (dimensions y, x), as projected surveys are delivered."""
    import xarray as xr

    x, y = np.arange(500e3, 510e3, 500.0), np.arange(7.0e6, 7.01e6, 500.0)
    attrs = {"units": "nT", "magnav_kind": "total_field_anomaly_nt"}
    ds = xr.Dataset(
        {"anomaly": (("y", "x"), np.zeros((y.size, x.size)), attrs)},
        coords={"y": y, "x": x},
        attrs={"geodetic_datum": "WGS84", "altitude_m": 100.0, "crs": "EPSG:32754"},
    )
    ds.to_netcdf(path)


@dataclass(frozen=True)
class Case:
    id: str
    argv: tuple[str, ...]
    expect: tuple[str, ...]  # pieces of the one-line message
    no_output: tuple[str, ...] = ()  # paths that must not exist afterwards


MAP = "builtin:osborne-magnetic"
INTEGRATE = ("ins", "integrate")
CASES = [
    # ---- run: the scenario file
    Case("run-missing", ("run", "nope.toml"), ("nope.toml", "does not exist")),
    Case("run-binary-junk", ("run", "junk.bin", "--out", "o"), ("junk.bin", "line 1", "not a text file"), ("o",)),
    Case("run-empty", ("run", "empty", "--out", "o"), ("empty", "is empty"), ("o",)),
    Case("run-folder", ("run", "adir", "--out", "o"), ("adir", "is a folder"), ("o",)),
    Case("run-nul-byte", ("run", "nul.toml", "--out", "o"), ("nul.toml", "line 2", "NUL"), ("o",)),
    Case("run-bad-toml", ("run", "syntax.toml", "--out", "o"), ("syntax.toml", "not valid TOML", "line 3"), ("o",)),
    Case("run-unknown-key", ("run", "unknown_key.toml", "--out", "o"), ("line 11", "'trajectory.sped_kts'"), ("o",)),
    Case("run-rate-1e9", ("run", "rate_1e9.toml", "--out", "o"), ("line 15", "'imu.rate_hz'", "[1, 2000]"), ("o",)),
    Case("run-rate-1e-3", ("run", "rate_1e-3.toml", "--out", "o"), ("line 15", "'imu.rate_hz'", "range"), ("o",)),
    Case("run-runs-0", ("run", "tiny.toml", "--runs", "0", "--out", "o"), ("--runs",), ("o",)),
    Case("run-runs-1e8", ("run", "tiny.toml", "--runs", "100000000", "--out", "o"), ("--runs", "100000]"), ("o",)),
    Case("run-jobs-0", ("run", "tiny.toml", "--jobs", "0", "--out", "o"), ("--jobs",), ("o",)),
    Case("run-duration", ("run", "tiny.toml", "--duration", "-5", "--out", "o"), ("--duration",), ("o",)),
    Case(
        "run-full-gravity",
        ("run", "full_gravity.toml", "--out", "o"),
        ("'map.path'", "full gravity", "allow_implausible"),
        ("o",),
    ),  # fmt: skip
    # ---- run: outputs, refused before the study is computed (the study is not even started: see the fixture)
    Case("run-out-is-file", ("run", "tiny.toml", "--out", "afile"), ("--out afile", "is a file")),
    Case("run-out-under-file", ("run", "tiny.toml", "--out", "afile/o"), ("--out afile/o", "afile is a file")),
    # ---- ins integrate
    Case(
        "integrate-missing",
        (*INTEGRATE, "nope.csv", "--init", "init.json", "--out", "t.csv"),
        ("nope.csv",),
        ("t.csv",),
    ),  # fmt: skip
    Case(
        "integrate-junk", (*INTEGRATE, "junk.bin", "--init", "init.json", "--out", "t.csv"), ("junk.bin",), ("t.csv",)
    ),  # fmt: skip
    Case("integrate-empty", (*INTEGRATE, "empty", "--init", "init.json", "--out", "t.csv"), ("empty",), ("t.csv",)),
    Case("integrate-folder", (*INTEGRATE, "adir", "--init", "init.json", "--out", "t.csv"), ("adir",), ("t.csv",)),
    Case(
        "integrate-init-junk",
        (*INTEGRATE, "imu.csv", "--init", "junk.bin", "--out", "t.csv"),
        ("junk.bin", "not a text file"),
        ("t.csv",),
    ),  # fmt: skip
    Case(
        "integrate-init-empty",
        (*INTEGRATE, "imu.csv", "--init", "empty", "--out", "t.csv"),
        ("empty", "not valid JSON"),
        ("t.csv",),
    ),  # fmt: skip
    Case(
        "integrate-nan-row",
        (*INTEGRATE, "imu_nan.csv", "--init", "init.json", "--out", "t.csv"),
        ("imu_nan.csv row 43 'gyro_y'", "finite"),
        ("t.csv",),
    ),  # fmt: skip
    Case(
        "integrate-gyro-1e6",
        (*INTEGRATE, "imu_gyro_1e6.csv", "--init", "init.json", "--out", "t.csv"),
        ("imu_gyro_1e6.csv row 121 'gyro_y'", "rad/s", "--allow-implausible"),
        ("t.csv",),
    ),  # fmt: skip
    Case(
        "integrate-accel-in-g",
        (*INTEGRATE, "imu_in_g.csv", "--init", "init.json", "--out", "t.csv"),
        ("imu_in_g.csv rows 1-", "in g?", "--allow-implausible"),
        ("t.csv",),
    ),  # fmt: skip
    Case(
        "integrate-out-folder",
        (*INTEGRATE, "imu.csv", "--init", "init.json", "--out", "adir"),
        ("--out adir", "is a folder"),
    ),  # fmt: skip
    Case(
        "integrate-out-under-file",
        (*INTEGRATE, "imu.csv", "--init", "init.json", "--out", "afile/t.csv"),
        ("--out afile/t.csv", "afile is a file"),
    ),  # fmt: skip
    Case(
        "integrate-altitude-hold",
        (*INTEGRATE, "imu.csv", "--init", "init.json", "--out", "t.csv", "--altitude-hold", "1e9"),
        ("--altitude-hold",),
        ("t.csv",),
    ),  # fmt: skip
    # ---- ins drift
    Case("drift-grade", ("ins", "drift", "--grade", "militaryish", "--out", "d"), ("militaryish",), ("d",)),
    Case(
        "drift-rate", ("ins", "drift", "--grade", "tactical", "--rate-hz", "1e9", "--out", "d"), ("--rate-hz",), ("d",)
    ),  # fmt: skip
    Case("drift-runs", ("ins", "drift", "--grade", "tactical", "--runs", "1", "--out", "d"), ("--runs",), ("d",)),
    Case(
        "drift-out-is-file",
        ("ins", "drift", "--grade", "tactical", "--duration", "10", "--out", "afile"),
        ("--out afile", "is a file"),
    ),  # fmt: skip
    # ---- calibrate
    Case(
        "calibrate-missing",
        ("calibrate", "nope.csv", "--lat", "-35", "--lon", "149", "--date", "2020-01-01"),
        ("nope.csv",),
    ),  # fmt: skip
    Case(
        "calibrate-junk",
        ("calibrate", "junk.bin", "--lat", "-35", "--lon", "149", "--date", "2020-01-01"),
        ("junk.bin",),
    ),  # fmt: skip
    Case(
        "calibrate-empty", ("calibrate", "empty", "--lat", "-35", "--lon", "149", "--date", "2020-01-01"), ("empty",)
    ),  # fmt: skip
    Case(
        "calibrate-gauss",
        ("calibrate", "cal_gauss.csv", "--lat", "-35", "--lon", "149", "--date", "2020-01-01"),
        ("cal_gauss.csv", "must be in nT", "gauss"),
    ),  # fmt: skip
    Case(
        "calibrate-date", ("calibrate", "cal_nt.csv", "--lat", "-35", "--lon", "149", "--date", "1st May"), ("--date",)
    ),  # fmt: skip
    Case(
        "calibrate-lat", ("calibrate", "cal_nt.csv", "--lat", "135", "--lon", "149", "--date", "2020-01-01"), ("--lat",)
    ),  # fmt: skip
    Case(
        "calibrate-out-folder",
        ("calibrate", "cal_nt.csv", "--lat", "-35", "--lon", "149", "--date", "2020-01-01", "--out", "adir"),
        ("--out adir", "is a folder"),
    ),  # fmt: skip
    # ---- map info / grid / sample / variability
    Case("map-info-missing", ("map", "info", "nope.nc"), ("nope.nc", "no such map file")),
    Case("map-info-junk", ("map", "info", "junk.bin"), ("junk.bin", "not a NetCDF file")),
    Case("map-info-empty", ("map", "info", "empty"), ("empty", "is empty")),
    Case("map-grid-junk", ("map", "grid", "junk.bin", "--spacing", "100", "--out", "g.nc"), ("junk.bin",), ("g.nc",)),
    Case("map-grid-empty", ("map", "grid", "empty", "--spacing", "100", "--out", "g.nc"), ("empty",), ("g.nc",)),
    Case(
        "map-grid-level-sigma",
        ("map", "grid", "points.csv", "--spacing", "100", "--out", "g.nc", "--level-sigma", "-3"),
        ("--level-sigma", ">= 0"),
        ("g.nc",),
    ),  # fmt: skip
    Case(
        "map-grid-out-folder",
        ("map", "grid", "points.csv", "--spacing", "100", "--out", "adir"),
        ("--out adir", "is a folder"),
    ),  # fmt: skip
    Case(
        "map-sample-junk", ("map", "sample", MAP, "--points", "junk.bin", "--out", "s.csv"), ("junk.bin",), ("s.csv",)
    ),  # fmt: skip
    Case(
        "map-sample-missing",
        ("map", "sample", MAP, "--points", "nope.csv", "--out", "s.csv"),
        ("nope.csv",),
        ("s.csv",),
    ),  # fmt: skip
    Case(
        "map-sample-bad-row",
        ("map", "sample", MAP, "--points", "points_bad.csv", "--out", "s.csv"),
        ("points_bad.csv row 2", "'lat_deg'"),
        ("s.csv",),
    ),  # fmt: skip
    Case(
        "map-sample-out-folder",
        ("map", "sample", MAP, "--points", "points.csv", "--out", "adir"),
        ("--out adir", "is a folder"),
    ),  # fmt: skip
    Case(
        "map-sample-out-under-file",
        ("map", "sample", MAP, "--points", "points.csv", "--out", "afile/s.csv"),
        ("--out afile/s.csv", "afile is a file"),
    ),  # fmt: skip
    Case(
        "map-variability-junk",
        ("map", "variability", "junk.bin", "--window", "1000", "--out", "v.nc"),
        ("junk.bin", "not a NetCDF file"),
        ("v.nc", "v.png"),
    ),  # fmt: skip
    Case(
        "map-variability-window",
        ("map", "variability", MAP, "--window", "-1", "--out", "v.nc"),
        ("--window",),
        ("v.nc", "v.png"),
    ),  # fmt: skip
    Case(
        "map-variability-out-folder",
        ("map", "variability", MAP, "--window", "1000", "--out", "adir"),
        ("--out adir", "is a folder"),
    ),  # fmt: skip
    # ---- demo
    Case("demo-out-is-file", ("demo", "--out", "afile"), ("--out afile", "is a file")),
    Case("demo-duration", ("demo", "--duration", "-1", "--out", "dm"), ("--duration",), ("dm",)),
    # ---- replay (generic rows only; its own messages are tested in tests/test_replay.py)
    Case("replay-missing", ("replay", "nope.ulg", "--map", MAP), ("nope.ulg",)),
    Case("replay-junk", ("replay", "junk.bin", "--map", MAP, "--out", "r.csv"), ("junk.bin",), ("r.csv",)),
    Case("replay-out-folder", ("replay", "junk.bin", "--map", MAP, "--out", "adir"), ("--out adir", "is a folder")),
    Case(
        "replay-out-under-file",
        ("replay", "imu.csv", "--map", MAP, "--init", "-21.8,140.7,400,0", "--out", "afile/r.csv"),
        ("--out afile/r.csv", "afile is a file"),
    ),  # fmt: skip
    Case("replay-empty", ("replay", "empty", "--map", MAP, "--out", "r.csv"), ("empty",), ("r.csv",)),
    Case("replay-folder", ("replay", "adir", "--map", MAP, "--out", "r.csv"), ("adir",), ("r.csv",)),
    Case(
        "replay-no-init",
        ("replay", "imu.csv", "--map", MAP, "--out", "r.csv"),
        ("imu.csv", "CSV", "--init"),
        ("r.csv",),
    ),  # fmt: skip
    Case(
        "replay-init-junk",
        ("replay", "imu.csv", "--map", MAP, "--init", "1,2,x", "--out", "r.csv"),
        ("--init",),
        ("r.csv",),
    ),  # fmt: skip
    Case(
        "replay-init-range",
        ("replay", "imu.csv", "--map", MAP, "--init", "95,140,400,0", "--out", "r.csv"),
        ("--init", "latitude"),
        ("r.csv",),
    ),  # fmt: skip
    Case(
        "replay-nan-row",
        ("replay", "imu_nan.csv", "--map", MAP, "--init", "-21.8,140.7,400,0", "--out", "r.csv"),
        ("imu_nan.csv", "row 43", "'gyro_y'"),
        ("r.csv",),
    ),  # fmt: skip
    Case(
        "replay-gap-stop",
        ("replay", "imu_gap.csv", "--map", MAP, "--init", "-21.8,140.7,400,0", "--on-gap", "stop", "--out", "r.csv"),
        ("imu_gap.csv", "row 101", "IMU gap of 3600", "t=0.990000 -> 3601.000000 s"),
        ("r.csv",),
    ),  # fmt: skip
    Case(
        "replay-max-gap",
        ("replay", "imu.csv", "--map", MAP, "--init", "-21.8,140.7,400,0", "--max-gap", "0", "--out", "r.csv"),
        ("--max-gap",),
        ("r.csv",),
    ),  # fmt: skip
    Case(
        "replay-interval",
        ("replay", "imu.csv", "--map", MAP, "--init", "-21.8,140.7,400,0", "--output-interval", "-1", "--out", "r.csv"),
        ("--output-interval",),
        ("r.csv",),
    ),  # fmt: skip
    Case(
        "replay-duration",
        ("replay", "imu.csv", "--map", MAP, "--init", "-21.8,140.7,400,0", "--duration", "0", "--out", "r.csv"),
        ("--duration",),
        ("r.csv",),
    ),  # fmt: skip
    Case(
        "replay-date",
        ("replay", "imu.csv", "--map", MAP, "--init", "-21.8,140.7,400,0", "--date", "2020-13-01"),
        ("--date",),
    ),  # fmt: skip
    Case(
        "replay-map-junk",
        ("replay", "imu.csv", "--map", "junk.bin", "--init", "-21.8,140.7,400,0", "--out", "r.csv"),
        ("junk.bin",),
        ("r.csv",),
    ),  # fmt: skip
    Case(
        "replay-summary-folder",
        ("replay", "imu.csv", "--map", MAP, "--init", "-21.8,140.7,400,0", "--summary-json", "adir"),
        ("--summary-json adir", "is a folder"),
    ),  # fmt: skip
    # ---- bridge (refused before any connection is tried)
    Case("bridge-connect-junk", ("bridge", "--connect", "udpin:host:notaport", "--map", MAP), ("--connect",)),
    Case(
        "bridge-map-missing", ("bridge", "--connect", "udpin:127.0.0.1:14550", "--map", "nope.nc"), ("nope.nc",)
    ),  # fmt: skip
    Case(
        "bridge-init-junk",
        ("bridge", "--connect", "udpin:127.0.0.1:14550", "--map", MAP, "--init", "a,b"),
        ("--init",),
    ),  # fmt: skip
    Case(
        "bridge-summary-folder",
        ("bridge", "--connect", "udpin:127.0.0.1:14550", "--map", MAP, "--summary-json", "adir", "--duration", "5"),
        ("--summary-json adir", "is a folder"),
    ),  # fmt: skip
    Case(
        "bridge-long-window",
        ("bridge", "--connect", "udpin:127.0.0.1:14550", "--map", MAP, "--window", "80", "--long-window", "60"),
        ("--long-window 60", "--window (80)"),
    ),  # fmt: skip
    # ---- suite
    Case("suite-seeds-0", ("suite", "--seeds", "0"), ("--seeds",)),
    Case("suite-rio-missing", ("suite", "--only", "rio", "--rio", "nope.csv.xz"), ("nope.csv.xz",)),
]


@pytest.fixture
def no_study(monkeypatch):
    """``run`` must refuse its bad inputs before any Monte Carlo run starts."""
    from magnav_ins.studies import runner

    def refuse(*args, **kwargs):
        raise AssertionError("the study was started despite a bad input")

    monkeypatch.setattr(runner, "execute", refuse)


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input(work, no_study, capsys, case):
    before = {p.name: p.stat().st_mtime_ns for p in work.iterdir()}
    status = main(list(case.argv))
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert status == 2, err
    assert len(lines) == 1 and lines[0].startswith("magnav-ins: error: "), err
    for piece in case.expect:
        assert piece in lines[0], (piece, lines[0])
    for out in case.no_output:
        assert not (work / out).exists(), out
    assert not [p for p in work.rglob("*") if p.name.endswith(".part") or "staging" in p.name]
    # nothing else appeared, and no input was touched
    assert {p.name: p.stat().st_mtime_ns for p in work.iterdir()} == before


def test_read_only_place(work, capsys, monkeypatch):
    """A place where the process may not create files is refused before the work, naming the option."""
    if os.geteuid() == 0 or not hasattr(os, "geteuid"):
        if not sys.platform.startswith("linux"):
            pytest.skip("needs a read-only folder: not root, or Linux /proc")
        target = "/proc/magnav-out.csv"  # no process may create files there, root included
    else:
        ro = work / "ro"
        ro.mkdir()
        ro.chmod(0o555)
        target = str(ro / "t.csv")
    status = main([*INTEGRATE, "imu.csv", "--init", "init.json", "--out", target])
    err = capsys.readouterr().err.strip()
    assert status == 2 and len(err.splitlines()) == 1, err
    assert f"--out {target}: cannot create files in" in err
    assert not Path(target).exists()


def test_allow_implausible_overrides(work, capsys):
    """The option named by the refusal integrates the file anyway."""
    assert main([*INTEGRATE, "imu_in_g.csv", "--init", "init.json", "--out", "t.csv", "--allow-implausible"]) == 0
    assert (work / "t.csv").stat().st_size > 0


def test_map_info_warns_about_an_implausible_map(work, capsys):
    """Inspection goes on (exit 0) with a one-line warning; navigating on the map ('run') is refused above."""
    assert main(["map", "info", "fullg.nc"]) == 0
    captured = capsys.readouterr()
    [warning] = [ln for ln in captured.err.splitlines() if ln.strip()]
    assert warning.startswith("magnav-ins: warning: fullg.nc") and "full gravity" in warning
    assert "gravity_disturbance_mgal" in captured.out


def test_antimeridian_wrapped_grid_is_read(work, capsys):
    """A longitude axis that wraps at 180 deg (..., 179.5, -180, ...) is made continuous, not refused ("flip the
    grid"): values at points on both sides are the file's own node values."""
    import pandas as pd
    import xarray as xr

    lon = np.r_[np.arange(170.0, 180.0, 0.5), np.arange(-180.0, -170.0, 0.5)]
    lat = np.arange(-20.0, -10.0, 0.5)
    v = np.random.default_rng(3).normal(0.0, 100.0, (lat.size, lon.size))
    attrs = {"units": "nT", "magnav_kind": "total_field_anomaly_nt"}
    xr.Dataset(
        {"anomaly": (("lat", "lon"), v, attrs)},
        coords={"lat": lat, "lon": lon},
        attrs={"geodetic_datum": "WGS84", "altitude_m": 1000.0},
    ).to_netcdf(work / "wrapped.nc")
    (work / "p.csv").write_text("lat_deg,lon_deg\n-15.0,179.5\n-15.0,-180.0\n-15.0,-175.0\n")
    assert main(["map", "sample", "wrapped.nc", "--points", "p.csv", "--out", "s.csv"]) == 0
    got = pd.read_csv(work / "s.csv")["value"].to_numpy()
    row = int(np.flatnonzero(lat == -15.0)[0])
    want = [v[row, int(np.flatnonzero(lon == x)[0])] for x in (179.5, -180.0, -175.0)]
    np.testing.assert_allclose(got, want, rtol=1e-9)


def test_utm_grid_is_used_in_its_own_crs(tmp_path):
    """A grid in UTM metres with a CRS opens as a projected map (issue 14: used in its own CRS), not refused."""
    from magnav_ins.maps.io import read_map

    _utm_grid(tmp_path / "utm.nc")
    m = read_map(tmp_path / "utm.nc")
    assert m.frame == "projected" and "UTM zone 54S" in m.projection.name
