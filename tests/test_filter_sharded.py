"""Particles sharded over devices (``shard_state``): a filter on 2 devices gives bitwise the
one-device results for the same key, keeps its state sharded, and runs the native fold
kernel per shard.

JAX fixes its devices when it starts, so the 2-device runs happen in a fresh process with
``XLA_FLAGS=--xla_force_host_platform_device_count=2`` (the 2 host devices of one CPU)."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import run_on_host_devices

from lidarjax.localization import init_gaussian, particle_mesh, shard_state

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = r"""
import json, os, re, sys
import numpy as np
import equinox as eqx
import jax, jax.numpy as jnp
import lidarjax
from lidarjax import maps
from lidarjax.rays import from_scan
from lidarjax.raytrace import GridSpec, accumulate, _native
from lidarjax.sim import make_office, simulate_scans
from lidarjax.localization import (
    OdometryMotionModel, ParticleFilter, ScanModel, global_injector, init_gaussian,
    relative_motion, shard_state,
)
from lidarjax.localization._sharding import state_mesh
import jaxlie

lidarjax.enable_compilation_cache()
out = {"devices": len(jax.devices())}
world = make_office(0)
poses = world.trajectory(9, jitter_m=0.2, seed=0)  # 8 steps: one bucket
az = np.linspace(-np.pi / 2, np.pi / 2, 31)
ranges = simulate_scans(world, poses, az, max_range_m=10.0, noise_sigma_m=0.01, seed=0)
T_ws = jaxlie.SE2.from_xy_theta(poses[:, 0], poses[:, 1], poses[:, 2])
spec = GridSpec.from_bounds(world.bounds[0] - 0.5, world.bounds[1] + 0.5, 0.2)
dm = maps.decay_rate_map(accumulate(spec, from_scan(T_ws, az, ranges, 0.05, 10.0)))
controls = np.asarray(relative_motion(poses))
zs = ranges[1:]


def leaves(tree):
    res = []
    for x in jax.tree.leaves(tree):
        if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
            x = jax.random.key_data(x)
        res.append(np.asarray(x))
    return res


def compare(a, b):
    la, lb = leaves(a), leaves(b)
    assert len(la) == len(lb)
    return all(
        x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y, equal_nan=True)
        for x, y in zip(la, lb)
    )


def layout(state):
    arrays = [state.log_weights, *jax.tree.leaves(state.particles)]
    return {
        "n_devices": [len(x.sharding.device_set) for x in arrays],
        "spec": [list(x.sharding.spec) for x in arrays],
        "shard_rows": [sorted(s.data.shape[0] for s in x.addressable_shards) for x in arrays],
    }


def case(name, backend, n, x64, **kw):
    with jax.enable_x64(x64):
        dtype = jnp.float64 if x64 else jnp.float32
        m = jax.tree.map(lambda x: x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating)
                         else x, dm)
        model = ScanModel(m, az, 0.05, 10.0, ray_floor=-10.0, beam_exponent=0.05, backend=backend)
        if kw.pop("extensions", False):
            free = np.ones(spec.shape, bool)
            kw.update(resampler="stratified", alpha_slow=0.01, alpha_fast=0.3,
                      injector=global_injector(spec, jnp.asarray(free)), kld=True, n_min=8,
                      kld_bin_size=(0.2, 0.2, 0.2))
        pf = ParticleFilter(OdometryMotionModel([0.03, 0.03, 0.01], inflation=2.0), model, **kw)
        state = init_gaussian(n, poses[0], [0.3, 0.3, 0.1], key=jax.random.key(3))
        state = jax.tree.map(lambda x: x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating)
                             else x, state)
        sharded = shard_state(state)
        one = pf.run(state, controls, zs)
        two = pf.run(sharded, controls, zs)
        r = {
            "equal": compare(one, two),
            "input": layout(sharded),
            "output": layout(two[0]),
            "one_device_output": len(one[0].log_weights.sharding.device_set),
            "resampled": int(np.sum(np.asarray(one[1].resampled))),
            "min_n_active": int(np.min(np.asarray(one[1].n_active))),
            "n_eff_max": float(np.max(np.asarray(one[1].n_eff))),
            "dtype": str(one[0].log_weights.dtype),
        }
        if name == "native":
            # step: on a sharded state a compiled program; the reference is the compiled
            # one-device step (under jit the state is traced: no mesh)
            step = eqx.filter_jit(lambda p, s, c, z: p.step(s, c, z))
            s1, i1 = step(pf, state, controls[0], zs[0])
            s2, i2 = pf.step(sharded, controls[0], zs[0])
            r["step_equal"] = compare((s1, i1), (s2, i2))
            r["step_output"] = layout(s2)
            n_b = az.shape[0]
            pad = np.ones(8, bool)
            text = type(pf)._run_padded.program.lower(
                pf, sharded, controls[:8], zs[:8], pad, np.int32(8), state_mesh(sharded)
            ).as_text()
            r["native_available"] = bool(_native.available())
            r["fold_calls"] = text.count("lidarjax_fold_")
            r["fold_local_rows"] = text.count(f"tensor<{n // 2 * n_b}x")
            r["fold_global_rows"] = text.count(f"tensor<{n * n_b}x")
            r["fold_threads"] = sorted(set(re.findall(r"threads = (\d+) : i64", text)))
            r["cores"] = len(os.sched_getaffinity(0))
            # the compiled program (after XLA's partitioning): its collectives
            hlo = type(pf)._run_padded.program.lower(
                pf, sharded, controls[:8], zs[:8], pad, np.int32(8), state_mesh(sharded)
            ).lowered.compile().as_text()
            r["collectives"] = {
                op: len(re.findall(r"= [^=]*? %s(-start)?\(" % op, hlo))
                for op in ("all-gather", "all-reduce", "collective-permute", "all-to-all",
                           "reduce-scatter", "collective-broadcast")
            }
        out[name] = r


