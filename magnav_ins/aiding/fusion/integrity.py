"""Integrity of the fusers: fault detection and exclusion (FDE) over a window of fixes, a recovery that needs
mutually consistent evidence, and the horizontal protection level (HPL). Shared by the UKF and the factor graph;
no filterpy, no gtsam here: the fusers hand in residuals and 2x2 covariances (north/east, m, m^2).

Tests on each fix (:meth:`FaultMonitor.assess`), in this order:

1. **Gate** (one fix): the NIS ``y^T S^-1 y`` of the fix against the fuser's prediction above the chi-square
   quantile ``gate_probability`` of its degrees of freedom (2, or 3 with a height) -> excluded, reason
   ``"NIS ... above gate ..."``.
2. **Window** (several fixes): the innovations of a consistent filter are white and their NIS are chi-square
   (Bar-Shalom, Li & Kirubarajan 2001, sec. 5.4.2), so the sum of the 2-dof north/east NIS of the last ``window``
   accepted fixes (within ``window_s``) and this one is chi-square with ``2 (n + 1)`` dof; above its
   ``window_probability`` quantile the fix is excluded, reason ``"window NIS ... over n fixes above ..."``. It
   catches what a single gate lets through: a run of fixes each a little off (a matcher pulled by a map-error
   patch, a filter that has been over-confident for a while).
3. **Recovery** (safe ``reset_after``): a fix excluded by the gate or the window test is either a fault or evidence
   that the filter has lost track. The excluded fixes since the last accepted one are kept (at most
   ``recovery_window``); when at
   least ``reset_after`` of them, this one included, are *mutually consistent* -- their residuals against the
   INS, ``r_i`` at ``t_i``, agree within their covariances ``R_i`` plus the INS error growth since,
   ``Q_i = P_ne(now) - P_ne(t_i)``: ``sum_i (r_i - r_bar)^T (R_i + Q_i)^-1 (r_i - r_bar)`` inside the
   ``window_probability`` quantile of a chi-square with ``2 (m - 1)`` dof, ``r_bar`` their weighted mean -- the
   filter, not the fixes, is taken to be wrong: verdict ``"recover"`` (the fuser widens its own covariance and
   applies the fix). Faults that are not mutually consistent (a matcher's false peaks at independent places,
   displaced in random directions) never reach that, however many arrive; the old rule (any ``reset_after``
   consecutive rejections re-accepted the next fix, with whatever error) accepted them. The window test's
   exclusions count too: its window slides only on an accepted fix, so after a run of accepted bad fixes every
   later fix, the right ones included, failed it (SITL run 47 played back: three fixes 160-380 m off accepted,
   the filter 200 m off, then six exclusions, the HPL at 1.5 km; with them counted, three exclusions and a bridge
   RMS of 92.5 m instead of 117.9 m; the other eight recordings played back within 3 m).

Every excluded fix says so in its :class:`Innovation` (``accepted=False``, the reason, ``extra["fault"] = 1``,
the test's statistic and threshold); an accepted one carries ``extra["window_nis"]``; a recovery
``extra["recovery"]`` (the number of consistent fixes it rests on).

Horizontal protection level (:meth:`FaultMonitor.hpl`, m), at ``integrity_risk`` per epoch:

``HPL = max(K sigma_max + m_f, d)`` with

* ``K = sqrt(-2 ln integrity_risk)`` and ``sigma_max^2`` the largest eigenvalue of the 2x2 horizontal covariance:
  for a Gaussian error ``P(|e| > K sigma_max) <= exp(-K^2 / 2) = integrity_risk`` (equality for a circular one).
* ``m_f`` the fault-detection margin: the error that faults the tests could not see may have caused. A bias ``b``
  on one fix passes the gate while ``b^T S^-1 b <= T_gate`` and moves the estimate by ``K_pos b``, at most
  ``sqrt(T_gate lambda_max(P- - P+))`` (the slope bound of RAIM, Brown & Chin 1998, applied to the Kalman
  update: ``K_pos S K_pos^T = P- - P+``, the fix's covariance reduction). One fault at a time (RAIM's
  single-fault hypothesis; several faults within a window are the window test's).

  The inertial fusers (:class:`common.InertialCore`: UKF, free inertial) carry the whole induced error: the
  fault's state error ``dx = K b`` is bounded by the *fault matrix* ``M = T_gate (P- - P+)`` (full state:
  ``(u^T K b)^2 <= T_gate u^T K S K^T u`` for every direction ``u``), which then evolves as the error itself does
  -- through the INS error transition without the process noise, ``M <- Phi M Phi^T`` (a velocity or tilt error
  the faulty fix left grows into position; the process noise is the fault-free term's), and through each later
  update, ``M <- A M A^T`` with ``A = I - K H`` (the part of an old error an update leaves). Any recent fix may
  be the faulty one: each of the last :data:`FAULT_MEMORY` accepted fixes keeps its own matrix, older ones are
  folded into one that bounds each of them (:func:`common_bound`, a Loewner bound; their sum, used before, was
  1.4-2.7 times the largest single fault on SITL run 29's GNSS-aided then map-aided flight, the Loewner bound
  within 1.4 times and mostly equal), and ``m_f`` is the largest ``sqrt(lambda_max(M_NE))``
  (:func:`fault_update`, :func:`fault_margin`; passed to :meth:`FaultMonitor.hpl` as ``margin_m``). Keeping only
  the larger of the old and the new fault at each fix is not enough: the one dropped may grow more later (its
  velocity part). So the
  margin comes from the information the fixes actually brought, not from the whole covariance: before this (still
  the factor graph's rule, :meth:`FaultMonitor.margin`) the margin at a fix was scaled with the filter's horizontal
  sigma between fixes, process noise included, and on the SITL flights the HPL reached 7.6-10 sigmas.
* ``d`` the doubt of unresolved exclusions: while fixes excluded since the last accepted one are unexplained, the
  filter may be the one that is wrong (:func:`exclusion_doubt`). For each such fix (residual ``r`` against the
  filter, covariance ``R``; the filter's horizontal covariance ``P`` now), the filter is taken to be
  over-confident by the least factor ``s >= 1`` that makes the fix consistent: ``r^T (s P + R)^-1 r`` at the
  gate's threshold (``s = 1`` for a fix inside the gate, excluded by the window test). If that fix were right, the
  filter's error would be the Kalman correction the fix asks for, ``G r`` with ``G = s P (s P + R)^-1``, give or
  take the combined covariance ``(P_s^-1 + R^-1)^-1``: ``d = max_i |G_i r_i| + K sqrt(lambda_max((P_s^-1 +
  R_i^-1)^-1))``. A precise fix far off (``R << s P``) asks for nearly its whole residual, ``d ~ |r| + K
  sigma_R``, as when the filter has lost track; a direction in which the fix is vague against the filter (the
  likelihood matcher's edge fix: cross-track position, 0.5-10 km along the track) or a fix that only the window
  test excluded asks for little. Before, the doubt was that worst case in every direction with a tenth of the
  filter's information or more,
  ``|r| + K sqrt(lambda_max(R + P))``: on SITL run 38 (a 10 km edge fix) the HPL was 51 km for 10 s and the
  autopilot landed on "EKF variance"; on run 40, played back, three fixes the window test excluded (each inside
  the gate, 160-500 m sigma along the track) left doubts of 283-772 m, where this rule gives 194-223 m.
  The next accepted fix resolves them (they were faults); a recovery resolves them the other way.
  A lone exclusion that only a filter more than :data:`MAX_DOUBT_INFLATION` (25) times over-confident in variance
  could explain (its errors 21 sigmas out) is taken for the matcher's fault and leaves no doubt, while the window
  holds accepted fixes, no other unresolved exclusion agrees with it and fewer than ``reset_after`` are unresolved:
  on SITL run 48 two false peaks, 0.8 and 4.7 km off with 50-400 m sigmas, against a filter confirmed 30 s before
  (sigma 36 m, error 25 m) raised the HPL to 0.98 and 5.4 km, the bridge went untrusted and ArduCopter landed on
  "EKF variance" (played back: trusted 91.3 -> 99.7 % of the denied outputs). A filter never confirmed by a fix
  (started off, or just recovered) keeps the full doubt of every exclusion.

No peer library (MagNav.jl, pyins, navlie, Stone Soup) provides FDE or protection levels for map-matching fixes;
the construction is that of Kalman-filter integrity monitoring against measurement faults (Joerger & Pervan 2013,
"Kalman filter-based integrity monitoring against sensor faults", J. Guidance, Control, and Dynamics 36(2)):
a detection test, a fault-free term from the covariance, and a margin for what the test can miss.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from ...core.errors import ConfigError
from ...core.types import DEFAULT_INTEGRITY_RISK
from ..gating import ChiSquareGate, chi2_threshold, nis

FloatArray = NDArray[np.float64]

#: default FDE settings (the fusers' constructor defaults; :class:`FaultMonitor`)
DEFAULT_WINDOW = 4
DEFAULT_WINDOW_S = 600.0
DEFAULT_WINDOW_PROBABILITY = 0.999
DEFAULT_RESET_AFTER = 3
DEFAULT_RECOVERY_WINDOW = 6
#: the largest over-confidence (variance factor ``s``; :func:`filter_inflation`) the doubt grants the filter on the
#: word of one excluded fix alone (:meth:`FaultMonitor.doubt`). 25 is a filter whose errors reach 21 of its sigmas at
#: the gate's probability (``sqrt(25 x 18.4)``); the worst seen is 7 (SITL flights, error over HPL at most 0.82 with
#: the HPL at 6-9 sigmas), on the real-data suite the HPL was exceeded at 0-0.3 % of the epochs.
MAX_DOUBT_INFLATION = 25.0


def integrity_factor(integrity_risk: float) -> float:
    """``K = sqrt(-2 ln risk)``: a 2-D Gaussian error exceeds ``K sigma_max`` with probability at most ``risk``."""
    if not (0.0 < integrity_risk < 1.0):
        raise ConfigError(f"integrity_risk must be in (0, 1), got {integrity_risk!r}")
    return math.sqrt(-2.0 * math.log(integrity_risk))


def filter_inflation(r: ArrayLike, R: ArrayLike, P: ArrayLike, gate: float) -> float:
    """The least ``s >= 1`` with ``r^T (s P + R)^-1 r <= gate``: how over-confident the filter (horizontal
    covariance ``P``, m^2) must be for an excluded fix (residual ``r`` m, covariance ``R`` m^2) to be consistent
    with it at the 2-dof NIS threshold ``gate``; 1e12 when no inflation can (the fix is off in a direction ``P``
    does not cover). A quadratic in ``s`` after a generalised eigen-decomposition of ``P`` against ``R``."""
    r = np.asarray(r, float).reshape(2)
    R = _psd(np.asarray(R, float)) + 1e-9 * np.eye(2)
    P = _psd(np.asarray(P, float))
    # P v = lam R v with V^T R V = I: r^T (s P + R)^-1 r = sum_i a_i / (s lam_i + 1), a_i = (v_i^T r)^2, so the
    # least s with that at the gate is the largest root of a quadratic (closed form; the doubt is on every output)
    lam, V = scipy.linalg.eigh(P, R)
    lam = np.maximum(lam, 0.0)
    a1, a2 = (V.T @ r) ** 2
    if not (math.isfinite(gate) and a1 / (lam[0] + 1.0) + a2 / (lam[1] + 1.0) > gate):
        return 1.0
    coeffs = [gate * lam[0] * lam[1], gate * (lam[0] + lam[1]) - a1 * lam[1] - a2 * lam[0], gate - a1 - a2]
    roots = np.roots(np.trim_zeros(coeffs, "f")) if any(coeffs[:2]) else np.array([])
    real = roots.real[np.abs(roots.imag) <= 1e-9 * np.maximum(1.0, np.abs(roots.real))]
    return max(1.0, float(real.max())) if real.size else 1e12


def exclusion_doubt(
    r: ArrayLike, R: ArrayLike, P: ArrayLike, gate: float, k: float, inflation: float | None = None
) -> float:
    """The doubt (m) an excluded fix leaves on the filter's position (module docstring, ``d``): ``r`` its residual
    against the filter (north, east; m), ``R`` its covariance and ``P`` the filter's horizontal covariance (m^2),
    ``gate`` the 2-dof NIS threshold the filter's inflation is solved for, ``k`` the integrity factor. The filter is
    inflated by the least ``s >= 1`` with ``r^T (s P + R)^-1 r <= gate`` (:func:`filter_inflation`); the doubt is
    the correction the fix would make to that filter plus ``k`` sigmas of their combination. ``inflation``: that
    ``s`` when the caller has it already."""
    r = np.asarray(r, float).reshape(2)
    s = filter_inflation(r, R, P, gate) if inflation is None else float(inflation)
    R = _psd(np.asarray(R, float)) + 1e-9 * np.eye(2)
    P = _psd(np.asarray(P, float))
    Ps = s * P
    G = Ps @ np.linalg.inv(Ps + R)
    C = Ps - G @ Ps  # (Ps^-1 + R^-1)^-1, without inverting a singular one
    return float(np.hypot(*(G @ r))) + k * math.sqrt(lambda_max(C))


def lambda_max(P: ArrayLike) -> float:
    """Largest eigenvalue of a symmetric 2x2 matrix (closed form; 0 for a negative or non-finite result)."""
    P = np.asarray(P, dtype=float)
    a, b, c = P[0, 0], 0.5 * (P[0, 1] + P[1, 0]), P[1, 1]
    lam = 0.5 * (a + c) + math.sqrt(max(0.25 * (a - c) ** 2 + b * b, 0.0))
    return lam if math.isfinite(lam) and lam > 0.0 else 0.0


def _psd(P: FloatArray) -> FloatArray:
    """The nearest positive semi-definite matrix of a symmetric 2x2 (eigenvalues clipped at 0)."""
    w, V = np.linalg.eigh(0.5 * (P + P.T))
    return (V * np.maximum(w, 0.0)) @ V.T


def gain_transfer(P_prior: ArrayLike, P_post: ArrayLike) -> FloatArray:
    """``A = P+ (P-)^-1`` (n, n): for a Kalman update, ``I - K H`` (what an update leaves of an earlier state
    error), from the covariances before and after it. Solved on the correlation scale (the states span m^2 to
    rad^2/s^2); states of zero variance are left as they are; identity if singular."""
    Pm = np.asarray(P_prior, float)
    Pp = np.asarray(P_post, float)
    d = np.sqrt(np.clip(np.diag(Pm), 0.0, None))
    live = d > 0.0
    A = np.eye(len(d))
    if not live.any():
        return A
    dl = d[live]
    Cm = Pm[np.ix_(live, live)] / np.outer(dl, dl)
    Cp = Pp[np.ix_(live, live)] / np.outer(dl, dl)
    try:
        An = np.linalg.solve(Cm.T, Cp.T).T  # Cp Cm^-1 (Cm symmetric)
    except np.linalg.LinAlgError:
        return A
    if not np.all(np.isfinite(An)):
        return A
    A[np.ix_(live, live)] = An * np.outer(dl, 1.0 / dl)
    return A


#: faults kept apart in the fault stack (:func:`fault_update`): the last this many accepted fixes
FAULT_MEMORY = 8


def fault_update(F: ArrayLike, A: ArrayLike, P_prior: ArrayLike, P_post: ArrayLike, threshold: float) -> FloatArray:
    """The fault stack (k, n, n; module docstring) after an accepted update. ``F[0]`` bounds every fault dropped
    from the stack (:func:`common_bound`), ``F[1:]`` the faults of the last :data:`FAULT_MEMORY` fixes, one each. Every
    matrix becomes ``A M A^T`` (``A = I - K H``: what the update leaves of an earlier error) and the new fix's
    ``threshold (P- - P+)`` is pushed (``threshold`` the gate's chi-square quantile; 0 or inf: a trusted fix, no
    fault); the oldest beyond the memory is folded into ``F[0]`` (no smaller than either of the two).
    ``P_prior``, ``P_post``: full covariances before and after the update."""
    A = np.asarray(A, float)
    F = np.asarray(F, float)
    out = A @ F @ A.T
    out = 0.5 * (out + np.swapaxes(out, 1, 2))
    if not (np.isfinite(threshold) and threshold > 0.0):
        return out
    D = np.asarray(P_prior, float) - np.asarray(P_post, float)
    w, V = np.linalg.eigh(0.5 * (D + D.T))
    out = np.concatenate([out, ((V * np.maximum(w, 0.0)) @ V.T * float(threshold))[None]])
    if len(out) > FAULT_MEMORY + 1:
        out[0] = common_bound(out[0], out[1])
        out = np.delete(out, 1, axis=0)
    return out


def common_bound(A: ArrayLike, B: ArrayLike, rtol: float = 1e-12) -> FloatArray:
    """A PSD matrix no smaller than either PSD ``A`` or ``B`` (n, n) in the Loewner order, and no larger than their
    sum: in the basis that whitens ``S = A + B`` (on its range) the two become ``a`` and ``I - a``, which share
    their eigenvectors, and the bound is ``max(alpha, 1 - alpha)`` on each (``alpha`` the eigenvalues of ``a``).
    Equal to ``A`` when ``B`` is a multiple ``c A`` with ``c <= 1``; to ``A + B`` when their ranges are orthogonal
    (both of which are the least such bound there). Linear maps keep the order, so the bound of two faults,
    propagated, still bounds each of them propagated (:func:`fault_update`)."""
    A = np.asarray(A, float)
    B = np.asarray(B, float)
    S = 0.5 * (A + B + A.T + B.T)
    s, V = np.linalg.eigh(S)
    keep = s > rtol * max(float(s[-1]), 0.0)
    if not keep.any():
        return np.zeros_like(S)
    L = V[:, keep] * np.sqrt(s[keep])  # S = L L^T on its range
    Li = (V[:, keep] / np.sqrt(s[keep])).T  # the pseudo-inverse of L
    a = Li @ (0.5 * (A + A.T)) @ Li.T
    alpha, W = np.linalg.eigh(0.5 * (a + a.T))
    alpha = np.clip(alpha, 0.0, 1.0)
    LW = L @ W
    out = (LW * np.maximum(alpha, 1.0 - alpha)) @ LW.T
    return 0.5 * (out + out.T)


def fault_margin(F: ArrayLike) -> float:
    """The fault-detection margin (m) of a fault stack (:func:`fault_update`): the largest ``sqrt(lambda_max)``
    of its matrices' north/east blocks (one fault at a time)."""
    F = np.asarray(F, float)
    return math.sqrt(max((lambda_max(M[0:2, 0:2]) for M in F), default=0.0))


