"""Systematic heading errors of wheel odometry, estimated against the front end.

A differential-drive robot's odometry carries two systematic heading errors (Borenstein
and Feng's UMBmark types): unequal wheel diameters turn the estimate a little with every
metre driven, and a wrong wheelbase scales every turn. Summed over a log they dominate
the odometry's heading drift: a constant ``0.3 deg/m`` is 30 degrees after 100 m. The
front end's increments are far more accurate than the odometry's, so the two systematic
terms are a robust weighted least-squares fit of the odometry's heading increments
against the front end's:

    wrap(dyaw_odo_k - dyaw_fe_k) = heading_rad_per_m * d_k + heading_gain * dyaw_odo_k + e_k

(``d_k`` the odometry increment's length in m), each increment weighted by the odometry
model's heading variance (:func:`~lidarjax.slam.odometry_sigmas`), a Cauchy kernel
scaled by the residuals' own spread (their median absolute deviation) against the front
end's failed matches, and a weak zero-mean Gaussian prior on both terms so that a log
without motion or turns leaves them at zero. The corrected odometry
subtracts them from every increment; the pose graph's and the back ends' odometry
factors then pull toward the front end's heading instead of toward the drift.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ._front_end import FrontEndConfig, _wrap, between_np, odometry_sigmas

__all__ = ["OdometryCalibration", "calibrate_odometry"]


def _poses(value, name: str) -> np.ndarray:
    a = np.asarray(value, float)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < 2:
        raise ValueError(
            f"{name} must be an [N, 3] array (x m, y m, yaw rad), N >= 2, got {a.shape}"
        )
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite (it holds NaN or inf)")
    return a


@dataclasses.dataclass(frozen=True)
class OdometryCalibration:
    """The odometry's systematic heading errors (:func:`calibrate_odometry`).

    Attributes:
        heading_rad_per_m: heading drift per metre driven (rad/m; positive: the odometry
            turns left of the truth).
        heading_gain: the share of each odometry turn that is error (dimensionless;
            0.01: the odometry reports about 1 % more turn than the truth).
        n_used: increments in the fit (those with a plausible match).
    """

    heading_rad_per_m: float = 0.0
    heading_gain: float = 0.0
    n_used: int = 0

    def increments(self, increments: np.ndarray) -> np.ndarray:
        """``[E 3]`` odometry increments ``(dx m, dy m, dyaw rad)`` with the systematic
        heading errors removed (translations unchanged)."""
        inc = np.array(increments, float, copy=True)
        if inc.ndim != 2 or inc.shape[1] != 3 or not np.all(np.isfinite(inc)):
            raise ValueError(f"increments must be a finite [E, 3] array, got {inc.shape}")
        d = np.hypot(inc[:, 0], inc[:, 1])
        inc[:, 2] = inc[:, 2] - self.heading_rad_per_m * d - self.heading_gain * inc[:, 2]
        return inc

    def apply(self, odometry_xy_yaw: np.ndarray) -> np.ndarray:
        """``[N 3]`` odometry poses re-chained from the corrected increments, starting at
        the first pose (a zero calibration gives the input back to round-off)."""
        odo = _poses(odometry_xy_yaw, "odometry_xy_yaw")
        inc = self.increments(between_np(odo[:-1], odo[1:]))
        # the SE(2) chain in closed form: headings are a running sum, and each step's
        # translation turns by the heading before it
        yaw = odo[0, 2] + np.concatenate([[0.0], np.cumsum(inc[:, 2])])
        c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
        step = np.stack([c * inc[:, 0] - s * inc[:, 1], s * inc[:, 0] + c * inc[:, 1]], 1)
        xy = odo[0, :2] + np.concatenate([np.zeros((1, 2)), np.cumsum(step, 0)])
        return np.column_stack([xy, _wrap(yaw)])


def calibrate_odometry(
    front_end_xy_yaw: np.ndarray,
    odometry_xy_yaw: np.ndarray,
    cfg: FrontEndConfig | None = None,
    *,
    valid: np.ndarray | None = None,
    prior_sigma_per_m: float = 0.05,
    prior_sigma_gain: float = 0.2,
    kernel_width: float = 2.385,
    iterations: int = 30,
) -> OdometryCalibration:
    """Fit the odometry's systematic heading errors against the front end's increments
    (module docstring).

    Args:
        front_end_xy_yaw: ``[N 3]`` the front end's poses ``(x m, y m, yaw rad)``.
        odometry_xy_yaw: ``[N 3]`` the raw odometry's poses.
        cfg: the front end's settings; their odometry model (``odometry_sigma_yaw_*``)
            weights the increments.
        valid: ``[N - 1]`` bool, the increments to use (default: all); pass
            ``FrontEndResult.plausible[1:]`` to leave out the front end's fallbacks, whose
            increments are the odometry's own.
        prior_sigma_per_m: standard deviation (rad/m) of the zero-mean prior on
            ``heading_rad_per_m``.
        prior_sigma_gain: standard deviation of the zero-mean prior on ``heading_gain``.
        kernel_width: the Cauchy kernel's width in robust standard deviations of the
            whitened residuals (1.4826 times their median absolute deviation, recomputed
            every iteration); 2.385 is 95 % efficient for Gaussian residuals.
        iterations: reweighting iterations (a fixed count), from no correction.

    Returns:
        :class:`OdometryCalibration`.

    Raises:
        ValueError: bad shapes or values, naming the argument.
    """
    cfg = FrontEndConfig() if cfg is None else cfg
    fe = _poses(front_end_xy_yaw, "front_end_xy_yaw")
    odo = _poses(odometry_xy_yaw, "odometry_xy_yaw")
    if odo.shape != fe.shape:
        raise ValueError(
            f"odometry_xy_yaw must have front_end_xy_yaw's shape {fe.shape}, got {odo.shape}"
        )
    n = fe.shape[0] - 1
    if valid is None:
        use = np.ones(n, bool)
    else:
        use = np.asarray(valid)
        if use.shape != (n,) or use.dtype != bool:
            raise ValueError(
                f"valid must be a bool array of shape ({n},), got {use.dtype} {use.shape}"
            )
    for name, v in (
        ("prior_sigma_per_m", prior_sigma_per_m),
        ("prior_sigma_gain", prior_sigma_gain),
        ("kernel_width", kernel_width),
    ):
        if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be a positive finite number, got {v!r}")
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iterations must be an int >= 1, got {iterations!r}")
    a = between_np(odo[:-1], odo[1:])[use]
    b = between_np(fe[:-1], fe[1:])[use]
    d = np.hypot(a[:, 0], a[:, 1])
    x = np.stack([d, a[:, 2]], 1)  # [E 2]
    r = _wrap(a[:, 2] - b[:, 2])  # [E]
    w0 = 1.0 / odometry_sigmas(a, cfg)[:, 2] ** 2
    prior = np.diag([1.0 / prior_sigma_per_m**2, 1.0 / prior_sigma_gain**2])
    beta = np.zeros(2)
    sw = np.sqrt(w0)
    for _ in range(iterations):
        z = (r - x @ beta) * sw
        # a floor keeps the weights finite where the residuals vanish (exact data)
        scale = max(1.4826 * float(np.median(np.abs(z))) if z.size else 0.0, 1e-9)
        w = w0 / (1.0 + (z / (kernel_width * scale)) ** 2)
        beta = np.linalg.solve(x.T @ (w[:, None] * x) + prior, x.T @ (w * r))
    return OdometryCalibration(float(beta[0]), float(beta[1]), int(use.sum()))
