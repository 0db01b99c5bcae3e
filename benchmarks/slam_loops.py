"""Loop search of decay-rate SLAM (issue #24): seconds of :func:`lidarjax.slam.find_loops`
with the local search only, with the wide search's second chance (the default), the
default without its submap cache (``LoopConfig(submap_cache=0)``), and the default with
each submap built one scan at a time (``GridMap.add_scan`` per scan, as before stop 69,
in place of the batched ``GridMap.add_scans``), timed in the same run on the same
front-end trajectory.

On the first ``--scans`` scans of each log with the experiment's drifting odometry
(``configs/slam.yaml``), the decay-rate front end (:func:`lidarjax.slam.run_front_end`)
gives the trajectory; :func:`~lidarjax.slam.find_loops` then runs with
``LoopConfig(wide_search_xy_m=0)``, ``LoopConfig()`` and ``LoopConfig(submap_cache=0)``,
each timed on its second call (the first compiles). Reported per log: seconds, candidates
tried, loops accepted, the ratio of the wide search's time to the local one's, the ratio
of the default's time to the uncached one's, and whether the two found the same loops
(edges and relative poses equal bit for bit); for the per-scan submaps, the loops both
found and the largest difference of their relative poses (the two traces differ by
round-off). The 1-minute load average is recorded before every timing.
Writes ``benchmarks/results/slam_loops.json``.

Usage: ``python benchmarks/slam_loops.py [--logs intel fhw orebro] [--scans 300]``.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
from _harness import RESULTS, machine_info, write_json
from slam import log_inputs  # benchmarks/slam.py

from lidarjax import slam
from lidarjax.slam._front_end import GridMap

OUT = RESULTS / "slam_loops.json"


def _per_scan(grid, poses, azimuths, ranges, *, sign=1.0):
    """The reference for ``GridMap.add_scans``: one ``add_scan`` per scan."""
    for p, r in zip(poses, ranges):
        grid.add_scan(p, azimuths, r, sign=sign)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--logs", nargs="+", default=["intel", "fhw", "orebro"])
    ap.add_argument("--scans", type=int, default=300)
    args = ap.parse_args()
    report = {"machine": machine_info(), "scans": args.scans, "logs": {}}
    configs = {
        "local_only": slam.LoopConfig(wide_search_xy_m=0.0),
        "with_wide_search": slam.LoopConfig(),
        "without_submap_cache": slam.LoopConfig(submap_cache=0),
        "per_scan_submaps": slam.LoopConfig(),
    }
    batched = GridMap.add_scans
    for name in args.logs:
        _, n, ranges, az, odo = log_inputs(name, args.scans)
        poses = slam.run_front_end(ranges, az, odo).poses
        path = float(np.hypot(*np.diff(poses[:, :2], axis=0).T).sum())
        row: dict = {"n_scans": n, "path_m": path}
        found = {}
        for key, cfg in configs.items():
            GridMap.add_scans = _per_scan if key == "per_scan_submaps" else batched
            # the first call compiles (the local match, the wide search); the second is
            # timed
            slam.find_loops(ranges, az, poses, cfg)
            load = os.getloadavg()[0]
            t = time.perf_counter()
            loops = found[key] = slam.find_loops(ranges, az, poses, cfg)
            row[key] = {
                "load_1min_before": load,
                "seconds": time.perf_counter() - t,
                "candidates": int(loops.n_tried),
                "loops": int(len(loops.edges)),
            }
        row["ratio_wide_over_local"] = (
            row["with_wide_search"]["seconds"] / row["local_only"]["seconds"]
        )
        row["ratio_cached_over_uncached"] = (
            row["with_wide_search"]["seconds"] / row["without_submap_cache"]["seconds"]
        )
        a, b = found["with_wide_search"], found["without_submap_cache"]
        row["cache_same_loops"] = bool(
            np.array_equal(a.edges, b.edges) and np.array_equal(a.measurements, b.measurements)
        )
        GridMap.add_scans = batched
        row["ratio_batched_over_per_scan"] = (
            row["with_wide_search"]["seconds"] / row["per_scan_submaps"]["seconds"]
        )
        c = found["per_scan_submaps"]
        ea = {tuple(e): m for e, m in zip(np.asarray(a.edges).tolist(), a.measurements)}
        ec = {tuple(e): m for e, m in zip(np.asarray(c.edges).tolist(), c.measurements)}
        both = sorted(set(ea) & set(ec))
        d = np.array([ea[k] - ec[k] for k in both]).reshape(-1, 3)
        row["per_scan_loops"] = {
            "both": len(both),
            "only_batched": len(set(ea) - set(ec)),
            "only_per_scan": len(set(ec) - set(ea)),
            "max_xy_difference_m": float(np.hypot(d[:, 0], d[:, 1]).max()) if both else None,
            "median_xy_difference_m": float(np.median(np.hypot(d[:, 0], d[:, 1])))
            if both
            else None,
            "max_yaw_difference_rad": float(np.abs(d[:, 2]).max()) if both else None,
        }
        report["logs"][name] = row
        print(name, row, flush=True)
    write_json(OUT, report)
    print("wrote", OUT)


if __name__ == "__main__":
    main()
