"""Ray primitives shared by every module: the slab test against axis-aligned boxes,
ray-cylinder (vertical, finite), ray-sphere, ray-plane, ray-segment, and the chunk/padding
helpers that bound memory of batched ray work. This is the only place these are written;
everything else imports them.

All kernels are NaN-free in value and gradient (double-``where`` before divisions and
square roots). Only ``jax`` and ``jaxtyping`` are imported, so every layer (also the
simulators in :mod:`lidarjax.sim`) may use them.
"""

from __future__ import annotations

import functools
import operator

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .. import _checks


def _moving(x: Array, eps: float) -> Array:
    """``x != 0`` (``eps == 0``) or ``|x| >= eps``: the component counts as non-zero."""
    if eps < 0:
        raise ValueError(f"eps must be >= 0, got {eps!r}")
    return x != 0 if eps == 0 else jnp.abs(x) >= eps


def _axis_slabs(lower, upper, origin, direction, eps: float, axis: int) -> list[tuple]:
    """:func:`slabs` of each coordinate separately, on ``[*b]`` slices along ``axis`` (of
    the broadcast shape; an input without that axis is used for every coordinate). The
    values are those of :func:`slabs`; XLA fuses the per-coordinate work on ``[*b]``
    arrays better than one pass over ``[*b d]`` ones."""
    o = jnp.asarray(origin)
    d = jnp.asarray(direction)
    arrays = (jnp.asarray(lower, o.dtype), jnp.asarray(upper, o.dtype), o, d)
    shape = jnp.broadcast_shapes(*(a.shape for a in arrays))
    if not -len(shape) <= axis < len(shape):
        raise ValueError(f"axis {axis} is out of range for inputs of shape {shape}")
    ax = axis - len(shape) if axis >= 0 else axis  # from the right, as broadcasting aligns

    def coord(a, k):
        if a.ndim < -ax:
            return a
        return jax.lax.index_in_dim(a, min(k, a.shape[ax] - 1), a.ndim + ax, keepdims=False)

    return [slabs(*(coord(a, k) for a in arrays), eps=eps) for k in range(shape[ax])]


def _sum(terms) -> Array:
    """Sum of the terms, left to right."""
    return functools.reduce(operator.add, terms)


def slabs(
    lower: Float[ArrayLike, "*b d"],
    upper: Float[ArrayLike, "*b d"],
    origin: Float[ArrayLike, "*b d"],
    direction: Float[ArrayLike, "*b d"],
    *,
    eps: float = 0.0,
):
    """Per-axis slab test of rays ``origin + t * direction`` against the box
    ``[lower, upper]`` (all arguments broadcast against each other; elementwise, so it
    also takes one coordinate's ``[*b]`` arrays).

    Args:
        lower: ``[*b d]`` lower box corner (m); cast to ``origin``'s dtype.
        upper: ``[*b d]`` upper box corner (m); cast to ``origin``'s dtype.
        origin: ``[*b d]`` ray starts (m).
        direction: ``[*b d]`` ray directions (any length; ``t`` is in its units).
        eps: a direction component with ``|v_k| < eps`` counts as zero (the ray rests on
            that axis); ``0`` (default) tests ``v_k != 0`` exactly.

    Returns:
        ``(moving, d_safe, inside_axis, t_near, t_far)``, each ``[*b d]``: whether the ray
        moves along each axis; ``direction`` with resting components replaced by 1;
        whether ``origin`` lies within the box's extent on each axis; the entry and exit
        parameters per axis (``-inf`` / ``+inf`` for a resting axis inside the slab,
        ``+inf`` / ``-inf`` outside it).
    """
    o = jnp.asarray(origin)
    d = jnp.asarray(direction)
    lo = jnp.asarray(lower, o.dtype)
    hi = jnp.asarray(upper, o.dtype)
    moving = _moving(d, eps)
    d_safe = jnp.where(moving, d, 1.0)
    ta = (lo - o) / d_safe
    tb = (hi - o) / d_safe
    inside_axis = (o >= lo) & (o <= hi)
    t_near = jnp.where(moving, jnp.minimum(ta, tb), jnp.where(inside_axis, -jnp.inf, jnp.inf))
    t_far = jnp.where(moving, jnp.maximum(ta, tb), jnp.where(inside_axis, jnp.inf, -jnp.inf))
    return moving, d_safe, inside_axis, t_near, t_far


