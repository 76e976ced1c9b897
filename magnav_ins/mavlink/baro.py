"""Barometric height aid for the bridge and the replay: static pressure -> a height the INS vertical channel follows.

The online pipeline clamps the INS height (``altitude_hold``: the free vertical channel diverges in minutes). Without a
barometer the clamp stays at the initial height, so a drone that climbs gets a wrong height (and the mechanisation's
radii and gravity with it). :class:`BaroHeight` turns pressure samples into a height referenced to the pressure at
initialisation,

    ``h_baro(t) = h0 + (alt(p(t)) - alt(p0))``

with ``alt`` the ICAO standard-atmosphere pressure altitude (:func:`magnav_ins.core.atmosphere.pressure_altitude_m`),
``h0`` the INS height at initialisation (m, ellipsoidal) and ``p0`` the filtered pressure then; :func:`hold_height`
moves the pipeline's altitude hold to it (the same clamp, with a moving reference).

Filtering, in pressure-altitude space: a running median of the last ``median_n`` samples (stamped with the middle
sample's time, so a steady climb is not delayed) removes spikes; a straight line fitted to the medians of the last
``window_s`` seconds is the low-pass, and is evaluated at the query time (extrapolated by at most ``extrapolate_s``
past the newest median) so a steady climb is followed without lag. Its slope is the climb rate (m/s, up).

Health: NaN, non-positive and implausible pressures (outside ``min_pa``-``max_pa``: above the tropopause or deeper
than any place on Earth) are dropped and counted; repeated or slightly older time stamps are dropped and counted; a
clock jump back by more than ``reset_backstep_s`` (an autopilot reboot) restarts the filter but keeps the reference.
When no sample has arrived for more than ``stale_s`` (on the IMU clock), the last baro height is held (and the
climb rate reported as 0) with a logged warning, until samples come back.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from ..core.atmosphere import TROPOPAUSE_P_PA, pressure_altitude_m

log = logging.getLogger(__name__)

#: plausible static pressure range, Pa: the tropopause (11 km, the formula's limit) to a deep-mine / storm maximum
MIN_PRESSURE_PA = TROPOPAUSE_P_PA
MAX_PRESSURE_PA = 115_000.0


@dataclass
class BaroHealth:
    """Counters of the barometric height aid. ``state``: ``none`` (no usable sample yet), ``active`` or ``stale``."""

    samples: int = 0
    rejected: int = 0
    out_of_order: int = 0
    clock_resets: int = 0
    stale_events: int = 0
    state: str = "none"

    def as_dict(self) -> dict[str, int | str]:
        return dict(self.__dict__)


class BaroHeight:
    """Pressure samples in, a height (m) and climb rate (m/s, up) out (module docstring).

    Call :meth:`push` with every pressure sample (``t`` s on the autopilot clock, Pa), :meth:`set_reference` once the
    INS is initialised (its height ``h0`` m), and :meth:`height` at IMU times. Times are seconds on the same clock
    as the IMU's.
    """

    def __init__(
        self,
        *,
        median_n: int = 5,
        window_s: float = 1.0,
        extrapolate_s: float = 0.25,
        stale_s: float = 2.0,
        reset_backstep_s: float = 1.0,
        min_pa: float = MIN_PRESSURE_PA,
        max_pa: float = MAX_PRESSURE_PA,
    ) -> None:
        from ..core.errors import ConfigError

        if median_n < 1 or not (window_s > 0 and extrapolate_s >= 0 and stale_s > 0 and 0 < min_pa < max_pa):
            raise ConfigError(
                f"baro filter: median_n >= 1, window_s > 0, extrapolate_s >= 0, stale_s > 0, 0 < min_pa < max_pa; got "
                f"{median_n}, {window_s}, {extrapolate_s}, {stale_s}, {min_pa}, {max_pa}"
            )
        self.median_n = int(median_n)
        self.window_s = float(window_s)
        self.extrapolate_s = float(extrapolate_s)
        self.stale_s = float(stale_s)
        self.reset_backstep_s = float(reset_backstep_s)
        self.min_pa = float(min_pa)
        self.max_pa = float(max_pa)
        self.health = BaroHealth()
        self._raw: deque[tuple[float, float]] = deque(maxlen=self.median_n)  # (t, pressure altitude m)
        self._med: deque[tuple[float, float]] = deque()  # medians within the fit window
        self._fit: tuple[float, float, float] | None = None  # (t_c, a(t_c) m, slope m/s)
        self._t_last = -math.inf  # newest accepted sample
        self._t_med = -math.inf  # newest median
        self._h0: float | None = None
        self._t_ref = math.nan
        self._a0: float | None = None

    # ------------------------------------------------------------------------------------------- input
    def push(self, t: float, pressure_pa: float) -> bool:
        """One pressure sample. Returns False (and counts why) when it was dropped."""
        h = self.health
        p = float(pressure_pa)
        if not (math.isfinite(p) and self.min_pa <= p <= self.max_pa and math.isfinite(t)):
            h.rejected += 1
            if h.rejected == 1 or h.rejected % 100 == 0:
                log.warning("barometer: pressure %r Pa at t=%r s dropped (implausible; %d so far)", p, t, h.rejected)
            return False
        if t <= self._t_last:
            if self._t_last - t > self.reset_backstep_s:
                h.clock_resets += 1
                log.warning("barometer: clock went back by %.1f s (reboot?): filter restarted", self._t_last - t)
                self._raw.clear()
                self._med.clear()
                self._fit = None
                self._t_med = -math.inf
            else:
                h.out_of_order += 1
                return False
        a = float(pressure_altitude_m(p))
        self._t_last = float(t)
        self._raw.append((float(t), a))
        ts = sorted(x[0] for x in self._raw)
        t_mid = ts[len(ts) // 2] if len(ts) % 2 else 0.5 * (ts[len(ts) // 2 - 1] + ts[len(ts) // 2])
        self._med.append((t_mid, float(np.median([x[1] for x in self._raw]))))
        self._t_med = t_mid
        while self._med and self._med[0][0] < t_mid - self.window_s:
            self._med.popleft()
        self._refit()
        h.samples += 1
        if self._h0 is not None and self._a0 is None and len(self._med) >= self.median_n:
            self._a0 = self._altitude_at(self._t_med)  # deferred reference: the first full median
        if h.state == "stale":
            log.info("barometer: pressure samples back after a gap, height follows the barometer again")
        h.state = "active"
        return True

    def _refit(self) -> None:
        tm = np.array([x[0] for x in self._med])
        am = np.array([x[1] for x in self._med])
        t_c = float(tm.mean())
        if len(tm) >= 3 and np.ptp(tm) > 0:
            dt = tm - t_c
            slope = float(np.dot(dt, am - am.mean()) / np.dot(dt, dt))
        else:
            slope = 0.0
        self._fit = (t_c, float(am.mean()), slope)

    def _altitude_at(self, t: float) -> float:
        """Fitted pressure altitude (m) at ``t``, extrapolated at most :attr:`extrapolate_s` past the newest median."""
        assert self._fit is not None
        t_c, a_c, slope = self._fit
        return a_c + slope * (min(t, self._t_med + self.extrapolate_s) - t_c)

    def set_reference(self, h0_m: float, t: float) -> None:
        """The INS height ``h0_m`` (m) at ``t`` (s): from now on ``height = h0 + alt(p) - alt(p(t))``. Without
        samples yet, the reference pressure is the first full median (``median_n`` samples)."""
        self._h0 = float(h0_m)
        self._t_ref = float(t)
        self._a0 = self._altitude_at(t) if self._fit is not None else None
        if self._a0 is not None:
            log.info("barometer: height referenced, %.1f m at pressure altitude %.1f m", self._h0, self._a0)

    @property
    def referenced(self) -> bool:
        """True once both the reference height and the reference pressure are known."""
        return self._h0 is not None and self._a0 is not None

    # ------------------------------------------------------------------------------------------ output
    def _update_state(self, t: float) -> bool:
        """Mark the barometer stale when its newest sample is more than :attr:`stale_s` older than ``t``; True
        when the height is fresh."""
        h = self.health
        if h.state == "none":
            return False
        fresh = t - self._t_last <= self.stale_s or t < self._t_last - self.reset_backstep_s
        if not fresh and h.state == "active":
            h.state = "stale"
            h.stale_events += 1
            held = self._height_at(self._t_last)
            log.warning(
                "barometer: no pressure sample for %.1f s, holding the last baro height (%s)",
                t - self._t_last,
                "not referenced yet" if held is None else f"{held:.1f} m",
            )
        return fresh

    def height(self, t: float) -> float | None:
        """The baro height (m, the INS's height frame) at IMU time ``t`` (s), or None before the first sample or the
        reference. Stale: the last baro height."""
        fresh = self._update_state(t)
        if not fresh or t < self._t_last - self.reset_backstep_s:  # stale, or the IMU clock restarted first
            t = self._t_last
        return self._height_at(t)

    def _height_at(self, t: float) -> float | None:
        if self._h0 is None or self._a0 is None or self._fit is None:
            return None
        return self._h0 + self._altitude_at(t) - self._a0

    def climb_rate(self, t: float) -> float | None:
        """Climb rate (m/s, up) at ``t``: the fitted slope; 0 when stale; None before the first sample."""
        if self._fit is None:
            return None
        return self._fit[2] if self._update_state(t) else 0.0


def hold_height(pipeline: object, h_m: float) -> bool:
    """Move the altitude hold of ``pipeline``'s INS to ``h_m`` (m): the next IMU step ends at that height with zero
    down velocity. Returns False when the pipeline holds no altitude (fusion ``graph``, ``altitude_hold=False``).

    Uses the fuser's :meth:`~magnav_ins.aiding.fusion.common.InertialCore.set_altitude_hold`.
    """
    fuser = getattr(pipeline, "fuser", None)
    if not getattr(fuser, "holds_altitude", False):
        return False
    fuser.set_altitude_hold(float(h_m))  # type: ignore[union-attr]
    return True
