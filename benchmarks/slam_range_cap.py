"""Front end of decay-rate SLAM (issue #24) at two range caps: scans per second and
real-time factor of :func:`lidarjax.slam.run_front_end` with the defaults since stop 46
(``range_cap_m=20``, ``window_m=22``, ``n_nodes=512``) against those before
(``range_cap_m=10``, ``window_m=12``, ``n_nodes=256``), timed in the same run.

On the first ``--scans`` scans of each log with the experiment's drifting odometry
(``configs/slam.yaml``; ``log_inputs`` of ``benchmarks/slam.py``), the front end runs once
per configuration. Scans/s leave out the first two scans (the first match compiles).
The real-time factor is scans/s over the log's scan rate, where its timestamps give one.
The 1-minute load average is recorded before every timing. Writes
``benchmarks/results/slam_range_cap.json``.

Usage: ``python benchmarks/slam_range_cap.py [--logs intel fhw orebro] [--scans 150]``.
"""

from __future__ import annotations

import argparse

from _harness import RESULTS, machine_info, write_json
from slam import _scan_rate, log_inputs, time_front_end  # benchmarks/slam.py

from lidarjax import slam

OUT = RESULTS / "slam_range_cap.json"


def time_front_ends(ranges, az, odo, configs: dict, rate) -> dict:
    """``{key: record}``: :func:`time_front_end` of each configuration in turn, one after
    the other in the same run, with its range cap and optical-depth nodes."""
    out = {}
    for key, cfg in configs.items():
        record, _ = time_front_end(ranges, az, odo, cfg, rate)
        out[key] = {"range_cap_m": cfg.range_cap_m, "n_nodes": cfg.n_nodes, **record}
    return out


def compare_front_ends(
    argv, out, default_logs, configs_of, ratio: tuple[str, str, str], default_scans: int = 150
):
    """The range-cap benchmarks' run: for each log of ``--logs`` (default
    ``default_logs``), its first ``--scans`` scans (default ``default_scans``) timed
    under ``configs_of(log)`` (a ``(configs, extra record fields)`` pair;
    :func:`time_front_ends`), and ``ratio =
    (key, numerator, denominator)`` of their scans/s; the report is written to ``out``."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--logs", nargs="+", default=default_logs)
    ap.add_argument("--scans", type=int, default=default_scans)
    args = ap.parse_args(argv)
    report = {"machine": machine_info(), "scans": args.scans, "logs": {}}
    for name in args.logs:
        log, n, ranges, az, odo = log_inputs(name, args.scans)
        rate = _scan_rate(log.timestamps_s[:n])
        configs, extra = configs_of(log)
        row: dict = {"n_scans": n, "scan_rate_hz": rate, **extra}
        row.update(time_front_ends(ranges, az, odo, configs, rate))
        key, num, den = ratio
        row[key] = row[num]["scans_per_s"] / row[den]["scans_per_s"]
        report["logs"][name] = row
        print(name, row, flush=True)
    write_json(out, report)
    print("wrote", out)


def main(argv=None) -> None:
    configs = {
        "cap_10_m": slam.FrontEndConfig(range_cap_m=10.0, window_m=12.0, n_nodes=256),
        "cap_20_m": slam.FrontEndConfig(),
    }
    compare_front_ends(
        argv,
        OUT,
        ["intel", "fhw", "orebro"],
        lambda log: (configs, {}),
        ("ratio_20_over_10", "cap_20_m", "cap_10_m"),
    )


if __name__ == "__main__":
    main()
