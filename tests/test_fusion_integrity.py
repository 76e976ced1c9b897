"""Fault detection and exclusion, recovery and protection levels of every fuser (``aiding/fusion/integrity.py``).

Scenario: the contract tests' 400 s flight with turns (tactical IMU, fixes every 10 s with a correlated 5 m
covariance, a 5 m height aid; :mod:`test_fusion_contract`). The dangerous case of issue 13: 10 % of the fixes, drawn
at random, displaced 500 m - 2 km in random directions while keeping their small covariance. Truth is known, so the
protection level is checked against the true horizontal error at every 1 s epoch.
"""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys

import numpy as np
import pytest
from test_fusion_contract import H_SIGMA, noise, run_inputs, truth

from magnav_ins.aiding.fusion import make_fuser
from magnav_ins.aiding.fusion.integrity import FaultMonitor, exclusion_doubt, hpl_fault_free, integrity_factor
from magnav_ins.core.frames import meters_to_latlon
from magnav_ins.core.types import LAYOUT_15, NavEstimate
from magnav_ins.ins.error_model import nav_error

FUSERS = ["ukf", "graph"]
SEEDS = {"ukf": (0, 1, 2), "graph": (0, 1)}


def displaced(fix, rng: np.random.Generator, lo_m: float = 500.0, hi_m: float = 2000.0):
    """``fix`` moved lo..hi m in a random direction, its (small) covariance kept."""
    d = rng.uniform(lo_m, hi_m)
    b = rng.uniform(0.0, 2.0 * np.pi)
    dlat, dlon = meters_to_latlon(d * np.cos(b), d * np.sin(b), fix.lat)
    return dataclasses.replace(fix, lat=fix.lat + float(dlat), lon=fix.lon + float(dlon), source="faulty")


def step_epochs(fuser, imu, fixes):  # noqa: ANN001, ANN201
    """Propagate ``fuser`` over ``imu`` and correct it with ``fixes`` ((fix, height) pairs, time order), yielding
    each 1 s epoch time (s) once the fuser stands at it."""
    i = q = 0
    for t_ep in np.arange(1.0, float(imu.t[-1]) + 1e-9, 1.0):
        while q < len(fixes) and fixes[q][0].t <= t_ep + 1e-9:
            f, h = fixes[q]
            j = int(np.searchsorted(imu.t, f.t + 1e-9, side="right"))
            fuser.propagate(imu.slice(i, j))
            i = j
            fuser.correct(f, height_m=h, height_sigma_m=H_SIGMA)
            q += 1
        j = int(np.searchsorted(imu.t, t_ep + 1e-9, side="right"))
        fuser.propagate(imu.slice(i, j))
        i = j
        yield float(t_ep)


def fly_epochs(kind: str, seed: int, faulty: set[int], *, init_offset_m: float = 0.0, rng_seed: int = 99):
    """Run ``kind`` over the contract flight with the fixes of index ``faulty`` displaced; returns the fuser, the
    true horizontal error and the HPL at every 1 s epoch, and the indices of the displaced fixes."""
    traj, _ = truth()
    init, imu, fixes = run_inputs(seed)
    if init_offset_m:
        dlat, dlon = meters_to_latlon(init_offset_m, 0.0, init.nav.lat)
        nav = dataclasses.replace(init.nav, lat=init.nav.lat + float(dlat), lon=init.nav.lon + float(dlon))
        init = NavEstimate(nav, init.P, LAYOUT_15)
    rng = np.random.default_rng(rng_seed + seed)
    fuser = make_fuser(kind, init, noise())
    todo = [(f, h, n in faulty) for n, (f, h) in enumerate(fixes)]
    todo = [(displaced(f, rng) if bad else f, h, bad) for f, h, bad in todo]
    err, hpl = [], []
    for _ in step_epochs(fuser, imu, [(f, h) for f, h, _ in todo]):
        est = fuser.estimate()
        k = int(np.argmin(np.abs(traj.t - est.nav.t)))
        err.append(float(np.hypot(*nav_error(est.nav, traj.at(k))[:2])))
        hpl.append(est.hpl_m)
    return fuser, np.array(err), np.array(hpl), [inn for inn in fuser.innovations]


