"""Endpoint (likelihood-field) sensor model, normalised per ray as in the dissertation's
comparison (Sec. 7.6.2, text below Eq. 7.32)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..maps._grid import EndpointMap
from ..rays import HIT, RayBatch
from ..raytrace import CellTerm, RayFold, fold_traversal, traverse
from ._common import (
    check_complete,
    check_model_inputs,
    default_max_cells,
    gather,
    mul0,
    safe_log,
)


def prepare(m: EndpointMap, rays: RayBatch):
    """Flattened inputs of the endpoint model: the hit field, the uniform term, and the
    rays from ``r_min`` to ``r_max`` (unit directions) whose traversal gives ``Z``."""
    flat = rays.flatten()
    field = m.hit_field()
    r_min, r_max = flat.r_min, flat.r_max
    finite_max = jnp.isfinite(r_max)
    rand = jnp.where(finite_max, m.z_rand / jnp.where(finite_max, r_max, 1.0), 0.0)
    norm = jnp.sqrt(jnp.sum(flat.directions**2, axis=-1, keepdims=True))
    unit = flat.directions / jnp.where(norm > 0, norm, 1.0)
    span = jnp.broadcast_to(r_max - r_min, flat.ranges.shape)
    starts = flat.origins + r_min * unit
    return flat, field, rand, unit, starts, span


def term(m: EndpointMap, field, rand):
    """Per-cell summand ``f_i d_i`` of the normaliser ``Z``."""
    return CellTerm.linear(slope=m.z_hit * field + rand)


def finish(m: EndpointMap, field, rand, f: RayFold, flat: RayBatch, unit, span):
    """Log-likelihood of flattened rays from the :class:`RayFold` of their ``Z`` rays."""
    spec = m.spec
    # Normaliser Z = int_{r_min}^{r_max} f(x(r)) dr of the cell-wise constant field: exact
    # sum over the traversed cells of f_i * d_i plus the uniform term outside the grid.
    f_last = m.z_hit * gather(field, f.last_cell) + rand
    out_len = jnp.maximum(span - f.grid_len, 0.0)
    z = f.body + jnp.where(f.any_valid, f_last * f.last_len, 0.0) + mul0(rand, out_len)
    # Field at the end point (the cell containing it; outside the grid only the uniform term).
    cell = spec.cell_of(flat.origins + flat.ranges[..., None] * unit)
    inside = spec.contains(cell)
    f_end = jnp.where(inside, m.z_hit * gather(field, cell), 0.0) + rand
    ok = (z > 0) & (f_end > 0)
    log_ratio = jnp.log(jnp.where(ok, f_end, 1.0)) - jnp.log(jnp.where(ok, z, 1.0))
    hit = jnp.where(ok, safe_log(1.0 - m.p_out) + log_ratio, -jnp.inf)
    return jnp.where(flat.kind == HIT, hit, safe_log(m.p_out))


@functools.partial(jax.jit, static_argnames=("max_cells",))
def _log_likelihood(m: EndpointMap, rays: RayBatch, max_cells: int):
    flat, field, rand, unit, starts, span = prepare(m, rays)
    tr = jax.vmap(lambda o, d, n: traverse(m.spec, o, d, n, max_cells))(starts, unit, span)
    f = fold_traversal(tr, term(m, field, rand))
    out = finish(m, field, rand, f, flat, unit, span)
    return check_complete(out, f.complete).reshape(rays.shape)


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
    check_model_inputs(map, EndpointMap, rays)
    span = rays.r_max - rays.r_min
    mc = default_max_cells(map.spec, span, max_cells)
    return _log_likelihood(map, rays, max_cells=mc)
