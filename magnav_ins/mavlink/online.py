"""The online pipeline of the companion-computer bridge and of the log replay: one factory, one input convention.

:func:`make_online_pipeline` builds the INS + map matcher + fuser (:class:`magnav_ins.pipeline.Pipeline`) that the
bridge (:mod:`.bridge`) runs on the autopilot's stream and that ``magnav-ins replay`` (:mod:`.replay`) runs over a
recording, so that a replay reproduces what the companion computer would have computed. Neither imports the other.

:class:`OnlinePipeline` is that pipeline fed the way an autopilot feeds it:

* IMU samples of a declared type (:data:`magnav_ins.ins.strapdown.SAMPLE_TYPES`): ``mean`` (rate over the interval
  ending at ``t``, the mechanisation's own input; PX4 ``sensor_combined``), ``instantaneous`` (the filtered rate at
  ``t``, ArduPilot's HIGHRES_IMU; turned into interval means by the trapezoid, :class:`~magnav_ins.ins.strapdown.
  SampleMeans`) or ``increment``;
* a static IMU correction (gyro and accelerometer biases, body FRD) measured before the run, e.g. by the bridge's
  ground alignment, subtracted from every sample; the fuser estimates what is left;
* external position fixes (the autopilot's own GNSS while it is healthy) through
  :meth:`~magnav_ins.pipeline.Pipeline.push_fix`;
* with ``background_matching`` (the live bridge) a batch matcher's scan runs in one worker thread while the IMU
  samples keep coming: a scan takes 0.1-1 s of CPU (more on a loaded companion computer), which would otherwise
  stop the bridge's loop, its outputs and its socket reads for that long. The fix is applied when the scan is
  done, at its own time (the UKF rewinds to it and re-propagates, ``buffer_s``); the stored window is shifted by the
  correction applied, so it stays one rigid INS track. One scan at a time: a window due while one is running waits
  for the next match time (counted in ``matches_deferred``). The replay and the offline runs stay synchronous.

Units: SI, body FRD, NED, as everywhere in the package.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np

from ..core.errors import ConfigError, InputError
from ..core.frames import latlon_to_meters, meters_to_latlon
from ..core.protocols import MatchWindow
from ..core.types import Fix, Innovation, NavEstimate, NavState
from ..ins.strapdown import SampleMeans
from ..pipeline import Pipeline

log = logging.getLogger(__name__)

#: IMU sample type the readers and the bridge assume when told ``auto``: ArduPilot's HIGHRES_IMU carries the
#: latest filtered sample (instantaneous); PX4's HIGHRES_IMU and ``sensor_combined`` carry rates averaged over
#: the sample interval (from the delta angles / velocities); a CSV recording is documented as interval means.
#: longest IMU interval (s) the bridge and the replay integrate; after a longer gap the INS restarts from its
#: last estimate with the position sigma grown by speed x gap
MAX_GAP_S = 0.5
AUTO_SAMPLE_TYPE = {"ardupilot": "instantaneous", "px4": "mean", "ulog": "mean", "csv": "mean", "other": "mean"}


class OnlinePipeline(Pipeline):
    """A :class:`~magnav_ins.pipeline.Pipeline` taking IMU samples of ``sample_type`` and removing a static bias
    (``gyro_bias_b`` rad/s, ``accel_bias_b`` m/s^2, body FRD) before the fuser sees them (module docstring). Other
    arguments as :class:`~magnav_ins.pipeline.Pipeline`."""

    def __init__(
        self,
        fuser: Any,
        matcher: Any = None,
        fmap: Any = None,
        *,
        sample_type: str = "mean",
        gyro_bias_b: np.ndarray | None = None,
        accel_bias_b: np.ndarray | None = None,
        background_matching: bool = False,
        **options: Any,
    ) -> None:
        super().__init__(fuser, matcher, fmap, **options)
        self.background_matching = bool(background_matching)
        self._executor: ThreadPoolExecutor | None = None
        self._job: tuple[Future, float] | None = None  # the scan running, and when it was started (IMU time)
        self.matches_deferred = 0
        #: IMU-clock seconds from the end of each background scan's window to its fix being applied
        self.match_delays_s: list[float] = []
        self._means = SampleMeans(sample_type)
        self.sample_type = sample_type
        self._gyro_bias = np.zeros(3)
        self._accel_bias = np.zeros(3)
        self.set_static_bias(gyro_bias_b, accel_bias_b)
        #: the INS attitude at the last IMU samples (for :meth:`push_attitude`), and its innovations
        self._track_attitude = getattr(fuser, "name", "") == "ukf"
        self._attitudes: deque[tuple[float, np.ndarray]] = deque(maxlen=64)
        self.attitude_innovations: list[Innovation] = []

    def set_sample_type(self, sample_type: str) -> None:
        """Change the sample type of later samples (the bridge learns it from the autopilot's heartbeat)."""
        self._means = SampleMeans(sample_type)
        self.sample_type = sample_type

    def set_static_bias(self, gyro_bias_b: np.ndarray | None, accel_bias_b: np.ndarray | None) -> None:
        """Subtract these biases (rad/s, m/s^2, body FRD; None = zero) from every later sample."""
        g = np.zeros(3) if gyro_bias_b is None else np.asarray(gyro_bias_b, float).reshape(3)
        a = np.zeros(3) if accel_bias_b is None else np.asarray(accel_bias_b, float).reshape(3)
        if not (np.all(np.isfinite(g)) and np.all(np.isfinite(a))):
            raise ConfigError(f"static IMU bias must be finite, got gyro {g.tolist()}, accel {a.tolist()}")
        self._gyro_bias, self._accel_bias = g, a

    @property
    def imu_bias(self) -> tuple[np.ndarray, np.ndarray]:
        """The whole bias removed from the samples now: static part + the fuser's estimate (gyro rad/s,
        accelerometer m/s^2, body FRD); what a restarted pipeline should start from."""
        b_a, b_g = getattr(self.fuser, "bias", (np.zeros(3), np.zeros(3)))
        return self._gyro_bias + np.asarray(b_g, float), self._accel_bias + np.asarray(b_a, float)

    def push_attitude(self, t: float, q_nb: np.ndarray, sigma_rad: tuple[float, float, float]) -> Innovation | None:
        """An independent attitude (the autopilot's AHRS): ``q_nb`` scalar-last body FRD -> NED at ``t`` (s, the IMU
        clock), 1-sigmas ``sigma_rad`` (tilt about north, east; heading), as a measurement of the INS attitude error
        (:mod:`magnav_ins.aiding.fusion.attitude_aid`). Compared with the INS attitude of the IMU sample nearest to
        ``t`` (within 50 ms; else not used, None). Only for the UKF (the free-inertial baseline stays free)."""
        from ..aiding.fusion.attitude_aid import attitude_error, correct_attitude

        if getattr(self.fuser, "name", "") != "ukf" or not self._attitudes:
            return None
        ts = np.array([a[0] for a in self._attitudes])
        k = int(np.argmin(np.abs(ts - t)))
        if abs(ts[k] - t) > 0.05:
            return None
        inn = correct_attitude(self.fuser, attitude_error(self._attitudes[k][1], q_nb), sigma_rad)
        self.attitude_innovations.append(inn)
        if inn.accepted:
            self._attitudes.clear()  # the INS attitudes before the correction are not the INS's any more
        return inn

    def nav_now(self) -> NavState:
        """The INS state now without propagating the covariance (:meth:`estimate` does): the UKF's and the free
        INS's stepper state, else the estimate's."""
        stepper = getattr(self.fuser, "_stepper", None)
        return stepper.nav if stepper is not None else self.estimate().nav

    def forget_last_sample(self) -> None:
        """After a gap: the next ``instantaneous`` sample has no previous one to average with."""
        self._means.reset()

    def push_imu(self, t: float, gyro_b: np.ndarray, accel_b: np.ndarray) -> None:
        """One IMU sample of this pipeline's sample type at ``t`` (s): rad/s and m/s^2 (rad and m/s for
        increments), body FRD."""
        if self._job is not None and self._job[0].done():
            self._collect()
        w, f = self._means.means(t, gyro_b, accel_b)
        super().push_imu(t, w - self._gyro_bias, f - self._accel_bias)
        if self._track_attitude:
            from ..aiding.fusion.attitude_aid import ins_attitude

            self._attitudes.append((float(t), ins_attitude(self.fuser)))

    def push_imu_batch(
        self,
        t: np.ndarray,
        gyro_b: np.ndarray,
        accel_b: np.ndarray,
        *,
        altitude_hold: np.ndarray | None = None,
        attitudes: bool = False,
    ) -> np.ndarray | None:
        """Several IMU samples of this pipeline's sample type (``t`` (m,) s; (m,3) rad/s and m/s^2, body FRD):
        the same as :meth:`push_imu` for each in turn, in one fuser call where possible
        (:meth:`~magnav_ins.pipeline.Pipeline.push_imu_batch`, whose ``altitude_hold`` and ``attitudes`` it takes)."""
        if self._job is not None and self._job[0].done():
            self._collect()
        t = np.asarray(t, dtype=float).reshape(-1)
        if len(t) == 0:
            return np.zeros((0, 4)) if attitudes else None
        ga = np.asarray(gyro_b, dtype=float).reshape(-1, 3)
        fa = np.asarray(accel_b, dtype=float).reshape(-1, 3)
        bad = ~(np.isfinite(ga).all(axis=1) & np.isfinite(fa).all(axis=1))
        if bad.any():  # as push_imu would: the pipeline names the sample (the means would spread the NaN)
            k = int(np.argmax(bad))
            if k:
                self.push_imu_batch(
                    t[:k], ga[:k], fa[:k], altitude_hold=None if altitude_hold is None else altitude_hold[:k]
                )
            super().push_imu(float(t[k]), ga[k], fa[k])
        w, f = self._means.means_batch(t, ga, fa)
        track = self._track_attitude or attitudes
        q = super().push_imu_batch(t, w - self._gyro_bias, f - self._accel_bias, altitude_hold=altitude_hold,
                                   attitudes=track)  # fmt: skip
        if self._track_attitude and q is not None:
            for k in range(max(0, len(t) - (self._attitudes.maxlen or 0)), len(t)):
                self._attitudes.append((float(t[k]), q[k].copy()))
        return q if attitudes else None

    @property
    def can_push_outputs(self) -> bool:
        """True when :meth:`push_imu_outputs` applies: a free-inertial fuser that can (no matcher, no queued
        reading, no attitude tracking)."""
        return (
            self.matcher is None
            and not self._pending
            and self._job is None
            and not self._track_attitude
            and getattr(self.fuser, "can_propagate_outputs", False)
        )

    def push_imu_outputs(
        self, t: np.ndarray, gyro_b: np.ndarray, accel_b: np.ndarray, out_idx: np.ndarray
    ) -> np.ndarray:
        """Several IMU samples as :meth:`push_imu_batch` (``t`` (m,) s, (m,3) rad/s and m/s^2 of this pipeline's
        sample type, body FRD), with the estimate after each sample ``out_idx`` (increasing indices) returned as
        rows (:data:`magnav_ins.aiding.fusion.free_run.ROW_COLUMNS`): the same numbers as :meth:`push_imu_batch` up
        to each of them and :meth:`estimate` there, in one compiled call (the free-inertial replay). Only when
        :attr:`can_push_outputs`."""
        if not self.can_push_outputs:
            raise ConfigError("push_imu_outputs: only for a free-inertial pipeline without a matcher")
        t = np.asarray(t, dtype=float).reshape(-1)
        if len(t) and not t[0] > self._t_imu + 1e-9:
            raise InputError(f"push_imu_outputs: time must increase: t={float(t[0])!r} s after t={self._t_imu!r} s")
        w, f = self._means.means_batch(t, gyro_b, accel_b)
        rows = self.fuser.propagate_outputs(t, w - self._gyro_bias, f - self._accel_bias, out_idx)
        if len(t):
            self._t_imu = float(t[-1])
        return rows

    # -- background matching -------------------------------------------------------------------------------
    def _match(self, win: MatchWindow, est: NavEstimate, long: MatchWindow | None = None) -> None:
        if not self.background_matching or self._batch:
            super()._match(win, est, long)
            return
        if self._job is not None:
            self.matches_deferred += 1
            self._n_readings -= 1  # try again at the next reading
            return
        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="magnav-matcher")
        self._job = (self._executor.submit(self.match_window, win, long), float(est.nav.t))

    def _collect(self) -> None:
        """Apply the finished scan's fix at its own time and shift the stored window by the correction."""
        assert self._job is not None
        future, t_start = self._job
        self._job = None
        try:
            fix = future.result()
        except Exception as exc:  # noqa: BLE001 - a matcher failure is a "no fix", not a stopped bridge
            log.warning("matcher failed: %s", exc)
            fix = Fix.no_fix(t_start, f"matcher error: {exc}", getattr(self.matcher, "name", ""))
        before = self.fuser.estimate()
        self.match_delays_s.append(float(before.nav.t) - float(fix.t))
        self.fixes.append(fix)
        inn = self.fuser.correct(fix)
        self.innovations.append(inn)
        if inn.accepted:
            after = self.fuser.estimate().nav
            dn, de = latlon_to_meters(after.lat - before.nav.lat, after.lon - before.nav.lon, before.nav.lat)
            for x in self._stored:  # the whole window is one INS track, before the correction
                dlat, dlon = meters_to_latlon(float(dn), float(de), x.lat, x.h)
                x.lat, x.lon = x.lat + float(dlat), x.lon + float(dlon)

    def finish_matching(self, timeout_s: float | None = None) -> None:
        """Wait for a running scan and apply its fix (tests, a clean stop); then free the worker thread."""
        if self._job is not None:
            self._job[0].result(timeout=timeout_s)
            self._collect()
        self.close()

    def close(self) -> None:
        """Free the worker thread (a scan still running finishes and is dropped)."""
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None
        self._job = None


