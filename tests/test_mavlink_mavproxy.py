"""The bridge behind a real MAVLink router (MAVProxy), and ``magnav-ins bridge`` as a process.

MAVProxy runs as a subprocess: its master (``udpin``) faces the emulated autopilot, its ``--out`` ports face two
bridges (one sending GLOBAL_POSITION_SENSOR unsigned, one GPS_INPUT with MAVLink 2 signing, the autopilot signing and
accepting both), as on a vehicle whose telemetry goes through a router on the companion computer. The bridges' requests, heartbeats and position outputs must cross MAVProxy to the autopilot and
the IMU stream must cross it the other way. The CLI test runs the real command line against the emulator.
"""

from __future__ import annotations

import math
import os
import re
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from magnav_ins.core.frames import horizontal_error_m
from magnav_ins.maps.builtin import load_map
from magnav_ins.mavlink.bridge import Bridge, BridgeConfig, ScalarAnomalyModel
from magnav_ins.mavlink.emulator import AutopilotEmulator, flight_over_map
from magnav_ins.mavlink.link import MAV_COMP_ID_ONBOARD_COMPUTER, MSG_ID, SET_MESSAGE_INTERVAL, MavLink
from magnav_ins.mavlink.replay import make_online_pipeline

START = (math.radians(-21.93), math.radians(140.62))  # inside builtin:osborne-magnetic, varied anomaly
BIN = Path(sys.executable).parent
KEY = bytes(range(32))  # MAVLink 2 signing key of the signed bridge and the emulated autopilot


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_udp_ports(n: int) -> list[int]:
    """``n`` distinct free ports (the sockets are held together so the OS cannot hand out one twice)."""
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


class OutputReader:
    """Drains a subprocess's text stream in a thread (so a full pipe never blocks it); ``wait_for`` a line."""

    def __init__(self, stream) -> None:
        self.lines: list[tuple[float, str]] = []
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream) -> None:
        for line in stream:
            with self._cond:
                self.lines.append((time.monotonic(), line.rstrip("\n")))
                self._cond.notify_all()

    def wait_for(self, pattern: str, timeout: float) -> float | None:
        """Monotonic time at which a line matching ``pattern`` appeared, or None after ``timeout`` s."""
        rx = re.compile(pattern)
        t_end = time.monotonic() + timeout
        with self._cond:
            while True:
                for t, line in self.lines:
                    if rx.search(line):
                        return t
                left = t_end - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)

    def text(self) -> str:
        self._thread.join(timeout=2.0)
        return "\n".join(line for _, line in self.lines)


def stop_process(proc: subprocess.Popen, timeout: float = 5.0) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=timeout)


@pytest.fixture(scope="module")
def osborne():
    return load_map("builtin:osborne-magnetic")


def _bridge(port: int, fmap, date: str, output: str, key: bytes | None = None) -> Bridge:
    """As in test_mavlink_bridge.py: the bridge's link is ``udpin``, the autopilot is system 1 component 1; GPS_INPUT
    goes to GPS2 (GPS_RAW_INT is the emulator's own GNSS) and positions are sent while that GNSS is healthy."""
    link = MavLink(f"udpin:127.0.0.1:{port}", source_system=1, peer_system=1, peer_component=1, signing_key=key)
    config = BridgeConfig(
        output=output, output_rate_hz=5.0, init_sigma_m=10.0, gps_id=1, send_while_gnss="yes", sample_type="mean"
    )

    def factory(nav0, sigma_m):
        return make_online_pipeline(nav0, sigma_m, fmap, grade="tactical", matcher="mlr", fusion="ukf")

    return Bridge(link, config, factory, ScalarAnomalyModel(date))


def _healthy_errors_m(outputs, kind: str, lat0: float, lon0: float) -> np.ndarray:
    out = [o for o in outputs if o.kind == kind and o.healthy]
    return horizontal_error_m([o.lat for o in out], [o.lon for o in out], lat0, lon0) if out else np.zeros(0)


# --- through MAVProxy -----------------------------------------------------------------------------------------------
def _mavproxy_command() -> list[str]:
    script = BIN / "mavproxy.py"
    return [str(script)] if script.is_file() else [sys.executable, "-m", "MAVProxy.mavproxy"]


