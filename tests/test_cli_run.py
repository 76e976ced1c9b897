"""``magnav-ins run``: a tiny free-inertial scenario end to end, overrides, and user errors -> exit status 2."""

from __future__ import annotations

import argparse
import json

import pytest

from magnav_ins.commands import run as run_cmd

TINY = """\
name = "tiny_drift"
seed = 5
runs = 3

[trajectory]
kind = "great_circle"
start = [-35.0, 149.0]
end = [-35.0, 149.5]
altitude_m = 500.0
speed_mps = 50.0
duration_s = 30.0

[imu]
grade = "tactical"
rate_hz = 10.0
"""


def _main(argv: list[str]) -> int:
    """The dispatcher's behaviour for this command only (independent of other command groups)."""
    from magnav_ins.core.errors import MagnavError

    parser = argparse.ArgumentParser(prog="magnav-ins")
    sub = parser.add_subparsers(dest="command", required=True)
    run_cmd.add_parser(sub)
    args = parser.parse_args(argv)
    try:
        return args.handler(args)
    except MagnavError as exc:
        print(f"magnav-ins: error: {exc}")
        return 2


def test_run_tiny_drift(tmp_path, capsys):
    sc = tmp_path / "tiny.toml"
    sc.write_text(TINY)
    out = tmp_path / "out"
    assert _main(["run", str(sc), "--out", str(out), "--runs", "2", "--quiet"]) == 0
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["runs"] == 2 and doc["seed"] == 5 and doc["estimators"] == {}
    fi = doc["free_inertial"]
    # 30 s of tactical-grade drift from 10 m initial position sigma: metres to hundreds of metres, not zero
    assert 1.0 < fi["rms_horizontal_m"] < 1000.0
    assert fi["max_horizontal_m"] >= fi["rms_horizontal_m"] >= 0.0
    assert (out / "free_inertial.png").stat().st_size > 0
    assert "free_inertial" in capsys.readouterr().out
    # the same seed reproduces the numbers exactly; --jobs does not change them
    out2 = tmp_path / "out2"
    assert _main(["run", str(sc), "--out", str(out2), "--runs", "2", "--jobs", "2", "--quiet", "--no-plots"]) == 0
    doc2 = json.loads((out2 / "metrics.json").read_text())
    assert doc2["free_inertial"] == fi


def test_run_user_errors_exit_2(tmp_path, capsys):
    sc = tmp_path / "bad.toml"
    sc.write_text(TINY.replace("rate_hz = 10.0", 'rate_hz = "fast"'))
    assert _main(["run", str(sc), "--out", str(tmp_path / "o")]) == 2
    msg = capsys.readouterr().out
    assert "'imu.rate_hz'" in msg and "line 15" in msg
    assert not (tmp_path / "o").exists()
    assert _main(["run", str(tmp_path / "missing.toml")]) == 2
    good = tmp_path / "good.toml"
    good.write_text(TINY)
    assert _main(["run", str(good), "--runs", "0", "--out", str(tmp_path / "o")]) == 2
    assert _main(["run", str(good), "--duration", "-5", "--out", str(tmp_path / "o")]) == 2
    assert "--duration" in capsys.readouterr().out
    assert not (tmp_path / "o").exists()


def test_cli_registers_run():
    cli = pytest.importorskip("magnav_ins.cli")
    assert "run" in cli.COMMAND_MODULES


OFF_MAP = """\
name = "radians_as_degrees"
seed = 1
runs = 1

[trajectory]
kind = "great_circle"
start = [-0.6632, 2.5220]   # -38.0, 144.5 deg written in radians
end = [-0.6630, 2.5224]
altitude_m = 10000.0
speed_mps = 100.0
duration_s = 20.0

[imu]
grade = "tactical"
rate_hz = 10.0

[map]
path = "builtin:eigen6c4-australia-se"
kind = "gravity_disturbance_mgal"

[sensor]
kind = "gravimeter"
sigma = 1.0
interval_s = 1.0

[[estimator]]
name = "mlr+ukf"
matcher = { kind = "mlr" }
fusion = { kind = "ukf" }
"""


def test_trajectory_off_the_map_is_said(tmp_path, capsys):
    """A study that can never get a fix still runs, but says why, on the terminal and in metrics.json / report.md
    (it used to exit 0 with 0 fix attempts and no word)."""
    from magnav_ins.cli import main

    sc = tmp_path / "off.toml"
    sc.write_text(OFF_MAP)
    out = tmp_path / "out"
    assert main(["run", str(sc), "--out", str(out), "--quiet", "--no-plots"]) == 0
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("magnav-ins: warning: ")]
    assert len(err) == 2, err
    assert "'trajectory'" in err[0] and "never crosses the map builtin:eigen6c4-australia-se" in err[0]
    assert "radians written as degrees?" in err[0]
    assert "estimator 'mlr+ukf': no fix attempt" in err[1]
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["estimators"]["mlr+ukf"]["fix_attempts"] == 0
    assert [f"magnav-ins: warning: {w}" for w in doc["warnings"]] == err
    assert all(w in (out / "report.md").read_text() for w in doc["warnings"])
