"""Reader and writer for PCD (Point Cloud Data, format v0.7) files.

Supports the three PCL encodings: ``ascii``, ``binary`` (little-endian point-major packed records)
and ``binary_compressed`` (LZF-compressed, field-major). LZF is encoded and decoded by the
compiled ``lzf`` module (python-lzf, liblzf) when it is importable, else by the pure-Python
codec of this module; :func:`lzf_backend` tells which, and the environment variable
``LIDARJAX_LZF`` (``auto`` | ``python-lzf`` | ``pure-python``) forces one. Both codecs read
exactly the same streams (liblzf's format, bounds-checked) and write streams that either
one (and PCL) reads.

A PCD file stores ``POINTS = WIDTH * HEIGHT`` points in row-major order (the column index runs
fastest). Every field is returned as an array of shape ``[height, width]`` (or
``[height, width, count]`` for fields with ``COUNT > 1``), keeping the dtype given by the file's
``SIZE``/``TYPE`` entries.

NumPy only; nothing here is called inside ``jit``.

Length (~1000 lines): one file format, read and written in its three encodings with the
LZF codec (and its switch to python-lzf), each path validating every header field so that a
corrupted file is an error.
"""

from __future__ import annotations

import dataclasses
import os
import struct
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

try:  # python-lzf: liblzf compiled; optional (the pure-Python codec below is the fallback)
    import lzf as _lzf_ext
except ImportError:  # pragma: no cover - depends on the environment
    _lzf_ext = None

from ._errors import DatasetFormatError
from ._text import NumberSyntaxError, is_decimal, is_integer, parse_integers, parse_numbers

