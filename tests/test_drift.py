"""``magnav-ins ins drift``: grade ordering after 30 min, the JSON contract, errors with exit status 2."""

from __future__ import annotations

import json

import numpy as np

from magnav_ins.cli import main

KEYS = {
    "grade",
    "runs",
    "seed",
    "duration_s",
    "sigma_horizontal_m_final",
    "model_sigma_horizontal_m_final",
    "t_s",
    "sigma_horizontal_m",
    "model_sigma_horizontal_m",
}


def _drift(tmp_path, grade, *extra):
    out = tmp_path / grade
    args = ["ins", "drift", "--grade", grade, "--duration", "1800", "--runs", "6", "--rate-hz", "2"]
    args += ["--output-dt", "60", "--out", str(out), "--quiet", *extra]
    assert main(args) == 0
    return json.loads((out / "drift.json").read_text()), out


def test_grades_are_ordered_after_30_min_and_json_has_the_contract(tmp_path):
    finals = {}
    for grade in ("navigation", "tactical", "commercial"):
        doc, out = _drift(tmp_path, grade)
        assert KEYS <= set(doc)
        assert doc["grade"] == grade and doc["runs"] == 6 and doc["seed"] == 1 and doc["duration_s"] == 1800.0
        n = len(doc["t_s"])
        assert n == 31 and len(doc["sigma_horizontal_m"]) == n and len(doc["model_sigma_horizontal_m"]) == n
        assert doc["t_s"][-1] == 1800.0
        assert doc["sigma_horizontal_m_final"] == doc["sigma_horizontal_m"][-1]
        assert (out / "drift.png").stat().st_size > 10_000
        finals[grade] = (doc["sigma_horizontal_m_final"], doc["model_sigma_horizontal_m_final"])
    for k in (0, 1):  # Monte Carlo and model
        assert finals["navigation"][k] < finals["tactical"][k] < finals["commercial"][k]
    # orders of magnitude as Storms Fig. 2.1: navigation grade < 2 km, tactical tens of km after 30 min
    assert finals["navigation"][1] < 2e3 and 1e4 < finals["tactical"][1] < 1e5


def test_same_seed_same_numbers(tmp_path):
    a, _ = _drift(tmp_path / "a", "tactical")
    b, _ = _drift(tmp_path / "b", "tactical")
    c, _ = _drift(tmp_path / "c", "tactical", "--seed", "2")
    assert a["sigma_horizontal_m"] == b["sigma_horizontal_m"]
    assert not np.isclose(a["sigma_horizontal_m_final"], c["sigma_horizontal_m_final"])


def test_bad_input_exits_2_and_names_it(tmp_path, capsys):
    out = tmp_path / "x"
    assert main(["ins", "drift", "--grade", "hg9900", "--out", str(out)]) == 2
    assert "'hg9900'" in capsys.readouterr().err
    for flag, value in (("--runs", "abc"), ("--duration", "-5"), ("--rate-hz", "nan"), ("--runs", "1")):
        assert main(["ins", "drift", "--grade", "tactical", flag, value, "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert flag in err and value in err
    assert not out.exists()
