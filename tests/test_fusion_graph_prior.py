"""The graph fuser's prior on node 0 should be the initial covariance itself. Its variances span ~25 orders of
magnitude (km^2 positions, ~5e-17 rad^2/s^2 for a navigation-grade gyro bias), and the absolute 1e-12 eigenvalue floor
in ``GraphFuser.__init__`` widens the gyro-bias sigma from 0.0015 deg/h to 0.21 deg/h (1e-6 rad/s): the graph fits a
1.3 deg/h gyro bias on run 6 of the Osborne eight-line study (true ~0.003 deg/h).

KNOWN DEFECT (issue 13), hence the strict xfails: removing the floor (correlation-scaled square-root information,
commit 3f391fd) made the 20-run study worse (ml+graph 186 -> 307 m RMS, NEES 3.0 -> 8.6). Not numerics (iSAM2's
marginals match a dense column-scaled solve with and without the floor): the loose gyro bias absorbs a model
difference from the UKF not yet found; the floor can go once that is fixed.
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


_FLOOR = "issue 13: the 1e-12 eigenvalue floor widens sub-1e-6 bias sigmas (module docstring)"


@pytest.mark.parametrize(
    "grade_name",
    [pytest.param("navigation", marks=pytest.mark.xfail(strict=True, reason=_FLOOR)), "tactical", "consumer"],
)
def test_node0_marginal_is_the_initial_covariance(grade_name: str) -> None:
    """Every 1-sigma of the node-0 marginal (LAYOUT_15) equals the initial one within 1 %, the smallest (gyro bias)
    included."""
    init, noise = _prior(grade_name)
    fuser = make_fuser("graph", init, noise)
    sig0 = np.sqrt(np.diag(init.P)[:15])
    sig = np.sqrt(np.diag(fuser.estimate().P)[:15])
    np.testing.assert_allclose(sig, sig0, rtol=1e-2)


@pytest.mark.xfail(strict=True, reason=_FLOOR)
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
