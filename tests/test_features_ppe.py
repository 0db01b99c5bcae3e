"""PPE (dissertation ch. 11): the tetrominoes, the fast greedy clustering
(lidarjax/features/_ppe.py) against the from-scratch reference
(lidarjax/features/_ppe_reference.py), stopping criteria and bad input."""

import itertools
import math

import numpy as np
import pytest
from test_features_plane_fit import _scene_scan

from lidarjax.datasets import fetch, read_pcd
from lidarjax.features import (
    TETROMINOES,
    PPEStop,
    extract_planes,
    extract_planes_path,
    linearized_plane_error,
    plane_error,
)
from lidarjax.features._ppe_reference import extract_planes_reference


@pytest.fixture(scope="module")
def synpeb_crop():
    cloud = read_pcd(fetch("synpeb-test-100"))
    return cloud.points_xyz.astype(np.float64)


# ---------------------------------------------------------------------------------------
# The tetrominoes (Figure 11.2)
# ---------------------------------------------------------------------------------------


def test_tetrominoes_are_the_17_valid_ones():
    assert TETROMINOES.shape == (17, 4, 2)
    assert len({tuple(map(tuple, t)) for t in TETROMINOES}) == 17

    def canonical(cells):
        forms = []
        for rot, flip in itertools.product(range(4), (False, True)):
            c = np.array(cells)
            if flip:
                c = c * [1, -1]
            for _ in range(rot):
                c = np.stack([c[:, 1], -c[:, 0]], 1)
            c = c - c.min(0)
            forms.append(tuple(sorted(map(tuple, c))))
        return min(forms)

    kinds = {}
    for t in TETROMINOES:
        assert len(set(t[:, 0])) > 1 and len(set(t[:, 1])) > 1  # never the I
        adj = sum(abs(a - b).sum() == 1 for a, b in itertools.combinations(t, 2))
        assert adj >= 3  # connected
        kinds.setdefault(canonical(t), []).append(t)
    assert sorted(len(v) for v in kinds.values()) == [1, 4, 4, 8]  # O, T, S/Z, L/J


# ---------------------------------------------------------------------------------------
# PPE
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "window, kwargs",
    [
        ((0, 0), dict(max_increment=5e-3)),
        ((40, 50), dict(max_increment=2e-3, max_distance_m=0.05)),
        ((80, 20), dict(max_planes=5, max_increment=None)),
        ((60, 0), dict(max_increment=1e-2)),
    ],
)
def test_fast_ppe_equals_reference(synpeb_crop, window, kwargs):
    r, c = window
    sub = synpeb_crop[r : r + 14, c : c + 15].copy()
    _check_fast_equals_reference(sub, kwargs)


@pytest.mark.parametrize("window", [(0, 0), (30, 40)])
def test_fast_ppe_equals_reference_on_generated_scans(window):
    """20 mm noise: near-tied tetrominoes (equal to ~1e-12 across plane edges) occur here;
    the float32-resolution order must decide them the same way in both implementations."""
    from lidarjax.sim import synpeb_scan

    r, c = window
    sub = synpeb_scan("train", 0, shape=(100, 100)).points[r : r + 16, c : c + 16].copy()
    _check_fast_equals_reference(sub, dict(max_increment=0.01, max_distance_m=0.1))


def _check_fast_equals_reference(sub, kwargs):
    sub[3, 4] = np.nan  # a no-return ray
    fast = extract_planes(sub, refit=False, **kwargs)
    ref = extract_planes_reference(sub, **kwargs)
    np.testing.assert_array_equal(fast.labels, ref.labels)
    np.testing.assert_array_equal(fast.step_kinds, ref.step_kinds)
    np.testing.assert_allclose(fast.step_costs, ref.step_costs, rtol=1e-6, atol=1e-10)  # (10 µm)²
    assert fast.stop == ref.stop and fast.n_atoms == ref.n_atoms
    assert fast.labels[3, 4] == -1
    assert len(set(fast.step_kinds.tolist())) >= 2


