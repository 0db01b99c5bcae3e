"""A built-in, seeded synthetic 2-D office world and a scan simulator (NumPy in and out).

The office is a set of wall segments: an outer shell, a corridor with rooms on both sides
joined by door gaps, and a few pillars (square or polygonal). A robot drives a closed loop
through the corridor and two rooms; :func:`simulate_scans` casts the beams of a planar
lidar against the segments (exact ray–segment intersection,
:func:`~lidarjax.raytrace.ray_segment`, in float64) and adds Gaussian range noise.
Everything is deterministic given the seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import numpy as np

from ..raytrace import first_segment_hits, pad_to_chunks, unchunk

__all__ = ["OfficeWorld", "make_office", "simulate_scans"]

_CHUNK = 4096  # rays per chunk of _cast_segments (bounds memory: [chunk k])


@jax.jit
def _first_hits(o, d, a, b):
    """First-hit distances of ray chunks ``[c chunk 2]`` on segments ``a -> b`` ``[k 2]``."""
    return jax.lax.map(lambda x: first_segment_hits(x[0], x[1], a, b)[0], (o, d))


@dataclass(frozen=True)
class OfficeWorld:
    """A 2-D world made of line segments.

    Attributes:
        segments: ``[k 2 2]`` wall segments ``(start, end)`` in metres.
        bounds: ``[2 2]`` ``(lower corner, upper corner)`` of the world in metres.
        waypoints: ``[w 2]`` closed loop (m) through free space, for :meth:`trajectory`.
        seed: the seed the world was made with.
    """

    segments: np.ndarray
    bounds: np.ndarray
    waypoints: np.ndarray
    seed: int

    def trajectory(self, n_poses: int, *, jitter_m: float = 0.0, seed: int = 0) -> np.ndarray:
        """Poses evenly spaced along the closed waypoint loop.

        Args:
            n_poses: number of poses.
            jitter_m: amplitude (m) of a smooth, seeded lateral weave added to the path
                (keep it below the corridor half-width).
            seed: phase of the weave.

        Returns:
            ``[n_poses 3]`` poses (x, y, theta), heading along the (woven) path.
        """
        if n_poses <= 1:
            raise ValueError(f"n_poses must be at least 2, got {n_poses}")
        loop = np.vstack([self.waypoints, self.waypoints[:1]])
        seg = np.diff(loop, axis=0)
        seg_len = np.linalg.norm(seg, axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg_len)])
        s = np.linspace(0.0, cum[-1], n_poses, endpoint=False)
        i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
        frac = (s - cum[i]) / seg_len[i]
        xy = loop[i] + frac[:, None] * seg[i]
        if jitter_m > 0:
            phase = np.random.default_rng(seed).uniform(0, 2 * np.pi, 2)
            u = seg[i] / seg_len[i, None]
            normal = np.stack([-u[:, 1], u[:, 0]], axis=1)
            # smooth weave that vanishes at the waypoints (so turns stay inside doors)
            amp = jitter_m * np.sin(np.pi * frac) * np.sin(2 * np.pi * s / 3.7 + phase[0])
            xy = xy + normal * amp[:, None]
        step = np.roll(xy, -1, axis=0) - np.roll(xy, 1, axis=0)
        theta = np.arctan2(step[:, 1], step[:, 0])
        return np.column_stack([xy, theta])


def _box(
    cx: float, cy: float, half: float
) -> list[tuple[tuple[float, float], tuple[float, float]]]:
    c = [
        (cx - half, cy - half),
        (cx + half, cy - half),
        (cx + half, cy + half),
        (cx - half, cy + half),
    ]
    return [(c[k], c[(k + 1) % 4]) for k in range(4)]


def _ngon(cx: float, cy: float, r: float, n: int, phase: float):
    a = phase + 2 * np.pi * np.arange(n) / n
    p = np.column_stack([cx + r * np.cos(a), cy + r * np.sin(a)])
    return [(tuple(p[k]), tuple(p[(k + 1) % n])) for k in range(n)]


def _wall_with_doors(x0: float, x1: float, y: float, doors: list[float], width: float):
    """Horizontal wall from x0 to x1 at height y with door gaps centred at ``doors``."""
    cuts = [x0]
    for d in sorted(doors):
        cuts += [d - width / 2, d + width / 2]
    cuts.append(x1)
    return [((cuts[k], y), (cuts[k + 1], y)) for k in range(0, len(cuts), 2)]


def make_office(seed: int = 0, *, width_m: float = 20.0, height_m: float = 12.0) -> OfficeWorld:
    """Build the seeded synthetic office.

    Args:
        seed: controls room partitions, door positions and pillar placement.
        width_m: outer width (m), at least 10.
        height_m: outer height (m), at least 8.

    Returns:
        An :class:`OfficeWorld`.
    """
    if width_m < 10 or height_m < 8:
        raise ValueError(f"office must be at least 10 m x 8 m, got {width_m} x {height_m}")
    rng = np.random.default_rng(seed)
    W, H = float(width_m), float(height_m)
    cy0, cy1 = H / 2 - 1.0, H / 2 + 1.0  # corridor between these walls
    segs: list = [((0, 0), (W, 0)), ((W, 0), (W, H)), ((W, H), (0, H)), ((0, H), (0, 0))]
    n_rooms = 3
    xs = np.linspace(0, W, n_rooms + 1)
    xs[1:-1] += rng.uniform(-1.0, 1.0, n_rooms - 1)
    low_doors = [float(rng.uniform(xs[k] + 1.0, xs[k + 1] - 1.0)) for k in range(n_rooms)]
    high_doors = [float(rng.uniform(xs[k] + 1.0, xs[k + 1] - 1.0)) for k in range(n_rooms)]
    segs += _wall_with_doors(0.0, W, cy0, low_doors, 1.0)
    segs += _wall_with_doors(0.0, W, cy1, high_doors, 1.0)
    for x in xs[1:-1]:  # room partitions
        segs.append(((x, 0.0), (x, cy0)))
        segs.append(((x, cy1), (x, H)))
    # pillars: one per room, away from the doors' paths
    for k in range(n_rooms):
        for y_lo, y_hi in ((0.8, cy0 - 1.8), (cy1 + 1.8, H - 0.8)):
            cx = rng.uniform(xs[k] + 1.0, xs[k + 1] - 1.0)
            cy = rng.uniform(y_lo, y_hi)
            if rng.uniform() < 0.5:
                segs += _box(cx, cy, rng.uniform(0.15, 0.3))
            else:
                segs += _ngon(cx, cy, rng.uniform(0.15, 0.3), 8, rng.uniform(0, np.pi))
    segments = np.asarray(segs, dtype=np.float64)
    ymid = H / 2
    # loop: along the corridor, into the first lower room and the last upper room
    d0, d1 = low_doors[0], high_doors[-1]
    waypoints = np.array(
        [
            [1.0, ymid],
            [d0, ymid],
            [d0, cy0 - 1.2],
            [d0, ymid],
            [d1, ymid],
            [d1, cy1 + 1.2],
            [d1, ymid],
            [W - 1.0, ymid],
        ]
    )
    bounds = np.array([[0.0, 0.0], [W, H]])
    return OfficeWorld(segments=segments, bounds=bounds, waypoints=waypoints, seed=seed)


def _cast_segments(
    segments: np.ndarray, origins: np.ndarray, directions: np.ndarray, max_range: float
) -> np.ndarray:
    """Distance to the first segment hit by each ray, ``inf`` if none within ``max_range``.

    Args:
        segments: ``[k 2 2]`` segments (m).
        origins: ``[n 2]`` ray origins (m).
        directions: ``[n 2]`` unit directions.
        max_range: rays longer than this report ``inf``.

    Returns:
        ``[n]`` distances (m).
    """
    segs = np.asarray(segments, np.float64)
    # host-side padding: one compilation per number of chunks, not per number of rays
    o = pad_to_chunks(np.asarray(origins, np.float64), _CHUNK, 0.0)
    d = pad_to_chunks(np.asarray(directions, np.float64), _CHUNK, 1.0)
    with jax.enable_x64(True):  # float64 whatever JAX's default
        t = unchunk(np.asarray(_first_hits(o, d, segs[:, 0], segs[:, 1])), len(origins))
    return np.where(t <= max_range, t, np.inf)


def simulate_scans(
    world: OfficeWorld,
    poses: np.ndarray,
    azimuths_rad: np.ndarray,
    *,
    max_range_m: float = 30.0,
    noise_sigma_m: float = 0.01,
    seed: int = 0,
) -> np.ndarray:
    """Simulate planar lidar scans in a world.

    Args:
        world: the world.
        poses: ``[s 3]`` sensor poses (x, y, theta) in metres / radians.
        azimuths_rad: ``[b]`` beam angles relative to the heading.
        max_range_m: readings without a return within this range are reported as exactly
            ``max_range_m`` (the no-return value, as in CARMEN logs).
        noise_sigma_m: standard deviation of the additive Gaussian range noise (m).
        seed: noise seed.

    Returns:
        ``[s b]`` ranges (m), clipped to ``[0, max_range_m]``.
    """
    poses = np.asarray(poses, dtype=np.float64)
    az = np.asarray(azimuths_rad, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != 3:
        raise ValueError(f"poses must have shape [s, 3], got {poses.shape}")
    if az.ndim != 1:
        raise ValueError(f"azimuths_rad must have shape [b], got {az.shape}")
    ang = poses[:, 2:3] + az[None, :]
    dirs = np.stack([np.cos(ang), np.sin(ang)], axis=-1).reshape(-1, 2)
    origins = np.repeat(poses[:, :2], len(az), axis=0)
    r = _cast_segments(world.segments, origins, dirs, max_range_m).reshape(len(poses), len(az))
    rng = np.random.default_rng(seed)
    hit = np.isfinite(r)
    noisy = r + rng.normal(0.0, noise_sigma_m, r.shape)
    return np.where(hit, np.clip(noisy, 0.0, np.nextafter(max_range_m, 0)), max_range_m)
