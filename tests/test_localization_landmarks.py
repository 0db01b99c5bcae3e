"""Pole-landmark mapping and localization (sections 12.4.2, 12.4.3)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lidarjax.features import Poles
from lidarjax.localization import (
    OdometryMotionModel,
    ParticleFilter,
    PoleMeasurementModel,
    build_pole_lookup,
    from_vector,
    init_uniform_disc,
    map_poles,
    merge_poles,
    overlap_clusters,
    pad_poles,
    segment_scans,
    sliding_window_filter,
    to_vector,
)
from lidarjax.localization._landmarks import pole_log_likelihood_reference


def brute_clusters(xy, w):
    n = len(xy)
    parent = list(range(n))

    def find(i):
        while parent[i] != i:
            i = parent[i]
        return i

    for i in range(n):
        for j in range(i + 1, n):
            h = 0.5 * (w[i] + w[j])
            if abs(xy[i, 0] - xy[j, 0]) < h and abs(xy[i, 1] - xy[j, 1]) < h:
                parent[find(i)] = find(j)
    return np.array([find(i) for i in range(n)])


def same_partition(a, b):
    return all((a[i] == a[j]) == (b[i] == b[j]) for i in range(len(a)) for j in range(len(a)))


def test_overlap_clusters_match_brute_force():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 6, (80, 2))
    w = rng.uniform(0.1, 0.9, 80)
    assert same_partition(overlap_clusters(xy, w), brute_clusters(xy, w))


def test_merge_poles_merges_duplicates_by_score():
    truth = np.array([[0.0, 0.0], [5.0, 1.0], [10.0, -3.0]])
    rng = np.random.default_rng(1)
    maps = []
    for _ in range(4):
        maps.append(
            Poles(truth + rng.normal(0, 0.05, truth.shape), np.full(3, 0.3), rng.uniform(0.6, 1, 3))
        )
    merged = merge_poles(maps)
    assert len(merged) == 3
    order = np.argsort(merged.xy[:, 0])
    allxy = np.stack([m.xy for m in maps])  # [4 3 2]
    alls = np.stack([m.score for m in maps])  # [4 3]
    expect = (alls[..., None] * allxy).sum(0) / alls.sum(0)[:, None]
    np.testing.assert_allclose(merged.xy[order], expect, atol=1e-12)
    np.testing.assert_allclose(merged.score[order], alls.mean(0), atol=1e-12)
    np.testing.assert_array_equal(merged.n_detections, [4, 4, 4])
    assert len(merge_poles(maps, min_detections=5)) == 0
    assert len(merge_poles([])) == 0


def test_sliding_window_drops_transient_poles():
    static = np.array([[0.0, 0.0], [4.0, 0.0]])
    local = []
    for t in range(5):
        xy = static.copy()
        if t == 2:  # a pedestrian seen once
            xy = np.vstack([xy, [2.0, 3.0]])
        local.append(Poles(xy, np.full(len(xy), 0.3), np.full(len(xy), 0.8)))
    out = sliding_window_filter(local, c=2, w=3)
    assert [len(p) for p in out][1:] == [2, 2, 2, 2]
    assert len(out[2]) == 2 and not np.any(np.all(out[2].xy == [2.0, 3.0], axis=1))
    # the first map has no history: its poles were seen once only
    assert len(out[0]) == 0
    m = map_poles(local, c=2, w=3)
    assert len(m) == 2
    with pytest.raises(ValueError, match="c <= w"):
        sliding_window_filter(local, c=4, w=3)


def test_lookup_is_exact_nearest_neighbour():
    rng = np.random.default_rng(2)
    lm = rng.uniform(0, 50, (120, 2))
    lookup = build_pole_lookup(lm, 3.0, cell_m=1.0, k=8)
    assert lookup.n_truncated == 0
    q = rng.uniform(-10, 60, (4000, 2))
    d = np.asarray(lookup.nearest_distance(jnp.asarray(q)))
    ref = np.minimum(np.linalg.norm(q[:, None] - lm[None], axis=-1).min(1), 3.0)
    np.testing.assert_allclose(d, ref, atol=1e-12)


def test_measurement_model_matches_numpy_reference():
    rng = np.random.default_rng(3)
    lm = rng.uniform(0, 40, (60, 2))
    model = PoleMeasurementModel(lm, var_m2=1.0, eps=0.1)
    parts = np.column_stack(
        [rng.uniform(5, 35, 500), rng.uniform(5, 35, 500), rng.uniform(-3, 3, 500)]
    )
    poles = rng.uniform(-15, 15, (12, 2))
    mask = rng.uniform(size=12) < 0.7
    ll = np.asarray(model(from_vector(jnp.asarray(parts)), (jnp.asarray(poles), jnp.asarray(mask))))
    ref = pole_log_likelihood_reference(parts, poles[mask], lm, var_m2=1.0, eps=0.1)
    np.testing.assert_allclose(ll, ref, rtol=1e-10, atol=1e-10)
    # d_max is where the density has fallen to p_min = 0.01
    dens = np.exp(-0.5 * model.d_max_m**2) / np.sqrt(2 * np.pi)
    np.testing.assert_allclose(dens, 0.01, rtol=1e-12)


def test_pad_poles_keeps_best():
    p = Poles(np.arange(10.0).reshape(5, 2), np.full(5, 0.2), np.array([0.1, 0.9, 0.5, 0.7, 0.2]))
    xy, mask = pad_poles([p, None, Poles.empty()], 3)
    np.testing.assert_array_equal(mask, [[True] * 3, [False] * 3, [False] * 3])
    np.testing.assert_allclose(xy[0], p.xy[[1, 3, 2]])


@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_landmark_particle_filter_tracks_synthetic_drive():
    """Landmarks along a road, noisy online detections, drifting odometry: the filter
    converges from a 2.5 m / 5 deg start and tracks to within 0.2 m."""
    rng = np.random.default_rng(4)
    s = np.linspace(0, 200, 201)  # 1 m steps
    truth = np.column_stack([s, 5 * np.sin(s / 40), np.arctan(5 / 40 * np.cos(s / 40))])
    lm_s = np.sort(rng.uniform(0, 220, 60))
    side = rng.choice([-1.0, 1.0], 60) * rng.uniform(4, 8, 60)
    lm = np.column_stack([lm_s, 5 * np.sin(lm_s / 40) + side])
    rel = to_vector(
        from_vector(jnp.asarray(truth[:-1])).inverse() @ from_vector(jnp.asarray(truth[1:]))
    )
    odo = np.asarray(rel) + rng.normal(0, [0.02, 0.01, 0.004], rel.shape)
    measured = []
    for t in range(1, len(truth)):
        w = lm[np.linalg.norm(lm - truth[t, :2], axis=1) < 20]
        x, y, th = truth[t]
        c, sn = np.cos(th), np.sin(th)
        local = (w - [x, y]) @ np.array([[c, -sn], [sn, c]])
        local = local + rng.normal(0, 0.05, local.shape)
        if t % 7 == 0:  # an unmapped pole
            local = np.vstack([local, [3.0, -6.0]])
        measured.append(Poles(local, np.full(len(local), 0.3), np.full(len(local), 0.8)))
    xy, mask = pad_poles(measured, 16)
    model = PoleMeasurementModel(lm)
    pf = ParticleFilter(OdometryMotionModel([0.02, 0.02, 0.005], inflation=2.0), model)
    state = init_uniform_disc(
        2000, truth[0, :2], 2.5, (truth[0, 2] - 0.087, truth[0, 2] + 0.087), key=jax.random.key(0)
    )
    _, info = pf.run(state, jnp.asarray(odo), (jnp.asarray(xy), jnp.asarray(mask)))
    est = np.asarray(to_vector(info.estimate))
    err = np.linalg.norm(est[:, :2] - truth[1:, :2], axis=1)
    assert np.mean(err[50:]) < 0.15, np.mean(err[50:])
    assert np.max(err[50:]) < 0.5
    assert not np.any(np.asarray(info.degenerate))


def test_bad_input():
    with pytest.raises(ValueError, match="landmarks_xy"):
        build_pole_lookup(np.zeros((0, 2)), 3.0)
    with pytest.raises(ValueError, match="d_max_m"):
        build_pole_lookup(np.zeros((2, 2)), -1.0)
    with pytest.raises(ValueError, match="var_m2"):
        PoleMeasurementModel(np.zeros((2, 2)), var_m2=0.0)
    with pytest.raises(ValueError, match="p_min"):
        PoleMeasurementModel(np.zeros((2, 2)), p_min=0.9)
    with pytest.raises(ValueError, match="poles\\[0\\]"):
        merge_poles([Poles(np.array([[np.nan, 0.0]]), np.ones(1), np.ones(1))])
    with pytest.raises(ValueError, match="width_m"):
        overlap_clusters(np.zeros((3, 2)), np.ones(2))


def test_segment_scans():
    s = np.array([0.0, 0.5, 1.0, 1.4, 1.6, 1.6, 1.6, 1.6, 2.9, 3.1, 3.5])
    xy = np.column_stack([s, np.zeros_like(s)])
    segs = segment_scans(xy, 1.5)
    assert [list(x) for x in segs] == [[0, 1, 2, 3], [4, 5, 6, 7, 8]]
    capped = segment_scans(xy, 1.5, max_scans=2)
    assert [list(x) for x in capped] == [[0, 3], [4, 8]]
    with pytest.raises(ValueError, match="segment_m"):
        segment_scans(xy, 0.0)
