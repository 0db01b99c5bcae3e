"""Readers and writers for raw lidar scans of the KITTI odometry and NCLT datasets.

KITTI odometry (Geiger et al., "Are we ready for autonomous driving?", CVPR 2012):

- ``sequences/<seq>/velodyne/<frame>.bin``: flat little-endian float32 quadruples
  ``x y z reflectance`` per point; x, y, z in metres in the Velodyne HDL-64E frame
  (x forward, y left, z up), reflectance in ``[0, 1]``. No header.
- ``sequences/<seq>/calib.txt``: lines ``<name>: <numbers>``; the line ``Tr:`` holds the 12
  numbers of the row-major 3x4 matrix ``T_cam_velo`` mapping Velodyne points into the left
  (rectified) camera frame ``cam0``.
- ``sequences/<seq>/times.txt`` and ``poses/<seq>.txt``: see :mod:`._kitti`.

NCLT (Carlevaris-Bianco et al., "University of Michigan North Campus long-term vision and
lidar dataset", IJRR 2016; the format follows the authors' ``read_vel_sync.py`` and
``read_vel_hits.py``):

- A *hit* is 8 little-endian bytes: ``x, y, z`` as uint16, ``intensity`` uint8, ``laser id``
  uint8. Coordinates are stored in 5 mm steps offset by 100 m: ``metres = raw * 0.005 - 100``
  (so the representable range is ``[-100, 227.675]`` m). Points are in the Velodyne
  HDL-32E frame.
- ``velodyne_sync/<utime>.bin``: the hits of one full revolution, nothing else.
- ``velodyne_hits.bin``: a stream of packets, each ``[magic: 4 x uint16 = 44444 (0xAD9C)]
  [num_hits: uint32] [utime: uint64, microseconds] [4 bytes padding] [num_hits hits]``.
- ``groundtruth_<date>.csv``: comma-separated rows ``utime, x, y, z, roll, pitch, yaw``
  (microseconds, metres, radians); some rows (typically at the start) hold NaN.

NumPy only; nothing here is called inside ``jit``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import struct
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ._errors import DatasetFormatError
from ._kitti import load_kitti_poses, load_kitti_times
from ._text import NumberSyntaxError, is_decimal, is_integer, is_number, parse_numbers

__all__ = [
    "KittiSequence",
    "NcltGroundTruth",
    "NcltHitsPacket",
    "iter_nclt_velodyne_hits",
    "load_kitti_sequence",
    "nclt_ground_truth_se2",
    "read_kitti_velodyne",
    "read_nclt_ground_truth",
    "read_nclt_velodyne_hits",
    "read_nclt_velodyne_sync",
    "write_kitti_velodyne",
    "write_nclt_ground_truth",
    "write_nclt_velodyne_hits",
    "write_nclt_velodyne_sync",
]

# --------------------------------------------------------------------------------------------
# KITTI
# --------------------------------------------------------------------------------------------

_KITTI_BIN_FORMAT = "little-endian float32 quadruples x y z reflectance (16 bytes per point)"
_KITTI_CALIB_FORMAT = "'Tr:' followed by 12 decimal numbers (row-major 3x4 T_cam_velo)"
_KITTI_DTYPE = np.dtype("<f4")


def read_kitti_velodyne(path: str | os.PathLike[str]) -> np.ndarray:
    """Read one KITTI odometry Velodyne scan (``velodyne/<frame>.bin``).

    Args:
        path: Binary scan file.

    Returns:
        float32 array ``[n, 4]``: x, y, z in metres in the Velodyne frame (x forward, y left,
        z up) and the reflectance (nominally in ``[0, 1]``). An empty file gives ``[0, 4]``.

    Raises:
        FileNotFoundError: ``path`` does not exist (the message names it).
        DatasetFormatError: The file size is not a multiple of 16 bytes, or a value is NaN or
            infinite (the message names the point index and its byte offset).
    """
    path = Path(path)
    with open(path, "rb") as f:
        data = f.read()
    if len(data) % 16:
        raise DatasetFormatError(
            path,
            f"file size {len(data)} bytes is not a multiple of 16 (truncated or not a KITTI scan)",
            expected=_KITTI_BIN_FORMAT,
        )
    points = np.frombuffer(data, dtype=_KITTI_DTYPE).reshape(-1, 4).astype(np.float32)
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        idx = int(np.flatnonzero(~finite)[0])
        raise DatasetFormatError(
            path,
            f"point {idx} (byte offset {16 * idx}) holds a NaN or infinite value "
            f"{points[idx].tolist()}",
            expected=_KITTI_BIN_FORMAT,
        )
    return points


def write_kitti_velodyne(path: str | os.PathLike[str], points: np.ndarray) -> None:
    """Write a KITTI odometry Velodyne scan.

    Args:
        path: Output file (overwritten).
        points: ``[n, 4]`` (x, y, z in metres, reflectance) or ``[n, 3]`` (reflectance 0).
            Stored as little-endian float32, so values are rounded to float32.

    Raises:
        ValueError: ``points`` does not have shape ``[n, 3]`` or ``[n, 4]``.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] not in (3, 4):
        raise ValueError(f"points must have shape [n, 3] or [n, 4], got {pts.shape}")
    out = np.zeros((pts.shape[0], 4), dtype=_KITTI_DTYPE)
    out[:, : pts.shape[1]] = pts
    with open(path, "wb") as f:
        f.write(out.tobytes())


