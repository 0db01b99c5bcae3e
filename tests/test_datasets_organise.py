"""Tests for organising spinning-lidar clouds (``lidarjax.datasets._organise``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lidarjax.datasets import (
    OrganisedScan,
    beam_elevations,
    organise_scan,
    read_kitti_velodyne,
    read_ply,
    write_kitti_velodyne,
    write_labelled_cloud,
)
from lidarjax.datasets._organise import _HDL32E_DEG


def room_scan(
    elev: np.ndarray, w: int, *, seed: int = 0, jitter_rad: float = 0.0, drop: float = 0.05
) -> np.ndarray:
    """Simulated organized scan ``[H, W, 3]`` (ring order, column j at azimuth 2 pi j / W)
    from inside a closed box room; ``drop`` of the rays have no return (NaN)."""
    rng = np.random.default_rng(seed)
    az = 2 * np.pi * np.arange(w) / w
    e = elev[:, None] + rng.normal(0.0, jitter_rad, (elev.size, w))
    a = az[None, :] + rng.normal(0.0, jitter_rad, (elev.size, w))
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1)
    lo, hi = np.array([-6.0, -5.0, -1.7]), np.array([8.0, 7.0, 2.5])
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, hi / d, np.where(d < 0, lo / d, np.inf)).min(axis=-1)
    pts = t[..., None] * d
    pts[rng.random(t.shape) < drop] = np.nan
    return pts


# ------------------------------------------------------------------------------ layouts


def test_beam_layouts() -> None:
    for sensor, h, lo, hi in [
        ("hdl64e", 64, -24.8, 2.0),
        ("hdl32e", 32, -30.67, 10.67),
        ("vlp16", 16, -15.0, 15.0),
    ]:
        elev = beam_elevations(sensor)
        assert elev.shape == (h,) and elev.dtype == np.float64
        assert (np.diff(elev) > 0).all()  # ascending: ring 0 lowest
        np.testing.assert_allclose(np.rad2deg(elev[[0, -1]]), [lo, hi], atol=1e-12)
    np.testing.assert_allclose(np.rad2deg(beam_elevations("VLP16")), np.arange(-15, 16, 2))
    np.testing.assert_allclose(np.diff(np.rad2deg(beam_elevations("hdl64e"))), 26.8 / 63)
    copy = beam_elevations("hdl32e")
    copy[0] = 0.0
    assert beam_elevations("hdl32e")[0] != 0.0
    with pytest.raises(ValueError, match="sensor must be one of"):
        beam_elevations("os1-64")


def test_hdl32e_table_agrees_with_the_simulator() -> None:
    from lidarjax.sim import HDL32E_ELEVATIONS_DEG, hdl32e

    np.testing.assert_array_equal(_HDL32E_DEG, HDL32E_ELEVATIONS_DEG)
    np.testing.assert_array_equal(beam_elevations("hdl32e"), hdl32e().elevations_rad)


# ------------------------------------------------------------------------------ organising


def test_kitti_bin_of_a_simulated_scan_organises_back(tmp_path: Path) -> None:
    elev = beam_elevations("hdl64e")
    w = 512
    grid = room_scan(elev, w, jitter_rad=np.deg2rad(0.02))  # [64, 512, 3], ring order
    refl = np.random.default_rng(1).uniform(0, 1, grid.shape[:2]).astype(np.float32)
    ok = np.isfinite(grid).all(axis=-1)
    order = np.random.default_rng(2).permutation(int(ok.sum()))  # a .bin has no order
    flat = np.column_stack([grid[ok], refl[ok]])[order]
    path = tmp_path / "000000.bin"
    write_kitti_velodyne(path, flat)
    scan = read_kitti_velodyne(path)

    out = organise_scan(
        scan[:, :3], elevations_rad=elev, n_columns=w, fields={"intensity": scan[:, 3]}
    )
    assert isinstance(out, OrganisedScan)
    assert (out.n_dropped, out.n_collisions, out.n_invalid) == (0, 0, 0)
    assert out.n_points == scan.shape[0] == out.n_filled
    cloud = out.cloud
    assert (cloud.height, cloud.width) == (64, w)
    assert list(cloud.fields) == ["x", "y", "z", "range", "intensity"]
    np.testing.assert_array_equal(out.row_rings, np.arange(64)[::-1])  # row 0 = top beam
    np.testing.assert_array_equal(out.row_elevations_rad, elev[::-1])
    want = grid.astype(np.float32)[::-1]
    assert cloud["x"].dtype == np.float32
    np.testing.assert_array_equal(cloud.points_xyz, want.astype(np.float64))  # NaN == NaN
    np.testing.assert_array_equal(out.filled, ok[::-1])
    np.testing.assert_array_equal(cloud["intensity"], np.where(ok, refl, np.nan)[::-1])
    np.testing.assert_allclose(
        cloud["range"], np.linalg.norm(want.astype(np.float64), axis=-1), rtol=1e-6
    )

    # The same grid from ring indices (as a Velodyne driver's `ring` field gives them).
    ring_of_point = np.broadcast_to(np.arange(64)[:, None], ok.shape)[ok][order]
    by_ring = organise_scan(scan[:, :3], elevations_rad=elev, n_columns=w, rings=ring_of_point)
    np.testing.assert_array_equal(by_ring.cloud.points_xyz, cloud.points_xyz)
    assert (by_ring.n_dropped, by_ring.n_collisions) == (0, 0)


def test_ppe_runs_on_an_organised_scan(tmp_path: Path) -> None:
    from lidarjax.features import extract_planes

    elev = beam_elevations("vlp16")
    grid = room_scan(elev, 90)
    pts = grid.reshape(-1, 3)
    out = organise_scan(pts[np.isfinite(pts).all(-1)], elevations_rad=elev, n_columns=90)
    seg = extract_planes(out.cloud.points_xyz, min_points=10, refit=False)
    assert seg.labels.shape == (16, 90)
    assert (seg.labels[~out.filled] == -1).all()
    assert seg.n_planes >= 5  # floor, ceiling and walls of the room (some split)
    big = seg.sizes >= 90
    assert big.sum() >= 4
    # Planes of a box room: every big plane's normal is a coordinate axis.
    np.testing.assert_allclose(np.abs(seg.normals[big]).max(axis=1), 1.0, atol=2e-3)
    # ... and the segmentation goes out as a labelled cloud (-1 -> 0: pass labels + 1).
    path = write_labelled_cloud(tmp_path / "seg.ply", out.cloud.points_xyz, seg.labels + 1)
    np.testing.assert_array_equal(read_ply(path)["label"], seg.labels + 1)


def test_collisions_keep_the_nearer_point() -> None:
    elev = np.deg2rad([-10.0, 0.0, 10.0])
    pts = np.array(
        [
            [10.0, 0.0, 0.0],  # row 1 (0 deg), column 0
            [5.0, 0.0, 0.0],  # same cell, nearer: kept
            [7.0, 0.01, 0.0],  # same cell, between
            [5.0, 0.0, 0.0],  # same cell, same range as the kept one: the earlier one wins
            [0.0, 4.0, np.tan(np.deg2rad(10)) * 4],  # row 0 (10 deg), column 1 (90 deg)
        ]
    )
    out = organise_scan(pts, elevations_rad=elev, n_columns=4, fields={"id": np.arange(5)})
    assert (out.n_collisions, out.n_dropped, out.n_invalid) == (3, 0, 0)
    assert out.n_points == 5 and out.n_filled == 2
    ids = out.cloud["id"]
    assert ids.dtype == np.int64
    np.testing.assert_array_equal(ids, [[0, 4, 0, 0], [1, 0, 0, 0], [0, 0, 0, 0]])
    assert out.cloud["range"][1, 0] == 5.0
    np.testing.assert_array_equal(out.filled, ids != 0)
    assert np.isnan(out.cloud["x"][2]).all()
    np.testing.assert_allclose(out.column_azimuths_rad, [0, np.pi / 2, -np.pi, -np.pi / 2])


def test_columns_and_azimuth_offset() -> None:
    w = 8
    step = 2 * np.pi / w
    az = np.array([0.49, 0.51, -0.49, -0.51, 3.99, 4.01]) * step
    r = np.arange(1.0, 7.0)  # point k (1-based) at range k: the lower k wins a shared cell
    pts = np.column_stack([r * np.cos(az), r * np.sin(az), np.zeros(az.size)])
    kw = dict(elevations_rad=np.array([0.0]), n_columns=w, fields={"k": np.arange(1, 7)})
    out = organise_scan(pts, **kw)
    cols = {int(k): j for j, k in enumerate(out.cloud["k"][0]) if k}
    assert cols == {1: 0, 2: 1, 4: 7, 5: 4} and out.n_collisions == 2
    shifted = organise_scan(pts, azimuth_offset_rad=step, **kw)
    cols = {int(k): j for j, k in enumerate(shifted.cloud["k"][0]) if k}
    assert cols == {2: 0, 1: 7, 4: 6, 5: 3} and shifted.n_collisions == 2
    np.testing.assert_allclose(shifted.column_azimuths_rad[[0, 7]], [step, 0.0], atol=1e-15)


def test_dropped_and_invalid_points() -> None:
    elev = np.deg2rad([-2.0, 0.0, 2.0])  # tolerance: 1 deg

    def at(el_deg: float, az: float = 0.0, r: float = 10.0) -> list[float]:
        e = np.deg2rad(el_deg)
        return [r * np.cos(e) * np.cos(az), r * np.cos(e) * np.sin(az), r * np.sin(e)]

    good = [at(0.0, 0.1 * k) for k in range(20)]
    far = [at(5.0), at(-3.5)]  # more than 1 deg from every beam
    invalid = [[np.nan, 0.0, 0.0], [0.0, 0.0, 0.0], [np.inf, 1.0, 1.0]]
    pts = np.array(good + far + invalid)
    out = organise_scan(pts, elevations_rad=elev, n_columns=64)
    assert (out.n_dropped, out.n_invalid, out.n_collisions) == (2, 3, 0)
    assert out.n_filled == 20 and out.n_points == len(pts)
    assert out.cloud["x"].dtype == np.float64
    # Edge of the tolerance above the top beam: 2.99 deg is kept, 3.01 deg dropped.
    edge = np.array([at(2.99), at(3.01, 1.0)])
    out = organise_scan(edge, elevations_rad=elev, n_columns=8, max_dropped_fraction=1.0)
    assert (out.n_filled, out.n_dropped) == (1, 1)
    # Too many dropped: an error naming the remedies; a wider tolerance accepts them.
    with pytest.raises(ValueError, match="2 of 4 valid points.*max_dropped_fraction"):
        organise_scan(np.array(good[:2] + far), elevations_rad=elev, n_columns=64)
    out = organise_scan(
        np.array(good[:2] + far), elevations_rad=elev, n_columns=64, max_elevation_error_rad=0.1
    )
    assert out.n_dropped == 0 and out.n_filled == 4
    out = organise_scan(
        np.array(good[:2] + far), elevations_rad=elev, n_columns=64, max_dropped_fraction=0.5
    )
    assert out.n_dropped == 2
    # A single beam takes every elevation by default.
    out = organise_scan(np.array(far), elevations_rad=[0.0], n_columns=4)
    assert out.n_dropped == 0 and out.n_filled == 1 and out.n_collisions == 1


def test_empty_cloud_and_float32_extra_fields() -> None:
    out = organise_scan(
        np.zeros((0, 3), np.float32),
        elevations_rad=beam_elevations("vlp16"),
        n_columns=10,
        fields={"t": np.zeros(0, np.float32), "ring": np.zeros(0, np.uint16)},
    )
    assert (out.cloud.height, out.cloud.width) == (16, 10)
    assert np.isnan(out.cloud["t"]).all() and (out.cloud["ring"] == 0).all()
    assert out.cloud["ring"].dtype == np.uint16 and out.n_points == 0


def test_argument_errors() -> None:
    elev = beam_elevations("vlp16")
    pts = np.zeros((3, 3))
    with pytest.raises(ValueError, match=r"points must have shape \[n, 3\].*scan\[:, :3\]"):
        organise_scan(np.zeros((3, 4)), elevations_rad=elev, n_columns=4)
    with pytest.raises(ValueError, match="points must be a float"):
        organise_scan(np.zeros((3, 3), int), elevations_rad=elev, n_columns=4)
    with pytest.raises(ValueError, match="elevations_rad must have shape"):
        organise_scan(pts, elevations_rad=[], n_columns=4)
    with pytest.raises(ValueError, match="elevations_rad must be finite"):
        organise_scan(pts, elevations_rad=[0.0, 2.0], n_columns=4)
    with pytest.raises(ValueError, match="elevations_rad must be distinct"):
        organise_scan(pts, elevations_rad=[0.0, 0.1, 0.0], n_columns=4)
    for bad in (0, 2.5, True, "8"):
        with pytest.raises(ValueError, match="n_columns"):
            organise_scan(pts, elevations_rad=elev, n_columns=bad)
    with pytest.raises(ValueError, match="azimuth_offset_rad"):
        organise_scan(pts, elevations_rad=elev, n_columns=4, azimuth_offset_rad=np.nan)
    with pytest.raises(ValueError, match="max_elevation_error_rad"):
        organise_scan(pts, elevations_rad=elev, n_columns=4, max_elevation_error_rad=0.0)
    with pytest.raises(ValueError, match="max_dropped_fraction"):
        organise_scan(pts, elevations_rad=elev, n_columns=4, max_dropped_fraction=1.5)
    with pytest.raises(ValueError, match="must not contain 'range'"):
        organise_scan(pts, elevations_rad=elev, n_columns=4, fields={"range": np.zeros(3)})
    with pytest.raises(ValueError, match=r"fields\['t'\] must have shape \[3\]"):
        organise_scan(pts, elevations_rad=elev, n_columns=4, fields={"t": np.zeros(4)})
    with pytest.raises(ValueError, match="rings must have shape"):
        organise_scan(pts, elevations_rad=elev, n_columns=4, rings=np.zeros(2, int))
    with pytest.raises(ValueError, match="rings must be integers"):
        organise_scan(pts, elevations_rad=elev, n_columns=4, rings=np.zeros(3))
    with pytest.raises(ValueError, match=r"rings must be in \[0, 16\).*16"):
        organise_scan(pts, elevations_rad=elev, n_columns=4, rings=np.array([0, 16, 1]))
    with pytest.raises(ValueError, match="rings must be in.*-1"):
        organise_scan(pts, elevations_rad=elev, n_columns=4, rings=np.array([0, -1, 1]))
