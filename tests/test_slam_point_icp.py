"""Point-to-line ICP lidar odometry (lidarjax.slam.point_icp_front_end, run_slam's "icp"
chain): normals and nearest neighbours against NumPy brute force, the registration on a
simulated office and a corridor, the chain's blocks, dtype and failures, bad input."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import lidarjax.slam._pipeline as pipeline
import lidarjax.slam._point_icp as picp
from lidarjax.metrics import absolute_trajectory_error
from lidarjax.sim import make_office, simulate_scans, wheel_odometry
from lidarjax.slam import (
    CHAIN_MODELS,
    FrontEndResult,
    Loops,
    PointIcpConfig,
    SlamConfig,
    front_end_pose_graph,
    point_icp_front_end,
    run_slam,
)
from lidarjax.slam._front_end import between_np, compose_np

DRIFT = dict(
    sigma_trans_rel=0.05,
    sigma_rot_per_m=float(np.deg2rad(1.0)),
    heading_bias_per_m=float(np.deg2rad(0.3)),
    sigma_rot_per_rad=0.02,
)
AZ = np.linspace(-np.pi / 2, np.pi / 2, 181)


@pytest.fixture(scope="module")
def office():
    """The office's first lap (100 poses, about 40 m): truth, 1 cm range noise, and the
    issue's drifting odometry."""
    world = make_office(0)
    truth = world.trajectory(100, jitter_m=0.2)
    ranges = simulate_scans(world, truth, AZ, max_range_m=30.0, noise_sigma_m=0.01, seed=0)
    return truth, ranges, wheel_odometry(truth, seed=0, **DRIFT)


def _numpy_normals(ranges, az, cap, cfg):
    """Brute force: each beam's neighbours in the window, the scatter's eigh."""
    n, b = ranges.shape
    h = cfg.normal_half_window
    normals = np.zeros((n, b, 2))
    target = np.zeros((n, b), bool)
    for i in range(n):
        ok = (ranges[i] > 0) & (ranges[i] < cap)
        xy = np.stack([ranges[i] * np.cos(az), ranges[i] * np.sin(az)], 1)
        for k in range(b):
            if not ok[k]:
                continue
            nb = [
                j
                for j in range(max(0, k - h), min(b, k + h + 1))
                if ok[j] and np.sum((xy[j] - xy[k]) ** 2) <= cfg.normal_radius_m**2
            ]
            if len(nb) < 3:
                continue
            pts = xy[nb]
            d = pts - pts.mean(0)
            val, vec = np.linalg.eigh(d.T @ d)
            if val[1] > 0 and val[0] <= cfg.max_flatness * val[1]:
                target[i, k] = True
                normals[i, k] = vec[:, 0]
    return normals, target


def test_scan_points_normals_match_numpy_eigh(office):
    _, ranges, _ = office
    cfg = PointIcpConfig()
    r = ranges[:6].copy()
    r[0, 50:60] = 0.0  # no-returns: no points
    r[1, 100:110] = 25.0  # beyond the cap
    xy, ok, nrm, tgt = picp.scan_points(r, AZ, 20.0, cfg)
    ref_n, ref_t = _numpy_normals(r, AZ, 20.0, cfg)
    np.testing.assert_array_equal(ok, (r > 0) & (r < 20.0))
    np.testing.assert_allclose(xy[ok], np.stack([r * np.cos(AZ), r * np.sin(AZ)], -1)[ok])
    np.testing.assert_array_equal(tgt, ref_t)
    assert tgt.sum() > 0.8 * ok.sum()  # an office of walls: most points are on lines
    dot = np.abs(np.sum(nrm * ref_n, -1))  # a normal's sign is arbitrary
    np.testing.assert_allclose(dot[tgt], 1.0, atol=1e-9)
    assert np.all(nrm[~tgt] == 0)


def test_scan_points_strides_wide_scans():
    cfg = PointIcpConfig(max_points=100)
    az = np.linspace(-np.pi, np.pi, 361, endpoint=False)
    r = np.full((2, 361), 5.0)
    xy, ok, _, tgt = picp.scan_points(r, az, 20.0, cfg)
    assert xy.shape == (2, 91, 2)  # every 4th beam: ceil(361 / 100) = 4
    np.testing.assert_allclose(xy[0, 1], [5 * np.cos(az[4]), 5 * np.sin(az[4])])
    # a circle of 5 m: neighbours 8.7 cm apart bend too little to fail the line test
    assert ok.all() and tgt.all()


