"""Shared pieces of the grid sensor models: NaN-safe math, input checks and the
pose-batched evaluation of 2-D scans for any grid model."""

from __future__ import annotations

from collections.abc import Callable

import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .. import _checks
from ..maps import AbstractGridModel, grid_log_likelihood
from ..rays import from_scan, is_concrete
from ..raytrace import map_chunked, max_cells_for


def check_model_type(model, model_type: type, name: str = "map") -> None:
    """Trace-time check that ``model`` is a ``model_type`` (``ValueError`` naming it)."""
    if not isinstance(model, model_type):
        raise ValueError(f"{name} must be a {model_type.__name__}, got {type(model).__name__}")


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


@_checks.checked_jit
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
        model: any grid model (:class:`~lidarjax.maps.AbstractGridModel`: decay-rate,
            reflection, endpoint, Gamma / Beta posterior or your own), or a callable
            ``fn(rays) -> [*batch]``.
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
    if isinstance(model, AbstractGridModel):
        if model.spec.dim != 2:
            raise ValueError(f"model must be a 2-D map for 2-D scans, got {model.spec.dim}-D")
        if max_cells is None:
            max_cells = max_cells_for(model.spec, model.walk_bound_m(r_min, r_max))
        return _at_poses(
            grid_log_likelihood,
            model,
            az,
            ranges,
            params,
            float(r_min),
            float(r_max),
            chunk_size,
            max_cells,
        )
    if callable(model):
        return _at_poses(
            model, None, az, ranges, params, float(r_min), float(r_max), chunk_size, None
        )
    raise ValueError(
        f"model must be a grid model (an AbstractGridModel) or a callable, got "
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
