"""What a GICP chain (issue #24, stop 66: ``SlamConfig.extra_chain_models`` with
``"gicp"``, :func:`lidarjax.slam.icp_front_end`) costs :func:`lidarjax.slam.run_slam`:
its scans per second against the decay-rate and endpoint front ends', timed one after
the other in the same run, and the pose graph with two chains against three.

Front ends: on the first ``--scans`` scans of each log with the experiment's drifting
odometry (``log_inputs`` of ``benchmarks/slam.py``), :func:`lidarjax.slam.run_front_end`
with the decay-rate and the endpoint model (scans/s without the first two scans, whose
match compiles), and :func:`lidarjax.slam.icp_front_end` on the readings below the
20 m cap, as ``run_slam`` runs it (scans/s over all scans but the first: nothing
compiles). ``all_scans_per_s`` is the rate of the three run one after the other, and
``all_rtf`` its real-time factor.

Pose graph: on every scan of each log, :func:`lidarjax.slam.front_end_pose_graph` over
the corrected poses standing in for the front end, the drifting odometry and no loop
closures, with a second chain and with a third (the poses with 1 cm / 0.1 degree of
noise per increment, independent per chain; a tenth of the third chain's increments
masked out as rejected registrations), best of 5 after a compiling call.

The 1-minute load average and the other processes' busy cores are recorded before every
timing. Writes ``benchmarks/results/slam_gicp_chain.json``.

Usage: ``python benchmarks/slam_gicp_chain.py [--logs intel fhw orebro] [--scans 300]``.
"""

from __future__ import annotations

import argparse

import numpy as np
from _harness import RESULTS, load_snapshot, machine_info, write_json
from slam import _scan_rate, log_inputs
from slam_extra_chain import _perturbed
from slam_odometry_calibration import best_of
from slam_range_cap import time_front_ends

from lidarjax import slam

OUT = RESULTS / "slam_gicp_chain.json"


def time_icp_chain(ranges, az, odo, cap: float, rate) -> dict:
    """One timed :func:`lidarjax.slam.icp_front_end` run, as ``run_slam`` calls it."""
    snap = load_snapshot()
    r = slam.icp_front_end(ranges, az, odo, max_range_m=cap, range_cap_m=cap)
    sps = (len(ranges) - 1) / r.seconds
    return {
        "load_before": snap,
        "scans_per_s": sps,
        "registered_share": float(np.mean(r.registered[1:])),
        "real_time_factor": None if rate is None else sps / rate,
    }


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
        cap = configs["decay_rate"].range_cap_m
        row["gicp"] = time_icp_chain(np.minimum(ranges, cap), az, odo, cap, rate)
        a, b, c = (row[k]["scans_per_s"] for k in ("decay_rate", "endpoint", "gicp"))
        row["ratio_gicp_over_decay_rate"] = c / a
        row["all_scans_per_s"] = 1.0 / (1.0 / a + 1.0 / b + 1.0 / c)
        row["all_rtf"] = None if rate is None else row["all_scans_per_s"] / rate

        full, m, _, _, odo_full = log_inputs(name, 10**9)
        fe = np.asarray(full.poses[:m], float)
        second, third = _perturbed(fe, 0), _perturbed(fe, 1)
        mask = np.random.default_rng(2).random(m - 1) > 0.1

        def graph(chains, masks):
            return slam.front_end_pose_graph(
                fe, odo_full, empty, cfg, extra_chains=chains, extra_chain_valid=masks
            ).poses.block_until_ready()

        graph([second], None)
        _, t_two = best_of(lambda: graph([second], None))  # noqa: B023
        graph([second, third], [None, mask])
        _, t_three = best_of(lambda: graph([second, third], [None, mask]))  # noqa: B023
        row["pose_graph_poses"] = m
        row["pose_graph_two_chains"] = t_two
        row["pose_graph_three_chains"] = t_three
        row["ratio_pose_graph_three_over_two"] = (
            t_three["seconds_best_of_5"] / t_two["seconds_best_of_5"]
        )
        report["logs"][name] = row
        print(
            f"{name}: decay rate {a:.2f}, endpoint {b:.2f}, gicp {c:.2f} scans/s "
            f"(gicp x{c / a:.2f} decay rate); all three {row['all_scans_per_s']:.2f} scans/s "
            f"(RTF {row['all_rtf']}); pose graph ({m} poses) two chains "
            f"{t_two['seconds_best_of_5'] * 1e3:.0f} ms, three "
            f"{t_three['seconds_best_of_5'] * 1e3:.0f} ms",
            flush=True,
        )
    write_json(OUT, report)
    print("wrote", OUT)


if __name__ == "__main__":
    main()
