"""Helpers shared by the gravity-matching baselines (TERCOM, ICCP, the point-mass filter) and PMHT-MM.

* :func:`track_window` - a batch window's INS-indicated track in frame metres, its gates, the reading variance
  with the map's error (``map_error.resolve_map_error``) and the INS drift within the batch.
* :func:`adds_information` / :func:`information_refusal` - the rule for issuing a fix (issue 16): a fix is issued
  whenever fusing it would shrink the prior's covariance (its information beyond the search gate's own is at least
  ``MIN_INFORMATION_RATIO`` of the prior's in some direction: whatever the prior, and also when the fix is wider than
  the prior), and refused as "flat map" only when it adds none. Until 2026-12 a fix had to be tighter than the prior
  in some direction: on the QLD West grid (precision IMU, 1 mGal, 2 runs) about every second batch was refused as
  "flat map" (TERCOM 41 of 86) although fusing its fix would still have shrunk the prior (97 % issued now).

Map error and its correlation (ours, stated): reading ``t`` has variance ``s_t^2 = sigma^2 + b sigma_map,t^2``,
``sigma_map,t`` the map's 1-sigma error at the INS position; ``b = clip(ell / ds, 1, T)`` with ``ell`` the map
error's correlation length and ``ds`` the median along-track distance between readings: readings closer than one
correlation length share their map error, so their map-error part counts as ``b`` times larger (each block of
``b`` readings carries the map-error information of one).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ...core.protocols import FieldMap, MatchWindow
from ...core.types import Fix
from ._local import WorkFrame, make_frame, map_components, sigma_window
from .map_error import resolve_map_error

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class TrackWindow:
    """The last ``T`` readings of a window in the frame about the INS position of the last reading.

    ``t`` (T,) s; ``z`` (T, c) readings; ``x_ins`` (T, 2) INS north/east m; ``cov`` (T, 2, 2) its covariance m^2;
    ``half`` (T, 2) gate half-widths m; ``good`` (T,) finite readings; ``s2`` (T,) reading variance (sensor + map
    error, map unit^2); ``rel_drift`` (T,) m the INS drift of scan t relative to the last scan,
    ``sqrt(sigma_T^2 - sigma_t^2)`` (the variance the INS adds between them, increments taken as independent); ``sensor_sigma`` the readings' own sigma; ``map_error_source`` where the map error
    came from (``map_error.MapErrorModel.source``)."""

    frame: WorkFrame
    t: FloatArray
    z: FloatArray
    x_ins: FloatArray
    cov: FloatArray
    half: FloatArray
    good: NDArray[np.bool_]
    s2: FloatArray
    rel_drift: FloatArray
    sensor_sigma: float
    map_error_source: str


def track_window(
    window: MatchWindow,
    fmap: FieldMap,
    batch: int,
    gate_sigma: float,
    window_floor_m: float,
    map_sigma: float | None = None,
    correlation_m: float | None = None,
) -> TrackWindow | str:
    """The window's last ``batch`` readings as a :class:`TrackWindow`, or the reason there is none (NaN readings,
    non-finite INS positions or covariances, wrong number of components)."""
    rd = window.readings
    T = min(int(batch), len(rd))
    if T < 2:
        return f"need at least 2 readings, got {T}"
    sl = slice(len(rd) - T, len(rd))
    ncomp = map_components(fmap)
    z = np.asarray(rd.value, dtype=float)[sl].reshape(T, -1)
    if z.shape[1] != ncomp:
        return f"reading has {z.shape[1]} components, map has {ncomp}"
    good = np.all(np.isfinite(z), axis=1)
    if good.sum() < 2:
        return "fewer than 2 finite readings (NaN)"
    lat, lon = np.asarray(window.lat, float)[sl], np.asarray(window.lon, float)[sl]
    if not (np.all(np.isfinite(lat)) and np.all(np.isfinite(lon))):
        return "INS positions not finite"
    cov = np.asarray(window.cov_ne, float)[sl]
    half = np.array([sigma_window(c, gate_sigma, window_floor_m) for c in cov])
    if not np.all(np.isfinite(half)):
        return "prior covariance not finite"
    frame = make_frame(fmap, float(lat[-1]), float(lon[-1]))
    dn, de = frame.to_ne(lat, lon)
    x_ins = np.column_stack([dn, de])
    s2, source = reading_variance(fmap, lat, lon, x_ins, float(rd.sigma), map_sigma, correlation_m)
    var_ins = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
    growth2 = np.maximum(np.diff(var_ins), 0.0)  # variance the INS adds between scans (m^2)
    rel = np.sqrt(np.append(np.cumsum(growth2[::-1])[::-1], 0.0))
    return TrackWindow(frame, np.asarray(rd.t, float)[sl], z, x_ins, cov, half, good, s2, rel, float(rd.sigma), source)


def reading_variance(
    fmap: FieldMap,
    lat: FloatArray,
    lon: FloatArray,
    x_ne: FloatArray,
    sensor_sigma: float,
    map_sigma: float | None = None,
    correlation_m: float | None = None,
) -> tuple[FloatArray, str]:
    """Per-reading variance ``sigma^2 + b sigma_map^2`` (map unit^2, (T,)) of readings at ``lat``, ``lon`` (rad; their
    frame positions ``x_ne`` (T, 2) m give the along-track spacing) and where the map error came from (module
    docstring; ``map_error.resolve_map_error`` with the matcher's ``map_sigma`` / ``correlation_m`` options)."""
    me = resolve_map_error(fmap, map_sigma, correlation_m)
    sig_m = np.asarray(me.sigma_at(lat, lon), float)
    sig_m = np.where(np.isfinite(sig_m), sig_m, 0.0)
    ds = np.hypot(*np.diff(np.asarray(x_ne, float), axis=0).T)
    ds_med = float(np.median(ds)) if ds.size else 0.0
    ell = float(me.correlation_m)
    b = float(np.clip(ell / ds_med, 1.0, len(sig_m))) if (np.isfinite(ell) and ell > 0 and ds_med > 0) else 1.0
    return float(sensor_sigma) ** 2 + b * sig_m**2, me.source


#: smallest information a fix must add, as a fraction of the prior's in its best direction (``adds_information``):
#: fusing it shrinks the prior's variance there by at least 1 - 1 / (1 + 0.05) = 4.8 %
MIN_INFORMATION_RATIO = 0.05


def information_ratio(cov_fix: FloatArray, cov_prior: FloatArray, gate_half: FloatArray | None = None) -> float:
    """Largest eigenvalue of ``P^1/2 (C^-1 - B^-1) P^1/2``: the readings' information in the fix (covariance ``C``
    (2, 2) m^2) beyond the search gate's own, relative to the prior's (``P`` (2, 2) m^2), in its best direction.

    ``B = diag(h_n^2, h_e^2) / 3`` is the variance of a uniform density over a gate of half-widths ``gate_half``
    (h_n, h_e) m: what a matcher whose posterior is confined to the gate (TERCOM's offset grid, the point masses)
    returns on a flat map, so its fix covariance holds the gate's information too; ``None``: no gate term (a
    covariance from the readings alone). 0 where the fix adds nothing (or the prior has no uncertainty left in some
    direction); fusing the fix shrinks the prior's variance by ``1 - 1 / (1 + ratio)`` in its best direction."""
    P = 0.5 * (np.asarray(cov_prior, float) + np.asarray(cov_prior, float).T)
    C = 0.5 * (np.asarray(cov_fix, float) + np.asarray(cov_fix, float).T)
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(C))):
        return 0.0
    ev, V = np.linalg.eigh(P)
    if ev[0] <= 0:
        return 0.0  # a prior without uncertainty in some direction: nothing to add there
    cev, CV = np.linalg.eigh(C)
    if cev[0] <= 0:
        return float("inf") if cev[-1] > 0 else 0.0
    J = (CV / cev) @ CV.T
    if gate_half is not None:
        h = np.asarray(gate_half, float)
        J = J - np.diag(3.0 / np.maximum(h, 1e-9) ** 2)
    S = V * np.sqrt(ev)  # P^1/2 up to a rotation: S' J S has the eigenvalues of P^1/2 J P^1/2
    return float(max(np.linalg.eigvalsh(S.T @ J @ S)[-1], 0.0))


