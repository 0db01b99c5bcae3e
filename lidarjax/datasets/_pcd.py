"""Reader and writer for PCD (Point Cloud Data, format v0.7) files.

Supports the three PCL encodings: ``ascii``, ``binary`` (little-endian point-major packed records)
and ``binary_compressed`` (LZF-compressed, field-major). The LZF codec is implemented here in
pure Python so that no compiled dependency is needed.

A PCD file stores ``POINTS = WIDTH * HEIGHT`` points in row-major order (the column index runs
fastest). Every field is returned as an array of shape ``[height, width]`` (or
``[height, width, count]`` for fields with ``COUNT > 1``), keeping the dtype given by the file's
``SIZE``/``TYPE`` entries.

NumPy only; nothing here is called inside ``jit``.
"""

from __future__ import annotations

import dataclasses
import os
import struct
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ._errors import DatasetFormatError

__all__ = ["PointCloud", "read_pcd", "write_pcd"]

# (TYPE, SIZE) -> numpy dtype (native byte order).
_PCD_DTYPES: dict[tuple[str, int], np.dtype] = {
    ("F", 4): np.dtype(np.float32),
    ("F", 8): np.dtype(np.float64),
    ("I", 1): np.dtype(np.int8),
    ("I", 2): np.dtype(np.int16),
    ("I", 4): np.dtype(np.int32),
    ("I", 8): np.dtype(np.int64),
    ("U", 1): np.dtype(np.uint8),
    ("U", 2): np.dtype(np.uint16),
    ("U", 4): np.dtype(np.uint32),
    ("U", 8): np.dtype(np.uint64),
}
_DTYPE_TO_PCD: dict[np.dtype, tuple[str, int]] = {dt: key for key, dt in _PCD_DTYPES.items()}

_DATA_ENCODINGS = ("ascii", "binary", "binary_compressed")
_DEFAULT_VIEWPOINT = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
_HEADER_KEYS = (
    "VERSION",
    "FIELDS",
    "SIZE",
    "TYPE",
    "COUNT",
    "WIDTH",
    "HEIGHT",
    "VIEWPOINT",
    "POINTS",
    "DATA",
)
_REQUIRED_KEYS = ("FIELDS", "SIZE", "TYPE", "WIDTH", "HEIGHT", "POINTS", "DATA")
_ACCEPTED_VERSIONS = (".7", "0.7")
_PADDING_FIELD = "_"  # PCL names padding fields "_"; they are skipped on reading.


