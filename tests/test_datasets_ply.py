"""Tests for the PLY reader/writer and the labelled-cloud writer in ``lidarjax.datasets._ply``."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from lidarjax.datasets import (
    DatasetFormatError,
    PointCloud,
    read_pcd,
    read_ply,
    write_labelled_cloud,
    write_ply,
)

FORMATS = ["ascii", "binary_little_endian", "binary_big_endian"]
DTYPES = [np.int8, np.uint8, np.int16, np.uint16, np.int32, np.uint32, np.float32, np.float64]


def _all_dtypes_cloud(shape=(3, 5), seed=0) -> dict[str, np.ndarray]:
    """One field per PLY type, with the type's extremes and (floats) nan / inf / -0 / tiny."""
    rng = np.random.default_rng(seed)
    fields = {}
    for dt in DTYPES:
        dt = np.dtype(dt)
        if dt.kind == "f":
            a = rng.normal(scale=1e3, size=shape).astype(dt)
            a.flat[:6] = [np.nan, np.inf, -np.inf, -0.0, np.finfo(dt).tiny / 4, np.finfo(dt).max]
        else:
            info = np.iinfo(dt)
            a = rng.integers(info.min, info.max, size=shape, dtype=dt, endpoint=True)
            a.flat[:2] = [info.min, info.max]
        fields[f"v_{dt.name}"] = a
    return fields


def _assert_same(got: PointCloud, fields: dict[str, np.ndarray]) -> None:
    assert list(got.fields) == list(fields)
    for name, want in fields.items():
        assert got[name].dtype == want.dtype, name
        assert got[name].shape == want.shape, name
        np.testing.assert_array_equal(got[name], want, err_msg=name)  # NaN == NaN here
        if want.dtype.kind == "f":
            np.testing.assert_array_equal(np.signbit(got[name]), np.signbit(want))


# ------------------------------------------------------------------------------ round trips


@pytest.mark.parametrize("fmt", FORMATS)
def test_round_trip_all_dtypes_organized(tmp_path: Path, fmt: str) -> None:
    fields = _all_dtypes_cloud()
    cloud = PointCloud.from_fields(fields, viewpoint=[1.5, -2, 3, 0.5, 0.5, 0.5, 0.5])
    path = write_ply(tmp_path / "c.ply", cloud, format=fmt)
    got = read_ply(path)
    assert (got.height, got.width) == (3, 5) and got.is_organized
    _assert_same(got, fields)
    np.testing.assert_array_equal(got.viewpoint, cloud.viewpoint)
    header = path.read_bytes().split(b"end_header")[0].decode()
    assert f"format {fmt} 1.0" in header
    assert "obj_info lidarjax height 3 width 5" in header
    assert "property uchar v_uint8" in header and "property double v_float64" in header


@pytest.mark.parametrize("fmt", FORMATS)
def test_round_trip_unorganized_and_empty(tmp_path: Path, fmt: str) -> None:
    rng = np.random.default_rng(1)
    fields = {"x": rng.normal(size=7).astype(np.float32), "i": np.arange(7, dtype=np.uint16)}
    got = read_ply(write_ply(tmp_path / "u.ply", fields, format=fmt))
    assert (got.height, got.width) == (1, 7) and not got.is_organized
    _assert_same(got, {k: v[None] for k, v in fields.items()})
    np.testing.assert_array_equal(got.viewpoint, [0, 0, 0, 1, 0, 0, 0])
    empty = {"x": np.zeros((0, 4), np.float32), "y": np.zeros((0, 4), np.float64)}
    got = read_ply(write_ply(tmp_path / "e.ply", empty, format=fmt))
    assert (got.height, got.width) == (0, 4)
    _assert_same(got, empty)


def test_default_viewpoint_not_written_and_pointcloud_helpers(tmp_path: Path) -> None:
    xyz = np.arange(12, dtype=np.float32).reshape(2, 2, 3)
    cloud = PointCloud.from_fields({"x": xyz[..., 0], "y": xyz[..., 1], "z": xyz[..., 2]})
    path = write_ply(tmp_path / "p.ply", cloud)
    assert b"viewpoint" not in path.read_bytes().split(b"end_header")[0]
    np.testing.assert_array_equal(read_ply(path).points_xyz, xyz)


