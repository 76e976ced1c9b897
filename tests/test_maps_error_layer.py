"""The map knows its own error (issue 13 item 1): the block k-fold cross-validated error layer of a gridded survey,
checked against a known truth (a synthetic field whose value is known everywhere) and on real tie lines
(``shared_data``); a layer the user gives; what ``map info`` says."""

from __future__ import annotations

import json

import numpy as np
import pytest

from magnav_ins import cli
from magnav_ins.core.errors import ConfigError, InputError, MapError
from magnav_ins.core.frames import ned_to_geodetic
from magnav_ins.core.types import FieldKind
from magnav_ins.maps.build import gradient_magnitude, grid_survey
from magnav_ins.maps.error_layer import ERROR_INFLATION, ErrorModel, _isotonic, fit_distance_model
from magnav_ins.maps.io import Survey, load_map, read_map, write_map
from magnav_ins.maps.synthetic import gaussian_random_field

ORIGIN = (-21.9 * np.pi / 180, 140.65 * np.pi / 180, 400.0)
TRUTH_STEP_M = 10.0
HALF_M = 3000.0


@pytest.fixture(scope="module")
def truth():
    """A Gaussian random field (50 nT, 250 m correlation) on a 10 m grid over 6 x 6 km: the truth everywhere."""
    n = int(2 * HALF_M / TRUTH_STEP_M) + 1
    return gaussian_random_field((n, n), TRUTH_STEP_M, 250.0, 50.0, np.random.default_rng(7))


def _sample(truth, n, e):
    i = np.clip(np.round((n + HALF_M) / TRUTH_STEP_M).astype(int), 0, truth.shape[0] - 1)
    j = np.clip(np.round((e + HALF_M) / TRUTH_STEP_M).astype(int), 0, truth.shape[1] - 1)
    return truth[i, j]


def _lines(truth, spacing, step=20.0, north_south=False, first_id=1):
    n, e, line = [], [], []
    offs = np.arange(-HALF_M + 200.0, HALF_M - 200.0 + 1, spacing)
    along = np.arange(-HALF_M + 100.0, HALF_M - 100.0 + 1, step)
    for k, o in enumerate(offs):
        nn, ee = (along, np.full_like(along, o)) if north_south else (np.full_like(along, o), along)
        n.append(nn)
        e.append(ee)
        line.append(np.full(along.size, first_id + k))
    n, e, line = np.concatenate(n), np.concatenate(e), np.concatenate(line)
    n_q, e_q = np.round(n / TRUTH_STEP_M) * TRUTH_STEP_M, np.round(e / TRUTH_STEP_M) * TRUTH_STEP_M  # on truth nodes
    lat, lon, h = ned_to_geodetic(np.stack([n_q, e_q, np.zeros_like(n_q)], -1), *ORIGIN)
    return Survey(lat, lon, h, _sample(truth, n_q, e_q), FieldKind.TOTAL_FIELD_ANOMALY_NT, line, "synthetic")