# --------------------------------------------------------------------------------------------
# Container
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class PointCloud:
    """A point cloud as read from / written to a PCD file (plain NumPy container).

    Attributes:
        fields: Field name -> array of shape ``[height, width]`` (``COUNT == 1``) or
            ``[height, width, count]``; dtype as stored in the file (e.g. float32 for ``F 4``,
            uint8 for ``U 1``). Units are those of the file (x, y, z usually metres).
        width: Number of columns (number of points for unorganized clouds).
        height: Number of rows; ``1`` for unorganized clouds.
        viewpoint: ``[7]`` float64 sensor pose ``tx ty tz qw qx qy qz`` (metres, unit
            quaternion) in the cloud's frame.
    """

    fields: dict[str, np.ndarray]
    width: int
    height: int
    viewpoint: np.ndarray = dataclasses.field(
        default_factory=lambda: np.array(_DEFAULT_VIEWPOINT, dtype=np.float64)
    )

    def __post_init__(self) -> None:
        width, height = int(self.width), int(self.height)
        if width < 0 or height < 0:
            raise ValueError(f"width and height must be non-negative, got {width}x{height}")
        viewpoint = np.asarray(self.viewpoint, dtype=np.float64).reshape(-1)
        if viewpoint.shape != (7,):
            raise ValueError(
                f"viewpoint must hold 7 values (tx ty tz qw qx qy qz), got {viewpoint.size}"
            )
        fields: dict[str, np.ndarray] = {}
        for name, value in self.fields.items():
            _check_field_name(name)
            arr = np.asarray(value)
            if arr.ndim not in (2, 3) or arr.shape[:2] != (height, width):
                raise ValueError(
                    f"field {name!r} has shape {arr.shape}, expected ({height}, {width}) or "
                    f"({height}, {width}, count)"
                )
            if arr.ndim == 3 and arr.shape[2] < 1:
                raise ValueError(f"field {name!r} has COUNT 0")
            _pcd_type_of(name, arr.dtype)
            fields[name] = arr
        object.__setattr__(self, "fields", fields)
        object.__setattr__(self, "width", width)
        object.__setattr__(self, "height", height)
        object.__setattr__(self, "viewpoint", viewpoint)

    @classmethod
    def from_fields(
        cls,
        fields: Mapping[str, Any],
        viewpoint: Any = None,
    ) -> PointCloud:
        """Builds a cloud from a dict of equally shaped arrays.

        Args:
            fields: Field name -> array of shape ``[height, width]``, ``[height, width, count]``
                or ``[n]`` (taken as an unorganized ``[1, n]`` row). Supported dtypes: float32,
                float64, (u)int8/16/32/64. Arrays are converted to C-contiguous native order.
            viewpoint: Optional ``[7]`` sensor pose ``tx ty tz qw qx qy qz``; defaults to the
                identity ``0 0 0 1 0 0 0``.

        Returns:
            The point cloud; ``height`` and ``width`` are the first two dimensions.

        Raises:
            ValueError: If ``fields`` is empty, shapes disagree, a name is not a valid PCD field
                name or a dtype cannot be stored in a PCD file (the field is named).
        """
        if not fields:
            raise ValueError("a point cloud needs at least one field")
        arrays: dict[str, np.ndarray] = {}
        shape: tuple[int, int] | None = None
        for name, value in fields.items():
            _check_field_name(name)
            arr = np.asarray(value)
            _pcd_type_of(name, arr.dtype)
            if arr.ndim == 1:
                arr = arr[None, :]
            if arr.ndim not in (2, 3):
                raise ValueError(
                    f"field {name!r} has shape {arr.shape}; expected [height, width] or "
                    "[height, width, count]"
                )
            if shape is None:
                shape = (int(arr.shape[0]), int(arr.shape[1]))
            elif arr.shape[:2] != shape:
                raise ValueError(
                    f"field {name!r} has shape {arr.shape}, but earlier fields have "
                    f"[height, width] = {list(shape)}"
                )
            arrays[name] = np.ascontiguousarray(arr, dtype=arr.dtype.newbyteorder("="))
        assert shape is not None
        if viewpoint is None:
            viewpoint = _DEFAULT_VIEWPOINT
        return cls(fields=arrays, width=shape[1], height=shape[0], viewpoint=viewpoint)

    @property
    def num_points(self) -> int:
        """Number of points, ``width * height``."""
        return self.width * self.height

    @property
    def is_organized(self) -> bool:
        """Whether the cloud is organized (image-like), i.e. ``height > 1``."""
        return self.height > 1

    @property
    def points_xyz(self) -> np.ndarray:
        """``[height, width, 3]`` float64 stack of the ``x``, ``y``, ``z`` fields (file units).

        Raises:
            ValueError: If any of ``x``, ``y``, ``z`` is missing or has ``COUNT > 1``.
        """
        missing = [k for k in ("x", "y", "z") if k not in self.fields]
        if missing:
            raise ValueError(
                f"point cloud has no field(s) {missing}; available fields: {list(self.fields)}"
            )
        for k in ("x", "y", "z"):
            if self.fields[k].ndim != 2:
                raise ValueError(f"field {k!r} has COUNT > 1, cannot build points_xyz")
        return np.stack([self.fields[k].astype(np.float64) for k in ("x", "y", "z")], axis=-1)

    def __getitem__(self, name: str) -> np.ndarray:
        """Returns field ``name`` (shape ``[height, width]`` or ``[height, width, count]``)."""
        try:
            return self.fields[name]
        except KeyError:
            raise KeyError(
                f"point cloud has no field {name!r}; available fields: {list(self.fields)}"
            ) from None

    def __contains__(self, name: object) -> bool:
        return name in self.fields

    def __repr__(self) -> str:
        desc = ", ".join(f"{k}:{v.dtype}{list(v.shape[2:]) or ''}" for k, v in self.fields.items())
        return f"PointCloud(height={self.height}, width={self.width}, fields=[{desc}])"


def _check_field_name(name: object) -> None:
    if not isinstance(name, str) or not name or any(ch.isspace() for ch in name):
        raise ValueError(f"invalid PCD field name {name!r}: must be a non-empty word")


