"""Front end of decay-rate SLAM (issue #24) with its default local map (the last 100
scans, ``FrontEndConfig.local_map_scans``, the default since stop 62) against the map of
every scan so far (``local_map_scans=0``, the default before), timed in the same run:
scans per second and real-time factor of :func:`lidarjax.slam.run_front_end`.

A local map removes the scan that leaves it (one more ``GridMap.add_scan``, with
``sign=-1``) after each match from scan 101 on; the matches read the same window of the
map either way. On the first ``--scans`` scans of each log with the experiment's drifting
odometry (``log_inputs`` of ``benchmarks/slam.py``); the two configurations run one after
the other. Scans/s leave out the first two scans (the first match compiles). The
1-minute load average is recorded before every timing. Writes
``benchmarks/results/slam_local_map.json``.

Usage: ``python benchmarks/slam_local_map.py [--logs intel fhw orebro] [--scans 300]``.
"""

from __future__ import annotations

from _harness import RESULTS
from slam_range_cap import compare_front_ends

from lidarjax import slam

OUT = RESULTS / "slam_local_map.json"


def main(argv=None) -> None:
    configs = {
        "every_scan": slam.FrontEndConfig(local_map_scans=0),
        "local_100": slam.FrontEndConfig(local_map_scans=100),
    }
    compare_front_ends(
        argv,
        OUT,
        ["intel", "fhw", "orebro"],
        lambda log: (configs, {"local_map_scans": 100}),
        ("ratio_local_over_every", "local_100", "every_scan"),
        default_scans=300,
    )


if __name__ == "__main__":
    main()
