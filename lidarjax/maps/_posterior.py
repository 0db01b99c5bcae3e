"""Closed-form full map posteriors and their measurement likelihoods (dissertation ch. 8).

For the reflection model (Eq. 8.3) and the decay-rate model (Eq. 8.4) the posterior over
every grid cell's map value is conjugate to the forward model, so a full map posterior needs
only the sufficient statistics ``H``, ``M``, ``R`` of a :class:`~lidarjax.raytrace.GridStats`
and the two prior parameters ``(alpha, beta)``:

- :class:`BetaPosteriorMap`: ``bel(mu_i) = Beta(H_i + alpha, M_i + beta)``, Eq. (8.15).
- :class:`GammaPosteriorMap`: ``bel(lambda_i) = Gamma(H_i + alpha, R_i + beta)`` (shape,
  rate), Eq. (8.17).

:func:`log_likelihood` evaluates the closed-form measurement likelihood ``L(z, x)`` of
Eq. (8.20), i.e. the forward likelihood integrated over the map posterior, as a product of
per-cell factors (Eq. 8.21): ``l_ref`` of Eq. (8.22) and ``l_dec`` (the unnumbered equation
after Eq. 8.23), including out-of-range measurements (the two unnumbered equations at the end
of section 8.4.5). :func:`occupancy` converts a Beta posterior map to occupancy probabilities
as in section 12.4.1.

Priors (section 8.5): by default ``alpha`` and ``beta`` are moment-matched to the empirical
mean and variance of the maximum-likelihood map values (Eqs. 7.22 / 7.10) over the observed
cells; ``prior="uniform"`` gives ``Beta(1, 1)`` / the uninformative ``Gamma(1, 0)`` whose
posterior modes are exactly the maximum-likelihood maps (Eqs. 8.16 / 8.18).
"""

from __future__ import annotations

import math
from typing import Literal

import jax.numpy as jnp
from jax.scipy.special import betainc
from jaxtyping import Array, ArrayLike, Float

from .._checks import check
from .._math import log1mexp
from ..rays import HIT, SUB, SUP, RayBatch, check_finite_nonnegative, is_concrete, reject_where
from ..raytrace import (
    CellTerm,
    GridSpec,
    GridStats,
    RayFold,
)
from ._model import AbstractGridModel, GridWalk, walk_log_likelihood

__all__ = [
    "BetaPosteriorMap",
    "GammaPosteriorMap",
    "beta_posterior",
    "gamma_posterior",
    "beta_moment_prior",
    "gamma_moment_prior",
    "log_likelihood",
    "occupancy",
]

PriorName = Literal["moments", "uniform"]


# --------------------------------------------------------------------------------------
# Validation helpers
# --------------------------------------------------------------------------------------


def _check_param(x, name: str, *, allow_zero: bool) -> Array:
    """A scalar prior parameter: finite and > 0 (or >= 0 with ``allow_zero``)."""
    if jnp.shape(x) != ():
        raise ValueError(f"{name} must be a scalar, got shape {jnp.shape(x)}")
    bound = ">= 0" if allow_zero else "> 0"
    if is_concrete(x):
        v = float(x)
        ok = math.isfinite(v) and (v >= 0 if allow_zero else v > 0)
        if not ok:
            raise ValueError(f"{name} must be finite and {bound}, got {v}")
        return jnp.asarray(v, jnp.result_type(float))
    x = jnp.asarray(x, jnp.result_type(float))
    bad = ~jnp.isfinite(x) | ((x < 0) if allow_zero else (x <= 0))
    return check(x, bad, f"{name} must be finite and {bound}")


def _check_stats(stats) -> GridStats:
    if not isinstance(stats, GridStats):
        raise ValueError(f"stats must be a GridStats, got {type(stats).__name__}")
    return stats


