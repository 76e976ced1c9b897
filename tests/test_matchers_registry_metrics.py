"""Registry (config dict -> matcher) and fix metrics (availability, error bins, NEES) against hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest

from magnav_ins.aiding.matchers import (
    KINDS,
    BayesGridMatcher,
    LikelihoodMatcher,
    ParticleFilter,
    PMHTMatcher,
    build_matcher,
    matcher_keys,
)
from magnav_ins.aiding.matchers._local import LocalFrame
from magnav_ins.aiding.matchers.metrics import (
    availability,
    error_bins,
    fix_metrics,
    fix_nees,
    fix_within_3m_fraction,
    no_fix_reasons,
)
from magnav_ins.core.errors import ConfigError
from magnav_ins.core.types import Fix


def test_build_pmht_from_scenario_table():
    m = build_matcher({"kind": "pmht", "batch": 30, "candidates": 20, "iterations": 15})
    assert isinstance(m, PMHTMatcher)
    assert (m.batch, m.candidates, m.iterations, m.name) == (30, 20, 15, "pmht")


@pytest.mark.parametrize(
    ("cfg", "cls", "attr", "value"),
    [
        ({"kind": "ml"}, LikelihoodMatcher, "method", "ml"),
        ({"kind": "mlr", "ratio_threshold": 3}, LikelihoodMatcher, "ratio_threshold", 3.0),
        ({"kind": "abl", "bin_size_m": 2.5}, LikelihoodMatcher, "method", "abl"),
        ({"kind": "bayes_grid", "tail": 0.16}, BayesGridMatcher, "tail", 0.16),
        ({"kind": "particle", "n_particles": 200}, ParticleFilter, "dynamics", "gauss_markov"),
        ({"kind": "particle_ins"}, ParticleFilter, "dynamics", "ins"),
        ({"kind": "pmht", "value_gate": None}, PMHTMatcher, "value_gate", None),
    ],
)
def test_build_each_kind(cfg, cls, attr, value):
    m = build_matcher(cfg)
    assert isinstance(m, cls)
    assert getattr(m, attr) == value


def test_nested_fix_matcher():
    m = build_matcher({"kind": "particle", "measurement": "fix", "fix_matcher": {"kind": "mlr", "min_distance_m": 10}})
    assert m.fix_matcher.method == "mlr" and m.fix_matcher.min_distance_m == 10.0


@pytest.mark.parametrize(
    ("cfg", "needle"),
    [
        ({"kind": "pmt"}, "'pmt'"),
        ({"batch": 3}, "'kind'"),
        ({"kind": "pmht", "batches": 3}, "'batches'"),
        ({"kind": "pmht", "batch": "30"}, "'batch'"),
        ({"kind": "pmht", "batch": 1}, "'batch'"),
        ({"kind": "ml", "method": "abl"}, "'method'"),
        ({"kind": "mlr", "demean": 1}, "'demean'"),
        ({"kind": "particle", "road": "x"}, "'road'"),
        ({"kind": "particle", "fix_matcher": {"kind": "bayes_grid"}}, "'fix_matcher'"),
        ({"kind": "bayes_grid", "tail": 0.7}, "'tail'"),
    ],
)
def test_config_errors_name_the_key(cfg, needle):
    with pytest.raises(ConfigError, match=needle):
        build_matcher(cfg)


def test_matcher_keys_lists_parameters():
    assert "candidates" in matcher_keys("pmht")
    assert "method" not in matcher_keys("mlr")
    assert set(KINDS) == {
        "ml",
        "mlr",
        "abl",
        "pmht",
        "bayes_grid",
        "particle",
        "particle_ins",
        "tercom",
        "iccp",
        "pmf",
        "feature",
    }


# ---------------------------------------------------------------------------------------------- metrics
def _fixes():
    fr = LocalFrame(np.radians(40.0), np.radians(10.0))
    errs = [(1.0, 0.0), (0.0, 5.0), (12.0, 0.0), (0.0, -30.0), (2.0, 2.0)]  # 1, 5, 12, 30, 2.83 m
    sig = [1.0, 5.0, 2.0, 10.0, 2.0]
    fixes = []
    for (dn, de), s in zip(errs, sig, strict=True):
        lat, lon = fr.to_latlon(dn, de)
        fixes.append(Fix(0.0, float(lat), float(lon), np.eye(2) * s**2))
    fixes += [
        Fix.no_fix(0.0, "ambiguous: ratio 1.2"),
        Fix.no_fix(0.0, "flat map: C small"),
        Fix.no_fix(0.0, "ambiguous: x"),
    ]
    truth_lat = np.full(len(fixes), fr.lat0)
    truth_lon = np.full(len(fixes), fr.lon0)
    return fixes, truth_lat, truth_lon


def test_fix_metrics_by_hand():
    fixes, tl, tn = _fixes()
    assert availability(fixes) == pytest.approx(5 / 8)
    bins = error_bins(fixes, tl, tn)
    assert bins == pytest.approx({"lt_3m": 0.4, "3_to_10m": 0.2, "10_to_20m": 0.2, "gt_20m": 0.2}, abs=1e-6)
    assert fix_within_3m_fraction(fixes, tl, tn) == pytest.approx(0.4, abs=1e-6)
    # NEES: (1/1)^2, (5/5)^2, (12/2)^2, (30/10)^2, (2^2 + 2^2)/4
    assert fix_nees(fixes, tl, tn) == pytest.approx([1.0, 1.0, 36.0, 9.0, 2.0], rel=1e-5)
    m = fix_metrics(fixes, tl, tn)
    assert m["fix_nees_mean"] == pytest.approx(49.0 / 5, rel=1e-5)
    assert m["fix_rms_m"] == pytest.approx(np.sqrt((1 + 25 + 144 + 900 + 8) / 5), rel=1e-5)
    assert m["attempts"] == 8 and m["fixes"] == 5
    assert no_fix_reasons(fixes) == {"ambiguous": 2, "flat map": 1}


def test_metrics_need_one_truth_per_fix():
    fixes, tl, tn = _fixes()
    from magnav_ins.core.errors import InputError

    with pytest.raises(InputError, match="one true position per fix"):
        error_bins(fixes, tl[:-1], tn)
