"""How much position information a map holds: feature variability, gradient RMS and the Cramér-Rao bound.

* Map feature variability (Wang et al. 2022, seed 001, eq. 14): at node ``i`` with a search window of ``n`` other
  nodes ``j``, ``C_i = (1/n) sum_j (x_i - x_j)^2`` (unit^2). Expanding the square, with ``S1``, ``S2`` and ``N`` the
  window sums of ``x``, ``x^2`` and the node count (centre included), ``n = N - 1`` and
  ``C_i = x_i^2 - 2 x_i (S1 - x_i) / n + (S2 - x_i^2) / n``; the sums are box filters
  (:func:`scipy.ndimage.uniform_filter`), so a raster costs O(cells). For a 3-component map the squared difference
  is the squared norm (sum over components). Values are demeaned first (C is invariant to a constant) so the
  expansion does not lose digits.
* Gradient RMS over a window: ``sqrt(mean_window |grad f|^2)`` (unit per metre; Frobenius norm for vector maps).
* Cramér-Rao lower bound on horizontal position: a reading ``z = f(p) + v``, ``v ~ N(0, sigma^2)`` carries Fisher
  information ``J = g g^T / sigma^2`` about ``p`` (``g`` the horizontal gradient; ``G^T G / sigma^2`` for a 3-axis
  reading with the (3, 2) gradient ``G``). One scalar reading constrains position only along ``g``: its bound is
  ``sigma / |g|`` (in general ``1 / sqrt(lambda_max(J))``). Readings that share one position offset (a window of a
  track, or of map cells) add their information; the bound on the offset is ``inv(sum J)`` (2 x 2, m^2), infinite
  along a direction no gradient spans (Van Trees, *Detection, Estimation and Modulation Theory I*, eq. 2.268).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import uniform_filter

from ..core.errors import InputError, MapError
from ..core.frames import meters_to_latlon, radii_of_curvature
from ..core.protocols import FieldMap
from ..core.types import FieldKind
from .grid import GridMap

FloatArray = NDArray[np.float64]


# ---------------------------------------------------------------------------------------------- helpers
def window_half_cells(window_m: float, spacing_m: tuple[float, float]) -> tuple[int, int]:
    """Half-widths (north, east) in cells of a square window ``window_m`` metres across (at least 1 cell)."""
    w = float(window_m)
    if not np.isfinite(w) or w <= 0.0:
        raise InputError(f"window_m: expected a positive window width in metres, got {window_m!r}")
    return max(1, int(round(0.5 * w / spacing_m[0]))), max(1, int(round(0.5 * w / spacing_m[1])))


def _box_sum(a: FloatArray, hn: int, he: int) -> FloatArray:
    size = (2 * hn + 1, 2 * he + 1)
    return uniform_filter(a, size=size, mode="constant", cval=0.0) * (size[0] * size[1])


def _as_components(values: ArrayLike) -> FloatArray:
    v = np.asarray(values, float)
    if v.ndim == 2:
        return v[:, :, None]
    if v.ndim == 3:
        return v
    raise InputError(f"values: expected (ny, nx) or (ny, nx, c), got shape {v.shape}")


def _node_spacing(fmap: GridMap) -> tuple[FloatArray, FloatArray]:
    """Per-row node spacing (north, east) in m, each (ny, 1): exact per latitude row for geodetic maps."""
    ny = fmap.shape[0]
    if fmap.frame == "projected":  # metres of the projection; the ground spacing at the map's centre
        dn, de = fmap.spacing_m
        return np.full((ny, 1), dn), np.full((ny, 1), de)
    if fmap.frame == "local":
        dn, de = fmap.spacing_m
        return np.full((ny, 1), dn), np.full((ny, 1), de)
    lat, lon = fmap.axes
    h = float(np.nanmean(fmap.altitude_m))
    r_n, r_e = radii_of_curvature(lat)
    return ((lat[1] - lat[0]) * (r_n + h))[:, None], ((lon[1] - lon[0]) * (r_e + h) * np.cos(lat))[:, None]


def _scalar_raster(fmap: GridMap, values: FloatArray, quantity: str, unit: str) -> GridMap:
    y, x = fmap.axes
    kind = FieldKind.TOTAL_FIELD_ANOMALY_NT if fmap.kind is FieldKind.VECTOR_FIELD_NT else fmap.kind
    return GridMap(
        y,
        x,
        values,
        kind=kind,
        frame=fmap.frame,
        altitude_m=fmap.altitude_m,
        datum=fmap.datum,
        origin=fmap.origin,
        crs=fmap.crs,
        name=f"{quantity} of {fmap.name}".strip(),
        metadata={**fmap.metadata, "quantity": quantity, "quantity_unit": unit},
    )


# ---------------------------------------------------------------------------------------------- feature variability
def feature_variability_array(values: ArrayLike, spacing_m: tuple[float, float], window_m: float) -> FloatArray:
    """Wang eq. 14 on a grid: ``C_i`` (unit^2, (ny, nx)) over a square window ``window_m`` metres across.

    ``values`` (ny, nx) or (ny, nx, c); ``spacing_m`` = (north, east) node spacing in m. NaN nodes are left out of
    the windows; ``C_i`` is NaN where the centre is NaN or its window holds no other finite node."""
    v = _as_components(values)
    hn, he = window_half_cells(window_m, spacing_m)
    ok = np.all(np.isfinite(v), axis=-1)
    if not ok.any():
        raise MapError("feature variability: the map has no finite node")
    count = _box_sum(ok.astype(float), hn, he)
    n = count - 1.0
    c_i = np.zeros(v.shape[:2])
    for c in range(v.shape[2]):
        x = np.where(ok, v[:, :, c] - np.mean(v[:, :, c][ok]), 0.0)
        s1 = _box_sum(x, hn, he)
        s2 = _box_sum(x * x, hn, he)
        with np.errstate(invalid="ignore", divide="ignore"):
            c_i += x * x - 2.0 * x * (s1 - x) / n + (s2 - x * x) / n
    c_i[~ok | (n < 0.5)] = np.nan
    return np.maximum(c_i, 0.0, where=np.isfinite(c_i), out=c_i)


def feature_variability(fmap: GridMap, window_m: float) -> GridMap:
    """Feature variability raster (Wang eq. 14) of a :class:`GridMap`, on the same grid, unit^2 (for a vector map,
    the squared norm of the component differences). The window is ``window_m`` metres across (cell counts from the
    spacing at the grid centre)."""
    c = feature_variability_array(fmap.values, fmap.spacing_m, window_m)
    return _scalar_raster(fmap, c, "feature_variability", f"{fmap.unit}^2")


def _window_offsets(window_m: float, step_m: float) -> tuple[FloatArray, FloatArray]:
    h = int(round(0.5 * float(window_m) / float(step_m)))
    if h < 1:
        raise InputError(f"window_m = {window_m!r} is narrower than two steps of {step_m!r} m")
    k = np.arange(-h, h + 1) * float(step_m)
    dn, de = np.meshgrid(k, k, indexing="ij")
    keep = (dn != 0.0) | (de != 0.0)
    return dn[keep], de[keep]


def feature_variability_track(
    fmap: FieldMap, lat: ArrayLike, lon: ArrayLike, window_m: float, step_m: float | None = None
) -> FloatArray:
    """``C_i`` (unit^2, (N,)) at each trajectory point (rad): the map is sampled on a square window ``window_m``
    across with ``step_m`` spacing (default: the map's node spacing) centred on the point; NaN samples are skipped."""
    lat_a = np.atleast_1d(np.asarray(lat, float))
    lon_a = np.atleast_1d(np.asarray(lon, float))
    if step_m is None:
        step_m = float(min(fmap.spacing_m)) if hasattr(fmap, "spacing_m") else float(window_m) / 10.0
    dn, de = _window_offsets(window_m, step_m)
    d_lat, d_lon = meters_to_latlon(dn[None, :], de[None, :], lat_a[:, None])
    centre = np.asarray(fmap.value(lat_a, lon_a), float)
    around = np.asarray(fmap.value(lat_a[:, None] + d_lat, lon_a[:, None] + d_lon), float)
    if centre.ndim == 1:
        centre, around = centre[:, None], around[:, :, None]
    sq = np.sum((around - centre[:, None, :]) ** 2, axis=-1)  # (N, M), NaN where off the map
    with np.errstate(invalid="ignore"):
        return np.nanmean(np.where(np.isfinite(sq), sq, np.nan), axis=1) if sq.size else np.full(lat_a.shape, np.nan)


def feature_variability_along_track(tmap: Any, window_m: float) -> FloatArray:
    """``C_i`` (unit^2, (N,)) at every point of a :class:`~magnav_ins.maps.track.TrackMap`, the window being the
    points of the same segment within ``window_m / 2`` of along-track distance (a road map is 1-D). Prefix sums,
    O(N)."""
    w = float(window_m)
    if not np.isfinite(w) or w <= 0.0:
        raise InputError(f"window_m: expected a positive window width in metres, got {window_m!r}")
    v = np.asarray(tmap.values, float)
    v = v[:, None] if v.ndim == 1 else v
    run = np.asarray(tmap.run_index, float)
    s = np.asarray(tmap.along_track_m, float)
    span = float(np.max(s)) + 2.0 * w + 1.0
    key = run * span + s  # increasing: segments in order, distance within each
    eps = 1e-6  # m: points exactly at the window edge are in, whatever the rounding of s
    lo = np.searchsorted(key, key - 0.5 * w - eps, side="left")
    hi = np.searchsorted(key, key + 0.5 * w + eps, side="right")
    ok = np.all(np.isfinite(v), axis=1)
    n = (np.concatenate([[0], np.cumsum(ok)])[hi] - np.concatenate([[0], np.cumsum(ok)])[lo]) - 1.0
    c_i = np.zeros(v.shape[0])
    for c in range(v.shape[1]):
        x = np.where(ok, v[:, c] - np.mean(v[ok, c]), 0.0) if ok.any() else np.zeros(v.shape[0])
        p1 = np.concatenate([[0.0], np.cumsum(x)])
        p2 = np.concatenate([[0.0], np.cumsum(x * x)])
        s1, s2 = p1[hi] - p1[lo], p2[hi] - p2[lo]
        with np.errstate(invalid="ignore", divide="ignore"):
            c_i += x * x - 2.0 * x * (s1 - x) / n + (s2 - x * x) / n
    c_i[~ok | (n < 0.5)] = np.nan
    return c_i


# ---------------------------------------------------------------------------------------------- gradients
def grid_gradient_ne(fmap: GridMap) -> FloatArray:
    """Horizontal gradient at every node by central differences (one-sided at edges), unit per metre, shape
    (ny, nx, c, 2) with c = 1 or 3 components, (d/dnorth, d/deast) of the map's grid axes."""
    v = _as_components(fmap.values)
    dn, de = _node_spacing(fmap)
    g = np.empty(v.shape + (2,))
    for c in range(v.shape[2]):
        g_y, g_x = np.gradient(v[:, :, c])
        g[:, :, c, 0] = g_y / dn
        g[:, :, c, 1] = g_x / de
    return g


def gradient_rms(fmap: GridMap, window_m: float) -> GridMap:
    """RMS of the horizontal gradient norm over a square window ``window_m`` across (unit per metre)."""
    g2 = np.sum(grid_gradient_ne(fmap) ** 2, axis=(2, 3))
    ok = np.isfinite(g2)
    hn, he = window_half_cells(window_m, fmap.spacing_m)
    count = _box_sum(ok.astype(float), hn, he)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(_box_sum(np.where(ok, g2, 0.0), hn, he) / count)
    rms[~ok] = np.nan
    return _scalar_raster(fmap, rms, "gradient_rms", f"{fmap.unit}/m")


# ---------------------------------------------------------------------------------------------- Cramér-Rao bound
def fisher_information_ne(
    grad_ne: ArrayLike, sigma: float | ArrayLike, weight: float | ArrayLike = 1.0, level: bool = False
) -> FloatArray:
    """Fisher information (m^-2, (..., 2, 2)) about horizontal position of one reading with gradient ``grad_ne``
    ((..., 2) scalar or (..., 3, 2) vector, unit/m) and noise ``sigma`` (unit, per reading or one value):
    ``w G^T G / sigma^2``.

    ``weight`` ``w`` (per reading or one value, in [0, 1]) is the share of a reading that is independent evidence
    (e.g. ``min(1, ds / ell)`` for readings ``ds`` apart whose errors are correlated over ``ell``: an
    effective-number approximation of a correlated error, not its exact information). ``level``: the reading also
    carries an unknown additive level per component (``z = m(p) + c + v``), and the information is about
    ``(north, east, c)`` ((..., 3, 3) for a scalar reading, (..., 5, 5) for a vector one: ``H = [G, I]``)."""
    g = np.asarray(grad_ne, float)
    if g.shape[-1] != 2:
        raise InputError(f"grad_ne: expected a trailing axis of 2 (north, east), got shape {g.shape}")
    s2 = np.asarray(sigma, float) ** 2
    if np.any(s2 <= 0):
        raise InputError(f"sigma: expected > 0, got {sigma!r}")
    w = np.asarray(weight, float)
    if np.any(~(w >= 0)) or np.any(w > 1):
        raise InputError(f"weight: expected values in [0, 1], got {weight!r}")
    vector = g.ndim >= 2 and g.shape[-2] == 3
    if level:  # the level's column of H: 1 per component
        gv = g if vector else g[..., None, :]
        eye = np.broadcast_to(np.eye(gv.shape[-2]), gv.shape[:-1] + (gv.shape[-2],))
        h = np.concatenate([gv, eye], axis=-1)
        j = np.einsum("...ci,...cj->...ij", h, h)
    elif vector:
        j = np.einsum("...ci,...cj->...ij", g, g)
    else:
        j = g[..., :, None] * g[..., None, :]
    scale = w / s2
    return j * np.reshape(scale, np.shape(scale) + (1, 1))


def _eig2(j: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Eigenvalues (small, large) of symmetric 2x2 matrices."""
    a, b, d = j[..., 0, 0], j[..., 0, 1], j[..., 1, 1]
    m = 0.5 * (a + d)
    r = np.sqrt(np.maximum(0.25 * (a - d) ** 2 + b * b, 0.0))
    return m - r, m + r


def inverse_2x2(j: ArrayLike, rcond: float = 1e-12) -> FloatArray:
    """Inverse of symmetric 2x2 information matrices; ``inf`` where singular (eigenvalue ratio below ``rcond``)."""
    j = np.asarray(j, float)
    a, b, d = j[..., 0, 0], j[..., 0, 1], j[..., 1, 1]
    det = a * d - b * b
    lo, hi = _eig2(j)
    singular = ~(lo > rcond * hi) | ~np.isfinite(det)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.stack([np.stack([d, -b], -1), np.stack([-b, a], -1)], -2) / det[..., None, None]
    inv[singular] = np.inf
    return inv


def crlb_along_gradient(grad_ne: ArrayLike, sigma: float | ArrayLike) -> FloatArray:
    """Best single-reading position bound (m): ``1 / sqrt(lambda_max(J))`` = ``sigma / |g|`` for a scalar reading;
    ``inf`` on a flat map."""
    _, hi = _eig2(fisher_information_ne(grad_ne, sigma))
    with np.errstate(divide="ignore"):
        return 1.0 / np.sqrt(hi)


@dataclass(frozen=True)
class CrlbSummary:
    """Bounds from an accumulated information matrix: ``cov_ne`` (..., 2, 2) m^2 (``inf`` where singular),
    ``semi_major_m`` / ``semi_minor_m`` (1-sigma ellipse axes, m) and ``drms_m = sqrt(trace cov)``."""

    cov_ne: FloatArray
    semi_major_m: FloatArray
    semi_minor_m: FloatArray
    drms_m: FloatArray


def summarise_information(j: ArrayLike) -> CrlbSummary:
    """Turn information matrices (..., 2, 2) into a :class:`CrlbSummary`."""
    j = np.asarray(j, float)
    lo, hi = _eig2(j)
    with np.errstate(divide="ignore", invalid="ignore"):
        major = np.where(lo > 1e-12 * hi, 1.0 / np.sqrt(lo), np.inf)
        minor = 1.0 / np.sqrt(hi)
    return CrlbSummary(inverse_2x2(j), major, minor, np.hypot(major, minor))


def crlb_track(
    fmap: FieldMap, lat: ArrayLike, lon: ArrayLike, sigma: float | ArrayLike, window: int | None = None
) -> tuple[FloatArray, CrlbSummary]:
    """Cramér-Rao bounds along a trajectory of readings (rad).

    Returns ``(along_gradient_m, summary)``: the single-reading bound ``sigma/|g|`` (N,), and the bound on a
    common position offset of the last ``window`` readings up to each point (all readings so far when ``None``),
    by summing their Fisher information (a cumulative sum, O(N)). Off-map points contribute nothing (their
    single-reading bound is NaN)."""
    g = np.asarray(fmap.gradient_ne(np.atleast_1d(lat), np.atleast_1d(lon)), float)
    j = fisher_information_ne(g, sigma)
    j = np.where(np.isfinite(j), j, 0.0)
    along = crlb_along_gradient(np.where(np.isfinite(g), g, 0.0), sigma)
    off = ~np.all(np.isfinite(g.reshape(g.shape[0], -1)), axis=1)
    along[off] = np.nan  # off the map: no reading, no bound
    cum = np.cumsum(j, axis=0)
    if window is not None:
        if int(window) < 1:
            raise InputError(f"window: expected a number of readings >= 1, got {window!r}")
        w = int(window)
        cum[w:] = cum[w:] - cum[:-w].copy()
    return along, summarise_information(cum)


def crlb_raster(fmap: GridMap, sigma: float, window_m: float) -> dict[str, FloatArray]:
    """Cramér-Rao rasters (m, each (ny, nx) on the map's grid) for readings of noise ``sigma`` (map unit):

    ``along_gradient`` - one reading at the node, ``sigma / |g|``; ``semi_major``, ``semi_minor``, ``drms`` - the
    bound on one position offset shared by readings at every node of a square window ``window_m`` across.
    ``inf`` where the information is singular (flat map, all gradients parallel), NaN where the map has no value.
    Plain arrays rather than :class:`GridMap` because a GridMap stores ``inf`` as missing data."""
    g = grid_gradient_ne(fmap)  # (ny, nx, c, 2)
    ok = np.all(np.isfinite(g), axis=(2, 3))
    g = np.where(ok[:, :, None, None], g, 0.0)
    j = fisher_information_ne(g if g.shape[2] == 3 else g[:, :, 0, :], sigma)
    hn, he = window_half_cells(window_m, fmap.spacing_m)
    jw = np.empty_like(j)
    for a in range(2):
        for b in range(2):
            jw[..., a, b] = _box_sum(j[..., a, b], hn, he)
    along = crlb_along_gradient(g if g.shape[2] == 3 else g[:, :, 0, :], sigma)
    s = summarise_information(jw)
    out = {"along_gradient": along, "semi_major": s.semi_major_m, "semi_minor": s.semi_minor_m, "drms": s.drms_m}
    for arr in out.values():
        arr[~ok] = np.nan
    return out


# ---------------------------------------------------------------------------------------------- posterior CRLB
def posterior_crlb(
    P0: ArrayLike,
    transitions: ArrayLike,
    process_noise: ArrayLike,
    information: ArrayLike,
    hold: tuple[int, ...] = (),
) -> FloatArray:
    """Posterior Cramér-Rao bound of a linear-Gaussian state sequence observed through nonlinear measurements
    (Tichavsky, Muravchik & Nehorai 1998, IEEE TSP 46(5), eq. 21 with linear dynamics; Bergman 1999 ch. 4 for
    terrain navigation): ``J_{k+1} = (Q_k + Phi_k J_k^-1 Phi_k^T)^-1 + I_{k+1}``, run here in covariance form
    ``P- = Phi P Phi^T + Q``, ``P = (P-^-1 + I)^-1`` (with the information form only where ``I`` is non-zero).

    ``P0`` (n, n) prior covariance; ``transitions`` (K, n, n) ``Phi_k`` from step k to k+1; ``process_noise``
    (K, n, n) ``Q_k``; ``information`` (K, n, n) the measurement Fisher information ``I_{k+1}`` added after step k
    (zeros where there is no reading; for a map reading ``H^T H / sigma^2`` with ``H`` the map gradient on the
    position states, :func:`fisher_information_ne`). ``hold``: states clamped by the mechanisation (e.g. the
    altitude hold's down position and velocity), whose rows and columns keep their value and lose their
    correlations after every step, as the fusers' covariance does. Returns the bound ``P_k`` (K + 1, n, n),
    row 0 = ``P0``."""
    P = np.array(P0, dtype=float)
    Phi = np.asarray(transitions, dtype=float)
    Q = np.asarray(process_noise, dtype=float)
    J = np.asarray(information, dtype=float)
    if Phi.ndim != 3 or Phi.shape[1:] != P.shape or Q.shape != Phi.shape or J.shape != Phi.shape:
        raise InputError(
            f"posterior_crlb: P0 {P.shape}, transitions {Phi.shape}, process_noise {Q.shape} and information "
            f"{J.shape} must be (n, n) and (K, n, n)"
        )
    hold = tuple(hold)
    out = np.empty((Phi.shape[0] + 1,) + P.shape)
    out[0] = P
    for k in range(Phi.shape[0]):
        held = np.diag(P)[list(hold)].copy() if hold else None
        P = Phi[k] @ P @ Phi[k].T + Q[k]
        if held is not None:
            P[hold, :] = 0.0
            P[:, hold] = 0.0
            P[hold, hold] = held
        if np.any(J[k]):
            free = [i for i in range(P.shape[0]) if i not in hold]
            Pf = P[np.ix_(free, free)]
            # (P^-1 + J)^-1 = (I + P J)^-1 P: no inverse of P (badly conditioned with a level or bias states)
            Pf = np.linalg.solve(np.eye(len(free)) + Pf @ J[k][np.ix_(free, free)], Pf)
            P[np.ix_(free, free)] = 0.5 * (Pf + Pf.T)
        out[k + 1] = P
    return out
