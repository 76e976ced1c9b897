"""Surveys as users download them: column mapping, line selection by type, orthometric heights through the shipped
geoid, in the readers, the ``map grid`` command and scenarios; and the real Rio and Osborne CSVs (``shared_data``)."""

from __future__ import annotations

import lzma

import numpy as np
import pandas as pd
import pytest

from magnav_ins import cli
from magnav_ins.core.errors import ConfigError, InputError
from magnav_ins.core.frames import meters_to_latlon
from magnav_ins.maps.error_layer import ERROR_INFLATION
from magnav_ins.maps.geoid import geoid_undulation
from magnav_ins.maps.io import load_map, parse_column_mapping, read_map, read_survey, select_lines
from magnav_ins.studies import model as Mdl
from magnav_ins.studies.scenario import scenario_from_dict

DEG = np.pi / 180.0
ORIGIN = (-22.25 * DEG, -42.3 * DEG)
TIE_OFFSET_NT = 100.0
RIO_COLUMNS = {"height_ellipsoidal_m": "height_ell_m", "line": "line_number"}


def _field(n, e):
    """Bilinear in north/east (m): every gridder here reproduces it exactly between lines."""
    return 50.0 + 0.02 * n - 0.03 * e + 1e-6 * n * e


def _rio_like(tmp_path, name="rio-like.csv.xz"):
    """A survey in the Rio file's layout: N-S flight lines 'LINE' 250 m apart, E-W tie lines 'TIE' whose readings
    carry a +100 nT levelling offset, columns longitude, latitude, total_field_anomaly_nt, height_ell_m, line_type,
    line_number."""
    rows = []
    along = np.arange(0.0, 3000.0 + 1e-9, 50.0)
    for k, e in enumerate(np.arange(0.0, 3000.0 + 1e-9, 250.0)):
        rows.append(("LINE", 1000 + k, along, np.full_like(along, e), 0.0))
    for k, n in enumerate((500.0, 1500.0, 2500.0)):
        rows.append(("TIE", 9000 + k, np.full_like(along, n), along, TIE_OFFSET_NT))
    recs = []
    for typ, lid, n, e, off in rows:
        dlat, dlon = meters_to_latlon(n, e, ORIGIN[0], 200.0)
        for i in range(len(n)):
            recs.append(
                {
                    "longitude": (ORIGIN[1] + dlon[i]) / DEG,
                    "latitude": (ORIGIN[0] + dlat[i]) / DEG,
                    "total_field_anomaly_nt": _field(n[i], e[i]) + off,
                    "height_ell_m": 200.0 + 0.001 * n[i],
                    "line_type": typ,
                    "line_number": lid,
                }
            )
    p = tmp_path / name
    pd.DataFrame(recs).to_csv(p, index=False, float_format="%.10f", compression="xz")
    return p


# ------------------------------------------------------------------------------------------------ geoid
def test_shipped_geoid_has_the_published_global_extremes():
    """EIGEN-6C4's (and EGM2008's) geoid low of about -106 m south of Sri Lanka and high of about +86 m over New
    Guinea (e.g. Pavlis et al. 2012, Fig. 14), and the wrap at 180 deg of longitude is continuous."""
    la, lo = np.meshgrid(np.linspace(-90, 90, 1081) * DEG, np.arange(2160) / 6.0 * DEG - np.pi, indexing="ij")
    n = geoid_undulation(la, lo)
    i, j = np.unravel_index(np.argmin(n), n.shape)
    assert -108.0 < n[i, j] < -104.0 and abs(la[i, j] / DEG - 4.7) < 2.0 and abs(lo[i, j] / DEG - 78.8) < 2.0
    i, j = np.unravel_index(np.argmax(n), n.shape)
    assert 84.0 < n[i, j] < 88.0 and abs(la[i, j] / DEG + 4.3) < 2.0 and abs(lo[i, j] / DEG - 138.7) < 2.0
    lat = np.linspace(-60, 60, 7) * DEG
    east, west = geoid_undulation(lat, np.full(7, 179.999 * DEG)), geoid_undulation(lat, np.full(7, -179.999 * DEG))
    np.testing.assert_allclose(east, west, atol=0.05)