def adds_information(
    cov_fix: FloatArray,
    cov_prior: FloatArray,
    gate_half: FloatArray | None = None,
    min_ratio: float = MIN_INFORMATION_RATIO,
) -> bool:
    """True when fusing the fix (covariance ``cov_fix`` (2, 2) m^2) would shrink the prior ``cov_prior`` (2, 2)
    m^2: :func:`information_ratio` (beyond the gate of half-widths ``gate_half`` m, if given) at least
    ``min_ratio``. A fix tighter than the prior in some direction always passes (ratio > 1 - 3 P / h^2 > 0.8 for
    a gate of 4 prior sigmas); a fix wider than the prior everywhere passes while it still carries information."""
    return information_ratio(cov_fix, cov_prior, gate_half) >= min_ratio


def information_refusal(
    t: float,
    cov_fix: FloatArray,
    cov_prior: FloatArray,
    source: str,
    score: float,
    gate_half: FloatArray | None = None,
) -> Fix:
    """The "no fix" of a fix that adds no information over its prior (reason names the ratio and both sigmas)."""
    sf = np.sqrt(np.maximum(np.linalg.eigvalsh(0.5 * (cov_fix + cov_fix.T)), 0.0))
    sp = np.sqrt(np.maximum(np.linalg.eigvalsh(0.5 * (cov_prior + cov_prior.T)), 0.0))
    r = information_ratio(cov_fix, cov_prior, gate_half)
    return Fix.no_fix(
        t,
        f"flat map: the fix adds no information over the prior (information ratio {r:.2g} < "
        f"{MIN_INFORMATION_RATIO:g}; fix sigmas {sf[0]:.3g} / {sf[-1]:.3g} m, prior sigmas {sp[0]:.3g} / "
        f"{sp[-1]:.3g} m)",
        source,
        score,
    )


