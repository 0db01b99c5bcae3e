"""Throughput of the grid sensor models: rays x poses evaluated per second.

One Intel Research Lab scan (180 beams) is evaluated at ``n_poses`` poses around its true
pose with :func:`lidarjax.sensor_models.ray_log_likelihoods_at_poses` for each model:
decay-rate (Eqs. 7.13/7.16), reflection (Eqs. 7.23/7.32), endpoint (likelihood field) and the
two full-map-posterior likelihoods (Eq. 8.20, Gamma / Beta). The map is built from all 910
scans of the log at 0.1 m cells, ``r_max`` = the log's usable range (80.19 m), float32.

Fast path: the same rays (same scan, same poses, same maps) are also evaluated with
:func:`lidarjax.sensor_models.batch_log_likelihood` (forward only; a sorted, chunked
``while_loop`` walk instead of a fixed per-ray cell budget), including building the rays from
the poses, as the differentiable path does. For the endpoint map this is the same per-ray
normalised model (every ray traced to ``r_max`` for its normaliser), not the classic
likelihood field that ``lidarjax.localization.ScanModel`` uses by default. Reported: its
rate, its speed-up over the differentiable path and over the NumPy reference (decay rate and
reflection only), and the largest absolute difference from the differentiable path over the
rays where both are finite (plus the count of rays finite in only one of them).

Reference: a plain per-ray NumPy/Python implementation of the decay-rate and reflection
forward models (cell walk with exact per-cell lengths, then the model's sum), written here
independently of the library. It is timed on a subset of the same rays in the same run and
its rate is extrapolated per ray; the subset is also compared against the JAX values.

Backends of the fast path, all in the same run on the same rays: the native C++ fold
(``backend="native"``, ``threads`` 1 and 2) and the pure-JAX fold (``backend="jax"``).
Ratios ``native/JAX`` (fast JAX path) and ``native/NumPy`` are throughput ratios (the other
path's time per ray divided by the native one's).

Timings: one warm-up call (compilation, reported separately), then the median (and best) of
``repeats`` calls (at least 7 for the fast paths) with ``jax.block_until_ready``. Every timed
block records the 1-minute load average right before it and is rerun after waiting for the
load to drop when it was above 0.5 (:mod:`benchmarks._harness`).

Run with ``python benchmarks/likelihood.py [--quick] [--out PATH] [--chunk-size N]
[--wait-budget S]``. Results go to ``--out`` (default ``benchmarks/results/likelihood.json``)
and a Markdown table is printed.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from _harness import (
    add_policy_args,
    machine_info,
    max_abs_diff,
    native_info,
    policy_from_args,
    ratio,
    warm,
    write_json,
)

from lidarjax import maps
from lidarjax.datasets import fetch, load_carmen
from lidarjax.rays import HIT, SUP, from_scan
from lidarjax.raytrace import GridSpec, accumulate, max_cells_for
from lidarjax.sensor_models import (
    batch_log_likelihood,
    posterior_log_likelihood,
    ray_log_likelihoods_at_poses,
)

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "likelihood.json"


# ------------------------------------------------------------------ NumPy reference


def walk_numpy(lo, res, shape, o, d, length):
    """Cells ``[(ix, iy, seg_len)]`` of one 2-D ray clipped to the grid, plus the clipped
    parameter interval ``(t0, t1)``. Plain Amanatides-Woo walk with exact lengths."""
    hi = lo + res * np.asarray(shape, float)
    t0, t1 = 0.0, float(length)
    for k in range(2):
        if d[k] != 0.0:
            ta, tb = (lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]
            t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
        elif not (lo[k] <= o[k] <= hi[k]):
            return [], 0.0, 0.0
    if t0 >= t1:
        return [], 0.0, 0.0
    tm = 0.5 * (t0 + min(t1, t0 + 1e-6 * res))  # a point just after the entry
    cell = [
        min(max(int(math.floor((o[k] + tm * d[k] - lo[k]) / res)), 0), shape[k] - 1)
        for k in range(2)
    ]
    step = [1 if d[k] > 0 else -1 for k in range(2)]
    t_next = [
        (lo[k] + (cell[k] + (1 if d[k] > 0 else 0)) * res - o[k]) / d[k] if d[k] != 0 else math.inf
        for k in range(2)
    ]
    t_delta = [res / abs(d[k]) if d[k] != 0 else math.inf for k in range(2)]
    out, t = [], t0
    tol = 1e-9 * (t1 + res)
    while True:
        tmin = min(t_next)
        end = min(tmin, t1)
        out.append((cell[0], cell[1], end - t))
        if tmin >= t1 - tol:
            break
        t = tmin
        for k in range(2):
            if t_next[k] <= tmin + tol:
                cell[k] += step[k]
                t_next[k] += t_delta[k]
        if not (0 <= cell[0] < shape[0] and 0 <= cell[1] < shape[1]):
            break
    return out, t0, t1


def _log(x):
    return math.log(x) if x > 0 else -math.inf


def decay_rate_numpy(rates, outside, lo, res, o, d, rng, kind, r_max):
    """log p(z) of one ray under the decay-rate model (Eqs. 7.13 / 7.16), r_min = 0."""
    length = r_max if kind == SUP else rng
    cells, t0, t1 = walk_numpy(lo, res, rates.shape, o, d, length)
    depth = sum(rates[i, j] * s for i, j, s in cells)
    grid_len = sum(s for _, _, s in cells)
    out_len = max(length - grid_len, 0.0)
    depth += outside * out_len if out_len > 0 else 0.0
    if kind == SUP:
        return -depth
    inside = bool(cells) and t1 >= length
    lam = rates[cells[-1][0], cells[-1][1]] if inside else outside
    return _log(lam) - depth


def reflection_numpy(probs, q_out, lo, res, o, d, rng, kind, r_max):
    """log p(z) of one ray under the reflection model (Eqs. 7.23 / 7.32), r_min = 0."""
    length = r_max if kind == SUP else rng
    cells, t0, t1 = walk_numpy(lo, res, probs.shape, o, d, length)
    inside = bool(cells) and t1 >= length
    before = cells[:-1] if inside else cells
    log_surv = sum(_log(1.0 - probs[i, j]) for i, j, _ in before)
    grid_len = sum(s for _, _, s in cells)
    out_len = max(length - grid_len, 0.0)
    log1m_qout = _log(1.0 - q_out)
    if out_len > 0:
        log_surv += log1m_qout * out_len / res
    if inside:
        i, j, last = cells[-1]
        q_k = probs[i, j]
        cell_lo = lo + res * np.array([i, j], float)
        far = min(
            max((cell_lo[k] - o[k]) / d[k], (cell_lo[k] + res - o[k]) / d[k])
            for k in range(2)
            if d[k] != 0
        )
        chord = max(far - (length - last), last, 1e-7 * res)
    if kind == HIT:
        if log_surv == -math.inf:
            return -math.inf
        if inside:
            return log_surv + _log(q_k) - math.log(chord)
        return log_surv + _log(-log1m_qout / res)
    if inside:
        log_surv += _log(1.0 - q_k * min(max(last / chord, 0.0), 1.0))
    return log_surv


# ------------------------------------------------------------------ benchmark


def _fmp(posterior_map, max_cells, rays):
    return posterior_log_likelihood(posterior_map, rays, max_cells=max_cells)


FAST_BACKENDS = (("jax", "jax", None), ("native_1t", "native", 1), ("native_2t", "native", 2))


@eqx.filter_jit
def _fast_at_poses(model, az, ranges, poses, r_max, chunk_size, backend="auto", threads=None):
    """``[p b]`` log-likelihoods of one scan at ``[p 3]`` poses via the fast forward path."""
    poses = jnp.asarray(poses, az.dtype)
    T = jaxlie.SE2.from_xy_theta(poses[:, 0], poses[:, 1], poses[:, 2])
    rays = from_scan(T, az, jnp.broadcast_to(ranges, (poses.shape[0], az.shape[0])), 0.0, r_max)
    return batch_log_likelihood(
        model, rays, chunk_size=chunk_size, backend=backend, threads=threads
    )


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer poses, repeats, reference rays")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--chunk-size", type=int, default=2048, help="batch_log_likelihood chunk_size")
    add_policy_args(ap)
    args = ap.parse_args(argv)
    policy = policy_from_args(args)
    t_start = time.perf_counter()
    machine = machine_info(native=native_info())
    n_poses = 60 if args.quick else 300
    repeats = 1 if args.quick else 3
    fast_repeats = max(repeats, 7)  # fast calls are cheap; more samples, less noise
    n_ref = 150 if args.quick else 600
    res = 0.1

    log = load_carmen(fetch("intel"))
    r_max = float(log.usable_range_m)
    P = log.poses
    rays = from_scan(
        jaxlie.SE2.from_xy_theta(P[:, 0], P[:, 1], P[:, 2]),
        log.azimuths_rad,
        log.ranges_m,
        0.0,
        r_max,
    )
    ends = np.asarray(rays.endpoints())[np.asarray(rays.kind) == HIT]
    spec = GridSpec.covering(np.concatenate([ends, P[:, :2]]), res, margin=3.0)
    t0 = time.perf_counter()
    stats = jax.block_until_ready(accumulate(spec, rays, backend="jax"))
    t_map = time.perf_counter() - t0
    dm, rm = maps.decay_rate_map(stats), maps.reflection_map(stats)
    em = maps.endpoint_map(stats, sigma_m=0.1)
    mc = max_cells_for(spec, r_max)
    gm, bm = maps.gamma_posterior(stats), maps.beta_posterior(stats)
    # (differentiable-path model, fast-path model)
    models = {
        "decay_rate": (dm, dm),
        "reflection": (rm, rm),
        "endpoint": (em, em),
        "fmp_gamma": (jax.tree_util.Partial(_fmp, gm, mc), gm),
        "fmp_beta": (jax.tree_util.Partial(_fmp, bm, mc), bm),
    }
    s = 455
    rng = np.random.default_rng(0)
    poses = P[s] + rng.normal(0.0, 1.0, (n_poses, 3)) * [0.5, 0.5, 0.05]
    az, ranges = log.azimuths_rad, log.ranges_m[s]
    n_rays = n_poses * az.size

    az_j = jnp.asarray(az, jnp.result_type(float))
    ranges_j = jnp.asarray(ranges, az_j.dtype)
    poses_j = jnp.asarray(poses, az_j.dtype)

    results, jax_out, fast_outs = {}, {}, {}
    for name, (m, fm) in models.items():

        def call(m=m):
            return ray_log_likelihoods_at_poses(m, az, ranges, poses, r_max=r_max)

        out, first = warm(call)
        out = np.asarray(out)
        scan_t = policy.time_calls(f"{name} differentiable", call, repeats, warmup=0)
        jax_out[name] = out
        med = scan_t["median_s"]
        print(f"{name}: {n_rays / med:.3g} rays*poses/s (first call {first:.1f} s)", flush=True)
        entry = {
            "first_call_s": first,
            "median_s": med,
            "rays_x_poses_per_s": n_rays / med,
            "differentiable": scan_t,
            "fast": {},
        }
        fast_out = {}
        for label, backend, threads in FAST_BACKENDS:

            def call_fast(fm=fm, backend=backend, threads=threads):
                return _fast_at_poses(
                    fm, az_j, ranges_j, poses_j, r_max, args.chunk_size, backend, threads
                )

            try:
                f_out, f_first = warm(call_fast)
            except Exception as e:  # noqa: BLE001 - recorded; the other paths still count
                entry["fast"][label] = {"error": f"{type(e).__name__}: {e}"}
                print(f"{name} fast {label} FAILED: {e}", flush=True)
                continue
            f_out = np.asarray(f_out)
            fast_out[label] = f_out
            t = policy.time_calls(f"{name} fast {label}", call_fast, fast_repeats, warmup=0)
            check = max_abs_diff(f_out, out)
            entry["fast"][label] = {
                "backend": backend,
                "threads": threads,
                "first_call_s": f_first,
                **t,
                "rays_per_s": n_rays / t["median_s"],
                "m_rays_per_s": n_rays / t["median_s"] / 1e6,
                "ns_per_ray": 1e9 * t["median_s"] / n_rays,
                "speedup_vs_differentiable": med / t["median_s"],
                "vs_differentiable": check,
            }
            print(
                f"{name} fast {label}: {n_rays / t['median_s']:.3g} rays*poses/s (first call "
                f"{f_first:.1f} s), {med / t['median_s']:.1f}x vs differentiable, max abs diff "
                f"{check['max_abs_diff']:.2e}, {check['n_finite_mismatch']} finite mismatches",
                flush=True,
            )
        fj = entry["fast"].get("jax", {})
        for label in ("native_1t", "native_2t"):
            fn = entry["fast"].get(label, {})
            if "median_s" in fn and "median_s" in fj:
                fn["native_over_jax"] = ratio(fj["median_s"], fn["median_s"])
                fn["native_over_jax_best"] = ratio(fj["best_s"], fn["best_s"])
                fn["vs_fast_jax"] = max_abs_diff(fast_out[label], fast_out["jax"])
        results[name] = entry
        fast_outs[name] = fast_out

    # NumPy per-ray reference on a random subset of the same (pose, beam) pairs.
    rates, probs = np.asarray(dm.rates, np.float64), np.asarray(rm.probs, np.float64)
    lo = np.asarray(spec.origin, np.float64)
    kind = np.asarray(rays.kind).reshape(log.ranges_m.shape)[s]
    pick = rng.choice(n_rays, size=min(n_ref, n_rays), replace=False)
    ref_fns = {
        "decay_rate": (decay_rate_numpy, rates, float(dm.outside_rate)),
        "reflection": (reflection_numpy, probs, float(rm.unknown_prob)),
    }
    for name, (fn, values, outside) in ref_fns.items():
        vals = np.empty(pick.size)

        def ref_loop(fn=fn, values=values, outside=outside, vals=vals):
            for n, idx in enumerate(pick):
                p, b = divmod(int(idx), az.size)
                th = poses[p, 2] + az[b]
                o = poses[p, :2]
                d = np.array([math.cos(th), math.sin(th)])
                vals[n] = fn(values, outside, lo, res, o, d, float(ranges[b]), int(kind[b]), r_max)

        timed = policy.time_calls(f"{name} numpy reference", ref_loop, 1, warmup=0)
        dt = timed["median_s"]
        got = jax_out[name].reshape(-1)[pick].astype(np.float64)
        check = max_abs_diff(got, vals, rel_tol=1e-3)  # against the float64 loop
        rate = pick.size / dt
        results[name]["numpy_reference"] = {
            "n_rays_timed": int(pick.size),
            "seconds": dt,
            "rays_per_s": rate,
            "ns_per_ray": 1e9 / rate,
            "load": timed["load"],
            "speedup": results[name]["rays_x_poses_per_s"] / rate,
            **check,
            "n_large_rel_diff_gt_1e-3": check["n_rel_diff_gt_1e-3"],
        }
        for label, f_out in fast_outs[name].items():  # each fast path vs the float64 loop
            g = f_out.reshape(-1)[pick].astype(np.float64)
            results[name]["fast"][label]["vs_numpy_reference"] = max_abs_diff(g, vals, rel_tol=1e-3)
        for f in results[name]["fast"].values():
            if "rays_per_s" in f:
                f["speedup_vs_numpy"] = f["rays_per_s"] / rate
                if f["backend"] == "native":
                    f["native_over_numpy"] = f["rays_per_s"] / rate
        print(f"{name} numpy reference: {rate:.3g} rays/s", flush=True)

    report = {
        "machine": machine,
        "quick": args.quick,
        "setup": {
            "log": "intel",
            "map_scans": log.n_scans,
            "resolution_m": res,
            "grid_shape": list(spec.shape),
            "r_max_m": r_max,
            "max_cells": mc,
            "scan_index": s,
            "n_poses": n_poses,
            "n_beams": int(az.size),
            "repeats": repeats,
            "fast_chunk_size": args.chunk_size,
            "fast_repeats": fast_repeats,
            "accumulate_s": t_map,
            "ratio_note": "native_over_X = X's time per ray / native's (higher is faster)",
        },
        "models": results,
        "load_policy": policy.summary(),
        "load_average_end": list(os.getloadavg()),
        "wall_time_s": time.perf_counter() - t_start,
    }
    write_json(args.out, report)

    def cell(r, label, key, fmt):
        v = r["fast"].get(label, {}).get(key)
        return "-" if v is None else format(v, fmt)

    lines = [
        f"Intel map {spec.shape[0]}x{spec.shape[1]} cells of {res} m, r_max {r_max:.1f} m, "
        f"{n_poses} poses x {az.size} beams, {jax.default_backend()} "
        f"({os.cpu_count()} cores), float32; rays*poses/s, median of warm calls",
        "",
        "| model | differentiable | NumPy loop | fast JAX | native 1t | native 2t | 1t/JAX "
        "| 2t/JAX | 2t/NumPy | max abs diff 2t vs JAX | load (2t) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in results.items():
        ref = r.get("numpy_reference")
        n2 = r["fast"].get("native_2t", {})
        load = n2.get("load", {}).get("load_1min")
        d2 = n2.get("vs_fast_jax", {}).get("max_abs_diff")
        lines.append(
            f"| {name} | {r['rays_x_poses_per_s']:.3g} | "
            f"{'-' if not ref else format(ref['rays_per_s'], '.3g')} | "
            f"{cell(r, 'jax', 'rays_per_s', '.3g')} | "
            f"{cell(r, 'native_1t', 'rays_per_s', '.3g')} | "
            f"{cell(r, 'native_2t', 'rays_per_s', '.3g')} | "
            f"{cell(r, 'native_1t', 'native_over_jax', '.2f')} | "
            f"{cell(r, 'native_2t', 'native_over_jax', '.2f')} | "
            f"{cell(r, 'native_2t', 'native_over_numpy', '.0f')} | "
            f"{'-' if d2 is None else format(d2, '.1e')} | "
            f"{'-' if load is None else format(load, '.2f')} |"
        )
    print("\n".join(lines))
    print(f"\n(wall time {report['wall_time_s']:.0f} s; JSON: {args.out})")
    return report


if __name__ == "__main__":
    main()
