"""Feature variability, gradient RMS and Cramér-Rao bounds against closed forms (ramps and a bowl)."""

from __future__ import annotations

import numpy as np
import pytest

from magnav_ins.core.errors import InputError
from magnav_ins.core.types import FieldKind
from magnav_ins.maps import variability as var
from magnav_ins.maps.grid import GridMap

ORIGIN = (0.6, 2.5, 100.0)
D = 10.0
AX_N = np.arange(0.0, 2000.0 + D / 2, D)
AX_E = np.arange(0.0, 1500.0 + D / 2, D)
NN, EE = np.meshgrid(AX_N, AX_E, indexing="ij")


def _local(values: np.ndarray, kind: FieldKind = FieldKind.TOTAL_FIELD_ANOMALY_NT) -> GridMap:
    return GridMap(AX_N, AX_E, values, kind=kind, frame="local", altitude_m=100.0, origin=ORIGIN, name="t")


def _ramp_ci(a: float, d: float, h: int) -> float:
    """C_i of f = a * northing on a (2h+1)^2 window: a^2 d^2 (2h+1) sum_p p^2 / ((2h+1)^2 - 1)."""
    m = 2 * h + 1
    return a**2 * d**2 * m * (h * (h + 1) * m / 3.0) / (m * m - 1)


def test_feature_variability_linear_ramp_closed_form():
    a = 0.3  # nT/m
    fmap = _local(5e4 + a * NN)  # a large offset must not matter
    c = feature = var.feature_variability(fmap, window_m=100.0)  # 100 m -> h = 5 cells
    assert feature.metadata["quantity"] == "feature_variability"
    inner = c.values[10:-10, 10:-10]
    np.testing.assert_allclose(inner, _ramp_ci(a, D, 5), rtol=1e-9)
    # direct evaluation of eq. 14 at one node
    i, j = 50, 60
    win = fmap.values[i - 5 : i + 6, j - 5 : j + 6].ravel()
    direct = np.sum((fmap.values[i, j] - win) ** 2) / (win.size - 1)
    assert c.values[i, j] == pytest.approx(direct, rel=1e-9)


def test_feature_variability_vector_is_sum_of_components_and_track_agrees():
    a, b = 0.3, -0.1
    vec = np.stack([a * NN, b * EE, np.zeros_like(NN)], axis=-1)
    c_vec = var.feature_variability(_local(vec, FieldKind.VECTOR_FIELD_NT), 100.0).values
    expect = _ramp_ci(a, D, 5) + _ramp_ci(b, D, 5)
    np.testing.assert_allclose(c_vec[10:-10, 10:-10], expect, rtol=1e-9)
    # along a trajectory (sampling the interpolated map at the node spacing) on the scalar ramp
    fmap = _local(a * NN)
    lat, lon = fmap.from_local(np.array([500.0, 800.0, 1200.0]), np.array([400.0, 700.0, 900.0]))
    c_trk = var.feature_variability_track(fmap, lat, lon, window_m=100.0)
    np.testing.assert_allclose(c_trk, _ramp_ci(a, D, 5), rtol=2e-3)


def test_gradient_rms_and_crlb_of_a_ramp():
    a, sigma = 0.3, 2.0
    fmap = _local(a * NN + 0.4 * EE)
    g = np.hypot(a, 0.4)
    np.testing.assert_allclose(var.gradient_rms(fmap, 50.0).values, g, rtol=1e-9)
    rasters = var.crlb_raster(fmap, sigma, window_m=50.0)
    np.testing.assert_allclose(rasters["along_gradient"], sigma / g, rtol=1e-9)
    # all gradients parallel: no information across them
    assert np.all(np.isinf(rasters["semi_major"]))
    h = var.window_half_cells(50.0, fmap.spacing_m)
    n_win = (2 * h[0] + 1) * (2 * h[1] + 1)
    np.testing.assert_allclose(rasters["semi_minor"][10:-10, 10:-10], sigma / g / np.sqrt(n_win), rtol=1e-9)


