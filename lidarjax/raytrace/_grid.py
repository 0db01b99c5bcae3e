"""Exact ray traversal of 2-D and 3-D grids (dissertation section 7.4).

For every ray, the decay-rate model (Eqs. 7.10, 7.13), the reflection model (Eq. 7.22) and
the full map posteriors of chapter 8 need the cells the ray passes and the exact distance
``d_i`` it travels inside each. This module computes them with a voxel walk in the spirit
of Amanatides & Woo, but NaN-free and without accumulated round-off: the parameter of the
next boundary crossing is recomputed from the cell index at every step, and crossings that
coincide (a ray through a cell corner/edge) are taken together, so no spurious zero-length
cell appears.

- :func:`traverse` walks one ray with a fixed budget of ``max_cells`` steps (``lax.scan``,
  reverse-mode differentiable with respect to the ray), padded + masked.
- :func:`accumulate` walks a whole :class:`~lidarjax.rays.RayBatch` and scatter-adds the
  per-cell statistics ``H`` (hits), ``M`` (misses) and ``R`` (travelled length) into a
  :class:`GridStats`. Rays are sorted by their expected cell count and processed in chunks
  with a ``lax.while_loop`` that stops when the chunk's longest ray is done, so memory is
  ``O(chunk_size + cells)`` and no ray is ever truncated.

Conventions: a grid covers ``[origin, origin + shape * resolution)`` per axis; cell
``(i, j[, k])`` covers ``origin + [i, i+1) * resolution`` etc. A point exactly on a
boundary belongs to the cell the ray *enters* there. Rays starting or ending outside the
grid are clipped to it.

Length (~1000 lines): DESIGN.md puts the grid geometry in one module: GridSpec and
GridStats, the exact single-ray walk, ``accumulate`` and the folds share the boundary
rule and its tolerances, which must not drift apart between copies.
"""

from __future__ import annotations

import functools
import math
import operator
from collections.abc import Sequence
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .. import _checks
from .._checks import check
from ..rays import HIT, SUB, SUP, RayBatch, is_concrete
from . import _native
from ._primitives import clip_to_box, n_chunks_for, pad_to_chunks, slabs


def _shape_entry(s) -> int:
    """One entry of a grid shape as an int (``ValueError`` for floats, bools, others)."""
    if isinstance(s, bool | np.bool_):
        raise ValueError(f"shape entries must be ints, got {s!r}")
    try:
        return operator.index(s)
    except TypeError:
        raise ValueError(f"shape entries must be ints, got {s!r}") from None


def _host_resolution(resolution) -> float:
    """A concrete cell size (m) as a float, or ``ValueError`` naming it."""
    try:
        res = float(resolution)
    except (TypeError, ValueError):
        raise ValueError(f"resolution must be a positive finite number, got {resolution!r}")
    if not (np.isfinite(res) and res > 0):
        raise ValueError(f"resolution must be a positive finite number, got {res}")
    return res


class GridSpec(eqx.Module):
    """Geometry of a regular 2-D or 3-D grid.

    Attributes:
        origin: ``[d]`` world coordinates (m) of the grid's lower corner.
        resolution: ``[]`` cell edge length (m).
        shape: static number of cells per axis, ``(nx, ny[, nz])``.
    """

    origin: Float[Array, " d"]
    resolution: Float[Array, ""]
    shape: tuple[int, ...] = eqx.field(static=True)

    def __init__(self, origin: ArrayLike, resolution: float, shape: Sequence[int]):
        """Validate and store the grid.

        Raises:
            ValueError: ``shape`` is not 2 or 3 positive integers (a float such as 4.7 is
                rejected, not truncated), ``origin`` has the wrong shape or a non-finite
                value, or ``resolution`` is not a positive finite number. Traced values
                are checked at run time (``eqx.error_if``).
        """
        shape = tuple(_shape_entry(s) for s in shape)
        if len(shape) not in (2, 3) or any(s <= 0 for s in shape):
            raise ValueError(f"shape must be 2 or 3 positive ints, got {shape}")
        origin = jnp.asarray(origin, dtype=jnp.result_type(float))
        if origin.shape != (len(shape),):
            raise ValueError(f"origin must have shape ({len(shape)},), got {origin.shape}")
        if is_concrete(origin):
            if not np.all(np.isfinite(np.asarray(origin))):
                raise ValueError(f"origin must be finite, got {np.asarray(origin)}")
        else:
            origin = check(origin, ~jnp.all(jnp.isfinite(origin)), "origin must be finite")
        resolution = jnp.asarray(resolution, dtype=origin.dtype)
        if resolution.shape != ():
            raise ValueError(f"resolution must be a scalar, got shape {resolution.shape}")
        if is_concrete(resolution):
            res = float(resolution)
            if not (np.isfinite(res) and res > 0):
                raise ValueError(f"resolution must be a positive finite number, got {res}")
        else:
            resolution = check(
                resolution,
                ~(jnp.isfinite(resolution) & (resolution > 0)),
                "resolution must be a positive finite number",
            )
        self.origin = origin
        self.resolution = resolution
        self.shape = shape

    @classmethod
    def from_bounds(cls, lower: ArrayLike, upper: ArrayLike, resolution: float) -> GridSpec:
        """Smallest grid with lower corner ``lower`` (m) that covers ``upper`` (m)."""
        resolution = _host_resolution(resolution)
        lo = np.asarray(lower, dtype=np.float64)
        hi = np.asarray(upper, dtype=np.float64)
        if lo.shape != hi.shape or lo.ndim != 1:
            raise ValueError(f"lower and upper must be [d] vectors, got {lo.shape}, {hi.shape}")
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise ValueError(f"lower and upper must be finite, got {lo}, {hi}")
        if np.any(hi <= lo):
            raise ValueError(f"upper {hi} must exceed lower {lo} on every axis")
        shape = np.maximum(np.ceil((hi - lo) / resolution - 1e-9), 1).astype(int)
        return cls(lo, resolution, tuple(shape))

    @classmethod
    def covering(cls, points: ArrayLike, resolution: float, margin: float = 0.0) -> GridSpec:
        """Grid covering a point set ``[n d]`` (m) plus ``margin`` (m) on each side, with
        its lower corner snapped to a multiple of ``resolution``."""
        resolution = _host_resolution(resolution)
        margin = float(margin)
        if not (np.isfinite(margin) and margin >= 0):
            raise ValueError(f"margin must be a finite number >= 0, got {margin}")
        p = np.asarray(points, dtype=np.float64).reshape(-1, np.shape(points)[-1])
        p = p[np.all(np.isfinite(p), axis=1)]
        if p.size == 0:
            raise ValueError("points must contain at least one finite point")
        lo = np.floor((p.min(0) - margin) / resolution) * resolution
        hi = p.max(0) + margin + 1e-9
        return cls.from_bounds(lo, hi, resolution)

    @property
    def dim(self) -> int:
        """Spatial dimension."""
        return len(self.shape)

    @property
    def n_cells(self) -> int:
        """Total number of cells."""
        return math.prod(self.shape)

    @property
    def upper(self) -> Float[Array, " d"]:
        """``[d]`` world coordinates (m) of the upper corner."""
        return self.origin + jnp.asarray(self.shape, self.origin.dtype) * self.resolution

    def cell_of(self, points: Float[ArrayLike, "*batch d"]) -> Int[Array, "*batch d"]:
        """Integer cell index (floor) of points; may lie outside ``[0, shape)``."""
        p = jnp.asarray(points)
        return jnp.floor((p - self.origin) / self.resolution).astype(jnp.int32)

    def contains(self, cells: Int[ArrayLike, "*batch d"]) -> Bool[Array, "*batch"]:
        """Whether integer cell indices lie inside the grid."""
        c = jnp.asarray(cells)
        return jnp.all((c >= 0) & (c < jnp.asarray(self.shape)), axis=-1)

    def cell_centers(self) -> Float[Array, "*shape d"]:
        """World coordinates (m) of all cell centres, shape ``[*shape d]``."""
        axes = [
            self.origin[k] + (jnp.arange(n, dtype=self.origin.dtype) + 0.5) * self.resolution
            for k, n in enumerate(self.shape)
        ]
        return jnp.stack(jnp.meshgrid(*axes, indexing="ij"), axis=-1)

    def extent(self) -> tuple[float, ...]:
        """Matplotlib ``imshow`` extent ``(x0, x1, y0, y1)`` of a 2-D grid (host floats)."""
        lo = np.asarray(self.origin)
        hi = np.asarray(self.upper)
        return (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))


