"""Tests for the seeded urban world simulator (lidarjax.sim: _lidar, _urban_world,
_urban_placement, _urban_cast, _odometry)."""

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lidarjax.datasets import load_urban_trajectory
from lidarjax.sim import (
    BOX_KINDS,
    HDL32E_ELEVATIONS_DEG,
    POLE_KINDS,
    LidarSpec,
    UrbanWorld,
    hdl32e,
    make_urban_world,
    simulate_urban_scan,
    simulate_urban_scans,
    urban_session,
    wheel_odometry,
)

BARREL = POLE_KINDS.index("barrel")


def hand_world(poles=(), boxes=(), crowns=()):
    """World from ``(x, y, r, h)`` poles, ``(cx, cy, cz, hx, hy, hz, yaw)`` boxes and
    ``(cx, cy, cz, r, rate)`` crowns."""
    poles = np.array(poles, dtype=float).reshape(-1, 4)
    boxes = np.array(boxes, dtype=float).reshape(-1, 7)
    crowns = np.array(crowns, dtype=float).reshape(-1, 5)
    return UrbanWorld(
        pole_xy=poles[:, :2],
        pole_radius_m=poles[:, 2],
        pole_height_m=poles[:, 3],
        pole_kind=np.zeros(len(poles), int),
        pole_id=np.arange(len(poles)),
        box_center=boxes[:, :3],
        box_half_size=boxes[:, 3:6],
        box_yaw=boxes[:, 6],
        box_kind=np.zeros(len(boxes), int),
        crown_center=crowns[:, :3],
        crown_radius_m=crowns[:, 3],
        crown_rate_per_m=crowns[:, 4],
        crown_pole_id=-np.ones(len(crowns), int),
        road_xy=np.array([[-500.0, -500.0], [-499.0, -500.0]]),
        road_half_width_m=np.array([5.0, 5.0]),
        road_new=np.array([True, True]),
        barrel_row_xy=np.zeros((2, 2)),
        barrel_row_normal=np.array([0.0, 1.0]),
    )


def flat_lidar(elev_deg=(0.0,), n_az=4, **kw):
    kw.setdefault("range_noise_m", 0.0)
    kw.setdefault("min_range_m", 0.1)
    return LidarSpec(elevations_rad=np.deg2rad(np.asarray(elev_deg, float)), n_azimuths=n_az, **kw)


def scan_ranges(world, lidar, pose=(0.0, 0.0, 0.0), seed=0):
    sc = simulate_urban_scan(world, np.array(pose), lidar, seed=seed)
    return sc.ranges_m.reshape(lidar.n_rings, lidar.n_azimuths)


# ------------------------------------------------------------------ analytic ray casting


def test_analytic_cylinder_box_sphere_and_miss():
    world = hand_world(
        poles=[(10.0, 0.0, 0.5, 5.0)],
        boxes=[(0.0, 10.0, 2.0, 1.0, 2.0, 3.0, np.pi / 2)],  # yawed: y extent is hx = 1
        crowns=[(0.0, -10.0, 1.73, 2.0, 1e7)],  # practically solid
    )
    r = scan_ranges(world, flat_lidar())[0]
    np.testing.assert_allclose(r[0], 9.5, atol=1e-4)  # forward: cylinder surface
    np.testing.assert_allclose(r[1], 9.0, atol=1e-4)  # left: box face
    assert r[2] == np.inf  # backward: nothing (horizontal ray, no ground)
    np.testing.assert_allclose(r[3], 8.0, atol=1e-4)  # right: sphere surface


def test_analytic_rotated_box_corner_and_vehicle_yaw():
    world = hand_world(boxes=[(-10.0, 0.0, 1.0, 1.0, 1.0, 3.0, np.pi / 4)])
    r = scan_ranges(world, flat_lidar())[0]
    np.testing.assert_allclose(r[2], 10.0 - math.sqrt(2.0), atol=1e-4)
    # rotate the vehicle by 180 deg: the box is now straight ahead
    r = scan_ranges(world, flat_lidar(), pose=(0.0, 0.0, np.pi))[0]
    np.testing.assert_allclose(r[0], 10.0 - math.sqrt(2.0), atol=1e-4)
    # translate the vehicle: range shrinks accordingly
    r = scan_ranges(world, flat_lidar(), pose=(-3.0, 0.0, np.pi))[0]
    np.testing.assert_allclose(r[0], 7.0 - math.sqrt(2.0), atol=1e-4)


