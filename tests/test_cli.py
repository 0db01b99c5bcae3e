"""The ``lidarjax`` command line, called in-process through ``lidarjax.cli.main``."""

from __future__ import annotations

import inspect
import json
import re
from pathlib import Path

import jax
import jaxlie
import matplotlib.image
import numpy as np
import pytest

from lidarjax.cli import CliInputError, build_parser, main
from lidarjax.datasets import (
    PointCloud,
    beam_elevations,
    fetch,
    load_carmen,
    load_grid_map,
    load_synpeb_pcd,
    read_map_server,
    read_pcd,
    read_polylines_csv,
    read_tum,
    write_bag_laser_scans,
    write_labelled_cloud,
    write_pcd,
)
from lidarjax.rays import from_scan
from lidarjax.raytrace import accumulate

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
COMMANDS = (
    "info",
    "datasets",
    "fetch",
    "map",
    "localize",
    "slam",
    "polylines",
    "planes",
    "poles",
    "experiment",
)

pytestmark = pytest.mark.skipif(not SHARED.is_dir(), reason="needs ../shared/data")


def run(*argv, capsys=None) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr() if capsys is not None else ("", "")
    return code, out, err


def _png_shape(path: Path) -> tuple[int, ...]:
    return matplotlib.image.imread(path).shape


# ---------------------------------------------------------------- help, info, data
def test_every_subcommand_is_documented():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert tuple(sub.choices) == COMMANDS


@pytest.mark.parametrize("command", COMMANDS)
def test_help(command, capsys):
    code, out, _ = run(command, "--help", capsys=capsys)
    assert code == 0
    assert f"usage: lidarjax {command}" in out
    assert "example:" in out and f"lidarjax {command}" in out.split("example:")[1]
    description = out.split("\n\n")[1]  # the paragraph after the usage line
    assert len(description.split()) >= 15, description


def test_top_level_help_lists_commands(capsys):
    code, out, _ = run("--help", capsys=capsys)
    assert code == 0
    for command in COMMANDS:
        assert command in out


def test_info(capsys):
    code, out, _ = run("info", capsys=capsys)
    assert code == 0
    assert f"jax        {jax.__version__}" in out
    assert "jaxlib" in out and "numpy" in out and "devices    cpu" in out
    assert "x64        True" in out  # tests/conftest.py turns float64 on
    for kernel in ("accumulate", "fold", "polyline_plus", "field_integral", "blur"):
        assert kernel in out
    assert str(SHARED.resolve()) in out
    assert "compilation cache" in out


def test_datasets(capsys, monkeypatch, tmp_path):
    monkeypatch.delenv("LIDARJAX_DATA", raising=False)
    monkeypatch.setenv("LIDARJAX_CACHE", str(tmp_path))  # an empty user cache
    code, out, _ = run("datasets", capsys=capsys)
    assert code == 0
    rows = {ln.split()[0]: ln for ln in out.splitlines()[1:] if ln.strip()}
    assert re.match(r"intel +yes +437\.9 KB +yes ", rows["intel"])  # local, URL known
    assert re.match(r"synpeb-test-100 +yes +371\.4 KB +no ", rows["synpeb-test-100"])
    assert re.match(r"aces +no +- +yes ", rows["aces"])
    assert "14 of 16 files found locally" in out


def test_fetch_verifies_local_copies(capsys, monkeypatch):
    monkeypatch.delenv("LIDARJAX_DATA", raising=False)
    code, out, _ = run("fetch", "intel", "kitti-00-times", capsys=capsys)
    assert code == 0
    assert str(fetch("intel")) in out and "sha256 verified" in out
    code, _, err = run("fetch", "no-such-file", capsys=capsys)
    assert code == 2 and "argument NAME" in err and "intel" in err
    code, _, err = run("fetch", capsys=capsys)
    assert code == 2 and "argument NAME" in err


