"""match_scan's refinements and their compilation. Each refinement is run here on its own
(a separately jitted ``refine_pose``) and the candidates are compared and gated in NumPy,
as the matcher's code comments say: the coarse-to-fine stages from the search's best, the
last stage from the start pose, the first of the best plausible candidates, else the
stiff refinement from the prior, else the prior. The numbers of FrontEndConfig that only
enter the matcher's arithmetic are traced arguments: changing one reuses the compiled
program."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from lidarjax.localization.refine import refine_pose
from lidarjax.maps import DecayRateMap, SmoothDecayRateField, blur
from lidarjax.raytrace import GridSpec
from lidarjax.sim import make_office, simulate_scans
from lidarjax.slam import FrontEndConfig, grid_map, match_scan
from lidarjax.slam import _front_end as fe
from lidarjax.slam._search import correlative_search

AZ = np.linspace(-np.pi / 2, np.pi / 2, 181)


@pytest.fixture(scope="module")
def office_map():
    """The first 20 poses of the simulated office, and the map of its even scans at the
    true poses (0.05 m cells, the default front end's)."""
    world = make_office(0)
    truth = world.trajectory(100, jitter_m=0.2)[:20]
    ranges = simulate_scans(world, truth, AZ, max_range_m=30.0, noise_sigma_m=0.01, seed=0)
    grid = grid_map(FrontEndConfig())
    for q in range(0, 12, 2):
        grid.add_scan(truth[q], AZ, ranges[q])
    return truth, ranges, grid


def _xy_yaw(p: jaxlie.SE2) -> np.ndarray:
    return np.array([*np.asarray(p.translation()), float(p.rotation().as_radians())])


def _objective(blurred, gap, stiffness, origin, az, rng, w, prior, inv_sig, cfg):
    """The matcher's objective on one stage's blurred rates: the scan's log-likelihood
    (HIT rays' optical depth to ``r - gap``) plus the Gaussian prior, ``stiffness`` times
    tighter."""
    n = blurred.shape[0]
    field = SmoothDecayRateField(
        DecayRateMap(GridSpec(origin, cfg.resolution_m, (n, n)), blurred, jnp.zeros((), w.dtype)),
        n_nodes=cfg.n_nodes,
        backend=cfg.backend,
    )
    pred = fe.se2(prior)

    def f(p):
        ll = fe._scan_log_likelihoods(field, p, az, rng, cfg, gap)
        dev = jaxlie.manifold.rminus(p, pred) * inv_sig
        return jnp.sum(w * ll) - 0.5 * stiffness**2 * jnp.sum(dev**2)

    return f


@functools.partial(jax.jit, static_argnames="cfg")
def _refine(blurred, gap, stiffness, p0, origin, az, rng, w, prior, inv_sig, cfg):
    f = _objective(blurred, gap, stiffness, origin, az, rng, w, prior, inv_sig, cfg)
    return refine_pose(f, fe.se2(p0), max_steps=cfg.max_steps)[0]


@functools.partial(jax.jit, static_argnames="cfg")
def _final_score(blurred, gap, p, origin, az, rng, w, prior, inv_sig, cfg):
    return _objective(blurred, gap, 1.0, origin, az, rng, w, prior, inv_sig, cfg)(fe.se2(p))


def _reference(grid, ranges, pose0, cfg, prior, sigmas):
    """match_scan's pose, written out refinement by refinement: ``(pose, plausible,
    candidates)``."""
    dt = jnp.float64
    rates, seen, origin, az, rng, graze = fe._window_inputs(grid, pose0[:2], AZ, ranges, cfg, dt)
    res = cfg.resolution_m
    w = fe._ray_weights(seen, origin, res, az, rng, fe.se2(pose0), cfg).astype(dt)
    inv_sig = 1.0 / np.asarray(sigmas, float)
    pred = fe.se2(prior)
    # the search's best lattice pose starts the coarse-to-fine stages
    n_xy = int(round(cfg.search_xy_m / res))
    n_yaw = int(round(cfg.search_yaw_rad / cfg.search_step_yaw_rad))
    table = jnp.maximum(
        jnp.log(blur(rates, cfg.search_blur_m / res) + cfg.rate_floor), cfg.ray_floor
    )
    start, s_best, s_runner = correlative_search(
        table,
        origin,
        res,
        az,
        rng,
        w * (rng < cfg.range_cap_m),
        jnp.asarray(pose0, dt),
        jnp.asarray(prior, dt),
        jnp.asarray(inv_sig, dt),
        n_xy=n_xy,
        n_yaw=n_yaw,
        step_yaw=cfg.search_step_yaw_rad,
        exclude_m=cfg.search_exclude_m,
    )

    # the refinements' settings (the gate is applied here, in NumPy): one compilation
    key = dataclasses.replace(cfg, gate_sigmas=7.0, ambiguous_gate_sigmas=3.0)
    data = (origin, az, rng, w, jnp.asarray(prior, dt), jnp.asarray(inv_sig, dt))

    def refine(blurred, gap, stiffness, p0):
        return _xy_yaw(_refine(blurred, gap, stiffness, jnp.asarray(p0, dt), *data, key))

    def final_score(blurred, gap, p):
        return float(_final_score(blurred, gap, jnp.asarray(p, dt), *data, key))

    stages = []
    for b in cfg.blur_schedule_m:
        stages.append((blur(rates, b / res), jnp.maximum(cfg.gap_cells * res, graze) + 2 * b))
    last = stages[-1]
    pose = np.asarray(start)
    for blurred, gap in stages:
        pose = refine(blurred, gap, 1.0, pose)
    candidates = [pose, refine(*last, 1.0, pose0)]
    if cfg.final_from_search:
        candidates.append(refine(*last, 1.0, np.asarray(start)))
    gate = cfg.gate_sigmas
    if float(s_best - s_runner) < cfg.ambiguous_margin:
        gate = min(gate, cfg.ambiguous_gate_sigmas)

    def plausible(p):
        dev = np.asarray(jaxlie.manifold.rminus(fe.se2(p), pred)) * inv_sig
        return float(np.sum(dev**2)) <= gate**2

    scores = [final_score(*last, c) if plausible(c) else -np.inf for c in candidates]
    if np.isfinite(max(scores)):
        return candidates[int(np.argmax(scores))], True, candidates
    q = refine(*last, cfg.gate_stiffness, np.asarray(prior))
    return (q if plausible(q) else np.asarray(prior, float)), False, candidates


@pytest.mark.parametrize(
    ("k", "offset", "prior_offset", "sigmas", "gate"),
    [
        # a good start: the direct refinement wins over the coarse-to-fine chain
        (13, (0.1, 0.0, 0.02), (0.0, 0.0, 0.0), (0.5, 0.5, 0.2), 7.0),
        (15, (0.0, -0.15, -0.04), (0.0, 0.0, 0.0), (0.5, 0.5, 0.2), 7.0),
        # a confident prior 0.6 m off the truth: no candidate within the gate, the stiff
        # refinement from the prior is
        (15, (0.0, 0.0, 0.0), (0.6, 0.0, 0.0), (0.05, 0.05, 0.02), 5.0),
        # ... and with a gate so tight that it is not either: the prior itself
        (15, (0.0, 0.0, 0.0), (0.6, 0.0, 0.0), (0.05, 0.05, 0.02), 0.05),
    ],
)
def test_match_scan_equals_its_refinements_run_one_by_one(
    office_map, k, offset, prior_offset, sigmas, gate
):
    truth, ranges, grid = office_map
    cfg = FrontEndConfig(gate_sigmas=gate, ambiguous_gate_sigmas=min(3.0, gate))
    pose0 = truth[k] + np.asarray(offset)
    prior = truth[k] + np.asarray(prior_offset)
    ref, ok, candidates = _reference(grid, ranges[k], pose0, cfg, prior, sigmas)
    m = match_scan(grid, AZ, ranges[k], pose0, cfg, prior_xy_yaw=prior, prior_sigmas=sigmas)
    assert m.plausible == ok
    # the same refinements in another compilation: round-off apart (a stopping test
    # decided one step apart moves a pose by up to ~1e-5 m)
    np.testing.assert_allclose(m.pose, ref, atol=1e-4)
    if ok:
        # the cases discriminate: the candidates are farther apart than the tolerance
        assert np.abs(candidates[0] - candidates[1]).max() > 1e-3
    elif gate < 1:
        np.testing.assert_array_equal(m.pose, prior)
    else:
        assert np.abs(m.pose - prior).max() > 1e-3


def test_traced_settings_do_not_recompile(office_map):
    """Gates, floors and the gap only enter the matcher's arithmetic: a match with other
    values runs the compiled program again (and gives another result); the model, a
    shape or a loop count are its static key."""
    truth, ranges, grid = office_map
    pose0 = truth[15] + np.array([0.0, 0.0, 0.0])
    prior = truth[15] + np.array([0.6, 0.0, 0.0])
    sig = np.array([0.05, 0.05, 0.02])
    base = FrontEndConfig()
    match_scan(grid, AZ, ranges[15], pose0, base, prior_xy_yaw=prior, prior_sigmas=sig)
    n0 = fe._match_jit._cache_size()
    poses = []
    for change in (
        dict(gate_sigmas=1e3),
        dict(gate_sigmas=5.0, gate_stiffness=2.0),
        dict(ambiguous_margin=0.0, ambiguous_gate_sigmas=1.0),
        dict(rate_floor=1e-2, ray_floor=-5.0, gap_cells=2.0),
        # fields the matcher does not read at all
        dict(local_map_scans=7, odometry_sigma_rel=0.2, prior_sigma_xy_m=0.3),
    ):
        cfg = dataclasses.replace(base, **change)
        m = match_scan(grid, AZ, ranges[15], pose0, cfg, prior_xy_yaw=prior, prior_sigmas=sig)
        poses.append(m.pose)
    assert fe._match_jit._cache_size() == n0
    assert len({tuple(p) for p in poses}) >= 3  # the values did reach the program
    assert n0 >= 1
    # a loop count is part of the static key (not compiled here: ~25 s)
    assert (
        fe._jit_settings(dataclasses.replace(base, max_steps=30), jnp.float64)[0]
        != (fe._jit_settings(base, jnp.float64)[0])
    )
