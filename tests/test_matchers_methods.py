"""Per-method checks of the matchers against known truth (synthetic maps, fixed seeds)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from matcher_scenarios import KIND_G, KIND_TF, KIND_V, ORIGIN, exact, latlon, local, make_window, nav_estimate
from scipy.ndimage import gaussian_filter1d

from magnav_ins.aiding.matchers import BayesGridMatcher, LikelihoodMatcher, ParticleFilter, PMHTMatcher
from magnav_ins.aiding.matchers._local import LocalFrame
from magnav_ins.aiding.matchers.bayes_grid import _tail_sigma
from magnav_ins.core.errors import ConfigError
from magnav_ins.core.protocols import MatchWindow
from magnav_ins.core.types import FieldReadings
from magnav_ins.core.units import NT_PER_MILLIGAUSS
from magnav_ins.maps.grid import GridMap
from magnav_ins.maps.synthetic import hallway_map, random_field_map
from magnav_ins.maps.track import TrackMap


# ---------------------------------------------------------------------------------------------- likelihood
def test_ml_full_map_scan_finds_true_location():
    rng = np.random.default_rng(21)
    fmap = exact(random_field_map((300, 300), 5.0, 40.0, 100.0, rng, kind=KIND_TF, origin=ORIGIN))
    nz = 25  # a 120 m section (Shockley sec. 4.5: sections make a match distinctive)
    truth = np.array([812.3, 433.7]) + 5.0 * np.arange(nz)[:, None] * np.array([0.6, 0.8])
    lat, lon = latlon(fmap, truth[:, 0], truth[:, 1])
    z = fmap.value(lat, lon) + rng.normal(0, 1.0, nz)
    # INS off by 500 m: only a whole-map scan (no search window) can find it
    off = np.array([400.0, -300.0])
    w = make_window(fmap, np.arange(float(nz)), truth, z, 1.0, KIND_TF, off, np.eye(2), np.zeros(2))
    fix = LikelihoodMatcher(method="ml", search_window=False).match(w, fmap)
    assert fix.available, fix.reason
    d = local(fmap, fix.lat, fix.lon) - truth[-1]
    assert np.hypot(*d) < 4.0  # the 1.5 km map is scanned on its 5 m nodes (max_nodes)
    assert d @ np.linalg.solve(fix.cov_ne, d) < 9.0


def _road(seed: int):
    rng = np.random.default_rng(seed)
    fr = LocalFrame(np.radians(39.8), np.radians(-84.0))
    s = np.arange(0.0, 1000.0, 1.0)  # a 1 km winding road, distance-sampled every 1 m (Shockley sec. 4.4)
    n, e = 100.0 * np.sin(s / 150.0), s
    lat, lon = fr.to_latlon(n, e)
    prof = gaussian_filter1d(rng.normal(0, 1, s.size + 100), 5)[50:-50]
    prof *= 30.0 / prof.std()
    return fr, n, e, lat, lon, prof, TrackMap(lat, lon, 0.0, prof, kind=KIND_TF)


def test_mlr_and_abl_fewer_fixes_but_more_within_3m_than_ml_on_road():
    """Shockley 003 sec. 4.4.1: ML always fixes; MLR (20 m, ratio 2) and ABL (5 m bin, normalised peak >= 0.5) fix
    less often but a larger share of their fixes lies within 3 m. Whole road scanned, no prior."""
    fr, n, e, lat, lon, prof, road = _road(3)
    sig, nz, trials = 3.0, 10, 80
    stats = {}
    for method, extra in (("ml", {}), ("mlr", {}), ("abl", {"peak_threshold": 0.5})):
        rr = np.random.default_rng(5)
        m = LikelihoodMatcher(method=method, search_window=False, **extra)
        issued, good = 0, 0
        for _ in range(trials):
            j = int(rr.integers(30, 970))
            idx = np.arange(j - nz + 1, j + 1)
            z = prof[idx] + rr.normal(0, sig, nz)
            w = MatchWindow(
                FieldReadings(idx * 1.0, z, sig, KIND_TF),
                lat[idx],
                lon[idx],
                np.zeros(nz),
                np.tile(np.eye(2) * 1e6, (nz, 1, 1)),
                np.zeros((nz, 2)),
            )
            fix = m.match(w, road)
            if fix.available:
                issued += 1
                fn, fe = fr.to_ne(fix.lat, fix.lon)
                good += np.hypot(fn - n[j], fe - e[j]) < 3.0
            else:
                assert ("ambiguous" if method == "mlr" else "no distinct peak") in fix.reason, fix.reason
        stats[method] = (issued / trials, good / max(issued, 1))
    (a_ml, q_ml), (a_mlr, q_mlr), (a_abl, q_abl) = stats["ml"], stats["mlr"], stats["abl"]
    assert a_ml == 1.0, stats
    assert a_mlr < a_ml and a_abl < a_ml, stats
    assert q_mlr > q_ml + 0.05 and q_abl > q_ml + 0.05, stats
    assert a_mlr > 0.3 and a_abl > 0.3, stats  # the tests still let most distinctive sections through


def test_abl_bin_mass_picks_broad_peak_over_needle():
    # hand-made surface on a 1-D row of candidates: a needle (one node) and a broad peak (5 nodes)
    from magnav_ins.aiding.matchers.likelihood import Surface

    fr = LocalFrame(ORIGIN[0], ORIGIN[1])
    e = np.arange(0.0, 100.0, 1.0)
    logl = np.full(e.size, -50.0)
    logl[20] = 0.0  # needle
    logl[70:75] = -0.2  # broad
    surf = Surface(fr, logl, np.zeros_like(e), e, None, 1.0, 1e9, 1.0, (np.inf, np.inf))
    ml = LikelihoodMatcher(method="ml", track_sigma_m=0.0).decide(surf, 0.0)
    abl = LikelihoodMatcher(method="abl", bin_size_m=5.0, track_sigma_m=0.0).decide(surf, 0.0)
    assert fr.to_ne(ml.lat, ml.lon)[1] == pytest.approx(20.0, abs=1e-6)
    assert fr.to_ne(abl.lat, abl.lon)[1] == pytest.approx(72.0, abs=1e-6)


def _road_surface(n, e, logl, along, lane):
    from magnav_ins.aiding.matchers.likelihood import Surface

    fr = LocalFrame(ORIGIN[0], ORIGIN[1])
    surf = Surface(
        fr, np.log(logl), n, e, None, 1.0, 1e9, 1.0, (np.inf, np.inf), -1, np.asarray(along, float), np.asarray(lane)
    )
    return fr, surf


def test_abl_road_bins_slide_along_one_road_not_across_an_intersection():
    """Shockley 003 sec. 4.3.3: the bin slides along the map's sequence of points. Road A runs east (n = 0), road B
    north through A at e = 50. Likelihood mass (by hand): A at the crossing 3, B 1 m either side of it 2 + 2, a broad
    peak on A at e = 80..84 of 5 x 1.2 = 6. Along one road the best 5 m bin is A's broad peak (6 > 3, 6 > 4), centred
    on e = 82; a round bin in the plane would have summed the crossing (3 + 2 + 2 = 7) and won there."""
    e_a = np.arange(0.0, 101.0)
    n_b = np.arange(-50.0, 51.0)
    n = np.r_[np.zeros_like(e_a), n_b]
    e = np.r_[e_a, np.full_like(n_b, 50.0)]
    along = np.r_[e_a, 1000.0 + n_b + 50.0]  # road B offset far along the sequence (as _track_surface does)
    w = np.full(n.size, 1e-9)
    w[50] = 3.0
    w[e_a.size + 49] = w[e_a.size + 51] = 2.0
    w[80:85] = 1.2
    fr, surf = _road_surface(n, e, w, along, np.zeros(n.size, dtype=np.int64))
    fix = LikelihoodMatcher(method="abl", bin_size_m=5.0, track_sigma_m=0.0).decide(surf, 0.0)
    assert fix.available, fix.reason
    assert fr.to_ne(fix.lat, fix.lon) == pytest.approx((0.0, 82.0), abs=1e-6)
    assert fix.score == pytest.approx(6.0 / w.sum(), rel=1e-9)  # the winning bin's normalised mass


def test_abl_road_bins_keep_travel_directions_apart_and_do_not_shift_a_needle():
    """Both travel directions at one point are two hypotheses (lanes): 2 + 2 at e = 10 (one per lane) lose to a single
    lane's 3 at e = 60, which must come back exactly at e = 60 (not half a bin early, where an equal-mass bin that
    just reaches the needle starts)."""
    e1 = np.arange(0.0, 100.0)
    n = np.zeros(2 * e1.size)
    e = np.r_[e1, e1]
    lane = np.r_[np.zeros(e1.size, dtype=np.int64), np.ones(e1.size, dtype=np.int64)]
    w = np.full(n.size, 1e-9)
    w[10] = w[e1.size + 10] = 2.0
    w[60] = 3.0
    fr, surf = _road_surface(n, e, w, np.r_[e1, e1], lane)
    fix = LikelihoodMatcher(method="abl", bin_size_m=5.0, track_sigma_m=0.0).decide(surf, 0.0)
    assert fix.available, fix.reason
    assert fr.to_ne(fix.lat, fix.lon) == pytest.approx((0.0, 60.0), abs=1e-6)
    # the threshold is on the normalised peak (3 / 7 here), before any binning
    no = LikelihoodMatcher(method="abl", peak_threshold=0.5, track_sigma_m=0.0).decide(surf, 0.0)
    assert not no.available and "no distinct peak" in no.reason and no.score == pytest.approx(3.0 / w.sum())


def test_demeaning_removes_a_constant_bias():
    rng = np.random.default_rng(8)
    fmap = random_field_map((200, 200), 5.0, 40.0, 100.0, rng, kind=KIND_TF, origin=ORIGIN)
    s = 5.0 * np.arange(20)  # an L-shaped 95 m section
    truth = np.array([500.0, 500.0]) + np.column_stack([np.minimum(s, 50.0), np.maximum(s - 50.0, 0.0)])
    lat, lon = latlon(fmap, truth[:, 0], truth[:, 1])
    z = fmap.value(lat, lon) + 80.0 + rng.normal(0, 1.0, s.size)  # uncalibrated sensor: +80 nT bias
    off, P = np.array([10.0, -8.0]), np.eye(2) * 225
    w = make_window(fmap, np.arange(float(s.size)), truth, z, 1.0, KIND_TF, off, P, np.zeros(2))
    fix = LikelihoodMatcher(method="ml", demean=True).match(w, fmap)
    assert fix.available, fix.reason
    assert np.hypot(*(local(fmap, fix.lat, fix.lon) - truth[-1])) < 2.0
    biased = LikelihoodMatcher(method="ml").match(w, fmap)  # without demeaning the bias wrecks the match
    assert not biased.available or np.hypot(*(local(fmap, biased.lat, biased.lon) - truth[-1])) > 2.0


def test_min_fix_sigma_adds_in_quadrature_and_keeps_the_fix():
    """``min_fix_sigma_m`` adds s^2 I to the fix covariance; the fix position and availability are unchanged."""
    rng = np.random.default_rng(8)
    fmap = random_field_map((200, 200), 5.0, 40.0, 100.0, rng, kind=KIND_TF, origin=ORIGIN)
    s = 5.0 * np.arange(20)
    truth = np.array([500.0, 500.0]) + np.column_stack([s, np.zeros_like(s)])
    lat, lon = latlon(fmap, truth[:, 0], truth[:, 1])
    z = fmap.value(lat, lon) + rng.normal(0, 1.0, s.size)
    w = make_window(
        fmap, np.arange(float(s.size)), truth, z, 1.0, KIND_TF, np.array([10.0, -8.0]), np.eye(2) * 225, np.zeros(2)
    )
    base = LikelihoodMatcher(method="ml", max_fix_sigma_m=1e3).match(w, fmap)
    floored = LikelihoodMatcher(method="ml", max_fix_sigma_m=1e3, min_fix_sigma_m=50.0).match(w, fmap)
    assert base.available and floored.available
    assert (floored.lat, floored.lon) == (base.lat, base.lon)
    assert np.allclose(floored.cov_ne - base.cov_ne, np.eye(2) * 2500.0)
    with pytest.raises(ConfigError, match="min_fix_sigma_m"):
        LikelihoodMatcher(min_fix_sigma_m=-1.0)


@pytest.mark.parametrize(("demean", "difference"), [(False, False), (True, False), (False, True), (True, True)])
def test_compiled_section_scan_equals_array_scan(monkeypatch, demean, difference):
    import magnav_ins.aiding.matchers.likelihood as lk

    rng = np.random.default_rng(9)
    fmap = random_field_map((120, 120), 5.0, 40.0, 100.0, rng, kind=KIND_V, origin=ORIGIN)
    truth = np.array([300.0, 280.0]) + 4.0 * np.arange(6)[:, None] * np.array([0.8, 0.6])
    lat, lon = latlon(fmap, truth[:, 0], truth[:, 1])
    z = fmap.value(lat, lon) + rng.normal(0, 2.0, (6, 3))
    w = make_window(fmap, np.arange(6.0), truth, z, 2.0, KIND_V, np.array([7.0, -5.0]), np.eye(2) * 100, np.zeros(2))
    m = LikelihoodMatcher(demean=demean, difference=difference)
    fast = m.surface(w, fmap)
    monkeypatch.setattr(lk, "_local_grid", lambda fmap, frame: None)
    slow = m.surface(w, fmap)
    assert fast.shape == slow.shape and fast.sigma2 == pytest.approx(slow.sigma2)
    ok = np.isfinite(slow.logl)
    assert np.array_equal(ok, np.isfinite(fast.logl))
    assert fast.logl[ok] == pytest.approx(slow.logl[ok], rel=1e-9, abs=1e-9)
    assert fast.variability == pytest.approx(slow.variability, rel=1e-12)


def test_distance_sampling_of_a_section():
    from magnav_ins.aiding.matchers.likelihood import distance_sample

    # a vehicle that stops (repeated position) and changes speed, along north; field = 2 * northing
    dn = np.array([0.0, 0.5, 0.5, 0.5, 2.0, 4.0, 7.0]) - 7.0
    de = np.zeros_like(dn)
    z = (2.0 * dn)[:, None]
    n2, e2, z2 = distance_sample(dn, de, z, 1.0)
    assert n2 == pytest.approx(np.arange(-7.0, 0.5, 1.0))
    assert z2[:, 0] == pytest.approx(2.0 * n2)  # linear field: interpolation is exact
    assert np.all(e2 == 0.0)


# ---------------------------------------------------------------------------------------------- Bayes grid
def test_tail_sigma_of_gaussian_is_sigma():
    x = np.arange(-10.0, 10.0, 0.01)
    pdf = np.exp(-0.5 * (x - 0.3) ** 2 / 1.7**2)
    assert _tail_sigma(pdf, x, 0.3, 0.1587) == pytest.approx(1.7, rel=2e-3)


def test_bayes_grid_hallway_rms_below_0p3_m_table_4_1():
    """Storms Table 4.1 (short): dt 0.1 s, sigma_a 0.08 m/s^2, updates every 1.5 s, 1 mG noise, initial sigma
    1.5 m, V_X 0.5 m/s, filter at (0, 0) and vehicle at (0, 1.145) m; 10 runs of 30 s; Storms' R (16 %/84 %)."""
    hm = hallway_map(np.random.default_rng(7))
    bg = BayesGridMatcher(covariance="spread")
    dt, sa, smeas = 0.1, 0.08, 1.0 * NT_PER_MILLIGAUSS
    F = np.eye(4)
    F[0, 2] = F[1, 3] = dt
    q = np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]) * sa**2
    Q = np.zeros((4, 4))
    Q[np.ix_([0, 2], [0, 2])] = q
    Q[np.ix_([1, 3], [1, 3])] = q
    H = np.eye(2, 4)
    errs = []
    for run in range(10):
        r = np.random.default_rng(100 + run)
        xt = np.array([0.0, 1.145, 0.5, 0.0])  # north (Storms X), east (Y), v_n, v_e
        x = np.array([0.0, 0.0, 0.5, 0.0])
        P = np.diag([1.5**2, 1.5**2, 0.01, 0.01])
        st = None
        for k in range(1, 301):
            xt = F @ xt
            x, P = F @ x, F @ P @ F.T + Q
            if k % 15:
                continue
            lat, lon = latlon(hm, xt[0], xt[1])
            z = hm.value(lat, lon)[0] + r.normal(0, smeas, 3)
            pr = nav_estimate(hm, k * dt, x[:2], x[2:], P[:2, :2])
            st = bg.initiate(pr) if st is None else bg.predict(st, pr)
            st = bg.update(st, FieldReadings(np.array([k * dt]), z[None], smeas, KIND_V), hm)
            fix = bg.to_fix(st)
            if fix.available:
                S = H @ P @ H.T + fix.cov_ne
                K = P @ H.T @ np.linalg.inv(S)
                x = x + K @ (local(hm, fix.lat, fix.lon) - x[:2])
                P = (np.eye(4) - K @ H) @ P
            if k >= 45:  # after the first few updates
                errs.append(np.hypot(*(x[:2] - xt[:2])))
    rms = float(np.sqrt(np.mean(np.square(errs))))
    assert rms < 0.3, rms


