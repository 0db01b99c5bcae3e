"""Tests for lidarjax.localization: resampling, weights, pose means, motion model,
initialisation, the particle filter and the scan measurement model.

Statistical checks use tolerances of 6 standard errors derived from the sample size, with
fixed keys, so they are deterministic and fail only if the tested moment is wrong."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from lidarjax.localization import (
    OdometryMotionModel,
    ParticleFilter,
    ParticleState,
    ScanModel,
    circular_mean,
    effective_sample_size,
    estimate,
    from_vector,
    init_gaussian,
    init_global,
    init_uniform_disc,
    multinomial_resample,
    normalize_log_weights,
    relative_motion,
    stratified_resample,
    systematic_resample,
    to_vector,
    weighted_mean,
)
from lidarjax.maps import EndpointMap, decay_rate_map, endpoint_map, reflection_map
from lidarjax.rays import from_scan
from lidarjax.raytrace import GridSpec, accumulate, max_cells_for
from lidarjax.sensor_models import (
    decay_rate_log_likelihood,
    endpoint_log_likelihood,
    reflection_log_likelihood,
)
from lidarjax.sim import OfficeWorld, simulate_scans
from lidarjax.testing import tree_allclose

Z = 6.0  # standard errors allowed in statistical checks


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _log_w(w):
    w = np.asarray(w, np.float64)
    with np.errstate(divide="ignore"):
        return jnp.asarray(np.log(w / w.sum()))


# --------------------------------------------------------------------------------------
# Weights and resampling
# --------------------------------------------------------------------------------------

WEIGHTS = np.array([0.31, 0.0, 0.07, 0.22, 0.0, 0.013, 0.187, 0.2])  # n = 8, sums to 1
RESAMPLER_FNS = {
    "systematic": systematic_resample,
    "stratified": stratified_resample,
    "multinomial": multinomial_resample,
}


def _offspring(fn, key, log_w, n_runs):
    n = log_w.shape[0]
    idx = jax.vmap(lambda k: fn(log_w, key=k))(jax.random.split(key, n_runs))
    assert idx.shape == (n_runs, n)
    idx = np.asarray(idx)
    assert idx.min() >= 0 and idx.max() < n
    return np.stack([np.bincount(row, minlength=n) for row in idx])  # [runs n]


@pytest.mark.parametrize("name", list(RESAMPLER_FNS))
def test_resampling_unbiased(name, key):
    """E[offspring_i] = n w_i. The per-run count variance is at most the multinomial
    n w_i (1 - w_i) for all three schemes. Systematic counts are floor(n w_i) or
    ceil(n w_i); stratified counts (one draw per stratum, only the two strata at the ends
    of particle i's CDF interval are uncertain) lie in [floor(n w_i) - 1, ceil(n w_i) + 1]."""
    n, runs = WEIGHTS.size, 4000
    counts = _offspring(RESAMPLER_FNS[name], key, _log_w(WEIGHTS), runs)
    assert np.all(counts.sum(axis=1) == n)
    nw = n * WEIGHTS
    se = np.sqrt(nw * (1 - WEIGHTS) / runs)
    np.testing.assert_array_less(np.abs(counts.mean(axis=0) - nw), Z * se + 1e-12)
    # zero-weight particles are never chosen
    assert np.all(counts[:, WEIGHTS == 0] == 0)
    lo, hi = np.floor(nw + 1e-12), np.ceil(nw - 1e-12)
    inside = (counts == lo) | (counts == hi)
    if name == "systematic":
        assert np.all(inside)
        assert {0, 1} <= set(counts[:, 2].tolist())  # n w_2 = 0.56: both values occur
    elif name == "stratified":
        assert np.all((counts >= lo - 1) & (counts <= hi + 1))
        assert not np.all(inside)  # stratified is not systematic
    else:
        assert counts.max() > hi.max() + 1  # multinomial has no such bound


def test_systematic_zero_weight_last_particle_never_chosen_float32(key):
    """With float32 weights the last comb position ``(n - 1 + u) / n`` rounds to exactly 1
    when the uniform offset ``u`` lies within half an ulp of ``n - 1`` below 1 (for
    n = 2**12: u > 1 - 2**-13). A zero-weight particle at the end of the CDF (e.g. one
    whose likelihood was 0) must still never be chosen. The keys are picked among many so
    that the offset is that close to 1 (float32 is JAX's default precision)."""
    n = 2**12
    w = np.ones(n)
    w[-1] = 0.0
    log_w = _log_w(w).astype(jnp.float32)
    keys = jax.random.split(key, 100000)
    u = jax.vmap(lambda k: jax.random.uniform(k, (), jnp.float32))(keys)
    picked = keys[np.flatnonzero(np.asarray(u) > 1 - 2.0**-13)]
    assert picked.shape[0] >= 1
    idx = np.asarray(jax.vmap(lambda k: systematic_resample(log_w, key=k))(picked))
    assert not np.any(idx == n - 1)


def test_normalize_log_weights():
    rng = np.random.default_rng(1)
    lw = rng.normal(size=10) * 30 - 500.0  # far from 0: needs the log-sum-exp shift
    out = np.asarray(normalize_log_weights(jnp.asarray(lw)))
    m = lw.max()
    ref = lw - (m + np.log(np.sum(np.exp(lw - m))))
    np.testing.assert_allclose(out, ref, rtol=1e-12, atol=1e-12)
    # -inf entries stay -inf and the rest are normalised
    lw2 = lw.copy()
    lw2[[2, 5]] = -np.inf
    out2 = np.asarray(normalize_log_weights(jnp.asarray(lw2)))
    assert np.all(out2[[2, 5]] == -np.inf)
    np.testing.assert_allclose(np.exp(out2).sum(), 1.0, rtol=1e-12)
    # all -inf, any NaN, or +inf: uniform, no NaN
    for bad in (
        np.full(7, -np.inf),
        np.array([0.0, np.nan, -1.0, 2.0, 0.0, 1.0, 3.0]),
        np.full(7, np.nan),
    ):
        out = np.asarray(normalize_log_weights(jnp.asarray(bad)))
        np.testing.assert_allclose(out, np.full(7, -np.log(7)), rtol=1e-14)


def test_effective_sample_size():
    n = 13
    np.testing.assert_allclose(float(effective_sample_size(jnp.zeros(n))), n, rtol=1e-12)
    np.testing.assert_allclose(float(effective_sample_size(jnp.full(n, -1234.5))), n, rtol=1e-12)
    one_hot = np.full(n, -np.inf)
    one_hot[4] = 0.0
    np.testing.assert_allclose(float(effective_sample_size(jnp.asarray(one_hot))), 1.0)
    rng = np.random.default_rng(2)
    lw = rng.normal(size=n) * 2
    w = np.exp(lw - lw.max())
    w /= w.sum()
    np.testing.assert_allclose(
        float(effective_sample_size(jnp.asarray(lw))), 1 / np.sum(w**2), rtol=1e-12
    )
    # degenerate weights give n, not NaN
    np.testing.assert_allclose(float(effective_sample_size(jnp.full(n, -np.inf))), n)


# --------------------------------------------------------------------------------------
# Pose vectors and means
# --------------------------------------------------------------------------------------


def test_circular_mean_wraps_at_pi():
    a = jnp.deg2rad(jnp.asarray([179.0, -179.0]))
    m = float(circular_mean(a, jnp.ones(2)))
    np.testing.assert_allclose(abs(m), np.pi, atol=1e-12)
    # unequal weights: pulled towards the heavier angle, across the cut
    m2 = float(circular_mean(jnp.deg2rad(jnp.asarray([170.0, -170.0])), jnp.asarray([1.0, 3.0])))
    ref = np.arctan2(
        np.sin(np.deg2rad(170)) + 3 * np.sin(np.deg2rad(-170)),
        np.cos(np.deg2rad(170)) + 3 * np.cos(np.deg2rad(-170)),
    )
    np.testing.assert_allclose(m2, ref, atol=1e-12)
    assert -np.pi < m2 < -np.deg2rad(170)  # between -180 and -170 deg
    # mean of -179 and 177 deg (equal weights) is exactly 179 deg: midpoint of the short arc
    m3 = float(circular_mean(jnp.deg2rad(jnp.asarray([-179.0, 177.0])), jnp.ones(2)))
    np.testing.assert_allclose(m3, np.deg2rad(179.0), atol=1e-12)


def test_circular_mean_batched_vs_numpy():
    rng = np.random.default_rng(3)
    a = rng.uniform(-np.pi, np.pi, size=(5, 9))
    w = rng.uniform(0, 1, size=(5, 9))
    ref = np.arctan2((w * np.sin(a)).sum(-1), (w * np.cos(a)).sum(-1))
    np.testing.assert_allclose(
        np.asarray(circular_mean(jnp.asarray(a), jnp.asarray(w))), ref, atol=1e-12
    )


def test_weighted_mean_se2_vs_numpy():
    rng = np.random.default_rng(4)
    n = 11
    v = np.column_stack(
        [rng.normal(size=n), rng.normal(size=n), _wrap(np.pi + rng.normal(size=n) * 0.2)]
    )
    w = rng.uniform(0.1, 2.0, n)
    m = weighted_mean(from_vector(v), jnp.asarray(w))
    wn = w / w.sum()
    np.testing.assert_allclose(np.asarray(m.translation()), wn @ v[:, :2], atol=1e-12)
    th = np.arctan2(wn @ np.sin(v[:, 2]), wn @ np.cos(v[:, 2]))
    np.testing.assert_allclose(_wrap(float(m.rotation().as_radians()) - th), 0.0, atol=1e-12)
    assert abs(th) > 2.5  # the headings straddle +-pi


def test_weighted_mean_se3():
    rng = np.random.default_rng(5)
    n = 7
    rot = jaxlie.SO3.from_rpy_radians(0.3, -0.4, 2.9)
    q = np.asarray(rot.wxyz)
    # the same rotation with random quaternion signs
    signs = np.where(rng.uniform(size=n) < 0.5, -1.0, 1.0)
    t = rng.normal(size=(n, 3))
    w = rng.uniform(0.1, 1.0, n)
    poses = jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3(jnp.asarray(signs[:, None] * q)), jnp.asarray(t)
    )
    m = weighted_mean(poses, jnp.asarray(w))
    np.testing.assert_allclose(np.asarray(m.translation()), (w / w.sum()) @ t, atol=1e-12)
    np.testing.assert_allclose(
        np.asarray(m.rotation().as_matrix()), np.asarray(rot.as_matrix()), atol=1e-12
    )
    # rotations about one axis: the chordal mean has angle 2 atan2(sum w sin(a/2), sum w cos(a/2))
    a = rng.uniform(-0.8, 0.8, n) + 1.0
    rz = jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.from_z_radians(jnp.asarray(a)), jnp.zeros((n, 3))
    )
    mz = weighted_mean(rz, jnp.asarray(w))
    ref = 2 * np.arctan2(w @ np.sin(a / 2), w @ np.cos(a / 2))
    np.testing.assert_allclose(
        np.asarray(mz.rotation().as_matrix()),
        np.asarray(jaxlie.SO3.from_z_radians(ref).as_matrix()),
        atol=1e-12,
    )