def offset_grid(
    half_n: float, half_e: float, step: float, max_nodes: int
) -> tuple[FloatArray, FloatArray, float, float]:
    """Offsets ``(K,)`` north, ``(K,)`` east (m) of a regular grid spanning ``[-half, half]`` on each axis with about
    ``step`` spacing (coarsened so it has at most ``max_nodes`` nodes), and the spacings ``(D_n, D_e)`` m."""
    step = max(float(step), 1e-3)
    while (2 * np.ceil(half_n / step) + 1) * (2 * np.ceil(half_e / step) + 1) > max_nodes:
        step *= 1.2
    kn, ke = max(int(np.ceil(half_n / step)), 1), max(int(np.ceil(half_e / step)), 1)
    on, oe = np.linspace(-half_n, half_n, 2 * kn + 1), np.linspace(-half_e, half_e, 2 * ke + 1)
    ON, OE = np.meshgrid(on, oe, indexing="ij")
    return ON.ravel(), OE.ravel(), float(on[1] - on[0]), float(oe[1] - oe[0])


def local_gradient2(frame: WorkFrame, n: FloatArray, e: FloatArray, h: float) -> FloatArray:
    """Squared horizontal gradient norm (unit^2/m^2, summed over components) at frame points, by central
    differences of step ``h`` m; 0 where the map has no value."""
    n = np.asarray(n, float)
    e = np.asarray(e, float)
    gn = frame.sample(n + h, e) - frame.sample(n - h, e)
    ge = frame.sample(n, e + h) - frame.sample(n, e - h)
    g2 = (gn.reshape(n.size, -1) ** 2 + ge.reshape(n.size, -1) ** 2).sum(axis=1) / (2 * h) ** 2
    return np.nan_to_num(g2)