def test_bayes_grid_rejects_two_equal_peaks():
    # map with two identical features inside the prior region: the posterior has two equal peaks
    n_ax = np.arange(0.0, 40.0, 0.5)
    e_ax = np.arange(0.0, 40.0, 0.5)
    gn, ge = np.meshgrid(n_ax, e_ax, indexing="ij")
    bump = lambda c: 500.0 * np.exp(-((gn - c[0]) ** 2 + (ge - c[1]) ** 2) / (2 * 1.0**2))  # noqa: E731
    vals = bump((20.0, 16.0)) + bump((20.0, 24.0))
    from magnav_ins.maps.grid import GridMap

    fmap = GridMap(n_ax, e_ax, vals, kind=KIND_TF, frame="local", altitude_m=0.0, origin=ORIGIN)
    bg = BayesGridMatcher()
    st = bg.initiate(nav_estimate(fmap, 0.0, np.array([20.0, 20.0]), np.zeros(2), np.eye(2) * 9.0))
    st = bg.update(st, FieldReadings(np.array([0.0]), np.array([500.0]), 5.0, KIND_TF), fmap)
    fix = bg.to_fix(st)
    assert not fix.available and "ambiguous" in fix.reason


# ---------------------------------------------------------------------------------------------- PMHT
def _pmht_window(fmap, rng, T=30, offset=(40.0, -35.0)):
    dt, sig = 10.0, 0.5
    v = np.array([12.0, 9.0])
    truth = np.array([1200.0, 1300.0]) + v * dt * np.arange(T)[:, None]
    lat, lon = latlon(fmap, truth[:, 0], truth[:, 1])
    z = fmap.value(lat, lon) + rng.normal(0, sig, T)
    P = np.eye(2) * 30.0**2
    return make_window(fmap, dt * np.arange(T), truth, z, sig, KIND_G, np.asarray(offset), P, v), truth