def test_nearest_matches_brute_force():
    rng = np.random.default_rng(0)
    p = rng.uniform(-10, 10, (200, 2)).astype(np.float32)
    t = rng.uniform(-10, 10, (777, 2)).astype(np.float32)
    t_ok = rng.random(777) > 0.3
    j, d2 = jax.jit(picp._nearest)(p, t, t_ok)
    j, d2 = np.asarray(j), np.asarray(d2)
    full = np.sum((p[:, None].astype(np.float64) - t[None]) ** 2, -1)
    full[:, ~t_ok] = np.inf
    best = full.min(1)
    assert t_ok[j].all()
    np.testing.assert_allclose(d2, full[np.arange(200), j], rtol=1e-5)
    # the index's bits cost a relative 2^-13 of the squared distance at most
    assert np.all(full[np.arange(200), j] <= best * (1 + 2**-12) + 1e-12)
    assert np.mean(j == full.argmin(1)) > 0.99
    # no target at all: infinite distance
    _, d_none = picp._nearest(p, t, np.zeros(777, bool))
    assert np.all(np.isinf(np.asarray(d_none)))


def _world_targets(ranges, pose, cfg):
    xy, _, nrm, tgt = picp.scan_points(ranges[None], AZ, 20.0, cfg)
    c, s = np.cos(pose[2]), np.sin(pose[2])
    rot = np.array([[c, -s], [s, c]])
    return xy[0] @ rot.T + pose[:2], nrm[0] @ rot.T, tgt[0]


@pytest.mark.parametrize("scan", [31, 53, 73])
def test_register_recovers_a_known_pose(office, scan):
    """A scan against the three before it placed at their true poses, from guesses off
    by up to 0.36 m and 6 degrees: noise-free readings give the true pose within 1.5 mm
    and 0.02 degree (measured 0-1.1 mm: point-to-line treats a corner's points as on a
    line), every guess the same pose; with 1 cm of range noise within 1 cm and 0.1
    degree (measured 1.6-5.3 mm)."""
    truth, noisy, _ = office
    cfg = PointIcpConfig()
    ks = [scan - 3, scan - 2, scan - 1, scan]
    exact = simulate_scans(make_office(0), truth[ks], AZ, max_range_m=30.0, noise_sigma_m=0.0)
    reg = jax.jit(picp.register, static_argnames="cfg")
    f32 = np.float32
    for ranges, tol_m, tol_deg in ((exact, 0.0015, 0.02), (noisy[ks], 0.01, 0.1)):
        parts = [_world_targets(ranges[i], truth[k], cfg) for i, k in enumerate(ks[:3])]
        tgt, tn, tok = (np.concatenate([q[i] for q in parts]) for i in range(3))
        xy, ok, _, _ = picp.scan_points(ranges[3:], AZ, 20.0, cfg)
        found = []
        for off in ((0.2, -0.15, 3.0), (-0.3, 0.1, -6.0), (0.0, 0.0, 0.0)):
            guess = truth[scan] + [off[0], off[1], np.deg2rad(off[2])]
            pose, last, inl = reg(
                guess.astype(f32),
                xy[0].astype(f32),
                ok[0],
                tgt.astype(f32),
                tn.astype(f32),
                tok,
                cfg,
            )
            pose = np.asarray(pose, float)
            assert np.hypot(*(pose[:2] - truth[scan, :2])) < tol_m
            assert abs(pose[2] - truth[scan, 2]) < np.deg2rad(tol_deg)
            assert float(inl) > 0.8
            assert np.all(np.asarray(last) <= [cfg.converged_m, cfg.converged_m, cfg.converged_rad])
            found.append(pose)
        np.testing.assert_allclose(found, [found[-1]] * 3, atol=1e-4)


