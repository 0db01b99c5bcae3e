"""The correlative pose search of decay-rate SLAM (lidarjax.slam.correlative_search)
against a brute-force NumPy evaluation of every lattice pose."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from lidarjax.slam import correlative_search

# float64 is enabled for the whole suite in tests/conftest.py (jax_enable_x64)


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def _brute_force(table, origin, res, az, rng, w, center, prior, inv_sig, n_xy, n_yaw, step):
    """Score of every lattice pose, one at a time, written out independently."""
    n0, n1 = table.shape
    floor = table.min()
    out = np.empty((2 * n_yaw + 1, 2 * n_xy + 1, 2 * n_xy + 1))
    poses = np.empty(out.shape + (3,))
    for k in range(-n_yaw, n_yaw + 1):
        yaw = center[2] + k * step
        for i in range(-n_xy, n_xy + 1):
            for j in range(-n_xy, n_xy + 1):
                x, y = center[0] + i * res, center[1] + j * res
                # end points of the scan at this pose, and their cells
                ex = x + rng * np.cos(yaw + az)
                ey = y + rng * np.sin(yaw + az)
                ci = np.floor((ex - origin[0]) / res).astype(int)
                cj = np.floor((ey - origin[1]) / res).astype(int)
                inside = (ci >= 0) & (ci < n0) & (cj >= 0) & (cj < n1)
                vals = np.full(rng.shape, floor)
                vals[inside] = table[ci[inside], cj[inside]]
                c, s = np.cos(prior[2]), np.sin(prior[2])
                dx, dy = x - prior[0], y - prior[1]
                dev = np.array([c * dx + s * dy, -s * dx + c * dy, _wrap(yaw - prior[2])])
                out[k + n_yaw, i + n_xy, j + n_xy] = np.sum(w * vals) - 0.5 * np.sum(
                    (dev * inv_sig) ** 2
                )
                poses[k + n_yaw, i + n_xy, j + n_xy] = (x, y, yaw)
    return out, poses


@pytest.fixture
def problem():
    rs = np.random.default_rng(3)
    res = 0.1
    table = np.log(rs.uniform(0.01, 3.0, (60, 50)))
    origin = np.array([-2.5, -2.0])
    b = 37
    az = np.sort(rs.uniform(-np.pi, np.pi, b))
    rng = rs.uniform(0.5, 3.5, b)  # some end points leave the table
    w = (rs.uniform(size=b) > 0.2).astype(float)
    center = np.array([0.53, 0.47, 0.3])
    prior = np.array([0.6, 0.4, 0.28])
    inv_sig = np.array([2.0, 3.0, 10.0])
    return table, origin, res, az, rng, w, center, prior, inv_sig


@pytest.mark.parametrize("n_xy, n_yaw", [(0, 0), (3, 0), (0, 4), (4, 3)])
def test_search_equals_brute_force(problem, n_xy, n_yaw):
    table, origin, res, az, rng, w, center, prior, inv_sig = problem
    step = 0.02
    ref, poses = _brute_force(
        table, origin, res, az, rng, w, center, prior, inv_sig, n_xy, n_yaw, step
    )
    best, score, runner = correlative_search(
        *(jnp.asarray(a) for a in (table, origin)),
        res,
        *(jnp.asarray(a) for a in (az, rng, w, center, prior, inv_sig)),
        n_xy=n_xy,
        n_yaw=n_yaw,
        step_yaw=step,
        exclude_m=0.25,
    )
    k = np.unravel_index(np.argmax(ref), ref.shape)
    np.testing.assert_allclose(float(score), ref[k], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(np.asarray(best), poses[k], atol=1e-12)
    far = np.hypot(poses[..., 0] - poses[k][0], poses[..., 1] - poses[k][1]) > 0.25
    expect = ref[far].max() if far.any() else -np.inf
    if np.isfinite(expect):
        np.testing.assert_allclose(float(runner), expect, rtol=1e-12, atol=1e-9)
    else:
        assert float(runner) == -np.inf


def test_search_finds_a_shifted_pattern():
    """End points drawn on a table's peaks from a known pose are found from a start off
    by several cells and a few heading steps."""
    res = 0.05
    n = 120
    table = np.full((n, n), -5.0)
    rs = np.random.default_rng(0)
    true = np.array([3.0, 3.0, 0.1])
    az = np.linspace(-np.pi, np.pi, 90, endpoint=False)
    rng = rs.uniform(1.0, 2.5, az.shape)
    ex = true[0] + rng * np.cos(true[2] + az)
    ey = true[1] + rng * np.sin(true[2] + az)
    table[np.floor(ex / res).astype(int), np.floor(ey / res).astype(int)] = 1.0
    center = true + np.array([0.2, -0.15, -0.06])
    best, score, runner = correlative_search(
        jnp.asarray(table),
        jnp.zeros(2),
        res,
        jnp.asarray(az),
        jnp.asarray(rng),
        jnp.ones(az.shape),
        jnp.asarray(center),
        jnp.asarray(center),
        jnp.zeros(3),
        n_xy=6,
        n_yaw=4,
        step_yaw=0.02,
        exclude_m=0.1,
    )
    np.testing.assert_allclose(np.asarray(best)[:2], true[:2], atol=res / 2 + 1e-9)
    np.testing.assert_allclose(float(best[2]), true[2], atol=0.01 + 1e-9)
    assert float(score) > float(runner) + 100.0
