"""Combining maps (issue 14 item 6): a fine grid over a coarse one with a blended edge, levelling and both error
layers; analytic cases and two real files (``shared_data``)."""

from __future__ import annotations

import numpy as np
import pytest

from magnav_ins import cli
from magnav_ins.core.errors import MapError
from magnav_ins.core.types import FieldKind
from magnav_ins.maps.combine import combine_maps
from magnav_ins.maps.grid import GridMap
from magnav_ins.maps.io import load_map, read_map, write_map

DEG = np.pi / 180.0
K = FieldKind.TOTAL_FIELD_ANOMALY_NT


def _field(lat, lon):
    return 100.0 * np.sin(lat / DEG * 7.0) + 50.0 * np.cos(lon / DEG * 5.0)


def _maps(offset=0.0, fine_alt=300.0, coarse_alt=300.0):
    lat_c = np.linspace(-23.0, -21.0, 41) * DEG
    lon_c = np.linspace(139.0, 141.0, 41) * DEG
    coarse = GridMap(lat_c, lon_c, _field(*np.meshgrid(lat_c, lon_c, indexing="ij")) - offset, kind=K,
                     frame="geodetic", altitude_m=coarse_alt, name="coarse", error_sigma=40.0,
                     error_correlation_m=20_000.0, error_source="coarse")  # fmt: skip
    lat_f = np.linspace(-22.2, -21.8, 81) * DEG
    lon_f = np.linspace(139.8, 140.2, 81) * DEG
    fine = GridMap(lat_f, lon_f, _field(*np.meshgrid(lat_f, lon_f, indexing="ij")), kind=K, frame="geodetic",
                   altitude_m=fine_alt, name="fine", error_sigma=5.0, error_correlation_m=500.0,
                   error_source="fine")  # fmt: skip
    return fine, coarse


def test_fine_inside_coarse_outside_blend_between():
    fine, coarse = _maps(offset=30.0)  # the coarse map sits 30 nT low (another regional field removed)
    m = combine_maps(fine, coarse, blend_m=2000.0)
    assert abs(m.metadata["coarse_levelled_by"] - 30.0) < 1.0
    la, lo = m.node_latlon()
    inside = (np.abs(la / DEG + 22.0) < 0.1) & (np.abs(lo / DEG - 140.0) < 0.1)  # > 2 km from the fine edge
    outside = (np.abs(la / DEG + 22.0) > 0.21) | (np.abs(lo / DEG - 140.0) > 0.21)
    np.testing.assert_allclose(m.values[inside], fine.value(la[inside], lo[inside]), atol=1e-9)
    np.testing.assert_allclose(m.values[outside], coarse.value(la[outside], lo[outside]) + 30.0, rtol=0, atol=1.0)
    # both maps hold the same field (after levelling): the blend is the field everywhere, within the coarse
    # map's interpolation error
    assert np.nanmax(np.abs(m.values - _field(la, lo))) < 3.0
    # the error layer: the fine sigma inside, the coarse one outside, the blend's in between (never below either's
    # weighted share, never above the coarse sigma)
    assert np.allclose(m.error_sigma[inside], 5.0) and np.allclose(m.error_sigma[outside], 40.0)
    assert m.error_sigma.min() >= 5.0 * 0.7 - 1e-9 and m.error_sigma.max() <= 40.0 + 1e-9
    assert m.error_correlation_m == 20_000.0


def test_blend_weights_are_a_raised_cosine_of_the_distance_to_the_edge():
    fine, coarse = _maps()
    fine = fine.with_values(np.full(fine.shape, 10.0))
    coarse = coarse.with_values(np.zeros(coarse.shape))
    m = combine_maps(fine, coarse, blend_m=3000.0, level=False)
    # along the parallel through the fine map's centre the combined value is 10 w(d), d the distance from the
    # nearest node where the fine map has no data (to the west, on this row)
    la, lo = m.node_latlon()
    row = int(np.argmin(np.abs(m.axes[0] + 22.0 * DEG)))
    covered = np.isfinite(fine.value(la[row], lo[row]))
    first = int(np.argmax(covered))  # first covered node from the west
    from magnav_ins.core.frames import latlon_to_meters

    _, d = latlon_to_meters(0.0, lo[row] - lo[row][first - 1], la[row])
    sel = covered & (d < 2800.0)
    sel[first + 20 :] = False
    w = m.values[row][sel] / 10.0
    assert np.all(np.diff(w) > 0) and w[0] < 0.1  # rises from the edge
    want = 0.5 - 0.5 * np.cos(np.pi * np.clip(d[sel] / 3000.0, 0, 1))
    np.testing.assert_allclose(w, want, atol=2e-3)


