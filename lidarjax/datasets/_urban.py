"""Seeded urban world simulator with an HDL-32E-like spinning lidar.

The world is built around a real vehicle trajectory (by default the KITTI odometry sequence
00 ground truth, :func:`load_urban_trajectory`): along both sides of the road the generator
(:func:`make_urban_world`) places street lamps, sign posts, traffic-light poles and tree
trunks (vertical cylinders, with permeable tree crowns on top), building facades, parked and
moving cars and pedestrians (oriented boxes), bushes (permeable spheres) and one row of
construction barrels (short, thick cylinders) on a straight stretch where no other pole-like
landmarks stand. :func:`urban_session` derives later mapping sessions ("weeks apart") from a
world: a few poles disappear, new ones appear, parked cars, pedestrians and moving cars are
re-sampled, and in one chosen session the whole barrel row is shifted sideways - the failure
case of a pole-based localizer whose only landmarks in a region moved.

:func:`simulate_scan` casts the rays of a spinning multi-beam lidar (:class:`LidarSpec`, by
default HDL-32E-like: 32 rings from -30.67 to +10.67 deg, 2170 azimuths) exactly against the
ground plane ``z = 0``, the cylinders, the boxes and the permeable spheres, in a jitted JAX
kernel (float32). Permeable spheres use a decay-rate model: a ray that would cross a length
``L`` inside the sphere is reflected inside with probability ``1 - exp(-rate * L)``, at an
exponentially distributed depth after entering. :func:`wheel_odometry` perturbs a
trajectory into drifting odometry.

Frames. The world frame is right-handed with ``z`` up and the ground at ``z = 0``. The
sensor frame has ``x`` forward, ``y`` left, ``z`` up; its origin is at ``(x, y,
mount_height_m)`` of the vehicle pose ``(x, y, yaw)`` with the vehicle's yaw and no roll or
pitch. All lengths are metres, all angles radians.

World generation is NumPy (and SciPy k-d trees); only the ray-casting kernel runs in JAX.
Everything is deterministic given the seeds.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from collections.abc import Iterator

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from ..raytrace import ray_box, ray_cylinder, ray_sphere
from ._kitti import load_kitti_poses, load_kitti_times

__all__ = [
    "BOX_KINDS",
    "CAMERA_TO_GROUND",
    "HDL32E_ELEVATIONS_DEG",
    "POLE_KINDS",
    "LidarSpec",
    "UrbanScan",
    "UrbanTrajectory",
    "UrbanWorld",
    "hdl32e",
    "load_urban_trajectory",
    "make_urban_world",
    "scan_seed",
    "simulate_scan",
    "simulate_scans",
    "simulate_urban_scan",
    "simulate_urban_scans",
    "urban_session",
    "wheel_odometry",
]

HDL32E_ELEVATIONS_DEG = np.linspace(-30.67, 10.67, 32)
HDL32E_ELEVATIONS_DEG.flags.writeable = False

POLE_KINDS = ("street_lamp", "sign_post", "traffic_light", "tree_trunk", "barrel")
BOX_KINDS = ("facade", "parked_car", "moving_car", "pedestrian")

_LAMP, _SIGN, _TLIGHT, _TREE, _BARREL = range(5)
_FACADE, _PARKED, _MOVING, _PEDESTRIAN = range(4)

# Rows map KITTI camera axes (x right, y down, z forward) to the ground frame (x forward,
# y left, z up): X = z_cam, Y = -x_cam, Z = -y_cam. det = +1.
CAMERA_TO_GROUND = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
CAMERA_TO_GROUND.flags.writeable = False

_KITTI_DT_S = 0.1
_ROAD_STEP_M = 0.5  # spacing of the resampled road polyline
_MARGIN_M = 0.05  # extra clearance covering the polyline resampling error
_REVISIT_RADIUS_M = 10.0  # road within this distance of earlier road counts as revisited
_REVISIT_GAP_M = 40.0  # ... if it is at least this far behind along the route
_BARREL_ZONE_M = 15.0  # no other poles / bushes / parked cars this close to the barrel row
_NEW_ID_STRIDE = 100_000  # pole ids added in session k are k * stride + 0, 1, ...
_N_SECTORS = 64  # azimuth sectors used for culling in the ray-casting kernel
_MEMORY_BUDGET = 200e6  # bytes of kernel work arrays per lax.map batch


# --------------------------------------------------------------------------------------------
# Small validation helpers
# --------------------------------------------------------------------------------------------


def _check_seed(seed: object, name: str = "seed") -> int:
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or int(seed) < 0:
        raise ValueError(f"{name} must be a non-negative integer, got {seed!r}")
    return int(seed)


def _check_poses(poses: object, name: str) -> np.ndarray:
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] < 1:
        raise ValueError(f"{name} must have shape [N, 3] with N >= 1, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    return arr


def _check_pose(pose: object, name: str = "pose_xy_yaw") -> np.ndarray:
    arr = np.asarray(pose, dtype=np.float64)
    if arr.shape != (3,):
        raise ValueError(f"{name} must have shape [3] (x, y, yaw), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr.tolist()}")
    return arr


def _check_nonneg(value: float, name: str) -> float:
    value = float(value)
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"{name} must be finite and >= 0, got {value}")
    return value


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


# --------------------------------------------------------------------------------------------
# Lidar, trajectory, scan containers
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class LidarSpec:
    """A spinning multi-beam lidar.

    Ray ``(ring i, column j)`` has elevation ``elevations_rad[i]`` and azimuth
    ``2 pi j / n_azimuths`` (wrapped to ``[-pi, pi)``; ``atan2(y, x)`` in the sensor frame,
    column 0 looks forward).

    Attributes:
        elevations_rad: ``[n_rings]`` float64 ring elevations (rad), each in ``(-pi/2, pi/2)``.
        n_azimuths: Columns per turn (2170 gives ~70 000 rays for 32 rings).
        max_range_m: Returns with a measured range above this are dropped (m).
        min_range_m: Returns with a measured range below this are dropped (m).
        range_noise_m: Standard deviation of the Gaussian radial noise (m).
        mount_height_m: Sensor height above the ground (m).
    """

    elevations_rad: np.ndarray
    n_azimuths: int = 2170
    max_range_m: float = 80.0
    min_range_m: float = 1.0
    range_noise_m: float = 0.02
    mount_height_m: float = 1.73

    def __post_init__(self) -> None:
        elev = np.array(self.elevations_rad, dtype=np.float64)
        if elev.ndim != 1 or elev.size < 1:
            raise ValueError(f"elevations_rad must have shape [n_rings >= 1], got {elev.shape}")
        if not np.all(np.isfinite(elev)) or np.any(np.abs(elev) >= np.pi / 2 - 1e-6):
            raise ValueError("elevations_rad must be finite and inside (-pi/2, pi/2)")
        elev.flags.writeable = False
        object.__setattr__(self, "elevations_rad", elev)
        if isinstance(self.n_azimuths, bool) or int(self.n_azimuths) != self.n_azimuths:
            raise ValueError(f"n_azimuths must be an integer, got {self.n_azimuths!r}")
        if int(self.n_azimuths) < 1:
            raise ValueError(f"n_azimuths must be >= 1, got {self.n_azimuths}")
        object.__setattr__(self, "n_azimuths", int(self.n_azimuths))
        _check_nonneg(self.min_range_m, "min_range_m")
        if not (math.isfinite(self.max_range_m) and self.max_range_m > self.min_range_m):
            raise ValueError(
                f"max_range_m must be finite and > min_range_m, got {self.max_range_m}"
            )
        _check_nonneg(self.range_noise_m, "range_noise_m")
        if not (math.isfinite(self.mount_height_m) and self.mount_height_m > 0):
            raise ValueError(f"mount_height_m must be > 0, got {self.mount_height_m}")

    @property
    def n_rings(self) -> int:
        return int(self.elevations_rad.size)

    @property
    def n_rays(self) -> int:
        return self.n_rings * self.n_azimuths

    @property
    def azimuths_rad(self) -> np.ndarray:
        """``[n_azimuths]`` column azimuths (rad) in ``[-pi, pi)``."""
        return _wrap(2 * np.pi * np.arange(self.n_azimuths) / self.n_azimuths)

    def directions(self) -> np.ndarray:
        """``[n_rings * n_azimuths, 3]`` unit ray directions in the sensor frame.

        Ring-major: ray ``i * n_azimuths + j`` is ring ``i``, column ``j``.
        """
        return _directions(self.elevations_rad.tobytes(), self.n_azimuths)

    @staticmethod
    def hdl32e(**overrides) -> LidarSpec:
        """HDL-32E-like lidar; see :func:`hdl32e`."""
        return hdl32e(**overrides)


@functools.lru_cache(maxsize=16)
def _directions(elev_bytes: bytes, n_az: int) -> np.ndarray:
    elev = np.frombuffer(elev_bytes, dtype=np.float64)
    az = 2 * np.pi * np.arange(n_az) / n_az
    ce, se = np.cos(elev)[:, None], np.sin(elev)[:, None]
    d = np.stack(
        [ce * np.cos(az)[None], ce * np.sin(az)[None], np.broadcast_to(se, (elev.size, n_az))],
        axis=-1,
    ).reshape(-1, 3)
    d.flags.writeable = False
    return d


def hdl32e(**overrides) -> LidarSpec:
    """Velodyne HDL-32E-like lidar: 32 rings from -30.67 to +10.67 deg, 2170 azimuths.

    Args:
        **overrides: Any :class:`LidarSpec` field (e.g. ``n_azimuths=360``).

    Returns:
        The lidar specification.
    """
    kwargs = {"elevations_rad": np.deg2rad(HDL32E_ELEVATIONS_DEG)}
    kwargs.update(overrides)
    return LidarSpec(**kwargs)


@dataclasses.dataclass(frozen=True, eq=False)
class UrbanTrajectory:
    """Ground-truth vehicle trajectory in a right-handed ground frame (z up).

    Attributes:
        xy_yaw: ``[N, 3]`` float64 poses ``(x, y, yaw)`` (m, m, rad).
        times_s: ``[N]`` float64 timestamps (s).
    """

    xy_yaw: np.ndarray
    times_s: np.ndarray

    def __post_init__(self) -> None:
        xy_yaw = _check_poses(self.xy_yaw, "xy_yaw")
        times = np.asarray(self.times_s, dtype=np.float64)
        if times.shape != (xy_yaw.shape[0],):
            raise ValueError(f"times_s must have shape [{xy_yaw.shape[0]}], got {times.shape}")
        object.__setattr__(self, "xy_yaw", xy_yaw)
        object.__setattr__(self, "times_s", times)

    @property
    def length_m(self) -> float:
        """Path length (m)."""
        return float(np.linalg.norm(np.diff(self.xy_yaw[:, :2], axis=0), axis=1).sum())


def load_urban_trajectory(
    path: str | os.PathLike[str] | None = None,
    *,
    times_path: str | os.PathLike[str] | None = None,
) -> UrbanTrajectory:
    """Load a KITTI pose file as a planar ground-frame trajectory.

    Camera positions are mapped to the ground frame by :data:`CAMERA_TO_GROUND` (``X =
    z_cam, Y = -x_cam, Z = -y_cam``; the height is dropped) and the yaw is the heading of the
    camera's forward axis projected on the ground.

    Args:
        path: KITTI pose file; ``None`` uses the registry file ``"kitti-00-poses"``.
        times_path: KITTI times file. If ``None``, the registry file ``"kitti-00-times"`` is
            used when ``path`` is ``None`` and times ``0, 0.1, 0.2, ...`` s otherwise.

    Returns:
        The trajectory (KITTI-00: 4541 poses, ~3.7 km).

    Raises:
        ValueError: The times file does not have one time per pose (names ``times_path``).
    """
    from ._registry import fetch

    if path is None:
        path = fetch("kitti-00-poses")
        if times_path is None:
            times_path = fetch("kitti-00-times")
    mats = load_kitti_poses(path, as_matrix=True)  # [N 4 4]
    pos = mats[:, :3, 3] @ CAMERA_TO_GROUND.T  # [N 3]
    fwd = mats[:, :3, 2] @ CAMERA_TO_GROUND.T  # camera z axis in the ground frame
    yaw = np.arctan2(fwd[:, 1], fwd[:, 0])
    if times_path is None:
        times = _KITTI_DT_S * np.arange(mats.shape[0])
    else:
        times = load_kitti_times(times_path)
        if times.shape != (mats.shape[0],):
            raise ValueError(
                f"times_path has {times.shape[0]} times but the pose file has {mats.shape[0]} poses"
            )
    return UrbanTrajectory(np.column_stack([pos[:, 0], pos[:, 1], yaw]), times)


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


# --------------------------------------------------------------------------------------------
# World container
# --------------------------------------------------------------------------------------------


_WORLD_SHAPES = {
    "pole_xy": (2,),
    "pole_radius_m": (),
    "pole_height_m": (),
    "pole_kind": (),
    "pole_id": (),
    "box_center": (3,),
    "box_half_size": (3,),
    "box_yaw": (),
    "box_kind": (),
    "crown_center": (3,),
    "crown_radius_m": (),
    "crown_rate_per_m": (),
    "crown_pole_id": (),
    "road_xy": (2,),
    "road_half_width_m": (),
    "road_new": (),
}
_WORLD_GROUPS = (
    ("pole_xy", "pole_radius_m", "pole_height_m", "pole_kind", "pole_id"),
    ("box_center", "box_half_size", "box_yaw", "box_kind"),
    ("crown_center", "crown_radius_m", "crown_rate_per_m", "crown_pole_id"),
    ("road_xy", "road_half_width_m", "road_new"),
)
_INT_FIELDS = {"pole_kind", "pole_id", "box_kind", "crown_pole_id"}


@dataclasses.dataclass(frozen=True, eq=False)
class UrbanWorld:
    """A static urban scene (world frame, z up, ground at ``z = 0``). All NumPy.

    Attributes:
        pole_xy: ``[P, 2]`` axis positions of vertical cylinders (m).
        pole_radius_m: ``[P]`` radii (m).
        pole_height_m: ``[P]`` heights; a pole spans ``0 <= z <= height`` (m).
        pole_kind: ``[P]`` int index into :data:`POLE_KINDS` (barrels are poles too).
        pole_id: ``[P]`` int id, stable across sessions (new poles of session ``k`` get
            ids ``k * 100000 + i``).
        box_center: ``[B, 3]`` oriented box centres (m).
        box_half_size: ``[B, 3]`` half extents along the box axes (m).
        box_yaw: ``[B]`` rotation of the box about ``z`` (rad).
        box_kind: ``[B]`` int index into :data:`BOX_KINDS`.
        crown_center: ``[C, 3]`` permeable sphere centres (tree crowns, bushes) (m).
        crown_radius_m: ``[C]`` radii (m).
        crown_rate_per_m: ``[C]`` decay rates (1/m) of the permeable-sphere model.
        crown_pole_id: ``[C]`` id of the tree trunk carrying the crown, ``-1`` for bushes.
        road_xy: ``[R, 2]`` route polyline resampled every 0.5 m (m).
        road_half_width_m: ``[R]`` road half-width around the route (m).
        road_new: ``[R]`` bool, False where the route revisits a street already driven
            (no objects are generated from there, to avoid duplicates).
        barrel_row_xy: ``[2, 2]`` end points of the barrel row's axis (m), as generated.
        barrel_row_normal: ``[2]`` unit road normal at the barrel row pointing away from
            the road.
        session: Session index the world belongs to.
    """

    pole_xy: np.ndarray
    pole_radius_m: np.ndarray
    pole_height_m: np.ndarray
    pole_kind: np.ndarray
    pole_id: np.ndarray
    box_center: np.ndarray
    box_half_size: np.ndarray
    box_yaw: np.ndarray
    box_kind: np.ndarray
    crown_center: np.ndarray
    crown_radius_m: np.ndarray
    crown_rate_per_m: np.ndarray
    crown_pole_id: np.ndarray
    road_xy: np.ndarray
    road_half_width_m: np.ndarray
    road_new: np.ndarray
    barrel_row_xy: np.ndarray
    barrel_row_normal: np.ndarray
    session: int = 0

    def __post_init__(self) -> None:
        for group in _WORLD_GROUPS:
            n = None
            for name in group:
                if name in _INT_FIELDS:
                    dtype = np.int64
                elif name == "road_new":
                    dtype = bool
                else:
                    dtype = np.float64
                arr = np.asarray(getattr(self, name), dtype=dtype)
                tail = _WORLD_SHAPES[name]
                if arr.ndim == 1 and arr.size == 0 and tail:
                    arr = arr.reshape((0, *tail))
                if arr.ndim != 1 + len(tail) or arr.shape[1:] != tail:
                    raise ValueError(f"{name} must have shape [n, *{tail}], got {arr.shape}")
                if n is None:
                    n = arr.shape[0]
                elif arr.shape[0] != n:
                    raise ValueError(f"{name} has {arr.shape[0]} rows, expected {n}")
                if dtype is np.float64 and not np.all(np.isfinite(arr)):
                    raise ValueError(f"{name} must be finite")
                object.__setattr__(self, name, arr)
        for name, shape in (("barrel_row_xy", (2, 2)), ("barrel_row_normal", (2,))):
            arr = np.asarray(getattr(self, name), dtype=np.float64)
            if arr.shape != shape:
                raise ValueError(f"{name} must have shape {list(shape)}, got {arr.shape}")
            object.__setattr__(self, name, arr)
        if np.any(self.pole_radius_m <= 0) or np.any(self.pole_height_m <= 0):
            raise ValueError("pole_radius_m and pole_height_m must be > 0")
        if np.any(self.box_half_size <= 0):
            raise ValueError("box_half_size must be > 0")
        if np.any(self.crown_radius_m <= 0) or np.any(self.crown_rate_per_m < 0):
            raise ValueError("crown_radius_m must be > 0 and crown_rate_per_m >= 0")

    @property
    def n_poles(self) -> int:
        return int(self.pole_xy.shape[0])

    @property
    def n_boxes(self) -> int:
        return int(self.box_center.shape[0])

    @property
    def n_crowns(self) -> int:
        return int(self.crown_center.shape[0])

    def replace(self, **changes) -> UrbanWorld:
        """A copy with some fields replaced."""
        return dataclasses.replace(self, **changes)


# --------------------------------------------------------------------------------------------
# World generation
# --------------------------------------------------------------------------------------------


class _Road:
    """Resampled route with tangents, half-widths, revisit mask and a k-d tree."""

    def __init__(self, xy: np.ndarray, half_width: np.ndarray, new: np.ndarray) -> None:
        self.xy = xy
        self.half_width = half_width
        self.new = new
        self.tree = cKDTree(xy)
        k = max(1, int(round(2.0 / _ROAD_STEP_M)))
        idx = np.arange(len(xy))
        diff = xy[np.minimum(idx + k, len(xy) - 1)] - xy[np.maximum(idx - k, 0)]
        norm = np.linalg.norm(diff, axis=1, keepdims=True)
        self.tangent = np.where(norm > 1e-9, diff / np.maximum(norm, 1e-12), [1.0, 0.0])
        self.normal = np.column_stack([-self.tangent[:, 1], self.tangent[:, 0]])  # left
        self.heading = np.arctan2(self.tangent[:, 1], self.tangent[:, 0])
        self.barrel_a = np.full(2, np.nan)
        self.barrel_b = np.full(2, np.nan)

    def clear_circle(self, xy: np.ndarray, radius: float, clearance: float) -> bool:
        d, _ = self.tree.query(xy)
        return bool(d >= clearance + radius + _MARGIN_M)

    def clear_box(self, center, half_xy, yaw, clearance: float) -> bool:
        reach = float(np.hypot(*half_xy)) + clearance + _MARGIN_M
        idx = self.tree.query_ball_point(center, reach)
        if not idx:
            return True
        p = self.xy[idx] - center
        c, s = math.cos(yaw), math.sin(yaw)
        u = np.abs(c * p[:, 0] + s * p[:, 1]) - half_xy[0]
        v = np.abs(-s * p[:, 0] + c * p[:, 1]) - half_xy[1]
        dist = np.hypot(np.maximum(u, 0), np.maximum(v, 0))
        return bool(dist.min() >= clearance + _MARGIN_M)

    def in_barrel_zone(self, xy: np.ndarray) -> bool:
        if not np.all(np.isfinite(self.barrel_a)):
            return False
        ab = self.barrel_b - self.barrel_a
        t = np.clip(np.dot(xy - self.barrel_a, ab) / max(np.dot(ab, ab), 1e-12), 0, 1)
        return bool(np.linalg.norm(xy - self.barrel_a - t * ab) < _BARREL_ZONE_M)


def _resample_route(xy: np.ndarray) -> np.ndarray:
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-6])
    xy = xy[keep]
    if len(xy) < 2:
        raise ValueError("trajectory must move (its poses are all at one point)")
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    s = np.arange(0.0, cum[-1] + 1e-9, _ROAD_STEP_M)
    return np.column_stack([np.interp(s, cum, xy[:, 0]), np.interp(s, cum, xy[:, 1])])


def _revisit_mask(xy: np.ndarray) -> np.ndarray:
    """True where the route point is new (no earlier route point within the revisit radius)."""
    tree = cKDTree(xy)
    pairs = tree.query_pairs(_REVISIT_RADIUS_M, output_type="ndarray")
    new = np.ones(len(xy), dtype=bool)
    if len(pairs):
        gap = np.abs(pairs[:, 0] - pairs[:, 1])
        pairs = pairs[gap * _ROAD_STEP_M > _REVISIT_GAP_M]
        new[pairs.max(axis=1)] = False
    return new


def _smooth_uniform(rng, n: int, lo: float, hi: float, knot_every: int) -> np.ndarray:
    knots = rng.uniform(lo, hi, size=n // knot_every + 2)
    return np.interp(np.arange(n) / knot_every, np.arange(knots.size), knots)


class _Occupancy:
    """Boolean grid (0.5 m cells) of claimed ground footprint, to keep objects apart."""

    cell = 0.5

    def __init__(self, road_xy: np.ndarray, pad: float = 120.0) -> None:
        self.lo = road_xy.min(axis=0) - pad
        shape = np.ceil((road_xy.max(axis=0) + pad - self.lo) / self.cell).astype(int) + 1
        self.grid = np.zeros(tuple(shape), dtype=bool)

    def _cells(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ij = np.floor((pts - self.lo) / self.cell).astype(np.int64)
        ij = np.clip(ij, 0, np.array(self.grid.shape) - 1)
        return ij[:, 0], ij[:, 1]

    def free(self, pts: np.ndarray) -> bool:
        return not bool(self.grid[self._cells(pts)].any())

    def mark(self, pts: np.ndarray) -> None:
        self.grid[self._cells(pts)] = True


def _disk_points(xy, radius: float) -> np.ndarray:
    n = int(np.ceil(radius / 0.2))
    g = np.linspace(-radius, radius, 2 * n + 1)
    gx, gy = np.meshgrid(g, g)
    inside = gx**2 + gy**2 <= radius**2 + 1e-9
    return np.column_stack([gx[inside], gy[inside]]) + xy


def _rect_points(center_xy, half_xy, yaw: float, pad: float) -> np.ndarray:
    hx, hy = half_xy[0] + pad, half_xy[1] + pad
    u = np.linspace(-hx, hx, int(np.ceil(2 * hx / 0.2)) + 1)
    v = np.linspace(-hy, hy, int(np.ceil(2 * hy / 0.2)) + 1)
    gu, gv = (a.ravel() for a in np.meshgrid(u, v))
    c, s = math.cos(yaw), math.sin(yaw)
    return np.column_stack([c * gu - s * gv, s * gu + c * gv]) + center_xy


class _Builder:
    """Accumulates objects while generating a world or a session."""

    def __init__(self) -> None:
        self.poles: list[tuple] = []  # (x, y, r, h, kind, id)
        self.boxes: list[tuple] = []  # (cx, cy, cz, hx, hy, hz, yaw, kind)
        self.crowns: list[tuple] = []  # (cx, cy, cz, r, rate, pole_id)


_POLE_DIMS = {  # kind: (diameter range, height range, lateral offset beyond the road edge)
    _LAMP: ((0.15, 0.3), (6.0, 9.0), (0.3, 1.5)),
    _SIGN: ((0.06, 0.12), (2.0, 3.5), (0.2, 1.5)),
    _TLIGHT: ((0.2, 0.35), (4.0, 7.0), (0.3, 1.0)),
    _TREE: ((0.2, 0.6), (3.0, 5.0), (1.0, 3.5)),
}


def _try_pole(road, occ, b: _Builder, rng, i: int, side: int, kind: int, pid: int, clr) -> bool:
    """Try to place one pole of ``kind`` next to road point ``i`` on ``side`` (+1 left)."""
    (d_lo, d_hi), (h_lo, h_hi), (o_lo, o_hi) = _POLE_DIMS[kind]
    r = 0.5 * rng.uniform(d_lo, d_hi)
    h = rng.uniform(h_lo, h_hi)
    off = road.half_width[i] + rng.uniform(o_lo, o_hi)
    xy = road.xy[i] + side * off * road.normal[i]
    if road.in_barrel_zone(xy) or not road.clear_circle(xy, r, clr):
        return False
    foot = _disk_points(xy, r + 1.0)
    if not occ.free(foot):
        return False
    if kind == _TREE:
        crown_r = rng.uniform(1.5, 3.0)
        room = float(road.tree.query(xy)[0]) - clr - _MARGIN_M
        crown_r = min(crown_r, room)
        if crown_r < 1.0:
            return False
        b.crowns.append((*xy, h + 0.6 * crown_r, crown_r, rng.uniform(0.8, 2.5), pid))
    occ.mark(foot)
    b.poles.append((*xy, r, h, kind, pid))
    return True


def _pick_kind(rng, p_tree: float) -> int:
    rest = (1 - p_tree) / 0.7
    return int(rng.choice(4, p=[0.35 * rest, 0.25 * rest, 0.1 * rest, p_tree]))


def _place_poles(road, occ, b: _Builder, rng, clr: float, next_id: int) -> int:
    n = len(road.xy)
    for side in (-1, 1):
        i = int(rng.integers(0, 20))
        block = -1
        spacing, p_tree = 12.0, 0.3
        while i < n:
            if i * _ROAD_STEP_M // 100 != block:  # new 100 m block: new density and mix
                block = int(i * _ROAD_STEP_M // 100)
                spacing = rng.uniform(8.0, 18.0)
                p_tree = 0.7 if rng.random() < 0.3 else 0.2
            if road.new[i]:
                kind = _pick_kind(rng, p_tree)
                if _try_pole(road, occ, b, rng, i, side, kind, next_id, clr):
                    next_id += 1
            i += max(1, int(rng.uniform(0.4, 1.6) * spacing / _ROAD_STEP_M))
    return next_id


def _try_box(road, occ, b, i, side, off, along, half, kind, clr, yaw_noise=0.0) -> bool:
    xy = road.xy[i] + side * off * road.normal[i] + along * road.tangent[i]
    yaw = float(road.heading[i] + yaw_noise)
    if not road.clear_box(xy, half[:2], yaw, clr):
        return False
    foot = _rect_points(xy, half[:2], yaw, 0.3)
    if not occ.free(foot):
        return False
    occ.mark(foot)
    b.boxes.append((*xy, half[2], *half, yaw, kind))
    return True


def _place_facades(road, occ, b, rng, clr) -> None:
    n = len(road.xy)
    for side in (-1, 1):
        s = rng.uniform(0, 10)
        while s < n * _ROAD_STEP_M:
            length = rng.uniform(8.0, 30.0)
            i = min(n - 1, int((s + length / 2) / _ROAD_STEP_M))
            if road.new[i]:
                thick = rng.uniform(0.5, 1.0)
                off = road.half_width[i] + rng.uniform(8.0, 15.0) + thick / 2
                half = np.array([length / 2, thick / 2, rng.uniform(3.0, 10.0)])
                # shrink on curves until it fits the corridor
                for _ in range(3):
                    if _try_box(road, occ, b, i, side, off, 0.0, half, _FACADE, clr):
                        break
                    half[0] *= 0.6
            gap = rng.uniform(2.0, 15.0) if rng.random() < 0.7 else rng.uniform(15.0, 40.0)
            s += length + gap


def _place_bushes(road, occ, b, rng, clr) -> None:
    n = len(road.xy)
    for side in (-1, 1):
        s = rng.uniform(0, 20)
        while s < n * _ROAD_STEP_M:
            i = min(n - 1, int(s / _ROAD_STEP_M))
            r = rng.uniform(0.5, 1.2)
            xy = road.xy[i] + side * (road.half_width[i] + rng.uniform(0.5, 4.0)) * road.normal[i]
            if (
                road.new[i]
                and not road.in_barrel_zone(xy)
                and road.clear_circle(xy, r, clr)
                and occ.free(_disk_points(xy, r + 0.2))
            ):
                occ.mark(_disk_points(xy, r + 0.2))
                b.crowns.append((*xy, 0.7 * r, r, rng.uniform(2.0, 5.0), -1))
            s += rng.uniform(10.0, 50.0)


def _place_dynamic(road, occ, b, rng, clr) -> None:
    """Parked cars, pedestrians and oncoming (moving) cars."""
    n = len(road.xy)
    for side in (-1, 1):
        s = rng.uniform(0, 20)
        while s < n * _ROAD_STEP_M:  # parked cars, in short queues
            i = min(n - 1, int(s / _ROAD_STEP_M))
            queue = int(rng.integers(1, 5))
            for k in range(queue):
                half = np.array([rng.uniform(2.0, 2.5), rng.uniform(0.85, 0.95), 0.0])
                half[2] = rng.uniform(0.65, 0.85)
                j = min(n - 1, i + int(k * 6.0 / _ROAD_STEP_M))
                off = max(road.half_width[j] - rng.uniform(0.0, 1.0), clr + 1.0)
                xy = road.xy[j] + side * off * road.normal[j]
                if road.new[j] and not road.in_barrel_zone(xy):
                    _try_box(
                        road,
                        occ,
                        b,
                        j,
                        side,
                        off,
                        0.0,
                        half,
                        _PARKED,
                        clr,
                        0.03 * rng.standard_normal(),
                    )
            s += queue * 6.0 + rng.uniform(10.0, 60.0)
        s = rng.uniform(0, 50)
        while s < n * _ROAD_STEP_M:  # pedestrians on the sidewalk
            i = min(n - 1, int(s / _ROAD_STEP_M))
            half = np.array([0.25, 0.3, rng.uniform(0.8, 0.95)])
            off = road.half_width[i] + rng.uniform(0.5, 3.0)
            if road.new[i]:
                _try_box(
                    road,
                    occ,
                    b,
                    i,
                    side,
                    off,
                    0.0,
                    half,
                    _PEDESTRIAN,
                    clr,
                    rng.uniform(-np.pi, np.pi),
                )
            s += rng.uniform(20.0, 150.0)
    s = rng.uniform(0, 50)
    while s < n * _ROAD_STEP_M:  # oncoming traffic on the left lane
        i = min(n - 1, int(s / _ROAD_STEP_M))
        half = np.array([rng.uniform(2.0, 2.5), 0.9, rng.uniform(0.7, 0.9)])
        off = clr + half[1] + _MARGIN_M + rng.uniform(0.1, 0.7)
        if road.new[i]:
            _try_box(road, occ, b, i, 1, off, 0.0, half, _MOVING, clr, np.pi)
        s += rng.uniform(40.0, 200.0)


def _place_barrels(road, occ, b, rng, clr, next_id: int) -> tuple[int, np.ndarray, np.ndarray]:
    n = len(road.xy)
    n_barrels = int(rng.integers(6, 11))
    spacing = 3.0
    length = (n_barrels - 1) * spacing
    win = int(np.ceil((length + 10.0) / _ROAD_STEP_M))
    starts = np.arange(0, n - win, int(10.0 / _ROAD_STEP_M))
    good = []
    for i0 in starts:
        seg = slice(i0, i0 + win)
        dh = _wrap(road.heading[seg] - road.heading[i0 + win // 2])
        if road.new[seg].all() and np.abs(dh).max() < np.deg2rad(3.0):
            good.append(i0)
    if not good:
        raise ValueError("trajectory has no straight stretch for the barrel row")
    good = np.array(good)
    rng.shuffle(good)
    for i0 in good[:200]:
        ic = i0 + win // 2
        side = 1 if rng.random() < 0.5 else -1
        out = side * road.normal[ic]
        base = road.xy[ic] + (road.half_width[ic] + 0.3) * out
        t = road.tangent[ic]
        along = (np.arange(n_barrels) - (n_barrels - 1) / 2) * spacing
        xy = base + along[:, None] * t
        r = 0.5 * rng.uniform(0.5, 0.6, n_barrels)
        h = rng.uniform(1.0, 1.2, n_barrels)
        ok = all(road.clear_circle(p, rr, clr) for p, rr in zip(xy, r))
        ok = ok and all(occ.free(_disk_points(p, rr + 0.3)) for p, rr in zip(xy, r))
        # the shifted row (up to 5 m further out) must also stay free
        ok = ok and all(occ.free(_disk_points(p + 5.0 * out, rr + 0.3)) for p, rr in zip(xy, r))
        if not ok:
            continue
        for k in range(n_barrels):
            occ.mark(_disk_points(xy[k], r[k] + 0.3))
            b.poles.append((*xy[k], r[k], h[k], _BARREL, next_id))
            next_id += 1
        road.barrel_a, road.barrel_b = xy[0].copy(), xy[-1].copy()
        return next_id, np.stack([xy[0], xy[-1]]), out
    raise ValueError("could not place the barrel row")


def _road_from_world(world: UrbanWorld) -> _Road:
    road = _Road(world.road_xy, world.road_half_width_m, world.road_new)
    road.barrel_a, road.barrel_b = world.barrel_row_xy[0], world.barrel_row_xy[1]
    return road


def _arrays(b: _Builder) -> dict:
    poles = np.array(b.poles, dtype=np.float64).reshape(-1, 6)
    boxes = np.array(b.boxes, dtype=np.float64).reshape(-1, 8)
    crowns = np.array(b.crowns, dtype=np.float64).reshape(-1, 6)
    return dict(
        pole_xy=poles[:, :2],
        pole_radius_m=poles[:, 2],
        pole_height_m=poles[:, 3],
        pole_kind=poles[:, 4].astype(np.int64),
        pole_id=poles[:, 5].astype(np.int64),
        box_center=boxes[:, :3],
        box_half_size=boxes[:, 3:6],
        box_yaw=boxes[:, 6],
        box_kind=boxes[:, 7].astype(np.int64),
        crown_center=crowns[:, :3],
        crown_radius_m=crowns[:, 3],
        crown_rate_per_m=crowns[:, 4],
        crown_pole_id=crowns[:, 5].astype(np.int64),
    )


def make_urban_world(
    trajectory: UrbanTrajectory | np.ndarray,
    *,
    seed: int = 0,
    road_half_width_m: tuple[float, float] = (4.0, 7.0),
    clearance_m: float = 2.5,
) -> UrbanWorld:
    """Generate a seeded urban scene around a trajectory.

    The route polyline is resampled every 0.5 m; the road half-width varies smoothly (knots
    every 50 m) within ``road_half_width_m``. Along both sides the generator places, per
    100 m block with its own density (one pole every 8-18 m on average per side before
    rejections) and mix (tree-lined or not): street lamps (diameter 0.15-0.3 m, 6-9 m
    tall), sign posts (0.06-0.12 m, 2-3.5 m), traffic-light poles (0.2-0.35 m, 4-7 m), tree
    trunks (0.2-0.6 m, 3-5 m, each with a permeable crown of radius 1-3 m on top), building
    facades (thin boxes 8-30 m long, 8-15 m behind the road edge, with gaps), bushes
    (permeable spheres), parked cars (~4.5 x 1.8 x 1.5 m at the road edge), pedestrians and
    oncoming cars on the left lane. One row of 6-10 construction barrels (diameter 0.5-0.6
    m, height 1.0-1.2 m, 3 m apart) stands at the road edge of a random straight stretch;
    no other poles, bushes or parked cars are within 15 m of it.

    No object comes closer than ``clearance_m`` (horizontally) to the route, objects do
    not overlap, and where the route revisits a street (within 10 m of route driven more
    than 40 m earlier) nothing new is generated, so loops see the same objects again.

    Args:
        trajectory: The route, an :class:`UrbanTrajectory` or an ``[N, 3]`` pose array.
        seed: Seed, ``>= 0``.
        road_half_width_m: ``(low, high)`` range of the road half-width (m).
        clearance_m: Minimum horizontal distance of any object to the route (m).

    Returns:
        The world (session 0).

    Raises:
        ValueError: Bad ``trajectory``, ``seed``, ``road_half_width_m`` or ``clearance_m``.
    """
    seed = _check_seed(seed)
    if isinstance(trajectory, UrbanTrajectory):
        xy_yaw = trajectory.xy_yaw
    else:
        xy_yaw = _check_poses(trajectory, "trajectory")
    lo, hi = (float(v) for v in road_half_width_m)
    if not (0 < lo <= hi) or not math.isfinite(hi):
        raise ValueError(f"road_half_width_m must be 0 < low <= high, got {road_half_width_m}")
    clr = _check_nonneg(clearance_m, "clearance_m")
    if lo < clr:
        raise ValueError("road_half_width_m low must be >= clearance_m")

    rng = np.random.default_rng([seed, 0x5EED_0B])
    road_xy = _resample_route(xy_yaw[:, :2])
    half = _smooth_uniform(rng, len(road_xy), lo, hi, int(50.0 / _ROAD_STEP_M))
    road = _Road(road_xy, half, _revisit_mask(road_xy))
    occ = _Occupancy(road_xy)
    b = _Builder()
    next_id, row_xy, row_normal = _place_barrels(road, occ, b, rng, clr, 0)
    _place_facades(road, occ, b, rng, clr)
    _place_poles(road, occ, b, rng, clr, next_id)
    _place_bushes(road, occ, b, rng, clr)
    _place_dynamic(road, occ, b, rng, clr)
    return UrbanWorld(
        **_arrays(b),
        road_xy=road_xy,
        road_half_width_m=half,
        road_new=road.new,
        barrel_row_xy=row_xy,
        barrel_row_normal=row_normal,
        session=0,
    )


def urban_session(
    world: UrbanWorld,
    session: int,
    *,
    seed: int = 0,
    barrel_session: int | None = None,
    p_remove: float = 0.05,
    p_add: float = 0.05,
    barrel_shift_m: float = 3.0,
    clearance_m: float = 2.5,
) -> UrbanWorld:
    """Derive the scene of a later mapping session from a session-0 world.

    Facades, bushes and (in session 0) all poles stay. Parked cars, pedestrians and moving
    cars are always re-sampled (also in session 0). In sessions ``>= 1`` every non-barrel
    pole is removed independently with probability ``p_remove`` (never all; tree crowns go
    with their trunks) and about ``p_add`` times as many new poles (new ids ``session *
    100000 + i``) appear along the road. Barrels are never removed or added; in session
    ``barrel_session`` all barrels are shifted by ``barrel_shift_m`` along
    ``world.barrel_row_normal`` (positive: away from the road), keeping their positions
    along the road.

    Args:
        world: The session-0 world from :func:`make_urban_world`.
        session: Session index, ``>= 0``.
        seed: Seed, ``>= 0``; the result is deterministic in ``(seed, session)``.
        barrel_session: Session in which the barrel row is shifted, or ``None``.
        p_remove: Removal probability per pole, in ``[0, 1]``.
        p_add: Expected new poles per existing pole, in ``[0, 1]``.
        barrel_shift_m: Sideways barrel shift (m).
        clearance_m: Minimum horizontal distance of re-sampled objects to the route (m).

    Returns:
        The session's world.

    Raises:
        ValueError: A bad argument (the message names it).
    """
    if not isinstance(world, UrbanWorld):
        raise ValueError(f"world must be an UrbanWorld, got {type(world).__name__}")
    session = _check_seed(session, "session")
    seed = _check_seed(seed)
    if barrel_session is not None:
        barrel_session = _check_seed(barrel_session, "barrel_session")
    for name, p in (("p_remove", p_remove), ("p_add", p_add)):
        if not (0.0 <= float(p) <= 1.0):
            raise ValueError(f"{name} must be in [0, 1], got {p}")
    if not math.isfinite(float(barrel_shift_m)):
        raise ValueError(f"barrel_shift_m must be finite, got {barrel_shift_m}")
    clr = _check_nonneg(clearance_m, "clearance_m")

    rng = np.random.default_rng([seed, session, 0x5E55])
    road = _road_from_world(world)
    pole_xy = world.pole_xy.copy()
    is_barrel = world.pole_kind == _BARREL
    keep = np.ones(world.n_poles, dtype=bool)
    if session > 0:
        drop = (rng.random(world.n_poles) < p_remove) & ~is_barrel
        if drop.any() and drop.sum() == world.n_poles:
            drop[int(rng.integers(world.n_poles))] = False
        keep = ~drop
    if barrel_session is not None and session == barrel_session:
        pole_xy[is_barrel] += float(barrel_shift_m) * world.barrel_row_normal

    b = _Builder()
    b.poles = [
        (*pole_xy[k], world.pole_radius_m[k], world.pole_height_m[k], world.pole_kind[k],
         world.pole_id[k])
        for k in np.flatnonzero(keep)
    ]  # fmt: skip
    kept_ids = set(world.pole_id[keep].tolist())
    b.crowns = [
        (*world.crown_center[k], world.crown_radius_m[k], world.crown_rate_per_m[k], pid)
        for k, pid in enumerate(world.crown_pole_id.tolist())
        if pid < 0 or pid in kept_ids
    ]
    b.boxes = [
        (*world.box_center[k], *world.box_half_size[k], world.box_yaw[k], _FACADE)
        for k in np.flatnonzero(world.box_kind == _FACADE)
    ]
    occ = _Occupancy(world.road_xy)
    for x, y, r, *_ in b.poles:
        occ.mark(_disk_points(np.array([x, y]), r + 1.0))
    for x, y, _, r, *_ in b.crowns:
        occ.mark(_disk_points(np.array([x, y]), min(r, 1.0)))
    for cx, cy, _, hx, hy, _, yaw, _ in b.boxes:
        occ.mark(_rect_points(np.array([cx, cy]), (hx, hy), yaw, 0.3))

    if session > 0:
        n_add = int(rng.binomial(int((~is_barrel).sum()), p_add))
        candidates = np.flatnonzero(road.new)
        next_id = session * _NEW_ID_STRIDE
        for _ in range(20 * n_add):
            if next_id - session * _NEW_ID_STRIDE >= n_add:
                break
            i = int(rng.choice(candidates))
            side = 1 if rng.random() < 0.5 else -1
            if _try_pole(road, occ, b, rng, i, side, _pick_kind(rng, 0.3), next_id, clr):
                next_id += 1
    _place_dynamic(road, occ, b, rng, clr)
    return world.replace(**_arrays(b), session=session)


# --------------------------------------------------------------------------------------------
# Ray casting
# --------------------------------------------------------------------------------------------


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

    t_ground = jnp.where(dz < -1e-9, ground_z / jnp.where(dz < -1e-9, dz, -1.0), inf)[:, 0]

    # Vertical finite cylinders: infinite-cylinder interval intersected with the z slab.
    origin = jnp.zeros(3, dirs.dtype)
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
    diff = np.abs(_wrap(phi[None, :] - sec_centre[:, None]))
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


def simulate_scan(
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
    pose = _check_pose(pose_xy_yaw)
    if not isinstance(lidar, LidarSpec):
        raise ValueError(f"lidar must be a LidarSpec, got {type(lidar).__name__}")
    seed = _check_seed(seed)
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
    """Noise seed of scan ``index`` in :func:`simulate_scans`."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0])


