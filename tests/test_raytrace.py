"""Tests of the exact grid ray tracer against independent NumPy references."""

from __future__ import annotations

from collections import defaultdict

import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from hypothesis import given

from lidarjax.rays import HIT, SUB, SUP, RayBatch, from_scan
from lidarjax.raytrace import GridSpec, accumulate, traverse, traverse_rays

traverse_jit = jax.jit(traverse, static_argnums=4)

# --------------------------------------------------------------------------------------
# Independent references
# --------------------------------------------------------------------------------------


def clip_interval(lo, hi, o, d, length):
    """Slab clipping in NumPy (d unit, may contain zeros)."""
    t0, t1 = 0.0, float(length)
    for k in range(len(o)):
        if d[k] == 0:
            if not (lo[k] <= o[k] <= hi[k]):
                return None
            continue
        a, b = (lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]
        t0, t1 = max(t0, min(a, b)), min(t1, max(a, b))
    return (t0, t1) if t0 < t1 else None


def exact_reference(lo, res, shape, o, d, length):
    """Cell -> length via all grid-line crossing parameters (sorted), midpoint cell lookup."""
    lo = np.asarray(lo, float)
    o = np.asarray(o, float)
    d = np.asarray(d, float)
    d = d / np.linalg.norm(d)
    hi = lo + np.asarray(shape) * res
    iv = clip_interval(lo, hi, o, d, length)
    out: dict[tuple[int, ...], float] = defaultdict(float)
    if iv is None:
        return out
    t0, t1 = iv
    ts = [t0, t1]
    for k in range(len(o)):
        if d[k] == 0:
            continue
        lines = lo[k] + res * np.arange(shape[k] + 1)
        tk = (lines - o[k]) / d[k]
        ts.extend(t for t in tk if t0 < t < t1)
    ts = np.unique(np.asarray(ts))
    for a, b in zip(ts[:-1], ts[1:]):
        if b - a <= 1e-12:
            continue
        mid = o + 0.5 * (a + b) * d
        cell = tuple(int(c) for c in np.floor((mid - lo) / res))
        cell = tuple(min(max(c, 0), n - 1) for c, n in zip(cell, shape))
        out[cell] += b - a
    return out


def dense_reference(lo, res, shape, o, d, length, n_samples=200_000):
    """Cell -> length by dense sampling of the ray (brute force)."""
    lo = np.asarray(lo, float)
    d = np.asarray(d, float) / np.linalg.norm(d)
    dt = length / n_samples
    t = (np.arange(n_samples) + 0.5) * dt
    p = np.asarray(o, float) + t[:, None] * d
    cells = np.floor((p - lo) / res).astype(int)
    inside = np.all((cells >= 0) & (cells < np.asarray(shape)), axis=1)
    out: dict[tuple[int, ...], float] = defaultdict(float)
    for c in map(tuple, cells[inside]):
        out[c] += dt
    return out


def as_dict(tr):
    out: dict[tuple[int, ...], float] = defaultdict(float)
    cells = np.asarray(tr.cells)
    lengths = np.asarray(tr.lengths)
    for c, v, ok in zip(cells, lengths, np.asarray(tr.valid)):
        if ok:
            out[tuple(int(x) for x in c)] += float(v)
    return out


def assert_same_cells(a, b, tol):
    keys = {k for k, v in a.items() if v > tol} | {k for k, v in b.items() if v > tol}
    for k in keys:
        assert abs(a.get(k, 0.0) - b.get(k, 0.0)) <= tol, (k, a.get(k), b.get(k))


# --------------------------------------------------------------------------------------
# traverse
# --------------------------------------------------------------------------------------

# XLA on the CPU flushes subnormal floats to zero (a coordinate of -1e-308 is 0 inside jit
# but negative in NumPy), so subnormals are excluded: they would test the FPU mode, not the
# walk.
coord = st.floats(-1.5, 3.5, allow_nan=False, allow_infinity=False, allow_subnormal=False)
# A direction component below 1e-9 in magnitude (but not 0) moves a ray that starts on a
# cell boundary by less than one ulp: the exact walk enters the cell on the side the
# component points to, the float reference (floor of the rounded positions) stays in the
# other. Such components are set to exactly 0 (rays along a boundary stay tested).
unit = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False, allow_subnormal=False).map(
    lambda c: 0.0 if abs(c) < 1e-9 else c
)