def ray_box(
    lower: Float[ArrayLike, "*b d"],
    upper: Float[ArrayLike, "*b d"],
    origin: Float[ArrayLike, "*b d"],
    direction: Float[ArrayLike, "*b d"],
    *,
    eps: float = 0.0,
    axis: int = -1,
) -> tuple[Float[Array, "*b"], Float[Array, "*b"]]:
    """Entry and exit parameters ``(t_enter, t_exit)`` of rays through the closed box
    ``[lower, upper]`` (slab test, unclipped: ``t_enter`` may be negative). The ray meets
    the box where ``t_enter <= t <= t_exit``; ``t_exit < t_enter`` means it misses.

    Args:
        lower: ``[*b d]`` lower box corner (m); broadcast against the rays.
        upper: ``[*b d]`` upper box corner (m).
        origin: ``[*b d]`` ray starts (m).
        direction: ``[*b d]`` ray directions (any length; ``t`` is in its units).
        eps: resting threshold of a direction component, see :func:`slabs`.
        axis: the coordinate axis of the inputs (default: the last). ``axis=0`` takes
            ``[d *b]`` inputs, which XLA's CPU backend vectorises several times better
            than a minor axis of size 2 or 3 when ``*b`` is large.

    Returns:
        ``[*b]`` entry and exit parameters (``-inf``/``inf`` for unbounded directions).
    """
    axes = _axis_slabs(lower, upper, origin, direction, eps, axis)
    t_enter = functools.reduce(jnp.maximum, (near for *_, near, _ in axes))
    t_exit = functools.reduce(jnp.minimum, (far for *_, far in axes))
    return t_enter, t_exit


def clip_to_box(
    lower: Float[ArrayLike, "*b d"],
    upper: Float[ArrayLike, "*b d"],
    origin: Float[ArrayLike, "*b d"],
    direction: Float[ArrayLike, "*b d"],
    length: Float[ArrayLike, "*b"],
    *,
    eps: float = 0.0,
    axis: int = -1,
) -> tuple[Float[Array, "*b"], Float[Array, "*b"]]:
    """Parameter interval ``[t_in, t_out]`` of rays ``origin + t * direction``,
    ``t in [0, length]``, inside the box ``[lower, upper]``.

    Args:
        lower, upper, origin, direction, eps, axis: as in :func:`ray_box`.
        length: ``[*b]`` upper parameter limit (in ``direction``'s units, ``inf`` allowed).

    Returns:
        ``(t_in, t_out)``, each ``[*b]``; both 0 where one is not finite. ``t_out < t_in``
        means the ray misses.
    """
    t_enter, t_exit = ray_box(lower, upper, origin, direction, eps=eps, axis=axis)
    t_in = jnp.maximum(t_enter, 0.0)
    t_out = jnp.minimum(t_exit, length)
    ok = jnp.isfinite(t_in) & jnp.isfinite(t_out)
    return jnp.where(ok, t_in, 0.0), jnp.where(ok, t_out, 0.0)


def box_exit(
    lower: Float[ArrayLike, "*b d"],
    upper: Float[ArrayLike, "*b d"],
    origin: Float[ArrayLike, "*b d"],
    direction: Float[ArrayLike, "*b d"],
    *,
    eps: float = 0.0,
    axis: int = -1,
) -> Float[Array, "*b"]:
    """Parameter where rays leave the box ``[lower, upper]``: the nearest far plane of the
    axes the ray moves along. The rays are assumed to be inside the box or to have entered
    it, so a resting axis never bounds the exit (also when rounding puts the origin just
    outside that slab).

    Args:
        lower, upper, origin, direction, eps, axis: as in :func:`ray_box`.

    Returns:
        ``[*b]`` exit parameter; ``inf`` for a zero direction.
    """
    axes = _axis_slabs(lower, upper, origin, direction, eps, axis)
    return functools.reduce(
        jnp.minimum, (jnp.where(moving, far, jnp.inf) for moving, *_, far in axes)
    )


