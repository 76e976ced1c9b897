"""Build a matcher from a configuration dict (a scenario file's ``matcher = { kind = ..., ... }``).

``build_matcher({"kind": "pmht", "batch": 30, "candidates": 20, "iterations": 15})`` -> a :class:`PMHTMatcher`.
Keys are the matcher's constructor parameters (see each class); an unknown ``kind`` or key, or a value of the wrong
type, raises :class:`~magnav_ins.core.errors.ConfigError` naming it. Kinds:

=================  ==========================================================  ========
kind               class                                                        protocol
=================  ==========================================================  ========
``ml``             :class:`~.likelihood.LikelihoodMatcher` (method "ml")         batch
``mlr``            :class:`~.likelihood.LikelihoodMatcher` (method "mlr")        batch
``abl``            :class:`~.likelihood.LikelihoodMatcher` (method "abl")        batch
``pmht``           :class:`~.pmht.PMHTMatcher`                                   batch
``bayes_grid``     :class:`~.bayes_grid.BayesGridMatcher`                        recursive
``particle``       :class:`~.particle.ParticleFilter` (MagNavigate dynamics)     recursive
``particle_ins``   :class:`~.particle.ParticleFilter` (``dynamics="ins"``)       recursive
``tercom``         :class:`~.tercom.TercomMatcher` (Golden 1980)                 batch
``iccp``           :class:`~.iccp.ICCPMatcher` (Besl & McKay 1992)               batch
``pmf``            :class:`~.pmf.PointMassFilter` (Bergman et al. 1999)          recursive
``feature``        :class:`~.features.FeatureMatcher` (Shockley's RSS fit)       batch
=================  ==========================================================  ========

``preset`` (where a class has ``PRESETS``) fills in a named set of defaults under the given keys, e.g.
``{"kind": "pmht", "preset": "wang", "batch": 15}`` is PMHT-MM as Wang et al. publish it with T = 15.

A particle filter's ``fix_matcher`` may itself be a config dict; its ``road`` map is passed as an object
(``build_matcher(cfg, road=track_map)``), or named in the dict as ``road = "map"``: the map the matcher matches
against is also the road network (a :class:`~magnav_ins.maps.track.TrackMap`; Shockley's road penalisation,
003 sec. 5.1), handed in as ``build_matcher(cfg, fmap=the_map)`` (without ``fmap`` the key is only checked).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from ...core.errors import ConfigError
from .bayes_grid import BayesGridMatcher
from .features import FeatureMatcher
from .iccp import ICCPMatcher
from .likelihood import LikelihoodMatcher
from .particle import ParticleFilter
from .pmf import PointMassFilter
from .pmht import PMHTMatcher
from .tercom import TercomMatcher

#: kind -> (class, fixed parameters the kind implies)
KINDS: dict[str, tuple[type, dict[str, Any]]] = {
    "ml": (LikelihoodMatcher, {"method": "ml"}),
    "mlr": (LikelihoodMatcher, {"method": "mlr"}),
    "abl": (LikelihoodMatcher, {"method": "abl"}),
    "pmht": (PMHTMatcher, {}),
    "bayes_grid": (BayesGridMatcher, {}),
    "particle": (ParticleFilter, {"dynamics": "gauss_markov"}),
    "particle_ins": (ParticleFilter, {"dynamics": "ins"}),
    "tercom": (TercomMatcher, {}),
    "iccp": (ICCPMatcher, {}),
    "pmf": (PointMassFilter, {}),
    "feature": (FeatureMatcher, {}),
}

#: kinds implementing ``RecursiveMatcher`` (initiate / predict / update / to_fix) rather than ``match``.
RECURSIVE_KINDS = frozenset({"bayes_grid", "particle", "particle_ins", "pmf"})

_OBJECT_KEYS = {"road"}


def matcher_keys(kind: str) -> list[str]:
    """The configuration keys a kind accepts (besides ``kind``)."""
    cls, fixed = _lookup(kind)
    names = {f.name for f in dataclasses.fields(cls) if f.init and f.name not in fixed}
    return sorted(names)  # "road" is accepted as the string "map" (module docstring)


def _lookup(kind: object) -> tuple[type, dict[str, Any]]:
    if not isinstance(kind, str) or kind not in KINDS:
        raise ConfigError(f"matcher 'kind': unknown matcher {kind!r}; expected one of {sorted(KINDS)}")
    return KINDS[kind]


def _check_type(kind: str, key: str, default: Any, value: Any) -> Any:
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"matcher {kind!r} key '{key}': expected true/false, got {value!r}")
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"matcher {kind!r} key '{key}': expected an integer, got {value!r}")
        return value
    if isinstance(default, float) or default is None:
        if value is None and default is None:
            return None
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"matcher {kind!r} key '{key}': expected a number, got {value!r}")
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ConfigError(f"matcher {kind!r} key '{key}': expected a string, got {value!r}")
        return value
    return value


def _with_preset(kind: str, cls: type, config: Mapping[str, Any]) -> Mapping[str, Any]:
    """``config`` over the defaults of its ``preset`` (a class's ``PRESETS``, e.g. PMHT's ``"wang"``): the keys the
    user gives win over the preset's."""
    name = config.get("preset")
    if not name:
        return config
    presets = getattr(cls, "PRESETS", {})
    if name not in presets:
        raise ConfigError(f"matcher {kind!r} key 'preset': unknown preset {name!r}; expected one of {sorted(presets)}")
    return {**presets[name], **config}


