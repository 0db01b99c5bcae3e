"""Decay-rate fields: the library's central map abstraction (dissertation ch. 1.3 and 3).

Unlike the reflection model, the decay-rate model needs no cells: any non-negative field
``lambda(x)`` (1/m) defines a consistent forward model (Eqs. 9.3-9.5, 9.11, 9.12),

- HIT at range ``r``: ``p(r) = lambda(s + r v) exp(-S(r))``, a density (1/m),
- SUB (reflected before ``r_min``): ``P = 1 - exp(-S(r_min))``,
- SUP (no return up to ``r_max``): ``P = exp(-S(r_max))``,

with the optical depth ``S(r) = int_0^r lambda(s + t v) dt``, and hence an inverse model:
maximise ``sum_k log p(z_k | lambda)`` over the field's parameters.

A field is an :class:`AbstractDecayRateField`: it implements ``decay_rate(points)`` and
``integral(origins, directions, lengths)``; :func:`field_log_likelihood` (the forward model)
and :func:`fit` (the inverse model, optimistix) are written once on top of these two.
Concrete fields:

- :class:`~lidarjax.maps.DecayRateMap`: piecewise-constant grid, exact piecewise integral
  from the ray tracer (Eq. 7.13);
- :class:`~lidarjax.maps.DCTMap`: ``lambda = f^2`` with ``f`` a cosine series, closed-form
  integral (Eq. 9.10 and its fast spectral / quadrature paths);
- :class:`~lidarjax.maps.SmoothDecayRateField`: the bilinear interpolant of a 2-D grid
  map's (optionally blurred) rates, for pose refinement; midpoint-rule integral;
- any smooth field of the user's: subclass :class:`AbstractQuadratureField`, implement
  ``rate_in_box(points)`` and the integral is Gauss-Legendre quadrature over the part of the
  ray inside the field's box.

Parameters and positivity: :func:`fit` optimises ``field.parameters()`` (by default every
inexact array leaf, i.e. ``eqx.filter(field, eqx.is_inexact_array)``) without constraints and
rebuilds the field with ``field.with_parameters(params)``. A field must therefore be
non-negative for *every* parameter value: the DCT map squares its series, the grid map's
parameters are the square roots of its rates, a user's field applies e.g. ``softplus``.
"""

from __future__ import annotations

import abc
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float, PyTree

from .._math import log1mexp, safe_log
from ..rays import HIT, SUB, RayBatch
from ..raytrace import map_chunked, ray_box

__all__ = [
    "AbstractDecayRateField",
    "AbstractQuadratureField",
    "box_segment",
    "combine_log_likelihood",
    "field_log_likelihood",
    "fit",
    "map_chunks",
]


class AbstractDecayRateField(eqx.Module):
    """A non-negative decay-rate field ``lambda(x)`` (1/m) over 2-D or 3-D space.

    Subclasses implement :attr:`dim`, :meth:`decay_rate` and :meth:`integral`; they may
    override :meth:`parameters` / :meth:`with_parameters` to choose what :func:`fit`
    optimises and how positivity is kept. Everything else (the forward model
    :meth:`log_likelihood`, the fit, pose refinement with
    :class:`~lidarjax.localization.refine.FieldScan`) works for any subclass.
    """

    @property
    @abc.abstractmethod
    def dim(self) -> int:
        """Spatial dimension (2 or 3)."""

    @abc.abstractmethod
    def decay_rate(self, points: Float[Array, "*b d"]) -> Float[Array, "*b"]:
        """``lambda(points)`` (1/m), ``>= 0``."""

    @abc.abstractmethod
    def integral(
        self,
        origins: Float[Array, "n d"],
        directions: Float[Array, "n d"],
        lengths: Float[Array, " n"],
    ) -> Float[Array, " n"]:
        """Optical depth ``S = int_0^r lambda(s + t v) dt`` per ray (dimensionless).

        Args:
            origins: ``[n d]`` ray starts ``s`` (m).
            directions: ``[n d]`` unit directions ``v``.
            lengths: ``[n]`` upper limits ``r`` (m), ``>= 0``, possibly ``inf``.
        """

    def parameters(self) -> PyTree:
        """What :func:`fit` optimises (unconstrained): by default every inexact array leaf
        of the field (other leaves ``None``)."""
        return eqx.filter(self, eqx.is_inexact_array)

    def with_parameters(self, params: PyTree) -> AbstractDecayRateField:
        """The field with ``params`` (a pytree like :meth:`parameters`) put back."""
        return eqx.combine(params, self)

    def log_likelihood(
        self, rays: RayBatch, *, chunk_size: int = 4096, rate_floor: float = 0.0
    ) -> Float[Array, "*batch"]:
        """Per-ray log-likelihood, see :func:`field_log_likelihood`."""
        return field_log_likelihood(self, rays, chunk_size=chunk_size, rate_floor=rate_floor)


