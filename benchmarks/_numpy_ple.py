"""Straightforward NumPy reference of PLE (dissertation ch. 10, Algorithm 1) for one scan.

It follows exactly the rules of :func:`lidarjax.features.extract_polylines` (see the
docstrings of ``lidarjax/features/_polyline.py``), written the plain way: ``prev`` / ``next``
arrays for the polylines, one array of removal errors, ``np.argmin`` over it every step
(``O(n)`` per step, the first index wins ties, like the JAX tournament tree) and, after a
removal, the errors of the affected vertices recomputed with vectorised NumPy over the rays
of their own sector only.

Rules (identical to the JAX version):

- Initial map (Algorithm 1, lines 1-10): ray ``i`` links to ray ``i + 1`` (cyclically when
  ``closed``) if both are reflected, their endpoints are at most ``l_max_m`` apart and the
  angle from ray ``i`` to ray ``i + 1`` is in ``(0, 180)`` deg (``cross(u_i, u_{i+1}) > 0``).
  Every ray with a link is a vertex; the squared residual ``cur`` of a reflected ray that is
  no vertex is ``d_rm²``, of every other ray 0.
- Interior vertex ``j`` (neighbours ``p`` and ``n``): ``e_j = Σ (r_k - r̂_k)² - cur_k`` over
  the rays strictly between ``p`` and ``n`` (in scan order, cyclic), ``r̂_k`` the distance
  along ray ``k`` to the line through the endpoints of ``p`` and ``n``. Not removable if the
  chord spans 180 deg or more (``cross(u_p, u_n) <= 0``), if ``p`` and ``n`` are neighbours
  of each other (a triangle would become a 2-gon), or if some of those rays does not
  cross the chord's line in front of the sensor (``cross(u_k, b_n - b_p) <= 0``).
- End vertex ``j``: the rays from ``j`` up to (excluding) its neighbour lose their segment
  and take the placeholder residual ``d_rm²``: ``e_j = Σ d_rm² - cur_k`` over them. If the
  polyline has only two vertices, it disappears as a whole: the neighbour's ray is included
  and both vertices are removed (recorded one after the other with the same error).
- Greedy loop: remove the vertex of least error while more than ``max_vertices`` vertices
  are left and the least error is finite.

The benchmark :mod:`benchmarks.polylines` checks that the removal orders agree with the JAX
implementation on every scan, and ``tests/test_numpy_ple_reference.py`` checks it on two
small scans.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ple_numpy"]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def ple_numpy(
    origin: np.ndarray,
    directions: np.ndarray,
    ranges: np.ndarray,
    reflected: np.ndarray,
    *,
    max_vertices: int,
    l_max_m: float = 1.0,
    d_rm_m: float = 0.5,
    closed: bool = False,
) -> tuple[list[int], list[float], np.ndarray, np.ndarray]:
    """PLE of one scan (Algorithm 1) with a ``MaxVertices(max_vertices)`` stopping criterion.

    Args:
        origin: ``[2]`` sensor position (m), shared by all rays.
        directions: ``[K 2]`` unit ray directions, counter-clockwise.
        ranges: ``[K]`` measured ranges (m); only used where ``reflected``.
        reflected: ``[K]`` bool, whether ray ``k`` is a HIT.
        max_vertices: ``J_max``: remove vertices while more than this many are left.
        l_max_m: longest connection between neighbouring endpoints (m).
        d_rm_m: placeholder residual for rays whose segment is removed (m).
        closed: whether the last and the first ray are neighbours (full revolution).

    Returns:
        ``(removal_order, removal_error, alive, successor)``: the removed ray indices in
        order, the error ``e_j`` (m²) of each removal, the ``[K]`` mask of surviving
        vertices and the ``[K]`` successor of each surviving vertex (``-1``: end of its
        polyline, or not a vertex).
    """
    o = np.asarray(origin, np.float64).reshape(2)
    dirs = np.asarray(directions, np.float64)
    refl = np.asarray(reflected, bool)
    r = np.where(refl, np.asarray(ranges, np.float64), 0.0)
    k = r.shape[0]
    ends = o + r[:, None] * dirs
    d_rm2 = float(d_rm_m) ** 2
    j_max = int(max_vertices)

    # ---- initial map (Algorithm 1, lines 1-10)
    idx = np.arange(k)
    nb = (idx + 1) % k
    gap = np.linalg.norm(ends[nb] - ends, axis=-1)
    conn = refl & refl[nb] & (gap <= l_max_m) & (_cross(dirs, dirs[nb]) > 0)
    if not closed:
        conn &= idx < k - 1
    nxt = np.where(conn, nb, -1)
    pb = (idx - 1) % k
    prv = np.where(conn[pb], pb, -1)
    alive = (nxt >= 0) | (prv >= 0)
    cur = np.where(refl & ~alive, d_rm2, 0.0)
    n_alive = int(alive.sum())

    def candidate(j: int):
        """``(e, rays, new_cur)`` of removing vertex ``j``; ``e = inf`` if not removable."""
        fail = (np.inf, None, None)
        if j < 0 or not alive[j]:
            return fail
        p, n = int(prv[j]), int(nxt[j])
        if p >= 0 and n >= 0:  # interior: the rays strictly between p and n hit the chord
            if not _cross(dirs[p], dirs[n]) > 0 or nxt[n] == p:
                return fail
            rays = (p + np.arange(1, (n - p) % k)) % k
            a = ends[p] - o
            ev = ends[n] - ends[p]
            den = _cross(dirs[rays], ev)
            if not np.all(den > 0):
                return fail
            rhat = _cross(a, ev) / den
            new = (r[rays] - rhat) ** 2
            if not np.all(np.isfinite(new)):
                return fail
            return float(np.sum(new - cur[rays])), rays, new
        if n >= 0:  # first vertex of an open polyline
            pair = nxt[n] < 0
            m = (n - j) % k + (1 if pair else 0)
            rays = (j + np.arange(m)) % k
        elif p >= 0:  # last vertex
            pair = prv[p] < 0
            m = (j - p) % k
            rays = (p + np.arange(0 if pair else 1, m + 1)) % k
        else:
            return fail
        return float(np.sum(d_rm2 - cur[rays])), rays, d_rm2

    err = np.array([candidate(j)[0] for j in range(k)], np.float64)
    order: list[int] = []
    order_err: list[float] = []
    for _ in range(k):
        j = int(np.argmin(err))
        e = float(err[j])
        if not (np.isfinite(e) and n_alive > j_max):
            break
        _, rays, new = candidate(j)
        p, n = int(prv[j]), int(nxt[j])
        interior = p >= 0 and n >= 0
        partner = n if n >= 0 else p
        pair = (not interior) and bool(nxt[n] < 0 if n >= 0 else prv[p] < 0)
        # unlink j (and its partner when a two-vertex polyline disappears)
        if p >= 0:
            nxt[p] = n if interior else -1
        if n >= 0:
            prv[n] = p if interior else -1
        nxt[j] = prv[j] = -1
        alive[j] = False
        order.append(j)
        order_err.append(e)
        n_alive -= 1
        if pair:
            alive[partner] = False
            nxt[partner] = prv[partner] = -1
            order.append(partner)
            order_err.append(e)
            n_alive -= 1
        cur[rays] = new
        # Algorithm 1, line 20: only the errors around the removal change
        touched = {j, partner, p, n}
        if p >= 0:
            touched.add(int(prv[p]))
        if n >= 0:
            touched.add(int(nxt[n]))
        for t in touched:
            if t >= 0:
                err[t] = candidate(t)[0]
    successor = np.where(alive, nxt, -1)
    return order, order_err, alive.copy(), successor
