"""Map-quality and pose-likelihood metrics (dissertation sections 7.6.2, 8.5.2 and 9.5.1).

- :func:`p_ref` and :func:`map_rmse` / :func:`p_ref_rmse`: the map-value comparison of
  section 9.5.1 (RMSE in reflection probability ``p_ref = 1 - exp(-lambda * 1 m)``).
- :func:`dirac_divergence`: ``D'(g||h)`` of Eq. (7.28), the negative log-likelihood of all
  measurements at the true pose.
- :func:`inverse_kl`: ``D(h||g)`` of Eq. (7.29), sample approximation over poses around the
  true pose.
- :func:`kl_to_gaussian`: ``D_KL(p_gt || p)`` of Eqs. (8.24)/(8.25), sample approximation.
"""

from __future__ import annotations

import math
from typing import Literal

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jax.scipy.special import logsumexp
from jaxtyping import Array, ArrayLike, Bool, Float

from .._checks import check
from ..rays import is_concrete

__all__ = [
    "p_ref",
    "map_rmse",
    "p_ref_rmse",
    "dirac_divergence",
    "inverse_kl",
    "kl_to_gaussian",
    "gaussian_log_density",
]


def p_ref(
    rates: Float[ArrayLike, "*shape"], distance_m: float | ArrayLike = 1.0
) -> Float[Array, "*shape"]:
    """Reflection probability ``p_ref = 1 - exp(-lambda * distance_m)`` (section 9.5.1).

    Section 9.5.1 (and the caption of Fig. 9.1) uses ``p_ref = 1 - exp(-lambda)``: the
    probability that a ray is reflected within 1 m of a homogeneous medium of decay rate
    ``lambda``; the 1 m is called an arbitrary choice, so it is a parameter here (pass the
    cell size to get the reflection probability per cell). Maps ``[0, inf]`` onto ``[0, 1]``.

    Args:
        rates: ``[*shape]`` decay rates (1/m), ``>= 0``; ``inf`` maps to 1.
        distance_m: reference distance (m), > 0. Default 1 m as in the dissertation.

    Returns:
        ``[*shape]`` reflection probabilities in ``[0, 1]``.
    """
    if is_concrete(rates):
        r = np.asarray(rates)
        if np.any(np.isnan(r)) or np.any(r < 0):
            raise ValueError("rates must be >= 0 and not NaN")
    if jnp.shape(distance_m) != ():
        raise ValueError(f"distance_m must be a scalar, got shape {jnp.shape(distance_m)}")
    if is_concrete(distance_m):
        dm = float(distance_m)
        if not (math.isfinite(dm) and dm > 0):
            raise ValueError(f"distance_m must be finite and > 0, got {dm}")
    rates = jnp.asarray(rates, jnp.result_type(float))
    return -jnp.expm1(-rates * distance_m)


def map_rmse(
    a: Float[ArrayLike, "*shape"],
    b: Float[ArrayLike, "*shape"],
    mask: Bool[ArrayLike, "*shape"] | None = None,
) -> Float[Array, ""]:
    """Root mean squared difference ``sqrt(mean_{mask} (a - b)^2)`` of two maps.

    Section 9.5.1 evaluates it over "the mid-points of all cells that were observed at
    least once" (pass that as ``mask``) on ``p_ref`` values (see :func:`p_ref_rmse`).

    Args:
        a: ``[*shape]`` map values.
        b: ``[*shape]`` map values (same shape).
        mask: optional ``[*shape]`` bool; cells to include (default all).

    Returns:
        ``[]`` RMSE in the units of the maps.

    Raises:
        ValueError: shape mismatch or an empty mask (runtime error under ``jit``).
    """
    a = jnp.asarray(a, jnp.result_type(float))
    b = jnp.asarray(b, a.dtype)
    if a.shape != b.shape:
        raise ValueError(f"a and b must have the same shape, got {a.shape} and {b.shape}")
    if mask is None:
        mask = jnp.ones(a.shape, bool)
    mask = jnp.asarray(mask)
    if mask.shape != a.shape:
        raise ValueError(f"mask must have shape {a.shape}, got {mask.shape}")
    if mask.dtype != jnp.bool_:
        raise ValueError(f"mask must be boolean, got dtype {mask.dtype}")
    n = jnp.sum(mask)
    if is_concrete(n):
        if int(n) == 0:
            raise ValueError("mask selects no cells")
    else:
        n = check(n, n == 0, "mask selects no cells")
    diff = jnp.where(mask, a - b, 0.0)
    return jnp.sqrt(jnp.sum(diff * diff) / jnp.maximum(n, 1))