def _estimate_ref(v, lw, frac):
    n = len(lw)
    k = max(1, math.ceil(frac * n))
    top = np.argsort(-lw)[:k]
    w = np.exp(lw[top] - lw[top].max())
    w /= w.sum()
    xy = w @ v[top, :2]
    th = np.arctan2(w @ np.sin(v[top, 2]), w @ np.cos(v[top, 2]))
    return xy, th


@pytest.mark.parametrize("frac", [0.1, 1.0])
def test_estimate_best_fraction_vs_numpy(frac):
    rng = np.random.default_rng(6)
    n = 50
    v = np.column_stack([rng.normal(size=(n, 2)) * 3, rng.uniform(-np.pi, np.pi, n)])
    lw = np.asarray(normalize_log_weights(jnp.asarray(rng.normal(size=n) * 2)))
    state = ParticleState(from_vector(v), jnp.asarray(lw), jax.random.key(0))
    est = estimate(state, frac)
    xy, th = _estimate_ref(v, lw, frac)
    np.testing.assert_allclose(np.asarray(est.translation()), xy, atol=1e-12)
    np.testing.assert_allclose(_wrap(float(est.rotation().as_radians()) - th), 0.0, atol=1e-12)
    for bad in (0.0, -0.1, 1.5):
        with pytest.raises(ValueError, match="best_fraction"):
            estimate(state, bad)


