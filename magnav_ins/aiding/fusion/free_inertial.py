"""The free-inertial "fuser": the INS alone, so that every study compares against no aiding.

It mechanises the IMU (:class:`ins.strapdown.StrapdownStepper`) and propagates the 15-state error covariance of
:mod:`ins.error_model` (so its NEES can be checked too); :meth:`FreeInertial.correct` applies nothing and returns a
rejected :class:`Innovation` with the reason "free inertial".
"""

from __future__ import annotations

import numpy as np

from ...core.errors import InputError
from ...core.types import Fix, Innovation
from .common import InertialCore, _SampleBuffer, residual_ne


class FreeInertial(InertialCore):
    """Unaided INS with covariance (constructor as :class:`common.InertialCore`; ``gate_probability`` accepted
    and ignored so that all fusers take the same options)."""

    name = "free_inertial"

    def __init__(self, *args, gate_probability: float | None = None, **kwargs) -> None:  # noqa: ARG002
        super().__init__(*args, **kwargs)
        self.innovations: list[Innovation] = []

    @property
    def can_propagate_outputs(self) -> bool:
        """True when :meth:`propagate_outputs` applies: the 15-state filter without optional states or history."""
        return self.n_states == 15 and self._history is None

    def propagate_outputs(
        self, t: np.ndarray, gyro_b: np.ndarray, accel_b: np.ndarray, out_idx: np.ndarray
    ) -> np.ndarray:
        """Mechanise the rate samples ``t`` (m,) s (after the current time, increasing), ``gyro_b`` rad/s,
        ``accel_b`` m/s^2 (m,3) body FRD, finite, and return the estimate after each sample ``out_idx`` (increasing
        indices into ``t``) as rows (:data:`.free_run.ROW_COLUMNS`: t, lat, lon, h, v_n, q_nb, and the north/east
        position covariance P_nn, P_ne, P_ee m^2): the same numbers as :meth:`propagate` of the samples up to each
        of them and :meth:`estimate` there (:mod:`.free_run`, one compiled call), the state left as that leaves
        it. Only when :attr:`can_propagate_outputs`. The rewind buffer is dropped (this fuser never rewinds)."""
        from .common import _constants
        from .free_run import ROW_COLUMNS, free_run

        if not self.can_propagate_outputs:
            raise InputError("FreeInertial.propagate_outputs: only for the 15-state filter without history")
        t = np.ascontiguousarray(t, dtype=float)
        idx = np.ascontiguousarray(out_idx, dtype=np.int64).reshape(-1)
        rows = np.empty((len(idx), len(ROW_COLUMNS)))
        if len(t) == 0:
            if len(idx):
                raise InputError("FreeInertial.propagate_outputs: output indices without samples")
            return rows
        if len(idx) and (idx[0] < 0 or idx[-1] >= len(t) or np.any(np.diff(idx) <= 0)):
            raise InputError("FreeInertial.propagate_outputs: output indices must increase within the samples")
        if not t[0] > self.t + 1e-9:
            raise InputError(f"FreeInertial.propagate_outputs: first sample t={t[0]!r} not after t={self.t!r}")
        w = np.ascontiguousarray(gyro_b, dtype=float).reshape(-1, 3) - self._b_g
        f = np.ascontiguousarray(accel_b, dtype=float).reshape(-1, 3) - self._b_a
        if not (np.isfinite(t).all() and np.isfinite(w).all() and np.isfinite(f).all()):
            raise InputError("FreeInertial.propagate_outputs: IMU samples hold non-finite values")
        st, sm = self._stepper, self._sums
        holds = np.full(len(t), st._hold)
        t_cov = np.array([self._t_cov])
        inv_a, inv_g, qc = _constants(self.noise)
        self._P = np.ascontiguousarray(self._P)
        n = free_run(st._s, t, w, f, st._cs, holds, sm.C_sum, sm.fn_sum, sm.Cf_sum, sm.Cw_sum, sm.C_prev, sm._acc,
                     t_cov, self.cov_step_s, self._P, self._altitude_hold is not None, inv_a,
                     inv_g, qc, idx, rows)  # fmt: skip
        self._t_cov = float(t_cov[0])
        if n < 0:
            k = -n - 1
            raise InputError(f"FreeInertial.propagate_outputs: time must increase at t={float(t[k])!r}")
        # no rewind (no fix is ever applied): no checkpoint (the next covariance step keeps one), no sample buffer
        self._samples, self._n_dropped, self._checkpoints = _SampleBuffer(), 0, []
        return rows

    def correct(self, fix: Fix, *, height_m: float | None = None, height_sigma_m: float | None = None) -> Innovation:  # noqa: ARG002
        """Record the fix's residual against the free INS, apply nothing."""
        import numpy as np

        r = residual_ne(fix, self._stepper.nav) if fix.available and np.isfinite(fix.lat) else np.full(2, np.nan)
        inn = Innovation(float(fix.t), r, np.full((2, 2), np.nan), float("nan"), False, "free inertial", fix.source)
        self.innovations.append(inn)
        return inn

    def correct_batch(self, fixes: list[Fix], cov) -> Innovation:  # noqa: ANN001, ARG002
        """Apply nothing (the batch counterpart of :meth:`correct`)."""
        import numpy as np

        t = float(fixes[-1].t) if fixes else float("nan")
        inn = Innovation(t, np.full(2, np.nan), np.full((2, 2), np.nan), float("nan"), False, "free inertial", "")
        self.innovations.append(inn)
        return inn