def test_analytic_ground_and_cylinder_top_cap():
    world = hand_world(poles=[(5.0, 0.0, 1.0, 1.0)])  # 1 m high barrel-like cylinder
    el = -math.degrees(math.atan2(0.73, 5.0))  # reaches z = 1 exactly above the axis
    lidar = flat_lidar(elev_deg=(-10.0, el), n_az=4)
    r = scan_ranges(world, lidar)
    ground = 1.73 / math.sin(math.radians(10.0))
    np.testing.assert_allclose(r[0, 1:], ground, atol=1e-4)
    np.testing.assert_allclose(r[1, 0], math.hypot(5.0, 0.73), atol=1e-4)  # top cap
    # ray over the top of a low cylinder hits the ground behind it
    low = hand_world(poles=[(5.0, 0.0, 0.3, 0.2)])
    r = scan_ranges(low, flat_lidar(elev_deg=(-10.0,)))
    np.testing.assert_allclose(r[0, 0], ground, atol=1e-4)


def test_range_limits():
    world = hand_world(poles=[(0.5, 0.0, 0.1, 5.0), (0.0, 100.0, 0.5, 5.0)])
    r = scan_ranges(world, flat_lidar(min_range_m=1.0, max_range_m=80.0))[0]
    assert r[0] == np.inf  # 0.4 m < min range, blocks everything behind
    assert r[1] == np.inf  # 99.5 m > max range
    r = scan_ranges(world, flat_lidar(min_range_m=0.1, max_range_m=120.0))[0]
    np.testing.assert_allclose(r[:2], [0.4, 99.5], atol=1e-4)


def _ref_ray(d, world, h):
    """Float64 nearest hit of one ray from (0, 0, h) in the world frame (pose at origin)."""
    best = -h / d[2] if d[2] < 0 else np.inf
    for (cx, cy), r, top in zip(world.pole_xy, world.pole_radius_m, world.pole_height_m):
        a = d[0] ** 2 + d[1] ** 2
        b = d[0] * cx + d[1] * cy
        c = cx**2 + cy**2 - r**2
        disc = b * b - a * c
        if disc < 0:
            continue
        t1, t2 = (b - math.sqrt(disc)) / a, (b + math.sqrt(disc)) / a
        za, zb = (0 - h) / d[2], (top - h) / d[2]
        t_in, t_out = max(t1, min(za, zb)), min(t2, max(za, zb))
        if t_in <= t_out and t_in > 0:
            best = min(best, t_in)
    for ctr, hs, yaw in zip(world.box_center, world.box_half_size, world.box_yaw):
        c, s = math.cos(yaw), math.sin(yaw)
        rot = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])
        o = rot @ (np.array([0, 0, h]) - ctr)
        u = rot @ d
        t_lo = (-hs - o) / u
        t_hi = (hs - o) / u
        t_in, t_out = np.minimum(t_lo, t_hi).max(), np.maximum(t_lo, t_hi).min()
        if t_in <= t_out and t_in > 0:
            best = min(best, t_in)
    for ctr, r in zip(world.crown_center, world.crown_radius_m):
        q = ctr - np.array([0, 0, h])
        tm = d @ q
        disc = r * r - (q @ q - tm * tm)
        if disc > 0 and tm - math.sqrt(disc) > 0:
            best = min(best, tm - math.sqrt(disc))
    return best


def test_kernel_matches_numpy_reference_on_random_world():
    rng = np.random.default_rng(3)

    def ring_positions(n, lo, hi):
        rad, ang = rng.uniform(lo, hi, n), rng.uniform(-np.pi, np.pi, n)
        return rad * np.cos(ang), rad * np.sin(ang)

    px, py = ring_positions(12, 3.0, 30.0)
    poles = np.column_stack([px, py, rng.uniform(0.05, 0.6, 12), rng.uniform(0.5, 8.0, 12)])
    bx, by = ring_positions(8, 8.0, 40.0)
    boxes = np.column_stack(
        [bx, by, rng.uniform(0.5, 3, 8), rng.uniform(0.3, 4, (8, 3)), rng.uniform(-3, 3, 8)]
    )
    sx, sy = ring_positions(5, 6.0, 30.0)
    crowns = np.column_stack(
        [sx, sy, rng.uniform(1, 6, 5), rng.uniform(0.5, 2.5, 5), 1e7 * np.ones(5)]
    )
    world = hand_world(poles, boxes, crowns)
    lidar = flat_lidar(elev_deg=np.linspace(-25.0, 8.0, 8), n_az=48, max_range_m=1e3)
    sc = simulate_urban_scan(world, np.zeros(3), lidar, seed=0)
    ref = np.array([_ref_ray(d, world, lidar.mount_height_m) for d in sc.directions])
    fin = np.isfinite(ref)
    np.testing.assert_array_equal(np.isfinite(sc.ranges_m), fin)
    assert fin.sum() > 200
    np.testing.assert_allclose(sc.ranges_m[fin], ref[fin], atol=1e-4, rtol=0)
    assert (sc.ranges_m[fin] < ref[fin] + 1e-4).all()


