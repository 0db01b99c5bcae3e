"""Fast forward evaluation of the grid sensor models for many rays (particle filters).

The differentiable ``log_likelihood`` functions walk every ray with a fixed cell budget
(``lax.scan`` of length ``max_cells``), so a batch costs ``n_rays * max_cells`` steps
however short its rays are. :func:`batch_log_likelihood` instead walks the rays with
:func:`lidarjax.raytrace.fold_rays` (sorted by length, chunked ``lax.while_loop``), whose
cost is close to the number of cells actually visited. It uses the very same walk, per-cell
term and finish of the model's grid-model protocol (:class:`~lidarjax.maps.AbstractGridModel`)
as the differentiable path, so both agree to round-off.
"""

from __future__ import annotations

from jaxtyping import Array, Float

from .. import _checks
from ..maps import AbstractGridModel
from ..rays import RayBatch
from ..raytrace import check_backend, fold_rays


@_checks.checked_jit
def _fast(model, rays: RayBatch, chunk_size: int, backend: str, threads: int | None):
    flat = rays.flatten()
    walk = model.walk(flat)
    f = fold_rays(
        model.spec,
        *walk,
        model.cell_term(flat),
        chunk_size,
        backend=backend,
        threads=threads,
    )
    return model.finish(f, flat, walk).reshape(rays.shape)


def batch_log_likelihood(
    model,
    rays: RayBatch,
    *,
    chunk_size: int = 2048,
    backend: str = "auto",
    threads: int | None = None,
) -> Float[Array, "*batch"]:
    """Per-ray log-likelihoods of a grid model, fast and forward-only.

    Same values as ``decay_rate_log_likelihood`` / ``reflection_log_likelihood`` /
    ``endpoint_log_likelihood`` / ``posterior_log_likelihood`` (to round-off), but
    without a per-ray cell budget: the work is proportional to the cells the rays
    actually visit (see :func:`lidarjax.raytrace.fold_rays`). Use it for particle
    weights; it is not reverse-differentiable (use the model's ``log_likelihood`` for
    gradients).

    Args:
        model: any grid model (:class:`~lidarjax.maps.AbstractGridModel`): a
            :class:`~lidarjax.maps.DecayRateMap`, :class:`~lidarjax.maps.ReflectionMap`,
            :class:`~lidarjax.maps.EndpointMap`, :class:`~lidarjax.maps.GammaPosteriorMap`,
            :class:`~lidarjax.maps.BetaPosteriorMap` or your own.
        rays: ``[*batch]`` rays of the map's dimension.
        chunk_size: rays walked together in one ``while_loop`` (static; memory is
            ``O(chunk_size)`` per step); JAX path only.
        backend: ``"auto"`` (the native C++ fold when built, else JAX with one warning),
            ``"native"`` or ``"jax"`` (see :mod:`lidarjax.raytrace._native`). Both walk
            the same cells with the same per-cell terms and the same finish; values agree
            to round-off (within 1e-9 relative in float64).
        threads: native worker threads (default: all cores).

    Returns:
        ``[*batch]`` log-likelihoods in the units of the matching model.

    Raises:
        ValueError: unknown model type, rays not a RayBatch, or mismatching dimensions.
    """
    if not isinstance(model, AbstractGridModel):
        raise ValueError(
            "model must be a grid model (an AbstractGridModel: DecayRateMap, ReflectionMap, "
            f"EndpointMap, GammaPosteriorMap, BetaPosteriorMap or your own); got "
            f"{type(model).__name__}"
        )
    if not isinstance(rays, RayBatch):
        raise ValueError(f"rays must be a RayBatch, got {type(rays).__name__}")
    if rays.dim != model.spec.dim:
        raise ValueError(f"rays are {rays.dim}-D but model is a {model.spec.dim}-D grid")
    if not isinstance(chunk_size, int) or chunk_size <= 0:
        raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}")
    if rays.ranges.size == 0:
        raise ValueError("rays is empty")
    check_backend(backend)
    return _fast(model, rays, chunk_size, backend, threads)
