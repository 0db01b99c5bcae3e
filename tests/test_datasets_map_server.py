"""ROS map_server maps (YAML + PGM) and .npz grid map files: orientation, round trips,
the occupancy conversions, and every bad input."""

from __future__ import annotations

import zipfile
from types import SimpleNamespace

import jaxlie
import numpy as np
import pytest
import yaml
from PIL import Image

from lidarjax.datasets import (
    GRID_MAP_FORMAT_VERSION,
    DatasetFormatError,
    fetch,
    load_carmen,
    load_grid_map,
    occupancy_from_decay_rate,
    occupancy_from_reflection,
    read_map_server,
    save_grid_map,
    write_map_server,
)
from lidarjax.maps import decay_rate_map, reflection_map
from lidarjax.rays import from_scan
from lidarjax.raytrace import GridSpec, accumulate

ORIGIN, RES, SHAPE = np.array([-1.3, 2.1]), 0.25, (7, 4)  # nx != ny: orientation shows


def _occupancy(seed: int = 0, nan_frac: float = 0.2) -> np.ndarray:
    rng = np.random.default_rng(seed)
    occ = rng.uniform(0, 1, SHAPE)
    occ[rng.uniform(size=SHAPE) < nan_frac] = np.nan
    return occ


def _nav2_value(p: np.ndarray, mode: str, negate: bool, occ_th=0.65, free_th=0.196):
    """nav2_map_server's OccupancyGrid value of 8-bit pixels (map_io.cpp), independently."""
    shade = p.astype(float) / 255.0
    occ = shade if negate else 1.0 - shade
    if mode == "raw":
        v = np.rint(255.0 * (1.0 - occ))
        return np.where(v <= 100, v, -1)
    out = np.where(occ > occ_th, 100, np.where(occ < free_th, 0, -1))
    if mode == "scale":
        mid = (occ <= occ_th) & (occ >= free_th)
        out = np.where(mid, np.rint(100 * (occ - free_th) / (occ_th - free_th)), out)
    return out


# ----------------------------------------------------------------------------------------
# orientation
# ----------------------------------------------------------------------------------------


def test_world_point_lands_on_the_right_pgm_pixel(tmp_path):
    occ = np.zeros(SHAPE)
    point = np.array([0.3, 2.6])  # cell (6, 2): x near the right edge, y in row 2 of 4
    spec = GridSpec(ORIGIN, RES, SHAPE)
    ix, iy = (int(i) for i in spec.cell_of(point))
    assert (ix, iy) == (6, 2)
    occ[ix, iy] = 1.0
    occ[0, 0] = np.nan  # lower-left cell unknown
    write_map_server(tmp_path / "m.yaml", occ, spec=spec)

    meta = yaml.safe_load((tmp_path / "m.yaml").read_text())
    assert meta == {
        "image": "m.pgm",
        "mode": "trinary",
        "resolution": 0.25,
        "origin": [-1.3, 2.1, 0.0],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
    }
    img = np.asarray(Image.open(tmp_path / "m.pgm"))  # an independent PGM reader
    assert img.shape == (4, 7) and img.dtype == np.uint8
    # ROS: column = floor((x - ox) / res), row = height - 1 - floor((y - oy) / res)
    col = int(np.floor((point[0] - meta["origin"][0]) / meta["resolution"]))
    row = img.shape[0] - 1 - int(np.floor((point[1] - meta["origin"][1]) / meta["resolution"]))
    assert (row, col) == (1, 6)
    expected = np.full((4, 7), 254)
    expected[row, col] = 0
    expected[3, 0] = 205  # lower-left = last row, first column
    np.testing.assert_array_equal(img, expected)

    m = read_map_server(tmp_path / "m.yaml")
    assert m.shape == SHAPE and m.pixels.shape == (4, 7)
    np.testing.assert_array_equal(m.pixels, expected)
    np.testing.assert_array_equal(m.occupancy, occ)  # NaN == NaN here
    np.testing.assert_array_equal(m.origin_xy, ORIGIN)
    assert m.resolution == RES and m.origin_yaw == 0.0


