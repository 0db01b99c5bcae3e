"""A KITTI pose file as a planar ground-frame vehicle trajectory (NumPy).

:func:`load_urban_trajectory` reads a KITTI odometry pose file (by default the shared
sequence 00 ground truth) and returns an :class:`UrbanTrajectory`: poses ``(x, y, yaw)``
in a right-handed ground frame with ``z`` up. The urban simulator in :mod:`lidarjax.sim`
builds its worlds around such a trajectory.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from ._kitti import load_kitti_poses, load_kitti_times

__all__ = ["CAMERA_TO_GROUND", "UrbanTrajectory", "load_urban_trajectory"]

# Rows map KITTI camera axes (x right, y down, z forward) to the ground frame (x forward,
# y left, z up): X = z_cam, Y = -x_cam, Z = -y_cam. det = +1.
CAMERA_TO_GROUND = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
CAMERA_TO_GROUND.flags.writeable = False

_KITTI_DT_S = 0.1


def _check_xy_yaw(poses: object) -> np.ndarray:
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] < 1:
        raise ValueError(f"xy_yaw must have shape [N, 3] with N >= 1, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("xy_yaw must be finite")
    return arr


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
        xy_yaw = _check_xy_yaw(self.xy_yaw)
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
