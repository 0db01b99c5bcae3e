"""The grid-model protocol: one interface for every forward sensor model on a grid map.

A grid model's log-likelihood of a ray is a fold over the cells the ray walks through
(dissertation Eqs. 7.13, 7.16, 7.23, 7.32, 8.20-8.22 all have this form): a per-cell
summand (:class:`~lidarjax.raytrace.CellTerm`, e.g. ``lambda_i d_i`` of the optical depth)
summed along the walk, then a per-ray *finish* that turns the sum and the last cell into
the log-likelihood of the ray's kind (HIT / SUB / SUP). :class:`AbstractGridModel` names
these three pieces:

- :meth:`~AbstractGridModel.walk`: which segment of each ray is walked (by default from the
  origin to :meth:`~lidarjax.rays.RayBatch.model_lengths`: the range for HIT, ``r_min`` for
  SUB, ``r_max`` for SUP);
- :meth:`~AbstractGridModel.cell_term`: the per-cell summand;
- :meth:`~AbstractGridModel.finish`: the per-ray formula.

Every driver uses only these: the differentiable path (:func:`walk_log_likelihood`, a
``lax.scan`` over a fixed cell budget), the fast forward path
(:func:`lidarjax.sensor_models.batch_log_likelihood` over
:func:`lidarjax.raytrace.fold_rays`, JAX or native C++), the pose-batched scan evaluation
(:func:`lidarjax.sensor_models.ray_log_likelihoods_at_poses`) and the particle filter's
:class:`lidarjax.localization.ScanModel`. A new grid model is one final equinox class
implementing the protocol, in one file.

The five models of the dissertation implement it: :class:`~lidarjax.maps.DecayRateMap`,
:class:`~lidarjax.maps.ReflectionMap`, :class:`~lidarjax.maps.EndpointMap`,
:class:`~lidarjax.maps.GammaPosteriorMap` and :class:`~lidarjax.maps.BetaPosteriorMap`.
"""

from __future__ import annotations

import abc
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .. import _checks
from .._checks import check
from ..rays import RayBatch, is_concrete
from ..raytrace import CellTerm, GridSpec, RayFold, fold_traversal, max_cells_for
from ..raytrace._grid import _traverse_unchecked, check_rays

__all__ = [
    "AbstractGridModel",
    "GridWalk",
    "check_complete",
    "check_grid_model",
    "default_max_cells",
    "walk_log_likelihood",
]


class GridWalk(NamedTuple):
    """The segment of each ray a grid model walks: ``origins + t * directions`` for
    ``t`` in ``[0, lengths]``.

    Attributes:
        origins: ``[n d]`` start points (m).
        directions: ``[n d]`` unit directions.
        lengths: ``[n]`` walked lengths (m).
    """

    origins: Float[Array, "n d"]
    directions: Float[Array, "n d"]
    lengths: Float[Array, " n"]


class AbstractGridModel(eqx.Module):
    """A forward sensor model on a grid map (see the module docstring).

    Subclasses hold the map (``spec`` and per-cell arrays) and implement
    :meth:`cell_term` and :meth:`finish`; they may override :meth:`walk` and
    :meth:`walk_bound_m` when they walk another segment than origin to
    :meth:`~lidarjax.rays.RayBatch.model_lengths` (the endpoint model walks
    ``[r_min, r_max]``).
    """

    spec: eqx.AbstractVar[GridSpec]

    def walk_dtype(self, flat: RayBatch):
        """Floating dtype of the walk: the rays' and the grid's, promoted."""
        return jnp.result_type(flat.origins.dtype, self.spec.origin.dtype)

    def walk(self, flat: RayBatch) -> GridWalk:
        """The walked segments of the ``[n]`` rays ``flat``: from the origin along the
        ray's direction to its :meth:`~lidarjax.rays.RayBatch.model_lengths`."""
        dtype = self.walk_dtype(flat)
        return GridWalk(
            flat.origins.astype(dtype),
            flat.directions.astype(dtype),
            flat.model_lengths().astype(dtype),
        )

    def walk_bound_m(self, r_min: float, r_max: float) -> float:
        """Longest walk (m) of a ray with these range limits (sizes the cell budget)."""
        return float(r_max)

    @abc.abstractmethod
    def cell_term(self, flat: RayBatch) -> CellTerm:
        """The per-cell summand folded along every walk of the ``[n]`` rays ``flat``."""

    @abc.abstractmethod
    def finish(self, fold: RayFold, flat: RayBatch, walk: GridWalk) -> Float[Array, " n"]:
        """Per-ray log-likelihoods ``[n]`` from the fold of the walks and the rays."""


