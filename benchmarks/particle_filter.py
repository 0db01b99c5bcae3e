"""Particle filter step of :mod:`lidarjax.localization` against a plain NumPy step.

Setup: a decay-rate map (Eq. 7.10) of the Intel Research Lab built from the even-numbered
scans at their SLAM-corrected poses, 0.1 m cells; the filter localizes on the odd-numbered
scans (180 beams, ``r_min`` 0, ``r_max`` = the log's usable range, per-ray floor -10 nats)
with an :class:`~lidarjax.localization.OdometryMotionModel` driven by the raw odometry
between consecutive odd scans and a :class:`~lidarjax.localization.ScanModel`.

Measured:

1. Seconds per :meth:`ParticleFilter.step` (motion update, measurement update, estimate,
   resampling), ``eqx.filter_jit``-ed, for 300 / 3000 / 30000 particles spread like a
   tracking filter (Gaussian 0.1 m / 0.05 rad around the true pose), on consecutive real
   scans: one warm-up step (compilation, reported separately), then the median of the
   following steps (``jax.block_until_ready``). The measurement update alone is timed too.
2. The same step in NumPy (:mod:`benchmarks._numpy_pf`, float64, vectorised over rays),
   timed in the same run on the same scans, and the per-particle log-likelihoods of both
   on the same particles compared.
3. Real-time factor of :meth:`ParticleFilter.run` (one ``lax.scan``) over all odd scans
   with 300 particles.

Run with ``python benchmarks/particle_filter.py [--quick] [--out PATH]``. Results go to
``benchmarks/results/particle_filter.json`` and a Markdown table is printed.
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

if __package__ in (None, ""):  # run as a script: make `benchmarks` and `lidarjax` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from _machine import machine_info

from benchmarks._numpy_pf import NumpyParticleFilter, scan_log_likelihoods
from lidarjax import maps
from lidarjax.datasets import fetch, load_carmen
from lidarjax.localization import (
    OdometryMotionModel,
    ParticleFilter,
    ScanModel,
    init_gaussian,
    relative_motion,
    to_vector,
)
from lidarjax.rays import HIT, from_scan
from lidarjax.raytrace import GridSpec, accumulate

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "particle_filter.json"

RESOLUTION = 0.1
RAY_FLOOR = -10.0
INIT_STD = (0.1, 0.1, 0.05)
# Motion noise per odd-scan step (two scans, ~1 m and ~0.5 rad of motion): a constant part
# plus a part proportional to the odometry increment.
SIGMA = (0.05, 0.05, 0.02)
ALPHA = ((0.1, 0.0, 0.0), (0.0, 0.1, 0.0), (0.02, 0.02, 0.1))
START = 100  # first odd scan (index into the odd scans) of the timed steps
GOAL_S_PER_STEP = 0.05
CHECK_RTOL = 1e-3


def _median_time(fn, repeats: int) -> tuple[list[float], object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return times, out


def _boundary_ties(poses, ranges, azimuths, kind, origin, res) -> np.ndarray:
    """``[n b]`` True for HIT rays whose end point lies within float32 round-off of a cell
    boundary: there float32 (JAX) and float64 (NumPy) may put the end into different
    cells, which changes ``log lambda_k`` by up to the per-ray floor."""
    th = poses[:, 2:3] + azimuths[None, :]
    ex = poses[:, 0:1] + ranges[None, :] * np.cos(th)
    ey = poses[:, 1:2] + ranges[None, :] * np.sin(th)
    eps = float(np.finfo(np.float32).eps)
    scale = np.abs(ex) + np.abs(ey) + ranges[None, :] + res
    close = np.zeros(ex.shape, bool)
    for e, lo in ((ex, origin[0]), (ey, origin[1])):
        u = (e - lo) / res
        close |= np.abs(u - np.round(u)) * res < 64 * eps * scale
    return close & (kind[None, :] == HIT)


def _compare(jax_rays, np_rays, ties) -> dict:
    """Per-ray and per-particle agreement of the JAX (float32) and NumPy (float64) values."""
    j = np.asarray(jax_rays, np.float64)
    diff = np.abs(j - np_rays)
    rel = diff / np.maximum(np.abs(np_rays), 1.0)
    sums_j, sums_n = j.sum(1), np_rays.sum(1)
    rel_sum = np.abs(sums_j - sums_n) / np.maximum(np.abs(sums_n), 1.0)
    keep = ~ties
    sj, sn = np.where(keep, j, 0.0).sum(1), np.where(keep, np_rays, 0.0).sum(1)
    rel_sum_nt = np.abs(sj - sn) / np.maximum(np.abs(sn), 1.0)
    return {
        "n_particles": int(j.shape[0]),
        "n_rays": int(j.size),
        "max_abs_diff_sum": float(np.abs(sums_j - sums_n).max()),
        "max_rel_diff_sum": float(rel_sum.max()),
        "n_particles_rel_diff_sum_gt_1e-3": int((rel_sum > CHECK_RTOL).sum()),
        "max_abs_diff_ray": float(diff.max()),
        "n_rays_rel_diff_gt_1e-3": int((rel > CHECK_RTOL).sum()),
        "n_boundary_tie_rays": int(ties.sum()),
        "n_rays_rel_diff_gt_1e-3_not_ties": int(((rel > CHECK_RTOL) & keep).sum()),
        "max_abs_diff_ray_not_ties": float(diff[keep].max()) if keep.any() else 0.0,
        "max_rel_diff_sum_without_ties": float(rel_sum_nt.max()),
        "agree": bool(rel_sum_nt.max() <= CHECK_RTOL),
    }


def _scan_period(timestamps) -> float:
    dt = np.diff(np.asarray(timestamps, np.float64))
    return float(np.median(dt[dt > 0]))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="300 particles, few steps, short run")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    quick = args.quick
    counts = [300] if quick else [300, 3000, 30000]
    jax_steps = {300: 2} if quick else {300: 9, 3000: 5, 30000: 2}
    np_steps = {300: 1} if quick else {300: 5, 3000: 2, 30000: 1}
    load_start = os.getloadavg()

    # ------------------------------------------------------------------ map and data
    log = load_carmen(fetch("intel"))
    r_max = float(log.usable_range_m)
    P, az = log.poses, log.azimuths_rad
    even = np.arange(0, log.n_scans, 2)
    odd = np.arange(1, log.n_scans, 2)
    rays = from_scan(
        jaxlie.SE2.from_xy_theta(P[even, 0], P[even, 1], P[even, 2]),
        az,
        log.ranges_m[even],
        0.0,
        r_max,
    )
    ends = np.asarray(rays.endpoints())[np.asarray(rays.kind) == HIT]
    spec = GridSpec.covering(np.concatenate([ends, P[:, :2]]), RESOLUTION, margin=3.0)
    dm = maps.decay_rate_map(jax.block_until_ready(accumulate(spec, rays)))
    controls = np.asarray(relative_motion(log.odometry[odd]))  # [T 3], odd k -> odd k + 1
    zs = log.ranges_m[odd[1:]]  # measurement of each step
    truth = P[odd[1:]]

    sensor = ScanModel(dm, az, 0.0, r_max, ray_floor=RAY_FLOOR)
    pf = ParticleFilter(OdometryMotionModel(SIGMA, ALPHA), sensor)
    step = eqx.filter_jit(pf.step)
    measure = eqx.filter_jit(lambda m, p, z: m.ray_log_likelihoods(p, z))
    scan_kwargs = {
        "rates": np.asarray(dm.rates, np.float64),
        "outside_rate": float(dm.outside_rate),
        "grid_origin": np.asarray(spec.origin, np.float64),
        "resolution": RESOLUTION,
        "azimuths": az,
        "r_min": 0.0,
        "r_max": r_max,
        "ray_floor": RAY_FLOOR,
    }
    npf = NumpyParticleFilter(SIGMA, ALPHA, scan_kwargs)
    kind = np.where(np.asarray(log.ranges_m) >= r_max, 2, HIT)

    # ------------------------------------------------------------------ steps
    per_count = {}
    for n in counts:
        key = jax.random.key(n)
        state = init_gaussian(n, P[odd[START]], INIT_STD, key=key)
        p0 = np.asarray(to_vector(state.particles), np.float64)
        k = START
        t0 = time.perf_counter()
        state, info = jax.block_until_ready(step(state, controls[k], zs[k]))
        first = time.perf_counter() - t0
        times, errs = [], []
        for _ in range(jax_steps[n]):
            k += 1
            t0 = time.perf_counter()
            state, info = jax.block_until_ready(step(state, controls[k], zs[k]))
            times.append(time.perf_counter() - t0)
            est = np.asarray(to_vector(info.estimate))
            errs.append(float(np.hypot(*(est[:2] - truth[k, :2]))))
        s_jax = statistics.median(times)

        # measurement update alone (same particles, same scan), and the comparison
        z, particles = zs[k], state.particles
        jax.block_until_ready(measure(sensor, particles, z))
        m_times, ray_ll = _median_time(lambda: measure(sensor, particles, z), 1 if n > 3000 else 3)
        pv = np.asarray(to_vector(particles), np.float64)
        t0 = time.perf_counter()
        np_ray_ll = scan_log_likelihoods(pv, z, per_ray=True, **scan_kwargs)
        np_measure = time.perf_counter() - t0
        ties = _boundary_ties(pv, z, az, kind[odd[1:]][k], scan_kwargs["grid_origin"], RESOLUTION)
        check = _compare(ray_ll, np_ray_ll, ties)

        # NumPy step from the same initial particles over the same scans
        rng = np.random.default_rng(n)
        parts, lw = p0, np.full(n, -math.log(n))
        np_times = []
        for i in range(np_steps[n] + 1):
            t0 = time.perf_counter()
            parts, lw, _, _, _ = npf.step(rng, parts, lw, controls[START + i], zs[START + i])
            if i:  # the first step only mirrors the JAX warm-up step
                np_times.append(time.perf_counter() - t0)
        s_np = statistics.median(np_times)
        rays_per_step = n * az.size
        per_count[str(n)] = {
            "particles": n,
            "beams": int(az.size),
            "jax": {
                "first_step_s": first,
                "s_per_step": s_jax,
                "step_times_s": times,
                "rays_per_s": rays_per_step / s_jax,
                "measurement_only_s": statistics.median(m_times),
                "measurement_fraction_of_step": statistics.median(m_times) / s_jax,
                "estimate_error_m": errs,
            },
            "numpy": {
                "s_per_step": s_np,
                "step_times_s": np_times,
                "n_steps_timed": len(np_times),
                "extrapolated": False,
                "rays_per_s": rays_per_step / s_np,
                "measurement_only_s": np_measure,
            },
            "numpy_over_jax": s_np / s_jax,
            "check_jax_vs_numpy": check,
        }
        print(
            f"{n} particles: jax {s_jax:.4g} s/step ({rays_per_step / s_jax:.3g} rays/s, "
            f"first {first:.1f} s), numpy {s_np:.4g} s/step, numpy/jax {s_np / s_jax:.2f}, "
            f"max rel diff of sums {check['max_rel_diff_sum']:.2e} "
            f"({check['max_rel_diff_sum_without_ties']:.2e} without boundary ties)",
            flush=True,
        )

    # ------------------------------------------------------------------ whole log
    n_run = 300
    n_steps = 20 if quick else controls.shape[0]
    state0 = init_gaussian(n_run, P[odd[0]], INIT_STD, key=jax.random.key(1))
    c, m = jnp.asarray(controls[:n_steps]), jnp.asarray(zs[:n_steps])
    t0 = time.perf_counter()
    jax.block_until_ready(pf.run(state0, c, m))
    run_first = time.perf_counter() - t0
    state0 = init_gaussian(n_run, P[odd[0]], INIT_STD, key=jax.random.key(2))
    t0 = time.perf_counter()
    _, infos = jax.block_until_ready(pf.run(state0, c, m))
    run_wall = time.perf_counter() - t0
    period = _scan_period(log.timestamps_s)
    duration = n_steps * 2 * period  # each step spans two scans of the log
    est = np.asarray(to_vector(infos.estimate))
    err = np.hypot(*(est[:, :2] - truth[:n_steps, :2]).T)
    run = {
        "particles": n_run,
        "steps": int(n_steps),
        "first_call_s": run_first,
        "wall_s": run_wall,
        "s_per_step": run_wall / n_steps,
        "scans_per_s": n_steps / run_wall,
        "scan_period_s": period,
        "log_duration_s": duration,
        "duration_note": (
            "Intel timestamps are not monotone: duration = steps * 2 * median positive "
            "timestamp difference of all scans (each step spans two scans); raw span of the "
            f"timestamps {float(np.ptp(log.timestamps_s)):.1f} s"
        ),
        "real_time_factor": run_wall / duration,
        "real_time_factor_note": "wall time / log duration; < 1 is faster than real time",
        "resampled_steps": int(np.asarray(infos.resampled).sum()),
        "degenerate_steps": int(np.asarray(infos.degenerate).sum()),
        "estimate_error_m_median": float(np.median(err)),
        "estimate_error_m_p95": float(np.percentile(err, 95)),
    }
    print(
        f"run: {n_steps} steps x {n_run} particles in {run_wall:.2f} s "
        f"({n_steps / run_wall:.1f} scans/s, real-time factor {run_wall / duration:.2e})",
        flush=True,
    )

    s300 = per_count["300"]["jax"]["s_per_step"]
    report = {
        "machine": machine_info(
            numpy_dtype="float64",
            load_average_start=list(load_start),
            load_average_end=list(os.getloadavg()),
        ),
        "quick": quick,
        "setup": {
            "log": "intel",
            "map_scans": int(even.size),
            "map_scans_note": "even-numbered scans at corrected poses; filter on odd scans",
            "resolution_m": RESOLUTION,
            "grid_shape": list(spec.shape),
            "r_min_m": 0.0,
            "r_max_m": r_max,
            "ray_floor": RAY_FLOOR,
            "beams": int(az.size),
            "init_std": list(INIT_STD),
            "motion_sigma": list(SIGMA),
            "motion_alpha": [list(a) for a in ALPHA],
            "first_step_odd_index": START,
            "chunk_size": sensor.chunk_size,
            "timing": "warm-up step, then median over consecutive real scans",
        },
        "particle_counts": per_count,
        "run": run,
        "goal": {
            "target": f"<= {GOAL_S_PER_STEP} s/step at 300 particles x 180 beams",
            "jax_s_per_step_300": s300,
            "met": bool(s300 <= GOAL_S_PER_STEP),
        },
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2))
    lines = [
        f"Intel decay-rate map {spec.shape[0]}x{spec.shape[1]} cells of {RESOLUTION} m, "
        f"{az.size} beams, r_max {r_max:.1f} m, {jax.default_backend()} "
        f"({os.cpu_count()} cores), {report['machine']['dtype']}",
        "",
        "| particles | JAX s/step | NumPy s/step | NumPy/JAX | JAX rays/s | max rel diff |",
        "|---|---|---|---|---|---|",
    ]
    for n, r in per_count.items():
        lines.append(
            f"| {n} | {r['jax']['s_per_step']:.4g} | {r['numpy']['s_per_step']:.4g} | "
            f"{r['numpy_over_jax']:.2f} | {r['jax']['rays_per_s']:.3g} | "
            f"{r['check_jax_vs_numpy']['max_rel_diff_sum']:.1e} |"
        )
    lines += [
        "",
        f"Whole log: {run['scans_per_s']:.1f} scans/s, real-time factor "
        f"{run['real_time_factor']:.2e}; goal <= {GOAL_S_PER_STEP} s/step at 300 particles: "
        f"{'met' if report['goal']['met'] else 'NOT met'} ({s300:.3f} s)",
    ]
    print("\n".join(lines))
    return report


if __name__ == "__main__":
    main()
