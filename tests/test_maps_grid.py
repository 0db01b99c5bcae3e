"""Tests for lidarjax.maps grid maps: Eq. (7.10), Eq. (7.22), distance transform."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lidarjax.maps import (
    DecayRateMap,
    EndpointMap,
    ReflectionMap,
    decay_rate_map,
    distance_transform,
    endpoint_map,
    reflection_map,
)
from lidarjax.rays import HIT, RayBatch
from lidarjax.raytrace import GridSpec, GridStats, accumulate


def _stats():
    spec = GridSpec([0.0, 0.0], 0.5, (3, 2))
    hits = jnp.array([[2, 0], [0, 1], [0, 0]], jnp.int32)
    misses = jnp.array([[1, 3], [0, 1], [0, 2]], jnp.int32)
    lengths = jnp.array([[1.5, 2.0], [0.0, 0.25], [0.0, 0.5]])
    return GridStats(spec, hits, misses, lengths)


def test_decay_rate_map_is_hits_over_lengths():
    m = decay_rate_map(_stats(), unknown_rate=0.3)
    # Eq. (7.10) by hand: 2/1.5, 0/2, unknown (R=0), 1/0.25, unknown, 0/0.5
    expected = np.array([[2 / 1.5, 0.0], [0.3, 4.0], [0.3, 0.0]])
    np.testing.assert_allclose(m.rates, expected, rtol=1e-14)
    assert float(m.outside_rate) == 0.3


def test_decay_rate_map_default_unknown_is_global_rate():
    m = decay_rate_map(_stats())
    glob = 3 / (1.5 + 2.0 + 0.25 + 0.5)
    np.testing.assert_allclose(float(m.outside_rate), glob, rtol=1e-14)
    np.testing.assert_allclose(m.rates[1, 0], glob, rtol=1e-14)
    # No traversal at all: unknown rate 0, no NaN.
    spec = GridSpec([0.0, 0.0], 1.0, (2, 2))
    z = jnp.zeros((2, 2), jnp.int32)
    empty = decay_rate_map(GridStats(spec, z, z, jnp.zeros((2, 2))))
    assert np.all(np.asarray(empty.rates) == 0) and float(empty.outside_rate) == 0


def test_decay_rate_map_gradient_nan_free():
    s = _stats()

    def f(lengths):
        return jnp.sum(decay_rate_map(GridStats(s.spec, s.hits, s.misses, lengths)).rates)

    g = jax.grad(f)(s.lengths)
    assert np.all(np.isfinite(np.asarray(g)))


def test_reflection_map_eq_7_22():
    m = reflection_map(_stats(), unknown_prob=0.25)
    expected = np.array([[2 / 3, 0.0], [0.25, 0.5], [0.25, 0.0]])
    np.testing.assert_allclose(m.probs, expected, rtol=1e-14)
    d = reflection_map(_stats())
    np.testing.assert_allclose(float(d.unknown_prob), 3 / 10, rtol=1e-14)


def test_maps_from_accumulate_match_hand_counts():
    # Two rays along a 1-cell-high corridor of 4 cells with resolution 1.
    spec = GridSpec([0.0, 0.0], 1.0, (4, 1))
    rays = RayBatch(
        origins=jnp.array([[0.5, 0.5], [0.0, 0.5]]),
        directions=jnp.array([[1.0, 0.0], [1.0, 0.0]]),
        ranges=jnp.array([2.25, 3.5]),
        kind=jnp.array([HIT, HIT]),
        r_min=jnp.array(0.0),
        r_max=jnp.array(10.0),
    )
    m = decay_rate_map(accumulate(spec, rays), unknown_rate=0.0)
    # Ray 1 covers x in [0.5, 2.75], ray 2 x in [0, 3.5]:
    # cell0 R = 0.5 + 1, cell1 R = 1 + 1, cell2 R = 0.75 + 1 (H 1), cell3 R = 0.5 (H 1).
    np.testing.assert_allclose(m.rates[:, 0], [0.0, 0.0, 1 / 1.75, 1 / 0.5], rtol=1e-12)


def _brute_distance(occ, res):
    idx = np.argwhere(occ)
    out = np.full(occ.shape, np.inf)
    for c in itertools.product(*[range(n) for n in occ.shape]):
        if len(idx):
            out[c] = np.sqrt(((idx - np.array(c)) ** 2).sum(1)).min() * res
    return out


@pytest.mark.parametrize("shape", [(7, 5), (4, 3, 5)])
def test_distance_transform_matches_brute_force(shape):
    rng = np.random.default_rng(1)
    occ = rng.random(shape) < 0.12
    occ.flat[3] = True
    d = distance_transform(occ, 0.3)
    np.testing.assert_allclose(d, _brute_distance(occ, 0.3), rtol=1e-12)
    assert np.all(np.isinf(np.asarray(distance_transform(np.zeros(shape, bool), 0.3))))


def test_endpoint_map_occupancy_threshold():
    s = _stats()
    em = endpoint_map(s, sigma_m=0.2)
    np.testing.assert_array_equal(em.occupied, np.asarray(s.hits) > 0)
    em2 = endpoint_map(s, sigma_m=0.2, occupied_threshold=0.6)  # only mu = 2/3 cell
    np.testing.assert_array_equal(em2.occupied, [[True, False], [False, False], [False, False]])
    np.testing.assert_allclose(
        em2.distances, _brute_distance(np.asarray(em2.occupied), 0.5), rtol=1e-12
    )
    f = em2.hit_field()
    np.testing.assert_allclose(
        f[2, 1],
        np.exp(-0.5 * (float(em2.distances[2, 1]) / 0.2) ** 2) / (np.sqrt(2 * np.pi) * 0.2),
    )


def test_bad_inputs_raise():
    s = _stats()
    with pytest.raises(ValueError, match="stats"):
        decay_rate_map(s.hits)
    with pytest.raises(ValueError, match="unknown_prob"):
        reflection_map(s, unknown_prob=1.5)
    with pytest.raises(ValueError, match="unknown_rate"):
        decay_rate_map(s, unknown_rate=-1.0)
    with pytest.raises(ValueError, match="sigma_m"):
        endpoint_map(s, sigma_m=0.0)
    with pytest.raises(ValueError, match="rates"):
        DecayRateMap(s.spec, jnp.zeros((2, 2)), jnp.array(0.0))
    with pytest.raises(ValueError, match="probs"):
        ReflectionMap(s.spec, jnp.zeros((3,)), jnp.array(0.0))
    assert issubclass(EndpointMap, object)
