"""Tests for lidarjax.sensor_models.batch_log_likelihood (the fast, forward-only path) and
lidarjax.raytrace.fold_rays: both must reproduce the differentiable ``lax.scan`` path
(``fold_traversal`` of ``traverse``) to round-off, on random rays and on the geometric
edge cases of the voxel walk."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lidarjax.maps import (
    BetaPosteriorMap,
    DecayRateMap,
    EndpointMap,
    GammaPosteriorMap,
    ReflectionMap,
    distance_transform,
    posterior_log_likelihood,
)
from lidarjax.rays import HIT, SUB, SUP, RayBatch
from lidarjax.raytrace import GridSpec, fold_rays, fold_traversal, max_cells_for, traverse
from lidarjax.sensor_models import (
    batch_log_likelihood,
    decay_rate_log_likelihood,
    endpoint_log_likelihood,
    reflection_log_likelihood,
)

TOL = 1e-9

# --------------------------------------------------------------------------------------
# Scenes
# --------------------------------------------------------------------------------------

SPEC2 = GridSpec(np.array([-1.0, 0.5]), 0.5, (8, 6))  # x in [-1, 3], y in [0.5, 3.5]
SPEC3 = GridSpec(np.array([-1.0, 0.5, 0.0]), 0.5, (5, 4, 3))


def _unit(d):
    d = np.asarray(d, np.float64)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _edge_rays_2d():
    """(origin, direction, range) of hand-picked geometric edge cases in SPEC2."""
    s2 = math.sqrt(2.0)
    return [
        # never enter the grid
        ((-3.0, -3.0), (-1.0, 0.0), 2.0),
        ((5.0, 2.0), (0.0, 1.0), 3.0),
        ((-3.0, 1.0), (-1.0, 0.2), 10.0),
        ((-2.0, 4.0), (1.0, 0.0), 5.0),  # parallel to the grid, above it
        # start inside and leave the grid
        ((1.0, 2.0), (1.0, 0.3), 10.0),
        ((0.3, 1.1), (-0.4, -1.0), 6.0),
        # start outside, enter, end inside / pass through
        ((-3.0, 1.2), (1.0, 0.0), 3.5),
        ((-3.0, 1.2), (1.0, 0.0), 9.0),
        ((1.3, -2.0), (0.1, 1.0), 3.0),
        # start outside and end before reaching the grid
        ((-3.0, 1.2), (1.0, 0.0), 1.0),
        # zero length inside and outside
        ((0.3, 1.1), (1.0, 0.0), 0.0),
        ((-3.0, -3.0), (1.0, 1.0), 0.0),
        ((0.0, 1.0), (0.0, 1.0), 0.0),  # zero length on a cell corner
        # axis-parallel, inside cells and along grid lines / the boundary
        ((0.2, 1.3), (1.0, 0.0), 2.1),
        ((0.2, 1.3), (-1.0, 0.0), 2.1),
        ((0.2, 1.3), (0.0, 1.0), 1.7),
        ((0.2, 1.3), (0.0, -1.0), 1.7),
        ((0.5, 0.7), (0.0, 1.0), 2.0),  # along the interior grid line x = 0.5
        ((-1.0, 0.5), (1.0, 0.0), 3.0),  # along the lower boundary y = 0.5
        ((-1.5, 1.0), (1.0, 0.0), 6.0),  # from outside along the grid line y = 1
        ((0.0, 3.5), (1.0, 0.0), 2.0),  # along the upper boundary y = 3.5
        # through cell corners
        ((-1.0, 0.5), (1.0, 1.0), 4.0),  # from the grid corner along the diagonal
        ((-2.0, -0.5), (1.0, 1.0), 3.0),  # enters exactly at the grid corner
        ((0.0, 1.0), (1.0, 1.0), s2),  # ends exactly on a corner
        ((2.0, 3.0), (-1.0, -1.0), 2.5 * s2),
        ((1.5, 1.0), (-1.0, 1.0), 10.0),  # anti-diagonal through corners, leaves
        ((3.0, 3.5), (-1.0, -1.0), 20.0),  # from the upper corner, whole diagonal
    ]


def _random_rays(rng, spec, n):
    lo, hi = np.asarray(spec.origin), np.asarray(spec.upper)
    o = rng.uniform(lo - 1.5, hi + 1.5, size=(n, spec.dim))
    d = _unit(rng.normal(size=(n, spec.dim)))
    r = rng.uniform(0.0, 1.2 * float(np.linalg.norm(hi - lo)), size=n)
    return o, d, r


def _axis_rays_3d():
    return [
        ((0.2, 1.3, 0.4), (1.0, 0.0, 0.0), 2.0),
        ((0.2, 1.3, 0.4), (0.0, -1.0, 0.0), 5.0),
        ((0.2, 1.3, 0.4), (0.0, 0.0, 1.0), 0.7),
        ((0.0, 1.0, 0.5), (1.0, 1.0, 1.0), 10.0),  # through cell corners
        ((-1.0, 0.5, 0.0), (1.0, 1.0, 1.0), 1.0),  # from the grid corner
        ((0.0, 1.0, 0.0), (1.0, 0.0, 0.0), 0.0),  # zero length on a corner
        ((-3.0, -3.0, -3.0), (-1.0, 0.0, 0.0), 2.0),  # never enters
        ((-0.5, 1.0, 0.5), (0.0, 1.0, 0.0), 3.0),  # along a grid edge line
    ]


def _geometry(dim, seed=0, n_random=40):
    rng = np.random.default_rng(seed)
    spec = SPEC2 if dim == 2 else SPEC3
    edges = _edge_rays_2d() if dim == 2 else _axis_rays_3d()
    o_e = np.array([e[0] for e in edges], np.float64)
    d_e = _unit([e[1] for e in edges])
    r_e = np.array([e[2] for e in edges], np.float64)
    o_r, d_r, r_r = _random_rays(rng, spec, n_random)
    return spec, np.vstack([o_e, o_r]), np.vstack([d_e, d_r]), np.concatenate([r_e, r_r])


def _all_kinds(o, d, r, r_min, r_max):
    """Every geometric ray as a HIT, a SUB and a SUP ray: shape [3, n]."""
    n = len(r)
    kind = np.repeat(np.array([HIT, SUB, SUP])[:, None], n, axis=1)
    return RayBatch(
        origins=jnp.asarray(np.broadcast_to(o, (3, *o.shape)).copy()),
        directions=jnp.asarray(np.broadcast_to(d, (3, *d.shape)).copy()),
        ranges=jnp.asarray(np.broadcast_to(r, (3, n)).copy()),
        kind=jnp.asarray(kind, jnp.int32),
        r_min=jnp.asarray(r_min, jnp.float64),
        r_max=jnp.asarray(r_max, jnp.float64),
    )


# (r_min, r_max): ordinary limits, a zero r_min (zero-length SUB rays) with an infinite
# r_max (SUP rays traced to the grid border), and an r_max shorter than some ranges.
LIMITS = [(0.4, 4.0), (0.0, math.inf), (0.25, 1.3)]


def _maps(spec, seed=1):
    rng = np.random.default_rng(seed)
    shape = spec.shape
    rates = rng.uniform(0.0, 2.0, shape)
    rates[rng.uniform(size=shape) < 0.15] = 0.0
    probs = rng.uniform(0.0, 1.0, shape)
    probs[rng.uniform(size=shape) < 0.1] = 0.0
    probs[rng.uniform(size=shape) < 0.05] = 1.0
    occupied = rng.uniform(size=shape) < 0.2
    occupied.flat[0] = True
    hits = rng.integers(0, 5, shape).astype(np.float64)
    misses = rng.integers(0, 8, shape).astype(np.float64)
    lengths = rng.uniform(0.0, 3.0, shape)
    unvisited = rng.uniform(size=shape) < 0.2
    hits[unvisited], misses[unvisited], lengths[unvisited] = 0.0, 0.0, 0.0
    f64 = jnp.float64
    return {
        "decay": DecayRateMap(spec, jnp.asarray(rates), jnp.asarray(0.3, f64)),
        "decay_zero_outside": DecayRateMap(spec, jnp.asarray(rates), jnp.asarray(0.0, f64)),
        "reflection": ReflectionMap(spec, jnp.asarray(probs), jnp.asarray(0.2, f64)),
        "endpoint": EndpointMap(
            spec,
            distance_transform(jnp.asarray(occupied), float(spec.resolution)),
            jnp.asarray(occupied),
            jnp.asarray(0.3, f64),
            jnp.asarray(0.8, f64),
            jnp.asarray(0.2, f64),
            jnp.asarray(0.05, f64),
        ),
        "beta": BetaPosteriorMap(
            spec,
            jnp.asarray(hits),
            jnp.asarray(misses),
            jnp.asarray(0.7, f64),
            jnp.asarray(2.5, f64),
        ),
        "gamma": GammaPosteriorMap(
            spec,
            jnp.asarray(hits),
            jnp.asarray(lengths),
            jnp.asarray(1.3, f64),
            jnp.asarray(0.6, f64),
        ),
        # improper prior: unvisited cells give -inf to rays that cross them
        "gamma_improper": GammaPosteriorMap(
            spec,
            jnp.asarray(hits),
            jnp.asarray(lengths),
            jnp.asarray(1.0, f64),
            jnp.asarray(0.0, f64),
        ),
    }


REFERENCE = {
    "decay": decay_rate_log_likelihood,
    "decay_zero_outside": decay_rate_log_likelihood,
    "reflection": reflection_log_likelihood,
    "endpoint": endpoint_log_likelihood,
    "beta": posterior_log_likelihood,
    "gamma": posterior_log_likelihood,
    "gamma_improper": posterior_log_likelihood,
}


def _assert_same(fast, ref):
    fast, ref = np.asarray(fast), np.asarray(ref)
    assert fast.shape == ref.shape
    assert not np.any(np.isnan(fast)) and not np.any(np.isnan(ref))
    # equal infinities (same sign) where either side is infinite
    inf = np.isinf(fast) | np.isinf(ref)
    np.testing.assert_array_equal(fast[inf], ref[inf])
    np.testing.assert_allclose(fast[~inf], ref[~inf], rtol=TOL, atol=TOL)


# --------------------------------------------------------------------------------------
# batch_log_likelihood vs the differentiable models
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("limits", LIMITS, ids=["finite", "rmin0_rmaxinf", "short_rmax"])
@pytest.mark.parametrize("name", list(REFERENCE))
@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_batch_matches_differentiable_2d(name, limits):
    spec, o, d, r = _geometry(2)
    rays = _all_kinds(o, d, r, *limits)  # 3 x 67 rays, not a multiple of chunk_size
    m = _maps(spec)[name]
    ref = REFERENCE[name](m, rays, max_cells=max_cells_for(spec))
    fast = batch_log_likelihood(m, rays, chunk_size=16)
    _assert_same(fast, ref)
    # the batch is non-trivial: finite HIT values occur, and of every kind for the
    # ordinary limits (r_min = 0 makes every SUB ray impossible)
    kinds = (HIT, SUB, SUP) if limits == LIMITS[0] else (HIT,)
    for k in kinds:
        assert np.any(np.isfinite(np.asarray(ref)[k])), (name, k)


def test_batch_hand_value_decay():
    """A closed form independent of the walk: a horizontal HIT ray through three cells of
    rates 1, 2, 3 (0.5 m each) ending half-way into the third: log 3 - (0.5 + 1 + 0.75)."""
    spec = GridSpec(np.array([0.0, 0.0]), 0.5, (4, 2))
    rates = np.zeros((4, 2))
    rates[:3, 0] = [1.0, 2.0, 3.0]
    m = DecayRateMap(spec, jnp.asarray(rates), jnp.asarray(0.0, jnp.float64))
    rays = RayBatch(
        origins=jnp.asarray([[0.0, 0.2], [0.0, 0.2]]),
        directions=jnp.asarray([[1.0, 0.0], [1.0, 0.0]]),
        ranges=jnp.asarray([1.25, 9.0]),
        kind=jnp.asarray([HIT, SUP], jnp.int32),
        r_min=jnp.asarray(0.0),
        r_max=jnp.asarray(1.25),
    )
    out = np.asarray(batch_log_likelihood(m, rays))
    np.testing.assert_allclose(out, [math.log(3.0) - 2.25, -2.25], rtol=1e-13, atol=1e-13)


# --------------------------------------------------------------------------------------
# fold_rays vs fold_traversal
# --------------------------------------------------------------------------------------


def _term_fn(values, cells, lengths):
    idx = tuple(jnp.clip(cells[..., k], 0, values.shape[k] - 1) for k in range(values.ndim))
    # nonlinear in the length and +1 per cell, so the cell count has to match too
    return values[idx] * jnp.sqrt(lengths) + 1.0


def _fold_reference(spec, o, d, lengths, values):
    mc = max_cells_for(spec)
    tr = jax.vmap(lambda a, b, c: traverse(spec, a, b, c, mc))(o, d, lengths)
    return fold_traversal(tr, jax.tree_util.Partial(_term_fn, values))


@pytest.mark.parametrize(("dim", "chunk_size"), [(2, 7), (3, 64)])
@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_fold_rays_matches_fold_traversal(dim, chunk_size):
    spec, o, d, r = _geometry(dim, seed=11, n_random=30)
    n = len(r)
    assert n % 7 and n < 64  # 7 does not divide n; 64 > n is one partial chunk
    rng = np.random.default_rng(12)
    # non-unit directions (normalised internally), infinite and zero lengths
    d = d * rng.uniform(0.3, 3.0, size=(n, 1))
    r = r.copy()
    r[rng.uniform(size=n) < 0.2] = np.inf
    r[:3] = 0.0
    values = jnp.asarray(rng.uniform(0.1, 2.0, spec.shape))
    o_j, d_j, r_j = jnp.asarray(o), jnp.asarray(d), jnp.asarray(r)
    ref = _fold_reference(spec, o_j, d_j, r_j, values)
    got = fold_rays(spec, o_j, d_j, r_j, jax.tree_util.Partial(_term_fn, values), chunk_size)
    assert bool(jnp.all(ref.complete)) and bool(jnp.all(got.complete))
    valid = np.asarray(ref.any_valid)
    assert valid.any() and not valid.all()
    np.testing.assert_array_equal(np.asarray(got.any_valid), valid)
    np.testing.assert_array_equal(
        np.asarray(got.last_cell)[valid], np.asarray(ref.last_cell)[valid]
    )
    for field in ("body", "last_len", "grid_len", "t_start", "t_end"):
        np.testing.assert_allclose(
            np.asarray(getattr(got, field)),
            np.asarray(getattr(ref, field)),
            rtol=TOL,
            atol=TOL,
            err_msg=field,
        )
    np.testing.assert_array_equal(np.asarray(got.last_len)[~valid], 0.0)
    np.testing.assert_array_equal(np.asarray(got.grid_len)[~valid], 0.0)


@pytest.mark.parametrize("streams", [1, 3])
@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_fold_rays_streams_do_not_change_results(streams):
    spec, o, d, r = _geometry(2, seed=5, n_random=30)
    values = jnp.asarray(np.random.default_rng(6).uniform(0.1, 2.0, spec.shape))
    term = jax.tree_util.Partial(_term_fn, values)
    args = (spec, jnp.asarray(o), jnp.asarray(d), jnp.asarray(r), term)
    ref = fold_rays(*args, chunk_size=4, streams=2)
    got = fold_rays(*args, chunk_size=4, streams=streams)
    for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(got)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=TOL, atol=TOL)


def test_fold_rays_bad_arguments():
    spec, o, d, r = _geometry(2, seed=5, n_random=3)
    term = jax.tree_util.Partial(_term_fn, jnp.ones(spec.shape))
    args = (spec, jnp.asarray(o), jnp.asarray(d), jnp.asarray(r), term)
    with pytest.raises(ValueError, match="chunk_size"):
        fold_rays(*args, chunk_size=0)
    with pytest.raises(ValueError, match="streams"):
        fold_rays(*args, streams=0)
    with pytest.raises(ValueError, match="empty"):
        fold_rays(spec, jnp.zeros((0, 2)), jnp.zeros((0, 2)), jnp.zeros(0), term)


def test_fold_rays_closed_form():
    """Independent of traverse: a ray crossing the whole grid along x travels the grid
    width inside it, the diagonal from the grid corner the diagonal of 6 x 6 cells (corner
    crossings taken together), a short ray inside the grid its length; with a zero map the
    term is exactly 1 per cell, so ``body`` counts the cells before the last."""
    spec = SPEC2
    o = jnp.asarray([[-5.0, 1.3], [-1.0, 0.5], [0.1, 1.1], [-5.0, -5.0]])
    d = jnp.asarray([[1.0, 0.0], [1.0, 1.0], [0.6, 0.8], [1.0, 0.0]])
    r = jnp.asarray([np.inf, np.inf, 1.7, 100.0])
    f = fold_rays(spec, o, d, r, jax.tree_util.Partial(_term_fn, jnp.zeros(spec.shape)), 3)
    np.testing.assert_allclose(
        np.asarray(f.grid_len), [4.0, 3.0 * math.sqrt(2.0), 1.7, 0.0], rtol=1e-12, atol=1e-12
    )
    # third ray: (0.1, 1.1) -> (1.12, 2.46) crosses x = 0.5, 1.0 and y = 1.5, 2.0 apart
    np.testing.assert_array_equal(np.asarray(f.body), [7.0, 5.0, 4.0, 0.0])
    np.testing.assert_array_equal(np.asarray(f.any_valid), [True, True, True, False])
    np.testing.assert_array_equal(np.asarray(f.last_cell)[:3], [[7, 1], [5, 5], [4, 3]])
    np.testing.assert_allclose(np.asarray(f.last_len)[:2], [0.5, 0.5 * math.sqrt(2.0)])


# --------------------------------------------------------------------------------------
# Input validation
# --------------------------------------------------------------------------------------


def test_bad_inputs_raise_value_error():
    spec, o, d, r = _geometry(2, n_random=3)
    rays = _all_kinds(o, d, r, 0.4, 4.0)
    m = _maps(spec)["decay"]
    with pytest.raises(ValueError, match="model must be a grid model"):
        batch_log_likelihood(np.zeros(spec.shape), rays)
    with pytest.raises(ValueError, match="rays must be a RayBatch"):
        batch_log_likelihood(m, (o, d, r))
    m3 = _maps(SPEC3)["decay"]
    with pytest.raises(ValueError, match="2-D but model is a 3-D"):
        batch_log_likelihood(m3, rays)
    for bad in (0, -3, 2.5, None):
        with pytest.raises(ValueError, match="chunk_size"):
            batch_log_likelihood(m, rays, chunk_size=bad)
    empty = RayBatch(
        origins=jnp.zeros((0, 2)),
        directions=jnp.zeros((0, 2)),
        ranges=jnp.zeros((0,)),
        kind=jnp.zeros((0,), jnp.int32),
        r_min=jnp.asarray(0.0),
        r_max=jnp.asarray(1.0),
    )
    with pytest.raises(ValueError, match="empty"):
        batch_log_likelihood(m, empty)
