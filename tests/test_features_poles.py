"""Tests of the pole extractor (section 12.4.1) against brute-force references."""

from __future__ import annotations

import itertools
import math

import jax.numpy as jnp
import numpy as np
import pytest

from lidarjax.features import (
    PoleConfig,
    Poles,
    extract_poles,
    extract_poles_from_occupancy,
    local_map_spec,
    mean_shift,
    pole_score_image,
    pole_score_maps,
)
from lidarjax.rays import HIT, SUP, RayBatch
from lidarjax.raytrace import GridSpec


def brute_scores(occ: np.ndarray, a: int, f: int) -> np.ndarray:
    """q_{a,j} literally from the definition; cells outside the grid are occupied in the
    hull and empty inside the pole; returned on the (q + 1) / 2 scale."""
    nx, ny, nz = occ.shape

    def o(x, y, z, outside):
        return occ[x, y, z] if 0 <= x < nx and 0 <= y < ny else outside

    out = np.empty_like(occ)
    for jx, jy, z in itertools.product(range(nx), range(ny), range(nz)):
        best = -np.inf
        for kx, ky in itertools.product(range(jx - a + 1, jx + 1), range(jy - a + 1, jy + 1)):
            inside = [o(x, y, z, 0.0) for x in range(kx, kx + a) for y in range(ky, ky + a)]
            ring = [
                o(x, y, z, 1.0)
                for x in range(kx - f, kx + a + f)
                for y in range(ky - f, ky + a + f)
                if not (kx <= x < kx + a and ky <= y < ky + a)
            ]
            best = max(best, np.mean(inside) - max(ring))
        out[jx, jy, z] = (best + 1) / 2
    return out


@pytest.mark.parametrize("f", [1, 2])
def test_score_maps_match_brute_force(f):
    rng = np.random.default_rng(f)
    occ = rng.uniform(size=(9, 8, 2)) ** 3
    occ[3:5, 4:6, :] = 0.95  # a 2 x 2 pole
    widths = (1, 2, 3)
    q = np.asarray(pole_score_maps(jnp.asarray(occ), widths, f))
    for i, a in enumerate(widths):
        np.testing.assert_allclose(q[i], brute_scores(occ, a, f), atol=1e-12)


def brute_run(q, q_min, min_cells):
    nx, ny, nz = q.shape
    s = np.zeros((nx, ny))
    z0 = np.zeros((nx, ny), int)
    h = np.zeros((nx, ny), int)
    for x, y in itertools.product(range(nx), range(ny)):
        best = (0, 0)
        z = 0
        while z < nz:
            if q[x, y, z] >= q_min:
                start = z
                while z < nz and q[x, y, z] >= q_min:
                    z += 1
                if z - start > best[0]:
                    best = (z - start, start)
            else:
                z += 1
        if best[0] >= min_cells:
            h[x, y], z0[x, y] = best
            s[x, y] = q[x, y, best[1] : best[1] + best[0]].mean()
    return s, z0, h


def test_score_image_matches_loop():
    rng = np.random.default_rng(3)
    q = rng.uniform(size=(6, 7, 12))
    q[2, 3, 1:8] = 0.9
    for min_cells in (1, 3, 5):
        s, z0, h = (np.asarray(v) for v in pole_score_image(jnp.asarray(q), 0.55, min_cells))
        rs, rz, rh = brute_run(q, 0.55, min_cells)
        np.testing.assert_allclose(s, rs, atol=1e-12)
        np.testing.assert_array_equal(h, rh)
        np.testing.assert_array_equal(z0[rh > 0], rz[rh > 0])
    assert h[2, 3] >= 7


def numpy_mean_shift(s, x, bw, steps=500):
    cx, cy = np.meshgrid(np.arange(s.shape[0]) + 0.5, np.arange(s.shape[1]) + 0.5, indexing="ij")
    for _ in range(steps):
        w = s * np.exp(-0.5 * ((cx - x[0]) ** 2 + (cy - x[1]) ** 2) / bw**2)
        new = np.array([np.sum(w * cx), np.sum(w * cy)]) / np.sum(w)
        if np.linalg.norm(new - x) < 1e-10:
            break
        x = new
    return x