def test_vector_round_trips():
    rng = np.random.default_rng(7)
    v2 = np.column_stack([rng.normal(size=(20, 2)) * 5, rng.uniform(-3.1, 3.1, 20)])
    np.testing.assert_allclose(np.asarray(to_vector(from_vector(v2))), v2, atol=1e-12)
    v3 = np.column_stack(
        [
            rng.normal(size=(20, 3)) * 5,
            rng.uniform(-3.1, 3.1, 20),
            rng.uniform(-1.5, 1.5, 20),
            rng.uniform(-3.1, 3.1, 20),
        ]
    )
    np.testing.assert_allclose(np.asarray(to_vector(from_vector(v3, jaxlie.SE3))), v3, atol=1e-10)
    # SE3 rotation convention R = Rz(yaw) Ry(pitch) Rx(roll)
    r, p, y = v3[0, 3:]
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    np.testing.assert_allclose(
        np.asarray(from_vector(v3[0], jaxlie.SE3).rotation().as_matrix()),
        rz @ ry @ rx,
        atol=1e-12,
    )
    with pytest.raises(ValueError, match="pose vectors"):
        from_vector(np.zeros((4, 4)))
    with pytest.raises(ValueError, match="pose group"):
        from_vector(np.zeros(3), jaxlie.SO2)
    with pytest.raises(ValueError, match="pose must be"):
        to_vector(jaxlie.SO2.identity())


def test_relative_motion_se2_vs_numpy():
    rng = np.random.default_rng(8)
    T = 12
    v = np.column_stack([np.cumsum(rng.normal(size=(T, 2)), 0), rng.uniform(-np.pi, np.pi, T)])
    rel = np.asarray(relative_motion(v))
    assert rel.shape == (T - 1, 3)
    dxy = v[1:, :2] - v[:-1, :2]
    c, s = np.cos(v[:-1, 2]), np.sin(v[:-1, 2])
    ref_xy = np.column_stack([c * dxy[:, 0] + s * dxy[:, 1], -s * dxy[:, 0] + c * dxy[:, 1]])
    np.testing.assert_allclose(rel[:, :2], ref_xy, atol=1e-12)
    np.testing.assert_allclose(_wrap(rel[:, 2] - (v[1:, 2] - v[:-1, 2])), 0.0, atol=1e-12)


def test_relative_motion_se3_composes_back():
    rng = np.random.default_rng(9)
    T = 6
    v = np.column_stack(
        [
            rng.normal(size=(T, 3)),
            rng.uniform(-3, 3, T),
            rng.uniform(-1.4, 1.4, T),
            rng.uniform(-3, 3, T),
        ]
    )
    rel = relative_motion(v, jaxlie.SE3)
    assert rel.shape == (T - 1, 6)
    pose = from_vector(v[0], jaxlie.SE3)
    for t in range(1, T):
        pose = pose @ from_vector(rel[t - 1], jaxlie.SE3)
        np.testing.assert_allclose(
            np.asarray(pose.as_matrix()),
            np.asarray(from_vector(v[t], jaxlie.SE3).as_matrix()),
            atol=1e-10,
        )


# --------------------------------------------------------------------------------------
# Motion model
# --------------------------------------------------------------------------------------


def _check_gaussian_sample(x, mean, std):
    """Sample mean, per-component variance and correlations of ``x [n k]`` against an
    independent Gaussian N(mean, diag(std^2)), each within Z standard errors."""
    n = x.shape[0]
    np.testing.assert_array_less(np.abs(x.mean(0) - mean), Z * std / np.sqrt(n))
    var = x.var(0, ddof=1)
    np.testing.assert_array_less(np.abs(var - std**2), Z * std**2 * np.sqrt(2.0 / (n - 1)))
    corr = np.corrcoef(x.T)
    off = corr[~np.eye(len(mean), dtype=bool)]
    np.testing.assert_array_less(np.abs(off), Z / np.sqrt(n))


def test_odometry_motion_model_se2_moments(key):
    n = 40000
    chi = np.array([0.5, -0.2, 0.3])
    sigma = np.array([0.02, 0.01, 0.005])
    alpha = np.array([[0.1, 0.0, 0.05], [0.02, 0.05, 0.0], [0.03, 0.0, 0.2]])
    model = OdometryMotionModel(sigma, alpha, inflation=1.5)
    std = 1.5 * (sigma + alpha @ np.abs(chi))
    np.testing.assert_allclose(np.asarray(model.std(jnp.asarray(chi))), std, rtol=1e-12)
    ident = jaxlie.SE2(jnp.tile(jaxlie.SE2.identity().parameters(), (n, 1)))
    out = model(ident, jnp.asarray(chi), key=key)
    xi = np.asarray(to_vector(ident.inverse() @ out))
    _check_gaussian_sample(xi, chi, std)


