"""Hostile inputs to the particle filter (issue #19, "Gradients and the filter"): NaN or
infinite controls, particles with log-likelihood +inf or NaN, states without particles.
Each flag of StepInfo must tell the truth, and n_eff must describe the weights the filter
actually keeps (checked against a NumPy computation from the returned log-weights)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lidarjax.localization import (
    OdometryMotionModel,
    ParticleFilter,
    ParticleState,
    effective_sample_size,
    estimate,
    global_injector,
    init_gaussian,
    init_global,
    init_uniform_disc,
    normalize_log_weights,
    to_vector,
)
from lidarjax.raytrace import GridSpec

N = 16


class PositionWithOverride(eqx.Module):
    """``log p(z | x) = -|x_xy - target|^2 / (2 s^2) + override_i``: ``z = (target [2],
    override [n])``; ``override`` injects +inf / NaN / -inf for chosen particles."""

    s: float = 0.1

    def __call__(self, particles, z):
        target, override = z
        d = particles.translation() - target
        return -0.5 * jnp.sum(d * d, axis=-1) / self.s**2 + override


SPEC = GridSpec(jnp.array([-2.0, -2.0]), 0.5, (8, 8))


def _filter(config: str, **kw) -> ParticleFilter:
    if config == "kld":
        kw.update(kld=True, n_min=4)
    elif config == "augmented":
        kw.update(
            alpha_slow=0.1,
            alpha_fast=0.5,
            injector=global_injector(SPEC, jnp.ones(SPEC.shape, bool)),
        )
    return ParticleFilter(OdometryMotionModel([0.05, 0.05, 0.01]), PositionWithOverride(), **kw)


def _state(seed: int = 0) -> ParticleState:
    return init_gaussian(N, [0.0, 0.0, 0.0], [0.3, 0.3, 0.05], key=jax.random.key(seed))


def _data(T: int):
    controls = np.tile([0.2, 0.0, 0.0], (T, 1))
    targets = 0.2 * np.arange(1, T + 1)[:, None] * np.array([1.0, 0.0])
    return controls, (jnp.asarray(targets), jnp.zeros((T, N)))


def _n_eff_numpy(log_weights) -> float:
    w = np.exp(np.asarray(log_weights, np.float64))
    return float(1.0 / np.sum(w * w))


# --------------------------------------------------------------------------------------
# NaN / infinite controls
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_concrete_bad_control_raises_naming_control(bad):
    pf, state = _filter("plain"), _state()
    controls, z = _data(4)
    with pytest.raises(ValueError, match="control"):
        pf.step(state, jnp.array([0.2, bad, 0.0]), jax.tree.map(lambda x: x[0], z))
    controls[2, 1] = bad
    with pytest.raises(ValueError, match=r"controls.*step 2"):
        pf.run(state, jnp.asarray(controls), z)


@pytest.mark.parametrize("config", ["plain", "kld", "augmented"])
@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_traced_bad_control_keeps_particles_and_flags_the_step(config):
    pf, state = _filter(config), _state(1)
    T = 6
    controls, z = _data(T)
    controls[2, 0] = np.nan
    controls[4, 2] = np.inf
    bad_steps = np.array([False, False, True, False, True, False])

    step = eqx.filter_jit(lambda s, c, zz: pf.step(s, c, zz))  # control traced
    s = state
    for t in range(T):
        zt = jax.tree.map(lambda x: x[t], z)
        new, info = step(s, jnp.asarray(controls[t]), zt)
        v = np.asarray(to_vector(new.particles))
        assert np.all(np.isfinite(v)), f"step {t}: non-finite particles"
        assert not np.any(np.isnan(np.asarray(new.log_weights)))
        assert bool(info.bad_control) == bad_steps[t]
        # n_eff describes the weights the step produced (before its resampling)
        if bad_steps[t]:
            np.testing.assert_array_equal(v, np.asarray(to_vector(s.particles)))
            np.testing.assert_array_equal(np.asarray(new.log_weights), np.asarray(s.log_weights))
            assert int(new.n_active) == int(s.n_active)
            assert not bool(info.resampled) and not bool(info.degenerate)
            assert int(info.injected) == 0
            np.testing.assert_allclose(float(info.n_eff), _n_eff_numpy(s.log_weights), rtol=1e-12)
            assert int(new.n_updates) == int(s.n_updates)
        else:
            assert not np.array_equal(v, np.asarray(to_vector(s.particles)))
        s = new

    # the same sequence through run (one lax.scan) inside jit: same flags, finite result
    final, infos = jax.jit(lambda st, c, zz: pf.run(st, c, zz))(state, jnp.asarray(controls), z)
    np.testing.assert_array_equal(np.asarray(infos.bad_control), bad_steps)
    assert np.all(np.isfinite(np.asarray(to_vector(final.particles))))
    assert np.all(np.isfinite(np.asarray(infos.n_eff)))
    np.testing.assert_allclose(
        np.asarray(to_vector(final.particles)), np.asarray(to_vector(s.particles)), atol=1e-12
    )


# --------------------------------------------------------------------------------------
# Likelihoods +inf and NaN
# --------------------------------------------------------------------------------------


def test_normalize_log_weights_infinite_entries_share_the_weight():
    lw = normalize_log_weights(jnp.array([0.0, jnp.inf, 3.0, -jnp.inf, jnp.inf]))
    np.testing.assert_allclose(np.exp(np.asarray(lw)), [0.0, 0.5, 0.0, 0.0, 0.5], atol=0)
    assert float(effective_sample_size(jnp.array([0.0, jnp.inf, 3.0, -jnp.inf, jnp.inf]))) == 2.0
    # NaN wins over +inf: uniform reset, never NaN
    lw = normalize_log_weights(jnp.array([jnp.inf, jnp.nan, 0.0, 1.0]))
    np.testing.assert_allclose(np.asarray(lw), np.full(4, -np.log(4.0)))


@pytest.mark.parametrize("config", ["plain", "kld"])
def test_infinite_likelihood_particles_share_the_weight_and_are_flagged(config):
    pf = _filter(config, resample_fraction=0.0)  # never resample: weights observable
    state = _state(2)
    override = jnp.zeros(N).at[3].set(jnp.inf).at[11].set(jnp.inf)
    z = (jnp.array([0.2, 0.0]), override)
    new, info = eqx.filter_jit(lambda s, c, zz: pf.step(s, c, zz))(
        state, jnp.array([0.2, 0.0, 0.0]), z
    )
    w = np.exp(np.asarray(new.log_weights))
    expected = np.zeros(N)
    expected[[3, 11]] = 0.5
    np.testing.assert_allclose(w, expected, atol=0)
    assert bool(info.infinite_likelihood) and not bool(info.degenerate)
    assert float(info.n_eff) == 2.0 == _n_eff_numpy(new.log_weights)
    # the estimate is the (circular) mean of the two particles that carry the weight
    v = np.asarray(to_vector(new.particles))
    np.testing.assert_allclose(
        np.asarray(to_vector(info.estimate))[:2], v[[3, 11], :2].mean(axis=0), atol=1e-12
    )


def test_infinite_likelihood_resampling_draws_only_those_particles():
    pf, state = _filter("plain"), _state(3)  # n_eff = 2 < 0.5 n: resamples
    override = jnp.zeros(N).at[5].set(jnp.inf).at[9].set(jnp.inf)
    new, info = pf.step(state, jnp.array([0.2, 0.0, 0.0]), (jnp.array([0.2, 0.0]), override))
    assert bool(info.resampled) and bool(info.infinite_likelihood)
    assert float(info.n_eff) == 2.0
    # the moved particles 5 and 9 are the only ancestors
    moved, _ = pf.step(
        state,
        jnp.array([0.2, 0.0, 0.0]),
        (jnp.array([0.2, 0.0]), override),
        update=False,
    )
    src = np.asarray(to_vector(moved.particles))[[5, 9]]
    out = np.asarray(to_vector(new.particles))
    dist = np.min(np.abs(out[:, None, :] - src[None, :, :]).sum(-1), axis=1)
    np.testing.assert_array_equal(dist, np.zeros(N))
    np.testing.assert_allclose(np.exp(np.asarray(new.log_weights)), np.full(N, 1.0 / N))


@pytest.mark.parametrize("config", ["plain", "kld"])
def test_nan_likelihood_is_degenerate_with_uniform_finite_weights(config):
    pf = _filter(config, resample_fraction=0.0)
    state = _state(4)
    override = jnp.zeros(N).at[7].set(jnp.nan).at[2].set(jnp.inf)
    new, info = pf.step(state, jnp.array([0.2, 0.0, 0.0]), (jnp.array([0.2, 0.0]), override))
    lw = np.asarray(new.log_weights)
    assert not np.any(np.isnan(lw))
    assert bool(info.degenerate) and not bool(info.infinite_likelihood)
    np.testing.assert_allclose(np.exp(lw), np.full(N, 1.0 / N))
    np.testing.assert_allclose(float(info.n_eff), _n_eff_numpy(lw), rtol=1e-12)
    assert float(info.n_eff) == pytest.approx(N)


# --------------------------------------------------------------------------------------
# States without particles
# --------------------------------------------------------------------------------------


def test_zero_particle_states_raise_naming_the_argument():
    state = _state()
    with pytest.raises(ValueError, match="log_weights"):
        ParticleState(jax.tree.map(lambda x: x[:0], state.particles), jnp.zeros(0), state.key)
    with pytest.raises(ValueError, match="log_weights"):
        normalize_log_weights(jnp.zeros(0))
    with pytest.raises(ValueError, match="log_weights"):
        effective_sample_size(jnp.zeros(0))
    empty = jax.tree.map(lambda x: x[:0] if getattr(x, "ndim", 0) else x, state)
    assert empty.log_weights.shape == (0,)
    pf = _filter("plain")
    controls, z = _data(3)
    with pytest.raises(ValueError, match="state"):
        pf.step(empty, jnp.asarray(controls[0]), jax.tree.map(lambda x: x[0], z))
    with pytest.raises(ValueError, match="state"):
        pf.run(empty, jnp.asarray(controls), z)
    with pytest.raises(ValueError, match="state"):
        estimate(empty)
    key = jax.random.key(0)
    with pytest.raises(ValueError, match="n must be"):
        init_gaussian(0, [0.0, 0.0, 0.0], [0.1, 0.1, 0.1], key=key)
    with pytest.raises(ValueError, match="n must be"):
        init_uniform_disc(0, [0.0, 0.0], 1.0, (0.0, 0.1), key=key)
    with pytest.raises(ValueError, match="n must be"):
        init_global(0, SPEC, jnp.ones(SPEC.shape, bool), key=key)
