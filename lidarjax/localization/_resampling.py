"""Particle weights and resampling (Thrun et al., Probabilistic Robotics ch. 4):
normalised log-weights, the effective sample size, systematic / stratified / multinomial
resampling over an active prefix of the particles, and KLD-sampling (Fox 2003): the
adaptive particle count from the number of occupied histogram bins."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray

from ._poses import Pose, to_vector

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
