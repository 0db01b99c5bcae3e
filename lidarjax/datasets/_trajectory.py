"""Trajectories out for the usual evaluation tools (evo, the TUM and KITTI scripts).

- TUM (``write_tum`` / ``read_tum``): one pose per line, ``t tx ty tz qx qy qz qw``
  (timestamp in seconds, translation in metres, unit quaternion with the scalar *last*).
- KITTI (``write_kitti_poses``; read with :func:`~lidarjax.datasets.load_kitti_poses`): one
  pose per line, the 12 entries of the row-major 3x4 matrix ``[R | t]``.

Poses are accepted as

- ``[n 3]`` planar poses ``(x, y, yaw)`` (m, m, rad): ``z = 0``, rotation ``yaw`` about z;
- ``[n 7]`` ``(tx, ty, tz, qw, qx, qy, qz)``: jaxlie's order, scalar *first*
  (``jaxlie.SE3.wxyz_xyz`` is the same numbers rotated: quaternion first);
- ``[n 4 4]`` homogeneous SE(3) or ``[n 3 3]`` homogeneous SE(2) matrices;
- any object with an ``as_matrix()`` method giving one of those, e.g. a batched
  ``jaxlie.SE2`` / ``jaxlie.SE3`` (``filter_info.estimate``).

Numbers are written with ``repr`` (the shortest text that reads back to the same float64),
so a file reads back exactly. NumPy only.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np

from ._errors import DatasetFormatError
from ._kitti import _read_rows

__all__ = ["TumTrajectory", "read_tum", "write_kitti_poses", "write_tum"]

_UNIT_TOL = 1e-6  # | |q| - 1 | allowed for a quaternion given to the writers
_ROT_TOL = 1e-6  # max |R^T R - I| allowed for a rotation matrix given to the writers
_READ_UNIT_TOL = 1e-3  # | |q| - 1 | allowed in a file (3 decimals or more); normalised
_TUM_FORMAT = "8 numbers per line: t tx ty tz qx qy qz qw (unit quaternion, scalar last)"


def _rows(x: np.ndarray) -> np.ndarray:
    """Row indices with a non-finite value."""
    return np.flatnonzero(~np.isfinite(x.reshape(x.shape[0], -1)).all(axis=1))


def _quat_from_matrix(rot: np.ndarray) -> np.ndarray:
    """``[n 3 3]`` rotation matrices -> ``[n 4]`` unit quaternions ``(w, x, y, z)``, w >= 0.

    Each row uses the largest of ``1 + tr R``, ``1 + 2 R_kk - tr R`` under the square root
    (Shepperd's method), so no division by a small number.
    """
    r = rot
    tr = r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2]
    cand = np.stack([tr, r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]], axis=1)
    k = np.argmax(cand, axis=1)
    q = np.empty((r.shape[0], 4))
    for case in range(4):
        sel = k == case
        if not sel.any():
            continue
        m = r[sel]
        if case == 0:
            s = 2.0 * np.sqrt(1.0 + tr[sel])
            q[sel] = np.stack(
                [0.25 * s, (m[:, 2, 1] - m[:, 1, 2]) / s, (m[:, 0, 2] - m[:, 2, 0]) / s,
                 (m[:, 1, 0] - m[:, 0, 1]) / s], axis=1)  # fmt: skip
        elif case == 1:
            s = 2.0 * np.sqrt(1.0 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2])
            q[sel] = np.stack(
                [(m[:, 2, 1] - m[:, 1, 2]) / s, 0.25 * s, (m[:, 0, 1] + m[:, 1, 0]) / s,
                 (m[:, 0, 2] + m[:, 2, 0]) / s], axis=1)  # fmt: skip
        elif case == 2:
            s = 2.0 * np.sqrt(1.0 + m[:, 1, 1] - m[:, 0, 0] - m[:, 2, 2])
            q[sel] = np.stack(
                [(m[:, 0, 2] - m[:, 2, 0]) / s, (m[:, 0, 1] + m[:, 1, 0]) / s, 0.25 * s,
                 (m[:, 1, 2] + m[:, 2, 1]) / s], axis=1)  # fmt: skip
        else:
            s = 2.0 * np.sqrt(1.0 + m[:, 2, 2] - m[:, 0, 0] - m[:, 1, 1])
            q[sel] = np.stack(
                [(m[:, 1, 0] - m[:, 0, 1]) / s, (m[:, 0, 2] + m[:, 2, 0]) / s,
                 (m[:, 1, 2] + m[:, 2, 1]) / s, 0.25 * s], axis=1)  # fmt: skip
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(q[:, :1] < 0, -q, q)


def _matrix_from_quat(q: np.ndarray) -> np.ndarray:
    """``[n 4]`` unit quaternions ``(w, x, y, z)`` -> ``[n 3 3]`` rotation matrices."""
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def _check_rotations(rot: np.ndarray, name: str) -> None:
    eye = np.eye(rot.shape[-1])
    dev = np.abs(np.swapaxes(rot, -1, -2) @ rot - eye).max(axis=(-2, -1))
    bad = (dev > _ROT_TOL) | (np.linalg.det(rot) <= 0)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"{name}[{i}]: rotation block is not a rotation matrix (max |R^T R - I| = "
            f"{dev[i]:.3g}, det {np.linalg.det(rot[i]):+.6g}; tolerance {_ROT_TOL})"
        )


def _check_bottom_row(m: np.ndarray, name: str) -> None:
    d = m.shape[-1]
    want = np.zeros(d)
    want[-1] = 1.0
    bad = ~(m[:, -1, :] == want).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{name}[{i}]: last row must be {want.tolist()}, got {m[i, -1].tolist()}")


def _as_array(poses: Any, name: str) -> np.ndarray:
    """float64 array of ``poses``; a jaxlie group (anything with ``as_matrix()``) as its
    homogeneous matrices, which must be batched."""
    if hasattr(poses, "as_matrix") and callable(poses.as_matrix):
        m = np.asarray(poses.as_matrix(), dtype=np.float64)
        if m.ndim != 3:
            raise ValueError(
                f"{name} must be a batched pose (as_matrix() of shape [n d d]), got a single "
                f"pose with matrix shape {m.shape}; add a leading axis"
            )
        return m
    return np.asarray(poses, dtype=np.float64)


def _poses_tq(poses: Any, name: str = "poses") -> tuple[np.ndarray, np.ndarray]:
    """Any accepted pose form -> ``(t [n 3] m, q [n 4] wxyz)``, validated."""
    p = _as_array(poses, name)
    if p.ndim == 0 or p.shape[0] == 0:
        raise ValueError(f"{name} must hold at least one pose, got shape {p.shape}")
    bad = _rows(p)
    if bad.size:
        raise ValueError(f"{name}[{int(bad[0])}] holds NaN or infinite values")
    if p.ndim == 2 and p.shape[1] == 3:
        half = 0.5 * p[:, 2]
        t = np.column_stack([p[:, 0], p[:, 1], np.zeros(p.shape[0])])
        zeros = np.zeros(p.shape[0])
        q = np.column_stack([np.cos(half), zeros, zeros, np.sin(half)])
        return t, q
    if p.ndim == 2 and p.shape[1] == 7:
        norm = np.linalg.norm(p[:, 3:], axis=1)
        off = np.abs(norm - 1.0) > _UNIT_TOL
        if off.any():
            i = int(np.flatnonzero(off)[0])
            raise ValueError(
                f"{name}[{i}]: quaternion (qw, qx, qy, qz) = {p[i, 3:].tolist()} has norm "
                f"{float(norm[i])!r}, not 1 within {_UNIT_TOL}"
            )
        return p[:, :3].copy(), p[:, 3:].copy()
    if p.ndim == 3 and p.shape[1:] == (4, 4):
        _check_bottom_row(p, name)
        _check_rotations(p[:, :3, :3], name)
        return p[:, :3, 3].copy(), _quat_from_matrix(p[:, :3, :3])
    if p.ndim == 3 and p.shape[1:] == (3, 3):
        _check_bottom_row(p, name)
        _check_rotations(p[:, :2, :2], name)
        yaw = np.arctan2(p[:, 1, 0], p[:, 0, 0])
        return _poses_tq(np.column_stack([p[:, 0, 2], p[:, 1, 2], yaw]), name)
    raise ValueError(
        f"{name} must have shape [n 3] (x, y, yaw), [n 7] (tx ty tz qw qx qy qz), [n 4 4] or "
        f"[n 3 3], got {p.shape}"
    )


def _fmt(rows: np.ndarray) -> str:
    return "".join(" ".join(map(repr, row)) + "\n" for row in rows.tolist())


def write_tum(path: str | os.PathLike[str], stamps_s: Any, poses: Any) -> Path:
    """Write a trajectory in the TUM RGB-D format (``evo_ape tum gt.tum est.tum``).

    Each line is ``t tx ty tz qx qy qz qw``: note the quaternion's scalar comes *last* in
    the file, first in ``[n 7]`` inputs (jaxlie's order).

    Args:
        path: Output file (overwritten).
        stamps_s: ``[n]`` timestamps (s), finite and strictly increasing.
        poses: ``[n 3]``, ``[n 7]``, ``[n 4 4]`` or ``[n 3 3]`` poses (see the module
            docstring), or a batched ``jaxlie.SE2`` / ``SE3``.

    Returns:
        The written path.

    Raises:
        ValueError: a bad shape, a non-finite value, a quaternion whose norm is not 1 within
            1e-6, a matrix whose rotation is not orthonormal within 1e-6, or a timestamp not
            after its predecessor; the message names the first bad row.
    """
    t, q = _poses_tq(poses)
    stamps = np.asarray(stamps_s, dtype=np.float64)
    if stamps.shape != (t.shape[0],):
        raise ValueError(f"stamps_s must have shape ({t.shape[0]},), got {stamps.shape}")
    bad = np.flatnonzero(~np.isfinite(stamps))
    if bad.size:
        raise ValueError(f"stamps_s[{int(bad[0])}] = {stamps[bad[0]]} is not finite")
    back = np.flatnonzero(np.diff(stamps) <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise ValueError(
            f"stamps_s must be strictly increasing: stamps_s[{i}] = {float(stamps[i])!r} is "
            f"not after stamps_s[{i - 1}] = {float(stamps[i - 1])!r}"
        )
    rows = np.column_stack([stamps, t, q[:, 1:], q[:, :1]])
    path = Path(path)
    path.write_text(_fmt(rows), encoding="ascii")
    return path


@dataclasses.dataclass(frozen=True)
class TumTrajectory:
    """A trajectory read by :func:`read_tum`.

    Attributes:
        stamps_s: float64 ``[n]`` timestamps (s), strictly increasing.
        poses: float64 ``[n 7]`` ``(tx, ty, tz, qw, qx, qy, qz)`` (m; unit quaternion in
            jaxlie's scalar-first order, so ``jaxlie.SE3(np.roll(poses, 4, axis=1))`` builds
            the SE(3) poses).
        path: the file.
    """

    stamps_s: np.ndarray
    poses: np.ndarray
    path: Path

    def as_matrices(self) -> np.ndarray:
        """float64 ``[n 4 4]`` homogeneous matrices ``T_world_body``."""
        out = np.zeros((self.poses.shape[0], 4, 4))
        out[:, :3, :3] = _matrix_from_quat(self.poses[:, 3:])
        out[:, :3, 3] = self.poses[:, :3]
        out[:, 3, 3] = 1.0
        return out

    def xy_yaw(self) -> np.ndarray:
        """float64 ``[n 3]`` planar poses ``(x, y, yaw)``: yaw is the heading of the body
        x axis projected onto the x-y plane (exact for rotations about z); z is dropped."""
        rot = _matrix_from_quat(self.poses[:, 3:])
        return np.column_stack(
            [self.poses[:, 0], self.poses[:, 1], np.arctan2(rot[:, 1, 0], rot[:, 0, 0])]
        )


def read_tum(path: str | os.PathLike[str]) -> TumTrajectory:
    """Read a TUM RGB-D trajectory file (``t tx ty tz qx qy qz qw`` per line).

    Blank lines and lines starting with ``#`` are skipped. Quaternions must have unit norm
    within 1e-3 (files commonly hold 4 to 6 decimals) and are returned normalised; all
    other numbers are returned exactly as written, so ``read_tum(write_tum(...))`` returns
    the timestamps and translations bit for bit and the quaternions to within 1 ulp.

    Args:
        path: The file.

    Returns:
        A :class:`TumTrajectory` (quaternions converted to scalar-first order).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        DatasetFormatError: a line without 8 numbers, a non-finite value, a quaternion that
            is not unit, a timestamp not after the previous one, or no poses; the message
            names the line.
    """
    path = Path(path)
    data, lines = _read_rows(path, 8, _TUM_FORMAT, what="poses")  # finite decimal numbers
    q_norm = np.linalg.norm(data[:, 4:], axis=1)
    bad_q = np.flatnonzero(np.abs(q_norm - 1.0) > _READ_UNIT_TOL)
    back = np.flatnonzero(data[1:, 0] <= data[:-1, 0]) + 1
    if bad_q.size or back.size:
        i, kind = min((int(idx[0]), kind) for idx, kind in ((bad_q, "q"), (back, "t")) if idx.size)
        if kind == "q":
            raise DatasetFormatError(
                path,
                f"quaternion norm {float(q_norm[i])!r} is not 1 within {_READ_UNIT_TOL}",
                line=lines[i],
                expected=_TUM_FORMAT,
            )
        raise DatasetFormatError(
            path,
            f"timestamp {float(data[i, 0])!r} is not after the previous one "
            f"({float(data[i - 1, 0])!r}, line {lines[i - 1]})",
            line=lines[i],
            expected=_TUM_FORMAT + ", timestamps strictly increasing",
        )
    q = np.column_stack([data[:, 7], data[:, 4:7]])  # scalar first
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    poses = np.column_stack([data[:, 1:4], q])
    stamps = np.ascontiguousarray(data[:, 0])
    for a in (stamps, poses):
        a.flags.writeable = False
    return TumTrajectory(stamps_s=stamps, poses=poses, path=path)


def write_kitti_poses(path: str | os.PathLike[str], poses: Any) -> Path:
    """Write poses in the KITTI odometry format (``evo_ape kitti gt.txt est.txt``).

    Each line holds the 12 entries of the row-major 3x4 matrix ``[R | t]``. KITTI's own
    ground truth is ``T_cam0_camk`` in camera axes (x right, y down, z forward); for a
    planar robot trajectory written from ``[n 3]`` poses the file is in the robot's world
    axes (z up). Read it back with ``load_kitti_poses(path, as_matrix=True)``.

    Args:
        path: Output file (overwritten).
        poses: ``[n 3]``, ``[n 7]``, ``[n 4 4]`` or ``[n 3 3]`` poses (see the module
            docstring), or a batched ``jaxlie.SE2`` / ``SE3``.

    Returns:
        The written path.

    Raises:
        ValueError: a bad shape, a non-finite value, a quaternion whose norm is not 1 within
            1e-6, or a matrix whose rotation is not orthonormal within 1e-6 (naming the row).
    """
    p = _as_array(poses, "poses")
    t, q = _poses_tq(p)  # validates
    if p.ndim == 3:  # [n 4 4] or [n 3 3]: the rotation as given, not through a quaternion
        rot = np.zeros((p.shape[0], 3, 3))
        d = p.shape[1] - 1
        rot[:, :d, :d] = p[:, :d, :d]
        if d == 2:
            rot[:, 2, 2] = 1.0
    elif p.shape[1] == 3:  # planar: exact cos / sin of the yaw
        c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
        rot = np.zeros((p.shape[0], 3, 3))
        rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1] = c, -s, s, c
        rot[:, 2, 2] = 1.0
    else:
        rot = _matrix_from_quat(q)
    rows = np.concatenate([rot, t[:, :, None]], axis=2).reshape(-1, 12)
    path = Path(path)
    path.write_text(_fmt(rows), encoding="ascii")
    return path