def _checked_counts(stats: GridStats, fields: tuple[str, ...]) -> dict[str, Array]:
    """``stats`` fields as float arrays checked to be finite and ``>= 0`` (``ValueError``
    naming the field when concrete, ``eqx.error_if`` when traced)."""
    dtype = jnp.result_type(float)
    return {
        name: check_finite_nonnegative(getattr(stats, name), f"stats.{name}").astype(dtype)
        for name in fields
    }


def _check_map_fields(m, fields: tuple[str, ...], beta_zero_ok: bool) -> None:
    """Concrete value checks of a posterior map built directly (``ValueError`` naming the
    field); traced fields are checked at run time by :func:`term`."""
    for name in fields:
        if is_concrete(getattr(m, name)):
            check_finite_nonnegative(getattr(m, name), name)
    if is_concrete(m.alpha):
        reject_where(
            m.alpha, lambda xp, a: ~(xp.isfinite(a) & (a > 0)), "alpha must be finite and > 0"
        )
    if is_concrete(m.beta):
        reject_where(
            m.beta,
            lambda xp, b: ~(xp.isfinite(b) & ((b > 0) | (beta_zero_ok & (b == 0)))),
            f"beta must be finite and {'>= 0' if beta_zero_ok else '> 0'}",
        )


def _check_prior_args(alpha, beta, prior) -> None:
    if prior not in ("moments", "uniform"):
        raise ValueError(f"prior must be 'moments' or 'uniform', got {prior!r}")
    if (alpha is None) != (beta is None):
        raise ValueError("alpha and beta must be given together (or both left None)")
    if alpha is not None and prior == "uniform":
        raise ValueError("prior='uniform' cannot be combined with explicit alpha and beta")


def _masked_moments(values, mask, name: str) -> tuple[Array, Array]:
    """Empirical mean and (population, ddof=0) variance of ``values[mask]``."""
    mask = jnp.asarray(mask)
    n = jnp.sum(mask)
    if is_concrete(n) and int(n) < 2:
        raise ValueError(
            f"{name}: moment matching (section 8.5) needs at least 2 observed cells, got {int(n)}"
        )
    n_safe = jnp.maximum(n, 1).astype(values.dtype)
    v = jnp.where(mask, values, 0.0)
    mean = jnp.sum(v) / n_safe
    var = jnp.sum(jnp.where(mask, (values - mean) ** 2, 0.0)) / n_safe
    return mean, var


def _check_matched(alpha, beta, name: str, detail: str) -> tuple[Array, Array]:
    bad = ~(jnp.isfinite(alpha) & jnp.isfinite(beta) & (alpha > 0) & (beta > 0))
    msg = f"{name}: moment-matched prior is invalid ({detail})"
    if is_concrete(bad):
        if bool(bad):
            raise ValueError(f"{msg}; got alpha={float(alpha)}, beta={float(beta)}")
        return alpha, beta
    alpha = check(alpha, bad, msg)
    return alpha, beta


# --------------------------------------------------------------------------------------
# Moment-matched priors (section 8.5)
# --------------------------------------------------------------------------------------


