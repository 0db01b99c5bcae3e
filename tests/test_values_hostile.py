"""Impossible values are rejected with an error naming the argument (issue "Reliability",
class "Values"): grid geometry, unnormalised poses and map parameters, eagerly and, where
the value can be traced, under ``jit``."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

import lidarjax.rays as lr
from lidarjax.maps import DecayRateMap, EndpointMap, ReflectionMap
from lidarjax.raytrace import GridSpec

# ------------------------------------------------------------------ GridSpec


@pytest.mark.parametrize(
    "origin, resolution, shape, match",
    [
        ([np.nan, 0.0], 0.1, (4, 4), "origin must be finite"),
        ([0.0, np.inf], 0.1, (4, 4), "origin must be finite"),
        ([0.0, 0.0], 0.1, (4.7, 4), "shape entries must be ints"),
        ([0.0, 0.0], 0.1, (4.0, 4), "shape entries must be ints"),
        ([0.0, 0.0], 0.1, (True, 4), "shape entries must be ints"),
        ([0.0, 0.0], 0.1, (0, 4), "shape must be 2 or 3 positive ints"),
        ([0.0, 0.0], 0.0, (4, 4), "resolution must be a positive finite"),
        ([0.0, 0.0], np.nan, (4, 4), "resolution must be a positive finite"),
        ([0.0, 0.0], [0.1, 0.1], (4, 4), "resolution must be a scalar"),
    ],
)
def test_gridspec_rejects(origin, resolution, shape, match):
    with pytest.raises(ValueError, match=match):
        GridSpec(origin, resolution, shape)


def test_gridspec_accepts_numpy_ints():
    spec = GridSpec([0.0, 0.0], 0.1, (np.int64(4), np.int32(5)))
    assert spec.shape == (4, 5) and all(type(s) is int for s in spec.shape)


@pytest.mark.parametrize("res", [0.0, -0.1, np.nan, np.inf, "abc"])
def test_covering_and_from_bounds_name_the_resolution(res):
    pts = np.array([[0.0, 0.0], [1.0, 2.0]])
    with pytest.raises(ValueError, match="resolution must be a positive finite"):
        GridSpec.covering(pts, res)
    with pytest.raises(ValueError, match="resolution must be a positive finite"):
        GridSpec.from_bounds([0.0, 0.0], [1.0, 1.0], res)


@pytest.mark.parametrize("margin", [-1.0, np.nan, np.inf])
def test_covering_rejects_bad_margin(margin):
    with pytest.raises(ValueError, match="margin must be a finite number >= 0"):
        GridSpec.covering(np.zeros((2, 2)), 0.1, margin=margin)


def test_from_bounds_rejects_non_finite():
    with pytest.raises(ValueError, match="must be finite"):
        GridSpec.from_bounds([0.0, np.nan], [1.0, 1.0], 0.1)


@pytest.mark.parametrize("res", [0.0, -0.5, np.nan])
def test_gridspec_traced_resolution_checked_under_jit(res):
    @jax.jit
    def cells(r):
        spec = GridSpec(jnp.zeros(2), r, (4, 4))
        return spec.cell_of(jnp.array([0.25, 0.25]))

    np.testing.assert_array_equal(cells(0.1), [2, 2])  # a valid traced value works
    with pytest.raises(Exception, match="resolution must be a positive finite number"):
        jax.block_until_ready(cells(res))


def test_gridspec_traced_origin_checked_under_jit():
    @jax.jit
    def upper(o):
        return GridSpec(o, 0.1, (4, 4)).upper

    np.testing.assert_allclose(upper(jnp.zeros(2)), [0.4, 0.4], rtol=1e-6)
    with pytest.raises(Exception, match="origin must be finite"):
        jax.block_until_ready(upper(jnp.array([0.0, jnp.nan])))


# ------------------------------------------------------------------ poses


AZ = jnp.linspace(-1.0, 1.0, 5)
RANGES = jnp.ones(5)


@pytest.mark.parametrize("scale", [2.0, 0.5, 0.0])
def test_unnormalised_se2_rejected(scale):
    T = jaxlie.SE2(jnp.array([scale, 0.0, 1.0, 2.0]))
    with pytest.raises(ValueError, match="unnormalised rotation"):
        lr.from_scan(T, AZ, RANGES, 0.0, 10.0)


def test_unnormalised_se2_rejected_under_jit():
    f = jax.jit(lambda p: lr.from_scan(jaxlie.SE2(p), AZ, RANGES, 0.0, 10.0).directions)
    d = f(jnp.array([1.0, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(jnp.linalg.norm(d, axis=-1), 1.0, rtol=1e-6)
    with pytest.raises(Exception, match="unnormalised rotation"):
        jax.block_until_ready(f(jnp.array([2.0, 0.0, 0.0, 0.0])))


def test_nearly_normalised_poses_pass():
    """Rounding of composed poses (far below the tolerance) is accepted; directions stay
    unit within it."""
    T = jaxlie.SE2.from_xy_theta(0.0, 0.0, 0.0)
    for _ in range(1000):
        T = T @ jaxlie.SE2.from_xy_theta(0.01, 0.0, 0.0137)
    rays = lr.from_scan(T, AZ, RANGES, 0.0, 10.0)
    n = np.linalg.norm(np.asarray(rays.directions), axis=-1)
    assert np.all(np.abs(n - 1) < lr.ROTATION_NORM_TOL)


def test_unnormalised_se3_rejected():
    pts = jnp.array([[[1.0, 0.0, 0.0], [0.0, 2.0, 0.5]]])
    good = jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.identity(), jnp.zeros(3))
    lr.from_points(good, pts, 0.0, 10.0)  # valid
    bad = jaxlie.SE3(jnp.array([0.0, 0.0, 0.0, 0.0, 1.0, 2.0, 3.0]))
    with pytest.raises(ValueError, match="unit quaternion must have norm 1"):
        lr.from_points(bad, pts, 0.0, 10.0)


# ------------------------------------------------------------------ maps


SPEC = GridSpec([0.0, 0.0], 0.5, (3, 4))


def test_maps_accept_valid_values():
    DecayRateMap(spec=SPEC, rates=jnp.full(SPEC.shape, 0.3), outside_rate=jnp.asarray(0.0))
    ReflectionMap(spec=SPEC, probs=jnp.full(SPEC.shape, 1.0), unknown_prob=jnp.asarray(0.5))
    EndpointMap(
        spec=SPEC,
        distances=jnp.full(SPEC.shape, jnp.inf),
        occupied=jnp.zeros(SPEC.shape, bool),
        sigma_m=jnp.asarray(0.1),
        z_hit=jnp.asarray(0.9),
        z_rand=jnp.asarray(0.1),
        p_out=jnp.asarray(0.0),
    )


@pytest.mark.parametrize("bad", [-0.1, np.nan, np.inf])
def test_decay_rate_map_rejects_impossible_rates(bad):
    rates = jnp.full(SPEC.shape, 0.3).at[1, 2].set(bad)
    with pytest.raises(ValueError, match="rates"):
        DecayRateMap(spec=SPEC, rates=rates, outside_rate=jnp.asarray(0.0))
    with pytest.raises(ValueError, match="outside_rate"):
        DecayRateMap(spec=SPEC, rates=jnp.full(SPEC.shape, 0.3), outside_rate=jnp.asarray(bad))


@pytest.mark.parametrize("bad", [1.5, -0.01, np.nan])
def test_reflection_map_rejects_non_probabilities(bad):
    probs = jnp.full(SPEC.shape, 0.5).at[0, 0].set(bad)
    with pytest.raises(ValueError, match="probs"):
        ReflectionMap(spec=SPEC, probs=probs, unknown_prob=jnp.asarray(0.5))
    with pytest.raises(ValueError, match="unknown_prob"):
        ReflectionMap(spec=SPEC, probs=jnp.full(SPEC.shape, 0.5), unknown_prob=jnp.asarray(bad))


@pytest.mark.parametrize(
    "field, value, match",
    [
        ("sigma_m", 0.0, "sigma_m"),
        ("sigma_m", np.nan, "sigma_m"),
        ("z_hit", -1.0, "z_hit"),
        ("z_rand", np.inf, "z_rand"),
        ("p_out", 1.0, "p_out"),
        ("p_out", -0.1, "p_out"),
        ("distances", -1.0, "distances"),
    ],
)
def test_endpoint_map_rejects_impossible_values(field, value, match):
    kw = dict(
        spec=SPEC,
        distances=jnp.full(SPEC.shape, 1.0),
        occupied=jnp.zeros(SPEC.shape, bool),
        sigma_m=jnp.asarray(0.1),
        z_hit=jnp.asarray(0.9),
        z_rand=jnp.asarray(0.1),
        p_out=jnp.asarray(0.0),
    )
    kw[field] = jnp.full(SPEC.shape, value) if field == "distances" else jnp.asarray(value)
    with pytest.raises(ValueError, match=match):
        EndpointMap(**kw)


def test_traced_maps_are_not_host_checked():
    """Maps rebuilt inside transformations (the fit's ``with_parameters``) still work."""
    m = DecayRateMap(spec=SPEC, rates=jnp.full(SPEC.shape, 0.3), outside_rate=jnp.asarray(0.0))

    def total(a):
        return jnp.sum(m.with_parameters(a).rates)

    g = jax.grad(total)(m.parameters())
    np.testing.assert_allclose(g, 2 * m.parameters(), rtol=1e-6)


# a zero direction used to be walked as a zero-length ray: a miss and no hit
@pytest.mark.parametrize("dim", [2, 3])
def test_raybatch_rejects_zero_direction(dim):
    o = np.zeros((3, dim))
    d = np.eye(dim)[[0, 1, 0]].astype(float)
    d[2] = 0.0
    args = (np.ones(3), np.zeros(3, np.int32), 0.0, 5.0)
    with pytest.raises(ValueError, match="directions must be non-zero"):
        lr.RayBatch(o, d, *args)
    d[2, -1] = 1e-30  # tiny but non-zero: a valid direction
    assert lr.RayBatch(o, d, *args).directions.shape == (3, dim)


def test_raybatch_rejects_zero_direction_under_jit():
    def build(d):
        return lr.RayBatch(jnp.zeros((2, 2)), d, jnp.ones(2), jnp.zeros(2, jnp.int32), 0.0, 5.0)

    f = jax.jit(lambda d: build(d).directions)
    ok = jnp.array([[1.0, 0.0], [0.0, -1.0]])
    np.testing.assert_array_equal(np.asarray(f(ok)), np.asarray(ok))
    with pytest.raises(Exception, match="directions must be non-zero"):
        jax.block_until_ready(f(jnp.array([[1.0, 0.0], [0.0, 0.0]])))
