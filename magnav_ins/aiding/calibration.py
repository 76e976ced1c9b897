"""Three-axis magnetometer calibration: swinging, strict 2-D ellipse, modified ellipsoid, full 3-D ellipsoid.

All follow Shockley (2012, dissertation, seed 003) sec. 2.4 and 3.1. The measurement model is eq. (2.6)/(2.14)
``m = C B + b + v``; every method returns the correction ``A = C^-1`` and bias ``b`` so that the calibrated
field is ``B = A (m - b)`` (eq. 2.22), in nT, body frame (FRD).

* ``swinging`` (eq. 2.9-2.13): biases from the mid-range of each axis over a level turn, scale factors from the
  half-ranges against the IGRF horizontal field, no distortion terms. Sign convention: Shockley's eq. (2.10)
  defines ``b_x = -(max + min) / 2`` and *adds* it (eq. 2.11) while eq. (2.12) *subtracts* ``b_z``; here ``b`` is
  always subtracted, so ``b_x = (max + min) / 2``. The eq. (2.13) numerator of ``sf_x, sf_y`` is the field the
  axis sees at its maximum during a level turn, i.e. ``|B_h|`` (Shockley writes ``B_x``, equal to ``|B_h|`` only
  when ``B_y = 0``; at AFIT ``B = [200, -21, 493]`` mG the two differ by 0.5 %).
* ``ellipse`` (eq. 2.23-2.28): the 2-D conic fit of the horizontal axes to ``|B_h|``; the vertical axis is left
  untouched (``A_zz = 1``, ``b_z = 0``).
* ``modified-ellipsoid`` (eq. 3.1-3.8): the ellipse fit, rescaled by ``alpha`` (eq. 3.2) so that the calibrated
  horizontal magnitude equals the IGRF ``|B_h|``, plus ``b_z`` (eq. 2.12) and ``sf_z`` (eq. 2.13) for the vertical.
  For platforms that only turn about the vertical (cars, ships, large aircraft in level turns).
* ``ellipsoid`` (eq. 2.15-2.22): the 9-parameter quadric fit, ``A = sqrtm(Q)`` (symmetric square root by SVD).
  For platforms that tumble (hand-held, small drones).

Published vs robust. Shockley sets ``k = b^T Q b = 0`` in eq. (2.16) ("Setting k = 0 on the left side"), which
scales the fitted ``Q`` by ``|B|^2 / (|B|^2 - k)`` and therefore ``A`` by its square root; eq. (3.2)'s ``alpha``
is the ratio of *squared* magnitudes, so it rescales the quadratic form ``Q_h`` (``A_h`` by ``sqrt(alpha)``), which
is what makes ``|B_h,calibrated| = |B_h|`` as sec. 3.1 states. ``published=True`` reproduces the k = 0 fit in raw
coordinates (that is what Table 3.1's "strict ellipse" column shows); the default solves the conic up to scale in
normalised coordinates (centred on the data mean, divided by its rms radius), recovers ``k`` exactly and checks
the conditioning of the design matrix, so the strict ellipse and the modified ellipsoid agree up to noise.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core.atomic import write_text_atomic
from ..core.errors import ConfigError, InputError, where
from ..core.units import DEG_TO_RAD, RAD_TO_DEG

FloatArray = NDArray[np.float64]

METHODS: tuple[str, ...] = ("modified-ellipsoid", "ellipsoid", "ellipse", "swinging")
#: methods that need the platform to turn about the vertical (level) and those that need it to tumble
LEVEL_METHODS = ("modified-ellipsoid", "ellipse", "swinging")
#: unknowns per method; at least ``POINTS_PER_PARAMETER`` readings per unknown are required
N_PARAMETERS = {"swinging": 6, "ellipse": 5, "modified-ellipsoid": 7, "ellipsoid": 9}
POINTS_PER_PARAMETER = 4
#: 2-D methods: the headings (about the fitted centre) must cover at least this many of 12 30-degree sectors
MIN_HEADING_SECTORS = 8
#: 3-D method: the thinnest principal spread of the readings over the widest; a level turn gives ~noise/|B_h|
MIN_TILT_SPREAD_RATIO = 0.1
#: the widest principal rms spread of the readings must be at least this fraction of the field the rotation moves:
#: |B_h| for the level methods (a full circle gives |B_h| / sqrt(2) ~ 0.71, a +-30 degree swing ~0.3), |B| for the
#: ellipsoid (a full tumble gives |B| / sqrt(3) ~ 0.58). Without a reference field, |m| stands in for it.
MIN_SPREAD_FRACTION = 0.2
#: refuse a fit whose normalised design matrix is worse conditioned than this
MAX_CONDITION = 1e8

CAL_FORMAT = "magnav_ins.mag_calibration"
CAL_VERSION = 1


# ----------------------------------------------------------------------------------------------- value type


@dataclass(frozen=True)
class MagnitudeStats:
    """Statistics of ``|B|`` over the calibration readings, nT: mean, standard deviation, max - min, and the rms
    of ``|B| - |B_ref|`` (the residual against the reference field magnitude)."""

    mean_nt: float
    std_nt: float
    span_nt: float
    rms_error_nt: float

    @classmethod
    def of(cls, b_nt: ArrayLike, ref_total_nt: float) -> MagnitudeStats:
        mag = np.linalg.norm(np.asarray(b_nt, float), axis=1)
        return cls(
            mean_nt=float(mag.mean()),
            std_nt=float(mag.std()),
            span_nt=float(mag.max() - mag.min()),
            rms_error_nt=float(np.sqrt(np.mean((mag - ref_total_nt) ** 2))),
        )


@dataclass(frozen=True)
class MagCalibration:
    """A magnetometer calibration: ``B = A (m - b)`` (Shockley eq. 2.22 / 3.8), everything in nT, body frame.

    ``A`` (3, 3) correction (scale factors and distortions, ``C^-1``), ``b`` (3,) bias in nT, ``method`` one of
    :data:`METHODS`, site ``lat``/``lon`` [rad] and ``alt`` [m ellipsoidal], ``date`` (ISO ``YYYY-MM-DD``) of the
    reference field ``field_ned_nt`` (IGRF, NED nT); ``before``/``after`` the ``|B|`` statistics of the raw and the
    calibrated readings; ``n_points`` readings used; ``condition`` of the normalised design matrix (1 for swinging).
    """

    A: FloatArray
    b: FloatArray
    method: str
    lat: float
    lon: float
    alt: float
    date: str
    field_ned_nt: FloatArray
    before: MagnitudeStats
    after: MagnitudeStats
    n_points: int
    condition: float = 1.0
    notes: str = ""

    def __post_init__(self) -> None:
        A = np.array(self.A, float)
        b = np.array(self.b, float)
        f = np.array(self.field_ned_nt, float)
        if A.shape != (3, 3) or not np.all(np.isfinite(A)):
            raise InputError(f"{where(key='A')}expected a finite 3x3 matrix, got shape {A.shape}")
        if b.shape != (3,) or not np.all(np.isfinite(b)):
            raise InputError(f"{where(key='b')}expected 3 finite values, got shape {b.shape}")
        if f.shape != (3,) or not np.all(np.isfinite(f)):
            raise InputError(f"{where(key='field_ned_nt')}expected 3 finite values, got shape {f.shape}")
        if self.method not in METHODS:
            raise ConfigError(f"{where(key='method')}unknown method {self.method!r}; expected one of {METHODS}")
        for arr in (A, b, f):
            arr.setflags(write=False)
        object.__setattr__(self, "A", A)
        object.__setattr__(self, "b", b)
        object.__setattr__(self, "field_ned_nt", f)

    @property
    def field_total_nt(self) -> float:
        """``|B_ref|``, nT."""
        return float(np.linalg.norm(self.field_ned_nt))

    @property
    def field_horizontal_nt(self) -> float:
        """``|B_h,ref| = sqrt(B_N^2 + B_E^2)``, nT."""
        return float(np.hypot(self.field_ned_nt[0], self.field_ned_nt[1]))

    def apply(self, m_nt: ArrayLike) -> FloatArray:
        """Calibrated readings ``A (m - b)``, nT, for ``m_nt`` of shape (3,) or (N, 3) (eq. 2.22 / 3.8)."""
        m = np.asarray(m_nt, float)
        if m.shape[-1] != 3:
            raise InputError(f"magnetometer readings: expected shape (N, 3), got {m.shape}")
        return (m - self.b) @ self.A.T

    # ------------------------------------------------------------------------------------------- JSON

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": CAL_FORMAT,
            "version": CAL_VERSION,
            "method": self.method,
            "unit": "nT",
            "A": self.A.tolist(),
            "b": self.b.tolist(),
            "site": {
                "lat_deg": self.lat * RAD_TO_DEG,
                "lon_deg": self.lon * RAD_TO_DEG,
                "alt_m": self.alt,
                "date": self.date,
            },
            "reference": {
                "model": "IGRF",
                "ned_nt": self.field_ned_nt.tolist(),
                "total_nt": self.field_total_nt,
                "horizontal_nt": self.field_horizontal_nt,
            },
            "residuals": {
                "n_points": self.n_points,
                "before": _stats_dict(self.before),
                "after": _stats_dict(self.after),
            },
            "condition": self.condition,
            "notes": self.notes,
        }

    def to_json(self, path: str | Path) -> None:
        """Write the calibration as JSON, atomically."""
        write_text_atomic(path, json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: str = "calibration") -> MagCalibration:
        """Validate and build; unknown or missing keys and wrong shapes raise :class:`InputError` naming the key."""
        _check_keys(
            d,
            required={"format", "version", "method", "A", "b", "site", "reference", "residuals"},
            optional={"unit", "condition", "notes"},
            source=source,
            prefix="",
        )
        if d["format"] != CAL_FORMAT:
            raise InputError(f"{source}: 'format': expected {CAL_FORMAT!r}, got {d['format']!r}")
        if d["version"] != CAL_VERSION:
            raise InputError(f"{source}: 'version': expected {CAL_VERSION}, got {d['version']!r}")
        if d.get("unit", "nT") != "nT":
            raise InputError(f"{source}: 'unit': expected 'nT', got {d['unit']!r}")
        site, ref, res = d["site"], d["reference"], d["residuals"]
        _check_keys(site, {"lat_deg", "lon_deg", "alt_m", "date"}, set(), source, "site.")
        _check_keys(ref, {"ned_nt"}, {"model", "total_nt", "horizontal_nt"}, source, "reference.")
        _check_keys(res, {"n_points", "before", "after"}, set(), source, "residuals.")
        A = _array(d["A"], (3, 3), source, "A")
        b = _array(d["b"], (3,), source, "b")
        f = _array(ref["ned_nt"], (3,), source, "reference.ned_nt")
        lat = _number(site["lat_deg"], source, "site.lat_deg", -90.0, 90.0)
        lon = _number(site["lon_deg"], source, "site.lon_deg", -360.0, 360.0)
        alt = _number(site["alt_m"], source, "site.alt_m", -1e4, 1e6)
        date = site["date"]
        try:
            if date != "":
                _dt.date.fromisoformat(str(date))
        except ValueError as exc:
            raise InputError(f"{source}: 'site.date': expected YYYY-MM-DD, got {date!r}") from exc
        n = res["n_points"]
        if not isinstance(n, int) or n < 0:
            raise InputError(f"{source}: 'residuals.n_points': expected a non-negative integer, got {n!r}")
        method = d["method"]
        if method not in METHODS:
            raise InputError(f"{source}: 'method': expected one of {METHODS}, got {method!r}")
        return cls(
            A=A,
            b=b,
            method=method,
            lat=lat * DEG_TO_RAD,
            lon=lon * DEG_TO_RAD,
            alt=alt,
            date=str(date),
            field_ned_nt=f,
            before=_stats_from(res["before"], source, "residuals.before"),
            after=_stats_from(res["after"], source, "residuals.after"),
            n_points=n,
            condition=_number(d.get("condition", 1.0), source, "condition", 0.0, math.inf),
            notes=str(d.get("notes", "")),
        )

    @classmethod
    def from_json(cls, path: str | Path) -> MagCalibration:
        """Read a calibration written by :meth:`to_json`; a malformed file raises :class:`InputError`."""
        path = Path(path)
        try:
            d = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError as exc:
            raise InputError(f"{path}: no such calibration file") from exc
        except json.JSONDecodeError as exc:
            raise InputError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from exc
        if not isinstance(d, dict):
            raise InputError(f"{path}: expected a JSON object")
        return cls.from_dict(d, source=str(path))


def _stats_dict(s: MagnitudeStats) -> dict[str, float]:
    return {"mean_nt": s.mean_nt, "std_nt": s.std_nt, "span_nt": s.span_nt, "rms_error_nt": s.rms_error_nt}


def _stats_from(d: Any, source: str, key: str) -> MagnitudeStats:
    names = {"mean_nt", "std_nt", "span_nt", "rms_error_nt"}
    _check_keys(d, names, set(), source, key + ".")
    return MagnitudeStats(
        **{k: _number(d[k], source, f"{key}.{k}", 0.0 if k != "mean_nt" else -math.inf) for k in names}
    )


def _check_keys(d: Any, required: set[str], optional: set[str], source: str, prefix: str) -> None:
    if not isinstance(d, Mapping):
        raise InputError(f"{source}: '{prefix.rstrip('.') or 'top level'}': expected an object, got {d!r}")
    unknown = sorted(set(d) - required - optional)
    if unknown:
        raise InputError(f"{source}: unknown key '{prefix}{unknown[0]}' (allowed: {sorted(required | optional)})")
    missing = sorted(required - set(d))
    if missing:
        raise InputError(f"{source}: missing key '{prefix}{missing[0]}'")


def _array(value: Any, shape: tuple[int, ...], source: str, key: str) -> FloatArray:
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{source}: '{key}': expected numbers of shape {shape}") from exc
    if arr.shape != shape or not np.all(np.isfinite(arr)):
        raise InputError(f"{source}: '{key}': expected finite numbers of shape {shape}, got shape {arr.shape}")
    return arr


def _number(value: Any, source: str, key: str, lo: float = -math.inf, hi: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise InputError(f"{source}: '{key}': expected a finite number, got {value!r}")
    if not lo <= value <= hi:
        raise InputError(f"{source}: '{key}': {value} outside [{lo}, {hi}]")
    return float(value)


# ------------------------------------------------------------------------------------------ input checks


def check_readings(
    m_nt: ArrayLike, method: str, source: str = "readings", field_ned_nt: ArrayLike | None = None
) -> FloatArray:
    """Validate readings (N, 3) nT for ``method``: shape, NaNs (rows named, 1-based), enough points, coverage.

    ``field_ned_nt`` (the reference field, NED nT) sets the scale of the coverage test; without it ``|m|`` does.
    Raises :class:`InputError` (bad data) or :class:`ConfigError` (unknown method) with a one-line reason that
    says which method would fit.
    """
    if method not in METHODS:
        raise ConfigError(f"unknown calibration method {method!r}; expected one of {', '.join(METHODS)}")
    m = np.asarray(m_nt, dtype=float)
    if m.ndim != 2 or m.shape[1] != 3:
        raise InputError(f"{source}: expected readings of shape (N, 3) [mx, my, mz], got {m.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(m), axis=1))
    if bad.size:
        rows = ", ".join(str(r + 1) for r in bad[:5]) + (f" and {bad.size - 5} more" if bad.size > 5 else "")
        raise InputError(f"{source}: non-finite magnetometer values in row(s) {rows}; drop or repair those rows")
    need = POINTS_PER_PARAMETER * N_PARAMETERS[method]
    if len(m) < need:
        raise InputError(
            f"{source}: {len(m)} readings are too few for the {method} method "
            f"({N_PARAMETERS[method]} unknowns); need at least {need}"
        )
    if field_ned_nt is not None:
        _check_unit(m, float(np.linalg.norm(np.asarray(field_ned_nt, float))), source)
    spread = _principal_spread(m)
    level = method in LEVEL_METHODS
    if field_ned_nt is not None:
        f = np.asarray(field_ned_nt, float).reshape(3)
        moved, what = (float(np.hypot(f[0], f[1])), "|B_h|") if level else (float(np.linalg.norm(f)), "|B|")
    else:
        moved, what = float(np.median(np.linalg.norm(m, axis=1))), "|m|"
    if spread[0] < MIN_SPREAD_FRACTION * moved:
        raise InputError(
            f"{source}: the readings barely change (rms spread {spread[0]:.0f} nT = {100 * spread[0] / moved:.1f} % of "
            f"{what} {moved:.0f} nT; need {100 * MIN_SPREAD_FRACTION:.0f} %): the sensor hardly rotated (one "
            f"heading or attitude, or small motions only), so there is no rotation coverage; {_advice(method)}"
        )
    if method == "ellipsoid" and spread[2] < MIN_TILT_SPREAD_RATIO * spread[0]:
        raise InputError(
            f"{source}: the readings lie close to a plane (thinnest/widest spread {spread[2] / spread[0]:.3f} < "
            f"{MIN_TILT_SPREAD_RATIO}): the platform turned about one axis only, which cannot determine a 3-D "
            "ellipsoid; use --method modified-ellipsoid"
        )
    return m


#: |readings| / |reference field| outside this range is a unit mistake, not distortion (hard-iron biases on vehicles
#: are a fraction of the Earth's field, soft iron a few tens of percent)
UNIT_RATIO_RANGE = (0.1, 10.0)
#: nT per unit, for the unit a misread file probably has
_UNITS_NT = {
    "gauss (G)": 1e5,
    "milligauss (mG)": 1e2,
    "microtesla (uT)": 1e3,
    "tesla (T)": 1e9,
    "ArduPilot's mG x 1000": 0.1,
}


def _check_unit(m: FloatArray, field_nt: float, source: str) -> None:
    """Readings must be in nT: compare their median magnitude with the reference field's."""
    med = float(np.median(np.linalg.norm(m, axis=1)))
    if field_nt <= 0 or UNIT_RATIO_RANGE[0] * field_nt <= med <= UNIT_RATIO_RANGE[1] * field_nt:
        return
    scale = field_nt / med if med > 0 else math.inf
    guess = min(_UNITS_NT, key=lambda u: abs(math.log(_UNITS_NT[u] / scale))) if med > 0 else None
    hint = ""
    if guess is not None and abs(math.log10(_UNITS_NT[guess] / scale)) < 0.5:
        hint = f"; they look like {guess}: multiply by {_UNITS_NT[guess]:g} to get nT"
    raise InputError(
        f"{source}: median |m| is {med:.4g} but the reference field at the site is {field_nt:.0f} nT: the readings "
        f"must be in nT{hint}"
    )


