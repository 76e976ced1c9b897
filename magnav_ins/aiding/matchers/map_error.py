"""The map's own prediction error as the matchers see it (DESIGN "Integrity").

A reading ``z`` at the true position ``x`` differs from the map prediction ``m(x)`` by the sensor noise *and* the
map error: ``z - m(x) = v_sensor + e_map(x)``, so every matcher's likelihood uses the variance
``sigma_sensor^2 + sigma_map(x)^2``. The map error is spatially correlated (correlation length ``ell``): readings
closer together than ``ell`` share most of their map error and are not independent evidence.

:func:`resolve_map_error` picks, in this order: a matcher's explicit ``map_sigma`` option (the user's number, kept
for old scenarios), the map's error layer (:attr:`GridMap.has_error_layer`, estimated by cross-validation when a
survey is gridded), else the stated default below for a map that does not know its error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...core.protocols import FieldMap

FloatArray = NDArray[np.float64]

#: A map without an error layer: 1-sigma map error = this fraction of the map's standard deviation ...
DEFAULT_ERROR_FRACTION_OF_STD = 0.10
#: ... with a correlation length of this many node spacings (a grid cannot resolve shorter errors).
DEFAULT_CORRELATION_NODES = 2.0


@dataclass(frozen=True)
class MapErrorModel:
    """Where the matcher's map error comes from: ``source`` is ``"option"``, ``"layer"`` or ``"default"``.

    ``uniform_sigma`` (map unit) is set for ``option`` / ``default``; for ``layer`` the sigma varies by position
    (:meth:`sigma_at`). ``correlation_m`` is the error's correlation length (m), NaN when unknown."""

    source: str
    uniform_sigma: float
    correlation_m: float
    fmap: FieldMap | None = None

    def sigma_at(self, lat: ArrayLike, lon: ArrayLike) -> FloatArray:
        """1-sigma map error (map unit) at ``(lat, lon)`` rad, shape of the broadcast inputs; off the map the
        layer's value is NaN and is replaced by the layer's largest value (the most cautious)."""
        la, lo = np.broadcast_arrays(np.asarray(lat, dtype=float), np.asarray(lon, dtype=float))
        if self.source != "layer":
            return np.full(la.shape, self.uniform_sigma)
        s = np.asarray(self.fmap.error_sigma_at(la, lo), dtype=float)  # type: ignore[union-attr]
        if np.any(~np.isfinite(s)):
            s = np.where(np.isfinite(s), s, float(np.nanmax(self.fmap.error_sigma)))  # type: ignore[union-attr]
        return s


def _default_for(fmap: FieldMap) -> tuple[float, float]:
    vals = np.asarray(getattr(fmap, "values", np.array([np.nan])), dtype=float)
    std = float(np.nanstd(vals)) if np.any(np.isfinite(vals)) else float("nan")
    spacing = getattr(fmap, "spacing_m", None)
    corr = DEFAULT_CORRELATION_NODES * float(np.mean(spacing)) if spacing is not None else float("nan")
    return DEFAULT_ERROR_FRACTION_OF_STD * std, corr


def resolve_map_error(
    fmap: FieldMap, map_sigma: float | None = None, correlation_m: float | None = None
) -> MapErrorModel:
    """The map error a matcher should use (module docstring): ``map_sigma`` (map unit, > 0) overrides the map's
    layer; ``correlation_m`` overrides the correlation length."""
    if map_sigma is not None and map_sigma > 0:
        corr = correlation_m if correlation_m is not None else getattr(fmap, "error_correlation_m", None)
        if corr is None:
            corr = _default_for(fmap)[1]
        return MapErrorModel("option", float(map_sigma), float(corr))
    if getattr(fmap, "has_error_layer", False):
        corr = correlation_m if correlation_m is not None else fmap.error_correlation_m  # type: ignore[attr-defined]
        return MapErrorModel("layer", float("nan"), float(corr), fmap)
    sig, corr = _default_for(fmap)
    return MapErrorModel("default", sig, float(correlation_m) if correlation_m is not None else corr)
