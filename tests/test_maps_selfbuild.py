"""Self-building maps: Welford/Chan accumulation, sigma/sqrt(count) error, merging, amalgamation, leader maps."""

from __future__ import annotations

import numpy as np
import pytest

from magnav_ins.core.errors import InputError, MapError
from magnav_ins.core.types import FieldKind
from magnav_ins.maps import selfbuild as sb
from magnav_ins.maps import synthetic as syn

ORIGIN = (0.62, 2.6, 50.0)


def _truth(rng: np.random.Generator, kind: FieldKind = FieldKind.TOTAL_FIELD_ANOMALY_NT):
    return syn.random_field_map((60, 80), 2.0, 10.0, 50.0, rng, kind=kind, origin=ORIGIN)


def _readings(truth, rng, n, sigma):
    ny, nx = truth.shape
    iy, ix = rng.integers(0, ny, n), rng.integers(0, nx, n)
    north, east = truth.axes
    lat, lon = truth.from_local(north[iy], east[ix])
    clean = truth.values[iy, ix]
    return lat, lon, clean + sigma * rng.standard_normal(clean.shape), iy, ix


def test_accumulated_map_error_shrinks_like_sigma_over_sqrt_count():
    rng = np.random.default_rng(11)
    truth = _truth(rng)
    sigma = 4.0
    acc = sb.MapAccumulator.like(truth)
    lat, lon, z, _, _ = _readings(truth, rng, 60 * 80 * 12, sigma)
    for chunk in np.array_split(np.arange(z.size), 7):  # batches of any size give the same statistics
        acc.add(lat[chunk], lon[chunk], z[chunk])
    built = acc.result()
    err = built.mean.values - truth.values
    for n in (4, 8, 12, 16, 20):
        cells = built.count == n
        assert cells.sum() > 30
        assert np.sqrt(np.mean(err[cells] ** 2)) == pytest.approx(sigma / np.sqrt(n), rel=0.2)
    # the per-node sample variance estimates sigma^2
    assert np.nanmean(built.variance[built.count >= 10]) == pytest.approx(sigma**2, rel=0.05)
    # the pooled variance is sigma^2 and sigma^2/n is calibrated: normalised errors have unit variance
    assert built.pooled_variance == pytest.approx(sigma**2, rel=0.03)
    ok = built.count >= 1
    # (4800 nodes: the mean of chi^2_1 values has a standard deviation of 0.02)
    assert np.mean(err[ok] ** 2 / built.variance_of_mean()[ok]) == pytest.approx(1.0, abs=0.08)
    # with each node's own variance the normalised error is Student-t: E[t^2] = (n - 1) / (n - 3)
    ok = built.count >= 8
    t2 = err[ok] ** 2 / built.variance_of_mean(pooled=False)[ok]
    n = built.count[ok]
    assert np.mean(t2) == pytest.approx(np.mean((n - 1) / (n - 3)), rel=0.1)


