"""Tests for lidarjax.sensor_models: decay-rate (Eqs. 7.13, 7.16), reflection (Eqs. 7.23,
7.32) and endpoint models, against hand-worked scenes and a slow NumPy reference."""

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from lidarjax.maps import DecayRateMap, EndpointMap, ReflectionMap, endpoint_map
from lidarjax.rays import HIT, SUB, SUP, RayBatch, from_scan
from lidarjax.raytrace import GridSpec, GridStats
from lidarjax.sensor_models import (
    decay_rate_log_likelihood,
    endpoint_log_likelihood,
    log_likelihood_at_poses,
    ray_log_likelihoods_at_poses,
    reflection_log_likelihood,
)
from lidarjax.testing import finite_difference

# ---------------------------------------------------------------------------------------
# Independent NumPy reference: dense list of all grid-line crossings along the ray.


def _breaks(origin, res, shape, o, d, t0, t1):
    """Sorted ray parameters in [t0, t1] where the ray crosses any grid line (plus t0, t1),
    and the crossing parameters beyond t1 (for chords)."""
    ts = []
    for k in range(len(shape)):
        if d[k] == 0:
            continue
        for i in range(shape[k] + 1):
            ts.append((origin[k] + i * res - o[k]) / d[k])
    ts = np.array(ts)
    inner = ts[(ts > t0) & (ts < t1)]
    return np.unique(np.concatenate([[t0, t1], inner])), np.sort(ts[ts > t1])


def _segments(origin, res, shape, o, d, t0, t1):
    """(cells [s d] or None if outside, lengths [s], starts [s]) of the ray on [t0, t1]."""
    b, beyond = _breaks(origin, res, shape, o, d, t0, t1)
    segs = []
    for a, c in zip(b[:-1], b[1:]):
        if c - a <= 0:
            continue
        mid = o + 0.5 * (a + c) * d
        cell = np.floor((mid - origin) / res).astype(int)
        inside = np.all(cell >= 0) and np.all(cell < np.array(shape))
        segs.append((tuple(cell) if inside else None, c - a, a))
    return segs, beyond


def _far(origin, res, shape, o, d):
    """A parameter beyond which the ray is surely outside the grid."""
    return float(np.linalg.norm(o - origin) + res * np.linalg.norm(shape) + 1.0)


def _ref_decay(rates, outside, origin, res, shape, o, d, r, kind, r_min, r_max):
    length = {HIT: r, SUB: r_min, SUP: r_max}[kind]
    t1 = min(length, _far(origin, res, shape, o, d))
    segs, _ = _segments(origin, res, shape, o, d, 0.0, t1)
    in_len = sum(s[1] for s in segs if s[0] is not None)
    depth = sum(rates[s[0]] * s[1] for s in segs if s[0] is not None)
    out_len = length - in_len
    depth += 0.0 if (outside == 0 or out_len == 0) else outside * out_len
    if kind == HIT:
        lam = rates[segs[-1][0]] if segs[-1][0] is not None else outside
        return (np.log(lam) if lam > 0 else -np.inf) - depth
    if kind == SUB:
        return np.log(-np.expm1(-depth)) if depth > 0 else -np.inf
    return -depth


def _ref_reflection(probs, q_out, origin, res, shape, o, d, r, kind, r_min, r_max):
    length = {HIT: r, SUB: r_min, SUP: r_max}[kind]
    t1 = min(length, _far(origin, res, shape, o, d))
    segs, beyond = _segments(origin, res, shape, o, d, 0.0, t1)
    in_len = sum(s[1] for s in segs if s[0] is not None)
    ends_inside = segs[-1][0] is not None and t1 == length
    full = segs[:-1] if ends_inside else segs
    log_s = sum(np.log(1 - probs[s[0]]) for s in full if s[0] is not None)
    log_s += (length - in_len) / res * np.log(1 - q_out)
    if ends_inside:
        cell, seg_len, start = segs[-1]
        chord = beyond[0] - start  # next grid-line crossing after the end point
        q = probs[cell]
        hit = log_s + np.log(q) - np.log(chord)
        surv = log_s + np.log(1 - q * seg_len / chord)
    else:
        hit = log_s + np.log(-np.log(1 - q_out) / res)
        surv = log_s
    if kind == HIT:
        return hit
    if kind == SUB:
        return np.log(-np.expm1(surv))
    return surv


