"""Tests of the ray batch type and its constructors."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from lidarjax.rays import HIT, SUB, SUP, RayBatch, classify, from_points, from_scan


def test_from_scan_geometry_matches_numpy():
    rng = np.random.default_rng(0)
    poses = rng.uniform(-3, 3, (4, 3))
    az = np.linspace(-np.pi / 2, np.pi / 2, 7)
    ranges = rng.uniform(0.0, 12.0, (4, 7))
    T = jaxlie.SE2.from_xy_theta(*jnp.asarray(poses.T))
    rays = from_scan(T, az, ranges, 0.5, 10.0)
    assert rays.shape == (4, 7) and rays.dim == 2
    ang = poses[:, 2:3] + az[None]
    np.testing.assert_allclose(rays.directions[..., 0], np.cos(ang), atol=1e-12)
    np.testing.assert_allclose(rays.directions[..., 1], np.sin(ang), atol=1e-12)
    np.testing.assert_allclose(rays.origins, np.repeat(poses[:, None, :2], 7, axis=1))
    end = poses[:, None, :2] + ranges[..., None] * np.stack([np.cos(ang), np.sin(ang)], -1)
    hit = np.asarray(rays.kind) == HIT
    np.testing.assert_allclose(np.asarray(rays.endpoints())[hit], end[hit], atol=1e-12)
    expected_kind = np.where(ranges < 0.5, SUB, np.where(ranges >= 10.0, SUP, HIT))
    np.testing.assert_array_equal(rays.kind, expected_kind)
    flat = rays.flatten()
    assert flat.shape == (28,)
    np.testing.assert_array_equal(flat.ranges, ranges.reshape(-1))


def test_from_scan_broadcasts_one_scan_over_many_poses():
    T = jaxlie.SE2.from_xy_theta(jnp.zeros(5), jnp.arange(5.0), jnp.zeros(5))
    rays = from_scan(T, jnp.zeros(3), jnp.ones(3), 0.0, 5.0)
    assert rays.shape == (5, 3)
    np.testing.assert_allclose(rays.origins[:, 0, 1], np.arange(5.0))


def test_classify_boundaries():
    k = classify(jnp.array([0.0, 0.49, 0.5, 9.99, 10.0, 80.0]), 0.5, 10.0)
    np.testing.assert_array_equal(k, [SUB, SUB, HIT, HIT, SUP, SUP])


@pytest.mark.parametrize("bad", [np.nan, -0.1, np.inf])
def test_from_scan_rejects_bad_ranges(bad):
    ranges = np.ones((2, 3))
    ranges[1, 2] = bad
    with pytest.raises(ValueError, match="ranges_m"):
        from_scan(jaxlie.SE2.identity(), np.zeros(3), ranges, 0.0, 5.0)


def test_from_scan_rejects_bad_ranges_under_jit():
    @eqx.filter_jit
    def build(r):
        return from_scan(jaxlie.SE2.identity(), jnp.zeros(2), r, 0.0, 5.0).ranges

    build(jnp.ones(2))
    with pytest.raises(eqx.EquinoxRuntimeError, match="ranges_m"):
        jax.block_until_ready(build(jnp.array([1.0, jnp.nan])))


def test_from_scan_rejects_bad_arguments():
    with pytest.raises(ValueError, match="T_world_sensor"):
        from_scan(jaxlie.SE3.identity(), np.zeros(3), np.ones(3), 0.0, 5.0)
    with pytest.raises(ValueError, match="azimuths_rad"):
        from_scan(jaxlie.SE2.identity(), np.zeros(3), np.ones(4), 0.0, 5.0)
    with pytest.raises(ValueError, match="r_max"):
        from_scan(jaxlie.SE2.identity(), np.zeros(3), np.ones(3), 2.0, 1.0)
    T = jaxlie.SE2.from_xy_theta(jnp.zeros(3), jnp.zeros(3), jnp.zeros(3))
    with pytest.raises(ValueError, match="broadcast"):
        from_scan(T, np.zeros(2), np.ones((4, 2)), 0.0, 5.0)


def test_from_points_geometry():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(2, 6, 3)) * 4
    pts[0, 0] = 0.0  # a point at the sensor origin
    R = jaxlie.SO3.from_rpy_radians(0.1, -0.2, 0.7)
    T = jaxlie.SE3.from_rotation_and_translation(R, jnp.array([1.0, 2.0, 3.0]))
    rays = from_points(T, pts, 0.0, 6.0)
    assert rays.shape == (2, 6) and rays.dim == 3
    world = np.asarray(jax.vmap(jax.vmap(T.apply))(jnp.asarray(pts)))
    hit = np.asarray(rays.kind) == HIT
    np.testing.assert_allclose(np.asarray(rays.endpoints())[hit], world[hit], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(rays.directions, axis=-1), 1.0, atol=1e-12)
    assert float(rays.ranges[0, 0]) == 0.0
    np.testing.assert_array_equal(
        rays.kind, np.where(np.linalg.norm(pts, axis=-1) >= 6.0, SUP, HIT)
    )
    with pytest.raises(ValueError, match="points_xyz"):
        from_points(T, np.full((2, 3), np.nan), 0.0, 6.0)
    with pytest.raises(ValueError, match="points_xyz"):
        from_points(T, np.zeros((2, 2)), 0.0, 6.0)


def test_raybatch_validates_shapes():
    with pytest.raises(ValueError, match="directions"):
        RayBatch(
            origins=jnp.zeros((3, 2)), directions=jnp.zeros((3, 3)), ranges=jnp.zeros(3),
            kind=jnp.zeros(3, jnp.int32), r_min=jnp.array(0.0), r_max=jnp.array(1.0),
        )  # fmt: skip
    with pytest.raises(ValueError, match="ranges"):
        RayBatch(
            origins=jnp.zeros((3, 2)), directions=jnp.zeros((3, 2)), ranges=jnp.zeros(4),
            kind=jnp.zeros(3, jnp.int32), r_min=jnp.array(0.0), r_max=jnp.array(1.0),
        )  # fmt: skip
    rays = from_scan(jaxlie.SE2.identity(), jnp.zeros(3), jnp.array([1.0, 9.0, 0.0]), 0.5, 5.0)
    assert rays.counts() == {"HIT": 1, "SUB": 1, "SUP": 1}
    # ranges [1, 9, 0] with r_min 0.5, r_max 5: HIT, SUP, SUB
    np.testing.assert_allclose(rays.mapping_lengths(), [1.0, 5.0, 0.0])  # SUB: its range
    np.testing.assert_allclose(rays.model_lengths(), [1.0, 5.0, 0.5])  # SUB: r_min
    np.testing.assert_allclose(rays.trace_lengths(), rays.mapping_lengths())


def test_from_spinning_scan_keeps_no_returns():
    import jaxlie

    from lidarjax.rays import from_spinning_scan

    d = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, -1.0]])
    T = jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.from_z_radians(np.pi / 2), np.array([1.0, 2.0, 1.5])
    )
    rays = from_spinning_scan(T, d, np.array([3.0, np.inf, 0.2]), r_min=0.5, r_max=50.0)
    np.testing.assert_allclose(rays.directions, [[0, 1, 0], [-1, 0, 0], [0, 0, -1]], atol=1e-12)
    np.testing.assert_allclose(rays.origins, np.tile([1.0, 2.0, 1.5], (3, 1)))
    np.testing.assert_allclose(rays.ranges, [3.0, 50.0, 0.2])
    np.testing.assert_array_equal(rays.kind, [HIT, SUP, SUB])
    np.testing.assert_allclose(rays.endpoints()[0], [1.0, 5.0, 1.5], atol=1e-12)
    with pytest.raises(ValueError, match="ranges_m"):
        from_spinning_scan(T, d, np.array([1.0, np.nan, 1.0]), r_max=50.0)
    with pytest.raises(ValueError, match="r_max"):
        from_spinning_scan(T, d, np.array([1.0, np.inf, 1.0]))
    with pytest.raises(ValueError, match="directions"):
        from_spinning_scan(T, d[:, :2], np.ones(3), r_max=50.0)
