"""A recorded autopilot stream played back to the bridge on a simulated clock: the bridge's real code path
(:class:`.bridge.Bridge`: GNSS aiding, ground alignment, the flat-world adaptation, attitude aid, outputs), offline
and deterministic, for diagnosis and for tests against a recorded ArduPilot SITL flight.

:class:`TlogPlayback` stands in for :class:`.link.MavLink`: it decodes a telemetry log (``.tlog``, pymavlink's
record: an 8-byte big-endian receive time in microseconds before each frame) with the same decoder and yields each
message once the simulated clock has reached its receive time; whatever the bridge sends is counted and dropped.
:func:`play` runs a bridge over a whole log and returns its outputs (the ``on_output`` records) and the log's
simulator truth (SIM_STATE), both on the log's clock (s, Unix time of reception).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink import mavutil

from ..core.errors import InputError
from .link import MavLink, TruthMessage


class TlogPlayback(MavLink):
    """A :class:`MavLink` whose peer is a recorded log (module docstring). ``clock()`` is the simulated time (the
    log's receive times, s); :meth:`recv` yields the messages received up to it."""

    def __init__(self, path: str | Path, clock: Callable[[], float], **kw: Any) -> None:
        p = Path(path)
        if not p.is_file():
            raise InputError(f"{p}: no such tlog file")
        if p.suffix == ".xz":  # a compressed recording (the tests' fixtures): read from a decompressed copy
            import lzma
            import tempfile

            self._tmp = tempfile.TemporaryDirectory(prefix="magnav-tlog-")
            plain = Path(self._tmp.name) / p.stem
            plain.write_bytes(lzma.decompress(p.read_bytes()))
            p = plain
        self._clock = clock
        self._pending_msg: tuple[float, object] | None = None
        self.sent = 0
        self.truth: list[TruthMessage] = []
        self.truth_t: list[float] = []
        super().__init__(str(p), **kw)
        self.first_t = self._peek_time()

    def _open(self):
        return mavutil.mavlink_connection(self.url, dialect="ardupilotmega", robust_parsing=True)

    def _next(self) -> tuple[float, object] | None:
        while True:
            m = self._conn.recv_msg()
            if m is None:
                return None
            kind = m.get_type()
            if kind in ("BAD_DATA", "UNKNOWN"):
                continue
            out = self._decode(m, kind)
            if out is None:
                continue
            return float(m._timestamp), out

    def _peek_time(self) -> float:
        if self._pending_msg is None:
            self._pending_msg = self._next()
        return math.inf if self._pending_msg is None else self._pending_msg[0]

    @property
    def finished(self) -> bool:
        return self._peek_time() == math.inf

    def recv(self, timeout: float = 0.0, budget_s: float = 0.05) -> Iterator[object]:
        now = self._clock()
        while self._pending_msg is not None or not self.finished:
            if self._peek_time() > now:
                break
            t, msg = self._pending_msg  # type: ignore[misc]
            self._pending_msg = None
            self.stats.received += 1
            if isinstance(msg, TruthMessage):
                self.truth.append(msg)
                self.truth_t.append(t)
            yield msg

    def _send(self, send: Callable[[], None]) -> None:
        self.sent += 1

    def write_raw(self, data: bytes) -> None:
        self.sent += 1

    def reconnect(self) -> None:
        pass


@dataclass
class Playback:
    """What :func:`play` returns: the bridge's output records, the truth (``truth`` rows ``t, lat, lon, h_msl, vn,
    ve``; rad, m, m/s), the bridge (for its health and pipeline)."""

    outputs: list[dict[str, Any]] = field(default_factory=list)
    truth: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    bridge: Any = None


def play(path: str | Path, make_bridge: Callable[[MavLink, Callable[[], float], Callable], Any],
         step_s: float = 0.005, until_s: float | None = None) -> Playback:  # fmt: skip
    """Play the log at ``path`` to the bridge ``make_bridge(link, clock, on_output)`` builds, polling it every
    ``step_s`` of simulated time (as the live bridge's loop does) until the log ends (or ``until_s`` after its
    start)."""
    now = [0.0]
    link = TlogPlayback(path, lambda: now[0])
    out = Playback()
    now[0] = link.first_t
    bridge = make_bridge(link, lambda: now[0], out.outputs.append)
    t_end = math.inf if until_s is None else link.first_t + until_s
    while not link.finished and now[0] < t_end:
        bridge.poll(0.0)
        now[0] += step_s
    bridge._finish()
    out.bridge = bridge
    out.truth = np.array(
        [
            (t, m.lat, m.lon, m.h_msl, float(m.v_n[0]), float(m.v_n[1]))
            for t, m in zip(link.truth_t, link.truth, strict=True)
        ]
    ).reshape(-1, 6)
    return out
