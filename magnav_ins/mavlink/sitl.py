"""ArduPilot SITL for tests and benchmarks: the patched ArduCopter of ``../shared/tools/ardupilot-sitl`` as a process.

That directory (beside the project, absent on a fresh clone: callers skip then) holds a built ArduCopter SITL (real
firmware, real EKF3) whose simulated magnetometer adds a crustal anomaly map to its main field
(``SITL_MAG_ANOMALY_GRID``, MAGANOM1 format: :func:`write_maganom`). :class:`Sitl` starts it in a temporary
directory (it writes ``eeprom.bin``, ``logs/`` and ``terrain/`` where it runs) as instance ``-I N`` on free loopback
ports, with the defaults files and extra parameters given, and stops it (terminate, then kill) however the caller
ends. Serial 0 is TCP ``5760 + 10 N`` (a ground station connects there: the simulation waits for it); serial 1
streams MAVLink to a UDP port where the bridge listens (``udpin``).

MAGANOM1: one text line ``MAGANOM1 lat0_deg lon0_deg dlat_deg dlon_deg nlat nlon\\n`` then ``nlat * nlon``
little-endian float32 nT, row-major, row ``i`` at latitude ``lat0 + i dlat``, column ``j`` at ``lon0 + j dlon``;
NaN = no data. The SITL interpolates bilinearly, 0 outside the grid or next to a NaN, and ignores height.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path
from types import TracebackType

import numpy as np

from ..core.atomic import atomic_path
from ..core.errors import InputError

log = logging.getLogger(__name__)

PROJECT_ROOT = Path(__file__).resolve().parents[2]
#: where the shared SITL build lives, relative to the project root (``../shared/tools/ardupilot-sitl``)
SITL_DIR = PROJECT_ROOT.parent / "shared" / "tools" / "ardupilot-sitl"
BASE_TCP_PORT = 5760


def sitl_dir() -> Path | None:
    """The SITL build directory if its ``arducopter`` binary is there and executable, else None."""
    exe = SITL_DIR / "arducopter"
    return SITL_DIR if exe.is_file() and os.access(exe, os.X_OK) else None


def _port_free(port: int, kind: int = socket.SOCK_STREAM) -> bool:
    with socket.socket(socket.AF_INET, kind) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def free_instance(rng: np.random.Generator | None = None) -> int:
    """An instance number ``N`` (10-89) whose SITL ports (TCP 5760-5763 + 10 N, UDP 5501 + 10 N, 9002-9003 + 10 N)
    are free now."""
    rng = rng if rng is not None else np.random.default_rng()
    for n in rng.permutation(np.arange(10, 90)):
        base = BASE_TCP_PORT + 10 * int(n)
        tcp = all(_port_free(base + k) for k in range(4))
        udp = all(
            _port_free(p, socket.SOCK_DGRAM) for p in (5501 + 10 * int(n), 9002 + 10 * int(n), 9003 + 10 * int(n))
        )
        if tcp and udp:
            return int(n)
    raise InputError("no free SITL instance (TCP ports 5860-6650 all taken)")


# ------------------------------------------------------------------------------------------------ MAGANOM1 grids
def write_maganom(
    path: str | os.PathLike[str], lat0_deg: float, lon0_deg: float, dlat_deg: float, dlon_deg: float, grid: np.ndarray
) -> None:
    """Write a MAGANOM1 file (module docstring): ``grid`` (nlat, nlon) nT, row ``i`` at ``lat0 + i dlat`` (deg)."""
    g = np.asarray(grid, dtype=float)
    if g.ndim != 2 or min(g.shape) < 2 or not (dlat_deg > 0 and dlon_deg > 0):
        raise InputError(f"MAGANOM1 grid must be 2-D with at least 2 x 2 nodes and positive steps, got {g.shape}")
    head = f"MAGANOM1 {float(lat0_deg)!r} {float(lon0_deg)!r} {float(dlat_deg)!r} {float(dlon_deg)!r} {g.shape[0]} {g.shape[1]}\n"
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(head.encode() + np.ascontiguousarray(g, dtype="<f4").tobytes())


def read_maganom(path: str | os.PathLike[str]) -> tuple[float, float, float, float, np.ndarray]:
    """``(lat0_deg, lon0_deg, dlat_deg, dlon_deg, grid)`` of a MAGANOM1 file."""
    p = Path(path)
    with p.open("rb") as f:
        head = f.readline().split()
        if len(head) != 7 or head[0] != b"MAGANOM1":
            raise InputError(f"{p}: not a MAGANOM1 file")
        lat0, lon0, dlat, dlon = map(float, head[1:5])
        nlat, nlon = int(head[5]), int(head[6])
        data = f.read(4 * nlat * nlon)
    if len(data) != 4 * nlat * nlon:
        raise InputError(f"{p}: MAGANOM1 data truncated ({len(data)} of {4 * nlat * nlon} bytes)")
    return lat0, lon0, dlat, dlon, np.frombuffer(data, dtype="<f4").reshape(nlat, nlon).astype(np.float64)


def maganom_value(world: tuple[float, float, float, float, np.ndarray], lat: float, lon: float) -> float:
    """The anomaly (nT) the SITL adds at ``lat``, ``lon`` (rad): bilinear, 0 off the grid or next to NaN."""
    lat0, lon0, dlat, dlon, g = world
    fi, fj = (math.degrees(lat) - lat0) / dlat, (math.degrees(lon) - lon0) / dlon
    if not (0 <= fi <= g.shape[0] - 1 and 0 <= fj <= g.shape[1] - 1):
        return 0.0
    i, j = min(int(fi), g.shape[0] - 2), min(int(fj), g.shape[1] - 2)
    ti, tj = fi - i, fj - j
    v = (1 - ti) * ((1 - tj) * g[i, j] + tj * g[i, j + 1]) + ti * ((1 - tj) * g[i + 1, j] + tj * g[i + 1, j + 1])
    return 0.0 if not math.isfinite(v) else float(v)


def grid_to_maganom(
    fmap,
    path: str | os.PathLike[str],
    step_m: float = 50.0,
    *,
    fill: bool = True,  # noqa: ANN001
) -> tuple[int, int]:
    """Sample a total-field :class:`~magnav_ins.maps.grid.GridMap` (any frame) on a regular lat/lon grid of about
    ``step_m`` spacing over its bounding box (bilinear) and write it as MAGANOM1. Returns the shape. ``fill``: nodes
    without data (gaps between survey lines, the corners of a rotated grid) take the value of the nearest node with
    data, because the SITL reads a missing node as 0 nT, a step of hundreds of nT the vehicle would fly through."""
    from ..core.frames import WGS84_A

    lat_min, lat_max, lon_min, lon_max = fmap.bounds_latlon
    lat_c = 0.5 * (lat_min + lat_max)
    dlat = step_m / WGS84_A
    dlon = step_m / (WGS84_A * math.cos(lat_c))
    la = lat_min + dlat * np.arange(int((lat_max - lat_min) / dlat) + 1)
    lo = lon_min + dlon * np.arange(int((lon_max - lon_min) / dlon) + 1)
    LA, LO = np.meshgrid(la, lo, indexing="ij")
    grid = np.asarray(fmap.value(LA, LO), float)
    if fill and not np.all(np.isfinite(grid)):
        from scipy import ndimage

        idx = ndimage.distance_transform_edt(~np.isfinite(grid), return_distances=False, return_indices=True)
        grid = grid[tuple(idx)]
    write_maganom(path, math.degrees(la[0]), math.degrees(lo[0]), math.degrees(dlat), math.degrees(dlon), grid)
    return grid.shape


# ------------------------------------------------------------------------------------------------ the process
class Sitl:
    """One ArduCopter SITL process (module docstring). ``home`` (lat_deg, lon_deg, alt_m MSL, heading_deg);
    ``defaults`` parameter files (the SITL's ``copter.parm`` first); ``params`` more parameters, written to a last
    defaults file (parameters set over MAVLink do not survive a restart with ``-w``); ``world`` a MAGANOM1 file;
    ``serial1_udp_port`` where serial 1 streams (None: no serial 1); ``speedup``; ``instance`` (None: a free one).
    Use as a context manager; :attr:`gcs_url` is serial 0."""

    def __init__(
        self,
        home: tuple[float, float, float, float],
        *,
        defaults: tuple[str | os.PathLike[str], ...] | None = None,
        params: dict[str, float] | None = None,
        world: str | os.PathLike[str] | None = None,
        serial1_udp_port: int | None = None,
        speedup: float = 1.0,
        instance: int | None = None,
        workdir: str | os.PathLike[str] | None = None,
        keep_workdir: bool = False,
    ) -> None:
        d = sitl_dir()
        if d is None:
            raise InputError(f"{SITL_DIR}: no ArduCopter SITL build there")
        self.dir = d
        self.home = home
        self.defaults = tuple(defaults) if defaults is not None else (d / "copter.parm",)
        self.params = dict(params or {})
        self.world = world
        self.serial1_udp_port = serial1_udp_port
        self.speedup = float(speedup)
        self.instance = instance
        self._workdir = Path(workdir) if workdir is not None else None
        self._own_workdir = workdir is None
        self.keep_workdir = keep_workdir
        self.proc: subprocess.Popen | None = None
        self.log_path: Path | None = None

    @property
    def gcs_port(self) -> int:
        assert self.instance is not None
        return BASE_TCP_PORT + 10 * self.instance

    @property
    def gcs_url(self) -> str:
        return f"tcp:127.0.0.1:{self.gcs_port}"

    def start(self, timeout_s: float = 30.0) -> Sitl:
        if self._workdir is None:
            self._workdir = Path(tempfile.mkdtemp(prefix="magnav-sitl-"))
        self._workdir.mkdir(parents=True, exist_ok=True)
        if self.instance is None:
            self.instance = free_instance()
        defaults = [str(Path(p).resolve()) for p in self.defaults]
        if self.params:
            extra = self._workdir / "extra.parm"
            extra.write_text("".join(f"{k} {v:.9g}\n" for k, v in self.params.items()))
            defaults.append(str(extra))
        lat, lon, alt, hdg = self.home
        cmd = [
            str(self.dir / "arducopter"), "--model", "+", "--speedup", f"{self.speedup:g}",
            "--home", f"{lat:.7f},{lon:.7f},{alt:.1f},{hdg:.0f}", "--defaults", ",".join(defaults),
            f"-I{self.instance}", "-w",
        ]  # fmt: skip
        if self.serial1_udp_port is not None:
            cmd += ["--serial1", f"udpclient:127.0.0.1:{self.serial1_udp_port}"]
        env = dict(os.environ)
        if self.world is not None:
            env["SITL_MAG_ANOMALY_GRID"] = str(Path(self.world).resolve())
        self.log_path = self._workdir / "sitl.log"
        out = self.log_path.open("w")
        self.proc = subprocess.Popen(
            cmd, cwd=self._workdir, env=env, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
            start_new_session=True,
        )  # fmt: skip
        out.close()
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            if self.proc.poll() is not None:
                raise InputError(f"SITL exited at start (status {self.proc.returncode}): {self.log_text()[-400:]}")
            if "Waiting for connection" in self.log_text() or not _port_free(self.gcs_port):
                log.info("SITL instance %d up (TCP %d), %s", self.instance, self.gcs_port, self._workdir)
                return self
            time.sleep(0.1)
        self.stop()
        raise InputError(f"SITL did not open TCP {self.gcs_port} within {timeout_s:.0f} s")

    def log_text(self) -> str:
        try:
            return self.log_path.read_text(errors="replace") if self.log_path is not None else ""
        except OSError:
            return ""

    def stop(self, timeout_s: float = 5.0) -> None:
        """Terminate the SITL process group, kill it if it does not exit, remove the work directory."""
        p = self.proc
        if p is not None and p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
            try:
                p.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(p.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                p.wait(timeout=timeout_s)
        self.proc = None
        if self._own_workdir and self._workdir is not None and not self.keep_workdir:
            shutil.rmtree(self._workdir, ignore_errors=True)

    def __enter__(self) -> Sitl:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()


#: the survey the SITL world is gridded from (every line, tie lines included), relative to the project root
OSBORNE_SURVEY = PROJECT_ROOT.parent / "shared" / "data" / "fatiando" / "osborne-magnetic.csv.xz"


def osborne_world(path: str | os.PathLike[str] | None = None, step_m: float = 50.0) -> Path:
    """The SITL world for the Osborne flights: the 1990 survey gridded at ``step_m`` from EVERY line, tie lines
    included (:func:`magnav_ins.maps.build.grid_survey`), as MAGANOM1 - not the map the bridge matches against
    (``builtin:osborne-magnetic``: flight lines only, 100 m), so that map error is part of the test, as it is in
    flight. Heights are not needed (the SITL ignores them). Written once to ``path`` (default: the system temp
    directory) and reused while it is newer than the survey. Returns its path."""
    from ..maps.build import grid_survey
    from ..maps.io import read_survey

    if not OSBORNE_SURVEY.is_file():
        raise InputError(f"{OSBORNE_SURVEY}: the Osborne survey is not there (../shared/data)")
    out = (
        Path(path)
        if path is not None
        else Path(tempfile.gettempdir()) / f"magnav-osborne-world-{step_m:g}m-filled.maganom"
    )
    if out.is_file() and out.stat().st_mtime >= OSBORNE_SURVEY.stat().st_mtime:
        return out
    survey = read_survey(OSBORNE_SURVEY, geoid_undulation_m=0.0)
    world = grid_survey(survey, step_m, name="osborne-all-lines")
    grid_to_maganom(world, out, step_m)
    return out


# ------------------------------------------------------------------------------------------------ a ground station
class GroundStation:
    """A minimal ground station on the SITL's serial 0 for tests and benchmarks: records the simulated truth
    (SIM_STATE), the autopilot's EKF position (GLOBAL_POSITION_INT) and status (EKF_STATUS_REPORT), what its GPS2 receives (GPS2_RAW: the
    bridge's GPS_INPUT when it feeds GPS2), every STATUSTEXT, the armed state and the flight mode, and sets
    parameters. Times are wall-clock (``time.monotonic``) receive times; positions rad, heights m MSL."""

    def __init__(self, url: str, *, connect_timeout_s: float = 30.0) -> None:
        from .link import MavLink

        self.link = MavLink(url, source_system=255, source_component=190)
        #: SIM_STATE rows: t, lat, lon (rad), h_msl (m), vn, ve, vd (m/s), roll, pitch, yaw (rad)
        self.truth: list[tuple[float, ...]] = []
        self.ekf: list[tuple[float, float, float, float]] = []  # t, lat, lon, h_msl
        self.gps: dict[int, list[tuple[float, int, float, float]]] = {0: [], 1: []}  # instance: t, fix, lat, lon
        self.texts: list[tuple[float, int, str]] = []
        #: EKF_STATUS_REPORT: t, flags, velocity, pos_horiz, pos_vert, compass test ratios ("variances")
        self.ekf_status: list[tuple[float, int, float, float, float, float]] = []
        self.params: dict[str, float] = {}
        self.armed = False
        self.mode = ""
        self.landed = "unknown"
        self.heartbeats = 0
        t_end = time.monotonic() + connect_timeout_s
        while self.heartbeats == 0:
            if time.monotonic() > t_end:
                raise InputError(f"no HEARTBEAT from the SITL on {url} within {connect_timeout_s:.0f} s")
            self.pump(0.1)

    def request_streams(self) -> None:
        for name, hz in (("SIM_STATE", 10.0), ("GLOBAL_POSITION_INT", 5.0), ("GPS_RAW_INT", 2.0), ("GPS2_RAW", 2.0),
                         ("EXTENDED_SYS_STATE", 2.0), ("EKF_STATUS_REPORT", 2.0)):  # fmt: skip
            self.link.request_message_interval(name, hz, 1, 1)

    def pump(self, timeout: float = 0.05) -> None:
        from .link import (
            EkfStatusMessage,
            GnssMessage,
            Heartbeat,
            LandedStateMessage,
            ParamMessage,
            PositionMessage,
            StatusTextMessage,
            TruthMessage,
        )

        for m in self.link.recv(timeout):
            now = time.monotonic()
            if isinstance(m, TruthMessage):
                v = m.v_n
                self.truth.append(
                    (now, m.lat, m.lon, m.h_msl, float(v[0]), float(v[1]), float(v[2]), m.roll, m.pitch, m.yaw)
                )
            elif isinstance(m, PositionMessage) and (m.lat != 0.0 or m.lon != 0.0):
                self.ekf.append((now, m.lat, m.lon, m.h_msl))
            elif isinstance(m, GnssMessage):
                self.gps[m.instance].append((now, m.fix_type, m.lat, m.lon))
            elif isinstance(m, StatusTextMessage):
                self.texts.append((now, m.severity, m.text))
                log.info("SITL: %s", m.text)
            elif isinstance(m, ParamMessage):
                self.params[m.name] = m.value
            elif isinstance(m, EkfStatusMessage):
                self.ekf_status.append((now, m.flags, m.velocity, m.pos_horiz, m.pos_vert, m.compass))
            elif isinstance(m, LandedStateMessage):
                self.landed = m.landed
            elif isinstance(m, Heartbeat) and (m.sysid, m.compid) == (1, 1):
                self.heartbeats += 1
                self.armed = m.armed
                self.mode = self.link.copter_mode_name(m.custom_mode)

    def wait(self, cond, timeout_s: float, what: str = "", *, every=None) -> bool:  # noqa: ANN001
        """Pump until ``cond()`` or ``timeout_s``; calls ``every()`` after each pump. False on timeout."""
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            self.pump(0.05)
            if every is not None:
                every()
            if cond():
                return True
        if what:
            log.warning("SITL: timed out after %.0f s waiting for %s", timeout_s, what)
        return False

    def set_param(self, name: str, value: float, timeout_s: float = 5.0) -> bool:
        """PARAM_SET and wait for the autopilot's PARAM_VALUE echo; True when it came back with the value."""
        self.params.pop(name, None)
        for _ in range(3):
            self.link.param_set(name, value)
            if self.wait(lambda: name in self.params, timeout_s / 3):
                return abs(self.params[name] - value) <= 1e-6 * max(1.0, abs(value))
        return False

    def said(self, pattern: str, since: float = -math.inf) -> bool:
        """Whether a STATUSTEXT containing ``pattern`` (case-insensitive) arrived after ``since``."""
        p = pattern.lower()
        return any(t >= since and p in text.lower() for t, _, text in self.texts)

    def close(self) -> None:
        self.link.close()
