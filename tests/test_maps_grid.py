"""GridMap and the interpolation kernels against analytic fields (independent truth)."""

from __future__ import annotations

import numpy as np
import pytest

from magnav_ins.core.errors import MapError
from magnav_ins.core.frames import meters_to_latlon
from magnav_ins.core.types import FieldKind
from magnav_ins.maps.grid import GridMap

DEG = np.pi / 180.0
KIND = FieldKind.TOTAL_FIELD_ANOMALY_NT


def _geo_map(f, ny=21, nx=31, kind=KIND, **kw):
    lat = np.linspace(-20.0, -19.0, ny) * DEG
    lon = np.linspace(140.0, 141.5, nx) * DEG
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    return GridMap(lat, lon, f(la, lo), kind=kind, frame="geodetic", altitude_m=100.0, name="t", **kw)


def _bilin(la, lo):
    return 3.0 + 200.0 * la - 50.0 * lo + 1e3 * la * lo


def _quad(la, lo):
    y, x = la / DEG + 19.5, lo / DEG - 140.7
    return 5.0 + 3.0 * y - 2.0 * x + 7.0 * y * y - 4.0 * x * y + 2.5 * x * x + 3.0 * x * x * y * y


def _queries(rng, n=2000):
    return rng.uniform(-20.0, -19.0, n) * DEG, rng.uniform(140.0, 141.5, n) * DEG


def test_bilinear_exact_on_bilinear_field(rng):
    m = _geo_map(_bilin)
    la, lo = _queries(rng)
    np.testing.assert_allclose(m.value(la, lo), _bilin(la, lo), rtol=0, atol=1e-9)


def test_bicubic_exact_on_biquadratic_field_up_to_the_border(rng):
    m = _geo_map(_quad)
    la, lo = _queries(rng)
    la = np.r_[la, -20.0 * DEG, -19.0 * DEG]
    lo = np.r_[lo, 140.0 * DEG, 141.5 * DEG]
    np.testing.assert_allclose(m.value(la, lo, method="bicubic"), _quad(la, lo), rtol=0, atol=1e-9)
    # bilinear is not exact on this field (so the test above can fail)
    assert np.max(np.abs(m.value(la, lo) - _quad(la, lo))) > 1e-4


@pytest.mark.parametrize("method", ["bilinear", "bicubic"])
def test_gradient_matches_finite_differences(rng, method):
    m = _geo_map(lambda la, lo: 100 * np.sin(la / DEG * 7) * np.cos(lo / DEG * 5), ny=41, nx=61)
    la, lo = _queries(rng, 300)
    la = np.clip(la, -19.99 * DEG, -19.01 * DEG)
    lo = np.clip(lo, 140.01 * DEG, 141.49 * DEG)
    g = m.gradient_ne(la, lo, method=method)
    d = 0.01  # m: small against the ~2.8 km cells, so FD stays inside one cell almost surely
    dlat, _ = meters_to_latlon(d, 0.0, la, 100.0)
    _, dlon = meters_to_latlon(0.0, d, la, 100.0)
    fd_n = (m.value(la + dlat, lo, method=method) - m.value(la - dlat, lo, method=method)) / (2 * d)
    fd_e = (m.value(la, lo + dlon, method=method) - m.value(la, lo - dlon, method=method)) / (2 * d)
    ok = np.abs(fd_n) < 1e3  # drop the rare point sitting on a cell edge
    np.testing.assert_allclose(g[ok, 0], fd_n[ok], rtol=1e-4, atol=1e-8)
    np.testing.assert_allclose(g[ok, 1], fd_e[ok], rtol=1e-4, atol=1e-8)


def test_nan_off_map_and_next_to_missing_nodes():
    vals = np.ones((5, 6))
    vals[2, 3] = np.nan
    m = GridMap(
        np.arange(5) * 10.0,
        np.arange(6) * 10.0,
        vals,
        kind=KIND,
        frame="local",
        altitude_m=0.0,
        origin=(-0.6, 2.4, 0.0),
    )
    n = np.array([5.0, 25.0, 15.0, -1.0, 41.0, 0.01, 39.99])
    e = np.array([5.0, 35.0, 25.0, 5.0, 5.0, 0.01, 49.99])
    v = m.value_ne(n, e)
    np.testing.assert_array_equal(np.isnan(v), [False, True, True, True, True, False, False])
    lat, lon = m.from_local(n, e)
    np.testing.assert_array_equal(m.covers(lat, lon), ~np.isnan(v))
    # bicubic needs the 4x4 stencil: a point two cells away from the hole is still finite, one inside is not
    assert np.isnan(m.value_ne([15.0], [15.0], method="bicubic"))[0]
    assert np.isfinite(m.value_ne([5.0], [5.0], method="bicubic"))[0]


def test_local_frame_value_and_gradient_against_geodetic_truth(rng):
    origin = (-21.0 * DEG, 140.0 * DEG, 300.0)
    north = np.linspace(-10e3, 10e3, 81)
    east = np.linspace(-10e3, 10e3, 101)
    nn, ee = np.meshgrid(north, east, indexing="ij")
    m = GridMap(north, east, 0.01 * nn - 0.02 * ee, kind=KIND, frame="local", altitude_m=300.0, origin=origin)
    n = rng.uniform(-9e3, 9e3, 200)
    e = rng.uniform(-9e3, 9e3, 200)
    lat, lon = m.from_local(n, e)
    np.testing.assert_allclose(m.to_local(lat, lon), (n, e), atol=1e-6)
    np.testing.assert_allclose(m.value(lat, lon), 0.01 * n - 0.02 * e, atol=1e-6)
    g = m.gradient_ne(lat, lon)
    d = 1.0
    dlat, _ = meters_to_latlon(d, 0.0, lat, 300.0)
    _, dlon = meters_to_latlon(0.0, d, lat, 300.0)
    fd_n = (m.value(lat + dlat, lon) - m.value(lat - dlat, lon)) / (2 * d)
    fd_e = (m.value(lat, lon + dlon) - m.value(lat, lon - dlon)) / (2 * d)
    np.testing.assert_allclose(g[:, 0], fd_n, atol=2e-6)
    np.testing.assert_allclose(g[:, 1], fd_e, atol=2e-6)


