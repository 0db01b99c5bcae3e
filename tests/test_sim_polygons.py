"""Tests of the random star-shaped polygons and their simulated scans (section 10.5)."""

from __future__ import annotations

import numpy as np
import pytest

from lidarjax.sim import random_polygon, simulate_polygon_scan

PAPER_VERTEX_COUNTS = (3, 4, 5, 6, 12, 36, 180)


def _winding_number(polygon: np.ndarray, point=(0.0, 0.0)) -> float:
    rel = polygon - np.asarray(point)
    ang = np.arctan2(rel[:, 1], rel[:, 0])
    steps = np.diff(ang, append=ang[0])
    steps = (steps + np.pi) % (2 * np.pi) - np.pi  # each step in [-pi, pi)
    return float(np.sum(steps) / (2 * np.pi))


def _distance_to_boundary(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    a = polygon[None, :, :]
    e = np.roll(polygon, -1, axis=0)[None, :, :] - a
    w = points[:, None, :] - a
    s = np.clip(np.sum(w * e, axis=-1) / np.sum(e * e, axis=-1), 0.0, 1.0)
    d = np.linalg.norm(w - s[..., None] * e, axis=-1)
    return d.min(axis=1)


@pytest.mark.parametrize("n", PAPER_VERTEX_COUNTS)
def test_random_polygon_shape_order_and_origin_inside(n):
    poly = random_polygon(n, seed=n)
    assert poly.shape == (n, 2)
    assert poly.dtype == np.float64
    ang = np.arctan2(poly[:, 1], poly[:, 0])
    assert np.all(np.diff(ang) > 0)  # sorted angles: counter-clockwise, star-shaped
    gaps = np.diff(ang, append=ang[0] + 2 * np.pi)
    assert np.all(gaps < np.pi)
    assert _winding_number(poly) == pytest.approx(1.0)  # origin strictly inside, CCW
    radii = np.hypot(poly[:, 0], poly[:, 1])
    assert np.all((radii >= 1.0) & (radii <= 10.0))


def test_random_polygon_is_deterministic_by_seed():
    np.testing.assert_array_equal(random_polygon(12, seed=7), random_polygon(12, seed=7))
    assert not np.allclose(random_polygon(12, seed=7), random_polygon(12, seed=8))


def test_random_polygon_radius_range():
    poly = random_polygon(36, seed=0, radius_range_m=(4.0, 5.0))
    radii = np.hypot(poly[:, 0], poly[:, 1])
    assert radii.min() >= 4.0 and radii.max() <= 5.0
    circle = random_polygon(5, seed=0, radius_range_m=(3.0, 3.0))
    np.testing.assert_allclose(np.hypot(circle[:, 0], circle[:, 1]), 3.0)


def test_triangles_always_enclose_origin():
    for seed in range(50):  # a random triangle misses the origin 3 times out of 4
        assert _winding_number(random_polygon(3, seed=seed)) == pytest.approx(1.0)


@pytest.mark.parametrize("n", [2, 0, -3])
def test_random_polygon_rejects_few_vertices(n):
    with pytest.raises(ValueError, match="n_vertices"):
        random_polygon(n, seed=0)


@pytest.mark.parametrize("bad", [(0.0, 1.0), (5.0, 1.0), (-1.0, 2.0), (1.0, np.inf), (1.0,)])
def test_random_polygon_rejects_bad_range(bad):
    with pytest.raises(ValueError, match="radius_range_m"):
        random_polygon(5, seed=0, radius_range_m=bad)


@pytest.mark.parametrize("n", PAPER_VERTEX_COUNTS)
def test_noiseless_scan_lands_on_polygon(n):
    poly = random_polygon(n, seed=100 + n)
    az, r = simulate_polygon_scan(poly, angular_sigma_rad=0.0, radial_sigma_m=0.0, seed=0)
    assert az.shape == r.shape == (360,)
    assert az.dtype == r.dtype == np.float64
    np.testing.assert_allclose(az, -np.pi + 2 * np.pi * np.arange(360) / 360)
    pts = np.column_stack([r * np.cos(az), r * np.sin(az)])
    assert np.all(_distance_to_boundary(pts, poly) < 1e-9)


def test_noiseless_scan_of_square_matches_closed_form():
    square = np.array([[-2.0, -2.0], [2.0, -2.0], [2.0, 2.0], [-2.0, 2.0]])
    # Clockwise order is accepted too.
    for poly in (square, square[::-1]):
        az, r = simulate_polygon_scan(
            poly, n_rays=720, angular_sigma_rad=0.0, radial_sigma_m=0.0, seed=0
        )
        expected = 2.0 / np.maximum(np.abs(np.cos(az)), np.abs(np.sin(az)))
        np.testing.assert_allclose(r, expected, rtol=1e-12)


def test_scan_is_deterministic_by_seed():
    poly = random_polygon(6, seed=3)
    a1, r1 = simulate_polygon_scan(poly, seed=5)
    a2, r2 = simulate_polygon_scan(poly, seed=5)
    _, r3 = simulate_polygon_scan(poly, seed=6)
    np.testing.assert_array_equal(a1, a2)
    np.testing.assert_array_equal(r1, r2)
    assert not np.array_equal(r1, r3)


def test_radial_noise_statistics():
    poly = random_polygon(180, seed=11, radius_range_m=(8.0, 10.0))
    kw = dict(n_rays=3600, angular_sigma_rad=0.0, seed=4)
    az, clean = simulate_polygon_scan(poly, radial_sigma_m=0.0, **kw)
    _, noisy = simulate_polygon_scan(poly, radial_sigma_m=0.03, **kw)
    res = noisy - clean
    assert np.std(res) == pytest.approx(0.03, rel=0.1)
    assert abs(np.mean(res)) < 3 * 0.03 / np.sqrt(3600) + 1e-12


def test_angular_noise_statistics():
    # On a square, the range changes with angle as d rho / d theta = rho tan(theta - phi),
    # so angular noise produces range residuals with std ~ sigma * rms(d rho / d theta).
    sigma = np.deg2rad(0.2)
    square = 5.0 * np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    kw = dict(n_rays=3600, radial_sigma_m=0.0, seed=9)
    az, clean = simulate_polygon_scan(square, angular_sigma_rad=0.0, **kw)
    _, noisy = simulate_polygon_scan(square, angular_sigma_rad=sigma, **kw)
    slope = np.gradient(clean, az)
    predicted = sigma * np.sqrt(np.mean(slope**2))
    assert np.std(noisy - clean) == pytest.approx(predicted, rel=0.1)


def test_default_noise_matches_paper_and_ranges_are_clipped():
    poly = random_polygon(12, seed=2, radius_range_m=(0.05, 0.1))
    _, r = simulate_polygon_scan(poly, radial_sigma_m=0.5, seed=1)
    assert np.all(r >= 0.0) and np.any(r == 0.0)
    # Defaults are the paper's 0.2 deg / 0.03 m / 360 rays: mostly centimetre-level error.
    big = random_polygon(180, seed=12, radius_range_m=(8.0, 10.0))
    az, r = simulate_polygon_scan(big, seed=3)
    assert r.shape == (360,)
    pts = np.column_stack([r * np.cos(az), r * np.sin(az)])
    dist = _distance_to_boundary(pts, big)
    assert 0.005 < np.median(dist) < 0.05


def test_scan_rejects_polygon_not_enclosing_origin():
    shifted = np.array([[1.0, 1.0], [2.0, 1.0], [2.0, 2.0], [1.0, 2.0]])
    with pytest.raises(ValueError, match="enclose the origin"):
        simulate_polygon_scan(shifted, seed=0)


def test_scan_rejects_bad_arguments():
    poly = random_polygon(4, seed=0)
    with pytest.raises(ValueError, match="polygon"):
        simulate_polygon_scan(poly[:2], seed=0)
    with pytest.raises(ValueError, match="n_rays"):
        simulate_polygon_scan(poly, n_rays=0, seed=0)
    with pytest.raises(ValueError, match="radial_sigma_m"):
        simulate_polygon_scan(poly, radial_sigma_m=-0.1, seed=0)
    with pytest.raises(ValueError, match="angular_sigma_rad"):
        simulate_polygon_scan(poly, angular_sigma_rad=np.nan, seed=0)