def _pcd_type_of(name: str, dtype: np.dtype) -> tuple[str, int]:
    key = _DTYPE_TO_PCD.get(np.dtype(dtype).newbyteorder("="))
    if key is None:
        raise ValueError(
            f"field {name!r} has dtype {np.dtype(dtype)}, which PCD cannot store; use float32, "
            "float64, int8/16/32/64 or uint8/16/32/64"
        )
    return key


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Header:
    names: list[str]
    dtypes: list[np.dtype]
    counts: list[int]
    width: int
    height: int
    viewpoint: np.ndarray
    points: int
    data: str
    data_offset: int  # byte offset of the first data byte
    data_line: int  # 1-based line number of the first data line


_HEADER_EXPECTED = (
    "PCD v0.7 header lines VERSION, FIELDS, SIZE, TYPE, [COUNT], WIDTH, HEIGHT, [VIEWPOINT], "
    "POINTS, DATA ascii|binary|binary_compressed"
)


def _parse_header(path: Path, raw: bytes) -> _Header:
    entries: dict[str, tuple[list[str], int]] = {}
    pos = 0
    lineno = 0
    data_offset = -1
    while pos < len(raw):
        end = raw.find(b"\n", pos)
        next_pos = len(raw) if end < 0 else end + 1
        lineno += 1
        text = raw[pos:next_pos].decode("latin-1")
        pos = next_pos
        text = text.split("#", 1)[0].strip()
        if not text:
            continue
        tokens = text.split()
        key = tokens[0].upper()
        if key not in _HEADER_KEYS:
            raise DatasetFormatError(
                path, f"unknown header entry {tokens[0]!r}", line=lineno, expected=_HEADER_EXPECTED
            )
        if key in entries:
            raise DatasetFormatError(
                path, f"duplicate header entry {key}", line=lineno, expected=_HEADER_EXPECTED
            )
        entries[key] = (tokens[1:], lineno)
        if key == "DATA":
            data_offset = pos
            break
    missing = [k for k in _REQUIRED_KEYS if k not in entries]
    if missing:
        raise DatasetFormatError(
            path, f"header lacks {', '.join(missing)}", expected=_HEADER_EXPECTED
        )

    def fail(key: str, message: str, expected: str) -> DatasetFormatError:
        return DatasetFormatError(path, message, line=entries[key][1], expected=expected)

    if "VERSION" in entries:
        version = entries["VERSION"][0]
        if len(version) != 1 or version[0] not in _ACCEPTED_VERSIONS:
            raise fail("VERSION", f"unsupported VERSION {' '.join(version)!r}", "VERSION 0.7")

    names = entries["FIELDS"][0]
    n_fields = len(names)
    if n_fields == 0:
        raise fail("FIELDS", "FIELDS lists no fields", "FIELDS name_1 .. name_k")
    real_names = [n for n in names if n != _PADDING_FIELD]
    if len(set(real_names)) != len(real_names):
        raise fail("FIELDS", f"duplicate field names in {names}", "distinct field names")

    def int_list(key: str, default: list[int] | None = None) -> list[int]:
        if key not in entries:
            assert default is not None
            return default
        values = entries[key][0]
        expected = f"{key} with {n_fields} positive integers (one per field in FIELDS)"
        if len(values) != n_fields:
            raise fail(key, f"{key} has {len(values)} entries but FIELDS has {n_fields}", expected)
        try:
            out = [int(v) for v in values]
        except ValueError:
            raise fail(key, f"non-integer {key} entry in {values}", expected) from None
        if any(v < 1 for v in out):
            raise fail(key, f"{key} entries must be >= 1, got {values}", expected)
        return out

    sizes = int_list("SIZE")
    counts = int_list("COUNT", [1] * n_fields)
    types = [t.upper() for t in entries["TYPE"][0]]
    if len(types) != n_fields:
        raise fail(
            "TYPE",
            f"TYPE has {len(types)} entries but FIELDS has {n_fields}",
            "TYPE with one of F, I, U per field",
        )
    dtypes: list[np.dtype] = []
    for name, t, s in zip(names, types, sizes, strict=True):
        dtype = _PCD_DTYPES.get((t, s))
        if dtype is None:
            raise fail(
                "TYPE",
                f"field {name!r} has unsupported TYPE {t} / SIZE {s}",
                "F 4|8, I 1|2|4|8 or U 1|2|4|8",
            )
        dtypes.append(dtype)

    def one_int(key: str) -> int:
        values = entries[key][0]
        try:
            if len(values) != 1:
                raise ValueError
            value = int(values[0])
            if value < 0:
                raise ValueError
        except ValueError:
            raise fail(
                key, f"bad {key} value {' '.join(values)!r}", f"{key} <non-negative integer>"
            ) from None
        return value

    width, height, points = one_int("WIDTH"), one_int("HEIGHT"), one_int("POINTS")
    if points != width * height:
        raise fail(
            "POINTS",
            f"POINTS {points} != WIDTH * HEIGHT = {width} * {height}",
            "POINTS = WIDTH * HEIGHT",
        )

    viewpoint = np.array(_DEFAULT_VIEWPOINT, dtype=np.float64)
    if "VIEWPOINT" in entries:
        values = entries["VIEWPOINT"][0]
        try:
            if len(values) != 7:
                raise ValueError
            viewpoint = np.array([float(v) for v in values], dtype=np.float64)
        except ValueError:
            raise fail(
                "VIEWPOINT", f"bad VIEWPOINT {' '.join(values)!r}", "VIEWPOINT tx ty tz qw qx qy qz"
            ) from None

    data_values = entries["DATA"][0]
    data = data_values[0].lower() if len(data_values) == 1 else " ".join(data_values)
    if data not in _DATA_ENCODINGS:
        raise fail("DATA", f"unknown DATA encoding {data!r}", "DATA ascii|binary|binary_compressed")

    return _Header(
        names=names,
        dtypes=dtypes,
        counts=counts,
        width=width,
        height=height,
        viewpoint=viewpoint,
        points=points,
        data=data,
        data_offset=data_offset,
        data_line=entries["DATA"][1] + 1,
    )