__all__ = ["PointCloud", "lzf_backend", "read_pcd", "write_pcd"]

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
_MAX_RECORD_BYTES = 2**31 - 1  # sum of SIZE * COUNT per point (NumPy's limit for a record)
_MAX_DIMENSION = 2**32 - 1  # WIDTH and HEIGHT are uint32 in PCL


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
    entries: dict[str, tuple[list[bytes], int]] = {}
    pos = 0
    lineno = 0
    data_offset = -1
    while pos < len(raw):
        end = raw.find(b"\n", pos)
        next_pos = len(raw) if end < 0 else end + 1
        lineno += 1
        line = raw[pos:next_pos].split(b"#", 1)[0]
        pos = next_pos
        tokens = line.split()  # ASCII whitespace only
        if not tokens:
            continue
        key = tokens[0].upper().decode("latin-1")
        if key not in _HEADER_KEYS:
            raise DatasetFormatError(
                path,
                f"unknown header entry {tokens[0].decode('latin-1')!r}",
                line=lineno,
                expected=_HEADER_EXPECTED,
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

    def text(key: str) -> str:
        return " ".join(v.decode("latin-1") for v in entries[key][0])

    if "VERSION" in entries:
        version = entries["VERSION"][0]
        if len(version) != 1 or version[0].decode("latin-1") not in _ACCEPTED_VERSIONS:
            raise fail("VERSION", f"unsupported VERSION {text('VERSION')!r}", "VERSION 0.7")

    raw_names = entries["FIELDS"][0]
    n_fields = len(raw_names)
    if n_fields == 0:
        raise fail("FIELDS", "FIELDS lists no fields", "FIELDS name_1 .. name_k")
    for name in raw_names:
        if any(b < 0x21 or b > 0x7E for b in name):
            raise fail(
                "FIELDS",
                f"invalid field name {name.decode('latin-1')!r} in FIELDS",
                "field names of printable ASCII characters",
            )
    names = [n.decode("ascii") for n in raw_names]
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
        if not all(is_integer(v, signed=False) for v in values):
            raise fail(key, f"non-integer {key} entry in {text(key)!r}", expected)
        out = [int(v) for v in values]
        if any(v < 1 for v in out):
            raise fail(key, f"{key} entries must be >= 1, got {text(key)!r}", expected)
        return out

    sizes = int_list("SIZE")
    counts = int_list("COUNT", [1] * n_fields)
    types = [t.upper().decode("latin-1") for t in entries["TYPE"][0]]
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
    record_size = sum(s * c for s, c in zip(sizes, counts, strict=True))
    if record_size > _MAX_RECORD_BYTES:
        key = "COUNT" if "COUNT" in entries else "SIZE"
        raise fail(
            key,
            f"COUNT {text('COUNT') if 'COUNT' in entries else '1 ..'} with SIZE {text('SIZE')} "
            f"gives {record_size} bytes per point",
            f"at most {_MAX_RECORD_BYTES} bytes per point (sum of SIZE * COUNT)",
        )

    def one_int(key: str) -> int:
        values = entries[key][0]
        if len(values) != 1 or not is_integer(values[0], signed=False):
            raise fail(key, f"bad {key} value {text(key)!r}", f"{key} <non-negative integer>")
        value = int(values[0])
        if key != "POINTS" and value > _MAX_DIMENSION:
            raise fail(key, f"{key} {value} is too large", f"{key} <= {_MAX_DIMENSION}")
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
        if len(values) != 7 or not all(is_decimal(v) for v in values):
            raise fail(
                "VIEWPOINT",
                f"bad VIEWPOINT {text('VIEWPOINT')!r}",
                "VIEWPOINT with 7 finite numbers tx ty tz qw qx qy qz",
            )
        viewpoint = np.array([float(v) for v in values], dtype=np.float64)
        if not np.isfinite(viewpoint).all():
            raise fail(
                "VIEWPOINT",
                f"VIEWPOINT {text('VIEWPOINT')!r} overflows",
                "VIEWPOINT with 7 finite numbers tx ty tz qw qx qy qz",
            )

    data_values = entries["DATA"][0]
    data = data_values[0].lower().decode("latin-1") if len(data_values) == 1 else text("DATA")
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
        DatasetFormatError: If the header is malformed or insane (``POINTS != WIDTH * HEIGHT``,
            inconsistent ``SIZE``/``TYPE``/``COUNT``, a record larger than ``2**31 - 1`` bytes,
            a non-decimal number), the payload does not have exactly the declared size
            (``binary``: ``POINTS`` records, nothing more or less; ``binary_compressed``: the
            two size fields match ``POINTS`` and the bytes that follow), the LZF stream is
            corrupt, an ASCII line has the wrong number of values, a value that is not a
            number of the field's type or out of its range, or there are more or fewer than
            ``POINTS`` non-blank data lines. The message names the path, the 1-based line
            where applicable, and the expected format.
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
    expected = (
        f"{total} whitespace-separated values per line ({_field_spec(header)}); decimal "
        "numbers (nan / inf allowed) for F fields, integers for I / U fields"
    )
    rows: list[list[bytes]] = []
    row_lines: list[int] = []
    lines = body.split(b"\n")
    for lineno, line in enumerate(lines, start=header.data_line):
        tokens = line.split()  # ASCII whitespace only
        if not tokens:
            continue
        if len(rows) == n:
            raise DatasetFormatError(
                path,
                f"more than POINTS = {n} data lines (extra or duplicated line)",
                line=lineno,
                expected=f"exactly {n} data lines, then only blank lines",
            )
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
    columns: list[np.ndarray] = []
    start = 0
    for name, dtype, count in zip(header.names, header.dtypes, header.counts, strict=True):
        tokens = [t for row in rows for t in row[start : start + count]]  # point-major
        try:
            if dtype.kind == "f":
                values = _ascii_floats(tokens, dtype)
            else:
                values = _ascii_integers(tokens, dtype)
        except NumberSyntaxError as err:
            raise DatasetFormatError(
                path,
                f"cannot parse {err.token!r} as {dtype} for field {name!r}",
                line=row_lines[err.index // count],
                expected=expected,
            ) from None
        except _OutOfRange as err:
            raise DatasetFormatError(
                path,
                f"value {err.token!r} of field {name!r} is out of range for {dtype}",
                line=row_lines[err.index // count],
                expected=expected,
            ) from None
        columns.append(values.reshape(n, count))
        start += count
    return columns


class _OutOfRange(ValueError):
    def __init__(self, index: int, token: bytes) -> None:
        self.index = index
        self.token = token.decode("latin-1")
        super().__init__(self.token)


def _ascii_floats(tokens: list[bytes], dtype: np.dtype) -> np.ndarray:
    """Decimal or nan/inf tokens -> float64 (correctly rounded) -> ``dtype``; overflow raises."""
    wide = np.array(parse_numbers(tokens), dtype=np.float64)
    with np.errstate(over="ignore"):
        out = wide.astype(dtype)
    for i in np.flatnonzero(np.isinf(out)):  # an overflowing literal, or a genuine "inf"
        if is_decimal(tokens[i]):
            raise _OutOfRange(int(i), tokens[i])
    return out


def _ascii_integers(tokens: list[bytes], dtype: np.dtype) -> np.ndarray:
    values = parse_integers(tokens)
    info = np.iinfo(dtype)
    if values and (min(values) < info.min or max(values) > info.max):
        i = next(i for i, v in enumerate(values) if not info.min <= v <= info.max)
        raise _OutOfRange(i, tokens[i])
    return np.array(values, dtype=dtype)


def _record_dtype(header: _Header) -> np.dtype:
    return np.dtype(
        [
            (f"f{i}", dt.newbyteorder("<"), (c,))
            for i, (dt, c) in enumerate(zip(header.dtypes, header.counts, strict=True))
        ]
    )


def _record_size(header: _Header) -> int:
    return sum(dt.itemsize * c for dt, c in zip(header.dtypes, header.counts, strict=True))


def _read_binary(path: Path, header: _Header, body: bytes) -> list[np.ndarray]:
    record_size = _record_size(header)
    need = header.points * record_size
    if len(body) != need:
        what = (
            f"truncated: {len(body)} bytes"
            if len(body) < need
            else f"too long: {len(body) - need} bytes beyond the {header.points} points"
        )
        raise DatasetFormatError(
            path,
            f"binary data {what}; the header declares POINTS * record size = "
            f"{header.points} * {record_size} = {need} bytes",
            expected=f"exactly {header.points} little-endian records of {record_size} bytes "
            f"({_field_spec(header)}) after the DATA line",
        )
    if header.points == 0:
        return [np.empty((0, c), dtype=dt) for dt, c in zip(header.dtypes, header.counts)]
    table = np.frombuffer(body, dtype=_record_dtype(header), count=header.points)
    return [
        table[f"f{i}"].astype(dt).reshape(header.points, c)
        for i, (dt, c) in enumerate(zip(header.dtypes, header.counts, strict=True))
    ]


_LZF_MAX_RATIO = 88  # a 3-byte back-reference expands to at most 264 bytes


def _read_binary_compressed(path: Path, header: _Header, body: bytes) -> list[np.ndarray]:
    sizes = [dt.itemsize * c for dt, c in zip(header.dtypes, header.counts, strict=True)]
    usize_expected = header.points * sum(sizes)
    expected = (
        "uint32 compressed size, uint32 uncompressed size, then exactly that many bytes of "
        f"LZF data decompressing to {usize_expected} bytes of field-major values "
        f"({_field_spec(header)})"
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
    if len(body) - 8 != csize:
        what = "truncated" if len(body) - 8 < csize else "trailing bytes"
        raise DatasetFormatError(
            path,
            f"compressed size {csize} in the size header, but {len(body) - 8} bytes follow "
            f"({what})",
            expected=expected,
        )
    if usize > _LZF_MAX_RATIO * csize:
        raise DatasetFormatError(
            path,
            f"{csize} bytes of LZF data cannot decompress to {usize} bytes",
            expected=expected,
        )
    try:
        plain = _lzf_decode(body[8:], usize)
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
        packed = _lzf_encode(plain)
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


LZF_ENV = "LIDARJAX_LZF"
"""Environment variable choosing the LZF codec: ``auto`` (default), ``python-lzf``,
``pure-python``."""
_LZF_BACKENDS = ("python-lzf", "pure-python")


def lzf_backend() -> str:
    """The LZF codec that :func:`read_pcd` and :func:`write_pcd` use for ``binary_compressed``.

    ``"python-lzf"`` (the compiled ``lzf`` module, liblzf; tens of times faster) when it is
    importable, else ``"pure-python"`` (this module's codec). The environment variable
    ``LIDARJAX_LZF`` forces one: ``auto`` (the default), ``python-lzf`` or ``pure-python``;
    it is read at every call, so it can be changed at run time (e.g. with pytest's
    ``monkeypatch.setenv``). Both codecs accept exactly the same streams and write streams
    that both (and PCL) read; the compressed bytes may differ.

    Returns:
        ``"python-lzf"`` or ``"pure-python"``.

    Raises:
        ValueError: If ``LIDARJAX_LZF`` holds another value.
        ImportError: If ``LIDARJAX_LZF=python-lzf`` but ``lzf`` cannot be imported.
    """
    choice = os.environ.get(LZF_ENV, "auto").strip().lower() or "auto"
    if choice == "auto":
        return "python-lzf" if _lzf_ext is not None else "pure-python"
    if choice not in _LZF_BACKENDS:
        raise ValueError(
            f"environment variable {LZF_ENV} must be one of auto, python-lzf, pure-python; "
            f"got {os.environ[LZF_ENV]!r}"
        )
    if choice == "python-lzf" and _lzf_ext is None:
        raise ImportError(
            f"{LZF_ENV}=python-lzf, but the 'lzf' module (pip install python-lzf) is not importable"
        )
    return choice


def _lzf_encode(data: bytes, backend: str | None = None) -> bytes:
    """LZF-compresses ``data`` with ``backend`` (default: :func:`lzf_backend`).

    PCL's format has no "stored" mode: incompressible data is written as an LZF stream of
    literal runs, slightly longer than the input (one control byte per 32 bytes), as the
    pure-Python encoder does. liblzf returns nothing when its output would exceed the given
    bound, so python-lzf gets the bound of that worst case plus a margin; should it still
    refuse, the pure-Python encoder writes the stream. An empty input is an empty stream.
    """
    backend = lzf_backend() if backend is None else backend
    data = bytes(data)
    if backend == "pure-python" or not data:
        return _lzf_compress(data)
    if backend != "python-lzf":
        raise ValueError(f"backend must be one of {_LZF_BACKENDS}, got {backend!r}")
    if _lzf_ext is None:
        raise ImportError("backend 'python-lzf' needs the 'lzf' module (pip install python-lzf)")
    packed = _lzf_ext.compress(data, len(data) + len(data) // 32 + 16)
    return _lzf_compress(data) if packed is None else packed


def _lzf_decode(data: bytes, expected_size: int, backend: str | None = None) -> bytes:
    """Decompresses an LZF stream with ``backend`` (default: :func:`lzf_backend`).

    Accepts exactly the streams :func:`_lzf_decompress` accepts (liblzf checks every
    literal run and back-reference against both buffers) and returns the same bytes.

    Raises:
        _LZFError: If the stream is corrupt or does not decode to ``expected_size`` bytes.
    """
    backend = lzf_backend() if backend is None else backend
    data = bytes(data)
    if backend == "pure-python":
        return _lzf_decompress(data, expected_size)
    if backend != "python-lzf":
        raise ValueError(f"backend must be one of {_LZF_BACKENDS}, got {backend!r}")
    if _lzf_ext is None:
        raise ImportError("backend 'python-lzf' needs the 'lzf' module (pip install python-lzf)")
    # liblzf cannot tell an empty result from an error: handle the empty cases here.
    if expected_size == 0:
        if data:
            raise _LZFError("stream decodes to more than the expected 0 bytes")
        return b""
    if not data:
        raise _LZFError(f"stream decodes to 0 bytes, expected {expected_size} (truncated stream?)")
    try:
        out = _lzf_ext.decompress(data, expected_size)
    except ValueError:
        raise _LZFError(
            "liblzf rejects the stream: a literal run or back-reference runs past the end "
            "of the input, or a back-reference points before the start of the output"
        ) from None
    if out is None:
        raise _LZFError(f"stream decodes to more than the expected {expected_size} bytes")
    if len(out) != expected_size:
        raise _LZFError(
            f"stream decodes to {len(out)} bytes, expected {expected_size} (truncated stream?)"
        )
    return out


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
