"""Shared pieces of the grid sensor models: NaN-safe math, input checks, the per-ray
traversal summary and the pose-batched evaluation of 2-D scans."""

from __future__ import annotations

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._math import log1mexp as log1mexp
from .._math import mul0 as mul0
from .._math import safe_log as safe_log
from ..rays import HIT, SUB, RayBatch, from_scan, is_concrete
from ..raytrace import GridSpec, fold_traversal, map_chunked, max_cells_for, traverse
from ..raytrace import gather as gather


def check_model_inputs(model, model_type: type, rays, name: str = "map") -> None:
    """Trace-time checks: map type, ray type and matching dimension (``ValueError``)."""
    if not isinstance(model, model_type):
        raise ValueError(f"{name} must be a {model_type.__name__}, got {type(model).__name__}")
    if not isinstance(rays, RayBatch):
        raise ValueError(f"rays must be a RayBatch, got {type(rays).__name__}")
    if rays.dim != model.spec.dim:
        raise ValueError(
            f"rays are {rays.dim}-D but {name} is a {model.spec.dim}-D grid "
            f"(rays.origins has shape {rays.origins.shape})"
        )


def default_max_cells(spec: GridSpec, length_m, max_cells: int | None) -> int:
    """A ``traverse`` budget: ``max_cells`` if given, else :func:`max_cells_for` the
    longest trace ``length_m`` (m) when it is concrete, else for the whole grid."""
    if max_cells is not None:
        if not isinstance(max_cells, int) or max_cells <= 0:
            raise ValueError(f"max_cells must be a positive int, got {max_cells!r}")
        return max_cells
    if length_m is not None and is_concrete(length_m):
        length = float(np.max(np.asarray(length_m))) if np.size(length_m) else 0.0
        return max_cells_for(spec, length)
    return max_cells_for(spec)


def trace_lengths(rays: RayBatch) -> Float[Array, "*batch"]:
    """Length each ray is traced to: the range (HIT), ``r_min`` (SUB) or ``r_max`` (SUP)."""
    return jnp.where(
        rays.kind == HIT, rays.ranges, jnp.where(rays.kind == SUB, rays.r_min, rays.r_max)
    )


@functools.partial(jax.jit, static_argnames=("term", "finish", "max_cells"))
def map_over_rays(term: Callable, finish: Callable, m, rays: RayBatch, max_cells: int) -> Array:
    """Differentiable per-ray evaluation of a grid model given as ``term(m)`` (the per-cell
    summand, see :func:`~lidarjax.raytrace.fold_traversal`) and ``finish(m, fold, origins,
    directions, lengths, kind)``: each ray is traversed with a fixed ``max_cells`` budget
    (``lax.scan``) to :func:`trace_lengths`; a run-time check fails if any ray was
    truncated. Returns ``[*batch]``."""
    flat = rays.flatten()
    lengths = trace_lengths(flat)
    tr = jax.vmap(lambda o, d, n: traverse(m.spec, o, d, n, max_cells))(
        flat.origins, flat.directions, lengths
    )
    fold = fold_traversal(tr, term(m))
    out = finish(m, fold, flat.origins, flat.directions, lengths, flat.kind)
    return check_complete(out, fold.complete).reshape(rays.shape)


def check_complete(out: Array, complete: Bool[Array, "*batch"]) -> Array:
    """Attach a run-time check that no traversal ran out of its ``max_cells`` budget."""
    return eqx.error_if(
        out, ~complete, "max_cells is too small for some rays; pass a larger max_cells"
    )


def _pose_params(poses) -> Float[Array, "p 4"]:
    if isinstance(poses, jaxlie.SE2):
        params = poses.parameters()
        if params.ndim != 2:
            raise ValueError(
                f"poses must be a jaxlie.SE2 with one batch axis [p], got batch axes "
                f"{poses.get_batch_axes()}"
            )
        return params
    if isinstance(poses, jaxlie.MatrixLieGroup):
        raise ValueError(f"poses must be a jaxlie.SE2 or a [p 3] array, got {type(poses).__name__}")
    p = jnp.asarray(poses)
    if p.ndim != 2 or p.shape[-1] != 3:
        raise ValueError(f"poses must have shape [p, 3] (x, y, theta), got {p.shape}")
    return jaxlie.SE2.from_xy_theta(p[:, 0], p[:, 1], p[:, 2]).parameters()