# ----------------------------------------------------------------------------------------
# round trips
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("negate", [False, True])
def test_trinary_round_trip_gives_the_classes(tmp_path, negate):
    occ = _occupancy(1)
    occ[1, 1], occ[2, 2], occ[3, 3] = 0.65, 0.196, 0.6500001  # on / just past thresholds
    write_map_server(tmp_path / "m.yaml", occ, origin_xy=ORIGIN, resolution=RES, negate=negate)
    m = read_map_server(tmp_path / "m.yaml")
    want = np.where(occ > 0.65, 1.0, np.where(occ < 0.196, 0.0, np.nan))  # NaN stays NaN
    np.testing.assert_array_equal(m.occupancy, want)
    assert m.negate is negate and m.mode == "trinary"
    ros = _nav2_value(m.pixels[::-1].T, "trinary", negate)
    np.testing.assert_array_equal(m.to_occupancy_grid(), ros)
    np.testing.assert_array_equal(ros, np.where(np.isnan(want), -1, 100 * want))


@pytest.mark.parametrize("negate", [False, True])
def test_scale_round_trip_within_half_a_grey_level(tmp_path, negate):
    occ = _occupancy(2, nan_frac=0.0)
    occ[0, :] = [0.0, 1.0, 0.5, 1 / 510]  # extremes and a tie
    write_map_server(
        tmp_path / "m.yaml", occ, origin_xy=ORIGIN, resolution=RES, mode="scale", negate=negate
    )
    m = read_map_server(tmp_path / "m.yaml")
    assert np.abs(m.occupancy - occ).max() <= 0.5 / 255 + 1e-12
    assert m.occupancy[0, 0] == 0.0 and m.occupancy[0, 1] == 1.0
    ros = _nav2_value(m.pixels[::-1].T, "scale", negate)
    np.testing.assert_array_equal(m.to_occupancy_grid(), ros)


def test_raw_round_trip_within_half_a_percent(tmp_path):
    occ = _occupancy(3)
    write_map_server(tmp_path / "m.yaml", occ, origin_xy=ORIGIN, resolution=RES, mode="raw")
    m = read_map_server(tmp_path / "m.yaml")
    np.testing.assert_array_equal(np.isnan(m.occupancy), np.isnan(occ))
    known = ~np.isnan(occ)
    assert np.abs(m.occupancy[known] - occ[known]).max() <= 0.005 + 1e-12
    np.testing.assert_array_equal(
        m.to_occupancy_grid(), _nav2_value(m.pixels[::-1].T, "raw", False)
    )


def test_trinary_pixels_follow_unusual_thresholds(tmp_path):
    # 205 (occ 0.196) is *occupied* for occupied_thresh 0.19: another unknown value is used
    occ = np.array([[0.0, 0.15], [0.5, np.nan]])
    kw = dict(origin_xy=[0, 0], resolution=1.0, occupied_thresh=0.19, free_thresh=0.18)
    write_map_server(tmp_path / "m.yaml", occ, **kw)
    m = read_map_server(tmp_path / "m.yaml")
    np.testing.assert_array_equal(m.occupancy, [[0.0, 0.0], [1.0, np.nan]])
    grid = m.to_occupancy_grid()
    np.testing.assert_array_equal(grid, _nav2_value(m.pixels[::-1].T, "trinary", False, 0.19, 0.18))
    with pytest.raises(ValueError, match="no 8-bit pixel"):
        write_map_server(
            tmp_path / "m.yaml", occ, origin_xy=[0, 0], resolution=1.0,
            occupied_thresh=0.5001, free_thresh=0.5,
        )  # fmt: skip


