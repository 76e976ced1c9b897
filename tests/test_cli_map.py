"""``magnav-ins map info|grid|sample`` end to end through the dispatcher, against analytic truth, and the user
mistakes that must end in a one-line message and exit status 2."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from magnav_ins import cli
from magnav_ins.core.types import FieldKind
from magnav_ins.maps.grid import GridMap
from magnav_ins.maps.io import read_map, write_map

DEG = np.pi / 180.0


@pytest.fixture
def main(monkeypatch):
    monkeypatch.setattr(cli, "COMMAND_MODULES", ("maps",))
    return cli.main


def _f(lat_deg, lon_deg):
    return 12.0 + 30.0 * (lat_deg + 35.0) - 7.0 * (lon_deg - 150.0) + 5.0 * (lat_deg + 35.0) * (lon_deg - 150.0)


@pytest.fixture
def bilinear_map(tmp_path):
    lat = np.linspace(-36.0, -34.0, 9)
    lon = np.linspace(149.0, 151.0, 11)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    m = GridMap(
        lat * DEG,
        lon * DEG,
        _f(la, lo),
        kind=FieldKind.GRAVITY_DISTURBANCE_MGAL,
        frame="geodetic",
        altitude_m=500.0,
        name="analytic",
    )
    write_map(m, tmp_path / "a.nc")
    return tmp_path / "a.nc"


def test_sample_matches_the_analytic_field(main, bilinear_map, tmp_path):
    pts = pd.DataFrame(
        {
            "lat_deg": [-35.3, -34.1, -35.999, -20.0],
            "lon_deg": [149.5, 150.9, 149.01, 150.0],
            "h_m": [500, 510, 490, 500],
            "id": ["a", "b", "c", "off"],
        }
    )
    pts.to_csv(tmp_path / "p.csv", index=False)
    assert (
        main(
            ["map", "sample", str(bilinear_map), "--points", str(tmp_path / "p.csv"), "--out", str(tmp_path / "o.csv")]
        )
        == 0
    )
    out = pd.read_csv(tmp_path / "o.csv")
    assert list(out.columns) == ["lat_deg", "lon_deg", "h_m", "id", "value"]
    np.testing.assert_allclose(out.value[:3], _f(pts.lat_deg[:3], pts.lon_deg[:3]), atol=1e-7)
    assert np.isnan(out.value[3])


def test_info_table_and_json(main, bilinear_map, capsys):
    assert main(["map", "info", str(bilinear_map), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["kind"] == "gravity_disturbance_mgal" and s["shape"] == [9, 11] and s["altitude_m"] == 500.0
    np.testing.assert_allclose(s["lat_deg"], [-36.0, -34.0])
    np.testing.assert_allclose(s["spacing_m"][0], 0.25 * DEG * 6_356_000, rtol=3e-3)
    vals = np.asarray(s["value_range"])
    assert s["level_sigma"]["source"] == "default" and 0.0 < s["level_sigma"]["sigma"] < 0.5 * np.ptp(vals)
    assert main(["map", "info", "builtin:osborne-magnetic"]) == 0
    out = capsys.readouterr().out
    assert "total_field_anomaly_nt [nT]" in out
    assert "level offset    1-sigma 30.2 nT (the matchers' stated default" in out


def test_grid_a_survey_then_use_it(main, tmp_path, capsys):
    e = np.arange(-1000.0, 1001.0, 10.0)
    rows = []
    for k, n in enumerate(np.arange(-1000.0, 1001.0, 100.0)):
        lat = -21.9 + n / 111_000.0
        lon = 140.6 + e / (111_000.0 * np.cos(np.deg2rad(21.9)))
        rows.append(
            pd.DataFrame(
                {
                    "flight_line": 10 + k,
                    "latitude": lat,
                    "longitude": lon,
                    "height_orthometric_m": 400.0,
                    "total_field_anomaly_nt": 3.0 * n / 100 + e / 50,
                }
            )
        )
    tie = pd.DataFrame(
        {
            "flight_line": 99,
            "latitude": -21.9 + np.arange(-1000, 1001, 10) / 111_000.0,
            "longitude": 140.6,
            "height_orthometric_m": 400.0,
            "total_field_anomaly_nt": 0.0,
        }
    )
    pd.concat(rows + [tie]).to_csv(tmp_path / "s.csv", index=False)
    out = tmp_path / "g.nc"
    args = ["map", "grid", str(tmp_path / "s.csv"), "--spacing", "50", "--geoid-m", "50", "--out", str(out)]
    assert main(args + ["--exclude-lines", "99"]) == 0
    m = read_map(out)
    assert m.metadata["excluded_lines"] == [99] and m.frame == "local"
    np.testing.assert_allclose(np.nanmean(m.altitude_m), 450.0, atol=0.01)  # H + N
    # the planar field is reproduced where the grid has data
    lat, lon = -21.9 + 420.0 / 111_000.0, 140.6 + 130.0 / (111_000.0 * np.cos(np.deg2rad(21.9)))
    np.testing.assert_allclose(m.value(lat * DEG, lon * DEG), 3.0 * 4.2 + 130 / 50, atol=0.2)
    assert main(args + ["--exclude-tie-lines"]) == 0
    assert "tie lines excluded: 99" in capsys.readouterr().out


def test_user_mistakes_exit_2_with_one_line(main, tmp_path, bilinear_map, capsys):
    ds = xr.load_dataset(bilinear_map)
    del ds.attrs["altitude_m"]
    ds.to_netcdf(tmp_path / "noalt.nc")
    (tmp_path / "bad.csv").write_text("lat_deg,lon_deg\n-35,150\n-35,xx\n")
    (tmp_path / "swap.csv").write_text("lat_deg,lon_deg\n150,-35\n")
    cases = [
        (["map", "info", str(tmp_path / "noalt.nc")], "'altitude_m'"),
        (["map", "info", str(tmp_path / "missing.nc")], "no such map file"),
        (["map", "info", "builtin:nope"], "no such shipped map"),
        (
            [
                "map",
                "sample",
                str(bilinear_map),
                "--points",
                str(tmp_path / "bad.csv"),
                "--out",
                str(tmp_path / "o.csv"),
            ],
            "row 2 column 'lon_deg'",
        ),
        (
            [
                "map",
                "sample",
                str(bilinear_map),
                "--points",
                str(tmp_path / "swap.csv"),
                "--out",
                str(tmp_path / "o.csv"),
            ],
            "swapped",
        ),
        (["map", "grid", str(tmp_path / "bad.csv"), "--spacing", "10", "--exclude-lines", "1,x"], "not an integer"),
    ]
    for argv, msg in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and msg in err, err
    assert not (tmp_path / "o.csv").exists()
    # supplied explicitly, the same file is accepted
    assert main(["map", "info", str(tmp_path / "noalt.nc"), "--altitude-m", "500"]) == 0
