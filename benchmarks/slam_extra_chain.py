"""What the second chain (issue #24, stop 64: ``SlamConfig.extra_chain_models``, by default
an endpoint front end beside the decay-rate one) costs :func:`lidarjax.slam.run_slam`:
the two front ends' scans per second, timed one after the other in the same run, and
the pose graph with one chain against two.

Front ends: on the first ``--scans`` scans of each log with the experiment's drifting
odometry (``log_inputs`` of ``benchmarks/slam.py``), :func:`lidarjax.slam.run_front_end`
with the decay-rate model and with the endpoint model (the defaults otherwise: a
100-scan local map, 20 m cap); scans/s leave out the first two scans (the first match
compiles). ``both_scans_per_s`` is the rate of the two run one after the other, as
``run_slam`` does, and ``both_rtf`` its real-time factor.

Pose graph: on every scan of each log, :func:`lidarjax.slam.front_end_pose_graph` over
the corrected poses standing in for the front end, the drifting odometry and no loop
closures, with one chain and with a second (the poses with 1 cm / 0.1 degree of noise
per increment; the cost does not depend on the values), best of 5 after a compiling
call.

The 1-minute load average is recorded before every timing. Writes
``benchmarks/results/slam_extra_chain.json``.

Usage: ``python benchmarks/slam_extra_chain.py [--logs intel fhw orebro] [--scans 300]``.
"""

from __future__ import annotations

import argparse

import numpy as np
from _harness import RESULTS, machine_info, write_json
from slam import _scan_rate, log_inputs
from slam_odometry_calibration import best_of
from slam_range_cap import time_front_ends

from lidarjax import slam
from lidarjax.slam._front_end import between_np, compose_np

OUT = RESULTS / "slam_extra_chain.json"


def _perturbed(poses: np.ndarray, seed: int = 0) -> np.ndarray:
    """The poses re-chained from their increments plus 1 cm / 0.1 degree of noise."""
    r = np.random.default_rng(seed)
    inc = between_np(poses[:-1], poses[1:])
    inc = inc + r.normal(0, 1, inc.shape) * [0.01, 0.01, np.deg2rad(0.1)]
    out = [poses[0]]
    for u in inc:
        out.append(compose_np(out[-1], u))
    return np.array(out)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--logs", nargs="+", default=["intel", "fhw", "orebro"])
    p.add_argument("--scans", type=int, default=300)
    args = p.parse_args(argv)
    report = {"machine": machine_info(), "scans": args.scans, "logs": {}}
    configs = {
        "decay_rate": slam.FrontEndConfig(),
        "endpoint": slam.FrontEndConfig(model="endpoint"),
    }
    empty = slam.Loops(np.zeros((0, 2), np.int64), np.zeros((0, 3)), 0)
    cfg = slam.SlamConfig()
    for name in args.logs:
        log, n, ranges, az, odo = log_inputs(name, args.scans)
        rate = _scan_rate(log.timestamps_s[:n])
        row: dict = {"n_scans": n, "scan_rate_hz": rate}
        row.update(time_front_ends(ranges, az, odo, configs, rate))
        a, b = row["decay_rate"]["scans_per_s"], row["endpoint"]["scans_per_s"]
        row["ratio_endpoint_over_decay_rate"] = b / a
        row["both_scans_per_s"] = 1.0 / (1.0 / a + 1.0 / b)
        row["both_rtf"] = None if rate is None else row["both_scans_per_s"] / rate

        full, m, _, _, odo_full = log_inputs(name, 10**9)
        fe = np.asarray(full.poses[:m], float)
        second = _perturbed(fe)
        slam.front_end_pose_graph(fe, odo_full, empty, cfg).poses.block_until_ready()
        _, t_one = best_of(
            lambda: slam.front_end_pose_graph(fe, odo_full, empty, cfg).poses.block_until_ready()  # noqa: B023
        )
        slam.front_end_pose_graph(fe, odo_full, empty, cfg, extra_chains=[second])
        _, t_two = best_of(
            lambda: slam.front_end_pose_graph(  # noqa: B023
                fe,
                odo_full,  # noqa: B023
                empty,
                cfg,
                extra_chains=[second],  # noqa: B023
            ).poses.block_until_ready()
        )
        row["pose_graph_poses"] = m
        row["pose_graph_one_chain"] = t_one
        row["pose_graph_two_chains"] = t_two
        row["ratio_pose_graph_two_over_one"] = (
            t_two["seconds_best_of_5"] / t_one["seconds_best_of_5"]
        )
        report["logs"][name] = row
        print(
            f"{name}: decay rate {a:.2f} scans/s, endpoint {b:.2f} scans/s (x{b / a:.2f}), "
            f"both {row['both_scans_per_s']:.2f} scans/s (RTF {row['both_rtf']}); pose graph "
            f"({m} poses) one chain {t_one['seconds_best_of_5'] * 1e3:.0f} ms, two "
            f"{t_two['seconds_best_of_5'] * 1e3:.0f} ms",
            flush=True,
        )
    write_json(OUT, report)
    print("wrote", OUT)


if __name__ == "__main__":
    main()
