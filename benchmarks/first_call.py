"""First calls in a fresh process, with and without JAX's persistent compilation cache.

Every new Python process traces, lowers and compiles each jitted program on its first
call (issue #25: 3-11 s per pipeline on 2 cores). :func:`lidarjax.enable_compilation_cache`
keeps the compiled programs in a folder; a second process still traces and lowers, but
loads the executables instead of compiling them. Measured here:

1. Process pairs. For each ``--min-compile-time`` threshold (s; programs that compiled
   faster are not written), a fresh process with an EMPTY temporary cache folder, then a
   second fresh process with the same folder, each timing the first call (compilation
   included) and a second call (warm) of:

   - ``decay_rate_map``: :func:`~lidarjax.raytrace.accumulate` of 40 simulated office
     scans (181 beams), :func:`~lidarjax.maps.decay_rate_map` (Eq. 7.10) and
     :func:`~lidarjax.sensor_models.log_likelihood_at_poses` of one scan at 64 poses;
   - ``particle_filter_run``: one :meth:`~lidarjax.localization.ParticleFilter.run` of 40
     steps with 200 particles (odometry motion model, ``ScanModel`` on that map);
   - ``dct_fit``: :func:`~lidarjax.maps.fit_dct` of 8 x 8 coefficients to 2 000 rays
     (at most 30 solver steps);
   - ``extract_polylines``: PLE on one simulated 180-ray polygon scan (12 vertices);
   - ``extract_planes``: PPE on a 32 x 32 generated SynPEB-style scan;
   - ``extract_poles``: the pole extractor on a 20 m x 20 m x 4 m local map of three
     cylinders seen by a 16-ring scanner from two poses.

   Per call: wall seconds, and from ``jax.monitoring`` the XLA compilations (with their
   seconds), the persistent-cache hits and misses (writes) and the tracing seconds, plus
   JAX's reason for every program it did not write: programs with host callbacks (each
   ``eqx.error_if`` is one) are never cached, so they compile in every process.
2. Shape buckets. One process without the cache runs ``ParticleFilter.run`` with 100 and
   then 120 steps (one compilation: both pad to 128) and the unpadded reference scan
   (``ParticleFilter._run``) with the same two lengths (two compilations): times and the
   compilation counts of each.

The load average is recorded before every process and every call (a first call cannot be
repeated in the same process, so there is no rerun policy; rerun the script when the
machine was busy). Run with ``python benchmarks/first_call.py [--quick] [--out PATH]
[--min-compile-time S ...] [--items NAME ...]``; results go to
``benchmarks/results/first_call.json`` and a Markdown table is printed. ``--items dct_fit``
(for example) times one workload alone (the others are skipped, so nothing they compile or
load is shared with it).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _harness import RESULTS, load_snapshot, machine_info, write_json

DEFAULT_OUT = RESULTS / "first_call.json"
ITEMS = (
    "decay_rate_map",
    "particle_filter_run",
    "dct_fit",
    "extract_polylines",
    "extract_planes",
    "extract_poles",
)
GOAL_SECOND_PROCESS_S = 1.0


# ----------------------------------------------------------------------------- JAX events


class Events:
    """Counts of JAX's compilation and cache events between :meth:`reset` calls."""

    COMPILE = "/jax/core/compile/backend_compile_duration"
    TRACE = "/jax/core/compile/jaxpr_trace_duration"
    LOWER = "/jax/core/compile/jaxpr_to_mlir_module_duration"

    def __init__(self):
        import jax

        self.reset()
        jax.monitoring.register_event_duration_secs_listener(self._duration)
        jax.monitoring.register_event_listener(self._event)
        # why a program was not written (host callbacks, e.g. eqx.error_if): JAX's compiler
        # logs it at DEBUG level
        events = self

        class Skipped(logging.Handler):
            def emit(self, record):
                msg = record.getMessage()
                if msg.startswith("Not writing persistent cache entry"):
                    events.not_written.append(msg[:160])

        log = logging.getLogger("jax._src.compiler")
        log.setLevel(logging.DEBUG)
        log.addHandler(Skipped(logging.DEBUG))

    def reset(self) -> None:
        self.compiles = 0
        self.compile_s = 0.0
        self.trace_s = 0.0
        self.lower_s = 0.0
        self.hits = 0
        self.misses = 0
        self.compiled: dict[str, int] = {}
        self.not_written: list[str] = []

    def _duration(self, event, duration, **kw):
        if event == self.COMPILE:
            self.compiles += 1
            self.compile_s += duration
            name = str(kw.get("fun_name", "?"))
            self.compiled[name] = self.compiled.get(name, 0) + 1
        elif event == self.TRACE:
            self.trace_s += duration
        elif event == self.LOWER:
            self.lower_s += duration

    def _event(self, event, **kw):
        if event == "/jax/compilation_cache/cache_hits":
            self.hits += 1
        elif event == "/jax/compilation_cache/cache_misses":
            self.misses += 1

    def record(self) -> dict:
        return {
            "backend_compiles": self.compiles,
            "backend_compile_s": self.compile_s,
            "trace_s": self.trace_s,
            "lower_s": self.lower_s,
            "cache_hits": self.hits,
            "cache_writes": self.misses,
            "compiled": dict(sorted(self.compiled.items(), key=lambda kv: -kv[1])[:12]),
            "not_written": list(self.not_written),
        }


