"""``magnav-ins ins integrate``: a round trip on pyins-simulated motion, and every bad input gives exit status 2, a
one-line message naming the file, row and column, and no output file."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from magnav_ins.cli import main
from magnav_ins.commands import ins_integrate
from magnav_ins.core.frames import horizontal_error_m

COLS = ["t", "gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"]


def _cli(argv: list[str]) -> int:
    """``magnav-ins ins integrate ARGV`` through the real dispatcher (MagnavError -> one line, exit status 2)."""
    return main(["ins", "integrate", *argv])


@pytest.fixture(scope="module")
def motion():
    """60 s of 100 Hz sine-velocity motion from pyins; mean rates = exact increments / interval."""
    sim = pytest.importorskip("pyins.sim")
    ref, imu = sim.generate_sine_velocity_motion(
        0.01, 60.0, [55.0, 37.0, 0.0], [5.0, -3.0, 0.0], velocity_change_amplitude=[1.0, 1.0, 0.0],
        sensor_type="increment",
    )  # fmt: skip
    t = imu.index.to_numpy(dtype=float) + 1000.0
    inc = imu.to_numpy()
    df = pd.DataFrame(inc / 0.01, columns=COLS[1:])
    df.insert(0, "t", t)
    r0 = ref.iloc[0]
    init = {
        "t": float(t[0]), "lat_deg": float(r0.lat), "lon_deg": float(r0.lon), "h_m": float(r0.alt),
        "v_n": [float(r0.VN), float(r0.VE), float(r0.VD)],
        "roll_deg": float(r0.roll), "pitch_deg": float(r0.pitch), "yaw_deg": float(r0.heading),
    }  # fmt: skip
    return ref, df, init


def _write(tmp_path, df: pd.DataFrame, init: dict, text: str | None = None):
    imu = tmp_path / "imu.csv"
    if text is None:
        df.to_csv(imu, index=False, float_format="%.17g")
    else:
        imu.write_text(text)
    ini = tmp_path / "init.json"
    ini.write_text(json.dumps(init))
    return imu, ini, tmp_path / "traj.csv"


def test_round_trip_against_pyins_truth(tmp_path, motion, capsys):
    ref, df, init = motion
    imu, ini, out = _write(tmp_path, df, init)
    # small chunks so that the state is carried across many chunk boundaries
    assert _cli([str(imu), "--init", str(ini), "--out", str(out), "--chunk-rows", "777"]) == 0
    assert "wrote 6000 states" in capsys.readouterr().out
    traj = pd.read_csv(out)
    assert list(traj.columns) == list(ins_integrate.TRAJ_COLUMNS)
    assert len(traj) == len(df)
    np.testing.assert_allclose(traj.t, df.t, atol=1e-9)
    err = horizontal_error_m(
        np.deg2rad(traj.lat_deg), np.deg2rad(traj.lon_deg), np.deg2rad(ref.lat), np.deg2rad(ref.lon)
    )
    assert err.max() < 1e-3
    np.testing.assert_allclose(traj[["vn", "ve", "vd"]], ref[["VN", "VE", "VD"]], atol=1e-5)
    np.testing.assert_allclose(traj[["roll_deg", "pitch_deg", "yaw_deg"]], ref[["roll", "pitch", "heading"]], atol=1e-6)
    # chunking does not change the numbers
    out2 = tmp_path / "traj2.csv"
    assert _cli([str(imu), "--init", str(ini), "--out", str(out2)]) == 0
    assert out.read_text() == out2.read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["imu.csv", "init.json", "traj.csv", "traj2.csv"]


def _small(df: pd.DataFrame, n: int = 50) -> pd.DataFrame:
    return df.iloc[:n].reset_index(drop=True).copy()


def _csv_with(df: pd.DataFrame, row: int, col: str, raw: str) -> str:
    """The CSV text of ``df`` with the field of data row ``row`` (1-based), column ``col`` replaced by ``raw``."""
    lines = df.to_csv(index=False, float_format="%.17g").splitlines()
    j = list(df.columns).index(col)
    fields = lines[row].split(",")
    fields[j] = raw
    lines[row] = ",".join(fields)
    return "\n".join(lines) + "\n"


def _bad_cases(df: pd.DataFrame, init: dict):
    d = _small(df)
    later = d.copy()
    later.loc[30:, "t"] += 1.0  # a 1.01 s interval before data row 31
    back = d.copy()
    back.loc[20, "t"] = back.loc[19, "t"]
    renamed = d.rename(columns={"accel_z": "acc_z"})
    missing = d.drop(columns=["gyro_y"])
    return {
        "nan": (_csv_with(d, 12, "gyro_y", "nan"), init, ["row 12", "'gyro_y'", "finite"], []),
        "empty": (_csv_with(d, 7, "accel_x", ""), init, ["row 7", "'accel_x'", "finite"], []),
        "inf": (_csv_with(d, 9, "accel_z", "inf"), init, ["row 9", "'accel_z'", "finite"], []),
        "malformed": (_csv_with(d, 5, "gyro_x", "0.1.2"), init, ["row 5", "'gyro_x'", "not a number"], []),
        "not_increasing": (back.to_csv(index=False), init, ["row 21", "'t'", "increase"], []),
        "gap": (later.to_csv(index=False), init, ["row 31", "'t'", "gap", "--max-gap"], []),
        "gap_over_max_gap": (later.to_csv(index=False), init, ["row 31", "'t'", "gap"], ["--max-gap", "0.5"]),
        "unknown_column": (renamed.to_csv(index=False), init, ["row 0", "'acc_z'", "unknown column"], []),
        "missing_column": (missing.to_csv(index=False), init, ["row 0", "'gyro_y'", "missing column"], []),
        "init_unknown_key": (d.to_csv(index=False), {**init, "alt_m": 3.0}, ["init.json", "'alt_m'", "unknown"], []),
        "init_missing_key": (
            d.to_csv(index=False),
            {k: v for k, v in init.items() if k != "yaw_deg"},
            ["init.json", "'yaw_deg'"],
            [],
        ),
        "init_bad_value": (d.to_csv(index=False), {**init, "h_m": "high"}, ["init.json", "'h_m'", "number"], []),
        "init_bad_v_n": (d.to_csv(index=False), {**init, "v_n": [1.0, 2.0]}, ["init.json", "'v_n'", "3"], []),
        "init_time": (d.to_csv(index=False), {**init, "t": init["t"] + 0.5}, ["init.json", "'t'", "row 1"], []),
    }


CASES = [
    "nan", "empty", "inf", "malformed", "not_increasing", "gap", "gap_over_max_gap", "unknown_column",
    "missing_column", "init_unknown_key", "init_missing_key", "init_bad_value", "init_bad_v_n", "init_time",
]  # fmt: skip


@pytest.mark.parametrize("case", CASES)
def test_bad_input_exit_2_one_line_no_output(tmp_path, motion, capsys, case):
    _, df, init = motion
    text, ini_d, expected, extra = _bad_cases(df, init)[case]
    imu, ini, out = _write(tmp_path, df, ini_d, text=text)
    status = _cli([str(imu), "--init", str(ini), "--out", str(out), "--chunk-rows", "16", *extra])
    err = capsys.readouterr().err.strip()
    assert status == 2
    assert len(err.splitlines()) == 1, err
    assert ("imu.csv" in err) or ("init.json" in err)
    for piece in expected:
        assert piece in err, (piece, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["imu.csv", "init.json"]


def test_max_gap_allows_a_gap(tmp_path, motion):
    _, df, init = motion
    d = _small(df)
    d.loc[30:, "t"] += 1.0
    imu, ini, out = _write(tmp_path, d, init)
    assert _cli([str(imu), "--init", str(ini), "--out", str(out), "--max-gap", "2"]) == 0
    assert len(pd.read_csv(out)) == len(d)


def test_malformed_json_and_missing_file(tmp_path, motion, capsys):
    _, df, init = motion
    imu, ini, out = _write(tmp_path, _small(df), init)
    ini.write_text('{"t": 1,\n "lat_deg": }')
    assert _cli([str(imu), "--init", str(ini), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "init.json" in err and "line 2" in err
    ini.write_text(json.dumps(init))
    assert _cli([str(tmp_path / "nope.csv"), "--init", str(ini), "--out", str(out)]) == 2
    assert "nope.csv" in capsys.readouterr().err
    assert not out.exists()
