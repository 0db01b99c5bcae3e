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

from .._math import log1mexp, mul0, safe_log
from ..rays import HIT, SUB, RayBatch, check_finite_nonnegative, is_concrete, reject_where
from ..raytrace import (
    CellTerm,
    GridSpec,
    GridStats,
    RayFold,
    box_exit,
    fold_traversal,
    gather,
    max_cells_for,
    traverse,
)
from ._field import AbstractDecayRateField
from ._model import AbstractGridModel, GridWalk


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
        reject_where(x, bad, message)


def _nonneg_finite(xp, a):
    return ~xp.isfinite(a) | (a < 0)


def _not_prob(xp, a):
    return ~((a >= 0) & (a <= 1))


class DecayRateMap(AbstractDecayRateField, AbstractGridModel):
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

    # -- the grid-model protocol (lidarjax.maps.AbstractGridModel), Eqs. (7.13), (7.16)
    def _checked(self) -> DecayRateMap:
        """The map with a run-time check (``eqx.error_if``) that traced rates are finite
        and ``>= 0``. Concrete maps are checked when built; a traced infinite rate would
        give ``inf * 0 = NaN`` pose gradients (and ``-inf`` values) instead of an error."""
        if is_concrete(self.rates) and is_concrete(self.outside_rate):
            return self
        checked = (
            check_finite_nonnegative(self.rates, "DecayRateMap.rates (1/m)"),
            check_finite_nonnegative(self.outside_rate, "DecayRateMap.outside_rate (1/m)"),
        )
        return eqx.tree_at(lambda t: (t.rates, t.outside_rate), self, checked)

    def cell_term(self, flat: RayBatch) -> CellTerm:
        """Per-cell summand ``lambda_i d_i`` of the optical depth."""
        return rate_term(self._checked())

    def finish(self, fold: RayFold, flat: RayBatch, walk: GridWalk) -> Float[Array, " n"]:
        """HIT: ``log lambda_k - Lambda(r)`` (Eq. 7.13); SUB: ``log(1 - exp(-Lambda(r_min)))``;
        SUP: ``-Lambda(r_max)`` (Eq. 7.16)."""
        length = walk.lengths
        inside = fold.any_valid & (fold.t_end >= length)
        lam_last = gather(self.rates, fold.last_cell)
        depth = grid_optical_depth(self, fold, length)
        lam_k = jnp.where(inside, lam_last, self.outside_rate)
        hit = safe_log(lam_k) - depth  # Eq. (7.13)
        sub = log1mexp(depth)  # Eq. (7.16): P(sub) = 1 - N(r_min)
        sup = -depth  # Eq. (7.16): P(sup) = N(r_max)
        return jnp.where(flat.kind == HIT, hit, jnp.where(flat.kind == SUB, sub, sup))


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


class ReflectionMap(AbstractGridModel):
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

    # -- the grid-model protocol (lidarjax.maps.AbstractGridModel), Eqs. (7.23), (7.32)
    def cell_term(self, flat: RayBatch) -> CellTerm:
        """Per-cell summand ``log(1 - q_i)`` of the cells a ray passes fully."""
        return CellTerm.linear(offset=safe_log(1.0 - self.probs))

    def finish(self, fold: RayFold, flat: RayBatch, walk: GridWalk) -> Float[Array, " n"]:
        """HIT: ``log P_k - log chord_k`` (Eqs. 7.23, 7.32); SUP: the survival to ``r_max``
        with the reflecting cell's chord fraction; SUB: one minus the survival to ``r_min``
        (see :func:`lidarjax.sensor_models.reflection_log_likelihood`)."""
        spec = self.spec
        dtype = spec.origin.dtype
        f, length = fold, walk.lengths
        inside = f.any_valid & (f.t_end >= length)
        out_len = jnp.maximum(length - f.grid_len, 0.0)
        direction = walk.directions
        norm = jnp.sqrt(jnp.sum(direction * direction, axis=-1, keepdims=True))
        unit = direction / jnp.where(norm > 0, norm, 1.0)

        q_k = gather(self.probs, f.last_cell)
        # Cells passed fully: all but the last, and the last too if the ray leaves the grid.
        log_before = f.body + jnp.where(f.any_valid & ~inside, safe_log(1.0 - q_k), 0.0)
        # Outside the grid: a homogeneous medium of cells of the grid's resolution with
        # reflection probability q_out, i.e. survival (1 - q_out)^(length / resolution).
        log1m_qout = safe_log(1.0 - self.unknown_prob)
        log_out = -mul0(-log1m_qout, out_len / spec.resolution)
        log_surv_full = log_before + log_out

        # Reflecting cell k: chord = full length of the ray's path inside v_k (Eq. 7.32),
        # from where the ray enters v_k (or starts, if it starts inside) to where it leaves.
        entry = length - f.last_len
        chord = _cell_exit(spec, f.last_cell, walk.origins, unit) - entry
        chord = jnp.maximum(jnp.maximum(chord, f.last_len), jnp.finfo(dtype).eps * spec.resolution)
        frac = jnp.clip(f.last_len / chord, 0.0, 1.0)

        # HIT density: P(x(r) in v_k) / chord_k, Eqs. (7.23) + (7.32); outside the grid the
        # density of the outside medium, rate -log(1 - q_out) / resolution.
        rate_out = -log1m_qout / spec.resolution
        hit_in = safe_log(q_k) - jnp.log(chord)
        hit_k = jnp.where(
            inside, hit_in, safe_log(jnp.where(jnp.isfinite(rate_out), rate_out, 1.0))
        )
        hit = jnp.where(log_surv_full > -jnp.inf, log_surv_full + hit_k, -jnp.inf)
        # Survival to L: the reflecting cell counts with the fraction of its chord
        # travelled, i.e. the CDF of the Eq. (7.32) density is linear inside a cell.
        log_surv = log_surv_full + jnp.where(inside, safe_log(1.0 - q_k * frac), 0.0)
        sub = log1mexp(-log_surv)
        return jnp.where(flat.kind == HIT, hit, jnp.where(flat.kind == SUB, sub, log_surv))


