"""Factor-graph fuser on GTSAM: IMU preintegration between fix times, robust position factors, iSAM2 online and
a batch Levenberg-Marquardt smoother offline. The ONLY module of the package that imports gtsam.

Graph (Forster et al. 2017, "On-Manifold Preintegration for Real-Time Visual-Inertial Odometry", eqs. 26-44;
Kaess et al. 2012 for iSAM2): a node ``(X_k: Pose3, V_k: velocity, B_k: ConstantBias)`` at the initial time and at every
fix time; a ``CombinedImuFactor`` between consecutive nodes (bias random walk inside the factor); a ``GPSFactor`` on
``X_k``'s translation for each accepted fix, its noise ``noiseModel.Robust(Huber(k), Gaussian(cov))`` with the fix's
2x2 north/east covariance and a vertical sigma (a height source if given, else loose); a prior on node 0 from the
initial :class:`NavEstimate`.

Frames. GTSAM works here in an Earth-fixed Cartesian frame L: the NED axes at the initial position, frozen to the
Earth (nav = NED, gravity +down). L is Earth-fixed, so the Earth rate is the constant ``omega_ie_L`` and there is no
transport rate; the plumb-line gravity turns as the vehicle moves away from the origin (1 mrad per 6.4 km). Each IMU
factor carries, in L, the gravity at its first node ``g_L(r_i)`` (``n_gravity``) and the Earth rate as GTSAM's
Coriolis vector, so that they enter through the first node's state with their Jacobians: the Earth rate taken out of
the gyros is ``R_i^T omega_ie_L dt`` and moves with the node's rotation ``R_i`` (a heading error drives the tilt,
``-omega_ie x psi``, as in the UKF's error model). Before issue 13's fix the Earth rate, Coriolis and gravity change
were taken out of the samples at the predicted attitude, frozen into the factor without that Jacobian: the graph
could not see its heading error through the tilt it drives and fitted the tilt drift with heading, tilt and gyro
bias (Osborne eight-line study: 7-20 mrad heading error with a 2 mrad sigma). What GTSAM's first-order terms leave
over the interval (the body turning away from ``R_i``, the velocity changing from ``v_i``, the gravity changing from
``g_L(r_i)``) is compensated in the samples (:meth:`_integrate`), and with keyframes on a node is added at least
every ``_KEYFRAME_MAX_S``. Body = FRD; ``Pose3`` rotation = ``C_Lb``; quaternion
order never leaves this module (rotations cross as matrices). The public face speaks :class:`NavState` /
:class:`NavEstimate` in WGS-84: L <-> geodetic through :class:`common.LocalFrame`.

Covariance. After each fix the joint marginal of ``(X_k, V_k, B_k)`` from iSAM2 is mapped to LAYOUT_15
(pos NED m, vel NED m/s, att NED rad, accel bias m/s^2, gyro bias rad/s). GTSAM's perturbations are "truth = estimate
(+) xi" with the pose increment in body axes, so ``pos_n = C_nL C_Lb xi_t``, ``att_n = C_nL C_Lb xi_R``,
``vel_n = C_nL xi_v``. Between fixes :meth:`estimate` returns ``pim.predict`` with the covariance of a temporary
graph marginal (the next node added without a fix factor), computed lazily and cached.

Latency. IMU samples since the last node are kept; a fix stamped in the past (but after the last node) splits them at
the fix time (the sample straddling it is cut in two), the node is placed at the fix time and the rest is
re-integrated, so a late fix is applied exactly as if it had arrived on time. A fix older than the last node is
rejected with a reason.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from ...core.errors import ConfigError, InputError
from ...core.types import (
    DEFAULT_INTEGRITY_RISK,
    LAYOUT_15,
    Fix,
    ImuBatch,
    Innovation,
    NavEstimate,
    NavState,
    NavTrajectory,
)
from ...ins.earth import omega_ie_n
from ..gating import ChiSquareGate, nis
from .common import ImuNoise, LocalFrame, check_time, fix_problem, rejected, residual_ne, symmetrise
from .integrity import (
    DEFAULT_RESET_AFTER,
    DEFAULT_WINDOW,
    DEFAULT_WINDOW_PROBABILITY,
    DEFAULT_WINDOW_S,
    FaultMonitor,
    Verdict,
)

FloatArray = np.ndarray
_TIME_TOL = 1e-9
_RW_FLOOR = 1e-12  # bias random walk for random-constant biases (keeps the factor's covariance regular)
_VAR_FLOOR = 1e-20  # variance given to a state the prior holds exactly (an ideal IMU's zero bias sigma), SI units^2
#: with keyframes on (``max_preintegration_rad``), also a keyframe once a preintegration spans this long (s): GTSAM's
#: Earth-rate and Coriolis terms are first order over the interval (rotation, velocity at its start); error-free IMU
#: on a 600 s flight with 6 deg/s turns and no fixes: 30 m with rotation keyframes only, 14.7 m at 60 s, 2.0 m at 20 s
_KEYFRAME_MAX_S = 20.0


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a x b`` of two 3-vectors (numpy's general ``cross`` costs ~40 us a call: most of the per-sample time)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _sqrt_information(P: FloatArray) -> FloatArray:
    """A square root ``U`` of the information ``P^-1`` (``U^T U = P^-1``) of a covariance whose
    variances span ~25 orders of magnitude (km^2 positions, ~5e-17 rad^2/s^2 navigation-grade gyro biases).

    Works on the correlation matrix ``C = D^-1 P D^-1`` (``D`` the standard deviations), whose eigenvalues are
    clipped at 1e-12 (PD) without touching the small states, then ``U = chol(C^-1)^T D^-1``. A state with a
    non-positive variance (held exactly) gets ``_VAR_FLOOR``. An absolute eigenvalue floor on ``P`` itself (1e-12
    before) raised the navigation grade's 0.0015 deg/h gyro-bias sigma to 1e-6 rad/s = 0.21 deg/h, letting the graph
    fit a 1.3 deg/h gyro bias on the Osborne tie-line flight."""
    P = 0.5 * (np.asarray(P, float) + np.asarray(P, float).T)
    d = np.diag(P).copy()
    held = ~(d > 0)
    if held.any():
        P = P.copy()
        P[held, :] = 0.0
        P[:, held] = 0.0
        P[held, held] = _VAR_FLOOR
        d = np.diag(P).copy()
    sd = np.sqrt(d)
    C = P / np.outer(sd, sd)
    w, Vec = np.linalg.eigh(0.5 * (C + C.T))
    w = np.maximum(w, 1e-12)
    Cinv = (Vec / w) @ Vec.T
    L = np.linalg.cholesky(0.5 * (Cinv + Cinv.T))
    return L.T / sd[None, :]


@dataclass
class _Node:
    t: float
    state: gtsam.NavState
    bias: gtsam.imuBias.ConstantBias


class GraphFuser:
    """GTSAM factor-graph fuser (iSAM2 online; :meth:`node_trajectory` with ``smoothed=True`` and
    :meth:`smoothed_track` give the batch LM solution over the whole graph).

    ``init``: initial state and its LAYOUT_15 covariance; ``noise``: IMU noise (continuous-time densities and bias
    sigmas); ``gate_probability``: chi-square gate on the 2-dof north/east NIS (None: no gate); ``huber_k``: Huber threshold in
    whitened units; ``vertical_sigma_m``: sigma of the vertical component of a fix without a height source (the
    measured height is then the predicted one); ``factorization``: "QR" (default; GTSAM's Cholesky reports an
    indeterminate system on poorly constrained graphs) or "CHOLESKY"; ``gravity_update_s``: period of the
    gravity-direction compensation; ``max_preintegration_rad``: a keyframe node (no fix) is added whenever the
    rotation preintegrated since the last node exceeds this angle (None: never). The gtsam wheel preintegrates the
    rotation in tangent space with Euler steps: through a 166-degree turn (roll-in at 42 deg/s, 50 Hz) one
    preintegration is 1.0 mrad off the product of the per-sample rotations, 10 s pieces 0.09 mrad, 2 s pieces
    0.002 mrad; the tilt and heading errors that leaves made the graph drift 15 km on a 59-min survey flight. With
    keyframes on, a node is also added once a preintegration spans ``_KEYFRAME_MAX_S`` (20 s).
    ``altitude_hold`` (m, ellipsoidal): the graph has no strapdown clamp, so a fix without its own height carries
    this height with 1-sigma ``altitude_hold_sigma_m``, a pseudo-measurement kept loose because the true height
    departs from it (a draped survey flight by tens of metres; a 1 m sigma bent the horizontal solution: error-free
    IMU and 80 m truth fixes on the 59-min Osborne tie-line flight gave 176 m RMS and NIS 6.3, 50 m gave 43 m and
    NIS 2.0, the UKF 35 m).
    """

    name = "graph"

    def __init__(
        self,
        init: NavEstimate,
        noise: ImuNoise,
        *,
        gate_probability: float | None = 0.9999,
        huber_k: float = 3.0,
        vertical_sigma_m: float = 1000.0,
        factorization: str = "QR",
        relinearize_skip: int = 1,
        gravity_update_s: float = 0.1,
        integration_sigma: float = 1e-4,
        reset_after: int = DEFAULT_RESET_AFTER,
        fault_window: int = DEFAULT_WINDOW,
        fault_window_s: float = DEFAULT_WINDOW_S,
        fault_probability: float = DEFAULT_WINDOW_PROBABILITY,
        integrity_risk: float = DEFAULT_INTEGRITY_RISK,
        max_preintegration_rad: float | None = None,
        altitude_hold: float | None = None,
        altitude_hold_sigma_m: float = 50.0,
    ) -> None:
        P0 = np.asarray(init.P, dtype=float)
        if P0.shape[0] < LAYOUT_15.size or P0.shape[0] != P0.shape[1]:
            raise ConfigError(f"GraphFuser: initial covariance must be at least 15x15, got {P0.shape}")
        if factorization.upper() not in ("QR", "CHOLESKY"):
            raise ConfigError(f"GraphFuser: factorization must be 'QR' or 'CHOLESKY', got {factorization!r}")
        self.noise = noise
        self.gate = ChiSquareGate(gate_probability, 2)
        self.huber_k = float(huber_k)
        self.reset_after = int(reset_after)
        self.monitor = FaultMonitor(
            gate_probability, window=fault_window, window_s=fault_window_s, window_probability=fault_probability,
            reset_after=reset_after, integrity_risk=integrity_risk,
        )  # fmt: skip
        self.vertical_sigma_m = float(vertical_sigma_m)
        self.gravity_update_s = float(gravity_update_s)
        if max_preintegration_rad is not None and not (0.0 < float(max_preintegration_rad) <= np.pi / 2):
            raise ConfigError(
                f"GraphFuser: max_preintegration_rad must be in (0, pi/2] or None, got {max_preintegration_rad!r}"
            )
        self.max_preintegration_rad = None if max_preintegration_rad is None else float(max_preintegration_rad)
        if altitude_hold is not None and not np.isfinite(altitude_hold):
            raise ConfigError(f"GraphFuser: altitude_hold must be a finite height (m) or None, got {altitude_hold!r}")
        if not (np.isfinite(altitude_hold_sigma_m) and altitude_hold_sigma_m > 0):
            raise ConfigError(f"GraphFuser: altitude_hold_sigma_m must be > 0, got {altitude_hold_sigma_m!r}")
        self.altitude_hold = None if altitude_hold is None else float(altitude_hold)
        self.altitude_hold_sigma_m = float(altitude_hold_sigma_m)
        nav0 = init.nav
        self.frame = LocalFrame(nav0.lat, nav0.lon, nav0.h)
        self._w_ie_L = omega_ie_n(nav0.lat)  # the Earth rate, constant in the Earth-fixed frame L
        self._integration_sigma = float(integration_sigma)

        ip = gtsam.ISAM2Params()
        ip.setFactorization(factorization.upper())
        ip.relinearizeSkip = int(relinearize_skip)
        self._isam = gtsam.ISAM2(ip)
        self._factorization = factorization.upper()
        self._graph = gtsam.NonlinearFactorGraph()  # every factor, for the batch smoother
        self._node_times: list[float] = []

        # node 0 and its priors
        state0 = self._to_gtsam(nav0)
        b_a = init.bias_a if hasattr(init, "bias_a") else np.zeros(3)
        b_g = init.bias_g if hasattr(init, "bias_g") else np.zeros(3)
        bias0 = gtsam.imuBias.ConstantBias(np.asarray(b_a, float), np.asarray(b_g, float))
        # the prior is the initial covariance itself (_sqrt_information: no absolute eigenvalue floor, which had
        # widened a navigation-grade gyro-bias sigma from 0.0015 to 0.21 deg/h; tests/test_fusion_graph_prior.py)
        Pl = self._layout_to_gtsam_cov(P0[:15, :15], state0)
        values = gtsam.Values()
        values.insert(X(0), state0.pose())
        values.insert(V(0), state0.velocity())
        values.insert(B(0), bias0)
        # one joint Gaussian prior on (X0, V0, B0) that keeps the cross-covariances of the initial P: the whitened
        # linear factor ||U dx||^2 with U^T U = Pl^-1, held at the initial values (LinearContainerFactor)
        U = _sqrt_information(Pl)
        prior = gtsam.JacobianFactor(X(0), U[:, 0:6], V(0), U[:, 6:9], B(0), U[:, 9:15], np.zeros(15),
                                     gtsam.noiseModel.Unit.Create(15))  # fmt: skip
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.LinearContainerFactor(prior, values))
        self._update(graph, values)
        self._k = 0
        self._node = _Node(float(nav0.t), state0, bias0)
        self._node_times.append(float(nav0.t))
        self._keyframe = False  # the last node carries no fix (added by add_node or max_preintegration_rad)
        self._P_node = self._node_covariance(0)
        self._t = float(nav0.t)
        self._buf_t: list[float] = []  # end time of each buffered sample
        self._buf_dt: list[float] = []
        self._buf_w: list[np.ndarray] = []
        self._buf_f: list[np.ndarray] = []
        self._pim = self._new_pim()
        self._comp = {"t": -np.inf, "df_b": np.zeros(3), "dw_b": np.zeros(3)}
        self._pred_cov_cache: tuple[float, FloatArray] | None = None
        self.innovations: list[Innovation] = []

    # ----------------------------------------------------------------------------------- frame conversions
    def _to_gtsam(self, nav: NavState) -> gtsam.NavState:
        r_L = self.frame.to_L(nav.lat, nav.lon, nav.h)
        C_nL = self.frame.C_nL(nav.lat, nav.lon)
        from ...core.frames import C_nb_from_q

        C_Lb = C_nL.T @ C_nb_from_q(nav.q_nb)
        return gtsam.NavState(gtsam.Rot3(C_Lb), np.asarray(r_L, float), C_nL.T @ nav.v_n)

    def _from_gtsam(self, t: float, s: gtsam.NavState) -> NavState:
        from scipy.spatial.transform import Rotation

        lat, lon, h = self.frame.to_geodetic(s.position())
        C_nL = self.frame.C_nL(float(lat), float(lon))
        C_nb = C_nL @ s.attitude().matrix()
        return NavState(
            float(t), float(lat), float(lon), float(h), C_nL @ s.velocity(), Rotation.from_matrix(C_nb).as_quat()
        )

    def _J_gtsam_to_layout(self, s: gtsam.NavState) -> FloatArray:
        """Maps GTSAM's [xi_R(3), xi_t(3) body; v(3) L; b_a(3), b_g(3)] to LAYOUT_15 (pos, vel, att NED, b_a, b_g)."""
        lat, lon, _ = self.frame.to_geodetic(s.position())
        C_nL = self.frame.C_nL(float(lat), float(lon))
        C_nb = C_nL @ s.attitude().matrix()
        J = np.zeros((15, 15))
        J[0:3, 3:6] = C_nb  # pos
        J[3:6, 6:9] = C_nL  # vel
        J[6:9, 0:3] = C_nb  # att
        J[9:15, 9:15] = np.eye(6)
        return J

    def _layout_to_gtsam_cov(self, P15: FloatArray, s: gtsam.NavState) -> FloatArray:
        J = self._J_gtsam_to_layout(s)
        Ji = np.linalg.inv(J)
        return symmetrise(Ji @ np.asarray(P15, float) @ Ji.T)

    # --------------------------------------------------------------------------------------------- helpers
    def _update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        for i in range(graph.size()):
            self._graph.add(graph.at(i))
        self._isam.update(graph, values)

    def _params_at(self, r_L: FloatArray) -> gtsam.PreintegrationCombinedParams:
        """Preintegration parameters of an IMU factor whose first node is at ``r_L`` (m, L): the IMU noise, the
        plumb-line gravity there, ``g_L(r_L)`` (a vector in L, not only down), and the Earth rate ``omega_ie_L`` as
        GTSAM's Coriolis vector. Both enter the factor in L through the first node's state (GTSAM's ``correctPIM``
        with its Jacobians w.r.t. that node's rotation and velocity), not as body-frame terms in the samples."""
        n = self.noise
        p = gtsam.PreintegrationCombinedParams(np.asarray(self.frame.gravity_L(r_L), float))
        p.setAccelerometerCovariance(np.eye(3) * n.accel_noise**2)
        p.setGyroscopeCovariance(np.eye(3) * n.gyro_noise**2)
        p.setIntegrationCovariance(np.eye(3) * self._integration_sigma**2)
        p.setBiasAccCovariance(np.eye(3) * max(n.accel_bias_rw, _RW_FLOOR) ** 2)
        p.setBiasOmegaCovariance(np.eye(3) * max(n.gyro_bias_rw, _RW_FLOOR) ** 2)
        p.setOmegaCoriolis(np.asarray(self._w_ie_L, float))
        return p

    def _pim_for(self, node: _Node) -> gtsam.PreintegratedCombinedMeasurements:
        """An empty preintegration from ``node`` (its position's gravity, its bias)."""
        return gtsam.PreintegratedCombinedMeasurements(self._params_at(node.state.position()), node.bias)

    def _new_pim(self) -> gtsam.PreintegratedCombinedMeasurements:
        return self._pim_for(self._node)

    def _integrate(self, pim, node: _Node, t_end: float, dt: float, w: FloatArray, f: FloatArray, comp: dict) -> None:
        """Preintegrate one sample compensated to the Earth-fixed frame L (dynamics ``dC_Lb = C_Lb [omega_Lb x]``,
        ``dv_L = C_Lb f + g_L(r) - 2 omega_ie x v_L``) beyond what the factor itself takes out at its first node
        ``i`` (:meth:`_params_at`: ``g_L(r_i)``, ``R_i^T omega_ie_L`` in node-i body axes, ``2 omega_ie_L x v_i``):
        ``omega' = omega - (C_bL omega_ie_L - dR_i^T R_i^T omega_ie_L)`` (``dR_i`` the rotation preintegrated so
        far) and ``f' = f + C_bL (g_L(r) - g_L(r_i) - 2 omega_ie_L x (v_L - v_i))``, with ``r, v_L, C_bL``
        predicted and refreshed every ``gravity_update_s``. These residuals vanish on a straight leg, so the
        attitude they are resolved with no longer matters to first order.

        gtsam integrates each sample as constant body rate and specific force, rotating the velocity increment by
        the attitude at the start of the sample. The samples are mean rates over the interval, so the increments
        (bias-corrected with the node's bias, which gtsam removes again) are first given the same corrections as
        the strapdown's: coning ``dtheta + dtheta_prev x dtheta / 12`` and rotation + sculling
        ``dv + dtheta x dv / 2 + (dtheta_prev x dv + dv_prev x dtheta) / 12`` (Savage 1998). On a manoeuvring
        flight with 6 deg/s turns (error-free IMU, 600 s, keyframes) this takes the graph from 30 m to 2.4 m."""
        if "g_i" not in comp:  # the factor's own terms (_params_at): gravity at the node, its Earth rate, Coriolis
            comp["g_i"] = self.frame.gravity_L(node.state.position())
            comp["w_i"] = node.state.attitude().matrix().T @ self._w_ie_L
        if t_end - comp["t"] >= self.gravity_update_s:
            pred = pim.predict(node.state, node.bias)
            C_bL = pred.attitude().matrix().T
            acc_L = (
                self.frame.gravity_L(pred.position())
                - comp["g_i"]
                - 2.0 * _cross(self._w_ie_L, pred.velocity() - node.state.velocity())
            )
            comp["df_b"] = C_bL @ acc_L
            comp["dw_b"] = -(C_bL @ self._w_ie_L - pim.deltaRij().matrix().T @ comp["w_i"])
            comp["t"] = t_end
        b_g, b_a = node.bias.gyroscope(), node.bias.accelerometer()
        dth = (w + comp["dw_b"] - b_g) * dt
        dv = (f + comp["df_b"] - b_a) * dt
        dth_c = dth.copy()
        dv_c = dv + 0.5 * _cross(dth, dv)
        prev = comp.get("prev")
        if prev is not None:
            dth_c += _cross(prev[0], dth) / 12.0
            dv_c += (_cross(prev[0], dv) + _cross(prev[1], dth)) / 12.0
        comp["prev"] = (dth, dv)
        pim.integrateMeasurement(dv_c / dt + b_a, dth_c / dt + b_g, dt)

    def _node_covariance(self, k: int) -> FloatArray:
        """Joint marginal of node k in GTSAM order [xi_R, xi_t, v, b_a, b_g] (stored) and in LAYOUT_15 (returned)."""
        jm = self._isam.jointMarginalCovariance([X(k), V(k), B(k)]).fullMatrix()
        self._P_node_g = symmetrise(jm)
        est = self._isam.calculateEstimate()
        state = gtsam.NavState(est.atPose3(X(k)), est.atVector(V(k)))
        J = self._J_gtsam_to_layout(state)
        return symmetrise(J @ jm @ J.T)

    def _predict_cov_g(self, pim, pred: gtsam.NavState) -> FloatArray:
        """Covariance (GTSAM order) of a new node at the end of ``pim``: the IMU factor linearised at
        (last node, prediction), whitened ``A_old dx_old + A_new dx_new = b``, so
        ``P_new = A_new^-1 (A_old P_old A_old^T + I) A_new^-T``."""
        k0, k1 = self._k, self._k + 1
        fac = gtsam.CombinedImuFactor(X(k0), V(k0), X(k1), V(k1), B(k0), B(k1), pim)
        vals = gtsam.Values()
        vals.insert(X(k0), self._node.state.pose())
        vals.insert(V(k0), self._node.state.velocity())
        vals.insert(B(k0), self._node.bias)
        vals.insert(X(k1), pred.pose())
        vals.insert(V(k1), pred.velocity())
        vals.insert(B(k1), self._node.bias)
        A, _ = fac.linearize(vals).jacobian()  # columns: X0 6, V0 3, X1 6, V1 3, B0 6, B1 6
        A_old = np.hstack([A[:, 0:9], A[:, 18:24]])
        A_new = np.hstack([A[:, 9:18], A[:, 24:30]])
        Ai = np.linalg.inv(A_new)
        return symmetrise(Ai @ (A_old @ self._P_node_g @ A_old.T + np.eye(A.shape[0])) @ Ai.T)

    # ------------------------------------------------------------------------------------------ Fuser API
    def propagate(self, imu: ImuBatch) -> None:
        """Preintegrate IMU samples (rates, body FRD) after the current time; samples at or before it are skipped."""
        if len(imu) == 0:
            return
        if not (np.all(np.isfinite(imu.gyro_b)) and np.all(np.isfinite(imu.accel_b)) and np.all(np.isfinite(imu.t))):
            raise InputError("GraphFuser.propagate: IMU batch holds non-finite values")
        if np.any(np.diff(imu.t) <= 0):
            k = int(np.argmax(np.diff(imu.t) <= 0))
            raise InputError(f"GraphFuser.propagate: IMU time not increasing at sample {k + 1}: t={imu.t[k + 1]!r} s")
        check_time(float(imu.t[-1]), self._t, "GraphFuser.propagate")
        comp = self._comp
        for k in range(len(imu)):
            t = float(imu.t[k])
            if t <= self._t + _TIME_TOL:
                continue
            dt = t - self._t
            w = imu.gyro_b[k]
            f = imu.accel_b[k]
            self._integrate(self._pim, self._node, t, dt, w, f, comp)
            self._buf_t.append(t)
            self._buf_dt.append(dt)
            self._buf_w.append(w)
            self._buf_f.append(f)
            self._t = t
            if self.max_preintegration_rad is not None and (
                np.linalg.norm(gtsam.Rot3.Logmap(self._pim.deltaRij())) > self.max_preintegration_rad
                or t - self._node.t >= _KEYFRAME_MAX_S
            ):
                self._comp = comp
                self._add_node(t, None, None, None)  # a keyframe: keeps each preintegrated rotation small
                comp = self._comp
        self._comp = comp
        self._pred_cov_cache = None

    def correct(self, fix: Fix, *, height_m: float | None = None, height_sigma_m: float | None = None) -> Innovation:
        """Add a node at ``fix.t`` with the IMU factor since the last node and, if the fix passes the NIS gate, a
        robust position factor; returns the innovation (rejected ones say why). Optional ``height_m`` (ellipsoidal,
        m) with ``height_sigma_m`` constrains the vertical. Fault detection, exclusion and recovery as in the UKF
        (:class:`integrity.FaultMonitor`); a recovery (``extra["recovery"]``) gives the new node, instead of the IMU
        factor from the last one, a prior at the IMU prediction with its navigation covariance inflated until the
        fix sits on the gate (``extra["inflation"]``): the graph lets go of the track it lost, as the UKF widens its
        covariance."""
        if height_m is None and self.altitude_hold is not None:  # the held height as a pseudo-measurement
            height_m, height_sigma_m = self.altitude_hold, self.altitude_hold_sigma_m
        problem = fix_problem(fix)
        if not problem and fix.t > self._t + 1e-6:
            problem = f"fix time {fix.t:.6f} s is after the last IMU time {self._t:.6f} s"
        at_keyframe = not problem and self._keyframe and abs(fix.t - self._node.t) <= _TIME_TOL
        if not problem and not at_keyframe and fix.t <= self._node.t + _TIME_TOL:
            problem = f"fix time {fix.t:.6f} s is not after the last graph node {self._node.t:.6f} s"
        if problem:
            inn = rejected(fix, problem)
        else:
            if at_keyframe:
                inn = self._fix_at_keyframe(fix, height_m, height_sigma_m)
            else:
                inn = self._add_node(float(fix.t), fix, height_m, height_sigma_m)
        self.innovations.append(inn)
        return inn

    def add_node(self, t: float) -> None:
        """Add a node without a fix at ``t`` (s; after the last node, not after the last IMU time): a keyframe, so
        that :meth:`node_trajectory` also covers times without fixes (as GTSAM's KITTI example does)."""
        if not (self._node.t + _TIME_TOL < t <= self._t + 1e-6):
            raise InputError(f"GraphFuser.add_node: t={t!r} s must lie in ({self._node.t!r}, {self._t!r}] s")
        self._add_node(float(t), None, None, None)

    def _add_node(self, t_new: float, fix: Fix | None, height_m: float | None, height_sigma_m: float | None):
        # split the buffered samples at the node time (a straddling sample is cut in two)
        rest: list[tuple[float, float, np.ndarray, np.ndarray]] = []
        if not self._buf_t or self._buf_t[-1] <= t_new + _TIME_TOL:
            # nothing to split: the running preintegration holds exactly these samples, integrated in this order
            # from the same node, bias and fresh compensation state as the loop below would (bit for bit)
            pim_a, buffered = self._pim, []
        else:
            pim_a, buffered = (
                self._new_pim(),
                list(zip(self._buf_t, self._buf_dt, self._buf_w, self._buf_f, strict=True)),
            )
        comp = {"t": -np.inf, "df_b": np.zeros(3), "dw_b": np.zeros(3)}
        t_prev = self._node.t
        for t, dt, w, f in buffered:
            if t <= t_new + _TIME_TOL:
                self._integrate(pim_a, self._node, t, dt, w, f, comp)
            elif t_prev < t_new - _TIME_TOL:
                self._integrate(pim_a, self._node, t_new, t_new - t_prev, w, f, comp)
                rest.append((t, t - t_new, w, f))
            else:
                rest.append((t, dt, w, f))
            t_prev = t
        k0, k1 = self._k, self._k + 1
        pred = pim_a.predict(self._node.state, self._node.bias)
        g = gtsam.NonlinearFactorGraph()
        vals = gtsam.Values()
        vals.insert(X(k1), pred.pose())
        vals.insert(V(k1), pred.velocity())
        vals.insert(B(k1), self._node.bias)
        inn = verdict = None
        imu_factor = gtsam.CombinedImuFactor(X(k0), V(k0), X(k1), V(k1), B(k0), B(k1), pim_a)
        if fix is not None:
            P_pred_g = self._predict_cov_g(pim_a, pred)
            Jp = self._J_gtsam_to_layout(pred)
            P_pred = symmetrise(Jp @ P_pred_g @ Jp.T)
            verdict, r, S, v = self._assess(fix, pred, P_pred, t_new, k1)
            if verdict.action == "recover" and v > self.gate.threshold:
                # cut the track the graph lost: the new node's prior is the IMU prediction with its navigation part
                # (rotation, translation, velocity in gtsam's order) inflated until the fix sits on the gate
                forced = v / self.gate.threshold
                Pg = P_pred_g.copy()
                Pg[0:9, :] *= np.sqrt(forced)
                Pg[:, 0:9] *= np.sqrt(forced)
                g.add(self._joint_prior(k1, pred, self._node.bias, Pg))
                P_pred = symmetrise(Jp @ Pg @ Jp.T)
                r = residual_ne(fix, self._from_gtsam(t_new, pred))
                S = P_pred[0:2, 0:2] + np.asarray(fix.cov_ne, float)
                verdict = Verdict("recover", extra={**verdict.extra, "inflation": forced}, group=verdict.group)
                v = nis(r, S)
            else:
                g.add(imu_factor)
            inn = self._fix_innovation(g, k1, pred, t_new, fix, height_m, height_sigma_m, verdict, r, S, v)
        else:
            g.add(imu_factor)
        self._update(g, vals)
        self._k = k1
        self._node_times.append(t_new)
        self._keyframe = fix is None
        self._refresh(rest, accepted=inn is not None and inn.accepted)
        if inn is not None and inn.accepted:
            self.monitor.accepted(
                t_new, v, P_pred[0:2, 0:2], self._P_node[0:2, 0:2], recovery=verdict.action == "recover"
            )
        return inn

    def _joint_prior(self, k: int, state: gtsam.NavState, bias: gtsam.imuBias.ConstantBias, P_g: FloatArray):
        """A joint Gaussian prior on ``(X_k, V_k, B_k)`` with covariance ``P_g`` (gtsam order) at ``state, bias``:
        the whitened linear factor ``||U dx||^2``, ``U^T U = P_g^-1``, held at those values."""
        values = gtsam.Values()
        values.insert(X(k), state.pose())
        values.insert(V(k), state.velocity())
        values.insert(B(k), bias)
        U = _sqrt_information(P_g)
        lin = gtsam.JacobianFactor(X(k), U[:, 0:6], V(k), U[:, 6:9], B(k), U[:, 9:15], np.zeros(15),
                                   gtsam.noiseModel.Unit.Create(15))  # fmt: skip
        return gtsam.LinearContainerFactor(lin, values)

    def _assess(
        self, fix: Fix, pred: gtsam.NavState, P_pred: FloatArray, t: float, k: int
    ) -> tuple[Verdict, FloatArray, FloatArray, float]:
        """The fault monitor's verdict on ``fix`` against the node ``k`` prediction ``pred`` (LAYOUT_15 covariance
        ``P_pred``) and the residual, innovation covariance and 2-dof NIS it rests on."""
        r = residual_ne(fix, self._from_gtsam(t, pred))
        cov_fix = np.asarray(fix.cov_ne, float)
        S = P_pred[0:2, 0:2] + cov_fix
        v = nis(r, S)
        return self.monitor.assess(t, r, S, cov_fix, P_pred[0:2, 0:2], tag=k), r, S, v

    def _fix_innovation(
        self,
        g: gtsam.NonlinearFactorGraph,
        k: int,
        pred: gtsam.NavState,
        t: float,
        fix: Fix,
        height_m: float | None,
        height_sigma_m: float | None,
        verdict: Verdict,
        r: FloatArray,
        S: FloatArray,
        v: float,
    ) -> Innovation:
        """Add the robust position factor of an accepted (or recovering) ``fix`` on node ``k`` to ``g``; the
        :class:`Innovation` either way (an excluded fix says which test excluded it)."""
        if verdict.action == "reject":
            return Innovation(float(fix.t), r, S, v, False, verdict.reason, fix.source, verdict.extra)
        nav_pred = self._from_gtsam(t, pred)
        cov_fix = np.asarray(fix.cov_ne, float)
        C_nL = self.frame.C_nL(nav_pred.lat, nav_pred.lon)
        h = float(height_m) if height_m is not None else nav_pred.h
        sv = float(height_sigma_m) if height_sigma_m is not None else self.vertical_sigma_m
        cov_n = np.zeros((3, 3))
        cov_n[:2, :2] = cov_fix
        cov_n[2, 2] = sv**2
        r_L = self.frame.to_L(fix.lat, fix.lon, h)
        gauss = gtsam.noiseModel.Gaussian.Covariance(C_nL.T @ cov_n @ C_nL)
        model = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(self.huber_k), gauss)
        g.add(gtsam.GPSFactor(X(k), np.asarray(r_L, float), model))
        return Innovation(float(fix.t), r, S, v, True, "", fix.source, dict(verdict.extra))

    def _refresh(self, rest: list[tuple[float, float, np.ndarray, np.ndarray]], accepted: bool) -> None:
        """After an update: read the last node from iSAM2 and re-integrate the samples ``rest`` after it."""
        if accepted:
            self._isam.update()  # one more relinearisation step
        est = self._isam.calculateEstimate()
        k1 = self._k
        state = gtsam.NavState(est.atPose3(X(k1)), est.atVector(V(k1)))
        self._node = _Node(self._node_times[-1], state, est.atConstantBias(B(k1)))
        self._P_node = self._node_covariance(k1)
        self._buf_t = [x[0] for x in rest]
        self._buf_dt = [x[1] for x in rest]
        self._buf_w = [x[2] for x in rest]
        self._buf_f = [x[3] for x in rest]
        self._pim = self._new_pim()
        comp = {"t": -np.inf, "df_b": np.zeros(3), "dw_b": np.zeros(3)}
        for t, dt, w, f in rest:
            self._integrate(self._pim, self._node, t, dt, w, f, comp)
        self._comp = comp
        self._pred_cov_cache = None

    def _fix_at_keyframe(self, fix: Fix, height_m: float | None, height_sigma_m: float | None) -> Innovation:
        """A fix stamped at the last node when that node is a keyframe (no fix yet): its factor goes on that node."""
        g = gtsam.NonlinearFactorGraph()
        P_prior = self._P_node
        verdict, r, S, v = self._assess(fix, self._node.state, P_prior, self._node.t, self._k)
        # a recovery here is applied as an acceptance (the node already hangs on its IMU factor)
        inn = self._fix_innovation(g, self._k, self._node.state, self._node.t, fix, height_m, height_sigma_m,
                                   verdict, r, S, v)  # fmt: skip
        if inn.accepted:
            self._update(g, gtsam.Values())
            self._keyframe = False
            rest = list(zip(self._buf_t, self._buf_dt, self._buf_w, self._buf_f, strict=True))
            self._refresh(rest, accepted=True)
            self.monitor.accepted(self._node.t, v, P_prior[0:2, 0:2], self._P_node[0:2, 0:2],
                                  recovery=verdict.action == "recover")  # fmt: skip
        return inn

    def estimate(self) -> NavEstimate:
        """The current state (``pim.predict`` from the last node) with its LAYOUT_15 covariance."""
        pred = self._pim.predict(self._node.state, self._node.bias)
        nav = self._from_gtsam(self._t, pred)
        if self._t <= self._node.t + _TIME_TOL:
            P = self._P_node
        else:
            if self._pred_cov_cache is None or self._pred_cov_cache[0] != self._t:
                self._pred_cov_cache = (self._t, self._predicted_covariance(pred))
            P = self._pred_cov_cache[1]
        m = self.monitor
        return NavEstimate(nav, P, LAYOUT_15, m.hpl(P[0:2, 0:2]), m.integrity_risk)

    def _predicted_covariance(self, pred: gtsam.NavState) -> FloatArray:
        J = self._J_gtsam_to_layout(pred)
        return symmetrise(J @ self._predict_cov_g(self._pim, pred) @ J.T)

    @property
    def bias(self) -> tuple[FloatArray, FloatArray]:
        """Current accelerometer (m/s^2) and gyro (rad/s) bias estimates, body FRD."""
        return np.asarray(self._node.bias.accelerometer()), np.asarray(self._node.bias.gyroscope())

    # ---------------------------------------------------------------------------------------- smoothing
    def node_trajectory(self, smoothed: bool = False) -> NavTrajectory:
        """States at the node times (the initial time and every fix time): the iSAM2 estimate, or with
        ``smoothed=True`` a batch Levenberg-Marquardt solution of the whole graph (QR or Cholesky as configured)."""
        values = self._isam.calculateEstimate()
        if smoothed:
            lm = gtsam.LevenbergMarquardtParams()
            lm.setLinearSolverType("MULTIFRONTAL_QR" if self._factorization == "QR" else "MULTIFRONTAL_CHOLESKY")
            values = gtsam.LevenbergMarquardtOptimizer(self._graph, values, lm).optimize()
        navs = [
            self._from_gtsam(t, gtsam.NavState(values.atPose3(X(k)), values.atVector(V(k))))
            for k, t in enumerate(self._node_times)
        ]
        return NavTrajectory(
            np.array([n.t for n in navs]),
            np.array([n.lat for n in navs]),
            np.array([n.lon for n in navs]),
            np.array([n.h for n in navs]),
            np.array([n.v_n for n in navs]),
            np.array([n.q_nb for n in navs]),
        )

    def smoothed_track(self, imu: ImuBatch, t_out: FloatArray) -> tuple[NavTrajectory, FloatArray]:
        """Offline: the batch Levenberg-Marquardt solution of the whole graph (as ``node_trajectory(smoothed=True)``)
        reported at the times ``t_out`` (s, increasing, within the first node and the last IMU time), with its
        horizontal covariance ``cov_ne`` (n, 2, 2) north/east m^2.

        Nodes are where :meth:`correct` received a fix (and where :meth:`add_node` was called), so in a study they
        are seconds to minutes apart. Between two nodes the track is re-integrated from the smoothed state and bias
        of the earlier node with the IMU samples ``imu`` (those fed to :meth:`propagate`, body FRD, compensated to L
        as in the online graph) and the mismatch with the smoothed later node (position and velocity in L) is spread
        linearly in time, so the track follows the manoeuvres the IMU saw and passes through every node; attitude is
        the re-integrated one. If IMU time remains after the last node, a closing node is added at the last IMU
        time first (:meth:`add_node`; call this once the run is over).

        Covariance: ``gtsam.Marginals`` of the batch solution at every node (the pose's translation block, body
        axes, rotated to NED; iSAM2's marginals, which are smoothed too, if Cholesky finds the system indeterminate),
        linearly interpolated in time between nodes: between sparse nodes this understates the smoother's
        uncertainty midway, where it is largest."""
        t_out = np.asarray(t_out, dtype=float).reshape(-1)
        if self._t > self._node.t + _TIME_TOL:
            self.add_node(self._t)
        times = np.asarray(self._node_times, dtype=float)
        if len(t_out) and (np.any(np.diff(t_out) < 0) or t_out[0] < times[0] - 1e-6 or t_out[-1] > times[-1] + 1e-6):
            raise InputError(
                f"GraphFuser.smoothed_track: output times must increase within [{times[0]!r}, {times[-1]!r}] s"
            )
        values = self._isam.calculateEstimate()
        lm = gtsam.LevenbergMarquardtParams()
        lm.setLinearSolverType("MULTIFRONTAL_QR" if self._factorization == "QR" else "MULTIFRONTAL_CHOLESKY")
        values = gtsam.LevenbergMarquardtOptimizer(self._graph, values, lm).optimize()
        nodes = [
            _Node(float(t), gtsam.NavState(values.atPose3(X(k)), values.atVector(V(k))), values.atConstantBias(B(k)))
            for k, t in enumerate(times)
        ]
        cov_nodes = np.empty((len(nodes), 2, 2))

        def node_covariances(marginals: Any) -> None:
            for k, node in enumerate(nodes):
                C_nb = self._J_gtsam_to_layout(node.state)[0:3, 3:6]
                S_t = np.asarray(marginals.marginalCovariance(X(k)))[3:6, 3:6]  # translation, body axes
                cov_nodes[k] = symmetrise(C_nb @ S_t @ C_nb.T)[0:2, 0:2]

        try:  # gtsam's Python Marginals factorises by Cholesky only (and may fail only when a marginal is asked)
            node_covariances(gtsam.Marginals(self._graph, values))
        except RuntimeError:  # indeterminate under Cholesky: iSAM2's own (QR) marginals at its linearisation point
            node_covariances(self._isam)
        cov = np.stack([np.interp(t_out, times, cov_nodes[:, a, b]) for a in range(2) for b in range(2)], -1).reshape(
            -1, 2, 2
        )

        t_imu = np.asarray(imu.t, dtype=float)
        starts = np.r_[-np.inf, t_imu[:-1]]
        pos = np.empty((len(t_out), 3))
        vel = np.empty((len(t_out), 3))
        rot: list[FloatArray] = [np.eye(3)] * len(t_out)
        for k in range(len(nodes) - 1):
            a, b = nodes[k].t, nodes[k + 1].t
            q = np.flatnonzero(
                (t_out >= a - _TIME_TOL) & (t_out <= b + _TIME_TOL)
                if k == 0
                else (t_out > a + _TIME_TOL) & (t_out <= b + _TIME_TOL)
            )
            idx = np.flatnonzero((t_imu > a + _TIME_TOL) & (starts < b - _TIME_TOL))
            ends = np.minimum(t_imu[idx], b)
            if len(idx) == 0 or ends[-1] < b - 1e-6:
                raise InputError(f"GraphFuser.smoothed_track: the IMU samples do not cover ({a!r}, {b!r}] s")
            # the segment ends bracketing each wanted time (and the node b itself) are predicted
            seg = np.searchsorted(ends, t_out[q] - _TIME_TOL)
            need = set(seg.tolist()) | set((seg - 1).tolist()) | {len(idx) - 1}
            pim = self._pim_for(nodes[k])
            comp = {"t": -np.inf, "df_b": np.zeros(3), "dw_b": np.zeros(3)}
            pred: dict[int, gtsam.NavState] = {-1: nodes[k].state}
            t_prev = a
            for j, i in enumerate(idx):
                self._integrate(
                    pim, nodes[k], float(ends[j]), float(ends[j] - t_prev), imu.gyro_b[i], imu.accel_b[i], comp
                )
                t_prev = float(ends[j])
                if j in need:
                    pred[j] = pim.predict(nodes[k].state, nodes[k].bias)
            end = pred[len(idx) - 1]
            dp = nodes[k + 1].state.position() - end.position()
            dv = nodes[k + 1].state.velocity() - end.velocity()
            seg_t = np.r_[a, ends]
            for m, jj in zip(q, seg, strict=True):
                t = float(t_out[m])
                j1 = min(int(jj), len(idx) - 1)
                j0 = j1 - 1
                t0, t1 = seg_t[j0 + 1], seg_t[j1 + 1]
                w = 0.0 if t1 <= t0 else min(max((t - t0) / (t1 - t0), 0.0), 1.0)
                s0, s1 = pred[j0], pred[j1]
                frac = (t - a) / (b - a)
                pos[m] = (1 - w) * s0.position() + w * s1.position() + frac * dp
                vel[m] = (1 - w) * s0.velocity() + w * s1.velocity() + frac * dv
                rot[m] = (s1 if w >= 0.5 else s0).attitude().matrix()
        if len(nodes) == 1:
            for m in range(len(t_out)):
                pos[m], vel[m], rot[m] = (
                    nodes[0].state.position(),
                    nodes[0].state.velocity(),
                    nodes[0].state.attitude().matrix(),
                )
        navs = [
            self._from_gtsam(float(t), gtsam.NavState(gtsam.Rot3(rot[m]), pos[m], vel[m])) for m, t in enumerate(t_out)
        ]
        traj = NavTrajectory(
            t_out.copy(),
            np.array([n.lat for n in navs]),
            np.array([n.lon for n in navs]),
            np.array([n.h for n in navs]),
            np.array([n.v_n for n in navs]).reshape(-1, 3),
            np.array([n.q_nb for n in navs]).reshape(-1, 4),
        )
        return traj, cov


