"""Grids as users download them (issue 14 items 1-3, 5): GeoTIFF / ER Mapper / GXF through GDAL, GMT COARDS and
legacy "cf" grids, CF NetCDF with a grid mapping; no-data, projected CRSs used in their own CRS (values and
gradients against analytic truth), units never guessed; ``map info`` / ``map convert``; every real file in
``../shared/data`` (``shared_data``) against a direct GDAL / xarray read."""

from __future__ import annotations

import json

import numpy as np
import pytest
import xarray as xr

from magnav_ins import cli
from magnav_ins.core.errors import ConfigError, MapError
from magnav_ins.core.frames import meters_to_latlon
from magnav_ins.core.types import FieldKind
from magnav_ins.maps.io import load_map, read_map, write_map
from magnav_ins.maps.projection import Projection

DEG = np.pi / 180.0
UTM55S = "EPSG:32755"  # WGS 84 / UTM zone 55S (south-east Australia)


def _plane(e, n):
    """A field linear in projected easting / northing (m): bilinear interpolation reproduces it exactly."""
    return 12.0 + 0.004 * (e - 500_000.0) - 0.003 * (n - 6_000_000.0)


@pytest.fixture
def utm_tif(tmp_path):
    import rasterio
    from rasterio.transform import from_origin

    ny, nx, step = 60, 80, 250.0
    west, north = 480_000.0, 6_010_000.0
    e = west + (np.arange(nx) + 0.5) * step
    n = north - (np.arange(ny) + 0.5) * step
    ee, nn = np.meshgrid(e, n)
    v = _plane(ee, nn).astype(np.float32)
    v[5, 7] = -9999.0  # no data
    p = tmp_path / "utm.tif"
    with rasterio.open(p, "w", driver="GTiff", width=nx, height=ny, count=1, dtype="float32", crs=UTM55S,
                       transform=from_origin(west, north, step, step), nodata=-9999.0) as ds:  # fmt: skip
        ds.write(v, 1)
    return p, e, n


def test_projected_geotiff_is_used_in_its_own_crs(utm_tif):
    p, e, n = utm_tif
    with pytest.raises(MapError, match=r"--kind.*--unit|--kind.*--altitude-m"):
        read_map(p)
    m = read_map(p, kind="gravity_disturbance_mgal", unit="mGal", altitude_m=100.0)
    assert m.frame == "projected" and m.metadata["format"] == "GeoTIFF (GDAL)"
    assert np.isnan(m.values).sum() == 1 and abs(m.metadata["no_data_fraction"] - 1 / (60 * 80)) < 1e-12
    proj = Projection(UTM55S)
    rng = np.random.default_rng(0)
    qe, qn = rng.uniform(e[10], e[-1], 200), rng.uniform(n[-1], n[10], 200)
    lat, lon = proj.inverse(qe, qn)
    np.testing.assert_allclose(m.value(lat, lon), _plane(qe, qn), atol=1e-6)
    # gradients in metres of true north / east at the query point: against finite differences of the field along
    # true north and east (1 m on the ellipsoid), which include the projection's scale and meridian convergence
    g = m.gradient_ne(lat, lon)
    for k, (dn, de) in enumerate(((1.0, 0.0), (0.0, 1.0))):
        dla, dlo = meters_to_latlon(np.full(200, dn), np.full(200, de), lat)
        fd = (m.value(lat + dla, lon + dlo) - m.value(lat - dla, lon - dlo)) / 2.0
        np.testing.assert_allclose(g[:, k], fd, rtol=1e-5, atol=1e-9)
    assert abs(m.spacing_m[0] - 250.0) < 1.0  # UTM scale 0.9996..1.0004 here


