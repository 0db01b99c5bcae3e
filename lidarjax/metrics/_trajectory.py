"""Planar trajectory error metrics (the columns of dissertation Table 12.2).

Following section 12.5.1, the deviation of an estimated trajectory from ground truth is
evaluated every ``spacing_m`` (1 m) of distance travelled along the ground-truth trajectory,
so that standing still or driving slowly does not weight the result.

Definitions. Both trajectories are time-aligned (row ``i`` of each belongs to the same
timestamp). Let ``s_i`` be the cumulative ground-truth arc length at row ``i`` (straight
segments between consecutive rows). The evaluation points are ``s = 0, d, 2d, ...,
floor(L / d) d`` with ``d = spacing_m`` and ``L`` the total arc length. At each ``s`` both
trajectories are interpolated between the two bracketing rows ``i, i + 1``
(``s_i <= s <= s_{i+1}``) with the same fraction ``t = (s - s_i) / (s_{i+1} - s_i)``:
x and y linearly, yaw along the shortest arc. With the ground-truth pose ``(x, y, psi)`` and
the position error ``e = est_xy - gt_xy``:

- longitudinal error ``e . (cos psi, sin psi)`` (along the ground-truth heading),
- lateral error ``e . (-sin psi, cos psi)`` (along the left normal),
- heading error ``est_yaw - psi`` wrapped to ``(-180, 180]`` degrees.

``delta_*`` are means of absolute values, ``sigma_*`` population standard deviations
(``ddof=0``) of the signed errors, ``rmse_*`` root mean squares. The heading ``psi`` is the
ground-truth *yaw* column, not the direction of travel.

NumPy only (evaluation code, not a hot path).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

__all__ = [
    "AbsoluteTrajectoryError",
    "RelativePoseError",
    "TrajectoryErrors",
    "absolute_trajectory_error",
    "align_se2",
    "interpolate_at_arclength",
    "relative_pose_error",
    "trajectory_errors",
]

_COUNT_RTOL = 1e-9  # L / spacing within this relative tolerance of an integer counts as one


@dataclass(frozen=True)
class TrajectoryErrors:
    """Trajectory error statistics over the evaluation points (Table 12.2 columns).

    Attributes:
        delta_pos_m: Mean absolute position error ``mean |e|`` (m), the ``Δpos`` column.
        rmse_pos_m: Root mean square position error (m).
        delta_lat_m: Mean absolute lateral error (m), perpendicular to the ground-truth
            heading (positive = estimate to the left).
        sigma_lat_m: Population standard deviation of the signed lateral error (m).
        delta_lon_m: Mean absolute longitudinal error (m), along the ground-truth heading
            (positive = estimate ahead).
        sigma_lon_m: Population standard deviation of the signed longitudinal error (m).
        delta_ang_deg: Mean absolute heading error (degrees), errors wrapped to (-180, 180].
        sigma_ang_deg: Population standard deviation of the signed heading error (degrees).
        rmse_ang_deg: Root mean square heading error (degrees).
        max_pos_m: Largest position error (m).
        n: Number of evaluation points used.
    """

    delta_pos_m: float
    rmse_pos_m: float
    delta_lat_m: float
    sigma_lat_m: float
    delta_lon_m: float
    sigma_lon_m: float
    delta_ang_deg: float
    sigma_ang_deg: float
    rmse_ang_deg: float
    max_pos_m: float
    n: int

    def as_dict(self) -> dict[str, Any]:
        """Field name -> value (floats and the int ``n``)."""
        return asdict(self)


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Wrap angles (rad) to ``(-pi, pi]``."""
    return np.pi - np.mod(np.pi - angle, 2.0 * np.pi)