def misfit_threshold(n: int, alpha: float) -> float:
    """Mean normalised squared misfit per reading above which ``n`` readings disagree with the map at false-alarm
    rate ``alpha``: ``chi2_{1-alpha}(n) / n`` (chi-square with ``n`` degrees of freedom; the fitted offset's two
    are not taken off, which makes the test slightly lenient). ``inf`` for ``n < 1``."""
    from scipy.stats import chi2

    if n < 1:
        return float("inf")
    return float(chi2.ppf(1.0 - float(alpha), int(n)) / int(n))


#: a rival peak counts when its likelihood density is at least this fraction of the best one (``rival_cover``)
RIVAL_PEAK_RATIO = 0.01


def rival_cover(
    frame: WorkFrame,
    y: FloatArray,
    z: FloatArray,
    v: FloatArray,
    d_fix: FloatArray,
    half: tuple[float, float],
    step: float,
    max_offsets: int,
    min_separation_m: float,
    peak_ratio: float = RIVAL_PEAK_RATIO,
) -> tuple[FloatArray, int]:
    """Covariance (2, 2) m^2 covering the rival minima of a batch match, and how many there are.

    The batch's registered track ``y`` (T, 2) frame m (readings ``z`` (T, c), variances ``v`` (T,) map unit^2) is
    translated by every offset ``d - d_fix`` of a regular grid over the gate (half-widths ``half`` m about the INS
    position, spacing about ``step`` m, at most ``max_offsets`` nodes; ``d_fix`` (2,) m the fix's own offset from
    the INS) and its Gaussian likelihood ``prod_t N(z_t; m(y_t + d - d_fix), v_t)`` evaluated; the rivals are then
    :func:`rival_moment`'s. A single best match's linearised covariance holds its own peak's width only; when the
    batch fits several places of the gate almost equally (a long INS error against a map whose features repeat)
    the fix may sit on the wrong one, and this term makes its covariance say so."""
    on, oe, Dn, De = offset_grid(float(half[0]), float(half[1]), step, max_offsets)
    K = on.size
    ll = np.zeros(K)
    sh_n, sh_e = on - float(d_fix[0]), oe - float(d_fix[1])
    for t in range(y.shape[0]):
        m = frame.sample(y[t, 0] + sh_n, y[t, 1] + sh_e).reshape(K, -1)
        ll -= 0.5 * np.sum((m - z[t]) ** 2, axis=1) / v[t]
    return rival_moment(ll, sh_n, sh_e, (Dn, De), min_separation_m, peak_ratio)


def rival_moment(
    ll: FloatArray,
    dn: FloatArray,
    de: FloatArray,
    spacing: tuple[float, float],
    min_separation_m: float,
    peak_ratio: float = RIVAL_PEAK_RATIO,
) -> tuple[FloatArray, int]:
    """Second moment (2, 2) m^2 about the fix of the rival peaks of a log-likelihood ``ll`` (K,) over a regular
    offset grid (:func:`offset_grid`'s order; ``dn``, ``de`` (K,) m each node's offset from the fix, ``spacing``
    (D_n, D_e) m), and how many rivals there are. Rivals are the likelihood's local maxima (3 x 3) at least
    ``min_separation_m`` from the fix holding at least ``peak_ratio`` of the best density; each is weighted by its
    share of the peaks' density (the fix's peak, the best density within ``min_separation_m`` of it, included):
    bayes_grid's ``cover_rivals`` for a batch. Zero with no rival (or no finite likelihood)."""
    from scipy import ndimage

    nn, ne = int(np.unique(dn).size), int(np.unique(de).size)
    Dn, De = float(spacing[0]), float(spacing[1])
    ll = np.where(np.isfinite(ll), ll, -np.inf)
    if not np.any(np.isfinite(ll)):
        return np.zeros((2, 2)), 0
    lk = np.exp(ll - np.max(ll)).reshape(nn, ne)
    dn, de = np.asarray(dn, float).reshape(nn, ne), np.asarray(de, float).reshape(nn, ne)
    far = dn**2 + de**2 >= float(min_separation_m) ** 2
    if np.all(far):  # the fix is off the grid's nodes: its peak is the nearest node's neighbourhood
        far = dn**2 + de**2 > np.min(dn**2 + de**2) + Dn**2 + De**2
    lmax = (lk == ndimage.maximum_filter(lk, size=3, mode="constant", cval=0.0)) & (lk >= peak_ratio)
    rivals = lmax & far
    if not np.any(rivals):
        return np.zeros((2, 2)), 0
    dens_fix = float(np.max(lk[~far])) if np.any(~far) else 0.0
    dens = lk[rivals]
    w = dens / (dens_fix + dens.sum())
    d = np.column_stack([dn[rivals], de[rivals]])
    return (d * w[:, None]).T @ d, int(rivals.sum())