# --------------------------------------------------------------------------------------
# geometry and chunking helpers


def box_segment(lower, upper, origin, direction, length):
    """Entry and exit distances ``0 <= t0 <= t1 <= length`` of one ray's part inside the
    box ``[lower, upper]`` (``t0 = t1 = 0`` when it misses the box); NaN-free for
    axis-parallel rays and infinite lengths. The slab test is
    :func:`~lidarjax.raytrace.ray_box` (in the promoted dtype of box and ray)."""
    dt = jnp.result_type(lower, upper, origin, direction)
    lo, hi = ray_box(lower, upper, jnp.asarray(origin, dt), jnp.asarray(direction, dt))
    # a ray that misses the box (or only touches it behind the origin / beyond its length)
    # has an empty segment at 0 — also for infinite lengths, where inf - inf would be NaN
    miss = (hi <= lo) | (hi <= 0) | (lo >= length)
    t0 = jnp.where(miss, 0.0, jnp.clip(lo, 0.0, length))
    t1 = jnp.where(miss, 0.0, jnp.clip(hi, 0.0, length))
    return t0, jnp.maximum(t1, t0)


def map_chunks(fn: Callable, args: tuple, chunk_size: int, *, checkpoint: bool = False):
    """``fn(*args)`` for batched ``args`` (leading axis ``n``; ``fn`` maps ``[c ...]`` to
    ``[c]``), evaluated ``chunk_size`` rows at a time with ``lax.map`` to bound memory (the
    last chunk is padded with copies of the last row, :func:`~lidarjax.raytrace.map_chunked`
    with ``fill="edge"``). With ``checkpoint`` each chunk is rematerialised in reverse mode,
    so gradients also need memory for one chunk only."""
    n = args[0].shape[0]
    if n <= chunk_size:
        return fn(*args)
    body = jax.checkpoint(lambda a: fn(*a)) if checkpoint else (lambda a: fn(*a))
    return map_chunked(body, tuple(args), chunk_size, fill="edge")


# --------------------------------------------------------------------------------------
# the generic forward model


def combine_log_likelihood(kind, rate_at_end, depth, rate_floor=0.0):
    """Log-likelihood of rays from their end-point decay rate and optical depth:
    ``log(lambda(end) + rate_floor) - S`` (HIT, Eq. 9.5 for ``rate_floor = 0``),
    ``log(1 - exp(-S))`` (SUB, Eq. 9.11), ``-S`` (SUP, Eq. 9.12); a zero end-point rate
    (and floor) at a HIT gives ``-inf`` (not NaN)."""
    hit = safe_log(rate_at_end + rate_floor) - depth
    return jnp.where(kind == HIT, hit, jnp.where(kind == SUB, log1mexp(depth), -depth))


def _check_field_rays(field, rays, name: str = "field") -> None:
    if not isinstance(field, AbstractDecayRateField):
        raise ValueError(f"{name} must be an AbstractDecayRateField, got {type(field).__name__}")
    if not isinstance(rays, RayBatch):
        raise ValueError(f"rays must be a RayBatch, got {type(rays).__name__}")
    if rays.dim != field.dim:
        raise ValueError(f"rays are {rays.dim}-D but the {name} is {field.dim}-D")


def _check_chunk(chunk_size) -> None:
    if not isinstance(chunk_size, int) or chunk_size <= 0:
        raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}")


def _check_rate_floor(rate_floor) -> float:
    try:
        floor = float(rate_floor)
    except (TypeError, ValueError):
        raise ValueError(f"rate_floor must be a number (1/m), got {rate_floor!r}") from None
    if not (np.isfinite(floor) and floor >= 0):
        raise ValueError(f"rate_floor must be finite and >= 0 (1/m), got {rate_floor!r}")
    return floor


