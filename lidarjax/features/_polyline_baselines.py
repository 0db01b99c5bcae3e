"""Heuristic polyline-extraction baselines of dissertation section 10.5 (plain NumPy).

* :func:`visvalingam` -- Visvalingam-Whyatt simplification (VVL) of initial polylines,
* :func:`iterative_endpoint_fit` -- iterative endpoint fit (IEF) of one scan,
* :func:`split_and_merge` -- split-and-merge (SAM): IEF with a total-least-squares line fit of
  every segment after each split.

Conventions: a polyline is an ``np.ndarray [m, 2]`` of vertices (``m >= 2``) in metres. Every
function returns ``(polylines, closed)`` with ``polylines: list[np.ndarray [m_i, 2]]`` and
``closed: list[bool]``; ``closed[i]`` means the last vertex of ``polylines[i]`` connects back to
its first (a polygon, ``m_i >= 3``). The vertex count ``J`` of a result is ``sum(m_i)``; each
function takes ``max_vertices`` (``J_max``) and returns a result with ``J <= max_vertices``.
"""

from __future__ import annotations

import heapq
from collections.abc import Sequence

import numpy as np

Result = tuple[list[np.ndarray], list[bool]]

# Distances at or below this fraction of the bounding-box diagonal of the points count as zero
# ("the point lies on the polyline"), so that round-off does not trigger useless splits.
_ZERO_REL_TOL = 1e-12
# |sin| of the angle between two adjacent fitted lines below which SAM treats them as parallel.
_PARALLEL_SIN = 1e-6


# --------------------------------------------------------------------------------------
# validation helpers


def _check_max_vertices(max_vertices: int) -> int:
    if isinstance(max_vertices, (bool, np.bool_)) or not isinstance(
        max_vertices, (int, np.integer)
    ):
        raise ValueError(f"max_vertices must be an integer >= 2, got {max_vertices!r}")
    if max_vertices < 2:
        raise ValueError(f"max_vertices must be >= 2, got {max_vertices}")
    return int(max_vertices)


def _check_points(points_xy: np.ndarray, name: str = "points_xy", min_rows: int = 0) -> np.ndarray:
    pts = np.asarray(points_xy, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"{name} must have shape [K, 2], got {pts.shape}")
    if pts.shape[0] < min_rows:
        raise ValueError(f"{name} needs at least {min_rows} points, got {pts.shape[0]}")
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"{name} must be finite (no NaN/inf)")
    return pts


def _check_point(p: np.ndarray, name: str) -> np.ndarray:
    q = np.asarray(p, dtype=float)
    if q.shape != (2,):
        raise ValueError(f"{name} must have shape [2], got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError(f"{name} must be finite (no NaN/inf)")
    return q


def _zero_tol(pts: np.ndarray) -> float:
    if pts.shape[0] == 0:
        return 0.0
    return _ZERO_REL_TOL * float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))


# --------------------------------------------------------------------------------------
# geometry


def point_segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Euclidean distance of points to the closed segment ``[a, b]``.

    Args:
        points: Query points, ``[n, 2]`` in metres.
        a: First segment end, ``[2]`` in metres.
        b: Second segment end, ``[2]`` in metres. ``a == b`` is allowed (distance to the
            point ``a``).

    Returns:
        Distances, ``[n]`` in metres (perpendicular distance where the foot of the perpendicular
        lies within the segment, otherwise the distance to the nearer end).

    Raises:
        ValueError: On bad shapes or non-finite input.
    """
    p = _check_points(points, "points")
    a = _check_point(a, "a")
    b = _check_point(b, "b")
    return _seg_dist(p, a, b)


def _seg_dist(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Unvalidated :func:`point_segment_distance`."""
    ab = b - a
    ap = p - a
    den = float(ab @ ab)
    if den == 0.0:
        return np.hypot(ap[:, 0], ap[:, 1])
    t = np.clip((ap @ ab) / den, 0.0, 1.0)
    d = ap - t[:, None] * ab
    return np.hypot(d[:, 0], d[:, 1])


def _triangle_area(pts: np.ndarray, i: int, j: int, k: int) -> float:
    ax, ay = pts[i]
    bx, by = pts[j]
    cx, cy = pts[k]
    return 0.5 * abs(float((bx - ax) * (cy - ay) - (by - ay) * (cx - ax)))


# --------------------------------------------------------------------------------------
# Visvalingam-Whyatt


