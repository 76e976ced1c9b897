"""Real indoor 3-axis magnetometer data with ground truth: the four phone walks of Kok & Solin (2024), matched with
Storms' Bayes grid and Shockley's ML on a map built from the walk's own first part.

Data: ``../shared/data/indoor_magnetic_kok/`` (PROVENANCE sec. 9; github.com/manonkok/1d-magnetic-field-slam, MIT):
a phone (iPhone) walked indoors, magnetometer ``m`` (uT, phone sensor frame, 10 Hz), orientation ``quat``
(scalar first) and positions ``dPos`` from ARKit visual-inertial odometry, the ground truth. Frames, as the repo's own
``tools/prepareData.m`` uses them: the ARKit body frame is the sensor frame turned by ``rotz(-pi/2)``; positions are
the cumulative sum of ``dPos`` (x, y horizontal, z vertical); the library walk's first 150 samples are cut. Here the
field is taken to the ARKit world frame, ``m_w = R(quat) rotz(-pi/2) m`` (checked on the data: its mean then holds
the Earth's field, |mean| 38-49 uT, ~90 % of it on the vertical axis; the other order of rotation leaves 8-10 uT),
and to the levelled body frame ``m_b = Rz(yaw)^T m_w`` (what a body-fixed sensor reads after tilt compensation:
Shockley's "body frame" maps, seed 003 sec. 4.1). Axes: north = world x, east = world y (the world frame has no
geographic reference; the field components keep the world axes).

Per walk (time fractions of the walk): the first ``--map-fraction`` (0.4) builds the map (the readings at their
true positions, gridded along the path: ``maps.selfbuild.path_map``, 0.1 m nodes, 0.15 m kernel, blank beyond
0.5 m); the next ``--cal-fraction`` (0.1) measures the map's error (readings minus map at the true positions:
Shockley's "empirical map noise", Table 4.1) and its correlation length along the path; that error becomes the map's
error layer, so both matchers use it; the rest (0.5) is the test. There a drifting odometry (Kok & Solin's own
drift model, ``runSLAM.m``: position increments in the body frame + N(0, 1e-4 m^2) per step, heading increments +
0.005 rad/s bias + N(0, 1e-4 rad^2) per step) drives Kok & Solin's EKF (position, heading, gyro bias;
``tools/dynamics.m``), started at the true position and heading (0.3 m, 3 deg 1-sigma), and every ``--every`` s a
fix is tried:

* ``bayes_grid``: Storms' Bayes grid (seed 004 sec. 3.4) on the last 3-axis reading, prior from the EKF, R by
  Storms' rule (likelihood lines through the peak, the default), our guards on;
* ``ml``: Shockley's maximum likelihood (seed 003 sec. 4.3.1) on a section of the last ``--section-s`` s of readings
  slid rigidly along the EKF's track, in a window around the EKF's prior;
* ``bayes_grid_body``: the Bayes grid on a map and readings in the levelled body frame: the heading-dependent
  field; a revisit walked in another direction reads differently (the mall's arms are walked out and back).

Both matchers treat map nodes without values as "the field here is unknown" (``off_map = "unknown"``: the
reading's likelihood under the map's own field statistics), so a walk that leaves the mapped path gets "no fix: off
the map" instead of a fix on the map's edge; ``--off-map impossible`` restores the old behaviour.

Figures per walk and method, over ``--seeds`` odometry draws: availability (fixes issued / attempts), fix error
median / 95th percentile (m), fix NEES (2 = consistent), the EKF's horizontal RMS over the test part, and the
odometry-only RMS (no fixes) beside it.

    python bench/kok_walks.py --seeds 10            # markdown tables
    python bench/kok_walks.py --seeds 10 --json     # one JSON line
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "indoor_magnetic_kok"
WALKS = ("eight", "square", "library", "mall")
#: samples cut at the start of each walk (the repo's prepareData.m: library 150, the others none)
CUT = {"library": 149}
#: Kok & Solin's drift settings (runSLAM.m): heading bias (rad/s), heading and position increment variances per step
ODO_BIAS, ODO_SH2, ODO_SP2 = 0.005, 1e-4, 1e-4
UT_TO_NT = 1000.0
#: how the matchers treat grid nodes without map values (the walk's map holds only the path walked in its first
#: part): "unknown" = the field there is drawn from the map's own statistics, so a vehicle that has left the map
#: gets "no fix: off the map" rather than a fix on the map's edge (``--off-map impossible``: the old behaviour)
OFF_MAP = "unknown"
#: a fixed local origin for the maps (the walks are not georeferenced)
ORIGIN = (np.radians(60.0), np.radians(25.0), 0.0)
FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Walk:
    """One walk: ``t`` (N,) s, truth ``ne`` (N, 2) m (world x, y), field ``m_w`` (world) and ``m_b`` (levelled
    body) (N, 3) nT, phone ``yaw`` (N,) rad (ZYX, about the world z axis); ``m_s`` the readings in the ARKit body
    frame (nT) and ``C_wb`` (N, 3, 3) the body-to-world rotations, for a calibration."""

    name: str
    t: FloatArray
    ne: FloatArray
    m_w: FloatArray
    m_b: FloatArray
    yaw: FloatArray
    m_s: FloatArray
    C_wb: FloatArray

    def with_bias(self, b: FloatArray) -> Walk:
        """The walk with the body-frame bias ``b`` (nT) removed from every reading."""
        from scipy.spatial.transform import Rotation

        m_s = self.m_s - b
        m_w = np.einsum("nij,nj->ni", self.C_wb, m_s)
        m_b = Rotation.from_euler("z", self.yaw[:, None]).inv().apply(m_w)
        return Walk(self.name, self.t, self.ne, m_w, m_b, self.yaw, m_s, self.C_wb)


def load_walk(name: str, data: Path = DATA) -> Walk:
    """Read ``name.mat`` (module docstring for the frames)."""
    import scipy.io as sio
    from scipy.spatial.transform import Rotation

    d = sio.loadmat(data / f"{name}.mat")
    pos = np.vstack([np.zeros((1, 3)), np.cumsum(np.asarray(d["dPos"], float), axis=0)])
    k0 = CUT.get(name, 0)
    q = np.asarray(d["quat"], float)[k0:]
    rot = Rotation.from_quat(q[:, [1, 2, 3, 0]])  # the repo's quaternions are scalar-first
    m_s = Rotation.from_euler("z", -np.pi / 2).apply(np.asarray(d["m"], float)[k0:] * UT_TO_NT)
    C_wb = rot.as_matrix()
    m_w = np.einsum("nij,nj->ni", C_wb, m_s)
    yaw = np.unwrap(rot.as_euler("ZYX")[:, 0])
    m_b = Rotation.from_euler("z", yaw[:, None]).inv().apply(m_w)
    t = np.ravel(np.asarray(d["t"], float))[k0:]
    ne = pos[k0:, :2] - pos[k0, :2]
    return Walk(name, t - t[0], ne, m_w, m_b, yaw, m_s, C_wb)


def bias_from_revisits(walk: Walk, sel: NDArray[np.bool_], radius_m: float = 0.15, min_dt_s: float = 5.0):
    """A constant sensor bias ``b`` (body frame, nT; hard iron) from the walk's own revisits: at two readings
    ``i``, ``j`` within ``radius_m`` of each other (and ``min_dt_s`` apart) the world field is the same, so
    ``C_i (m_i - b) = C_j (m_j - b)``; stacked over all such pairs among ``sel``, a linear least-squares problem
    ``(C_i - C_j) b = C_i m_i - C_j m_j``. A phone turning about the vertical only cannot see the bias along its
    rotation axis (the design matrix's smallest singular value is then 3-5 % of the largest on the library and mall
    walks): directions below ``rcond`` (0.1) of the largest singular value are left at zero. Returns ``b`` and the
    number of pairs (b = 0 with fewer than 10)."""
    from scipy.spatial import cKDTree

    idx = np.flatnonzero(sel)
    tree = cKDTree(walk.ne[idx])
    pairs = [(idx[a], idx[b]) for a, b in tree.query_pairs(radius_m) if abs(walk.t[idx[a]] - walk.t[idx[b]]) > min_dt_s]
    if len(pairs) < 10:
        return np.zeros(3), len(pairs)
    i, j = np.array(pairs).T
    A = (walk.C_wb[i] - walk.C_wb[j]).reshape(-1, 3)
    y = (walk.m_w[i] - walk.m_w[j]).reshape(-1)
    b, *_ = np.linalg.lstsq(A, y, rcond=0.1)
    return b, len(pairs)


# ------------------------------------------------------------------------------------------------ odometry + EKF
def odometry(walk: Walk, rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    """Kok & Solin's simulated odometry from the truth: body-frame position increments (N-1, 2) m and measured
    yaw rates (N-1,) rad/s, with their noise and heading bias (``prepareData.m``)."""
    dt = np.diff(walk.t)
    dpsi = np.diff(walk.yaw)
    dp_n = np.diff(walk.ne, axis=0)
    c, s = np.cos(walk.yaw[:-1]), np.sin(walk.yaw[:-1])
    dp_b = np.column_stack([c * dp_n[:, 0] + s * dp_n[:, 1], -s * dp_n[:, 0] + c * dp_n[:, 1]])
    dp_b = dp_b + np.sqrt(ODO_SP2) * rng.standard_normal(dp_b.shape)
    omega = dpsi / dt + ODO_BIAS + np.sqrt(ODO_SH2) * rng.standard_normal(len(dt)) / dt
    return dp_b, omega


class OdometryEkf:
    """Kok & Solin's EKF (``tools/dynamics.m``): state ``[north, east, yaw, gyro bias]``; ``p += R(yaw) dp_b``,
    ``yaw += (omega - b) dt``; noise ``sp2`` on each body increment, ``sh2`` on each heading increment, a small
    bias walk. Position fixes update it (2x2, north/east)."""

    def __init__(self, ne0: FloatArray, yaw0: float, sigma_pos: float, sigma_yaw: float, sigma_bias: float) -> None:
        self.x = np.array([ne0[0], ne0[1], yaw0, 0.0])
        self.P = np.diag([sigma_pos**2, sigma_pos**2, sigma_yaw**2, sigma_bias**2])

    def predict(self, dp_b: FloatArray, omega: float, dt: float) -> None:
        psi = self.x[2]
        c, s = np.cos(psi), np.sin(psi)
        R = np.array([[c, -s], [s, c]])
        dR = np.array([[-s, -c], [c, -s]])
        self.x[:2] = self.x[:2] + R @ dp_b
        self.x[2] = psi + (omega - self.x[3]) * dt
        F = np.eye(4)
        F[:2, 2] = dR @ dp_b
        F[2, 3] = -dt
        G = np.zeros((4, 3))
        G[:2, :2] = R
        G[2, 2] = 1.0
        Q = np.diag([ODO_SP2, ODO_SP2, ODO_SH2])
        self.P = F @ self.P @ F.T + G @ Q @ G.T + np.diag([0, 0, 0, (1e-4) ** 2 * dt])

    def update(self, z_ne: FloatArray, R: FloatArray) -> tuple[FloatArray, float]:
        H = np.eye(2, 4)
        y = z_ne - self.x[:2]
        S = self.P[:2, :2] + R
        nis = float(y @ np.linalg.solve(S, y))
        K = np.linalg.solve(S, H @ self.P).T
        self.x = self.x + K @ y
        A = np.eye(4) - K @ H
        self.P = A @ self.P @ A.T + K @ R @ K.T
        return K[:2] @ y, nis


# ------------------------------------------------------------------------------------------------ maps
def build_map(walk: Walk, frame: str, sel: NDArray[np.bool_]) -> Any:
    from magnav_ins.core.types import FieldKind
    from magnav_ins.maps.selfbuild import path_map

    v = walk.m_w if frame == "world" else walk.m_b
    return path_map(
        walk.ne[sel, 0], walk.ne[sel, 1], v[sel], kind=FieldKind.VECTOR_FIELD_NT, spacing_m=0.1, origin=ORIGIN,
        length_scale_m=0.15, max_distance_m=0.5, name=f"{walk.name} ({frame} frame)",
    )  # fmt: skip


def map_error(fmap: Any, walk: Walk, frame: str, sel: NDArray[np.bool_]) -> tuple[float, float, FloatArray, float]:
    """Readings of the calibration part minus the map at their true positions: RMS over the 3 components (nT),
    the correlation length along the path (m; where the residual autocorrelation falls below exp(-1/2)), the RMS
    per component (nT), and the fraction of the calibration readings the map covers."""
    v = (walk.m_w if frame == "world" else walk.m_b)[sel]
    lat, lon = fmap.from_local(walk.ne[sel, 0], walk.ne[sel, 1])
    r = v - fmap.value(lat, lon)
    ok = np.all(np.isfinite(r), axis=1)
    rr = r[ok] - np.mean(r[ok], axis=0)
    per = np.sqrt(np.mean(rr**2, axis=0))
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(walk.ne[sel][ok], axis=0).T))])
    corr = 0.5
    for lag in range(1, len(rr) // 2):
        rho = np.sum(rr[:-lag] * rr[lag:]) / np.sum(rr * rr)
        if rho < np.exp(-0.5):
            corr = max(float(np.median(s[lag:] - s[:-lag])), 0.1)
            break
    return float(np.sqrt(np.mean(per**2))), corr, per, float(ok.mean())


# ------------------------------------------------------------------------------------------------ one test run
def run_test(
    walk: Walk,
    fmap: Any,
    frame: str,
    method: str,
    test: NDArray[np.intp],
    rng: np.random.Generator,
    every_s: float,
    section_s: float,
    sigma_reading: float,
    off_map: str = OFF_MAP,
) -> dict[str, Any]:
    """Odometry EKF over the test samples ``test`` with fixes from ``method`` (None: odometry only)."""
    from magnav_ins.aiding.matchers import BayesGridMatcher, LikelihoodMatcher
    from magnav_ins.core.protocols import MatchWindow
    from magnav_ins.core.types import FieldKind, FieldReadings, NavEstimate, NavState

    kind = FieldKind.VECTOR_FIELD_NT
    vals = walk.m_w if frame == "world" else walk.m_b
    dp_b, omega = odometry(walk, rng)
    k0 = int(test[0])
    ne0 = walk.ne[k0] + rng.normal(0.0, 0.3, 2)
    ekf = OdometryEkf(ne0, walk.yaw[k0] + rng.normal(0.0, np.radians(3.0)), 0.3, np.radians(3.0), 0.01)
    bg = BayesGridMatcher(off_map=off_map) if method == "bayes_grid" else None
    ml = LikelihoodMatcher(method="ml", off_map=off_map) if method == "ml" else None
    hist: list[tuple[float, float, float]] = []  # (t, n, e) of the EKF at each test sample
    errs, fix_err, fix_nees, attempts, issued, reasons = [], [], [], 0, 0, {}
    next_fix = walk.t[k0] + every_s
    for k in test:
        if k > k0:
            ekf.predict(dp_b[k - 1], omega[k - 1], walk.t[k] - walk.t[k - 1])
        hist.append((walk.t[k], ekf.x[0], ekf.x[1]))
        errs.append(float(np.hypot(*(ekf.x[:2] - walk.ne[k]))))
        if method is None or walk.t[k] < next_fix - 1e-9:
            continue
        next_fix += every_s
        attempts += 1
        P = ekf.P[:2, :2]
        lat, lon = fmap.from_local(np.array([ekf.x[0]]), np.array([ekf.x[1]]))
        if bg is not None:
            Pf = np.eye(15) * 1e-4
            Pf[:2, :2] = P
            nav = NavState(walk.t[k], float(lat[0]), float(lon[0]), 0.0, np.zeros(3), np.array([0, 0, 0, 1.0]))
            st = bg.initiate(NavEstimate(nav, Pf))
            st = bg.update(st, FieldReadings(np.array([walk.t[k]]), vals[k][None], sigma_reading, kind), fmap)
            fix = bg.to_fix(st)
        else:
            nsec = max(2, int(round(section_s / max(np.median(np.diff(walk.t)), 1e-3))))
            h = np.array(hist[-nsec:])
            idx = np.arange(k - len(h) + 1, k + 1)
            la, lo = fmap.from_local(h[:, 1], h[:, 2])
            win = MatchWindow(
                FieldReadings(walk.t[idx], vals[idx], sigma_reading, kind), la, lo, np.zeros(len(h)),
                np.tile(P, (len(h), 1, 1)), np.zeros((len(h), 2)),
            )  # fmt: skip
            fix = ml.match(win, fmap)  # type: ignore[union-attr]
        if not fix.available:
            key = fix.reason.split(":")[0]
            reasons[key] = reasons.get(key, 0) + 1
            continue
        issued += 1
        n_f, e_f = fmap.to_local(np.array([fix.lat]), np.array([fix.lon]))
        z = np.array([float(n_f[0]), float(e_f[0])])
        d = z - walk.ne[k]
        fix_err.append(float(np.hypot(*d)))
        fix_nees.append(float(d @ np.linalg.solve(fix.cov_ne, d)))
        corr, _ = ekf.update(z, np.asarray(fix.cov_ne, float))
        if len(hist) > 1:  # keep the stored track one rigid odometry section (as the pipeline does)
            hist = [(tt, nn + corr[0], ee + corr[1]) for tt, nn, ee in hist]
    e = np.asarray(errs)
    return {
        "rms_m": float(np.sqrt(np.mean(e**2))),
        "max_m": float(e.max()),
        "final_m": float(e[-1]),
        "attempts": attempts,
        "issued": issued,
        "fix_err": fix_err,
        "fix_nees": fix_nees,
        "reasons": reasons,
    }


def walk_table(name: str, args: argparse.Namespace) -> dict[str, Any]:
    walk = load_walk(name, args.data)
    n = len(walk.t)
    T = walk.t[-1]
    map_sel = walk.t < args.map_fraction * T
    cal_sel = (walk.t >= args.map_fraction * T) & (walk.t < (args.map_fraction + args.cal_fraction) * T)
    test = np.flatnonzero(walk.t >= (args.map_fraction + args.cal_fraction) * T)
    bias, pairs = bias_from_revisits(walk, map_sel | cal_sel) if args.calibrate else (np.zeros(3), 0)
    walk = walk.with_bias(bias)
    out: dict[str, Any] = {
        "samples": n,
        "duration_s": float(T),
        "length_m": float(np.sum(np.hypot(*np.diff(walk.ne, axis=0).T))),
        "test_s": float(walk.t[test[-1]] - walk.t[test[0]]),
        "bias_nt": [float(x) for x in bias],
        "bias_pairs": pairs,
    }
    maps: dict[str, Any] = {}
    for frame in ("world", "body"):
        fmap = build_map(walk, frame, map_sel)
        sig, corr, per, cover = map_error(fmap, walk, frame, cal_sel)
        maps[frame] = fmap.with_error_layer(sig, corr, "bench/kok_walks.py: calibration part of the walk")
        lat, lon = fmap.from_local(walk.ne[test, 0], walk.ne[test, 1])
        out[f"map_{frame}"] = {
            "error_rms_nt": sig,
            "error_per_axis_nt": [float(x) for x in per],
            "correlation_m": corr,
            "calibration_covered": cover,
            "test_covered": float(np.mean(np.all(np.isfinite(fmap.value(lat, lon)), axis=1))),
        }
    rows: dict[str, Any] = {}
    for method, frame in (("bayes_grid", "world"), ("ml", "world"), ("bayes_grid_body", "body"), (None, "world")):
        runs = [
            run_test(
                walk, maps[frame], frame, "bayes_grid" if method == "bayes_grid_body" else method, test,
                np.random.default_rng([args.seed, s]), args.every, args.section, args.sigma,
                getattr(args, "off_map", OFF_MAP),
            )
            for s in range(args.seeds)
        ]  # fmt: skip
        fe = np.concatenate([r["fix_err"] for r in runs]) if runs else np.zeros(0)
        fn = np.concatenate([r["fix_nees"] for r in runs]) if runs else np.zeros(0)
        att = sum(r["attempts"] for r in runs)
        rms = np.array([r["rms_m"] for r in runs])
        reasons: dict[str, int] = {}
        for r in runs:
            for k, v in r["reasons"].items():
                reasons[k] = reasons.get(k, 0) + v
        rows[method or "odometry"] = {
            "rms_m_median": float(np.median(rms)),
            "rms_m_min": float(rms.min()),
            "rms_m_max": float(rms.max()),
            "availability": (sum(r["issued"] for r in runs) / att) if att else None,
            "fix_err_median_m": float(np.median(fe)) if fe.size else None,
            "fix_err_p95_m": float(np.percentile(fe, 95)) if fe.size else None,
            "fix_nees_mean": float(np.mean(fn)) if fn.size else None,
            "fix_nees_median": float(np.median(fn)) if fn.size else None,
            "no_fix_reasons": reasons,
        }
    out["methods"] = rows
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--walks", nargs="*", default=list(WALKS))
    ap.add_argument("--seeds", type=int, default=10, help="odometry noise draws per walk")
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--map-fraction", type=float, default=0.4)
    ap.add_argument("--cal-fraction", type=float, default=0.1)
    ap.add_argument("--every", type=float, default=1.0, help="seconds between fix attempts")
    ap.add_argument("--section", type=float, default=3.0, help="ML section length (s)")
    ap.add_argument("--sigma", type=float, default=100.0, help="magnetometer noise per axis (nT)")
    ap.add_argument("--no-calibrate", dest="calibrate", action="store_false", help="keep the sensor bias in")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--off-map", choices=("unknown", "impossible"), default=OFF_MAP, help="map nodes without values")
    args = ap.parse_args(argv)
    if not args.data.is_dir():
        print(f"kok_walks: data folder {args.data} not found (../shared/data/indoor_magnetic_kok)", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    res = {w: walk_table(w, args) for w in args.walks}
    if args.json:
        print(json.dumps({"kok_walks": res, "wall_s": time.perf_counter() - t0}, separators=(",", ":")))
        return 0

    def f(x: Any, d: int = 2) -> str:
        return "-" if x is None else f"{x:.{d}f}"

    for w, r in res.items():
        mw, mb = r["map_world"], r["map_body"]
        print(
            f"\n### {w}: {r['duration_s']:.0f} s, {r['length_m']:.0f} m walked, test {r['test_s']:.0f} s; map error "
            f"(world / body frame) {mw['error_rms_nt'] / 1000:.2f} / {mb['error_rms_nt'] / 1000:.2f} uT RMS, "
            f"correlation {mw['correlation_m']:.2f} m; the map covers {100 * mw['test_covered']:.0f} % of the test "
            f"positions; sensor bias removed {np.round(np.asarray(r['bias_nt']) / 1000, 1).tolist()} uT "
            f"({r['bias_pairs']} revisit pairs)\n"
        )
        print(
            "| method | availability | fix error median / p95 (m) | fix NEES mean / median | RMS (m), median [min, max] |"
        )
        print("|---|---:|---:|---:|---:|")
        for m, x in r["methods"].items():
            avail = "-" if x["availability"] is None else f"{100 * x['availability']:.0f} %"
            print(
                f"| {m} | {avail} | {f(x['fix_err_median_m'])} / {f(x['fix_err_p95_m'])} "
                f"| {f(x['fix_nees_mean'])} / {f(x['fix_nees_median'])} "
                f"| {f(x['rms_m_median'])} [{f(x['rms_m_min'])}, {f(x['rms_m_max'])}] |"
            )
    print(f"\n({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