def p_ref_rmse(
    rates_a: Float[ArrayLike, "*shape"],
    rates_b: Float[ArrayLike, "*shape"],
    mask: Bool[ArrayLike, "*shape"] | None = None,
    distance_m: float = 1.0,
) -> Float[Array, ""]:
    """RMSE in ``p_ref`` between two decay-rate maps (section 9.5.1, Table 9.2).

    Args:
        rates_a: ``[*shape]`` decay rates (1/m).
        rates_b: ``[*shape]`` decay rates (1/m).
        mask: optional ``[*shape]`` bool, e.g. cells observed at least once.
        distance_m: reference distance of :func:`p_ref` (m).

    Returns:
        ``[]`` RMSE (dimensionless).
    """
    return map_rmse(p_ref(rates_a, distance_m), p_ref(rates_b, distance_m), mask)


def dirac_divergence(log_likelihoods: Float[ArrayLike, "*batch"]) -> Float[Array, ""]:
    """``D'(g||h) = -sum_j log p(z_j | s_j, m)``, Eq. (7.28).

    The KL divergence from a Dirac ground truth at the true poses to the pose likelihood,
    up to the model-independent constant ``eta'`` that the dissertation drops.

    Args:
        log_likelihoods: ``[*batch]`` log-likelihoods of all measurements evaluated at the
            true poses (any units; as produced by a sensor model's ``log_likelihood``).

    Returns:
        ``[]`` the negated sum; ``+inf`` if any measurement is impossible.
    """
    ll = jnp.asarray(log_likelihoods, jnp.result_type(float))
    if ll.size == 0:
        raise ValueError("log_likelihoods is empty")
    return -jnp.sum(ll)


def _pose_array(x, name: str) -> Array:
    if isinstance(x, jaxlie.SE2):
        return jnp.concatenate([x.translation(), x.rotation().as_radians()[..., None]], axis=-1)
    if isinstance(x, jaxlie.MatrixLieGroup):
        raise ValueError(f"{name}: only jaxlie.SE2 poses or arrays are supported")
    return jnp.asarray(x, jnp.result_type(float))