def _ref_endpoint(
    dist, sigma, z_hit, z_rand, p_out, origin, res, shape, o, d, r, kind, r_min, r_max
):
    if kind != HIT:
        return np.log(p_out)

    def field(cell):
        g = 0.0 if cell is None else np.exp(-0.5 * (dist[cell] / sigma) ** 2)
        return z_hit * g / (np.sqrt(2 * np.pi) * sigma) + z_rand / r_max

    segs, _ = _segments(origin, res, shape, o, d, r_min, r_max)
    z = sum(field(s[0]) * s[1] for s in segs)
    cell = np.floor((o + r * d - origin) / res).astype(int)
    inside = np.all(cell >= 0) and np.all(cell < np.array(shape))
    return np.log(1 - p_out) + np.log(field(tuple(cell) if inside else None)) - np.log(z)


# ---------------------------------------------------------------------------------------
# Fixtures


def _rays(o, d, r, kind, r_min, r_max):
    return RayBatch(
        origins=jnp.asarray(o, jnp.float64),
        directions=jnp.asarray(d, jnp.float64),
        ranges=jnp.asarray(r, jnp.float64),
        kind=jnp.asarray(kind, jnp.int32),
        r_min=jnp.asarray(r_min, jnp.float64),
        r_max=jnp.asarray(r_max, jnp.float64),
    )


def _random_scene(seed, n=40, dim=2, r_min=0.4, r_max=7.0):
    rng = np.random.default_rng(seed)
    shape = (7, 5) if dim == 2 else (4, 5, 3)
    spec = GridSpec(np.full(dim, -1.0), 0.7, shape)
    lo, hi = np.asarray(spec.origin), np.asarray(spec.upper)
    o = rng.uniform(lo - 1.0, hi + 1.0, size=(n, dim))
    d = rng.normal(size=(n, dim))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    kind = rng.choice([HIT, HIT, HIT, SUB, SUP], size=n)
    r = np.where(kind == HIT, rng.uniform(r_min, r_max, n), 0.0)
    r = np.where(kind == SUB, r_min * 0.5, r)
    r = np.where(kind == SUP, r_max + 1.0, r)
    return rng, spec, _rays(o, d, r, kind, r_min, r_max)


def _ray_args(spec, rays, i):
    return (
        np.asarray(spec.origin),
        float(spec.resolution),
        spec.shape,
        np.asarray(rays.origins[i]),
        np.asarray(rays.directions[i]),
        float(rays.ranges[i]),
        int(rays.kind[i]),
        float(rays.r_min),
        float(rays.r_max),
    )


# ---------------------------------------------------------------------------------------
# Hand-worked corridor: cells of 1 m along x, lambda = (0.5, 1, 2), q = (0.2, 0.5, 0.4).

CORRIDOR = GridSpec([0.0, 0.0], 1.0, (3, 1))


def _corridor_rays():
    # from x = 0.2 along +x: HIT at 2.5 (x = 2.7, in cell 2), SUB, SUP with r_max = 10.
    return _rays([[0.2, 0.5]] * 3, [[1.0, 0.0]] * 3, [2.5, 0.1, 10.0], [HIT, SUB, SUP], 0.5, 10.0)


def test_decay_rate_corridor_by_hand():
    m = DecayRateMap(CORRIDOR, jnp.array([[0.5], [1.0], [2.0]]), jnp.array(0.1))
    ll = np.asarray(decay_rate_log_likelihood(m, _corridor_rays()))
    # HIT: d = (0.8, 1.0, 0.7): log 2 - (0.5*0.8 + 1*1 + 2*0.7)
    np.testing.assert_allclose(ll[0], np.log(2.0) - 2.8, rtol=1e-12)
    # SUB: Lambda(r_min = 0.5) = 0.5 * 0.5
    np.testing.assert_allclose(ll[1], np.log(1 - np.exp(-0.25)), rtol=1e-12)
    # SUP: Lambda(10) = 0.4 + 1 + 2 + 0.1 * (10 - 2.8)
    np.testing.assert_allclose(ll[2], -(3.4 + 0.72), rtol=1e-12)


