"""Decay-rate forward sensor model (dissertation Sec. 7.3, Eqs. 7.11-7.16)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..maps._grid import DecayRateMap, grid_optical_depth, rate_term
from ..rays import HIT, SUB, RayBatch, check_finite_nonnegative, is_concrete
from ..raytrace import RayFold
from ._common import (
    check_model_inputs,
    default_max_cells,
    gather,
    log1mexp,
    map_over_rays,
    safe_log,
    trace_lengths,
)


def _checked(m: DecayRateMap) -> DecayRateMap:
    """``m`` with a run-time check (``eqx.error_if``) that traced rates are finite and
    ``>= 0``. Concrete maps are checked when built; a traced infinite rate would give
    ``inf * 0 = NaN`` pose gradients (and ``-inf`` values) instead of an error."""
    if is_concrete(m.rates) and is_concrete(m.outside_rate):
        return m
    checked = (
        check_finite_nonnegative(m.rates, "DecayRateMap.rates (1/m)"),
        check_finite_nonnegative(m.outside_rate, "DecayRateMap.outside_rate (1/m)"),
    )
    return eqx.tree_at(lambda t: (t.rates, t.outside_rate), m, checked)


def term(m: DecayRateMap):
    """Per-cell summand ``lambda_i d_i`` of the optical depth."""
    return rate_term(_checked(m))


def finish(m: DecayRateMap, f: RayFold, origin, direction, length, kind):
    """Log-likelihood of rays from their :class:`~lidarjax.raytrace.RayFold` (any batch)."""
    inside = f.any_valid & (f.t_end >= length)
    lam_last = gather(m.rates, f.last_cell)
    depth = grid_optical_depth(m, f, length)
    lam_k = jnp.where(inside, lam_last, m.outside_rate)
    hit = safe_log(lam_k) - depth  # Eq. (7.13)
    sub = log1mexp(depth)  # Eq. (7.16): P(sub) = 1 - N(r_min)
    sup = -depth  # Eq. (7.16): P(sup) = N(r_max)
    return jnp.where(kind == HIT, hit, jnp.where(kind == SUB, sub, sup))


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
    check_model_inputs(map, DecayRateMap, rays)
    mc = default_max_cells(map.spec, trace_lengths(rays), max_cells)
    return map_over_rays(term, finish, map, rays, max_cells=mc)
