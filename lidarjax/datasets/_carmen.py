"""Reader for CARMEN laser logs (the Radish SLAM-corrected ``*-corrected.log.gz`` files).

Only ``FLASER`` messages are scans::

    FLASER n r_1 ... r_n x y theta odom_x odom_y odom_theta ipc_timestamp hostname logger_timestamp

``x y theta`` is the SLAM-corrected laser pose (ground truth), ``odom_*`` the raw odometry.
Two ``PARAM`` lines are honoured: ``laser_front_laser_resolution <deg>`` (angular step; without
it the field of view is 180 degrees) and ``robot_front_laser_max <m>`` (usable range). All
other messages (``ODOM``, ``NEFF``, other ``PARAM`` lines, ``#`` comments, ...) are ignored.
"""

from __future__ import annotations

import gzip
import math
import os
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._errors import DatasetFormatError
from ._text import NUMBER_FORMAT, NumberSyntaxError, is_decimal, is_integer, parse_numbers

__all__ = ["AZIMUTH_LAYOUTS", "CarmenLog", "load_carmen"]

_FLASER_FORMAT = (
    "'FLASER n r_1 .. r_n x y theta odom_x odom_y odom_theta ipc_timestamp hostname "
    "logger_timestamp' with n + 11 whitespace-separated tokens"
)
_RESOLUTION_PARAM = "laser_front_laser_resolution"
_MAX_RANGE_PARAM = "robot_front_laser_max"
_RESOLUTION_KEY = _RESOLUTION_PARAM.encode()
_MAX_RANGE_KEY = _MAX_RANGE_PARAM.encode()
_GZIP_MAGIC = b"\x1f\x8b"


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class CarmenLog:
    """Scans and poses of one CARMEN laser log.

    All arrays are float64 and read-only.

    Attributes:
        ranges_m: Raw range readings in metres, shape ``[n_scans, n_beams]``, unchanged from
            the file (no-returns keep the sensor's maximum value).
        azimuths_rad: Beam angles relative to the robot heading in radians, shape
            ``[n_beams]``, evenly spaced from ``-fov/2`` to ``+fov/2`` inclusive.
        poses: SLAM-corrected laser poses ``(x [m], y [m], theta [rad])`` in the map frame,
            shape ``[n_scans, 3]``.
        odometry: Raw odometry poses ``(x [m], y [m], theta [rad])``, shape ``[n_scans, 3]``.
        timestamps_s: IPC timestamps in seconds, shape ``[n_scans]``. Copied verbatim; in
            some logs they are constant or not monotone.
        max_range_m: The sensor's no-return value in metres (the largest reading in the log).
        usable_range_m: Readings at or beyond this range (metres) are no-returns.
        path: File the log was read from.
    """

    ranges_m: np.ndarray
    azimuths_rad: np.ndarray
    poses: np.ndarray
    odometry: np.ndarray
    timestamps_s: np.ndarray
    max_range_m: float
    usable_range_m: float
    path: Path

    @property
    def n_scans(self) -> int:
        """Number of scans."""
        return int(self.ranges_m.shape[0])

    @property
    def n_beams(self) -> int:
        """Number of beams per scan."""
        return int(self.ranges_m.shape[1])

    @property
    def fov_rad(self) -> float:
        """Angle between the first and the last beam in radians."""
        return float(self.azimuths_rad[-1] - self.azimuths_rad[0])

    @property
    def no_return(self) -> np.ndarray:
        """No-return mask ``ranges_m >= usable_range_m``, bool ``[n_scans, n_beams]``."""
        return self.ranges_m >= self.usable_range_m

    def subset(self, indices: slice | int | np.ndarray | list[int]) -> CarmenLog:
        """A new log holding only some scans.

        Args:
            indices: Anything that indexes the scan axis of a NumPy array: a slice, an
                integer, an integer array ``[k]`` or a boolean mask ``[n_scans]``.

        Returns:
            A log with the selected scans in the given order; ``azimuths_rad``,
            ``max_range_m``, ``usable_range_m`` and ``path`` are shared with this log.
        """
        if not isinstance(indices, slice):
            indices = np.asarray(indices)
            if indices.ndim == 0:
                indices = indices.reshape(1)
        return CarmenLog(
            ranges_m=_readonly(np.array(self.ranges_m[indices])),
            azimuths_rad=self.azimuths_rad,
            poses=_readonly(np.array(self.poses[indices])),
            odometry=_readonly(np.array(self.odometry[indices])),
            timestamps_s=_readonly(np.array(self.timestamps_s[indices])),
            max_range_m=self.max_range_m,
            usable_range_m=self.usable_range_m,
            path=self.path,
        )

    def __repr__(self) -> str:
        return (
            f"CarmenLog(path={str(self.path)!r}, n_scans={self.n_scans}, n_beams={self.n_beams}, "
            f"fov_deg={math.degrees(self.fov_rad):.2f}, max_range_m={self.max_range_m}, "
            f"usable_range_m={self.usable_range_m})"
        )


