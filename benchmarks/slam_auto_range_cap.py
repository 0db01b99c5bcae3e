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

import numpy as np
from _harness import RESULTS
from slam_range_cap import compare_front_ends

from lidarjax import slam

OUT = RESULTS / "slam_auto_range_cap.json"


def _configs(log):
    cap = slam.auto_range_cap(np.minimum(log.ranges_m, log.max_range_m), float(log.usable_range_m))
    configs = {
        "cap_20_m": slam.FrontEndConfig(),
        "auto": slam.FrontEndConfig().with_range_cap(cap),
    }
    return configs, {"auto_range_cap_m": cap}


def main(argv=None) -> None:
    compare_front_ends(
        argv,
        OUT,
        ["acapulco", "freiburg-101", "intel"],
        _configs,
        ("ratio_auto_over_20", "auto", "cap_20_m"),
    )


if __name__ == "__main__":
    main()
