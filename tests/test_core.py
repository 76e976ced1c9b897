"""core: geodesy round trips and known values, normal gravity against boule, value-type validation, CLI errors."""

from __future__ import annotations

import numpy as np
import pytest

from magnav_ins.core import frames
from magnav_ins.core.errors import InputError
from magnav_ins.core.types import FieldKind, FieldReadings, Fix, ImuBatch, NavState
from magnav_ins.ins import earth


def test_ecef_round_trip(rng):
    lat = rng.uniform(-np.pi / 2 + 1e-6, np.pi / 2 - 1e-6, 2000)
    lon = rng.uniform(-np.pi, np.pi, 2000)
    h = rng.uniform(-1e4, 1e6, 2000)
    lat2, lon2, h2 = frames.ecef_to_geodetic(frames.geodetic_to_ecef(lat, lon, h))
    assert np.max(np.abs(lat2 - lat)) < 1e-12
    assert np.max(np.abs(frames.wrap_angle(lon2 - lon))) < 1e-12
    assert np.max(np.abs(h2 - h)) < 1e-6


def test_point_forms_are_the_array_forms_bit_for_bit(rng):
    """The one-point twins the fusers call per IMU sample (ecef_to_geodetic_point, C_en_point, gravity_n_point)
    give exactly the numbers of the array functions, not merely close ones (results must not move)."""
    lat = rng.uniform(-np.pi / 2 + 1e-6, np.pi / 2 - 1e-6, 500)
    lon = rng.uniform(-np.pi, np.pi, 500)
    h = rng.uniform(-1e3, 2e4, 500)
    r = frames.geodetic_to_ecef(lat, lon, h)
    for k in range(len(lat)):
        assert [float(v) for v in frames.ecef_to_geodetic_point(*r[k])] == [
            float(v) for v in frames.ecef_to_geodetic(r[k])
        ]
        assert np.array_equal(frames.C_en_point(lat[k], lon[k]), frames.C_en(lat[k], lon[k]))
        assert np.array_equal(earth.gravity_n_point(lat[k], h[k]), earth.gravity_n(float(lat[k]), float(h[k])))


def test_ecef_known_points():
    # equator / prime meridian, and the north pole
    np.testing.assert_allclose(frames.geodetic_to_ecef(0.0, 0.0, 0.0), [frames.WGS84_A, 0, 0], atol=1e-9)
    np.testing.assert_allclose(frames.geodetic_to_ecef(np.pi / 2, 0.0, 100.0), [0, 0, frames.WGS84_B + 100], atol=1e-6)


def test_radii_known_values():
    r_n, r_e = frames.radii_of_curvature(0.0)
    assert r_e == pytest.approx(frames.WGS84_A)
    assert r_n == pytest.approx(frames.WGS84_A * (1 - frames.WGS84_E2))
    r_n, r_e = frames.radii_of_curvature(np.pi / 2)
    assert r_n == pytest.approx(r_e)  # both equal a^2/b at the pole
    assert r_e == pytest.approx(frames.WGS84_A**2 / frames.WGS84_B)


def test_ned_round_trip_and_small_displacements():
    lat0, lon0, h0 = np.deg2rad(-22.0), np.deg2rad(140.6), 300.0
    ned = np.array([[1000.0, -2000.0, -50.0], [0.0, 0.0, 0.0], [-5e4, 3e4, 100.0]])
    lat, lon, h = frames.ned_to_geodetic(ned, lat0, lon0, h0)
    np.testing.assert_allclose(frames.geodetic_to_ned(lat, lon, h, lat0, lon0, h0), ned, atol=1e-6)
    dlat, dlon = frames.meters_to_latlon(100.0, 200.0, lat0, h0)
    dn, de = frames.latlon_to_meters(dlat, dlon, lat0, h0)
    assert dn == pytest.approx(100.0) and de == pytest.approx(200.0)
    # small-displacement formula agrees with the exact NED transform to 5 mm over 200 m
    exact = frames.geodetic_to_ned(lat0 + dlat, lon0 + dlon, h0, lat0, lon0, h0)
    np.testing.assert_allclose(exact[:2], [100.0, 200.0], atol=5e-3)


