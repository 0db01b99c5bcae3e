"""What a fresh process pays for the SLAM front end's scan matcher
(:func:`lidarjax.slam.match_scan`): its compilation, its warm run time, and the compilations
a sweep of gate settings costs.

Each measurement runs in a fresh Python process without the persistent compilation cache
(JAX compiles everything), on the simulated office of the test suite (181 beams, the map of
six scans at their true poses, 0.05 m cells, the default :class:`~lidarjax.slam.
FrontEndConfig`):

- ``first_match_s``: the first ``match_scan`` (tracing, lowering, XLA compilation, run);
  ``compile_s``: the XLA compilation seconds JAX reports for it (``jax.monitoring``);
- ``warm_match_s``: median of 10 further matches (other scans and starts);
- ``sweep``: matches under four other gate settings (``gate_sigmas``,
  ``ambiguous_gate_sigmas``, ``ambiguous_margin``, ``gate_stiffness``), as a Hydra sweep or a
  test would run them: wall seconds and the number of XLA compilations;
- ``front_end_s``: :func:`lidarjax.slam.run_front_end` of the first 40 office scans after
  all that (its matches are warm).

``--tree PATH`` (repeatable) measures other source trees of lidarjax as well (for example
a worktree of an earlier commit, ``git worktree add /tmp/old <commit>``; each runs with
``PYTHONPATH=PATH``), alternating with this checkout ``--repeats`` times; the load average
is recorded before every process. Writes ``benchmarks/results/slam_match_compile.json``.

Usage: ``python benchmarks/slam_match_compile.py [--tree PATH ...] [--repeats 2]``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from _harness import RESULTS, ROOT, load_snapshot, machine_info, time_stats, write_json

OUT = RESULTS / "slam_match_compile.json"

CHILD = r"""
import json, statistics, time
import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
events = []
jax.monitoring.register_event_duration_secs_listener(
    lambda name, secs, **kw: events.append((name, secs))
)
COMPILE = "/jax/core/compile/backend_compile_duration"

from lidarjax.sim import make_office, simulate_scans, wheel_odometry
from lidarjax.slam import FrontEndConfig, grid_map, match_scan, run_front_end

az = np.linspace(-np.pi / 2, np.pi / 2, 181)
world = make_office(0)
truth = world.trajectory(100, jitter_m=0.2)[:40]
ranges = simulate_scans(world, truth, az, max_range_m=30.0, noise_sigma_m=0.01, seed=0)
cfg = FrontEndConfig()
grid = grid_map(cfg)
for q in range(0, 12, 2):
    grid.add_scan(truth[q], az, ranges[q])

def compiles(since):
    sel = [s for n, s in events[since:] if n == COMPILE]
    return len(sel), float(sum(sel))

out = {}
n0 = len(events)
t = time.perf_counter()
m = match_scan(grid, az, ranges[13], truth[13] + np.array([0.1, 0.0, 0.02]), cfg)
out["first_match_s"] = time.perf_counter() - t
out["compilations"], out["compile_s"] = compiles(n0)
warm = []
for k in (11, 13, 15, 17, 19):
    for off in ((0.1, 0.0, 0.02), (0.0, -0.15, -0.04)):
        t = time.perf_counter()
        match_scan(grid, az, ranges[k], truth[k] + np.array(off), cfg)
        warm.append(time.perf_counter() - t)
out["warm_match_s"] = statistics.median(warm)
prior = truth[15] + np.array([0.6, 0.0, 0.0])
sig = np.array([0.05, 0.05, 0.02])
n0 = len(events)
t = time.perf_counter()
for kw in (dict(gate_sigmas=1e3), dict(gate_sigmas=5.0), dict(gate_sigmas=3.0, gate_stiffness=2.0),
           dict(ambiguous_margin=0.0, ambiguous_gate_sigmas=2.0)):
    match_scan(grid, az, ranges[15], truth[15], FrontEndConfig(**kw), prior_xy_yaw=prior,
               prior_sigmas=sig)
out["sweep"] = {"configs": 4, "seconds": time.perf_counter() - t}
out["sweep"]["compilations"], out["sweep"]["compile_s"] = compiles(n0)
odo = wheel_odometry(truth, seed=0, sigma_trans_rel=0.05, sigma_rot_per_m=0.0175,
                     heading_bias_per_m=0.0052, sigma_rot_per_rad=0.02)
t = time.perf_counter()
r = run_front_end(ranges, az, odo, cfg)
out["front_end_s"] = time.perf_counter() - t
out["front_end_scans"] = len(ranges)
out["first_pose"] = m.pose.tolist()
print("RESULT " + json.dumps(out))
"""


def run_child(tree: Path | None) -> dict:
    """One fresh process on ``tree`` (None: this checkout), no persistent cache."""
    env = dict(os.environ, LIDARJAX_JAX_CACHE="off")
    if tree is not None:
        env["PYTHONPATH"] = str(tree)
    snap = load_snapshot()
    # run in the tree's folder: ``python -c`` puts the working folder first on sys.path
    proc = subprocess.run(
        [sys.executable, "-c", CHILD + "\nimport lidarjax; print('FROM ' + lidarjax.__file__)"],
        env=env,
        cwd=tree or ROOT,
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"the child on {tree or ROOT} failed:\n{proc.stderr[-2000:]}")
    lines = proc.stdout.splitlines()
    line = [x for x in lines if x.startswith("RESULT ")][-1]
    source = [x for x in lines if x.startswith("FROM ")][-1][len("FROM ") :]
    if not Path(source).is_relative_to(tree or ROOT):
        raise RuntimeError(f"the child on {tree or ROOT} imported lidarjax from {source}")
    return {"load_before": snap, "lidarjax": source, **json.loads(line[len("RESULT ") :])}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tree", type=Path, action="append", default=[])
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--out", type=Path, default=OUT)
    args = p.parse_args(argv)
    trees = {"this checkout": None, **{str(t): t.resolve() for t in args.tree}}
    runs = {name: [] for name in trees}
    for _ in range(args.repeats):
        for name, tree in trees.items():
            runs[name].append(run_child(tree))
            r = runs[name][-1]
            print(
                f"{name}: first match {r['first_match_s']:.1f} s (compile {r['compile_s']:.1f}"
                f" s), warm {r['warm_match_s']:.3f} s, sweep {r['sweep']['seconds']:.1f} s"
                f" ({r['sweep']['compilations']} compilations), front end"
                f" {r['front_end_s']:.1f} s; load {r['load_before']['load_1min']:.2f}",
                flush=True,
            )
    summary = {}
    for name, rs in runs.items():
        summary[name] = {
            key: time_stats([r[key] for r in rs])
            for key in ("first_match_s", "compile_s", "warm_match_s", "front_end_s")
        }
        summary[name]["sweep_s"] = time_stats([r["sweep"]["seconds"] for r in rs])
        summary[name]["sweep_compilations"] = [r["sweep"]["compilations"] for r in rs]
    report = {"machine": machine_info(), "trees": list(trees), "runs": runs, "summary": summary}
    print(f"wrote {write_json(args.out, report)}")


if __name__ == "__main__":
    main()
