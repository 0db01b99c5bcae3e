"""Tests of the polyline-extraction metrics of section 10.5 against hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest

from lidarjax.metrics import (
    area_ratio,
    explained_fraction,
    polygon_area,
    ray_rmse,
    star_polygon,
)
from lidarjax.sim import random_polygon

SQUARE = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])  # side 2, area 4


def _inside(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Even-odd point-in-polygon test, ``[p 2]`` points against ``[n 2]`` vertices."""
    px, py = points[:, 0:1], points[:, 1:2]
    a = polygon[None, :, :]
    b = np.roll(polygon, -1, axis=0)[None, :, :]
    ax, ay, bx, by = a[..., 0], a[..., 1], b[..., 0], b[..., 1]
    straddle = (ay > py) != (by > py)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = ax + (py - ay) * (bx - ax) / (by - ay)
    return np.sum(straddle & (px < x_cross), axis=1) % 2 == 1


def _raster_areas(gt: np.ndarray, est: np.ndarray, n: int = 200):
    both = np.vstack([gt, est])
    lo, hi = both.min(axis=0), both.max(axis=0)
    xs = np.linspace(lo[0], hi[0], n + 1)
    ys = np.linspace(lo[1], hi[1], n + 1)
    cx, cy = 0.5 * (xs[:-1] + xs[1:]), 0.5 * (ys[:-1] + ys[1:])
    pts = np.stack(np.meshgrid(cx, cy), axis=-1).reshape(-1, 2)
    cell = (xs[1] - xs[0]) * (ys[1] - ys[0])
    in_gt, in_est = _inside(pts, gt), _inside(pts, est)
    return (
        cell * np.count_nonzero(in_gt & in_est),
        cell * np.count_nonzero(in_gt ^ in_est),
        cell * np.count_nonzero(in_est),
    )


# --- ray_rmse / explained_fraction -------------------------------------------------------


def test_ray_rmse_uses_reflected_and_intersected_rays_only():
    ranges = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    expected = np.array([1.1, np.inf, 2.5, 9.0, np.nan])
    reflected = np.array([True, True, True, False, True])
    # Qualifying rays: 0 (error -0.1) and 2 (error 0.5).
    assert ray_rmse(ranges, expected, reflected) == pytest.approx(np.sqrt((0.01 + 0.25) / 2))
    assert ray_rmse(ranges, ranges, reflected) == 0.0


def test_ray_rmse_returns_inf_when_nothing_qualifies():
    ranges = np.array([1.0, 2.0])
    assert ray_rmse(ranges, np.array([np.inf, 1.0]), np.array([True, False])) == np.inf
    assert ray_rmse(ranges, np.array([np.inf, np.nan]), np.array([True, True])) == np.inf


def test_ray_rmse_validates_inputs():
    with pytest.raises(ValueError, match="shape"):
        ray_rmse(np.ones(3), np.ones(2), np.ones(3, dtype=bool))
    with pytest.raises(TypeError, match="reflected"):
        ray_rmse(np.ones(3), np.ones(3), np.ones(3))
    with pytest.raises(ValueError, match="finite"):
        ray_rmse(np.array([np.inf, 1.0]), np.ones(2), np.ones(2, dtype=bool))


def test_explained_fraction_hand_values():
    reflected = np.array([True, True, True, True])
    assert explained_fraction(np.array([1.0, np.inf, np.inf, 2.0]), reflected) == 0.5
    assert explained_fraction(np.array([1.0, 2.0, 3.0, 4.0]), reflected) == 1.0
    # Only reflected rays count: an intersected no-return ray does not raise f above 1.
    expected = np.array([1.0, np.inf, 3.0, np.nan])
    assert explained_fraction(expected, np.array([True, True, False, False])) == 0.5


def test_explained_fraction_validates_inputs():
    with pytest.raises(ValueError, match="reflected"):
        explained_fraction(np.ones(3), np.zeros(3, dtype=bool))
    with pytest.raises(ValueError, match="shape"):
        explained_fraction(np.ones(3), np.ones(2, dtype=bool))
    with pytest.raises(TypeError, match="reflected"):
        explained_fraction(np.ones(3), np.ones(3, dtype=int))


# --- polygon_area / star_polygon ---------------------------------------------------------


def test_polygon_area_known_shapes():
    assert polygon_area(SQUARE) == pytest.approx(4.0)
    tri = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 3.0]])
    assert polygon_area(tri) == pytest.approx(6.0)
    assert polygon_area(tri[::-1]) == pytest.approx(6.0)  # orientation does not matter
    n, r = 7, 2.5
    ang = 2 * np.pi * np.arange(n) / n
    ngon = r * np.column_stack([np.cos(ang), np.sin(ang)])
    assert polygon_area(ngon) == pytest.approx(0.5 * n * r**2 * np.sin(2 * np.pi / n))
    notched = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [2.0, 1.0], [0.0, 4.0]])
    assert polygon_area(notched) == pytest.approx(16.0 - 0.5 * 4.0 * 3.0)
    assert polygon_area(np.array([[0.0, 0.0], [1.0, 1.0]])) == 0.0