def test_reflection_corridor_by_hand():
    m = ReflectionMap(CORRIDOR, jnp.array([[0.2], [0.5], [0.4]]), jnp.array(0.1))
    ll = np.asarray(reflection_log_likelihood(m, _corridor_rays()))
    # HIT in cell 2: P = 0.4 * 0.8 * 0.5, chord of cell 2 = 1 m (Eq. 7.32).
    np.testing.assert_allclose(ll[0], np.log(0.16), rtol=1e-12)
    # SUB at r_min = 0.5 inside cell 0, whose chord from the sensor is 0.8 m:
    # P(sub) = q_0 * 0.5 / 0.8.
    np.testing.assert_allclose(ll[1], np.log(0.2 * 0.5 / 0.8), rtol=1e-12)
    # SUP: all three cells fully traversed, then 7.2 m outside = 7.2 cells of q = 0.1.
    np.testing.assert_allclose(ll[2], np.log(0.8 * 0.5 * 0.6) + 7.2 * np.log(0.9), rtol=1e-12)
    # HIT density in the first cell uses the chord from the sensor (0.8 m), not 1 m.
    first = _rays([[0.2, 0.5]], [[1.0, 0.0]], [0.6], [HIT], 0.5, 10.0)
    np.testing.assert_allclose(reflection_log_likelihood(m, first)[0], np.log(0.2 / 0.8))


def test_reflection_chord_is_full_cell_path_diagonal():
    # A diagonal ray through a single cell: chord = sqrt(2) regardless of the range.
    spec = GridSpec([0.0, 0.0], 1.0, (1, 1))
    m = ReflectionMap(spec, jnp.array([[0.3]]), jnp.array(0.0))
    s = np.sqrt(0.5)
    rays = _rays([[0.0, 0.0]] * 2, [[s, s]] * 2, [0.3, 1.2], [HIT, HIT], 0.0, 5.0)
    np.testing.assert_allclose(
        reflection_log_likelihood(m, rays), np.log(0.3 / np.sqrt(2.0)) * np.ones(2)
    )


def test_endpoint_corridor_by_hand():
    spec = GridSpec([0.0, 0.0], 1.0, (4, 1))
    hits = jnp.array([[0], [0], [0], [1]], jnp.int32)
    z = jnp.zeros((4, 1), jnp.int32)
    em = endpoint_map(
        GridStats(spec, hits, z, jnp.zeros((4, 1))),
        sigma_m=1.0,
        z_hit=1.0,
        z_rand=0.0,
        p_out=0.1,
    )
    np.testing.assert_allclose(em.distances[:, 0], [3.0, 2.0, 1.0, 0.0])
    rays = _rays([[0.0, 0.5]] * 3, [[1.0, 0.0]] * 3, [2.5, 0.1, 9.0], [HIT, SUB, SUP], 1.0, 8.0)
    ll = np.asarray(endpoint_log_likelihood(em, rays))
    g = lambda x: np.exp(-0.5 * x * x) / np.sqrt(2 * np.pi)  # noqa: E731
    z_norm = g(2.0) + g(1.0) + g(0.0)  # cells 1..3 each 1 m inside [r_min, r_max]
    np.testing.assert_allclose(ll[0], np.log(0.9 * g(1.0) / z_norm), rtol=1e-12)
    np.testing.assert_allclose(ll[1:], np.log(0.1), rtol=1e-12)


# ---------------------------------------------------------------------------------------
# Random scenes against the NumPy reference


@pytest.mark.parametrize("dim", [2, 3])
def test_decay_rate_matches_numpy_reference(dim):
    rng, spec, rays = _random_scene(3 + dim, dim=dim)
    rates = rng.uniform(0.0, 1.5, spec.shape) * (rng.random(spec.shape) > 0.1)
    m = DecayRateMap(spec, jnp.asarray(rates), jnp.asarray(0.2))
    ll = np.asarray(decay_rate_log_likelihood(m, rays))
    ref = [_ref_decay(rates, 0.2, *_ray_args(spec, rays, i)) for i in range(rays.n)]
    np.testing.assert_allclose(ll, ref, rtol=1e-10, atol=1e-10)
    assert not np.any(np.isnan(ll))


def test_decay_rate_infinite_r_max():
    _, spec, rays = _random_scene(11, n=10, r_max=7.0)
    rays = _rays(rays.origins, rays.directions, rays.ranges, rays.kind, 0.4, np.inf)
    for outside, sup_value in [(0.2, -np.inf), (0.0, None)]:
        m = DecayRateMap(spec, jnp.full(spec.shape, 0.5), jnp.asarray(outside))
        ll = np.asarray(decay_rate_log_likelihood(m, rays))
        assert not np.any(np.isnan(ll))
        sup = ll[np.asarray(rays.kind) == SUP]
        if sup_value is not None:
            assert np.all(sup == sup_value)
        else:
            assert np.all(np.isfinite(sup))


