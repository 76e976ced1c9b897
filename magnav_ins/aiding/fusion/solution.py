"""The matcher's own solution as the navigation solution: a stand-alone navigator behind the ``Fuser`` protocol.

MagNavigate (Shockley 2012, seed 003, ch. V; Raquet, Shockley & Fisher, seed 000, sec. 3.3) navigates with a
particle filter alone: no INS, the weighted particle mean is the position at each epoch and the particle cloud's
spread its uncertainty. In this toolkit the particle filter is a recursive matcher (``aiding.matchers.particle``)
and the pipeline hands a matcher's fixes to a fuser; with ``fix_output = "posterior"`` the "fix" is the cloud's
weighted mean and covariance, and this fuser reports it as the estimate: it keeps no state of its own besides the
last solution, and takes no IMU data except the time.

* :meth:`SolutionFuser.propagate` advances the time only; the position and its covariance stay those of the last
  solution (between two readings the reported solution is up to one reading interval old: 1 m at Shockley's 1 m
  reading spacing).
* :meth:`SolutionFuser.correct` replaces the solution with an available fix (its ``cov_ne`` is the covariance);
  a "no fix" keeps the last one (its :class:`Innovation` says why). The innovation records the change of the
  solution against the last one (``S`` = the sum of both covariances, informative only: the two are not
  independent).
* :meth:`SolutionFuser.estimate` reports the position with its covariance in the ``LAYOUT_15`` slots; the
  velocity is reported as zero with NaN variance (not estimated: the particles' velocities stay in the matcher),
  the height is held (``altitude_hold``, else the initial height), the attitude is level with the initial heading.
  The protection level is the fault-free one (:func:`~.integrity.hpl_fault_free`).

Pair it only with a matcher whose fix is a navigation solution (the particle filter's posterior): a matcher of
independent position fixes (ML, the Bayes grid, the particle increment) would jump from fix to fix with no filter.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ...core.errors import InputError
from ...core.frames import euler_from_q_nb, latlon_to_meters, q_nb_from_euler
from ...core.types import LAYOUT_15, Fix, ImuBatch, Innovation, NavEstimate, NavState
from .common import ImuNoise, fix_problem, rejected
from .integrity import hpl_fault_free

FloatArray = NDArray[np.float64]


class SolutionFuser:
    """Report the matcher's last solution (module docstring).

    ``init``: the starting estimate (its position and 2x2 position covariance are the solution until the first
    fix); ``noise``: accepted for the common ``make_fuser`` signature, unused; ``altitude_hold``: the reported
    height (m; default the initial height)."""

    name = "solution"

    def __init__(
        self,
        init: NavEstimate,
        noise: ImuNoise | None = None,  # noqa: ARG002 - the common make_fuser signature
        *,
        altitude_hold: float | None = None,
    ) -> None:
        nav = init.nav
        cov = np.asarray(init.cov_ne, dtype=float)
        if not (np.all(np.isfinite(cov)) and np.linalg.eigvalsh(0.5 * (cov + cov.T)).min() > 0):
            raise InputError(f"solution: the initial position covariance is not positive definite: {cov.tolist()}")
        self._t = float(nav.t)
        self.lat, self.lon = float(nav.lat), float(nav.lon)
        self.h = float(nav.h) if altitude_hold is None else float(altitude_hold)
        self.cov = 0.5 * (cov + cov.T)
        self.yaw = float(euler_from_q_nb(nav.q_nb)[2])
        self.innovations: list[Innovation] = []

    @property
    def t(self) -> float:
        return self._t

    def propagate(self, imu: ImuBatch) -> None:
        """Advance the time to the last sample (the solution itself changes only with a fix)."""
        t = np.asarray(imu.t, dtype=float)
        if len(t) == 0:
            return
        if not np.all(np.isfinite(t)) or t[0] <= self._t - 1e-12 or np.any(np.diff(t) <= 0):
            raise InputError(f"solution.propagate: sample times must increase from t={self._t!r} s, got {t[:3]}")
        self._t = float(t[-1])

    def correct(self, fix: Fix, *, height_m: float | None = None, height_sigma_m: float | None = None) -> Innovation:  # noqa: ARG002
        """Take an available fix as the new solution; keep the last one on "no fix"."""
        why = fix_problem(fix)
        if why:
            inn = rejected(fix, why)
        else:
            dlon = (fix.lon - self.lon + np.pi) % (2.0 * np.pi) - np.pi
            dn, de = latlon_to_meters(fix.lat - self.lat, dlon, self.lat, self.h)
            y = np.array([float(dn), float(de)])
            R = 0.5 * (np.asarray(fix.cov_ne, float) + np.asarray(fix.cov_ne, float).T)
            S = self.cov + R
            nis = float(y @ np.linalg.solve(S, y))
            self.lat, self.lon, self.cov = float(fix.lat), float(fix.lon), R
            inn = Innovation(float(fix.t), y, S, nis, True, "", fix.source)
        self.innovations.append(inn)
        return inn

    def estimate(self) -> NavEstimate:
        """The last solution in the ``LAYOUT_15`` slots (module docstring)."""
        nav = NavState(self._t, self.lat, self.lon, self.h, np.zeros(3), q_nb_from_euler(0.0, 0.0, self.yaw))
        P15 = np.full((15, 15), np.nan)
        p = LAYOUT_15["pos"].start
        P15[p : p + 2, p : p + 2] = self.cov
        return NavEstimate(nav, P15, hpl_m=hpl_fault_free(self.cov))