def _advice(method: str) -> str:
    if method in LEVEL_METHODS:
        return "turn the platform through at least 240 degrees of heading (a full circle is best)"
    return "rotate the sensor through many attitudes (tumble it), or for level turns use modified-ellipsoid"


def _principal_spread(m: FloatArray) -> FloatArray:
    """Standard deviations of ``m`` along its principal axes, largest first."""
    c = m - m.mean(axis=0)
    return np.linalg.svd(c, compute_uv=False) / math.sqrt(len(m))


def _check_heading_coverage(m_h: FloatArray, centre: FloatArray, method: str, source: str) -> None:
    heading = np.arctan2(m_h[:, 1] - centre[1], m_h[:, 0] - centre[0])
    sectors = np.unique(np.floor((heading + math.pi) / (math.pi / 6.0)).astype(int) % 12).size
    if sectors < MIN_HEADING_SECTORS:
        raise InputError(
            f"{source}: the readings cover only {sectors * 30} degrees of heading; the {method} method needs at "
            f"least {MIN_HEADING_SECTORS * 30} (turn through a full circle)"
        )


# ---------------------------------------------------------------------------------------------- fits


@dataclass(frozen=True)
class QuadricFit:
    """Result of a conic/quadric fit ``|A (x - b)| = r``: ``A`` symmetric positive definite, ``b`` centre (in the
    units of ``x``), ``condition`` of the column-normalised design matrix."""

    A: FloatArray
    b: FloatArray
    condition: float


