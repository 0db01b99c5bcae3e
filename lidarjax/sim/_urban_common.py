"""Object kinds, argument checks and angle helpers shared by the urban simulator modules."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["BOX_KINDS", "POLE_KINDS"]

POLE_KINDS = ("street_lamp", "sign_post", "traffic_light", "tree_trunk", "barrel")
BOX_KINDS = ("facade", "parked_car", "moving_car", "pedestrian")

_LAMP, _SIGN, _TLIGHT, _TREE, _BARREL = range(5)
_FACADE, _PARKED, _MOVING, _PEDESTRIAN = range(4)


def check_seed(seed: object, name: str = "seed") -> int:
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or int(seed) < 0:
        raise ValueError(f"{name} must be a non-negative integer, got {seed!r}")
    return int(seed)


def check_poses(poses: object, name: str) -> np.ndarray:
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] < 1:
        raise ValueError(f"{name} must have shape [N, 3] with N >= 1, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    return arr


def check_pose(pose: object, name: str = "pose_xy_yaw") -> np.ndarray:
    arr = np.asarray(pose, dtype=np.float64)
    if arr.shape != (3,):
        raise ValueError(f"{name} must have shape [3] (x, y, yaw), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr.tolist()}")
    return arr


def check_nonneg(value: float, name: str) -> float:
    value = float(value)
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"{name} must be finite and >= 0, got {value}")
    return value


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi
