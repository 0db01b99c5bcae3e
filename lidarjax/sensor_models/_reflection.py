"""Reflection (hit-counting) forward sensor model (dissertation Sec. 7.5.2, Eqs. 7.22,
7.23 and the density conversion Eq. 7.32)."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from ..maps._grid import ReflectionMap
from ..rays import HIT, SUB, RayBatch
from ..raytrace import CellTerm, RayFold, box_exit
from ._common import (
    check_model_inputs,
    default_max_cells,
    gather,
    log1mexp,
    map_over_rays,
    mul0,
    safe_log,
    trace_lengths,
)


def _cell_exit(spec, cell, origin, direction):
    """Ray parameter (m) where the ray ``origin + t * direction`` (unit direction) leaves
    the box of ``cell`` (:func:`~lidarjax.raytrace.box_exit`); batched over leading axes."""
    lo = spec.origin + cell.astype(spec.origin.dtype) * spec.resolution
    hi = lo + spec.resolution
    dt = jnp.result_type(lo, origin, direction)
    return box_exit(lo, hi, jnp.asarray(origin, dt), jnp.asarray(direction, dt))


def term(m: ReflectionMap):
    """Per-cell summand ``log(1 - q_i)`` of the cells a ray passes fully."""
    return CellTerm.linear(offset=safe_log(1.0 - m.probs))


def finish(m: ReflectionMap, f: RayFold, origin, direction, length, kind):
    """Log-likelihood of rays from their :class:`~lidarjax.raytrace.RayFold` (any batch)."""
    spec = m.spec
    dtype = spec.origin.dtype
    inside = f.any_valid & (f.t_end >= length)
    out_len = jnp.maximum(length - f.grid_len, 0.0)
    norm = jnp.sqrt(jnp.sum(direction * direction, axis=-1, keepdims=True))
    unit = direction / jnp.where(norm > 0, norm, 1.0)

    q_k = gather(m.probs, f.last_cell)
    # Cells passed fully: all but the last, and the last too if the ray leaves the grid.
    log_before = f.body + jnp.where(f.any_valid & ~inside, safe_log(1.0 - q_k), 0.0)
    # Outside the grid: a homogeneous medium of cells of the grid's resolution with
    # reflection probability q_out, i.e. survival (1 - q_out)^(length / resolution).
    log1m_qout = safe_log(1.0 - m.unknown_prob)
    log_out = -mul0(-log1m_qout, out_len / spec.resolution)
    log_surv_full = log_before + log_out

    # Reflecting cell k: chord = full length of the ray's path inside v_k (Eq. 7.32),
    # from where the ray enters v_k (or starts, if it starts inside) to where it leaves it.
    entry = length - f.last_len
    chord = _cell_exit(spec, f.last_cell, origin, unit) - entry
    chord = jnp.maximum(jnp.maximum(chord, f.last_len), jnp.finfo(dtype).eps * spec.resolution)
    frac = jnp.clip(f.last_len / chord, 0.0, 1.0)

    # HIT density: P(x(r) in v_k) / chord_k, Eqs. (7.23) + (7.32); outside the grid the
    # density of the outside medium, rate -log(1 - q_out) / resolution.
    rate_out = -log1m_qout / spec.resolution
    hit_in = safe_log(q_k) - jnp.log(chord)
    hit_k = jnp.where(inside, hit_in, safe_log(jnp.where(jnp.isfinite(rate_out), rate_out, 1.0)))
    hit = jnp.where(log_surv_full > -jnp.inf, log_surv_full + hit_k, -jnp.inf)
    # Survival to L: the reflecting cell counts with the fraction of its chord travelled,
    # i.e. the CDF of the Eq. (7.32) density is linear inside a cell.
    log_surv = log_surv_full + jnp.where(inside, safe_log(1.0 - q_k * frac), 0.0)
    sub = log1mexp(-log_surv)
    return jnp.where(kind == HIT, hit, jnp.where(kind == SUB, sub, log_surv))


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
    check_model_inputs(map, ReflectionMap, rays)
    mc = default_max_cells(map.spec, trace_lengths(rays), max_cells)
    return map_over_rays(term, finish, map, rays, max_cells=mc)