def test_mean_shift_finds_modes_of_synthetic_map():
    cx, cy = np.meshgrid(np.arange(40) + 0.5, np.arange(30) + 0.5, indexing="ij")
    centres = np.array([[10.3, 8.7], [25.6, 20.2], [31.1, 6.4]])
    s = sum(np.exp(-0.5 * ((cx - c[0]) ** 2 + (cy - c[1]) ** 2) / 1.5**2) for c in centres)
    seeds = centres + np.array([[1.2, -0.8], [-1.0, 1.1], [0.7, 0.9]])
    modes = np.asarray(
        mean_shift(jnp.asarray(s), jnp.asarray(seeds), 1.0, max_steps=500, tol_cells=1e-9)
    )
    ref = np.array([numpy_mean_shift(s, x, 1.0) for x in seeds])
    np.testing.assert_allclose(modes, ref, atol=1e-5)
    # modes of the kernel-smoothed map of well-separated Gaussians are their centres
    np.testing.assert_allclose(modes, centres, atol=1e-2)


def cast_cylinders(origin, dirs, poles_xyr, height, r_max):
    """Ranges of rays against the ground z = 0 and vertical cylinders [0, height] (numpy)."""
    r = np.full(len(dirs), np.inf)
    down = dirs[:, 2] < 0
    r[down] = -origin[2] / dirs[down, 2]
    for px, py, rad in poles_xyr:
        ox, oy = origin[0] - px, origin[1] - py
        a = dirs[:, 0] ** 2 + dirs[:, 1] ** 2
        b = 2 * (ox * dirs[:, 0] + oy * dirs[:, 1])
        c = ox**2 + oy**2 - rad**2
        disc = b * b - 4 * a * c
        ok = (disc >= 0) & (a > 0)
        t = np.where(ok, (-b - np.sqrt(np.where(ok, disc, 0))) / (2 * np.where(ok, a, 1)), np.inf)
        z = origin[2] + t * dirs[:, 2]
        t = np.where((t > 0) & (z >= 0) & (z <= height), t, np.inf)
        r = np.minimum(r, t)
    return np.where(r < r_max, r, r_max)


# ring elevations (deg): HDL-32E (1.33 deg apart) and HDL-64E (KITTI; 1/3 and 1/2 deg apart)
RINGS_32 = np.linspace(-30.67, 10.67, 32)
RINGS_64 = np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.33, 32)])


def synthetic_rays(poles_xyr, sensors, n_az=720, height=4.0, r_max=40.0, rings_deg=RINGS_32):
    el = np.deg2rad(np.asarray(rings_deg, float))
    az = np.linspace(-np.pi, np.pi, n_az, endpoint=False)
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    o, dd, rr = [], [], []
    for s in sensors:
        rr.append(cast_cylinders(np.asarray(s), d, poles_xyr, height, r_max))
        o.append(np.tile(s, (len(d), 1)))
        dd.append(d)
    r = np.concatenate(rr)
    kind = np.where(r < r_max, HIT, SUP).astype(np.int32)
    return RayBatch(
        jnp.asarray(np.concatenate(o)),
        jnp.asarray(np.concatenate(dd)),
        jnp.asarray(r),
        jnp.asarray(kind),
        jnp.asarray(0.5),
        jnp.asarray(r_max),
    )


SMALL = PoleConfig(extent_m=(20.0, 20.0, 4.0), max_poles=16)


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_extract_poles_finds_cylinders():
    truth = np.array([[5.05, 3.1, 0.15], [-4.2, 6.3, 0.25], [2.5, -7.1, 0.1]])
    rays = synthetic_rays(truth, [(0.0, 0.0, 1.73), (1.0, 0.2, 1.73)])
    spec = local_map_spec([0.5, 0.0], SMALL)
    assert spec.shape == (100, 100, 20)
    poles = extract_poles(rays, spec, SMALL)
    assert len(poles) == 3
    d = np.linalg.norm(poles.xy[:, None] - truth[None, :, :2], axis=-1)
    # within one voxel: only the sensor-facing half of a cylinder is observed, which pulls
    # the estimate towards the sensor by up to about half a radius
    assert np.all(d.min(1) < 0.2), d.min(1)
    # the width-weighted mean score averages over all widths, so it may dip below q_min
    assert np.all(poles.score > 0.5) and np.all(poles.score <= 1)
    # widths: a square of edge ~ diameter, i.e. 1-3 cells of 0.2 m
    assert np.all((poles.width_m >= 0.2) & (poles.width_m <= 0.8))
    order = d.argmin(1)
    assert poles.width_m[order == 1] >= poles.width_m[order == 2]
    # all poles reach from near the floor to about the cylinder height
    assert np.all(poles.z_range_m[:, 1] - poles.z_range_m[:, 0] >= SMALL.h_min_m)


