"""The real-data suite's mechanics (``magnav_ins.studies.suite``) on two short Osborne cases: runs map to cases,
groups pool their cases, a missing survey is a stated skip, and the JSON line has the issue's shape."""

from __future__ import annotations

import json

import numpy as np
import pytest

from magnav_ins.core.errors import ConfigError
from magnav_ins.studies import suite


def test_suite_groups_pool_their_cases(monkeypatch, tmp_path):
    short = (("duration_s", 90.0),)
    cases = [
        suite.Case("osborne_tactical", suite.OSBORNE_SURVEY, suite.OSBORNE_MAP, 10152, 65.0, "tactical",
                   trajectory_keys=short),
        suite.Case("osborne_navigation", suite.OSBORNE_SURVEY, suite.OSBORNE_MAP, 10153, 80.0, "navigation",
                   trajectory_keys=short),
    ]  # fmt: skip
    monkeypatch.setattr(suite, "osborne_cases", lambda quick: cases)
    res = suite.run_suite(seeds=2, rio_survey=tmp_path / "absent.csv.xz")
    assert res.runs == 4 and [c.name for c, _ in res.cases] == [
        "osborne_tactical:10152@65",
        "osborne_navigation:10153@80",
    ]
    assert "not found" in res.groups["rio"]["skipped"]
    names = [e["name"] for e in suite.ESTIMATORS]
    for g in ("osborne_tactical", "osborne_navigation"):
        assert list(res.groups[g]) == names
        for m in res.groups[g].values():
            assert m["runs"] == 2 and m["free_rms_horizontal_m"] > 0
            assert m["median_run_rms_horizontal_m"] > 0
            assert {"rms_horizontal_m", "nees_mean", "fix_nees_mean", "hpl_exceedance", "divergence_rate"} <= set(m)
    # one case per group here: the group figures are that case's
    assert res.groups["osborne_tactical"] == res.cases[0][1]
    line = json.dumps({"groups": res.groups}, allow_nan=False)
    assert set(json.loads(line)["groups"]) == {"osborne_tactical", "osborne_navigation", "rio"}
    assert "osborne_tactical:10152@65" in suite.report(res)


def test_suite_refuses_unknown_groups():
    with pytest.raises(ConfigError, match="unknown suite group"):
        suite.run_suite(only=("osborne",))


def test_suite_command_is_listed_and_refuses_bad_options(capsys):
    from magnav_ins import cli

    assert "suite" in cli.COMMAND_MODULES
    assert cli.main(["suite", "--only", "osborne", "--quiet"]) == 2
    assert "unknown suite group" in capsys.readouterr().err
    assert cli.main(["suite", "--seeds", "0", "--quiet"]) == 2


def test_median_run_rms_is_the_median_of_each_runs_own_rms():
    from magnav_ins.studies.metrics import RunMetrics

    runs = [
        RunMetrics(e=np.array([3.0, 4.0]), nees=np.zeros(2)),  # RMS sqrt(12.5)
        RunMetrics(e=np.array([1.0, np.nan, 1.0]), nees=np.zeros(3)),  # RMS 1 over its finite samples
        RunMetrics(e=np.array([100.0, 100.0, 100.0, 100.0]), nees=np.zeros(4)),  # RMS 100: moves the pooled RMS
        RunMetrics(e=np.array([np.nan]), nees=np.zeros(1)),  # no finite sample: left out
    ]
    assert suite.median_run_rms(runs) == pytest.approx(np.sqrt(12.5))
    assert suite.median_run_rms(runs[3:]) is None


def test_suite_flies_only_the_estimators_asked_for(monkeypatch, tmp_path):
    case = suite.Case("osborne_tactical", suite.OSBORNE_SURVEY, suite.OSBORNE_MAP, 10152, 65.0, "tactical",
                      trajectory_keys=(("duration_s", 60.0),))  # fmt: skip
    res = suite.run_suite(seeds=1, cases=[case], estimators=("pmht+ukf",), rio_survey=tmp_path / "absent.csv.xz")
    assert res.runs == 1 and list(res.groups["osborne_tactical"]) == ["pmht+ukf"]
    assert res.groups["rio"] == {"skipped": "no case"}
    with pytest.raises(ConfigError, match="unknown suite estimator"):
        suite.run_suite(estimators=("pmht",))
