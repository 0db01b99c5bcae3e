"""Tests for the PCD reader/writer and the LZF codec in ``lidarjax.datasets._pcd``."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from lidarjax.datasets._errors import DatasetFormatError
from lidarjax.datasets._pcd import (
    PointCloud,
    _lzf_compress,
    _lzf_decompress,
    _LZFError,
    read_pcd,
    write_pcd,
)

ENCODINGS = ("ascii", "binary", "binary_compressed")


def synpeb_test_100() -> Path:
    """Path of the shared SynPEB sample cloud (ascii, 100 x 100, fields x y z intensity)."""
    shared = Path(__file__).resolve().parents[1].parent / "shared"
    return shared / "data" / "synpeb" / "test_100.pcd"


def make_fields(height: int = 6, width: int = 7, seed: int = 0) -> dict[str, np.ndarray]:
    """Organized float32 x/y/z with NaNs plus extra fields of several dtypes and counts."""
    rng = np.random.default_rng(seed)
    shape = (height, width)
    xyz = {k: (rng.normal(size=shape) * 10).astype(np.float32) for k in "xyz"}
    xyz["x"][0, 1] = np.nan
    xyz["z"][height - 1, :] = np.nan  # a whole row of invalid returns
    return {
        **xyz,
        "label": rng.integers(0, 256, size=shape, dtype=np.uint8),
        "ring": rng.integers(0, 65536, size=shape, dtype=np.uint16),
        "id": rng.integers(-(2**31), 2**31, size=shape, dtype=np.int32),
        "time": rng.uniform(0, 1e9, size=shape) + rng.normal(size=shape) * 1e-7,
        "normal": rng.normal(size=(*shape, 3)).astype(np.float32),
        "big": rng.integers(0, 2**63, size=shape, dtype=np.uint64) * np.uint64(2) + np.uint64(1),
    }


def assert_same_cloud(a: PointCloud, b: PointCloud) -> None:
    assert (a.height, a.width) == (b.height, b.width)
    assert list(a.fields) == list(b.fields)
    for name in a.fields:
        assert a[name].dtype == b[name].dtype, name
        assert a[name].shape == b[name].shape, name
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)  # NaNs compare equal
    np.testing.assert_array_equal(a.viewpoint, b.viewpoint)


# ------------------------------------------------------------------------------------------
# Round trips
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("data", ENCODINGS)
def test_round_trip_organized(tmp_path: Path, data: str) -> None:
    viewpoint = [1.5, -2.25, 0.1, np.cos(0.3), 0.0, 0.0, np.sin(0.3)]
    cloud = PointCloud.from_fields(make_fields(), viewpoint=viewpoint)
    path = write_pcd(tmp_path / f"cloud_{data}.pcd", cloud, data=data)
    assert f"DATA {data}" in path.read_bytes().decode("latin-1")
    back = read_pcd(path)
    assert_same_cloud(cloud, back)
    assert back.is_organized
    assert back["x"].dtype == np.float32 and back["x"].shape == (6, 7)
    assert back["label"].dtype == np.uint8
    assert back["ring"].dtype == np.uint16
    assert back["id"].dtype == np.int32
    assert back["time"].dtype == np.float64
    assert back["normal"].shape == (6, 7, 3)
    assert np.isnan(back["x"][0, 1]) and np.isnan(back["z"][-1]).all()
    xyz = back.points_xyz
    assert xyz.shape == (6, 7, 3) and xyz.dtype == np.float64
    np.testing.assert_array_equal(xyz[..., 1], cloud["y"].astype(np.float64))


@pytest.mark.parametrize("data", ENCODINGS)
def test_round_trip_unorganized_from_dict(tmp_path: Path, data: str) -> None:
    rng = np.random.default_rng(1)
    fields = {
        "x": rng.normal(size=50).astype(np.float32),
        "y": rng.normal(size=50).astype(np.float32),
        "z": np.full(50, -0.0, dtype=np.float32),
        "flag": rng.integers(-128, 128, size=50, dtype=np.int8),
    }
    back = read_pcd(write_pcd(tmp_path / "u.pcd", fields, data=data))
    assert (back.height, back.width) == (1, 50)
    assert not back.is_organized
    for name, value in fields.items():
        np.testing.assert_array_equal(back[name], value[None, :])
        assert back[name].dtype == value.dtype
    np.testing.assert_array_equal(back.viewpoint, [0, 0, 0, 1, 0, 0, 0])


@pytest.mark.parametrize("data", ENCODINGS)
def test_round_trip_empty_cloud(tmp_path: Path, data: str) -> None:
    cloud = PointCloud.from_fields({"x": np.zeros((1, 0), np.float32)})
    back = read_pcd(write_pcd(tmp_path / "empty.pcd", cloud, data=data))
    assert back["x"].shape == (1, 0)


def test_constant_cloud_compresses(tmp_path: Path) -> None:
    fields = {k: np.full((100, 100), 2.5, dtype=np.float32) for k in "xyz"}
    path_c = write_pcd(tmp_path / "c.pcd", fields, data="binary_compressed")
    path_b = write_pcd(tmp_path / "b.pcd", fields, data="binary")
    assert path_c.stat().st_size < 0.1 * path_b.stat().st_size
    np.testing.assert_array_equal(read_pcd(path_c)["y"], fields["y"])


def test_reads_version_variants_comments_and_defaults(tmp_path: Path) -> None:
    text = (
        "# a comment line\n"
        "VERSION .7\n"
        "FIELDS x y _ z\n"  # PCL padding field "_" is dropped
        "SIZE 4 4 1 8\n"
        "TYPE F F U F\n"
        "WIDTH 2  # trailing comment\n"
        "HEIGHT 1\n"
        "POINTS 2\n"
        "DATA ascii\n"
        "1.5 nan 7 -2\n"
        "\n"
        "-0.25 3 0 1e300\n"
    )
    path = tmp_path / "v.pcd"
    path.write_text(text)
    cloud = read_pcd(path)
    assert list(cloud.fields) == ["x", "y", "z"]
    np.testing.assert_array_equal(cloud["x"], np.array([[1.5, -0.25]], np.float32))
    assert np.isnan(cloud["y"][0, 0]) and cloud["y"][0, 1] == 3
    assert cloud["z"].dtype == np.float64 and cloud["z"][0, 1] == 1e300
    np.testing.assert_array_equal(cloud.viewpoint, [0, 0, 0, 1, 0, 0, 0])
    path.write_text(text.replace("VERSION .7", "VERSION 0.7"))
    assert read_pcd(path).width == 2


def test_point_cloud_accessors() -> None:
    cloud = PointCloud.from_fields({"x": np.zeros((2, 3)), "intensity": np.ones((2, 3))})
    assert cloud.num_points == 6 and cloud.is_organized
    np.testing.assert_array_equal(cloud["intensity"], np.ones((2, 3)))
    with pytest.raises(KeyError, match="nope"):
        cloud["nope"]
    with pytest.raises(ValueError, match="'y'"):
        cloud.points_xyz


def test_from_fields_validation() -> None:
    with pytest.raises(ValueError, match="'flag'"):
        PointCloud.from_fields({"x": np.zeros((2, 2)), "flag": np.zeros((2, 2), dtype=bool)})
    with pytest.raises(ValueError, match="'c'"):
        PointCloud.from_fields({"x": np.zeros((2, 2)), "c": np.zeros((2, 2), dtype=np.complex64)})
    with pytest.raises(ValueError, match="'y'"):
        PointCloud.from_fields({"x": np.zeros((2, 2)), "y": np.zeros((2, 3))})
    with pytest.raises(ValueError):
        PointCloud.from_fields({})
    with pytest.raises(ValueError):
        PointCloud.from_fields({"x": np.zeros((2, 2))}, viewpoint=[0, 0, 0])


# ------------------------------------------------------------------------------------------
# The shared SynPEB sample
# ------------------------------------------------------------------------------------------


def test_synpeb_sample() -> None:
    cloud = read_pcd(synpeb_test_100())
    assert cloud.is_organized and (cloud.height, cloud.width) == (100, 100)
    assert list(cloud.fields) == ["x", "y", "z", "intensity"]
    assert cloud["intensity"].dtype == np.float32
    assert np.unique(cloud["intensity"]).size == 13
    np.testing.assert_allclose(cloud.points_xyz[0, 0], [4.302361, -1.651522, 1.495239], atol=1e-6)


# ------------------------------------------------------------------------------------------
# LZF codec
# ------------------------------------------------------------------------------------------


def test_lzf_hand_built_stream() -> None:
    stream = bytes(
        [
            0x02, *b"abc",  # literal run of 3 bytes
            0xC0, 0x02,  # length code 6 -> 8 bytes, offset 2 + 1 = 3 (overlapping copy)
            0xE0, 11, 0x00,  # length 7 + 11 + 2 = 20, offset 1: repeat the last byte
            0x00, *b"Z",  # literal run of 1 byte
            0x20, 31,  # length 1 + 2 = 3 bytes from offset 32: the first three bytes
        ]
    )  # fmt: skip
    expected = b"abc" + b"abcabcab" + b"b" * 20 + b"Z" + b"abc"
    assert _lzf_decompress(stream, len(expected)) == expected


@pytest.mark.parametrize(
    "data",
    [
        b"",
        b"q",
        b"xy",
        np.random.default_rng(2).bytes(20_000),
        b"0123456789" * 3_000,
        bytes(70_000),
        b"ab" * 500 + b"c" * 1000 + b"abc" * 700,
        np.arange(5000, dtype=np.float32).tobytes(),
    ],
    ids=["empty", "one", "two", "random", "period10", "zeros", "mixed-overlap", "float-ramp"],
)
def test_lzf_round_trip(data: bytes) -> None:
    packed = _lzf_compress(data)
    assert _lzf_decompress(packed, len(data)) == data


def test_lzf_compresses_constant_and_uses_overlapping_references() -> None:
    data = bytes([7]) * 100_000
    packed = _lzf_compress(data)
    assert len(packed) < 0.1 * len(data)
    # The only way to encode a run this compactly is with offset-1 (overlapping) references.
    assert _lzf_decompress(packed, len(data)) == data


def test_lzf_errors() -> None:
    data = b"hello hello hello world " * 50
    packed = _lzf_compress(data)
    with pytest.raises(_LZFError):
        _lzf_decompress(packed[:-3], len(data))  # truncated stream
    with pytest.raises(_LZFError):
        _lzf_decompress(packed, len(data) + 1)  # size mismatch
    with pytest.raises(_LZFError):
        _lzf_decompress(packed, len(data) - 1)
    with pytest.raises(_LZFError):
        _lzf_decompress(bytes([0x20, 0x05]), 3)  # reference before start of output
    with pytest.raises(_LZFError):
        _lzf_decompress(bytes([0x05, 1, 2]), 6)  # literal run past end


# ------------------------------------------------------------------------------------------
# Corrupt inputs
# ------------------------------------------------------------------------------------------


def _write(tmp_path: Path, data: str) -> Path:
    ramp = np.arange(20, dtype=np.float32).reshape(4, 5)
    fields = {k: ramp * (i + 1) for i, k in enumerate("xyz")}
    return write_pcd(tmp_path / f"c_{data}.pcd", fields, data=data)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        read_pcd(tmp_path / "nope.pcd")


def test_truncated_binary(tmp_path: Path) -> None:
    path = _write(tmp_path, "binary")
    path.write_bytes(path.read_bytes()[:-5])
    with pytest.raises(DatasetFormatError, match="truncated") as info:
        read_pcd(path)
    assert str(path) in str(info.value)


def test_ascii_line_with_missing_value(tmp_path: Path) -> None:
    path = _write(tmp_path, "ascii")
    lines = path.read_text().split("\n")
    data_index = next(i for i, line in enumerate(lines) if line.startswith("DATA"))
    bad = data_index + 5  # 0-based index of the 5th data line
    lines[bad] = " ".join(lines[bad].split()[:-1])
    path.write_text("\n".join(lines))
    with pytest.raises(DatasetFormatError) as info:
        read_pcd(path)
    assert info.value.line == bad + 1
    assert f"{path}:{bad + 1}:" in str(info.value)


def test_ascii_too_few_lines_and_bad_token(tmp_path: Path) -> None:
    path = _write(tmp_path, "ascii")
    text = path.read_text()
    path.write_text("\n".join(text.split("\n")[:-4]) + "\n")
    with pytest.raises(DatasetFormatError, match="of 20 points") as info:
        read_pcd(path)
    assert str(path) in str(info.value)
    path.write_text(text.replace("\n1 2 3\n", "\n1 2 three\n"))
    with pytest.raises(DatasetFormatError, match="three") as info:
        read_pcd(path)
    assert info.value.line is not None and str(path) in str(info.value)


def test_bad_data_keyword(tmp_path: Path) -> None:
    path = _write(tmp_path, "ascii")
    path.write_text(path.read_text().replace("DATA ascii", "DATA zip"))
    with pytest.raises(DatasetFormatError, match="zip") as info:
        read_pcd(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize(
    ("old", "new", "needle"),
    [
        ("SIZE 4 4 4", "SIZE 4 4", "SIZE"),
        ("TYPE F F F", "TYPE F F X", "TYPE"),
        ("COUNT 1 1 1", "COUNT 1 1", "COUNT"),
        ("POINTS 20", "POINTS 21", "POINTS"),
        ("WIDTH 5\n", "", "WIDTH"),
        ("VERSION 0.7", "VERSION 0.5", "VERSION"),
        ("VIEWPOINT", "VIEWPOINT 1 2 #", "VIEWPOINT"),
    ],
)
def test_malformed_header(tmp_path: Path, old: str, new: str, needle: str) -> None:
    path = _write(tmp_path, "binary")
    raw = path.read_bytes()
    assert old.encode() in raw
    path.write_bytes(raw.replace(old.encode(), new.encode(), 1))
    with pytest.raises(DatasetFormatError, match=needle) as info:
        read_pcd(path)
    assert str(path) in str(info.value)


def test_truncated_lzf_stream(tmp_path: Path) -> None:
    path = _write(tmp_path, "binary_compressed")
    raw = path.read_bytes()
    start = raw.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
    csize, usize = struct.unpack("<II", raw[start : start + 8])
    payload = raw[start + 8 : start + 8 + csize]
    # Cut the file short: the size header no longer matches the payload.
    path.write_bytes(raw[: start + 8 + csize - 4])
    with pytest.raises(DatasetFormatError) as info:
        read_pcd(path)
    assert str(path) in str(info.value)
    # Consistent size header but a truncated stream: the LZF decoder itself must notice.
    short = payload[:-4]
    path.write_bytes(raw[:start] + struct.pack("<II", len(short), usize) + short)
    with pytest.raises(DatasetFormatError, match="LZF") as info:
        read_pcd(path)
    assert str(path) in str(info.value)


# ------------------------------------------------------------------------------------------
# Header/payload size mismatches and header sanity (nothing beyond POINTS is ignored)
# ------------------------------------------------------------------------------------------


def _payload_start(raw: bytes) -> int:
    return raw.index(b"\nDATA") + raw[raw.index(b"\nDATA") + 1 :].index(b"\n") + 2


@pytest.mark.parametrize("data", ["binary", "binary_compressed"])
def test_trailing_byte_rejected(tmp_path: Path, data: str) -> None:
    path = _write(tmp_path, data)
    path.write_bytes(path.read_bytes() + b"\x00")
    with pytest.raises(DatasetFormatError) as info:
        read_pcd(path)
    assert str(path) in str(info.value)


def test_inserted_byte_in_binary_payload_rejected(tmp_path: Path) -> None:
    path = _write(tmp_path, "binary")
    raw = path.read_bytes()
    cut = _payload_start(raw) + 7
    path.write_bytes(raw[:cut] + b"\x01" + raw[cut:])
    with pytest.raises(DatasetFormatError, match="binary data") as info:
        read_pcd(path)
    assert str(path) in str(info.value)


def test_ascii_duplicated_or_extra_line_rejected(tmp_path: Path) -> None:
    path = _write(tmp_path, "ascii")
    lines = path.read_text().split("\n")
    data_index = next(i for i, line in enumerate(lines) if line.startswith("DATA"))
    dup = lines[: data_index + 4] + [lines[data_index + 3]] + lines[data_index + 4 :]
    path.write_text("\n".join(dup))
    with pytest.raises(DatasetFormatError, match="more than POINTS") as info:
        read_pcd(path)
    assert str(path) in str(info.value)
    assert info.value.line == len(lines)  # the first line after the 20 points (1-based)
    path.write_text("\n".join(lines) + "1 2 3\n")
    with pytest.raises(DatasetFormatError, match="more than POINTS"):
        read_pcd(path)
    # Blank lines and trailing whitespace after the points are not data.
    path.write_text("\n".join(lines) + "\n \t\r\n\n")
    assert read_pcd(path).num_points == 20


def test_binary_compressed_size_fields(tmp_path: Path) -> None:
    path = _write(tmp_path, "binary_compressed")
    raw = path.read_bytes()
    start = _payload_start(raw)
    csize, usize = struct.unpack("<II", raw[start : start + 8])
    payload = raw[start + 8 :]
    assert len(payload) == csize
    cases = {
        "compressed size": struct.pack("<II", csize - 1, usize) + payload,  # extra bytes
        "compressed size ": struct.pack("<II", csize + 1, usize) + payload,  # truncated
        "uncompressed size": struct.pack("<II", csize, usize + 4) + payload,
        "LZF": struct.pack("<II", csize + 2, usize) + payload + b"\x00\x00",
    }
    for needle, body in cases.items():
        path.write_bytes(raw[:start] + body)
        with pytest.raises(DatasetFormatError, match=needle.strip()) as info:
            read_pcd(path)
        assert str(path) in str(info.value)


def _binary_file(tmp_path: Path, header: str, payload: bytes = b"") -> Path:
    path = tmp_path / "h.pcd"
    path.write_bytes(header.encode("latin-1") + payload)
    return path


@pytest.mark.parametrize("points", [1, 0])
def test_huge_count_rejected(tmp_path: Path, points: int) -> None:
    header = (
        "VERSION 0.7\nFIELDS x\nSIZE 4\nTYPE F\nCOUNT 3000000000\n"
        f"WIDTH {points}\nHEIGHT 1\nPOINTS {points}\nDATA binary\n"
    )
    path = _binary_file(tmp_path, header, bytes(64))
    with pytest.raises(DatasetFormatError, match="COUNT") as info:
        read_pcd(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize(
    ("old", "new", "needle"),
    [
        ("WIDTH 5\n", "WIDTH 5_0\n", "WIDTH"),
        ("SIZE 4 4 4", "SIZE 4 4 +4", "SIZE"),
        ("COUNT 1 1 1", "COUNT 1 1_0 1", "COUNT"),
        ("VIEWPOINT 0", "VIEWPOINT 0_0", "VIEWPOINT"),
        ("VIEWPOINT 0", "VIEWPOINT nan", "VIEWPOINT"),
        ("FIELDS x y z", "FIELDS x y\xa0z", "FIELDS"),
        ("FIELDS x y z", "FIELDS x y \xffz", "field name"),
        ("DATA binary", "DATA\xa0binary", "DATA"),
    ],
)
def test_strict_header_values(tmp_path: Path, old: str, new: str, needle: str) -> None:
    path = _write(tmp_path, "binary")
    raw = path.read_bytes()
    assert old.encode() in raw
    path.write_bytes(raw.replace(old.encode(), new.encode("latin-1"), 1))
    with pytest.raises(DatasetFormatError, match=needle) as info:
        read_pcd(path)
    assert str(path) in str(info.value)


def test_absurd_dimensions_rejected(tmp_path: Path) -> None:
    header = f"FIELDS x\nSIZE 4\nTYPE F\nWIDTH {10**30}\nHEIGHT 0\nPOINTS 0\nDATA ascii\n"
    path = _binary_file(tmp_path, header)
    with pytest.raises(DatasetFormatError, match="WIDTH") as info:
        read_pcd(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize(
    ("token", "needle"),
    [("1_5", "1_5"), ("1e39", "out of range"), ("1e400", "out of range"), ("0x10", "0x10")],
)
def test_ascii_strict_float_tokens(tmp_path: Path, token: str, needle: str) -> None:
    path = _write(tmp_path, "ascii")
    text = path.read_text()
    path.write_text(text.replace("\n1 2 3\n", f"\n{token} 2 3\n"))
    with pytest.raises(DatasetFormatError, match=needle) as info:
        read_pcd(path)
    assert str(path) in str(info.value) and info.value.line is not None


def test_ascii_integer_and_nonfinite_tokens(tmp_path: Path) -> None:
    header = "FIELDS x n\nSIZE 4 1\nTYPE F U\nWIDTH 3\nHEIGHT 1\nPOINTS 3\nDATA ascii\n"
    path = _binary_file(tmp_path, header + "nan 1\n-inf +2\nInfinity 255\n")
    cloud = read_pcd(path)
    assert np.isnan(cloud["x"][0, 0]) and cloud["x"][0, 1] == -np.inf
    np.testing.assert_array_equal(cloud["n"], [[1, 2, 255]])
    for bad in ("256", "7.0", "1_0", "-1"):
        path = _binary_file(tmp_path, header + f"1 1\n2 {bad}\n3 3\n")
        with pytest.raises(DatasetFormatError, match="'n'") as info:
            read_pcd(path)
        assert info.value.line == 9