@eqx.filter_jit
def _at_poses(model_fn, model, az, ranges, params, r_min, r_max, chunk_size, max_cells):
    chunk = min(chunk_size, params.shape[0])

    def one_chunk(p):
        rays = from_scan(jaxlie.SE2(p), az, ranges, r_min, r_max)  # [c b]
        if model is None:
            return model_fn(rays)
        return model_fn(model, rays, max_cells=max_cells)

    # padding poses are copies of the last one (valid poses: no NaN in reverse mode)
    return map_chunked(one_chunk, params, chunk, fill="edge").reshape(params.shape[0], -1)


def ray_log_likelihoods_at_poses(
    model,
    azimuths_rad: Float[ArrayLike, " b"],
    ranges_m: Float[ArrayLike, " b"],
    poses,
    *,
    r_min: float = 0.0,
    r_max: float = np.inf,
    chunk_size: int = 64,
    max_cells: int | None = None,
) -> Float[Array, "p b"]:
    """Per-ray log-likelihoods of one 2-D scan evaluated at many sensor poses.

    Args:
        model: a :class:`~lidarjax.maps.DecayRateMap`, :class:`~lidarjax.maps.ReflectionMap`
            or :class:`~lidarjax.maps.EndpointMap` (dispatched to the matching model), or a
            callable ``fn(rays) -> [*batch]``.
        azimuths_rad: ``[b]`` beam angles relative to the sensor heading (rad).
        ranges_m: ``[b]`` raw range readings (m), classified by ``r_min``/``r_max``.
        poses: ``[p 3]`` array of ``(x, y, theta)`` (m, m, rad) or a ``jaxlie.SE2`` with
            batch axes ``[p]`` (world-from-sensor).
        r_min: minimum range (m).
        r_max: maximum range (m).
        chunk_size: poses evaluated together (``vmap``); chunks run sequentially with
            ``lax.map`` to bound memory.
        max_cells: traversal budget per ray; default never truncates.

    Returns:
        ``[p b]`` log-likelihoods (differentiable w.r.t. ``poses``).
    """
    from ..maps._grid import DecayRateMap, EndpointMap, ReflectionMap
    from ._decay_rate import log_likelihood as _decay
    from ._endpoint import log_likelihood as _endpoint
    from ._reflection import log_likelihood as _reflection

    if not isinstance(chunk_size, int) or chunk_size <= 0:
        raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}")
    az = jnp.asarray(azimuths_rad, dtype=jnp.result_type(float))
    ranges = jnp.asarray(ranges_m, dtype=az.dtype)
    if az.ndim != 1 or ranges.shape != az.shape:
        raise ValueError(
            f"azimuths_rad and ranges_m must both have shape [b], got {az.shape} and {ranges.shape}"
        )
    if not (is_concrete(r_min) and is_concrete(r_max)):
        raise ValueError("r_min and r_max must be concrete numbers")
    if not (np.isfinite(float(r_min)) and 0 <= float(r_min) < float(r_max)):
        raise ValueError(f"need 0 <= r_min < r_max, got r_min={r_min}, r_max={r_max}")
    params = _pose_params(poses)
    dispatch = {DecayRateMap: _decay, ReflectionMap: _reflection, EndpointMap: _endpoint}
    model_fn = dispatch.get(type(model))
    if model_fn is not None:
        if model.spec.dim != 2:
            raise ValueError(f"model must be a 2-D map for 2-D scans, got {model.spec.dim}-D")
        budget = r_max if model_fn is not _endpoint else float(r_max) - float(r_min)
        mc = default_max_cells(model.spec, budget, max_cells)
        return _at_poses(
            model_fn, model, az, ranges, params, float(r_min), float(r_max), chunk_size, mc
        )
    if callable(model):
        return _at_poses(
            model, None, az, ranges, params, float(r_min), float(r_max), chunk_size, None
        )
    raise ValueError(
        f"model must be a DecayRateMap, ReflectionMap, EndpointMap or a callable, got "
        f"{type(model).__name__}"
    )


def log_likelihood_at_poses(
    model: Callable | object,
    azimuths_rad: Float[ArrayLike, " b"],
    ranges_m: Float[ArrayLike, " b"],
    poses,
    *,
    r_min: float = 0.0,
    r_max: float = np.inf,
    chunk_size: int = 64,
    max_cells: int | None = None,
) -> Float[Array, " p"]:
    """Summed log-likelihood of one 2-D scan at each of many poses, Eq. (7.15).

    Same arguments as :func:`ray_log_likelihoods_at_poses`.

    Returns:
        ``[p]`` log-likelihoods ``sum_b log p(z_b | s_p, m)``.
    """
    return jnp.sum(
        ray_log_likelihoods_at_poses(
            model,
            azimuths_rad,
            ranges_m,
            poses,
            r_min=r_min,
            r_max=r_max,
            chunk_size=chunk_size,
            max_cells=max_cells,
        ),
        axis=-1,
    )
