"""Plane-extraction baselines for organized 3-D scans, dissertation ch. 11 (Table 11.1).

* :func:`msac_planes` -- iterative RANSAC with MSAC scoring (Torr & Zisserman 2000): extract
  the best plane of the remaining points, remove its inliers, repeat.
* :func:`peac_planes` -- PEAC-style agglomerative hierarchical clustering of image blocks
  (after Feng, Taguchi & Kamat, ICRA 2014) followed by pixel-level refinement.

Conventions: an organized scan is ``points [H, W, 3]`` (float, metres, sensor frame with the
sensor at the origin); a pixel whose coordinates are not all finite (NaN rows) is a missing
return. Both functions return ``labels [H, W]`` (``int64``): ``-1`` for points not assigned to
any plane (including missing returns) and ``0 .. J-1`` for the ``J`` extracted planes, numbered
by decreasing point count (ties by extraction order). Plain NumPy (plus ``scipy.ndimage`` for
connected components); deterministic given the arguments (and ``seed`` for MSAC).
"""

from __future__ import annotations

import heapq

import numpy as np
from scipy import ndimage

# |n| of the (unnormalised) normal of a sampled triple, relative to the product of its two edge
# lengths (i.e. |sin| of the angle at the first point), below which the triple is degenerate.
_DEGENERATE_SIN = 1e-6
# Number of (hypothesis, point) pairs scored per chunk in MSAC (bounds the temporary memory to
# about 4 * _MSAC_CHUNK_ELEMS bytes).
_MSAC_CHUNK_ELEMS = 1 << 22


# --------------------------------------------------------------------------------------
# validation helpers