def test_register_keeps_the_guess_along_a_corridor():
    """Two parallel walls: the lines fix the cross-track position and the heading; the
    along-track offset of the guess stays (no drift along the null direction)."""
    cfg = PointIcpConfig()
    xs = np.arange(-10, 10, 0.05)
    walls = np.concatenate([np.stack([xs, np.full_like(xs, y)], 1) for y in (-1.0, 1.2)])
    normals = np.tile([0.0, 1.0], (len(walls), 1))
    truth = np.array([0.3, 0.1, np.deg2rad(2.0)])
    c, s = np.cos(truth[2]), np.sin(truth[2])
    src = (walls[::3] - truth[:2]) @ np.array([[c, -s], [s, c]])  # in the scan's frame
    src = src[np.abs(src[:, 0]) < 8]
    guess = truth + [0.25, -0.08, np.deg2rad(-1.5)]
    f32 = np.float32
    pose, _, _ = picp.register(
        guess.astype(f32),
        src.astype(f32),
        np.ones(len(src), bool),
        walls.astype(f32),
        normals.astype(f32),
        np.ones(len(walls), bool),
        cfg,
    )
    pose = np.asarray(pose, float)
    assert np.all(np.isfinite(pose))
    assert abs(pose[1] - truth[1]) < 1e-3 and abs(pose[2] - truth[2]) < 1e-4
    assert abs(pose[0] - guess[0]) < 0.02  # along the corridor: the guess's x


def test_chain_on_the_office_lap(office):
    """A whole lap (100 scans) from the drifting odometry: every scan registered, the
    chain within 1 cm RMSE of the truth (the odometry: 0.73 m)."""
    truth, ranges, odo = office
    r = point_icp_front_end(ranges, AZ, odo)
    assert r.poses.shape == (100, 3) and r.registered.shape == (100,)
    np.testing.assert_array_equal(r.poses[0], odo[0])
    assert r.registered.all()
    ate = absolute_trajectory_error(r.poses, truth)
    assert absolute_trajectory_error(odo, truth).rmse_m > 0.5
    assert ate.rmse_m < 0.01 and ate.max_m < 0.03  # measured 0.0068 m
    d = between_np(r.poses[:-1], r.poses[1:]) - between_np(truth[:-1], truth[1:])
    assert np.median(np.hypot(d[:, 0], d[:, 1])) < 0.006  # measured 3.2 mm
    assert np.all(np.abs(r.poses[:, 2]) <= np.pi)


def test_chain_is_the_same_in_any_block_size_and_dtype(office, monkeypatch):
    """Blocks of 16 scans (padded last block) give the chain of one 128-scan block, bit
    for bit; so does JAX's float32 default (the chain runs in float32 either way)."""
    truth, ranges, odo = office
    a = point_icp_front_end(ranges[:70], AZ, odo[:70])
    monkeypatch.setattr(picp, "BLOCK_SCANS", 16)
    b = point_icp_front_end(ranges[:70], AZ, odo[:70])
    np.testing.assert_array_equal(a.poses, b.poses)
    np.testing.assert_array_equal(a.registered, b.registered)
    with jax.enable_x64(False):
        c = point_icp_front_end(ranges[:70], AZ, odo[:70])
    np.testing.assert_array_equal(a.poses, c.poses)


def test_chain_marks_a_failed_scan_and_takes_the_odometry(office):
    """A scan without returns and a scan from elsewhere (another place's readings) are
    not registered; their increments are the odometry's."""
    truth, ranges, odo = office
    r = ranges[:30].copy()
    r[10] = 0.0  # no returns
    r[20] = ranges[80]  # another part of the office
    res = point_icp_front_end(r, AZ, odo[:30])
    assert not res.registered[10] and not res.registered[20]
    assert res.registered[[k for k in range(30) if k not in (10, 20)]].all()
    for k in (10, 20):
        want = compose_np(res.poses[k - 1], between_np(odo[k - 1], odo[k]))
        np.testing.assert_allclose(res.poses[k], want, atol=1e-5)
    # the scans after the failures are matched again
    ate = absolute_trajectory_error(res.poses, truth[:30])
    assert ate.rmse_m < 0.05


def test_one_scan_is_its_odometry_pose():
    r = point_icp_front_end(np.full((1, 5), 3.0), np.linspace(-1, 1, 5), [[1.0, 2.0, 0.5]])
    np.testing.assert_array_equal(r.poses, [[1.0, 2.0, 0.5]])
    assert r.registered.tolist() == [True]


