"""A functional particle filter over SE(2) / SE(3) poses (Thrun et al., Probabilistic
Robotics ch. 4 and 8; dissertation section 12.4.3).

Everything is a pure function of a :class:`ParticleState` (particles, normalised
log-weights, PRNG key). One :meth:`ParticleFilter.step` is: motion update (sample from the
motion model), measurement update (add the measurement log-likelihood of every particle),
pose estimate, and resampling when the effective sample size ``n_eff = 1 / sum w_i^2``
falls below ``resample_fraction * n``. :meth:`ParticleFilter.run` is one ``lax.scan`` over
a sequence of controls and measurements, so a whole log compiles once and runs without
host round-trips; ``jax.vmap`` over independent runs (keys / initial states) works.

Optional extensions, all with static shapes (off by default, so the plain filter is
unchanged):

* Augmented MCL (Thrun et al. Table 8.3): random-particle injection driven by short- and
  long-term averages of the measurement likelihood (``alpha_slow`` / ``alpha_fast`` and
  an ``injector`` such as :func:`global_injector`), for recovery from kidnapping.
* KLD-sampling (Fox 2003): an adaptive number ``n_active`` of live particles chosen at
  each resampling from the number of occupied histogram bins (``kld=True``); see
  :func:`kld_particle_count` and :func:`count_occupied_bins`.
* A proposal hook: a motion model with a ``propose`` method samples the new particles
  with the measurement in view and returns importance corrections (see
  :meth:`ParticleFilter.step`).
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
from ..raytrace import GridSpec
from ._poses import Pose, dof, from_vector, take, to_vector, weighted_mean

ResamplerName = Literal["systematic", "stratified", "multinomial"]


# --------------------------------------------------------------------------------------
# Weights and resampling
# --------------------------------------------------------------------------------------


def _check_particle_count(log_weights, name: str) -> int:
    """The number of particles ``n`` (last axis); ``ValueError`` naming ``name`` if 0."""
    shape = jnp.shape(log_weights)
    if len(shape) == 0 or shape[-1] == 0:
        raise ValueError(
            f"{name} has no particles (log-weights of shape {tuple(shape)}); a particle "
            "filter needs at least one"
        )
    return int(shape[-1])


def normalize_log_weights(log_weights: Float[Array, "*b n"]) -> Float[Array, "*b n"]:
    """Log-weights shifted so that ``sum exp = 1`` (over the last axis).

    Special cases, each reported by :class:`StepInfo` when it happens in a filter step:

    - some weight is ``+inf`` (a particle with infinite likelihood, no NaN): the ``k``
      particles at ``+inf`` share the weight equally (log-weight ``-log k``), all others
      get weight 0 (the limit of the normalised weights as those likelihoods grow);
    - every weight is zero (all ``-inf``, e.g. every particle got likelihood 0) or any is
      NaN: uniform weights ``-log n``, so the filter never produces NaN weights.

    Raises:
        ValueError: ``log_weights`` has no particles (last axis of length 0).
    """
    n = _check_particle_count(log_weights, "log_weights")
    nan = jnp.any(jnp.isnan(log_weights), axis=-1, keepdims=True)
    at_inf = log_weights == jnp.inf
    n_inf = jnp.sum(at_inf, axis=-1, keepdims=True)
    has_inf = n_inf > 0
    lse = jax.nn.logsumexp(jnp.where(has_inf, 0.0, log_weights), axis=-1, keepdims=True)
    ok = jnp.isfinite(lse) & ~nan
    finite = log_weights - jnp.where(ok, lse, 0.0)
    shared = jnp.where(at_inf, -jnp.log(jnp.maximum(n_inf, 1).astype(log_weights.dtype)), -jnp.inf)
    out = jnp.where(has_inf, shared, jnp.where(ok, finite, -math.log(n)))
    return jnp.where(nan, -math.log(n), out).astype(log_weights.dtype)


def effective_sample_size(log_weights: Float[Array, "*b n"]) -> Float[Array, "*b"]:
    """``n_eff = 1 / sum_i w_i^2`` of the weights as :func:`normalize_log_weights` makes
    them (between 1 and n; ``k`` when ``k`` particles share the weight after ``+inf``
    likelihoods, ``n`` after a reset to uniform)."""
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


def _draw_count(n: int, n_active):
    """``None`` (draw ``n``) or the int32 number of draws ``clip(n_active, 1, n)``."""
    if n_active is None:
        return None
    return jnp.clip(jnp.asarray(n_active, jnp.int32), 1, n)


def _fill_inactive(idx, m):
    """Slots ``i >= m`` get the ancestors of slots ``i mod m`` (valid poses that the
    caller gives log-weight ``-inf``); the first ``m`` slots are unchanged."""
    if m is None:
        return idx
    i = jnp.arange(idx.shape[0])
    return jnp.where(i < m, idx, idx[i % m])


def systematic_resample(
    log_weights: Float[Array, " n"], *, key: PRNGKeyArray, n_active=None
) -> Int[Array, " n"]:
    """Low-variance (systematic) resampling, Thrun et al. Table 4.4: one uniform offset
    ``u ~ U[0, 1)`` and the comb ``(i + u) / m``, ``i < m``. Returns ``[n]`` ancestor
    indices.

    ``n_active`` (optional int scalar, may be traced; default ``n``): draw exactly
    ``m = clip(n_active, 1, n)`` ancestors with the comb of ``m`` teeth, so each particle
    gets ``m w_i`` offspring in expectation. Slots ``i >= m`` are filler (copies of slot
    ``i mod m``) for the caller to give log-weight ``-inf``. (Drawing ``n`` and keeping the
    first ``m`` would be biased: the output is ordered by ancestor.)"""
    n = log_weights.shape[0]
    m = _draw_count(n, n_active)
    u = jax.random.uniform(key, (), dtype=log_weights.dtype)
    denom = n if m is None else m.astype(log_weights.dtype)
    positions = (jnp.arange(n, dtype=log_weights.dtype) + u) / denom
    return _fill_inactive(_inverse_cdf(log_weights, positions), m)


def stratified_resample(
    log_weights: Float[Array, " n"], *, key: PRNGKeyArray, n_active=None
) -> Int[Array, " n"]:
    """Stratified resampling: one uniform draw in each stratum ``[i/m, (i+1)/m)``,
    ``i < m`` (``m = n``, or ``clip(n_active, 1, n)`` as in :func:`systematic_resample`;
    slots ``>= m`` are filler)."""
    n = log_weights.shape[0]
    m = _draw_count(n, n_active)
    u = jax.random.uniform(key, (n,), dtype=log_weights.dtype)
    denom = n if m is None else m.astype(log_weights.dtype)
    positions = (jnp.arange(n, dtype=log_weights.dtype) + u) / denom
    return _fill_inactive(_inverse_cdf(log_weights, positions), m)


def multinomial_resample(
    log_weights: Float[Array, " n"], *, key: PRNGKeyArray, n_active=None
) -> Int[Array, " n"]:
    """Multinomial resampling: ``m`` independent draws from the weights (as the inverse
    CDF of ``m`` sorted uniforms, ``O(n log n)`` time and ``O(n)`` memory); ``m = n``, or
    ``clip(n_active, 1, n)`` as in :func:`systematic_resample` (slots ``>= m`` are
    filler)."""
    n = log_weights.shape[0]
    m = _draw_count(n, n_active)
    u = jax.random.uniform(key, (n,), dtype=log_weights.dtype)
    if m is not None:  # the first m uniforms are iid; the rest sort to the end
        u = jnp.where(jnp.arange(n) < m, u, 2.0)
    return _fill_inactive(_inverse_cdf(log_weights, jnp.sort(u)), m)


RESAMPLERS: dict[str, Callable] = {
    "systematic": systematic_resample,
    "stratified": stratified_resample,
    "multinomial": multinomial_resample,
}


# --------------------------------------------------------------------------------------
# KLD-sampling (Fox 2003)
# --------------------------------------------------------------------------------------


def _check_open_unit(name: str, x) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a number in (0, 1), got {x!r}")
    if not 0 < float(x) < 1:
        raise ValueError(f"{name} must lie in (0, 1), got {x!r}")
    return float(x)


def kld_particle_count(
    k: Int[ArrayLike, "*b"], epsilon: float = 0.05, delta: float = 0.01
) -> Int[Array, "*b"]:
    """Number of particles KLD-sampling needs for ``k`` occupied bins (Fox 2003, eq. 7):
    with probability ``1 - delta`` the Kullback-Leibler divergence between the sample
    histogram and the true (binned) posterior stays below ``epsilon`` (nats) when

    ``n = (k-1)/(2 epsilon) * (1 - 2/(9(k-1)) + sqrt(2/(9(k-1))) z_{1-delta})^3``,

    the Wilson-Hilferty approximation of ``chi2_{1-delta}(k-1) / (2 epsilon)`` (``z`` the
    standard normal ``1 - delta`` quantile; relative error below 1 % for ``k >= 10``).

    Args:
        k: integer array (may be traced) of occupied-bin counts.
        epsilon: KL bound (static, in (0, 1)).
        delta: failure probability (static, in (0, 1)).

    Returns:
        int32 array of ``k``'s shape: ``ceil(n)``, at least 1 (``1`` for ``k <= 1``).
    """
    epsilon = _check_open_unit("epsilon", epsilon)
    delta = _check_open_unit("delta", delta)
    kf = jnp.asarray(k).astype(jnp.result_type(float))
    z = jax.scipy.special.ndtri(jnp.asarray(1.0 - delta, kf.dtype))
    km1 = jnp.maximum(kf - 1.0, 1.0)
    a = 2.0 / (9.0 * km1)
    n = km1 / (2.0 * epsilon) * (1.0 - a + jnp.sqrt(a) * z) ** 3
    n = jnp.clip(jnp.ceil(n), 1.0, 2.0**30)  # large-k overflow guard for int32
    return jnp.where(kf <= 1, 1, n.astype(jnp.int32))


def _angle_dims(k: int) -> tuple[int, ...]:
    return (2,) if k == 3 else (3, 4, 5)


def _bin_keys(v: Float[Array, "n k"], bin_size) -> Int[Array, "n k"]:
    """int32 bin index ``floor(v_j * (1 / bin_size_j))`` of each pose-vector component,
    angles first wrapped to ``[-pi, pi)`` (so ``pi`` and ``-pi`` share a bin). The
    reciprocal is explicit because XLA may rewrite a division by a constant that way,
    which would move values on a bin edge (e.g. ``-pi`` with 30-degree bins)."""
    k = v.shape[-1]
    ang = np.zeros(k, bool)
    ang[list(_angle_dims(k))] = True
    v = jnp.where(ang, jnp.mod(v + jnp.pi, 2 * jnp.pi) - jnp.pi, v)
    inv = np.asarray([1.0 / float(b) for b in bin_size])
    b = jnp.floor(v * jnp.asarray(inv, v.dtype))
    b = jnp.clip(jnp.nan_to_num(b, nan=0.0), -(2.0**30), 2.0**30)
    return b.astype(jnp.int32)


def _group_starts(bins: Int[Array, "n k"], *minor, major=None):
    """Lexicographic sort of the rows of ``bins`` (optionally after a ``major`` key and
    before ``minor`` tie-breakers): the sort order and, per sorted row, whether it
    starts a new bin (differs from the previous row in some bin index)."""
    cols = [*minor, *(bins[:, j] for j in range(bins.shape[1] - 1, -1, -1))]
    if major is not None:
        cols.append(major)
    order = jnp.lexsort(cols)  # the last key is the primary one
    sb = bins[order]
    new = jnp.concatenate([jnp.ones(1, bool), jnp.any(sb[1:] != sb[:-1], axis=-1)])
    return order, new


def _check_bin_size(bin_size, k: int) -> tuple[float, ...]:
    bs = tuple(float(b) for b in np.asarray(bin_size, np.float64).reshape(-1))
    if len(bs) != k or not all(np.isfinite(b) and b > 0 for b in bs):
        raise ValueError(
            f"bin_size must be {k} positive finite numbers (one per pose-vector "
            f"component), got {bin_size!r}"
        )
    return bs


def count_occupied_bins(
    poses: Pose | Float[Array, "n k"],
    active_mask: Bool[ArrayLike, " n"] | None,
    bin_size,
) -> Int[Array, ""]:
    """Number of distinct histogram bins occupied by the active particles (the ``k`` of
    KLD-sampling).

    The bin of a pose vector ``v`` is ``floor(v_j * (1 / bin_size_j))`` per component,
    angles wrapped to ``[-pi, pi)`` first. Static shapes: one lexicographic sort of the integer
    bin indices (inactive rows last) and a count of the rows that differ from their
    predecessor; ``O(n log n)`` time, ``O(n k)`` memory.

    Args:
        poses: ``[n]`` batched ``jaxlie.SE2`` / ``jaxlie.SE3``, or ``[n k]`` pose vectors
            (``k = 3``: ``(x, y, theta)``; ``k = 6``: ``(x, y, z, roll, pitch, yaw)``; m, rad).
        active_mask: ``[n]`` bool, the particles to count (``None``: all).
        bin_size: ``k`` bin edge lengths (m, rad), e.g. ``(0.5, 0.5, radians(10))``.

    Returns:
        int32 scalar, ``0`` when no particle is active.
    """
    v = poses if isinstance(poses, jnp.ndarray | np.ndarray) else to_vector(poses)
    v = jnp.asarray(v, jnp.result_type(float))
    if v.ndim != 2 or v.shape[1] not in (3, 6):
        raise ValueError(f"poses must be [n] SE2/SE3 poses or [n 3|6] vectors, got {v.shape}")
    n, k = v.shape
    bins = _bin_keys(v, _check_bin_size(bin_size, k))
    active = jnp.ones(n, bool) if active_mask is None else jnp.asarray(active_mask, bool)
    if active.shape != (n,):
        raise ValueError(f"active_mask must have shape ({n},), got {active.shape}")
    order, new = _group_starts(bins, major=~active)  # active rows first
    return jnp.sum(new & active[order]).astype(jnp.int32)


def _kld_sequential_count(
    bins: Int[Array, "n k"], epsilon: float, delta: float, n_min: int
) -> Int[Array, ""]:
    """Fox's stopping rule on ``n`` iid candidates (in draw order) with bin indices
    ``bins``: the smallest ``m`` with ``m >= kld_particle_count(k_m)`` and ``m >= n_min``,
    ``k_m`` the number of bins occupied by the first ``m`` candidates (``n`` if none)."""
    n = bins.shape[0]
    pos = jnp.arange(n)
    order, new = _group_starts(bins, pos)  # ties in draw order: first occurrence first
    first = jnp.zeros(n, bool).at[order].set(new)
    k_m = jnp.cumsum(first.astype(jnp.int32))
    m = pos + 1
    ok = (m >= kld_particle_count(k_m, epsilon, delta)) & (m >= n_min)
    return jnp.where(jnp.any(ok), jnp.argmax(ok) + 1, n).astype(jnp.int32)


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
    total = eqx.error_if(total, total <= 0, "free has no True cell to sample from")
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
        injected: int32, number of resampled particles replaced by injector samples
            (augmented MCL; 0 otherwise).
        n_active: int32, number of live particles after the step (KLD-sampling; ``n``
            otherwise).
        bad_control: the control had a NaN or infinite entry (only possible under
            ``jit`` / ``lax.scan``; concrete controls raise ``ValueError``). The step then
            left the particles and weights as they were (no motion, no measurement
            update, no resampling); ``estimate`` and ``n_eff`` describe those kept
            particles.
        infinite_likelihood: some live particle had log-likelihood ``+inf`` (and none
            NaN): the ``k`` particles at ``+inf`` share the weight equally, the others
            get weight 0, so ``n_eff = k`` (see :func:`normalize_log_weights`).
    """

    estimate: Pose
    n_eff: Float[Array, ""]
    resampled: Bool[Array, ""]
    degenerate: Bool[Array, ""]
    injected: Int[Array, ""]
    n_active: Int[Array, ""]
    bad_control: Bool[Array, ""] = eqx.field(default_factory=lambda: jnp.zeros((), bool))
    infinite_likelihood: Bool[Array, ""] = eqx.field(default_factory=lambda: jnp.zeros((), bool))