def test_increments_are_brute_force_error_differences(synpeb_crop):
    """Σ of the step increments = the clustering error of the partition, recomputed from
    scratch by least squares, at several points of the same greedy run."""
    sub = synpeb_crop[20:34, 30:46]
    sub = (
        sub * (1.0 + np.random.default_rng(5).normal(0.0, 0.005, sub.shape[:2]))[..., None]
    )  # ~20 mm
    full = extract_planes(sub, max_increment=math.inf, refit=False)
    assert full.stop is PPEStop.EXHAUSTED
    K = sub.shape[0] * sub.shape[1]
    total = np.cumsum(full.step_costs)
    J = K
    js = []
    for kind in full.step_kinds:
        J -= 3 if kind == 0 else 1
        js.append(J)
    checked = 0
    for step in (10, 40, 90, len(js) // 2, len(js) - 1):
        seg = extract_planes(sub, max_increment=None, max_planes=js[step], refit=False)
        assert len(seg.step_costs) == step + 1
        brute = sum(linearized_plane_error(sub[seg.labels == j]) for j in range(seg.n_planes))
        np.testing.assert_allclose(brute, total[step], rtol=1e-8, atol=1e-10)
        checked += 1
    assert checked == 5
    assert (full.step_costs[full.step_kinds == 0] >= 0).all()


def test_ppe_separates_wall_and_floor_and_refits_exactly():
    pts, gt = _scene_scan(sigma=0.02, seed=4)
    seg = extract_planes(pts, max_increment=2e-2, max_distance_m=0.5, min_points=20)
    assert seg.n_planes == 2
    for j in range(2):
        g = np.bincount(gt[seg.labels == j]).argmax()
        assert (gt[seg.labels == j] == g).mean() > 0.97
        expected = np.array([1.0, 0, 0]) if g == 0 else np.array([0, 0, -1.0])
        assert np.degrees(np.arccos(min(1.0, seg.normals[j] @ expected))) < 1.0
        # refit error = Eq. 11.2 of the returned plane over its rays, <= the linearised plane's
        mem = seg.labels == j
        r = np.linalg.norm(pts[mem], axis=-1)
        d = pts[mem] / r[:, None]
        E = plane_error(seg.supports[j], seg.normals[j], np.zeros_like(d), d, r)
        np.testing.assert_allclose(seg.errors[j], E, rtol=1e-9)
        assert seg.errors[j] <= seg.linear_errors[j] * 1.05
    assert (seg.labels >= 0).mean() > 0.95
    assert 0.015 < seg.rmse < 0.025


def test_outlier_filter_blocks_depth_jumps():
    pts, _ = _scene_scan(h=10, w=12, az=(-0.2, 0.2), el=(0.1, -0.1))  # wall only, 0.11 m spacing
    pts[:, 6:] *= 1.5  # right half: same directions, 50 % farther (1.5 m jump)
    joined = extract_planes(pts, max_increment=math.inf, refit=False)
    split = extract_planes(pts, max_increment=math.inf, max_distance_m=0.5, refit=False)

    def shared(labels):
        return set(labels[:, :6].ravel()) & set(labels[:, 6:].ravel()) - {-1}

    assert shared(joined.labels)
    assert not shared(split.labels)
    assert split.n_planes == 2 and (split.labels >= 0).all()


def test_max_planes_and_max_increment_stop():
    pts, _ = _scene_scan(h=10, w=12, sigma=0.02, seed=1)
    seg = extract_planes(pts, max_increment=None, max_planes=30, refit=False)
    assert seg.stop is PPEStop.MAX_PLANES
    J = seg.n_planes + seg.n_atoms
    assert 27 < J <= 30
    seg = extract_planes(pts, max_increment=1e-3, refit=False)
    assert seg.stop is PPEStop.MAX_INCREMENT and seg.step_costs.max() <= 1e-3


@pytest.mark.parametrize(
    "points, kwargs, match",
    [
        (np.ones((4, 4, 2)), {}, "points"),
        (np.ones((1, 9, 3)), {}, "points"),
        (np.full((4, 4, 3), np.nan), {}, "points"),
        (
            np.where(np.eye(4, dtype=bool)[..., None] & (np.arange(3) == 0), np.nan, 1.0),
            {},
            "partly NaN",
        ),
        (np.where(np.eye(4, dtype=bool)[..., None], np.inf, np.ones((4, 4, 3))), {}, "inf"),
        (np.zeros((4, 4, 3)), {}, "origin"),
        (np.ones((4, 4, 3)), dict(max_increment=-1.0), "max_increment"),
        (np.ones((4, 4, 3)), dict(max_planes=0), "max_planes"),
        (np.ones((4, 4, 3)), dict(max_distance_m=0.0), "max_distance_m"),
        (np.ones((4, 4, 3)), dict(min_points=3), "min_points"),
    ],
)
def test_bad_input(points, kwargs, match):
    with pytest.raises(ValueError, match=match):
        extract_planes(points, **kwargs)


def test_path_equals_separate_runs(synpeb_crop):
    sub = synpeb_crop[50:64, 60:74]
    incs = [2e-3, 1e-5, 5e-4]
    path = extract_planes_path(sub, incs, max_distance_m=0.1, refit=False)
    for e, seg in zip(incs, path):
        one = extract_planes(sub, max_increment=e, max_distance_m=0.1, refit=False)
        np.testing.assert_array_equal(seg.labels, one.labels)
        np.testing.assert_array_equal(seg.step_costs, one.step_costs)
        assert seg.stop == one.stop
    assert path[1].n_planes != path[0].n_planes
    with pytest.raises(ValueError, match="max_increments"):
        extract_planes_path(sub, [])
    with pytest.raises(ValueError, match="max_increment"):
        extract_planes_path(sub, [1e-3, -1.0])


def test_reference_is_private_and_stop_is_an_enumeration():
    """Issue #21: the reference lives in lidarjax.features._ppe_reference only, and the
    result stores why the loop stopped as a PPEStop."""
    import lidarjax.features

    assert not hasattr(lidarjax.features, "extract_planes_reference")
    assert "extract_planes_reference" not in lidarjax.features.__all__
    assert {s.value for s in PPEStop} == {"max_planes", "max_increment", "exhausted"}
    pts, _ = _scene_scan(h=6, w=7, sigma=0.02, seed=2)
    seg = extract_planes(pts, max_increment=1e-3, refit=False)
    assert isinstance(seg.stop, PPEStop) and not hasattr(seg, "stop_reason")
