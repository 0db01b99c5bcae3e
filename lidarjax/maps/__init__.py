"""Grid maps (dissertation chs. 7-8) built from :class:`~lidarjax.raytrace.GridStats`:
maximum-likelihood decay-rate, reflection and endpoint maps, and the closed-form full map
posteriors (Beta / Gamma per cell) with their measurement likelihoods and occupancy."""

from ._grid import DecayRateMap as DecayRateMap
from ._grid import EndpointMap as EndpointMap
from ._grid import ReflectionMap as ReflectionMap
from ._grid import decay_rate_map as decay_rate_map
from ._grid import distance_transform as distance_transform
from ._grid import endpoint_map as endpoint_map
from ._grid import reflection_map as reflection_map
from ._posterior import BetaPosteriorMap as BetaPosteriorMap
from ._posterior import GammaPosteriorMap as GammaPosteriorMap
from ._posterior import beta_moment_prior as beta_moment_prior
from ._posterior import beta_posterior as beta_posterior
from ._posterior import gamma_moment_prior as gamma_moment_prior
from ._posterior import gamma_posterior as gamma_posterior
from ._posterior import log_likelihood as posterior_log_likelihood
from ._posterior import occupancy as occupancy

__all__ = [
    "DecayRateMap",
    "ReflectionMap",
    "EndpointMap",
    "decay_rate_map",
    "reflection_map",
    "endpoint_map",
    "distance_transform",
    "BetaPosteriorMap",
    "GammaPosteriorMap",
    "beta_posterior",
    "gamma_posterior",
    "beta_moment_prior",
    "gamma_moment_prior",
    "posterior_log_likelihood",
    "occupancy",
]
