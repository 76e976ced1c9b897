"""Study figures (matplotlib, Agg backend, PNG written atomically). Every function takes the ``runs.nc`` dataset
made by :func:`magnav_ins.studies.runner.runs_dataset`, so figures can be redrawn from a finished study::

    ds = xarray.load_dataset("out/runs.nc"); plots.study_figures(ds, "out")

* :func:`plot_track` - truth and estimated tracks of one run over the map, fixes with 3-sigma ellipses.
* :func:`plot_error_vs_time` - RMS (over runs) horizontal error vs time per estimator with the filter's 3-sigma.
* :func:`plot_error_cdf` - empirical CDF of the horizontal error per estimator (pooled over runs and time).
* :func:`plot_free_inertial` - free-inertial drift of every run and its RMS.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..core.atomic import atomic_path  # noqa: E402
from ..core.frames import latlon_to_meters  # noqa: E402
from ..core.units import DEG_TO_RAD  # noqa: E402
from .scenario import FREE_INERTIAL  # noqa: E402

_DPI = 110


def _save(fig: Any, path: Path) -> Path:
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format="png", dpi=_DPI, bbox_inches="tight")
    finally:
        plt.close(fig)
    return path


def _time_axis(t_s: np.ndarray) -> tuple[np.ndarray, str]:
    span = float(t_s[-1] - t_s[0]) if len(t_s) else 0.0
    if span > 2 * 3600:
        return t_s / 3600.0, "time (h)"
    if span > 600:
        return t_s / 60.0, "time (min)"
    return t_s, "time (s)"


def _names(ds: Any) -> list[str]:
    return [str(n) for n in ds["estimator"].values]


def _h_err(ds: Any) -> np.ndarray:
    return np.hypot(ds["err_north_m"].values.astype(float), ds["err_east_m"].values.astype(float))  # (R, E, N)


def plot_error_vs_time(ds: Any, path: str | Path) -> Path:
    """RMS over runs of the horizontal error (m) vs time per estimator; dashed: RMS over runs of the filter's
    horizontal 3-sigma (3 sqrt(P_nn + P_ee)) where the estimator has a covariance."""
    e = _h_err(ds)
    x, xlabel = _time_axis(ds["time"].values)
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for j, name in enumerate(_names(ds)):
        with np.errstate(invalid="ignore"):
            rms = np.sqrt(np.nanmean(e[:, j] ** 2, axis=0))
        (line,) = ax.plot(x, rms, lw=1.6 if name != FREE_INERTIAL else 1.2, label=f"{name} RMS")
        s2 = ds["sigma_north_m"].values[:, j].astype(float) ** 2 + ds["sigma_east_m"].values[:, j].astype(float) ** 2
        if np.isfinite(s2).any():
            with np.errstate(invalid="ignore"):
                three_sigma = 3.0 * np.sqrt(np.nanmean(s2, axis=0))
            ax.plot(x, three_sigma, ls="--", lw=1.0, color=line.get_color(), label=f"{name} 3σ")
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("horizontal error (m)")
    ax.set_title(f"Horizontal error, RMS over {ds.sizes['run']} run(s)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, ncol=2)
    return _save(fig, Path(path))


def plot_error_cdf(ds: Any, path: str | Path) -> Path:
    """Empirical CDF of the horizontal error (m) per estimator, pooled over runs and samples."""
    e = _h_err(ds)
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for j, name in enumerate(_names(ds)):
        v = np.sort(e[:, j].ravel()[np.isfinite(e[:, j].ravel())])
        if v.size:
            ax.plot(np.maximum(v, 1e-3), np.arange(1, v.size + 1) / v.size, label=name)
    ax.set_xscale("log")
    ax.set_xlabel("horizontal error (m)")
    ax.set_ylabel("fraction of samples ≤ error")
    ax.set_ylim(0, 1)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("Error CDF (all runs, all samples)")
    return _save(fig, Path(path))


def plot_free_inertial(ds: Any, path: str | Path) -> Path:
    """Free-inertial horizontal drift (m) of every run (thin) and its RMS over runs (thick)."""
    names = _names(ds)
    j = names.index(FREE_INERTIAL)
    e = _h_err(ds)[:, j]
    x, xlabel = _time_axis(ds["time"].values)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for r in range(e.shape[0]):
        ax.plot(x, e[r], color="0.6", lw=0.6, alpha=0.7)
    ax.plot(x, np.sqrt(np.nanmean(e**2, axis=0)), color="C3", lw=2.0, label=f"RMS over {e.shape[0]} run(s)")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("horizontal error (m)")
    ax.set_title("Free-inertial drift")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, Path(path))


def plot_track(ds: Any, path: str | Path, fmap: Any = None, run: int = 0, ellipse_every: int = 1) -> Path:
    """Truth and estimated tracks of run ``run`` over the map (when ``fmap``, a
    :class:`~magnav_ins.core.protocols.FieldMap`, is given), fixes as dots with their 3-sigma ellipses.

    Axes are east/north (m, or km for tracks longer than 20 km) from the truth's first point in an equirectangular
    projection about it (distortion below 1 % within a few hundred km of the start)."""
    lat0 = float(ds["truth_lat_deg"].values[0]) * DEG_TO_RAD
    lon0 = float(ds["truth_lon_deg"].values[0]) * DEG_TO_RAD
    lat = ds["truth_lat_deg"].values * DEG_TO_RAD
    lon = ds["truth_lon_deg"].values * DEG_TO_RAD
    t = ds["time"].values
    m_n, m_e = latlon_to_meters(1.0, 1.0, lat0)  # metres per rad of latitude / longitude at the start

    def ne_of(la: np.ndarray, lo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (la - lat0) * m_n, (lo - lon0) * m_e

    tn, te = ne_of(lat, lon)
    extent = max(np.ptp(tn), np.ptp(te), 1.0)
    scale, unit = (1e-3, "km") if extent > 20e3 else (1.0, "m")
    names = _names(ds)
    fig, ax = plt.subplots(figsize=(7.5, 6.5))
    if fmap is not None:
        pad = 0.08 * extent + 10.0
        gn = np.linspace(tn.min() - pad, tn.max() + pad, 220)
        ge = np.linspace(te.min() - pad, te.max() + pad, 220)
        GN, GE = np.meshgrid(gn, ge, indexing="ij")
        val = np.asarray(fmap.value(lat0 + GN.ravel() / m_n, lon0 + GE.ravel() / m_e), float)
        if val.ndim == 2:  # vector map: show the magnitude
            val = np.linalg.norm(val, axis=1)
        val = val.reshape(GN.shape)
        if np.isfinite(val).any():
            lo, hi = np.nanpercentile(val, [2, 98])
            im = ax.pcolormesh(ge * scale, gn * scale, val, cmap="RdBu_r", vmin=lo, vmax=hi, shading="auto", alpha=0.8)
            kind = getattr(fmap, "kind", None)
            label = "map |B|" if getattr(kind, "components", 1) == 3 else "map"
            fig.colorbar(im, ax=ax, shrink=0.8, label=f"{label} ({getattr(kind, 'unit', '')})")
    ax.plot(te * scale, tn * scale, "k-", lw=2.0, label="truth")
    for j, name in enumerate(names):
        dn = ds["err_north_m"].values[run, j].astype(float)
        de = ds["err_east_m"].values[run, j].astype(float)
        (line,) = ax.plot(
            (te + de) * scale, (tn + dn) * scale, lw=1.2, ls=":" if name == FREE_INERTIAL else "-", label=name
        )
        avail = ds["fix_available"].values[run, j].astype(bool)
        if not avail.any():
            continue
        ft = ds["fix_t_s"].values[run, j][avail]
        fn = np.interp(ft, t, tn) + ds["fix_err_north_m"].values[run, j][avail].astype(float)
        fe = np.interp(ft, t, te) + ds["fix_err_east_m"].values[run, j][avail].astype(float)
        ax.plot(fe * scale, fn * scale, ".", ms=4, color=line.get_color(), label=f"{name} fixes")
        sn = ds["fix_sigma_north_m"].values[run, j][avail].astype(float)
        se = ds["fix_sigma_east_m"].values[run, j][avail].astype(float)
        rho = np.nan_to_num(ds["fix_corr_ne"].values[run, j][avail].astype(float))
        th = np.linspace(0, 2 * np.pi, 48)
        circle = np.vstack([np.cos(th), np.sin(th)])
        for k in range(0, len(fn), max(1, ellipse_every)):
            if not (np.isfinite(sn[k]) and np.isfinite(se[k])):
                continue
            P = np.array([[sn[k] ** 2, rho[k] * sn[k] * se[k]], [rho[k] * sn[k] * se[k], se[k] ** 2]])
            w, V = np.linalg.eigh(P)
            pts = V @ (3.0 * np.sqrt(np.maximum(w, 0.0))[:, None] * circle)  # rows: north, east (m)
            ax.plot((fe[k] + pts[1]) * scale, (fn[k] + pts[0]) * scale, color=line.get_color(), lw=0.5)
    ax.set_xlabel(f"east ({unit}) from the start")
    ax.set_ylabel(f"north ({unit}) from the start")
    # equal scales, and a box no flatter than 1:3 around the data
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    wx, wy = x1 - x0, y1 - y0
    if wy < wx / 3:
        c = 0.5 * (y0 + y1)
        ax.set_ylim(c - wx / 6, c + wx / 6)
    elif wx < wy / 3:
        c = 0.5 * (x0 + x1)
        ax.set_xlim(c - wy / 6, c + wy / 6)
    ax.set_aspect("equal")
    ax.set_title(f"Run {int(ds['run'].values[run])}: tracks, fixes and 3σ ellipses")
    ax.legend(fontsize=7, loc="best")
    ax.grid(True, alpha=0.3)
    return _save(fig, Path(path))


def study_figures(ds: Any, out_dir: str | Path, fmap: Any = None) -> list[Path]:
    """All study figures into ``out_dir``: ``track.png``, ``error_vs_time.png``, ``error_cdf.png``,
    ``free_inertial.png``. Returns their paths."""
    out = Path(out_dir)
    return [
        plot_track(ds, out / "track.png", fmap=fmap),
        plot_error_vs_time(ds, out / "error_vs_time.png"),
        plot_error_cdf(ds, out / "error_cdf.png"),
        plot_free_inertial(ds, out / "free_inertial.png"),
    ]