class GridStats(eqx.Module):
    """Per-cell ray statistics, the sufficient statistics of every grid model.

    Attributes:
        spec: the grid.
        hits: ``[*shape]`` int32, ``H_i``: rays reflected inside the cell.
        misses: ``[*shape]`` int32, ``M_i``: rays that traversed the cell without reflection.
        lengths: ``[*shape]`` float, ``R_i = sum_j d_i(j)``: total distance (m) travelled
            inside the cell by all rays, up to their reflection point (Eq. 7.10).
    """

    spec: GridSpec
    hits: Int[Array, "*shape"]
    misses: Int[Array, "*shape"]
    lengths: Float[Array, "*shape"]

    def __add__(self, other: GridStats) -> GridStats:
        if not isinstance(other, GridStats) or other.spec.shape != self.spec.shape:
            raise ValueError("can only add GridStats of the same grid")
        return GridStats(
            self.spec,
            self.hits + other.hits,
            self.misses + other.misses,
            self.lengths + other.lengths,
        )

    @property
    def visited(self) -> Bool[Array, "*shape"]:
        """Cells touched by at least one ray."""
        return (self.hits + self.misses) > 0


class Traversal(eqx.Module):
    """Cells visited by one ray, in order, padded to ``max_cells``.

    Attributes:
        cells: ``[max_cells d]`` int32 cell indices (clipped into the grid on padding).
        lengths: ``[max_cells]`` distance (m) travelled inside each cell; 0 on padding.
        valid: ``[max_cells]`` bool, which entries are real cells.
        is_last: ``[max_cells]`` bool, True at the ray's last cell (where it ends or leaves
            the grid).
        complete: ``[]`` bool, False if ``max_cells`` was too small for the ray.
        t_start: ``[]`` ray parameter (m) where the clipped ray starts.
        t_end: ``[]`` ray parameter (m) where the clipped ray ends.
    """

    cells: Int[Array, "max_cells d"]
    lengths: Float[Array, " max_cells"]
    valid: Bool[Array, " max_cells"]
    is_last: Bool[Array, " max_cells"]
    complete: Bool[Array, ""]
    t_start: Float[Array, ""]
    t_end: Float[Array, ""]


class _WalkState(eqx.Module):
    cell: Int[Array, " d"]
    t: Float[Array, ""]
    active: Bool[Array, ""]


class _Ray(eqx.Module):
    origin: Float[Array, " d"]
    direction: Float[Array, " d"]
    # next boundary of cell c along axis k: t_first_k + (c_k - c0_k) * t_scale_k, measured
    # from the first cell so that round-off does not grow with the distance to the origin
    t_first: Float[Array, " d"]
    c0: Int[Array, " d"]
    t_scale: Float[Array, " d"]
    t_start: Float[Array, ""]
    t_end: Float[Array, ""]
    tol: Float[Array, ""]


def _slabs(spec: GridSpec, o, d):
    """:func:`~lidarjax.raytrace.slabs` against the grid's box."""
    return slabs(spec.origin.astype(o.dtype), spec.upper.astype(o.dtype), o, d)