@pytest.mark.shared_data
def test_shipped_geoid_matches_the_source_grid(shared_data):
    import xarray as xr

    g = xr.load_dataset(shared_data / "fatiando" / "earth-geoid-10arcmin.nc").geoid
    rng = np.random.default_rng(3)
    la, lo = rng.uniform(-90, 90, 200), rng.uniform(-180, 180, 200)
    ref = g.interp(latitude=xr.DataArray(la, dims="p"), longitude=xr.DataArray(lo, dims="p")).values
    np.testing.assert_allclose(geoid_undulation(la * DEG, lo * DEG), ref, atol=1e-6)


def test_orthometric_heights_use_the_shipped_geoid_by_default_and_say_so(tmp_path, caplog):
    text = "flight_line,latitude,longitude,height_orthometric_m,total_field_anomaly_nt\n"
    text += "1,-21.90,140.60,400,10\n1,-21.90,140.61,400,12\n2,-21.91,140.60,401,14\n"
    p = tmp_path / "o.csv.xz"
    p.write_bytes(lzma.compress(text.encode()))
    with caplog.at_level("INFO", logger="magnav_ins.maps"):
        s = read_survey(p)
    n = geoid_undulation(s.lat, s.lon)
    np.testing.assert_allclose(s.h, np.array([400.0, 400.0, 401.0]) + n)
    assert 40.0 < n.min() and n.max() < 43.0  # Osborne's undulation (the builtin map's N = 40.7 .. 42.1 m)
    assert "EIGEN-6C4" in s.heights and "EIGEN-6C4" in caplog.text and "--geoid-m" in caplog.text
    np.testing.assert_allclose(read_survey(p, geoid_undulation_m=-3.0).h, [397.0, 397.0, 398.0])


# ------------------------------------------------------------------------------------------------ columns, lines
def test_column_mapping_reads_a_file_with_other_names(tmp_path):
    p = _rio_like(tmp_path)
    with pytest.raises(InputError, match="no height column"):
        read_survey(p)
    s = read_survey(p, columns=RIO_COLUMNS)
    assert s.line_types() == ["LINE", "TIE"] and s.ids_of_type("TIE") == [9000, 9001, 9002]
    np.testing.assert_allclose(s.h.min(), 200.0, atol=1e-6)
    assert len(s.line_ids()) == 13 + 3
    ties = select_lines(s, line_type="TIE")
    assert set(ties.line.tolist()) == {9000, 9001, 9002} and set(ties.line_type.tolist()) == {"TIE"}
    both = select_lines(s, exclude_line_type="TIE", exclude_lines=[1000])
    assert 1000 not in both.line and set(both.line_type.tolist()) == {"LINE"}


@pytest.mark.parametrize(
    ("columns", "match"),
    [
        ({"height": "height_ell_m"}, "'height' is not one of our survey columns"),
        ({"height_ellipsoidal_m": "h_ell"}, "no column 'h_ell'"),
        ({"height_ellipsoidal_m": "height_ell_m", "line": "height_ell_m"}, "mapped twice"),
    ],
)
def test_bad_column_mapping_names_the_mapping(tmp_path, columns, match):
    with pytest.raises(InputError, match=match):
        read_survey(_rio_like(tmp_path), columns=columns)


def test_bad_line_selection_lists_what_exists(tmp_path):
    s = read_survey(_rio_like(tmp_path), columns=RIO_COLUMNS)
    with pytest.raises(InputError, match=r"no line type \['tie'\].*\['LINE', 'TIE'\]"):
        select_lines(s, line_type="tie")
    with pytest.raises(InputError, match=r"\[5\] are not line ids"):
        select_lines(s, lines=[5])
    with pytest.raises(InputError, match="OUR_NAME=FILE_COLUMN"):
        parse_column_mapping(["height_ellipsoidal_m"])