def test_star_polygon_orders_counter_clockwise():
    poly = random_polygon(36, seed=5)
    shuffled = poly[np.random.default_rng(0).permutation(36)]
    np.testing.assert_array_equal(star_polygon(shuffled), poly)
    # About another centre: angles measured from that centre increase.
    c = np.array([0.3, -0.2])
    ordered = star_polygon(shuffled, c)
    ang = np.arctan2(ordered[:, 1] - c[1], ordered[:, 0] - c[0])
    assert np.all(np.diff(ang) >= 0)
    assert sorted(map(tuple, ordered)) == sorted(map(tuple, poly))


# --- area_ratio --------------------------------------------------------------------------


def test_area_ratio_identical_polygons_is_zero():
    poly = random_polygon(12, seed=1)
    assert area_ratio(poly, poly) == pytest.approx(0.0, abs=1e-12)
    shuffled = poly[np.random.default_rng(1).permutation(12)]
    assert area_ratio(poly, shuffled) == pytest.approx(0.0, abs=1e-12)
    assert area_ratio(poly[::-1], poly) == pytest.approx(0.0, abs=1e-12)  # clockwise GT


def test_area_ratio_concentric_squares():
    big = 2.0 * SQUARE  # side 4, area 16
    # GT big, E small: (16 - 4) / 4; GT small, E big: (16 - 4) / 16.
    assert area_ratio(big, SQUARE) == pytest.approx(3.0, rel=1e-12)
    assert area_ratio(SQUARE, big) == pytest.approx(0.75, rel=1e-12)


def test_area_ratio_rotated_square_octagon():
    # Side-2 square vs. the same square rotated by 45 deg: the intersection is the regular
    # octagon with inradius 1, area 8 tan(pi/8) = 8 (sqrt 2 - 1); union = 8 - that.
    diamond = np.sqrt(2.0) * np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
    inter = 8.0 * (np.sqrt(2.0) - 1.0)
    expected = ((8.0 - inter) - inter) / 4.0  # = 6 - 4 sqrt 2
    assert area_ratio(SQUARE, diamond) == pytest.approx(expected, rel=1e-12)
    assert area_ratio(diamond, SQUARE) == pytest.approx(6.0 - 4.0 * np.sqrt(2.0), rel=1e-12)


def test_area_ratio_is_translation_invariant_with_center():
    gt, est = random_polygon(6, seed=2), random_polygon(12, seed=3)
    shift = np.array([12.0, -7.0])
    a0 = area_ratio(gt, est)
    assert area_ratio(gt + shift, est + shift, center=shift) == pytest.approx(a0, rel=1e-10)


def test_area_ratio_symmetric_difference_is_symmetric():
    gt, est = random_polygon(5, seed=20), random_polygon(36, seed=21)
    sym_1 = area_ratio(gt, est) * polygon_area(est)
    sym_2 = area_ratio(est, gt) * polygon_area(gt)
    assert sym_1 == pytest.approx(sym_2, rel=1e-10)


@pytest.mark.parametrize(
    ("n_gt", "n_est", "seed"), [(3, 4, 0), (5, 12, 1), (36, 6, 2), (12, 12, 3)]
)
def test_area_ratio_matches_raster(n_gt, n_est, seed):
    gt = random_polygon(n_gt, seed=seed)
    est = random_polygon(n_est, seed=1000 + seed)
    a = area_ratio(gt, est)
    inter, sym, est_area = _raster_areas(gt, est)
    assert est_area == pytest.approx(polygon_area(est), rel=0.01)
    assert a * polygon_area(est) == pytest.approx(sym, rel=0.01)
    exact_inter = 0.5 * (polygon_area(gt) + polygon_area(est) - a * polygon_area(est))
    assert exact_inter == pytest.approx(inter, rel=0.01)


def test_area_ratio_close_estimate_matches_raster():
    # An estimate that hugs the ground truth: the boundaries cross many times.
    gt = random_polygon(36, seed=8, radius_range_m=(5.0, 8.0))
    rng = np.random.default_rng(0)
    est = gt * rng.uniform(0.9, 1.1, (36, 1))
    est = est[rng.permutation(36)]  # E is built by angular ordering
    a = area_ratio(gt, est)
    assert 0.0 < a < 0.3
    e_poly = star_polygon(est)
    _, sym, _ = _raster_areas(gt, e_poly, n=400)
    assert a * polygon_area(e_poly) == pytest.approx(sym, rel=0.02)


def test_area_ratio_rejects_bad_polygons():
    with pytest.raises(ValueError, match="at least 3"):
        area_ratio(SQUARE, SQUARE[:2])
    half_plane = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])  # centre on an edge
    with pytest.raises(ValueError, match="strictly inside"):
        area_ratio(SQUARE, half_plane)
    with pytest.raises(ValueError, match="strictly inside"):
        area_ratio(SQUARE + 5.0, SQUARE)
    with pytest.raises(ValueError, match="strictly inside"):
        area_ratio(SQUARE, SQUARE, center=(1.0, 1.0))  # centre at a vertex
    # Encloses the centre but is not star-shaped around it (a slot hides part of the edge).
    notched = np.array(
        [[-3, -3], [3, -3], [3, 3], [1, 3], [1, 1], [0.5, 1], [0.5, 3], [-3, 3]], dtype=float
    )
    with pytest.raises(ValueError, match="star-shaped"):
        area_ratio(notched, SQUARE)