def test_lower_coarse_map_is_continued_up_and_bad_requests():
    fine, coarse = _maps(fine_alt=1000.0, coarse_alt=0.0)
    m = combine_maps(fine, coarse)
    assert m.metadata["coarse_continued_m"] == [0.0, 1000.0]
    fine2, coarse2 = _maps(fine_alt=0.0, coarse_alt=1000.0)
    assert combine_maps(fine2, coarse2).metadata["coarse_height_above_fine_m"] == 1000.0
    g = coarse.with_values(coarse.values, kind=FieldKind.GRAVITY_DISTURBANCE_MGAL)
    with pytest.raises(MapError, match="holds"):
        combine_maps(fine, g)
    far = GridMap(np.linspace(10, 11, 5) * DEG, np.linspace(10, 11, 5) * DEG, np.ones((5, 5)), kind=K,
                  frame="geodetic", altitude_m=0.0)  # fmt: skip
    with pytest.raises(MapError, match="does not cover"):
        combine_maps(fine, far)
    assert "none" in combine_maps(fine.with_error_layer(None), coarse).metadata["error_layer"]


def test_map_combine_cli(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(cli, "COMMAND_MODULES", ("maps",))
    fine, coarse = _maps(offset=12.0)
    write_map(fine, tmp_path / "f.nc")
    write_map(coarse, tmp_path / "c.nc")
    assert cli.main(["map", "combine", str(tmp_path / "f.nc"), str(tmp_path / "c.nc"), "--out",
                     str(tmp_path / "m.nc")]) == 0  # fmt: skip
    assert "coarse levelled by +11." in capsys.readouterr().out  # the 12 nT, within the coarse interpolation
    assert read_map(tmp_path / "m.nc").has_error_layer


@pytest.mark.shared_data
def test_real_survey_tile_over_a_global_grid(shared_data):
    """Geoscience Australia's Magmap tile (0.9 km) over EMAG2 (1 deg, global): inside the tile the combined map is
    the tile, far outside it is EMAG2 (levelled), and the combined map agrees with the tile's own values where the
    tile has data beyond the blend zone."""
    fine = load_map(str(shared_data / "map_formats" / "QLDWestMagnetic.ers"), kind="total_field_anomaly_nt",
                    unit="nT", altitude_m=80.0, error_sigma=50.0, error_correlation_m=2000.0)  # fmt: skip
    coarse = load_map(str(shared_data / "map_formats" / "EMAG2_V2_1x1.grd"), kind="total_field_anomaly_nt",
                      unit="nT", altitude_m=4000.0, datum="WGS84", error_sigma=60.0,
                      error_correlation_m=100_000.0)  # fmt: skip
    m = combine_maps(fine, coarse, margin_m=30_000.0, blend_m=5000.0)
    assert m.metadata["coarse_height_above_fine_m"] == 3920.0 and "coarse_levelled_by" in m.metadata
    la, lo = m.node_latlon()
    core = (np.abs(la / DEG + 20.5) < 0.4) & (np.abs(lo / DEG - 140.5) < 0.4)
    np.testing.assert_allclose(m.values[core], fine.value(la[core], lo[core]), atol=1e-6)
    ring = (np.abs(la / DEG + 20.5) > 0.75) | (np.abs(lo / DEG - 140.5) > 0.75)
    want = coarse.value(la[ring], lo[ring]) + m.metadata["coarse_levelled_by"]
    np.testing.assert_allclose(m.values[ring], want, atol=1e-6)
    assert np.allclose(m.error_sigma[core], 50.0) and np.allclose(m.error_sigma[ring], 60.0)
    assert np.isfinite(m.values).all()
