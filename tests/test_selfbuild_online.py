"""Self-building maps while navigating (seed 000 sec. 2.1, 4.0; seed 003 sec. 6.2): weighted readings, ageing
amalgamation that prefers the most current readings, the online builder's trust gate, and the two-lap study."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from magnav_ins.core.errors import InputError
from magnav_ins.maps import selfbuild as sb
from magnav_ins.maps.grid import GridMap

ORIGIN = (np.radians(45.0), np.radians(7.0), 0.0)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))


def _grid(values: float = 0.0) -> GridMap:
    ax = np.arange(0.0, 5.0, 1.0)
    return GridMap(ax, ax, np.full((5, 5), values), kind="total_field_anomaly_nt", frame="local", altitude_m=0.0,
                   origin=ORIGIN)  # fmt: skip


def _at(g: GridMap, n: float, e: float):
    return g.from_local(np.array([n]), np.array([e]))


def test_weighted_readings_give_the_inverse_variance_mean_by_hand():
    g = _grid()
    acc = sb.MapAccumulator.like(g)
    lat, lon = _at(g, 2.0, 3.0)
    acc.add(np.repeat(lat, 2), np.repeat(lon, 2), [10.0, 20.0], weights=[1 / 4.0, 1 / 1.0], t=[5.0, 9.0])
    acc.add(lat, lon, [13.0], weights=[1 / 4.0], t=3.0)
    built = acc.result()
    # (10/4 + 20/1 + 13/4) / (1/4 + 1 + 1/4) = 25.75 / 1.5
    assert built.mean.values[2, 3] == pytest.approx(25.75 / 1.5)
    assert built.variance_of_mean()[2, 3] == pytest.approx(1.0 / 1.5)
    assert built.last_t[2, 3] == 9.0 and built.count[2, 3] == 3
    assert np.isnan(built.last_t[0, 0]) and built.count[0, 0] == 0
    # unit weights: the plain mean and sample variance as before
    plain = sb.MapAccumulator.like(g)
    plain.add(np.repeat(lat, 3), np.repeat(lon, 3), [10.0, 20.0, 13.0])
    b2 = plain.result()
    assert b2.mean.values[2, 3] == pytest.approx(43.0 / 3.0)
    assert b2.variance[2, 3] == pytest.approx(np.var([10.0, 20.0, 13.0], ddof=1))
    assert b2.weight is None


def test_amalgamation_prefers_the_most_current_contribution():
    """Old map: 4 readings of variance 1 at t = 0 (value 10); new map: 1 reading of variance 1 at t = 100 (value
    20). With the field drifting at 0.05 unit^2/s the old mean's variance is 1/4 + 0.05 x 100 = 5.25, the new one's
    1: weights 1/5.25 and 1, mean (10/5.25 + 20) / (1/5.25 + 1) = 18.4. By variance alone the old one wins (10)."""
    g = _grid()
    lat, lon = _at(g, 1.0, 1.0)
    old, new = sb.MapAccumulator.like(g), sb.MapAccumulator.like(g)
    old.add(np.repeat(lat, 4), np.repeat(lon, 4), [10.0] * 4, weights=[1.0] * 4, t=0.0)
    new.add(lat, lon, [20.0], weights=[1.0], t=100.0)
    maps = [old.result(), new.result()]
    cur = sb.amalgamate(maps, by="current", change_rate=0.05)
    expect = (10 / 5.25 + 20.0) / (1 / 5.25 + 1.0)
    assert cur.mean.values[1, 1] == pytest.approx(expect)
    assert cur.variance_of_mean()[1, 1] == pytest.approx(1.0 / (1 / 5.25 + 1.0))
    assert sb.amalgamate(maps, by="variance").mean.values[1, 1] == pytest.approx(10.0)
    assert sb.amalgamate(maps, by="current", change_rate=0.0).mean.values[1, 1] == pytest.approx(12.0)
    with pytest.raises(InputError, match="change_rate"):
        sb.amalgamate(maps, by="current")


def test_online_builder_takes_readings_only_where_the_position_is_trusted():
    g = _grid()
    b = sb.OnlineMapBuilder(g, reading_sigma=2.0, gradient_rms=10.0, trust_sigma_m=0.5)
    lat, lon = _at(g, 3.0, 3.0)
    assert b.current_map() is None
    assert b.offer(lat, lon, [7.0], np.eye(2) * 1.0, 1.0) == 0  # 1 m: not trusted
    assert b.offer(lat, lon, [7.0], np.eye(2) * 0.09, 2.0) == 1  # 0.3 m
    m = b.current_map()
    assert m.values[3, 3] == pytest.approx(7.0) and np.isnan(m.values[0, 0])
    # its error layer: 1 / sqrt(W), W = 1 / (2^2 + 10^2 0.3^2) = 1 / 13
    assert m.error_sigma_at(lat, lon)[0] == pytest.approx(np.sqrt(13.0))
    assert b.offered == 2 and b.taken == 1


@pytest.mark.slow
def test_second_lap_navigates_on_the_map_the_first_lap_built():
    import selfbuild_study as S

    fm = S.field()
    r = S.one_run(fm, 0, S.gradient_rms(fm))
    assert r["self_built_lap2_rms_m"] < 0.5 * r["no_map_lap2_rms_m"]
    assert r["true_map_lap2_rms_m"] < r["self_built_lap2_rms_m"]