def test_odometry_motion_model_composes_on_the_right(key):
    """From a common start pose X0 the particles are X0 @ T(xi): in the world frame the
    mean displacement is R(theta0) chi_xy."""
    n = 20000
    chi = np.array([0.4, 0.1, -0.2])
    sigma = np.array([0.03, 0.03, 0.01])
    model = OdometryMotionModel(sigma)
    x0 = np.array([2.0, -1.0, 2.5])
    start = from_vector(np.tile(x0, (n, 1)))
    v = np.asarray(to_vector(model(start, jnp.asarray(chi), key=key)))
    c, s = np.cos(x0[2]), np.sin(x0[2])
    mean_xy = x0[:2] + np.array([c * chi[0] - s * chi[1], s * chi[0] + c * chi[1]])
    # the world-frame xy noise is a rotation of independent N(0, 0.03^2): std 0.03 per axis
    np.testing.assert_array_less(np.abs(v[:, :2].mean(0) - mean_xy), Z * 0.03 / np.sqrt(n))
    np.testing.assert_array_less(abs(_wrap(v[:, 2] - x0[2] - chi[2]).mean()), Z * 0.01 / np.sqrt(n))


def test_odometry_motion_model_se3(key):
    n = 20000
    chi = np.array([0.3, 0.1, -0.2, 0.05, -0.03, 0.2])
    sigma = np.array([0.02, 0.02, 0.01, 0.004, 0.004, 0.01])
    model = OdometryMotionModel(sigma, group=jaxlie.SE3)
    # from the identity the increments are recovered exactly
    ident = jaxlie.SE3(jnp.tile(jaxlie.SE3.identity().parameters(), (n, 1)))
    xi = np.asarray(to_vector(model(ident, jnp.asarray(chi), key=key)))
    _check_gaussian_sample(xi, chi, sigma)
    # from a rotated start the mean translation is t0 + R0 chi_t
    x0 = np.array([1.0, 2.0, 0.5, 0.2, -0.3, 1.1])
    start = from_vector(np.tile(x0, (n, 1)), jaxlie.SE3)
    out = model(start, jnp.asarray(chi), key=jax.random.fold_in(key, 1))
    r0 = np.asarray(from_vector(x0, jaxlie.SE3).rotation().as_matrix())
    mean_t = x0[:3] + r0 @ chi[:3]
    # xi_t noise (std <= 0.02 per axis) rotated: per-axis std <= 0.02 (+ rotation noise
    # times |chi_t| <= 0.02 * 0.4)
    tol = Z * (0.02 + 0.02 * 0.4) / np.sqrt(n)
    np.testing.assert_array_less(np.abs(np.asarray(out.translation()).mean(0) - mean_t), tol)


def test_odometry_motion_model_bad_arguments():
    with pytest.raises(ValueError, match="sigma must be"):
        OdometryMotionModel([0.1, 0.1])
    with pytest.raises(ValueError, match="sigma must be"):
        OdometryMotionModel([0.1, 0.1, 0.1], group=jaxlie.SE3)
    with pytest.raises(ValueError, match="alpha"):
        OdometryMotionModel([0.1, 0.1, 0.1], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="inflation"):
        OdometryMotionModel([0.1, 0.1, 0.1], inflation=[1.0, 2.0])
    with pytest.raises(ValueError, match="sigma must be finite"):
        OdometryMotionModel([0.1, -0.1, 0.1])
    with pytest.raises(ValueError, match="sigma must be finite"):
        OdometryMotionModel([0.1, np.nan, 0.1])
    with pytest.raises(ValueError, match="alpha must be finite"):
        OdometryMotionModel([0.1, 0.1, 0.1], -np.eye(3))
    with pytest.raises(ValueError, match="inflation must be finite"):
        OdometryMotionModel([0.1, 0.1, 0.1], inflation=-1.0)
    with pytest.raises(ValueError, match="pose group"):
        OdometryMotionModel([0.1, 0.1, 0.1], group=jaxlie.SO3)


# --------------------------------------------------------------------------------------
# Initialisation
# --------------------------------------------------------------------------------------


def _check_uniform_weights(state, n):
    assert state.n == n
    np.testing.assert_allclose(np.asarray(state.log_weights), -np.log(n), rtol=1e-14)


def test_init_gaussian_moments(key):
    n = 20000
    mean = np.array([1.0, -2.0, 0.5])
    std = np.array([0.3, 0.1, 0.2])
    state = init_gaussian(n, mean, std, key=key)
    _check_uniform_weights(state, n)
    _check_gaussian_sample(np.asarray(to_vector(state.particles)), mean, std)
    # SE3, and the state's key is a fresh one
    mean6 = np.array([1.0, 2.0, 3.0, 0.1, -0.2, 0.3])
    std6 = np.array([0.5, 0.4, 0.3, 0.05, 0.04, 0.03])
    s3 = init_gaussian(n, mean6, std6, jaxlie.SE3, key=key)
    _check_gaussian_sample(np.asarray(to_vector(s3.particles)), mean6, std6)
    assert not np.array_equal(
        np.asarray(jax.random.key_data(s3.key)), np.asarray(jax.random.key_data(key))
    )


def test_init_gaussian_bad_input(key):
    for bad_n in (0, -1, 2.5, "3"):
        with pytest.raises(ValueError, match="n must"):
            init_gaussian(bad_n, np.zeros(3), np.ones(3), key=key)
    with pytest.raises(ValueError, match="mean"):
        init_gaussian(5, np.zeros(2), np.ones(3), key=key)
    with pytest.raises(ValueError, match="std"):
        init_gaussian(5, np.zeros(3), np.ones(6), key=key)
    with pytest.raises(ValueError, match="std"):
        init_gaussian(5, np.zeros(3), np.array([1.0, -1.0, 1.0]), key=key)
    with pytest.raises(ValueError, match="mean"):
        init_gaussian(5, np.array([0.0, np.nan, 0.0]), np.ones(3), key=key)
    with pytest.raises(ValueError, match="mean"):
        init_gaussian(5, np.zeros(3), np.ones(3), jaxlie.SE3, key=key)


