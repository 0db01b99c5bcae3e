"""Measurement-driven global initialisation (``pose_lattice``, ``init_from_scan``): the
lattice against a brute-force NumPy construction, the proposal density against numerical
integration, the importance weights against a quadrature posterior, and a real
ray-traced scan model finding the pose in a simulated office."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from lidarjax.localization import (
    ScanModel,
    init_from_scan,
    lattice_scores,
    pose_lattice,
    to_vector,
)
from lidarjax.localization._global import proposal_log_density
from lidarjax.maps import decay_rate_map, smooth_stats
from lidarjax.rays import from_scan
from lidarjax.raytrace import GridSpec, accumulate
from lidarjax.sim import make_office, simulate_scans


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _mask(shape, seed=0, p=0.6):
    rng = np.random.default_rng(seed)
    return rng.random(shape) < p


SPEC = GridSpec(np.array([-1.0, 2.0]), 0.1, (23, 17))


def test_pose_lattice_against_brute_force():
    free = _mask(SPEC.shape)
    lat = pose_lattice(SPEC, free, position_step_m=0.3, n_headings=5)
    assert lat.step_cells == 3 and lat.n_headings == 5
    ref = {}
    for bi in range(0, 23, 3):
        for bj in range(0, 17, 3):
            cells = [
                (i, j)
                for i in range(bi, min(bi + 3, 23))
                for j in range(bj, min(bj + 3, 17))
                if free[i, j]
            ]
            if cells:
                c = np.mean(np.asarray(cells, float), axis=0)
                ref[(bi // 3, bj // 3)] = (
                    len(cells),
                    -1.0 + (c[0] + 0.5) * 0.1,
                    2.0 + (c[1] + 0.5) * 0.1,
                    cells,
                )
    assert lat.n_blocks == len(ref)
    assert lat.n_free == int(free.sum())
    pos, counts = np.asarray(lat.positions), np.asarray(lat.counts)
    start, cells = np.asarray(lat.block_start), np.asarray(lat.block_cells)
    cb = np.asarray(lat.cell_block)
    got = {}
    for b in range(lat.n_blocks):
        mine = cells[start[b] : start[b] + counts[b]]
        ij = [tuple(int(t) for t in np.unravel_index(c, SPEC.shape)) for c in mine]
        key = (ij[0][0] // 3, ij[0][1] // 3)
        assert all((i // 3, j // 3) == key for i, j in ij)
        assert all(cb[i, j] == b for i, j in ij)
        got[key] = (int(counts[b]), float(pos[b, 0]), float(pos[b, 1]), sorted(ij))
    assert set(got) == set(ref)
    for k, (n, x, y, ij) in ref.items():
        assert got[k][0] == n and got[k][3] == sorted(ij)
        np.testing.assert_allclose(got[k][1:3], (x, y), atol=1e-5)
    assert np.all(cb[~free] == -1)
    hyp = np.asarray(lat.hypotheses())
    assert hyp.shape == (5 * lat.n_blocks, 3)
    np.testing.assert_allclose(hyp[:5, 2], -np.pi + (np.arange(5) + 0.5) * 2 * np.pi / 5, atol=1e-6)


def test_pose_lattice_budget_coarsens_minimally():
    free = np.ones(SPEC.shape, bool)
    lat = pose_lattice(SPEC, free, position_step_m=0.1, n_headings=4, max_hypotheses=200)
    k = lat.step_cells
    blocks = lambda k: math.ceil(23 / k) * math.ceil(17 / k)  # noqa: E731
    assert blocks(k) * 4 <= 200 < blocks(k - 1) * 4
    assert lat.n_hypotheses == blocks(k) * 4


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"free": np.ones((3, 3), bool)}, "shape"),
        ({"free": np.ones(SPEC.shape, np.int32)}, "bool"),
        ({"free": np.zeros(SPEC.shape, bool)}, "no True"),
        ({"position_step_m": 0.0}, "position_step_m"),
        ({"position_step_m": float("nan")}, "position_step_m"),
        ({"n_headings": 0}, "n_headings"),
        ({"n_headings": 2.5}, "n_headings"),
        ({"max_hypotheses": 3, "n_headings": 4}, "max_hypotheses"),
    ],
)
def test_pose_lattice_rejects_bad_input(kwargs, match):
    args = {"free": np.ones(SPEC.shape, bool), **kwargs}
    free = args.pop("free")
    with pytest.raises(ValueError, match=match):
        pose_lattice(SPEC, free, **args)


@pytest.mark.parametrize("uniform_fraction", [0.0, 0.3, 1.0])
def test_proposal_density_integrates_to_one(uniform_fraction):
    """The mixture density, summed over a fine grid of the free cells x headings,
    integrates to 1 (the lattice part and the uniform part are both normalised)."""
    free = _mask(SPEC.shape, seed=3)
    lat = pose_lattice(SPEC, free, position_step_m=0.4, n_headings=6)
    rng = np.random.default_rng(0)
    log_probs = rng.normal(0, 2, lat.n_hypotheses)
    log_probs = log_probs - np.log(np.exp(log_probs).sum())
    # midpoint rule: 4 x 4 points per cell, 24 headings (4 per bin)
    sub = (np.arange(4) + 0.5) / 4
    th = -np.pi + (np.arange(24) + 0.5) * 2 * np.pi / 24
    ii, jj = np.nonzero(free)
    xs = -1.0 + (ii[:, None, None] + sub[None, :, None]) * 0.1
    ys = 2.0 + (jj[:, None, None] + sub[None, None, :]) * 0.1
    xs, ys = np.broadcast_arrays(xs, ys)
    pts = np.stack([xs.ravel(), ys.ravel()], -1)
    v = np.concatenate([np.repeat(pts, th.size, 0), np.tile(th, pts.shape[0])[:, None]], axis=-1)
    lq = np.asarray(
        proposal_log_density(
            lat, jnp.asarray(log_probs, jnp.float32), jnp.asarray(v, jnp.float32), uniform_fraction
        )
    )
    integral = np.exp(lq.astype(np.float64)).sum() * (0.1 / 4) ** 2 * (2 * np.pi / 24)
    assert abs(integral - 1.0) < 1e-4


class GaussianPose(eqx.Module):
    """Toy scan model: a Gaussian likelihood in (x, y, theta) around a pose (the ranges
    are ignored)."""

    mean: jax.Array
    std: jax.Array

    def __call__(self, particles, ranges):
        v = to_vector(particles)
        d = v - self.mean
        d = d.at[:, 2].set(jnp.arctan2(jnp.sin(d[:, 2]), jnp.cos(d[:, 2])))
        return -0.5 * jnp.sum((d / self.std) ** 2, axis=-1)


def _quadrature_moments(free, spec, mean, std, n_sub=6, n_th=180):
    """Posterior ``1{free} N(x; mean, std)`` moments by the midpoint rule."""
    sub = (np.arange(n_sub) + 0.5) / n_sub
    ii, jj = np.nonzero(free)
    xs = spec_o(spec)[0] + (ii[:, None, None] + sub[None, :, None]) * float(spec.resolution)
    ys = spec_o(spec)[1] + (jj[:, None, None] + sub[None, None, :]) * float(spec.resolution)
    xs, ys = np.broadcast_arrays(xs, ys)
    x, y = xs.ravel(), ys.ravel()
    th = -np.pi + (np.arange(n_th) + 0.5) * 2 * np.pi / n_th
    wxy = np.exp(-0.5 * (((x - mean[0]) / std[0]) ** 2 + ((y - mean[1]) / std[1]) ** 2))
    wth = np.exp(-0.5 * (_wrap(th - mean[2]) / std[2]) ** 2)
    z = wxy.sum()
    mx, my = (wxy * x).sum() / z, (wxy * y).sum() / z
    sx = math.sqrt((wxy * (x - mx) ** 2).sum() / z)
    mth = math.atan2((wth * np.sin(th)).sum(), (wth * np.cos(th)).sum())
    return np.array([mx, my, mth]), sx


def spec_o(spec):
    return np.asarray(spec.origin, np.float64)


def test_init_from_scan_weights_give_the_posterior():
    """A coarse lattice (0.5 m, 8 headings) over a free region with holes and a Gaussian
    likelihood (0.25 m, 0.3 rad) near a border: the weighted particles reproduce the
    quadrature posterior's mean and spread; the unweighted ones do not."""
    spec = GridSpec(np.array([0.0, 0.0]), 0.1, (40, 30))
    free = np.ones(spec.shape, bool)
    free[5:12, 8:20] = False
    free[25:, 24:] = False
    mean = np.array([1.1, 0.9, 2.9])
    std = np.array([0.25, 0.25, 0.3])
    lat = pose_lattice(spec, free, position_step_m=0.5, n_headings=8)
    model = GaussianPose(jnp.asarray(mean, jnp.float32), jnp.asarray(std, jnp.float32))
    n = 200_000
    st = init_from_scan(
        n, lat, model, jnp.zeros(3), key=jax.random.PRNGKey(0), uniform_fraction=0.1
    )
    v = np.asarray(to_vector(st.particles), np.float64)
    w = np.exp(np.asarray(st.log_weights, np.float64))
    assert abs(w.sum() - 1) < 1e-4
    n_eff = 1 / np.sum(w**2)
    assert n_eff > 0.05 * n
    ref_mean, ref_sx = _quadrature_moments(free, spec, mean, std)
    mx, my = (w * v[:, 0]).sum(), (w * v[:, 1]).sum()
    sx = math.sqrt((w * (v[:, 0] - mx) ** 2).sum())
    mth = math.atan2((w * np.sin(v[:, 2])).sum(), (w * np.cos(v[:, 2])).sum())
    se = ref_sx / math.sqrt(n_eff)
    assert abs(mx - ref_mean[0]) < 6 * se
    assert abs(my - ref_mean[1]) < 6 * se
    assert abs(sx - ref_sx) < 0.03 * ref_sx
    assert abs(_wrap(mth - ref_mean[2])) < 6 * 0.3 / math.sqrt(n_eff)
    # without the weights the lattice proposal is measurably off (0.5 m blocks, 45 deg bins)
    ux = v[:, 0].mean()
    usx = v[:, 0].std()
    assert abs(ux - ref_mean[0]) > 20 * se or abs(usx - ref_sx) > 0.1 * ref_sx
    assert np.all(free[((v[:, :2]) / 0.1).astype(int)[:, 0], ((v[:, :2]) / 0.1).astype(int)[:, 1]])


