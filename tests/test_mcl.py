"""End-to-end Monte-Carlo localization on a real log segment, and the MCL experiment on a
small config."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import carmen_even_scan_stats
from test_experiments import run_experiment

from lidarjax import localization as loc
from lidarjax import maps


@pytest.fixture(scope="module")
def intel():
    return carmen_even_scan_stats("intel", r_min=0.1)


@pytest.mark.parametrize("model", ["dec", "end"])
@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_mcl_localizes_real_segment(intel, model):
    """Odd Intel scans 1..121 (not used for mapping), raw odometry, 300 particles from an
    offset start: mean position error over all 60 steps < 0.2 m."""
    log, stats = intel
    m = maps.decay_rate_map(stats) if model == "dec" else maps.endpoint_map(stats, sigma_m=0.1)
    odd = np.arange(1, 122, 2)
    beams = np.arange(0, log.n_beams, 4)
    scan_model = loc.ScanModel(m, log.azimuths_rad[beams], 0.1, log.usable_range_m, ray_floor=-10.0)
    motion = loc.OdometryMotionModel(
        sigma=[0.02, 0.02, 0.01], alpha=[[0.1, 0, 0], [0, 0.1, 0], [0.05, 0, 0.1]]
    )
    pf = loc.ParticleFilter(motion, scan_model)
    start = log.poses[odd[0]] + np.array([0.15, -0.1, 0.05])
    state = loc.init_gaussian(300, start, [0.2, 0.2, 0.05], key=jax.random.key(1))
    controls = loc.relative_motion(jnp.asarray(log.odometry[odd]))
    _, info = pf.run(state, controls, jnp.asarray(log.ranges_m[odd[1:]][:, beams]))
    est = np.asarray(loc.to_vector(info.estimate))
    gt = log.poses[odd[1:]]
    err = np.linalg.norm(est[:, :2] - gt[:, :2], axis=1)
    head = np.abs(np.angle(np.exp(1j * (est[:, 2] - gt[:, 2]))))
    assert err.mean() < 0.2, err
    assert np.rad2deg(head).mean() < 3.0
    assert not bool(np.asarray(info.degenerate).any())
    # without the measurement update the same filter drifts with the odometry
    _, dead = pf.run(
        state,
        controls,
        jnp.asarray(log.ranges_m[odd[1:]][:, beams]),
        jnp.zeros(controls.shape[0], bool),
    )
    dead_err = np.linalg.norm(np.asarray(loc.to_vector(dead.estimate))[:, :2] - gt[:, :2], axis=1)
    assert dead_err.mean() > 2 * err.mean()


@pytest.mark.slow
def test_mcl_experiment_small(tmp_path):
    res = run_experiment(
        "mcl",
        tmp_path,
        "logs=[intel]",
        "robustness_log=intel",
        "models=[dec,end,fmp_dec]",
        "filter.runs=2",
        "filter.particles=100",
        "filter.max_steps=12",
        "filter.n_beams=15",
        "refine.every=6",
        "refine.blur_schedule_m=[0.15,0.0]",
        "refine.beam_stride=4",
    )
    assert set(res["logs"]) == {"intel", "intel*"}
    r = res["logs"]["intel"]
    assert r["n_steps"] == 12 and r["n_beams"] == 15
    assert set(r["models"]) == {"dec", "end", "fmp_dec"}
    for v in r["models"].values():
        assert np.isfinite(v["pos_err_m"]) and v["pos_err_m"] < 3.0
        assert 0 <= v["converged_runs"] <= 2
    assert r["refine"]["steps"] == [5, 11]
    assert np.isfinite(r["refine"]["refined_pos_err"])
    assert "refine" not in res["logs"]["intel*"]
    for f in ("results.md", "errors.png", "trajectories.png"):
        assert (tmp_path / f).stat().st_size > 0
    assert "| intel* |" in (tmp_path / "results.md").read_text()


@pytest.mark.slow
def test_mcl_remedies_experiment_small(tmp_path):
    """The remedies experiment end to end on a short Intel segment: diagnosis, a few
    variants (incl. coarse-to-fine and augmented MCL) and a small global localization."""
    res = run_experiment(
        "mcl_remedies",
        tmp_path,
        "logs=[intel]",
        "filter.runs=2",
        "filter.max_steps=10",
        "diagnose.models=[dec,end,dec@0.1]",
        "only=[end,dec,fmp_dec+c2f,dec+augmented,dec+zrand0.05]",
        "global_localization.runs=1",
        "~global_localization.variants",
        "+global_localization.variants={end:{model:end,particles:500},"
        "c2f:{model:fmp_dec,particles:500,coarse_to_fine:{sigmas_m:[0.0,0.1,0.2]}},"
        "scan:{model:dec,particles:500,init:global_scan,"
        "coarse_to_fine:{sigmas_m:[0.0,0.1,0.2],spread_factor:0.35}}}",
    )
    r = res["logs"]["intel"]
    d = r["diagnosis"]
    assert set(d) == {"dec", "end", "dec@0.1"}
    # the traced model is sharper than the likelihood field and smoothing widens it
    assert d["dec"]["fall_nats"]["0.1 m"] > 5 * d["end"]["fall_nats"]["0.1 m"]
    assert d["dec@0.1"]["fall_nats"]["0.1 m"] < d["dec"]["fall_nats"]["0.1 m"]
    assert d["dec"]["below_floor_fraction"] > d["dec@0.1"]["below_floor_fraction"]
    assert set(r["variants"]) == {"end", "dec", "fmp_dec+c2f", "dec+augmented", "dec+zrand0.05"}
    for v in r["variants"].values():
        assert v["runs"] == 2 and 0 <= v["converged_runs"] <= 2
        assert len(v["curve"]) == 10 and np.all(np.isfinite(v["curve"]))
        assert v["ms_per_step"] > 0
    assert set(r["global"]) == {"end", "c2f", "scan"}
    assert r["global"]["end"]["particles"] == 500
    # drawn from the start scan's posterior: localized from the first step
    scan = r["global"]["scan"]
    assert scan["init_seconds_per_run"] > 0 and scan["converged_runs"] == 1
    assert max(scan["curve"]) < 0.5
    text = (tmp_path / "results.md").read_text()
    assert "| fmp_dec+c2f |" in text and "Global localization" in text
    for f in ("surfaces.png", "errors.png"):
        assert (tmp_path / f).stat().st_size > 0
