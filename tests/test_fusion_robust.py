"""The UKF's Student-t down-weighting of fixes (``robust_dof``, ``robust_sources``; issue 17): against the closed-form
Kalman update (the measurement is linear in the error state, so the UKF's update is the Kalman filter's), and the
mechanism it is for: a fix far out in its tight direction, applied with a strong position-velocity correlation,
moves the velocity; down-weighted, it moves it less."""

from __future__ import annotations

import numpy as np
import pytest

from magnav_ins.aiding.fusion import make_fuser
from magnav_ins.aiding.fusion.common import ImuNoise
from magnav_ins.core.errors import ConfigError
from magnav_ins.core.frames import latlon_to_meters, meters_to_latlon, q_nb_from_euler
from magnav_ins.core.types import LAYOUT_15, Fix, NavEstimate, NavState

NOISE = ImuNoise(1e-4, 1e-6, 1e-4, 1e-7)
LAT, LON, H = -0.38, 2.45, 400.0
SP, SV, RHO = 40.0, 0.4, 0.95  # position m, velocity m/s 1-sigma per axis, their correlation
R_TIGHT, R_LOOSE = 40.0, 300.0  # the fix's 1-sigmas: tight north, loose east


def _init() -> NavEstimate:
    nav = NavState(0.0, LAT, LON, H, np.array([10.0, 0.0, 0.0]), q_nb_from_euler(0.0, 0.0, 0.0))
    sig = np.r_[[SP] * 3, [SV] * 3, [1e-3] * 3, [1e-3] * 3, [1e-6] * 3]
    P = np.diag(sig**2)
    for a in range(3):
        P[a, 3 + a] = P[3 + a, a] = RHO * SP * SV
    return NavEstimate(nav, P, LAYOUT_15)


def _fix(dn: float, de: float, scale: float = 1.0, source: str = "ml") -> Fix:
    dlat, dlon = meters_to_latlon(dn, de, LAT, H)
    return Fix(0.0, LAT + float(dlat), LON + float(dlon), scale * np.diag([R_TIGHT**2, R_LOOSE**2]), source=source)


def _apply(fix: Fix, **opt) -> tuple[np.ndarray, np.ndarray, object]:
    f = make_fuser("ukf", _init(), NOISE, **opt)
    inn = f.correct(fix)
    nav = f.estimate().nav
    dn, de = latlon_to_meters(nav.lat - LAT, nav.lon - LON, LAT)
    return np.array([float(dn), float(de)]), np.asarray(nav.v_n[:2]) - np.array([10.0, 0.0]), inn


def test_a_far_fix_is_applied_with_its_covariance_scaled_as_a_student_t() -> None:
    nu = 4.0
    fix = _fix(200.0, 30.0)  # 200 m north: 5 tight sigmas, NIS 12.5 against P + R (inside the 99.99 % gate)
    dp, dv, inn = _apply(fix, robust_dof=nu, robust_sources=("ml",))
    assert inn.accepted
    v = inn.extra["nis_full"]
    lam = (nu + v) / (nu + 2.0)
    assert 10.0 < v < 18.0 and inn.extra["robust_scale"] == pytest.approx(lam)
    # closed form: the plain update with R * lam
    dp1, dv1, _ = _apply(_fix(200.0, 30.0, lam))
    assert np.allclose(dp, dp1, atol=1e-6) and np.allclose(dv, dv1, atol=1e-9)
    # Kalman by hand on the north position/velocity pair: gain P_vp / (P_pp + lam R)
    k_v = RHO * SP * SV / (SP**2 + lam * R_TIGHT**2)
    assert dv[0] == pytest.approx(k_v * 200.0, rel=0.02)
    # the mechanism: without it the same fix moves the velocity by 0.95 m/s, with nu = 4 by 0.51 m/s
    _, dv0, inn0 = _apply(fix)
    assert "robust_scale" not in inn0.extra
    assert dv0[0] == pytest.approx(RHO * SP * SV / (SP**2 + R_TIGHT**2) * 200.0, rel=0.02)
    assert dv[0] < 0.6 * dv0[0]


def test_close_fixes_and_other_sources_keep_their_covariance() -> None:
    close = _fix(20.0, -50.0)  # NIS under 2: scale 1
    for fix, opt in ((close, {"robust_dof": 4.0}), (_fix(200.0, 30.0, source="gnss"), {"robust_dof": 4.0,
                                                                                      "robust_sources": ["ml"]})):  # fmt: skip
        dp, dv, inn = _apply(fix, **opt)
        dp0, dv0, _ = _apply(fix)
        assert "robust_scale" not in inn.extra
        assert np.allclose(dp, dp0, atol=1e-9) and np.allclose(dv, dv0, atol=1e-12)


@pytest.mark.parametrize("opt", [{"robust_dof": 0.0}, {"robust_dof": "4"}, {"robust_sources": "ml"}])
def test_bad_robust_options_are_config_errors(opt: dict) -> None:
    with pytest.raises(ConfigError):
        make_fuser("ukf", _init(), NOISE, **opt)
