"""PPE's view of an organized scan (dissertation ch. 11): what the fast greedy loop
(:mod:`._ppe`) and the reference (:mod:`._ppe_reference`) share before they cluster.

- Input checks: :func:`_check_scan` (the organized scan) and :func:`_check_params` (the
  stopping criteria and the outlier filter).
- The scan graph: the 4-neighbours of every ray that pass the geometric outlier filter
  ``d`` (:func:`_neighbours`).
- The 17 valid tetrominoes (Figure 11.2, :data:`TETROMINOES`), their placements in the scan
  (:func:`_tetromino_table`) and their creation costs ``e_crt`` (:func:`_tetromino_costs`,
  one batched JAX call).
- The greedy order: increments are compared at float32 resolution (:func:`_q`,
  :func:`_qs`), then by step kind and ray / plane index.

Conventions: organized scans are ``points [H, W, 3]`` in the sensor frame (sensor at the
origin, metres), NaN rows for no-return rays; rays are addressed by their flat index
``row * W + column``.
"""

from __future__ import annotations

import dataclasses
import math
import struct

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..raytrace import pad_to_chunks, unchunk
from ._plane_stats import _points_stats, _stats_error

__all__ = ["TETROMINOES"]

# --------------------------------------------------------------------------------------
# The greedy order
# --------------------------------------------------------------------------------------


def _q(cost):
    """The greedy order compares error increments at float32 resolution (7 digits), then
    by (kind, ray / plane index). Increments that agree to ~1e-12 do occur (tetrominoes
    sharing 3 rays across a plane edge), and float64 rounding (which differs between
    formulas and between JAX and NumPy) must not decide between them."""
    return np.asarray(cost, dtype=np.float64).astype(np.float32).astype(np.float64)


_F32 = struct.Struct("f")


def _qs(cost: float) -> float:
    """:func:`_q` of one Python float (round to nearest float32, ~0.3 µs)."""
    return _F32.unpack(_F32.pack(cost))[0]


# --------------------------------------------------------------------------------------
# Tetrominoes (Figure 11.2)
# --------------------------------------------------------------------------------------


def _make_tetrominoes() -> np.ndarray:
    shapes: set[tuple[tuple[int, int], ...]] = set()
    frontier = {((0, 0),)}
    for _ in range(3):
        grown = set()
        for cells in frontier:
            for r, c in cells:
                for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                    cell = (r + dr, c + dc)
                    if cell not in cells:
                        grown.add(tuple(sorted(cells + (cell,))))
        frontier = grown
    for cells in frontier:
        r0 = min(r for r, _ in cells)
        c0 = min(c for _, c in cells)
        norm = tuple(sorted((r - r0, c - c0) for r, c in cells))
        rows = {r for r, _ in norm}
        cols = {c for _, c in norm}
        if len(rows) == 1 or len(cols) == 1:  # the I-tetromino: collinear, ambiguous
            continue
        shapes.add(norm)
    out = np.array(sorted(shapes), dtype=np.int64)
    assert out.shape == (17, 4, 2)
    return out


TETROMINOES: np.ndarray = _make_tetrominoes()
"""``[17, 4, 2]`` (row, column) offsets of the 17 valid tetrominoes (one O, four T, four
S/Z, eight L/J), relative to the top-left corner of their bounding box."""

# Internal 4-neighbour pairs of each tetromino: [17, n_pairs<=4, 2] (padded with -1).
_TET_PAIRS = []
for _cells in TETROMINOES:
    _pairs = [
        (i, j)
        for i in range(4)
        for j in range(i + 1, 4)
        if abs(_cells[i, 0] - _cells[j, 0]) + abs(_cells[i, 1] - _cells[j, 1]) == 1
    ]
    _TET_PAIRS.append(_pairs + [(-1, -1)] * (4 - len(_pairs)))
_TET_PAIRS = np.array(_TET_PAIRS, dtype=np.int64)


