"""Shared test helpers: tree comparison and central finite differences."""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np


def tree_allclose(a, b, *, rtol: float = 1e-9, atol: float = 1e-12) -> bool:
    """True when two pytrees have the same structure and all leaves are close."""
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    if ta != tb:
        return False
    return all(
        np.allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol) for x, y in zip(la, lb)
    )


def finite_difference(f: Callable, x, *, eps: float = 1e-6) -> np.ndarray:
    """Central finite-difference Jacobian of ``f`` at ``x`` (float64), shape out.shape + x.shape."""
    x = jnp.asarray(x, dtype=jnp.float64)
    flat = x.reshape(-1)
    cols = []
    for i in range(flat.size):
        e = jnp.zeros_like(flat).at[i].set(eps)
        fp = np.asarray(f((flat + e).reshape(x.shape)), dtype=np.float64)
        fm = np.asarray(f((flat - e).reshape(x.shape)), dtype=np.float64)
        cols.append((fp - fm) / (2 * eps))
    jac = np.stack(cols, axis=-1)
    return jac.reshape(np.shape(cols[0]) + x.shape)


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
