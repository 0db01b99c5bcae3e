"""DCT map fit (dissertation Sec. 9.4.4): the precomputed objective, maximum-likelihood
recovery of a known map from simulated rays, the grid initial map (Eq. 7.10) and scan
matching on a fitted map of a synthetic room."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import optimistix as optx
import pytest

import lidarjax.maps._fit as fit_module
from lidarjax.localization import to_vector
from lidarjax.localization.refine import refine_dct_scan_pose
from lidarjax.maps import (
    DCTMap,
    dct_from_grid,
    dct_grid_initial_map,
    dct_log_likelihood,
    dct_objective,
    decay_rate_map,
    fit_dct,
)
from lidarjax.rays import HIT, SUB, SUP, RayBatch, from_scan
from lidarjax.raytrace import GridSpec, accumulate


def np_amplitude(coeffs, lower, extent, pts):
    """``f`` at ``pts [n d]`` from the cosine series (NumPy)."""
    xt = np.pi * (np.asarray(pts) - lower) / extent
    out = np.broadcast_to(coeffs, (xt.shape[0],) + coeffs.shape)
    for k in range(coeffs.ndim):
        basis = np.cos(np.arange(coeffs.shape[k])[None, :] * xt[:, k, None])
        out = np.einsum("nl...,nl->n...", out, basis)
    return out


def make_rays(origins, directions, ranges, kind, r_min, r_max):
    f = lambda x: jnp.asarray(x, jnp.float64)
    return RayBatch(
        f(origins), f(directions), f(ranges), jnp.asarray(kind, jnp.int32), f(r_min), f(r_max)
    )


def simulate_rays(coeffs, lower, extent, n, rng, r_min=0.1, r_max=1.9, n_grid=600):
    """Rays from origins in the box's central part (all stay in the box up to r_max): the
    first reflection by inverse-CDF sampling of the exponential with rate lambda(x(r)),
    S(r) = E ~ Exp(1), on a fine grid along each ray."""
    o = lower + extent * rng.uniform(1 / 3, 2 / 3, (n, 2))
    th = rng.uniform(-np.pi, np.pi, n)
    d = np.stack([np.cos(th), np.sin(th)], -1)
    t = np.linspace(0.0, r_max, n_grid)
    pts = o[:, None, :] + t[None, :, None] * d[:, None, :]
    lam = np_amplitude(coeffs, lower, extent, pts.reshape(-1, 2)).reshape(n, n_grid) ** 2
    S = np.concatenate(
        [np.zeros((n, 1)), np.cumsum(0.5 * (lam[:, 1:] + lam[:, :-1]) * np.diff(t), axis=1)], 1
    )
    E = rng.exponential(size=n)
    r = np.array([np.interp(E[i], S[i], t) if E[i] < S[i, -1] else np.inf for i in range(n)])
    kind = np.where(r < r_min, SUB, np.where(np.isinf(r), SUP, HIT))
    ranges = np.where(kind == SUB, 0.5 * r_min, np.where(kind == SUP, r_max, r))
    return make_rays(o, d, ranges, kind, r_min, r_max)


TRUE_COEFFS = np.array(
    [
        [1.0, -0.2, 0.1, 0.0],
        [0.25, 0.0, 0.15, 0.05],
        [0.0, 0.1, -0.05, 0.0],
        [0.05, 0.0, 0.0, 0.05],
    ]
)
LOWER, EXTENT = np.array([-1.0, 0.5]), np.array([6.0, 6.0])


@pytest.fixture(scope="module")
def sim_rays():
    grid = LOWER + EXTENT * np.stack(np.meshgrid(*[np.linspace(0, 1, 41)] * 2), -1).reshape(-1, 2)
    assert np.min(np_amplitude(TRUE_COEFFS, LOWER, EXTENT, grid)) > 0.3  # f > 0: smooth lambda
    return simulate_rays(TRUE_COEFFS, LOWER, EXTENT, 3000, np.random.default_rng(0))


# --------------------------------------------------------------------------------------
# 1. the precomputed objective


@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_objective_equals_sum_of_log_likelihoods(sim_rays):
    rays = jax.tree.map(lambda x: x[:150] if x.ndim else x, sim_rays)
    counts = rays.counts()
    assert min(counts.values()) >= 5, counts
    obj = dct_objective(rays, LOWER, EXTENT, (3, 4))
    assert obj.n_rays == 150

    def direct(a):
        return jnp.sum(dct_log_likelihood(DCTMap(a, LOWER, EXTENT), rays))

    both = jax.jit(lambda a: (obj(a), jax.grad(obj)(a), direct(a), jax.grad(direct)(a)))
    rng = np.random.default_rng(1)
    for _ in range(3):
        a = 0.3 * rng.normal(size=(3, 4))
        a[0, 0] = rng.uniform(0.5, 1.5)
        v, g, v_ref, g_ref = both(jnp.asarray(a))
        assert float(v) == pytest.approx(float(v_ref), rel=1e-9)
        np.testing.assert_allclose(np.asarray(g), np.asarray(g_ref), rtol=1e-9, atol=1e-9)


def first_rays(rays, n):
    return jax.tree.map(lambda x: x[:n] if x.ndim else x, rays)


def test_ray_bucket():
    assert [fit_module.ray_bucket(n) for n in (0, 1, 64, 65, 150, 2000, 2049, 2500)] == [
        0,
        64,
        64,
        80,
        160,
        2048,
        2560,
        2560,
    ]
    assert fit_module.ray_bucket(3, minimum=16) == 16
    ns = np.arange(1, 20000)
    b = np.array([fit_module.ray_bucket(n) for n in ns])
    assert np.all(b >= ns) and np.all(np.diff(b) >= 0)
    assert np.all(b[ns >= 64] <= 1.25 * ns[ns >= 64])  # at most 25 % padding
    assert len(np.unique(b)) < 60  # few buckets, hence few compiled programs
    with pytest.raises(ValueError, match="n must be"):
        fit_module.ray_bucket(-1)


def test_bucketed_setup_matches_unpadded_objective(sim_rays):
    """fit_dct's set-up pads the rays to a shape bucket (one program for many inputs): its
    objective equals the unpadded :func:`dct_objective` (value and gradient, float64), its
    padding contributes exactly zero, and its initial map is the grid initial map of the
    unpadded rays."""
    rays = first_rays(sim_rays, 150)
    counts = rays.counts()
    assert min(counts.values()) >= 5, counts
    shape = (4, 4)
    obj = dct_objective(rays, LOWER, EXTENT, shape)
    pobj, a0 = fit_module._bucketed_setup(rays, shape, LOWER, EXTENT, initial=True)
    n_pad = fit_module.ray_bucket(150)
    assert n_pad > 150  # padded rays are present
    assert pobj.hit_points.shape == (n_pad, 2) and int(pobj.hit_mask.sum()) == counts["HIT"]
    assert pobj.w_sub.shape[0] == fit_module.ray_bucket(counts["SUB"], minimum=16)
    assert pobj.w_sub.shape[0] > counts["SUB"] and int(pobj.sub_mask.sum()) == counts["SUB"]
    assert float(pobj.n_rays) == obj.n_rays == 150
    np.testing.assert_allclose(np.asarray(pobj.w_free), np.asarray(obj.w_free), rtol=1e-12)

    # garbage in the padded rows changes nothing, bit for bit
    rng = np.random.default_rng(5)
    spoiled = eqx.tree_at(
        lambda o: (o.hit_points, o.w_sub),
        pobj,
        (
            jnp.where(pobj.hit_mask[:, None], pobj.hit_points, rng.normal(size=(n_pad, 2))),
            jnp.where(
                pobj.sub_mask[:, None, None],
                pobj.w_sub,
                jnp.asarray(rng.uniform(-1.0, 1.0, pobj.w_sub.shape)),
            ),
        ),
    )
    ev = jax.jit(lambda a: tuple(x for o in (obj, pobj, spoiled) for x in (o(a), jax.grad(o)(a))))
    for _ in range(3):
        a = 0.3 * rng.normal(size=shape)
        a[0, 0] = rng.uniform(0.5, 1.5)
        v, g, pv, pg, sv, sg = ev(jnp.asarray(a))
        assert float(pv) == pytest.approx(float(v), rel=1e-12)
        np.testing.assert_allclose(np.asarray(pg), np.asarray(g), rtol=1e-10, atol=1e-12)
        assert float(sv) == float(pv) and np.array_equal(np.asarray(sg), np.asarray(pg))

    # the initial map of the set-up: the grid ML map (Eq. 7.10) of the unpadded rays
    grid = decay_rate_map(accumulate(GridSpec(LOWER, 0.75, (8, 8)), rays))
    ref = dct_from_grid(grid, shape, max_rate=20.0)
    np.testing.assert_allclose(np.asarray(a0), np.asarray(ref.coeffs), rtol=1e-12, atol=1e-14)
    init = dct_grid_initial_map(rays, LOWER, EXTENT, shape)
    np.testing.assert_allclose(np.asarray(init.coeffs), np.asarray(ref.coeffs), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(init.extent), EXTENT, rtol=1e-15)


def test_fit_compiles_once_per_ray_bucket(sim_rays):
    """Two ray sets of different sizes in one bucket (total and SUB rays) run the same two
    compiled programs (set-up and solve); the fit equals the unpadded solve."""
    a, b = first_rays(sim_rays, 130), first_rays(sim_rays, 150)
    sub_a, sub_b = a.counts()["SUB"], b.counts()["SUB"]
    assert fit_module.ray_bucket(130) == fit_module.ray_bucket(150)
    assert fit_module.ray_bucket(sub_a, minimum=16) == fit_module.ray_bucket(sub_b, minimum=16)
    init = DCTMap(TRUE_COEFFS[:3, :2], LOWER, EXTENT)  # a shape no other test fits

    def sizes():  # programs in the in-memory caches of the two jitted functions
        setup = fit_module._setup.program._cached  # checked_jit -> eqx.filter_jit -> jax.jit
        return setup._cache_size(), fit_module._minimise._cached._cache_size()

    before = sizes()
    m_a, _ = fit_dct(a, init=init, max_steps=6)
    after_a = sizes()
    m_b, sol_b = fit_dct(b, init=init, max_steps=6)
    assert sizes() == after_a == (before[0] + 1, before[1] + 1)
    assert not np.allclose(np.asarray(m_a.coeffs), np.asarray(m_b.coeffs))
    # another bucket compiles again (the count above is not blind)
    fit_dct(first_rays(sim_rays, 170), init=init, max_steps=6)
    assert sizes() == (before[0] + 2, before[1] + 2)

    # the same solve without padding (the objective of dct_objective)
    solver = optx.LBFGS(rtol=1e-3, atol=1e-3)
    ref = fit_module._minimise(
        dct_objective(b, LOWER, EXTENT, (3, 2)), solver, init.coeffs, 6, False
    )
    assert int(sol_b.stats["num_steps"]) == int(ref.stats["num_steps"])
    np.testing.assert_allclose(np.asarray(m_b.coeffs), np.asarray(ref.value), rtol=1e-8, atol=1e-10)


# --------------------------------------------------------------------------------------
# 2./3. recovery, solver result, errors, compile once


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_fit_recovers_known_map(sim_rays, monkeypatch):
    # the jitted solver may be traced once for this problem size
    monkeypatch.setattr(
        fit_module,
        "_minimise",
        eqx.filter_jit(eqx.debug.assert_max_traces(fit_module._minimise.__wrapped__, max_traces=1)),
    )
    rng = np.random.default_rng(2)
    true = DCTMap(TRUE_COEFFS, LOWER, EXTENT)
    init = DCTMap(TRUE_COEFFS + 0.1 * rng.normal(size=(4, 4)), LOWER, EXTENT)
    m, sol = fit_dct(sim_rays, init=init, rtol=1e-8, atol=1e-8)
    assert sol.result == optx.RESULTS.successful
    ll = float(jnp.sum(dct_log_likelihood(m, sim_rays)))
    ll_true = float(jnp.sum(dct_log_likelihood(true, sim_rays)))
    ll_init = float(jnp.sum(dct_log_likelihood(init, sim_rays)))
    assert ll >= ll_true - 1e-6 and ll > ll_init
    # held-out points in the well-observed centre of the box
    pts = LOWER + EXTENT * rng.uniform(0.3, 0.7, (500, 2))
    lam, lam_true = np.asarray(m.decay_rate(pts)), np.asarray(true.decay_rate(pts))
    rel_rmse = np.sqrt(np.mean((lam - lam_true) ** 2)) / np.sqrt(np.mean(lam_true**2))
    assert rel_rmse < 0.2, rel_rmse
    # the fit is not just the start: the start was clearly worse
    lam0 = np.asarray(init.decay_rate(pts))
    assert rel_rmse < np.sqrt(np.mean((lam0 - lam_true) ** 2)) / np.sqrt(np.mean(lam_true**2))

    # same-size problem (same HIT/SUB/SUP counts), different data: no retrace
    other = simulate_rays(TRUE_COEFFS, LOWER, EXTENT, 3000, np.random.default_rng(3))
    kinds, other_kinds = np.asarray(sim_rays.kind), np.asarray(other.kind)
    idx = np.concatenate(  # same count per kind as sim_rays (repeat rays where short)
        [np.resize(np.flatnonzero(other_kinds == k), (kinds == k).sum()) for k in (HIT, SUB, SUP)]
    )
    other = jax.tree.map(lambda x: x[idx] if x.ndim else x, other)
    m2, sol2 = fit_dct(other, init=init, rtol=1e-8, atol=1e-8)
    assert sol2.result == optx.RESULTS.successful
    assert not np.allclose(np.asarray(m2.coeffs), np.asarray(m.coeffs))


def test_fit_errors(sim_rays):
    init = DCTMap(TRUE_COEFFS, LOWER, EXTENT)
    bad = make_rays([[0.0, 1.0]], [[1.0, 0.0]], [10.0], [HIT], 0.1, 20.0)
    with pytest.raises(ValueError, match="no evidence"):
        fit_dct(bad, init=init)
    empty = make_rays(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0), 0.1, 2.0)
    with pytest.raises(ValueError, match="empty"):
        fit_dct(empty, init=init)
    with pytest.raises(ValueError, match="init.shape"):
        fit_dct(sim_rays, (3, 3), init=init)
    with pytest.raises(ValueError, match="shape, lower and extent"):
        fit_dct(sim_rays, (3, 3))


# --------------------------------------------------------------------------------------
# 4. grid initial map


def test_grid_initial_map_matches_ml_grid_rates():
    """Axis-parallel rays on a 3 x 2 grid of 1 m cells: H and R per cell by interval
    overlaps; with one cell per coefficient the DCT interpolates sqrt(H / R) (Eq. 7.10)."""
    lower, shape = np.array([0.0, 0.0]), (3, 2)
    rays_spec = [  # origin, axis (0: +x, 1: +y), range
        ((0.2, 0.5), 0, 2.5),
        ((0.3, 0.5), 0, 1.1),
        ((0.3, 1.5), 0, 0.4),
        ((0.1, 1.5), 0, 2.2),
        ((1.5, 0.1), 1, 1.6),
        ((2.5, 0.3), 1, 1.45),
        ((0.4, 0.2), 1, 0.6),
        ((1.2, 1.5), 0, 1.2),
    ]
    H, R = np.zeros(shape), np.zeros(shape)
    for (ox, oy), ax, r in rays_spec:
        o = np.array([ox, oy])
        end = o.copy()
        end[ax] += r
        cross = 1 - ax
        j = int(np.floor(o[cross]))
        for i in range(shape[ax]):
            overlap = max(0.0, min(end[ax], i + 1) - max(o[ax], i))
            cell = (i, j) if ax == 0 else (j, i)
            R[cell] += overlap
        H[tuple(np.floor(end).astype(int))] += 1
    assert np.all(R > 0) and np.all(H > 0)
    lam = H / R
    o = np.array([s[0] for s in rays_spec])
    d = np.array([[1.0, 0.0] if s[1] == 0 else [0.0, 1.0] for s in rays_spec])
    r = np.array([s[2] for s in rays_spec])
    rays = make_rays(o, d, r, np.full(len(r), HIT), 0.0, 10.0)
    m = dct_grid_initial_map(rays, lower, [3.0, 2.0], shape, oversample=1, max_rate=None)
    centres = np.stack(np.meshgrid(np.arange(3) + 0.5, np.arange(2) + 0.5, indexing="ij"), -1)
    np.testing.assert_allclose(
        np.asarray(m.amplitude(centres.reshape(-1, 2))) ** 2, lam.reshape(-1), rtol=1e-9
    )
    # max_rate clips before the transform
    m_clip = dct_grid_initial_map(rays, lower, [3.0, 2.0], shape, oversample=1, max_rate=1.0)
    np.testing.assert_allclose(
        np.asarray(m_clip.amplitude(centres.reshape(-1, 2))) ** 2,
        np.minimum(lam, 1.0).reshape(-1),
        rtol=1e-9,
    )
    with pytest.raises(ValueError, match="oversample"):
        dct_grid_initial_map(rays, lower, [3.0, 2.0], shape, oversample=0)
    with pytest.raises(ValueError, match="square"):
        dct_grid_initial_map(rays, lower, [3.0, 3.0], shape, oversample=1)


# --------------------------------------------------------------------------------------
# 5. scan matching in a synthetic room


def room_segments():
    """6 x 5 m room with a square pillar and a wall stub, as segments [s 2 2]."""
    w, h = 6.0, 5.0
    segs = [((0, 0), (w, 0)), ((w, 0), (w, h)), ((w, h), (0, h)), ((0, h), (0, 0))]
    px, py, s = 3.8, 2.2, 0.6
    segs += [
        ((px, py), (px + s, py)),
        ((px + s, py), (px + s, py + s)),
        ((px + s, py + s), (px, py + s)),
        ((px, py + s), (px, py)),
    ]
    segs += [((0.0, 3.5), (1.6, 3.5))]
    return np.array(segs, float)


def simulate_scan(pose, azimuths, segs, noise, rng):
    """Nearest ray-segment intersection per beam (NumPy), plus Gaussian range noise."""
    x, y, th = pose
    ang = th + azimuths
    d = np.stack([np.cos(ang), np.sin(ang)], -1)  # [b 2]
    a, e = segs[:, 0], segs[:, 1] - segs[:, 0]  # [s 2]
    rel = a[None] - np.array([x, y])  # [1 s 2]
    den = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]  # [b s]
    den = np.where(den == 0, np.nan, den)
    t = (rel[..., 0] * e[None, :, 1] - rel[..., 1] * e[None, :, 0]) / den
    u = (rel[..., 0] * d[:, None, 1] - rel[..., 1] * d[:, None, 0]) / den
    t = np.where((t > 0) & (u >= 0) & (u <= 1), t, np.inf)
    r = t.min(axis=1)
    return r + noise * rng.standard_normal(r.shape)


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_scan_matching_in_synthetic_room():
    rng = np.random.default_rng(0)
    segs = room_segments()
    az = np.linspace(-np.pi, np.pi, 90, endpoint=False)
    r_min, r_max = 0.05, 20.0
    n_map = 20
    poses = np.column_stack(
        [rng.uniform(0.6, 3.3, n_map), rng.uniform(0.6, 3.0, n_map), rng.uniform(-3, 3, n_map)]
    )
    ranges = np.stack([simulate_scan(p, az, segs, 0.01, rng) for p in poses])
    assert np.all(np.isfinite(ranges))  # closed room: every beam hits
    rays = from_scan(jaxlie.SE2.from_xy_theta(*poses.T), az, ranges, r_min, r_max)
    m, sol = fit_dct(rays, (24, 20), lower=[-0.3, -0.3], extent=[6.6, 5.5])
    assert sol.result == optx.RESULTS.successful

    held_out = np.array([[1.2, 1.0, 0.3], [2.5, 1.5, 2.0], [3.0, 4.2, -1.0]])
    for k, p in enumerate(held_out):
        scan = simulate_scan(p, az, segs, 0.01, rng)
        ang = 2.1 * k + 0.4
        start = p + np.array([0.5 * np.cos(ang), 0.5 * np.sin(ang), np.deg2rad(5.0) * (-1) ** k])
        pose, _ = refine_dct_scan_pose(
            m,
            az,
            scan,
            jaxlie.SE2.from_xy_theta(*start),
            r_min,
            r_max,
            blur_schedule_m=(0.3, 0.1),
        )
        v = np.asarray(to_vector(pose))
        err_xy = np.linalg.norm(v[:2] - p[:2])
        err_deg = np.rad2deg(abs(np.angle(np.exp(1j * (v[2] - p[2])))))
        assert err_xy < 0.05 and err_deg < 1.0, (k, err_xy, err_deg)