def _timed(events: Events, fn) -> dict:
    """First call of ``fn`` (events counted), then a second, warm call."""
    import jax

    load = os.getloadavg()[0]
    events.reset()
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    rec = {"first_call_s": first, "load_1min": load, **events.record()}
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    rec["second_call_s"] = time.perf_counter() - t0
    return rec


# ----------------------------------------------------------------------------- workloads


def _office():
    """A simulated office: poses, azimuths, ranges, rays and a grid over it."""
    import jaxlie
    import numpy as np

    from lidarjax.rays import from_scan
    from lidarjax.raytrace import GridSpec
    from lidarjax.sim import make_office, simulate_scans

    world = make_office(0)
    poses = world.trajectory(41, jitter_m=0.2, seed=0)
    az = np.linspace(-np.pi / 2, np.pi / 2, 181)
    ranges = simulate_scans(world, poses, az, max_range_m=10.0, noise_sigma_m=0.01, seed=0)
    T = jaxlie.SE2.from_xy_theta(poses[:, 0], poses[:, 1], poses[:, 2])
    rays = from_scan(T, az, ranges, 0.05, 10.0)
    spec = GridSpec.from_bounds(world.bounds[0] - 0.5, world.bounds[1] + 0.5, 0.1)
    return poses, az, ranges, rays, spec


