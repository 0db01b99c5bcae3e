"""Tests of the trajectory error metrics (``lidarjax.metrics._trajectory``)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from lidarjax.metrics._trajectory import (
    TrajectoryErrors,
    interpolate_at_arclength,
    trajectory_errors,
)


def _straight(n: int, length: float, heading: float) -> np.ndarray:
    s = np.linspace(0.0, length, n)
    return np.stack([s * np.cos(heading), s * np.sin(heading), np.full(n, heading)], axis=1)


def _offset(gt: np.ndarray, lon: float, lat: float, dyaw: float = 0.0) -> np.ndarray:
    c, s = np.cos(gt[:, 2]), np.sin(gt[:, 2])
    est = gt.copy()
    est[:, 0] += lon * c - lat * s
    est[:, 1] += lon * s + lat * c
    est[:, 2] += dyaw
    return est


def _brute_force(est, gt, spacing, valid=None):
    """Loop implementation of the documented definition (math module only)."""
    n = len(gt)
    valid = [True] * n if valid is None else list(valid)
    arc = [0.0]
    for k in range(1, n):
        arc.append(arc[-1] + math.hypot(gt[k, 0] - gt[k - 1, 0], gt[k, 1] - gt[k - 1, 1]))
    total = arc[-1]

    def wrap(a):
        return math.atan2(math.sin(a), math.cos(a))

    def interp(p, j, t):
        x = p[j, 0] + t * (p[j + 1, 0] - p[j, 0])
        y = p[j, 1] + t * (p[j + 1, 1] - p[j, 1])
        return x, y, wrap(p[j, 2] + t * wrap(p[j + 1, 2] - p[j, 2]))

    lat, lon, ang, dist = [], [], [], []
    k = 0
    while k * spacing <= total * (1 + 1e-9):
        s = min(k * spacing, total)
        k += 1
        j = next(j for j in range(n - 1) if arc[j] <= s <= arc[j + 1])
        t = (s - arc[j]) / (arc[j + 1] - arc[j])
        if not ((valid[j] or t == 1.0) and (valid[j + 1] or t == 0.0)):
            continue
        ex, ey, eyaw = interp(est, j, t)
        gx, gy, gyaw = interp(gt, j, t)
        dx, dy = ex - gx, ey - gy
        lon.append(dx * math.cos(gyaw) + dy * math.sin(gyaw))
        lat.append(-dx * math.sin(gyaw) + dy * math.cos(gyaw))
        ang.append(math.degrees(wrap(eyaw - gyaw)))
        dist.append(math.hypot(dx, dy))

    def mean(v):
        return sum(v) / len(v)

    def std(v):
        m = mean(v)
        return math.sqrt(sum((x - m) ** 2 for x in v) / len(v))

    return {
        "delta_pos_m": mean(dist),
        "rmse_pos_m": math.sqrt(mean([d * d for d in dist])),
        "delta_lat_m": mean([abs(v) for v in lat]),
        "sigma_lat_m": std(lat),
        "delta_lon_m": mean([abs(v) for v in lon]),
        "sigma_lon_m": std(lon),
        "delta_ang_deg": mean([abs(v) for v in ang]),
        "sigma_ang_deg": std(ang),
        "rmse_ang_deg": math.sqrt(mean([a * a for a in ang])),
        "max_pos_m": max(dist),
        "n": len(dist),
    }


def _assert_metrics_close(got: TrajectoryErrors, want: dict, atol: float = 1e-9):
    d = got.as_dict()
    assert set(d) == set(want)
    assert d["n"] == want["n"]
    for key, value in want.items():
        assert d[key] == pytest.approx(value, abs=atol), key


def _smooth_random(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, n)
    heading = 0.3 + np.cumsum(rng.normal(0.0, 0.05, n))
    speed = 0.3 + 0.2 * np.sin(7 * t) ** 2
    xy = np.cumsum(np.stack([speed * np.cos(heading), speed * np.sin(heading)], 1), axis=0)
    gt = np.concatenate([xy, np.angle(np.exp(1j * heading))[:, None]], axis=1)
    est = gt.copy()
    est[:, :2] += np.cumsum(rng.normal(0.0, 0.02, (n, 2)), axis=0)
    est[:, 2] = np.angle(np.exp(1j * (heading + np.cumsum(rng.normal(0.0, 0.01, n)))))
    return est, gt


# ------------------------------------------------------------------------------------------


def test_straight_line_constant_offset():
    gt = _straight(101, 20.0, heading=0.7)
    est = _offset(gt, lon=0.1, lat=0.3)
    r = trajectory_errors(est, gt)
    assert isinstance(r, TrajectoryErrors)
    assert r.n == 21
    assert r.delta_lat_m == pytest.approx(0.3, abs=1e-12)
    assert r.delta_lon_m == pytest.approx(0.1, abs=1e-12)
    assert r.sigma_lat_m == pytest.approx(0.0, abs=1e-12)
    assert r.sigma_lon_m == pytest.approx(0.0, abs=1e-12)
    assert r.delta_pos_m == pytest.approx(math.sqrt(0.1), abs=1e-12)
    assert r.rmse_pos_m == pytest.approx(math.sqrt(0.1), abs=1e-12)
    assert r.max_pos_m == pytest.approx(math.sqrt(0.1), abs=1e-12)
    assert r.delta_ang_deg == r.sigma_ang_deg == r.rmse_ang_deg == 0.0
    # sign conventions: lateral left positive -> negate the offset, same magnitudes
    r2 = trajectory_errors(_offset(gt, lon=-0.1, lat=-0.3), gt)
    assert r2.delta_lat_m == pytest.approx(0.3, abs=1e-12)
    assert r2.delta_lon_m == pytest.approx(0.1, abs=1e-12)


def test_signed_errors_through_sigma():
    # lateral +0.3 for the first half, -0.1 after: signed mean 0.1, std 0.2
    gt = _straight(41, 40.0, heading=-1.2)
    lat = np.where(np.arange(41) <= 20, 0.3, -0.1)
    c, s = np.cos(gt[:, 2]), np.sin(gt[:, 2])
    est = gt.copy()
    est[:, 0] -= lat * s
    est[:, 1] += lat * c
    r = trajectory_errors(est, gt, spacing_m=1.0)
    # rows are 1 m apart, so evaluation points coincide with rows 0..40
    assert r.n == 41
    signed = lat
    assert r.delta_lat_m == pytest.approx(np.abs(signed).mean(), abs=1e-12)
    assert r.sigma_lat_m == pytest.approx(signed.std(), abs=1e-12)


def test_circle_heading_rotated_offset():
    radius, n = 5.0, 361
    phi = np.linspace(0.0, 2 * np.pi, n)
    heading = phi + np.pi / 2  # counter-clockwise travel
    gt = np.stack([radius * np.cos(phi), radius * np.sin(phi), np.angle(np.exp(1j * heading))], 1)
    est = _offset(gt, lon=-0.05, lat=0.2, dyaw=np.radians(2.0))
    est[:, 2] = np.angle(np.exp(1j * est[:, 2]))
    chord = 2 * radius * np.sin(np.pi / (n - 1))
    r = trajectory_errors(est, gt, spacing_m=chord)  # evaluation points = rows
    assert r.n == n
    assert r.delta_lat_m == pytest.approx(0.2, abs=1e-9)
    assert r.delta_lon_m == pytest.approx(0.05, abs=1e-9)
    assert r.delta_ang_deg == pytest.approx(2.0, abs=1e-9)
    assert r.sigma_ang_deg == pytest.approx(0.0, abs=1e-9)
    assert r.rmse_ang_deg == pytest.approx(2.0, abs=1e-9)
    assert r.delta_pos_m == pytest.approx(math.hypot(0.2, 0.05), abs=1e-9)
    # with 1 m spacing the points fall between rows; still close (chord interpolation)
    r1 = trajectory_errors(est, gt, spacing_m=1.0)
    assert r1.n == int(np.floor((n - 1) * chord)) + 1
    assert r1.delta_lat_m == pytest.approx(0.2, abs=1e-4)
    assert r1.delta_lon_m == pytest.approx(0.05, abs=1e-4)


def test_heading_wraparound():
    gt = _straight(11, 10.0, heading=0.0)
    gt[:, 2] = np.radians(179.0)
    est = gt.copy()
    est[:, 2] = np.radians(-179.0)
    r = trajectory_errors(est, gt)
    assert r.delta_ang_deg == pytest.approx(2.0, abs=1e-9)
    assert r.rmse_ang_deg == pytest.approx(2.0, abs=1e-9)
    assert r.sigma_ang_deg == pytest.approx(0.0, abs=1e-9)
    # exactly opposite headings give +180 (the interval is (-180, 180])
    est[:, 2] = gt[:, 2] - np.pi
    r = trajectory_errors(est, gt)
    assert r.delta_ang_deg == pytest.approx(180.0, abs=1e-9)
    assert r.sigma_ang_deg == pytest.approx(0.0, abs=1e-9)


def test_evaluation_point_count():
    gt = _straight(8, 10.5, heading=2.0)
    for spacing, expected in [(1.0, 11), (2.0, 6), (0.5, 22), (10.5, 2), (20.0, 1), (3.5, 4)]:
        r = trajectory_errors(gt, gt, spacing_m=spacing)
        assert r.n == expected == math.floor(10.5 / spacing + 1e-12) + 1
        assert r.delta_pos_m == 0.0
    est, gt = _smooth_random(300, seed=1)
    length = np.linalg.norm(np.diff(gt[:, :2], axis=0), axis=1).sum()
    for spacing in (0.7, 1.0, 2.5):
        assert trajectory_errors(est, gt, spacing_m=spacing).n == math.floor(length / spacing) + 1


def _resample(p: np.ndarray, k: int) -> np.ndarray:
    """Insert ``k - 1`` points linearly (yaw on the shortest arc) into every segment."""
    rows = []
    for j in range(len(p) - 1):
        for m in range(k):
            t = m / k
            dyaw = np.angle(np.exp(1j * (p[j + 1, 2] - p[j, 2])))
            rows.append(
                [
                    p[j, 0] + t * (p[j + 1, 0] - p[j, 0]),
                    p[j, 1] + t * (p[j + 1, 1] - p[j, 1]),
                    np.angle(np.exp(1j * (p[j, 2] + t * dyaw))),
                ]
            )
    rows.append(p[-1])
    return np.array(rows)


def test_time_sampling_independence():
    est, gt = _smooth_random(60, seed=2)
    base = trajectory_errors(est, gt, spacing_m=0.9)
    for k in (2, 3, 7):
        r = trajectory_errors(_resample(est, k), _resample(gt, k), spacing_m=0.9)
        _assert_metrics_close(r, base.as_dict(), atol=1e-9)
    # standing still (repeated rows) does not change anything either
    idx = np.sort(np.concatenate([np.arange(60), np.full(15, 10), np.full(5, 59)]))
    r = trajectory_errors(est[idx], gt[idx], spacing_m=0.9)
    _assert_metrics_close(r, base.as_dict(), atol=1e-12)


@pytest.mark.parametrize("seed", [3, 4])
def test_matches_brute_force(seed):
    est, gt = _smooth_random(200, seed=seed)
    for spacing in (1.0, 0.37):
        _assert_metrics_close(
            trajectory_errors(est, gt, spacing_m=spacing), _brute_force(est, gt, spacing)
        )


def test_valid_mask():
    gt = _straight(21, 10.0, heading=0.4)  # rows 0.5 m apart
    est = _offset(gt, lon=0.2, lat=-0.1)
    valid = np.ones(21, dtype=bool)
    valid[:5] = False  # rows 0..4 (s <= 2.0 m) invalid
    est[:5] = np.nan
    r = trajectory_errors(est, gt, valid=valid)
    # s = 0, 1, 2 need invalid rows; s = 3 .. 10 are fine
    assert r.n == 8
    assert r.delta_lon_m == pytest.approx(0.2, abs=1e-12)
    assert r.delta_lat_m == pytest.approx(0.1, abs=1e-12)
    _assert_metrics_close(r, _brute_force(np.nan_to_num(est), gt, 1.0, valid))
    # an invalid row in the middle removes the points touching it
    valid2 = np.ones(21, dtype=bool)
    valid2[7] = False  # s = 3.5; points s = 3 (row 6, t=1 -> only row 6) and 4 (row 8)
    est2 = _offset(gt, lon=0.2, lat=-0.1)
    est2[7] = np.nan
    r2 = trajectory_errors(est2, gt, valid=valid2)
    assert r2.n == 11
    valid2[6] = False  # now s = 3 (row 6 itself) is lost
    assert trajectory_errors(est2, gt, valid=valid2).n == 10


def test_valid_mask_with_nan_ground_truth():
    est, gt = _smooth_random(120, seed=5)
    gt_nan = gt.copy()
    gt_nan[40:45] = np.nan
    valid = np.isfinite(gt_nan).all(axis=1)
    r = trajectory_errors(est, gt_nan, valid=valid)
    length = np.linalg.norm(np.diff(gt[valid, :2], axis=0), axis=1).sum()
    # the arc length bridges the NaN rows; points between rows 39 and 45 are skipped
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(gt[valid, :2], axis=0), axis=1))])
    s = np.arange(math.floor(length) + 1)
    skipped = int(np.sum((s > arc[39]) & (s < arc[40])))
    assert skipped >= 1
    assert r.n == math.floor(length) + 1 - skipped


def test_interpolate_at_arclength():
    p = np.array([[0.0, 0.0, np.radians(179.0)], [2.0, 4.0, np.radians(-179.0)], [2.0, 4.0, 0.0]])
    arc = np.array([0.0, 10.0, 20.0])
    out = interpolate_at_arclength(p, np.array([0.0, 5.0, 2.5, 10.0, 20.0]), arc)
    assert out.shape == (5, 3)
    np.testing.assert_allclose(out[0], p[0], atol=0)
    np.testing.assert_allclose(out[1, :2], [1.0, 2.0], atol=1e-15)
    assert abs(out[1, 2]) == pytest.approx(np.pi, abs=1e-12)  # shortest arc through 180 deg
    assert out[1, 2] > 0  # wrapped to (-pi, pi]
    np.testing.assert_allclose(out[2], [0.5, 1.0, np.radians(179.5)], atol=1e-12)
    np.testing.assert_array_equal(out[3], p[1])
    np.testing.assert_array_equal(out[4], p[2])
    # constant arc length (standing still): a query there returns the first such row
    out = interpolate_at_arclength(p, np.array([10.0]), np.array([0.0, 10.0, 10.0]))
    np.testing.assert_array_equal(out[0], p[1])
    with pytest.raises(ValueError, match="s_query"):
        interpolate_at_arclength(p, np.array([21.0]), arc)
    with pytest.raises(ValueError, match="arclength"):
        interpolate_at_arclength(p, np.array([1.0]), np.array([0.0, 5.0, 4.0]))
    with pytest.raises(ValueError, match="xy_yaw"):
        interpolate_at_arclength(p[:, :2], np.array([1.0]), arc)


def test_as_dict_and_frozen():
    gt = _straight(11, 10.0, heading=0.0)
    r = trajectory_errors(_offset(gt, 0.1, 0.0), gt)
    d = r.as_dict()
    assert list(d) == [f.name for f in dataclasses.fields(TrajectoryErrors)]
    assert isinstance(d["n"], int) and isinstance(d["delta_pos_m"], float)
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.n = 3  # type: ignore[misc]


def test_bad_inputs():
    gt = _straight(11, 10.0, heading=0.0)
    with pytest.raises(ValueError, match="same shape"):
        trajectory_errors(gt[:5], gt)
    with pytest.raises(ValueError, match="estimate_xy_yaw"):
        trajectory_errors(gt[:, :2], gt)
    with pytest.raises(ValueError, match="truth_xy_yaw"):
        trajectory_errors(gt, gt[:, :2])
    with pytest.raises(ValueError, match="at least 2"):
        trajectory_errors(gt[:1], gt[:1])
    for spacing in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="spacing_m"):
            trajectory_errors(gt, gt, spacing_m=spacing)
    bad = gt.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="estimate_xy_yaw.*row 3"):
        trajectory_errors(bad, gt)
    with pytest.raises(ValueError, match="truth_xy_yaw.*row 3"):
        trajectory_errors(gt, bad)
    with pytest.raises(ValueError, match="valid"):
        trajectory_errors(gt, gt, valid=np.ones(5, dtype=bool))
    with pytest.raises(ValueError, match="valid"):
        trajectory_errors(gt, gt, valid=np.ones(11))
    still = np.zeros((5, 3))
    with pytest.raises(ValueError, match="never moves"):
        trajectory_errors(still, still)
    with pytest.raises(ValueError, match="no evaluation point"):
        trajectory_errors(gt, gt, valid=np.zeros(11, dtype=bool))


# -- absolute trajectory error (per pose, after SE(2) alignment) ---------------------------


def _rigid(poses, theta, t):
    c, s = np.cos(theta), np.sin(theta)
    xy = poses[:, :2] @ np.array([[c, s], [-s, c]]) + t
    return np.column_stack([xy, poses[:, 2] + theta])


def test_ate_undoes_a_rigid_motion_and_reports_it():
    from lidarjax.metrics import absolute_trajectory_error, align_se2

    rng = np.random.default_rng(0)
    truth = np.column_stack([np.cumsum(rng.normal(0, 1, (50, 2)), 0), rng.uniform(-3, 3, 50)])
    est = _rigid(truth, -0.7, np.array([3.0, -2.0]))  # truth moved rigidly
    theta, t = align_se2(est, truth)
    np.testing.assert_allclose(theta, 0.7, atol=1e-12)
    ate = absolute_trajectory_error(est, truth)
    assert ate.rmse_m < 1e-12 and ate.n == 50
    np.testing.assert_allclose(ate.aligned[:, :2], truth[:, :2], atol=1e-12)
    raw = absolute_trajectory_error(est, truth, align=False)
    dist = np.linalg.norm(est[:, :2] - truth[:, :2], axis=1)  # brute force
    np.testing.assert_allclose(raw.rmse_m, np.sqrt(np.mean(dist**2)), rtol=1e-12)
    np.testing.assert_allclose(raw.max_m, dist.max(), rtol=1e-12)


def test_ate_alignment_minimises_the_squared_error():
    """No nearby rigid motion does better than the SVD alignment (brute-force check)."""
    from lidarjax.metrics import absolute_trajectory_error

    rng = np.random.default_rng(1)
    truth = np.column_stack([rng.uniform(-10, 10, (40, 2)), np.zeros(40)])
    est = _rigid(truth, 0.3, np.array([1.0, 2.0])) + rng.normal(0, 0.2, (40, 3))
    best = absolute_trajectory_error(est, truth).rmse_m
    for dth in (-1e-3, 1e-3):
        for dt in ([1e-3, 0], [0, -1e-3]):
            ate = absolute_trajectory_error(est, truth)
            moved = _rigid(ate.aligned, dth, np.asarray(dt))
            assert absolute_trajectory_error(moved, truth, align=False).rmse_m > best


def test_ate_masks_and_bad_input():
    from lidarjax.metrics import absolute_trajectory_error

    truth = np.column_stack([np.arange(6.0), np.zeros(6), np.zeros(6)])
    est = truth + [0.1, 0.0, 0.0]
    est[2] = np.nan  # a row without an estimate is skipped, not an error
    ate = absolute_trajectory_error(est, truth, align=False)
    assert ate.n == 5 and np.isnan(ate.errors_m[2])
    np.testing.assert_allclose(ate.rmse_m, 0.1)
    with pytest.raises(ValueError, match="estimate_xy_yaw"):
        absolute_trajectory_error(est[:, :2], truth)
    with pytest.raises(ValueError, match="same shape"):
        absolute_trajectory_error(est[:4], truth)
    with pytest.raises(ValueError, match="valid"):
        absolute_trajectory_error(est, truth, valid=np.ones(3, bool))
    with pytest.raises(ValueError, match="at least 2"):
        absolute_trajectory_error(est, truth, valid=np.eye(6, dtype=bool)[0])
