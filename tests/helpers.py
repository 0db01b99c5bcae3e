"""Shared test fixtures: the mapping half of the CARMEN localization tests.

The gradient tools that used to live here (``tree_allclose``, ``finite_difference``) are
public now: :mod:`lidarjax.testing`."""

from __future__ import annotations

import numpy as np


def carmen_even_scan_stats(name: str, r_min: float, resolution: float = 0.1, margin: float = 3.0):
    """``(log, GridStats)`` of a shared CARMEN log's even-numbered scans at their corrected
    poses, on a grid covering their endpoints (the mapping half of the localization tests)."""
    import jaxlie

    from lidarjax.datasets import fetch, load_carmen
    from lidarjax.rays import from_scan
    from lidarjax.raytrace import GridSpec, accumulate

    log = load_carmen(fetch(name))
    idx = np.arange(0, log.n_scans, 2)
    p = log.poses[idx]
    rays = from_scan(
        jaxlie.SE2.from_xy_theta(p[:, 0], p[:, 1], p[:, 2]),
        log.azimuths_rad,
        log.ranges_m[idx],
        r_min,
        log.usable_range_m,
    )
    spec = GridSpec.covering(
        np.asarray(rays.endpoints()[rays.kind == 0]), resolution, margin=margin
    )
    return log, accumulate(spec, rays)