def beta_moment_prior(stats: GridStats) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Beta prior ``(alpha, beta)`` moment-matched to the maximum-likelihood reflection map.

    Section 8.5 (and section 12.4.1): with ``E = mean`` and ``V = var`` of the ML reflection
    map ``mu_i = H_i / (H_i + M_i)`` (Eq. 7.22 / 8.16) over all cells where it is defined
    (``H_i + M_i > 0``; the text says "over all voxels", but the ML value does not exist in
    unobserved voxels),

        alpha = -E (E^2 - E + V) / V,
        beta  = (E - V + E V - 2 E^2 + E^3) / V,

    i.e. ``alpha = E (E(1-E)/V - 1)``, ``beta = (1-E)(E(1-E)/V - 1)``. ``V`` is the
    population variance (divided by the number of cells, ddof = 0). The per-voxel
    leave-one-out variant mentioned in the text is not used (as in the dissertation).

    Args:
        stats: grid statistics; ``hits`` and ``misses`` are used.

    Returns:
        ``(alpha, beta)``, scalars > 0.

    Raises:
        ValueError: fewer than two observed cells, or ``V = 0`` / ``V >= E (1 - E)`` (no
            Beta distribution has these moments). Under ``jit`` this is a runtime error.
    """
    stats = _check_stats(stats)
    h = jnp.asarray(stats.hits, jnp.result_type(float))
    n = h + jnp.asarray(stats.misses, h.dtype)
    observed = n > 0
    mu = h / jnp.where(observed, n, 1.0)
    e, v = _masked_moments(mu, observed, "stats")
    v_safe = jnp.where(v > 0, v, 1.0)
    alpha = jnp.where(v > 0, -e * (e * e - e + v) / v_safe, jnp.nan)
    beta = jnp.where(v > 0, (e - v + e * v - 2 * e * e + e**3) / v_safe, jnp.nan)
    return _check_matched(alpha, beta, "stats", "needs 0 < var < mean (1 - mean) of H/(H+M)")


def gamma_moment_prior(stats: GridStats) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Gamma prior ``(alpha, beta)`` (shape, rate) moment-matched to the ML decay-rate map.

    Section 8.5: with ``E = mean`` and ``V = var`` of the ML decay rates
    ``lambda_i = H_i / R_i`` (Eq. 7.10 / 8.18) over all cells where they are finite
    (``R_i > 0``), ``alpha = E^2 / V`` and ``beta = E / V`` (1/m). ``V`` is the population
    variance (ddof = 0).

    Args:
        stats: grid statistics; ``hits`` and ``lengths`` are used.

    Returns:
        ``(alpha, beta)``, scalars > 0; ``beta`` in metres.

    Raises:
        ValueError: fewer than two cells with ``R_i > 0``, or zero variance / zero mean.
    """
    stats = _check_stats(stats)
    r = jnp.asarray(stats.lengths, jnp.result_type(float))
    h = jnp.asarray(stats.hits, r.dtype)
    observed = r > 0
    lam = h / jnp.where(observed, r, 1.0)
    e, v = _masked_moments(lam, observed, "stats")
    v_safe = jnp.where(v > 0, v, 1.0)
    alpha = jnp.where(v > 0, e * e / v_safe, jnp.nan)
    beta = jnp.where(v > 0, e / v_safe, jnp.nan)
    return _check_matched(alpha, beta, "stats", "needs a positive mean and variance of H/R")


# --------------------------------------------------------------------------------------
# Posterior maps
# --------------------------------------------------------------------------------------


class _AbstractPosteriorModel(AbstractGridModel):
    """The grid-model protocol of the full map posteriors, Eqs. (8.20)-(8.22): the walk
    is in the promoted dtype of the rays, the grid and the posterior parameters; per-cell
    terms and the finish are :func:`term` and :func:`finish`."""

    def walk_dtype(self, flat: RayBatch):
        return jnp.result_type(flat.origins.dtype, self.spec.origin.dtype, self.a.dtype)

    def cell_term(self, flat: RayBatch) -> CellTerm:
        return term(self)

    def finish(self, fold: RayFold, flat: RayBatch, walk: GridWalk) -> Float[Array, " n"]:
        return finish(self, fold, walk.origins, walk.directions, walk.lengths, flat.kind)


