"""SynPEB scans: the organized-scan container and its PCD files (NumPy).

A SynPEB scan is an organized 3-D scan in which every point carries the ground-truth label
of the plane it lies on (0 = no return). :class:`SynPEBScan` holds one (the generated scans
of :func:`lidarjax.sim.simulate_synpeb_scan` and :func:`lidarjax.sim.synpeb_scan` are
such containers); :func:`write_synpeb_pcd` and :func:`load_synpeb_pcd` write and read the
SynPEB PCD layout (organized, fields ``x y z intensity``, the label in ``intensity``), e.g.
the shared crop ``synpeb/test_100.pcd`` of a published scan.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from ._errors import DatasetFormatError
from ._pcd import PointCloud, read_pcd, write_pcd

__all__ = ["SynPEBScan", "load_synpeb_pcd", "write_synpeb_pcd"]


@dataclasses.dataclass(frozen=True, eq=False)
class SynPEBScan:
    """A simulated organized SynPEB scan with ground-truth plane labels.

    Attributes:
        points: ``[H W 3]`` float64 points (m) in the sensor frame: noisy range times the
            nominal ray direction; NaN where there is no return.
        ranges: ``[H W]`` float64 noisy ranges (m), NaN where there is no return.
        labels: ``[H W]`` int64 ground-truth plane label of each point (0 = no return).
        azimuth_rad: ``[W]`` float64 nominal azimuth of each column (``atan2(y, x)``).
        elevation_rad: ``[H]`` float64 nominal elevation of each row (row 0 at the top).
        plane_normals: ``[P+1 3]`` float64 plane normals indexed by label (row 0 NaN).
        plane_offsets: ``[P+1]`` float64 plane offsets (m) indexed by label (row 0 NaN).
        adjacent_labels: ``[M 2]`` int64 label pairs sharing an edge (see
            :class:`SynPEBScene`).
        seed: the noise seed.
        scene_seed: the scene's seed (``None`` for hand-made scenes).
    """

    points: np.ndarray
    ranges: np.ndarray
    labels: np.ndarray
    azimuth_rad: np.ndarray
    elevation_rad: np.ndarray
    plane_normals: np.ndarray
    plane_offsets: np.ndarray
    adjacent_labels: np.ndarray
    seed: int
    scene_seed: int | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``, rows and columns of the scan."""
        return (int(self.labels.shape[0]), int(self.labels.shape[1]))


_SYNPEB_PCD_EXPECTED = (
    "an organized PCD (HEIGHT > 1) with fields x y z intensity, intensity holding the "
    "integer plane label (0 = no return)"
)


def write_synpeb_pcd(
    path: str | os.PathLike[str], scan: SynPEBScan, *, data: str = "binary_compressed"
) -> Path:
    """Writes a scan as a SynPEB PCD file: organized, fields ``x y z intensity`` (float32).

    The label is stored as a float32 in ``intensity``; points without return are NaN.

    Args:
        path: output file (overwritten).
        scan: the scan.
        data: PCD encoding, ``"ascii"``, ``"binary"`` or ``"binary_compressed"``.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ValueError: if ``scan`` is not a :class:`SynPEBScan` or ``data`` is unknown.
    """
    if not isinstance(scan, SynPEBScan):
        raise ValueError(f"scan must be a SynPEBScan, got {type(scan).__name__}")
    pts = np.asarray(scan.points, dtype=np.float32)
    fields = {
        "x": pts[..., 0],
        "y": pts[..., 1],
        "z": pts[..., 2],
        "intensity": np.asarray(scan.labels).astype(np.float32),
    }
    return write_pcd(path, PointCloud.from_fields(fields), data=data)


def load_synpeb_pcd(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Reads a SynPEB PCD file (organized; ``intensity`` holds the plane label).

    Args:
        path: the file, e.g. the shared ``synpeb/test_100.pcd`` crop.

    Returns:
        ``(points, labels)``: ``[H W 3]`` float64 points (m) and ``[H W]`` int64 labels;
        points with a NaN coordinate get label 0.

    Raises:
        DatasetFormatError: if the file is not an organized cloud with fields
            ``x y z intensity`` or a label is not a non-negative integer (a ``ValueError``).
    """
    cloud = read_pcd(path)
    missing = [k for k in ("x", "y", "z", "intensity") if k not in cloud]
    if missing:
        raise DatasetFormatError(
            path,
            f"missing field(s) {missing}; has {list(cloud.fields)}",
            expected=_SYNPEB_PCD_EXPECTED,
        )
    if not cloud.is_organized:
        raise DatasetFormatError(
            path,
            f"cloud is not organized (HEIGHT {cloud.height}, WIDTH {cloud.width})",
            expected=_SYNPEB_PCD_EXPECTED,
        )
    if any(cloud[k].ndim != 2 for k in ("x", "y", "z", "intensity")):
        raise DatasetFormatError(
            path, "fields x y z intensity must have COUNT 1", expected=_SYNPEB_PCD_EXPECTED
        )
    points = cloud.points_xyz
    valid = np.all(np.isfinite(points), axis=-1)
    raw = cloud["intensity"].astype(np.float64)
    good = np.isfinite(raw) & (raw >= 0) & (raw == np.round(raw))
    bad = valid & ~good
    if np.any(bad):
        row, col = np.argwhere(bad)[0]
        raise DatasetFormatError(
            path,
            f"intensity {raw[row, col]!r} at row {row}, column {col} is not a plane label",
            expected=_SYNPEB_PCD_EXPECTED,
        )
    labels = np.where(valid, np.where(good, raw, 0.0), 0.0).astype(np.int64)
    return points, labels
