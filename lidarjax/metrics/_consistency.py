"""Reference-free map consistency of a trajectory: how well the scans of different visits
agree where the trajectory puts them.

For every end point (a reading strictly between 0 and ``max_range_m``) of scan ``i`` at
``poses[i]``, its *cross-visit distance* is the distance to the nearest end point of any
scan ``j`` with ``|i - j| >= min_separation`` (another visit of the place, not the scans
taken just before or after), counted only when it is at most ``cap_m``. A trajectory that
places two visits of a wall on top of each other gives small distances; a drifted or
mis-closed one spreads them. The measure needs no ground truth, so it also scores a
reference trajectory (e.g. the SLAM-corrected poses of a CARMEN log) on the same footing
as an estimate.

NumPy and a k-d tree (SciPy); evaluation code, not a hot path.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["CrossVisitDistance", "cross_visit_distance"]


@dataclass(frozen=True)
class CrossVisitDistance:
    """Cross-visit distances of a trajectory's end points (module docstring).

    Attributes:
        distances_m: ``[N B]`` each reading's cross-visit distance (m); NaN where the
            reading is no end point or has no cross-visit neighbour within ``cap_m``.
        mean_m, median_m, p90_m: mean, median and 90th percentile of the finite
            distances (m), i.e. over the end points with a neighbour within ``cap_m``
            only (read them with ``fraction``: a misplaced visit also pushes points out
            of the cap); NaN when there are none.
        fraction: share of the end points with a cross-visit neighbour within ``cap_m``
            (NaN without end points).
        n_points: end points.
    """

    distances_m: np.ndarray
    mean_m: float
    median_m: float
    p90_m: float
    fraction: float
    n_points: int


def _positive(name: str, v) -> float:
    if isinstance(v, bool) or not isinstance(v, numbers.Real) or not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive finite number, got {v!r}")
    return float(v)


def cross_visit_distance(
    poses: np.ndarray,
    ranges_m: np.ndarray,
    azimuths_rad: np.ndarray,
    *,
    min_separation: int = 30,
    max_range_m: float = 10.0,
    cap_m: float = 0.3,
    chunk_size: int = 65536,
) -> CrossVisitDistance:
    """Cross-visit distances of the scans' end points at ``poses`` (module docstring).

    Args:
        poses: ``[N 3]`` sensor poses ``(x m, y m, yaw rad)``.
        ranges_m: ``[N B]`` readings (m), finite and >= 0; readings at or beyond
            ``max_range_m`` and zeros are no end points.
        azimuths_rad: ``[B]`` beam angles in the sensor frame (rad).
        min_separation: least index distance of two scans counted as different visits
            (the loop search's default; scans of the shared CARMEN logs are 0.55-0.95 m
            apart on average, so 30 scans is some 15-30 m of path: raise it for denser
            logs).
        max_range_m: readings at or beyond are not used (m).
        cap_m: largest counted distance (m).
        chunk_size: neighbour entries (end points times neighbours) per k-d tree query
            (memory bound).

    Returns:
        :class:`CrossVisitDistance`.

    Raises:
        ValueError: naming the offending argument.
    """
    p = np.asarray(poses, float)
    r = np.asarray(ranges_m, float)
    az = np.asarray(azimuths_rad, float)
    if r.ndim != 2:
        raise ValueError(f"ranges_m must be an [N, B] array, got shape {r.shape}")
    if not np.all(np.isfinite(r)) or np.any(r < 0):
        raise ValueError("ranges_m must be finite and >= 0")
    n, b = r.shape
    if p.shape != (n, 3) or not np.all(np.isfinite(p)):
        raise ValueError(f"poses must be a finite [{n}, 3] array, got shape {p.shape}")
    if az.shape != (b,) or not np.all(np.isfinite(az)):
        raise ValueError(f"azimuths_rad must be a finite [{b}] array, got shape {az.shape}")
    if isinstance(min_separation, bool) or not isinstance(min_separation, (int, np.integer)):
        raise ValueError(f"min_separation must be a positive int, got {min_separation!r}")
    if min_separation <= 0:
        raise ValueError(f"min_separation must be a positive int, got {min_separation!r}")
    max_range_m = _positive("max_range_m", max_range_m)
    cap_m = _positive("cap_m", cap_m)
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)):
        raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}")
    if chunk_size <= 0:
        raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}")

    ok = (r > 0) & (r < max_range_m)
    ang = p[:, 2:3] + az
    xy = np.stack([p[:, 0:1] + r * np.cos(ang), p[:, 1:2] + r * np.sin(ang)], -1)[ok]
    scan = np.broadcast_to(np.arange(n)[:, None], (n, b))[ok]
    m = xy.shape[0]
    best = np.full(m, np.inf)
    if m > 1:
        bound = float(np.nextafter(cap_m, np.inf))
        tree = cKDTree(xy)
        todo = np.arange(m)
        k = min(16, m)
        # Widen k for the points whose k nearest within the cap are all of the same visit:
        # at most log2(m / 16) + 1 rounds, ending at k = m (every point seen).
        while todo.size:
            still = []
            step = max(1, chunk_size // k)
            for s in range(0, todo.size, step):
                q = todo[s : s + step]
                # the bound is strict: nextafter keeps distances of exactly cap_m
                d, idx = tree.query(xy[q], k=k, distance_upper_bound=bound)
                d, idx = d.reshape(q.size, k), idx.reshape(q.size, k)
                other = np.isfinite(d)
                other[other] = np.abs(scan[idx[other]] - np.repeat(scan[q], k)[other.ravel()]) >= (
                    min_separation
                )
                dm = np.where(other, d, np.inf).min(1)
                best[q] = dm
                # unresolved: no other visit among k neighbours that all lie within the cap
                still.append(q[~np.isfinite(dm) & np.isfinite(d[:, -1])])
            todo = np.concatenate(still) if still else np.zeros(0, int)
            if k == m:
                break
            k = min(2 * k, m)
    out = np.full((n, b), np.nan)
    out[ok] = np.where(np.isfinite(best), best, np.nan)
    fin = best[np.isfinite(best)]
    stats = (
        (float(fin.mean()), float(np.median(fin)), float(np.percentile(fin, 90)))
        if fin.size
        else (math.nan,) * 3
    )
    return CrossVisitDistance(out, *stats, fin.size / m if m else math.nan, m)
