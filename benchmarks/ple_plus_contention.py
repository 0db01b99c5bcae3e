"""PLE+ under CPU contention: one scan per call, unpinned vs pinned to one core, on an
idle machine and with two busy-loop processes (issue #20), for both backends.

Every condition runs in a fresh subprocess (pinning must precede JAX's start-up): 8
Intel scans (180 rays) at J = 50, PLE+ with its defaults after one warm-up call per scan,
timed with ``block_until_ready``, once with ``backend="jax"`` (the optimistix search, whose
loop iterations XLA hands between pool threads) and once with ``backend="native"`` (the
C++ kernel, serial on the calling thread; the default where the library is built).
"loaded" starts two ``while True: pass`` processes for the duration of the subprocess
(always stopped). The 1-minute load average is recorded before each condition. Each row
holds both backends' times and ``speedup_native`` = median JAX time / median native time.
Writes ``benchmarks/results/ple_plus_contention.json``.

Usage: ``python benchmarks/ple_plus_contention.py [--scans N] [--thorough]``
(``--thorough``: the experiment's search, ``rounds=10, restarts=4``; written to
``ple_plus_contention_thorough.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

from _harness import RESULTS, machine_info, write_json

OUT = RESULTS / "ple_plus_contention.json"

WORKER = r"""
import json, sys, time
pin = sys.argv[1] == "pinned"
n = int(sys.argv[2])
kw = json.loads(sys.argv[3])
import lidarjax
if pin:
    lidarjax.pin_to_one_core()
import jax
jax.config.update("jax_enable_x64", True)
import jaxlie, numpy as np
from lidarjax import features as F
from lidarjax.datasets import fetch, load_carmen
from lidarjax.rays import from_scan
log = load_carmen(fetch("intel"))
rmax = log.usable_range_m
times = {"jax": [], "native": []}
for s in range(0, 40 * n, 40):
    r = np.minimum(log.ranges_m[s], rmax)
    rays = from_scan(jaxlie.SE2.identity(), log.azimuths_rad, r, 0.0, rmax)
    ple = F.extract_polylines(rays, max_vertices=50, l_max_m=1.0, d_rm_m=0.5, closed=False)
    for backend in times:
        run = lambda: F.optimize_polylines(ple, rays, backend=backend, **kw).map.vertices
        jax.block_until_ready(run())  # warm-up
        t = time.perf_counter()
        jax.block_until_ready(run())
        times[backend].append(time.perf_counter() - t)
print(json.dumps(times))
"""


def _stats(times: list[float]) -> dict:
    s = sorted(times)
    return {"times_s": times, "median_s": s[len(s) // 2], "max_s": s[-1]}


def run(pin: str, loaded: bool, n: int, kw: dict) -> dict:
    load_before = os.getloadavg()[0]
    burners = []
    try:
        if loaded:
            burners = [
                subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)
            ]
            time.sleep(1.0)
        out = subprocess.run(
            [sys.executable, "-c", WORKER, pin, str(n), json.dumps(kw)], capture_output=True,
            text=True,
            timeout=3600,
        )  # fmt: skip
    finally:
        for b in burners:
            b.kill()
            b.wait()
    if out.returncode != 0:
        raise RuntimeError(out.stderr[-2000:])
    times = json.loads(out.stdout.strip().splitlines()[-1])
    jx, nat = _stats(times["jax"]), _stats(times["native"])
    return {
        "pin": pin,
        "loaded": loaded,
        "load_1min_before": load_before,
        "jax": jx,
        "native": nat,
        "speedup_native": jx["median_s"] / nat["median_s"],
    }


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=8)
    ap.add_argument(
        "--thorough", action="store_true",
        help="the experiment's search (rounds=10, restarts=4) instead of the defaults",
    )  # fmt: skip
    args = ap.parse_args(argv)
    kw = {"rounds": 10, "restarts": 4} if args.thorough else {}
    rows = []
    for loaded in (False, True):
        for pin in ("unpinned", "pinned"):
            rows.append(run(pin, loaded, args.scans, kw))
            r = rows[-1]
            print(f"{'loaded' if loaded else 'idle':6s} {pin:8s} load {r['load_1min_before']:.2f}: "
                  f"jax median {r['jax']['median_s']:.3f} s, max {r['jax']['max_s']:.3f} s; "
                  f"native median {r['native']['median_s']:.4f} s, "
                  f"max {r['native']['max_s']:.4f} s; speedup {r['speedup_native']:.0f}x",
                  flush=True)  # fmt: skip
    out = OUT.with_name(OUT.stem + ("_thorough" if args.thorough else "") + ".json")
    res = {
        "cpu_count": os.cpu_count(),
        "optimize_polylines_kwargs": kw,
        "rows": rows,
        # after the timed subprocesses, so that this process starts no JAX client before them
        "machine": machine_info(),
    }
    write_json(out, res)


if __name__ == "__main__":
    main()
