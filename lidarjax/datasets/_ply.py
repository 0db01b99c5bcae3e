"""Reader and writer for PLY (Polygon File Format) point clouds, and labelled segmentations.

A PLY file is an ASCII header (``ply``, ``format``, ``comment`` / ``obj_info`` lines,
``element <name> <count>`` each followed by its ``property`` lines, ``end_header``) and a body
in one of three encodings: ``ascii`` (one element record per line), ``binary_little_endian``
or ``binary_big_endian`` (packed records). :func:`read_ply` returns the ``vertex`` element as
a :class:`~lidarjax.datasets.PointCloud` (one field per scalar property, dtype as declared);
every other element (faces, edges, ...) is parsed past, list properties included, so that a
mesh's vertices are read correctly and a truncated or overlong file is an error.

PLY has no notion of an organized cloud. :func:`write_ply` records the grid in an
``obj_info lidarjax height <H> width <W>`` header line (and a non-default viewpoint in
``obj_info lidarjax viewpoint tx ty tz qw qx qy qz``), which :func:`read_ply` honours;
clouds from other tools have no such line and are read unorganized (height 1).

:func:`write_labelled_cloud` writes points with an integer segment label per point (fields
``x y z label``: float32 and uint32, PCL's ``PointXYZL``) as PCD or PLY, which PCL, Open3D
and CloudCompare read.

NumPy only; nothing here is called inside ``jit``. Reading is vectorised: binary elements
without list properties are one :func:`numpy.frombuffer` of a structured dtype, ASCII values
are checked with one regular expression per column and converted by NumPy.
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
from ._pcd import PointCloud, _ascii_body, write_pcd
from ._text import DECIMAL_RE, INTEGER_RE, NUMBER_RE

__all__ = ["read_ply", "write_labelled_cloud", "write_ply"]

# PLY scalar type names (both spellings of the specification) -> NumPy dtype.
_PLY_TYPES: dict[str, np.dtype] = {
    "char": np.dtype(np.int8),
    "int8": np.dtype(np.int8),
    "uchar": np.dtype(np.uint8),
    "uint8": np.dtype(np.uint8),
    "short": np.dtype(np.int16),
    "int16": np.dtype(np.int16),
    "ushort": np.dtype(np.uint16),
    "uint16": np.dtype(np.uint16),
    "int": np.dtype(np.int32),
    "int32": np.dtype(np.int32),
    "uint": np.dtype(np.uint32),
    "uint32": np.dtype(np.uint32),
    "float": np.dtype(np.float32),
    "float32": np.dtype(np.float32),
    "double": np.dtype(np.float64),
    "float64": np.dtype(np.float64),
}
_DTYPE_TO_PLY: dict[np.dtype, str] = {
    np.dtype(np.int8): "char",
    np.dtype(np.uint8): "uchar",
    np.dtype(np.int16): "short",
    np.dtype(np.uint16): "ushort",
    np.dtype(np.int32): "int",
    np.dtype(np.uint32): "uint",
    np.dtype(np.float32): "float",
    np.dtype(np.float64): "double",
}
_STRUCT_CODES = {
    np.dtype(np.int8): "b",
    np.dtype(np.uint8): "B",
    np.dtype(np.int16): "h",
    np.dtype(np.uint16): "H",
    np.dtype(np.int32): "i",
    np.dtype(np.uint32): "I",
}
_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
_BYTE_ORDER = {"binary_little_endian": "<", "binary_big_endian": ">"}
_VERSIONS = (b"1.0", b"1")
_DEFAULT_VIEWPOINT = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
_HEADER_EXPECTED = (
    "PLY header: 'ply', 'format ascii|binary_little_endian|binary_big_endian 1.0', "
    "comment / obj_info lines, 'element <name> <count>' each followed by "
    "'property <type> <name>' or 'property list <count type> <item type> <name>' lines, "
    "'end_header'; types char uchar short ushort int uint float double (or int8 .. float64)"
)


# --------------------------------------------------------------------------------------------
# Header
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass
class _Property:
    name: str
    dtype: np.dtype  # the item type of a list property
    count_dtype: np.dtype | None  # None for a scalar property


@dataclasses.dataclass
class _Element:
    name: str
    count: int
    line: int
    properties: list[_Property] = dataclasses.field(default_factory=list)

    @property
    def has_lists(self) -> bool:
        return any(p.count_dtype is not None for p in self.properties)


@dataclasses.dataclass
class _Header:
    format: str
    elements: list[_Element]
    vertex: _Element
    height: int
    width: int
    viewpoint: np.ndarray
    data_offset: int
    data_line: int  # 1-based line number of the first body line (ASCII)


def _parse_header(path: Path, raw: bytes) -> _Header:
    def fail(message: str, line: int | None) -> DatasetFormatError:
        return DatasetFormatError(path, message, line=line, expected=_HEADER_EXPECTED)

    first = raw.find(b"\n")
    if raw[: first if first >= 0 else len(raw)].rstrip() != b"ply":
        raise fail("not a PLY file: the first line is not 'ply'", 1)
    pos = first + 1
    lineno = 1
    fmt: str | None = None
    elements: list[_Element] = []
    grid: tuple[int, int, int] | None = None  # (height, width, line)
    viewpoint = np.array(_DEFAULT_VIEWPOINT, dtype=np.float64)
    data_offset = -1
    while pos < len(raw):
        end = raw.find(b"\n", pos)
        if end < 0:
            break  # a header line must end in a newline; end_header is missing
        lineno += 1
        tokens = raw[pos:end].split()  # ASCII whitespace only (also drops a trailing \r)
        pos = end + 1
        if not tokens:
            raise fail("blank line in the header", lineno)
        key = tokens[0]
        if key == b"end_header":
            if len(tokens) != 1:
                raise fail("text after 'end_header'", lineno)
            data_offset = pos
            break
        if key == b"comment" or key == b"obj_info":
            if len(tokens) > 1 and tokens[1] == b"lidarjax":
                if len(tokens) > 2 and tokens[2] == b"height":
                    if grid is not None:
                        raise fail("duplicate 'lidarjax height .. width ..' line", lineno)
                    grid = _parse_grid(tokens, lineno, fail)
                elif len(tokens) > 2 and tokens[2] == b"viewpoint":
                    viewpoint = _parse_viewpoint(tokens, lineno, fail)
            continue
        if key == b"format":
            if fmt is not None:
                raise fail("duplicate 'format' line", lineno)
            if len(tokens) != 3 or tokens[1].decode("latin-1") not in _FORMATS:
                raise fail(
                    f"bad format line {_text(tokens)!r}",
                    lineno,
                )
            if tokens[2] not in _VERSIONS:
                raise fail(f"unsupported PLY version {tokens[2].decode('latin-1')!r}", lineno)
            fmt = tokens[1].decode("ascii")
            continue
        if key == b"element":
            if len(tokens) != 3 or not tokens[2].isdigit():
                raise fail(f"bad element line {_text(tokens)!r}", lineno)
            name = tokens[1].decode("latin-1")
            if any(e.name == name for e in elements):
                raise fail(f"duplicate element {name!r}", lineno)
            elements.append(_Element(name=name, count=int(tokens[2]), line=lineno))
            continue
        if key == b"property":
            if not elements:
                raise fail("'property' line before any 'element' line", lineno)
            elements[-1].properties.append(_parse_property(tokens, lineno, elements[-1], fail))
            continue
        raise fail(f"unknown header keyword {key.decode('latin-1')!r}", lineno)
    if data_offset < 0:
        raise fail("the header has no 'end_header' line (truncated file?)", None)
    if fmt is None:
        raise fail("the header has no 'format' line", None)
    for element in elements:
        if element.count and not element.properties:
            raise fail(f"element {element.name!r} has no properties", element.line)
    vertex = next((e for e in elements if e.name == "vertex"), None)
    if vertex is None:
        raise fail("no 'vertex' element: nothing to read as a point cloud", None)
    if not vertex.properties:
        raise fail("the 'vertex' element has no properties", vertex.line)
    if vertex.has_lists:
        raise DatasetFormatError(
            path,
            "list properties in the 'vertex' element are not supported",
            line=vertex.line,
            expected="a 'vertex' element of scalar properties only",
        )
    height, width = 1, vertex.count
    if grid is not None:
        height, width, grid_line = grid
        if height * width != vertex.count:
            raise DatasetFormatError(
                path,
                f"lidarjax grid height {height} x width {width} = {height * width} != "
                f"{vertex.count} vertices",
                line=grid_line,
                expected="'obj_info lidarjax height H width W' with H * W = vertex count",
            )
    return _Header(
        format=fmt,
        elements=elements,
        vertex=vertex,
        height=height,
        width=width,
        viewpoint=viewpoint,
        data_offset=data_offset,
        data_line=lineno + 1,
    )


def _text(tokens: list[bytes]) -> str:
    return b" ".join(tokens).decode("latin-1")


def _parse_type(token: bytes, lineno: int, fail) -> np.dtype:
    dtype = _PLY_TYPES.get(token.decode("latin-1"))
    if dtype is None:
        raise fail(f"unknown property type {token.decode('latin-1')!r}", lineno)
    return dtype


def _parse_property(tokens: list[bytes], lineno: int, element: _Element, fail) -> _Property:
    if len(tokens) >= 2 and tokens[1] == b"list":
        if len(tokens) != 5:
            raise fail(f"bad list property line {_text(tokens)!r}", lineno)
        count_dtype = _parse_type(tokens[2], lineno, fail)
        if count_dtype.kind not in "iu":
            raise fail(f"list count type {tokens[2].decode('latin-1')!r} is not an integer", lineno)
        prop = _Property(
            tokens[4].decode("latin-1"), _parse_type(tokens[3], lineno, fail), count_dtype
        )
    else:
        if len(tokens) != 3:
            raise fail(f"bad property line {_text(tokens)!r}", lineno)
        prop = _Property(tokens[2].decode("latin-1"), _parse_type(tokens[1], lineno, fail), None)
    if any(p.name == prop.name for p in element.properties):
        raise fail(f"duplicate property {prop.name!r} in element {element.name!r}", lineno)
    if any(b < 0x21 or b > 0x7E for b in prop.name.encode("latin-1")):
        raise fail(f"invalid property name {prop.name!r}", lineno)
    return prop


def _parse_grid(tokens: list[bytes], lineno: int, fail) -> tuple[int, int, int]:
    # obj_info lidarjax height H width W
    if (
        len(tokens) != 6
        or tokens[4] != b"width"
        or not tokens[3].isdigit()
        or not tokens[5].isdigit()
    ):
        raise fail(
            f"bad lidarjax grid line {_text(tokens)!r}; expected 'obj_info lidarjax height H "
            "width W'",
            lineno,
        )
    return int(tokens[3]), int(tokens[5]), lineno


def _parse_viewpoint(tokens: list[bytes], lineno: int, fail) -> np.ndarray:
    values = tokens[3:]
    if len(values) != 7 or not all(DECIMAL_RE.fullmatch(v) for v in values):
        raise fail(
            f"bad lidarjax viewpoint line {_text(tokens)!r}; expected 'obj_info lidarjax "
            "viewpoint tx ty tz qw qx qy qz' with 7 finite numbers",
            lineno,
        )
    viewpoint = np.array([float(v) for v in values], dtype=np.float64)
    if not np.isfinite(viewpoint).all():
        raise fail(f"lidarjax viewpoint {_text(values)!r} overflows", lineno)
    return viewpoint


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


def read_ply(path: str | os.PathLike[str]) -> PointCloud:
    """Reads the ``vertex`` element of a PLY file as a point cloud.

    Every scalar property of ``vertex`` becomes a field of that name with the declared type
    (``char``/``int8`` -> int8, ``uchar``/``uint8`` -> uint8, ``short`` -> int16, ``ushort``
    -> uint16, ``int`` -> int32, ``uint`` -> uint32, ``float`` -> float32, ``double`` ->
    float64). Other elements (e.g. ``face`` with its list property) are parsed past and
    dropped. ASCII bodies hold one element record per line (blank lines are skipped); numbers
    are decimal literals (``nan`` / ``inf`` allowed for float properties).

    Args:
        path: File to read.

    Returns:
        The cloud: ``[height, width]`` fields, organized when the file carries lidarjax's
        ``obj_info lidarjax height H width W`` line (as :func:`write_ply` writes it),
        otherwise unorganized (``height == 1``, ``width`` = number of vertices). The viewpoint
        is the one recorded by :func:`write_ply`, else the identity.

    Raises:
        FileNotFoundError: If ``path`` does not exist.
        DatasetFormatError: If the file is not PLY, the header is malformed (unknown keyword
            or type, property before any element, duplicate names, a grid that does not
            match the vertex count, no ``vertex`` element or one with list properties), the
            body is truncated or has trailing data, a list count is negative, or an ASCII
            record has the wrong number of values or a value that is not a number of its
            type or out of its range. The message names the path, the line where known and
            the expected format.
    """
    path = Path(path)
    raw = path.read_bytes()
    header = _parse_header(path, raw)
    if header.format == "ascii":
        columns = _read_ascii(path, header, raw)
    else:
        columns = _read_binary(path, header, raw)
    shape = (header.height, header.width)
    fields = {
        p.name: np.ascontiguousarray(col.reshape(shape))
        for p, col in zip(header.vertex.properties, columns, strict=True)
    }
    return PointCloud(
        fields=fields, width=header.width, height=header.height, viewpoint=header.viewpoint
    )


def _element_spec(element: _Element) -> str:
    parts = []
    for p in element.properties:
        if p.count_dtype is None:
            parts.append(f"{p.name}:{p.dtype}")
        else:
            parts.append(f"{p.name}:list[{p.count_dtype}]{p.dtype}")
    return f"element {element.name!r} ({' '.join(parts)})"


# -------------------------------------------------------------------------------- binary


def _read_binary(path: Path, header: _Header, raw: bytes) -> list[np.ndarray]:
    order = _BYTE_ORDER[header.format]
    offset = header.data_offset
    columns: list[np.ndarray] = []
    for element in header.elements:
        if element.has_lists:
            offset = _skip_binary_lists(path, element, raw, offset, order)
            continue
        record = np.dtype(
            [(f"f{i}", p.dtype.newbyteorder(order)) for i, p in enumerate(element.properties)]
        )
        need = element.count * record.itemsize
        if len(raw) - offset < need:
            raise DatasetFormatError(
                path,
                f"binary data truncated: element {element.name!r} needs {element.count} "
                f"records of {record.itemsize} bytes = {need} bytes at byte offset {offset}, "
                f"but only {len(raw) - offset} bytes are left",
                expected=f"{element.count} packed {header.format} records of "
                f"{_element_spec(element)}",
            )
        if element is header.vertex:
            table = np.frombuffer(raw, dtype=record, count=element.count, offset=offset)
            columns = [table[f"f{i}"].astype(p.dtype) for i, p in enumerate(element.properties)]
        offset += need
    if offset != len(raw):
        raise DatasetFormatError(
            path,
            f"{len(raw) - offset} bytes of trailing data after the last element "
            f"(byte offset {offset})",
            expected="the file to end after the records of all declared elements",
        )
    return columns


def _skip_binary_lists(path: Path, element: _Element, raw: bytes, offset: int, order: str) -> int:
    """Byte offset just after the records of an element with list properties."""
    if element.count == 0:
        return offset
    expected = f"{element.count} packed records of {_element_spec(element)}"

    def truncated(index: int, at: int) -> DatasetFormatError:
        return DatasetFormatError(
            path,
            f"binary data truncated inside record {index} of element {element.name!r} "
            f"(byte offset {at}, file size {len(raw)})",
            expected=expected,
        )

    counters = {
        p.name: struct.Struct(order + _STRUCT_CODES[p.count_dtype])
        for p in element.properties
        if p.count_dtype is not None
    }

    def read_count(prop: _Property, at: int, index: int) -> int:
        counter = counters[prop.name]
        if at + counter.size > len(raw):
            raise truncated(index, at)
        (value,) = counter.unpack_from(raw, at)
        if value < 0:
            raise DatasetFormatError(
                path,
                f"negative list length {value} for property {prop.name!r} in record {index} "
                f"of element {element.name!r} (byte offset {at})",
                expected=expected,
            )
        return value

    # Fast path: assume every record has the list lengths of the first one, view all
    # records at once and check that assumption (by induction it then holds exactly).
    lengths: list[int] = []
    at = offset
    for p in element.properties:
        if p.count_dtype is None:
            at += p.dtype.itemsize
        else:
            lengths.append(read_count(p, at, 0))
            at += p.count_dtype.itemsize + lengths[-1] * p.dtype.itemsize
        if at > len(raw):
            raise truncated(0, at)
    layout = []
    k = 0
    for i, p in enumerate(element.properties):
        if p.count_dtype is None:
            layout.append((f"s{i}", p.dtype.newbyteorder(order)))
        else:
            layout.append((f"c{i}", p.count_dtype.newbyteorder(order)))
            if lengths[k]:
                layout.append((f"v{i}", p.dtype.newbyteorder(order), (lengths[k],)))
            k += 1
    record = np.dtype(layout)
    if offset + element.count * record.itemsize <= len(raw):
        table = np.frombuffer(raw, dtype=record, count=element.count, offset=offset)
        k = 0
        uniform = True
        for i, p in enumerate(element.properties):
            if p.count_dtype is not None:
                uniform = uniform and bool((table[f"c{i}"] == lengths[k]).all())
                k += 1
        if uniform:
            return offset + element.count * record.itemsize
    # General case: walk the records (variable list lengths, e.g. triangles and quads).
    at = offset
    for index in range(element.count):
        for p in element.properties:
            if p.count_dtype is None:
                at += p.dtype.itemsize
            else:
                n = read_count(p, at, index)
                at += p.count_dtype.itemsize + n * p.dtype.itemsize
            if at > len(raw):
                raise truncated(index, at)
    return at


# -------------------------------------------------------------------------------- ascii

# The bytes a line of numbers may hold: ASCII whitespace (where bytes.split() separates) and
# the characters of decimal literals, nan / inf / infinity in any case, and integers.
_NUMBER_BYTES = b" \t\n\r\v\f0123456789+-.eEnNaAiIfFtTyY"
_NUMBER_LUT = np.zeros(256, dtype=bool)
_NUMBER_LUT[list(_NUMBER_BYTES)] = True


@dataclasses.dataclass
class _AsciiBody:
    """Token layout of an ASCII body: records are the non-blank lines."""

    body: bytes
    tokens: list[bytes]  # every token of the body, in order
    record_line: np.ndarray  # [R] 0-based body line of each record
    record_size: np.ndarray  # [R] tokens per record
    record_first: np.ndarray  # [R] index into `tokens` of each record's first token
    line_start: np.ndarray  # [L] byte offset of each body line
    line_end: np.ndarray  # [L] byte offset of the end of each body line (its newline)


def _ascii_layout(body: bytes) -> _AsciiBody:
    data = np.frombuffer(body, dtype=np.uint8)
    ws = (data == 32) | (np.subtract(data, 9, dtype=np.uint8) <= 4)  # space, \t \n \v \f \r
    starts = ~ws
    starts[1:] &= ws[:-1]
    newlines = np.flatnonzero(data == 10)
    line_start = np.concatenate([[0], newlines + 1])
    line_end = np.concatenate([newlines, [len(body)]])
    token_at = np.flatnonzero(starts)  # byte offset of each token
    first = np.searchsorted(token_at, line_start)  # index of each line's first token
    size = np.searchsorted(token_at, line_end) - first
    record_line = np.flatnonzero(size > 0)
    return _AsciiBody(
        body=body,
        tokens=body.split(),
        record_line=record_line,
        record_size=size[record_line],
        record_first=first[record_line],
        line_start=line_start,
        line_end=line_end,
    )


def _read_ascii(path: Path, header: _Header, raw: bytes) -> list[np.ndarray]:
    layout = _ascii_layout(raw[header.data_offset :])
    n_records = layout.record_line.size

    def lineno(record: int) -> int:
        return header.data_line + int(layout.record_line[record])

    columns: list[np.ndarray] = []
    cursor = 0
    for element in header.elements:
        if n_records - cursor < element.count:
            raise DatasetFormatError(
                path,
                f"file ends after {n_records - cursor} of {element.count} records of element "
                f"{element.name!r}",
                line=header.data_line + layout.line_start.size - 1,
                expected=f"one line per record of {_element_spec(element)}",
            )
        records = slice(cursor, cursor + element.count)
        values = _ascii_element(path, element, layout, records, lineno)
        if element is header.vertex:
            columns = values
        cursor += element.count
    if cursor != n_records:
        raise DatasetFormatError(
            path,
            f"{n_records - cursor} extra data line(s) after the last element",
            line=lineno(cursor),
            expected="the file to end after the records of all declared elements",
        )
    return columns


def _ascii_element(
    path: Path, element: _Element, layout: _AsciiBody, records: slice, lineno
) -> list[np.ndarray]:
    """Checks the records of one element; the columns of a scalar element (else [])."""
    count = records.stop - records.start
    if count == 0:
        return [np.empty(0, dtype=p.dtype) for p in element.properties]
    sizes = layout.record_size[records]
    first_token = int(layout.record_first[records.start])
    n_tokens = int(sizes.sum())
    tokens = layout.tokens[first_token : first_token + n_tokens]
    if element.has_lists:
        expected = (
            f"one line per record of {_element_spec(element)}: each list as its length, "
            "then that many values"
        )
    else:
        expected = f"one line of {len(element.properties)} values per record of " + (
            _element_spec(element)
        )

    def fail(record: int, message: str) -> DatasetFormatError:
        return DatasetFormatError(path, message, line=lineno(record), expected=expected)

    # Every byte of the element's lines must be whitespace or may be part of a number.
    lo = int(layout.line_start[layout.record_line[records.start]])
    hi = int(layout.line_end[layout.record_line[records.stop - 1]])
    if layout.body[lo:hi].translate(None, _NUMBER_BYTES):
        text = np.frombuffer(layout.body, dtype=np.uint8, count=hi - lo, offset=lo)
        bad_bytes = np.flatnonzero(~_NUMBER_LUT[text])
        at = lo + int(bad_bytes[0])
        line = int(np.searchsorted(layout.line_start, at, side="right")) - 1
        record = int(np.searchsorted(layout.record_line, line))
        token = next(
            t
            for t in layout.body[layout.line_start[line] : layout.line_end[line]].split()
            if not _NUMBER_LUT[np.frombuffer(t, dtype=np.uint8)].all()
        )
        raise fail(record, f"{token.decode('latin-1')!r} is not a number")

    if element.has_lists:
        table = np.array(tokens, dtype=np.bytes_)
        _check_ascii_lists(element, tokens, table, sizes, records.start, fail)
        try:
            table.astype(np.float64)
        except ValueError:
            i = next(i for i, t in enumerate(tokens) if NUMBER_RE.fullmatch(t) is None)
            record = records.start + int(np.searchsorted(np.cumsum(sizes), i, side="right"))
            raise fail(record, f"{tokens[i].decode('latin-1')!r} is not a number") from None
        return []

    k = len(element.properties)
    wrong = np.flatnonzero(sizes != k)
    if wrong.size:
        i = int(wrong[0])
        raise fail(records.start + i, f"record has {sizes[i]} values")
    table = np.array(tokens, dtype=np.bytes_).reshape(count, k)
    return [
        _ascii_column(p, table[:, j], tokens[j::k], records.start, fail)
        for j, p in enumerate(element.properties)
    ]


def _ascii_column(prop: _Property, column: np.ndarray, tokens, first: int, fail) -> np.ndarray:
    is_float = prop.dtype.kind == "f"
    single = NUMBER_RE if is_float else INTEGER_RE

    def syntax_error() -> DatasetFormatError:
        i = next(i for i, t in enumerate(tokens) if single.fullmatch(t) is None)
        return fail(
            first + i,
            f"cannot parse {tokens[i].decode('latin-1')!r} as {prop.dtype} for property "
            f"{prop.name!r}",
        )

    def out_of_range(i: int) -> DatasetFormatError:
        return fail(
            first + i,
            f"value {tokens[i].decode('latin-1')!r} of property {prop.name!r} is out of range "
            f"for {prop.dtype}",
        )

    # The byte check above leaves exactly the tokens Python's float() / int() parse and
    # the accepted number syntax agrees on (no '_', no inner whitespace).
    if is_float:
        try:
            wide = column.astype(np.float64)
        except ValueError:
            raise syntax_error() from None
        with np.errstate(over="ignore"):
            values = wide.astype(prop.dtype)
        for i in np.flatnonzero(np.isinf(values)):  # an overflowing literal, or a real "inf"
            if DECIMAL_RE.fullmatch(tokens[i]):
                raise out_of_range(int(i))
        return values
    try:
        wide = column.astype(np.int64)
    except ValueError:
        raise syntax_error() from None
    except OverflowError:
        if any(single.fullmatch(t) is None for t in tokens):
            raise syntax_error() from None
        i = next(i for i, t in enumerate(tokens) if not -(2**63) <= int(t) < 2**63)
        raise out_of_range(i) from None
    info = np.iinfo(prop.dtype)
    bad = np.flatnonzero((wide < info.min) | (wide > info.max))
    if bad.size:
        raise out_of_range(int(bad[0]))
    return wide.astype(prop.dtype)


def _check_ascii_lists(
    element: _Element, tokens: list[bytes], table: np.ndarray, sizes: np.ndarray, first, fail
):
    """Checks that each record's list lengths account for exactly its tokens."""
    props = element.properties
    lists = [i for i, p in enumerate(props) if p.count_dtype is not None]
    start = 0
    if len(lists) == 1:
        # One list: its length follows from the record size; check all length tokens at once.
        length = sizes - len(props)
        at = np.cumsum(sizes) - sizes + lists[0]
        ok = length >= 0
        try:
            ok[ok] = table[at[ok]].astype(np.int64) == length[ok]
        except (ValueError, OverflowError):  # a length that is no integer: found below
            ok[:] = False
        if ok.all():
            return
        start = int(np.argmin(ok))
    # Several lists, or from the first bad record on: walk the records.
    offset = int(np.sum(sizes[:start]))
    for r in range(start, sizes.size):
        size = int(sizes[r])
        at = 0
        for p in props:
            if p.count_dtype is None:
                at += 1
                continue
            token = tokens[offset + at] if at < size else b""
            if not INTEGER_RE.fullmatch(token) or int(token) < 0:
                raise fail(first + r, f"bad list length {token.decode('latin-1')!r} of {p.name!r}")
            at += 1 + int(token)
            if at > size:
                break
        if at != size:
            raise fail(first + r, f"record has {size} values, its list lengths make it {at}")
        offset += size


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def write_ply(
    path: str | os.PathLike[str],
    cloud: PointCloud | Mapping[str, Any],
    *,
    format: str = "binary_little_endian",
) -> Path:
    """Writes a cloud as a PLY file (one ``vertex`` element) that :func:`read_ply` reads back.

    Each field becomes a scalar ``vertex`` property of the matching PLY type (float32 ->
    ``float``, float64 -> ``double``, (u)int8/16/32 -> ``(u)char``/``(u)short``/``(u)int``).
    The grid is recorded as ``obj_info lidarjax height H width W`` and a non-default
    viewpoint as ``obj_info lidarjax viewpoint ...``; other tools ignore these lines and see
    ``H * W`` vertices in row-major order. ASCII floats are written with 9 (float32) / 17
    (float64) significant digits so that they round-trip; NaN is written as ``nan``.

    Args:
        path: Output file (overwritten).
        cloud: A :class:`~lidarjax.datasets.PointCloud`, or a dict of field arrays passed to
            :meth:`~lidarjax.datasets.PointCloud.from_fields`.
        format: ``"binary_little_endian"`` (default), ``"binary_big_endian"`` or ``"ascii"``.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ValueError: If ``format`` is unknown, or a field has ``COUNT > 1`` or a dtype PLY
            cannot store (int64 / uint64); the field is named.
    """
    if format not in _FORMATS:
        raise ValueError(f"format must be one of {_FORMATS}, got {format!r}")
    if not isinstance(cloud, PointCloud):
        cloud = PointCloud.from_fields(cloud)
    if not cloud.fields:
        raise ValueError("cannot write a point cloud without fields")
    path = Path(path)
    n = cloud.num_points
    names = list(cloud.fields)
    arrays: list[np.ndarray] = []
    types: list[str] = []
    for name in names:
        arr = np.asarray(cloud.fields[name])
        if arr.ndim != 2:
            raise ValueError(
                f"field {name!r} has COUNT {arr.shape[2]} > 1; PLY stores one value per "
                "property: split it into scalar fields"
            )
        ply_type = _DTYPE_TO_PLY.get(arr.dtype.newbyteorder("="))
        if ply_type is None:
            raise ValueError(
                f"field {name!r} has dtype {arr.dtype}, which PLY cannot store; use float32, "
                "float64 or (u)int8/16/32"
            )
        arrays.append(arr.reshape(n))
        types.append(ply_type)
    lines = [
        "ply",
        f"format {format} 1.0",
        "comment written by lidarjax",
        f"obj_info lidarjax height {cloud.height} width {cloud.width}",
    ]
    if not np.array_equal(cloud.viewpoint, _DEFAULT_VIEWPOINT):
        lines.append(
            "obj_info lidarjax viewpoint " + " ".join(f"{v:.17g}" for v in cloud.viewpoint)
        )
    lines.append(f"element vertex {n}")
    lines += [f"property {t} {name}" for t, name in zip(types, names, strict=True)]
    lines.append("end_header")
    head = ("\n".join(lines) + "\n").encode("ascii")
    if format == "ascii":
        body = _ascii_body([a.reshape(n, 1) for a in arrays], n)
    else:
        order = _BYTE_ORDER[format]
        record = np.dtype([(f"f{i}", a.dtype.newbyteorder(order)) for i, a in enumerate(arrays)])
        table = np.empty(n, dtype=record)
        for i, a in enumerate(arrays):
            table[f"f{i}"] = a
        body = table.tobytes()
    path.write_bytes(head + body)
    return path


