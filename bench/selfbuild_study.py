"""Self-building maps while navigating (Raquet, Shockley & Fisher, seed 000 sec. 2.1 and 4.0; Shockley, seed 003
sec. 6.2): a second pass over an area navigates on the map the first pass built, in the same run; and maps of two
users amalgamated, preferring the most current readings and weighing each user's position error.

**Same run.** A cart with a bar of five 3-axis magnetometers across it (0.2 m apart, 1 mG noise, a reading each
0.5 s) drives two laps of a 20 m square (0.5 m/s, corners filleted at 1 m, Storms' random wander, sigma_a 0.02
m/s^2) over a random 3-axis field (12 mG, 0.6 m correlation: the Storms-like hallway's statistics). Its filter is
Storms' constant-velocity Kalman filter with the turn command (``aiding.fusion.cv_kf``). GNSS (0.1 m) is there on
lap 1 only. The online map (``maps.selfbuild.OnlineMapBuilder``, 0.2 m nodes) takes every reading while the
filter's 1-sigma is below 0.25 m, weighted by ``1 / (sigma^2 + g^2 sigma_pos^2)``; on lap 2 a Bayes grid fix (the
centre sensor, Storms' R rule, the map's own error layer) every 1.5 s updates the filter, and readings keep going
in while the filter is trusted. Lap-2 horizontal RMS is compared with the same filter without any map (dead
reckoning once GNSS is lost) and with the true field as map (the limit).

**Across users.** User A maps the square at t = 0 with GNSS of 0.05 m; at t = 600 s a 2 m patch of the field
changes (a 20 mG bump: furniture moved); user B maps it at t = 1200 s with a worse position (0.1 m) and two sensors.
``amalgamate(by="variance")`` keeps, per node, the better-determined mean (mostly A's, stale on the patch);
``by="current"`` ages each contribution by the field's change rate (stated here from the bump: (20 mG)^2 / 600 s)
(stated here from the bump: (20 mG)^2 / 600 s) and combines them: the RMS of each map against the field as it is
now, on the patch and elsewhere, over the nodes both users mapped.

    python bench/selfbuild_study.py --runs 10
    python bench/selfbuild_study.py --runs 10 --json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

import numpy as np

ORIGIN = (np.radians(39.78), np.radians(-84.08), 0.0)
NT_PER_MG = 100.0
SQUARE = [[5.0, 5.0], [25.0, 5.0], [25.0, 25.0], [5.0, 25.0]]
OFFSETS = np.array([-0.4, -0.2, 0.0, 0.2, 0.4])
#: the field change on the patch between the two users (mG)
BUMP_MG = 20.0


def field(seed: int = 7):
    from magnav_ins.core.types import FieldKind
    from magnav_ins.maps.synthetic import random_field_map

    return random_field_map((301, 301), 0.1, 0.6, 12.0 * NT_PER_MG, np.random.default_rng(seed),
                            kind=FieldKind.VECTOR_FIELD_NT, origin=ORIGIN)  # fmt: skip


def gradient_rms(fmap: Any) -> float:
    v = np.asarray(fmap.values, float)
    gn, ge = np.gradient(v, 0.1, 0.1, axis=(0, 1))
    return float(np.sqrt(np.nanmean(gn**2 + ge**2)))


def one_run(truth_map: Any, seed: int, g_rms: float) -> dict[str, float]:
    from magnav_ins.aiding.fusion.cv_kf import CvKalmanFuser
    from magnav_ins.aiding.matchers import BayesGridMatcher
    from magnav_ins.core.types import FieldReadings, Fix, ImuBatch, NavEstimate, NavState
    from magnav_ins.ins.ground_path import Wander, ground_path
    from magnav_ins.ins.simulate import ideal_imu
    from magnav_ins.maps.selfbuild import OnlineMapBuilder

    rng = np.random.default_rng([2026, seed])
    pts = SQUARE + SQUARE + [SQUARE[0]]
    rate = 20.0
    tr = ground_path(pts, 0.5, rate, ORIGIN, corner_radius_m=1.0, rng=rng,
                     wander=Wander(accel_sigma_mps2=0.02, cross_gain=0.1, along_gain=0.1, max_offset_m=0.5))  # fmt: skip
    imu = ideal_imu(tr)
    imu_gyro = imu.gyro_b + rng.normal(0.0, 1e-3, imu.gyro_b.shape)
    T = tr.t[-1]
    t_lose = 0.5 * T
    n_true, e_true = truth_map.to_local(tr.lat, tr.lon)
    head = np.arctan2(tr.v_n[:, 1], tr.v_n[:, 0])
    sigma = 1.0 * NT_PER_MG
    P0 = np.eye(15) * 1e-6
    P0[0, 0] = P0[1, 1] = 0.1**2
    P0[3, 3] = P0[4, 4] = 0.02**2
    init = NavEstimate(tr.at(0), P0)
    results: dict[str, float] = {}
    built_err = np.nan
    for mode in ("no_map", "self_built", "true_map"):
        kf = CvKalmanFuser(init, None, accel_sigma_mps2=0.02, turn_command=True)
        builder = OnlineMapBuilder(truth_map, sigma, g_rms, trust_sigma_m=0.25) if mode == "self_built" else None
        bg = BayesGridMatcher()
        r = np.random.default_rng([2027, seed])  # the same GNSS and reading noise for every mode
        errs = []
        next_read, next_fix = 0.5, 1.5
        for k in range(1, len(tr.t)):
            kf.propagate(ImuBatch(tr.t[k : k + 1], imu_gyro[k : k + 1], imu.accel_b[k : k + 1]))
            t = tr.t[k]
            if t >= next_read - 1e-9:
                next_read += 0.5
                right = np.array([-np.sin(head[k]), np.cos(head[k])])
                sn, se = n_true[k] + OFFSETS * right[0], e_true[k] + OFFSETS * right[1]
                la, lo = truth_map.from_local(sn, se)
                z = truth_map.value(la, lo) + r.normal(0.0, sigma, (len(OFFSETS), 3))
                est = kf.estimate()
                en, ee = truth_map.to_local(np.array([est.nav.lat]), np.array([est.nav.lon]))
                psi = float(np.arctan2(est.nav.v_n[1], est.nav.v_n[0]))
                rgt = np.array([-np.sin(psi), np.cos(psi)])
                ela, elo = truth_map.from_local(en[0] + OFFSETS * rgt[0], ee[0] + OFFSETS * rgt[1])
                gnss = r.normal(0.0, 0.1, 2)
                if builder is not None:
                    builder.offer(ela, elo, z, est.cov_ne, t)
                if t >= next_fix - 1e-9:
                    next_fix += 1.5
                    if t < t_lose:  # lap 1: GNSS
                        gla, glo = truth_map.from_local(
                            np.array([n_true[k] + gnss[0]]), np.array([e_true[k] + gnss[1]])
                        )
                        kf.correct(Fix(t, float(gla[0]), float(glo[0]), np.eye(2) * 0.01, True, "", 0.0, "gnss"))
                    elif mode != "no_map":
                        fmap = truth_map if mode == "true_map" else builder.current_map()  # type: ignore[union-attr]
                        Pf = np.eye(15) * 1e-6
                        Pf[:2, :2] = est.cov_ne
                        prior = NavEstimate(NavState(t, est.nav.lat, est.nav.lon, 0.0, np.zeros(3), est.nav.q_nb), Pf)
                        mz = bg.update(bg.initiate(prior), FieldReadings(np.array([t]), z[2][None], sigma,
                                                                         truth_map.kind), fmap)  # fmt: skip
                        fix = bg.to_fix(mz)
                        if fix.available:
                            kf.correct(fix)
            if t >= t_lose:
                est = kf.estimate()
                en, ee = truth_map.to_local(np.array([est.nav.lat]), np.array([est.nav.lon]))
                errs.append(float(np.hypot(en[0] - n_true[k], ee[0] - e_true[k])))
        results[f"{mode}_lap2_rms_m"] = float(np.sqrt(np.mean(np.square(errs))))
        results[f"{mode}_lap2_max_m"] = float(np.max(errs))
        if builder is not None:
            m = builder.current_map()
            v = np.asarray(m.values)
            ok = np.all(np.isfinite(v), axis=-1)
            built_err = float(np.sqrt(np.mean((v[ok] - np.asarray(truth_map.values)[ok]) ** 2)))
            results["built_nodes"] = int(ok.sum())
            results["built_taken_fraction"] = builder.taken / max(builder.offered, 1)
    results["built_map_rms_nt"] = built_err
    return results


def across_users(truth_map: Any, seed: int, g_rms: float) -> dict[str, float]:
    from magnav_ins.maps.selfbuild import MapAccumulator, amalgamate

    rng = np.random.default_rng([2028, seed])
    y, x = truth_map.axes
    gn, ge = np.meshgrid(y, x, indexing="ij")
    bump_centre = np.array([25.0, 15.0])
    bump = BUMP_MG * NT_PER_MG * np.exp(-0.5 * ((gn - bump_centre[0]) ** 2 + (ge - bump_centre[1]) ** 2) / 0.7**2)
    now = np.asarray(truth_map.values, float) + bump[:, :, None]
    new_map = truth_map.with_values(now)
    patch = np.hypot(gn - bump_centre[0], ge - bump_centre[1]) < 1.5
    s = np.linspace(0, 80, 1600)
    from magnav_ins.ins.ground_path import Path2D

    c, psi = Path2D.from_points(SQUARE + [SQUARE[0]], 1.0).at(s)
    right = np.column_stack([-np.sin(psi), np.cos(psi)])
    built = []
    for fmap, sig_pos, offs, t0 in ((truth_map, 0.05, OFFSETS, 0.0), (new_map, 0.1, OFFSETS[1::2], 1200.0)):
        acc = MapAccumulator.like(truth_map, f"user at t={t0:.0f} s")
        for o in offs:
            tn, te = c[:, 0] + o * right[:, 0], c[:, 1] + o * right[:, 1]
            la, lo = fmap.from_local(tn, te)
            z = fmap.value(la, lo) + rng.normal(0.0, NT_PER_MG, (len(s), 3))
            en, ee = tn + rng.normal(0.0, sig_pos, len(s)), te + rng.normal(0.0, sig_pos, len(s))
            ela, elo = truth_map.from_local(en, ee)
            acc.add(ela, elo, z, weights=1.0 / (NT_PER_MG**2 + g_rms**2 * sig_pos**2), t=t0 + s / 0.5)
        built.append(acc.result())
    rate = (BUMP_MG * NT_PER_MG) ** 2 / 600.0
    both = np.all(np.isfinite(np.asarray(built[0].mean.values)), axis=-1) & np.all(
        np.isfinite(np.asarray(built[1].mean.values)), axis=-1
    )  # the nodes both users mapped: where a rule has a choice to make
    out = {}
    for rule, m in (("by_variance", amalgamate(built, by="variance")),
                    ("by_current", amalgamate(built, by="current", change_rate=rate, t_now=1400.0)),
                    ("user_a_only", built[0]), ("user_b_only", built[1])):  # fmt: skip
        v = np.asarray(m.mean.values, float)
        ok = np.all(np.isfinite(v), axis=-1) & both
        d = v - now
        out[f"{rule}_patch_rms_nt"] = float(np.sqrt(np.mean(d[ok & patch] ** 2)))
        out[f"{rule}_elsewhere_rms_nt"] = float(np.sqrt(np.mean(d[ok & ~patch] ** 2)))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    fm = field()
    g = gradient_rms(fm)
    runs = [one_run(fm, s, g) for s in range(args.runs)]
    users = [across_users(fm, s, g) for s in range(args.runs)]
    keys = runs[0].keys()
    summary = {k: {"median": float(np.median([r[k] for r in runs])), "min": float(np.min([r[k] for r in runs])),
                   "max": float(np.max([r[k] for r in runs]))} for k in keys}  # fmt: skip
    usum = {k: float(np.median([u[k] for u in users])) for k in users[0]}
    wall = time.perf_counter() - t0
    if args.json:
        print(json.dumps({"same_run": summary, "across_users": usum, "runs": args.runs, "wall_s": wall},
                         separators=(",", ":")))  # fmt: skip
        return 0
    print(f"Same run, lap 2 without GNSS ({args.runs} runs; median [min, max]):\n")
    print("| map on lap 2 | horizontal RMS (m) | max (m) |\n|---|---:|---:|")
    for mode, label in (("no_map", "none (dead reckoning)"), ("self_built", "built on lap 1 (and lap 2)"),
                        ("true_map", "the true field (limit)")):  # fmt: skip
        a, b = summary[f"{mode}_lap2_rms_m"], summary[f"{mode}_lap2_max_m"]
        print(f"| {label} | {a['median']:.3f} [{a['min']:.3f}, {a['max']:.3f}] | {b['median']:.2f} |")
    print(f"\nbuilt map: {summary['built_map_rms_nt']['median']:.0f} nT RMS against the truth on "
          f"{summary['built_nodes']['median']:.0f} nodes\n")  # fmt: skip
    print("Across users (median over runs; RMS against the field as it is now, nT):\n")
    print("| map | on the changed patch | elsewhere |\n|---|---:|---:|")
    for rule in ("user_a_only", "user_b_only", "by_variance", "by_current"):
        print(f"| {rule} | {usum[f'{rule}_patch_rms_nt']:.0f} | {usum[f'{rule}_elsewhere_rms_nt']:.0f} |")
    print(f"\n({wall:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
