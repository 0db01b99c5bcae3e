"""DCT maps (dissertation ch. 9): the field, its spectrum, the three optical-depth paths,
the log-likelihood, the closed-form derivatives of Sec. 9.4.4 and the grid conversions,
each against an independent NumPy reference."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import simpson

from lidarjax.maps import (
    DCTMap,
    DecayRateMap,
    dct_closed_form_derivatives,
    dct_closed_form_terms,
    dct_from_grid,
    dct_log_likelihood,
    dct_optical_depth,
    dct_quadrature_nodes,
    dct_spectrum,
    dct_to_grid,
    rays_in_box,
)
from lidarjax.rays import HIT, SUB, SUP, RayBatch
from lidarjax.raytrace import GridSpec
from lidarjax.testing import finite_difference

METHODS = ("paper", "spectral", "quadrature")


# --------------------------------------------------------------------------------------
# independent NumPy references


def np_amplitude_loop(coeffs, lower, extent, p):
    """``f`` at one point by an explicit loop over all coefficients."""
    xt = np.pi * (np.asarray(p) - lower) / extent
    total = 0.0
    for idx in itertools.product(*[range(n) for n in coeffs.shape]):
        term = coeffs[idx]
        for k, i in enumerate(idx):
            term *= np.cos(i * xt[k])
        total += term
    return total


def np_amplitude(coeffs, lower, extent, pts):
    """Vectorised ``f`` at ``pts [n d]`` (cosine basis per axis, tensor contraction)."""
    xt = np.pi * (np.asarray(pts) - lower) / extent
    out = np.broadcast_to(coeffs, (xt.shape[0],) + coeffs.shape)
    for k in range(coeffs.ndim):
        basis = np.cos(np.arange(coeffs.shape[k])[None, :] * xt[:, k, None])  # [n L]
        out = np.einsum("nl...,nl->n...", out, basis)
    return out


def np_rate(coeffs, lower, extent, pts):
    pts = np.asarray(pts)
    inside = np.all((pts >= lower) & (pts <= lower + extent), axis=-1)
    return np.where(inside, np_amplitude(coeffs, lower, extent, pts) ** 2, 0.0)


def np_spectrum_pairs(coeffs):
    """O(I^2) product-to-sum: cos(a x) cos(b x) = (cos((a+b) x) + cos((a-b) x)) / 2."""
    shape = coeffs.shape
    out = np.zeros(tuple(2 * n - 1 for n in shape))
    idx = list(itertools.product(*[range(n) for n in shape]))
    for i in idx:
        for j in idx:
            w = coeffs[i] * coeffs[j] / 2 ** len(shape)
            for combo in itertools.product((0, 1), repeat=len(shape)):
                p = tuple(i[k] + j[k] if c else abs(i[k] - j[k]) for k, c in enumerate(combo))
                out[p] += w
    return out


def np_cosine_series(spec, lower, extent, pts):
    return np_amplitude(spec, lower, extent, pts)


def np_clip(lower, upper, o, d, r):
    """Entry/exit distances of the ray segment [0, r] in the box (slab method in NumPy)."""
    t0, t1 = 0.0, r
    for k in range(len(o)):
        if d[k] == 0:
            if not lower[k] <= o[k] <= upper[k]:
                return 0.0, 0.0
            continue
        ta, tb = (lower[k] - o[k]) / d[k], (upper[k] - o[k]) / d[k]
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
    return (t0, t1) if t1 > t0 else (0.0, 0.0)


def np_depth(coeffs, lower, extent, o, d, r, n=20001):
    """Simpson integral of f^2 over the clipped segment."""
    t0, t1 = np_clip(lower, lower + extent, o, d, r)
    if t1 <= t0:
        return 0.0
    t = np.linspace(t0, t1, n)
    f = np_amplitude(coeffs, lower, extent, o + t[:, None] * d)
    return simpson(f**2, x=t)


def make_rays(origins, directions, ranges, kind, r_min=0.0, r_max=np.inf):
    return RayBatch(
        origins=jnp.asarray(origins, jnp.float64),
        directions=jnp.asarray(directions, jnp.float64),
        ranges=jnp.asarray(ranges, jnp.float64),
        kind=jnp.asarray(kind, jnp.int32),
        r_min=jnp.asarray(r_min, jnp.float64),
        r_max=jnp.asarray(r_max, jnp.float64),
    )


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# --------------------------------------------------------------------------------------
# 1. the map


def test_dctmap_validation():
    with pytest.raises(ValueError, match="coeffs"):
        DCTMap(np.ones(3), [0.0], [1.0])
    with pytest.raises(ValueError, match="coeffs"):
        DCTMap(np.ones((2, 2, 2, 2)), np.zeros(4), np.ones(4))
    with pytest.raises(ValueError, match="lower and extent"):
        DCTMap(np.ones((2, 2)), [0.0, 0.0, 0.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="lower and extent"):
        DCTMap(np.ones((2, 2)), [0.0, 0.0], [1.0])
    with pytest.raises(ValueError, match="lower and extent"):
        DCTMap(np.ones((2, 2, 2)), [0.0, 0.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="extent"):
        DCTMap(np.ones((2, 2)), [0.0, 0.0], [1.0, 0.0])
    with pytest.raises(ValueError, match="extent"):
        DCTMap(np.ones((2, 2)), [0.0, 0.0], [-1.0, 2.0])
    with pytest.raises(ValueError, match="finite"):
        DCTMap(np.array([[1.0, np.nan], [0.0, 1.0]]), [0.0, 0.0], [1.0, 1.0])


@pytest.mark.parametrize("shape", [(3, 4), (2, 3, 2)])
def test_amplitude_and_decay_rate_match_loop(shape):
    rng = np.random.default_rng(len(shape))
    d = len(shape)
    coeffs = rng.normal(size=shape)
    lower = rng.uniform(-2, 0, d)
    extent = rng.uniform(1, 3, d)
    m = DCTMap(coeffs, lower, extent)
    assert m.dim == d and m.shape == shape and m.n_parameters == np.prod(shape)
    pts = lower + rng.uniform(0, 1, (20, d)) * extent
    ref = np.array([np_amplitude_loop(coeffs, lower, extent, p) for p in pts])
    np.testing.assert_allclose(np.asarray(m.amplitude(pts)), ref, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(np.asarray(m.decay_rate(pts)), ref**2, rtol=1e-12, atol=1e-13)
    # outside the box (one coordinate beyond either face): lambda = 0, f itself is not 0
    out = pts.copy()
    out[:10, 0] = lower[0] - 0.1
    out[10:, d - 1] = lower[d - 1] + extent[d - 1] + 0.2
    np.testing.assert_array_equal(np.asarray(m.decay_rate(out)), 0.0)
    assert np.any(np.abs(np.asarray(m.amplitude(out))) > 1e-3)


# --------------------------------------------------------------------------------------
# 2. spectrum


@pytest.mark.parametrize("shape", [(1, 1), (3, 4), (2, 3, 2)])
def test_spectrum_reconstructs_squared_field(shape):
    rng = np.random.default_rng(sum(shape))
    d = len(shape)
    coeffs = rng.normal(size=shape)
    lower, extent = -np.ones(d), rng.uniform(1, 3, d)
    spec = np.asarray(dct_spectrum(jnp.asarray(coeffs)))
    assert spec.shape == tuple(2 * n - 1 for n in shape)
    pts = lower + rng.uniform(0, 1, (50, d)) * extent
    f = np.array([np_amplitude_loop(coeffs, lower, extent, p) for p in pts])
    lam_series = np_cosine_series(spec, lower, extent, pts)
    np.testing.assert_allclose(lam_series, f**2, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(spec, np_spectrum_pairs(coeffs), rtol=1e-10, atol=1e-12)


# --------------------------------------------------------------------------------------
# 3. optical depth


def _depth_cases_2d(lower, extent):
    """Named rays (origin, direction, length) covering the clipping cases."""
    lo, hi = lower, lower + extent
    c = lower + 0.5 * extent
    return {
        "inside": (c + [0.1, -0.2], unit([0.3, 0.8]), 0.7),
        "axis_x": (c + [-0.3, 0.15], np.array([1.0, 0.0]), 0.9),
        "axis_y": (c + [0.2, -0.4], np.array([0.0, 1.0]), 1.1),
        "axis_x_neg": (c, np.array([-1.0, 0.0]), 0.6),
        "starts_outside": (lo - [0.5, 0.3], unit([1.0, 0.7]), 2.0),
        "leaves": (c, unit([-0.4, 1.0]), 10.0),
        "axis_x_through": (np.array([lo[0] - 1.0, c[1]]), np.array([1.0, 0.0]), 50.0),
        "misses": (lo - [0.5, 0.3], unit([-1.0, 0.2]), 5.0),
        "passes_by": (np.array([lo[0] - 1.0, hi[1] + 0.3]), unit([1.0, 0.01]), 5.0),
        "axis_outside": (np.array([lo[0] - 1.0, hi[1] + 0.3]), np.array([1.0, 0.0]), 5.0),
        "zero_length": (c, unit([1.0, 1.0]), 0.0),
        "inf_inside": (c + [0.1, 0.1], unit([0.6, -0.8]), np.inf),
        "inf_outside": (lo - [0.5, 0.3], unit([1.0, 0.9]), np.inf),
        "inf_axis": (c, np.array([0.0, -1.0]), np.inf),
    }


def _check_depths(m, coeffs, lower, extent, cases):
    names = list(cases)
    o = np.array([cases[k][0] for k in names], float)
    d = np.array([cases[k][1] for k in names], float)
    r = np.array([cases[k][2] for k in names], float)
    depth = {
        meth: np.asarray(dct_optical_depth(m, o, d, r, method=meth, chunk_size=5))
        for meth in METHODS
    }
    ref = np.array([np_depth(coeffs, lower, extent, o[i], d[i], r[i]) for i in range(len(r))])
    for meth in METHODS:
        assert np.all(np.isfinite(depth[meth])), (meth, dict(zip(names, depth[meth])))
        np.testing.assert_allclose(depth[meth], depth["paper"], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(depth[meth], ref, rtol=1e-6, atol=1e-12)
    return dict(zip(names, depth["spectral"]))


def test_optical_depth_methods_agree_2d():
    rng = np.random.default_rng(5)
    coeffs = rng.normal(size=(3, 4))
    lower, extent = np.array([-1.0, 0.5]), np.array([2.0, 1.5])
    m = DCTMap(coeffs, lower, extent)
    cases = _depth_cases_2d(lower, extent)
    for k in range(6):  # random rays starting anywhere near the box
        o = lower - 0.5 + rng.uniform(0, 1, 2) * (extent + 1.0)
        cases[f"random{k}"] = (o, unit(rng.normal(size=2)), rng.uniform(0, 4))
    depth = _check_depths(m, coeffs, lower, extent, cases)
    assert depth["misses"] == 0.0 and depth["axis_outside"] == 0.0
    assert depth["zero_length"] == 0.0
    assert depth["leaves"] > 0


def test_optical_depth_axis_parallel_outside_infinite():
    """A ray that misses the box with infinite length has S = 0 (not inf - inf = NaN)."""
    lower, extent = np.array([0.0, 0.0]), np.array([2.0, 2.0])
    m = DCTMap(np.ones((2, 2)), lower, extent)
    o = np.array([[-1.0, 3.0]])
    d = np.array([[1.0, 0.0]])
    depth = np.asarray(dct_optical_depth(m, o, d, np.array([np.inf])))
    np.testing.assert_array_equal(depth, 0.0)


def test_paper_depth_near_degenerate_direction():
    """Along a box diagonal a denominator of Eq. (9.10) rounds to -1.1e-16 instead of 0; the
    paper path's widened degenerate case (PAPER_DEGENERATE_PHASE) keeps it exact."""
    coeffs = np.array([[1.0, 0.5], [0.5, 0.3]])
    lower, extent = np.zeros(2), np.array([3.0, 1.0])
    m = DCTMap(coeffs, lower, extent)
    o, d = np.array([0.2, 0.3]), np.array([3.0, 1.0]) / np.sqrt(10.0)  # box diagonal
    ref = np_depth(coeffs, lower, extent, o, d, 1.0)
    for meth in METHODS:
        got = float(dct_optical_depth(m, o[None], d[None], np.array([1.0]), method=meth)[0])
        assert got == pytest.approx(ref, rel=1e-9), meth


