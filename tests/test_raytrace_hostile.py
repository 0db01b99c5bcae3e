"""Hostile inputs to the geometry core: never hang, never guess.

NaN or infinite poses, azimuths, directions and resolutions must raise an error naming the
argument (``ValueError`` for concrete values, ``eqx.error_if`` under ``jit``), and the
degenerate rays that used to hang or are easy to get wrong (tiny direction components in
float32, rays along grid lines, through cell corners, outside the grid, on its boundary,
of length 0 or ``inf``) must give exactly what an independent brute-force reference gives.

The reference (:func:`reference_walk`) proposes candidate cells by dense sampling along the
ray and measures each candidate exactly, clipping the ray to the cell's box in rational
arithmetic (``fractions.Fraction``), so it shares no code or rounding with the walker.
Three former hangs also run in a subprocess with a timeout, so that a regression fails
instead of hanging the suite.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap
from fractions import Fraction

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from lidarjax.localization import ScanModel
from lidarjax.maps import decay_rate_map
from lidarjax.rays import (
    HIT,
    SUB,
    SUP,
    RayBatch,
    classify,
    from_points,
    from_scan,
    from_spinning_scan,
)
from lidarjax.raytrace import (
    GridSpec,
    _native,
    accumulate,
    fold_rays,
    gather,
    max_cells_for,
    traverse,
)
from lidarjax.sensor_models import batch_log_likelihood

# eqx.error_if raises EquinoxRuntimeError under eqx.filter_jit / eagerly; under plain
# jax.jit the failed callback surfaces as a JaxRuntimeError (XlaRuntimeError) or, when the
# error is met at dispatch, as ValueError("INTERNAL: CpuCallback error ..."), each carrying
# the same message (the tests match it; traced values cannot trip the eager checks).
RUNTIME = (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError, ValueError)

# accumulate's walks: the pure-JAX one and, when built, the native kernel
BACKENDS = [
    "jax",
    pytest.param(
        "native",
        marks=pytest.mark.skipif(not _native.available(), reason="native kernels not built"),
    ),
]

SPEC_LO, SPEC_RES, SPEC_SHAPE = (0.0, 0.0), 0.5, (6, 5)  # box [0, 3] x [0, 2.5]
AZ = np.linspace(-1.2, 1.2, 7)
RANGES = np.array([0.9, 1.4, 0.1, 2.0, 4.5, 1.1, 0.7])  # one SUB (0.1), one SUP (4.5)
R_MIN, R_MAX = 0.2, 4.0


def spec2() -> GridSpec:
    return GridSpec(SPEC_LO, SPEC_RES, SPEC_SHAPE)


def good_rays() -> RayBatch:
    T = jaxlie.SE2.from_xy_theta(jnp.array([1.1, 1.6]), jnp.array([1.2, 1.3]), jnp.zeros(2))
    return from_scan(T, AZ, np.stack([RANGES, RANGES[::-1]]), R_MIN, R_MAX)


@pytest.fixture(scope="module")
def decay_map():
    return decay_rate_map(accumulate(spec2(), good_rays()), unknown_rate=0.3)


def with_leaf(rays: RayBatch, name: str, index, value) -> RayBatch:
    """``rays`` with one entry of a field replaced, bypassing the constructor's checks
    (``eqx.tree_at`` does not call ``__init__``): this reaches the geometry core itself."""
    return eqx.tree_at(lambda r: getattr(r, name), rays, getattr(rays, name).at[index].set(value))


# --------------------------------------------------------------------------------------
# Independent brute-force reference
# --------------------------------------------------------------------------------------


def _fr(x) -> Fraction:
    return Fraction(float(x))


def reference_walk(lo, res, shape, o, d, length, tol=1e-9):
    """The cells ``o + t u`` (``u = d / |d|``, ``t in [0, length]``) visits, in order.

    Conventions, as documented by :mod:`lidarjax.raytrace`: the grid box is closed, cells
    are half-open ``[i, i + 1) * res`` except that the last cell of an axis also owns the
    upper face; a ray resting on a grid line belongs to the cell above it; a zero-length
    ray inside the box visits the cell its direction points into (clipped to the grid).

    Returns:
        ``(cells, ends_inside)``: ``cells`` a list of ``(cell, length_m)`` sorted along the
        ray, cells shorter than ``tol`` dropped (coincident crossings are one step);
        ``ends_inside`` whether the endpoint lies in the closed box.
    """
    dim = len(shape)
    d = np.asarray(d)
    u = d / np.sqrt(np.sum(d * d))  # in the input's dtype, like the walker
    Og, U = [_fr(x) for x in o], [_fr(x) for x in u]
    LO, RES = [_fr(x) for x in lo], _fr(res)
    HI = [LO[k] + shape[k] * RES for k in range(dim)]
    t_lo, t_hi = Fraction(0), _fr(length) if np.isfinite(length) else math.inf
    for k in range(dim):
        if U[k] == 0:
            if not LO[k] <= Og[k] <= HI[k]:
                return [], False
            continue
        ta, tb = (LO[k] - Og[k]) / U[k], (HI[k] - Og[k]) / U[k]
        t_lo, t_hi = max(t_lo, min(ta, tb)), min(t_hi, max(ta, tb))
    ends_inside = np.isfinite(length) and t_hi >= _fr(length) and t_lo <= t_hi

    def rest_index(k):
        return min(math.floor((Og[k] - LO[k]) / RES), shape[k] - 1)

    if float(length) == 0:
        if not ends_inside:
            return [], False
        cell = []
        for k in range(dim):
            rel = (Og[k] - LO[k]) / RES
            c = math.ceil(rel) - 1 if U[k] < 0 else math.floor(rel)
            cell.append(min(max(c, 0), shape[k] - 1))
        return [(tuple(cell), 0.0)], True
    if not t_lo < t_hi:
        return [], False
    # candidates: the cells of dense samples and their neighbours (spacing < res / 4)
    a, b = float(t_lo), float(t_hi)
    n = int(8 * (b - a) / float(res)) + 16
    t = a + (np.arange(n) + 0.5) / n * (b - a)
    p = np.asarray(o, np.float64) + t[:, None] * np.asarray(u, np.float64)
    base = np.floor((p - np.asarray(lo, np.float64)) / float(res)).astype(int)
    offsets = np.stack(np.meshgrid(*[[-1, 0, 1]] * dim, indexing="ij"), -1).reshape(-1, dim)
    cand = {tuple(c) for c in (base[:, None, :] + offsets[None]).reshape(-1, dim)}
    cand = {c for c in cand if all(0 <= c[k] < shape[k] for k in range(dim))}
    out = []
    for c in cand:
        t0, t1 = t_lo, t_hi
        for k in range(dim):
            if U[k] == 0:
                if rest_index(k) != c[k]:
                    t1 = t0 - 1  # the resting coordinate is in another cell
                continue
            ca, cb = LO[k] + c[k] * RES, LO[k] + (c[k] + 1) * RES
            ta, tb = (ca - Og[k]) / U[k], (cb - Og[k]) / U[k]
            t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
        if t1 - t0 > tol:
            out.append((t0, c, float(t1 - t0)))
    out.sort()
    return [(c, seg) for _, c, seg in out], ends_inside


def reference_stats(lo, res, shape, rays: RayBatch):
    """H, M, R of :func:`accumulate` (default ``sub_rays="ignore"``) from
    :func:`reference_walk`: misses in every visited cell but the last, a hit in the last
    cell of a HIT ray that ends inside the grid, a miss there otherwise."""
    H, M, R = np.zeros(shape, int), np.zeros(shape, int), np.zeros(shape)
    flat = rays.flatten()
    r_max = float(flat.r_max)
    for o, d, r, k in zip(*(np.asarray(x) for x in (flat.origins, flat.directions, flat.ranges))
                          , np.asarray(flat.kind)):  # fmt: skip
        if k == SUB:
            continue
        cells, ends_inside = reference_walk(lo, res, shape, o, d, r_max if k == SUP else r)
        for c, seg in cells:
            R[c] += seg
        for c, _ in cells[:-1]:
            M[c] += 1
        if cells:
            if k == HIT and ends_inside:
                H[cells[-1][0]] += 1
            else:
                M[cells[-1][0]] += 1
    return H, M, R


def assert_stats_match(stats, ref, rtol=1e-12, atol=1e-12):
    H, M, R = ref
    np.testing.assert_array_equal(np.asarray(stats.hits), H)
    np.testing.assert_array_equal(np.asarray(stats.misses), M)
    np.testing.assert_allclose(np.asarray(stats.lengths), R, rtol=rtol, atol=atol)


def ray_batch(rows, r_min, r_max, dtype=np.float64) -> RayBatch:
    o, d, r, k = zip(*rows)
    return RayBatch(
        np.asarray(o, dtype),
        np.asarray(d, dtype),
        np.asarray(r, dtype),
        np.asarray(k, np.int32),
        np.asarray(r_min, dtype),
        np.asarray(r_max, dtype),
    )


# --------------------------------------------------------------------------------------
# Degenerate geometry against the reference
# --------------------------------------------------------------------------------------

SQ2 = math.sqrt(2.0)
ROWS_2D = [
    # along the interior grid line x = 1.0 (belongs to column 2), up
    ((1.0, 0.2), (0.0, 1.0), 1.7, HIT),
    # along the lower face y = 0, and along the upper face y = 2.5 (the top row owns it)
    ((0.25, 0.0), (1.0, 0.0), 2.25, HIT),
    ((2.9, 2.5), (-1.0, 0.0), 9.0, SUP),
    # along y = 1.5 from outside on the right
    ((4.0, 1.5), (-1.0, 0.0), 3.2, HIT),
    # diagonals through cell corners (coincident crossings), from a corner, from outside
    ((0.0, 0.0), (1.0, 1.0), 2.0, HIT),
    ((0.5, 2.5), (1.0, -1.0), 1.6, HIT),
    ((-1.0, -1.0), (1.0, 1.0), 9.0, SUP),
    ((1.0, 1.0), (-1.0, -1.0), 0.9, HIT),
    # slope 2 through corners: u is rounded, the slivers must merge
    ((0.0, 0.0), (1.0, 2.0), 2.4, HIT),
    # wholly outside: missing, parallel outside, touching only the corner (0, 0)
    ((-1.0, -1.0), (-1.0, 0.3), 2.0, HIT),
    ((5.0, 5.0), (1.0, 1.0), 9.0, SUP),
    ((-0.5, 0.2), (0.0, 1.0), 2.0, HIT),
    ((-1.0, 1.0), (1.0, -1.0), 3.0, HIT),
    # starting on the boundary: lower face inward, upper face inward, upper face outward
    ((0.0, 1.2), (1.0, 0.0), 1.1, HIT),
    ((3.0, 1.2), (-1.0, 0.0), 0.8, HIT),
    ((3.0, 1.2), (1.0, 0.0), 1.0, HIT),
    # ending exactly on a grid line, and on the grid's upper face (binary-exact values)
    ((0.25, 0.7), (1.0, 0.0), 0.75, HIT),
    ((2.25, 0.7), (1.0, 0.0), 0.75, HIT),
    # zero length: inside, on an interior corner pointing down-left, on the upper corner,
    # outside, and a zero-length SUB (ignored)
    ((1.2, 0.7), (1.0, 0.0), 0.0, HIT),
    ((1.0, 1.0), (-1.0, 0.0), 0.0, HIT),
    ((3.0, 2.5), (1.0, 1.0), 0.0, HIT),
    ((-1.0, 1.0), (1.0, 0.0), 0.0, HIT),
    ((1.2, 0.7), (1.0, 0.0), 0.0, SUB),
    # a SUB ray is ignored however long
    ((0.3, 0.3), (1.0, 0.0), 0.1, SUB),
]
# SUP rays traced to r_max = inf, i.e. to the grid border
ROWS_INF = [
    ((1.0, 0.2), (0.0, 1.0), 0.0, SUP),
    ((0.0, 0.0), (1.0, 1.0), 0.0, SUP),
    ((-1.0, 1.25), (1.0, 0.0), 0.0, SUP),
    ((-1.0, -1.0), (-1.0, 0.3), 0.0, SUP),
    ((2.0, 2.0), (-3.0, -1.0), 0.0, SUP),
    ((1.1, 1.1), (0.3, 0.4), 0.7, HIT),
]
SPEC3 = ((-1.0, 0.0, 0.0), 0.25, (4, 5, 6))  # box [-1, 0] x [0, 1.25] x [0, 1.5]
ROWS_3D = [
    # along a grid edge (two resting coordinates on grid lines)
    ((-0.5, 0.25, 0.0), (0.0, 0.0, 1.0), 1.2, HIT),
    # space diagonal through cube corners
    ((-1.0, 0.0, 0.0), (1.0, 1.0, 1.0), 1.5, SUP),
    # a diagonal lying in the grid plane z = 0.5
    ((-1.0, 0.0, 0.5), (1.0, 1.0, 0.0), 1.0, HIT),
    # starting on the upper x face going out; starting on the lower y face going in
    ((0.0, 0.6, 0.6), (1.0, 0.2, 0.1), 1.0, HIT),
    ((-0.6, 0.0, 0.6), (0.1, 1.0, -0.2), 0.9, HIT),
    # outside, parallel to a face; zero length on an edge; through a corner from outside
    ((-1.1, 0.3, 0.3), (0.0, 1.0, 1.0), 1.0, HIT),
    ((-0.5, 0.5, 0.75), (0.0, -1.0, -1.0), 0.0, HIT),
    ((-1.5, -0.5, -0.5), (1.0, 1.0, 1.0), 9.0, SUP),
]


@pytest.mark.parametrize(
    "rows, lo, res, shape, r_max, chunk_size",
    [
        (ROWS_2D, SPEC_LO, SPEC_RES, SPEC_SHAPE, 4.0, 1024),
        (ROWS_2D, SPEC_LO, SPEC_RES, SPEC_SHAPE, 4.0, 5),  # several sorted chunks
        (ROWS_INF, SPEC_LO, SPEC_RES, SPEC_SHAPE, np.inf, 1024),
        (ROWS_3D, *SPEC3, 2.0, 1024),
    ],
    ids=["2d", "2d-chunked", "2d-inf", "3d"],
)
@pytest.mark.parametrize("backend", BACKENDS)
def test_accumulate_degenerate_rays_match_reference(
    rows, lo, res, shape, r_max, chunk_size, backend
):
    rays = ray_batch(rows, 0.05 if r_max < np.inf else 0.0, r_max)
    stats = accumulate(GridSpec(lo, res, shape), rays, chunk_size=chunk_size, backend=backend)
    assert_stats_match(stats, reference_stats(lo, res, shape, rays))


@pytest.mark.parametrize(
    "rows, lo, res, shape",
    [
        (ROWS_2D + [(o, d, np.inf, k) for o, d, _, k in ROWS_INF], SPEC_LO, SPEC_RES, SPEC_SHAPE),
        (ROWS_3D + [(o, d, np.inf, k) for o, d, _, k in ROWS_3D[:3]], *SPEC3),
    ],
    ids=["2d", "3d"],
)
def test_traverse_and_fold_rays_degenerate_rays_match_reference(rows, lo, res, shape):
    """Ray by ray, lengths as given (``inf`` traces to the border; SUB rays too)."""
    spec = GridSpec(lo, res, shape)
    o = jnp.asarray([r[0] for r in rows])
    d = jnp.asarray([r[1] for r in rows])
    lengths = np.asarray([r[2] for r in rows], float)
    mc = max_cells_for(spec)
    tr = jax.vmap(lambda o, d, length: traverse(spec, o, d, length, mc))(o, d, lengths)
    W = np.random.default_rng(0).uniform(0.5, 2.0, shape)
    weights = jnp.asarray(W)

    def term(cells, seg):
        return gather(weights, cells) * seg

    fold = fold_rays(spec, o, d, jnp.asarray(lengths), term, chunk_size=4)
    tr, fold = jax.tree.map(np.asarray, (tr, fold))
    for i, (oi, di, _, _) in enumerate(rows):
        cells, _ = reference_walk(lo, res, shape, np.asarray(oi), np.asarray(di), lengths[i])
        valid = tr.valid[i]
        assert tr.complete[i]
        got = [tuple(int(x) for x in c) for c in tr.cells[i][valid]]
        assert got == [c for c, _ in cells], (i, got, cells)
        np.testing.assert_allclose(tr.lengths[i][valid], [s for _, s in cells], atol=1e-12)
        assert np.all(np.isfinite(tr.lengths[i]))
        assert tr.is_last[i][valid].tolist() == [False] * (len(cells) - 1) + [True] * bool(cells)
        body = sum(W[c] * s for c, s in cells[:-1])
        np.testing.assert_allclose(fold.body[i], body, atol=1e-12)
        np.testing.assert_allclose(fold.grid_len[i], sum(s for _, s in cells), atol=1e-12)
        assert bool(fold.any_valid[i]) == bool(cells)
        if cells:
            assert tuple(int(x) for x in fold.last_cell[i]) == cells[-1][0]
            np.testing.assert_allclose(fold.last_len[i], cells[-1][1], atol=1e-12)


def float32_spec(lo, res, shape) -> GridSpec:
    """A float32 grid although tests/conftest.py enables x64 (GridSpec would promote)."""
    return jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), GridSpec(lo, res, shape))


TINY_ROWS_2D = [
    ((50.0, 50.0), (1.0, 1e-37), 450.0, HIT),
    ((50.0, 0.0), (1.0, 1e-37), 450.0, HIT),
    ((100.0, 100.0), (1.0, -1e-37), 450.0, HIT),  # starts on a line, drifts down: row 0
    ((100.0, 100.0), (1e-37, 1.0), 900.0, SUP),
    ((50.0, 50.0), (-1e-37, -1.0), 450.0, HIT),
    ((50.0, 0.0), (1.0, -1e-37), 450.0, HIT),  # on the lower face, leaving at once
    ((1000.0, 300.0), (-1.0, 1e-37), 1000.0, SUP),
]
TINY_ROWS_3D = [
    ((100.0, 100.0, 50.0), (1e-37, -1e-37, 1.0), 700.0, HIT),
    ((50.0, 200.0, 0.0), (-1e-37, 1.0, 1e-37), 999.0, SUP),
]


@pytest.mark.parametrize(
    "rows, lo, shape",
    [(TINY_ROWS_2D, (0.0, 0.0), (10, 10)), (TINY_ROWS_3D, (0.0, 0.0, 0.0), (5, 5, 10))],
    ids=["2d", "3d"],
)
def test_tiny_direction_component_float32_finishes_and_is_exact(rows, lo, shape):
    """A component of 1e-37 with 100 m cells in float32: resolution / d overflows (1e39);
    once this made 0 * inf = NaN and the walk never ended. Compared with the reference
    walk and with the same rays in float64 (where nothing overflows)."""
    spec32 = float32_spec(lo, 100.0, shape)
    rays32 = ray_batch(rows, 0.0, 800.0, np.float32)
    assert rays32.origins.dtype == np.float32 and spec32.origin.dtype == jnp.float32
    ref32 = reference_stats(lo, 100.0, shape, rays32)
    for backend in ("jax", "native") if _native.available() else ("jax",):
        stats = accumulate(spec32, rays32, backend=backend)
        assert stats.lengths.dtype == jnp.float32
        assert_stats_match(stats, ref32, rtol=1e-6, atol=1e-3)
    # float64 path as a second oracle, including a decay-rate log-likelihood
    spec64 = GridSpec(lo, 100.0, shape)
    rays64 = ray_batch(rows, 0.0, 800.0)
    assert_stats_match(accumulate(spec64, rays64), reference_stats(lo, 100.0, shape, rays64))
    rates = np.random.default_rng(1).uniform(0.001, 0.01, shape)
    m64 = decay_rate_map(accumulate(spec64, rays64), unknown_rate=0.002)
    m64 = eqx.tree_at(lambda m: m.rates, m64, jnp.asarray(rates))
    m32 = jax.tree.map(lambda x: x.astype(jnp.float32) if eqx.is_inexact_array(x) else x, m64)
    ll32 = batch_log_likelihood(m32, rays32)
    ll64 = batch_log_likelihood(m64, rays64)
    assert ll32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(ll32), np.asarray(ll64), rtol=1e-5, atol=1e-5)


# --------------------------------------------------------------------------------------
# NaN / inf into accumulate, batch_log_likelihood and ScanModel
# --------------------------------------------------------------------------------------


def _pose(theta=0.0, x=1.1):
    return jaxlie.SE2.from_xy_theta(jnp.array([x, 1.6]), jnp.array([1.2, 1.3]),
                                    jnp.array([theta, 0.1]))  # fmt: skip


BAD_POSES = {"nan-heading": dict(theta=np.nan), "inf-origin": dict(x=np.inf)}
SCANS = np.stack([RANGES, RANGES])


@eqx.filter_jit
def _stats_and_ll_from_pose(params, az, m):
    rays = from_scan(jaxlie.SE2(params), az, SCANS, R_MIN, R_MAX)
    return accumulate(m.spec, rays).lengths, batch_log_likelihood(m, rays)


@pytest.mark.parametrize("bad", list(BAD_POSES))
def test_bad_pose_raises_eagerly_and_under_jit(bad, decay_map):
    T = _pose(**BAD_POSES[bad])
    with pytest.raises(ValueError, match="T_world_sensor must be finite"):
        accumulate(spec2(), from_scan(T, AZ, SCANS, R_MIN, R_MAX))
    with pytest.raises(ValueError, match="T_world_sensor must be finite"):
        batch_log_likelihood(decay_map, from_scan(T, AZ, SCANS, R_MIN, R_MAX))
    _stats_and_ll_from_pose(_pose().parameters(), AZ, decay_map)  # valid input runs
    with pytest.raises(eqx.EquinoxRuntimeError, match="T_world_sensor must be finite"):
        jax.block_until_ready(_stats_and_ll_from_pose(T.parameters(), AZ, decay_map))
    # plain jax.jit, as a user would write it
    both = jax.jit(lambda p, m: _stats_and_ll_from_pose(p, AZ, m))
    with pytest.raises(RUNTIME, match="T_world_sensor must be finite"):
        jax.block_until_ready(both(T.parameters(), decay_map))


def test_nan_azimuth_raises_eagerly_and_under_jit(decay_map):
    az = AZ.copy()
    az[3] = np.nan
    with pytest.raises(ValueError, match="azimuths_rad must be finite"):
        accumulate(spec2(), from_scan(_pose(), az, RANGES, R_MIN, R_MAX))
    with pytest.raises(ValueError, match="azimuths_rad must be finite"):
        batch_log_likelihood(decay_map, from_scan(_pose(), az, RANGES, R_MIN, R_MAX))
    params = _pose().parameters()
    _stats_and_ll_from_pose(params, jnp.asarray(AZ), decay_map)
    with pytest.raises(eqx.EquinoxRuntimeError, match="azimuths_rad must be finite"):
        jax.block_until_ready(_stats_and_ll_from_pose(params, jnp.asarray(az), decay_map))


def _length_term(cells, seg):
    return seg


@eqx.filter_jit
def _stats_ll_fold(rays, m):
    flat = rays.flatten()
    fold = fold_rays(m.spec, flat.origins, flat.directions, flat.mapping_lengths(), _length_term)
    return accumulate(m.spec, rays).lengths, batch_log_likelihood(m, rays), fold.body


@pytest.mark.parametrize(
    "field, index, value, message",
    [
        ("directions", (0, 2, 1), np.nan, "ray directions must be finite"),
        ("origins", (1, 0, 0), np.inf, "ray origins must be finite"),
        ("ranges", (0, 1), np.nan, "ray lengths must be >= 0 and not NaN"),
    ],
)
def test_geometry_core_rejects_bad_rays_itself(field, index, value, message, decay_map):
    """Rays that slipped past the builders (``tree_at`` skips ``RayBatch.__init__``) are
    still caught by the core's own checks, eagerly and under ``jit``: no hang."""
    bad = with_leaf(good_rays(), field, index, value)
    spec = spec2()
    for backend in ("jax", "native") if _native.available() else ("jax",):
        with pytest.raises(RUNTIME, match=message):
            jax.block_until_ready(accumulate(spec, bad, backend=backend).hits)
    with pytest.raises(RUNTIME, match=message):
        jax.block_until_ready(batch_log_likelihood(decay_map, bad))
    _stats_ll_fold(good_rays(), decay_map)
    with pytest.raises(RUNTIME, match=message):
        jax.block_until_ready(_stats_ll_fold(bad, decay_map))