def _cylinder_rays(n_az: int = 360):
    """3-D rays of a 16-ring scanner at two poses among three vertical cylinders."""
    import jax.numpy as jnp
    import numpy as np

    from lidarjax.rays import HIT, SUP, RayBatch

    poles = np.array([[5.0, 3.0, 0.15], [-4.0, 6.0, 0.25], [2.5, -7.0, 0.1]])
    height, r_max = 4.0, 30.0
    el = np.radians(np.linspace(-15.0, 15.0, 16))
    azs = np.linspace(-np.pi, np.pi, n_az, endpoint=False)
    E, A = np.meshgrid(el, azs, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    origins, ranges = [], []
    for o in ((0.0, 0.0, 1.7), (1.0, 0.5, 1.7)):
        o = np.asarray(o)
        r = np.full(len(d), np.inf)
        down = d[:, 2] < 0
        r[down] = -o[2] / d[down, 2]  # the ground z = 0
        for px, py, rad in poles:
            ox, oy = o[0] - px, o[1] - py
            a = d[:, 0] ** 2 + d[:, 1] ** 2
            b = 2 * (ox * d[:, 0] + oy * d[:, 1])
            c = ox**2 + oy**2 - rad**2
            disc = b * b - 4 * a * c
            ok = (disc >= 0) & (a > 0)
            t = np.where(
                ok, (-b - np.sqrt(np.where(ok, disc, 0.0))) / (2 * np.where(ok, a, 1)), np.inf
            )
            z = o[2] + t * d[:, 2]
            r = np.where((t > 0) & (z >= 0) & (z <= height) & (t < r), t, r)
        origins.append(np.tile(o, (len(d), 1)))
        ranges.append(r)
    r = np.concatenate(ranges)
    kind = np.where(r < r_max, HIT, SUP).astype(np.int32)
    r = np.where(r < r_max, r, r_max)
    return RayBatch(
        jnp.asarray(np.concatenate(origins)),
        jnp.asarray(np.concatenate([d, d])),
        jnp.asarray(r),
        jnp.asarray(kind),
        jnp.asarray(0.5),
        jnp.asarray(r_max),
    )


def worker(args) -> dict:
    """One fresh process: the cache (if any), then the first call of every item."""
    t_process = time.perf_counter()
    import jax

    if args.x64:
        jax.config.update("jax_enable_x64", True)
    import lidarjax

    t_import = time.perf_counter() - t_process
    folder = None
    if args.cache is not None:
        folder = lidarjax.enable_compilation_cache(
            args.cache, min_compile_time_s=args.min_compile_time
        )
    events = Events()

    import jax.numpy as jnp
    import jaxlie
    import numpy as np

    from lidarjax import features, maps
    from lidarjax.localization import (
        OdometryMotionModel,
        ParticleFilter,
        ScanModel,
        init_gaussian,
        relative_motion,
    )
    from lidarjax.rays import HIT, RayBatch, from_scan
    from lidarjax.raytrace import accumulate
    from lidarjax.sensor_models import log_likelihood_at_poses
    from lidarjax.sim import random_polygon, simulate_polygon_scan, synpeb_scan

    out: dict = {"import_s": t_import, "cache_folder": None if folder is None else str(folder)}
    items: dict = {}
    t_setup = time.perf_counter()
    poses, az, ranges, rays, spec = _office()
    out["setup_s"] = time.perf_counter() - t_setup

    at = poses[20] + np.random.default_rng(0).normal(0.0, [0.1, 0.1, 0.03], (64, 3))

    def decay():
        dm = maps.decay_rate_map(accumulate(spec, rays))
        return log_likelihood_at_poses(dm, az, ranges[20], at, r_min=0.05, r_max=10.0)

    selected = set(args.items)
    if "decay_rate_map" in selected:
        items["decay_rate_map"] = _timed(events, decay)

    if "particle_filter_run" in selected:
        dm = maps.decay_rate_map(accumulate(spec, rays))
        pf = ParticleFilter(
            OdometryMotionModel([0.03, 0.03, 0.01], inflation=2.0),
            ScanModel(dm, az[::4], 0.05, 10.0, ray_floor=-10.0),
        )
        controls = np.asarray(relative_motion(poses))
        zs = ranges[1:, ::4]
        state = init_gaussian(200, poses[0], [0.1, 0.1, 0.05], key=jax.random.key(0))
        items["particle_filter_run"] = _timed(events, lambda: pf.run(state, controls, zs))

    flat = rays.flatten()
    ends = np.asarray(flat.endpoints())
    box = np.all((ends > [2.0, 2.0]) & (ends < [8.0, 8.0]), -1)
    idx = np.flatnonzero((np.asarray(flat.kind) == HIT) & box)[:2000]
    sub = RayBatch(
        flat.origins[idx],
        flat.directions[idx],
        flat.ranges[idx],
        flat.kind[idx],
        flat.r_min,
        flat.r_max,
    )
    # the ray selection above is NumPy work on device arrays: finished before the timer
    jax.block_until_ready(sub)
    if "dct_fit" in selected:
        items["dct_fit"] = _timed(
            events,
            lambda: maps.fit_dct(sub, (8, 8), lower=[2.0, 2.0], extent=[6.0, 6.0], max_steps=30)[0],
        )

    polygon = random_polygon(7, seed=2, radius_range_m=(2.0, 6.0))
    a_poly, r_poly = simulate_polygon_scan(polygon, n_rays=180, seed=2)
    prays = from_scan(jaxlie.SE2.identity(), a_poly, r_poly, 0.0, np.inf)
    if "extract_polylines" in selected:
        items["extract_polylines"] = _timed(
            events, lambda: features.extract_polylines(prays, max_vertices=12).stats
        )

    pts = synpeb_scan("train", 0, shape=(32, 32)).points
    if "extract_planes" in selected:
        items["extract_planes"] = _timed(
            events, lambda: jnp.asarray(features.extract_planes(pts).labels)
        )

    crays = _cylinder_rays()
    pcfg = features.PoleConfig(extent_m=(20.0, 20.0, 4.0), max_poles=16)
    pspec = features.local_map_spec([0.5, 0.0], pcfg)
    if "extract_poles" in selected:
        items["extract_poles"] = _timed(
            events, lambda: jnp.asarray(features.extract_poles(crays, pspec, pcfg).xy)
        )

    out["items"] = items
    out["first_calls_total_s"] = sum(v["first_call_s"] for v in items.values())
    out["process_s"] = time.perf_counter() - t_process
    out["cache_entries"] = len(os.listdir(folder)) if folder is not None else None
    return out


def bucket_worker(args) -> dict:
    """One process without the cache: ``run`` with 100 then 120 steps, padded and not."""
    import jax

    if args.x64:
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    from lidarjax import maps
    from lidarjax.localization import (
        OdometryMotionModel,
        ParticleFilter,
        ScanModel,
        init_gaussian,
        relative_motion,
    )
    from lidarjax.raytrace import accumulate

    events = Events()
    poses, az, ranges, rays, spec = _office()
    dm = maps.decay_rate_map(accumulate(spec, rays))
    pf = ParticleFilter(
        OdometryMotionModel([0.03, 0.03, 0.01], inflation=2.0),
        ScanModel(dm, az[::4], 0.05, 10.0, ray_floor=-10.0),
    )
    # 121 poses: the 41 office poses forth and back and forth again
    loop = np.concatenate([poses, poses[-2::-1], poses[1:]])
    scans = np.concatenate([ranges, ranges[-2::-1], ranges[1:]])
    controls = np.asarray(relative_motion(loop))
    zs = scans[1:, ::4]
    state = init_gaussian(200, loop[0], [0.1, 0.1, 0.05], key=jax.random.key(0))
    out: dict = {}
    for label, run in (
        ("bucketed", lambda c, z: pf.run(state, c, z)),
        ("unpadded", lambda c, z: pf._run(state, jnp.asarray(c), jnp.asarray(z))),
    ):
        rec = {}
        for T in (100, 120):
            rec[f"T{T}"] = _timed(events, lambda T=T, run=run: run(controls[:T], zs[:T]))
            name = "jit(_run_padded)" if label == "bucketed" else "jit(_run)"
            rec[f"T{T}"]["run_compiles"] = rec[f"T{T}"]["compiled"].get(name, 0)
        rec["run_compiles_total"] = rec["T100"]["run_compiles"] + rec["T120"]["run_compiles"]
        out[label] = rec
    return out


# ----------------------------------------------------------------------------- driver


def _spawn(argv: list[str], env_extra: dict) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        result = Path(tmp) / "result.json"
        env = {**os.environ, **env_extra}
        cmd = [sys.executable, str(Path(__file__).resolve()), *argv, "--result", str(result)]
        snap = load_snapshot()
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, env=env)
        wall = time.perf_counter() - t0
        rec = json.loads(result.read_text())
    rec["wall_s"] = wall
    rec["load_before"] = snap
    return rec