def test_bridges_behind_mavproxy_get_imu_and_reach_the_autopilot(osborne, tmp_path):
    pytest.importorskip("MAVProxy", reason="MAVProxy is not installed (pip install MAVProxy, in the test extras)")
    flight = flight_over_map(
        osborne, start=START, heading=0.3, speed_mps=0.0, duration_s=30.0, rate_hz=50.0, altitude_m=400.0, seed=13
    )
    p_master, p_gps, p_gpsi = free_udp_ports(3)
    cmd = [
        *_mavproxy_command(),
        f"--master=udpin:127.0.0.1:{p_master}",
        f"--out=udpout:127.0.0.1:{p_gps}",
        f"--out=udpout:127.0.0.1:{p_gpsi}",
        "--daemon",
        "--non-interactive",
        "--no-state",  # no logs, no aircraft directory
        f"--state-basedir={tmp_path}",
        "--default-modules=",  # a bare router: no param fetch, no console
        "--streamrate=-1",  # do not ask the autopilot for streams itself: the bridges must
        "--mav20",
    ]
    env = {**os.environ, "HOME": str(tmp_path)}  # MAVProxy reads ~/.mavinit.scr
    proc = subprocess.Popen(
        cmd,
        cwd=tmp_path,
        env=env,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    log = OutputReader(proc.stdout)
    links: list[MavLink] = []
    try:
        assert log.wait_for(r"Waiting for heartbeat", 20.0) is not None, f"MAVProxy did not start:\n{log.text()}"
        bridges = {
            "global_position_sensor": _bridge(p_gps, osborne, flight.date, "global_position_sensor"),
            # signed: it drops anything unsigned, so its IMU proves signed frames cross the (keyless) router intact
            "gps_input": _bridge(p_gpsi, osborne, flight.date, "gps_input", key=KEY),
        }
        links += [b.link for b in bridges.values()]
        # the autopilot signs what it sends and still accepts the unsigned bridge
        ap = MavLink(
            f"udpout:127.0.0.1:{p_master}", source_system=1, source_component=1, signing_key=KEY, accept_unsigned=True
        )
        links.append(ap)
        with AutopilotEmulator(ap, flight.truth, flight.imu, flight.mag_b_nt) as emu:
            t_end = time.monotonic() + 8.0
            while time.monotonic() < t_end:
                for b in bridges.values():
                    b.poll(timeout=0.002)
            time.sleep(0.2)
        assert proc.poll() is None, f"MAVProxy died:\n{log.text()}"
    finally:
        stop_process(proc)
        for link in links:
            link.close()
    rec = emu.record
    # the bridges' SET_MESSAGE_INTERVAL for HIGHRES_IMU crossed MAVProxy (which itself asked for nothing)
    asks = [c for c in rec.commands if c.command == SET_MESSAGE_INTERVAL and int(c.params[0]) == MSG_ID["HIGHRES_IMU"]]
    assert asks and all(c.compid == MAV_COMP_ID_ONBOARD_COMPUTER for c in asks)
    assert rec.imu_sent > 200
    for b in bridges.values():  # the IMU crossed MAVProxy to both outputs
        assert b.health.imu_samples > 200 and b.health.state in ("aligning", "running") and b.health.healthy
        assert b.link.stats.bad_data == 0 and b.link.stats.rejected_signature == 0
    # heartbeats of the companion computer (not MAVProxy's own GCS heartbeats) and positions came back within 5 s
    assert rec.first_heartbeat_s is not None and rec.first_heartbeat_s < 5.0
    assert rec.heartbeats_from_bridge >= 8  # two bridges at 1 Hz for 8 s
    assert rec.first_output_s is not None and rec.first_output_s < 5.0
    lat0, lon0 = flight.truth.lat[0], flight.truth.lon[0]
    for kind in ("global_position_sensor", "gps_input"):
        first = min((o.t_rx for o in rec.outputs if o.kind == kind and o.healthy), default=math.inf)
        assert first - emu.started_at < 5.0, f"no healthy {kind} within 5 s"
        err = _healthy_errors_m(rec.outputs, kind, lat0, lon0)
        assert len(err) >= 15, f"only {len(err)} healthy {kind} outputs in 8 s at 5 Hz"
        assert err.max() < 50.0, (kind, err.max())
    gps = [o for o in rec.outputs if o.kind == "gps_input" and o.healthy]
    assert all(o.fields["fix_type"] == 3 and o.fields["time_week"] > 2000 for o in gps)
    # PX4 >= 1.18 maps GLOBAL_POSITION_SENSOR.id to an EKF2_AGPn_ID slot, where 0 means "slot disabled"
    gps_sensor = [o for o in rec.outputs if o.kind == "global_position_sensor"]
    assert all(o.fields["id"] != 0 and o.fields["target_system"] == 1 for o in gps_sensor)


# --- the command line -----------------------------------------------------------------------------------------------
def _cli(*args: str) -> list[str]:
    script = BIN / "magnav-ins"
    head = (
        [str(script)]
        if script.is_file()
        else [sys.executable, "-c", "from magnav_ins.cli import main; raise SystemExit(main())"]
    )
    return [*head, *args]


def test_cli_bridge_sends_heartbeats_and_gps_input_and_exits_0(osborne):
    flight = flight_over_map(
        osborne, start=START, heading=1.0, speed_mps=0.0, duration_s=60.0, rate_hz=50.0, altitude_m=400.0, seed=17
    )
    port = free_udp_port()
    cmd = _cli(
        "bridge",
        "--connect",
        f"udpin:127.0.0.1:{port}",
        "--map",
        "builtin:osborne-magnetic",
        "--duration",
        "6",
        "--output",
        "gps_input",
        "--imu-rate",
        "50",
        "--date",
        flight.date,
        "--gps-id",  # GPS2: the emulator's GPS_RAW_INT is the autopilot's own GNSS, the bridge's initial position
        "1",
        "--send-while-gnss",
        "yes",
    )
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out, err = OutputReader(proc.stdout), OutputReader(proc.stderr)
    ap = MavLink(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    try:
        t_ready = err.wait_for(r"bridge on udpin", 240.0)  # after the warm-up (a fresh install compiles kernels)
        assert t_ready is not None, f"the bridge did not start:\n{err.text()}"
        with AutopilotEmulator(ap, flight.truth, flight.imu, flight.mag_b_nt) as emu:
            rc = proc.wait(timeout=30.0)
    finally:
        stop_process(proc)
        ap.close()
    rec = emu.record
    assert rc == 0, err.text()
    assert rec.first_heartbeat_s is not None and emu.started_at + rec.first_heartbeat_s - t_ready < 5.0
    gps = [o for o in rec.outputs if o.kind == "gps_input"]
    assert rec.first_output_s is not None and emu.started_at + rec.first_output_s - t_ready < 5.0
    healthy = [o for o in gps if o.healthy]
    assert healthy and healthy[0].t_rx - t_ready < 5.0
    assert len(healthy) >= 10
    assert _healthy_errors_m(healthy, "gps_input", flight.truth.lat[0], flight.truth.lon[0]).max() < 50.0
    summary = [line for line in out.text().splitlines() if line.startswith("bridge stopped:")]
    assert len(summary) == 1, out.text()
    n_out = int(re.search(r"(\d+) outputs", summary[0]).group(1))
    assert n_out >= len(healthy)  # the receiver cannot have seen more than was sent (UDP loopback loses none here)


@pytest.mark.parametrize(
    ("extra", "expected"),
    [
        (["--init=-21.9,140.6,400"], "--init"),  # three numbers instead of four; "=" as argparse needs for "-"
        (["--signing-key", "no/such/key.bin"], "no/such/key.bin"),
        (["--connect", "udpin:127.0.0.1:notaport"], "port 'notaport' is not a number"),
        (["--connect", "telnet://x"], "expected udpin:HOST:PORT"),
    ],
    ids=["bad-init", "unreadable-signing-key", "bad-port", "bad-url"],
)
def test_cli_bridge_bad_option_is_one_line_and_exit_2(extra, expected, tmp_path):
    port = free_udp_port()
    args = ["bridge", "--connect", f"udpin:127.0.0.1:{port}", "--map", "builtin:osborne-magnetic", *extra]
    res = subprocess.run(_cli(*args), cwd=tmp_path, capture_output=True, text=True, timeout=60.0)
    assert res.returncode == 2, (res.stdout, res.stderr)
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("magnav-ins: error:") and expected in lines[0], res.stderr
    assert "Traceback" not in res.stderr and res.stdout == ""


def test_cli_bridge_sigterm_stops_cleanly_with_its_summary(osborne, tmp_path):
    """A service manager stops the bridge with SIGTERM: it closes the link, prints its summary, writes the summary
    JSON and exits 0 within a few seconds (it used to die at once with status 143)."""
    import json
    import signal

    flight = flight_over_map(
        osborne, start=START, heading=0.0, speed_mps=0.0, duration_s=60.0, rate_hz=50.0, altitude_m=400.0, seed=19
    )
    port = free_udp_port()
    summary = tmp_path / "summary.json"
    cmd = _cli(
        "bridge", "--connect", f"udpin:127.0.0.1:{port}", "--map", "builtin:osborne-magnetic", "--imu-rate", "50",
        "--date", flight.date, "--gps-id", "1", "--summary-json", str(summary),
    )  # fmt: skip
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out, err = OutputReader(proc.stdout), OutputReader(proc.stderr)
    ap = MavLink(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    try:
        assert err.wait_for(r"bridge on udpin", 240.0) is not None, err.text()
        with AutopilotEmulator(ap, flight.truth, flight.imu, flight.mag_b_nt):
            assert err.wait_for(r"magnav: aligning", 20.0) is not None, err.text()
            t0 = time.monotonic()
            proc.send_signal(signal.SIGTERM)
            rc = proc.wait(timeout=10.0)
            stopped_in = time.monotonic() - t0
    finally:
        stop_process(proc)
        ap.close()
    assert rc == 0 and stopped_in < 10.0, (rc, stopped_in, err.text()[-500:])
    assert "stopped by SIGTERM" in err.text()
    assert sum(line.startswith("bridge stopped:") for line in out.text().splitlines()) == 1, out.text()
    doc = json.loads(summary.read_text())
    assert doc["stopped_by"] == "SIGTERM" and doc["imu_samples"] > 0 and doc["state"] == "aligning"