def test_error_layer_is_honest_against_a_known_truth(truth):
    """E-W lines 200 m apart over a known smooth field, gridded with the cross-validated layer (no inflation: the
    synthetic survey has no levelling difference between line sets). At independent N-S check lines the layer is
    conservative - the cross-validation fills its held-out blocks along the lines (linear), which is worse than the
    map's cubic spline across them on so smooth a field: RMS of (map - truth) / sigma 0.18, i.e. sigma about 5x
    the error - but it tells good from bad places: larger where the map is worse (between lines, steep field)."""
    s = _lines(truth, 200.0)
    m = grid_survey(s, 25.0, error_inflation=1.0)
    assert m.has_error_layer and "cross-validation" in m.error_source
    check = _lines(truth, 450.0, north_south=True, first_id=900)
    r = m.value(check.lat, check.lon) - check.value
    sig = m.error_sigma_at(check.lat, check.lon)
    ok = np.isfinite(r)
    z = r[ok] / sig[ok]
    z_rms = float(np.sqrt(np.mean(z**2)))
    assert 0.1 < z_rms < 1.0, z_rms  # never over-confident here (measured 0.18)
    assert np.mean(np.abs(z) > 3.0) < 0.003
    # the layer tells good from bad places: the check points it gives the largest third of sigmas have a larger
    # error than the smallest third
    q1, q2 = np.quantile(sig[ok], [1 / 3, 2 / 3])
    lo, hi = np.abs(r[ok][sig[ok] <= q1]), np.abs(r[ok][sig[ok] >= q2])
    assert np.sqrt(np.mean(hi**2)) > 2.0 * np.sqrt(np.mean(lo**2))
    # between lines (100 m from both) larger than on a line
    e_q = np.linspace(-2000, 2000, 50)
    on = m.error_sigma_ne(np.full(50, -HALF_M + 200.0 + 10 * 200.0), e_q)
    mid = m.error_sigma_ne(np.full(50, -HALF_M + 300.0 + 10 * 200.0), e_q)
    assert np.median(mid) > 1.5 * np.median(on)
    assert 50.0 < m.error_correlation_m < 2000.0
    # the default inflation scales the layer and nothing else
    m2 = grid_survey(s, 25.0)
    np.testing.assert_allclose(m2.error_sigma, np.minimum(m.error_sigma * ERROR_INFLATION, 3 * 50.0), rtol=0.2)
    np.testing.assert_array_equal(m2.values, m.values)


def test_layer_round_trips_and_is_optional(tmp_path, truth):
    s = _lines(truth, 300.0, step=30.0)
    m = grid_survey(s, 50.0)
    write_map(m, tmp_path / "m.nc")
    back = read_map(tmp_path / "m.nc")
    np.testing.assert_allclose(back.error_sigma, m.error_sigma)
    assert back.error_correlation_m == m.error_correlation_m
    assert back.metadata["error_model"]["folds"] == 5
    assert not grid_survey(s, 50.0, error_folds=0).has_error_layer


def test_isotonic_fit_and_distance_model():
    # pool-adjacent-violators against a brute-force check: the fit is non-decreasing and keeps the weighted mean
    y = np.array([1.0, 3.0, 2.0, 2.0, 5.0, 4.0])
    w = np.array([1.0, 1.0, 2.0, 1.0, 1.0, 3.0])
    f = _isotonic(y, w)
    assert np.all(np.diff(f) >= 0) and abs(np.sum(f * w) - np.sum(y * w)) < 1e-12
    np.testing.assert_allclose(f, [1.0, 2.25, 2.25, 2.25, 4.25, 4.25])
    # residuals with sigma^2 = 4 + (30 m * g)^2 growing with distance: the fit recovers a and b
    rng = np.random.default_rng(1)
    d = rng.uniform(0, 200, 40_000)
    g = rng.uniform(0, 0.5, d.size)
    true_a, true_b = 4.0 * (1 + d / 100), (30.0 * (1 + d / 200)) ** 2
    r = rng.normal(0, np.sqrt(true_a + true_b * g**2))
    centre, a, b = fit_distance_model(d, g, r)
    ta = np.interp(centre, d[np.argsort(d)], true_a[np.argsort(d)])
    tb = (30.0 * (1 + centre / 200)) ** 2
    np.testing.assert_allclose(np.sqrt(b), np.sqrt(tb), rtol=0.15)
    np.testing.assert_allclose(np.sqrt(a), np.sqrt(ta), rtol=0.5, atol=0.6)
    em = ErrorModel(centre, a, b, 100.0, 300.0, 5, 200.0, d.size, 1.0, 0.0)
    assert np.isnan(em.sigma_at(np.nan, 0.1)) and em.sigma_at(1e6, 10.0) == 100.0  # the cap


def test_gradient_magnitude_of_a_plane_and_at_nan_edges():
    nn, ee = np.meshgrid(np.arange(6) * 10.0, np.arange(7) * 10.0, indexing="ij")
    v = 3.0 * nn - 4.0 * ee
    v[2, 3] = np.nan
    g = gradient_magnitude(v, 10.0)
    np.testing.assert_allclose(g[np.isfinite(v)], 5.0)


