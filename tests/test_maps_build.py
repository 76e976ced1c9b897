"""Survey gridding: synthetic line surveys over an analytic field, and Osborne tie-line cross-validation."""

from __future__ import annotations

import numpy as np
import pytest

from magnav_ins.core.errors import InputError
from magnav_ins.core.frames import ned_to_geodetic
from magnav_ins.core.types import FieldKind
from magnav_ins.maps.build import cross_lines, crossover_differences, grid_survey, line_directions, tie_line_misfit
from magnav_ins.maps.io import Survey, read_survey

ORIGIN = (-21.9 * np.pi / 180, 140.65 * np.pi / 180, 400.0)
OSBORNE_TIES = [5816, 5817, 5818, 5819, *range(10149, 10167)]


def field(n, e):
    return 100 * np.sin(2 * np.pi * n / 1500) * np.cos(2 * np.pi * e / 2000) + 80 * np.exp(
        -((n - 300) ** 2 + (e + 200) ** 2) / 400**2
    )


def synthetic_survey(line_spacing=100.0, step=10.0, ties=(-1000.0, 1000.0)):
    n, e, line = [], [], []
    for k, nl in enumerate(np.arange(-2000.0, 2000.0 + 1, line_spacing)):
        ee = np.arange(-2500.0, 2500.0 + 1, step)
        n.append(np.full_like(ee, nl) + 3.0 * np.sin(ee / 700))  # lines wander a little, as flown ones do
        e.append(ee)
        line.append(np.full(ee.size, 100 + k))
    for k, el in enumerate(ties):
        nn = np.arange(-2000.0, 2000.0 + 1, step)
        n.append(nn)
        e.append(np.full_like(nn, el))
        line.append(np.full(nn.size, 901 + k))
    n, e, line = np.concatenate(n), np.concatenate(e), np.concatenate(line)
    lat, lon, h = ned_to_geodetic(np.stack([n, e, np.zeros_like(n)], -1), *ORIGIN)
    return Survey(lat, lon, h, field(n, e), FieldKind.TOTAL_FIELD_ANOMALY_NT, line, "synthetic"), n, e


def test_tie_lines_found_by_direction():
    s, _, _ = synthetic_survey()
    assert cross_lines(s) == [901, 902]
    az = {d.line: np.rad2deg(d.azimuth) for d in line_directions(s)}
    assert abs(az[100] - 90.0) < 1.0 and min(az[901], 180 - az[901]) < 1e-6


def test_bidirectional_grid_recovers_the_field_and_beats_triangulation(rng):
    s, n, e = synthetic_survey()
    m = grid_survey(s, 25.0, exclude_lines=[901, 902])
    assert m.metadata["gridder"] == "bidirectional" and m.metadata["excluded_lines"] == [901, 902]
    # the held-out tie lines, whose truth is known
    tie = np.isin(s.line, [901, 902])
    err_bi = m.value(s.lat[tie], s.lon[tie]) - s.value[tie]
    lin = grid_survey(s, 25.0, exclude_lines=[901, 902], method="linear")
    err_lin = lin.value(s.lat[tie], s.lon[tie]) - s.value[tie]
    rms_bi, rms_lin = np.sqrt(np.nanmean(err_bi**2)), np.sqrt(np.nanmean(err_lin**2))
    assert np.mean(np.isfinite(err_bi)) > 0.97
    assert rms_bi < 0.3, rms_bi  # nT, on a field of +-180 nT (measured 0.15 nT)
    assert rms_bi < 0.1 * rms_lin  # linear triangulation across 100 m lines: ~8 nT
    # draped altitude comes from the readings' heights
    assert np.nanmax(np.abs(m.altitude_m - 400.0)) < 2.0


def test_scattered_gridders_and_gaps():
    s, n, e = synthetic_survey(line_spacing=200.0, ties=())
    s = Survey(s.lat, s.lon, s.h, s.value, s.kind, None, "no lines")
    m = grid_survey(s, 50.0, method="cubic")
    assert m.metadata["gridder"] == "cubic"
    # a node far from every reading is NaN (the max_gap guard): 200 m line spacing, gap 150 m
    assert np.isnan(m.values).any() and np.isfinite(m.values).mean() > 0.9


def test_bad_requests():
    s, _, _ = synthetic_survey()
    with pytest.raises(InputError, match=r"\[7\] are not line ids"):
        grid_survey(s, 25.0, exclude_lines=[7])
    with pytest.raises(InputError, match="positive"):
        grid_survey(s, -1.0)
    with pytest.raises(InputError, match="method"):
        grid_survey(s, 25.0, method="kriging")


@pytest.mark.shared_data
def test_osborne_tie_line_cross_validation(shared_data):
    """Grid the east-west flight lines only; predict the 22 north-south tie lines' real readings."""
    s = read_survey(shared_data / "fatiando" / "osborne-magnetic.csv.xz", geoid_undulation_m=0.0)
    ties = cross_lines(s)
    assert ties == OSBORNE_TIES
    m = grid_survey(s, 50.0, exclude_lines=ties)
    r = tie_line_misfit(m, s, ties)
    n = sum(v["n"] for v in r.values())
    rms = np.sqrt(sum(v["rms"] ** 2 * v["n"] for v in r.values()) / n)
    assert rms < 38.0  # linear triangulation of the same lines gives 39 nT
    # the common offset of the misfit is the levelling difference seen directly at crossovers (independent of gridding)
    mean = sum(v["mean"] * v["n"] for v in r.values()) / n
    xo = crossover_differences(s, ties)
    assert xo.size > 1000 and abs(mean - xo.mean()) < 3.0
    assert np.sqrt(rms**2 - mean**2) < 30.0  # scatter about the offset
    assert n > 0.99 * np.isin(s.line, ties).sum()
