"""Particle filter step on 1 vs 2 devices: particles sharded with
:func:`lidarjax.localization.shard_state` (strong and weak scaling); ray accumulation on
1 vs 2 devices: rays split with :func:`lidarjax.raytrace.accumulate_sharded`; the memory
per device of a grid split in row tiles by :func:`lidarjax.raytrace.accumulate_tiled`.

Setup: a simulated office (:func:`lidarjax.sim.make_office`, 41 poses, 181 beams of which
every 4th is used, 10 m range), its decay-rate map (0.1 m cells), an
:class:`~lidarjax.localization.OdometryMotionModel` and a
:class:`~lidarjax.localization.ScanModel` (per-ray floor -10 nats). Particles start
Gaussian around the first pose (0.1 m / 0.05 rad).

Devices: JAX fixes its devices when it starts, so every configuration runs in a fresh
subprocess (``JAX_PLATFORMS=cpu``):

- ``1dev``: ``XLA_FLAGS=--xla_force_host_platform_device_count=1`` (the default, made
  explicit), an unsharded state;
- ``2dev``: ``--xla_force_host_platform_device_count=2`` (the machine's cores as two host
  devices), the state sharded over both, and in the same process the unsharded state on
  one of them (the same-run reference).

XLA's CPU runtime already spreads some of one device's work over the cores (its intra-op
thread pool, shared by the host devices of a process) and the native fold kernel runs on
``threads`` worker threads; so 1 device is not 1 core, and the gain of 2 devices is the
part of a step that one device leaves serial (the JAX ray walk's ``while_loop`` chunks).
With the native backend the sharded runs give each shard ``cores // devices`` threads
(``--native-threads``), so both configurations use all cores.

Measured, per backend (``native`` when built, ``jax``): seconds per filter step, from the
median of ``--repeats`` timed :meth:`ParticleFilter.run` calls over ``--steps`` steps (one
compiled ``lax.scan``; the first call, compilation included, is reported separately),
divided by the number of steps, for every particle count ``n`` in ``--counts`` (default
3 000 and 30 000), and ``n / 2`` on 1 device for weak scaling:

- strong scaling ``t_1(n) / t_2(n)`` (speed-up, 2 is perfect), against the ``1dev``
  process and against the unsharded run of the ``2dev`` process (same run);
- weak scaling ``t_1(n / 2) / t_2(n)`` (efficiency, 1 is perfect: twice the particles on
  twice the devices in the same time).

Each worker checks that its sharded final state equals the unsharded one bitwise and
records the load average before each timed block (:mod:`benchmarks._harness`).

Accumulate section (``--sections accumulate``): ``--rays`` (default 2 000 000) random 2-D
rays (origins uniform in a 51.2 m square grid of 0.05 m cells, 1024 x 1024, directions
uniform, ranges uniform in [0, 10] m, 10 % SUP with ``r_max`` 10 m) accumulated per
backend; rays per second from the median of ``--repeats`` timed calls (the first call,
compilation included, reported separately): ``accumulate`` in the ``1dev`` process, and
in the ``2dev`` process ``accumulate`` on one device (same-run reference) and
``accumulate_sharded`` over both (the native kernel gets ``cores // devices`` threads per
shard). The sharded counts are checked equal to the one-device counts. Tiled memory: in
the ``2dev`` process, ``accumulate_tiled`` of 1000 rays into a ``--tiled-side`` squared
grid (default 10 000 x 10 000 = 10^8 cells, float32: 1.2 GB in all, 0.6 GB per device;
``--quick``: 1000 x 1000) and the bytes each device holds, summed over the
``addressable_shards`` of H, M and R, next to the analytic ``12 * cells / devices``.

Run with ``python benchmarks/scaling.py [--quick] [--sections filter accumulate]
[--counts N ...] [--steps T] [--repeats R] [--rays N] [--tiled-side S]
[--backends native jax] [--out PATH]``; results go to
``benchmarks/results/scaling.json`` (``--quick``: tiny sizes, written to
``scaling_quick.json``, a smoke test only) and a Markdown table is printed.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _harness import (
    RESULTS,
    add_policy_args,
    load_snapshot,
    machine_info,
    ratio,
    write_json,
)

DEFAULT_OUT = RESULTS / "scaling.json"
QUICK_OUT = RESULTS / "scaling_quick.json"
DEVICE_FLAG = "--xla_force_host_platform_device_count"


# ----------------------------------------------------------------------------- worker


def _office_model(backend: str, threads: int | None):
    """The simulated office, its decay-rate map and the filter of this benchmark."""
    import jaxlie
    import numpy as np

    from lidarjax import maps
    from lidarjax.localization import (
        OdometryMotionModel,
        ParticleFilter,
        ScanModel,
        relative_motion,
    )
    from lidarjax.rays import from_scan
    from lidarjax.raytrace import GridSpec, accumulate
    from lidarjax.sim import make_office, simulate_scans

    world = make_office(0)
    poses = world.trajectory(41, jitter_m=0.2, seed=0)
    az = np.linspace(-np.pi / 2, np.pi / 2, 181)
    ranges = simulate_scans(world, poses, az, max_range_m=10.0, noise_sigma_m=0.01, seed=0)
    T_ws = jaxlie.SE2.from_xy_theta(poses[:, 0], poses[:, 1], poses[:, 2])
    spec = GridSpec.from_bounds(world.bounds[0] - 0.5, world.bounds[1] + 0.5, 0.1)
    dm = maps.decay_rate_map(accumulate(spec, from_scan(T_ws, az, ranges, 0.05, 10.0)))
    model = ScanModel(dm, az[::4], 0.05, 10.0, ray_floor=-10.0, backend=backend, threads=threads)
    pf = ParticleFilter(OdometryMotionModel([0.03, 0.03, 0.01], inflation=2.0), model)
    return pf, poses, np.asarray(relative_motion(poses)), ranges[1:, ::4]


def _equal(a, b) -> bool:
    import jax
    import jax.numpy as jnp
    import numpy as np

    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
            x, y = jax.random.key_data(x), jax.random.key_data(y)
        if not np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True):
            return False
    return True


def _random_rays(n: int, seed: int = 0):
    """The accumulate benchmark's grid (1024 x 1024 cells of 0.05 m) and ``n`` rays."""
    import numpy as np

    from lidarjax.rays import HIT, SUP, RayBatch
    from lidarjax.raytrace import GridSpec

    spec = GridSpec(np.zeros(2), 0.05, (1024, 1024))
    rng = np.random.default_rng(seed)
    o = rng.uniform(0.0, 51.2, (n, 2)).astype(np.float32)
    a = rng.uniform(-np.pi, np.pi, n)
    d = np.stack([np.cos(a), np.sin(a)], 1).astype(np.float32)
    r = rng.uniform(0.0, 10.0, n).astype(np.float32)
    kind = np.where(rng.uniform(size=n) < 0.1, SUP, HIT).astype(np.int32)
    r = np.where(kind == SUP, np.float32(np.inf), r)
    return spec, RayBatch(o, d, r, kind, 0.0, 10.0)