@given(
    o=st.tuples(coord, coord),
    d=st.tuples(unit, unit).filter(lambda v: np.hypot(*v) > 1e-3),
    length=st.floats(0.0, 5.0),
)
def test_traverse_2d_matches_exact_reference(o, d, length):
    spec = GridSpec([0.0, 0.0], 0.25, (8, 10))
    tr = traverse_jit(spec, jnp.array(o), jnp.array(d), length, 64)
    assert bool(tr.complete)
    got = as_dict(tr)
    ref = exact_reference([0.0, 0.0], 0.25, (8, 10), o, d, length)
    assert_same_cells(got, ref, 1e-9)
    # lengths sum to the clipped length
    lo, hi = np.zeros(2), np.array([2.0, 2.5])
    iv = clip_interval(lo, hi, np.array(o), np.array(d) / np.linalg.norm(d), length)
    expected = 0.0 if iv is None else iv[1] - iv[0]
    assert abs(float(jnp.sum(tr.lengths)) - expected) <= 1e-9
    assert np.all(np.isfinite(np.asarray(tr.lengths)))


@given(
    o=st.tuples(coord, coord, coord),
    d=st.tuples(unit, unit, unit).filter(lambda v: np.linalg.norm(v) > 1e-3),
    length=st.floats(0.0, 5.0),
)
def test_traverse_3d_matches_exact_reference(o, d, length):
    spec = GridSpec([-0.5, 0.0, 0.0], 0.3, (7, 6, 5))
    tr = traverse_jit(spec, jnp.array(o), jnp.array(d), length, 64)
    assert bool(tr.complete)
    ref = exact_reference([-0.5, 0.0, 0.0], 0.3, (7, 6, 5), o, d, length)
    assert_same_cells(as_dict(tr), ref, 1e-9)
    assert abs(float(jnp.sum(tr.lengths)) - sum(ref.values())) <= 1e-9


def test_traverse_matches_dense_sampling_2d_and_3d():
    rng = np.random.default_rng(3)
    for dim, shape in ((2, (12, 9)), (3, (6, 7, 5))):
        spec = GridSpec(np.full(dim, -0.2), 0.2, shape)
        for _ in range(10):
            o = rng.uniform(-0.5, 1.5, dim)
            d = rng.normal(size=dim)
            length = rng.uniform(0.1, 3.0)
            tr = traverse_jit(spec, jnp.array(o), jnp.array(d), length, 64)
            dense = dense_reference(np.full(dim, -0.2), 0.2, shape, o, d, length)
            # Dense sampling is exact up to one sample per cell boundary.
            assert_same_cells(as_dict(tr), dense, 2 * length / 200_000 + 1e-12)


@pytest.mark.parametrize(
    "o, d, length, cells, lengths",
    [
        # axis-parallel along +x inside row 1
        ([0.05, 0.15], [1.0, 0.0], 0.3, [(0, 1), (1, 1), (2, 1), (3, 1)], [0.05, 0.1, 0.1, 0.05]),
        # axis-parallel along -y, start exactly on a boundary
        ([0.25, 0.3], [0.0, -1.0], 0.25, [(2, 2), (2, 1), (2, 0)], [0.1, 0.1, 0.05]),
        # ray exactly along a grid line x = 0.2 belongs to column 2 (floor convention)
        ([0.2, 0.0], [0.0, 1.0], 0.15, [(2, 0), (2, 1)], [0.1, 0.05]),
        # diagonal through cell corners: only the diagonal cells, no zero-length neighbours
        (
            [0.0, 0.0],
            [1.0, 1.0],
            np.sqrt(2) * 0.3,
            [(0, 0), (1, 1), (2, 2)],
            [np.sqrt(2) * 0.1] * 3,
        ),
        # starts outside, enters through the left face
        ([-1.0, 0.05], [1.0, 0.0], 1.15, [(0, 0), (1, 0)], [0.1, 0.05]),
    ],
)
def test_traverse_hand_cases(o, d, length, cells, lengths):
    spec = GridSpec([0.0, 0.0], 0.1, (5, 5))
    tr = traverse_jit(spec, jnp.array(o), jnp.array(d), length, 12)
    valid = np.asarray(tr.valid)
    np.testing.assert_array_equal(np.asarray(tr.cells)[valid], np.array(cells))
    np.testing.assert_allclose(np.asarray(tr.lengths)[valid], lengths, atol=1e-12)
    assert np.asarray(tr.is_last)[valid][-1] and not np.any(np.asarray(tr.is_last)[valid][:-1])