def test_vector_map_shapes(rng):
    lat = np.linspace(0.1, 0.2, 11)
    lon = np.linspace(0.3, 0.4, 12)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    v = np.stack([la, lo, la + lo], axis=-1) * 1e4
    m = GridMap(lat, lon, v, kind=FieldKind.VECTOR_FIELD_NT, frame="geodetic", altitude_m=0.0)
    q = rng.uniform(0.1, 0.2, 7), rng.uniform(0.3, 0.4, 7)
    out = m.value(*q)
    assert out.shape == (7, 3)
    np.testing.assert_allclose(out, np.stack([q[0], q[1], q[0] + q[1]], axis=-1) * 1e4, rtol=1e-12)
    assert m.gradient_ne(*q).shape == (7, 3, 2)
    assert m.covers(*q).all()


def test_longitude_wrap_and_spacing():
    lat = np.linspace(-1.0, 1.0, 5) * DEG
    lon = np.linspace(170.0, 190.0, 21) * DEG  # crosses the antimeridian
    m = GridMap(lat, lon, np.tile(np.arange(21.0), (5, 1)), kind=KIND, frame="geodetic", altitude_m=0.0)
    np.testing.assert_allclose(m.value([0.0], [-175.0 * DEG]), [15.0], atol=1e-9)
    dn, de = m.spacing_m
    assert abs(dn - 0.5 * DEG * 6335439.3) < 1.0 and abs(de - DEG * 6378137.0) < 1.0


def test_refuses_bad_grids():
    with pytest.raises(MapError, match="strictly increasing"):
        GridMap([2.0, 1.0], [0.0, 1.0], np.ones((2, 2)), kind=KIND, frame="local", altitude_m=0, origin=(0, 0, 0))
    with pytest.raises(MapError, match="radians"):
        GridMap([-30.0, -20.0], [140.0, 141.0], np.ones((2, 2)), kind=KIND, frame="geodetic", altitude_m=0)
    with pytest.raises(MapError, match="every value is NaN"):
        GridMap([0.0, 0.1], [0.0, 0.1], np.full((2, 2), np.nan), kind=KIND, frame="geodetic", altitude_m=0)
    with pytest.raises(MapError, match="origin"):
        GridMap([0.0, 1.0], [0.0, 1.0], np.ones((2, 2)), kind=KIND, frame="local", altitude_m=0)


def test_altitude_is_explicit():
    m = _geo_map(_bilin, altitude_tolerance_m=50.0)
    la, lo = np.array([-19.5 * DEG]), np.array([140.5 * DEG])
    assert np.isfinite(m.value(la, lo, h=120.0)).all()
    with pytest.raises(MapError, match="upward-continue"):
        m.value(la, lo, h=1000.0)
    m2 = _geo_map(_bilin)  # no tolerance: h ignored
    np.testing.assert_array_equal(m2.value(la, lo, h=5000.0), m2.value(la, lo))


def test_gridmap_is_a_fieldmap():
    from magnav_ins.core.protocols import FieldMap

    assert isinstance(_geo_map(_bilin), FieldMap)


def test_query_on_the_last_node_is_on_the_map():
    m = _geo_map(_bilin)
    la, lo = np.array([-19.0 * DEG, -20.0 * DEG]), np.array([141.5 * DEG, 140.0 * DEG])
    for meth in ("bilinear", "bicubic"):
        np.testing.assert_allclose(m.value(la, lo, method=meth), _bilin(la, lo), atol=1e-9)


def test_compiled_tangent_plane_matches_core_frames(rng):
    from magnav_ins.core.frames import geodetic_to_ned, ned_to_geodetic
    from magnav_ins.maps.tangent import geodetic_to_tangent, tangent_to_geodetic

    lat0, lon0, h0 = -0.38, 2.455, 400.0
    lat = lat0 + rng.uniform(-0.01, 0.01, 500)  # +-60 km
    lon = lon0 + rng.uniform(-0.01, 0.01, 500)
    n, e = geodetic_to_tangent(lat, lon, lat0, lon0, h0)
    ref = geodetic_to_ned(lat, lon, h0, lat0, lon0, h0)
    np.testing.assert_allclose(n, ref[:, 0], atol=1e-7)
    np.testing.assert_allclose(e, ref[:, 1], atol=1e-7)
    # inverse: back to the same points (height h0), and the point lies on the NED ray of (n, e, down)
    la, lo = tangent_to_geodetic(n, e, lat0, lon0, h0)
    np.testing.assert_allclose(la, lat, atol=1e-14)
    np.testing.assert_allclose(lo, lon, atol=1e-14)
    la2, lo2, h2 = ned_to_geodetic(ref, lat0, lon0, h0)
    np.testing.assert_allclose(h2, h0, atol=1e-6)
    np.testing.assert_allclose(la2, la, atol=1e-14)