def _design(x: FloatArray) -> FloatArray:
    """Design matrix of eq. (2.19) (3-D, N x 9) or eq. (2.25) (2-D, N x 5)."""
    if x.shape[1] == 3:
        X, Y, Z = x.T
        return np.column_stack([X * X, Y * Y, Z * Z, 2 * X * Y, 2 * X * Z, 2 * Y * Z, -2 * X, -2 * Y, -2 * Z])
    X, Y = x.T
    return np.column_stack([X * X, Y * Y, 2 * X * Y, -2 * X, -2 * Y])


def _unpack_q(p: FloatArray, dim: int) -> tuple[FloatArray, FloatArray]:
    if dim == 3:
        q11, q22, q33, q12, q13, q23 = p[:6]
        Q = np.array([[q11, q12, q13], [q12, q22, q23], [q13, q23, q33]])
        return Q, p[6:9]
    q11, q22, q12 = p[:3]
    return np.array([[q11, q12], [q12, q22]]), p[3:5]


def _sqrtm_spd(Q: FloatArray, what: str, source: str) -> FloatArray:
    """Symmetric square root by eigen-decomposition (Shockley's SVD ``U sqrt(S) U^T``, sec. 2.4.5)."""
    w, U = np.linalg.eigh(0.5 * (Q + Q.T))
    if np.any(w <= 0.0):
        raise InputError(
            f"{source}: the {what} fit is not an ellipse/ellipsoid (eigenvalues {np.array2string(w, precision=3)}); "
            "the readings do not cover enough rotation or are dominated by disturbances"
        )
    return (U * np.sqrt(w)) @ U.T


