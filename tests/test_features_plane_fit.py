"""The ray-path plane model (Eqs. 11.1, 11.2), its exact fit and the exact refit of a
segmentation (lidarjax/features/_plane_fit.py)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

from lidarjax.features import (
    fit_planes,
    linearized_plane_error,
    plane_error,
    plane_ranges,
    refit_segmentation,
)
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