def _setup(spec: GridSpec, origin, direction, length) -> tuple[_Ray, _WalkState]:
    """Clip one ray to the grid box (slab test) and find its first cell."""
    dtype = jnp.result_type(origin, direction, length, spec.origin)
    o = jnp.asarray(origin, dtype)
    d = jnp.asarray(direction, dtype)
    length = jnp.asarray(length, dtype)
    norm = jnp.sqrt(jnp.sum(d * d))
    nz = norm > 0
    d = d / jnp.where(nz, norm, 1.0)
    length = jnp.where(nz, length, 0.0)

    lo = spec.origin.astype(dtype)
    moving, d_safe, inside_axis, t_near, t_far = _slabs(spec, o, d)
    t_enter = jnp.max(t_near)
    t_exit = jnp.min(t_far)
    t0 = jnp.maximum(t_enter, 0.0)
    t1 = jnp.minimum(length, t_exit)
    starts_inside = jnp.all(inside_axis)
    active = (t0 < t1) | ((length == 0) & starts_inside)
    t1 = jnp.where(active, t1, t0)
    t0 = jnp.where(jnp.isfinite(t0), t0, 0.0)
    t1 = jnp.where(jnp.isfinite(t1), t1, t0)

    # First cell: the cell the ray is in just after t0. On an entry face the index is the
    # boundary cell exactly; elsewhere floor (moving up) / ceil - 1 (moving down).
    p0 = o + t0 * d
    rel = (p0 - lo) / spec.resolution
    cell = jnp.where(d < 0, jnp.ceil(rel) - 1, jnp.floor(rel))
    entry_axis = jnp.argmax(t_near)
    entered = (t_enter > 0) & (jnp.arange(d.shape[0]) == entry_axis)
    n = jnp.asarray(spec.shape, dtype)
    cell = jnp.where(entered, jnp.where(d > 0, 0.0, n - 1), cell)
    cell = jnp.clip(jnp.where(jnp.isfinite(cell), cell, 0.0), 0, n - 1).astype(jnp.int32)

    eps = jnp.finfo(dtype).eps
    tol = 32 * eps * (t1 + spec.resolution)
    # Next boundary of cell c along axis k: lo_k + (c_k + up_k) * res, reached at
    # t = (lo_k - o_k + (c0_k + up_k) * res) / d_k + (c_k - c0_k) * res / d_k (inf if d_k = 0).
    first = (lo - o + (cell + (d > 0)).astype(dtype) * spec.resolution) / d_safe
    t_first = jnp.where(moving, first, jnp.inf)
    # A direction component so small that one cell takes more than the largest float
    # (1e-37 with 100 m cells in float32) must not make 0 * inf = NaN in _step.
    big = jnp.finfo(dtype).max
    t_scale = jnp.where(moving, jnp.clip(spec.resolution / d_safe, -big, big), 0.0)
    return _Ray(o, d, t_first, cell, t_scale, t0, t1, tol), _WalkState(cell, t0, active)


def _step(spec: GridSpec, ray: _Ray, state: _WalkState):
    """One cell of the walk: the segment inside ``state.cell`` and the next state."""
    d = ray.direction
    moving = d != 0
    up = d > 0
    t_axis = ray.t_first + (state.cell - ray.c0).astype(d.dtype) * ray.t_scale
    t_min = jnp.min(t_axis)
    last = t_min >= ray.t_end - ray.tol
    t_stop = jnp.where(last, ray.t_end, t_min)
    seg = jnp.maximum(t_stop - state.t, 0.0)
    valid = state.active & ((seg > ray.tol) | last)
    seg = jnp.where(valid, seg, 0.0)
    step = moving & (t_axis <= t_min + ray.tol)
    cell = state.cell + jnp.where(step, jnp.where(up, 1, -1), 0).astype(jnp.int32)
    inside = spec.contains(cell)
    new = _WalkState(cell, jnp.where(state.active, t_stop, state.t), state.active & ~last & inside)
    return (state.cell, seg, valid, valid & (last | ~inside)), new


@functools.partial(jax.jit, static_argnames=("max_cells",))
def traverse(
    spec: GridSpec,
    origin: Float[ArrayLike, " d"],
    direction: Float[ArrayLike, " d"],
    length: Float[ArrayLike, ""],
    max_cells: int,
) -> Traversal:
    """Cells visited by one ray and the exact length travelled inside each (Sec. 7.4).

    The ray is ``origin + t * direction`` for ``t`` in ``[0, length]``, clipped to the grid
    box. ``direction`` need not be unit (it is normalised; ``t`` is then in metres); a zero
    direction is treated as a zero-length ray. A zero-length ray starting inside the grid
    visits its start cell with length 0. Differentiable (reverse and forward mode) with
    respect to ``origin``, ``direction`` and ``length`` wherever the visited cell sequence
    is locally constant. Batch over rays with ``jax.vmap``.

    Args:
        spec: the grid.
        origin: ``[d]`` ray start (m).
        direction: ``[d]`` ray direction.
        length: ``[]`` ray length (m); ``inf`` traces to the grid border.
        max_cells: static budget of cells; a ray through ``c`` cells needs ``c`` (at most
            ``sum_k |d_k| * length / resolution + d``). ``complete`` is False if exceeded.

    Returns:
        A :class:`Traversal`; ``lengths[valid]`` sums to the clipped length.
    """
    if not isinstance(max_cells, int) or max_cells <= 0:
        raise ValueError(f"max_cells must be a positive int, got {max_cells!r}")
    origin = jnp.asarray(origin)
    if origin.shape != (spec.dim,) or jnp.shape(direction) != (spec.dim,):
        raise ValueError(
            f"origin and direction must have shape ({spec.dim},) for a {spec.dim}-D grid, got "
            f"{origin.shape} and {jnp.shape(direction)}"
        )
    if jnp.shape(length) != ():
        raise ValueError(f"length must be a scalar, got shape {jnp.shape(length)}")
    origin, direction, length = check_rays(
        spec, origin, jnp.asarray(direction), jnp.asarray(length), name="traverse"
    )
    return _traverse_unchecked(spec, origin, direction, length, max_cells)


