"""Tests of the closed-form full map posteriors (ch. 8) against independent computations:
numerical integration (scipy.integrate.quad), Monte-Carlo over posterior maps (NumPy),
scipy.stats moments and distribution functions."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate, stats

from lidarjax.maps._posterior import (
    BetaPosteriorMap,
    GammaPosteriorMap,
    beta_moment_prior,
    beta_posterior,
    gamma_moment_prior,
    gamma_posterior,
    log_likelihood,
    occupancy,
)
from lidarjax.rays import HIT, SUB, SUP, RayBatch
from lidarjax.raytrace import GridSpec, GridStats, accumulate

# --------------------------------------------------------------------------------------
# Helpers and independent references
# --------------------------------------------------------------------------------------


def make_stats(spec, hits, misses, lengths):
    return GridStats(
        spec=spec,
        hits=jnp.asarray(hits, jnp.int32),
        misses=jnp.asarray(misses, jnp.int32),
        lengths=jnp.asarray(lengths, jnp.float64),
    )


def make_rays(origins, directions, ranges, kinds, r_min=0.0, r_max=100.0):
    d = np.asarray(directions, float)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return RayBatch(
        origins=jnp.asarray(origins, jnp.float64),
        directions=jnp.asarray(d),
        ranges=jnp.asarray(ranges, jnp.float64),
        kind=jnp.asarray(kinds, jnp.int32),
        r_min=jnp.asarray(r_min, jnp.float64),
        r_max=jnp.asarray(r_max, jnp.float64),
    )


def quad_ref(a, b, delta):
    """int mu^delta (1 - mu)^(1 - delta) Beta(mu; a, b) dmu."""
    f = lambda mu: mu**delta * (1 - mu) ** (1 - delta) * stats.beta.pdf(mu, a, b)
    return integrate.quad(f, 0, 1, epsabs=1e-13, epsrel=1e-11)[0]


def quad_dec(a, b, d, delta):
    """int lambda^delta exp(-lambda d) Gamma(lambda; shape a, rate b) dlambda."""
    f = lambda lam: lam**delta * np.exp(-lam * d) * stats.gamma.pdf(lam, a, scale=1 / b)
    return integrate.quad(f, 0, np.inf, epsabs=1e-14, epsrel=1e-11)[0]


def cell_lengths(lo, res, shape, o, d, length):
    """Ordered list of (cell, length) of a ray: all grid-line crossings, midpoint lookup."""
    lo, o, d = (np.asarray(x, float) for x in (lo, o, d))
    d = d / np.linalg.norm(d)
    hi = lo + np.asarray(shape) * res
    t0, t1 = 0.0, float(length)
    for k in range(len(o)):
        if d[k] == 0:
            continue
        a, b = (lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]
        t0, t1 = max(t0, min(a, b)), min(t1, max(a, b))
    if not t0 < t1:
        return [], 0.0, 0.0
    ts = {t0, t1}
    for k in range(len(o)):
        if d[k] != 0:
            for line in lo[k] + res * np.arange(shape[k] + 1):
                t = (line - o[k]) / d[k]
                if t0 < t < t1:
                    ts.add(t)
    ts = sorted(ts)
    out = []
    for a, b in zip(ts[:-1], ts[1:]):
        if b - a > 1e-12:
            cell = tuple(int(c) for c in np.floor((o + 0.5 * (a + b) * d - lo) / res))
            out.append((cell, b - a))
    return out, t0, t1


# --------------------------------------------------------------------------------------
# Per-cell closed forms vs numerical integration (Eq. 8.22 and the l_dec analogue)
# --------------------------------------------------------------------------------------

SINGLE = GridSpec([0.0, 0.0], 1.0, (1, 1))


@pytest.mark.parametrize("h,m", [(0, 0), (3, 7), (12, 1)])
def test_l_ref_single_cell_vs_quad(h, m):
    post = beta_posterior(make_stats(SINGLE, [[h]], [[m]], [[1.0]]), alpha=0.7, beta=2.5)
    a, b = h + 0.7, m + 2.5
    # HIT at 0.5 m, SUP with r_max 0.8 m, SUB with r_min 0.4 m; all inside the one cell.
    rays = make_rays(
        [[0.1, 0.5]] * 3, [[1.0, 0.0]] * 3, [0.5, 5.0, 0.1], [HIT, SUP, SUB], r_min=0.4, r_max=0.8
    )
    got = np.exp(np.asarray(log_likelihood(post, rays)))
    want = [quad_ref(a, b, 1), quad_ref(a, b, 0), 1 - quad_ref(a, b, 0)]
    np.testing.assert_allclose(got, want, rtol=1e-9)


@pytest.mark.parametrize("h,r", [(0, 0.0), (2, 3.5), (9, 0.8)])
def test_l_dec_single_cell_vs_quad(h, r):
    post = gamma_posterior(make_stats(SINGLE, [[h]], [[1]], [[r]]), alpha=1.3, beta=0.6)
    a, b = h + 1.3, r + 0.6
    rays = make_rays(
        [[0.1, 0.5]] * 3, [[1.0, 0.0]] * 3, [0.5, 5.0, 0.1], [HIT, SUP, SUB], r_min=0.4, r_max=0.8
    )
    got = np.exp(np.asarray(log_likelihood(post, rays)))
    want = [quad_dec(a, b, 0.5, 1), quad_dec(a, b, 0.8, 0), 1 - quad_dec(a, b, 0.4, 0)]
    np.testing.assert_allclose(got, want, rtol=1e-8)


ROW = GridSpec([0.0, 0.0], 1.0, (4, 1))
ROW_H = [[2], [0], [5], [1]]
ROW_M = [[4], [3], [1], [0]]
ROW_R = [[3.0], [2.5], [1.2], [0.0]]


def test_l_ref_multi_cell_vs_quad():
    post = beta_posterior(make_stats(ROW, ROW_H, ROW_M, ROW_R), alpha=1.5, beta=0.5)
    a = np.ravel(ROW_H) + 1.5
    b = np.ravel(ROW_M) + 0.5
    # HIT: from x=0.4 to x=2.6 -> cells 0, 1 miss, cell 2 reflects.
    # SUP: r_max = 3.3 from x=0.4 -> cells 0..3 miss.  SUB: r_min = 1.9 -> cells 0, 1, 2.
    rays = make_rays(
        [[0.4, 0.5]] * 3, [[1.0, 0.0]] * 3, [2.2, 9.0, 0.5], [HIT, SUP, SUB], r_min=1.9, r_max=3.3
    )
    got = np.exp(np.asarray(log_likelihood(post, rays)))
    miss = [quad_ref(a[i], b[i], 0) for i in range(4)]
    want = [
        miss[0] * miss[1] * quad_ref(a[2], b[2], 1),
        np.prod(miss),
        1 - miss[0] * miss[1] * miss[2],
    ]
    np.testing.assert_allclose(got, want, rtol=1e-9)


def test_l_dec_multi_cell_vs_quad():
    post = gamma_posterior(make_stats(ROW, ROW_H, ROW_M, ROW_R), alpha=0.8, beta=0.3)
    a = np.ravel(ROW_H) + 0.8
    b = np.ravel(ROW_R) + 0.3
    rays = make_rays(
        [[0.4, 0.5]] * 3, [[1.0, 0.0]] * 3, [2.2, 9.0, 0.5], [HIT, SUP, SUB], r_min=1.9, r_max=3.3
    )
    got = np.exp(np.asarray(log_likelihood(post, rays)))
    hit = quad_dec(a[0], b[0], 0.6, 0) * quad_dec(a[1], b[1], 1.0, 0) * quad_dec(a[2], b[2], 0.6, 1)
    sup = np.prod([quad_dec(a[i], b[i], d, 0) for i, d in enumerate([0.6, 1.0, 1.0, 0.7])])
    sub = 1 - np.prod([quad_dec(a[i], b[i], d, 0) for i, d in enumerate([0.6, 1.0, 0.3])])
    np.testing.assert_allclose(got, [hit, sup, sub], rtol=1e-8)


def test_l_dec_matches_printed_closed_form():
    """The unnumbered l_dec of section 8.4.5 as printed in the dissertation."""
    post = gamma_posterior(make_stats(SINGLE, [[4]], [[1]], [[2.0]]), alpha=2.0, beta=1.0)
    a, b, d = 6.0, 3.0, 0.5
    rays = make_rays([[0.1, 0.5]] * 3, [[1.0, 0.0]] * 3, [d, 9.0, 0.1], [HIT, SUP, SUB], d, d)
    got = np.asarray(log_likelihood(post, rays))
    printed = lambda delta: ((b / (b + d)) ** a) * (a / (b + d)) ** delta
    np.testing.assert_allclose(np.exp(got), [printed(1), printed(0), 1 - printed(0)], rtol=1e-12)


# --------------------------------------------------------------------------------------
# Whole rays vs Monte Carlo over maps drawn from the posterior
# --------------------------------------------------------------------------------------

GRID = GridSpec([0.0, 0.0], 1.0, (3, 3))
G_H = np.array([[0, 2, 1], [3, 0, 0], [1, 4, 0]])
G_M = np.array([[5, 1, 2], [0, 2, 0], [3, 1, 0]])
G_R = np.array([[4.0, 1.5, 2.2], [0.9, 1.7, 0.0], [2.5, 0.6, 0.0]])
MC_RAYS = dict(
    origins=[[0.5, 0.2], [0.5, 0.2], [-1.0, 1.5], [1.5, -0.5], [0.5, 0.2], [2.5, 2.5]],
    directions=[[1, 1], [1, 1], [1, 0], [0, 1], [1, 1], [-1, -0.3]],
    # diagonal HIT inside, diagonal SUP leaving the grid, HIT entering from outside,
    # HIT ending outside after crossing, SUB, HIT in unvisited cells.
    ranges=[2.4, 20.0, 2.7, 5.0, 0.1, 1.9],
    kinds=[HIT, SUP, HIT, HIT, SUB, HIT],
)
R_MIN, R_MAX = 1.3, 6.0


def _forward_per_map(values, alpha_beta_draw_out, rays_np, model):
    """Forward likelihood of every ray for each drawn map, by NumPy (independent path)."""
    out = []
    n_draw = values.shape[0]
    for o, d, rng, kind in rays_np:
        d = np.asarray(d, float) / np.linalg.norm(d)
        length = {HIT: rng, SUB: R_MIN, SUP: R_MAX}[kind]
        segs, t0, t1 = cell_lengths(GRID.origin, 1.0, GRID.shape, o, d, length)
        ends_inside = bool(segs) and t1 >= length - 1e-9
        r_out = length - (t1 - t0)
        like = np.ones(n_draw)
        for k, (cell, seg) in enumerate(segs):
            v = values[:, cell[0], cell[1]]
            delta = kind == HIT and ends_inside and k == len(segs) - 1
            like *= model(v, seg, delta)
        delta_out = kind == HIT and not ends_inside
        if r_out > 1e-9 or delta_out:
            like *= model(alpha_beta_draw_out, r_out, delta_out)
        out.append(1 - like if kind == SUB else like)
    return out


def _mc_check(post, values, out_values, model):
    rays = make_rays(**MC_RAYS, r_min=R_MIN, r_max=R_MAX)
    got = np.exp(np.asarray(log_likelihood(post, rays)))
    rays_np = list(
        zip(MC_RAYS["origins"], MC_RAYS["directions"], MC_RAYS["ranges"], MC_RAYS["kinds"])
    )
    samples = _forward_per_map(values, out_values, rays_np, model)
    for g, s in zip(got, samples):
        mean, se = s.mean(), s.std(ddof=1) / np.sqrt(s.size)
        assert abs(g - mean) < 5 * se + 1e-12, (g, mean, se)


def test_reflection_likelihood_vs_monte_carlo():
    rng = np.random.default_rng(0)
    alpha, beta, n = 0.9, 1.7, 200_000
    post = beta_posterior(make_stats(GRID, G_H, G_M, G_R), alpha=alpha, beta=beta)
    mus = rng.beta(G_H + alpha, G_M + beta, size=(n, 3, 3))
    mu_out = rng.beta(alpha, beta, size=n)
    model = lambda mu, seg, delta: mu if delta else 1 - mu
    _mc_check(post, mus, mu_out, model)


def test_decay_likelihood_vs_monte_carlo():
    rng = np.random.default_rng(1)
    alpha, beta, n = 1.6, 0.8, 200_000
    post = gamma_posterior(make_stats(GRID, G_H, G_M, G_R), alpha=alpha, beta=beta)
    lams = rng.gamma(G_H + alpha, 1.0 / (G_R + beta), size=(n, 3, 3))
    lam_out = rng.gamma(alpha, 1.0 / beta, size=n)
    model = lambda lam, seg, delta: (lam if delta else 1.0) * np.exp(-lam * seg)
    _mc_check(post, lams, lam_out, model)


def test_dirac_limit_reproduces_ml_likelihood():
    """Scaling H, M, R by k -> inf concentrates the posterior at the ML map, so L(z, x)
    tends to the ML forward likelihoods (Eq. 8.23 and the ML l_dec of section 8.4.5)."""
    k = 1e7
    spec = ROW
    h, m, r = np.ravel(ROW_H[:3]) * k, np.ravel(ROW_M[:3]) * k, np.ravel(ROW_R[:3]) * k
    rays = make_rays([[0.4, 0.5]] * 3, [[1.0, 0.0]] * 3, [2.2] * 3, [HIT] * 3, r_max=3.3)
    pad = lambda x: jnp.asarray(np.append(x, 1.0)[:, None])
    one, zero = jnp.asarray(1.0, jnp.float64), jnp.asarray(0.0, jnp.float64)
    ref = BetaPosteriorMap(spec, pad(h), pad(m), one, one)
    dec = GammaPosteriorMap(spec, pad(h), pad(r), one, zero)
    q = h / (h + m)
    lam = h / r
    want_ref = (1 - q[0]) * (1 - q[1]) * q[2]
    want_dec = np.exp(-lam[0] * 0.6 - lam[1] * 1.0 - lam[2] * 0.6) * lam[2]
    np.testing.assert_allclose(np.exp(log_likelihood(ref, rays)), [want_ref] * 3, rtol=1e-5)
    np.testing.assert_allclose(np.exp(log_likelihood(dec, rays)), [want_dec] * 3, rtol=1e-5)


# --------------------------------------------------------------------------------------
# Priors and modes
# --------------------------------------------------------------------------------------


def _random_stats(seed=3, shape=(6, 5)):
    rng = np.random.default_rng(seed)
    spec = GridSpec([0.0, 0.0], 0.5, shape)
    hits = rng.integers(0, 6, shape)
    misses = rng.integers(0, 9, shape)
    lengths = rng.uniform(0.2, 4.0, shape)
    unseen = rng.random(shape) < 0.3
    hits[unseen] = 0
    misses[unseen] = 0
    lengths[unseen] = 0.0
    return make_stats(spec, hits, misses, lengths), hits, misses, lengths


def test_beta_moment_prior_reproduces_ml_moments():
    st, h, m, _ = _random_stats()
    seen = (h + m) > 0
    q = h[seen] / (h + m)[seen]
    alpha, beta = beta_moment_prior(st)
    dist = stats.beta(float(alpha), float(beta))
    np.testing.assert_allclose([dist.mean(), dist.var()], [q.mean(), q.var()], rtol=1e-10)
    post = beta_posterior(st)  # default: moments
    np.testing.assert_allclose([post.alpha, post.beta], [alpha, beta], rtol=0)


def test_gamma_moment_prior_reproduces_ml_moments():
    st, h, _, r = _random_stats()
    seen = r > 0
    lam = h[seen] / r[seen]
    alpha, beta = gamma_moment_prior(st)
    dist = stats.gamma(float(alpha), scale=1 / float(beta))
    np.testing.assert_allclose([dist.mean(), dist.var()], [lam.mean(), lam.var()], rtol=1e-10)
    post = gamma_posterior(st)
    np.testing.assert_allclose([post.alpha, post.beta], [alpha, beta], rtol=0)


def test_uniform_prior_modes_are_ml_maps():
    st, h, m, r = _random_stats(seed=5)
    ref = beta_posterior(st, prior="uniform")
    dec = gamma_posterior(st, prior="uniform")
    assert float(ref.alpha) == 1.0 and float(ref.beta) == 1.0
    assert float(dec.alpha) == 1.0 and float(dec.beta) == 0.0
    seen = (h + m) > 0
    q = np.where(seen, h / np.maximum(h + m, 1), -1.0)  # Eq. (7.22)
    lam = np.where(r > 0, h / np.where(r > 0, r, 1.0), -1.0)  # Eq. (7.10)
    np.testing.assert_allclose(ref.mode(fill_value=-1.0), q, rtol=1e-12)
    np.testing.assert_allclose(dec.mode(fill_value=-1.0), lam, rtol=1e-12)


def test_posterior_moments_match_scipy():
    st, h, m, r = _random_stats(seed=7)
    ref = beta_posterior(st, alpha=0.6, beta=2.0)
    dec = gamma_posterior(st, alpha=1.4, beta=0.5)
    np.testing.assert_allclose(ref.mean(), stats.beta.mean(h + 0.6, m + 2.0), rtol=1e-12)
    np.testing.assert_allclose(ref.variance(), stats.beta.var(h + 0.6, m + 2.0), rtol=1e-12)
    np.testing.assert_allclose(dec.mean(), stats.gamma.mean(h + 1.4, scale=1 / (r + 0.5)))
    np.testing.assert_allclose(dec.variance(), stats.gamma.var(h + 1.4, scale=1 / (r + 0.5)))
    # Mode vs a dense numerical argmax of the density.
    grid = np.linspace(1e-6, 1 - 1e-6, 200_001)
    for i, j in [(0, 0), (2, 3), (4, 1)]:
        a, b = h[i, j] + 0.6, m[i, j] + 2.0
        want = grid[np.argmax(stats.beta.logpdf(grid, a, b))]
        np.testing.assert_allclose(ref.mode()[i, j], want, atol=1e-4)


# --------------------------------------------------------------------------------------
# Occupancy (section 12.4.1)
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("mu_o", [0.0, 0.2, 0.65, 1.0])
def test_occupancy_vs_scipy(mu_o):
    st, h, m, _ = _random_stats(seed=11)
    post = beta_posterior(st, alpha=0.8, beta=1.9)
    np.testing.assert_allclose(
        occupancy(post, mu_o), stats.beta.sf(mu_o, h + 0.8, m + 1.9), rtol=1e-9, atol=1e-14
    )


# --------------------------------------------------------------------------------------
# Robustness: NaN-free, jit, batching, gradients
# --------------------------------------------------------------------------------------


def test_nan_free_on_unvisited_cells_and_improper_prior():
    spec = GridSpec([0.0, 0.0], 1.0, (3, 3))
    zeros = make_stats(spec, np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)))
    rays = make_rays(
        [[0.5, 0.5], [0.5, 0.5], [0.5, 0.5], [-5, -5], [0.5, 0.5], [1.0, 1.0]],
        [[1, 0], [1, 1], [0, 1], [1, 0], [1, 0], [1, 0]],
        [1.2, 50.0, 0.0, 1.0, 0.0, 0.0],
        [HIT, SUP, SUB, HIT, HIT, HIT],
        r_min=0.0,
        r_max=np.inf,
    )
    for post in [
        beta_posterior(zeros, prior="uniform"),
        gamma_posterior(zeros, prior="uniform"),
        gamma_posterior(zeros, alpha=2.0, beta=1.0),
    ]:
        ll = np.asarray(log_likelihood(post, rays))
        assert not np.any(np.isnan(ll)), ll
        assert ll[2] == -np.inf  # SUB with r_min = 0 is impossible
        assert np.all(np.isfinite(occupancy(beta_posterior(zeros, prior="uniform"))))
    # Uniform Beta prior on unvisited cells: each miss 1/2, the hit 1/2.
    ll = np.asarray(log_likelihood(beta_posterior(zeros, prior="uniform"), rays))
    np.testing.assert_allclose(ll[0], 2 * np.log(0.5))
    # Improper Gamma(1, 0): positive length through an unvisited cell is impossible.
    ll = np.asarray(log_likelihood(gamma_posterior(zeros, prior="uniform"), rays))
    assert ll[0] == -np.inf and ll[1] == -np.inf
    # SUP with r_max = inf under a proper gamma prior: never returning has probability 0.
    ll = np.asarray(log_likelihood(gamma_posterior(zeros, alpha=2.0, beta=1.0), rays))
    assert ll[1] == -np.inf and np.isfinite(ll[0])


def test_jit_batch_shape_and_finite_gradients():
    post = gamma_posterior(make_stats(GRID, G_H, G_M, G_R), alpha=1.2, beta=0.4)
    flat = make_rays(**MC_RAYS, r_min=R_MIN, r_max=R_MAX)
    batched = jax.tree.map(lambda x: x.reshape(2, 3, *x.shape[1:]) if x.ndim else x, flat)
    ll = log_likelihood(post, batched)
    assert ll.shape == (2, 3)
    np.testing.assert_allclose(ll.ravel(), log_likelihood(post, flat), rtol=1e-12)
    np.testing.assert_allclose(jax.jit(log_likelihood)(post, flat), ll.ravel(), rtol=1e-12)

    def total(ranges):
        r = flat
        return jnp.sum(
            log_likelihood(
                post, RayBatch(r.origins, r.directions, ranges, r.kind, r.r_min, r.r_max)
            )
        )

    g = jax.grad(total)(flat.ranges)
    assert np.all(np.isfinite(g))
    # Gradients vs central differences (all ranges lie away from cell boundaries).
    eps = 1e-6
    for i in (0, 2, 5):
        e = jnp.zeros_like(flat.ranges).at[i].set(eps)
        fd = (total(flat.ranges + e) - total(flat.ranges - e)) / (2 * eps)
        np.testing.assert_allclose(g[i], fd, rtol=1e-5)


def test_consistent_with_accumulated_stats():
    """End-to-end: stats from accumulate(), likelihood of the mapping rays is finite."""
    rng = np.random.default_rng(2)
    n = 6  # same batch shape as the other GRID tests: reuses the compiled kernel
    ang = rng.uniform(0, 2 * np.pi, n)
    rays = make_rays(
        np.tile([[1.5, 1.5]], (n, 1)),
        np.stack([np.cos(ang), np.sin(ang)], 1),
        rng.uniform(0.2, 1.4, n),
        np.full(n, HIT),
        r_max=10.0,
    )
    st = accumulate(GRID, rays)
    for post in [beta_posterior(st), gamma_posterior(st)]:
        ll = np.asarray(log_likelihood(post, rays))
        assert np.all(np.isfinite(ll))


# --------------------------------------------------------------------------------------
# Input validation
# --------------------------------------------------------------------------------------


def test_bad_inputs_raise_value_error_naming_argument():
    st, *_ = _random_stats()
    with pytest.raises(ValueError, match="alpha"):
        beta_posterior(st, alpha=-1.0, beta=1.0)
    with pytest.raises(ValueError, match="beta"):
        beta_posterior(st, alpha=1.0, beta=0.0)
    with pytest.raises(ValueError, match="beta"):
        gamma_posterior(st, alpha=1.0, beta=-0.1)
    with pytest.raises(ValueError, match="alpha and beta"):
        gamma_posterior(st, alpha=1.0)
    with pytest.raises(ValueError, match="prior"):
        beta_posterior(st, prior="flat")
    with pytest.raises(ValueError, match="stats"):
        beta_posterior(np.zeros((3, 3)))
    one = make_stats(SINGLE, [[1]], [[2]], [[1.0]])
    with pytest.raises(ValueError, match="stats"):
        beta_posterior(one)
    same = make_stats(ROW, [[1]] * 4, [[1]] * 4, [[1.0]] * 4)
    with pytest.raises(ValueError, match="stats"):
        gamma_posterior(same)
    post = beta_posterior(st, prior="uniform")
    with pytest.raises(ValueError, match="posterior_map"):
        log_likelihood(st, make_rays([[0, 0]], [[1, 0]], [1.0], [HIT]))
    with pytest.raises(ValueError, match="rays"):
        log_likelihood(post, make_rays([[0, 0, 0]], [[1, 0, 0]], [1.0], [HIT]))
    with pytest.raises(ValueError, match="mu_o"):
        occupancy(post, 1.5)
    with pytest.raises(ValueError, match="beta_map"):
        occupancy(gamma_posterior(st, prior="uniform"))
