"""Is the autopilot's own GNSS to be trusted? The bridge's view of GPS_RAW_INT / GPS2_RAW.

While the autopilot's GNSS is healthy the bridge fuses it (the INS biases are estimated in flight, as on every
MagNav flight test); when it is lost or marked untrusted the bridge continues on map fixes alone. States:

``none``     no healthy fix seen yet
``healthy``  a 3D fix, enough satellites, a stated accuracy within the limit, at most ``timeout_s`` old
``lost``     was healthy, now is not (fix lost, too few satellites, accuracy gone, messages stopped); it becomes
             healthy again only after ``recover_s`` of uninterrupted health (a receiver coming out of jamming
             reports fixes before they are right)
``denied``   told not to trust it: an operator command or ``deny_after_s`` (tests); only :meth:`allow` ends it

The raw receiver messages are used, never GLOBAL_POSITION_INT (the autopilot's EKF output: once the bridge feeds
the autopilot, that is the bridge's own position coming back). GPS_RAW_INT carries no jamming or spoofing flags in
the MAVLink dialect of pymavlink 2.4.50 (GNSS_INTEGRITY is not in it); a receiver that loses its fix under jamming
is caught by the fix type.
"""

from __future__ import annotations

import math

from .link import GnssMessage

#: 1-sigma (m) assumed for a fix that states neither ``h_acc`` nor HDOP, and the floor of any stated one
DEFAULT_SIGMA_M = 5.0
SIGMA_FLOOR_M = 0.5
#: user equivalent range error (m) turning an HDOP into a horizontal 1-sigma when ``h_acc`` is not sent
UERE_M = 3.0


def gnss_sigma_m(msg: GnssMessage) -> float:
    """Horizontal 1-sigma of a GNSS fix, m: ``h_acc``, else HDOP x :data:`UERE_M`, else :data:`DEFAULT_SIGMA_M`;
    at least :data:`SIGMA_FLOOR_M`."""
    if math.isfinite(msg.sigma_h) and msg.sigma_h > 0:
        s = msg.sigma_h
    elif math.isfinite(msg.hdop) and msg.hdop > 0:
        s = msg.hdop * UERE_M
    else:
        s = DEFAULT_SIGMA_M
    return max(float(s), SIGMA_FLOOR_M)


class GnssMonitor:
    """The state machine of the module docstring. ``min_satellites`` (a count of -1, "unknown", passes),
    ``max_sigma_m`` (m), ``timeout_s``, ``recover_s``, ``deny_after_s`` (s from :meth:`start`) on the caller's
    monotonic clock."""

    def __init__(
        self,
        *,
        min_satellites: int = 6,
        max_sigma_m: float = 10.0,
        timeout_s: float = 1.5,
        recover_s: float = 10.0,
        deny_after_s: float | None = None,
    ) -> None:
        self.min_satellites = int(min_satellites)
        self.max_sigma_m = float(max_sigma_m)
        self.timeout_s = float(timeout_s)
        self.recover_s = float(recover_s)
        self.deny_after_s = deny_after_s
        self.state = "none"
        self.reason = "no GNSS fix yet"
        self.last: GnssMessage | None = None  # the latest healthy fix
        self.last_sigma_m = math.nan
        self._t_good = -math.inf
        self._good_since: float | None = None
        self._t_start: float | None = None
        self.messages = 0
        self.losses = 0

    def start(self, now: float) -> None:
        if self._t_start is None:
            self._t_start = now

    @property
    def healthy(self) -> bool:
        return self.state == "healthy"

    def problem(self, msg: GnssMessage) -> str:
        """Why ``msg`` is not a usable fix ("" when it is)."""
        if msg.fix_type < 3:
            return f"no 3D fix (fix type {msg.fix_type})"
        if not msg.has_position:
            return "position 0 N 0 E"
        if 0 <= msg.satellites < self.min_satellites:
            return f"{msg.satellites} satellites < {self.min_satellites}"
        s = gnss_sigma_m(msg)
        if s > self.max_sigma_m:
            return f"accuracy {s:.1f} m > {self.max_sigma_m:.0f} m"
        return ""

    def push(self, msg: GnssMessage, now: float) -> None:
        self.start(now)
        self.messages += 1
        problem = self.problem(msg)
        if problem:
            self._good_since = None
            if self.state == "healthy":
                self._lose(problem)
            elif self.state in ("none", "lost"):
                self.reason = problem
            return
        self.last = msg
        self.last_sigma_m = gnss_sigma_m(msg)
        self._t_good = now
        if self.state == "none":
            self.state, self.reason = "healthy", ""
        elif self.state == "lost":
            if self._good_since is None:
                self._good_since = now
            elif now - self._good_since >= self.recover_s:
                self.state, self.reason = "healthy", ""

    def update(self, now: float) -> str:
        """Apply the timeouts at ``now``; returns the state."""
        self.start(now)
        if self.deny_after_s is not None and self.state != "denied" and now - self._t_start >= self.deny_after_s:
            self.deny(f"--deny-gnss-after {self.deny_after_s:g} s")
        if self.state == "healthy" and now - self._t_good > self.timeout_s:
            self._lose(f"no GNSS message for {now - self._t_good:.1f} s")
        return self.state

    def _lose(self, reason: str) -> None:
        self.state, self.reason = "lost", reason
        self.losses += 1
        self._good_since = None

    def deny(self, reason: str) -> None:
        """Stop trusting the GNSS until :meth:`allow` (operator command, test option)."""
        if self.state == "healthy":
            self.losses += 1
        self.state, self.reason = "denied", reason
        self._good_since = None

    def allow(self) -> None:
        """End an operator denial: the GNSS is trusted again after ``recover_s`` of health."""
        if self.state == "denied":
            self.state, self.reason = "lost", "operator allowed the GNSS again; waiting for it to be healthy"
            self.deny_after_s = None