# ---------------------------------------------------------------- map
@pytest.fixture(scope="module")
def intel_map(tmp_path_factory):
    out = tmp_path_factory.mktemp("map")
    code = main(
        ["map", "carmen/intel", "-o", str(out), "--scans", "0:60", "--chunk", "16"]
        + ["--resolution", "0.1", "--no-progress"]
    )
    assert code == 0
    return out


def test_map_files(intel_map):
    for f in ("map.npz", "map.yaml", "map.pgm", "map.png"):
        assert (intel_map / f).stat().st_size > 0, f
    gm = load_grid_map(intel_map / "map.npz")
    assert gm.model == "decay_rate" and gm.resolution == pytest.approx(0.1)
    nx, ny = gm.shape
    for name in ("hits", "misses", "lengths", "rates"):
        assert gm.arrays[name].shape == (nx, ny), name
    assert gm.meta["n_scans_used"] == 60 and gm.meta["source"] == "carmen/intel"
    ros = read_map_server(intel_map / "map.yaml")
    assert ros.occupancy.shape == (nx, ny)
    assert ros.resolution == pytest.approx(0.1)
    np.testing.assert_allclose(ros.origin_xy, gm.origin, atol=1e-9)
    occupied = ros.occupancy == 1
    assert occupied.any() and (ros.occupancy == 0).sum() > occupied.sum()
    assert np.all(gm.arrays["hits"][occupied] > 0)  # an occupied cell reflected something
    h, w, _ = _png_shape(intel_map / "map.png")
    assert h > 300 and w > 300


def test_map_chunks_equal_one_accumulation(intel_map):
    """The statistics accumulated in chunks of 16 scans are those of one call."""
    gm = load_grid_map(intel_map / "map.npz")
    log = load_carmen(fetch("intel"))
    p = log.poses[:60]
    rays = from_scan(
        jaxlie.SE2.from_xy_theta(p[:, 0], p[:, 1], p[:, 2]),
        log.azimuths_rad,
        log.ranges_m[:60],
        gm.meta["r_min_m"],
        gm.meta["r_max_m"],
    )
    from lidarjax.raytrace import GridSpec

    stats = accumulate(GridSpec(gm.origin, gm.resolution, gm.shape), rays)
    np.testing.assert_array_equal(gm.arrays["hits"], np.asarray(stats.hits))
    np.testing.assert_array_equal(gm.arrays["misses"], np.asarray(stats.misses))
    np.testing.assert_allclose(gm.arrays["lengths"], np.asarray(stats.lengths), rtol=1e-9)
    lam = gm.arrays["rates"]
    seen = gm.arrays["lengths"] > 0
    np.testing.assert_allclose(lam[seen], gm.arrays["hits"][seen] / gm.arrays["lengths"][seen])


@pytest.mark.parametrize("model", ["reflection", "endpoint"])
def test_map_other_models(model, tmp_path):
    assert main(["map", "intel", "-o", str(tmp_path), "--scans", "0:10", "--model", model,
                 "--resolution", "0.2", "--no-progress"]) == 0  # fmt: skip
    gm = load_grid_map(tmp_path / "map.npz")
    assert gm.model == model
    key = {"reflection": "probs", "endpoint": "distances"}[model]
    assert gm.arrays[key].shape == gm.shape
    assert read_map_server(tmp_path / "map.yaml").occupancy.shape == gm.shape


