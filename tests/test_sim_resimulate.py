"""lidarjax.sim.resimulate_scans: a log's own surfaces, cast again from exact poses.

References: the office world's exact segment caster (simulate_scans, the geometry core's
ray/segment intersection) and hand-built scans whose world is known in closed form.
"""

import numpy as np
import pytest

from lidarjax.sim import make_office, resimulate_scans, simulate_scans

AZ = np.linspace(-np.pi / 2, np.pi / 2, 181)
MAX_RANGE = 20.0


@pytest.fixture(scope="module")
def office():
    world = make_office(0)
    poses = world.trajectory(60, jitter_m=0.2)
    exact = simulate_scans(world, poses, AZ, max_range_m=MAX_RANGE, noise_sigma_m=0.0)
    return world, poses, exact


def test_resimulated_office_scans_match_the_exact_caster(office):
    _, poses, exact = office
    out = resimulate_scans(exact, AZ, poses, max_range_m=MAX_RANGE, noise_sigma_m=0.0)
    r = out.ranges_m
    assert r.shape == exact.shape and np.all(np.isfinite(r))
    hit = exact < MAX_RANGE
    # the same beams return (a ray through a rasterized corner gap may slip, rarely)
    assert np.mean((r < MAX_RANGE) == hit) > 0.995
    both = hit & (r < MAX_RANGE)
    err = r[both] - exact[both]
    # the walls are exact segments: most readings land on them; the rest end early, on a
    # link between end points of two surfaces (a pillar's edge and the wall behind it)
    assert np.mean(np.abs(err) < 1e-3) > 0.95
    assert np.all(err < 0.2) and np.mean(err < -0.02) < 0.04
    assert out.occupied.dtype == bool and out.cell_m == 0.01 and out.n_segments > 0


def test_noise_is_gaussian_with_the_given_sigma_and_seeded(office):
    _, poses, exact = office
    kw = dict(max_range_m=MAX_RANGE)
    clean = resimulate_scans(exact, AZ, poses, noise_sigma_m=0.0, **kw).ranges_m
    a = resimulate_scans(exact, AZ, poses, noise_sigma_m=0.05, seed=3, **kw).ranges_m
    b = resimulate_scans(exact, AZ, poses, noise_sigma_m=0.05, seed=3, **kw).ranges_m
    c = resimulate_scans(exact, AZ, poses, noise_sigma_m=0.05, seed=4, **kw).ranges_m
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    ok = (clean > 0.5) & (clean < MAX_RANGE - 0.5)
    d = a[ok] - clean[ok]
    assert abs(d.mean()) < 0.003 and 0.047 < d.std() < 0.053
    # no-returns stay exactly the no-return value, noise or not
    np.testing.assert_array_equal(a[clean >= MAX_RANGE], MAX_RANGE)


def test_no_return_beams_read_max_range_and_add_no_surface():
    # one pose facing a wall at x = 5 seen by the beams within +-30 deg; the rest no-returns
    az = np.deg2rad(np.arange(-90.0, 90.5, 1.0))
    r = np.where(np.abs(az) <= np.deg2rad(30), 5.0 / np.cos(az), MAX_RANGE)[None]
    pose = np.zeros((1, 3))
    out = resimulate_scans(r, az, pose, max_range_m=MAX_RANGE, noise_sigma_m=0.0)
    front = np.abs(az) <= np.deg2rad(29.5)
    np.testing.assert_allclose(out.ranges_m[0, front], r[0, front], atol=0.012)
    away = np.abs(az) >= np.deg2rad(31)
    np.testing.assert_array_equal(out.ranges_m[0, away], MAX_RANGE)
    # readings at or beyond max_range_m make no surface: the grid spans only the wall
    xs = out.origin_m[0] + out.cell_m * np.nonzero(out.occupied.any(0))[0]
    assert xs.min() > 4.9 and xs.max() < 5.1


