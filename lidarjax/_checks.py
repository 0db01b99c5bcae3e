"""Run-time checks of traced values that keep compiled programs cacheable.

``eqx.error_if`` raises from inside a compiled program through a host callback, and JAX
never writes a program with a host callback to its persistent compilation cache
(:func:`lidarjax.enable_compilation_cache`): every process would recompile the library's
main programs (ray accumulation, likelihoods at poses, the particle filter, pole
extraction) for 3-7 s. This module turns such checks into boolean outputs instead:

- :func:`check` is ``eqx.error_if`` with the same arguments and the same result, except
  that inside a program traced by :func:`checked_jit` (or a :func:`scan` / :func:`map`
  body) at the same trace level, the condition becomes an output flag of the program
  (no callback) rather than a callback;
- :func:`checked_jit` is ``eqx.filter_jit`` whose program returns those flags; the call
  raises :class:`equinox.EquinoxRuntimeError` with the check's message on the host when
  one is set (one device-to-host copy of a few booleans per call). Under someone else's
  ``jit``/``vmap``/``grad`` the flags are traced; they are then re-attached as checks of
  the enclosing trace (``eqx.error_if``, or the enclosing :func:`checked_jit`'s flags);
- :func:`scan` and :func:`map` are ``lax.scan`` / ``lax.map`` that collect the checks of
  their body per iteration and reduce them after the loop, at the caller's level;
  :func:`cond` is ``lax.cond`` that returns its branches' checks (up to 64 each; more stay
  ``eqx.error_if``) to the caller's level.

A check inside a plain ``lax.scan``, ``while_loop``, ``cond`` or ``vmap`` body is at another
trace level and stays an ``eqx.error_if`` (correct, just not cacheable). Semantics never
change: a failed check raises, as before, with its message.
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

try:  # the current trace (JAX >= 0.4.36); without it every check stays an eqx.error_if
    from jax._src.core import trace_ctx as _trace_ctx
except ImportError:  # pragma: no cover - older JAX
    _trace_ctx = None

__all__ = ["check", "checked_jit", "cond", "map", "scan"]


class _Collector:
    """The checks met while tracing one program (or loop body) at one trace level."""

    def __init__(self):
        self.trace = _current_trace()
        self.flags: list[jax.Array] = []
        self.messages: list[str] = []


_local = threading.local()


def _stack() -> list[_Collector]:
    if not hasattr(_local, "stack"):
        _local.stack = []
    return _local.stack


def _current_trace():
    return None if _trace_ctx is None else _trace_ctx.trace


def _trace_of(x) -> Any:
    return getattr(x, "_trace", None)


def check(x, pred, msg: str):
    """``eqx.error_if(x, pred, msg)``: fail with ``msg`` where ``pred`` holds.

    Inside a :func:`checked_jit` program (or :func:`scan`/:func:`map` body), a traced
    ``pred`` of that program's own trace level becomes one of its output flags and ``x``
    is returned unchanged; otherwise this is exactly ``eqx.error_if`` (eager values raise
    now, traced ones through a callback).

    Args:
        x: the pytree of arrays that carries the check (use the returned value).
        pred: boolean array of any shape; the check fails if any entry is true.
        msg: the error message (name the argument).

    Returns:
        ``x``.
    """
    stack = _stack()
    if stack and isinstance(pred, jax.core.Tracer):
        top = stack[-1]
        if top.trace is not None and _trace_of(pred) is top.trace:
            top.flags.append(jnp.any(pred))
            top.messages.append(msg)
            return x
    return eqx.error_if(x, pred, msg)


def _collect(fn: Callable, *args, **kwargs):
    """Run ``fn`` with a fresh collector at the current trace level:
    ``(out, flags [n] bool, messages (n,))``."""
    col = _Collector()
    stack = _stack()
    stack.append(col)
    try:
        out = fn(*args, **kwargs)
    finally:
        stack.pop()
    flags = jnp.stack(col.flags) if col.flags else jnp.zeros((0,), bool)
    return out, flags, tuple(col.messages)


def _is_plain_array(x) -> bool:
    """An array a callback can carry (not a typed PRNG key array)."""
    return eqx.is_array(x) and not jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _reattach(out, flags, messages: tuple[str, ...]):
    """The checks ``flags`` (``[..., n]``, any leading axes reduced) of ``messages`` on
    ``out``: raised now when concrete, else checks of the enclosing trace."""
    if not messages:
        return out
    if not isinstance(flags, jax.core.Tracer):
        bad = jax.device_get(flags).reshape(-1, len(messages)).any(axis=0)
        for b, m in zip(bad, messages):
            if b:
                raise eqx.EquinoxRuntimeError(m)
        return out
    flags = flags.reshape(-1, len(messages)).any(axis=0)
    arrays, static = eqx.partition(out, _is_plain_array)
    for i, m in enumerate(messages):
        arrays = check(arrays, flags[i], m)
    return eqx.combine(arrays, static)


def checked_jit(fn: Callable | None = None, **jit_kwargs):
    """``eqx.filter_jit`` whose traced :func:`check` calls are returned as flags and
    raised on the host after the call (see the module docstring); usable as
    ``@checked_jit`` or ``@checked_jit(donate=...)``."""
    if fn is None:
        return functools.partial(checked_jit, **jit_kwargs)

    @eqx.filter_jit(**jit_kwargs)
    @functools.wraps(fn)  # the compiled program keeps fn's name (jit_<name>)
    def program(*args, **kwargs):
        return _collect(fn, *args, **kwargs)

    @functools.wraps(fn)
    def call(*args, **kwargs):
        out, flags, messages = program(*args, **kwargs)
        return _reattach(out, flags, messages)

    call.program = program  # the jitted program (for ``.lower``), returning the flags too
    return call


def scan(f: Callable, init, xs=None, length: int | None = None, **kwargs):
    """``jax.lax.scan(f, init, xs, length, ...)`` whose body's :func:`check` calls are
    collected per iteration and checked after the loop at the caller's level."""
    box: dict[str, tuple[str, ...]] = {}

    def body(carry, x):
        (carry, y), flags, messages = _collect(f, carry, x)
        box["messages"] = messages
        return carry, (y, flags)

    carry, (ys, flags) = jax.lax.scan(body, init, xs, length, **kwargs)
    carry = _reattach(carry, flags, box.get("messages", ()))
    return carry, ys