def test_pmht_converges_in_a_few_iterations_on_gravity_field():
    rng = np.random.default_rng(31)
    fmap = random_field_map((400, 400), 10.0, 300.0, 20.0, rng, kind=KIND_G, origin=ORIGIN)
    w, truth = _pmht_window(fmap, rng)
    # Wang's claim is about the EM started at the INS (as published); started at the offset likelihood's best node
    # (the default, em_start = "likelihood") it converges to the same fix
    m = PMHTMatcher(batch=30, candidates=20, iterations=15, tolerance_m=0.01, em_start="ins")
    res = m.run(w, fmap)
    assert not isinstance(res, str), res
    assert res.iterations <= 8, res.iterations
    fix = m.match(w, fmap)
    other = PMHTMatcher(batch=30, candidates=20, iterations=15, tolerance_m=0.01).match(w, fmap)
    assert np.hypot(*(local(fmap, fix.lat, fix.lon) - local(fmap, other.lat, other.lon))) < 0.5
    assert fix.available, fix.reason
    assert np.hypot(*(local(fmap, fix.lat, fix.lon) - truth[-1])) < 8.0  # INS was 53 m off
    # retrodiction: a fix per scan, each close to its truth
    fixes = PMHTMatcher(mode="retrodiction").match_all(w, fmap)
    assert len(fixes) == 30 and all(f.available for f in fixes)
    err = [np.hypot(*(local(fmap, f.lat, f.lon) - tr)) for f, tr in zip(fixes, truth, strict=True)]
    assert np.median(err) < 8.0