def test_write_errors(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="format"):
        write_ply(tmp_path / "a.ply", {"x": np.zeros(2, np.float32)}, format="binary")
    with pytest.raises(ValueError, match="'n'.*COUNT"):
        write_ply(tmp_path / "a.ply", {"n": np.zeros((1, 2, 3), np.float32)})
    with pytest.raises(ValueError, match="'t'.*int64"):
        write_ply(tmp_path / "a.ply", {"t": np.zeros(2, np.int64)})


def test_big_binary_and_ascii_agree(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    n = 20_000
    fields = {
        "x": rng.normal(size=n).astype(np.float32),
        "t": rng.uniform(0, 1e6, size=n),
        "ring": rng.integers(0, 64, size=n).astype(np.uint8),
    }
    a = read_ply(write_ply(tmp_path / "a.ply", fields, format="ascii"))
    b = read_ply(write_ply(tmp_path / "b.ply", fields, format="binary_big_endian"))
    for k in fields:
        np.testing.assert_array_equal(a[k], b[k])
        np.testing.assert_array_equal(a[k][0], fields[k])


# ------------------------------------------------------------------------------ foreign files

_MESH_HEADER = """ply\r
format {fmt} 1.0\r
comment made by another tool\r
obj_info a mesh, not organised\r
element vertex 4\r
property float32 x\r
property float32 y\r
property float32 z\r
property uint8 red\r
property uchar green\r
property uchar blue\r
element face 3\r
property list uchar int vertex_indices\r
property uchar flags\r
element edge 2\r
property int vertex1\r
property int vertex2\r
end_header\r
"""
_VERTS = [
    (0.0, 0.0, 0.0, 255, 0, 0),
    (1.0, 0.0, 0.5, 0, 255, 0),
    (1.0, 1.0, -0.25, 0, 0, 255),
    (0.0, 1.0, 1e-3, 7, 8, 9),
]
_FACES = [([0, 1, 2], 1), ([0, 2, 3], 2), ([0, 1, 2, 3], 3)]  # triangles and a quad
_EDGES = [(0, 1), (2, 3)]


def _foreign_mesh(fmt: str, faces=_FACES) -> bytes:
    header = _MESH_HEADER.format(fmt=fmt).encode()
    if fmt == "ascii":
        lines = [" ".join(str(v) for v in vert) for vert in _VERTS]
        lines += [f"{len(ix)} {' '.join(map(str, ix))} {fl}" for ix, fl in faces]
        lines += [f"{a} {b}" for a, b in _EDGES]
        return header + ("\n".join(lines) + "\n").encode()
    o = "<" if fmt == "binary_little_endian" else ">"
    body = b"".join(struct.pack(o + "fffBBB", *v) for v in _VERTS)
    body += b"".join(struct.pack(f"{o}B{len(ix)}iB", len(ix), *ix, fl) for ix, fl in faces)
    body += b"".join(struct.pack(o + "ii", a, b) for a, b in _EDGES)
    return header + body


def _check_foreign(got: PointCloud) -> None:
    assert (got.height, got.width) == (1, 4)
    assert list(got.fields) == ["x", "y", "z", "red", "green", "blue"]
    want = np.array(_VERTS)
    for j, name in enumerate(got.fields):
        np.testing.assert_array_equal(got[name][0], want[:, j].astype(got[name].dtype))
    assert got["x"].dtype == np.float32 and got["red"].dtype == np.uint8


@pytest.mark.parametrize("fmt", FORMATS)
def test_foreign_mesh_with_faces_edges_comments(tmp_path: Path, fmt: str) -> None:
    path = tmp_path / "mesh.ply"
    path.write_bytes(_foreign_mesh(fmt))
    _check_foreign(read_ply(path))


@pytest.mark.parametrize("fmt", FORMATS)
def test_foreign_uniform_triangles(tmp_path: Path, fmt: str) -> None:
    """All faces triangles: the vectorised skip path."""
    faces = [([0, 1, 2], 1), ([0, 2, 3], 2), ([1, 2, 3], 0)]
    path = tmp_path / "tri.ply"
    path.write_bytes(_foreign_mesh(fmt, faces))
    _check_foreign(read_ply(path))


def test_element_before_vertex_and_blank_lines(tmp_path: Path) -> None:
    text = (
        "ply\nformat ascii 1.0\nelement camera 1\nproperty float f\nproperty list uchar float k\n"
        "element vertex 2\nproperty double x\nproperty char c\nend_header\n"
        "500 2 0.1 -0.2\n\n  1.5 -3\n\t\n-2.5e3 127\n\n"
    )
    path = tmp_path / "cam.ply"
    path.write_text(text)
    got = read_ply(path)
    np.testing.assert_array_equal(got["x"][0], [1.5, -2500.0])
    np.testing.assert_array_equal(got["c"][0], [-3, 127])
    assert got["c"].dtype == np.int8


def test_vertex_between_binary_list_elements(tmp_path: Path) -> None:
    header = (
        b"ply\nformat binary_little_endian 1.0\nelement meta 2\nproperty list ushort short v\n"
        b"element vertex 2\nproperty float x\nelement face 1\n"
        b"property list uint uint vertex_indices\nend_header\n"
    )
    meta = struct.pack("<H3h", 3, 1, 2, 3) + struct.pack("<H", 0)
    vert = struct.pack("<2f", 0.25, -8.0)
    face = struct.pack("<I2I", 2, 0, 1)
    path = tmp_path / "m.ply"
    path.write_bytes(header + meta + vert + face)
    np.testing.assert_array_equal(read_ply(path)["x"][0], np.float32([0.25, -8.0]))


def test_obj_info_grid_and_comment_grid(tmp_path: Path) -> None:
    text = (
        "ply\nformat ascii 1.0\ncomment lidarjax height 2 width 2\nelement vertex 4\n"
        "property float x\nend_header\n1\n2\n3\n4\n"
    )
    path = tmp_path / "g.ply"
    path.write_text(text)
    got = read_ply(path)
    np.testing.assert_array_equal(got["x"], [[1, 2], [3, 4]])


# ------------------------------------------------------------------------------ corruption


def _ascii_file(body: str = "1 2\n3 4\n", header_extra: str = "", props: str | None = None):
    props = "property float x\nproperty uchar c\n" if props is None else props
    return (
        f"ply\nformat ascii 1.0\n{header_extra}element vertex 2\n{props}end_header\n{body}"
    ).encode()


_CORRUPT_HEADERS = {
    "not ply": (b"plx\nformat ascii 1.0\nend_header\n", "not a PLY file"),
    "empty": (b"", "not a PLY file"),
    "no end_header": (b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n", "end_header"),
    "header no newline": (b"ply\nformat ascii 1.0\nend_header", "end_header"),
    "no format": (b"ply\nelement vertex 0\nproperty float x\nend_header\n", "no 'format'"),
    "bad format": (b"ply\nformat binary 1.0\nend_header\n", "bad format"),
    "bad version": (b"ply\nformat ascii 2.0\nend_header\n", "version"),
    "two formats": (b"ply\nformat ascii 1.0\nformat ascii 1.0\nend_header\n", "duplicate 'format'"),
    "unknown keyword": (b"ply\nformat ascii 1.0\nfoo bar\nend_header\n", "unknown header keyword"),
    "blank header line": (b"ply\nformat ascii 1.0\n\nend_header\n", "blank line"),
    "property first": (b"ply\nformat ascii 1.0\nproperty float x\nend_header\n", "before any"),
    "unknown type": (_ascii_file(props="property float16 x\n"), "unknown property type"),
    "bad property": (_ascii_file(props="property float\n"), "bad property line"),
    "float count": (_ascii_file(props="property list float int i\n"), "not an integer"),
    "bad list": (_ascii_file(props="property list uchar i\n"), "bad list property"),
    "dup property": (_ascii_file(props="property float x\nproperty int x\n"), "duplicate property"),
    "bad name": (_ascii_file(props="property float x\xe9\n"), "invalid property name"),
    "bad element": (b"ply\nformat ascii 1.0\nelement vertex -1\nend_header\n", "bad element"),
    "dup element": (
        b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nelement vertex 0\n"
        b"property float x\nend_header\n",
        "duplicate element",
    ),
    "no vertex": (
        b"ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int i\nend_header\n",
        "no 'vertex' element",
    ),
    "vertex without properties": (
        b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n",
        "no properties",
    ),
    "element without properties": (
        b"ply\nformat ascii 1.0\nelement stuff 2\nelement vertex 0\nproperty float x\nend_header\n",
        "no properties",
    ),
    "vertex list": (_ascii_file(props="property list uchar float x\n"), "not supported"),
    "end_header text": (b"ply\nformat ascii 1.0\nend_header now\n", "after 'end_header'"),
    "grid mismatch": (_ascii_file(header_extra="obj_info lidarjax height 3 width 1\n"), "!= 2"),
    "bad grid": (_ascii_file(header_extra="obj_info lidarjax height 2 wide 1\n"), "grid line"),
    "dup grid": (
        _ascii_file(
            header_extra="obj_info lidarjax height 2 width 1\nobj_info lidarjax height 2 width 1\n"
        ),
        "duplicate",
    ),
    "bad viewpoint": (_ascii_file(header_extra="obj_info lidarjax viewpoint 0 0 0 1 0 0\n"), "vi"),
    "nan viewpoint": (
        _ascii_file(header_extra="obj_info lidarjax viewpoint 0 0 nan 1 0 0 0\n"),
        "viewpoint",
    ),
    "huge viewpoint": (
        _ascii_file(header_extra="obj_info lidarjax viewpoint 0 0 1e999 1 0 0 0\n"),
        "overflows",
    ),
}

_CORRUPT_ASCII_BODIES = {
    "too few lines": ("1 2\n", "file ends after 1 of 2"),
    "extra line": ("1 2\n3 4\n5 6\n", "extra data line"),
    "too many values": ("1 2 3\n3 4\n", "record has 3 values"),
    "too few values": ("1 2\n3 4\n5\n", "extra data line"),
    "short and long": ("1\n3 4 5\n", "record has 1 values"),
    "underscore": ("1_0 2\n3 4\n", "is not a number"),
    "nbsp": ("1\xa02\n3 4\n", "is not a number"),
    "word": ("abc 2\n3 4\n", "is not a number"),
    "bad decimal": ("1.2.3 2\n3 4\n", "cannot parse '1.2.3'"),
    "bad exponent": ("1e 2\n3 4\n", "cannot parse '1e'"),
    "float for int": ("1 2.5\n3 4\n", "cannot parse '2.5'"),
    "nan for int": ("1 nan\n3 4\n", "cannot parse 'nan'"),
    "uchar range": ("1 256\n3 4\n", "out of range for uint8"),
    "negative uchar": ("1 2\n3 -1\n", "out of range"),
    "huge int": ("1 2\n3 99999999999999999999999\n", "out of range"),
    "float32 overflow": ("1e39 2\n3 4\n", "out of range for float32"),
    "nul byte": ("1\x00 2\n3 4\n", "is not a number"),
}


@pytest.mark.parametrize("case", sorted(_CORRUPT_HEADERS))
def test_corrupt_headers(tmp_path: Path, case: str) -> None:
    raw, message = _CORRUPT_HEADERS[case]
    path = tmp_path / "bad.ply"
    path.write_bytes(raw)
    with pytest.raises(DatasetFormatError, match=message) as info:
        read_ply(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("case", sorted(_CORRUPT_ASCII_BODIES))
def test_corrupt_ascii_bodies(tmp_path: Path, case: str) -> None:
    body, message = _CORRUPT_ASCII_BODIES[case]
    path = tmp_path / "bad.ply"
    path.write_bytes(_ascii_file("") + body.encode("latin-1"))
    with pytest.raises(DatasetFormatError, match=message) as info:
        read_ply(path)
    assert str(path) in str(info.value)
    assert info.value.line is not None and info.value.line >= 7  # body lines start at line 7


def test_ascii_error_line_numbers(tmp_path: Path) -> None:
    path = tmp_path / "bad.ply"
    path.write_bytes(_ascii_file("1 2\n\n3 x4\n"))
    with pytest.raises(DatasetFormatError) as info:
        read_ply(path)
    assert info.value.line == 9  # header 6 lines, then "1 2", blank, "3 x4"


def test_ascii_float_infinity_literals_are_values(tmp_path: Path) -> None:
    path = tmp_path / "inf.ply"
    path.write_bytes(_ascii_file("inf 2\n-Infinity 4\n"))
    np.testing.assert_array_equal(read_ply(path)["x"][0], [np.inf, -np.inf])


_CORRUPT_FACES = {
    "list too long": ("3 0 1 2 3 1", "list lengths make it"),
    "list too short": ("3 0 1 1", "list lengths make it"),
    "negative length": ("-3 0 1 2 1", "bad list length"),
    "length not integer": ("3.0 0 1 2 1", "bad list length"),
    "bad value": ("3 0 1 x 1", "is not a number"),
    "bad value syntax": ("3 0 1 1e 1", "is not a number"),
}


@pytest.mark.parametrize("case", sorted(_CORRUPT_FACES))
def test_corrupt_ascii_faces(tmp_path: Path, case: str) -> None:
    line, message = _CORRUPT_FACES[case]
    raw = _foreign_mesh("ascii").split(b"\n")
    raw[-5] = line.encode()  # the second face (lines: ..., faces x3, edges x2, "")
    path = tmp_path / "bad.ply"
    path.write_bytes(b"\n".join(raw))
    with pytest.raises(DatasetFormatError, match=message) as info:
        read_ply(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian"])
def test_corrupt_binary(tmp_path: Path, fmt: str) -> None:
    raw = _foreign_mesh(fmt)
    header_len = raw.index(b"end_header\r\n") + len(b"end_header\r\n")
    path = tmp_path / "bad.ply"
    o = "<" if fmt == "binary_little_endian" else ">"
    cases = {
        "truncated vertices": (raw[: header_len + 20], "truncated: element 'vertex'"),
        "truncated faces": (raw[:-20], "truncated inside record 2"),
        "truncated edges": (raw[:-3], "truncated"),
        "trailing bytes": (raw + b"\x00", "trailing data"),
        "no body": (raw[:header_len], "truncated"),
    }
    # A face list length pointing past the end of the file.
    face0 = header_len + 4 * 15
    cases["huge list length"] = (raw[:face0] + b"\xff" + raw[face0 + 1 :], "truncated")
    for name, (data, message) in cases.items():
        path.write_bytes(data)
        with pytest.raises(DatasetFormatError, match=message) as info:
            read_ply(path)
        assert str(path) in str(info.value), name
    # Negative list length with a signed count type.
    header = (
        b"ply\nformat " + fmt.encode() + b" 1.0\nelement vertex 1\nproperty float x\n"
        b"element face 2\nproperty list char int i\nend_header\n"
    )
    body = struct.pack(o + "f", 1.0) + struct.pack(o + "b2i", 2, 0, 0) + struct.pack(o + "b", -1)
    path.write_bytes(header + body)
    with pytest.raises(DatasetFormatError, match="negative list length -1"):
        read_ply(path)


@pytest.mark.parametrize("fmt", FORMATS)
def test_mutation_fuzz_raises_only_format_errors(tmp_path: Path, fmt: str) -> None:
    """Seeded byte mutations of a mesh file: read or DatasetFormatError, nothing else."""
    seed = _foreign_mesh(fmt)
    rng = np.random.default_rng(len(fmt))
    path = tmp_path / "m.ply"
    alphabet = b"0123456789 -+.e\n\r\t\x00\xffnaif_"
    n_read = 0
    for _ in range(150):
        data = bytearray(seed)
        for _ in range(int(rng.integers(1, 4))):
            kind = rng.integers(4)
            at = int(rng.integers(0, max(len(data), 1)))
            byte = alphabet[int(rng.integers(len(alphabet)))]
            if kind == 0:
                data[at] = byte
            elif kind == 1:
                data.insert(at, byte)
            elif kind == 2 and len(data) > 1:
                del data[at]
            else:
                data = data[:at]
        path.write_bytes(bytes(data))
        try:
            got = read_ply(path)
        except DatasetFormatError as err:
            assert str(path) in str(err)
        else:
            n_read += 1
            assert isinstance(got, PointCloud)
    assert n_read > 0


# ------------------------------------------------------------------------------ labelled clouds


@pytest.mark.parametrize("suffix", [".pcd", ".ply", ".PLY"])
@pytest.mark.parametrize("organized", [True, False])
def test_labelled_cloud_round_trip(tmp_path: Path, suffix: str, organized: bool) -> None:
    rng = np.random.default_rng(3)
    points = rng.normal(size=(6, 8, 3))
    points[0, 0] = np.nan  # no return
    labels = rng.integers(0, 20, size=(6, 8))
    labels[1, 1] = 2**32 - 1
    if not organized:
        points, labels = points.reshape(-1, 3), labels.reshape(-1)
    path = write_labelled_cloud(tmp_path / f"seg{suffix}", points, labels)
    got = read_pcd(path) if suffix == ".pcd" else read_ply(path)
    assert list(got.fields) == ["x", "y", "z", "label"]
    assert got["label"].dtype == np.uint32 and got["x"].dtype == np.float32
    shape = labels.shape if organized else (1, labels.size)
    assert (got.height, got.width) == shape
    np.testing.assert_array_equal(got["label"], labels.reshape(shape))
    np.testing.assert_array_equal(got.points_xyz, points.astype(np.float32).reshape(*shape, 3))


def test_labelled_cloud_formats_and_encodings(tmp_path: Path) -> None:
    points = np.zeros((3, 3))
    labels = np.array([0, 1, 2], dtype=np.uint8)
    p = write_labelled_cloud(tmp_path / "a.txt", points, labels, format="ply", encoding="ascii")
    assert b"format ascii 1.0" in p.read_bytes()
    assert b"property uint label" in p.read_bytes()
    np.testing.assert_array_equal(read_ply(p)["label"][0], labels)
    p = write_labelled_cloud(tmp_path / "b.pcd", points, labels, encoding="ascii")
    assert b"FIELDS x y z label" in p.read_bytes() and b"TYPE F F F U" in p.read_bytes()
    np.testing.assert_array_equal(read_pcd(p)["label"][0], labels)
    assert (
        b"DATA binary_compressed"
        in write_labelled_cloud(tmp_path / "c.pcd", points, labels).read_bytes()
    )


def test_labelled_cloud_errors(tmp_path: Path) -> None:
    pts = np.zeros((4, 3))
    with pytest.raises(ValueError, match="suffix"):
        write_labelled_cloud(tmp_path / "a.xyz", pts, np.zeros(4, int))
    with pytest.raises(ValueError, match="format must be"):
        write_labelled_cloud(tmp_path / "a.pcd", pts, np.zeros(4, int), format="las")
    with pytest.raises(ValueError, match="points must have shape"):
        write_labelled_cloud(tmp_path / "a.pcd", np.zeros((4, 2)), np.zeros(4, int))
    with pytest.raises(ValueError, match="labels must have shape"):
        write_labelled_cloud(tmp_path / "a.pcd", pts, np.zeros(5, int))
    with pytest.raises(ValueError, match="labels must be integers"):
        write_labelled_cloud(tmp_path / "a.pcd", pts, np.zeros(4))
    with pytest.raises(ValueError, match=r"seg.labels \+ 1"):
        write_labelled_cloud(tmp_path / "a.pcd", pts, np.array([0, -1, 2, 3]))
    with pytest.raises(ValueError, match="2\\*\\*32"):
        write_labelled_cloud(tmp_path / "a.pcd", pts, np.array([0, 1, 2, 2**32]))
