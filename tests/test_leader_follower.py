"""Storms' leader-follower pieces (seed 004 sec. 3.5, 4.5): the cross-track error of Diagram 3.1, the PID tracking
controller (sec. 3.5.2, Fig. 3.6), the Table 4.2 counts and one follower run."""

from __future__ import annotations

import numpy as np
import pytest

from magnav_ins.studies.leader_follower import (
    FollowerOutcome,
    LeaderFollowerConfig,
    PidTracker,
    cross_track,
    run_follower,
    table_4_2,
)


def test_cross_track_error_by_hand():
    track = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])  # north 10 m, then east 10 m
    e, tang, k, s = cross_track(np.array([4.0, 0.3]), track, -1)
    assert e == pytest.approx(0.3) and tang == pytest.approx([1.0, 0.0]) and k == 0 and s == pytest.approx(4.0)
    e, tang, k, s = cross_track(np.array([10.2, 6.0]), track, -1)  # south of... north of the east leg: its left
    assert e == pytest.approx(-0.2) and tang == pytest.approx([0.0, 1.0]) and k == 1 and s == pytest.approx(16.0)


def test_pid_step_response_matches_the_closed_loop_of_storms_gains():
    """Double-integrator plant x'' = u (eq. 3.7's B), Storms' gains Kp 10, Ki 0.05, Kd 3.5: the closed loop is
    close to s^2 + 3.5 s + 10 (zeta = 0.553, omega_n = 3.16 rad/s), overshoot exp(-pi zeta / sqrt(1 - zeta^2)) =
    12.5 %. Storms' design goals (Fig. 3.6): rise time < 1 s, settling close to 2 s (met); overshoot < 0.1 m for a
    1 m step (not met by these gains on this plant: 0.126 m)."""
    pid, dt, x, v, xs = PidTracker(), 1e-3, 0.0, 0.0, []
    for _ in range(6000):
        u = pid.command(x - 1.0, dt)
        v += u * dt
        x += v * dt
        xs.append(x)
    xs = np.array(xs)
    t = np.arange(len(xs)) * dt
    rise = t[np.argmax(xs >= 0.9)] - t[np.argmax(xs >= 0.1)]
    settle = t[np.flatnonzero(np.abs(xs - 1.0) > 0.02)[-1]]
    zeta = 3.5 / (2.0 * np.sqrt(10.0))
    assert rise < 1.0
    assert 1.5 < settle < 2.5
    assert xs.max() - 1.0 == pytest.approx(np.exp(-np.pi * zeta / np.sqrt(1 - zeta**2)), abs=0.01)


def test_table_4_2_counts():
    cfg = LeaderFollowerConfig()
    outs = [FollowerOutcome(s, False, 0, 0.1) for s in (-3.0, 0.5, 10.0, 12.0, 16.5)]
    assert table_4_2(outs, cfg) == {"runs": 5, "completed": 1, "successful": 3, "past_turn": 4, "not_making_turn": 1}


def test_follower_on_a_rich_map_completes_the_route():
    """On the Storms-like hallway with variations everywhere, a follower with the leader's 4-sensor map makes it
    down the side hallway and stays within the hallway's half-width of the leader's true track."""
    from magnav_ins.maps.synthetic import hallway_map

    fmap = hallway_map(np.random.default_rng(41), origin=(np.radians(39.78), np.radians(-84.08), 0.0),
                       main_length_m=22.0, side_length_m=12.0)  # fmt: skip
    half = 2.286 / 2
    route = np.array([[0.0, half], [22.0 - half, half], [22.0 - half, 12.0]])
    cfg = LeaderFollowerConfig(sensors=4, completed_m=8.0, successful_m=5.0)
    out = run_follower(cfg, fmap, route, route[1], np.random.default_rng(3))
    assert not out.hit_wall and out.side_m >= 8.0
    assert out.attempts > 20 and out.fixes / out.attempts > 0.9
    assert out.cross_rms_m < 0.5


def test_hallway_map_quiet_centre_and_quiet_stretch():
    from magnav_ins.maps.synthetic import hallway_map

    kw = {"main_length_m": 30.0, "side_length_m": 15.0}
    plain = np.asarray(hallway_map(np.random.default_rng(5), **kw).values)
    quiet = np.asarray(
        hallway_map(np.random.default_rng(5), centre_fraction=0.1, quiet_side_m=(8.0, 12.0), **kw).values
    )
    mean = np.array([40.0, 100.0, 230.0]) * 100.0  # the map's constant part (mG -> nT)
    dev_p, dev_q = plain - mean, quiet - mean  # the same random field, rescaled
    centre, wall = 3, 0  # main hallway columns: centre line (1.143 m) and the west wall
    assert np.allclose(dev_q[:60, centre], 0.1 * dev_p[:60, centre])
    assert np.allclose(dev_q[:60, wall], dev_p[:60, wall])
    side_row = plain.shape[0] - 1  # the side hallway's north wall: quiet only in the stretch 8-12 m from its start
    cols = np.arange(plain.shape[1])
    in_stretch = (cols * 0.381 - 2.286 >= 8.0) & (cols * 0.381 - 2.286 <= 12.0)
    assert np.allclose(dev_q[side_row, in_stretch], 0.1 * dev_p[side_row, in_stretch])
    assert np.allclose(dev_q[side_row, ~in_stretch & (cols > 8)], dev_p[side_row, ~in_stretch & (cols > 8)])
