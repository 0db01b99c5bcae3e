"""Decay-rate SLAM (issue #24): front-end scans per second (and real-time factor) and the back
end's seconds per iteration, with the classical baseline timed in the same run.

On the first ``--scans`` scans of each log with the experiment's drifting odometry
(``configs/slam.yaml``): the decay-rate front end (:func:`lidarjax.slam.run_front_end`;
scans/s after its first scan, which compiles), the endpoint front end, the GICP + GTSAM
baseline's front end, :func:`lidarjax.slam.find_revisits` (best of 3), the reference-free
consistency scores :func:`lidarjax.metrics.cross_visit_distance` and
:func:`lidarjax.slam.trajectory_log_likelihood` of the front end's trajectory (best of 3),
the pose graph over
the front end's increments and its loop closures
(:func:`lidarjax.slam.front_end_pose_graph`: the plain chain, and the robust chain with the
odometry and the revisits; best of 3 after a compiling call), and one call each of
:func:`lidarjax.slam.optimize_joint` and :func:`lidarjax.slam.optimize_alternating`
(``--steps`` L-BFGS iterations; seconds per iteration, after a compiling call). The
decay-rate front end runs twice, with the optical depth from the native kernel (the
default where it is built) and from the pure-JAX path, and one scan's objective (value and
gradient in the pose) is timed on both; it runs a third time without the grazing cut
(``grazing_cells=0``; ``grazing_cost``: its scans/s over the default's). Front-end
scans/s leave out the first two scans (the first match compiles; reported as
``first_scan_s``). The 1-minute load average is recorded before every timing. Writes
``benchmarks/results/slam.json``.

Usage: ``python benchmarks/slam.py [--logs intel fhw orebro] [--scans 200] [--steps 20]``.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
from _harness import RESULTS, machine_info, write_json

from lidarjax import slam
from lidarjax.datasets import fetch, load_carmen
from lidarjax.metrics import cross_visit_distance
from lidarjax.raytrace import _native
from lidarjax.sim import wheel_odometry
from lidarjax.slam._front_end import between_np

OUT = RESULTS / "slam.json"


def log_inputs(name: str, scans: int):
    """``(log, n, ranges [n B], azimuths [B], odometry [n 3])`` of the first ``scans`` scans
    of a shared log, with the experiment's drifting odometry (``configs/slam.yaml``)."""
    log = load_carmen(fetch(name), azimuth_layout="sweep")  # as the experiment
    n = min(scans, log.n_scans)
    ranges = np.minimum(log.ranges_m[:n], log.max_range_m)
    odo = wheel_odometry(
        log.poses[:n],
        seed=0,
        sigma_trans_rel=0.05,
        sigma_rot_per_m=float(np.deg2rad(1.0)),
        heading_bias_per_m=float(np.deg2rad(0.3)),
        sigma_rot_per_rad=0.02,
    )
    return log, n, ranges, log.azimuths_rad, odo


def _scan_rate(stamps):
    dt = np.diff(stamps)
    if dt.size == 0 or not np.all(dt > 0):
        return None
    return float(dt.size / (stamps[-1] - stamps[0]))


def time_front_end(ranges, az, odo, cfg, rate):
    """One timed :func:`lidarjax.slam.run_front_end` run: ``(record, result)``. The record
    holds the 1-minute load before it, scans/s and the median seconds per scan without the
    first two scans (the first match compiles; their sum is ``first_scan_s``), and the
    real-time factor (scans/s over ``rate``, Hz; None without one)."""
    load = os.getloadavg()[0]
    fe = slam.run_front_end(ranges, az, odo, cfg)
    per = fe.seconds_per_scan[2:]
    sps = float(len(per) / per.sum())
    record = {
        "load_1min_before": load,
        "scans_per_s": sps,
        "median_s_per_scan": float(np.median(per)),
        "first_scan_s": float(fe.seconds_per_scan[0] + fe.seconds_per_scan[1]),
        "real_time_factor": None if rate is None else sps / rate,
    }
    return record, fe