def test_map_from_bag_matches_the_log(tmp_path):
    """A ROS 1 bag of 20 scans (tf poses) maps onto the grid of the same CARMEN scans."""
    log = load_carmen(fetch("intel")).subset(slice(0, 20))
    bag = write_bag_laser_scans(tmp_path / "intel.bag", log)
    args = ["--resolution", "0.2", "--no-progress", "--max-range", str(log.usable_range_m)]
    assert main(["map", str(bag), "-o", str(tmp_path / "bag"), *args]) == 0
    assert main(["map", "intel", "--scans", "0:20", "-o", str(tmp_path / "log"), *args]) == 0
    a = load_grid_map(tmp_path / "bag" / "map.npz")
    b = load_grid_map(tmp_path / "log" / "map.npz")
    assert a.meta["azimuth_layout"] is None and b.meta["azimuth_layout"] == "spread"
    assert a.shape == b.shape
    np.testing.assert_allclose(a.origin, b.origin, atol=1e-4)
    assert a.arrays["hits"].sum() == b.arrays["hits"].sum()  # same HIT rays (float32 ranges)
    assert np.mean(a.arrays["hits"] != b.arrays["hits"]) < 1e-3


# ---------------------------------------------------------------- localize
def test_localize(intel_map, tmp_path, capsys):
    out = tmp_path / "loc"
    code, text, _ = run(
        "localize", intel_map / "map.npz", "intel", "-o", out, "--scans", "0:30",
        "--particles", "200", "--chunk", "8", "--no-progress", capsys=capsys,
    )  # fmt: skip
    assert code == 0
    log = load_carmen(fetch("intel"))
    tum = read_tum(out / "trajectory.tum")
    assert tum.poses.shape == (29, 7)  # one estimate after each of scans 1..29
    np.testing.assert_allclose(tum.stamps_s, log.timestamps_s[1:30])
    kitti = np.loadtxt(out / "trajectory_kitti.txt")
    assert kitti.shape == (29, 12)
    np.testing.assert_allclose(kitti[:, [3, 7]], tum.poses[:, :2], atol=1e-12)
    errors = json.loads((out / "errors.json").read_text())
    pos = np.linalg.norm(tum.poses[:, :2] - log.poses[1:30, :2], axis=1)
    assert errors["ate_m"] == pytest.approx(np.sqrt(np.mean(pos**2)), rel=1e-9)
    assert errors["ate_m"] < 0.1  # tracking on the mapped scans, from the true start
    assert f"{errors['ate_m']:.3f} m" in text and "ATE" in text
    assert _png_shape(out / "errors.png")[0] > 200


def test_localize_chunks_continue_the_filter(intel_map, tmp_path):
    """Running the filter in chunks of 4 steps gives the trajectory of one run."""
    common = ["--scans", "0:14", "--particles", "50", "--no-progress", "--seed", "3"]
    for name, chunk in (("a", "4"), ("b", "100")):
        argv = ["localize", str(intel_map / "map.npz"), "intel", "-o", str(tmp_path / name)]
        assert main([*argv, *common, "--chunk", chunk]) == 0
    a = (tmp_path / "a" / "trajectory.tum").read_text()
    assert a == (tmp_path / "b" / "trajectory.tum").read_text()


def test_localize_init_pose(intel_map, tmp_path):
    log = load_carmen(fetch("intel"))
    x, y, th = log.poses[0]
    argv = ["localize", str(intel_map / "map.npz"), "intel", "-o", str(tmp_path)]
    opts = ["--scans", "0:6", "--particles", "20", "--no-progress", "--init-std", "0,0,0"]
    assert main([*argv, *opts, "--init", f"{x},{y},{th}"]) == 0
    assert main([*argv, *opts, "--init", "1,2"]) == 2