def test_projected_map_round_trips_and_reprojects(tmp_path, utm_tif):
    p, e, n = utm_tif
    m = read_map(p, kind="gravity_disturbance_mgal", unit="mGal", altitude_m=100.0)
    write_map(m, tmp_path / "p.nc")
    back = read_map(tmp_path / "p.nc")
    assert back.frame == "projected"
    np.testing.assert_array_equal(back.values, m.values)
    lat, lon = Projection(UTM55S).inverse(e[20], n[30])
    assert abs(float(back.value(lat, lon)) - _plane(e[20], n[30])) < 1e-6
    geo = read_map(p, kind="gravity_disturbance_mgal", unit="mGal", altitude_m=100.0, reproject=True)
    assert geo.frame == "geodetic" and geo.metadata["reprojected_from"]
    q = np.random.default_rng(1)
    la = q.uniform(geo.lat[5], geo.lat[-5], 100)
    lo = q.uniform(geo.lon[5], geo.lon[-5], 100)
    qe, qn = Projection(UTM55S).forward(la, lo)
    ok = np.isfinite(geo.value(la, lo)) & np.isfinite(m.value(la, lo))
    np.testing.assert_allclose(geo.value(la, lo)[ok], _plane(qe, qn)[ok], atol=1e-4)  # a plane stays ~ a plane


def _nc(tmp_path, name, values, units, coords=("lat", "lon"), extra=None):
    y = np.linspace(-30.0, -29.0, values.shape[0])
    x = np.linspace(140.0, 141.0, values.shape[1])
    attrs = {} if units is None else {"units": units}
    ds = xr.Dataset({"a_long_erddap_name": (coords, values, attrs)}, coords={coords[0]: y, coords[1]: x})
    if coords == ("lat", "lon"):
        ds["lat"].attrs["units"] = "degrees_north"
        ds["lon"].attrs["units"] = "degrees_east"
    ds.attrs.update(extra or {})
    p = tmp_path / name
    ds.to_netcdf(p)
    return p


@pytest.mark.parametrize(
    ("units", "given", "factor"),
    [("mGal", None, 1.0), ("um/s^2", None, 0.1), ("m s-2", None, 1e5), ("Degree", "um/s^2", 0.1), (None, "gu", 0.1)],
)
def test_gravity_units_are_read_or_given_and_converted(tmp_path, units, given, factor):
    v = np.arange(20.0).reshape(4, 5) + 1.0
    p = _nc(tmp_path, "g.nc", v, units)
    kw = {"kind": "gravity_disturbance_mgal", "altitude_m": 0.0, "datum": "WGS84"}
    if given is not None:
        with pytest.raises(MapError, match=r"variable 'a_long_erddap_name'.*--unit UNIT \(scenario \[map\] unit\)"):
            read_map(p, **kw)
    m = read_map(p, **kw, unit=given)
    np.testing.assert_allclose(m.values, v * factor)


def test_impossible_or_conflicting_units_are_refused(tmp_path):
    p = _nc(tmp_path, "g.nc", np.ones((4, 5)), "mGal")
    kw = {"kind": "gravity_disturbance_mgal", "altitude_m": 0.0, "datum": "WGS84"}
    with pytest.raises(MapError, match="the file says units='mGal' but unit='um/s\\^2'"):
        read_map(p, **kw, unit="um/s^2")
    with pytest.raises(MapError, match="not a unit of gravity_disturbance_mgal"):
        read_map(p, **kw, unit="nT")
    with pytest.raises(MapError, match="units='mGal' is not a unit of total_field_anomaly_nt"):
        read_map(p, kind="total_field_anomaly_nt", altitude_m=0.0, datum="WGS84")


def test_metres_without_crs_need_one_and_nodata_conventions(tmp_path):
    v = np.full((4, 5), 3.0)
    v[0, 0], v[1, 1] = -99999.0, 1e32
    p = _nc(tmp_path, "xy.nc", v, "nT", coords=("y", "x"))
    with pytest.raises(MapError, match=r"unknown projection.*--crs"):
        read_map(p, kind="total_field_anomaly_nt", altitude_m=0.0)
    m = read_map(p, kind="total_field_anomaly_nt", altitude_m=0.0, crs="+proj=tmerc +lat_0=-30 +lon_0=140 +datum=WGS84")
    assert m.frame == "projected" and int(np.isnan(m.values).sum()) == 2