# --------------------------------------------------------------------------------------
# Input checks
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Params:
    """Checked PPE parameters.

    Attributes:
        max_increment: ``e`` (m²); ``inf`` = no threshold.
        max_planes: ``J_max``; ``0`` = no limit.
        max_distance_m: ``d`` (m); ``inf`` = no outlier filter.
    """

    max_increment: float
    max_planes: int
    max_distance_m: float


def _check_scan(points) -> tuple[np.ndarray, np.ndarray]:
    """The organized scan as ``(points [H, W, 3] float64, valid [H, W])``.

    Raises:
        ValueError: If ``points`` is not a float ``[H, W, 3]`` scan of at least 2 x 2 rays,
            has a partly-NaN or inf point, no valid point, or a point at the origin.
    """
    pts = np.asarray(points)
    if pts.ndim != 3 or pts.shape[-1] != 3:
        raise ValueError(f"points must be an organized scan of shape [H, W, 3], got {pts.shape}")
    if pts.shape[0] < 2 or pts.shape[1] < 2:
        raise ValueError(f"points must be at least 2 x 2 rays, got {pts.shape[:2]}")
    if not np.issubdtype(pts.dtype, np.floating):
        raise ValueError(f"points must be floating point, got dtype {pts.dtype}")
    pts = pts.astype(np.float64)
    bad = np.isnan(pts).any(-1) != np.isnan(pts).all(-1)
    if bad.any():
        raise ValueError(
            f"points: {int(bad.sum())} points are partly NaN (a no-return point must be all NaN)"
        )
    if np.isinf(pts).any():
        raise ValueError("points must not contain inf (mark no-return rays with NaN)")
    valid = ~np.isnan(pts).any(-1)
    if not valid.any():
        raise ValueError("points: the scan has no valid (non-NaN) point")
    r = np.linalg.norm(np.where(valid[..., None], pts, 1.0), axis=-1)
    if (r[valid] <= 0).any():
        raise ValueError("points: some points lie at the sensor origin (range 0)")
    return pts, valid


def _check_params(max_increment, max_planes, max_distance_m, min_points) -> _Params:
    """``max_increment`` (``None``: no threshold), ``max_planes`` (``None``: no limit),
    ``max_distance_m`` (``None``: no filter) and ``min_points`` checked and normalised.

    Raises:
        ValueError: Naming the first parameter out of range.
    """
    if max_increment is None:
        inc = math.inf
    else:
        inc = float(max_increment)
        if not inc >= 0:
            raise ValueError(f"max_increment must be >= 0 (m²), got {max_increment}")
    if max_planes is None:
        jmax = 0
    else:
        if int(max_planes) != max_planes or max_planes < 1:
            raise ValueError(f"max_planes must be a positive integer, got {max_planes}")
        jmax = int(max_planes)
    if max_distance_m is None:
        dmax = math.inf
    else:
        dmax = float(max_distance_m)
        if not dmax > 0:
            raise ValueError(f"max_distance_m must be > 0 (m), got {max_distance_m}")
    if int(min_points) != min_points or min_points < 4:
        raise ValueError(f"min_points must be an integer >= 4, got {min_points}")
    return _Params(max_increment=inc, max_planes=jmax, max_distance_m=dmax)


def _check_inputs(points, max_increment, max_planes, max_distance_m, min_points):
    """:func:`_check_scan` then :func:`_check_params`: ``(points, valid, params)``."""
    pts, valid = _check_scan(points)
    return pts, valid, _check_params(max_increment, max_planes, max_distance_m, min_points)


# --------------------------------------------------------------------------------------
# The scan graph and the tetromino placements
# --------------------------------------------------------------------------------------


