"""Process-level settings a user may opt into (never applied on import): pinning to one
CPU core and JAX's persistent compilation cache.

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

The persistent compilation cache (:func:`enable_compilation_cache`) keeps XLA's compiled
programs on disk, so a new process loads them instead of compiling again (issue #25:
first calls compiled for 3-11 s each in every process). The experiments and the test
suite turn it on; importing ``lidarjax`` does not.
"""

from __future__ import annotations

import os
import tempfile
import warnings
from pathlib import Path

CACHE_ENV = "LIDARJAX_JAX_CACHE"
"""Environment variable naming the compilation cache folder (``off``, ``0`` or empty:
no cache)."""

CACHE_MIN_COMPILE_TIME_S = 0.0
"""Programs that compiled faster than this (s) are not written to the cache. 0 caches
every program: a second process then loads even the small helper programs (10-50 ms of
compilation each, dozens per first call of a pipeline) instead of compiling them
(``benchmarks/first_call.py`` measures both)."""

_DISABLED = ("", "off", "0")


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


_VECTOR_ISAS = (("avx512", "avx512f"), ("avx2", "avx2"), ("avx", "avx"), ("sse4_2", "sse4_2"))


def cpu_info(cpuinfo: str | Path = "/proc/cpuinfo") -> dict:
    """``{"cpu_model": str | None, "cpu_vector_isa": "avx512" | "avx2" | "avx" | "sse4_2" |
    None}``: the first model name in ``cpuinfo`` and the widest of these among the first
    processor's flags (Linux; None where the file is missing or says nothing). XLA
    compiles float32 code for the CPU it runs on, so results that depend on rounding (the
    SLAM front end's trajectories, docs/results/slam.md) name it."""
    try:
        text = Path(cpuinfo).read_text()
    except OSError:
        return {"cpu_model": None, "cpu_vector_isa": None}
    model = flags = None
    for line in text.splitlines():
        key, _, value = line.partition(":")
        key = key.strip()
        if key == "model name" and model is None:
            model = value.strip() or None
        elif key == "flags" and flags is None:
            flags = set(value.split())
    isa = next((name for name, flag in _VECTOR_ISAS if flag in (flags or ())), None)
    return {"cpu_model": model, "cpu_vector_isa": isa}


def default_compilation_cache_dir() -> Path | None:
    """The folder :func:`enable_compilation_cache` uses when given no path.

    ``$LIDARJAX_JAX_CACHE`` if set (``off``, ``0`` or empty: ``None``, no cache), else
    ``jax-compilation-cache`` in the user cache, ``$XDG_CACHE_HOME/lidarjax`` (default
    ``~/.cache/lidarjax``).
    """
    env = os.environ.get(CACHE_ENV)
    if env is not None:
        if env.strip().lower() in _DISABLED:
            return None
        return Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / "lidarjax" / "jax-compilation-cache"


def _check_writable(folder: Path) -> None:
    """Create ``folder`` and write (and remove) a probe file in it; ``OSError`` if not."""
    folder.mkdir(parents=True, exist_ok=True)
    fd, probe = tempfile.mkstemp(prefix=".lidarjax-probe-", dir=folder)
    os.close(fd)
    os.unlink(probe)


def enable_compilation_cache(
    path: str | os.PathLike | None = None, *, min_compile_time_s: float | None = None
) -> Path | None:
    """Keep JAX's compiled programs in a folder, so later processes load instead of compile.

    A new process compiles every jitted program on its first call (3-11 s for a scan
    likelihood, a particle filter run or a map fit on 2 cores). With the cache a second
    process finds the executable on disk under a key of the program, its input shapes,
    the jaxlib version and the XLA flags, so an entry is never reused for something else.
    Tracing and lowering still happen in every process; only XLA's compilation is saved.
    JAX never writes programs with host callbacks (``jax.debug.print``, a traced
    ``eqx.error_if``), so those compile in every process; the library's own programs
    return their run-time checks as outputs instead (``lidarjax._checks``), so they are
    cached (``benchmarks/first_call.py`` lists any program that is not).

    Called by the experiments and the test suite; never by importing ``lidarjax``. Safe to
    call at any time: JAX opens the cache at the first compilation after the folder is set
    (checked with JAX 0.10), so programs compiled before the call are just not cached.
    Calling it again with the same folder changes nothing; with another folder, the cache
    JAX already opened is dropped and the new folder is used from the next compilation
    on. It sets JAX's ``jax_compilation_cache_dir``,
    ``jax_persistent_cache_min_compile_time_secs`` and
    ``jax_persistent_cache_min_entry_size_bytes`` (-1: no size threshold). The folder is
    trusted: whoever can write to it can make this process run code, so never point it to
    a folder others can write to. It holds about 50 MB per jaxlib version and is safe to
    delete at any time.

    Args:
        path: the cache folder (created if needed). Default
            :func:`default_compilation_cache_dir`: ``$LIDARJAX_JAX_CACHE`` if set (``off``,
            ``0`` or empty disable the cache), else
            ``$XDG_CACHE_HOME/lidarjax/jax-compilation-cache`` (``~/.cache/...``).
        min_compile_time_s: programs compiled faster than this (s) are not written;
            default :data:`CACHE_MIN_COMPILE_TIME_S` (0: every program).

    Returns:
        The folder in use, or ``None`` when the cache is disabled (by the environment
        variable or ``jax_enable_compilation_cache=False``, JAX's own switch) or the
        folder cannot be written (then with a ``RuntimeWarning``). In both cases JAX's
        configuration is left as it was.

    Raises:
        ValueError: ``min_compile_time_s`` is negative or not a number.
    """
    if min_compile_time_s is None:
        min_compile_time_s = CACHE_MIN_COMPILE_TIME_S
    if isinstance(min_compile_time_s, bool) or not isinstance(min_compile_time_s, (int, float)):
        raise ValueError(f"min_compile_time_s must be a number >= 0, got {min_compile_time_s!r}")
    if not min_compile_time_s >= 0:
        raise ValueError(f"min_compile_time_s must be a number >= 0, got {min_compile_time_s!r}")
    folder = default_compilation_cache_dir() if path is None else Path(path).expanduser()
    if folder is None:
        return None
    import jax

    if not jax.config.jax_enable_compilation_cache:
        return None
    try:
        folder = folder.resolve()
        _check_writable(folder)
    except OSError as e:
        warnings.warn(
            f"JAX compilation cache disabled: cannot write to {str(folder)!r} ({e}); every "
            f"process compiles its programs again (set {CACHE_ENV} to another folder or to "
            "'off')",
            RuntimeWarning,
            stacklevel=2,
        )
        return None
    previous = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
    # -1: no size threshold, and JAX may not raise it for its file system
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    if previous != str(folder):
        jax.config.update("jax_compilation_cache_dir", str(folder))
        _reopen_cache_if_open()
    return folder


def _reopen_cache_if_open() -> None:
    """Make JAX open the cache again at its next compilation: once opened, JAX keeps the
    folder it opened even when ``jax_compilation_cache_dir`` changes (a no-op before)."""
    from jax._src import compilation_cache

    if getattr(compilation_cache, "_cache", None) is not None:
        compilation_cache.reset_cache()
