"""Tests of the plane-segmentation metrics (Hoover scores, k of Eq. (11.5), RMSE of
Eq. (11.6)) on hand-labelled toy segmentations and against a loop reference."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from lidarjax.metrics import HooverScores, hoover_scores, k_value, segmentation_rmse


def _halves() -> np.ndarray:
    """6x6 ground truth: label 1 in columns 0-2, label 2 in columns 3-5 (18 points each)."""
    gt = np.ones((6, 6), dtype=int)
    gt[:, 3:] = 2
    return gt


def _quadrants() -> np.ndarray:
    """6x6 ground truth: quadrants 1 (top left), 2 (top right), 3, 4 (9 points each)."""
    gt = np.empty((6, 6), dtype=int)
    gt[:3, :3], gt[:3, 3:], gt[3:, :3], gt[3:, 3:] = 1, 2, 3, 4
    return gt


def _counts(s: HooverScores) -> tuple[int, ...]:
    return (s.n_correct, s.n_over, s.n_under, s.n_missed, s.n_noise)


# ----------------------------------------------------------------------------- toy cases


def test_perfect_segmentation():
    gt = _quadrants()
    relabel = {1: 7, 2: 0, 3: 3, 4: 5}
    pred = np.vectorize(relabel.get)(gt)
    s = hoover_scores(gt, pred)
    assert (s.n_gt, s.n_pred) == (4, 4)
    assert _counts(s) == (4, 0, 0, 0, 0)
    np.testing.assert_array_equal(s.correct_pairs, [[1, 7], [2, 0], [3, 3], [4, 5]])
    assert s.f == 1.0 and s.k == 1.0
    assert np.isnan(s.angle_deg) and s.n_angle_pairs == 0


def test_over_segmentation():
    gt = _halves()
    pred = np.full((6, 6), 2)
    pred[:3, :3] = 0  # region 1 split into a top ...
    pred[3:, :3] = 1  # ... and a bottom half
    s = hoover_scores(gt, pred)
    assert _counts(s) == (1, 1, 0, 0, 0)
    np.testing.assert_array_equal(s.over_segmented, [1])
    np.testing.assert_array_equal(s.correct_pairs, [[2, 2]])
    assert s.f == 0.5 and s.k == 0.5


def test_over_segmentation_needs_enough_coverage():
    gt = _halves()
    pred = np.full((6, 6), 2)
    pred[:2, :3] = 0  # 6 points
    pred[2:4, :3] = 1  # 6 points; the parts cover 12 < 0.8 * 18 points of region 1
    pred[4:, :3] = -1
    s = hoover_scores(gt, pred)
    assert _counts(s) == (1, 0, 0, 1, 2)
    np.testing.assert_array_equal(s.missed, [1])
    np.testing.assert_array_equal(s.noise, [0, 1])


def test_under_segmentation():
    gt = _quadrants()
    pred = np.where(gt <= 2, 0, gt)  # the two top quadrants merged into machine region 0
    s = hoover_scores(gt, pred)
    assert _counts(s) == (2, 0, 1, 0, 0)
    np.testing.assert_array_equal(s.under_segmenting, [0])
    np.testing.assert_array_equal(s.correct_pairs, [[3, 3], [4, 4]])


def test_missed_region_unassigned():
    gt = _halves()
    pred = np.where(gt == 1, 0, -1)
    s = hoover_scores(gt, pred)
    assert s.n_pred == 1
    assert _counts(s) == (1, 0, 0, 1, 0)
    np.testing.assert_array_equal(s.missed, [2])


def test_missed_region_scattered():
    # Region 2 is covered by machine regions that straddle it and region 3; none lies
    # mostly inside one ground-truth region and none covers one to 80 %.
    gt = np.repeat([1, 2, 3], 12).reshape(6, 6)  # rows 0-1: 1, rows 2-3: 2, rows 4-5: 3
    pred = np.zeros((6, 6), dtype=int)
    pred[2:, :] = np.array([1, 1, 2, 2, 3, 3])[None, :]
    s = hoover_scores(gt, pred)
    np.testing.assert_array_equal(s.correct_pairs, [[1, 0]])
    np.testing.assert_array_equal(s.missed, [2, 3])
    np.testing.assert_array_equal(s.noise, [1, 2, 3])
    assert _counts(s) == (1, 0, 0, 2, 3)


def test_noise_region():
    gt = _halves()
    pred = np.where(gt == 1, 0, 1)
    pred[0:2, 2:4] = 5  # 4 points, half in each ground-truth region
    s = hoover_scores(gt, pred)
    assert _counts(s) == (2, 0, 0, 0, 1)
    np.testing.assert_array_equal(s.noise, [5])
    np.testing.assert_array_equal(s.correct_pairs, [[1, 0], [2, 1]])


def test_correct_detection_takes_precedence_over_over_segmentation():
    # Machine region 0 covers 16 of the 18 points of region 1 and is correct; fragment 3
    # (2 points inside region 1) would make {0, 3} an over-segmentation, but a region in a
    # correct detection takes no part in other classes, so the fragment is noise.
    gt = _halves()
    pred = np.where(gt == 1, 0, 1)
    pred[0:2, 0] = 3
    s = hoover_scores(gt, pred)
    assert _counts(s) == (2, 0, 0, 0, 1)
    np.testing.assert_array_equal(s.noise, [3])


@pytest.mark.parametrize(
    ("threshold", "size", "overlap", "correct"),
    [
        (0.8, 10, 8, True),  # exactly T * M_m counts
        (0.8, 10, 7, False),  # just below does not
        (0.7, 10, 7, True),  # 0.7 * 10 = 7.000000000000001 in floating point
        (0.9, 10, 9, True),
        (0.9, 10, 8, False),
        (1.0, 10, 10, True),
        (1.0, 10, 9, False),
    ],
)
def test_threshold_boundary_gt_side(threshold, size, overlap, correct):
    gt = np.ones(size, dtype=int)
    pred = np.full(size, -1)
    pred[:overlap] = 0
    s = hoover_scores(gt, pred, threshold=threshold)
    assert (s.n_correct == 1) is correct
    assert (s.n_missed, s.n_noise) == ((0, 0) if correct else (1, 1))


@pytest.mark.parametrize(("inside", "correct"), [(8, True), (7, False)])
def test_threshold_boundary_pred_side(inside, correct):
    # Machine region 0 has 10 points, `inside` of them on region 1 (8 points), the rest on
    # region 2 (20 points, correctly detected by machine region 1 elsewhere).
    gt = np.array([1] * 8 + [2] * (10 - inside + 20))
    pred = np.array([0] * inside + [-1] * (8 - inside) + [0] * (10 - inside) + [1] * 20)
    assert np.sum(pred == 0) == 10
    s = hoover_scores(gt, pred)
    assert s.n_gt == 2
    assert ([1, 0] in s.correct_pairs.tolist()) is correct


def test_unlabelled_gt_points_are_ignored():
    gt = _quadrants()
    pred = gt - 1
    ref = hoover_scores(gt, pred)
    gt2 = np.zeros((8, 8), dtype=int)
    gt2[:6, :6] = gt
    gt2[0, 0] = -3  # negative ground truth is unlabelled too
    pred2 = np.full((8, 8), 9)  # machine region 9 lies only on unlabelled points
    pred2[:6, :6] = pred
    pred2[6:, :3] = 0  # region 0 extends onto 6 unlabelled points
    pred2[0, 0] = 1  # a point of region 0 on unlabelled truth is given to region 1
    s = hoover_scores(gt2, pred2)
    assert (s.n_gt, s.n_pred) == (4, 4)
    assert _counts(s) == _counts(ref) == (4, 0, 0, 0, 0)
    assert s.k == 1.0  # region 1 has 8 labelled points now, all correctly detected
    # The authors' convention counts every machine point: region 0 then has 8 of its 14
    # points on region 1 (< 80 %), region 9 is noise.
    s2 = hoover_scores(gt2, pred2, count_unlabelled=True)
    assert s2.n_pred == 5
    assert _counts(s2) == (3, 0, 0, 1, 2)
    np.testing.assert_array_equal(s2.noise, [0, 9])


def test_min_gt_label_excludes_non_plane_labels():
    """SynPEB files number their planes from 10 (the authors' evaluation counts labels
    >= 10); a smaller label (the shared crop's 3) is not a plane and must not count."""
    gt = _quadrants() + 10  # planes 11 .. 14
    gt[0, :] = 3  # a non-plane class over the top row (3 rays each of planes 11 and 12)
    pred = np.where(gt >= 10, gt - 11, -1)  # every plane found exactly, the class left out
    by_default = hoover_scores(gt, pred)  # label 3 counts as a plane that is missed
    assert (by_default.n_gt, by_default.n_missed, by_default.n_correct) == (5, 1, 4)
    assert by_default.f == 4 / 5 and by_default.k == 30 / 36
    s = hoover_scores(gt, pred, min_gt_label=10)
    assert (s.n_gt, s.n_missed, s.n_correct) == (4, 0, 4)
    assert s.f == 1.0 and s.k == 1.0
    assert k_value(gt, pred, min_gt_label=10) == 1.0
    # independent reference: the same as relabelling the non-plane class as unlabelled (0)
    rng = np.random.default_rng(5)
    gt_r = rng.choice([0, 3, 7, 10, 11, 12], size=(20, 20))
    pred_r = rng.choice([-1, 0, 1, 2], size=(20, 20))
    for t in (0.6, 0.8):
        a = hoover_scores(gt_r, pred_r, threshold=t, min_gt_label=10)
        b = hoover_scores(np.where(gt_r >= 10, gt_r, 0), pred_r, threshold=t)
        assert _counts(a) == _counts(b) and (a.n_gt, a.n_pred) == (b.n_gt, b.n_pred) == (3, 3)
        assert a.f == b.f and a.k == b.k
    for bad in (0, -1, 2.5, True, "10"):
        with pytest.raises(ValueError, match="min_gt_label"):
            hoover_scores(gt, pred, min_gt_label=bad)


def test_min_gt_label_on_the_shared_crop():
    """The shared SynPEB crop has 13 labels, one of them (3, 20 rays) below 10."""
    from lidarjax.datasets import fetch, load_synpeb_pcd

    _, gt = load_synpeb_pcd(fetch("synpeb-test-100"))
    labels = np.unique(gt[gt > 0])
    assert labels.size == 13 and labels[labels < 10].tolist() == [3]
    perfect = np.where(gt > 0, gt, -1)
    assert hoover_scores(gt, perfect).n_gt == 13
    s = hoover_scores(gt, perfect, min_gt_label=10)
    assert s.n_gt == 12 and s.n_correct == 12 and s.n_pred == 12


def test_label_permutation_invariance():
    rng = np.random.default_rng(3)
    for _ in range(10):
        gt, pred = _random_case(rng)
        s = hoover_scores(gt, pred)
        gmap = rng.permutation(np.arange(1, 40))  # positive -> positive
        pmap = rng.permutation(np.arange(0, 40)) + 100  # non-negative -> non-negative
        gt2 = np.where(gt > 0, gmap[np.maximum(gt, 1) - 1], gt)
        pred2 = np.where(pred >= 0, pmap[np.maximum(pred, 0)], pred)
        s2 = hoover_scores(gt2, pred2)
        assert _counts(s2) == _counts(s)
        assert (s2.n_gt, s2.n_pred, s2.k) == (s.n_gt, s.n_pred, s.k)
        mapped = {(int(gmap[a - 1]), int(pmap[b])) for a, b in s.correct_pairs.tolist()}
        assert {tuple(p) for p in s2.correct_pairs.tolist()} == mapped


def test_flat_and_image_inputs_agree():
    rng = np.random.default_rng(5)
    gt, pred = _random_case(rng)
    a = hoover_scores(gt, pred)
    b = hoover_scores(gt.ravel(), pred.ravel())
    assert _counts(a) == _counts(b)
    np.testing.assert_array_equal(a.correct_pairs, b.correct_pairs)


def test_empty_prediction():
    gt = _halves()
    s = hoover_scores(gt, np.full((6, 6), -1))
    assert (s.n_pred, s.n_missed, s.f, s.k) == (0, 2, 0.0, 0.0)
    assert s.correct_pairs.shape == (0, 2)


def test_empty_ground_truth():
    s = hoover_scores(np.zeros((3, 3), dtype=int), np.zeros((3, 3), dtype=int))
    assert (s.n_gt, s.n_pred) == (0, 0)
    assert np.isnan(s.f) and np.isnan(s.k)


# ----------------------------------------------------------------- loop reference checks


def _reference(gt, pred, threshold):
    """Hoover classification with explicit loops over regions and exact rationals."""
    t = Fraction(str(threshold))
    labelled = gt > 0
    gts = sorted(set(gt[labelled].tolist()))
    preds = sorted(set(pred[labelled & (pred >= 0)].tolist()))
    size_gt = {m: int(np.sum(gt == m)) for m in gts}
    size_pred = {n: int(np.sum((pred == n) & labelled)) for n in preds}
    ov = {(m, n): int(np.sum((gt == m) & (pred == n))) for m in gts for n in preds}

    correct = []
    for m in gts:
        for n in preds:
            o = ov[m, n]
            if o >= t * size_pred[n] and o >= t * size_gt[m]:
                correct.append((m, n))
    gt_c = {m for m, _ in correct}
    pred_c = {n for _, n in correct}

    over, over_parts = [], set()
    for m in gts:
        if m in gt_c:
            continue
        parts = [n for n in preds if n not in pred_c and 0 < ov[m, n] >= t * size_pred[n]]
        if len(parts) >= 2 and sum(ov[m, n] for n in parts) >= t * size_gt[m]:
            over.append(m)
            over_parts.update(parts)
    under, under_parts = [], set()
    for n in preds:
        if n in pred_c:
            continue
        parts = [m for m in gts if m not in gt_c and 0 < ov[m, n] >= t * size_gt[m]]
        if len(parts) >= 2 and sum(ov[m, n] for m in parts) >= t * size_pred[n]:
            under.append(n)
            under_parts.update(parts)
    missed = [m for m in gts if m not in gt_c and m not in over and m not in under_parts]
    noise = [n for n in preds if n not in pred_c and n not in under and n not in over_parts]
    k = sum(size_gt[m] for m in gt_c) / int(labelled.sum()) if labelled.any() else np.nan
    return {
        "correct": sorted(correct),
        "over": over,
        "under": under,
        "missed": missed,
        "noise": noise,
        "k": k,
        "sets": (gt_c, pred_c, over, over_parts, under, under_parts, missed, noise),
    }


def _random_case(rng, shape=(12, 12)):
    """Blocky random ground truth and a prediction derived from it by random merges,
    splits, erasures and spurious patches."""
    h, w = shape
    n_gt = rng.integers(1, 8)
    # ground truth: nearest of a few random seeds (Voronoi cells), some cells unlabelled
    seeds = rng.uniform(0, [h, w], size=(n_gt, 2))
    yy, xx = np.mgrid[:h, :w]
    d = (yy[..., None] - seeds[:, 0]) ** 2 + (xx[..., None] - seeds[:, 1]) ** 2
    gt = np.argmin(d, axis=-1) + 1
    gt[rng.random(shape) < rng.uniform(0, 0.15)] = 0
    # prediction: each ground-truth region maps to a random machine label (merges)
    pred = rng.integers(0, n_gt + 2, size=n_gt + 1)[np.where(gt > 0, gt, 0)]
    pred[gt == 0] = rng.integers(-1, n_gt + 2, size=int(np.sum(gt == 0)))
    # splits along a random line
    for _ in range(rng.integers(0, 3)):
        lab = rng.integers(0, n_gt + 2)
        cut = rng.integers(0, w)
        pred[(pred == lab) & (xx >= cut)] = rng.integers(10, 20)
    # spurious rectangular patches and erased points
    for _ in range(rng.integers(0, 3)):
        y0, x0 = rng.integers(0, h - 2), rng.integers(0, w - 2)
        pred[y0 : y0 + rng.integers(1, 5), x0 : x0 + rng.integers(1, 5)] = rng.integers(20, 25)
    pred[rng.random(shape) < rng.uniform(0, 0.2)] = -1
    return gt, pred


@pytest.mark.parametrize("seed", range(60))
def test_matches_loop_reference(seed):
    rng = np.random.default_rng(seed)
    gt, pred = _random_case(rng)
    threshold = float(rng.choice([0.55, 0.6, 0.7, 0.75, 0.8, 0.9, 1.0]))
    s = hoover_scores(gt, pred, threshold=threshold)
    ref = _reference(gt, pred, threshold)
    assert [tuple(p) for p in s.correct_pairs.tolist()] == ref["correct"]
    assert s.over_segmented.tolist() == ref["over"]
    assert s.under_segmenting.tolist() == ref["under"]
    assert s.missed.tolist() == ref["missed"]
    assert s.noise.tolist() == ref["noise"]
    assert s.k == pytest.approx(ref["k"])
    # Every region gets exactly one class.
    gt_c, pred_c, over, over_parts, under, under_parts, missed, noise = ref["sets"]
    for m in set(gt[gt > 0].tolist()):
        assert (m in gt_c) + (m in over) + (m in under_parts) + (m in missed) == 1
    for n in set(pred[(gt > 0) & (pred >= 0)].tolist()):
        assert (n in pred_c) + (n in under) + (n in over_parts) + (n in noise) == 1
    assert s.n_correct + s.n_over + len(under_parts) + s.n_missed == s.n_gt


def test_random_cases_hit_every_class():
    """The random generator exercises all five classes, so the reference check has teeth."""
    totals = np.zeros(5, dtype=int)
    for seed in range(60):
        rng = np.random.default_rng(seed)
        gt, pred = _random_case(rng)
        threshold = float(rng.choice([0.55, 0.6, 0.7, 0.75, 0.8, 0.9, 1.0]))
        totals += np.array(_counts(hoover_scores(gt, pred, threshold=threshold)))
    assert np.all(totals > 0), totals


# -------------------------------------------------------------------------------- angle


def _angle_case():
    gt = np.zeros((6, 6), dtype=int)
    gt[:, :2], gt[:, 2:4], gt[:, 4:] = 1, 2, 3
    pred = gt + 10
    gt_normals = np.array([[0, 0, 0], [0, 0, 1], [1, 0, 0], [0, 1, 0]], dtype=float)
    a = np.radians(10.0)
    pred_normals = {
        11: np.array([0.0, 0.0, -2.0]),  # sign and length do not matter
        12: np.array([np.cos(a), 0.0, np.sin(a)]),  # 80 deg to plane 11 instead of 90
        13: np.array([0.0, 1.0, 0.0]),
    }
    adjacent = np.array([[1, 2], [2, 3], [1, 3]])
    return gt, pred, gt_normals, pred_normals, adjacent


def test_angle_metric():
    gt, pred, gn, pn, adj = _angle_case()
    s = hoover_scores(gt, pred, gt_normals=gn, pred_normals=pn, gt_adjacent=adj)
    assert s.n_angle_pairs == 3
    assert s.angle_deg == pytest.approx(10.0 / 3.0)


def test_angle_metric_skips_pairs_not_correctly_detected():
    gt, pred, gn, pn, adj = _angle_case()
    pred[gt == 3] = -1  # plane 3 missed: only pair (1, 2) remains
    s = hoover_scores(gt, pred, gt_normals=gn, pred_normals=pn, gt_adjacent=adj)
    assert s.n_angle_pairs == 1
    assert s.angle_deg == pytest.approx(10.0)
    pred[gt == 2] = -1
    s = hoover_scores(gt, pred, gt_normals=gn, pred_normals=pn, gt_adjacent=adj)
    assert s.n_angle_pairs == 0 and np.isnan(s.angle_deg)


def test_angle_metric_obtuse_normals_fold_to_acute():
    gt, pred, gn, pn, _ = _angle_case()
    gn = gn.copy()
    gn[2] = [np.cos(np.radians(120)), 0.0, np.sin(np.radians(120))]  # 30 deg to z, folded
    pn = dict(pn)
    pn[12] = np.array([np.cos(np.radians(65)), 0.0, np.sin(np.radians(65))])  # 25 deg
    s = hoover_scores(gt, pred, gt_normals=gn, pred_normals=pn, gt_adjacent=[[1, 2]])
    assert s.angle_deg == pytest.approx(5.0)


# ------------------------------------------------------------------------------------ k


def test_k_value_toy():
    gt = np.array([1] * 20 + [2] * 10 + [3] * 6 + [0] * 8)
    pred = np.array([0] * 20 + [1] * 5 + [2] * 5 + [3] * 6 + [4] * 8)
    # planes 1 and 3 correct (26 points), plane 2 over-segmented but not correct
    assert k_value(gt, pred) == pytest.approx(26 / 36)
    s = hoover_scores(gt, pred)
    assert s.k == pytest.approx(26 / 36)
    assert s.f == pytest.approx(2 / 3)
    assert _counts(s) == (2, 1, 0, 0, 0)


def test_k_counts_whole_gt_plane_for_a_correct_detection():
    gt = np.array([1] * 10 + [2] * 10)
    pred = np.array([0] * 8 + [-1] * 2 + [1] * 10)  # plane 1 correct at 80 % coverage
    assert k_value(gt, pred) == pytest.approx(1.0)
    assert k_value(gt, pred, threshold=0.9) == pytest.approx(0.5)


# --------------------------------------------------------------------------------- RMSE


def test_segmentation_rmse_pools_rays():
    labels = np.array([0, 0, 0, 1, -1, -1])
    ranges = np.array([1.0, 2.0, 3.0, 4.0, np.nan, 7.0])
    rhat = np.array([1.1, 1.9, 3.0, 4.4, 5.0, np.inf])
    expected = np.sqrt((0.01 + 0.01 + 0.0 + 0.16) / 4)  # over rays, not planes
    assert segmentation_rmse(ranges, rhat, labels) == pytest.approx(expected)
    per_plane = np.sqrt((0.02 / 3 + 0.16) / 2)
    assert abs(segmentation_rmse(ranges, rhat, labels) - per_plane) > 1e-3


def test_segmentation_rmse_image_and_outlier_guard():
    rng = np.random.default_rng(0)
    labels = rng.integers(-1, 4, size=(5, 7))
    ranges = rng.uniform(1.0, 10.0, size=(5, 7))
    rhat = ranges + rng.normal(0.0, 0.02, size=(5, 7))
    rhat[labels == 3] += 20.0  # a wildly wrong plane
    use = labels >= 0
    direct = np.sqrt(np.mean((ranges[use] - rhat[use]) ** 2))
    assert segmentation_rmse(ranges, rhat, labels) == pytest.approx(direct)
    keep = use & (labels != 3)
    guarded = np.sqrt(np.mean((ranges[keep] - rhat[keep]) ** 2))
    assert segmentation_rmse(ranges, rhat, labels, max_plane_rmse_m=10.0) == pytest.approx(guarded)


def test_segmentation_rmse_no_assigned_ray_is_nan():
    assert np.isnan(segmentation_rmse(np.ones(3), np.ones(3), np.full(3, -1)))


# ---------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (
            {"gt_labels": np.ones((3, 3), dtype=int), "pred_labels": np.ones((3, 4), dtype=int)},
            "gt_labels and pred_labels",
        ),
        ({"gt_labels": np.ones((3, 3)), "pred_labels": np.ones((3, 3), dtype=int)}, "gt_labels"),
        (
            {"gt_labels": np.ones((3, 3), dtype=int), "pred_labels": np.ones((3, 3)) * 0.5},
            "pred_labels",
        ),
        ({"gt_labels": np.ones(3, dtype=bool), "pred_labels": np.ones(3, dtype=int)}, "gt_labels"),
        (
            {
                "gt_labels": np.ones(3, dtype=int),
                "pred_labels": np.ones(3, dtype=int),
                "threshold": 0.5,
            },
            "threshold",
        ),
        (
            {
                "gt_labels": np.ones(3, dtype=int),
                "pred_labels": np.ones(3, dtype=int),
                "threshold": 1.01,
            },
            "threshold",
        ),
        (
            {
                "gt_labels": np.ones(3, dtype=int),
                "pred_labels": np.ones(3, dtype=int),
                "threshold": float("nan"),
            },
            "threshold",
        ),
        (
            {
                "gt_labels": np.ones(3, dtype=int),
                "pred_labels": np.ones(3, dtype=int),
                "gt_adjacent": [[1, 2]],
            },
            "gt_normals",
        ),
        (
            {
                "gt_labels": np.ones(3, dtype=int),
                "pred_labels": np.ones(3, dtype=int),
                "gt_normals": np.eye(3),
                "pred_normals": np.eye(3),
                "gt_adjacent": [1, 2],
            },
            "gt_adjacent",
        ),
        (
            {
                "gt_labels": np.ones(3, dtype=int),
                "pred_labels": np.ones(3, dtype=int),
                "gt_normals": np.eye(3),
                "pred_normals": np.eye(3),
                "gt_adjacent": [[1.0, 2.0]],
            },
            "gt_adjacent",
        ),
    ],
)
def test_hoover_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        hoover_scores(**kwargs)


