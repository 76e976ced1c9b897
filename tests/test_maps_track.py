"""TrackMap: along-track distance, distance resampling, nearest-point queries, gradients, road networks."""

from __future__ import annotations

import numpy as np
import pytest

from magnav_ins.core.errors import InputError, MapError
from magnav_ins.core.frames import horizontal_error_m, ned_to_geodetic
from magnav_ins.core.protocols import FieldMap
from magnav_ins.core.types import FieldKind
from magnav_ins.maps.grid import GridMap
from magnav_ins.maps.track import TrackMap, road_network_from_grid

ORIGIN = (0.7, -1.4, 200.0)


def _line(heading: float, n_pts: int = 60, step: float = 2.7):
    s = np.arange(n_pts) * step
    r = np.stack([s * np.cos(heading), s * np.sin(heading), np.zeros_like(s)], axis=-1)
    lat, lon, _ = ned_to_geodetic(r, *ORIGIN)
    return s, r, lat, lon


def test_along_track_distance_and_resampling():
    s, r, lat, lon = _line(np.radians(30.0))
    a = 0.8  # nT per metre along the road
    tm = TrackMap(lat, lon, 200.0, 1000.0 + a * s, kind="total_field_anomaly_nt", max_distance_m=3.0)
    assert isinstance(tm, FieldMap)
    np.testing.assert_allclose(tm.along_track_m, s, atol=1e-6)
    # the local-plane distance agrees with an independent geodetic distance (measured at h = 0, hence shorter by
    # about 200 m / R = 3e-5)
    assert horizontal_error_m(lat[-1], lon[-1], lat[0], lon[0]) == pytest.approx(s[-1], rel=5e-5)
    np.testing.assert_allclose(tm.heading, np.radians(30.0), atol=1e-6)
    rs = tm.resample(1.0)
    assert len(rs) == int(np.floor(s[-1])) + 1
    np.testing.assert_allclose(np.diff(rs.along_track_m), 1.0, atol=1e-6)
    np.testing.assert_allclose(rs.values, 1000.0 + a * rs.along_track_m, atol=1e-6)
    np.testing.assert_allclose(np.hypot(np.diff(rs.northing), np.diff(rs.easting)), 1.0, atol=1e-6)


def test_nearest_value_covers_and_gradient():
    psi = np.radians(-50.0)
    s, r, lat, lon = _line(psi, step=1.0)
    g_n, g_e = 0.3, -0.2  # a planar field a n + b e sampled along the road
    vals = g_n * r[:, 0] + g_e * r[:, 1]
    tm = TrackMap(lat, lon, 200.0, vals, kind="gravity_disturbance_mgal", max_distance_m=4.0)
    # queries 2.5 m and 6 m to the side of point 20 (perpendicular to the road)
    perp = np.array([-np.sin(psi), np.cos(psi), 0.0])
    q = np.stack([r[20] + 2.5 * perp, r[20] + 6.0 * perp])
    q_lat, q_lon, _ = ned_to_geodetic(q, *ORIGIN)
    idx, dist, s_q = tm.nearest(q_lat, q_lon)
    np.testing.assert_array_equal(idx, [20, 20])
    np.testing.assert_allclose(dist, [2.5, 6.0], atol=1e-3)
    np.testing.assert_allclose(s_q, [20.0, 20.0], atol=1e-6)
    v = tm.value(q_lat, q_lon)
    assert v[0] == pytest.approx(vals[20]) and np.isnan(v[1])
    np.testing.assert_array_equal(tm.covers(q_lat, q_lon), [True, False])
    g = tm.gradient_ne(q_lat, q_lon)
    dfds = g_n * np.cos(psi) + g_e * np.sin(psi)
    np.testing.assert_allclose(g[0], dfds * np.array([np.cos(psi), np.sin(psi)]), atol=1e-6)
    assert np.all(np.isnan(g[1]))


