"""The classical SLAM baseline (small_gicp registration + GTSAM pose graph)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("gtsam")
pytest.importorskip("small_gicp")

from lidarjax.metrics import absolute_trajectory_error  # noqa: E402
from lidarjax.sim import make_office, simulate_scans, wheel_odometry  # noqa: E402
from lidarjax.slam import IcpSlamResult, icp_front_end, icp_pose_graph_slam  # noqa: E402
from lidarjax.slam._front_end import between_np  # noqa: E402

# the drifting odometry the comparison uses on every log
DRIFT = dict(
    sigma_trans_rel=0.05,
    sigma_rot_per_m=float(np.deg2rad(1.0)),
    heading_bias_per_m=float(np.deg2rad(0.3)),
    sigma_rot_per_rad=0.02,
)
AZ = np.linspace(-np.pi / 2, np.pi / 2, 181)
MAX_RANGE = 30.0


@pytest.fixture(scope="module")
def office_run():
    """1.3 laps of the office loop (100 poses a lap): the last 30 scans revisit the start."""
    world = make_office(0)
    lap = world.trajectory(100, jitter_m=0.2)
    truth = np.vstack([lap, lap[:30]])
    ranges = simulate_scans(world, truth, AZ, max_range_m=MAX_RANGE, noise_sigma_m=0.01, seed=0)
    odo = wheel_odometry(truth, seed=0, **DRIFT)
    result = icp_pose_graph_slam(ranges, AZ, odo, max_range_m=MAX_RANGE)
    return truth, ranges, odo, result


def test_office_recovers_trajectory(office_run):
    truth, _, odo, r = office_run
    assert isinstance(r, IcpSlamResult)
    n = truth.shape[0]
    assert r.poses.shape == r.odometry_poses.shape == (n, 3)
    assert r.registered.shape == (n,) and r.registered.mean() > 0.95
    np.testing.assert_allclose(r.poses[0], odo[0], atol=1e-6)
    assert np.all(np.abs(r.poses[:, 2]) <= np.pi)
    ate_odo = absolute_trajectory_error(odo, truth).rmse_m
    ate_front = absolute_trajectory_error(r.odometry_poses, truth).rmse_m
    ate_slam = absolute_trajectory_error(r.poses, truth)
    assert ate_odo > 0.5  # the drift is real
    assert ate_front < 0.1 * ate_odo
    assert ate_slam.rmse_m < 0.05 * ate_odo
    assert ate_slam.rmse_m < 0.02 and ate_slam.max_m < 0.06
    assert r.seconds_front_end > 0 and r.seconds_back_end > 0


def test_office_detects_the_revisit(office_run):
    truth, _, _, r = office_run
    loops = r.loops
    assert loops.ndim == 2 and loops.shape[1] == 2 and loops.dtype == np.int64
    assert len(loops) > 0
    i, j = loops[:, 0], loops[:, 1]
    assert np.all(i - j >= 30)
    # the second lap (scans 100..129) closes onto the first lap's start
    assert np.any((i >= 100) & (j < 30))
    # every accepted loop joins scans that really are close
    gap = np.linalg.norm(truth[i, :2] - truth[j, :2], axis=1)
    assert gap.max() < 4.0


def test_loops_are_true_revisits():
    """A short run (into a room and back out along the same path, another office):
    every accepted loop joins scans that really are within the search radius."""
    world = make_office(1)
    lap = world.trajectory(100)
    truth = lap[:40]
    ranges = simulate_scans(world, truth, AZ, max_range_m=MAX_RANGE, noise_sigma_m=0.01, seed=1)
    odo = wheel_odometry(truth, seed=1, **DRIFT)
    r = icp_pose_graph_slam(ranges, AZ, odo, max_range_m=MAX_RANGE, loop_min_separation=10)
    gap = np.linalg.norm(truth[r.loops[:, 0], :2] - truth[r.loops[:, 1], :2], axis=1)
    assert np.all(gap < 4.0)
    assert absolute_trajectory_error(r.poses, truth).rmse_m < 0.05


def test_front_end_alone_is_the_pipelines_chain(office_run):
    """icp_front_end is the whole pipeline's registration chain, bit for bit (the loop
    closures and the pose graph do not feed back into it)."""
    truth, ranges, odo, r = office_run
    f = icp_front_end(ranges, AZ, odo, max_range_m=MAX_RANGE)
    np.testing.assert_array_equal(f.poses, r.odometry_poses)
    np.testing.assert_array_equal(f.registered, r.registered)
    assert f.seconds > 0
    # and it is a lidar odometry: ten times better than the odometry it starts from
    assert absolute_trajectory_error(f.poses, truth).rmse_m < 0.1 * (
        absolute_trajectory_error(odo, truth).rmse_m
    )


def test_front_end_takes_no_points_from_readings_at_or_beyond_the_cap():
    """Readings at or beyond max_range_m (no-returns) carry no point: where a scan keeps
    too few, the chain takes the odometry's increment and says so."""
    r, a, o = _inputs()
    r[5:8] = 10.0
    f = icp_front_end(r, a, o, max_range_m=10.0)
    assert not f.registered[5:8].any()
    # scans 5-7 took the odometry's increments
    np.testing.assert_allclose(
        between_np(f.poses[4:7], f.poses[5:8]), between_np(o[4:7], o[5:8]), atol=1e-9
    )


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"max_range_m": 0.0}, "max_range_m"),
        ({"max_range_m": 10.0, "range_cap_m": float("nan")}, "range_cap_m"),
        ({"max_range_m": 10.0, "voxel_m": -0.1}, "voxel_m"),
    ],
)
def test_front_end_bad_options_raise(kwargs, name):
    r, a, o = _inputs()
    with pytest.raises(ValueError, match=name):
        icp_front_end(r, a, o, **kwargs)
    with pytest.raises(ValueError, match="ranges_m"):
        icp_front_end(r * 0.0, a, o, max_range_m=10.0)


