"""Reflection (hit-counting) forward sensor model (dissertation Sec. 7.5.2, Eqs. 7.22,
7.23 and the density conversion Eq. 7.32).

The model's per-cell term and finish are :class:`~lidarjax.maps.ReflectionMap`'s
grid-model protocol (:class:`~lidarjax.maps.AbstractGridModel`)."""

from __future__ import annotations

from jaxtyping import Array, Float

from ..maps import ReflectionMap, grid_log_likelihood
from ..rays import RayBatch
from ._common import check_model_type


def log_likelihood(
    map: ReflectionMap, rays: RayBatch, *, max_cells: int | None = None
) -> Float[Array, "*batch"]:
    """Log-likelihood of each ray under the reflection model, Eqs. (7.23) and (7.32).

    The ray reflects in cell ``k`` with probability ``P_k = q_k prod_{i before k} (1 - q_i)``
    (Eq. 7.23). Eq. (7.32) turns this into a density by dividing by the length of the
    ray's path through ``v_k`` (its *chord*: from where the ray enters ``v_k``, or starts if
    the sensor is inside it, to where it would leave ``v_k``, not just up to the end point):
    the density is constant, ``P_k / chord_k``, inside each cell. Its CDF is therefore
    linear inside a cell, which fixes partially traversed cells:

    - HIT at range ``r`` in cell ``k``: ``log p(r) = log P_k - log chord_k``.
    - SUP: ``P(sup) = prod_{i fully before r_max} (1 - q_i) * (1 - q_k * f_k)`` with ``k``
      the cell containing ``r_max`` and ``f_k`` the fraction of its chord travelled before
      ``r_max``;
    - SUB: ``P(sub) = 1 - S(r_min)`` with the same survival ``S`` evaluated at ``r_min``.

    So HIT densities over ``[r_min, r_max)`` plus ``P(sub) + P(sup)`` integrate to 1.
    Outside the grid, space is a homogeneous medium of cells of the grid's resolution with
    reflection probability ``q_out = map.unknown_prob``: a length ``l`` outside survives
    with ``(1 - q_out)^(l / resolution)`` and a HIT there has density
    ``S(r) * (-log(1 - q_out) / resolution)`` (the continuum limit, which keeps the
    normalisation exact). NaN-free in value and gradient; ``q_k = 0`` gives ``-inf``.

    Args:
        map: the reflection map.
        rays: ``[*batch]`` rays of the map's dimension.
        max_cells: static traversal budget per ray (default never truncates).

    Returns:
        ``[*batch]`` log-likelihoods (log density in log(1/m) for HIT, log probability for
        SUB/SUP).

    Raises:
        ValueError: wrong map type, rays not a RayBatch, or mismatching dimensions.
    """
    check_model_type(map, ReflectionMap)
    return grid_log_likelihood(map, rays, max_cells=max_cells)
