"""Shockley (2012, seed 003) ch. IV with 3-axis readings in the body frame: road maps per direction of travel or in
the navigation frame, same-vehicle / cross-vehicle / uncalibrated readings, demeaning and differencing, ML and MLR,
Shockley's error bins with confidence intervals over runs.

Map: a 3-axis (NED) Gaussian random field, 30 mG per axis, 10 m correlation, sampled every 1 m along a street grid
(2 east-west and 2 north-south streets of 1 km: ``maps.track.road_network_from_grid``). A strapdown sensor reads the
field in the level body frame, ``B_b = C_bn(psi) B_n`` (``maps.track.ned_to_body``): the same road read the other
way has ``x`` and ``y`` of opposite sign. Each trial drives a section of 4 readings 1 m apart (3 m: Shockley's best
composition, sec. 4.6.1) along a random road in a random direction; the whole map is scanned (no prior), every map
point and both directions of travel being a candidate for the section's last reading.

Maps (rows):

* ``nav + attitude``: the map in NED, the readings rotated to NED with the vehicle's heading (``body_to_ned``; the
  heading from the INS or a compass, 1 deg error); candidates are the map points whose road heading agrees with the
  vehicle's within 45 deg;
* ``per direction``: a body-frame map for each direction of travel (``TrackMap.directional``); no heading needed;
* ``one direction only``: the body-frame map of one pass along each road used for both directions of travel (what
  a map recorded in the body frame by one drive gives; Shockley's maps were recorded per direction).

Readings (Shockley Table 4.1, the empirical map noise, 1-sigma per axis x / y / z): same vehicle 2.66 / 2.51 / 2.77
mG, cross vehicle 7.19 / 7.01 / 7.42 mG; uncalibrated adds a hard-iron bias per vehicle and run, N(0, 30 mG) per
body axis. Compositions (sec. 4.6): raw, demeaned (the section mean removed from the readings and from each
candidate), differenced (successive differences; the noise variance doubles). Methods: ML (the best candidate) and
MLR (the best over the best at least 20 m away, fix only when the ratio exceeds 2: sec. 4.3.2). The last three rows
use 10 m sections (11 readings): demeaning and differencing remove the bias but also the section's own mean or
slow trend, which a 3 m section on a 10 m-correlation field mostly consists of.

Feature rows (sec. 4.6.3, ``aiding.matchers.features``): a second map of the same streets whose field is a smooth
background (20 mG per axis, 100 m correlation) plus sparse features (a bump every 60 m on average, 1.5-3 m wide,
30 mG per axis: Shockley's pipes and bridges); each trial reads 10-20 m before to 10-20 m after a random feature,
the readings rotated to the navigation frame with a 1 deg heading error; the observed feature is aligned on its
defining peak with every map feature read within 45 deg of the vehicle's heading and fitted by RSS. Methods: the best fit always (the ML pick)
and the fit thresholded at an RMS residual of ``FEATURE_RSS_THRESHOLD`` reading sigmas.

Output per row and method: availability and the fractions of fixes in Shockley's bins (< 3 m, 3-10, 10-20, > 20 m),
each with a 95 % interval over the runs (mean +- 1.96 sd / sqrt(runs); the bins over the runs that issued fixes).

    python bench/shockley_vector_roads.py --runs 10 --trials 200
    python bench/shockley_vector_roads.py --json
    python bench/shockley_vector_roads.py --features-only --runs 10 --trials 200
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from typing import Any

import numpy as np

NT_PER_MG = 100.0
SAME = np.array([2.66, 2.51, 2.77]) * NT_PER_MG
CROSS = np.array([7.19, 7.01, 7.42]) * NT_PER_MG
ORIGIN = (np.radians(39.78), np.radians(-84.08), 0.0)
BINS = (3.0, 10.0, 20.0)
BIN_NAMES = ("lt_3m", "3_to_10m", "10_to_20m", "ge_20m")


def road_map():
    from magnav_ins.core.types import FieldKind
    from magnav_ins.maps.synthetic import random_field_map
    from magnav_ins.maps.track import road_network_from_grid

    g = random_field_map((1001, 1001), 1.0, 10.0, 30.0 * NT_PER_MG, np.random.default_rng(12),
                         kind=FieldKind.VECTOR_FIELD_NT, origin=ORIGIN)  # fmt: skip
    return road_network_from_grid(g, [250.0, 750.0], [250.0, 750.0], 1.0)


class Candidates:
    """Every (segment, end point, direction) with a full section of ``k`` points behind it on its road."""

    def __init__(self, track: Any, k: int) -> None:
        fwd, rev = track.directional(False), track.directional(True)
        self.ne = np.column_stack([track.northing, track.easting])
        idx, direction, heading = [], [], []
        for s in range(track.n_segments):
            sl = track.segment(s)
            pts = np.arange(sl.start, sl.stop)
            for j in range(k - 1, len(pts)):
                idx.append(pts[j - k + 1 : j + 1])  # forward: readings at these points, last one = end
                direction.append(0)
                heading.append(track.heading[pts[j]])
            for j in range(len(pts) - k, -1, -1):
                idx.append(pts[j : j + k][::-1])  # reverse
                direction.append(1)
                heading.append(track.heading[pts[j]] + np.pi)
        self.idx = np.array(idx)  # (M, k) map point indices, in reading order
        self.direction = np.array(direction)
        self.heading = np.array(heading)
        self.end = self.idx[:, -1]
        # per point: NED values, and body-frame values forward / reverse (both maps hold every point)
        self.ned = track.values
        order_f = np.arange(len(track))
        self.body_f = np.empty_like(track.values)
        self.body_f[order_f] = fwd.values
        self.body_r = np.empty_like(track.values)
        rev_order = np.concatenate([np.arange(len(track))[track.segment(s)][::-1] for s in range(track.n_segments)])
        self.body_r[rev_order] = rev.values


def compose(x: np.ndarray, how: str) -> np.ndarray:
    """Section composition on the reading axis (-2): raw, demeaned, differenced."""
    if how == "demean":
        return x - x.mean(axis=-2, keepdims=True)
    if how == "difference":
        return np.diff(x, axis=-2)
    return x


def trial(c: Candidates, case: dict[str, Any], rng: np.random.Generator, k: int) -> tuple[bool, float]:
    """One section: returns (fix issued by MLR, error of the ML fix (m)); ML always issues."""
    m = rng.integers(len(c.idx))
    truth_pts, psi = c.idx[m], c.heading[m]
    noise = case["noise"]
    z_b = np.vstack([c.body_f[p] if c.direction[m] == 0 else c.body_r[p] for p in truth_pts])
    z_b = z_b + rng.normal(0.0, 1.0, z_b.shape) * noise + case["bias"](rng)
    var = noise**2 * (2.0 if case["compose"] == "difference" else 1.0)
    if case["map"] == "nav":
        from magnav_ins.maps.track import body_to_ned

        z = body_to_ned(z_b, psi + np.radians(rng.normal(0.0, 1.0)))
        cand = np.flatnonzero(np.cos(c.heading - psi) > np.cos(np.radians(45.0)))
        mv = c.ned[c.idx[cand]]
    elif case["map"] == "per_direction":
        z, cand = z_b, np.arange(len(c.idx))
        mv = np.where((c.direction == 0)[:, None, None], c.body_f[c.idx], c.body_r[c.idx])
    else:  # one direction only: the forward body-frame values, whatever the direction of travel
        z, cand = z_b, np.arange(len(c.idx))
        mv = c.body_f[c.idx]
    zc, mc = compose(z[None], case["compose"]), compose(mv, case["compose"])
    ll = -0.5 * np.sum((zc - mc) ** 2 / var, axis=(1, 2))
    best = int(np.argmax(ll))
    end_ne = c.ne[c.end[cand]]
    err = float(np.hypot(*(end_ne[best] - c.ne[truth_pts[-1]])))
    far = np.hypot(*(end_ne - end_ne[best]).T) >= 20.0
    ratio_ok = (not far.any()) or (ll[best] - ll[far].max() > np.log(2.0))
    return bool(ratio_ok), err


CASES = {
    "nav + attitude, same vehicle": {"map": "nav", "noise": SAME, "uncal": False, "compose": "raw"},
    "per direction, same vehicle": {"map": "per_direction", "noise": SAME, "uncal": False, "compose": "raw"},
    "one direction only, same vehicle": {"map": "one_direction", "noise": SAME, "uncal": False, "compose": "raw"},
    "per direction, cross vehicle": {"map": "per_direction", "noise": CROSS, "uncal": False, "compose": "raw"},
    "per direction, cross vehicle, uncalibrated": {"map": "per_direction", "noise": CROSS, "uncal": True,
                                                   "compose": "raw"},
    "per direction, cross vehicle, uncalibrated, demeaned": {"map": "per_direction", "noise": CROSS, "uncal": True,
                                                             "compose": "demean"},
    "per direction, cross vehicle, uncalibrated, differenced": {"map": "per_direction", "noise": CROSS, "uncal": True,
                                                                "compose": "difference"},
    "10 m sections, cross vehicle, uncalibrated": {"map": "per_direction", "noise": CROSS, "uncal": True,
                                                   "compose": "raw", "k": 11},
    "10 m sections, cross vehicle, uncalibrated, demeaned": {"map": "per_direction", "noise": CROSS, "uncal": True,
                                                             "compose": "demean", "k": 11},
    "10 m sections, cross vehicle, uncalibrated, differenced": {"map": "per_direction", "noise": CROSS, "uncal": True,
                                                                "compose": "difference", "k": 11},
}  # fmt: skip


#: RSS threshold of the feature rows: RMS residual per sample and axis, in reading sigmas
FEATURE_RSS_THRESHOLD = 1.5
FEATURE_CASES = {
    "features, nav + attitude, same vehicle": {"noise": SAME, "uncal": False, "compose": "raw"},
    "features, nav + attitude, cross vehicle": {"noise": CROSS, "uncal": False, "compose": "raw"},
    "features, nav + attitude, cross vehicle, uncalibrated, demeaned": {"noise": CROSS, "uncal": True,
                                                                       "compose": "demean"},
}  # fmt: skip


def feature_map():
    """The feature road map (module docstring): smooth background plus sparse bumps along each street (NED)."""
    from magnav_ins.core.types import FieldKind
    from magnav_ins.maps.synthetic import random_field_map
    from magnav_ins.maps.track import TrackMap, road_network_from_grid

    g = random_field_map((251, 251), 4.0, 100.0, 20.0 * NT_PER_MG, np.random.default_rng(21),
                         kind=FieldKind.VECTOR_FIELD_NT, origin=ORIGIN)  # fmt: skip
    base = road_network_from_grid(g, [250.0, 750.0], [250.0, 750.0], 1.0)
    rng = np.random.default_rng(22)
    v = base.values.copy()
    for s in range(base.n_segments):
        idx = np.arange(len(base))[base.segment(s)]
        x = base.along_track_m[idx]
        for c in np.cumsum(rng.exponential(60.0, 40)):
            if c > x[-1]:
                break
            w = rng.uniform(1.5, 3.0)
            v[idx] += np.exp(-0.5 * ((x - c) / w) ** 2)[:, None] * rng.normal(0.0, 30.0 * NT_PER_MG, 3)
    return TrackMap(base.lat, base.lon, base.h, v, kind=base.kind, segment_id=base.segment_id,
                    origin=base.origin, metadata={"step_m": 1.0})  # fmt: skip


def run_feature_case(track: Any, spec: dict[str, Any], runs: int, trials: int, seed: int) -> dict[str, Any]:
    """Availability and error bins of feature matching by RSS (best fit / thresholded) over ``runs`` x ``trials``."""
    from magnav_ins.aiding.matchers.features import FeatureMatcher

    sigma = float(np.mean(spec["noise"]))
    best = FeatureMatcher(threshold_sigma=4.0, background_m=30.0, min_length_m=2.0, compose=spec["compose"])
    feats, profiles, points = best.map_features(track, sigma)
    ne = np.column_stack([track.northing, track.easting])
    per_run: dict[str, list[list[float]]] = {"best": [], "thresholded": []}
    for r in range(runs):
        rng = np.random.default_rng([seed, 100 + r])
        bias = rng.normal(0.0, 30.0 * NT_PER_MG, 3) if spec["uncal"] else np.zeros(3)
        errs, ok = [], []
        for _ in range(trials):
            f = feats[rng.integers(len(feats))]
            prof, pts = profiles[f.road], points[f.road]
            a = max(0, f.start - int(rng.integers(10, 21)))
            b = min(len(prof), f.stop + int(rng.integers(10, 21)))
            z = prof[a:b] + rng.normal(0.0, 1.0, (b - a, 3)) * spec["noise"] + bias  # heading error below
            psi = float(track.heading[pts[b - 1]]) + (np.pi if f.direction else 0.0)  # travel heading
            from magnav_ins.maps.track import body_to_ned, ned_to_body

            z = body_to_ned(ned_to_body(z, psi), psi + np.radians(rng.normal(0.0, 1.0)))
            k, _, rms, why = best.match_profile(z, track, sigma, psi + np.radians(rng.normal(0.0, 1.0)))
            if k < 0:
                errs.append(np.nan)
                ok.append(False)
                continue
            errs.append(float(np.hypot(*(ne[k] - ne[pts[b - 1]]))))
            ok.append(rms <= FEATURE_RSS_THRESHOLD)
        err, ok_a = np.array(errs), np.array(ok)
        for meth, sel in (("best", np.isfinite(err)), ("thresholded", ok_a)):
            e = err[sel]
            frac = np.histogram(e, bins=[0.0, *BINS, np.inf])[0] / len(e) if len(e) else np.full(4, np.nan)
            per_run[meth].append([sel.mean(), *frac])
    return _summarise(per_run)


def _summarise(per_run: dict[str, list[list[float]]]) -> dict[str, Any]:
    out = {}
    for meth, rows in per_run.items():
        a = np.array(rows)
        n = np.sum(np.isfinite(a), axis=0)
        with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(np.where(n > 0, a, 0.0), axis=0)
            half = np.where(n > 1, 1.96 * np.nanstd(a, axis=0, ddof=1) / np.sqrt(np.maximum(n, 1)), np.nan)
        mean = np.where(n > 0, mean, np.nan)
        out[meth] = {name: [_num(mv), _num(h)] for name, mv, h in zip(("availability", *BIN_NAMES), mean, half,
                                                                    strict=True)}  # fmt: skip
    return out


def run_case(c: Candidates, spec: dict[str, Any], runs: int, trials: int, seed: int, k: int) -> dict[str, Any]:
    per_run: dict[str, list[list[float]]] = {"ml": [], "mlr": []}
    for r in range(runs):
        rng = np.random.default_rng([seed, r])
        b = rng.normal(0.0, 30.0 * NT_PER_MG, 3) if spec["uncal"] else np.zeros(3)
        case = {**spec, "bias": lambda _rng, b=b: b}
        res = [trial(c, case, rng, k) for _ in range(trials)]
        ok = np.array([x[0] for x in res])
        err = np.array([x[1] for x in res])
        for meth, sel in (("ml", np.ones(len(err), bool)), ("mlr", ok)):
            e = err[sel]
            frac = np.histogram(e, bins=[0.0, *BINS, np.inf])[0] / len(e) if len(e) else np.full(4, np.nan)
            per_run[meth].append([sel.mean(), *frac])
    out = {}
    for meth, rows in per_run.items():
        a = np.array(rows)
        n = np.sum(np.isfinite(a), axis=0)
        with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(np.where(n > 0, a, 0.0), axis=0)
            half = np.where(n > 1, 1.96 * np.nanstd(a, axis=0, ddof=1) / np.sqrt(np.maximum(n, 1)), np.nan)
        mean = np.where(n > 0, mean, np.nan)
        out[meth] = {name: [_num(mv), _num(h)] for name, mv, h in zip(("availability", *BIN_NAMES), mean, half,
                                                                    strict=True)}  # fmt: skip
    return out


def _num(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--seed", type=int, default=2012)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--features-only", action="store_true", help="only the feature (RSS) rows")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    cases = {} if args.features_only else CASES
    track = road_map()
    cands = {k: Candidates(track, k) for k in sorted({spec.get("k", 4) for spec in cases.values()})}
    res = {
        name: run_case(cands[spec.get("k", 4)], spec, args.runs, args.trials, args.seed, spec.get("k", 4))
        for name, spec in cases.items()
    }
    ftrack = feature_map()
    fres = {
        name: run_feature_case(ftrack, spec, args.runs, args.trials, args.seed) for name, spec in FEATURE_CASES.items()
    }
    n_cand = len(cands[4].idx) if 4 in cands else 0
    wall = time.perf_counter() - t0
    if args.json:
        print(json.dumps({"shockley_vector_roads": res, "features_rss": fres, "runs": args.runs, "trials": args.trials, "wall_s": wall},
                         separators=(",", ":")))  # fmt: skip
        return 0
    print("| map, readings | method | availability | < 3 m | 3-10 m | 10-20 m | > 20 m |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for name, r in res.items():
        for meth in ("ml", "mlr"):
            x = r[meth]
            cells = " | ".join(
                "-" if x[b][0] is None else f"{100 * x[b][0]:.0f} +- {100 * (x[b][1] or 0.0):.0f} %"
                for b in ("availability", *BIN_NAMES)
            )
            print(f"| {name} | {meth.upper()} | {cells} |")
    labels = {"best": "RSS, best fit (= ML)", "thresholded": f"RSS <= {FEATURE_RSS_THRESHOLD:g} sigma"}
    for name, r in fres.items():
        for meth in ("best", "thresholded"):
            x = r[meth]
            cells = " | ".join(
                "-" if x[b][0] is None else f"{100 * x[b][0]:.0f} +- {100 * (x[b][1] or 0.0):.0f} %"
                for b in ("availability", *BIN_NAMES)
            )
            print(f"| {name} | {labels[meth]} | {cells} |")
    print(f"\n({args.runs} runs x {args.trials} sections, {n_cand} candidates, {track.total_length_m:.0f} m of "
          f"road; {wall:.0f} s)")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
