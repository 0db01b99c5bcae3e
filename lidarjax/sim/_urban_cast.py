"""Simulated turns of a spinning multi-beam lidar in an urban world.

:func:`simulate_urban_scan` casts the rays of a spinning multi-beam lidar
(:class:`~lidarjax.sim.LidarSpec`, by default HDL-32E-like: 32 rings from -30.67 to +10.67
deg, 2170 azimuths) exactly against the ground plane ``z = 0``, the cylinders, the boxes
and the permeable spheres of an :class:`~lidarjax.sim.UrbanWorld`, in a jitted JAX kernel
(float32) built on the geometry core's primitives (:func:`~lidarjax.raytrace.ray_plane`,
:func:`~lidarjax.raytrace.ray_cylinder`, :func:`~lidarjax.raytrace.ray_box`,
:func:`~lidarjax.raytrace.ray_sphere`). Permeable spheres use a decay-rate model: a ray
that would cross a length ``L`` inside the sphere is reflected inside with probability
``1 - exp(-rate * L)``, at an exponentially distributed depth after entering.
:func:`simulate_urban_scans` simulates a drive lazily.

Frames. The sensor frame has ``x`` forward, ``y`` left, ``z`` up; its origin is at ``(x, y,
mount_height_m)`` of the vehicle pose ``(x, y, yaw)`` with the vehicle's yaw and no roll or
pitch. All lengths are metres, all angles radians. Object culling is NumPy; only the
ray-casting kernel runs in JAX. Everything is deterministic given the seeds.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Iterator

import jax
import jax.numpy as jnp
import numpy as np

from ..raytrace import ray_box, ray_cylinder, ray_plane, ray_sphere
from ._lidar import LidarSpec
from ._urban_common import check_pose, check_poses, check_seed, wrap_angle
from ._urban_world import UrbanWorld

__all__ = ["UrbanScan", "scan_seed", "simulate_urban_scan", "simulate_urban_scans"]

_N_SECTORS = 64  # azimuth sectors used for culling in the ray-casting kernel
_MEMORY_BUDGET = 200e6  # bytes of kernel work arrays per lax.map batch


@dataclasses.dataclass(frozen=True, eq=False)
class UrbanScan:
    """One simulated lidar turn.

    Attributes:
        directions: ``[n, 3]`` unit ray directions in the sensor frame (ring-major, ``n =
            n_rings * n_azimuths``).
        ranges_m: ``[n]`` measured ranges (m); ``inf`` where there is no return.
        pose_xy_yaw: ``[3]`` vehicle pose ``(x, y, yaw)`` of the scan.
        mount_height_m: Sensor height above the ground (m).
    """

    directions: np.ndarray
    ranges_m: np.ndarray
    pose_xy_yaw: np.ndarray
    mount_height_m: float

    def points(self) -> np.ndarray:
        """``[m, 3]`` finite returns in the sensor frame (m)."""
        ok = np.isfinite(self.ranges_m)
        return self.directions[ok] * self.ranges_m[ok, None]

    def T_world_sensor(self) -> np.ndarray:
        """``[4, 4]`` homogeneous transform from the sensor to the world frame."""
        x, y, yaw = self.pose_xy_yaw
        c, s = math.cos(yaw), math.sin(yaw)
        out = np.eye(4)
        out[:2, :2] = [[c, -s], [s, c]]
        out[:3, 3] = [x, y, self.mount_height_m]
        return out

    def points_world(self) -> np.ndarray:
        """``[m, 3]`` finite returns in the world frame (m)."""
        t = self.T_world_sensor()
        return self.points() @ t[:3, :3].T + t[:3, 3]


def _cast_sector(dirs, cyl, box, sph, expo, ground_z):
    """Exact nearest-hit range of rays from the origin in one azimuth sector.

    Args:
        dirs: ``[R, 3]`` unit directions.
        cyl: ``[Mc, 6]`` cylinders ``(cx, cy, r, z0, z1, valid)`` (sensor frame).
        box: ``[Mb, 9]`` boxes ``(ox, oy, oz, hx, hy, hz, cos, sin, valid)`` where ``o`` is
            the sensor origin in the box frame and ``(cos, sin)`` the box yaw.
        sph: ``[Ms, 6]`` spheres ``(cx, cy, cz, r, rate, valid)``.
        expo: ``[R, Ms]`` standard exponential draws (reflection depth times rate).
        ground_z: Ground height in the sensor frame (``-mount_height``).

    Returns:
        ``[R]`` true ranges, ``inf`` for no hit.
    """
    inf = jnp.float32(jnp.inf)
    dx, dy, dz = dirs[:, 0:1], dirs[:, 1:2], dirs[:, 2:3]  # [R 1]

    origin = jnp.zeros(3, dirs.dtype)

    # Ground plane z = ground_z, hit only by rays going down.
    ground = jnp.stack([jnp.zeros_like(ground_z), jnp.zeros_like(ground_z), ground_z])
    up = jnp.array([0.0, 0.0, 1.0], dirs.dtype)
    t_plane = jax.vmap(ray_plane, in_axes=(None, 0, None, None))(origin, dirs, ground, up)
    t_ground = jnp.where(dz[:, 0] < -1e-9, t_plane, inf)

    # Vertical finite cylinders: infinite-cylinder interval intersected with the z slab.
    ray = dirs[:, None, :]  # [R 1 3]
    tin, tout = ray_cylinder(
        cyl[None, :, 0:2], cyl[None, :, 2], cyl[None, :, 3], cyl[None, :, 4], origin, ray, eps=1e-12
    )
    hit = (cyl[None, :, 5] > 0) & (tin <= tout) & (tin > 0)
    t_cyl = jnp.min(jnp.where(hit, tin, inf), axis=1)

    # Oriented boxes: slab test in the box frame.
    c, s = box[None, :, 6], box[None, :, 7]
    ux, uy = c * dx + s * dy, -s * dx + c * dy  # [R Mb] ray direction in the box frame
    # coordinate-major [3 ...] stacks of per-coordinate rows: XLA's CPU backend then fuses
    # the per-axis slab work into fast loops (a [..., 3] layout is ~10x slower here)
    u = jnp.stack([ux, uy, jnp.broadcast_to(dz, ux.shape)])  # [3 R Mb]
    half = [box[None, :, 3 + k] for k in range(3)]
    o = jnp.stack([box[None, :, k] for k in range(3)])  # [3 1 Mb]
    lo, hi = jnp.stack([-h for h in half]), jnp.stack(half)
    tin, tout = ray_box(lo, hi, o, u, eps=1e-12, axis=0)  # [R Mb]
    hit = (box[None, :, 8] > 0) & (tin <= tout) & (tin > 0)
    t_box = jnp.min(jnp.where(hit, tin, inf), axis=1)

    # Permeable spheres: reflection at an exponential depth after entering.
    rate = sph[None, :, 4]
    t_enter, t_out = ray_sphere(sph[None, :, 0:3], sph[None, :, 3], origin, ray)  # [R Ms]
    t_in = jnp.maximum(t_enter, 0.0)
    depth = jnp.where(rate > 0, expo / jnp.where(rate > 0, rate, 1.0), inf)
    t_hit = t_in + depth
    hit = (sph[None, :, 5] > 0) & (t_enter < t_out) & (t_out > 0) & (t_hit < t_out)
    t_sph = jnp.min(jnp.where(hit, t_hit, inf), axis=1)

    return jnp.minimum(jnp.minimum(t_ground, t_cyl), jnp.minimum(t_box, t_sph))


@functools.partial(jax.jit, static_argnames=("batch_size",))
def _cast_kernel(key, dirs, cyl, box, sph, ground_z, noise, lo, hi, batch_size):
    """Ranges of ``[K, R]`` sector rays against per-sector object lists (float32)."""
    k_noise, k_exp = jax.random.split(key)
    n_sec, n_ray = dirs.shape[:2]
    expo = jax.random.exponential(k_exp, (n_sec, n_ray, sph.shape[1]), dtype=jnp.float32)

    def one(args):
        return _cast_sector(*args, ground_z)

    t = jax.lax.map(one, (dirs, cyl, box, sph, expo), batch_size=batch_size)
    meas = t + noise * jax.random.normal(k_noise, t.shape, dtype=jnp.float32)
    ok = jnp.isfinite(meas) & (meas >= lo) & (meas <= hi)
    return jnp.where(ok, meas, jnp.inf)


@functools.lru_cache(maxsize=16)
def _sector_layout(elev_bytes: bytes, n_az: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sector ray directions ``[K, n_rings * cps, 3]``, sector centres and half-widths."""
    elev = np.frombuffer(elev_bytes, dtype=np.float64)
    n_sec = min(_N_SECTORS, n_az)
    cps = -(-n_az // n_sec)
    cols = np.minimum(np.arange(n_sec * cps), n_az - 1).reshape(n_sec, cps)
    az = 2 * np.pi * cols / n_az  # increasing within a sector
    centre = 0.5 * (az[:, 0] + az[:, -1])
    half = 0.5 * (az[:, -1] - az[:, 0])
    ce, se = np.cos(elev), np.sin(elev)
    d = np.stack(
        [
            ce[None, :, None] * np.cos(az)[:, None, :],
            ce[None, :, None] * np.sin(az)[:, None, :],
            np.broadcast_to(se[None, :, None], (n_sec, elev.size, cps)),
        ],
        axis=-1,
    ).reshape(n_sec, elev.size * cps, 3)
    return jnp.asarray(d, dtype=jnp.float32), centre, half


def _bucket(n: int) -> int:
    return max(8, 1 << max(0, int(n) - 1).bit_length())


def _gather_sectors(centre_xy, bound_r, feats, null_row, reach, sec_centre, sec_half):
    """Per-sector padded feature arrays ``[K, M, F]`` of objects that may be hit."""
    dist = np.hypot(centre_xy[:, 0], centre_xy[:, 1])
    near = dist - bound_r <= reach
    idx_near = np.flatnonzero(near)
    dist, bound_r = dist[idx_near], bound_r[idx_near]
    phi = np.arctan2(centre_xy[idx_near, 1], centre_xy[idx_near, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        ang = np.where(dist > bound_r, np.arcsin(np.minimum(1.0, bound_r / dist)), np.pi)
    diff = np.abs(wrap_angle(phi[None, :] - sec_centre[:, None]))
    member = diff <= ang[None, :] + sec_half[:, None] + 1e-3  # [K O]
    count = member.sum(axis=1)
    m = _bucket(count.max() if count.size else 0)
    order = np.argsort(~member, axis=1, kind="stable")[:, :m]
    table = np.vstack([feats[idx_near], null_row[None]])
    null = table.shape[0] - 1
    if order.shape[1] < m:
        order = np.pad(order, ((0, 0), (0, m - order.shape[1])), constant_values=null)
    order = np.where(np.arange(m)[None, :] < count[:, None], order, null)
    return jnp.asarray(table[order], dtype=jnp.float32)


def _sensor_objects(world: UrbanWorld, pose: np.ndarray, lidar: LidarSpec, sec_c, sec_h):
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    h = lidar.mount_height_m
    reach = lidar.max_range_m + 6 * lidar.range_noise_m + 0.1

    def to_sensor(xy):
        px, py = xy[:, 0] - x, xy[:, 1] - y
        return np.column_stack([c * px + s * py, -s * px + c * py])

    pxy = to_sensor(world.pole_xy)
    r = world.pole_radius_m
    cyl = np.column_stack([pxy, r, np.full_like(r, -h), world.pole_height_m - h, np.ones_like(r)])
    cyl = _gather_sectors(
        pxy, r, cyl, np.array([1e4, 1e4, 0.0, 0.0, -1.0, 0.0]), reach, sec_c, sec_h
    )

    bxy = to_sensor(world.box_center[:, :2])
    bz = world.box_center[:, 2] - h
    yaw_s = world.box_yaw - yaw
    cb, sb = np.cos(yaw_s), np.sin(yaw_s)
    # sensor origin in the box frame: R(yaw_s)^T (0 - centre)
    ox = -(cb * bxy[:, 0] + sb * bxy[:, 1])
    oy = -(-sb * bxy[:, 0] + cb * bxy[:, 1])
    hs = world.box_half_size
    box = np.column_stack([ox, oy, -bz, hs, cb, sb, np.ones_like(bz)])
    bound = np.hypot(hs[:, 0], hs[:, 1])
    null_box = np.array([1e4, 1e4, 1e4, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0])
    box = _gather_sectors(bxy, bound, box, null_box, reach, sec_c, sec_h)

    sxy = to_sensor(world.crown_center[:, :2])
    rr = world.crown_radius_m
    sph = np.column_stack(
        [sxy, world.crown_center[:, 2] - h, rr, world.crown_rate_per_m, np.ones_like(rr)]
    )
    null_sph = np.array([1e4, 1e4, 1e4, 1.0, 0.0, 0.0])
    sph = _gather_sectors(sxy, rr, sph, null_sph, reach, sec_c, sec_h)
    return cyl, box, sph


def simulate_urban_scan(
    world: UrbanWorld, pose_xy_yaw: np.ndarray, lidar: LidarSpec, *, seed: int
) -> UrbanScan:
    """Simulate one lidar turn from a vehicle pose.

    Objects are culled per 5.6-deg azimuth sector with NumPy (bounding circles against the
    sector's wedge, and range), padded to a power-of-two count, and cast against exactly in
    a jitted float32 JAX kernel: ground plane, vertical cylinders, oriented boxes and
    permeable spheres. The nearest hit gets ``N(0, range_noise_m^2)`` noise; measured ranges
    outside ``[min_range_m, max_range_m]`` and rays hitting nothing become ``inf``.

    Args:
        world: The scene.
        pose_xy_yaw: ``[3]`` vehicle pose ``(x, y, yaw)`` (m, m, rad).
        lidar: The lidar.
        seed: Noise seed, ``>= 0``; same ``(world, pose, lidar, seed)`` gives the same scan.

    Returns:
        The scan (``n_rings * n_azimuths`` rays, ring-major).

    Raises:
        ValueError: Bad ``world``, ``pose_xy_yaw``, ``lidar`` or ``seed``.
    """
    if not isinstance(world, UrbanWorld):
        raise ValueError(f"world must be an UrbanWorld, got {type(world).__name__}")
    pose = check_pose(pose_xy_yaw)
    if not isinstance(lidar, LidarSpec):
        raise ValueError(f"lidar must be a LidarSpec, got {type(lidar).__name__}")
    seed = check_seed(seed)
    return _simulate(world, pose, lidar, seed)


def _simulate(world, pose, lidar, seed) -> UrbanScan:
    elev_bytes = lidar.elevations_rad.tobytes()
    dirs_sec, sec_c, sec_h = _sector_layout(elev_bytes, lidar.n_azimuths)
    cyl, box, sph = _sensor_objects(world, pose, lidar, sec_c, sec_h)
    n_sec, n_ray = dirs_sec.shape[:2]
    per_sector = n_ray * (cyl.shape[1] + box.shape[1] + 2 * sph.shape[1]) * 4 * 12
    batch = int(max(1, min(n_sec, _MEMORY_BUDGET // per_sector)))
    ranges = _cast_kernel(
        jax.random.key(seed),
        dirs_sec,
        cyl,
        box,
        sph,
        jnp.float32(-lidar.mount_height_m),
        jnp.float32(lidar.range_noise_m),
        jnp.float32(lidar.min_range_m),
        jnp.float32(lidar.max_range_m),
        batch_size=batch,
    )
    n_rings, n_az = lidar.n_rings, lidar.n_azimuths
    cps = n_ray // n_rings
    ranges = np.asarray(ranges, dtype=np.float64).reshape(n_sec, n_rings, cps)
    ranges = ranges.transpose(1, 0, 2).reshape(n_rings, n_sec * cps)[:, :n_az].ravel()
    return UrbanScan(
        directions=lidar.directions(),
        ranges_m=ranges,
        pose_xy_yaw=pose,
        mount_height_m=float(lidar.mount_height_m),
    )


def scan_seed(seed: int, index: int) -> int:
    """Noise seed of scan ``index`` in :func:`simulate_urban_scans`."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0])


def simulate_urban_scans(
    world: UrbanWorld,
    poses_xy_yaw: np.ndarray,
    lidar: LidarSpec,
    *,
    seed: int,
    progress: bool = True,
) -> Iterator[UrbanScan]:
    """Simulate a scan at each pose (lazily, to bound memory).

    Args:
        world: The scene.
        poses_xy_yaw: ``[N, 3]`` vehicle poses.
        lidar: The lidar.
        seed: Seed, ``>= 0``; scan ``i`` uses the noise seed ``scan_seed(seed, i)``.
        progress: Show a tqdm progress bar.

    Returns:
        An iterator over ``N`` scans.

    Raises:
        ValueError: Bad ``world``, ``poses_xy_yaw``, ``lidar`` or ``seed`` (raised
            immediately, not at the first ``next``).
    """
    if not isinstance(world, UrbanWorld):
        raise ValueError(f"world must be an UrbanWorld, got {type(world).__name__}")
    poses = check_poses(poses_xy_yaw, "poses_xy_yaw")
    if not isinstance(lidar, LidarSpec):
        raise ValueError(f"lidar must be a LidarSpec, got {type(lidar).__name__}")
    seed = check_seed(seed)

    def gen() -> Iterator[UrbanScan]:
        it = range(poses.shape[0])
        if progress:
            from tqdm.auto import tqdm

            it = tqdm(it, desc="urban scans", unit="scan", mininterval=0.5)
        for i in it:
            yield _simulate(world, poses[i], lidar, scan_seed(seed, i))

    return gen()