# ------------------------------------------------------------------ permeable crowns


def _crown_setup(rate):
    # sensor 50 m up, so the ground is far out of range; crown at 10 m ahead
    world = hand_world(crowns=[(10.0, 0.0, 50.0, 2.0, rate)])
    lidar = flat_lidar(elev_deg=np.linspace(-10.0, 10.0, 41), n_az=360, mount_height_m=50.0)
    return world, lidar


def test_crown_solid_and_invisible_limits():
    world, lidar = _crown_setup(1e7)
    sc = simulate_urban_scan(world, np.zeros(3), lidar, seed=0)
    q = np.array([10.0, 0.0, 0.0])
    tm = sc.directions @ q
    disc = 4.0 - (q @ q - tm**2)
    hits = (disc > 1e-3) & (tm > 0)
    np.testing.assert_allclose(sc.ranges_m[hits], tm[hits] - np.sqrt(disc[hits]), atol=1e-4)
    assert np.isinf(sc.ranges_m[(disc < -1e-3) | (tm < 0)]).all()
    world, lidar = _crown_setup(0.0)
    assert np.isinf(simulate_urban_scan(world, np.zeros(3), lidar, seed=0).ranges_m).all()


def test_crown_reflection_fraction_matches_decay_model():
    rate = 0.3
    world, lidar = _crown_setup(rate)
    q = np.array([10.0, 0.0, 0.0])
    observed, expected, var = 0, 0.0, 0.0
    for seed in range(3):
        sc = simulate_urban_scan(world, np.zeros(3), lidar, seed=seed)
        tm = sc.directions @ q
        disc = 4.0 - (q @ q - tm**2)
        through = (disc > 1e-6) & (tm > 0)
        p = 1 - np.exp(-rate * 2 * np.sqrt(disc[through]))
        observed += int(np.isfinite(sc.ranges_m[through]).sum())
        expected += p.sum()
        var += (p * (1 - p)).sum()
        # reflections lie inside the sphere
        pts = sc.points()
        assert (np.linalg.norm(pts - q, axis=1) <= 2.0 + 1e-3).all()
    assert var > 100
    assert abs(observed - expected) < 4 * math.sqrt(var)


# ------------------------------------------------------------------ trajectory


@pytest.fixture(scope="module")
def traj():
    return load_urban_trajectory()


@pytest.fixture(scope="module")
def world(traj):
    return make_urban_world(traj, seed=0)


# ------------------------------------------------------------------ world and sessions


def _dense_route(traj):
    xy = traj.xy_yaw[:, :2]
    seg = np.diff(xy, axis=0)
    n = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / 0.05)).astype(int)
    pts = [xy[i] + np.linspace(0, 1, k, endpoint=False)[:, None] * seg[i] for i, k in enumerate(n)]
    return np.vstack([*pts, xy[-1:]])


def _box_clearance(world, tree, route):
    out = []
    for ctr, hs, yaw in zip(world.box_center, world.box_half_size, world.box_yaw):
        idx = tree.query_ball_point(ctr[:2], math.hypot(hs[0], hs[1]) + 3.0)
        if not idx:
            continue
        p = route[idx] - ctr[:2]
        c, s = math.cos(yaw), math.sin(yaw)
        u = np.abs(c * p[:, 0] + s * p[:, 1]) - hs[0]
        v = np.abs(-s * p[:, 0] + c * p[:, 1]) - hs[1]
        out.append(np.hypot(np.maximum(u, 0), np.maximum(v, 0)).min())
    return np.array(out + [np.inf])