def test_gmt_legacy_cf_grid_orientation(tmp_path):
    """GMT's "cf" layout: 1-D z stored row by row from the top (north) row; gridline registration."""
    nx, ny = 7, 4
    lon = np.linspace(10.0, 16.0, nx)
    lat = np.linspace(-3.0, 0.0, ny)
    la, lo = np.meshgrid(lat[::-1], lon, indexing="ij")  # top row first
    z = (100 * la + lo).ravel()
    ds = xr.Dataset(
        {
            "x_range": ("side", [10.0, 16.0], {"units": "longitude [degrees_east]"}),
            "y_range": ("side", [-3.0, 0.0], {"units": "latitude [degrees_north]"}),
            "z_range": ("side", [z.min(), z.max()], {"units": "nT"}),
            "spacing": ("side", [1.0, 1.0]),
            "dimension": ("side", np.array([nx, ny], dtype=np.int32)),
            "z": ("xysize", z.astype(np.float32), {"node_offset": np.int32(0)}),
        }
    )
    ds.to_netcdf(tmp_path / "cf.grd")
    m = read_map(tmp_path / "cf.grd", kind="total_field_anomaly_nt", altitude_m=0.0, datum="WGS84")
    assert m.metadata["format"] == "GMT legacy cf grid"
    np.testing.assert_allclose(m.value(-1.0 * DEG, 13.0 * DEG), -100.0 + 13.0, atol=1e-4)


