"""Chi-square gates for innovations (generic: any dimension, any test probability).

A residual ``r`` (m) with predicted covariance ``S`` (m^2) has normalised innovation squared
``nis = r^T S^-1 r``, chi-square distributed with ``dim(r)`` degrees of freedom when the model is right
(Bar-Shalom, Li & Kirubarajan 2001, sec. 5.4.2 and eq. 5.4.2-6). A gate with probability ``P_G`` accepts
``nis <= chi2.ppf(P_G, dof)``. Used by the fusers (2-dof position fixes) and available to the matchers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.special import gammaincinv

from ..core.errors import ConfigError


def chi2_threshold(dof: int, probability: float) -> float:
    """The ``probability`` quantile of a chi-square with ``dof`` degrees of freedom."""
    if not (0.0 < probability < 1.0):
        raise ConfigError(f"gate probability must be in (0, 1), got {probability}")
    if dof < 1:
        raise ConfigError(f"gate degrees of freedom must be >= 1, got {dof}")
    return float(2.0 * gammaincinv(dof / 2.0, probability))  # scipy.stats.chi2.ppf's own formula, bit for bit


def nis(residual: ArrayLike, S: ArrayLike) -> float:
    """Normalised innovation squared ``r^T S^-1 r`` (solved, not inverted); ``inf`` when ``S`` is singular."""
    r = np.asarray(residual, dtype=float).reshape(-1)
    S = np.asarray(S, dtype=float)
    try:
        return float(r @ np.linalg.solve(S, r))
    except np.linalg.LinAlgError:
        return float("inf")


@dataclass(frozen=True)
class ChiSquareGate:
    """Accept a residual when its NIS is inside the ``probability`` chi-square quantile for ``dof`` dof;
    ``probability=None`` is no gate (every finite NIS passes)."""

    probability: float | None = 0.999
    dof: int = 2

    @property
    def threshold(self) -> float:
        return float("inf") if self.probability is None else chi2_threshold(self.dof, self.probability)

    def accepts(self, nis_value: float) -> bool:
        """True when ``nis_value`` is finite and at most the threshold."""
        return bool(np.isfinite(nis_value) and nis_value <= self.threshold)


def consistency_band(dof: int, n: int, probability: float = 0.95) -> tuple[float, float]:
    """Two-sided ``probability`` band for the MEAN of ``n`` independent chi-square(``dof``) values
    (Bar-Shalom et al. 2001 eq. 5.4.2-8): ``chi2.ppf((1 -+ p)/2, n dof) / n``."""
    from scipy.stats import chi2  # here: scipy.stats costs ~30 MB to import, the fusers need only the quantile

    a = (1.0 - probability) / 2.0
    return float(chi2.ppf(a, n * dof) / n), float(chi2.ppf(1.0 - a, n * dof) / n)
