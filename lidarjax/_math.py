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
