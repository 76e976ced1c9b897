"""Synthetic scenarios with known truth for the matcher tests (tests/test_matchers_*.py).

Each scenario builds a map and runs one trial of a matcher from a seeded generator, returning the fix and the true
position at the fix time. Positions are handled in the map's local plane (``GridMap.to_local`` / ``from_local``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from magnav_ins.core.protocols import MatchWindow
from magnav_ins.core.types import FieldKind, FieldReadings, Fix, NavEstimate, NavState
from magnav_ins.maps.grid import GridMap
from magnav_ins.maps.synthetic import random_field_map

ORIGIN = (np.radians(45.0), np.radians(7.0), 0.0)
KIND_TF = FieldKind.TOTAL_FIELD_ANOMALY_NT
KIND_G = FieldKind.GRAVITY_DISTURBANCE_MGAL
KIND_V = FieldKind.VECTOR_FIELD_NT


def latlon(fmap: Any, n: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return fmap.from_local(np.atleast_1d(np.asarray(n, float)), np.atleast_1d(np.asarray(e, float)))


def local(fmap: Any, lat: float, lon: float) -> np.ndarray:
    n, e = fmap.to_local(np.array([lat]), np.array([lon]))
    return np.array([float(np.ravel(n)[0]), float(np.ravel(e)[0])])


def make_window(
    fmap: Any,
    t: np.ndarray,
    true_ne: np.ndarray,
    z: np.ndarray,
    sigma: float,
    kind: FieldKind,
    ins_offset: np.ndarray,
    P: np.ndarray,
    v_ne: np.ndarray,
) -> MatchWindow:
    """Window whose INS track is the truth shifted by ``ins_offset`` (m), covariance ``P`` at every reading."""
    n = len(t)
    lat, lon = latlon(fmap, true_ne[:, 0] + ins_offset[0], true_ne[:, 1] + ins_offset[1])
    return MatchWindow(
        FieldReadings(t, z, sigma, kind), lat, lon, np.zeros(n), np.tile(P, (n, 1, 1)), np.tile(v_ne, (n, 1))
    )


def nav_estimate(fmap: Any, t: float, ne: np.ndarray, v_ne: np.ndarray, P_ne: np.ndarray) -> NavEstimate:
    lat, lon = latlon(fmap, ne[0], ne[1])
    P = np.eye(15) * 1e-4
    P[:2, :2] = P_ne
    nav = NavState(t, float(lat[0]), float(lon[0]), 0.0, np.array([v_ne[0], v_ne[1], 0.0]), np.array([0, 0, 0, 1.0]))
    return NavEstimate(nav, P)


def exact(fmap: GridMap) -> GridMap:
    """The map with a zero error layer: a synthetic map whose readings are drawn from it is the truth, so the
    matchers must not add the default map error of a map that does not know its error (``map_error.py``)."""
    ell = float(fmap.metadata.get("correlation_length_m", 1.0)) * np.sqrt(2.0)  # the field's 1/e length
    out = fmap.with_error_layer(0.0, ell, "synthetic: exact")
    out.metadata.update(level_sigma=0.0, level_sigma_source="synthetic: readings drawn from the map")
    return out


def flat_like(fmap: GridMap) -> GridMap:
    """The same grid holding a constant field (no features)."""
    return fmap.with_values(np.full_like(np.asarray(fmap.values), 7.0))


@dataclass
class Scenario:
    """A matcher config, a map builder and a trial runner ``trial(matcher, fmap, rng, mode) -> (Fix, truth_ne)``.

    ``mode``: "normal", "off_map" (the INS says we are far off the map), "nan" (NaN readings)."""

    config: dict[str, Any]
    build_map: Callable[[np.random.Generator], GridMap]
    trial: Callable[[Any, GridMap, np.random.Generator, str], tuple[Fix, np.ndarray]]


# ---------------------------------------------------------------------------------------------- batch: likelihood
def _likelihood_map(rng: np.random.Generator) -> GridMap:
    return exact(random_field_map((300, 300), 5.0, 40.0, 100.0, rng, kind=KIND_TF, origin=ORIGIN))


def _likelihood_trial(m: Any, fmap: GridMap, rng: np.random.Generator, mode: str) -> tuple[Fix, np.ndarray]:
    """10 readings 4 m apart along a random heading, INS offset ~ N(0, 15^2 I) m, noise 2 nT."""
    nz, sig, ps = 10, 2.0, 15.0
    head = rng.uniform(0, 2 * np.pi)
    start = rng.uniform(300.0, 1100.0, 2)
    s = 4.0 * np.arange(nz)
    true_ne = start + np.column_stack([s * np.cos(head), s * np.sin(head)])
    lat, lon = latlon(fmap, true_ne[:, 0], true_ne[:, 1])
    z = fmap.value(lat, lon) + rng.normal(0.0, sig, nz)
    if mode == "nan":
        z[:] = np.nan
    P = np.eye(2) * ps**2
    off = rng.multivariate_normal([0, 0], P) + (np.array([5e4, 0.0]) if mode == "off_map" else 0.0)
    w = make_window(fmap, np.arange(nz, dtype=float), true_ne, z, sig, KIND_TF, off, P, np.zeros(2))
    return m.match(w, fmap), true_ne[-1]


# ---------------------------------------------------------------------------------------------- batch: PMHT
def _gravity_map(rng: np.random.Generator) -> GridMap:
    return exact(random_field_map((400, 400), 10.0, 300.0, 20.0, rng, kind=KIND_G, origin=ORIGIN))


def _pmht_trial(m: Any, fmap: GridMap, rng: np.random.Generator, mode: str) -> tuple[Fix, np.ndarray]:
    """T = 30 gravimeter readings every 10 s at 15 m/s (Wang's set-up scaled down), sigma 0.5 mGal, INS offset
    ~ N(0, 30^2 I) m."""
    T, dt, sig, ps = 30, 10.0, 0.5, 30.0
    head = rng.uniform(0, 2 * np.pi)
    v = 15.0 * np.array([np.cos(head), np.sin(head)])
    start = np.array([2000.0, 2000.0]) - v * dt * (T - 1) / 2 + rng.uniform(-300, 300, 2)
    true_ne = start + v * dt * np.arange(T)[:, None]
    lat, lon = latlon(fmap, true_ne[:, 0], true_ne[:, 1])
    z = fmap.value(lat, lon) + rng.normal(0.0, sig, T)
    if mode == "nan":
        z[:] = np.nan
    P = np.eye(2) * ps**2
    off = rng.multivariate_normal([0, 0], P) + (np.array([5e4, 0.0]) if mode == "off_map" else 0.0)
    w = make_window(fmap, dt * np.arange(T), true_ne, z, sig, KIND_G, off, P, v)
    return m.match(w, fmap), true_ne[-1]


# ---------------------------------------------------------------------------------------------- recursive: Bayes
def _vector_map(rng: np.random.Generator) -> GridMap:
    return exact(random_field_map((200, 200), 0.381, 0.6, 1200.0, rng, kind=KIND_V, origin=ORIGIN))


def _bayes_trial(m: Any, fmap: GridMap, rng: np.random.Generator, mode: str) -> tuple[Fix, np.ndarray]:
    """One 3-axis reading (sigma 100 nT = 1 mG, Storms Table 4.1) with a prior ~ N(truth, 0.5^2 I) m."""
    sig, ps = 100.0, 0.5
    truth = rng.uniform(15.0, 60.0, 2)
    lat, lon = latlon(fmap, truth[0], truth[1])
    z = fmap.value(lat, lon)[0] + rng.normal(0.0, sig, 3)
    if mode == "nan":
        z[:] = np.nan
    P = np.eye(2) * ps**2
    prior_ne = truth + rng.multivariate_normal([0, 0], P) + (np.array([5e4, 0.0]) if mode == "off_map" else 0.0)
    st = m.initiate(nav_estimate(fmap, 0.0, prior_ne, np.zeros(2), P), rng)
    st = m.predict(st, nav_estimate(fmap, 1.0, prior_ne, np.zeros(2), P))
    st = m.update(st, FieldReadings(np.array([1.0]), z[None], sig, KIND_V), fmap)
    return m.to_fix(st), truth


# ---------------------------------------------------------------------------------------------- recursive: particle
def _particle_map(rng: np.random.Generator) -> GridMap:
    return exact(random_field_map((400, 400), 2.0, 25.0, 50.0, rng, kind=KIND_TF, origin=ORIGIN))


def _particle_trial(m: Any, fmap: GridMap, rng: np.random.Generator, mode: str) -> tuple[Fix, np.ndarray]:
    """20 s at 4 m/s with a reading (sigma 5 nT) each second; INS offset uniform in +-15 m plus a slow drift;
    particles from the prior covariance."""
    sig, steps, dt = 5.0, 20, 1.0
    head = rng.uniform(0, 2 * np.pi)
    v = 4.0 * np.array([np.cos(head), np.sin(head)])
    p = np.array([400.0, 400.0]) + rng.uniform(-50, 50, 2)
    off = rng.uniform(-15, 15, 2) + (np.array([5e4, 0.0]) if mode == "off_map" else 0.0)
    drift = rng.normal(0.0, 0.05, 2)
    P = np.eye(2) * 15.0**2
    st = m.initiate(nav_estimate(fmap, 0.0, p + off, v, P), rng)
    for k in range(1, steps + 1):
        p = p + v * dt
        st = m.predict(st, nav_estimate(fmap, k * dt, p + off + drift * k, v, P))
        lat, lon = latlon(fmap, p[0], p[1])
        z = fmap.value(lat, lon) + rng.normal(0.0, sig, 1)
        if mode == "nan":
            z[:] = np.nan
        st = m.update(st, FieldReadings(np.array([k * dt]), z, sig, KIND_TF), fmap)
    return m.to_fix(st), p


SCENARIOS: dict[str, Scenario] = {
    "ml": Scenario({"kind": "ml"}, _likelihood_map, _likelihood_trial),
    "mlr": Scenario({"kind": "mlr"}, _likelihood_map, _likelihood_trial),
    "abl": Scenario({"kind": "abl"}, _likelihood_map, _likelihood_trial),
    "pmht": Scenario({"kind": "pmht", "batch": 30, "candidates": 20, "iterations": 15}, _gravity_map, _pmht_trial),
    # one isolated fix judged on its own: the posterior R (Storms' likelihood-line R, the default, is for a fix fused
    # with the same prior again, and on single readings of this map ~10 % of its fixes sit on a wrong peak at NEES ~70)
    "bayes_grid": Scenario({"kind": "bayes_grid", "covariance": "posterior"}, _vector_map, _bayes_trial),
    "particle_ins": Scenario(
        {"kind": "particle_ins", "init": "gaussian", "ins_sigma": 0.2},
        _particle_map,
        _particle_trial,
    ),
    "particle": Scenario(
        {"kind": "particle", "init": "gaussian", "accel_sigma": 0.1},
        _particle_map,
        _particle_trial,
    ),
}


# ---------------------------------------------------------------------------------------------- known map error
@dataclass(frozen=True)
class ErrorField:
    """A truth field, and the map a matcher is given: truth plus a correlated error field of known 1-sigma
    ``sigma`` and correlation length ``ell_m`` (the 1/e lag of the kernel of ``map_error.py``, drawn by
    :func:`magnav_ins.maps.synthetic.gaussian_random_field` with its length scale ``ell_m / sqrt(2)``), with its
    error layer (``with_layer``) and without (``without_layer``)."""

    truth: GridMap
    with_layer: GridMap
    without_layer: GridMap
    sigma: float
    ell_m: float


def error_field(
    seed: int,
    shape: tuple[int, int],
    spacing_m: float,
    ell_field_m: float,
    sigma_field: float,
    sigma: float,
    ell_m: float,
) -> ErrorField:
    """Truth ``random_field_map`` and truth + error (module docstring of :class:`ErrorField`)."""
    from magnav_ins.maps.synthetic import gaussian_random_field

    rng = np.random.default_rng(seed)
    truth = random_field_map(shape, spacing_m, ell_field_m, sigma_field, rng, kind=KIND_TF, origin=ORIGIN)
    err = gaussian_random_field(shape, spacing_m, ell_m / np.sqrt(2.0), sigma, rng)
    noisy = truth.with_values(np.asarray(truth.values) + err)
    return ErrorField(exact(truth), noisy.with_error_layer(sigma, ell_m, "known"), noisy, sigma, ell_m)


def section_trial(
    m: Any,
    ef: ErrorField,
    fmap: GridMap,
    rng: np.random.Generator,
    nz: int = 30,
    step_m: float = 10.0,
    level_sigma: float = 0.0,
) -> tuple[Fix, np.ndarray]:
    """A straight section of ``nz`` readings ``step_m`` apart along a random heading, read from the TRUTH (noise
    2 nT) plus a constant level offset ~ N(0, ``level_sigma``^2) drawn per section, matched against ``fmap``; INS
    offset ~ N(0, 15^2 I) m."""
    sig, ps = 2.0, 15.0
    head = rng.uniform(0, 2 * np.pi)
    start = rng.uniform(400.0, 1100.0, 2)
    s = step_m * np.arange(nz)
    true_ne = start + np.column_stack([s * np.cos(head), s * np.sin(head)])
    lat, lon = latlon(ef.truth, true_ne[:, 0], true_ne[:, 1])
    z = ef.truth.value(lat, lon) + rng.normal(0.0, sig, nz) + (rng.normal(0.0, level_sigma) if level_sigma else 0.0)
    P = np.eye(2) * ps**2
    off = rng.multivariate_normal([0, 0], P)
    w = make_window(fmap, np.arange(nz, dtype=float), true_ne, z, sig, KIND_TF, off, P, np.zeros(2))
    return m.match(w, fmap), true_ne[-1]


def particle_trial(
    m: Any, ef: ErrorField, fmap: GridMap, rng: np.random.Generator, steps: int = 40
) -> tuple[Fix, np.ndarray]:
    """As ``_particle_trial`` (4 m/s, a reading each second, sigma 2 nT) with the readings from the TRUTH and the
    particles weighted against ``fmap``."""
    sig, dt = 2.0, 1.0
    head = rng.uniform(0, 2 * np.pi)
    v = 4.0 * np.array([np.cos(head), np.sin(head)])
    p = np.array([400.0, 400.0]) + rng.uniform(-50, 50, 2)
    P = np.eye(2) * 15.0**2
    off = rng.multivariate_normal([0, 0], P)
    st = m.initiate(nav_estimate(fmap, 0.0, p + off, v, P), rng)
    for k in range(1, steps + 1):
        p = p + v * dt
        st = m.predict(st, nav_estimate(fmap, k * dt, p + off, v, P))
        lat, lon = latlon(ef.truth, p[0], p[1])
        z = ef.truth.value(lat, lon) + rng.normal(0.0, sig, 1)
        st = m.update(st, FieldReadings(np.array([k * dt]), z, sig, KIND_TF), fmap)
    return m.to_fix(st), p
