"""Tests for the gradient-guided particle proposal (lidarjax.localization._guided): exact
importance weights against closed-form posteriors, the shift against finite differences,
robustness to degenerate inputs, the filter hook and the smooth scan surrogate.

Statistical checks use fixed keys and tolerances of a few delta-method standard errors
of the self-normalised importance-sampling estimates, so they are deterministic and fail
only if the estimated moment is wrong. float64 comes from conftest.py."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from scipy import stats
from test_localization import GaussianPosition

from lidarjax import maps
from lidarjax.localization import (
    OdometryMotionModel,
    ParticleFilter,
    from_vector,
    init_gaussian,
    to_vector,
)
from lidarjax.localization._guided import (
    GradientGuidedMotion,
    SmoothScanSurrogate,
    smooth_scan_surrogate,
)
from lidarjax.localization.refine import SmoothDecayRateField, SmoothDecayRateScan
from lidarjax.raytrace import GridSpec
from lidarjax.testing import finite_difference

Z = 4.0  # standard errors allowed in statistical checks


# --------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------


class GaussianX(eqx.Module):
    """log N(x_obs; x, r^2) of the world x coordinate (up to a constant)."""

    x_obs: jax.Array
    r: jax.Array

    def __call__(self, particles, z):
        d = particles.translation()[:, 0] - self.x_obs
        return -0.5 * d * d / self.r**2


class Linear(eqx.Module):
    """a . t_world + b * theta_world (no angle wrapping for small headings)."""

    a: jax.Array
    b: jax.Array

    def __call__(self, particles, z):
        return particles.translation() @ self.a + self.b * particles.rotation().as_radians()


def _ancestors(vecs, n_each):
    v = np.repeat(np.asarray(vecs, np.float64), n_each, axis=0)
    return from_vector(jnp.asarray(v))


def _weighted_moments(x, log_w):
    """Self-normalised weighted mean / variance of ``x`` with delta-method standard errors,
    and the effective sample size."""
    x = np.asarray(x, np.float64)
    lw = np.asarray(log_w, np.float64)
    w = np.exp(lw - lw.max())
    w /= w.sum()
    mean = np.sum(w * x)
    c = x - mean
    var = np.sum(w * c * c)
    se_mean = np.sqrt(np.sum(w * w * c * c))
    se_var = np.sqrt(np.sum(w * w * (c * c - var) ** 2))
    return mean, var, se_mean, se_var, 1.0 / np.sum(w * w)


def _kalman_1d(m0, s, x_obs, r):
    k = s**2 / (s**2 + r**2)
    return m0 + k * (x_obs - m0), (1 - k) * s**2


# --------------------------------------------------------------------------------------
# Exactness of the importance weights
# --------------------------------------------------------------------------------------

X0, CHI = 0.4, np.array([0.3, 0.1, 0.2])  # ancestor x (heading 0) and control


@pytest.mark.parametrize(
    "step_scale, n_grad_steps", [(1.0, 1), (0.5, 1), (0.3, 4)], ids=["one", "half", "iter"]
)
def test_gaussian_posterior_matches_kalman(key, step_scale, n_grad_steps):
    """Only x is random (y / theta std 0): prior N(x0 + chi, s^2), likelihood N(x_obs; x,
    r^2). The weighted particles (log-likelihood + correction) reproduce the closed-form
    posterior mean and variance."""
    n, s, r, x_obs = 20_000, 0.5, 0.5, X0 + CHI[0] + 0.4
    motion = GradientGuidedMotion(
        OdometryMotionModel([s, 0.0, 0.0]),
        GaussianX(jnp.asarray(x_obs), jnp.asarray(r)),
        step_scale=step_scale,
        n_grad_steps=n_grad_steps,
    )
    anc = _ancestors([[X0, -0.2, 0.0]], n)
    new, corr = motion.propose(anc, jnp.asarray(CHI), None, key=key)
    x = np.asarray(new.translation()[:, 0])
    log_w = np.asarray(motion.surrogate(new, None)) + np.asarray(corr)
    mean, var, se_m, se_v, n_eff = _weighted_moments(x, log_w)
    ref_mean, ref_var = _kalman_1d(X0 + CHI[0], s, x_obs, r)
    assert abs(mean - ref_mean) < Z * se_m
    assert abs(var - ref_var) < Z * se_v
    # the proposal really moved: the unweighted sample mean is off the prior mean
    assert abs(x.mean() - (X0 + CHI[0])) > 0.1
    assert n_eff > 0.3 * n
    # zero-std components are deterministic
    np.testing.assert_allclose(np.asarray(new.translation()[:, 1]), -0.2 + CHI[1], atol=1e-12)
    np.testing.assert_allclose(np.asarray(new.rotation().as_radians()), CHI[2], atol=1e-12)


def test_linear_log_likelihood_gives_equal_weights(key):
    """For log p(z | xi) linear in xi, the kappa = 1, step_scale = 1 proposal is the exact
    posterior: log-likelihood + correction is the same for all descendants of an ancestor,
    namely L(X transform(chi)) + |s * g|^2 / 2 (g: gradient in the robot frame)."""
    a, b = np.array([0.7, -1.3]), 2.0
    std = np.array([0.2, 0.3, 0.05])
    sur = Linear(jnp.asarray(a), jnp.asarray(b))
    motion = GradientGuidedMotion(OdometryMotionModel(std), sur)
    anc_v = np.array([[0.0, 0.0, 0.0], [1.0, -2.0, 0.6], [-0.5, 0.3, -0.9]])
    n_each = 500
    anc = _ancestors(anc_v, n_each)
    new, corr = motion.propose(anc, jnp.asarray(CHI), None, key=key)
    total = np.asarray(sur(new, None)) + np.asarray(corr)
    for i, (_, _, th) in enumerate(anc_v):
        rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
        g = np.concatenate([rot.T @ a, [b]])
        mean_pose = jaxlie.SE2.from_xy_theta(*anc_v[i]) @ from_vector(jnp.asarray(CHI))
        expected = float(sur(jax.tree.map(lambda t: t[None], mean_pose), None)[0])
        expected += 0.5 * np.sum((std * g) ** 2)
        block = total[i * n_each : (i + 1) * n_each]
        np.testing.assert_allclose(block, expected, rtol=0, atol=1e-9)
    # the correction is not trivially constant itself
    assert np.std(np.asarray(corr)) > 0.1


class LinearTranslation3(eqx.Module):
    a: jax.Array

    def __call__(self, particles, z):
        return particles.translation() @ self.a


@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_linear_log_likelihood_gives_equal_weights_se3(key):
    """The same exactness in SE(3): a log-likelihood linear in the world translation is
    linear in xi's translation part (gradient R^T a), flat in its rotation part."""
    a = np.array([0.7, -1.3, 2.1])
    std = np.array([0.2, 0.1, 0.3, 0.05, 0.0, 0.1])
    chi = np.array([0.3, 0.1, -0.2, 0.05, 0.1, 0.2])
    sur = LinearTranslation3(jnp.asarray(a))
    motion = GradientGuidedMotion(OdometryMotionModel(std, group=jaxlie.SE3), sur)
    anc_v = np.array([[1.0, -2.0, 0.5, 0.3, -0.2, 0.6], [0.0, 0.0, 0.0, -0.4, 0.2, -0.9]])
    anc = from_vector(jnp.asarray(np.repeat(anc_v, 300, axis=0)), jaxlie.SE3)
    new, corr = motion.propose(anc, jnp.asarray(chi), None, key=key)
    total = np.asarray(sur(new, None)) + np.asarray(corr)
    for i in range(2):
        a0 = from_vector(jnp.asarray(anc_v[i : i + 1]), jaxlie.SE3)
        rot = np.asarray(a0.rotation().as_matrix())[0]
        g = np.concatenate([rot.T @ a, np.zeros(3)])
        expected = float(sur(a0 @ from_vector(jnp.asarray(chi[None]), jaxlie.SE3), None)[0])
        expected += 0.5 * np.sum((std * g) ** 2)
        np.testing.assert_allclose(total[i * 300 : (i + 1) * 300], expected, rtol=0, atol=1e-9)
        d = np.asarray(motion.shift(a0, chi, None))[0]
        np.testing.assert_allclose(d, std**2 * g, atol=1e-12)
    assert np.std(np.asarray(corr)) > 0.1