# ---------------------------------------------------------------- errors
def test_missing_and_corrupt_inputs(intel_map, tmp_path, capsys):
    code, _, err = run("map", tmp_path / "nope.log", "-o", tmp_path / "o", capsys=capsys)
    assert code == 2
    assert err.count("\n") == 1 and "argument LOG" in err and "nope.log" in err
    bad = tmp_path / "bad.log"
    bad.write_text("FLASER 3 1.0 2.0\n")
    code, _, err = run("map", bad, "-o", tmp_path / "o", capsys=capsys)
    assert code == 2 and err.count("\n") == 1 and "argument LOG" in err and "bad.log" in err
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    code, _, err = run("localize", junk, "intel", "-o", tmp_path / "o", capsys=capsys)
    assert code == 2 and err.count("\n") == 1 and "argument MAP" in err
    code, _, err = run("localize", tmp_path / "x.npz", "intel", "-o", tmp_path / "o", capsys=capsys)
    assert code == 2 and "argument MAP" in err and "no such file" in err
    code, _, err = run("planes", junk, "-o", tmp_path / "o", capsys=capsys)
    assert code == 2 and "argument CLOUD" in err
    code, _, err = run("map", "intel", "-o", tmp_path / "o", "--scans", "5:5", capsys=capsys)
    assert code == 2 and "argument --scans" in err
    code, _, err = run("map", "intel", capsys=capsys)  # argparse: -o is required
    assert code == 2 and "-o/--out" in err
    with pytest.raises(CliInputError):  # --debug: the exception itself
        main(["--debug", "map", str(bad), "-o", str(tmp_path / "o")])


# ---------------------------------------------------------------- features
def test_polylines(tmp_path, capsys):
    code, out, _ = run(
        "polylines", "intel", "-o", tmp_path, "--scan", "633", "--J", "20", capsys=capsys
    )
    assert code == 0
    summary = json.loads((tmp_path / "polylines.json").read_text())
    assert summary["method"] == "PLE" and 2 <= summary["J"] <= 20
    pls = read_polylines_csv(tmp_path / "polylines.csv")
    assert len(pls) == summary["n_polylines"]
    # closed polygons repeat their first vertex in the file
    assert sum(len(p) for p in pls) == summary["J"] + sum(summary["closed"])
    assert 0 < summary["rmse_m"] < 0.5 and 0.5 < summary["explained_fraction"] <= 1
    svg = (tmp_path / "polylines.svg").read_text()
    assert svg.count("<polyline") == len(pls) and "<circle" in svg
    assert _png_shape(tmp_path / "polylines.png")[0] > 200


def test_polylines_plus_never_worse(tmp_path):
    for name, extra in (("ple", []), ("plus", ["--plus"])):
        argv = ["polylines", "intel", "-o", str(tmp_path / name), "--scan", "100", "--J", "12"]
        assert main(argv + extra) == 0
    ple = json.loads((tmp_path / "ple" / "polylines.json").read_text())
    plus = json.loads((tmp_path / "plus" / "polylines.json").read_text())
    assert plus["method"] == "PLE+" and plus["J"] == ple["J"]
    assert plus["rmse_m"] <= ple["rmse_m"] + 1e-12


@pytest.fixture(scope="module")
def synpeb_planes(tmp_path_factory):
    out = tmp_path_factory.mktemp("planes")
    assert main(["planes", str(fetch("synpeb-test-100")), "-o", str(out)]) == 0
    return out


def test_planes(synpeb_planes):
    summary = json.loads((synpeb_planes / "planes.json").read_text())
    cloud = read_pcd(synpeb_planes / "labelled.pcd")
    labels = np.asarray(cloud.fields["label"]).astype(int) - 1  # 0 in the file: no plane
    assert labels.shape == (100, 100) == tuple(summary["shape"])
    assert summary["n_planes"] == labels.max() + 1 >= 8
    assert summary["points_on_planes"] == int((labels >= 0).sum())
    for p in summary["planes"]:
        assert p["points"] == int((labels == p["label"]).sum()) >= 30
        assert np.linalg.norm(p["normal"]) == pytest.approx(1, abs=1e-5)
    crop, _ = load_synpeb_pcd(fetch("synpeb-test-100"))
    xyz = np.stack([cloud.fields[f] for f in "xyz"], -1)
    np.testing.assert_allclose(xyz, crop, atol=1e-6)  # the scan's own points, float32
    assert _png_shape(synpeb_planes / "planes.png")[1] > 300


