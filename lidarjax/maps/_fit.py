"""Inverse model of DCT maps (Sec. 9.4.4): the coefficients that maximise the joint
log-likelihood of the mapping rays, found with optimistix.

The optical depth of a ray is linear in the spectrum ``c(A)`` of the squared field
(:func:`~lidarjax.maps.dct_spectrum`): ``S_k = <c(A), W_k>``. The fit therefore sums the
weights ``W_k`` of all HIT and SUP rays once, before the optimisation, and each objective
evaluation costs one spectrum (``O(I^2)``-ish einsum), ``f`` at the HIT end points
(``O(K I)``) and the SUB terms — instead of ``O(K I^2)`` for Eq. (9.10) per ray.

Solver: L-BFGS (``optx.LBFGS``). The problem has ``I = L M`` unknowns (100 … 1600 in
Table 9.2). The exact Hessian costs ``O(K I^2)`` to assemble (1.3e9 flops at 40 x 40 with
500 rays, 2.6e10 with 1e4 rays) plus an ``O(I^3)`` solve per step; dense BFGS needs only
gradients but its ``O(I^2)`` update made a step cost 8 ms at 40 x 40 against 1 ms for
L-BFGS (history 10), which reached the same log-likelihood in fewer seconds on the Intel
patch. The default tolerances follow the paper's stopping rule, a relative change of the
log-likelihood below 1e-3, applied by optimistix's Cauchy test to the per-ray mean objective
(and, as optimistix requires, to the coefficients). That rule is only safe with a good
start: from the paper's one-cell-per-coefficient grid DCT some HIT end points have
``f ~ 0``, L-BFGS crawls and the rule stopped after 13 steps on 1e4 Intel rays, so the
default start projects a 2x finer grid (:func:`grid_initial_map`).

Compile once per shape bucket (issue #25): :func:`fit_dct` selects and pads the rays on
the host (NumPy) and runs its whole set-up (summed weights, SUB weights, HIT end points, the
box check and the grid initial map) as ONE jitted program over ``ray_bucket(n)`` rays
(padding rays are masked out and contribute exactly zero), then one jitted solve whose
inputs have the bucketed shapes and whose ray count is a traced scalar. Inputs with other
ray counts in the same bucket reuse both compiled programs, and a second process loads
two programs from the persistent cache instead of tracing ~65 small eager ones.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._checks import checked_jit
from .._math import log1mexp
from ..rays import HIT, SUB, SUP, RayBatch
from ..raytrace import GridSpec, accumulate, pad_to_chunks
from ._dct import (
    DCTMap,
    _amplitude,
    _segment,
    dct_spectrum,
    from_grid,
    quadrature_nodes,
    ray_weights,
    rays_in_box,
)
from ._grid import decay_rate_map

__all__ = ["DCTObjective", "dct_objective", "fit_dct", "grid_initial_map", "ray_bucket"]


class DCTObjective(eqx.Module):
    """Precomputed sufficient data of a ray set for the DCT log-likelihood; call
    ``obj(coeffs)`` for the total log-likelihood (nats) of all rays, Eqs. (9.5), (9.11),
    (9.12). Build with :func:`dct_objective`.

    Attributes:
        lower, extent: the map box (m).
        w_free: summed weights ``sum_k W_k`` of HIT and SUP rays (spectrum shape).
        w_sub: ``[n_sub *spectrum]`` weights of SUB rays (their depth to ``r_min``).
        hit_points: ``[n_hit d]`` normalised HIT end points.
        n_rays: number of rays.
    """

    lower: jax.Array
    extent: jax.Array
    w_free: jax.Array
    w_sub: jax.Array
    hit_points: jax.Array
    n_rays: int = eqx.field(static=True)

    def __call__(self, coeffs: jax.Array) -> jax.Array:
        return _total_log_likelihood(coeffs, self.w_free, self.w_sub, self.hit_points)


def _total_log_likelihood(coeffs, w_free, w_sub, hit_points, sub_mask=None, hit_mask=None):
    """Sum of the rays' log-likelihoods (nats) from the precomputed terms; rows of
    ``w_sub`` / ``hit_points`` whose mask is False (padding) contribute exactly 0 to the
    value and the gradient."""
    c = dct_spectrum(coeffs)
    f = _amplitude(coeffs, hit_points)
    f2 = f * f
    pos = f2 > 0
    log_lam = jnp.where(pos, jnp.log(jnp.where(pos, f2, 1.0)), -jnp.inf)
    depth_sub = jnp.tensordot(w_sub, c, axes=c.ndim)
    if hit_mask is not None:
        log_lam = jnp.where(hit_mask, log_lam, 0.0)
    if sub_mask is None:
        log_sub = log1mexp(depth_sub)
    else:
        log_sub = jnp.where(sub_mask, log1mexp(jnp.where(sub_mask, depth_sub, 1.0)), 0.0)
    return jnp.sum(log_lam) - jnp.sum(w_free * c) + jnp.sum(log_sub)


class _BucketedObjective(eqx.Module):
    """:class:`DCTObjective` over rays padded to a shape bucket (built by :func:`_setup`):
    ``hit_points [nb d]`` of every (padded) ray with ``hit_mask [nb]`` (True for real HIT
    rays), ``w_sub [ns *spectrum]`` with ``sub_mask [ns]``, and the real ray count
    ``n_rays`` as a traced scalar, so inputs of one bucket share the solver's program."""

    lower: jax.Array
    extent: jax.Array
    w_free: jax.Array
    w_sub: jax.Array
    sub_mask: jax.Array
    hit_points: jax.Array
    hit_mask: jax.Array
    n_rays: jax.Array

    def __call__(self, coeffs: jax.Array) -> jax.Array:
        return _total_log_likelihood(
            coeffs, self.w_free, self.w_sub, self.hit_points, self.sub_mask, self.hit_mask
        )


