"""The bridge's track log carries its horizontal covariance, and the SITL bench's NEES uses it.

``sigma_h`` (the largest 1-sigma, what GPS_INPUT's accuracy field carries in every direction) understates the NEES
of an elongated ellipse: the map fixes' ellipses are 2-10 times longer along the track than across it. Independent
truth: errors drawn from the covariance itself, whose NEES over 2 has mean 1.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from magnav_ins.commands.bridge import _TrackWriter
from magnav_ins.core.frames import meters_to_latlon
from magnav_ins.mavlink.sitl_flight import _track_nees


def _cov(sig_major: float, sig_minor: float, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    R = np.array([[c, -s], [s, c]])
    return R @ np.diag([sig_major**2, sig_minor**2]) @ R.T


def _write_track(path, n: int = 3000, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """A track whose errors are drawn from its own covariance (200 x 30 m, 35 deg from north); returns truth (rad)."""
    rng = np.random.default_rng(seed)
    lat0, lon0 = math.radians(-21.9), math.radians(140.7)
    P = _cov(200.0, 30.0, math.radians(35.0))
    e = rng.multivariate_normal(np.zeros(2), P, size=n)
    lat_t = lat0 + np.linspace(0.0, 1e-4, n)
    lon_t = np.full(n, lon0)
    w = _TrackWriter(str(path))
    for k in range(n):
        dlat, dlon = meters_to_latlon(e[k, 0], e[k, 1], lat_t[k], 0.0)
        w({"t_wall": 1000.0 + 0.1 * k, "t": 0.1 * k, "lat": lat_t[k] + float(dlat), "lon": lon_t[k] + float(dlon),
           "h": 400.0, "sigma_h": 200.0, "cov_ne": P, "hpl": 900.0, "trusted": True, "sent": True,
           "state": "running", "aiding": "map"})  # fmt: skip
    w.close()
    return lat_t, lon_t


def test_track_nees_uses_the_covariance_and_sigma_h_understates_it(tmp_path):
    path = tmp_path / "track.csv"
    lat_t, lon_t = _write_track(path)
    tr = pd.read_csv(path)
    assert {"cov_nn_m2", "cov_ne_m2", "cov_ee_m2"} <= set(tr.columns)
    nees = _track_nees(tr, lat_t, lon_t)
    assert abs(nees - 1.0) < 0.08, nees
    # an old track (no covariance): |e|^2 / sigma_max^2, here (200^2 + 30^2) / (2 x 200^2) = 0.51 on average
    old = _track_nees(tr.drop(columns=["cov_nn_m2", "cov_ne_m2", "cov_ee_m2"]), lat_t, lon_t)
    assert abs(old - 0.51) < 0.05 and old < 0.6 * nees, (old, nees)


def test_track_nees_sees_an_error_across_the_ellipse(tmp_path):
    """A 3-sigma error across a long ellipse is 3 sigmas (NEES 4.5), not 0.45 of the largest sigma (NEES 0.1)."""
    path = tmp_path / "track.csv"
    P = _cov(200.0, 30.0, 0.0)  # long north, narrow east
    lat0, lon0 = math.radians(-21.9), math.radians(140.7)
    dlat, dlon = meters_to_latlon(0.0, 90.0, lat0, 0.0)
    w = _TrackWriter(str(path))
    w({"t_wall": 1.0, "t": 0.0, "lat": lat0 + float(dlat), "lon": lon0 + float(dlon), "h": 0.0, "sigma_h": 200.0,
       "cov_ne": P, "hpl": 900.0, "trusted": True, "sent": True, "state": "running", "aiding": "map"})  # fmt: skip
    w.close()
    tr = pd.read_csv(path)
    assert _track_nees(tr, np.array([lat0]), np.array([lon0])) == pytest.approx(4.5, rel=2e-3)
