"""The closed loop: INS + map matcher + fuser over one stream of IMU samples and field readings.

Parts come in through the constructor (no object owns everything): a :class:`~magnav_ins.core.protocols.Fuser`
(which runs the INS: UKF, factor graph or free inertial, from :func:`magnav_ins.aiding.fusion.make_fuser`), a matcher
(a batch :class:`~magnav_ins.core.protocols.MapMatcher` or a :class:`~magnav_ins.core.protocols.RecursiveMatcher`,
or None for no aiding) and the :class:`~magnav_ins.core.protocols.FieldMap` it matches against.

Loop (Wang et al. 2022, seed 001, Fig. 1 / sec. 3.3; Storms 2009, seed 004, sec. 3.4 for the recursive form):

* IMU samples go to ``fuser.propagate``. A sample that straddles an event time (a reading, an output time) is cut
  in two at the event (rates are interval means, so both parts keep the rates), so every event sees the state at its
  own time.
* At each reading time the fuser's current estimate is the matcher's prior: the INS-indicated position, its 2x2
  covariance and velocity are stored with the reading. A batch matcher gets a :class:`MatchWindow` of the last
  ``window`` readings every ``match_every`` readings (once the window is full); a recursive matcher is initiated
  from the first estimate, predicted with each new estimate and updated with each reading, and asked for a fix every
  ``match_every`` readings. A batch window whose INS-indicated track spans less than ``min_section_m`` (default: one
  map cell) is not matched: "no fix: section too short" (a hovering, landing or parked vehicle: its readings repeat
  one value, which fits every place where the map is flat along the few metres the INS drifts, so a profile matcher
  would issue a narrow fix anywhere; measured on the SITL flight of issue 17, fixes from the descent and the ground
  were 120-345 m off with 25-35 m sigmas). When a fix is accepted, the stored window positions are shifted by the correction
  applied at the fix time, so the window stays one rigid INS track. With ``long_window`` a window whose fix is
  ambiguous, or whose likelihood reaches the edge of the search window, is matched again over the last
  ``long_window`` readings (:meth:`Pipeline.match_window`): a section over a smooth stretch of the map fits several
  places, and a longer one reaches the next features (the bridge's default, twice its 80-reading window: on the
  SITL flights of issue 17 with 11-28 such refusals each, the bridge lost trust for 14-119 s on 6 of 16 recordings
  played back, 9-44 s on 4 with it).
* Every fix (also "no fix") goes to ``fuser.correct`` (its :class:`Innovation` records acceptance and reason), with
  the optional height aid ``height_aid(t) -> (h_m, sigma_m)`` (e.g. a barometer). A batch matcher in retrodiction
  mode (``mode = "retrodiction"`` with ``match_batch``, PMHT-MM) gives a fix per scan and their joint covariance;
  the available ones go together to ``fuser.correct_batch`` (one correlated measurement; no height aid).

Online: :meth:`Pipeline.push_imu` and :meth:`Pipeline.push_reading` (sample by sample; a reading stamped in the
future is queued until the IMU reaches it; a late one uses the current estimate moved back along the velocity);
:meth:`Pipeline.estimate` gives the current :class:`NavEstimate`. Offline: :meth:`Pipeline.run` over an
:class:`ImuBatch` and :class:`FieldReadings` returns a :class:`PipelineResult` with the trajectory and covariance at
``output_dt``, the fixes and the innovations.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from .core.errors import ConfigError, InputError
from .core.frames import latlon_to_meters, meters_to_latlon
from .core.protocols import FieldMap, MatchWindow
from .core.types import (
    DEFAULT_INTEGRITY_RISK,
    EDGE_REASON,
    FieldKind,
    FieldReadings,
    Fix,
    ImuBatch,
    Innovation,
    NavEstimate,
    NavTrajectory,
)

FloatArray = NDArray[np.float64]
HeightAid = Callable[[float], "tuple[float, float] | None"]
_TOL = 1e-9

#: "no fix" reasons of a batch matcher for which a longer window is tried (``Pipeline(long_window=...)``): the
#: section does not single out one place, and more of the track may (the likelihood matchers' "ambiguous: ..." and
#: :data:`~magnav_ins.core.types.EDGE_REASON`)
LONG_WINDOW_REASONS = ("ambiguous", EDGE_REASON)


@dataclass(frozen=True)
class PipelineResult:
    """What an offline run produced: ``trajectory`` (estimated states at the output times), ``P`` (N,15,15) the
    fuser's covariance at those times (LAYOUT_15), every ``fixes`` the matcher issued (including "no fix"), every
    fuser ``innovations`` (accepted or excluded with a reason) and ``hpl_m`` (N,) the fuser's horizontal protection
    level at the output times (m, at ``integrity_risk``; NaN where the fuser gives none)."""

    trajectory: NavTrajectory
    P: FloatArray
    fixes: list[Fix] = field(default_factory=list)
    innovations: list[Innovation] = field(default_factory=list)
    hpl_m: FloatArray = field(default_factory=lambda: np.zeros(0))
    integrity_risk: float = DEFAULT_INTEGRITY_RISK


@dataclass
class _Stored:
    t: float
    value: FloatArray | float
    lat: float
    lon: float
    h: float
    cov_ne: FloatArray
    v_ne: FloatArray


def _track_span_m(stored: list[_Stored]) -> float:
    """Diagonal (m) of the north/east extent of the stored INS-indicated positions."""
    lat = np.array([x.lat for x in stored])
    lon = np.array([x.lon for x in stored])
    dn, de = latlon_to_meters(lat - lat[0], lon - lon[0], float(lat[0]))
    return float(np.hypot(np.ptp(dn), np.ptp(de)))


class Pipeline:
    """Compose a fuser, a matcher and a map (module docstring).

    ``window``: readings per batch-matcher window (K); ``match_every``: readings between match attempts;
    ``reading_sigma`` and ``reading_kind``: the readings' 1-sigma noise and kind for :meth:`push_reading` (taken from
    the :class:`FieldReadings` in :meth:`run`); ``height_aid``: optional ``t -> (h, sigma)`` height source;
    ``rng``: generator for a recursive matcher's initiation; ``min_section_m``: shortest INS-indicated track (m, the
    diagonal of its north/east extent) a batch window must span to be matched (None: the map's cell size,
    ``fmap.spacing_m``, else 0; 0 = no test; module docstring); ``long_window``: readings of a second, longer
    window a batch matcher is asked to match when the ``window`` one gives no fix for one of
    :data:`LONG_WINDOW_REASONS` (None: no second try; :meth:`match_window`).
    """

    def __init__(
        self,
        fuser,
        matcher=None,
        fmap: FieldMap | None = None,
        *,
        window: int = 30,
        match_every: int = 10,
        reading_sigma: float | None = None,
        reading_kind: FieldKind | str | None = None,
        height_aid: HeightAid | None = None,
        rng: np.random.Generator | None = None,
        min_section_m: float | None = None,
        long_window: int | None = None,
    ) -> None:
        if matcher is not None and fmap is None:
            raise ConfigError("Pipeline: a matcher needs a map (fmap)")
        if window < 1 or match_every < 1:
            raise ConfigError(f"Pipeline: window and match_every must be >= 1, got {window}, {match_every}")
        self.fuser = fuser
        self.matcher = matcher
        self.fmap = fmap
        self.window = int(window)
        self.match_every = int(match_every)
        if long_window is not None and not (isinstance(long_window, int | np.integer) and long_window > window):
            raise ConfigError(
                f"Pipeline: long_window must be a number of readings above window ({window}), got {long_window!r}"
            )
        self.long_window = None if long_window is None else int(long_window)
        self.reading_sigma = reading_sigma
        kind = reading_kind if reading_kind is not None else getattr(fmap, "kind", None)
        self.reading_kind = FieldKind(kind) if kind is not None else None
        self.height_aid = height_aid
        self.rng = rng if rng is not None else np.random.default_rng(0)
        if min_section_m is None:
            spacing = getattr(fmap, "spacing_m", None)
            min_section_m = float(max(spacing)) if spacing is not None else 0.0
        if not (np.isfinite(min_section_m) and min_section_m >= 0.0):
            raise ConfigError(f"Pipeline: min_section_m must be a number of metres >= 0, got {min_section_m!r}")
        self.min_section_m = float(min_section_m)
        self._recursive = matcher is not None and hasattr(matcher, "initiate") and hasattr(matcher, "to_fix")
        # retrodiction (Wang sec. 3.3): the matcher returns a fix per scan with their joint covariance, the fuser
        # takes them as one correlated measurement (aiding.fusion.batch)
        self._batch = (
            matcher is not None and getattr(matcher, "mode", "") == "retrodiction" and hasattr(matcher, "match_batch")
        )
        if self._batch and not hasattr(fuser, "correct_batch"):
            raise ConfigError(
                f"Pipeline: matcher {getattr(matcher, 'name', '?')!r} in retrodiction mode needs a fuser that fuses a "
                f"batch of correlated fixes (correct_batch: ukf, free_inertial); {getattr(fuser, 'name', '?')!r} has none"
            )
        self._rstate = None
        self._stored: deque[_Stored] = deque(maxlen=max(self.window, self.long_window or 0))
        self._pending: list[tuple[float, FloatArray | float]] = []  # readings ahead of the IMU
        self._n_readings = 0
        self._t_imu = float(fuser.estimate().nav.t)
        self.fixes: list[Fix] = []
        self.innovations: list[Innovation] = []
        self.external_innovations: list[Innovation] = []  # of push_fix (GNSS, surveyed points)

    # ---------------------------------------------------------------------------------------------- online
    def estimate(self) -> NavEstimate:
        """The fuser's current estimate."""
        return self.fuser.estimate()

    def push_imu(self, t: float, gyro_b: FloatArray, accel_b: FloatArray) -> None:
        """One IMU sample: mean rates over ``(t_prev, t]`` (rad/s, m/s^2 specific force, body FRD)."""
        w = np.asarray(gyro_b, dtype=float).reshape(3)
        f = np.asarray(accel_b, dtype=float).reshape(3)
        if not (np.isfinite(t) and np.all(np.isfinite(w)) and np.all(np.isfinite(f))):
            raise InputError(f"Pipeline.push_imu: non-finite sample at t={t!r}: gyro {w.tolist()}, accel {f.tolist()}")
        if t <= self._t_imu + _TOL:
            raise InputError(f"Pipeline.push_imu: time must increase: t={t!r} s after t={self._t_imu!r} s")
        self._pending.sort(key=lambda x: x[0])
        while self._pending and self._pending[0][0] <= t + _TOL:
            t_r, value = self._pending.pop(0)
            if t_r > self._t_imu + _TOL:
                self._propagate_to(t_r, w, f)
            self._on_reading(t_r, value)
        self.fuser.propagate(ImuBatch(np.array([t]), w[None, :], f[None, :]))
        self._t_imu = float(t)

    def push_imu_batch(
        self,
        t: FloatArray,
        gyro_b: FloatArray,
        accel_b: FloatArray,
        *,
        altitude_hold: FloatArray | None = None,
        attitudes: bool = False,
    ) -> FloatArray | None:
        """Several IMU samples (``t`` (m,) s increasing, rates (m,3) as :meth:`push_imu`): the same as
        :meth:`push_imu` for each in turn (with the fuser's altitude hold moved to ``altitude_hold[k]`` m before
        sample ``k``, :func:`magnav_ins.mavlink.baro.hold_height`), in one fuser call when no queued reading falls
        among them. ``attitudes``: return the INS attitude ``q_nb`` (m,4) after each sample."""
        t = np.asarray(t, dtype=float).reshape(-1)
        w = np.asarray(gyro_b, dtype=float).reshape(-1, 3)
        f = np.asarray(accel_b, dtype=float).reshape(-1, 3)
        m = len(t)
        if m == 0:
            return np.zeros((0, 4)) if attitudes else None
        if len(w) != m or len(f) != m:
            raise InputError(f"Pipeline.push_imu_batch: {m} times but {len(w)} gyro and {len(f)} accel samples")
        bad = ~(np.isfinite(t) & np.isfinite(w).all(axis=1) & np.isfinite(f).all(axis=1))
        if bad.any():
            k = int(np.argmax(bad))
            raise InputError(
                f"Pipeline.push_imu: non-finite sample at t={float(t[k])!r}: gyro {w[k].tolist()}, accel {f[k].tolist()}"
            )
        prev_t = np.concatenate([[self._t_imu], t[:-1]])
        bad = t <= prev_t + _TOL
        if bad.any():
            k = int(np.argmax(bad))
            raise InputError(
                f"Pipeline.push_imu: time must increase: t={float(t[k])!r} s after t={float(prev_t[k])!r} s"
            )
        self._pending.sort(key=lambda x: x[0])
        if self._pending and self._pending[0][0] <= t[-1] + _TOL:  # a queued reading falls among them
            from .aiding.fusion.attitude_aid import ins_attitude

            q = np.empty((m, 4))
            for k in range(m):
                if altitude_hold is not None:
                    self.fuser.set_altitude_hold(float(altitude_hold[k]))
                Pipeline.push_imu(self, float(t[k]), w[k], f[k])  # these samples are the fuser's own
                q[k] = ins_attitude(self.fuser) if attitudes else 0.0
            return q if attitudes else None
        kw: dict = {} if altitude_hold is None else {"altitude_hold": altitude_hold}
        if attitudes:
            kw["attitudes"] = True
        q = self.fuser.propagate(ImuBatch(t, w, f), **kw)
        self._t_imu = float(t[-1])
        return q if attitudes else None

    def push_reading(self, t: float, value: FloatArray | float) -> Fix | None:
        """One field reading at ``t`` (s) in the map's unit. Returns the fix issued at this reading, if any
        (readings ahead of the IMU are queued and return None)."""
        if self.reading_sigma is None or self.reading_kind is None:
            raise ConfigError("Pipeline.push_reading: construct the pipeline with reading_sigma and reading_kind")
        v = np.asarray(value, dtype=float)
        if not (np.isfinite(t) and np.all(np.isfinite(v))):
            raise InputError(f"Pipeline.push_reading: non-finite reading at t={t!r}: {v.tolist()}")
        if t > self._t_imu + _TOL:
            self._pending.append((float(t), v))
            return None
        n = len(self.fixes)
        self._on_reading(float(t), v)
        return self.fixes[-1] if len(self.fixes) > n else None

    def push_fix(self, fix: Fix, *, height_m: float | None = None, height_sigma_m: float | None = None) -> Innovation:
        """An external position fix (GNSS, a surveyed point) at ``fix.t`` (at or before the IMU time: the fuser
        applies a late one at its own time). It goes to ``fuser.correct`` like a matcher's fix, the stored matcher
        window is shifted by the correction (as for a matcher fix), and its innovation is kept in
        ``external_innovations`` (``fixes`` and ``innovations`` hold the matcher's only). Returns the innovation."""
        before = self.fuser.estimate()
        if height_m is not None:
            inn = self.fuser.correct(fix, height_m=float(height_m), height_sigma_m=height_sigma_m)
        else:
            inn = self.fuser.correct(fix)
        self.external_innovations.append(inn)
        if inn.accepted and abs(before.nav.t - fix.t) <= 1e-6:
            self._shift_window(before)
        return inn

    # ------------------------------------------------------------------------------------------ internals
    def _shift_window(self, before: NavEstimate) -> None:
        """Shift the stored window positions by the correction the fuser applied since ``before``."""
        after = self.fuser.estimate().nav
        dn, de = latlon_to_meters(after.lat - before.nav.lat, after.lon - before.nav.lon, before.nav.lat)
        dh = after.h - before.nav.h
        for x in self._stored:
            dlat, dlon = meters_to_latlon(float(dn), float(de), x.lat, x.h)
            x.lat, x.lon, x.h = x.lat + float(dlat), x.lon + float(dlon), x.h + dh

    def _propagate_to(self, t_c: float, w: FloatArray, f: FloatArray) -> None:
        """The first part of a straddling sample, up to the event time ``t_c``."""
        self.fuser.propagate(ImuBatch(np.array([t_c]), w[None, :], f[None, :]))
        self._t_imu = float(t_c)

    def _on_reading(self, t: float, value: FloatArray | float) -> None:
        est = self.fuser.estimate()
        nav = est.nav
        lat, lon, h = nav.lat, nav.lon, nav.h
        if t < nav.t - _TOL:  # late reading: move the current position back along the velocity
            dlat, dlon = meters_to_latlon(-nav.v_n[0] * (nav.t - t), -nav.v_n[1] * (nav.t - t), nav.lat, nav.h)
            lat, lon, h = lat + float(dlat), lon + float(dlon), h + nav.v_n[2] * (nav.t - t)
        cov = np.asarray(est.cov_ne, dtype=float)
        self._stored.append(_Stored(t, value, lat, lon, h, cov, np.asarray(nav.v_n[:2], float)))
        self._n_readings += 1
        if self.matcher is None:
            return
        if self._recursive:
            if self._rstate is None:
                self._rstate = self.matcher.initiate(est, self.rng)
            else:
                self._rstate = self.matcher.predict(self._rstate, est)
            one = FieldReadings(
                np.array([t]), np.asarray(value, float)[None, ...], self.reading_sigma, self.reading_kind
            )
            self._rstate = self.matcher.update(self._rstate, one, self.fmap)
            if self._n_readings % self.match_every == 0:
                self._apply_fix(self.matcher.to_fix(self._rstate), est)
        elif len(self._stored) >= self.window and self._n_readings % self.match_every == 0:
            s = list(self._stored)[-self.window :]
            span = _track_span_m(s)
            if span < self.min_section_m:
                reason = (
                    f"section too short: the INS track spans {span:.0f} m, under {self.min_section_m:g} m "
                    "(hovering or on the ground?)"
                )
                self._apply_fix(Fix.no_fix(t, reason, getattr(self.matcher, "name", "matcher")), est)
                return
            long = list(self._stored) if self.long_window and len(self._stored) == self.long_window else None
            self._match(self._window_of(s), est, None if long is None else self._window_of(long))

    def _window_of(self, s: list[_Stored]) -> MatchWindow:
        readings = FieldReadings(
            np.array([x.t for x in s]), np.array([x.value for x in s]), self.reading_sigma, self.reading_kind
        )
        return MatchWindow(
            readings,
            np.array([x.lat for x in s]),
            np.array([x.lon for x in s]),
            np.array([x.h for x in s]),
            np.array([x.cov_ne for x in s]),
            np.array([x.v_ne for x in s]),
        )

    def match_window(self, win: MatchWindow, long: MatchWindow | None = None) -> Fix:
        """The matcher's fix for ``win``; when that is a "no fix" for one of :data:`LONG_WINDOW_REASONS` (an
        ambiguous likelihood, or one that reaches the edge of the search window: the section holds too few features
        to single out one place) and ``long`` (the last ``long_window`` readings) is given, the fix for ``long``
        (whatever it is; its reason says which window it came from)."""
        fix = self.matcher.match(win, self.fmap)
        if long is None or fix.available or not fix.reason.startswith(LONG_WINDOW_REASONS):
            return fix
        second = self.matcher.match(long, self.fmap)
        if second.available:
            return second
        return replace(second, reason=f"{fix.reason}; {len(long.readings)} readings: {second.reason}")

    def _match(self, win: MatchWindow, est: NavEstimate, long: MatchWindow | None = None) -> None:
        """Match a full window of a batch matcher and apply the fix(es) (a subclass may run it elsewhere);
        ``long``: the longer window of a second try (:meth:`match_window`)."""
        if self._batch:
            fixes, cov = self.matcher.match_batch(win, self.fmap)
            self._apply_batch(fixes, cov, est)
        else:
            self._apply_fix(self.match_window(win, long), est)

    def _apply_batch(self, fixes: list[Fix], cov: FloatArray, before: NavEstimate) -> None:
        """A retrodiction batch: every fix is kept; the available ones go to ``fuser.correct_batch`` with their
        joint covariance (one innovation); a batch without any goes to ``fuser.correct`` as its last "no fix"."""
        self.fixes.extend(fixes)
        ok = [f for f in fixes if f.available]
        inn = self.fuser.correct_batch(ok, cov) if ok else self.fuser.correct(fixes[-1])
        self.innovations.append(inn)
        if inn.accepted:
            after = self.fuser.estimate().nav
            dn, de = latlon_to_meters(after.lat - before.nav.lat, after.lon - before.nav.lon, before.nav.lat)
            dh = after.h - before.nav.h
            for x in self._stored:  # keep the window one rigid INS track
                dlat, dlon = meters_to_latlon(float(dn), float(de), x.lat, x.h)
                x.lat, x.lon, x.h = x.lat + float(dlat), x.lon + float(dlon), x.h + dh

    def _apply_fix(self, fix: Fix, before: NavEstimate) -> None:
        self.fixes.append(fix)
        aid = self.height_aid(fix.t) if (self.height_aid is not None and np.isfinite(fix.t)) else None
        if aid is not None:
            inn = self.fuser.correct(fix, height_m=float(aid[0]), height_sigma_m=float(aid[1]))
        else:
            inn = self.fuser.correct(fix)
        self.innovations.append(inn)
        if inn.accepted and abs(before.nav.t - fix.t) <= 1e-6:
            after = self.fuser.estimate().nav
            dn, de = latlon_to_meters(after.lat - before.nav.lat, after.lon - before.nav.lon, before.nav.lat)
            dh = after.h - before.nav.h
            for x in self._stored:  # keep the window one rigid INS track
                dlat, dlon = meters_to_latlon(float(dn), float(de), x.lat, x.h)
                x.lat, x.lon, x.h = x.lat + float(dlat), x.lon + float(dlon), x.h + dh

    # --------------------------------------------------------------------------------------------- offline
    def run(self, imu: ImuBatch, readings: FieldReadings | None = None, output_dt: float = 1.0) -> PipelineResult:
        """Process a whole recording. The estimate is recorded at ``t0 + k output_dt`` (t0 = the fuser's start)
        up to the last IMU time. Readings outside the IMU span are ignored."""
        if not output_dt > 0:
            raise ConfigError(f"Pipeline.run: output_dt must be > 0, got {output_dt}")
        if len(imu) and np.any(np.diff(imu.t) <= 0):
            raise InputError("Pipeline.run: IMU times must increase strictly")
        if readings is not None:
            self.reading_sigma = readings.sigma
            self.reading_kind = readings.kind
            if len(readings) and np.any(np.diff(readings.t) < 0):
                raise InputError("Pipeline.run: reading times must not decrease")
        t0 = self._t_imu
        t_end = float(imu.t[-1]) if len(imu) else t0
        t_out = t0 + output_dt * np.arange(int(np.floor((t_end - t0) / output_dt + 1e-9)) + 1)
        events: list[tuple[float, int, int]] = [(float(t), 0, k) for k, t in enumerate(t_out)]
        if readings is not None:
            ok = np.flatnonzero((readings.t > t0 + _TOL) & (readings.t <= t_end + _TOL))
            events += [(float(readings.t[k]), 1, int(k)) for k in ok]
        events.sort()
        outs: list[NavEstimate] = []
        i = int(np.searchsorted(imu.t, t0 + _TOL, side="right"))
        for t_ev, kind, k in events:
            j = int(np.searchsorted(imu.t, t_ev + _TOL, side="right"))
            if j > i:
                self.fuser.propagate(imu.slice(i, j))
                self._t_imu = float(imu.t[j - 1])
                i = j
            if t_ev > self._t_imu + _TOL and i < len(imu):
                self._propagate_to(t_ev, imu.gyro_b[i], imu.accel_b[i])
            if kind == 0:
                outs.append(self.fuser.estimate())
            else:
                self._on_reading(t_ev, readings.value[k])
        if i < len(imu):
            self.fuser.propagate(imu.slice(i, len(imu)))
            self._t_imu = t_end
        navs = [o.nav for o in outs]
        traj = NavTrajectory(
            np.array([n.t for n in navs]),
            np.array([n.lat for n in navs]),
            np.array([n.lon for n in navs]),
            np.array([n.h for n in navs]),
            np.array([n.v_n for n in navs]).reshape(-1, 3),
            np.array([n.q_nb for n in navs]).reshape(-1, 4),
        )
        P = np.array([np.asarray(o.P)[:15, :15] for o in outs]).reshape(-1, 15, 15)
        hpl = np.array([float(o.hpl_m) for o in outs], dtype=float)
        risk = float(outs[0].integrity_risk) if outs else DEFAULT_INTEGRITY_RISK
        return PipelineResult(traj, P, list(self.fixes), list(self.innovations), hpl, risk)
