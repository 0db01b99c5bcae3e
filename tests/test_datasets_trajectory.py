"""TUM / KITTI trajectory writers: exact round trips, column order, validation, and evo.

The evo tests run the ``evo_ape`` command line from the venv on files written here and
compare its RMSE with an independent computation (closed-form alignment + lidarjax.metrics).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from lidarjax.datasets import (
    DatasetFormatError,
    fetch,
    load_carmen,
    load_kitti_poses,
    read_tum,
    write_kitti_poses,
    write_tum,
)
from lidarjax.metrics import absolute_trajectory_error, trajectory_errors

EVO_APE = Path(sys.executable).parent / "evo_ape"


# ----------------------------------------------------------------------------------------
# helpers (independent of the module under test)
# ----------------------------------------------------------------------------------------


def _rodrigues(axis_angle: np.ndarray) -> np.ndarray:
    """[n 3] rotation vectors -> [n 3 3] matrices."""
    theta = np.linalg.norm(axis_angle, axis=1)
    k = axis_angle / theta[:, None]
    kx = np.zeros((len(k), 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    kx = kx - np.swapaxes(kx, 1, 2)
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    return np.eye(3) + s * kx + (1 - c) * kx @ kx


def _rot_z(yaw: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.zeros((len(yaw), 3, 3))
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1], out[:, 2, 2] = c, -s, s, c, 1
    return out


def _se3(rot: np.ndarray, t: np.ndarray) -> np.ndarray:
    out = np.zeros((len(rot), 4, 4))
    out[:, :3, :3], out[:, :3, 3], out[:, 3, 3] = rot, t, 1.0
    return out


def _random_se3(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    aa = rng.normal(size=(n, 3))
    aa *= rng.uniform(0.1, np.pi, n)[:, None] / np.linalg.norm(aa, axis=1, keepdims=True)
    return _se3(_rodrigues(aa), rng.normal(0, 5, (n, 3)))


def _align_se2(est_xy_yaw: np.ndarray, gt_xy_yaw: np.ndarray) -> np.ndarray:
    """Least-squares rigid 2-D alignment of the estimate's positions onto the ground truth
    (closed form: the rotation angle is atan2 of the summed cross and dot products)."""
    e = est_xy_yaw[:, :2] - est_xy_yaw[:, :2].mean(0)
    g = gt_xy_yaw[:, :2] - gt_xy_yaw[:, :2].mean(0)
    theta = np.arctan2(np.sum(e[:, 0] * g[:, 1] - e[:, 1] * g[:, 0]), np.sum(e * g))
    c, s = np.cos(theta), np.sin(theta)
    xy = e @ np.array([[c, s], [-s, c]]) + gt_xy_yaw[:, :2].mean(0)
    return np.column_stack([xy, est_xy_yaw[:, 2] + theta])


def _evo_ape(tmp_path: Path, fmt: str, ref: Path, est: Path, *args: str) -> dict:
    res = tmp_path / f"res_{ref.stem}_{est.stem}_{len(args)}.zip"
    env = dict(os.environ, HOME=str(tmp_path), MPLBACKEND="Agg")
    cmd = [str(EVO_APE), fmt, str(ref), str(est), *args, "--save_results", str(res)]
    cmd += ["--no_warnings"]
    proc = subprocess.run(cmd, env=env, cwd=tmp_path, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    with zipfile.ZipFile(res) as z:
        return json.loads(z.read("stats.json"))


def _planar_walk(n: int, step_m: float, seed: int) -> np.ndarray:
    """[n 3] poses moving exactly ``step_m`` per row along their heading."""
    rng = np.random.default_rng(seed)
    yaw = np.cumsum(rng.normal(0, 0.25, n))
    xy = np.cumsum(step_m * np.column_stack([np.cos(yaw), np.sin(yaw)]), axis=0)
    return np.column_stack([xy, yaw])


def _perturb(gt: np.ndarray, seed: int) -> np.ndarray:
    """Noise on every pose, then a rigid offset (0.4 rad, (3, -2) m) of the whole path."""
    rng = np.random.default_rng(seed)
    est = gt + rng.normal(0, [0.05, 0.05, 0.02], gt.shape)
    c, s = np.cos(0.4), np.sin(0.4)
    est[:, :2] = est[:, :2] @ np.array([[c, s], [-s, c]]) + [3.0, -2.0]
    est[:, 2] += 0.4
    return est


# ----------------------------------------------------------------------------------------
# TUM
# ----------------------------------------------------------------------------------------


def test_tum_round_trip_se3_exact(tmp_path):
    m = _random_se3(50, 0)
    q = np.array(jaxlie.SO3.from_matrix(jnp.asarray(m[:, :3, :3])).wxyz)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    poses = np.column_stack([m[:, :3, 3], q])  # tx ty tz qw qx qy qz
    stamps = 1.3e9 + np.cumsum(np.random.default_rng(1).uniform(0.01, 0.2, 50))
    traj = read_tum(write_tum(tmp_path / "a.tum", stamps, poses))
    np.testing.assert_array_equal(traj.stamps_s, stamps)
    np.testing.assert_array_equal(traj.poses[:, :3], poses[:, :3])
    np.testing.assert_allclose(traj.poses[:, 3:], poses[:, 3:], rtol=0, atol=4e-16)
    np.testing.assert_allclose(traj.as_matrices(), m, rtol=0, atol=1e-14)
    se3 = jaxlie.SE3(jnp.asarray(np.roll(traj.poses, 4, axis=1)))  # as documented
    np.testing.assert_allclose(np.asarray(se3.as_matrix()), m, rtol=0, atol=1e-12)


def test_tum_column_order_scalar_last(tmp_path):
    # qw = 0.1 is the only distinctive component: it must come last in the file
    q = np.array([0.1, 0.2, 0.4, np.sqrt(1 - 0.01 - 0.04 - 0.16)])
    write_tum(tmp_path / "a.tum", [5.0], np.array([[1.0, 2.0, 3.0, *q]]))
    line = (tmp_path / "a.tum").read_text().split()
    assert [float(v) for v in line] == [5.0, 1.0, 2.0, 3.0, q[1], q[2], q[3], q[0]]


def test_tum_planar_poses_rotate_about_z(tmp_path):
    gt = _planar_walk(40, 0.3, 2)
    traj = read_tum(write_tum(tmp_path / "p.tum", np.arange(40.0), gt))
    np.testing.assert_allclose(traj.as_matrices()[:, :3, :3], _rot_z(gt[:, 2]), atol=1e-15)
    np.testing.assert_array_equal(traj.poses[:, :2], gt[:, :2])
    assert (traj.poses[:, 2] == 0).all() and (traj.poses[:, 4:6] == 0).all()
    wrapped = np.angle(np.exp(1j * gt[:, 2]))
    np.testing.assert_allclose(traj.xy_yaw(), np.column_stack([gt[:, :2], wrapped]), atol=1e-14)


def test_tum_matrix_and_jaxlie_inputs_agree(tmp_path):
    m = _random_se3(30, 3)
    m[0, :3, :3] = np.diag([1.0, -1.0, -1.0])  # 180 deg: trace -1, the hard case
    m[1, :3, :3] = np.diag([-1.0, -1.0, 1.0])
    stamps = np.arange(30.0)
    a = read_tum(write_tum(tmp_path / "m.tum", stamps, m))
    np.testing.assert_allclose(a.as_matrices(), m, rtol=0, atol=1e-14)
    se3 = jaxlie.SE3.from_matrix(jnp.asarray(m))
    b = read_tum(write_tum(tmp_path / "j.tum", stamps, se3))
    np.testing.assert_allclose(b.as_matrices(), m, rtol=0, atol=1e-12)
    gt = _planar_walk(10, 0.5, 4)
    se2 = jaxlie.SE2.from_xy_theta(*jnp.asarray(gt).T)
    c = read_tum(write_tum(tmp_path / "s.tum", stamps[:10], se2))
    d = read_tum(write_tum(tmp_path / "t.tum", stamps[:10], np.asarray(se2.as_matrix())))
    e = read_tum(write_tum(tmp_path / "u.tum", stamps[:10], gt))
    np.testing.assert_allclose(c.poses, e.poses, atol=1e-14)
    np.testing.assert_allclose(d.poses, e.poses, atol=1e-14)
    with pytest.raises(ValueError, match="must be a batched pose"):
        write_tum(tmp_path / "v.tum", stamps[:3], jaxlie.SE2.from_xy_theta(1.0, 2.0, 0.3))
    with pytest.raises(ValueError, match="must be a batched pose"):
        write_kitti_poses(tmp_path / "v.txt", jaxlie.SE3.identity())


@pytest.mark.parametrize(
    ("poses", "match"),
    [
        (np.zeros((2, 5)), "must have shape"),
        (np.zeros((0, 3)), "at least one pose"),
        (np.array([[0, 0, 0], [np.nan, 0, 0.0]]), r"poses\[1\] holds NaN"),
        (np.array([[0, 0, 0, 1, 0, 0, 0], [0, 0, 0, 1 + 2e-6, 0, 0, 0]]), r"poses\[1\].*norm"),
        (np.array([np.eye(4), np.diag([1, 1, 1.00001, 1])]), r"poses\[1\].*rotation"),
        (np.array([np.eye(4), np.diag([1, 1, -1, 1.0])]), r"poses\[1\].*det"),
        (np.array([np.eye(4), np.eye(4) + np.eye(4, k=-3)]), r"poses\[1\]: last row"),
        (np.array([np.eye(3), np.diag([1, 2, 1.0])]), r"poses\[1\].*rotation"),
    ],
)
def test_writers_reject_bad_poses(tmp_path, poses, match):
    with pytest.raises(ValueError, match=match):
        write_tum(tmp_path / "a.tum", np.arange(float(len(poses))), poses)
    with pytest.raises(ValueError, match=match):
        write_kitti_poses(tmp_path / "a.txt", poses)


def test_write_tum_rejects_bad_stamps(tmp_path):
    poses = np.zeros((4, 3))
    with pytest.raises(ValueError, match=r"stamps_s\[2\] = 1.0 is not after stamps_s\[1\]"):
        write_tum(tmp_path / "a.tum", [0.0, 1.0, 1.0, 2.0], poses)
    with pytest.raises(ValueError, match=r"stamps_s\[3\] = 0.5"):
        write_tum(tmp_path / "a.tum", [0.0, 1.0, 2.0, 0.5], poses)
    with pytest.raises(ValueError, match=r"stamps_s\[0\] = nan is not finite"):
        write_tum(tmp_path / "a.tum", [np.nan, 1.0, 2.0, 3.0], poses)
    with pytest.raises(ValueError, match=r"stamps_s must have shape \(4,\)"):
        write_tum(tmp_path / "a.tum", [0.0, 1.0], poses)


def test_read_tum_comments_and_short_decimals(tmp_path):
    # a line of the TUM RGB-D ground truth (4 decimals: |q| = 1 only to ~1e-4)
    text = (
        "# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n\n"
        "1305031098.6659 1.3563 0.6305 1.6380 0.6132 0.5962 -0.3311 -0.3986\r\n"
        "1305031098.6758 1.3543 0.6306 1.6360 0.6129 0.5966 -0.3316 -0.3980\n"
    )
    (tmp_path / "gt.txt").write_text(text)
    traj = read_tum(tmp_path / "gt.txt")
    raw = np.array([0.6132, 0.5962, -0.3311, -0.3986])
    np.testing.assert_allclose(
        traj.poses[0, 3:], np.r_[raw[3], raw[:3]] / np.linalg.norm(raw), atol=1e-15
    )
    np.testing.assert_array_equal(traj.stamps_s, [1305031098.6659, 1305031098.6758])


@pytest.mark.parametrize(
    ("line2", "match"),
    [
        ("1 0 0 0 0 0 0", "found 7 values, not 8"),
        ("1 0 0 0 0 0 0 1 2", "found 9 values, not 8"),
        ("1 0 0 x 0 0 0 1", "non-numeric"),
        ("1 0 0 1_0 0 0 0 1", "non-numeric"),
        ("1 0 0 nan 0 0 0 1", "NaN or infinite"),
        ("1 0 0 0 0 0 0 1.01", "quaternion norm"),
        ("0 0 0 0 0 0 0 1", "not after the previous one"),
        ("-1 0 0 0 0 0 0 1", "not after the previous one"),
    ],
)
def test_read_tum_rejects_bad_lines(tmp_path, line2, match):
    (tmp_path / "a.tum").write_text("0 0 0 0 0 0 0 1\n" + line2 + "\n")
    with pytest.raises(DatasetFormatError, match=match) as info:
        read_tum(tmp_path / "a.tum")
    assert info.value.line == 2 and info.value.path == str(tmp_path / "a.tum")


def test_read_tum_rejects_empty_file(tmp_path):
    (tmp_path / "a.tum").write_text("# nothing\n\n")
    with pytest.raises(DatasetFormatError, match="no poses"):
        read_tum(tmp_path / "a.tum")


# ----------------------------------------------------------------------------------------
# KITTI
# ----------------------------------------------------------------------------------------


def test_kitti_round_trip_through_load_kitti_poses(tmp_path):
    m = _random_se3(40, 5)
    back = load_kitti_poses(write_kitti_poses(tmp_path / "k.txt", m), as_matrix=True)
    np.testing.assert_allclose(back, m, rtol=0, atol=1e-14)
    gt = _planar_walk(20, 0.5, 6)
    path = write_kitti_poses(tmp_path / "p.txt", gt)
    rows = np.loadtxt(path).reshape(-1, 3, 4)
    np.testing.assert_array_equal(rows[:, :, :3], _rot_z(gt[:, 2]))  # exact cos / sin
    np.testing.assert_array_equal(rows[:, :2, 3], gt[:, :2])
    np.testing.assert_array_equal(rows[:, 2, 3], 0.0)
    q = np.column_stack([np.cos(gt[:, 2] / 2), np.zeros((20, 2)), np.sin(gt[:, 2] / 2)])
    quat_poses = np.column_stack([gt[:, :2], np.zeros(20), q])
    back = load_kitti_poses(write_kitti_poses(tmp_path / "q.txt", quat_poses), as_matrix=True)
    np.testing.assert_allclose(back[:, :3, :3], _rot_z(gt[:, 2]), rtol=0, atol=1e-15)


# ----------------------------------------------------------------------------------------
# evo
# ----------------------------------------------------------------------------------------


def test_evo_ape_tum_matches_lidarjax_metrics(tmp_path):
    """evo's SE(3) Umeyama alignment of planar data is the SE(2) alignment; its ATE RMSE
    matches lidarjax.metrics on the aligned trajectory (rows exactly 0.5 m apart, so the
    metric's evaluation points are the rows)."""
    gt = _planar_walk(300, 0.5, 7)
    est = _perturb(gt, 8)
    stamps = 1000.0 + 0.1 * np.arange(300)
    write_tum(tmp_path / "gt.tum", stamps, gt)
    write_tum(tmp_path / "est.tum", stamps, est)
    stats = _evo_ape(tmp_path, "tum", tmp_path / "gt.tum", tmp_path / "est.tum", "--align")

    aligned = _align_se2(est, gt)
    errors = trajectory_errors(aligned, gt, spacing_m=0.5)
    assert errors.n == 300
    per_pose = np.sqrt(np.mean(np.sum((aligned[:, :2] - gt[:, :2]) ** 2, axis=1)))
    np.testing.assert_allclose(errors.rmse_pos_m, per_pose, rtol=1e-9)
    np.testing.assert_allclose(stats["rmse"], errors.rmse_pos_m, rtol=1e-6)
    np.testing.assert_allclose(stats["max"], errors.max_pos_m, rtol=1e-6)
    assert 0.03 < stats["rmse"] < 0.1  # the noise, not the 0.4 rad / 3.6 m offset
    # lidarjax.metrics' own ATE (SVD alignment) gives evo's numbers too
    ate = absolute_trajectory_error(est, gt)
    np.testing.assert_allclose(ate.rmse_m, stats["rmse"], rtol=1e-6)
    np.testing.assert_allclose(ate.max_m, stats["max"], rtol=1e-6)
    np.testing.assert_allclose(ate.mean_m, stats["mean"], rtol=1e-6)
    np.testing.assert_allclose(ate.median_m, stats["median"], rtol=1e-6)
    np.testing.assert_allclose(ate.aligned[:, :2], aligned[:, :2], atol=1e-9)


def test_evo_ape_kitti_on_intel_poses(tmp_path):
    gt = load_carmen(fetch("intel")).poses  # [910 3], irregular steps
    est = _perturb(gt, 9)
    write_kitti_poses(tmp_path / "gt.txt", gt)
    write_kitti_poses(tmp_path / "est.txt", est)
    stats = _evo_ape(tmp_path, "kitti", tmp_path / "gt.txt", tmp_path / "est.txt", "--align")
    aligned = _align_se2(est, gt)
    dist = np.linalg.norm(aligned[:, :2] - gt[:, :2], axis=1)
    np.testing.assert_allclose(stats["rmse"], np.sqrt(np.mean(dist**2)), rtol=1e-6)
    np.testing.assert_allclose(stats["max"], dist.max(), rtol=1e-6)
    np.testing.assert_allclose(absolute_trajectory_error(est, gt).rmse_m, stats["rmse"], 1e-6)
    # without alignment evo sees the rigid offset
    raw = _evo_ape(tmp_path, "kitti", tmp_path / "gt.txt", tmp_path / "est.txt")
    assert raw["rmse"] > 1.0
    unaligned = absolute_trajectory_error(est, gt, align=False)
    np.testing.assert_allclose(unaligned.rmse_m, raw["rmse"], rtol=1e-6)


def test_evo_reads_our_quaternion_order(tmp_path):
    """Rotation errors seen by evo (``-r angle_deg``) equal the angles of R_gt^T R_est
    computed from the matrices, for quaternion ([n 7]) and matrix ([n 4 4]) inputs."""
    gt = _random_se3(60, 10)
    rng = np.random.default_rng(11)
    aa = rng.normal(size=(60, 3))
    angle = rng.uniform(0.2, 2.5, 60)  # rad, below pi: the angle of the rotation vector
    aa *= (angle / np.linalg.norm(aa, axis=1))[:, None]
    est = _se3(gt[:, :3, :3] @ _rodrigues(aa), gt[:, :3, 3])
    expected = np.sqrt(np.mean(np.degrees(angle) ** 2))
    q_est = np.array(jaxlie.SO3.from_matrix(jnp.asarray(est[:, :3, :3])).wxyz)
    q_est /= np.linalg.norm(q_est, axis=1, keepdims=True)
    stamps = np.arange(60.0)
    write_tum(tmp_path / "gt.tum", stamps, gt)
    write_tum(tmp_path / "est.tum", stamps, np.column_stack([est[:, :3, 3], q_est]))
    stats = _evo_ape(tmp_path, "tum", tmp_path / "gt.tum", tmp_path / "est.tum", "-r", "angle_deg")
    np.testing.assert_allclose(stats["rmse"], expected, rtol=1e-6)


def _independent_tum(text: str) -> np.ndarray | None:
    """A plain float() parser of the same format: [n 8] rows as written, or None."""
    rows = []
    for line in text.split("\n"):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        if len(tokens) != 8:
            return None
        try:
            rows.append([float(t) for t in tokens])
        except ValueError:
            return None
    return np.array(rows) if rows else None


def test_read_tum_mutation_fuzz(tmp_path):
    """A mutant is rejected with DatasetFormatError or read as an independent parser reads
    it (up to the documented quaternion normalisation)."""
    gt = _planar_walk(6, 0.5, 12)
    good = write_tum(tmp_path / "a.tum", np.arange(6.0), gt).read_bytes()
    rng = np.random.default_rng(0)
    alphabet = b"0123456789.-e\n #x"
    n_read = 0
    for _ in range(400):
        data = bytearray(good)
        pos = int(rng.integers(0, len(data)))
        kind = rng.integers(3)
        if kind == 0:
            data[pos] = alphabet[int(rng.integers(len(alphabet)))]
        elif kind == 1:
            del data[pos]
        else:
            data.insert(pos, alphabet[int(rng.integers(len(alphabet)))])
        (tmp_path / "m.tum").write_bytes(bytes(data))
        try:
            ours = read_tum(tmp_path / "m.tum")
        except DatasetFormatError:
            continue
        n_read += 1
        theirs = _independent_tum(bytes(data).decode("latin-1"))
        assert theirs is not None, bytes(data)
        np.testing.assert_array_equal(ours.stamps_s, theirs[:, 0])
        np.testing.assert_array_equal(ours.poses[:, :3], theirs[:, 1:4])
        q = np.column_stack([theirs[:, 7], theirs[:, 4:7]])
        np.testing.assert_allclose(ours.poses[:, 3:], q / np.linalg.norm(q, axis=1)[:, None])
    assert n_read > 50
