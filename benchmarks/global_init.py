"""Seconds for measurement-driven global initialisation (``localization.pose_lattice`` +
``init_from_scan``) against one scan-model evaluation of the same number of particles
timed in the same run.

Setup: per log, the map and protocol of ``configs/mcl_remedies.yaml`` (0.1 m cells, 30
beams, the start scan), the lattice of ``experiments/mcl_remedies.py``'s
``LATTICE_DEFAULTS`` (0.5 m blocks, 72 headings, at most 4 M hypotheses), the decay-rate
map smoothed by 0.6 x the block side, 20 000 particles. ``init_from_scan`` is compiled by
a first call (not timed) and timed ``--repeats`` times; the reference is
``ScanModel(particles, z)`` on 20 000 uniform particles (one measurement update of the
filter's width). The 1-minute load average is recorded before every timed block and the
block is rerun after waiting when it was above 0.5 (:mod:`benchmarks._harness`).

Run with ``python benchmarks/global_init.py [--logs a,b] [--repeats N] [--out PATH]``;
results go to ``benchmarks/results/global_init.json``.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import jax
import numpy as np
from _harness import (
    RESULTS,
    add_policy_args,
    experiments_on_path,
    machine_info,
    policy_from_args,
    remedies_config,
    write_json,
)

experiments_on_path()  # times the experiment's own lattice, map cache and protocol
from _common import mapping_stats  # noqa: E402
from mcl import prepare  # noqa: E402
from mcl_remedies import LATTICE_DEFAULTS, MapCache, _free_mask  # noqa: E402

from lidarjax import localization as loc  # noqa: E402

DEFAULT_OUT = RESULTS / "global_init.json"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", default="intel,csail")
    ap.add_argument("--particles", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    add_policy_args(ap)
    args = ap.parse_args(argv)
    policy = policy_from_args(args)
    cfg = remedies_config()
    load_start = os.getloadavg()
    n = int(args.particles)
    results = {}
    for name in [x for x in args.logs.split(",") if x]:
        log, r_min, r_max, az, seq, key = prepare(name, cfg)
        stats, spec, p_out = mapping_stats(log, cfg, r_min, r_max)
        cache = MapCache(stats, cfg, p_out)
        free = np.asarray(_free_mask(stats))
        t0 = time.perf_counter()
        lat = loc.pose_lattice(
            spec,
            free,
            position_step_m=LATTICE_DEFAULTS["position_step_m"],
            n_headings=LATTICE_DEFAULTS["n_headings"],
            max_hypotheses=LATTICE_DEFAULTS["max_hypotheses"],
        )
        lattice_s = time.perf_counter() - t0
        sigma = LATTICE_DEFAULTS["smoothing_factor"] * lat.step_m
        sm = loc.ScanModel(
            cache.get("dec", sigma), az, r_min, r_max, ray_floor=float(cfg.ray_floor)
        )
        z0 = seq["z0"]

        def init(sm=sm, lat=lat, z0=z0):
            return loc.init_from_scan(n, lat, sm, z0, key=jax.random.PRNGKey(0))

        uniform = loc.init_global(n, spec, free, key=jax.random.PRNGKey(1)).particles
        ref_fn = jax.jit(lambda p, sm=sm, z0=z0: sm(p, z0))

        def ref(uniform=uniform, ref_fn=ref_fn):
            return ref_fn(uniform)

        jax.block_until_ready(init())
        jax.block_until_ready(ref())
        t_init = policy.time_calls(f"{name} init", init, args.repeats, warmup=0)
        t_ref = policy.time_calls(f"{name} ref", ref, args.repeats, warmup=0)
        results[name] = {
            "grid_shape": list(spec.shape),
            "free_cells": int(free.sum()),
            "lattice_step_m": lat.step_m,
            "hypotheses": lat.n_hypotheses,
            "lattice_build_s": lattice_s,
            "init_s": t_init["median_s"],
            "hypotheses_per_s": lat.n_hypotheses / t_init["median_s"],
            "reference_update_s": t_ref["median_s"],
            "ratio_to_one_update": t_init["median_s"] / t_ref["median_s"],
            "load": {"init": t_init["load"], "reference": t_ref["load"]},
        }
        r = results[name]
        print(
            f"{name}: {r['hypotheses']} hypotheses ({r['lattice_step_m']:.1f} m), init "
            f"{r['init_s']:.2f} s = {r['ratio_to_one_update']:.0f} x one {n}-particle update "
            f"({r['reference_update_s'] * 1e3:.0f} ms), load {t_init['load']['load_1min']:.2f}",
            flush=True,
        )
    report = {
        "machine": machine_info(
            load_average_start=list(load_start), load_average_end=list(os.getloadavg())
        ),
        "setup": {
            "particles": n,
            "beams": 30,
            "lattice": LATTICE_DEFAULTS,
            "repeats": args.repeats,
        },
        "logs": results,
        "load_policy": policy.summary() if hasattr(policy, "summary") else None,
    }
    write_json(args.out, report)
    return report


if __name__ == "__main__":
    main()
