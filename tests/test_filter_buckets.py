"""``ParticleFilter.run`` pads its steps to a bucket: one compilation per bucket, and the
results of the unpadded scan (``ParticleFilter._run``, the reference) for the same key."""

from __future__ import annotations

import contextlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lidarjax.localization import (
    OdometryMotionModel,
    ParticleFilter,
    global_injector,
    init_gaussian,
)
from lidarjax.localization._filter import step_bucket
from lidarjax.raytrace import GridSpec

BACKEND_COMPILE = "/jax/core/compile/backend_compile_duration"


class NoisyPosition(eqx.Module):
    """Measurement ``z = (x, y) + N(0, s^2 I)`` of each particle's position."""

    s: jax.Array

    def __call__(self, particles, z):
        d = particles.translation() - z
        return -0.5 * jnp.sum(d * d, axis=-1) / self.s**2


def _filter(**kw) -> ParticleFilter:
    return ParticleFilter(
        OdometryMotionModel([0.05, 0.05, 0.02]), NoisyPosition(jnp.asarray(0.1)), **kw
    )


def _data(T: int, seed: int = 0, dtype=np.float64):
    """``T`` forward controls and noisy position measurements (a kidnapping after 2/3)."""
    rng = np.random.default_rng(seed)
    controls = np.tile([0.2, 0.0, 0.05], (T, 1)) + rng.normal(0, 0.01, (T, 3))
    z = np.cumsum(controls[:, :2], axis=0) + rng.normal(0, 0.1, (T, 2))
    z[2 * T // 3 :] += 1.5
    updates = rng.random(T) > 0.2
    return controls.astype(dtype), z.astype(dtype), updates


def _state(n: int, key, dtype=jnp.float64):
    state = init_gaussian(n, [0.0, 0.0, 0.0], [0.15, 0.15, 0.05], key=key)
    return jax.tree.map(
        lambda x: x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x, state
    )


@contextlib.contextmanager
def count_compiles(name: str):
    """Count XLA compilations of the jitted function ``name`` (``jax.monitoring``: every
    backend compilation, including loads from the persistent cache, records an event)."""
    counts = {"n": 0}

    def listener(event, duration, **kw):
        if event == BACKEND_COMPILE and kw.get("fun_name") == f"jit({name})":
            counts["n"] += 1

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield counts
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def _leaves_equal(a, b) -> None:
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(la, lb, strict=True):
        if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
            x, y = jax.random.key_data(x), jax.random.key_data(y)
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape
        np.testing.assert_array_equal(x, y)


def _leaves_close(a, b, atol: float) -> None:
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
            x, y = jax.random.key_data(x), jax.random.key_data(y)
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape
        if np.issubdtype(x.dtype, np.floating):
            np.testing.assert_allclose(x, y, rtol=0, atol=atol)
        else:
            np.testing.assert_array_equal(x, y)


def test_step_bucket_rule():
    assert [step_bucket(t) for t in (0, 1, 7, 8, 9, 16, 17)] == [8, 8, 8, 8, 16, 16, 32]
    assert step_bucket(100) == step_bucket(120) == step_bucket(128) == 128
    assert step_bucket(129) == 256
    with pytest.raises(ValueError, match="n_steps"):
        step_bucket(-1)


def test_run_equals_unpadded_scan_float64(key):
    pf = _filter()
    T = 13  # padded to 16
    controls, z, updates = _data(T)
    state = _state(48, key)
    padded = pf.run(state, controls, z, updates)
    ref = pf._run(state, jnp.asarray(controls), jnp.asarray(z), jnp.asarray(updates))
    assert padded[1].n_eff.shape == (T,)
    _leaves_close(padded, ref, atol=1e-12)
    assert bool(jnp.any(ref[1].resampled))  # the comparison covers resampling steps
    # updates=None: every step updates, as before
    _leaves_close(
        pf.run(state, controls, z), pf._run(state, jnp.asarray(controls), jnp.asarray(z)), 1e-12
    )


def test_run_equals_unpadded_scan_float32_exactly():
    with jax.enable_x64(False):  # JAX's default dtypes: float32 everywhere
        pf = _filter()
        T = 11
        controls, z, updates = _data(T, seed=3, dtype=np.float32)
        state = _state(40, jax.random.key(1), jnp.float32)
        padded = pf.run(state, controls, z, updates)
        ref = pf._run(state, jnp.asarray(controls), jnp.asarray(z), jnp.asarray(updates))
        assert padded[0].log_weights.dtype == jnp.float32
        assert padded[1].estimate.parameters().dtype == jnp.float32
        _leaves_equal(padded, ref)
        assert bool(jnp.any(ref[1].resampled))


def test_run_with_kld_and_augmented_mcl_equals_unpadded_scan(key):
    spec = GridSpec(np.array([-2.0, -2.0]), 0.5, (12, 12))
    free = np.ones(spec.shape, bool)
    free[:3, :3] = False
    pf = _filter(
        resampler="stratified",
        alpha_slow=0.01,
        alpha_fast=0.3,
        injector=global_injector(spec, jnp.asarray(free)),
        kld=True,
        kld_bin_size=(0.1, 0.1, 0.2),
        n_min=20,
    )
    T = 10  # padded to 16
    controls, z, updates = _data(T, seed=1)
    state = _state(96, key)
    padded = pf.run(state, controls, z, updates)
    ref = pf._run(state, jnp.asarray(controls), jnp.asarray(z), jnp.asarray(updates))
    _leaves_close(padded, ref, atol=1e-12)
    # the features were active, so every state field went through the padded steps
    assert int(np.min(np.asarray(ref[1].n_active))) < 96
    assert int(ref[0].n_updates) == int(updates.sum())


def test_run_compiles_once_per_bucket(key):
    pf = _filter()
    state = _state(37, key)  # a particle count no other test of this module uses
    c120, z120, u120 = _data(120)
    with count_compiles("_run_padded") as first:
        a = pf.run(state, c120[:100], z120[:100], u120[:100])
    with count_compiles("_run_padded") as second:
        b = pf.run(state, c120, z120, u120)
    with count_compiles("_run_padded") as third:  # JAX-array inputs share the program
        pf.run(state, jnp.asarray(c120[:110]), jnp.asarray(z120[:110]))
    assert (first["n"], second["n"], third["n"]) == (1, 0, 0)
    assert a[1].n_eff.shape == (100,) and b[1].n_eff.shape == (120,)
    # the first 100 steps of the longer run are the shorter run
    _leaves_equal(jax.tree.map(lambda x: x[:100], b[1]), a[1])
    # the unpadded reference compiles per length
    with count_compiles("_run") as ref:
        pf._run(state, jnp.asarray(c120[:100]), jnp.asarray(z120[:100]), jnp.asarray(u120[:100]))
        pf._run(state, jnp.asarray(c120), jnp.asarray(z120), jnp.asarray(u120))
    assert ref["n"] == 2


def test_run_inside_jit_and_with_no_steps(key):
    pf = _filter()
    T = 6
    controls, z, updates = _data(T, seed=2)
    state = _state(48, key)
    eager = pf.run(state, controls, z, updates)
    traced = eqx.filter_jit(lambda p, s, c, zz, u: p.run(s, c, zz, u))(
        pf, state, jnp.asarray(controls), jnp.asarray(z), jnp.asarray(updates)
    )
    _leaves_close(traced, eager, atol=1e-12)
    final, infos = pf.run(state, controls[:0], z[:0], updates[:0])
    _leaves_equal(final, state)  # no step: the state comes back unchanged
    assert infos.n_eff.shape == (0,) and infos.estimate.parameters().shape == (0, 4)


def test_run_rejects_mismatched_step_axes(key):
    pf = _filter()
    controls, z, updates = _data(9)
    state = _state(8, key)
    with pytest.raises(ValueError, match="measurements must have a leading axis of 9"):
        pf.run(state, controls, z[:8])
    with pytest.raises(ValueError, match="updates must have a leading axis of 9"):
        pf.run(state, controls, z, updates[:5])
    with pytest.raises(ValueError, match="measurements must have a leading"):
        pf.run(state, controls, (z, np.float64(1.0)))
