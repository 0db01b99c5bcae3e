"""PPE (dissertation ch. 11): ray-path plane model, exact fits, and the greedy clustering
against a from-scratch reference."""

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize
import scipy.stats

from lidarjax.datasets import fetch, read_pcd
from lidarjax.features import (
    AUTO_FLOOR_M2,
    AUTO_KAPPA,
    TETROMINOES,
    auto_max_increment,
    estimate_noise,
    extract_planes,
    extract_planes_path,
    extract_planes_reference,
    fit_planes,
    linearized_plane_error,
    plane_error,
    plane_ranges,
    refit_segmentation,
)
from lidarjax.features._plane import _merge_py, _points_stats, _stats_error, _stats_error_py
from lidarjax.raytrace import ray_plane


def _grid_dirs(h, w, az=(-0.5, 0.5), el=(0.4, -0.4)):
    a, e = np.meshgrid(np.linspace(*el, h), np.linspace(*az, w), indexing="ij")
    return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1)


def _scene_scan(h=16, w=20, sigma=0.0, seed=0, az=(-0.5, 0.5), el=(0.4, -0.4)):
    """Rays from the origin onto a wall x = 3 and a floor z = -1 (first hit), + noise."""
    v = _grid_dirs(h, w, az, el)
    t_wall = 3.0 / v[..., 0]
    with np.errstate(divide="ignore"):
        t_floor = np.where(v[..., 2] < 0, -1.0 / v[..., 2], np.inf)
    t = np.minimum(t_wall, t_floor)
    gt = np.where(t_wall <= t_floor, 0, 1)
    r = t + np.random.default_rng(seed).normal(0.0, sigma, t.shape)
    return v * r[..., None], gt


@pytest.fixture(scope="module")
def synpeb_crop():
    cloud = read_pcd(fetch("synpeb-test-100"))
    return cloud.points_xyz.astype(np.float64)


# ---------------------------------------------------------------------------------------
# Model (Eqs. 11.1, 11.2)
# ---------------------------------------------------------------------------------------


def test_plane_ranges_and_error_by_hand():
    th = np.array([0.0, 0.3, -0.6])
    dirs = np.stack([np.cos(th), np.sin(th), np.zeros(3)], -1)
    origins = np.array([[0.0, 0, 0], [0.5, 0, 0], [0.0, 1.0, 2.0]])
    rhat = plane_ranges(np.array([2.0, 7.0, -3.0]), np.array([2.0, 0.0, 0.0]), origins, dirs)
    expected = np.array([2.0, 1.5 / np.cos(0.3), 2.0 / np.cos(0.6)])
    np.testing.assert_allclose(rhat, expected, rtol=1e-12)
    r = expected + np.array([0.1, -0.2, 0.05])
    E = plane_error(np.array([2.0, 0, 0]), np.array([1.0, 0, 0]), origins, dirs, r)
    np.testing.assert_allclose(E, 0.01 + 0.04 + 0.0025, rtol=1e-12)
    E_masked = plane_error(
        np.array([2.0, 0, 0]), np.array([1.0, 0, 0]), origins, dirs, r, np.array([1, 0, 1], bool)
    )
    np.testing.assert_allclose(E_masked, 0.0125, rtol=1e-12)
    # the ray-path error is not the point-to-plane distance: that is shorter by cos(incidence)
    endpoint = origins[2] + r[2] * dirs[2]
    np.testing.assert_allclose(endpoint[0] - 2.0, 0.05 * np.cos(0.6), rtol=1e-12)