def test_world_clearance_and_sizes(traj, world):
    route = _dense_route(traj)
    tree = cKDTree(route)
    d_pole = tree.query(world.pole_xy)[0] - world.pole_radius_m
    assert d_pole.min() >= 2.5
    d_crown = tree.query(world.crown_center[:, :2])[0] - world.crown_radius_m
    assert d_crown.min() >= 2.5
    assert _box_clearance(world, tree, route).min() >= 2.5
    dia = 2 * world.pole_radius_m
    kinds = {
        "street_lamp": (0.15, 0.3, 6, 9),
        "sign_post": (0.06, 0.12, 2, 3.5),
        "traffic_light": (0.2, 0.35, 4, 7),
        "tree_trunk": (0.2, 0.6, 3, 5),
        "barrel": (0.5, 0.6, 1.0, 1.2),
    }
    for k, name in enumerate(POLE_KINDS):
        m = world.pole_kind == k
        assert m.any(), name
        d_lo, d_hi, h_lo, h_hi = kinds[name]
        assert (dia[m] >= d_lo).all() and (dia[m] <= d_hi).all(), name
        assert (world.pole_height_m[m] >= h_lo).all() and (world.pole_height_m[m] <= h_hi).all()
    assert set(np.unique(world.box_kind)) == set(range(len(BOX_KINDS)))
    assert len(np.unique(world.pole_id)) == world.n_poles
    # density: about one pole every 10-15 m per side on newly generated road
    new_km = world.road_new.sum() * 0.5 / 1000
    non_barrel = (world.pole_kind != BARREL).sum()
    assert 2 * new_km * 1000 / 20 < non_barrel < 2 * new_km * 1000 / 8
    # no duplicates on revisits: poles are well separated
    dd, _ = cKDTree(world.pole_xy).query(world.pole_xy, k=2)
    assert dd[:, 1].min() > 1.0


def test_world_deterministic(traj, world):
    again = make_urban_world(traj, seed=0)
    for f in ("pole_xy", "pole_radius_m", "box_center", "box_yaw", "crown_center", "pole_id"):
        np.testing.assert_array_equal(getattr(again, f), getattr(world, f))
    other = make_urban_world(traj, seed=1)
    assert other.n_poles != world.n_poles or not np.allclose(other.pole_xy, world.pole_xy)


def test_barrel_row(world):
    m = world.pole_kind == BARREL
    assert 6 <= m.sum() <= 10
    xy = world.pole_xy[m]
    gaps = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    np.testing.assert_allclose(gaps, 3.0, atol=1e-9)
    d = (xy[-1] - xy[0]) / np.linalg.norm(xy[-1] - xy[0])
    np.testing.assert_allclose(abs(d @ world.barrel_row_normal), 0.0, atol=1e-9)
    # the only poles in the region
    others = world.pole_xy[~m]
    dist = np.linalg.norm(others[:, None] - xy[None], axis=2).min(axis=1)
    assert dist.min() > 10.0


def test_sessions(world):
    s0 = urban_session(world, 0, seed=0)
    np.testing.assert_array_equal(s0.pole_xy, world.pole_xy)
    np.testing.assert_array_equal(s0.pole_id, world.pole_id)
    s1 = urban_session(world, 1, seed=0)
    again = urban_session(world, 1, seed=0)
    np.testing.assert_array_equal(s1.pole_xy, again.pole_xy)
    np.testing.assert_array_equal(s1.box_center, again.box_center)
    kept = np.isin(world.pole_id, s1.pole_id)
    assert 0 < (~kept).sum() < 0.15 * world.n_poles
    new = ~np.isin(s1.pole_id, world.pole_id)
    assert 0 < new.sum() < 0.15 * world.n_poles
    assert (s1.pole_id[new] >= 100_000).all()
    assert (s1.pole_kind[new] != BARREL).all()
    # kept poles did not move; parked cars were re-sampled; facades kept
    common = np.isin(s1.pole_id, world.pole_id)
    np.testing.assert_array_equal(s1.pole_xy[common], world.pole_xy[kept])
    fac = BOX_KINDS.index("facade")
    np.testing.assert_array_equal(
        s1.box_center[s1.box_kind == fac], world.box_center[world.box_kind == fac]
    )
    car = BOX_KINDS.index("parked_car")
    assert not np.array_equal(
        s1.box_center[s1.box_kind == car], world.box_center[world.box_kind == car]
    )


