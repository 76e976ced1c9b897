"""Map matchers: a window of field readings (or a recursive state) -> a position :class:`~magnav_ins.core.types.Fix`.

* :mod:`.likelihood` - ML, MLR, ABL (Shockley 2012, seed 003, sec. 4.3; Raquet et al., seed 000, eq. 1)
* :mod:`.pmht` - PMHT-MM (Wang et al. 2022, seed 001, sec. 3)
* :mod:`.bayes_grid` - Storms' Bayes grid matcher (seed 004, sec. 3.4)
* :mod:`.particle` - MagNavigate and INS-driven particle filters (seed 003 ch. V)
* :mod:`.features` - Shockley's feature matching with an RSS fit on road maps (seed 003 sec. 4.6.3)
* :mod:`.metrics` - availability, fix error bins, fix NEES
* :mod:`.registry` - ``build_matcher(config_dict)``

Every matcher returns a :class:`Fix` ("no fix" with a reason for data problems, never an exception).
"""

from .bayes_grid import BayesGridMatcher, BayesGridState
from .features import FeatureMatcher
from .likelihood import ABL, ML, MLR, LikelihoodMatcher
from .particle import ParticleFilter, ParticleState
from .pmht import PMHTMatcher
from .registry import KINDS, RECURSIVE_KINDS, build_matcher, matcher_keys

__all__ = [
    "ABL",
    "KINDS",
    "ML",
    "MLR",
    "RECURSIVE_KINDS",
    "BayesGridMatcher",
    "BayesGridState",
    "FeatureMatcher",
    "LikelihoodMatcher",
    "PMHTMatcher",
    "ParticleFilter",
    "ParticleState",
    "build_matcher",
    "matcher_keys",
]