def _traverse_unchecked(spec: GridSpec, origin, direction, length, max_cells: int) -> Traversal:
    """:func:`traverse` without the input checks: batched callers check the whole batch
    once (:func:`check_rays`, outside their ``vmap``) and ``vmap`` this."""
    ray, state = _setup(spec, origin, direction, length)

    def body(s, _):
        out, s = _step(spec, ray, s)
        return s, out

    final, (cells, lengths, valid, is_last) = jax.lax.scan(body, state, None, length=max_cells)
    return Traversal(
        cells=cells,
        lengths=lengths,
        valid=valid,
        is_last=is_last,
        complete=~final.active,
        t_start=ray.t_start,
        t_end=ray.t_end,
    )


class RayFold(eqx.Module):
    """A traversal reduced to what the grid sensor models need (see :func:`fold_traversal`
    and :func:`fold_rays`). Fields have the rays' batch shape ``[*b]``.

    Attributes:
        body: ``sum term(cell, length)`` over the visited cells except the final one.
        last_cell: ``[*b d]`` final visited cell (where the ray ends or leaves the grid);
            meaningless where ``any_valid`` is False.
        last_len: length (m) travelled in ``last_cell`` (0 where ``any_valid`` is False).
        grid_len: total length (m) travelled inside the grid.
        any_valid: the ray visits at least one cell.
        t_start: ray parameter (m) where the clipped ray starts.
        t_end: ray parameter (m) where the clipped ray ends.
        complete: False if a fixed cell budget truncated the ray (scan path only).
    """

    body: Array
    last_cell: Array
    last_len: Array
    grid_len: Array
    any_valid: Array
    t_start: Array
    t_end: Array
    complete: Array


def fold_traversal(tr: Traversal, term) -> RayFold:
    """Reduce a (possibly batched) :class:`Traversal` to a :class:`RayFold`.

    Args:
        tr: traversal with fields ``[*b max_cells ...]``.
        term: ``term(cells [..., d] int32, lengths [...]) -> [...]``, elementwise; its
            value on padding entries is discarded.

    Differentiable like :func:`traverse`.
    """
    last = tr.is_last & tr.valid
    body_mask = tr.valid & ~last
    vals = term(tr.cells, tr.lengths)
    body = jnp.sum(jnp.where(body_mask, vals, 0.0), axis=-1)
    last_cell = jnp.sum(jnp.where(last[..., None], tr.cells, 0), axis=-2)
    last_len = jnp.sum(jnp.where(last, tr.lengths, 0.0), axis=-1)
    grid_len = jnp.sum(jnp.where(tr.valid, tr.lengths, 0.0), axis=-1)
    return RayFold(
        body=body,
        last_cell=last_cell,
        last_len=last_len,
        grid_len=grid_len,
        any_valid=jnp.any(tr.valid, axis=-1),
        t_start=tr.t_start,
        t_end=tr.t_end,
        complete=tr.complete,
    )


def _fold_sorted(spec: GridSpec, origins, directions, lengths, term, chunk: int):
    """Walk rays (already sorted by work) in chunks; per-ray fold outputs in input order."""
    n = origins.shape[0]
    dtype = jnp.result_type(origins.dtype, spec.origin.dtype)
    chunk = max(1, min(chunk, n))
    n_chunks = -(-n // chunk)
    pad = n_chunks * chunk - n

    def prep(x):
        widths = [(0, pad)] + [(0, 0)] * (x.ndim - 1)
        return jnp.pad(x, widths).reshape(n_chunks, chunk, *x.shape[1:])

    setup = jax.vmap(functools.partial(_setup, spec))
    step = jax.vmap(functools.partial(_step, spec))
    budget = walk_bound(spec)

    def one_chunk(xs):
        o, d, length = xs
        ray, state = setup(o.astype(dtype), d.astype(dtype), length.astype(dtype))
        zero = jnp.zeros(o.shape[0], dtype)
        init = (state, zero, state.cell, zero, zero, jnp.zeros(o.shape[0], bool), 0)

        def cond(carry):
            return jnp.any(carry[0].active) & (carry[-1] < budget)

        def body(carry):
            s, acc, last_cell, last_len, grid_len, any_valid, it = carry
            (cell, seg, valid, last), s = step(ray, s)
            vals = term(cell, seg)
            acc = acc + jnp.where(valid & ~last, vals, 0.0)
            is_end = valid & last
            last_cell = jnp.where(is_end[:, None], cell, last_cell)
            last_len = jnp.where(is_end, seg, last_len)
            return s, acc, last_cell, last_len, grid_len + seg, any_valid | valid, it + 1

        final, acc, last_cell, last_len, grid_len, any_valid, _ = jax.lax.while_loop(
            cond, body, init
        )
        acc = _check_walk_ended(acc, final.active)
        return acc, last_cell, last_len, grid_len, any_valid, ray.t_start, ray.t_end

    outs = _checks.map(one_chunk, (prep(origins), prep(directions), prep(lengths)))
    return [x.reshape(n_chunks * chunk, *x.shape[2:])[:n] for x in outs]


@_checks.checked_jit
def fold_rays(
    spec: GridSpec,
    origins: Float[Array, "n d"],
    directions: Float[Array, "n d"],
    lengths: Float[Array, " n"],
    term,
    chunk_size: int = 2048,
    streams: int = 2,
    *,
    backend: str = "auto",
    threads: int | None = None,
) -> RayFold:
    """:func:`fold_traversal` of many rays without a per-ray cell budget (forward only).

    With a :class:`CellTerm` and ``backend`` ``"native"`` (or ``"auto"`` when the native
    kernels are built, see :mod:`lidarjax.raytrace._native`) the walk runs in C++ on
    ``threads`` threads (default: all cores) with the same walk and the same per-cell
    terms; ``chunk_size`` and ``streams`` then do not matter. Any other ``term`` uses the
    JAX path.

    Rays are sorted by expected cell count and walked in chunks of ``chunk_size``, each
    chunk in a ``lax.while_loop`` that stops when its longest ray is done, so the work is
    close to the number of cells actually visited (unlike ``traverse``'s fixed budget) and
    no ray is truncated. The sorted rays are dealt round-robin to ``streams`` independent
    chunk sequences, which XLA's CPU runtime may execute concurrently (on 2 cores, 2
    streams were about 20 % faster than 1 under load). The walk is the same as
    :func:`traverse`'s (same cells, same lengths); only the summation order of ``body``
    differs. Not reverse-differentiable (use :func:`fold_traversal` for gradients).

    Args:
        spec: the grid.
        origins: ``[n d]`` ray starts (m).
        directions: ``[n d]`` directions (normalised internally).
        lengths: ``[n]`` lengths (m), ``inf`` traces to the grid border.
        term: ``term(cells [c d] int32, lengths [c]) -> [c]``, elementwise. A plain
            function is compiled in as a constant; pass a :class:`jax.tree_util.Partial` or
            an ``equinox.Module`` to keep the arrays it closes over traced.
        chunk_size: rays walked together (static, >= 1).
        streams: independent chunk sequences (static, >= 1).
        backend: ``"auto"``, ``"native"`` or ``"jax"`` (static).
        threads: native worker threads (static; default all cores).

    Returns:
        A :class:`RayFold` with fields of leading shape ``[n]`` (``complete`` all True).

    Raises:
        ValueError: bad ``chunk_size``/``streams``/``threads``/``backend``, no rays, or
            ``backend="native"`` with a ``term`` that is not a :class:`CellTerm`.
        RuntimeError: ``backend="native"`` but the native kernels are unavailable.
    """
    if not isinstance(chunk_size, int) or chunk_size <= 0:
        raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}")
    if not isinstance(streams, int) or streams <= 0:
        raise ValueError(f"streams must be a positive int, got {streams!r}")
    threads = _native.check_threads(threads)
    n, _ = origins.shape
    if n == 0:
        raise ValueError("origins is empty: no rays to fold")
    if backend == "native" and not isinstance(term, CellTerm):
        raise ValueError(
            f"backend='native' needs a CellTerm term, got {type(term).__name__}; "
            "use backend='jax' for arbitrary terms"
        )
    dtype = jnp.result_type(origins.dtype, spec.origin.dtype)
    _native.check_backend(backend)
    # the kernel validates its rays and grid itself (naming the first bad ray)
    if isinstance(term, CellTerm) and _native.resolve(backend) == "native":
        fields = _native.fold(
            spec,
            term.mode,
            term.tables.astype(dtype),
            origins.astype(dtype),
            directions.astype(dtype),
            lengths.astype(dtype),
            threads,
        )
    else:
        origins, directions, lengths = check_rays(spec, origins, directions, lengths)
        fields = _fold_streams(spec, origins, directions, lengths, term, chunk_size, streams)
    acc, last_cell, last_len, grid_len, any_valid, t_start, t_end = fields
    return RayFold(
        body=acc,
        last_cell=last_cell,
        last_len=last_len,
        grid_len=grid_len,
        any_valid=any_valid,
        t_start=t_start,
        t_end=t_end,
        complete=jnp.ones(n, bool),
    )


