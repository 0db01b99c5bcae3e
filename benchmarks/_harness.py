"""What every benchmark shares: timing, differences, the machine record, the load policy and
JSON output. The one common module of ``benchmarks/``.

The scripts are run as ``python benchmarks/<name>.py`` from the repository root (the
Makefile's ``bench`` target) with ``lidarjax`` installed in the environment
(``pip install -e .``), so ``import lidarjax`` needs no ``sys.path`` change and this module
(like ``_numpy_reference``, ``_numpy_pf``, ``_numpy_ple``) is importable as ``_harness``
because Python puts the script's own folder first on ``sys.path``. The benchmarks that time
an experiment's own code call :func:`experiments_on_path` before importing it.

- Timing: :func:`time_calls` (warm-up calls, then ``repeats`` timed calls, each ended with
  ``jax.block_until_ready``), :func:`time_stats` (median / min / mean / max of a list of
  seconds), :func:`warm` (one call, compilation included).
- Differences: :func:`max_abs_diff` (absolute / relative differences over two pytrees of
  arrays, and whether their NaN / inf entries agree).
- Record: :func:`machine_info` (CPU, versions, dtype, load) and :func:`write_json`.
- Load: every timed block is wrapped by :meth:`LoadPolicy.measure`:

  1. Right before the block, the 1-minute load average (``os.getloadavg()[0]``), the whole
     triple, the number of running tasks (``/proc/loadavg``) and the CPU cores kept busy by
     other processes over a short idle sample of ``/proc/stat`` are recorded.
  2. The block runs (it does its own warm-up-free timing and returns a dict with at least
     ``times_s``).
  3. If the 1-minute load average was above ``threshold`` (0.5), the policy waits up to
     ``max_wait_s`` (60 s) for it to drop to the threshold (polling), as long as the run's
     total waiting stays within ``budget_s``, then reruns the block once and records the
     load again. Both attempts are kept in the JSON; the attempt with the lower load average
     is the reported one (the rerun on a tie). Without budget left there is no rerun and
     the record says so.

  :meth:`LoadPolicy.time_calls` combines it with :func:`time_calls`: the warm-up calls run
  once, outside the policy; only the timed calls are rerun.

Caveat written into every record: the 1-minute load average lags by about a minute and
includes this benchmark's own threads, so after a minute of timing on 2 cores it is above
0.5 even on an otherwise idle machine; ``other_busy_cores`` (sampled while this process is
idle) is the better sign of other work on the machine.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

import lidarjax
from lidarjax._runtime import cpu_info

ROOT = Path(__file__).resolve().parents[1]
"""The repository root."""
EXPERIMENTS = ROOT / "experiments"
RESULTS = ROOT / "benchmarks" / "results"
"""Where the recorded measurements live (quick runs should write elsewhere)."""

THRESHOLD = 0.5
MAX_WAIT_S = 60.0
BUDGET_S = 120.0
NOTE = (
    "load_1min is os.getloadavg()[0] right before the block; it lags ~1 min and includes "
    "this benchmark's own threads. other_busy_cores: cores busy in /proc/stat over a short "
    "sample while this process was idle (other processes). Rerun policy: if load_1min > "
    "threshold, wait up to max_wait_s (within the run's wait budget) for it to drop, rerun "
    "once and report the attempt with the lower load."
)


# ------------------------------------------------------------------ load


def load_1min() -> float:
    return float(os.getloadavg()[0])


def _proc_stat() -> tuple[int, int] | None:
    """``(busy, total)`` jiffies of all CPUs from ``/proc/stat``, or None."""
    try:
        with open("/proc/stat") as f:
            vals = [int(v) for v in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = vals[3] + (vals[4] if len(vals) > 4 else 0)
    return sum(vals) - idle, sum(vals)


def other_busy_cores(sample_s: float = 0.25) -> float | None:
    """CPU cores kept busy over ``sample_s`` while this process sleeps (so: by others)."""
    a = _proc_stat()
    t0 = time.perf_counter()
    time.sleep(sample_s)
    b = _proc_stat()
    dt = time.perf_counter() - t0
    if a is None or b is None or b[1] == a[1]:
        return None
    n = os.cpu_count() or 1
    return n * (b[0] - a[0]) / (b[1] - a[1]) if dt > 0 else None


def load_snapshot() -> dict:
    """The load figures recorded right before a timed block."""
    la = os.getloadavg()
    running = None
    try:
        with open("/proc/loadavg") as f:
            running = f.read().split()[3]
    except (OSError, IndexError):
        pass
    return {
        "load_1min": float(la[0]),
        "loadavg": [float(x) for x in la],
        "running_tasks": running,
        "other_busy_cores": other_busy_cores(),
    }


# ------------------------------------------------------------------ timing


def time_stats(times_s: Sequence[float]) -> dict:
    """Summary of a list of durations.

    Args:
        times_s: ``[n]`` seconds, ``n >= 1``.

    Returns:
        ``times_s`` (the list, as floats), ``median_s``, ``mean_s``, ``min_s``, ``max_s``
        and ``best_s`` (the same as ``min_s``; the name the recorded JSON files use).

    Raises:
        ValueError: if ``times_s`` is empty.
    """
    times = [float(t) for t in times_s]
    if not times:
        raise ValueError("times_s must hold at least one duration")
    return {
        "times_s": times,
        "median_s": statistics.median(times),
        "mean_s": statistics.fmean(times),
        "min_s": min(times),
        "max_s": max(times),
        "best_s": min(times),
    }


def time_calls(
    fn: Callable[[], object],
    repeats: int,
    *,
    warmup: int = 1,
    budget_s: float | None = None,
    return_output: bool = False,
):
    """Time calls of ``fn``, each ended with ``jax.block_until_ready`` on its result.

    Args:
        fn: the call to time, without arguments. Its result may be any pytree (JAX arrays
            are waited for; other leaves are left alone).
        repeats: number of timed calls (``>= 1``).
        warmup: untimed calls first (compilation, caches); the first one's seconds are
            reported as ``first_call_s``. ``0`` when the caller has already warmed ``fn``.
        budget_s: stop the timed calls early once they have taken this many seconds in
            total (at least one call is always timed).
        return_output: also return the result of the last call.

    Returns:
        :func:`time_stats` of the timed calls, plus ``first_call_s`` when ``warmup > 0``;
        with ``return_output`` the pair ``(stats, output)``.

    Raises:
        ValueError: if ``repeats < 1`` or ``warmup < 0``.
    """
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    if warmup < 0:
        raise ValueError(f"warmup must be >= 0, got {warmup}")
    out = None
    first = None
    for i in range(warmup):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        if i == 0:
            first = time.perf_counter() - t0
    times: list[float] = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
        if budget_s is not None and sum(times) >= budget_s:
            break
    stats = time_stats(times)
    if first is not None:
        stats["first_call_s"] = first
    return (stats, out) if return_output else stats


def warm(fn: Callable[[], object]):
    """First call (compilation included): ``(output, seconds)``."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - t0


