"""Decay-rate forward sensor model (dissertation Sec. 7.3, Eqs. 7.11-7.16).

The model's per-cell term and finish are :class:`~lidarjax.maps.DecayRateMap`'s
grid-model protocol (:class:`~lidarjax.maps.AbstractGridModel`)."""

from __future__ import annotations

from jaxtyping import Array, Float

from ..maps import DecayRateMap, grid_log_likelihood
from ..rays import RayBatch
from ._common import check_model_type


def log_likelihood(
    map: DecayRateMap, rays: RayBatch, *, max_cells: int | None = None
) -> Float[Array, "*batch"]:
    """Log-likelihood of each ray under the decay-rate model, Eqs. (7.13) and (7.16).

    With the optical depth ``Lambda(r) = int_0^r lambda(x(r')) dr' = sum_i lambda_i d_i``
    (exact per-cell lengths ``d_i`` from :func:`lidarjax.raytrace.traverse`; the parts of
    the ray outside the grid use ``map.outside_rate``):

    - HIT at range ``r``: ``log p(r) = log lambda_k - Lambda(r)`` (Eq. 7.13), a density in
      1/m. ``k`` is the cell containing the end point (the last cell the ray traverses);
      ``lambda_k = map.outside_rate`` if the end point lies outside the grid.
      ``lambda_k = 0`` gives ``-inf``.
    - SUB: ``log P(sub) = log(1 - exp(-Lambda(r_min)))`` (Eq. 7.16), computed stably.
    - SUP: ``log P(sup) = -Lambda(r_max)`` (Eq. 7.16); ``-inf`` for ``r_max = inf`` unless
      the outside rate is 0.

    Densities over ``[r_min, r_max)`` plus both probabilities integrate to 1. Values and
    gradients are NaN-free; the HIT value is differentiable w.r.t. the ray (hence the pose)
    wherever the end point does not cross a cell boundary.

    Args:
        map: the decay-rate map (named ``map`` to match the model signature).
        rays: ``[*batch]`` rays of the map's dimension.
        max_cells: static traversal budget per ray; default: enough for the longest ray
            (bounded by the grid size), never truncating. Too small a budget raises at run
            time.

    Returns:
        ``[*batch]`` log-likelihoods.

    Raises:
        ValueError: ``map`` is not a :class:`~lidarjax.maps.DecayRateMap`, ``rays`` is not
            a :class:`~lidarjax.rays.RayBatch`, or their dimensions differ. Traced rates
            that are infinite, NaN or negative raise at run time (``eqx.error_if``);
            concrete ones are rejected when the map is built.
    """
    check_model_type(map, DecayRateMap)
    return grid_log_likelihood(map, rays, max_cells=max_cells)