def drift_misfit_variance(fmap: FieldMap, x_ins: FloatArray, rel_drift: FloatArray) -> FloatArray | None:
    """Variance (T,) map unit^2 a rigid match of the batch must allow each reading for the INS drift relative to
    the last reading (``rel_drift`` (T,) m, 1 sigma per axis; ``x_ins`` (T, 2) frame m the INS track), through the
    map's own field (:func:`.map_error.field_variogram`, ``gamma``), or None for a map that is not a grid.

    Reading ``t`` is displaced by ``delta_t ~ N(0, r_t^2 I)`` from where the rigidly moved track puts it, so its
    misfit gains ``e_t = m(x_t + delta_t) - m(x_t)``, of variance ``D_t = E 2 gamma(|delta_t|)`` (the variogram,
    not the local gradient: the drift may exceed the map's correlation length, where a gradient says nothing). The
    drift is one velocity error held over the batch, so these misfits are correlated along the track: for two
    readings ``h`` apart displaced alike by ``delta`` (across the track; ``delta = sqrt(r_t r_s)``) the correlation
    of ``e`` is ``rho_ts = (2 gamma(sqrt(h^2 + delta^2)) - 2 gamma(h)) / 2 gamma(delta)``, and ``D_t`` is counted
    ``b_t = sum_s rho_ts`` times (clipped to ``[1, T]``: a diagonal likelihood then gives a common error the
    information of the correlated block, as :func:`reading_variance` does for the map error). Why (issue 16):
    with the tactical IMU on QLD West the INS track deforms by 3-11 km over a 30-reading batch on a 0.9 km map;
    replaying the batches of three runs, TERCOM's fixes whose truth lay in the gate had a NEES of 21 mean with the
    drift through the local gradient at the best offset, 20.6 with the variogram alone (``b = 1``), 1.6 with
    ``b``; on the Gulf of Alaska (precision IMU, 4 runs) ``b`` from the field's own correlation instead of the
    misfits' made the fixes conservative (NEES 0.82, 136 of 172 issued; with ``rho_ts``: 0.99, 161)."""
    from .map_error import field_variogram

    vg = field_variogram(fmap)
    if vg is None:
        return None
    x = np.asarray(x_ins, float)
    r = np.asarray(rel_drift, float)
    D = vg.drift_variance(r)
    h = np.hypot(x[:, None, 0] - x[None, :, 0], x[:, None, 1] - x[None, :, 1])
    dl = np.sqrt(r[:, None] * r[None, :])
    den = 2.0 * vg.at(dl)
    num = 2.0 * vg.at(np.hypot(h, dl)) - 2.0 * vg.at(h)
    rho = np.where(den > 0, np.clip(num / np.where(den > 0, den, 1.0), 0.0, 1.0), (h == 0).astype(float))
    b = np.clip(np.sum(rho, axis=1), 1.0, float(len(x)))
    return D * b