def test_map_grid_by_line_type_predicts_the_tie_lines(tmp_path, monkeypatch, capsys):
    """Grid only the 'LINE' lines (linear triangulation, which would use any line given to it) and predict the 'TIE'
    lines: the misfit is exactly minus their +100 nT offset, i.e. no tie-line reading entered the map."""
    monkeypatch.setattr(cli, "COMMAND_MODULES", ("maps",))
    p = _rio_like(tmp_path)
    out = tmp_path / "rio.nc"
    argv = ["map", "grid", str(p), "--spacing", "50", "--method", "linear", "--out", str(out)]
    argv += ["--column", "height_ellipsoidal_m=height_ell_m", "--column", "line=line_number"]
    assert cli.main(argv + ["--line-type", "LINE", "--check-lines", "TIE"]) == 0
    text = capsys.readouterr().out
    assert "TIE lines (3) predicted" in text
    chk = read_map(out).metadata["check_lines"]
    assert abs(chk["mean"] + TIE_OFFSET_NT) < 1e-4 and chk["std"] < 1e-4 and chk["n"] > 100
    # the same through load_map (scenarios, map info / sample): the map reproduces the field at the flight lines
    m = load_map(str(p), grid_spacing_m=50.0, columns=RIO_COLUMNS, line_type="LINE", method="linear")
    dlat, dlon = meters_to_latlon(np.array([700.0, 2200.0]), np.array([1100.0, 2900.0]), ORIGIN[0], 200.0)
    np.testing.assert_allclose(
        m.value(ORIGIN[0] + dlat, ORIGIN[1] + dlon),
        _field(np.array([700.0, 2200.0]), np.array([1100.0, 2900.0])),
        atol=1e-3,
    )
    # the tie lines would measure the error between line sets at their crossovers (never gridded), but 3 x 13
    # crossovers are too few for the term (error_layer.MIN_CROSSOVERS): the layer keeps the stated inflation; a tie
    # line in exclude_lines is used for nothing, and the map's values do not change
    assert m.metadata["error_model"]["between_lines"]["lines"] == 0
    assert m.metadata["error_model"]["inflation"] == ERROR_INFLATION
    left = load_map(str(p), grid_spacing_m=50.0, columns=RIO_COLUMNS, line_type="LINE", method="linear",
                    exclude_lines=[9000])  # fmt: skip
    assert left.metadata["excluded_lines"] == [9000]
    np.testing.assert_array_equal(left.values, m.values)
    assert cli.main(argv + ["--line-type", "LINE", "--check-lines", "TIE", "--error-lines", "TIE"]) == 0
    assert "in-sample" in capsys.readouterr().out
    # user mistakes: one line, exit status 2
    assert cli.main(argv + ["--line-type", "LINE", "--error-lines", "LINE"]) == 2
    assert cli.main(argv + ["--line-type", "TIE", "--check-lines", "TIE"]) == 2
    assert cli.main(argv[:-2] + ["--out", str(tmp_path / "x.nc"), "--column", "bogus"]) == 2
    assert "OUR_NAME=FILE_COLUMN" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------ scenarios
def _scenario(survey, **traj):
    return {
        "name": "rio-like",
        "trajectory": {"kind": "survey_line", "survey": str(survey), "speed_mps": 60.0, **traj},
        "imu": {"grade": "navigation", "rate_hz": 5.0},
        "map": {
            "path": str(survey),
            "kind": "total_field_anomaly_nt",
            "grid_spacing_m": 50.0,
            "columns": RIO_COLUMNS,
            "line_type": "LINE",
        },
        "sensor": {"kind": "scalar_magnetometer", "source": "survey", "sigma": 1e-9, "interval_s": 1.0},
    }


def test_scenario_flies_the_lines_of_a_type_through_the_column_mapping(tmp_path):
    p = _rio_like(tmp_path)
    sc = scenario_from_dict(_scenario(p, line_type="TIE", columns=RIO_COLUMNS))
    pts = Mdl.survey_line_points(sc)
    assert list(dict.fromkeys(pts["line"].tolist())) == [9000, 9001, 9002]
    np.testing.assert_allclose(pts["value"], _field(*_ne(pts)) + TIE_OFFSET_NT, atol=0.01)
    fmap = Mdl.build_map(sc)
    assert fmap.metadata["line_type"] == "LINE" and "ellipsoidal" in fmap.metadata["heights"]
    # one listed line of the type; a listed line of another type is refused naming the key
    one = Mdl.survey_line_points(scenario_from_dict(_scenario(p, line_type="TIE", line=9001, columns=RIO_COLUMNS)))
    assert set(one["line"].tolist()) == {9001}
    with pytest.raises(ConfigError, match="trajectory.line.*not of line_type 'TIE'"):
        Mdl.survey_line_points(scenario_from_dict(_scenario(p, line_type="TIE", line=1000, columns=RIO_COLUMNS)))
    with pytest.raises(ConfigError, match="trajectory.survey.*no height column"):
        Mdl.survey_line_points(scenario_from_dict(_scenario(p, line_type="TIE")))