def check_grid_model(model, rays, name: str = "map") -> None:
    """Trace-time checks: ``model`` implements :class:`AbstractGridModel`, ``rays`` is a
    :class:`~lidarjax.rays.RayBatch` of the same dimension (``ValueError``)."""
    if not isinstance(model, AbstractGridModel):
        raise ValueError(
            f"{name} must be a grid model (an AbstractGridModel: DecayRateMap, "
            f"ReflectionMap, EndpointMap, GammaPosteriorMap, BetaPosteriorMap or your own), "
            f"got {type(model).__name__}"
        )
    if not isinstance(rays, RayBatch):
        raise ValueError(f"rays must be a RayBatch, got {type(rays).__name__}")
    if rays.dim != model.spec.dim:
        raise ValueError(
            f"rays are {rays.dim}-D but {name} is a {model.spec.dim}-D grid "
            f"(rays.origins has shape {rays.origins.shape})"
        )


def default_max_cells(spec: GridSpec, length_m, max_cells: int | None) -> int:
    """A ``traverse`` budget: ``max_cells`` if given, else :func:`max_cells_for` the
    longest walk ``length_m`` (m) when it is concrete, else for the whole grid."""
    if max_cells is not None:
        if not isinstance(max_cells, int) or max_cells <= 0:
            raise ValueError(f"max_cells must be a positive int, got {max_cells!r}")
        return max_cells
    if length_m is not None and is_concrete(length_m):
        length = float(np.max(np.asarray(length_m))) if np.size(length_m) else 0.0
        return max_cells_for(spec, length)
    return max_cells_for(spec)


def check_complete(out: Array, complete: Bool[Array, "*batch"]) -> Array:
    """Attach a run-time check that no walk ran out of its ``max_cells`` budget."""
    return check(out, ~complete, "max_cells is too small for some rays; pass a larger max_cells")


@_checks.checked_jit
def _walk_log_likelihood(model: AbstractGridModel, rays: RayBatch, max_cells: int):
    flat = rays.flatten()
    w = GridWalk(*check_rays(model.spec, *model.walk(flat), "traverse"))  # outside the vmap
    tr = jax.vmap(lambda o, d, n: _traverse_unchecked(model.spec, o, d, n, max_cells))(*w)
    fold = fold_traversal(tr, model.cell_term(flat))
    out = model.finish(fold, flat, w)
    return check_complete(out, fold.complete).reshape(rays.shape)


def walk_log_likelihood(
    model: AbstractGridModel, rays: RayBatch, *, max_cells: int | None = None
) -> Float[Array, "*batch"]:
    """Per-ray log-likelihoods of any grid model, differentiable (the reference path).

    Every ray is walked with a fixed cell budget (``lax.scan`` of length ``max_cells``),
    so the result is differentiable in the rays (hence poses) and the map's arrays.

    Args:
        model: an :class:`AbstractGridModel`.
        rays: ``[*batch]`` rays of the model's dimension.
        max_cells: static budget per ray; default: enough for the longest walk (the
            whole grid when the rays are traced), never truncating. Too small a budget
            raises at run time.

    Returns:
        ``[*batch]`` log-likelihoods.

    Raises:
        ValueError: ``model`` is not a grid model, ``rays`` not a RayBatch, or their
            dimensions differ.
    """
    check_grid_model(model, rays)
    lengths = None if max_cells is not None else model.walk(rays.flatten()).lengths
    mc = default_max_cells(model.spec, lengths, max_cells)
    return _walk_log_likelihood(model, rays, max_cells=mc)
