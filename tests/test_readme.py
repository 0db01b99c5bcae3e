"""The Python examples of the README (its quickstart) and of the guide (docs/guide/*.md) run
as written (against the shared real data)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
GUIDE = ROOT / "docs" / "guide"
# The guide's pages in reading order: later examples continue the earlier ones (one namespace).
GUIDE_ORDER = (
    "data.md",
    "ray-tracing.md",
    "sensor-models.md",
    "localization.md",
    "dct-maps.md",
    "fields.md",
    "polylines.md",
    "planes.md",
    "poles.md",
    "plots.md",
    "notebooks.md",
    "guarantees.md",
    "performance.md",
    "tests.md",
)


# Pages whose examples run on their own, each in a fresh namespace (they reuse names such
# as ``log`` and ``out`` that the pages above define differently).
STANDALONE = ("formats.md", "command-line.md", "scaling.md", "slam.md")


def python_blocks(path: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.S)


def test_guide_order_lists_every_page():
    """A new guide page joins GUIDE_ORDER, so its examples run too."""
    assert sorted(GUIDE_ORDER + STANDALONE) == sorted(p.name for p in GUIDE.glob("*.md"))


@pytest.mark.slow
def test_readme_quickstart_runs():
    blocks = python_blocks(README)
    assert len(blocks) >= 1
    ns: dict = {}
    for code in blocks:
        exec(compile(code, str(README), "exec"), ns)
    assert ns["log"].ranges_m.shape == (910, 180)
    assert ns["ll"].shape == (180,)
    assert np.all(np.isfinite(np.asarray(ns["ll"])))  # the scan helped build the map
    track, odd = np.asarray(ns["track"]), ns["odd"]
    assert track.shape == (19, 3)
    err = np.linalg.norm(track[:, :2] - ns["log"].poses[odd[1:], :2], axis=1)
    assert err.mean() < 0.2, err
    # the formats section
    out = ns["out"]
    assert ns["bag_log"].ranges_m.shape == (50, 180)
    assert np.array_equal(ns["bag_log"].ranges_m, ns["log"].ranges_m[:50].astype(np.float32))
    assert (ns["crop_ply"].height, ns["crop_ply"].width) == (100, 100)
    assert ns["organised"].cloud.height == 16 and ns["organised"].n_dropped == 0
    for name in ("crop.pcd", "intel.yaml", "intel.pgm", "intel.npz", "track.tum"):
        assert (out / name).is_file(), name
    for name in ("track.kitti", "scan.csv", "scan.svg", "planes.ply"):
        assert (out / name).is_file(), name
    assert ns["ds"].read_tum(out / "track.tum").poses.shape[0] == 19


@pytest.mark.slow
def test_guide_examples_run():
    blocks = [(GUIDE / name, code) for name in GUIDE_ORDER for code in python_blocks(GUIDE / name)]
    assert len(blocks) >= 9
    ns: dict = {}
    for path, code in blocks:  # later blocks continue the earlier ones
        exec(compile(code, str(path), "exec"), ns)
    assert ns["log"].ranges_m.shape == (910, 180)
    assert int(ns["stats"].hits.sum()) == ns["rays"].counts()["HIT"]
    assert ns["ll"].shape == (180,) and ns["ll_fmp"].shape == (180,)
    # the optical depth of a smooth field on the native kernel and the JAX path
    assert ns["depth"].shape == (180,) and float(ns["depth"].max()) > 0
    np.testing.assert_allclose(ns["depth"], ns["depth_jax"], rtol=1e-9, atol=1e-9)
    assert np.all(np.isfinite(np.asarray(ns["ll_fmp"])))
    assert ns["scores"].shape == (100,)
    track, odd = np.asarray(ns["track"]), ns["odd"]
    assert track.shape == (19, 3)
    err = np.linalg.norm(track[:, :2] - ns["log"].poses[odd[1:], :2], axis=1)
    assert err.mean() < 0.2, err
    refined = np.asarray(ns["loc"].to_vector(ns["pose"]))
    assert np.linalg.norm(refined[:2] - ns["log"].poses[odd[-1], :2]) < 0.1
    # DCT maps
    import optimistix as optx

    assert ns["dct"].shape == (32, 32) and ns["sol"].result == optx.RESULTS.successful
    assert np.all(np.isfinite(np.asarray(ns["ll_dct"])))
    matched = np.asarray(ns["matched"].translation())
    assert np.linalg.norm(matched - ns["log"].poses[ns["s"], :2]) < 0.05
    # bring your own decay-rate field
    bumps, bumps0, patch = ns["bumps"], ns["bumps0"], ns["patch"]
    ll_b = np.asarray(ns["maps"].field_log_likelihood(bumps, patch))
    ll_b0 = np.asarray(ns["maps"].field_log_likelihood(bumps0, patch))
    assert np.all(np.isfinite(ll_b)) and ll_b.sum() > ll_b0.sum() + 0.1 * ll_b.size
    assert int(ns["sol_b"].stats["num_steps"]) > 1
    assert np.all(np.isfinite(np.asarray(ns["pose_b"].parameters())))
    # polylines (PLE / PLE+)
    ple, plus, scan = ns["ple"], ns["plus"], ns["scan"]
    assert int(ple.stats.n_vertices) <= 20 and len(ns["polylines"]) == int(ple.stats.n_polylines)
    assert float(plus.sse_after_m2) <= float(plus.sse_before_m2)
    r_hat = np.asarray(ns["r_hat"])
    assert r_hat.shape == (180,)
    explained = np.isfinite(r_hat) & (np.asarray(scan.kind) == 0)
    assert explained.sum() == int(ple.stats.n_explained)
    # planes (PPE)
    seg, hv, fit = ns["seg"], ns["hv"], ns["fit"]
    assert seg.labels.shape == (100, 100) and seg.normals.shape == (seg.n_planes, 3)
    # the guide scores SynPEB-file planes only (labels >= 10): 12 on the crop, 10 found
    assert hv.n_gt == 12 and hv.n_correct >= 10
    assert bool(fit.converged)
    np.testing.assert_allclose(float(fit.error), float(seg.errors[0]), rtol=1e-6)
    assert 0.0005 < ns["sigma"] < 0.005
    assert ns["room"].points.shape == (100, 100, 3)
    # poles
    poles, pole_map, ll = ns["poles"], ns["pole_map"], np.asarray(ns["ll_poles"])
    assert len(poles) >= 3 and len(pole_map) == len(poles)
    d = np.linalg.norm(poles.xy[:, None] - ns["world"].pole_xy[None], axis=-1).min(1)
    assert np.median(d) < 0.2, d
    assert ll.shape == (3,) and ll[0] > ll[1] and ll[0] > ll[2]
    # plots and gradient checks (guide pages plots.md, tests.md)
    assert ns["ax"].get_xlabel() == "x (m)" and ns["ax_poles"].get_ylabel() == "y (m)"
    assert ns["report"] is not None and ns["J"].shape == (2, 3)


@pytest.mark.slow
@pytest.mark.parametrize("name", STANDALONE)
def test_standalone_guide_pages_run(name, tmp_path, monkeypatch):
    """The formats and command-line pages, each from a fresh namespace; they leave their
    files in temporary folders, and the last page's results are checked."""
    monkeypatch.chdir(ROOT)
    blocks = python_blocks(GUIDE / name)
    assert len(blocks) >= 2 if name == "formats.md" else len(blocks) >= 1
    ns: dict = {}
    for code in blocks:
        exec(compile(code, str(GUIDE / name), "exec"), ns)
    if name == "formats.md":
        assert ns["back"] is not None and (ns["out"] / "scan100.svg").is_file()
        assert (ns["out"] / "intel.pgm").is_file() and (ns["out"] / "gt.tum").is_file()
    elif name == "command-line.md":
        assert (ns["out"] / "intel" / "map.npz").is_file()
    elif name == "slam.md":  # the front end beats the odometry; the back end's objective rises
        assert (ns["out"] / "joint_poses.txt").is_file()
        assert ns["joint"].objective[-1] >= ns["joint"].objective[0]
        # the odometry's calibration finds the simulated drift (0.3 deg/m; 0.25 measured
        # over the 17 m of this office run) and no turn error to speak of
        assert 0.15 < np.rad2deg(ns["cal"].heading_rad_per_m) < 0.45
        assert abs(ns["cal"].heading_gain) < 0.02 and ns["cal"].n_used == 39
        # the second front end and the two-chain graph beat the odometry (measured: 0.013
        # and 0.021 m against 0.052 m)
        from lidarjax.metrics import absolute_trajectory_error as ate

        ate_odo = ate(ns["odometry"], ns["truth"]).rmse_m
        assert ate(ns["second"].poses, ns["truth"]).rmse_m < ate_odo / 2
        assert ate(np.asarray(ns["two_chains"].poses), ns["truth"]).rmse_m < ate_odo
        # the ICP chain registers every scan (measured 4.3 mm off, the odometry 52 mm)
        assert ns["icp"].registered.all()
        assert ate(ns["icp"].poses, ns["truth"]).rmse_m < 0.01
        # SLAM on re-simulated scans, scored against the exact poses, beats the odometry
        t = ns["intel_truth"]
        assert ns["exact"].ranges_m.shape == (60, 180)
        assert ate(ns["on_exact"].poses, t).rmse_m < ate(ns["intel_odometry"], t).rmse_m / 2
        # the square with a correlated loop closure: its cost is 0.5 |W r|^2 on the odometry
        # edges and the Cauchy loss on the loop (NumPy, here), lower than at the start,
        # and the answer is not the diagonal one
        sq, corr = ns["square"], ns["correlated"]
        p, w, z = np.asarray(corr.poses), ns["w"], ns["measurements"]
        cost = 0.0
        for k, (i, j) in enumerate(ns["edges"]):
            c, s_ = np.cos(p[i, 2]), np.sin(p[i, 2])
            d = p[j, :2] - p[i, :2]
            rel = np.array([c * d[0] + s_ * d[1], -s_ * d[0] + c * d[1], p[j, 2] - p[i, 2]])
            cz, sz = np.cos(z[k, 2]), np.sin(z[k, 2])
            dz = rel[:2] - z[k, :2]
            th = np.arctan2(np.sin(rel[2] - z[k, 2]), np.cos(rel[2] - z[k, 2]))
            # Log of Z^-1 rel: (V(th)^-1 R(-z_yaw) (t_rel - t_z), th)
            u = np.array([cz * dz[0] + sz * dz[1], -sz * dz[0] + cz * dz[1]])
            a_, b_ = (np.sin(th) / th, (1 - np.cos(th)) / th) if th != 0 else (1.0, 0.0)
            v = np.linalg.solve([[a_, -b_], [b_, a_]], u)
            r = w[k] @ np.array([v[0], v[1], th])
            s2 = float(r @ r)
            cost += 4.5 * np.log1p(s2 / 9.0) if ns["robust"][k] else 0.5 * s2
        np.testing.assert_allclose(float(corr.cost), cost, rtol=1e-9)
        assert float(corr.cost) < float(corr.cost0)
        assert not np.allclose(p, np.asarray(sq.poses), atol=1e-4)
        # the reference-free scores rank the truth above the drifting odometry
        # (measured: cross-visit mean 86.9 against 126.8 mm, 1.742 against 1.335 nats per ray)
        c, ll = ns["cross_visit_distance"], ns["trajectory_log_likelihood"]
        args = (ns["ranges"], ns["azimuths"])
        kw = {"min_separation": 15, "max_range_m": 10.0}
        assert c(ns["truth"], *args, **kw).mean_m < 0.8 * c(ns["odometry"], *args, **kw).mean_m
        cfg = ns["BackEndConfig"](n_nodes=64)
        assert ll(ns["truth"], ns["azimuths"], ns["ranges"], cfg) > (
            ll(ns["odometry"], ns["azimuths"], ns["ranges"], cfg) + 0.2
        )
    else:  # scaling.md: the sharded run equals one device's; a sweep resumed and merged
        assert np.array_equal(
            np.asarray(ns["final"].log_weights), np.asarray(ns["same"].log_weights)
        )
        assert [r["status"] for r in ns["merge"](ns["sweep"])["rows"]] == ["done", "done"]
