"""The grid-model protocol (``lidarjax.maps.AbstractGridModel``): a new model is one class,
and every driver (differentiable walk, fast fold in JAX and native, pose-batched scans, the
particle filter's ScanModel) evaluates it; checked against a closed form."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from jaxtyping import Array, Float

from lidarjax import localization as loc
from lidarjax import maps
from lidarjax.rays import HIT, SUB, RayBatch, from_scan
from lidarjax.raytrace import CellTerm, GridSpec, GridStats, RayFold
from lidarjax.raytrace._native import available as native_available
from lidarjax.sensor_models import (
    AbstractGridModel,
    GridWalk,
    batch_log_likelihood,
    grid_log_likelihood,
    ray_log_likelihoods_at_poses,
)
from lidarjax.testing import finite_difference


class Transmittance(AbstractGridModel):
    """A toy model in one class: every reading has log-likelihood ``-sum_i mu_i d_i`` along
    its model length, plus ``log mu_k`` of the end cell for HIT rays (an exponential
    range model with a per-cell rate, like the decay-rate model) and ``log 0.5`` extra for
    SUB rays."""

    spec: GridSpec
    mu: Float[Array, "*shape"]

    def cell_term(self, flat: RayBatch) -> CellTerm:
        return CellTerm.linear(slope=self.mu)

    def finish(self, fold: RayFold, flat: RayBatch, walk: GridWalk) -> Float[Array, " n"]:
        mu_last = self.mu[tuple(jnp.moveaxis(fold.last_cell, -1, 0))]
        depth = fold.body + jnp.where(fold.any_valid, mu_last * fold.last_len, 0.0)
        extra = jnp.where(flat.kind == HIT, jnp.log(mu_last), 0.0)
        return -depth + extra + jnp.where(flat.kind == SUB, jnp.log(0.5), 0.0)


MU = 0.3  # 1/m, the same in every cell: the closed form is -MU * length (+ log terms)


def _setup():
    spec = GridSpec(origin=jnp.array([-10.0, -10.0]), resolution=0.5, shape=(40, 40))
    model = Transmittance(spec, jnp.full(spec.shape, MU))
    az = jnp.linspace(-np.pi, np.pi, 24, endpoint=False)
    ranges = jnp.asarray(np.random.default_rng(0).uniform(0.2, 6.0, 24)).at[:3].set(0.05)
    ranges = ranges.at[3:6].set(50.0)  # SUP
    return spec, model, az, ranges


def _closed_form(rays: RayBatch) -> np.ndarray:
    kind = np.asarray(rays.kind)
    length = np.asarray(rays.model_lengths())
    return (
        -MU * length
        + np.where(kind == HIT, np.log(MU), 0.0)
        + np.where(kind == SUB, np.log(0.5), 0.0)
    )


def test_a_model_in_one_class_runs_through_every_driver():
    spec, model, az, ranges = _setup()
    poses = jaxlie.SE2.from_xy_theta(
        jnp.array([0.0, 1.0, -2.0]), jnp.array([0.0, 0.5, 1.5]), jnp.array([0.0, 1.0, -2.5])
    )
    n = 3
    rays = from_scan(poses, az, jnp.broadcast_to(ranges, (n, az.shape[0])), 0.1, 8.0)
    assert set(np.unique(np.asarray(rays.kind))) == {0, 1, 2}  # all three kinds
    want = _closed_form(rays)
    np.testing.assert_allclose(grid_log_likelihood(model, rays), want, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(
        batch_log_likelihood(model, rays, backend="jax"), want, rtol=1e-12, atol=1e-12
    )
    if native_available():
        np.testing.assert_allclose(
            batch_log_likelihood(model, rays, backend="native"), want, rtol=1e-12, atol=1e-12
        )
    at_poses = ray_log_likelihoods_at_poses(model, az, ranges, poses, r_min=0.1, r_max=8.0)
    np.testing.assert_allclose(at_poses, want, rtol=1e-12, atol=1e-12)
    scan = loc.ScanModel(model, az, 0.1, 8.0, backend="jax")
    np.testing.assert_allclose(scan(poses, ranges), want.sum(-1), rtol=1e-12)


def test_a_model_in_one_class_is_differentiable_in_the_pose():
    spec, model, az, ranges = _setup()

    def total(xyt):
        pose = jaxlie.SE2.from_xy_theta(xyt[0], xyt[1], xyt[2])
        return jnp.sum(grid_log_likelihood(model, from_scan(pose, az, ranges, 0.1, 8.0)))

    x0 = jnp.array([0.3, -0.2, 0.4])
    g = jax.grad(total)(x0)
    assert np.all(np.isfinite(np.asarray(g)))
    # constant rate: only SUB/SUP/HIT lengths matter and they do not depend on the pose
    np.testing.assert_allclose(g, finite_difference(total, x0), atol=1e-6)
    np.testing.assert_allclose(g, 0.0, atol=1e-9)


def test_grid_model_gradient_in_the_map_matches_finite_differences():
    spec, model, az, ranges = _setup()
    rays = from_scan(jaxlie.SE2.from_xy_theta(0.2, 0.1, 0.3), az, ranges, 0.1, 8.0)
    rng = np.random.default_rng(3)
    mu0 = jnp.asarray(rng.uniform(0.1, 0.5, spec.shape))

    def total(mu):
        return jnp.sum(grid_log_likelihood(Transmittance(spec, mu), rays))

    g = np.asarray(jax.grad(total)(mu0))
    # a few cells by central differences
    for idx in [(20, 20), (21, 20), (20, 23), (25, 25)]:
        e = jnp.zeros(spec.shape).at[idx].set(1e-6)
        fd = (total(mu0 + e) - total(mu0 - e)) / 2e-6
        np.testing.assert_allclose(g[idx], fd, rtol=1e-6, atol=1e-8)


def test_the_five_models_implement_the_protocol():
    spec = GridSpec(origin=jnp.zeros(2), resolution=1.0, shape=(4, 4))
    hits = jnp.arange(16, dtype=jnp.int32).reshape(spec.shape) % 3
    misses = jnp.arange(16, dtype=jnp.int32).reshape(spec.shape) % 4 + 1
    stats = GridStats(spec=spec, hits=hits, misses=misses, lengths=0.7 * (hits + misses))
    models = [
        maps.decay_rate_map(stats),
        maps.reflection_map(stats),
        maps.endpoint_map(stats, sigma_m=0.5),
        maps.gamma_posterior(stats),
        maps.beta_posterior(stats),
    ]
    for m in models:
        assert isinstance(m, maps.AbstractGridModel), type(m).__name__
    rays = from_scan(jaxlie.SE2.from_xy_theta(2.0, 2.0, 0.0), jnp.zeros(1), jnp.ones(1), 0, 9)
    for m in models:  # the public per-model functions are the generic walk
        assert np.isfinite(np.asarray(grid_log_likelihood(m, rays))).all()


def test_not_a_grid_model_is_refused_by_every_driver():
    _, _, az, ranges = _setup()
    rays = from_scan(jaxlie.SE2.identity(), az, ranges, 0.1, 8.0)

    class NotAModel(eqx.Module):
        spec: GridSpec

    bad = NotAModel(GridSpec(origin=jnp.zeros(2), resolution=1.0, shape=(2, 2)))
    with pytest.raises(ValueError, match="map must be a grid model"):
        grid_log_likelihood(bad, rays)
    with pytest.raises(ValueError, match="model must be a grid model"):
        batch_log_likelihood(bad, rays)
    with pytest.raises(ValueError, match="map must be a grid model"):
        loc.ScanModel(bad, az, 0.1, 8.0)
    with pytest.raises(TypeError):  # abstract methods missing: cannot be instantiated

        class Half(AbstractGridModel):
            spec: GridSpec

            def cell_term(self, flat):
                return CellTerm.linear(slope=jnp.zeros(self.spec.shape))

        Half(GridSpec(origin=jnp.zeros(2), resolution=1.0, shape=(2, 2)))
