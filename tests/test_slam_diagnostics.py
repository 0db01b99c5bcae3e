"""slam.reference_match_errors: the matcher's error against maps at reference poses."""

from __future__ import annotations

import numpy as np
import pytest

from lidarjax.sim import make_office, simulate_scans
from lidarjax.slam import (
    FrontEndConfig,
    grid_map,
    match_scan,
    odometry_sigmas,
    reference_match_errors,
)

AZ = np.linspace(-np.pi / 2, np.pi / 2, 181)


def _between(a, b):
    """``a^-1 b`` of two ``[3]`` poses, written out independently of the library."""
    c, s = np.cos(a[2]), np.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array(
        [c * dx + s * dy, -s * dx + c * dy, (b[2] - a[2] + np.pi) % (2 * np.pi) - np.pi]
    )


def _moved(p, d):
    """The pose ``p`` moved by ``d = (forward, left, yaw)`` in its own frame."""
    c, s = np.cos(p[2]), np.sin(p[2])
    return np.array([p[0] + c * d[0] - s * d[1], p[1] + s * d[0] + c * d[1], p[2] + d[2]])


@pytest.fixture(scope="module")
def office():
    world = make_office(0)
    truth = world.trajectory(100, jitter_m=0.2)[:17]
    ranges = simulate_scans(world, truth, AZ, max_range_m=30.0, noise_sigma_m=0.01, seed=0)
    return truth, ranges


def _independent(truth, ranges, k, cfg, first=0):
    """Scan ``k`` matched against a map of scans ``first .. k-1`` at ``truth``, built and
    matched here with the public pieces: its error in the reference frame."""
    grid = grid_map(cfg)
    for j in range(first, k):
        grid.add_scan(truth[j], AZ, ranges[j])
    sig = odometry_sigmas(_between(truth[k - 1], truth[k])[None], cfg)[0]
    m = match_scan(grid, AZ, ranges[k], truth[k], cfg, prior_sigmas=sig)
    return _between(truth[k], m.pose), m.n_used


def test_each_error_is_the_match_against_the_map_at_the_reference_poses(office):
    truth, ranges = office
    cfg = FrontEndConfig(model="endpoint")
    r = reference_match_errors(ranges, AZ, truth, cfg, every=4)
    np.testing.assert_array_equal(r.indices, [4, 8, 12, 16])
    assert r.errors.shape == (4, 3) and r.n_used.shape == (4,)
    err, used = _independent(truth, ranges, 12, cfg)
    np.testing.assert_allclose(r.errors[2], err, atol=1e-9)
    assert r.n_used[2] == used
    # a simulated world at its exact poses, a map of 4-16 scans: within half a 5 cm cell
    # (measured: at most 13 mm forward, 1.6 mm left)
    assert np.all(np.abs(r.errors[:, :2]) < 0.025) and np.all(np.abs(r.errors[:, 2]) < 0.01)
    s = r.summary()
    assert s["n_matches"] == 4
    np.testing.assert_allclose(s["mean_forward_mm"], 1e3 * r.errors[:, 0].mean())
    np.testing.assert_allclose(s["median_abs_left_mm"], 1e3 * np.median(np.abs(r.errors[:, 1])))
    np.testing.assert_allclose(r.standard_error, r.errors.std(0, ddof=1) / 2.0)


def test_a_local_map_holds_only_the_last_scans(office):
    truth, ranges = office
    cfg = FrontEndConfig(model="endpoint")
    r = reference_match_errors(ranges, AZ, truth, cfg, every=8, local_scans=3)
    np.testing.assert_array_equal(r.indices, [8, 16])
    err, used = _independent(truth, ranges, 16, cfg, first=13)
    np.testing.assert_allclose(r.errors[1], err, atol=1e-6)
    assert r.n_used[1] == used


def test_a_reference_pose_moved_off_shows_as_the_opposite_error(office):
    """The last scan's reference moved 10 cm forward and 6 cm right: its match stays near
    the scan's true pose, so the error (in the moved reference's frame) is about (-10, +6)
    cm; the sign convention (forward, left) and the frame are what this pins down. The
    match depends on where it starts by up to half a cell (measured 2.4 cm for a 3 cm
    move: the last stage's local maxima), hence the tolerance. The endpoint model: the
    convention does not depend on the model, and its matcher is compiled already."""
    truth, ranges = office
    cfg = FrontEndConfig(model="endpoint")
    k = truth.shape[0] - 1
    moved = truth.copy()
    moved[k] = _moved(truth[k], (0.10, -0.06, 0.0))
    exact = reference_match_errors(ranges, AZ, truth, cfg, every=k)
    off = reference_match_errors(ranges, AZ, moved, cfg, every=k)
    np.testing.assert_array_equal(off.indices, [k])
    assert np.all(np.abs(exact.errors[0, :2]) < 0.025)  # measured (2, 10) mm
    np.testing.assert_allclose(off.errors[0, :2] - exact.errors[0, :2], [-0.10, 0.06], atol=0.025)
    assert abs(off.errors[0, 2] - exact.errors[0, 2]) < 0.01


@pytest.mark.parametrize(
    "kwargs, kind, text",
    [
        (dict(every=0), ValueError, "every must be >= 1"),
        (dict(every=1.5), TypeError, "every must be an integer"),
        (dict(every=True), TypeError, "every must be an integer"),
        (dict(local_scans=-1), ValueError, "local_scans must be >= 0"),
        (dict(every=50), ValueError, "matches no scan"),
    ],
)
def test_bad_counts_name_the_argument(office, kwargs, kind, text):
    truth, ranges = office
    with pytest.raises(kind, match=text):
        reference_match_errors(ranges, AZ, truth, **kwargs)


def test_bad_poses_name_the_argument(office):
    truth, ranges = office
    with pytest.raises(ValueError, match="poses_xy_yaw must have shape"):
        reference_match_errors(ranges, AZ, truth[:-1])
    bad = truth.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="poses_xy_yaw must be finite"):
        reference_match_errors(ranges, AZ, bad)
    with pytest.raises(ValueError, match="at least 2 scans"):
        reference_match_errors(ranges[:1], AZ, truth[:1])