def test_euler_quaternion_round_trip(rng):
    roll, pitch, yaw = rng.uniform(-3, 3, 100), rng.uniform(-1.5, 1.5, 100), rng.uniform(-3, 3, 100)
    q = frames.q_nb_from_euler(roll, pitch, yaw)
    r2, p2, y2 = frames.euler_from_q_nb(q)
    np.testing.assert_allclose(frames.wrap_angle(r2 - roll), 0, atol=1e-9)
    np.testing.assert_allclose(p2, pitch, atol=1e-9)
    np.testing.assert_allclose(frames.wrap_angle(y2 - yaw), 0, atol=1e-9)
    # yaw of 90 deg maps body forward onto east
    c = frames.C_nb_from_q(frames.q_nb_from_euler(0.0, 0.0, np.pi / 2))
    np.testing.assert_allclose(c @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_skew_is_cross_product(rng):
    a, b = rng.normal(size=3), rng.normal(size=3)
    np.testing.assert_allclose(frames.skew(a) @ b, np.cross(a, b))


def test_normal_gravity_against_boule():
    boule = pytest.importorskip("boule")
    lat_deg = np.linspace(-90, 90, 181)
    for h in (0.0, 100.0, 10_000.0, 30_000.0):
        ref_mgal = boule.WGS84.normal_gravity((np.zeros_like(lat_deg), lat_deg, np.full_like(lat_deg, h)))
        ours_mgal = earth.normal_gravity(np.deg2rad(lat_deg), h) * 1e5
        assert np.max(np.abs(ours_mgal - ref_mgal)) < 0.01  # mGal
    # the mechanisation's second-order form stays within 0.1 mGal below 10 km
    g_d = earth.gravity_n(np.deg2rad(lat_deg), 10_000.0)[:, 2]
    assert np.max(np.abs(g_d - earth.normal_gravity(np.deg2rad(lat_deg), 10_000.0))) < 1e-6


def test_somigliana_defining_values():
    assert earth.somigliana(0.0) == pytest.approx(frames.WGS84_GAMMA_E, abs=1e-10)
    assert earth.somigliana(np.pi / 2) == pytest.approx(frames.WGS84_GAMMA_P, abs=1e-10)


def test_earth_rates():
    w = earth.omega_ie_n(0.0)
    np.testing.assert_allclose(w, [frames.WGS84_OMEGA_E, 0, 0])
    # flying east at the equator: transport rate about north equals v / (R_E + h)
    rho = earth.omega_en_n(0.0, 0.0, [0.0, 100.0, 0.0])
    assert rho[0] == pytest.approx(100.0 / frames.WGS84_A)
    # coriolis on an eastward velocity at the equator points up (negative down)
    assert earth.coriolis_n(0.0, 0.0, [0.0, 100.0, 0.0])[2] < 0


def test_value_types_validate():
    with pytest.raises(InputError, match="same length"):
        ImuBatch(np.arange(3.0), np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(InputError, match="shape"):
        FieldReadings(np.arange(3.0), np.zeros(3), 1.0, FieldKind.VECTOR_FIELD_NT)
    with pytest.raises(InputError, match="sigma"):
        FieldReadings(np.arange(3.0), np.zeros(3), float("nan"), "total_field_anomaly_nt")
    nav = NavState(0.0, 0.1, 0.2, 10.0, [1, 2, 3], [0, 0, 0, 2])
    np.testing.assert_allclose(nav.q_nb, [0, 0, 0, 1])
    nf = Fix.no_fix(5.0, "off the map", "ml")
    assert not nf.available and nf.reason == "off the map" and np.isnan(nf.lat)


def test_atomic_write_mode_and_no_leftovers(tmp_path):
    import os

    from magnav_ins.core.atomic import atomic_path, write_text_atomic

    out = tmp_path / "a.txt"
    write_text_atomic(out, "x")
    umask = os.umask(0)
    os.umask(umask)
    assert out.read_text() == "x" and (out.stat().st_mode & 0o777) == (0o666 & ~umask)
    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "b.txt") as tmp:
            tmp.write_text("half")
            raise RuntimeError("writer failed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_cli_joins_negative_comma_lists_to_their_option():
    from magnav_ins.cli import _join_negative_lists

    assert _join_negative_lists(["bridge", "--init", "-21.93,140.6,400,-5"]) == ["bridge", "--init=-21.93,140.6,400,-5"]
    assert _join_negative_lists(["--seed", "-3"]) == ["--seed", "-3"]  # plain negative numbers argparse handles itself
    assert _join_negative_lists(["--init=-1,2,3,4"]) == ["--init=-1,2,3,4"]
