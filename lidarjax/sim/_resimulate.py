"""Re-simulated logs: a log's own surfaces at given poses, cast again, so the poses are exact.

A real log scored against its reference poses measures the reference's errors too: on the
shared CARMEN logs the corrected poses are 2-3 cm off per increment (docs/results/slam.md,
stop 49). :func:`resimulate_scans` turns a log into a world whose poses are exact by
construction. It joins each scan's neighbouring end points (at the given poses) into
segments, rasterizes every scan's segments into one fine grid (the world), frees the cells
around every pose (the robot stood there), and casts every beam again from the same poses
into that world, with fresh range noise. The
scans keep the log's geometry (its corridors, clutter, beam layout and path), but they are
consistent with the poses up to the noise, and the truth is the poses.

Casting marches each ray in steps of a third of a cell. The grid stores, per cell, one
segment whose three-cell band covers it; the reading is where the ray crosses that
segment's line (exact for the segment), at the first sample whose cell holds a segment the
ray has crossed by then. An isolated end point (no neighbour within ``link_m``) occupies its
own cell only, and a ray reads the entry of that cell. Where several surfaces share a cell,
one of them decides.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from ._urban_common import check_poses, check_seed

__all__ = ["ResimulatedScans", "resimulate_scans"]

_MAX_CELLS = 400_000_000
_RING = [(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1) if (i, j) != (0, 0)]


@dataclass(frozen=True)
class ResimulatedScans:
    """Output of :func:`resimulate_scans`.

    Attributes:
        ranges_m: ``[N B]`` re-simulated readings (m); ``max_range_m`` where a beam meets no
            surface within it (the no-return value, as in CARMEN logs).
        occupied: ``[ny nx]`` bool, the world's cells: within one cell of a surface segment
            (or holding an isolated end point). Row ``i``, column ``j`` spans
            ``origin_m + cell_m * (j, i)`` to ``origin_m + cell_m * (j + 1, i + 1)``.
        origin_m: ``[2]`` world coordinates of the grid's lower-left corner (m).
        cell_m: cell size (m).
        n_segments: number of surface segments rasterized (isolated end points included).
    """

    ranges_m: np.ndarray
    occupied: np.ndarray
    origin_m: np.ndarray
    cell_m: float
    n_segments: int


def _check_number(value: object, name: str, *, positive: bool) -> float:
    """A finite real number (no bool), ``> 0`` or ``>= 0``; else a ValueError naming it."""
    want = "a positive finite number" if positive else "finite and >= 0"
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise ValueError(f"{name} must be {want}, got {value!r}")
    v = float(value)
    if not (math.isfinite(v) and (v > 0 if positive else v >= 0)):
        raise ValueError(f"{name} must be {want}, got {value!r}")
    return v


def _segments(ranges, az, poses, max_range_m, link_m):
    """Segments joining neighbouring beams' end points of each scan: ``[k 2 2]`` (m)."""
    hit = (ranges > 0) & (ranges < max_range_m)
    ang = poses[:, 2:3] + az[None, :]
    x = poses[:, 0:1] + ranges * np.cos(ang)
    y = poses[:, 1:2] + ranges * np.sin(ang)
    pts = np.stack([x, y], -1)  # [N B 2]
    a, b = pts[:, :-1], pts[:, 1:]
    keep = hit[:, :-1] & hit[:, 1:] & (np.linalg.norm(b - a, axis=-1) <= link_m)
    segs = np.stack([a[keep], b[keep]], 1)
    # isolated end points (no neighbour within link_m) stay in the world as points
    lone = hit.copy()
    lone[:, :-1] &= ~keep
    lone[:, 1:] &= ~keep
    p = pts[lone]
    return np.concatenate([segs, np.stack([p, p], 1)], 0)


def _rasterize(segs, origin, cell, shape):
    """Grid of segment ids (-1: free).

    Each segment marks the cells it crosses (sampled every third of a cell) and their eight
    neighbours: a band of three cells, so that no ray slips between two of its cells, while
    the hit itself is computed on the segment's line. Isolated end points (``a == b``) mark
    their own cell only. Priority where they share a cell: a segment's own cells, then its
    band, then points (written in the reverse order).
    """
    occ = np.full(shape, -1, np.int32)
    point = np.all(segs[:, 0] == segs[:, 1], axis=1)
    length = np.linalg.norm(segs[:, 1] - segs[:, 0], axis=-1)
    steps = np.ceil(length / (cell / 3.0)).astype(np.int64) + 1
    chunk = 200_000
    passes = [(True, [(0, 0)]), (False, _RING), (False, [(0, 0)])]
    for points, offsets in passes:
        for i0 in range(0, len(segs), chunk):  # bounded memory (host-side, not over rays)
            sel = np.nonzero(point[i0 : i0 + chunk] == points)[0] + i0
            s, n = segs[sel], steps[sel]
            rep = np.repeat(np.arange(len(s)), n)
            first = np.cumsum(n) - n
            k = np.arange(len(rep)) - np.repeat(first, n)
            f = k / np.maximum(np.repeat(n, n) - 1, 1)
            p = s[rep, 0] + (s[rep, 1] - s[rep, 0]) * f[:, None]
            ij = np.floor((p - origin) / cell).astype(np.int64)
            sid = sel[rep].astype(np.int32)
            for di, dj in offsets:
                occ[ij[:, 1] + dj, ij[:, 0] + di] = sid
    return occ