def _fold_streams(spec, origins, directions, lengths, term, chunk_size, streams):
    """JAX path of :func:`fold_rays`: rays sorted by expected work, dealt round-robin to
    ``streams`` chunked walks; the seven fold fields in input order."""
    n = origins.shape[0]
    dtype = jnp.result_type(origins.dtype, spec.origin.dtype)
    unit_sum = jnp.sum(jnp.abs(directions), axis=-1) / jnp.maximum(
        jnp.sqrt(jnp.sum(directions * directions, axis=-1)), jnp.finfo(dtype).tiny
    )
    work = unit_sum * jnp.minimum(lengths, _box_diagonal(spec))
    order = jnp.argsort(work)
    streams = min(streams, n)
    parts = [order[p::streams] for p in range(streams)]
    results = [
        _fold_sorted(spec, origins[sel], directions[sel], lengths[sel], term, chunk_size)
        for sel in parts
    ]
    fields = []
    for k in range(len(results[0])):
        first = results[0][k]
        out = jnp.zeros((n, *first.shape[1:]), first.dtype)
        for sel, res in zip(parts, results):
            out = out.at[sel].set(res[k])
        fields.append(out)
    return fields


class CellTerm(eqx.Module):
    """A per-cell fold term given by tables over the grid, the form every grid sensor
    model's term takes; the JAX walk calls it, the native kernel reads its tables.

    ``term(cell c, length l)`` by ``mode`` (``A``, ``B``, ``a``, ``b``, ``log_b`` are
    ``[*shape]`` tables stacked in ``tables``):

    - ``0``: ``A[c] + B[c] * l``;  ``1``: ``B[c] * l``;  ``2``: ``A[c]``;
    - ``3``: ``a[c] * (log_b[c] - log(b[c] + l))`` for ``l > 0``, else 0 (the no-reflection
      factor of the Gamma full posterior, Sec. 8.4.5).

    Attributes:
        tables: ``[k *shape]`` per-cell tables (``k`` = 2, 1, 1, 3 by mode).
        mode: static term form.
    """

    tables: Float[Array, "k *shape ..."]
    mode: int = eqx.field(static=True)

    def __init__(self, tables: Float[ArrayLike, "k *shape ..."], mode: int):
        need = _native.TERM_MODES
        if mode not in need:
            raise ValueError(f"mode must be 0, 1, 2 or 3, got {mode!r}")
        tables = jnp.asarray(tables)
        if tables.ndim not in (3, 4) or tables.shape[0] != need[mode]:
            raise ValueError(
                f"tables must have shape [{need[mode]} *shape] for mode {mode}, got {tables.shape}"
            )
        self.tables = tables
        self.mode = mode

    @classmethod
    def linear(cls, offset: Array | None = None, slope: Array | None = None) -> CellTerm:
        """``offset[c] + slope[c] * l`` (either may be None, meaning 0)."""
        if offset is None and slope is None:
            raise ValueError("give offset, slope or both")
        if offset is None:
            return cls(jnp.asarray(slope)[None], 1)
        if slope is None:
            return cls(jnp.asarray(offset)[None], 2)
        return cls(jnp.stack([jnp.asarray(offset), jnp.asarray(slope)]), 0)

    @classmethod
    def gamma(cls, a: Array, b: Array) -> CellTerm:
        """``a[c] * (log b[c] - log(b[c] + l))`` for ``l > 0`` (``a, b > 0``)."""
        a, b = jnp.asarray(a), jnp.asarray(b)
        return cls(jnp.stack([a, b, jnp.log(b)]), 3)

    def __call__(self, cells: Int[Array, "... d"], lengths: Array) -> Array:
        t = self.tables
        if self.mode == 0:
            return gather(t[0], cells) + gather(t[1], cells) * lengths
        if self.mode == 1:
            return gather(t[0], cells) * lengths
        if self.mode == 2:
            return gather(t[0], cells)
        pos = lengths > 0
        d_safe = jnp.where(pos, lengths, 1.0)
        a, b, log_b = (gather(t[k], cells) for k in range(3))
        return jnp.where(pos, a * (log_b - jnp.log(b + d_safe)), 0.0)


