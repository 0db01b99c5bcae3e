"""Gradient-based pose refinement: the continuous decay-rate field, its scan likelihood
(against closed forms, scipy and finite differences) and convergence on real scans."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import optimistix as optx
import pytest
from helpers import carmen_even_scan_stats, finite_difference
from scipy import ndimage

from lidarjax import maps
from lidarjax.localization import to_vector
from lidarjax.localization.refine import (
    SmoothDecayRateField,
    SmoothDecayRateScan,
    blur,
    refine_pose,
    refine_scan_pose,
    smooth_fields,
)
from lidarjax.raytrace import GridSpec


def _map(rates, origin=(-2.0, -1.0), res=0.25, outside=0.0):
    rates = jnp.asarray(rates, jnp.float64)
    spec = GridSpec(origin, res, rates.shape)
    return maps.DecayRateMap(spec, rates, jnp.asarray(outside, jnp.float64))


def _bilinear_ref(rates, origin, res, pts):
    """Independent numpy bilinear interpolation of cell-centre samples, edges clamped."""
    nx, ny = rates.shape
    out = []
    for x, y in pts:
        u = (x - origin[0]) / res - 0.5
        v = (y - origin[1]) / res - 0.5
        i, j = int(np.floor(u)), int(np.floor(v))
        fx, fy = u - i, v - j
        acc = 0.0
        for di, wx in ((0, 1 - fx), (1, fx)):
            for dj, wy in ((0, 1 - fy), (1, fy)):
                ii, jj = min(max(i + di, 0), nx - 1), min(max(j + dj, 0), ny - 1)
                acc += wx * wy * rates[ii, jj]
        out.append(acc)
    return np.array(out)


def test_field_is_bilinear_interpolant():
    rng = np.random.default_rng(0)
    rates = rng.uniform(0, 3, (12, 9))
    m = _map(rates)
    pts = rng.uniform([-2.0, -1.0], [-2.0 + 12 * 0.25, -1.0 + 9 * 0.25], (200, 2))
    got = np.asarray(SmoothDecayRateField(m)(jnp.asarray(pts)))
    np.testing.assert_allclose(got, _bilinear_ref(rates, (-2.0, -1.0), 0.25, pts), rtol=1e-12)
    # cell centres reproduce the cell values exactly; off the grid: outside rate
    centres = np.asarray(m.spec.cell_centers()).reshape(-1, 2)
    np.testing.assert_allclose(np.asarray(SmoothDecayRateField(m)(centres)), rates.ravel())
    m2 = _map(rates, outside=0.7)
    assert float(SmoothDecayRateField(m2)(jnp.asarray([5.0, 5.0]))) == pytest.approx(0.7)


@pytest.mark.parametrize("sigma_cells", [1.5, 2.0])
def test_blur_matches_scipy_gaussian_filter(sigma_cells):
    rates = np.random.default_rng(1).uniform(0, 1, (30, 17))
    ref = ndimage.gaussian_filter(rates, sigma_cells, mode="nearest", truncate=3.0)
    np.testing.assert_allclose(np.asarray(blur(jnp.asarray(rates), sigma_cells)), ref, atol=1e-12)
    assert blur(jnp.asarray(rates), 0.0) is not None
    np.testing.assert_array_equal(np.asarray(blur(jnp.asarray(rates), 0.0)), rates)
    with pytest.raises(ValueError, match="sigma_cells"):
        blur(jnp.asarray(rates), -1.0)


def test_scan_likelihood_closed_form_on_linear_field():
    """On a field linear in x (exactly reproduced by the bilinear interpolant between the
    outermost cell centres) the midpoint rule is exact: Lambda = int (a + b x) dr."""
    res, nx, ny = 0.2, 60, 40
    origin = np.array([-6.0, -4.0])
    xc = origin[0] + (np.arange(nx) + 0.5) * res
    a, b = 0.7, 0.1  # rates 0.11 .. 1.29 1/m: a possible (non-negative) field
    rates = np.broadcast_to((a + b * xc)[:, None], (nx, ny))
    m = _map(rates, origin=origin, res=res, outside=0.3)
    field = SmoothDecayRateField(m)
    az = np.array([0.0, 0.7, np.pi, -2.0])
    ranges = np.array([3.0, 2.5, 0.05, 100.0])  # HIT, HIT, SUB (r_min 0.1), SUP (r_max 50)
    pose = np.array([0.3, -0.2, 0.4])
    scan = SmoothDecayRateScan(field, az, ranges, 0.1, 50.0, rate_floor=0.0, ray_floor=None)
    ll = np.asarray(scan.ray_log_likelihoods(jaxlie.SE2.from_xy_theta(*pose)))

    def depth(theta, r):
        c = np.cos(pose[2] + theta)
        return a * r + b * (pose[0] * r + 0.5 * c * r * r)

    for k in (0, 1):
        th, r = az[k], ranges[k]
        x_end = pose[0] + r * np.cos(pose[2] + th)
        assert ll[k] == pytest.approx(np.log(a + b * x_end) - depth(th, r), rel=1e-10)
    assert ll[2] == pytest.approx(np.log(-np.expm1(-depth(az[2], 0.1))), rel=1e-10)
    # SUP: inside the box the linear field, beyond the box the outside rate
    th = pose[2] + az[3]
    d = np.array([np.cos(th), np.sin(th)])
    lo, hi = origin, origin + res * np.array([nx, ny])
    t_exit = min(max((lo[i] - pose[i]) / d[i], (hi[i] - pose[i]) / d[i]) for i in range(2))
    # the bilinear field is clamped (constant) outside the hull of the cell centres in x
    xs = pose[0] + np.linspace(0, t_exit, 400001) * d[0]
    lam = a + b * np.clip(xs, xc[0], xc[-1])
    inside = np.trapezoid(lam, dx=t_exit / 400000)
    assert ll[3] == pytest.approx(-(inside + 0.3 * (50.0 - t_exit)), rel=1e-7)


def test_scan_likelihood_gradient_matches_finite_differences():
    jax.config.update("jax_enable_x64", True)
    rng = np.random.default_rng(3)
    rates = ndimage.gaussian_filter(rng.uniform(0, 4, (50, 50)), 2.0)
    m = _map(rates, origin=(-5.0, -5.0), res=0.2, outside=0.1)
    az = np.linspace(-1.5, 1.5, 7)
    ranges = rng.uniform(0.5, 3.5, 7)
    scan = SmoothDecayRateScan(SmoothDecayRateField(m, 0.3), az, ranges, 0.0, 8.0)
    p0 = np.array([0.13, -0.21, 0.37])

    @jax.jit
    def f(v):
        return scan(jaxlie.SE2.from_xy_theta(v[0], v[1], v[2]))

    g = np.asarray(jax.grad(f)(jnp.asarray(p0)))
    fd = finite_difference(f, p0, eps=1e-6)
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-6)


def test_refine_pose_recovers_optimum_of_quadratic():
    target = np.array([1.0, -0.5, 0.1])

    def obj(pose):
        v = jnp.concatenate([pose.translation(), pose.rotation().as_radians()[None]])
        return -jnp.sum(jnp.asarray([1.0, 2.0, 1.0]) * (v - target) ** 2)

    pose, sol = refine_pose(obj, jaxlie.SE2.from_xy_theta(0.0, 0.0, 0.0))
    assert sol.result == optx.RESULTS.successful
    np.testing.assert_allclose(np.asarray(to_vector(pose)), target, atol=1e-3)


def test_refine_bad_input():
    m = _map(np.ones((4, 4)))
    with pytest.raises(ValueError, match="pose0"):
        refine_pose(
            lambda p: 0.0, jaxlie.SE2.from_xy_theta(jnp.zeros(2), jnp.zeros(2), jnp.zeros(2))
        )
    with pytest.raises(ValueError, match="blur_m"):
        SmoothDecayRateField(m, -0.1)
    with pytest.raises(ValueError, match="map"):
        SmoothDecayRateField(maps.ReflectionMap(m.spec, jnp.ones((4, 4)) * 0.5, jnp.asarray(0.5)))
    with pytest.raises(ValueError, match="shape"):
        SmoothDecayRateScan(SmoothDecayRateField(m), [0.0, 1.0], [1.0], 0.0, 5.0)
    with pytest.raises(ValueError, match="ranges"):
        SmoothDecayRateScan(SmoothDecayRateField(m), [0.0], [np.nan], 0.0, 5.0)
    with pytest.raises(ValueError, match="blur_schedule_m"):
        smooth_fields(m, [])


@pytest.fixture(scope="module")
def intel_map():
    log, stats = carmen_even_scan_stats("intel", r_min=0.0)
    return log, maps.decay_rate_map(stats)


@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_refinement_converges_on_real_scans(intel_map):
    """From 0.3 m / 5 deg offsets, odd (unmapped) Intel scans refine to the optimum that
    refinement started at the corrected pose finds (within 1 cm / 0.25 deg). That optimum
    lies within 5 cm / 1.5 deg of the corrected pose; the SLAM poses are not exact (e.g.
    the likelihood optimum of scan 101 sits 4 cm / 0.9 deg from its corrected pose)."""
    log, m = intel_map
    fields = smooth_fields(m)
    refine = jax.jit(
        lambda ranges, p: refine_scan_pose(
            fields, log.azimuths_rad, ranges, jaxlie.SE2(p), 0.0, log.usable_range_m
        )[0].parameters()
    )

    def run(i, start):
        p0 = jaxlie.SE2.from_xy_theta(*start).parameters()
        return np.asarray(to_vector(jaxlie.SE2(refine(jnp.asarray(log.ranges_m[i]), p0))))

    def gap(a, b):
        return np.linalg.norm(a[:2] - b[:2]), np.rad2deg(abs(np.angle(np.exp(1j * (a[2] - b[2])))))

    for k, i in enumerate((101, 301, 701)):
        gt = log.poses[i]
        ang = k * 2 * np.pi / 3 + 0.3
        off = np.array([0.3 * np.cos(ang), 0.3 * np.sin(ang), np.deg2rad(5.0) * (-1) ** k])
        opt = run(i, gt)
        got = run(i, gt + off)
        d_opt, a_opt = gap(got, opt)
        d_gt, a_gt = gap(opt, gt)
        assert d_opt < 0.01 and a_opt < 0.25, (i, d_opt, a_opt)
        assert d_gt < 0.05 and a_gt < 1.5, (i, d_gt, a_gt)
