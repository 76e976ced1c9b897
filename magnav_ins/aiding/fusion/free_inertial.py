"""The free-inertial "fuser": the INS alone, so that every study compares against no aiding.

It mechanises the IMU (:class:`ins.strapdown.StrapdownStepper`) and propagates the 15-state error covariance of
:mod:`ins.error_model` (so its NEES can be checked too); :meth:`FreeInertial.correct` applies nothing and returns a
rejected :class:`Innovation` with the reason "free inertial".
"""

from __future__ import annotations

from ...core.types import Fix, Innovation
from .common import InertialCore, residual_ne


class FreeInertial(InertialCore):
    """Unaided INS with covariance (constructor as :class:`common.InertialCore`; ``gate_probability`` accepted
    and ignored so that all fusers take the same options)."""

    name = "free_inertial"

    def __init__(self, *args, gate_probability: float | None = None, **kwargs) -> None:  # noqa: ARG002
        super().__init__(*args, **kwargs)
        self.innovations: list[Innovation] = []

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