def _bracket(arclength: np.ndarray, s_query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bracketing row ``i`` and fraction ``t`` with ``s = (1 - t) s_i + t s_{i+1}``.

    ``i`` is the row before the first row whose arc length reaches ``s`` (so a query equal
    to a row's arc length gives ``t = 1`` on the segment ending there, except ``s = s_0``
    which gives ``i = 0, t = 0``); zero-length segments give ``t = 0``.
    """
    n = arclength.shape[0]
    j = np.searchsorted(arclength, s_query, side="left")
    i = np.clip(j - 1, 0, n - 2)
    ds = arclength[i + 1] - arclength[i]
    safe = np.where(ds > 0, ds, 1.0)
    t = np.where(ds > 0, (s_query - arclength[i]) / safe, 0.0)
    return i, np.clip(t, 0.0, 1.0)


def _interp(xy_yaw: np.ndarray, i: np.ndarray, t: np.ndarray) -> np.ndarray:
    a, b = xy_yaw[i], xy_yaw[i + 1]
    # Where a weight is exactly 0 the other row is returned unchanged (even if the unused
    # row holds NaN).
    xy = np.where(
        (t == 0.0)[:, None],
        a[:, :2],
        np.where(
            (t == 1.0)[:, None], b[:, :2], (1.0 - t)[:, None] * a[:, :2] + t[:, None] * b[:, :2]
        ),
    )
    yaw = np.where(
        t == 0.0,
        a[:, 2],
        np.where(t == 1.0, b[:, 2], a[:, 2] + t * _wrap(b[:, 2] - a[:, 2])),
    )
    return np.concatenate([xy, _wrap(yaw)[:, None]], axis=1)


def interpolate_at_arclength(
    xy_yaw: np.ndarray, s_query: np.ndarray, arclength: np.ndarray
) -> np.ndarray:
    """Interpolate planar poses at given arc lengths.

    For each query the bracketing rows ``i, i + 1`` with ``arclength[i] <= s <=
    arclength[i+1]`` are found; x and y are interpolated linearly and yaw along the shortest
    arc with the fraction ``t = (s - arclength[i]) / (arclength[i+1] - arclength[i])``. A
    query equal to a row's arc length returns that row exactly (the first such row when
    the arc length is constant over several rows).

    Args:
        xy_yaw: ``[N, 3]`` poses x (m), y (m), yaw (rad), ``N >= 2``.
        s_query: ``[M]`` arc lengths (m) within ``[arclength[0], arclength[-1]]``.
        arclength: ``[N]`` non-decreasing arc length (m) of each row (need not be the arc
            length of ``xy_yaw`` itself, e.g. the ground truth's for an estimate).

    Returns:
        float64 ``[M, 3]`` interpolated poses, yaw wrapped to ``(-pi, pi]``.

    Raises:
        ValueError: Bad shapes, fewer than 2 rows, ``arclength`` not finite and
            non-decreasing, or a query non-finite or outside the arc-length range.
    """
    xy_yaw = np.asarray(xy_yaw, dtype=np.float64)
    s_query = np.asarray(s_query, dtype=np.float64)
    arclength = np.asarray(arclength, dtype=np.float64)
    if xy_yaw.ndim != 2 or xy_yaw.shape[1] != 3:
        raise ValueError(f"xy_yaw must have shape [N, 3], got {xy_yaw.shape}")
    if xy_yaw.shape[0] < 2:
        raise ValueError(f"xy_yaw needs at least 2 rows, got {xy_yaw.shape[0]}")
    if arclength.shape != (xy_yaw.shape[0],):
        raise ValueError(f"arclength must have shape [{xy_yaw.shape[0]}], got {arclength.shape}")
    if not np.isfinite(arclength).all() or np.any(np.diff(arclength) < 0):
        raise ValueError("arclength must be finite and non-decreasing")
    if s_query.ndim != 1:
        raise ValueError(f"s_query must have shape [M], got {s_query.shape}")
    if not np.isfinite(s_query).all() or np.any(
        (s_query < arclength[0]) | (s_query > arclength[-1])
    ):
        raise ValueError(
            f"s_query must be finite and within [{arclength[0]}, {arclength[-1]}] "
            f"(got range [{s_query.min(initial=np.inf)}, {s_query.max(initial=-np.inf)}])"
        )
    i, t = _bracket(arclength, s_query)
    return _interp(xy_yaw, i, t)


def _check_poses(name: str, arr: Any) -> np.ndarray:
    out = np.asarray(arr, dtype=np.float64)
    if out.ndim != 2 or out.shape[1] != 3:
        raise ValueError(f"{name} must have shape [N, 3] (x, y, yaw), got {out.shape}")
    return out


def _checked_pair(estimate_xy_yaw, truth_xy_yaw) -> tuple[np.ndarray, np.ndarray]:
    """The checked ``[N 3]`` estimate and ground truth, of the same shape."""
    est = _check_poses("estimate_xy_yaw", estimate_xy_yaw)
    gt = _check_poses("truth_xy_yaw", truth_xy_yaw)
    if est.shape != gt.shape:
        raise ValueError(
            f"estimate_xy_yaw and truth_xy_yaw must have the same shape, got {est.shape} "
            f"and {gt.shape}"
        )
    return est, gt


def _ground_truth_arclength(gt_xy: np.ndarray) -> np.ndarray:
    """Cumulative arc length, joining consecutive rows with finite positions.

    Rows with non-finite positions get the arc length of the previous finite row (0 before
    the first one), so the result is finite and non-decreasing.
    """
    finite = np.isfinite(gt_xy).all(axis=1)
    idx = np.flatnonzero(finite)
    arc = np.zeros(gt_xy.shape[0])
    if idx.size >= 2:
        steps = np.linalg.norm(np.diff(gt_xy[idx], axis=0), axis=1)
        arc_finite = np.concatenate([[0.0], np.cumsum(steps)])
        # index of the last finite row at or before each row
        last = np.maximum.accumulate(np.where(finite, np.arange(gt_xy.shape[0]), -1))
        pos = np.searchsorted(idx, np.maximum(last, idx[0]))
        arc = np.where(last >= 0, arc_finite[pos], 0.0)
    return arc


def trajectory_errors(
    estimate_xy_yaw: np.ndarray,
    truth_xy_yaw: np.ndarray,
    *,
    spacing_m: float = 1.0,
    valid: np.ndarray | None = None,
) -> TrajectoryErrors:
    """Errors of an estimated planar trajectory w.r.t. ground truth, every ``spacing_m``.

    See the module docstring for the definitions. Rows with ``valid == False`` (e.g. before
    the filter starts, or NaN ground truth) may hold NaN; an evaluation point is skipped if
    a bracketing row with nonzero interpolation weight is invalid (a point that coincides
    with a row needs only that row). The ground-truth arc length joins consecutive rows
    whose ground-truth position is finite, so skipping invalid rows does not shorten it.

    Args:
        estimate_xy_yaw: ``[N, 3]`` estimated x (m), y (m), yaw (rad).
        truth_xy_yaw: ``[N, 3]`` ground-truth x (m), y (m), yaw (rad), same timestamps.
        spacing_m: Distance between evaluation points along the ground truth (m), > 0.
        valid: Optional bool ``[N]``; ``None`` means all rows are valid.

    Returns:
        :class:`TrajectoryErrors` over the ``n`` used evaluation points (at most
        ``floor(L / spacing_m) + 1``, ``L`` the ground-truth length; a ratio ``L /
        spacing_m`` within a relative 1e-9 of an integer counts as that integer).

    Raises:
        ValueError: Shapes do not match, fewer than 2 rows, NaN/inf in a valid row,
            ``spacing_m`` not a positive finite number, ``valid`` not a bool ``[N]`` array,
            the ground truth never moves, or no evaluation point has valid rows. The
            message names the offending argument.
    """
    est, gt = _checked_pair(estimate_xy_yaw, truth_xy_yaw)
    n_rows = gt.shape[0]
    if n_rows < 2:
        raise ValueError(f"truth_xy_yaw needs at least 2 rows, got {n_rows}")
    spacing = float(spacing_m)
    if not np.isfinite(spacing) or spacing <= 0:
        raise ValueError(f"spacing_m must be a positive finite number, got {spacing_m!r}")
    if valid is None:
        ok = np.ones(n_rows, dtype=bool)
    else:
        ok = np.asarray(valid)
        if ok.dtype != np.bool_ or ok.shape != (n_rows,):
            raise ValueError(
                f"valid must be a bool array of shape [{n_rows}], got dtype {ok.dtype} and "
                f"shape {ok.shape}"
            )
    for name, arr in (("estimate_xy_yaw", est), ("truth_xy_yaw", gt)):
        bad = ok & ~np.isfinite(arr).all(axis=1)
        if bad.any():
            raise ValueError(
                f"{name} holds NaN or infinite values in valid row {int(np.flatnonzero(bad)[0])}"
            )

    arc = _ground_truth_arclength(gt[:, :2])
    length = float(arc[-1])
    if length <= 0:
        raise ValueError("truth_xy_yaw never moves (total arc length 0)")
    count = int(np.floor(length / spacing * (1.0 + _COUNT_RTOL))) + 1
    s = np.minimum(np.arange(count) * spacing, length)

    i, t = _bracket(arc, s)
    use = (ok[i] | (t == 1.0)) & (ok[i + 1] | (t == 0.0))
    if not use.any():
        raise ValueError("no evaluation point lies between valid rows (see valid)")
    i, t = i[use], t[use]
    e_pose = _interp(est, i, t)
    g_pose = _interp(gt, i, t)

    err = e_pose[:, :2] - g_pose[:, :2]
    cos, sin = np.cos(g_pose[:, 2]), np.sin(g_pose[:, 2])
    lon = err[:, 0] * cos + err[:, 1] * sin
    lat = -err[:, 0] * sin + err[:, 1] * cos
    dist = np.hypot(err[:, 0], err[:, 1])
    ang = np.degrees(_wrap(e_pose[:, 2] - g_pose[:, 2]))
    ang = np.where(ang <= -180.0, 180.0, ang)  # guard the (-180, 180] convention

    return TrajectoryErrors(
        delta_pos_m=float(dist.mean()),
        rmse_pos_m=float(np.sqrt(np.mean(dist**2))),
        delta_lat_m=float(np.abs(lat).mean()),
        sigma_lat_m=float(lat.std()),
        delta_lon_m=float(np.abs(lon).mean()),
        sigma_lon_m=float(lon.std()),
        delta_ang_deg=float(np.abs(ang).mean()),
        sigma_ang_deg=float(ang.std()),
        rmse_ang_deg=float(np.sqrt(np.mean(ang**2))),
        max_pos_m=float(dist.max()),
        n=int(i.shape[0]),
    )


@dataclass(frozen=True)
class AbsoluteTrajectoryError:
    """Absolute trajectory error per pose after alignment (what ``evo_ape`` reports as
    APE w.r.t. the translation part).

    Attributes:
        rmse_m: Root mean square position error (m).
        mean_m: Mean position error (m).
        median_m: Median position error (m).
        max_m: Largest position error (m).
        n: Number of poses used.
        rotation_rad: Rotation of the alignment applied to the estimate (rad).
        translation_m: ``[2]`` translation of the alignment (m).
        errors_m: ``[N]`` position error per row (m; NaN where not used).
        aligned: ``[N 3]`` the aligned estimate ``(x, y, yaw)``.
    """

    rmse_m: float
    mean_m: float
    median_m: float
    max_m: float
    n: int
    rotation_rad: float
    translation_m: np.ndarray
    errors_m: np.ndarray
    aligned: np.ndarray


def _paired(estimate_xy_yaw, truth_xy_yaw, valid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Checked ``[N 3]`` estimate and truth and the rows to use: finite positions in both
    and ``valid`` (optional ``[N]`` bool)."""
    est, gt = _checked_pair(estimate_xy_yaw, truth_xy_yaw)
    use = np.isfinite(est[:, :2]).all(1) & np.isfinite(gt[:, :2]).all(1)
    if valid is not None:
        valid = np.asarray(valid, bool)
        if valid.shape != (est.shape[0],):
            raise ValueError(f"valid must have shape [{est.shape[0]}], got {valid.shape}")
        use &= valid
    return est, gt, use


def align_se2(
    estimate_xy_yaw: np.ndarray, truth_xy_yaw: np.ndarray, *, valid: np.ndarray | None = None
) -> tuple[float, np.ndarray]:
    """The rigid planar motion ``(theta, t)`` that maps the estimate's positions onto the
    ground truth's in the least-squares sense (Kabsch / Umeyama without scale, by SVD of the
    2 x 2 cross-covariance; reflections excluded). On planar trajectories this is the SE(3)
    alignment ``evo_ape --align`` computes.

    Args:
        estimate_xy_yaw: ``[N 3]`` estimated poses ``(x [m], y [m], yaw [rad])``.
        truth_xy_yaw: ``[N 3]`` ground truth, row ``i`` at the same time as the estimate's.
        valid: optional ``[N]`` bool, rows to use (default: rows finite in both).

    Returns:
        ``(theta [rad], t [2] m)``: ``aligned_xy = R(theta) @ est_xy + t``.

    Raises:
        ValueError: bad shapes, or fewer than 2 usable rows.
    """
    est, gt, use = _paired(estimate_xy_yaw, truth_xy_yaw, valid)
    if use.sum() < 2:
        raise ValueError(f"need at least 2 finite, valid rows to align, got {int(use.sum())}")
    e, g = est[use, :2], gt[use, :2]
    me, mg = e.mean(0), g.mean(0)
    u, _, vt = np.linalg.svd((g - mg).T @ (e - me))
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    r = u @ np.diag([1.0, d]) @ vt
    theta = float(np.arctan2(r[1, 0], r[0, 0]))
    return theta, mg - r @ me


def absolute_trajectory_error(
    estimate_xy_yaw: np.ndarray,
    truth_xy_yaw: np.ndarray,
    *,
    align: bool = True,
    valid: np.ndarray | None = None,
) -> AbsoluteTrajectoryError:
    """Absolute trajectory error (ATE) per pose: the position errors of the estimate after
    an optional rigid alignment onto the ground truth (:func:`align_se2`), every row
    counted (unlike :func:`trajectory_errors`, which samples by distance travelled).
    ``evo_ape tum gt est --align`` gives the same RMSE on files written by
    :func:`lidarjax.datasets.write_tum` (tested).

    Args:
        estimate_xy_yaw: ``[N 3]`` estimated poses ``(x [m], y [m], yaw [rad])``.
        truth_xy_yaw: ``[N 3]`` ground truth at the same times.
        align: align first (default) or compare as given.
        valid: optional ``[N]`` bool, rows to use (default: rows finite in both).

    Returns:
        An :class:`AbsoluteTrajectoryError`.
    """
    est, gt, use = _paired(estimate_xy_yaw, truth_xy_yaw, valid)
    if not use.any():
        raise ValueError("no row is finite and valid in both trajectories")
    theta, t = align_se2(est, gt, valid=use) if align else (0.0, np.zeros(2))
    c, s_ = np.cos(theta), np.sin(theta)
    xy = est[:, :2] @ np.array([[c, s_], [-s_, c]]) + t
    aligned = np.column_stack([xy, _wrap(est[:, 2] + theta)])
    err = np.where(use, np.linalg.norm(xy - gt[:, :2], axis=1), np.nan)
    e = err[use]
    return AbsoluteTrajectoryError(
        rmse_m=float(np.sqrt(np.mean(e**2))),
        mean_m=float(np.mean(e)),
        median_m=float(np.median(e)),
        max_m=float(np.max(e)),
        n=int(use.sum()),
        rotation_rad=theta,
        translation_m=np.asarray(t, np.float64),
        errors_m=err,
        aligned=aligned,
    )


@dataclass(frozen=True)
class RelativePoseError:
    """Relative pose error (RPE) over pose pairs ``delta_m`` apart along the ground truth's
    path (what ``evo_rpe --delta <d> --delta_unit m --pairs_from_reference`` reports; drift
    per ``delta_m``).

    Attributes:
        rmse_m: Root mean square translation error of the relative motions (m).
        mean_m: Mean translation error (m).
        max_m: Largest translation error (m).
        rotation_rmse_rad: Root mean square rotation error of the relative motions (rad).
        rotation_mean_rad: Mean absolute rotation error (rad).
        n: Number of pairs.
        delta_m: The path distance between the poses of a pair (m).
        pairs: ``[n 2]`` row indices ``(i, j)`` of the pairs.
        translation_m: ``[n]`` translation error per pair (m).
        rotation_rad: ``[n]`` absolute rotation error per pair (rad).
    """

    rmse_m: float
    mean_m: float
    max_m: float
    rotation_rmse_rad: float
    rotation_mean_rad: float
    n: int
    delta_m: float
    pairs: np.ndarray
    translation_m: np.ndarray
    rotation_rad: np.ndarray


def _path_pairs(xy: np.ndarray, delta_m: float) -> np.ndarray:
    """Consecutive pairs along the path: from row ``i``, the first later row ``j`` whose
    path length from ``i`` (straight segments) is at least ``delta_m``; the next pair
    starts at ``j``. ``[n 2]`` int."""
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    pairs, start, acc = [], 0, 0.0
    for k, d in enumerate(step, start=1):  # evaluation code: a plain loop over rows
        acc += float(d)
        if acc >= delta_m:
            pairs.append((start, k))
            start, acc = k, 0.0
    return np.asarray(pairs, np.int64).reshape(-1, 2)


def relative_pose_error(
    estimate_xy_yaw: np.ndarray, truth_xy_yaw: np.ndarray, *, delta_m: float = 1.0
) -> RelativePoseError:
    """Relative pose error (RPE): how far the estimate's relative motion over ``delta_m`` of
    the ground truth's path differs from the true one (drift; alignment-free).

    Pairs ``(i, j)``: from row 0, the first row whose ground-truth path length from ``i``
    reaches ``delta_m``, then again from there (consecutive pairs along the ground truth's
    path, as ``evo_rpe --delta_unit m --pairs_from_reference``; evo's default takes the
    pairs along the estimate's path, which changes with the error being measured). For
    each pair the error motion is ``E = (G_i^-1 G_j)^-1 (P_i^-1 P_j)`` with ``G`` the
    ground-truth and ``P`` the estimated poses in SE(2); its translation norm (m) and the
    absolute value of its angle (rad) are reported. ``evo_rpe tum gt est --delta 1
    --delta_unit m --pairs_from_reference`` gives the same translation and rotation
    statistics on files written by :func:`lidarjax.datasets.write_tum` (tested).

    Args:
        estimate_xy_yaw: ``[N 3]`` estimated poses ``(x [m], y [m], yaw [rad])``.
        truth_xy_yaw: ``[N 3]`` ground truth at the same times.
        delta_m: path distance between the poses of a pair (m, > 0).

    Returns:
        A :class:`RelativePoseError`.

    Raises:
        ValueError: bad shapes, non-finite poses, a bad ``delta_m``, or a ground-truth path
            shorter than ``delta_m`` (no pair).
    """
    est, gt, use = _paired(estimate_xy_yaw, truth_xy_yaw, None)
    if not use.all() or not (np.isfinite(est[:, 2]).all() and np.isfinite(gt[:, 2]).all()):
        raise ValueError("estimate_xy_yaw and truth_xy_yaw must be finite everywhere for RPE")
    if not (isinstance(delta_m, (int, float, np.floating)) and np.isfinite(delta_m)):
        raise ValueError(f"delta_m must be a finite number > 0, got {delta_m!r}")
    if delta_m <= 0:
        raise ValueError(f"delta_m must be > 0, got {delta_m!r}")
    pairs = _path_pairs(gt[:, :2], float(delta_m))
    if pairs.shape[0] == 0:
        length = float(np.sum(np.linalg.norm(np.diff(gt[:, :2], axis=0), axis=1)))
        raise ValueError(
            f"the ground-truth path ({length:.3f} m) is shorter than delta_m = {delta_m} m: no pair"
        )
    i, j = pairs[:, 0], pairs[:, 1]

    def relative(p):  # P_i^-1 P_j as (x, y, yaw) in frame i
        c, s_ = np.cos(p[i, 2]), np.sin(p[i, 2])
        d = p[j, :2] - p[i, :2]
        return np.column_stack(
            [c * d[:, 0] + s_ * d[:, 1], -s_ * d[:, 0] + c * d[:, 1], p[j, 2] - p[i, 2]]
        )

    g, q = relative(gt), relative(est)
    # E = g^-1 q: translation R(-g_yaw) (q_t - g_t), angle q_yaw - g_yaw
    c, s_ = np.cos(g[:, 2]), np.sin(g[:, 2])
    dt = q[:, :2] - g[:, :2]
    et = np.hypot(c * dt[:, 0] + s_ * dt[:, 1], -s_ * dt[:, 0] + c * dt[:, 1])
    er = np.abs(_wrap(q[:, 2] - g[:, 2]))
    return RelativePoseError(
        rmse_m=float(np.sqrt(np.mean(et**2))),
        mean_m=float(np.mean(et)),
        max_m=float(np.max(et)),
        rotation_rmse_rad=float(np.sqrt(np.mean(er**2))),
        rotation_mean_rad=float(np.mean(er)),
        n=int(pairs.shape[0]),
        delta_m=float(delta_m),
        pairs=pairs,
        translation_m=et,
        rotation_rad=er,
    )