def test_pmht_flags_divergence_when_truth_outside_gate():
    rng = np.random.default_rng(32)
    fmap = random_field_map((400, 400), 10.0, 300.0, 20.0, rng, kind=KIND_G, origin=ORIGIN)
    w, _ = _pmht_window(fmap, rng, offset=(600.0, 0.0))  # 20 sigma off: the true cells are not in the windows
    fix = PMHTMatcher().match(w, fmap)
    assert not fix.available and "diverged" in fix.reason, fix.reason


def test_pmht_ambiguity_term_covers_a_wrong_mode_on_a_periodic_map():
    """A map periodic along north (period 300 m, constant along east): offsets of whole periods fit the readings
    equally well, so the batch likelihood has a mode every 300 m inside the +-696 m gate. With the INS 220 m north of
    the truth the EM climbs the mode one period away; the local covariance (EM, Cramer-Rao bound) claims a few metres,
    the ambiguity term must cover the 300 m (north NEES below the 99 % chi-square(1) bound 6.6); that fix is then
    wider than the 200 m prior everywhere. By default (de-prior, issue 13)
    the gate's information is taken out of that spread too, and the location is not de-priored (the likelihood has
    several modes in the gate, where the Gaussian algebra does not hold): refused as well."""
    rng = np.random.default_rng(33)
    base = random_field_map((400, 400), 10.0, 300.0, 20.0, rng, kind=KIND_G, origin=ORIGIN)
    ny, nx = np.asarray(base.values).shape[:2]
    fmap = base.with_values(20.0 * np.sin(2 * np.pi * 10.0 * np.arange(ny) / 300.0)[:, None] * np.ones((1, nx)))
    fmap = fmap.with_error_layer(0.0, correlation_m=10.0)  # readings drawn from this map: no map error
    T, dt, sig, v = 30, 10.0, 0.5, np.array([12.0, 0.0])
    truth = np.array([300.0, 2000.0]) + v * dt * np.arange(T)[:, None]
    z = fmap.value(*latlon(fmap, truth[:, 0], truth[:, 1])) + rng.normal(0, sig, T)
    w = make_window(fmap, dt * np.arange(T), truth, z, sig, KIND_G, np.array([220.0, 50.0]), np.eye(2) * 200.0**2, v)
    fix = PMHTMatcher(ambiguity_floor=False).match(w, fmap)
    assert fix.available, fix.reason
    d = local(fmap, fix.lat, fix.lon) - truth[-1]
    assert 250.0 < d[0] < 350.0  # the wrong mode, one period north
    assert d[0] ** 2 / fix.cov_ne[0, 0] > 100.0  # the local covariance claims a few metres
    # east is unobservable (the map is constant along east): a partial fix, east variance capped at (10 h)^2
    from magnav_ins.aiding.matchers.pmht import GATE_SIGMA

    assert np.isclose(fix.cov_ne[1, 1], (10 * GATE_SIGMA * 200.0) ** 2, rtol=1e-3)  # h = the gate's half-width
    m = PMHTMatcher(ambiguity_floor=True, ambiguity_deprior=False, deprior_location=False, em_start="ins")
    res = m.run(w, fmap)
    cov, near = m._ambiguity_cov(res, len(res.t) - 1)
    assert near < m.ambiguity_mass and (d[0] ** 2 / cov[0, 0]) < 6.6  # the ambiguity term covers the wrong mode
    # ... and so the fix is no tighter than the 200 m prior in any direction, and honest about the wrong mode (with
    # a 3-sigma gate it was refused as adding no information; the 3.48-sigma gate's own information is less)
    fix = m.match(w, fmap)
    d = local(fmap, fix.lat, fix.lon) - truth[-1]
    assert fix.available and np.linalg.eigvalsh(fix.cov_ne).min() >= 200.0**2, fix.reason
    assert d[0] ** 2 / fix.cov_ne[0, 0] < 6.6
    res = PMHTMatcher().run(w, fmap)
    assert res.ambiguity is not None and res.ambiguity[4] > 1  # several modes in the gate
    fix = PMHTMatcher().match(w, fmap)
    assert not fix.available and "adds no information" in fix.reason, fix.reason


