"""The particle set: :class:`ParticleState` (particles, normalised log-weights, PRNG key,
active count) and its initialisations (Gaussian, uniform disc, uniform over a map's free
cells), random-particle injection for augmented MCL, and the pose estimate."""

from __future__ import annotations

import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray

from .._checks import check
from ..rays import is_concrete
from ..raytrace import GridSpec
from ._poses import Pose, dof, from_vector, take, weighted_mean
from ._resampling import _check_particle_count

# --------------------------------------------------------------------------------------
# State, initialisation, estimate
# --------------------------------------------------------------------------------------


class ParticleState(eqx.Module):
    """Particle filter state.

    ``ParticleState(particles, log_weights, key)`` gives the defaults for the optional
    fields (all particles active, augmented-MCL averages not yet started).

    Attributes:
        particles: ``[n]`` batched ``jaxlie.SE2`` or ``jaxlie.SE3`` (world-from-sensor).
        log_weights: ``[n]`` normalised log-weights (``-inf`` for inactive slots).
        key: PRNG key for the next step.
        n_active: int32 scalar, number of live (leading) particles with KLD-sampling;
            slots ``>= n_active`` have log-weight ``-inf`` (default ``n``).
        log_w_slow: scalar, log of the long-term average measurement likelihood of
            augmented MCL (nats; default ``-inf``, not started).
        log_w_fast: scalar, log of the short-term average (nats; default ``-inf``).
        n_updates: int32 scalar, measurement updates folded into the averages (default 0).
    """

    particles: Pose
    log_weights: Float[Array, " n"]
    key: PRNGKeyArray
    n_active: Int[Array, ""]
    log_w_slow: Float[Array, ""]
    log_w_fast: Float[Array, ""]
    n_updates: Int[Array, ""]

    def __init__(
        self,
        particles: Pose,
        log_weights: Float[ArrayLike, " n"],
        key: PRNGKeyArray,
        n_active: Int[ArrayLike, ""] | None = None,
        log_w_slow: Float[ArrayLike, ""] | None = None,
        log_w_fast: Float[ArrayLike, ""] | None = None,
        n_updates: Int[ArrayLike, ""] | None = None,
    ):
        log_weights = jnp.asarray(log_weights)
        n = _check_particle_count(log_weights, "log_weights")
        batch = log_weights.shape[:-1]
        dtype = log_weights.dtype

        def scalar(x, default, dt):
            return jnp.full(batch, default, dt) if x is None else jnp.asarray(x, dt)

        self.particles = particles
        self.log_weights = log_weights
        self.key = key
        self.n_active = scalar(n_active, n, jnp.int32)
        self.log_w_slow = scalar(log_w_slow, -jnp.inf, dtype)
        self.log_w_fast = scalar(log_w_fast, -jnp.inf, dtype)
        self.n_updates = scalar(n_updates, 0, jnp.int32)

    @property
    def n(self) -> int:
        """Number of particle slots (the maximum with KLD-sampling)."""
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


def _free_cell_counts(spec, free) -> Int[Array, " cells"]:
    """Validated running count of the free cells of a 2-D grid mask (``cumsum``)."""
    free = jnp.asarray(free)
    if spec.dim != 2 or free.shape != spec.shape or free.dtype != jnp.bool_:
        raise ValueError(
            f"free must be a bool array of the 2-D grid's shape {spec.shape}, got "
            f"{free.dtype} {free.shape}"
        )
    if is_concrete(free) and not bool(np.any(np.asarray(free))):
        raise ValueError("free has no True cell to sample from")
    counts = jnp.cumsum(free.ravel().astype(jnp.int32))  # [cells], counts[-1] = #free
    return counts


def _sample_free(n: int, spec, counts, k_c, k_u, k_h) -> Float[Array, "n 3"]:
    """``[n 3]`` pose vectors uniform over the free cells (``counts`` from
    :func:`_free_cell_counts`) with uniform headings."""
    total = counts[-1]
    total = check(total, total <= 0, "free has no True cell to sample from")
    # the r-th free cell (r uniform in 0..total-1) is the first index with count > r
    r = jax.random.randint(k_c, (n,), 0, jnp.maximum(total, 1))
    flat = jnp.searchsorted(counts, r, side="right")
    ij = jnp.stack(jnp.unravel_index(flat, spec.shape), axis=-1)
    dtype = spec.origin.dtype
    u = jax.random.uniform(k_u, (n, 2), dtype=dtype)
    xy = spec.origin + (ij.astype(dtype) + u) * spec.resolution
    h = jax.random.uniform(k_h, (n,), dtype=dtype, minval=-jnp.pi, maxval=jnp.pi)
    return jnp.concatenate([xy, h[:, None]], axis=-1)


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
    counts = _free_cell_counts(spec, free)
    k_c, k_u, k_h, k_next = jax.random.split(key, 4)
    return _state(k_next, from_vector(_sample_free(n, spec, counts, k_c, k_u, k_h)))


class _GlobalInjector(eqx.Module):
    """``injector(key, n) -> [n] SE2``: poses uniform over the free cells of a grid (the
    sampling of :func:`init_global`)."""

    spec: GridSpec
    counts: Int[Array, " cells"]

    def __call__(self, key: PRNGKeyArray, n: int) -> jaxlie.SE2:
        k_c, k_u, k_h = jax.random.split(key, 3)
        return from_vector(_sample_free(n, self.spec, self.counts, k_c, k_u, k_h))


def global_injector(spec, free: Bool[ArrayLike, "nx ny"]) -> Callable:
    """Random-particle source for augmented MCL (``ParticleFilter(injector=...)``):
    returns ``injector(key, n)``, ``n`` SE(2) poses drawn exactly like
    :func:`init_global` (uniform over the free cells of ``free`` on the 2-D grid
    ``spec``, uniform heading). An ``equinox.Module``, so the mask is traced data.

    Raises:
        ValueError: as :func:`init_global` for a bad grid or mask.
    """
    return _GlobalInjector(spec, _free_cell_counts(spec, free))


def estimate(state: ParticleState, best_fraction: float = 0.1) -> Pose:
    """Pose estimate: weighted mean of the ``ceil(best_fraction * n)`` particles with the
    largest weights (Sec. 12.4.3 uses the best 10 %; ``best_fraction=1`` is the plain
    weighted mean), circular mean for angles. With KLD-sampling ``n`` is the number of
    active particles ``state.n_active`` (inactive ones have weight 0)."""
    if not 0 < best_fraction <= 1:
        raise ValueError(f"best_fraction must lie in (0, 1], got {best_fraction!r}")
    _check_particle_count(state.log_weights, "state")
    n = state.n
    k = max(1, math.ceil(best_fraction * n))
    top_lw, idx = jax.lax.top_k(state.log_weights, k)
    w = jnp.exp(top_lw - jnp.max(top_lw))
    n_act = state.n_active
    k_act = jnp.maximum(1, jnp.ceil(best_fraction * n_act)).astype(jnp.int32)
    k_act = jnp.where(n_act >= n, k, k_act)
    w = jnp.where(jnp.arange(k) < k_act, w, 0.0)
    return weighted_mean(take(state.particles, idx), w)
