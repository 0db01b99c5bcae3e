"""Vectorised NumPy reference for :func:`lidarjax.raytrace.accumulate`.

The same exact grid walk as the JAX implementation (Amanatides & Woo style, with the
parameter of the next boundary crossing recomputed from the integer cell index at every
step and coinciding crossings taken together), written as plain NumPy over all rays of a
chunk at once. It serves two purposes in ``benchmarks/raytrace.py``: an independent
check of the JAX results and a baseline for the throughput numbers.

Every step works on the rays that are still walking: the per-axis state lives in 1-D
arrays (one per axis, which is much faster in NumPy than reductions over a short trailing
axis), finished rays are masked and the arrays are compacted once enough rays are done.
The visited cells of all steps are buffered and scattered into the grid with
``np.bincount`` whenever the buffer is full, so memory is bounded by ``chunk_size`` and
``flush_size`` (plus the output grids), not by the total number of visited cells.

Arithmetic is done in the floating dtype of the inputs (float32 or float64) with the same
formulas as the JAX walk, so the hit and miss counts agree exactly; only the summation
order of the travelled lengths differs (they are summed in float64 here).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = ["accumulate_numpy"]


def _setup(origin, resolution, shape, o, d, length):
    """Clip rays to the grid box and find their first cells.

    Args:
        origin: ``[dim]`` grid lower corner.
        resolution: cell size (scalar of the working dtype).
        shape: cells per axis.
        o: per-axis list of ``[m]`` ray origins.
        d: per-axis list of ``[m]`` ray directions (any length, normalised here).
        length: ``[m]`` ray lengths (``inf`` allowed).

    Returns:
        ``(d, t0, t1, tol, cell, active)``: unit directions (per-axis list), start and end
        parameters of the clipped ray, the per-ray tolerance, the first cell (per-axis
        list of int64) and whether the ray visits any cell.
    """
    dim = len(shape)
    dtype = length.dtype
    inf = dtype.type(np.inf)
    sq = d[0] * d[0]
    for k in range(1, dim):
        sq = sq + d[k] * d[k]
    norm = np.sqrt(sq)
    nz = norm > 0
    safe_norm = np.where(nz, norm, dtype.type(1))
    d = [dk / safe_norm for dk in d]
    length = np.where(nz, length, dtype.type(0))

    t_near, t_far, inside = [], [], []
    for k in range(dim):
        lo = origin[k]
        hi = origin[k] + dtype.type(shape[k]) * resolution
        moving = d[k] != 0
        d_safe = np.where(moving, d[k], dtype.type(1))
        ta = (lo - o[k]) / d_safe
        tb = (hi - o[k]) / d_safe
        ins = (o[k] >= lo) & (o[k] <= hi)
        t_near.append(np.where(moving, np.minimum(ta, tb), np.where(ins, -inf, inf)))
        t_far.append(np.where(moving, np.maximum(ta, tb), np.where(ins, inf, -inf)))
        inside.append(ins)
    t_enter = t_near[0]
    t_exit = t_far[0]
    starts_inside = inside[0]
    for k in range(1, dim):
        t_enter = np.maximum(t_enter, t_near[k])
        t_exit = np.minimum(t_exit, t_far[k])
        starts_inside = starts_inside & inside[k]
    t0 = np.maximum(t_enter, dtype.type(0))
    t1 = np.minimum(length, t_exit)
    active = (t0 < t1) | ((length == 0) & starts_inside)
    t1 = np.where(active, t1, t0)
    t0 = np.where(np.isfinite(t0), t0, dtype.type(0))
    t1 = np.where(np.isfinite(t1), t1, t0)

    # The entry axis is the first axis whose near-slab parameter is the maximum (argmax).
    entry_axis = np.full(t0.shape, dim, dtype=np.int64)
    for k in reversed(range(dim)):
        entry_axis = np.where(t_near[k] == t_enter, k, entry_axis)
    entered = t_enter > 0
    cell = []
    for k in range(dim):
        rel = (o[k] + t0 * d[k] - origin[k]) / resolution
        c = np.where(d[k] < 0, np.ceil(rel) - 1, np.floor(rel))
        face = np.where(d[k] > 0, dtype.type(0), dtype.type(shape[k] - 1))
        c = np.where(entered & (entry_axis == k), face, c)
        c = np.where(np.isfinite(c), c, dtype.type(0))
        cell.append(np.clip(c, 0, shape[k] - 1).astype(np.int64))
    tol = dtype.type(32) * np.finfo(dtype).eps * (t1 + resolution)
    return d, t0, t1, tol, cell, active


def accumulate_numpy(
    origin: Sequence[float] | np.ndarray,
    resolution: float,
    shape: Sequence[int],
    origins: np.ndarray,
    directions: np.ndarray,
    lengths: np.ndarray,
    is_hit: np.ndarray,
    use: np.ndarray,
    *,
    chunk_size: int = 1 << 17,
    flush_size: int = 1 << 22,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-cell hit counts, miss counts and travelled lengths of a batch of rays.

    Semantics of :func:`lidarjax.raytrace.accumulate`: each used ray
    ``origins + t * directions / |directions|``, ``t`` in ``[0, lengths]``, is clipped to the
    grid box ``[origin, origin + shape * resolution)`` and walked cell by cell. Every
    traversed cell gets the exact length travelled inside it and a miss, except the
    ray's last cell, which gets a hit instead when ``is_hit`` and the ray's end lies inside
    the grid. Rays with ``use == False`` contribute nothing.

    Args:
        origin: ``[dim]`` world coordinates (m) of the grid's lower corner, ``dim`` 2 or 3.
        resolution: cell edge length (m).
        shape: cells per axis.
        origins: ``[n dim]`` ray start points (m).
        directions: ``[n dim]`` ray directions (normalised internally).
        lengths: ``[n]`` ray lengths (m), ``inf`` to trace to the grid border.
        is_hit: ``[n]`` bool, whether the ray ends in a reflection.
        use: ``[n]`` bool, whether the ray is traced at all.
        chunk_size: rays set up and walked together.
        flush_size: visited cells buffered before they are scattered into the grid.

    Returns:
        ``(hits, misses, lengths)`` of shape ``shape``: int64, int64 and float64. The walk
        runs in the floating dtype of ``origins``/``directions``/``lengths``; the lengths
        are summed in float64.

    Raises:
        ValueError: on inconsistent shapes or invalid grid parameters.
    """
    shape = tuple(int(s) for s in shape)
    dim = len(shape)
    if dim not in (2, 3) or any(s <= 0 for s in shape):
        raise ValueError(f"shape must be 2 or 3 positive ints, got {shape}")
    origins = np.asarray(origins)
    directions = np.asarray(directions)
    lengths = np.asarray(lengths)
    dtype = np.result_type(origins.dtype, directions.dtype, lengths.dtype, np.float32)
    n = lengths.shape[0]
    if origins.shape != (n, dim) or directions.shape != (n, dim):
        raise ValueError(
            f"origins and directions must have shape ({n}, {dim}), got {origins.shape} and "
            f"{directions.shape}"
        )
    is_hit = np.asarray(is_hit, dtype=bool).reshape(n)
    use = np.asarray(use, dtype=bool).reshape(n)
    if not (np.isfinite(resolution) and resolution > 0):
        raise ValueError(f"resolution must be a positive finite number, got {resolution}")

    grid_origin = np.asarray(origin, dtype=dtype).reshape(dim)
    res = dtype.type(resolution)
    inf = dtype.type(np.inf)
    n_cells = math.prod(shape)
    strides = [math.prod(shape[k + 1 :]) for k in range(dim)]
    hits = np.zeros(n_cells, np.int64)
    misses = np.zeros(n_cells, np.int64)
    total = np.zeros(n_cells, np.float64)
    buf_idx: list[np.ndarray] = []
    buf_seg: list[np.ndarray] = []
    buf_hit: list[np.ndarray] = []
    buffered = 0

    def flush():
        nonlocal buffered
        if not buf_idx:
            return
        idx = np.concatenate(buf_idx)
        seg = np.concatenate(buf_seg)
        hit = np.concatenate(buf_hit)
        total[:] += np.bincount(idx, weights=seg, minlength=n_cells)
        hits[:] += np.bincount(idx[hit], minlength=n_cells)
        misses[:] += np.bincount(idx[~hit], minlength=n_cells)
        buf_idx.clear()
        buf_seg.clear()
        buf_hit.clear()
        buffered = 0

    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        for start in range(0, n, chunk_size):
            sl = slice(start, min(start + chunk_size, n))
            sel = use[sl]
            if not sel.any():
                continue
            o = [origins[sl, k][sel].astype(dtype) for k in range(dim)]
            d = [directions[sl, k][sel].astype(dtype) for k in range(dim)]
            length = lengths[sl][sel].astype(dtype)
            hit_ray = is_hit[sl][sel]
            d, t, t_end, tol, cell, active = _setup(grid_origin, res, shape, o, d, length)
            ends_inside = hit_ray & (t_end >= length - tol)

            # Keep only rays that walk. The boundary parameter of cell index c along axis k
            # is t_base_k + c * t_scale_k (inf for an axis the ray does not move along).
            keep = np.flatnonzero(active)
            t, t_end, tol, ends_inside = t[keep], t_end[keep], tol[keep], ends_inside[keep]
            cell = [x[keep] for x in cell]
            t_base, t_scale, step_dir = [], [], []
            for k in range(dim):
                dk = d[k][keep]
                moving = dk != 0
                up = dk > 0
                d_safe = np.where(moving, dk, dtype.type(1))
                offset = np.where(up, res, dtype.type(0))
                t_base.append(
                    np.where(moving, (grid_origin[k] + offset - o[k][keep]) / d_safe, inf)
                )
                t_scale.append(np.where(moving, res / d_safe, dtype.type(0)))
                step_dir.append(np.where(up, 1, -1) * moving)
            alive = np.ones(keep.shape[0], bool)
            n_alive = keep.shape[0]

            while n_alive:
                t_axis = [t_base[k] + cell[k].astype(dtype) * t_scale[k] for k in range(dim)]
                t_min = t_axis[0]
                for k in range(1, dim):
                    t_min = np.minimum(t_min, t_axis[k])
                last = t_min >= t_end - tol
                t_stop = np.where(last, t_end, t_min)
                seg = np.maximum(t_stop - t, dtype.type(0))
                valid = alive & ((seg > tol) | last)

                flat = cell[0] * strides[0]
                for k in range(1, dim):
                    flat = flat + cell[k] * strides[k]
                inside = np.ones_like(alive)
                thresh = t_min + tol
                for k in range(dim):
                    cell[k] = cell[k] + step_dir[k] * (t_axis[k] <= thresh)
                    inside &= (cell[k] >= 0) & (cell[k] < shape[k])
                ends_here = last | ~inside
                hit_here = ends_here & ends_inside

                v = np.flatnonzero(valid)
                buf_idx.append(flat[v])
                buf_seg.append(seg[v])
                buf_hit.append(hit_here[v])
                buffered += v.shape[0]
                if buffered >= flush_size:
                    flush()

                t = t_stop
                alive &= ~ends_here
                n_alive = int(np.count_nonzero(alive))
                if 0 < n_alive <= alive.shape[0] // 2:
                    a = np.flatnonzero(alive)
                    t_base = [x[a] for x in t_base]
                    t_scale = [x[a] for x in t_scale]
                    step_dir = [x[a] for x in step_dir]
                    cell = [x[a] for x in cell]
                    t, t_end, tol, ends_inside = t[a], t_end[a], tol[a], ends_inside[a]
                    alive = np.ones(a.shape[0], bool)
        flush()
    return hits.reshape(shape), misses.reshape(shape), total.reshape(shape)