def test_reads_ascii_and_16_bit_pgm_and_comments(tmp_path):
    text = "image: a.pgm\nresolution: 0.5\norigin: [1, 2, 0.3]\noccupied_thresh: 0.65\n"
    text += "free_thresh: 0.196\nmode: scale\n"
    (tmp_path / "a.yaml").write_text(text)  # negate omitted: 0
    (tmp_path / "a.pgm").write_bytes(b"P2\n# comment\n3 2 # width height\n4\n0 1 2\n3 4 4\n")
    m = read_map_server(tmp_path / "a.yaml")
    np.testing.assert_allclose(m.occupancy, 1 - np.array([[0, 1, 2], [3, 4, 4]])[::-1].T / 4)
    assert m.origin_yaw == 0.3 and m.maxval == 4 and not m.negate
    (tmp_path / "a.pgm").write_bytes(b"P5 2 1 1000\n" + np.array([0, 1000], ">u2").tobytes())
    m = read_map_server(tmp_path / "a.yaml")
    np.testing.assert_array_equal(m.occupancy, [[1.0], [0.0]])
    assert m.pixels.dtype == np.uint16


# ----------------------------------------------------------------------------------------
# occupancy from lidarjax maps
# ----------------------------------------------------------------------------------------


def test_occupancy_from_decay_rate_and_reflection_formulas():
    lam = np.array([[0.0, 1.0], [10.0, np.inf]])
    seen = np.array([[True, True], [True, False]])
    occ = occupancy_from_decay_rate(lam, 0.1, seen)
    np.testing.assert_allclose(occ[:, 0], [0.0, 1 - np.exp(-1.0)], rtol=1e-15)
    np.testing.assert_allclose(occ[0, 1], 1 - np.exp(-0.1), rtol=1e-15)
    assert np.isnan(occ[1, 1])
    assert occupancy_from_decay_rate([np.inf], spec=SimpleNamespace(resolution=0.1))[0] == 1.0
    p = np.array([[0.2, 0.9], [0.0, 1.0]])
    np.testing.assert_array_equal(occupancy_from_reflection(p, np.ones_like(seen)), p)
    np.testing.assert_array_equal(occupancy_from_reflection(p), p)
    np.testing.assert_array_equal(occupancy_from_reflection(p, seen), [[0.2, 0.9], [0, np.nan]])


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: occupancy_from_decay_rate([-1.0], 0.1), "rates_per_m must be >= 0"),
        (lambda: occupancy_from_decay_rate([np.nan], 0.1), "rates_per_m must be >= 0"),
        (lambda: occupancy_from_decay_rate([1.0], 0.0), "resolution must be a positive"),
        (lambda: occupancy_from_decay_rate([1.0]), "give resolution"),
        (
            lambda: occupancy_from_decay_rate([1.0], 0.1, spec=SimpleNamespace(resolution=1)),
            "either spec or resolution",
        ),
        (lambda: occupancy_from_decay_rate([1.0], spec=object()), "spec must have a resolution"),
        (lambda: occupancy_from_decay_rate([1.0], 0.1, [1]), "observed_mask must be a bool"),
        (lambda: occupancy_from_reflection([1.5]), r"p_ref must lie in \[0, 1\]"),
        (lambda: occupancy_from_reflection([np.nan]), r"p_ref must lie in \[0, 1\]"),
        (lambda: occupancy_from_reflection([0.5], [True, False]), "observed_mask must be"),
    ],
)
def test_occupancy_conversions_reject_bad_input(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_intel_maps_to_map_server_end_to_end(tmp_path):
    log = load_carmen(fetch("intel"))
    sel = slice(0, 40, 4)
    T = jaxlie.SE2.from_xy_theta(*log.poses[sel].T)
    rays = from_scan(T, log.azimuths_rad, log.ranges_m[sel], 0.0, log.usable_range_m)
    spec = GridSpec.covering(log.poses[sel, :2], 0.2, margin=10.0)
    stats = accumulate(spec, rays)
    lam = decay_rate_map(stats)
    occ = occupancy_from_decay_rate(lam.rates, spec=spec, observed_mask=stats.lengths > 0)
    write_map_server(tmp_path / "intel.yaml", occ, spec=spec, mode="trinary")
    m = read_map_server(tmp_path / "intel.yaml")
    assert m.shape == spec.shape
    np.testing.assert_allclose(m.origin_xy, np.asarray(spec.origin), rtol=0, atol=0)
    want = np.where(occ > 0.65, 1.0, np.where(occ < 0.196, 0.0, np.nan))
    np.testing.assert_array_equal(m.occupancy, want)
    assert np.nansum(m.occupancy) > 50 and (m.occupancy == 0).sum() > 1000
    # the reflection map's walls are where the decay-rate map's are
    ref = occupancy_from_reflection(
        reflection_map(stats).probs, np.asarray(stats.hits + stats.misses) > 0
    )
    write_map_server(tmp_path / "ref.yaml", ref, spec=spec)
    both = (read_map_server(tmp_path / "ref.yaml").occupancy == 1) & (m.occupancy == 1)
    assert both.sum() > 0.5 * (m.occupancy == 1).sum()


# ----------------------------------------------------------------------------------------
# write: bad input
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("occ", "kwargs", "match"),
    [
        (np.zeros((2, 2, 2)), {}, r"occupancy must be a non-empty \[nx ny\]"),
        (np.zeros((0, 2)), {}, "occupancy must be a non-empty"),
        (np.full((2, 2), 1.5), {}, r"occupancy must lie in \[0, 1\]"),
        (np.full((2, 2), -np.inf), {}, r"occupancy must lie in \[0, 1\]"),
        (np.full((2, 2), np.nan), {"mode": "scale"}, "mode='scale' cannot mark unknown"),
        (np.zeros((2, 2)), {"mode": "png"}, "mode must be one of"),
        (np.zeros((2, 2)), {"occupied_thresh": 1.0}, "occupied_thresh must be a number"),
        (np.zeros((2, 2)), {"free_thresh": 0.0}, "free_thresh must be a number"),
        (np.zeros((2, 2)), {"free_thresh": 0.7}, "free_thresh .* must be below"),
        (np.zeros((2, 2)), {"negate": 1}, "negate must be a bool"),
        (np.zeros((2, 2)), {"resolution": 0.0}, "resolution must be a positive"),
        (np.zeros((2, 2)), {"origin_xy": [0, 0, 0]}, r"origin_xy must have shape \(2,\)"),
        (np.zeros((2, 2)), {"origin_xy": [0, np.nan]}, "origin_xy must be a finite"),
        (np.zeros((2, 2)), {"origin_xy": None}, "give origin_xy and resolution"),
        (np.zeros((2, 2)), {"spec": GridSpec([0, 0], 1.0, (2, 2))}, "either spec or"),
        (np.zeros((2, 2)), {"spec": object(), "origin_xy": None, "resolution": None}, "spec must"),
        (
            np.zeros((2, 3)),
            {"spec": GridSpec([0, 0], 1.0, (3, 2)), "origin_xy": None, "resolution": None},
            r"spec.shape \(3, 2\) does not match occupancy.shape \(2, 3\)",
        ),
    ],
)
def test_write_map_server_rejects_bad_input(tmp_path, occ, kwargs, match):
    kw = {"origin_xy": [0.0, 0.0], "resolution": 0.1, **kwargs}
    with pytest.raises(ValueError, match=match):
        write_map_server(tmp_path / "m.yaml", occ, **kw)