def test_batches_and_merge_equal_direct_statistics():
    rng = np.random.default_rng(5)
    truth = _truth(rng, FieldKind.VECTOR_FIELD_NT)
    lat, lon, z, iy, ix = _readings(truth, rng, 3000, 2.0)
    a, b = sb.MapAccumulator.like(truth), sb.MapAccumulator.like(truth)
    a.add(lat[:1000], lon[:1000], z[:1000])
    a.add(lat[1000:1700], lon[1000:1700], z[1000:1700])
    b.add(lat[1700:], lon[1700:], z[1700:])
    a.merge(b)
    flat = iy * truth.shape[1] + ix
    cell = np.bincount(flat).argmax()
    direct = z[flat == cell]
    i, j = divmod(int(cell), truth.shape[1])
    assert a.count[i, j] == direct.shape[0]
    np.testing.assert_allclose(a.mean()[i, j], direct.mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(a.variance()[i, j], direct.var(axis=0, ddof=1), rtol=1e-10)
    assert a.count.sum() == 3000


def test_off_grid_and_nan_readings_are_skipped():
    rng = np.random.default_rng(1)
    truth = _truth(rng)
    acc = sb.MapAccumulator.like(truth)
    lat, lon = truth.from_local(np.array([10.0, 5000.0, 20.0]), np.array([10.0, 10.0, 30.0]))
    assert acc.add(lat, lon, np.array([1.0, 2.0, np.nan])) == 1
    with pytest.raises(InputError):
        acc.add(lat, lon, np.zeros(2))
    from magnav_ins.core.types import FieldReadings

    rd = FieldReadings(t=np.arange(3.0), value=np.ones((3, 3)), sigma=1.0, kind="vector_field_nt")
    with pytest.raises(InputError, match="vector_field_nt"):
        acc.add_readings(rd, lat, lon)
    rd = FieldReadings(t=np.arange(3.0), value=np.array([5.0, 6.0, 7.0]), sigma=1.0, kind="total_field_anomaly_nt")
    assert acc.add_readings(rd, lat, lon) == 2
    with pytest.raises(MapError, match="3 reading"):
        acc.result(min_count=3)
    assert acc.result(min_count=2).count.max() == 2


def test_amalgamation_keeps_the_better_cell():
    rng = np.random.default_rng(9)
    truth = _truth(rng)
    good, poor = sb.MapAccumulator.like(truth), sb.MapAccumulator.like(truth)
    lat, lon, z, _, _ = _readings(truth, rng, 40_000, 1.0)
    good.add(lat[: z.size // 2], lon[: z.size // 2], z[: z.size // 2])
    lat, lon, z, _, _ = _readings(truth, rng, 40_000, 10.0)
    poor.add(lat, lon, z)
    maps = [poor.result(), good.result()]
    merged = sb.amalgamate(maps)
    both = np.isfinite(maps[0].mean.values) & np.isfinite(maps[1].mean.values)
    only_poor = np.isfinite(maps[0].mean.values) & ~np.isfinite(maps[1].mean.values)
    assert only_poor.any()

    def rms(m, cells):
        return np.sqrt(np.mean((m.mean.values[cells] - truth.values[cells]) ** 2))

    # where both have data the good (sigma 1) map wins; where only the poor one does, it fills the gap
    assert rms(merged, both) == pytest.approx(rms(maps[1], both))
    assert rms(merged, both) < 0.2 * rms(maps[0], both)
    np.testing.assert_array_equal(merged.mean.values[only_poor], maps[0].mean.values[only_poor])
    by_count = sb.amalgamate(maps, by="count")
    assert np.all(by_count.count >= np.maximum(maps[0].count, maps[1].count))
    # known noise levels give the same choice as the pooled estimates
    known = sb.amalgamate(maps, reading_sigma=[10.0, 1.0])
    np.testing.assert_array_equal(known.count, merged.count)
    with pytest.raises(InputError):
        sb.amalgamate([])


def test_leader_follower_map_from_estimated_positions():
    rng = np.random.default_rng(2)
    hall = syn.hallway_map(rng)
    # leader drives up the main hallway's centre line with three sensors 0.381 m apart (Storms sec. 3.5)
    s = np.arange(0.0, 32.0, 0.25)
    north_true = s
    east_true = np.full_like(s, 1.143)
    offsets = np.array([[0.0, -0.381], [0.0, 0.0], [0.0, 0.381]])
    lat, lon = hall.from_local(north_true, east_true)
    n_s, e_s = sb.sensor_positions(lat, lon, np.zeros_like(s), offsets, hall.origin)
    readings = hall.value_ne(n_s, e_s)  # (N, 3 sensors, 3 axes)
    bias = np.array([0.7, -0.4])  # the leader's estimate is off by a constant
    lmap = sb.leader_follower_map(
        n_s + bias[0], e_s + bias[1], readings, kind="vector_field_nt", spacing_m=0.1, origin=hall.origin
    )
    # the follower's map, read at estimated positions, reproduces the field at true positions
    q_n, q_e = np.linspace(2.0, 30.0, 200), np.full(200, 1.143 + 0.2)
    got = lmap.value_ne(q_n + bias[0], q_e + bias[1])
    want = hall.value_ne(q_n, q_e)
    field_std = np.nanstd(hall.values, axis=(0, 1))  # ~1200 nT per axis
    assert np.all(np.sqrt(np.mean((got - want) ** 2, axis=0)) < 0.1 * field_std)
    # nothing is invented beyond the sensors' span
    assert np.all(np.isnan(lmap.value_ne(np.array([10.0]) + bias[0], np.array([2.2]) + bias[1])))