def test_traverse_degenerate_rays_are_nan_free():
    spec = GridSpec([0.0, 0.0], 0.1, (5, 5))
    # zero-length ray inside: one cell, length 0
    tr = traverse_jit(spec, jnp.array([0.12, 0.37]), jnp.array([1.0, 0.0]), 0.0, 4)
    assert np.asarray(tr.valid).sum() == 1
    assert tuple(np.asarray(tr.cells)[0]) == (1, 3) and float(tr.lengths[0]) == 0.0
    # ray missing the grid entirely
    tr = traverse_jit(spec, jnp.array([-1.0, -1.0]), jnp.array([-1.0, 0.2]), 5.0, 4)
    assert not np.asarray(tr.valid).any() and float(jnp.sum(tr.lengths)) == 0.0
    # zero direction
    tr = traverse_jit(spec, jnp.array([0.2, 0.2]), jnp.array([0.0, 0.0]), 1.0, 4)
    assert float(jnp.sum(tr.lengths)) == 0.0
    # infinite length traces to the border
    tr = traverse_jit(spec, jnp.array([0.05, 0.05]), jnp.array([1.0, 0.0]), jnp.inf, 8)
    assert abs(float(jnp.sum(tr.lengths)) - 0.45) < 1e-12
    for t in (tr,):
        assert np.all(np.isfinite(np.asarray(t.lengths)))


def test_traverse_reports_incomplete_budget():
    spec = GridSpec([0.0, 0.0], 0.1, (50, 50))
    tr = traverse_jit(spec, jnp.array([0.05, 0.05]), jnp.array([1.0, 0.0]), 4.0, 10)
    assert not bool(tr.complete)


def test_traverse_gradients_match_finite_differences():
    spec = GridSpec([0.0, 0.0], 0.1, (20, 20))
    w = jnp.asarray(np.random.default_rng(0).uniform(0.1, 2.0, (20, 20)))

    @jax.jit
    def integral(params):
        o, d, length = params[:2], params[2:4], params[4]
        tr = traverse_jit(spec, o, d, length, 64)
        return jnp.sum(w[tr.cells[:, 0], tr.cells[:, 1]] * tr.lengths)

    x = jnp.array([0.33, 0.41, 0.8, 0.35, 1.13])
    g_rev = jax.grad(integral)(x)
    g_fwd = jax.jacfwd(integral)(x)
    np.testing.assert_allclose(g_rev, g_fwd, rtol=1e-10, atol=1e-12)
    eps = 1e-6
    fd = np.array(
        [
            (integral(x + eps * np.eye(5)[i]) - integral(x - eps * np.eye(5)[i])) / (2 * eps)
            for i in range(5)
        ]
    )
    np.testing.assert_allclose(g_rev, fd, rtol=1e-6, atol=1e-8)
    # d/d(length) of the integral is the weight of the end cell (cf. Eq. 7.12)
    end = np.asarray(x[:2] + x[4] * x[2:4] / jnp.linalg.norm(x[2:4]))
    ci = np.floor(end / 0.1).astype(int)
    assert abs(float(g_rev[4]) - float(w[ci[0], ci[1]])) < 1e-10
    assert np.all(np.isfinite(np.asarray(jax.grad(integral)(jnp.array([0.1, 0.1, 1.0, 0.0, 0.5])))))