def test_user_given_layer_cli_and_scenario(tmp_path, monkeypatch, capsys):
    from magnav_ins.studies import model as Mdl
    from magnav_ins.studies.scenario import scenario_from_dict

    lat = np.linspace(-30, -29, 11) * np.pi / 180
    lon = np.linspace(140, 141, 12) * np.pi / 180
    g = np.random.default_rng(0).normal(0, 10, (11, 12))
    from magnav_ins.maps.grid import GridMap

    bare = GridMap(lat, lon, g, kind=FieldKind.GRAVITY_DISTURBANCE_MGAL, frame="geodetic", altitude_m=0.0, name="b")
    write_map(bare, tmp_path / "b.nc")
    monkeypatch.setattr(cli, "COMMAND_MODULES", ("maps",))
    assert cli.main(["map", "info", str(tmp_path / "b.nc")]) == 0
    assert "no error layer (matchers use their stated default)" in capsys.readouterr().out
    assert cli.main(["map", "info", str(tmp_path / "b.nc"), "--json", "--map-error-sigma", "2.5",
                     "--map-error-correlation-m", "8000"]) == 0  # fmt: skip
    e = json.loads(capsys.readouterr().out)["error_layer"]
    assert e["sigma_median"] == 2.5 and e["correlation_m"] == 8000.0 and "given by the user" in e["source"]
    assert cli.main(["map", "info", str(tmp_path / "b.nc"), "--map-error-sigma", "2.5"]) == 2
    assert "--map-error-correlation-m" in capsys.readouterr().err
    with pytest.raises(MapError, match="positive"):
        load_map(str(tmp_path / "b.nc"), error_sigma=-1.0, error_correlation_m=10.0)
    doc = {
        "name": "e",
        "trajectory": {
            "kind": "great_circle",
            "start": [-29.8, 140.2],
            "end": [-29.2, 140.8],
            "altitude_m": 0.0,
            "speed_mps": 100.0,
        },  # fmt: skip
        "imu": {"grade": "navigation"},
        "map": {
            "path": str(tmp_path / "b.nc"),
            "kind": "gravity_disturbance_mgal",
            "error_sigma": 1.5,
            "error_correlation_m": 20000.0,
        },  # fmt: skip
    }
    fm = Mdl.build_map(scenario_from_dict(doc))
    assert fm.has_error_layer and float(np.median(fm.error_sigma)) == 1.5 and fm.error_correlation_m == 20000.0
    doc["map"].pop("error_correlation_m")
    with pytest.raises(ConfigError, match="map.error_sigma.*error_correlation_m"):
        scenario_from_dict(doc)


def test_shipped_maps_carry_their_error_layer():
    for name in ("osborne-magnetic", "eigen6c4-australia-se"):
        m = load_map(f"builtin:{name}")
        assert m.has_error_layer and m.error_correlation_m > 0 and m.error_source
    g = load_map("builtin:eigen6c4-australia-se")
    assert 1.0 < float(np.median(g.error_sigma)) < 6.0 and "Sandwell" in g.error_source
    o = load_map("builtin:osborne-magnetic")
    assert 5.0 < float(np.median(o.error_sigma)) < 80.0


def test_shipped_osborne_layer_is_honest_on_the_independent_tie_lines():
    """The shipped map's layer against the tie lines (not used for the map; shipped as builtin:osborne-tie-lines),
    split into level and local part (ERROR_INFLATION's docstring): on the 11 even-indexed lines, which the inflation
    was not calibrated on, the RMS of the per-line demeaned (map - reading) / sigma is about 1, and each line's
    level offset lies within 1.5 of the level prior's 1-sigma (the stated default: 10 % of the map's std)."""
    from magnav_ins.aiding.matchers.map_error import resolve_level
    from magnav_ins.maps.builtin import load_survey_lines

    m = load_map("builtin:osborne-magnetic")
    s = load_survey_lines("builtin:osborne-tie-lines")
    level = resolve_level(m)
    assert level.source == "default" and 20.0 < level.sigma < 40.0
    ids = sorted(int(i) for i in np.unique(s.line))
    z2, n = 0.0, 0
    for lid in ids[1::2]:
        k = s.line == lid
        r = m.value(s.lat[k], s.lon[k]) - s.value[k]
        sig = m.error_sigma_at(s.lat[k], s.lon[k])
        ok = np.isfinite(r) & np.isfinite(sig)
        assert ok.mean() > 0.98
        assert abs(r[ok].mean()) < 1.5 * level.sigma
        z2 += float(np.sum(((r[ok] - r[ok].mean()) / sig[ok]) ** 2))
        n += int(ok.sum())
    assert 0.8 < np.sqrt(z2 / n) < 1.1


