"""Reference-free map consistency (lidarjax.metrics.cross_visit_distance): exact against a
brute-force NumPy reference, and it ranks a mis-closed loop below the true trajectory."""

from __future__ import annotations

import numpy as np
import pytest

from lidarjax.metrics import cross_visit_distance
from lidarjax.sim import make_office, simulate_scans


def _brute(poses, ranges, az, sep, max_range, cap):
    ok = (ranges > 0) & (ranges < max_range)
    ang = poses[:, 2:3] + az
    pts = np.stack([poses[:, 0:1] + ranges * np.cos(ang), poses[:, 1:2] + ranges * np.sin(ang)], -1)
    out = np.full(ranges.shape, np.nan)
    n = len(poses)
    for i in range(n):
        others = np.concatenate(
            [pts[j][ok[j]] for j in range(n) if abs(i - j) >= sep] or [np.zeros((0, 2))]
        )
        for k in np.flatnonzero(ok[i]):
            if others.size:
                d = np.hypot(*(others - pts[i, k]).T).min()
                if d <= cap:
                    out[i, k] = d
    return out


@pytest.mark.parametrize(
    ("sep", "cap", "chunk"),
    [(5, 0.3, 65536), (1, 0.2, 7), (39, 1.0, 100), (10, 0.05, 65536), (40, 1.0, 64)],
)
def test_cross_visit_distance_matches_brute_force(sep, cap, chunk):
    rng = np.random.default_rng(0)
    n, b = 40, 25
    poses = np.c_[rng.uniform(0, 3, (n, 2)), rng.uniform(-3, 3, n)]
    ranges = rng.uniform(0, 4, (n, b))
    ranges[rng.random((n, b)) < 0.1] = 0.0  # no reading
    ranges[rng.random((n, b)) < 0.1] = 5.0  # beyond max_range_m: no end point
    az = np.linspace(-1.5, 1.5, b)
    r = cross_visit_distance(
        poses, ranges, az, min_separation=sep, max_range_m=4.5, cap_m=cap, chunk_size=chunk
    )
    ref = _brute(poses, ranges, az, sep, 4.5, cap)
    np.testing.assert_array_equal(np.isnan(r.distances_m), np.isnan(ref))
    np.testing.assert_allclose(r.distances_m, ref, rtol=0, atol=1e-12)
    fin = ref[np.isfinite(ref)]
    ok = (ranges > 0) & (ranges < 4.5)
    assert r.n_points == ok.sum()
    assert r.fraction == pytest.approx(fin.size / ok.sum())
    if fin.size:
        assert r.mean_m == pytest.approx(fin.mean(), abs=1e-12)
        assert r.median_m == pytest.approx(np.median(fin), abs=1e-12)
        assert r.p90_m == pytest.approx(np.percentile(fin, 90), abs=1e-12)
    else:  # sep 40 = n: no other visit at all
        assert sep >= n and np.isnan(r.mean_m) and r.fraction == 0


def test_cross_visit_distance_counts_distances_of_exactly_the_cap():
    # two scans of one beam, end points 0.25 m apart (exact in binary)
    poses = np.array([[0.0, 0.0, 0.0], [0.0, 0.25, 0.0]])
    r = cross_visit_distance(poses, np.ones((2, 1)), np.zeros(1), min_separation=1, cap_m=0.25)
    np.testing.assert_array_equal(r.distances_m, [[0.25], [0.25]])
    r = cross_visit_distance(poses, np.ones((2, 1)), np.zeros(1), min_separation=1, cap_m=0.2)
    assert np.isnan(r.distances_m).all() and r.fraction == 0 and np.isnan(r.mean_m)
    # numpy scalars are numbers too
    r = cross_visit_distance(
        poses, np.ones((2, 1)), np.zeros(1), min_separation=np.int64(1), cap_m=np.float32(0.5)
    )
    assert r.fraction == 1


def test_cross_visit_distance_ranks_a_misclosed_loop_below_the_truth():
    world = make_office(0)
    lap = world.trajectory(60, jitter_m=0.2)
    truth = np.vstack([lap, lap[:20]])  # the last 20 scans revisit the start
    az = np.linspace(-np.pi / 2, np.pi / 2, 181)
    ranges = simulate_scans(world, truth, az, max_range_m=30.0, noise_sigma_m=0.01, seed=0)
    scores = {}
    for shift in (0.0, 0.05, 0.15):
        est = truth.copy()
        est[60:, 0] += shift  # the second visit of the start off by `shift` along x
        scores[shift] = cross_visit_distance(est, ranges, az, max_range_m=30.0, min_separation=50)
    # measured: mean 17.2 / 25.4 / 40.7 mm (the truth's are not 0: the two visits sample
    # the walls at different points)
    assert scores[0.0].mean_m < 0.8 * scores[0.05].mean_m < 0.8 * 0.8 * scores[0.15].mean_m
    # a rigid motion of the whole trajectory changes nothing
    c, s = np.cos(0.7), np.sin(0.7)
    moved = np.c_[
        3 + c * truth[:, 0] - s * truth[:, 1],
        -2 + s * truth[:, 0] + c * truth[:, 1],
        truth[:, 2] + 0.7,
    ]
    m = cross_visit_distance(moved, ranges, az, max_range_m=30.0, min_separation=50)
    np.testing.assert_allclose(m.distances_m, scores[0.0].distances_m, atol=1e-9)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"poses": np.zeros((3, 2))}, "poses"),
        ({"poses": np.full((4, 3), np.nan)}, "poses"),
        ({"ranges_m": np.ones(5)}, "ranges_m"),
        ({"ranges_m": -np.ones((4, 5))}, "ranges_m"),
        ({"ranges_m": np.full((4, 5), np.nan)}, "ranges_m"),
        ({"azimuths_rad": np.zeros(4)}, "azimuths_rad"),
        ({"min_separation": 0}, "min_separation"),
        ({"min_separation": True}, "min_separation"),
        ({"min_separation": 2.0}, "min_separation"),
        ({"max_range_m": 0.0}, "max_range_m"),
        ({"cap_m": np.inf}, "cap_m"),
        ({"cap_m": -1.0}, "cap_m"),
        ({"chunk_size": 0}, "chunk_size"),
    ],
)
def test_cross_visit_distance_rejects_bad_input(kwargs, name):
    args = {
        "poses": np.zeros((4, 3)),
        "ranges_m": np.ones((4, 5)),
        "azimuths_rad": np.zeros(5),
        **kwargs,
    }
    with pytest.raises(ValueError, match=name):
        cross_visit_distance(**args)