def ray_cylinder(
    center: Float[ArrayLike, "*b 2"],
    radius: Float[ArrayLike, "*b"],
    z_min: Float[ArrayLike, "*b"],
    z_max: Float[ArrayLike, "*b"],
    origin: Float[ArrayLike, "*b 3"],
    direction: Float[ArrayLike, "*b 3"],
    *,
    eps: float = 0.0,
) -> tuple[Float[Array, "*b"], Float[Array, "*b"]]:
    """Entry and exit parameters of 3-D rays through a closed vertical finite cylinder
    (axis parallel to ``z``): the interval of the infinite cylinder
    ``(x - c_x)^2 + (y - c_y)^2 <= r^2`` intersected with the slab ``z_min <= z <= z_max``
    (unclipped: ``t_enter`` may be negative). The ray meets the cylinder where
    ``t_enter <= t <= t_exit``; ``t_exit < t_enter`` means it misses (a ray that misses
    the infinite cylinder gets ``(inf, -inf)``). A tangent ray touches it
    (``t_enter == t_exit`` on the mantle).

    Args:
        center: ``[*b 2]`` axis position ``(c_x, c_y)`` (m).
        radius: ``[*b]`` radius ``r`` (m).
        z_min: ``[*b]`` bottom height (m).
        z_max: ``[*b]`` top height (m).
        origin: ``[*b 3]`` ray starts (m).
        direction: ``[*b 3]`` ray directions (any length; ``t`` is in its units).
        eps: a ray with ``v_x^2 + v_y^2 < eps`` counts as vertical (inside or outside the
            mantle for all ``t``) and one with ``|v_z| < eps`` as horizontal; ``0``
            (default) tests for exact zeros.

    Returns:
        ``(t_enter, t_exit)``, each ``[*b]`` (``-inf``/``inf`` for unbounded directions).
    """
    o = jnp.asarray(origin)
    d = jnp.asarray(direction)
    c = jnp.asarray(center)
    r = jnp.asarray(radius)
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    px, py = c[..., 0] - o[..., 0], c[..., 1] - o[..., 1]  # axis relative to the ray start
    a = dx * dx + dy * dy
    vertical = ~_moving(a, eps)
    a_safe = jnp.where(vertical, 1.0, a)
    t_mid = (dx * px + dy * py) / a_safe  # closest approach to the axis in the xy plane
    wx, wy = px - t_mid * dx, py - t_mid * dy
    disc = r * r - (wx * wx + wy * wy)
    pos = disc > 0
    half = jnp.where(pos, jnp.sqrt(jnp.where(pos, disc, 1.0) / a_safe), 0.0)
    inside_axis = px * px + py * py <= r * r
    t1 = jnp.where(vertical, jnp.where(inside_axis, -jnp.inf, jnp.inf), t_mid - half)
    t2 = jnp.where(vertical, jnp.where(inside_axis, jnp.inf, -jnp.inf), t_mid + half)
    miss = ~vertical & (disc < 0)
    t1 = jnp.where(miss, jnp.inf, t1)
    t2 = jnp.where(miss, -jnp.inf, t2)
    _, _, _, s1, s2 = slabs(z_min, z_max, o[..., 2], dz, eps=eps)  # elementwise: the z slab
    return jnp.maximum(t1, s1), jnp.minimum(t2, s2)


def ray_sphere(
    center: Float[ArrayLike, "*b d"],
    radius: Float[ArrayLike, "*b"],
    origin: Float[ArrayLike, "*b d"],
    direction: Float[ArrayLike, "*b d"],
) -> tuple[Float[Array, "*b"], Float[Array, "*b"]]:
    """Entry and exit distances of rays through a closed ball (a disc in 2-D):
    ``t = v . (c - s) -/+ sqrt(r^2 - |c - s - (v . (c - s)) v|^2)`` (unclipped:
    ``t_enter`` may be negative, e.g. for a ray starting inside). ``t_exit < t_enter``
    means the ray misses (``(inf, -inf)``); a tangent ray gives ``t_enter == t_exit``.

    Args:
        center: ``[*b d]`` centre ``c`` (m).
        radius: ``[*b]`` radius ``r`` (m).
        origin: ``[*b d]`` ray starts ``s`` (m).
        direction: ``[*b d]`` unit directions ``v``.

    Returns:
        ``(t_enter, t_exit)``, each ``[*b]`` (m).
    """
    c, o, v = (jnp.asarray(x) for x in (center, origin, direction))
    r = jnp.asarray(radius)
    # per component ([*b] arrays, which XLA fuses better than [*b d] ones)
    w = [c[..., k] - o[..., k] for k in range(v.shape[-1])]
    d = [v[..., k] for k in range(v.shape[-1])]
    t_mid = _sum(dk * wk for dk, wk in zip(d, w))  # closest approach to the centre
    q = [wk - t_mid * dk for dk, wk in zip(d, w)]
    disc = r * r - _sum(qk * qk for qk in q)
    pos = disc > 0
    half = jnp.where(pos, jnp.sqrt(jnp.where(pos, disc, 1.0)), 0.0)
    miss = disc < 0
    return jnp.where(miss, jnp.inf, t_mid - half), jnp.where(miss, -jnp.inf, t_mid + half)