def loewner_max(A: FloatArray, B: FloatArray, big: float = np.inf, information: bool = False) -> FloatArray:
    """A covariance no smaller than ``A`` and ``B`` (2, 2) in the Loewner order: in the basis that whitens ``A``,
    each eigenvalue of ``B`` raised to at least 1 (``A`` where it is larger, ``B`` where that is). ``information``:
    ``B`` is an information matrix (its inverse the covariance; it may be singular). Variances capped at ``big``."""
    ev, V = np.linalg.eigh(0.5 * (A + A.T))
    L = V * np.sqrt(np.maximum(ev, 1e-12 * max(float(ev[-1]), 1e-300)))  # A = L L'
    if information:
        mu, W = np.linalg.eigh(L.T @ B @ L)
        lam = 1.0 / np.maximum(np.minimum(mu, 1.0), 1e-300)
    else:
        Li = np.linalg.inv(L)
        lam, W = np.linalg.eigh(Li @ B @ Li.T)
        lam = np.maximum(lam, 1.0)
    out = L @ ((W * np.minimum(lam, big / max(float(ev[0]), 1e-300))) @ W.T) @ L.T
    return 0.5 * (out + out.T)


#: a peak's region: where the log-likelihood is within this of its maximum (the 99.9 % region of a 2-D Gaussian,
#: chi-square(2) quantile 13.8, halved; as the likelihood matchers' ``HPD_LOG_DROP``)
EDGE_LOG_DROP = 0.5 * 13.8155


def edge_normals(ll: FloatArray, k_best: int, drop: float = EDGE_LOG_DROP) -> FloatArray:
    """Unit outward normals (J, 2) north/east of the borders of a regular ``(m_n, m_e)`` offset grid (``ll`` its
    log-likelihood, rows north from the most negative offset, columns east) that the best peak's region touches:
    the connected region (8-neighbours) about node ``k_best`` (flat index) where ``ll`` is within ``drop`` (default
    :data:`EDGE_LOG_DROP`, the 99.9 % region) of its maximum. Where it touches a border the likelihood goes on beyond the grid and its
    moments there are truncated. Empty (0, 2) when it touches none."""
    from scipy import ndimage

    ll = np.asarray(ll, float)
    top = float(ll.flat[k_best])
    mask = np.isfinite(ll) & (ll >= top - float(drop))
    lab, _ = ndimage.label(mask, structure=np.ones((3, 3), dtype=bool))
    main = lab.flat[k_best]
    if main == 0:
        return np.zeros((0, 2))
    sides = ((lab[0] == main, (-1.0, 0.0)), (lab[-1] == main, (1.0, 0.0)),
             (lab[:, 0] == main, (0.0, -1.0)), (lab[:, -1] == main, (0.0, 1.0)))  # fmt: skip
    out = [n for hit, n in sides if np.any(hit)]
    return np.array(out, float).reshape(-1, 2)


def truncated_sides(normals: FloatArray, cov: FloatArray, half: FloatArray) -> FloatArray:
    """The border normals (J', 2) among ``normals`` (:func:`edge_normals`: the likelihood's peak region runs out of
    the gate through them) along which a fix of covariance ``cov`` (2, 2) m^2 claims to know more than the gate of
    half-widths ``half`` (2,) m does: its information along ``n``, ``n' C^-1 n``, exceeds ``1 / (n . half)^2`` (the
    position along ``n`` known to better than the gate's half-width, the other direction held). Beyond such a
    border the likelihood is unknown, so what the fix claims along ``n`` rests on a truncated surface (a mode cut by
    the border, or the true mode outside it). A ridge that runs out of the gate along the direction the fix leaves
    open (its information across the ridge only) is not truncated in that sense; the information is used, not the
    marginal variance, so that a long ridge tilted towards the border does not hide a narrow direction crossing it
    (a slightly tilted along-track ridge is then truncated too: on Rio most batches, module docstring of
    :mod:`.pmht`, "Search gate")."""
    n = np.asarray(normals, float).reshape(-1, 2)
    if n.size == 0:
        return n
    c = 0.5 * (np.asarray(cov, float) + np.asarray(cov, float).T)
    ev, V = np.linalg.eigh(c)
    info = (V / np.maximum(ev, 1e-300)) @ V.T
    h = np.abs(n @ np.asarray(half, float))
    return n[np.einsum("ji,ik,jk->j", n, info, n) * h**2 > 1.0]