def _inputs(n=12, b=AZ.size):
    ranges = np.full((n, b), 5.0)
    odo = np.zeros((n, 3))
    odo[:, 0] = np.arange(n) * 0.1
    return ranges, AZ[:b].copy(), odo


@pytest.mark.parametrize(
    ("change", "name"),
    [
        (lambda r, a, o: (r[0], a, o), "ranges_m"),
        (lambda r, a, o: (r + np.nan, a, o), "ranges_m"),
        (lambda r, a, o: (r * 0.0, a, o), "ranges_m"),
        (lambda r, a, o: (-r, a, o), "ranges_m"),
        (lambda r, a, o: (r, a[:-1], o), "azimuths_rad"),
        (lambda r, a, o: (r, np.full_like(a, np.inf), o), "azimuths_rad"),
        (lambda r, a, o: (r, a, o[:-1]), "odometry_xy_yaw"),
        (lambda r, a, o: (r, a, o[:, :2]), "odometry_xy_yaw"),
        (lambda r, a, o: (r, a, o + np.nan), "odometry_xy_yaw"),
    ],
)
def test_bad_arrays_raise(change, name):
    r, a, o = change(*_inputs())
    with pytest.raises(ValueError, match=name):
        icp_pose_graph_slam(r, a, o, max_range_m=10.0)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"max_range_m": 0.0}, "max_range_m"),
        ({"max_range_m": float("nan")}, "max_range_m"),
        ({"max_range_m": 10.0, "range_cap_m": -1.0}, "range_cap_m"),
        ({"max_range_m": 10.0, "voxel_m": 0.0}, "voxel_m"),
        ({"max_range_m": 10.0, "loop_radius_m": float("inf")}, "loop_radius_m"),
        ({"max_range_m": 10.0, "loop_min_separation": 3}, "loop_min_separation"),
        ({"max_range_m": 10.0, "loop_min_separation": 30.5}, "loop_min_separation"),
        ({"max_range_m": 10.0, "seed": -1}, "seed"),
    ],
)
def test_bad_options_raise(kwargs, name):
    r, a, o = _inputs()
    with pytest.raises(ValueError, match=name):
        icp_pose_graph_slam(r, a, o, **kwargs)


def test_no_returns_fall_back_to_odometry():
    """Scans without a single return cannot be registered: the odometry chain is kept."""
    r, a, o = _inputs()
    r[:] = 10.0  # all no-returns
    res = icp_pose_graph_slam(r, a, o, max_range_m=10.0)
    np.testing.assert_allclose(res.odometry_poses, o, atol=1e-9)
    np.testing.assert_allclose(res.poses, o, atol=1e-6)
    assert not res.registered[1:].any() and res.loops.shape == (0, 2)


@pytest.mark.slow  # ~20 s: the Intel log through the whole pipeline
def test_intel_log_beats_drifting_odometry():
    from lidarjax.datasets import fetch, load_carmen

    log = load_carmen(fetch("intel"))
    odo = wheel_odometry(log.poses, seed=0, **DRIFT)
    r = icp_pose_graph_slam(log.ranges_m, log.azimuths_rad, odo, max_range_m=log.usable_range_m)
    ate_odo = absolute_trajectory_error(odo, log.poses).rmse_m
    ate_slam = absolute_trajectory_error(r.poses, log.poses).rmse_m
    assert ate_slam < 0.15  # measured 0.064 m (odometry 6.3 m)
    assert ate_slam < 0.05 * ate_odo
    assert len(r.loops) > 100


@pytest.mark.parametrize("separation", [30, 1000])
def test_failed_isam_update_is_solved_in_batch(office_run, monkeypatch, separation):
    """An iSAM2 update that raises GTSAM's indeterminate-system error (as on
    freiburg-campus) is replaced by a batch solve of every factor so far: at the first
    loop closure (separation 30) or at the final update (separation 1000: no loops, so
    the final update is the only one). The run ends where the undisturbed run does."""
    import gtsam

    truth, ranges, odo, _ = office_run
    undisturbed = icp_pose_graph_slam(
        ranges, AZ, odo, max_range_m=MAX_RANGE, loop_min_separation=separation
    )
    real = gtsam.ISAM2
    failed = []

    class FailsOnce:
        def __init__(self, *args):
            self._isam = real(*args)

        def update(self, *args):
            if len(args) == 2 and not failed:
                failed.append(True)
                raise RuntimeError("Indeterminate linear system detected (simulated)")
            return self._isam.update(*args)

        def __getattr__(self, name):
            return getattr(self._isam, name)

    monkeypatch.setattr(gtsam, "ISAM2", FailsOnce)
    r = icp_pose_graph_slam(ranges, AZ, odo, max_range_m=MAX_RANGE, loop_min_separation=separation)
    assert failed and r.isam_restarts == 1 and undisturbed.isam_restarts == 0
    assert (len(r.loops) > 0) == (separation == 30)
    if separation == 30:
        assert absolute_trajectory_error(r.poses, truth).rmse_m < 0.02
    np.testing.assert_array_equal(r.loops, undisturbed.loops)
    np.testing.assert_allclose(r.poses, undisturbed.poses, atol=1e-3)
