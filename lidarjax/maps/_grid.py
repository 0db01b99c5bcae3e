"""Grid maps of the three forward sensor models of chapter 7.

- :class:`DecayRateMap`: one decay rate ``lambda_i`` (1/m) per cell, the maximum-likelihood
  estimate ``H_i / R_i`` of Eq. (7.10).
- :class:`ReflectionMap`: one reflection probability ``mu_i = H_i / (H_i + M_i)`` per cell,
  Eq. (7.22) (the "hit-counting" model).
- :class:`EndpointMap`: the likelihood field of the endpoint model (Thrun et al.), i.e. the
  Euclidean distance from every cell centre to the nearest occupied cell centre, plus the
  mixture weights of the heuristic.

All three are built from a :class:`~lidarjax.raytrace.GridStats` and consumed by the
``log_likelihood(map, rays)`` functions of :mod:`lidarjax.sensor_models`.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._math import mul0
from ..rays import _reject, is_concrete
from ..raytrace import (
    CellTerm,
    GridSpec,
    GridStats,
    RayFold,
    fold_traversal,
    gather,
    max_cells_for,
    traverse,
)
from ._field import AbstractDecayRateField


def _check_stats(stats) -> None:
    if not isinstance(stats, GridStats):
        raise ValueError(f"stats must be a GridStats, got {type(stats).__name__}")


def _check_scalar(value, name: str, *, lo: float = 0.0, hi: float | None = None) -> None:
    if not is_concrete(value):
        return
    if np.ndim(value) != 0:
        raise ValueError(f"{name} must be a scalar, got shape {np.shape(value)}")
    v = float(value)
    if not np.isfinite(v) or v < lo or (hi is not None and v > hi):
        bound = f"[{lo}, {hi}]" if hi is not None else f">= {lo}"
        raise ValueError(f"{name} must be finite and {bound}, got {v}")


def _check_values(x, bad, message: str) -> None:
    """Raise ``ValueError(message ...)`` if concrete ``x`` has an entry with ``bad(xp, x)``
    (traced values, e.g. a map rebuilt inside ``grad`` by :func:`~lidarjax.maps.fit`, are
    not checked)."""
    if is_concrete(x):
        _reject(x, bad, message)


def _nonneg_finite(xp, a):
    return ~xp.isfinite(a) | (a < 0)


def _not_prob(xp, a):
    return ~((a >= 0) & (a <= 1))


class DecayRateMap(AbstractDecayRateField):
    """Decay-rate map (dissertation Sec. 7.3): a piecewise-constant decay rate per cell.

    A :class:`~lidarjax.maps.AbstractDecayRateField`: ``decay_rate`` looks up the cell of a
    point, ``integral`` is the exact piecewise sum ``sum_i lambda_i d_i`` of the ray tracer
    (Eq. 7.13), and :func:`~lidarjax.maps.fit` optimises the amplitudes
    ``sqrt(lambda_i)`` (:meth:`parameters`), so the rates stay non-negative.

    Attributes:
        spec: the grid.
        rates: ``[*shape]`` decay rate ``lambda_i`` (1/m) per cell, ``>= 0``.
        outside_rate: ``[]`` decay rate (1/m) assumed for every point outside the grid.
    """

    spec: GridSpec
    rates: Float[Array, "*shape"]
    outside_rate: Float[Array, ""]

    def __check_init__(self):
        if not isinstance(self.spec, GridSpec):
            raise ValueError(f"spec must be a GridSpec, got {type(self.spec).__name__}")
        if tuple(jnp.shape(self.rates)) != self.spec.shape:
            raise ValueError(
                f"rates must have the grid shape {self.spec.shape}, got {jnp.shape(self.rates)}"
            )
        if jnp.shape(self.outside_rate) != ():
            raise ValueError(f"outside_rate must be a scalar, got {jnp.shape(self.outside_rate)}")
        _check_values(self.rates, _nonneg_finite, "rates (1/m) must be finite and >= 0")
        _check_values(
            self.outside_rate, _nonneg_finite, "outside_rate (1/m) must be finite and >= 0"
        )

    @property
    def dim(self) -> int:
        """Spatial dimension (2 or 3)."""
        return self.spec.dim

    def decay_rate(self, points: Float[ArrayLike, "*b d"]) -> Float[Array, "*b"]:
        """Rate (1/m) of the cell containing each point; ``outside_rate`` off the grid."""
        cells = self.spec.cell_of(points)
        return jnp.where(self.spec.contains(cells), gather(self.rates, cells), self.outside_rate)

    def integral(
        self,
        origins: Float[Array, "n d"],
        directions: Float[Array, "n d"],
        lengths: Float[Array, " n"],
    ) -> Float[Array, " n"]:
        """Optical depth ``sum_i lambda_i d_i`` per ray (exact per-cell lengths ``d_i`` from
        :func:`~lidarjax.raytrace.traverse`, ``outside_rate`` beyond the grid), Eq. (7.13).
        Differentiable in the rates and the rays (where the cell sequence is locally
        constant). The traversal budget covers the longest ray when ``lengths`` is concrete,
        else the whole grid."""
        length_m = float(np.max(np.asarray(lengths))) if is_concrete(lengths) else None
        if length_m is not None and not np.isfinite(length_m):
            length_m = None
        budget = max_cells_for(self.spec, length_m)
        tr = jax.vmap(lambda o, d, r: traverse(self.spec, o, d, r, budget))(
            origins, directions, lengths
        )
        return grid_optical_depth(self, fold_traversal(tr, rate_term(self)), lengths)

    def parameters(self) -> Float[Array, "*shape"]:
        """``sqrt(rates)``: :func:`~lidarjax.maps.fit` optimises amplitudes ``a`` with
        ``lambda = a^2`` (like the DCT map's ``f^2``); ``outside_rate`` stays fixed."""
        return jnp.sqrt(self.rates)

    def with_parameters(self, params: Float[Array, "*shape"]) -> DecayRateMap:
        """The map with rates ``params**2``."""
        return DecayRateMap(spec=self.spec, rates=params**2, outside_rate=self.outside_rate)


def rate_term(m: DecayRateMap):
    """Per-cell summand ``lambda_i d_i`` of the optical depth (a traversal ``term``)."""
    return CellTerm.linear(slope=m.rates)


def grid_optical_depth(m: DecayRateMap, fold: RayFold, lengths) -> Array:
    """Optical depth ``Lambda(L) = int_0^L lambda`` of rays from their traversal fold with
    :func:`rate_term`: the cells inside the grid plus the parts outside at
    ``m.outside_rate`` (``0 * inf := 0`` for an infinite ray)."""
    out_len = jnp.maximum(lengths - fold.grid_len, 0.0)
    lam_last = gather(m.rates, fold.last_cell)
    depth = fold.body + jnp.where(fold.any_valid, lam_last * fold.last_len, 0.0)
    return depth + mul0(m.outside_rate, out_len)


class ReflectionMap(eqx.Module):
    """Reflection (hit-counting) map: a reflection probability per cell, Eq. (7.22).

    Attributes:
        spec: the grid.
        probs: ``[*shape]`` probability ``mu_i`` in ``[0, 1]`` that a ray entering the cell
            is reflected inside it.
        unknown_prob: ``[]`` reflection probability used outside the grid (see
            :func:`lidarjax.sensor_models.reflection_log_likelihood` for how space outside
            the grid is treated).
    """

    spec: GridSpec
    probs: Float[Array, "*shape"]
    unknown_prob: Float[Array, ""]

    def __check_init__(self):
        if not isinstance(self.spec, GridSpec):
            raise ValueError(f"spec must be a GridSpec, got {type(self.spec).__name__}")
        if tuple(jnp.shape(self.probs)) != self.spec.shape:
            raise ValueError(
                f"probs must have the grid shape {self.spec.shape}, got {jnp.shape(self.probs)}"
            )
        if jnp.shape(self.unknown_prob) != ():
            raise ValueError(f"unknown_prob must be a scalar, got {jnp.shape(self.unknown_prob)}")
        _check_values(self.probs, _not_prob, "probs must be probabilities in [0, 1]")
        _check_values(self.unknown_prob, _not_prob, "unknown_prob must be a probability in [0, 1]")


class EndpointMap(eqx.Module):
    """Likelihood field of the endpoint model (dissertation Sec. 7.6.2, after Eq. 7.32).

    Attributes:
        spec: the grid.
        distances: ``[*shape]`` Euclidean distance (m) from each cell centre to the nearest
            occupied cell centre (``inf`` if no cell is occupied).
        occupied: ``[*shape]`` bool, the cells treated as obstacles.
        sigma_m: ``[]`` standard deviation (m) of the Gaussian hit term.
        z_hit: ``[]`` weight of the Gaussian term.
        z_rand: ``[]`` weight of the uniform term ``z_rand / r_max``.
        p_out: ``[]`` absolute probability ``P`` of an out-of-range measurement (SUB or SUP).
    """

    spec: GridSpec
    distances: Float[Array, "*shape"]
    occupied: Bool[Array, "*shape"]
    sigma_m: Float[Array, ""]
    z_hit: Float[Array, ""]
    z_rand: Float[Array, ""]
    p_out: Float[Array, ""]

    def __check_init__(self):
        if not isinstance(self.spec, GridSpec):
            raise ValueError(f"spec must be a GridSpec, got {type(self.spec).__name__}")
        for name in ("distances", "occupied"):
            if tuple(jnp.shape(getattr(self, name))) != self.spec.shape:
                raise ValueError(
                    f"{name} must have the grid shape {self.spec.shape}, got "
                    f"{jnp.shape(getattr(self, name))}"
                )
        _check_values(
            self.distances, lambda xp, a: xp.isnan(a) | (a < 0), "distances (m) must be >= 0"
        )
        _check_values(
            self.sigma_m, lambda xp, a: ~xp.isfinite(a) | (a <= 0), "sigma_m must be finite and > 0"
        )
        for name in ("z_hit", "z_rand"):
            _check_values(getattr(self, name), _nonneg_finite, f"{name} must be finite and >= 0")
        _check_values(
            self.p_out, lambda xp, a: ~((a >= 0) & (a < 1)), "p_out must be a probability in [0, 1)"
        )

    def hit_field(self) -> Float[Array, "*shape"]:
        """``[*shape]`` Gaussian term ``N(dist_i; 0, sigma)`` (1/m) per cell."""
        s = self.sigma_m
        return jnp.exp(-0.5 * (self.distances / s) ** 2) / (jnp.sqrt(2 * jnp.pi) * s)


def decay_rate_map(stats: GridStats, *, unknown_rate: float | None = None) -> DecayRateMap:
    """Maximum-likelihood decay-rate map ``lambda_i = H_i / R_i``, Eq. (7.10).

    Args:
        stats: per-cell hits ``H`` and travelled lengths ``R`` (m).
        unknown_rate: rate (1/m) for never-traversed cells (``R_i = 0``) and for all space
            outside the grid. Default: the global ML rate ``sum(H) / sum(R)`` (0 if no ray
            traversed the grid), i.e. the rate of a map with a single cell.

    Returns:
        A :class:`DecayRateMap`; NaN-free (and with NaN-free gradients w.r.t. the stats).
    """
    _check_stats(stats)
    h = jnp.asarray(stats.hits, dtype=stats.lengths.dtype)
    r = stats.lengths
    if unknown_rate is None:
        total_r = jnp.sum(r)
        pos = total_r > 0
        unknown = jnp.where(pos, jnp.sum(h) / jnp.where(pos, total_r, 1.0), 0.0)
    else:
        _check_scalar(unknown_rate, "unknown_rate")
        unknown = jnp.asarray(unknown_rate, r.dtype)
    seen = r > 0
    rates = jnp.where(seen, h / jnp.where(seen, r, 1.0), unknown)
    return DecayRateMap(spec=stats.spec, rates=rates, outside_rate=unknown)


def reflection_map(stats: GridStats, *, unknown_prob: float | None = None) -> ReflectionMap:
    """Reflection map ``mu_i = H_i / (H_i + M_i)``, Eq. (7.22).

    Args:
        stats: per-cell hits ``H`` and misses ``M``.
        unknown_prob: reflection probability of never-visited cells (``H_i + M_i = 0``) and
            of space outside the grid. Default: the global ratio ``sum(H) / sum(H + M)``
            (0 if nothing was visited).

    Returns:
        A :class:`ReflectionMap`.
    """
    _check_stats(stats)
    dtype = stats.lengths.dtype
    h = jnp.asarray(stats.hits, dtype)
    n = h + jnp.asarray(stats.misses, dtype)
    if unknown_prob is None:
        total = jnp.sum(n)
        pos = total > 0
        unknown = jnp.where(pos, jnp.sum(h) / jnp.where(pos, total, 1.0), 0.0)
    else:
        _check_scalar(unknown_prob, "unknown_prob", hi=1.0)
        unknown = jnp.asarray(unknown_prob, dtype)
    seen = n > 0
    probs = jnp.where(seen, h / jnp.where(seen, n, 1.0), unknown)
    return ReflectionMap(spec=stats.spec, probs=probs, unknown_prob=unknown)


@jax.jit
def _squared_edt(blocked: Bool[Array, "*shape"]) -> Float[Array, "*shape"]:
    """Exact squared Euclidean distance transform in cell units (separable, one 1-D pass
    ``g(i) = min_j f(j) + (i - j)^2`` per axis; exact because squared distances separate)."""
    f = jnp.where(blocked, 0.0, jnp.inf)
    for axis in range(f.ndim):
        x = jnp.moveaxis(f, axis, -1)
        n = x.shape[-1]
        j = jnp.arange(n, dtype=x.dtype)

        def one(i, x=x, j=j):
            return jnp.min(x + (i - j) ** 2, axis=-1)

        g = jax.lax.map(one, j)  # [n *rest]
        f = jnp.moveaxis(jnp.moveaxis(g, 0, -1), -1, axis)
    return f


def distance_transform(
    occupied: Bool[ArrayLike, "*shape"], resolution: float
) -> Float[Array, "*shape"]:
    """Exact Euclidean distance (m) from each cell centre to the nearest occupied cell
    centre of a 2-D or 3-D grid (``inf`` everywhere if nothing is occupied).

    Cost ``O(n_cells * max(shape))``, memory ``O(n_cells)`` (one pass per axis).

    Args:
        occupied: ``[*shape]`` bool mask.
        resolution: cell edge length (m).
    """
    occ = jnp.asarray(occupied)
    if occ.ndim not in (2, 3) or occ.dtype != jnp.bool_:
        raise ValueError(f"occupied must be a 2-D or 3-D bool array, got {occ.dtype}{occ.shape}")
    return jnp.sqrt(_squared_edt(occ)) * jnp.asarray(resolution, jnp.result_type(float))


def endpoint_map(
    stats: GridStats,
    *,
    sigma_m: float,
    occupied_threshold: float = 0.0,
    z_hit: float = 0.9,
    z_rand: float = 0.1,
    p_out: float = 0.05,
) -> EndpointMap:
    """Likelihood-field map of the endpoint model.

    A cell is occupied when its reflection probability ``mu_i = H_i / (H_i + M_i)``
    (Eq. 7.22) exceeds ``occupied_threshold`` (default 0: every cell with a hit). The
    likelihood field is ``z_hit * N(dist; 0, sigma_m) + z_rand / r_max`` with ``dist`` the
    exact Euclidean distance from the cell centre to the nearest occupied cell centre; the
    sensor model normalises it per ray (see
    :func:`lidarjax.sensor_models.endpoint_log_likelihood`).

    Args:
        stats: per-cell hits and misses.
        sigma_m: standard deviation (m) of the Gaussian term, ``> 0``.
        occupied_threshold: threshold on ``mu_i`` in ``[0, 1)``.
        z_hit: weight of the Gaussian term, ``>= 0``.
        z_rand: weight of the uniform term, ``>= 0``.
        p_out: probability ``P`` of an out-of-range (SUB/SUP) measurement, in ``[0, 1)``.

    Returns:
        An :class:`EndpointMap`.
    """
    _check_stats(stats)
    _check_scalar(sigma_m, "sigma_m")
    if is_concrete(sigma_m) and float(sigma_m) <= 0:
        raise ValueError(f"sigma_m must be > 0, got {sigma_m}")
    _check_scalar(occupied_threshold, "occupied_threshold", hi=1.0)
    _check_scalar(z_hit, "z_hit")
    _check_scalar(z_rand, "z_rand")
    _check_scalar(p_out, "p_out", hi=1.0)
    dtype = stats.lengths.dtype
    h = jnp.asarray(stats.hits, dtype)
    n = h + jnp.asarray(stats.misses, dtype)
    mu = jnp.where(n > 0, h / jnp.where(n > 0, n, 1.0), 0.0)
    occupied = (h > 0) & (mu > occupied_threshold)
    dist = distance_transform(occupied, stats.spec.resolution).astype(dtype)
    as_arr = functools.partial(jnp.asarray, dtype=dtype)
    return EndpointMap(
        spec=stats.spec,
        distances=dist,
        occupied=occupied,
        sigma_m=as_arr(sigma_m),
        z_hit=as_arr(z_hit),
        z_rand=as_arr(z_rand),
        p_out=as_arr(p_out),
    )


__all__ = [
    "DecayRateMap",
    "ReflectionMap",
    "EndpointMap",
    "decay_rate_map",
    "reflection_map",
    "endpoint_map",
    "distance_transform",
]
