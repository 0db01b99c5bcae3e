"""The point-to-line ICP chain (issue #24, stop 68: :func:`lidarjax.slam.point_icp_front_end`,
``SlamConfig.extra_chain_models`` ``"icp"``) against small_gicp's chain
(:func:`lidarjax.slam.icp_front_end`, ``"gicp"``), timed one after the other in the same
run on the same inputs: every scan of each log with the experiment's drifting odometry
(``log_inputs`` of ``benchmarks/slam.py``, drift seed 0), the readings below the log's
range cap (:func:`lidarjax.slam.auto_range_cap`), as ``run_slam`` runs them.

Per chain: scans per second (the ICP chain's first call, compilation included, and its
best of 3 warm calls; small_gicp's one call: nothing compiles), the share of scans
registered, and its increments against the log's corrected poses: the median
translation (m) and rotation (rad) error and the number of gross errors (more than 0.3 m
or 0.05 rad), over all increments (a rejected registration's is the odometry's).

The 1-minute load average and the other processes' busy cores are recorded before every
timing. Writes ``benchmarks/results/slam_icp_chain.json``.

Usage: ``python benchmarks/slam_icp_chain.py [--logs intel fhw orebro edmonton]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _harness import RESULTS, load_snapshot, machine_info, write_json
from slam import _scan_rate, log_inputs

from lidarjax import slam
from lidarjax.slam._front_end import between_np

OUT = RESULTS / "slam_icp_chain.json"
GROSS_M, GROSS_RAD = 0.3, 0.05


def increment_errors(chain: np.ndarray, truth: np.ndarray) -> dict:
    """The chain's increments against the truth's."""
    d = between_np(chain[:-1], chain[1:]) - between_np(truth[:-1], truth[1:])
    rot = np.abs(np.arctan2(np.sin(d[:, 2]), np.cos(d[:, 2])))
    trans = np.hypot(d[:, 0], d[:, 1])
    return {
        "median_m": float(np.median(trans)),
        "median_rad": float(np.median(rot)),
        "gross": int(np.sum((trans > GROSS_M) | (rot > GROSS_RAD))),
    }


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--logs", nargs="+", default=["intel", "fhw", "orebro", "edmonton"])
    args = p.parse_args(argv)
    try:
        import small_gicp  # noqa: F401

        have_gicp = True
    except ImportError:
        have_gicp = False
    report = {"machine": machine_info(), "logs": {}}
    for name in args.logs:
        log, n, ranges, az, odo = log_inputs(name, 10**9)
        cap = slam.auto_range_cap(ranges, log.usable_range_m)
        r = np.minimum(ranges, cap)
        truth = np.asarray(log.poses[:n], float)
        rate = _scan_rate(log.timestamps_s[:n])
        row: dict = {"n_scans": n, "range_cap_m": cap, "scan_rate_hz": rate}
        snap = load_snapshot()
        t = time.perf_counter()
        first = slam.point_icp_front_end(r, az, odo, range_cap_m=cap)
        first_s = time.perf_counter() - t
        warm, warm_snap = [], load_snapshot()
        for _ in range(3):
            t = time.perf_counter()
            res = slam.point_icp_front_end(r, az, odo, range_cap_m=cap)
            warm.append(time.perf_counter() - t)
        np.testing.assert_array_equal(res.poses, first.poses)  # deterministic
        best = min(warm)
        row["icp"] = {
            "load_before_first": snap,
            "load_before_warm": warm_snap,
            "first_call_s": first_s,
            "warm_best_of_3_s": best,
            "scans_per_s_first": (n - 1) / first_s,
            "scans_per_s": (n - 1) / best,
            "real_time_factor": None if rate is None else (n - 1) / best / rate,
            "registered_share": float(np.mean(res.registered[1:])),
            "increments": increment_errors(res.poses, truth),
        }
        msg = (
            f"{name} ({n} scans): icp {(n - 1) / best:.0f} scans/s warm, "
            f"{(n - 1) / first_s:.0f} with compilation; "
            f"increments {row['icp']['increments']}"
        )
        if have_gicp:
            snap = load_snapshot()
            g = slam.icp_front_end(r, az, odo, max_range_m=cap, range_cap_m=cap)
            row["gicp"] = {
                "load_before": snap,
                "seconds": g.seconds,
                "scans_per_s": (n - 1) / g.seconds,
                "registered_share": float(np.mean(g.registered[1:])),
                "increments": increment_errors(g.poses, truth),
            }
            row["ratio_icp_warm_over_gicp_speed"] = g.seconds / best
            msg += (
                f" | gicp {(n - 1) / g.seconds:.1f} scans/s, increments {row['gicp']['increments']}"
            )
        report["logs"][name] = row
        print(msg, flush=True)
    write_json(OUT, report)
    print("wrote", OUT)


if __name__ == "__main__":
    main()