def _read_kitti_calib_tr(path: Path) -> np.ndarray | None:
    """Parse the ``Tr:`` line of a KITTI ``calib.txt`` into a ``[4, 4]`` matrix.

    Returns ``None`` if the file has no ``Tr:`` line.
    """
    for lineno, line in enumerate(path.read_bytes().split(b"\n"), start=1):
        key, sep, rest = line.partition(b":")
        if not sep or key.strip() != b"Tr":
            continue
        tokens = rest.split()  # ASCII whitespace only
        if len(tokens) != 12:
            raise DatasetFormatError(
                path,
                f"'Tr:' line holds {len(tokens)} values, not 12",
                line=lineno,
                expected=_KITTI_CALIB_FORMAT,
            )
        try:
            values = np.array(parse_numbers(tokens))
        except NumberSyntaxError as exc:
            raise DatasetFormatError(
                path, f"non-numeric value ({exc})", line=lineno, expected=_KITTI_CALIB_FORMAT
            ) from None
        if not np.isfinite(values).all():
            raise DatasetFormatError(
                path, "value is NaN or infinite", line=lineno, expected=_KITTI_CALIB_FORMAT
            )
        mat = np.eye(4)
        mat[:3, :] = values.reshape(3, 4)
        return mat
    return None


@dataclasses.dataclass(frozen=True, eq=False)
class KittiSequence:
    """One KITTI odometry sequence: scan files, ground-truth poses, times, calibration.

    Attributes:
        root: Dataset root (holding ``sequences/`` and ``poses/``).
        sequence: Sequence name, e.g. ``"00"``.
        poses: float64 ``[n, 4, 4]`` ground-truth poses ``T_world_cam`` (camera ``cam0`` at
            scan time to the first camera frame; metres).
        times: float64 ``[n]`` scan timestamps in seconds, or ``None`` when
            ``sequences/<seq>/times.txt`` is absent.
        scan_paths: The ``n`` scan files, sorted by name.
        T_cam_velo: float64 ``[4, 4]`` Velodyne-to-camera transform from the ``Tr:`` line of
            ``sequences/<seq>/calib.txt``; the identity when that file or line is absent
            (then ``poses`` are *not* Velodyne poses; check ``has_calibration``).
        has_calibration: Whether ``T_cam_velo`` was read from a file.
    """

    root: Path
    sequence: str
    poses: np.ndarray
    times: np.ndarray | None
    scan_paths: tuple[Path, ...]
    T_cam_velo: np.ndarray
    has_calibration: bool

    def __len__(self) -> int:
        """Number of scans (= number of poses)."""
        return len(self.scan_paths)

    def scan(self, i: int) -> np.ndarray:
        """Read scan ``i`` (supports negative indices).

        Returns:
            float32 ``[n_i, 4]`` points (x, y, z in metres in the Velodyne frame, reflectance).

        Raises:
            IndexError: ``i`` is out of range.
        """
        return read_kitti_velodyne(self.scan_paths[i])

    @property
    def velodyne_poses(self) -> np.ndarray:
        """float64 ``[n, 4, 4]`` poses ``T_world_velo = T_world_cam @ T_cam_velo``."""
        return self.poses @ self.T_cam_velo