class BetaPosteriorMap(_AbstractPosteriorModel):
    """Full posterior over a reflection map, ``bel(mu_i) = Beta(H_i + alpha, M_i + beta)``
    (Eq. 8.15).

    Attributes:
        spec: the grid.
        hits: ``[*shape]`` float, ``H_i``.
        misses: ``[*shape]`` float, ``M_i``.
        alpha: ``[]`` prior parameter (> 0).
        beta: ``[]`` prior parameter (> 0).

    Concrete fields are checked at construction (finite, ``hits``/``misses`` ``>= 0``;
    ``ValueError`` naming the field); traced ones when a likelihood is evaluated
    (``eqx.error_if``).
    """

    spec: GridSpec
    hits: Float[Array, "*shape"]
    misses: Float[Array, "*shape"]
    alpha: Float[Array, ""]
    beta: Float[Array, ""]

    @property
    def a(self) -> Float[Array, "*shape"]:
        """``[*shape]`` first posterior parameter ``H_i + alpha``."""
        return self.hits + self.alpha

    @property
    def b(self) -> Float[Array, "*shape"]:
        """``[*shape]`` second posterior parameter ``M_i + beta``."""
        return self.misses + self.beta

    def __check_init__(self):
        _check_map_fields(self, ("hits", "misses"), beta_zero_ok=False)

    def mean(self) -> Float[Array, "*shape"]:
        """``[*shape]`` posterior mean reflection probability ``a / (a + b)``."""
        return self.a / (self.a + self.b)

    def variance(self) -> Float[Array, "*shape"]:
        """``[*shape]`` posterior variance ``a b / ((a + b)^2 (a + b + 1))``."""
        a, b = self.a, self.b
        s = a + b
        return a * b / (s * s * (s + 1))

    def mode(self, *, fill_value: float = 0.0) -> Float[Array, "*shape"]:
        """``[*shape]`` posterior mode of the reflection probability.

        ``(a - 1) / (a + b - 2)`` clipped to ``[0, 1]`` when ``a + b > 2``; for ``a + b <= 2``
        the boundary the density diverges at (1 if ``a >= 1 > b``, 0 if ``b >= 1 > a``). With
        the uniform prior this is the ML reflection map ``H / (H + M)`` (Eqs. 7.22, 8.16).

        Args:
            fill_value: value where the mode is not unique (flat density ``a = b = 1``,
                e.g. unobserved cells under the uniform prior, or bimodal ``a, b < 1``).
        """
        a, b = self.a, self.b
        s = a + b
        interior = jnp.clip((a - 1) / jnp.where(s > 2, s - 2, 1.0), 0.0, 1.0)
        edge = jnp.where((a >= 1) & (b < 1), 1.0, jnp.where((b >= 1) & (a < 1), 0.0, fill_value))
        return jnp.where(s > 2, interior, edge).astype(a.dtype)


class GammaPosteriorMap(_AbstractPosteriorModel):
    """Full posterior over a decay-rate map, ``bel(lambda_i) = Gamma(H_i + alpha, R_i + beta)``
    with shape ``a`` and rate ``b`` (1/m) (Eq. 8.17).

    Attributes:
        spec: the grid.
        hits: ``[*shape]`` float, ``H_i``.
        lengths: ``[*shape]`` float, ``R_i`` (m).
        alpha: ``[]`` prior shape (> 0).
        beta: ``[]`` prior rate (m, >= 0; 0 is the improper uninformative prior).

    Concrete fields are checked at construction (finite, ``hits``/``lengths`` ``>= 0``;
    ``ValueError`` naming the field); traced ones when a likelihood is evaluated
    (``eqx.error_if``). An infinite ``R_i`` or ``beta`` would make the rate posterior a
    point mass at 0 and the likelihood ``log(inf) - log(inf + d)``, i.e. NaN.
    """

    spec: GridSpec
    hits: Float[Array, "*shape"]
    lengths: Float[Array, "*shape"]
    alpha: Float[Array, ""]
    beta: Float[Array, ""]

    @property
    def a(self) -> Float[Array, "*shape"]:
        """``[*shape]`` posterior shape ``H_i + alpha``."""
        return self.hits + self.alpha

    @property
    def b(self) -> Float[Array, "*shape"]:
        """``[*shape]`` posterior rate ``R_i + beta`` (m)."""
        return self.lengths + self.beta

    def __check_init__(self):
        _check_map_fields(self, ("hits", "lengths"), beta_zero_ok=True)

    def mean(self) -> Float[Array, "*shape"]:
        """``[*shape]`` posterior mean decay rate ``a / b`` (1/m); ``inf`` where ``b = 0``."""
        return self.a / self.b

    def variance(self) -> Float[Array, "*shape"]:
        """``[*shape]`` posterior variance ``a / b^2`` (1/m^2); ``inf`` where ``b = 0``."""
        return self.a / (self.b * self.b)

    def mode(self, *, fill_value: float = 0.0) -> Float[Array, "*shape"]:
        """``[*shape]`` posterior mode ``max(a - 1, 0) / b`` (1/m).

        With the uninformative prior ``Gamma(1, 0)`` this is the ML decay-rate map
        ``H / R`` (Eqs. 7.10, 8.18): ``inf`` for ``H > 0, R = 0``.

        Args:
            fill_value: value where the density is flat (``a = 1, b = 0``: unobserved
                cells under the uninformative prior).
        """
        a, b = self.a, self.b
        interior = jnp.maximum(a - 1, 0.0) / jnp.where(b > 0, b, 1.0)
        improper = jnp.where(a > 1, jnp.inf, jnp.where(a < 1, 0.0, fill_value))
        return jnp.where(b > 0, interior, improper).astype(a.dtype)