def test_extract_from_occupancy_equals_ray_path():
    truth = np.array([[3.0, 2.0, 0.2]])
    # same ray count and grid as the test above: no recompilation
    rays = synthetic_rays(truth, [(0.0, 0.0, 1.73), (0.5, -0.3, 1.73)])
    spec = local_map_spec([0.0, 0.0], SMALL)
    poles, occ = extract_poles(rays, spec, SMALL, return_occupancy=True)
    again = extract_poles_from_occupancy(occ, spec, SMALL)
    np.testing.assert_allclose(again.xy, poles.xy)
    np.testing.assert_allclose(again.score, poles.score)
    assert len(poles) == 1 and np.linalg.norm(poles.xy[0] - truth[0, :2]) < 0.2


def test_short_stacks_and_walls_are_not_poles():
    spec = GridSpec(jnp.zeros(3), 0.2, (30, 30, 12))
    occ = np.full(spec.shape, 0.01)
    occ[10, 10, 0:4] = 0.99  # 0.8 m stub: below h_min = 1 m
    occ[24:27, 5:25, :] = 0.99  # a wall: no free hull
    occ[7, 22, 2:10] = 0.99  # a thin pole (one cell)
    occ[14:17, 10:13, 1:12] = 0.99  # a thick pole (3 x 3 cells)
    tight = PoleConfig(extent_m=(6.0, 6.0, 2.4), mean_shift_steps=1000, mean_shift_tol_m=1e-9)
    poles = extract_poles_from_occupancy(jnp.asarray(occ), spec, tight)
    assert len(poles) == 2
    thin, thick = (0, 1) if poles.xy[0, 0] < 2 else (1, 0)
    # both lie in symmetric surroundings (every hull inside the grid, clear of the wall),
    # so the modes are exactly their centres (mean shift run to convergence)
    np.testing.assert_allclose(poles.xy[thin], [1.5, 4.5], atol=1e-6)
    np.testing.assert_allclose(poles.xy[thick], [3.1, 2.3], atol=1e-6)
    assert 0.2 <= poles.width_m[thin] <= 0.35
    assert 0.5 <= poles.width_m[thick] <= 0.8
    np.testing.assert_allclose(poles.z_range_m[thin], [0.4, 2.0], atol=1e-9)
    np.testing.assert_allclose(poles.z_range_m[thick], [0.2, 2.4], atol=1e-9)


def test_candidate_widths_are_physical_sizes():
    """Widths 1 cell .. max_width_m at every resolution (also after ``replace`` and when a
    grid's resolution overrides the config's); explicit cell counts stay as given."""
    from dataclasses import replace

    c = PoleConfig()  # 0.2 m voxels, max_width_m = 1.0
    assert c.width_cells == (1, 2, 3, 4, 5) and c.widths == (1, 2, 3, 4, 5)
    fine = replace(c, resolution_m=0.1)
    assert fine.width_cells == tuple(range(1, 11))  # 0.1 .. 1.0 m
    assert replace(fine, resolution_m=0.25).width_cells == (1, 2, 3, 4)
    assert PoleConfig(resolution_m=0.1, max_width_m=0.6).width_cells == (1, 2, 3, 4, 5, 6)
    assert PoleConfig(resolution_m=0.5, max_width_m=0.2).width_cells == (1,)  # at least 1
    for res in (0.05, 0.1, 0.2, 0.3):  # the largest width is max_width_m to half a cell
        a_max = PoleConfig(resolution_m=res).width_cells[-1]
        assert abs(a_max * res - 1.0) <= 0.5 * res + 1e-12
    explicit = PoleConfig(widths=(1, 3))
    assert replace(explicit, resolution_m=0.1).width_cells == (1, 3)
    for kwargs, name in (
        (dict(max_width_m=0.0), "max_width_m"),
        (dict(max_width_m=float("inf")), "max_width_m"),
        (dict(max_width_m="1"), "max_width_m"),
        (dict(widths=()), "widths"),
        (dict(widths=(2, 2)), "widths"),
        (dict(widths=(1.5,)), "widths"),
        (dict(widths=(True,)), "widths"),
    ):
        with pytest.raises(ValueError, match=name):
            PoleConfig(**kwargs)


