"""Endpoint (likelihood-field) sensor model, normalised per ray as in the dissertation's
comparison (Sec. 7.6.2, text below Eq. 7.32), and the classic (unnormalised) likelihood
field of MCL.

The normalised model's walk, per-cell term and finish are
:class:`~lidarjax.maps.EndpointMap`'s grid-model protocol
(:class:`~lidarjax.maps.AbstractGridModel`)."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._math import safe_log
from ..maps import EndpointMap, grid_log_likelihood
from ..rays import HIT, RayBatch
from ..raytrace import gather
from ._common import check_model_type


def log_likelihood(
    map: EndpointMap, rays: RayBatch, *, max_cells: int | None = None
) -> Float[Array, "*batch"]:
    """Log-likelihood of each ray under the endpoint (likelihood-field) model.

    The heuristic field is ``f(x) = z_hit * N(dist(x); 0, sigma) + z_rand / r_max`` with
    ``dist(x)`` the map's distance of the cell containing ``x`` (cell-wise constant; outside
    the grid ``dist = inf``, so only the uniform term remains; for ``r_max = inf`` the
    uniform term is 0). As described below Eq. (7.32), out-of-range measurements get the
    absolute probability ``P = map.p_out`` and in-range values are normalised per ray so
    that they integrate to ``1 - P`` over the sensor range:

    - HIT at range ``r``: ``p(r) = (1 - P) f(x(r)) / Z``, ``Z = int_{r_min}^{r_max} f(x(r')) dr'``.
      ``Z`` is computed exactly for the cell-wise constant field by traversing the ray
      from ``r_min`` to ``r_max`` (``sum_i f_i d_i`` plus the uniform term times the length
      outside the grid), i.e. the field is sampled at cell resolution.
    - SUB and SUP: ``P`` each. The text treats "out of range" as one outcome with prior
      ``P``; the model's outcomes are "in range" (mass ``1 - P``) and "out of range"
      (mass ``P``), whichever side of the range the reading falls on.

    The ray path is ignored apart from the normaliser (the model sees through walls).
    ``Z = 0`` (``z_rand = 0`` and no field mass along the ray) gives ``-inf``.

    Args:
        map: the endpoint map.
        rays: ``[*batch]`` rays of the map's dimension.
        max_cells: static traversal budget per ray for ``Z`` (default never truncates).

    Returns:
        ``[*batch]`` log-likelihoods (log density for HIT, log probability otherwise).

    Raises:
        ValueError: wrong map type, rays not a RayBatch, or mismatching dimensions.
    """
    check_model_type(map, EndpointMap)
    return grid_log_likelihood(map, rays, max_cells=max_cells)


def likelihood_field_log_likelihood(map: EndpointMap, rays: RayBatch) -> Float[Array, "*batch"]:
    """Log-likelihood of each ray under the classic likelihood-field model of MCL.

    Not normalised per ray (unlike :func:`endpoint_log_likelihood`), so no ray walk:
    in-range readings get ``log(1 - P) + log(z_hit N(dist(x(r)); 0, sigma) + z_rand / r_max)``
    with ``x(r)`` the end point and ``dist`` its cell's distance (outside the grid only the
    uniform term); SUB and SUP readings get ``log P`` with ``P = map.p_out``. About 10x
    cheaper than the normalised model; the particle filter's default for endpoint maps.

    Args:
        map: the endpoint map.
        rays: ``[*batch]`` rays of the map's dimension.

    Returns:
        ``[*batch]`` log-likelihoods (log 1/m for HIT, log probability otherwise).

    Raises:
        ValueError: wrong map type, rays not a RayBatch, or mismatching dimensions.
    """
    check_model_type(map, EndpointMap)
    if not isinstance(rays, RayBatch):
        raise ValueError(f"rays must be a RayBatch, got {type(rays).__name__}")
    if rays.dim != map.spec.dim:
        raise ValueError(f"rays are {rays.dim}-D but map is a {map.spec.dim}-D grid")
    spec = map.spec
    cell = spec.cell_of(rays.endpoints())
    inside = spec.contains(cell)
    f = jnp.where(inside, map.z_hit * gather(map.hit_field(), cell), 0.0)
    f = f + map.random_density(rays.r_max)
    hit = safe_log(1.0 - map.p_out) + safe_log(f)
    return jnp.where(rays.kind == HIT, hit, safe_log(map.p_out))