def _control_leaves(control) -> list:
    """The floating-point leaves of a control pytree (integer leaves are always finite)."""
    return [x for x in jax.tree.leaves(control) if jnp.issubdtype(jnp.result_type(x), jnp.inexact)]


def _check_controls_concrete(control, name: str, per_step: bool) -> None:
    """``ValueError`` naming ``name`` if every leaf of ``control`` is concrete and one has a
    NaN or infinite entry (no-op for traced controls: no host sync inside ``scan``)."""
    leaves = _control_leaves(control)
    if not leaves or not all(is_concrete(x) for x in leaves):
        return
    for x in leaves:
        a = np.asarray(x)
        bad = ~np.isfinite(a)
        if np.any(bad):
            first = tuple(int(i) for i in np.argwhere(bad)[0])
            where = f" (step {first[0]})" if per_step and first else ""
            raise ValueError(
                f"{name} must be finite (NaN or infinite odometry?); found {a[first]!r} at "
                f"index {first}{where}"
            )


def _bad_control(control) -> Bool[Array, ""]:
    """Traced test: does any floating-point leaf of ``control`` hold a NaN or inf?"""
    bad = jnp.zeros((), bool)
    for x in _control_leaves(control):
        bad = bad | jnp.any(~jnp.isfinite(x))
    return bad