def cross2(a: Float[ArrayLike, "*b 2"], b: Float[ArrayLike, "*b 2"]) -> Float[Array, "*b"]:
    """2-D cross product ``a_x b_y - a_y b_x`` (``[*b 2]`` each, broadcast) -> ``[*b]``."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def ray_segment(
    origin: Float[Array, " 2"],
    direction: Float[Array, " 2"],
    start: Float[Array, " 2"],
    end: Float[Array, " 2"],
) -> Float[Array, ""]:
    """Distance along one 2-D ray to its intersection with one line segment.

    Solves ``origin + t * direction = start + u * (end - start)`` for ``t > 0`` and
    ``u`` in ``[0, 1]``. Both segment ends are inclusive up to round-off: ``u`` may lie
    outside ``[0, 1]`` by ``64 eps (|origin| + |start - origin| + |end - start|) |direction|
    / |direction x (end - start)|`` (``|.|`` the 1-norm; the error of ``u`` when a vertex
    lies on the ray up to rounding of its coordinates, e.g. a vertex placed at
    ``origin + r * direction``), so a ray through a vertex hits both segments that share
    it and a ray whose endpoint is a polyline's end vertex hits that polyline, also at
    long range and grazing incidence. Parallel rays (``|direction x (end - start)|`` below
    ``64 eps |end - start| |direction|``) and degenerate segments miss. NaN-free: the
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
    den = cross2(direction, e)
    tiny = jnp.finfo(den.dtype).tiny
    scale = jnp.sqrt(jnp.sum(e * e)) * jnp.sqrt(jnp.sum(direction * direction))
    ok = jnp.abs(den) > 64 * jnp.finfo(den.dtype).eps * jnp.maximum(scale, tiny)
    den_safe = jnp.where(ok, den, 1.0)
    t = cross2(w, e) / den_safe
    u = cross2(w, direction) / den_safe
    # round-off of u: the numerator cross2(w, direction) carries the rounding of the
    # coordinates (~eps (|origin| + |w|) |direction|), the denominator that of e; 1-norms
    # (no square roots: the bound only enters a comparison). It is >= 64 eps, as
    # |den| <= |e| |direction|.
    norm1 = lambda x: jnp.sum(jnp.abs(x))  # noqa: E731
    u_scale = (norm1(origin) + norm1(w) + norm1(e)) * norm1(direction)
    slack = 64 * jnp.finfo(den.dtype).eps * u_scale / jnp.abs(den_safe)
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


