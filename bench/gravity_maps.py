"""Where gravity-map aiding is possible before flying (issue 16, item 5): feature variability and Cramer-Rao maps
of each grid of the gravity comparison, with the scenario's track, one figure per map.

Per map (the grid as the scenario loads it: the QLD grid continued to 100 m, the marine grid at sea level, the
EIGEN-6C4 10' grid at 10 km):

* the field (mGal) with the flight's truth track;
* ``sqrt(C_i)`` (mGal), Wang et al.'s map feature variability (eq. 14) over a 5 km window
  (:func:`magnav_ins.maps.variability.feature_variability`);
* the Cramer-Rao bound (m, DRMS) on a common position offset of 1 mGal readings at every node of a window as long
  as a 30-reading batch at 22 m/s (6.6 km; :func:`magnav_ins.maps.variability.crlb_raster`), and the single-reading
  bound ``sigma / |grad|`` along the track.

Writes ``docs/gravity_information_<stem>.png`` and prints one JSON line with the medians along each track.
Run: ``python bench/gravity_maps.py [--out docs] [--json]``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ("gravity_melbourne_sydney", "gravity_qld_west", "gravity_gulf_of_alaska")
VARIABILITY_WINDOW_M = 5000.0
BATCH_WINDOW_M = 30 * 10.0 * 22.0
SIGMA_MGAL = 1.0


def figure(stem: str, out: Path) -> dict[str, float]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from magnav_ins.maps.variability import crlb_raster, crlb_track, feature_variability, feature_variability_track
    from magnav_ins.studies.model import PipelineModel
    from magnav_ins.studies.scenario import load_scenario

    sc = load_scenario(ROOT / "examples" / "scenarios" / f"{stem}.toml")
    sh = PipelineModel(sc).shared()
    fmap, truth = sh["map"], sh["truth"]
    lat, lon = np.asarray(fmap.axes[0]), np.asarray(fmap.axes[1])
    extent = [np.degrees(lon[0]), np.degrees(lon[-1]), np.degrees(lat[0]), np.degrees(lat[-1])]
    C = np.asarray(feature_variability(fmap, VARIABILITY_WINDOW_M).values)
    cr = crlb_raster(fmap, SIGMA_MGAL, BATCH_WINDOW_M)
    k = np.arange(0, len(truth.t), max(1, int(10.0 * sc.imu.rate_hz)))  # a reading every 10 s
    tl, to = truth.lat[k], truth.lon[k]
    along, _ = crlb_track(fmap, tl, to, SIGMA_MGAL)
    c_track = feature_variability_track(fmap, tl, to, VARIABILITY_WINDOW_M, step_m=VARIABILITY_WINDOW_M / 20.0)
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.6), constrained_layout=True)
    panels = [
        (np.asarray(fmap.values), "field (mGal)", "RdBu_r", None),
        (np.sqrt(C), f"sqrt(C_i), {VARIABILITY_WINDOW_M / 1000:.0f} km window (mGal)", "viridis", None),
        (np.clip(cr["drms"], 0, None), f"CRLB DRMS, {BATCH_WINDOW_M / 1000:.1f} km window, 1 mGal (m)", "magma_r",
         matplotlib.colors.LogNorm()),
    ]  # fmt: skip
    for a, (img, title, cmap, norm) in zip(ax, panels, strict=True):
        img = np.where(np.isfinite(img), img, np.nan)
        im = a.imshow(img, origin="lower", extent=extent, cmap=cmap, norm=norm, aspect="auto")
        a.plot(np.degrees(truth.lon), np.degrees(truth.lat), "k-", lw=0.8)
        a.set_title(title, fontsize=10)
        a.set_xlabel("longitude (deg)")
        fig.colorbar(im, ax=a, shrink=0.85)
    ax[0].set_ylabel("latitude (deg)")
    fig.suptitle(f"{stem}: {fmap.name}, {fmap.spacing_m[0]:.0f} x {fmap.spacing_m[1]:.0f} m nodes at "
                 f"{float(fmap.altitude_m):.0f} m")  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"gravity_information_{stem}.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    ok = np.isfinite(cr["drms"])
    return {
        "figure": str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path),
        "spacing_m": [float(x) for x in fmap.spacing_m],
        "std_mgal": float(np.nanstd(fmap.values)),
        "track_sqrt_variability_median_mgal": float(np.nanmedian(np.sqrt(c_track))),
        "track_single_reading_crlb_median_m": float(np.nanmedian(along)),
        "map_crlb_drms_median_m": float(np.median(cr["drms"][ok])),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    ap.add_argument("--only", nargs="*", default=list(SCENARIOS))
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    res = {stem: figure(stem, args.out) for stem in args.only}
    if args.json:
        print(json.dumps(res, separators=(",", ":")))
    else:
        for stem, r in res.items():
            print(stem, r)
    return 0


if __name__ == "__main__":
    sys.exit(main())
