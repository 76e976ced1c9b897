"""NetCDF round trips, refused metadata-less maps, survey CSV validation, shipped maps."""

from __future__ import annotations

import lzma

import numpy as np
import pytest
import xarray as xr

from magnav_ins.core.errors import InputError, MapError
from magnav_ins.core.types import FieldKind
from magnav_ins.maps.builtin import BUILTIN_MAPS, load_survey_lines
from magnav_ins.maps.grid import GridMap
from magnav_ins.maps.io import load_map, read_map, read_survey, read_survey_line, write_map

DEG = np.pi / 180.0


def _geo(rng, kind=FieldKind.GRAVITY_DISTURBANCE_MGAL):
    lat = np.linspace(-38.0, -35.0, 13) * DEG
    lon = np.linspace(144.5, 150.0, 23) * DEG
    shape = (13, 23) if kind.components == 1 else (13, 23, 3)
    v = rng.normal(0, 30, shape)
    v[3, 4] = np.nan
    return GridMap(
        lat,
        lon,
        v,
        kind=kind,
        frame="geodetic",
        altitude_m=10_000.0,
        name="g",
        metadata={"source": "test", "seed": 12345, "list": [1, 2]},
    )


def _same(a: GridMap, b: GridMap):
    assert (a.kind, a.frame, a.datum, a.crs, a.name, a.unit) == (b.kind, b.frame, b.datum, b.crs, b.name, b.unit)
    for x, y in zip(a.axes, b.axes, strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-15, atol=1e-15)
    np.testing.assert_array_equal(a.values, b.values)  # NaN == NaN here
    np.testing.assert_array_equal(a.altitude_m, b.altitude_m)
    np.testing.assert_allclose(a.origin, b.origin, rtol=1e-14)
    assert a.metadata == b.metadata


def test_roundtrip_geodetic_scalar_and_vector(tmp_path, rng):
    for kind in (FieldKind.GRAVITY_DISTURBANCE_MGAL, FieldKind.VECTOR_FIELD_NT):
        m = _geo(rng, kind)
        write_map(m, tmp_path / f"{kind.value}.nc")
        _same(m, read_map(tmp_path / f"{kind.value}.nc"))


def test_roundtrip_local_draped(tmp_path, rng):
    n = np.arange(20) * 0.381
    e = np.arange(30) * 0.381
    alt = 200.0 + rng.normal(0, 1, (20, 30))
    m = GridMap(
        n,
        e,
        rng.normal(0, 5, (20, 30)),
        kind=FieldKind.TOTAL_FIELD_ANOMALY_NT,
        frame="local",
        altitude_m=alt,
        origin=(0.7, -1.47, 250.0),
        crs="hallway frame",
        name="hall",
    )
    write_map(m, tmp_path / "m.nc")
    _same(m, read_map(tmp_path / "m.nc"))
    # float32 storage: values rounded, everything else kept
    write_map(m, tmp_path / "m32.nc", dtype="float32")
    m32 = read_map(tmp_path / "m32.nc")
    np.testing.assert_allclose(m32.values, m.values, rtol=1e-6)


def _bare(tmp_path, drop: str):
    lat = np.linspace(-30, -29, 4)
    lon = np.linspace(140, 141, 5)
    da = xr.DataArray(
        np.ones((4, 5)),
        dims=("latitude", "longitude"),
        coords={"latitude": lat, "longitude": lon},
        attrs={"units": "nT", "magnav_kind": "total_field_anomaly_nt"},
    )
    ds = xr.Dataset({"anomaly": da}, attrs={"geodetic_datum": "WGS84", "altitude_m": 100.0})
    if drop in da.attrs:
        del ds["anomaly"].attrs[drop]
    else:
        del ds.attrs[drop]
    p = tmp_path / f"no_{drop}.nc"
    ds.to_netcdf(p)
    return p


@pytest.mark.parametrize(
    ("drop", "override"),
    [
        ("magnav_kind", {"kind": "total_field_anomaly_nt"}),
        ("units", None),
        ("geodetic_datum", {"datum": "WGS84"}),
        ("altitude_m", {"altitude_m": 100.0}),
    ],
)
def test_metadata_less_file_is_refused_naming_the_attribute(tmp_path, drop, override):
    p = _bare(tmp_path, drop)
    with pytest.raises(MapError, match=f"'{drop}'"):
        read_map(p)
    if override is not None:  # supplied explicitly, the file is accepted
        m = read_map(p, **override)
        assert m.kind is FieldKind.TOTAL_FIELD_ANOMALY_NT and m.altitude_m == 100.0


def test_wrong_unit_and_conflicting_override(tmp_path):
    p = _bare(tmp_path, "altitude_m")
    ds = xr.load_dataset(p)
    ds["anomaly"].attrs["units"] = "mGal"
    ds.attrs["altitude_m"] = 1.0
    ds.to_netcdf(tmp_path / "u.nc")
    with pytest.raises(MapError, match="units='mGal'"):
        read_map(tmp_path / "u.nc")
    with pytest.raises(MapError, match="requested"):
        read_map(_bare(tmp_path, "units").with_name("no_units.nc"), kind="gravity_disturbance_mgal")


