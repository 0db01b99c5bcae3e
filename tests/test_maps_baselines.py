"""Tests of the continuous occupancy-map baselines (GPOM, Hilbert maps) of Sec. 9.5.2."""

import jax.numpy as jnp
import numpy as np
import pytest

from lidarjax.maps.baselines import (
    GPOccupancyMap,
    HilbertMap,
    fit_gpom,
    fit_hilbert,
    occupancy_reflection_map,
    occupancy_training_points,
    rasterize,
)
from lidarjax.rays import HIT, SUB, SUP, RayBatch, classify
from lidarjax.raytrace import GridSpec
from lidarjax.sensor_models import reflection_log_likelihood


def _rays(origins, directions, ranges, kinds, r_max):
    d = np.asarray(directions, float)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return RayBatch(
        origins=jnp.asarray(np.asarray(origins, float)),
        directions=jnp.asarray(d),
        ranges=jnp.asarray(np.asarray(ranges, float)),
        kind=jnp.asarray(np.asarray(kinds, np.int32)),
        r_min=jnp.asarray(0.1),
        r_max=jnp.asarray(float(r_max)),
    )


# --------------------------------------------------------------------------------------
# occupancy_training_points on hand-made rays in the box [0, 4]^2, r_max = 4 m

BOX_LO, BOX_HI = np.array([0.0, 0.0]), np.array([4.0, 4.0])
STEP = 0.25
S2 = np.sqrt(0.5)
HAND = dict(
    origins=[(1, 1), (3.5, 0.5), (2, 2), (0.25, -1), (5, 5), (0.5, 0.5)],
    directions=[(1, 0), (0, 1), (-1, 0), (0, 1), (-S2, -S2), (0.6, 0.8)],
    ranges=[2.0, 3.9, 0.05, 4.0, 1.0, 2.5],
    kinds=[HIT, HIT, SUB, SUP, HIT, HIT],
    r_max=4.0,
)
# free interval [t0, t1] (m) of each ray inside the box; None: no free samples
HAND_FREE = [(0.0, 1.9), (0.0, 3.5), None, (1.0, 4.0), None, (0.0, 2.4)]


def test_training_points_hand_made():
    rays = _rays(**HAND)
    pts, lab = occupancy_training_points(rays, BOX_LO, BOX_HI, free_step_m=STEP, seed=3)
    assert pts.dtype == np.float64 and pts.shape == (lab.shape[0], 2)
    assert set(np.unique(lab)) == {0, 1}
    # occupied = in-box HIT end points: ray 0 -> (3, 1), ray 5 -> (2, 2.5)
    occ = pts[lab == 1]
    np.testing.assert_allclose(occ[np.argsort(occ[:, 0])], [[2.0, 2.5], [3.0, 1.0]], atol=1e-12)

    free = pts[lab == 0]
    assert np.all((free >= BOX_LO) & (free <= BOX_HI))
    o = np.asarray(HAND["origins"], float)
    d = np.asarray(rays.directions)
    claimed = np.zeros(free.shape[0], bool)
    for j, interval in enumerate(HAND_FREE):
        rel = free - o[j]
        t = rel @ d[j]
        perp = np.abs(rel[:, 0] * d[j, 1] - rel[:, 1] * d[j, 0])
        on_line = perp < 1e-9
        if interval is None:
            assert not np.any(on_line & (t >= -1e-9)), f"ray {j} must give no free points"
            continue
        t0, t1 = interval
        mine = on_line & (t >= t0 - 1e-9) & (t <= t1 + 1e-9)
        assert not np.any(on_line & ~mine & (t >= 0)), f"ray {j}: sample outside [t0, t1]"
        ts = np.sort(t[mine])
        assert ts.size == np.floor((t1 - ts[0]) / STEP + 1e-9) + 1
        np.testing.assert_allclose(np.diff(ts), STEP, atol=1e-9)
        assert 0 <= ts[0] - t0 < STEP + 1e-12  # random offset in [0, step)
        assert 0 <= t1 - ts[-1] < STEP + 1e-12  # no further sample fits
        claimed |= mine
    assert claimed.all()
    # HIT free samples stop 0.1 m before the end point
    assert np.min(np.linalg.norm(free - [3.0, 1.0], axis=1)) >= 0.1 - 1e-9


