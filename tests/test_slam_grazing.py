"""Grazing-angle free space in the SLAM front end's map (``grazing_lengths``,
``GridMap(grazing_m=...)``, ``FrontEndConfig(grazing_cells=...)``), against closed forms
on a straight wall."""

from __future__ import annotations

import numpy as np
import pytest

from lidarjax.sim import make_office, simulate_scans
from lidarjax.slam import FrontEndConfig, GridMap, grazing_lengths, grid_map, match_scan


def _wall_scan(phi_deg, height=1.0):
    """Beams at ``phi`` (deg, from the x axis) from the origin onto the wall ``y =
    height``: ranges ``height / sin(phi)``."""
    phi = np.deg2rad(np.asarray(phi_deg, float))
    return phi, height / np.sin(phi)


def test_grazing_lengths_on_a_straight_wall_are_the_closed_form():
    phi, r = _wall_scan(np.arange(3.0, 60.0, 1.0))
    delta, cap = 0.05, 1.0
    g = grazing_lengths(phi, r, 20.0, delta, cap)
    # the angle between each ray and the wall is phi: the last delta / sin(phi) of the
    # ray is within delta of it (the first and last beams have one neighbour: delta)
    want = np.minimum(delta / np.sin(phi), cap)
    np.testing.assert_allclose(g[1:-1], want[1:-1], rtol=1e-9)
    assert g[0] == delta and g[-1] == delta
    assert g[1] > 0.7  # 4 deg: 0.717 m
    # capped at max_m
    g2 = grazing_lengths(phi, r, 20.0, delta, 0.3)
    np.testing.assert_allclose(g2[1:-1], np.minimum(want[1:-1], 0.3), rtol=1e-9)
    # the same in any frame: the rays' azimuths shifted with the wall turned
    phi_shift = phi + 0.7
    np.testing.assert_allclose(grazing_lengths(phi_shift, r, 20.0, delta, cap), g, rtol=1e-9)


def test_grazing_lengths_edges_corners_and_no_returns():
    az = np.deg2rad(np.arange(0.0, 10.0, 1.0))
    r = np.array([2.0, 2.0, 20.0, 3.0, 20.0, 2.0, 4.0, 2.0, 2.0, 2.0])
    g = grazing_lengths(az, r, 20.0, 0.05, 1.0)
    assert g[2] == 0 and g[4] == 0  # no-returns
    assert g[3] == 0.05  # a lone return between no-returns
    assert g[6] == 0.05  # a spike: the surface bends by more than max_bend_rad
    assert np.all(g[r < 20] >= 0.05)
    # never longer than the ray
    phi, rr = _wall_scan([2.0, 2.5, 3.0], height=0.01)
    assert np.all(grazing_lengths(phi, rr, 20.0, 0.05, 1.0) <= rr + 1e-15)


def test_grid_map_grazing_keeps_the_wall_row_free_of_grazing_rays():
    # rays at 3-30 deg onto the wall y = 1 (a cell boundary); the row of cells below the
    # wall, y in [0.95, 1), is where each ray runs within 0.05 m of the wall: delta /
    # sin(phi) of its length. With grazing_m = 0.05 only the last 0.05 m of each ray
    # (the part kept before the return) stays there.
    phi, r = _wall_scan(np.arange(3.0, 31.0, 1.0))
    res, delta = 0.05, 0.05
    plain, cut = GridMap(res, 25.0), GridMap(res, 25.0, grazing_m=delta, grazing_max_m=1.0)
    for g in (plain, cut):
        g.add_scan([0.0, 0.0, 0.0], phi, r)
    np.testing.assert_array_equal(plain.hits, cut.hits)
    row = 19 - int(plain.lo[1])  # global cell row floor(0.95 / 0.05) = 19
    assert np.array_equal(plain.lo, cut.lo)
    skip = grazing_lengths(phi, r, 25.0, delta, 1.0)
    np.testing.assert_allclose(plain.lengths[:, row].sum(), np.sum(delta / np.sin(phi)), rtol=1e-5)
    # (the first and last beams have one neighbour each: no surface direction, not cut)
    kept = np.full(r.size, delta)
    kept[[0, -1]] = delta / np.sin(phi[[0, -1]])
    np.testing.assert_allclose(cut.lengths[:, row].sum(), kept.sum(), rtol=1e-5)
    # length is conserved elsewhere: the cut maps lose exactly the skipped stretches
    lost = plain.lengths.sum() - cut.lengths.sum()
    np.testing.assert_allclose(lost, np.sum(skip - delta), rtol=1e-6)
    assert cut.lengths.min() > -1e-9
    # add then remove gives zeros with grazing too
    cut.add_scan([0.0, 0.0, 0.0], phi, r, sign=-1.0)
    np.testing.assert_allclose(cut.lengths, 0.0, atol=1e-9)
    np.testing.assert_allclose(cut.hits, 0.0, atol=1e-12)