def test_write_map_server_refuses_a_pgm_path(tmp_path):
    with pytest.raises(ValueError, match="path_yaml must be the YAML file"):
        write_map_server(tmp_path / "m.pgm", np.zeros((2, 2)), origin_xy=[0, 0], resolution=1.0)


# ----------------------------------------------------------------------------------------
# read: bad files
# ----------------------------------------------------------------------------------------

_GOOD_YAML = {
    "image": "m.pgm",
    "resolution": 0.1,
    "origin": [0.0, 0.0, 0.0],
    "negate": 0,
    "occupied_thresh": 0.65,
    "free_thresh": 0.196,
}


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"image": None}, "missing keys"),
        ({"resolution": None}, "missing keys"),
        ({"origin": None}, "missing keys"),
        ({"occupied_thresh": None}, "missing keys"),
        ({"free_thresh": None}, "missing keys"),
        ({"image": 3}, "image must be a file name"),
        ({"resolution": 0}, "resolution must lie in"),
        ({"resolution": "0.1"}, "resolution must be a finite number"),
        ({"resolution": True}, "resolution must be a finite number"),
        ({"origin": [0, 0]}, "origin must be 3 finite numbers"),
        ({"origin": [0, 0, float("inf")]}, "origin must be 3 finite numbers"),
        ({"occupied_thresh": 1.5}, r"occupied_thresh must lie in \[0.0, 1.0\]"),
        ({"free_thresh": 0.9}, "free_thresh 0.9 must be below"),
        ({"negate": 2}, "negate must be 0 or 1"),
        ({"negate": 0.5}, "negate must be 0 or 1"),
        ({"mode": "trinary2"}, "mode must be one of"),
    ],
)
def test_read_map_server_rejects_bad_yaml_values(tmp_path, change, match):
    doc = {**_GOOD_YAML, **change}
    doc = {k: v for k, v in doc.items() if v is not None}
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(doc))
    write_map_server(tmp_path / "ok.yaml", np.zeros((2, 2)), origin_xy=[0, 0], resolution=1.0)
    (tmp_path / "ok.pgm").rename(tmp_path / "m.pgm")
    with pytest.raises(DatasetFormatError, match=match) as info:
        read_map_server(tmp_path / "m.yaml")
    assert str(tmp_path / "m.yaml") in str(info.value)


