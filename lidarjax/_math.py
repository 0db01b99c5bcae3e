"""NaN-safe scalar math shared by the sensor models, maps and localization: ``log`` of
zero, ``log(1 - exp(-x))`` and ``0 * inf``, each with finite gradients."""

from __future__ import annotations

import math

import jax.numpy as jnp
from jax import Array

_LOG2 = math.log(2.0)


def safe_log(x: Array) -> Array:
    """``log(x)`` with ``log(0) = -inf`` and a finite (zero) gradient at ``x <= 0``."""
    pos = x > 0
    return jnp.where(pos, jnp.log(jnp.where(pos, x, 1.0)), -jnp.inf)


def log1mexp(x: Array) -> Array:
    """``log(1 - exp(-x))`` for ``x >= 0``, stable for small and large ``x``; ``-inf`` at
    ``x <= 0`` with a zero (not NaN) gradient there."""
    pos = x > 0
    xs = jnp.where(pos, x, 1.0)
    small = xs < _LOG2
    a = jnp.log(-jnp.expm1(-jnp.where(small, xs, _LOG2)))
    b = jnp.log1p(-jnp.exp(-jnp.where(small, _LOG2, xs)))
    return jnp.where(pos, jnp.where(small, a, b), -jnp.inf)


def mul0(a: Array, b: Array) -> Array:
    """``a * b`` with ``0 * inf := 0``; NaN-free gradients (zero where the product is 0 or
    infinite)."""
    zero = (a == 0) | (b == 0)
    infinite = ~zero & ~(jnp.isfinite(a) & jnp.isfinite(b))
    safe = zero | infinite
    prod = jnp.where(safe, 1.0, a) * jnp.where(safe, 1.0, b)
    return jnp.where(zero, 0.0, jnp.where(infinite, jnp.sign(a) * jnp.sign(b) * jnp.inf, prod))


def symmetric_eigh_small(a: Array, sweeps: int = 8) -> tuple[Array, Array]:
    """Eigen-decomposition of a batch of small symmetric matrices ``[..., k, k]`` by
    cyclic Jacobi rotations, in plain jnp (no LAPACK call).

    For the 3 x 3 / 6 x 6 pose covariances of particle filters. jaxlib's batched LAPACK
    kernels (``eigh``, ``solve``, ``cholesky``) split the batch over XLA's CPU thread pool
    and wait on it from inside a pool thread; in a vmapped ``lax.scan`` on a 2-core
    machine two such kernels can occupy every pool thread and wait for each other for
    ever (observed here, the XLA CPU Eigen-pool reentrancy wedge). A fixed number of
    sweeps keeps the loop bounded; 8 sweeps reach float64 round-off for ``k <= 6``
    (Jacobi converges quadratically).

    Returns:
        ``(w [..., k], v [..., k, k])`` with ``a = v diag(w) v^T`` (columns of ``v`` the
        eigenvectors; eigenvalues unsorted).
    """
    a = jnp.asarray(a)
    k = a.shape[-1]
    v = jnp.broadcast_to(jnp.eye(k, dtype=a.dtype), a.shape)
    eye = jnp.eye(k, dtype=a.dtype)
    for _ in range(sweeps):
        for p in range(k - 1):
            for q in range(p + 1, k):
                app, aqq, apq = a[..., p, p], a[..., q, q], a[..., p, q]
                theta = 0.5 * jnp.arctan2(2 * apq, app - aqq)
                c, s = jnp.cos(theta), jnp.sin(theta)
                # rotation in the (p, q) plane that zeroes a_pq in r^T a r
                r = jnp.broadcast_to(eye, a.shape)
                r = r.at[..., p, p].set(c).at[..., q, q].set(c)
                r = r.at[..., p, q].set(-s).at[..., q, p].set(s)
                a = jnp.swapaxes(r, -1, -2) @ a @ r
                v = v @ r
    return jnp.diagonal(a, axis1=-2, axis2=-1), v