# ------------------------------------------------------------------ differences


def _rel_key(rel_tol: float) -> str:
    return "n_rel_diff_gt_" + np.format_float_scientific(rel_tol, trim="-", exp_digits=1)


def max_abs_diff(a, b, *, rel_tol: float | None = None) -> dict:
    """How far ``a`` is from the reference ``b``, over all leaves of two pytrees of arrays.

    Values are compared in float64 over the entries finite in both; entries that are
    non-finite in one or both are counted instead (NaN matches NaN, ``+inf`` matches
    ``+inf``).

    Args:
        a: an array, or a pytree of arrays (the values under test).
        b: the reference, with the tree structure and leaf shapes of ``a``.
        rel_tol: when given, also count the entries whose relative difference exceeds it.

    Returns:
        - ``n_compared``: entries finite in both;
        - ``max_abs_diff``: largest ``|a - b|`` over them (None if there are none);
        - ``max_rel_diff``: largest ``|a - b| / max(|b|, 1)`` over them (None if none);
        - ``max_abs_value``: largest ``|b|`` over them (None if none);
        - ``n_finite_mismatch``: entries finite in exactly one of ``a``, ``b``;
        - ``n_mismatch_both_nonfinite``: entries non-finite in both with different values
          (NaN against an infinity, or infinities of opposite sign);
        - with ``rel_tol``: ``rel_tol`` and ``n_rel_diff_gt_<rel_tol>`` (e.g.
          ``n_rel_diff_gt_1e-3``), the entries finite in both with a relative difference
          above ``rel_tol``.

    Raises:
        ValueError: if the tree structures or the shapes of corresponding leaves differ.
    """
    leaves_a, tree_a = jax.tree_util.tree_flatten(a)
    leaves_b, tree_b = jax.tree_util.tree_flatten(b)
    if tree_a != tree_b:
        raise ValueError(f"a and b must have the same tree structure, got {tree_a} and {tree_b}")
    xs, ys = [], []
    for i, (x, y) in enumerate(zip(leaves_a, leaves_b, strict=True)):
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        if x.shape != y.shape:
            raise ValueError(
                f"a and b must have the same shapes, got {x.shape} and {y.shape} (leaf {i})"
            )
        xs.append(x.ravel())
        ys.append(y.ravel())
    x = np.concatenate(xs) if xs else np.zeros(0)
    y = np.concatenate(ys) if ys else np.zeros(0)
    fx, fy = np.isfinite(x), np.isfinite(y)
    both = fx & fy
    d = np.abs(x[both] - y[both])
    ref = np.abs(y[both])
    rel = d / np.maximum(ref, 1.0)
    neither = ~fx & ~fy
    same_nonfinite = (x[neither] == y[neither]) | (np.isnan(x[neither]) & np.isnan(y[neither]))
    out = {
        "n_compared": int(both.sum()),
        "max_abs_diff": float(d.max()) if d.size else None,
        "max_rel_diff": float(rel.max()) if rel.size else None,
        "max_abs_value": float(ref.max()) if ref.size else None,
        "n_finite_mismatch": int((fx != fy).sum()),
        "n_mismatch_both_nonfinite": int((~same_nonfinite).sum()),
    }
    if rel_tol is not None:
        out["rel_tol"] = float(rel_tol)
        out[_rel_key(rel_tol)] = int((rel > rel_tol).sum())
    return out


