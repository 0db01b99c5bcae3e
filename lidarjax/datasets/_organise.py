"""Organising the unordered cloud of a spinning multi-beam lidar into a ``[H, W]`` range image.

A spinning lidar fires ``H`` beams at fixed elevations and sweeps them around the vertical
axis; formats such as KITTI's ``.bin`` store the returns as an unordered ``[n, 3]`` list.
:func:`organise_scan` puts each point back into its cell of an organized
:class:`~lidarjax.datasets.PointCloud` (the input PPE and range-image methods need):

- row: the beam. Either the beam whose nominal elevation is nearest to the point's
  elevation ``atan2(z, hypot(x, y))`` (points farther than a tolerance from every beam are
  dropped and counted), or, when the cloud carries one (Velodyne and Ouster drivers write a
  ``ring`` field), the given ring index. Rows are ordered by elevation, **row 0 at the top**
  (highest beam), like an image.
- column: the azimuth ``atan2(y, x)``; column ``j`` is centred on
  ``azimuth_offset_rad + 2 pi j / W`` (column 0 looks along ``+x`` by default; the column
  index grows counter-clockwise seen from above) and spans ``+- pi / W`` around it.
- two points in one cell: the nearer one is kept, the other counted as a collision.

Beam layouts of common sensors: :func:`beam_elevations`. Everything is nominal geometry
from the sensor's origin: real sensors' beams start a few centimetres off the axis and
deviate from the datasheet by up to about half a degree per unit, so for real data prefer
the ring index, or widen ``max_elevation_error_rad``.

NumPy only; nothing here is called inside ``jit``. Vectorised: one sort for the collisions.
"""

from __future__ import annotations

import dataclasses
import math
import operator
from collections.abc import Mapping
from typing import Any

import numpy as np

from ._pcd import PointCloud

__all__ = ["OrganisedScan", "beam_elevations", "organise_scan"]

# Nominal beam elevations (degrees), ascending: index k is ring k of the Velodyne ROS driver
# (ring 0 = lowest beam).
#
# HDL-64E (KITTI's sensor): the Velodyne HDL-64E S2 datasheet gives a vertical field of view
# of "+2 deg up to -24.8 deg down with 64 equally spaced angular subdivisions (approximately
# 0.4 deg)", and the KITTI paper (Geiger et al., IJRR 2013) a 26.8 deg vertical field of
# view. Nominal only: the real sensor has two blocks of 32 lasers with different spacing and
# every unit ships with its own calibration of each laser's angle.
_HDL64E_DEG = np.linspace(-24.8, 2.0, 64)
# HDL-32E: -30.67 .. +10.67 deg in 31 equal steps of about 1.33 deg (datasheet: +10.67 to
# -30.67 deg); the same table as ``lidarjax.sim.HDL32E_ELEVATIONS_DEG`` (a test checks that).
_HDL32E_DEG = np.linspace(-30.67, 10.67, 32)
# VLP-16 (Puck): -15 .. +15 deg in 2 deg steps (datasheet: +-15 deg, 2 deg resolution).
_VLP16_DEG = np.arange(-15.0, 16.0, 2.0)

_LAYOUTS_DEG: dict[str, np.ndarray] = {
    "hdl64e": _HDL64E_DEG,
    "hdl32e": _HDL32E_DEG,
    "vlp16": _VLP16_DEG,
}
for _table in _LAYOUTS_DEG.values():
    _table.flags.writeable = False

_RESERVED = ("x", "y", "z", "range")