def first_segment_hits(
    origins: Float[Array, "n 2"],
    directions: Float[Array, "n 2"],
    starts: Float[Array, "s 2"],
    ends: Float[Array, "s 2"],
    valid: Bool[Array, " s"] | None = None,
    *,
    chunk_size: int | None = None,
) -> tuple[Float[Array, " n"], Int[Array, " n"]]:
    """:func:`first_segment_hit` for a batch of rays against one set of segments.

    Args:
        origins: ``[n 2]`` ray starts (m).
        directions: ``[n 2]`` unit directions.
        starts, ends, valid: the segments, as in :func:`first_segment_hit`.
        chunk_size: with more than ``chunk_size`` rays, they run ``chunk_size`` at a time
            (:func:`map_chunked`) so memory stays at ``[chunk_size s]``; ``None``: at once.

    Returns:
        ``(t, index)``, each ``[n]``, as in :func:`first_segment_hit`.
    """
    hit = jax.vmap(first_segment_hit, in_axes=(0, 0, None, None, None))
    n = origins.shape[0]
    if chunk_size is None or n <= chunk_size:
        return hit(origins, directions, starts, ends, valid)
    return map_chunked(
        lambda x: hit(x[0], x[1], starts, ends, valid),
        (origins, directions),
        chunk_size,
        fill=(0.0, 1.0),  # padded rays: finite, non-zero directions
    )


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
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size <= 0:
        raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}")
    return max(1, -(-int(n) // chunk_size))


def _namespace(x):
    """The array namespace of ``x``: NumPy for NumPy arrays (host-side, no compilation),
    ``jax.numpy`` for everything else."""
    get = getattr(x, "__array_namespace__", None)
    return jnp if get is None else get()


def pad_to_chunks(x: ArrayLike, chunk_size: int, fill=0) -> Array:
    """Pad the leading axis of ``x`` ``[n ...]`` to a multiple of ``chunk_size`` and
    reshape to ``[n_chunks chunk_size ...]`` (for ``lax.map`` / ``lax.scan`` over chunks,
    which bounds memory to one chunk's work).

    Args:
        x: ``[n ...]`` array; a NumPy array is padded with NumPy (and stays one).
        chunk_size: rows per chunk (positive int).
        fill: value of the padding rows, or ``"edge"`` for copies of the last row (keeps
            the padded rows as well-behaved as real ones, e.g. for gradients through a
            kernel that is singular at zeros; needs ``n >= 1``).

    Returns:
        ``[n_chunks chunk_size ...]`` with ``n_chunks = max(1, ceil(n / chunk_size))``.
    """
    xp = _namespace(x)
    x = xp.asarray(x)
    n = x.shape[0]
    k = n_chunks_for(n, chunk_size)
    widths = [(0, k * chunk_size - n)] + [(0, 0)] * (x.ndim - 1)
    if isinstance(fill, str):
        if fill != "edge":
            raise ValueError(f"fill must be a value or 'edge', got {fill!r}")
        if n == 0:
            raise ValueError("fill='edge' needs at least one row to copy")
        padded = xp.pad(x, widths, mode="edge")
    else:
        padded = xp.pad(x, widths, constant_values=fill)
    return padded.reshape(k, chunk_size, *x.shape[1:])


def unchunk(x: ArrayLike, n: int) -> Array:
    """Inverse of :func:`pad_to_chunks`: ``[n_chunks chunk ...]`` -> the first ``n`` rows
    ``[n ...]`` (NumPy stays NumPy)."""
    return x.reshape(x.shape[0] * x.shape[1], *x.shape[2:])[:n]


def map_chunked(fn, xs, chunk_size: int, fill=0):
    """``fn`` over the leading axis of the pytree ``xs`` in chunks of ``chunk_size``
    (``lax.map`` over padded chunks, so memory is one chunk's).

    Args:
        fn: maps a chunk pytree ``[chunk ...]`` to a pytree of ``[chunk ...]`` arrays
            (row-wise: a padded row must not change the real rows' outputs).
        xs: pytree of arrays with a common leading axis ``n``.
        chunk_size: rows per chunk.
        fill: padding of every leaf (a value or ``"edge"``, see :func:`pad_to_chunks`), or
            a pytree of such with the structure of ``xs`` (one per leaf).

    Returns:
        ``fn``'s outputs for the ``n`` real rows, ``[n ...]`` per leaf.
    """
    leaves, tree = jax.tree.flatten(xs)
    if not leaves:
        raise ValueError("xs has no arrays to chunk")
    n = leaves[0].shape[0]
    if isinstance(fill, (tuple, list, dict)):
        fills = tree.flatten_up_to(fill)
    else:
        fills = [fill] * len(leaves)
    chunked = tree.unflatten(
        [pad_to_chunks(a, chunk_size, f) for a, f in zip(leaves, fills, strict=True)]
    )
    out = _checks.map(fn, chunked)
    return jax.tree.map(lambda a: unchunk(a, n), out)


__all__ = [
    "slabs",
    "ray_box",
    "clip_to_box",
    "box_exit",
    "ray_cylinder",
    "ray_sphere",
    "ray_plane",
    "cross2",
    "ray_segment",
    "first_segment_hit",
    "first_segment_hits",
    "n_chunks_for",
    "pad_to_chunks",
    "unchunk",
    "map_chunked",
]
