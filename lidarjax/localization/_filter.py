"""A functional particle filter over SE(2) / SE(3) poses (Thrun et al., Probabilistic
Robotics ch. 4 and 8; dissertation section 12.4.3).

Everything is a pure function of a :class:`ParticleState` (particles, normalised
log-weights, PRNG key). One :meth:`ParticleFilter.step` is: motion update (sample from the
motion model), measurement update (add the measurement log-likelihood of every particle),
pose estimate, and resampling when the effective sample size ``n_eff = 1 / sum w_i^2``
falls below ``resample_fraction * n``. :meth:`ParticleFilter.run` is one ``lax.scan`` over
a sequence of controls and measurements, so a whole log compiles once and runs without
host round-trips; ``jax.vmap`` over independent runs (keys / initial states) works.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray

from ..rays import is_concrete
from ._poses import Pose, dof, from_vector, take, weighted_mean

ResamplerName = Literal["systematic", "stratified", "multinomial"]


# --------------------------------------------------------------------------------------
# Weights and resampling
# --------------------------------------------------------------------------------------


def normalize_log_weights(log_weights: Float[Array, " n"]) -> Float[Array, " n"]:
    """Log-weights shifted so that ``sum exp = 1``. If every weight is zero (all ``-inf``,
    e.g. every particle got likelihood 0) or any is NaN, the result is uniform, so the
    filter never produces NaN weights; :class:`StepInfo` reports such steps."""
    n = log_weights.shape[-1]
    lse = jax.nn.logsumexp(log_weights, axis=-1, keepdims=True)
    ok = jnp.isfinite(lse) & ~jnp.any(jnp.isnan(log_weights), axis=-1, keepdims=True)
    return jnp.where(ok, log_weights - jnp.where(ok, lse, 0.0), -math.log(n))


def effective_sample_size(log_weights: Float[Array, " n"]) -> Float[Array, ""]:
    """``n_eff = 1 / sum_i w_i^2`` of the normalised weights (between 1 and n)."""
    w = jnp.exp(normalize_log_weights(log_weights))
    return 1.0 / jnp.sum(w * w, axis=-1)


def _inverse_cdf(log_weights, positions):
    """Ancestor of each position in ``[0, 1)`` under the weights' CDF. A position that
    rounds up to the total (float32) maps to the last particle with positive weight, so a
    zero-weight particle is never chosen."""
    w = jnp.exp(normalize_log_weights(log_weights))
    n = w.shape[0]
    cdf = jnp.cumsum(w)
    idx = jnp.searchsorted(cdf, positions * cdf[-1], side="right")
    last_positive = jnp.max(jnp.where(w > 0, jnp.arange(n), 0))
    return jnp.clip(idx, 0, last_positive).astype(jnp.int32)


def systematic_resample(log_weights: Float[Array, " n"], *, key: PRNGKeyArray) -> Int[Array, " n"]:
    """Low-variance (systematic) resampling, Thrun et al. Table 4.4: one uniform offset
    ``u ~ U[0, 1/n)`` and the comb ``u + i/n``. Returns ``[n]`` ancestor indices."""
    n = log_weights.shape[0]
    u = jax.random.uniform(key, (), dtype=log_weights.dtype)
    return _inverse_cdf(log_weights, (jnp.arange(n, dtype=log_weights.dtype) + u) / n)


def stratified_resample(log_weights: Float[Array, " n"], *, key: PRNGKeyArray) -> Int[Array, " n"]:
    """Stratified resampling: one uniform draw in each stratum ``[i/n, (i+1)/n)``."""
    n = log_weights.shape[0]
    u = jax.random.uniform(key, (n,), dtype=log_weights.dtype)
    return _inverse_cdf(log_weights, (jnp.arange(n, dtype=log_weights.dtype) + u) / n)


def multinomial_resample(log_weights: Float[Array, " n"], *, key: PRNGKeyArray) -> Int[Array, " n"]:
    """Multinomial resampling: ``n`` independent draws from the weights (as the inverse
    CDF of ``n`` sorted uniforms, ``O(n log n)`` time and ``O(n)`` memory)."""
    n = log_weights.shape[0]
    u = jnp.sort(jax.random.uniform(key, (n,), dtype=log_weights.dtype))
    return _inverse_cdf(log_weights, u)


RESAMPLERS: dict[str, Callable] = {
    "systematic": systematic_resample,
    "stratified": stratified_resample,
    "multinomial": multinomial_resample,
}


# --------------------------------------------------------------------------------------
# State, initialisation, estimate
# --------------------------------------------------------------------------------------


class ParticleState(eqx.Module):
    """Particle filter state.

    Attributes:
        particles: ``[n]`` batched ``jaxlie.SE2`` or ``jaxlie.SE3`` (world-from-sensor).
        log_weights: ``[n]`` normalised log-weights.
        key: PRNG key for the next step.
    """

    particles: Pose
    log_weights: Float[Array, " n"]
    key: PRNGKeyArray

    @property
    def n(self) -> int:
        """Number of particles."""
        return int(self.log_weights.shape[-1])


def _check_n(n) -> int:
    if not isinstance(n, (int, np.integer)) or n <= 0:
        raise ValueError(f"n must be a positive int, got {n!r}")
    return int(n)


def _state(key, particles) -> ParticleState:
    n = particles.parameters().shape[0]
    dtype = particles.parameters().dtype
    return ParticleState(particles, jnp.full((n,), -math.log(n), dtype), key)


def init_gaussian(
    n: int,
    mean: Float[ArrayLike, " k"],
    std: Float[ArrayLike, " k"],
    group: type = jaxlie.SE2,
    *,
    key: PRNGKeyArray,
) -> ParticleState:
    """``n`` particles with pose vectors ``mean + std * N(0, I)`` (independent per
    component; angles in rad), uniform weights.

    Args:
        n: number of particles.
        mean: ``[k]`` pose vector, ``(x, y, theta)`` or ``(x, y, z, roll, pitch, yaw)``.
        std: ``[k]`` standard deviations (m, rad).
        group: ``jaxlie.SE2`` (k = 3) or ``jaxlie.SE3`` (k = 6).
        key: PRNG key (split; the state keeps a fresh one).
    """
    n = _check_n(n)
    k = dof(group)
    mean = jnp.asarray(mean, dtype=jnp.result_type(float))
    std = jnp.asarray(std, dtype=mean.dtype)
    if mean.shape != (k,) or std.shape != (k,):
        raise ValueError(f"mean and std must have shape ({k},), got {mean.shape} and {std.shape}")
    if not bool(jnp.all(jnp.isfinite(mean))) or not bool(jnp.all((std >= 0) & jnp.isfinite(std))):
        raise ValueError("mean must be finite and std finite and >= 0")
    k_draw, k_next = jax.random.split(key)
    v = mean + std * jax.random.normal(k_draw, (n, k), dtype=mean.dtype)
    return _state(k_next, from_vector(v, group))


def init_uniform_disc(
    n: int,
    center_xy: Float[ArrayLike, " 2"],
    radius_m: float,
    heading_rad: tuple[float, float],
    *,
    key: PRNGKeyArray,
) -> ParticleState:
    """``n`` SE(2) particles uniform in a disc of ``radius_m`` around ``center_xy`` with
    headings uniform in ``[heading_rad[0], heading_rad[1]]`` (Sec. 12.4.3 uses 2.5 m and
    +-5 deg around the first pose)."""
    n = _check_n(n)
    c = jnp.asarray(center_xy, dtype=jnp.result_type(float))
    if c.shape != (2,) or not bool(jnp.all(jnp.isfinite(c))):
        raise ValueError(f"center_xy must be 2 finite numbers, got {center_xy!r}")
    if not (np.isfinite(radius_m) and radius_m >= 0):
        raise ValueError(f"radius_m must be finite and >= 0, got {radius_m!r}")
    lo, hi = (float(h) for h in heading_rad)
    if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
        raise ValueError(f"heading_rad must be a finite interval (lo <= hi), got {heading_rad!r}")
    k_r, k_a, k_h, k_next = jax.random.split(key, 4)
    r = radius_m * jnp.sqrt(jax.random.uniform(k_r, (n,), dtype=c.dtype))
    a = jax.random.uniform(k_a, (n,), dtype=c.dtype, minval=-jnp.pi, maxval=jnp.pi)
    h = jax.random.uniform(k_h, (n,), dtype=c.dtype, minval=lo, maxval=hi)
    v = jnp.stack([c[0] + r * jnp.cos(a), c[1] + r * jnp.sin(a), h], axis=-1)
    return _state(k_next, from_vector(v))


def init_global(
    n: int, spec, free: Bool[ArrayLike, "nx ny"], *, key: PRNGKeyArray
) -> ParticleState:
    """``n`` SE(2) particles uniform over the free cells of a 2-D grid (uniform position
    inside a free cell chosen uniformly, uniform heading): global localization.

    Inverse-CDF sampling over the running count of free cells (``cumsum`` +
    ``searchsorted``): memory ``O(n + cells)`` and time ``O(cells + n log cells)``, so
    100 000 particles on a 631 x 629 grid need a few MB. Jittable (``free`` may be
    traced; an all-False mask then raises at run time through ``eqx.error_if``).

    Args:
        n: number of particles (static).
        spec: the 2-D :class:`~lidarjax.raytrace.GridSpec`.
        free: ``[nx ny]`` bool mask of free cells (e.g. ``occupancy < 0.2`` of visited
            cells); at least one must be True.
        key: PRNG key.

    Raises:
        ValueError: bad ``n``, a non-2-D grid, a mask of the wrong shape/dtype, or (when
            concrete) no free cell.
    """
    n = _check_n(n)
    free = jnp.asarray(free)
    if spec.dim != 2 or free.shape != spec.shape or free.dtype != jnp.bool_:
        raise ValueError(
            f"free must be a bool array of the 2-D grid's shape {spec.shape}, got "
            f"{free.dtype} {free.shape}"
        )
    if is_concrete(free) and not bool(np.any(np.asarray(free))):
        raise ValueError("free has no True cell to sample from")
    k_c, k_u, k_h, k_next = jax.random.split(key, 4)
    counts = jnp.cumsum(free.ravel().astype(jnp.int32))  # [cells], counts[-1] = #free
    total = counts[-1]
    total = eqx.error_if(total, total <= 0, "free has no True cell to sample from")
    # the r-th free cell (r uniform in 0..total-1) is the first index with count > r
    r = jax.random.randint(k_c, (n,), 0, jnp.maximum(total, 1))
    flat = jnp.searchsorted(counts, r, side="right")
    ij = jnp.stack(jnp.unravel_index(flat, spec.shape), axis=-1)
    dtype = spec.origin.dtype
    u = jax.random.uniform(k_u, (n, 2), dtype=dtype)
    xy = spec.origin + (ij.astype(dtype) + u) * spec.resolution
    h = jax.random.uniform(k_h, (n,), dtype=dtype, minval=-jnp.pi, maxval=jnp.pi)
    return _state(k_next, from_vector(jnp.concatenate([xy, h[:, None]], axis=-1)))


def estimate(state: ParticleState, best_fraction: float = 0.1) -> Pose:
    """Pose estimate: weighted mean of the ``ceil(best_fraction * n)`` particles with the
    largest weights (Sec. 12.4.3 uses the best 10 %; ``best_fraction=1`` is the plain
    weighted mean), circular mean for angles."""
    if not 0 < best_fraction <= 1:
        raise ValueError(f"best_fraction must lie in (0, 1], got {best_fraction!r}")
    k = max(1, math.ceil(best_fraction * state.n))
    top_lw, idx = jax.lax.top_k(state.log_weights, k)
    w = jnp.exp(top_lw - jnp.max(top_lw))
    return weighted_mean(take(state.particles, idx), w)


# --------------------------------------------------------------------------------------
# Motion model
# --------------------------------------------------------------------------------------


class OdometryMotionModel(eqx.Module):
    """Odometry motion model of Sec. 12.4.3: ``X_t = X_{t-1} transform(xi)``,
    ``xi ~ N(chi, Sigma)`` in the robot frame, ``chi`` the relative odometry.

    ``Sigma`` is diagonal with standard deviations
    ``inflation * (sigma + alpha @ |chi|)``: a constant part plus a part proportional to
    the magnitude of the motion (e.g. ``alpha[2, 0]`` adds heading noise per metre
    driven). (The dissertation writes ``transform(xi) X_{t-1}`` for its matrix convention;
    here poses are world-from-robot, so the robot-frame increment multiplies on the right.)

    Attributes:
        sigma: ``[k]`` constant standard deviations per step (m, rad).
        alpha: ``[k k]`` proportional standard deviations (per m or rad of ``|chi_j|``).
        inflation: factor on all standard deviations (the "inflated noise" of Sec. 12.4.3).
        group: ``jaxlie.SE2`` (k = 3) or ``jaxlie.SE3`` (k = 6).
    """

    sigma: Float[Array, " k"]
    alpha: Float[Array, "k k"]
    inflation: Float[Array, ""]
    group: type = eqx.field(static=True)

    def __init__(self, sigma, alpha=None, inflation: float = 1.0, group: type = jaxlie.SE2):
        k = dof(group)
        self.group = group
        self.sigma = jnp.asarray(sigma, dtype=jnp.result_type(float))
        self.alpha = (
            jnp.zeros((k, k), self.sigma.dtype)
            if alpha is None
            else jnp.asarray(alpha, self.sigma.dtype)
        )
        self.inflation = jnp.asarray(inflation, self.sigma.dtype)
        if self.sigma.shape != (k,) or self.alpha.shape != (k, k) or self.inflation.shape != ():
            raise ValueError(
                f"sigma must be [{k}], alpha [{k} {k}] and inflation a scalar for "
                f"{group.__name__}; got {self.sigma.shape}, {self.alpha.shape}, "
                f"{self.inflation.shape}"
            )
        for name, x in (
            ("sigma", self.sigma),
            ("alpha", self.alpha),
            ("inflation", self.inflation),
        ):
            if is_concrete(x) and not bool(jnp.all((x >= 0) & jnp.isfinite(x))):
                raise ValueError(f"{name} must be finite and >= 0")

    def std(self, control: Float[Array, " k"]) -> Float[Array, " k"]:
        """Standard deviations of ``xi`` for the control ``chi``."""
        return self.inflation * (self.sigma + self.alpha @ jnp.abs(control))

    def __call__(self, particles: Pose, control: Float[Array, " k"], *, key: PRNGKeyArray) -> Pose:
        n = particles.parameters().shape[0]
        k = dof(self.group)
        dtype = particles.parameters().dtype
        control = jnp.asarray(control, dtype)
        xi = control + self.std(control).astype(dtype) * jax.random.normal(key, (n, k), dtype)
        return particles @ from_vector(xi, self.group)


# --------------------------------------------------------------------------------------
# The filter
# --------------------------------------------------------------------------------------


class StepInfo(eqx.Module):
    """Per-step output of :meth:`ParticleFilter.step` (stacked ``[T]`` by ``run``).

    Attributes:
        estimate: pose estimate after the measurement update (before resampling).
        n_eff: effective sample size after the measurement update.
        resampled: whether the particles were resampled.
        degenerate: every particle had likelihood 0 (or NaN); the weights were reset to
            uniform instead of becoming NaN.
    """

    estimate: Pose
    n_eff: Float[Array, ""]
    resampled: Bool[Array, ""]
    degenerate: Bool[Array, ""]


class ParticleFilter(eqx.Module):
    """Particle filter with pluggable, pure motion and measurement models.

    Attributes:
        motion: ``motion(particles [n], control, *, key) -> particles [n]``, e.g.
            :class:`OdometryMotionModel`.
        measurement: ``measurement(particles [n], z) -> [n]`` log-likelihoods (``-inf``
            allowed), e.g. :class:`~lidarjax.localization.ScanModel`. Use an
            ``equinox.Module`` so its arrays (the map) are traced, not baked in.
        resample_fraction: resample when ``n_eff < resample_fraction * n``.
        resampler: ``"systematic"`` (low variance, default), ``"stratified"`` or
            ``"multinomial"``.
        best_fraction: fraction of highest-weight particles averaged for the estimate.
    """

    motion: Callable
    measurement: Callable
    resample_fraction: float = eqx.field(static=True, default=0.5)
    resampler: str = eqx.field(static=True, default="systematic")
    best_fraction: float = eqx.field(static=True, default=0.1)

    def __check_init__(self):
        if self.resampler not in RESAMPLERS:
            raise ValueError(
                f"resampler must be one of {sorted(RESAMPLERS)}, got {self.resampler!r}"
            )
        if not 0 <= self.resample_fraction <= 1:
            raise ValueError(
                f"resample_fraction must lie in [0, 1], got {self.resample_fraction!r}"
            )
        if not 0 < self.best_fraction <= 1:
            raise ValueError(f"best_fraction must lie in (0, 1], got {self.best_fraction!r}")

    def step(
        self, state: ParticleState, control, z, update: bool | Bool[Array, ""] = True
    ) -> tuple[ParticleState, StepInfo]:
        """One filter step: motion update with ``control``, measurement update with ``z``
        (skipped where ``update`` is False), estimate, conditional resampling."""
        key, k_motion, k_resample = jax.random.split(state.key, 3)
        particles = self.motion(state.particles, control, key=k_motion)
        n = state.log_weights.shape[0]
        update = jnp.asarray(update)
        ll = jax.lax.cond(
            update,
            lambda: jnp.asarray(self.measurement(particles, z), state.log_weights.dtype),
            lambda: jnp.zeros_like(state.log_weights),
        )
        raw = state.log_weights + ll
        degenerate = ~jnp.any(raw > -jnp.inf) | jnp.any(jnp.isnan(raw))
        log_weights = normalize_log_weights(raw)
        mid = ParticleState(particles, log_weights, key)
        est = estimate(mid, self.best_fraction)
        n_eff = effective_sample_size(log_weights)
        resample = update & (n_eff < self.resample_fraction * n)
        idx = jnp.where(
            resample, RESAMPLERS[self.resampler](log_weights, key=k_resample), jnp.arange(n)
        )
        particles = take(particles, idx)
        log_weights = jnp.where(resample, -math.log(n), log_weights)
        info = StepInfo(est, n_eff, resample, degenerate & update)
        return ParticleState(particles, log_weights, key), info

    @eqx.filter_jit
    def run(
        self, state: ParticleState, controls, measurements, updates=None
    ) -> tuple[ParticleState, StepInfo]:
        """Filter a whole sequence with one ``lax.scan``.

        Args:
            state: initial state.
            controls: pytree with leading axis ``[T]`` (e.g. ``[T k]`` relative odometry).
            measurements: pytree with leading axis ``[T]`` (e.g. ``[T b]`` ranges).
            updates: optional ``[T]`` bool, measurement update on/off per step.

        Returns:
            The final state and the stacked ``[T]`` :class:`StepInfo`.
        """
        n_steps = jax.tree.leaves(controls)[0].shape[0]
        if updates is None:
            updates = jnp.ones(n_steps, bool)

        def body(s, xs):
            c, z, u = xs
            return self.step(s, c, z, u)

        return jax.lax.scan(body, state, (controls, measurements, updates))