def test_correction_equals_gaussian_log_density_ratio(key):
    """log_correction = log N(xi; chi, Sigma) - log N(xi; chi + delta, kappa^2 Sigma) with
    an independently computed (clipped) delta and scipy densities, xi recovered from the
    output poses; the zero-std component contributes nothing."""
    a, b = np.array([0.7, -1.3]), 80.0  # heading shift clipped at max_shift_std
    std = np.array([0.2, 0.0, 0.05])
    kappa, step, cap = 1.7, 0.8, 2.5
    motion = GradientGuidedMotion(
        OdometryMotionModel(std),
        Linear(jnp.asarray(a), jnp.asarray(b)),
        step_scale=step,
        proposal_inflation=kappa,
        max_shift_std=cap,
    )
    anc_v = np.array([[1.0, -2.0, 0.6], [-0.5, 0.3, -0.9]])
    anc = _ancestors(anc_v, 200)
    new, corr = motion.propose(anc, jnp.asarray(CHI), None, key=key)
    xi = np.asarray(to_vector(anc.inverse() @ new))
    th = np.repeat(anc_v[:, 2], 200)
    g = np.stack([np.cos(th) * a[0] + np.sin(th) * a[1], -np.sin(th) * a[0] + np.cos(th) * a[1]])
    g = np.concatenate([g.T, np.full((len(th), 1), b)], axis=1)
    delta = np.clip(step * std**2 * g, -cap * std, cap * std)
    assert np.any(np.abs(delta[:, 2]) == cap * std[2])  # the clip is exercised
    np.testing.assert_allclose(np.asarray(motion.shift(anc, CHI, None)), delta, atol=1e-12)
    act = std > 0
    ref = np.sum(
        stats.norm.logpdf(xi[:, act], CHI[act], std[act])
        - stats.norm.logpdf(xi[:, act], CHI[act] + delta[:, act], kappa * std[act]),
        axis=1,
    )
    np.testing.assert_allclose(np.asarray(corr), ref, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(xi[:, 1], CHI[1], atol=1e-12)


def test_inflated_proposal_is_unbiased_and_beats_the_prior(key):
    """Likelihood 10x narrower than the prior and 2.5 prior std away from it, kappa = 2:
    still the closed-form posterior, with a much larger n_eff than the prior proposal."""
    n, s, r = 20_000, 0.5, 0.05
    m0 = X0 + CHI[0]
    x_obs = m0 + 2.5 * s
    lik = GaussianX(jnp.asarray(x_obs), jnp.asarray(r))
    prior = OdometryMotionModel([s, 0.0, 0.0])
    motion = GradientGuidedMotion(prior, lik, proposal_inflation=2.0)
    anc = _ancestors([[X0, 0.0, 0.0]], n)
    k_guided, k_prior = jax.random.split(key)
    new, corr = motion.propose(anc, jnp.asarray(CHI), None, key=k_guided)
    mean, var, se_m, se_v, n_eff = _weighted_moments(new.translation()[:, 0], lik(new, None) + corr)
    ref_mean, ref_var = _kalman_1d(m0, s, x_obs, r)
    assert abs(mean - ref_mean) < Z * se_m
    assert abs(var - ref_var) < Z * se_v
    # the shift hit the 3-std cap (the gradient step alone would overshoot by far)
    np.testing.assert_allclose(np.asarray(motion.shift(anc, CHI, None))[:, 0], 3 * s)
    plain = motion(anc, jnp.asarray(CHI), key=k_prior)  # __call__ = the prior
    *_, n_eff_prior = _weighted_moments(plain.translation()[:, 0], lik(plain, None))
    assert n_eff > 5 * n_eff_prior


def test_iterated_shift_converges_to_posterior_mode():
    """Damped preconditioned ascent on log prior + Gaussian log-likelihood converges to the
    posterior mean (= mode); a single step does not."""
    s, r = 0.5, 0.3
    m0 = X0 + CHI[0]
    x_obs = m0 + 0.4
    lik = GaussianX(jnp.asarray(x_obs), jnp.asarray(r))
    anc = _ancestors([[X0, 0.0, 0.0]], 2)
    ref_mean, _ = _kalman_1d(m0, s, x_obs, r)
    for steps, close in ((1, False), (30, True)):
        motion = GradientGuidedMotion(
            OdometryMotionModel([s, 0.0, 0.0]), lik, step_scale=0.3, n_grad_steps=steps
        )
        d = np.asarray(motion.shift(anc, CHI, None))
        assert np.allclose(d[:, 0], ref_mean - m0, atol=1e-10) == close
        np.testing.assert_array_equal(d[:, 1:], 0.0)


# --------------------------------------------------------------------------------------
# Gradient and robustness
# --------------------------------------------------------------------------------------


class Wavy(eqx.Module):
    """A smooth nonlinear function of the whole SE(2) pose."""

    c: jax.Array

    def __call__(self, particles, z):
        t = particles.translation()
        th = particles.rotation().as_radians()
        return (
            jnp.sin(1.3 * t[:, 0] + 0.4 * t[:, 1] * t[:, 1])
            - 0.5 * jnp.sum((t - self.c) ** 2, axis=-1)
            + jnp.cos(th - 0.3) * t[:, 0]
        )


@pytest.mark.parametrize("step_scale, autodiff", [(1.0, "forward"), (0.7, "reverse")])
def test_shift_is_sigma_times_finite_difference_gradient(step_scale, autodiff):
    sur = Wavy(jnp.asarray([0.5, -0.2]))
    std = np.array([0.3, 0.2, 0.1])
    motion = GradientGuidedMotion(
        OdometryMotionModel(std),
        sur,
        step_scale=step_scale,
        max_shift_std=np.inf,
        autodiff=autodiff,
    )
    anc_v = np.array([[0.0, 0.0, 0.0], [1.0, -0.5, 0.8], [-0.7, 0.9, -2.0], [0.2, 0.4, 3.0]])
    anc = from_vector(jnp.asarray(anc_v))
    d = np.asarray(motion.shift(anc, CHI, None))
    for i in range(len(anc_v)):
        p = jax.tree.map(lambda t, i=i: t[i : i + 1], anc)
        fd = finite_difference(
            lambda e, p=p: sur(p @ from_vector(e[None] + CHI), None)[0], np.zeros(3)
        )
        np.testing.assert_allclose(d[i], step_scale * std**2 * fd, rtol=1e-6, atol=1e-10)
    assert np.all(np.abs(d) > 1e-4)  # every component really shifted


class Hostile(eqx.Module):
    """-inf for world x < 0, NaN for world y > 1, an infinite gradient at x = 0.5 (sqrt),
    otherwise a smooth bump."""

    def __call__(self, particles, z):
        t = particles.translation()
        x, y = t[:, 0], t[:, 1]
        val = -((x - 2.0) ** 2) - (y - 0.5) ** 2 + jnp.sqrt(jnp.abs(x - 0.5))
        val = jnp.where(x < 0, -jnp.inf, val)
        return jnp.where(y > 1, jnp.nan, val)


@pytest.mark.parametrize("autodiff", ["forward", "reverse"])
@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_zero_std_and_non_finite_surrogate(key, autodiff):
    chi = np.array([0.25, 0.0, 0.0])
    # world (x, y) at xi = chi: (-0.75, 0) -inf; (1.25, 1.5) NaN; (0.5, 0) inf gradient;
    # (1.25, 0.25) fine
    anc_v = np.array([[-1.0, 0.0, 0.0], [1.0, 1.5, 0.0], [0.25, 0.0, 0.0], [1.0, 0.25, 0.0]])
    anc = _ancestors(anc_v, 50)
    motion = GradientGuidedMotion(
        OdometryMotionModel([0.1, 0.0, 0.05]), Hostile(), proposal_inflation=1.0, autodiff=autodiff
    )
    d = np.asarray(motion.shift(anc, chi, None)).reshape(4, 50, 3)
    np.testing.assert_array_equal(d[:3], 0.0)
    assert np.all(d[3, :, 0] > 0.01)  # the good particle moves towards x = 2
    np.testing.assert_array_equal(d[..., 1:], 0.0)  # y: zero std; theta: zero gradient
    new, corr = motion.propose(anc, chi, None, key=key)
    params, corr = np.asarray(new.parameters()), np.asarray(corr)
    assert np.all(np.isfinite(params)) and np.all(np.isfinite(corr))
    # unshifted particles with kappa = 1: proposal = prior, correction exactly 0
    np.testing.assert_array_equal(corr[:150], 0.0)
    assert np.all(corr[150:] != 0.0)
    xi = np.asarray(to_vector(anc.inverse() @ new))
    np.testing.assert_allclose(xi[:, 1], 0.0, atol=1e-12)  # zero std: no noise
    # every step of an iterated shift, with inflation, stays finite too
    it = GradientGuidedMotion(
        OdometryMotionModel([0.1, 0.0, 0.05]),
        Hostile(),
        proposal_inflation=1.5,
        n_grad_steps=5,
        autodiff=autodiff,
    )
    new2, corr2 = it.propose(anc, chi, None, key=key)
    assert np.all(np.isfinite(np.asarray(new2.parameters())))
    assert np.all(np.isfinite(np.asarray(corr2)))
    np.testing.assert_array_equal(np.asarray(it.shift(anc, chi, None))[:150], 0.0)


def test_call_is_the_plain_motion_model_and_jits(key):
    base = OdometryMotionModel([0.1, 0.2, 0.05])
    motion = GradientGuidedMotion(base, Wavy(jnp.asarray([0.0, 0.0])))
    anc = _ancestors([[0.0, 1.0, 0.5]], 7)
    a = motion(anc, jnp.asarray(CHI), key=key)
    b = base(anc, jnp.asarray(CHI), key=key)
    np.testing.assert_array_equal(np.asarray(a.parameters()), np.asarray(b.parameters()))
    jitted = eqx.filter_jit(lambda m, p, k: m.propose(p, CHI, None, key=k))
    p1, c1 = jitted(motion, anc, key)
    p2, c2 = motion.propose(anc, CHI, None, key=key)
    np.testing.assert_allclose(np.asarray(p1.parameters()), np.asarray(p2.parameters()), atol=1e-13)
    np.testing.assert_allclose(np.asarray(c1), np.asarray(c2), atol=1e-12)


# --------------------------------------------------------------------------------------
# Through the particle filter
# --------------------------------------------------------------------------------------


class _Probe(eqx.Module):
    """Identity motion whose proposal reports corrections 0, 1, 2, ..."""

    def __call__(self, particles, control, *, key):
        return particles

    def propose(self, particles, control, z, *, key):
        return particles, jnp.arange(particles.parameters().shape[0], dtype=jnp.float64)


def _has_proposal_hook() -> bool:
    """Whether ParticleFilter.step adds a motion model's proposal correction (probed)."""
    state = init_gaussian(4, [0.0, 0.0, 0.0], [0.1, 0.1, 0.0], key=jax.random.key(0))
    pf = ParticleFilter(_Probe(), lambda p, z: jnp.zeros(4), resample_fraction=0.0)
    new, _ = pf.step(state, jnp.zeros(3), None)
    return bool(np.ptp(np.asarray(new.log_weights)) > 1.0)


HOOK = _has_proposal_hook()


SIG_Q, SIG_Z, SIG_0 = 0.1, 0.05, 0.15  # motion, measurement and prior std (m)


def _toy_data(T, seed=0):
    rng = np.random.default_rng(seed)
    controls = np.tile([0.2, 0.0, 0.0], (T, 1))
    truth = np.zeros((T, 2))
    x = rng.normal(0.0, SIG_0, 2)
    for t in range(T):
        x = x + controls[t, :2] + rng.normal(0.0, SIG_Q, 2)
        truth[t] = x
    z = truth + rng.normal(0.0, SIG_Z, (T, 2))
    return jnp.asarray(controls), jnp.asarray(z), truth


def _kalman(controls, z, updates):
    m, p = np.zeros(2), SIG_0**2
    means, variances = [], []
    for t in range(len(z)):
        m, p = m + np.asarray(controls[t, :2]), p + SIG_Q**2
        if updates[t]:
            k = p / (p + SIG_Z**2)
            m, p = m + k * (np.asarray(z[t]) - m), (1 - k) * p
        means.append(m)
        variances.append(p)
    return np.array(means), np.array(variances)


@pytest.mark.skipif(not HOOK, reason="ParticleFilter.step has no proposal hook yet")
@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_filter_with_guided_motion_tracks_kalman_posterior(key):
    """Heading fixed, linear-Gaussian motion and measurement: the guided filter's mean
    matches the Kalman filter within Monte-Carlo error, and its n_eff beats the plain
    filter's (measurement 2x narrower than the motion noise)."""
    n, T = 2000, 12
    controls, z, _ = _toy_data(T)
    base = OdometryMotionModel([SIG_Q, SIG_Q, 0.0])
    meas = GaussianPosition(jnp.asarray(SIG_Z))
    guided = GradientGuidedMotion(base, meas, step_scale=0.25, n_grad_steps=3)
    state = init_gaussian(n, [0.0, 0.0, 0.0], [SIG_0, SIG_0, 0.0], key=key)
    updates = np.arange(T) != 3  # one prediction-only step (the plain motion model)
    pf = ParticleFilter(guided, meas, best_fraction=1.0)
    _, infos = pf.run(state, controls, z, jnp.asarray(updates))
    _, plain = ParticleFilter(base, meas, best_fraction=1.0).run(
        state, controls, z, jnp.asarray(updates)
    )
    est = np.asarray(infos.estimate.translation())
    kf_mean, kf_var = _kalman(controls, z, updates)
    n_eff = np.minimum.accumulate(np.asarray(infos.n_eff))[:, None]
    mc = 2.0 * np.sqrt(kf_var)[:, None] / np.sqrt(n_eff)
    np.testing.assert_array_less(np.abs(est - kf_mean), 6.0 * np.broadcast_to(mc, est.shape))
    np.testing.assert_array_equal(np.asarray(infos.estimate.rotation().as_radians()), 0.0)
    # (bounded by the spread of the ancestors' predictive likelihoods, which no
    # per-ancestor proposal removes: here about 1.6x on average, 7x at the worst step)
    assert np.mean(np.asarray(infos.n_eff)) > 1.3 * np.mean(np.asarray(plain.n_eff))
    assert np.min(np.asarray(infos.n_eff)) > 3 * np.min(np.asarray(plain.n_eff))


# --------------------------------------------------------------------------------------
# Smooth scan surrogate
# --------------------------------------------------------------------------------------


def _map(seed=0):
    rng = np.random.default_rng(seed)
    rates = rng.uniform(0.0, 3.0, (16, 12))
    spec = GridSpec((-2.0, -1.5), 0.25, rates.shape)
    return maps.DecayRateMap(spec, jnp.asarray(rates), jnp.asarray(0.2))


AZ = np.linspace(-np.pi, np.pi, 9, endpoint=False)
R_MIN, R_MAX = 0.1, 2.0


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_smooth_scan_surrogate_matches_per_particle_scan():
    m = _map()
    rng = np.random.default_rng(1)
    ranges = rng.uniform(0.0, 2.5, AZ.shape)  # HIT, SUB and SUP readings
    ranges[:2] = [0.05, 2.4]
    poses = np.column_stack(
        [rng.uniform(-1.5, 1.5, 6), rng.uniform(-1.0, 1.0, 6), rng.uniform(-3, 3, 6)]
    )
    particles = from_vector(jnp.asarray(poses))
    sur = smooth_scan_surrogate(m, AZ, R_MIN, R_MAX, blur_m=0.3, n_nodes=32)
    assert isinstance(sur, SmoothScanSurrogate)
    got = np.asarray(sur(particles, jnp.asarray(ranges)))
    field = SmoothDecayRateField(m, 0.3)
    at = eqx.filter_jit(lambda obj, p: obj(p))  # one compile for the loop
    ref = [
        float(at(SmoothDecayRateScan(field, AZ, ranges, R_MIN, R_MAX, n_nodes=32), from_vector(p)))
        for p in poses
    ]
    assert got.shape == (6,)
    np.testing.assert_allclose(got, ref, rtol=1e-12)
    # a ready field is used as is; the blur matters
    np.testing.assert_allclose(
        np.asarray(smooth_scan_surrogate(field, AZ, R_MIN, R_MAX, n_nodes=32)(particles, ranges)),
        got,
        rtol=1e-12,
    )
    unblurred = smooth_scan_surrogate(m, AZ, R_MIN, R_MAX, blur_m=0.0, n_nodes=32)
    assert not np.allclose(np.asarray(unblurred(particles, ranges)), got)


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_smooth_scan_surrogate_gradient_drives_the_shift():
    m = _map(2)
    true_pose = jaxlie.SE2.from_xy_theta(0.2, -0.1, 0.4)
    az = np.linspace(-np.pi, np.pi, 30, endpoint=False)
    rng = np.random.default_rng(3)
    ranges = jnp.asarray(rng.uniform(0.3, 1.8, az.shape))
    sur = smooth_scan_surrogate(m, az, R_MIN, R_MAX, blur_m=0.2)
    std = np.array([0.05, 0.05, 0.02])
    motion = GradientGuidedMotion(OdometryMotionModel(std), sur, max_shift_std=np.inf)
    anc = from_vector(to_vector(true_pose)[None] + jnp.asarray(rng.normal(0, 0.1, (4, 3))))
    chi = jnp.zeros(3)
    d = np.asarray(eqx.filter_jit(lambda mo: mo.shift(anc, chi, ranges))(motion))
    assert np.all(np.isfinite(d)) and np.all(np.abs(d) > 0)
    value = jax.jit(lambda e, p: sur(p @ from_vector(e[None]), ranges)[0])
    for i in range(4):
        p = jax.tree.map(lambda t, i=i: t[i : i + 1], anc)
        fd = finite_difference(lambda e, p=p: value(e, p), np.zeros(3))
        np.testing.assert_allclose(d[i], std**2 * fd, rtol=1e-5, atol=1e-12)
    new, corr = eqx.filter_jit(lambda mo: mo.propose(anc, chi, ranges, key=jax.random.key(1)))(
        motion
    )
    assert np.all(np.isfinite(np.asarray(new.parameters()))) and np.all(np.isfinite(corr))


# --------------------------------------------------------------------------------------
# Bad arguments
# --------------------------------------------------------------------------------------


def test_bad_arguments():
    base = OdometryMotionModel([0.1, 0.1, 0.1])
    sur = Wavy(jnp.zeros(2))
    for kwargs, name in [
        (dict(step_scale=-1.0), "step_scale"),
        (dict(step_scale=np.inf), "step_scale"),
        (dict(step_scale="1"), "step_scale"),
        (dict(proposal_inflation=0.5), "proposal_inflation"),
        (dict(proposal_inflation=np.nan), "proposal_inflation"),
        (dict(max_shift_std=0.0), "max_shift_std"),
        (dict(max_shift_std=np.nan), "max_shift_std"),
        (dict(n_grad_steps=0), "n_grad_steps"),
        (dict(n_grad_steps=2.0), "n_grad_steps"),
        (dict(n_grad_steps=True), "n_grad_steps"),
        (dict(autodiff="numeric"), "autodiff"),
    ]:
        with pytest.raises(ValueError, match=name):
            GradientGuidedMotion(base, sur, **kwargs)
    with pytest.raises(ValueError, match="motion"):
        GradientGuidedMotion(lambda p, c, key: p, sur)
    with pytest.raises(ValueError, match="surrogate"):
        GradientGuidedMotion(base, 3.0)
    motion = GradientGuidedMotion(base, sur)
    with pytest.raises(ValueError, match="control"):
        motion.shift(_ancestors([[0.0, 0.0, 0.0]], 2), jnp.zeros(2), None)
    with pytest.raises(ValueError, match="decay_rate_map_or_field"):
        smooth_scan_surrogate(jnp.ones((4, 4)), AZ, R_MIN, R_MAX)
    with pytest.raises(ValueError, match="r_min"):
        smooth_scan_surrogate(_map(), AZ, 2.0, 1.0)
    with pytest.raises(ValueError, match="n_nodes"):
        smooth_scan_surrogate(_map(), AZ, R_MIN, R_MAX, n_nodes=0)
    with pytest.raises(ValueError, match="blur_m"):
        smooth_scan_surrogate(_map(), AZ, R_MIN, R_MAX, blur_m=-0.1)


# --------------------------------------------------------------------------------------
# Curvature (Laplace) proposal
# --------------------------------------------------------------------------------------


class GaussianXY(eqx.Module):
    """A correlated Gaussian log-likelihood of the world (x, y) position (nats)."""

    mean: jax.Array
    precision: jax.Array

    def __call__(self, particles, z):
        d = particles.translation() - self.mean
        return -0.5 * jnp.einsum("ni,ij,nj->n", d, self.precision, d)


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_curvature_proposal_is_exact_for_a_gaussian_likelihood_in_xi(key):
    """With the heading noise off, the robot-frame increment enters the world position
    linearly, so a Gaussian likelihood of (x, y) makes the posterior over xi Gaussian; the
    Laplace proposal (one Newton step, kappa = 1) is then the exact posterior and
    log-likelihood + correction is the same for every descendant of an ancestor."""
    std = np.array([0.3, 0.2, 0.0])
    prec = np.array([[40.0, 15.0], [15.0, 25.0]])  # narrower than the prior, correlated
    sur = GaussianXY(jnp.asarray([1.1, -0.4]), jnp.asarray(prec))
    motion = GradientGuidedMotion(OdometryMotionModel(std), sur, curvature=True)
    anc_v = np.array([[0.2, -0.3, 0.4], [1.0, 0.1, -1.2]])
    anc = _ancestors(anc_v, 400)
    new, corr = motion.propose(anc, jnp.asarray(CHI), None, key=key)
    total = np.asarray(sur(new, None)) + np.asarray(corr)
    for i in range(len(anc_v)):
        block = total[i * 400 : (i + 1) * 400]
        assert np.ptp(block) < 1e-9, np.ptp(block)
    # the plain gradient step is not exact here (curved likelihood): weights vary
    plain = GradientGuidedMotion(OdometryMotionModel(std), sur)
    new_p, corr_p = plain.propose(anc, jnp.asarray(CHI), None, key=key)
    assert np.ptp(np.asarray(sur(new_p, None)) + np.asarray(corr_p)) > 1.0


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_curvature_proposal_unbiased_for_nonlinear_likelihood(key):
    """A non-Gaussian likelihood in x (quartic well, offset from the prior): the weighted
    particles of the Laplace proposal (2 Newton steps, kappa = 1.5) reproduce the posterior
    mean and variance computed by quadrature."""

    class Quartic(eqx.Module):
        c: jax.Array

        def __call__(self, particles, z):
            d = particles.translation()[:, 0] - self.c
            return -8.0 * d**4 - 2.0 * d * d

    n, s = 40_000, 0.6
    c = X0 + CHI[0] + 0.5
    motion = GradientGuidedMotion(
        OdometryMotionModel([s, 0.0, 0.0]),
        Quartic(jnp.asarray(c)),
        curvature=True,
        n_grad_steps=2,
        proposal_inflation=1.5,
    )
    anc = _ancestors([[X0, 0.0, 0.0]], n)
    new, corr = motion.propose(anc, jnp.asarray(CHI), None, key=key)
    x = np.asarray(new.translation()[:, 0])
    log_w = np.asarray(motion.surrogate(new, None)) + np.asarray(corr)
    mean, var, se_m, se_v, n_eff = _weighted_moments(x, log_w)
    grid = np.linspace(-6, 8, 200_001)
    m0 = X0 + CHI[0]
    logp = -0.5 * ((grid - m0) / s) ** 2 - 8.0 * (grid - c) ** 4 - 2.0 * (grid - c) ** 2
    p = np.exp(logp - logp.max())
    p /= p.sum()
    ref_mean = np.sum(p * grid)
    ref_var = np.sum(p * (grid - ref_mean) ** 2)
    assert abs(mean - ref_mean) < Z * se_m
    assert abs(var - ref_var) < Z * se_v
    assert n_eff > 0.5 * n  # the proposal is close to the posterior


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_curvature_hessian_and_shift_vs_finite_differences():
    """The Newton shift equals s * (I + B)^-1 (s * g) with g and the Hessian from central
    finite differences of the surrogate in xi (nonlinear SE2 surrogate, all components)."""

    class Bumpy(eqx.Module):
        def __call__(self, particles, z):
            t = particles.translation()
            th = particles.rotation().as_radians()
            return -3.0 * (t[:, 0] - 0.8) ** 2 - (t[:, 1] + 0.2) ** 2 * (1 + 0.5 * jnp.sin(th))

    std = np.array([0.2, 0.15, 0.1])
    sur = Bumpy()
    motion = GradientGuidedMotion(OdometryMotionModel(std), sur, curvature=True)
    anc_v = np.array([[0.1, 0.3, 0.2], [-0.4, 0.0, 1.0]])
    shift = np.asarray(motion.shift(_ancestors(anc_v, 1), jnp.asarray(CHI), None))
    for i, v in enumerate(anc_v):
        anc = _ancestors([v], 1)

        def f(xi, anc=anc):
            return float(sur(anc @ from_vector(jnp.asarray(xi)[None]), None)[0])

        h = 1e-4
        g = np.array([(f(CHI + h * e) - f(CHI - h * e)) / (2 * h) for e in np.eye(3)])
        hess = np.array(
            [
                [
                    (
                        f(CHI + h * (a + b))
                        - f(CHI + h * (a - b))
                        - f(CHI - h * (a - b))
                        + f(CHI - h * (a + b))
                    )
                    / (4 * h * h)
                    for b in np.eye(3)
                ]
                for a in np.eye(3)
            ]
        )
        bmat = -(std[:, None] * hess * std[None, :])
        w, q = np.linalg.eigh(0.5 * (bmat + bmat.T))
        prec = np.eye(3) + (q * np.maximum(w, 0)) @ q.T
        ref = std * np.linalg.solve(prec, std * g)
        np.testing.assert_allclose(shift[i], ref, rtol=1e-5, atol=1e-8)


@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_curvature_non_finite_surrogate_is_not_moved(key):
    class Bad(eqx.Module):
        def __call__(self, particles, z):
            x = particles.translation()[:, 0]
            return jnp.where(x > 0.5, -jnp.inf, -(x**2))

    motion = GradientGuidedMotion(OdometryMotionModel([0.2, 0.1, 0.0]), Bad(), curvature=True)
    anc = _ancestors([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]], 1)
    new, corr = motion.propose(anc, jnp.asarray(CHI), None, key=key)
    sh = np.asarray(motion.shift(anc, jnp.asarray(CHI), None))
    assert np.all(np.isfinite(np.asarray(new.parameters()))) and np.all(np.isfinite(corr))
    np.testing.assert_array_equal(sh[0], 0.0)  # -inf surrogate: unshifted
    assert abs(sh[1, 0]) > 0  # finite one moves
    with pytest.raises(ValueError, match="curvature"):
        GradientGuidedMotion(OdometryMotionModel([0.2, 0.1, 0.0]), Bad(), curvature=1)


