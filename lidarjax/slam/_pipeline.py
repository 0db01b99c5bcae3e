"""The whole decay-rate SLAM system: front end, loop closures, pose graph, joint back end.

:func:`run_slam` runs, on raw odometry and scans:

1. :func:`~lidarjax.slam.run_front_end` (decay-rate lidar odometry, online);
2. :func:`~lidarjax.slam.find_loops` on the front end's trajectory;
3. :func:`~lidarjax.slam.optimize_pose_graph` over the front end's increments and the loop
   closures (Cauchy-robust), which closes the loops;
4. the back end from there (``"joint"``: :func:`~lidarjax.slam.optimize_joint`, poses and
   field together; ``"alternating"``: :func:`~lidarjax.slam.optimize_alternating`; or
   ``"none"``), with the raw odometry's increments as factors.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from ._back_end import BackEndConfig, BackEndResult, optimize_alternating, optimize_joint
from ._front_end import FrontEndConfig, _check_inputs, between_np, run_front_end
from ._loops import LoopConfig, Loops, find_loops
from ._pose_graph import optimize_pose_graph

__all__ = ["SlamConfig", "SlamResult", "odometry_sigmas", "run_slam"]


@dataclasses.dataclass(frozen=True)
class SlamConfig:
    """Settings of :func:`run_slam`.

    Attributes:
        front: front-end settings (its ``odometry_sigma_*`` also weight the back end's
            odometry factors).
        loops: loop-search settings.
        back: back-end settings.
        back_end: ``"joint"``, ``"alternating"`` or ``"none"``.
        chain_sigma_xy_m, chain_sigma_yaw_rad: standard deviations of the front end's
            increments in the pose graph.
        loop_sigma_xy_m, loop_sigma_yaw_rad: of the loop closures.
        cauchy_scale: Cauchy kernel scale of the loop closures (whitened units).
    """

    front: FrontEndConfig = dataclasses.field(default_factory=FrontEndConfig)
    loops: LoopConfig = dataclasses.field(default_factory=LoopConfig)
    back: BackEndConfig = dataclasses.field(default_factory=BackEndConfig)
    back_end: str = "joint"
    chain_sigma_xy_m: float = 0.05
    chain_sigma_yaw_rad: float = 0.01
    loop_sigma_xy_m: float = 0.1
    loop_sigma_yaw_rad: float = 0.02
    cauchy_scale: float = 1.0

    def __post_init__(self):
        if self.back_end not in ("joint", "alternating", "none"):
            raise ValueError(
                f"back_end must be 'joint', 'alternating' or 'none', got {self.back_end!r}"
            )
        for name in (
            "chain_sigma_xy_m",
            "chain_sigma_yaw_rad",
            "loop_sigma_xy_m",
            "loop_sigma_yaw_rad",
            "cauchy_scale",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")


@dataclasses.dataclass(frozen=True)
class SlamResult:
    """Output of :func:`run_slam`; poses are ``[N 3]`` ``(x m, y m, yaw rad)``.

    Attributes:
        poses: the final estimate (after the back end, or the pose graph for ``"none"``).
        front_end_poses: the front end's.
        pose_graph_poses: after the pose graph.
        loops: the accepted loop closures.
        back_end: the back end's result (None for ``"none"``).
        seconds: wall time per stage (s): ``front_end``, ``loops``, ``pose_graph``,
            ``back_end``.
        front_end_seconds_per_scan: ``[N]``.
    """

    poses: np.ndarray
    front_end_poses: np.ndarray
    pose_graph_poses: np.ndarray
    loops: Loops
    back_end: BackEndResult | None
    seconds: dict
    front_end_seconds_per_scan: np.ndarray


def odometry_sigmas(increments: np.ndarray, cfg: FrontEndConfig) -> np.ndarray:
    """``[E 3]`` standard deviations (m, m, rad) of ``[E 3]`` odometry increments under the
    front end's noise model (``cfg.odometry_sigma_*``)."""
    inc = np.asarray(increments, float)
    d = np.hypot(inc[:, 0], inc[:, 1])
    sxy = cfg.odometry_sigma_xy_m + cfg.odometry_sigma_rel * d
    syaw = (
        cfg.odometry_sigma_yaw_rad
        + cfg.odometry_sigma_yaw_per_m * d
        + cfg.odometry_sigma_yaw_rel * np.abs(inc[:, 2])
    )
    return np.stack([sxy, sxy, syaw], 1)


def run_slam(
    ranges_m: np.ndarray,
    azimuths_rad: np.ndarray,
    odometry_xy_yaw: np.ndarray,
    cfg: SlamConfig | None = None,
    *,
    progress: bool = False,
) -> SlamResult:
    """Decay-rate SLAM from raw odometry and 2-D scans (module docstring).

    Args:
        ranges_m: ``[N B]`` readings (m); no-returns as the sensor's maximum reading.
        azimuths_rad: ``[B]`` beam angles (rad).
        odometry_xy_yaw: ``[N 3]`` raw odometry poses; the estimate starts at its first.
        cfg: settings.
        progress: tqdm progress bars.

    Returns:
        :class:`SlamResult`.
    """
    cfg = SlamConfig() if cfg is None else cfg
    rng, az, odo = _check_inputs(ranges_m, azimuths_rad, odometry_xy_yaw)
    n = rng.shape[0]
    secs = {}
    fe = run_front_end(rng, az, odo, cfg.front, progress=progress)
    secs["front_end"] = fe.seconds
    t = time.perf_counter()
    loops = find_loops(rng, az, fe.poses, cfg.loops, cfg.front, progress=progress)
    secs["loops"] = time.perf_counter() - t
    t = time.perf_counter()
    if n > 1:
        chain = np.stack([np.arange(n - 1), np.arange(1, n)], 1)
        inc = between_np(fe.poses[:-1], fe.poses[1:])
        sig = np.tile(
            [cfg.chain_sigma_xy_m, cfg.chain_sigma_xy_m, cfg.chain_sigma_yaw_rad], (n - 1, 1)
        )
        lsig = np.tile(
            [cfg.loop_sigma_xy_m, cfg.loop_sigma_xy_m, cfg.loop_sigma_yaw_rad],
            (len(loops.edges), 1),
        )
        pg = optimize_pose_graph(
            fe.poses,
            np.concatenate([chain, loops.edges]).astype(np.int32),
            np.concatenate([inc, loops.measurements]),
            np.concatenate([sig, lsig]),
            robust=np.concatenate([np.zeros(n - 1, bool), np.ones(len(loops.edges), bool)]),
            cauchy_scale=cfg.cauchy_scale,
        )
        pg_poses = np.asarray(pg.poses, float)
    else:
        pg_poses = fe.poses.copy()
    secs["pose_graph"] = time.perf_counter() - t
    back = None
    poses = pg_poses
    secs["back_end"] = 0.0
    if cfg.back_end != "none" and n > 1:
        edges = np.stack([np.arange(n - 1), np.arange(1, n)], 1)
        inc = between_np(odo[:-1], odo[1:])
        f = optimize_joint if cfg.back_end == "joint" else optimize_alternating
        back = f(pg_poses, az, rng, edges, inc, odometry_sigmas(inc, cfg.front), cfg.back)
        poses = back.poses
        secs["back_end"] = back.seconds
    return SlamResult(poses, fe.poses, pg_poses, loops, back, secs, fe.seconds_per_scan)
