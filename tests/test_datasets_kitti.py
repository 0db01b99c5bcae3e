"""Tests of the KITTI pose and timestamp readers (``lidarjax.datasets._kitti``)."""

from __future__ import annotations

import jaxlie
import numpy as np
import pytest

from lidarjax.datasets._errors import DatasetFormatError
from lidarjax.datasets._kitti import load_kitti_poses, load_kitti_times
from lidarjax.datasets._registry import fetch


def _rot_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _pose_line(rot: np.ndarray, t, fmt: str = "{:.6e}") -> str:
    mat = np.concatenate([rot, np.asarray(t, dtype=float)[:, None]], axis=1)
    return " ".join(fmt.format(v) for v in mat.reshape(-1))


def test_sequence_00_poses():
    path = fetch("kitti-00-poses")
    poses = load_kitti_poses(path)
    assert isinstance(poses, jaxlie.SE3)
    assert poses.get_batch_axes() == (4541,)
    mats = np.asarray(poses.as_matrix())
    assert mats.shape == (4541, 4, 4)
    np.testing.assert_allclose(mats[0], np.eye(4), atol=1e-6)
    rot = mats[:, :3, :3]
    np.testing.assert_allclose(
        rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape), atol=1e-9
    )
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-9)
    # Translation of pose 1 (second line of the file), read independently.
    row = [float(v) for v in path.read_text().splitlines()[1].split()]
    np.testing.assert_allclose(
        np.asarray(poses.translation())[1], [row[3], row[7], row[11]], rtol=0, atol=1e-12
    )
    np.testing.assert_allclose(rot[1], np.reshape(row, (3, 4))[:, :3], atol=2e-6)
    # The drive is about 3.7 km long.
    steps = np.linalg.norm(np.diff(mats[:, :3, 3], axis=0), axis=1)
    assert 3500 < steps.sum() < 3900


def test_sequence_00_as_matrix():
    path = fetch("kitti-00-poses")
    mats = load_kitti_poses(path, as_matrix=True)
    assert isinstance(mats, np.ndarray)
    assert mats.shape == (4541, 4, 4) and mats.dtype == np.float64
    np.testing.assert_array_equal(mats[:, 3, :], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (4541, 4)))
    np.testing.assert_allclose(mats, np.asarray(load_kitti_poses(path).as_matrix()), atol=1e-9)


def test_sequence_00_times():
    times = load_kitti_times(fetch("kitti-00-times"))
    assert times.shape == (4541,) and times.dtype == np.float64
    assert times[0] == 0.0
    assert np.all(np.diff(times) > 0)
    assert times[1] == pytest.approx(0.1037359)
    assert 400 < times[-1] < 500  # about 10 Hz


def test_small_file_reorthonormalised(tmp_path):
    rots = [np.eye(3), _rot_y(0.3), _rot_y(-2.0)]
    trans = [[0.0, 0.0, 0.0], [1.5, -0.25, 10.0], [-3.0, 0.5, 20.125]]
    # 4 significant digits: the stored rotations are visibly not orthonormal.
    text = "\n".join(_pose_line(r, t, "{:.3e}") for r, t in zip(rots, trans)) + "\n\n"
    path = tmp_path / "poses.txt"
    path.write_text(text)
    mats = load_kitti_poses(path, as_matrix=True)
    assert mats.shape == (3, 4, 4)
    stored = np.loadtxt(path).reshape(3, 3, 4)
    assert np.abs(stored[:, :, :3] @ stored[:, :, :3].transpose(0, 2, 1) - np.eye(3)).max() > 1e-5
    rot = mats[:, :3, :3]
    np.testing.assert_allclose(
        rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (3, 3, 3)), atol=1e-12
    )
    np.testing.assert_allclose(rot, np.stack(rots), atol=1e-3)
    np.testing.assert_array_equal(mats[:, :3, 3], stored[:, :, 3])
    se3 = load_kitti_poses(path)
    np.testing.assert_allclose(np.asarray(se3.translation()), stored[:, :, 3], atol=1e-12)
    np.testing.assert_allclose(np.asarray(se3.rotation().as_matrix()), rot, atol=1e-9)


@pytest.mark.parametrize(
    ("bad", "fragment"),
    [
        (" ".join(["1"] * 11), "11 values"),
        ("1 0 0 0 0 1 0 0 0 0 1 abc", "non-numeric"),
        ("1 0 0 0 0 1 0 0 0 0 1 nan", "NaN"),
        (" ".join(["0"] * 12), "rotation"),
        ("2 0 0 0 0 2 0 0 0 0 2 0", "rotation"),
        ("-1 0 0 0 0 1 0 0 0 0 1 0", "rotation"),  # reflection
    ],
)
def test_bad_pose_rows(tmp_path, bad, fragment):
    good = _pose_line(np.eye(3), [0, 0, 0])
    path = tmp_path / "poses.txt"
    path.write_text("\n".join([good, "", good, bad, good]) + "\n")
    with pytest.raises(DatasetFormatError) as info:
        load_kitti_poses(path)
    assert info.value.line == 4
    assert f"{path}:4:" in str(info.value)
    assert fragment in str(info.value)


def test_empty_files(tmp_path):
    path = tmp_path / "empty.txt"
    path.write_text("\n\n")
    with pytest.raises(DatasetFormatError):
        load_kitti_poses(path)
    with pytest.raises(DatasetFormatError):
        load_kitti_times(path)


def test_bad_times(tmp_path):
    path = tmp_path / "times.txt"
    path.write_text("0.0\n0.1\n0.2 0.3\n")
    with pytest.raises(DatasetFormatError, match=":3:"):
        load_kitti_times(path)
    path.write_text("0.0\nx\n")
    with pytest.raises(DatasetFormatError, match=":2:"):
        load_kitti_times(path)
    path.write_text("0.0\n0.5\n1.0\n")
    np.testing.assert_array_equal(load_kitti_times(path), [0.0, 0.5, 1.0])


@pytest.mark.parametrize(
    ("bad", "fragment"),
    [
        ("1 0 0 0 0 1 0 0 0 0 1 1_0", "1_0"),
        ("1 0 0 0 0 1 0 0 0 0 1 0x1", "0x1"),
        ("1 0 0 0 0 1 0 0 0 0 1\xa00", "11 values"),  # NBSP does not separate values
        ("1 0 0 0 0 1 0 0 0 0 1 1e999", "NaN or infinite"),
    ],
)
def test_strict_numbers_in_poses(tmp_path, bad, fragment):
    good = _pose_line(np.eye(3), [0, 0, 0])
    path = tmp_path / "poses.txt"
    path.write_bytes("\n".join([good, bad, good]).encode("latin-1"))
    with pytest.raises(DatasetFormatError) as info:
        load_kitti_poses(path)
    assert info.value.line == 2 and f"{path}:2:" in str(info.value)
    assert fragment in str(info.value)


def test_strict_numbers_in_times(tmp_path):
    path = tmp_path / "times.txt"
    for bad in ("0_1", "0.1\r0.2", "\x850.1"):
        path.write_bytes(b"0.0\n" + bad.encode("latin-1") + b"\n0.3\n")
        with pytest.raises(DatasetFormatError, match=":2:"):
            load_kitti_times(path)
