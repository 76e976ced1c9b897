"""Matcher latency on a 1000 x 1000 map and fix quality on the contract-test scenarios.

Latency (median and 95th percentile of wall time, and median process CPU time, over repeated calls, after a
warm-up that compiles the numba kernels; the machine's load average is printed with them because a shared
machine inflates wall times):

* ``ml_full_map_scan``: one scalar reading against every node of a 1000 x 1000 local grid (search window off,
  native nodes; target < 20 ms);
* ``ml_window_section``: MLR on a 10-reading section in a 4-sigma search window (prior sigma 50 m, 10 m grid, the
  quantisation-aware default resolution);
* ``pmht_batch``: PMHT-MM with T = 30 scans, 20 candidates, 15 EM iterations forced (tolerance 0) on a 1000 x 1000
  gravity grid, prior sigma 100 m (3-sigma gates of 61 x 61 nodes; target < 20 ms);
* ``particle_update`` / ``particle_predict``: 500 particles, scalar reading (target < 2 ms);
* ``bayes_grid_update``: 3-axis reading, prior sigma 1.5 m (Storms Table 4.1) on a 0.381 m grid.

Quality (``--quality``): for every matcher kind, the contract-test scenario of ``tests/matcher_scenarios.py``
(``K`` trials): availability, median / max fix error (m), mean and median fix NEES (2 is consistent); and ML / MLR /
ABL on a road map (``2 K`` trials per section length) with Shockley's error bins.

    python bench/matchers.py --json [--repeat 30] [--quality] [--trials 40]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from magnav_ins.aiding.matchers import BayesGridMatcher, LikelihoodMatcher, ParticleFilter, PMHTMatcher
from magnav_ins.core.protocols import MatchWindow
from magnav_ins.core.types import FieldKind, FieldReadings, NavEstimate, NavState
from magnav_ins.maps.synthetic import random_field_map

ORIGIN = (np.radians(45.0), np.radians(7.0), 0.0)


def _timeit(fn, repeat: int) -> dict[str, float]:
    fn()  # warm-up (numba compilation, caches)
    ts, cs = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        ts.append(time.perf_counter() - t0)
        cs.append(time.process_time() - c0)
    ts_ms = 1e3 * np.asarray(ts)
    return {
        "median_ms": round(float(np.median(ts_ms)), 3),
        "p95_ms": round(float(np.percentile(ts_ms, 95)), 3),
        "cpu_median_ms": round(float(np.median(1e3 * np.asarray(cs))), 3),
    }


def _window(fmap, truth_ne, z, sigma, kind, off, P, v) -> MatchWindow:
    n = len(z)
    lat, lon = fmap.from_local(truth_ne[:, 0] + off[0], truth_ne[:, 1] + off[1])
    return MatchWindow(
        FieldReadings(np.arange(n, dtype=float) * 10.0, z, sigma, kind),
        lat,
        lon,
        np.zeros(n),
        np.tile(P, (n, 1, 1)),
        np.tile(v, (n, 1)),
    )


def _nav(fmap, t, ne, v, P) -> NavEstimate:
    lat, lon = fmap.from_local(np.array([ne[0]]), np.array([ne[1]]))
    PP = np.eye(15) * 1e-4
    PP[:2, :2] = P
    return NavEstimate(
        NavState(t, float(lat[0]), float(lon[0]), 0.0, np.array([v[0], v[1], 0.0]), np.array([0, 0, 0, 1.0])), PP
    )


def latency(repeat: int) -> dict[str, Any]:
    rng = np.random.default_rng(1)
    out: dict[str, Any] = {}
    tf = random_field_map((1000, 1000), 10.0, 100.0, 100.0, rng, kind=FieldKind.TOTAL_FIELD_ANOMALY_NT, origin=ORIGIN)
    truth = np.array([[5000.0, 5000.0]])
    z = tf.value(*tf.from_local(truth[:, 0], truth[:, 1])) + 1.0
    w1 = _window(tf, truth, z, 1.0, FieldKind.TOTAL_FIELD_ANOMALY_NT, (0.0, 0.0), np.eye(2), np.zeros(2))
    ml_full = LikelihoodMatcher(method="ml", search_window=False, quantisation=0.0)
    out["ml_full_map_scan"] = {**_timeit(lambda: ml_full.match(w1, tf), repeat), "nodes": 1_000_000}

    sec = np.array([4000.0, 4000.0]) + 10.0 * np.arange(10)[:, None] * np.array([0.6, 0.8])
    zs = tf.value(*tf.from_local(sec[:, 0], sec[:, 1])) + rng.normal(0, 1.0, 10)
    w10 = _window(tf, sec, zs, 1.0, FieldKind.TOTAL_FIELD_ANOMALY_NT, (40.0, -30.0), np.eye(2) * 2500, np.zeros(2))
    ml_win = LikelihoodMatcher(method="mlr")
    surf = ml_win.surface(w10, tf)
    out["ml_window_section"] = {**_timeit(lambda: ml_win.match(w10, tf), repeat), "nodes": int(len(surf.logl))}

    g = random_field_map((1000, 1000), 10.0, 300.0, 20.0, rng, kind=FieldKind.GRAVITY_DISTURBANCE_MGAL, origin=ORIGIN)
    v = np.array([15.0, 10.0])
    tr = np.array([3000.0, 3000.0]) + v * 10.0 * np.arange(30)[:, None]
    zg = g.value(*g.from_local(tr[:, 0], tr[:, 1])) + rng.normal(0, 0.5, 30)
    wg = _window(g, tr, zg, 0.5, FieldKind.GRAVITY_DISTURBANCE_MGAL, (60.0, -50.0), np.eye(2) * 100.0**2, v)
    pm = PMHTMatcher(batch=30, candidates=20, iterations=15, tolerance_m=0.0)
    res = pm.run(wg, g)
    fix = pm.match(wg, g)
    err = float(np.hypot(*(np.ravel(g.to_local(np.array([fix.lat]), np.array([fix.lon]))) - tr[-1])))
    out["pmht_batch"] = {
        **_timeit(lambda: pm.match(wg, g), repeat),
        "T": 30,
        "candidates": 20,
        "iterations": int(res.iterations),
        "gate_nodes_per_scan": int(np.prod(2 * np.ceil(res.half[-1] / 10.0) + 1)),
        "fix_error_m": round(err, 2),
    }

    pf = ParticleFilter(n_particles=500, dynamics="ins", init="gaussian")
    p0 = np.array([5000.0, 5000.0])
    st = pf.initiate(_nav(tf, 0.0, p0, np.array([5.0, 0.0]), np.eye(2) * 400.0), np.random.default_rng(2))
    st = pf.predict(st, _nav(tf, 1.0, p0 + [5.0, 0.0], np.array([5.0, 0.0]), np.eye(2) * 400.0))
    zr = FieldReadings(
        np.array([1.0]),
        tf.value(*tf.from_local(np.array([5005.0]), np.array([5000.0]))),
        5.0,
        FieldKind.TOTAL_FIELD_ANOMALY_NT,
    )
    out["particle_update"] = {**_timeit(lambda: pf.update(st, zr, tf), repeat), "particles": 500}
    nxt = _nav(tf, 2.0, p0 + [10.0, 0.0], np.array([5.0, 0.0]), np.eye(2) * 400.0)
    out["particle_predict"] = {**_timeit(lambda: pf.predict(st, nxt), repeat), "particles": 500}

    vm = random_field_map((1000, 1000), 0.381, 0.6, 1200.0, rng, kind=FieldKind.VECTOR_FIELD_NT, origin=ORIGIN)
    bg = BayesGridMatcher()
    pb = np.array([190.0, 190.0])
    bst = bg.initiate(_nav(vm, 0.0, pb, np.zeros(2), np.eye(2) * 1.5**2))
    zb = vm.value(*vm.from_local(np.array([190.3]), np.array([189.6])))
    rb = FieldReadings(np.array([0.0]), zb, 100.0, FieldKind.VECTOR_FIELD_NT)
    out["bayes_grid_update"] = {**_timeit(lambda: bg.update(bst, rb, vm), repeat), "prior_sigma_m": 1.5}
    return out


def quality(trials: int) -> dict[str, Any]:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from matcher_scenarios import SCENARIOS, local  # noqa: PLC0415

    from magnav_ins.aiding.matchers import build_matcher

    out: dict[str, Any] = {}
    for kind, sc in SCENARIOS.items():
        fmap = sc.build_map(np.random.default_rng(11))
        m = build_matcher(sc.config)
        rng = np.random.default_rng(2)
        nees, errs = [], []
        for _ in range(trials):
            fix, truth = sc.trial(m, fmap, rng, "normal")
            if fix.available:
                d = local(fmap, fix.lat, fix.lon) - truth
                nees.append(float(d @ np.linalg.solve(fix.cov_ne, d)))
                errs.append(float(np.hypot(*d)))
        out[kind] = {
            "availability": round(len(errs) / trials, 3),
            "median_error_m": round(float(np.median(errs)), 3) if errs else None,
            "max_error_m": round(float(np.max(errs)), 3) if errs else None,
            "nees_mean": round(float(np.mean(nees)), 3) if nees else None,
            "nees_median": round(float(np.median(nees)), 3) if nees else None,
        }
    return out


def road_comparison(trials: int) -> dict[str, Any]:
    """ML / MLR / ABL on a 1 km winding road (1 m distance-sampled map, 30 nT features of ~5 m, 3 nT noise), whole
    road scanned (no search window), sections of 1, 3 and 10 readings 1 m apart: availability and Shockley's error
    bins (fractions of the fixes issued)."""
    from scipy.ndimage import gaussian_filter1d

    from magnav_ins.aiding.matchers._local import LocalFrame
    from magnav_ins.aiding.matchers.metrics import fix_metrics
    from magnav_ins.maps.track import TrackMap

    rng = np.random.default_rng(3)
    fr = LocalFrame(np.radians(39.8), np.radians(-84.0))
    s = np.arange(0.0, 1000.0, 1.0)
    n, e = 100.0 * np.sin(s / 150.0), s
    lat, lon = fr.to_latlon(n, e)
    prof = gaussian_filter1d(rng.normal(0, 1, s.size + 100), 5)[50:-50]
    prof *= 30.0 / prof.std()
    road = TrackMap(lat, lon, 0.0, prof, kind=FieldKind.TOTAL_FIELD_ANOMALY_NT)
    sig = 3.0
    out: dict[str, Any] = {}
    for nz in (1, 3, 10):
        for method in ("ml", "mlr", "abl"):
            rr = np.random.default_rng(5)
            m = LikelihoodMatcher(method=method, search_window=False)
            fixes, tl, tn = [], [], []
            for _ in range(trials):
                j = int(rr.integers(30, 970))
                idx = np.arange(j - nz + 1, j + 1)
                z = prof[idx] + rr.normal(0, sig, nz)
                w = MatchWindow(
                    FieldReadings(idx * 1.0, z, sig, FieldKind.TOTAL_FIELD_ANOMALY_NT),
                    lat[idx],
                    lon[idx],
                    np.zeros(nz),
                    np.tile(np.eye(2) * 1e6, (nz, 1, 1)),
                    np.zeros((nz, 2)),
                )
                fixes.append(m.match(w, road))
                tl.append(lat[j])
                tn.append(lon[j])
            met = fix_metrics(fixes, np.array(tl), np.array(tn))
            keys = ("availability", "fix_error_lt_3m", "fix_error_3_to_10m", "fix_error_10_to_20m", "fix_error_gt_20m")
            out[f"{method}_section{nz}"] = {k: round(met[k], 3) for k in keys} | {
                "nees_mean": round(met["fix_nees_mean"], 2)
            }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", action="store_true", help="print one JSON line")
    ap.add_argument("--repeat", type=int, default=30)
    ap.add_argument("--quality", action="store_true", help="also run the contract scenarios")
    ap.add_argument("--trials", type=int, default=40)
    args = ap.parse_args()
    t0 = time.perf_counter()
    result: dict[str, Any] = {"bench": "matchers", "map": "1000 x 1000", "latency": latency(args.repeat)}
    result["targets_ms"] = {"ml_full_map_scan": 20.0, "pmht_batch": 20.0, "particle_update": 2.0}
    if args.quality:
        result["quality"] = quality(args.trials)
        result["quality_trials"] = args.trials
        result["road"] = road_comparison(2 * args.trials)
    result["wall_s"] = round(time.perf_counter() - t0, 1)
    result["load_average_1min"] = round(os.getloadavg()[0], 2)
    result["cpu_count"] = os.cpu_count()
    if args.json:
        print(json.dumps(result))
    else:
        for k, v in result["latency"].items():
            print(f"{k:22s} {v}")
        for k, v in {**result.get("quality", {}), **result.get("road", {})}.items():
            print(f"{k:22s} {v}")


if __name__ == "__main__":
    main()