def test_pmht_ambiguity_term_unused_where_the_likelihood_is_unambiguous():
    """On the rough synthetic gravity map the batch likelihood is concentrated about the EM's mode (more than 90 %
    within 1.5 offset cells): with ``ambiguity_mass = 0.9`` (the rule until 2026-12) the fix covariance is the local
    one (to the EM's tolerance: without the ambiguity term the EM starts at the INS, not at the likelihood's best
    offset). The default (1.0) uses the term wherever it exists, and the fix is still close to the truth."""
    rng = np.random.default_rng(31)
    fmap = random_field_map((400, 400), 10.0, 300.0, 20.0, rng, kind=KIND_G, origin=ORIGIN)
    fmap = fmap.with_error_layer(0.0, correlation_m=10.0)  # readings drawn from this map: no map error
    w, _ = _pmht_window(fmap, rng)
    m = PMHTMatcher(ambiguity_mass=0.9)
    res = m.run(w, fmap)
    assert m._ambiguity_cov(res, len(res.t) - 1)[1] > m.ambiguity_mass
    a, b = m.match(w, fmap), PMHTMatcher(ambiguity_floor=False).match(w, fmap)
    assert a.available and b.available
    assert np.allclose(a.cov_ne, b.cov_ne, rtol=1e-3)
    c = PMHTMatcher().match(w, fmap)
    assert c.available and np.hypot(*(local(fmap, c.lat, c.lon) - local(fmap, a.lat, a.lon))) < 10.0


def test_pmht_adaptive_drift_follows_a_drifting_ins_track():
    """The INS track drifts within the batch (velocity error ~ N(0, 0.5^2) m/s per axis: up to ~150 m over the
    290 s batch) and its position sigma grows by 0.5 m/s. A batch held rigid by the fixed 0.05 m/sqrt(s) random walk
    fits the readings badly (the profile check refuses some fixes, and those issued are overconfident); with
    ``adaptive_drift`` the random walk takes the sigma growth (5 m per scan) and the offset likelihood the drift
    relative to the last scan. Measured (seed 31, 20 trials): 19 / 20 fixes, fix NEES mean 11.9 (median 6.0)
    against 15 / 20 and 827 (median 721) for the rigid batch. Still above 2: a velocity error is a deterministic
    ramp, which a random walk of the same end sigma does not cover. Since the offset likelihood is tempered for the
    INS's deformation as a velocity error (``temper``, issue 13) both are honest (NEES 1.21 and 1.28) and the
    adaptive batch is the more accurate; without the temper 7.6 against 92. The tracks run off the 4 km map's north
    edge in their last scans; ``off_map = "impossible"`` keeps that part of the batch out of the offset likelihood, as
    when these figures were measured (the default "holes" does the same beyond the map's extent; with "unknown" the
    rigid batch's misfit on the map makes the field-unknown hypothesis win: its NEES is 30)."""
    rng = np.random.default_rng(31)
    fmap = random_field_map((400, 400), 10.0, 300.0, 20.0, rng, kind=KIND_G, origin=ORIGIN)
    fmap.metadata["level_sigma"] = 0.0  # readings drawn from this map: no level offset
    T, dt, sig, v = 30, 10.0, 0.5, np.array([12.0, 9.0])
    tt = dt * np.arange(T)
    P = np.array([np.eye(2) * (30.0 + 0.5 * t) ** 2 for t in tt])
    nees: dict[tuple[bool, bool], list[float]] = {(a, b): [] for a in (True, False) for b in (True, False)}
    err: dict[tuple[bool, bool], list[float]] = {(a, b): [] for a in (True, False) for b in (True, False)}
    for _ in range(20):
        truth = np.array([1200.0, 1300.0]) + rng.uniform(-300, 300, 2) + v * tt[:, None]
        z = fmap.value(*latlon(fmap, truth[:, 0], truth[:, 1])) + rng.normal(0, sig, T)
        ins = truth + rng.normal(0, 30.0, 2) + rng.normal(0, 0.5, 2) * (tt - tt[-1])[:, None]
        lat, lon = latlon(fmap, ins[:, 0], ins[:, 1])
        w = MatchWindow(FieldReadings(tt, z, sig, KIND_G), lat, lon, np.zeros(T), P, np.tile(v, (T, 1)))
        for ad in (True, False):
            for temper in (True, False):
                fix = PMHTMatcher(adaptive_drift=ad, temper=temper, off_map="impossible").match(w, fmap)
                if fix.available:
                    d = local(fmap, fix.lat, fix.lon) - truth[-1]
                    nees[ad, temper].append(float(d @ np.linalg.solve(fix.cov_ne, d)))
                    err[ad, temper].append(float(np.hypot(*d)))
    assert len(nees[True, True]) >= 16 and len(nees[False, True]) >= 16, {k: len(x) for k, x in nees.items()}
    mean = {k: float(np.mean(x)) for k, x in nees.items()}
    assert mean[True, True] < 3.0 and mean[False, True] < 3.0, mean
    assert mean[True, False] < 20.0 and mean[False, False] > 40.0, mean
    assert np.median(err[True, True]) < np.median(err[False, True]), err


