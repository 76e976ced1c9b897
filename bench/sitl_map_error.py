"""The SITL world's field against the map the bridge matches: the map error model the SITL flight tells the bridge.

The world (:func:`magnav_ins.mavlink.sitl.osborne_world`: the Osborne survey gridded at 50 m from every line) minus
``builtin:osborne-magnetic`` (flight lines only, 100 m) along ``--sections`` straight sections of ``--length-m``
(readings 7.5 m apart) at random places and headings over the whole map (the flown routes play no
part), each demeaned (the bridge's matcher demeans). One JSON line: percentiles of the sections' RMS error (nT), the
error per unit map gradient (``c`` in ``sigma^2 = s0^2 + (c |grad|)^2``: median of the sections' RMS error over
their RMS gradient, and per gradient bin), the mean square of the sections' RMS normalised by that model with the
stated ``s0`` and ``c`` (1 = calibrated) and by a uniform sigma, and the pooled autocorrelation of the demeaned
error along the sections (lag m: value; the map error's correlation length is the 1/e lag).

With ``--fixes N``: instead, the fixes. N straight sections of 80 readings (0.5 s apart at ``--speed``) at random
places and headings, read from the world (+ 1 nT noise and a level offset), with the INS track off by a draw of the
prior (``--prior`` m 1-sigma per axis) and a velocity error (0.05 m/s), matched against the map by a fresh bridge
matcher (:func:`magnav_ins.mavlink.sitl_flight.sitl_matcher`, optionally changed by ``--matcher`` JSON). One JSON line:
fixes issued, the refusals by reason, the fixes' NEES (``e' C^-1 e / 2``: mean with its bootstrap 90 % interval,
median; 0.69 for a Gaussian), the share beyond the 99.9 % quantile, the median fix sigmas and error (m).

Usage: ``python bench/sitl_map_error.py [--sections 2000] [--length-m 400] [--seed 7] [--s0 0.3] [--c 6.5]``
       ``[--uniform 4]``
       ``python bench/sitl_map_error.py --fixes 400 [--seed 1] [--prior 25] [--speed 10] [--matcher JSON]``
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from magnav_ins.maps.builtin import load_map
from magnav_ins.mavlink.sitl import osborne_world, read_maganom

R_EARTH = 6378137.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sections", type=int, default=2000)
    ap.add_argument("--length-m", type=float, default=400.0)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--s0", type=float, default=0.3, help="model floor, nT")
    ap.add_argument("--c", type=float, default=6.5, help="model error per unit gradient, m")
    ap.add_argument("--uniform", type=float, default=4.0, help="a uniform sigma to compare, nT")
    ap.add_argument("--fixes", type=int, default=0, help="check N fixes of the bridge's matcher instead")
    ap.add_argument("--prior", type=float, default=25.0, help="INS prior 1-sigma per axis, m (--fixes)")
    ap.add_argument("--speed", type=float, default=10.0, help="m/s (--fixes; the SITL copter flies 10)")
    ap.add_argument("--matcher", default=None, help="JSON changes to the SITL matcher (--fixes)")
    a = ap.parse_args()
    lat0, lon0, dlat, dlon, grid = read_maganom(osborne_world())
    fmap = load_map("builtin:osborne-magnetic")

    def world(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
        fi, fj = (np.degrees(lat) - lat0) / dlat, (np.degrees(lon) - lon0) / dlon
        ok = (fi >= 0) & (fi <= grid.shape[0] - 1) & (fj >= 0) & (fj <= grid.shape[1] - 1)
        i = np.clip(fi.astype(int), 0, grid.shape[0] - 2)
        j = np.clip(fj.astype(int), 0, grid.shape[1] - 2)
        ti, tj = fi - i, fj - j
        v = (1 - ti) * ((1 - tj) * grid[i, j] + tj * grid[i, j + 1]) + ti * (
            (1 - tj) * grid[i + 1, j] + tj * grid[i + 1, j + 1]
        )
        return np.where(ok & (v != 0), v, np.nan)  # 0 = no data in the SITL's file

    rng = np.random.default_rng(a.seed)
    if a.fixes:
        print(json.dumps(check_fixes(a, fmap, world, rng)))
        return
    la_min, la_max, lo_min, lo_max = fmap.bounds_latlon
    step = 7.5
    k = int(a.length_m / step) + 1
    s = np.arange(k) * step
    rms, grad, acs = [], [], []
    lags = np.arange(0, min(k, 61), 4)
    while len(rms) < a.sections:
        la, lo, hd = rng.uniform(la_min, la_max), rng.uniform(lo_min, lo_max), rng.uniform(0, 2 * np.pi)
        lat = la + s * np.cos(hd) / R_EARTH
        lon = lo + s * np.sin(hd) / (R_EARTH * np.cos(la))
        m, w = np.asarray(fmap.value(lat, lon), float), world(lat, lon)
        if not (np.all(np.isfinite(m)) and np.all(np.isfinite(w))):
            continue
        d = (w - m) - np.mean(w - m)
        g = np.asarray(fmap.gradient_ne(lat, lon), float)
        rms.append(float(np.sqrt(np.mean(d**2))))
        grad.append(float(np.sqrt(np.mean(np.sum(g**2, axis=1)))))
        acs.append([float(np.mean(d[: k - L] * d[L:])) for L in lags])
    r, g = np.array(rms), np.array(grad)
    ratio = r / np.maximum(g, 1e-12)
    bins = [0.0, 0.05, 0.2, 0.5, 1.0, 3.0, np.inf]
    per_bin = {}
    for lo_, hi_ in zip(bins[:-1], bins[1:], strict=True):
        sel = (g >= lo_) & (g < hi_)
        if sel.any():
            per_bin[f"{lo_:g}-{hi_:g} nT/m"] = {
                "sections": int(sel.sum()),
                "rms_error_median_nt": round(float(np.median(r[sel])), 2),
                "error_per_gradient_median_m": round(float(np.median(ratio[sel])), 1),
            }
    model = np.sqrt(a.s0**2 + (a.c * g) ** 2)
    ac = np.mean(acs, axis=0)
    out = {
        "sections": len(r),
        "seed": a.seed,
        "length_m": a.length_m,
        "rms_error_pct_10_50_90_99_nt": [round(float(x), 2) for x in np.percentile(r, [10, 50, 90, 99])],
        "rms_error_pooled_nt": round(float(np.sqrt(np.mean(r**2))), 2),
        "error_per_gradient_median_m": round(float(np.median(ratio)), 2),
        "per_gradient_bin": per_bin,
        "model": {"s0_nt": a.s0, "c_m": a.c},
        "model_normalised_mean_square": round(float(np.mean((r / model) ** 2)), 2),
        "model_normalised_mean_square_by_gradient_tercile": [
            round(float(np.mean((r[q] / model[q]) ** 2)), 2) for q in np.array_split(np.argsort(g), 3)
        ],
        "uniform_normalised_mean_square_by_gradient_tercile": [
            round(float(np.mean((r[q] / a.uniform) ** 2)), 3) for q in np.array_split(np.argsort(g), 3)
        ],
        "autocorrelation": {int(L): round(float(v / ac[0]), 2) for L, v in zip(lags * step, ac, strict=True)},
    }
    print(json.dumps(out))


def check_fixes(a: argparse.Namespace, fmap, world, rng: np.random.Generator) -> dict:  # noqa: ANN001
    """The ``--fixes`` check (module docstring)."""
    from magnav_ins.aiding.matchers.registry import build_matcher
    from magnav_ins.core.protocols import MatchWindow
    from magnav_ins.core.types import FieldReadings
    from magnav_ins.mavlink.sitl_flight import sitl_matcher

    cfg = {**sitl_matcher(), **(json.loads(a.matcher) if a.matcher else {})}
    la_min, la_max, lo_min, lo_max = fmap.bounds_latlon
    k, dt, verr = 80, 0.5, 0.05
    tau = (np.arange(k) - (k - 1)) * dt  # s, last reading 0
    s = tau * a.speed
    nees, sig, err, refused = [], [], [], {}
    tried = 0
    while tried < a.fixes:
        la, lo, hd = rng.uniform(la_min, la_max), rng.uniform(lo_min, lo_max), rng.uniform(0, 2 * np.pi)
        n_t, e_t = s * np.cos(hd), s * np.sin(hd)
        coslat = np.cos(la)
        lat_t, lon_t = la + n_t / R_EARTH, lo + e_t / (R_EARTH * coslat)
        around = [fmap.value(lat_t + dn / R_EARTH, lon_t + de / (R_EARTH * coslat))
                  for dn, de in ((0, 0), (300, 0), (-300, 0), (0, 300), (0, -300))]  # fmt: skip
        w = world(lat_t, lon_t)
        if not (all(np.all(np.isfinite(np.asarray(v, float))) for v in around) and np.all(np.isfinite(w))):
            continue
        tried += 1
        z = w + rng.normal(0.0, 1.0, k) + rng.normal(0.0, 5.0)
        off = rng.normal(0.0, a.prior, 2)
        dv = rng.normal(0.0, verr, 2)
        n_i, e_i = n_t + off[0] + dv[0] * tau, e_t + off[1] + dv[1] * tau
        sd2 = np.maximum(a.prior**2 - (verr * tau) ** 2, 1.0)
        win = MatchWindow(
            FieldReadings(1000.0 + tau, z, 1.0, "total_field_anomaly_nt"), la + n_i / R_EARTH,
            lo + e_i / (R_EARTH * coslat), np.full(k, 460.0), sd2[:, None, None] * np.eye(2), np.zeros((k, 2)),
        )  # fmt: skip
        fix = build_matcher(dict(cfg)).match(win, fmap)
        if not fix.available:
            key = fix.reason.split(":")[0].split(" (")[0]
            refused[key] = refused.get(key, 0) + 1
            continue
        e = np.array([(fix.lat - lat_t[-1]) * R_EARTH, (fix.lon - lon_t[-1]) * R_EARTH * coslat])
        nees.append(float(e @ np.linalg.solve(fix.cov_ne, e)) / 2.0)
        sig.append(np.sqrt(np.linalg.eigvalsh(fix.cov_ne)))
        err.append(float(np.hypot(*e)))
    x = np.array(nees)
    boot = [float(rng.choice(x, x.size).mean()) for _ in range(500)]
    sg = np.array(sig)
    return {
        "tried": tried, "seed": a.seed, "prior_m": a.prior, "speed_mps": a.speed, "matcher": cfg,
        "fixes": int(x.size), "refused": refused,
        "fix_nees_mean": round(float(x.mean()), 2),
        "fix_nees_mean_ci90": [round(float(np.percentile(boot, q)), 2) for q in (5, 95)],
        "fix_nees_median": round(float(np.median(x)), 2),
        "beyond_999": round(float(np.mean(2 * x > 13.82)), 3),
        "sigma_major_median_m": round(float(np.median(sg[:, 1])), 1),
        "sigma_minor_median_m": round(float(np.median(sg[:, 0])), 1),
        "error_median_m": round(float(np.median(err)), 1),
    }  # fmt: skip


if __name__ == "__main__":
    main()
