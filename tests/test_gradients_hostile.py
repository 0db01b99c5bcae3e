"""Pose gradients of every grid model at degenerate inputs (issue #19, "Gradients and the
filter"): the convention is that gradients are finite wherever the log-likelihood is
(and never NaN where it is -inf), and equal central finite differences (float64) where
the function is smooth.

Models: decay rate (Eqs. 7.13, 7.16), reflection (Eqs. 7.23, 7.32), endpoint, and the
full posteriors Beta (Eq. 8.22) and Gamma (decay-rate analogue, section 8.4.5), the
latter also with the improper uniform prior. Maps come from simulated scans of a small
room, on a grid that extends past the room (cells with zero statistics).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from test_localization import _small_world

from lidarjax.maps import (
    BetaPosteriorMap,
    DecayRateMap,
    EndpointMap,
    GammaPosteriorMap,
    ReflectionMap,
    beta_posterior,
    decay_rate_map,
    endpoint_map,
    gamma_posterior,
    posterior_log_likelihood,
    reflection_map,
)
from lidarjax.rays import HIT, SUB, SUP, RayBatch, from_scan
from lidarjax.raytrace import GridSpec, GridStats, accumulate
from lidarjax.sensor_models import (
    batch_log_likelihood,
    decay_rate_log_likelihood,
    endpoint_log_likelihood,
    reflection_log_likelihood,
)
from lidarjax.sim import OfficeWorld, simulate_scans
from lidarjax.testing import finite_difference

R_MIN, R_MAX = 0.15, 3.5
# cell edges at -0.5 + 0.25 k; the room is [0, 4] x [0, 3], the grid reaches x = 5.5, so
# the cells right of x ~ 4.25 were never visited (zero statistics)
SPEC = GridSpec(np.array([-0.5, -0.5]), 0.25, (24, 16))
AZ8 = np.linspace(-np.pi, np.pi, 8, endpoint=False) + 0.1
TRUTH = np.array([1.5, 1.4, 0.3])  # x = 1.5 lies on a cell edge

FNS = {
    DecayRateMap: decay_rate_log_likelihood,
    ReflectionMap: reflection_log_likelihood,
    EndpointMap: endpoint_log_likelihood,
    BetaPosteriorMap: posterior_log_likelihood,
    GammaPosteriorMap: posterior_log_likelihood,
}


def _world() -> OfficeWorld:
    return _small_world()  # 4 m x 3 m room with a 0.4 m pillar


def _stats() -> GridStats:
    az = np.linspace(-np.pi, np.pi, 24, endpoint=False)
    poses = np.array([[1.0, 1.0, 0.0], [1.2, 2.2, 1.0], [3.3, 0.7, 2.0], [3.4, 2.4, -2.5]])
    scans = simulate_scans(_world(), poses, az, max_range_m=R_MAX, noise_sigma_m=0.01, seed=1)
    rays = from_scan(jaxlie.SE2.from_xy_theta(*poses.T), az, scans, R_MIN, R_MAX)
    return accumulate(SPEC, rays)


@pytest.fixture(scope="module")
def maps():
    st = _stats()
    assert np.any(np.asarray(st.hits + st.misses) == 0)  # some cells have zero statistics
    return {
        "decay": decay_rate_map(st),
        "reflection": reflection_map(st),
        "endpoint": endpoint_map(st, sigma_m=0.1),
        "beta": beta_posterior(st),
        "gamma": gamma_posterior(st),
        "gamma_uniform": gamma_posterior(st, prior="uniform"),
    }


def _rays(pose, ranges, kinds, r_min, r_max) -> RayBatch:
    T = jaxlie.SE2.from_xy_theta(pose[0], pose[1], pose[2])
    r = from_scan(T, AZ8, ranges, 0.0, r_max)
    return RayBatch(r.origins, r.directions, r.ranges, kinds, r_min, r_max)


def _per_ray(model, pose, ranges, kinds, r_min, r_max):
    return FNS[type(model)](model, _rays(pose, ranges, kinds, r_min, r_max))


_VALUE = eqx.filter_jit(_per_ray)
_JAC_REV = eqx.filter_jit(jax.jacrev(_per_ray, argnums=1))
_JAC_FWD = eqx.filter_jit(jax.jacfwd(_per_ray, argnums=1))


def _truth_ranges() -> np.ndarray:
    z = simulate_scans(_world(), TRUTH[None], AZ8 - 0.0, max_range_m=R_MAX, seed=2)[0]
    return z


def _kinds(ranges, r_min=R_MIN, r_max=R_MAX):
    return np.where(ranges < r_min, SUB, np.where(ranges >= r_max, SUP, HIT)).astype(np.int32)


def _case(name: str):
    """(pose [3], ranges [8], kinds [8], r_min, r_max) of a degenerate scan."""
    if name == "true_pose":  # a real scan at its own pose; the sensor sits on a cell edge
        z = _truth_ranges()
        z[3] = 0.05  # one SUB reading
        return TRUTH, z, _kinds(z), R_MIN, R_MAX
    if name == "ends_on_cell_edges":  # sensor on a cell corner, end points on cell edges
        pose = np.array([1.0, 1.5, -0.1])  # with AZ8 + 0.1: beams at multiples of 45 deg
        diag = np.sqrt(2.0)
        z = np.array([0.5, 0.25 * diag, 0.75, 0.5 * diag, 1.0, diag, 0.25, 0.75 * diag])
        return pose, z, _kinds(z), R_MIN, R_MAX
    if name == "zero_length":  # SUB with r_min = 0 (impossible) and zero-range HITs
        z = np.zeros(8)
        kinds = np.array([SUB, HIT] * 4, np.int32)
        return np.array([1.37, 1.12, 0.2]), z, kinds, 0.0, R_MAX
    if name == "all_sup":
        z = np.full(8, R_MAX)
        return np.array([1.37, 1.12, 0.2]), z, _kinds(z), R_MIN, R_MAX
    if name == "leaving_grid":  # near the right edge: HITs beyond the grid, SUP leaving it
        z = np.array([1.0, 0.7, 2.0, 3.5, 3.0, 0.3, 0.9, 3.5])
        return np.array([5.31, 2.07, 0.1]), z, _kinds(z), R_MIN, R_MAX
    if name == "zero_statistics":  # short rays in never-visited cells
        z = np.array([0.3, 0.4, 0.35, 0.2, 0.3, 0.25, 0.45, 0.33])
        return np.array([4.93, 1.04, 0.2]), z, _kinds(z), R_MIN, R_MAX
    raise ValueError(name)


def _args(name):
    pose, z, kinds, r_min, r_max = _case(name)
    return (
        jnp.asarray(pose, jnp.float64),
        jnp.asarray(z, jnp.float64),
        jnp.asarray(kinds, jnp.int32),
        jnp.asarray(r_min, jnp.float64),
        jnp.asarray(r_max, jnp.float64),
    )


MODELS = ["decay", "reflection", "endpoint", "beta", "gamma", "gamma_uniform"]
CASES = [
    "true_pose",
    "ends_on_cell_edges",
    "zero_length",
    "all_sup",
    "leaving_grid",
    "zero_statistics",
]


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("model", MODELS)
@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_pose_gradient_finite_where_value_finite(maps, model, case):
    m = maps[model]
    pose, *rest = _args(case)
    value = np.asarray(_VALUE(m, pose, *rest))
    j_rev = np.asarray(_JAC_REV(m, pose, *rest))
    j_fwd = np.asarray(_JAC_FWD(m, pose, *rest))
    assert not np.any(np.isnan(value)), value
    assert not np.any(np.isnan(j_rev)), j_rev
    assert not np.any(np.isnan(j_fwd)), j_fwd
    finite = np.isfinite(value)
    assert np.all(np.isfinite(j_rev[finite])) and np.all(np.isfinite(j_fwd[finite]))
    np.testing.assert_allclose(j_rev[finite], j_fwd[finite], rtol=1e-10, atol=1e-10)
    # the forward-only particle-filter path gives the same values
    rays = _rays(pose, *rest)
    np.testing.assert_allclose(
        np.asarray(batch_log_likelihood(m, rays, backend="jax")), value, rtol=1e-9, atol=1e-12
    )


# Where the function is smooth: poses off every cell edge (0.25 m grid), all end points
# away from cell edges. Same scans as above (mixed kinds, all SUP, leaving the grid, cells
# with zero statistics), summed over the rays.
SMOOTH = {
    "true_pose": np.array([1.513, 1.381, 0.307]),
    "all_sup": np.array([1.37, 1.12, 0.2]),
    "leaving_grid": np.array([5.31, 2.07, 0.1]),
    "zero_statistics": np.array([4.93, 1.04, 0.2]),
}


@pytest.mark.parametrize("case", list(SMOOTH))
@pytest.mark.parametrize("model", MODELS)
def test_pose_gradient_matches_finite_differences(maps, model, case):
    m = maps[model]
    _, *rest = _args(case)
    pose = jnp.asarray(SMOOTH[case])

    def total(p):
        return jnp.sum(_VALUE(m, p, *rest))

    value = float(total(pose))
    g = np.asarray(jnp.sum(_JAC_REV(m, pose, *rest), axis=0))
    assert not np.any(np.isnan(g))
    if not np.isfinite(value):
        return  # e.g. the improper prior on unvisited cells: -inf, gradient checked above
    fd = finite_difference(total, pose, eps=1e-6)
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-6)


def test_gamma_posterior_true_pose_gradient_float32():
    """The issue's report: NaN pose gradients of the Gamma posterior at the true pose in
    float32 too (every ray)."""
    st = _stats()
    z = _truth_ranges()
    with jax.enable_x64(False):
        spec32 = GridSpec(np.asarray(SPEC.origin, np.float32), 0.25, SPEC.shape)
        st32 = GridStats(spec32, st.hits, st.misses, jnp.asarray(st.lengths, jnp.float32))
        post = gamma_posterior(st32)
        assert post.a.dtype == jnp.float32

        def total(p):
            T = jaxlie.SE2.from_xy_theta(p[0], p[1], p[2])
            rays = from_scan(T, AZ8, jnp.asarray(z, jnp.float32), R_MIN, R_MAX)
            return jnp.sum(posterior_log_likelihood(post, rays))

        pose = jnp.asarray(TRUTH, jnp.float32)
        value, g = jax.jit(jax.value_and_grad(total))(pose)
        assert g.dtype == jnp.float32
        assert np.isfinite(float(value))
        assert np.all(np.isfinite(np.asarray(g))), g


# --------------------------------------------------------------------------------------
# Infinite decay rates / statistics: a clear error instead of NaN values
# --------------------------------------------------------------------------------------


def test_infinite_statistics_in_posterior_maps_raise():
    spec = GridSpec(np.array([0.0, 0.0]), 1.0, (3, 3))
    h, ones = jnp.zeros((3, 3)), jnp.ones((3, 3))
    inf_len = ones.at[1, 0].set(jnp.inf)
    with pytest.raises(ValueError, match="stats.lengths"):
        gamma_posterior(GridStats(spec, h, h, inf_len), alpha=1.0, beta=1.0)
    with pytest.raises(ValueError, match="stats.hits"):
        beta_posterior(GridStats(spec, h.at[0, 0].set(jnp.nan), h, ones))
    with pytest.raises(ValueError, match="lengths"):
        GammaPosteriorMap(spec, h, inf_len, jnp.asarray(1.0), jnp.asarray(1.0))
    with pytest.raises(ValueError, match="alpha"):
        GammaPosteriorMap(spec, h, ones, jnp.asarray(jnp.inf), jnp.asarray(1.0))
    with pytest.raises(ValueError, match="misses"):
        BetaPosteriorMap(spec, h, ones.at[2, 2].set(-1.0), jnp.asarray(1.0), jnp.asarray(1.0))

    rays = RayBatch(
        jnp.array([[0.5, 0.5], [0.5, 0.5]]),
        jnp.array([[1.0, 0.0], [1.0, 0.0]]),
        jnp.array([2.5, 20.0]),
        jnp.array([HIT, SUP]),
        jnp.asarray(0.1),
        jnp.asarray(10.0),
    )

    # traced: the likelihood raises at run time instead of returning NaN
    @eqx.filter_jit
    def traced_posterior(lengths):
        return posterior_log_likelihood(
            GammaPosteriorMap(spec, h, lengths, jnp.asarray(1.0), jnp.asarray(1.0)), rays
        )

    @eqx.filter_jit
    def traced_decay(rates):
        return decay_rate_log_likelihood(DecayRateMap(spec, rates, jnp.asarray(0.1)), rays)

    assert np.all(np.isfinite(np.asarray(traced_posterior(ones))))
    assert np.all(np.isfinite(np.asarray(traced_decay(ones))))
    for fn, bad in [(traced_posterior, inf_len), (traced_decay, ones.at[1, 0].set(jnp.inf))]:
        with pytest.raises(Exception, match="finite"):
            jax.block_until_ready(fn(bad))
