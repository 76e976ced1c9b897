"""Grid survey readings into a :class:`~magnav_ins.maps.grid.GridMap` (local tangent-plane frame, metres).

Two gridders:

* ``"bidirectional"`` (default for line surveys): the classic two-pass line-data gridder (bi-directional gridding,
  e.g. Geosoft BIGRID). Lines are first resampled *along* each line (linear, where the survey is dense: ~7 m at
  Osborne) at regular along-line stations, then each station column is interpolated *across* the lines with a
  natural cubic spline (where the survey is sparse: ~200 m line spacing), which follows the curvature of anomalies
  between lines better than linear triangulation. Gaps larger than ``max_gap_m`` (along) or ``2.5 x`` the median line
  spacing (across) are left NaN. Only lines running within 20 deg of the dominant line direction take part; cross
  (tie) lines are left out and listed in the map's metadata (``ignored_lines``).
* ``"linear"`` / ``"cubic"`` (scattered data, or forced): block-mean reduction on a ``spacing/2`` grid, then Delaunay
  triangulation with linear or Clough-Tocher cubic interpolation (scipy); nodes farther than ``max_gap_m`` from any
  reading are NaN.

Coordinates are projected to the local NED tangent plane about the survey centroid (``core.frames``) before gridding.
The map surface height (``altitude_m``) is gridded the same way, giving a draped map (ellipsoidal m).

How the tie lines of a survey are identified (:func:`line_directions`, :func:`cross_lines`): each line's azimuth is
the principal axis of its points in the local plane (PCA); the dominant direction is the length-weighted median
azimuth (mod 180 deg); lines more than 20 deg from it are cross lines. At Osborne this gives 285 east-west flight
lines and 22 north-south tie lines (5816-5819, 10149-10166).

Osborne cross-validation (grid the flight lines, predict the tie lines; ``bench/maps.py``): RMS 37.3 nT at 50 m
(linear triangulation: 38.7 nT), of which a common offset of -24 nT is the levelling difference between the two
line sets in the published data - the flight-line readings within 5 m of a tie-line reading are 24.0 nT lower on
average (:func:`crossover_differences`) - leaving 28.2 nT of scatter.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from ..core.errors import InputError, MagnavError, MapError
from ..core.frames import geodetic_to_ned
from .error_layer import (
    DEFAULT_FOLDS,
    ERROR_INFLATION,
    ErrorModel,
    correlation_length,
    cross_validate,
    fit_between_lines,
    nearest_distance,
)
from .grid import GridMap
from .interp import bilinear, bilinear_scalar
from .survey import Survey

FloatArray = NDArray[np.float64]
CROSS_LINE_TOLERANCE_RAD = np.deg2rad(20.0)


@dataclass(frozen=True)
class LineDirection:
    """One survey line: ``line`` id, ``azimuth`` (rad in [0, pi), from north towards east), ``length_m``, ``n``."""

    line: int
    azimuth: float
    length_m: float
    n: int


def _local(survey: Survey) -> tuple[FloatArray, FloatArray, tuple[float, float, float]]:
    lat0 = float(np.mean(survey.lat))
    lon0 = float(np.angle(np.mean(np.exp(1j * survey.lon))))
    h0 = float(np.mean(survey.h))
    r = geodetic_to_ned(survey.lat, survey.lon, h0, lat0, lon0, h0)
    return r[:, 0], r[:, 1], (lat0, lon0, h0)


def line_directions(survey: Survey) -> list[LineDirection]:
    """Azimuth and length of every line (principal axis of its points in the local plane)."""
    n, e, _ = _local(survey)
    out = []
    assert survey.line is not None
    order = np.argsort(survey.line, kind="stable")
    ids, starts = np.unique(survey.line[order], return_index=True)
    bounds = np.r_[starts, len(order)]
    for k, lid in enumerate(ids):
        idx = order[bounds[k] : bounds[k + 1]]
        if len(idx) < 2:
            out.append(LineDirection(int(lid), float("nan"), 0.0, len(idx)))
            continue
        X = np.c_[n[idx] - n[idx].mean(), e[idx] - e[idx].mean()]
        w, v = np.linalg.eigh(X.T @ X)
        az = float(np.arctan2(v[1, 1], v[0, 1]) % np.pi)
        u = X @ v[:, 1]
        out.append(LineDirection(int(lid), az, float(u.max() - u.min()), len(idx)))
    return out


def dominant_azimuth(dirs: Sequence[LineDirection]) -> float:
    """Length-weighted dominant line azimuth (rad in [0, pi)), via the doubled-angle mean (axial data)."""
    w = np.array([d.length_m for d in dirs if np.isfinite(d.azimuth)])
    a = np.array([d.azimuth for d in dirs if np.isfinite(d.azimuth)])
    if len(a) == 0:
        raise InputError("survey lines: no line has two or more readings")
    return float((np.angle(np.sum(w * np.exp(2j * a))) / 2.0) % np.pi)


def cross_lines(survey: Survey, tolerance_rad: float = CROSS_LINE_TOLERANCE_RAD) -> list[int]:
    """Ids of the lines running more than ``tolerance_rad`` off the dominant direction (tie lines)."""
    dirs = line_directions(survey)
    az0 = dominant_azimuth(dirs)
    off = [d.line for d in dirs if np.isfinite(d.azimuth) and _axial_diff(d.azimuth, az0) > tolerance_rad]
    return sorted(off)


def crossover_level_sigma(
    survey: Survey, n: FloatArray, e: FloatArray, max_distance_m: float, min_pairs: int = 10
) -> tuple[float, int, int] | None:
    """Crossover estimate of the level offset between a survey's line sets: for each line running off the dominant
    direction (:func:`cross_lines`), the median of its readings minus the nearest reading of the other lines, over
    the pairs at most ``max_distance_m`` apart (``n``, ``e`` the readings' local positions, m; the median: a local
    disagreement, e.g. a mis-registered anomaly, is not a level); returns (RMS over the cross lines of those
    medians, map unit; cross lines used; pairs), or None without at least two cross lines with ``min_pairs`` pairs
    each. The RMS keeps the lines' common part: a flight's offset from the map is the level difference itself, not
    its spread. Osborne (all lines, 50 m): 24.0 nT over its 22 tie lines; Rio: 1.2 nT over 5."""
    from scipy.spatial import cKDTree

    ties = cross_lines(survey)
    if not ties:
        return None
    is_tie = np.isin(survey.line, np.asarray(ties, dtype=np.int64))  # type: ignore[arg-type]
    if is_tie.all() or not is_tie.any():
        return None
    tree = cKDTree(np.column_stack([n[~is_tie], e[~is_tie]]))
    other = np.asarray(survey.value, float)[~is_tie]
    d, k = tree.query(np.column_stack([n[is_tie], e[is_tie]]), k=1, distance_upper_bound=max_distance_m)
    close = np.isfinite(d)
    diff = np.asarray(survey.value, float)[is_tie][close] - other[k[close]]
    lines = np.asarray(survey.line)[is_tie][close]
    means = [float(np.median(diff[lines == lid])) for lid in np.unique(lines) if np.sum(lines == lid) >= min_pairs]
    if len(means) < 2:
        return None
    return float(np.sqrt(np.mean(np.square(means)))), len(means), int(close.sum())


def _axial_diff(a: float, b: float) -> float:
    d = abs(a - b) % np.pi
    return min(d, np.pi - d)


def grid_survey(
    survey: Survey,
    spacing_m: float,
    *,
    exclude_lines: Sequence[int] = (),
    method: str = "auto",
    max_gap_m: float | None = None,
    name: str = "",
    error_folds: int = DEFAULT_FOLDS,
    error_block_m: float | None = None,
    error_seed: int = 0,
    error_inflation: float = ERROR_INFLATION,
    level_sigma: float | None = None,
    check_lines: Survey | None = None,
) -> GridMap:
    """Grid ``survey`` at ``spacing_m`` (m) in a local tangent-plane frame; returns a draped local :class:`GridMap`.

    ``exclude_lines``: line ids to leave out (an unknown id is an error). ``method``: ``"auto"`` (bidirectional when
    the survey has line ids, else linear), ``"bidirectional"``, ``"linear"`` or ``"cubic"``. ``max_gap_m`` (default
    ``max(3 * spacing, 100 m)``) bounds along-line gaps and the distance to data for the scattered gridders.

    The map carries its error layer (:mod:`magnav_ins.maps.error_layer`): a block ``error_folds``-fold
    cross-validation (blocks of ``error_block_m``, default about one line spacing; folds drawn from
    ``error_seed``) re-grids the survey ``error_folds`` more times; ``error_folds=0`` gives a map without a layer.
    The between-line-set error (the module docstring of :mod:`~magnav_ins.maps.error_layer`, "Crossovers") is
    measured at the crossovers of the lines that are not gridded - the survey's cross lines the bidirectional
    gridder leaves out, and ``check_lines`` (readings of other lines, e.g. the survey's tie lines when only its
    flight lines are gridded; used for the error estimate and the level crossovers only, never for the grid) - and
    added in quadrature to the cross-validated sigma. Without crossing lines ``error_inflation`` multiplies the
    cross-validated sigma instead (default :data:`~magnav_ins.maps.error_layer.ERROR_INFLATION`, calibrated on
    Osborne's independent tie lines).

    The map's level prior (``metadata["level_sigma"]``, map unit: the 1-sigma of a constant offset between a
    flight's readings and the map, which the matchers marginalise; ``aiding.matchers.map_error.resolve_level``):
    ``level_sigma`` if given; else none is stored and the matchers' stated default applies, which is never less than
    the survey's own levelling differences when the gridded lines cross each other (tie lines among them): their
    crossover estimate (:func:`crossover_level_sigma`) is stored as ``metadata["level_crossover"]``.
    """
    if not (np.isfinite(spacing_m) and spacing_m > 0):
        raise InputError(f"grid spacing must be a positive number of metres, got {spacing_m!r}")
    if method not in ("auto", "bidirectional", "linear", "cubic"):
        raise InputError(f"gridding method {method!r}: expected auto, bidirectional, linear or cubic")
    src = survey.source or "survey"
    if exclude_lines:
        ids = survey.line_ids()
        unknown = sorted(set(int(i) for i in exclude_lines) - set(ids.tolist()))
        if unknown:
            raise InputError(f"{src}: exclude_lines {unknown} are not line ids of the survey")
        survey = survey.select(~np.isin(survey.line, np.asarray(exclude_lines, dtype=np.int64)))  # type: ignore[arg-type]
    if len(survey) < 4:
        raise InputError(f"{src}: {len(survey)} readings left to grid; need at least 4")
    if check_lines is not None and (check_lines.line is None or len(check_lines) == 0):
        raise InputError(f"{src}: check_lines must be survey readings with line ids")
    if method == "auto":
        method = "bidirectional" if survey.line is not None else "linear"
    if method == "bidirectional" and survey.line is None:
        raise InputError(f"{src}: bidirectional gridding needs a line id column ('flight_line' or 'line')")
    gap = float(max_gap_m) if max_gap_m is not None else max(3.0 * spacing_m, 100.0)
    n, e, origin = _local(survey)
    north = np.arange(np.floor(n.min() / spacing_m), np.ceil(n.max() / spacing_m) + 1) * spacing_m
    east = np.arange(np.floor(e.min() / spacing_m), np.ceil(e.max() / spacing_m) + 1) * spacing_m
    if north.size * east.size > 50_000_000:
        raise InputError(
            f"{src}: {north.size} x {east.size} nodes at {spacing_m} m is too large; use a coarser spacing"
        )
    meta: dict[str, object] = {
        "gridder": method,
        "spacing_m": float(spacing_m),
        "source": survey.source,
        "readings": len(survey),
        "excluded_lines": sorted(int(i) for i in exclude_lines),
    }
    if method == "bidirectional":
        vals, alt, ignored, az0 = _bidirectional(survey, n, e, north, east, spacing_m, gap)
        meta["ignored_lines"] = ignored
        meta["line_azimuth_deg"] = float(np.rad2deg(az0))
    else:
        vals, alt = _scattered(n, e, survey.value, survey.h, north, east, spacing_m, gap, method)
    if not np.isfinite(vals).any():
        raise MapError(f"{src}: gridding produced no finite node (spacing {spacing_m} m too coarse for the data?)")
    alt = np.where(np.isfinite(alt), alt, np.nanmean(alt))
    err = None
    err_model = None
    if error_folds:
        err, err_model = _error_layer(
            survey,
            n,
            e,
            north,
            east,
            vals,
            spacing_m,
            method,
            gap,
            meta,
            error_folds,
            error_block_m,
            error_seed,
            error_inflation,
            _crossing_readings(survey, n, e, origin, meta, check_lines),
        )
        meta["error_model"] = err_model.as_metadata()
    if level_sigma is not None:
        if not (np.isfinite(level_sigma) and level_sigma >= 0):
            raise InputError(f"level_sigma must be a number >= 0 (map unit), got {level_sigma!r}")
        meta["level_sigma"] = float(level_sigma)
        meta["level_sigma_source"] = "stated when gridding"
    elif survey.line is not None:
        both = survey if check_lines is None else _concat(survey, check_lines)
        nb, eb = (n, e) if check_lines is None else _local(both)[:2]
        xo = crossover_level_sigma(both, nb, eb, max(0.5 * spacing_m, 5.0))
        if xo is not None:
            meta["level_crossover"] = {"rms": round(xo[0], 6), "lines": xo[1], "pairs": xo[2]}
    return GridMap(
        north,
        east,
        vals,
        kind=survey.kind,
        frame="local",
        altitude_m=alt,
        origin=origin,
        crs="local tangent plane (NED) about origin, WGS84",
        name=name or (survey.source and survey.source.split("/")[-1]) or "survey",
        metadata=meta,
        error_sigma=err,
        error_correlation_m=None if err_model is None else err_model.stated_correlation_m,
        error_source="" if err_model is None else err_model.describe(),
    )


def _concat(a: Survey, b: Survey) -> Survey:
    """The readings of ``a`` and ``b`` (both with line ids) as one survey (``a``'s kind and source)."""
    assert a.line is not None and b.line is not None
    return Survey(
        np.r_[a.lat, b.lat], np.r_[a.lon, b.lon], np.r_[a.h, b.h], np.r_[a.value, b.value], a.kind,
        np.r_[a.line, b.line], a.source,
    )  # fmt: skip


def _crossing_readings(
    survey: Survey,
    n: FloatArray,
    e: FloatArray,
    origin: tuple[float, float, float],
    meta: dict[str, object],
    check_lines: Survey | None,
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.int64]] | None:
    """The readings of lines that are not gridded (the survey's ignored cross lines and ``check_lines``) as local
    ``(n, e, value, line)`` (m, m, map unit, id) about the map's ``origin``; None when there are none."""
    parts = []
    ignored = np.asarray(meta.get("ignored_lines", []), dtype=np.int64)
    if ignored.size and survey.line is not None:
        m = np.isin(survey.line, ignored)
        parts.append((n[m], e[m], survey.value[m], survey.line[m]))
    if check_lines is not None:
        assert check_lines.line is not None
        r = geodetic_to_ned(check_lines.lat, check_lines.lon, origin[2], *origin)
        parts.append((r[:, 0], r[:, 1], np.asarray(check_lines.value, float), check_lines.line))
    if not parts:
        return None
    return tuple(np.concatenate([p[k] for p in parts]) for k in range(4))  # type: ignore[return-value]


def _error_layer(
    survey: Survey,
    n: FloatArray,
    e: FloatArray,
    north: FloatArray,
    east: FloatArray,
    vals: FloatArray,
    spacing_m: float,
    method: str,
    gap: float,
    meta: dict[str, object],
    folds: int,
    block_m: float | None,
    seed: int,
    inflation: float,
    crossing: tuple[FloatArray, FloatArray, FloatArray, NDArray[np.int64]] | None = None,
) -> tuple[FloatArray, ErrorModel]:
    """The error layer of the map ``vals`` gridded from ``survey`` (local ``n``, ``e`` m): block k-fold
    cross-validation with the same gridder (:func:`magnav_ins.maps.error_layer.cross_validate`), the model evaluated
    at every node's distance to the nearest reading used; plus the between-line-set term fitted at the crossovers of
    the ``crossing`` readings (local n, e, value, line) when they give one (:func:`_between_lines`)."""
    used = np.ones(len(survey), dtype=bool)
    if method == "bidirectional":
        used = ~np.isin(survey.line, np.asarray(meta.get("ignored_lines", []), dtype=np.int64))  # type: ignore[arg-type]
    sub = survey.select(used) if not used.all() else survey
    coords = np.c_[n[used], e[used]]
    nn, ee = np.meshgrid(north, east, indexing="ij")
    nodes = np.c_[nn.ravel(), ee.ravel()]
    finite = np.isfinite(vals.ravel())
    node_d = np.full(nodes.shape[0], np.nan)
    node_d[finite] = nearest_distance(coords, nodes[finite])
    az = float(np.deg2rad(meta["line_azimuth_deg"])) if "line_azimuth_deg" in meta else None  # type: ignore[arg-type]
    grad = gradient_magnitude(vals, spacing_m)
    north0, east0 = float(north[0]), float(east[0])
    g_read = bilinear_scalar(
        np.ascontiguousarray(np.nan_to_num(grad, nan=np.nanmedian(grad))),
        north0,
        spacing_m,
        east0,
        spacing_m,
        np.ascontiguousarray(coords[:, 0]),
        np.ascontiguousarray(coords[:, 1]),
        0.0,
    )

    def regrid(train: NDArray[np.bool_], test: NDArray[np.int64], fold_gap: float) -> FloatArray:
        try:
            m = grid_survey(sub.select(train), spacing_m, method=method, max_gap_m=max(gap, fold_gap), error_folds=0)
        except MagnavError:  # a fold that leaves too little to grid predicts nothing
            return np.full(len(test), np.nan)
        return np.asarray(m.value(sub.lat[test], sub.lon[test]), dtype=float)

    model = cross_validate(
        coords,
        sub.value,
        regrid,
        node_d,
        spacing_m,
        g_read,
        folds=folds,
        block_m=block_m,
        azimuth_rad=az,
        seed=seed,
        inflation=inflation,
    )
    if crossing is not None:
        model = _between_lines(model, crossing, coords, vals, grad, north0, east0, spacing_m)
    g_nodes = np.where(np.isfinite(grad), grad, np.nanmedian(grad))
    layer = model.sigma_at(node_d.reshape(vals.shape), g_nodes)
    return layer, model


def _between_lines(
    model: ErrorModel,
    crossing: tuple[FloatArray, FloatArray, FloatArray, NDArray[np.int64]],
    coords: FloatArray,
    vals: FloatArray,
    grad: FloatArray,
    north0: float,
    east0: float,
    spacing_m: float,
) -> ErrorModel:
    """``model`` with the between-line-set term (:func:`magnav_ins.maps.error_layer.fit_between_lines`) fitted at
    the crossovers: the ``crossing`` readings within half a node spacing (at least 5 m) of a gridded reading
    (``coords``, local m), and the correlation length of the misfit along those lines
    (:func:`_misfit_correlation`); ``model`` unchanged when they give no term. The term replaces the inflation."""
    cn, ce, cv, cl = crossing
    d = nearest_distance(coords, np.c_[cn, ce])
    qn, qe = np.ascontiguousarray(cn), np.ascontiguousarray(ce)
    res = bilinear_scalar(np.ascontiguousarray(vals), north0, spacing_m, east0, spacing_m, qn, qe, 0.0) - cv
    g = bilinear_scalar(np.ascontiguousarray(grad), north0, spacing_m, east0, spacing_m, qn, qe, 0.0)
    m = d <= max(0.5 * spacing_m, 5.0)
    if not m.any():
        return model
    cv_var = replace(model, inflation=1.0).sigma_at(d[m], g[m]) ** 2
    fit = fit_between_lines(res[m], cl[m], cv_var, g[m])
    if fit is None:
        return model
    c, p, lines, points = fit
    return replace(
        model,
        inflation=1.0,
        between_var=c,
        between_position_m=p,
        between_lines=lines,
        between_points=points,
        between_correlation_m=_misfit_correlation(np.c_[cn, ce], res, cl, spacing_m, model.block_m),
    )


def _misfit_correlation(
    coords: FloatArray, residual: FloatArray, line: NDArray[np.int64], spacing_m: float, block_m: float
) -> float:
    """Correlation length (m) of the misfit ``residual`` (map - reading; each line's median removed) of the lines not
    gridded along those lines (:func:`magnav_ins.maps.error_layer.correlation_length`, pairs within a line, cells
    of ``spacing_m``): the map error as a line crossing the gridded ones sees it; NaN when it cannot be measured."""
    ok = np.isfinite(residual)
    coords, r, ln = coords[ok], residual[ok], np.asarray(line)[ok]
    if r.size < 10:
        return float("nan")
    rd = np.empty_like(r)
    for lid in np.unique(ln):
        k = ln == lid
        rd[k] = r[k] - np.median(r[k])
    scale = float(np.sqrt(np.mean(rd**2)))
    if not scale > 0:
        return float("nan")
    _, fold = np.unique(ln, return_inverse=True)
    length, lags, _ = correlation_length(
        coords, rd / scale, fold.astype(np.int64), spacing_m, max(20.0 * block_m, 40.0 * spacing_m),
        np.random.default_rng(0), monotone=True,
    )  # fmt: skip
    return float(length) if lags.size else float("nan")


def gradient_magnitude(values: FloatArray, spacing_m: float) -> FloatArray:
    """Horizontal gradient magnitude (unit / m) of a local grid (ny, nx) of node spacing ``spacing_m``: central
    differences inside, one-sided at the edges and next to NaN nodes; NaN where neither neighbour is finite."""
    out = []
    for ax in (0, 1):
        v = np.moveaxis(values, ax, 0)
        fwd = np.full_like(v, np.nan)
        bwd = np.full_like(v, np.nan)
        fwd[:-1] = (v[1:] - v[:-1]) / spacing_m
        bwd[1:] = (v[1:] - v[:-1]) / spacing_m
        both = np.isfinite(fwd) & np.isfinite(bwd)
        g = np.where(both, 0.5 * (fwd + bwd), np.where(np.isfinite(fwd), fwd, bwd))
        out.append(np.moveaxis(g, 0, ax))
    return np.hypot(out[0], out[1])


# ------------------------------------------------------------------------------------------------ scattered
def _block_mean(
    n: FloatArray, e: FloatArray, fields: Sequence[FloatArray], block: float
) -> tuple[FloatArray, FloatArray, list[FloatArray]]:
    i = np.floor((n - n.min()) / block).astype(np.int64)
    j = np.floor((e - e.min()) / block).astype(np.int64)
    key = i * (j.max() + 1) + j
    uk, inv = np.unique(key, return_inverse=True)
    cnt = np.bincount(inv)

    def mean(a: FloatArray) -> FloatArray:
        return np.bincount(inv, weights=a) / cnt

    return mean(n), mean(e), [mean(f) for f in fields]


def _scattered(
    n: FloatArray,
    e: FloatArray,
    v: FloatArray,
    h: FloatArray,
    north: FloatArray,
    east: FloatArray,
    spacing: float,
    gap: float,
    method: str,
) -> tuple[FloatArray, FloatArray]:
    from scipy.interpolate import CloughTocher2DInterpolator, LinearNDInterpolator
    from scipy.spatial import QhullError, cKDTree

    bn, be, (bv, bh) = _block_mean(n, e, [v, h], 0.5 * spacing)
    pts = np.c_[bn, be]
    nn, ee = np.meshgrid(north, east, indexing="ij")
    q = np.c_[nn.ravel(), ee.ravel()]
    try:
        f = (CloughTocher2DInterpolator if method == "cubic" else LinearNDInterpolator)(pts, bv)
        fh = LinearNDInterpolator(f.tri, bh)
    except QhullError as exc:
        raise InputError(f"survey readings cannot be triangulated (all on one line?): {exc}") from None
    vals = f(q)
    alt = fh(q)
    d, _ = cKDTree(pts).query(q, k=1)
    vals[d > gap] = np.nan
    return vals.reshape(nn.shape), alt.reshape(nn.shape)


# ------------------------------------------------------------------------------------------------ bidirectional
def _bidirectional(
    survey: Survey,
    n: FloatArray,
    e: FloatArray,
    north: FloatArray,
    east: FloatArray,
    spacing: float,
    gap: float,
) -> tuple[FloatArray, FloatArray, list[int], float]:
    from scipy.interpolate import CubicSpline

    dirs = line_directions(survey)
    az0 = dominant_azimuth(dirs)
    use = {d.line for d in dirs if np.isfinite(d.azimuth) and _axial_diff(d.azimuth, az0) <= CROSS_LINE_TOLERANCE_RAD}
    ignored = sorted(d.line for d in dirs if d.line not in use)
    ca, sa = np.cos(az0), np.sin(az0)
    u = n * ca + e * sa  # along the lines
    w = -n * sa + e * ca  # across the lines
    step = 0.5 * spacing  # work grid finer than the output, so the final resampling adds little smoothing
    u_nodes = np.arange(np.floor(u.min() / step), np.ceil(u.max() / step) + 1) * step
    assert survey.line is not None
    lines = sorted(use)
    order = np.argsort(survey.line, kind="stable")
    ids, starts = np.unique(survey.line[order], return_index=True)
    bounds = np.r_[starts, len(order)]
    pos = {int(i): k for k, i in enumerate(ids)}
    W = np.full((len(lines), u_nodes.size), np.nan)
    V = np.full_like(W, np.nan)
    H = np.full_like(W, np.nan)
    for r, lid in enumerate(lines):
        k = pos[lid]
        idx = order[bounds[k] : bounds[k + 1]]
        o = np.argsort(u[idx], kind="stable")
        uu, ww, vv, hh = u[idx][o], w[idx][o], survey.value[idx][o], survey.h[idx][o]
        lo = np.searchsorted(u_nodes, uu[0])
        hi = np.searchsorted(u_nodes, uu[-1], side="right")
        if hi - lo < 1:
            continue
        un = u_nodes[lo:hi]
        j = np.clip(np.searchsorted(uu, un), 1, len(uu) - 1)
        ok = (uu[j] - uu[j - 1]) <= gap
        W[r, lo:hi] = np.where(ok, np.interp(un, uu, ww), np.nan)
        V[r, lo:hi] = np.where(ok, np.interp(un, uu, vv), np.nan)
        H[r, lo:hi] = np.where(ok, np.interp(un, uu, hh), np.nan)
    # line spacing: median separation of neighbouring lines at common stations
    with warnings.catch_warnings():  # a line without a station on the work grid (a fold's fragment) is NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        line_w = np.nanmedian(W, axis=1)
    sep = np.diff(np.sort(line_w[np.isfinite(line_w)]))
    sep = sep[sep > 0.25 * spacing]
    across_gap = 2.5 * float(np.median(sep)) if sep.size else 2.5 * gap
    w_nodes = np.arange(np.floor(np.nanmin(W) / step), np.ceil(np.nanmax(W) / step) + 1) * step
    G = np.full((w_nodes.size, u_nodes.size), np.nan)
    GH = np.full_like(G, np.nan)
    merge = 0.25 * spacing
    for c in range(u_nodes.size):
        ok = np.isfinite(W[:, c]) & np.isfinite(V[:, c])
        if ok.sum() < 2:
            continue
        wc, vc, hc = W[ok, c], V[ok, c], H[ok, c]
        o = np.argsort(wc)
        wc, vc, hc = wc[o], vc[o], hc[o]
        # merge repeated lines closer than a quarter cell (their mean)
        grp = np.r_[0, np.cumsum(np.diff(wc) > merge)]
        if grp[-1] + 1 < len(wc):
            cnt = np.bincount(grp)
            wc, vc, hc = (np.bincount(grp, a) / cnt for a in (wc, vc, hc))
        if len(wc) < 2:
            continue
        lo = np.searchsorted(w_nodes, wc[0])
        hi = np.searchsorted(w_nodes, wc[-1], side="right")
        wn = w_nodes[lo:hi]
        col = CubicSpline(wc, vc, bc_type="natural")(wn) if len(wc) >= 3 else np.interp(wn, wc, vc)
        j = np.clip(np.searchsorted(wc, wn), 1, len(wc) - 1)
        bad = (wc[j] - wc[j - 1]) > across_gap
        col[bad] = np.nan
        G[lo:hi, c] = col
        hcol = np.interp(wn, wc, hc)
        hcol[bad] = np.nan
        GH[lo:hi, c] = hcol
    # resample the (w, u) work grid at the output (north, east) nodes
    nn, ee = np.meshgrid(north, east, indexing="ij")
    qu = (nn * ca + ee * sa).ravel()
    qw = (-nn * sa + ee * ca).ravel()
    stack = np.ascontiguousarray(np.stack([G, GH], axis=-1))
    out = bilinear(stack, float(w_nodes[0]), step, float(u_nodes[0]), step, qw, qu, 0.0)
    return out[:, 0].reshape(nn.shape), out[:, 1].reshape(nn.shape), ignored, az0


# ------------------------------------------------------------------------------------------------ validation
def crossover_differences(survey: Survey, lines: Sequence[int], max_distance_m: float = 5.0) -> FloatArray:
    """Reading differences (other lines minus ``lines``) at crossovers: every reading of ``lines`` whose nearest
    reading on another line lies within ``max_distance_m`` (m). Their mean is the levelling offset between the two
    sets of lines, which no gridder of one set can recover when predicting the other."""
    from scipy.spatial import cKDTree

    assert survey.line is not None
    n, e, _ = _local(survey)
    sel = np.isin(survey.line, np.asarray(lines, dtype=np.int64))
    if sel.all() or not sel.any():
        raise InputError("crossover_differences: need readings both on and off the given lines")
    d, i = cKDTree(np.c_[n[~sel], e[~sel]]).query(np.c_[n[sel], e[sel]])
    ok = d <= max_distance_m
    return survey.value[~sel][i[ok]] - survey.value[sel][ok]


def tie_line_misfit(fmap: GridMap, survey: Survey, lines: Sequence[int], method: str = "bilinear") -> dict[int, dict]:
    """Per line: predicted minus observed readings of ``lines`` on ``fmap`` (``rms``, ``mean``, ``std`` in the map
    unit, ``n`` points compared, ``n_off`` points off the map)."""
    out: dict[int, dict] = {}
    assert survey.line is not None
    for lid in lines:
        m = survey.line == lid
        r = fmap.value(survey.lat[m], survey.lon[m], method=method) - survey.value[m]  # type: ignore[arg-type]
        f = np.isfinite(r)
        out[int(lid)] = {
            "rms": float(np.sqrt(np.mean(r[f] ** 2))) if f.any() else float("nan"),
            "mean": float(np.mean(r[f])) if f.any() else float("nan"),
            "std": float(np.std(r[f])) if f.any() else float("nan"),
            "n": int(f.sum()),
            "n_off": int((~f).sum()),
        }
    return out