def visvalingam(
    points_xy: np.ndarray,
    chains: Sequence[np.ndarray],
    closed: Sequence[bool],
    max_vertices: int,
) -> Result:
    """Visvalingam-Whyatt simplification (VVL) of a set of initial polylines.

    Repeatedly removes the globally cheapest vertex until ``J <= max_vertices``. The cost of an
    interior vertex is the area of the triangle it spans with its current two neighbours (in a
    closed chain every vertex is interior). End vertices of an open chain with ``>= 3`` vertices
    are not removable; an open chain with exactly two vertices (a straight segment) is removed
    as a whole at cost 0 (``J`` drops by 2), which is why VVL discards solitary line segments
    (section 10.5). A closed chain with 3 vertices loses no further vertex. Ties are broken by
    the smallest point index (for a two-vertex chain, the smaller of its two indices). Uses a
    binary heap with lazy invalidation; a removal only re-prices the two neighbours.

    Args:
        points_xy: Scan endpoints, ``[K, 2]`` in metres.
        chains: Initial polylines as integer index arrays into ``points_xy`` (scan order), each
            ``[m_i]`` with ``m_i >= 2`` (``>= 3`` if closed); no index may occur twice.
        closed: Per chain, whether it is a closed polygon; ``len(closed) == len(chains)``.
        max_vertices: ``J_max >= 2``; must be at least ``3 * sum(closed)`` (closed chains
            cannot shrink below triangles).

    Returns:
        ``(polylines, closed)``: the surviving chains in input order (vanished two-vertex open
        chains are dropped), each ``[m, 2]`` with the kept vertex coordinates in chain order,
        and their closed flags. ``J <= max_vertices``; if the input already satisfies this, it
        is returned unchanged.

    Raises:
        ValueError: On bad shapes, non-finite points, bad or repeated indices, mismatched
            ``closed``, or ``max_vertices`` below 2 or below ``3 * sum(closed)``.
    """
    jmax = _check_max_vertices(max_vertices)
    pts = _check_points(points_xy)
    n_pts = pts.shape[0]
    closed_flags = [bool(c) for c in closed]
    if len(closed_flags) != len(chains):
        raise ValueError(
            f"closed must have one flag per chain: {len(closed_flags)} flags, {len(chains)} chains"
        )
    idx_chains: list[np.ndarray] = []
    for c, (chain, is_closed) in enumerate(zip(chains, closed_flags, strict=True)):
        arr = np.asarray(chain)
        if arr.ndim != 1 or not (arr.size == 0 or np.issubdtype(arr.dtype, np.integer)):
            raise ValueError(f"chains[{c}] must be a 1-D integer index array, got {arr!r}")
        need = 3 if is_closed else 2
        if arr.size < need:
            raise ValueError(f"chains[{c}] needs at least {need} vertices, got {arr.size}")
        if arr.min() < 0 or arr.max() >= n_pts:
            raise ValueError(f"chains[{c}] has indices outside [0, {n_pts})")
        idx_chains.append(arr.astype(np.int64))
    all_idx = np.concatenate(idx_chains) if idx_chains else np.zeros(0, np.int64)
    if np.unique(all_idx).size != all_idx.size:
        raise ValueError("chains must not share or repeat point indices")
    n_closed = sum(closed_flags)
    if jmax < 3 * n_closed:
        raise ValueError(
            f"max_vertices={jmax} is unreachable: {n_closed} closed chains keep >= 3 vertices each"
        )

    # linked lists over point indices
    prev = np.full(n_pts, -1, np.int64)
    nxt = np.full(n_pts, -1, np.int64)
    chain_of = np.full(n_pts, -1, np.int64)
    alive = np.zeros(n_pts, bool)
    version = np.zeros(n_pts, np.int64)
    sizes = [int(a.size) for a in idx_chains]
    for c, arr in enumerate(idx_chains):
        prev[arr[1:]] = arr[:-1]
        nxt[arr[:-1]] = arr[1:]
        if closed_flags[c]:
            prev[arr[0]] = arr[-1]
            nxt[arr[-1]] = arr[0]
        chain_of[arr] = c
        alive[arr] = True

    def cost(u: int) -> float | None:
        """Current removal cost of vertex ``u`` or ``None`` if it is not removable."""
        c = chain_of[u]
        size = sizes[c]
        if closed_flags[c]:
            return _triangle_area(pts, prev[u], u, nxt[u]) if size >= 4 else None
        if size == 2:
            other = nxt[u] if nxt[u] >= 0 else prev[u]
            return 0.0 if u < other else None
        if prev[u] >= 0 and nxt[u] >= 0:
            return _triangle_area(pts, prev[u], u, nxt[u])
        return None

    heap: list[tuple[float, int, int]] = []

    def refresh(u: int) -> None:
        version[u] += 1
        k = cost(u)
        if k is not None:
            heapq.heappush(heap, (k, u, int(version[u])))

    for u in all_idx.tolist():
        k = cost(u)
        if k is not None:
            heap.append((k, u, 0))
    heapq.heapify(heap)

    n_vert = int(all_idx.size)
    while n_vert > jmax:
        if not heap:  # unreachable given the check on 3 * n_closed above
            raise RuntimeError("no removable vertex left")
        k, u, ver = heapq.heappop(heap)
        # stale: removed, re-priced, or (closed chain shrunk to 3 elsewhere) no longer removable
        if not alive[u] or ver != version[u] or cost(u) is None:
            continue
        c = chain_of[u]
        if not closed_flags[c] and sizes[c] == 2:
            other = nxt[u] if nxt[u] >= 0 else prev[u]
            alive[u] = alive[other] = False
            sizes[c] = 0
            n_vert -= 2
            continue
        p, n = int(prev[u]), int(nxt[u])
        nxt[p] = n
        prev[n] = p
        alive[u] = False
        sizes[c] -= 1
        n_vert -= 1
        refresh(p)
        refresh(n)

    polylines: list[np.ndarray] = []
    out_closed: list[bool] = []
    for c, arr in enumerate(idx_chains):
        kept = arr[alive[arr]]
        if kept.size:
            polylines.append(pts[kept].copy())
            out_closed.append(closed_flags[c])
    return polylines, out_closed