@eqx.filter_jit
def _scan_step(model, params, ranges):
    return model(jaxlie.SE2(params), ranges)


def test_scan_model_rejects_bad_particles_and_azimuths(decay_map):
    model = ScanModel(decay_map, AZ, R_MIN, R_MAX, ray_floor=-30.0)
    good = model(_pose(), RANGES)
    assert good.shape == (2,) and np.all(np.isfinite(np.asarray(good)))
    for kw in BAD_POSES.values():
        with pytest.raises(ValueError, match="T_world_sensor must be finite"):
            model(_pose(**kw), RANGES)
    az = AZ.copy()
    az[0] = np.nan
    with pytest.raises(ValueError, match="azimuths"):
        ScanModel(decay_map, az, R_MIN, R_MAX)

    np.testing.assert_allclose(_scan_step(model, _pose().parameters(), RANGES), good, rtol=1e-12)
    for kw in BAD_POSES.values():
        with pytest.raises(eqx.EquinoxRuntimeError, match="T_world_sensor must be finite"):
            jax.block_until_ready(_scan_step(model, _pose(**kw).parameters(), RANGES))
    nan_az = eqx.tree_at(lambda m: m.azimuths, model, jnp.asarray(az))  # skips __init__
    with pytest.raises(eqx.EquinoxRuntimeError, match="azimuths_rad must be finite"):
        jax.block_until_ready(_scan_step(nan_az, _pose().parameters(), RANGES))
    bad_r = RANGES.copy()
    bad_r[2] = np.nan
    with pytest.raises(eqx.EquinoxRuntimeError, match="ranges_m must be finite"):
        jax.block_until_ready(_scan_step(model, _pose().parameters(), bad_r))


