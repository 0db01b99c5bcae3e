"""Tests of the SynPEB-style scene generator, ray caster and scan simulator (lidarjax.sim).

The SynPEB PCD I/O tests are in ``test_datasets_synpeb_io.py``."""

from __future__ import annotations

import numpy as np
import pytest

from lidarjax.datasets import SynPEBScan, fetch, load_synpeb_pcd
from lidarjax.sim import (
    ConvexPolyhedron,
    SynPEBScene,
    cast_rays,
    make_synpeb_scene,
    simulate_synpeb_scan,
    synpeb_scan,
    synpeb_split,
)

# Room seen from inside: x in [-2, 4], y in [-3, 3.5], z in [-1.3, 1.7].
ROOM_LO, ROOM_HI = (-2.0, -3.0, -1.3), (4.0, 3.5, 1.7)
ROOM_LABELS = (1, 2, 3, 4, 5, 6)  # -x, +x, -y, +y, -z, +z


def _room() -> ConvexPolyhedron:
    return ConvexPolyhedron.box(ROOM_LO, ROOM_HI, ROOM_LABELS, inside_out=True)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _reference_cast(scene: SynPEBScene, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Face-by-face reference: intersect each face plane, keep points inside the face's solid."""
    dirs = _unit(dirs)
    ranges = np.full(len(dirs), np.inf)
    labels = np.zeros(len(dirs), dtype=np.int64)
    for poly in scene.polyhedra:
        for n, d, lab in zip(poly.normals, poly.offsets, poly.labels, strict=True):
            for k, v in enumerate(dirs):
                nv = n @ v
                if nv == 0.0:
                    continue
                t = d / nv
                if not 0.0 < t < ranges[k]:
                    continue
                if np.all(poly.normals @ (t * v) - poly.offsets <= 1e-9):
                    ranges[k], labels[k] = t, lab
    ranges[~np.isfinite(ranges)] = np.nan
    return ranges, labels


# ------------------------------------------------------------------------------------------
# Ray casting on hand-made scenes
# ------------------------------------------------------------------------------------------


def test_room_from_inside_matches_analytic_distances():
    scene = SynPEBScene.from_polyhedra([_room()])
    dirs = np.array(
        [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1], [1, 1, 0]],
        dtype=float,
    )
    ranges, labels = cast_rays(scene, dirs)
    np.testing.assert_allclose(ranges[:6], [4.0, 2.0, 3.5, 3.0, 1.7, 1.3], rtol=1e-12)
    np.testing.assert_array_equal(labels[:6], [2, 1, 4, 3, 6, 5])
    # (1, 1, 0)/sqrt 2 reaches y = 3.5 before x = 4.
    assert ranges[6] == pytest.approx(3.5 * np.sqrt(2.0), rel=1e-12)
    assert labels[6] == 4
    # Another origin inside the room shifts the distances.
    ranges, labels = cast_rays(scene, dirs[:2], origin_m=(1.0, 0.5, 0.0))
    np.testing.assert_allclose(ranges, [3.0, 3.0], rtol=1e-12)
    # Random directions: the exit point lies on the labelled wall and inside the room.
    dirs = _unit(np.random.default_rng(0).normal(size=(500, 3)))
    ranges, labels = cast_rays(scene, dirs)
    pts = ranges[:, None] * dirs
    n, d = scene.plane_normals[labels], scene.plane_offsets[labels]
    np.testing.assert_allclose(np.sum(n * pts, axis=1), d, atol=1e-12)
    assert np.all(pts >= np.array(ROOM_LO) - 1e-12) and np.all(pts <= np.array(ROOM_HI) + 1e-12)


def test_unit_box_hits_front_and_top_faces_and_misses_beside():
    box = ConvexPolyhedron.box((2.0, -0.5, -1.5), (3.0, 0.5, -0.5), (11, 12, 13, 14, 15, 16))
    scene = SynPEBScene.from_polyhedra([box])
    targets = np.array(
        [
            [2.0, 0.2, -1.0],  # on the -x face
            [2.5, 0.1, -0.5],  # on the top face: at x = 2 the ray is at z = -0.4, above it
            [2.0, 0.5, -1.4],  # edge point on the -x face (y = +0.5 boundary)
            [0.0, 1.0, 0.0],  # beside the box: no return (there is no room)
            [-1.0, 0.0, -1.0],  # behind the sensor: no return
        ]
    )
    ranges, labels = cast_rays(scene, targets)
    np.testing.assert_allclose(ranges[:3], np.linalg.norm(targets[:3], axis=1), rtol=1e-12)
    assert labels[0] == 11 and labels[1] == 16 and labels[2] in (11, 14)
    assert np.all(np.isnan(ranges[3:])) and np.all(labels[3:] == 0)


