"""Maps of a walked path (``maps.selfbuild.path_map``) and the Kok & Solin indoor walks (``bench/kok_walks.py``):
frames checked on the real data, revisit calibration, one short matching run."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from magnav_ins.core.errors import InputError
from magnav_ins.core.types import FieldKind
from magnav_ins.maps.selfbuild import path_map

ORIGIN = (np.radians(60.0), np.radians(25.0), 0.0)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))


def test_path_map_reproduces_a_field_along_the_path_and_blanks_elsewhere():
    """A circle of radius 3 m walked with readings of a smooth field f(n, e) = (10 n, 5 e, 100): on the path the
    kernel mean reproduces f to the kernel's smoothing (second order: curvature x length^2 / 2), 1 m off it NaN."""
    a = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    n, e = 3.0 * np.cos(a), 3.0 * np.sin(a)
    v = np.column_stack([10 * n, 5 * e, np.full_like(n, 100.0)])
    m = path_map(n, e, v, kind=FieldKind.VECTOR_FIELD_NT, spacing_m=0.05, origin=ORIGIN, length_scale_m=0.1,
                 max_distance_m=0.3)  # fmt: skip
    lat, lon = m.from_local(n, e)
    got = m.value(lat, lon)
    assert np.all(np.isfinite(got))
    assert got == pytest.approx(v, abs=0.2)  # |d2f/ds2| = 10 * 3 / 3^2 ... * 0.1^2 / 2: < 0.2 nT
    lat, lon = m.from_local(np.array([0.0, 4.0]), np.array([0.0, 0.0]))  # the loop's centre, 1 m outside
    assert np.all(np.isnan(m.value(lat, lon)))
    with pytest.raises(InputError, match="length_scale_m"):
        path_map(n, e, v, kind="vector_field_nt", spacing_m=0.1, origin=ORIGIN, length_scale_m=0.0,
                 max_distance_m=0.3)  # fmt: skip
    with pytest.raises(InputError, match="component"):
        path_map(n, e, v[:, 0], kind="vector_field_nt", spacing_m=0.1, origin=ORIGIN, length_scale_m=0.1,
                 max_distance_m=0.3)  # fmt: skip


@pytest.mark.shared_data
def test_kok_world_frame_holds_the_earth_field_and_positions_match_the_attitude(shared_data):
    import kok_walks as K

    for name in K.WALKS:
        w = K.load_walk(name, shared_data / "indoor_magnetic_kok")
        mean = w.m_w.mean(axis=0)
        # the world-frame mean is the Earth's field (38-49 uT here), mostly on the vertical axis
        assert 30e3 < np.linalg.norm(mean) < 60e3, name
        assert abs(mean[2]) > 0.85 * np.linalg.norm(mean), name
        # the phone is held across the walking direction: heading of motion = yaw + 90 deg, within 10 deg (median)
        v = np.diff(w.ne, axis=0)
        fast = np.hypot(*v.T) > 0.05
        d = np.angle(np.exp(1j * (np.arctan2(v[fast, 1], v[fast, 0]) - w.yaw[1:][fast] - np.pi / 2)))
        assert abs(np.degrees(np.median(d))) < 10.0, name


@pytest.mark.shared_data
def test_kok_revisit_calibration_makes_revisits_agree(shared_data):
    """On the square walk, readings within 0.15 m of each other (5 s apart) differ less in the world frame once
    the bias found from the first half's revisits is removed, also on the second half (not used to find it)."""
    import kok_walks as K
    from scipy.spatial import cKDTree

    w = K.load_walk("square", shared_data / "indoor_magnetic_kok")
    half = w.t < 0.5 * w.t[-1]
    b, pairs = K.bias_from_revisits(w, half)
    assert pairs > 100 and np.linalg.norm(b) > 1e3

    def misfit(walk, sel):
        idx = np.flatnonzero(sel)
        pp = [(idx[i], idx[j]) for i, j in cKDTree(walk.ne[idx]).query_pairs(0.15)
              if abs(walk.t[idx[i]] - walk.t[idx[j]]) > 5]  # fmt: skip
        i, j = np.array(pp).T
        return float(np.sqrt(np.mean((walk.m_w[i] - walk.m_w[j]) ** 2)))

    second = ~half
    assert misfit(w.with_bias(b), second) < 0.85 * misfit(w, second)


@pytest.mark.shared_data
def test_kok_eight_bayes_grid_beats_odometry(shared_data):
    """One odometry draw on the 'eight' walk: the Bayes grid on the walk's own first-part map keeps the error
    below the drifting odometry's, with most attempts answered."""
    import argparse

    import kok_walks as K

    args = argparse.Namespace(data=shared_data / "indoor_magnetic_kok", seeds=1, seed=1, map_fraction=0.4,
                              cal_fraction=0.1, every=1.0, section=3.0, sigma=100.0, calibrate=True)  # fmt: skip
    r = K.walk_table("eight", args)["methods"]
    assert r["bayes_grid"]["availability"] > 0.8
    assert r["bayes_grid"]["rms_m_median"] < 0.8 * r["odometry"]["rms_m_median"]
    assert r["bayes_grid"]["fix_err_median_m"] < 0.4