def _neighbours(pts: np.ndarray, valid: np.ndarray, max_distance_m: float) -> np.ndarray:
    """``[K, 4]`` flat indices of the up/down/left/right neighbours that pass the outlier
    filter (both valid, distance <= d), ``-1`` otherwise."""
    H, W = valid.shape
    idx = np.arange(H * W).reshape(H, W)
    nbr = np.full((H, W, 4), -1, dtype=np.int64)
    with np.errstate(invalid="ignore"):
        dv = np.linalg.norm(pts[1:] - pts[:-1], axis=-1)  # [H-1, W]
        dh = np.linalg.norm(pts[:, 1:] - pts[:, :-1], axis=-1)  # [H, W-1]
    ev = valid[1:] & valid[:-1] & (dv <= max_distance_m)
    eh = valid[:, 1:] & valid[:, :-1] & (dh <= max_distance_m)
    nbr[1:, :, 0] = np.where(ev, idx[:-1], -1)  # up
    nbr[:-1, :, 1] = np.where(ev, idx[1:], -1)  # down
    nbr[:, 1:, 2] = np.where(eh, idx[:, :-1], -1)  # left
    nbr[:, :-1, 3] = np.where(eh, idx[:, 1:], -1)  # right
    return nbr.reshape(H * W, 4)


def _tetromino_table(valid: np.ndarray, nbr: np.ndarray):
    """All placements of the 17 tetrominoes: anchors ``[T]``, shape ids ``[T]``, cells
    ``[T, 4]`` (flat indices), restricted to placements inside the scan whose cells are
    valid and whose internal neighbour pairs all pass the outlier filter."""
    H, W = valid.shape
    anchors, shape_ids, cells = [], [], []
    for s, offs in enumerate(TETROMINOES):
        hr, wc = offs[:, 0].max(), offs[:, 1].max()
        rr, cc = np.meshgrid(np.arange(H - hr), np.arange(W - wc), indexing="ij")
        rr, cc = rr.ravel(), cc.ravel()
        cl = (rr[:, None] + offs[None, :, 0]) * W + (cc[:, None] + offs[None, :, 1])
        ok = valid.ravel()[cl].all(axis=1)
        for i, j in _TET_PAIRS[s]:
            if i < 0:
                continue
            # j is a 4-neighbour of i: check that the edge survived the filter
            ok &= (nbr[cl[:, i]] == cl[:, j, None]).any(axis=1)
        anchors.append((rr * W + cc)[ok])
        shape_ids.append(np.full(ok.sum(), s, dtype=np.int64))
        cells.append(cl[ok])
    return np.concatenate(anchors), np.concatenate(shape_ids), np.concatenate(cells).reshape(-1, 4)


_TET_CHUNK = 1 << 15  # tetromino placements per lax.map chunk (bounds the memory)


@jax.jit
def _tetromino_costs_jax(points: Array, cells: Array) -> Array:
    """``e_crt`` of ``cells [n_chunks, chunk, 4]`` (flat ray indices into ``points [K, 3]``)."""

    def chunk(c):
        W, m, C = _points_stats(points[c], xp=jnp)
        return _stats_error(W, m, C, xp=jnp)

    return jax.lax.map(chunk, cells)


def _tetromino_costs(pts_flat: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """``e_crt`` of every tetromino placement: one batched JAX call, chunked with
    ``lax.map`` (float64 NumPy when x64 is off, so the greedy order does not depend on
    JAX's precision)."""
    n = cells.shape[0]
    if n == 0:
        return np.zeros(0)
    if jax.config.jax_enable_x64:
        # host-side padding (NumPy in, NumPy out): one compilation per number of chunks
        padded = pad_to_chunks(np.asarray(cells, np.int64), _TET_CHUNK, fill="edge")
        out = _tetromino_costs_jax(jnp.asarray(pts_flat), jnp.asarray(padded))
        return unchunk(np.asarray(out), n)
    out = np.empty(n)
    for i in range(0, n, _TET_CHUNK):
        W, m, C = _points_stats(pts_flat[cells[i : i + _TET_CHUNK]])
        out[i : i + _TET_CHUNK] = _stats_error(W, m, C)
    return out