def fit_quadric(
    x: ArrayLike, radius: float, *, published: bool = False, source: str = "readings", what: str = "ellipsoid"
) -> QuadricFit:
    """Fit ``|A (x - b)| = radius`` to points ``x`` (N, 2) or (N, 3): eq. (2.15-2.22) in 3-D, (2.23-2.28) in 2-D.

    ``published=True``: eq. (2.19)/(2.25) as printed, ``D p = radius^2`` in raw coordinates with ``k = 0``, so
    ``A`` is too large by ``sqrt(r^2 / (r^2 - k))``. Default: solve ``D p = 1`` in normalised coordinates (mean
    removed, divided by the rms radius), then ``Q = Q' r^2 / (1 + b^T Q' b)``, which is the exact solution of
    eq. (2.16) with ``k`` kept. Raises :class:`InputError` if the normalised design matrix has condition number
    above :data:`MAX_CONDITION` or the quadric is not an ellipse/ellipsoid.
    """
    x = np.asarray(x, float)
    dim = x.shape[1]
    if published:
        D = _design(x)
        p, *_ = np.linalg.lstsq(D, np.full(len(x), radius**2), rcond=None)
        Q, v = _unpack_q(p, dim)
        b = np.linalg.solve(Q, v)
        cond = float(np.linalg.cond(D / np.linalg.norm(D, axis=0)))
        return QuadricFit(A=_sqrtm_spd(Q, what, source), b=b, condition=cond)
    centre = x.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((x - centre) ** 2, axis=1))))
    xn = (x - centre) / scale
    D = _design(xn)
    col = np.linalg.norm(D, axis=0)
    cond = float(np.linalg.cond(D / col))
    if not np.isfinite(cond) or cond > MAX_CONDITION:
        raise InputError(
            f"{source}: the {what} fit is ill-conditioned (condition number {cond:.3g} > {MAX_CONDITION:.0e}): "
            "the rotations do not excite every parameter"
            + ("; for level turns use --method modified-ellipsoid" if dim == 3 else "")
        )
    pn, *_ = np.linalg.lstsq(D / col, np.ones(len(x)), rcond=None)
    Qn, v = _unpack_q(pn / col, dim)
    bn = np.linalg.solve(Qn, v)
    gain = 1.0 + float(bn @ Qn @ bn)  # (x - b)^T Qn (x - b) = 1 + b^T Qn b on the fitted quadric
    if gain <= 0.0:
        raise InputError(f"{source}: the {what} fit is degenerate (1 + b^T Q b = {gain:.3g} <= 0)")
    Q = Qn * (radius / scale) ** 2 / gain
    return QuadricFit(A=_sqrtm_spd(Q, what, source), b=centre + scale * bn, condition=cond)