def beam_elevations(sensor: str) -> np.ndarray:
    """Nominal beam elevations of a spinning lidar, for :func:`organise_scan`.

    ``"hdl64e"``: Velodyne HDL-64E (KITTI), 64 beams equally spaced from -24.8 to +2.0 deg,
    the datasheet's nominal layout (the real sensor's two laser blocks are spaced about
    1/3 and 1/2 deg, and each unit has its own calibration). ``"hdl32e"``: Velodyne
    HDL-32E, 32 beams equally spaced from -30.67 to +10.67 deg (about 1.33 deg apart; the
    simulator's :func:`~lidarjax.sim.hdl32e` layout). ``"vlp16"``: Velodyne VLP-16, 16
    beams from -15 to +15 deg in 2 deg steps.

    Args:
        sensor: ``"hdl64e"``, ``"hdl32e"`` or ``"vlp16"`` (case-insensitive).

    Returns:
        ``[H]`` float64 elevations in radians, ascending: entry ``k`` is ring ``k`` as the
        Velodyne driver numbers them (ring 0 = lowest beam). A fresh, writeable array.

    Raises:
        ValueError: If ``sensor`` is not one of the names above.
    """
    key = sensor.lower() if isinstance(sensor, str) else sensor
    if key not in _LAYOUTS_DEG:
        raise ValueError(f"sensor must be one of {sorted(_LAYOUTS_DEG)}, got {sensor!r}")
    return np.deg2rad(_LAYOUTS_DEG[key])


@dataclasses.dataclass(frozen=True, eq=False)
class OrganisedScan:
    """Result of :func:`organise_scan`: the organized cloud and what did not fit into it.

    Every input point is counted exactly once: ``n_points == n_filled + n_collisions +
    n_dropped + n_invalid``.

    Attributes:
        cloud: ``[H, W]`` organized cloud with the fields ``x``, ``y``, ``z`` and ``range``
            (m; float32 for float32 input points, else float64) and the given extra fields.
            Cells without a point are NaN in the float fields and 0 in integer extra
            fields (use :attr:`filled`).
        n_dropped: valid points farther than the elevation tolerance from every beam (not
            in the cloud; always 0 when organised by ring).
        n_collisions: points that fell into an already taken cell and were farther than
            the point kept there (not in the cloud).
        n_invalid: points with a NaN / infinite coordinate or at the origin (not in the
            cloud).
        row_elevations_rad: ``[H]`` nominal elevation of each row (descending: row 0 is the
            highest beam).
        row_rings: ``[H]`` ring (index into ``elevations_rad``) of each row.
        column_azimuths_rad: ``[W]`` azimuth of each column's centre, in ``[-pi, pi)``.
    """

    cloud: PointCloud
    n_dropped: int
    n_collisions: int
    n_invalid: int
    row_elevations_rad: np.ndarray
    row_rings: np.ndarray
    column_azimuths_rad: np.ndarray

    @property
    def filled(self) -> np.ndarray:
        """``[H, W]`` bool: cells holding a point."""
        return np.isfinite(self.cloud["x"])

    @property
    def n_filled(self) -> int:
        """Number of points in the cloud (filled cells)."""
        return int(self.filled.sum())

    @property
    def n_points(self) -> int:
        """Number of input points."""
        return self.n_filled + self.n_collisions + self.n_dropped + self.n_invalid