# ------------------------------------------------------------------ record


def machine_info(**extra) -> dict:
    """CPU, platform, library versions, dtype and load at the time of the call.

    Args:
        **extra: further entries (e.g. ``native=native_info()``); they override the defaults
            of the same name.

    Returns:
        ``cpu_count``, ``cpu_model``, ``cpu_vector_isa`` (``lidarjax._runtime.cpu_info``),
        ``platform``, ``python``, the versions of ``jax``,
        ``numpy``, ``equinox``, ``optimistix`` and ``lidarjax``, ``jax_backend``, ``dtype``
        (JAX's default float), ``xla_flags`` (the ``XLA_FLAGS`` environment variable),
        ``load_average_start`` (``os.getloadavg()``), ``load_snapshot``
        (:func:`load_snapshot`) and ``noise_note``.
    """
    cpu = cpu_info()
    info = {
        "cpu_count": os.cpu_count(),
        "cpu_model": cpu["cpu_model"] or platform.processor() or platform.machine(),
        "cpu_vector_isa": cpu["cpu_vector_isa"],
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "numpy": np.__version__,
        "equinox": getattr(eqx, "__version__", None),
        "optimistix": getattr(optx, "__version__", None),
        "lidarjax": getattr(lidarjax, "__version__", None),
        "jax_backend": jax.default_backend(),
        "dtype": str(jnp.result_type(float)),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "load_average_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "load_snapshot": load_snapshot(),
        "noise_note": "shared 2-core machine; other processes may have been running",
    }
    info.update(extra)
    return info