def test_reflection_matches_numpy_reference():
    rng, spec, rays = _random_scene(21)
    probs = rng.uniform(0.05, 0.9, spec.shape)
    m = ReflectionMap(spec, jnp.asarray(probs), jnp.asarray(0.15))
    ll = np.asarray(reflection_log_likelihood(m, rays))
    ref = [_ref_reflection(probs, 0.15, *_ray_args(spec, rays, i)) for i in range(rays.n)]
    np.testing.assert_allclose(ll, ref, rtol=1e-9, atol=1e-9)


def test_endpoint_matches_numpy_reference():
    rng, spec, rays = _random_scene(31)
    hits = (rng.random(spec.shape) < 0.15).astype(np.int32)
    misses = rng.integers(0, 3, spec.shape).astype(np.int32)
    stats = GridStats(spec, jnp.asarray(hits), jnp.asarray(misses), jnp.ones(spec.shape))
    em = endpoint_map(stats, sigma_m=0.5, z_hit=0.8, z_rand=0.2, p_out=0.07)
    ll = np.asarray(endpoint_log_likelihood(em, rays))
    idx = np.argwhere(hits > 0)
    dist = np.zeros(spec.shape)
    for c in np.ndindex(*spec.shape):
        dist[c] = np.sqrt(((idx - np.array(c)) ** 2).sum(1)).min() * 0.7
    ref = [
        _ref_endpoint(dist, 0.5, 0.8, 0.2, 0.07, *_ray_args(spec, rays, i)) for i in range(rays.n)
    ]
    np.testing.assert_allclose(ll, ref, rtol=1e-10, atol=1e-10)


# ---------------------------------------------------------------------------------------
# Normalisation: HIT densities over [r_min, r_max) + P(sub) + P(sup) = 1


def _total_probability(fn, m, spec, o, d, r_min, r_max, n_out=2):
    """Integrate the HIT density piecewise (Gauss-Legendre between all grid-line crossings,
    which bound the pieces where the density is smooth) and add P(sub) + P(sup) (only
    P(sup) for ``n_out=1``: the endpoint model's single out-of-range outcome)."""
    b, _ = _breaks(np.asarray(spec.origin), float(spec.resolution), spec.shape, o, d, r_min, r_max)
    x, w = np.polynomial.legendre.leggauss(10)
    rs, ws = [], []
    for a, c in zip(b[:-1], b[1:]):
        rs.append(0.5 * (c - a) * x + 0.5 * (a + c))
        ws.append(0.5 * (c - a) * w)
    rs, ws = np.concatenate(rs), np.concatenate(ws)
    n = 600  # fixed size (one compilation): pad with zero-weight nodes
    assert rs.size <= n
    rs = np.concatenate([rs, np.full(n - rs.size, rs[0])])
    ws = np.concatenate([ws, np.zeros(n - ws.size)])
    kinds = np.concatenate([np.full(n, HIT), [SUB, SUP]])
    ranges = np.concatenate([rs, [0.5 * r_min, r_max + 1]])
    rays = _rays(np.tile(o, (n + 2, 1)), np.tile(d, (n + 2, 1)), ranges, kinds, r_min, r_max)
    p = np.exp(np.asarray(fn(m, rays)))
    return float(np.sum(ws * p[:n]) + np.sum(p[n + 2 - n_out :]))


@pytest.mark.parametrize("model", ["decay", "reflection", "endpoint"])
def test_models_are_normalised(model):
    rng = np.random.default_rng(5)
    spec = GridSpec([0.0, 0.0], 1.0, (8, 6))
    if model == "decay":
        m = DecayRateMap(spec, jnp.asarray(rng.uniform(0, 0.6, spec.shape)), jnp.asarray(0.05))
        fn = decay_rate_log_likelihood
    elif model == "reflection":
        m = ReflectionMap(spec, jnp.asarray(rng.uniform(0, 0.5, spec.shape)), jnp.asarray(0.1))
        fn = reflection_log_likelihood
    else:
        hits = jnp.asarray(rng.random(spec.shape) < 0.1, jnp.int32)
        z = jnp.zeros(spec.shape, jnp.int32)
        m = endpoint_map(GridStats(spec, hits, z, jnp.ones(spec.shape)), sigma_m=0.6, p_out=0.2)
        fn = endpoint_log_likelihood
    for _ in range(4):
        o = rng.uniform([-2.0, -2.0], [10.0, 8.0])
        ang = rng.uniform(0, 2 * np.pi)
        d = np.array([np.cos(ang), np.sin(ang)])
        n_out = 1 if model == "endpoint" else 2  # endpoint: (1 - P) in range + P out of range
        total = _total_probability(fn, m, spec, o, d, 0.3, 12.0, n_out)
        np.testing.assert_allclose(total, 1.0, atol=1e-6)


