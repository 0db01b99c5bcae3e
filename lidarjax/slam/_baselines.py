"""Classical 2-D SLAM baseline: small_gicp scan registration and a GTSAM pose graph.

The reference the decay-rate SLAM system is measured against in the same run (issue #24):
an off-the-shelf pipeline built from PyPI packages, NumPy in and out.

1. Points. Each scan becomes 2-D points in the sensor frame (no-returns, readings at or
   beyond ``max_range_m``, and readings beyond ``range_cap_m`` are dropped). small_gicp
   registers 3-D clouds, and a single plane of points ``z = 0`` is degenerate for it: a
   point's neighbourhood on a wall is a line, whose covariance has *two* near-zero
   eigenvalues (across the wall and along z), so GICP's plane regulariser may pick the
   z-axis as the "normal" and stop constraining the wall-normal direction. Each 2-D point
   is therefore extruded into a short vertical column (``z = -0.1, 0, +0.1`` m): a wall
   becomes a vertical plane whose normal is the in-plane wall normal, exactly the
   constraint a 2-D point-to-line ICP uses. Height ``z``, unobservable on vertical
   planes, is damped by small_gicp's Levenberg-Marquardt solver; the 4x4 result is
   projected to SE(2) (``x``, ``y``, ``yaw = atan2(R10, R00)``).
2. Front end. Scan ``k`` is registered (GICP, coarse then fine correspondence radius)
   against a local submap, the previous ``_SUBMAP_SCANS`` scans in the chain's frame, from
   the guess ``T_{k-1} (odo_{k-1}^-1 odo_k)``. The result is accepted when small_gicp
   converged, at least ``_FRONT_MIN_INLIERS`` of the scan's points lie within
   ``_INLIER_M`` of the submap, and the correction to the guess stays below
   ``_FRONT_MAX_CORR_M`` / ``_FRONT_MAX_CORR_RAD``; otherwise the odometry guess is kept
   (and enters the pose graph with odometry-sized noise).
3. Loop closures. For scan ``i``, the candidates are scans ``j <= i - loop_min_separation``
   whose current estimate lies within ``loop_radius_m`` of scan ``i``'s (the current
   estimate is the incrementally optimised graph, iSAM2); the ``_LOOP_CANDIDATES`` nearest
   are registered against a submap of scans ``j-3..j+3`` (in ``j``'s frame) from the
   estimated relative pose, with a wide-to-narrow correspondence schedule. A loop is
   accepted when ``_LOOP_MIN_INLIERS`` of the points lie within ``_INLIER_M`` of the
   submap, the aligned points' RMS distance is below ``_LOOP_MAX_RMS_M``, the matched walls
   constrain every translation direction (``_LOOP_MIN_WEAK``: without it a corridor lets
   the scan slide by metres with a perfect fit), and the correction stays below
   ``_LOOP_MAX_CORR_M`` / ``_LOOP_MAX_CORR_RAD``.
4. Back end. GTSAM ``Pose2`` nodes, a ``PriorFactorPose2`` on node 0,
   ``BetweenFactorPose2`` for the registration chain (2 cm / 0.5 deg) and for loops
   (Cauchy-robust, 5 cm / 1 deg), optimised by ``LevenbergMarquardtOptimizer``.

gtsam and small_gicp are optional dependencies (``pip install lidarjax[slam]``); they are
imported when :func:`icp_pose_graph_slam` runs.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

__all__ = ["IcpFrontEndResult", "IcpSlamResult", "icp_front_end", "icp_pose_graph_slam"]

# --- points ------------------------------------------------------------------------------
_LAYERS_Z_M = (-0.1, 0.0, 0.1)  # each 2-D point becomes a short vertical column (see above)
_NEIGHBOURS = 12  # neighbours for small_gicp's covariance estimate
_MAX_ITERATIONS = 50  # per small_gicp alignment stage
_REGISTRATION = "GICP"  # small_gicp registration type
# --- front end ---------------------------------------------------------------------------
_SUBMAP_SCANS = 8  # previous scans in the front end's local submap
_FRONT_CORR_M = (1.0, 0.3)  # GICP correspondence radii, coarse then fine (m)
_INLIER_M = 0.1  # a 2-D point is an inlier within this distance of the target (m)
_FRONT_MIN_INLIERS = 0.3  # accepted scan-to-submap registration: inlier fraction
_FRONT_MAX_CORR_M = 0.5  # ... and correction to the odometry guess (m, rad)
_FRONT_MAX_CORR_RAD = math.radians(15.0)
# --- loop closures -----------------------------------------------------------------------
_LOOP_CANDIDATES = 2  # nearest candidates registered per scan
_LOOP_SUBMAP_HALF = 3  # submap around a candidate j: scans j-3..j+3
_LOOP_CORR_M = (2.0, 1.0, 0.4, 0.2)  # wide-to-narrow correspondence radii (m)
_LOOP_MIN_INLIERS = 0.5  # accepted loop: inlier fraction
_LOOP_MAX_RMS_M = 0.06  # ... RMS distance of the inliers (m)
_LOOP_MIN_WEAK = 0.02  # ... constraint of the weakest translation direction (see _fit)
_LOOP_MAX_CORR_M = 2.0  # ... correction to the estimated relative pose (m, rad)
_LOOP_MAX_CORR_RAD = math.radians(20.0)
# --- pose graph --------------------------------------------------------------------------
_SEQ_SIGMAS = (0.02, 0.02, math.radians(0.5))  # accepted registration (m, m, rad)
_ODO_SIGMAS_REL = 0.1  # fallback to odometry: sigma = 10 % of the step (m) ...
_ODO_SIGMAS_MIN = (0.05, 0.05, math.radians(2.0))  # ... and at least these
_LOOP_SIGMAS = (0.05, 0.05, math.radians(1.0))
_LOOP_CAUCHY_K = 1.0  # Cauchy kernel width (in sigmas)
_PRIOR_SIGMAS = (1e-3, 1e-3, 1e-4)


@dataclass(frozen=True)
class IcpSlamResult:
    """Result of :func:`icp_pose_graph_slam`.

    Attributes:
        poses: ``[N, 3]`` optimised poses ``(x [m], y [m], yaw [rad])``, yaw wrapped to
            ``(-pi, pi]``, in the odometry's frame (row 0 equals ``odometry_xy_yaw[0]``).
        odometry_poses: ``[N, 3]`` the front end's scan-to-submap registration chain before
            the pose graph (same frame and conventions).
        loops: ``[L, 2]`` int64 accepted loop closures ``(i, j)``, ``j < i``: scan ``i`` was
            registered against the submap around scan ``j``.
        seconds_front_end: Wall time (s) of the point preparation, scan-to-submap and loop
            registrations.
        seconds_back_end: Wall time (s) of the pose-graph work (incremental iSAM2 updates
            and the final Levenberg-Marquardt optimisation).
        registered: ``[N]`` bool, ``True`` where the scan-to-submap registration was
            accepted (row 0, the anchor, is ``True``); ``False`` rows kept the odometry
            increment.
        isam_restarts: how often an iSAM2 update failed (GTSAM's indeterminate-system
            error) and every factor so far was solved in batch (Levenberg-Marquardt)
            instead, iSAM2 restarted from that solution.
    """

    poses: np.ndarray
    odometry_poses: np.ndarray
    loops: np.ndarray
    seconds_front_end: float
    seconds_back_end: float
    registered: np.ndarray
    isam_restarts: int = 0


# --- SE(2) helpers (NumPy) ---------------------------------------------------------------


def _wrap(a):
    """Wrap angles (rad) to ``(-pi, pi]``."""
    return np.pi - np.mod(np.pi - np.asarray(a, np.float64), 2.0 * np.pi)


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a * b`` for poses ``(x, y, yaw)``."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], _wrap(a[2] + b[2])])


def _inverse(a: np.ndarray) -> np.ndarray:
    """``a^-1`` for a pose ``(x, y, yaw)``."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([-c * a[0] - s * a[1], s * a[0] - c * a[1], _wrap(-a[2])])