def hollow_trunk_occupancy(res: float, diameter: float, shape_m=(6.0, 6.0, 2.0)):
    """Occupancy of a trunk seen from all sides: the cells its surface passes through are
    occupied (0.99); the unobserved interior and the free space around are 0.01."""
    n = tuple(int(round(e / res)) for e in shape_m)
    centre = np.array([3.03, 2.97])
    xs = (np.arange(n[0]) + 0.5) * res
    ys = (np.arange(n[1]) + 0.5) * res
    d = np.hypot(xs[:, None] - centre[0], ys[None, :] - centre[1])
    surface = np.abs(d - diameter / 2) <= 0.5 * res * math.sqrt(2)
    occ = np.where(surface[:, :, None], 0.99, 0.01) * np.ones(n)
    return occ, GridSpec(jnp.zeros(3), res, n), centre


@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_wide_trunk_found_at_fine_and_coarse_voxels():
    """Regression (issue #20): the candidate widths were 1-5 cells at every resolution, so
    at 0.1 m no square wider than 0.5 m existed; the free hull of every candidate square
    then cut through a 0.6 m trunk and it was never a pole. Widths in metres find trunks
    of 0.3 m and 0.6 m at 0.1 m and 0.2 m, at their centres."""
    for diameter in (0.3, 0.6):
        for res in (0.1, 0.2):
            occ, spec, centre = hollow_trunk_occupancy(res, diameter)
            cfg = PoleConfig(resolution_m=res, extent_m=(6.0, 6.0, 2.0), max_poles=8)
            poles = extract_poles_from_occupancy(jnp.asarray(occ), spec, cfg)
            assert len(poles) == 1, (diameter, res, len(poles))
            # the occupancy is symmetric about the trunk up to the raster: within a cell
            assert np.linalg.norm(poles.xy[0] - centre) < res, (diameter, res, poles.xy)
            # the whole stack qualifies (2 m >= h_min)
            np.testing.assert_allclose(poles.z_range_m[0], [0.0, 2.0], atol=1e-9)
            # a square of edge ~ the diameter or more, never beyond max_width_m
            assert diameter - res <= poles.width_m[0] <= cfg.max_width_m + 1e-9
        # the old candidate set at 0.1 m: only the trunk whose surface fits in 5 cells
        occ, spec, _ = hollow_trunk_occupancy(0.1, diameter)
        old = PoleConfig(
            resolution_m=0.1, extent_m=(6.0, 6.0, 2.0), max_poles=8, widths=(1, 2, 3, 4, 5)
        )
        n_old = len(extract_poles_from_occupancy(jnp.asarray(occ), spec, old))
        assert n_old == (1 if diameter < 0.4 else 0), (diameter, n_old)


@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_trunk_from_rays_at_fine_and_coarse_voxels():
    """Ray-traced trunks of 0.3-0.6 m (the simulator's range): a trunk circled by the
    sensor at 5 m is found at 0.1 m and 0.2 m voxels; with the old 1-5 cell widths the
    0.6 m one was missed at 0.1 m."""
    truth = np.array([[0.03, 0.07, 0.3], [3.0, 2.9, 0.15]])  # 0.6 m and 0.3 m
    sensors = [(5.0, 0.0, 1.73), (0.0, 5.0, 1.73), (-5.0, 0.0, 1.73), (0.0, -5.0, 1.73)]
    rays = synthetic_rays(truth, sensors, rings_deg=RINGS_64, r_max=30.0)
    for res in (0.1, 0.2):
        cfg = PoleConfig(resolution_m=res, extent_m=(10.0, 10.0, 3.0), max_poles=16)
        poles = extract_poles(rays, local_map_spec([1.0, 1.0], cfg), cfg)
        d = np.linalg.norm(poles.xy[:, None] - truth[None, :, :2], axis=-1)
        assert len(poles) == 2 and np.all(d.min(0) < 0.1), (res, poles.xy)
    old = PoleConfig(
        resolution_m=0.1, extent_m=(10.0, 10.0, 3.0), max_poles=16, widths=(1, 2, 3, 4, 5)
    )
    poles = extract_poles(rays, local_map_spec([1.0, 1.0], old), old)
    d = np.linalg.norm(poles.xy[:, None] - truth[None, :, :2], axis=-1)
    assert len(poles) == 1 and d[0, 1] < 0.1  # only the 0.3 m trunk


