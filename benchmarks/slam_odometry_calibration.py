"""What the odometry's calibration (issue #24, stop 63) costs :func:`lidarjax.slam.run_slam`:
:func:`lidarjax.slam.calibrate_odometry` and :meth:`~lidarjax.slam.OdometryCalibration.apply`
against the pose graph it feeds (:func:`lidarjax.slam.front_end_pose_graph`), timed in the
same run.

On every scan of each log, the experiment's drifting odometry (``log_inputs`` of
``benchmarks/slam.py``) is calibrated against the log's corrected poses standing in for a
front end (the cost does not depend on the values), and the pose graph over those poses,
the calibrated odometry and no loop closures is solved (best of 5, after a compiling
call). The 1-minute load average is recorded before every timing. Writes
``benchmarks/results/slam_odometry_calibration.json``.

Usage: ``python benchmarks/slam_odometry_calibration.py [--logs intel fhw orebro]``.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
from _harness import RESULTS, machine_info, write_json
from slam import log_inputs

from lidarjax import slam

OUT = RESULTS / "slam_odometry_calibration.json"


def best_of(fn, repeats: int = 5):
    load = os.getloadavg()[0]
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return out, {"load_1min_before": load, "seconds_best_of_5": min(times)}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--logs", nargs="+", default=["intel", "fhw", "orebro"])
    args = p.parse_args(argv)
    report = {"machine": machine_info(), "logs": {}}
    empty = slam.Loops(np.zeros((0, 2), np.int64), np.zeros((0, 3)), 0)
    for name in args.logs:
        log, n, _, _, odo = log_inputs(name, 10**9)
        fe = np.asarray(log.poses[:n], float)
        cal, t_fit = best_of(lambda: slam.calibrate_odometry(fe, odo))  # noqa: B023
        fixed, t_apply = best_of(lambda: cal.apply(odo))  # noqa: B023
        cfg = slam.SlamConfig(calibrate_odometry=True)
        slam.front_end_pose_graph(fe, fixed, empty, cfg).poses.block_until_ready()
        _, t_pg = best_of(
            lambda: slam.front_end_pose_graph(fe, fixed, empty, cfg).poses.block_until_ready()  # noqa: B023
        )
        row = {
            "poses": n,
            "heading_deg_per_m": float(np.rad2deg(cal.heading_rad_per_m)),
            "heading_gain": cal.heading_gain,
            "calibrate_odometry": t_fit,
            "apply": t_apply,
            "pose_graph_no_loops": t_pg,
            "ratio_calibration_over_pose_graph": (
                t_fit["seconds_best_of_5"] + t_apply["seconds_best_of_5"]
            )
            / t_pg["seconds_best_of_5"],
        }
        report["logs"][name] = row
        print(
            f"{name}: {n} poses, fit {t_fit['seconds_best_of_5'] * 1e3:.1f} ms, apply "
            f"{t_apply['seconds_best_of_5'] * 1e3:.1f} ms, pose graph "
            f"{t_pg['seconds_best_of_5'] * 1e3:.1f} ms (load {t_fit['load_1min_before']:.2f}); "
            f"drift {row['heading_deg_per_m']:.3f} deg/m (simulated 0.3)",
            flush=True,
        )
    write_json(OUT, report)


if __name__ == "__main__":
    main()