# ---------------------------------------------------------------------------------------
# -inf, NaN-freedom, gradients


def _scan_loglik(fn, m, az, ranges, r_min, r_max):
    def f(pose):
        T = jaxlie.SE2.from_xy_theta(pose[0], pose[1], pose[2])
        return jnp.sum(fn(m, from_scan(T, az, ranges, r_min, r_max)))

    return f


def test_zero_rate_reflecting_cell_is_minus_inf_without_nan():
    m = DecayRateMap(CORRIDOR, jnp.array([[0.5], [1.0], [0.0]]), jnp.array(0.1))
    rays = _corridor_rays()

    def by_rates(r):
        return decay_rate_log_likelihood(DecayRateMap(CORRIDOR, r, jnp.array(0.1)), rays)

    @jax.jit
    def value_and_vjp(r):
        ll, vjp = jax.vjp(by_rates, r)
        return ll, vjp(jnp.ones(3))[0]

    ll, g_map = value_and_vjp(m.rates)
    assert float(ll[0]) == -np.inf and np.all(np.isfinite(np.asarray(ll[1:])))
    assert not np.any(np.isnan(np.asarray(g_map)))
    pose = jnp.array([0.2, 0.5, 0.0])
    for model_map, fn in [
        (m, decay_rate_log_likelihood),
        (
            ReflectionMap(CORRIDOR, jnp.array([[0.5], [1.0], [0.0]]), jnp.array(0.1)),
            reflection_log_likelihood,
        ),
    ]:
        f = _scan_loglik(fn, model_map, jnp.array([0.0]), jnp.array([2.5]), 0.5, 10.0)
        value, g = jax.jit(jax.value_and_grad(f))(pose)
        assert float(value) == -np.inf
        assert not np.any(np.isnan(np.asarray(g)))


def test_degenerate_inputs_nan_free():
    # Ray along a cell boundary, zero-length HIT, SUP/HIT ending on the grid border, with
    # q = 1 everywhere (-inf values) and a finite decay-rate map.
    spec = GridSpec([0.0, 0.0], 1.0, (3, 3))
    rays = _rays(
        [[0.0, 1.0], [1.5, 1.5], [0.5, 0.5], [0.5, 0.5]],
        [[1.0, 0.0], [0.0, 1.0], [1.0, 0.0], [1.0, 0.0]],
        [2.0, 0.0, 5.0, 2.5],
        [HIT, HIT, SUP, HIT],
        0.0,
        5.0,
    )
    for m, fn in [
        (DecayRateMap(spec, jnp.ones((3, 3)), jnp.array(0.0)), decay_rate_log_likelihood),
        (ReflectionMap(spec, jnp.full((3, 3), 1.0), jnp.array(1.0)), reflection_log_likelihood),
    ]:

        @jax.jit
        def value_and_vjp(o, m=m, fn=fn):
            ll, vjp = jax.vjp(
                lambda o: fn(m, _rays(o, rays.directions, rays.ranges, rays.kind, 0, 5)), o
            )
            return ll, vjp(jnp.ones(4))[0]

        ll, g = value_and_vjp(rays.origins)
        assert not np.any(np.isnan(np.asarray(ll)))
        assert not np.any(np.isnan(np.asarray(g)))


@pytest.mark.parametrize("model", ["decay", "reflection"])
def test_pose_gradient_matches_finite_differences(model):
    rng = np.random.default_rng(8)
    spec = GridSpec([-3.0, -3.0], 0.5, (12, 12))
    if model == "decay":
        m = DecayRateMap(spec, jnp.asarray(rng.uniform(0.05, 1.0, spec.shape)), jnp.asarray(0.1))
        fn = decay_rate_log_likelihood
    else:
        m = ReflectionMap(spec, jnp.asarray(rng.uniform(0.05, 0.6, spec.shape)), jnp.asarray(0.1))
        fn = reflection_log_likelihood
    az = jnp.linspace(-np.pi, np.pi, 13)[:-1]
    # beams: one SUB (0.05 < r_min), one SUP (9 > r_max), the rest HITs
    ranges = jnp.asarray(rng.uniform(0.1, 4.0, 12)).at[0].set(0.05).at[1].set(9.0)
    f = jax.jit(_scan_loglik(fn, m, az, ranges, 0.2, 6.0))
    pose = jnp.array([0.13, -0.27, 0.31])
    assert np.isfinite(float(f(pose)))
    g = jax.jit(jax.grad(f))(pose)
    np.testing.assert_allclose(g, finite_difference(f, pose, eps=1e-6), rtol=1e-5, atol=1e-6)
    assert np.linalg.norm(np.asarray(g)) > 1e-3
    np.testing.assert_allclose(jax.jit(jax.jacfwd(f))(pose), g, rtol=1e-10, atol=1e-10)