# ------------------------------------------------------------------------------------------------ peer run
def kitti_example_peer(gps_skip: int = 10, factorization: str = "QR") -> dict[str, np.ndarray]:
    """Run GTSAM's own ``examples/IMUKittiExampleGPS.py`` (from the installed wheel, not copied) with the iSAM2
    factorisation switched to ``factorization`` and return its smoothed positions at the GPS epochs in its
    z-up frame: ``{"t": (N,), "xyz": (N,3), "gps_xyz": (N,3)}``. Its printing is swallowed."""
    path = Path(gtsam.__file__).resolve().parent / "examples" / "IMUKittiExampleGPS.py"
    if not path.is_file():
        raise InputError(f"{path}: GTSAM's KITTI example is not in the installed gtsam package")
    spec = importlib.util.spec_from_file_location("_gtsam_kitti_example", path)
    mod = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    spec.loader.exec_module(mod)

    class _Params(gtsam.ISAM2Params):
        def setFactorization(self, _name: str) -> None:  # noqa: N802 (GTSAM's name)
            super().setFactorization(factorization)

    class _Gtsam:  # the example's view of the gtsam module, with the factorisation forced
        def __getattr__(self, name: str):
            return _Params if name == "ISAM2Params" else getattr(gtsam, name)

    mod.gtsam = _Gtsam()
    with contextlib.redirect_stdout(io.StringIO()):
        calib, imu, gps = mod.loadKittiData()
        noise_gps = gtsam.noiseModel.Diagonal.Precisions(np.asarray([0, 0, 0] + [1.0 / 0.07] * 3))
        sx = gtsam.noiseModel.Diagonal.Precisions(np.asarray([0, 0, 0, 1, 1, 1]))
        sv = gtsam.noiseModel.Diagonal.Sigmas(np.ones(3) * 1000.0)
        sb = gtsam.noiseModel.Diagonal.Sigmas(np.asarray([0.1] * 3 + [5.00e-05] * 3))
        isam = mod.optimize(gps, imu, sx, sv, sb, noise_gps, calib, 1, gps_skip)
        res = isam.calculateEstimate()
    idx = range(1, len(gps))
    return {
        "t": np.array([gps[i].time for i in idx]),
        "xyz": np.array([res.atPose3(X(i)).translation() for i in idx]),
        "gps_xyz": np.array([gps[i].position for i in idx]),
    }