def _read_bytes(path: Path) -> bytes:
    raw = path.read_bytes()
    if raw[:2] == _GZIP_MAGIC:
        try:
            raw = gzip.decompress(raw)
        except (EOFError, gzip.BadGzipFile, zlib.error) as exc:
            raise DatasetFormatError(
                path,
                f"corrupt or truncated gzip stream ({type(exc).__name__}: {exc})",
                expected="a complete gzip-compressed CARMEN log",
            ) from exc
    # Kept as bytes: tokens are separated by ASCII whitespace only (str.split() would also
    # split at NBSP, NEL or control characters), and odd bytes surface as format errors.
    return raw


_MAX_FOV_DEG = 360.0


def _param_value(path: Path, tokens: list[bytes], lineno: int) -> float:
    name = tokens[1].decode("latin-1")
    limit = _MAX_FOV_DEG if name == _RESOLUTION_PARAM else math.inf
    value = math.nan
    if len(tokens) > 2 and is_decimal(tokens[2]):
        value = float(tokens[2])
    if not (math.isfinite(value) and 0 < value <= limit):
        got = tokens[2].decode("latin-1") if len(tokens) > 2 else "nothing"
        bound = f"in (0, {limit:g}]" if math.isfinite(limit) else "positive decimal"
        raise DatasetFormatError(
            path,
            f"invalid value {got!r} for PARAM {name}",
            line=lineno,
            expected=f"'PARAM {name} <{bound} number> ...'",
        )
    return value


NO_RETURN_MARGIN = 0.02
"""Readings within this fraction of the log's largest reading are no-returns."""


def _fail(path: Path, lineno: int, message: str) -> DatasetFormatError:
    return DatasetFormatError(path, message, line=lineno, expected=_FLASER_FORMAT)


AZIMUTH_LAYOUTS = ("spread", "sweep")
"""Values of :func:`load_carmen`'s ``azimuth_layout``."""


def _gaps(n_beams: int, layout: str) -> int:
    """Angular steps the field of view spans: ``n_beams - 1``, or ``n_beams`` for an even
    count in the sweep layout (a centred sweep of ``n_beams + 1`` beams, the last missing)."""
    return n_beams if layout == "sweep" and n_beams % 2 == 0 else n_beams - 1


