"""Tolles-Lawson aircraft magnetic compensation (Tolles & Lawson 1950; as in Gnadt's MagNav.jl ``create_TL_A``,
``create_TL_coef``).

The platform field seen by a scalar magnetometer is modelled as a linear combination of terms built from the
direction cosines of the Earth field measured by a vector magnetometer, ``c = B_b / |B_b|`` (body frame FRD):

* permanent (3): ``c_x, c_y, c_z``
* induced (6): ``Bt c_i c_j`` for ``i <= j`` (``xx, xy, xz, yy, yz, zz``)
* eddy (9): ``Bt c_i dc_j/dt`` for all ``i, j``

with ``Bt = |B_b| / bt_scale`` (MagNav.jl scales by 50 000 nT). The 18 terms are linearly dependent:
``c_x^2 + c_y^2 + c_z^2 = 1`` and ``c . dc/dt = 0``; the 16-term set (``pruned=True``, MagNav's ``:induced_5``,
``:eddy_8``) drops ``Bt c_z^2`` and ``Bt c_z dc_z/dt``. Derivatives are per second here (central differences,
``numpy.gradient``), so eddy coefficients are in nT s (MagNav.jl differences per sample).

The fit (``create_TL_coef``): band-pass every column of the design matrix and the scalar signal (Butterworth,
default 0.1-0.9 Hz, order 4, zero phase), trim the filter edges, then (ridge) least squares
``coef = (A^T A + lambda I)^-1 A^T B``. Compensation removes the model's interference minus its mean
(``B_c = B - (A coef - mean(A coef))``), as MagNav.jl does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.signal import butter, sosfiltfilt

from ..core.errors import ConfigError, InputError

FloatArray = NDArray[np.float64]

BT_SCALE_NT = 50_000.0
#: unregularised fit: singular values of the column-normalised, band-passed design below RCOND * largest are
#: dropped (truncated SVD). The 18-term set is rank deficient, and band-passing makes ``Bt (c_x^2 + c_y^2 + c_z^2)``
#: (= Bt, slowly varying) nearly null, so without truncation its coefficient blows up and leaks the slow field.
RCOND = 1e-3
TERMS: tuple[str, ...] = ("permanent", "induced", "eddy")
_PAIRS_INDUCED = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_PAIRS_EDDY = tuple((i, j) for i in range(3) for j in range(3))


def term_names(terms: tuple[str, ...] = TERMS, pruned: bool = False) -> list[str]:
    """Names of the design-matrix columns, in order (``perm_x``, ``ind_xy``, ``eddy_zx`` = ``c_z dc_x/dt``)."""
    ax = "xyz"
    names: list[str] = []
    if "permanent" in terms:
        names += [f"perm_{a}" for a in ax]
    if "induced" in terms:
        names += [f"ind_{ax[i]}{ax[j]}" for i, j in _PAIRS_INDUCED if not (pruned and (i, j) == (2, 2))]
    if "eddy" in terms:
        names += [f"eddy_{ax[i]}{ax[j]}" for i, j in _PAIRS_EDDY if not (pruned and (i, j) == (2, 2))]
    return names


def _check_inputs(vector_nt: ArrayLike, dt: float, scalar_nt: ArrayLike | None = None) -> tuple[FloatArray, ...]:
    v = np.asarray(vector_nt, float)
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputError(f"vector magnetometer: expected shape (N, 3) nT, got {v.shape}")
    if len(v) < 3:
        raise InputError(f"vector magnetometer: {len(v)} samples; need at least 3 for time derivatives")
    bad = np.flatnonzero(~np.all(np.isfinite(v), axis=1))
    if bad.size:
        raise InputError(f"vector magnetometer: non-finite values in row(s) {', '.join(str(r + 1) for r in bad[:5])}")
    if np.any(np.linalg.norm(v, axis=1) <= 0.0):
        raise InputError("vector magnetometer: zero field magnitude; direction cosines undefined")
    if not (math.isfinite(dt) and dt > 0):
        raise ConfigError(f"dt {dt}: expected a positive sample interval in s")
    if scalar_nt is None:
        return (v,)
    s = np.asarray(scalar_nt, float)
    if s.shape != (len(v),):
        raise InputError(f"scalar magnetometer: expected shape ({len(v)},) to match the vector data, got {s.shape}")
    bad = np.flatnonzero(~np.isfinite(s))
    if bad.size:
        raise InputError(f"scalar magnetometer: non-finite values in row(s) {', '.join(str(r + 1) for r in bad[:5])}")
    return v, s


def tl_design_matrix(
    vector_nt: ArrayLike,
    dt: float,
    terms: tuple[str, ...] = TERMS,
    pruned: bool = False,
    bt_scale_nt: float = BT_SCALE_NT,
) -> FloatArray:
    """Tolles-Lawson design matrix (N, K) from vector readings ``vector_nt`` (N, 3) nT sampled every ``dt`` s
    (MagNav.jl ``create_TL_A``); K = 18 (16 with ``pruned``) for all three term groups."""
    unknown = [t for t in terms if t not in TERMS]
    if unknown or not terms:
        raise ConfigError(f"Tolles-Lawson terms {terms!r}: expected a non-empty subset of {TERMS}")
    (v,) = _check_inputs(vector_nt, dt)
    bt = np.linalg.norm(v, axis=1)
    c = v / bt[:, None]
    bts = bt / bt_scale_nt
    cols: list[FloatArray] = []
    if "permanent" in terms:
        cols += [c[:, 0], c[:, 1], c[:, 2]]
    if "induced" in terms:
        cols += [bts * c[:, i] * c[:, j] for i, j in _PAIRS_INDUCED if not (pruned and (i, j) == (2, 2))]
    if "eddy" in terms:
        dc = np.gradient(c, dt, axis=0)
        cols += [bts * c[:, i] * dc[:, j] for i, j in _PAIRS_EDDY if not (pruned and (i, j) == (2, 2))]
    return np.column_stack(cols)


def bandpass(x: ArrayLike, dt: float, band_hz: tuple[float, float], order: int = 4) -> FloatArray:
    """Zero-phase Butterworth band-pass along axis 0 (MagNav.jl ``bpf_data``: pass 0.1-0.9 Hz, 4 poles)."""
    lo, hi = band_hz
    nyq = 0.5 / dt
    if not 0.0 < lo < hi < nyq:
        raise ConfigError(f"band-pass {band_hz} Hz: expected 0 < low < high < Nyquist {nyq:.3g} Hz")
    sos = butter(order, [lo, hi], btype="bandpass", fs=1.0 / dt, output="sos")
    return sosfiltfilt(sos, np.asarray(x, float), axis=0)


@dataclass(frozen=True)
class TollesLawson:
    """Fitted Tolles-Lawson model: ``coef`` (K,) in nT (eddy terms nT s), the ``terms`` used, ``pruned`` (16 vs
    18 terms), ``bt_scale_nt``; ``fit_residual_nt`` the rms of the (filtered) fit residual."""

    coef: FloatArray
    terms: tuple[str, ...] = TERMS
    pruned: bool = False
    bt_scale_nt: float = BT_SCALE_NT
    fit_residual_nt: float = math.nan

    @property
    def names(self) -> list[str]:
        return term_names(self.terms, self.pruned)

    @classmethod
    def fit(
        cls,
        vector_nt: ArrayLike,
        scalar_nt: ArrayLike,
        dt: float,
        *,
        terms: tuple[str, ...] = TERMS,
        pruned: bool = False,
        ridge: float = 0.0,
        band_hz: tuple[float, float] | None = (0.1, 0.9),
        order: int = 4,
        trim: int = 20,
        bt_scale_nt: float = BT_SCALE_NT,
    ) -> TollesLawson:
        """Fit the coefficients on a calibration flight (MagNav.jl ``create_TL_coef``).

        ``vector_nt`` (N, 3) nT body frame, ``scalar_nt`` (N,) nT, ``dt`` [s]. With ``band_hz`` both sides are
        band-passed and ``trim`` samples dropped at each end; ``band_hz=None`` fits the raw signals (then the
        Earth field's own variation must be removed from ``scalar_nt`` beforehand). ``ridge`` is lambda of
        ``(A^T A + lambda I)^-1 A^T B``; 0 uses truncated-SVD least squares on normalised columns (see :data:`RCOND`).
        """
        v, s = _check_inputs(vector_nt, dt, scalar_nt)
        A = tl_design_matrix(v, dt, terms, pruned, bt_scale_nt)
        y = s - s.mean()
        if band_hz is not None:
            A = bandpass(A, dt, band_hz, order)
            y = bandpass(y, dt, band_hz, order)
            if len(y) <= 2 * trim + A.shape[1]:
                raise InputError(f"Tolles-Lawson fit: {len(y)} samples are too few after trimming {trim} at each end")
            A, y = A[trim:-trim], y[trim:-trim]
        if len(y) < A.shape[1]:
            raise InputError(f"Tolles-Lawson fit: {len(y)} samples for {A.shape[1]} coefficients")
        if ridge < 0:
            raise ConfigError(f"ridge {ridge}: expected >= 0")
        if ridge > 0:
            coef = np.linalg.solve(A.T @ A + ridge * np.eye(A.shape[1]), A.T @ y)
        else:
            scale = np.linalg.norm(A, axis=0)
            scale[scale == 0.0] = 1.0
            coef_n, *_ = np.linalg.lstsq(A / scale, y, rcond=RCOND)
            coef = coef_n / scale
        resid = float(np.sqrt(np.mean((y - A @ coef) ** 2)))
        return cls(coef=coef, terms=tuple(terms), pruned=pruned, bt_scale_nt=bt_scale_nt, fit_residual_nt=resid)

    def interference(self, vector_nt: ArrayLike, dt: float) -> FloatArray:
        """Modelled platform interference ``A coef`` (N,) nT."""
        return tl_design_matrix(vector_nt, dt, self.terms, self.pruned, self.bt_scale_nt) @ self.coef

    def compensate(self, vector_nt: ArrayLike, scalar_nt: ArrayLike, dt: float) -> FloatArray:
        """Compensated scalar signal ``B - (A coef - mean(A coef))``, nT (N,)."""
        v, s = _check_inputs(vector_nt, dt, scalar_nt)
        f = self.interference(v, dt)
        return s - (f - f.mean())


# ------------------------------------------------------------------------------------------ simulation


@dataclass(frozen=True)
class BoxPattern:
    """A simulated compensation flight: ``t`` [s], ``vector_nt`` (N, 3) body-frame Earth field seen by the
    vector magnetometer, ``scalar_nt`` (N,) scalar magnetometer = Earth total field + interference + noise,
    ``earth_total_nt`` (N,) truth, ``interference_nt`` (N,) truth, ``dt`` [s]."""

    t: FloatArray
    vector_nt: FloatArray
    scalar_nt: FloatArray
    earth_total_nt: FloatArray
    interference_nt: FloatArray
    dt: float


def simulate_box_pattern(
    coef: ArrayLike,
    rng: np.random.Generator,
    *,
    field_ned_nt: ArrayLike = (18_000.0, 1_000.0, 45_000.0),
    dt: float = 0.1,
    leg_s: float = 120.0,
    pitch_amp: float = math.radians(5.0),
    roll_amp: float = math.radians(10.0),
    yaw_amp: float = math.radians(5.0),
    anomaly_nt: float = 30.0,
    vector_noise_nt: float = 1.0,
    scalar_noise_nt: float = 0.05,
    terms: tuple[str, ...] = TERMS,
    pruned: bool = False,
) -> BoxPattern:
    """Fly the standard compensation box: four legs (headings N, E, S, W, ``leg_s`` each), each with pitch,
    roll then yaw oscillations (periods 6, 8, 6 s; amplitudes in rad) separated by straight flight. The Earth field
    is ``field_ned_nt`` plus a slowly varying (< 0.02 Hz) total-field anomaly of rms ``anomaly_nt``; the scalar
    magnetometer adds the Tolles-Lawson interference with coefficients ``coef`` (order of :func:`term_names`).
    """
    from scipy.spatial.transform import Rotation

    n_leg = int(round(leg_s / dt))
    t = np.arange(4 * n_leg) * dt
    tl = t % leg_s
    leg = (t // leg_s).astype(int)
    third = leg_s / 3.0

    def burst(k: int, period: float, amp: float) -> FloatArray:
        on = (tl >= k * third + 0.1 * third) & (tl < (k + 1) * third - 0.1 * third)
        return np.where(on, amp * np.sin(2 * math.pi * (tl - k * third) / period), 0.0)

    pitch = burst(0, 6.0, pitch_amp)
    roll = burst(1, 8.0, roll_amp)
    yaw = leg * (math.pi / 2.0) + burst(2, 6.0, yaw_amp)
    C_nb = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll])).as_matrix()
    f_n = np.asarray(field_ned_nt, float)
    # slowly varying anomaly along the track (low-pass filtered noise), along the main-field direction
    raw = rng.standard_normal(len(t))
    sos = butter(2, 0.02, btype="lowpass", fs=1.0 / dt, output="sos")
    smooth = sosfiltfilt(sos, raw)
    anomaly = anomaly_nt * smooth / smooth.std()
    B_n = f_n[None, :] * (1.0 + anomaly / np.linalg.norm(f_n))[:, None]
    B_b = np.einsum("nji,nj->ni", C_nb, B_n)  # C_bn B_n = C_nb^T B_n
    earth_total = np.linalg.norm(B_b, axis=1)
    model = TollesLawson(coef=np.asarray(coef, float), terms=terms, pruned=pruned)
    interference = model.interference(B_b, dt)
    vector = B_b + vector_noise_nt * rng.standard_normal(B_b.shape)
    scalar = earth_total + interference + scalar_noise_nt * rng.standard_normal(len(t))
    return BoxPattern(t, vector, scalar, earth_total, interference, dt)