def _clear_footprints(ids, xy, origin, cell, radius):
    """Free every cell whose centre lies within ``radius`` of a pose (in place): the robot
    stood there, so no surface can (a door closed in one scan and passed through later,
    a person who stood where the robot drove)."""
    k = int(math.ceil(radius / cell))
    di, dj = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij")
    c = np.floor((xy - origin) / cell).astype(np.int64)  # the poses' cells
    for a, b in zip(di.ravel(), dj.ravel()):
        i, j = c[:, 0] + a, c[:, 1] + b
        centre = origin + (np.stack([i, j], 1) + 0.5) * cell
        near = np.linalg.norm(centre - xy, axis=1) <= radius
        ok = near & (i >= 0) & (i < ids.shape[1]) & (j >= 0) & (j < ids.shape[0])
        ids[j[ok], i[ok]] = -1


def _cross(u, v):
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


@functools.lru_cache(maxsize=8)
def _make_caster(n_steps: int):
    @jax.jit
    def cast(ids, a, b, origin, cell, poses, az, max_range, noise):
        ny, nx = ids.shape
        step = max_range / n_steps
        t = (jnp.arange(n_steps) + 0.5) * step  # [S]

        def one(args):
            pose, nz = args
            o = pose[:2]
            ang = pose[2] + az  # [B]
            d = jnp.stack([jnp.cos(ang), jnp.sin(ang)], -1)  # [B 2]
            p = o + t[None, :, None] * d[:, None, :]  # [B S 2]
            ij = jnp.floor((p - origin) / cell).astype(jnp.int32)
            inside = (ij[..., 0] >= 0) & (ij[..., 0] < nx) & (ij[..., 1] >= 0) & (ij[..., 1] < ny)
            sid = ids[jnp.clip(ij[..., 1], 0, ny - 1), jnp.clip(ij[..., 0], 0, nx - 1)]
            sid = jnp.where(inside, sid, -1)
            sa, sb = a[jnp.maximum(sid, 0)], b[jnp.maximum(sid, 0)]  # [B S 2]
            e = sb - sa
            point = jnp.sum(e * e, -1) == 0.0  # an isolated end point: its cell is the hit
            # the ray meets the segment's line at t_line; a sample counts once past it
            den = _cross(d[:, None, :], e)
            par = jnp.abs(den) < 1e-12
            t_line = _cross(sa - o, e) / jnp.where(par, 1.0, den)
            # a sample hits where its cell holds a surface whose line the ray crosses before
            # the next sample (or crossed already: the segment ends in this cell)
            t_entry = t - 0.5 * step  # within a step after the ray entered the cell
            t_hit = jnp.where(point, t_entry, jnp.maximum(t_line, t_entry - cell))
            hit = (sid >= 0) & (point | (~par & (t_line <= t[None, :] + 0.5 * step)))
            any_hit = hit.any(1)
            k = jnp.argmax(hit, axis=1)  # the first sample past a surface
            th = jnp.take_along_axis(t_hit, k[:, None], axis=1)[:, 0]
            r = jnp.clip(th + nz, 0.0, jnp.nextafter(max_range, 0.0))
            return jnp.where(any_hit & (th < max_range), r, max_range)

        return jax.lax.map(one, (poses, noise))

    return cast


