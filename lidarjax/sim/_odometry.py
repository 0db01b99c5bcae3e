"""Drifting wheel odometry from ground-truth planar poses (NumPy)."""

from __future__ import annotations

import math

import numpy as np

from ._urban_common import check_nonneg, check_poses, check_seed, wrap_angle

__all__ = ["wheel_odometry"]


def wheel_odometry(
    trajectory_xy_yaw: np.ndarray,
    *,
    seed: int,
    sigma_trans_rel: float = 0.01,
    sigma_rot_per_m: float = float(np.deg2rad(0.2)),
    heading_bias_per_m: float = float(np.deg2rad(0.01)),
    scale_bias: float = 0.0,
    sigma_rot_per_rad: float = 0.0,
) -> np.ndarray:
    """Drifting wheel odometry from ground-truth poses.

    Each relative motion ``(dx, dy, dyaw)`` between consecutive poses (in the frame of the
    first) of length ``d`` becomes ``((1 + scale_bias) dx + N(0, (sigma_trans_rel d)^2),
    (1 + scale_bias) dy + N(0, (sigma_trans_rel d)^2), dyaw + heading_bias_per_m d +
    N(0, (sigma_rot_per_m d + sigma_rot_per_rad |dyaw|)^2))`` and the noisy motions are
    chained from the first ground-truth pose. The rotation term ``sigma_rot_per_rad``
    (default 0) makes turning on the spot drift too, as indoor robots' odometry does.

    Args:
        trajectory_xy_yaw: ``[N, 3]`` ground-truth poses ``(x, y, yaw)``.
        seed: Seed, ``>= 0``.
        sigma_trans_rel: Translation noise per metre travelled (dimensionless).
        sigma_rot_per_m: Heading noise per metre travelled (rad/m).
        heading_bias_per_m: Systematic heading drift (rad/m).
        scale_bias: Relative odometry scale error.
        sigma_rot_per_rad: Heading noise per radian turned (dimensionless).

    Returns:
        ``[N, 3]`` odometry poses; row 0 equals the ground truth's.

    Raises:
        ValueError: Bad ``trajectory_xy_yaw``, ``seed`` or a noise parameter.
    """
    gt = check_poses(trajectory_xy_yaw, "trajectory_xy_yaw")
    seed = check_seed(seed)
    check_nonneg(sigma_trans_rel, "sigma_trans_rel")
    check_nonneg(sigma_rot_per_m, "sigma_rot_per_m")
    check_nonneg(sigma_rot_per_rad, "sigma_rot_per_rad")
    if not math.isfinite(heading_bias_per_m):
        raise ValueError(f"heading_bias_per_m must be finite, got {heading_bias_per_m}")
    if not (math.isfinite(scale_bias) and scale_bias > -1):
        raise ValueError(f"scale_bias must be finite and > -1, got {scale_bias}")
    rng = np.random.default_rng([seed, 0x0D0])
    delta = np.diff(gt[:, :2], axis=0)
    c, s = np.cos(gt[:-1, 2]), np.sin(gt[:-1, 2])
    lx = c * delta[:, 0] + s * delta[:, 1]
    ly = -s * delta[:, 0] + c * delta[:, 1]
    dyaw = wrap_angle(np.diff(gt[:, 2]))
    d = np.hypot(lx, ly)
    noise = rng.standard_normal((d.size, 3))
    lx = (1 + scale_bias) * lx + sigma_trans_rel * d * noise[:, 0]
    ly = (1 + scale_bias) * ly + sigma_trans_rel * d * noise[:, 1]
    sigma_rot = sigma_rot_per_m * d + sigma_rot_per_rad * np.abs(dyaw)
    dyaw = dyaw + heading_bias_per_m * d + sigma_rot * noise[:, 2]
    out = np.empty_like(gt)
    out[0] = gt[0]
    yaw = np.concatenate([[gt[0, 2]], gt[0, 2] + np.cumsum(dyaw)])
    cy, sy = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    out[1:, 0] = gt[0, 0] + np.cumsum(cy * lx - sy * ly)
    out[1:, 1] = gt[0, 1] + np.cumsum(sy * lx + cy * ly)
    out[:, 2] = wrap_angle(yaw)
    return out