def gauss(particles, z):
    # a measurement model lidarjax does not know to be per particle
    return -0.5 * jnp.sum((particles.translation() - z) ** 2, axis=-1) / 0.05


def generic_case():
    pf = ParticleFilter(OdometryMotionModel([0.03, 0.03, 0.01], inflation=2.0), gauss)
    state = init_gaussian(32, poses[0], [0.3, 0.3, 0.1], key=jax.random.key(5))
    sharded = shard_state(state)
    one = pf.run(state, controls, poses[1:, :2])
    two = pf.run(sharded, controls, poses[1:, :2])
    step = eqx.filter_jit(lambda p, s, c, z: p.step(s, c, z))
    s1, i1 = step(pf, state, controls[0], poses[1, :2])
    s2, i2 = pf.step(sharded, controls[0], poses[1, :2])
    out["generic"] = {
        "equal": compare(one, two),
        "step_equal": compare((s1, i1), (s2, i2)),
        "output": layout(two[0]),
        "step_output": layout(s2),
        "resampled": int(np.sum(np.asarray(one[1].resampled))),
    }


case("jax64", "jax", 96, True, extensions=True)
case("native", "auto", 64, False)
generic_case()
try:
    shard_state(init_gaussian(63, poses[0], [0.1, 0.1, 0.1], key=jax.random.key(0)))
    out["indivisible"] = None
except ValueError as e:
    out["indivisible"] = str(e)
print("RESULT " + json.dumps(out))
"""


@pytest.fixture(scope="module")
def two_devices() -> dict:
    return run_on_host_devices(SCRIPT, ROOT)


def _split_over_two(lay: dict, n: int) -> None:
    assert all(d == 2 for d in lay["n_devices"])
    assert all(s == ["particles"] for s in lay["spec"])
    assert all(rows == [n // 2, n // 2] for rows in lay["shard_rows"])


@pytest.mark.parametrize(("name", "n"), [("jax64", 96), ("native", 64)])
def test_sharded_run_equals_one_device_bitwise(two_devices, name, n):
    assert two_devices["devices"] == 2
    r = two_devices[name]
    assert r["equal"], "sharded run differs from the one-device run"
    _split_over_two(r["input"], n)
    _split_over_two(r["output"], n)  # run keeps the layout
    assert r["one_device_output"] == 1  # an unsharded state stays on one device
    assert r["resampled"] > 0  # the comparison covers the resampling steps
    assert r["n_eff_max"] > 2  # ... and weights that are not all on one particle
    assert r["dtype"] == ("float64" if name == "jax64" else "float32")


def test_sharded_step_equals_one_device_bitwise(two_devices):
    r = two_devices["native"]
    assert r["step_equal"], "sharded step differs from the one-device step"
    _split_over_two(r["step_output"], 64)  # step keeps the layout


def test_one_collective_per_step(two_devices):
    """The sharded step's only collective is one all-gather (per-shard check flags
    included): several independent collectives per step can deadlock XLA's CPU runtime
    on a small thread pool (each device's part of a collective holds a pool thread)."""
    counts = two_devices["native"]["collectives"]
    assert counts["all-gather"] == 1, counts
    assert sum(counts.values()) == 1, counts


def test_sharded_generic_measurement_equals_one_device_bitwise(two_devices):
    """A measurement model not known to be per particle: the state is gathered and the
    one-device step runs on every device; same results, same layout."""
    r = two_devices["generic"]
    assert r["equal"] and r["step_equal"]
    _split_over_two(r["output"], 32)
    _split_over_two(r["step_output"], 32)
    assert r["resampled"] > 0


def test_sharded_extensions_were_active(two_devices):
    """KLD-sampling, augmented MCL and stratified resampling ran in the float64 case."""
    r = two_devices["jax64"]
    assert r["min_n_active"] < 96  # KLD-sampling changed the particle count


def test_native_fold_runs_per_shard(two_devices):
    r = two_devices["native"]
    if r["native_available"]:  # "auto" picked the native kernel: one call per shard
        assert r["fold_calls"] >= 1
        assert r["fold_local_rows"] >= 1 and r["fold_global_rows"] == 0
        # threads=None: the process's cores divided between its 2 devices
        assert r["fold_threads"] == [str(max(1, r["cores"] // 2))]
    else:  # "auto" fell back to the JAX walk: no custom call at all
        assert r["fold_calls"] == 0


def test_indivisible_particle_count_raises(two_devices):
    msg = two_devices["indivisible"]
    assert msg is not None and "n = 63" in msg and "2" in msg


def test_shard_state_on_one_device(key):
    """In this process (one CPU device) sharding is a no-op placement: same values."""
    state = init_gaussian(10, [0.0, 0.0, 0.0], [0.1, 0.1, 0.1], key=key)
    mesh = particle_mesh()
    placed = shard_state(state, mesh)
    for x, y in zip(jax.tree.leaves(state), jax.tree.leaves(placed), strict=True):
        if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
            x, y = jax.random.key_data(x), jax.random.key_data(y)
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    with pytest.raises(ValueError, match="mesh"):
        shard_state(state, mesh=object())
    batched = jax.tree.map(lambda x: jnp.stack([x, x]), state)
    with pytest.raises(ValueError, match="unbatched"):
        shard_state(batched, mesh)
