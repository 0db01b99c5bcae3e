"""Tests for the adaptive particle-filter extensions in lidarjax.localization: augmented
MCL (random-particle injection), KLD-sampling (adaptive particle count) and the proposal
hook of ParticleFilter.step.

float64 comes from tests/conftest.py (``jax_enable_x64``), as in test_localization.py.
Statistical checks use tolerances of ``Z`` standard errors with fixed keys, so they are
deterministic and fail only if the tested quantity is wrong."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from scipy.stats import chi2, norm

from lidarjax.localization import (
    OdometryMotionModel,
    ParticleFilter,
    ParticleState,
    count_occupied_bins,
    estimate,
    from_vector,
    global_injector,
    init_gaussian,
    kld_particle_count,
    multinomial_resample,
    normalize_log_weights,
    stratified_resample,
    systematic_resample,
    to_vector,
)
from lidarjax.raytrace import GridSpec

Z = 6.0  # standard errors allowed in statistical checks
SIG_Q, SIG_Z, SIG_0 = 0.05, 0.2, 0.5  # motion, measurement and prior std (m)


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


class GaussianPosition(eqx.Module):
    """Measurement z = (x, y) + N(0, s^2 I), log-likelihood shifted by ``-offset`` nats."""

    s: jax.Array
    offset: float = eqx.field(static=True, default=0.0)

    def __call__(self, particles, z):
        d = particles.translation() - z
        return -0.5 * jnp.sum(d * d, axis=-1) / self.s**2 - self.offset


class BoxInjector(eqx.Module):
    """``n`` SE(2) poses uniform in the box ``[lo, hi]`` with heading 0."""

    lo: jax.Array
    hi: jax.Array

    def __call__(self, key, n):
        u = jax.random.uniform(key, (n, 2), dtype=self.lo.dtype)
        xy = self.lo + u * (self.hi - self.lo)
        return from_vector(jnp.concatenate([xy, jnp.zeros((n, 1), xy.dtype)], axis=-1))


class MarkerInjector(eqx.Module):
    """Every injected pose is the marker pose ``v``."""

    v: jax.Array

    def __call__(self, key, n):
        return from_vector(jnp.broadcast_to(self.v, (n, 3)))


# jitted steps shared by the tests (one compile per filter configuration)
_STEP = eqx.filter_jit(lambda pf, s, c, z: pf.step(s, c, z))
_STEP_U = eqx.filter_jit(lambda pf, s, c, z, u: pf.step(s, c, z, u))


def _box():
    return BoxInjector(jnp.asarray([-1.0, -1.0]), jnp.asarray([6.0, 6.0]))


def _kalman(controls, z, s0=SIG_0, sq=SIG_Q, sz=SIG_Z):
    """Exact posterior mean / variance per axis (heading fixed at 0: linear Gaussian)."""
    m, p = np.zeros(2), s0**2
    means, variances = [], []
    for t in range(len(z)):
        m, p = m + np.asarray(controls[t, :2]), p + sq**2
        k = p / (p + sz**2)
        m, p = m + k * (np.asarray(z[t]) - m), (1 - k) * p
        means.append(m)
        variances.append(p)
    return np.array(means), np.array(variances)


def _toy_data(T, seed=0, s0=SIG_0, sq=SIG_Q, sz=SIG_Z):
    rng = np.random.default_rng(seed)
    controls = np.tile([0.2, 0.0, 0.0], (T, 1))
    truth = np.zeros((T, 2))
    x = rng.normal(0.0, s0, 2)
    for t in range(T):
        x = x + controls[t, :2] + rng.normal(0.0, sq, 2)
        truth[t] = x
    z = truth + rng.normal(0.0, sz, (T, 2))
    return jnp.asarray(controls), jnp.asarray(z), truth


# --------------------------------------------------------------------------------------
# KLD particle count and occupied bins
# --------------------------------------------------------------------------------------


def _wilson_hilferty(k, eps, delta):
    k = np.asarray(k, np.float64)
    z = norm.ppf(1 - delta)
    km1 = np.maximum(k - 1, 1)
    a = 2 / (9 * km1)
    n = km1 / (2 * eps) * (1 - a + np.sqrt(a) * z) ** 3
    return np.where(k <= 1, 1, np.maximum(np.ceil(n), 1)).astype(int)


def test_kld_particle_count_vs_chi_square():
    # tabulated chi-square quantiles chi2_{0.99}(dof) (the reference itself)
    for dof, q in ((10, 23.209), (50, 76.154), (100, 135.807)):
        assert abs(chi2.ppf(0.99, dof) - q) < 1e-3
    k = np.array([10, 11, 20, 51, 101, 300, 1000, 5000])
    for eps, delta in ((0.05, 0.01), (0.01, 0.01), (0.02, 0.05), (0.1, 0.2)):
        got = np.asarray(kld_particle_count(jnp.asarray(k), eps, delta))
        assert got.dtype == np.int32 and got.shape == k.shape
        np.testing.assert_array_equal(got, _wilson_hilferty(k, eps, delta))
        exact = chi2.ppf(1 - delta, k - 1) / (2 * eps)
        # Wilson-Hilferty is within 1 % for k >= 10; ceil adds at most one particle
        np.testing.assert_array_less(np.abs(got - exact), 0.01 * exact + 1.0)
    # the tabulated values directly: k - 1 = 10, 50, 100 degrees of freedom
    got = np.asarray(kld_particle_count(jnp.asarray([11, 51, 101]), 0.01, 0.01))
    np.testing.assert_array_less(
        np.abs(got - np.array([23.209, 76.154, 135.807]) / 0.02), 0.01 * got
    )
    # k <= 1 needs one particle; small k still follows the closed form; monotone in k
    np.testing.assert_array_equal(np.asarray(kld_particle_count(jnp.asarray([0, 1]))), [1, 1])
    ks = np.arange(0, 400)
    n = np.asarray(kld_particle_count(jnp.asarray(ks), 0.05, 0.01))
    np.testing.assert_array_equal(n, _wilson_hilferty(ks, 0.05, 0.01))
    assert np.all(np.diff(n) >= 0)
    # jit with a traced k
    out = jax.jit(lambda kk: kld_particle_count(kk, 0.05, 0.01))(jnp.asarray(51))
    assert int(out) == int(_wilson_hilferty(51, 0.05, 0.01))


def _brute_bins(v, active, bin_size, angle_dims):
    v = np.array(v, np.float64)
    v[:, angle_dims] = _wrap(v[:, angle_dims])
    b = np.floor(v * (1 / np.asarray(bin_size)))  # the documented bin rule
    return len({tuple(row) for row in b[np.asarray(active)]})


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_count_occupied_bins_vs_brute_force():
    rng = np.random.default_rng(0)
    count = jax.jit(count_occupied_bins, static_argnums=2)
    bs2 = (0.5, 0.5, math.radians(30))
    for trial in range(8):
        n = 300
        v = np.column_stack([rng.normal(size=(n, 2)) * 1.5, rng.uniform(-4, 4, n)])
        # headings right at and across +-pi: -pi, pi and pi - tiny share one bin class
        v[:20, 2] = rng.choice([np.pi, -np.pi, np.pi - 1e-9, -np.pi + 1e-9, 3.3, -3.3], 20)
        active = rng.uniform(size=n) < rng.uniform(0.2, 1.0)
        ref = _brute_bins(v, active, bs2, [2])
        assert int(count(jnp.asarray(v), jnp.asarray(active), bs2)) == ref
        # jaxlie poses give the same count (to_vector returns angles in (-pi, pi])
        poses = from_vector(jnp.asarray(v))
        assert int(count_occupied_bins(poses, jnp.asarray(active), bs2)) == ref
        if trial == 0:  # all active (None) and no active particle
            assert int(count_occupied_bins(jnp.asarray(v), None, bs2)) == _brute_bins(
                v, np.ones(n, bool), bs2, [2]
            )
            assert int(count_occupied_bins(jnp.asarray(v), jnp.zeros(n, bool), bs2)) == 0
    # pi and -pi are the same angle: one bin
    v = np.array([[0.1, 0.1, np.pi], [0.1, 0.1, -np.pi]])
    assert int(count_occupied_bins(jnp.asarray(v), None, bs2)) == 1
    # SE(3) pose vectors, coarse bins so that duplicates occur
    bs3 = (1.0, 1.0, 1.0, 0.5, 0.5, 1.0)
    v3 = np.column_stack(
        [
            rng.normal(size=(400, 3)) * 0.3,
            rng.uniform(-0.3, 0.3, (400, 2)),
            rng.uniform(-np.pi, np.pi, 400),
        ]
    )
    v3[:10, 5] = np.pi
    v3[10:20, 5] = -np.pi
    active = rng.uniform(size=400) < 0.6
    ref = _brute_bins(v3, active, bs3, [3, 4, 5])
    assert 1 < ref < active.sum()
    assert int(count_occupied_bins(jnp.asarray(v3), jnp.asarray(active), bs3)) == ref
    # vmap over masks
    masks = rng.uniform(size=(4, 300)) < 0.5
    vv = np.column_stack([rng.normal(size=(300, 2)), rng.uniform(-np.pi, np.pi, 300)])
    got = jax.vmap(lambda m: count_occupied_bins(jnp.asarray(vv), m, bs2))(jnp.asarray(masks))
    np.testing.assert_array_equal(np.asarray(got), [_brute_bins(vv, m, bs2, [2]) for m in masks])


# --------------------------------------------------------------------------------------
# Resampling exactly n_active ancestors
# --------------------------------------------------------------------------------------

WEIGHTS = np.array([0.31, 0.0, 0.07, 0.22, 0.0, 0.013, 0.187, 0.2])  # n = 8, sums to 1
RESAMPLER_FNS = {
    "systematic": systematic_resample,
    "stratified": stratified_resample,
    "multinomial": multinomial_resample,
}


@pytest.mark.parametrize("name", list(RESAMPLER_FNS))
def test_resample_n_active_unbiased(name, key):
    """With ``n_active = m`` the first m slots hold m draws with E[offspring_i] = m w_i
    (drawing n and truncating to the first m would over-represent low indices: the
    output is ordered by ancestor); the remaining slots copy slot ``i mod m``."""
    fn = RESAMPLER_FNS[name]
    w = WEIGHTS
    n, runs = w.size, 4000
    with np.errstate(divide="ignore"):
        lw = jnp.asarray(np.log(w))
    for m in (1, 3, 5, 8):
        keys = jax.random.split(jax.random.fold_in(key, m), runs)
        idx = np.asarray(jax.vmap(lambda k: fn(lw, key=k, n_active=jnp.asarray(m)))(keys))
        assert idx.shape == (runs, n) and idx.min() >= 0 and idx.max() < n
        counts = np.stack([np.bincount(row[:m], minlength=n) for row in idx])
        assert np.all(counts.sum(axis=1) == m)
        assert np.all(counts[:, w == 0] == 0)  # zero-weight particles never chosen
        se = np.sqrt(m * w * (1 - w) / runs)
        np.testing.assert_array_less(np.abs(counts.mean(axis=0) - m * w), Z * se + 1e-12)
        filler = np.arange(n) % m
        np.testing.assert_array_equal(idx[:, m:], idx[:, filler[m:]])
        if name == "systematic":  # counts are floor(m w_i) or ceil(m w_i)
            mw = m * w
            assert np.all((counts >= np.floor(mw - 1e-12)) & (counts <= np.ceil(mw + 1e-12)))
    # n_active = None keeps the original n-draw behaviour bit for bit; n_active >= n too
    k0 = jax.random.key(3)
    np.testing.assert_array_equal(
        np.asarray(fn(lw, key=k0)), np.asarray(fn(lw, key=k0, n_active=n + 5))
    )


# --------------------------------------------------------------------------------------
# ParticleState defaults and estimate with inactive slots
# --------------------------------------------------------------------------------------


def test_state_defaults_and_estimate_ignores_inactive(key):
    state = init_gaussian(8, [0.0, 0.0, 0.0], [1.0, 1.0, 0.5], key=key)
    assert int(state.n_active) == 8 and int(state.n_updates) == 0
    assert float(state.log_w_slow) == -np.inf and float(state.log_w_fast) == -np.inf
    assert state.log_w_slow.dtype == state.log_weights.dtype
    # 3-argument construction keeps working and has the same pytree structure
    s3 = ParticleState(state.particles, state.log_weights, state.key)
    assert jax.tree.structure(s3) == jax.tree.structure(state)
    # 5 live particles; the 3 inactive ones sit far away and have weight 0
    rng = np.random.default_rng(1)
    v = np.column_stack([rng.normal(size=(8, 2)), rng.uniform(-3, 3, 8)])
    v[5:, :2] = 1000.0
    lw = np.full(8, -np.inf)
    lw[:5] = np.asarray(normalize_log_weights(jnp.asarray(rng.normal(size=5))))
    s = ParticleState(from_vector(jnp.asarray(v)), jnp.asarray(lw), key, n_active=5)
    for frac, k in ((1.0, 5), (0.5, 3), (0.1, 1)):
        top = np.argsort(-lw[:5])[:k]
        w = np.exp(lw[top] - lw[top].max())
        w /= w.sum()
        est = estimate(s, frac)
        np.testing.assert_allclose(np.asarray(est.translation()), w @ v[top, :2], atol=1e-12)
        th = np.arctan2(w @ np.sin(v[top, 2]), w @ np.cos(v[top, 2]))
        np.testing.assert_allclose(_wrap(float(est.rotation().as_radians()) - th), 0, atol=1e-12)


# --------------------------------------------------------------------------------------
# KLD-sampling in the filter
# --------------------------------------------------------------------------------------


def _kld_filter(**kw):
    return ParticleFilter(
        OdometryMotionModel([SIG_Q, SIG_Q, 0.0]),
        GaussianPosition(jnp.asarray(SIG_Z)),
        best_fraction=1.0,
        kld=True,
        kld_bin_size=(0.1, 0.1, 1.0),
        **kw,
    )


def test_kld_count_follows_fox_rule(key):
    """Particles spread over exactly K bins with equal total weight per bin: the first
    few hundred iid candidates hit all K bins, so Fox's rule stops at
    ``kld_particle_count(K)`` (or ``n_min`` for K = 1). Inactive slots get weight -inf,
    a degenerate update stays uniform over the live slots only."""
    n = 2000
    for n_bins in (1, 7, 20):
        rng = np.random.default_rng(n_bins)
        centre = 0.05 + 0.1 * (np.arange(n) % n_bins)  # bin centres along x (bin 0.1 m)
        v = np.column_stack([centre + rng.uniform(-0.02, 0.02, n), np.full(n, 0.05), 0 * centre])
        # a flat measurement (huge std): the weights stay the uneven prior weights, whose
        # total per bin is ~1/K; resample_fraction 0.99 forces a resampling now
        pf = ParticleFilter(
            OdometryMotionModel([0.0, 0.0, 0.0]),
            GaussianPosition(jnp.asarray(1e6)),
            resample_fraction=0.99,
            kld=True,
            kld_bin_size=(0.1, 0.1, 1.0),
            n_min=25,
        )
        lw = np.log(rng.uniform(0.5, 1.5, n))
        lw = np.asarray(normalize_log_weights(jnp.asarray(lw)))
        s = ParticleState(from_vector(jnp.asarray(v)), jnp.asarray(lw), key)
        z = jnp.asarray([0.0, 0.05])
        new, info = _STEP(pf, s, jnp.zeros(3), z)
        assert bool(info.resampled)
        expect = 25 if n_bins == 1 else int(kld_particle_count(n_bins, 0.05, 0.01))
        assert int(info.n_active) == int(new.n_active) == expect
        m = expect
        lw_new = np.asarray(new.log_weights)
        np.testing.assert_allclose(lw_new[:m], -np.log(m), rtol=1e-12)
        assert np.all(lw_new[m:] == -np.inf)
        # live particles cover all K bins
        vn = np.asarray(to_vector(new.particles))[:m]
        assert len(set(np.floor(vn[:, 0] / 0.1).astype(int))) == n_bins
        # degenerate update (likelihood 0 everywhere): uniform over the live slots only
        pf0 = eqx.tree_at(lambda p: p.measurement.s, pf, jnp.asarray(0.0))
        deg, info0 = _STEP(pf0, new, jnp.zeros(3), z)
        assert bool(info0.degenerate) and not bool(info0.resampled)
        lw0 = np.asarray(deg.log_weights)
        np.testing.assert_allclose(lw0[:m], -np.log(m), rtol=1e-12)
        assert np.all(lw0[m:] == -np.inf) and int(deg.n_active) == m


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_kld_filter_shrinks_and_tracks_kalman(key):
    """Prior std 0.5 m, measurement std 0.2 m, bins 0.1 m: the live count drops as the
    posterior concentrates, and the weighted mean matches the Kalman posterior mean
    (single runs within Monte-Carlo error, the mean over runs without bias)."""
    n, T, runs = 2000, 12, 12
    controls, z, _ = _toy_data(T, seed=0)
    pf = _kld_filter()
    keys = jax.random.split(key, runs)
    states = jax.vmap(lambda k: init_gaussian(n, [0.0, 0.0, 0.0], [SIG_0, SIG_0, 0.0], key=k))(keys)
    finals, infos = jax.vmap(lambda s: pf.run(s, controls, z))(states)
    n_active = np.asarray(infos.n_active)  # [runs T]
    resampled = np.asarray(infos.resampled)
    assert resampled[:, 0].all()  # the first update already needs resampling
    first = n_active[:, 0]
    assert np.all(first < n) and np.all(n_active[:, -1] < 0.5 * first)
    assert np.all(n_active >= 10) and np.all(n_active <= n)
    # live count only changes at resampling
    same = n_active[:, 1:] == n_active[:, :-1]
    assert np.all(same | resampled[:, 1:])
    # final states: weights -inf beyond n_active, normalised over the live ones
    lw = np.asarray(finals.log_weights)
    for r in range(runs):
        m = int(finals.n_active[r])
        assert np.all(lw[r, m:] == -np.inf) and np.all(np.isfinite(lw[r, :m]))
        np.testing.assert_allclose(np.exp(lw[r]).sum(), 1.0, rtol=1e-12)
    kf_mean, kf_var = _kalman(controls, z)
    est = np.asarray(infos.estimate.translation())  # [runs T 2]
    err = est - kf_mean
    n_eff = np.minimum.accumulate(np.asarray(infos.n_eff), axis=1)[..., None]
    mc = 2.0 * np.sqrt(kf_var)[None, :, None] / np.sqrt(n_eff)
    np.testing.assert_array_less(np.abs(err), Z * np.broadcast_to(mc, err.shape))
    # no bias: the mean error over independent runs is within its standard error
    se = err.std(axis=0, ddof=1) / np.sqrt(runs)
    np.testing.assert_array_less(np.abs(err.mean(axis=0)), Z * se)


# --------------------------------------------------------------------------------------
# Augmented MCL
# --------------------------------------------------------------------------------------


def _aug_filter(injector, a_slow=0.01, a_fast=0.3, motion_sigma=SIG_Q, offset=0.0, **kw):
    return ParticleFilter(
        OdometryMotionModel([motion_sigma, motion_sigma, 0.0]),
        GaussianPosition(jnp.asarray(SIG_Z), offset),
        best_fraction=1.0,
        alpha_slow=a_slow,
        alpha_fast=a_fast,
        injector=injector,
        **kw,
    )


def _loop(pf, state, z):
    """Python loop of jitted steps (zero controls); returns the states and infos."""
    states, infos = [], []
    for t in range(z.shape[0]):
        state, info = _STEP(pf, state, jnp.zeros(3), jnp.asarray(z[t]))
        states.append(state)
        infos.append(info)
    return states, jax.tree.map(lambda *x: np.stack([np.asarray(a) for a in x]), *infos)


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_augmented_injects_after_kidnapping(key):
    """The robot sits at the origin; from step 15 the measurement says (4, 4): w_fast
    drops below w_slow, particles are injected (Binomial(n, p) many) and the filter
    recovers. With consistent measurements injection stays ~0, and without augmented MCL
    the filter never recovers."""
    n, T, t_k = 500, 30, 15
    z_kid = np.zeros((T, 2))
    z_kid[t_k:] = [4.0, 4.0]
    state = init_gaussian(n, [0.0, 0.0, 0.0], [0.1, 0.1, 0.0], key=key)
    pf = _aug_filter(_box())
    states, info = _loop(pf, state, z_kid)
    inj = info.injected
    assert inj[:t_k].sum() == 0
    assert inj[t_k] > 0.05 * n and inj[t_k:].sum() > n
    np.testing.assert_allclose(info.estimate.unit_complex_xy[-5:, 2:], 4.0, atol=0.1)
    # w_fast < w_slow right after the kidnapping, not before
    before, after = states[t_k - 1], states[t_k]
    assert float(before.log_w_fast) >= float(before.log_w_slow) - 0.1
    assert float(after.log_w_fast) < float(after.log_w_slow)
    # the injected count is Binomial(n, p) with p = 1 - w_fast / w_slow
    p = 1 - np.exp(float(after.log_w_fast) - float(after.log_w_slow))
    assert abs(inj[t_k] - n * p) < Z * np.sqrt(n * p * (1 - p))
    # steady state with consistent measurements: (almost) no injection
    _, info_ok = _loop(pf, state, np.zeros((T, 2)))
    assert info_ok.injected.sum() <= 0.005 * n * T
    # the same kidnapping without augmented MCL does not recover
    plain = ParticleFilter(pf.motion, pf.measurement, best_fraction=1.0)
    _, info_plain = _loop(plain, state, z_kid)
    assert np.all(info_plain.injected == 0)
    xy = info_plain.estimate.unit_complex_xy[-5:, 2:]
    assert np.all(np.linalg.norm(xy - 4.0, axis=1) > 1)


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_augmented_log_averages_vs_linear_reference(key):
    """The log-space averages equal a float64 linear-space reference: the normalised
    exponential means ``sum_k a (1-a)^(t-k) w_k / sum_k a (1-a)^(t-k)`` of the weighted
    mean likelihoods ``w_k`` of the update steps. With a log-likelihood offset of -1000
    nats (linear space underflows to 0) the log averages shift by exactly -1000."""
    a_s, a_f = 0.1, 0.5
    n, T = 64, 9
    rng = np.random.default_rng(5)
    z = jnp.asarray(rng.normal(size=(T, 2)) * 0.3)
    updates = [True, True, False, True, True, True, False, True, True]
    state0 = init_gaussian(n, [0.0, 0.0, 0.0], [0.3, 0.3, 0.0], key=key)
    traces = {}
    for offset in (0.0, 1000.0):
        pf = _aug_filter(_box(), a_s, a_f, motion_sigma=0.0, offset=offset)
        step = eqx.filter_jit(pf.step)
        s, w_avg, got, injected = state0, [], [], 0
        for t in range(T):
            if updates[t]:  # zero motion noise and control: the particles do not move
                xy = np.asarray(s.particles.translation())
                ll = -0.5 * np.sum((xy - np.asarray(z[t])) ** 2, axis=1) / SIG_Z**2
                w_avg.append(np.sum(np.exp(np.asarray(s.log_weights)) * np.exp(ll)))
            s, info = step(s, jnp.zeros(3), z[t], jnp.asarray(updates[t]))
            injected += int(info.injected)
            got.append((float(s.log_w_slow), float(s.log_w_fast), int(s.n_updates)))
        traces[offset] = np.array(got)
        if offset == 0.0:
            assert injected > 0  # the sequence exercises resampling with injection
            w = np.array(w_avg)
            j = 0
            for t in range(T):
                j += updates[t]
                assert traces[0.0][t, 2] == j
                for col, a in ((0, a_s), (1, a_f)):
                    c = a * (1 - a) ** np.arange(j - 1, -1, -1)
                    ref = np.sum(c * w[:j]) / np.sum(c)
                    np.testing.assert_allclose(traces[0.0][t, col], np.log(ref), rtol=1e-12)
    assert np.exp(-1000.0) == 0.0  # linear space would underflow
    np.testing.assert_allclose(traces[1000.0][:, :2], traces[0.0][:, :2] - 1000.0, rtol=1e-12)
    np.testing.assert_array_equal(traces[1000.0][:, 2], traces[0.0][:, 2])


@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_injected_particles_come_from_the_injector(key):
    """An injector that puts every pose at a marker: right after the first injection
    exactly ``info.injected`` particles sit at the marker, the others are resampled
    copies of the previous particles."""
    n, marker = 200, np.array([7.0, -3.0, 1.234])
    pf = _aug_filter(MarkerInjector(jnp.asarray(marker)), motion_sigma=0.0)
    s = init_gaussian(n, [0.0, 0.0, 0.0], [0.1, 0.1, 0.0], key=key)
    step = eqx.filter_jit(pf.step)
    for t in range(12):
        z = jnp.zeros(2) if t < 5 else jnp.asarray([2.0, 2.0])
        prev = np.asarray(to_vector(s.particles))
        s, info = step(s, jnp.zeros(3), z)
        k = int(info.injected)
        v = np.asarray(to_vector(s.particles))
        at_marker = np.all(np.abs(v - marker) < 1e-9, axis=1)
        if t < 5:
            assert k == 0 and not at_marker.any()
        if k > 0:
            assert at_marker.sum() == k
            d = np.abs(v[~at_marker, None, :] - prev[None, :, :]).max(axis=-1)
            assert np.all(d.min(axis=1) < 1e-9)  # each one is a copy of a previous particle
            break
    else:
        pytest.fail("no injection after the measurement jumped")


def test_global_injector(key):
    spec = GridSpec(np.array([-1.0, 2.0]), 0.5, (6, 5))
    free = np.random.default_rng(10).uniform(size=spec.shape) < 0.4
    inj = global_injector(spec, jnp.asarray(free))
    v = np.asarray(to_vector(eqx.filter_jit(lambda f, k: f(k, 6000))(inj, key)))
    cell = np.floor((v[:, :2] - [-1.0, 2.0]) / 0.5).astype(int)
    assert np.all(free[cell[:, 0], cell[:, 1]])
    k = int(free.sum())
    counts = np.zeros(spec.shape)
    np.add.at(counts, (cell[:, 0], cell[:, 1]), 1)
    p = 1.0 / k
    np.testing.assert_array_less(np.abs(counts[free] - 6000 * p), Z * np.sqrt(6000 * p * (1 - p)))
    assert abs(v[:, 2].mean()) < Z * (2 * np.pi) / np.sqrt(12 * 6000)
    with pytest.raises(ValueError, match="free"):
        global_injector(spec, jnp.zeros(spec.shape, bool))
    with pytest.raises(ValueError, match="free"):
        global_injector(spec, jnp.ones((5, 6), bool))


# --------------------------------------------------------------------------------------
# The proposal hook
# --------------------------------------------------------------------------------------


class FixedProposal(eqx.Module):
    """``propose`` returns known particles and corrections; ``__call__`` (used on steps
    without a measurement update) shifts every particle by the control."""

    target: jax.Array  # [n 3] pose vectors
    correction: jax.Array  # [n]

    def __call__(self, particles, control, *, key):
        n = particles.parameters().shape[0]
        return particles @ from_vector(jnp.broadcast_to(control, (n, 3)))

    def propose(self, particles, control, z, *, key):
        return from_vector(self.target), self.correction


def test_proposal_hook_uses_propose_and_adds_correction(key):
    n = 16
    rng = np.random.default_rng(7)
    target = np.column_stack([rng.normal(size=(n, 2)), rng.uniform(-3, 3, n)])
    meas = GaussianPosition(jnp.asarray(0.5))
    z = jnp.asarray([0.3, -0.2])
    ll = np.asarray(meas(from_vector(jnp.asarray(target)), z))
    lw = normalize_log_weights(jnp.asarray(rng.normal(size=n)))
    s = ParticleState(from_vector(jnp.asarray(rng.normal(size=(n, 3)))), lw, key)
    control = jnp.asarray([0.5, 0.0, 0.1])
    # a correction that cancels the measurement exactly: the weights do not change
    pf = ParticleFilter(FixedProposal(jnp.asarray(target), -jnp.asarray(ll)), meas, 0.0)
    new, info = _STEP_U(pf, s, control, z, jnp.asarray(True))
    np.testing.assert_allclose(np.asarray(to_vector(new.particles)), target, atol=1e-12)
    np.testing.assert_allclose(np.asarray(new.log_weights), np.asarray(lw), atol=1e-12)
    # an arbitrary correction is added to the log-likelihood before normalising
    c = rng.normal(size=n) * 2
    pf = ParticleFilter(FixedProposal(jnp.asarray(target), jnp.asarray(c)), meas, 0.0)
    new, info = _STEP_U(pf, s, control, z, jnp.asarray(True))
    ref = np.asarray(lw) + ll + c
    ref = ref - np.log(np.sum(np.exp(ref - ref.max()))) - ref.max()
    np.testing.assert_allclose(np.asarray(new.log_weights), ref, atol=1e-12)
    assert not bool(info.resampled)
    # no update: the plain motion model, weights unchanged
    off, _ = _STEP_U(pf, s, control, z, jnp.asarray(False))
    moved = s.particles @ from_vector(jnp.broadcast_to(control, (n, 3)))
    np.testing.assert_allclose(
        np.asarray(off.particles.parameters()), np.asarray(moved.parameters()), atol=1e-12
    )
    np.testing.assert_allclose(np.asarray(off.log_weights), np.asarray(lw), atol=1e-13)
    # inside run (lax.scan) with mixed updates, and with a traced update flag under jit
    T = 4
    final, infos = pf.run(
        s, jnp.tile(control, (T, 1)), jnp.tile(z, (T, 1)), jnp.asarray([False, True, False, True])
    )
    assert np.all(np.isfinite(np.asarray(final.log_weights)))
    np.testing.assert_allclose(
        np.asarray(to_vector(infos.estimate))[1],
        np.asarray(to_vector(estimate(new, pf.best_fraction))),
        atol=1e-12,
    )


class WideProposal(eqx.Module):
    """Samples the odometry noise from a ``scale`` times wider Gaussian than the motion
    model and (if ``corrected``) returns the importance correction
    ``log N(d; 0, s^2) - log N(d; 0, (scale s)^2)`` per pose-vector component."""

    base: OdometryMotionModel
    scale: float = eqx.field(static=True, default=2.0)
    corrected: bool = eqx.field(static=True, default=True)

    def __call__(self, particles, control, *, key):
        return self.base(particles, control, key=key)

    def propose(self, particles, control, z, *, key):
        n = particles.parameters().shape[0]
        dtype = particles.parameters().dtype
        e = jax.random.normal(key, (n, 3), dtype)
        std = self.base.std(control)
        xi = control + self.scale * std * e
        # components with std 0 are point masses under both densities: no correction
        lc = jnp.where(std > 0, math.log(self.scale) - 0.5 * (self.scale**2 - 1) * e**2, 0.0)
        lc = jnp.sum(lc, axis=-1)
        return particles @ from_vector(xi), lc if self.corrected else jnp.zeros(n, dtype)


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_proposal_hook_is_a_valid_importance_sampler(key):
    """A 2x wider proposal with the right correction reproduces the Kalman posterior
    (mean and variance); the same proposal without the correction is visibly too wide."""
    n, T, runs = 2000, 15, 6
    sq, sz, s0 = 0.05, 0.1, 0.15
    controls, z, _ = _toy_data(T, seed=3, s0=s0, sq=sq, sz=sz)
    kf_mean, kf_var = _kalman(controls, z, s0, sq, sz)
    keys = jax.random.split(key, runs)
    states = jax.vmap(lambda k: init_gaussian(n, [0.0, 0.0, 0.0], [s0, s0, 0.0], key=k))(keys)
    base = OdometryMotionModel([sq, sq, 0.0])
    ratios = {}
    for corrected in (True, False):
        pf = ParticleFilter(
            WideProposal(base, corrected=corrected),
            GaussianPosition(jnp.asarray(sz)),
            best_fraction=1.0,
        )
        finals, infos = jax.vmap(lambda s: pf.run(s, controls, z))(states)
        w = np.exp(np.asarray(finals.log_weights))  # [runs n]
        xy = np.asarray(finals.particles.translation())  # [runs n 2]
        mean = np.einsum("rn,rnd->rd", w, xy)
        var = np.einsum("rn,rnd->rd", w, (xy - mean[:, None]) ** 2)
        ratios[corrected] = var.mean() / kf_var[-1]
        if corrected:
            err = np.asarray(infos.estimate.translation()) - kf_mean
            n_eff = np.minimum.accumulate(np.asarray(infos.n_eff), axis=1)[..., None]
            mc = 2.0 * np.sqrt(kf_var)[None, :, None] / np.sqrt(n_eff)
            np.testing.assert_array_less(np.abs(err), Z * np.broadcast_to(mc, err.shape))
    assert abs(ratios[True] - 1) < 0.15
    assert ratios[False] > 1.3  # the check can fail: a missing correction is caught


# --------------------------------------------------------------------------------------
# Everything together, configuration errors
# --------------------------------------------------------------------------------------


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_run_vmap_all_features(key):
    n, T, runs = 256, 10, 3
    spec = GridSpec(np.array([-2.0, -2.0]), 0.5, (12, 12))
    free = np.ones(spec.shape, bool)
    free[:3, :3] = False
    pf = ParticleFilter(
        WideProposal(OdometryMotionModel([SIG_Q, SIG_Q, 0.01])),
        GaussianPosition(jnp.asarray(SIG_Z)),
        resampler="stratified",
        alpha_slow=0.01,
        alpha_fast=0.3,
        injector=global_injector(spec, jnp.asarray(free)),
        kld=True,
        kld_bin_size=(0.1, 0.1, 0.2),
        n_min=20,
    )
    controls, z, _ = _toy_data(T, seed=1)
    z = z.at[6:].add(2.0)  # a kidnapping halfway
    updates = jnp.asarray([True, True, False, True, True, True, True, False, True, True])
    keys = jax.random.split(key, runs)
    states = jax.vmap(lambda k: init_gaussian(n, [0.0, 0.0, 0.0], [SIG_0, SIG_0, 0.1], key=k))(keys)
    run = eqx.filter_jit(lambda p, s: jax.vmap(lambda si: p.run(si, controls, z, updates))(s))
    finals, infos = run(pf, states)
    assert infos.n_active.shape == (runs, T) and infos.injected.shape == (runs, T)
    for leaf in jax.tree.leaves((finals, infos)):
        if jnp.issubdtype(leaf.dtype, jnp.floating):
            assert not np.any(np.isnan(np.asarray(leaf)))
    assert np.all(np.isfinite(np.asarray(infos.estimate.parameters())))
    n_act = np.asarray(infos.n_active)
    assert np.all((n_act >= 20) & (n_act <= n)) and n_act.min() < n
    assert np.all(np.asarray(infos.injected) <= n_act)
    assert np.asarray(infos.injected)[:, 6:].sum() > 0
    assert not np.any(np.asarray(infos.resampled) & ~np.asarray(updates)[None])
    lw = np.asarray(finals.log_weights)
    for r in range(runs):
        m = int(finals.n_active[r])
        assert np.all(lw[r, m:] == -np.inf)
        np.testing.assert_allclose(np.exp(lw[r]).sum(), 1.0, rtol=1e-12)
    # the vmapped run equals a single run; the scan carry keeps its structure
    f0, i0 = pf.run(jax.tree.map(lambda x: x[0], states), controls, z, updates)
    np.testing.assert_allclose(np.asarray(i0.n_active), n_act[0])
    np.testing.assert_allclose(
        np.asarray(f0.particles.parameters()),
        np.asarray(finals.particles.parameters())[0],
        atol=1e-12,
    )
    s0 = jax.tree.map(lambda x: x[0], states)
    assert jax.tree.structure(f0) == jax.tree.structure(s0)
    assert jax.tree.map(lambda x: x.dtype, f0) == jax.tree.map(lambda x: x.dtype, s0)


def test_bad_configuration():
    m = OdometryMotionModel([0.1, 0.1, 0.1])
    meas = GaussianPosition(jnp.asarray(0.1))
    inj = _box()
    for kw, name in (
        (dict(alpha_slow=0.2, alpha_fast=0.1, injector=inj), "alpha_slow"),
        (dict(alpha_slow=0.1, alpha_fast=0.1, injector=inj), "alpha_slow"),
        (dict(alpha_slow=0.1, injector=inj), "alpha_slow"),
        (dict(alpha_slow=-0.1, alpha_fast=0.1, injector=inj), "alpha_slow"),
        (dict(alpha_fast=1.5, injector=inj), "alpha_fast"),
        (dict(alpha_fast=-0.5, injector=inj), "alpha_fast"),
        (dict(alpha_slow=0.01, alpha_fast=0.1), "injector"),
        (dict(kld=True, kld_bin_size=(0.5, 0.5)), "kld_bin_size"),
        (dict(kld=True, kld_bin_size=(0.5, 0.5, -0.1)), "kld_bin_size"),
        (dict(kld=True, kld_bin_size=(0.5,) * 6), "kld_bin_size"),  # SE2 motion
        (dict(kld=True, n_min=0), "n_min"),
        (dict(kld=True, n_min=-3), "n_min"),
        (dict(kld=True, n_min=2.5), "n_min"),
        (dict(kld=True, kld_epsilon=0.0), "kld_epsilon"),
        (dict(kld=True, kld_epsilon=1.5), "kld_epsilon"),
        (dict(kld=True, kld_delta=0.0), "kld_delta"),
        (dict(kld=True, kld_delta=1.0), "kld_delta"),
        (dict(kld="yes"), "kld"),
    ):
        with pytest.raises(ValueError, match=name):
            ParticleFilter(m, meas, **kw)
    # valid configurations
    ParticleFilter(m, meas, alpha_slow=0.0, alpha_fast=0.1, injector=inj)
    ParticleFilter(m, meas, alpha_slow=0.001, alpha_fast=1.0, injector=inj, kld=True)
    m3 = OdometryMotionModel(np.full(6, 0.1), group=jaxlie.SE3)
    ParticleFilter(m3, meas, kld=True, kld_bin_size=(0.5,) * 6)
    # a list or array of bin sizes becomes a hashable tuple (static under jit)
    pf_list = ParticleFilter(m, meas, kld=True, kld_bin_size=[0.5, 0.5, 0.2])
    assert pf_list.kld_bin_size == (0.5, 0.5, 0.2)
    with pytest.raises(ValueError, match="kld_bin_size"):
        ParticleFilter(m, meas, kld=True, kld_bin_size="big")
    for eps, delta, name in ((0.0, 0.01, "epsilon"), (0.05, 1.0, "delta"), (-1.0, 0.5, "epsilon")):
        with pytest.raises(ValueError, match=name):
            kld_particle_count(10, eps, delta)
    with pytest.raises(ValueError, match="bin_size"):
        count_occupied_bins(jnp.zeros((4, 3)), None, (0.5, 0.5))
    with pytest.raises(ValueError, match="active_mask"):
        count_occupied_bins(jnp.zeros((4, 3)), jnp.ones(3, bool), (0.5, 0.5, 0.5))
    # an injector returning poses of the wrong group / count fails at trace time
    bad = ParticleFilter(
        m, meas, alpha_slow=0.01, alpha_fast=0.1, injector=lambda k, n: jaxlie.SE3.identity((n,))
    )
    s = init_gaussian(8, [0.0, 0.0, 0.0], [0.1, 0.1, 0.1], key=jax.random.key(0))
    with pytest.raises(ValueError, match="injector"):
        bad.step(s, jnp.zeros(3), jnp.zeros(2))
    # bin sizes that do not match the particles (motion without a group attribute)
    pf = ParticleFilter(
        FixedProposal(jnp.zeros((8, 3)), jnp.zeros(8)), meas, kld=True, kld_bin_size=(0.5,) * 6
    )
    with pytest.raises(ValueError, match="kld_bin_size"):
        pf.step(s, jnp.zeros(3), jnp.zeros(2))