def test_ray_plane_parallel_and_gradients():
    o = jnp.array([0.1, -0.2, 0.3])
    v = jnp.array([1.0, 0.0, 0.0])
    assert ray_plane(o, v, jnp.array([0.0, 0.0, 1.0]), jnp.array([0.0, 0.0, 1.0])) == jnp.inf
    g = jax.grad(lambda n: ray_plane(o, v, jnp.zeros(3), n))(jnp.array([0.0, 0.0, 1.0]))
    assert jnp.all(jnp.isfinite(g))
    x = jnp.array([3.0, 0.5, -0.2])
    n = jnp.array([0.9, 0.3, 0.1])
    v = jnp.array([0.8, 0.6, 0.0])

    @jax.jit
    def f(params):
        return ray_plane(params[:3], v, x, params[3:])

    p = jnp.concatenate([o, n])
    jf, jr = jax.jacfwd(f)(p), jax.jacrev(f)(p)
    np.testing.assert_allclose(jf, jr, rtol=1e-12)
    fd = np.array([(f(p + 1e-6 * e) - f(p - 1e-6 * e)) / 2e-6 for e in np.eye(6)])
    np.testing.assert_allclose(jf, fd, rtol=1e-6, atol=1e-8)


# ---------------------------------------------------------------------------------------
# Exact fits
# ---------------------------------------------------------------------------------------


_PAD = 64  # every single-set fit is padded to this many rays: one compilation for all tests


def _fit(o, d, r):
    n = len(r)
    m = np.arange(_PAD) < n
    pad = _PAD - n
    o = np.concatenate([o, np.zeros((pad, 3))])
    d = np.concatenate([d, np.tile([1.0, 0.0, 0.0], (pad, 1))])
    r = np.concatenate([r, np.ones(pad)])
    return fit_planes(o, d, r, m)


def _plane_rays(n_rays, normal, dist, sigma, seed, origin=(0.0, 0.0, 0.0)):
    rng = np.random.default_rng(seed)
    normal = np.asarray(normal) / np.linalg.norm(normal)
    d = rng.normal(size=(n_rays, 3)) * 0.3 + normal
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.tile(np.asarray(origin, float), (n_rays, 1))
    t = (dist - o @ normal) / (d @ normal)
    return o, d, t + rng.normal(0.0, sigma, n_rays)


def test_fit_recovers_noiseless_plane():
    normal = np.array([0.3, -0.8, 0.5]) / np.linalg.norm([0.3, -0.8, 0.5])
    o, d, r = _plane_rays(40, normal, 4.0, 0.0, seed=1, origin=(0.2, -0.1, 0.3))
    fit = _fit(o, d, r)
    np.testing.assert_allclose(fit.normal, normal, atol=1e-9)
    np.testing.assert_allclose(fit.support @ normal, 4.0, atol=1e-9)
    assert fit.error < 1e-18 and bool(fit.converged)


def test_fit_matches_scipy_least_squares_on_noisy_rays():
    for seed, normal in enumerate([[1.0, 0.2, -0.1], [-0.2, 0.9, 0.6], [0.1, 0.1, -1.0]]):
        normal = np.asarray(normal) / np.linalg.norm(normal)
        o, d, r = _plane_rays(60, normal, 3.0 + seed, 0.03, seed=seed + 10)
        fit = _fit(o, d, r)

        # independent parametrisation: spherical angles + distance, residuals r - d/(n.v)
        def res(q):
            n = np.array([np.cos(q[1]) * np.cos(q[0]), np.cos(q[1]) * np.sin(q[0]), np.sin(q[1])])
            return r - q[2] / (d @ n)

        q0 = [
            np.arctan2(normal[1], normal[0]) + 0.05,
            np.arcsin(normal[2]) - 0.05,
            3.0 + seed + 0.1,
        ]
        ref = scipy.optimize.least_squares(res, q0, xtol=1e-15, ftol=1e-15, gtol=1e-15)
        n_ref = ref.x[:2]
        n_ref = np.array(
            [
                np.cos(n_ref[1]) * np.cos(n_ref[0]),
                np.cos(n_ref[1]) * np.sin(n_ref[0]),
                np.sin(n_ref[1]),
            ]
        )
        np.testing.assert_allclose(float(fit.error), 2 * ref.cost, rtol=1e-9)
        np.testing.assert_allclose(np.abs(fit.normal @ n_ref), 1.0, atol=1e-10)
        np.testing.assert_allclose(fit.support @ fit.normal, abs(ref.x[2]), rtol=1e-8)
        # and the fitted error is the model's error of the fitted plane
        np.testing.assert_allclose(
            plane_error(fit.support, fit.normal, o, d, r), fit.error, rtol=1e-10
        )