@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_init_from_scan_is_deterministic_and_checks_inputs():
    free = np.ones(SPEC.shape, bool)
    lat = pose_lattice(SPEC, free, position_step_m=0.5, n_headings=4)
    model = GaussianPose(jnp.asarray([0.0, 3.0, 0.0]), jnp.asarray([0.3, 0.3, 0.5]))
    a = init_from_scan(50, lat, model, jnp.zeros(2), key=jax.random.PRNGKey(3))
    b = init_from_scan(50, lat, model, jnp.zeros(2), key=jax.random.PRNGKey(3))
    assert np.array_equal(
        np.asarray(a.particles.parameters()), np.asarray(b.particles.parameters())
    )
    assert np.array_equal(np.asarray(a.log_weights), np.asarray(b.log_weights))
    # precomputed scores (one scoring for several draws) give the same state
    sc = lattice_scores(lat, model, jnp.zeros(2))
    c = init_from_scan(50, lat, model, jnp.zeros(2), key=jax.random.PRNGKey(3), scores=sc)
    assert np.array_equal(
        np.asarray(a.particles.parameters()), np.asarray(c.particles.parameters())
    )
    assert np.array_equal(np.asarray(a.log_weights), np.asarray(c.log_weights))
    with pytest.raises(ValueError, match="scores must have shape"):
        init_from_scan(5, lat, model, jnp.zeros(2), key=jax.random.PRNGKey(0), scores=sc[:-1])
    with pytest.raises(ValueError, match="n must"):
        init_from_scan(0, lat, model, jnp.zeros(2), key=jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="uniform_fraction"):
        init_from_scan(5, lat, model, jnp.zeros(2), key=jax.random.PRNGKey(0), uniform_fraction=1.5)
    with pytest.raises(ValueError, match="chunk_size"):
        init_from_scan(5, lat, model, jnp.zeros(2), key=jax.random.PRNGKey(0), chunk_size=0)
    with pytest.raises(ValueError, match="lattice"):
        init_from_scan(5, "lattice", model, jnp.zeros(2), key=jax.random.PRNGKey(0))

    def nan_model(p, r):
        return jnp.full(p.parameters().shape[:1], jnp.nan)

    def impossible(p, r):
        return jnp.full(p.parameters().shape[:1], -jnp.inf)

    with pytest.raises(Exception, match="NaN"):
        init_from_scan(5, lat, nan_model, jnp.zeros(2), key=jax.random.PRNGKey(0))
    with pytest.raises(Exception, match="finite score"):
        init_from_scan(5, lat, impossible, jnp.zeros(2), key=jax.random.PRNGKey(0))


