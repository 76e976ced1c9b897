"""Fusion back ends behind :class:`magnav_ins.core.protocols.Fuser`: a UKF (filterpy), a factor graph (GTSAM,
iSAM2 + batch LM) and a free-inertial baseline. :func:`make_fuser` builds one by name without importing the
other back ends' libraries."""

from __future__ import annotations

from ...core.errors import ConfigError
from ...core.types import NavEstimate
from .common import ImuNoise, LocalFrame

FUSER_KINDS = ("ukf", "graph", "free_inertial")


def make_fuser(kind: str, init: NavEstimate, noise: ImuNoise, **options):
    """A fuser of ``kind`` ("ukf", "graph" or "free_inertial") starting from ``init`` with IMU ``noise``;
    ``options`` go to its constructor (a :class:`ConfigError` names an unknown kind)."""
    if kind == "ukf":
        from .ukf import UkfFuser

        return UkfFuser(init, noise, **options)
    if kind == "graph":
        from .graph import GraphFuser

        return GraphFuser(init, noise, **options)
    if kind == "free_inertial":
        from .free_inertial import FreeInertial

        return FreeInertial(init, noise, **options)
    raise ConfigError(f"unknown fusion kind {kind!r}; expected one of {', '.join(FUSER_KINDS)}")


__all__ = ["FUSER_KINDS", "ImuNoise", "LocalFrame", "make_fuser"]