@functools.partial(jax.jit, static_argnames=("shape", "chunk_size", "method"))
def _weights(m, origins, directions, lengths, use, shape, chunk_size, method):
    """``sum_k W_k`` over the rays with ``use`` (see :func:`~lidarjax.maps._dct.ray_weights`).

    ``method="spectral"`` sums the closed-form weights per ray; ``"quadrature"`` integrates
    each cosine product with the Gauss-Legendre rule of
    :func:`~lidarjax.maps.dct_quadrature_nodes` (exact to rounding, as the weights are
    band-limited like ``f^2``) as one matrix product per chunk:
    ``W = sum_nodes w cos(p x~) cos(q y~)`` — 5x faster at 40 x 40.
    """
    spec_shape = tuple(2 * n - 1 for n in shape)
    d = len(shape)
    n_nodes = quadrature_nodes(m)
    gl_x, gl_w = (jnp.asarray(v, origins.dtype) for v in np.polynomial.legendre.leggauss(n_nodes))
    freqs = [jnp.arange(k, dtype=origins.dtype) for k in spec_shape]

    def one_spectral(o, dr, r, u):
        st, vt, ell = _segment(m, o, dr, r)
        return jnp.where(u, ray_weights(spec_shape, st, vt, ell), 0.0)

    def chunk_quadrature(o, dr, r, u):
        st, vt, ell = jax.vmap(lambda a, b, c: _segment(m, a, b, c))(o, dr, r)  # [c d] [c d] [c]
        t = 0.5 * (gl_x + 1.0)[None, :] * ell[:, None]  # [c n]
        pts = st[:, None, :] + t[..., None] * vt[:, None, :]  # [c n d]
        wt = (0.5 * ell * u)[:, None] * gl_w[None, :]  # [c n]
        cos = [jnp.cos(pts[..., k, None] * freqs[k]).reshape(-1, spec_shape[k]) for k in range(d)]
        wt = wt.reshape(-1)
        if d == 2:
            return (cos[0] * wt[:, None]).T @ cos[1]
        return jnp.einsum("np,n,nq,ns->pqs", cos[0], wt, cos[1], cos[2])

    chunk = max(1, min(chunk_size, origins.shape[0]))
    # padding rays are unused (``use`` False) and finite (no NaN in reverse mode)
    fills = ((origins, 0.0), (directions, 1.0), (lengths, 0.0), (use, False))
    xs = tuple(pad_to_chunks(x, chunk, fill) for x, fill in fills)

    def body(acc, x):
        if method == "quadrature":
            return acc + chunk_quadrature(*x), None
        return acc + jnp.sum(jax.vmap(one_spectral)(*x), axis=0), None

    acc0 = jnp.zeros(spec_shape, origins.dtype)
    total, _ = jax.lax.scan(body, acc0, xs)
    return total