def test_read_map_server_rejects_bad_yaml_syntax(tmp_path):
    (tmp_path / "m.yaml").write_text("image: m.pgm\norigin: [0, 0\nresolution: 0.1\n")
    with pytest.raises(DatasetFormatError, match="not valid YAML") as info:
        read_map_server(tmp_path / "m.yaml")
    assert info.value.line is not None and info.value.path == str(tmp_path / "m.yaml")
    (tmp_path / "m.yaml").write_text("- a\n- b\n")
    with pytest.raises(DatasetFormatError, match="top level must be a mapping"):
        read_map_server(tmp_path / "m.yaml")
    (tmp_path / "m.yaml").write_text("!!python/object:os.system {}\n")  # not for safe_load
    with pytest.raises(DatasetFormatError, match="not valid YAML"):
        read_map_server(tmp_path / "m.yaml")


@pytest.mark.parametrize(
    ("image", "match"),
    [
        (b"\x89PNG\r\n\x1a\n", "not a PGM image"),
        (b"P6\n2 2\n255\n" + bytes(12), "not a PGM image"),
        (b"P5\n2 2\n255\n" + bytes(3), "raster holds 3 bytes"),
        (b"P5\n2 2\n255\n" + bytes(5), "raster holds 5 bytes"),
        (b"P5\n2 2\n", "truncated or malformed header"),
        (b"P5\n2 x\n255\n" + bytes(4), "truncated or malformed header"),
        (b"P5\n0 2\n255\n", "bad size"),
        (b"P5\n2 2\n0\n" + bytes(4), "bad size"),
        (b"P5\n2 2\n255", "header must end with one whitespace"),
        (b"P2\n2 2\n255\n1 2 3\n", "ASCII raster must hold 4"),
        (b"P2\n2 2\n255\n1 2 3 -4\n", "ASCII raster must hold 4"),
        (b"P2\n2 2\n9\n1 2 3 10\n", "pixel value 10 exceeds maxval 9"),
        (b"", "not a PGM image"),
    ],
)
def test_read_map_server_rejects_bad_images(tmp_path, image, match):
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(_GOOD_YAML))
    (tmp_path / "m.pgm").write_bytes(image)
    with pytest.raises(DatasetFormatError, match=match) as info:
        read_map_server(tmp_path / "m.yaml")
    assert info.value.path == str(tmp_path / "m.pgm")


def test_read_map_server_missing_files(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_map_server(tmp_path / "none.yaml")
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(_GOOD_YAML))
    with pytest.raises(FileNotFoundError):
        read_map_server(tmp_path / "m.yaml")