def test_descending_latitude_file_is_flipped(tmp_path):
    lat = np.linspace(-29.0, -30.0, 11)  # north to south, as many grids are stored
    lon = np.linspace(140.0, 141.0, 6)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    ds = xr.Dataset(
        {"g": (("latitude", "longitude"), 10 * la + lo, {"units": "mGal"})},
        coords={"latitude": lat, "longitude": lon},
        attrs={"magnav_kind": "gravity_disturbance_mgal", "geodetic_datum": "WGS84", "altitude_m": 0.0},
    )
    ds.to_netcdf(tmp_path / "d.nc")
    m = read_map(tmp_path / "d.nc")
    np.testing.assert_allclose(m.value([-29.55 * DEG], [140.33 * DEG]), [10 * -29.55 + 140.33], atol=1e-9)


# ------------------------------------------------------------------------------------------------ surveys
HEADER = "flight_line,latitude,longitude,height_ellipsoidal_m,total_field_anomaly_nt\n"
GOOD = "1,-21.90,140.60,400,10\n1,-21.90,140.61,400,12\n2,-21.91,140.60,401,\n2,-21.91,140.61,401,14\n"


def _csv(tmp_path, text, name="s.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_survey_reads_and_drops_missing_values(tmp_path):
    s = read_survey(_csv(tmp_path, HEADER + GOOD))
    assert len(s) == 3 and s.kind is FieldKind.TOTAL_FIELD_ANOMALY_NT
    np.testing.assert_allclose(s.lat[0], -21.9 * DEG)
    np.testing.assert_array_equal(s.line, [1, 1, 2])
    line = read_survey_line(_csv(tmp_path, HEADER + GOOD), 1)
    np.testing.assert_allclose(line["value"], [10, 12])


def test_survey_xz_and_orthometric_heights(tmp_path):
    text = HEADER.replace("height_ellipsoidal_m", "height_orthometric_m") + GOOD
    p = tmp_path / "s.csv.xz"
    p.write_bytes(lzma.compress(text.encode()))
    s = read_survey(p, geoid_undulation_m=52.5)  # a given undulation overrides the shipped geoid
    np.testing.assert_allclose(s.h, [452.5, 452.5, 453.5])
    assert "52.50 m (given)" in s.heights


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("", "empty"),
        (HEADER, "no data rows"),
        (HEADER + "1,-21.9,140.6,400,10,99\n", "malformed"),
        (HEADER.replace("latitude", "lat") + GOOD, "latitude"),
        (HEADER.replace("total_field_anomaly_nt", "total_field_anomaly_pt") + GOOD, "unit 'pt'"),
        (HEADER.replace("total_field_anomaly_nt", "reading") + GOOD, "no value column"),
        (HEADER + "1,140.6,-21.9,400,10\n", "swapped"),
        (HEADER + "1,-21.9,140.6,400,\n", "every value is missing"),
        (HEADER + GOOD + "3,-21.9,abc,400,1\n", "row 5 column 'longitude'"),
        (HEADER + GOOD + "3,,140.6,400,1\n", "row 5 column 'latitude': missing"),
        (HEADER.replace(",height_ellipsoidal_m", "").replace(",400", "") + "1,-21.9,140.6,1\n", "no height column"),
        (HEADER + "1.5,-21.9,140.6,400,1\n", "not an integer"),
    ],
)
def test_bad_survey_csv(tmp_path, text, match):
    with pytest.raises(InputError, match=match):
        read_survey(_csv(tmp_path, text))


def test_unknown_line_and_missing_file(tmp_path):
    with pytest.raises(InputError, match="no line 7"):
        read_survey_line(_csv(tmp_path, HEADER + GOOD), 7)
    with pytest.raises(InputError, match="no such survey"):
        read_survey(tmp_path / "nope.csv")


# ------------------------------------------------------------------------------------------------ load_map / builtin
def test_load_map_dispatch(tmp_path, rng):
    m = _geo(rng)
    write_map(m, tmp_path / "g.nc")
    _same(m, load_map(str(tmp_path / "g.nc")))
    with pytest.raises(MapError, match="grid spacing"):
        load_map(str(_csv(tmp_path, HEADER + GOOD)))
    with pytest.raises(MapError, match="no such shipped map"):
        load_map("builtin:nowhere")
    with pytest.raises(MapError, match="no such map file"):
        load_map(str(tmp_path / "x.nc"))
    with pytest.raises(MapError, match=r"unknown map option\(s\) \['spacing'\]"):
        load_map("builtin:osborne-magnetic", spacing=3)


def test_shipped_maps_load_with_metadata():
    for name in BUILTIN_MAPS:
        m = load_map(f"builtin:{name}")
        assert np.isfinite(m.values).mean() > 0.9 and m.metadata["made_by"] == "bench/make_builtin_maps.py"
    g = load_map("builtin:eigen6c4-australia-se")
    assert g.kind is FieldKind.GRAVITY_DISTURBANCE_MGAL and g.altitude_m == 10_000.0
    lat0, lat1, lon0, lon1 = g.bounds_latlon
    assert lat0 <= -38 * DEG and lat1 >= -35 * DEG and lon0 <= 144.5 * DEG and lon1 >= 150 * DEG
    # the disturbance is small (|dg| < 150 mGal at 10 km), i.e. normal gravity was removed
    assert np.nanmax(np.abs(g.values)) < 150.0