def test_optical_depth_methods_agree_3d():
    rng = np.random.default_rng(6)
    coeffs = rng.normal(size=(2, 3, 2))
    lower, extent = np.array([0.0, -1.0, 0.5]), np.array([1.5, 2.0, 1.0])
    m = DCTMap(coeffs, lower, extent)
    c = lower + 0.5 * extent
    cases = {
        "inside": (c, unit([0.2, 0.5, -0.3]), 0.6),
        "axis_z": (c, np.array([0.0, 0.0, 1.0]), 0.3),
        "axis_y_leaves": (c, np.array([0.0, 1.0, 0.0]), 5.0),
        "outside_in": (lower - 0.4, unit([1.0, 1.2, 0.8]), 3.0),
        "misses": (lower - 0.4, unit([-1.0, 0.3, 0.1]), 3.0),
        "zero": (c, unit([1.0, 1.0, 1.0]), 0.0),
        # (a direction with rational ratios d_k / extent_k would make some denominators of
        # Eq. 9.10 rounding-level nonzero; see test_paper_depth_near_degenerate_direction)
        "inf": (c, unit([0.31, -0.23, 0.87]), np.inf),
    }
    for k in range(5):
        o = lower - 0.3 + rng.uniform(0, 1, 3) * (extent + 0.6)
        cases[f"random{k}"] = (o, unit(rng.normal(size=3)), rng.uniform(0, 3))
    depth = _check_depths(m, coeffs, lower, extent, cases)
    assert depth["misses"] == 0.0 and depth["zero"] == 0.0


