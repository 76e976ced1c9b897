"""Loosely coupled error-state UKF on filterpy (``UnscentedKalmanFilter`` + ``MerweScaledSigmaPoints``).
The ONLY module of the package that imports filterpy.

Architecture (Wang et al. 2022, sec. 3.3 and Fig. 1, seed 001; Groves 2013 sec. 14.1-14.2): the strapdown INS
(:class:`ins.strapdown.StrapdownStepper`) runs on bias-corrected IMU samples; the filter state is the 15-state error
``x = [dp_n, dv_n, psi, db_a, db_g]`` (LAYOUT_15, every error "estimate minus truth", defined in
:mod:`ins.error_model`). Prediction: ``x <- Phi x`` with ``(Phi, Qd)`` from :func:`ins.error_model.system_matrices`
and :func:`ins.error_model.discretize` recomputed for each propagation interval (at most ``cov_step_s``, and exactly
the interval up to a fix), pushed through the unscented transform. Measurement: a fix's north/east position,
``z = r_fix - r_ins`` (m, NED at the INS position) and ``h(x) = -x[pos N, E]``, noise ``R = fix.cov_ne`` (any SPD
2x2); with an optional height source ``z`` gains ``-(h_src - h_ins)`` and ``h(x)`` gains ``x[pos D]``.

Optional states (``scale_factors``, ``map_bias_sigma_m``; :class:`common.ExtraStates`,
:func:`ins.error_model.augment_system`): 6 scale-factor errors ``[ds_a, ds_g]`` (21 states; the velocity and
tilt rows gain ``-C_nb diag(f_b)`` and ``-C_nb diag(omega_ib_b)``, the estimates are fed back into the IMU
correction as the biases are) and/or a north/east map-registration bias ``db_map`` (m; a fix then measures
``z = r_fix - r_ins - b_map_est = -dp_NE - db_map + v``, so fixes sharing the map's offset are correlated in time,
Gauss-Markov with ``map_bias_tau_s``). The reported innovation is then ``z`` after the map-bias estimate is taken
off. Without them the filter is the 15-state one above, number for number.

Fault detection and exclusion (:class:`integrity.FaultMonitor`): the single-fix gate (NIS ``y^T S^-1 y`` against
the ``gate_probability`` chi-square quantile, 2 dof, 3 with a height), a window test on the sum of the last
``fault_window`` accepted fixes' NIS (within ``fault_window_s``, at ``fault_probability``), and a recovery: when at
least ``reset_after`` excluded fixes (this one included) are mutually consistent, the filter has lost track and the
fix is applied with the navigation covariance inflated so that it sits on the gate (``extra["inflation"]``,
``extra["recovery"]``); faults that do not agree with each other are never re-accepted. An excluded fix leaves the
filter untouched and its :class:`Innovation` says which test excluded it. :meth:`estimate` carries the horizontal
protection level ``hpl_m`` at ``integrity_risk`` (covariance, fault-detection margin and the doubt of unresolved
exclusions; :mod:`.integrity`). Covariance: symmetrised, eigenvalues floored at 0 after each step, tiny jitter before
the sigma-point Cholesky (:func:`psd_sqrt`: states known exactly, zero variance, keep zero spread). Closed loop: after an accepted update the estimated
errors are fed back (``C_nb <- exp(-[psi x]) C_nb``, position/velocity minus their errors, biases ``b <- b - db``)
and the error state is reset to zero (the covariance is kept; the reset Jacobian is I to first order, Groves
sec. 14.2.7).

Latency: a fix stamped in the past (up to ``buffer_s``) is applied at its own time: the INS, biases and covariance
are restored from the last checkpoint before the fix (one per covariance step), re-propagated through the buffered
IMU samples to the fix time, corrected, and re-propagated to now with the corrected biases
(:class:`common.InertialCore`). Older fixes are rejected with a reason.

Smoothing (offline, ``keep_history=True``): :meth:`InertialCore.smooth` -- a closed-loop error-state RTS pass
about the filter's trajectory, then optional relinearised passes about the previous smoothed trajectory (iterated
smoother, Gauss-Newton); with sparse fixes and a consumer IMU the first pass is limited by the filter's drift
between fixes (KITTI: 0.86 m single pass, 0.74 m after three passes, the factor graph's batch LM 0.74 m).

Sigma points: ``alpha = 1, beta = 2, kappa = 0`` by default (lambda = 0, no negative central weight; with linear
``f``/``h`` the UKF then reproduces the Kalman filter exactly).
"""

