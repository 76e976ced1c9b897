"""The SITL flight offline: a copter flies a square over Osborne, GNSS-aided for a minute, then on map fixes alone.

The same online pipeline the bridge runs (``magnav_ins.mavlink.online.make_online_pipeline``), fed sample by sample
with a simulated flight: a square of ``side_m`` at ``speed_mps`` and ``altitude_m`` above the survey's ground
(``waypoints``), IMU errors of ``grade`` (seeded), a magnetometer = IGRF main field + the anomaly of the SITL world
(the survey gridded at 50 m from every line, tie lines included: ``sitl.osborne_world``, as the SITL sees it) + 1 nT
noise + a constant offset; GNSS fixes (0.5 m) every second for ``gnss_s``; the readings' offset is calibrated against
the map (``builtin:osborne-magnetic``) while GNSS-aided, as the bridge does; the autopilot's attitude (truth with a
constant error of ``attitude_source_error`` rad 1-sigma and 0.002 rad noise) aids the INS every
``attitude_interval`` s when ``attitude_aid``. For tuning the matcher before a SITL
flight (minutes instead of a quarter of an hour) and for spreads over seeds, which one SITL flight cannot give.

Usage: ``python bench/copter_square.py '{"seeds": [1, 2, 3], "reading_interval": 0.5, "window": 40}' [--json]``
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

from magnav_ins.core.frames import horizontal_error_m, meters_to_latlon
from magnav_ins.core.types import Fix
from magnav_ins.ins.imu_models import corrupt, get_grade
from magnav_ins.ins.simulate import ideal_imu, waypoints
from magnav_ins.maps.builtin import load_map
from magnav_ins.maps.reference import igrf_ned
from magnav_ins.mavlink.bridge import ScalarAnomalyModel
from magnav_ins.mavlink.emulator import magnetometer_body_nt
from magnav_ins.mavlink.online import make_online_pipeline
from magnav_ins.mavlink.replay import _reason_key
from magnav_ins.mavlink.sitl import maganom_value, osborne_world, read_maganom

DEFAULTS = {
    "seeds": [1],
    "home": [-21.95, 140.65],
    "side_m": 2000.0,
    "speed_mps": 15.0,
    "altitude_m": 460.0,
    "rate_hz": 50.0,
    "grade": "autopilot",
    "filter_grade": None,
    "gnss_s": 60.0,
    "reading_interval": 0.5,
    "reading_sigma": 5.0,
    "window": 40,
    "match_every": 5,
    "matcher": "mlr",
    "mag_noise_nt": 1.0,
    "offset_nt": 30.0,
    "attitude_sigma": [0.01, 0.01, 0.05],
    "date": "2026-03-20",
    "fusion_options": {},
    "attitude_aid": True,
    "attitude_interval": 1.0,
    "attitude_aid_sigma": [0.01, 0.01, 0.035],
    "attitude_source_error": [0.003, 0.003, 0.02],
}


def run_one(cfg: dict, seed: int, fmap, world) -> dict:  # noqa: ANN001
    lat0, lon0 = (math.radians(x) for x in cfg["home"])
    s, h = cfg["side_m"], cfg["altitude_m"]
    pts = []
    for dn, de in ((0, 0), (s, 0), (s, s), (0, s), (0, 0)):
        dlat, dlon = meters_to_latlon(dn, de, lat0, h)
        pts.append((lat0 + float(dlat), lon0 + float(dlon), h))
    pts.insert(1, (pts[0][0] + 1e-7, pts[0][1], h))  # start heading north
    truth = waypoints(pts[1:], cfg["speed_mps"], cfg["rate_hz"], turn_rate=math.radians(20.0))
    rng = np.random.default_rng(seed)
    imu, _ = corrupt(ideal_imu(truth), get_grade(cfg["grade"]), rng)
    b_main = igrf_ned(lat0, lon0, h, cfg["date"]).reshape(3)
    anomaly = np.array([maganom_value(world, la, lo) for la, lo in zip(truth.lat, truth.lon, strict=True)])
    mag = magnetometer_body_nt(truth, anomaly + cfg["offset_nt"], b_main)
    mag += rng.normal(0.0, cfg["mag_noise_nt"], mag.shape)
    nav0 = truth.at(0)
    pipe = make_online_pipeline(
        nav0, 1.0, fmap, grade=cfg["filter_grade"] or cfg["grade"], matcher=cfg["matcher"],
        reading_sigma=cfg["reading_sigma"], window=cfg["window"], match_every=cfg["match_every"],
        attitude_sigma_rad=tuple(cfg["attitude_sigma"]), fusion_options=cfg["fusion_options"],
    )  # fmt: skip
    model = ScalarAnomalyModel(cfg["date"])
    # the autopilot's AHRS: truth with a constant error (tilt, heading; drawn once) and 0.002 rad white noise
    from scipy.spatial.transform import Rotation

    src_err = Rotation.from_rotvec(rng.normal(0.0, 1.0, 3) * np.asarray(cfg["attitude_source_error"]))
    next_att = 0.0
    t_gnss = cfg["gnss_s"]
    next_gnss = next_read = 0.0
    errs, sig, times = [], [], []
    for k in range(1, len(truth)):
        t = float(imu.t[k])
        pipe.push_imu(t, imu.gyro_b[k], imu.accel_b[k])
        if t < t_gnss and t >= next_gnss:
            pipe.push_fix(Fix(t, truth.lat[k], truth.lon[k], np.eye(2) * 0.25, True, "", math.nan, "gnss"))
            next_gnss = t + 1.0
        if cfg["attitude_aid"] and t >= next_att:
            noise = Rotation.from_rotvec(rng.normal(0.0, 0.002, 3))
            q_src = (noise * src_err * Rotation.from_quat(truth.q_nb[k])).as_quat()
            pipe.push_attitude(t, q_src, tuple(cfg["attitude_aid_sigma"]))
            next_att = t + cfg["attitude_interval"]
        if t >= next_read:
            nav = pipe.estimate().nav
            v = model(mag[k], nav)
            if t < t_gnss:
                mv = float(np.asarray(fmap.value(nav.lat, nav.lon)).reshape(-1)[0])
                if math.isfinite(mv):
                    model.observe(v, mv)
                    v = model(mag[k], nav)
            pipe.push_reading(t, v)
            next_read = t + cfg["reading_interval"]
        if k % int(cfg["rate_hz"]) == 0 and t >= t_gnss:
            est = pipe.estimate()
            errs.append(float(horizontal_error_m(est.nav.lat, est.nav.lon, truth.lat[k], truth.lon[k])))
            sig.append(math.sqrt(max(np.linalg.eigvalsh(est.cov_ne).max(), 0.0)))
            times.append(t)
    e, sg = np.array(errs), np.array(sig)
    reasons: dict[str, int] = {}
    for f in pipe.fixes:
        if not f.available:
            reasons[_reason_key(f.reason)] = reasons.get(_reason_key(f.reason), 0) + 1
    acc = [i for i in pipe.innovations if i.accepted and i.t >= t_gnss]
    return {
        "seed": seed,
        "denied_s": round(times[-1] - t_gnss, 1),
        "rms_m": round(float(np.sqrt(np.mean(e**2))), 1),
        "max_m": round(float(e.max()), 1),
        "final_m": round(float(e[-1]), 1),
        "sigma_mean_m": round(float(sg.mean()), 1),
        "sigma_max_m": round(float(sg.max()), 1),
        "nees": round(float(np.mean((e / sg) ** 2) / 2.0), 2),
        "untrusted_fraction_100m": round(float(np.mean(sg > 100.0)), 3),
        "fixes_issued_denied": sum(1 for f in pipe.fixes if f.available and f.t >= t_gnss),
        "fixes_accepted_denied": len(acc),
        "fix_attempts": len(pipe.fixes),
        "no_fix_reasons": reasons,
        "offset_nt": round(model.offset_nt, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default="{}", help="JSON overrides of the defaults")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    cfg = {**DEFAULTS, **json.loads(a.config)}
    fmap = load_map("builtin:osborne-magnetic")
    world = read_maganom(osborne_world())
    t0 = time.perf_counter()
    runs = [run_one(cfg, s, fmap, world) for s in cfg["seeds"]]
    rms = np.array([r["rms_m"] for r in runs])
    out = {
        "config": {k: v for k, v in cfg.items() if k != "seeds"},
        "runs": runs,
        "rms_median_m": float(np.median(rms)),
        "rms_max_m": float(rms.max()),
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    print(json.dumps(out) if a.json else json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
