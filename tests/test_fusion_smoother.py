"""The UKF's smoother: the relinearised (iterated) passes of ``InertialCore.smooth`` against the first, closed-loop
RTS pass and against truth on the contract scenario (simulated flight, tactical IMU, fixes every 10 s), where the
filter's trajectory is already a good linearisation point, so relinearising must change almost nothing (a wrong
sign or frame in the defect, the measurement model or the prior moves the result by the fixes' metres). On the
KITTI drive (slow) it must reach the factor graph's batch solution."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_fusion_contract import H_SIGMA, noise, run_inputs, truth

from magnav_ins.aiding.fusion import make_fuser
from magnav_ins.core.errors import InputError
from magnav_ins.ins.error_model import nav_error


def _smoothed_errors(tr, traj) -> np.ndarray:
    k = np.array([int(np.argmin(np.abs(traj.t - t))) for t in tr.t])
    return np.array([nav_error(tr.at(i), traj.at(int(j)))[:3] for i, j in enumerate(k)])


def test_relinearised_smoother_is_a_fixed_point_on_a_good_linearisation() -> None:
    traj, _ = truth()
    init, imu, fixes = run_inputs(2)
    fuser = make_fuser("ukf", init, noise(), keep_history=True)
    i = 0
    for fix, h in fixes:
        j = int(np.searchsorted(imu.t, fix.t + 1e-9, side="right"))
        fuser.propagate(imu.slice(i, j))
        i = j
        fuser.correct(fix, height_m=h, height_sigma_m=H_SIGMA)
    (s1, P1), (s2, P2), (s3, _) = (fuser.smooth(n) for n in (1, 2, 3))
    assert np.allclose(s1.t, s2.t) and np.allclose(s2.t, s3.t)
    d12 = np.array([np.hypot(*nav_error(s2.at(k), s1.at(k))[:2]) for k in range(len(s1))])
    d23 = np.array([np.hypot(*nav_error(s3.at(k), s2.at(k))[:2]) for k in range(len(s1))])
    sig = np.sqrt(P1[:, 0, 0] + P1[:, 1, 1])
    assert np.all(d12 < 0.1 * sig), (d12 / sig).max()  # relinearising about a good trajectory: tiny change
    assert d23.max() < 0.2 * max(d12.max(), 1e-3)  # and it converges
    e1 = np.hypot(*_smoothed_errors(s1, traj)[:, :2].T)
    e2 = np.hypot(*_smoothed_errors(s2, traj)[:, :2].T)
    assert np.sqrt(np.mean(e2**2)) == pytest.approx(np.sqrt(np.mean(e1**2)), rel=0.05)
    assert np.allclose(np.sqrt(P2[:, 0, 0]), np.sqrt(P1[:, 0, 0]), rtol=0.05)
    with pytest.raises(InputError):
        fuser.smooth(0)


@pytest.mark.slow
def test_kitti_iterated_smoother_reaches_the_batch_graph() -> None:
    """KITTI (GTSAM's files), GPS every 10th epoch: the relinearised UKF smoother must land within 2 % of the
    factor graph's batch solution (same data, same noise), while the single closed-loop RTS pass is >10 % worse."""
    import importlib.util
    from pathlib import Path

    bench = Path(__file__).resolve().parents[1] / "bench" / "kitti_fusion.py"
    spec = importlib.util.spec_from_file_location("kitti_fusion_bench", bench)
    kf = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(kf)
    try:
        kf.data_dir()
    except SystemExit:
        pytest.skip("KITTI files (gtsam wheel Data/ or ../shared/data/kitti_gtsam) not found")
    out = kf.measure(kf.parse(["--no-peer", "--fusers", "ukf,graph", "--smooth-iterations", "3"]))
    ukf, graph = out["fusers"]["ukf"], out["fusers"]["graph"]
    assert ukf["smoothed"]["rms_horizontal_m"] < 1.02 * graph["smoothed"]["rms_horizontal_m"]
    assert ukf["smoothed_single_pass"]["rms_horizontal_m"] > 1.1 * graph["smoothed"]["rms_horizontal_m"]
    assert max(ukf["smoothed"]["rms_horizontal_m"], graph["smoothed"]["rms_horizontal_m"]) <= 0.75


def test_two_fixes_at_one_time_smooth_like_their_combination() -> None:
    """Two fixes at the same time with noise 2R carry the information of one with R: the (linear) filter and the
    smoother must give the same trajectory either way (the smoother must add the two closed-loop corrections of
    that step, not keep the last one)."""
    init, imu, fixes = run_inputs(3)
    runs = []
    for copies in (1, 2):
        fuser = make_fuser("ukf", init, noise(), keep_history=True, gate_probability=None)
        i = 0
        for fix, h in fixes:
            j = int(np.searchsorted(imu.t, fix.t + 1e-9, side="right"))
            fuser.propagate(imu.slice(i, j))
            i = j
            for _ in range(copies):
                f = dataclasses.replace(fix, cov_ne=np.asarray(fix.cov_ne) * copies)
                fuser.correct(f, height_m=h, height_sigma_m=H_SIGMA * np.sqrt(copies))
        runs.append(fuser.smooth(1)[0])
    a, b = runs
    assert np.allclose(a.t, b.t)
    d = np.array([np.hypot(*nav_error(a.at(k), b.at(k))[:2]) for k in range(len(a))])
    assert d.max() < 0.05, d.max()  # metres; fix noise is 4-5 m, filter-vs-smoother differences are metres
