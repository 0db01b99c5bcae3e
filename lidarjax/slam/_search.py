"""Correlative pose search: the scan's end-point log-likelihood on a lattice of poses.

A gradient refinement finds the nearest basin of the scan log-likelihood; where the start
is off by more than a basin's width (a corridor's repeating doors, a loop closure after
drift) it converges to the wrong one. The search evaluates, exhaustively, the end-point
term of the model (``log`` of the blurred rate at each HIT ray's end point, the free-space
term left out) at every pose of a lattice around a centre: translations on the map's own
cells (so a candidate's end points are the centre's shifted by whole cells, one gather per
point and candidate, nearest cell) and headings in ``step_yaw`` steps. The best lattice
pose (with the Gaussian prior added) starts the decay-rate refinement.

Costs ``n_yaw * (2 n_xy + 1)^2 * b`` table lookups, chunked over the headings (one heading
at a time in a bounded ``lax.map``), so memory is ``(2 n_xy + 1)^2 * b`` per step.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

__all__ = ["correlative_search"]


def _wrap(a):
    return (a + jnp.pi) % (2 * jnp.pi) - jnp.pi


@functools.partial(jax.jit, static_argnames=("n_xy", "n_yaw", "step_yaw", "exclude_m"))
def correlative_search(
    table: Float[Array, "n n"],
    origin: Float[Array, 2],
    res: float,
    az: Float[Array, " b"],
    rng: Float[Array, " b"],
    weights: Float[Array, " b"],
    center: Float[Array, 3],
    prior: Float[Array, 3],
    inv_sigmas: Float[Array, 3],
    *,
    n_xy: int,
    n_yaw: int,
    step_yaw: float,
    exclude_m: float,
) -> tuple[Float[Array, 3], Float[Array, ""], Float[Array, ""]]:
    """Exhaustive search of ``sum_b weights_b * table[end point_b]`` plus the Gaussian
    prior over poses ``center + (i res, j res, k step_yaw)``, ``|i|, |j| <= n_xy``,
    ``|k| <= n_yaw``.

    Args:
        table: ``[n n]`` per-cell log-likelihood of an end point (nats); cell ``(i, j)``
            covers ``origin + res * [i, i + 1) x [j, j + 1)``. End points off the table
            score its minimum.
        origin: ``[2]`` lower corner (m); res: cell size (m).
        az, rng: ``[b]`` beam angles (rad) and ranges (m) of the scan.
        weights: ``[b]`` ray weights (0 leaves a ray out, e.g. a no-return).
        center: ``[3]`` lattice centre ``(x m, y m, yaw rad)``.
        prior: ``[3]`` mean of the Gaussian prior; inv_sigmas: ``[3]`` its inverse
            standard deviations (1/m, 1/m, 1/rad), in the prior's frame (0: no prior).
        n_xy, n_yaw: lattice half widths (static); step_yaw: heading step (rad).
        exclude_m: the runner-up is the best lattice pose farther than this (m) from the
            best in position.

    Returns:
        ``(best pose [3], best score, runner-up score)`` (scores with the prior, nats).
    """
    dt = table.dtype
    floor = jnp.min(table)
    # padded table: shifts up to n_xy off either side read the floor
    pad = jnp.pad(table, n_xy + 1, constant_values=floor)
    offs = jnp.arange(-n_xy, n_xy + 1)
    yaws = center[2] + step_yaw * jnp.arange(-n_yaw, n_yaw + 1, dtype=dt)
    local = jnp.stack([rng * jnp.cos(az), rng * jnp.sin(az)], -1)  # [b 2] sensor frame

    def per_yaw(yaw):
        c, s = jnp.cos(yaw), jnp.sin(yaw)
        pts = center[:2] + jnp.stack(
            [c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1]], -1
        )
        # shifted into the padded table; indices off it are clipped onto its border,
        # which holds the floor
        idx = jnp.floor((pts - origin) / res).astype(jnp.int32) + (n_xy + 1)
        ix = jnp.clip(idx[:, 0][None, :] + offs[:, None], 0, pad.shape[0] - 1)  # [2n+1 b]
        iy = jnp.clip(idx[:, 1][None, :] + offs[:, None], 0, pad.shape[1] - 1)
        vals = pad[ix[:, None, :], iy[None, :, :]]  # [2n+1 2n+1 b]
        return jnp.sum(vals * weights, -1)

    score = jax.lax.map(per_yaw, yaws)  # [2k+1 2n+1 2n+1]
    dx = res * offs.astype(dt)
    gx = center[0] + dx[None, :, None]
    gy = center[1] + dx[None, None, :]
    gyaw = yaws[:, None, None]
    # prior: deviation from the prior mean in its frame
    cp, sp = jnp.cos(prior[2]), jnp.sin(prior[2])
    ex, ey = gx - prior[0], gy - prior[1]
    d0 = (cp * ex + sp * ey) * inv_sigmas[0]
    d1 = (-sp * ex + cp * ey) * inv_sigmas[1]
    d2 = _wrap(gyaw - prior[2]) * inv_sigmas[2]
    total = score - 0.5 * (d0**2 + d1**2 + d2**2)
    flat = jnp.argmax(total)
    k, i, j = jnp.unravel_index(flat, total.shape)
    best = jnp.stack([center[0] + dx[i], center[1] + dx[j], yaws[k]])
    far = jnp.hypot(gx - best[0], gy - best[1]) > exclude_m
    runner = jnp.max(jnp.where(jnp.broadcast_to(far, total.shape), total, -jnp.inf))
    return best, total[k, i, j], runner
