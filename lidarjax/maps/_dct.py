"""DCT maps (dissertation ch. 3 and 9): continuous, differentiable decay-rate maps whose
parameters are the spectral coefficients of the continuous extension of the inverse DCT.

A :class:`DCTMap` over the box ``[lower, lower + extent]`` defines, Eq. (9.6),

    lambda(x) = f(x)^2,   f(x) = sum_{l,m} a_lm cos(l x~) cos(m y~),   x~ = pi (x - x0) / X,

(and the 3-D analogue with ``[l m n]``). Space outside the box has decay rate 0: only the
part of a ray inside the box contributes to its optical depth ``S = int_0^r lambda``; a HIT
whose end point lies outside the box therefore has density 0 and a SUB ray whose first
``r_min`` metres miss the box has probability 0 (select rays with :func:`rays_in_box`).

Three ways to compute ``S`` for a ray, all exact (they agree to ~1e-12 in float64):

- ``method="paper"``: Eq. (9.10) (see :data:`PAPER_DEGENERATE_PHASE`), a double sum over
  all coefficient pairs ``(i, j)`` and the sign combinations ``alpha, beta, gamma`` —
  ``O(I^2)`` per ray with ``I = L M`` coefficients; the reference.
- ``method="spectral"``: ``lambda`` is itself a cosine series with
  ``(2L-1) x (2M-1)`` coefficients (:func:`dct_spectrum`, computed once per map), so ``S`` is
  a sum of ``O(4 L M)`` closed-form terms ``r cos(theta_mid) sinc(omega r / 2)`` per ray.
  The ``sinc`` form equals Eq. (9.10)'s ``[sin]_0^r / denominator`` and its limit
  ``r cos(theta_0)`` for a zero denominator, and stays accurate when the denominator is
  merely tiny (where Eq. 9.10 cancels catastrophically).
- ``method="quadrature"``: Gauss-Legendre quadrature of ``f^2`` along the ray with a node
  count derived from the map's highest frequency and the box diagonal
  (:func:`quadrature_nodes`), so the error is at machine precision.
- ``method="auto"`` (default): spectral for small maps, quadrature for large ones
  (:data:`AUTO_SPECTRAL_MAX_PARAMETERS`).

Length (~700 lines): the DCT map type, its spectrum, the closed-form optical depth and
its derivatives (Eqs. 9.5, 9.9-9.12) and the quadrature path belong to one map type and
share private helpers; the fit lives in ``_fit.py``.
"""

from __future__ import annotations

import functools
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ..rays import HIT, SUB, RayBatch, is_concrete
from ..raytrace import GridSpec
from ._field import (
    AbstractDecayRateField,
    box_segment,
    combine_log_likelihood,
    map_chunks,
)
from ._grid import DecayRateMap

METHODS = ("auto", "paper", "spectral", "quadrature")