def test_fit_batched_padding_equals_single_fits():
    sets = [
        _plane_rays(n, nrm, 2.5, 0.02, seed=s)
        for s, (n, nrm) in enumerate([(7, [1, 0, 0]), (30, [0.5, 0.5, 0.1]), (12, [0.2, -1, 0.3])])
    ]
    N = _PAD
    o = np.zeros((3, N, 3))
    d = np.tile([1.0, 0, 0], (3, N, 1))
    r = np.ones((3, N))
    m = np.zeros((3, N), bool)
    for i, (oi, di, ri) in enumerate(sets):
        o[i, : len(ri)], d[i, : len(ri)], r[i, : len(ri)], m[i, : len(ri)] = oi, di, ri, True
    batch = fit_planes(o, d, r, m)
    for i, (oi, di, ri) in enumerate(sets):
        one = _fit(oi, di, ri)
        np.testing.assert_allclose(batch.error[i], one.error, rtol=1e-9)
        np.testing.assert_allclose(batch.normal[i], one.normal, atol=1e-9)
        assert int(batch.n_rays[i]) == len(ri)


def test_fit_bad_input():
    o, d, r = _plane_rays(5, [1, 0, 0], 2.0, 0.01, seed=0)
    with pytest.raises(ValueError, match="mask"):
        fit_planes(o, d, r, np.array([1, 1, 0, 0, 0], bool))
    with pytest.raises(ValueError, match="directions"):
        fit_planes(o, d[:4], r)
    with pytest.raises(ValueError, match="ranges"):
        fit_planes(o, d, np.where(np.arange(5) == 2, np.nan, r))


# ---------------------------------------------------------------------------------------
# Linearised clustering error (sufficient statistics)
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