# --------------------------------------------------------------------------------------------
# Labelled segmentations
# --------------------------------------------------------------------------------------------

_LABELLED_FORMATS = {".pcd": "pcd", ".ply": "ply"}


def write_labelled_cloud(
    path: str | os.PathLike[str],
    points: Any,
    labels: Any,
    *,
    format: str | None = None,
    encoding: str | None = None,
) -> Path:
    """Writes points with one integer label each (a segmentation) as PCD or PLY.

    The fields are ``x y z`` (float32) and ``label`` (uint32), the layout of PCL's
    ``PointXYZL``, which PCL, Open3D and CloudCompare (as a scalar field) read.
    :func:`~lidarjax.datasets.read_pcd` / :func:`read_ply` give the labels back exactly
    (``cloud["label"]``, uint32) and the points rounded to float32; an organized ``[H, W]``
    input stays organized.

    A :class:`~lidarjax.features.PlaneSegmentation` marks rays on no plane with ``-1``; pass
    ``seg.labels + 1`` (0 = no plane, plane ``j`` -> ``j + 1``) together with the scan's
    points: ``write_labelled_cloud("seg.pcd", points, seg.labels + 1)``.

    Args:
        path: Output file (overwritten); its suffix (``.pcd`` or ``.ply``, any case) picks the
            format unless ``format`` is given.
        points: ``[H, W, 3]`` (organized) or ``[n, 3]`` points (m); NaN marks no return.
        labels: ``[H, W]`` or ``[n]`` integer labels matching ``points``, each in
            ``[0, 2**32 - 1]``.
        format: ``"pcd"`` or ``"ply"``; default: from the suffix of ``path``.
        encoding: PCD ``DATA`` (``"binary_compressed"`` by default, ``"binary"``,
            ``"ascii"``) or PLY ``format`` (``"binary_little_endian"`` by default,
            ``"binary_big_endian"``, ``"ascii"``).

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ValueError: If the format cannot be determined or is unknown, ``points`` is not
            ``[H, W, 3]`` / ``[n, 3]`` real numbers, ``labels`` does not match it, is not
            integer or has a value outside ``[0, 2**32 - 1]`` (the argument is named).
    """
    path = Path(path)
    if format is None:
        format = _LABELLED_FORMATS.get(path.suffix.lower())
        if format is None:
            raise ValueError(
                f"cannot tell the format of {str(path)!r} from its suffix; name it .pcd or "
                "'.ply', or pass format='pcd' | 'ply'"
            )
    if format not in ("pcd", "ply"):
        raise ValueError(f"format must be 'pcd' or 'ply', got {format!r}")
    pts = np.asarray(points)
    if pts.ndim not in (2, 3) or pts.shape[-1] != 3:
        raise ValueError(f"points must have shape [H, W, 3] or [n, 3], got {pts.shape}")
    if pts.dtype.kind not in "fiu":
        raise ValueError(f"points must be real numbers, got dtype {pts.dtype}")
    lab = np.asarray(labels)
    if lab.shape != pts.shape[:-1]:
        raise ValueError(
            f"labels must have shape {list(pts.shape[:-1])} (one per point), got {list(lab.shape)}"
        )
    if lab.dtype.kind not in "iu":
        raise ValueError(f"labels must be integers, got dtype {lab.dtype}")
    if lab.size and (int(lab.min()) < 0 or int(lab.max()) > np.iinfo(np.uint32).max):
        bad = int(lab.min()) if int(lab.min()) < 0 else int(lab.max())
        hint = " (a PlaneSegmentation's -1: pass seg.labels + 1)" if bad == -1 else ""
        raise ValueError(f"labels must be in [0, 2**32 - 1], got {bad}{hint}")
    if pts.ndim == 2:
        pts, lab = pts[None], lab[None]
    with np.errstate(over="ignore", invalid="ignore"):
        xyz = pts.astype(np.float32)
    fields = {
        "x": xyz[..., 0],
        "y": xyz[..., 1],
        "z": xyz[..., 2],
        "label": lab.astype(np.uint32),
    }
    cloud = PointCloud.from_fields(fields)
    if format == "pcd":
        return write_pcd(path, cloud, data=encoding or "binary_compressed")
    return write_ply(path, cloud, format=encoding or "binary_little_endian")