def test_vector_values_and_segments_resample_independently():
    s1, _, lat1, lon1 = _line(0.0, n_pts=11, step=1.5)
    s2, _, lat2, lon2 = _line(np.pi / 2, n_pts=9, step=2.0)
    lat, lon = np.concatenate([lat1, lat2]), np.concatenate([lon1, lon2])
    s = np.concatenate([s1, s2])
    vals = np.column_stack([s, 2 * s, -s])
    tm = TrackMap(lat, lon, 200.0, vals, kind=FieldKind.VECTOR_FIELD_NT, segment_id=[3] * 11 + [7] * 9)
    assert tm.n_segments == 2 and tm.total_length_m == pytest.approx(15.0 + 16.0)
    np.testing.assert_allclose(tm.along_track_m[11:], s2, atol=1e-6)
    rs = tm.resample(0.5)
    assert len(rs) == 31 + 33 and set(np.unique(rs.segment_id)) == {3, 7}
    np.testing.assert_allclose(rs.values[:, 1], 2 * rs.along_track_m, atol=1e-6)
    g = tm.gradient_ne(lat2[3:4], lon2[3:4])
    assert g.shape == (1, 3, 2)
    np.testing.assert_allclose(g[0], [[0.0, 1.0], [0.0, 2.0], [0.0, -1.0]], atol=1e-6)


def test_road_network_from_grid_samples_the_grid():
    ax = np.arange(0.0, 201.0, 5.0)
    nn, ee = np.meshgrid(ax, ax, indexing="ij")
    grid = GridMap(
        ax, ax, 0.5 * nn - 0.25 * ee, kind="total_field_anomaly_nt", frame="local", altitude_m=0.0, origin=ORIGIN
    )
    roads = road_network_from_grid(grid, [50.0, 150.0], [20.0, 100.0, 180.0], step_m=1.0)
    assert roads.n_segments == 5 and len(roads) == 5 * 201
    np.testing.assert_allclose(roads.values, 0.5 * roads.northing - 0.25 * roads.easting, atol=1e-6)
    np.testing.assert_allclose(np.abs(roads.heading[:201]), np.pi / 2, atol=1e-6)  # east-west streets
    np.testing.assert_allclose(roads.heading[2 * 201 :], 0.0, atol=1e-6)  # north-south streets
    # a query near a crossing finds a point on one of the two streets
    lat, lon = grid.from_local(np.array([50.4]), np.array([100.3]))
    _, dist, _ = roads.nearest(lat, lon)
    assert dist[0] < 0.6


def test_bad_inputs():
    s, _, lat, lon = _line(0.0, n_pts=5)
    with pytest.raises(MapError, match="coincide"):
        TrackMap(np.r_[lat, lat[-1]], np.r_[lon, lon[-1]], 0.0, np.zeros(6), kind="total_field_anomaly_nt")
    with pytest.raises(MapError, match="shape"):
        TrackMap(lat, lon, 0.0, np.zeros((5, 3)), kind="total_field_anomaly_nt")
    with pytest.raises(MapError, match="radians"):
        TrackMap(np.degrees(lat), lon, 0.0, np.zeros(5), kind="total_field_anomaly_nt")
    tm = TrackMap(lat, lon, 0.0, np.zeros(5), kind="total_field_anomaly_nt")
    with pytest.raises(InputError, match="step_m"):
        tm.resample(0.0)


def test_from_readings_drops_stops_and_distance_samples():
    from magnav_ins.core.types import FieldReadings

    s, _, lat, lon = _line(0.2, n_pts=30, step=1.7)
    # the vehicle stops at point 10 for 25 readings (repeated positions), as at a traffic signal
    rep = np.r_[np.arange(10), np.full(25, 10), np.arange(11, 30)]
    rd = FieldReadings(t=np.arange(rep.size) * 0.02, value=3.0 * s[rep], sigma=1.0, kind="total_field_anomaly_nt")
    tm = TrackMap.from_readings(rd, lat[rep], lon[rep], 200.0)
    assert len(tm) == 30
    dm = TrackMap.from_readings(rd, lat[rep], lon[rep], 200.0, step_m=0.5)
    np.testing.assert_allclose(dm.values, 3.0 * dm.along_track_m, atol=1e-6)
    assert dm.metadata["reading_sigma"] == 1.0