@pytest.mark.shared_data
def test_rio_layer_on_its_tie_lines_is_too_small_a_known_limit(shared_data):
    """A survey not tuned on: Rio's map from its flight lines (LINE), its tie lines (TIE) as truth. With the
    inflation calibrated on Osborne's local part (1.40) Rio's layer is too small: the RMS of (map - reading) / sigma
    is about 1.4 (measured 1.43), not the 1 of an honest layer. A known limit (README: the inflation is
    survey-specific), pinned from both sides so that a change of it, either way, is seen."""
    from magnav_ins.maps.io import read_survey, select_lines

    s = read_survey(
        shared_data / "rio_magnetic" / "rio-magnetic.csv.xz",
        columns={"height_ellipsoidal_m": "height_ell_m", "line": "line_number"},
    )
    m = grid_survey(select_lines(s, line_type="LINE"), 250.0)
    t = s.of_type("TIE")
    z = (m.value(t.lat, t.lon) - t.value) / m.error_sigma_at(t.lat, t.lon)
    ok = np.isfinite(z)
    assert 1.2 < np.sqrt(np.mean(z[ok] ** 2)) < 1.6


def test_crossover_level_of_tie_lines_offset_from_the_flight_lines(truth):
    """E-W flight lines and N-S tie lines read from one truth, the tie lines +20 nT off (a levelling difference):
    the crossover estimate (median per tie line of tie minus the nearest flight reading) finds the 20 nT, the map
    stores it as metadata["level_crossover"], and the matchers' level prior is the larger of it and 10 % of the
    map's std; a stated level_sigma wins."""
    from dataclasses import replace

    from magnav_ins.aiding.matchers.map_error import resolve_level
    from magnav_ins.maps.build import _local, crossover_level_sigma

    flights = _lines(truth, 400.0, step=20.0)
    ties = _lines(truth, 1000.0, step=20.0, north_south=True, first_id=100)
    ties = replace(ties, value=ties.value + 20.0)
    s = Survey(
        np.r_[flights.lat, ties.lat], np.r_[flights.lon, ties.lon], np.r_[flights.h, ties.h],
        np.r_[flights.value, ties.value], flights.kind, np.r_[flights.line, ties.line], "synthetic",
    )  # fmt: skip
    n, e, _ = _local(s)
    rms, lines, pairs = crossover_level_sigma(s, n, e, 15.0)
    assert lines == ties.line_ids().size and pairs > 10 * lines
    assert rms == pytest.approx(20.0, abs=0.5)
    m = grid_survey(s, 50.0, error_folds=0)
    assert m.metadata["level_crossover"]["rms"] == pytest.approx(rms, abs=1.0)
    lvl = resolve_level(m)
    assert lvl.source == "default" and lvl.sigma == pytest.approx(max(rms, 0.1 * np.nanstd(m.values)))
    assert crossover_level_sigma(flights, *_local(flights)[:2], 15.0) is None  # no cross lines
    stated = grid_survey(s, 50.0, error_folds=0, level_sigma=7.0)
    assert (resolve_level(stated).sigma, resolve_level(stated).source) == (7.0, "map")
    with pytest.raises(InputError, match="level_sigma"):
        grid_survey(s, 50.0, error_folds=0, level_sigma=-1.0)