# --------------------------------------------------------------------------------------
# iterative endpoint fit / split-and-merge


def _segment_ranges(verts: list[int], n_pts: int, closed: bool) -> list[tuple[int, int]]:
    """Point-index ranges ``(i, j)`` of the segments between consecutive sorted vertex
    indices; for a closed scan the last range wraps (``j = n_pts`` stands for point 0)."""
    ranges = list(zip(verts[:-1], verts[1:], strict=True))
    if closed:
        ranges.append((verts[-1], n_pts))
    return ranges


def _farthest_inner(
    pts: np.ndarray, i: int, j: int, a: np.ndarray, b: np.ndarray
) -> tuple[float, int]:
    """Largest distance of the points strictly between indices ``i`` and ``j`` (``j`` may be
    ``K``, the wrap to point 0) to segment ``[a, b]`` and its point index (first on ties);
    ``(-1, -1)`` if there is no such point."""
    if j - i < 2:
        return -1.0, -1
    d = _seg_dist(pts[i + 1 : j], a, b)
    m = int(np.argmax(d))
    return float(d[m]), i + 1 + m


def _closed_start(pts: np.ndarray) -> list[int]:
    d = np.hypot(*(pts - pts[0]).T)
    f = int(np.argmax(d))
    if d[f] == 0.0:
        raise ValueError("points_xy: all points coincide; a closed scan needs two distinct points")
    return [0, f]


def _pack(vertices: np.ndarray, closed: bool) -> Result:
    return [vertices], [bool(closed and vertices.shape[0] >= 3)]


def iterative_endpoint_fit(points_xy: np.ndarray, closed: bool, max_vertices: int) -> Result:
    """Iterative endpoint fit (IEF) of the endpoints of one scan.

    Open scan: starts from the segment first point -> last point. Closed scan (full
    revolution): starts from the two-vertex loop of point 0 and the point farthest from it
    (smallest index on ties) and refines both halves alike. Each step inserts, as a vertex, the
    point with the largest distance to the segment of the current polyline whose index range
    contains it (smallest index on ties). Stops when ``J == max_vertices`` or every point lies
    on the polyline (all distances zero up to round-off, ``1e-12`` of the points' bounding-box
    diagonal; in particular when all points are vertices).

    Args:
        points_xy: Reflected scan endpoints in scan order, ``[K, 2]`` in metres, ``K >= 2``
            (max-range readings removed by the caller).
        closed: Whether the scan is a full revolution to be represented by a polygon.
        max_vertices: ``J_max >= 2``.

    Returns:
        ``([polyline], [is_closed])`` with one polyline ``[m, 2]`` whose vertices are scan
        points in scan order (closed scans: starting at point 0); ``is_closed`` is true for a
        closed scan with ``m >= 3`` (a two-vertex loop is returned as an open segment).

    Raises:
        ValueError: On bad shapes, non-finite points, ``K < 2``, ``max_vertices < 2``, or a
            closed scan whose points all coincide.
    """
    jmax = _check_max_vertices(max_vertices)
    pts = _check_points(points_xy, min_rows=2)
    n_pts = pts.shape[0]
    closed = bool(closed)
    tol = _zero_tol(pts)
    verts = _closed_start(pts) if closed else [0, n_pts - 1]

    def best(i: int, j: int) -> tuple[float, int]:
        return _farthest_inner(pts, i, j, pts[i], pts[j % n_pts])

    # per segment (keyed by its start index): (max distance, arg point index)
    cand = {i: best(i, j) for i, j in _segment_ranges(verts, n_pts, closed)}
    end_of = dict(_segment_ranges(verts, n_pts, closed))
    while len(verts) < jmax:
        # largest distance, then smallest point index
        i_best = max(cand, key=lambda i: (cand[i][0], -cand[i][1]))
        d, k = cand[i_best]
        if k < 0 or d <= tol:
            break
        j = end_of[i_best]
        verts.append(k)
        end_of[i_best], end_of[k] = k, j
        cand[i_best], cand[k] = best(i_best, k), best(k, j)
    verts.sort()
    return _pack(pts[verts].copy(), closed)