def _ne(pts):
    from magnav_ins.core.frames import latlon_to_meters

    n, e = latlon_to_meters(pts["lat"] - ORIGIN[0], pts["lon"] - ORIGIN[1], ORIGIN[0])
    return np.asarray(n), np.asarray(e)


@pytest.mark.parametrize(
    ("patch", "match"),
    [
        ({"trajectory": {"line": None}}, "needs 'line'.*or 'line_type'"),
        ({"trajectory": {"columns": {"height": "x"}}}, "trajectory.columns.height.*not a survey column"),
        ({"trajectory": {"geoid_m": "40"}}, "trajectory.geoid_m.*expected a number"),
        ({"map": {"path": "builtin:osborne-magnetic"}}, "map.columns.*survey CSV"),
    ],
)
def test_scenario_survey_key_errors(tmp_path, patch, match):
    d = _scenario(_rio_like(tmp_path), line=1000)
    for table, kv in patch.items():
        for k, v in kv.items():
            if v is None:
                d[table].pop(k)
            else:
                d[table][k] = v
    with pytest.raises(ConfigError, match=match):
        scenario_from_dict(d)


# ------------------------------------------------------------------------------------------------ real files
@pytest.mark.shared_data
def test_rio_survey_runs_in_a_scenario_as_downloaded(shared_data):
    """The Rio CSV as downloaded: the map gridded from the flight lines (LINE), a tie line (TIE) flown with its own
    readings; the map predicts those readings."""
    rio = shared_data / "rio_magnetic" / "rio-magnetic.csv.xz"
    d = _scenario(rio, line_type="TIE", line=9141, columns=RIO_COLUMNS)
    d["map"]["grid_spacing_m"] = 250.0
    d["trajectory"]["duration_s"] = 300.0
    d["estimator"] = [{"name": "ml+ukf", "matcher": {"kind": "ml"}, "window": 10, "fusion": {"kind": "ukf"}}]
    sc = scenario_from_dict(d)
    truth = Mdl.build_truth(sc)
    fmap = Mdl.build_map(sc)
    r = Mdl.simulate_readings(sc, truth, fmap, np.random.default_rng(0))
    pred = fmap.value(np.interp(r.t, truth.t, truth.lat), np.interp(r.t, truth.t, truth.lon))
    ok = np.isfinite(pred)
    assert ok.mean() > 0.9 and len(r.t) > 200
    misfit = pred[ok] - r.value[ok]
    # the map predicts the tie line's readings (measured: 6.7 nT RMS on a 18.5 nT signal over these 300 s)
    assert np.sqrt(np.mean(misfit**2)) < 0.5 * np.std(r.value)
    out = Mdl.PipelineModel(sc).run(np.random.SeedSequence(1))
    assert {e.name for e in out.estimators} >= {"ml+ukf"}


@pytest.mark.shared_data
def test_osborne_survey_with_orthometric_heights_runs_as_downloaded(shared_data):
    """Osborne's CSV (orthometric heights) flown as downloaded: the shipped geoid makes its heights ellipsoidal,
    matching the shipped tie-line file (made with the same geoid) to its 0.1 m rounding."""
    osb = shared_data / "fatiando" / "osborne-magnetic.csv.xz"
    d = {
        "name": "osborne",
        "trajectory": {"kind": "survey_line", "survey": str(osb), "line": 10152, "speed_mps": 60.0},
        "imu": {"grade": "navigation", "rate_hz": 5.0},
    }
    pts = Mdl.survey_line_points(scenario_from_dict(d))
    ref = Mdl.survey_line_points(
        scenario_from_dict({**d, "trajectory": {**d["trajectory"], "survey": "builtin:osborne-tie-lines"}})
    )
    np.testing.assert_allclose(pts["h"], ref["h"], atol=0.051)
    np.testing.assert_allclose(pts["value"], ref["value"])
    d["trajectory"]["geoid_m"] = 0.0
    np.testing.assert_allclose(Mdl.survey_line_points(scenario_from_dict(d))["h"] + 40.7, ref["h"], atol=1.5)
