"""The odometry's systematic heading errors (lidarjax.slam.calibrate_odometry) and their
use in run_slam's pose graph."""

import numpy as np
import pytest

import lidarjax.slam._pipeline as pipeline
from lidarjax.slam import (
    FrontEndConfig,
    FrontEndResult,
    Loops,
    OdometryCalibration,
    SlamConfig,
    calibrate_odometry,
    front_end_pose_graph,
    odometry_sigmas,
    run_slam,
)
from lidarjax.slam._front_end import between_np, compose_np

BETA, GAMMA = np.deg2rad(0.3), 0.03  # rad/m; per radian of the odometry's turn


def _chain(p0, inc):
    out = [np.asarray(p0, float)]
    for u in inc:
        out.append(compose_np(out[-1], u))
    return np.array(out)


def _truth(n=300, seed=0):
    """A wandering path: 0.2-1 m steps, turns of up to +-0.5 rad."""
    r = np.random.default_rng(seed)
    d = r.uniform(0.2, 1.0, n - 1)
    inc = np.stack([d, r.normal(0, 0.02, n - 1), r.uniform(-0.5, 0.5, n - 1)], 1)
    return _chain([1.0, -2.0, 0.3], inc)


def _odometry(truth, beta=BETA, gamma=GAMMA):
    """Odometry whose heading increments obey the calibration's model exactly:
    ``dyaw_odo - dyaw = beta d + gamma dyaw_odo`` (translations exact)."""
    inc = between_np(truth[:-1], truth[1:])
    d = np.hypot(inc[:, 0], inc[:, 1])
    inc[:, 2] = (inc[:, 2] + beta * d) / (1.0 - gamma)
    return _chain(truth[0], inc)


def _reference_fit(fe, odo, cfg, prior=(0.05, 0.2), stderr=False):
    """Weighted least squares with the prior, no robust kernel: an independent closed
    form through np.linalg.lstsq on the whitened system (and, with ``stderr``, its
    standard errors from the residuals' spread)."""
    a, b = between_np(odo[:-1], odo[1:]), between_np(fe[:-1], fe[1:])
    d = np.hypot(a[:, 0], a[:, 1])
    r = np.arctan2(np.sin(a[:, 2] - b[:, 2]), np.cos(a[:, 2] - b[:, 2]))
    s = odometry_sigmas(a, cfg)[:, 2]
    x = np.stack([d, a[:, 2]], 1) / s[:, None]
    x = np.concatenate([x, np.diag([1 / prior[0], 1 / prior[1]])])
    y = np.concatenate([r / s, [0.0, 0.0]])
    beta = np.linalg.lstsq(x, y, rcond=None)[0]
    if not stderr:
        return beta
    sigma2 = np.sum((y - x @ beta)[:-2] ** 2) / (len(y) - 4)
    return beta, np.sqrt(np.diag(np.linalg.inv(x.T @ x)) * sigma2)


def test_calibration_recovers_systematic_heading_errors():
    truth = _truth()
    odo = _odometry(truth)
    cfg = FrontEndConfig()
    c = calibrate_odometry(truth, odo, cfg)
    assert isinstance(c, OdometryCalibration) and c.n_used == len(truth) - 1
    # exact data: only the weak prior's shrinkage is left (well under 1 %)
    assert c.heading_rad_per_m == pytest.approx(BETA, rel=1e-2)
    assert c.heading_gain == pytest.approx(GAMMA, rel=1e-2)
    # with Gaussian match noise (0.3 deg) the kernel costs little efficiency: the fit
    # agrees with closed-form weighted least squares within its standard error
    inc = between_np(truth[:-1], truth[1:])
    inc[:, 2] += np.random.default_rng(7).normal(0.0, np.deg2rad(0.3), len(inc))
    noisy = _chain(truth[0], inc)
    ls, se = _reference_fit(noisy, odo, cfg, stderr=True)
    got = calibrate_odometry(noisy, odo, cfg)
    diff = np.array([got.heading_rad_per_m, got.heading_gain]) - ls
    assert np.all(np.abs(diff) < se)
    assert np.all(np.abs(ls - [BETA, GAMMA]) < 3 * se)
    # the corrected odometry's increments are the truth's up to that shrinkage, and far
    # closer than the raw odometry's
    raw = between_np(odo[:-1], odo[1:])[:, 2] - between_np(truth[:-1], truth[1:])[:, 2]
    fixed = c.apply(odo)
    err = between_np(fixed[:-1], fixed[1:])[:, 2] - between_np(truth[:-1], truth[1:])[:, 2]
    assert np.abs(err).max() < 0.01 * np.abs(raw).max()
    np.testing.assert_allclose(fixed[0], odo[0])
    # translations are left alone
    np.testing.assert_allclose(
        between_np(fixed[:-1], fixed[1:])[:, :2], between_np(odo[:-1], odo[1:])[:, :2], atol=1e-12
    )


def test_exact_calibration_gives_the_truth_back():
    truth = _truth(seed=1)
    odo = _odometry(truth)
    fixed = OdometryCalibration(BETA, GAMMA).apply(odo)
    np.testing.assert_allclose(
        between_np(fixed[:-1], fixed[1:]), between_np(truth[:-1], truth[1:]), atol=1e-12
    )
    # a zero calibration is the identity
    np.testing.assert_allclose(OdometryCalibration().apply(odo), odo, atol=1e-12)


