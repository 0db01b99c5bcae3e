"""Tests of the KITTI pose file -> planar trajectory loader
(``lidarjax.datasets._urban_trajectory``; moved from the urban simulator's tests)."""

import numpy as np
import pytest

from lidarjax.datasets import fetch, load_urban_trajectory
from lidarjax.datasets._urban_trajectory import CAMERA_TO_GROUND


@pytest.fixture(scope="module")
def traj():
    return load_urban_trajectory()


def test_trajectory_loader(traj):
    assert traj.xy_yaw.shape == (4541, 3)
    assert traj.times_s.shape == (4541,)
    assert 3600 < traj.length_m < 3800
    step = np.diff(traj.xy_yaw[:, :2], axis=0)
    dist = np.linalg.norm(step, axis=1)
    motion = np.arctan2(step[:, 1], step[:, 0])
    err = np.rad2deg(np.abs((traj.xy_yaw[:-1, 2] - motion + np.pi) % (2 * np.pi) - np.pi))
    # KITTI-00 has a few slow, sharp turns where the camera's displacement over 0.1 s
    # deviates up to ~35 deg from its heading (pose jitter); at speed they agree closely.
    assert np.percentile(err[dist > 0.3], 95) < 10
    assert err[dist > 1.0].max() < 10
    np.testing.assert_allclose(np.linalg.det(CAMERA_TO_GROUND), 1.0)
    # camera forward (z) -> ground x, camera right (x) -> ground -y, camera down (y) -> -z
    np.testing.assert_array_equal(CAMERA_TO_GROUND @ [0, 0, 1], [1, 0, 0])
    np.testing.assert_array_equal(CAMERA_TO_GROUND @ [1, 0, 0], [0, -1, 0])


def test_trajectory_without_times_file(tmp_path):
    t = load_urban_trajectory(fetch("kitti-00-poses"))
    np.testing.assert_allclose(t.times_s[:3], [0.0, 0.1, 0.2])