def test_crlb_window_of_a_bowl_closed_form():
    c, sigma = 1e-3, 1.0
    fmap = _local(c * ((NN - 1000.0) ** 2 + (EE - 750.0) ** 2))
    rasters = var.crlb_raster(fmap, sigma, window_m=100.0)
    i, j = 100, 75  # the bowl's bottom: gradient 2c(dn, de), central differences exact for a quadratic
    hn = 5
    m = 2 * hn + 1
    j_nn = 4 * c**2 / sigma**2 * m * D**2 * hn * (hn + 1) * m / 3.0  # sum over the window of (2c dn)^2
    assert rasters["semi_major"][i, j] == pytest.approx(1.0 / np.sqrt(j_nn), rel=1e-9)
    assert rasters["semi_minor"][i, j] == pytest.approx(1.0 / np.sqrt(j_nn), rel=1e-9)
    assert np.isinf(rasters["along_gradient"][i, j])  # flat at the very bottom


def test_crlb_track_accumulates_readings():
    a, sigma = 0.3, 2.0
    fmap = _local(a * NN)
    lat, lon = fmap.from_local(np.linspace(200.0, 1800.0, 40), np.full(40, 700.0))
    along, summ = var.crlb_track(fmap, lat, lon, sigma, window=10)
    np.testing.assert_allclose(along, sigma / a, rtol=1e-6)
    off_lat, off_lon = fmap.from_local(np.array([500.0, 9000.0]), np.array([700.0, 700.0]))
    along_off, s_off = var.crlb_track(fmap, off_lat, off_lon, sigma)
    assert np.isfinite(along_off[0]) and np.isnan(along_off[1])
    assert s_off.semi_minor_m[1] == pytest.approx(s_off.semi_minor_m[0])  # the off-map reading adds nothing
    np.testing.assert_allclose(summ.semi_minor_m[9:], sigma / a / np.sqrt(10), rtol=1e-6)
    np.testing.assert_allclose(summ.semi_minor_m[:9], sigma / a / np.sqrt(np.arange(1, 10)), rtol=1e-6)
    assert np.all(np.isinf(summ.semi_major_m))  # a north ramp says nothing about east
    # a turn adds the missing direction: a bowl seen from points on a circle
    bowl = _local(1e-3 * ((NN - 1000.0) ** 2 + (EE - 750.0) ** 2))
    ang = np.linspace(0.0, 2 * np.pi, 36, endpoint=False)
    lat, lon = bowl.from_local(1000.0 + 300.0 * np.cos(ang), 750.0 + 300.0 * np.sin(ang))
    _, s = var.crlb_track(bowl, lat, lon, 1.0)
    # |g| = 2c r = 0.6 nT/m everywhere on the circle; information isotropic: 36 * 0.36 / 2 per axis
    assert s.semi_major_m[-1] == pytest.approx(1.0 / np.sqrt(36 * 0.36 / 2), rel=2e-2)
    assert s.semi_minor_m[-1] == pytest.approx(1.0 / np.sqrt(36 * 0.36 / 2), rel=2e-2)


def test_geodetic_map_gradient_scaling():
    lat = np.radians(np.linspace(-35.2, -35.0, 41))
    lon = np.radians(np.linspace(149.0, 149.3, 61))
    from magnav_ins.core.frames import radii_of_curvature

    r_n, _ = radii_of_curvature(lat)
    values = np.repeat(((lat - lat[0]) * (r_n + 0.0))[:, None], lon.size, axis=1) * 0.05  # 0.05 mGal per m north
    gm = GridMap(lat, lon, values, kind=FieldKind.GRAVITY_DISTURBANCE_MGAL, frame="geodetic", altitude_m=0.0)
    g = var.grid_gradient_ne(gm)
    np.testing.assert_allclose(g[5:-5, 5:-5, 0, 0], 0.05, rtol=1e-3)
    np.testing.assert_allclose(g[..., 0, 1], 0.0, atol=1e-12)


def test_bad_window_and_sigma():
    fmap = _local(NN * 0.1)
    with pytest.raises(InputError, match="window_m"):
        var.feature_variability(fmap, -3.0)
    with pytest.raises(InputError, match="sigma"):
        var.crlb_raster(fmap, 0.0, 50.0)