@jax.jit
def _stats_and_fold_at_resolution(res):
    spec = GridSpec(SPEC_LO, res, SPEC_SHAPE)
    rays = good_rays()
    flat = rays.flatten()
    fold = fold_rays(spec, flat.origins, flat.directions, flat.mapping_lengths(), _length_term)
    return accumulate(spec, rays, backend="jax").lengths, fold.grid_len


@jax.jit
def _stats_at_resolution_native(res):
    return accumulate(GridSpec(SPEC_LO, res, SPEC_SHAPE), good_rays(), backend="native").lengths


@pytest.mark.parametrize("res", [np.nan, np.inf, 0.0, -0.5])
def test_traced_bad_resolution_reaches_check_rays(res, decay_map):
    """``GridSpec`` rejects a concrete resolution at once and a traced one at run time
    (``eqx.error_if`` in ``GridSpec``, before the walks' own ``check_rays``); a spec that
    bypasses ``__init__`` (``eqx.tree_at``) is still caught by the walks."""
    with pytest.raises(ValueError, match="resolution"):
        GridSpec(SPEC_LO, res, SPEC_SHAPE)
    lengths, _ = _stats_and_fold_at_resolution(SPEC_RES)
    np.testing.assert_allclose(lengths, accumulate(spec2(), good_rays()).lengths)
    with pytest.raises(RUNTIME, match="resolution must be a positive finite number"):
        jax.block_until_ready(_stats_and_fold_at_resolution(res))
    if _native.available():
        with pytest.raises(RUNTIME, match="resolution must be a positive finite number"):
            jax.block_until_ready(_stats_at_resolution_native(res))
    # a map whose spec carries the bad resolution (tree_at skips GridSpec.__init__)
    bad_map = eqx.tree_at(lambda m: m.spec.resolution, decay_map, jnp.asarray(res))
    with pytest.raises(RUNTIME, match="resolution.*positive and finite"):
        jax.block_until_ready(batch_log_likelihood(bad_map, good_rays()))