def test_planes_unorganized_ply_needs_shape(synpeb_planes, tmp_path, capsys):
    crop, _ = load_synpeb_pcd(fetch("synpeb-test-100"))
    ply = write_labelled_cloud(
        tmp_path / "flat.ply", crop.reshape(-1, 3), np.zeros(10_000, np.int64)
    )
    code, _, err = run("planes", ply, "-o", tmp_path / "a", capsys=capsys)
    assert code == 2 and "argument CLOUD" in err and "--shape" in err
    code, _, err = run("planes", ply, "-o", tmp_path / "a", "--shape", "99", "100", capsys=capsys)
    assert code == 2 and "argument --shape" in err
    assert main(["planes", str(ply), "-o", str(tmp_path / "b"), "--shape", "100", "100"]) == 0
    a = json.loads((tmp_path / "b" / "planes.json").read_text())
    b = json.loads((synpeb_planes / "planes.json").read_text())
    assert a["n_planes"] == b["n_planes"]  # the float32 copy of the same scan


def test_planes_organises_a_spinning_lidar_cloud(tmp_path, capsys):
    """An unordered HDL-32E-like cloud of a floor 1.73 m below the sensor and a wall 8 m
    to its left (|x| < 6 m) is put back into 32 x 360 cells; PPE finds both planes."""
    el = beam_elevations("hdl32e")
    az = 2 * np.pi * np.arange(360) / 360
    e, a = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        r_floor = np.where(d[:, 2] < 0, -1.73 / d[:, 2], np.inf)
        r_wall = np.where(d[:, 1] > 0, 8.0 / d[:, 1], np.inf)
    r_wall[np.abs(r_wall * d[:, 0]) > 6] = np.inf
    r = np.minimum(np.minimum(r_floor, r_wall), 40.0)
    keep = r < 40.0
    pts = (d * r[:, None])[keep]
    pts = pts[np.random.default_rng(0).permutation(len(pts))]  # unordered
    ply = write_labelled_cloud(tmp_path / "scan.ply", pts, np.zeros(len(pts), np.int64))
    code, out, _ = run(
        "planes", ply, "-o", tmp_path / "o", "--organise", "hdl32e", "--columns", "360",
        capsys=capsys,
    )  # fmt: skip
    assert code == 0
    assert f"organised {len(pts)} points into 32 x 360" in out and "0 off every beam" in out
    summary = json.loads((tmp_path / "o" / "planes.json").read_text())
    assert summary["shape"] == [32, 360] and summary["valid_points"] == len(pts)
    normals = np.array([p["normal"] for p in summary["planes"] if p["points"] > 500])
    assert len(normals) == 2  # the floor and the wall, each in one piece
    assert np.max(np.abs(normals[:, 2])) > 0.999 and np.max(np.abs(normals[:, 1])) > 0.999
    code, _, err = run("planes", ply, "-o", tmp_path / "x", "--organise", "hdl32e",
                       "--shape", "32", "360", capsys=capsys)  # fmt: skip
    assert code == 2 and "argument --organise" in err