def time_scan_objective(ranges, az, poses, k: int = 30, reps: int = 200):
    """Milliseconds per value-and-gradient of one scan's decay-rate log-likelihood in its
    pose (the front end's BFGS objective: the last stage, scan ``k`` on the map of the
    scans before it, float32 as the front end), native kernel and JAX path in the same
    run, each the best of 3 blocks of ``reps`` calls after a compiling call."""
    import jax
    import jax.numpy as jnp

    from lidarjax.maps import DecayRateMap, SmoothDecayRateField
    from lidarjax.raytrace import GridSpec
    from lidarjax.slam._front_end import GridMap, _scan_log_likelihoods, se2

    cfg = slam.FrontEndConfig()
    grid = GridMap(cfg.resolution_m, cfg.range_cap_m)
    for j in range(k):
        grid.add_scan(poses[j], az, ranges[j])
    h, r, origin = grid.window(poses[k][:2], cfg.window_cells)
    rates = np.where(r > 1e-9, h / np.maximum(r, 1e-9), 0.0).astype(np.float32)
    n = rates.shape[0]
    spec = GridSpec(jnp.asarray(origin, jnp.float32), cfg.resolution_m, (n, n))
    grid_map = DecayRateMap(spec, jnp.asarray(rates), jnp.float32(0.0))
    azj = jnp.asarray(az, jnp.float32)
    rj = jnp.asarray(np.minimum(ranges[k], cfg.range_cap_m), jnp.float32)
    gap = cfg.gap_cells * cfg.resolution_m
    p0 = jnp.asarray(poses[k], jnp.float32)
    out = {"rays": int(az.shape[0]), "nodes_per_ray": cfg.n_nodes, "cells": int(n * n)}
    for backend in ("native", "jax"):
        if backend == "native" and not _native.available():
            continue
        field = SmoothDecayRateField(grid_map, n_nodes=cfg.n_nodes, backend=backend)

        def objective(p, field=field):
            return jnp.sum(_scan_log_likelihoods(field, se2(p), azj, rj, cfg, gap))

        vg = jax.jit(jax.value_and_grad(objective))
        jax.block_until_ready(vg(p0))
        load = os.getloadavg()[0]
        best = np.inf
        for _ in range(3):
            t = time.perf_counter()
            for i in range(reps):
                res = vg(p0 + 1e-4 * i)
            jax.block_until_ready(res)
            best = min(best, (time.perf_counter() - t) / reps)
        out[backend] = {"load_1min_before": load, "ms_per_value_and_grad": 1e3 * best}
    if "native" in out:
        out["native_speedup"] = (
            out["jax"]["ms_per_value_and_grad"] / (out["native"]["ms_per_value_and_grad"])
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--logs", nargs="+", default=["intel", "fhw", "orebro"])
    ap.add_argument("--scans", type=int, default=200)
    ap.add_argument("--steps", type=int, default=20)
    args = ap.parse_args()
    report = {"machine": machine_info(), "scans": args.scans, "logs": {}}
    for name in args.logs:
        log, n, ranges, az, odo = log_inputs(name, args.scans)
        rate = _scan_rate(log.timestamps_s[:n])
        row: dict = {"n_scans": n, "scan_rate_hz": rate}
        for model in ("decay_rate", "endpoint"):
            cfg = slam.FrontEndConfig(model=model)
            row[f"front_end_{model}"], fe = time_front_end(ranges, az, odo, cfg, rate)
            row[f"front_end_{model}"]["backend"] = _native.resolve(cfg.backend)
            if model == "decay_rate":
                start = fe.poses
        # the grazing cut's cost: the decay-rate front end without it
        rec, _ = time_front_end(ranges, az, odo, slam.FrontEndConfig(grazing_cells=0.0), rate)
        rec["grazing_cost"] = rec["scans_per_s"] / row["front_end_decay_rate"]["scans_per_s"]
        row["front_end_decay_rate_no_grazing"] = rec
        # the decay-rate front end on the pure-JAX optical depth (the fallback and
        # oracle of the native kernel, which "auto" picks on a CPU where it is built)
        rec, _ = time_front_end(ranges, az, odo, slam.FrontEndConfig(backend="jax"), rate)
        rec["backend"] = "jax"
        rec["native_speedup"] = row["front_end_decay_rate"]["scans_per_s"] / rec["scans_per_s"]
        row["front_end_decay_rate_jax"] = rec
        row["scan_objective"] = time_scan_objective(ranges, az, start)
        loops = slam.find_loops(ranges, az, start)
        load = os.getloadavg()[0]
        times = []
        for _ in range(3):
            t = time.perf_counter()
            revisits = slam.find_revisits(ranges, az, start)
            times.append(time.perf_counter() - t)
        row["find_revisits"] = {
            "load_1min_before": load,
            "seconds_best_of_3": min(times),
            "candidates": int(revisits.n_tried),
            "revisits": int(len(revisits.edges)),
        }
        # the reference-free consistency scores of the front end's trajectory (best of 3;
        # the log-likelihood after a compiling call)
        slam.trajectory_log_likelihood(start, az, ranges)
        for key, fn in (
            ("cross_visit_distance", lambda: cross_visit_distance(start, ranges, az)),
            (
                "trajectory_log_likelihood",
                lambda: slam.trajectory_log_likelihood(start, az, ranges),
            ),
        ):
            load = os.getloadavg()[0]
            times = []
            for _ in range(3):
                t = time.perf_counter()
                fn()
                times.append(time.perf_counter() - t)
            row[key] = {"load_1min_before": load, "seconds_best_of_3": min(times)}
        # the plain chain (no odometry, no revisits) and the default (robust chain with
        # the odometry and the revisits)
        for robust in (False, True):
            cfg = slam.SlamConfig(robust_chain=robust)
            rv = revisits if robust else None
            slam.front_end_pose_graph(start, odo, loops, cfg, rv).poses.block_until_ready()
            load = os.getloadavg()[0]
            times = []
            for _ in range(3):
                t = time.perf_counter()
                pg = slam.front_end_pose_graph(start, odo, loops, cfg, rv)
                pg.poses.block_until_ready()
                times.append(time.perf_counter() - t)
            row["pose_graph_robust_chain" if robust else "pose_graph_plain_chain"] = {
                "load_1min_before": load,
                "seconds_best_of_3": min(times),
                "iterations": int(pg.n_iters),
                "poses": n,
                "loops": int(len(loops.edges)),
                "revisits": 0 if rv is None else int(len(rv.edges)),
            }
        load = os.getloadavg()[0]
        t = time.perf_counter()
        ic = slam.icp_pose_graph_slam(ranges, az, odo, max_range_m=log.usable_range_m)
        row["icp_gtsam"] = {
            "load_1min_before": load,
            "seconds_total": time.perf_counter() - t,
            "front_end_scans_per_s": n / max(ic.seconds_front_end, 1e-9),
            "seconds_back_end": ic.seconds_back_end,
        }
        edges = np.stack([np.arange(n - 1), np.arange(1, n)], 1)
        inc = between_np(odo[:-1], odo[1:])
        sig = slam.odometry_sigmas(inc, slam.FrontEndConfig())
        for kind, f, cfg in (
            ("joint", slam.optimize_joint, slam.BackEndConfig(max_steps=args.steps)),
            (
                "alternating",
                slam.optimize_alternating,
                slam.BackEndConfig(max_steps=args.steps, rounds=1),
            ),
        ):
            # first call compiles; the second is timed
            f(start, az, ranges, edges, inc, sig, slam.BackEndConfig(max_steps=1, rounds=1))
            load = os.getloadavg()[0]
            r = f(start, az, ranges, edges, inc, sig, cfg)
            row[f"back_end_{kind}"] = {
                "load_1min_before": load,
                "seconds": r.seconds,
                "seconds_per_iteration": r.seconds_per_iteration,
                "iterations": args.steps,
                "rays": n * az.shape[0],
            }
        report["logs"][name] = row
        print(name, {k: v for k, v in row.items()})
    write_json(OUT, report)
    print("wrote", OUT)


if __name__ == "__main__":
    main()
