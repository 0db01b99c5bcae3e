"""The NumPy PLE reference of the polyline benchmark (benchmarks/_numpy_ple.py) follows the
same rules as :func:`lidarjax.features.extract_polylines`."""

from __future__ import annotations

import sys
from pathlib import Path

import jaxlie
import numpy as np
import pytest

from lidarjax import rays as R
from lidarjax.features import extract_polylines
from lidarjax.sim import random_polygon, simulate_polygon_scan

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from _numpy_ple import ple_numpy  # noqa: E402


def _open_scan():
    """90 rays over 135 deg inside a 7-gon, with 8 max-range readings (SUP rays)."""
    poly = random_polygon(7, seed=11, radius_range_m=(1.5, 5.0))
    az, r = simulate_polygon_scan(poly, n_rays=240, seed=11)
    az, r = az[40:130], r[40:130].copy()
    r_max = 8.0
    drop = np.random.default_rng(11).choice(90, 8, replace=False)
    r[drop] = r_max
    return R.from_scan(jaxlie.SE2.identity(), az, r, 0.0, r_max), False


def _closed_scan():
    poly = random_polygon(6, seed=3, radius_range_m=(2.0, 4.0))
    az, r = simulate_polygon_scan(poly, n_rays=72, seed=3)
    return R.from_scan(jaxlie.SE2.identity(), az, r), True


@pytest.mark.parametrize("make", [_open_scan, _closed_scan], ids=["open-90", "closed-72"])
@pytest.mark.parametrize("j_max", [6, 12])
def test_numpy_ple_matches_jax(make, j_max):
    rays, closed = make()
    res = extract_polylines(rays, max_vertices=j_max, l_max_m=1.0, d_rm_m=0.5, closed=closed)
    order, errors, alive, successor = ple_numpy(
        np.asarray(rays.origins)[0],
        np.asarray(rays.directions),
        np.asarray(rays.ranges),
        np.asarray(rays.kind) == R.HIT,
        max_vertices=j_max,
        l_max_m=1.0,
        d_rm_m=0.5,
        closed=closed,
    )
    jo = np.asarray(res.removal_order)
    n = int(np.sum(jo >= 0))
    assert n == len(order) > 20
    np.testing.assert_array_equal(jo[:n], order)
    np.testing.assert_allclose(np.asarray(res.removal_error)[:n], errors, rtol=1e-9, atol=1e-15)
    act = np.asarray(res.map.active)
    np.testing.assert_array_equal(act, alive)
    np.testing.assert_array_equal(np.where(act, np.asarray(res.map.successor), -1), successor)
    if not closed:  # the open scan exercises SUP rays and several polylines
        assert int(np.sum(np.asarray(rays.kind) != R.HIT)) == 8
        assert int(res.initial_stats.n_polylines) >= 2