def field_log_likelihood(
    field: AbstractDecayRateField,
    rays: RayBatch,
    *,
    chunk_size: int = 4096,
    rate_floor: float = 0.0,
) -> Float[Array, "*batch"]:
    """Log-likelihood of each ray under any decay-rate field, Eqs. (9.3)-(9.5), (9.11),
    (9.12) (module docstring), from ``field.integral`` (to the range for HIT, ``r_min`` for
    SUB, ``r_max`` for SUP) and ``field.decay_rate`` at HIT end points.

    Differentiable in the field's parameters and in the rays (hence the sensor pose) as far
    as the field is; NaN-free wherever the field's ``integral`` is.

    Args:
        field: any :class:`AbstractDecayRateField`.
        rays: ``[*batch]`` rays of the field's dimension.
        chunk_size: rays evaluated together; larger batches run in chunks (``lax.map``,
            rematerialised in reverse mode) so memory stays bounded.
        rate_floor: added to the decay rate at HIT end points (1/m, finite, ``>= 0``):
            ``log(lambda(end) + rate_floor) - S``, so an end point where the field is 0
            has a finite log-likelihood (a robustness floor for pose refinement; with a
            positive floor the HIT term is no longer a normalised density). Default 0:
            Eq. (9.5) exactly.

    Returns:
        ``[*batch]`` log-likelihoods (nats; HIT values are log densities in log(1/m)).
    """
    _check_field_rays(field, rays)
    _check_chunk(chunk_size)
    rate_floor = _check_rate_floor(rate_floor)
    flat = rays.flatten()
    if flat.ranges.shape[0] == 0:
        return jnp.zeros(rays.shape, flat.origins.dtype)
    length = flat.model_lengths()
    r_end = jnp.where(flat.kind == HIT, flat.ranges, 0.0)  # no inf end points (SUP)

    def chunk(o, d, ell, r, k):
        depth = field.integral(o, d, ell)
        lam = field.decay_rate(o + r[:, None] * d)
        return combine_log_likelihood(k, lam, depth, rate_floor)

    out = map_chunks(
        chunk,
        (flat.origins, flat.directions, length, r_end, flat.kind),
        chunk_size,
        checkpoint=True,
    )
    return out.reshape(rays.shape)


# --------------------------------------------------------------------------------------
# a generic smooth field: Gauss-Legendre quadrature inside a box


class AbstractQuadratureField(AbstractDecayRateField):
    """Base class for a user's smooth field on a box ``[lower, lower + extent]``: implement
    :meth:`rate_in_box` (``>= 0`` for every parameter value) and declare the two box
    attributes; the decay rate is 0 outside the box and the optical depth is the
    ``quadrature_nodes()``-point Gauss-Legendre rule over the part of the ray inside the box
    (exact for fields that are polynomials of degree ``< 2 n`` along rays; otherwise choose
    enough nodes for the finest detail of the field along the longest chord).

    :meth:`parameters` leaves the box out of the fit. Construct subclasses with keyword
    arguments: the box attributes come first in the dataclass field order.

    Attributes:
        lower: ``[d]`` lower box corner (m).
        extent: ``[d]`` box edge lengths (m).
    """

    lower: eqx.AbstractVar[Float[Array, " d"]]
    extent: eqx.AbstractVar[Float[Array, " d"]]

    @abc.abstractmethod
    def rate_in_box(self, points: Float[Array, "*b d"]) -> Float[Array, "*b"]:
        """``lambda(points)`` (1/m) for points inside the box (values outside are unused)."""

    def quadrature_nodes(self) -> int:
        """Gauss-Legendre nodes per ray (default 64); override for finer fields."""
        return 64

    @property
    def dim(self) -> int:
        return int(jnp.shape(self.lower)[0])

    def contains(self, points: Float[ArrayLike, "*b d"]) -> Array:
        """``[*b]`` bool: points inside the closed box."""
        p = jnp.asarray(points)
        return jnp.all((p >= self.lower) & (p <= self.lower + self.extent), axis=-1)

    def decay_rate(self, points: Float[Array, "*b d"]) -> Float[Array, "*b"]:
        p = jnp.asarray(points)
        inside = self.contains(p)
        # evaluate at a point inside the box where outside, so the user's function never
        # sees far-away (or infinite) coordinates
        safe = jnp.where(inside[..., None], p, self.lower + 0.5 * self.extent)
        return jnp.where(inside, self.rate_in_box(safe), 0.0)

    def integral(self, origins, directions, lengths):
        n = self.quadrature_nodes()
        if not isinstance(n, int) or n < 1:
            raise ValueError(f"quadrature_nodes() must return a positive int, got {n!r}")
        x, w = np.polynomial.legendre.leggauss(n)
        dtype = jnp.result_type(origins.dtype, self.lower.dtype)
        x, w = jnp.asarray(x, dtype), jnp.asarray(w, dtype)
        upper = self.lower + self.extent
        t0, t1 = jax.vmap(lambda o, d, r: box_segment(self.lower, upper, o, d, r))(
            origins, directions, lengths
        )
        half = 0.5 * (t1 - t0)
        t = (t0 + half)[:, None] + half[:, None] * x[None, :]  # [n K]
        pts = origins[:, None, :] + t[..., None] * directions[:, None, :]
        # The nodes lie inside the box up to rounding: clip them into it (so a node a
        # rounding error outside is not dropped, and a ray that misses the box, whose
        # nodes all sit at its origin with weight 0, never shows the user's function a
        # far-away point) and call rate_in_box directly.
        pts = jnp.clip(pts, self.lower, upper)
        return half * jnp.sum(self.rate_in_box(pts) * w, axis=-1)

    def parameters(self) -> PyTree:
        params = eqx.filter(self, eqx.is_inexact_array)
        return eqx.tree_at(lambda f: (f.lower, f.extent), params, (None, None))