@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_ring_spacing_limits_the_voxel_size():
    """Why the Table 12.2 analogue missed 12 of 14 trunks at 0.1 m (issue #20): a 32-ring
    lidar (1.33 deg apart) hits a trunk 8 m away every 0.19 m in height, so every second
    0.1 m layer is unobserved (score 0.5 < q_min) and no run reaches h_min = 1 m. The same
    trunk is found at 0.2 m, and at 0.1 m by KITTI's 64-ring sensor (0.05 m apart)."""
    truth = np.array([[0.23, 8.07, 0.2]])
    sensors = [(x, 0.0, 1.73) for x in (-1.0, -0.3, 0.4, 1.1)]  # one 1.5 m segment
    for rings, res, found in (
        (RINGS_32, 0.2, True), (RINGS_32, 0.1, False), (RINGS_64, 0.1, True), (RINGS_64, 0.2, True)
    ):  # fmt: skip
        rays = synthetic_rays(truth, sensors, rings_deg=rings, r_max=30.0)
        cfg = PoleConfig(resolution_m=res, extent_m=(6.0, 6.0, 3.0), max_poles=8)
        spec = local_map_spec([0.0, 6.0], cfg)
        poles, occ = extract_poles(rays, spec, cfg, return_occupancy=True)
        hit = [np.linalg.norm(p - truth[0, :2]) < 0.25 for p in poles.xy]
        assert any(hit) == found, (len(rings), res, poles.xy)
        if not found:  # the cause: unobserved layers between the rings break the run
            q = np.asarray(pole_score_maps(occ, cfg.width_cells, cfg.free_cells)).max(0)
            c = np.floor((truth[0, :2] - np.asarray(spec.origin)[:2]) / res).astype(int)
            on = q[c[0] - 3 : c[0] + 4, c[1] - 3 : c[1] + 4].max(axis=(0, 1)) >= cfg.q_min
            runs = [len(r) for r in "".join("1" if v else "0" for v in on).split("0")]
            assert on.sum() >= 1.5 * cfg.min_cells  # the trunk scores on most layers ...
            assert max(runs) < cfg.min_cells  # ... but no 1 m of them is contiguous


def brute_seeds(s: np.ndarray, r: int) -> np.ndarray:
    """Seeds by definition: S > 0, no higher cell within r (Chebyshev), and no equal cell
    of lower flat index within r that is itself such a maximum."""
    nx, ny = s.shape

    def win(i, j):
        return [
            (a, b)
            for a in range(max(0, i - r), min(nx, i + r + 1))
            for b in range(max(0, j - r), min(ny, j + r + 1))
        ]

    peak = np.array(
        [
            [s[i, j] > 0 and all(s[i, j] >= s[c] for c in win(i, j)) for j in range(ny)]
            for i in range(nx)
        ]
    )
    out = np.zeros_like(peak)
    for i, j in itertools.product(range(nx), range(ny)):
        out[i, j] = peak[i, j] and not any(peak[c] and c < (i, j) for c in win(i, j))
    return out


def test_one_seed_per_plateau():
    """Regression: every cell of a flat top of S was a seed, so one wide pole (a plateau of
    ~a x a cells) could take all max_poles seeds and hide the other poles."""
    from lidarjax.features._poles import _local_maxima

    rng = np.random.default_rng(4)
    s = np.round(rng.uniform(size=(17, 15)), 1) * (rng.uniform(size=(17, 15)) < 0.5)  # ties
    s[2:6, 3:8] = 1.5  # a 4 x 5 plateau
    s[12, 12] = 1.2  # a strict maximum
    for r in (1, 2, 3):
        seeds = np.asarray(_local_maxima(jnp.asarray(s), r))
        np.testing.assert_array_equal(seeds, brute_seeds(s, r))
    seeds = np.asarray(_local_maxima(jnp.asarray(s), 2))
    assert seeds[2:6, 3:8].sum() == 1 and seeds[2, 3] and seeds[12, 12]
    # end to end: a 3 x 3 pole (a plateau of S) and a thinner, weaker one; two seeds
    spec = GridSpec(jnp.zeros(3), 0.2, (30, 30, 10))
    occ = np.full(spec.shape, 0.01)
    occ[8:11, 8:11, :] = 0.99
    occ[20, 21, :] = 0.9
    cfg = PoleConfig(extent_m=(6.0, 6.0, 2.0), max_poles=2)
    poles = extract_poles_from_occupancy(jnp.asarray(occ), spec, cfg)
    assert len(poles) == 2
    np.testing.assert_allclose(np.sort(poles.xy[:, 0]), [1.9, 4.1], atol=0.1)