def _weights_method(method: str) -> str:
    if method not in ("spectral", "quadrature"):
        raise ValueError(f"method must be 'spectral' or 'quadrature', got {method!r}")
    return method


def dct_objective(
    rays: RayBatch,
    lower,
    extent,
    shape: tuple[int, ...],
    *,
    chunk_size: int = 256,
    check: bool = True,
    method: str = "spectral",
) -> DCTObjective:
    """Precompute the data term of the DCT fit for ``rays`` over the box
    ``[lower, lower + extent]`` with ``shape`` coefficients.

    Args:
        rays: mapping rays (any batch shape); with ``check`` every ray must carry evidence
            inside the box (:func:`~lidarjax.maps.rays_in_box`).
        lower, extent: ``[d]`` box corner and edge lengths (m).
        shape: coefficients per axis ``(L, M[, N])``.
        chunk_size: rays per ``vmap`` chunk when summing the weights.
        check: raise ``ValueError`` if some rays have no evidence in the box (a HIT end point
            outside it would make the likelihood 0 for every map).
        method: how the summed weights of HIT and SUP rays are integrated: ``"spectral"``
            (default) or ``"quadrature"`` (see ``_weights``).
    """
    if not isinstance(rays, RayBatch):
        raise ValueError(f"rays must be a RayBatch, got {type(rays).__name__}")
    shape = tuple(int(s) for s in shape)
    if len(shape) != rays.dim or any(s < 1 for s in shape):
        raise ValueError(f"shape must be {rays.dim} positive ints, got {shape}")
    flat = rays.flatten()
    if flat.ranges.shape[0] == 0:
        raise ValueError("rays is empty")
    probe = DCTMap(jnp.zeros(shape, flat.origins.dtype), lower, extent)
    if check:
        ok = np.asarray(rays_in_box(probe, flat))
        if not ok.all():
            raise ValueError(
                f"rays: {int((~ok).sum())} of {ok.size} rays carry no evidence inside the map "
                "box (HIT end point outside it, or the ray misses it); select rays with "
                "lidarjax.maps.rays_in_box"
            )
    length = flat.model_lengths()
    kind = np.asarray(flat.kind)
    use = jnp.asarray((kind == HIT) | (kind == SUP))
    w_free = _weights(
        probe,
        flat.origins,
        flat.directions,
        length,
        use,
        shape,
        chunk_size,
        _weights_method(method),
    )
    sub = np.flatnonzero(kind == SUB)
    spec_shape = tuple(2 * n - 1 for n in shape)
    if sub.size:
        w_sub = _chunked_stack(probe, flat, sub, length, chunk_size, spec_shape)
    else:
        w_sub = jnp.zeros((0,) + spec_shape, flat.origins.dtype)
    hit = np.flatnonzero(kind == HIT)
    ends = flat.origins[hit] + flat.ranges[hit, None] * flat.directions[hit]
    return DCTObjective(
        lower=probe.lower,
        extent=probe.extent,
        w_free=w_free,
        w_sub=w_sub,
        hit_points=probe.normalized(ends),
        n_rays=int(flat.ranges.shape[0]),
    )


@functools.partial(jax.jit, static_argnames=("spec_shape",))
def _stack_weights(probe, origins, directions, lengths, spec_shape):
    def one(o, d, r):
        st, vt, ell = _segment(probe, o, d, r)
        return ray_weights(spec_shape, st, vt, ell)

    return jax.vmap(one)(origins, directions, lengths)


def _chunked_stack(probe, flat, idx, length, chunk_size, spec_shape):
    """Per-ray weights ``[len(idx) *spectrum]`` in host-side chunks (the result is stored)."""
    out = []
    for lo in range(0, idx.size, chunk_size):
        sl = idx[lo : lo + chunk_size]
        out.append(
            _stack_weights(probe, flat.origins[sl], flat.directions[sl], length[sl], spec_shape)
        )
    return jnp.concatenate(out, axis=0)


MIN_RAY_BUCKET = 64
"""The smallest number of rays :func:`fit_dct` compiles its set-up and solve for."""