def test_barrel_session_shift(world):
    s2 = urban_session(
        world, 2, seed=0, barrel_session=2, barrel_shift_m=3.0, p_remove=0.0, p_add=0.0
    )
    assert s2.n_poles == world.n_poles
    np.testing.assert_array_equal(s2.pole_id, world.pole_id)
    b = world.pole_kind == BARREL
    disp = s2.pole_xy - world.pole_xy
    np.testing.assert_array_equal(disp[~b], 0.0)
    n = world.barrel_row_normal
    along = (world.barrel_row_xy[1] - world.barrel_row_xy[0]) / np.linalg.norm(
        world.barrel_row_xy[1] - world.barrel_row_xy[0]
    )
    np.testing.assert_allclose(disp[b] @ n, 3.0, atol=1e-9)
    np.testing.assert_allclose(disp[b] @ along, 0.0, atol=1e-9)
    # the shifted barrels move away from the road
    route = cKDTree(world.road_xy)
    assert (route.query(s2.pole_xy[b])[0] > route.query(world.pole_xy[b])[0] + 2.0).all()
    s3 = urban_session(world, 3, seed=0, barrel_session=2)
    np.testing.assert_array_equal(s3.pole_xy[s3.pole_kind == BARREL], world.pole_xy[b])


# ------------------------------------------------------------------ odometry


def test_wheel_odometry():
    n = 1001
    gt = np.column_stack([np.arange(n, dtype=float), np.zeros(n), np.zeros(n)])
    errs = []
    for seed in range(5):
        odo = wheel_odometry(gt, seed=seed)
        np.testing.assert_array_equal(odo[0], gt[0])
        errs.append(np.linalg.norm(odo[:, :2] - gt[:, :2], axis=1))
    errs = np.mean(errs, axis=0)
    assert errs[50] < errs[500] < errs[1000]
    assert errs[1000] > 1.0
    np.testing.assert_array_equal(wheel_odometry(gt, seed=7), wheel_odometry(gt, seed=7))
    np.testing.assert_allclose(
        wheel_odometry(gt, seed=1, sigma_trans_rel=0, sigma_rot_per_m=0, heading_bias_per_m=0), gt
    )


def test_wheel_odometry_drifts_when_turning_on_the_spot():
    """sigma_rot_per_rad: a robot turning on the spot (d = 0) gets heading noise of std
    sigma * |dyaw| per step (the per-metre terms are zero there); 0 keeps the old model."""
    n = 20001
    gt = np.column_stack([np.zeros(n), np.zeros(n), np.arange(n) * 0.1])
    gt[:, 2] = np.mod(gt[:, 2] + np.pi, 2 * np.pi) - np.pi
    odo = wheel_odometry(gt, seed=3, sigma_rot_per_rad=0.05, heading_bias_per_m=0.0)
    np.testing.assert_array_equal(odo[:, :2], 0.0)  # no translation at all
    steps = np.angle(np.exp(1j * (np.diff(odo[:, 2]) - 0.1)))  # per-step heading error
    assert abs(np.std(steps) / (0.05 * 0.1) - 1) < 0.03  # 20 000 samples: ~0.5 % spread
    assert abs(np.mean(steps)) < 4 * 0.005 / np.sqrt(n)
    # default 0: the same odometry as before the term existed, and no rotation noise here
    np.testing.assert_allclose(wheel_odometry(gt, seed=3, heading_bias_per_m=0.0), gt)
    with pytest.raises(ValueError, match="sigma_rot_per_rad"):
        wheel_odometry(gt, seed=0, sigma_rot_per_rad=-1.0)


# ------------------------------------------------------------------ scans on the route


def test_scan_layout_and_mount_height():
    lidar = hdl32e(n_azimuths=64, range_noise_m=0.0)
    assert lidar.n_rings == 32
    np.testing.assert_allclose(HDL32E_ELEVATIONS_DEG, np.linspace(-30.67, 10.67, 32))
    sc = simulate_urban_scan(hand_world(), np.array([3.0, -2.0, 0.7]), lidar, seed=0)
    assert sc.directions.shape == (32 * 64, 3) and sc.ranges_m.shape == (32 * 64,)
    np.testing.assert_allclose(np.linalg.norm(sc.directions, axis=1), 1.0)
    el = np.arcsin(sc.directions[:, 2]).reshape(32, 64)
    np.testing.assert_allclose(el, np.deg2rad(HDL32E_ELEVATIONS_DEG)[:, None] * np.ones(64))
    pts = sc.points()
    assert len(pts) > 0
    np.testing.assert_allclose(pts[:, 2], -1.73, atol=1e-4)
    world_pts = sc.points_world()
    np.testing.assert_allclose(world_pts[:, 2], 0.0, atol=1e-4)
    # upward rings see nothing
    assert np.isinf(sc.ranges_m.reshape(32, 64)[HDL32E_ELEVATIONS_DEG > 0]).all()