def gather(values: Array, cells: Int[Array, "... d"]) -> Array:
    """``values[cells]`` for integer index vectors ``cells`` (clipped into the grid)."""
    idx = tuple(jnp.clip(cells[..., k], 0, values.shape[k] - 1) for k in range(values.ndim))
    return values[idx]


def max_cells_for(spec: GridSpec, length_m: float | None = None) -> int:
    """A ``max_cells`` budget for :func:`traverse` that no ray of length ``length_m`` (m)
    can exceed in this grid (default: rays crossing the whole grid)."""
    per_axis = [n + 1 for n in spec.shape]
    if length_m is not None and np.isfinite(length_m):
        res = float(spec.resolution)
        per_axis = [min(p, int(np.ceil(float(length_m) / res)) + 2) for p in per_axis]
    return int(sum(per_axis))


def traverse_rays(spec: GridSpec, rays: RayBatch, max_cells: int | None = None) -> Traversal:
    """:func:`traverse` for every ray of a batch, each traced to its
    :meth:`~lidarjax.rays.RayBatch.mapping_lengths` (range, or ``r_max`` for SUP rays).

    Args:
        spec: the grid; its dimension must match the rays'.
        rays: any batch shape ``[*batch]``.
        max_cells: static per-ray budget; default :func:`max_cells_for` the longest
            possible ray, which never truncates.

    Returns:
        A :class:`Traversal` whose fields have leading axes ``[*batch]``.
    """
    if not isinstance(rays, RayBatch):
        raise ValueError(f"rays must be a RayBatch, got {type(rays).__name__}")
    if rays.dim != spec.dim:
        raise ValueError(f"rays are {rays.dim}-D but spec is a {spec.dim}-D grid")
    if max_cells is None:
        max_cells = max_cells_for(spec)
    return _traverse_rays(spec, rays, max_cells=max_cells)


@_checks.checked_jit
def _traverse_rays(spec: GridSpec, rays: RayBatch, max_cells: int) -> Traversal:
    flat = rays.flatten()
    o, d, n = check_rays(spec, flat.origins, flat.directions, flat.mapping_lengths(), "traverse")
    tr = jax.vmap(lambda o, d, length: _traverse_unchecked(spec, o, d, length, max_cells))(o, d, n)
    return jax.tree.map(lambda x: x.reshape(*rays.shape, *x.shape[1:]), tr)


def expected_cell_count(spec: GridSpec, rays: RayBatch) -> Float[Array, "*batch"]:
    """Upper bound on the number of cells each ray visits (before clipping to the grid)."""
    lengths = jnp.minimum(rays.mapping_lengths(), _box_diagonal(spec))
    return jnp.sum(jnp.abs(rays.directions), axis=-1) * lengths / spec.resolution + spec.dim


def _clip_to_box(spec: GridSpec, origins, directions, lengths):
    """Parameter interval ``[t_in, t_out]`` of every ray inside the grid box."""
    return clip_to_box(spec.origin, spec.upper, origins, directions, lengths)


def walk_bound(spec: GridSpec) -> int:
    """Most cells any ray can visit in ``spec``: each step of the walk moves at least one
    axis index by one, monotonically, so at most ``sum(shape)`` steps plus the first cell
    (``sum(shape) + dim`` is used). Every loop over cells stops at this bound."""
    return int(sum(spec.shape)) + spec.dim


def _check_walk_ended(x, active):
    """Fail loudly (``eqx.error_if``) if any walk hit :func:`walk_bound` still active,
    which only non-finite inputs can cause; the result would be wrong otherwise."""
    return check(
        x,
        jnp.any(active),
        "ray walk exceeded the grid's cell bound (non-finite ray origin, direction or "
        "length, or grid origin/resolution)",
    )


def check_rays(spec: GridSpec, origins, directions, lengths, name: str = "rays"):
    """Run-time validation of ray inputs (``eqx.error_if``, eager or under ``jit``):
    origins and directions finite, lengths not NaN and not negative (``inf`` traces to the
    grid border), the grid origin finite and its resolution positive and finite. Returns
    ``(origins, directions, lengths)`` carrying the checks (use the returned values)."""
    bad_o = ~jnp.all(jnp.isfinite(origins))
    origins = check(origins, bad_o, f"{name}: ray origins must be finite (NaN or inf pose?)")
    bad_d = ~jnp.all(jnp.isfinite(directions))
    directions = check(
        directions, bad_d, f"{name}: ray directions must be finite (NaN or inf heading/azimuth?)"
    )
    bad_l = jnp.any(jnp.isnan(lengths) | (lengths < 0))
    lengths = check(lengths, bad_l, f"{name}: ray lengths must be >= 0 and not NaN")
    bad_g = ~(jnp.all(jnp.isfinite(spec.origin)) & jnp.isfinite(spec.resolution)) | ~(
        spec.resolution > 0
    )
    origins = check(
        origins, bad_g, "spec: grid origin must be finite and resolution positive and finite"
    )
    return origins, directions, lengths