@pytest.mark.parametrize(
    "o, d, length",
    [((np.nan, 1.0), (1.0, 0.0), 1.0), ((np.inf, 1.0), (-1.0, 0.0), 1.0),
     ((1.0, 1.0), (1.0, 0.0), np.nan), ((1.0, 1.0), (np.nan, 0.0), 1.0)],
    ids=["nan-origin", "inf-origin", "nan-length", "nan-direction"],
)  # fmt: skip
def test_traverse_rejects_non_finite_rays(o, d, length):
    with pytest.raises(RUNTIME, match="must be"):
        tr = traverse(spec2(), jnp.asarray(o), jnp.asarray(d), length, 16)
        jax.block_until_ready(tr)


# --------------------------------------------------------------------------------------
# Former hangs, in a subprocess with a timeout
# --------------------------------------------------------------------------------------


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_subprocess_float32_tiny_component_does_not_hang():
    """Default JAX (no x64, float32 everywhere), as the bug was first met."""
    proc = _run(
        """
        import json, jax, jax.numpy as jnp, numpy as np
        from lidarjax.rays import RayBatch, HIT, SUP
        from lidarjax.raytrace import GridSpec, accumulate
        from lidarjax.maps import decay_rate_map
        from lidarjax.sensor_models import batch_log_likelihood
        assert not jax.config.jax_enable_x64
        spec = GridSpec([0.0, 0.0], 100.0, (10, 10))
        rays = RayBatch(jnp.array([[50.0, 50.0], [100.0, 100.0]]),
                        jnp.array([[1.0, 1e-37], [1e-37, 1.0]]), jnp.array([450.0, 900.0]),
                        jnp.array([HIT, SUP]), jnp.array(0.0), jnp.array(800.0))
        st = accumulate(spec, rays)
        ll = batch_log_likelihood(decay_rate_map(st, unknown_rate=0.01), rays)
        print(json.dumps({"dtype": str(st.lengths.dtype), "H": np.asarray(st.hits).tolist(),
                          "M": np.asarray(st.misses).tolist(),
                          "R": np.asarray(st.lengths).tolist(),
                          "ll": np.asarray(ll).tolist()}))
        """
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["dtype"] == "float32"
    rays = ray_batch(
        [((50.0, 50.0), (1.0, 1e-37), 450.0, HIT), ((100.0, 100.0), (1e-37, 1.0), 900.0, SUP)],
        0.0,
        800.0,
        np.float32,
    )
    H, M, R = reference_stats((0.0, 0.0), 100.0, (10, 10), rays)
    np.testing.assert_array_equal(out["H"], H)
    np.testing.assert_array_equal(out["M"], M)
    np.testing.assert_allclose(out["R"], R, rtol=1e-6)
    assert np.all(np.isfinite(out["ll"]))


def test_subprocess_nan_heading_and_azimuth_raise_under_jit():
    proc = _run(
        """
        import jax, jax.numpy as jnp, jaxlie, numpy as np
        from lidarjax.rays import from_scan
        from lidarjax.raytrace import GridSpec, accumulate
        from lidarjax.maps import decay_rate_map
        from lidarjax.sensor_models import batch_log_likelihood
        spec = GridSpec([0.0, 0.0], 0.5, (6, 5))
        az = jnp.linspace(-1.0, 1.0, 5)
        m = decay_rate_map(accumulate(spec, from_scan(jaxlie.SE2.from_xy_theta(1.0, 1.0, 0.0),
                           az, jnp.ones(5), 0.1, 4.0)), unknown_rate=0.1)

        @jax.jit
        def run(theta, az):
            rays = from_scan(jaxlie.SE2.from_xy_theta(1.0, 1.0, theta), az, jnp.ones(5), 0.1, 4.0)
            return accumulate(spec, rays).lengths.sum() + batch_log_likelihood(m, rays).sum()

        run(0.0, az).block_until_ready()
        for theta, a, name in ((jnp.nan, az, "T_world_sensor"), (0.0, az.at[2].set(jnp.nan),
                                                                   "azimuths_rad")):
            try:
                run(theta, a).block_until_ready()
            except Exception as e:
                assert name + " must be finite" in str(e), str(e)[-2000:]
                print("raised", name)
            else:
                raise SystemExit("no error for " + name)
        """
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "raised T_world_sensor" in proc.stdout and "raised azimuths_rad" in proc.stdout


def test_subprocess_nan_direction_past_builders_raises_in_core():
    """NaN directions that reach the walk directly (no builder) end in an error."""
    proc = _run(
        """
        import jax, jax.numpy as jnp, equinox as eqx
        from lidarjax.rays import RayBatch, HIT
        from lidarjax.raytrace import GridSpec, accumulate
        spec = GridSpec([0.0, 0.0], 0.5, (6, 5))
        rays = RayBatch(jnp.ones((3, 2)), jnp.ones((3, 2)), jnp.ones(3),
                        jnp.full(3, HIT), jnp.array(0.0), jnp.array(4.0))
        bad = eqx.tree_at(lambda r: r.directions, rays, rays.directions.at[1, 0].set(jnp.nan))
        f = jax.jit(lambda r: accumulate(spec, r).hits)
        f(rays).block_until_ready()
        try:
            f(bad).block_until_ready()
        except Exception as e:
            assert "ray directions must be finite" in str(e), str(e)[-2000:]
            print("raised")
        """
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "raised" in proc.stdout


# --------------------------------------------------------------------------------------
# The builders' checks (lidarjax.rays), eager and under jit
# --------------------------------------------------------------------------------------


def test_from_scan_checks_pose_azimuths_ranges_and_limits():
    T = jaxlie.SE2.identity()
    az, r = np.zeros(3), np.ones(3)
    with pytest.raises(ValueError, match="T_world_sensor must be finite"):
        from_scan(jaxlie.SE2.from_xy_theta(0.0, 0.0, np.nan), az, r)
    with pytest.raises(ValueError, match="T_world_sensor must be finite"):
        from_scan(jaxlie.SE2.from_xy_theta(-np.inf, 0.0, 0.0), az, r)
    for bad_az in (np.nan, np.inf):
        with pytest.raises(ValueError, match="azimuths_rad must be finite"):
            from_scan(T, np.array([0.0, bad_az, 0.0]), r)
    with pytest.raises(ValueError, match="r_min must be finite and >= 0"):
        from_scan(T, az, r, -0.1, 5.0)
    with pytest.raises(ValueError, match="r_min must be finite and >= 0"):
        from_scan(T, az, r, np.nan, 5.0)
    with pytest.raises(ValueError, match="r_max must be larger than r_min"):
        from_scan(T, az, r, 2.0, 1.0)
    with pytest.raises(ValueError, match="r_max must be larger than r_min"):
        from_scan(T, az, r, 0.0, np.nan)
    with pytest.raises(ValueError, match="scalars"):
        from_scan(T, az, r, 0.0, np.ones(2))

    @eqx.filter_jit
    def build(params, az, r, r_min, r_max):
        return from_scan(jaxlie.SE2(params), az, r, r_min, r_max)

    ok = build(T.parameters(), jnp.asarray(az), jnp.asarray(r), 0.0, 5.0)
    ref = from_scan(T, az, r, 0.0, 5.0)
    for a, b in zip(jax.tree.leaves(ok), jax.tree.leaves(ref)):
        np.testing.assert_array_equal(a, b)
    args = (T.parameters(), jnp.asarray(az), jnp.asarray(r), jnp.asarray(0.0), jnp.asarray(5.0))
    cases = [
        (0, jaxlie.SE2.from_xy_theta(0.0, 0.0, np.nan).parameters(), "T_world_sensor"),
        (0, jaxlie.SE2.from_xy_theta(0.0, np.inf, 0.0).parameters(), "T_world_sensor"),
        (1, jnp.array([0.0, np.nan, 0.0]), "azimuths_rad must be finite"),
        (2, jnp.array([1.0, -1.0, 1.0]), "ranges_m must be finite and non-negative"),
        (3, jnp.asarray(-0.5), "r_min must be finite and >= 0"),
        (4, jnp.asarray(np.nan), "r_max must be larger than r_min"),
        (4, jnp.asarray(0.0), "r_max must be larger than r_min"),
    ]
    for i, value, message in cases:
        bad = list(args)
        bad[i] = value
        with pytest.raises(eqx.EquinoxRuntimeError, match=message):
            jax.block_until_ready(build(*bad).kind)


def test_from_points_and_spinning_scan_checks():
    T = jaxlie.SE3.identity()
    nan_T = jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.identity(), jnp.array([0, np.nan, 0])
    )
    d = np.eye(3)
    with pytest.raises(ValueError, match="T_world_sensor must be finite"):
        from_points(nan_T, np.ones((2, 3)))
    with pytest.raises(ValueError, match="T_world_sensor must be finite"):
        from_spinning_scan(nan_T, d, np.ones(3))
    with pytest.raises(ValueError, match="directions must be finite and non-zero"):
        from_spinning_scan(T, np.array([[1.0, 0, 0], [0, np.inf, 0], [0, 0, 1]]), np.ones(3))
    with pytest.raises(ValueError, match="directions must be finite and non-zero"):
        from_spinning_scan(T, np.array([[1.0, 0, 0], [0, 0, 0], [0, 0, 1]]), np.ones(3))
    with pytest.raises(ValueError, match="ranges_m must be >= 0"):
        from_spinning_scan(T, d, np.array([1.0, -2.0, 1.0]), r_max=5.0)
    with pytest.raises(ValueError, match="r_min"):
        from_spinning_scan(T, d, np.ones(3), r_min=-1.0, r_max=5.0)

    @eqx.filter_jit
    def spin(params, dirs, r, r_max):
        return from_spinning_scan(jaxlie.SE3(params), dirs, r, 0.1, r_max)

    @eqx.filter_jit
    def points(params, pts):
        return from_points(jaxlie.SE3(params), pts, 0.0, 5.0)

    p, nan_p = T.parameters(), nan_T.parameters()
    np.testing.assert_array_equal(
        spin(p, jnp.asarray(d), jnp.array([1.0, np.inf, 0.05]), 5.0).kind, [HIT, SUP, SUB]
    )
    points(p, jnp.ones((2, 3)))
    cases = [
        (lambda: spin(nan_p, d, jnp.ones(3), 5.0), "T_world_sensor must be finite"),
        (lambda: spin(p, jnp.asarray(d).at[1, 1].set(np.nan), jnp.ones(3), 5.0), "finite"),
        (lambda: spin(p, jnp.asarray(d).at[2].set(0.0), jnp.ones(3), 5.0), "non-zero"),
        (lambda: spin(p, d, jnp.array([1.0, np.nan, 1.0]), 5.0), "ranges_m must be >= 0"),
        (lambda: spin(p, d, jnp.array([1.0, -1.0, 1.0]), 5.0), "ranges_m must be >= 0"),
        (lambda: spin(p, d, jnp.array([1.0, np.inf, 1.0]), jnp.inf), "give a finite r_max"),
        (lambda: points(nan_p, jnp.ones((2, 3))), "T_world_sensor must be finite"),
        (lambda: points(p, jnp.ones((2, 3)).at[0, 1].set(np.nan)), "points_xyz"),
    ]
    for call, message in cases:
        with pytest.raises(eqx.EquinoxRuntimeError, match=message):
            jax.block_until_ready(call())


def test_raybatch_constructor_checks_values():
    fields = dict(
        origins=jnp.zeros((3, 2)),
        directions=jnp.array([[1.0, 0.0]] * 3),
        ranges=jnp.array([1.0, 0.1, np.inf]),
        kind=jnp.array([HIT, SUB, SUP]),
        r_min=0.2,
        r_max=5.0,
    )
    rays = RayBatch(**fields)  # +inf is a valid raw reading of a SUP ray
    assert rays.r_min == 0.2  # concrete fields are stored as given
    RayBatch(**{**fields, "ranges": jnp.array([0.2, 0.1, np.inf]), "r_max": 0.2})  # r_max = r_min
    cases = [
        ("origins", fields["origins"].at[1, 0].set(np.nan), "origins must be finite"),
        ("directions", fields["directions"].at[2, 1].set(-np.inf), "directions must be finite"),
        ("ranges", fields["ranges"].at[0].set(np.nan), "ranges must be >= 0 and not NaN"),
        ("ranges", fields["ranges"].at[1].set(-0.1), "ranges must be >= 0 and not NaN"),
        ("ranges", fields["ranges"].at[0].set(np.inf), r"\+inf only for SUP"),
        ("kind", fields["kind"].at[0].set(3), "kind must be HIT"),
        ("r_min", -1.0, "r_min must be finite and >= 0"),
        ("r_max", 0.1, "r_max must be at least r_min"),
    ]
    # each check rides on its own field (eqx.error_if): return them all
    build = eqx.filter_jit(lambda **kw: RayBatch(**kw))
    build(**{k: jnp.asarray(v) for k, v in fields.items()})
    for name, value, message in cases:
        with pytest.raises(ValueError, match=message):
            RayBatch(**{**fields, name: value})
        traced = {k: jnp.asarray(v) for k, v in {**fields, name: value}.items()}
        with pytest.raises(eqx.EquinoxRuntimeError, match=message):
            jax.block_until_ready(build(**traced))


def test_classify_never_calls_nan_a_hit():
    np.testing.assert_array_equal(classify(jnp.array([0.1, 1.0, np.inf]), 0.2, 5.0),
                                  [SUB, HIT, SUP])  # fmt: skip
    with pytest.raises(ValueError, match="ranges_m must be >= 0 and not NaN"):
        classify(jnp.array([1.0, np.nan]), 0.2, 5.0)
    with pytest.raises(ValueError, match="r_max must be at least r_min"):
        classify(jnp.array([1.0]), 0.2, 0.1)
    f = jax.jit(classify)
    with pytest.raises(RUNTIME, match="ranges_m must be >= 0 and not NaN"):
        jax.block_until_ready(f(jnp.array([1.0, np.nan]), 0.2, 5.0))
    with pytest.raises(RUNTIME, match="r_min must be finite"):
        jax.block_until_ready(f(jnp.array([1.0]), -0.2, 5.0))
