"""``particle_ins`` on a map with two identical places (issue 13, scope item 3): an attempt refused as ambiguous is
followed by more readings and more attempts; no later fix may pick one of the two places with a covariance that
excludes the other (on the Osborne tie line 5817 a fix right after such a refusal was 3.7 km off with 260 m sigmas)."""

from __future__ import annotations

import functools

import numpy as np
from matcher_scenarios import KIND_TF, ORIGIN, latlon, local, nav_estimate

from magnav_ins.aiding.matchers import build_matcher
from magnav_ins.core.types import FieldReadings
from magnav_ins.maps.grid import GridMap
from magnav_ins.maps.synthetic import gaussian_random_field

#: the map repeats itself every PERIOD_M east: the readings fit the truth and the truth + PERIOD_M equally well
PERIOD_M = 600.0
SPACING_M = 10.0
#: chi-square (2 dof) 99.9 %: a fix "covers" a place within this Mahalanobis^2
COVER_CHI2 = 13.8155


@functools.cache
def twin_map_of() -> GridMap:
    """A map that repeats itself every :data:`PERIOD_M` east (five copies), with a 2 nT error layer."""
    tile = gaussian_random_field((301, int(PERIOD_M / SPACING_M)), SPACING_M, 40.0, 50.0, np.random.default_rng(4))
    field = np.tile(tile, (1, 5))  # 3000 m east: five identical copies
    ax_n = np.arange(field.shape[0]) * SPACING_M
    ax_e = np.arange(field.shape[1]) * SPACING_M
    fmap = GridMap(ax_n, ax_e, field, kind=KIND_TF, frame="local", altitude_m=0.0, origin=ORIGIN, name="twins")
    return fmap.with_error_layer(np.full(field.shape, 2.0), 50.0, "test")


def _fly(fmap: GridMap, seed: int, config: dict) -> tuple[list, list[np.ndarray], np.ndarray]:
    """Fly north at 30 m/s over the twin map from a prior 250 m (1-sigma) wide east, asking for a fix every 20
    readings (1 nT, one a second), with matcher options ``config``; returns the fixes, the true positions at them
    and the offset of the copy of the truth the prior favours (the ghost)."""
    rng = np.random.default_rng(seed)
    m = build_matcher({"kind": "particle_ins", **config})
    v = np.array([30.0, 0.0])
    p = np.array([400.0, 1500.0 + rng.uniform(-100.0, 100.0)])
    P = np.diag([60.0**2, 250.0**2])
    off = rng.multivariate_normal([0.0, 0.0], P)
    ghost = np.array([0.0, PERIOD_M if off[1] > 0 else -PERIOD_M])
    st = m.initiate(nav_estimate(fmap, 0.0, p + off, v, P), rng)
    fixes, truths = [], []
    for k in range(1, 61):
        p = p + v
        st = m.predict(st, nav_estimate(fmap, float(k), p + off, v, P))
        z = fmap.value(*latlon(fmap, p[0], p[1])) + rng.normal(0.0, 1.0, 1)
        st = m.update(st, FieldReadings(np.array([float(k)]), z, 1.0, KIND_TF), fmap)
        if k % 20 == 0:
            fixes.append(m.to_fix(st))
            truths.append(p.copy())
    return fixes, truths, ghost


def _one_sided(config: dict, seeds: range) -> tuple[int, int, int]:
    """Over ``seeds``: the issued fixes, those that do not cover both places, and the flights with an attempt
    refused as ambiguous."""
    issued = bad = flights = 0
    for seed in seeds:
        fixes, truths, ghost = _fly(twin_map_of(), seed, config)
        flights += any("ambiguous" in f.reason for f in fixes)
        for f, p in zip(fixes, truths, strict=True):
            if not f.available:
                continue
            d = local(twin_map_of(), f.lat, f.lon) - p
            to_truth = float(d @ np.linalg.solve(f.cov_ne, d))
            to_ghost = float((d - ghost) @ np.linalg.solve(f.cov_ne, d - ghost))
            issued += 1
            bad += to_truth > COVER_CHI2 or to_ghost > COVER_CHI2
    return issued, bad, flights


def test_no_fix_picks_one_of_two_identical_places():
    """Defaults: attempts refused as ambiguous (the cloud spans both places), and no later attempt picks one."""
    issued, bad, flights = _one_sided({}, range(30))
    assert flights >= 5, flights  # the situation: an attempt refused as ambiguous, more readings, more attempts
    assert bad == 0, (issued, bad)
    # without the sparse-draws rule and the rival check the cloud collapses onto one copy by resampling and its
    # increment is tight; the rival check alone leaves about half the issued fixes one-sided here
    issued0, bad0, _ = _one_sided({"min_draws": 0.0, "rival_grid": 0}, range(30))
    assert bad0 >= 30, (issued0, bad0)
    issued1, bad1, _ = _one_sided({"min_draws": 0.0}, range(30))
    assert bad1 >= 10, (issued1, bad1)


def test_subclouds_refuse_most_one_sided_fixes():
    """The optional sub-clouds (module docstring, "Sub-clouds"): three of them, without the sparse-draws rule."""
    issued, bad, _ = _one_sided({"min_draws": 0.0, "subclouds": 3}, range(30))
    assert bad <= 3, (issued, bad)