def test_traverse_rejects_bad_shapes():
    spec = GridSpec([0.0, 0.0], 0.1, (5, 5))
    with pytest.raises(ValueError, match="origin"):
        traverse(spec, jnp.zeros(3), jnp.ones(3), 1.0, 4)
    with pytest.raises(ValueError, match="max_cells"):
        traverse(spec, jnp.zeros(2), jnp.ones(2), 1.0, 0)


# --------------------------------------------------------------------------------------
# accumulate
# --------------------------------------------------------------------------------------


def reference_stats(spec_lo, res, shape, rays: RayBatch, sub_as_hit=False):
    H = np.zeros(shape, int)
    M = np.zeros(shape, int)
    R = np.zeros(shape)
    lo = np.asarray(spec_lo, float)
    hi = lo + np.asarray(shape) * res
    flat = rays.flatten()
    r_max = float(flat.r_max)
    for o, d, r, k in zip(
        np.asarray(flat.origins),
        np.asarray(flat.directions),
        np.asarray(flat.ranges),
        np.asarray(flat.kind),
    ):
        if k == SUB and not sub_as_hit:
            continue
        length = r_max if k == SUP else r
        cells = exact_reference(lo, res, shape, o, d, length)
        if length == 0 and np.all((o >= lo) & (o <= hi)):
            # a zero-length hit is a reflection in the start cell
            c = tuple(np.minimum(np.floor((o - lo) / res).astype(int), np.asarray(shape) - 1))
            H[c] += k != SUP
            continue
        if not cells:
            continue
        iv = clip_interval(lo, hi, o, d / np.linalg.norm(d), length)
        ends_inside = k != SUP and iv is not None and abs(iv[1] - length) < 1e-12
        # the last cell along the ray is the one with the largest entry parameter
        order = sorted(cells, key=lambda c: np.dot((np.asarray(c) + 0.5) * res + lo - o, d))
        for c in order:
            R[c] += cells[c]
        for c in order[:-1]:
            M[c] += 1
        if ends_inside:
            H[order[-1]] += 1
        else:
            M[order[-1]] += 1
    return H, M, R


def test_accumulate_hand_made_scene():
    """Three rays in a 4 x 3 grid of 1 m cells, H/M/R worked out by hand."""
    spec = GridSpec([0.0, 0.0], 1.0, (4, 3))
    rays = RayBatch(
        origins=jnp.array([[0.5, 0.5], [0.5, 0.5], [0.5, 2.5], [3.5, 1.5]]),
        directions=jnp.array([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0], [-1.0, 0.0]]),
        ranges=jnp.array([2.0, 0.3, 10.0, 1.0]),
        kind=jnp.array([HIT, SUB, SUP, HIT]),
        r_min=jnp.array(0.5),
        r_max=jnp.array(10.0),
    )
    st_ = accumulate(spec, rays)
    H = np.zeros((4, 3), int)
    M = np.zeros((4, 3), int)
    R = np.zeros((4, 3))
    # ray 0: (0.5,0.5) -> (2.5,0.5): misses cells (0,0),(1,0), hit in (2,0)
    M[0, 0] += 1
    M[1, 0] += 1
    H[2, 0] += 1  # noqa: E702
    R[0, 0] += 0.5
    R[1, 0] += 1.0
    R[2, 0] += 0.5  # noqa: E702
    # ray 1: SUB -> ignored
    # ray 2: SUP along row 2 from x=0.5 to the border x=4: misses everywhere
    M[:, 2] += 1
    R[0, 2] += 0.5
    R[1:, 2] += 1.0  # noqa: E702
    # ray 3: (3.5,1.5) -> (2.5,1.5): miss in (3,1), hit in (2,1) at its boundary... no: the
    # endpoint x=2.5 lies inside cell 2
    M[3, 1] += 1
    H[2, 1] += 1  # noqa: E702
    R[3, 1] += 0.5
    R[2, 1] += 0.5  # noqa: E702
    np.testing.assert_array_equal(np.asarray(st_.hits), H)
    np.testing.assert_array_equal(np.asarray(st_.misses), M)
    np.testing.assert_allclose(np.asarray(st_.lengths), R, atol=1e-12)
    # SUB rays as hits: ray 1 adds a hit at (0,0) with length 0.3
    st2 = accumulate(spec, rays, sub_rays="hit")
    assert int(st2.hits[0, 0]) == 1 and abs(float(st2.lengths[0, 0]) - 0.8) < 1e-12


