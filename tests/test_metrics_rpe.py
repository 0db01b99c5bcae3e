"""Relative pose error (``lidarjax.metrics.relative_pose_error``): against ``evo_rpe`` on
files written by ``write_tum``, closed forms (a rigidly moved copy has no RPE; a scaled
straight drive has RPE = scale error x pair length), pair selection, and bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from lidarjax.datasets import write_tum
from lidarjax.metrics import relative_pose_error

EVO_RPE = Path(sys.executable).parent / "evo_rpe"


def _walk(n: int, seed: int) -> np.ndarray:
    """[n 3] poses with random step lengths (0.05-0.45 m) and headings."""
    rng = np.random.default_rng(seed)
    yaw = np.cumsum(rng.normal(0, 0.3, n))
    step = rng.uniform(0.05, 0.45, n)[:, None]
    xy = np.cumsum(step * np.column_stack([np.cos(yaw), np.sin(yaw)]), axis=0)
    return np.column_stack([xy, yaw])


def _evo_rpe(tmp_path: Path, ref: Path, est: Path, relation: str) -> dict:
    res = tmp_path / f"rpe_{relation}.zip"
    env = dict(os.environ, HOME=str(tmp_path), MPLBACKEND="Agg")
    cmd = [str(EVO_RPE), "tum", str(ref), str(est), "--delta", "1", "--delta_unit", "m"]
    cmd += ["--pairs_from_reference", "-r", relation, "--save_results", str(res), "--no_warnings"]
    proc = subprocess.run(cmd, env=env, cwd=tmp_path, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    with zipfile.ZipFile(res) as z:
        return json.loads(z.read("stats.json"))


@pytest.mark.skipif(not EVO_RPE.exists(), reason="evo (a dev dependency) is not installed")
def test_rpe_matches_evo_rpe(tmp_path):
    gt = _walk(400, 1)
    rng = np.random.default_rng(2)
    est = gt + np.cumsum(rng.normal(0, [0.01, 0.01, 0.004], gt.shape), axis=0)  # drift
    stamps = 50.0 + 0.1 * np.arange(len(gt))
    write_tum(tmp_path / "gt.tum", stamps, gt)
    write_tum(tmp_path / "est.tum", stamps, est)
    trans = _evo_rpe(tmp_path, tmp_path / "gt.tum", tmp_path / "est.tum", "trans_part")
    angle = _evo_rpe(tmp_path, tmp_path / "gt.tum", tmp_path / "est.tum", "angle_deg")
    rpe = relative_pose_error(est, gt, delta_m=1.0)
    assert rpe.n > 50
    np.testing.assert_allclose(rpe.rmse_m, trans["rmse"], rtol=1e-6)
    np.testing.assert_allclose(rpe.mean_m, trans["mean"], rtol=1e-6)
    np.testing.assert_allclose(rpe.max_m, trans["max"], rtol=1e-6)
    np.testing.assert_allclose(np.rad2deg(rpe.rotation_rmse_rad), angle["rmse"], rtol=1e-6)
    np.testing.assert_allclose(np.rad2deg(rpe.rotation_mean_rad), angle["mean"], rtol=1e-6)


def test_rigidly_moved_copy_has_no_rpe():
    gt = _walk(200, 3)
    c, s = np.cos(0.7), np.sin(0.7)
    est = np.column_stack([gt[:, :2] @ np.array([[c, s], [-s, c]]) + [4.0, -1.0], gt[:, 2] + 0.7])
    rpe = relative_pose_error(est, gt, delta_m=2.0)
    assert rpe.n > 10 and rpe.max_m < 1e-9 and rpe.rotation_rmse_rad < 1e-12


def test_scaled_straight_drive():
    """Along a straight line an odometry scale error s gives |E| = s x pair length."""
    x = np.cumsum(np.full(101, 0.3)) - 0.3  # 0, 0.3, ..., 30 m
    gt = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    est = gt * [1.1, 0.0, 0.0]
    rpe = relative_pose_error(est, gt, delta_m=1.0)
    # from row i the first row >= 1 m on: 4 rows (1.2 m) later
    np.testing.assert_array_equal(rpe.pairs[:3], [[0, 4], [4, 8], [8, 12]])
    np.testing.assert_allclose(rpe.translation_m, 0.1 * 1.2, rtol=1e-9)
    assert rpe.rotation_rmse_rad == 0.0


def test_bad_input():
    gt = _walk(20, 4)
    with pytest.raises(ValueError, match="delta_m"):
        relative_pose_error(gt, gt, delta_m=0.0)
    with pytest.raises(ValueError, match="delta_m"):
        relative_pose_error(gt, gt, delta_m=float("nan"))
    with pytest.raises(ValueError, match="shorter than delta_m"):
        relative_pose_error(gt, gt, delta_m=1e6)
    bad = gt.copy()
    bad[3, 2] = np.nan
    with pytest.raises(ValueError, match="finite"):
        relative_pose_error(bad, gt)
    with pytest.raises(ValueError, match="same shape"):
        relative_pose_error(gt[:5], gt)
