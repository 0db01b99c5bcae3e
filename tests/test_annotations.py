"""jaxtyping's runtime checks on the public entry points: every call below runs under
``jaxtyped(typechecker=beartype)``, so the shapes and dtypes the signatures annotate
(``Float[Array, "*batch"]``, ``[p b]`` …) are enforced for arguments and return values,
with the dimension names bound consistently within one call.

Only valid inputs are checked here: bad input is the library's own business (a
``ValueError`` naming the argument, tested in the ``*_hostile`` files), which a type
checker running first would pre-empt.
"""

from __future__ import annotations

import inspect

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from beartype import beartype
from jaxtyping import Array, Float, jaxtyped

from lidarjax import features, maps, rays, raytrace, sensor_models
from lidarjax import localization as loc


def checked(fn):
    """``fn`` with jaxtyping + beartype checks (jit wrappers are unwrapped first)."""
    inner = inspect.unwrap(fn)
    if not hasattr(inner, "__globals__"):
        inner = getattr(fn, "__wrapped__", inner)
    assert hasattr(inner, "__globals__"), f"cannot check {fn!r}"
    return jaxtyped(typechecker=beartype)(inner)


@pytest.fixture(scope="module")
def scene():
    spec = raytrace.GridSpec(jnp.array([-5.0, -5.0]), 0.25, (40, 40))
    az = jnp.linspace(-3.0, 3.0, 30)
    ranges = jnp.asarray(np.random.default_rng(0).uniform(0.1, 6.0, 30))
    poses = jaxlie.SE2.from_xy_theta(jnp.zeros(4), jnp.linspace(-1, 1, 4), jnp.linspace(0, 1, 4))
    batch = checked(rays.from_scan)(poses, az, jnp.broadcast_to(ranges, (4, 30)), 0.2, 5.0)
    stats = checked(raytrace.accumulate)(spec, batch)
    return spec, az, ranges, batch, stats


def test_rays_and_statistics(scene):
    spec, az, ranges, batch, stats = scene
    assert batch.shape == (4, 30)
    flat = batch.flatten()
    assert checked(batch.model_lengths)().shape == (4, 30)
    assert checked(batch.mapping_lengths)().shape == (4, 30)
    tr = checked(raytrace.traverse)(spec, flat.origins[0], flat.directions[0], flat.ranges[0], 60)
    assert tr.cells.shape == (60, 2)
    assert stats.hits.shape == spec.shape


def test_grid_models_every_driver(scene):
    spec, az, ranges, batch, stats = scene
    models = {
        "dec": checked(maps.decay_rate_map)(stats),
        "ref": checked(maps.reflection_map)(stats),
        "end": checked(maps.endpoint_map)(stats, sigma_m=0.3),
        "gamma": checked(maps.gamma_posterior)(stats),
        "beta": checked(maps.beta_posterior)(stats),
    }
    for name, m in models.items():
        a = checked(sensor_models.grid_log_likelihood)(m, batch)
        b = sensor_models.batch_log_likelihood(m, batch, backend="jax")
        assert a.shape == b.shape == (4, 30), name
    poses = jnp.array([[0.0, 0.0, 0.1], [0.2, -0.1, 0.3]])
    for fn in (sensor_models.log_likelihood_at_poses, sensor_models.ray_log_likelihoods_at_poses):
        out = checked(fn)(models["dec"], az, ranges, poses, r_min=0.2, r_max=5.0)
        assert out.shape[0] == 2
    for fn, m in (
        (sensor_models.decay_rate_log_likelihood, models["dec"]),
        (sensor_models.reflection_log_likelihood, models["ref"]),
        (sensor_models.endpoint_log_likelihood, models["end"]),
        (sensor_models.likelihood_field_log_likelihood, models["end"]),
        (sensor_models.posterior_log_likelihood, models["gamma"]),
    ):
        assert checked(fn)(m, batch).shape == (4, 30)
    assert checked(maps.occupancy)(models["beta"], 0.2).shape == spec.shape


def test_particle_filter_pieces(scene):
    _, az, ranges, batch, stats = scene
    logw = jnp.log(jnp.array([0.1, 0.2, 0.3, 0.4]))
    assert checked(loc.normalize_log_weights)(logw).shape == (4,)
    assert checked(loc.effective_sample_size)(logw).shape == ()
    idx = checked(loc.systematic_resample)(logw, key=jax.random.key(0))
    assert idx.shape == (4,)
    scan = loc.ScanModel(maps.decay_rate_map(stats), az, 0.2, 5.0, backend="jax")
    particles = jaxlie.SE2.from_xy_theta(jnp.zeros(3), jnp.zeros(3), jnp.zeros(3))
    assert checked(scan.ray_log_likelihoods)(particles, ranges).shape == (3, 30)


def test_polylines(scene):
    _, az, ranges, _, _ = scene
    scan = rays.from_scan(jaxlie.SE2.identity(), az, ranges, 0.0, 10.0)
    ext = checked(features.extract_polylines)(scan, max_vertices=8)
    assert ext.map.vertices.shape[-1] == 2
    assert checked(ext.map.expected_ranges)(scan).shape == (30,)


def test_the_checks_are_live():
    """A wrong return shape under ``checked`` fails (so the tests above can fail)."""

    def shorter(x: Float[Array, " n"]) -> Float[Array, " n"]:
        return x[:-1]

    with pytest.raises(Exception, match="shorter"):
        checked(shorter)(jnp.ones(3))
    # and the library's own (string) annotations are resolved: an int array is no Float
    with pytest.raises(Exception, match="log_weights"):
        checked(loc.normalize_log_weights)(jnp.ones(4, jnp.int32))
