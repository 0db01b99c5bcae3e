"""Milliseconds per particle-filter step of the localization remedies
(``experiments/mcl_remedies.py``), one filter at a time, against the plain decay-rate
filter with 300 particles timed in the same run.

Setup: the Intel map and protocol of ``configs/mcl_remedies.yaml`` (0.1 m cells, 30 beams,
the first 100 odd-numbered scans, raw odometry, start N(0, 1 m^2) / N(0, 0.1 rad^2)); each
variant is built by the experiment's own ``make_filter`` so the benchmark times exactly
what the tables report. One ``ParticleFilter.run`` (a ``lax.scan`` over all steps) is
compiled once (``lower().compile()``, not timed), then timed ``--repeats`` times; the
median divided by the number of steps is the time per step (motion, measurement,
estimate, resampling). The 1-minute load average is recorded before every timed block
and the block is rerun after waiting when it was above 0.5 (:mod:`benchmarks._harness`).
Goal of the issue: <= 50 ms per step on 2 cores for the chosen default.

Run with ``python benchmarks/mcl_remedies.py [--variants a,b,...] [--repeats N]
[--out PATH]``; results go to ``benchmarks/results/mcl_remedies.json``.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import equinox as eqx
import jax
from _harness import (
    RESULTS,
    add_policy_args,
    experiments_on_path,
    machine_info,
    native_info,
    policy_from_args,
    remedies_config,
    write_json,
)
from omegaconf import OmegaConf

experiments_on_path()  # times the experiment's own filters (make_filter) and protocol
from _common import mapping_stats  # noqa: E402
from mcl import initial_states, prepare  # noqa: E402
from mcl_remedies import MapCache, _variant, make_filter  # noqa: E402

DEFAULT_OUT = RESULTS / "mcl_remedies.json"
REFERENCE = "dec"
DEFAULT_VARIANTS = [
    "dec",
    "end",
    "fmp_dec",
    "dec+smooth0.1",
    "fmp_dec+c2f",
    "fmp_dec+c2f+1000",
    "dec+3000",
    "dec+c2f0.35+3000",
    "fmp_dec+c2f0.35+2000",
    "dec+augmented",
    "dec+kld",
    "dec+guided_gradient",
    "dec+guided",
]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", default=",".join(DEFAULT_VARIANTS))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--log", default="intel")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    add_policy_args(ap)
    args = ap.parse_args(argv)
    policy = policy_from_args(args)
    cfg = remedies_config()
    names = [v for v in args.variants.split(",") if v]
    unknown = set(names) - set(cfg.variants)
    if unknown:
        raise SystemExit(f"unknown variants {sorted(unknown)}; choose from {list(cfg.variants)}")
    if REFERENCE not in names:
        names.insert(0, REFERENCE)
    load_start = os.getloadavg()
    log, r_min, r_max, az, seq, key = prepare(args.log, cfg)
    stats, spec, p_out = mapping_stats(log, cfg, r_min, r_max)
    cache = MapCache(stats, cfg, p_out)
    n_steps = int(seq["z"].shape[0])
    results = {}
    for name in names:
        v = _variant(cfg.variants[name])
        pf = make_filter(v, cache, az, cfg, r_min, r_max)
        n = int(v.get("particles", cfg.filter.particles))
        fcfg = OmegaConf.merge(cfg, {"filter": {"particles": n, "runs": 1}})
        state = jax.tree.map(lambda x: x[0], initial_states(key, seq["start"], fcfg))
        t0 = time.perf_counter()
        compiled = eqx.filter_jit(pf.run).lower(state, seq["controls"], seq["z"]).compile()
        compile_s = time.perf_counter() - t0

        def call(compiled=compiled, state=state):
            return compiled(state, seq["controls"], seq["z"])

        timed = policy.time_calls(name, call, args.repeats)  # one untimed warm-up call first
        results[name] = {
            "particles": n,
            "ms_per_step": 1e3 * timed["median_s"] / n_steps,
            "ms_per_step_best": 1e3 * timed["best_s"] / n_steps,
            "compile_s": compile_s,
            "load": timed["load"],
        }
        print(
            f"{name:22s} {n:6d} particles: {results[name]['ms_per_step']:8.2f} ms/step "
            f"(load {timed['load']['load_1min']:.2f})",
            flush=True,
        )
    ref = results[REFERENCE]["ms_per_step"]
    for r in results.values():
        r["ratio_to_dec_300"] = r["ms_per_step"] / ref
    report = {
        "machine": machine_info(
            native=native_info(),
            load_average_start=list(load_start),
            load_average_end=list(os.getloadavg()),
        ),
        "setup": {
            "log": args.log,
            "steps": n_steps,
            "beams": int(az.shape[0]),
            "grid_shape": list(spec.shape),
            "repeats": args.repeats,
            "reference": f"{REFERENCE} (300 particles), same run",
        },
        "variants": results,
        "load_policy": policy.summary() if hasattr(policy, "summary") else None,
    }
    write_json(args.out, report)
    print("\n| variant | particles | ms/step | × dec 300 | load |\n|---|---|---|---|---|")
    for k, r in results.items():
        print(
            f"| {k} | {r['particles']} | {r['ms_per_step']:.2f} | {r['ratio_to_dec_300']:.2f} | "
            f"{r['load']['load_1min']:.2f} |"
        )
    return report


if __name__ == "__main__":
    main()
