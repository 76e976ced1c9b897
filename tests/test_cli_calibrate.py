"""``magnav-ins calibrate``: end to end through the dispatcher on a simulated circle drive at AFIT (IGRF), and
the user mistakes that must end in a one-line message and exit status 2."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from magnav_ins import cli
from magnav_ins.aiding.calibration import MagCalibration, simulate_level_circles
from magnav_ins.core.units import DEG_TO_RAD
from magnav_ins.maps.reference import igrf_ned

SITE = ["--lat", "39.78", "--lon", "-84.08", "--alt", "250", "--date", "2011-08-11"]  # AFIT, Shockley's site
C = np.array([[1.05, 0.015, 0.0], [0.015, 0.96, 0.0], [0.0, 0.0, 1.0]])
B = np.array([2500.0, -4000.0, 1000.0])


@pytest.fixture
def main(monkeypatch):
    """The real dispatcher with only this command group registered (isolates from other groups)."""
    monkeypatch.setattr(cli, "COMMAND_MODULES", ("calibrate",))
    return cli.main


@pytest.fixture
def field():
    return np.asarray(igrf_ned(39.78 * DEG_TO_RAD, -84.08 * DEG_TO_RAD, 250.0, "2011-08-11"), float).reshape(3)


def _write(path, m):
    pd.DataFrame({"t": np.arange(len(m)) * 0.02, "mx": m[:, 0], "my": m[:, 1], "mz": m[:, 2]}).to_csv(path, index=False)
    return path


def test_calibrate_writes_json_that_recovers_the_truth(main, field, tmp_path, capsys):
    m, B_b = simulate_level_circles(field, C, B, 100.0, np.random.default_rng(4))
    csv = _write(tmp_path / "r.csv", m)
    out = tmp_path / "cal.json"
    assert main(["calibrate", str(csv), "--method", "modified-ellipsoid", *SITE, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    total = float(np.linalg.norm(field))
    assert f"|B| = {total:.1f} nT" in text and "before" in text and "after" in text
    cal = MagCalibration.from_json(out)
    assert cal.method == "modified-ellipsoid" and cal.n_points == len(m)
    assert cal.lat == pytest.approx(39.78 * DEG_TO_RAD)
    np.testing.assert_allclose(cal.A[:2, :2], np.linalg.inv(C[:2, :2]), atol=2e-3)
    np.testing.assert_allclose(cal.b[:2], B[:2], atol=30.0)
    np.testing.assert_allclose(cal.apply(m)[:, :2], B_b[:, :2], atol=600.0)
    assert cal.after.std_nt < cal.before.std_nt / 5
    assert math.isclose(cal.field_total_nt, total)


@pytest.mark.parametrize("method", ["swinging", "ellipse"])
def test_other_level_methods_run(main, field, tmp_path, method):
    m, _ = simulate_level_circles(field, C, B, 100.0, np.random.default_rng(5))
    assert main(["calibrate", str(_write(tmp_path / "r.csv", m)), "--method", method, *SITE]) == 0


def _err(main, capsys, argv):
    code = main(argv)
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.startswith("magnav-ins: error:") and "\n" not in err and "Traceback" not in err
    return err


def test_nan_rows_named(main, field, tmp_path, capsys):
    m, _ = simulate_level_circles(field, C, B, 100.0, np.random.default_rng(6))
    m[7, 1] = np.nan
    err = _err(main, capsys, ["calibrate", str(_write(tmp_path / "r.csv", m)), *SITE])
    assert "row(s) 8" in err


def test_ellipsoid_on_level_data_suggests_modified(main, field, tmp_path, capsys):
    m, _ = simulate_level_circles(field, C, B, 100.0, np.random.default_rng(7))
    err = _err(main, capsys, ["calibrate", str(_write(tmp_path / "r.csv", m)), "--method", "ellipsoid", *SITE])
    assert "modified-ellipsoid" in err


def test_one_heading_refused(main, field, tmp_path, capsys):
    m = field + B + 100.0 * np.random.default_rng(8).standard_normal((400, 3))
    err = _err(main, capsys, ["calibrate", str(_write(tmp_path / "r.csv", m)), *SITE])
    assert "no rotation coverage" in err


def test_too_few_points(main, field, tmp_path, capsys):
    m, _ = simulate_level_circles(field, C, B, 100.0, np.random.default_rng(9), n_circles=1, n_per_circle=12)
    err = _err(main, capsys, ["calibrate", str(_write(tmp_path / "r.csv", m)), *SITE])
    assert "too few" in err


def test_missing_column_and_file_and_bad_date(main, tmp_path, capsys):
    p = tmp_path / "r.csv"
    p.write_text("t,mx,my\n0,1,2\n")
    assert "missing column 'mz'" in _err(main, capsys, ["calibrate", str(p), *SITE])
    assert "no such file" in _err(main, capsys, ["calibrate", str(tmp_path / "none.csv"), *SITE])
    bad_date = [*SITE[:6], "--date", "11/08/2011"]
    assert "YYYY-MM-DD" in _err(main, capsys, ["calibrate", str(p), *bad_date])


def test_registered_in_dispatcher():
    assert "calibrate" in cli.COMMAND_MODULES


def test_ellipsoid_on_tumbling_data(main, field, tmp_path):
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(10)
    C3 = np.array([[1.05, 0.02, -0.03], [0.02, 0.96, 0.01], [-0.03, 0.01, 1.02]])
    B_b = Rotation.random(800, random_state=rng).apply(field, inverse=True)
    m = B_b @ C3.T + B + 100.0 * rng.standard_normal(B_b.shape)
    out = tmp_path / "cal.json"
    assert (
        main(["calibrate", str(_write(tmp_path / "r.csv", m)), "--method", "ellipsoid", *SITE, "--out", str(out)]) == 0
    )
    cal = MagCalibration.from_json(out)
    np.testing.assert_allclose(cal.A, np.linalg.inv(C3), atol=3e-3)
    np.testing.assert_allclose(cal.b, B, atol=60.0)
    assert cal.after.std_nt < 150.0 < 1000.0 < cal.before.std_nt
