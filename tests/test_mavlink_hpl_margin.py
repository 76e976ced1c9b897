"""The HPL's fault margin on a bridge flight: the faults of older fixes folded into one matrix that bounds each.

On SITL run 29's recording (played back, ``magnav_ins.mavlink.playback``) the bridge's HPL went above its 500 m
limit 326 s into the GNSS-denied leg, the error never above 0.26 of it. Per output: ``K sigma`` (3.72 sigma at
the 1e-3 risk) was 56 % of it, the fault margin 44 %. The margin's largest matrix was the fold of the faults older
than the last eight fixes (the GNSS-aided fixes and the first map fixes), which was their *sum*: 1.4-2.7 times the
largest single fault among them (all faults kept: 10 m instead of 27 m 120 s into the denied leg, 206 m instead of
316 m at 400 s). :func:`~magnav_ins.aiding.fusion.integrity.common_bound` folds them into a Loewner bound of each
instead, within 1.4 times of the exact margin there and equal to it from 200 s on, with the same memory.
"""

from __future__ import annotations

import numpy as np
import pytest

from magnav_ins.aiding.fusion import integrity
from magnav_ins.aiding.fusion.integrity import common_bound, fault_margin, fault_update


def _psd(rng: np.random.Generator, n: int, rank: int) -> np.ndarray:
    G = rng.normal(size=(n, rank)) * rng.uniform(0.1, 10.0, size=rank)
    return G @ G.T


def _min_eig(M: np.ndarray) -> float:
    return float(np.linalg.eigvalsh(0.5 * (M + M.T)).min())


@pytest.mark.parametrize("seed", range(6))
def test_common_bound_is_above_each_and_below_the_sum(seed):
    rng = np.random.default_rng(seed)
    n = 9
    for rank_a, rank_b in ((9, 9), (2, 3), (1, 1), (3, 9)):
        A, B = _psd(rng, n, rank_a), _psd(rng, n, rank_b)
        X = common_bound(A, B)
        scale = float(np.trace(A + B))
        assert _min_eig(X - A) >= -1e-9 * scale
        assert _min_eig(X - B) >= -1e-9 * scale
        assert _min_eig(A + B - X) >= -1e-9 * scale


def test_common_bound_is_the_larger_when_one_is_a_multiple_and_the_sum_when_orthogonal():
    rng = np.random.default_rng(7)
    A = _psd(rng, 5, 2)
    np.testing.assert_allclose(common_bound(A, 0.3 * A), A, atol=1e-9 * np.trace(A))
    np.testing.assert_allclose(common_bound(0.3 * A, A), A, atol=1e-9 * np.trace(A))
    D1, D2 = np.diag([4.0, 0.0, 0.0]), np.diag([0.0, 9.0, 1.0])
    np.testing.assert_allclose(common_bound(D1, D2), D1 + D2, atol=1e-12)
    assert not common_bound(np.zeros((3, 3)), np.zeros((3, 3))).any()


def _flight(fold_memory: int, monkeypatch, summed: bool = False) -> list[float]:
    """A 2-D INS error (position, velocity, a tilt-like acceleration bias; m, m/s, m/s^2) with 60 GNSS-like fixes
    (3 m, every s) and then 20 map-like fixes (50 m, every 15 s): the fault margin after each covariance step."""
    monkeypatch.setattr(integrity, "FAULT_MEMORY", fold_memory)
    if summed:  # the fold before: the sum of the dropped faults
        orig = integrity.common_bound
        monkeypatch.setattr(integrity, "common_bound", lambda A, B: np.asarray(A) + np.asarray(B))
    dt, n = 0.5, 6
    Phi = np.eye(n)
    for i in range(2):
        Phi[i, 2 + i] = dt
        Phi[i, 4 + i] = 0.5 * dt * dt
        Phi[2 + i, 4 + i] = dt
    Q = np.diag([0.0, 0.0, 1e-4, 1e-4, 1e-8, 1e-8])
    P = np.diag([9.0, 9.0, 0.25, 0.25, 1e-4, 1e-4])
    H = np.zeros((2, n))
    H[0, 0] = H[1, 1] = 1.0
    F = np.zeros((1, n, n))
    T = integrity.chi2_threshold(2, 0.9999)
    out = []
    for k in range(int(360 / dt)):
        t = k * dt
        P = Phi @ P @ Phi.T + Q
        F = Phi @ F @ Phi.T
        gnss = t < 60 and k % 2 == 0
        mapfix = t >= 60 and k % 30 == 0
        if gnss or mapfix:
            R = np.eye(2) * (9.0 if gnss else 2500.0)
            S = H @ P @ H.T + R
            K = P @ H.T @ np.linalg.inv(S)
            A = np.eye(n) - K @ H
            P_post = A @ P @ A.T + K @ R @ K.T
            F = fault_update(F, A, P, P_post, T)
            P = P_post
        out.append(fault_margin(F))
    if summed:
        monkeypatch.setattr(integrity, "common_bound", orig)
    return out


def test_the_folded_margin_bounds_the_exact_one_and_is_tighter_than_the_sum(monkeypatch):
    exact = np.array(_flight(10_000, monkeypatch))
    folded = np.array(_flight(8, monkeypatch))
    summed = np.array(_flight(8, monkeypatch, summed=True))
    assert np.all(folded >= exact * (1 - 1e-9) - 1e-9)
    assert np.all(folded <= summed * (1 + 1e-9) + 1e-9)
    mid = slice(int(60 / 0.5), int(180 / 0.5))  # the map-fix leg while the GNSS-aided faults still dominate
    ratio_folded, ratio_summed = folded[mid] / exact[mid], summed[mid] / exact[mid]
    assert np.max(ratio_folded) < 1.7 and np.max(ratio_summed) > 2.2, (ratio_folded.max(), ratio_summed.max())
    assert np.mean(folded[mid]) < 0.75 * np.mean(summed[mid])