def _json_default(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray | jax.Array):
        return np.asarray(x).tolist()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"{type(x).__name__} is not JSON serialisable")


def write_json(path: str | os.PathLike, report: dict) -> Path:
    """Write ``report`` to ``path`` (indented, trailing newline), creating its folder.

    NumPy scalars and arrays, JAX arrays and paths are converted; non-finite floats are
    written as ``NaN`` / ``Infinity`` like :func:`json.dumps` does.

    Returns:
        The path written.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2, default=_json_default) + "\n")
    return path


def native_info() -> dict:
    """Whether the native kernels are usable, why not, and the build record."""
    from lidarjax.raytrace import _build, _native

    info: dict = {
        "available": bool(_native.available()),
        "unavailable_reason": _native.unavailable_reason(),
        "default_threads": _native.default_threads(),
        "isa": _native.isa(),
    }
    try:
        info["build"] = json.loads(_build.INFO.read_text())
    except (OSError, ValueError):
        info["build"] = None
    return info


def ratio(a: float | None, b: float | None) -> float | None:
    """``a / b`` or None."""
    if a is None or b is None or b == 0:
        return None
    return a / b


# ------------------------------------------------------------------ load policy


@dataclass
class LoadPolicy:
    """Records the load before each timed block and reruns blocks timed on a busy machine."""

    threshold: float = THRESHOLD
    max_wait_s: float = MAX_WAIT_S
    budget_s: float = BUDGET_S
    poll_s: float = 2.0
    waited_s: float = 0.0
    blocks: int = 0
    reruns: int = 0
    above: int = 0
    log: list = field(default_factory=list)

    def remaining(self) -> float:
        return max(self.budget_s - self.waited_s, 0.0)

    def wait(self) -> dict:
        """Wait up to ``max_wait_s`` (within the budget) for the load to drop."""
        limit = min(self.max_wait_s, self.remaining())
        t0 = time.perf_counter()
        while load_1min() > self.threshold and time.perf_counter() - t0 < limit:
            time.sleep(min(self.poll_s, max(limit - (time.perf_counter() - t0), 0.0)))
        waited = time.perf_counter() - t0
        self.waited_s += waited
        return {"waited_s": waited, "load_1min_after_wait": load_1min()}

    def measure(self, label: str, block: Callable[[], dict]) -> dict:
        """Run ``block`` under the policy; its result plus a ``load`` record."""
        self.blocks += 1
        attempts = []
        snap = load_snapshot()
        res = block()
        attempts.append({**snap, "above_threshold": snap["load_1min"] > self.threshold})
        results = [res]
        skipped = None
        if snap["load_1min"] > self.threshold:
            self.above += 1
            if self.remaining() > 0:
                w = self.wait()
                snap2 = load_snapshot()
                res2 = block()
                self.reruns += 1
                attempts.append(
                    {**snap2, "above_threshold": snap2["load_1min"] > self.threshold, **w}
                )
                results.append(res2)
            else:
                skipped = "wait budget exhausted"
        for a, r in zip(attempts, results, strict=True):
            a["median_s"] = r.get("median_s")
            a["best_s"] = r.get("best_s")
        pick = min(range(len(attempts)), key=lambda i: (attempts[i]["load_1min"], -i))
        out = dict(results[pick])
        out["load"] = {
            "load_1min": attempts[pick]["load_1min"],
            "above_threshold": attempts[pick]["above_threshold"],
            "first_attempt_above_threshold": attempts[0]["above_threshold"],
            "rerun": len(attempts) > 1,
            "rerun_skipped": skipped,
            "selected_attempt": pick,
            "attempts": attempts,
        }
        self.log.append(
            {"block": label, "load_1min": attempts[pick]["load_1min"], "rerun": len(attempts) > 1}
        )
        tag = f"load {attempts[0]['load_1min']:.2f}"
        if len(attempts) > 1:
            tag += f" -> rerun at {attempts[1]['load_1min']:.2f}"
        med = out.get("median_s")
        print(
            f"  [{label}] {'' if med is None else f'median {med * 1e3:.2f} ms, '}{tag}",
            flush=True,
        )
        return out

    def time_calls(
        self,
        label: str,
        fn: Callable[[], object],
        repeats: int,
        *,
        warmup: int = 1,
        return_output: bool = False,
    ):
        """:func:`time_calls` under the policy: the ``warmup`` calls run once, before and
        outside :meth:`measure` (the first one's seconds are ``first_call_s``); the
        ``repeats`` timed calls are the block that may be rerun.

        Returns:
            The timing record with its ``load``; with ``return_output`` the pair
            ``(record, output of the last call)``.
        """
        if warmup < 0:
            raise ValueError(f"warmup must be >= 0, got {warmup}")
        first = None
        holder: dict = {}
        for i in range(warmup):
            holder["out"], dt = warm(fn)
            if i == 0:
                first = dt

        def block():
            stats, holder["out"] = time_calls(fn, repeats, warmup=0, return_output=True)
            return stats

        timed = self.measure(label, block)
        if first is not None:
            timed["first_call_s"] = first
        return (timed, holder["out"]) if return_output else timed

    def summary(self) -> dict:
        return {
            "threshold_load_1min": self.threshold,
            "max_wait_s": self.max_wait_s,
            "wait_budget_s": self.budget_s,
            "waited_s_total": self.waited_s,
            "blocks": self.blocks,
            "blocks_first_attempt_above_threshold": self.above,
            "reruns": self.reruns,
            "note": NOTE,
            "per_block": self.log,
        }


def add_policy_args(parser) -> None:
    """``--max-wait`` / ``--wait-budget`` / ``--load-threshold`` options."""
    parser.add_argument(
        "--max-wait", type=float, default=MAX_WAIT_S, help="max wait per busy block (s)"
    )
    parser.add_argument(
        "--wait-budget",
        type=float,
        default=BUDGET_S,
        help="total waiting for the load to drop per run (s); 0 disables reruns",
    )
    parser.add_argument("--load-threshold", type=float, default=THRESHOLD)


def policy_from_args(args) -> LoadPolicy:
    return LoadPolicy(
        threshold=args.load_threshold, max_wait_s=args.max_wait, budget_s=args.wait_budget
    )


# ------------------------------------------------------------------ experiments


def experiments_on_path() -> Path:
    """Put ``experiments/`` first on ``sys.path`` (moving it there if already present) and
    return it.

    For the benchmarks that time an experiment's own code, so that they measure exactly what
    the experiment's tables report: ``global_init.py`` and ``mcl_remedies.py``
    (``experiments/mcl.py``, ``mcl_remedies.py``, ``_common.py``) and ``fields.py``
    (``experiments/custom_field.py``). ``experiments/`` holds modules with the names of
    benchmarks (``mcl_remedies``, ``poles``, ...), so it must come before ``benchmarks/``
    for the plain imports that follow the call.
    """
    path = str(EXPERIMENTS)
    while path in sys.path:
        sys.path.remove(path)
    sys.path.insert(0, path)
    return EXPERIMENTS


def remedies_config(root: Path = ROOT):
    """``configs/mcl_remedies.yaml`` merged over ``configs/mcl.yaml`` under ``root`` (the
    experiments' config without a Hydra run), for the localization benchmarks."""
    from omegaconf import OmegaConf

    root = Path(root)
    cfg = OmegaConf.load(root / "configs" / "mcl_remedies.yaml")
    base = OmegaConf.load(root / "configs" / "mcl.yaml")
    return OmegaConf.merge(base, {k: v for k, v in cfg.items() if k not in ("defaults", "hydra")})