class DCTMap(AbstractDecayRateField):
    """A DCT decay-rate map, Eq. (9.6).

    Attributes:
        coeffs: ``[L M]`` (2-D) or ``[L M N]`` (3-D) spectral coefficients ``a_lm`` (the
            decay rate is the square of their cosine series, so units are sqrt(1/m)).
        lower: ``[d]`` world coordinates (m) of the box's lower corner.
        extent: ``[d]`` box edge lengths ``X, Y[, Z]`` (m).
    """

    coeffs: Float[Array, "*shape"]
    lower: Float[Array, " d"]
    extent: Float[Array, " d"]

    def __init__(self, coeffs: ArrayLike, lower: ArrayLike, extent: ArrayLike):
        coeffs = jnp.asarray(coeffs)
        if not jnp.issubdtype(coeffs.dtype, jnp.floating):
            coeffs = coeffs.astype(jnp.result_type(float))
        if coeffs.ndim not in (2, 3) or any(s < 1 for s in coeffs.shape):
            raise ValueError(f"coeffs must have shape [L M] or [L M N], got {coeffs.shape}")
        lower = jnp.asarray(lower, coeffs.dtype)
        extent = jnp.asarray(extent, coeffs.dtype)
        d = coeffs.ndim
        if lower.shape != (d,) or extent.shape != (d,):
            raise ValueError(
                f"lower and extent must have shape ({d},) for {d}-D coeffs, got "
                f"{lower.shape} and {extent.shape}"
            )
        if is_concrete(extent) and not np.all(np.asarray(extent) > 0):
            raise ValueError(f"extent must be positive on every axis, got {np.asarray(extent)}")
        if is_concrete(coeffs) and not np.all(np.isfinite(np.asarray(coeffs))):
            raise ValueError("coeffs must be finite")
        self.coeffs, self.lower, self.extent = coeffs, lower, extent

    @property
    def dim(self) -> int:
        """Spatial dimension (2 or 3)."""
        return self.coeffs.ndim

    @property
    def shape(self) -> tuple[int, ...]:
        """Number of coefficients per axis ``(L, M[, N])``."""
        return tuple(self.coeffs.shape)

    @property
    def n_parameters(self) -> int:
        """``I = L M [N]``, the number of real parameters (the memory budget)."""
        return math.prod(self.shape)

    @property
    def upper(self) -> Float[Array, " d"]:
        """``[d]`` upper corner of the box (m)."""
        return self.lower + self.extent

    def normalized(self, points: Float[ArrayLike, "*b d"]) -> Float[Array, "*b d"]:
        """pi-normalised coordinates ``x~ = pi (x - lower) / extent`` (rad)."""
        return jnp.pi * (jnp.asarray(points) - self.lower) / self.extent

    def contains(self, points: Float[ArrayLike, "*b d"]) -> Array:
        """``[*b]`` bool: the points lie inside the closed box."""
        p = jnp.asarray(points)
        return jnp.all((p >= self.lower) & (p <= self.upper), axis=-1)

    def amplitude(self, points: Float[ArrayLike, "*b d"]) -> Float[Array, "*b"]:
        """The CEIDCT ``f(x) = sum a_lm cos(l x~) cos(m y~)`` (before squaring) at points,
        evaluated with the cosine series (its 2-pi-periodic even extension outside the box).
        """
        p = jnp.asarray(points)
        if p.shape[-1:] != (self.dim,):
            raise ValueError(f"points must have shape [..., {self.dim}], got {p.shape}")
        return _amplitude(self.coeffs, self.normalized(p))

    def smoothed(self, sigma_m: float) -> DCTMap:
        """The map whose amplitude ``f`` is convolved with a Gaussian of standard deviation
        ``sigma_m`` (m) (applied to the even periodic extension): each coefficient is scaled
        by ``exp(-sigma^2 |k|^2 / 2)`` with ``k = pi (l / X, m / Y)`` rad/m. A wider basin
        for coarse-to-fine pose refinement; ``sigma_m = 0`` returns the map. ``sigma_m`` may
        be traced (e.g. scanned over a blur schedule)."""
        if is_concrete(sigma_m):
            if not (np.isfinite(sigma_m) and sigma_m >= 0):
                raise ValueError(f"sigma_m must be finite and >= 0, got {sigma_m!r}")
            if sigma_m == 0:
                return self
        k2 = 0.0
        for ax, n in enumerate(self.shape):
            shape = [1] * self.dim
            shape[ax] = n
            kk = jnp.pi * jnp.arange(n, dtype=self.coeffs.dtype) / self.extent[ax]
            k2 = k2 + (kk**2).reshape(shape)
        return DCTMap(self.coeffs * jnp.exp(-0.5 * sigma_m**2 * k2), self.lower, self.extent)

    def decay_rate(self, points: Float[ArrayLike, "*b d"]) -> Float[Array, "*b"]:
        """``lambda(x) = f(x)^2`` (1/m), Eq. (9.6); 0 outside the box."""
        p = jnp.asarray(points)
        lam = self.amplitude(p) ** 2
        return jnp.where(self.contains(p), lam, 0.0)

    def integral(
        self,
        origins: Float[Array, "n d"],
        directions: Float[Array, "n d"],
        lengths: Float[Array, " n"],
    ) -> Float[Array, " n"]:
        """Optical depth per ray (:func:`optical_depth` with ``method="auto"``); the
        :class:`~lidarjax.maps.AbstractDecayRateField` interface."""
        return optical_depth(self, origins, directions, lengths)

    def parameters(self) -> Float[Array, "*shape"]:
        """The coefficients (unconstrained: ``lambda = f^2 >= 0`` for any value)."""
        return self.coeffs

    def with_parameters(self, params: Float[Array, "*shape"]) -> DCTMap:
        """The map with coefficients ``params`` over the same box."""
        return DCTMap(params, self.lower, self.extent)


def _amplitude(coeffs, xt):
    """``f`` at normalised coordinates ``xt [*b d]``."""
    bases = [
        jnp.cos(jnp.arange(n, dtype=xt.dtype) * xt[..., k, None])
        for k, n in enumerate(coeffs.shape)
    ]
    if coeffs.ndim == 2:
        out = jnp.einsum("...l,lm,...m->...", bases[0], coeffs, bases[1])
    else:
        out = jnp.einsum("...l,lmn,...m,...n->...", bases[0], coeffs, bases[1], bases[2])
    return out