def test_map_convert_and_info_cli(tmp_path, utm_tif, monkeypatch, capsys):
    monkeypatch.setattr(cli, "COMMAND_MODULES", ("maps",))
    p, e, n = utm_tif
    assert cli.main(["map", "info", str(p)]) == 2
    err = capsys.readouterr().err
    assert "--kind" in err and "--altitude-m" in err and str(p) in err and err.count("\n") == 1
    opts = ["--kind", "gravity_disturbance_mgal", "--unit", "mGal", "--altitude-m", "100"]
    assert cli.main(["map", "info", str(p), "--json", *opts]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["format"] == "GeoTIFF (GDAL)" and s["frame"] == "projected" and "UTM zone 55S" in s["crs_name"]
    assert "in its own CRS" in s["used_as"] and abs(s["spacing_m"][0] - 250) < 1 and s["error_layer"] is None
    out = tmp_path / "c.nc"
    assert cli.main(["map", "convert", str(p), *opts, "--out", str(out)]) == 0
    assert read_map(out).frame == "projected"
    assert cli.main(["map", "convert", str(p), *opts, "--reproject", "--out", str(tmp_path / "g.nc")]) == 0
    assert read_map(tmp_path / "g.nc").frame == "geodetic"


def test_scenario_reads_a_downloaded_grid(utm_tif):
    from magnav_ins.studies import model as Mdl
    from magnav_ins.studies.scenario import scenario_from_dict

    p, e, n = utm_tif
    lat, lon = Projection(UTM55S).inverse(np.array([e[10], e[60]]), np.array([n[40], n[20]]))
    doc = {
        "name": "tif",
        "trajectory": {
            "kind": "great_circle",
            "start": [lat[0] / DEG, lon[0] / DEG],
            "end": [lat[1] / DEG, lon[1] / DEG],
            "altitude_m": 100.0,
            "speed_mps": 50.0,
        },  # fmt: skip
        "imu": {"grade": "navigation"},
        "map": {"path": str(p), "kind": "gravity_disturbance_mgal", "unit": "mGal", "altitude_m": 100.0},
    }
    fm = Mdl.build_map(scenario_from_dict(doc))
    assert fm.frame == "projected" and fm.kind is FieldKind.GRAVITY_DISTURBANCE_MGAL
    doc["map"].pop("unit")
    with pytest.raises(ConfigError, match=r"map.path.*--unit UNIT \(scenario \[map\] unit\)"):
        Mdl.build_map(scenario_from_dict(doc))
    doc["map"]["unit"] = "mGal"
    doc["map"]["path"] = "builtin:osborne-magnetic"
    with pytest.raises(ConfigError, match=r"map\.(unit|altitude_m).*grid file"):
        scenario_from_dict(doc)


# ------------------------------------------------------------------------------------------------ real files
GRAV = {"QLDWestGravity.nc", "Gabbs_USGS_CBA2p60_ALL_gridded.tif", "QLDWestGravity", "QLDWestGravity.ers",
        "AK_gulf_grav.nc", "grav.V18.par.surf.1km.sq.nc"}  # fmt: skip
REAL = [
    "map_formats/EMAG2_V2_1x1.grd",
    "map_formats/Gabbs_USGS_CBA2p60_ALL_gridded.tif",
    "map_formats/QLDWestGravity",
    "map_formats/QLDWestGravity.ers",
    "map_formats/QLDWestMagnetic",
    "map_formats/QLDWestMagnetic.ers",
    "map_formats/brtpgrd.gxf",
    "map_formats/ga_survey409_tmi.nc",
    "ga_qld_west/QLDWestGravity.nc",
    "ga_qld_west/QLDWestMagnetic.nc",
    "marine_gravity/AK_gulf_grav.nc",
    "marine_gravity/grav.V18.par.surf.1km.sq.nc",
    "rio_magnetic/rio-de-janeiro-magnetic-grid.nc",
]


def _opts(name):
    """What each file does not state (PROVENANCE sec. 6-10), given as a user would."""
    d = {"kind": "gravity_disturbance_mgal" if name in GRAV else "total_field_anomaly_nt", "altitude_m": 0.0}
    d["unit"] = ("um/s^2" if name.startswith("QLDWestGravity") else "mGal") if name in GRAV else "nT"
    if name in ("QLDWestGravity.nc", "QLDWestMagnetic.nc", "EMAG2_V2_1x1.grd", "AK_gulf_grav.nc"):
        d["datum"] = "WGS84"
    if name.startswith("grav.V18"):  # local x/y of GMT example 37; any CRS makes it usable
        d["crs"] = "+proj=tmerc +lat_0=0 +lon_0=0 +datum=WGS84"
    if name.startswith("rio"):  # verde's Mercator with the true scale at the survey's mean latitude
        d.update(variable="total_field_anomaly", crs="+proj=merc +lat_ts=-22.248 +datum=WGS84", altitude_m=300.0)
    return d


def _direct(path, name, opts):
    """(y, x, values, geographic) by a direct read: GDAL (rasterio) for everything GDAL opens, else xarray."""
    import rasterio

    p = path.with_name(path.name + ".ers") if path.suffix == "" else path
    if name.startswith("EMAG2"):  # GMT legacy cf grid: no GDAL driver; the documented layout (top row first)
        ds = xr.load_dataset(p)
        nx, ny = (int(v) for v in ds["dimension"].values)
        z = ds["z"].values.reshape(ny, nx).astype(float)
        z[z == -99999.0] = np.nan
        return np.linspace(90, -90, ny), np.linspace(-180, 180, nx), z, True
    if name.startswith(("rio", "grav.V18")):
        da = xr.load_dataset(p)[opts.get("variable", "z")]
        return da[da.dims[0]].values, da[da.dims[1]].values, da.values.astype(float), False
    with rasterio.open(p) as ds:
        v = ds.read(1, masked=True).astype(float).filled(np.nan)
        t = ds.transform
        x = t.c + (np.arange(ds.width) + 0.5) * t.a
        y = t.f + (np.arange(ds.height) + 0.5) * t.e
        geographic = ds.crs is None or ds.crs.is_geographic
    v[(v == -99999.0) | (np.abs(v) >= 1e30)] = np.nan
    return y, x, v, geographic


@pytest.mark.shared_data
@pytest.mark.parametrize("rel", REAL, ids=lambda r: r.split("/")[-1])
def test_every_real_file_opens_converts_and_samples_like_a_direct_read(shared_data, rel, tmp_path):
    from scipy.interpolate import RegularGridInterpolator

    path = shared_data / rel
    name = path.name
    opts = _opts(name)
    with pytest.raises(MapError) as exc:
        read_map(path)
    msg = str(exc.value)
    assert "\n" not in msg and str(path) in msg and ("--kind" in msg or "--variable" in msg)
    m = load_map(str(path), **opts)
    # converted to this project's format and read back: the same map
    write_map(m, tmp_path / "c.nc", dtype="float32")
    back = read_map(tmp_path / "c.nc")
    assert back.frame == m.frame and back.kind is m.kind
    y, x, v, geographic = _direct(path, name, opts)
    factor = {"um/s^2": 0.1}.get(opts["unit"], 1.0)
    oy, ox = np.argsort(y), np.argsort(x)
    ref = RegularGridInterpolator((y[oy], x[ox]), v[oy][:, ox] * factor, bounds_error=False)
    rng = np.random.default_rng(14)
    qy = rng.uniform(y.min(), y.max(), 100)
    qx = rng.uniform(x.min(), x.max(), 100)
    if geographic:
        lat, lon = qy * DEG, qx * DEG
    else:
        lat, lon = Projection(opts.get("crs") or m.crs).inverse(qx, qy)
    want = ref(np.c_[qy, qx])
    for mm in (m, back):
        got = mm.value(lat, lon)
        assert np.array_equal(np.isnan(got), np.isnan(want)), f"{name}: NaN pattern differs"
        scale = np.nanmax(np.abs(v * factor))
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=2e-7 * scale)