def load_carmen(
    path: str | os.PathLike[str],
    *,
    usable_range_m: float | None = None,
    azimuth_layout: str = "spread",
) -> CarmenLog:
    """Load the ``FLASER`` scans of a CARMEN log.

    The file may be gzip-compressed (detected by its magic bytes) or plain text.

    Azimuths (``azimuth_layout``):

    - ``"spread"`` (default, the shared data's README): evenly spread from ``-fov / 2`` to
      ``+fov / 2`` inclusive, where the field of view is ``resolution * (n_beams - 1)``
      when the log has a ``PARAM laser_front_laser_resolution <deg>`` line, else 180
      degrees.
    - ``"sweep"``: the scanner's own layout, a sweep of ``2 m + 1`` beams centred on the
      heading at the angular step ``resolution`` (the ``PARAM``, else ``180 / (2 m)``
      degrees), beam ``i`` at ``(i - m) * resolution``; an odd count is the whole sweep
      (``m = (n_beams - 1) / 2``), an even count the sweep without its last beam
      (``m = n_beams / 2``: 180 beams lie at -90 ... +89 degrees, 360 at -90 ... +89.5).
      For odd counts both layouts agree. On the shared logs' corrected poses the sweep
      layout is the self-consistent one: with it the end points of scans at least 30
      apart lie closer to each other (median nearest-neighbour distance,
      ``lidarjax.metrics.cross_visit_distance``) on all seven logs with 180 or 360 beams
      (intel 9.95 -> 8.82 mm, fhw 18.84 -> 16.27 mm, edmonton 37.6 -> 33.2 mm,
      freiburg-101 11.3 -> 10.2 mm), and rotating the sweep by a quarter step either way
      raises that median on all seven.

    The no-return value ``max_range_m`` is the largest reading in the log. Unless given,
    ``usable_range_m`` is ``(1 - NO_RETURN_MARGIN) * max_range_m`` (sensors report
    saturated readings that scatter slightly below their maximum, e.g. 51.05-51.25 m), or
    ``PARAM robot_front_laser_max`` when present and smaller. If a ``PARAM`` appears several
    times, the last one wins.

    Args:
        path: Log file.
        usable_range_m: Override for the usable range in metres (readings at or beyond it
            are no-returns); must be positive.
        azimuth_layout: ``"spread"`` or ``"sweep"`` (above).

    Returns:
        The parsed log.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: ``usable_range_m`` is not a positive number, or ``azimuth_layout`` is
            not one of ``AZIMUTH_LAYOUTS``.
        DatasetFormatError: Truncated gzip, malformed ``FLASER`` line (wrong token count,
            a value that is not a plain decimal number such as ``1_5`` or ``0x1``, beam count
            differing from earlier scans, NaN, infinite or negative range, non-finite pose or
            timestamp), malformed honoured ``PARAM`` (not a positive decimal; a resolution
            above 360 degrees), a field of view ``resolution * (n_beams - 1)`` above 360
            degrees (``resolution * n_beams`` for an even count in the sweep layout), or no
            ``FLASER`` line at all. The message carries the 1-based line number. Tokens are
            separated by ASCII whitespace only.
    """
    path = Path(path)
    if not isinstance(azimuth_layout, str) or azimuth_layout not in AZIMUTH_LAYOUTS:
        raise ValueError(f"azimuth_layout must be one of {AZIMUTH_LAYOUTS}, got {azimuth_layout!r}")
    if usable_range_m is not None and not (math.isfinite(usable_range_m) and usable_range_m > 0):
        raise ValueError(f"usable_range_m must be a positive number, got {usable_range_m!r}")
    raw = _read_bytes(path)

    resolution_deg: float | None = None
    resolution_line = 0
    declared_max: float | None = None
    n_beams: int | None = None
    first_scan_line = 0
    rows: list[list[float]] = []
    line_numbers: list[int] = []  # 1-based line of each scan

    for lineno, line in enumerate(raw.split(b"\n"), start=1):
        if not line.startswith((b"FLASER", b"PARAM")):
            continue
        tokens = line.split()  # ASCII whitespace only
        kind = tokens[0]
        if kind == b"PARAM":
            if len(tokens) >= 2 and tokens[1] == _RESOLUTION_KEY:
                resolution_deg = _param_value(path, tokens, lineno)
                resolution_line = lineno
            elif len(tokens) >= 2 and tokens[1] == _MAX_RANGE_KEY:
                declared_max = _param_value(path, tokens, lineno)
            continue
        if kind != b"FLASER":
            continue  # e.g. "FLASERX": another message type

        if len(tokens) < 2:
            raise _fail(path, lineno, "FLASER line has no beam count")
        if not is_integer(tokens[1], signed=False):
            raise _fail(
                path, lineno, f"beam count {tokens[1].decode('latin-1')!r} is not an integer"
            )
        n = int(tokens[1])
        if n <= 0:
            raise _fail(path, lineno, f"beam count must be positive, got {n}")
        if n_beams is None:
            n_beams, first_scan_line = n, lineno
        elif n != n_beams:
            raise _fail(
                path,
                lineno,
                f"scan has {n} beams but the scan on line {first_scan_line} has {n_beams}",
            )
        if len(tokens) != n + 11:
            raise _fail(path, lineno, f"FLASER with n={n} has {len(tokens)} tokens, not {n + 11}")

        # Numeric tokens: r_1..r_n, 6 pose values, ipc_timestamp, (hostname), logger_ts.
        numeric = tokens[2 : n + 9]
        numeric.append(tokens[-1])
        try:
            rows.append(parse_numbers(numeric))
        except NumberSyntaxError as err:
            raise _fail(
                path, lineno, f"non-numeric value {err.token!r} ({NUMBER_FORMAT})"
            ) from None
        line_numbers.append(lineno)

    if not rows:
        raise DatasetFormatError(
            path, "no FLASER scans in the log (empty log)", expected=_FLASER_FORMAT
        )
    assert n_beams is not None
    data = np.array(rows, dtype=np.float64)  # [n_scans, n_beams + 8]
    _check_values(path, data, n_beams, line_numbers)
    ranges_m = np.ascontiguousarray(data[:, :n_beams])
    poses = np.ascontiguousarray(data[:, n_beams : n_beams + 3])
    odometry = np.ascontiguousarray(data[:, n_beams + 3 : n_beams + 6])
    timestamps_s = np.ascontiguousarray(data[:, n_beams + 6])

    gaps = _gaps(n_beams, azimuth_layout)
    fov_deg = 180.0 if resolution_deg is None else resolution_deg * gaps
    if not (math.isfinite(fov_deg) and fov_deg <= _MAX_FOV_DEG):
        raise DatasetFormatError(
            path,
            f"PARAM {_RESOLUTION_PARAM} {resolution_deg:g} deg with {n_beams} beams gives "
            f"a field of view of {fov_deg:g} deg",
            line=resolution_line,
            expected=f"resolution * ({'n_beams' if gaps == n_beams else 'n_beams - 1'}) "
            f"<= {_MAX_FOV_DEG:g} deg",
        )
    fov = math.radians(fov_deg)
    # Centred on the heading; a missing last beam ends the layout one step short.
    last = fov / 2 - (fov / gaps if gaps == n_beams else 0.0)
    azimuths = np.linspace(-fov / 2, last, n_beams) if n_beams > 1 else np.zeros(1)

    max_range = float(ranges_m.max())
    if usable_range_m is not None:
        usable = float(usable_range_m)
    else:
        # Saturated readings scatter a little below the largest one (e.g. 51.05-51.25 m),
        # so everything within NO_RETURN_MARGIN of the maximum counts as a no-return.
        usable = max_range * (1.0 - NO_RETURN_MARGIN)
        if declared_max is not None:
            usable = min(usable, declared_max)

    return CarmenLog(
        ranges_m=_readonly(ranges_m),
        azimuths_rad=_readonly(azimuths),
        poses=_readonly(poses),
        odometry=_readonly(odometry),
        timestamps_s=_readonly(timestamps_s),
        max_range_m=max_range,
        usable_range_m=usable,
        path=path,
    )


def _check_values(path: Path, data: np.ndarray, n_beams: int, line_numbers: list[int]) -> None:
    """Reject NaN/infinite/negative ranges and non-finite poses or timestamps."""
    ranges = data[:, :n_beams]
    bad_range = ~(ranges >= 0.0) | np.isinf(ranges)  # NaN compares False
    bad_other = ~np.isfinite(data[:, n_beams:])
    bad_rows = np.flatnonzero(bad_range.any(axis=1) | bad_other.any(axis=1))
    if bad_rows.size == 0:
        return
    row = int(bad_rows[0])
    if bad_range[row].any():
        i = int(np.flatnonzero(bad_range[row])[0])
        message = f"range r_{i + 1} = {ranges[row, i]!r} is negative or not finite"
    else:
        message = "pose, odometry or timestamp value is not finite"
    raise _fail(path, line_numbers[row], message)