def _log_interp(log_old, log_new, rate):
    """``log((1 - rate) exp(log_old) + rate exp(log_new))`` for ``rate`` in [0, 1]
    without leaving log space (``rate = 1`` gives ``log_new``, ``0`` gives ``log_old``)."""
    a = jnp.where(rate < 1, jnp.log1p(-jnp.minimum(rate, 1.0)) + log_old, -jnp.inf)
    b = jnp.where(rate > 0, jnp.log(jnp.maximum(rate, 0.0)) + log_new, -jnp.inf)
    return jnp.logaddexp(a, b)


def _average_rate(alpha: float, t, dtype):
    """Rate of the ``t``-th (1-based) update of a bias-corrected exponential average:
    ``alpha / (1 - (1 - alpha)^t)`` (``1`` at ``t = 1``, tending to ``alpha``; ``1/t``,
    the running mean, for ``alpha = 0``)."""
    t = jnp.asarray(t, dtype)
    if alpha == 0:
        return 1.0 / t
    if alpha == 1:
        return jnp.ones_like(t)
    return alpha / -jnp.expm1(t * math.log1p(-alpha))


def _where_tree(mask, a, b):
    """Per-particle ``where(mask, a, b)`` over the leaves of two ``[n]`` pose batches."""

    def sel(x, y):
        return jnp.where(mask.reshape(mask.shape + (1,) * (y.ndim - 1)), x.astype(y.dtype), y)

    return jax.tree.map(sel, a, b)