def test_training_points_sub_rays_and_determinism():
    rays = _rays(**HAND)
    a = occupancy_training_points(rays, BOX_LO, BOX_HI, seed=7)
    b = occupancy_training_points(rays, BOX_LO, BOX_HI, seed=7)
    c = occupancy_training_points(rays, BOX_LO, BOX_HI, seed=8)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert a[0].shape != c[0].shape or not np.array_equal(a[0], c[0])
    # only SUB rays: nothing at all
    sub = _rays([(2, 2), (1, 1)], [(1, 0), (0, 1)], [0.05, 0.02], [SUB, SUB], 4.0)
    pts, lab = occupancy_training_points(sub, BOX_LO, BOX_HI)
    assert pts.shape == (0, 2) and lab.shape == (0,)


def test_training_points_errors():
    rays = _rays(**HAND)
    rays3 = RayBatch(
        origins=jnp.zeros((2, 3)),
        directions=jnp.tile(jnp.array([1.0, 0.0, 0.0]), (2, 1)),
        ranges=jnp.ones(2),
        kind=jnp.zeros(2, jnp.int32),
        r_min=jnp.asarray(0.0),
        r_max=jnp.asarray(5.0),
    )
    with pytest.raises(ValueError, match="2-D"):
        occupancy_training_points(rays3, BOX_LO, BOX_HI)
    with pytest.raises(ValueError, match="lower"):
        occupancy_training_points(rays, [1.0, 0.0], [1.0, 4.0])
    with pytest.raises(ValueError, match="lower"):
        occupancy_training_points(rays, [5.0, 0.0], [1.0, 4.0])
    with pytest.raises(ValueError, match="free_step_m"):
        occupancy_training_points(rays, BOX_LO, BOX_HI, free_step_m=0.0)
    with pytest.raises(ValueError, match="rays"):
        occupancy_training_points("rays", BOX_LO, BOX_HI)


# --------------------------------------------------------------------------------------
# synthetic square room: walls on the boundary of [0, 4] x [0, 3]

ROOM_LO, ROOM_HI = np.array([0.0, 0.0]), np.array([4.0, 3.0])
MAP_LO, MAP_HI = ROOM_LO - 0.5, ROOM_HI + 0.5
WALLS = np.array([[0, 1.5], [4, 1.5], [2, 0], [2, 3], [0.05, 1.0], [3.95, 2.0], [1.0, 2.95]])
MIDDLE = np.array([[2.0, 1.5], [1.6, 1.4], [2.4, 1.7]])
GP_BUDGET, HB_BUDGET = 400, 300


def room_rays(poses, n_beams=120, r_max=10.0, phase=0.0):
    """Exact rays from poses inside the room to its walls (NumPy ray-box intersection)."""
    ang = phase + np.arange(n_beams) * 2 * np.pi / n_beams
    dirs = np.stack([np.cos(ang), np.sin(ang)], axis=-1)
    o = np.repeat(np.asarray(poses, float), n_beams, axis=0)
    d = np.tile(dirs, (len(poses), 1))
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, (ROOM_HI - o) / d, np.where(d < 0, (ROOM_LO - o) / d, np.inf))
    r = t.min(axis=1)
    return RayBatch(
        origins=jnp.asarray(o),
        directions=jnp.asarray(d),
        ranges=jnp.asarray(r),
        kind=classify(jnp.asarray(r), 0.0, r_max),
        r_min=jnp.asarray(0.0),
        r_max=jnp.asarray(r_max),
    )


@pytest.fixture(scope="module")
def room_data():
    rays = room_rays([(1, 1), (3, 1), (3, 2), (1, 2)])
    return occupancy_training_points(rays, MAP_LO, MAP_HI, seed=0)


@pytest.fixture(scope="module")
def gpom(room_data):
    return fit_gpom(*room_data, GP_BUDGET, seed=1)


@pytest.fixture(scope="module")
def hilbert(room_data):
    return fit_hilbert(*room_data, HB_BUDGET, seed=1)