def test_pgm_mutation_fuzz(tmp_path):
    """Every mutant of a written PGM is rejected with DatasetFormatError or read as PIL
    reads it."""
    write_map_server(tmp_path / "m.yaml", _occupancy(4), origin_xy=ORIGIN, resolution=RES)
    good = (tmp_path / "m.pgm").read_bytes()
    rng = np.random.default_rng(0)
    for _ in range(400):
        data = bytearray(good)
        pos = int(rng.integers(0, len(data)))
        kind = rng.integers(3)
        if kind == 0:
            data[pos] = int(rng.integers(256))
        elif kind == 1:
            del data[pos]
        else:
            data.insert(pos, int(rng.integers(256)))
        (tmp_path / "m.pgm").write_bytes(bytes(data))
        try:
            m = read_map_server(tmp_path / "m.yaml")
        except DatasetFormatError:
            continue
        img = np.asarray(Image.open(tmp_path / "m.pgm"))  # PIL rescales to maxval 255
        assert img.shape == m.pixels.shape and m.pixels.max() <= m.maxval
        if m.maxval == 255:
            np.testing.assert_array_equal(m.pixels, img)


# ----------------------------------------------------------------------------------------
# .npz grid maps
# ----------------------------------------------------------------------------------------


def test_grid_map_round_trip_2d_and_3d(tmp_path):
    rng = np.random.default_rng(5)
    arrays = {
        "rates": rng.uniform(0, 3, SHAPE),
        "hits": rng.integers(0, 9, SHAPE).astype(np.int32),
        "seen": rng.uniform(size=SHAPE) < 0.5,
        "grad": rng.normal(size=(*SHAPE, 2)),
        "outside_rate": np.float64(0.25),
    }
    meta = {"source": "intel", "scans": [0, 4, 8], "unit": "1/m"}
    path = save_grid_map(
        tmp_path / "m", arrays, origin=ORIGIN, resolution=RES, model="decay_rate", meta=meta
    )
    assert path == tmp_path / "m.npz"
    f = load_grid_map(path)
    assert f.model == "decay_rate" and f.meta == meta and f.shape == SHAPE
    assert f.format_version == GRID_MAP_FORMAT_VERSION and f.resolution == RES
    np.testing.assert_array_equal(f.origin, ORIGIN)
    assert f.arrays.keys() == arrays.keys()
    for k, v in arrays.items():
        np.testing.assert_array_equal(f.arrays[k], v)
        assert f.arrays[k].dtype == np.asarray(v).dtype
    spec = GridSpec([0.0, 1.0, -2.0], 0.5, (2, 3, 4))
    f3 = load_grid_map(
        save_grid_map(tmp_path / "c.npz", {"probs": np.full((2, 3, 4), 0.3)}, spec=spec, model="r")
    )
    assert f3.shape == (2, 3, 4) and f3.meta == {}
    np.testing.assert_array_equal(f3.origin, [0.0, 1.0, -2.0])
    # the duck-typed spec alone fixes the shape of scalar-only maps too
    duck = SimpleNamespace(origin=np.zeros(2), resolution=1.0, shape=(3, 3))
    assert load_grid_map(save_grid_map(tmp_path / "s", {"a": 1.0}, spec=duck, model="x")).shape == (
        3,
        3,
    )


@pytest.mark.parametrize(
    ("arrays", "kwargs", "match"),
    [
        ({}, {}, "arrays must be a non-empty dict"),
        ({"a": 1.0}, {}, "only scalars"),
        ({"a": np.zeros((3, 4)), "b": np.zeros((3, 5))}, {}, r"arrays\['b'\] has shape"),
        ({"a": np.zeros(3)}, {}, "fewer than 2 grid axes"),
        ({"__format__": np.zeros((3, 4))}, {}, "bad name"),
        ({"a b": np.zeros((3, 4))}, {}, "bad name"),
        ({"a": np.array(["x"])}, {}, "must be numeric or bool"),
        ({"a": np.zeros((3, 4), dtype=object)}, {}, "must be numeric or bool"),
        ({"a": np.zeros((3, 4))}, {"model": ""}, "model must be a non-empty string"),
        ({"a": np.zeros((3, 4))}, {"meta": {"x": object()}}, "meta must be JSON"),
        ({"a": np.zeros((3, 4))}, {"meta": {"x": float("nan")}}, "meta must be JSON"),
        ({"a": np.zeros((3, 4))}, {"meta": [1]}, "meta must be a dict"),
        ({"a": np.zeros((3, 4))}, {"origin": [0.0]}, "origin must have 2 or 3 entries"),
        ({"a": np.zeros((3, 4))}, {"resolution": -1.0}, "resolution must be a positive"),
        ({"a": np.zeros((3, 4))}, {"spec": GridSpec([0, 0], 1.0, (3, 4))}, "either spec"),
        (
            {"a": np.zeros((3, 4))},
            {"spec": GridSpec([0, 0], 1.0, (4, 3)), "origin": None, "resolution": None},
            r"grid shape \(4, 3\)",
        ),
    ],
)
def test_save_grid_map_rejects_bad_input(tmp_path, arrays, kwargs, match):
    kw = {"origin": [0.0, 0.0], "resolution": 0.1, "model": "m", **kwargs}
    with pytest.raises(ValueError, match=match):
        save_grid_map(tmp_path / "m.npz", arrays, **kw)


