"""Front end of decay-rate SLAM (issue #24) at the log's own range cap
(:func:`lidarjax.slam.auto_range_cap`, the default of ``lidarjax slam`` and of
``experiments/slam.py`` since stop 57) against the fixed 20 m of stops 46-56, timed in
the same run: scans per second and real-time factor of :func:`lidarjax.slam.run_front_end`.

The cap comes from each log's whole scan set, as the experiment chooses it; the timing
runs on its first ``--scans`` scans with the experiment's drifting odometry
(``log_inputs`` of ``benchmarks/slam.py``). Where the log's cap is 20 m the two
configurations are the same, and their ratio shows the timing's noise. Scans/s leave out
the first two scans (the first match compiles). The 1-minute load average is recorded
before every timing. Writes ``benchmarks/results/slam_auto_range_cap.json``.

Usage: ``python benchmarks/slam_auto_range_cap.py [--logs acapulco freiburg-101 intel]
[--scans 150]``.
"""

from __future__ import annotations

import argparse

import numpy as np
from _harness import RESULTS, machine_info, write_json
from slam import _scan_rate, log_inputs  # benchmarks/slam.py
from slam_range_cap import time_front_ends

from lidarjax import slam

OUT = RESULTS / "slam_auto_range_cap.json"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--logs", nargs="+", default=["acapulco", "freiburg-101", "intel"])
    ap.add_argument("--scans", type=int, default=150)
    args = ap.parse_args()
    report = {"machine": machine_info(), "scans": args.scans, "logs": {}}
    for name in args.logs:
        log, n, ranges, az, odo = log_inputs(name, args.scans)
        cap = slam.auto_range_cap(
            np.minimum(log.ranges_m, log.max_range_m), float(log.usable_range_m)
        )
        rate = _scan_rate(log.timestamps_s[:n])
        row: dict = {"n_scans": n, "scan_rate_hz": rate, "auto_range_cap_m": cap}
        configs = {
            "cap_20_m": slam.FrontEndConfig(),
            "auto": slam.FrontEndConfig().with_range_cap(cap),
        }
        row.update(time_front_ends(ranges, az, odo, configs, rate))
        row["ratio_auto_over_20"] = row["auto"]["scans_per_s"] / row["cap_20_m"]["scans_per_s"]
        report["logs"][name] = row
        print(name, row, flush=True)
    write_json(OUT, report)
    print("wrote", OUT)


if __name__ == "__main__":
    main()