def test_lattice_scores_chunking_matches_direct():
    free = _mask(SPEC.shape, seed=5)
    lat = pose_lattice(SPEC, free, position_step_m=0.3, n_headings=7)
    model = GaussianPose(jnp.asarray([0.0, 3.0, 1.0]), jnp.asarray([0.3, 0.3, 0.5]))
    direct = np.asarray(model(jaxlie.SE2.from_xy_theta(*lat.hypotheses().T), None))
    for c in (1, 13, 10_000):
        np.testing.assert_allclose(
            np.asarray(lattice_scores(lat, model, None, c)), direct, rtol=1e-6
        )


@pytest.mark.slow
def test_init_from_scan_finds_the_pose_in_an_office():
    """A decay-rate map of a simulated 20 m x 12 m office; one 60-beam scan at an unknown
    pose: 95 % of the weight lies within 0.5 m / 0.2 rad of it (the posterior of a map
    smoothed by 0.3 m)."""
    world = make_office(seed=0)
    poses = world.trajectory(120, jitter_m=0.3, seed=1)
    az = np.linspace(-np.pi / 2, np.pi / 2, 91)
    r_min, r_max = 0.1, 15.0
    scans = simulate_scans(world, poses, az, max_range_m=r_max, noise_sigma_m=0.01, seed=0)
    spec = GridSpec.covering(world.bounds, 0.1, margin=0.5)
    rays = from_scan(jaxlie.SE2.from_xy_theta(*poses.T), az, scans, r_min, r_max)
    stats = accumulate(spec, rays)
    h = np.asarray(stats.hits, float)
    nn = h + np.asarray(stats.misses, float)
    free = (nn > 0) & (h < 0.2 * np.maximum(nn, 1))
    lat = pose_lattice(spec, free, position_step_m=0.5, n_headings=72)
    model = ScanModel(
        decay_rate_map(smooth_stats(stats, 0.3)), az[::3], r_min, r_max, ray_floor=-10.0
    )
    truth = world.trajectory(120, jitter_m=0.3, seed=2)[37]
    z = simulate_scans(world, truth[None], az, max_range_m=r_max, noise_sigma_m=0.01, seed=5)[0][
        ::3
    ]
    st = init_from_scan(2000, lat, model, jnp.asarray(z), key=jax.random.PRNGKey(1))
    v = np.asarray(to_vector(st.particles), np.float64)
    w = np.exp(np.asarray(st.log_weights, np.float64))
    d = np.linalg.norm(v[:, :2] - truth[:2], axis=1)
    dth = np.abs(_wrap(v[:, 2] - truth[2]))
    # a uniform start puts ~0.1 % of the mass there (240 m^2 x 2 pi)
    assert w[(d < 0.5) & (dth < 0.2)].sum() > 0.95
    assert np.linalg.norm((w[:, None] * v[:, :2]).sum(0) - truth[:2]) < 0.25