def build_matcher(config: Mapping[str, Any], *, road: Any = None, fmap: Any = None) -> Any:
    """A matcher from ``config`` (must hold ``kind``); see the module docstring. ``fmap``: the map the matcher will
    match against (used only for ``road = "map"``)."""
    if not isinstance(config, Mapping):
        raise ConfigError(f"matcher: expected a table/dict with a 'kind', got {type(config).__name__}")
    if "kind" not in config:
        raise ConfigError(f"matcher: missing key 'kind'; expected one of {sorted(KINDS)}")
    kind = config["kind"]
    cls, fixed = _lookup(kind)
    config = _with_preset(kind, cls, config)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}  # not the matcher's run-time state
    kwargs: dict[str, Any] = dict(fixed)
    for key, value in config.items():
        if key == "kind":
            continue
        if key not in fields or key in fixed:
            raise ConfigError(f"matcher {kind!r}: unknown key '{key}'; expected one of {matcher_keys(kind)}")
        if key in _OBJECT_KEYS:
            if value != "map":
                raise ConfigError(
                    f"matcher {kind!r} key '{key}': expected \"map\" (the matched map is the road network), got {value!r}"
                )
            if fmap is not None:
                if not callable(getattr(fmap, "nearest", None)):
                    raise ConfigError(
                        f"matcher {kind!r} key '{key}': road = \"map\" needs a road map (a track map with points "
                        f"along roads), got {type(fmap).__name__}"
                    )
                road = fmap
            continue
        f = fields[key]
        default = f.default if f.default is not dataclasses.MISSING else None
        if key == "fix_matcher":
            if not isinstance(value, Mapping):
                raise ConfigError(f"matcher {kind!r} key 'fix_matcher': expected a matcher table, got {value!r}")
            if value.get("kind") in RECURSIVE_KINDS:
                raise ConfigError(f"matcher {kind!r} key 'fix_matcher': must be a batch matcher, got {value['kind']!r}")
            kwargs[key] = build_matcher(value)
            continue
        if value is None and "None" in str(f.type):
            kwargs[key] = None
            continue
        kwargs[key] = _check_type(kind, key, default, value)
    if road is not None:
        if "road" not in fields:
            raise ConfigError(f"matcher {kind!r}: takes no road map")
        kwargs["road"] = road
    if "name" not in kwargs:
        kwargs["name"] = kind
    return cls(**kwargs)