def test_rays_parallel_to_faces():
    inside_slab = ConvexPolyhedron.box((2.0, -1.0, -1.0), (3.0, 1.0, 1.0), range(1, 7))
    outside_slab = ConvexPolyhedron.box((2.0, 1.0, -1.0), (3.0, 2.0, 1.0), range(7, 13))
    for box, expected in ((inside_slab, (2.0, 1)), (outside_slab, (np.nan, 0))):
        ranges, labels = cast_rays(SynPEBScene.from_polyhedra([box]), np.array([[1.0, 0, 0]]))
        np.testing.assert_equal((ranges[0], labels[0]), expected)


def test_oblique_half_space_matches_analytic_range():
    # Solid x + z >= 2 sqrt 2 (outward normal -(1, 0, 1)/sqrt 2): the plane is 2 m away.
    plane = ConvexPolyhedron(np.array([[-1.0, 0.0, -1.0]]), np.array([-2.0 * np.sqrt(2)]), [7])
    scene = SynPEBScene.from_polyhedra([plane])
    np.testing.assert_allclose(scene.plane_normals[7], -_unit([1.0, 0.0, 1.0]))
    assert scene.plane_offsets[7] == pytest.approx(-2.0)
    a = np.deg2rad(np.linspace(-40.0, 130.0, 50))
    dirs = np.column_stack([np.cos(a), np.zeros_like(a), np.sin(a)])
    ranges, labels = cast_rays(scene, dirs)
    np.testing.assert_allclose(ranges, 2.0 * np.sqrt(2.0) / (np.cos(a) + np.sin(a)), rtol=1e-12)
    np.testing.assert_array_equal(labels, 7)
    # Away from the plane: no return.
    ranges, labels = cast_rays(scene, -dirs)
    assert np.all(np.isnan(ranges)) and np.all(labels == 0)


def test_nearest_hit_wins_in_any_order():
    near = ConvexPolyhedron.box((2.0, -0.5, -0.5), (4.0, 0.5, 0.5), range(11, 17))
    far = ConvexPolyhedron.box((3.0, -1.0, -1.0), (3.5, 1.0, 1.0), range(21, 27))
    dirs = np.array([[1.0, 0.0, 0.0], _unit([3.0, 0.8, 0.0])])
    for order in ([_room(), near, far], [far, near, _room()], [near, _room(), far]):
        ranges, labels = cast_rays(SynPEBScene.from_polyhedra(order), dirs)
        # Along +x the near box (entered at x = 2) hides the overlapping far box and the wall.
        assert ranges[0] == pytest.approx(2.0) and labels[0] == 11
        # Towards (3, 0.8, 0) only the far box is in the way (it spans |y| <= 1).
        assert ranges[1] == pytest.approx(3.0 / _unit([3.0, 0.8, 0.0])[0]) and labels[1] == 21


def test_cast_rays_matches_face_by_face_reference_on_a_generated_scene():
    scene = make_synpeb_scene(seed=3)
    rng = np.random.default_rng(1)
    az = rng.uniform(-np.pi, np.pi, 300)
    el = np.arcsin(rng.uniform(-1.0, 1.0, 300))
    dirs = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    # Half of the rays aimed at object vertices' neighbourhood to exercise culling.
    verts = np.vstack([p.vertices()[0] for p in scene.polyhedra[1:]])
    dirs = np.vstack([dirs, verts[:300] + rng.normal(0.0, 0.05, verts[:300].shape)])
    ranges, labels = cast_rays(scene, dirs, chunk_size=37)
    ref_r, ref_l = _reference_cast(scene, dirs)
    np.testing.assert_array_equal(cast_rays(scene, dirs, chunk_size=10_000)[1], labels)
    np.testing.assert_allclose(ranges, ref_r, rtol=1e-9)
    np.testing.assert_array_equal(labels, ref_l)
    assert np.all(labels > 0)  # closed room
    assert len(np.unique(labels)) > 20


# ------------------------------------------------------------------------------------------
# Scene structure
# ------------------------------------------------------------------------------------------


def test_box_and_room_adjacency():
    scene = SynPEBScene.from_polyhedra([_room()])
    # Each of the 6 faces of a box meets the 4 non-opposite faces: 12 edges.
    assert scene.adjacent_labels.shape == (12, 2)
    opposite = {(1, 2), (3, 4), (5, 6)}
    assert not opposite & {tuple(p) for p in scene.adjacent_labels.tolist()}