def _resolve_prior(stats, alpha, beta, prior, matcher, uniform):
    _check_prior_args(alpha, beta, prior)
    if alpha is None:
        if prior == "uniform":
            return uniform
        return matcher(stats)
    return alpha, beta


def beta_posterior(
    stats: GridStats,
    *,
    alpha: float | None = None,
    beta: float | None = None,
    prior: PriorName = "moments",
) -> BetaPosteriorMap:
    """Closed-form reflection-map posterior ``Beta(H_i + alpha, M_i + beta)``, Eq. (8.15).

    Args:
        stats: grid statistics (``hits``, ``misses``).
        alpha: prior parameter (> 0); give together with ``beta``.
        beta: prior parameter (> 0).
        prior: used when ``alpha``/``beta`` are None: ``"moments"`` (default) moment-matches
            the ML map as in section 8.5 (:func:`beta_moment_prior`); ``"uniform"`` is
            ``Beta(1, 1)``, whose posterior mode is the ML map of Eqs. (7.22) / (8.16).

    Returns:
        A :class:`BetaPosteriorMap` over ``stats.spec``.

    Raises:
        ValueError: bad ``stats``/``alpha``/``beta``/``prior`` (message names the argument),
            including NaN, infinite or negative entries of the used ``stats`` fields (under
            ``jit``: a runtime ``eqx.error_if`` error with the same message).
    """
    stats = _check_stats(stats)
    counts = _checked_counts(stats, ("hits", "misses"))
    alpha, beta = _resolve_prior(stats, alpha, beta, prior, beta_moment_prior, (1.0, 1.0))
    alpha = _check_param(alpha, "alpha", allow_zero=False)
    beta = _check_param(beta, "beta", allow_zero=False)
    dtype = jnp.result_type(float)
    return BetaPosteriorMap(
        spec=stats.spec,
        hits=counts["hits"],
        misses=counts["misses"],
        alpha=alpha.astype(dtype),
        beta=beta.astype(dtype),
    )


