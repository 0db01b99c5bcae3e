"""Reading ROS bags: scans per second of :func:`lidarjax.datasets.read_bag_laser_scans` on a
bag made from the Intel Research Lab CARMEN log, against :func:`load_carmen` of the same log
timed in the same run.

Data: the shared intel log (910 scans x 180 beams, ``fetch("intel")``), written once per
bag kind with :func:`write_bag_laser_scans` (``LaserScan`` on ``/scan``, ``Odometry`` on
``/odom``, ``/tf`` with ``map -> odom -> laser``; 2730 messages) into a temporary folder:

- ``ros1``: a ROS 1 ``.bag`` file;
- ``ros2_sqlite3`` / ``ros2_mcap``: ROS 2 bag folders with the two storage plugins.

Measured (median of ``--repeats`` calls after one untimed warm-up call):

- ``read_bag_laser_scans``: the whole call (open the bag, decode the 910 scans, the 910
  odometry and 910 tf messages, sample odometry and tf poses at the scan stamps);
- ``read_bag_scans_only``: the same bag read with ``tf``/odometry absent (a bag written with
  ``odom_topic=None, tf=False``): the LaserScan decoding alone;
- ``load_carmen``: the reference, parsing the gzip-compressed text log.

Scans/s is 910 / seconds; the ratio is ``load_carmen`` seconds / bag seconds (> 1: the bag
reads faster). Before timing, each bag is read back and checked against the log (ranges
equal to their float32 rounding, stamps exact, poses and odometry within 1e-12); a mismatch
aborts the run. The 1-minute load average is recorded before every timed block and the
block rerun after waiting when it was above 0.5 (:mod:`benchmarks._harness`).

Run with ``python benchmarks/rosbag_read.py [--repeats N] [--out PATH] [--quick]``
(``--quick``: one repeat, no waiting for the load; write its output elsewhere). Results go to
``benchmarks/results/rosbag_read.json`` and a Markdown summary is printed.
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

import numpy as np
from _harness import RESULTS, add_policy_args, machine_info, policy_from_args, write_json

from lidarjax.datasets import fetch, load_carmen, read_bag_laser_scans, write_bag_laser_scans

DEFAULT_OUT = RESULTS / "rosbag_read.json"
KINDS = {
    "ros1": dict(version=1),
    "ros2_sqlite3": dict(version=2, storage="sqlite3"),
    "ros2_mcap": dict(version=2, storage="mcap"),
}


def check_round_trip(log, path: Path) -> None:
    back = read_bag_laser_scans(path, usable_range_m=log.usable_range_m)
    ok = (
        np.array_equal(back.ranges_m, log.ranges_m.astype(np.float32).astype(np.float64))
        and np.array_equal(back.timestamps_s, log.timestamps_s)
        and np.abs(back.poses[:, :2] - log.poses[:, :2]).max() <= 1e-12
        and np.abs(back.odometry[:, :2] - log.odometry[:, :2]).max() <= 1e-12
    )
    dyaw = (back.poses[:, 2] - log.poses[:, 2] + np.pi) % (2 * np.pi) - np.pi
    if not (ok and np.abs(dyaw).max() <= 1e-12):
        raise SystemExit(f"round trip through {path} does not reproduce the log")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--quick", action="store_true")
    add_policy_args(ap)
    args = ap.parse_args(argv)
    if args.quick:
        args.repeats, args.wait_budget = 1, 0.0
    policy = policy_from_args(args)
    load_start = os.getloadavg()

    source = fetch("intel")
    log = load_carmen(source)
    n = log.n_scans
    carmen = policy.time_calls("load_carmen", lambda: load_carmen(source), args.repeats)
    rows: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for kind, kw in KINDS.items():
            suffix = ".bag" if kw["version"] == 1 else ""
            full = write_bag_laser_scans(Path(tmp, f"{kind}{suffix}"), log, **kw)
            scans = write_bag_laser_scans(
                Path(tmp, f"{kind}_scans{suffix}"), log, odom_topic=None, tf=False, **kw
            )
            check_round_trip(log, full)
            t_full = policy.time_calls(
                f"{kind} full", lambda p=full: read_bag_laser_scans(p), args.repeats
            )
            t_scans = policy.time_calls(
                f"{kind} scans only", lambda p=scans: read_bag_laser_scans(p), args.repeats
            )
            rows[kind] = {
                "bag_bytes": sum(f.stat().st_size for f in [full, *full.glob("*")] if f.is_file()),
                "read_bag_laser_scans_s": t_full["median_s"],
                "scans_per_s": n / t_full["median_s"],
                "read_bag_scans_only_s": t_scans["median_s"],
                "scans_only_per_s": n / t_scans["median_s"],
                "ratio_load_carmen_over_bag": carmen["median_s"] / t_full["median_s"],
                "timing": {"full": t_full, "scans_only": t_scans},
            }
    report = {
        "machine": machine_info(
            load_average_start=list(load_start), load_average_end=list(os.getloadavg())
        ),
        "setup": {"log": "intel", "n_scans": n, "n_beams": log.n_beams, "repeats": args.repeats},
        "load_carmen": {
            "seconds": carmen["median_s"],
            "scans_per_s": n / carmen["median_s"],
            "timing": carmen,
        },
        "bags": rows,
        "load_policy": policy.summary(),
    }
    write_json(args.out, report)
    print(markdown(report))
    return report


def markdown(report: dict) -> str:
    c = report["load_carmen"]
    lines = [
        f"ROS bag reading, intel log ({report['setup']['n_scans']} scans), "
        f"median of {report['setup']['repeats']} calls",
        "",
        "| source | seconds | scans/s | scans only: scans/s | load_carmen / bag |",
        "|---|---|---|---|---|",
        f"| load_carmen (text, gzip) | {c['seconds']:.3f} | {c['scans_per_s']:.0f} | | 1 |",
    ]
    for kind, r in report["bags"].items():
        lines.append(
            f"| {kind} | {r['read_bag_laser_scans_s']:.3f} | {r['scans_per_s']:.0f} "
            f"| {r['scans_only_per_s']:.0f} | {r['ratio_load_carmen_over_bag']:.2f} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
