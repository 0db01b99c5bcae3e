"""Two JAX processes on 127.0.0.1 (``lidarjax.distributed.initialize_cpu``: the CPU backend
with gloo collectives), one CPU device each: ``jax.devices()`` holds both, a ``psum``
crosses the processes, and a particle filter sharded over the two processes' devices
(``shard_state(state, particle_mesh())``) gives bitwise the one-device results, which
each process computes on its own device and compares with the rows it holds.

Both processes are killed if either fails or the pair runs past its deadline."""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# two processes on 2 cores: ~45 s (both compile the filter twice), so slow
pytestmark = pytest.mark.slow

DEADLINE_S = 300

WORKER = r"""
import json, sys
import lidarjax.distributed as dist

process_id, port = int(sys.argv[1]), int(sys.argv[2])
dist.initialize_cpu(f"127.0.0.1:{port}", 2, process_id, timeout_s=120)

import jax, jax.numpy as jnp, jaxlie, numpy as np
from jax.sharding import NamedSharding, PartitionSpec as P
from lidarjax import maps
from lidarjax.localization import (
    OdometryMotionModel, ParticleFilter, ScanModel, init_gaussian, particle_mesh,
    relative_motion, shard_state,
)
from lidarjax.rays import from_scan
from lidarjax.raytrace import GridSpec, _native, accumulate
from lidarjax.sim import make_office, simulate_scans

out = {
    "process": jax.process_index(),
    "processes": jax.process_count(),
    "devices": [d.id for d in jax.devices()],
    "local_devices": [d.id for d in jax.local_devices()],
}
mesh = particle_mesh()  # all global devices: one per process

# (b) a psum over the processes: 0 + 1 + ... + 7 from 4 rows per process
x = jax.device_put(np.arange(8.0, dtype=np.float32), NamedSharding(mesh, P("particles")))
psum = jax.shard_map(
    lambda v: jax.lax.psum(jnp.sum(v), "particles"), mesh=mesh, in_specs=P("particles"),
    out_specs=P(),
)
out["psum_local_rows"] = [np.asarray(s.data).tolist() for s in x.addressable_shards]
out["psum"] = float(jax.jit(psum)(x).addressable_data(0))

# (a) the sharded filter against the one-device filter (every process builds the same
# map and the same initial state from the same seeds)
world = make_office(0)
poses = world.trajectory(9, jitter_m=0.2, seed=0)  # 8 steps
az = np.linspace(-np.pi / 2, np.pi / 2, 31)
ranges = simulate_scans(world, poses, az, max_range_m=10.0, noise_sigma_m=0.01, seed=0)
T_ws = jaxlie.SE2.from_xy_theta(poses[:, 0], poses[:, 1], poses[:, 2])
spec = GridSpec.from_bounds(world.bounds[0] - 0.5, world.bounds[1] + 0.5, 0.2)
dm = maps.decay_rate_map(accumulate(spec, from_scan(T_ws, az, ranges, 0.05, 10.0)))
pf = ParticleFilter(
    OdometryMotionModel([0.03, 0.03, 0.01], inflation=2.0),
    ScanModel(dm, az, 0.05, 10.0, ray_floor=-10.0, beam_exponent=0.05),
)
controls, zs = np.asarray(relative_motion(poses)), ranges[1:]
state = init_gaussian(64, poses[0], [0.3, 0.3, 0.1], key=jax.random.key(3))
sharded = shard_state(state, mesh)
two = pf.run(sharded, controls, zs)
one = pf.run(state, controls, zs)  # this process's device alone


def bits(x):
    return jax.random.key_data(x) if jnp.issubdtype(x.dtype, jax.dtypes.prng_key) else x


checked, equal = 0, True
for a, b in zip(jax.tree.leaves(two), jax.tree.leaves(one), strict=True):
    a, b = bits(a), np.asarray(bits(b))
    for shard in a.addressable_shards:  # this process's rows (or its replica)
        d = np.asarray(shard.data)
        equal &= d.dtype == b.dtype and np.array_equal(d, b[shard.index], equal_nan=True)
        checked += 1
lw = two[0].log_weights
out.update(
    equal=bool(equal),
    checked=checked,
    n_leaves=len(jax.tree.leaves(two)),
    input_devices=len(sharded.log_weights.sharding.device_set),
    output_devices=len(lw.sharding.device_set),
    output_spec=list(lw.sharding.spec),
    output_local_rows=[int(s.data.shape[0]) for s in lw.addressable_shards],
    one_device_output=len(one[0].log_weights.sharding.device_set),
    resampled=int(np.sum(np.asarray(one[1].resampled))),
    n_eff_max=float(np.max(np.asarray(one[1].n_eff))),
    native=bool(_native.available()),
)
print("RESULT " + json.dumps(out), flush=True)
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env() -> dict:
    env = dict(os.environ)
    # one CPU device per process: drop any forced host device count
    flags = re.sub(r"--xla_force_host_platform_device_count=\S*", "", env.get("XLA_FLAGS", ""))
    env["XLA_FLAGS"] = flags.strip()
    env.pop("LIDARJAX_HOST_DEVICES", None)
    env["JAX_PLATFORMS"] = "cpu"
    return env


@pytest.fixture(scope="module")
def two_processes() -> list[dict]:
    """Run the worker as processes 0 and 1; their RESULT dicts, by process id."""
    port = _free_port()
    with tempfile.TemporaryDirectory() as tmp:
        logs = [Path(tmp) / f"process{i}.log" for i in range(2)]
        procs = []
        try:
            for i, log in enumerate(logs):
                with open(log, "w") as fh:
                    procs.append(
                        subprocess.Popen(
                            [sys.executable, "-c", WORKER, str(i), str(port)],
                            cwd=ROOT,
                            env=_env(),
                            stdout=fh,
                            stderr=subprocess.STDOUT,
                        )
                    )
            deadline = time.monotonic() + DEADLINE_S
            while any(p.poll() is None for p in procs):
                if any(p.poll() not in (None, 0) for p in procs):
                    break  # one failed: the other may wait for it forever
                if time.monotonic() > deadline:
                    break
                time.sleep(0.5)
        finally:
            for p in procs:
                if p.poll() is None:
                    p.kill()
                p.wait(timeout=30)
        texts = [log.read_text(errors="replace") for log in logs]
    codes = [p.returncode for p in procs]
    assert codes == [0, 0], f"exit codes {codes}\n" + "\n".join(
        f"--- process {i}\n{t[-3000:]}" for i, t in enumerate(texts)
    )
    results = []
    for t in texts:
        line = [ln for ln in t.splitlines() if ln.startswith("RESULT ")][-1]
        results.append(json.loads(line[len("RESULT ") :]))
    return results


def test_two_processes_share_their_devices(two_processes):
    p0, p1 = two_processes
    assert [p0["process"], p1["process"]] == [0, 1]
    assert p0["processes"] == p1["processes"] == 2
    assert len(p0["devices"]) == 2 and p0["devices"] == p1["devices"]  # the global devices
    assert len(p0["local_devices"]) == len(p1["local_devices"]) == 1
    assert p0["local_devices"] != p1["local_devices"]
    assert sorted(p0["local_devices"] + p1["local_devices"]) == sorted(p0["devices"])


def test_psum_across_processes(two_processes):
    p0, p1 = two_processes
    assert p0["psum_local_rows"] == [[0.0, 1.0, 2.0, 3.0]]  # each process holds its half
    assert p1["psum_local_rows"] == [[4.0, 5.0, 6.0, 7.0]]
    assert p0["psum"] == p1["psum"] == 28.0  # ... and the sum covers both halves


def test_sharded_filter_over_processes_equals_one_device_bitwise(two_processes):
    for r in two_processes:
        assert r["equal"], f"process {r['process']}: sharded run differs from one device"
        assert r["checked"] == r["n_leaves"] >= 10  # every leaf, one local shard each
        assert r["input_devices"] == r["output_devices"] == 2  # spans both processes
        assert r["output_spec"] == ["particles"]
        assert r["output_local_rows"] == [32]  # 64 particles, 32 per process
        assert r["one_device_output"] == 1
        assert r["resampled"] > 0  # the comparison covers resampling steps
        assert r["n_eff_max"] > 2