def read_pcd(path: str | os.PathLike[str]) -> PointCloud:
    """Reads a PCD v0.7 file in ``ascii``, ``binary`` or ``binary_compressed`` encoding.

    Fields named ``_`` (PCL padding) are dropped.

    Args:
        path: File to read.

    Returns:
        The cloud; each field has shape ``[HEIGHT, WIDTH]`` (``[HEIGHT, WIDTH, COUNT]`` when
        ``COUNT > 1``) and the dtype given by its ``TYPE``/``SIZE``.

    Raises:
        FileNotFoundError: If ``path`` does not exist.
        DatasetFormatError: If the header is malformed, the data is truncated or corrupt, or an
            ASCII line has the wrong number of values (the message names the path, the 1-based
            line where applicable, and the expected format).
    """
    path = Path(path)
    raw = path.read_bytes()
    header = _parse_header(path, raw)
    body = raw[header.data_offset :]
    if header.data == "ascii":
        columns = _read_ascii(path, header, body)
    elif header.data == "binary":
        columns = _read_binary(path, header, body)
    else:
        columns = _read_binary_compressed(path, header, body)

    fields: dict[str, np.ndarray] = {}
    for name, count, col in zip(header.names, header.counts, columns, strict=True):
        if name == _PADDING_FIELD:
            continue
        shape = (header.height, header.width) + ((count,) if count > 1 else ())
        fields[name] = np.ascontiguousarray(col.reshape(shape))
    return PointCloud(
        fields=fields, width=header.width, height=header.height, viewpoint=header.viewpoint
    )


def _field_spec(header: _Header) -> str:
    return " ".join(
        f"{n}:{dt}" + (f"x{c}" if c > 1 else "")
        for n, dt, c in zip(header.names, header.dtypes, header.counts, strict=True)
    )