# ---------------------------------------------------------------------------------------------- particle filters
def test_gauss_markov_acceleration_is_stationary_with_sigma():
    rng = np.random.default_rng(41)
    fmap = random_field_map((50, 50), 2.0, 10.0, 10.0, rng, kind=KIND_TF, origin=ORIGIN)
    pf = ParticleFilter(n_particles=4000)
    st = pf.initiate(nav_estimate(fmap, 0.0, np.array([50.0, 50.0]), np.zeros(2), np.eye(2)), rng)
    for k in range(1, 21):  # 20 s = 10 tau: the zero initial acceleration is forgotten
        st = pf.predict(st, nav_estimate(fmap, float(k), np.array([50.0, 50.0]), np.zeros(2), np.eye(2)))
    assert np.std(st.acc) == pytest.approx(5.0, rel=0.05)  # Shockley sec. 5.1: sigma = 5 m/s^2


def test_road_penalisation_pulls_cloud_onto_road():
    fr = LocalFrame(ORIGIN[0], ORIGIN[1])
    e = np.arange(-200.0, 200.0, 1.0)
    lat, lon = fr.to_latlon(np.zeros_like(e), e)  # an east-west road through the origin
    road = TrackMap(lat, lon, 0.0, np.zeros_like(e), kind=KIND_TF)
    rng = np.random.default_rng(42)
    pf = ParticleFilter(
        n_particles=20000, road=road, dynamics="ins", ins_sigma=1e-6, resample_threshold=0.0, init="disc"
    )
    fmap = random_field_map((50, 50), 2.0, 10.0, 10.0, rng, kind=KIND_TF, origin=ORIGIN)
    prior = nav_estimate(fmap, 0.0, local(fmap, ORIGIN[0], ORIGIN[1]), np.zeros(2), np.eye(2))
    st = pf.initiate(prior, rng)
    st = pf.predict(st, nav_estimate(fmap, 1.0, local(fmap, ORIGIN[0], ORIGIN[1]), np.zeros(2), np.eye(2)))
    w = np.exp(st.logw)
    n_mean = w @ st.pos[:, 0]
    n_sd = np.sqrt(w @ (st.pos[:, 0] - n_mean) ** 2)
    # uniform 50 m disc x N(0, 6^2) across the road -> almost exactly N(0, 6^2) (the disc is 8 sigma wide)
    assert abs(n_mean) < 0.3
    assert n_sd == pytest.approx(6.0, rel=0.05)


def test_particle_fix_mode_uses_inner_matcher():
    rng = np.random.default_rng(43)
    fmap = random_field_map((300, 300), 2.0, 25.0, 50.0, rng, kind=KIND_V, origin=ORIGIN)
    pf = ParticleFilter(dynamics="ins", measurement="fix", init="gaussian")
    truth = np.array([300.0, 300.0])
    st = pf.initiate(nav_estimate(fmap, 0.0, truth + [5.0, -4.0], np.zeros(2), np.eye(2) * 36.0), rng)
    lat, lon = latlon(fmap, truth[0], truth[1])
    z = fmap.value(lat, lon)[0] + rng.normal(0, 5.0, 3)
    st = pf.update(st, FieldReadings(np.array([0.0]), z[None], 5.0, KIND_V), fmap)
    fix = pf.to_fix(st)
    assert fix.available, fix.reason
    d = local(fmap, fix.lat, fix.lon) - truth
    assert np.hypot(*d) < 5.0  # the prior was 6.4 m off
    assert d @ np.linalg.solve(fix.cov_ne, d) < 9.0


# ---------------------------------------------------------------------------------------------- geodetic grid maps
def test_matchers_on_a_geodetic_grid_map():
    """Maps on a lat/lon grid have no native local nodes: the scans interpolate (ML section, PMHT batch)."""
    from magnav_ins.core.frames import radii_of_curvature
    from magnav_ins.maps.grid import GridMap
    from magnav_ins.maps.synthetic import gaussian_random_field

    rng = np.random.default_rng(51)
    lat0, lon0 = ORIGIN[0], ORIGIN[1]
    r_n, r_e = (float(x) for x in radii_of_curvature(lat0))
    n_ax = np.arange(300) * 10.0
    e_ax = np.arange(300) * 10.0
    vals = gaussian_random_field((300, 300), 10.0, 300.0, 20.0, rng)
    fmap = GridMap(
        lat0 + n_ax / r_n, lon0 + e_ax / (r_e * np.cos(lat0)), vals, kind=KIND_G, frame="geodetic", altitude_m=0.0
    ).with_error_layer(0.0, 300.0)  # the readings are drawn from this map: it is exact
    fmap.metadata["level_sigma"] = 0.0  # ... and on its level
    # PMHT: 30 scans 71 m apart, inside the 3 km map
    v = np.array([5.0, 5.0])
    truth = np.array([-800.0, -700.0]) + v * 10.0 * np.arange(30)[:, None]  # about the grid centre
    lat, lon = latlon(fmap, truth[:, 0], truth[:, 1])
    z = fmap.value(lat, lon) + rng.normal(0, 0.5, 30)
    w = make_window(fmap, 10.0 * np.arange(30), truth, z, 0.5, KIND_G, np.array([35.0, -20.0]), np.eye(2) * 900, v)
    fix = PMHTMatcher().match(w, fmap)
    assert fix.available, fix.reason
    d = local(fmap, fix.lat, fix.lon) - truth[-1]
    assert np.hypot(*d) < 10.0 and d @ np.linalg.solve(fix.cov_ne, d) < 12.0
    # MLR on the last 12 readings (an 780 m section)
    w12 = make_window(
        fmap, 10.0 * np.arange(12), truth[-12:], z[-12:], 0.5, KIND_G, np.array([35.0, -20.0]), np.eye(2) * 900, v
    )
    fix = LikelihoodMatcher(method="mlr").match(w12, fmap)
    assert fix.available, fix.reason
    d = local(fmap, fix.lat, fix.lon) - truth[-1]
    assert np.hypot(*d) < 10.0 and d @ np.linalg.solve(fix.cov_ne, d) < 12.0