# --------------------------------------------------------------------------------------
# the generic inverse model


def fit(
    field0: AbstractDecayRateField,
    rays: RayBatch,
    *,
    solver: optx.AbstractMinimiser | None = None,
    rtol: float = 1e-6,
    atol: float = 1e-6,
    max_steps: int = 1000,
    throw: bool = False,
    chunk_size: int = 4096,
) -> tuple[AbstractDecayRateField, optx.Solution]:
    """Maximum-likelihood fit of any decay-rate field to rays (the inverse model).

    Maximises ``sum_k log p(z_k | field)`` (:func:`field_log_likelihood`) over
    ``field0.parameters()`` with optimistix — minimising the negative mean per ray, so the
    tolerances are scale-free — and returns ``field0.with_parameters(optimum)``. The whole
    optimisation is one compiled call (``eqx.filter_jit``); rays are processed in chunks.

    Args:
        field0: initial field (also fixes everything that is not a parameter, e.g. a box or a
            grid geometry).
        rays: mapping rays (any batch shape, at least one); every ray must have a finite
            log-likelihood under ``field0`` (e.g. no HIT where ``decay_rate`` is 0).
        solver: an optimistix minimiser; default ``optx.LBFGS(rtol, atol)``.
        rtol, atol: tolerances of the default solver.
        max_steps: iteration limit.
        throw: raise if the solver fails (default: report it in ``Solution.result``).
        chunk_size: rays per chunk (memory bound).

    Returns:
        ``(field, solution)``: the fitted field and optimistix's ``Solution``
        (``.stats["num_steps"]``, ``.result``).

    Raises:
        ValueError: wrong types or dimensions, no rays, or a non-finite initial
            log-likelihood (naming how many rays are affected).
    """
    _check_field_rays(field0, rays, "field0")
    _check_chunk(chunk_size)
    if not isinstance(max_steps, int) or max_steps < 1:
        raise ValueError(f"max_steps must be a positive int, got {max_steps!r}")
    flat = rays.flatten()
    if flat.ranges.shape[0] == 0:
        raise ValueError("rays is empty")
    ll0 = np.asarray(field_log_likelihood(field0, flat, chunk_size=chunk_size))
    bad = ~np.isfinite(ll0)
    if bad.any():
        kinds = np.asarray(flat.kind)[bad]
        raise ValueError(
            f"field0 gives a non-finite log-likelihood for {int(bad.sum())} of {bad.size} rays "
            f"(kinds {sorted(set(kinds.tolist()))}, 0=HIT 1=SUB 2=SUP; e.g. a HIT where the "
            "decay rate is 0): start from a field that is positive wherever rays end"
        )
    if solver is None:
        solver = optx.LBFGS(rtol=rtol, atol=atol)
    params0 = field0.parameters()
    sol = _minimise(field0, params0, flat, solver, max_steps, throw, chunk_size)
    return field0.with_parameters(sol.value), sol


@eqx.filter_jit
def _minimise(field0, params0, rays, solver, max_steps, throw, chunk_size):
    n = rays.ranges.shape[0]

    def fn(params, args):
        fld, r = args
        ll = field_log_likelihood(fld.with_parameters(params), r, chunk_size=chunk_size)
        return -jnp.sum(ll) / n

    return optx.minimise(fn, solver, params0, args=(field0, rays), max_steps=max_steps, throw=throw)