def _read_ascii(path: Path, header: _Header, body: bytes) -> list[np.ndarray]:
    n, total = header.points, sum(header.counts)
    expected = f"{total} whitespace-separated values per line ({_field_spec(header)})"
    rows: list[list[str]] = []
    row_lines: list[int] = []
    lines = body.decode("latin-1").split("\n")
    for lineno, line in enumerate(lines, start=header.data_line):
        if len(rows) == n:
            break
        tokens = line.split()
        if not tokens:
            continue
        if len(tokens) != total:
            raise DatasetFormatError(
                path, f"line has {len(tokens)} values", line=lineno, expected=expected
            )
        rows.append(tokens)
        row_lines.append(lineno)
    if len(rows) < n:
        last = header.data_line + max(len(lines) - 1, 0)
        raise DatasetFormatError(
            path,
            f"file ends after {len(rows)} of {n} points",
            line=last,
            expected=f"{n} data lines of {expected}",
        )
    table = np.array(rows, dtype=str).reshape(n, total)
    columns: list[np.ndarray] = []
    start = 0
    for name, dtype, count in zip(header.names, header.dtypes, header.counts, strict=True):
        block = table[:, start : start + count]
        try:
            columns.append(block.astype(dtype))
        except (ValueError, OverflowError):
            row, token = _find_bad_token(block, dtype)
            raise DatasetFormatError(
                path,
                f"cannot parse {token!r} as {dtype} for field {name!r}",
                line=row_lines[row],
                expected=expected,
            ) from None
        start += count
    return columns


def _find_bad_token(block: np.ndarray, dtype: np.dtype) -> tuple[int, str]:
    for i, row in enumerate(block):
        for token in row:
            try:
                np.array([token]).astype(dtype)
            except (ValueError, OverflowError):
                return i, str(token)
    return 0, "?"  # pragma: no cover - the caller only calls this after a failure


def _record_dtype(header: _Header) -> np.dtype:
    return np.dtype(
        [
            (f"f{i}", dt.newbyteorder("<"), (c,))
            for i, (dt, c) in enumerate(zip(header.dtypes, header.counts, strict=True))
        ]
    )


def _read_binary(path: Path, header: _Header, body: bytes) -> list[np.ndarray]:
    record = _record_dtype(header)
    need = header.points * record.itemsize
    if len(body) < need:
        raise DatasetFormatError(
            path,
            f"binary data truncated: {len(body)} bytes, need {need}",
            expected=f"{header.points} little-endian records of {record.itemsize} bytes "
            f"({_field_spec(header)})",
        )
    table = np.frombuffer(body, dtype=record, count=header.points)
    return [
        table[f"f{i}"].astype(dt).reshape(header.points, c)
        for i, (dt, c) in enumerate(zip(header.dtypes, header.counts, strict=True))
    ]