def simulate_scans(
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
    poses = _check_poses(poses_xy_yaw, "poses_xy_yaw")
    if not isinstance(lidar, LidarSpec):
        raise ValueError(f"lidar must be a LidarSpec, got {type(lidar).__name__}")
    seed = _check_seed(seed)

    def gen() -> Iterator[UrbanScan]:
        it = range(poses.shape[0])
        if progress:
            from tqdm.auto import tqdm

            it = tqdm(it, desc="urban scans", unit="scan", mininterval=0.5)
        for i in it:
            yield _simulate(world, poses[i], lidar, scan_seed(seed, i))

    return gen()


# Alias: ``lidarjax.datasets.simulate_scans`` already names the office-world simulator.
simulate_urban_scans = simulate_scans

# --------------------------------------------------------------------------------------------
# Odometry
# --------------------------------------------------------------------------------------------


def wheel_odometry(
    trajectory_xy_yaw: np.ndarray,
    *,
    seed: int,
    sigma_trans_rel: float = 0.01,
    sigma_rot_per_m: float = float(np.deg2rad(0.2)),
    heading_bias_per_m: float = float(np.deg2rad(0.01)),
    scale_bias: float = 0.0,
) -> np.ndarray:
    """Drifting wheel odometry from ground-truth poses.

    Each relative motion ``(dx, dy, dyaw)`` between consecutive poses (in the frame of the
    first) of length ``d`` becomes ``((1 + scale_bias) dx + N(0, (sigma_trans_rel d)^2),
    (1 + scale_bias) dy + N(0, (sigma_trans_rel d)^2), dyaw + heading_bias_per_m d +
    N(0, (sigma_rot_per_m d)^2))`` and the noisy motions are chained from the first
    ground-truth pose.

    Args:
        trajectory_xy_yaw: ``[N, 3]`` ground-truth poses ``(x, y, yaw)``.
        seed: Seed, ``>= 0``.
        sigma_trans_rel: Translation noise per metre travelled (dimensionless).
        sigma_rot_per_m: Heading noise per metre travelled (rad/m).
        heading_bias_per_m: Systematic heading drift (rad/m).
        scale_bias: Relative odometry scale error.

    Returns:
        ``[N, 3]`` odometry poses; row 0 equals the ground truth's.

    Raises:
        ValueError: Bad ``trajectory_xy_yaw``, ``seed`` or a noise parameter.
    """
    gt = _check_poses(trajectory_xy_yaw, "trajectory_xy_yaw")
    seed = _check_seed(seed)
    _check_nonneg(sigma_trans_rel, "sigma_trans_rel")
    _check_nonneg(sigma_rot_per_m, "sigma_rot_per_m")
    if not math.isfinite(heading_bias_per_m):
        raise ValueError(f"heading_bias_per_m must be finite, got {heading_bias_per_m}")
    if not (math.isfinite(scale_bias) and scale_bias > -1):
        raise ValueError(f"scale_bias must be finite and > -1, got {scale_bias}")
    rng = np.random.default_rng([seed, 0x0D0])
    delta = np.diff(gt[:, :2], axis=0)
    c, s = np.cos(gt[:-1, 2]), np.sin(gt[:-1, 2])
    lx = c * delta[:, 0] + s * delta[:, 1]
    ly = -s * delta[:, 0] + c * delta[:, 1]
    dyaw = _wrap(np.diff(gt[:, 2]))
    d = np.hypot(lx, ly)
    noise = rng.standard_normal((d.size, 3))
    lx = (1 + scale_bias) * lx + sigma_trans_rel * d * noise[:, 0]
    ly = (1 + scale_bias) * ly + sigma_trans_rel * d * noise[:, 1]
    dyaw = dyaw + heading_bias_per_m * d + sigma_rot_per_m * d * noise[:, 2]
    out = np.empty_like(gt)
    out[0] = gt[0]
    yaw = np.concatenate([[gt[0, 2]], gt[0, 2] + np.cumsum(dyaw)])
    cy, sy = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    out[1:, 0] = gt[0, 0] + np.cumsum(cy * lx - sy * ly)
    out[1:, 1] = gt[0, 1] + np.cumsum(sy * lx + cy * ly)
    out[:, 2] = _wrap(yaw)
    return out


simulate_urban_scan = simulate_scan  # the name exported by lidarjax.datasets