def organise_scan(
    points: Any,
    *,
    elevations_rad: Any,
    n_columns: int,
    azimuth_offset_rad: float = 0.0,
    fields: Mapping[str, Any] | None = None,
    rings: Any = None,
    max_elevation_error_rad: float | None = None,
    max_dropped_fraction: float = 0.1,
) -> OrganisedScan:
    """Organizes a spinning-lidar cloud into an ``[H, W]`` grid (rows = beams, top first).

    Each point goes to the row of its beam and the column of its azimuth (see the module
    docstring); when two points share a cell the nearer one (smaller range) is kept, ties
    going to the earlier point. The beam is the ring given in ``rings`` if present, else the
    beam of nearest nominal elevation; a point whose elevation is farther than
    ``max_elevation_error_rad`` from every beam is dropped and counted in ``n_dropped``,
    and more than ``max_dropped_fraction`` of the valid points dropped is an error (a wrong
    layout, a cloud not in the sensor frame, or a sensor whose beams start off-axis).

    Args:
        points: ``[n, 3]`` float points ``x y z`` (m) in the sensor frame (``x`` forward,
            ``y`` left, ``z`` up), e.g. ``read_kitti_velodyne(path)[:, :3]``.
        elevations_rad: ``[H]`` beam elevations (rad) in ring order, distinct, inside
            ``(-pi/2, pi/2)``, e.g. :func:`beam_elevations`.
        n_columns: ``W``, columns per turn (e.g. 2048 for an HDL-64E at 10 Hz, whose
            azimuth step is about 0.17 deg).
        azimuth_offset_rad: azimuth of column 0's centre (rad).
        fields: extra per-point fields to organise along, name -> ``[n]`` array (e.g.
            ``{"intensity": scan[:, 3]}``); any dtype a PCD can store; names other than
            ``x``, ``y``, ``z``, ``range``.
        rings: ``[n]`` integer ring index of each point in ``[0, H)`` (index into
            ``elevations_rad``); when given it decides the row and no point is dropped.
        max_elevation_error_rad: elevation tolerance (rad) of the nearest-beam assignment;
            default half the smallest gap between two beams (every beam when ``H == 1``).
        max_dropped_fraction: largest accepted fraction of dropped valid points, in
            ``[0, 1]``.

    Returns:
        An :class:`OrganisedScan`.

    Raises:
        ValueError: If an argument has the wrong shape, type or range (it is named), or more
            than ``max_dropped_fraction`` of the valid points miss every beam.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(
            f"points must have shape [n, 3], got {pts.shape} (KITTI scans are [n, 4]: pass "
            "scan[:, :3] and the reflectance in fields=)"
        )
    if pts.dtype.kind != "f":
        raise ValueError(f"points must be a float array, got dtype {pts.dtype}")
    n = pts.shape[0]
    out_dtype = np.dtype(np.float32) if pts.dtype == np.float32 else np.dtype(np.float64)

    elev = np.asarray(elevations_rad, dtype=np.float64)
    if elev.ndim != 1 or elev.size < 1:
        raise ValueError(f"elevations_rad must have shape [H >= 1], got {elev.shape}")
    if not np.isfinite(elev).all() or (np.abs(elev) >= np.pi / 2).any():
        raise ValueError("elevations_rad must be finite and inside (-pi/2, pi/2)")
    ascending = np.sort(elev)
    gaps = np.diff(ascending)
    if (gaps <= 0).any():
        raise ValueError("elevations_rad must be distinct")
    h = elev.size

    if isinstance(n_columns, bool):
        raise ValueError(f"n_columns must be a positive integer, got {n_columns!r}")
    try:
        w = operator.index(n_columns)
    except TypeError:
        raise ValueError(f"n_columns must be a positive integer, got {n_columns!r}") from None
    if w < 1:
        raise ValueError(f"n_columns must be a positive integer, got {w}")
    offset = float(azimuth_offset_rad)
    if not math.isfinite(offset):
        raise ValueError(f"azimuth_offset_rad must be finite, got {azimuth_offset_rad!r}")
    if max_elevation_error_rad is None:
        tol = float(gaps.min()) / 2 if h > 1 else math.pi
    else:
        tol = float(max_elevation_error_rad)
        if not (math.isfinite(tol) and tol > 0):
            raise ValueError(
                f"max_elevation_error_rad must be finite and positive, got "
                f"{max_elevation_error_rad!r}"
            )
    frac = float(max_dropped_fraction)
    if not 0.0 <= frac <= 1.0:
        raise ValueError(f"max_dropped_fraction must be in [0, 1], got {max_dropped_fraction!r}")

    extra: dict[str, np.ndarray] = {}
    for name, value in (fields or {}).items():
        if name in _RESERVED:
            raise ValueError(f"fields must not contain {name!r}: organise_scan computes it")
        arr = np.asarray(value)
        if arr.shape != (n,):
            raise ValueError(f"fields[{name!r}] must have shape [{n}], got {list(arr.shape)}")
        extra[name] = arr

    ring_idx: np.ndarray | None = None
    if rings is not None:
        ring_arr = np.asarray(rings)
        if ring_arr.shape != (n,):
            raise ValueError(f"rings must have shape [{n}], got {list(ring_arr.shape)}")
        if ring_arr.dtype.kind not in "iu":
            raise ValueError(f"rings must be integers, got dtype {ring_arr.dtype}")
        if n and (int(ring_arr.min()) < 0 or int(ring_arr.max()) >= h):
            bad = int(ring_arr.min()) if int(ring_arr.min()) < 0 else int(ring_arr.max())
            raise ValueError(
                f"rings must be in [0, {h}) (one per entry of elevations_rad), got {bad}"
            )
        ring_idx = ring_arr.astype(np.int64)

    # Rows: beams by descending elevation (row 0 = highest beam).
    row_rings = np.argsort(-elev, kind="stable")
    row_of_ring = np.empty(h, dtype=np.int64)
    row_of_ring[row_rings] = np.arange(h)

    xyz = pts.astype(np.float64)
    rng = np.sqrt(np.sum(xyz * xyz, axis=1))
    valid = np.isfinite(xyz).all(axis=1) & (rng > 0)
    n_invalid = int(n - valid.sum())
    idx = np.flatnonzero(valid)
    x, y, z = xyz[idx, 0], xyz[idx, 1], xyz[idx, 2]

    if ring_idx is None:
        el = np.arctan2(z, np.hypot(x, y))
        order = np.argsort(elev, kind="stable")  # ascending[k] == elev[order[k]]
        hi = np.clip(np.searchsorted(ascending, el), 0, h - 1)
        lo = np.clip(hi - 1, 0, h - 1)
        near = np.where(np.abs(el - ascending[lo]) <= np.abs(el - ascending[hi]), lo, hi)
        ring = order[near]
        ok = np.abs(el - ascending[near]) <= tol
        n_dropped = int(idx.size - ok.sum())
        if n_dropped > frac * idx.size:
            raise ValueError(
                f"{n_dropped} of {idx.size} valid points ({n_dropped / idx.size:.1%}) lie "
                f"farther than {tol:.3g} rad from every beam of elevations_rad (more than "
                f"max_dropped_fraction = {frac}); wrong beam layout, points not in the sensor "
                "frame, or beams off the sensor axis: check elevations_rad, pass rings=, or "
                "raise max_elevation_error_rad / max_dropped_fraction"
            )
        idx, x, y, ring = idx[ok], x[ok], y[ok], ring[ok]
    else:
        n_dropped = 0
        ring = ring_idx[idx]

    az = np.arctan2(y, x) - offset
    col = np.rint(az * (w / (2 * np.pi))).astype(np.int64) % w
    cell = row_of_ring[ring] * w + col
    # Nearest point per cell: sort by (cell, range, input index), keep each cell's first.
    perm = np.lexsort((idx, rng[idx], cell))
    cell_sorted = cell[perm]
    first = np.ones(cell_sorted.size, dtype=bool)
    first[1:] = cell_sorted[1:] != cell_sorted[:-1]
    winners = idx[perm[first]]
    win_cells = cell_sorted[first]
    n_collisions = int(idx.size - winners.size)

    out: dict[str, np.ndarray] = {}
    for k, name in enumerate(("x", "y", "z")):
        grid = np.full(h * w, np.nan, dtype=out_dtype)
        grid[win_cells] = pts[winners, k]
        out[name] = grid.reshape(h, w)
    grid = np.full(h * w, np.nan, dtype=out_dtype)
    grid[win_cells] = rng[winners]
    out["range"] = grid.reshape(h, w)
    for name, arr in extra.items():
        fill = np.nan if arr.dtype.kind in "fc" else 0
        grid = np.full(h * w, fill, dtype=arr.dtype)
        grid[win_cells] = arr[winners]
        out[name] = grid.reshape(h, w)

    azimuths = offset + 2 * np.pi * np.arange(w) / w
    azimuths = (azimuths + np.pi) % (2 * np.pi) - np.pi
    return OrganisedScan(
        cloud=PointCloud(fields=out, width=w, height=h),
        n_dropped=n_dropped,
        n_collisions=n_collisions,
        n_invalid=n_invalid,
        row_elevations_rad=elev[row_rings],
        row_rings=row_rings,
        column_azimuths_rad=azimuths,
    )