def test_room_training_points(room_data):
    pts, lab = room_data
    # occupied points are exactly the wall points
    occ = pts[lab == 1]
    on_wall = np.isclose(occ, ROOM_LO).any(axis=1) | np.isclose(occ, ROOM_HI).any(axis=1)
    assert occ.shape[0] == 4 * 120 and on_wall.all()
    free = pts[lab == 0]
    assert np.all((free > ROOM_LO) & (free < ROOM_HI))


@pytest.mark.parametrize("which", ["gpom", "hilbert"])
def test_room_occupancy(which, request):
    m = request.getfixturevalue(which)
    p_wall = m.occupancy(WALLS)
    p_mid = m.occupancy(MIDDLE)
    assert p_wall.shape == (WALLS.shape[0],) and p_mid.shape == (MIDDLE.shape[0],)
    assert np.all(p_wall > 0.5), p_wall
    assert np.all(p_mid < 0.5), p_mid
    assert np.all((p_wall >= 1e-6) & (p_wall <= 1 - 1e-6))
    assert m.occupancy(np.zeros((0, 2))).shape == (0,)


def test_gpom_parameters_and_stratification(gpom, room_data):
    assert isinstance(gpom, GPOccupancyMap)
    assert gpom.n_parameters == GP_BUDGET
    assert gpom.points.shape == (GP_BUDGET, 2) and gpom.labels.shape == (GP_BUDGET,)
    assert gpom.model.alpha_.shape[0] == GP_BUDGET  # K^-1 y
    frac = room_data[1].mean()
    assert abs(gpom.labels.mean() - frac) <= 1.0 / GP_BUDGET
    # the kept points are a subset of the training set with their labels
    pts, lab = room_data
    idx = [np.flatnonzero(np.all(pts == p, axis=1))[0] for p in gpom.points]
    np.testing.assert_array_equal(lab[idx], gpom.labels)
    # fewer points than the budget: all are used
    small = fit_gpom(pts[:50], lab[:50], 1000)
    assert small.n_parameters == 50


def test_gpom_far_field_and_probit(gpom):
    far = np.array([[40.0, 40.0]])
    np.testing.assert_allclose(gpom.occupancy(far), 0.5, atol=1e-9)
    from scipy.stats import norm

    mu, sd = gpom.latent(WALLS)
    np.testing.assert_allclose(gpom.occupancy(WALLS), norm.cdf(mu / np.sqrt(1 + sd**2)))


def test_hilbert_parameters(hilbert):
    assert isinstance(hilbert, HilbertMap)
    assert hilbert.n_parameters == HB_BUDGET
    assert hilbert.features.components_.shape == (HB_BUDGET, 2)
    assert hilbert.classifier.coef_.shape == (1, HB_BUDGET)


@pytest.mark.parametrize("fit", [fit_gpom, fit_hilbert])
def test_seeded_determinism(fit, room_data):
    q = np.concatenate([WALLS, MIDDLE])
    a = fit(*room_data, 100, seed=5).occupancy(q)
    b = fit(*room_data, 100, seed=5).occupancy(q)
    c = fit(*room_data, 100, seed=6).occupancy(q)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize("fit", [fit_gpom, fit_hilbert])
def test_fit_errors(fit):
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    lab = np.array([1, 0, 0])
    with pytest.raises(ValueError, match="budget"):
        fit(pts, lab, 0)
    with pytest.raises(ValueError, match="budget"):
        fit(pts, lab, 2.5)
    with pytest.raises(ValueError, match="points"):
        fit(np.zeros((0, 2)), np.zeros(0, int), 5)
    with pytest.raises(ValueError, match="labels"):
        fit(pts, np.array([1, 0, 2]), 5)
    with pytest.raises(ValueError, match="labels"):
        fit(pts, np.array([1.0, 0.5, 0.0]), 5)
    with pytest.raises(ValueError, match="labels"):
        fit(pts, lab[:2], 5)
    with pytest.raises(ValueError, match="points"):
        fit(pts[:, :1], lab, 5)
    with pytest.raises(ValueError, match="points"):
        fit(np.array([[0.0, np.nan], [1, 0], [0, 1]]), lab, 5)
    with pytest.raises(ValueError, match="seed"):
        fit(pts, lab, 2, seed=-1)


def test_hilbert_needs_both_classes():
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    with pytest.raises(ValueError, match="both classes"):
        fit_hilbert(pts, np.zeros(3, int), 2)
    with pytest.raises(ValueError, match="gamma"):
        fit_hilbert(pts, np.array([1, 0, 0]), 2, gamma=0.0)