def _stats_equal(a, b) -> dict:
    import numpy as np

    ra, rb = np.asarray(a.lengths), np.asarray(b.lengths)
    return {
        "counts_equal": bool(
            np.array_equal(np.asarray(a.hits), np.asarray(b.hits))
            and np.array_equal(np.asarray(a.misses), np.asarray(b.misses))
        ),
        "lengths_max_rel_err": float(np.max(np.abs(ra - rb) / np.maximum(1.0, np.abs(ra)))),
    }


def accumulate_worker(args, k: int, policy) -> dict:
    """Accumulate throughput (rays/s) per backend and layout; tiled memory on 2 devices."""
    import jax
    import numpy as np

    from lidarjax.raytrace import (
        GridSpec,
        _native,
        accumulate,
        accumulate_sharded,
        accumulate_tiled,
    )

    cores = _native.default_threads()
    spec, rays = _random_rays(args.rays)
    out: dict = {"rays": args.rays, "grid": list(spec.shape), "resolution_m": 0.05}
    runs: dict = {}
    for backend in args.backends:
        if backend == "native" and not _native.available():
            runs[backend] = {"skipped": _native.unavailable_reason()}
            continue
        rec: dict = {}
        results = {}
        layouts = ["one"] if k == 1 else ["one", "sharded"]
        for layout in layouts:
            if layout == "one":
                threads = args.native_threads or cores
                fn = lambda t=threads: accumulate(spec, rays, backend=backend, threads=t)  # noqa: E731
            else:
                threads = args.native_threads or max(1, cores // k)
                fn = lambda t=threads: accumulate_sharded(  # noqa: E731
                    spec, rays, backend=backend, threads=t
                )
            timed, res = policy.time_calls(
                f"{k}dev accumulate {backend} {layout}",
                fn,
                args.repeats,
                warmup=1,
                return_output=True,
            )
            timed["rays_per_s"] = args.rays / timed["median_s"]
            timed["native_threads"] = threads if backend == "native" else None
            rec[layout] = timed
            results[layout] = res
        if "sharded" in rec:
            rec["sharded"].update(_stats_equal(results["one"], results["sharded"]))
        runs[backend] = rec
    out["runs"] = runs
    if k > 1:
        side = args.tiled_side - args.tiled_side % k
        big = GridSpec(np.zeros(2), 0.1, (side, side))
        few = _random_rays(1000, seed=1)[1]
        t0 = time.perf_counter()
        tiled = jax.block_until_ready(accumulate_tiled(big, few))
        per_device: dict = {}
        for x in (tiled.hits, tiled.misses, tiled.lengths):
            for sh in x.addressable_shards:
                per_device[str(sh.device)] = per_device.get(str(sh.device), 0) + sh.data.nbytes
        cells = side * side
        out["tiled"] = {
            "grid": [side, side],
            "cells": cells,
            "devices": k,
            "bytes_per_device": per_device,
            "bytes_per_device_analytic": 12 * cells // k,
            "bytes_one_device_analytic": 12 * cells,
            "bytes_per_device_for_1e8_cells_analytic": 12 * 10**8 // k,
            "shard_shape": list(tiled.hits.addressable_shards[0].data.shape),
            "seconds": time.perf_counter() - t0,
            # peak resident memory of this whole process (both devices, all sections so far)
            "process_max_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
            "note": (
                "resident H, M, R (int32, int32, float32) per device; while a chunk is "
                "walked a device also holds the walk's accumulators (a complex64 and an "
                "int32 per tile cell: 12 bytes per tile cell more) and one chunk of rays"
            ),
        }
    return out


def worker(args) -> dict:
    """One process with ``args.devices`` host devices: time every (backend, n, layout)."""
    import jax
    from _harness import native_info, policy_from_args

    from lidarjax.localization import init_gaussian, shard_state
    from lidarjax.raytrace import _native

    k = len(jax.devices())
    if k != args.devices:
        raise RuntimeError(f"expected {args.devices} devices, JAX has {k} (XLA_FLAGS?)")
    policy = policy_from_args(args)
    cores = _native.default_threads()
    out: dict = {"devices": k, "cores": cores, "xla_flags": os.environ.get("XLA_FLAGS", "")}
    runs: dict = {}
    for backend in args.backends if "filter" in args.sections else ():
        if backend == "native" and not _native.available():
            runs[backend] = {"skipped": _native.unavailable_reason()}
            continue
        rec: dict = {}
        layouts = ["one"] if k == 1 else ["one", "sharded"]
        counts = sorted(set(args.counts) | ({n // 2 for n in args.counts} if k == 1 else set()))
        for layout in layouts:
            threads = None
            if backend == "native":
                threads = args.native_threads or (cores if layout == "one" else max(1, cores // k))
            pf, poses, controls, zs = _office_model(backend, threads)
            c, z = controls[: args.steps], zs[: args.steps]
            for n in counts:
                state = init_gaussian(n, poses[0], [0.1, 0.1, 0.05], key=jax.random.key(0))
                if layout == "sharded":
                    state = shard_state(state)
                label = f"{k}dev {backend} {layout} n={n}"
                timed, res = policy.time_calls(
                    label,
                    lambda pf=pf, s=state: pf.run(s, c, z),
                    args.repeats,
                    warmup=1,
                    return_output=True,
                )
                timed["step_s"] = timed["median_s"] / len(c)
                timed["best_step_s"] = timed["best_s"] / len(c)
                timed["native_threads"] = threads
                timed["final"] = res
                rec.setdefault(layout, {})[str(n)] = timed
        if "sharded" in rec:  # the sharded filter is the one-device filter, bitwise
            for n, r in rec["sharded"].items():
                r["equals_unsharded"] = _equal(r["final"], rec["one"][n]["final"])
        for lay in rec.values():
            for r in lay.values():
                r.pop("final")
        runs[backend] = rec
    out["runs"] = runs
    out["steps"] = args.steps
    if "accumulate" in args.sections:
        out["accumulate"] = accumulate_worker(args, k, policy)
    out["native"] = native_info()
    out["load_policy"] = policy.summary()
    return out


# ----------------------------------------------------------------------------- driver


def _spawn(devices: int, argv: list[str]) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        result = Path(tmp) / "result.json"
        env = dict(os.environ)
        flags = [f for f in env.get("XLA_FLAGS", "").split() if not f.startswith(DEVICE_FLAG)]
        env["XLA_FLAGS"] = " ".join([*flags, f"{DEVICE_FLAG}={devices}"])
        env["JAX_PLATFORMS"] = "cpu"
        cmd = [sys.executable, str(Path(__file__).resolve()), *argv]
        cmd += ["--worker", "--devices", str(devices), "--result", str(result)]
        snap = load_snapshot()
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, env=env)
        rec = json.loads(result.read_text())
    rec["wall_s"] = time.perf_counter() - t0
    rec["load_before"] = snap
    return rec


def _step(rec: dict, backend: str, layout: str, n: int) -> float | None:
    try:
        return rec["runs"][backend][layout][str(n)]["step_s"]
    except KeyError:
        return None


def summarise(one: dict, two: dict, counts, backends) -> dict:
    """Strong and weak scaling from the two processes' step times."""
    out: dict = {}
    for b in backends:
        rows = {}
        for n in counts:
            t1 = _step(one, b, "one", n)
            t1_half = _step(one, b, "one", n // 2)
            t2_one = _step(two, b, "one", n)
            t2 = _step(two, b, "sharded", n)
            rows[str(n)] = {
                "step_s_1dev": t1,
                "step_s_1dev_half": t1_half,
                "step_s_2dev_unsharded": t2_one,
                "step_s_2dev_sharded": t2,
                "strong_speedup": ratio(t1, t2),
                "strong_speedup_same_run": ratio(t2_one, t2),
                "weak_efficiency": ratio(t1_half, t2),
                "equals_unsharded": (
                    two.get("runs", {})
                    .get(b, {})
                    .get("sharded", {})
                    .get(str(n), {})
                    .get("equals_unsharded")
                ),
            }
        out[b] = rows
    return out


def summarise_accumulate(one: dict, two: dict, backends) -> dict:
    """Rays per second on 1 and 2 devices and the tiled grid's memory per device."""
    a1, a2 = one.get("accumulate", {}), two.get("accumulate", {})
    out: dict = {}
    for b in backends:
        r1 = a1.get("runs", {}).get(b, {})
        r2 = a2.get("runs", {}).get(b, {})
        get = lambda r, lay: r.get(lay, {}).get("rays_per_s")  # noqa: E731
        t1, t2_one, t2 = get(r1, "one"), get(r2, "one"), get(r2, "sharded")
        out[b] = {
            "rays_per_s_1dev": t1,
            "rays_per_s_2dev_unsharded": t2_one,
            "rays_per_s_2dev_sharded": t2,
            "speedup": ratio(t2, t1),
            "speedup_same_run": ratio(t2, t2_one),
            "counts_equal": r2.get("sharded", {}).get("counts_equal"),
        }
    out["tiled"] = a2.get("tiled")
    return out


def markdown_accumulate(summary: dict) -> str:
    lines = [
        "| backend | 1 dev (Mrays/s) | 2 dev sharded | speed-up (same run) | counts equal |",
        "|---|---|---|---|---|",
    ]
    for b, r in summary.items():
        if b == "tiled":
            continue
        m1 = r["rays_per_s_1dev"] and r["rays_per_s_1dev"] / 1e6
        m2 = r["rays_per_s_2dev_sharded"] and r["rays_per_s_2dev_sharded"] / 1e6
        lines.append(
            f"| {b} | {_f(m1, '.2f')} | {_f(m2, '.2f')} | {_f(r['speedup'], '.2f')} "
            f"({_f(r['speedup_same_run'], '.2f')}) | {r['counts_equal']} |"
        )
    t = summary.get("tiled")
    if t:
        per = ", ".join(f"{v / 2**20:.1f}" for v in t["bytes_per_device"].values())
        lines.append(
            f"\nTiled {t['grid'][0]} x {t['grid'][1]} grid on {t['devices']} devices: "
            f"{per} MiB per device (H, M, R; analytic {t['bytes_per_device_analytic'] / 2**20:.1f} "
            f"MiB; a 10^8-cell grid: {t['bytes_per_device_for_1e8_cells_analytic'] / 2**20:.1f} "
            "MiB per device)"
        )
    return "\n".join(lines)


def _f(x, fmt) -> str:
    return "–" if x is None else format(x, fmt)


def markdown(summary: dict) -> str:
    lines = [
        "| backend | n | 1 dev (ms/step) | 2 dev sharded | strong speed-up "
        "(same run) | weak efficiency | bitwise |",
        "|---|---|---|---|---|---|---|",
    ]
    for b, rows in summary.items():
        for n, r in rows.items():
            lines.append(
                f"| {b} | {n} | {_f(r['step_s_1dev'] and r['step_s_1dev'] * 1e3, '.2f')} | "
                f"{_f(r['step_s_2dev_sharded'] and r['step_s_2dev_sharded'] * 1e3, '.2f')} | "
                f"{_f(r['strong_speedup'], '.2f')} ({_f(r['strong_speedup_same_run'], '.2f')}) "
                f"| {_f(r['weak_efficiency'], '.2f')} | {r['equals_unsharded']} |"
            )
    return "\n".join(lines)


def main(argv=None) -> dict | None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="tiny sizes: a smoke test only")
    ap.add_argument("--counts", type=int, nargs="+", default=None, help="particle counts")
    ap.add_argument("--steps", type=int, default=None, help="filter steps per timed run")
    ap.add_argument("--repeats", type=int, default=None, help="timed runs per configuration")
    ap.add_argument("--backends", nargs="+", default=["native", "jax"], choices=["native", "jax"])
    ap.add_argument(
        "--native-threads",
        type=int,
        default=None,
        help="native threads per shard (default: all cores, divided by the devices)",
    )
    ap.add_argument(
        "--sections",
        nargs="+",
        default=["filter", "accumulate"],
        choices=["filter", "accumulate"],
        help="what to measure",
    )
    ap.add_argument("--rays", type=int, default=None, help="rays of the accumulate section")
    ap.add_argument("--tiled-side", type=int, default=None, help="cells per side of the tiled grid")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--devices", type=int, default=1, help=argparse.SUPPRESS)
    ap.add_argument("--result", type=Path, default=None, help=argparse.SUPPRESS)
    add_policy_args(ap)
    args = ap.parse_args(argv)
    if args.counts is None:
        args.counts = [32, 64] if args.quick else [3000, 30000]
    if args.steps is None:
        args.steps = 4 if args.quick else 16
    if args.repeats is None:
        args.repeats = 1 if args.quick else 5
    if args.rays is None:
        args.rays = 20_000 if args.quick else 2_000_000
    if args.tiled_side is None:
        args.tiled_side = 1000 if args.quick else 10_000
    if any(n % 4 for n in args.counts):  # n and n / 2 must split over 2 devices
        ap.error(f"--counts must be multiples of 4, got {args.counts}")

    if args.worker:
        write_json(args.result, worker(args))
        return None

    passthrough = [
        "--counts",
        *map(str, args.counts),
        "--steps",
        str(args.steps),
        "--repeats",
        str(args.repeats),
        "--backends",
        *args.backends,
        "--sections",
        *args.sections,
        "--rays",
        str(args.rays),
        "--tiled-side",
        str(args.tiled_side),
        "--max-wait",
        str(args.max_wait),
        "--wait-budget",
        str(args.wait_budget),
        "--load-threshold",
        str(args.load_threshold),
    ]
    if args.native_threads is not None:
        passthrough += ["--native-threads", str(args.native_threads)]
    print("1 device ...", flush=True)
    one = _spawn(1, passthrough)
    print("2 devices ...", flush=True)
    two = _spawn(2, passthrough)
    summary = summarise(one, two, args.counts, args.backends)
    summary_acc = summarise_accumulate(one, two, args.backends)
    report = {
        "benchmark": "scaling",
        "quick": args.quick,
        "counts": args.counts,
        "steps": args.steps,
        "repeats": args.repeats,
        "summary": summary,
        "rays": args.rays,
        "sections": args.sections,
        "summary_accumulate": summary_acc,
        "processes": {"1dev": one, "2dev": two},
        "note": (
            "strong_speedup = step time on 1 device (separate process, device count 1) / "
            "sharded on 2 host devices; strong_speedup_same_run uses the unsharded run of the "
            "2-device process; weak_efficiency = 1 device at n/2 over 2 devices at n. XLA's "
            "CPU intra-op thread pool serves all host devices of a process, and the native "
            "kernel is multi-threaded, so 1 device already uses several cores for parts of "
            "a step."
        ),
        "machine": machine_info(),
        "load_average_end": list(os.getloadavg()),
    }
    out = args.out or (QUICK_OUT if args.quick else DEFAULT_OUT)
    write_json(out, report)
    if "filter" in args.sections:
        print(markdown(summary))
    if "accumulate" in args.sections:
        print(markdown_accumulate(summary_acc))
    print(f"wrote {out}")
    return report


if __name__ == "__main__":
    main()