def ray_bucket(n: int, *, minimum: int = MIN_RAY_BUCKET) -> int:
    """The number of rays :func:`fit_dct` pads ``n`` rays to: the smallest ``m 2^k >= n``
    with ``m`` in 4..7 (quarter-octave steps, so at most 25 % of the rays are padding), at
    least ``minimum``; ``0`` stays ``0``. E.g. 2000 -> 2048, 2100 and 2500 -> 2560, 150 ->
    160. Every bucket compiles its own programs; inputs of one bucket share them."""
    n = int(n)
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    if n == 0:
        return 0
    n = max(n, int(minimum))
    k = max(n.bit_length() - 3, 0)  # n / 2^k in [4, 8)
    return -(-n // (1 << k)) << k


def _host_rays(rays: RayBatch) -> tuple[np.ndarray, ...]:
    """Flattened ``origins, directions, ranges, kind`` as NumPy arrays (no device op)."""
    d = rays.dim
    return (
        np.asarray(rays.origins).reshape(-1, d),
        np.asarray(rays.directions).reshape(-1, d),
        np.asarray(rays.ranges).reshape(-1),
        np.asarray(rays.kind).reshape(-1),
    )


def _padded(rays: RayBatch, arrays, n_pad: int) -> tuple[RayBatch, np.ndarray]:
    """``arrays`` (``origins, directions, ranges, kind``, ``[n ...]``) padded with inert
    rays to ``n_pad``: SUB rays of range 0 from the origin along the first axis, which the
    grid statistics ignore; the masks of :func:`_setup` remove them from every other term.
    Returns the batch (with the limits of ``rays``) and ``valid [n_pad]`` (True for the
    real rays)."""
    o, dr, r, k = arrays
    n, d = o.shape
    pad = n_pad - n
    e0 = np.zeros((pad, d), dr.dtype)
    e0[:, 0] = 1.0
    out = RayBatch._trusted(
        np.concatenate([o, np.zeros((pad, d), o.dtype)]),
        np.concatenate([dr, e0]),
        np.concatenate([r, np.zeros(pad, r.dtype)]),
        np.concatenate([k, np.full(pad, SUB, k.dtype)]),
        rays.r_min,
        rays.r_max,
    )
    return out, np.arange(n_pad) < n


def _box(lower, extent, d: int, dtype) -> tuple[np.ndarray, np.ndarray]:
    """The map box as NumPy arrays of ``dtype``, checked as :class:`DCTMap` checks it."""
    lower, extent = np.asarray(lower, dtype), np.asarray(extent, dtype)
    if lower.shape != (d,) or extent.shape != (d,):
        raise ValueError(
            f"lower and extent must have shape ({d},) for {d}-D coeffs, got "
            f"{lower.shape} and {extent.shape}"
        )
    if not np.all(extent > 0):
        raise ValueError(f"extent must be positive on every axis, got {extent}")
    return lower, extent


def _grid_spec(lower, extent, shape: tuple[int, ...], oversample: int) -> GridSpec:
    """The grid of :func:`grid_initial_map` (``ValueError`` for non-square cells)."""
    if not isinstance(oversample, int) or oversample < 1:
        raise ValueError(f"oversample must be a positive int, got {oversample!r}")
    ext = np.asarray(extent, float)
    res = ext / (oversample * np.asarray(shape, float))
    if not np.allclose(res, res[0], rtol=1e-9):
        raise ValueError(
            f"extent {ext} / shape {tuple(shape)} gives non-square cells {res}; the grid "
            "initialisation needs square cells (pass init= instead)"
        )
    return GridSpec(np.asarray(lower, float), float(res[0]), tuple(oversample * s for s in shape))


def _initial_map(spec: GridSpec, rays: RayBatch, shape, max_rate) -> DCTMap:
    return from_grid(decay_rate_map(accumulate(spec, rays)), tuple(shape), max_rate=max_rate)


_initial_map_program = checked_jit(_initial_map)


def grid_initial_map(
    rays: RayBatch,
    lower,
    extent,
    shape: tuple[int, ...],
    *,
    oversample: int = 2,
    max_rate: float | None = 20.0,
) -> DCTMap:
    """Initial guess of the fit (Sec. 9.4.4): the DCT of ``sqrt`` of the maximum-likelihood
    decay-rate grid map (Eq. 7.10) over the box, truncated to ``shape`` coefficients. The
    grid has ``oversample`` cells per coefficient and axis (the paper's one cell per
    coefficient, ``oversample=1``, interpolates the cell values exactly and rings between
    them, which leaves some HIT end points with ``f ~ 0`` and the optimiser crawling; the
    band-limited projection of a 2x finer grid does not). Cells no ray traversed get the
    global ML rate; rates are clipped at ``max_rate`` (1/m).

    The box must be split into square cells: ``extent / shape`` equal on every axis.
    Computed as one jitted program over the rays padded to :func:`ray_bucket` rays (the
    padding is ignored by the grid statistics).
    """
    if not isinstance(rays, RayBatch):
        raise ValueError(f"rays must be a RayBatch, got {type(rays).__name__}")
    shape = tuple(int(s) for s in shape)
    spec = _grid_spec(lower, extent, shape, oversample)
    if rays.dim != spec.dim:
        raise ValueError(f"rays are {rays.dim}-D but spec is a {spec.dim}-D grid")
    arrays = _host_rays(rays)
    n = arrays[2].shape[0]
    if n == 0:
        raise ValueError("rays is empty")
    padded, _ = _padded(rays, arrays, ray_bucket(n))
    return _initial_map_program(spec, padded, shape, max_rate)


def _sub_weights(probe: DCTMap, sub: RayBatch, sub_valid, chunk_size: int):
    """``[ns *spectrum]`` weights of the (padded) SUB rays; zero rows for the padding."""
    spec_shape = tuple(2 * n - 1 for n in probe.shape)

    def one(x):
        o, d, r, u = x
        st, vt, ell = _segment(probe, o, d, r)
        return jnp.where(u, ray_weights(spec_shape, st, vt, ell), 0.0)

    xs = (sub.origins, sub.directions, sub.model_lengths(), sub_valid)
    return jax.lax.map(one, xs, batch_size=min(chunk_size, sub.ranges.shape[0]))


@checked_jit
def _setup(
    shape, lower, extent, rays, valid, sub, sub_valid, n_rays, spec, chunk_size, method, max_rate
):
    """The whole set-up of :func:`fit_dct` as one program over padded rays: the bucketed
    objective, the number of real rays without evidence in the box, and the coefficients
    of :func:`grid_initial_map` (``spec`` given) or ``None``."""
    dtype = rays.origins.dtype
    probe = DCTMap(jnp.zeros(shape, dtype), lower, extent)
    length = rays.model_lengths()
    use = ((rays.kind == HIT) | (rays.kind == SUP)) & valid
    w_free = _weights(
        probe, rays.origins, rays.directions, length, use, probe.shape, chunk_size, method
    )
    if sub is None:
        w_sub = jnp.zeros((0,) + w_free.shape, dtype)
        sub_valid = jnp.zeros((0,), bool)
    else:
        w_sub = _sub_weights(probe, sub, sub_valid, chunk_size)
    ends = rays.origins + rays.ranges[:, None] * rays.directions
    obj = _BucketedObjective(
        lower=probe.lower,
        extent=probe.extent,
        w_free=w_free,
        w_sub=w_sub,
        sub_mask=sub_valid,
        hit_points=probe.normalized(ends),
        hit_mask=(rays.kind == HIT) & valid,
        n_rays=jnp.asarray(n_rays, dtype),
    )
    n_outside = jnp.sum(valid & ~rays_in_box(probe, rays))
    a0 = None
    if spec is not None:
        a0 = _initial_map(spec, rays, shape, max_rate).coeffs.astype(dtype)
    return obj, n_outside, a0


def _bucketed_setup(
    rays: RayBatch, shape, lower, extent, *, initial: bool, chunk_size: int = 256
) -> tuple[_BucketedObjective, jax.Array | None]:
    """Check the inputs, select and pad the rays on the host (NumPy) and run
    :func:`_setup`: the bucketed objective and, with ``initial``, the coefficients of
    :func:`grid_initial_map` (else ``None``)."""
    if not isinstance(rays, RayBatch):
        raise ValueError(f"rays must be a RayBatch, got {type(rays).__name__}")
    shape = tuple(int(s) for s in shape)
    if len(shape) != rays.dim or any(s < 1 for s in shape):
        raise ValueError(f"shape must be {rays.dim} positive ints, got {shape}")
    if not isinstance(chunk_size, int) or chunk_size <= 0:
        raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}")
    arrays = _host_rays(rays)
    n = arrays[2].shape[0]
    if n == 0:
        raise ValueError("rays is empty")
    dtype = arrays[0].dtype
    spec = _grid_spec(lower, extent, shape, 2) if initial else None
    lower, extent = _box(lower, extent, rays.dim, dtype)
    padded, valid = _padded(rays, arrays, ray_bucket(n))
    sub_idx = np.flatnonzero(arrays[3] == SUB)
    sub, sub_valid = None, None
    if sub_idx.size:
        sub_arrays = tuple(a[sub_idx] for a in arrays)
        # SUB rays are few (often none): their own, smaller bucket
        sub, sub_valid = _padded(rays, sub_arrays, ray_bucket(sub_idx.size, minimum=16))
    obj, n_outside, a0 = _setup(
        shape,
        lower,
        extent,
        padded,
        valid,
        sub,
        sub_valid,
        np.asarray(n, dtype),
        spec,
        chunk_size,
        "spectral",
        20.0,
    )
    n_outside = int(n_outside)
    if n_outside:
        raise ValueError(
            f"rays: {n_outside} of {n} rays carry no evidence inside the map "
            "box (HIT end point outside it, or the ray misses it); select rays with "
            "lidarjax.maps.rays_in_box"
        )
    return obj, a0