def map(f: Callable, xs, **kwargs):  # noqa: A001 - mirrors jax.lax.map
    """``jax.lax.map(f, xs, ...)`` whose body's :func:`check` calls are collected per
    iteration and checked after the loop at the caller's level."""
    box: dict[str, tuple[str, ...]] = {}

    def body(x):
        out, flags, messages = _collect(f, x)
        box["messages"] = messages
        return out, flags

    ys, flags = jax.lax.map(body, xs, **kwargs)
    return _reattach(ys, flags, box.get("messages", ()))


_COND_SLOTS = 64  # checks per branch returned by cond (a branch with more keeps callbacks)


def cond(pred, true_fn: Callable, false_fn: Callable, *operands):
    """``jax.lax.cond(pred, true_fn, false_fn, *operands)`` whose branches' :func:`check`
    calls are returned (a fixed ``[64]`` flag vector per branch, so both branches have the
    same output structure) and checked at the caller's level; a check fails only if its
    branch ran."""
    box: dict[str, tuple[str, ...]] = {}
    zeros = jnp.zeros((_COND_SLOTS,), bool)

    def branch(fn, key):
        def run(*ops):
            out, flags, messages = _collect(fn, *ops)
            if len(messages) > _COND_SLOTS:  # too many: keep them as eqx.error_if
                out = _reattach(out, flags, messages)
                flags, messages = jnp.zeros((0,), bool), ()
            box[key] = messages
            mine = zeros.at[: len(messages)].set(flags) if messages else zeros
            return (out, mine, zeros) if key == "true" else (out, zeros, mine)

        return run

    out, f_true, f_false = jax.lax.cond(
        pred, branch(true_fn, "true"), branch(false_fn, "false"), *operands
    )
    for key, flags in (("true", f_true), ("false", f_false)):
        messages = box.get(key, ())
        out = _reattach(out, flags[: len(messages)], messages)
    return out
