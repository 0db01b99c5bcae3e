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

Timings: one warm-up call (compilation, reported separately), then the median of
``repeats`` calls (at least 5 for the fast path) with ``jax.block_until_ready``.

Run with ``python benchmarks/likelihood.py [--quick] [--out PATH] [--chunk-size N]``. Results
go to ``--out`` (default ``benchmarks/results/likelihood.json``; write quick or loaded runs
elsewhere) and a Markdown table is printed.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make `lidarjax` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from _machine import machine_info

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


@eqx.filter_jit
def _fast_at_poses(model, az, ranges, poses, r_max, chunk_size):
    """``[p b]`` log-likelihoods of one scan at ``[p 3]`` poses via the fast forward path."""
    poses = jnp.asarray(poses, az.dtype)
    T = jaxlie.SE2.from_xy_theta(poses[:, 0], poses[:, 1], poses[:, 2])
    rays = from_scan(T, az, jnp.broadcast_to(ranges, (poses.shape[0], az.shape[0])), 0.0, r_max)
    return batch_log_likelihood(model, rays, chunk_size=chunk_size)


def _compare(got, ref) -> dict:
    """Differences of ``got`` from ``ref`` over the entries finite in both (float64)."""
    got, ref = np.asarray(got, np.float64).ravel(), np.asarray(ref, np.float64).ravel()
    both = np.isfinite(got) & np.isfinite(ref)
    diff = np.abs(got[both] - ref[both])
    rel = diff / np.maximum(np.abs(ref[both]), 1.0)
    return {
        "n_compared": int(both.sum()),
        "max_abs_diff": float(diff.max()) if diff.size else None,
        "max_rel_diff": float(rel.max()) if rel.size else None,
        "n_finite_mismatch": int((np.isfinite(got) != np.isfinite(ref)).sum()),
        "n_mismatch_both_nonfinite": int(
            (~np.isfinite(got) & ~np.isfinite(ref) & (got != ref)).sum()
        ),
    }


def time_jax(fn, repeats: int) -> tuple[float, float, np.ndarray]:
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return first, statistics.median(times), np.asarray(out)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer poses, repeats, reference rays")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--chunk-size", type=int, default=2048, help="batch_log_likelihood chunk_size")
    args = ap.parse_args(argv)
    n_poses = 60 if args.quick else 300
    repeats = 1 if args.quick else 3
    fast_repeats = max(repeats, 5)  # fast calls are cheap; more samples, less noise
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
    stats = jax.block_until_ready(accumulate(spec, rays))
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

    results, jax_out = {}, {}
    for name, (m, fm) in models.items():

        def call(m=m):
            return ray_log_likelihoods_at_poses(m, az, ranges, poses, r_max=r_max)

        def call_fast(fm=fm):
            return _fast_at_poses(fm, az_j, ranges_j, poses_j, r_max, args.chunk_size)

        first, med, out = time_jax(call, repeats)
        jax_out[name] = out
        print(f"{name}: {n_rays / med:.3g} rays*poses/s (first call {first:.1f} s)", flush=True)
        f_first, f_med, f_out = time_jax(call_fast, fast_repeats)
        check = _compare(f_out, out)
        results[name] = {
            "first_call_s": first,
            "median_s": med,
            "rays_x_poses_per_s": n_rays / med,
            "fast_first_call_s": f_first,
            "fast_median_s": f_med,
            "fast_rays_per_s": n_rays / f_med,
            "fast_speedup_vs_scan": med / f_med,
            "fast_speedup_vs_numpy": None,  # set below where a NumPy reference exists
            "fast_max_abs_diff": check["max_abs_diff"],
            "fast_max_rel_diff": check["max_rel_diff"],
            "fast_n_compared": check["n_compared"],
            "fast_n_finite_mismatch": check["n_finite_mismatch"],
            "fast_n_nonfinite_mismatch": check["n_mismatch_both_nonfinite"],
        }
        print(
            f"{name} fast: {n_rays / f_med:.3g} rays*poses/s (first call {f_first:.1f} s), "
            f"{med / f_med:.1f}x vs scan, max abs diff {check['max_abs_diff']:.2e}, "
            f"{check['n_finite_mismatch']} finite mismatches",
            flush=True,
        )

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
        t0 = time.perf_counter()
        for n, idx in enumerate(pick):
            p, b = divmod(int(idx), az.size)
            th = poses[p, 2] + az[b]
            o = poses[p, :2]
            d = np.array([math.cos(th), math.sin(th)])
            vals[n] = fn(values, outside, lo, res, o, d, float(ranges[b]), int(kind[b]), r_max)
        dt = time.perf_counter() - t0
        got = jax_out[name].reshape(-1)[pick].astype(np.float64)
        both = np.isfinite(vals) & np.isfinite(got)
        diff = np.abs(vals[both] - got[both])
        rel = diff / np.maximum(np.abs(vals[both]), 1.0)
        rate = pick.size / dt
        results[name]["numpy_reference"] = {
            "n_rays_timed": int(pick.size),
            "seconds": dt,
            "rays_per_s": rate,
            "speedup": results[name]["rays_x_poses_per_s"] / rate,
            "fast_speedup": results[name]["fast_rays_per_s"] / rate,
            "max_abs_diff": float(diff.max()) if diff.size else None,
            "max_rel_diff": float(rel.max()) if rel.size else None,
            "n_finite_mismatch": int((np.isfinite(vals) != np.isfinite(got)).sum()),
            "n_large_rel_diff_gt_1e-3": int((rel > 1e-3).sum()),
        }
        results[name]["fast_speedup_vs_numpy"] = results[name]["fast_rays_per_s"] / rate
        print(f"{name} numpy reference: {rate:.3g} rays/s", flush=True)

    report = {
        "machine": machine_info(),
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
        },
        "models": results,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2))
    lines = [
        f"Intel map {spec.shape[0]}x{spec.shape[1]} cells of {res} m, r_max {r_max:.1f} m, "
        f"{n_poses} poses x {az.size} beams, {jax.default_backend()} "
        f"({os.cpu_count()} cores), float32",
        "",
        "| model | JAX rays*poses/s | first call (s) | NumPy loop rays/s | speedup | "
        "max rel diff | fast rays*poses/s | fast first call (s) | fast vs scan | "
        "fast vs NumPy | fast max abs diff |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in results.items():
        ref = r.get("numpy_reference")
        ref_cols = (
            f"{ref['rays_per_s']:.3g} | {ref['speedup']:.1f}x | {ref['max_rel_diff']:.1e}"
            if ref
            else "- | - | -"
        )
        vs_np = r["fast_speedup_vs_numpy"]
        fdiff = r["fast_max_abs_diff"]
        fast_cols = (
            f"{r['fast_rays_per_s']:.3g} | {r['fast_first_call_s']:.1f} | "
            f"{r['fast_speedup_vs_scan']:.1f}x | "
            f"{'-' if vs_np is None else f'{vs_np:.1f}x'} | "
            f"{'-' if fdiff is None else f'{fdiff:.1e}'}"
        )
        lines.append(
            f"| {name} | {r['rays_x_poses_per_s']:.3g} | {r['first_call_s']:.1f} | {ref_cols} | "
            f"{fast_cols} |"
        )
    print("\n".join(lines))
    return report


if __name__ == "__main__":
    main()