def test_contact_adjacency_of_touching_boxes():
    a = ConvexPolyhedron.box((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), range(1, 7))
    b = ConvexPolyhedron.box((1.0, 0.0, 0.0), (2.0, 1.0, 0.5), range(11, 17))
    pairs = {tuple(p) for p in SynPEBScene.from_polyhedra([a, b]).adjacent_labels.tolist()}
    assert (2, 16) in pairs  # a's +x face meets b's top along the concave step edge
    assert (2, 11) not in pairs  # the touching faces are parallel, not an edge
    assert (5, 15) not in pairs and (3, 13) not in pairs  # coplanar bottoms / sides
    c = ConvexPolyhedron.box((5.0, 0.0, 0.0), (6.0, 1.0, 1.0), range(21, 27))  # far away
    pairs = {tuple(p) for p in SynPEBScene.from_polyhedra([a, c]).adjacent_labels.tolist()}
    assert all((p[0] < 20) == (p[1] < 20) for p in pairs)


def test_generated_scene_structure():
    scene = make_synpeb_scene(seed=1000)  # this scene holds a staircase
    assert scene.polyhedra[0].inside_out and not any(p.inside_out for p in scene.polyhedra[1:])
    assert np.all(np.isnan(scene.plane_normals[0])) and np.isnan(scene.plane_offsets[0])
    labels = np.concatenate([p.labels for p in scene.polyhedra])
    np.testing.assert_array_equal(np.unique(labels), np.arange(1, scene.num_labels + 1))
    n_faces = labels.size
    assert n_faces > scene.num_labels  # coplanar staircase faces share labels
    for poly in scene.polyhedra:
        assert np.unique(poly.labels).size == poly.labels.size
        np.testing.assert_allclose(scene.plane_normals[poly.labels], poly.normals, atol=1e-12)
        np.testing.assert_allclose(scene.plane_offsets[poly.labels], poly.offsets, atol=1e-12)
    # Room: floor 1.2-1.5 m below, ceiling 1.5-1.8 m above, front wall 3-5 m ahead.
    room = scene.polyhedra[0]
    floor, ceiling, front = room.offsets[0], room.offsets[1], room.offsets[3]
    assert 1.2 <= floor <= 1.5 and 1.5 <= ceiling <= 1.8 and 3.0 <= front <= 5.0
    assert room.normals[0][2] < -0.99 and room.normals[3][0] > 0.95
    # Objects stay inside the room and at least 0.8 m from the sensor.
    for poly in scene.polyhedra[1:]:
        verts = poly.vertices()[0]
        assert np.all(verts @ room.normals.T - room.offsets <= 1e-9)
        assert np.min(np.linalg.norm(verts, axis=1)) >= 0.8
    adj = scene.adjacent_labels
    assert adj.ndim == 2 and adj.shape[1] == 2 and np.all(adj[:, 0] < adj[:, 1])
    cos = np.abs(np.sum(scene.plane_normals[adj[:, 0]] * scene.plane_normals[adj[:, 1]], axis=1))
    assert np.all(cos < 1.0 - 1e-9)  # adjacent planes are never parallel
    assert {(1, 3), (1, 4), (2, 3)} <= {tuple(p) for p in adj.tolist()}  # floor/ceiling-walls


def test_scene_is_deterministic_by_seed():
    a, b, c = make_synpeb_scene(seed=7), make_synpeb_scene(seed=7), make_synpeb_scene(seed=8)
    np.testing.assert_array_equal(a.plane_normals, b.plane_normals)
    np.testing.assert_array_equal(a.plane_offsets, b.plane_offsets)
    np.testing.assert_array_equal(a.adjacent_labels, b.adjacent_labels)
    assert a.seed == 7
    assert a.plane_offsets.shape != c.plane_offsets.shape or not np.allclose(
        a.plane_offsets[1:], c.plane_offsets[1:]
    )


# ------------------------------------------------------------------------------------------
# Scans
# ------------------------------------------------------------------------------------------


