"""Shockley's feature matching with a root-sum-squared fit (Shockley 2012, seed 003, sec. 4.6.3).

A magnetic *feature* is a deviation from the otherwise slowly changing field along a road (an underground pipe, a
bridge: 003 Fig. 4.4). Features are found the same way in the readings and in a road map
(:class:`~magnav_ins.maps.track.TrackMap`), both distance sampled at the map's step:

* the background is the running median of the samples over ``background_m`` metres; the deviation of a sample is
  its distance from the background (Euclidean over the field's components) in reading sigmas;
* a feature is a maximal run of samples whose deviation exceeds ``threshold_sigma``, at least ``min_length_m``
  long; its *defining peak* is its sample of largest deviation (a high or a low).

Matching (sec. 4.6.3): the observed feature of the section (the strongest one wholly inside it) is compared with
every map feature of the road map read in a direction of travel within ``heading_tolerance_deg`` (45 deg) of the
section's own (from its INS track: a feature of a navigation-frame map read the other way is its mirror image, and a
symmetric bump would match both ways), in both directions along each road: the two defining peaks are
aligned, and the comparison runs over the samples both features hold about the aligned peak ("the shorter of the two
becomes the length for comparison"). The fit is the root-sum-squared residual

    RSS = sqrt( sum_k || z_k - m_k ||^2 )

over those samples and the field's components (after ``demean`` or ``difference`` of both, as the likelihood
matchers compose sections, 003 sec. 4.6). The best fit is the map feature of smallest RSS *per compared sample*
(features differ in length); with equal sigmas this is the maximum likelihood feature. The RSS can be thresholded,
which the likelihood cannot (sec. 4.6.3): ``rss_threshold`` (in reading sigmas, per sample and component: the RMS
residual ``RSS / sqrt(n c)``) gives "no fix" when even the best feature fits worse, the availability-for-accuracy
trade. ``rss_threshold = None`` always reports the best feature (the ML pick).

The fix is the map point aligned with the section's last reading (the aligned peak plus the samples read since the
observed peak, along the feature's road in its direction of travel). Its covariance: the alignment is to the
nearest sample and the observed peak may sit one sample off the map's, so ``sigma = step`` per axis, plus
``min_fix_sigma_m`` in quadrature. It does not contain the chance that the best feature is the wrong one: the
threshold is the control for that (the fix NEES of the bench says how often it fails).

"No fix" (with the reason) when the map is not a road map, the readings hold no complete feature, the map has no
feature, or the best RSS is above the threshold.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from ...core.errors import ConfigError
from ...core.protocols import FieldMap, MatchWindow
from ...core.types import Fix
from ._local import make_frame

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Feature:
    """One feature on a sampled profile: samples ``start`` .. ``stop - 1`` and the defining ``peak`` (indices into
    the profile); ``road`` and ``direction`` (0 forward, 1 reversed) for a map feature (-1 for an observed one)."""

    start: int
    stop: int
    peak: int
    road: int = -1
    direction: int = -1


def deviation(values: FloatArray, step_m: float, background_m: float, sigma: float) -> FloatArray:
    """Per sample of ``values`` (n, c) sampled every ``step_m`` metres: the distance from the running median over
    ``background_m`` metres (Euclidean over the components), in units of ``sigma``."""
    v = np.asarray(values, float).reshape(len(values), -1)
    size = max(3, int(round(background_m / step_m)) | 1)  # odd window in samples
    bg = np.column_stack([ndimage.median_filter(v[:, j], size=size, mode="nearest") for j in range(v.shape[1])])
    return np.sqrt(np.sum((v - bg) ** 2, axis=1)) / float(sigma)


def find_features(dev: FloatArray, threshold: float, min_samples: int) -> list[Feature]:
    """The maximal runs of ``dev > threshold`` at least ``min_samples`` long, each with its peak (largest ``dev``)."""
    above = np.asarray(dev) > threshold
    lab, n = ndimage.label(above)
    out = []
    for k in range(1, n + 1):
        idx = np.flatnonzero(lab == k)
        if idx.size >= min_samples:
            out.append(Feature(int(idx[0]), int(idx[-1]) + 1, int(idx[np.argmax(dev[idx])])))
    return out


def rss_fit(z: FloatArray, obs: Feature, m: FloatArray, feat: Feature, compose: str = "raw") -> tuple[float, int]:
    """RSS of the observed feature ``obs`` of the profile ``z`` (n, c) against the map feature ``feat`` of the
    profile ``m`` (N, c), peaks aligned, over the samples both features hold (module docstring). Returns (RSS, the
    number of compared samples x components)."""
    before = min(obs.peak - obs.start, feat.peak - feat.start)
    after = min(obs.stop - obs.peak, feat.stop - feat.peak)
    a = np.asarray(z, float).reshape(len(z), -1)[obs.peak - before : obs.peak + after]
    b = np.asarray(m, float).reshape(len(m), -1)[feat.peak - before : feat.peak + after]
    if compose == "demean":
        a, b = a - a.mean(axis=0), b - b.mean(axis=0)
    elif compose == "difference":
        a, b = np.diff(a, axis=0), np.diff(b, axis=0)
    return float(np.sqrt(np.sum((a - b) ** 2))), int(a.size)


@dataclass
class FeatureMatcher:
    """Feature matching with an RSS fit on a road map (module docstring). Batch: :meth:`match`.

    Parameters: ``threshold_sigma`` feature detection (deviation from the background in reading sigmas);
    ``background_m`` running-median window (m); ``min_length_m`` shortest feature (m); ``rss_threshold`` largest
    accepted RMS residual per sample and component, in reading sigmas (None: always the best feature);
    ``compose`` "raw" | "demean" | "difference"; ``min_fix_sigma_m`` added to the fix 1-sigma;
    ``heading_tolerance_deg`` candidates by direction of travel."""

    threshold_sigma: float = 4.0
    background_m: float = 30.0
    min_length_m: float = 2.0
    rss_threshold: float | None = None
    compose: str = "raw"
    min_fix_sigma_m: float = 0.0
    heading_tolerance_deg: float = 45.0
    name: str = "feature_rss"
    _cache: dict[Any, Any] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.compose not in ("raw", "demean", "difference"):
            raise ConfigError(f"feature 'compose': expected 'raw', 'demean' or 'difference', got {self.compose!r}")
        for key in ("threshold_sigma", "background_m"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"feature '{key}': expected > 0, got {getattr(self, key)!r}")
        if self.rss_threshold is not None and not self.rss_threshold > 0:
            raise ConfigError(f"feature 'rss_threshold': expected > 0 or unset, got {self.rss_threshold!r}")

    def map_features(self, track: Any, sigma: float) -> tuple[list[Feature], list[FloatArray], list[FloatArray]]:
        """The features of every road of ``track`` in both directions of travel: the features, and per (road,
        direction) its profile (values) and its point indices into the map, in travel order."""
        key = (id(track), float(sigma))
        hit = self._cache.get(key)
        if hit is not None and hit[0] is track:
            return hit[1]
        step = _step(track)
        feats: list[Feature] = []
        profiles: list[FloatArray] = []
        points: list[FloatArray] = []
        vals = np.asarray(track.values, float).reshape(len(track), -1)
        for s in range(track.n_segments):
            idx = np.arange(len(track))[track.segment(s)]
            for direction, order in ((0, idx), (1, idx[::-1])):
                prof = vals[order]
                dev = deviation(prof, step, self.background_m, sigma)
                k = len(profiles)
                for f in find_features(dev, self.threshold_sigma, _min_samples(self.min_length_m, step)):
                    feats.append(Feature(f.start, f.stop, f.peak, k, direction))
                profiles.append(prof)
                points.append(order)
        self._cache[key] = (track, (feats, profiles, points))
        return feats, profiles, points

    def match_profile(
        self, z: FloatArray, track: Any, sigma: float, heading: float | None = None
    ) -> tuple[int, Feature | None, float, str]:
        """The best map feature for the readings ``z`` (n, c) sampled at the map's step, in travel order: returns
        (map point index of the last reading, the map feature, RMS residual per sample in sigmas, "" or the reason
        of a "no fix"). With the travel ``heading`` (rad from north) only map features read in a direction of
        travel within ``heading_tolerance_deg`` of it are candidates."""
        step = _step(track)
        z = np.asarray(z, float).reshape(len(z), -1)
        dev = deviation(z, step, self.background_m, sigma)
        obs = [
            f
            for f in find_features(dev, self.threshold_sigma, _min_samples(self.min_length_m, step))
            if f.start > 0 and f.stop < len(z)  # wholly inside the section
        ]
        if not obs:
            return -1, None, np.nan, "no feature: no complete feature in the readings"
        o = max(obs, key=lambda f: dev[f.peak])
        feats, profiles, points = self.map_features(track, sigma)
        if not feats:
            return -1, None, np.nan, "no feature: the map holds no feature"
        best, best_rms = None, np.inf
        cos_tol = np.cos(np.radians(self.heading_tolerance_deg))
        for f in feats:
            if heading is not None:
                h_map = float(track.heading[points[f.road][f.peak]]) + (np.pi if f.direction else 0.0)
                if np.cos(h_map - heading) < cos_tol:
                    continue
            rss, n = rss_fit(z, o, profiles[f.road], f, self.compose)
            rms = rss / np.sqrt(max(n, 1)) / float(sigma)
            if rms < best_rms:
                best, best_rms = f, rms
        if best is None:
            return -1, None, np.nan, "no feature: no map feature read in this direction of travel"
        if self.rss_threshold is not None and best_rms > self.rss_threshold:
            return (
                -1,
                best,
                best_rms,
                (f"no feature fits: best RMS residual {best_rms:.2f} sigma above {self.rss_threshold:g}"),
            )
        j = best.peak + (len(z) - 1 - o.peak)
        order = points[best.road]
        if not 0 <= j < len(order):
            return -1, best, best_rms, "no fix: the matched feature's road ends before the last reading"
        return int(order[j]), best, best_rms, ""

    def match(self, window: MatchWindow, fmap: FieldMap) -> Fix:
        """A fix for the window's last reading (module docstring); the readings are distance sampled at the map's
        step along their INS-indicated track first."""
        from .likelihood import distance_sample

        rd = window.readings
        t = float(rd.t[-1])
        if not callable(getattr(fmap, "nearest", None)):
            return Fix.no_fix(t, "feature matching needs a road map (a track map)", self.name)
        z = np.asarray(rd.value, float).reshape(len(rd), -1)
        if not np.all(np.isfinite(z)):
            return Fix.no_fix(t, "reading is NaN", self.name)
        frame = make_frame(fmap, float(window.lat[-1]), float(window.lon[-1]))
        dn, de = frame.to_ne(np.asarray(window.lat), np.asarray(window.lon))
        _, _, zs = distance_sample(dn, de, z, _step(fmap))
        moved = np.hypot(dn[-1] - dn[0], de[-1] - de[0])
        heading = float(np.arctan2(de[-1] - de[0], dn[-1] - dn[0])) if moved > _step(fmap) else None
        k, _, rms, why = self.match_profile(zs, fmap, float(rd.sigma), heading)
        if why:
            return Fix.no_fix(t, why, self.name, rms)
        sig2 = _step(fmap) ** 2 + self.min_fix_sigma_m**2
        return Fix(t, float(fmap.lat[k]), float(fmap.lon[k]), np.eye(2) * sig2, True, "", rms, self.name)


def _step(track: Any) -> float:
    step = (getattr(track, "metadata", {}) or {}).get("step_m")
    if step:
        return float(step)
    d = np.hypot(np.diff(track.northing), np.diff(track.easting))
    d = d[d > 0]
    return float(np.median(d)) if d.size else 1.0


def _min_samples(length_m: float, step_m: float) -> int:
    return max(1, int(np.ceil(length_m / step_m - 1e-9)))