# --------------------------------------------------------------------------------------
# rasterize and the reflection map


def test_rasterize_covers_box_and_matches(hilbert):
    lo, hi = np.array([-0.5, -0.5]), np.array([4.52, 3.5])
    spec, probs = rasterize(hilbert.occupancy, lo, hi, resolution_m=0.05)
    assert isinstance(spec, GridSpec)
    assert spec.shape == (101, 80) and probs.shape == spec.shape
    np.testing.assert_allclose(spec.origin, lo)
    upper = np.asarray(spec.upper)
    assert np.all(upper >= hi - 1e-12) and np.all(upper - 0.05 < hi)
    centers = np.asarray(spec.cell_centers())
    np.testing.assert_allclose(probs, hilbert.occupancy(centers.reshape(-1, 2)).reshape(101, 80))
    np.testing.assert_allclose(centers[3, 7], lo + (np.array([3, 7]) + 0.5) * 0.05)


def test_rasterize_chunked_analytic():
    # 300 x 300 = 90000 cells > one chunk
    fn = lambda p: 0.5 * (1 + np.sin(p[:, 0]) * np.cos(p[:, 1]))
    spec, probs = rasterize(fn, [0.0, 0.0], [15.0, 15.0], resolution_m=0.05)
    assert spec.shape == (300, 300)
    c = np.asarray(spec.cell_centers())
    np.testing.assert_allclose(probs, 0.5 * (1 + np.sin(c[..., 0]) * np.cos(c[..., 1])))


def test_rasterize_errors():
    with pytest.raises(ValueError, match="occupancy_fn"):
        rasterize(lambda p: np.zeros(3), [0, 0], [1, 1], resolution_m=0.1)
    with pytest.raises(ValueError, match="occupancy_fn"):
        rasterize(lambda p: np.full(p.shape[0], 1.5), [0, 0], [1, 1], resolution_m=0.1)
    with pytest.raises(ValueError, match="occupancy_fn"):
        rasterize(None, [0, 0], [1, 1])
    with pytest.raises(ValueError, match="lower"):
        rasterize(lambda p: np.zeros(p.shape[0]), [0, 0], [0, 1])
    with pytest.raises(ValueError, match="resolution_m"):
        rasterize(lambda p: np.zeros(p.shape[0]), [0, 0], [1, 1], resolution_m=-0.1)


def test_occupancy_reflection_map_fields():
    spec = GridSpec.from_bounds([0.0, 0.0], [1.0, 0.5], 0.1)
    probs = np.linspace(0, 1, 50).reshape(10, 5)
    m = occupancy_reflection_map(spec, probs)
    np.testing.assert_allclose(m.probs, probs)
    np.testing.assert_allclose(m.unknown_prob, probs.mean())
    assert m.probs.dtype == jnp.float64
    assert float(occupancy_reflection_map(spec, probs, unknown_prob=0.2).unknown_prob) == 0.2
    with pytest.raises(ValueError, match="probs"):
        occupancy_reflection_map(spec, probs.T)
    with pytest.raises(ValueError, match="probs"):
        occupancy_reflection_map(spec, probs + 0.5)
    with pytest.raises(ValueError, match="unknown_prob"):
        occupancy_reflection_map(spec, probs, unknown_prob=1.5)
    with pytest.raises(ValueError, match="spec"):
        occupancy_reflection_map(None, probs)


@pytest.mark.parametrize("which", ["gpom", "hilbert"])
def test_reflection_likelihood_beats_constant_map(which, request):
    m = request.getfixturevalue(which)
    test_rays = room_rays([(2.0, 1.5), (1.5, 2.5)], n_beams=90, phase=0.013)
    spec, probs = rasterize(m.occupancy, MAP_LO, MAP_HI)
    ll = np.asarray(reflection_log_likelihood(occupancy_reflection_map(spec, probs), test_rays))
    assert ll.shape == (180,) and np.all(np.isfinite(ll))
    const = occupancy_reflection_map(spec, np.full(spec.shape, 0.5))
    ll_const = np.asarray(reflection_log_likelihood(const, test_rays))
    assert ll.sum() > ll_const.sum()
