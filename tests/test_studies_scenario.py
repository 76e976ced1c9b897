"""Scenario validation: errors name the key and its line; defaults; path resolution; the shipped examples."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from magnav_ins.core.errors import ConfigError
from magnav_ins.core.types import FieldKind
from magnav_ins.studies.scenario import load_scenario, locate_keys

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "scenarios"

GOOD = """\
name = "tiny"
seed = 3
runs = 2

[trajectory]
kind = "great_circle"
start = [-38.0, 144.5]
end = [-37.9, 144.6]
altitude_m = 100.0
speed_mps = 22.0
duration_s = 60.0

[imu]
grade = "tactical"
rate_hz = 50.0

[map]
path = "synthetic:random_field"
kind = "gravity_disturbance_mgal"

[sensor]
kind = "gravimeter"
sigma = 1.0
interval_s = 10.0

[[estimator]]
name = "ml+ukf"
matcher = { kind = "ml", ratio_threshold = 2.5 }
fusion = { kind = "ukf" }

[[estimator]]
name = "pmht"
matcher = { kind = "pmht", batch = 30 }
fusion = { kind = "ukf" }
"""


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "s.toml"
    p.write_text(text)
    return p


def _line_of(text: str, needle: str) -> int:
    return next(i for i, line in enumerate(text.splitlines(), 1) if needle in line)


def test_good_scenario_and_defaults(tmp_path):
    sc = load_scenario(_write(tmp_path, GOOD))
    assert sc.name == "tiny" and sc.seed == 3 and sc.runs == 2
    assert sc.trajectory.start_deg == (-38.0, 144.5) and sc.trajectory.duration_s == 60.0
    assert sc.imu.grade == "tactical" and sc.imu.rate_hz == 50.0
    assert sc.init.position_sigma_m == 10.0 and sc.init.attitude_sigma_deg == (0.02, 0.02, 0.2)  # DESIGN defaults
    assert sc.map.kind is FieldKind.GRAVITY_DISTURBANCE_MGAL
    assert [e.name for e in sc.estimators] == ["ml+ukf", "pmht"]
    assert sc.estimators[1].matcher == {"kind": "pmht", "batch": 30}
    assert sc.lines["estimator[1].matcher.batch"] == _line_of(GOOD, "batch = 30")


@pytest.mark.parametrize(
    ("old", "new", "key", "needle"),
    [
        ("speed_mps = 22.0", "sped_mps = 22.0", "trajectory.sped_mps", "sped_mps"),  # unknown key
        ('grade = "tactical"', "grade = 3", "imu.grade", "grade = 3"),  # wrong type
        ("sigma = 1.0", 'sigma = "1 mGal"', "sensor.sigma", "sigma = "),  # units in the value, not the key
        ("sigma = 1.0", "sigma = -1.0", "sensor.sigma", "sigma = "),  # out of range
        ("batch = 30 }", "batch = 30 }\ncolour = 2", "estimator[1].colour", "colour = 2"),
        ("batch = 30 }", "batch = 30, bogus = 1 }", "estimator[1].matcher.bogus", "bogus = 1"),  # registry keys
        ("batch = 30 }", 'batch = "thirty" }', "estimator[1].matcher", "thirty"),  # registry types
        ('kind = "pmht"', 'kind = "pmhtt"', "estimator[1].matcher.kind", "pmhtt"),
        ('fusion = { kind = "ukf" }\n\n[[', 'fusion = { kind = "ekf" }\n\n[[', "estimator[0].fusion.kind", "ekf"),
        ("rate_hz = 50.0", "rate_hz = 50.0\nrate_ft = 2", "imu.rate_ft", "rate_ft"),
        ("start = [-38.0, 144.5]", "start = [-138.0, 144.5]", "trajectory.start", "start = "),
        ('kind = "gravimeter"', 'kind = "scalar_magnetometer"', "sensor.kind", "scalar_magnetometer"),
    ],
)
def test_errors_name_key_and_line(tmp_path, old, new, key, needle):
    text = GOOD.replace(old, new, 1)
    with pytest.raises(ConfigError) as ei:
        load_scenario(_write(tmp_path, text))
    msg = str(ei.value)
    assert f"'{key}'" in msg, msg
    assert f"line {_line_of(text, needle)}" in msg, msg
    assert "s.toml" in msg


def test_missing_key_names_key_and_table_line(tmp_path):
    text = GOOD.replace("speed_mps = 22.0\n", "")
    with pytest.raises(ConfigError) as ei:
        load_scenario(_write(tmp_path, text))
    msg = str(ei.value)
    assert "trajectory.speed_mps" in msg and "missing" in msg
    assert f"line {_line_of(text, '[trajectory]')}" in msg


def test_missing_file_names_key_and_line(tmp_path):
    text = GOOD.replace('"synthetic:random_field"', '"no_such_map.nc"')
    with pytest.raises(ConfigError) as ei:
        load_scenario(_write(tmp_path, text))
    msg = str(ei.value)
    assert "'map.path'" in msg and f"line {_line_of(text, 'no_such_map')}" in msg
    assert str(tmp_path / "no_such_map.nc") in msg  # resolved against the scenario's folder


def test_relative_path_resolves_against_scenario_dir(tmp_path):
    (tmp_path / "maps").mkdir()
    (tmp_path / "maps" / "m.nc").write_bytes(b"")
    sc = load_scenario(_write(tmp_path, GOOD.replace('"synthetic:random_field"', '"maps/m.nc"')))
    assert Path(sc.map.path) == (tmp_path / "maps" / "m.nc").resolve()


def test_missing_scenario_file_and_bad_toml(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_scenario(tmp_path / "nope.toml")
    with pytest.raises(ConfigError, match=r"line 2"):
        load_scenario(_write(tmp_path, 'name = "x"\nruns = = 2\n'))


def test_reserved_and_duplicate_names(tmp_path):
    with pytest.raises(ConfigError, match=r"line \d+.*reserved"):
        load_scenario(_write(tmp_path, GOOD.replace('name = "pmht"', 'name = "free_inertial"')))
    with pytest.raises(ConfigError, match="duplicate"):
        load_scenario(_write(tmp_path, GOOD.replace('name = "pmht"', 'name = "ml+ukf"')))


def test_locate_keys_scan():
    text = 'a = 1\n[t]  # comment [x]\nb = "[not a header]"\nc = [\n  1,\n  2,\n]\n"q k" = 2\n[[e]]\nm = { kind = "x", n = 2 }\n[[e]]\nm = 1\n'
    lines = locate_keys(text)
    assert lines["a"] == 1 and lines["t"] == 2 and lines["t.b"] == 3 and lines["t.c"] == 4
    assert lines["t.q k"] == 8
    assert lines["e[0]"] == 9 and lines["e[0].m.kind"] == 10 and lines["e[0].m.n"] == 10 and lines["e[1].m"] == 12


@pytest.mark.parametrize("path", sorted(EXAMPLES.glob("*.toml")), ids=lambda p: p.name)
def test_examples_validate(path):
    if (
        re.search(r"fatiando|\.\./\.\./\.\./shared", path.read_text())
        and not (Path(__file__).resolve().parents[2] / "shared" / "data").is_dir()
    ):
        pytest.skip("needs ../shared/data")
    sc = load_scenario(path)
    assert sc.estimators or "drift" in path.name


# ---------------------------------------------------------------------------------- per-estimator IMU grade (issue 8)
DRIFT = """\
name = "grades"

