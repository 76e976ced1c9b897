"""A map error that follows the field's gradient (``map_gradient_error_m`` of the likelihood matchers; issue 17).

A map gridded from other (or fewer) lines than the field it is flown over is off by about ``c |grad|``: its features
sit a few metres from where they are (the SITL's world against ``builtin:osborne-magnetic``: 6.5 m times the
gradient over 2000 random sections, ``magnav_ins/mavlink/sitl_flight.py``). Synthetic check against independent
truth: the map is the truth read at positions moved by a smooth random displacement of 1-sigma ``c`` per axis,
so its error is ``grad . u``. With the gradient term the fixes' NEES is honest; without it (the same small uniform
map_sigma) the fixes are over-confident."""

from __future__ import annotations

import json

import numpy as np
import pytest
from matcher_scenarios import KIND_TF, ORIGIN, exact, local, section_trial

from magnav_ins.aiding.matchers import build_matcher
from magnav_ins.core.errors import ConfigError
from magnav_ins.maps.synthetic import gaussian_random_field, random_field_map

SHIFT_M = 4.0  # 1-sigma of the map's displacement per axis, m
SHIFT_ELL_M = 50.0  # its correlation length (1/e lag), m


class _Displaced:
    """What ``section_trial`` needs: the truth the readings come from."""

    def __init__(self, truth) -> None:  # noqa: ANN001
        self.truth = truth


def _displaced_map():
    """(scenario, map): the truth the readings come from and the map moved by the displacement field."""
    rng = np.random.default_rng(11)
    truth = random_field_map((300, 300), 5.0, 40.0, 100.0, rng, kind=KIND_TF, origin=ORIGIN)
    n_ax, e_ax = truth.axes
    gn, ge = np.meshgrid(n_ax, e_ax, indexing="ij")
    un = gaussian_random_field(gn.shape, 5.0, SHIFT_ELL_M / np.sqrt(2.0), SHIFT_M, rng)
    ue = gaussian_random_field(gn.shape, 5.0, SHIFT_ELL_M / np.sqrt(2.0), SHIFT_M, rng)
    lat, lon = truth.from_local(gn + un, ge + ue)
    moved = np.asarray(truth.value(lat, lon), float)
    moved = np.where(np.isfinite(moved), moved, np.asarray(truth.values))  # the border: unmoved
    return _Displaced(exact(truth)), truth.with_values(moved)


@pytest.fixture(scope="module")
def displaced_map():
    return _displaced_map()


def _fix_nees(config: dict, scenario, fmap, trials: int = 40) -> tuple[float, int]:
    m = build_matcher({"kind": "ml", **config})
    rng = np.random.default_rng(2)
    out = []
    for _ in range(trials):
        fix, truth_ne = section_trial(m, scenario, fmap, rng)
        if fix.available:
            d = local(fmap, fix.lat, fix.lon) - truth_ne
            out.append(float(d @ np.linalg.solve(fix.cov_ne, d)) / 2.0)
    return float(np.mean(out)), len(out)


def test_gradient_error_makes_fixes_on_a_displaced_map_honest(displaced_map):
    scenario, fmap = displaced_map
    base = {"map_sigma": 0.5, "map_correlation_m": SHIFT_ELL_M, "level_sigma": 0.0}
    with_term, n1 = _fix_nees({**base, "map_gradient_error_m": SHIFT_M}, scenario, fmap)
    without, n2 = _fix_nees(base, scenario, fmap)
    assert n1 >= 28 and n2 >= 28
    assert 0.3 <= with_term <= 2.0, (with_term, without)
    assert without > 3.0, (with_term, without)


def test_gradient_error_option_validated_and_off_by_default():
    assert build_matcher({"kind": "ml"}).map_gradient_error_m == 0.0
    with pytest.raises(ConfigError):
        build_matcher({"kind": "ml", "map_gradient_error_m": -1.0})


def test_sitl_bridge_is_told_the_measured_map_error_model(tmp_path):
    from magnav_ins.mavlink.sitl_flight import (
        SITL_MAP_CORRELATION_M,
        SITL_MAP_GRADIENT_ERROR_M,
        SITL_MAP_SIGMA_NT,
        FlightPlan,
        bridge_command,
    )

    cmd = bridge_command(FlightPlan(map_sigma_nt=SITL_MAP_SIGMA_NT), 14550, tmp_path / "s.json", tmp_path / "t.csv")
    matcher = json.loads(cmd[cmd.index("--matcher") + 1])
    assert matcher["map_sigma"] == SITL_MAP_SIGMA_NT
    assert matcher["map_gradient_error_m"] == SITL_MAP_GRADIENT_ERROR_M > 0
    assert matcher["map_correlation_m"] == SITL_MAP_CORRELATION_M > 0
    build_matcher(matcher)  # a valid configuration