def test_poles_from_a_cloud(tmp_path):
    """Three 0.3 m poles standing on a ground disc, seen from a sensor 1.73 m up."""
    rng = np.random.default_rng(0)
    centres = np.array([[5.0, 0.0], [-4.0, 6.0], [8.0, -7.0]])
    parts = []
    for cx, cy in centres:
        th, z = rng.uniform(0, 2 * np.pi, 3000), rng.uniform(0, 5, 3000)
        parts.append(np.c_[cx + 0.15 * np.cos(th), cy + 0.15 * np.sin(th), z])
    r, a = rng.uniform(2, 14, 20000), rng.uniform(0, 2 * np.pi, 20000)
    parts.append(np.c_[r * np.cos(a), r * np.sin(a), np.zeros_like(r)])
    p = np.concatenate(parts).astype(np.float32)
    pcd = tmp_path / "poles.pcd"
    write_pcd(pcd, PointCloud.from_fields({"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]}))
    assert main(["poles", str(pcd), "-o", str(tmp_path / "o"), "--sensor", "0,0,1.73"]) == 0
    found = np.loadtxt(tmp_path / "o" / "poles.csv", delimiter=",", skiprows=1, ndmin=2)
    assert found.shape == (3, 6)
    d = np.linalg.norm(found[:, None, :2] - centres[None], axis=-1)
    assert np.all(d.min(axis=0) < 0.2)
    assert json.loads((tmp_path / "o" / "poles.json").read_text())["n_poles"] == 3


@pytest.mark.slow  # a simulated HDL-32E drive: ~30 s on 2 cores
def test_poles_sim(tmp_path, capsys):
    code, out, _ = run("poles", "sim", "-o", tmp_path, "--scans", "40:42", capsys=capsys)
    assert code == 0
    summary = json.loads((tmp_path / "poles.json").read_text())
    assert summary["true_poles_in_map"] >= 1
    assert summary["true_poles_found_within_0_5m"] >= 1
    assert "true poles in the local map found" in out


def test_experiment_list_and_unknown(capsys):
    code, out, _ = run("experiment", "--list", capsys=capsys)
    assert code == 0
    for name in ("demo", "mcl", "planes", "poles", "polylines"):
        assert any(ln.startswith(name + " ") for ln in out.splitlines()), name
    assert "_common" not in out
    code, _, err = run("experiment", "no_such_experiment", capsys=capsys)
    assert code == 2 and "argument NAME" in err and "demo" in err


# ---------------------------------------------------------------- --azimuth-layout
LOG_COMMANDS = ("map", "localize", "slam", "polylines")  # the subcommands that read a laser log


def _write_carmen(path: Path, n_scans: int = 6, n_beams: int = 36) -> Path:
    """A small CARMEN log: a robot driving through a 6 m x 6 m room, ``n_beams`` (even)
    beams traced at the sweep layout's 5-degree steps (no PARAM line), odometry offset
    from the corrected poses; one 20 m no-return in the first scan."""
    az = np.radians(-90 + 180 / n_beams * np.arange(n_beams))
    lines = ["# synthetic log for tests/test_cli.py"]
    for i in range(n_scans):
        x, y, th = -0.5 + 0.2 * i, 0.1 * i, 0.05 * i
        d = np.stack([np.cos(th + az), np.sin(th + az)], -1)
        wall = np.where(d > 0, 3.0, -3.0) - np.array([x, y])  # the walls ahead, per axis
        with np.errstate(divide="ignore"):
            r = np.where(d != 0, wall / d, np.inf).min(axis=1)
        if i == 0:
            r[-1] = 20.0
        pose = [x, y, th, x + 1.0, y - 2.0, th + 0.1]
        nums = " ".join(f"{v:.6f}" for v in [*r, *pose])
        lines.append(f"FLASER {n_beams} {nums} {100 + 0.1 * i:.3f} host {100 + 0.1 * i:.3f}")
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def small_log(tmp_path_factory) -> Path:
    return _write_carmen(tmp_path_factory.mktemp("carmen") / "room.log")


@pytest.fixture(scope="module")
def small_maps(small_log, tmp_path_factory) -> dict[str, Path]:
    """``lidarjax map`` of the small log without the option and with each layout."""
    out = tmp_path_factory.mktemp("layout-maps")
    maps = {}
    for name, extra in (("default", []), ("spread", ["--azimuth-layout", "spread"]),
                        ("sweep", ["--azimuth-layout", "sweep"])):  # fmt: skip
        argv = ["map", str(small_log), "-o", str(out / name), "--resolution", "0.1"]
        assert main([*argv, "--no-progress", *extra]) == 0, name
        maps[name] = out / name / "map.npz"
    return maps


def _option(command: str) -> object:
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    return next(a for a in sub.choices[command]._actions if a.dest == "azimuth_layout")


@pytest.mark.parametrize("command", LOG_COMMANDS)
def test_azimuth_layout_option(command, capsys):
    """Optional, default None, choices = the library's layouts; the help says both."""
    from lidarjax.cli._inputs import DEFAULT_AZIMUTH_LAYOUT
    from lidarjax.datasets import AZIMUTH_LAYOUTS

    action = _option(command)
    assert action.option_strings == ["--azimuth-layout"] and not action.required
    assert action.default is None and tuple(action.choices) == AZIMUTH_LAYOUTS
    # None reads the log as load_carmen does by default
    default = inspect.signature(load_carmen).parameters["azimuth_layout"].default
    assert default == DEFAULT_AZIMUTH_LAYOUT == "spread"
    code, out, _ = run(command, "--help", capsys=capsys)
    assert code == 0 and "--azimuth-layout {spread,sweep}" in out
    text = " ".join(out.split("--azimuth-layout {spread,sweep}")[2].split())
    assert "spread = evenly from -fov/2 to +fov/2" in text and "sweep = the scanner's" in text
    assert "-90 ... +89 deg for 180 beams" in text


def test_load_log_azimuth_layout(small_log):
    """Both load_carmen calls of load_log (registry name, file) get the layout."""
    from lidarjax.cli._inputs import load_log

    for value, path in (("intel", fetch("intel")), (str(small_log), small_log)):
        for layout in (None, "spread", "sweep"):
            loaded = load_log(value, azimuth_layout=layout)
            want = load_carmen(path, azimuth_layout=layout or "spread").azimuths_rad
            np.testing.assert_array_equal(loaded.log.azimuths_rad, want)
            assert loaded.azimuth_layout == (layout or "spread")
    with pytest.raises(CliInputError, match="argument --azimuth-layout"):
        load_log(str(small_log), azimuth_layout="diagonal")


def test_map_azimuth_layout(small_log, small_maps):
    """The map's statistics are those of the rays at the chosen layout's azimuths, and
    map.npz records the layout ("spread" without the option)."""
    from lidarjax.raytrace import GridSpec

    hits = {}
    for name, layout in (("default", "spread"), ("spread", "spread"), ("sweep", "sweep")):
        gm = load_grid_map(small_maps[name])
        assert gm.meta["azimuth_layout"] == layout, name
        log = load_carmen(small_log, azimuth_layout=layout)
        p = log.poses
        rays = from_scan(
            jaxlie.SE2.from_xy_theta(p[:, 0], p[:, 1], p[:, 2]),
            log.azimuths_rad,
            log.ranges_m,
            gm.meta["r_min_m"],
            gm.meta["r_max_m"],
        )
        stats = accumulate(GridSpec(gm.origin, gm.resolution, gm.shape), rays)
        np.testing.assert_array_equal(gm.arrays["hits"], np.asarray(stats.hits), err_msg=name)
        np.testing.assert_array_equal(gm.arrays["misses"], np.asarray(stats.misses))
        hits[name] = gm.arrays["hits"]
    np.testing.assert_array_equal(hits["default"], hits["spread"])
    assert hits["sweep"].shape != hits["spread"].shape or np.any(hits["sweep"] != hits["spread"])


def test_localize_azimuth_layout(small_log, small_maps, tmp_path, monkeypatch, capsys):
    """The filter's scan model gets the chosen layout's azimuths; errors.json records the
    layout; a map built with the other layout is pointed out."""
    import lidarjax.localization as loc

    seen = []
    real = loc.ScanModel

    def spy(*args, **kwargs):
        model = real(*args, **kwargs)
        seen.append(np.asarray(model.azimuths))
        return model

    monkeypatch.setattr(loc, "ScanModel", spy)
    common = ["--particles", "16", "--beams", "36", "--init-std", "0.05,0.05,0.02"]
    for name, layout, extra in (("default", "spread", []),
                                ("sweep", "sweep", ["--azimuth-layout", "sweep"])):  # fmt: skip
        out = tmp_path / name
        code, text, _ = run("localize", small_maps["sweep"], small_log, "-o", out,
                            "--no-progress", *common, *extra, capsys=capsys)  # fmt: skip
        assert code == 0, name
        want = load_carmen(small_log, azimuth_layout=layout).azimuths_rad
        np.testing.assert_allclose(seen[-1], want, rtol=0, atol=1e-12, err_msg=name)
        assert json.loads((out / "errors.json").read_text())["azimuth_layout"] == layout
        mismatch = "MAP was built with the sweep azimuth layout, LOG is read with the spread"
        assert (mismatch in text) == (layout == "spread"), text
    assert len(seen) == 2


def _svg_points(path: Path) -> np.ndarray:
    """The scan points of polylines.svg in metres (50 px per m, y up)."""
    import xml.etree.ElementTree as ET

    ns = "{http://www.w3.org/2000/svg}"
    circles = ET.parse(path).getroot().iter(f"{ns}circle")
    return np.array([[float(c.get("cx")) / 50, -float(c.get("cy")) / 50] for c in circles])


def test_polylines_azimuth_layout(small_log, tmp_path):
    """The scan points drawn in polylines.svg lie at the chosen layout's azimuths, and
    polylines.json records the layout."""
    for name, layout, extra in (("default", "spread", []),
                                ("sweep", "sweep", ["--azimuth-layout", "sweep"])):  # fmt: skip
        out = tmp_path / name
        argv = ["polylines", str(small_log), "-o", str(out), "--scan", "2", "--J", "8"]
        assert main([*argv, *extra]) == 0, name
        log = load_carmen(small_log, azimuth_layout=layout)
        r, az = log.ranges_m[2], log.azimuths_rad
        keep = r < log.usable_range_m
        want = (r[:, None] * np.stack([np.cos(az), np.sin(az)], -1))[keep]
        got = _svg_points(out / "polylines.svg")
        assert got.shape == want.shape == (36, 2)
        np.testing.assert_allclose(got, want, atol=1e-5, err_msg=name)
        assert json.loads((out / "polylines.json").read_text())["azimuth_layout"] == layout


@pytest.mark.parametrize("command", LOG_COMMANDS)
def test_azimuth_layout_bad_value(command, small_log, tmp_path, capsys):
    before = ["map.npz"] if command == "localize" else []
    code, _, err = run(command, *before, small_log, "-o", tmp_path / "o",
                       "--azimuth-layout", "diagonal", capsys=capsys)  # fmt: skip
    assert code == 2
    assert "argument --azimuth-layout: invalid choice: 'diagonal'" in err
    assert "spread" in err and "sweep" in err
    assert not (tmp_path / "o").exists()


@pytest.fixture(scope="module")
def small_bag(small_log, tmp_path_factory) -> Path:
    log = load_carmen(small_log)
    return write_bag_laser_scans(tmp_path_factory.mktemp("bag") / "room.bag", log)


def test_azimuth_layout_rejected_for_a_bag(small_bag, small_maps, tmp_path, capsys):
    """A bag's scans carry their own angles: the option is an input error for a bag, even
    with the default value, not ignored."""
    from lidarjax.cli._inputs import load_log

    loaded = load_log(str(small_bag))  # the bag itself reads fine
    assert loaded.kind == "bag" and loaded.azimuth_layout is None
    for command in LOG_COMMANDS:
        before = [small_maps["default"]] if command == "localize" else []
        for layout in ("spread", "sweep"):
            code, _, err = run(command, *before, small_bag, "-o", tmp_path / command,
                               "--azimuth-layout", layout, capsys=capsys)  # fmt: skip
            assert code == 2, (command, layout)
            assert err.count("\n") == 1 and "argument --azimuth-layout" in err
            assert "ROS bag" in err and "angle_min" in err
