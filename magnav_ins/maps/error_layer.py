"""A gridded survey's own prediction error, estimated by spatial block k-fold cross-validation (DESIGN "Integrity").

The question: how far is the map from the true field at a node? Where the map has readings nearby it is close; between
survey lines and far from data it is interpolated and can be far off. Cross-validation measures exactly this on
the survey itself (Roberts et al. 2017, *Cross-validation strategies for data with temporal, spatial, hierarchical
or phylogenetic structure*, Ecography 40: blocks, not random points, because nearby readings share their errors;
Verde's ``BlockKFold``, Uieda 2018, JOSS 3(30):957):

1. The readings used for the map are grouped into square blocks of side ``b`` (default: twice the 90th percentile of
   the distance from a map node to its nearest reading, i.e. about one line spacing on a line survey; in the survey
   lines' own along/across frame when the lines are known) and the blocks are split into ``k`` folds
   (``verde.BlockKFold``, shuffled: the only verde import of the package).
2. For each fold the map is re-gridded without it, with the same gridder and spacing (its gap limit raised to
   ``1.5 b`` so that the hole is filled, as the map fills the space between lines), and predicts the held-out
   readings: their residuals ``r = map - reading`` are the map error at distance ``d`` from the nearest reading it
   was built from (the readings' own noise, < 1 nT for airborne magnetics, is included and negligible).
3. The residuals' spread as a function of ``d`` is the error model: the mean squared residual in bins of equal count
   along ``d``, made non-decreasing by pool-adjacent-violators (isotonic regression: the error cannot shrink with
   distance from the data), interpolated linearly between bin centres; beyond the last bin it grows with the last
   bins' slope up to the held-out readings' own standard deviation (a map knows nothing more than the mean there).
4. The error layer is that model at every map node's distance to the nearest used reading (a k-d tree), in the map's
   unit, on the map's nodes: small along the lines, larger between them, largest far from data.
5. The error's correlation length: the held-out residuals, standardised by the model, are averaged into cells of the
   map's spacing; their autocorrelation within each fold is binned by lag, and the correlation length is the lag
   where it falls below 1/e (linear between bins; the largest lag if it never does).

The layer is an estimate made on the survey's own readings: a levelling difference between line sets (e.g. the
-24 nT between Osborne's flight and tie lines) is not visible to it, and is not a per-node error either: the
matchers marginalise a constant level offset per section (``aiding.matchers.map_error.resolve_level``; its prior
1-sigma is the map's ``metadata["level_sigma"]``, else 10 % of the map's standard deviation).

Crossovers: the local error between line sets. Cross-validation within one set of lines cannot see what differs
between that set and any other line flown over the area: navigation (registration) and height differences and
along-line levelling errors. A survey's tie lines measure it: where a tie-line reading lies within half a node
spacing of a gridded line's reading (a *crossover*), the map there is anchored by the gridded line and its
cross-validated error is small, so the tie reading's misfit (map - reading, less its line's median misfit: the
level, above) is the between-line-set error. Its variance beyond the cross-validated one is fitted, as the
cross-validation's, as ``c + p^2 |grad m|^2`` (non-negative least squares over all crossovers,
:func:`fit_between_lines`: ``sqrt(c)`` a map-unit floor, ``p`` a registration error in m) and added in quadrature
everywhere on the map (:class:`ErrorModel`). The map's correlation length is then measured as the
cross-validation's (step 5) on the misfit (each line's median removed) along those lines, everywhere on them: the
map's error as a line flown across the gridded ones sees it, both parts together (it decides how many independent
pieces of evidence a section of readings holds; a levelling error correlated over kilometres, as on Rio's tie line
9160, is not the cross-validation's few hundred metres); the map states the larger of it and the
cross-validation's length (never claiming more independent evidence than either supports). The lines used are the survey's cross lines that the gridder leaves
out, or lines given only for this (``grid_survey(check_lines=...)``; a survey gridded with ``line_type = "LINE"``
gives its other lines): they never enter the grid. Without crossing lines the cross-validated sigma is multiplied
by :data:`ERROR_INFLATION` instead, a constant calibrated on one survey. ``bench/maps.py --only error_layer`` and
``--only crossover`` check the layer on tie lines (the RMS of residual / sigma should be about 1).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core.errors import InputError

FloatArray = NDArray[np.float64]

#: default number of folds
DEFAULT_FOLDS = 5
#: residuals per distance bin of the error model (at least), and the most bins
MIN_PER_BIN = 50
MAX_BINS = 24
#: Without crossing lines to measure it (module docstring, "Crossovers") the cross-validated sigma is multiplied by
#: this factor, for what cross-validation within one set of lines cannot see (navigation and height differences
#: between line sets); with them the measured between-line-set term replaces it. It covers the *local* part of the map error only: a
#: constant level offset between a flight and the map (Osborne's tie lines sit -24.3 nT, per line -17 to -30 nT,
#: below its flight lines' levelling) is not a per-node error and is the matchers' level term
#: (``aiding.matchers.map_error.resolve_level``, marginalised per section). Calibrated without test leakage
#: (``bench/maps.py --only level_split``): the RMS of the per-line demeaned (map - tie reading) / uninflated sigma
#: on the 11 odd-indexed of Osborne's 22 tie lines (sorted by id) is 1.40; checked on the other 11: 1.32 (0.95
#: with the factor); on Rio's tie lines (gridded from LINE, not tuned on): 2.46 (1.76 with the factor: Rio's
#: layer is too small, the factor is survey-specific). Until 2026-12 the factor was 1.94, calibrated on all 22
#: tie lines with their level offset in it.
ERROR_INFLATION = 1.40
#: sigma never exceeds this many standard deviations of the readings
CAP_STD = 3.0
#: cells sampled per fold for the autocorrelation (pairwise distances: n^2 / 2)
CORRELATION_SAMPLE = 2500
_E_FOLD = float(np.exp(-1.0))


@dataclass(frozen=True)
class ErrorModel:
    """1-sigma map error (map unit) as a function of the distance ``d`` to the nearest reading (m) and of the map's
    horizontal gradient magnitude ``g`` (map unit per m) at the point: ``sigma^2 = a(d) + b(d) g^2``, fitted on the
    held-out readings of a block k-fold cross-validation (module docstring). ``distance_m`` are the distance bins'
    centres, ``a`` (unit^2) and ``b`` (m^2) the fit there (non-decreasing in ``d``; ``sqrt(b)`` reads as the
    position error, m, that the map's interpolation amounts to); ``cap`` bounds sigma; ``correlation_m`` is the
    error's correlation length; ``folds``, ``block_m``, ``n`` (residuals used), ``rms`` and ``mean`` (of the
    residuals) say how it was made."""

    distance_m: FloatArray
    a: FloatArray
    b: FloatArray
    cap: float
    correlation_m: float
    folds: int
    block_m: float
    n: int
    rms: float
    mean: float
    correlation_lags_m: FloatArray = field(default_factory=lambda: np.zeros(0))
    correlation: FloatArray = field(default_factory=lambda: np.zeros(0))
    inflation: float = 1.0
    #: the between-line-set term (module docstring, "Crossovers"): sigma_x^2 = between_var + between_position_m^2 g^2
    #: (unit^2, m), fitted on ``between_points`` crossover readings of ``between_lines`` lines not gridded; 0 = none
    between_var: float = 0.0
    between_position_m: float = 0.0
    between_lines: int = 0
    between_points: int = 0
    #: the correlation length (m) of the misfit along the lines that measured the between-line-set term (NaN =
    #: none): the map's error as a line crossing the gridded ones sees it, cross-validation and between-line-set
    #: parts together; the map states the larger of it and the cross-validation's ``correlation_m``
    between_correlation_m: float = float("nan")

    @property
    def stated_correlation_m(self) -> float:
        """The correlation length the map carries (m): the larger of :attr:`between_correlation_m` (when measured)
        and the cross-validation's. Never the shorter: a shorter length claims more independent evidence per section
        of readings, and the along-line estimate from a few lines is noisy (Osborne's two halves of tie lines: 129
        and 245 m, against the cross-validation's 200 m)."""
        if not np.isfinite(self.between_correlation_m):
            return self.correlation_m
        return max(self.between_correlation_m, self.correlation_m)

    def _coef(self, d: FloatArray) -> tuple[FloatArray, FloatArray]:
        x = self.distance_m
        sa, sb = np.sqrt(self.a), np.sqrt(self.b)
        ra, rb = np.interp(d, x, sa), np.interp(d, x, sb)
        if len(x) >= 2:  # beyond the last bin: grow with the last bins' slope
            far = d > x[-1]
            dx = max(float(x[-1] - x[-2]), 1e-9)
            ra = np.where(far, sa[-1] + max((sa[-1] - sa[-2]) / dx, 0.0) * (d - x[-1]), ra)
            rb = np.where(far, sb[-1] + max((sb[-1] - sb[-2]) / dx, 0.0) * (d - x[-1]), rb)
        return ra**2, rb**2

    def sigma_at(self, distance_m: ArrayLike, gradient: ArrayLike = 0.0) -> FloatArray:
        """The model at ``distance_m`` (m) and gradient magnitude ``gradient`` (map unit / m), broadcast; NaN
        inputs give NaN."""
        d, g = np.broadcast_arrays(np.asarray(distance_m, dtype=float), np.asarray(gradient, dtype=float))
        a, b = self._coef(d)
        var = self.inflation**2 * (a + b * g**2) + self.between_var + self.between_position_m**2 * g**2
        out = np.minimum(np.sqrt(var), self.cap)
        return np.where(np.isfinite(d) & np.isfinite(g), out, np.nan)

    def describe(self) -> str:
        """One line for ``GridMap.error_source``."""
        return (
            f"block {self.folds}-fold cross-validation (verde.BlockKFold, {self.block_m:.0f} m blocks, "
            f"{self.n} held-out readings, residual RMS {self.rms:.3g}): sigma^2 = a(d) + b(d) |grad|^2 of the distance "
            f"d to the nearest reading ({self.distance_m[0]:.0f} .. {self.distance_m[-1]:.0f} m: sqrt(a) "
            f"{np.sqrt(self.a[0]):.3g} .. {np.sqrt(self.a[-1]):.3g}, sqrt(b) {np.sqrt(self.b[0]):.3g} .. "
            f"{np.sqrt(self.b[-1]):.3g} m), "
            + (
                f"plus, in quadrature, the between-line-set error at {self.between_points} crossovers of "
                f"{self.between_lines} lines not gridded: {np.sqrt(self.between_var):.3g} and "
                f"{self.between_position_m:.3g} m x |grad|; the misfit along those lines is correlated over "
                f"{self.between_correlation_m:.0f} m (cross-validation: {self.correlation_m:.0f} m; the map states "
                f"the larger)"
                if self.between_lines
                else f"times {self.inflation:g} for what one line set cannot see (no crossing lines to measure it)"
            )
        )

    def as_metadata(self) -> dict[str, object]:
        """JSON-able summary for the map's metadata."""
        return {
            "method": "block k-fold cross-validation (verde.BlockKFold), sigma^2 = a(d) + b(d) |grad|^2",
            "folds": self.folds,
            "block_m": round(self.block_m, 3),
            "held_out": self.n,
            "residual_rms": round(self.rms, 6),
            "residual_mean": round(self.mean, 6),
            "distance_m": [round(float(v), 3) for v in self.distance_m],
            "sqrt_a": [round(float(np.sqrt(v)), 6) for v in self.a],
            "sqrt_b_m": [round(float(np.sqrt(v)), 6) for v in self.b],
            "cap": round(self.cap, 6),
            "inflation": self.inflation,
            "between_lines": {
                "sigma0": round(float(np.sqrt(self.between_var)), 6),
                "position_m": round(self.between_position_m, 3),
                "lines": self.between_lines,
                "points": self.between_points,
                "correlation_m": None
                if not np.isfinite(self.between_correlation_m)
                else round(self.between_correlation_m, 3),
            },
            "stated_correlation_m": round(self.stated_correlation_m, 3),
            "correlation_m": round(self.correlation_m, 3),
            "correlation_lags_m": [round(float(v), 3) for v in self.correlation_lags_m],
            "correlation": [round(float(v), 4) for v in self.correlation],
        }


def nearest_distance(points_ne: FloatArray, query_ne: FloatArray) -> FloatArray:
    """Distance (m) from each query (N, 2) to the nearest of ``points_ne`` (M, 2), both northing/easting m."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(points_ne).query(query_ne, k=1)
    return np.asarray(d, dtype=float)


def block_folds(
    coords_ne: FloatArray, block_m: float, folds: int, seed: int, azimuth_rad: float | None = None
) -> list[NDArray[np.int64]]:
    """Held-out index sets of a spatial block k-fold split (``verde.BlockKFold``, shuffled; with thousands of blocks the folds hold about equal numbers of readings without verde's balancing, which is quadratic in the blocks) of points at
    ``coords_ne`` (N, 2) m. With ``azimuth_rad`` (survey lines' direction from north) the blocks are squares in the
    lines' own along/across frame."""
    import verde

    n, e = coords_ne[:, 0], coords_ne[:, 1]
    if azimuth_rad is not None:
        ca, sa = np.cos(azimuth_rad), np.sin(azimuth_rad)
        n, e = n * ca + e * sa, -n * sa + e * ca
    kf = verde.BlockKFold(spacing=block_m, n_splits=folds, shuffle=True, random_state=seed, balance=False)
    return [np.asarray(test, dtype=np.int64) for _, test in kf.split(np.c_[e, n])]


def _isotonic(y: FloatArray, w: FloatArray) -> FloatArray:
    """Weighted least-squares non-decreasing fit of ``y`` (pool adjacent violators)."""
    vals: list[float] = []
    wts: list[float] = []
    cnt: list[int] = []
    for yi, wi in zip(y, w, strict=True):
        vals.append(float(yi))
        wts.append(float(wi))
        cnt.append(1)
        while len(vals) > 1 and vals[-2] > vals[-1]:
            wsum = wts[-2] + wts[-1]
            v = (vals[-2] * wts[-2] + vals[-1] * wts[-1]) / wsum
            c = cnt[-2] + cnt[-1]
            del vals[-1], wts[-1], cnt[-1]
            vals[-1], wts[-1], cnt[-1] = v, wsum, c
    return np.repeat(vals, cnt)


def fit_distance_model(
    distance_m: FloatArray, gradient: FloatArray, residual: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Bin centres (median distance, m) and the coefficients ``a`` (unit^2), ``b`` (m^2) of ``E[r^2] = a + b g^2``
    in equal-count bins of distance (non-negative least squares per bin, then each made non-decreasing in distance
    by pool-adjacent-violators; module docstring, step 3)."""
    from scipy.optimize import nnls

    ok = np.isfinite(distance_m) & np.isfinite(residual) & np.isfinite(gradient)
    d, g, r = distance_m[ok], gradient[ok], residual[ok]
    if d.size < 2 * MIN_PER_BIN:
        raise InputError(
            f"map error layer: only {d.size} held-out readings were predicted by the folds; need at least "
            f"{2 * MIN_PER_BIN} (a larger survey, or error_folds=0)"
        )
    nb = int(min(MAX_BINS, d.size // MIN_PER_BIN))
    o = np.argsort(d, kind="stable")
    d, g, r = d[o], g[o], r[o]
    edges = np.linspace(0, d.size, nb + 1).astype(int)
    centre, aa, bb = [], [], []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        gs = g[lo:hi] / max(float(np.std(g[lo:hi])), 1e-300)  # scaled for the solver's conditioning
        A = np.c_[np.ones(hi - lo), gs**2]
        coef, _ = nnls(A, r[lo:hi] ** 2)
        centre.append(float(np.median(d[lo:hi])))
        aa.append(coef[0])
        bb.append(coef[1] / max(float(np.std(g[lo:hi])), 1e-300) ** 2)
    cnt = np.diff(edges).astype(float)
    a_fit = _isotonic(np.asarray(aa), cnt)
    b_fit = _isotonic(np.asarray(bb), cnt)
    c = np.asarray(centre)
    keep = np.r_[np.diff(c) > 0, True]  # equal centres would make np.interp ill-defined: keep the last of each
    return c[keep], a_fit[keep], b_fit[keep]


#: crossovers needed (at least) for the between-line-set term, and lines with at least this many crossovers each
MIN_CROSSOVERS = 2 * MIN_PER_BIN
MIN_CROSSOVERS_PER_LINE = 10


def fit_between_lines(
    residual: FloatArray, line: NDArray[np.int64], cv_variance: FloatArray, gradient: FloatArray
) -> tuple[float, float, int, int] | None:
    """The between-line-set term (module docstring, "Crossovers") from crossover misfits ``residual`` (map - reading,
    map unit) of readings on lines ``line``, with the cross-validated error variance ``cv_variance`` (unit^2,
    uninflated) and the map's gradient magnitude ``gradient`` (unit / m) at them: each line's median misfit (its
    level) is removed, then ``r^2 - cv_variance = c + p^2 g^2`` is fitted by non-negative least squares. Returns
    ``(c, p, lines, points)`` (unit^2, m) or None with fewer than :data:`MIN_CROSSOVERS` crossovers on lines with
    at least :data:`MIN_CROSSOVERS_PER_LINE` each, or fewer than two such lines."""
    from scipy.optimize import nnls

    ok = np.isfinite(residual) & np.isfinite(cv_variance) & np.isfinite(gradient)
    r, ln, v, g = residual[ok], np.asarray(line)[ok], cv_variance[ok], gradient[ok]
    keep = np.zeros(r.size, dtype=bool)
    rd = np.zeros(r.size)
    used = 0
    for lid in np.unique(ln):
        m = ln == lid
        if m.sum() < MIN_CROSSOVERS_PER_LINE:
            continue
        rd[m] = r[m] - np.median(r[m])
        keep |= m
        used += 1
    if used < 2 or keep.sum() < MIN_CROSSOVERS:
        return None
    y = rd[keep] ** 2 - v[keep]
    gs = max(float(np.std(g[keep])), 1e-300)  # scaled for the solver's conditioning
    coef, _ = nnls(np.c_[np.ones(keep.sum()), (g[keep] / gs) ** 2], y)
    return float(coef[0]), float(np.sqrt(coef[1]) / gs), used, int(keep.sum())


def correlation_length(
    coords_ne: FloatArray,
    z: FloatArray,
    fold: NDArray[np.int64],
    cell_m: float,
    max_lag_m: float,
    rng: np.random.Generator,
    monotone: bool = False,
) -> tuple[float, FloatArray, FloatArray]:
    """Correlation length (m) of the standardised residuals ``z`` at ``coords_ne`` (module docstring, step 5):
    ``(length, lags, correlation)`` with the zero lag first (correlation 1). ``fold`` gives each residual's fold
    (pairs are taken within a fold: the errors of one map). ``monotone``: the binned correlation is first made
    non-increasing in lag (pool-adjacent-violators weighted by the pairs per bin), for few residuals whose binned
    correlation is noisy (a first crossing of 1/e would then be a crossing of the noise)."""
    from scipy.spatial.distance import pdist

    edges = np.geomspace(0.5 * cell_m, max_lag_m, 17)
    num = np.zeros(len(edges) - 1)
    den = np.zeros(len(edges) - 1)
    var_sum, var_n = 0.0, 0
    for f in np.unique(fold):
        m = fold == f
        # cell means of the fold's residuals (errors shorter than the map's spacing do not matter to it)
        key_n = np.floor(coords_ne[m, 0] / cell_m).astype(np.int64)
        key_e = np.floor(coords_ne[m, 1] / cell_m).astype(np.int64)
        _, inv = np.unique(key_n * 1_000_003 + key_e, return_inverse=True)
        cnt = np.bincount(inv)
        cn = np.bincount(inv, coords_ne[m, 0]) / cnt
        ce = np.bincount(inv, coords_ne[m, 1]) / cnt
        cz = np.bincount(inv, z[m]) / cnt
        if len(cz) > CORRELATION_SAMPLE:
            pick = rng.choice(len(cz), CORRELATION_SAMPLE, replace=False)
            cn, ce, cz = cn[pick], ce[pick], cz[pick]
        if len(cz) < 3:
            continue
        cz = cz - cz.mean()
        var_sum += float(np.sum(cz**2))
        var_n += len(cz)
        h = pdist(np.c_[cn, ce])
        i, j = np.triu_indices(len(cz), k=1)
        b = np.searchsorted(edges, h, side="right") - 1
        ok = (b >= 0) & (b < len(num))
        num += np.bincount(b[ok], (cz[i] * cz[j])[ok], minlength=len(num))
        den += np.bincount(b[ok], minlength=len(num))
    valid = den > 10
    if var_n == 0 or valid.sum() < 2:
        return float(max_lag_m), np.zeros(0), np.zeros(0)
    centre = np.r_[0.0, np.sqrt(edges[:-1] * edges[1:])[valid]]
    corr = np.r_[1.0, (num[valid] / den[valid]) / (var_sum / var_n)]
    if monotone:
        corr[1:] = -_isotonic(-corr[1:], den[valid].astype(float))
    below = np.flatnonzero(corr < _E_FOLD)
    if below.size == 0:
        return float(max_lag_m), centre, corr
    k = int(below[0])
    x0, x1, y0, y1 = centre[k - 1], centre[k], corr[k - 1], corr[k]
    length = x0 + (y0 - _E_FOLD) / (y0 - y1) * (x1 - x0)
    return float(max(length, 0.5 * cell_m)), centre, corr


def cross_validate(
    coords_ne: FloatArray,
    values: FloatArray,
    regrid: Callable[[NDArray[np.bool_], NDArray[np.int64], float], FloatArray],
    node_distance_m: FloatArray,
    spacing_m: float,
    gradient: FloatArray,
    *,
    folds: int = DEFAULT_FOLDS,
    block_m: float | None = None,
    azimuth_rad: float | None = None,
    seed: int = 0,
    inflation: float = ERROR_INFLATION,
) -> ErrorModel:
    """Estimate the error model (module docstring) of a map gridded from readings ``values`` at ``coords_ne``
    (N, 2) northing/easting m. ``regrid(train_mask, test_index, max_gap_m)`` grids the readings where
    ``train_mask`` is True and returns that map's values at the readings ``test_index`` (NaN off that map);
    ``node_distance_m`` are the full map's nodes' distances to the nearest reading (for the default block size);
    ``spacing_m`` the map's node spacing; ``gradient`` (N,) the full map's gradient magnitude (unit / m) at the
    readings."""
    if folds < 2:
        raise InputError(f"map error layer: need at least 2 folds, got {folds}")
    dn = node_distance_m[np.isfinite(node_distance_m)]
    if block_m is None:
        block_m = 2.0 * float(np.percentile(dn, 90)) if dn.size else 4.0 * spacing_m
        block_m = max(block_m, 2.0 * spacing_m)
    rng = np.random.default_rng(seed)
    held = block_folds(coords_ne, block_m, folds, seed, azimuth_rad)
    res = np.full(len(values), np.nan)
    dist = np.full(len(values), np.nan)
    fold_of = np.full(len(values), -1, dtype=np.int64)
    for k, test in enumerate(held):
        train = np.ones(len(values), dtype=bool)
        train[test] = False
        if train.sum() < 4 or test.size == 0:
            continue
        res[test] = regrid(train, test, 1.5 * block_m) - values[test]
        dist[test] = nearest_distance(coords_ne[train], coords_ne[test])
        fold_of[test] = k
    ok = np.isfinite(res) & np.isfinite(dist) & np.isfinite(gradient)
    centre, a, b = fit_distance_model(dist[ok], gradient[ok], res[ok])
    cap = CAP_STD * float(np.std(values[ok]))
    model = ErrorModel(centre, a, b, cap, float("nan"), folds, float(block_m), int(ok.sum()), 0.0, 0.0)
    z = res[ok] / np.maximum(model.sigma_at(dist[ok], gradient[ok]), 1e-12)
    corr_len, lags, corr = correlation_length(
        coords_ne[ok], z, fold_of[ok], spacing_m, max(20.0 * block_m, 40.0 * spacing_m), rng
    )
    return ErrorModel(
        centre,
        a,
        b,
        cap,
        corr_len,
        folds,
        float(block_m),
        int(ok.sum()),
        float(np.sqrt(np.mean(res[ok] ** 2))),
        float(np.mean(res[ok])),
        lags,
        corr,
        float(inflation),
    )