from __future__ import annotations

import dataclasses
import sys
import types
from typing import Any

import numpy as np
import scipy.linalg

from ...core.types import DEFAULT_INTEGRITY_RISK, Fix, Innovation, NavEstimate
from ...ins.error_model import apply_error
from ..gating import ChiSquareGate, nis
from .common import ExtraStates, ImuNoise, InertialCore, Samples, fix_problem, rejected, residual_ne, symmetrise
from .integrity import (
    DEFAULT_RESET_AFTER,
    DEFAULT_WINDOW,
    DEFAULT_WINDOW_PROBABILITY,
    DEFAULT_WINDOW_S,
    FaultMonitor,
)


def _import_filterpy_kalman() -> Any:
    """``filterpy.kalman`` without importing ``scipy.stats`` (~30 MB resident, a third of a 1 M-row replay's
    margin): its modules bind ``filterpy.stats.logpdf`` at import, and ``filterpy.stats`` imports ``scipy.stats``
    for it. They are imported here against a stand-in ``filterpy.stats`` whose ``logpdf`` imports the real one at
    its first call (only filterpy's ``likelihood`` / ``log_likelihood`` properties call it; this module never
    does); the stand-in is removed again, so any later ``import filterpy.stats`` gets the real module."""
    if "filterpy.kalman" in sys.modules or "filterpy.stats" in sys.modules:
        import filterpy.kalman

        return filterpy.kalman

    def logpdf(*args: Any, **kwargs: Any) -> Any:
        from filterpy.stats import logpdf as real

        return real(*args, **kwargs)

    stand_in = types.ModuleType("filterpy.stats", "lazy stand-in (magnav_ins.aiding.fusion.ukf)")
    stand_in.logpdf = logpdf  # type: ignore[attr-defined]
    sys.modules["filterpy.stats"] = stand_in
    try:
        import filterpy.kalman
    finally:
        if sys.modules.get("filterpy.stats") is stand_in:
            del sys.modules["filterpy.stats"]
        import filterpy

        if getattr(filterpy, "stats", None) is stand_in:
            del filterpy.stats
    return filterpy.kalman


_kalman = _import_filterpy_kalman()
MerweScaledSigmaPoints = _kalman.MerweScaledSigmaPoints
UnscentedKalmanFilter = _kalman.UnscentedKalmanFilter
unscented_transform = _kalman.unscented_transform


def psd_sqrt(A: np.ndarray) -> np.ndarray:
    """Upper-triangular ``U`` with ``U^T U = A`` for the sigma points (filterpy's ``sqrt_method``), ``A`` a
    covariance whose exactly known states have zero variance: the Cholesky factor of the block of states with a
    positive variance and zero rows for the others, whose sigma points then do not spread (for a PSD matrix their
    cross-covariances are zero too). A clamped vertical channel starts and stays at zero variance (the bridge and
    the replay build such a prior); filterpy's default (a plain Cholesky) needs ``A`` positive definite and failed
    on it ("6-th leading minor not positive definite", issue 18)."""
    live = np.diag(A) > 0.0
    if live.all():
        return scipy.linalg.cholesky(A)
    idx = np.flatnonzero(live)
    U = np.zeros_like(A)
    U[np.ix_(idx, idx)] = scipy.linalg.cholesky(A[np.ix_(idx, idx)])
    return U


def _fx(x: np.ndarray, dt: float, Phi: np.ndarray) -> np.ndarray:  # noqa: ARG001 (filterpy's signature)
    return Phi @ x


def _hx_ne(x: np.ndarray, H: np.ndarray | None = None) -> np.ndarray:
    return -x[0:2] if H is None else H @ x


