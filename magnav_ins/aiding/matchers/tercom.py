"""TERCOM: batch profile correlation over a grid of offsets (Baker & Clem 1977, "Terrain contour matching (TERCOM)
primer", ASD-TR-77-61; Golden 1980, "Terrain contour matching (TERCOM): a cruise missile guidance aid", Proc. SPIE
238, 10-18).

The field profile measured along the INS-indicated track of a batch (the last ``batch`` readings, positions
``x_t``) is compared with the map profile along the same track translated rigidly by an offset ``d`` on a regular
grid covering the gate (``gate_sigma`` prior sigmas of the last reading): the criterion is Golden's mean absolute
difference ``MAD(d) = mean_t |z_t - m(x_t + d)| / s_t`` (``criterion="mad"``) or the mean squared difference
``MSD(d) = mean_t (z_t - m(x_t + d))^2 / s_t^2`` (``"msd"``). The offset with the smallest criterion is the fix
(at the last reading: ``x_T + d*``). TERCOM is translation-only: it assumes the INS track's shape is right over the
batch.

Fix covariance (ours; TERCOM reports none): the second moment about ``d*`` of the Gaussian batch likelihood of the
offset over the grid (a flat prior over the gate), ``p(d) ~ prod_t N(z_t; m(x_t + d), v_t)`` with
``v_t = s_t^2 + |grad m|_t^2 (D_n^2 + D_e^2) / 12 + u_t`` (the offset cell through the local gradient at ``d*``),
plus ``D^2 / 12`` per axis for the grid quantisation, plus the second moment about ``d*`` of the likelihood's
rival peaks in the gate (:func:`._batch.rival_moment`, as ICCP's ``rival_cover``; ``cover_rivals``). ``s_t^2`` is
the sensor variance plus the map's error (:mod:`._batch`). ``u_t`` is the misfit the INS drift of scan ``t``
relative to the last one (``r_t``, 1 sigma) makes on a rigid match: through the map's variogram, counted as often
as the field correlates along the track (:func:`._batch.drift_misfit_variance`; ``variogram_drift``), or
``|grad m|_t^2 r_t^2`` on a map that is not a grid. Why (issue 16, QLD West, tactical IMU, 10 runs): with the
drift through the local gradient at ``d*`` run 4 lost lock. The INS track deforms by 2-10 km within a 30-reading
batch (3-11 km in the first half hour) on a 0.9 km map; where ``d*`` lay on a smooth patch its small gradient
allowed the early readings little drift, the truth's rigid offset misfit by the deformation, and fixes sat on
wrong minima with small sigmas (t = 900 s: the truth's peak 19 log-likelihood units below the best, the fix 8.9 km
off with a 3.3 km sigma). Fused, they pulled the filter's velocity 80-160 m/s off, the track then deformed by 30-60 km within a batch, the truth left
the gate and the track the map ("off the map"): fix NEES mean 101 (median 2.6), filter NEES 24.5, run 4 flagged
by Wang's rule. With the variogram allowance (same 10 runs): fix NEES 1.4 / 0.9, filter NEES 2.5, no run
diverged, 27.9 km mean (was 35.6); replaying the batches of three runs, NEES 21 -> 1.6 where the truth lay in the
gate (the rival cover adds little there). Precision IMU, first 10 runs: 553 m mean (666), fix NEES 1.3 (532: run
9 lost lock), filter NEES 1.7 (204); Gulf of Alaska, 4 runs: 999 m (734), fix NEES 1.15 (2.1): more cautious
where the drift is small (the allowance takes the growth of the position variance as the drift, an upper bound;
the sigmas' difference, a lower one, made 1 of 10 tactical runs diverge).

No fix ("diverged") when the readings disagree with the map at ``d*``: their mean ``(z - m)^2 / v`` per reading
above ``max_chi2`` or, with ``misfit_alpha`` set, above the chi-square test's threshold ``chi2_{1-alpha}(n) / n``
(``n`` the good readings; 1.99 for 30 readings at ``alpha = 1e-3``). The test is off by default (issue 16,
measured before the variogram allowance): on QLD West, precision IMU, run 9 of 20 lost lock once its filter had
drifted out of the gate and issued 35 fixes with a mean NEES of 6,094 (2-8 km off with 15-900 m sigmas, misfit
1.3-8.6 per reading, most above 2, where a run in lock had 0.3-1.5); with ``misfit_alpha = 1e-3`` 15 fixes with a
mean NEES of 51. But with the tactical IMU (10 runs) it issued 89 % of the fixes (97 % without) and 2 runs
diverged (none without). "Flat map" only when the fix adds no information over the prior beyond the offset grid's
own (:func:`._batch.adds_information`); "off the map" when no offset has map values for every good reading.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...core.errors import ConfigError
from ...core.protocols import FieldMap, MatchWindow
from ...core.types import Fix
from ._batch import (
    adds_information,
    drift_misfit_variance,
    information_refusal,
    local_gradient2,
    misfit_threshold,
    offset_grid,
    rival_moment,
    track_window,
)
from ._local import spacing_of


@dataclass
class TercomMatcher:
    """TERCOM batch matcher (module docstring). ``batch`` readings per profile; ``criterion`` "mad" | "msd";
    ``gate_sigma`` gate half-width in prior sigmas (at least ``window_floor_m`` m); ``step_m`` offset grid spacing
    (default a quarter of the map's node spacing, at most a twentieth of the gate), coarsened to at most
    ``max_offsets`` offsets; ``map_sigma`` / ``correlation_m`` override the map's error (``map_error``);
    ``max_chi2`` the misfit above which the fix is "diverged", and ``misfit_alpha`` (None: off) the false-alarm rate
    of a chi-square test of the misfit that refuses it too; ``variogram_drift`` the INS drift's misfit through the
    map's variogram (else the local gradient); ``cover_rivals`` the rival peaks' moment in the covariance."""

    batch: int = 30
    criterion: str = "mad"
    gate_sigma: float = 4.0
    window_floor_m: float = 10.0
    step_m: float | None = None
    max_offsets: int = 40_000
    map_sigma: float | None = None
    correlation_m: float | None = None
    max_chi2: float = 9.0
    misfit_alpha: float | None = None
    variogram_drift: bool = True
    cover_rivals: bool = True
    name: str = "tercom"

    def __post_init__(self) -> None:
        if not (isinstance(self.batch, int) and self.batch >= 2):
            raise ConfigError(f"tercom 'batch': expected an integer >= 2, got {self.batch!r}")
        if self.criterion not in ("mad", "msd"):
            raise ConfigError(f"tercom 'criterion': expected 'mad' or 'msd', got {self.criterion!r}")
        for key in ("gate_sigma", "max_chi2"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"tercom '{key}': expected > 0, got {getattr(self, key)!r}")
        if self.misfit_alpha is not None and not 0 < self.misfit_alpha < 1:
            raise ConfigError(f"tercom 'misfit_alpha': expected 0 < misfit_alpha < 1, got {self.misfit_alpha!r}")
        if self.max_offsets < 9:
            raise ConfigError(f"tercom 'max_offsets': expected >= 9, got {self.max_offsets!r}")

    def match(self, window: MatchWindow, fmap: FieldMap) -> Fix:
        """One fix at the window's last reading (or a "no fix" with the reason)."""
        t_last = float(window.readings.t[-1]) if len(window.readings) else float("nan")
        try:
            return self._match(window, fmap, t_last)
        except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
            return Fix.no_fix(t_last, f"TERCOM failed on the data: {exc}", self.name)

    def _match(self, window: MatchWindow, fmap: FieldMap, t_last: float) -> Fix:
        tw = track_window(window, fmap, self.batch, self.gate_sigma, self.window_floor_m, self.map_sigma,
                          self.correlation_m)  # fmt: skip
        if isinstance(tw, str):
            return Fix.no_fix(t_last, tw, self.name)
        hn, he = float(tw.half[-1, 0]), float(tw.half[-1, 1])
        step = self.step_m or min(0.25 * spacing_of(fmap, min(hn, he) / 10.0), min(hn, he) / 20.0)
        on, oe, Dn, De = offset_grid(hn, he, step, self.max_offsets)
        idx = np.flatnonzero(tw.good)
        K = on.size
        resid = np.empty((idx.size, K))
        for r, t in enumerate(idx):
            m = tw.frame.sample(tw.x_ins[t, 0] + on, tw.x_ins[t, 1] + oe).reshape(K, -1)
            resid[r] = np.sqrt(np.sum((m - tw.z[t]) ** 2, axis=1))  # |z - m| (norm over components)
        finite = np.all(np.isfinite(resid), axis=0)
        if not np.any(finite):
            return Fix.no_fix(t_last, "off the map: no offset in the gate has map values along the track", self.name)
        s = np.sqrt(tw.s2[idx])[:, None]
        crit = np.mean(resid / s, axis=0) if self.criterion == "mad" else np.mean((resid / s) ** 2, axis=0)
        crit = np.where(finite, crit, np.inf)
        k = int(np.argmin(crit))
        d = np.array([on[k], oe[k]])
        # likelihood of the offset: variance with the offset cell and the INS drift through the local gradient
        g2 = local_gradient2(tw.frame, tw.x_ins[idx, 0] + d[0], tw.x_ins[idx, 1] + d[1], max(0.5 * min(Dn, De), 0.5))
        drift = drift_misfit_variance(fmap, tw.x_ins[idx], tw.rel_drift[idx]) if self.variogram_drift else None
        if drift is None:  # not a grid (or switched off): the drift through the local gradient
            drift = g2 * tw.rel_drift[idx] ** 2
        v = tw.s2[idx] + g2 * (Dn**2 + De**2) / 12.0 + drift
        ll = np.where(finite, -0.5 * np.sum(resid**2 / v[:, None], axis=0), -np.inf)
        p = np.exp(ll - np.max(ll))
        p /= p.sum()
        a = np.column_stack([on - d[0], oe - d[1]])
        C = np.einsum("k,ki,kj->ij", p, a, a) + np.diag([Dn**2, De**2]) / 12.0
        if self.cover_rivals:  # the profile fits elsewhere in the gate too: C covers those minima
            sep = max(3.0 * float(np.sqrt(np.max(np.linalg.eigvalsh(C)))), 4.0 * max(Dn, De))
            C = C + rival_moment(ll, a[:, 0], a[:, 1], (Dn, De), sep)[0]
        chi2 = float(np.mean(resid[:, k] ** 2 / v))
        prior = tw.cov[-1]
        if not adds_information(C, prior, (hn, he)):  # C holds the offset grid's own (uniform) information
            return information_refusal(t_last, C, prior, self.name, chi2, (hn, he))
        limit = self.max_chi2
        if self.misfit_alpha is not None:
            limit = min(limit, misfit_threshold(idx.size, self.misfit_alpha))
        if chi2 > limit:
            return Fix.no_fix(
                t_last,
                f"diverged: readings disagree with the map at the best offset (chi2 per reading {chi2:.3g} above "
                f"{limit:.3g})",
                self.name,
                chi2,
            )
        x = tw.x_ins[-1] + d
        lat, lon = tw.frame.to_latlon(x[0], x[1])
        return Fix(float(tw.t[-1]), float(lat), float(lon), 0.5 * (C + C.T), True, "", chi2, self.name)