def _fit_box(init, shape, lower, extent):
    """``(shape, lower, extent)`` of a fit: ``init``'s box (and shape, which ``shape``
    must equal if given) or the given ones."""
    if init is not None:
        if not isinstance(init, DCTMap):
            raise ValueError(f"init must be a DCTMap, got {type(init).__name__}")
        shape = init.shape if shape is None else tuple(shape)
        if tuple(shape) != init.shape:
            raise ValueError(f"shape {tuple(shape)} differs from init.shape {init.shape}")
        lower, extent = init.lower, init.extent
    if shape is None or lower is None or extent is None:
        raise ValueError("pass shape, lower and extent, or an init map")
    return tuple(shape), lower, extent


def fit_dct(
    rays: RayBatch,
    shape: tuple[int, ...] | None = None,
    *,
    lower=None,
    extent=None,
    init: DCTMap | None = None,
    solver: optx.AbstractMinimiser | None = None,
    rtol: float = 1e-3,
    atol: float = 1e-3,
    max_steps: int = 1000,
    throw: bool = False,
    chunk_size: int = 256,
) -> tuple[DCTMap, optx.Solution]:
    """Maximum-likelihood DCT map of a ray set (the inverse model of Sec. 9.4.4).

    Maximises ``sum_k log p(z_k | A)`` over the coefficients ``A`` (minimising the negative
    mean per ray, so the tolerances are scale-free) with optimistix, starting from ``init``
    or from :func:`grid_initial_map`. The rays are padded to :func:`ray_bucket` rays (the
    SUB rays to their own bucket), so another ray count in the same bucket compiles
    nothing new (module docstring); the padding contributes exactly zero.

    Args:
        rays: mapping rays, all with evidence inside the box.
        shape: coefficients per axis; default ``init.shape``.
        lower, extent: ``[d]`` the box (m); default ``init``'s box.
        init: initial map (its box is used); default: DCT of the grid ML map.
        solver: an optimistix minimiser; default ``optx.LBFGS(rtol, atol)`` (module
            docstring).
        rtol, atol: tolerances of the default solver; ``rtol = 1e-3`` is the paper's stop
            at a relative log-likelihood change below 1e-3.
        max_steps: iteration limit.
        throw: raise if the solver fails (default: report it in ``Solution.result``).
        chunk_size: rays per ``vmap`` chunk in the precomputation.

    Returns:
        ``(map, solution)``: the fitted :class:`DCTMap` and optimistix's ``Solution``
        (``.stats["num_steps"]``, ``.result``).
    """
    shape, lower, extent = _fit_box(init, shape, lower, extent)
    obj, a0 = _bucketed_setup(
        rays, shape, lower, extent, initial=init is None, chunk_size=chunk_size
    )
    if a0 is None:
        a0 = jnp.asarray(init.coeffs, obj.w_free.dtype)
    if solver is None:
        solver = optx.LBFGS(rtol=rtol, atol=atol)
    sol = _minimise(obj, solver, a0, max_steps, throw)
    return DCTMap(sol.value, obj.lower, obj.extent), sol


@eqx.filter_jit
def _minimise(obj, solver, a0, max_steps, throw):
    def fn(a, args):
        return -args(a) / args.n_rays

    return optx.minimise(fn, solver, a0, args=obj, max_steps=max_steps, throw=throw)