def _f(x, fmt=".2f") -> str:
    return "–" if x is None else format(x, fmt)


def markdown(rep: dict) -> str:
    lines = []
    for pair in rep["pairs"]:
        t = pair["min_compile_time_s"]
        lines += [
            f"\nCompilation cache, min compile time {t} s (first call, s; compilations / "
            "cache hits in parentheses):\n",
            "| call | no cache (1st process) | cached (2nd process) | warm call |",
            "|---|---|---|---|",
        ]
        a, b = pair["first_process"]["items"], pair["second_process"]["items"]
        for k in (k for k in ITEMS if k in a):
            x, y = a[k], b[k]
            lines.append(
                f"| {k} | {_f(x['first_call_s'])} ({x['backend_compiles']}) | "
                f"{_f(y['first_call_s'])} ({y['backend_compiles']} / {y['cache_hits']}) | "
                f"{_f(y['second_call_s'], '.3f')} |"
            )
        lines.append(
            f"| all first calls | {_f(pair['first_process']['first_calls_total_s'])} | "
            f"{_f(pair['second_process']['first_calls_total_s'])} | |"
        )
        for k in (k for k in ITEMS if k in a):  # never cached, whatever the threshold
            names = sorted({m.split("'")[1] for m in a[k]["not_written"] if "callback" in m})
            if names:
                lines.append(f"\n- {k}: not cacheable (host callbacks): {', '.join(names)}")
    bk = rep.get("buckets")
    if bk:
        lines += [
            "\n`ParticleFilter.run`, 100 then 120 steps in one process (no cache):\n",
            "| path | 100 steps (s) | 120 steps (s) | compilations of the scan |",
            "|---|---|---|---|",
        ]
        for label in ("bucketed", "unpadded"):
            r = bk[label]
            lines.append(
                f"| {label} | {_f(r['T100']['first_call_s'])} | {_f(r['T120']['first_call_s'])}"
                f" | {r['run_compiles_total']} |"
            )
    return "\n".join(lines) + "\n"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="threshold 0 only, no bucket run")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument(
        "--min-compile-time",
        type=float,
        nargs="+",
        default=[0.0, 1.0],
        help="cache thresholds to compare (s); 1.0 is JAX's default",
    )
    ap.add_argument("--no-x64", dest="x64", action="store_false", help="float32 (JAX default)")
    ap.add_argument(
        "--items",
        nargs="+",
        choices=ITEMS,
        default=list(ITEMS),
        help="workloads to time (default: all; others are skipped, e.g. to time one alone)",
    )
    ap.add_argument("--worker", choices=("calls", "buckets"), help=argparse.SUPPRESS)
    ap.add_argument("--cache", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--result", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        if args.min_compile_time and len(args.min_compile_time) == 1:
            args.min_compile_time = args.min_compile_time[0]
        rec = worker(args) if args.worker == "calls" else bucket_worker(args)
        args.result.write_text(json.dumps(rec))
        return rec

    t_start = time.perf_counter()
    thresholds = [0.0] if args.quick else list(args.min_compile_time)
    common = ([] if args.x64 else ["--no-x64"]) + ["--items", *args.items]
    pairs = []
    for t in thresholds:
        with tempfile.TemporaryDirectory(prefix="lidarjax-first-call-") as cache:
            argv_w = ["--worker", "calls", "--cache", cache, "--min-compile-time", str(t), *common]
            print(f"threshold {t} s: first process (empty cache) ...", flush=True)
            first = _spawn(argv_w, {})
            print(f"threshold {t} s: second process (same cache) ...", flush=True)
            second = _spawn(argv_w, {})
        pairs.append(
            {
                "min_compile_time_s": t,
                "first_process": first,
                "second_process": second,
                "second_process_max_first_call_s": max(
                    v["first_call_s"] for v in second["items"].values()
                ),
            }
        )
    buckets = None
    if not args.quick:
        print("shape buckets: 100 then 120 steps ...", flush=True)
        buckets = _spawn(["--worker", "buckets", *common], {"LIDARJAX_JAX_CACHE": "off"})
    rep = {
        "machine": machine_info(),
        "x64": args.x64,
        "goal_second_process_first_call_s": GOAL_SECOND_PROCESS_S,
        "pairs": pairs,
        "buckets": buckets,
        "load_end": load_snapshot(),
        "total_s": time.perf_counter() - t_start,
        "note": (
            "first_call_s includes tracing, lowering and compilation (or loading from the "
            "cache); second_call_s is the warm call. load_1min is recorded before every call "
            "and process; first calls cannot be rerun in the same process."
        ),
    }
    write_json(args.out, rep)
    print(markdown(rep))
    print(f"wrote {args.out}")
    return rep


if __name__ == "__main__":
    main()