# --------------------------------------------------------------------------------------
# 4. quadrature node count


def test_quadrature_node_count_needed_and_sufficient():
    rng = np.random.default_rng(7)
    coeffs = rng.normal(size=(30, 30))
    m = DCTMap(coeffs, [0.0, 0.0], [10.0, 10.0])
    n = dct_quadrature_nodes(m)
    # long rays across the box (the diagonal is the worst case) and a few shorter ones
    o = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 3.0], [5.0, 0.0], [0.1, 9.9]])
    d = unit([[1.0, 1.0], [-1.0, 1.0], [1.0, 0.2], [0.1, 1.0], [1.0, -1.0]])
    r = np.full(5, np.inf)
    spectral = np.asarray(dct_optical_depth(m, o, d, r, method="spectral"))
    full = np.asarray(dct_optical_depth(m, o, d, r, method="quadrature", n_nodes=n))
    half = np.asarray(dct_optical_depth(m, o, d, r, method="quadrature", n_nodes=n // 2))
    default = np.asarray(dct_optical_depth(m, o, d, r, method="quadrature"))
    np.testing.assert_array_equal(default, full)
    assert np.max(np.abs(full - spectral) / spectral) < 1e-11
    assert np.max(np.abs(half - spectral) / spectral) > 1e-9


# --------------------------------------------------------------------------------------
# 5. log-likelihood


@pytest.mark.parametrize("method", METHODS)
def test_loglik_constant_map_is_exponential(method):
    a = 1.3
    lam = a**2
    m = DCTMap([[a]], [0.0, 0.0], [4.0, 3.0])
    o = np.array([[1.0, 1.0], [0.5, 2.5], [3.5, 0.5], [2.0, 1.5]])
    d = unit([[1.0, 0.5], [1.0, 0.0], [-1.0, 1.0], [0.0, -1.0]])
    ranges = np.array([1.2, 0.05, 9.0, 0.7])
    kind = np.array([HIT, SUB, SUP, HIT])
    r_min, r_max = 0.2, 0.6
    rays = make_rays(o, d, ranges, kind, r_min, r_max)
    ll = np.asarray(dct_log_likelihood(m, rays, method=method))
    ref = [
        np.log(lam) - lam * 1.2,
        np.log(-np.expm1(-lam * r_min)),
        -lam * r_max,
        np.log(lam) - lam * 0.7,
    ]
    np.testing.assert_allclose(ll, ref, rtol=1e-12)


def test_loglik_normalised():
    """int_{r_min}^{r_max} p_hit(r) dr + P(sub) + P(sup) = 1 for one ray direction."""
    rng = np.random.default_rng(8)
    coeffs = 0.15 * rng.normal(size=(3, 3))
    coeffs[0, 0] = 0.6
    m = DCTMap(coeffs, [0.0, 0.0], [5.0, 5.0])
    o, d = np.array([1.0, 1.5]), unit([0.8, 0.5])
    r_min, r_max = 0.3, 3.5  # the ray leaves the box after ~4.6 m
    r = np.linspace(r_min, r_max, 2001)
    n = r.size
    hits = make_rays(np.tile(o, (n, 1)), np.tile(d, (n, 1)), r, np.full(n, HIT), r_min, r_max)
    p_hit = np.exp(np.asarray(dct_log_likelihood(m, hits)))
    sub_sup = make_rays(
        np.tile(o, (2, 1)), np.tile(d, (2, 1)), [0.1, 10.0], [SUB, SUP], r_min, r_max
    )
    p_sub, p_sup = np.exp(np.asarray(dct_log_likelihood(m, sub_sup)))
    assert 0.01 < p_sub < 0.99 and 0.01 < p_sup < 0.99
    total = simpson(p_hit, x=r) + p_sub + p_sup
    assert total == pytest.approx(1.0, abs=1e-9)


def test_hit_outside_box_is_minus_inf():
    coeffs = np.array([[1.0, 0.3], [0.2, -0.1]])
    m = DCTMap(coeffs, [0.0, 0.0], [2.0, 2.0])
    d = [[1.0, 0.0], unit([1.0, 1.0])]
    rays = make_rays([[1.0, 1.0], [1.0, 1.0]], d, [3.0, 0.5], [HIT, HIT])
    for method in METHODS:
        ll = np.asarray(dct_log_likelihood(m, rays, method=method))
        assert ll[0] == -np.inf and np.isfinite(ll[1]), method
    # gradients stay finite: of the -inf ray itself and of a masked sum
    jac = jax.jacrev(lambda c: dct_log_likelihood(DCTMap(c, m.lower, m.extent), rays))
    assert np.all(np.isfinite(np.asarray(jax.jit(jac)(jnp.asarray(coeffs)))))


# --------------------------------------------------------------------------------------
# 6./7. closed-form derivatives and terms


@pytest.fixture(scope="module")
def deriv_setup():
    rng = np.random.default_rng(9)
    coeffs = 0.3 * rng.normal(size=(3, 4))
    coeffs[0, 0] = 0.9
    lower, extent = np.array([-1.0, 0.0]), np.array([3.0, 2.5])
    m = DCTMap(coeffs, lower, extent)
    o = np.array(
        [[0.0, 1.0], [-2.0, 0.5], [0.5, 1.5], [-1.2, -0.2], [0.3, 0.4], [1.0, 2.0], [0.2, 0.8]]
    )
    d = unit([[1.0, 0.3], [1.0, 0.2], [-0.5, -1.0], [0.6, 0.8], [1.0, 0.0], [0.43, -1.0], [0, 1]])
    ranges = np.array([1.2, 2.5, 0.05, 0.1, 5.0, 9.0, 0.9])
    kind = np.array([HIT, HIT, SUB, SUB, SUP, SUP, HIT])
    rays = make_rays(o, d, ranges, kind, r_min=0.4, r_max=3.0)
    assert np.all(np.asarray(rays_in_box(m, rays)))
    return m, rays


@pytest.fixture(scope="module")
def spectral_hessian(deriv_setup):
    m, rays = deriv_setup
    return np.asarray(jax.jit(jax.hessian(_ll_fn(m, rays, "spectral")))(m.coeffs.reshape(-1)))


def _ll_fn(m, rays, method):
    return lambda a: dct_log_likelihood(
        DCTMap(a.reshape(m.shape), m.lower, m.extent), rays, method=method
    )


@pytest.mark.parametrize("method", METHODS)
def test_closed_form_derivatives_match_autodiff(deriv_setup, spectral_hessian, method):
    m, rays = deriv_setup
    a = m.coeffs.reshape(-1)
    f = _ll_fn(m, rays, method)
    extra = method == "spectral"

    @jax.jit
    def autodiff(a):
        out = (f(a), jax.jacrev(f)(a), jax.jacfwd(jax.jacrev(f))(a))
        if extra:  # forward- and reverse-mode must agree
            out += (jax.jacfwd(f)(a), jax.jacrev(jax.jacrev(f))(a))
        return out

    g_cf, h_cf = (np.asarray(x) for x in dct_closed_form_derivatives(m, rays))
    res = [np.asarray(x) for x in autodiff(a)]
    g_ad, h_ad = res[1], res[2]
    assert g_cf.shape == (rays.n, a.size) and h_cf.shape == (rays.n, a.size, a.size)
    np.testing.assert_allclose(g_cf, g_ad, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(h_cf, h_ad, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(spectral_hessian, h_ad, rtol=1e-8, atol=1e-10)  # jax.hessian
    if extra:
        np.testing.assert_allclose(res[3], g_ad, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(res[4], h_ad, rtol=1e-10, atol=1e-12)
        value = lambda x: autodiff(x)[0]
        grad = lambda x: autodiff(x)[1]
        fd_g = finite_difference(value, a, eps=1e-6)
        np.testing.assert_allclose(fd_g, g_ad, rtol=1e-6, atol=1e-7)
        fd_h = finite_difference(grad, a, eps=1e-5)
        np.testing.assert_allclose(fd_h, h_ad, rtol=1e-6, atol=1e-6)


def test_paper_sub_hessian_erratum(deriv_setup, spectral_hessian):
    """Eq. for the SUB Hessian as printed (+ N^2 C_i C_j / (1-N)^2) is wrong; differentiating
    the printed gradient N C_i / (1-N) gives the minus sign. HIT and SUP are unaffected."""
    m, rays = deriv_setup
    kind = np.asarray(rays.kind)
    _, h_fix = dct_closed_form_derivatives(m, rays)
    _, h_paper = dct_closed_form_derivatives(m, rays, sub_hessian="paper")
    h_ad = spectral_hessian
    h_fix, h_paper = np.asarray(h_fix), np.asarray(h_paper)
    sub = kind == SUB
    np.testing.assert_allclose(h_paper[~sub], h_ad[~sub], rtol=1e-8, atol=1e-10)
    for k in np.flatnonzero(sub):
        err = np.max(np.abs(h_paper[k] - h_ad[k])) / np.max(np.abs(h_ad[k]))
        assert err > 1e-2, (k, err)
        # the difference is exactly 2 N^2 C_i C_j / (1 - N)^2
        t = dct_closed_form_terms(m, rays.origins[k], rays.directions[k], 0.0, rays.r_min)
        N, Ci = float(t["N"]), np.asarray(t["C_i"])
        np.testing.assert_allclose(
            h_paper[k] - h_fix[k], 2 * N**2 * np.outer(Ci, Ci) / (1 - N) ** 2, rtol=1e-9
        )
    with pytest.raises(ValueError, match="sub_hessian"):
        dct_closed_form_derivatives(m, rays, sub_hessian="nope")


def test_closed_form_terms(deriv_setup):
    m, rays = deriv_setup
    a = np.asarray(m.coeffs).reshape(-1)
    lower, extent = np.asarray(m.lower), np.asarray(m.extent)
    for k, r, ell in ((0, 0.8, 1.7), (1, 1.8, 2.2), (2, 0.8, 1.3), (4, 1.0, 9.0)):
        o, d = np.asarray(rays.origins[k]), np.asarray(rays.directions[k])
        t = {key: np.asarray(v) for key, v in dct_closed_form_terms(m, o, d, r, ell).items()}
        S = np_depth(np.asarray(m.coeffs), lower, extent, o, d, ell)
        assert float(t["S"]) == pytest.approx(0.5 * a @ t["C_ij"] @ a, rel=1e-10)
        assert float(t["S"]) == pytest.approx(S, rel=1e-7)
        assert float(t["N"]) == pytest.approx(np.exp(-S), rel=1e-7)
        end = o + r * d
        phi = np.array(
            [
                np_amplitude_loop(np.eye(a.size)[i].reshape(m.shape), lower, extent, end)
                for i in range(a.size)
            ]
        )
        assert np.all((end >= lower) & (end <= lower + extent))
        assert float(t["lam"]) == pytest.approx((phi @ a) ** 2, rel=1e-12)
        np.testing.assert_allclose(t["B_ij"], 2 * np.outer(phi, phi), rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(t["C_i"], t["C_ij"] @ a, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(t["C_ij"], t["C_ij"].T, rtol=1e-12, atol=1e-14)


# --------------------------------------------------------------------------------------
# 8. pose gradient


def test_pose_gradient_matches_finite_differences():
    rng = np.random.default_rng(10)
    coeffs = 0.3 * rng.normal(size=(4, 3))
    coeffs[0, 0] = 1.0
    m = DCTMap(coeffs, [0.0, 0.0], [4.0, 3.0])
    origins = np.array([[1.0, 1.0], [0.7, 1.4], [2.5, 2.0], [3.0, 0.6]])
    thetas = np.array([0.4, 0.0, -2.0, np.pi / 2])  # 0: direction exactly (1, 0)
    ranges = np.array([1.5, 2.1, 1.2, 1.3])
    n = len(ranges)

    def ll(params):
        o, th = params[:, :2], params[:, 2]
        d = jnp.stack([jnp.cos(th), jnp.sin(th)], -1)
        rays = RayBatch(o, d, jnp.asarray(ranges), jnp.full(n, HIT, jnp.int32), 0.0, 10.0)
        return dct_log_likelihood(m, rays)

    both = jax.jit(lambda p: (ll(p), jax.jacrev(ll)(p)))
    params = jnp.asarray(np.concatenate([origins, thetas[:, None]], axis=1))
    assert float(jnp.cos(params[1, 2])) == 1.0 and float(jnp.sin(params[1, 2])) == 0.0
    jac = np.asarray(both(params)[1])  # [n n 3]
    fd = finite_difference(lambda p: both(p)[0], params, eps=1e-6)
    assert np.all(np.isfinite(jac))
    np.testing.assert_allclose(jac, fd, rtol=1e-6, atol=1e-7)
    # per-ray gradients are nonzero in every pose coordinate
    assert np.all(np.abs(np.einsum("iij->ij", jac)) > 1e-6)


# --------------------------------------------------------------------------------------
# 9. grid conversions


def _grid(rates, origin=(-1.0, 0.5), res=0.5):
    rates = jnp.asarray(rates, jnp.float64)
    return DecayRateMap(GridSpec(origin, res, rates.shape), rates, jnp.asarray(0.0))


def test_from_grid_interpolates_and_projects():
    rng = np.random.default_rng(11)
    rates = rng.uniform(0.1, 3.0, (6, 4))
    g = _grid(rates)
    full = dct_from_grid(g)
    assert full.shape == (6, 4)
    np.testing.assert_allclose(np.asarray(full.lower), [-1.0, 0.5])
    np.testing.assert_allclose(np.asarray(full.extent), [3.0, 2.0])
    back = dct_to_grid(full, (6, 4))
    np.testing.assert_allclose(np.asarray(back.rates), rates, rtol=1e-10)
    centres = np.asarray(g.spec.cell_centers()).reshape(-1, 2)
    np.testing.assert_allclose(np.asarray(full.decay_rate(centres)), rates.reshape(-1), rtol=1e-10)
    # truncated: least squares of sqrt(rates) on the cosine basis at the cell centres
    shape = (3, 2)
    trunc = dct_from_grid(g, shape)
    basis = np.stack(
        [
            np_amplitude(np.eye(6)[i].reshape(shape), np.array([-1.0, 0.5]), [3.0, 2.0], centres)
            for i in range(6)
        ],
        axis=1,
    )
    ls = np.linalg.lstsq(basis, np.sqrt(rates).reshape(-1), rcond=None)[0]
    np.testing.assert_allclose(np.asarray(trunc.coeffs).reshape(-1), ls, rtol=1e-10, atol=1e-12)
    for bad in [(7, 4), (0, 2), (2, 2, 2)]:
        with pytest.raises(ValueError, match="shape"):
            dct_from_grid(g, bad)
    with pytest.raises(ValueError, match="non-square"):
        dct_to_grid(full, (6, 6))


# --------------------------------------------------------------------------------------
# 10. smoothing


def test_smoothed_single_coefficient_and_gaussian_convolution():
    lower, extent = np.array([0.0, -1.0]), np.array([3.0, 2.0])
    sigma = 0.2
    c = np.zeros((4, 3))
    c[2, 1] = 0.7
    m = DCTMap(c, lower, extent)
    assert m.smoothed(0.0) is m
    s = np.asarray(m.smoothed(sigma).coeffs)
    k2 = (np.pi * 2 / 3.0) ** 2 + (np.pi * 1 / 2.0) ** 2
    expected = np.zeros_like(c)
    expected[2, 1] = 0.7 * np.exp(-(sigma**2) * k2 / 2)
    np.testing.assert_allclose(s, expected, rtol=1e-12, atol=1e-15)
    # general map: amplitude = E[f(x + sigma Z)], Z ~ N(0, I), by Gauss-Hermite quadrature
    rng = np.random.default_rng(12)
    coeffs = rng.normal(size=(5, 4))
    m = DCTMap(coeffs, lower, extent)
    x, w = np.polynomial.hermite_e.hermegauss(40)
    w = w / w.sum()
    pts = lower + rng.uniform(0, 1, (6, 2)) * extent
    ref = []
    for p in pts:
        q = p + sigma * np.stack(np.meshgrid(x, x, indexing="ij"), -1).reshape(-1, 2)
        ref.append(np.sum(np.outer(w, w).reshape(-1) * np_amplitude(coeffs, lower, extent, q)))
    got = np.asarray(m.smoothed(sigma).amplitude(pts))
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-12)
    assert np.max(np.abs(got - np.asarray(m.amplitude(pts)))) > 1e-2
    for bad in (-0.1, np.nan, np.inf):
        with pytest.raises(ValueError, match="sigma"):
            m.smoothed(bad)


# --------------------------------------------------------------------------------------
# 11. rays_in_box


def test_rays_in_box_classification():
    m = DCTMap(np.ones((2, 2)), [0.0, 0.0], [2.0, 2.0])
    cases = [
        # (origin, direction, range, kind, expected)
        ([1.0, 1.0], [1.0, 0.0], 0.5, HIT, True),  # ends inside
        ([1.0, 1.0], [1.0, 0.0], 1.5, HIT, False),  # ends outside
        ([-1.0, 1.0], [1.0, 0.0], 1.5, HIT, True),  # starts outside, ends inside
        ([-1.0, 1.0], [1.0, 0.0], 0.5, HIT, False),  # ends before the box
        ([1.0, 1.0], [0.0, 1.0], 0.1, SUB, True),  # r_min = 0.5 inside the box
        ([-1.0, 1.0], [1.0, 0.0], 0.1, SUB, False),  # first r_min metres miss the box
        ([-0.2, 1.0], [1.0, 0.0], 0.1, SUB, True),  # ... or reach it
        ([-1.0, 3.0], [1.0, 0.0], 9.0, SUP, False),  # passes above the box
        ([-1.0, 1.0], [1.0, 0.0], 9.0, SUP, True),  # crosses the box
        ([-1.0, 1.0], [-1.0, 0.0], 9.0, SUP, False),  # points away
        ([3.0, 3.0], unit([-1.0, -1.0]), 9.0, SUP, True),  # diagonal through
        ([3.0, 0.5], unit([-1.0, 2.0]), 9.0, SUP, False),  # misses a corner
    ]
    o, d, r, k, expected = (np.array([c[i] for c in cases]) for i in range(5))
    rays = make_rays(o, d, r, k, r_min=0.5, r_max=5.0)
    np.testing.assert_array_equal(np.asarray(rays_in_box(m, rays)), expected.astype(bool))
    # infinite r_max
    rays = make_rays(o, d, r, k, r_min=0.5, r_max=np.inf)
    np.testing.assert_array_equal(np.asarray(rays_in_box(m, rays)), expected.astype(bool))
