"""Tests of the SynPEB PCD reader / writer (``lidarjax.datasets._synpeb_io``); the scans
written are generated with :mod:`lidarjax.sim`."""

from __future__ import annotations

import numpy as np
import pytest

from lidarjax.datasets import (
    DatasetFormatError,
    fetch,
    load_synpeb_pcd,
    write_pcd,
    write_synpeb_pcd,
)
from lidarjax.sim import ConvexPolyhedron, SynPEBScene, make_synpeb_scene, simulate_synpeb_scan


@pytest.mark.parametrize("data", ["binary_compressed", "ascii"])
def test_pcd_round_trip(tmp_path, data):
    scan = simulate_synpeb_scan(make_synpeb_scene(seed=2), shape=(15, 20), seed=0)
    path = write_synpeb_pcd(tmp_path / "scan.pcd", scan, data=data)
    points, labels = load_synpeb_pcd(path)
    assert points.shape == (15, 20, 3) and points.dtype == np.float64
    assert labels.dtype == np.int64
    np.testing.assert_array_equal(points, scan.points.astype(np.float32).astype(np.float64))
    np.testing.assert_array_equal(labels, scan.labels)


def test_pcd_round_trip_with_no_returns(tmp_path):
    box = ConvexPolyhedron.box((2.0, -0.5, -0.5), (3.0, 0.5, 0.5), range(1, 7))
    scan = simulate_synpeb_scan(SynPEBScene.from_polyhedra([box]), shape=(10, 10), seed=0)
    points, labels = load_synpeb_pcd(write_synpeb_pcd(tmp_path / "s.pcd", scan))
    np.testing.assert_array_equal(labels, scan.labels)
    assert np.all(np.isnan(points[labels == 0]))


def test_shared_synpeb_crop_has_13_labels():
    points, labels = load_synpeb_pcd(fetch("synpeb-test-100"))
    assert points.shape == (100, 100, 3) and labels.shape == (100, 100)
    assert np.unique(labels).size == 13 and np.all(labels > 0)
    r = np.linalg.norm(points, axis=-1)
    assert 1.9 < r.min() and r.max() < 5.0


def test_load_rejects_unorganized_or_incomplete_clouds(tmp_path):
    xyz = np.zeros((1, 5), dtype=np.float32)
    flat = write_pcd(tmp_path / "flat.pcd", {"x": xyz, "y": xyz, "z": xyz, "intensity": xyz})
    with pytest.raises(DatasetFormatError, match="not organized"):
        load_synpeb_pcd(flat)
    grid = np.zeros((3, 4), dtype=np.float32)
    no_label = write_pcd(tmp_path / "nolabel.pcd", {"x": grid, "y": grid, "z": grid})
    with pytest.raises(DatasetFormatError, match="intensity"):
        load_synpeb_pcd(no_label)
    bad = write_pcd(
        tmp_path / "bad.pcd", {"x": grid, "y": grid, "z": grid, "intensity": grid + 0.5}
    )
    with pytest.raises(DatasetFormatError, match="plane label"):
        load_synpeb_pcd(bad)
