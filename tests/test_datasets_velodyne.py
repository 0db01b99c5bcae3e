"""Tests of the KITTI / NCLT raw lidar readers and writers (``lidarjax.datasets._velodyne``).

Files are written both with the module's writers and independently by hand (``tofile`` /
``struct``), then read back.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest

from lidarjax.datasets._errors import DatasetFormatError
from lidarjax.datasets._velodyne import (
    KittiSequence,
    iter_nclt_velodyne_hits,
    load_kitti_sequence,
    nclt_ground_truth_se2,
    read_kitti_velodyne,
    read_nclt_ground_truth,
    read_nclt_velodyne_hits,
    read_nclt_velodyne_sync,
    write_kitti_velodyne,
    write_nclt_ground_truth,
    write_nclt_velodyne_hits,
    write_nclt_velodyne_sync,
)

# ------------------------------------------------------------------------------------------
# KITTI scans
# ------------------------------------------------------------------------------------------


def _kitti_points(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = np.empty((n, 4), dtype=np.float32)
    pts[:, :3] = rng.uniform(-80, 80, size=(n, 3))
    pts[:, 3] = rng.uniform(0, 1, size=n)
    return pts


def test_kitti_read_hand_written(tmp_path):
    pts = _kitti_points(37)
    path = tmp_path / "000000.bin"
    pts.astype("<f4").tofile(path)
    out = read_kitti_velodyne(path)
    assert out.shape == (37, 4) and out.dtype == np.float32
    np.testing.assert_array_equal(out, pts)


def test_kitti_read_struct_packed(tmp_path):
    rows = [(1.5, -2.25, 0.125, 0.5), (10.0, 20.0, -1.0, 0.0)]
    path = tmp_path / "x.bin"
    path.write_bytes(b"".join(struct.pack("<4f", *r) for r in rows))
    np.testing.assert_array_equal(read_kitti_velodyne(path), np.array(rows, dtype=np.float32))


def test_kitti_write_roundtrip_and_layout(tmp_path):
    pts = _kitti_points(20, seed=1)
    path = tmp_path / "a.bin"
    write_kitti_velodyne(path, pts)
    assert path.stat().st_size == 20 * 16
    np.testing.assert_array_equal(np.fromfile(path, dtype="<f4").reshape(-1, 4), pts)
    np.testing.assert_array_equal(read_kitti_velodyne(path), pts)


def test_kitti_write_xyz_only(tmp_path):
    xyz = np.array([[1.0, 2.0, 3.0], [-4.0, 5.5, 6.25]])
    path = tmp_path / "b.bin"
    write_kitti_velodyne(path, xyz)
    out = read_kitti_velodyne(path)
    np.testing.assert_array_equal(out[:, :3], xyz.astype(np.float32))
    np.testing.assert_array_equal(out[:, 3], 0.0)


def test_kitti_empty_file(tmp_path):
    path = tmp_path / "e.bin"
    path.write_bytes(b"")
    assert read_kitti_velodyne(path).shape == (0, 4)


def test_kitti_truncated(tmp_path):
    path = tmp_path / "t.bin"
    _kitti_points(3).astype("<f4").tofile(path)
    path.write_bytes(path.read_bytes()[:-3])
    with pytest.raises(DatasetFormatError, match="multiple of 16") as info:
        read_kitti_velodyne(path)
    assert str(path) in str(info.value)


def test_kitti_nonfinite(tmp_path):
    pts = _kitti_points(5)
    pts[3, 1] = np.nan
    path = tmp_path / "n.bin"
    pts.astype("<f4").tofile(path)
    with pytest.raises(DatasetFormatError, match="point 3") as info:
        read_kitti_velodyne(path)
    assert str(path) in str(info.value)


def test_kitti_missing_file(tmp_path):
    path = tmp_path / "nope.bin"
    with pytest.raises(FileNotFoundError, match="nope.bin"):
        read_kitti_velodyne(path)


def test_kitti_write_bad_shape(tmp_path):
    with pytest.raises(ValueError, match="shape"):
        write_kitti_velodyne(tmp_path / "x.bin", np.zeros((4, 5)))


# ------------------------------------------------------------------------------------------
# KITTI sequence
# ------------------------------------------------------------------------------------------


def _make_sequence(root, n=3, *, calib=True, times=True, n_poses=None):
    seq = root / "sequences" / "05"
    (seq / "velodyne").mkdir(parents=True)
    (root / "poses").mkdir()
    scans = []
    for k in range(n):
        pts = _kitti_points(10 + k, seed=k)
        pts.astype("<f4").tofile(seq / "velodyne" / f"{k:06d}.bin")
        scans.append(pts)
    n_poses = n if n_poses is None else n_poses
    lines = []
    for k in range(n_poses):
        lines.append(" ".join(str(v) for v in [1, 0, 0, k, 0, 1, 0, 0, 0, 0, 1, 2.0 * k]))
    (root / "poses" / "05.txt").write_text("\n".join(lines) + "\n")
    if times:
        (seq / "times.txt").write_text("".join(f"{0.1 * k:e}\n" for k in range(n)))
    tr = None
    if calib:
        tr = np.array([[0.0, -1.0, 0.0, 0.1], [0.0, 0.0, -1.0, -0.2], [1.0, 0.0, 0.0, -0.3]])
        text = "P0: " + " ".join(["0"] * 12) + "\n"
        text += "Tr: " + " ".join(f"{v:.6e}" for v in tr.reshape(-1)) + "\n"
        (seq / "calib.txt").write_text(text)
    return scans, tr


def test_kitti_sequence(tmp_path):
    scans, tr = _make_sequence(tmp_path, n=3)
    seq = load_kitti_sequence(tmp_path, "05")
    assert isinstance(seq, KittiSequence)
    assert len(seq) == 3
    assert [p.name for p in seq.scan_paths] == ["000000.bin", "000001.bin", "000002.bin"]
    assert seq.poses.shape == (3, 4, 4)
    np.testing.assert_allclose(seq.poses[2, :3, 3], [2.0, 0.0, 4.0])
    np.testing.assert_allclose(seq.times, [0.0, 0.1, 0.2])
    assert seq.has_calibration
    np.testing.assert_allclose(seq.T_cam_velo[:3], tr)
    np.testing.assert_array_equal(seq.T_cam_velo[3], [0, 0, 0, 1])
    np.testing.assert_array_equal(seq.scan(1), scans[1])
    np.testing.assert_array_equal(seq.scan(-1), scans[2])
    np.testing.assert_allclose(seq.velodyne_poses, seq.poses @ seq.T_cam_velo)
    assert load_kitti_sequence(tmp_path, 5).sequence == "05"


def test_kitti_sequence_without_calib_and_times(tmp_path):
    _make_sequence(tmp_path, n=2, calib=False, times=False)
    seq = load_kitti_sequence(tmp_path, "05")
    assert seq.times is None
    assert not seq.has_calibration
    np.testing.assert_array_equal(seq.T_cam_velo, np.eye(4))


def test_kitti_sequence_count_mismatch(tmp_path):
    _make_sequence(tmp_path, n=3, n_poses=2)
    with pytest.raises(DatasetFormatError, match="2 poses but 3 scans"):
        load_kitti_sequence(tmp_path, "05")


def test_kitti_sequence_bad_calib(tmp_path):
    _make_sequence(tmp_path, n=2)
    calib = tmp_path / "sequences" / "05" / "calib.txt"
    calib.write_text("Tr: 1 2 3\n")
    with pytest.raises(DatasetFormatError, match="calib.txt:1"):
        load_kitti_sequence(tmp_path, "05")


def test_kitti_sequence_missing(tmp_path):
    with pytest.raises(FileNotFoundError, match="velodyne"):
        load_kitti_sequence(tmp_path, "07")
    _make_sequence(tmp_path, n=2)
    (tmp_path / "poses" / "05.txt").unlink()
    with pytest.raises(FileNotFoundError, match="05.txt"):
        load_kitti_sequence(tmp_path, "05")


# ------------------------------------------------------------------------------------------
# NCLT velodyne_sync
# ------------------------------------------------------------------------------------------


def _raw_hits(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    raw = rng.integers(0, 65536, size=(n, 3), dtype=np.uint16)
    inten = rng.integers(0, 256, size=n, dtype=np.uint8)
    lid = rng.integers(0, 32, size=n, dtype=np.uint8)
    return raw, inten, lid


def _hits_bytes(raw, inten, lid) -> bytes:
    return b"".join(
        struct.pack("<HHHBB", int(x), int(y), int(z), int(i), int(la))
        for (x, y, z), i, la in zip(raw, inten, lid, strict=True)
    )


def test_nclt_sync_read_struct_packed(tmp_path):
    raw, inten, lid = _raw_hits(25)
    path = tmp_path / "1400000000000000.bin"
    path.write_bytes(_hits_bytes(raw, inten, lid))
    pts, i_out, l_out = read_nclt_velodyne_sync(path)
    assert pts.shape == (25, 3) and pts.dtype == np.float64
    assert i_out.dtype == np.uint8 and l_out.dtype == np.uint8
    # independent conversion, one value at a time in Python floats
    expected = [[v * 0.005 - 100.0 for v in row] for row in raw.tolist()]
    np.testing.assert_array_equal(pts, expected)
    np.testing.assert_array_equal(i_out, inten)
    np.testing.assert_array_equal(l_out, lid)


def test_nclt_sync_known_values(tmp_path):
    path = tmp_path / "k.bin"
    # raw 20000 -> 0 m, raw 0 -> -100 m, raw 20200 -> 1 m
    path.write_bytes(struct.pack("<HHHBB", 20000, 0, 20200, 7, 31))
    pts, inten, lid = read_nclt_velodyne_sync(path)
    np.testing.assert_allclose(pts, [[0.0, -100.0, 1.0]], atol=1e-12)
    assert inten.tolist() == [7] and lid.tolist() == [31]


def test_nclt_sync_tofile_structured(tmp_path):
    raw, inten, lid = _raw_hits(9, seed=3)
    rec = np.zeros(9, dtype=[("xyz", "<u2", (3,)), ("i", "u1"), ("l", "u1")])
    rec["xyz"], rec["i"], rec["l"] = raw, inten, lid
    path = tmp_path / "s.bin"
    rec.tofile(path)
    pts, i_out, l_out = read_nclt_velodyne_sync(path)
    np.testing.assert_array_equal(pts, raw * 0.005 - 100.0)
    np.testing.assert_array_equal(i_out, inten)
    np.testing.assert_array_equal(l_out, lid)


def test_nclt_sync_writer_roundtrip(tmp_path):
    raw, inten, lid = _raw_hits(40, seed=4)
    pts = raw * 0.005 - 100.0
    path = tmp_path / "w.bin"
    write_nclt_velodyne_sync(path, pts, inten, lid)
    assert path.read_bytes() == _hits_bytes(raw, inten, lid)
    p2, i2, l2 = read_nclt_velodyne_sync(path)
    np.testing.assert_array_equal(p2, pts)
    np.testing.assert_array_equal(i2, inten)
    np.testing.assert_array_equal(l2, lid)


def test_nclt_sync_writer_rejects(tmp_path):
    with pytest.raises(ValueError, match="points must lie"):
        write_nclt_velodyne_sync(tmp_path / "x.bin", [[300.0, 0.0, 0.0]], [0], [0])
    with pytest.raises(ValueError, match="intensity"):
        write_nclt_velodyne_sync(tmp_path / "x.bin", [[0.0, 0.0, 0.0]], [256], [0])
    with pytest.raises(ValueError, match="laser_id"):
        write_nclt_velodyne_sync(tmp_path / "x.bin", [[0.0, 0.0, 0.0]], [1], [0, 1])


def test_nclt_sync_truncated_and_missing(tmp_path):
    path = tmp_path / "t.bin"
    path.write_bytes(struct.pack("<HHHBB", 1, 2, 3, 4, 5) + b"\x00\x01\x02")
    with pytest.raises(DatasetFormatError, match="multiple of 8") as info:
        read_nclt_velodyne_sync(path)
    assert str(path) in str(info.value)
    with pytest.raises(FileNotFoundError, match="missing.bin"):
        read_nclt_velodyne_sync(tmp_path / "missing.bin")


# ------------------------------------------------------------------------------------------
# NCLT velodyne_hits
# ------------------------------------------------------------------------------------------


def _packet_bytes(utime: int, raw, inten, lid, magic: int = 44444) -> bytes:
    header = struct.pack("<HHHH", magic, magic, magic, magic)
    header += struct.pack("<I", len(raw)) + struct.pack("<Q", utime) + b"\x00" * 4
    return header + _hits_bytes(raw, inten, lid)


def test_magic_value():
    assert struct.pack("<H", 44444) == b"\x9c\xad"


def test_nclt_hits_read_hand_written(tmp_path):
    packets = [(1326030975726043 + 1000 * k, *_raw_hits(k + 1, seed=k)) for k in range(4)]
    packets.append((1326030975800000, *_raw_hits(0)))  # empty packet
    path = tmp_path / "velodyne_hits.bin"
    path.write_bytes(b"".join(_packet_bytes(*p) for p in packets))
    out = read_nclt_velodyne_hits(path)
    assert len(out) == 5
    for got, (utime, raw, inten, lid) in zip(out, packets, strict=True):
        assert got.utime == utime and isinstance(got.utime, np.int64)
        np.testing.assert_array_equal(got.points, (raw * 0.005 - 100.0).reshape(-1, 3))
        np.testing.assert_array_equal(got.intensity, inten)
        np.testing.assert_array_equal(got.laser_id, lid)
        utime_u, pts_u, int_u, lid_u = got  # unpacks as a 4-tuple
        assert pts_u.shape == (len(raw), 3)
    assert len(read_nclt_velodyne_hits(path, max_packets=2)) == 2
    assert len(list(iter_nclt_velodyne_hits(path, max_packets=0))) == 0


def test_nclt_hits_writer_roundtrip(tmp_path):
    packets = []
    expected_bytes = b""
    for k in range(3):
        raw, inten, lid = _raw_hits(5 + k, seed=10 + k)
        packets.append((1000 + k, raw * 0.005 - 100.0, inten, lid))
        expected_bytes += _packet_bytes(1000 + k, raw, inten, lid)
    path = tmp_path / "h.bin"
    write_nclt_velodyne_hits(path, packets)
    assert path.read_bytes() == expected_bytes
    out = read_nclt_velodyne_hits(path)
    for got, (utime, pts, inten, lid) in zip(out, packets, strict=True):
        assert got.utime == utime
        np.testing.assert_array_equal(got.points, pts)
        np.testing.assert_array_equal(got.intensity, inten)
        np.testing.assert_array_equal(got.laser_id, lid)


def test_nclt_hits_bad_magic_quotes_offset(tmp_path):
    p0 = _packet_bytes(5, *_raw_hits(3))
    p1 = _packet_bytes(6, *_raw_hits(2), magic=44443)
    path = tmp_path / "bad.bin"
    path.write_bytes(p0 + p1)
    offset = len(p0)
    assert offset == 24 + 3 * 8
    with pytest.raises(DatasetFormatError, match=f"byte offset {offset}") as info:
        read_nclt_velodyne_hits(path)
    assert str(path) in str(info.value) and "magic" in str(info.value)
    # the first packet alone is fine
    assert len(read_nclt_velodyne_hits(path, max_packets=1)) == 1


def test_nclt_hits_truncated(tmp_path):
    p0 = _packet_bytes(5, *_raw_hits(3))
    p1 = _packet_bytes(6, *_raw_hits(4))
    path = tmp_path / "trunc.bin"
    path.write_bytes(p0 + p1[:-5])  # hits of packet 1 cut short
    with pytest.raises(DatasetFormatError, match=f"truncated packet at byte offset {len(p0)}"):
        read_nclt_velodyne_hits(path)
    path.write_bytes(p0 + p1[:15])  # header of packet 1 cut short
    with pytest.raises(DatasetFormatError, match=f"header at byte offset {len(p0)}"):
        read_nclt_velodyne_hits(path)
    path.write_bytes(p0 + p1[:5])  # not even the magic
    with pytest.raises(DatasetFormatError, match=f"byte offset {len(p0)}"):
        read_nclt_velodyne_hits(path)


def test_nclt_hits_missing(tmp_path):
    with pytest.raises(FileNotFoundError, match="no_hits.bin"):
        read_nclt_velodyne_hits(tmp_path / "no_hits.bin")


# ------------------------------------------------------------------------------------------
# NCLT ground truth
# ------------------------------------------------------------------------------------------

_GT_TEXT = """\
1357847238890423,nan,nan,nan,nan,nan,nan
1357847238900421,0.5,-1.25,0.1,0.01,-0.02,1.5
1357847238910431,0.75,-1.5,0.125,0.0,0.0,-3.0
"""


def test_nclt_ground_truth_hand_written(tmp_path):
    path = tmp_path / "groundtruth_2013-01-10.csv"
    path.write_text(_GT_TEXT)
    gt = read_nclt_ground_truth(path)
    utime, xyz_rpy, valid = gt
    assert utime.dtype == np.int64
    assert utime.tolist() == [1357847238890423, 1357847238900421, 1357847238910431]
    assert xyz_rpy.shape == (3, 6)
    assert np.isnan(xyz_rpy[0]).all()
    np.testing.assert_array_equal(xyz_rpy[1], [0.5, -1.25, 0.1, 0.01, -0.02, 1.5])
    assert valid.tolist() == [False, True, True]
    assert int((~valid).sum()) == 1


def test_nclt_ground_truth_header_and_writer(tmp_path):
    rng = np.random.default_rng(0)
    utime = np.array([10, 20, 30, 40], dtype=np.int64) + 1357847238890423
    xyz_rpy = rng.normal(size=(4, 6))
    xyz_rpy[2, 3] = np.nan
    path = tmp_path / "gt.csv"
    write_nclt_ground_truth(path, utime, xyz_rpy)
    path.write_text("utime,x,y,z,roll,pitch,yaw\n" + path.read_text())
    gt = read_nclt_ground_truth(path)
    np.testing.assert_array_equal(gt.utime, utime)
    np.testing.assert_array_equal(gt.xyz_rpy, xyz_rpy)  # NaN positions compare equal
    assert gt.valid.tolist() == [True, True, False, True]


def test_nclt_ground_truth_bad_rows(tmp_path):
    path = tmp_path / "gt.csv"
    path.write_text("1,0,0,0,0,0,0\n2,0,0,0,0,0\n")
    with pytest.raises(DatasetFormatError, match="gt.csv:2: found 6 fields"):
        read_nclt_ground_truth(path)
    path.write_text("1,0,0,0,0,0,0\n2,0,0,abc,0,0,0\n")
    with pytest.raises(DatasetFormatError, match="gt.csv:2"):
        read_nclt_ground_truth(path)
    path.write_text("nan,0,0,0,0,0,0\n")
    with pytest.raises(DatasetFormatError, match="gt.csv:1"):
        read_nclt_ground_truth(path)
    path.write_text("\n")
    with pytest.raises(DatasetFormatError, match="no data rows"):
        read_nclt_ground_truth(path)
    with pytest.raises(FileNotFoundError, match="absent.csv"):
        read_nclt_ground_truth(tmp_path / "absent.csv")


def test_nclt_ground_truth_se2():
    xyz_rpy = np.array(
        [
            [1.0, 2.0, -0.5, 0.1, 0.2, 0.3],
            [-3.0, 4.0, 0.0, 0.0, 0.0, -np.pi],
            [np.nan] * 6,
        ]
    )
    se2 = nclt_ground_truth_se2(xyz_rpy)
    np.testing.assert_allclose(se2[0], [1.0, -2.0, -0.3])
    np.testing.assert_allclose(se2[1], [-3.0, -4.0, np.pi])
    assert np.isnan(se2[2]).all()
    # Driving "east" in NCLT (yaw +90 deg, +y) is driving along -y, heading -90 deg, z-up.
    east = nclt_ground_truth_se2(np.array([[0.0, 1.0, 0, 0, 0, np.pi / 2]]))[0]
    np.testing.assert_allclose(east, [0.0, -1.0, -np.pi / 2])
    with pytest.raises(ValueError, match="xyz_rpy"):
        nclt_ground_truth_se2(np.zeros((3, 7)))


# ------------------------------------------------------------------------------------------
# Declared sizes and strict numbers
# ------------------------------------------------------------------------------------------


def test_nclt_hits_huge_num_hits_rejected_before_reading(tmp_path):
    # 24-byte header announcing 2**32 - 1 hits (34 GB), then 16 bytes: a 40-byte file.
    header = struct.pack("<4HIQ4x", 44444, 44444, 44444, 44444, 2**32 - 1, 1326030975726043)
    path = tmp_path / "velodyne_hits.bin"
    path.write_bytes(header + bytes(16))
    with pytest.raises(DatasetFormatError, match="4294967295 hits") as info:
        read_nclt_velodyne_hits(path)
    assert str(path) in str(info.value)
    assert "byte offset 0" in str(info.value)


@pytest.mark.parametrize(
    ("row", "fragment"),
    [
        ("99999999999999999999,0,0,0,0,0,0", "int64"),
        ("1_5,0,0,0,0,0,0", "1_5"),
        ("15,0,0,0_1,0,0,0", "0_1"),
        ("15,0,0,0x1,0,0,0", "0x1"),
        ("15.5,0,0,0,0,0,0", "integer"),
        ("15,0,0,inf,0,0,0", "infinite"),
        ("15,0,0,\xa01,0,0,0", "bad value"),
    ],
)
def test_nclt_ground_truth_strict_values(tmp_path, row, fragment):
    path = tmp_path / "gt.csv"
    path.write_bytes(("utime,x,y,z,roll,pitch,yaw\n1,0,0,0,0,0,0\n" + row + "\n").encode("latin-1"))
    with pytest.raises(DatasetFormatError, match="gt.csv:3") as info:
        read_nclt_ground_truth(path)
    assert fragment in str(info.value)


def test_nclt_ground_truth_one_header_line_only(tmp_path):
    path = tmp_path / "gt.csv"
    path.write_text("utime,x,y,z,roll,pitch,yaw\n" * 2 + "1,0,0,0,0,0,0\n")
    with pytest.raises(DatasetFormatError, match="gt.csv:2"):
        read_nclt_ground_truth(path)
    path.write_text("utime,x,y,z,roll,pitch,yaw\n1.0e3,0,0,0,0,0,0\n")
    assert read_nclt_ground_truth(path).utime.tolist() == [1000]


def test_kitti_calib_strict_numbers(tmp_path):
    _make_sequence(tmp_path, n=2)
    calib = tmp_path / "sequences" / "05" / "calib.txt"
    for bad in ("1_0", "0x1", "nan"):
        calib.write_text("Tr: " + " ".join(["0"] * 11 + [bad]) + "\n")
        with pytest.raises(DatasetFormatError, match="calib.txt:1"):
            load_kitti_sequence(tmp_path, "05")