def test_scenario_states_the_level_prior():
    """[map] options.level_sigma reaches the matchers' level prior; a map stated exact (error_sigma = 0: the readings
    are drawn from it) has no level offset; the shared built-in map is not modified; a bad value is a ConfigError."""
    from magnav_ins.aiding.matchers.map_error import resolve_level
    from magnav_ins.studies import model as Mdl
    from magnav_ins.studies.scenario import scenario_from_dict

    def doc(options: dict) -> dict:
        return {
            "name": "lv",
            "trajectory": {
                "kind": "great_circle",
                "start": [-35.0, 145.0],
                "end": [-34.5, 145.5],
                "altitude_m": 10000.0,
                "speed_mps": 200.0,
            },  # fmt: skip
            "imu": {"grade": "navigation"},
            "map": {"path": "builtin:eigen6c4-australia-se", "kind": "gravity_disturbance_mgal", "options": options},
        }

    default = resolve_level(Mdl.build_map(scenario_from_dict(doc({}))))
    assert default.source == "default" and default.sigma > 0.5  # 10 % of the map's std (tens of mGal)
    stated = resolve_level(Mdl.build_map(scenario_from_dict(doc({"level_sigma": 2.5}))))
    assert (stated.sigma, stated.source) == (2.5, "map")
    exact = resolve_level(Mdl.build_map(scenario_from_dict(doc({"error_sigma": 0.0}))))
    assert exact.sigma == 0.0 and "stated exact" in exact.detail
    assert resolve_level(load_map("builtin:eigen6c4-australia-se")).source == "default"  # the cached map untouched
    with pytest.raises(ConfigError, match="level_sigma must be a number >= 0"):
        Mdl.build_map(scenario_from_dict(doc({"level_sigma": -1.0})))


def test_crossovers_of_lines_not_gridded_measure_the_error_between_line_sets(truth):
    """Tie lines whose recorded positions are 100 m west of where they were read (a registration error between
    line sets, which cross-validation within the flight lines cannot see): given as check_lines (never gridded),
    their crossovers with the flight lines give the layer a between-line-set term (a position error of tens of
    metres times the gradient) and the layer is honest on them (z RMS 0.94 measured; 1.84 without the term).
    Tie lines read where they were recorded give no term (the layer stays the cross-validated one, uninflated)."""
    flights = _lines(truth, 200.0)
    shifted = _lines(np.roll(truth, -10, axis=1), 500.0, north_south=True, first_id=900)  # read 100 m east
    m = grid_survey(flights, 25.0, check_lines=shifted)
    between = m.metadata["error_model"]["between_lines"]
    assert between["lines"] == shifted.line_ids().size and between["points"] > 100
    assert 25.0 < between["position_m"] < 120.0
    assert m.metadata["error_model"]["inflation"] == 1.0 and "crossovers" in m.error_source
    np.testing.assert_array_equal(m.values, grid_survey(flights, 25.0, error_folds=0).values)  # not gridded
    r = m.value(shifted.lat, shifted.lon) - shifted.value
    ok = np.isfinite(r)
    z_with = np.sqrt(np.mean((r[ok] / m.error_sigma_at(shifted.lat, shifted.lon)[ok]) ** 2))
    plain = grid_survey(flights, 25.0, error_inflation=1.0)
    z_without = np.sqrt(np.mean((r[ok] / plain.error_sigma_at(shifted.lat, shifted.lon)[ok]) ** 2))
    assert 0.7 < z_with < 1.3 and z_without > 1.5, (z_with, z_without)
    exact = _lines(truth, 500.0, north_south=True, first_id=900)
    m0 = grid_survey(flights, 25.0, check_lines=exact)
    b0 = m0.metadata["error_model"]["between_lines"]
    assert b0["position_m"] < 5.0 and b0["sigma0"] < 2.0
    np.testing.assert_allclose(m0.error_sigma, plain.error_sigma, rtol=0.05)
    with pytest.raises(InputError, match="check_lines"):
        grid_survey(flights, 25.0, check_lines=exact.select(np.zeros(len(exact), dtype=bool)))