def test_scan_on_route_sees_pole_and_is_deterministic(traj, world):
    lamp = POLE_KINDS.index("street_lamp")
    m = np.flatnonzero(world.pole_kind == lamp)
    d = np.linalg.norm(traj.xy_yaw[:, None, :2] - world.pole_xy[None, m], axis=2)
    i_pose, j = np.unravel_index(np.argmin(d), d.shape)
    pole = m[j]
    lidar = hdl32e(n_azimuths=360, range_noise_m=0.0)
    sc = simulate_urban_scan(world, traj.xy_yaw[i_pose], lidar, seed=5)
    pw = sc.points_world()
    r_axis = np.linalg.norm(pw[:, :2] - world.pole_xy[pole], axis=1)
    on = (r_axis < world.pole_radius_m[pole] + 0.05) & (pw[:, 2] > 0.05)  # not the ground
    assert on.sum() >= 3
    np.testing.assert_allclose(r_axis[on], world.pole_radius_m[pole], atol=2e-3)
    assert (pw[on, 2] <= world.pole_height_m[pole] + 1e-3).all()
    noisy = hdl32e(n_azimuths=128)
    a = simulate_urban_scan(world, traj.xy_yaw[i_pose], noisy, seed=1)
    b = simulate_urban_scan(world, traj.xy_yaw[i_pose], noisy, seed=1)
    c = simulate_urban_scan(world, traj.xy_yaw[i_pose], noisy, seed=2)
    np.testing.assert_array_equal(a.ranges_m, b.ranges_m)
    assert not np.array_equal(a.ranges_m, c.ranges_m)
    scans = list(simulate_urban_scans(world, traj.xy_yaw[:2], noisy, seed=4, progress=False))
    again = list(simulate_urban_scans(world, traj.xy_yaw[:2], noisy, seed=4, progress=False))
    assert len(scans) == 2
    np.testing.assert_array_equal(scans[1].ranges_m, again[1].ranges_m)


# ------------------------------------------------------------------ bad input


def test_bad_input_raises_value_error(world):
    lidar = hdl32e(n_azimuths=16)
    with pytest.raises(ValueError, match="pose_xy_yaw"):
        simulate_urban_scan(world, np.zeros(2), lidar, seed=0)
    with pytest.raises(ValueError, match="pose_xy_yaw"):
        simulate_urban_scan(world, np.array([0.0, np.nan, 0.0]), lidar, seed=0)
    with pytest.raises(ValueError, match="seed"):
        simulate_urban_scan(world, np.zeros(3), lidar, seed=-1)
    with pytest.raises(ValueError, match="lidar"):
        simulate_urban_scan(world, np.zeros(3), "hdl32e", seed=0)
    with pytest.raises(ValueError, match="poses_xy_yaw"):
        simulate_urban_scans(world, np.zeros((4, 2)), lidar, seed=0)
    with pytest.raises(ValueError, match="trajectory_xy_yaw"):
        wheel_odometry(np.zeros((5, 4)), seed=0)
    with pytest.raises(ValueError, match="seed"):
        wheel_odometry(np.zeros((5, 3)), seed=-3)
    with pytest.raises(ValueError, match="trajectory"):
        make_urban_world(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="seed"):
        make_urban_world(np.zeros((3, 3)), seed=-1)
    with pytest.raises(ValueError, match="session"):
        urban_session(world, -1)
    with pytest.raises(ValueError, match="p_remove"):
        urban_session(world, 1, p_remove=1.5)
    with pytest.raises(ValueError, match="n_azimuths"):
        hdl32e(n_azimuths=0)
    with pytest.raises(ValueError, match="max_range_m"):
        hdl32e(max_range_m=0.5)
    with pytest.raises(ValueError, match="elevations_rad"):
        LidarSpec(elevations_rad=np.array([2.0]))
    with pytest.raises(ValueError, match="pole_radius_m"):
        hand_world(poles=[(1.0, 1.0, -0.1, 2.0)])