def gamma_posterior(
    stats: GridStats,
    *,
    alpha: float | None = None,
    beta: float | None = None,
    prior: PriorName = "moments",
) -> GammaPosteriorMap:
    """Closed-form decay-rate-map posterior ``Gamma(H_i + alpha, R_i + beta)``, Eq. (8.17).

    Args:
        stats: grid statistics (``hits``, ``lengths``).
        alpha: prior shape (> 0); give together with ``beta``.
        beta: prior rate (m, >= 0).
        prior: used when ``alpha``/``beta`` are None: ``"moments"`` (default) moment-matches
            the ML map as in section 8.5 (:func:`gamma_moment_prior`); ``"uniform"`` is the
            uninformative ``Gamma(1, 0)`` whose posterior mode is the ML map of Eqs. (7.10) /
            (8.18). That prior is improper: unobserved cells (``R_i = 0``) then give
            likelihood 0 (log ``-inf``) to any ray passing them with positive length.

    Returns:
        A :class:`GammaPosteriorMap` over ``stats.spec``.

    Raises:
        ValueError: bad ``stats``/``alpha``/``beta``/``prior`` (message names the argument),
            including NaN, infinite or negative entries of the used ``stats`` fields (under
            ``jit``: a runtime ``eqx.error_if`` error with the same message).
    """
    stats = _check_stats(stats)
    counts = _checked_counts(stats, ("hits", "lengths"))
    alpha, beta = _resolve_prior(stats, alpha, beta, prior, gamma_moment_prior, (1.0, 0.0))
    alpha = _check_param(alpha, "alpha", allow_zero=False)
    beta = _check_param(beta, "beta", allow_zero=True)
    dtype = jnp.result_type(float)
    return GammaPosteriorMap(
        spec=stats.spec,
        hits=counts["hits"],
        lengths=counts["lengths"],
        alpha=alpha.astype(dtype),
        beta=beta.astype(dtype),
    )


# --------------------------------------------------------------------------------------
# Closed-form per-cell factors (Eqs. 8.21, 8.22 and the decay-rate analogue)
# --------------------------------------------------------------------------------------


def _log_l_ref(a, b, delta):
    """log of Eq. (8.22): ``a^delta b^(1-delta) / (a + b)``, ``a, b > 0``."""
    return jnp.where(delta, jnp.log(a), jnp.log(b)) - jnp.log(a + b)


def _log_l_dec(a, b, d, delta):
    """log of ``l_dec(d, delta) = (b / (b + d))^a (a / (b + d))^delta`` (section 8.4.5).

    This is ``E[lambda^delta exp(-lambda d)]`` for ``lambda ~ Gamma(a, b)`` (rate ``b``):
    ``b^a Gamma(a + delta) / (Gamma(a) (b + d)^(a + delta))``. ``d = 0, delta = 0`` gives 0;
    ``b = 0 < d`` (improper posterior) gives ``-inf``; ``b + d = 0`` with ``delta = 1``
    (the improper mean) is capped at ``a / tiny`` so sums stay NaN-free.
    """
    pos = d > 0
    d_safe = jnp.where(pos, d, 1.0)
    miss = jnp.where(pos, a * (jnp.log(b) - jnp.log(b + d_safe)), 0.0)
    tiny = jnp.finfo(jnp.result_type(b)).tiny
    hit = jnp.log(a) - jnp.log(jnp.maximum(b + d, tiny))
    return miss + jnp.where(delta, hit, 0.0)


def _log1mexp(x):
    """``log(1 - exp(x))`` for ``x < 0``, stable at both ends; ``-inf`` for ``x >= 0``.

    NaN-free in value and gradient: both branches see only arguments where they are
    finite (double ``where``), and ``x >= 0`` (including ``+inf``, e.g. the log-density
    of a HIT ray above 0, whose SUB branch is computed and then discarded) gets a zero
    gradient. The previous form clipped ``x`` to 0 and differentiated ``log(-expm1(0))``,
    whose infinite derivative times the zero cotangent of the untaken branch gave NaN.
    """
    return jnp.where(jnp.isnan(x), x, log1mexp(-x))


def _gather(values: Array, cells: Array) -> Array:
    return values[tuple(jnp.moveaxis(cells, -1, 0))]


# --------------------------------------------------------------------------------------
# Measurement likelihood L(z, x), Eq. (8.20)
# --------------------------------------------------------------------------------------