def test_init_uniform_disc(key):
    n = 20000
    c = np.array([3.0, -1.0])
    radius, lo, hi = 2.5, -0.1, 0.3
    state = init_uniform_disc(n, c, radius, (lo, hi), key=key)
    _check_uniform_weights(state, n)
    v = np.asarray(to_vector(state.particles))
    d = np.linalg.norm(v[:, :2] - c, axis=1)
    assert np.all(d <= radius * (1 + 1e-12))
    assert np.all((v[:, 2] >= lo) & (v[:, 2] <= hi))
    # uniform in area: P(d < r) = (r / R)^2; uniform heading: mean (lo + hi) / 2
    for frac in (0.25, 0.5, 0.9):
        p = frac**2
        assert abs(np.mean(d < frac * radius) - p) < Z * np.sqrt(p * (1 - p) / n)
    np.testing.assert_array_less(np.abs(v[:, :2].mean(0) - c), Z * (radius / 2) / np.sqrt(n))
    assert abs(v[:, 2].mean() - (lo + hi) / 2) < Z * (hi - lo) / np.sqrt(12 * n)
    # degenerate disc and interval
    s0 = init_uniform_disc(10, c, 0.0, (0.2, 0.2), key=key)
    np.testing.assert_allclose(
        np.asarray(to_vector(s0.particles)), np.tile([3.0, -1.0, 0.2], (10, 1)), atol=1e-12
    )


def test_init_uniform_disc_bad_input(key):
    with pytest.raises(ValueError, match="center_xy"):
        init_uniform_disc(5, np.zeros(3), 1.0, (0.0, 1.0), key=key)
    with pytest.raises(ValueError, match="center_xy"):
        init_uniform_disc(5, np.array([0.0, np.inf]), 1.0, (0.0, 1.0), key=key)
    with pytest.raises(ValueError, match="radius_m"):
        init_uniform_disc(5, np.zeros(2), -1.0, (0.0, 1.0), key=key)
    with pytest.raises(ValueError, match="radius_m"):
        init_uniform_disc(5, np.zeros(2), np.nan, (0.0, 1.0), key=key)
    with pytest.raises(ValueError, match="heading_rad"):
        init_uniform_disc(5, np.zeros(2), 1.0, (1.0, 0.0), key=key)
    with pytest.raises(ValueError, match="heading_rad"):
        init_uniform_disc(5, np.zeros(2), 1.0, (0.0, np.inf), key=key)
    with pytest.raises(ValueError, match="n must"):
        init_uniform_disc(0, np.zeros(2), 1.0, (0.0, 1.0), key=key)


def test_init_global(key):
    spec = GridSpec(np.array([-1.0, 2.0]), 0.5, (6, 5))
    rng = np.random.default_rng(10)
    free = rng.uniform(size=spec.shape) < 0.4
    n = 12000
    state = init_global(n, spec, jnp.asarray(free), key=key)
    _check_uniform_weights(state, n)
    v = np.asarray(to_vector(state.particles))
    cell = np.floor((v[:, :2] - [-1.0, 2.0]) / 0.5).astype(int)
    assert np.all((cell >= 0) & (cell < np.array(spec.shape)))
    assert np.all(free[cell[:, 0], cell[:, 1]])
    assert np.all(np.abs(v[:, 2]) <= np.pi)
    # uniform over the free cells (binomial count per cell) and headings
    k = int(free.sum())
    counts = np.zeros(spec.shape)
    np.add.at(counts, (cell[:, 0], cell[:, 1]), 1)
    p = 1.0 / k
    np.testing.assert_array_less(np.abs(counts[free] - n * p), Z * np.sqrt(n * p * (1 - p)))
    assert abs(v[:, 2].mean()) < Z * (2 * np.pi) / np.sqrt(12 * n)
    # uniform inside a cell: offsets within the cell have mean 1/2
    off = (v[:, :2] - [-1.0, 2.0]) / 0.5 - cell
    np.testing.assert_array_less(np.abs(off.mean(0) - 0.5), Z / np.sqrt(12 * n))


def test_init_global_bad_input(key):
    spec = GridSpec(np.array([0.0, 0.0]), 0.5, (6, 5))
    with pytest.raises(ValueError, match="free"):
        init_global(5, spec, jnp.ones((5, 6), bool), key=key)
    with pytest.raises(ValueError, match="free"):
        init_global(5, spec, jnp.ones((6, 5)), key=key)
    with pytest.raises(ValueError, match="free"):
        init_global(5, spec, jnp.zeros((6, 5), bool), key=key)
    spec3 = GridSpec(np.zeros(3), 0.5, (2, 2, 2))
    with pytest.raises(ValueError, match="free"):
        init_global(5, spec3, jnp.ones((2, 2, 2), bool), key=key)
    with pytest.raises(ValueError, match="n must"):
        init_global(0, spec, jnp.ones((6, 5), bool), key=key)