def load_kitti_sequence(root: str | os.PathLike[str], sequence: str | int = "00") -> KittiSequence:
    """Index a KITTI odometry sequence laid out as in the official archives.

    Expected layout::

        root/poses/<sequence>.txt                   (required)
        root/sequences/<sequence>/velodyne/*.bin    (required, at least one scan)
        root/sequences/<sequence>/times.txt         (optional; ``times`` is None if absent)
        root/sequences/<sequence>/calib.txt         (optional; identity ``T_cam_velo`` if
                                                     absent or without a ``Tr:`` line)

    Scans are not read here; use :meth:`KittiSequence.scan`.

    Args:
        root: Dataset root directory.
        sequence: Sequence name, e.g. ``"00"``; an int is zero-padded to two digits.

    Returns:
        The indexed sequence.

    Raises:
        FileNotFoundError: The pose file or the ``velodyne`` folder is missing, or the
            folder holds no ``.bin`` file.
        DatasetFormatError: The numbers of scans, poses and (if present) times differ, or a
            pose/time/calibration file is malformed.
    """
    root = Path(root)
    if isinstance(sequence, int):
        sequence = f"{sequence:02d}"
    seq_dir = root / "sequences" / sequence
    velo_dir = seq_dir / "velodyne"
    pose_path = root / "poses" / f"{sequence}.txt"
    if not velo_dir.is_dir():
        raise FileNotFoundError(f"KITTI scan folder not found: {velo_dir}")
    scan_paths = tuple(sorted(velo_dir.glob("*.bin")))
    if not scan_paths:
        raise FileNotFoundError(f"no .bin scans in KITTI scan folder {velo_dir}")
    if not pose_path.is_file():
        raise FileNotFoundError(f"KITTI pose file not found: {pose_path}")
    poses = load_kitti_poses(pose_path, as_matrix=True)
    if len(poses) != len(scan_paths):
        raise DatasetFormatError(
            pose_path,
            f"{len(poses)} poses but {len(scan_paths)} scans in {velo_dir}",
            expected="one pose per scan",
        )
    times_path = seq_dir / "times.txt"
    times = None
    if times_path.is_file():
        times = load_kitti_times(times_path)
        if len(times) != len(scan_paths):
            raise DatasetFormatError(
                times_path,
                f"{len(times)} timestamps but {len(scan_paths)} scans in {velo_dir}",
                expected="one timestamp per scan",
            )
    calib_path = seq_dir / "calib.txt"
    T_cam_velo = _read_kitti_calib_tr(calib_path) if calib_path.is_file() else None
    has_calibration = T_cam_velo is not None
    if T_cam_velo is None:
        T_cam_velo = np.eye(4)
    return KittiSequence(
        root=root,
        sequence=sequence,
        poses=poses,
        times=times,
        scan_paths=scan_paths,
        T_cam_velo=T_cam_velo,
        has_calibration=has_calibration,
    )


# --------------------------------------------------------------------------------------------
# NCLT
# --------------------------------------------------------------------------------------------

NCLT_SCALE_M = 0.005  # metres per raw unit
NCLT_OFFSET_M = -100.0  # metres at raw value 0
NCLT_MAGIC = 44444  # 0xAD9C, repeated four times at the start of every hits packet

