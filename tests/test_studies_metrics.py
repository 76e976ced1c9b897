"""Study metrics against hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest

from magnav_ins.core.frames import meters_to_latlon
from magnav_ins.studies import metrics as M


def test_ne_errors_and_horizontal_error_round_trip():
    lat0 = np.full(3, np.deg2rad(-35.0))
    lon0 = np.full(3, np.deg2rad(149.0))
    dn_true = np.array([3.0, 0.0, -4.0])
    de_true = np.array([4.0, -5.0, 3.0])
    dlat, dlon = meters_to_latlon(dn_true, de_true, lat0)
    dn, de = M.ne_errors(lat0 + dlat, lon0 + dlon, lat0, lon0)
    assert np.allclose(dn, dn_true, atol=1e-6) and np.allclose(de, de_true, atol=1e-6)
    assert np.allclose(M.horizontal_errors(lat0 + dlat, lon0 + dlon, lat0, lon0), 5.0, atol=1e-6)


def test_nees_hand_computed():
    # P = [[4, 0], [0, 9]], d = (2, 3) -> 4/4 + 9/9 = 2; correlated P = [[2, 1], [1, 2]], d = (1, 1) -> 2/3
    P = np.array([[[4.0, 0.0], [0.0, 9.0]], [[2.0, 1.0], [1.0, 2.0]], [[1.0, 0.0], [0.0, -1.0]]])
    q = M.nees_ne([2.0, 1.0, 1.0], [3.0, 1.0, 1.0], P)
    assert q[0] == pytest.approx(2.0)
    assert q[1] == pytest.approx(2.0 / 3.0)
    assert np.isnan(q[2])  # not positive definite


def test_sigma_h():
    assert M.sigma_h_m(np.diag([9.0, 16.0])[None])[0] == pytest.approx(5.0)


def test_fix_error_bins_hand_computed():
    bins = M.fix_error_bins([1.0, 2.9, 3.0, 9.9, 15.0, 20.0, 100.0, np.nan])
    assert bins == {"lt_3m": 2 / 7, "3_to_10m": 2 / 7, "10_to_20m": 1 / 7, "ge_20m": 2 / 7}
    assert all(np.isnan(v) for v in M.fix_error_bins([]).values())


def test_divergence_test():
    n = 400
    t = np.arange(n, dtype=float)
    free = 0.01 * t**2  # quadratic drift
    bounded = 5.0 + np.sin(t)  # settled
    growing = 0.02 * t**2  # grows, as bad as free inertial
    slow = 0.001 * t**2  # grows but stays < half the free-inertial error
    assert not M.is_divergent(bounded, free)
    assert M.is_divergent(growing, free)
    assert not M.is_divergent(slow, free)
    assert M.is_divergent(free, free)
    bad = bounded.copy()
    bad[-1] = np.nan
    assert M.is_divergent(bad, free)


def test_filter_divergence_is_the_error_leaving_its_covariance():
    """The NEES test (module docstring): a run whose error grows with a covariance that grows as fast (an aided run
    without late fixes, following free inertial honestly) is not divergent, though Wang's error-growth test flags
    it; one whose last-quarter NEES mean exceeds chi-square(2)'s 99 % point (9.21) is. A consistent filter's NEES
    (chi-square(2) draws, 200 runs of 40 epochs) is flagged in at most 1 % of runs."""
    assert M.NEES_DIVERGENCE_BOUND == pytest.approx(9.2103, abs=1e-4)
    t = np.linspace(0.0, 1.0, 40)
    growing = 10.0 + 1000.0 * t**2
    free = 10.0 + 1200.0 * t**2
    honest = np.full(40, 2.0)  # error and covariance grow together
    assert M.is_divergent(growing, free) and not M.is_nees_divergent(honest)
    leaving = np.r_[np.full(30, 2.0), np.full(10, 12.0)]
    assert M.is_nees_divergent(leaving)
    assert M.is_nees_divergent(np.full(40, np.nan)) is None
    rng = np.random.default_rng(3)
    flags = [M.is_nees_divergent(rng.chisquare(2, 40)) for _ in range(200)]
    assert np.mean(flags) <= 0.01
    runs = [M.RunMetrics(growing, honest, divergent=True), M.RunMetrics(growing, leaving, divergent=True)]
    a = M.aggregate(runs, "ml", "ukf")
    assert a["divergence_rate"] == 1.0 and a["nees_divergence_rate"] == 0.5
    assert M.aggregate([M.RunMetrics(growing, np.full(40, np.nan))], None, "free")["nees_divergence_rate"] is None


def test_aggregate_hand_computed():
    r1 = M.RunMetrics(np.array([3.0, 4.0]), np.array([1.0, 3.0]), np.array([1.0, 5.0]), 4, False)
    r2 = M.RunMetrics(np.array([0.0, 12.0]), np.array([np.nan, 2.0]), np.array([25.0]), 2, True)
    a = M.aggregate([r1, r2], "ml", "ukf")
    assert a["rms_horizontal_m"] == pytest.approx(np.sqrt((9 + 16 + 0 + 144) / 4))
    assert a["mean_horizontal_m"] == pytest.approx(19 / 4)
    assert a["max_horizontal_m"] == 12.0
    assert a["final_horizontal_m"] == pytest.approx(np.sqrt((16 + 144) / 2))
    assert a["divergence_rate"] == 0.5
    assert a["availability"] == pytest.approx(3 / 6)
    assert a["nees_mean"] == pytest.approx(2.0)
    assert a["fix_within_3m_fraction"] == pytest.approx(1 / 3)
    assert a["fix_error_bins"]["3_to_10m"] == pytest.approx(1 / 3)
    assert a["fix_error_bins"]["ge_20m"] == pytest.approx(1 / 3)
    assert a["matcher"] == "ml" and a["fusion"] == "ukf"


def test_hpl_statistics_and_fix_nees_hand_computed():
    e = np.array([1.0, 5.0, 3.0, np.inf, 2.0])
    h = np.array([2.0, 4.0, 3.0, 10.0, np.nan])
    med, exc = M.hpl_statistics(e, h)
    # HPL finite on 4 samples (median of 2, 4, 3, 10 = 3.5); exceeded by 5 > 4 and by the blown-up inf: 2 of 4
    assert med == pytest.approx(3.5) and exc == pytest.approx(0.5)
    assert M.hpl_statistics(e, np.full(5, np.nan)) == (None, None)
    runs = [
        M.RunMetrics(e=np.array([1.0, 2.0]), nees=np.array([2.0, 2.0]), hpl_m=np.array([3.0, 1.0]),
                     fix_nees=np.array([1.0, 3.0])),
        M.RunMetrics(e=np.array([1.0, 2.0]), nees=np.array([2.0, 2.0]), fix_nees=np.array([5.0])),
    ]  # fmt: skip
    m = M.aggregate(runs, "ml", "ukf")
    # the second run has no protection level: only the first one's two samples count
    assert m["hpl_median_m"] == pytest.approx(2.0) and m["hpl_exceedance"] == pytest.approx(0.5)
    assert m["fix_nees_mean"] == pytest.approx(3.0)
