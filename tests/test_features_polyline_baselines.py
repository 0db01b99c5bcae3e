"""Tests of the heuristic polyline-extraction baselines of Sec. 10.5 (VVL, IEF, SAM)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lidarjax.features._polyline_baselines import (
    _intersect,
    iterative_endpoint_fit,
    point_segment_distance,
    split_and_merge,
    visvalingam,
)

# --------------------------------------------------------------------------------------
# fixtures / reference implementations


def _l_shape(na=40, nb=20, arm_a=4.0, arm_b=2.0, sigma=0.0, seed=0):
    """Scan of an L: ``na`` points from (arm_a, 0) towards the corner (0, 0) (exclusive), then
    ``nb + 1`` points from the corner up to (0, arm_b). Returns (points, corner index)."""
    x = np.linspace(arm_a, 0.0, na, endpoint=False)
    y = np.linspace(0.0, arm_b, nb + 1)
    pts = np.r_[np.c_[x, np.zeros_like(x)], np.c_[np.zeros_like(y), y]]
    pts = pts + np.random.default_rng(seed).normal(0.0, sigma, pts.shape)
    return pts, na


def _square_scan(n=64, offset=0.0):
    """``n`` points CCW around the square [-1, 1]^2, equally spaced in arc length (perimeter 8);
    the first point sits at arc length ``offset`` from the corner (1, 1)."""
    corners = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1], [1, 1]], float)
    out = []
    for s in np.linspace(0.0, 8.0, n, endpoint=False) + offset:
        s = s % 8.0
        e = int(s // 2)
        out.append(corners[e] + (s - 2 * e) / 2 * (corners[e + 1] - corners[e]))
    return np.array(out)


def _area(pts, i, j, k):
    ax, ay = pts[i]
    bx, by = pts[j]
    cx, cy = pts[k]
    return 0.5 * abs(float((bx - ax) * (cy - ay) - (by - ay) * (cx - ax)))


def _naive_vvl(pts, chains, closed, jmax):
    """O(n^2) Visvalingam: recompute every cost in every step."""
    chains = [[int(i) for i in c] for c in chains]
    n_vert = sum(len(c) for c in chains)
    while n_vert > jmax:
        best = None  # (cost, point index, chain, position or None for the whole chain)
        for c, (ch, cl) in enumerate(zip(chains, closed)):
            n = len(ch)
            cands = []
            if cl and n >= 4:
                cands = [
                    (_area(pts, ch[p - 1], ch[p], ch[(p + 1) % n]), ch[p], c, p) for p in range(n)
                ]
            elif not cl and n == 2:
                cands = [(0.0, min(ch), c, None)]
            elif not cl and n >= 3:
                cands = [
                    (_area(pts, ch[p - 1], ch[p], ch[p + 1]), ch[p], c, p) for p in range(1, n - 1)
                ]
            for cand in cands:
                if best is None or cand[:2] < best[:2]:
                    best = cand
        _, _, c, p = best
        if p is None:
            chains[c] = []
            n_vert -= 2
        else:
            del chains[c][p]
            n_vert -= 1
    polys = [pts[ch] for ch in chains if ch]
    flags = [cl for ch, cl in zip(chains, closed) if ch]
    return polys, flags


def _dist_py(p, a, b):
    """Point-segment distance in plain Python."""
    abx, aby = b[0] - a[0], b[1] - a[1]
    apx, apy = p[0] - a[0], p[1] - a[1]
    den = abx * abx + aby * aby
    t = 0.0 if den == 0 else min(1.0, max(0.0, (apx * abx + apy * aby) / den))
    return math.hypot(apx - t * abx, apy - t * aby)


def _naive_ief(pts, closed, jmax):
    """IEF by brute force: every step scans all non-vertex points and their segments."""
    n = len(pts)
    if closed:
        verts = {0, int(np.argmax(np.linalg.norm(pts - pts[0], axis=1)))}
    else:
        verts = {0, n - 1}
    while len(verts) < jmax:
        vs = sorted(verts)
        best_d, best_k = -1.0, -1
        for k in range(n):
            if k in verts:
                continue
            lo = max(v for v in vs if v < k)
            hi = min((v for v in vs if v > k), default=0)  # default: wrap to point 0
            d = _dist_py(pts[k], pts[lo], pts[hi])
            if d > best_d:
                best_d, best_k = d, k
        if best_k < 0 or best_d == 0.0:
            break
        verts.add(best_k)
    vs = sorted(verts)
    return pts[vs], closed and len(vs) >= 3


def _naive_sam(pts, closed, jmax):
    """SAM by brute force: refit everything each step, intersect via ``np.linalg.solve``."""
    n = len(pts)
    if closed:
        verts = [0, int(np.argmax(np.linalg.norm(pts - pts[0], axis=1)))]
    else:
        verts = [0, n - 1]

    def fit(vs):
        if closed and len(vs) == 2:
            return pts[vs]
        ends = list(zip(vs[:-1], vs[1:])) + ([(vs[-1], vs[0] + n)] if closed else [])
        lines = []
        for i, j in ends:
            sub = pts[[k % n for k in range(i, j + 1)]]
            c = sub.mean(axis=0)
            lines.append((c, np.linalg.svd(sub - c)[2][0]))
        out = []
        for m, v in enumerate(vs):
            if not closed and m in (0, len(vs) - 1):
                c, u = lines[0] if m == 0 else lines[-1]
                out.append(c + ((pts[v] - c) @ u) * u)
                continue
            (c1, u1), (c2, u2) = lines[m - 1], lines[m]
            if abs(u1[0] * u2[1] - u1[1] * u2[0]) < 1e-6:
                out.append(c1 + ((pts[v] - c1) @ u1) * u1)
            else:
                s = np.linalg.solve(np.c_[u1, -u2], c2 - c1)
                out.append(c1 + s[0] * u1)
        return np.array(out)

    fitted = False
    while len(verts) < jmax:
        vs = sorted(verts)
        vxy = fit(vs) if fitted else pts[vs]
        best_d, best_k = -1.0, -1
        for k in range(n):
            if k in vs:
                continue
            pos = max(m for m, v in enumerate(vs) if v < k)
            d = _dist_py(pts[k], vxy[pos], vxy[(pos + 1) % len(vs)])
            if d > best_d:
                best_d, best_k = d, k
        if best_k < 0 or best_d < 1e-12:
            break
        verts.append(best_k)
        fitted = True
    return fit(sorted(verts))


def _random_chains(rng, n_pts=70):
    pts = rng.uniform(0.0, 10.0, (n_pts, 2))
    perm = rng.permutation(n_pts)
    sizes = [2, 2, 3, 2, 9, 12, 2, 5]
    flags = [False] * len(sizes)
    sizes += [8, 3]  # a closed octagon and a closed triangle
    flags += [True, True]
    chains, start = [], 0
    for s in sizes:
        chains.append(perm[start : start + s])
        start += s
    return pts, chains, flags


def _count(result):
    return sum(len(p) for p in result[0])


# --------------------------------------------------------------------------------------
# point_segment_distance


def test_point_segment_distance_hand_cases():
    a, b = np.array([0.0, 0.0]), np.array([2.0, 0.0])
    p = np.array([[1.0, 1.5], [-3.0, 4.0], [5.0, -4.0], [0.5, 0.0], [2.0, -0.25]])
    np.testing.assert_allclose(point_segment_distance(p, a, b), [1.5, 5.0, 5.0, 0.0, 0.25])
    # degenerate segment: distance to the point
    np.testing.assert_allclose(point_segment_distance(p, a, a), np.hypot(p[:, 0], p[:, 1]))


def test_point_segment_distance_matches_dense_sampling():
    rng = np.random.default_rng(1)
    for _ in range(10):
        a, b = rng.normal(size=2), rng.normal(size=2)
        p = rng.normal(scale=2.0, size=(30, 2))
        t = np.linspace(0.0, 1.0, 4001)
        seg = a + t[:, None] * (b - a)
        brute = np.min(np.linalg.norm(p[:, None, :] - seg[None], axis=-1), axis=1)
        d = point_segment_distance(p, a, b)
        assert np.all(d <= brute + 1e-12)
        np.testing.assert_allclose(d, brute, atol=1e-3 * np.linalg.norm(b - a) + 1e-12)


def test_point_segment_distance_errors():
    with pytest.raises(ValueError, match="points"):
        point_segment_distance(np.zeros((3, 3)), np.zeros(2), np.ones(2))
    with pytest.raises(ValueError, match="a must"):
        point_segment_distance(np.zeros((3, 2)), np.zeros(3), np.ones(2))
    with pytest.raises(ValueError, match="b must"):
        point_segment_distance(np.zeros((3, 2)), np.zeros(2), np.array([np.nan, 0.0]))


# --------------------------------------------------------------------------------------
# Visvalingam


def test_vvl_removes_smallest_triangle_first():
    pts = np.array([[0.0, 0.0], [1.0, 2.0], [2.0, 1.0], [3.0, 1.2], [4.0, 1.0], [5.0, 0.0]])
    chain = [np.arange(6)]
    areas = {k: _area(pts, k - 1, k, k + 1) for k in range(1, 5)}
    cheapest = min(areas, key=areas.get)
    polys, flags = visvalingam(pts, chain, [False], 5)
    assert flags == [False]
    np.testing.assert_array_equal(polys[0], np.delete(pts, cheapest, axis=0))
    # the ends never go while the chain has >= 3 vertices
    polys, _ = visvalingam(pts, chain, [False], 2)
    np.testing.assert_array_equal(polys[0], pts[[0, 5]])


def test_vvl_ties_go_to_smallest_point_index():
    # zig-zag: all three interior triangles have area exactly 1; point indices 2, 7, 1
    pts = np.zeros((10, 2))
    order = [5, 2, 7, 1, 9]
    pts[order] = [[0, 0], [1, 1], [2, 0], [3, 1], [4, 0]]
    polys, _ = visvalingam(pts, [np.array(order)], [False], 4)
    np.testing.assert_array_equal(polys[0], pts[[5, 2, 7, 9]])


def test_vvl_drops_solitary_segment_at_zero_cost():
    pts = np.array([[0, 0], [1, 0.01], [2, 0], [3, 0.01], [10, 10], [10, 12]], float)
    chains = [np.arange(4), np.array([4, 5])]
    polys, flags = visvalingam(pts, chains, [False, False], 5)  # J: 6 -> 4, not 5
    assert _count((polys, flags)) == 4 and flags == [False]
    np.testing.assert_array_equal(polys[0], pts[:4])
    # an open 3-vertex chain becomes a 2-vertex segment that then vanishes at cost 0
    chains = [np.array([0, 1, 2]), np.array([3, 4, 5])]
    pts2 = np.array([[0, 0], [1, 5], [2, 0], [0, 10], [1, 10.001], [2, 10]], float)
    polys, _ = visvalingam(pts2, chains, [False, False], 3)
    np.testing.assert_array_equal(polys[0], pts2[:3])
    assert len(polys) == 1


def test_vvl_closed_chain():
    # unit square plus a barely-bent vertex (index 4) at the chain's start: it goes first
    pts = np.array([[0.0, 0.0], [0, 1], [1, 1], [1, 0], [0.5, -1e-3]], float)
    chain = [np.array([4, 0, 1, 2, 3])]
    polys, flags = visvalingam(pts, chain, [True], 4)
    assert flags == [True]
    np.testing.assert_array_equal(polys[0], pts[[0, 1, 2, 3]])
    polys, flags = visvalingam(pts, chain, [True], 3)
    assert flags == [True] and polys[0].shape == (3, 2)
    # a closed triangle is returned as is when the budget allows it
    polys, _ = visvalingam(pts, [np.array([0, 1, 2])], [True], 3)
    np.testing.assert_array_equal(polys[0], pts[:3])


@pytest.mark.parametrize("seed", range(4))
def test_vvl_matches_naive_on_random_chains(seed):
    rng = np.random.default_rng(seed)
    pts, chains, flags = _random_chains(rng)
    n_vert = sum(len(c) for c in chains)
    for jmax in range(n_vert + 2, 3 * sum(flags) - 1, -1):
        got = visvalingam(pts, chains, flags, jmax)
        want = _naive_vvl(pts, chains, flags, jmax)
        assert _count(got) <= jmax
        assert got[1] == want[1]
        assert len(got[0]) == len(want[0])
        for g, w in zip(got[0], want[0]):
            np.testing.assert_array_equal(g, w)


def test_vvl_errors():
    pts = np.random.default_rng(0).normal(size=(10, 2))
    ok = [np.arange(4), np.array([5, 6, 7])]
    with pytest.raises(ValueError, match="max_vertices"):
        visvalingam(pts, ok, [False, False], 1)
    with pytest.raises(ValueError, match="max_vertices"):
        visvalingam(pts, ok, [False, False], 3.0)
    with pytest.raises(ValueError, match="max_vertices"):
        visvalingam(pts, ok, [True, True], 5)  # two closed chains keep >= 6 vertices
    with pytest.raises(ValueError, match="points_xy"):
        visvalingam(pts[:, :1], ok, [False, False], 4)
    bad = pts.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="points_xy"):
        visvalingam(bad, ok, [False, False], 4)
    with pytest.raises(ValueError, match="closed"):
        visvalingam(pts, ok, [False], 4)
    with pytest.raises(ValueError, match="chains"):
        visvalingam(pts, [np.array([0, 10])], [False], 4)
    with pytest.raises(ValueError, match="chains"):
        visvalingam(pts, [np.arange(4), np.array([3, 4])], [False, False], 4)
    with pytest.raises(ValueError, match="chains"):
        visvalingam(pts, [np.array([0, 1])], [True], 4)
    with pytest.raises(ValueError, match="chains"):
        visvalingam(pts, [np.array([0.0, 1.0])], [False], 4)


# --------------------------------------------------------------------------------------
# iterative endpoint fit


@pytest.mark.parametrize("seed", range(5))
def test_ief_finds_corner_of_noisy_l(seed):
    pts, corner = _l_shape(sigma=0.002, seed=seed)
    (poly,), (cl,) = iterative_endpoint_fit(pts, False, 3)
    assert not cl
    np.testing.assert_array_equal(poly, pts[[0, corner, len(pts) - 1]])


@pytest.mark.parametrize("closed", [False, True])
def test_ief_matches_brute_force(closed):
    rng = np.random.default_rng(3)
    for _ in range(2):
        ang = np.sort(rng.uniform(0, 2 * np.pi, 60))
        pts = np.c_[np.cos(ang), np.sin(ang)] * rng.uniform(2, 6, 60)[:, None]
        for jmax in (2, 3, 4, 9, 25, 59, 60, 80):
            (poly,), (cl,) = iterative_endpoint_fit(pts, closed, jmax)
            want, want_cl = _naive_ief(pts, closed, jmax)
            assert len(poly) <= jmax
            assert cl == want_cl
            np.testing.assert_array_equal(poly, want)


def test_ief_stops_when_points_lie_on_polyline():
    pts = np.c_[np.arange(10.0), np.zeros(10)]
    (poly,), (cl,) = iterative_endpoint_fit(pts, False, 8)
    np.testing.assert_array_equal(poly, pts[[0, 9]])
    assert not cl
    few = np.random.default_rng(0).normal(size=(5, 2))
    (poly,), _ = iterative_endpoint_fit(few, False, 10)
    np.testing.assert_array_equal(poly, few)


def test_ief_closed_square():
    pts = _square_scan(64, offset=1.0)  # starts at (0, 1), the middle of the top edge
    corners = np.array([[0, 1], [-1, 1], [-1, -1], [1, -1], [1, 1]], float)
    (poly,), (cl,) = iterative_endpoint_fit(pts, True, 2)
    assert not cl and poly.shape == (2, 2)
    np.testing.assert_array_equal(poly, [[0, 1], [-1, -1]])  # farthest from (0, 1), first
    (poly,), (cl,) = iterative_endpoint_fit(pts, True, 3)
    assert cl and poly.shape == (3, 2)
    for jmax in (5, 6, 64, 100):  # all other points lie on the polygon: stops at 5
        (poly,), (cl,) = iterative_endpoint_fit(pts, True, jmax)
        assert cl
        np.testing.assert_array_equal(poly, corners)


def test_ief_ties_go_to_smallest_point_index():
    # closed: 0 -> farthest point 3, then point 1 (distance 4); then points 2 and 4 are at
    # exactly the same distance h from their segments; point 2 has the smaller index
    h = float(np.hypot(0.5, 0.5))
    pts = np.array([[0, 0], [2, 4], [4.5, 2.5], [6, 0], [3, -h]], float)
    (poly,), (cl,) = iterative_endpoint_fit(pts, True, 4)
    assert cl
    np.testing.assert_array_equal(poly, pts[[0, 1, 2, 3]])
    # open: points 1 and 3 tie on the chord
    pts = np.array([[0, 0], [1, 1], [2, 0], [3, 1], [4, 0]], float)
    (poly,), _ = iterative_endpoint_fit(pts, False, 3)
    np.testing.assert_array_equal(poly, pts[[0, 1, 4]])


# --------------------------------------------------------------------------------------
# split-and-merge


def test_sam_noiseless_l_recovers_corner():
    pts, _ = _l_shape(sigma=0.0)
    (poly,), (cl,) = split_and_merge(pts, False, 3)
    assert not cl
    np.testing.assert_allclose(poly, [[4.0, 0.0], [0.0, 0.0], [0.0, 2.0]], atol=1e-9)
    # nothing left to split: stops at 3 vertices
    (poly10,), _ = split_and_merge(pts, False, 10)
    np.testing.assert_allclose(poly10, poly, atol=1e-9)


def test_sam_corner_beats_ief_on_noisy_l():
    err_ief, err_sam = [], []
    for seed in range(10):
        pts, _ = _l_shape(na=80, nb=40, sigma=0.02, seed=seed)
        (p_ief,), _ = iterative_endpoint_fit(pts, False, 3)
        (p_sam,), _ = split_and_merge(pts, False, 3)
        err_ief.append(np.linalg.norm(p_ief[1]))
        err_sam.append(np.linalg.norm(p_sam[1]))
    assert np.mean(err_sam) < 0.5 * np.mean(err_ief)
    assert np.sum(np.array(err_sam) < np.array(err_ief)) >= 7


def test_sam_open_segment_is_fitted_line():
    # two vertices: the end points projected onto the TLS line of all points
    x = np.linspace(0.0, 4.0, 21)
    pts = np.c_[x, 0.5 * x + 1.0]
    pts[1:-1:2, 1] += 0.1
    pts[2:-1:2, 1] -= 0.1
    (poly,), (cl,) = split_and_merge(pts, False, 2)
    assert not cl
    c = pts.mean(axis=0)
    u = np.linalg.svd(pts - c)[2][0]
    want = c + ((pts[[0, -1]] - c) @ u)[:, None] * u
    np.testing.assert_allclose(poly, want, atol=1e-12)


@pytest.mark.parametrize("closed", [False, True])
def test_sam_matches_brute_force(closed):
    rng = np.random.default_rng(11)
    ang = np.sort(rng.uniform(0, 2 * np.pi, 50))
    pts = np.c_[np.cos(ang), np.sin(ang)] * rng.uniform(2, 6, 50)[:, None]
    for jmax in (2, 3, 4, 6, 12, 25):
        (poly,), _ = split_and_merge(pts, closed, jmax)
        np.testing.assert_allclose(poly, _naive_sam(pts, closed, jmax), atol=1e-9)


def test_sam_ties_go_to_smallest_point_index():
    # closed diamond: the first split (unfitted) ties between points 1 and 3
    pts = np.array([[0, 0], [1, 1], [2, 0], [1, -1]], float)
    (poly,), (cl,) = split_and_merge(pts, True, 3)
    assert cl
    np.testing.assert_allclose(poly, _naive_sam(pts, True, 3), atol=1e-12)
    # the triangle's first edge is the fitted line through points 0 and 1: y = x
    np.testing.assert_allclose(poly[1, 0], poly[1, 1], atol=1e-12)
    np.testing.assert_allclose(poly[0, 0], poly[0, 1], atol=1e-12)


def test_sam_intersection_and_parallel_fallback():
    l1 = (np.array([0.0, 1.0]), np.array([1.0, 0.0]))  # y = 1
    l2 = (np.array([3.0, 0.0]), np.array([0.6, 0.8]))
    np.testing.assert_allclose(_intersect(l1, l2, np.zeros(2)), [3.75, 1.0], atol=1e-12)
    # nearly parallel (sin = 1e-7): projection of the fallback point onto the first line
    l3 = (np.array([0.0, 5.0]), np.array([np.sqrt(1 - 1e-14), 1e-7]))
    p = np.array([2.0, -4.0])
    np.testing.assert_allclose(_intersect(l1, l3, p), [2.0, 1.0], rtol=0, atol=1e-12)
    c, u = l3
    np.testing.assert_allclose(_intersect(l3, l1, p), c + ((p - c) @ u) * u, rtol=0, atol=1e-12)
    assert abs(_intersect(l3, l1, p)[1] - (5.0 + 2e-7)) < 1e-9


def test_sam_closed_square_from_corner():
    pts = _square_scan(64, offset=0.0)
    corners = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], float)
    for jmax in (4, 5, 20):
        (poly,), (cl,) = split_and_merge(pts, True, jmax)
        assert cl
        np.testing.assert_allclose(poly, corners, atol=1e-9)
    (poly,), (cl,) = split_and_merge(pts, True, 2)  # unfitted two-vertex loop
    assert not cl
    np.testing.assert_array_equal(poly, [[1, 1], [-1, -1]])


def test_sam_closed_square_off_corner_converges_onto_square():
    # starting mid-edge, SAM inserts collinear vertices (parallel-line fallback) before it
    # reaches zero residual; all vertices must still lie on the square
    pts = _square_scan(64, offset=1.0)
    (poly,), (cl,) = split_and_merge(pts, True, 64)
    assert cl and 4 < len(poly) < 64
    assert np.all(np.isfinite(poly))
    np.testing.assert_allclose(np.max(np.abs(poly), axis=1), 1.0, atol=1e-9)
    closed_poly = np.r_[poly, poly[:1]]
    resid = np.min(
        [point_segment_distance(pts, a, b) for a, b in zip(closed_poly[:-1], closed_poly[1:])],
        axis=0,
    )
    assert np.max(resid) < 1e-9


def test_budget_respected_on_random_scans():
    rng = np.random.default_rng(7)
    for _ in range(3):
        ang = np.sort(rng.uniform(0, 2 * np.pi, 80))
        pts = np.c_[np.cos(ang), np.sin(ang)] * rng.uniform(2, 6, 80)[:, None]
        for closed in (False, True):
            for jmax in (2, 3, 5, 11, 40):
                for fn in (iterative_endpoint_fit, split_and_merge):
                    (poly,), (cl,) = fn(pts, closed, jmax)
                    assert 2 <= len(poly) <= jmax
                    assert cl == (closed and len(poly) >= 3)
                    assert np.all(np.isfinite(poly))


@pytest.mark.parametrize("fn", [iterative_endpoint_fit, split_and_merge])
def test_ief_sam_errors(fn):
    pts = np.random.default_rng(0).normal(size=(10, 2))
    for bad in (1, 0, -3, 2.5, True):
        with pytest.raises(ValueError, match="max_vertices"):
            fn(pts, False, bad)
    with pytest.raises(ValueError, match="points_xy"):
        fn(pts[:, :1], False, 4)
    with pytest.raises(ValueError, match="points_xy"):
        fn(pts[:1], False, 4)
    nan = pts.copy()
    nan[4, 0] = np.nan
    with pytest.raises(ValueError, match="points_xy"):
        fn(nan, False, 4)
    with pytest.raises(ValueError, match="points_xy"):
        fn(np.ones((5, 2)), True, 4)
