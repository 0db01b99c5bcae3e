"""The benchmarks' shared module ``benchmarks/_harness.py`` (timer, difference helper, machine
record, JSON output, load policy), and that every ``benchmarks/[a-z]*.py`` script imports.

The scripts run as ``python benchmarks/<name>.py``: their folder is first on ``sys.path`` and
they import ``_harness`` by its plain name. The tests do the same inside :func:`_bench_imports`,
which restores ``sys.path``, ``os.environ`` and ``sys.modules`` (the modules of
``benchmarks/`` and ``experiments/`` imported meanwhile) afterwards, so that other tests see
the interpreter as it was (``experiments/`` has modules with the names of benchmarks).
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import json
import math
import os
import sys
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
EXPERIMENTS = ROOT / "experiments"
SCRIPTS = sorted(BENCH.glob("[a-z]*.py"))
SLEEP_S = 0.01


@contextlib.contextmanager
def _bench_imports():
    path, env, before = list(sys.path), dict(os.environ), set(sys.modules)
    sys.path.insert(0, str(BENCH))
    try:
        yield
    finally:
        sys.path[:] = path
        os.environ.clear()
        os.environ.update(env)
        for name in set(sys.modules) - before:
            file = str(getattr(sys.modules[name], "__file__", None) or "")
            if file.startswith((str(BENCH), str(EXPERIMENTS))):
                del sys.modules[name]


@pytest.fixture(scope="module")
def h():
    """``benchmarks/_harness.py`` imported as a script would import it."""
    with _bench_imports():
        yield importlib.import_module("_harness")


# ---------------------------------------------------------------------------------- timing


def test_time_calls_sleep(h):
    calls = []

    def fn():
        calls.append(1)
        time.sleep(SLEEP_S)
        return jnp.arange(3.0)

    t, out = h.time_calls(fn, 3, return_output=True)
    assert len(calls) == 4  # one warm-up call, three timed
    assert len(t["times_s"]) == 3
    assert all(x >= SLEEP_S for x in t["times_s"])
    assert t["first_call_s"] >= SLEEP_S
    assert t["min_s"] >= SLEEP_S
    assert t["min_s"] == t["best_s"] == min(t["times_s"])
    assert t["max_s"] == max(t["times_s"])
    assert t["min_s"] <= t["median_s"] <= t["max_s"]
    assert t["min_s"] <= t["mean_s"] <= t["max_s"]
    np.testing.assert_array_equal(np.asarray(out), [0.0, 1.0, 2.0])
    json.dumps(t)  # a timing record is plain JSON


def test_time_calls_without_warmup_and_budget(h):
    calls = []

    def fn():
        calls.append(1)

    t = h.time_calls(fn, 2, warmup=0)
    assert len(calls) == 2 and len(t["times_s"]) == 2 and "first_call_s" not in t
    calls.clear()
    t = h.time_calls(fn, 5, warmup=2, budget_s=0.0)  # the budget stops after one timed call
    assert len(calls) == 3 and len(t["times_s"]) == 1
    calls.clear()
    t = h.time_calls(fn, 4, warmup=0, budget_s=1e9)
    assert len(calls) == 4
    with pytest.raises(ValueError, match="repeats"):
        h.time_calls(fn, 0)
    with pytest.raises(ValueError, match="warmup"):
        h.time_calls(fn, 1, warmup=-1)


def test_time_stats(h):
    s = h.time_stats([3.0, 1.0, 2.0, 6.0])
    assert s == {
        "times_s": [3.0, 1.0, 2.0, 6.0],
        "median_s": 2.5,
        "mean_s": 3.0,
        "min_s": 1.0,
        "max_s": 6.0,
        "best_s": 1.0,
    }
    with pytest.raises(ValueError, match="times_s"):
        h.time_stats([])


def test_load_policy_time_calls(h):
    calls = []

    def fn():
        calls.append(1)
        time.sleep(SLEEP_S)
        return np.float64(len(calls))

    quiet = h.LoadPolicy(threshold=math.inf)  # never above: no rerun
    t, out = quiet.time_calls("block", fn, 2, return_output=True)
    assert len(calls) == 3 and out == 3.0
    assert t["first_call_s"] >= SLEEP_S and t["median_s"] >= SLEEP_S
    assert t["load"]["rerun"] is False and set(t["load"]["attempts"][0]) >= {
        "load_1min",
        "loadavg",
        "other_busy_cores",
    }
    busy = h.LoadPolicy(threshold=-1.0, budget_s=0.0)  # always above, no budget to wait
    calls.clear()
    t = busy.time_calls("busy", fn, 2, warmup=0)
    assert len(calls) == 2
    assert t["load"]["rerun"] is False and t["load"]["rerun_skipped"] == "wait budget exhausted"
    assert busy.summary()["blocks_first_attempt_above_threshold"] == 1


# ----------------------------------------------------------------------------- differences


def test_max_abs_diff_hand_computed(h):
    nan, inf = math.nan, math.inf
    a = np.array([1.0, 2.0, nan, inf, 5.0, nan, -inf, 7.0])
    b = np.array([1.5, -2.0, nan, inf, inf, 1.0, inf, 0.5])
    # finite in both: entries 0, 1, 7 with |a - b| = 0.5, 4, 6.5 and
    # |a - b| / max(|b|, 1) = 0.5 / 1.5, 4 / 2, 6.5 / 1
    d = h.max_abs_diff(a, b, rel_tol=0.5)
    assert d == {
        "n_compared": 3,
        "max_abs_diff": 6.5,
        "max_rel_diff": 6.5,
        "max_abs_value": 2.0,
        "n_finite_mismatch": 2,  # 5 vs inf, nan vs 1
        "n_mismatch_both_nonfinite": 1,  # -inf vs inf (nan vs nan and inf vs inf agree)
        "rel_tol": 0.5,
        "n_rel_diff_gt_5e-1": 2,  # 2 and 6.5
    }
    assert h.max_abs_diff(a, b, rel_tol=1e-3)["n_rel_diff_gt_1e-3"] == 3
    # the second argument is the reference: relative to |a| = 1, 2, 7 the largest is 4 / 2
    assert h.max_abs_diff(b, a)["max_rel_diff"] == 2.0


def test_max_abs_diff_pytrees_and_edge_cases(h):
    a = {"x": jnp.array([[1.0, 2.0]]), "y": (np.array([3], np.int32), np.float32(-1.0))}
    b = {"x": np.array([[1.25, 2.0]]), "y": (np.array([0]), np.float64(-1.0))}
    d = h.max_abs_diff(a, b)
    assert d["n_compared"] == 4 and d["max_abs_diff"] == 3.0 and d["max_rel_diff"] == 3.0
    assert d["max_abs_value"] == 2.0 and d["n_finite_mismatch"] == 0

    none = h.max_abs_diff([math.nan], [math.nan])
    assert none["n_compared"] == 0 and none["max_abs_diff"] is None
    assert none["max_rel_diff"] is None and none["max_abs_value"] is None
    assert none["n_finite_mismatch"] == 0 and none["n_mismatch_both_nonfinite"] == 0

    same = np.linspace(-3.0, 3.0, 7)
    assert h.max_abs_diff(same, same)["max_abs_diff"] == 0.0

    with pytest.raises(ValueError, match="shape"):
        h.max_abs_diff(np.zeros(6), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="shape"):
        h.max_abs_diff(np.zeros(3), np.zeros(4))
    with pytest.raises(ValueError, match="tree structure"):
        h.max_abs_diff({"x": np.zeros(2)}, {"z": np.zeros(2)})
    with pytest.raises(ValueError, match="tree structure"):
        h.max_abs_diff((np.zeros(2),), (np.zeros(2), np.zeros(2)))


# ---------------------------------------------------------------------- record and output


def test_machine_info(h):
    m = h.machine_info(dtype="overridden", native={"available": False})
    assert set(m) >= {
        "cpu_count",
        "cpu_model",
        "cpu_vector_isa",
        "platform",
        "python",
        "jax",
        "numpy",
        "equinox",
        "optimistix",
        "lidarjax",
        "jax_backend",
        "xla_flags",
        "load_average_start",
        "load_snapshot",
        "noise_note",
    }
    assert m["dtype"] == "overridden" and m["native"] == {"available": False}
    assert set(m["load_snapshot"]) == {"load_1min", "loadavg", "running_tasks", "other_busy_cores"}
    assert len(m["load_average_start"]) == 3
    assert h.machine_info()["dtype"] in ("float32", "float64")
    json.dumps(m)


def test_write_json(h, tmp_path):
    report = {
        "a": np.float32(1.5),
        "b": np.arange(3),
        "c": jnp.array([0.5, 2.0]),
        "d": {"e": [np.int64(7), None, True]},
        "p": tmp_path,
        "inf": math.inf,
    }
    path = h.write_json(tmp_path / "sub" / "r.json", report)
    assert path == tmp_path / "sub" / "r.json"
    text = path.read_text()
    assert text.endswith("}\n")
    assert json.loads(text) == {
        "a": 1.5,
        "b": [0, 1, 2],
        "c": [0.5, 2.0],
        "d": {"e": [7, None, True]},
        "p": str(tmp_path),
        "inf": math.inf,
    }
    with pytest.raises(TypeError, match="object"):
        h.write_json(tmp_path / "bad.json", {"x": object()})


def test_experiments_on_path(h):
    with _bench_imports():
        sys.path.append(str(EXPERIMENTS))  # present, but behind benchmarks/
        assert h.experiments_on_path() == EXPERIMENTS
        assert sys.path[0] == str(EXPERIMENTS)
        assert sys.path.count(str(EXPERIMENTS)) == 1


def test_ratio(h):
    assert h.ratio(3.0, 2.0) == 1.5
    assert h.ratio(None, 2.0) is None and h.ratio(1.0, 0.0) is None


# ------------------------------------------------------------------------ the benchmarks


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.stem)
def test_benchmark_imports(script):
    """Each benchmark script imports (as a module, so ``main`` does not run)."""
    name = f"benchmark_{script.stem}"
    with _bench_imports():
        spec = importlib.util.spec_from_file_location(name, script)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod  # dataclasses look their module up
        try:
            spec.loader.exec_module(mod)
        finally:
            del sys.modules[name]
        assert callable(mod.main)
        assert not hasattr(mod, "_machine"), "machine_info comes from _harness"