[trajectory]
kind = "great_circle"
start = [-35.0, 149.0]
end = [-35.0, 152.0]
altitude_m = 1000.0
speed_mps = 100.0

[imu]
grade = "tactical"

[[estimator]]
name = "nav"
imu_grade = "navigation"
fusion = { kind = "free_inertial" }
"""


def test_free_inertial_estimator_of_another_grade_needs_no_matcher_map_or_sensor(tmp_path):
    sc = load_scenario(_write(tmp_path, DRIFT))
    (est,) = sc.estimators
    assert est.imu_grade == "navigation" and est.matcher is None and est.matcher_kind is None
    assert est.fusion_kind == "free_inertial" and sc.imu.grade == "tactical"
    assert sc.map is None and sc.sensor is None
    good = load_scenario(_write(tmp_path, GOOD))
    assert all(e.imu_grade is None for e in good.estimators)  # default: the [imu] grade


@pytest.mark.parametrize(
    ("text", "old", "new", "key", "needle", "match"),
    [
        (DRIFT, 'imu_grade = "navigation"', 'imu_grade = "nav-grade"', "estimator[0].imu_grade", "nav-grade", "one of"),
        (DRIFT, 'imu_grade = "navigation"', "imu_grade = 2", "estimator[0].imu_grade", "imu_grade = 2", "string"),
        (DRIFT, 'kind = "free_inertial"', 'kind = "ukf"', "estimator[0].matcher", "[[estimator]]", "missing"),
        (DRIFT, 'imu_grade = "navigation"', "window = 3", "estimator[0].window", "window = 3", "needs a matcher"),
        (
            GOOD,
            'name = "pmht"',
            'name = "pmht"\nimu_grade = "quantumm"',
            "estimator[1].imu_grade",
            "quantumm",
            "one of",
        ),
    ],
)
def test_imu_grade_and_optional_matcher_errors_name_key_and_line(tmp_path, text, old, new, key, needle, match):
    text = text.replace(old, new, 1)
    with pytest.raises(ConfigError) as ei:
        load_scenario(_write(tmp_path, text))
    msg = str(ei.value)
    assert key in msg and match in msg, msg
    assert f"line {_line_of(text, needle)}" in msg, msg


def test_matcher_is_still_required_by_an_aided_fuser_with_a_map(tmp_path):
    text = GOOD.replace('matcher = { kind = "ml", ratio_threshold = 2.5 }\n', "")
    with pytest.raises(ConfigError, match=r"missing key 'estimator\[0\]\.matcher'"):
        load_scenario(_write(tmp_path, text))
    # a matcher-less free-inertial estimator beside aided ones is fine
    sc = load_scenario(
        _write(tmp_path, text.replace('fusion = { kind = "ukf" }', 'fusion = { kind = "free_inertial" }', 1))
    )
    assert sc.estimators[0].matcher is None and sc.estimators[1].matcher_kind == "pmht"


# ---------------------------------------------------------------------------------- ranges at the edge (issue 18)
@pytest.mark.parametrize(
    ("old", "new", "key", "match"),
    [
        ("rate_hz = 50.0", "rate_hz = 1e9", "imu.rate_hz", r"out of range; expected \[1, 2000\]"),
        ("rate_hz = 50.0", "rate_hz = 0.001", "imu.rate_hz", r"out of range; expected \[1, 2000\]"),
        ("speed_mps = 22.0", "speed_mps = 0.0", "trajectory.speed_mps", "positive"),
        ("speed_mps = 22.0", "speed_mps = 1e5", "trajectory.speed_mps", r"\(0, 3000\]"),
        ("altitude_m = 100.0", "altitude_m = 1e7", "trajectory.altitude_m", r"\[-11000, 100000\]"),
        ("duration_s = 60.0", "duration_s = 1e12", "trajectory.duration_s", "out of range"),
        ("runs = 2", "runs = 10000000", "runs", r"\[1, 100000\]"),
        ("interval_s = 10.0", "interval_s = 0.001", "sensor.interval_s", "shorter than one IMU period"),
        ("sigma = 1.0", "sigma = 5000.0", "sensor.sigma", "implausible for a gravimeter"),
        ("window = 1", "window = 0", "estimator[0].window", ">= 1"),
    ],
)
def test_out_of_range_values_name_the_key(tmp_path, old, new, key, match):
    text = GOOD.replace('fusion = { kind = "ukf" }', 'fusion = { kind = "ukf" }\nwindow = 1', 1).replace(old, new, 1)
    assert text != GOOD
    with pytest.raises(ConfigError, match=match) as ei:
        load_scenario(_write(tmp_path, text))
    assert f"'{key}'" in str(ei.value) and "s.toml line " in str(ei.value)


def test_samples_per_run_limit_names_rate_and_duration(tmp_path):
    # 3 deg of longitude at 22 m/s is about 3.4 h: at 2000 Hz that is 2.4e7 samples, above the 2e7 limit
    text = GOOD.replace("end = [-37.9, 144.6]", "end = [-37.9, 148.0]").replace("duration_s = 60.0\n", "")
    with pytest.raises(ConfigError, match=r"'imu\.rate_hz'.*IMU samples per run.*duration_s"):
        load_scenario(_write(tmp_path, text.replace("rate_hz = 50.0", "rate_hz = 2000.0")))
    assert load_scenario(_write(tmp_path, text)).imu.rate_hz == 50.0  # 6e5 samples: fine


def test_attitude_sigma_range(tmp_path):
    text = GOOD.replace("[map]", "[init]\nattitude_sigma_deg = [0.1, 0.1, 45.0]\n\n[map]")
    with pytest.raises(ConfigError, match=r"'init\.attitude_sigma_deg'.*\[0, 30\]"):
        load_scenario(_write(tmp_path, text))


# ---------------------------------------------------------------------------------- the documented schema (issue 18)
def _accepted_keys(data: dict, table: str) -> set[str]:
    """The keys the validator accepts in ``table`` of ``data``: read from its unknown-key error."""
    import copy

    from magnav_ins.studies.scenario import scenario_from_dict

    d = copy.deepcopy(data)
    target = d if table == "" else (d["estimator"][0] if table == "estimator" else d[table])
    target["zz_not_a_key"] = 1
    with pytest.raises(ConfigError, match="unknown key") as ei:
        scenario_from_dict(d)
    m = re.search(r"expected one of:? \[?([^\]\)]*)", str(ei.value))
    assert m, str(ei.value)
    return {k.strip(" '\"") for k in m.group(1).split(",")}


def test_schema_documents_every_accepted_key():
    """SCHEMA (and so docs/scenarios.md) lists exactly the keys the validator accepts, per table and trajectory
    kind. A key added to a validator needs its ScenarioKey line in studies/scenario.py (then regenerate the docs)."""
    import tomllib

    from magnav_ins.studies.scenario import SCHEMA, TRAJECTORY_KINDS

    data = tomllib.loads(GOOD)
    for table in ("", "imu", "map", "sensor", "estimator"):
        documented = {k.name for k in SCHEMA if k.table == table}
        assert _accepted_keys(data, table) == documented, f"[{table or 'top level'}]"
    data["init"] = {}
    assert _accepted_keys(data, "init") == {k.name for k in SCHEMA if k.table == "init"}
    for kind in TRAJECTORY_KINDS:
        data["trajectory"] = {"kind": kind}
        documented = {k.name for k in SCHEMA if k.table == "trajectory" and (not k.kinds or kind in k.kinds)}
        assert _accepted_keys(data, "trajectory") == documented, f"[trajectory] kind = {kind!r}"


def test_docs_scenarios_md_is_generated_from_the_schema():
    from magnav_ins.studies.scenario_doc import schema_markdown

    doc = Path(__file__).resolve().parents[1] / "docs" / "scenarios.md"
    assert doc.read_text(encoding="utf-8") == schema_markdown(), (
        "docs/scenarios.md is out of date: python -m magnav_ins.studies.scenario_doc > docs/scenarios.md"
    )


def test_docs_example_validates(tmp_path):
    from magnav_ins.studies.scenario_doc import _EXAMPLE

    sc = load_scenario(_write(tmp_path, _EXAMPLE))
    assert sc.estimators[0].matcher_kind == "pmht" and sc.imu.rate_hz == 100.0