def test_variability_command_writers(tmp_path):
    import xarray as xr

    from magnav_ins.commands import map_variability as cmd

    a = 0.3
    fmap = _local(a * NN)
    rasters = cmd.compute(fmap, 100.0, sigma=2.0)
    out = tmp_path / "sub" / "var.nc"
    cmd.write_netcdf(out, fmap, rasters, 100.0)
    cmd.write_png(out.with_suffix(".png"), fmap, rasters, 100.0)
    assert out.with_suffix(".png").stat().st_size > 1000
    assert [p.name for p in out.parent.iterdir() if p.name.startswith(".")] == []  # no temporary left behind
    with xr.open_dataset(out) as ds:
        assert ds.attrs["window_m"] == 100.0
        assert ds["feature_variability"].attrs["units"] == "nT^2"
        np.testing.assert_allclose(ds["feature_variability"].values[10:-10, 10:-10], _ramp_ci(a, D, 5), rtol=1e-9)
        np.testing.assert_allclose(ds["crlb_along_gradient"].values, 2.0 / a, rtol=1e-9)
        np.testing.assert_allclose(ds["northing"].values, AX_N)
    with pytest.raises(InputError, match="sigma"):
        cmd.compute(fmap, 100.0, sigma=-1.0)


def test_feature_variability_agrees_with_the_matchers_window_version():
    # peer: the matchers' per-window eq. 14 (aiding/matchers/_local.py), on a random field (no tied values)
    _local_mod = pytest.importorskip("magnav_ins.aiding.matchers._local")
    from magnav_ins.maps.synthetic import gaussian_random_field

    vals = gaussian_random_field(NN.shape, D, 60.0, 5.0, np.random.default_rng(4))
    c = var.feature_variability(_local(vals), 70.0).values  # h = 4 (rounded from 3.5)
    for i, j in [(30, 40), (100, 20), (150, 140)]:
        win = vals[i - 4 : i + 5, j - 4 : j + 5]
        assert c[i, j] == pytest.approx(_local_mod.feature_variability(win, vals[i, j]), rel=1e-9)


def test_feature_variability_along_a_track_map():
    from magnav_ins.maps.track import TrackMap

    # two roads, values a*s, 1 m sampling: interior points see 2h neighbours at distances 1..h either side
    fmap = _local(NN)
    n1 = np.arange(0.0, 300.0, 1.0)
    lat, lon = fmap.from_local(np.r_[n1, np.full(200, 500.0)], np.r_[np.full(300, 100.0), np.arange(200.0)])
    a = 0.5
    vals = np.r_[a * n1, a * np.arange(200.0)]
    tm = TrackMap(lat, lon, 100.0, vals, kind="total_field_anomaly_nt", segment_id=np.r_[np.zeros(300), np.ones(200)])
    c = var.feature_variability_along_track(tm, window_m=20.0)
    h = 10
    expect = a**2 * 2 * np.sum(np.arange(1, h + 1) ** 2) / (2 * h)
    np.testing.assert_allclose(c[20:280], expect, rtol=1e-6)
    np.testing.assert_allclose(c[320:480], expect, rtol=1e-6)
    # the end of a road has only one side (and never borrows points from the next road)
    assert c[299] == pytest.approx(a**2 * np.sum(np.arange(1, h + 1) ** 2) / h, rel=1e-6)


def test_variability_command_end_to_end(tmp_path, capsys):
    """``magnav-ins map variability`` through the real dispatcher on a ramp map written by maps.io."""
    import xarray as xr

    from magnav_ins.cli import main
    from magnav_ins.maps.io import write_map

    src = tmp_path / "ramp.nc"
    write_map(_local(0.3 * NN), src)
    out = tmp_path / "out" / "v.nc"
    assert main(["map", "variability", str(src), "--window", "100", "--out", str(out), "--sigma", "2"]) == 0
    assert "feature_variability" in capsys.readouterr().out
    with xr.open_dataset(out) as ds:
        np.testing.assert_allclose(ds["crlb_along_gradient"].values, 2.0 / 0.3, rtol=1e-9)
        np.testing.assert_allclose(ds["feature_variability"].values[10:-10, 10:-10], _ramp_ci(0.3, D, 5), rtol=1e-9)
    assert out.with_suffix(".png").exists()
    # user mistakes: one line on stderr, exit status 2, nothing written
    bad = tmp_path / "bad.nc"
    assert main(["map", "variability", str(src), "--window", "-1", "--out", str(bad)]) == 2
    assert main(["map", "variability", str(tmp_path / "none.nc"), "--window", "10", "--out", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith("magnav-ins: error:") for line in err)
    assert not bad.exists()