def _box_diagonal(spec: GridSpec):
    return spec.resolution * math.sqrt(sum(s * s for s in spec.shape))


_BLOCK_RAYS = 1 << 16


def _walk_block(
    spec: GridSpec, origins, directions, lengths, ray_hits, use, chunk_size: int, tile=None
):
    """``(R, V, H)`` (lengths, visits = H + M, hits) of one block of rays, flat
    ``[n_cells]``: the block is sorted by expected work and walked in chunks.

    ``tile = (row0, rows)`` (``row0`` may be traced, ``rows`` static): the same walk over
    the whole grid, adding only the cells of the rows ``[row0, row0 + rows)`` (flat
    ``[rows * prod(shape[1:])]``; other cells go to the discarded last bin)."""
    dtype = origins.dtype
    # Sort by expected work so each chunk's while-loop runs about as long as its rays need.
    # expected cells walked: L1 length of the part of the ray inside the grid box
    t_in, t_out = _clip_to_box(spec, origins, directions, lengths)
    work = jnp.sum(jnp.abs(directions), axis=-1) * jnp.maximum(t_out - t_in, 0.0)
    work = jnp.where(use, work, -1.0)
    order = jnp.argsort(work)
    o_c, d_c, l_c, h_c, u_c = (
        pad_to_chunks(x[order], chunk_size, fill)
        for x, fill in (
            (origins, 0.0),
            (directions, 0.0),
            (lengths, 0.0),
            (ray_hits, False),
            (use, False),
        )
    )
    shape = spec.shape if tile is None else (tile[1], *spec.shape[1:])
    n_cells = math.prod(shape)
    strides = jnp.asarray(np.cumprod((1,) + shape[:0:-1])[::-1].copy(), jnp.int32)
    # Accumulators (last entry = bin for padding): lengths R, visits V = H + M, hits H.
    # Lengths R (real part) and visits V = H + M (imaginary part) share one complex
    # accumulator: one scatter per step instead of two (~1.4x faster on CPU). V is exact
    # while it stays below 2**24 (float32): a block has at most _BLOCK_RAYS rays.
    cdtype = jnp.complex64 if dtype == jnp.float32 else jnp.complex128
    acc0 = (jnp.zeros(n_cells + 1, cdtype), jnp.zeros(n_cells + 1, jnp.int32))

    setup = jax.vmap(functools.partial(_setup, spec))
    step = jax.vmap(functools.partial(_step, spec))
    budget = walk_bound(spec)

    if tile is None:

        def flat_index(cell, valid):
            return jnp.where(valid, jnp.sum(cell * strides, axis=-1), n_cells)

    else:
        shift = jnp.zeros(spec.dim, jnp.int32).at[0].set(tile[0])

        def flat_index(cell, valid):
            local = cell - shift
            inside = valid & (local[..., 0] >= 0) & (local[..., 0] < tile[1])
            return jnp.where(inside, jnp.sum(local * strides, axis=-1), n_cells)

    def chunk_body(acc, xs):
        o, d, length, is_hit, use_c = xs
        ray, state = setup(o, d, length)
        state = _WalkState(state.cell, state.t, state.active & use_c)
        # A hit is counted in the ray's last cell only if it ends inside the grid.
        ends_inside = is_hit & state.active & (ray.t_end >= length - ray.tol)

        def cond(carry):
            return jnp.any(carry[1].active) & (carry[-1] < budget)

        def body(carry):
            (rv, hits), s, last_cell, ended, it = carry
            (cell, seg, valid, last), s = step(ray, s)
            upd = jax.lax.complex(seg, valid.astype(dtype))
            rv = rv.at[flat_index(cell, valid)].add(upd, mode="promise_in_bounds")
            is_end = valid & last
            last_cell = jnp.where(is_end[:, None], cell, last_cell)
            return (rv, hits), s, last_cell, ended | is_end, it + 1

        init = (acc, state, state.cell, jnp.zeros_like(state.active), 0)
        (rv, hits), final, last_cell, ended, _ = jax.lax.while_loop(cond, body, init)
        rv = _check_walk_ended(rv, final.active)
        # only rays whose walk reached their end cell record a hit there
        hit_flat = flat_index(last_cell, ends_inside & ended)
        hits = hits.at[hit_flat].add(1, mode="promise_in_bounds")
        return (rv, hits), None

    (rv, hits), _ = _checks.scan(chunk_body, acc0, (o_c, d_c, l_c, h_c, u_c))
    visits = jnp.round(rv.imag[:n_cells]).astype(jnp.int32)
    return rv.real[:n_cells], visits, hits[:n_cells]


@_checks.checked_jit
def _accumulate(
    spec: GridSpec,
    origins,
    directions,
    ranges,
    kind,
    r_max,
    *,
    chunk_size: int,
    block: int,
    sub_as_hit: bool,
):
    """JAX path of :func:`accumulate` (compiled; see :func:`_accumulate_blocks`)."""
    return _accumulate_blocks(
        spec,
        origins,
        directions,
        ranges,
        kind,
        r_max,
        chunk_size=chunk_size,
        block=block,
        sub_as_hit=sub_as_hit,
    )