def test_published_grid_angles():
    scan = simulate_synpeb_scan(SynPEBScene.from_polyhedra([_room()]), seed=0)
    assert scan.shape == (500, 500)
    np.testing.assert_allclose(
        np.rad2deg(scan.azimuth_rad), -35.0 + 0.14 * np.arange(500), rtol=0, atol=1e-12
    )
    np.testing.assert_allclose(np.rad2deg(scan.elevation_rad), np.linspace(30.0, -30.0, 500))
    # Points lie on the nominal grid: column = azimuth, row = elevation.
    p = scan.points
    az = np.arctan2(p[..., 1], p[..., 0])
    np.testing.assert_allclose(az, np.broadcast_to(scan.azimuth_rad, az.shape), rtol=0, atol=1e-12)
    el = np.arctan2(p[..., 2], np.hypot(p[..., 0], p[..., 1]))
    np.testing.assert_allclose(
        el, np.broadcast_to(scan.elevation_rad[:, None], el.shape), rtol=0, atol=1e-12
    )
    # The shared 100 x 100 crop is rows/columns 100..199 of this grid.
    pts, _ = load_synpeb_pcd(fetch("synpeb-test-100"))
    crop_az = np.arctan2(pts[..., 1], pts[..., 0])
    crop_el = np.arctan2(pts[..., 2], np.hypot(pts[..., 0], pts[..., 1]))
    np.testing.assert_allclose(
        crop_az, np.broadcast_to(scan.azimuth_rad[100:200], crop_az.shape), rtol=0, atol=1e-6
    )
    np.testing.assert_allclose(
        crop_el,
        np.broadcast_to(scan.elevation_rad[100:200, None], crop_el.shape),
        rtol=0,
        atol=1e-6,
    )


def test_scan_fields_and_points_on_labelled_planes():
    scene = make_synpeb_scene(seed=11)
    clean = simulate_synpeb_scan(
        scene, shape=(40, 50), radial_sigma_m=0.0, angular_sigma_deg=0.0, seed=0
    )
    assert isinstance(clean, SynPEBScan)
    assert clean.points.shape == (40, 50, 3) and clean.points.dtype == np.float64
    assert clean.ranges.shape == (40, 50) and clean.labels.dtype == np.int64
    assert clean.azimuth_rad.shape == (50,) and clean.elevation_rad.shape == (40,)
    np.testing.assert_allclose(np.rad2deg(clean.azimuth_rad[[0, -1]]), [-35.0, 34.86])
    np.testing.assert_allclose(np.rad2deg(clean.elevation_rad[[0, -1]]), [30.0, -30.0])
    assert np.all(clean.labels >= 1) and np.all(np.isfinite(clean.points))
    np.testing.assert_array_equal(clean.adjacent_labels, scene.adjacent_labels)
    assert clean.scene_seed == 11 and clean.seed == 0

    def plane_residual(scan):
        n = scan.plane_normals[scan.labels]
        return np.sum(n * scan.points, axis=-1) - scan.plane_offsets[scan.labels]

    np.testing.assert_allclose(plane_residual(clean), 0.0, atol=1e-9)
    noisy = simulate_synpeb_scan(scene, shape=(40, 50), seed=3)
    # Off-plane error = range noise * n.u (+ a negligible angular term): |.| < 6 sigma.
    assert np.max(np.abs(plane_residual(noisy))) < 6 * 0.02


def test_noise_statistics():
    scene = make_synpeb_scene(seed=21)
    shape = (60, 60)  # 3600 rays
    clean = simulate_synpeb_scan(
        scene, shape=shape, radial_sigma_m=0.0, angular_sigma_deg=0.0, seed=5
    )
    noisy = simulate_synpeb_scan(scene, shape=shape, seed=5)
    same = noisy.labels == clean.labels  # the angular noise may flip rays at plane edges
    assert same.mean() > 0.99
    resid = (noisy.ranges - clean.ranges)[same]
    n = resid.size
    # std of a Gaussian sample: relative standard error 1/sqrt(2n) ~ 1.2 %; allow 5 of them.
    assert abs(np.std(resid) / 0.02 - 1.0) < 5.0 / np.sqrt(2 * n)
    assert abs(np.mean(resid)) < 5.0 * 0.02 / np.sqrt(n)
    # Angular noise alone moves the range by far less than a millimetre on smooth surfaces.
    ang = simulate_synpeb_scan(scene, shape=shape, radial_sigma_m=0.0, seed=5)
    ang_resid = np.abs(ang.ranges - clean.ranges)[ang.labels == clean.labels]
    assert np.median(ang_resid) < 1e-4 and np.max(ang_resid) < 5e-3
    assert np.any(ang_resid > 0.0)


def test_scan_determinism():
    scene = make_synpeb_scene(seed=4)
    a = simulate_synpeb_scan(scene, shape=(20, 30), seed=9)
    b = simulate_synpeb_scan(make_synpeb_scene(seed=4), shape=(20, 30), seed=9)
    c = simulate_synpeb_scan(scene, shape=(20, 30), seed=10)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.labels, b.labels)
    assert not np.allclose(a.ranges, c.ranges)


