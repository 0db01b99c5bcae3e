"""Ray primitives shared by every module: the slab test against axis-aligned boxes,
ray-plane, ray-segment, and the chunk/padding helpers that bound memory of batched ray
work. This is the only place these are written; everything else imports them.

All functions are NaN-free in value and gradient (double-``where`` before divisions).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int


def slabs(lower: Float[ArrayLike, " d"], upper: Float[ArrayLike, " d"], origin, direction):
    """Per-axis slab test of rays ``origin + t * direction`` against the box
    ``[lower, upper]`` (any leading axes on the rays; ``lower``/``upper`` broadcast).

    Args:
        lower: ``[..., d]`` lower box corner (m).
        upper: ``[..., d]`` upper box corner (m).
        origin: ``[..., d]`` ray starts (m).
        direction: ``[..., d]`` ray directions (any length).

    Returns:
        ``(moving, d_safe, inside_axis, t_near, t_far)``, each ``[..., d]``:
        ``direction != 0``; ``direction`` with zeros replaced by 1; whether ``origin`` lies
        within the box's extent on each axis; the entry and exit parameters per axis
        (``-inf`` / ``+inf`` for a resting axis inside the slab, ``+inf`` / ``-inf``
        outside it).
    """
    o = jnp.asarray(origin)
    d = jnp.asarray(direction)
    lo = jnp.asarray(lower, o.dtype)
    hi = jnp.asarray(upper, o.dtype)
    moving = d != 0
    d_safe = jnp.where(moving, d, 1.0)
    ta = (lo - o) / d_safe
    tb = (hi - o) / d_safe
    inside_axis = (o >= lo) & (o <= hi)
    t_near = jnp.where(moving, jnp.minimum(ta, tb), jnp.where(inside_axis, -jnp.inf, jnp.inf))
    t_far = jnp.where(moving, jnp.maximum(ta, tb), jnp.where(inside_axis, jnp.inf, -jnp.inf))
    return moving, d_safe, inside_axis, t_near, t_far


def ray_box(
    lower: Float[ArrayLike, " d"],
    upper: Float[ArrayLike, " d"],
    origin: Float[ArrayLike, "*b d"],
    direction: Float[ArrayLike, "*b d"],
) -> tuple[Float[Array, "*b"], Float[Array, "*b"]]:
    """Entry and exit parameters ``(t_enter, t_exit)`` of rays through the closed box
    ``[lower, upper]`` (slab test, unclipped: ``t_enter`` may be negative). The ray meets
    the box where ``t_enter <= t <= t_exit``; ``t_exit < t_enter`` means it misses.

    Args:
        lower: ``[d]`` lower box corner (m).
        upper: ``[d]`` upper box corner (m).
        origin: ``[*b d]`` ray starts (m).
        direction: ``[*b d]`` ray directions (any length; ``t`` is in its units).

    Returns:
        ``[*b]`` entry and exit parameters (``-inf``/``inf`` for unbounded directions).
    """
    _, _, _, near, far = slabs(lower, upper, origin, direction)
    return jnp.max(near, axis=-1), jnp.min(far, axis=-1)


def clip_to_box(lower, upper, origin, direction, length):
    """Parameter interval ``[t_in, t_out]`` of rays ``origin + t * direction``,
    ``t in [0, length]``, inside the box ``[lower, upper]``; both 0 where not finite.
    ``t_out < t_in`` means the ray misses. Shapes as in :func:`ray_box`."""
    t_enter, t_exit = ray_box(lower, upper, origin, direction)
    t_in = jnp.maximum(t_enter, 0.0)
    t_out = jnp.minimum(t_exit, length)
    ok = jnp.isfinite(t_in) & jnp.isfinite(t_out)
    return jnp.where(ok, t_in, 0.0), jnp.where(ok, t_out, 0.0)


def box_exit(lower, upper, origin, direction) -> Array:
    """Parameter where rays leave the box ``[lower, upper]`` (far planes only; the rays are
    assumed to be inside or to have entered it). Shapes as in :func:`ray_box`;
    ``inf`` for a zero direction."""
    return ray_box(lower, upper, origin, direction)[1]


def _cross2(a: Array, b: Array) -> Array:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _cross2(a: Array, b: Array) -> Array:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def ray_segment(
    origin: Float[Array, " 2"],
    direction: Float[Array, " 2"],
    start: Float[Array, " 2"],
    end: Float[Array, " 2"],
) -> Float[Array, ""]:
    """Distance along one 2-D ray to its intersection with one line segment.

    Solves ``origin + t * direction = start + u * (end - start)`` for ``t > 0`` and
    ``u`` in ``[0, 1]`` (widened by a few ulps so a ray through a vertex hits both
    segments that share it). Parallel rays (and degenerate segments) miss. NaN-free: the
    gradient is finite everywhere and exact wherever the ray hits the segment's interior.

    Args:
        origin: ``[2]`` ray start (m).
        direction: ``[2]`` unit direction.
        start: ``[2]`` first segment vertex (m).
        end: ``[2]`` second segment vertex (m).

    Returns:
        Scalar distance ``t`` (m), ``inf`` when the ray misses the segment.
    """
    e = end - start
    w = start - origin
    den = _cross2(direction, e)
    tiny = jnp.finfo(den.dtype).tiny
    scale = jnp.sqrt(jnp.sum(e * e)) * jnp.sqrt(jnp.sum(direction * direction))
    ok = jnp.abs(den) > 64 * jnp.finfo(den.dtype).eps * jnp.maximum(scale, tiny)
    den_safe = jnp.where(ok, den, 1.0)
    t = _cross2(w, e) / den_safe
    u = _cross2(w, direction) / den_safe
    slack = 64 * jnp.finfo(den.dtype).eps
    hit = ok & (t > 0) & (u >= -slack) & (u <= 1 + slack)
    return jnp.where(hit, t, jnp.inf)


def first_segment_hit(
    origin: Float[Array, " 2"],
    direction: Float[Array, " 2"],
    starts: Float[Array, "s 2"],
    ends: Float[Array, "s 2"],
    valid: Bool[Array, " s"] | None = None,
) -> tuple[Float[Array, ""], Int[Array, ""]]:
    """First intersection of one 2-D ray with a set of segments (padded + masked).

    Args:
        origin: ``[2]`` ray start (m).
        direction: ``[2]`` unit direction.
        starts: ``[s 2]`` segment start vertices (m).
        ends: ``[s 2]`` segment end vertices (m).
        valid: ``[s]`` mask of real segments (default: all).

    Returns:
        ``(t, index)``: the distance (m, ``inf`` if no segment is hit) and the index of the
        first segment hit (the lowest index among equally near ones; ``-1`` if none).
    """
    t = jax.vmap(ray_segment, in_axes=(None, None, 0, 0))(origin, direction, starts, ends)
    if valid is not None:
        t = jnp.where(valid, t, jnp.inf)
    i = jnp.argmin(t)
    tmin = t[i]
    return tmin, jnp.where(jnp.isfinite(tmin), i, -1).astype(jnp.int32)


def ray_plane(
    origin: Float[Array, " d"],
    direction: Float[Array, " d"],
    support: Float[Array, " d"],
    normal: Float[Array, " d"],
) -> Float[Array, ""]:
    """Signed distance along one ray to its intersection with an infinite plane (Eq. 11.1).

    Solves ``n . (origin + t * direction - support) = 0`` for ``t``:
    ``t = n . (support - origin) / (n . direction)``. Works in 2-D (a line) and 3-D. The
    result is negative when the plane lies behind the ray start. A ray parallel to the
    plane (``|n . v|`` below a few ulps of ``|n| |v|``) gives ``inf``; the gradient stays
    finite there (double-``where``).

    Args:
        origin: ``[d]`` ray start ``s`` (m).
        direction: ``[d]`` unit ray direction ``v``.
        support: ``[d]`` any point ``x`` on the plane (m).
        normal: ``[d]`` plane normal ``n`` (any length, not zero).

    Returns:
        Scalar ``t`` (m) or ``inf``.
    """
    den = jnp.sum(normal * direction)
    scale = jnp.sqrt(jnp.sum(normal * normal) * jnp.sum(direction * direction))
    tiny = jnp.finfo(den.dtype).tiny
    ok = jnp.abs(den) > 64 * jnp.finfo(den.dtype).eps * jnp.maximum(scale, tiny)
    t = jnp.sum(normal * (support - origin)) / jnp.where(ok, den, 1.0)
    return jnp.where(ok, t, jnp.inf)


def n_chunks_for(n: int, chunk_size: int) -> int:
    """Number of chunks of ``chunk_size`` needed for ``n`` items (at least 1)."""
    if not isinstance(chunk_size, int) or chunk_size <= 0:
        raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}")
    return max(1, -(-int(n) // chunk_size))


def pad_to_chunks(x: Array, chunk_size: int, fill=0) -> Array:
    """Pad the leading axis of ``x`` ``[n ...]`` with ``fill`` to a multiple of
    ``chunk_size`` and reshape to ``[n_chunks chunk_size ...]`` (for ``lax.map`` /
    ``lax.scan`` over chunks, which bounds memory to one chunk's work)."""
    n = x.shape[0]
    k = n_chunks_for(n, chunk_size)
    widths = [(0, k * chunk_size - n)] + [(0, 0)] * (x.ndim - 1)
    return jnp.pad(x, widths, constant_values=fill).reshape(k, chunk_size, *x.shape[1:])


def unchunk(x: Array, n: int) -> Array:
    """Inverse of :func:`pad_to_chunks`: ``[n_chunks chunk ...]`` -> the first ``n`` rows."""
    return x.reshape(x.shape[0] * x.shape[1], *x.shape[2:])[:n]


def map_chunked(fn, xs, chunk_size: int, fill=0):
    """``fn`` over the leading axis of the pytree ``xs`` in chunks of ``chunk_size``
    (``lax.map`` over padded chunks, so memory is one chunk's); returns the outputs for
    the real rows only. ``fn`` maps a chunk pytree ``[chunk ...]`` to a pytree of
    ``[chunk ...]`` arrays."""
    leaves = jax.tree.leaves(xs)
    if not leaves:
        raise ValueError("xs has no arrays to chunk")
    n = leaves[0].shape[0]
    chunked = jax.tree.map(lambda a: pad_to_chunks(a, chunk_size, fill), xs)
    out = jax.lax.map(fn, chunked)
    return jax.tree.map(lambda a: unchunk(a, n), out)


__all__ = [
    "slabs",
    "ray_box",
    "clip_to_box",
    "box_exit",
    "ray_plane",
    "ray_segment",
    "first_segment_hit",
    "n_chunks_for",
    "pad_to_chunks",
    "unchunk",
    "map_chunked",
]