def _hx_ned(x: np.ndarray, H: np.ndarray | None = None) -> np.ndarray:
    ne = -x[0:2] if H is None else H @ x
    return np.array([ne[0], ne[1], x[2]])  # z = [dN, dE, h_src - h_ins]; h_ins - h_true = -dp_D


class UkfFuser(InertialCore):
    """Error-state UKF fuser (see the module docstring). ``init``: initial INS state and its 15x15 covariance;
    ``noise``: IMU noise; ``gate_probability``: chi-square gate (None: no gate, e.g. for trusted GNSS fixes); ``cov_step_s``: longest covariance step (s);
    ``buffer_s``: how far back a late fix may be applied (s); ``altitude_hold``: clamp the INS height (m);
    ``keep_history``: record every covariance step, IMU sample and accepted fix for :meth:`smooth` (RTS smoother,
    offline; ``smooth(iterations)``); ``reset_after``, ``fault_window``, ``fault_window_s`` (s),
    ``fault_probability``, ``integrity_risk``: fault detection and protection level (:class:`integrity.FaultMonitor`);
    ``scale_factors``, ``scale_factor_tau_s`` (s), ``map_bias_sigma_m`` (m),
    ``map_bias_tau_s`` (s), ``map_bias_sources``: optional states (module docstring, :class:`common.ExtraStates`)."""

    name = "ukf"

    def __init__(
        self,
        init: NavEstimate,
        noise: ImuNoise,
        *,
        gate_probability: float | None = 0.9999,
        cov_step_s: float = 1.0,
        buffer_s: float = 120.0,
        altitude_hold: float | None = None,
        reset_after: int = DEFAULT_RESET_AFTER,
        fault_window: int = DEFAULT_WINDOW,
        fault_window_s: float = DEFAULT_WINDOW_S,
        fault_probability: float = DEFAULT_WINDOW_PROBABILITY,
        integrity_risk: float = DEFAULT_INTEGRITY_RISK,
        keep_history: bool = False,
        alpha: float = 1.0,
        beta: float = 2.0,
        kappa: float = 0.0,
        scale_factors: bool = False,
        scale_factor_tau_s: float | None = None,
        map_bias_sigma_m: float | None = None,
        map_bias_tau_s: float | None = None,
        map_bias_sources: tuple[str, ...] | None = None,
    ) -> None:
        self.extra = ExtraStates.from_options(
            noise, scale_factors=scale_factors, scale_factor_tau_s=scale_factor_tau_s,
            map_bias_sigma_m=map_bias_sigma_m, map_bias_tau_s=map_bias_tau_s, map_bias_sources=map_bias_sources,
        )  # fmt: skip
        n = self._n = self.extra.layout.size
        self._points = MerweScaledSigmaPoints(n, alpha=alpha, beta=beta, kappa=kappa, sqrt_method=psd_sqrt)
        self._ukf = UnscentedKalmanFilter(dim_x=n, dim_z=2, dt=1.0, hx=_hx_ne, fx=_fx, points=self._points)
        self.gate_probability = None if gate_probability is None else float(gate_probability)
        self.gate = ChiSquareGate(self.gate_probability, 2)
        self.reset_after = int(reset_after)
        self.innovations: list[Innovation] = []
        super().__init__(
            init,
            noise,
            integrity_risk=integrity_risk,
            cov_step_s=cov_step_s,
            buffer_s=buffer_s,
            altitude_hold=altitude_hold,
            keep_history=keep_history,
            scale_factors=scale_factors,
            scale_factor_tau_s=scale_factor_tau_s,
            map_bias_sigma_m=map_bias_sigma_m,
            map_bias_tau_s=map_bias_tau_s,
            map_bias_sources=map_bias_sources,
        )
        self.monitor = FaultMonitor(
            self.gate_probability, window=fault_window, window_s=fault_window_s, window_probability=fault_probability,
            reset_after=reset_after, integrity_risk=integrity_risk,
        )  # fmt: skip

    def _jitter(self, P: np.ndarray) -> np.ndarray:
        # relative jitter per state: a floor scaled by the trace (dominated by the position, m^2) would lift the
        # precision gyro-bias variance (~1e-17 rad^2/s^2) by eight orders of magnitude; states with zero variance
        # (known exactly, e.g. a clamped height) stay at zero (psd_sqrt leaves them out of the Cholesky factor)
        P = symmetrise(P, 0.0)
        d = np.diag(P)
        return P + np.diag(np.where(d > 0.0, 1e-12 * d, 0.0))

    def _predict_cov(self, Phi: np.ndarray, Qd: np.ndarray) -> None:
        """Unscented prediction of the (zero) error state through ``x <- Phi x`` with noise ``Qd``."""
        u = self._ukf
        u.x = np.zeros(self._n)
        u.P = self._jitter(self._P)
        u.Q = Qd
        # filterpy's predict() without its last step, the sigma points of the predicted covariance (a Cholesky and
        # 2n+1 points, a third of the cost): only the predicted P is kept here, and correct() draws its own points
        u.compute_process_sigmas(u._dt, _fx, Phi=Phi)
        u.x, u.P = unscented_transform(u.sigmas_f, u.Wm, u.Wc, u.Q, u.x_mean, u.residual_x)
        self._P = symmetrise(u.P, 0.0)

    def correct(self, fix: Fix, *, height_m: float | None = None, height_sigma_m: float | None = None) -> Innovation:
        """Apply a position fix (north/east; with ``height_m``, ellipsoidal m, and ``height_sigma_m`` also the
        vertical) at ``fix.t``; returns the innovation (rejected ones say why)."""
        inn = self._correct(fix, height_m, height_sigma_m)
        self.innovations.append(inn)
        return inn

    def _correct(self, fix: Fix, height_m: float | None, height_sigma_m: float | None) -> Innovation:
        problem = fix_problem(fix)
        if problem:
            return rejected(fix, problem)
        if height_m is not None and not (
            np.isfinite(height_m) and height_sigma_m is not None and np.isfinite(height_sigma_m) and height_sigma_m > 0
        ):
            return rejected(fix, f"bad height aid: height_m={height_m}, height_sigma_m={height_sigma_m}")
        if fix.t > self.t + 1e-6:
            return rejected(fix, f"fix time {fix.t:.6f} s is after the last IMU time {self.t:.6f} s")
        rest = Samples.empty()
        if fix.t < self.t - 1e-6:
            r = self._rewind(float(fix.t))
            if r is None:
                return rejected(fix, f"fix time {fix.t:.6f} s is older than the replay buffer ({self.buffer_s} s)")
            rest = r
        self._advance_cov()
        nav = self._stepper.nav
        res = residual_ne(fix, nav)
        biased = self.extra.biased(fix)
        if biased:  # z = fix - INS - b_map_est = -dp_NE - db_map + v
            res = res - self._b_map
        H_ne = self._fix_rows(fix) if biased else None
        R = np.asarray(fix.cov_ne, float)
        u = self._ukf
        n = self._n
        # sigma points of the current covariance (identity prediction, no noise)
        u.x = np.zeros(n)
        u.P = self._jitter(self._P)
        u.Q = np.zeros((n, n))
        u.predict(fx=_fx, Phi=np.eye(n))
        if height_m is not None:
            z = np.r_[res, float(height_m) - nav.h]
            Rz = np.zeros((3, 3))
            Rz[:2, :2] = R
            Rz[2, 2] = float(height_sigma_m) ** 2
            hx0, dim = _hx_ned, 3
        else:
            z, Rz, hx0, dim = res, R, _hx_ne, 2

        def hx(x: np.ndarray) -> np.ndarray:
            return hx0(x, H_ne)

        # innovation covariance by the unscented transform, for the gate (before touching the filter)
        Zs = np.array([hx(s) for s in u.sigmas_f])
        zp = u.Wm @ Zs
        dZ = Zs - zp
        S = (u.Wc[:, None] * dZ).T @ dZ + Rz
        y = z - zp
        v = nis(y, S)
        gate = self.gate if dim == 2 else ChiSquareGate(self.gate_probability, dim)
        S_ne = S[:2, :2]
        v_ne = nis(y[:2], S_ne)  # reported: the north/east NIS (2 dof), comparable across fusers
        forced = 0.0
        verdict = self.monitor.assess(fix.t, y[:2], S_ne, R, self._P[0:2, 0:2].copy(), nis_gate=v, dof=dim)
        if verdict.action == "recover" and np.isfinite(v) and v > gate.threshold:
            # recovery: mutually consistent excluded fixes say the filter, not the fixes, is wrong; inflate the
            # navigation covariance until this fix sits on the gate, then apply it
            forced = v / gate.threshold
            k = slice(0, 9)
            self._P[k, :] *= np.sqrt(forced)
            self._P[:, k] *= np.sqrt(forced)
            self._record_inflated_prior()
            u.P = self._jitter(self._P)
            u.predict(fx=_fx, Phi=np.eye(n))
            Zs = np.array([hx(s) for s in u.sigmas_f])
            zp = u.Wm @ Zs
            dZ = Zs - zp
            S = (u.Wc[:, None] * dZ).T @ dZ + Rz
            y = z - zp
            v = nis(y, S)
            S_ne = S[:2, :2]
        elif verdict.action == "reject":
            self._replay(rest)
            return Innovation(float(fix.t), y[:2], S_ne, v_ne, False, verdict.reason, fix.source, verdict.extra)
        P_prior = self._P.copy()
        u._dim_z = dim
        u.update(z, R=Rz, hx=hx)
        dx = np.asarray(u.x, float)
        self._P = symmetrise(u.P, 0.0)
        self.monitor.accepted(
            fix.t, nis(y[:2], S_ne), P_prior[0:2, 0:2], self._P[0:2, 0:2], recovery=verdict.action == "recover"
        )
        # h is linear in the error state: A = I - K H is what this update leaves of an earlier (fault) error
        H = np.column_stack([hx(e) for e in np.eye(n)])
        self._fault_update(np.eye(n) - np.asarray(u.K, float) @ H, P_prior, self._P, gate.threshold)
        # closed-loop feedback, then reset the error state
        corrected = apply_error(nav, -dx[:9])
        self._stepper.reset(corrected)
        self._set_aux(self._aux() - dx[9:n])
        u.x = np.zeros(n)
        self._record_update(dx)
        self._record_fix(fix, height_m, height_sigma_m)
        # the corrected state becomes the checkpoint at the fix time
        self._checkpoints.pop()
        self._checkpoint()
        self._replay(rest)
        extra = {"nis_full": v, "nis_dof": float(dim), **verdict.extra}
        if forced:
            extra["inflation"] = forced
            v_ne = nis(y[:2], S_ne)
        return Innovation(float(fix.t), y[:2], S_ne, v_ne, True, "", fix.source, extra)

    def correct_batch(self, fixes: list[Fix], cov: np.ndarray) -> Innovation:
        """Fuse a batch of correlated fixes (time order) with their joint covariance ``cov`` (2J, 2J) m^2 as one
        stacked measurement (:mod:`.batch`: stochastic cloning over the replay buffer, which must cover the
        batch); gated at ``gate_probability`` with 2J dof. Returns one innovation at the last fix time."""
        from .batch import correct_batch

        P_before = self.estimate().cov_ne.copy()
        inn = correct_batch(self, fixes, cov, self.gate_probability)
        if inn.accepted:  # the batch's covariance reduction, at the current time, sets the fault-detection margin
            self.monitor.accepted(inn.t, inn.nis, P_before, self.estimate().cov_ne)
        elif inn.reason.startswith("NIS") and fixes:
            C = np.asarray(cov, float)
            inn = dataclasses.replace(inn, extra={**inn.extra, "fault": 1.0})
            self.monitor.exclusion(inn.t, inn.residual_ne, C[-2:, -2:], P_before)
        self.innovations.append(inn)
        return inn