def _accumulate_blocks(
    spec: GridSpec,
    origins,
    directions,
    ranges,
    kind,
    r_max,
    *,
    chunk_size: int,
    block: int,
    sub_as_hit: bool,
    tile=None,
):
    """``(R, M, H)`` of the rays: a ``lax.scan`` over blocks of ``block`` rays read with
    ``dynamic_slice`` (the last block is shifted back to stay in bounds and masks the rays
    an earlier block took), so temporaries are ``O(block + n_cells)``. ``tile = (row0,
    rows)``: only the grid rows ``[row0, row0 + rows)`` (see :func:`_walk_block`), arrays
    of shape ``(rows, *spec.shape[1:])``."""
    dtype = origins.dtype
    n = origins.shape[0]
    block = min(block, n)
    n_blocks = n_chunks_for(n, block)

    def block_body(carry, b):
        start = jnp.minimum(b * block, n - block)
        take = lambda x: jax.lax.dynamic_slice_in_dim(x, start, block)  # noqa: E731
        o, d, rng, k = take(origins), take(directions), take(ranges), take(kind)
        fresh = start + jnp.arange(block) >= b * block
        is_hit = (k == HIT) | ((k == SUB) & sub_as_hit)
        use = fresh & (is_hit | (k == SUP))
        trace = jnp.where(k == SUP, r_max.astype(dtype), rng)
        o, d, checked = check_rays(spec, o, d, jnp.where(use, trace, 0))
        trace = jnp.where(use, checked, trace)
        r_b, v_b, h_b = _walk_block(spec, o, d, trace, is_hit, use, chunk_size, tile)
        r, v, h = carry
        return (r + r_b, v + v_b, h + h_b), None

    shape = spec.shape if tile is None else (tile[1], *spec.shape[1:])
    n_cells = math.prod(shape)
    init = (jnp.zeros(n_cells, dtype), jnp.zeros(n_cells, jnp.int32), jnp.zeros(n_cells, jnp.int32))
    (r, v, h), _ = _checks.scan(block_body, init, jnp.arange(n_blocks))
    return r.reshape(shape), (v - h).reshape(shape), h.reshape(shape)


@functools.partial(jax.jit, static_argnames=("sub_as_hit", "threads"))
def _accumulate_native(spec, origins, directions, ranges, kind, r_max, *, sub_as_hit, threads):
    return _native.accumulate(spec, origins, directions, ranges, kind, r_max, sub_as_hit, threads)


def _accumulate_args(spec: GridSpec, rays: RayBatch, sub_rays: str, chunk_size: int):
    """The argument checks of :func:`accumulate` and its flat ``[n]`` ray arrays in the
    common float dtype: ``(origins, directions, ranges, kind, r_max)``."""
    if not isinstance(spec, GridSpec):
        raise ValueError(f"spec must be a GridSpec, got {type(spec).__name__}")
    if not isinstance(rays, RayBatch):
        raise ValueError(f"rays must be a RayBatch, got {type(rays).__name__}")
    if rays.dim != spec.dim:
        raise ValueError(f"rays are {rays.dim}-D but spec is a {spec.dim}-D grid")
    if sub_rays not in ("ignore", "hit"):
        raise ValueError(f"sub_rays must be 'ignore' or 'hit', got {sub_rays!r}")
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size <= 0:
        raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}")
    flat = rays.flatten()
    if flat.ranges.shape[0] == 0:
        raise ValueError("rays is empty")
    # canonical first: float64 NumPy rays without x64 are float32 rays, with no warning
    dtype = jnp.result_type(jax.dtypes.canonicalize_dtype(flat.origins.dtype), spec.origin.dtype)
    return (
        flat.origins.astype(dtype),
        flat.directions.astype(dtype),
        flat.ranges.astype(dtype),
        flat.kind,
        jnp.asarray(flat.r_max, dtype),
    )


def accumulate(
    spec: GridSpec,
    rays: RayBatch,
    *,
    chunk_size: int = 1024,
    sub_rays: Literal["ignore", "hit"] = "ignore",
    backend: str = "auto",
    threads: int | None = None,
) -> GridStats:
    """Per-cell hit counts H, miss counts M and travelled lengths R of a ray batch.

    HIT rays are traced to their range: every cell before the reflection cell gets a miss,
    the reflection cell a hit (if the endpoint lies inside the grid), and every traversed
    cell the distance travelled inside it (Eq. 7.10's denominator). SUP rays (no return)
    count as misses up to ``r_max``. SUB rays contribute nothing by default; with
    ``sub_rays="hit"`` they are treated as hits at their recorded range.

    Memory besides the rays themselves: the native kernel needs ``threads`` private
    accumulators (``O(threads * n_cells)``) and nothing per ray; the JAX path scans over
    blocks of 65 536 rays, each sorted by expected cell count, split into chunks of
    ``chunk_size`` and walked until its longest ray ends (``O(block + n_cells)``), so no
    ray is truncated. Every walk is bounded by :func:`walk_bound`; non-finite origins or
    directions and NaN or negative traced lengths raise (``eqx.error_if`` on the JAX
    path, an ``XlaRuntimeError`` from the kernel), eagerly and under ``jit``.

    Args:
        spec: the grid; its dimension must match the rays'.
        rays: any batch shape.
        chunk_size: rays walked together by the JAX path (static).
        sub_rays: ``"ignore"`` or ``"hit"``.
        backend: ``"auto"`` (native C++ walk when built, else JAX with one warning),
            ``"native"`` or ``"jax"``; see :mod:`lidarjax.raytrace._native`. Both give the
            same counts (up to sliver segments at the walk tolerance, see the README);
            lengths agree to round-off.
        threads: native worker threads, each with private accumulators merged at the end
            (default: all cores). Ignored by the JAX path.

    Returns:
        :class:`GridStats` with arrays of shape ``spec.shape``. Counts are exact integers;
        lengths are summed in the rays' float dtype.
    """
    args = _accumulate_args(spec, rays, sub_rays, chunk_size)
    threads = _native.check_threads(threads)
    _native.check_backend(backend)
    n = args[2].shape[0]
    if _native.resolve(backend) == "native":
        lengths, misses, hits = _accumulate_native(
            spec, *args, sub_as_hit=sub_rays == "hit", threads=threads
        )
    else:
        lengths, misses, hits = _accumulate(
            spec,
            *args,
            chunk_size=min(chunk_size, n),
            block=max(_BLOCK_RAYS, chunk_size),
            sub_as_hit=sub_rays == "hit",
        )
    return GridStats(spec=spec, hits=hits, misses=misses, lengths=lengths)


__all__ = [
    "GridSpec",
    "GridStats",
    "Traversal",
    "traverse",
    "traverse_rays",
    "max_cells_for",
    "accumulate",
    "expected_cell_count",
    "RayFold",
    "CellTerm",
    "fold_traversal",
    "fold_rays",
    "gather",
]