def make_online_pipeline(
    nav0: NavState,
    sigma_pos_m: float,
    fmap: Any,
    *,
    grade: str = "tactical",
    matcher: str | dict[str, Any] = "mlr",
    fusion: str = "ukf",
    reading_sigma: float = 5.0,
    window: int = 30,
    match_every: int = 10,
    long_window: int | None = None,
    velocity_sigma_mps: float = 0.2,
    attitude_sigma_rad: tuple[float, float, float] = (0.005, 0.005, 0.02),
    altitude_hold: bool = True,
    sample_type: str = "mean",
    gyro_bias_b: np.ndarray | None = None,
    accel_bias_b: np.ndarray | None = None,
    fusion_options: dict[str, Any] | None = None,
    rng: np.random.Generator | None = None,
    background_matching: bool = False,
) -> OnlinePipeline:
    """The online pipeline of the bridge and the replay, starting from ``nav0``.

    ``sigma_pos_m``: 1-sigma of the initial north/east position (m; the down sigma is the same); ``fmap``: the map
    (its ``kind`` is the readings' kind); ``grade``: IMU grade name (:func:`magnav_ins.ins.imu_models.get_grade`) for
    the filter's noise and initial bias covariance; ``matcher``: a registry kind (``"mlr"``) or a full config dict
    (:func:`magnav_ins.aiding.matchers.registry.build_matcher`), ``"none"`` for no matching; ``fusion``: ``ukf`` |
    ``graph`` | ``free_inertial`` (:func:`magnav_ins.aiding.fusion.make_fuser`), with ``fusion_options`` for its
    constructor; ``reading_sigma``: 1-sigma of a reading in the map's unit (sensor noise and uncompensated vehicle
    field); ``window`` / ``match_every`` / ``long_window``: readings per batch-matcher window, between match
    attempts, and of the longer window tried after an ambiguous one (:class:`~magnav_ins.pipeline.Pipeline`); ``velocity_sigma_mps`` (m/s) and ``attitude_sigma_rad`` (roll, pitch,
    yaw, rad): initial 1-sigmas; ``altitude_hold``: clamp the INS height to ``nav0.h`` (the free vertical channel
    diverges in minutes); the bridge and the replay move the clamp to the barometric height when pressure arrives
    (:func:`.baro.hold_height`); ``sample_type``, ``gyro_bias_b``, ``accel_bias_b``, ``background_matching``:
    :class:`OnlinePipeline`.
    """
    from ..aiding.fusion import ImuNoise, make_fuser
    from ..ins.error_model import initial_covariance
    from ..ins.imu_models import get_grade

    if not (math.isfinite(sigma_pos_m) and sigma_pos_m > 0):
        raise ConfigError(f"initial position sigma must be a positive number of metres, got {sigma_pos_m!r}")
    g = get_grade(grade)
    P0 = initial_covariance(g, sigma_pos_m, velocity_sigma_mps, np.asarray(attitude_sigma_rad, float))
    if altitude_hold:
        P0[2, :] = P0[:, 2] = 0.0  # height clamped: no vertical position / velocity error
        P0[5, :] = P0[:, 5] = 0.0
    init = NavEstimate(nav0, P0)
    options: dict[str, Any] = dict(fusion_options or {})
    if fusion in ("ukf", "free_inertial") and altitude_hold:
        options.setdefault("altitude_hold", float(nav0.h))
    fuser = make_fuser(fusion, init, ImuNoise.from_grade(g), **options)
    m = None
    if fusion != "free_inertial" and matcher not in (None, "none"):
        from ..aiding.matchers.registry import build_matcher  # here: the free INS needs none (scipy.stats, 30 MB)

        m = build_matcher({"kind": matcher} if isinstance(matcher, str) else dict(matcher))
    kind = getattr(fmap, "kind", None)
    return OnlinePipeline(
        fuser,
        m,
        fmap if m is not None else None,
        sample_type=sample_type,
        gyro_bias_b=gyro_bias_b,
        accel_bias_b=accel_bias_b,
        window=window,
        match_every=match_every,
        long_window=long_window,
        reading_sigma=float(reading_sigma),
        reading_kind=kind,
        height_aid=None,
        rng=rng if rng is not None else np.random.default_rng(0),
        background_matching=background_matching,
    )
