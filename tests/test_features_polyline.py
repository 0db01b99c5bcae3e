"""PLE / PLE+ (dissertation ch. 10) against brute-force NumPy references."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from lidarjax import rays as R
from lidarjax.features import (
    AIC,
    MaxRMSE,
    PolylineMap,
    extract_polylines,
    is_full_revolution,
    optimize_polylines,
)
from lidarjax.raytrace import first_segment_hit, ray_segment
from lidarjax.sim import random_polygon, simulate_polygon_scan
from lidarjax.testing import finite_difference

D_RM = 0.5


# ---------------------------------------------------------------- independent references


def np_first_hit(o, dirs, segs):
    """Brute-force first intersection of rays ``o + t dirs`` with segments ``[(a, b)]``."""
    if len(segs) == 0:
        return np.full(len(dirs), np.inf)
    a = np.array([s[0] for s in segs])[None]  # [1 s 2]
    e = np.array([s[1] for s in segs])[None] - a
    d = np.asarray(dirs)[:, None]  # [n 1 2]
    w = a - np.asarray(o)
    den = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * e[..., 1] - w[..., 1] * e[..., 0]) / den
        u = (w[..., 0] * d[..., 1] - w[..., 1] * d[..., 0]) / den
    ok = (np.abs(den) > 1e-14) & (t > 0) & (u >= -1e-9) & (u <= 1 + 1e-9)
    return np.where(ok, t, np.inf).min(axis=1)


def cost(poly_list, closed_list, o, dirs, r, refl, d_rm=D_RM):
    """Σ over reflected rays of d² (d_rm² when the ray hits nothing), and the explained set."""
    segs = []
    for pl, c in zip(poly_list, closed_list):
        pts = list(pl) + ([pl[0]] if c else [])
        segs += [(np.asarray(a), np.asarray(b)) for a, b in zip(pts[:-1], pts[1:])]
    t = np_first_hit(o, dirs, segs) if segs else np.full(len(dirs), np.inf)
    hit = refl & np.isfinite(t)
    d2 = np.where(hit, (r - np.where(hit, t, 0)) ** 2, d_rm**2)
    return float(np.sum(d2[refl])), hit


def naive_ple(o, dirs, r, refl, closed, l_max, j_max, d_rm=D_RM):
    """Algorithm 1 with every error recomputed by brute force each step (O(n^2) steps)."""
    k = len(r)
    ends = o + r[:, None] * dirs
    chains: list[list[int]] = []
    cur: list[int] = []
    for i in range(k):
        nb = i + 1
        ok = nb < k or closed
        nb %= k
        link = (
            ok
            and refl[i]
            and refl[nb]
            and np.linalg.norm(ends[nb] - ends[i]) <= l_max
            and dirs[i][0] * dirs[nb][1] - dirs[i][1] * dirs[nb][0] > 0
        )
        if not cur:
            cur = [i]
        if link:
            cur.append(nb)
        else:
            if len(cur) >= 2:
                chains.append(cur)
            cur = []
    if cur and len(cur) >= 2:
        chains.append(cur)
    is_closed = [False] * len(chains)
    if closed and chains:
        if len(chains) == 1 and len(chains[0]) == k + 1:  # full polygon
            chains[0] = chains[0][:-1]
            is_closed[0] = True
        elif len(chains) > 1 and chains[-1][-1] == 0 and chains[0][0] == 0:
            chains[0] = chains[-1][:-1] + chains[0]
            chains.pop()
            is_closed.pop()
    order, errs = [], []

    def geo(ch):
        return [ends[i] for i in ch]

    def total(chs, cls):
        return cost([geo(c) for c in chs], cls, o, dirs, r, refl, d_rm)

    while sum(len(c) for c in chains) > j_max:
        base, hit0 = total(chains, is_closed)
        best = (np.inf, None, None)
        for ci, ch in enumerate(chains):
            for pos, v in enumerate(ch):
                new = [list(c) for c in chains]
                ncl = list(is_closed)
                interior = is_closed[ci] or 0 < pos < len(ch) - 1
                if interior:
                    if is_closed[ci] and len(ch) <= 3:
                        continue
                    new[ci].pop(pos)
                    removed = [v]
                elif len(ch) == 2:
                    removed = [v, ch[1 - pos]]
                    new.pop(ci)
                    ncl.pop(ci)
                else:
                    new[ci].pop(pos)
                    removed = [v]
                c_new, hit1 = total(new, ncl)
                if interior and not np.array_equal(hit0, hit1):
                    continue  # the chord must explain the same rays (span < 180 deg)
                e = c_new - base
                if e < best[0] - 1e-12 or (abs(e - best[0]) <= 1e-12 and v < best[1][0]):
                    best = (e, removed, (new, ncl))
        if best[1] is None:
            break
        order += best[1]
        errs += [best[0]] * len(best[1])
        chains, is_closed = best[2]
    return order, errs, chains, is_closed


def office_scan(seed, n=90, fov=np.deg2rad(240), dropout=0.05):
    """A partial scan of a random room with boxes, dropouts and far readings."""
    rng = np.random.default_rng(seed)
    poly = random_polygon(8, seed=seed, radius_range_m=(3.0, 9.0))
    segs = [(poly[i], poly[(i + 1) % len(poly)]) for i in range(len(poly))]
    for _ in range(3):
        c = rng.uniform(-2, 2, 2)
        h = rng.uniform(0.2, 0.5)
        box = c + h * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
        if np.all(np.linalg.norm(box, axis=1) > 0.8):
            segs += [(box[i], box[(i + 1) % 4]) for i in range(4)]
    az = np.linspace(-fov / 2, fov / 2, n)
    dirs = np.stack([np.cos(az), np.sin(az)], 1)
    r = np_first_hit(np.zeros(2), dirs, segs) + rng.normal(0, 0.02, n)
    r_max = 8.0
    r = np.where(rng.uniform(size=n) < dropout, r_max, np.minimum(r, r_max))
    return az, r, r_max


def make_rays(az, r, r_max=np.inf):
    return R.from_scan(jaxlie.SE2.identity(), az, r, 0.0, r_max)


# ---------------------------------------------------------------- ray-segment kernel


def test_ray_segment_hits_and_misses():
    o = jnp.zeros(2)
    d = jnp.array([1.0, 0.0])
    assert float(ray_segment(o, d, jnp.array([2.0, -1]), jnp.array([2.0, 1]))) == pytest.approx(2)
    assert np.isinf(float(ray_segment(o, d, jnp.array([2.0, 0.5]), jnp.array([2.0, 1]))))
    assert np.isinf(float(ray_segment(o, d, jnp.array([-2.0, -1]), jnp.array([-2.0, 1]))))
    # parallel ray and degenerate segment miss, with finite gradients
    g = jax.grad(lambda a: jnp.where(jnp.isfinite(y := ray_segment(o, d, a, a + 1.0)), y, 0.0))
    assert np.all(np.isfinite(g(jnp.array([1.0, 0.0]))))
    # through a shared vertex: both segments are hit
    v = jnp.array([3.0, 0.0])
    assert float(ray_segment(o, d, jnp.array([3.0, -1]), v)) == pytest.approx(3)
    assert float(ray_segment(o, d, v, jnp.array([4.0, 1]))) == pytest.approx(3)
    t, i = first_segment_hit(
        o, d, jnp.array([[5.0, -1], [2.0, -1], [1.0, 1]]), jnp.array([[5.0, 1], [2.0, 1], [1, 2.0]])
    )
    assert float(t) == pytest.approx(2) and int(i) == 1


def test_ray_segment_gradients():
    o = jnp.array([0.1, -0.2])
    x = jnp.array([0.3, 0.9, 0.5, 2.0, -1.0, 2.5, 1.5])  # angle, start, end

    def f(x):
        d = jnp.array([jnp.cos(x[0]), jnp.sin(x[0])])
        return ray_segment(o, d, x[1:3], x[3:5]) * x[5] + x[6]

    jf, jr = jax.jacfwd(f)(x), jax.jacrev(f)(x)
    np.testing.assert_allclose(jf, jr, rtol=1e-12)
    np.testing.assert_allclose(jr, finite_difference(jax.jit(f), x, eps=1e-6), rtol=1e-6, atol=1e-9)


# ---------------------------------------------------------------- polyline map


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_polyline_map_roundtrip_and_expected_ranges():
    rng = np.random.default_rng(1)
    pls = [rng.uniform(-5, 5, (4, 2)), rng.uniform(-5, 5, (2, 2)), rng.uniform(-5, 5, (3, 2))]
    m = PolylineMap.from_polylines(pls, [False, False, True], n_slots=12)
    back, cl = m.to_polylines()
    assert cl == [False, False, True]
    for a, b in zip(back, pls):
        np.testing.assert_array_equal(a, b)
    assert int(m.n_vertices) == 9
    az = np.linspace(-np.pi, np.pi, 200, endpoint=False)
    o = np.array([0.3, -0.1])
    rays = R.from_scan(jaxlie.SE2.from_xy_theta(*o, 0.0), az, np.ones(200))
    segs = [(p[i], p[i + 1]) for p in pls[:2] for i in range(len(p) - 1)]
    segs += [(pls[2][i], pls[2][(i + 1) % 3]) for i in range(3)]
    ref = np_first_hit(o, np.asarray(rays.directions), segs)
    got = np.asarray(m.expected_ranges(rays))
    assert np.array_equal(np.isfinite(ref), np.isfinite(got))
    np.testing.assert_allclose(got[np.isfinite(ref)], ref[np.isfinite(ref)], rtol=1e-12)


def test_polyline_map_bad_input():
    with pytest.raises(ValueError, match="polylines\\[0\\]"):
        PolylineMap.from_polylines([np.zeros((1, 2))])
    with pytest.raises(ValueError, match="non-finite"):
        PolylineMap.from_polylines([np.array([[0, 0], [np.nan, 1]])])
    with pytest.raises(ValueError, match="n_slots"):
        PolylineMap.from_polylines([np.zeros((3, 2))], n_slots=2)


# ---------------------------------------------------------------- PLE


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_ple_removal_order_and_errors_match_brute_force(seed):
    """Eq. (10.3) errors equal brute-force likelihood differences, and the fast greedy loop
    removes exactly the vertices a naive O(n^2) loop removes, in the same order."""
    az, r, r_max = office_scan(seed)
    rays = make_rays(az, r, r_max)
    j_max = 10
    res = extract_polylines(rays, max_vertices=j_max, l_max_m=1.0, d_rm_m=D_RM)
    refl = r < r_max
    dirs = np.asarray(rays.directions)
    order, errs, chains, cls = naive_ple(np.zeros(2), dirs, r, refl, False, 1.0, j_max)
    n = int(np.sum(np.asarray(res.removal_order) >= 0))
    assert n == len(order) > 30
    np.testing.assert_array_equal(np.asarray(res.removal_order)[:n], order)
    np.testing.assert_allclose(np.asarray(res.removal_error)[:n], errs, rtol=1e-9, atol=1e-12)
    got, gcl = res.map.to_polylines()
    assert sorted(map(len, got)) == sorted(map(len, chains))
    # the tracked statistics equal a brute-force evaluation of the final map
    ends = r[:, None] * dirs
    sse, hit = cost([ends[c] for c in chains], cls, np.zeros(2), dirs, r, refl)
    assert float(res.stats.sse_m2) == pytest.approx(sse, rel=1e-9)
    assert int(res.stats.n_explained) == int(hit.sum())
    assert int(res.stats.n_vertices) <= j_max


@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_ple_closed_scan_matches_brute_force():
    poly = random_polygon(6, seed=3, radius_range_m=(2.0, 4.0))
    az, r = simulate_polygon_scan(poly, n_rays=90, seed=3)
    rays = make_rays(az, r)
    assert is_full_revolution(rays)
    res = extract_polylines(rays, max_vertices=6)
    dirs = np.asarray(rays.directions)
    order, errs, chains, cls = naive_ple(np.zeros(2), dirs, r, np.ones(90, bool), True, 1.0, 6)
    n = len(order)
    np.testing.assert_array_equal(np.asarray(res.removal_order)[:n], order)
    np.testing.assert_allclose(np.asarray(res.removal_error)[:n], errs, rtol=1e-9, atol=1e-12)
    got, gcl = res.map.to_polylines()
    assert cls == [True] and gcl == [True] and len(got[0]) == 6


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_ple_batched_equals_single_and_criteria():
    scans = [office_scan(s, n=90) for s in (4, 5)]
    az = scans[0][0]
    rays = make_rays(az, np.stack([s[1] for s in scans]), 8.0)
    batch = extract_polylines(rays, max_vertices=12)
    for i in range(2):
        one = extract_polylines(make_rays(az, scans[i][1], 8.0), max_vertices=12)
        np.testing.assert_array_equal(batch.removal_order[i], one.removal_order)
        np.testing.assert_array_equal(batch.map.successor[i], one.map.successor)
    # MaxRMSE: the final map respects the bound and the next removal would break it
    one_rays = make_rays(az, scans[0][1], 8.0)
    full = extract_polylines(one_rays, max_vertices=2)
    # the same criteria structure for both runs: one compilation, values are traced
    res = extract_polylines(one_rays, max_vertices=2, criteria=[MaxRMSE(0.05), AIC(1e3)])
    assert float(res.stats.rmse_m) <= 0.05
    k = int(res.n_steps) - 1  # the refused step
    n_done = int(np.sum(np.asarray(res.removal_order) >= 0))
    np.testing.assert_array_equal(
        np.asarray(res.removal_order)[:n_done], np.asarray(full.removal_order)[:n_done]
    )
    assert k >= 1
    nxt = extract_polylines(one_rays, max_vertices=int(res.stats.n_vertices) - 1)
    assert float(nxt.stats.rmse_m) > 0.05
    # AIC (sigma known): a removal of dn vertices is taken iff e <= 4 sigma^2 dn
    sig = 0.02
    aic = extract_polylines(one_rays, max_vertices=2, criteria=[MaxRMSE(1e3), AIC(sig)])
    m = int(np.sum(np.asarray(aic.removal_order) >= 0))
    order_full, e_full = np.asarray(full.removal_order), np.asarray(full.removal_error)
    np.testing.assert_array_equal(np.asarray(aic.removal_order)[:m], order_full[:m])
    assert 0 < m < int(np.sum(order_full >= 0))
    assert np.all(e_full[:m] <= 8 * sig**2) and e_full[m] > 4 * sig**2


def test_ple_bad_input():
    az, r, r_max = office_scan(0, n=30)
    rays = make_rays(az, r, r_max)
    with pytest.raises(ValueError, match="stopping criterion"):
        extract_polylines(rays)
    with pytest.raises(ValueError, match="counter-clockwise"):
        extract_polylines(make_rays(az[::-1], r, r_max), max_vertices=5)
    with pytest.raises(ValueError, match="l_max_m"):
        extract_polylines(rays, max_vertices=5, l_max_m=0.0)
    with pytest.raises(ValueError, match="MaxVertices"):
        extract_polylines(rays, max_vertices=1)


# ---------------------------------------------------------------- PLE+


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_ple_plus_never_increases_the_objective():
    """On simulated polygon scans PLE+ lowers Σ d² (true first-intersection model), keeps
    the explained set (f unchanged) and reports the sums it reached."""
    gains = []
    for n_vertices, seed in [(4, 0), (5, 1), (12, 2), (36, 3)]:
        poly = random_polygon(n_vertices, seed=seed)
        az, r = simulate_polygon_scan(poly, n_rays=90, seed=seed)
        rays = make_rays(az, r)
        ple = extract_polylines(rays, max_vertices=8)
        plus = optimize_polylines(ple, rays)
        before = np.asarray(ple.map.expected_ranges(rays))
        after = np.asarray(plus.map.expected_ranges(rays))
        assert np.array_equal(np.isfinite(before), np.isfinite(after))
        sse0 = np.sum((r - before)[np.isfinite(before)] ** 2)
        sse1 = np.sum((r - after)[np.isfinite(after)] ** 2)
        assert sse1 <= sse0
        assert float(plus.sse_after_m2) == pytest.approx(sse1, rel=1e-9)
        assert float(plus.sse_before_m2) == pytest.approx(sse0, rel=1e-9)
        gains.append(sse1 / sse0)
    assert min(gains) < 0.7  # and it actually improves


def test_ple_plus_end_vertices_stay_on_their_rays():
    az, r, r_max = office_scan(7, n=90)
    rays = make_rays(az, r, r_max)
    ple = extract_polylines(rays, max_vertices=8)
    plus = optimize_polylines(ple, rays)
    assert float(plus.sse_after_m2) <= float(plus.sse_before_m2)
    succ = np.asarray(ple.map.successor)
    act = np.asarray(ple.map.active)
    pred = np.full(len(succ), -1)
    pred[succ[act & (succ >= 0)]] = np.flatnonzero(act & (succ >= 0))
    ends = np.flatnonzero(act & ((succ < 0) | (pred < 0)))
    v = np.asarray(plus.map.vertices)[ends]
    d = np.asarray(rays.directions)[ends]
    np.testing.assert_allclose(v[:, 0] * d[:, 1] - v[:, 1] * d[:, 0], 0, atol=1e-9)
    assert np.any(np.abs(np.asarray(plus.map.vertices) - np.asarray(ple.map.vertices)) > 1e-6)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"restarts": -1}, "restarts"),
        ({"restart_sigma": 0.0}, "restart_sigma"),
        ({"restart_sigma": (0.02, float("nan"))}, "restart_sigma"),
        ({"restart_sigma": ()}, "restart_sigma"),
        ({"pattern_m": (0.1, -0.2)}, "pattern_m"),
        ({"rounds": 0}, "rounds"),
        ({"max_steps": 0}, "max_steps"),
    ],
)
def test_ple_plus_bad_search_settings_name_the_argument(kwargs, name):
    az, r, r_max = office_scan(7, n=90)
    rays = make_rays(az, r, r_max)
    ple = extract_polylines(rays, max_vertices=8)
    with pytest.raises(ValueError, match=name):
        optimize_polylines(ple, rays, **kwargs)
