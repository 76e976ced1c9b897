"""Shockley's body-frame vector road maps (seed 003 sec. 4.1-4.2; ``maps.track``): the same road read the other way
reads differently; per-direction maps and the navigation frame with the attitude applied agree."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from magnav_ins.core.errors import MapError
from magnav_ins.maps.track import TrackMap, body_to_ned, ned_to_body

ORIGIN = (np.radians(39.78), np.radians(-84.08), 0.0)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))


def _road_east(n: int = 50) -> TrackMap:
    from magnav_ins.maps.tangent import tangent_to_geodetic

    e = np.arange(n, dtype=float)
    lat, lon = tangent_to_geodetic(np.zeros(n), e, *ORIGIN)
    v = np.column_stack([200.0 + 10 * np.sin(e / 5), -21.0 + 5 * np.cos(e / 7), 493.0 + e])  # NED, nT
    return TrackMap(lat, lon, 0.0, v, kind="vector_field_nt", origin=ORIGIN)


def test_ned_body_rotation_by_hand_and_round_trip():
    v = np.array([[200.0, -21.0, 493.0]])
    assert ned_to_body(v, 0.0) == pytest.approx(v)
    assert ned_to_body(v, np.pi / 2) == pytest.approx(np.array([[-21.0, -200.0, 493.0]]))  # heading east: x = E, y = -N
    psi = np.array([0.3, 1.7, -2.2])
    w = np.array([[1.0, 2.0, 3.0], [-4.0, 5.0, 6.0], [7.0, -8.0, 9.0]])
    assert body_to_ned(ned_to_body(w, psi), psi) == pytest.approx(w)


def test_reversed_direction_reads_differently_on_a_body_frame_road_map():
    road = _road_east()
    fwd, rev = road.directional(False), road.directional(True)
    assert np.allclose(road.heading, np.pi / 2)
    # driving east: x = E, y = -N; driving west the same road reads x = -E, y = N: x and y flip, z stays
    lat, lon = road.lat[10:20], road.lon[10:20]
    f, r = fwd.value(lat, lon), rev.value(lat, lon)
    assert f[:, :2] == pytest.approx(-r[:, :2])
    assert f[:, 2] == pytest.approx(r[:, 2])
    assert np.max(np.abs(f[:, :2] - r[:, :2])) > 100.0  # they do differ (by twice the horizontal field)
    assert f == pytest.approx(ned_to_body(road.values[10:20], np.pi / 2))
    # reverse map points run backwards along the road; applying each map's own attitude gives the NED field back
    assert rev.along_track_m[0] == 0.0 and rev.easting[0] == pytest.approx(road.easting[-1])
    assert body_to_ned(rev.values, rev.heading) == pytest.approx(road.values[::-1])
    scalar = TrackMap(road.lat, road.lon, 0.0, road.values[:, 0], kind="total_field_anomaly_nt", origin=ORIGIN)
    with pytest.raises(MapError, match="vector"):
        scalar.directional()


def test_per_direction_maps_match_where_a_one_direction_map_fails():
    import shockley_vector_roads as S

    track = S.road_map()
    c = S.Candidates(track, 4)
    rng = np.random.default_rng(5)
    zero = {"noise": S.SAME, "uncal": False, "compose": "raw", "bias": lambda _r: np.zeros(3)}
    per = [S.trial(c, {**zero, "map": "per_direction"}, rng, 4)[1] for _ in range(60)]
    one = [S.trial(c, {**zero, "map": "one_direction"}, rng, 4)[1] for _ in range(60)]
    assert np.mean(np.array(per) < 3.0) > 0.85
    assert np.mean(np.array(one) < 3.0) < 0.75  # about half the sections are driven the other way