@pytest.mark.parametrize("kind", FUSERS)
def test_displaced_fixes_with_small_sigmas_are_excluded_and_hpl_holds(kind: str) -> None:
    n_fixes = len(run_inputs(0)[2])
    errs, hpls, n_false = [], [], 0
    for seed in SEEDS[kind]:
        faulty = set(np.random.default_rng(500 + seed).choice(n_fixes, n_fixes // 10, replace=False).tolist())
        fuser, err, hpl, inns = fly_epochs(kind, seed, faulty)
        bad = [inn for inn in inns if inn.source == "faulty"]
        assert len(bad) == len(faulty) == n_fixes // 10
        for inn in bad:  # every displaced fix excluded, and it says so
            assert not inn.accepted, (kind, seed, inn)
            assert inn.extra.get("fault") == 1.0 and ("NIS" in inn.reason), inn.reason
        n_false += sum(1 for inn in inns if inn.source != "faulty" and not inn.accepted)
        assert fuser.monitor.n_faults >= len(faulty) and fuser.monitor.n_recoveries == 0
        assert np.all(np.isfinite(hpl)) and np.all(hpl > 0)
        errs.append(err)
        hpls.append(hpl)
    err, hpl = np.concatenate(errs), np.concatenate(hpls)
    exceed = float(np.mean(err > hpl))
    assert exceed <= 0.01, f"{kind}: HPL exceeded at {exceed:.1%} of epochs"
    assert n_false <= 1, f"{kind}: {n_false} good fixes excluded"
    assert np.max(err) < 60.0  # no displaced fix pulled the solution
    # the protection level is a bound, not a blanket: its median stays within a few tens of metres here
    assert np.median(hpl) < 150.0, np.median(hpl)


@pytest.mark.parametrize("kind", FUSERS)
def test_consecutive_faults_are_never_re_accepted(kind: str) -> None:
    """Six displaced fixes in a row, in random directions: the old rule re-accepted the fourth; the mutual-
    consistency test must not, and the HPL must cover the filter while it cannot tell who is wrong."""
    fuser, err, hpl, inns = fly_epochs(kind, 4, set(range(15, 21)))
    bad = [inn for inn in inns if inn.source == "faulty"]
    assert len(bad) == 6 and not any(inn.accepted for inn in bad)
    assert fuser.monitor.n_recoveries == 0
    assert np.mean(err > hpl) <= 0.01 and np.max(err) < 60.0
    # while the faults were unresolved the protection level covered the hypothesis "the filter is wrong"
    assert np.max(hpl[150:215]) > 500.0


@pytest.mark.parametrize("kind", FUSERS)
def test_lost_filter_recovers_on_consistent_fixes(kind: str) -> None:
    """A filter started 1.5 km off with a 10 m sigma rejects the (correct) fixes; three mutually consistent ones
    make it recover, and the protection level covers it from the first fix on."""
    fuser, err, hpl, inns = fly_epochs(kind, 5, set(), init_offset_m=1500.0)
    assert fuser.monitor.n_recoveries >= 1
    rec = [inn for inn in inns if inn.accepted and inn.extra.get("recovery")]
    assert rec and rec[0].extra["recovery"] >= 3 and rec[0].extra.get("inflation", 0.0) > 1.0
    assert err[-100:].max() < 60.0, err[-100:].max()
    t_first = int(inns[0].t)  # before any fix nothing can tell the filter it is off
    assert np.mean(err[t_first:] > hpl[t_first:]) <= 0.01


def test_monitor_units() -> None:
    # K for 1e-3: a circular 2-D Gaussian exceeds K sigma with probability exactly exp(-K^2/2)
    assert integrity_factor(1e-3) == pytest.approx(math.sqrt(2.0 * math.log(1e3)), rel=1e-12)
    P = np.array([[900.0, 300.0], [300.0, 400.0]])
    lam = np.linalg.eigvalsh(P).max()
    assert hpl_fault_free(P, 1e-3) == pytest.approx(integrity_factor(1e-3) * math.sqrt(lam), rel=1e-12)
    e = np.random.default_rng(0).multivariate_normal([0, 0], np.eye(2) * 100.0, 400_000)
    assert np.mean(np.hypot(e[:, 0], e[:, 1]) > hpl_fault_free(np.eye(2) * 100.0, 0.01)) == pytest.approx(
        0.01, rel=0.05
    )
    # consistent excluded fixes -> recovery; scattered ones -> never
    R = np.eye(2) * 25.0
    Pf = np.eye(2) * 100.0
    m = FaultMonitor(0.9999, reset_after=3)
    # the filter is 800 m off; its covariance grows 30 m (1-sigma) between fixes, and so may the residual
    v = [m.assess(t, np.array([800.0, -300.0]) + 3.0 * t, Pf * (1 + t) + R, R, Pf * (1 + t)) for t in (0.0, 10.0, 20.0)]
    assert [x.action for x in v] == ["reject", "reject", "recover"] and v[2].extra["recovery"] == 3.0
    m = FaultMonitor(0.9999, reset_after=3)
    rng = np.random.default_rng(1)
    acts = [m.assess(10.0 * k, rng.uniform(-2000, 2000, 2), Pf + R, R, Pf).action for k in range(12)]
    assert set(acts) == {"reject"}
    assert m.hpl(Pf) > 1000.0  # the doubt of unresolved exclusions
    # the window test: four fixes each inside the gate, together too far out
    m = FaultMonitor(0.9999, window=4)
    S = np.eye(2) * 100.0
    verdicts = []
    for t in range(3):
        vd = m.assess(float(t), np.array([30.0, 0.0]), S, R, Pf)  # NIS 9 each (gate 18.4)
        verdicts.append(vd)
        if vd.action == "accept":
            m.accepted(float(t), 9.0, Pf, Pf * 0.8)
    # 9 + 9 = 18 <= 18.47 (4 dof, 0.999); 27 > 22.46 (6 dof)
    assert [x.action for x in verdicts] == ["accept", "accept", "reject"]
    assert verdicts[2].reason.startswith("window NIS 27.0 over 3 fixes") and verdicts[2].extra["fault"] == 1.0


def test_free_inertial_hpl_is_its_covariance() -> None:
    init, imu, _ = run_inputs(0)
    f = make_fuser("free_inertial", init, noise())
    f.propagate(imu.slice(0, 2000))
    est = f.estimate()
    assert est.hpl_m == pytest.approx(hpl_fault_free(est.cov_ne, est.integrity_risk), rel=1e-12)


def test_ukf_takes_a_prior_with_exactly_known_states() -> None:
    """The bridge and the replay clamp the height and give it zero variance (issue 18 item 1: "6-th leading minor
    not positive definite"); the sigma points must not need a positive definite covariance."""
    init, imu, fixes = run_inputs(0)
    P0 = np.array(init.P)
    P0[2, :] = P0[:, 2] = P0[5, :] = P0[:, 5] = 0.0
    f = make_fuser("ukf", NavEstimate(init.nav, P0, LAYOUT_15), noise(), altitude_hold=float(init.nav.h))
    for fix, _ in fixes[:5]:
        f.propagate(imu.slice(0, int(np.searchsorted(imu.t, fix.t + 1e-9, side="right"))))
        assert f.correct(fix).accepted
    P = f.estimate().P
    assert abs(P[2, 2]) < 1e-12 and abs(P[5, 5]) < 1e-12 and np.all(np.isfinite(P))  # held: round-off only


@pytest.mark.shared_data
@pytest.mark.parametrize("fusion", ["ukf", "graph", "free_inertial"])
def test_replay_sample_ulg_with_init_runs_with_every_fuser(shared_data, tmp_path, fusion: str) -> None:
    log = shared_data / "px4_ulog" / "sample.ulg"
    out = tmp_path / "rp.csv"
    cmd = [sys.executable, "-m", "magnav_ins.cli", "replay", str(log), "--map", "builtin:osborne-magnetic",
           "--init", "-21.9,140.6,400,0", "--fusion", fusion, "--duration", "20", "--out", str(out)]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    rows = out.read_text().splitlines()
    assert len(rows) > 90 and "Traceback" not in res.stderr
    assert rows[0].split(",")[-1] == "hpl_m"
    hpl = np.array([float(r.split(",")[-1]) for r in rows[1:]])
    assert np.all(np.isfinite(hpl) & (hpl > 0))


def test_fuser_options_match_the_constructors() -> None:
    import inspect

    from magnav_ins.aiding.fusion import FUSER_OPTIONS
    from magnav_ins.aiding.fusion.common import InertialCore
    from magnav_ins.aiding.fusion.graph import GraphFuser
    from magnav_ins.aiding.fusion.ukf import UkfFuser

    def kw(cls) -> set[str]:
        return {n for n, p in inspect.signature(cls.__init__).parameters.items() if p.kind is p.KEYWORD_ONLY}

    assert set(FUSER_OPTIONS["ukf"]) == kw(UkfFuser)
    assert set(FUSER_OPTIONS["graph"]) == kw(GraphFuser)
    assert set(FUSER_OPTIONS["free_inertial"]) == kw(InertialCore) | {"gate_probability"}


def test_rejected_batch_is_a_fault_and_widens_the_hpl() -> None:
    """A batch of correlated fixes (PMHT retrodiction, :mod:`aiding.fusion.batch`) displaced 2 km with small sigmas
    is excluded, counted as a fault, and the protection level covers the hypothesis that the filter is wrong."""
    init, imu, fixes = run_inputs(0)
    f = make_fuser("ukf", init, noise())
    batch = [displaced(fx, np.random.default_rng(7), 2000.0, 2000.0) for fx, _ in fixes[:3]]
    shift = [dataclasses.replace(b, lat=batch[0].lat + (fx.lat - fixes[0][0].lat), lon=batch[0].lon + (fx.lon - fixes[0][0].lon))
             for b, (fx, _) in zip(batch, fixes[:3], strict=True)]  # fmt: skip
    f.propagate(imu.slice(0, int(np.searchsorted(imu.t, shift[-1].t + 1e-9, side="right"))))
    hpl0 = f.estimate().hpl_m
    inn = f.correct_batch(shift, np.kron(np.eye(3), np.array([[25.0, 6.0], [6.0, 16.0]])))
    assert not inn.accepted and inn.extra.get("fault") == 1.0 and f.monitor.n_faults == 1
    assert f.estimate().hpl_m > 1500.0 > 10 * hpl0


def _epochs(fuser, imu, fixes) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001
    """Run ``fuser`` over ``fixes`` ((fix, height) pairs) at 1 s epochs; (lat, lon) rad and the fault margin (m)."""
    pos, margin = [], []
    for _ in step_epochs(fuser, imu, fixes):
        nav = fuser.estimate().nav
        pos.append((nav.lat, nav.lon))
        margin.append(fuser.fault_margin())
    return np.array(pos), np.array(margin)


def test_ukf_fault_margin_bounds_what_an_undetected_fix_bias_leaves() -> None:
    """The fault margin is a bound on the error a bias inside the gate leaves (integrity.py: the fault matrix
    ``T (P- - P+)`` propagated by the INS error transition, shrunk by later updates): one fix displaced along the
    innovation covariance's major axis to 0.8 of the gate moves the estimate by less than the margin at every
    epoch after it, by a good part of it (the bound is not vacuous)."""
    from magnav_ins.core.frames import latlon_to_meters

    init, imu, fixes = run_inputs(0)
    # the gate alone (no window test: it would exclude the fixes after the fault, a detection, not what the margin
    # is for; the run's decisions must stay those of the clean run)
    clean = make_fuser("ukf", init, noise(), fault_window=0)
    p0, m0 = _epochs(clean, imu, fixes)
    k_bad = 12
    inn = clean.innovations[k_bad]
    S = np.asarray(inn.S)
    w, V = np.linalg.eigh(S)
    T2 = clean.monitor.gate_threshold(2)
    b = math.sqrt(0.8 * T2 * w[-1]) * V[:, -1]  # b' S^-1 b = 0.8 T2, along the major axis ...
    if b @ np.linalg.solve(S, inn.residual_ne) > 0:  # ... against the fix's own residual, so the gate passes it
        b = -b
    bad = list(fixes)
    f, h = bad[k_bad]
    dlat, dlon = meters_to_latlon(b[0], b[1], f.lat)
    bad[k_bad] = (dataclasses.replace(f, lat=f.lat + float(dlat), lon=f.lon + float(dlon)), h)
    biased = make_fuser("ukf", init, noise(), fault_window=0)
    p1, m1 = _epochs(biased, imu, bad)
    assert [i.accepted for i in biased.innovations] == [i.accepted for i in clean.innovations]
    dn, de = latlon_to_meters(p1[:, 0] - p0[:, 0], p1[:, 1] - p0[:, 1], p0[:, 0])
    moved = np.hypot(dn, de)
    after = np.arange(len(moved)) >= int(math.ceil(f.t)) - 1
    assert np.all(moved[after] <= m1[after] + 0.05), float(np.max(moved[after] - m1[after]))
    assert np.max(moved[after] / m1[after]) > 0.3
    # the margin depends on covariances only: the same with and without the fault (up to the UKF's linearisation
    # about a trajectory 20-40 m apart)
    np.testing.assert_allclose(m0, m1, rtol=0.02, atol=1e-6)


def test_doubt_of_an_exclusion_is_the_correction_the_fix_asks_of_the_least_inflated_filter() -> None:
    """The doubt an excluded fix leaves (integrity module docstring, ``d``), against closed forms: for isotropic
    ``P = p I`` and ``R = rho I`` the least inflation making a residual ``r`` consistent is ``s p = |r|^2 / T - rho``
    and the doubt ``G |r| + K sqrt(s p rho / (s p + rho))`` with ``G = s p / (s p + rho)``; a fix the window test
    excluded inside the gate (``s = 1``) with ``R = P`` asks for half its residual. An edge fix (cross-track
    position, 10 km sigma along the track) leaves a doubt of its cross-track residual's order, not of its 10 km (SITL
    run 38: the HPL was 51 km for 10 s, then the autopilot's EKF failsafe)."""
    K = integrity_factor(1e-3)
    p, rho = 30.0**2, 20.0**2
    P, R = np.eye(2) * p, np.eye(2) * rho
    r = np.array([400.0, 3000.0])
    m = FaultMonitor(0.9999)
    T = m.gate_threshold(2)
    assert m.assess(0.0, r, P + R, R, P).action == "reject"
    sp = float(r @ r) / T - rho
    G = sp / (sp + rho)
    assert m.hpl(P) == pytest.approx(G * math.hypot(*r) + K * math.sqrt(sp * rho / (sp + rho)), rel=1e-6)
    assert math.hypot(*r) < m.hpl(P) < math.hypot(*r) + K * 20.0  # a precise fix far off: its whole residual
    # inside the gate (the window test's exclusion): half the residual when R = P, and K sigmas of P / 2
    r_in = np.array([60.0, -20.0])
    assert float(r_in @ np.linalg.solve(2 * P, r_in)) < T
    assert exclusion_doubt(r_in, P, P, T, K) == pytest.approx(0.5 * math.hypot(*r_in) + K * math.sqrt(p / 2), rel=1e-9)
    # the edge fix: 400 m across (excluded), 3 km along where it says nothing
    heading = math.radians(30.0)  # along-track unit vector (north, east)
    u = np.array([math.cos(heading), math.sin(heading)])
    n = np.array([-u[1], u[0]])
    R_edge = 1e4**2 * np.outer(u, u) + rho * np.outer(n, n)
    m2 = FaultMonitor(0.9999)
    assert m2.assess(0.0, 400.0 * n + 3000.0 * u, P + R_edge, R_edge, P).action == "reject"
    assert 400.0 < m2.hpl(P) < 1000.0
    # a fix 20 km vague along the track and in the gate across it leaves no more than the fault-free level
    assert exclusion_doubt(40.0 * n + 3000.0 * u, R_edge, P, T, K) < K * 30.0 + 40.0


def test_window_exclusions_that_agree_recover_and_scattered_ones_do_not() -> None:
    """SITL run 47 (played back): three fixes 160-380 m off (NEES 7-10 against their own covariance, each inside
    the gate) were accepted one after the other and took the filter 200 m off; from then on every fix, the right
    ones included, failed the window test, whose sum still held the accepted bad ones (the window slides only on
    acceptance): six exclusions, the doubt raised the HPL to 1.5 km, the bridge went untrusted and ArduCopter landed
    on "EKF variance". Window exclusions are now evidence that the filter lost track, as gate exclusions are:
    three that agree with each other recover (the fix is applied, the window restarts); three in random
    directions, each as far off, do not."""
    R = np.eye(2) * 25.0
    Pf = np.eye(2) * 100.0
    S = Pf + R
    # gate (2 dof, 0.9999) 18.4; window (0.999): 4 dof 18.47, 6 dof 22.46
    for scattered in (False, True):
        m = FaultMonitor(0.9999, window=4, reset_after=3)
        for t in (0.0, 10.0):  # two accepted fixes, NIS 8 each: the window holds 16
            r = np.array([0.0, math.sqrt(8.0 * 125.0)])
            assert m.assess(t, r, S, R, Pf).action == "accept"
            m.accepted(t, 8.0, Pf, Pf * 0.8)
        rng = np.random.default_rng(3)
        acts = []
        for k in range(6):
            ang = rng.uniform(0.0, 2.0 * math.pi) if scattered else 0.3
            r = math.sqrt(8.5 * 125.0) * np.array([math.cos(ang), math.sin(ang)])  # NIS 8.5: inside the gate
            v = m.assess(20.0 + 10.0 * k, r + (0.0 if scattered else 2.0 * k), S, R, Pf)
            acts.append(v.action)
            if v.action != "reject":
                m.accepted(20.0 + 10.0 * k, 8.5, Pf, Pf * 0.8, recovery=v.action == "recover")
                break
        if scattered:
            assert acts == ["reject"] * 6 and m.n_recoveries == 0
            assert m.hpl(Pf) > 30.0
        else:
            assert acts == ["reject", "reject", "recover"] and m.n_recoveries == 1
            assert v.extra["recovery"] == 3.0 and "window_nis" in v.extra
            # the window restarted: the next fix like it is judged on its own
            assert m.assess(60.0, r, S, R, Pf).action == "accept"


def test_a_lone_implausible_exclusion_leaves_no_doubt_on_a_confirmed_filter() -> None:
    """SITL run 48: two false peaks 0.8 and 4.7 km off (50-80 m sigmas) against a filter confirmed by fixes 30 s
    before (sigma 36 m, error 25 m): each set the HPL alone (0.98 and 5.4 km), the bridge went untrusted and the
    autopilot landed. Only a filter 30 times over-confident in variance could explain the first (errors of 22 of its
    sigmas): a fault of the matcher's. It counts when a second exclusion agrees with it, when three are unresolved,
    or when no fix ever confirmed the filter."""
    from magnav_ins.aiding.fusion.integrity import MAX_DOUBT_INFLATION, filter_inflation

    P = np.diag([28.6**2, 35.9**2])
    R = np.diag([50.0**2, 79.0**2])
    r = np.array([537.5, -599.0])
    gate = FaultMonitor(0.9999).gate_threshold()
    assert filter_inflation(r, R, P, gate) > MAX_DOUBT_INFLATION
    # a fix 9 sigmas of the filter off (outside the gate) needs an inflation of 3: it keeps its doubt
    near = np.array([130.0, 100.0])
    assert 1.0 < filter_inflation(near * 2.2, R, P, gate) < 5.0

    def monitor(confirmed: bool) -> FaultMonitor:
        m = FaultMonitor(0.9999, window=4, reset_after=3)
        if confirmed:
            assert m.assess(0.0, np.array([10.0, -5.0]), P + R, R, P).action == "accept"
            m.accepted(0.0, 0.05, P, P * 0.7)
        return m

    nominal = FaultMonitor(0.9999).k * math.sqrt(35.9**2)
    m = monitor(True)
    assert m.assess(30.0, r, P + R, R, P).action == "reject"
    assert m.hpl(P, margin_m=0.0) == pytest.approx(nominal)  # no doubt
    m.assess(40.0, r + np.array([20.0, -10.0]), P + R, R, P)  # a second one agrees: the filter may be lost
    assert m.hpl(P, margin_m=0.0) > 700.0
    m = monitor(False)  # never confirmed: full doubt from the first
    m.assess(30.0, r, P + R, R, P)
    assert m.hpl(P, margin_m=0.0) > 700.0
    m = monitor(True)  # a plausible one keeps its doubt on a confirmed filter
    assert m.assess(30.0, near * 2.2, P + R, R, P).action == "reject"
    assert m.hpl(P, margin_m=0.0) > nominal + 50.0