def test_window_floor_cells_gives_a_tight_prior_a_window_of_whole_map_cells():
    """A prior sigma of 3 m makes a search window of +-12 m (grown to +-48 m), inside one 100 m cell of the map:
    the flat-map test sees no nodes' variation and the likelihood of a smooth map cannot fit its peak in it, so no
    fix (the SITL flights' "flat map" refusals just after the GNSS was lost). ``window_floor_cells=2`` scans at least
    two cells each way, and the fix it gives is where the vehicle is (within 3 of its sigmas)."""
    rng = np.random.default_rng(3)
    fmap = exact(random_field_map((60, 60), 100.0, 400.0, 100.0, rng, kind=KIND_TF, origin=ORIGIN))
    s = 5.0 * np.arange(80)  # 400 m at 10 m/s, a reading every 0.5 s
    truth = np.array([2500.0, 2500.0]) + np.column_stack([s, 0.3 * s])
    lat, lon = latlon(fmap, truth[:, 0], truth[:, 1])
    z = fmap.value(lat, lon) + rng.normal(0, 2.0, s.size)
    w = make_window(fmap, 0.5 * np.arange(80.0), truth, z, 2.0, KIND_TF, np.array([2.0, -2.0]), np.eye(2) * 9.0,
                    np.zeros(2))  # fmt: skip
    narrow = LikelihoodMatcher(method="ml", demean=True).match(w, fmap)
    assert not narrow.available
    wide = LikelihoodMatcher(method="ml", demean=True, window_floor_cells=2.0).match(w, fmap)
    assert wide.available, wide.reason
    err = local(fmap, wide.lat, wide.lon) - truth[-1]
    assert float(err @ np.linalg.solve(wide.cov_ne, err)) < 9.0
    with pytest.raises(ConfigError, match="window_floor_cells"):
        LikelihoodMatcher(window_floor_cells=-1.0)


def test_edge_fix_gives_the_cross_track_fix_a_smooth_along_track_map_holds():
    """A map that varies with northing only, flown east-north-east (like the SITL square's west leg, which the map
    fixes across the track but not along it): the likelihood is a ridge
    along the track that reaches the edge of every widened window, so no fix; ``edge_fix`` multiplies it with the
    prior and keeps the likelihood's own information: a fix whose cross-track (north) sigma is tight and holds the
    truth, and whose along-track (east) position is the prior's (the INS's) with a sigma of ``edge_fix_sigma_m``."""
    rng = np.random.default_rng(5)
    base = random_field_map((80, 80), 100.0, 400.0, 100.0, rng, kind=KIND_TF, origin=ORIGIN)
    ridge = np.repeat(base.values[:, :1], base.values.shape[1], axis=1)  # a function of northing only
    fmap = exact(
        GridMap(base.northing, base.easting, ridge, kind=KIND_TF, frame="local", origin=ORIGIN, altitude_m=0.0)
    )
    s = 5.0 * np.arange(80)  # 400 m at 10 m/s, a reading every 0.5 s
    truth = np.array([4000.0, 2000.0]) + np.column_stack([0.3 * s, s])  # east-north-east
    lat, lon = latlon(fmap, truth[:, 0], truth[:, 1])
    z = fmap.value(lat, lon) + rng.normal(0, 1.0, s.size)
    offset = np.array([40.0, -60.0])  # the INS is 40 m north and 60 m west of the truth
    P = np.diag([50.0**2, 60.0**2])
    w = make_window(fmap, 0.5 * np.arange(80.0), truth, z, 1.0, KIND_TF, offset, P, np.array([0.0, 10.0]))
    kw = dict(method="ml", demean=True, window_floor_cells=2.0, min_fix_sigma_m=0.0, max_fix_sigma_m=150.0)
    plain = LikelihoodMatcher(**kw, edge_fix=False).match(w, fmap)
    assert not plain.available and plain.reason.startswith("likelihood reaches the edge")
    fix = LikelihoodMatcher(**kw, edge_fix=True).match(w, fmap)
    assert fix.available, fix.reason
    at = local(fmap, fix.lat, fix.lon)
    sd_n, sd_e = np.sqrt(np.diag(fix.cov_ne))
    assert sd_n < 20.0 and abs(at[0] - truth[-1, 0]) < 3.0 * sd_n  # cross-track: fixed, within 3 sigma
    assert sd_e > 5000.0 and abs(at[1] - (truth[-1, 1] + offset[1])) < 1.0  # along-track: the INS's, no information
    assert LikelihoodMatcher().edge_fix  # on by default (the suite's straight tie lines: a ridge along the track)
    with pytest.raises(ConfigError, match="edge_fix_sigma_m"):
        LikelihoodMatcher(edge_fix_sigma_m=0.0)