def test_stats_error_equals_lstsq_and_merges_exactly():
    rng = np.random.default_rng(3)
    for n in (4, 9, 50):
        a, b = rng.normal([3, 0, 0], 0.4, (n, 3)), rng.normal([3, 1, 0.5], 0.4, (n + 2, 3))
        Wa, ma, Ca = _points_stats(a)
        Wb, mb, Cb = _points_stats(b)
        np.testing.assert_allclose(_stats_error(Wa, ma, Ca), linearized_plane_error(a), rtol=1e-9)
        st = _merge_py(
            (float(Wa), *ma.tolist(), *Ca.tolist()), (float(Wb), *mb.tolist(), *Cb.tolist())
        )
        W, m, C = st[0], np.array(st[1:4]), np.array(st[4:])
        np.testing.assert_allclose(_stats_error_py(st), _stats_error(W, m, C), rtol=1e-12)
        Wr, mr, Cr = _points_stats(np.concatenate([a, b]))
        np.testing.assert_allclose(W, Wr, rtol=1e-13)
        np.testing.assert_allclose(m, mr, rtol=1e-12)
        np.testing.assert_allclose(C, Cr, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(
            _stats_error(W, m, C), linearized_plane_error(np.concatenate([a, b])), rtol=1e-9
        )


def test_linearized_error_tracks_the_exact_ray_path_error():
    """E_lin = Σ (r - r̂)² (r / r̂)²: within a few % of Eq. 11.2 at 20 mm noise, 2-5 m."""
    for seed in range(4):
        normal = np.array([1.0, 0.3 * seed - 0.4, -0.2])
        o, d, r = _plane_rays(60, normal, 2.0 + seed, 0.02, seed=seed)
        exact = float(_fit(o, d, r).error)
        lin = linearized_plane_error(d * r[:, None])
        assert abs(lin / exact - 1.0) < 0.03


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
    from lidarjax.datasets import synpeb_scan

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
    assert fast.stop_reason == ref.stop_reason and fast.n_atoms == ref.n_atoms
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
    assert full.stop_reason == "exhausted"
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
    assert seg.stop_reason == "max_planes"
    J = seg.n_planes + seg.n_atoms
    assert 27 < J <= 30
    seg = extract_planes(pts, max_increment=1e-3, refit=False)
    assert seg.stop_reason == "max_increment" and seg.step_costs.max() <= 1e-3


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
        assert seg.stop_reason == one.stop_reason
    assert path[1].n_planes != path[0].n_planes
    with pytest.raises(ValueError, match="max_increments"):
        extract_planes_path(sub, [])
    with pytest.raises(ValueError, match="max_increment"):
        extract_planes_path(sub, [1e-3, -1.0])


def test_estimate_noise_recovers_radial_sigma():
    for sigma, seed in ((0.02, 0), (0.005, 1)):
        pts, _ = _scene_scan(h=40, w=50, sigma=sigma, seed=seed)
        assert abs(estimate_noise(pts) / sigma - 1.0) < 0.1


def test_refit_segmentation_matches_fit_planes():
    pts, gt = _scene_scan(h=12, w=16, sigma=0.02, seed=2)
    labels = gt.copy()
    labels[0, 0] = -1
    sup, nrm, err = refit_segmentation(pts, labels)
    assert sup.shape == (2, 3) and err.shape == (2,)
    for j in range(2):
        m = labels == j
        r = np.linalg.norm(pts[m], axis=-1)
        E = plane_error(sup[j], nrm[j], np.zeros((m.sum(), 3)), pts[m] / r[:, None], r)
        np.testing.assert_allclose(err[j], E, rtol=1e-9)
        # the exact minimum: no better than the linearised plane's exact error by > 0
        assert err[j] <= linearized_plane_error(pts[m]) * 1.05
    with pytest.raises(ValueError, match="labels"):
        refit_segmentation(pts, np.where(np.arange(gt.size).reshape(gt.shape) < 2, 2, labels))
    with pytest.raises(ValueError, match="labels"):
        refit_segmentation(pts, labels.astype(float))


def test_fit_one_scan_column_is_finite():
    """The endpoints of one scan column are collinear: the plane is not determined, but the
    fit must neither pass through the sensor nor blow up (the error stays at the noise)."""
    el = np.linspace(-0.3, 0.3, 14)
    d = np.stack([np.cos(el), np.zeros(14), np.sin(el)], -1)
    r = 3.0 / d[:, 0] + np.random.default_rng(0).normal(0.0, 0.02, 14)
    fit = _fit(np.zeros((14, 3)), d, r)
    assert np.isfinite(float(fit.error)) and float(fit.error) <= np.sum((r - 3.0 / d[:, 0]) ** 2)
    assert abs(float(fit.support @ fit.normal)) > 1.0  # not through the sensor


# ---------------------------------------------------------------------------------------
# Stopping criteria: no silent collapse, the default threshold rule (issue #20)
# ---------------------------------------------------------------------------------------


def test_no_stopping_criterion_raises():
    """Without e and J_max the greedy loop would merge every connected ray into one plane
    (stop_reason 'exhausted'); that must be an error naming both arguments."""
    pts, _ = _scene_scan(h=8, w=10, sigma=0.02, seed=3)
    for fn in (extract_planes, extract_planes_reference):
        with pytest.raises(ValueError, match="max_increment=None and max_planes=None"):
            fn(pts, max_increment=None)
        with pytest.raises(ValueError, match="max_increment"):
            fn(pts, max_increment="automatic")
    with pytest.raises(ValueError, match="max_increments"):
        extract_planes_path(pts, [1e-3, None])
    with pytest.raises(ValueError, match="max_increments"):
        extract_planes_path(pts, "auto")
    # an explicit "no threshold" still runs to the end, and J_max alone is a criterion
    assert extract_planes(pts, max_increment=math.inf, refit=False).stop_reason == "exhausted"
    seg = extract_planes(pts, max_increment=None, max_planes=20, refit=False)
    assert seg.stop_reason == "max_planes"


def _brute_force_sigma(pts):
    """sigma_hat from scratch: every 4-ray placement of the 17 tetrominoes, each fitted by
    least squares (linearized_plane_error), median / median of chi²(1)."""
    H, W = pts.shape[:2]
    errs = []
    for shape in TETROMINOES:
        for r in range(H - shape[:, 0].max()):
            for c in range(W - shape[:, 1].max()):
                errs.append(linearized_plane_error(pts[r + shape[:, 0], c + shape[:, 1]]))
    return np.sqrt(np.median(errs) / scipy.stats.chi2(1).median())


@pytest.mark.parametrize("sigma, branch", [(0.02, "kappa"), (0.0005, "floor")])
def test_auto_threshold_is_the_documented_rule(sigma, branch):
    """e = max(200 sigma_hat², 0.01 m²) with sigma_hat recomputed by brute force, and
    extract_planes(points) uses it."""
    pts, _ = _scene_scan(h=12, w=14, sigma=sigma, seed=8)
    sig = _brute_force_sigma(pts)
    expected = max(200.0 * sig**2, 0.01)
    assert (AUTO_KAPPA, AUTO_FLOOR_M2) == (200.0, 0.01)
    assert ("kappa" if 200.0 * sig**2 > 0.01 else "floor") == branch
    np.testing.assert_allclose(auto_max_increment(pts), expected, rtol=1e-9)
    auto = extract_planes(pts, refit=False)
    same = extract_planes(pts, max_increment=expected, refit=False)
    np.testing.assert_array_equal(auto.labels, same.labels)
    np.testing.assert_array_equal(auto.step_costs, same.step_costs)
    assert auto.stop_reason == "max_increment" and auto.step_costs.max() <= expected
    ref = extract_planes_reference(pts)
    np.testing.assert_array_equal(ref.labels, auto.labels)
    path = extract_planes_path(pts, ["auto", 1e-4], refit=False)
    np.testing.assert_array_equal(path[0].labels, auto.labels)


def _synpeb_window(radial_sigma_m, angular_sigma_deg=1e-3, n=64):
    """A 64 x 64 window of a generated SynPEB-style scan at the full 500 x 500 angular
    resolution (0.14° x 0.12°): floor, a wall and four object faces of training scene 0."""
    from lidarjax.datasets import make_synpeb_scene, simulate_synpeb_scan

    return simulate_synpeb_scan(
        make_synpeb_scene(seed=1000),
        shape=(n, n),
        radial_sigma_m=radial_sigma_m,
        angular_sigma_deg=angular_sigma_deg,
        seed=1007,
        azimuth_deg=(18.2, 18.2 + (n - 1) * 0.14),
        elevation_deg=(-15.7, -15.7 - (n - 1) * 60.0 / 499),
    )


def test_default_rule_neither_collapses_nor_over_segments():
    """Issue #20: at 0.4 mm radial noise 200 sigma_hat² (the old default) cuts planes into
    spurious pieces; the default rule gives the ground-truth planes at 0.4 mm and 20 mm."""
    from lidarjax.metrics import hoover_scores

    for radial, min_f in ((0.0004, 0.85), (0.02, 0.5)):
        scan = _synpeb_window(radial)
        seg = extract_planes(scan.points, max_distance_m=0.2, refit=False)
        h = hoover_scores(scan.labels, seg.labels)
        n_big = int((np.bincount(scan.labels.ravel())[1:] >= 50).sum())
        assert seg.stop_reason == "max_increment"  # no collapse into one plane
        assert n_big >= 5 and seg.n_planes >= n_big - 1, (radial, seg.n_planes, n_big)
        assert h.n_noise <= 2 and h.n_over == 0 and h.n_under == 0, (radial, h)
        assert h.f >= min_f and h.k >= 0.9, (radial, h.f, h.k)
        if radial < 1e-3:  # the old relative rule over-segments the same scan
            old = extract_planes(
                scan.points,
                max_increment=200 * estimate_noise(scan.points) ** 2,
                max_distance_m=0.2,
                refit=False,
            )
            assert old.n_planes >= seg.n_planes + 5
            assert hoover_scores(scan.labels, old.labels).n_noise >= h.n_noise + 5
