"""KITTI IMU + GPS (as shipped in the gtsam wheel): UKF, factor graph and free inertial, GPS every N-th epoch.

Frames. The GPS file is in a local Cartesian frame with z up (GTSAM uses it with ``MakeSharedU``); we take it as
East-North-Up (x -> east, y -> north; any other azimuth only turns the tiny Earth-rate vector), place its origin at
48.98 N, 8.39 E, 0 m (Karlsruhe, the place of the 2013 GTSAM file; the converted file records no origin) and convert
to WGS-84 through local NED: north = y, east = x, down = -z. The OXTS IMU axes are x forward, y left, z up (FLU);
body FRD = (x, -y, -z), for both the gyro and the accelerometer. Rates are "mean over the interval ending at t".

Start. At the GPS epoch 1 (as GTSAM's example): position = GPS, velocity = (GPS[2] - GPS[1]) / dt, yaw from that
velocity, roll and pitch from the first specific-force sample (levelling). 1-sigma: 0.3 m, 0.5 m/s, roll/pitch 5 deg
(``--tilt-sigma-deg``; the car accelerates, levelling is off by ~2 deg), 5 deg yaw,
accelerometer bias 0.1 m/s^2 and gyro bias 5e-5 rad/s (the example's bias prior). IMU white noise from
``KittiEquivBiasedImu_metadata.txt`` (AccelerometerSigma 0.01 m/s^2/sqrt(Hz), GyroscopeSigma 1.75e-4 rad/s/sqrt(Hz)).
Bias random walk: the metadata's per-sample bias sigmas (1.67e-4 m/s^2, 2.91e-6 rad/s at AverageDeltaT, i.e.
1.67e-3 m/s^3/sqrt(Hz) and 2.91e-5 rad/s^2/sqrt(Hz)) make both fusers diverge on this data; GTSAM's example in
fact scales its between-bias sigma by sqrt(cumulative sample count) (:func:`example_bias_rw`), so by default BOTH
fusers use the constant random walk that accumulates the same bias variance over the run as the example does:
0.0256 m/s^3/sqrt(Hz) and 4.46e-4 rad/s^2/sqrt(Hz) (derived from the files, not tuned on the errors;
``--accel-bias-rw``, ``--gyro-bias-rw`` override, ``--sweep`` adds a 3x3 grid around it for both fusers). Fixes: GPS every ``--fix-every`` epochs (N/E sigma
0.265 m, the example's 1/0.07 precision) with the GPS height as height aid (same sigma), none in
``--outage START:DURATION`` (s from the start); no NIS gate and a nearly Gaussian Huber (k = 100) by default, since
these are GNSS fixes, not map matches. Errors: horizontal distance to EVERY GPS epoch after the start, of the online
(causal) estimate, and a smoothed one: for the graph the batch-LM solution with a keyframe node at every GPS epoch,
for the UKF its Rauch-Tung-Striebel smoother (``UkfFuser.smooth``): one closed-loop pass about the filter's
trajectory, then ``--smooth-iterations`` - 1 relinearised passes (Gauss-Newton, like the graph's LM). The peer reports a smoothed figure: GTSAM's own ``IMUKittiExampleGPS.py`` (run from the installed wheel, iSAM2 switched to QR;
its final iSAM2 estimate, smoothed).

    python bench/kitti_fusion.py --json [--fix-every 10] [--outage 100:30] [--no-peer]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from magnav_ins.aiding.fusion.common import ImuNoise
from magnav_ins.core.frames import horizontal_error_m, ned_to_geodetic, q_nb_from_euler
from magnav_ins.core.types import LAYOUT_15, Fix, ImuBatch, NavEstimate, NavState
from magnav_ins.core.units import DEG_TO_RAD

ORIGIN = (48.98 * DEG_TO_RAD, 8.39 * DEG_TO_RAD, 0.0)
GPS_SIGMA_M = float(np.sqrt(0.07))
FILES = ("KittiEquivBiasedImu.txt", "KittiGps_converted.txt", "KittiEquivBiasedImu_metadata.txt")


def data_dir() -> Path:
    """The gtsam wheel's Data folder (found from the installed package's location), else ../shared/data/kitti_gtsam."""
    import importlib.util

    spec = importlib.util.find_spec("gtsam")
    if spec is not None and spec.origin is not None:
        d = Path(spec.origin).resolve().parent / "Data"
        if all((d / f).is_file() for f in FILES):
            return d
    d = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kitti_gtsam"
    if all((d / f).is_file() for f in FILES):
        return d
    sys.exit("KITTI files not found in the gtsam package nor in ../shared/data/kitti_gtsam")


def load() -> dict:
    d = data_dir()
    imu = np.loadtxt(d / FILES[0], skiprows=1)
    gps = np.loadtxt(d / FILES[1], delimiter=",", skiprows=1)
    meta = dict(zip(*(ln.split() for ln in (d / FILES[2]).read_text().splitlines()[:2]), strict=False))
    meta = {k: float(v) for k, v in meta.items()}
    flu_to_frd = np.array([1.0, -1.0, -1.0])
    t_imu = imu[1:, 0]  # row 0 holds a sentinel dt
    acc = imu[1:, 2:5] * flu_to_frd
    gyr = imu[1:, 5:8] * flu_to_frd
    r_ned = np.column_stack([gps[:, 2], gps[:, 1], -gps[:, 3]])
    lat, lon, h = ned_to_geodetic(r_ned, *ORIGIN)
    return {"t_imu": t_imu, "acc": acc, "gyr": gyr, "t_gps": gps[:, 0], "lat": lat, "lon": lon, "h": h,
            "r_ned": r_ned, "gps_xyz": gps[:, 1:4], "meta": meta}  # fmt: skip


def split_at(t: np.ndarray, w: np.ndarray, f: np.ndarray, cuts: np.ndarray) -> tuple:
    """Insert sample ends at the times ``cuts`` (the straddling rate sample is cut in two, same rates)."""
    idx = np.searchsorted(t, cuts)
    keep = (idx < len(t)) & (idx > 0)
    new = cuts[keep & ~np.isclose(t[np.minimum(idx, len(t) - 1)], cuts, atol=1e-9, rtol=0)]
    ins = np.searchsorted(t, new)
    return np.insert(t, ins, new), np.insert(w, ins, w[ins], axis=0), np.insert(f, ins, f[ins], axis=0)


def initial(data: dict, i0: int, tilt_sigma: float = 2 * DEG_TO_RAD) -> NavEstimate:
    dt = data["t_gps"][i0 + 1] - data["t_gps"][i0]
    v_n = (data["r_ned"][i0 + 1] - data["r_ned"][i0]) / dt
    k = int(np.searchsorted(data["t_imu"], data["t_gps"][i0]))
    f = data["acc"][k]
    roll, pitch = np.arctan2(-f[1], -f[2]), np.arctan2(f[0], np.hypot(f[1], f[2]))
    yaw = np.arctan2(v_n[1], v_n[0])
    nav = NavState(float(data["t_gps"][i0]), float(data["lat"][i0]), float(data["lon"][i0]), float(data["h"][i0]),
                   v_n, q_nb_from_euler(roll, pitch, yaw))  # fmt: skip
    sig = np.r_[[0.3] * 3, [0.5] * 3, [tilt_sigma] * 2, 5 * DEG_TO_RAD, [0.1] * 3, [5e-5] * 3]
    return NavEstimate(nav, np.diag(sig**2), LAYOUT_15)


def example_bias_rw(data: dict, i0: int = 1) -> tuple[float, float]:
    """The bias random walks (m/s^3/sqrt(Hz), rad/s^2/sqrt(Hz)) that GTSAM's ``IMUKittiExampleGPS.py`` effectively
    uses on this file. It puts a node at every GPS epoch and a between-bias factor of sigma
    ``sqrt(n_cum) * BiasSigma`` (``n_cum``: IMU samples integrated SINCE THE START, never reset), so its bias
    variance grows by ``n_cum(i) * BiasSigma^2`` over epoch ``i``; a constant random walk ``q`` that accumulates the
    same variance over the run has ``q^2 = sum_i n_cum(i) BiasSigma^2 / (t_end - t_start)``."""
    t_gps, t_imu = data["t_gps"], data["t_imu"]
    n_cum = np.array([np.count_nonzero((t_imu >= t_gps[i0]) & (t_imu <= t)) for t in t_gps[i0 + 1 :]], float)
    scale = np.sqrt(n_cum.sum() / (t_gps[-1] - t_gps[i0]))
    m = data["meta"]
    return float(m["AccelerometerBiasSigma"] * scale), float(m["GyroscopeBiasSigma"] * scale)


def noise(meta: dict, rw_a: float | None = None, rw_g: float | None = None) -> ImuNoise:
    """IMU noise from the metadata; bias random walks (m/s^3/sqrt(Hz), rad/s^2/sqrt(Hz)) from the metadata's
    per-sample sigmas unless given."""
    tau = 3600.0
    dt = meta["AverageDeltaT"]
    rw_a = meta["AccelerometerBiasSigma"] / np.sqrt(dt) if rw_a is None else rw_a
    rw_g = meta["GyroscopeBiasSigma"] / np.sqrt(dt) if rw_g is None else rw_g
    return ImuNoise(meta["AccelerometerSigma"], meta["GyroscopeSigma"], rw_a * np.sqrt(tau / 2), rw_g * np.sqrt(tau / 2),
                    tau, tau, 0.1, 5e-5)  # fmt: skip


def run(
    fuser,  # noqa: ANN001
    data: dict,
    i0: int,
    fix_every: int,
    outage: tuple[float, float] | None,
    keyframes: bool = False,
    smooth_iterations: int = 3,
) -> dict:
    """Drive ``fuser`` over the data; errors of the online estimate at every GPS epoch after the start. With
    ``keyframes`` (graph only) a node is added at every GPS epoch and the batch-smoothed figure is added too."""
    t_gps = data["t_gps"]
    t, w, f = split_at(data["t_imu"], data["gyr"], data["acc"], t_gps[i0:])
    est_lat, est_lon = [], []
    rejections = 0
    t0 = time.perf_counter()
    j = int(np.searchsorted(t, t_gps[i0], side="right"))
    for i in range(i0 + 1, len(t_gps)):
        k = int(np.searchsorted(t, t_gps[i] + 1e-9, side="right"))
        fuser.propagate(ImuBatch(t[j:k], w[j:k], f[j:k]))
        j = k
        in_outage = outage is not None and outage[0] <= t_gps[i] - t_gps[i0] < outage[0] + outage[1]
        if (i - i0) % fix_every == 0 and not in_outage:
            inn = fuser.correct(Fix(float(t_gps[i]), float(data["lat"][i]), float(data["lon"][i]),
                              np.eye(2) * GPS_SIGMA_M**2, source="gps"),
                           height_m=float(data["h"][i]), height_sigma_m=GPS_SIGMA_M)  # fmt: skip
            rejections += not inn.accepted
        elif keyframes:
            fuser.add_node(float(t_gps[i]))
        nav = fuser.estimate().nav
        est_lat.append(nav.lat)
        est_lon.append(nav.lon)
    wall = time.perf_counter() - t0
    e = horizontal_error_m(np.array(est_lat), np.array(est_lon), data["lat"][i0 + 1 :], data["lon"][i0 + 1 :])
    out = {"rms_horizontal_m": float(np.sqrt(np.mean(e**2))), "max_horizontal_m": float(e.max()),
           "wall_s": round(wall, 3), "epochs": len(e), "rejected_fixes": int(rejections)}  # fmt: skip

    def smoothed(get) -> dict:  # noqa: ANN001
        t0 = time.perf_counter()
        tr = get()
        k = np.clip(np.searchsorted(t_gps, tr.t - 1e-6), 0, len(t_gps) - 1)
        at_epoch = (np.abs(t_gps[k] - tr.t) < 1e-6) & (tr.t > t_gps[i0] + 1e-6)
        es = horizontal_error_m(tr.lat[at_epoch], tr.lon[at_epoch], data["lat"][k[at_epoch]], data["lon"][k[at_epoch]])
        return {"rms_horizontal_m": float(np.sqrt(np.mean(es**2))), "max_horizontal_m": float(es.max()),
                "wall_s": round(wall + time.perf_counter() - t0, 3), "epochs": len(es)}  # fmt: skip

    if keyframes:
        out["smoothed"] = smoothed(lambda: fuser.node_trajectory(smoothed=True)) | {"how": "batch LM"}
    elif getattr(fuser, "_history", None) is not None:
        out["smoothed_single_pass"] = smoothed(lambda: fuser.smooth(1)[0]) | {"how": "closed-loop RTS, 1 pass"}
        if smooth_iterations > 1:
            out["smoothed"] = smoothed(lambda: fuser.smooth(smooth_iterations)[0]) | {
                "how": f"relinearised RTS, {smooth_iterations} passes"
            }
        else:
            out["smoothed"] = out["smoothed_single_pass"]
    return out


def make_fusers(init: NavEstimate, nz: ImuNoise) -> dict:
    from magnav_ins.aiding.fusion import make_fuser

    return {k: make_fuser(k, init, nz) for k in ("ukf", "graph", "free_inertial")}


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--fix-every", type=int, default=10)
    ap.add_argument("--outage", default=None, help="START:DURATION in s from the start (no fixes inside)")
    ap.add_argument("--fusers", default="ukf,graph,free_inertial")
    ap.add_argument("--no-peer", action="store_true", help="skip GTSAM's own example")
    ap.add_argument(
        "--accel-bias-rw",
        type=float,
        default=None,
        help="m/s^3/sqrt(Hz); default: the GTSAM example's effective value (example_bias_rw)",
    )
    ap.add_argument("--gyro-bias-rw", type=float, default=None, help="rad/s^2/sqrt(Hz); default as above")
    ap.add_argument("--tilt-sigma-deg", type=float, default=5.0, help="initial roll/pitch 1-sigma")
    ap.add_argument("--gate", type=float, default=None, help="chi-square gate probability (default: none, GPS)")
    ap.add_argument("--huber-k", type=float, default=100.0, help="graph's Huber threshold (default: ~Gaussian)")
    ap.add_argument("--smooth-iterations", type=int, default=3, help="UKF smoother passes (1: closed-loop RTS only)")
    ap.add_argument(
        "--sweep",
        action="store_true",
        help="also run UKF and graph over the bias-walk grid {0.01,0.02,0.05} x {1e-4,3e-4,1e-3}",
    )
    ap.add_argument("--json", action="store_true")
    return ap.parse_args(argv)  # fmt: skip


def measure(a: argparse.Namespace) -> dict:
    """Run the fusers (and the peer) as configured; returns the result dictionary printed by :func:`main`."""
    outage = tuple(float(x) for x in a.outage.split(":")) if a.outage else None
    data = load()
    i0 = 1
    init = initial(data, i0, a.tilt_sigma_deg * DEG_TO_RAD)
    ex_a, ex_g = example_bias_rw(data, i0)
    rw_a = ex_a if a.accel_bias_rw is None else a.accel_bias_rw
    rw_g = ex_g if a.gyro_bias_rw is None else a.gyro_bias_rw
    nz = noise(data["meta"], rw_a, rw_g)
    from magnav_ins.aiding.fusion import make_fuser

    def one(name: str, nz: ImuNoise) -> dict:
        opts: dict = {} if name == "free_inertial" else {"gate_probability": a.gate}
        if name == "graph":
            opts["huber_k"] = a.huber_k
        if name == "ukf":
            opts["keep_history"] = True  # for the RTS-smoothed figures
        fuser = make_fuser(name, init, nz, **opts)
        return run(fuser, data, i0, a.fix_every, outage, name == "graph", a.smooth_iterations)

    out: dict = {"fusers": {}, "fix_every": a.fix_every, "outage": a.outage,
                 "bias_rw": {"accel_m_s3_rtHz": rw_a, "gyro_rad_s2_rtHz": rw_g,
                             "source": "GTSAM example's effective walk" if (a.accel_bias_rw, a.gyro_bias_rw) == (None, None)
                             else "command line"},
                 "imu_noise": nz.__dict__}  # fmt: skip
    for name in a.fusers.split(","):
        out["fusers"][name] = one(name, nz)
    if a.sweep:
        grid = []
        for ga in (0.01, 0.02, 0.05):
            for gg in (1e-4, 3e-4, 1e-3):
                n2 = noise(data["meta"], ga, gg)
                u, g = one("ukf", n2), one("graph", n2)
                grid.append({"accel_bias_rw": ga, "gyro_bias_rw": gg,
                             "ukf_online": u["rms_horizontal_m"], "ukf_smoothed": u["smoothed"]["rms_horizontal_m"],
                             "ukf_smoothed_single_pass": u["smoothed_single_pass"]["rms_horizontal_m"],
                             "graph_online": g["rms_horizontal_m"], "graph_smoothed": g["smoothed"]["rms_horizontal_m"]})  # fmt: skip
        out["sweep"] = grid
    if not a.no_peer:
        from magnav_ins.aiding.fusion.graph import kitti_example_peer

        t0 = time.perf_counter()
        try:
            peer = kitti_example_peer(a.fix_every, "QR")
            e = np.linalg.norm(peer["xyz"][:, :2] - peer["gps_xyz"][:, :2], axis=1)
            out["peer_gtsam_example_qr"] = {"rms_horizontal_m": float(np.sqrt(np.mean(e**2))),
                                            "max_horizontal_m": float(e.max()),
                                            "wall_s": round(time.perf_counter() - t0, 3), "smoothed": True}  # fmt: skip
        except Exception as exc:  # the peer is informative only
            out["peer_gtsam_example_qr"] = {"error": f"{type(exc).__name__}: {exc}"}
    return out


def main(argv: list[str] | None = None) -> int:
    a = parse(argv)
    out = measure(a)
    if a.json:
        print(json.dumps(out))
    else:
        b = out["bias_rw"]
        print(f"IMU: accel {out['imu_noise']['accel_noise']} m/s^2/rtHz, gyro {out['imu_noise']['gyro_noise']} "
              f"rad/s/rtHz; bias walks {b['accel_m_s3_rtHz']:.4g} m/s^3/rtHz, {b['gyro_rad_s2_rtHz']:.4g} "
              f"rad/s^2/rtHz ({b['source']})")  # fmt: skip
        for k, v in out["fusers"].items():
            print(f"{k:14s} online   rms {v['rms_horizontal_m']:.3f} m  max {v['max_horizontal_m']:.3f} m  "
                  f"{v['wall_s']:.2f} s")  # fmt: skip
            for lab in ("smoothed_single_pass", "smoothed"):
                if lab in v and (lab == "smoothed_single_pass" or v[lab].get("how", "").find("1 pass") < 0):
                    w = v[lab]
                    print(f"{'':14s} smoothed rms {w['rms_horizontal_m']:.3f} m  max {w['max_horizontal_m']:.3f} m  "
                          f"{w['wall_s']:.2f} s  ({w['how']})")  # fmt: skip
        print("peer (GTSAM IMUKittiExampleGPS.py, QR, smoothed):", out.get("peer_gtsam_example_qr"))
        for r in out.get("sweep", []):
            print(" ".join(f"{k}={v:.4g}" for k, v in r.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