def _between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a^-1 * b``."""
    return _compose(_inverse(a), b)


def _to_matrix(p: np.ndarray) -> np.ndarray:
    """``[4, 4]`` homogeneous 3-D transform of a planar pose."""
    c, s = math.cos(p[2]), math.sin(p[2])
    t = np.eye(4)
    t[:2, :2] = [[c, -s], [s, c]]
    t[:2, 3] = p[:2]
    return t


def _from_matrix(t: np.ndarray) -> np.ndarray:
    """Project a ``[4, 4]`` transform to SE(2): ``(x, y, atan2(R10, R00))``."""
    return np.array([t[0, 3], t[1, 3], math.atan2(t[1, 0], t[0, 0])])


def _transform(p: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Points ``[n, 2]`` mapped by pose ``p``."""
    c, s = math.cos(p[2]), math.sin(p[2])
    return xy @ np.array([[c, s], [-s, c]]) + p[:2]


# --- validation --------------------------------------------------------------------------


def _positive(value, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return v


def _check_inputs(ranges_m, azimuths_rad, odometry_xy_yaw):
    ranges = np.asarray(ranges_m, dtype=np.float64)
    az = np.asarray(azimuths_rad, dtype=np.float64)
    odo = np.asarray(odometry_xy_yaw, dtype=np.float64)
    if ranges.ndim != 2 or ranges.shape[0] < 1 or ranges.shape[1] < 1:
        raise ValueError(f"ranges_m must have shape [N, B] with N, B >= 1, got {ranges.shape}")
    if not np.all(np.isfinite(ranges)):
        raise ValueError("ranges_m must be finite (no NaN or inf)")
    if np.any(ranges <= 0):
        raise ValueError("ranges_m must be positive (use max_range_m for no-returns)")
    if az.shape != (ranges.shape[1],):
        raise ValueError(f"azimuths_rad must have shape [B] = [{ranges.shape[1]}], got {az.shape}")
    if not np.all(np.isfinite(az)):
        raise ValueError("azimuths_rad must be finite")
    if odo.shape != (ranges.shape[0], 3):
        raise ValueError(
            f"odometry_xy_yaw must have shape [N, 3] = [{ranges.shape[0]}, 3], got {odo.shape}"
        )
    if not np.all(np.isfinite(odo)):
        raise ValueError("odometry_xy_yaw must be finite")
    return ranges, az, odo


def _import_backends():
    try:
        import gtsam
        import small_gicp
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError(
            "icp_pose_graph_slam needs gtsam and small_gicp (pip install 'lidarjax[slam]')"
        ) from err
    return gtsam, small_gicp


def _import_small_gicp():
    try:
        import small_gicp
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError(
            "the GICP front end (icp_front_end, run_slam's 'gicp' chain) needs small_gicp "
            "(pip install 'lidarjax[slam]')"
        ) from err
    return small_gicp


# --- registration ------------------------------------------------------------------------


def _extrude(xy: np.ndarray) -> np.ndarray:
    """2-D points ``[n, 2]`` -> 3-D columns ``[n * layers, 3]`` (see the module docstring)."""
    n = xy.shape[0]
    out = np.empty((len(_LAYERS_Z_M), n, 3))
    out[:, :, :2] = xy[None]
    out[:, :, 2] = np.asarray(_LAYERS_Z_M)[:, None]
    return out.reshape(-1, 3)


class _Cloud:
    """A preprocessed small_gicp cloud: voxel-downsampled, per-point covariances, k-d tree."""

    def __init__(self, sg, xy: np.ndarray, voxel_m: float):
        self.cloud, self.tree = sg.preprocess_points(
            _extrude(xy), downsampling_resolution=voxel_m, num_neighbors=_NEIGHBOURS
        )
        self._normals = None

    @property
    def normals_xy(self) -> np.ndarray:
        """``[m, 2]`` in-plane unit normals: the minor axis of each covariance's xy block."""
        if self._normals is None:
            cov = np.asarray(self.cloud.covs())[:, :2, :2]
            _, vec = np.linalg.eigh(cov)
            self._normals = vec[:, :, 0]
        return self._normals


def _fit(target: _Cloud, source_xy: np.ndarray, pose: np.ndarray) -> tuple[float, float, float]:
    """How well ``source_xy`` mapped by ``pose`` fits ``target``.

    Returns:
        The fraction of the points within ``_INLIER_M`` of a target point; the RMS distance
        (m) of those inliers; and the constraint of the weakest translation direction,
        ``lambda_min(sum n n^T) / n_inliers`` over the target normals ``n`` at the inliers
        (in ``[0, 0.5]``; near 0 when all matched walls are parallel, as in a corridor).
    """
    p = _transform(pose, source_xy)
    idx, d2 = target.tree.batch_nearest_neighbor_search(np.column_stack([p, np.zeros(len(p))]))
    idx = np.asarray(idx, np.int64).reshape(-1)
    d2 = np.asarray(d2, np.float64).reshape(-1)
    ok = (idx >= 0) & (d2 <= _INLIER_M**2)
    if not ok.any():
        return 0.0, math.inf, 0.0
    nrm = target.normals_xy[idx[ok]]
    weak = float(np.linalg.eigvalsh(nrm.T @ nrm)[0]) / int(ok.sum())
    return float(ok.mean()), float(np.sqrt(d2[ok].mean())), weak


def _register(
    sg, target: _Cloud, source: _Cloud, guess: np.ndarray, radii
) -> tuple[np.ndarray, bool]:
    """GICP from ``guess`` with a shrinking correspondence radius; SE(2) result and whether
    the last stage converged."""
    pose = guess
    converged = False
    for r in radii:
        res = sg.align(
            target.cloud,
            source.cloud,
            target.tree,
            init_T_target_source=_to_matrix(pose),
            registration_type=_REGISTRATION,
            max_correspondence_distance=r,
            max_iterations=_MAX_ITERATIONS,
        )
        pose = _from_matrix(np.asarray(res.T_target_source))
        converged = bool(res.converged)
    return pose, converged


def _scan_points(ranges: np.ndarray, az: np.ndarray, max_range_m: float, cap: float) -> np.ndarray:
    keep = (ranges < max_range_m) & (ranges <= cap) & (ranges > 0)
    r = ranges[keep]
    return np.column_stack([r * np.cos(az[keep]), r * np.sin(az[keep])])


def _scan_clouds(sg, ranges, az, max_range_m: float, range_cap_m: float, voxel_m: float):
    """Each scan's 2-D points (:func:`_scan_points`) and its small_gicp cloud (None for a
    scan with fewer points than a covariance needs): ``(points, sources)``."""
    points = [_scan_points(r, az, max_range_m, range_cap_m) for r in ranges]
    return points, [_Cloud(sg, p, voxel_m) if len(p) >= _NEIGHBOURS else None for p in points]


def _chain_step(sg, chain, window, points, source, odo, k: int, voxel_m: float):
    """The front end's step ``k`` (module docstring, 2.): scan ``k``'s pose registered
    against the submap of the scans in ``window`` (placed at ``chain``), from the odometry's
    guess; ``(pose [3], registered)``, the guess itself where the registration is rejected
    or there are too few points."""
    guess = _compose(chain[k - 1], _between(odo[k - 1], odo[k]))
    if source is None:
        return guess, False
    sub_xy = np.concatenate([_transform(chain[m], points[m]) for m in window])
    if len(sub_xy) < _NEIGHBOURS:
        return guess, False
    target = _Cloud(sg, sub_xy, voxel_m)
    pose, converged = _register(sg, target, source, guess, _FRONT_CORR_M)
    frac, _, _ = _fit(target, points[k], pose)
    corr = _between(guess, pose)
    ok = (
        converged
        and frac >= _FRONT_MIN_INLIERS
        and math.hypot(corr[0], corr[1]) <= _FRONT_MAX_CORR_M
        and abs(corr[2]) <= _FRONT_MAX_CORR_RAD
    )
    return (pose, True) if ok else (guess, False)


def _icp_chain(ranges, az, odo, max_range_m: float, range_cap_m: float, voxel_m: float, progress):
    """:func:`icp_front_end` on checked inputs (readings ``<= 0`` carry no point either):
    ``(poses [N 3], registered [N], seconds)``."""
    sg = _import_small_gicp()
    t0 = time.perf_counter()
    n = ranges.shape[0]
    points, sources = _scan_clouds(sg, ranges, az, max_range_m, range_cap_m, voxel_m)
    chain = np.empty((n, 3))
    chain[0] = odo[0]
    registered = np.zeros(n, bool)
    registered[0] = True
    window: deque[int] = deque([0], maxlen=_SUBMAP_SCANS)
    steps = range(1, n)
    if progress:
        from tqdm.auto import tqdm

        steps = tqdm(steps, desc="icp front end", unit="scan")
    for k in steps:
        chain[k], registered[k] = _chain_step(
            sg, chain, window, points, sources[k], odo, k, voxel_m
        )
        window.append(k)
    chain[:, 2] = _wrap(chain[:, 2])
    return chain, registered, time.perf_counter() - t0


@dataclass(frozen=True)
class IcpFrontEndResult:
    """Result of :func:`icp_front_end`.

    Attributes:
        poses: ``[N, 3]`` the registration chain ``(x [m], y [m], yaw [rad])``, row 0 equal
            to ``odometry_xy_yaw[0]``, yaw wrapped to ``(-pi, pi]``.
        registered: ``[N]`` bool, ``True`` where the scan-to-submap registration was
            accepted (row 0 too); a ``False`` row took the odometry's increment.
        seconds: wall time (s).
    """

    poses: np.ndarray
    registered: np.ndarray
    seconds: float


def icp_front_end(
    ranges_m: np.ndarray,
    azimuths_rad: np.ndarray,
    odometry_xy_yaw: np.ndarray,
    *,
    max_range_m: float,
    range_cap_m: float = 20.0,
    voxel_m: float = 0.05,
    progress: bool = False,
) -> IcpFrontEndResult:
    """The front end of :func:`icp_pose_graph_slam` alone: each scan registered by
    small_gicp against the previous scans' submap from the odometry's guess (module
    docstring, 1.-2.), without loop closures or a pose graph. :func:`~lidarjax.slam.run_slam`
    runs it as a further chain of increments (``SlamConfig.extra_chain_models``
    ``"gicp"``): it fails at other scans than the decay-rate and endpoint front ends.

    Args:
        ranges_m: ``[N, B]`` ranges (m), all positive.
        azimuths_rad: ``[B]`` beam angles (rad).
        odometry_xy_yaw: ``[N, 3]`` raw odometry poses; its increments are the guesses and
            row 0 anchors the chain.
        max_range_m: no-return threshold (m): readings ``>= max_range_m`` are dropped.
        range_cap_m: readings beyond this (m) are dropped too.
        voxel_m: voxel size (m) of the downsampling.
        progress: tqdm progress bar.

    Returns:
        :class:`IcpFrontEndResult`; the same chain as
        :attr:`IcpSlamResult.odometry_poses` and :attr:`IcpSlamResult.registered`.

    Raises:
        ValueError: bad shapes or values (the message names the argument).
        ImportError: small_gicp is not installed.
    """
    ranges, az, odo = _check_inputs(ranges_m, azimuths_rad, odometry_xy_yaw)
    max_range_m = _positive(max_range_m, "max_range_m")
    range_cap_m = _positive(range_cap_m, "range_cap_m")
    voxel_m = _positive(voxel_m, "voxel_m")
    return IcpFrontEndResult(
        *_icp_chain(ranges, az, odo, max_range_m, range_cap_m, voxel_m, progress)
    )


# --- the pipeline ------------------------------------------------------------------------


def _pose2_values(gtsam, poses: np.ndarray):
    """``gtsam.Values`` holding ``Pose2`` ``k`` = row ``k`` of ``poses`` ``[K, 3]``."""
    values = gtsam.Values()
    for k, p in enumerate(poses):
        values.insert(k, gtsam.Pose2(*p))
    return values


def _levenberg_marquardt(gtsam, graph, initial):
    """``graph`` solved by GTSAM's Levenberg-Marquardt (at most 100 iterations) from the
    ``gtsam.Values`` ``initial``."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    return gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()


def _batch_restart(gtsam, graph, poses: np.ndarray):
    """Solve ``graph`` (every factor so far) with Levenberg-Marquardt from ``poses``
    ``[K, 3]``, and a new iSAM2 holding the graph at that solution: ``(isam, estimate)``."""
    current = _levenberg_marquardt(gtsam, graph, _pose2_values(gtsam, poses))
    isam = gtsam.ISAM2(gtsam.ISAM2Params())
    isam.update(graph, current)
    return isam, isam.calculateEstimate()


def icp_pose_graph_slam(
    ranges_m: np.ndarray,
    azimuths_rad: np.ndarray,
    odometry_xy_yaw: np.ndarray,
    *,
    max_range_m: float,
    range_cap_m: float = 20.0,
    voxel_m: float = 0.05,
    loop_radius_m: float = 4.0,
    loop_min_separation: int = 30,
    progress: bool = False,
    seed: int = 0,
) -> IcpSlamResult:
    """Classical 2-D SLAM: small_gicp scan-to-submap GICP, loop closures, GTSAM pose graph.

    The pipeline (thresholds in the module docstring of :mod:`lidarjax.slam._baselines`):
    scans become 2-D points extruded into short vertical columns for small_gicp; each scan
    is registered against the previous scans from the odometry-predicted pose (falling back
    to the odometry increment when the registration is rejected); scans revisiting a place
    are registered against a submap there; the chain and the loops are optimised as a
    ``Pose2`` graph (iSAM2 online, Levenberg-Marquardt at the end, Cauchy-robust loops).

    Args:
        ranges_m: ``[N, B]`` ranges (m), one planar scan per row, all positive.
        azimuths_rad: ``[B]`` beam angles (rad) in the sensor frame.
        odometry_xy_yaw: ``[N, 3]`` raw odometry poses ``(x [m], y [m], yaw [rad])``; only
            its increments are used, and row 0 anchors the result's frame.
        max_range_m: No-return threshold (m): readings ``>= max_range_m`` are dropped.
        range_cap_m: Readings beyond this (m) are dropped too: far points are sparse (1 deg
            beams are 35 cm apart at 20 m) and hurt the covariance estimates.
        voxel_m: Voxel size (m) of the downsampling of scans and submaps.
        loop_radius_m: Loop candidates lie within this distance (m) of the current
            estimate of the scan.
        loop_min_separation: A candidate ``j`` for scan ``i`` has ``j <= i -
            loop_min_separation`` (scans); at least 7, the span of a loop submap.
        progress: Show a tqdm progress bar over the scans.
        seed: Seed (``>= 0``) of the loop-candidate tie-breaking; the pipeline is otherwise
            deterministic (small_gicp runs single-threaded).

    Returns:
        An :class:`IcpSlamResult`.

    Raises:
        ValueError: Bad shapes, non-finite or non-positive ranges, non-finite azimuths or
            odometry, or a bad option (each message names the argument).
        ImportError: gtsam or small_gicp is not installed.
    """
    ranges, az, odo = _check_inputs(ranges_m, azimuths_rad, odometry_xy_yaw)
    max_range_m = _positive(max_range_m, "max_range_m")
    range_cap_m = _positive(range_cap_m, "range_cap_m")
    voxel_m = _positive(voxel_m, "voxel_m")
    loop_radius_m = _positive(loop_radius_m, "loop_radius_m")
    if isinstance(loop_min_separation, bool) or not isinstance(
        loop_min_separation, (int, np.integer)
    ):
        raise ValueError(f"loop_min_separation must be an int, got {loop_min_separation!r}")
    if loop_min_separation < 2 * _LOOP_SUBMAP_HALF + 1:
        raise ValueError(
            f"loop_min_separation must be at least {2 * _LOOP_SUBMAP_HALF + 1}, "
            f"got {loop_min_separation}"
        )
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be an int >= 0, got {seed!r}")
    gtsam, sg = _import_backends()
    rng = np.random.default_rng(int(seed))
    n = ranges.shape[0]

    t_front = 0.0
    t_back = 0.0
    tic = time.perf_counter()
    points, sources = _scan_clouds(sg, ranges, az, max_range_m, range_cap_m, voxel_m)
    t_front += time.perf_counter() - tic

    chain = np.empty((n, 3))
    chain[0] = odo[0]
    registered = np.zeros(n, bool)
    registered[0] = True
    est = np.empty((n, 3))  # current best estimate (chain corrected by the optimised graph)
    est[0] = odo[0]
    loops: list[tuple[int, int]] = []
    restarts = 0

    tic = time.perf_counter()
    isam = gtsam.ISAM2(gtsam.ISAM2Params())
    new_graph = gtsam.NonlinearFactorGraph()
    new_values = gtsam.Values()
    full_graph = gtsam.NonlinearFactorGraph()
    prior = gtsam.PriorFactorPose2(
        0, gtsam.Pose2(*odo[0]), gtsam.noiseModel.Diagonal.Sigmas(np.array(_PRIOR_SIGMAS))
    )
    new_graph.add(prior)
    full_graph.add(prior)
    new_values.insert(0, gtsam.Pose2(*odo[0]))
    seq_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array(_SEQ_SIGMAS))
    loop_noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Cauchy.Create(_LOOP_CAUCHY_K),
        gtsam.noiseModel.Diagonal.Sigmas(np.array(_LOOP_SIGMAS)),
    )
    t_back += time.perf_counter() - tic

    window: deque[int] = deque([0], maxlen=_SUBMAP_SCANS)
    steps = range(1, n)
    if progress:
        from tqdm.auto import tqdm

        steps = tqdm(steps, desc="icp slam", unit="scan")
    for k in steps:
        # ---- front end: scan k against the local submap of the previous scans
        tic = time.perf_counter()
        delta_odo = _between(odo[k - 1], odo[k])
        src = sources[k]
        chain[k], registered[k] = _chain_step(sg, chain, window, points, src, odo, k, voxel_m)
        window.append(k)
        rel = _between(chain[k - 1], chain[k])
        est[k] = _compose(est[k - 1], rel)
        t_front += time.perf_counter() - tic

        tic = time.perf_counter()
        if registered[k]:
            noise = seq_noise
        else:
            step = math.hypot(delta_odo[0], delta_odo[1])
            sig = np.maximum(np.array(_ODO_SIGMAS_MIN), _ODO_SIGMAS_REL * step)
            noise = gtsam.noiseModel.Diagonal.Sigmas(sig)
        factor = gtsam.BetweenFactorPose2(k - 1, k, gtsam.Pose2(*rel), noise)
        new_graph.add(factor)
        full_graph.add(factor)
        new_values.insert(k, gtsam.Pose2(*est[k]))
        t_back += time.perf_counter() - tic

        # ---- loop closures: scan k against submaps around earlier, nearby scans
        if src is None or k < loop_min_separation:
            continue
        tic = time.perf_counter()
        old = np.arange(0, k - loop_min_separation + 1)
        dist = np.hypot(*(est[old, :2] - est[k, :2]).T)
        near = old[dist <= loop_radius_m]
        found = []
        if near.size:
            # nearest first; the seeded jitter only breaks exact ties
            key = dist[near] + 1e-9 * rng.random(near.size)
            for j in near[np.argsort(key)][:_LOOP_CANDIDATES]:
                j = int(j)
                lo, hi = max(0, j - _LOOP_SUBMAP_HALF), min(k, j + _LOOP_SUBMAP_HALF + 1)
                sub_xy = np.concatenate(
                    [_transform(_between(chain[j], chain[m]), points[m]) for m in range(lo, hi)]
                )
                if len(sub_xy) < _NEIGHBOURS:
                    continue
                target = _Cloud(sg, sub_xy, voxel_m)
                guess_jk = _between(est[j], est[k])
                pose, converged = _register(sg, target, src, guess_jk, _LOOP_CORR_M)
                frac, rms, weak = _fit(target, points[k], pose)
                corr = _between(guess_jk, pose)
                if (
                    converged
                    and frac >= _LOOP_MIN_INLIERS
                    and rms <= _LOOP_MAX_RMS_M
                    and weak >= _LOOP_MIN_WEAK
                    and math.hypot(corr[0], corr[1]) <= _LOOP_MAX_CORR_M
                    and abs(corr[2]) <= _LOOP_MAX_CORR_RAD
                ):
                    found.append((j, pose))
        t_front += time.perf_counter() - tic
        if found:
            tic = time.perf_counter()
            for j, pose in found:
                factor = gtsam.BetweenFactorPose2(j, k, gtsam.Pose2(*pose), loop_noise)
                new_graph.add(factor)
                full_graph.add(factor)
                loops.append((k, j))
            try:
                isam.update(new_graph, new_values)
                isam.update()
                current = isam.calculateEstimate()
            except RuntimeError:
                # iSAM2's partial refactorisation can fail on a loop far from the estimate
                # (freiburg-campus, drift seed 0, scan 1576): every factor so far in batch
                # (damped), and iSAM2 again from that solution
                isam, current = _batch_restart(gtsam, full_graph, est[: k + 1])
                restarts += 1
            new_graph = gtsam.NonlinearFactorGraph()
            new_values = gtsam.Values()
            est[: k + 1] = gtsam.utilities.extractPose2(current)
            t_back += time.perf_counter() - tic

    tic = time.perf_counter()
    if new_values.size() or new_graph.size():
        try:
            isam.update(new_graph, new_values)
        except RuntimeError:  # as above; the batch solve below starts from the estimate
            isam = None
            restarts += 1
    initial = _pose2_values(gtsam, est) if isam is None else isam.calculateEstimate()
    result = _levenberg_marquardt(gtsam, full_graph, initial)
    poses = np.asarray(gtsam.utilities.extractPose2(result), np.float64).reshape(n, 3)
    poses[:, 2] = _wrap(poses[:, 2])
    t_back += time.perf_counter() - tic

    chain[:, 2] = _wrap(chain[:, 2])
    return IcpSlamResult(
        poses=poses,
        odometry_poses=chain,
        loops=np.asarray(loops, np.int64).reshape(-1, 2),
        seconds_front_end=float(t_front),
        seconds_back_end=float(t_back),
        registered=registered,
        isam_restarts=restarts,
    )
