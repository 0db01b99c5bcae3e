"""Readers for KITTI odometry ground-truth poses and timestamps.

Pose files hold one pose per line: the 12 numbers of the row-major 3x4 matrix ``[R | t]``
mapping points from the camera frame at that time to the first camera frame (camera axes:
x right, y down, z forward). Time files hold one timestamp in seconds per line.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal, overload

import jax.numpy as jnp
import jaxlie
import numpy as np

from ._errors import DatasetFormatError
from ._text import NumberSyntaxError, parse_numbers

__all__ = ["load_kitti_poses", "load_kitti_times"]

_POSES_FORMAT = "12 decimal numbers per line: row-major 3x4 [R | t] with R a rotation matrix"
_TIMES_FORMAT = "one finite decimal number (seconds) per line"
_ROTATION_TOL = 1e-3  # max deviation of the singular values of R from 1


def _read_rows(
    path: Path, n_cols: int, expected: str, what: str = "data rows"
) -> tuple[np.ndarray, list[int]]:
    """Parse a whitespace-separated numeric table with exactly ``n_cols`` columns.

    Lines end at ``\\n``; values are separated by ASCII whitespace and must be decimal
    numbers (``1_5``, ``0x1`` are rejected). Blank lines and ``#`` comment lines are skipped.

    Returns:
        float64 array ``[n_rows, n_cols]`` and the 1-based line number of each row.
    """
    rows: list[list[float]] = []
    lines: list[int] = []
    for lineno, line in enumerate(path.read_bytes().split(b"\n"), start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith(b"#"):
            continue
        if len(tokens) != n_cols:
            raise DatasetFormatError(
                path,
                f"found {len(tokens)} values, not {n_cols}",
                line=lineno,
                expected=expected,
            )
        try:
            values = parse_numbers(tokens)
        except NumberSyntaxError as exc:
            raise DatasetFormatError(
                path, f"non-numeric value ({exc})", line=lineno, expected=expected
            ) from None
        if not all(np.isfinite(values)):
            raise DatasetFormatError(
                path, "value is NaN or infinite", line=lineno, expected=expected
            )
        rows.append(values)
        lines.append(lineno)
    if not rows:
        raise DatasetFormatError(path, f"file holds no {what}", expected=expected)
    return np.asarray(rows, dtype=np.float64), lines


@overload
def load_kitti_poses(
    path: str | os.PathLike[str], *, as_matrix: Literal[False] = ...
) -> jaxlie.SE3: ...
@overload
def load_kitti_poses(path: str | os.PathLike[str], *, as_matrix: Literal[True]) -> np.ndarray: ...
def load_kitti_poses(
    path: str | os.PathLike[str], *, as_matrix: bool = False
) -> jaxlie.SE3 | np.ndarray:
    """Load KITTI odometry poses ``T_world_camera``.

    Each rotation block is re-orthonormalised with an SVD (the files store it rounded to 7
    significant digits); translations are returned as stored.

    Args:
        path: Pose file, ``n`` lines of 12 numbers.
        as_matrix: Return homogeneous NumPy matrices instead of a ``jaxlie.SE3``.

    Returns:
        ``jaxlie.SE3`` with batch shape ``[n]`` (translations in metres), or, with
        ``as_matrix=True``, a float64 array ``[n, 4, 4]``.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        DatasetFormatError: A line does not hold 12 finite numbers, its 3x3 block is not
            close to a rotation matrix, or the file has no poses. The message names the line.
    """
    path = Path(path)
    data, lines = _read_rows(path, 12, _POSES_FORMAT)
    data = data.reshape(-1, 3, 4)
    rot_raw = data[:, :, :3]  # [n, 3, 3]
    trans = np.ascontiguousarray(data[:, :, 3])  # [n, 3] metres

    u, s, vt = np.linalg.svd(rot_raw)
    det = np.linalg.det(u @ vt)  # [n], +-1
    bad = (np.abs(s - 1.0).max(axis=-1) > _ROTATION_TOL) | (det < 0)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise DatasetFormatError(
            path,
            f"3x3 block is not a rotation matrix (singular values {s[row].tolist()}, "
            f"det sign {det[row]:+.0f})",
            line=lines[row],
            expected=_POSES_FORMAT,
        )
    rot = u @ vt  # nearest rotation; det = +1 checked above

    if as_matrix:
        out = np.zeros((data.shape[0], 4, 4))
        out[:, :3, :3] = rot
        out[:, :3, 3] = trans
        out[:, 3, 3] = 1.0
        return out
    return jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.from_matrix(jnp.asarray(rot)), jnp.asarray(trans)
    )


def load_kitti_times(path: str | os.PathLike[str]) -> np.ndarray:
    """Load KITTI odometry timestamps.

    Args:
        path: Times file, one number per line.

    Returns:
        float64 array ``[n]`` of timestamps in seconds.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        DatasetFormatError: A line does not hold exactly one finite number, or the file is
            empty. The message names the line.
    """
    return _read_rows(Path(path), 1, _TIMES_FORMAT)[0][:, 0]