def test_grid_map_grazing_zero_is_the_plain_map():
    world = make_office(0)
    poses = world.trajectory(100, jitter_m=0.2)[:3]
    az = np.linspace(-np.pi / 2, np.pi / 2, 181)
    ranges = simulate_scans(world, poses, az, max_range_m=10.0, noise_sigma_m=0.01, seed=0)
    off = FrontEndConfig(range_cap_m=10.0, window_m=12.0, grazing_cells=0.0)
    a, b = GridMap(0.05, 10.0), grid_map(off)
    for p, rr in zip(poses, ranges):
        a.add_scan(p, az, rr)
        b.add_scan(p, az, rr)
    np.testing.assert_array_equal(a.lengths, b.lengths)
    np.testing.assert_array_equal(a.hits, b.hits)


def test_match_scan_with_grazing_recovers_a_perturbed_pose():
    """The office's map at the true poses of the even scans, an odd scan matched from
    0.1-0.2 m and 0.03-0.05 rad off, with the grazing stretches left out of the map and
    of the scan's optical depth."""
    world = make_office(0)
    truth = world.trajectory(100, jitter_m=0.2)[:40]
    az = np.linspace(-np.pi / 2, np.pi / 2, 181)
    ranges = simulate_scans(world, truth, az, max_range_m=30.0, noise_sigma_m=0.01, seed=0)
    cfg = FrontEndConfig(range_cap_m=10.0, window_m=12.0, grazing_cells=1.0)
    grid = grid_map(cfg)
    assert grid.grazing_m == pytest.approx(0.05)
    for k in range(0, truth.shape[0], 2):
        grid.add_scan(truth[k], az, ranges[k])
    k = 15
    for off in ((0.2, 0.0, 0.05), (0.0, -0.2, -0.05), (0.1, 0.0, 0.03)):
        m = match_scan(grid, az, ranges[k], truth[k] + np.array(off), cfg)
        assert np.hypot(*(m.pose[:2] - truth[k, :2])) < 0.025
        assert abs(np.angle(np.exp(1j * (m.pose[2] - truth[k, 2])))) < 0.006


def test_grazing_is_on_by_default_and_the_endpoint_model_ignores_it():
    # the endpoint model has no free-space term: its map keeps every ray's free length
    # and its matches get no grazing gap, whatever grazing_cells says
    from lidarjax.slam._front_end import _grazing

    assert FrontEndConfig().grazing_cells == 1.0
    assert grid_map(FrontEndConfig()).grazing_m == pytest.approx(0.05)
    ep = FrontEndConfig(model="endpoint", grazing_cells=2.0)
    assert grid_map(ep).grazing_m == 0.0
    phi, r = _wall_scan(np.linspace(3, 30, 28))
    assert np.all(_grazing(phi, r, FrontEndConfig(grazing_cells=2.0)) > 0)
    np.testing.assert_array_equal(_grazing(phi, r, ep), 0.0)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"final_from_search": 1}, "final_from_search"),
        ({"mask_unmapped": "yes"}, "mask_unmapped"),
        ({"grazing_cells": -1.0}, "grazing_cells"),
        ({"grazing_cells": float("nan")}, "grazing_cells"),
        ({"grazing_max_m": 0.0}, "grazing_max_m"),
        ({"grazing_cells": 2.0, "grazing_max_m": 0.05}, "grazing_max_m"),
    ],
)
def test_grazing_settings_reject_bad_values(kwargs, name):
    with pytest.raises(ValueError, match=name):
        FrontEndConfig(**kwargs)


def test_grid_map_rejects_bad_grazing_values():
    with pytest.raises(ValueError, match="grazing_m"):
        GridMap(0.05, 10.0, grazing_m=-0.1)
    with pytest.raises(ValueError, match="grazing_max_m"):
        GridMap(0.05, 10.0, grazing_m=0.1, grazing_max_m=0.05)


@pytest.mark.parametrize(
    ("args", "name"),
    [
        ((np.zeros(3), np.ones(4), 20.0, 0.05, 1.0), "azimuths and ranges"),
        ((np.zeros((2, 3)), np.ones((2, 3)), 20.0, 0.05, 1.0), "azimuths and ranges"),
        ((np.zeros(3), np.array([1.0, np.nan, 1.0]), 20.0, 0.05, 1.0), "ranges"),
        ((np.zeros(3), np.array([1.0, -1.0, 1.0]), 20.0, 0.05, 1.0), "ranges"),
        ((np.zeros(3), np.ones(3), 20.0, -0.05, 1.0), "delta_m"),
        ((np.zeros(3), np.ones(3), 20.0, 0.05, 0.01), "max_m"),
    ],
)
def test_grazing_lengths_rejects_bad_input(args, name):
    with pytest.raises(ValueError, match=name):
        grazing_lengths(*args)