def test_shipped_osborne_map_predicts_the_independent_tie_lines():
    """The shipped map was gridded without the tie lines; their real readings are an independent check."""
    from magnav_ins.maps.build import tie_line_misfit

    m = load_map("builtin:osborne-magnetic")
    s = load_survey_lines("builtin:osborne-tie-lines")
    ids = s.line_ids()
    assert len(ids) == 22 and set(ids) & set(m.metadata.get("excluded_lines", [])) == set(ids)
    r = tie_line_misfit(m, s, ids)
    n = sum(v["n"] for v in r.values())
    rms = np.sqrt(sum(v["rms"] ** 2 * v["n"] for v in r.values()) / n)
    assert rms < 40.0
    assert n > 0.98 * len(s)


def test_error_layer_roundtrip_and_interpolation(tmp_path, rng):
    """The map error layer survives write/read, interpolates bilinearly between nodes and is NaN off the map."""
    m = _geo(rng)
    ny, nx = m.shape
    err = np.add.outer(np.arange(ny), np.arange(nx)).astype(float)  # linear in both axes: bilinear is exact
    em = m.with_error_layer(err, 750.0, "test ramp")
    assert em.has_error_layer and not m.has_error_layer
    write_map(em, tmp_path / "e.nc")
    back = read_map(tmp_path / "e.nc")
    _same(em, back)
    np.testing.assert_array_equal(back.error_sigma, err)
    assert back.error_correlation_m == 750.0 and back.error_source == "test ramp"
    lat, lon = m.axes
    # halfway between nodes (2, 5) and (3, 6): 2.5 + 5.5
    q = back.error_sigma_at(0.5 * (lat[2] + lat[3]), 0.5 * (lon[5] + lon[6]))
    assert abs(float(q) - 8.0) < 1e-9
    assert np.isnan(back.error_sigma_at(lat[0] - 0.1, lon[0]))
    assert np.all(np.isnan(m.error_sigma_at(lat[:3], lon[:3])))
    with pytest.raises(MapError, match="error_correlation_m"):
        m.with_error_layer(1.0, None)
    assert not em.with_error_layer(None).has_error_layer


def test_plain_netcdf_reader_equals_xarray(tmp_path, rng, monkeypatch):
    """``read_map`` reads this project's plain float files with netCDF4 alone (no xarray/pandas import: ~50 MB of
    a log replay's memory); the map is the same as through xarray, value for value (NaN holes, float32 storage,
    draped altitude, error layer, metadata). Packed, integer or string variables are left to xarray."""
    import magnav_ins.maps.io as mio
    from magnav_ins.maps.shipped import data_path

    m = _geo(rng)
    write_map(m, tmp_path / "g64.nc")
    write_map(m.with_error_layer(3.0, 2000.0, "test layer"), tmp_path / "g32.nc", dtype="float32")
    n, e = np.arange(20) * 50.0, np.arange(30) * 50.0
    local = GridMap(n, e, rng.normal(0, 5, (20, 30)), kind=FieldKind.TOTAL_FIELD_ANOMALY_NT, frame="local",
                    altitude_m=200.0 + rng.normal(0, 1, (20, 30)), origin=(-0.6, 2.4, 10.0), name="l")  # fmt: skip
    write_map(local, tmp_path / "local.nc", compress=False)
    files = [tmp_path / "g64.nc", tmp_path / "g32.nc", tmp_path / "local.nc"]
    files += [data_path(f"{name}.nc") for name in ("osborne-magnetic", "eigen6c4-australia-se")]
    for p in files:
        assert mio._PlainNetcdf.open(p) is not None, p
        plain = read_map(p)
        with monkeypatch.context() as mp:
            mp.setattr(mio._PlainNetcdf, "open", classmethod(lambda cls, path: None))
            ref = read_map(p)
        _same(plain, ref)
        assert (plain.has_error_layer, plain.error_correlation_m, plain.error_source) == (
            ref.has_error_layer, ref.error_correlation_m, ref.error_source)  # fmt: skip
        if ref.has_error_layer:
            np.testing.assert_array_equal(plain.error_sigma, ref.error_sigma)
    assert np.isnan(read_map(tmp_path / "g32.nc").values[3, 4])  # the hole stays a hole
    vec = _geo(rng, FieldKind.VECTOR_FIELD_NT)
    write_map(vec, tmp_path / "vec.nc")
    assert mio._PlainNetcdf.open(tmp_path / "vec.nc") is None  # string 'component' axis: xarray's
    _same(vec, read_map(tmp_path / "vec.nc"))
    assert mio._PlainNetcdf.open(data_path("eigen6c4-geoid-10arcmin.nc")) is None  # int16 packed: xarray's