def resimulate_scans(
    ranges_m: np.ndarray,
    azimuths_rad: np.ndarray,
    poses_xy_yaw: np.ndarray,
    *,
    max_range_m: float,
    cell_m: float = 0.01,
    link_m: float = 0.3,
    noise_sigma_m: float = 0.01,
    footprint_m: float = 0.2,
    seed: int = 0,
) -> ResimulatedScans:
    """Re-simulate a log's scans in the world of its own surfaces at the given poses.

    Each scan's neighbouring end points (readings in ``(0, max_range_m)``, at
    ``poses_xy_yaw``) closer than ``link_m`` are joined into segments; every scan's segments
    are rasterized into one grid of ``cell_m`` cells; then every beam of every scan is cast
    again from its pose into that world (the first segment it crosses, on the segment's
    line; see the module's docstring) and gets Gaussian noise of ``noise_sigma_m``.

    The returned scans are consistent with ``poses_xy_yaw`` up to the noise (and the
    rare isolated end point, read at its cell's entry): score a SLAM system on them
    against ``poses_xy_yaw`` and the reference's own errors are out of the score. Where
    the poses disagree about a wall, every copy of it is in the world and a ray meets
    the nearest: on the shared intel log, re-simulated readings are a median 7 cm
    shorter than the log's.

    Cost: the casting marches ``3 max_range_m / cell_m`` samples per beam (intel, 910
    scans of 180 beams to 20 m at 1 cm: about a minute on 2 CPU cores).

    Args:
        ranges_m: ``[N B]`` readings (m); ``>= max_range_m`` (or ``<= 0``) are no-returns
            and add no surface. NaN is an error.
        azimuths_rad: ``[B]`` beam angles relative to the heading (rad).
        poses_xy_yaw: ``[N 3]`` sensor poses ``(x m, y m, yaw rad)``: the world is built at
            them and the scans are cast from them (they become the exact truth).
        max_range_m: the sensor's range (m): surfaces come from readings below it, rays are
            cast up to it, and a beam without a surface within it reads exactly
            ``max_range_m``.
        cell_m: the world grid's cell size (m).
        link_m: largest gap (m) between neighbouring end points of a scan that still forms
            a surface; farther end points stay isolated points.
        noise_sigma_m: standard deviation of the readings' Gaussian noise (m).
        footprint_m: no surface within this distance (m) of any pose: the robot stood
            there. Without it, a door closed in one scan and driven through later, or a
            person who stood where the robot drove, is a wall across the path, and the
            scans near it read almost 0 m (0 turns it off).
        seed: noise seed (>= 0).

    Returns:
        A :class:`ResimulatedScans`.

    Raises:
        ValueError: a bad argument (named), or a world of more than 4e8 cells (raise
            ``cell_m`` or lower ``max_range_m``).
    """
    poses = check_poses(poses_xy_yaw, "poses_xy_yaw")
    seed = check_seed(seed)
    max_range_m = _check_number(max_range_m, "max_range_m", positive=True)
    cell_m = _check_number(cell_m, "cell_m", positive=True)
    link_m = _check_number(link_m, "link_m", positive=True)
    footprint_m = _check_number(footprint_m, "footprint_m", positive=False)
    noise_sigma_m = _check_number(noise_sigma_m, "noise_sigma_m", positive=False)
    az = np.asarray(azimuths_rad, np.float64)
    if az.ndim != 1 or az.size < 1 or not np.all(np.isfinite(az)):
        raise ValueError(f"azimuths_rad must be a finite [B] array, got shape {az.shape}")
    ranges = np.asarray(ranges_m, np.float64)
    if ranges.shape != (len(poses), len(az)):
        raise ValueError(
            f"ranges_m must have shape [N B] = {(len(poses), len(az))} (poses_xy_yaw, "
            f"azimuths_rad), got {ranges.shape}"
        )
    if np.isnan(ranges).any():
        raise ValueError("ranges_m contains NaN")

    segs = _segments(ranges, az, poses, max_range_m, link_m)
    pts = np.concatenate([segs.reshape(-1, 2), poses[:, :2]], 0)
    lo = np.floor(pts.min(0) / cell_m) * cell_m - 2 * cell_m
    hi = pts.max(0) + 2 * cell_m
    # rays reach max_range_m from every pose: beyond the surfaces' box they meet nothing
    shape = tuple(int(v) for v in np.ceil((hi - lo) / cell_m)[::-1])
    if shape[0] * shape[1] > _MAX_CELLS:
        raise ValueError(
            f"the world grid would have {shape[0] * shape[1]:.3g} cells (> {_MAX_CELLS:.0e}) at "
            f"cell_m={cell_m}; raise cell_m or lower max_range_m"
        )
    ids = _rasterize(segs, lo, cell_m, shape)
    if footprint_m > 0:
        _clear_footprints(ids, poses[:, :2], lo, cell_m, footprint_m)

    rng = np.random.default_rng([seed, 0x5E5])
    noise = rng.normal(0.0, noise_sigma_m, ranges.shape)
    n_steps = int(math.ceil(max_range_m / (cell_m / 3.0)))
    cast = _make_caster(n_steps)
    with jax.enable_x64(True):
        out = cast(
            jnp.asarray(ids),
            jnp.asarray(segs[:, 0]),
            jnp.asarray(segs[:, 1]),
            jnp.asarray(lo),
            jnp.float64(cell_m),
            jnp.asarray(poses),
            jnp.asarray(az),
            jnp.float64(max_range_m),
            jnp.asarray(noise),
        )
        out = np.asarray(out, np.float64)
    return ResimulatedScans(
        ranges_m=out, occupied=ids >= 0, origin_m=lo, cell_m=cell_m, n_segments=len(segs)
    )