def test_init_global_jit_and_large_grid(key):
    """Jittable with a traced mask (an all-False traced mask raises at run time), and
    O(particles + cells): 100 000 particles on a 631 x 629 grid (which took 12.8 GB for
    2 000 particles with particles x cells sampling) sample only free cells, uniformly."""
    import equinox as eqx

    spec = GridSpec(np.array([0.0, 0.0]), 0.1, (631, 629))
    rng = np.random.default_rng(4)
    free = rng.uniform(size=spec.shape) < 0.3
    sample = eqx.filter_jit(lambda f, k: init_global(100_000, spec, f, key=k))
    state = sample(jnp.asarray(free), key)
    v = np.asarray(to_vector(state.particles))
    cell = np.floor(v[:, :2] / 0.1).astype(int)
    assert np.all(free[cell[:, 0], cell[:, 1]])
    # first vs second half of the free cells (in flat order): a fair split of the draws
    order = np.flatnonzero(free.ravel())
    rank = np.searchsorted(order, np.ravel_multi_index(cell.T, spec.shape))
    half = np.mean(rank < len(order) // 2)
    assert abs(half - (len(order) // 2) / len(order)) < Z * np.sqrt(0.25 / 100_000)
    with pytest.raises(Exception, match="no True cell"):
        jax.block_until_ready(sample(jnp.zeros(spec.shape, bool), key).log_weights)


# --------------------------------------------------------------------------------------
# The particle filter on a linear-Gaussian toy problem
# --------------------------------------------------------------------------------------


class GaussianPosition(eqx.Module):
    """Measurement z = (x, y) + N(0, s^2 I)."""

    s: jax.Array

    def __call__(self, particles, z):
        d = particles.translation() - z
        return -0.5 * jnp.sum(d * d, axis=-1) / self.s**2


SIG_Q, SIG_Z, SIG_0 = 0.05, 0.1, 0.15  # motion, measurement and prior std (m)
N_TOY, T_TOY = 64, 6  # shared shapes, so the compiled run / step are reused across tests


def _toy(key, n=N_TOY, resampler="systematic", best_fraction=0.1):
    pf = ParticleFilter(
        OdometryMotionModel([SIG_Q, SIG_Q, 0.0]),
        GaussianPosition(jnp.asarray(SIG_Z)),
        resampler=resampler,
        best_fraction=best_fraction,
    )
    state = init_gaussian(n, [0.0, 0.0, 0.0], [SIG_0, SIG_0, 0.0], key=key)
    return pf, state


def _toy_data(T=T_TOY, seed=0):
    rng = np.random.default_rng(seed)
    controls = np.tile([0.2, 0.0, 0.0], (T, 1))
    truth = np.zeros((T, 2))
    x = rng.normal(0.0, SIG_0, 2)
    for t in range(T):
        x = x + controls[t, :2] + rng.normal(0.0, SIG_Q, 2)
        truth[t] = x
    z = truth + rng.normal(0.0, SIG_Z, (T, 2))
    return jnp.asarray(controls), jnp.asarray(z), truth


def _kalman(controls, z):
    """Exact posterior mean / variance per axis (heading fixed at 0: linear Gaussian)."""
    m, p = np.zeros(2), SIG_0**2
    means, variances = [], []
    for t in range(len(z)):
        m, p = m + np.asarray(controls[t, :2]), p + SIG_Q**2
        k = p / (p + SIG_Z**2)
        m, p = m + k * (np.asarray(z[t]) - m), (1 - k) * p
        means.append(m)
        variances.append(p)
    return np.array(means), np.array(variances)


def _one_step(pf, state, control, z, update):
    return pf.step(state, control, z, update)


# one jitted step for every test on the toy problem: must never be traced twice
_STEP = eqx.filter_jit(eqx.debug.assert_max_traces(_one_step, max_traces=1))


def test_step_compiles_once(key):
    pf, state = _toy(key)
    controls, z, _ = _toy_data()
    infos = []
    for t in range(T_TOY):
        state, info = _STEP(pf, state, controls[t], z[t], jnp.asarray(t != 2))
        infos.append(info)
    # a new filter object of the same structure (different measurement noise) reuses it
    pf2 = eqx.tree_at(lambda p: p.measurement.s, pf, jnp.asarray(0.3))
    state, _ = _STEP(pf2, state, controls[0], z[0], jnp.asarray(True))
    assert bool(jnp.all(jnp.isfinite(state.log_weights)))
    # the step really ran: resampling happened at least once
    assert any(bool(i.resampled) for i in infos)


def test_run_equals_python_loop_of_steps(key):
    pf, state0 = _toy(key)
    controls, z, _ = _toy_data()
    updates = jnp.asarray([True, False, True, True, False, True])
    final, infos = pf.run(state0, controls, z, updates)
    state = state0
    for t in range(T_TOY):
        state, info = _STEP(pf, state, controls[t], z[t], updates[t])
        assert tree_allclose(jax.tree.map(lambda x: x[t], infos), info, rtol=1e-10, atol=1e-12)
    assert tree_allclose(final.particles, state.particles, rtol=1e-10, atol=1e-12)
    assert tree_allclose(final.log_weights, state.log_weights, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(
        np.asarray(jax.random.key_data(final.key)), np.asarray(jax.random.key_data(state.key))
    )
    # skipped updates never resample; some update did
    assert not bool(jnp.any(infos.resampled & ~updates))
    assert bool(jnp.any(infos.resampled))


@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_run_vmap_over_keys(key):
    n_runs = 2
    controls, z, _ = _toy_data()
    pf, _ = _toy(key)
    keys = jax.random.split(key, n_runs)
    states = jax.vmap(lambda k: _toy(k)[1])(keys)
    updates = jnp.ones(T_TOY, bool)
    finals, infos = jax.vmap(lambda s: pf.run(s, controls, z, updates))(states)
    assert infos.n_eff.shape == (n_runs, T_TOY)
    params = np.asarray(finals.particles.parameters())
    assert params.shape == (n_runs, N_TOY, 4)
    for i in range(n_runs):
        f_i, info_i = pf.run(jax.tree.map(lambda x: x[i], states), controls, z, updates)
        np.testing.assert_allclose(np.asarray(f_i.particles.parameters()), params[i], atol=1e-12)
        np.testing.assert_allclose(np.asarray(info_i.n_eff), np.asarray(infos.n_eff[i]), rtol=1e-10)
    # distinct keys give distinct runs
    for i in range(n_runs):
        for j in range(i + 1, n_runs):
            assert not np.allclose(params[i], params[j])


def test_updates_false_leaves_weights_unchanged(key):
    pf, state = _toy(key)
    rng = np.random.default_rng(11)
    lw = normalize_log_weights(jnp.asarray(rng.normal(size=N_TOY) * 3))
    state = ParticleState(state.particles, lw, state.key)
    controls, z, _ = _toy_data()
    new, info = _STEP(pf, state, controls[0], z[0], jnp.asarray(False))
    np.testing.assert_allclose(np.asarray(new.log_weights), np.asarray(lw), rtol=1e-13, atol=1e-13)
    assert not bool(info.resampled) and not bool(info.degenerate)
    # the motion update still moved the particles by the control (on average)
    dx = np.asarray(new.particles.translation() - state.particles.translation())
    assert abs(dx[:, 0].mean() - 0.2) < Z * SIG_Q / np.sqrt(N_TOY)
    final, infos = pf.run(state, controls, z, jnp.zeros(T_TOY, bool))
    np.testing.assert_allclose(
        np.asarray(final.log_weights), np.asarray(lw), rtol=1e-12, atol=1e-12
    )
    assert not bool(jnp.any(infos.resampled))


@pytest.mark.parametrize("s", [0.0, np.nan])
def test_degenerate_measurement(key, s):
    """A measurement noise of 0 gives every particle likelihood 0 (log -inf), NaN gives
    NaN log-likelihoods: weights become uniform, no NaN, StepInfo.degenerate is set."""
    pf, state = _toy(key)
    pf = eqx.tree_at(lambda p: p.measurement.s, pf, jnp.asarray(s))
    lw = normalize_log_weights(jnp.asarray(np.random.default_rng(12).normal(size=N_TOY)))
    state = ParticleState(state.particles, lw, state.key)
    controls, z, _ = _toy_data()
    ll = np.asarray(pf.measurement(state.particles, z[0]))
    assert np.all(ll == -np.inf) if s == 0 else np.all(np.isnan(ll))
    new, info = _STEP(pf, state, controls[0], z[0], jnp.asarray(True))
    assert bool(info.degenerate)
    assert np.all(np.isfinite(np.asarray(new.log_weights)))
    np.testing.assert_allclose(np.asarray(new.log_weights), -np.log(N_TOY), rtol=1e-13)
    np.testing.assert_allclose(float(info.n_eff), N_TOY, rtol=1e-12)
    assert np.all(np.isfinite(np.asarray(info.estimate.parameters())))
    assert np.all(np.isfinite(np.asarray(new.particles.parameters())))
    # with updates off the same measurement is not degenerate and weights are kept
    kept, info_off = _STEP(pf, state, controls[0], z[0], jnp.asarray(False))
    assert not bool(info_off.degenerate)
    np.testing.assert_allclose(np.asarray(kept.log_weights), np.asarray(lw), rtol=1e-13)


def test_filter_tracks_kalman_posterior(key):
    """Heading fixed at 0 and Gaussian motion / measurement noise: the exact posterior is
    the Kalman filter's. The PF mean (best_fraction = 1) must match its mean within a
    Monte-Carlo tolerance, and the truth within the posterior std."""
    n, T = 3000, 15
    controls, z, truth = _toy_data(T, seed=0)
    pf, state = _toy(key, n=n, best_fraction=1.0)
    _, infos = pf.run(state, controls, z)
    est = np.asarray(infos.estimate.translation())
    kf_mean, kf_var = _kalman(controls, z)
    kf_std = np.sqrt(kf_var)[:, None]
    # Monte-Carlo error of a weighted mean: std / sqrt(n_eff) with the smallest n_eff so
    # far (the particles descend from that set), x2 for the resampling correlation
    n_eff = np.minimum.accumulate(np.asarray(infos.n_eff))[:, None]
    assert n_eff.min() > 0.1 * n
    mc = 2.0 * kf_std / np.sqrt(n_eff)
    np.testing.assert_array_less(np.abs(est - kf_mean), Z * np.broadcast_to(mc, est.shape))
    np.testing.assert_array_less(
        np.abs(est[-5:] - truth[-5:]), Z * np.broadcast_to(kf_std[-5:], (5, 2))
    )
    # headings never change
    np.testing.assert_array_equal(np.asarray(infos.estimate.rotation().as_radians()), 0.0)
    assert bool(jnp.any(infos.resampled))


def test_particle_filter_bad_arguments():
    m = OdometryMotionModel([0.1, 0.1, 0.1])
    meas = GaussianPosition(jnp.asarray(0.1))
    with pytest.raises(ValueError, match="resampler"):
        ParticleFilter(m, meas, resampler="residual")
    with pytest.raises(ValueError, match="resample_fraction"):
        ParticleFilter(m, meas, resample_fraction=1.5)
    with pytest.raises(ValueError, match="best_fraction"):
        ParticleFilter(m, meas, best_fraction=0.0)


# --------------------------------------------------------------------------------------
# ScanModel on a small synthetic world
# --------------------------------------------------------------------------------------


def _small_world():
    segs = [
        ((0.0, 0.0), (4.0, 0.0)),
        ((4.0, 0.0), (4.0, 3.0)),
        ((4.0, 3.0), (0.0, 3.0)),
        ((0.0, 3.0), (0.0, 0.0)),
        ((2.3, 1.3), (2.7, 1.3)),
        ((2.7, 1.3), (2.7, 1.7)),
        ((2.7, 1.7), (2.3, 1.7)),
        ((2.3, 1.7), (2.3, 1.3)),
    ]
    return OfficeWorld(
        segments=np.asarray(segs, np.float64),
        bounds=np.array([[0.0, 0.0], [4.0, 3.0]]),
        waypoints=np.array([[1.0, 1.0], [3.0, 2.5]]),
        seed=0,
    )


R_MIN, R_MAX = 0.15, 3.5
AZ = np.linspace(-np.pi, np.pi, 24, endpoint=False)
SPEC = GridSpec(np.array([-0.5, -0.5]), 0.25, (20, 16))


@pytest.fixture(scope="module")
def scan_setup():
    world = _small_world()
    map_poses = np.array([[1.0, 1.0, 0.0], [1.2, 2.2, 1.0], [3.3, 0.7, 2.0], [3.4, 2.4, -2.5]])
    scans = simulate_scans(world, map_poses, AZ, max_range_m=R_MAX, noise_sigma_m=0.01, seed=1)
    rays = from_scan(jaxlie.SE2.from_xy_theta(*map_poses.T), AZ, scans, R_MIN, R_MAX)
    stats = accumulate(SPEC, rays)
    truth = np.array([1.5, 1.4, 0.3])
    ranges = simulate_scans(world, truth[None], AZ, max_range_m=R_MAX, noise_sigma_m=0.01, seed=2)[
        0
    ]
    ranges[3] = 0.05  # one SUB reading
    rng = np.random.default_rng(13)
    v = truth + rng.normal(0.0, [0.3, 0.3, 0.2], (9, 3))
    v[0] = truth
    return {
        "stats": stats,
        "ranges": ranges,
        "particles": from_vector(v),
        "poses": v,
    }


@pytest.mark.parametrize(("kind", "floor"), [("decay", -6.0), ("decay", None)])
def test_scan_model_equals_sum_of_differentiable_model(scan_setup, kind, floor):
    stats = scan_setup["stats"]
    if kind == "decay":
        m, ref_fn = decay_rate_map(stats), decay_rate_log_likelihood
    elif kind == "reflection":
        m, ref_fn = reflection_map(stats), reflection_log_likelihood
    else:
        m, ref_fn = endpoint_map(stats, sigma_m=0.2), endpoint_log_likelihood
    model = ScanModel(m, AZ, R_MIN, R_MAX, ray_floor=floor, endpoint_normalized=True, chunk_size=50)
    ranges = scan_setup["ranges"]
    got = np.asarray(model(scan_setup["particles"], jnp.asarray(ranges)))
    n = len(scan_setup["poses"])
    rays = from_scan(
        scan_setup["particles"], AZ, np.broadcast_to(ranges, (n, AZ.size)), R_MIN, R_MAX
    )
    ll = np.asarray(ref_fn(m, rays, max_cells=max_cells_for(SPEC)))  # [n b]
    assert ll.shape == (n, AZ.size)
    ref = (ll if floor is None else np.maximum(ll, floor)).sum(axis=1)
    assert got.shape == (n,)
    fin = np.isfinite(ref)
    np.testing.assert_array_equal(got[~fin], ref[~fin])
    np.testing.assert_allclose(got[fin], ref[fin], rtol=1e-9, atol=1e-9)
    if floor is not None:
        assert np.all(fin)
        assert np.any(ll < floor)  # the floor was active
        assert np.argmax(got) == 0  # the true pose is the most likely one
    # per-ray values too
    per_ray = np.asarray(model.ray_log_likelihoods(scan_setup["particles"], jnp.asarray(ranges)))
    ref_ray = ll if floor is None else np.maximum(ll, floor)
    fin = np.isfinite(ref_ray)
    np.testing.assert_array_equal(per_ray[~fin], ref_ray[~fin])
    np.testing.assert_allclose(per_ray[fin], ref_ray[fin], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("floor", [None, -4.0])
def test_scan_model_likelihood_field_vs_numpy(scan_setup, floor):
    m = endpoint_map(scan_setup["stats"], sigma_m=0.2, z_hit=0.85, z_rand=0.15, p_out=0.07)
    model = ScanModel(m, AZ, R_MIN, R_MAX, ray_floor=floor)
    ranges = scan_setup["ranges"]
    got = np.asarray(eqx.filter_jit(model)(scan_setup["particles"], jnp.asarray(ranges)))
    dist = np.asarray(m.distances)
    origin, res = np.array([-0.5, -0.5]), 0.25
    sigma = 0.2
    ref = []
    for x, y, th in scan_setup["poses"]:
        total = 0.0
        for a, r in zip(AZ, ranges):
            if r < R_MIN or r >= R_MAX:
                ll = np.log(0.07)
            else:
                p = np.array([x + r * np.cos(th + a), y + r * np.sin(th + a)])
                c = np.floor((p - origin) / res).astype(int)
                f = 0.15 / R_MAX
                if np.all(c >= 0) and np.all(c < np.array(SPEC.shape)):
                    g = np.exp(-0.5 * (dist[c[0], c[1]] / sigma) ** 2) / (
                        np.sqrt(2 * np.pi) * sigma
                    )
                    f += 0.85 * g
                ll = np.log(1 - 0.07) + np.log(f)
            total += ll if floor is None else max(ll, floor)
        ref.append(total)
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-10)
    assert np.argmax(got) == 0


def test_scan_model_bad_inputs(scan_setup):
    m = decay_rate_map(scan_setup["stats"])
    model = ScanModel(m, AZ, R_MIN, R_MAX)
    with pytest.raises(ValueError, match="ranges must have shape"):
        model(scan_setup["particles"], jnp.ones(5))
    with pytest.raises(ValueError, match="ranges must have shape"):
        model(scan_setup["particles"], jnp.ones((2, 24)))
    with pytest.raises(ValueError, match="particles"):
        model(jaxlie.SE3.identity(), jnp.ones(24))
    with pytest.raises(ValueError, match="map must be a grid model"):
        ScanModel(scan_setup["stats"], AZ, R_MIN, R_MAX)
    with pytest.raises(ValueError, match="map must be a grid model"):
        ScanModel(np.zeros(SPEC.shape), AZ, R_MIN, R_MAX)
    for lo, hi in ((1.0, 1.0), (2.0, 1.0), (-0.1, 1.0), (np.nan, 1.0)):
        with pytest.raises(ValueError, match="r_min"):
            ScanModel(m, AZ, lo, hi)
    with pytest.raises(ValueError, match="azimuths"):
        ScanModel(m, np.zeros((2, 3)), R_MIN, R_MAX)
    with pytest.raises(ValueError, match="azimuths"):
        ScanModel(m, np.array([0.0, np.nan]), R_MIN, R_MAX)
    with pytest.raises(ValueError, match="ray_floor"):
        ScanModel(m, AZ, R_MIN, R_MAX, ray_floor=-np.inf)
    spec3 = GridSpec(np.zeros(3), 0.5, (2, 2, 2))
    m3 = EndpointMap(
        spec3,
        jnp.zeros((2, 2, 2)),
        jnp.ones((2, 2, 2), bool),
        jnp.asarray(0.2),
        jnp.asarray(0.9),
        jnp.asarray(0.1),
        jnp.asarray(0.05),
    )
    with pytest.raises(ValueError, match="2-D"):
        ScanModel(m3, AZ, R_MIN, R_MAX)
