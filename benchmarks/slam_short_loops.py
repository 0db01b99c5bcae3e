"""What the short loop search (issue #24, stop 65: ``SlamConfig.short_loop_separation``,
off by default) costs against the loop rounds' search it follows.

On the first ``--scans`` scans of each log (``log_inputs`` of ``benchmarks/slam.py``),
:func:`lidarjax.slam.find_loops` along the corrected poses (standing in for the pose
graph's) with the experiment's loop settings (``configs/slam.yaml``: 4 m radius, 30 scans
apart, every second scan, the 6 m wide search) and with ``SlamConfig
(short_loop_separation=7).short_loop_config`` (every scan, 7 apart, 7-scan submaps, no
wide search), one after the other in the same run, each once (a search takes tens of
seconds; the first match's compilation is done beforehand on a few scans). Along the
corrected poses the loop rounds' search needs fewer wide searches than along a drifted
front end, so the ratio is an upper bound for a first round.

The 1-minute load average (and the cores busy with other work) is recorded before each
search. Writes ``benchmarks/results/slam_short_loops.json``.

Usage: ``python benchmarks/slam_short_loops.py [--logs orebro fhw intel] [--scans 300]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _harness import RESULTS, load_snapshot, machine_info, write_json
from slam import log_inputs

from lidarjax import slam

OUT = RESULTS / "slam_short_loops.json"
LOOPS = slam.LoopConfig(radius_m=4.0, min_separation=30, every=2, wide_search_xy_m=6.0)


def _timed(ranges, az, poses, lcfg, front) -> dict:
    load = load_snapshot()
    t = time.perf_counter()
    found = slam.find_loops(ranges, az, poses, lcfg, front)
    s = time.perf_counter() - t
    return {
        **load,
        "seconds": s,
        "n_tried": int(found.n_tried),
        "n_accepted": int(len(found.edges)),
        "seconds_per_tried": s / max(found.n_tried, 1),
    }


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--logs", nargs="+", default=["orebro", "fhw", "intel"])
    p.add_argument("--scans", type=int, default=300)
    args = p.parse_args(argv)
    short = slam.SlamConfig(loops=LOOPS, short_loop_separation=7).short_loop_config
    report = {"machine": machine_info(), "scans": args.scans, "logs": {}}
    for name in args.logs:
        log, n, ranges, az, _ = log_inputs(name, args.scans)
        front = slam.FrontEndConfig().with_range_cap(
            slam.auto_range_cap(ranges, log.usable_range_m)
        )
        poses = np.asarray(log.poses[:n], float)
        slam.find_loops(ranges[:12], az, poses[:12], short, front)  # compile the matches
        row = {
            "n_scans": n,
            "range_cap_m": front.range_cap_m,
            "loop_rounds_search": _timed(ranges, az, poses, LOOPS, front),
            "short_search": _timed(ranges, az, poses, short, front),
        }
        a, b = row["loop_rounds_search"], row["short_search"]
        row["ratio_short_over_loops"] = b["seconds"] / a["seconds"]
        report["logs"][name] = row
        print(
            f"{name} ({n} scans): loop search {a['seconds']:.1f} s ({a['n_tried']} tried, "
            f"{a['n_accepted']} accepted, load {a['load_1min']:.2f}), short search "
            f"{b['seconds']:.1f} s ({b['n_tried']} tried, {b['n_accepted']} accepted, load "
            f"{b['load_1min']:.2f}): x{row['ratio_short_over_loops']:.2f}",
            flush=True,
        )
    write_json(OUT, report)
    print("wrote", OUT)


if __name__ == "__main__":
    main()