# --------------------------------------------------------------------------------------
# the decay rate as a cosine series (the spectral fast path)


def dct_spectrum(coeffs: Float[Array, "*shape"]) -> Float[Array, "*spectrum"]:
    """Cosine-series coefficients of ``lambda = f^2``: ``lambda(x) = sum_{p,q} c_pq cos(p x~)
    cos(q y~)`` with ``p < 2L - 1``, ``q < 2M - 1`` (the product-to-sum expansion of
    Eq. 9.7 with the terms of equal frequency grouped). Differentiable;
    ``[2L-1 2M-1]`` or ``[2L-1 2M-1 2N-1]``.

    Computed as the autoconvolution of the even exponential-series coefficients
    (``cos(l x) = (e^{ilx} + e^{-ilx}) / 2``) with a real FFT: ``O(I log I)`` instead of the
    ``O(I^2)`` pair sum.
    """
    b = coeffs
    for k, n in enumerate(coeffs.shape):
        w = np.full(n, 0.5)
        w[0] = 1.0
        shape = [1] * coeffs.ndim
        shape[k] = n
        b = b * jnp.asarray(w.reshape(shape), coeffs.dtype)
        b = jnp.concatenate([jnp.flip(jax.lax.slice_in_dim(b, 1, n, axis=k), axis=k), b], axis=k)
    sizes = tuple(_fft_size(4 * n - 3) for n in coeffs.shape)
    axes = tuple(range(coeffs.ndim))
    spec = jnp.fft.rfftn(b, s=sizes, axes=axes)
    conv = jnp.fft.irfftn(spec * spec, s=sizes, axes=axes)
    out = conv
    for k, n in enumerate(coeffs.shape):
        out = jax.lax.slice_in_dim(out, 2 * n - 2, 4 * n - 3, axis=k)
        w = np.full(2 * n - 1, 2.0)
        w[0] = 1.0
        shape = [1] * coeffs.ndim
        shape[k] = 2 * n - 1
        out = out * jnp.asarray(w.reshape(shape), coeffs.dtype)
    return out


def _fft_size(n: int) -> int:
    """Smallest 2^a 3^b 5^c >= n."""
    best = 1 << (n - 1).bit_length()
    for a in range(best.bit_length() + 1):
        for b in range(12):
            v = (1 << a) * 3**b
            if v >= n:
                best = min(best, v)
                break
            for c in range(1, 8):
                w = v * 5**c
                if w >= n:
                    best = min(best, w)
                    break
    return best


def _signs(d: int) -> np.ndarray:
    """The ``2^(d-1)`` sign vectors ``(1, +-1, ...)`` of the product-to-sum formula."""
    return np.array([(1,) + s for s in itertools.product((1, -1), repeat=d - 1)], float)


def ray_weights(spectrum_shape: tuple[int, ...], st, vt, length):
    """Weights ``W_pq`` with ``S = int_0^length lambda = sum_pq c_pq W_pq`` for a ray that
    starts at normalised ``st [d]`` with normalised direction ``vt [d]`` (rad/m):
    ``W_pq = length / 2^(d-1) sum_signs cos(theta_mid) sinc(omega length / 2)`` with
    ``theta = p x~ +- q y~`` and ``omega = p v~x +- q v~y`` (the closed-form integral of each
    cosine term, equal to Eq. 9.10's ``[sin]_0^r / omega`` and to ``r cos(theta_0)`` at
    ``omega = 0``). ``S`` is linear in the spectrum, so the map fit sums ``W`` over rays
    once."""
    d = len(spectrum_shape)
    freqs = [jnp.arange(n, dtype=st.dtype) for n in spectrum_shape]
    mid = st + vt * (0.5 * length)
    half = vt * (0.5 * length)
    # exp(i f x) per axis; the phases of the (p, q) grid are outer products, so the only
    # transcendental functions are the O(L + M) ones here.
    e_mid = [jnp.exp(1j * f * mid[k]) for k, f in enumerate(freqs)]
    e_half = [jnp.exp(1j * f * half[k]) for k, f in enumerate(freqs)]
    w_axis = [f * half[k] for k, f in enumerate(freqs)]
    total = 0.0
    for sign in _signs(d):
        em, eh, w = e_mid[0], e_half[0], w_axis[0]
        for k in range(1, d):
            nm = e_mid[k] if sign[k] > 0 else jnp.conj(e_mid[k])
            nh = e_half[k] if sign[k] > 0 else jnp.conj(e_half[k])
            em = jnp.multiply.outer(em, nm)
            eh = jnp.multiply.outer(eh, nh)
            w = jnp.add.outer(w, sign[k] * w_axis[k])
        # int_0^r cos(theta0 + omega r') dr' = r cos(theta_mid) sinc(omega r / 2)
        total = total + jnp.real(em) * _sinc(w, jnp.imag(eh))
    return total * (length / (2 ** (d - 1)))