def log_likelihood(
    posterior_map: BetaPosteriorMap | GammaPosteriorMap,
    rays: RayBatch,
    *,
    max_cells: int | None = None,
) -> Float[Array, "*batch"]:
    """Log of the closed-form measurement likelihood ``L(z, x)`` (Eq. 8.20) per ray.

    ``L`` factorises over the cells the ray enters (Eq. 8.21). Per cell, with posterior
    parameters ``a_i, b_i``, travelled length ``r_i`` (m) and reflection indicator
    ``delta_i`` (1 only in the reflecting cell of a HIT ray):

    - reflection model (:class:`BetaPosteriorMap`), Eq. (8.22):
      ``l_ref = a_i^delta_i b_i^(1 - delta_i) / (a_i + b_i)`` (a probability);
    - decay-rate model (:class:`GammaPosteriorMap`), section 8.4.5 after Eq. (8.23):
      ``l_dec = (b_i / (b_i + r_i))^a_i (a_i / (b_i + r_i))^delta_i`` (a density in 1/m for
      HIT rays).

    Ray kinds (end of section 8.4.5): HIT rays multiply the no-reflection factors of all
    cells before the reflecting cell and the reflection factor of that cell; SUP rays give
    ``P(r > r_max) = prod_{i in I(r_max)} l(r_i, 0)``; SUB rays give
    ``P(r < r_min) = 1 - prod_{i in I(r_min)} l(r_i, 0)`` (computed as ``log1mexp``).

    Ray parts outside the grid: the path outside the grid (before entering and after
    leaving, total length ``r_out``) is treated as *one* extra unobserved cell with the prior
    ``(alpha, beta)`` (``H = M = R = 0``), in the spirit of "a single prior to all points
    outside" (section 7.4.2): it contributes ``l(r_out, delta_out)``, where ``delta_out = 1``
    for HIT rays ending outside the grid. Cells entered with zero length (only the start
    cell of a zero-length ray) count only if they reflect the ray.

    Jit-compiled; ``NaN``-free: impossible measurements give ``-inf``.

    Args:
        posterior_map: a :class:`BetaPosteriorMap` or :class:`GammaPosteriorMap`.
        rays: a :class:`~lidarjax.rays.RayBatch` of any batch shape ``[*batch]`` and the
            map's dimension.
        max_cells: static per-ray cell budget (default: enough for any ray,
            :func:`~lidarjax.raytrace.max_cells_for`). A truncated ray is a runtime error.

    Returns:
        ``[*batch]`` log-likelihoods: log-probabilities for SUB/SUP rays (and all rays of
        the reflection model), log-densities (log 1/m) for HIT rays of the decay-rate model.
        Reflection-model HIT probabilities are not converted to densities (Eq. 7.32);
        divide by the reflecting cell's chord length yourself when comparing models.
    """
    if not isinstance(posterior_map, (BetaPosteriorMap, GammaPosteriorMap)):
        raise ValueError(
            "posterior_map must be a BetaPosteriorMap or GammaPosteriorMap, got "
            f"{type(posterior_map).__name__}"
        )
    if not isinstance(rays, RayBatch):
        raise ValueError(f"rays must be a RayBatch, got {type(rays).__name__}")
    spec = posterior_map.spec
    if rays.dim != spec.dim:
        raise ValueError(f"rays are {rays.dim}-D but posterior_map is a {spec.dim}-D grid")
    return walk_log_likelihood(posterior_map, rays, max_cells=max_cells)


def _checked_ab(posterior_map):
    """Posterior parameters ``(a, b)``; traced ones carry a run-time check (``a > 0`` and
    ``b > 0``, ``b >= 0`` for the Gamma posterior, both finite): an infinite or NaN
    statistic would otherwise turn likelihoods into NaN (``log(inf) - log(inf + d)``).
    Concrete maps were checked when they were built."""
    a, b = posterior_map.a, posterior_map.b
    if is_concrete(a) and is_concrete(b):
        return a, b
    b_ok = b >= 0 if isinstance(posterior_map, GammaPosteriorMap) else b > 0
    bad = ~(jnp.isfinite(a) & jnp.isfinite(b) & (a > 0) & b_ok)
    a = check(
        a,
        bad,
        f"{type(posterior_map).__name__}: hits, misses/lengths, alpha and beta must be "
        "finite and >= 0 (alpha > 0)",
    )
    return a, b