def gaussian_log_density(
    sample_poses: Float[ArrayLike, "m k"],
    true_pose: Float[ArrayLike, " k"],
    cov: Float[ArrayLike, "k k"],
    *,
    angle_axes: tuple[int, ...] | None = None,
) -> Float[Array, " m"]:
    """``log N(s_i; s, cov)`` of sample poses around the true pose.

    Args:
        sample_poses: ``[m k]`` poses, e.g. ``(x, y, theta)`` (m, m, rad), or a batched
            ``jaxlie.SE2`` (converted to ``(x, y, theta)``).
        true_pose: ``[k]`` true pose (or a ``jaxlie.SE2``).
        cov: ``[k k]`` symmetric positive-definite covariance.
        angle_axes: components that are angles; their differences are wrapped to
            ``[-pi, pi)``. Default: ``(2,)`` for ``k = 3`` (SE(2) poses), else none.

    Returns:
        ``[m]`` log densities (log of 1/(m^2 rad) for SE(2) poses).
    """
    x = _pose_array(sample_poses, "sample_poses")
    mu = _pose_array(true_pose, "true_pose")
    cov = jnp.asarray(cov, x.dtype)
    if x.ndim != 2:
        raise ValueError(f"sample_poses must have shape [m, k], got {x.shape}")
    k = x.shape[1]
    if mu.shape != (k,):
        raise ValueError(f"true_pose must have shape ({k},), got {mu.shape}")
    if cov.shape != (k, k):
        raise ValueError(f"cov must have shape ({k}, {k}), got {cov.shape}")
    if is_concrete(cov):
        c = np.asarray(cov)
        if not np.allclose(c, c.T) or np.any(np.linalg.eigvalsh(c) <= 0):
            raise ValueError("cov must be symmetric positive definite")
    if angle_axes is None:
        angle_axes = (2,) if k == 3 else ()
    if any(not (0 <= ax < k) for ax in angle_axes):
        raise ValueError(f"angle_axes must index the {k} pose components, got {angle_axes}")
    diff = x - mu
    for ax in angle_axes:
        diff = diff.at[:, ax].set(jnp.mod(diff[:, ax] + jnp.pi, 2 * jnp.pi) - jnp.pi)
    chol = jnp.linalg.cholesky(cov)
    w = jax.scipy.linalg.solve_triangular(chol, diff.T, lower=True)  # [k m]
    maha = jnp.sum(w * w, axis=0)
    logdet = 2 * jnp.sum(jnp.log(jnp.diag(chol)))
    return -0.5 * (maha + logdet + k * math.log(2 * math.pi))


def _check_samples(log_lik_samples, sample_poses) -> Array:
    ll = jnp.asarray(log_lik_samples, jnp.result_type(float))
    if ll.ndim != 1 or ll.shape[0] < 1:
        raise ValueError(f"log_lik_samples must have shape [m] with m >= 1, got {ll.shape}")
    m = _pose_array(sample_poses, "sample_poses").shape[0]
    if m != ll.shape[0]:
        raise ValueError(
            f"sample_poses has {m} poses but log_lik_samples has {ll.shape[0]} entries"
        )
    if is_concrete(ll):
        v = np.asarray(ll)
        if np.any(np.isnan(v)) or np.any(v == np.inf):
            raise ValueError("log_lik_samples must not contain NaN or +inf")
        if not np.any(np.isfinite(v)):
            raise ValueError("log_lik_samples: every sample pose has likelihood 0")
    return ll


def _xlogy_diff(p, log_p, log_q):
    """``p * (log p - log q)`` with ``0 * (...) = 0``."""
    return jnp.where(p > 0, p * (jnp.where(p > 0, log_p, 0.0) - log_q), 0.0)


def inverse_kl(
    log_lik_samples: Float[ArrayLike, " m"],
    sample_poses: Float[ArrayLike, "m k"],
    true_pose: Float[ArrayLike, " k"],
    cov: Float[ArrayLike, "k k"],
    *,
    normalize_reference: bool = False,
    angle_axes: tuple[int, ...] | None = None,
) -> Float[Array, ""]:
    """Inverse KL divergence ``D(h||g)`` between pose likelihood and a Gaussian, Eq. (7.29).

    ``D(h||g) ~= sum_i p_i log(p_i / N(s_i; s, cov))`` over ``m`` sample poses ``s_i``
    (section 7.6.2 draws them uniformly in a disc of radius 2.5 m around the true pose).

    Normalisation, exactly as in the text: ``p_i = p(z | s_i, m) / sum_k p(z | s_k, m)``
    (a softmax of ``log_lik_samples``, so the likelihoods' units and constant factors
    cancel), while ``N(s_i; s, cov)`` is the Gaussian *density* value, not normalised over
    the samples. The result therefore depends on the units of ``cov`` and may be negative.
    With ``normalize_reference=True`` the Gaussian values are normalised over the samples
    too, giving the KL divergence between two discrete distributions on the samples
    (``>= 0``, zero iff they agree).

    Args:
        log_lik_samples: ``[m]`` measurement log-likelihoods ``log p(z | s_i, m)`` (summed
            over the rays of a scan); ``-inf`` allowed, NaN/``+inf`` not.
        sample_poses: ``[m k]`` sample poses (``(x, y, theta)`` in m, m, rad for ``k = 3``)
            or a batched ``jaxlie.SE2``.
        true_pose: ``[k]`` true pose ``s`` (or a ``jaxlie.SE2``).
        cov: ``[k k]`` covariance ``Sigma`` of the ground-truth Gaussian.
        normalize_reference: also normalise the Gaussian over the samples (see above).
        angle_axes: angular pose components (wrapped); default ``(2,)`` for ``k = 3``.

    Returns:
        ``[]`` the divergence (nats).
    """
    ll = _check_samples(log_lik_samples, sample_poses)
    log_g = gaussian_log_density(sample_poses, true_pose, cov, angle_axes=angle_axes)
    if normalize_reference:
        log_g = log_g - logsumexp(log_g)
    log_p = ll - logsumexp(ll)
    p = jnp.exp(log_p)
    return jnp.sum(_xlogy_diff(p, log_p, log_g))


