"""The field model of the bridge and the replay: a body magnetometer vector -> a total-field anomaly reading.

:class:`ScalarAnomalyModel` (re-exported by :mod:`.bridge`, its home until the replay needed it without the bridge's
MAVLink stack: ``magnav-ins replay`` of a CSV or ULog imports no pymavlink). Units: nT, body FRD; positions rad.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..core.types import NavState


class ScalarAnomalyModel:
    """Field model for total-field anomaly maps: ``|A (m - b)| - F_IGRF(position, date) - offset`` in nT.

    ``calibration`` (a :class:`~magnav_ins.aiding.calibration.MagCalibration`, or None for raw readings) removes the
    vehicle's hard- and soft-iron effects; the IGRF total field is recomputed when the estimate has moved more than
    ``refresh_m`` (it changes by a few nT per km). ``offset_nt``: what is left between the readings and the map
    where the position is known (a main-field model that is not the IGRF, as in a simulator; a constant vehicle
    field): :meth:`observe` takes a reading and the map's value at a GNSS-known position and keeps the median of the
    last ``offset_window`` differences once there are ``offset_min_samples`` of them (0 before; the bridge calls it
    only while GNSS-aided, so the offset is frozen when the GNSS is lost).
    """

    def __init__(
        self,
        date: str,
        calibration: object | None = None,
        refresh_m: float = 2000.0,
        *,
        offset_min_samples: int = 50,
        offset_window: int = 3000,
    ) -> None:
        from collections import deque

        self._igrf_total: Any = None  # the IGRF (ppigrf, and pandas under it: 24 MB): :meth:`prepare` imports it
        self.date = date
        self.calibration = calibration
        self.refresh_m = refresh_m
        self._cache: tuple[float, float, float] | None = None  # lat, lon, F
        self.offset_nt = 0.0
        self.offset_min_samples = int(offset_min_samples)
        self._residuals: deque[float] = deque(maxlen=int(offset_window))
        self._established = False

    def prepare(self) -> float:
        """Import the IGRF (ppigrf and pandas under it: 325 modules, 0.3-2 s on a loaded 2-core machine) and evaluate
        it once, so that the first reading costs what every other does (15-20 ms when the IGRF is recomputed). The
        bridge calls this before its loop runs: imported at the first reading, it stalled the loop right after the INS
        started (0.8-2.1 s without an output in the SITL flights of the README). Returns the seconds spent."""
        import time

        t0 = time.perf_counter()
        if self._igrf_total is None:
            from ..maps.reference import igrf_total

            self._igrf_total = igrf_total
        self._igrf_total(0.0, 0.0, 0.0, self.date)  # the date is parsed and the coefficients read now
        return time.perf_counter() - t0

    @property
    def offset_samples(self) -> int:
        return len(self._residuals)

    def __call__(self, mag_b_nt: np.ndarray, nav: NavState) -> float:
        m = np.asarray(mag_b_nt, float)
        if self.calibration is not None:
            m = np.asarray(self.calibration.apply(m), float).reshape(3)  # type: ignore[attr-defined]
        if self._cache is None or _distance_m(self._cache[0], self._cache[1], nav.lat, nav.lon) > self.refresh_m:
            if self._igrf_total is None:  # not prepared (a replay): imported now
                from ..maps.reference import igrf_total

                self._igrf_total = igrf_total
            f = float(np.asarray(self._igrf_total(nav.lat, nav.lon, nav.h, self.date)).reshape(-1)[0])
            self._cache = (nav.lat, nav.lon, f)
        return float(np.linalg.norm(m)) - self._cache[2] - self.offset_nt

    def observe(self, value_nt: float, map_value_nt: float) -> bool:
        """A reading ``value_nt`` (as returned by this model now) where the map says ``map_value_nt``; updates
        ``offset_nt``. Returns True the first time the offset is established."""
        self._residuals.append(float(value_nt) + self.offset_nt - float(map_value_nt))
        if len(self._residuals) < self.offset_min_samples:
            return False
        self.offset_nt = float(np.median(self._residuals))
        first = not self._established
        self._established = True
        return first


def _distance_m(lat0: float, lon0: float, lat1: float, lon1: float) -> float:
    from ..core.frames import horizontal_error_m

    return float(horizontal_error_m(lat1, lon1, lat0, lon0))