def _write_geosoft_grd(path, values, x0, y0, step, *, es=4, compressed=False):
    """A Geosoft binary grid, version 2 (Geosoft "Grid File Format", as harmonica documents it): a 512-byte header
    (ES, SF, NE, NV, KX as int32; DE, DV, X0, Y0, ROT, ZBASE, ZMULT as float64 at offsets 20 and 60), then the rows
    from the south (KX = 1: NV rows of NE values), float32 with the dummy -1e32 for no data."""
    import struct

    nv, ne = values.shape
    header = bytearray(512)
    struct.pack_into("<5i", header, 0, es, 2, ne, nv, 1)
    struct.pack_into("<5d", header, 20, step, step, x0, y0, 0.0)
    struct.pack_into("<2d", header, 60, 0.0, 1.0)
    body = np.where(np.isnan(values), -1e32, values).astype("<f4").tobytes()
    path.write_bytes(bytes(header) + body)


def test_geosoft_binary_grd_reads_its_nodes_in_its_own_crs(tmp_path):
    """No real Geosoft .grd is in ../shared/data: the file is written here from the format's documented layout, so the
    node values, the south-to-north row order, the dummy and the origin are independent truth for the reader."""
    pytest.importorskip("harmonica")
    ny, nx, step = 30, 40, 200.0
    x0, y0 = 480_000.0, 5_990_000.0  # the south-west node (UTM 55S)
    e = x0 + np.arange(nx) * step
    n = y0 + np.arange(ny) * step
    ee, nn = np.meshgrid(e, n)
    v = _plane(ee, nn)
    v[3, 4] = np.nan
    p = tmp_path / "survey.grd"
    _write_geosoft_grd(p, v, x0, y0, step)
    with pytest.raises(MapError, match="crs"):
        read_map(p, kind="total_field_anomaly_nt", unit="nT", altitude_m=80.0)
    m = read_map(p, kind="total_field_anomaly_nt", unit="nT", altitude_m=80.0, crs=UTM55S)
    assert m.frame == "projected" and "Geosoft" in m.metadata["format"]
    assert np.isnan(m.values).sum() == 1
    lat, lon = Projection(UTM55S).inverse(ee.ravel(), nn.ravel())
    got = m.value(lat, lon)
    ok = ~np.isnan(v.ravel())
    np.testing.assert_allclose(got[ok], v.ravel()[ok], rtol=0, atol=1e-3)  # float32 rounding of ~100 nT values
    assert np.isnan(got[~ok]).all()


def test_a_truncated_geosoft_grd_is_one_message(tmp_path):
    pytest.importorskip("harmonica")
    p = tmp_path / "cut.grd"
    _write_geosoft_grd(p, np.ones((10, 12)), 0.0, 0.0, 100.0)
    p.write_bytes(p.read_bytes()[:600])
    with pytest.raises(MapError, match="cut.grd"):
        read_map(p, kind="total_field_anomaly_nt", unit="nT", altitude_m=0.0, crs=UTM55S)