def test_link_m_decides_whether_neighbouring_end_points_form_a_wall():
    # beams 10 deg apart meet a wall at x = 4 from the origin: neighbouring end points are
    # 0.70-1.05 m apart. A second pose at (2, 0.35) looks at the wall between two of them.
    az = np.deg2rad(np.arange(-40.0, 40.5, 10.0))
    poses = np.array([[0.0, 0.0, 0.0], [2.0, 0.35, 0.0]])
    ranges = np.vstack([4.0 / np.cos(az), np.full_like(az, MAX_RANGE)])
    kw = dict(max_range_m=MAX_RANGE, noise_sigma_m=0.0)
    sparse = resimulate_scans(ranges, az, poses, link_m=0.3, **kw)
    wall = resimulate_scans(ranges, az, poses, link_m=1.2, **kw)
    ahead = int(np.argmin(np.abs(az)))
    assert sparse.ranges_m[1, ahead] == MAX_RANGE  # between isolated points: no return
    assert abs(wall.ranges_m[1, ahead] - 2.0) < 1e-9  # on the segment's line
    # the first pose reads its own end points again in both worlds
    np.testing.assert_allclose(wall.ranges_m[0], ranges[0], atol=1e-9)
    # an isolated point: the entry of its 1 cm cell (plus at most a 1/3 cm step)
    d = sparse.ranges_m[0] - ranges[0]
    assert np.all((d <= 1e-9) & (d >= -0.01 / np.abs(np.cos(az)) - 0.0034))
    assert sparse.n_segments == az.size and wall.n_segments == az.size - 1


def test_footprint_frees_where_the_robot_stood():
    # a door at x = 2, closed in the first scan (seen from the origin), is passed through
    # later: the robot stands at (2, 0) facing on, with no return of its own
    az = np.deg2rad(np.arange(-20.0, 20.5, 1.0))
    poses = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    ranges = np.vstack([2.0 / np.cos(az), np.full_like(az, MAX_RANGE)])
    kw = dict(max_range_m=MAX_RANGE, noise_sigma_m=0.0)
    ghost = resimulate_scans(ranges, az, poses, footprint_m=0.0, **kw)
    free = resimulate_scans(ranges, az, poses, footprint_m=0.2, **kw)
    ahead = int(np.argmin(np.abs(az)))
    assert ghost.ranges_m[1, ahead] < 0.02  # inside the door that is no longer there
    assert free.ranges_m[1, ahead] == MAX_RANGE
    # no world cell within 0.2 m of a pose (cell centres)
    j, i = np.nonzero(free.occupied)
    centres = free.origin_m + (np.stack([i, j], 1) + 0.5) * free.cell_m
    assert np.linalg.norm(centres[:, None] - poses[None, :, :2], axis=-1).min() > 0.2
    # the first scan's beams through the freed 0.4 m of the door now pass (|y| < 0.2 m)
    y = 2.0 * np.tan(az)
    assert np.all(free.ranges_m[0, np.abs(y) < 0.17] == MAX_RANGE)
    np.testing.assert_allclose(
        free.ranges_m[0, np.abs(y) > 0.25], ranges[0, np.abs(y) > 0.25], atol=1e-9
    )


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(cell_m=0.0), "cell_m"),
        (dict(cell_m=float("nan")), "cell_m"),
        (dict(cell_m=True), "cell_m"),
        (dict(link_m=-1.0), "link_m"),
        (dict(max_range_m=0.0), "max_range_m"),
        (dict(max_range_m=float("inf")), "max_range_m"),
        (dict(noise_sigma_m=-0.01), "noise_sigma_m"),
        (dict(noise_sigma_m=float("nan")), "noise_sigma_m"),
        (dict(seed=-1), "seed"),
        (dict(footprint_m=-0.1), "footprint_m"),
        (dict(footprint_m=float("nan")), "footprint_m"),
        (dict(cell_m=1e-4), "cell_m"),  # a world of too many cells
    ],
)
def test_bad_settings_are_named(office, kwargs, match):
    _, poses, exact = office
    kw = dict(max_range_m=MAX_RANGE) | kwargs
    with pytest.raises(ValueError, match=match):
        resimulate_scans(exact[:3], AZ, poses[:3], **kw)


def test_bad_arrays_are_named(office):
    _, poses, exact = office
    with pytest.raises(ValueError, match="ranges_m"):
        resimulate_scans(exact[:3, :-1], AZ, poses[:3], max_range_m=MAX_RANGE)
    bad = exact[:3].copy()
    bad[1, 2] = np.nan
    with pytest.raises(ValueError, match="ranges_m"):
        resimulate_scans(bad, AZ, poses[:3], max_range_m=MAX_RANGE)
    p = poses[:3].copy()
    p[0, 2] = np.inf
    with pytest.raises(ValueError, match="poses_xy_yaw"):
        resimulate_scans(exact[:3], AZ, p, max_range_m=MAX_RANGE)
    with pytest.raises(ValueError, match="azimuths_rad"):
        resimulate_scans(exact[:3], AZ[None], poses[:3], max_range_m=MAX_RANGE)