def _as_tuple(b):
    """A hashable tuple of floats for a static field (left as is if not convertible; the
    filter's check then reports it)."""
    try:
        return tuple(float(x) for x in np.asarray(b, np.float64).reshape(-1))
    except (TypeError, ValueError):
        return b


class ParticleFilter(eqx.Module):
    """Particle filter with pluggable, pure motion and measurement models.

    Attributes:
        motion: ``motion(particles [n], control, *, key) -> particles [n]``, e.g.
            :class:`OdometryMotionModel`. If it also has a method
            ``propose(particles, control, z, *, key) -> (particles [n], log_correction [n])``
            that is used on measurement-update steps (see :meth:`step`).
        measurement: ``measurement(particles [n], z) -> [n]`` log-likelihoods (``-inf``
            allowed), e.g. :class:`~lidarjax.localization.ScanModel`. Use an
            ``equinox.Module`` so its arrays (the map) are traced, not baked in.
        resample_fraction: resample when ``n_eff < resample_fraction * n``.
        resampler: ``"systematic"`` (low variance, default), ``"stratified"`` or
            ``"multinomial"``.
        best_fraction: fraction of highest-weight particles averaged for the estimate.
        alpha_slow, alpha_fast: augmented MCL (Thrun et al. Table 8.3) decay rates of the
            long- and short-term averages of the measurement likelihood; ``0`` and ``0``
            (default) turn it off, otherwise ``0 <= alpha_slow < alpha_fast <= 1``.
        injector: ``injector(key, n) -> [n] poses`` of the particles' group, the source
            of random particles for augmented MCL (e.g. :func:`global_injector`).
        kld: KLD-sampling (Fox 2003): adapt the number of live particles at each
            resampling.
        kld_epsilon, kld_delta: KL bound (nats) and failure probability, both in (0, 1).
        kld_bin_size: bin edge lengths per pose-vector component (m, rad): 3 for SE(2),
            6 for SE(3).
        n_min: lower bound on the number of live particles with KLD-sampling.

    Augmented MCL. On every measurement update the weighted mean likelihood
    ``w_avg = sum_i w_i p(z | x_i)`` (``w`` the previous normalised weights) updates the
    averages ``w_slow += a_slow (w_avg - w_slow)`` and ``w_fast += a_fast (w_avg -
    w_fast)``, kept in log space (``logaddexp``) because scan log-likelihoods of hundreds
    of nats underflow in linear space. The averages are bias-corrected exponential means
    (Thrun's recursion started at 0 and divided by ``1 - (1 - a)^t`` after ``t``
    updates), so both equal ``w_avg`` after the first update and the first step cannot
    inject spuriously. The injection probability is ``p = max(0, 1 - w_fast / w_slow)``.
    An update step resamples when ``n_eff`` is low *or* ``p > 0`` (Thrun resamples every
    step; the ``n_eff`` test alone would rarely fire after a kidnapping, when all
    likelihoods are uniformly small), and every resampled live particle is then
    replaced, with probability ``p``, by an injector sample (``n`` candidates are drawn
    and selected with a Bernoulli mask, so shapes stay static).

    KLD-sampling. The state's ``n`` slots are the maximum; ``state.n_active`` leading
    ones are live, the others have log-weight ``-inf`` and are ignored by the estimate,
    ``n_eff``, the resampling threshold (``resample_fraction * n_active``) and the
    resampler. At a resampling, ``n`` iid candidates are drawn from the weights, and
    Fox's rule picks the smallest ``m`` with ``m >= kld_particle_count(k_m)`` and
    ``m >= n_min`` (``k_m`` the bins occupied by the first ``m`` candidates; ``n`` if
    none); then exactly ``n_active = m`` ancestors are drawn afresh with the chosen
    resampler (unbiased: ``m w_i`` offspring in expectation). The bins are those of the
    posterior particles (after motion and measurement). With static shapes the motion and
    measurement models still run on all ``n`` slots, so ``n_active`` reports how many
    particles the posterior needs; it does not save compute in JAX.
    """

    motion: Callable
    measurement: Callable
    resample_fraction: float = eqx.field(static=True, default=0.5)
    resampler: str = eqx.field(static=True, default="systematic")
    best_fraction: float = eqx.field(static=True, default=0.1)
    alpha_slow: float = eqx.field(static=True, default=0.0)
    alpha_fast: float = eqx.field(static=True, default=0.0)
    injector: Callable | None = None
    kld: bool = eqx.field(static=True, default=False)
    kld_epsilon: float = eqx.field(static=True, default=0.05)
    kld_delta: float = eqx.field(static=True, default=0.01)
    kld_bin_size: tuple = eqx.field(
        static=True, default=(0.5, 0.5, math.radians(10)), converter=lambda b: _as_tuple(b)
    )
    n_min: int = eqx.field(static=True, default=10)

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
        for name in ("alpha_slow", "alpha_fast"):
            a = getattr(self, name)
            if isinstance(a, bool) or not isinstance(a, (int, float)) or not 0 <= a <= 1:
                raise ValueError(f"{name} must be a number in [0, 1], got {a!r}")
        if self.augmented:
            if not self.alpha_slow < self.alpha_fast:
                raise ValueError(
                    f"alpha_slow must be < alpha_fast for augmented MCL, got "
                    f"alpha_slow={self.alpha_slow!r}, alpha_fast={self.alpha_fast!r}"
                )
            if self.injector is None or not callable(self.injector):
                raise ValueError(
                    "injector must be a callable (key, n) -> poses when "
                    "alpha_slow / alpha_fast are set"
                )
        if not isinstance(self.kld, bool):
            raise ValueError(f"kld must be a bool, got {self.kld!r}")
        _check_open_unit("kld_epsilon", self.kld_epsilon)
        _check_open_unit("kld_delta", self.kld_delta)
        if isinstance(self.n_min, bool) or not isinstance(self.n_min, (int, np.integer)):
            raise ValueError(f"n_min must be a positive int, got {self.n_min!r}")
        if self.n_min <= 0:
            raise ValueError(f"n_min must be a positive int, got {self.n_min!r}")
        try:
            bs = np.asarray(self.kld_bin_size, np.float64)
        except (TypeError, ValueError):
            bs = None
        if (
            bs is None
            or bs.ndim != 1
            or bs.size not in (3, 6)
            or not np.all(np.isfinite(bs) & (bs > 0))
        ):
            raise ValueError(
                "kld_bin_size must be 3 (SE2) or 6 (SE3) positive finite bin sizes, got "
                f"{self.kld_bin_size!r}"
            )
        group = getattr(self.motion, "group", None)
        if group in (jaxlie.SE2, jaxlie.SE3) and self.kld and bs.size != dof(group):
            raise ValueError(
                f"kld_bin_size must have {dof(group)} entries for {group.__name__}, got "
                f"{self.kld_bin_size!r}"
            )

    @property
    def augmented(self) -> bool:
        """Whether augmented MCL (random-particle injection) is on."""
        return self.alpha_slow != 0 or self.alpha_fast != 0

    def _predict(self, state: ParticleState, control, z, update, key):
        """Motion update and log-likelihood (plus importance correction) per particle."""
        dtype = state.log_weights.dtype
        if not hasattr(self.motion, "propose"):
            particles = self.motion(state.particles, control, key=key)
            ll = jax.lax.cond(
                update,
                lambda: jnp.asarray(self.measurement(particles, z), dtype),
                lambda: jnp.zeros_like(state.log_weights),
            )
            return particles, ll

        def proposed():
            p, log_corr = self.motion.propose(state.particles, control, z, key=key)
            ll = jnp.asarray(self.measurement(p, z), dtype) + jnp.asarray(log_corr, dtype)
            return jax.tree.map(lambda x, y: x.astype(y.dtype), p, state.particles), ll

        def prior():
            p = self.motion(state.particles, control, key=key)
            p = jax.tree.map(lambda x, y: x.astype(y.dtype), p, state.particles)
            return p, jnp.zeros_like(state.log_weights)

        return jax.lax.cond(update, proposed, prior)

    def step(
        self, state: ParticleState, control, z, update: bool | Bool[Array, ""] = True
    ) -> tuple[ParticleState, StepInfo]:
        """One filter step: motion update with ``control``, measurement update with ``z``
        (skipped where ``update`` is False), estimate, conditional resampling (with
        random-particle injection and an adaptive particle count when configured; see
        the class docstring).

        Proposal hook: if ``self.motion`` has ``propose(particles, control, z, *, key)
        -> (new_particles [n], log_correction [n])``, update steps take the new particles
        from it and add ``log_correction = log p(x_new | x_prev, u) - log q(x_new | x_prev,
        u, z)`` (nats; prior minus proposal density of each new particle) to the
        measurement log-likelihood before normalising. The weights then stay
        ``w_prev * p(z | x) p(x | x_prev, u) / q(x | ...)``, so the filter remains a valid
        importance sampler of the same posterior for any proposal ``q`` whose support
        covers the prior's. Steps without an update use the plain ``motion(...)``.

        Bad input: a concrete ``control`` with a NaN or infinite entry raises
        ``ValueError``; a traced one (under ``jit`` / in :meth:`run`'s ``scan``) makes the
        step keep the previous particles and weights (no motion, measurement update or
        resampling) and sets ``StepInfo.bad_control``. Measurement log-likelihoods that are
        NaN or all ``-inf`` reset the weights to uniform (``StepInfo.degenerate``);
        ``+inf`` ones share the weight among those particles
        (``StepInfo.infinite_likelihood``). A state with no particles raises
        ``ValueError``.
        """
        n = _check_particle_count(state.log_weights, "state")
        _check_controls_concrete(control, "control", per_step=False)
        key, k_motion, k_resample = jax.random.split(state.key, 3)
        if self.kld or self.augmented:
            k_resample, k_cand, k_inject = jax.random.split(k_resample, 3)
        dtype = state.log_weights.dtype
        # A NaN/inf control (traced): no motion, no measurement update, no resampling;
        # the motion model sees zeros so that nothing downstream is computed from NaN.
        bad_control = _bad_control(control)
        safe_control = jax.tree.map(
            lambda x: (
                jnp.where(bad_control, jnp.zeros_like(x), x)
                if jnp.issubdtype(jnp.result_type(x), jnp.inexact)
                else x
            ),
            control,
        )
        update = jnp.asarray(update) & ~bad_control
        particles, ll = self._predict(state, safe_control, z, update, k_motion)
        particles = _where_tree(jnp.broadcast_to(bad_control, (n,)), state.particles, particles)

        n_active = jnp.asarray(state.n_active, jnp.int32)
        slots = jnp.arange(n)
        raw = state.log_weights + ll
        if self.kld:
            active = slots < n_active
            raw = jnp.where(active, raw, -jnp.inf)
        nan = jnp.any(jnp.isnan(raw))
        degenerate = ~jnp.any(raw > -jnp.inf) | nan
        infinite = jnp.any(raw == jnp.inf) & ~nan
        log_weights = normalize_log_weights(raw)
        if self.kld:  # the uniform fallback of normalize_log_weights: live slots only
            uniform = jnp.where(active, -jnp.log(n_active.astype(dtype)), -jnp.inf)
            log_weights = jnp.where(degenerate, uniform, log_weights)
        log_weights = jnp.where(bad_control, state.log_weights, log_weights)

        # augmented MCL: bias-corrected exponential averages of w_avg in log space
        log_w_slow, log_w_fast = state.log_w_slow, state.log_w_fast
        n_updates = state.n_updates
        p_inject = jnp.zeros((), dtype)
        if self.augmented:
            log_w_avg = jax.nn.logsumexp(raw)  # log sum_i w_i p(z | x_i) (w normalised)
            fold = update & ~jnp.isnan(log_w_avg) & (log_w_avg < jnp.inf)
            t = n_updates + 1
            new_slow = _log_interp(log_w_slow, log_w_avg, _average_rate(self.alpha_slow, t, dtype))
            new_fast = _log_interp(log_w_fast, log_w_avg, _average_rate(self.alpha_fast, t, dtype))
            log_w_slow = jnp.where(fold, new_slow, log_w_slow).astype(dtype)
            log_w_fast = jnp.where(fold, new_fast, log_w_fast).astype(dtype)
            n_updates = jnp.where(fold, t, n_updates).astype(jnp.int32)
            diff = log_w_fast - log_w_slow  # NaN when both are -inf: no information
            p_inject = jnp.where(
                jnp.isnan(diff), 0.0, jnp.clip(-jnp.expm1(jnp.minimum(diff, 0.0)), 0.0, 1.0)
            ).astype(dtype)

        mid = ParticleState(particles, log_weights, key, n_active=n_active)
        est = estimate(mid, self.best_fraction)
        n_eff = effective_sample_size(log_weights)
        if self.kld:
            resample = update & (n_eff < self.resample_fraction * n_active.astype(dtype))
        else:
            resample = update & (n_eff < self.resample_fraction * n)
        if self.augmented:
            resample = resample | (update & (p_inject > 0))

        resample_fn = RESAMPLERS[self.resampler]
        if self.kld:
            u = jax.random.uniform(k_cand, (n,), dtype=dtype)
            cand = _inverse_cdf(log_weights, u)  # n iid draws, in draw order
            v = to_vector(particles)
            if v.shape[-1] != len(self.kld_bin_size):
                raise ValueError(
                    f"kld_bin_size must have {v.shape[-1]} entries for these particles, "
                    f"got {len(self.kld_bin_size)}"
                )
            bins = _bin_keys(v, self.kld_bin_size)[cand]
            m = _kld_sequential_count(bins, self.kld_epsilon, self.kld_delta, self.n_min)
            idx = resample_fn(log_weights, key=k_resample, n_active=m)
            n_next = jnp.where(resample, m, n_active).astype(jnp.int32)
        else:
            idx = resample_fn(log_weights, key=k_resample)
            n_next = jnp.where(resample, n, n_active).astype(jnp.int32)
        idx = jnp.where(resample, idx, slots)
        particles = take(particles, idx)
        live = slots < n_next

        injected = jnp.zeros((), jnp.int32)
        if self.augmented:
            k_draw, k_coin = jax.random.split(k_inject)
            fresh = self.injector(k_draw, n)
            if type(fresh) is not type(particles) or (
                fresh.parameters().shape != particles.parameters().shape
            ):
                raise ValueError(
                    f"injector must return [{n}] {type(particles).__name__} poses, got "
                    f"{type(fresh).__name__} {getattr(fresh.parameters(), 'shape', None)}"
                )
            coin = jax.random.uniform(k_coin, (n,), dtype=dtype) < p_inject
            swap = resample & live & coin
            particles = _where_tree(swap, fresh, particles)
            injected = jnp.sum(swap).astype(jnp.int32)

        if self.kld:
            reset = jnp.where(live, -jnp.log(n_next.astype(dtype)), -jnp.inf)
        else:
            reset = -math.log(n)
        log_weights = jnp.where(resample, reset, log_weights)
        info = StepInfo(
            est,
            n_eff,
            resample,
            degenerate & update,
            injected,
            n_next,
            bad_control=bad_control,
            infinite_likelihood=infinite & update,
        )
        new_state = ParticleState(
            particles,
            log_weights,
            key,
            n_active=n_next,
            log_w_slow=log_w_slow,
            log_w_fast=log_w_fast,
            n_updates=n_updates,
        )
        return new_state, info

    def run(
        self, state: ParticleState, controls, measurements, updates=None
    ) -> tuple[ParticleState, StepInfo]:
        """Filter a whole sequence with one ``lax.scan`` (jit-compiled).

        Args:
            state: initial state (at least one particle).
            controls: pytree with leading axis ``[T]`` (e.g. ``[T k]`` relative odometry).
                Concrete controls must be finite (checked once, before the scan); traced
                ones with a NaN/inf step are flagged per step (``StepInfo.bad_control``).
            measurements: pytree with leading axis ``[T]`` (e.g. ``[T b]`` ranges).
            updates: optional ``[T]`` bool, measurement update on/off per step.

        Returns:
            The final state and the stacked ``[T]`` :class:`StepInfo`.

        Raises:
            ValueError: ``state`` has no particles, or a concrete control is NaN/inf
                (the message names ``controls`` and the step).
        """
        _check_particle_count(state.log_weights, "state")
        _check_controls_concrete(controls, "controls", per_step=True)
        return self._run(state, controls, measurements, updates)

    @eqx.filter_jit
    def _run(self, state: ParticleState, controls, measurements, updates=None):
        n_steps = jax.tree.leaves(controls)[0].shape[0]
        if updates is None:
            updates = jnp.ones(n_steps, bool)

        def body(s, xs):
            c, z, u = xs
            return self.step(s, c, z, u)

        return jax.lax.scan(body, state, (controls, measurements, updates))