def term(posterior_map):
    """Per-cell summand of ``log L`` for a cell the ray passes without reflection."""
    a, b = _checked_ab(posterior_map)
    if isinstance(posterior_map, BetaPosteriorMap):
        return CellTerm.linear(offset=_log_l_ref(a, b, False))
    return CellTerm.gamma(a, b)


def finish(posterior_map, f: RayFold, origin, direction, trace_len, kind):
    """``log L(z, x)`` of rays from their :class:`~lidarjax.raytrace.RayFold` (any batch)."""
    spec = posterior_map.spec
    dtype = f.body.dtype
    is_hit = kind == HIT
    eps = jnp.finfo(dtype).eps
    tol = 32 * eps * (f.t_end + spec.resolution)
    ends_inside = f.any_valid & (f.t_end >= trace_len - tol)
    delta_last = is_hit & ends_inside
    # a cell entered with zero length counts only if it reflects the ray
    entered_last = f.any_valid & ((f.last_len > 0) | delta_last)
    r_out = jnp.maximum(trace_len - (f.t_end - f.t_start), 0.0)
    delta_out = is_hit & ~ends_inside
    out_used = (r_out > tol) | delta_out
    a_k = _gather(posterior_map.a, f.last_cell)
    b_k = _gather(posterior_map.b, f.last_cell)
    alpha, beta = posterior_map.alpha, posterior_map.beta
    if isinstance(posterior_map, BetaPosteriorMap):
        last_log = _log_l_ref(a_k, b_k, delta_last)
        out_log = _log_l_ref(alpha, beta, delta_out)
    else:
        last_log = _log_l_dec(a_k, b_k, f.last_len, delta_last)
        out_log = _log_l_dec(alpha, beta, r_out, delta_out)
    total = f.body + jnp.where(entered_last, last_log, 0.0)
    total = total + jnp.where(out_used, out_log, 0.0)
    result = jnp.where(kind == SUB, _log1mexp(total), total)
    return jnp.where((kind == HIT) | (kind == SUB) | (kind == SUP), result, -jnp.inf)


# --------------------------------------------------------------------------------------
# Occupancy (section 12.4.1)
# --------------------------------------------------------------------------------------


def occupancy(beta_map: BetaPosteriorMap, mu_o: float | ArrayLike = 0.2) -> Float[Array, "*shape"]:
    """Occupancy probability ``o_j = int_{mu_o}^1 Beta(mu; a_j, b_j) dmu`` (section 12.4.1).

    Computed as ``1 - I_{mu_o}(a_j, b_j) = I_{1 - mu_o}(b_j, a_j)`` with the regularised
    incomplete beta function (the symmetric form avoids cancellation for large ``o_j``).

    Args:
        beta_map: a :class:`BetaPosteriorMap`.
        mu_o: reflection-probability threshold above which a cell counts as occupied,
            scalar in ``[0, 1]`` (the dissertation uses 0.2).

    Returns:
        ``[*shape]`` occupancy probabilities in ``[0, 1]``.
    """
    if not isinstance(beta_map, BetaPosteriorMap):
        raise ValueError(f"beta_map must be a BetaPosteriorMap, got {type(beta_map).__name__}")
    if jnp.shape(mu_o) != ():
        raise ValueError(f"mu_o must be a scalar, got shape {jnp.shape(mu_o)}")
    if is_concrete(mu_o):
        m = float(mu_o)
        if not (0.0 <= m <= 1.0):
            raise ValueError(f"mu_o must lie in [0, 1], got {m}")
    else:
        mu_o = check(mu_o, (mu_o < 0) | (mu_o > 1), "mu_o must lie in [0, 1]")
    a, b = beta_map.a, beta_map.b
    x = jnp.asarray(1.0 - jnp.asarray(mu_o, a.dtype), a.dtype)
    return jnp.clip(betainc(b, a, jnp.broadcast_to(x, a.shape)), 0.0, 1.0)