_NCLT_HIT_DTYPE = np.dtype(
    [("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("intensity", "u1"), ("laser_id", "u1")]
)
assert _NCLT_HIT_DTYPE.itemsize == 8
_NCLT_HEADER = struct.Struct("<4HIQ4x")  # magic x4, num_hits, utime, padding: 24 bytes
_NCLT_HIT_FORMAT = "8-byte hits: uint16 x, y, z (raw * 0.005 - 100 m), uint8 intensity, laser id"
_NCLT_PACKET_FORMAT = (
    "packets of 4 x uint16 magic 44444, uint32 num_hits, uint64 utime, 4 padding bytes, "
    "then num_hits 8-byte hits"
)
_NCLT_GT_FORMAT = (
    "7 comma-separated decimal numbers per row: integer utime, x, y, z, roll, pitch, yaw "
    "(nan allowed)"
)


class NcltHitsPacket(NamedTuple):
    """One packet of an NCLT ``velodyne_hits.bin`` file.

    Attributes:
        utime: Timestamp in microseconds (np.int64).
        points: float64 ``[n, 3]`` x, y, z in metres (Velodyne frame).
        intensity: uint8 ``[n]``.
        laser_id: uint8 ``[n]`` (0..31 for the HDL-32E).
    """

    utime: np.int64
    points: np.ndarray
    intensity: np.ndarray
    laser_id: np.ndarray


class NcltGroundTruth(NamedTuple):
    """Rows of an NCLT ``groundtruth_<date>.csv`` file (all rows, none dropped).

    Attributes:
        utime: int64 ``[N]`` timestamps in microseconds.
        xyz_rpy: float64 ``[N, 6]`` x, y, z (metres), roll, pitch, yaw (radians), in NCLT's
            frame (x north, y east, z down); NaN where the file holds NaN.
        valid: bool ``[N]``, False for the rows with a NaN (``(~valid).sum()`` is the number
            of such rows).
    """

    utime: np.ndarray
    xyz_rpy: np.ndarray
    valid: np.ndarray


def _decode_hits(raw: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xyz = np.stack([raw["x"], raw["y"], raw["z"]], axis=-1).astype(np.float64)
    points = xyz * NCLT_SCALE_M + NCLT_OFFSET_M
    return points, raw["intensity"].copy(), raw["laser_id"].copy()


def _encode_hits(points: np.ndarray, intensity: np.ndarray, laser_id: np.ndarray) -> bytes:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape [n, 3], got {pts.shape}")
    n = pts.shape[0]
    if not np.isfinite(pts).all():
        raise ValueError("points hold NaN or infinite values")
    raw = np.round((pts - NCLT_OFFSET_M) / NCLT_SCALE_M)
    if raw.size and (raw.min() < 0 or raw.max() > 65535):
        lo, hi = NCLT_OFFSET_M, NCLT_OFFSET_M + 65535 * NCLT_SCALE_M
        raise ValueError(f"points must lie in [{lo}, {hi}] m per coordinate")
    out = np.zeros(n, dtype=_NCLT_HIT_DTYPE)
    out["x"], out["y"], out["z"] = raw[:, 0], raw[:, 1], raw[:, 2]
    for name, value in (("intensity", intensity), ("laser_id", laser_id)):
        arr = np.asarray(value)
        if arr.shape != (n,):
            raise ValueError(f"{name} must have shape [{n}], got {arr.shape}")
        if arr.size and (
            not np.array_equal(arr, np.round(arr)) or arr.min() < 0 or arr.max() > 255
        ):
            raise ValueError(f"{name} must hold integers in [0, 255]")
        out[name] = arr
    return out.tobytes()


def read_nclt_velodyne_sync(
    path: str | os.PathLike[str],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read one NCLT ``velodyne_sync/<utime>.bin`` scan.

    Args:
        path: Binary scan file (a packed sequence of 8-byte hits).

    Returns:
        ``(points, intensity, laser_id)``: float64 ``[n, 3]`` x, y, z in metres
        (``raw * 0.005 - 100``, Velodyne frame), uint8 ``[n]``, uint8 ``[n]``.

    Raises:
        FileNotFoundError: ``path`` does not exist (the message names it).
        DatasetFormatError: The file size is not a multiple of 8 bytes.
    """
    path = Path(path)
    with open(path, "rb") as f:
        data = f.read()
    if len(data) % 8:
        raise DatasetFormatError(
            path,
            f"file size {len(data)} bytes is not a multiple of 8 (truncated?)",
            expected=_NCLT_HIT_FORMAT,
        )
    return _decode_hits(np.frombuffer(data, dtype=_NCLT_HIT_DTYPE))


def write_nclt_velodyne_sync(
    path: str | os.PathLike[str],
    points: np.ndarray,
    intensity: np.ndarray,
    laser_id: np.ndarray,
) -> None:
    """Write an NCLT ``velodyne_sync`` scan (inverse of :func:`read_nclt_velodyne_sync`).

    Args:
        path: Output file (overwritten).
        points: ``[n, 3]`` metres, each coordinate in ``[-100, 227.675]``; rounded to 5 mm.
        intensity: ``[n]`` integers in ``[0, 255]``.
        laser_id: ``[n]`` integers in ``[0, 255]``.

    Raises:
        ValueError: Wrong shapes, non-finite points or values out of range.
    """
    payload = _encode_hits(points, intensity, laser_id)
    with open(path, "wb") as f:
        f.write(payload)


def iter_nclt_velodyne_hits(
    path: str | os.PathLike[str], max_packets: int | None = None
) -> Iterator[NcltHitsPacket]:
    """Stream the packets of an NCLT ``velodyne_hits.bin`` file (memory use: one packet).

    Args:
        path: The hits file.
        max_packets: Stop after this many packets (``None``: read to the end).

    Yields:
        :class:`NcltHitsPacket` ``(utime, points [n, 3] m, intensity [n], laser_id [n])``.

    Raises:
        FileNotFoundError: ``path`` does not exist (the message names it).
        DatasetFormatError: A packet does not start with the magic, or a header or the hits
            of a packet are truncated (``num_hits`` is checked against the file size before
            anything is read); the message quotes the byte offset.
        ValueError: ``max_packets`` is negative.
    """
    if max_packets is not None and max_packets < 0:
        raise ValueError(f"max_packets must be >= 0 or None, got {max_packets}")
    path = Path(path)
    with open(path, "rb") as f:
        file_size = os.fstat(f.fileno()).st_size
        offset = 0
        count = 0
        while max_packets is None or count < max_packets:
            header = f.read(_NCLT_HEADER.size)
            if not header:
                return
            if len(header) < 8 or struct.unpack_from("<4H", header) != (NCLT_MAGIC,) * 4:
                got = header[:8].hex()
                raise DatasetFormatError(
                    path,
                    f"bad packet magic at byte offset {offset} (packet {count}): got 0x{got}, "
                    f"expected 4 x uint16 {NCLT_MAGIC} (0x9cad9cad9cad9cad on disk)",
                    expected=_NCLT_PACKET_FORMAT,
                )
            if len(header) < _NCLT_HEADER.size:
                raise DatasetFormatError(
                    path,
                    f"truncated packet header at byte offset {offset} (packet {count}): "
                    f"{len(header)} of {_NCLT_HEADER.size} bytes",
                    expected=_NCLT_PACKET_FORMAT,
                )
            *_, num_hits, utime = _NCLT_HEADER.unpack(header)
            if utime > np.iinfo(np.int64).max:
                raise DatasetFormatError(
                    path,
                    f"utime {utime} at byte offset {offset + 12} does not fit in int64",
                    expected=_NCLT_PACKET_FORMAT,
                )
            available = file_size - offset - _NCLT_HEADER.size
            if 8 * num_hits > available:  # checked before reading: num_hits may be ~2**32
                raise DatasetFormatError(
                    path,
                    f"truncated packet at byte offset {offset} (packet {count}): header "
                    f"announces {num_hits} hits ({8 * num_hits} bytes), only "
                    f"{max(available, 0)} bytes follow in the {file_size}-byte file",
                    expected=_NCLT_PACKET_FORMAT,
                )
            body = f.read(8 * num_hits)
            if len(body) != 8 * num_hits:  # the file shrank while being read
                raise DatasetFormatError(
                    path,
                    f"truncated packet at byte offset {offset} (packet {count}): header "
                    f"announces {num_hits} hits ({8 * num_hits} bytes), only {len(body)} "
                    "bytes follow",
                    expected=_NCLT_PACKET_FORMAT,
                )
            points, intensity, laser_id = _decode_hits(np.frombuffer(body, _NCLT_HIT_DTYPE))
            yield NcltHitsPacket(np.int64(utime), points, intensity, laser_id)
            offset += _NCLT_HEADER.size + 8 * num_hits
            count += 1


def read_nclt_velodyne_hits(
    path: str | os.PathLike[str], max_packets: int | None = None
) -> list[NcltHitsPacket]:
    """Read the packets of an NCLT ``velodyne_hits.bin`` file into a list.

    The full files are tens of GB; use ``max_packets`` or :func:`iter_nclt_velodyne_hits`.

    Args:
        path: The hits file.
        max_packets: Read at most this many packets (``None``: all).

    Returns:
        List of :class:`NcltHitsPacket` ``(utime int64 us, points float64 [n, 3] m,
        intensity uint8 [n], laser_id uint8 [n])``, in file order.

    Raises:
        FileNotFoundError: ``path`` does not exist (the message names it).
        DatasetFormatError: Bad magic or truncation; the message quotes the byte offset.
    """
    return list(iter_nclt_velodyne_hits(path, max_packets))


def write_nclt_velodyne_hits(
    path: str | os.PathLike[str],
    packets: Iterable[tuple[int, np.ndarray, np.ndarray, np.ndarray]],
) -> None:
    """Write an NCLT ``velodyne_hits.bin`` file (inverse of :func:`read_nclt_velodyne_hits`).

    Args:
        path: Output file (overwritten).
        packets: ``(utime, points [n, 3] m, intensity [n], laser_id [n])`` tuples; ``utime`` a
            non-negative integer (microseconds). Padding bytes are written as zeros.

    Raises:
        ValueError: Invalid utime, shapes or values out of range (see
            :func:`write_nclt_velodyne_sync`).
    """
    with open(path, "wb") as f:
        for utime, points, intensity, laser_id in packets:
            payload = _encode_hits(points, intensity, laser_id)
            utime_int = int(utime)
            if utime_int != utime or not 0 <= utime_int <= np.iinfo(np.int64).max:
                raise ValueError(f"utime must be a non-negative int64, got {utime!r}")
            f.write(_NCLT_HEADER.pack(*(NCLT_MAGIC,) * 4, len(payload) // 8, utime_int))
            f.write(payload)


_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1
_EXACT_FLOAT_INT = 2**53  # float64 holds every integer up to this exactly


def _parse_utime(token: bytes) -> int:
    """An integer literal in int64, or a decimal literal of an exactly representable integer."""
    text = token.decode("latin-1")
    if is_integer(token):
        value = int(token)
        if not _INT64_MIN <= value <= _INT64_MAX:
            raise ValueError(f"utime {text!r} does not fit in int64")
        return value
    if is_decimal(token):
        value = float(token)
        if math.isfinite(value) and value == int(value) and abs(value) <= _EXACT_FLOAT_INT:
            return int(value)
    raise ValueError(f"utime {text!r} is not an integer")


def read_nclt_ground_truth(path: str | os.PathLike[str]) -> NcltGroundTruth:
    """Read an NCLT ``groundtruth_<date>.csv`` file.

    Rows are ``utime, x, y, z, roll, pitch, yaw`` (microseconds, metres, radians) in NCLT's
    frame: x north, y east, z down (see :func:`nclt_ground_truth_se2` for a z-up planar
    pose). Rows whose pose holds a NaN are *kept* and flagged by ``valid = False``. Blank
    lines, ``#`` comments and one non-numeric header line at the top are skipped. Values are
    decimal numbers or ``nan``; ``utime`` is an integer (in int64; a decimal literal such as
    ``1.3e15`` is accepted when it is an integer below ``2**53``).

    Args:
        path: The CSV file.

    Returns:
        :class:`NcltGroundTruth` ``(utime int64 [N], xyz_rpy float64 [N, 6], valid bool [N])``.

    Raises:
        FileNotFoundError: ``path`` does not exist (the message names it).
        DatasetFormatError: A row does not have 7 fields, holds a value that is not a decimal
            number or ``nan`` (``1_5``, ``inf``), a missing, non-integer or out-of-int64
            utime, a second header line, or the file holds no rows. The message names the
            line.
    """
    path = Path(path)
    utimes: list[int] = []
    rows: list[list[float]] = []
    header_skipped = False
    for lineno, line in enumerate(path.read_bytes().split(b"\n"), start=1):
        text = line.strip()  # ASCII whitespace only
        if not text or text.startswith(b"#"):
            continue
        tokens = [t.strip() for t in text.split(b",")]
        if len(tokens) != 7:
            raise DatasetFormatError(
                path,
                f"found {len(tokens)} fields, not 7",
                line=lineno,
                expected=_NCLT_GT_FORMAT,
            )
        if not rows and not header_skipped and not any(is_number(t) for t in tokens):
            header_skipped = True  # a header line such as "utime,x,y,z,roll,pitch,yaw"
            continue
        try:
            utime = _parse_utime(tokens[0])
            values = parse_numbers(tokens[1:])
        except ValueError as exc:
            raise DatasetFormatError(
                path, f"bad value ({exc})", line=lineno, expected=_NCLT_GT_FORMAT
            ) from None
        if np.isinf(values).any():
            raise DatasetFormatError(
                path, "value is infinite", line=lineno, expected=_NCLT_GT_FORMAT
            )
        utimes.append(utime)
        rows.append(values)
    if not rows:
        raise DatasetFormatError(path, "file holds no data rows", expected=_NCLT_GT_FORMAT)
    xyz_rpy = np.asarray(rows, dtype=np.float64)
    return NcltGroundTruth(
        utime=np.asarray(utimes, dtype=np.int64),
        xyz_rpy=xyz_rpy,
        valid=~np.isnan(xyz_rpy).any(axis=1),
    )


def write_nclt_ground_truth(
    path: str | os.PathLike[str], utime: np.ndarray, xyz_rpy: np.ndarray
) -> None:
    """Write an NCLT-style ground-truth CSV (inverse of :func:`read_nclt_ground_truth`).

    Values are written with ``repr`` precision (exact round trip); NaN is written as ``nan``.

    Args:
        path: Output file (overwritten).
        utime: ``[N]`` integer timestamps in microseconds.
        xyz_rpy: ``[N, 6]`` x, y, z (m), roll, pitch, yaw (rad).

    Raises:
        ValueError: Shapes disagree.
    """
    utime = np.asarray(utime)
    xyz_rpy = np.asarray(xyz_rpy, dtype=np.float64)
    if utime.ndim != 1 or xyz_rpy.shape != (utime.shape[0], 6):
        raise ValueError(
            f"utime must be [N] and xyz_rpy [N, 6], got {utime.shape} and {xyz_rpy.shape}"
        )
    with open(path, "w") as f:
        for t, row in zip(utime.tolist(), xyz_rpy.tolist(), strict=True):
            f.write(",".join([str(int(t))] + [repr(float(v)) for v in row]) + "\n")


def nclt_ground_truth_se2(xyz_rpy: np.ndarray) -> np.ndarray:
    """Planar poses from NCLT ground truth, converted to a right-handed z-up frame.

    NCLT's ground truth uses x north, y east, z down (yaw measured from north towards
    east). Flipping the y axis (and with it z) gives the right-handed z-up frame x north,
    y west, in which the planar pose is ``(x, -y, -yaw)``; yaw is then counter-clockwise
    from the x axis, as in the rest of lidarjax. The returned yaw is wrapped to
    ``(-pi, pi]``. NaN rows stay NaN.

    Args:
        xyz_rpy: ``[N, 6]`` x, y, z (m), roll, pitch, yaw (rad) as read by
            :func:`read_nclt_ground_truth`.

    Returns:
        float64 ``[N, 3]``: x (m), y (m), yaw (rad).

    Raises:
        ValueError: ``xyz_rpy`` is not ``[N, 6]``.
    """
    arr = np.asarray(xyz_rpy, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 6:
        raise ValueError(f"xyz_rpy must have shape [N, 6], got {arr.shape}")
    yaw = -arr[:, 5]
    yaw = np.pi - np.mod(np.pi - yaw, 2.0 * np.pi)  # wrap to (-pi, pi]
    return np.stack([arr[:, 0], -arr[:, 1], yaw], axis=-1)
