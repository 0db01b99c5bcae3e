"""Forward sensor models on grid maps (dissertation ch. 7): pure, jit-compiled
``log_likelihood(map, rays) -> [*batch]`` functions and pose-batched scan evaluation.

- :func:`decay_rate_log_likelihood`: Eqs. (7.13), (7.16).
- :func:`reflection_log_likelihood`: Eqs. (7.23), (7.32).
- :func:`endpoint_log_likelihood`: likelihood field, normalised per ray (below Eq. 7.32);
  :func:`likelihood_field_log_likelihood`: the classic unnormalised likelihood field.
- :class:`AbstractGridModel` (defined in :mod:`lidarjax.maps` beside the maps that
  implement it): the one protocol of every grid model (walk, per-cell term, finish);
  :func:`grid_log_likelihood` evaluates any of them differentiably.
- :func:`posterior_log_likelihood`: full map posteriors, Eq. (8.22) and its decay-rate
  analogue (implemented in :mod:`lidarjax.maps`).
- :func:`dct_log_likelihood`: DCT maps, Eqs. (9.5), (9.9)-(9.12) (in :mod:`lidarjax.maps`).
- :func:`log_likelihood_at_poses` / :func:`ray_log_likelihoods_at_poses`: one 2-D scan at
  many poses.
- :func:`batch_log_likelihood`: any of the grid models above, forward only, with work
  proportional to the cells the rays visit (particle filters).
"""

from ..maps import AbstractGridModel as AbstractGridModel
from ..maps import GridWalk as GridWalk
from ..maps import dct_log_likelihood as dct_log_likelihood
from ..maps import grid_log_likelihood as grid_log_likelihood
from ..maps import posterior_log_likelihood as posterior_log_likelihood
from ._common import log_likelihood_at_poses as log_likelihood_at_poses
from ._common import ray_log_likelihoods_at_poses as ray_log_likelihoods_at_poses
from ._decay_rate import log_likelihood as decay_rate_log_likelihood
from ._endpoint import likelihood_field_log_likelihood as likelihood_field_log_likelihood
from ._endpoint import log_likelihood as endpoint_log_likelihood
from ._fast import batch_log_likelihood as batch_log_likelihood
from ._reflection import log_likelihood as reflection_log_likelihood
from ._sharded import log_likelihood_at_poses_sharded as log_likelihood_at_poses_sharded

__all__ = [
    "log_likelihood_at_poses_sharded",
    "AbstractGridModel",
    "GridWalk",
    "grid_log_likelihood",
    "likelihood_field_log_likelihood",
    "decay_rate_log_likelihood",
    "reflection_log_likelihood",
    "endpoint_log_likelihood",
    "posterior_log_likelihood",
    "dct_log_likelihood",
    "log_likelihood_at_poses",
    "ray_log_likelihoods_at_poses",
    "batch_log_likelihood",
]