@pytest.mark.parametrize("dim", [2, 3])
def test_accumulate_matches_reference_on_random_rays(dim):
    rng = np.random.default_rng(dim)
    n = 300
    shape = (9, 7) if dim == 2 else (6, 5, 4)
    lo = np.full(dim, -0.3)
    res = 0.25
    origins = rng.uniform(-0.5, 2.0, (n, dim))
    d = rng.normal(size=(n, dim))
    d[: n // 10, 1:] = 0.0  # some axis-parallel rays
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ranges = rng.uniform(0.0, 3.0, n)
    ranges[:5] = 0.0
    rays = RayBatch(
        origins=jnp.asarray(origins),
        directions=jnp.asarray(d),
        ranges=jnp.asarray(ranges),
        kind=jnp.asarray(rng.choice([HIT, SUB, SUP], n, p=[0.7, 0.1, 0.2])).astype(jnp.int32),
        r_min=jnp.array(0.1),
        r_max=jnp.array(2.5),
    )
    # small chunk size: several chunks plus padding must give identical results
    stats = accumulate(GridSpec(lo, res, shape), rays, chunk_size=64)
    H, M, R = reference_stats(lo, res, shape, rays)
    np.testing.assert_array_equal(np.asarray(stats.hits), H)
    np.testing.assert_array_equal(np.asarray(stats.misses), M)
    np.testing.assert_allclose(np.asarray(stats.lengths), R, atol=1e-9)
    # chunking does not change anything
    stats_big = accumulate(GridSpec(lo, res, shape), rays, chunk_size=4096)
    np.testing.assert_array_equal(np.asarray(stats_big.misses), np.asarray(stats.misses))


def test_accumulate_total_length_equals_sum_of_clipped_lengths():
    rng = np.random.default_rng(7)
    spec = GridSpec([0.0, 0.0], 0.1, (40, 30))
    poses = jaxlie.SE2.from_xy_theta(
        jnp.asarray(rng.uniform(0.5, 3.5, 20)),
        jnp.asarray(rng.uniform(0.5, 2.5, 20)),
        jnp.asarray(rng.uniform(-np.pi, np.pi, 20)),
    )
    az = jnp.linspace(-np.pi / 2, np.pi / 2, 91)
    ranges = jnp.asarray(rng.uniform(0.0, 6.0, (20, 91)))
    rays = from_scan(poses, az, ranges, 0.0, 5.0)
    stats = accumulate(spec, rays)
    flat = rays.flatten()
    lo, hi = np.zeros(2), np.array([4.0, 3.0])
    total = 0.0
    for o, d, length in zip(
        np.asarray(flat.origins), np.asarray(flat.directions), np.asarray(flat.mapping_lengths())
    ):
        iv = clip_interval(lo, hi, o, d, length)
        total += 0.0 if iv is None else iv[1] - iv[0]
    assert abs(float(stats.lengths.sum()) - total) < 1e-9
    end = np.asarray(flat.endpoints())
    inside = np.all((end >= lo) & (end < hi), axis=1) & (np.asarray(flat.kind) == HIT)
    assert int(inside.sum()) > 100
    assert int(stats.hits.sum()) == int(inside.sum())


def test_accumulate_rejects_bad_input():
    spec = GridSpec([0.0, 0.0], 0.1, (5, 5))
    rays3 = RayBatch(
        origins=jnp.zeros((2, 3)),
        directions=jnp.ones((2, 3)),
        ranges=jnp.ones(2),
        kind=jnp.zeros(2, jnp.int32),
        r_min=jnp.array(0.0),
        r_max=jnp.array(1.0),
    )
    with pytest.raises(ValueError, match="3-D"):
        accumulate(spec, rays3)
    with pytest.raises(ValueError, match="sub_rays"):
        accumulate(GridSpec(jnp.zeros(3), 0.1, (2, 2, 2)), rays3, sub_rays="maybe")
    empty = RayBatch(
        origins=jnp.zeros((0, 2)),
        directions=jnp.zeros((0, 2)),
        ranges=jnp.zeros(0),
        kind=jnp.zeros(0, jnp.int32),
        r_min=jnp.array(0.0),
        r_max=jnp.array(1.0),
    )
    with pytest.raises(ValueError, match="empty"):
        accumulate(spec, empty)


def test_gridspec_validation_and_helpers():
    with pytest.raises(ValueError, match="resolution"):
        GridSpec([0.0, 0.0], 0.0, (3, 3))
    with pytest.raises(ValueError, match="shape"):
        GridSpec([0.0, 0.0], 0.1, (3,))
    with pytest.raises(ValueError, match="origin"):
        GridSpec([0.0, 0.0, 0.0], 0.1, (3, 3))
    spec = GridSpec.covering(np.array([[0.03, -0.52], [1.0, 2.0]]), 0.1, margin=0.0)
    assert np.all(np.asarray(spec.origin) <= np.array([0.03, -0.52]))
    assert np.all(np.asarray(spec.upper) >= np.array([1.0, 2.0]))
    centers = spec.cell_centers()
    assert centers.shape == (*spec.shape, 2)
    np.testing.assert_array_equal(
        np.asarray(spec.cell_of(centers)), np.stack(np.indices(spec.shape), -1)
    )


def test_traverse_rays_matches_single_ray_traverse():
    spec = GridSpec([0.0, 0.0], 0.1, (30, 20))
    T = jaxlie.SE2.from_xy_theta(
        jnp.array([1.0, 2.0]), jnp.array([1.0, 0.5]), jnp.array([0.3, 2.0])
    )
    az = jnp.linspace(-1.5, 1.5, 5)
    ranges = jnp.array([[0.5, 1.0, 9.0, 0.0, 2.0], [0.2, 3.0, 0.7, 1.1, 9.5]])
    rays = from_scan(T, az, ranges, 0.1, 4.0)
    tr = traverse_rays(spec, rays)
    assert tr.cells.shape[:2] == (2, 5) and bool(jnp.all(tr.complete))
    for s in range(2):
        for b in range(5):
            length = float(rays.mapping_lengths()[s, b])
            one = traverse(
                spec, rays.origins[s, b], rays.directions[s, b], length, tr.cells.shape[2]
            )
            np.testing.assert_array_equal(np.asarray(one.valid), np.asarray(tr.valid[s, b]))
            np.testing.assert_allclose(np.asarray(one.lengths), np.asarray(tr.lengths[s, b]))


def test_accumulate_float64_numpy_rays_without_x64_warn_nothing():
    """float64 NumPy rays (the NumPy default) in a float32 process are float32 rays: the
    same statistics as the float32 batch, and no dtype-truncation warning."""
    with jax.enable_x64(False):  # the suite runs with x64 on
        _float64_rays_in_float32_process()


def _float64_rays_in_float32_process():
    import warnings

    from lidarjax.rays import HIT, RayBatch

    spec = GridSpec(np.zeros(2), 0.1, (40, 40))
    rng = np.random.default_rng(0)
    a = rng.uniform(-np.pi, np.pi, 300)
    o, d = rng.uniform(0.5, 3.5, (300, 2)), np.stack([np.cos(a), np.sin(a)], 1)
    r = rng.uniform(0.1, 2.0, 300)
    rays64 = RayBatch(o, d, r, np.full(300, HIT), 0.0, 5.0)
    rays32 = RayBatch(*(x.astype(np.float32) for x in (o, d, r)), np.full(300, HIT), 0.0, 5.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        s64 = accumulate(spec, rays64, backend="jax")
    s32 = accumulate(spec, rays32, backend="jax")
    assert s64.lengths.dtype == np.float32
    np.testing.assert_array_equal(np.asarray(s64.hits), np.asarray(s32.hits))
    np.testing.assert_array_equal(np.asarray(s64.lengths), np.asarray(s32.lengths))