def kl_to_gaussian(
    log_lik_samples: Float[ArrayLike, " m"],
    sample_poses: Float[ArrayLike, "m k"],
    true_pose: Float[ArrayLike, " k"],
    cov: Float[ArrayLike, "k k"],
    *,
    estimator: Literal["paper", "discrete"] = "paper",
    angle_axes: tuple[int, ...] | None = None,
) -> Float[Array, ""]:
    """KL divergence ``D_KL(p_gt || p)`` from the pose likelihood to the ground truth,
    Eqs. (8.24)/(8.25).

    ``p_gt = N(x; s, cov)`` (section 8.5.2: isotropic, sigma = 0.05 m), and
    ``p(x) ∝ p(z | x, m)`` (MLM) or ``∝ L(z, x)`` (FMP, Eq. 8.20), i.e. ``log_lik_samples``
    from the ML sensor models or from
    :func:`lidarjax.maps.posterior_log_likelihood`. Both ``p_gt``
    and ``p`` are normalised over the ``m`` sample poses (as the text prescribes):
    ``g_i = N(s_i) / sum_k N(s_k)``, ``p_i = p(z|s_i) / sum_k p(z|s_k)``.

    Estimators:

    - ``"paper"``: ``sum_i log(g_i / p_i)``, the Monte-Carlo sum printed after Eq. (8.25)
      (a sum, not a mean, as printed; it estimates the integral when the ``s_i`` are drawn
      from ``p_gt``, up to the factor ``m``). Can be negative; ``+inf`` if some ``p_i = 0``.
    - ``"discrete"``: ``sum_i g_i log(g_i / p_i)``, the KL divergence between the two
      normalised discrete distributions on the samples (``>= 0``), appropriate for samples
      not drawn from ``p_gt`` (e.g. a uniform disc or a grid).

    Args:
        log_lik_samples: ``[m]`` log-likelihoods at the sample poses.
        sample_poses: ``[m k]`` sample poses or a batched ``jaxlie.SE2``.
        true_pose: ``[k]`` true pose.
        cov: ``[k k]`` ground-truth covariance.
        estimator: ``"paper"`` or ``"discrete"`` (see above).
        angle_axes: angular pose components; default ``(2,)`` for ``k = 3``.

    Returns:
        ``[]`` the divergence (nats).
    """
    if estimator not in ("paper", "discrete"):
        raise ValueError(f"estimator must be 'paper' or 'discrete', got {estimator!r}")
    ll = _check_samples(log_lik_samples, sample_poses)
    log_g = gaussian_log_density(sample_poses, true_pose, cov, angle_axes=angle_axes)
    log_g = log_g - logsumexp(log_g)
    log_p = ll - logsumexp(ll)
    if estimator == "paper":
        return jnp.sum(log_g - log_p)
    g = jnp.exp(log_g)
    return jnp.sum(_xlogy_diff(g, log_g, log_p))
