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


def run_on_host_devices(script: str, cwd, n_devices: int = 2, timeout: int = 300) -> dict:
    """Run ``script`` with ``python -c`` in a fresh process whose CPU is ``n_devices`` JAX
    devices (``XLA_FLAGS=--xla_force_host_platform_device_count``: JAX fixes its devices
    when it starts) and return the JSON it prints on its last ``RESULT `` line."""
    import json
    import os
    import subprocess
    import sys

    env = dict(os.environ)
    env["XLA_FLAGS"] = (
        env.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={n_devices}"
    ).strip()
    env["JAX_PLATFORMS"] = "cpu"
    proc = subprocess.run(
        [sys.executable, "-c", script],
        env=env,
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT ") :])
