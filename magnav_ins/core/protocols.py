"""The seams where algorithms plug in. Each is a small :class:`typing.Protocol`; implementations do not inherit.

* :class:`FieldMap` - a geophysical map (``maps.grid.GridMap``, ``maps.track.TrackMap``).
* :class:`MapMatcher` - batch matchers (ML, MLR, ABL, PMHT-MM): a window of readings -> one :class:`Fix`.
* :class:`RecursiveMatcher` - matchers with explicit state (Bayes grid, particle filter).
* :class:`Fuser` - fusion back ends (UKF, factor graph, free inertial).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .types import FieldKind, FieldReadings, Fix, ImuBatch, Innovation, NavEstimate


@runtime_checkable
class FieldMap(Protocol):
    """A map of a scalar or 3-component field. Positions in rad / m ellipsoidal; values in ``kind``'s unit."""

    kind: FieldKind

    def value(self, lat: ArrayLike, lon: ArrayLike, h: ArrayLike | None = None) -> NDArray[np.float64]:
        """Field at the points; NaN off the map. Shape ``(N,)`` or ``(N, 3)``."""
        ...

    def gradient_ne(self, lat: ArrayLike, lon: ArrayLike, h: ArrayLike | None = None) -> NDArray[np.float64]:
        """Horizontal gradient (d/dnorth, d/deast) in unit per metre, shape ``(N, 2)`` or ``(N, 3, 2)``."""
        ...

    def covers(self, lat: ArrayLike, lon: ArrayLike) -> NDArray[np.bool_]:
        """True where the map has a finite value."""
        ...


@dataclass(frozen=True)
class MatchWindow:
    """What a batch matcher sees: readings and the INS-predicted track at the reading times.

    ``lat``, ``lon`` (N,) rad and ``h`` (N,) m are the INS-indicated positions at ``readings.t``;
    ``cov_ne`` (N,2,2) m^2 their horizontal covariance (from the fuser); ``v_ne`` (N,2) m/s the INS velocity.
    """

    readings: FieldReadings
    lat: NDArray[np.float64]
    lon: NDArray[np.float64]
    h: NDArray[np.float64]
    cov_ne: NDArray[np.float64]
    v_ne: NDArray[np.float64]


class MapMatcher(Protocol):
    """Batch matcher: returns a fix at the time of the window's last reading (or a "no fix")."""

    name: str

    def match(self, window: MatchWindow, fmap: FieldMap) -> Fix: ...


class RecursiveMatcher(Protocol):
    """Matcher with explicit state: ``initiate`` from a prior, ``predict`` with the INS motion,
    ``update`` with a reading, ``to_fix`` to report the current position as a :class:`Fix`."""

    name: str

    def initiate(self, prior: NavEstimate, rng: np.random.Generator) -> Any: ...

    def predict(self, state: Any, prior: NavEstimate) -> Any: ...

    def update(self, state: Any, readings: FieldReadings, fmap: FieldMap) -> Any: ...

    def to_fix(self, state: Any) -> Fix: ...


class Fuser(Protocol):
    """Fusion back end: propagates with IMU samples, corrects with fixes."""

    name: str

    def propagate(self, imu: ImuBatch) -> None: ...

    def correct(self, fix: Fix) -> Innovation: ...

    def estimate(self) -> NavEstimate: ...