def _sinc(w, sin_w):
    """``sin(w) / w`` given ``sin(w)``; the Taylor series below ``|w| < 1e-3`` (where the
    division loses digits), NaN-free gradients at ``w = 0``."""
    small = jnp.abs(w) < 1e-3
    w2 = w * w
    taylor = 1.0 - w2 / 6.0 + w2 * w2 / 120.0
    return jnp.where(small, taylor, sin_w / jnp.where(small, 1.0, w))


def _depth_spectral(spectrum, st, vt, length):
    """``int_0^length lambda`` from the spectrum (see :func:`ray_weights`)."""
    return jnp.sum(spectrum * ray_weights(spectrum.shape, st, vt, length))


# --------------------------------------------------------------------------------------
# Eq. (9.10) as written (reference path, O(I^2) per ray)


def _pair_frequencies(shape: tuple[int, ...]) -> np.ndarray:
    """Frequencies of every term of Eq. (9.10): ``[K I I d]`` with ``K = 2^(2d-1)`` sign
    combinations; term ``(k, i, j)`` has frequency ``beta_k (idx_i + alpha_k idx_j)``."""
    d = len(shape)
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, d)
    out = []
    for alpha in itertools.product((1, -1), repeat=d):
        for beta in _signs(d):
            f = beta * (idx[:, None, :] + np.asarray(alpha) * idx[None, :, :])
            out.append(f)
    return np.stack(out).astype(float)


PAPER_DEGENERATE_PHASE = 1e-3
"""The ``"paper"`` path treats a term of Eq. (9.10) as degenerate when its phase change over
the ray ``|den r|`` is below this (not only at ``den == 0`` exactly, as printed): for tiny
nonzero ``den`` — e.g. a ray along a box diagonal, where ``(l_i + l_j) v~x - (m_i + m_j) v~y``
rounds to 1e-16 — the printed quotient ``[sin]_0^r / den`` cancels catastrophically. There
the degenerate case ``r cos(theta_0)`` is extended by its series in ``den r`` to third
order (truncation error ``< r (den r)^4 / 24 ~ 4e-14 r``)."""


def _paper_A(shape, st, vt, length):
    """``A(i, j, alpha, beta, gamma)`` of Eq. (9.10) for all terms, ``[K I I]``."""
    fr = jnp.asarray(_pair_frequencies(shape), st.dtype)
    den = fr @ vt  # [K I I]
    theta0 = fr @ st
    x = den * length
    zero = jnp.abs(x) < PAPER_DEGENERATE_PHASE
    den_safe = jnp.where(zero, 1.0, den)
    regular = (jnp.sin(theta0 + den_safe * length) - jnp.sin(theta0)) / den_safe
    x2 = x * x
    series = length * (
        jnp.cos(theta0) * (1.0 - x2 / 6.0) - jnp.sin(theta0) * 0.5 * x * (1.0 - x2 / 12.0)
    )
    return jnp.where(zero, series, regular)


def _depth_paper(coeffs, st, vt, length):
    a = coeffs.reshape(-1)
    A = _paper_A(coeffs.shape, st, vt, length)
    k = A.shape[0]
    return jnp.einsum("i,kij,j->", a, A, a) / k


# --------------------------------------------------------------------------------------
# Gauss-Legendre quadrature path


def quadrature_nodes(m: DCTMap) -> int:
    """Gauss-Legendre node count for ``method="quadrature"``, from the coefficient shape
    alone (so it is static under ``jit``). Along a ray inside the box, axis ``k`` advances
    by at most ``X_k``, i.e. by at most ``pi`` in ``x~_k``, so the phase of the highest
    frequency of ``f^2`` (``2 (n_k - 1)`` per axis) changes by at most
    ``2 pi sum_k (n_k - 1)`` over the ray; on the reference interval ``[-1, 1]`` the
    integrand is a sum of ``exp(i kappa u)`` with ``kappa <= pi sum_k (n_k - 1)``.
    Gauss-Legendre with ``n`` nodes is exact to degree ``2n - 1`` and the Chebyshev
    coefficients of ``exp(i kappa u)`` decay like ``(e kappa / 2k)^k``, so
    ``n = kappa / 2 + 6 kappa^(1/3) + 10`` reaches machine precision (checked in the
    tests)."""
    kappa = np.pi * sum(n - 1 for n in m.shape)
    return int(math.ceil(kappa / 2 + 6 * kappa ** (1 / 3) + 10))


