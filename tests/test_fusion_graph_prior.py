"""The graph fuser's prior on node 0 is the initial covariance itself. Its variances span ~25 orders of magnitude
(km^2 positions, ~5e-17 rad^2/s^2 for a navigation-grade gyro bias); an absolute 1e-12 eigenvalue floor (before
issue 13's fix) widened the gyro-bias sigma from 0.0015 deg/h to 0.21 deg/h (1e-6 rad/s) and the graph fitted a
1.3 deg/h gyro bias on run 6 of the Osborne eight-line study (true ~0.003 deg/h). The floor hid a model defect
(the Earth rate taken out of the gyros at the predicted attitude with no Jacobian, ``test_fusion_graph_earth_rate.py``);
with that fixed the prior is exact (correlation-scaled square-root information).
"""

from __future__ import annotations

import numpy as np
import pytest

gtsam = pytest.importorskip("gtsam")

from magnav_ins.aiding.fusion import ImuNoise, make_fuser  # noqa: E402
from magnav_ins.core.types import NavEstimate, NavState  # noqa: E402
from magnav_ins.ins.error_model import initial_covariance  # noqa: E402
from magnav_ins.ins.imu_models import get_grade  # noqa: E402


def _prior(grade_name: str) -> tuple[NavEstimate, ImuNoise]:
    grade = get_grade(grade_name)
    nav0 = NavState(0.0, np.deg2rad(-21.0), np.deg2rad(140.0), 400.0, np.array([70.0, 0.0, 0.0]),
                    np.array([0.0, 0.0, 0.0, 1.0]))  # fmt: skip
    P0 = initial_covariance(grade, position_sigma_m=100.0, velocity_sigma_mps=0.5,
                            attitude_sigma_rad=np.deg2rad([0.05, 0.05, 0.5]))  # fmt: skip
    return NavEstimate(nav0, P0), ImuNoise.from_grade(grade)


@pytest.mark.parametrize("grade_name", ["navigation", "tactical", "consumer"])
def test_node0_marginal_is_the_initial_covariance(grade_name: str) -> None:
    """Every 1-sigma of the node-0 marginal (LAYOUT_15) equals the initial one within 1 %, the smallest (gyro bias)
    included."""
    init, noise = _prior(grade_name)
    fuser = make_fuser("graph", init, noise)
    sig0 = np.sqrt(np.diag(init.P)[:15])
    sig = np.sqrt(np.diag(fuser.estimate().P)[:15])
    np.testing.assert_allclose(sig, sig0, rtol=1e-2)


def test_ideal_imu_prior_holds_the_zero_biases() -> None:
    """A grade with zero bias sigmas (an ideal IMU) still builds, with the biases held to ~1e-10."""
    init, noise = _prior("navigation")
    P0 = np.array(init.P, float)
    P0[9:15, :] = 0.0
    P0[:, 9:15] = 0.0
    fuser = make_fuser("graph", NavEstimate(init.nav, P0), noise)
    sig = np.sqrt(np.diag(fuser.estimate().P)[:15])
    assert np.all(sig[9:15] < 1e-9), sig[9:15]
    np.testing.assert_allclose(sig[:9], np.sqrt(np.diag(P0)[:9]), rtol=1e-2)
