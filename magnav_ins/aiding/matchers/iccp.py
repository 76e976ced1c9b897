"""ICCP: iterative closest contour point (Besl & McKay 1992, "A method for registration of 3-D shapes", IEEE PAMI 14(2)
- the ICP iteration; Kamgar-Parsi & Kamgar-Parsi 1999, "Vehicle localization on gravity maps", Proc. SPIE 3693 -
contours of the measured field as the point sets to register to).

Each reading ``z_t`` of a batch lies, on a perfect map, on the level line (contour) ``m(x) = z_t`` through the
true position; the INS-indicated track ``p_t`` (the last ``batch`` readings) is off by a rigid motion. Iterate:

1. For each scan, the closest point ``q_t`` of its contour to the current transformed track point
   ``y_t = R(theta) (p_t - c) + c + tr`` (``c`` the track centroid); the contours are extracted once per batch from
   the map sampled on a grid over the gate (level crossings on the grid edges, linearly interpolated).
2. The rigid transform (``rotation=True``: rotation and translation; else translation only) minimising
   ``sum_t |R (p_t - c) + c + tr - q_t|^2`` in closed form (2-D Procrustes / Kabsch).
3. Stop when no transformed point moves by more than ``tolerance_m`` or after ``iterations``.

The fix is the transformed last point ``y_T``. ICP converges to the nearest local optimum: with an initial error
larger than the contour spacing it can lock onto a wrong set of contours (the baseline's known weakness).

Fix covariance (ours; ICCP reports none): the linearised information of the readings about the transform
``beta = (tr_n, tr_e, theta)``: ``I = sum_t a_t a_t' / v_t``, ``a_t = [g_t; g_t . R J (p_t - c)]`` with ``g_t`` the map
gradient at ``y_t`` and ``J`` the 90-degree rotation, ``v_t = s_t^2 + |g_t|^2 (h^2 / 12 + r_t^2)`` (``h`` the contour
sampling step, ``r_t`` the INS drift relative to the last scan), scaled by ``max(1, chi2)`` (the mean normalised
misfit ``(z_t - m(y_t))^2 / v_t``), carried to ``y_T`` by ``A = [I_2, R J (p_T - c)]``. That covariance holds the width of the fix's own minimum only:
with ``cover_rivals`` (default) it is widened by the second moment about the fix of the other minima of the
registered track's translation likelihood over the gate (:func:`._batch.rival_cover`; issue 16: with the tactical
IMU on QLD West ICCP's fixes sat on wrong minima with sigmas of a few hundred m). No fix: "flat map" when the
level lines of fewer than 3 readings cross the gate or the fix adds no information over the prior
(:func:`._batch.adds_information`); "diverged" when the misfit exceeds ``max_chi2`` or the fix leaves the gate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from ...core.errors import ConfigError
from ...core.protocols import FieldMap, MatchWindow
from ...core.types import Fix
from ._batch import adds_information, information_refusal, local_gradient2, rival_cover, track_window
from ._local import map_components, spacing_of, window_axes

FloatArray = NDArray[np.float64]
_J = np.array([[0.0, -1.0], [1.0, 0.0]])


def _rot(theta: float) -> FloatArray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def contour_points(an: FloatArray, ae: FloatArray, values: FloatArray, level: float) -> FloatArray:
    """Points ``(K, 2)`` (north, east, in the axes' units) where the grid ``values`` (len(an), len(ae)) crosses
    ``level``, linearly interpolated along the grid edges (NaN nodes skipped)."""
    f = np.asarray(values, float) - level
    out = []
    a, b = f[:, :-1], f[:, 1:]  # east-going edges
    ok = np.isfinite(a) & np.isfinite(b) & (a * b <= 0) & (a != b)
    i, j = np.nonzero(ok)
    w = a[i, j] / (a[i, j] - b[i, j])
    out.append(np.column_stack([an[i], ae[j] + w * (ae[j + 1] - ae[j])]))
    a, b = f[:-1, :], f[1:, :]  # north-going edges
    ok = np.isfinite(a) & np.isfinite(b) & (a * b <= 0) & (a != b)
    i, j = np.nonzero(ok)
    w = a[i, j] / (a[i, j] - b[i, j])
    out.append(np.column_stack([an[i] + w * (an[i + 1] - an[i]), ae[j]]))
    return np.concatenate(out) if out else np.zeros((0, 2))


def rigid_fit(a: FloatArray, b: FloatArray, rotation: bool) -> tuple[float, FloatArray]:
    """``(theta, tr)`` minimising ``sum |R(theta) a_k + tr - b_k|^2`` (2-D Procrustes; ``a``, ``b`` (K, 2))."""
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    if not rotation:
        return 0.0, mb - ma
    H = (a - ma).T @ (b - mb)
    theta = float(np.arctan2(H[0, 1] - H[1, 0], H[0, 0] + H[1, 1]))
    return theta, mb - _rot(theta) @ ma


@dataclass
class ICCPMatcher:
    """ICCP batch matcher (module docstring). ``batch`` readings; ``gate_sigma`` prior sigmas (at least
    ``window_floor_m`` m) of the contour search region; ``iterations`` / ``tolerance_m`` of the ICP loop;
    ``rotation`` (rigid motion with rotation, else translation only); ``contour_step_m`` sampling of the map for the
    contours (default half the node spacing, at most a twentieth of the gate), coarsened to ``max_contour_nodes``
    per scan; ``map_sigma`` / ``correlation_m`` override the map's error; ``max_chi2`` the misfit cut-off;
    ``cover_rivals`` widen the fix covariance over the rival minima of the registered track's translation
    likelihood (:func:`._batch.rival_cover`, on an offset grid of at most ``max_offsets`` nodes)."""

    batch: int = 30
    gate_sigma: float = 4.0
    window_floor_m: float = 10.0
    iterations: int = 30
    tolerance_m: float = 0.5
    rotation: bool = True
    contour_step_m: float | None = None
    max_contour_nodes: int = 4096
    map_sigma: float | None = None
    correlation_m: float | None = None
    max_chi2: float = 9.0
    cover_rivals: bool = True
    max_offsets: int = 40_000
    name: str = "iccp"

    def __post_init__(self) -> None:
        if not (isinstance(self.batch, int) and self.batch >= 3):
            raise ConfigError(f"iccp 'batch': expected an integer >= 3, got {self.batch!r}")
        if not (isinstance(self.iterations, int) and self.iterations >= 1):
            raise ConfigError(f"iccp 'iterations': expected an integer >= 1, got {self.iterations!r}")
        for key in ("gate_sigma", "tolerance_m", "max_chi2"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"iccp '{key}': expected > 0, got {getattr(self, key)!r}")

    def match(self, window: MatchWindow, fmap: FieldMap) -> Fix:
        """One fix at the window's last reading (or a "no fix" with the reason)."""
        t_last = float(window.readings.t[-1]) if len(window.readings) else float("nan")
        try:
            return self._match(window, fmap, t_last)
        except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
            return Fix.no_fix(t_last, f"ICCP failed on the data: {exc}", self.name)

    def _match(self, window: MatchWindow, fmap: FieldMap, t_last: float) -> Fix:
        if map_components(fmap) != 1:
            return Fix.no_fix(t_last, "ICCP needs a scalar map (level lines of one component)", self.name)
        tw = track_window(window, fmap, self.batch, self.gate_sigma, self.window_floor_m, self.map_sigma,
                          self.correlation_m)  # fmt: skip
        if isinstance(tw, str):
            return Fix.no_fix(t_last, tw, self.name)
        hn, he = float(np.max(tw.half[:, 0])), float(np.max(tw.half[:, 1]))
        step0 = self.contour_step_m or min(0.5 * spacing_of(fmap, min(hn, he) / 10.0), min(hn, he) / 20.0)
        an, ae, step = window_axes(hn, he, step0, self.max_contour_nodes)
        GN, GE = np.meshgrid(an, ae, indexing="ij")
        idx, trees, any_map = [], [], False
        for t in np.flatnonzero(tw.good):
            v = tw.frame.sample(tw.x_ins[t, 0] + GN.ravel(), tw.x_ins[t, 1] + GE.ravel()).reshape(GN.shape)
            any_map = any_map or bool(np.any(np.isfinite(v)))
            pts = contour_points(an, ae, v, float(tw.z[t, 0]))
            if len(pts):
                idx.append(t)
                trees.append(cKDTree(pts + tw.x_ins[t]))
        if not any_map:
            return Fix.no_fix(t_last, "off the map: no map values in the gates", self.name)
        if len(idx) < 3:
            return Fix.no_fix(
                t_last, f"flat map: the level lines of only {len(idx)} readings cross their gates", self.name
            )
        idx = np.asarray(idx)
        p = tw.x_ins[idx]
        c = p.mean(axis=0)
        theta, tr = 0.0, np.zeros(2)
        y = p.copy()
        for _ in range(self.iterations):
            q = np.array([tree.query(yk)[1] for tree, yk in zip(trees, y, strict=True)])
            q = np.array([tree.data[k] for tree, k in zip(trees, q, strict=True)])
            theta, tr = rigid_fit(p - c, q - c, self.rotation)
            y_new = (p - c) @ _rot(theta).T + c + tr
            moved = float(np.max(np.hypot(*(y_new - y).T)))
            y = y_new
            if moved <= self.tolerance_m:
                break
        R = _rot(theta)
        yT = R @ (tw.x_ins[-1] - c) + c + tr
        if np.any(np.abs(yT - tw.x_ins[-1]) > tw.half[-1]):
            return Fix.no_fix(t_last, "diverged: the registered track left the gate", self.name)
        # linearised information about (tr_n, tr_e, theta) from every good reading at its registered position
        good = np.flatnonzero(tw.good)
        yg = (tw.x_ins[good] - c) @ R.T + c + tr
        m = tw.frame.sample(yg[:, 0], yg[:, 1]).reshape(good.size, -1)[:, 0]
        h = max(0.5 * step, 0.5)
        gn = (tw.frame.sample(yg[:, 0] + h, yg[:, 1]) - tw.frame.sample(yg[:, 0] - h, yg[:, 1])).ravel() / (2 * h)
        ge = (tw.frame.sample(yg[:, 0], yg[:, 1] + h) - tw.frame.sample(yg[:, 0], yg[:, 1] - h)).ravel() / (2 * h)
        ok = np.isfinite(m) & np.isfinite(gn) & np.isfinite(ge)
        if ok.sum() < 3:
            return Fix.no_fix(t_last, "off the map: the registered track left the map", self.name)
        g = np.column_stack([gn, ge])[ok]
        lever = (tw.x_ins[good][ok] - c) @ (R @ _J).T  # d y_t / d theta = R J (p_t - c)
        a = np.column_stack([g, np.sum(g * lever, axis=1)])
        g2 = local_gradient2(tw.frame, yg[ok, 0], yg[ok, 1], h)
        v = tw.s2[good][ok] + g2 * (step**2 / 12.0 + tw.rel_drift[good][ok] ** 2)
        r = tw.z[good][ok, 0] - m[ok]
        chi2 = float(np.mean(r**2 / v))
        info = (a / v[:, None]).T @ a
        if not self.rotation:
            info = info[:2, :2]
        big = (10.0 * float(np.max(tw.half[-1]))) ** 2
        ev, V = np.linalg.eigh(0.5 * (info + info.T))
        cov_b = (V / np.maximum(ev, 1.0 / big)) @ V.T * max(1.0, chi2)
        A = np.eye(2) if not self.rotation else np.column_stack([np.eye(2), R @ _J @ (tw.x_ins[-1] - c)])
        C = A @ cov_b @ A.T + np.eye(2) * step**2 / 12.0
        if self.cover_rivals:  # the registered track fits elsewhere in the gate too: C covers those minima
            ostep = min(0.25 * spacing_of(fmap, min(hn, he) / 10.0), min(hn, he) / 20.0)
            sep = max(3.0 * float(np.sqrt(np.max(np.linalg.eigvalsh(C)))), 4.0 * ostep)
            cover, _ = rival_cover(tw.frame, yg[ok], tw.z[good][ok], v + g2 * ostep**2 / 6.0, yT - tw.x_ins[-1],
                                   (hn, he), ostep, self.max_offsets, sep)  # fmt: skip
            C = C + cover
        prior = tw.cov[-1]
        if not adds_information(C, prior, (hn, he)):
            return information_refusal(t_last, C, prior, self.name, chi2, (hn, he))
        if chi2 > self.max_chi2:
            return Fix.no_fix(
                t_last,
                f"diverged: readings disagree with the map along the registered track (chi2 per reading {chi2:.3g} "
                f"above {self.max_chi2:g})",
                self.name,
                chi2,
            )
        lat, lon = tw.frame.to_latlon(yT[0], yT[1])
        return Fix(float(tw.t[-1]), float(lat), float(lon), 0.5 * (C + C.T), True, "", chi2, self.name)