def _cell_exit(spec, cell, origin, direction):
    """Ray parameter (m) where the ray ``origin + t * direction`` (unit direction) leaves
    the box of ``cell`` (:func:`~lidarjax.raytrace.box_exit`); batched over leading axes."""
    lo = spec.origin + cell.astype(spec.origin.dtype) * spec.resolution
    hi = lo + spec.resolution
    dt = jnp.result_type(lo, origin, direction)
    return box_exit(lo, hi, jnp.asarray(origin, dt), jnp.asarray(direction, dt))


class EndpointMap(AbstractGridModel):
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

    def random_density(self, r_max) -> Float[Array, ""]:
        """The uniform term ``z_rand / r_max`` (1/m) of the field; 0 for ``r_max = inf``."""
        finite_max = jnp.isfinite(r_max)
        return jnp.where(finite_max, self.z_rand / jnp.where(finite_max, r_max, 1.0), 0.0)

    # -- the grid-model protocol (lidarjax.maps.AbstractGridModel), normalised per ray
    def walk(self, flat: RayBatch) -> GridWalk:
        """The normaliser ``Z`` integrates the field over ``[r_min, r_max]`` of each ray:
        the walk starts at ``r_min`` along the unit direction and covers ``r_max - r_min``."""
        norm = jnp.sqrt(jnp.sum(flat.directions**2, axis=-1, keepdims=True))
        unit = flat.directions / jnp.where(norm > 0, norm, 1.0)
        span = jnp.broadcast_to(flat.r_max - flat.r_min, flat.ranges.shape)
        return GridWalk(flat.origins + flat.r_min * unit, unit, span)

    def walk_bound_m(self, r_min: float, r_max: float) -> float:
        """The walk covers ``[r_min, r_max]``."""
        return float(r_max) - float(r_min)

    def cell_term(self, flat: RayBatch) -> CellTerm:
        """Per-cell summand ``f_i d_i`` of the normaliser ``Z``."""
        return CellTerm.linear(
            slope=self.z_hit * self.hit_field() + self.random_density(flat.r_max)
        )

    def finish(self, fold: RayFold, flat: RayBatch, walk: GridWalk) -> Float[Array, " n"]:
        """HIT: ``log(1 - P) + log f(x(r)) - log Z``; SUB and SUP: ``log P`` (see
        :func:`lidarjax.sensor_models.endpoint_log_likelihood`)."""
        spec, f = self.spec, fold
        field, rand = self.hit_field(), self.random_density(flat.r_max)
        unit, span = walk.directions, walk.lengths
        # Normaliser Z = int_{r_min}^{r_max} f(x(r)) dr of the cell-wise constant field:
        # exact sum over the walked cells of f_i * d_i plus the uniform term off the grid.
        f_last = self.z_hit * gather(field, f.last_cell) + rand
        out_len = jnp.maximum(span - f.grid_len, 0.0)
        z = f.body + jnp.where(f.any_valid, f_last * f.last_len, 0.0) + mul0(rand, out_len)
        # Field at the end point (its cell; outside the grid only the uniform term).
        cell = spec.cell_of(flat.origins + flat.ranges[..., None] * unit)
        inside = spec.contains(cell)
        f_end = jnp.where(inside, self.z_hit * gather(field, cell), 0.0) + rand
        ok = (z > 0) & (f_end > 0)
        log_ratio = jnp.log(jnp.where(ok, f_end, 1.0)) - jnp.log(jnp.where(ok, z, 1.0))
        hit = jnp.where(ok, safe_log(1.0 - self.p_out) + log_ratio, -jnp.inf)
        return jnp.where(flat.kind == HIT, hit, safe_log(self.p_out))


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
