"""Resolution-aware smoothing of grid statistics: kernel estimates of the per-cell rates.

A maximum-likelihood grid map puts all the evidence of a wall into the one or two cells
the mapping rays happened to end in. At localization time a pose error of one cell then
moves a beam's end point into a cell that was never hit (``lambda = 0``, an impossible
reading) and the scan likelihood falls by tens of nats per beam: on the shared CARMEN logs
the decay-rate scan likelihood of 30 beams drops by 80-100 nats for a 0.1 m shift (the
likelihood field of the endpoint model by 2-6 nats), so a particle filter only keeps
particles within about one cell of the truth.

:func:`smooth_stats` replaces the counts of every cell by a Gaussian-weighted sum over its
neighbours (a kernel estimate, as in kernel density / kernel regression): hits, misses and
travelled lengths are smoothed with the same kernel, so any grid model built from the
result (``decay_rate_map`` gives ``lambda_i = sum_j w_ij H_j / sum_j w_ij R_j``, the
full posteriors use the smoothed counts as evidence) is the model of a map whose
resolution is the kernel width rather than the cell size. The kernel weights of a cell sum
to 1, so the total evidence is preserved (up to what leaks out across the grid border).

:func:`blur` is the same kernel with the border cells extended instead of zero (a constant
map stays constant), for blurring a map's rates, e.g. by
:class:`~lidarjax.maps.SmoothDecayRateField`.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..raytrace import GridStats

__all__ = ["blur", "gaussian_kernel_1d", "smooth_stats", "smooth_cells"]


def gaussian_kernel_1d(sigma_cells: float, truncate: float = 3.0) -> np.ndarray:
    """Normalised 1-D Gaussian weights ``[2h + 1]`` (``h = ceil(truncate * sigma)``), sum 1.

    Args:
        sigma_cells: standard deviation in cells (> 0).
        truncate: half-width of the kernel in standard deviations (> 0).
    """
    if not (np.isfinite(sigma_cells) and sigma_cells > 0):
        raise ValueError(f"sigma_cells must be finite and > 0, got {sigma_cells!r}")
    if not (np.isfinite(truncate) and truncate > 0):
        raise ValueError(f"truncate must be finite and > 0, got {truncate!r}")
    half = max(1, math.ceil(truncate * sigma_cells))
    x = np.arange(-half, half + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma_cells) ** 2)
    return k / k.sum()


def smooth_cells(
    values: Float[Array, "*shape"],
    sigma_cells: float,
    truncate: float = 3.0,
    *,
    edge: str = "zero",
) -> Float[Array, "*shape"]:
    """Separable Gaussian smoothing of a per-cell array along every axis.

    Args:
        values: ``[*shape]`` per-cell values (any number of axes).
        sigma_cells: standard deviation in cells; 0 returns ``values`` unchanged.
        truncate: kernel half-width in standard deviations.
        edge: what lies beyond the grid: ``"zero"`` (default; sums are preserved except
            for what leaks across the border, as kernel estimates of counts need) or
            ``"nearest"`` (the border cells extended, so a constant array stays constant;
            ``scipy.ndimage.gaussian_filter``'s ``mode="nearest"``).

    Returns:
        ``[*shape]`` smoothed values (floating dtype).
    """
    if not np.isfinite(sigma_cells) or sigma_cells < 0:
        raise ValueError(f"sigma_cells must be finite and >= 0, got {sigma_cells!r}")
    if edge not in ("zero", "nearest"):
        raise ValueError(f'edge must be "zero" or "nearest", got {edge!r}')
    out = jnp.asarray(values)
    if not jnp.issubdtype(out.dtype, jnp.floating):
        out = out.astype(jnp.result_type(float))
    if sigma_cells == 0:
        return out
    k = jnp.asarray(gaussian_kernel_1d(sigma_cells, truncate), out.dtype)
    half = (k.shape[0] - 1) // 2
    for axis in range(out.ndim):
        n = out.shape[axis]
        moved = jnp.moveaxis(out, axis, -1)
        pad = [(0, 0)] * (moved.ndim - 1) + [(half, half)]
        padded = jnp.pad(moved, pad, mode="edge" if edge == "nearest" else "constant")
        # sum_t k[t] * padded[..., i + t]: a static loop over the kernel taps (a few to a
        # few dozen), each a shifted slice; memory stays O(cells)
        acc = jnp.zeros_like(moved)
        for t in range(k.shape[0]):
            acc = acc + k[t] * padded[..., t : t + n]
        out = jnp.moveaxis(acc, -1, axis)
    return out


def blur(values: Float[Array, "*shape"], sigma_cells: float) -> Float[Array, "*shape"]:
    """Gaussian blur of a per-cell array (e.g. a decay-rate map's rates) with the border
    cells extended: :func:`smooth_cells` with ``truncate = 3`` and ``edge="nearest"``, as
    ``scipy.ndimage.gaussian_filter(values, sigma_cells, mode="nearest", truncate=3)``.

    Args:
        values: ``[*shape]`` per-cell values.
        sigma_cells: standard deviation in cells (finite, ``>= 0``; 0 returns ``values``).

    Returns:
        ``[*shape]`` blurred values; a non-negative array stays non-negative.
    """
    if not np.isfinite(sigma_cells) or sigma_cells < 0:
        raise ValueError(f"sigma_cells must be finite and >= 0, got {sigma_cells!r}")
    if sigma_cells == 0:
        return values
    return smooth_cells(values, sigma_cells, 3.0, edge="nearest")


def smooth_stats(stats: GridStats, sigma_m: float, *, truncate: float = 3.0) -> GridStats:
    """Gaussian kernel estimate of a grid's statistics (hits, misses, lengths), for maps
    that localize robustly.

    The smoothed statistics are floats: ``H'_i = sum_j w_ij H_j``, ``M'_i = sum_j w_ij M_j``
    and ``R'_i = sum_j w_ij R_j`` with ``w_ij`` a normalised Gaussian of the distance
    between cell centres (standard deviation ``sigma_m``), separable over the axes and zero
    beyond the grid. Every grid model accepts them: ``decay_rate_map`` then estimates
    ``lambda`` as a kernel-weighted rate, ``reflection_map`` a kernel-weighted hit ratio,
    ``gamma_posterior`` / ``beta_posterior`` use the weighted counts as evidence.

    Choose ``sigma_m`` from the expected pose error and the cell size, not the data: about
    one cell (e.g. 0.1 m on a 0.1 m grid) keeps walls sharp while a pose one cell off still
    sees them; ``sigma_m = 0`` returns the statistics unchanged (as floats).

    Args:
        stats: the grid statistics (2-D or 3-D).
        sigma_m: kernel standard deviation (m), finite and >= 0.
        truncate: kernel half-width in standard deviations.

    Returns:
        A :class:`~lidarjax.raytrace.GridStats` on the same grid with float ``hits``,
        ``misses`` and ``lengths`` (m).

    Raises:
        ValueError: ``stats`` is not a GridStats, or a bad ``sigma_m`` / ``truncate``.
    """
    if not isinstance(stats, GridStats):
        raise ValueError(f"stats must be a GridStats, got {type(stats).__name__}")
    try:
        sigma = float(sigma_m)
    except (TypeError, ValueError):
        raise ValueError(f"sigma_m must be a number (m), got {sigma_m!r}") from None
    if not (np.isfinite(sigma) and sigma >= 0):
        raise ValueError(f"sigma_m must be finite and >= 0 (m), got {sigma_m!r}")
    if not (np.isfinite(truncate) and truncate > 0):
        raise ValueError(f"truncate must be finite and > 0, got {truncate!r}")
    dtype = stats.lengths.dtype
    s_cells = sigma / float(stats.spec.resolution)
    return GridStats(
        stats.spec,
        smooth_cells(jnp.asarray(stats.hits, dtype), s_cells, truncate),
        smooth_cells(jnp.asarray(stats.misses, dtype), s_cells, truncate),
        smooth_cells(stats.lengths, s_cells, truncate),
    )
