"""The compiled covariance step (``aiding/fusion/cov_step.py``) against the Python formulas it replaces:
:func:`magnav_ins.ins.error_model.system_matrices` with the step-averaged blocks and the 30x30 Van Loan exponential
of :func:`magnav_ins.aiding.fusion.common.discretize_fast`; and the eigen-decomposition-free path of
``symmetrise`` against the eigen-decomposition."""

from __future__ import annotations

import numpy as np
import pytest

from magnav_ins.aiding.fusion import common
from magnav_ins.aiding.fusion.common import ExtraStates, ImuNoise, step_matrices, symmetrise
from magnav_ins.core.frames import q_nb_from_euler, skew
from magnav_ins.core.types import NavState
from magnav_ins.ins.error_model import system_matrices
from magnav_ins.ins.imu_models import get_grade


@pytest.mark.parametrize("grade", ["consumer", "tactical", "navigation"])
def test_compiled_step_equals_the_python_van_loan(grade: str) -> None:
    rng = np.random.default_rng(18)
    noise = ImuNoise.from_grade(get_grade(grade))
    for _ in range(40):
        nav = NavState(0.0, rng.uniform(-1.4, 1.4), rng.uniform(-3, 3), rng.uniform(-100, 5000), rng.normal(0, 50, 3),
                       q_nb_from_euler(*rng.uniform(-1, 1, 3)))  # fmt: skip
        C_sum = np.eye(3) * rng.uniform(0.5, 1.0) + rng.normal(0, 0.1, (3, 3))
        fn_sum = rng.normal(0, 10, 3)
        sum_dt = float(rng.choice([0.0, rng.uniform(0.05, 1.0)]))
        dt = rng.uniform(0.01, 5.0)
        Phi, Qd = step_matrices(nav, C_sum, fn_sum, sum_dt, dt, noise)
        F, G, Qc = system_matrices(nav.lat, nav.h, nav.v_n, common._dcm(nav.q_nb), np.zeros(3), noise)
        if sum_dt > 0:
            F[3:6, 6:9] = -skew(fn_sum / sum_dt)
            F[3:6, 9:12] = -C_sum / sum_dt
            F[6:9, 12:15] = -C_sum / sum_dt
        Phi_py, Qd_py = common.discretize_fast(F, G, Qc, dt)
        assert np.abs(Phi - Phi_py).max() <= 1e-13 * np.abs(Phi_py).max()
        assert np.abs(Qd - Qd_py).max() <= 1e-13 * np.abs(Qd_py).max()
    # the optional states keep the Python path
    extra = ExtraStates.from_options(noise, scale_factors=True)
    Phi, _ = step_matrices(nav, C_sum, fn_sum, 0.3, 0.5, noise, extra, np.eye(3), np.eye(3))
    assert Phi.shape == (21, 21)


def test_symmetrise_fast_path_keeps_what_the_eigen_decomposition_keeps() -> None:
    rng = np.random.default_rng(5)
    for _ in range(200):
        A = rng.normal(size=(15, 15)) * np.logspace(-8, 3, 15)[:, None]
        P = A @ A.T
        if rng.random() < 0.5:  # a held state: an exactly zero row and column
            P[[2, 5], :] = 0.0
            P[:, [2, 5]] = 0.0
        np.testing.assert_array_equal(symmetrise(P), 0.5 * (P + P.T))
    N = np.diag([1.0, 2.0, -1e-3])  # not PSD: clipped by the eigen-decomposition
    out = symmetrise(N)
    assert np.linalg.eigvalsh(out).min() >= -1e-15 and out[0, 0] == pytest.approx(1.0)
