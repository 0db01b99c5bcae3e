"""Localization remedies of the measurement side: kernel-smoothed grid statistics
(``maps.smooth_stats``), the uniform-mixture (``z_rand``) and tempered (``beam_exponent``)
scan likelihoods of ``ScanModel``. References are brute-force NumPy computations."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from lidarjax import maps
from lidarjax.localization import ScanModel, from_vector
from lidarjax.rays import HIT, SUB, SUP, classify, from_scan
from lidarjax.raytrace import GridSpec, GridStats, accumulate
from lidarjax.sim import OfficeWorld, simulate_scans


def _brute_smooth(a: np.ndarray, sigma: float, truncate: float = 3.0) -> np.ndarray:
    """Direct N-D sum over all cells within the truncated box, zero outside."""
    half = max(1, int(np.ceil(truncate * sigma)))
    w1 = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
    w1 /= w1.sum()
    out = np.zeros_like(a, dtype=np.float64)
    for idx in np.ndindex(a.shape):
        acc = 0.0
        for off in np.ndindex(*(2 * half + 1,) * a.ndim):
            src = tuple(i + o - half for i, o in zip(idx, off))
            if all(0 <= s < n for s, n in zip(src, a.shape)):
                acc += np.prod([w1[o] for o in off]) * a[src]
        out[idx] = acc
    return out


@pytest.mark.parametrize("shape", [(9, 7), (5, 6, 4)])
def test_smooth_cells_vs_brute_force(shape):
    rng = np.random.default_rng(0)
    a = rng.gamma(1.0, 2.0, shape)
    got = np.asarray(maps.smooth_cells(jnp.asarray(a), 0.8))
    np.testing.assert_allclose(got, _brute_smooth(a, 0.8), rtol=1e-12, atol=1e-12)
    assert np.array_equal(np.asarray(maps.smooth_cells(jnp.asarray(a), 0.0)), a)


def test_smooth_cells_preserves_interior_mass_and_gaussian_shape():
    a = np.zeros((41, 41))
    a[20, 20] = 5.0
    s = 2.0
    got = np.asarray(maps.smooth_cells(jnp.asarray(a), s))
    np.testing.assert_allclose(got.sum(), 5.0, rtol=1e-12)
    # separable normalised Gaussian: ratio of neighbours is exp(-(2k+1)/(2 s^2))
    row = got[20, 20:26]
    np.testing.assert_allclose(row[1:] / row[:-1], np.exp(-(2 * np.arange(5) + 1) / (2 * s * s)))
    # on the border mass leaks out, never in
    b = np.zeros((10, 10))
    b[0, 0] = 1.0
    assert float(np.asarray(maps.smooth_cells(jnp.asarray(b), 1.0)).sum()) < 1.0


def _stats():
    spec = GridSpec(np.array([0.0, 0.0]), 0.1, (12, 10))
    rng = np.random.default_rng(3)
    hits = rng.integers(0, 4, spec.shape).astype(np.int32)
    misses = rng.integers(0, 6, spec.shape).astype(np.int32)
    lengths = rng.uniform(0.0, 2.0, spec.shape) * (hits + misses > 0)
    return GridStats(spec, jnp.asarray(hits), jnp.asarray(misses), jnp.asarray(lengths))


def test_smooth_stats_models_are_kernel_rates():
    st = _stats()
    sm = maps.smooth_stats(st, 0.15)  # 1.5 cells
    h = _brute_smooth(np.asarray(st.hits, np.float64), 1.5)
    m = _brute_smooth(np.asarray(st.misses, np.float64), 1.5)
    r = _brute_smooth(np.asarray(st.lengths), 1.5)
    np.testing.assert_allclose(np.asarray(sm.hits), h, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(sm.misses), m, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(sm.lengths), r, rtol=1e-12, atol=1e-12)
    dec = maps.decay_rate_map(sm)
    seen = r > 0
    np.testing.assert_allclose(np.asarray(dec.rates)[seen], (h / np.where(seen, r, 1))[seen])
    ref = maps.reflection_map(sm)
    vis = (h + m) > 0
    np.testing.assert_allclose(np.asarray(ref.probs)[vis], (h / np.where(vis, h + m, 1))[vis])
    g = maps.gamma_posterior(sm, alpha=1.0, beta=0.5)
    np.testing.assert_allclose(np.asarray(g.hits), h, rtol=1e-12)
    # sigma 0: the same numbers, as floats
    z = maps.smooth_stats(st, 0.0)
    assert np.array_equal(np.asarray(z.hits), np.asarray(st.hits, np.float64))
    assert z.hits.dtype == st.lengths.dtype


@pytest.mark.parametrize(
    ("args", "match"),
    [
        ((-0.1,), "sigma_m"),
        ((float("nan"),), "sigma_m"),
        (("wide",), "sigma_m"),
    ],
)
def test_smooth_stats_bad_input(args, match):
    with pytest.raises(ValueError, match=match):
        maps.smooth_stats(_stats(), *args)
    with pytest.raises(ValueError, match="stats"):
        maps.smooth_stats(np.zeros((3, 3)), 0.1)
    with pytest.raises(ValueError, match="truncate"):
        maps.smooth_stats(_stats(), 0.1, truncate=0.0)


# ------------------------------------------------------------------ ScanModel remedies

R_MIN, R_MAX = 0.15, 3.5
AZ = np.linspace(-np.pi, np.pi, 24, endpoint=False)
SPEC = GridSpec(np.array([-0.5, -0.5]), 0.25, (20, 16))


@pytest.fixture(scope="module")
def scan():
    segs = [
        ((0.0, 0.0), (4.0, 0.0)),
        ((4.0, 0.0), (4.0, 3.0)),
        ((4.0, 3.0), (0.0, 3.0)),
        ((0.0, 3.0), (0.0, 0.0)),
        ((2.0, 0.0), (2.0, 1.2)),
    ]
    world = OfficeWorld(
        segments=np.asarray(segs, np.float64),
        bounds=np.array([[0.0, 0.0], [4.0, 3.0]]),
        waypoints=np.array([[1.0, 1.0], [3.0, 2.5]]),
        seed=0,
    )
    map_poses = np.array([[1.0, 1.0, 0.0], [1.2, 2.2, 1.0], [3.3, 0.7, 2.0], [3.4, 2.4, -2.5]])
    scans = simulate_scans(world, map_poses, AZ, max_range_m=R_MAX, noise_sigma_m=0.01, seed=1)
    stats = accumulate(
        SPEC, from_scan(jaxlie.SE2.from_xy_theta(*map_poses.T), AZ, scans, R_MIN, R_MAX)
    )
    truth = np.array([1.5, 1.4, 0.3])
    ranges = simulate_scans(world, truth[None], AZ, max_range_m=R_MAX, noise_sigma_m=0.01, seed=2)[
        0
    ]
    ranges[3] = 0.05  # SUB
    ranges[7] = R_MAX + 1.0  # SUP
    rng = np.random.default_rng(13)
    v = truth + rng.normal(0.0, [0.3, 0.3, 0.2], (9, 3))
    return {"stats": stats, "ranges": ranges, "particles": from_vector(v)}


@pytest.mark.parametrize("model", ["dec", "fmp_dec", "end"])
@pytest.mark.parametrize(
    ("z_rand", "beta", "floor"), [(0.1, 1.0, None), (0.05, 0.3, -8.0), (0.0, 0.5, -6.0)]
)
def test_scan_model_mixture_and_tempering_vs_numpy(scan, model, z_rand, beta, floor):
    st = scan["stats"]
    m = {
        "dec": maps.decay_rate_map(st),
        "fmp_dec": maps.gamma_posterior(st),
        "end": maps.endpoint_map(st, sigma_m=0.2),
    }[model]
    ranges = jnp.asarray(scan["ranges"])
    pure = ScanModel(m, AZ, R_MIN, R_MAX)
    p = np.exp(np.asarray(pure.ray_log_likelihoods(scan["particles"], ranges)))  # [n b]
    kind = np.asarray(classify(ranges, R_MIN, R_MAX))
    u = np.where(kind == HIT, 1.0 / R_MAX, np.where(kind == SUB, R_MIN / R_MAX, 0.0))
    with np.errstate(divide="ignore"):
        ref = np.log((1 - z_rand) * p + z_rand * u)
    if floor is not None:
        ref = np.maximum(ref, floor)
    ref = beta * ref
    got_model = ScanModel(m, AZ, R_MIN, R_MAX, z_rand=z_rand, beam_exponent=beta, ray_floor=floor)
    got = np.asarray(got_model.ray_log_likelihoods(scan["particles"], ranges))
    fin = np.isfinite(ref)
    np.testing.assert_array_equal(got[~fin], ref[~fin])
    np.testing.assert_allclose(got[fin], ref[fin], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(
        np.asarray(got_model(scan["particles"], ranges)), ref.sum(1), rtol=1e-9, atol=1e-9
    )
    assert (kind == SUP).any() and (kind == SUB).any()
    if z_rand > 0:  # the mixture bounds every in-range beam from below
        assert np.all(got[:, kind == HIT] >= beta * np.log(z_rand / R_MAX) - 1e-12)


def test_scan_model_mixture_is_normalised_in_range():
    """(1 - z) p + z u integrates to 1 over readings when p does: the uniform part has
    density 1/r_max on [r_min, r_max) plus mass r_min/r_max at SUB and 0 at SUP."""
    z = 0.2
    mass_hit = (R_MAX - R_MIN) / R_MAX
    mass_sub = R_MIN / R_MAX
    assert np.isclose(z * (mass_hit + mass_sub) + (1 - z) * 1.0, 1.0)


def test_scan_model_remedy_bad_arguments(scan):
    m = maps.decay_rate_map(scan["stats"])
    for bad in (-0.1, 1.0, float("nan"), "x"):
        with pytest.raises(ValueError, match="z_rand"):
            ScanModel(m, AZ, R_MIN, R_MAX, z_rand=bad)
    for bad in (0.0, 1.5, float("nan"), None):
        with pytest.raises(ValueError, match="beam_exponent"):
            ScanModel(m, AZ, R_MIN, R_MAX, beam_exponent=bad)
    with pytest.raises(ValueError, match="z_rand"):
        ScanModel(m, AZ, R_MIN, float("inf"), z_rand=0.1)


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_coarse_to_fine_uses_the_level_of_the_spread(scan):
    """Each call equals the ScanModel of the level picked by the particles' spread (RMS
    distance from their mean): coarse for a wide cloud, the finest for a tight one; under
    vmap each filter gets its own level."""
    from lidarjax.localization import CoarseToFineScanModel, coarse_to_fine_scan_model

    st = scan["stats"]
    sig = (0.0, 0.25, 0.5)
    c2f = coarse_to_fine_scan_model(st, maps.decay_rate_map, sig, AZ, R_MIN, R_MAX, ray_floor=-8.0)
    assert isinstance(c2f, CoarseToFineScanModel)
    ranges = jnp.asarray(scan["ranges"])
    center = np.array([1.5, 1.4, 0.3])
    rng = np.random.default_rng(5)
    for spread, want in ((0.05, 0), (0.3, 1), (0.8, 2)):
        v = center + rng.normal(0.0, 1.0, (64, 3)) * [1, 1, 0.1]
        xy = v[:, :2] - v[:, :2].mean(0)
        v[:, :2] = center[:2] + xy * spread / np.sqrt(np.mean(np.sum(xy**2, -1)))
        p = from_vector(jnp.asarray(v))
        assert int(c2f.level(p)) == want
        ref = ScanModel(
            maps.decay_rate_map(maps.smooth_stats(st, sig[want])), AZ, R_MIN, R_MAX, ray_floor=-8.0
        )
        np.testing.assert_allclose(
            np.asarray(c2f(p, ranges)), np.asarray(ref(p, ranges)), rtol=1e-12
        )
    # batched over two filters with different spreads
    tight = from_vector(jnp.asarray(center + rng.normal(0, 0.01, (64, 3))))
    wide = from_vector(jnp.asarray(center + rng.normal(0, 0.6, (64, 3)) * [1, 1, 0.1]))
    both = jax.tree.map(lambda a, b: jnp.stack([a, b]), tight, wide)
    got = jax.vmap(lambda p: c2f(p, ranges))(both)
    np.testing.assert_allclose(np.asarray(got[0]), np.asarray(c2f(tight, ranges)), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(got[1]), np.asarray(c2f(wide, ranges)), rtol=1e-12)
    with pytest.raises(ValueError, match="sigmas_m"):
        coarse_to_fine_scan_model(st, maps.decay_rate_map, (0.2, 0.1), AZ, R_MIN, R_MAX)
    with pytest.raises(ValueError, match="spread_factor"):
        coarse_to_fine_scan_model(
            st, maps.decay_rate_map, (0.0, 0.1), AZ, R_MIN, R_MAX, spread_factor=0
        )
    with pytest.raises(ValueError, match="share"):
        CoarseToFineScanModel(
            [
                ScanModel(maps.decay_rate_map(st), AZ, R_MIN, R_MAX),
                ScanModel(maps.gamma_posterior(st), AZ, R_MIN, R_MAX),
            ],
            (0.0, 0.1),
        )