AUTO_SPECTRAL_MAX_PARAMETERS = 256
"""``method="auto"`` uses the spectral path up to this many coefficients and quadrature
above (measured on 2 CPU cores, 2-D: spectral 6.5 us/ray vs quadrature 66 us/ray at
10 x 10, but 1.1 ms vs 0.59 ms at 40 x 40 — the spectral path's ``(2L-1)(2M-1)``
element-wise terms lose to quadrature's matrix products as ``L M`` grows)."""


def resolve_method(m: DCTMap, method: str) -> str:
    """The concrete path for ``method`` (``"auto"`` picks by the number of coefficients)."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if method == "auto":
        return "spectral" if m.n_parameters <= AUTO_SPECTRAL_MAX_PARAMETERS else "quadrature"
    return method


def _depth_quadrature(coeffs, st, vt, length, nodes, weights):
    u = 0.5 * (nodes + 1.0) * length  # [n]
    pts = st + u[:, None] * vt  # [n d]
    f = _amplitude(coeffs, pts)
    return 0.5 * length * jnp.sum(weights * f**2)


# --------------------------------------------------------------------------------------
# clipping rays to the box and the log-likelihood


def _segment(m: DCTMap, origin, direction, length):
    """Normalised start point, normalised direction and length of the in-box part."""
    t0, t1 = box_segment(m.lower, m.upper, origin, direction, length)
    st = m.normalized(origin + t0 * direction)
    vt = jnp.pi * direction / m.extent
    return st, vt, t1 - t0


def _ray_depth(m: DCTMap, method: str, spectrum, quad, origin, direction, length):
    st, vt, ell = _segment(m, origin, direction, length)
    if method == "paper":
        return _depth_paper(m.coeffs, st, vt, ell)
    if method == "spectral":
        return _depth_spectral(spectrum, st, vt, ell)
    return _depth_quadrature(m.coeffs, st, vt, ell, *quad)


def _check(m, rays, method, chunk_size):
    if not isinstance(m, DCTMap):
        raise ValueError(f"map must be a DCTMap, got {type(m).__name__}")
    if not isinstance(rays, RayBatch):
        raise ValueError(f"rays must be a RayBatch, got {type(rays).__name__}")
    if rays.dim != m.dim:
        raise ValueError(f"rays are {rays.dim}-D but the DCT map is {m.dim}-D")
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if not isinstance(chunk_size, int) or chunk_size <= 0:
        raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}")


@functools.partial(jax.jit, static_argnames=("method", "chunk_size", "n_nodes"))
def _optical_depth(m, origins, directions, lengths, method, chunk_size, n_nodes):
    spectrum = dct_spectrum(m.coeffs) if method == "spectral" else None
    quad = None
    if method == "quadrature":
        x, w = np.polynomial.legendre.leggauss(n_nodes)
        quad = (jnp.asarray(x, origins.dtype), jnp.asarray(w, origins.dtype))
    fn = functools.partial(_ray_depth, m, method, spectrum, quad)
    if origins.shape[0] == 0:
        return jnp.zeros((0,), origins.dtype)
    return map_chunks(jax.vmap(fn), (origins, directions, lengths), chunk_size)


def optical_depth(
    map: DCTMap,
    origins: Float[ArrayLike, "n d"],
    directions: Float[ArrayLike, "n d"],
    lengths: Float[ArrayLike, " n"],
    *,
    method: str = "auto",
    chunk_size: int = 1024,
    n_nodes: int | None = None,
) -> Float[Array, " n"]:
    """``S(s, v, r) = int_0^r lambda(s + v r') dr'`` per ray, Eq. (9.10) (only the part of
    the ray inside the box contributes).

    Args:
        map: the DCT map.
        origins: ``[n d]`` ray origins (m).
        directions: ``[n d]`` unit directions.
        lengths: ``[n]`` distances ``r`` (m), ``>= 0`` (``inf`` integrates to the box exit).
        method: ``"auto"`` (default), ``"paper"`` (Eq. 9.10, O(I^2) per ray),
            ``"spectral"`` or ``"quadrature"`` (see the module docstring).
        chunk_size: rays evaluated together (``vmap``); chunks run with ``lax.map``.
        n_nodes: Gauss-Legendre nodes for ``"quadrature"``; default
            :func:`quadrature_nodes`.

    Returns:
        ``[n]`` optical depths (dimensionless).
    """
    o = jnp.asarray(origins)
    d = jnp.asarray(directions, o.dtype)
    r = jnp.asarray(lengths, o.dtype)
    if o.ndim != 2 or o.shape[-1] != map.dim or d.shape != o.shape or r.shape != o.shape[:1]:
        raise ValueError(
            f"origins, directions must be [n {map.dim}] and lengths [n]; got {o.shape}, "
            f"{d.shape}, {r.shape}"
        )
    method = resolve_method(map, method)
    if method != "quadrature":
        n_nodes = 0
    elif n_nodes is None:
        n_nodes = quadrature_nodes(map)
    elif not isinstance(n_nodes, int) or n_nodes < 1:
        raise ValueError(f"n_nodes must be a positive int, got {n_nodes!r}")
    return _optical_depth(map, o, d, r, method, chunk_size, n_nodes)


def log_likelihood(
    map: DCTMap,
    rays: RayBatch,
    *,
    method: str = "auto",
    chunk_size: int = 1024,
    n_nodes: int | None = None,
) -> Float[Array, "*batch"]:
    """Log-likelihood of each ray under a DCT map, Eqs. (9.5), (9.9), (9.11), (9.12).

    - HIT at range ``r``: ``log p(r) = log lambda(s + v r) - S(s, v, r)`` (a density, 1/m).
    - SUB: ``log P(sub) = log(1 - exp(-S(s, v, r_min)))`` (Eq. 9.11).
    - SUP: ``log P(super) = -S(s, v, r_max)`` (Eq. 9.12).

    ``lambda = 0`` outside the box (module docstring): a HIT end point outside the box gives
    ``-inf``. Differentiable in the coefficients and in the rays (hence the sensor pose);
    values and gradients are NaN-free.

    Args:
        map: the DCT map.
        rays: ``[*batch]`` rays of the map's dimension.
        method: ``"auto"`` (default), ``"spectral"``, ``"quadrature"`` or ``"paper"``
            (Eq. 9.10 as written, ``O(I^2)`` per ray: small maps only).
        chunk_size: rays per ``vmap`` chunk (memory bound).
        n_nodes: quadrature nodes (default :func:`quadrature_nodes`).

    Returns:
        ``[*batch]`` log-likelihoods (nats).
    """
    _check(map, rays, method, chunk_size)
    flat = rays.flatten()
    length = flat.model_lengths()
    depth = optical_depth(
        map,
        flat.origins,
        flat.directions,
        length,
        method=method,
        chunk_size=chunk_size,
        n_nodes=n_nodes,
    )
    lam = map.decay_rate(flat.origins + flat.ranges[:, None] * flat.directions)
    return combine_log_likelihood(flat.kind, lam, depth).reshape(rays.shape)


def rays_in_box(map: DCTMap, rays: RayBatch) -> Array:
    """``[*batch]`` bool: rays whose evidence lies in the map box — HIT rays ending inside
    it, SUB rays whose first ``r_min`` metres reach it and SUP rays that cross it."""
    flat = rays.flatten()
    length = flat.model_lengths()
    t0, t1 = jax.vmap(lambda o, d, r: box_segment(map.lower, map.upper, o, d, r))(
        flat.origins, flat.directions, jnp.minimum(length, 1e30)
    )
    end_in = map.contains(flat.origins + flat.ranges[:, None] * flat.directions)
    ok = jnp.where(flat.kind == HIT, end_in, t1 > t0)
    return ok.reshape(rays.shape)


# --------------------------------------------------------------------------------------
# the paper's closed-form derivatives (Sec. 9.4.4)


def _basis(shape, xt):
    """``phi_i(x) = prod_k cos(idx_i^k x~_k)``, ``[I]`` at one normalised point."""
    vecs = [jnp.cos(jnp.arange(n, dtype=xt.dtype) * xt[k]) for k, n in enumerate(shape)]
    out = vecs[0]
    for v in vecs[1:]:
        out = jnp.multiply.outer(out, v)
    return out.reshape(-1)


def closed_form_terms(map: DCTMap, origin, direction, r, length):
    """The paper's shortcut quantities for one ray (Sec. 9.4.4), from Eq. (9.10):

    Args:
        map: the DCT map.
        origin, direction: ``[d]`` the ray.
        r: end-point range (m) where ``lambda`` and ``B`` are evaluated (HIT).
        length: range up to which ``S`` and ``C`` are integrated (``r``, ``r_min``, ``r_max``).

    Returns:
        dict with ``lam`` (``lambda`` at the end point), ``B_ij [I I]`` (``2 phi_i phi_j``),
        ``B_i [I]`` (``sum_j a_j B_ij``), ``C_ij [I I]`` (``1/8 sum (A_ij + A_ji)``),
        ``C_i [I]`` (``sum_j a_j C_ij``), ``S`` and ``N = exp(-S)`` (Eq. 9.9).
    """
    a = map.coeffs.reshape(-1)
    st, vt, ell = _segment(map, origin, direction, length)
    A = _paper_A(map.shape, st, vt, ell)  # [K I I]
    k = A.shape[0]
    C_ij = jnp.sum(A + jnp.swapaxes(A, -1, -2), axis=0) / k
    C_i = C_ij @ a
    S = jnp.einsum("i,kij,j->", a, A, a) / k
    end = origin + r * direction
    phi = _basis(map.shape, map.normalized(end)) * map.contains(end)
    B_ij = 2.0 * jnp.outer(phi, phi)
    B_i = B_ij @ a
    lam = (phi @ a) ** 2
    return dict(lam=lam, B_ij=B_ij, B_i=B_i, C_ij=C_ij, C_i=C_i, S=S, N=jnp.exp(-S))


def closed_form_derivatives(
    map: DCTMap, rays: RayBatch, *, sub_hessian: str = "corrected"
) -> tuple[Float[Array, "n I"], Float[Array, "n I I"]]:
    """First and second derivatives of each ray's log-likelihood w.r.t. the coefficients,
    from the closed forms of Sec. 9.4.4 (``O(I^2)`` per ray; for checks on small maps):

    - gradient: ``N C_i / (1 - N)`` (SUB), ``B_i / lambda - C_i`` (HIT), ``-C_i`` (SUP);
    - Hessian: ``B_ij / lambda - B_i B_j / lambda^2 - C_ij`` (HIT), ``-C_ij`` (SUP), and for
      SUB ``N (C_ij - C_i C_j) / (1 - N) - N^2 C_i C_j / (1 - N)^2``.

    The dissertation prints the last SUB term with a plus sign,
    ``+ N^2 C_i C_j / (1 - N)^2``; differentiating its own first derivative
    ``N C_i / (1 - N)`` (with ``dN/da_j = -N C_j``) gives the minus sign, which is what
    ``jax.hessian`` confirms. ``sub_hessian="paper"`` returns the printed version.

    Args:
        map: the DCT map (coefficients flattened row-major, ``i = l M + m``).
        rays: ``[n]`` rays (flattened).
        sub_hessian: ``"corrected"`` (default) or ``"paper"``.

    Returns:
        ``(grad [n I], hess [n I I])``.
    """
    if sub_hessian not in ("corrected", "paper"):
        raise ValueError(f"sub_hessian must be 'corrected' or 'paper', got {sub_hessian!r}")
    _check(map, rays, "paper", 1)
    flat = rays.flatten()
    length = flat.model_lengths()
    sign = 1.0 if sub_hessian == "paper" else -1.0

    def one(o, d, r, ell, kind):
        t = closed_form_terms(map, o, d, r, ell)
        lam, N = t["lam"], t["N"]
        Ci, Cij, Bi, Bij = t["C_i"], t["C_ij"], t["B_i"], t["B_ij"]
        g_hit = Bi / lam - Ci
        h_hit = Bij / lam - jnp.outer(Bi, Bi) / lam**2 - Cij
        g_sub = N * Ci / (1 - N)
        CC = jnp.outer(Ci, Ci)
        h_sub = N * (Cij - CC) / (1 - N) + sign * N**2 * CC / (1 - N) ** 2
        g = jnp.where(kind == HIT, g_hit, jnp.where(kind == SUB, g_sub, -Ci))
        h = jnp.where(kind == HIT, h_hit, jnp.where(kind == SUB, h_sub, -Cij))
        return g, h

    return jax.vmap(one)(flat.origins, flat.directions, flat.ranges, length, flat.kind)


# --------------------------------------------------------------------------------------
# conversion from / to grid maps


def _dct_matrix(n_cells: int, n_coeffs: int, dtype) -> np.ndarray:
    """``T[c, l] = cos(pi l (c + 1/2) / n_cells)``: the CEIDCT basis at cell centres."""
    c = np.arange(n_cells)[:, None] + 0.5
    return np.cos(np.pi * np.arange(n_coeffs)[None, :] * c / n_cells).astype(dtype)


def from_grid(
    grid: DecayRateMap, shape: tuple[int, ...] | None = None, *, max_rate: float | None = None
) -> DCTMap:
    """DCT map whose amplitude ``f`` is the least-squares (DCT-II) projection of
    ``sqrt(lambda)`` of a grid map onto the first ``shape`` cosines — the initial guess of
    the DCT fit (Sec. 9.4.4). With ``shape == grid.spec.shape`` it interpolates: ``f`` at the
    cell centres equals ``sqrt(lambda_i)``.

    Args:
        grid: a decay-rate grid map (its box becomes the DCT map's box).
        shape: coefficients per axis (default: the grid's shape); at most the grid's.
        max_rate: clip rates above this (1/m) before the transform (tames the ringing of
            cells with a tiny traversed length); ``None`` = no clipping.

    Returns:
        A :class:`DCTMap` over the grid's box.
    """
    if not isinstance(grid, DecayRateMap):
        raise ValueError(f"grid must be a DecayRateMap, got {type(grid).__name__}")
    gshape = grid.spec.shape
    shape = gshape if shape is None else tuple(int(s) for s in shape)
    if len(shape) != len(gshape) or any(s < 1 or s > g for s, g in zip(shape, gshape)):
        raise ValueError(f"shape must be {len(gshape)} ints in [1, {gshape}], got {shape}")
    rates = grid.rates
    if max_rate is not None:
        rates = jnp.minimum(rates, max_rate)
    g = jnp.sqrt(jnp.maximum(rates, 0.0))
    a = g
    for k, (nc, nk) in enumerate(zip(gshape, shape)):
        T = _dct_matrix(nc, nk, np.float64)
        scale = np.full(nk, 2.0 / nc)
        scale[0] = 1.0 / nc
        proj = jnp.asarray(T * scale[None, :], g.dtype)  # [nc nk]
        a = jnp.moveaxis(jnp.tensordot(a, proj, axes=([k], [0])), -1, k)
    spec = grid.spec
    ext = jnp.asarray(gshape, spec.origin.dtype) * spec.resolution
    return DCTMap(a, spec.origin, ext)


def to_grid(map: DCTMap, cells: tuple[int, ...] | None = None) -> DecayRateMap:
    """Decay rates at the cell centres of a regular grid over the box (for plotting and
    the cell-wise comparison of Table 9.2); ``outside_rate = 0`` as in the DCT model.

    Args:
        map: the DCT map.
        cells: cells per axis (default 8 per coefficient).
    """
    cells = tuple(8 * s for s in map.shape) if cells is None else tuple(int(c) for c in cells)
    if len(cells) != map.dim or any(c < 1 for c in cells):
        raise ValueError(f"cells must be {map.dim} positive ints, got {cells}")
    if not is_concrete(map.extent):
        raise ValueError("to_grid needs a concrete map extent")
    ext = np.asarray(map.extent, float)
    res = ext / np.asarray(cells)
    if not np.allclose(res, res[0], rtol=1e-9):
        raise ValueError(
            f"cells {cells} give non-square cells {res} for the extent {ext}; choose cells "
            "proportional to the extent"
        )
    spec = GridSpec(map.lower, float(res[0]), cells)
    bases = [
        jnp.asarray(_dct_matrix(c, n, np.float64), map.coeffs.dtype)
        for c, n in zip(cells, map.shape)
    ]
    f = map.coeffs
    for k, T in enumerate(bases):
        f = jnp.moveaxis(jnp.tensordot(f, T, axes=([k], [1])), -1, k)
    zero = jnp.zeros((), map.coeffs.dtype)
    return DecayRateMap(spec=spec, rates=f**2, outside_rate=zero)


__all__ = [
    "DCTMap",
    "METHODS",
    "PAPER_DEGENERATE_PHASE",
    "closed_form_derivatives",
    "closed_form_terms",
    "dct_spectrum",
    "from_grid",
    "log_likelihood",
    "optical_depth",
    "quadrature_nodes",
    "resolve_method",
    "AUTO_SPECTRAL_MAX_PARAMETERS",
    "ray_weights",
    "rays_in_box",
    "to_grid",
]