def _level_reference(field_ned_nt: FloatArray) -> tuple[float, float, float]:
    bh = float(np.hypot(field_ned_nt[0], field_ned_nt[1]))
    return bh, float(field_ned_nt[2]), float(np.linalg.norm(field_ned_nt))


def _vertical_terms(z: FloatArray, b_z_ref: float) -> tuple[float, float]:
    """``b_z`` (eq. 2.12) and ``sf_z`` (eq. 2.13) for a level turn. With the vertical axis barely excited the
    two are not separately observable; eq. (2.13) evaluated on the bias-corrected readings gives ``sf_z ~ 1``."""
    b_z = 0.5 * (z.max() + z.min()) - b_z_ref
    zc = float(np.mean(z - b_z))
    sf_z = b_z_ref / zc if abs(zc) > 1e-9 else 1.0
    return float(b_z), float(sf_z)


def fit_swinging(m_nt: FloatArray, field_ned_nt: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Swinging calibration (eq. 2.9-2.13 with IGRF known): ``A = diag(sf)``, ``b`` = mid-ranges (x, y) and
    eq. (2.12) (z). Returns ``(A, b)``."""
    bh, bz, _ = _level_reference(field_ned_nt)
    mx, mn = m_nt.max(axis=0), m_nt.min(axis=0)
    b_xy = 0.5 * (mx[:2] + mn[:2])
    sf_xy = bh / (mx[:2] - b_xy)
    b_z, sf_z = _vertical_terms(m_nt[:, 2], bz)
    return np.diag([sf_xy[0], sf_xy[1], sf_z]), np.array([b_xy[0], b_xy[1], b_z])


def fit_ellipse(
    m_nt: FloatArray, field_ned_nt: FloatArray, *, published: bool = False, source: str = "readings"
) -> tuple[FloatArray, FloatArray, float]:
    """Strict 2-D ellipse (eq. 2.23-2.28): horizontal axes only, ``A_zz = 1``, ``b_z = 0``. Returns ``(A, b, cond)``."""
    bh, _, _ = _level_reference(field_ned_nt)
    fit = fit_quadric(m_nt[:, :2], bh, published=published, source=source, what="ellipse")
    A = np.eye(3)
    A[:2, :2] = fit.A
    return A, np.array([fit.b[0], fit.b[1], 0.0]), fit.condition


def fit_modified_ellipsoid(
    m_nt: FloatArray, field_ned_nt: FloatArray, *, published: bool = False, source: str = "readings"
) -> tuple[FloatArray, FloatArray, float]:
    """Modified ellipsoid (Shockley eq. 3.1-3.8): ellipse fit, ``alpha = |B_h|^2 / mean |A_h (m_h - b_h)|^2``
    (eq. 3.2) applied to the quadratic form (``A_h -> sqrt(alpha) A_h``), ``b_z``/``sf_z`` from eq. (2.12-2.13),
    ``A_alpha = [[sqrt(alpha) A_h, 0], [0, sf_z]]`` (eq. 3.5). Returns ``(A, b, cond)``."""
    bh, bz, _ = _level_reference(field_ned_nt)
    fit = fit_quadric(m_nt[:, :2], bh, published=published, source=source, what="ellipse")
    bt_h = (m_nt[:, :2] - fit.b) @ fit.A.T
    alpha = bh**2 / float(np.mean(np.sum(bt_h**2, axis=1)))
    b_z, sf_z = _vertical_terms(m_nt[:, 2], bz)
    A = np.zeros((3, 3))
    A[:2, :2] = math.sqrt(alpha) * fit.A
    A[2, 2] = sf_z
    return A, np.array([fit.b[0], fit.b[1], b_z]), fit.condition


def fit_ellipsoid(
    m_nt: FloatArray, field_ned_nt: FloatArray, *, published: bool = False, source: str = "readings"
) -> tuple[FloatArray, FloatArray, float]:
    """Full 3-D ellipsoid (eq. 2.15-2.22), ``A = sqrtm(Q)``. Returns ``(A, b, cond)``."""
    fit = fit_quadric(m_nt, float(np.linalg.norm(field_ned_nt)), published=published, source=source)
    return fit.A, fit.b, fit.condition


def calibrate(
    m_nt: ArrayLike,
    method: str,
    field_ned_nt: ArrayLike,
    *,
    lat: float = 0.0,
    lon: float = 0.0,
    alt: float = 0.0,
    date: str = "",
    published: bool = False,
    source: str = "readings",
) -> MagCalibration:
    """Calibrate readings ``m_nt`` (N, 3) nT body frame against the reference field ``field_ned_nt`` (NED nT, e.g.
    :func:`magnav_ins.maps.reference.igrf_ned` at the site ``lat``/``lon`` [rad], ``alt`` [m], ``date``).

    Level methods assume the body z axis points down during the turns (body x-y horizontal). Bad input raises
    :class:`InputError` (one line, says why and which method fits); an unknown method :class:`ConfigError`.
    """
    if method not in METHODS:
        raise ConfigError(f"unknown calibration method {method!r}; expected one of {', '.join(METHODS)}")
    f = np.asarray(field_ned_nt, float).reshape(3)
    if not np.all(np.isfinite(f)) or np.linalg.norm(f) <= 0:
        raise InputError(f"reference field {f}: expected a finite non-zero NED vector in nT")
    bh, _, total = _level_reference(f)
    if method in LEVEL_METHODS and bh < 0.05 * total:
        raise InputError(
            f"reference horizontal field {bh:.0f} nT is < 5 % of |B| = {total:.0f} nT (near a magnetic pole): a level "
            "turn cannot calibrate the horizontal axes here; use --method ellipsoid with tumbling data"
        )
    m = check_readings(m_nt, method, source, f)
    cond = 1.0
    if method == "swinging":
        A, b = fit_swinging(m, f)
    elif method == "ellipse":
        A, b, cond = fit_ellipse(m, f, published=published, source=source)
    elif method == "modified-ellipsoid":
        A, b, cond = fit_modified_ellipsoid(m, f, published=published, source=source)
    else:
        A, b, cond = fit_ellipsoid(m, f, published=published, source=source)
    if method in LEVEL_METHODS:
        _check_heading_coverage(m[:, :2], b[:2], method, source)
    cal_tmp = (m - b) @ A.T
    return MagCalibration(
        A=A,
        b=b,
        method=method,
        lat=float(lat),
        lon=float(lon),
        alt=float(alt),
        date=str(date),
        field_ned_nt=f,
        before=MagnitudeStats.of(m, total),
        after=MagnitudeStats.of(cal_tmp, total),
        n_points=len(m),
        condition=cond,
        notes="published k=0 form" if published else "",
    )


# ------------------------------------------------------------------------------------------ simulation


def level_turn_field_b(field_ned_nt: ArrayLike, heading: ArrayLike) -> FloatArray:
    """Earth field in a level body frame (FRD) at the given headings [rad]: ``C_bn(psi) B_n``, nT, (N, 3)."""
    f = np.asarray(field_ned_nt, float)
    psi = np.asarray(heading, float)
    c, s = np.cos(psi), np.sin(psi)
    return np.column_stack([c * f[0] + s * f[1], -s * f[0] + c * f[1], np.full_like(psi, f[2])])


def simulate_level_circles(
    field_ned_nt: ArrayLike,
    C: ArrayLike,
    b_nt: ArrayLike,
    noise_nt: float,
    rng: np.random.Generator,
    *,
    n_circles: int = 3,
    n_per_circle: int = 360,
    start_heading: float = math.pi,
) -> tuple[FloatArray, FloatArray]:
    """Shockley's simulation (sec. 3.2.1): a level platform driving ``n_circles`` circles from ``start_heading``
    [rad]; readings ``m = C B_b + b + v`` (eq. 2.14) with white noise ``noise_nt`` [nT, 1 sigma].
    Returns ``(m_nt (N, 3), B_b_true_nt (N, 3))``."""
    psi = start_heading + np.linspace(0.0, 2.0 * math.pi * n_circles, n_circles * n_per_circle, endpoint=False)
    B_b = level_turn_field_b(field_ned_nt, psi)
    m = B_b @ np.asarray(C, float).T + np.asarray(b_nt, float) + noise_nt * rng.standard_normal(B_b.shape)
    return m, B_b
