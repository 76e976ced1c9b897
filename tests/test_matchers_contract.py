"""Contract tests run against every matcher (batch and recursive) on synthetic maps with known truth.

NEES band: for a consistent 2-D fix the NEES is chi-square with 2 degrees of freedom (mean 2, sd 2). Over the
K = 40 trials of a run the sample mean has a standard deviation of 2 / sqrt(40) = 0.32 if the covariance is right,
so a band of [1, 4] is about -3 / +6 of those sigmas: it accepts covariances mis-scaled by less than a factor of 2
either way and fails anything worse (e.g. the quantisation-blind ML scan that gave a mean of ~100, or a particle
filter inflated by roughening at ~0.6), while leaving room for the heavier tails a real matcher has (a wrong peak
that its covariance only partly covers).
"""

from __future__ import annotations

import numpy as np
import pytest
from matcher_scenarios import SCENARIOS, flat_like, local

from magnav_ins.aiding.matchers import RECURSIVE_KINDS, build_matcher
from magnav_ins.core.types import Fix

K_TRIALS = 40


@pytest.fixture(params=sorted(SCENARIOS))
def scenario(request):
    kind = request.param
    sc = SCENARIOS[kind]
    fmap = sc.build_map(np.random.default_rng(11))
    return kind, sc, fmap


def test_protocol_methods(scenario):
    kind, sc, _ = scenario
    m = build_matcher(sc.config)
    if kind in RECURSIVE_KINDS:
        for meth in ("initiate", "predict", "update", "to_fix"):
            assert callable(getattr(m, meth))
    else:
        assert callable(m.match)
    assert m.name == kind


def test_fix_nees_consistent(scenario):
    kind, sc, fmap = scenario
    m = build_matcher(sc.config)
    rng = np.random.default_rng(2)
    nees, errs, issued = [], [], 0
    for _ in range(K_TRIALS):
        fix, truth = sc.trial(m, fmap, rng, "normal")
        assert isinstance(fix, Fix)
        if not fix.available:
            assert fix.reason
            continue
        issued += 1
        P = np.asarray(fix.cov_ne)
        assert P.shape == (2, 2) and np.allclose(P, P.T) and np.all(np.linalg.eigvalsh(P) > 0)
        d = local(fmap, fix.lat, fix.lon) - truth
        nees.append(float(d @ np.linalg.solve(P, d)))
        errs.append(float(np.hypot(*d)))
    assert issued >= 0.8 * K_TRIALS, f"{kind}: only {issued} fixes in {K_TRIALS} trials"
    mean_nees = float(np.mean(nees))
    assert 1.0 <= mean_nees <= 4.0, f"{kind}: fix NEES mean {mean_nees:.2f} outside [1, 4]"
    # and the fixes are useful: median error well inside the prior sigma of the scenario (>= 15 m). A particle
    # filter's fix is an increment (the readings' evidence alone, the prior divided out), not a posterior that
    # still holds the prior: half the prior sigma for those, a third for the others.
    limit = 7.5 if kind in ("particle", "particle_ins") else 5.0
    assert np.median(errs) < limit, f"{kind}: median fix error {np.median(errs):.2f} m"


def test_no_fix_off_the_map(scenario):
    kind, sc, fmap = scenario
    m = build_matcher(sc.config)
    fix, _ = sc.trial(m, fmap, np.random.default_rng(3), "off_map")
    assert not fix.available
    assert "off the map" in fix.reason, fix.reason


def test_no_fix_on_flat_map(scenario):
    kind, sc, fmap = scenario
    m = build_matcher(sc.config)
    fix, _ = sc.trial(m, flat_like(fmap), np.random.default_rng(4), "normal")
    assert not fix.available
    assert "flat map" in fix.reason, fix.reason


def test_nan_readings_give_no_fix_not_exception(scenario):
    kind, sc, fmap = scenario
    m = build_matcher(sc.config)
    fix, _ = sc.trial(m, fmap, np.random.default_rng(5), "nan")
    assert not fix.available
    assert "nan" in fix.reason.lower(), fix.reason