def _read_binary_compressed(path: Path, header: _Header, body: bytes) -> list[np.ndarray]:
    sizes = [dt.itemsize * c for dt, c in zip(header.dtypes, header.counts, strict=True)]
    usize_expected = header.points * sum(sizes)
    expected = (
        "uint32 compressed size, uint32 uncompressed size, then LZF data decompressing to "
        f"{usize_expected} bytes of field-major values ({_field_spec(header)})"
    )
    if len(body) < 8:
        raise DatasetFormatError(
            path, "binary_compressed data lacks its 8-byte size header", expected=expected
        )
    csize, usize = struct.unpack("<II", body[:8])
    if usize != usize_expected:
        raise DatasetFormatError(
            path,
            f"uncompressed size {usize} does not match POINTS * record size = {usize_expected}",
            expected=expected,
        )
    if len(body) - 8 < csize:
        raise DatasetFormatError(
            path,
            f"compressed data truncated: {len(body) - 8} bytes, header says {csize}",
            expected=expected,
        )
    try:
        plain = _lzf_decompress(body[8 : 8 + csize], usize)
    except _LZFError as err:
        raise DatasetFormatError(path, f"corrupt LZF stream: {err}", expected=expected) from None
    columns: list[np.ndarray] = []
    offset = 0
    for dt, c, size in zip(header.dtypes, header.counts, sizes, strict=True):
        nbytes = size * header.points
        chunk = np.frombuffer(
            plain, dtype=dt.newbyteorder("<"), count=header.points * c, offset=offset
        )
        columns.append(chunk.astype(dt).reshape(header.points, c))
        offset += nbytes
    return columns


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def write_pcd(
    path: str | os.PathLike[str],
    cloud: PointCloud | Mapping[str, Any],
    *,
    data: str = "binary_compressed",
) -> Path:
    """Writes a cloud as a PCD v0.7 file that :func:`read_pcd` reads back exactly.

    Args:
        path: Output file (overwritten).
        cloud: A :class:`PointCloud`, or a dict of field arrays passed to
            :meth:`PointCloud.from_fields`.
        data: Encoding, one of ``"ascii"``, ``"binary"``, ``"binary_compressed"``. ASCII floats
            are written with 9 (float32) / 17 (float64) significant digits so they round-trip.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ValueError: If ``data`` is not a known encoding or the fields cannot be stored.
    """
    if data not in _DATA_ENCODINGS:
        raise ValueError(f"data must be one of {_DATA_ENCODINGS}, got {data!r}")
    if not isinstance(cloud, PointCloud):
        cloud = PointCloud.from_fields(cloud)
    if not cloud.fields:
        raise ValueError("cannot write a point cloud without fields")
    path = Path(path)
    n = cloud.num_points
    names = list(cloud.fields)
    counts = [cloud.fields[k].shape[2] if cloud.fields[k].ndim == 3 else 1 for k in names]
    arrays = [np.asarray(cloud.fields[k]).reshape(n, c) for k, c in zip(names, counts, strict=True)]
    types = [_pcd_type_of(k, a.dtype) for k, a in zip(names, arrays, strict=True)]
    viewpoint = " ".join(_format_float64(v) for v in cloud.viewpoint.tolist())
    header = "\n".join(
        [
            "# .PCD v0.7 - Point Cloud Data file format",
            "VERSION 0.7",
            "FIELDS " + " ".join(names),
            "SIZE " + " ".join(str(s) for _, s in types),
            "TYPE " + " ".join(t for t, _ in types),
            "COUNT " + " ".join(str(c) for c in counts),
            f"WIDTH {cloud.width}",
            f"HEIGHT {cloud.height}",
            f"VIEWPOINT {viewpoint}",
            f"POINTS {n}",
            f"DATA {data}",
            "",
        ]
    ).encode("ascii")

    if data == "ascii":
        body = _ascii_body(arrays, n)
    elif data == "binary":
        record = np.dtype(
            [(f"f{i}", a.dtype.newbyteorder("<"), (a.shape[1],)) for i, a in enumerate(arrays)]
        )
        table = np.empty(n, dtype=record)
        for i, a in enumerate(arrays):
            table[f"f{i}"] = a
        body = table.tobytes()
    else:
        plain = b"".join(a.astype(a.dtype.newbyteorder("<")).tobytes() for a in arrays)
        packed = _lzf_compress(plain)
        body = struct.pack("<II", len(packed), len(plain)) + packed
    path.write_bytes(header + body)
    return path


def _format_float64(value: float) -> str:
    return f"{value:.17g}"


def _ascii_body(arrays: list[np.ndarray], n: int) -> bytes:
    columns: list[list[str]] = []
    for a in arrays:
        if a.dtype.kind == "f":
            fmt = "%.9g" if a.dtype.itemsize == 4 else "%.17g"  # enough digits to round-trip
        else:
            fmt = "%d"
        for j in range(a.shape[1]):
            columns.append([fmt % v for v in a[:, j].tolist()])
    lines = [" ".join(row) for row in zip(*columns, strict=True)] if n else []
    return "".join(line + "\n" for line in lines).encode("ascii")


# --------------------------------------------------------------------------------------------
# LZF codec (liblzf format as used by PCL's binary_compressed encoding)
# --------------------------------------------------------------------------------------------

_LZF_MAX_LITERAL = 32  # literal runs: control byte 0..31 -> 1..32 bytes
_LZF_MAX_OFFSET = 8192  # back-references reach at most 8192 bytes back
_LZF_MAX_MATCH = 264  # back-reference length 3 .. 7 + 255 + 2
_LZF_HASH_BITS = 16
_LZF_SKIP_SHIFT = 6  # after 64 consecutive misses step 2 bytes, after 128 step 3, ...


class _LZFError(ValueError):
    """An LZF stream is corrupt or does not decode to the expected size."""