def test_visible_label_count_is_plausible():
    # Measured on seeds 1000-1009 at 100 x 100: 30-48 distinct labels (27-43 with >= 10
    # points); at 500 x 500 30-56 labels with >= 50 points (43 on average).
    for seed in (1000, 1004, 2001):
        scan = simulate_synpeb_scan(make_synpeb_scene(seed=seed), shape=(100, 100), seed=1)
        labels, counts = np.unique(scan.labels, return_counts=True)
        assert 0 not in labels
        assert 25 <= labels.size <= 65, (seed, labels.size)
        assert 20 <= np.sum(counts >= 10) <= 60
        assert {1, 2, 4} <= set(labels.tolist())  # floor, ceiling and front wall visible


def test_no_return_gives_nan_and_label_zero():
    box = ConvexPolyhedron.box((2.0, -0.5, -0.5), (3.0, 0.5, 0.5), range(1, 7))
    scan = simulate_synpeb_scan(SynPEBScene.from_polyhedra([box]), shape=(20, 20), seed=0)
    miss = scan.labels == 0
    assert miss.any() and (~miss).any()
    assert np.all(np.isnan(scan.points[miss])) and np.all(np.isnan(scan.ranges[miss]))
    assert np.all(np.isfinite(scan.points[~miss]))


# ------------------------------------------------------------------------------------------
# Splits
# ------------------------------------------------------------------------------------------


def test_splits_are_fixed_and_distinct():
    train = synpeb_split("train", shape=(12, 12))
    assert len(train) == 10
    assert len(synpeb_split("test", shape=(12, 12), n=3)) == 3
    assert synpeb_split("train", shape=(12, 12), n=0) == []
    again = synpeb_scan("train", 4, shape=(12, 12))
    np.testing.assert_array_equal(again.points, train[4].points)
    seeds = {s.scene_seed for s in train} | {
        synpeb_scan("test", i, shape=(4, 4)).scene_seed for i in (0, 29)
    }
    assert len(seeds) == 12
    assert not np.allclose(train[0].ranges, train[1].ranges)


# ------------------------------------------------------------------------------------------
# Bad input
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(0, 10), (10, -1), (10,), (10, 10, 3), "ab", (2.5, 3)])
def test_bad_shape_is_rejected(shape):
    scene = SynPEBScene.from_polyhedra([_room()])
    with pytest.raises(ValueError, match="shape"):
        simulate_synpeb_scan(scene, shape=shape, seed=0)
    with pytest.raises(ValueError, match="shape"):
        synpeb_scan("train", 0, shape=shape)


def test_bad_arguments_name_the_argument():
    scene = SynPEBScene.from_polyhedra([_room()])
    with pytest.raises(ValueError, match="directions"):
        cast_rays(scene, np.ones((4, 2)))
    with pytest.raises(ValueError, match="directions"):
        cast_rays(scene, np.zeros((1, 3)))
    with pytest.raises(ValueError, match="chunk_size"):
        cast_rays(scene, np.ones((1, 3)), chunk_size=0)
    with pytest.raises(ValueError, match="radial_sigma_m"):
        simulate_synpeb_scan(scene, shape=(4, 4), radial_sigma_m=-1.0, seed=0)
    with pytest.raises(ValueError, match="elevation_deg"):
        simulate_synpeb_scan(scene, shape=(4, 4), elevation_deg=(95.0, 0.0), seed=0)
    with pytest.raises(ValueError, match="split"):
        synpeb_split("validation")
    with pytest.raises(ValueError, match="split"):
        synpeb_scan("val", 0)
    with pytest.raises(ValueError, match="index"):
        synpeb_scan("train", 10)
    with pytest.raises(ValueError, match="n must"):
        synpeb_split("train", n=-1)
    with pytest.raises(ValueError, match="normals"):
        ConvexPolyhedron(np.ones((3, 2)), np.ones(3), [1, 2, 3])
    with pytest.raises(ValueError, match="labels"):
        ConvexPolyhedron(np.eye(3), np.ones(3), [0, 1, 2])
    with pytest.raises(ValueError, match="offsets"):
        ConvexPolyhedron(np.eye(3), np.ones(2), [1, 2, 3])
    with pytest.raises(ValueError, match="different planes"):
        SynPEBScene.from_polyhedra([ConvexPolyhedron(np.eye(3), np.ones(3), [1, 1, 2])])