def _raw_npz(tmp_path, **changes):
    good = {
        "__format__": np.int64(1),
        "__origin__": np.zeros(2),
        "__resolution__": np.float64(0.1),
        "__shape__": np.array([3, 4]),
        "__model__": np.str_("m"),
        "__meta__": np.str_("{}"),
        "array/a": np.zeros((3, 4)),
    }
    good.update(changes)
    data = {k: v for k, v in good.items() if v is not None}
    np.savez(tmp_path / "m.npz", **data)
    return tmp_path / "m.npz"


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"__format__": np.int64(GRID_MAP_FORMAT_VERSION + 1)}, "newer than this lidarjax"),
        ({"__format__": np.int64(0)}, "bad format version"),
        ({"__format__": np.float64(1)}, "__format__ must be a scalar"),
        ({"__format__": None}, r"missing keys \['__format__'\]"),
        ({"__shape__": None, "__meta__": None}, "missing keys"),
        ({"array/a": np.zeros((3, 5))}, r"array 'a' has shape \(3, 5\), not the grid shape"),
        ({"array/b": np.zeros((4, 3))}, "array 'b' has shape"),
        ({"__shape__": np.array([3, 4, 1])}, "__shape__ must be 2 positive ints"),
        ({"__shape__": np.array([3, 0])}, "__shape__ must be 2 positive ints"),
        ({"__origin__": np.array([0.0, np.nan])}, "__origin__ must be 2 or 3 finite"),
        ({"__origin__": np.zeros(4)}, "__origin__ must be 2 or 3 finite"),
        ({"__resolution__": np.float64(0.0)}, "__resolution__ must be positive"),
        ({"__model__": np.int64(3)}, "__model__ must be a scalar"),
        ({"__meta__": np.str_("{")}, "__meta__ is not JSON"),
        ({"__meta__": np.str_("[1]")}, "__meta__ must be a JSON object"),
        ({"array/a": None}, "holds no arrays"),
        ({"extra": np.zeros(1)}, "unexpected key 'extra'"),
        ({"array/a": np.array(["s"] * 12).reshape(3, 4)}, "array 'a' has dtype"),
        ({"array/a": np.zeros((3, 4), dtype=object)}, "not a readable .npz"),  # pickled
    ],
)
def test_load_grid_map_rejects_bad_files(tmp_path, changes, match):
    path = _raw_npz(tmp_path, **changes)
    with pytest.raises(DatasetFormatError, match=match) as info:
        load_grid_map(path)
    assert info.value.path == str(path)


def test_load_grid_map_rejects_non_archives(tmp_path):
    (tmp_path / "m.npz").write_bytes(b"not a zip")
    with pytest.raises(DatasetFormatError, match="not a readable .npz"):
        load_grid_map(tmp_path / "m.npz")
    with zipfile.ZipFile(tmp_path / "z.npz", "w") as z:
        z.writestr("__format__.npy", b"garbage")
    with pytest.raises(DatasetFormatError):
        load_grid_map(tmp_path / "z.npz")
    with pytest.raises(FileNotFoundError):
        load_grid_map(tmp_path / "none.npz")
    np.save(tmp_path / "a.npy", np.zeros(3))
    with pytest.raises(DatasetFormatError, match="single .npy array"):
        load_grid_map(tmp_path / "a.npy")