def _lzf_decompress(data: bytes, expected_size: int) -> bytes:
    """Decompresses an LZF stream.

    Args:
        data: The compressed stream (no size prefix).
        expected_size: Exact decompressed size in bytes.

    Returns:
        The decompressed bytes, of length ``expected_size``.

    Raises:
        _LZFError: If the stream is truncated, references data before the start of the output,
            or decodes to a different size.
    """
    src = bytes(data)
    n = len(src)
    out = bytearray()
    ip = 0
    while ip < n:
        ctrl = src[ip]
        ip += 1
        if ctrl < 32:
            end = ip + ctrl + 1
            if end > n:
                raise _LZFError(
                    f"literal run of {ctrl + 1} bytes at input offset {ip - 1} runs past the "
                    f"end of the {n}-byte stream"
                )
            out += src[ip:end]
            ip = end
        else:
            length = ctrl >> 5
            if length == 7:
                if ip >= n:
                    raise _LZFError(f"stream ends inside a back-reference at offset {ip - 1}")
                length += src[ip]
                ip += 1
            if ip >= n:
                raise _LZFError(f"stream ends inside a back-reference at offset {ip - 1}")
            offset = ((ctrl & 0x1F) << 8) + src[ip] + 1
            ip += 1
            length += 2
            start = len(out) - offset
            if start < 0:
                raise _LZFError(
                    f"back-reference {offset} bytes back at input offset {ip} points before "
                    f"the start of the {len(out)}-byte output"
                )
            if offset >= length:
                out += out[start : start + length]
            else:  # overlapping copy == repeating the last `offset` bytes
                reps = -(-length // offset)
                out += (out[start:] * reps)[:length]
        if len(out) > expected_size:
            raise _LZFError(f"stream decodes to more than the expected {expected_size} bytes")
    if len(out) != expected_size:
        raise _LZFError(
            f"stream decodes to {len(out)} bytes, expected {expected_size} (truncated stream?)"
        )
    return bytes(out)


def _lzf_compress(data: bytes) -> bytes:
    """Compresses bytes into an LZF stream (greedy hash-table matcher).

    Matches of 3 .. 264 bytes up to 8192 bytes back are found through a ``2**16``-entry table
    of the most recent position of each hashed 3-byte prefix; everything else is emitted as
    literal runs of at most 32 bytes. Like LZ4, the scan takes growing steps through long
    stretches without matches, which keeps incompressible input fast.

    Args:
        data: Bytes to compress.

    Returns:
        The LZF stream (no size prefix); ``_lzf_decompress(result, len(data)) == data``.
    """
    src = bytes(data)
    n = len(src)
    out = bytearray()
    shift = 32 - _LZF_HASH_BITS
    table = [-1] * (1 << _LZF_HASH_BITS)

    def emit_literals(lo: int, hi: int) -> None:
        for s in range(lo, hi, _LZF_MAX_LITERAL):
            e = min(s + _LZF_MAX_LITERAL, hi)
            out.append(e - s - 1)
            out.extend(src[s:e])

    literal_start = 0
    ip = 0
    misses = 0  # consecutive failed lookups; long misses speed up the scan (as in LZ4)
    limit = n - 2  # a match needs three bytes to hash
    while ip < limit:
        v = (src[ip] << 16) | (src[ip + 1] << 8) | src[ip + 2]
        h = ((v * 2654435761) & 0xFFFFFFFF) >> shift
        ref = table[h]
        table[h] = ip
        if ref < 0 or ip - ref > _LZF_MAX_OFFSET or src[ref : ref + 3] != src[ip : ip + 3]:
            ip += 1 + (misses >> _LZF_SKIP_SHIFT)
            misses += 1
            continue
        misses = 0
        length = _match_length(src, ref, ip, min(_LZF_MAX_MATCH, n - ip))
        emit_literals(literal_start, ip)
        off = ip - ref - 1
        code = length - 2
        if code < 7:
            out.append((code << 5) | (off >> 8))
        else:
            out.append((7 << 5) | (off >> 8))
            out.append(code - 7)
        out.append(off & 0xFF)
        ip += length
        literal_start = ip
        # Remember the tail of the match so that the following data can refer to it.
        for pos in (ip - 2, ip - 1):
            if pos + 2 < n:
                w = (src[pos] << 16) | (src[pos + 1] << 8) | src[pos + 2]
                table[((w * 2654435761) & 0xFFFFFFFF) >> shift] = pos
    emit_literals(literal_start, n)
    return bytes(out)


def _match_length(src: bytes, ref: int, ip: int, max_len: int) -> int:
    """Longest ``L <= max_len`` with ``src[ref:ref+L] == src[ip:ip+L]``, given ``L >= 3``."""
    if src[ref : ref + max_len] == src[ip : ip + max_len]:
        return max_len
    lo, hi = 3, max_len  # prefix of length lo matches, of length hi does not
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if src[ref : ref + mid] == src[ip : ip + mid]:
            lo = mid
        else:
            hi = mid
    return lo
