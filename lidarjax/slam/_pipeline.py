"""The whole decay-rate SLAM system: front end, loop closures, pose graph, joint back end.

:func:`run_slam` runs, on raw odometry and scans:

1. :func:`~lidarjax.slam.run_front_end` (decay-rate lidar odometry, online), a second
   front end with the endpoint model and a point-to-line ICP chain
   (:func:`~lidarjax.slam.point_icp_front_end`; ``SlamConfig.extra_chain_models``);
2. :func:`~lidarjax.slam.find_loops` and :func:`~lidarjax.slam.find_revisits` on the
   front end's trajectory;
3. :func:`front_end_pose_graph`: :func:`~lidarjax.slam.optimize_pose_graph` over the
   front ends' increments, the loop closures and the revisits (all Cauchy-robust) and the
   odometry's increments (without their systematic heading errors, fitted against the
   front end by :func:`~lidarjax.slam.calibrate_odometry`), which closes the loops; with
   ``loop_rounds > 1`` the loop search runs again along the pose graph's trajectory and
   the graph is solved again;
4. the back end from there (``"joint"``: :func:`~lidarjax.slam.optimize_joint`, poses and
   field together; ``"alternating"``: :func:`~lidarjax.slam.optimize_alternating`; or
   ``"none"``), with the same odometry's increments as factors.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from ._back_end import BackEndConfig, BackEndResult, optimize_alternating, optimize_joint
from ._baselines import _icp_chain, _import_small_gicp
from ._calibration import OdometryCalibration, calibrate_odometry
from ._front_end import (
    MATCHING_MODELS,
    FrontEndConfig,
    _check_inputs,
    between_np,
    odometry_sigmas,
    run_front_end,
)
from ._loops import LoopConfig, Loops, find_loops, find_revisits
from ._point_icp import PointIcpConfig, point_icp_chain
from ._pose_graph import PoseGraphResult, optimize_pose_graph

__all__ = [
    "CHAIN_MODELS",
    "REJECTED_WEIGHT",
    "SlamConfig",
    "SlamResult",
    "front_end_pose_graph",
    "run_slam",
]

CHAIN_MODELS = (*MATCHING_MODELS, "icp", "gicp")
"""What :attr:`SlamConfig.extra_chain_models` may name: a front end with a matching
model (:data:`~lidarjax.slam.MATCHING_MODELS`); ``"icp"``, point-to-line ICP
scan-to-submap registration in JAX (:func:`~lidarjax.slam.point_icp_front_end`,
settings :attr:`SlamConfig.icp`); or ``"gicp"``, small_gicp's scan-to-submap
registration (:func:`~lidarjax.slam.icp_front_end`, the classical baseline's front end;
needs small_gicp, ``pip install 'lidarjax[slam]'``)."""

GICP_VOXEL_M = 0.05
"""Voxel size (m) of the ``"gicp"`` chain's downsampling (:func:`~lidarjax.slam.icp_front_end`'s
default, as the baseline runs)."""


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
        cauchy_scale: Cauchy kernel scale of the loop closures (and, with
            ``robust_chain``, of the front end's increments), in whitened units.
        robust_chain: the front end's increments get the Cauchy kernel too, and the raw
            odometry's increments join the graph as plain factors weighted by the front
            end's odometry model (:func:`odometry_sigmas`); False: the front end's
            increments as plain factors, no odometry. A whole-map front end snaps onto
            an earlier visit in one increment, and its loop closures then agree with it,
            so a graph of plain increments stays where the front end is (ATE intel
            0.196 -> 0.192 m). With the robust chain the snap's increment is down-weighted,
            the odometry bridges it, and the loops spread the correction over the loop:
            pose graph ATE on the shared logs (drift seed 0) intel 0.192 -> 0.076 m,
            fhw 0.358 -> 0.138 m, orebro 0.356 -> 0.276 m (seed 1: intel 0.209 ->
            0.095 m). Where no loop closure spans a snap, only ``revisits`` keep it.
        revisits: add :func:`~lidarjax.slam.find_revisits`'s pairs (the front end's own
            relative poses where it put two visits on the same walls) as Cauchy-robust
            factors with the loop sigmas times ``revisit_sigma_scale``. Without them the
            robust chain gives up every snap no loop closure spans: on the shared logs'
            front ends (drift seed 0) with no loop closures, pose graph ATE intel 0.791 m,
            orebro 0.784 m against the front end's 0.196 and 0.366 m; with the revisits
            alone 0.076 and 0.272 m. For a whole-map front end only: a local map's
            (``FrontEndConfig.local_map_scans > 0``) never matched two visits to each
            other, so its relative pose between them is no measurement (intel, fhw, drift
            seed 0, 30 scans: with them 0.061 and 0.160 m, without 0.060 and 0.150 m).
            None (default): on exactly when ``front.local_map_scans`` is 0
            (:attr:`uses_revisits`).
        revisit_min_overlap, revisit_cell_m: ``min_overlap`` and ``cell_m`` of
            :func:`~lidarjax.slam.find_revisits` (its candidates are ``loops``').
        revisit_sigma_scale: the revisits' sigmas over the loop closures' (> 1: a fresh
            match outweighs the front end's own belief where they disagree).
        loop_rounds: rounds of loop search (>= 1). Round ``r > 1`` searches again along
            the pose graph of round ``r - 1`` (pairs already closed, and candidate pairs
            whose relative pose has barely moved since the last round, see
            ``LoopConfig.retry_xy_m``, are not matched again), adds the new loops and
            solves the pose graph again; it stops early when a round finds none. The
            pose graph brings a drifted revisit within the loop search's reach. Pose
            graph ATE, one round -> two, on the shared logs (20 m range cap, 256 nodes
            per ray, drift seeds 0-2 on orebro, 0-1 on fhw): orebro 0.763 / 0.292 /
            0.379 -> 0.326 / 0.292 / 0.376 m, fhw 0.166 / 0.135 -> 0.165 / 0.138 m (10 m
            cap: fhw seed 0 0.195 -> 0.132 m, orebro seed 0 0.715 -> 0.737 m).
        calibrate_odometry: before the loop search, fit the odometry's systematic
            heading errors (drift per metre, error per radian turned) against the front
            end's increments (:func:`~lidarjax.slam.calibrate_odometry`, the front end's
            fallbacks left out) and give the pose graph and the back end the corrected
            odometry. The odometry factors otherwise pull the heading toward the drift
            wherever the Cauchy-robust chain gives way: edmonton (drift seeds 0-2, a
            log nobody tuned to) 0.733 / 1.106 / 1.324 -> 0.397 / 0.800 / 0.961 m,
            freiburg-101 0.053 / 0.055 / 0.048 -> 0.049 / 0.050 / 0.047 m; intel, fhw
            and orebro (six seeds) within 2 mm by mean. The front end still predicts
            from the raw odometry.
        extra_chain_models: front-end models (:data:`CHAIN_MODELS`: ``"decay_rate"``,
            ``"endpoint"``, ``"icp"``, ``"gicp"``) run as further front ends, with
            ``front``'s settings otherwise (``"icp"``:
            :func:`~lidarjax.slam.point_icp_front_end` with :attr:`icp`, and ``"gicp"``:
            :func:`~lidarjax.slam.icp_front_end`, on the readings below
            ``front.range_cap_m``, their rejected registrations left out of the graph),
            each an independent lidar odometry from the same raw odometry. Their increments
            join the pose graph as further Cauchy-robust chains; with ``k`` chains in all,
            every chain's sigmas are ``sqrt(k)`` times ``chain_sigma_*`` (chains that agree
            weigh as one). Where one front end fails and a loop closure or the odometry
            rejects its increment, another front end's increment bridges the gap instead of
            the odometry alone. The loop search, the calibration, the graph's starting poses
            and the back end follow the first front end (``front``). Needs ``robust_chain``.
            None (default): the other matching model and the ICP chain
            (:attr:`chain_models`: endpoint and ICP front ends beside a decay-rate one,
            decay-rate and ICP beside an endpoint one); ``()``: one chain. Pose graph ATE,
            mean (docs/results/slam.md): the endpoint chain beside the decay-rate one (stop
            64, six drift seeds) orebro 0.242 -> 0.177 m (better on all six), intel 0.063
            -> 0.061 m, fhw 0.128 -> 0.138 m (worse on all six); on logs nobody tuned to
            edmonton 0.719 -> 0.521, freiburg-101 0.049 -> 0.045, csail 0.144 -> 0.129,
            belgioioso 0.090 -> 0.084 m. The ICP chain added (stop 68, 17 runs re-solved)
            intel 0.053 -> 0.050 m (2 seeds), fhw 0.133 -> 0.123 m (3), orebro 0.177 ->
            0.158 m (6), edmonton 0.525 -> 0.415 m (3), freiburg-101, csail and belgioioso
            (1 each) 0.045 -> 0.045, 0.131 -> 0.101 and 0.074 -> 0.070 m: better on 13
            runs, worse on 4; it costs 2-8 s a log.
        short_loop_separation: > 0 (at least 3): after the loop rounds, a further loop
            search along the pose graph matches every scan against the submap of the
            nearest earlier scan at least this many scans back
            (:attr:`short_loop_config`; pairs already closed are skipped, and the
            log's level is the loop rounds'), and the graph is solved once more with
            the loop closures it accepts. Each is a fresh match of a scan against a few
            scans placed by the pose graph, independent of the front ends' chains: a
            further measurement across every stretch of them. They are appended to
            ``SlamResult.loops`` (the last ``SlamResult.n_short_loops``). 0 (default):
            off. At 7 (stop 65, re-solves of stop 64's runs; docs/results/slam.md),
            mean over six drift seeds: orebro 0.177 -> 0.163 m (better on four), intel
            0.061 -> 0.059 m (six), fhw 0.138 -> 0.140 m (worse on five); on logs nobody
            tuned to freiburg-101 0.045 -> 0.040, csail 0.129 -> 0.112, belgioioso 0.084
            -> 0.079, edmonton 0.521 -> 0.527 m (better on seven runs of ten). It adds a
            match per scan: 0.9-1.9 times the first loop search's time
            (benchmarks/slam_short_loops.py).
        icp: the ``"icp"`` chain's settings (:class:`~lidarjax.slam.PointIcpConfig`).
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
    robust_chain: bool = True
    revisits: bool | None = None
    revisit_min_overlap: float = 0.5
    revisit_cell_m: float = 0.1
    revisit_sigma_scale: float = 4.0
    loop_rounds: int = 2
    calibrate_odometry: bool = True
    extra_chain_models: tuple[str, ...] | None = None
    short_loop_separation: int = 0
    icp: PointIcpConfig = dataclasses.field(default_factory=PointIcpConfig)

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
            "revisit_cell_m",
            "revisit_sigma_scale",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")
        if not isinstance(self.robust_chain, bool):
            raise ValueError(f"robust_chain must be a bool, got {self.robust_chain!r}")
        if not isinstance(self.calibrate_odometry, bool):
            raise ValueError(f"calibrate_odometry must be a bool, got {self.calibrate_odometry!r}")
        if self.revisits is not None and not isinstance(self.revisits, bool):
            raise ValueError(f"revisits must be a bool or None, got {self.revisits!r}")
        v = self.loop_rounds
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"loop_rounds must be an int >= 1, got {v!r}")
        v = self.revisit_min_overlap
        if not (isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v <= 1):
            raise ValueError(f"revisit_min_overlap must be in (0, 1], got {v!r}")
        if not isinstance(self.icp, PointIcpConfig):
            raise ValueError(f"icp must be a PointIcpConfig, got {type(self.icp).__name__}")
        v = self.short_loop_separation
        if isinstance(v, bool) or not isinstance(v, int) or not (v == 0 or v >= 3):
            raise ValueError(f"short_loop_separation must be 0 (off) or an int >= 3, got {v!r}")
        v = self.extra_chain_models
        if v is not None and (not isinstance(v, tuple) or any(m not in CHAIN_MODELS for m in v)):
            raise ValueError(
                f"extra_chain_models must be None or a tuple of models from "
                f"{CHAIN_MODELS}, got {v!r}"
            )
        if v is not None and len(set(v)) != len(v):
            raise ValueError(f"extra_chain_models must not repeat a model, got {v!r}")
        if v and not self.robust_chain:
            raise ValueError(
                "extra_chain_models needs robust_chain=True (the chains are weighed against "
                "each other through the Cauchy kernel and the odometry factors); set "
                "extra_chain_models=() for a plain chain"
            )

    @property
    def chain_models(self) -> tuple[str, ...]:
        """The models of :func:`run_slam`'s further front ends: ``extra_chain_models``
        if set, else the matching model other than ``front.model`` and ``"icp"`` when
        ``robust_chain`` (none without it)."""
        if self.extra_chain_models is not None:
            return self.extra_chain_models
        if not self.robust_chain:
            return ()
        return (*(m for m in MATCHING_MODELS if m != self.front.model), "icp")

    @property
    def short_loop_config(self) -> LoopConfig:
        """The short loop search's settings (``short_loop_separation`` > 0): ``loops``
        with ``min_separation`` ``short_loop_separation``, ``submap_half``
        ``(short_loop_separation - 1) // 2``, every scan, and neither the wide nor the
        far search (the pose graph's poses are close)."""
        s = max(self.short_loop_separation, 3)
        return dataclasses.replace(
            self.loops,
            min_separation=s,
            submap_half=(s - 1) // 2,
            every=1,
            wide_search_xy_m=0.0,
            far_radius_m=0.0,
        )

    @property
    def uses_revisits(self) -> bool:
        """Whether :func:`run_slam` adds the revisits: ``revisits`` if set, else whether
        the front end matches against every scan so far (``front.local_map_scans == 0``)."""
        if self.revisits is not None:
            return self.revisits
        return self.front.local_map_scans == 0


@dataclasses.dataclass(frozen=True)
class SlamResult:
    """Output of :func:`run_slam`; poses are ``[N 3]`` ``(x m, y m, yaw rad)``.

    Attributes:
        poses: the final estimate (after the back end, or the pose graph for ``"none"``).
        front_end_poses: the front end's.
        pose_graph_poses: after the pose graph.
        loops: the accepted loop closures (of every round).
        revisits: :func:`~lidarjax.slam.find_revisits`'s pairs (empty without
            ``cfg.uses_revisits``).
        back_end: the back end's result (None for ``"none"``).
        seconds: wall time per stage (s): ``front_end``, ``extra_front_ends``, ``loops`` (with the
            revisits), ``short_loops``, ``pose_graph``, ``back_end``.
        front_end_seconds_per_scan: ``[N]``.
        front_end_n_used: ``[N]`` rays in each match's objective (0 for the first scan).
        front_end_information: ``[N 3 3]`` each match's information (``FrontEndResult
            .information``: the scan's log-likelihood alone, rays taken as independent, so
            over-confident; zeros for the first scan).
        front_end_plausible: ``[N]`` bool, False where the match failed the gate and the
            front end fell back (a match under a tighter prior, or the odometry's
            prediction; ``FrontEndResult.plausible``).
        odometry_calibration: the odometry's systematic heading errors fitted against
            the front end (None without ``cfg.calibrate_odometry``).
        odometry: ``[N 3]`` the odometry the pose graph and the back end used (the raw
            odometry corrected by ``odometry_calibration``, or the raw odometry).
        extra_front_end_poses: ``[N 3]`` poses of each of ``cfg.chain_models``'s
            front ends, in that order (empty without them); their wall time is
            ``seconds["extra_front_ends"]``.
        loop_weights: ``[L]`` the final pose graph's weight of each of ``loops``
            (:attr:`PoseGraphResult.edge_weights`: ``1 / (1 + s^2 / c^2)`` for a whitened
            residual ``s`` and the Cauchy scale ``c``): near 1 the graph kept the loop
            closure, below :data:`REJECTED_WEIGHT` it took it for an outlier. Empty for
            a single scan.
        revisit_weights: ``[R]`` the same for ``revisits``.
        chain_weights: ``[1 + len(extra_front_end_poses), N - 1]`` the final pose
            graph's weight of each front end's increment ``k -> k + 1``, the first front
            end's row first, then ``cfg.chain_models``'s: a weight below
            :data:`REJECTED_WEIGHT` marks an increment the loops and the other factors
            overruled (a failed match); all 1 without ``cfg.robust_chain`` (plain
            factors); NaN where an increment is not in the graph
            (``extra_chain_valid``).
        pose_graph_cost: the final pose graph's robust cost
            (:attr:`PoseGraphResult.cost`; 0.0 for a single scan).
        n_short_loops: how many of ``loops`` (the last ones) the short loop search
            found (``SlamConfig.short_loop_separation``; 0 without it); its wall time
            is ``seconds["short_loops"]``.
        extra_chain_valid: ``[N - 1]`` bool per extra front end (the order of
            ``extra_front_end_poses``): the increments in the pose graph. All True for
            a matching model's front end; for ``"gicp"`` the accepted registrations
            (:attr:`~lidarjax.slam.IcpFrontEndResult.registered`), its other rows
            having taken the raw odometry's increment. ``chain_weights`` is NaN where
            an increment is not in the graph.
    """

    poses: np.ndarray
    front_end_poses: np.ndarray
    pose_graph_poses: np.ndarray
    loops: Loops
    revisits: Loops
    back_end: BackEndResult | None
    seconds: dict
    front_end_seconds_per_scan: np.ndarray
    front_end_n_used: np.ndarray | None = None
    front_end_information: np.ndarray | None = None
    front_end_plausible: np.ndarray | None = None
    odometry_calibration: OdometryCalibration | None = None
    odometry: np.ndarray | None = None
    extra_front_end_poses: tuple[np.ndarray, ...] = ()
    loop_weights: np.ndarray | None = None
    revisit_weights: np.ndarray | None = None
    chain_weights: np.ndarray | None = None
    pose_graph_cost: float = 0.0
    n_short_loops: int = 0
    extra_chain_valid: tuple[np.ndarray, ...] = ()


def front_end_pose_graph(
    front_end_poses: np.ndarray,
    odometry_xy_yaw: np.ndarray,
    loops: Loops,
    cfg: SlamConfig | None = None,
    revisits: Loops | None = None,
    extra_chains: tuple[np.ndarray, ...] | list[np.ndarray] = (),
    extra_chain_valid: tuple[np.ndarray | None, ...] | list[np.ndarray | None] | None = None,
) -> PoseGraphResult:
    """The pose graph of :func:`run_slam`'s step 3, started at the front end's poses.

    Edges: the front end's increments ``(k, k + 1)`` (``cfg.chain_sigma_*``, times
    ``sqrt(1 + len(extra_chains))``), the loop
    closures (``cfg.loop_sigma_*``, Cauchy-robust), the revisits if given (the loop
    sigmas times ``cfg.revisit_sigma_scale``, Cauchy-robust) and, with
    ``cfg.robust_chain``, the odometry's increments (:func:`odometry_sigmas` of
    ``cfg.front``), the front end's increments then Cauchy-robust too (see
    :class:`SlamConfig`).

    Args:
        front_end_poses: ``[N 3]`` the front end's poses ``(x m, y m, yaw rad)``, N >= 2.
        odometry_xy_yaw: ``[N 3]`` odometry poses (used with ``cfg.robust_chain``;
            :func:`run_slam` passes them calibrated, ``SlamResult.odometry``).
        loops: the loop closures (:func:`~lidarjax.slam.find_loops`).
        cfg: settings.
        revisits: :func:`~lidarjax.slam.find_revisits` on ``front_end_poses`` (None:
            none; :func:`run_slam` passes them with ``cfg.uses_revisits``).
        extra_chains: ``[N 3]`` poses of further front ends (:attr:`SlamConfig.chain_models`),
            each a further Cauchy-robust chain of increments.
        extra_chain_valid: one ``[N - 1]`` bool mask (or None: all) per extra chain, the
            increments that join the graph (a ``"gicp"`` chain's rejected registrations,
            which took the raw odometry's increment, do not); None: all of every chain.

    Returns:
        :class:`~lidarjax.slam.PoseGraphResult`; its ``edge_weights`` are ordered chain,
        loops, revisits, odometry, then each extra chain's valid increments.
    """
    cfg = SlamConfig() if cfg is None else cfg
    fe = np.asarray(front_end_poses, float)
    odo = np.asarray(odometry_xy_yaw, float)
    if fe.ndim != 2 or fe.shape[1] != 3 or fe.shape[0] < 2 or not np.all(np.isfinite(fe)):
        raise ValueError(f"front_end_poses must be a finite [N, 3] array, N >= 2, got {fe.shape}")
    if odo.shape != fe.shape or not np.all(np.isfinite(odo)):
        raise ValueError(
            f"odometry_xy_yaw must be a finite {list(fe.shape)} array like front_end_poses, "
            f"got {odo.shape}"
        )
    extra = list(extra_chains)
    for i, c in enumerate(extra):
        c = np.asarray(c, float)
        if c.shape != fe.shape or not np.all(np.isfinite(c)):
            raise ValueError(
                f"extra_chains[{i}] must be a finite {list(fe.shape)} array like "
                f"front_end_poses, got {c.shape}"
            )
        extra[i] = c
    if extra and not cfg.robust_chain:
        raise ValueError("extra_chains needs cfg.robust_chain=True")
    n = fe.shape[0]
    valid = _chain_masks(extra_chain_valid, len(extra), n)
    chain = np.stack([np.arange(n - 1), np.arange(1, n)], 1)
    edges = [chain, np.asarray(loops.edges).reshape(-1, 2)]
    meas = [between_np(fe[:-1], fe[1:]), np.asarray(loops.measurements, float).reshape(-1, 3)]
    chain_sig = math.sqrt(1 + len(extra)) * np.array(
        [cfg.chain_sigma_xy_m, cfg.chain_sigma_xy_m, cfg.chain_sigma_yaw_rad]
    )
    sig = [
        np.tile(chain_sig, (n - 1, 1)),
        np.tile(
            [cfg.loop_sigma_xy_m, cfg.loop_sigma_xy_m, cfg.loop_sigma_yaw_rad],
            (len(edges[1]), 1),
        ),
    ]
    robust = [np.full(n - 1, cfg.robust_chain), np.ones(len(edges[1]), bool)]
    if revisits is not None:
        re = np.asarray(revisits.edges).reshape(-1, 2)
        rm = np.asarray(revisits.measurements, float).reshape(-1, 3)
        if re.shape[0] != rm.shape[0] or (re.size and (re.min() < 0 or re.max() >= n)):
            raise ValueError(
                f"revisits must pair indices in [0, {n}) with one measurement each, got "
                f"edges {re.shape} and measurements {rm.shape}"
            )
        s = cfg.revisit_sigma_scale
        edges.append(re)
        meas.append(rm)
        sig.append(
            np.tile([s * cfg.loop_sigma_xy_m] * 2 + [s * cfg.loop_sigma_yaw_rad], (len(re), 1))
        )
        robust.append(np.ones(len(re), bool))
    if cfg.robust_chain:
        inc = between_np(odo[:-1], odo[1:])
        edges.append(chain)
        meas.append(inc)
        sig.append(odometry_sigmas(inc, cfg.front))
        robust.append(np.zeros(n - 1, bool))
    for c, ok in zip(extra, valid):
        edges.append(chain[ok])
        meas.append(between_np(c[:-1], c[1:])[ok])
        sig.append(np.tile(chain_sig, (int(ok.sum()), 1)))
        robust.append(np.ones(int(ok.sum()), bool))
    return optimize_pose_graph(
        fe,
        np.concatenate(edges).astype(np.int32),
        np.concatenate(meas),
        np.concatenate(sig),
        robust=np.concatenate(robust),
        cauchy_scale=cfg.cauchy_scale,
    )


def _chain_masks(extra_chain_valid, n_extra: int, n: int) -> list[np.ndarray]:
    """The ``[N - 1]`` bool mask of each extra chain's increments in the graph (checked)."""
    if extra_chain_valid is None:
        return [np.ones(n - 1, bool)] * n_extra
    masks = list(extra_chain_valid)
    if len(masks) != n_extra:
        raise ValueError(
            f"extra_chain_valid must hold one mask per extra chain ({n_extra}), got {len(masks)}"
        )
    for i, m in enumerate(masks):
        if m is None:
            masks[i] = np.ones(n - 1, bool)
            continue
        m = np.asarray(m)
        if m.shape != (n - 1,) or m.dtype != bool:
            raise ValueError(
                f"extra_chain_valid[{i}] must be a bool array of shape [{n - 1}] (one per "
                f"increment), got {m.dtype} {m.shape}"
            )
        masks[i] = m
    return masks


def _joined(loops: Loops, more: Loops) -> Loops:
    """``loops`` followed by ``more`` (a later search along the same front end's level:
    its ``scene_level``)."""
    return Loops(
        np.concatenate([loops.edges, more.edges]),
        np.concatenate([loops.measurements, more.measurements]),
        loops.n_tried + more.n_tried,
        more.scene_level,
    )


REJECTED_WEIGHT = 0.1
"""A pose-graph edge whose final weight (:attr:`PoseGraphResult.edge_weights`) is below
this was taken for an outlier: its whitened residual is over 3 Cauchy scales (``1 / (1 +
3^2) = 0.1``), where a factor that fits has weight near 1."""


def _split_weights(pg, n, loops, revisits, robust_chain, valid):
    """``(loop_weights, revisit_weights, chain_weights, cost)`` of
    :func:`front_end_pose_graph`'s result ``pg`` (edge order: chain, loops, revisits,
    odometry, extra chains' valid increments; ``valid``: their ``[N - 1]`` masks, NaN
    weights where an increment is not in the graph); empty arrays and cost 0 for ``pg``
    None (a single scan)."""
    n_extra = len(valid)
    n_l, n_r = (
        len(np.asarray(loops.edges).reshape(-1, 2)),
        len(np.asarray(revisits.edges).reshape(-1, 2)),
    )
    if pg is None:
        return np.zeros(0), np.zeros(0), np.ones((1 + n_extra, max(n - 1, 0))), 0.0
    w = np.asarray(pg.edge_weights, float)
    m = n - 1
    expect = m * (1 + int(robust_chain)) + sum(int(v.sum()) for v in valid) + n_l + n_r
    if w.shape != (expect,):
        raise RuntimeError(f"pose graph has {w.shape} edge weights, expected {expect}")
    rows = [w[:m]]
    lw, rw = w[m : m + n_l], w[m + n_l : m + n_l + n_r]
    at = m + n_l + n_r + m * int(robust_chain)
    for v in valid:
        row = np.full(m, np.nan)
        row[v] = w[at : at + int(v.sum())]
        rows.append(row)
        at += int(v.sum())
    return lw, rw, np.stack(rows), float(pg.cost)


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
    if "gicp" in cfg.chain_models:
        _import_small_gicp()  # before the front ends' minutes, not after
    n = rng.shape[0]
    secs = {}
    fe = run_front_end(rng, az, odo, cfg.front, progress=progress)
    secs["front_end"] = fe.seconds
    extra, extra_valid = [], []
    secs["extra_front_ends"] = 0.0
    for m in cfg.chain_models:
        if m in ("icp", "gicp"):
            cap = cfg.front.range_cap_m  # the front end's no-returns: readings at the cap
            if m == "icp":
                p, ok, s = point_icp_chain(rng, az, odo, cap, cfg.icp, progress)
            else:
                p, ok, s = _icp_chain(rng, az, odo, cap, cap, GICP_VOXEL_M, progress)
            extra.append(p)
            extra_valid.append(np.asarray(ok[1:], bool))  # rejected registrations: out
            secs["extra_front_ends"] += s
            continue
        x = run_front_end(rng, az, odo, dataclasses.replace(cfg.front, model=m), progress=progress)
        extra.append(np.asarray(x.poses, float))
        extra_valid.append(np.ones(n - 1, bool))
        secs["extra_front_ends"] += x.seconds
    cal = None
    if cfg.calibrate_odometry and n > 1:
        valid = None if fe.plausible is None else np.asarray(fe.plausible[1:], bool)
        cal = calibrate_odometry(fe.poses, odo, cfg.front, valid=valid)
        odo = cal.apply(odo)
    t = time.perf_counter()
    loops = find_loops(rng, az, fe.poses, cfg.loops, cfg.front, progress=progress)
    if cfg.uses_revisits:
        revisits = find_revisits(
            rng,
            az,
            fe.poses,
            cfg.loops,
            range_cap_m=cfg.front.range_cap_m,
            cell_m=cfg.revisit_cell_m,
            min_overlap=cfg.revisit_min_overlap,
        )
    else:
        revisits = Loops(np.zeros((0, 2), np.int64), np.zeros((0, 3)), 0)
    secs["loops"] = time.perf_counter() - t
    secs["pose_graph"] = 0.0

    def solve(found):
        t = time.perf_counter()
        g = front_end_pose_graph(fe.poses, odo, found, cfg, revisits, extra, extra_valid)
        secs["pose_graph"] += time.perf_counter() - t
        return g, np.asarray(g.poses, float)

    pg_poses = searched = fe.poses.copy()
    pg = None
    for r in range(cfg.loop_rounds if n > 1 else 0):
        if r > 0:
            t = time.perf_counter()
            more = find_loops(
                rng,
                az,
                pg_poses,
                cfg.loops,
                cfg.front,
                known=loops.edges,
                previous_poses=searched,
                level_poses=fe.poses,
                scene_level=loops.scene_level,  # along fe.poses too: computed once
                progress=progress,
            )
            searched = pg_poses
            secs["loops"] += time.perf_counter() - t
            if len(more.edges) == 0:
                break
            loops = _joined(loops, more)
        pg, pg_poses = solve(loops)
    secs["short_loops"] = 0.0
    n_short = 0
    if cfg.short_loop_separation > 0 and pg is not None:
        # every scan against a few scans placed by the pose graph: a second measurement
        # across each stretch of the chains
        t = time.perf_counter()
        short = find_loops(
            rng,
            az,
            pg_poses,
            cfg.short_loop_config,
            cfg.front,
            known=loops.edges,
            level_poses=fe.poses,
            scene_level=loops.scene_level,
            progress=progress,
        )
        secs["short_loops"] = time.perf_counter() - t
        n_short = len(short.edges)
        if n_short:
            loops = _joined(loops, short)
            pg, pg_poses = solve(loops)
    weights = _split_weights(pg, n, loops, revisits, cfg.robust_chain, extra_valid)
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
    return SlamResult(
        poses,
        fe.poses,
        pg_poses,
        loops,
        revisits,
        back,
        secs,
        fe.seconds_per_scan,
        fe.n_used,
        fe.information,
        fe.plausible,
        cal,
        odo,
        tuple(extra),
        *weights,
        n_short,
        tuple(extra_valid),
    )
