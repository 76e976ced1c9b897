"""The bridge flies a real ArduPilot copter GNSS-denied: ArduCopter SITL (real firmware, real EKF3) in a magnetic world.

The world: the Osborne survey gridded at 50 m from EVERY line, tie lines included (``sitl.osborne_world``), loaded
into the patched SITL's magnetometer; the bridge matches against ``builtin:osborne-magnetic`` (flight lines only, 100
m), so the map is never the world. The flight: the copter arms and takes off on its own GNSS (SITL GPS1), climbs to
``--altitude-m``, heads out along the first side of a square, the GNSS is denied ``--deny-after-s`` after take-off
(``SIM_GPS1_ENABLE=0``), and it flies the square (sides ``--side-m``) in GUIDED on the bridge's position alone, returns
and lands. The bridge runs as ``magnav-ins bridge`` (the real command) on SITL serial 1:

* ``--output gps_input``: GPS_INPUT to GPS2 (``GPS2_TYPE=14``; ``GPS_AUTO_SWITCH=1`` makes it primary when GPS1 fails);
* ``--output odometry``: ODOMETRY (``VISO_TYPE=1``, EKF3 source set 2 = ExternalNav; the bridge asks for set 2 when
  the GNSS is lost).

Truth is SITL's SIM_STATE. One JSON line (``--json``): ``gnss_denied_s``, ``bridge_rms_horizontal_m`` (the bridge's
trusted outputs vs truth while denied), ``ekf_rms_horizontal_m`` / ``ekf_max_horizontal_m`` (the autopilot's
GLOBAL_POSITION_INT vs truth while denied), ``landing_from_home_m``, ``fixes_issued``, ``fixes_accepted`` (the
bridge's map fixes), ``failsafes`` (every failsafe or EKF warning text), ``landed``, plus timings.

The SITL's own simulated gyro drift (``SIM_DRIFT_SPEED``, default 0.05 deg/s per minute on all three axes, a
triangle wave reaching 0.25 deg/s after 5 minutes) is set to 0: it is a test of ArduPilot's EKF, far outside the
in-run stability of any MEMS gyro and of the ``autopilot`` IMU grade; ``--sim-drift`` keeps it.

Run by hand (about 15 minutes for the default square at 15 m/s):
``python bench/sitl_flight.py --json [--output gps_input|odometry] [--home LAT,LON] [--side-m 2000]
[--altitude-m 80] [--denied-s 300] [--speed-mps 15]``
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from magnav_ins.core.frames import horizontal_error_m, meters_to_latlon
from magnav_ins.mavlink.sitl import GroundStation, Sitl, free_udp_port, osborne_world, sitl_dir

ROOT = Path(__file__).resolve().parents[1]
FAILSAFE_WORDS = ("failsafe", "variance", "glitch", "ekf3 lane switch", "ekf primary", "gps 1: not healthy",
                  "bad", "compass error", "yaw reset", "emergency", "crash", "lost")  # fmt: skip
IGNORED = ("prearm", "arming", "ekf3 imu0 is using", "ekf3 imu1 is using")


def _sitl_params(output: str, speed_mps: float, sim_drift: bool) -> dict[str, float]:
    p: dict[str, float] = {
        "SERIAL1_PROTOCOL": 2,  # MAVLink 2 to the companion
        "SR1_EXTRA1": 0,  # the bridge asks for what it needs (SET_MESSAGE_INTERVAL)
        "WPNAV_SPEED": speed_mps * 100.0,
        "WPNAV_ACCEL": 250.0,
        # SITL's gyros leave out the Earth's rotation (a flat, non-rotating world): with a fixed heading the missing
        # 7e-5 rad/s is a constant body-frame bias that the bridge's ground alignment measures; turning the vehicle
        # at every corner would make it a bias that rotates with the heading
        "WP_YAW_BEHAVIOR": 0,
        "RTL_ALT": 0.0,  # return at the current height
        "FENCE_ENABLE": 0,
    }
    if not sim_drift:
        p["SIM_DRIFT_SPEED"] = 0.0
    if output == "gps_input":
        p.update({"GPS2_TYPE": 14, "GPS_AUTO_SWITCH": 1})
    else:
        p.update({"VISO_TYPE": 1, "EK3_SRC2_POSXY": 6, "EK3_SRC2_VELXY": 6, "EK3_SRC2_POSZ": 1, "EK3_SRC2_YAW": 1,
                  "EK3_SRC2_VELZ": 0})  # fmt: skip
    return p


def _bridge_cmd(args, port: int, summary: Path, track: Path) -> list[str]:  # noqa: ANN001
    exe = Path(sys.executable).with_name("magnav-ins")
    head = [str(exe)] if exe.is_file() else [sys.executable, "-m", "magnav_ins.cli"]
    cmd = [*head, "bridge", "--connect", f"udpin:127.0.0.1:{port}", "--map", "builtin:osborne-magnetic",
           "--output", args.output, "--rate", "10", "--summary-json", str(summary), "--track-csv", str(track),
           "--date", "2026-03-20"]  # fmt: skip
    for opt in ("reading_interval", "window", "match_every", "reading_sigma", "matcher"):
        if getattr(args, opt) is not None:
            cmd += ["--" + opt.replace("_", "-"), str(getattr(args, opt))]
    if args.output == "gps_input":
        cmd += ["--gps-id", "1"]
    else:
        cmd += ["--ekf-source-set", "2"]
    return cmd + list(args.bridge_arg or [])


def _interp_truth(truth: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.interp(t, truth[:, 0], truth[:, 1]), np.interp(t, truth[:, 0], truth[:, 2])


def fly(args: argparse.Namespace) -> dict:  # noqa: C901 - one flight, step by step
    home_lat, home_lon = (math.radians(float(x)) for x in args.home.split(","))
    world = osborne_world()
    port = free_udp_port()
    work = Path(tempfile.mkdtemp(prefix="magnav-sitl-flight-"))
    summary_path, track_path = work / "bridge.json", work / "track.csv"
    sitl = Sitl(
        (math.degrees(home_lat), math.degrees(home_lon), args.home_alt_m, 0.0),
        defaults=(sitl_dir() / "copter.parm",),
        params=_sitl_params(args.output, args.speed_mps, args.sim_drift),
        world=world,
        serial1_udp_port=port,
        speedup=args.speedup,
        keep_workdir=args.keep,
    )
    bridge = None
    gcs = None
    out: dict = {"output": args.output, "side_m": args.side_m, "altitude_m": args.altitude_m,
                 "speed_mps": args.speed_mps, "home": args.home}  # fmt: skip
    t_start = time.monotonic()
    try:
        bridge = subprocess.Popen(
            _bridge_cmd(args, port, summary_path, track_path), stdin=subprocess.DEVNULL,
            stdout=(work / "bridge.out").open("w"), stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
        # wait for the bridge's warm-up before the SITL starts streaming to it
        t_end = time.monotonic() + 300
        while "bridge on udpin" not in (work / "bridge.out").read_text(errors="replace"):
            if bridge.poll() is not None or time.monotonic() > t_end:
                raise RuntimeError("bridge did not start: " + (work / "bridge.out").read_text()[-2000:])
            time.sleep(0.5)
        sitl.start()
        gcs = GroundStation(sitl.gcs_url)
        gcs.request_streams()
        link = gcs.link
        if not gcs.wait(lambda: gcs.said("EKF3 IMU0 is using GPS"), 120, "EKF3 using GPS"):
            raise RuntimeError("EKF3 never used the GPS")
        gcs.wait(lambda: False, 5.0)  # home and origin settle
        link.set_mode("GUIDED")
        t_arm = time.monotonic()
        while not gcs.armed:
            if time.monotonic() - t_arm > 60:
                raise RuntimeError("did not arm: " + "; ".join(t for _, _, t in gcs.texts[-8:]))
            link.arm(True)
            gcs.wait(lambda: gcs.armed, 3.0)
        link.takeoff(args.altitude_m)
        t_takeoff = time.monotonic()
        out["armed_after_s"] = round(t_takeoff - t_start, 1)
        home_h = args.home_alt_m
        gcs.wait(lambda: bool(gcs.ekf) and gcs.ekf[-1][3] - home_h > 0.9 * args.altitude_m, 90, "climb")
        corners_ne = [(args.side_m, 0.0), (args.side_m, args.side_m), (0.0, args.side_m), (0.0, 0.0)]
        t_deny = None
        denied = {"done": False}

        def deny_when_due() -> None:
            nonlocal t_deny
            if not denied["done"] and time.monotonic() - t_takeoff >= args.deny_after_s:
                gcs.link.param_set("SIM_GPS1_ENABLE", 0)
                t_deny = time.monotonic()
                denied["done"] = True
                logging.info("GNSS denied (SIM_GPS1_ENABLE=0) %.0f s after take-off", t_deny - t_takeoff)

        aborted = ""
        for dn, de in corners_ne:
            if aborted:
                break
            dlat, dlon = meters_to_latlon(dn, de, home_lat, 0.0)
            lat, lon = home_lat + float(dlat), home_lon + float(dlon)
            leg_timeout = 1.8 * args.side_m / args.speed_mps + 60

            def arrived(lat=lat, lon=lon) -> bool:
                if not gcs.ekf:
                    return False
                return float(horizontal_error_m(gcs.ekf[-1][1], gcs.ekf[-1][2], lat, lon)) < 15.0

            t_leg = time.monotonic()
            while time.monotonic() - t_leg < leg_timeout and not arrived():
                if gcs.mode not in ("GUIDED", ""):  # a failsafe took over: let it land, record it
                    aborted = f"mode {gcs.mode} at {time.monotonic() - t_takeoff:.0f} s after take-off"
                    break
                link.goto(lat, lon, args.altitude_m)
                gcs.wait(arrived, 2.0, every=deny_when_due)
                if not gcs.armed:
                    aborted = "disarmed in flight"
                    break
        if t_deny is None:
            deny_when_due()
            t_deny = t_deny or time.monotonic()
        out["aborted"] = aborted
        if gcs.armed and not aborted:
            link.set_mode("LAND")
        gcs.wait(lambda: not gcs.armed, 300, "landing and disarm")
        t_land = time.monotonic()
        out["landed"] = not gcs.armed
        out["gnss_denied_s"] = round(t_land - t_deny, 1)
        out["flight_s"] = round(t_land - t_takeoff, 1)
        truth = np.array(gcs.truth)
        lat_e, lon_e = truth[-1, 1], truth[-1, 2]
        out["landing_from_home_m"] = round(float(horizontal_error_m(lat_e, lon_e, home_lat, home_lon)), 1)
        ekf = np.array(gcs.ekf)
        m = (ekf[:, 0] >= t_deny) & (ekf[:, 0] <= t_land)
        la, lo = _interp_truth(truth, ekf[m, 0])
        e = horizontal_error_m(ekf[m, 1], ekf[m, 2], la, lo)
        out["ekf_rms_horizontal_m"] = round(float(np.sqrt(np.mean(e**2))), 1)
        out["ekf_max_horizontal_m"] = round(float(e.max()), 1)
        out["ekf_final_horizontal_m"] = round(float(e[-1]), 1)
        texts = [(round(t - t_takeoff, 1), s, x) for t, s, x in gcs.texts if t >= t_takeoff]
        out["failsafes"] = [
            f"{t}: {x}" for t, s, x in texts
            if any(w in x.lower() for w in FAILSAFE_WORDS) and not any(i in x.lower() for i in IGNORED)
        ]  # fmt: skip
        out["autopilot_texts"] = len(texts)
        out["_t"] = (t_takeoff, t_deny, t_land)
        out["_truth"] = truth
    finally:
        if bridge is not None and bridge.poll() is None:
            os.killpg(bridge.pid, signal.SIGTERM)  # the bridge's clean stop writes its summary
            try:
                bridge.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(bridge.pid, signal.SIGKILL)
                bridge.wait()
        if gcs is not None:
            gcs.close()
        sitl.stop()
    if summary_path.is_file():
        s = json.loads(summary_path.read_text())
        out["fixes_issued"] = s["map_fixes_issued"]
        out["fixes_accepted"] = s["map_fixes_accepted"]
        out["fix_attempts"] = s["map_fixes"]
        out["gnss_fixes_accepted"] = s["gnss_fixes_accepted"]
        out["bridge_statustexts"] = s["statustexts_sent"]
        out["field_offset_nt"] = None if not math.isfinite(s["field_offset_nt"]) else round(s["field_offset_nt"], 1)
        out["bridge_history"] = s["history"][-12:]
        out["no_fix_reasons"] = s.get("no_fix_reasons", {})
        out["rejected_reasons"] = s.get("rejected_reasons", {})
        out["attitude_updates"] = s.get("attitude_accepted", 0)
    if track_path.is_file() and "_truth" in out:
        import pandas as pd

        tr = pd.read_csv(track_path)
        t_takeoff, t_deny, t_land = out["_t"]
        # the track's wall clock is time.time(); the ground station's is time.monotonic()
        offset = time.time() - time.monotonic()
        tw = tr.t_wall.to_numpy() - offset
        m = (tw >= t_deny) & (tw <= t_land) & (tr.trusted.to_numpy() == 1)
        if m.any():
            la, lo = _interp_truth(out["_truth"], tw[m])
            e = horizontal_error_m(np.radians(tr.lat_deg.to_numpy()[m]), np.radians(tr.lon_deg.to_numpy()[m]), la, lo)
            out["bridge_rms_horizontal_m"] = round(float(np.sqrt(np.mean(e**2))), 1)
            out["bridge_max_horizontal_m"] = round(float(e.max()), 1)
            sig = tr.sigma_h_m.to_numpy()[m]
            out["bridge_nees"] = round(float(np.mean((e / np.maximum(sig, 1e-3)) ** 2) / 2.0), 2)
        md = (tw >= t_deny) & (tw <= t_land)
        out["bridge_trusted_fraction_denied"] = round(float(np.mean(tr.trusted.to_numpy()[md])), 3) if md.any() else 0
    out.pop("_truth", None)
    out.pop("_t", None)
    out["wall_s"] = round(time.monotonic() - t_start, 1)
    if args.keep:
        out["workdir"] = str(work)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON line")
    ap.add_argument("--output", default="gps_input", choices=["gps_input", "odometry"])
    ap.add_argument("--home", default="-21.95,140.65", help="LAT,LON deg inside the Osborne map")
    ap.add_argument("--home-alt-m", type=float, default=380.0)
    ap.add_argument("--side-m", type=float, default=2000.0)
    ap.add_argument("--altitude-m", type=float, default=80.0)
    ap.add_argument("--speed-mps", type=float, default=15.0)
    ap.add_argument("--deny-after-s", type=float, default=60.0, help="deny the GNSS this long after take-off")
    ap.add_argument("--denied-s", type=float, default=None, help="(informative) the square is sized by --side-m")
    ap.add_argument("--speedup", type=float, default=1.0)
    ap.add_argument("--sim-drift", action="store_true", help="keep the SITL's simulated gyro drift")
    ap.add_argument("--reading-interval", type=float, default=None, help="bridge option (default: the bridge's)")
    ap.add_argument("--window", type=int, default=None, help="bridge option")
    ap.add_argument("--match-every", type=int, default=None, help="bridge option")
    ap.add_argument("--reading-sigma", type=float, default=None, help="bridge option")
    ap.add_argument("--matcher", default=None, help="bridge option (a kind or a JSON table)")
    ap.add_argument("--bridge-arg", action="append", help="extra argument for magnav-ins bridge (repeatable)")
    ap.add_argument("--keep", action="store_true", help="keep the work directory (logs, track)")
    ap.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(asctime)s %(message)s")
    if sitl_dir() is None:
        raise SystemExit("../shared/tools/ardupilot-sitl is not beside the project")
    out = fly(args)
    print(json.dumps(out) if args.json else json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