def _check_scan(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(points as float64 [H, W, 3], finite mask [H, W])`` or raise ``ValueError``."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise ValueError(f"points must have shape [H, W, 3], got {pts.shape}")
    if pts.shape[0] == 0 or pts.shape[1] == 0:
        raise ValueError(f"points must not be empty, got shape {pts.shape}")
    finite = np.all(np.isfinite(pts), axis=2)
    if not finite.any():
        raise ValueError("points has no finite point (all returns missing)")
    return pts, finite


def _check_positive(value: float, name: str) -> float:
    if isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {value!r}") from None
    if not np.isfinite(v) or v <= 0.0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return v


def _check_int(value: int, name: str, minimum: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")
    return int(value)


def _relabel_by_size(labels: np.ndarray) -> np.ndarray:
    """Map labels ``>= 0`` to ``0 .. J-1`` by decreasing count (ties: smaller old label first)."""
    out = np.full(labels.shape, -1, dtype=np.int64)
    valid = labels >= 0
    if not valid.any():
        return out
    old, counts = np.unique(labels[valid], return_counts=True)
    order = np.lexsort((old, -counts))  # primary key: count descending, then old label
    mapping = np.empty(int(old.max()) + 1, dtype=np.int64)
    mapping[old[order]] = np.arange(old.size, dtype=np.int64)
    out[valid] = mapping[labels[valid]]
    return out


def _fit_plane(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Total-least-squares plane of ``pts [n, 3]`` (``n >= 3``): ``(unit normal, centroid)``."""
    c = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    return vt[-1], c


# --------------------------------------------------------------------------------------
# MSAC


def _msac_best_triple(
    q: np.ndarray, q32_t: np.ndarray, triples: np.ndarray, t2: float
) -> np.ndarray | None:
    """Best MSAC plane among the planes through ``triples [K, 3]`` (indices into ``q [m, 3]``).

    Each plane is scored by the MSAC cost ``sum_i min(d_i^2, t^2)`` over all points, computed
    in chunks of hypotheses as ``[c, 3] @ [3, m]`` products in float32 (``q32_t [3, m]`` is
    ``q.T`` as float32; the coordinates are centred, so the rounding error, about 1e-6 m, is
    far below any useful threshold).

    Returns:
        ``plane [4] = (n, d)`` with unit ``n`` and ``n . x + d = 0`` of the cheapest
        non-degenerate plane (the first on ties), or ``None`` if all triples are degenerate.
    """
    a, b, c = q[triples[:, 0]], q[triples[:, 1]], q[triples[:, 2]]
    ab, ac = b - a, c - a
    n = np.cross(ab, ac)
    nn = np.linalg.norm(n, axis=1)
    ok = nn > _DEGENERATE_SIN * np.linalg.norm(ab, axis=1) * np.linalg.norm(ac, axis=1)
    ok &= nn > 0.0
    if not ok.any():
        return None
    n = n[ok] / nn[ok, None]
    d = -np.einsum("kj,kj->k", n, a[ok])
    n32, d32, t2_32 = n.astype(np.float32), d.astype(np.float32)[:, None], np.float32(t2)
    m = q.shape[0]
    chunk = max(1, _MSAC_CHUNK_ELEMS // max(m, 1))
    best_cost, best_k = np.inf, -1
    for k0 in range(0, n.shape[0], chunk):
        dist = n32[k0 : k0 + chunk] @ q32_t  # [c, m] signed distances up to the offset
        dist += d32[k0 : k0 + chunk]
        np.square(dist, out=dist)
        np.minimum(dist, t2_32, out=dist)
        cost = dist.sum(axis=1, dtype=np.float64)
        k = int(np.argmin(cost))
        if cost[k] < best_cost:
            best_cost, best_k = float(cost[k]), k0 + k
    return np.r_[n[best_k], d[best_k]]


def msac_planes(
    points: np.ndarray,
    *,
    threshold_m: float = 0.05,
    min_remaining_fraction: float = 0.05,
    max_planes: int = 100,
    n_iterations: int = 500,
    min_points: int = 30,
    seed: int = 0,
    connected: bool = False,
) -> np.ndarray:
    """Iterative plane extraction with MSAC-scored RANSAC (Torr & Zisserman 2000).

    Repeats on the remaining (finite, not yet assigned) points: draw ``n_iterations`` random
    minimal sets of 3 points at once, fit the plane through each, score every plane by the MSAC
    cost ``C = sum_i min(d_i^2, t^2)`` over all remaining points (``d_i``: orthogonal
    point-plane distance, ``t = threshold_m``; scored in chunks with float32 matrix products of
    the centred points) and keep the cheapest. Its inliers (``d_i < t``) are refitted by total
    least squares (SVD); the inliers of the refitted plane form a new plane and are removed.
    Stops when the remaining fraction of the finite points is ``<= min_remaining_fraction``,
    when ``max_planes`` planes were extracted, or when the best plane has fewer than
    ``min_points`` inliers (it is then not assigned). Degenerate (collinear or repeated)
    triples are skipped.

    Args:
        points: Organized scan, ``[H, W, 3]`` in metres (sensor frame); rows with a non-finite
            coordinate are missing returns.
        threshold_m: Inlier threshold ``t`` of the MSAC cost, metres (``> 0``).
        min_remaining_fraction: Stop once at most this fraction of the finite points is left
            unassigned, in ``[0, 1)``.
        max_planes: Maximum number of planes, ``>= 1``.
        n_iterations: Number of random 3-point samples per extracted plane, ``>= 1``.
        min_points: Minimum number of inliers of an extracted plane, ``>= 3``.
        seed: Seed of the ``numpy.random.default_rng`` that draws the samples.
        connected: If true, keep only the largest 4-connected component (in the image grid) of
            the inliers of each plane; the other inliers stay available for later planes. Off by
            default (pure MSAC, as in the dissertation's baseline).

    Returns:
        ``labels [H, W]`` (``int64``): ``-1`` for unassigned or missing points, ``0 .. J-1`` for
        the planes, numbered by decreasing point count.

    Raises:
        ValueError: If ``points`` is not ``[H, W, 3]`` or has no finite point, or a parameter is
            out of range (the message names it).
    """
    pts, finite = _check_scan(points)
    t = _check_positive(threshold_m, "threshold_m")
    try:
        frac = float(min_remaining_fraction)
    except (TypeError, ValueError):
        frac = np.nan
    if isinstance(min_remaining_fraction, (bool, np.bool_)) or not 0.0 <= frac < 1.0:
        raise ValueError(
            f"min_remaining_fraction must lie in [0, 1), got {min_remaining_fraction!r}"
        )
    max_planes = _check_int(max_planes, "max_planes", 1)
    n_iterations = _check_int(n_iterations, "n_iterations", 1)
    min_points = _check_int(min_points, "min_points", 3)
    seed = _check_int(seed, "seed", 0)
    h, w = finite.shape
    rng = np.random.default_rng(seed)

    flat_idx = np.flatnonzero(finite.ravel())  # pixel index of every finite point
    xyz = pts.reshape(-1, 3)[flat_idx]
    xyz = xyz - xyz.mean(axis=0)  # centred for better-conditioned products
    n_total = flat_idx.size
    labels = np.full(h * w, -1, dtype=np.int64)
    remaining = np.arange(n_total)  # indices into xyz
    t2 = t * t
    n_planes = 0
    while (
        n_planes < max_planes
        and remaining.size > frac * n_total
        and remaining.size >= max(3, min_points)
    ):
        q = xyz[remaining]
        triples = rng.integers(0, q.shape[0], size=(n_iterations, 3))
        plane = _msac_best_triple(q, np.ascontiguousarray(q.T, dtype=np.float32), triples, t2)
        if plane is None:
            break
        inl = np.abs(q @ plane[:3] + plane[3]) < t
        if inl.sum() < 3:
            break
        normal, centroid = _fit_plane(q[inl])
        inl = np.abs((q - centroid) @ normal) < t
        if connected and inl.any():
            mask = np.zeros(h * w, dtype=bool)
            mask[flat_idx[remaining[inl]]] = True
            comp, n_comp = ndimage.label(mask.reshape(h, w))
            if n_comp > 1:
                sizes = np.bincount(comp.ravel())[1:]
                keep = 1 + int(np.argmax(sizes))
                inl &= comp.ravel()[flat_idx[remaining]] == keep
        if inl.sum() < min_points:
            break
        labels[flat_idx[remaining[inl]]] = n_planes
        remaining = remaining[~inl]
        n_planes += 1
    return _relabel_by_size(labels.reshape(h, w))


# --------------------------------------------------------------------------------------
# PEAC: sufficient statistics


def _stats_mse(n: np.ndarray, s: np.ndarray, ss: np.ndarray) -> np.ndarray:
    """Plane-fit MSE from sufficient statistics.

    Args:
        n: Point counts, ``[...]`` (``> 0``).
        s: Sums of the points, ``[..., 3]`` (m).
        ss: Sums of the outer products ``p p^T``, ``[..., 3, 3]`` (m^2).

    Returns:
        ``[...]``: the smallest eigenvalue of the covariance ``ss/n - (s/n)(s/n)^T`` in m^2, i.e.
        the mean squared orthogonal distance of the points to their total-least-squares plane.
    """
    mean = s / n[..., None]
    cov = ss / n[..., None, None] - mean[..., :, None] * mean[..., None, :]
    return np.maximum(np.linalg.eigvalsh(cov)[..., 0], 0.0)


def _stats_plane(n: float, s: np.ndarray, ss: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(unit normal [3], centroid [3])`` of the total-least-squares plane of the statistics."""
    mean = s / n
    cov = ss / n - np.outer(mean, mean)
    _, vec = np.linalg.eigh(cov)
    return vec[:, 0], mean


def _merged_mse(
    a: tuple[float, np.ndarray, np.ndarray], b: tuple[float, np.ndarray, np.ndarray]
) -> float:
    """MSE of the union of two point sets given their statistics ``(n, s, ss)`` (O(1))."""
    n = np.asarray(a[0] + b[0], dtype=np.float64)
    return float(_stats_mse(n, a[1] + b[1], a[2] + b[2]))


def _block_view(arr: np.ndarray, bs: int) -> np.ndarray:
    """``arr [H, W, ...]`` cropped to whole blocks -> ``[hb, wb, bs * bs, ...]``."""
    hb, wb = arr.shape[0] // bs, arr.shape[1] // bs
    a = arr[: hb * bs, : wb * bs]
    a = a.reshape(hb, bs, wb, bs, *arr.shape[2:]).swapaxes(1, 2)
    return a.reshape(hb, wb, bs * bs, *arr.shape[2:])


def _jumps(r: np.ndarray, max_jump: float) -> tuple[np.ndarray, np.ndarray]:
    """Depth discontinuities between horizontal ``[H, W-1]`` and vertical ``[H-1, W]`` neighbour
    pixels: ``|r_a - r_b| > max_jump * min(r_a, r_b)`` (false where a range is NaN)."""
    with np.errstate(invalid="ignore"):
        jh = np.abs(r[:, 1:] - r[:, :-1]) > max_jump * np.minimum(r[:, 1:], r[:, :-1])
        jv = np.abs(r[1:] - r[:-1]) > max_jump * np.minimum(r[1:], r[:-1])
    return jh, jv


# --------------------------------------------------------------------------------------
# PEAC


def peac_planes(
    points: np.ndarray,
    *,
    block_size: int = 10,
    max_block_mse: float = 6e-4,
    max_merge_mse: float = 6e-4,
    max_depth_jump: float = 0.1,
    min_points: int = 300,
    refine_threshold_m: float = 0.06,
    refine: bool = True,
    max_missing_fraction: float = 0.0,
) -> np.ndarray:
    """PEAC-style plane extraction by agglomerative hierarchical clustering of image blocks.

    Follows the scheme of Feng, Taguchi & Kamat, "Fast plane extraction in organized point
    clouds using agglomerative hierarchical clustering" (ICRA 2014):

    1. *Graph initialisation.* The image is cut into non-overlapping ``block_size x block_size``
       blocks (pixels of a last partial block row/column belong to no block). A block becomes a
       node unless more than ``max_missing_fraction`` of its pixels are missing (default 0:
       any missing point, as in the paper), it contains a depth discontinuity between two
       4-neighbour pixels (``|r_a - r_b| > max_depth_jump * min(r_a, r_b)`` for ranges ``r``)
       or its plane-fit MSE exceeds ``max_block_mse``. Accepted 4-neighbour blocks are joined by an
       edge unless a pixel pair across their common border has a depth discontinuity.
    2. *Clustering.* Every node carries the sufficient statistics ``(n, sum p, sum p p^T)``, so
       the MSE of a merge (smallest eigenvalue of the 3x3 covariance) costs O(1). Repeatedly the
       node with the smallest MSE is taken from a heap (lazy invalidation); among its neighbours
       the one whose merge gives the smallest MSE is found. If that MSE is below
       ``max_merge_mse`` the two nodes merge (the union inherits all edges and re-enters the
       heap); otherwise the node leaves the graph and becomes a plane if it has at least
       ``min_points`` points (else it is discarded). A node without neighbours is treated the
       same way.
    3. *Refinement* (``refine=True``). Pixels of blocks on the border of a plane (a 4-neighbour
       block has another label) are re-assigned to the closest of the planes of their own and
       the 4-neighbour blocks, or unassigned if that orthogonal distance is not below
       ``refine_threshold_m`` (erosion). Then unassigned finite pixels (borders, rejected
       blocks, partial blocks) are added by region growing: in waves, a pixel next to labelled
       4-neighbours (without a depth discontinuity between them) joins the closest of their
       planes if its orthogonal distance to it is below ``refine_threshold_m``. Planes fitted
       from the cluster statistics are used throughout; planes left with fewer than
       ``min_points`` points are dropped.

    Thresholds are absolute: with radial noise sigma, a plane seen head-on has an MSE of about
    sigma^2 (4e-4 m^2 for 20 mm), so the MSE thresholds must exceed sigma^2 and
    ``refine_threshold_m`` is typically about 3 sigma. The defaults suit sigma = 20 mm.

    Args:
        points: Organized scan, ``[H, W, 3]`` in metres (sensor frame, sensor at the origin);
            rows with a non-finite coordinate are missing returns.
        block_size: Block edge length in pixels, ``>= 2``.
        max_block_mse: Largest plane-fit MSE of an accepted block, m^2 (``> 0``).
        max_merge_mse: Largest plane-fit MSE of a merged cluster, m^2 (``> 0``).
        max_depth_jump: Relative range jump between 4-neighbour pixels that counts as a depth
            discontinuity (``> 0``).
        min_points: Minimum number of points of a plane, ``>= 3``.
        refine_threshold_m: Largest orthogonal distance (m) at which refinement assigns a pixel
            to a plane (``> 0``).
        refine: Whether to run the pixel-level refinement (step 3).
        max_missing_fraction: Largest fraction of missing points of an accepted block, in
            ``[0, 1)``; the default 0 rejects every block with a missing point, as PEAC does
            (scattered single dropouts then fragment the planes). Statistics use the finite
            points only.

    Returns:
        ``labels [H, W]`` (``int64``): ``-1`` for unassigned or missing points, ``0 .. J-1`` for
        the planes, numbered by decreasing point count.

    Raises:
        ValueError: If ``points`` is not ``[H, W, 3]`` or has no finite point, or a parameter is
            out of range (the message names it).
    """
    pts, finite = _check_scan(points)
    bs = _check_int(block_size, "block_size", 2)
    max_block_mse = _check_positive(max_block_mse, "max_block_mse")
    max_merge_mse = _check_positive(max_merge_mse, "max_merge_mse")
    max_depth_jump = _check_positive(max_depth_jump, "max_depth_jump")
    min_points = _check_int(min_points, "min_points", 3)
    refine_thr = _check_positive(refine_threshold_m, "refine_threshold_m")
    try:
        max_missing = float(max_missing_fraction)
    except (TypeError, ValueError):
        max_missing = np.nan
    if isinstance(max_missing_fraction, (bool, np.bool_)) or not 0.0 <= max_missing < 1.0:
        raise ValueError(f"max_missing_fraction must lie in [0, 1), got {max_missing_fraction!r}")
    h, w = finite.shape

    # centre the coordinates (better-conditioned sums); missing points -> 0 in q
    offset = pts[finite].mean(axis=0)
    q = np.where(finite[..., None], pts - offset, 0.0)
    r = np.where(finite, np.linalg.norm(np.where(finite[..., None], pts, 0.0), axis=2), np.nan)
    jh, jv = _jumps(r, max_depth_jump)

    hb, wb = h // bs, w // bs
    block_labels = np.full((hb, wb), -1, dtype=np.int64)
    planes: list[tuple[np.ndarray, np.ndarray]] = []  # (normal, centroid) in centred coordinates
    if hb > 0 and wb > 0:
        planes = _peac_cluster(
            q,
            finite,
            jh,
            jv,
            bs,
            max_block_mse,
            max_merge_mse,
            max_missing,
            min_points,
            block_labels,
        )

    labels = np.full((h, w), -1, dtype=np.int64)
    labels[: hb * bs, : wb * bs] = np.repeat(np.repeat(block_labels, bs, axis=0), bs, axis=1)
    labels[~finite] = -1
    if refine and planes:
        normals = np.array([p[0] for p in planes])
        offsets = -np.einsum("kj,kj->k", normals, np.array([p[1] for p in planes]))
        labels = _peac_erode(q, labels, block_labels, bs, normals, offsets, refine_thr)
        labels = _peac_grow(q, finite, labels, jh, jv, normals, offsets, refine_thr)
        counts = np.bincount(labels[labels >= 0], minlength=len(planes))
        labels[(labels >= 0) & (counts[np.maximum(labels, 0)] < min_points)] = -1
    return _relabel_by_size(labels)


def _peac_cluster(
    q: np.ndarray,
    finite: np.ndarray,
    jh: np.ndarray,
    jv: np.ndarray,
    bs: int,
    max_block_mse: float,
    max_merge_mse: float,
    max_missing: float,
    min_points: int,
    block_labels: np.ndarray,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Steps 1-2 of :func:`peac_planes`; writes plane ids into ``block_labels [hb, wb]`` and
    returns the planes ``(unit normal [3], centroid [3])`` (centred coordinates)."""
    hb, wb = block_labels.shape
    nb = hb * wb
    # ---- node acceptance
    qb = _block_view(q, bs).reshape(nb, bs * bs, 3)
    cnt = _block_view(finite, bs).reshape(nb, -1).sum(axis=1).astype(np.float64)
    full = (cnt >= 3) & (cnt >= (1.0 - max_missing) * bs * bs)
    # discontinuities inside blocks: drop the pixel pairs that straddle two blocks
    jh_in = jh[: hb * bs, : wb * bs - 1].copy()
    jh_in[:, bs - 1 :: bs] = False
    jv_in = jv[: hb * bs - 1, : wb * bs].copy()
    jv_in[bs - 1 :: bs, :] = False
    jh_in = np.pad(jh_in, ((0, 0), (0, 1)))
    jv_in = np.pad(jv_in, ((0, 1), (0, 0)))
    jump = _block_view(jh_in | jv_in, bs).reshape(nb, -1).any(axis=1)
    s = qb.sum(axis=1)
    ss = np.einsum("kpi,kpj->kij", qb, qb)
    mse = _stats_mse(np.maximum(cnt, 1.0), s, ss)
    accepted = full & ~jump & (mse <= max_block_mse)

    # ---- edges between accepted 4-neighbour blocks without a discontinuity across the border
    acc = accepted.reshape(hb, wb)
    nbrs: list[set[int]] = [set() for _ in range(nb)]
    if wb > 1:
        # pixel pairs (row, bs*j + bs - 1) -- (row, bs*(j+1)) across vertical block borders
        cross = jh[: hb * bs, bs - 1 : (wb - 1) * bs : bs].reshape(hb, bs, wb - 1).any(axis=1)
        ok = acc[:, :-1] & acc[:, 1:] & ~cross
        for i, j in zip(*np.nonzero(ok), strict=True):
            a = i * wb + j
            nbrs[a].add(a + 1)
            nbrs[a + 1].add(a)
    if hb > 1:
        cross = jv[bs - 1 : (hb - 1) * bs : bs, : wb * bs].reshape(hb - 1, wb, bs).any(axis=2)
        ok = acc[:-1, :] & acc[1:, :] & ~cross
        for i, j in zip(*np.nonzero(ok), strict=True):
            a = i * wb + j
            nbrs[a].add(a + wb)
            nbrs[a + wb].add(a)

    # ---- agglomerative hierarchical clustering (merge u into v; v keeps its id)
    members: list[list[int]] = [[k] for k in range(nb)]
    alive = accepted.copy()
    version = np.zeros(nb, dtype=np.int64)
    heap = [(float(mse[k]), k, 0) for k in np.flatnonzero(accepted)]
    heapq.heapify(heap)
    planes: list[tuple[np.ndarray, np.ndarray]] = []
    while heap:
        m_v, v, ver = heapq.heappop(heap)
        if not alive[v] or ver != version[v]:
            continue
        if nbrs[v]:
            cand = np.array(sorted(nbrs[v]))
            m_c = _stats_mse(cnt[v] + cnt[cand], s[v] + s[cand], ss[v] + ss[cand])
            best = int(np.argmin(m_c))
            if m_c[best] < max_merge_mse:
                u = int(cand[best])
                cnt[v] += cnt[u]
                s[v] += s[u]
                ss[v] += ss[u]
                members[v].extend(members[u])
                members[u] = []
                alive[u] = False
                for x in nbrs[u]:
                    nbrs[x].discard(u)
                    if x != v:
                        nbrs[x].add(v)
                        nbrs[v].add(x)
                nbrs[u] = set()
                version[v] += 1
                heapq.heappush(heap, (float(m_c[best]), v, int(version[v])))
                continue
        # finalise v: a plane if large enough, else discarded
        alive[v] = False
        for x in nbrs[v]:
            nbrs[x].discard(v)
        nbrs[v] = set()
        if cnt[v] >= min_points:
            idx = np.array(members[v])
            block_labels[idx // wb, idx % wb] = len(planes)
            planes.append(_stats_plane(cnt[v], s[v], ss[v]))
    return planes


def _peac_erode(
    q: np.ndarray,
    labels: np.ndarray,
    block_labels: np.ndarray,
    bs: int,
    normals: np.ndarray,
    offsets: np.ndarray,
    thr: float,
) -> np.ndarray:
    """Refinement, part 1: re-assign or unassign the pixels of plane-border blocks."""
    pad = np.pad(block_labels, 1, constant_values=-2)  # -2: outside the block grid
    # labels of the block and of its 4 neighbours (up, down, left, right)   [hb, wb, 5]
    cand = np.stack(
        [pad[1:-1, 1:-1], pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]], axis=-1
    )
    own = cand[..., 0]
    border = (own >= 0) & np.any((cand[..., 1:] != own[..., None]) & (cand[..., 1:] != -2), -1)
    out = labels.copy()
    bi, bj = np.nonzero(border)
    if bi.size == 0:
        return out
    # pixel coordinates of every pixel of every border block
    di, dj = np.divmod(np.arange(bs * bs), bs)
    pi = (bi[:, None] * bs + di[None, :]).ravel()
    pj = (bj[:, None] * bs + dj[None, :]).ravel()
    c = np.repeat(cand[bi, bj], bs * bs, axis=0)  # [n_pix, 5]; < 0: no plane
    x = q[pi, pj]
    dist = np.abs(np.einsum("pj,pcj->pc", x, normals[np.maximum(c, 0)]) + offsets[np.maximum(c, 0)])
    dist[c < 0] = np.inf
    k = np.argmin(dist, axis=1)
    dmin = dist[np.arange(k.size), k]
    out[pi, pj] = np.where(dmin < thr, c[np.arange(k.size), k], -1)
    return out


def _peac_grow(
    q: np.ndarray,
    finite: np.ndarray,
    labels: np.ndarray,
    jh: np.ndarray,
    jv: np.ndarray,
    normals: np.ndarray,
    offsets: np.ndarray,
    thr: float,
) -> np.ndarray:
    """Refinement, part 2: region growing into unassigned finite pixels (in waves).

    A wave examines only open pixels next to pixels labelled in the previous wave (initially:
    next to any labelled pixel), so the cost is proportional to the grown area.
    """
    h, w = labels.shape
    out = labels.ravel().copy()
    idx = np.arange(h * w).reshape(h, w)
    # nbr[p, d]: flat index of the 4-neighbour of pixel p in direction d (up, down, left,
    # right), -1 outside the image or across a depth discontinuity (the relation is symmetric)
    nbr = np.full((h, w, 4), -1, dtype=np.int64)
    nbr[1:, :, 0] = np.where(jv, -1, idx[:-1])
    nbr[:-1, :, 1] = np.where(jv, -1, idx[1:])
    nbr[:, 1:, 2] = np.where(jh, -1, idx[:, :-1])
    nbr[:, :-1, 3] = np.where(jh, -1, idx[:, 1:])
    nbr = nbr.reshape(-1, 4)
    qf = q.reshape(-1, 3)
    open_ = finite.ravel() & (out < 0)  # pixels that may still be assigned
    seeds = np.flatnonzero(out >= 0)
    while seeds.size:
        cand = nbr[seeds].ravel()
        cand = np.unique(cand[cand >= 0])
        cand = cand[open_[cand]]
        if cand.size == 0:
            break
        nb = nbr[cand]
        c = np.where(nb >= 0, out[np.maximum(nb, 0)], -1)  # candidate planes [n, 4]
        cs = np.maximum(c, 0)
        dist = np.abs(np.einsum("pj,pcj->pc", qf[cand], normals[cs]) + offsets[cs])
        dist[c < 0] = np.inf
        k = np.argmin(dist, axis=1)
        rows = np.arange(k.size)
        ok = dist[rows, k] < thr
        seeds = cand[ok]
        out[seeds] = c[rows, k][ok]
        open_[seeds] = False
        # candidates that failed stay open: a later wave may offer them another plane
    return out.reshape(h, w)