# ---------------------------------------------------------------------------------------
# Pose batching


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_log_likelihood_at_poses_matches_direct_evaluation():
    rng = np.random.default_rng(4)
    spec = GridSpec([-3.0, -3.0], 0.5, (12, 12))
    m = DecayRateMap(spec, jnp.asarray(rng.uniform(0.05, 1.0, spec.shape)), jnp.asarray(0.1))
    az = jnp.linspace(-1.5, 1.5, 9)
    ranges = jnp.asarray(rng.uniform(0.1, 7.0, 9))
    poses = jnp.asarray(rng.uniform([-1, -1, -np.pi], [1, 1, np.pi], (7, 3)))
    T = jaxlie.SE2.from_xy_theta(poses[:, 0], poses[:, 1], poses[:, 2])
    direct = decay_rate_log_likelihood(m, from_scan(T, az, ranges[None], 0.2, 6.0))
    # per-ray variant, chunked into 3 lax.map steps of 3 poses (last one padded)
    per_ray = ray_log_likelihoods_at_poses(m, az, ranges, poses, r_min=0.2, r_max=6.0, chunk_size=3)
    assert per_ray.shape == (7, 9)
    np.testing.assert_allclose(per_ray, direct, rtol=1e-12)
    # summed variant, SE2 poses and a model callable
    via_fn = log_likelihood_at_poses(
        lambda rays: decay_rate_log_likelihood(m, rays), az, ranges, T, r_min=0.2, r_max=6.0
    )
    np.testing.assert_allclose(via_fn, direct.sum(-1), rtol=1e-12)
    em = EndpointMap(
        spec,
        jnp.ones(spec.shape),
        jnp.zeros(spec.shape, bool),
        *map(jnp.asarray, [1.0, 0.5, 0.5, 0.1]),
    )
    v = log_likelihood_at_poses(em, az, ranges, poses, r_min=0.2, r_max=6.0)
    assert v.shape == (7,) and np.all(np.isfinite(np.asarray(v)))


# ---------------------------------------------------------------------------------------
# Bad inputs


def test_bad_inputs_raise_value_error():
    dm = DecayRateMap(CORRIDOR, jnp.ones((3, 1)), jnp.array(0.1))
    rm = ReflectionMap(CORRIDOR, jnp.full((3, 1), 0.5), jnp.array(0.1))
    rays = _corridor_rays()
    rays3 = _rays([[0.0, 0.0, 0.0]], [[1.0, 0.0, 0.0]], [1.0], [HIT], 0.0, 5.0)
    with pytest.raises(ValueError, match="map"):
        decay_rate_log_likelihood(rm, rays)
    with pytest.raises(ValueError, match="map"):
        reflection_log_likelihood(dm, rays)
    with pytest.raises(ValueError, match="map"):
        endpoint_log_likelihood(dm, rays)
    with pytest.raises(ValueError, match="rays"):
        decay_rate_log_likelihood(dm, rays3)
    with pytest.raises(ValueError, match="rays"):
        reflection_log_likelihood(rm, rays.origins)
    with pytest.raises(ValueError, match="max_cells"):
        decay_rate_log_likelihood(dm, rays, max_cells=0)
    with pytest.raises(ValueError, match="poses"):
        log_likelihood_at_poses(dm, jnp.zeros(2), jnp.ones(2), jnp.zeros((4, 2)))
    with pytest.raises(ValueError, match="ranges_m"):
        log_likelihood_at_poses(dm, jnp.zeros(2), jnp.ones(3), jnp.zeros((4, 3)))
    with pytest.raises(ValueError, match="model"):
        log_likelihood_at_poses("nope", jnp.zeros(2), jnp.ones(2), jnp.zeros((4, 3)))
    with pytest.raises(Exception, match="max_cells"):
        jax.block_until_ready(decay_rate_log_likelihood(dm, rays, max_cells=1))