def test_ml_refuses_a_likelihood_cut_off_by_the_maps_edge():
    """A section flown north up to 20 m short of where the map's data end (its northern rows hold no values, as
    the Osborne tie lines begin at the map's edge): hypotheses north of the truth put readings off the map and are
    impossible, so the likelihood's peak region ends at the data's edge; its moments would be truncated and its
    peak pushed inwards. ML gives "map edge" (no fix), with and without ``edge_fix``; the same section 2 km inside
    the map is fixed, within 3 sigma."""
    rng = np.random.default_rng(11)
    base = random_field_map((80, 80), 100.0, 1500.0, 100.0, rng, kind=KIND_TF, origin=ORIGIN)
    vals = np.array(base.values, dtype=float)
    gap = base.northing >= 6000.0  # no data from 6 km north on: bilinear values end at 5.9 km
    vals[gap, :] = np.nan
    fmap = exact(base.with_values(vals))
    s = 10.0 * np.arange(60)
    P = np.diag([40.0**2, 40.0**2])
    for north_end, expect_fix in ((5880.0, False), (4000.0, True)):
        truth = np.column_stack([north_end - s[::-1], np.full(s.size, 3000.0)])
        lat, lon = latlon(fmap, truth[:, 0], truth[:, 1])
        z = fmap.value(lat, lon) + rng.normal(0, 5.0, s.size)  # a peak region some 60 m wide
        w = make_window(fmap, np.arange(60.0), truth, z, 5.0, KIND_TF, np.array([-30.0, 20.0]), P, np.array([10.0, 0]))
        for edge_fix in (False, True):
            fix = LikelihoodMatcher(method="ml", edge_fix=edge_fix).match(w, fmap)
            if expect_fix:
                assert fix.available, fix.reason
                err = local(fmap, fix.lat, fix.lon) - truth[-1]
                assert float(err @ np.linalg.solve(fix.cov_ne, err)) < 11.8  # 3 sigma (2 dof)
            else:
                assert not fix.available and fix.reason.startswith("map edge"), fix.reason


def test_ml_issues_a_fix_wider_than_the_prior_while_it_adds_information():
    """The issuing rule (issue 16's, as the batch matchers'): a fix 1.5 prior sigmas wide still shrinks the INS
    covariance (by 31 %) and is issued; one 10 prior sigmas wide adds 1 % and is "likelihood too spread"; an
    explicit ``max_fix_sigma_m`` keeps its old meaning (the better direction's 1-sigma at most that)."""
    rng = np.random.default_rng(3)
    fmap = exact(random_field_map((60, 60), 100.0, 800.0, 100.0, rng, kind=KIND_TF, origin=ORIGIN))
    truth = np.column_stack([2000.0 + 10.0 * np.arange(30), np.full(30, 3000.0)])
    lat, lon = latlon(fmap, truth[:, 0], truth[:, 1])
    P = np.diag([40.0**2, 40.0**2])
    w = make_window(fmap, np.arange(30.0), truth, fmap.value(lat, lon), 1.0, KIND_TF, np.zeros(2), P, np.zeros(2))
    m = LikelihoodMatcher(method="ml")
    surf = replace(m.surface(w, fmap), prior_cov=P)
    assert m._too_spread(surf, (1.5 * 40.0) ** 2 * np.eye(2), 0.0, 1.0, True) is None
    wide = m._too_spread(surf, (10.0 * 40.0) ** 2 * np.eye(2), 0.0, 1.0, True)
    assert wide is not None and wide.reason.startswith("likelihood too spread: the fix adds no information")
    capped = LikelihoodMatcher(method="ml", max_fix_sigma_m=40.0)._too_spread(surf, 60.0**2 * np.eye(2), 0.0, 1.0, True)
    assert capped is not None and "above 40 m" in capped.reason


def test_ml_edge_fix_keeps_a_map_edge_likelihood_when_the_prior_stays_off_the_edge():
    """A map that varies with northing only and has no data east of 6 km, flown east-north-east towards that edge (a
    straight line that ends at the map's edge): the likelihood is a ridge along east that runs into the data's edge,
    so without ``edge_fix`` "map edge"; with it (the default) the likelihood times the prior (40 m, 1.5 km from the
    edge: it stays off it) gives the cross-track fix, holding the truth within 3 sigma, and no information along."""
    rng = np.random.default_rng(5)
    base = random_field_map((80, 80), 100.0, 400.0, 100.0, rng, kind=KIND_TF, origin=ORIGIN)
    ridge = np.repeat(base.values[:, :1], base.values.shape[1], axis=1)  # a function of northing only
    ridge[:, base.easting >= 6000.0] = np.nan
    fmap = exact(
        GridMap(base.northing, base.easting, ridge, kind=KIND_TF, frame="local", origin=ORIGIN, altitude_m=0.0)
    )
    s = 5.0 * np.arange(80)
    truth = np.array([4000.0, 4100.0]) + np.column_stack([0.3 * s, s])  # east-north-east, ends 1.5 km from the edge
    lat, lon = latlon(fmap, truth[:, 0], truth[:, 1])
    z = fmap.value(lat, lon) + rng.normal(0, 1.0, s.size)
    P = np.diag([40.0**2, 40.0**2])
    w = make_window(
        fmap, 0.5 * np.arange(80.0), truth, z, 1.0, KIND_TF, np.array([30.0, -20.0]), P, np.array([0, 10.0])
    )
    kw = dict(method="ml", demean=True, window_floor_cells=2.0, window_growth=5)
    plain = LikelihoodMatcher(**kw, edge_fix=False).match(w, fmap)
    assert not plain.available and plain.reason.startswith("map edge"), plain.reason
    fix = LikelihoodMatcher(**kw).match(w, fmap)
    assert fix.available, fix.reason
    at = local(fmap, fix.lat, fix.lon)
    sd_n, sd_e = np.sqrt(np.diag(fix.cov_ne))
    assert sd_n < 20.0 and abs(at[0] - truth[-1, 0]) < 3.0 * sd_n  # cross-track: fixed
    assert sd_e > 5000.0  # along-track: nothing