def test_bad_normals():
    gt, pred, gn, pn, adj = _angle_case()
    gn = gn.copy()
    gn[1] = 0.0
    with pytest.raises(ValueError, match="gt_normals"):
        hoover_scores(gt, pred, gt_normals=gn, pred_normals=pn, gt_adjacent=adj)
    _, _, gn, pn, _ = _angle_case()
    del pn[13]
    with pytest.raises(ValueError, match="pred_normals"):
        hoover_scores(gt, pred, gt_normals=gn, pred_normals=pn, gt_adjacent=adj)


def test_k_value_bad_input():
    with pytest.raises(ValueError, match="threshold"):
        k_value(np.ones(3, dtype=int), np.ones(3, dtype=int), threshold=0.3)


def test_segmentation_rmse_bad_input():
    ok = np.ones(3)
    with pytest.raises(ValueError, match="ranges, rhat and pred_labels"):
        segmentation_rmse(ok, np.ones(4), np.zeros(3, dtype=int))
    with pytest.raises(ValueError, match="pred_labels"):
        segmentation_rmse(ok, ok, np.zeros(3))
    with pytest.raises(ValueError, match="rhat"):
        segmentation_rmse(ok, np.array([1.0, np.inf, 1.0]), np.zeros(3, dtype=int))
    with pytest.raises(ValueError, match="ranges"):
        segmentation_rmse(np.array([np.nan, 1.0, 1.0]), ok, np.zeros(3, dtype=int))
    with pytest.raises(ValueError, match="max_plane_rmse_m"):
        segmentation_rmse(ok, ok, np.zeros(3, dtype=int), max_plane_rmse_m=0.0)
