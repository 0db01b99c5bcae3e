"""Pole-landmark mapping and particle-filter localization (sections 12.4.2 and 12.4.3).

- **Mapping** (:func:`map_poles`): the local maps of a trajectory's segments yield pole
  landmarks in the world frame; two landmarks are the same pole if their square footprints
  (edge = estimated width) overlap. A sliding window keeps only landmarks seen at least
  ``c`` times in the last ``w`` local maps (:func:`sliding_window_filter`), and every
  cluster of overlapping squares is merged by score-weighted averaging of centres and widths
  (:func:`merge_poles`).
- **Localization**: :class:`PoleMeasurementModel` is the measurement model of Sec. 12.4.3,
  ``p(Lambda | X, L) = prod_k (N(||X lambda_k - l_n(k)||; sigma) + eps)`` with
  nearest-neighbour association ``n(k)``, for all particles and all online poles at once.
  Association uses :class:`PoleLookup`, a 2-D grid whose cells list every landmark that can
  be the nearest neighbour of a point in the cell, so one query is a gather of ``k``
  candidates instead of a k-d tree walk. Distances are clipped at ``d_max``, where the
  density has fallen to ``p_min`` (as in the authors' implementation), so landmarks farther
  than ``d_max`` need not be found.

Mapping bookkeeping is NumPy (irregular, once per local map); the measurement model is
pure JAX and runs inside :meth:`~lidarjax.localization.ParticleFilter.run`'s ``lax.scan``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import equinox as eqx
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..features import Poles

__all__ = [
    "PoleMap",
    "overlap_clusters",
    "merge_poles",
    "sliding_window_filter",
    "map_poles",
    "PoleLookup",
    "build_pole_lookup",
    "PoleMeasurementModel",
    "pad_poles",
    "segment_scans",
]


@dataclass(frozen=True)
class PoleMap:
    """A global pole-landmark map (NumPy).

    Attributes:
        xy: ``[L 2]`` landmark positions in the world frame (m).
        width_m: ``[L]`` footprint edge lengths (m).
        score: ``[L]`` mean pole scores of the merged detections.
        n_detections: ``[L]`` number of local-map detections merged into each landmark.
    """

    xy: np.ndarray
    width_m: np.ndarray
    score: np.ndarray
    n_detections: np.ndarray

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    def as_poles(self) -> Poles:
        return Poles(self.xy, self.width_m, self.score)


def _concat(poles: Sequence[Poles]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    if not poles:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0, int)
    for i, p in enumerate(poles):
        if not isinstance(p, Poles):
            raise ValueError(f"poles[{i}] must be a Poles, got {type(p).__name__}")
        if not (np.all(np.isfinite(p.xy)) and np.all(np.isfinite(p.width_m))):
            raise ValueError(f"poles[{i}] has non-finite positions or widths")
        if np.any(p.width_m < 0) or np.any(p.score < 0):
            raise ValueError(f"poles[{i}] has negative widths or scores")
    xy = np.concatenate([p.xy for p in poles]).reshape(-1, 2)
    w = np.concatenate([p.width_m for p in poles])
    s = np.concatenate([p.score for p in poles])
    src = np.concatenate([np.full(len(p), i) for i, p in enumerate(poles)]).astype(int)
    return xy, w, s, src


def _overlap_pairs(xy: np.ndarray, width: np.ndarray) -> np.ndarray:
    """Index pairs ``[m 2]`` (i < j) whose axis-aligned squares overlap."""
    if len(xy) < 2:
        return np.zeros((0, 2), int)
    reach = float(np.max(width)) * math.sqrt(2.0)
    pairs = cKDTree(xy).query_pairs(reach + 1e-12, output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros((0, 2), int)
    i, j = pairs[:, 0], pairs[:, 1]
    half = 0.5 * (width[i] + width[j])
    d = np.abs(xy[i] - xy[j])
    keep = (d[:, 0] < half) & (d[:, 1] < half)
    return pairs[keep]


def overlap_clusters(xy: ArrayLike, width_m: ArrayLike) -> np.ndarray:
    """Connected components of overlapping square footprints (section 12.4.2).

    Args:
        xy: ``[n 2]`` centres (m).
        width_m: ``[n]`` edge lengths (m); squares that merely touch do not overlap.

    Returns:
        ``[n]`` component label of every square (``0 .. n_components - 1``).
    """
    xy = np.asarray(xy, float).reshape(-1, 2)
    width = np.asarray(width_m, float).reshape(-1)
    if width.shape != (len(xy),):
        raise ValueError(f"width_m must have shape [{len(xy)}], got {width.shape}")
    n = len(xy)
    if n == 0:
        return np.zeros(0, int)
    pairs = _overlap_pairs(xy, width)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def merge_poles(poles: Sequence[Poles], *, min_detections: int = 1) -> PoleMap:
    """Merge pole detections whose footprints overlap into single landmarks.

    Each cluster of overlapping squares becomes one landmark at the score-weighted mean
    of the centres, with the score-weighted mean width and the mean score (section
    12.4.2). Clusters of fewer than ``min_detections`` detections are dropped.

    Args:
        poles: detections in the world frame (e.g. one :class:`Poles` per local map).
        min_detections: minimum cluster size.

    Returns:
        :class:`PoleMap`.
    """
    if not isinstance(min_detections, int) or min_detections < 1:
        raise ValueError(f"min_detections must be an int >= 1, got {min_detections!r}")
    xy, w, s, _ = _concat(poles)
    if len(xy) == 0:
        return PoleMap(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0, int))
    lab = overlap_clusters(xy, w)
    n_lab = int(lab.max()) + 1
    count = np.bincount(lab, minlength=n_lab)
    wt = np.maximum(s, 1e-12)
    tot = np.bincount(lab, wt, n_lab)
    mx = np.bincount(lab, wt * xy[:, 0], n_lab) / tot
    my = np.bincount(lab, wt * xy[:, 1], n_lab) / tot
    mw = np.bincount(lab, wt * w, n_lab) / tot
    ms = np.bincount(lab, s, n_lab) / count
    keep = count >= min_detections
    return PoleMap(np.stack([mx, my], -1)[keep], mw[keep], ms[keep], count[keep])


def sliding_window_filter(local_poles: Sequence[Poles], c: int = 2, w: int = 3) -> list[Poles]:
    """Keep a local map's landmark only if it was seen in at least ``c`` of the last ``w``
    local maps (itself included), correspondences by overlapping footprints (Sec. 12.4.2).

    Args:
        local_poles: per local map, poles in the world frame, in trajectory order.
        c: minimum number of sightings.
        w: window length in local maps (``c <= w``).

    Returns:
        The filtered poles of every local map.
    """
    if not (isinstance(c, int) and isinstance(w, int) and 1 <= c <= w):
        raise ValueError(f"need ints 1 <= c <= w, got c={c!r}, w={w!r}")
    out = []
    for t, cur in enumerate(local_poles):
        if not isinstance(cur, Poles):
            raise ValueError(f"local_poles[{t}] must be a Poles, got {type(cur).__name__}")
        if c == 1 or len(cur) == 0:
            out.append(cur)
            continue
        window = list(local_poles[max(0, t - w + 1) : t + 1])
        xy, wd, _, src = _concat(window)
        me = len(window) - 1
        pairs = _overlap_pairs(xy, wd)
        seen = [{me} for _ in range(len(cur))]
        offset = len(xy) - len(cur)
        for i, j in pairs:
            for a, b in ((i, j), (j, i)):
                if a >= offset and src[b] != me:
                    seen[a - offset].add(int(src[b]))
        keep = np.array([len(x) >= c for x in seen], bool)
        out.append(cur.take(keep))
    return out


def map_poles(
    local_poles: Sequence[Poles], *, c: int = 2, w: int = 3, min_detections: int = 1
) -> PoleMap:
    """Global landmark map from per-segment local maps (section 12.4.2): sliding-window
    filter of dynamic objects, then merging of overlapping footprints.

    Args:
        local_poles: per local map, poles in the world frame, in trajectory order.
        c, w: sliding-window parameters (seen ``c`` times in the last ``w`` local maps).
        min_detections: minimum detections per merged landmark.
    """
    return merge_poles(sliding_window_filter(local_poles, c, w), min_detections=min_detections)


# --------------------------------------------------------------------------------------
# Vectorised nearest-neighbour association and the measurement model
# --------------------------------------------------------------------------------------


class PoleLookup(eqx.Module):
    """Candidate table for nearest-landmark queries.

    Attributes:
        landmarks: ``[L 2]`` landmark positions (m).
        origin: ``[2]`` lower corner of the table's grid (m).
        cell_m: cell size (m).
        table: ``[nx ny k]`` landmark indices per cell, ``-1`` padded. A cell lists every
            landmark within ``min(d_c, d_max) + 2 h`` of its centre, where ``d_c`` is the
            centre's nearest-landmark distance and ``h`` the half diagonal: this contains
            the nearest landmark of every point of the cell whose nearest distance is below
            ``d_max``.
        cand_x, cand_y: ``[k nx*ny]`` the candidates' coordinates, slot-major (padding far
            away), so a query is ``k`` scalar gathers and element-wise minima.
        d_max: distances are clipped here (m); points off the table get ``d_max``.
        n_truncated: number of cells whose candidate list exceeded ``k`` (0 means every
            query is exact).
    """

    landmarks: Float[Array, "L 2"]
    origin: Float[Array, " 2"]
    cell_m: float = eqx.field(static=True)
    table: Int[Array, "nx ny k"]
    cand_x: Float[Array, "k c"]
    cand_y: Float[Array, "k c"]
    d_max: Float[Array, ""]
    n_truncated: int = eqx.field(static=True)

    def nearest_distance_xy(
        self, x: Float[Array, "*b"], y: Float[Array, "*b"]
    ) -> Float[Array, "*b"]:
        """``min(min_l ||(x, y) - l||, d_max)`` for every point given as coordinate arrays."""
        nx, ny, k = self.table.shape
        i = jnp.floor((x - self.origin[0]) / self.cell_m).astype(jnp.int32)
        j = jnp.floor((y - self.origin[1]) / self.cell_m).astype(jnp.int32)
        inside = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
        flat = jnp.clip(i, 0, nx - 1) * ny + jnp.clip(j, 0, ny - 1)
        best = None
        for slot in range(k):  # static, small: element-wise minima vectorise well on CPU
            d2 = (self.cand_x[slot][flat] - x) ** 2 + (self.cand_y[slot][flat] - y) ** 2
            best = d2 if best is None else jnp.minimum(best, d2)
        d = jnp.sqrt(jnp.minimum(best, self.d_max**2))
        return jnp.where(inside, d, self.d_max)

    def nearest_distance(self, points: Float[Array, "*b 2"]) -> Float[Array, "*b"]:
        """``min(min_l ||p - l||, d_max)`` for every point."""
        points = jnp.asarray(points, self.landmarks.dtype)
        return self.nearest_distance_xy(points[..., 0], points[..., 1])


def build_pole_lookup(
    landmarks_xy: ArrayLike, d_max_m: float, *, cell_m: float = 1.0, k: int = 8
) -> PoleLookup:
    """Build a :class:`PoleLookup` over the landmarks' bounding box grown by ``d_max_m``.

    Args:
        landmarks_xy: ``[L 2]`` landmark positions (m), ``L >= 1``.
        d_max_m: clipping distance (m), > 0.
        cell_m: table cell size (m).
        k: candidates per cell (static); see ``n_truncated``.
    """
    xy = np.asarray(landmarks_xy, float)
    if xy.ndim != 2 or xy.shape[1] != 2 or len(xy) == 0:
        raise ValueError(f"landmarks_xy must have shape [L >= 1, 2], got {xy.shape}")
    if not np.all(np.isfinite(xy)):
        raise ValueError("landmarks_xy must be finite")
    if not (d_max_m > 0 and math.isfinite(d_max_m)):
        raise ValueError(f"d_max_m must be finite and > 0, got {d_max_m!r}")
    if not (cell_m > 0 and math.isfinite(cell_m)):
        raise ValueError(f"cell_m must be finite and > 0, got {cell_m!r}")
    if not isinstance(k, int) or k < 1:
        raise ValueError(f"k must be a positive int, got {k!r}")
    lo = np.floor((xy.min(0) - d_max_m) / cell_m) * cell_m - cell_m
    hi = xy.max(0) + d_max_m + cell_m
    nx, ny = (np.ceil((hi - lo) / cell_m).astype(int) + 1).tolist()
    cx, cy = np.meshgrid(
        lo[0] + (np.arange(nx) + 0.5) * cell_m,
        lo[1] + (np.arange(ny) + 0.5) * cell_m,
        indexing="ij",
    )
    centres = np.stack([cx.ravel(), cy.ravel()], -1)
    tree = cKDTree(xy)
    h = 0.5 * math.sqrt(2.0) * cell_m
    d_c, _ = tree.query(centres, k=1)
    radius = np.minimum(d_c, d_max_m) + 2 * h
    kq = min(k + 1, len(xy))
    d, idx = tree.query(centres, k=kq)
    d = d.reshape(len(centres), kq)
    idx = idx.reshape(len(centres), kq)
    within = d <= radius[:, None] + 1e-9
    n_trunc = int(np.sum(np.sum(within, 1) > k)) if kq > k else 0
    idx = np.where(within, idx, -1)[:, :k]
    if idx.shape[1] < k:
        idx = np.concatenate([idx, np.full((len(idx), k - idx.shape[1]), -1)], 1)
    table = idx.reshape(nx, ny, k).astype(np.int32)
    far = 1e6 + float(np.max(np.abs(xy)))  # padding: beyond d_max from every query on the table
    cand = np.where((idx >= 0)[..., None], xy[np.maximum(idx, 0)], far)  # [cells k 2]
    dtype = jnp.result_type(float)
    return PoleLookup(
        jnp.asarray(xy, dtype),
        jnp.asarray(lo, dtype),
        float(cell_m),
        jnp.asarray(table),
        jnp.asarray(cand[..., 0].T, dtype),
        jnp.asarray(cand[..., 1].T, dtype),
        jnp.asarray(d_max_m, dtype),
        n_trunc,
    )


def _d_max(var: float, p_min: float) -> float:
    arg = math.sqrt(2 * math.pi * var) * p_min
    if not (0 < arg < 1):
        bound = 1 / math.sqrt(2 * math.pi * var)
        raise ValueError(f"p_min must lie in (0, 1 / sqrt(2 pi var)) = (0, {bound:.4g})")
    return math.sqrt(-2.0 * var * math.log(arg))


class PoleMeasurementModel(eqx.Module):
    """Measurement model of Sec. 12.4.3 for :class:`~lidarjax.localization.ParticleFilter`.

    ``log p(Lambda | X, L) = sum_k m_k log(N(min(d_k, d_max); 0, var) + eps)`` with
    ``d_k = min_n ||X lambda_k - l_n||`` (nearest-neighbour association), ``m_k`` the mask
    of valid online poles and ``N`` the 1-D normal density of variance ``var``.

    Call as ``model(particles, (poles_xy [K 2], mask [K]))`` with online poles in the robot
    frame; returns ``[n]`` log-likelihoods. Cost: ``n K k`` distance evaluations.

    Attributes:
        lookup: the landmark table.
        var_m2: landmark position variance ``sigma`` of the dissertation (m², 1.0 there).
        eps: the constant addend for poles that are not in the map (0.1 there).
    """

    lookup: PoleLookup
    var_m2: Float[Array, ""]
    eps: Float[Array, ""]

    def __init__(
        self,
        landmarks_xy: ArrayLike,
        *,
        var_m2: float = 1.0,
        eps: float = 0.1,
        p_min: float = 0.01,
        cell_m: float = 1.0,
        k: int = 8,
    ):
        if not (var_m2 > 0 and math.isfinite(var_m2)):
            raise ValueError(f"var_m2 must be finite and > 0, got {var_m2!r}")
        if not (eps >= 0 and math.isfinite(eps)):
            raise ValueError(f"eps must be finite and >= 0, got {eps!r}")
        self.lookup = build_pole_lookup(landmarks_xy, _d_max(var_m2, p_min), cell_m=cell_m, k=k)
        dtype = jnp.result_type(float)
        self.var_m2 = jnp.asarray(var_m2, dtype)
        self.eps = jnp.asarray(eps, dtype)

    @property
    def d_max_m(self) -> float:
        return float(self.lookup.d_max)

    def __call__(
        self, particles: jaxlie.SE2, z: tuple[Float[Array, "K 2"], Bool[Array, " K"]]
    ) -> Float[Array, " n"]:
        poles_xy, mask = z
        dtype = self.lookup.landmarks.dtype
        poles_xy = jnp.asarray(poles_xy, dtype)
        prm = particles.parameters().astype(dtype)  # [n 4]: cos, sin, x, y (jaxlie SE2)
        c, s, x, y = (prm[:, i : i + 1] for i in range(4))
        px, py = poles_xy[:, 0], poles_xy[:, 1]
        d = self.lookup.nearest_distance_xy(x + c * px - s * py, y + s * px + c * py)  # [n K]
        dens = jnp.exp(-0.5 * d * d / self.var_m2) / jnp.sqrt(2 * jnp.pi * self.var_m2)
        return jnp.sum(jnp.where(mask, jnp.log(dens + self.eps), 0.0), axis=-1)


def pole_log_likelihood_reference(
    particles_xy_yaw: np.ndarray,
    poles_xy: np.ndarray,
    landmarks_xy: np.ndarray,
    *,
    var_m2: float = 1.0,
    eps: float = 0.1,
    p_min: float = 0.01,
) -> np.ndarray:
    """Plain NumPy brute force of :class:`PoleMeasurementModel` (all pairs, no table)."""
    d_max = _d_max(var_m2, p_min)
    x, y, t = (np.asarray(particles_xy_yaw, float)[:, i] for i in range(3))
    c, s = np.cos(t), np.sin(t)
    px, py = poles_xy[:, 0], poles_xy[:, 1]
    wx = x[:, None] + c[:, None] * px - s[:, None] * py
    wy = y[:, None] + s[:, None] * px + c[:, None] * py
    d = np.sqrt(
        (wx[..., None] - landmarks_xy[:, 0]) ** 2 + (wy[..., None] - landmarks_xy[:, 1]) ** 2
    ).min(-1)
    d = np.minimum(d, d_max)
    dens = np.exp(-0.5 * d * d / var_m2) / np.sqrt(2 * np.pi * var_m2)
    return np.log(dens + eps).sum(-1)


def pad_poles(poles_robot: Sequence[Poles | None], k: int) -> tuple[np.ndarray, np.ndarray]:
    """Stack per-step online poles into static-shape arrays for ``lax.scan``.

    Args:
        poles_robot: per filter step, poles in the robot frame (``None`` or empty for no
            measurement).
        k: padded pole count; steps with more poles keep the ``k`` highest-scoring ones.

    Returns:
        ``(xy [T k 2], mask [T k])``.
    """
    if not isinstance(k, int) or k < 1:
        raise ValueError(f"k must be a positive int, got {k!r}")
    xy = np.zeros((len(poles_robot), k, 2))
    mask = np.zeros((len(poles_robot), k), bool)
    for t, p in enumerate(poles_robot):
        if p is None or len(p) == 0:
            continue
        order = np.argsort(-p.score, kind="stable")[:k]
        xy[t, : len(order)] = p.xy[order]
        mask[t, : len(order)] = True
    return xy, mask


def segment_scans(
    xy: ArrayLike, segment_m: float = 1.5, *, max_scans: int | None = None
) -> list[np.ndarray]:
    """Split a trajectory into segments of equal length for local maps (section 12.4.2).

    Segment ``i`` holds the scans whose arc length lies in ``[i L, (i + 1) L)``; the last,
    incomplete segment is dropped. With ``max_scans``, a segment with more scans (e.g. the
    vehicle waiting at a light) keeps ``max_scans`` of them, evenly spread and always
    including its last scan.

    Args:
        xy: ``[N 2]`` positions (m) of the scans in trajectory order.
        segment_m: segment length ``L`` (m).
        max_scans: optional cap on the scans per segment.

    Returns:
        Per segment, the increasing scan indices (the last one is the segment's end, where
        its local map becomes available).
    """
    xy = np.asarray(xy, float)
    if xy.ndim != 2 or xy.shape[1] != 2 or not np.all(np.isfinite(xy)):
        raise ValueError(f"xy must be finite with shape [N, 2], got {xy.shape}")
    if not (segment_m > 0 and math.isfinite(segment_m)):
        raise ValueError(f"segment_m must be finite and > 0, got {segment_m!r}")
    if max_scans is not None and (not isinstance(max_scans, int) or max_scans < 1):
        raise ValueError(f"max_scans must be a positive int or None, got {max_scans!r}")
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    seg = np.floor(arc / segment_m).astype(int)
    out = []
    for i in range(int(seg[-1])):  # the segment containing the last scan is incomplete
        idx = np.flatnonzero(seg == i)
        if len(idx) == 0:
            continue
        if max_scans is not None and len(idx) > max_scans:
            pick = np.round(np.linspace(0, len(idx) - 1, max_scans)).astype(int)
            idx = idx[np.unique(pick)]
        out.append(idx)
    return out
