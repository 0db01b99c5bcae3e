"""Process-level CPU settings a user may opt into (never applied on import).

XLA's CPU runtime hands the work of a compiled computation between the threads of its
pool. For small computations that run many sequential steps (PLE+'s Levenberg–Marquardt
loops over ~50 vertices) each hand-off waits for a core; when other processes keep the
cores busy, a call that takes 0.06–0.2 s on its own core takes 1.5–25 s (issue #20:
measured on 2 cores with two busy-loop processes; no per-computation XLA option changes
it). Pinning the whole process to one core before JAX starts its CPU client keeps every
hand-off on that core: 0.06 s idle and 0.2 s under the same load. It must happen before
the first JAX computation, because the pool threads inherit the affinity when they are
created, and it trades away multi-core speed-ups of large computations (grid folds,
batched likelihoods), so it is a user's choice, not a default.
"""

from __future__ import annotations

import os


def pin_to_one_core(core: int | None = None) -> int:
    """Pin this process (and the threads JAX will start) to one CPU core.

    Call it first, before any JAX computation, e.g. at the top of a script or notebook.
    Linux only (``os.sched_setaffinity``).

    Args:
        core: the core to use; default: the lowest core the process may run on now.

    Returns:
        The core the process is pinned to.

    Raises:
        RuntimeError: JAX's backends are already initialised (pinning now would leave the
            existing pool threads on their cores, which is slower than not pinning), or
            the platform has no ``sched_setaffinity``.
        ValueError: ``core`` is not one of the cores this process may run on.
    """
    if not hasattr(os, "sched_setaffinity"):
        raise RuntimeError("pin_to_one_core needs os.sched_setaffinity (Linux)")
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        raise RuntimeError(
            "pin_to_one_core must run before the first JAX computation: JAX's CPU client "
            "and its thread pool already exist (call it at the top of the script)"
        )
    allowed = sorted(os.sched_getaffinity(0))
    if core is None:
        core = allowed[0]
    if isinstance(core, bool) or not isinstance(core, int) or core not in allowed:
        raise ValueError(f"core must be one of the allowed cores {allowed}, got {core!r}")
    os.sched_setaffinity(0, {core})
    return core