def hpl_fault_free(cov_ne: ArrayLike, integrity_risk: float = DEFAULT_INTEGRITY_RISK) -> float:
    """``K sigma_max`` (m): the protection level of a covariance alone (no fault margin); ``cov_ne`` (2,2) m^2."""
    return integrity_factor(integrity_risk) * math.sqrt(lambda_max(cov_ne))


@dataclass(frozen=True)
class Verdict:
    """What :meth:`FaultMonitor.assess` decided: ``action`` "accept", "reject" or "recover"; ``reason`` for a
    rejection; ``extra`` for the :class:`Innovation`; ``group`` the tags of the earlier excluded fixes a recovery
    rests on (oldest first; the fuser may apply them too)."""

    action: str
    reason: str = ""
    extra: dict[str, float] = field(default_factory=dict)
    group: tuple[Any, ...] = ()


@dataclass
class _Excluded:
    t: float
    r: FloatArray  # residual fix - INS (north, east) m at t
    R: FloatArray  # fix covariance m^2
    P: FloatArray  # fuser's horizontal covariance at t (prior) m^2
    test: str  # what excluded it: "gate", "window" (both may take part in a recovery) or "external"
    tag: Any = None


class FaultMonitor:
    """The fault detection, recovery and protection level of one fuser (module docstring).

    ``gate_probability``: the single-fix gate (None: no gate, no window test, no recovery: trusted fixes);
    ``window``: accepted fixes in the window test (0: no window test); ``window_s``: their maximum age (s);
    ``window_probability``: the window and mutual-consistency tests' probability; ``reset_after``: mutually
    consistent excluded fixes needed for a recovery (0: never recover); ``recovery_window``: excluded fixes kept
    for it; ``integrity_risk``: of the protection level, per epoch."""

    def __init__(
        self,
        gate_probability: float | None = 0.9999,
        *,
        window: int = DEFAULT_WINDOW,
        window_s: float = DEFAULT_WINDOW_S,
        window_probability: float = DEFAULT_WINDOW_PROBABILITY,
        reset_after: int = DEFAULT_RESET_AFTER,
        recovery_window: int = DEFAULT_RECOVERY_WINDOW,
        integrity_risk: float = DEFAULT_INTEGRITY_RISK,
    ) -> None:
        if int(window) < 0 or int(reset_after) < 0:
            raise ConfigError(f"fault window and reset_after must be >= 0, got {window!r}, {reset_after!r}")
        if not (window_s > 0):
            raise ConfigError(f"fault window_s must be > 0 s, got {window_s!r}")
        chi2_threshold(2, window_probability)  # validates the probability
        self.gate_probability = None if gate_probability is None else float(gate_probability)
        self.window = int(window)
        self.window_s = float(window_s)
        self.window_probability = float(window_probability)
        self.reset_after = int(reset_after)
        self.recovery_window = max(int(recovery_window), self.reset_after)
        self.integrity_risk = float(integrity_risk)
        self.k = integrity_factor(self.integrity_risk)
        self._gate2 = ChiSquareGate(self.gate_probability, 2)
        self._accepted: deque[tuple[float, float]] = deque()  # (t, 2-dof NIS) of the window
        self._excluded: list[_Excluded] = []  # unresolved exclusions since the last accepted fix
        self._margin = 0.0  # fault-detection margin (m) at the last accepted fix
        self._lam_ref = 0.0  # lambda_max of the horizontal covariance just after it (m^2)
        self.n_faults = 0  # fixes excluded by a test
        self.n_recoveries = 0

    # ------------------------------------------------------------------------------------------- decisions
    def gate_threshold(self, dof: int = 2) -> float:
        """The single-fix gate for ``dof`` degrees of freedom (inf without a gate)."""
        return ChiSquareGate(self.gate_probability, dof).threshold

    def assess(
        self,
        t: float,
        residual_ne: ArrayLike,
        S_ne: ArrayLike,
        R_ne: ArrayLike,
        P_ne: ArrayLike,
        *,
        nis_gate: float | None = None,
        dof: int = 2,
        tag: Any = None,
    ) -> Verdict:
        """Decide on a fix at ``t`` (s) with residual fix - INS ``residual_ne`` (m), innovation covariance
        ``S_ne`` (2,2), fix covariance ``R_ne`` and the fuser's prior horizontal covariance ``P_ne`` (m^2).
        ``nis_gate`` / ``dof``: the NIS the gate tests when it has more dof than north/east (a height); ``tag``:
        the fuser's handle of this fix, returned in a later recovery's ``group``. A "reject" is recorded here; after
        "accept" or "recover" the fuser applies the fix and calls :meth:`accepted`."""
        r = np.asarray(residual_ne, float).reshape(2)
        S = np.asarray(S_ne, float)
        R = np.asarray(R_ne, float)
        P = np.asarray(P_ne, float)
        v2 = nis(r, S)
        v = v2 if nis_gate is None else float(nis_gate)
        if self.gate_probability is None:
            return Verdict("accept", extra={"nis_ne": v2})
        T = self.gate_threshold(dof)
        if not (np.isfinite(v) and v <= T):
            ex = _Excluded(float(t), r, R, P, "gate", tag)
            group = self._recovery_group(ex, P) if np.isfinite(v) else None
            if group is not None:
                return Verdict(
                    "recover",
                    extra={"recovery": float(len(group) + 1), "nis_gate": v},
                    group=tuple(e.tag for e in group),
                )
            self._exclude(ex)
            return Verdict(
                "reject", f"NIS {v:.1f} above gate {T:.1f} ({dof} dof)", {"fault": 1.0, "gate": T, "nis_gate": v}
            )
        if self.window > 0:
            self._prune(float(t), self.window)
            n = len(self._accepted) + 1
            s = v2 + sum(x[1] for x in self._accepted)
            Tw = chi2_threshold(2 * n, self.window_probability)
            if n > 1 and s > Tw:
                ex = _Excluded(float(t), r, R, P, "window", tag)
                group = self._recovery_group(ex, P)
                if group is not None:
                    return Verdict(
                        "recover",
                        extra={"recovery": float(len(group) + 1), "nis_gate": v, "window_nis": s},
                        group=tuple(e.tag for e in group),
                    )
                self._exclude(ex)
                return Verdict(
                    "reject",
                    f"window NIS {s:.1f} over {n} fixes above {Tw:.1f}",
                    {"fault": 1.0, "window_nis": s, "window_dof": 2.0 * n, "window_threshold": Tw, "nis_gate": v},
                )
            return Verdict("accept", extra={"window_nis": s, "window_dof": 2.0 * n})
        return Verdict("accept")

    def exclusion(self, t: float, residual_ne: ArrayLike, R_ne: ArrayLike, P_ne: ArrayLike) -> None:
        """Record a fix the fuser excluded by a test of its own (a batch of correlated fixes gated as one): it
        counts as a fault and its residual (m) joins the doubt until a fix is accepted; it takes no part in a
        recovery."""
        r = np.asarray(residual_ne, float).reshape(2)
        if np.all(np.isfinite(r)):
            R, P = np.asarray(R_ne, float), np.asarray(P_ne, float)
            self._exclude(_Excluded(float(t), r, R, P, "external"))

    def _exclude(self, ex: _Excluded) -> None:
        self.n_faults += 1
        self._excluded.append(ex)
        if len(self._excluded) > self.recovery_window:
            self._excluded.pop(0)

    def _prune(self, t: float, keep: int) -> None:
        """Drop window entries older than ``window_s`` at ``t`` and all but the last ``keep``."""
        while self._accepted and (t - self._accepted[0][0] > self.window_s or len(self._accepted) > keep):
            self._accepted.popleft()

    def _recovery_group(self, new: _Excluded, P_now: FloatArray) -> list[_Excluded] | None:
        """The largest set of earlier exclusions by the gate or the window test that, with ``new``, is mutually
        consistent and has at least ``reset_after`` members (None: no recovery). Residuals are compared with
        covariance ``R_i + Q_i``, ``Q_i = P_now - P_i`` (the INS error growth since ``t_i``, no fix having been
        applied since)."""
        if self.reset_after < 1:
            return None
        old = [e for e in self._excluded if e.test != "external"]
        if len(old) + 1 < self.reset_after:
            return None
        for size in range(len(old), self.reset_after - 2, -1):
            for combo in itertools.combinations(old, size):
                members = [*combo, new]
                if self._consistent(members, P_now):
                    return list(combo)
        return None

    def _consistent(self, members: list[_Excluded], P_now: FloatArray) -> bool:
        if len(members) < 2:
            return True
        W = np.zeros((2, 2))
        Wr = np.zeros(2)
        Ci = []
        for e in members:
            C = e.R + _psd(P_now - e.P)
            inv = np.linalg.inv(C)
            Ci.append(inv)
            W += inv
            Wr += inv @ e.r
        r_bar = np.linalg.solve(W, Wr)
        q = sum(float((e.r - r_bar) @ inv @ (e.r - r_bar)) for e, inv in zip(members, Ci, strict=True))
        return q <= chi2_threshold(2 * (len(members) - 1), self.window_probability)

    def accepted(self, t: float, nis_ne: float, P_prior_ne: ArrayLike, P_post_ne: ArrayLike, *, recovery: bool = False):
        """The fuser applied a fix at ``t`` (2-dof NIS ``nis_ne``; horizontal covariance before and after, m^2):
        resolve the exclusions, slide the window (a recovery starts a new one), update the fault margin."""
        Pm = np.asarray(P_prior_ne, float)
        Pp = np.asarray(P_post_ne, float)
        self._excluded.clear()
        if recovery:
            self.n_recoveries += 1
            self._accepted.clear()
        elif self.window > 0 and np.isfinite(nis_ne):
            self._prune(float(t), self.window - 1)
            self._accepted.append((float(t), float(nis_ne)))
        T = self._gate2.threshold if self.gate_probability is not None else 0.0
        lam_m = lambda_max(Pm)
        old = self._margin * math.sqrt(lam_m / self._lam_ref) if self._lam_ref > 0 else 0.0
        try:
            shrink = float(np.linalg.norm(Pp @ np.linalg.inv(Pm), 2))
        except np.linalg.LinAlgError:
            shrink = 1.0
        new2 = T * lambda_max(_psd(Pm - Pp)) if np.isfinite(T) else 0.0
        self._margin = max(min(shrink, 1.0) * old, math.sqrt(new2))
        self._lam_ref = lambda_max(Pp)

    # ----------------------------------------------------------------------------------- protection level
    def margin(self, P_ne: ArrayLike) -> float:
        """The fault-detection margin (m) now, for the current horizontal covariance ``P_ne`` (m^2)."""
        if self._margin <= 0.0 or self._lam_ref <= 0.0:
            return 0.0
        return self._margin * math.sqrt(lambda_max(P_ne) / self._lam_ref)

    def doubt(self, P_ne: ArrayLike) -> float:
        """The doubt term (m): the largest :func:`exclusion_doubt` of the unresolved exclusions that could be right
        (0 without any). While the window holds accepted fixes (the filter was confirmed by fixes consistent with
        its covariance), one the filter could only explain by being more than :data:`MAX_DOUBT_INFLATION` times
        over-confident (in variance) counts only when another unresolved exclusion agrees with it, or when
        ``reset_after`` or more are unresolved (module docstring, ``d``). A filter never confirmed (started off,
        or just recovered) is granted nothing."""
        if not self._excluded:
            return 0.0
        P = np.asarray(P_ne, float)
        gate = self._gate2.threshold if self.gate_probability is not None else math.inf
        lone_ok = bool(self._accepted) and len(self._excluded) < max(self.reset_after, 2)
        out = 0.0
        for e in self._excluded:
            s = filter_inflation(e.r, e.R, P, gate)
            if lone_ok and s > MAX_DOUBT_INFLATION:
                others = [x for x in self._excluded if x is not e]
                if not any(self._consistent([x, e], P) for x in others):
                    continue  # a lone fix no plausible filter error explains: a fault of the matcher's
            out = max(out, exclusion_doubt(e.r, e.R, P, gate, self.k, inflation=s))
        return out

    def hpl(self, P_ne: ArrayLike, margin_m: float | None = None) -> float:
        """The horizontal protection level (m) for the current horizontal covariance ``P_ne`` (m^2); NaN when
        ``P_ne`` is not finite. ``margin_m``: the fault-detection margin (m) when the fuser tracks it
        (:func:`fault_update`); None: :meth:`margin`, this monitor's own (scaled with the covariance)."""
        P = np.asarray(P_ne, float)
        if not np.all(np.isfinite(P)):
            return float("nan")
        m = self.margin(P) if margin_m is None else float(margin_m)
        nominal = self.k * math.sqrt(lambda_max(P)) + m
        return max(nominal, self.doubt(P))