@pytest.mark.parametrize("k", [2, 3, 6])
def test_symmetric_eigh_small_vs_numpy(k):
    """The LAPACK-free Jacobi eigensolver the curvature proposal uses: eigenvalues equal
    NumPy's, the eigenvectors are orthonormal and reconstruct the matrix, including
    diagonal, zero, repeated-eigenvalue and badly scaled inputs."""
    from lidarjax._math import symmetric_eigh_small

    rng = np.random.default_rng(k)
    m = rng.normal(size=(200, k, k))
    m = m + np.swapaxes(m, -1, -2)
    m[0] = np.diag(np.arange(k, dtype=float))
    m[1] = np.eye(k)
    m[2] = 0.0
    m[3] = 1e6 * np.outer(np.ones(k), np.ones(k))
    m[4] = 1e-8 * m[5]
    w, v = (np.asarray(x) for x in symmetric_eigh_small(jnp.asarray(m)))
    scale = np.maximum(np.abs(m).max(axis=(-1, -2)), 1e-300)[:, None]
    np.testing.assert_allclose(
        np.sort(w, -1) / scale, np.linalg.eigvalsh(m) / scale, rtol=0, atol=1e-12
    )
    rec = np.einsum("nij,nj,nkj->nik", v, w, v)
    np.testing.assert_allclose(rec / scale[..., None], m / scale[..., None], atol=1e-12)
    np.testing.assert_allclose(
        np.einsum("nji,njk->nik", v, v), np.broadcast_to(np.eye(k), m.shape), atol=1e-12
    )