def _tls_line(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Total-least-squares line of points ``[n, 2]``: (centroid ``[2]``, unit direction
    ``[2]``)."""
    c = p.mean(axis=0)
    q = p - c
    _, vecs = np.linalg.eigh(q.T @ q)
    return c, vecs[:, -1]


def _project(p: np.ndarray, line: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    c, u = line
    return c + float((p - c) @ u) * u


def _intersect(
    l1: tuple[np.ndarray, np.ndarray], l2: tuple[np.ndarray, np.ndarray], fallback: np.ndarray
) -> np.ndarray:
    """Intersection of two lines; projection of ``fallback`` onto ``l1`` if nearly parallel."""
    (c1, u1), (c2, u2) = l1, l2
    s = float(u1[0] * u2[1] - u1[1] * u2[0])  # sin of the angle (unit directions)
    if abs(s) < _PARALLEL_SIN:
        return _project(fallback, l1)
    w = c2 - c1
    t = float(w[0] * u2[1] - w[1] * u2[0]) / s
    return c1 + t * u1


def split_and_merge(points_xy: np.ndarray, closed: bool, max_vertices: int) -> Result:
    """Split-and-merge (SAM): iterative endpoint fit with line fitting.

    Like :func:`iterative_endpoint_fit`, but the polyline is fitted to the points: every
    segment's line is the total-least-squares (orthogonal regression / PCA) line of the points
    of its index range, inclusive of its two vertex points. An interior vertex is the
    intersection of its two adjacent fitted lines (if ``|sin angle| < 1e-6``, the projection of
    the vertex's scan point onto the preceding line); an open end vertex is the projection of
    its end point onto its line. The next split point is the non-vertex point with the largest
    distance to its fitted segment (smallest index on ties). Fitting starts after the first
    split: the first split point is chosen on the unfitted start polyline, exactly as in IEF.
    The returned vertices are always fitted, except for the two-vertex loop of a closed scan
    (both of its "segments" would share both vertices), which is returned as the raw points.

    Args:
        points_xy: Reflected scan endpoints in scan order, ``[K, 2]`` in metres, ``K >= 2``
            (max-range readings removed by the caller).
        closed: Whether the scan is a full revolution to be represented by a polygon.
        max_vertices: ``J_max >= 2``.

    Returns:
        ``([polyline], [is_closed])`` with one polyline ``[m, 2]`` of fitted vertices in scan
        order (closed scans: starting at the vertex of point 0); ``is_closed`` as in
        :func:`iterative_endpoint_fit`.

    Raises:
        ValueError: As :func:`iterative_endpoint_fit`.
    """
    jmax = _check_max_vertices(max_vertices)
    pts = _check_points(points_xy, min_rows=2)
    n_pts = pts.shape[0]
    closed = bool(closed)
    tol = _zero_tol(pts)
    verts = _closed_start(pts) if closed else [0, n_pts - 1]
    lines: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def line_of(i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
        if (i, j) not in lines:
            lines[(i, j)] = _tls_line(pts[np.arange(i, j + 1) % n_pts])
        return lines[(i, j)]

    def fitted(vs: list[int]) -> np.ndarray:
        if closed and len(vs) == 2:
            return pts[vs].copy()
        segs = [line_of(i, j) for i, j in _segment_ranges(vs, n_pts, closed)]
        out = np.empty((len(vs), 2))
        for m, v in enumerate(vs):
            if m == 0 and not closed:
                out[m] = _project(pts[v], segs[0])
            elif m == len(vs) - 1 and not closed:
                out[m] = _project(pts[v], segs[-1])
            else:
                out[m] = _intersect(segs[m - 1], segs[m], pts[v])
        return out

    n_split = 0
    while len(verts) < jmax:
        verts.sort()
        # before the first split the polyline is the unfitted IEF start (chord / loop)
        vxy = fitted(verts) if n_split else pts[verts]
        best_d, best_k = -1.0, -1
        for m, (i, j) in enumerate(_segment_ranges(verts, n_pts, closed)):
            d, k = _farthest_inner(pts, i, j, vxy[m], vxy[(m + 1) % len(verts)])
            if d > best_d:  # strict: the earlier segment (smaller indices) wins ties
                best_d, best_k = d, k
        if best_k < 0 or best_d <= tol:
            break
        verts.append(best_k)
        n_split += 1
    verts.sort()
    return _pack(fitted(verts), closed)