@pytest.mark.parametrize(
    "field, value",
    [
        ("submap_scans", 0),
        ("max_points", 4),
        ("iterations", 1.5),
        ("normal_half_window", True),
        ("inlier_m", 0.0),
        ("cauchy_m", -0.1),
        ("cauchy_m", float("nan")),
        ("min_inlier_fraction", 1.5),
        ("radii_m", ()),
        ("radii_m", (1.0, -0.3)),
        ("radii_m", [1.0]),
    ],
)
def test_bad_config_raises(field, value):
    with pytest.raises(ValueError, match=field):
        PointIcpConfig(**{field: value})


def test_cauchy_zero_is_off_and_bad_inputs_raise():
    assert PointIcpConfig(cauchy_m=0.0).cauchy_m == 0.0
    az = np.linspace(-1, 1, 5)
    ok = dict(ranges_m=np.full((3, 5), 3.0), azimuths_rad=az, odometry_xy_yaw=np.zeros((3, 3)))
    for what, bad in (
        ("ranges_m", dict(ranges_m=np.full((3, 5), -1.0))),
        ("ranges_m", dict(ranges_m=np.full((3, 5), np.nan))),
        ("azimuths_rad", dict(azimuths_rad=az[:4])),
        ("odometry_xy_yaw", dict(odometry_xy_yaw=np.zeros((2, 3)))),
        ("range_cap_m", dict(range_cap_m=0.0)),
        ("cfg", dict(cfg=SlamConfig())),
    ):
        with pytest.raises(ValueError, match=what):
            point_icp_front_end(**{**ok, **bad})
    with pytest.raises(ValueError, match="icp"):
        SlamConfig(icp="fast")


def test_icp_is_a_chain_model_of_run_slam(monkeypatch):
    """extra_chain_models ("endpoint", "icp"): the point-to-line chain (on the readings
    below the front end's range cap, with SlamConfig.icp) joins the pose graph where it
    registered, as a masked chain."""
    assert CHAIN_MODELS == ("decay_rate", "endpoint", "icp", "gicp")
    rng = np.random.default_rng(3)
    n = 30
    inc = np.stack([rng.uniform(0.3, 0.6, n - 1), np.zeros(n - 1), rng.normal(0, 0.1, n - 1)], 1)
    truth = [np.zeros(3)]
    for u in inc:
        truth.append(compose_np(truth[-1], u))
    truth = np.array(truth)
    a, b, c = (truth + rng.normal(0, 0.005, truth.shape) for _ in range(3))
    reg = np.ones(n, bool)
    reg[[5, 17]] = False
    seen = {}

    def fake_chain(rng_, az, odometry, cap, cfg, progress):
        seen.update(cap=cap, cfg=cfg, shape=rng_.shape)
        return c, reg, 0.125

    def fake_front_end(rng_, azimuths, odometry, fcfg, progress=False):
        p = a if fcfg.model == "decay_rate" else b
        k = rng_.shape[0]
        return FrontEndResult(p, np.zeros(k), 0.5, np.zeros(k), None, None, np.ones(k, bool))

    empty = Loops(np.zeros((0, 2), np.int64), np.zeros((0, 3)), 0)
    monkeypatch.setattr(pipeline, "point_icp_chain", fake_chain)
    monkeypatch.setattr(pipeline, "run_front_end", fake_front_end)
    monkeypatch.setattr(pipeline, "find_loops", lambda *a_, **k: empty)
    icfg = PointIcpConfig(submap_scans=5)
    cfg = SlamConfig(
        back_end="none", loop_rounds=1, extra_chain_models=("endpoint", "icp"), icp=icfg
    )
    res = run_slam(np.full((n, 4), 5.0), np.linspace(-1, 1, 4), truth, cfg)
    assert seen == {"cap": cfg.front.range_cap_m, "cfg": icfg, "shape": (n, 4)}
    assert res.seconds["extra_front_ends"] == 0.5 + 0.125
    np.testing.assert_array_equal(res.extra_front_end_poses[1], c)
    assert res.extra_chain_valid[1].tolist() == reg[1:].tolist()
    pg = front_end_pose_graph(
        a, res.odometry, empty, cfg, extra_chains=[b, c], extra_chain_valid=[None, reg[1:]]
    )
    np.testing.assert_allclose(res.pose_graph_poses, np.asarray(pg.poses), atol=1e-9)
    np.testing.assert_array_equal(np.isnan(res.chain_weights[2]), ~reg[1:])