def test_calibration_resists_failed_matches_and_honours_valid():
    truth = _truth(seed=2)
    odo = _odometry(truth)
    inc = between_np(truth[:-1], truth[1:])
    bad = np.zeros(len(inc), bool)
    bad[::15] = True  # 7 % of the matches off by 10-20 degrees, all one way
    inc[bad, 2] += np.deg2rad(np.linspace(10, 20, bad.sum()))
    fe = _chain(truth[0], inc)
    cfg = FrontEndConfig()
    plain = _reference_fit(fe, odo, cfg)
    robust = calibrate_odometry(fe, odo, cfg)
    # least squares is dragged off by the failures; the robust kernel is not
    assert abs(plain[0] - BETA) > 0.3 * BETA
    assert robust.heading_rad_per_m == pytest.approx(BETA, rel=0.1)
    assert robust.heading_gain == pytest.approx(GAMMA, rel=0.1)
    # leaving the failures out gives the clean fit of the remaining increments
    c = calibrate_odometry(fe, odo, cfg, valid=~bad)
    assert c.n_used == int((~bad).sum())
    assert c.heading_rad_per_m == pytest.approx(BETA, rel=1e-2)
    assert c.heading_gain == pytest.approx(GAMMA, rel=1e-2)


def test_calibration_without_motion_stays_at_zero():
    # a robot that never moves or turns: the prior keeps both terms at zero (no NaN)
    still = np.tile([2.0, 1.0, 0.5], (20, 1))
    c = calibrate_odometry(still, still)
    assert (c.heading_rad_per_m, c.heading_gain) == (0.0, 0.0)
    np.testing.assert_allclose(c.apply(still), still)


@pytest.mark.parametrize(
    ("args", "kwargs", "name"),
    [
        ((np.zeros((1, 3)), np.zeros((1, 3))), {}, "front_end_xy_yaw"),
        ((np.zeros((5, 2)), np.zeros((5, 3))), {}, "front_end_xy_yaw"),
        ((np.zeros((5, 3)), np.full((5, 3), np.nan)), {}, "odometry_xy_yaw"),
        ((np.zeros((5, 3)), np.zeros((6, 3))), {}, "odometry_xy_yaw"),
        ((np.zeros((5, 3)), np.zeros((5, 3))), {"valid": np.ones(5, bool)}, "valid"),
        ((np.zeros((5, 3)), np.zeros((5, 3))), {"valid": np.ones(4)}, "valid"),
        ((np.zeros((5, 3)), np.zeros((5, 3))), {"prior_sigma_per_m": 0.0}, "prior_sigma_per_m"),
        ((np.zeros((5, 3)), np.zeros((5, 3))), {"prior_sigma_gain": np.inf}, "prior_sigma_gain"),
        ((np.zeros((5, 3)), np.zeros((5, 3))), {"kernel_width": True}, "kernel_width"),
        ((np.zeros((5, 3)), np.zeros((5, 3))), {"iterations": 0}, "iterations"),
    ],
)
def test_calibration_rejects_bad_input(args, kwargs, name):
    with pytest.raises(ValueError, match=name):
        calibrate_odometry(*args, **kwargs)


def test_bad_input_of_apply_and_config():
    with pytest.raises(ValueError, match="odometry_xy_yaw"):
        OdometryCalibration(0.01, 0.0).apply(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="increments"):
        OdometryCalibration(0.01, 0.0).increments(np.full((4, 3), np.nan))
    with pytest.raises(ValueError, match="calibrate_odometry"):
        SlamConfig(calibrate_odometry=1)


@pytest.mark.parametrize("calibrate", [True, False])
def test_run_slam_gives_the_pose_graph_the_calibrated_odometry(monkeypatch, calibrate):
    truth = _truth(n=80, seed=3)
    odo = _odometry(truth)
    plausible = np.ones(len(truth), bool)
    plausible[40] = False  # a fallback: its increment is left out of the fit

    def fake_front_end(rng, azimuths, odometry, cfg, progress=False):
        n = rng.shape[0]
        return FrontEndResult(truth, np.zeros(n), 0.0, np.zeros(n), None, None, plausible)

    e = np.array([[2, 70], [5, 75]])
    loops = Loops(e, between_np(truth[e[:, 0]], truth[e[:, 1]]), 2)
    monkeypatch.setattr(pipeline, "run_front_end", fake_front_end)
    monkeypatch.setattr(pipeline, "find_loops", lambda *a, **k: loops)
    cfg = SlamConfig(
        back_end="none",
        loop_rounds=1,
        calibrate_odometry=calibrate,
        extra_chain_models=("endpoint",),  # no ICP chain on these fake readings
    )
    ranges, az = np.full((len(truth), 4), 5.0), np.linspace(-1, 1, 4)
    r = run_slam(ranges, az, odo, cfg)
    if calibrate:
        c = r.odometry_calibration
        assert c.n_used == len(truth) - 2
        assert c.heading_rad_per_m == pytest.approx(BETA, rel=0.05)
        np.testing.assert_allclose(r.odometry, c.apply(odo))
    else:
        assert r.odometry_calibration is None
        np.testing.assert_allclose(r.odometry, odo)
    # the pose graph is the one over that odometry
    assert len(r.extra_front_end_poses) == 1  # the endpoint chain (the same here)
    pg = front_end_pose_graph(truth, r.odometry, loops, cfg, extra_chains=r.extra_front_end_poses)
    np.testing.assert_allclose(r.pose_graph_poses, np.asarray(pg.poses), atol=1e-9)
