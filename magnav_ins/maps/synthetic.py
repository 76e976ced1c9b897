"""Synthetic fields for tests and studies: Gaussian random fields, point-dipole and point-mass anomalies, and a
Storms-like indoor 3-axis hallway map.

* Gaussian random field: white noise filtered in the wavenumber domain so that the covariance is the squared
  exponential ``C(r) = sigma^2 exp(-r^2 / (2 l^2))`` (``l`` = ``correlation_length_m``; the correlation falls to
  ``exp(-1/2) = 0.607`` at lag ``l``). The filter is the Fourier transform of the Gaussian kernel whose
  self-convolution is ``C``: ``H(k) = exp(-|k|^2 l^2 / 4)`` (k in rad/m). The field is generated on a grid padded by
  ``4 l`` and cropped, so the FFT's periodicity does not correlate opposite edges.
* Point dipole: ``B = mu0 / (4 pi) (3 (m . r_hat) r_hat - m) / r^3`` (Blakely 1995 eq. 4.13); its total-field
  anomaly in a main field of direction ``b_hat`` is ``dT = b_hat . B`` (Blakely eq. 12.1).
* Point mass: vertical attraction ``g_D = G M (d_s - d) / r^3`` (down positive; Blakely eq. 3.4).
* Hallway: Storms (2009, seed 004) sec. 3.2: an L-shaped pair of hallways mapped with a three-axis HMR2300 on a
  0.381 m (15 in) grid, 930 grid points; Table 3.1 readings are 370-4010 counts (15000 counts per gauss), i.e.
  roughly x 25-105 mG, y 55-150 mG, z 190-270 mG, with jumps of 5-25 mG between neighbouring grid points;
  Table 4.1 puts the hallway centre line at 1.145 m from the wall. 1 mG = 100 nT.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core.errors import InputError
from ..core.types import FieldKind
from ..core.units import NT_PER_MILLIGAUSS
from .grid import GridMap

FloatArray = NDArray[np.float64]

MU0_OVER_4PI = 1e-7  # T m / A
TESLA_TO_NT = 1e9
G_NEWTON = 6.67430e-11  # m^3 kg^-1 s^-2 (CODATA 2018)
MPS2_TO_MGAL = 1e5

#: Storms (2009) grid spacing, 15 in (sec. 3.2.1).
HALLWAY_SPACING_M = 0.381


def _check_positive(name: str, value: float) -> float:
    value = float(value)
    if not np.isfinite(value) or value <= 0.0:
        raise InputError(f"{name}: expected a positive finite number, got {value!r}")
    return value


def gaussian_random_field(
    shape: tuple[int, int],
    spacing_m: tuple[float, float] | float,
    correlation_length_m: float,
    sigma: float,
    rng: np.random.Generator,
    components: int = 1,
) -> FloatArray:
    """A stationary zero-mean Gaussian random field with squared-exponential covariance (module docstring).

    ``shape`` is ``(ny, nx)`` (northing, easting), ``spacing_m`` the node spacing ``(d_north, d_east)`` in m,
    ``correlation_length_m`` the length scale ``l`` (m), ``sigma`` the standard deviation (any unit). Returns
    ``(ny, nx)`` for one component, ``(ny, nx, components)`` (independent components) otherwise. Reproducible
    from ``rng``.
    """
    ny, nx = (int(shape[0]), int(shape[1]))
    if ny < 1 or nx < 1:
        raise InputError(f"shape: expected two positive sizes, got {shape!r}")
    dn, de = (spacing_m, spacing_m) if np.isscalar(spacing_m) else spacing_m  # type: ignore[misc]
    dn, de = _check_positive("spacing_m", dn), _check_positive("spacing_m", de)
    ell = _check_positive("correlation_length_m", correlation_length_m)
    if sigma < 0:
        raise InputError(f"sigma: expected >= 0, got {sigma!r}")
    pad_n, pad_e = int(np.ceil(4.0 * ell / dn)), int(np.ceil(4.0 * ell / de))
    my, mx = ny + 2 * pad_n, nx + 2 * pad_e
    k_n = 2.0 * np.pi * np.fft.fftfreq(my, d=dn)
    k_e = 2.0 * np.pi * np.fft.rfftfreq(mx, d=de)
    k2 = k_n[:, None] ** 2 + k_e[None, :] ** 2
    h = np.exp(-k2 * ell**2 / 4.0)
    # variance of irfft2(H * fft(white)) = mean |H|^2 over the full spectrum (Parseval); count the rfft half twice
    weight = np.full(k_e.shape, 2.0)
    weight[0] = 1.0
    if mx % 2 == 0:
        weight[-1] = 1.0
    var = float(np.sum(h**2 * weight[None, :]) / (my * mx))
    scale = sigma / np.sqrt(var)
    out = np.empty((ny, nx, components))
    for c in range(components):
        white = rng.standard_normal((my, mx))
        field = np.fft.irfft2(np.fft.rfft2(white) * h, s=(my, mx)) * scale
        out[:, :, c] = field[pad_n : pad_n + ny, pad_e : pad_e + nx]
    return out[:, :, 0] if components == 1 else out


def empirical_correlation(field: ArrayLike, lag_cells: int, axis: int = 0) -> float:
    """Sample correlation coefficient of a 2-D field with itself shifted by ``lag_cells`` along ``axis``."""
    f = np.asarray(field, float)
    a = np.take(f, np.arange(f.shape[axis] - lag_cells), axis=axis).ravel()
    b = np.take(f, np.arange(lag_cells, f.shape[axis]), axis=axis).ravel()
    a, b = a - a.mean(), b - b.mean()
    return float(np.sum(a * b) / np.sqrt(np.sum(a * a) * np.sum(b * b)))


def direction_ned(inclination: float, declination: float) -> FloatArray:
    """Unit NED vector of a field with ``inclination`` (down from horizontal) and ``declination`` (east of north), rad."""
    ci = np.cos(inclination)
    return np.array([ci * np.cos(declination), ci * np.sin(declination), np.sin(inclination)])


def dipole_field_ned(r_obs_n: ArrayLike, r_src_n: ArrayLike, moment_n: ArrayLike) -> FloatArray:
    """Field (nT, NED, shape (N, 3)) of a point dipole of moment ``moment_n`` (A m^2, NED) at ``r_src_n`` (m, NED)
    seen at ``r_obs_n`` (m, NED, (N, 3)); Blakely (1995) eq. 4.13."""
    r = np.atleast_2d(np.asarray(r_obs_n, float)) - np.asarray(r_src_n, float)
    dist = np.linalg.norm(r, axis=-1, keepdims=True)
    if np.any(dist == 0.0):
        raise InputError("dipole_field_ned: an observation point coincides with the source")
    r_hat = r / dist
    m = np.asarray(moment_n, float)
    b_t = MU0_OVER_4PI * (3.0 * (r_hat @ m)[:, None] * r_hat - m) / dist**3
    return b_t * TESLA_TO_NT


def dipole_total_field_anomaly(
    r_obs_n: ArrayLike, r_src_n: ArrayLike, moment_n: ArrayLike, main_dir_n: ArrayLike
) -> FloatArray:
    """Total-field anomaly ``b_hat . B_dipole`` (nT, (N,)) in a main field of NED direction ``main_dir_n``
    (normalised here); Blakely (1995) eq. 12.1. Points and moment as :func:`dipole_field_ned`."""
    b_hat = np.asarray(main_dir_n, float)
    b_hat = b_hat / np.linalg.norm(b_hat)
    return dipole_field_ned(r_obs_n, r_src_n, moment_n) @ b_hat


def point_mass_gravity_mgal(r_obs_n: ArrayLike, r_src_n: ArrayLike, mass_kg: float) -> FloatArray:
    """Down component of the attraction (mGal, (N,)) of a point mass ``mass_kg`` at ``r_src_n`` (m, NED) seen at
    ``r_obs_n`` (m, NED, (N, 3)): the gravity disturbance it causes (Blakely 1995 eq. 3.4)."""
    r = np.asarray(r_src_n, float) - np.atleast_2d(np.asarray(r_obs_n, float))
    dist = np.linalg.norm(r, axis=-1)
    return G_NEWTON * mass_kg * r[:, 2] / dist**3 * MPS2_TO_MGAL


def grid_axes(shape: tuple[int, int], spacing_m: float | tuple[float, float]) -> tuple[FloatArray, FloatArray]:
    """Northing and easting axes (m) starting at 0 for a local grid of ``shape`` and ``spacing_m``."""
    dn, de = (spacing_m, spacing_m) if np.isscalar(spacing_m) else spacing_m  # type: ignore[misc]
    return np.arange(shape[0]) * float(dn), np.arange(shape[1]) * float(de)


def random_field_map(
    shape: tuple[int, int],
    spacing_m: float,
    correlation_length_m: float,
    sigma: float,
    rng: np.random.Generator,
    *,
    kind: FieldKind = FieldKind.TOTAL_FIELD_ANOMALY_NT,
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    altitude_m: float = 0.0,
    name: str = "gaussian random field",
) -> GridMap:
    """A local-frame :class:`GridMap` holding :func:`gaussian_random_field` (3 independent components for
    ``vector_field_nt``). ``origin`` = ``(lat0, lon0, h0)`` (rad, rad, m) of the local frame."""
    northing, easting = grid_axes(shape, spacing_m)
    values = gaussian_random_field(shape, spacing_m, correlation_length_m, sigma, rng, components=kind.components)
    return GridMap(
        northing,
        easting,
        values,
        kind=kind,
        frame="local",
        altitude_m=altitude_m,
        origin=origin,
        name=name,
        metadata={"correlation_length_m": correlation_length_m, "sigma": sigma, "source": "synthetic"},
    )


def hallway_map(
    rng: np.random.Generator,
    *,
    main_length_m: float = 33.0,
    side_length_m: float = 17.0,
    width_m: float = 2.286,
    spacing_m: float = HALLWAY_SPACING_M,
    mean_mg: tuple[float, float, float] = (40.0, 100.0, 230.0),
    sigma_mg: float = 12.0,
    correlation_length_m: float = 0.6,
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    centre_fraction: float = 1.0,
    quiet_side_m: tuple[float, float] | None = None,
) -> GridMap:
    """A Storms-like indoor three-axis map (module docstring): an L-shaped hallway on a ``spacing_m`` grid.

    ``centre_fraction`` < 1 makes the variations weaker towards each hallway's centre line (Storms sec. 4.4.2: "there
    is not much variation in the middle of the hallway", larger variations "near structures such as walls"): the
    random field is scaled by ``f + (1 - f) |d| / half-width`` (``d`` the distance from the centre line).
    ``quiet_side_m`` = (start, end) m along the side hallway (from the main hallway's east wall) scales the field by
    ``centre_fraction`` across the whole width there (sec. 4.5.1: a section "right around 10 meters" of the side
    hallway "does not have a lot of variation"). The defaults leave the field as it was.

    The main hallway runs north (the X axis of Storms Fig. 3.2) for ``main_length_m`` with its west wall at
    easting 0 and width ``width_m``; the side hallway leaves its far end eastward for ``side_length_m``. Nodes
    outside the L are NaN (Storms filled them with zeros, which a matcher would take for data). Values are NED
    components in nT: ``mean_mg`` plus a Gaussian random field of ``sigma_mg`` and ``correlation_length_m`` per
    axis (defaults fitted by eye to Storms' Table 3.1). The default lengths give 931 nodes inside the L, against
    Storms' 930 measured grid points, and a side hallway longer than the 16 m of his Table 4.2. Local-frame :class:`GridMap` of kind ``vector_field_nt``.
    """
    ny = int(round(main_length_m / spacing_m)) + 1
    nx = int(round((width_m + side_length_m) / spacing_m)) + 1
    n_width = int(round(width_m / spacing_m)) + 1
    northing, easting = grid_axes((ny, nx), spacing_m)
    field = gaussian_random_field((ny, nx), spacing_m, correlation_length_m, sigma_mg, rng, components=3)
    if centre_fraction != 1.0 or quiet_side_m is not None:
        f = float(centre_fraction)
        if not 0.0 <= f <= 1.0:
            raise InputError(f"centre_fraction: expected 0 <= f <= 1, got {centre_fraction!r}")
        gn, ge = np.meshgrid(northing, easting, indexing="ij")
        half = width_m / 2.0
        d_main = np.abs(ge - half)  # from the main hallway's centre line
        d_side = np.abs(gn - (northing[-1] - half))  # from the side hallway's centre line
        in_side = ge > width_m
        d = np.where(in_side, d_side, np.where(gn > northing[-1] - width_m, np.minimum(d_main, d_side), d_main))
        scale = f + (1.0 - f) * np.clip(d / half, 0.0, 1.0)
        if quiet_side_m is not None:
            a, b = (float(x) for x in quiet_side_m)
            quiet = in_side & (ge - width_m >= a) & (ge - width_m <= b)
            scale = np.where(quiet, f, scale)
        field = field * scale[:, :, None]
    values = (field + np.asarray(mean_mg, float)) * NT_PER_MILLIGAUSS
    inside = np.zeros((ny, nx), dtype=bool)
    inside[:, :n_width] = True  # main hallway
    inside[ny - n_width :, :] = True  # side hallway at the far end
    values[~inside] = np.nan
    return GridMap(
        northing,
        easting,
        values,
        kind=FieldKind.VECTOR_FIELD_NT,
        frame="local",
        altitude_m=origin[2],
        origin=origin,
        name="storms-like hallway",
        metadata={
            "source": "synthetic, after Storms (2009) sec. 3.2 and Table 3.1",
            "spacing_m": spacing_m,
            "centre_line_easting_m": width_m / 2.0,
        },
    )