def test_local_map_spec_snaps_to_raster():
    a = local_map_spec([3.03, -7.91])
    b = local_map_spec([100.17, 4.4])
    for s in (a, b):
        o = np.asarray(s.origin)
        np.testing.assert_allclose(o[:2] / 0.2, np.round(o[:2] / 0.2), atol=1e-9)
        assert s.shape == (150, 150, 25)
    np.testing.assert_allclose(np.asarray(a.origin)[:2] + 15.0, [3.03, -7.91], atol=0.1 + 1e-9)


def test_poles_container_and_bad_input():
    p = Poles(np.array([[1.0, 0.0]]), np.array([0.2]), np.array([0.8]))
    q = p.transform([1.0, 2.0, math.pi / 2])
    np.testing.assert_allclose(q.xy, [[1.0, 3.0]], atol=1e-12)
    assert len(Poles.empty()) == 0
    with pytest.raises(ValueError, match="width_m"):
        Poles(np.zeros((2, 2)), np.zeros(3), np.zeros(2))
    with pytest.raises(ValueError, match="widths"):
        PoleConfig(widths=(0, 1))
    with pytest.raises(ValueError, match="q_min"):
        PoleConfig(q_min=1.5)
    spec = GridSpec(jnp.zeros(3), 0.2, (10, 10, 5))
    with pytest.raises(ValueError, match="occ"):
        extract_poles_from_occupancy(jnp.zeros((10, 10, 4)), spec)
    with pytest.raises(ValueError, match="occ"):
        extract_poles_from_occupancy(jnp.full((10, 10, 5), jnp.nan), spec)
    with pytest.raises(ValueError, match="center_xy"):
        local_map_spec([np.nan, 0.0])
    with pytest.raises(ValueError, match="config"):
        extract_poles_from_occupancy(jnp.zeros((10, 10, 5)), spec, config={"q_min": 0.5})


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_fast_occupancy_equals_occupancy():
    from lidarjax.features import fast_occupancy
    from lidarjax.maps import beta_posterior, occupancy
    from lidarjax.raytrace import GridStats

    rng = np.random.default_rng(7)
    spec = GridSpec(jnp.zeros(3), 0.2, (30, 30, 20))
    hits = rng.poisson(0.3, spec.shape)
    misses = rng.poisson(3.0, spec.shape)
    hits[:2] = rng.integers(30, 200, hits[:2].shape)  # beyond the table (H >= 32)
    misses[-3:] = rng.integers(250, 5000, misses[-3:].shape)  # beyond the table (M >= 256)
    stats = GridStats(spec, jnp.asarray(hits), jnp.asarray(misses), jnp.zeros(spec.shape))
    post = beta_posterior(stats)
    ref = np.asarray(occupancy(post, 0.2))
    np.testing.assert_allclose(np.asarray(fast_occupancy(post, 0.2)), ref, rtol=0, atol=1e-12)
    # more voxels outside the table than the sparse path holds: the dense fallback
    big = GridStats(spec, jnp.asarray(hits), jnp.asarray(misses + 300), jnp.zeros(spec.shape))
    post = beta_posterior(big)
    np.testing.assert_allclose(
        np.asarray(fast_occupancy(post, 0.2)), np.asarray(occupancy(post, 0.2)), atol=1e-12
    )


def test_matched_prior_equals_moment_prior_and_survives_sparse_maps():
    from lidarjax.features import matched_beta_prior
    from lidarjax.maps import beta_moment_prior
    from lidarjax.raytrace import GridStats

    rng = np.random.default_rng(8)
    spec = GridSpec(jnp.zeros(3), 0.2, (10, 10, 5))
    hits = rng.poisson(0.5, spec.shape)
    misses = rng.poisson(4.0, spec.shape)
    stats = GridStats(spec, jnp.asarray(hits), jnp.asarray(misses), jnp.zeros(spec.shape))
    np.testing.assert_allclose(matched_beta_prior(stats), beta_moment_prior(stats), rtol=1e-10)
    # every voxel seen once: ML values are 0 or 1, V = E (1 - E), no Beta has these moments
    once = rng.uniform(size=spec.shape) < 0.3
    sparse = GridStats(
        spec, jnp.asarray(once.astype(int)), jnp.asarray((~once).astype(int)), jnp.zeros(spec.shape)
    )
    with pytest.raises(Exception, match="V|var|Beta|moment"):
        beta_moment_prior(sparse)
    a, b = (float(x) for x in matched_beta_prior(sparse))
    e = once.mean()
    np.testing.assert_allclose(a / (a + b), e, rtol=1e-9)  # the mean is kept
    np.testing.assert_allclose(a + b, 1 / 0.99 - 1, rtol=1e-9)  # the clamped variance
