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
   with 300 particles (native backend, all cores; the JAX backend too with ``--run-jax``).

Backends: every step and measurement update is timed with the native C++ fold
(``ScanModel(backend="native", threads=1)`` and ``threads=2``) and with the pure-JAX fold
(``backend="jax"``) in the same run, from the same particles on the same scans. Ratios
``native/JAX`` and ``native/NumPy`` are speed ratios (the other path's time per step divided
by the native one's). Goals (2 cores): <= 15 ms per step at 300 particles and <= 120 ms at
3 000 particles x 180 beams. Every timed block records the 1-minute load average right
before it and is rerun after waiting for the load to drop when it was above 0.5
(:mod:`benchmarks._harness`).

Run with ``python benchmarks/particle_filter.py [--quick] [--out PATH] [--wait-budget S]
[--run-jax]``. Results go to ``benchmarks/results/particle_filter.json`` and a Markdown table
is printed.
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
    time_calls,
    warm,
    write_json,
)
from _numpy_pf import NumpyParticleFilter, scan_log_likelihoods

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
GOAL_S_PER_STEP = {300: 0.015, 3000: 0.120}  # native, 2 cores
VARIANTS = (("native_1t", "native", 1), ("native_2t", "native", 2), ("jax", "jax", None))
CHECK_RTOL = 1e-3


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
    """Per-ray and per-particle agreement of the JAX (float32) and NumPy (float64) values,
    with and without the boundary-tie rays (:func:`_harness.max_abs_diff` of the ``[n b]``
    rays and of the ``[n]`` per-particle sums)."""
    j = np.asarray(jax_rays, np.float64)
    keep = ~ties
    n_gt = "n_rel_diff_gt_1e-3"  # the count above CHECK_RTOL in max_abs_diff's record
    rays = max_abs_diff(j, np_rays, rel_tol=CHECK_RTOL)
    sums = max_abs_diff(j.sum(1), np_rays.sum(1), rel_tol=CHECK_RTOL)
    rays_nt = max_abs_diff(j[keep], np_rays[keep], rel_tol=CHECK_RTOL)
    sums_nt = max_abs_diff(np.where(keep, j, 0.0).sum(1), np.where(keep, np_rays, 0.0).sum(1))
    nonfinite = rays["n_finite_mismatch"] + rays["n_mismatch_both_nonfinite"]
    return {
        "n_particles": int(j.shape[0]),
        "n_rays": int(j.size),
        "max_abs_diff_sum": sums["max_abs_diff"],
        "max_rel_diff_sum": sums["max_rel_diff"],
        "n_particles_rel_diff_sum_gt_1e-3": sums[n_gt],
        "max_abs_diff_ray": rays["max_abs_diff"],
        "n_rays_rel_diff_gt_1e-3": rays[n_gt],
        "n_boundary_tie_rays": int(ties.sum()),
        "n_rays_rel_diff_gt_1e-3_not_ties": rays_nt[n_gt],
        "max_abs_diff_ray_not_ties": rays_nt["max_abs_diff"] or 0.0,
        "max_rel_diff_sum_without_ties": sums_nt["max_rel_diff"],
        "rays": rays,
        "sums": sums,
        "agree": bool(
            nonfinite == 0
            and sums_nt["max_rel_diff"] is not None
            and sums_nt["max_rel_diff"] <= CHECK_RTOL
        ),
    }


def _scan_period(timestamps) -> float:
    dt = np.diff(np.asarray(timestamps, np.float64))
    return float(np.median(dt[dt > 0]))


def _timed_steps(step, state, controls, zs, truth, k0: int, n_steps: int) -> dict:
    """``n_steps`` warm steps from ``state`` on scans ``k0 + 1 ...`` (a rerun repeats them),
    each timed by :func:`_harness.time_calls`; the estimate errors are taken afterwards."""
    carry = {"state": state, "k": k0, "estimates": []}

    def one_step():
        k = carry["k"] = carry["k"] + 1
        carry["state"], info = out = step(carry["state"], controls[k], zs[k])
        carry["estimates"].append((k, info.estimate))
        return out

    timed = time_calls(one_step, n_steps, warmup=0)
    errs = []
    for k, estimate in carry["estimates"]:
        est = np.asarray(to_vector(estimate))
        errs.append(float(np.hypot(*(est[:2] - truth[k, :2]))))
    return {**timed, "estimate_error_m": errs, "_state": carry["state"], "_k": carry["k"]}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="300 particles, few steps, short run")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--run-jax", action="store_true", help="whole-log run with JAX too (+80 s)")
    add_policy_args(ap)
    args = ap.parse_args(argv)
    policy = policy_from_args(args)
    t_start = time.perf_counter()
    quick = args.quick
    counts = [300] if quick else [300, 3000, 30000]
    steps_n = {300: 3} if quick else {300: 9, 3000: 7, 30000: 1}
    np_steps = {300: 1} if quick else {300: 5, 3000: 2, 30000: 1}
    load_start = os.getloadavg()
    machine_native = native_info()

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
    dm = maps.decay_rate_map(jax.block_until_ready(accumulate(spec, rays, backend="jax")))
    controls = np.asarray(relative_motion(log.odometry[odd]))  # [T 3], odd k -> odd k + 1
    zs = log.ranges_m[odd[1:]]  # measurement of each step
    truth = P[odd[1:]]

    motion = OdometryMotionModel(SIGMA, ALPHA)
    sensors, pfs, steps = {}, {}, {}
    for label, backend, threads in VARIANTS:
        sensors[label] = ScanModel(
            dm, az, 0.0, r_max, ray_floor=RAY_FLOOR, backend=backend, threads=threads
        )
        pfs[label] = ParticleFilter(motion, sensors[label])
        steps[label] = eqx.filter_jit(pfs[label].step)
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
        print(f"{n} particles:", flush=True)
        key = jax.random.key(n)
        state0 = init_gaussian(n, P[odd[START]], INIT_STD, key=key)
        p0 = np.asarray(to_vector(state0.particles), np.float64)
        rays_per_step = n * az.size
        entry: dict = {"particles": n, "beams": int(az.size)}
        last = {}
        for label, _, _ in VARIANTS:
            step = steps[label]
            try:
                (state1, _), first = warm(
                    lambda step=step: step(state0, controls[START], zs[START])
                )
            except Exception as e:  # noqa: BLE001 - recorded; the other paths still count
                entry[label] = {"error": f"{type(e).__name__}: {e}"}
                print(f"  {label} FAILED: {e}", flush=True)
                continue
            timed = policy.measure(
                f"{n} {label} step",
                lambda step=step, state1=state1: _timed_steps(
                    step, state1, controls, zs, truth, START, steps_n[n]
                ),
            )
            last[label] = (timed.pop("_state"), timed.pop("_k"))
            entry[label] = {
                "first_step_s": first,
                "s_per_step": timed["median_s"],
                "ms_per_step": 1e3 * timed["median_s"],
                "ms_per_step_best": 1e3 * timed["best_s"],
                "step_times_s": timed["times_s"],
                "rays_per_s": rays_per_step / timed["median_s"],
                "estimate_error_m": timed["estimate_error_m"],
                "load": timed["load"],
            }

        # measurement update alone (same particles, same scan for every backend)
        ref_label = next((lb for lb in ("jax", "native_2t", "native_1t") if lb in last), None)
        if ref_label is None:
            raise RuntimeError(f"every backend failed at {n} particles")
        state_m, k = last[ref_label]
        z, particles = zs[k], state_m.particles
        pv = np.asarray(to_vector(particles), np.float64)
        t0 = time.perf_counter()
        np_ray_ll = scan_log_likelihoods(pv, z, per_ray=True, **scan_kwargs)
        np_measure = time.perf_counter() - t0
        ties = _boundary_ties(pv, z, az, kind[odd[1:]][k], scan_kwargs["grid_origin"], RESOLUTION)
        ray_lls = {}
        for label, _, _ in VARIANTS:
            if "error" in entry.get(label, {"error": 1}):
                continue
            sensor = sensors[label]

            def call(sensor=sensor):
                return measure(sensor, particles, z)

            ray_lls[label], _ = warm(call)
            timed = policy.time_calls(
                f"{n} {label} measurement", call, 7 if n <= 3000 else 1, warmup=0
            )
            e = entry[label]
            e["measurement_only_s"] = timed["median_s"]
            e["measurement_only_ms"] = 1e3 * timed["median_s"]
            e["measurement_only_ms_best"] = 1e3 * timed["best_s"]
            e["measurement_fraction_of_step"] = timed["median_s"] / e["s_per_step"]
            e["measurement_load"] = timed["load"]
            e["check_vs_numpy"] = _compare(ray_lls[label], np_ray_ll, ties)
        for label in ("native_1t", "native_2t"):
            if label in ray_lls and "jax" in ray_lls:
                a = np.asarray(ray_lls[label], np.float64)
                b = np.asarray(ray_lls["jax"], np.float64)
                rays = max_abs_diff(a, b, rel_tol=CHECK_RTOL)
                sums = max_abs_diff(a.sum(1), b.sum(1))
                entry[label]["vs_jax_rays"] = {
                    "max_abs_diff_ray": rays["max_abs_diff"],
                    "n_rays_rel_diff_gt_1e-3": rays["n_rel_diff_gt_1e-3"],
                    "max_rel_diff_sum": sums["max_rel_diff"],
                    "rays": rays,
                }

        # NumPy step from the same initial particles over the same scans
        def np_block(n=n, p0=p0):
            carry = {"rng": np.random.default_rng(n), "parts": p0, "lw": np.full(n, -math.log(n))}
            carry["i"] = 0

            def np_step():
                i = carry["i"]
                carry["parts"], carry["lw"], _, _, _ = npf.step(
                    carry["rng"], carry["parts"], carry["lw"], controls[START + i], zs[START + i]
                )
                carry["i"] = i + 1

            n_run = np_steps[n] + (1 if n <= 3000 else 0)
            warmup = 1 if n_run > 1 else 0  # the first step only mirrors the JAX warm-up step
            return time_calls(np_step, n_run - warmup, warmup=warmup)

        np_t = policy.measure(f"{n} numpy step", np_block)
        s_np = np_t["median_s"]
        entry["numpy"] = {
            "s_per_step": s_np,
            "ms_per_step": 1e3 * s_np,
            "step_times_s": np_t["times_s"],
            "n_steps_timed": len(np_t["times_s"]),
            "extrapolated": False,
            "rays_per_s": rays_per_step / s_np,
            "measurement_only_s": np_measure,
            "load": np_t["load"],
        }
        jx = entry.get("jax", {})
        for label in ("native_1t", "native_2t", "jax"):
            e = entry.get(label, {})
            if "s_per_step" not in e:
                continue
            e["numpy_over_this"] = s_np / e["s_per_step"]
            if label != "jax":
                e["native_over_jax"] = ratio(jx.get("s_per_step"), e["s_per_step"])
                e["native_over_jax_measurement"] = ratio(
                    jx.get("measurement_only_s"), e.get("measurement_only_s")
                )
                e["native_over_numpy"] = s_np / e["s_per_step"]
        entry["numpy_over_jax"] = ratio(s_np, jx.get("s_per_step"))
        goal = GOAL_S_PER_STEP.get(n)
        if goal is not None:
            n2 = entry.get("native_2t", {})
            entry["goal"] = {
                "target_s_per_step": goal,
                "native_2t_s_per_step": n2.get("s_per_step"),
                "met": bool(n2.get("s_per_step") is not None and n2["s_per_step"] <= goal),
                "native_2t_measurement_only_s": n2.get("measurement_only_s"),
            }
        per_count[str(n)] = entry
        summary = ", ".join(
            f"{lb} {entry[lb]['ms_per_step']:.1f} ms/step "
            f"(meas {entry[lb].get('measurement_only_ms', float('nan')):.1f} ms)"
            for lb, _, _ in VARIANTS
            if "ms_per_step" in entry.get(lb, {})
        )
        print(f"{n} particles: {summary}, numpy {1e3 * s_np:.1f} ms/step", flush=True)

    # ------------------------------------------------------------------ whole log
    n_run = 300
    n_steps = 20 if quick else controls.shape[0]
    c, m = jnp.asarray(controls[:n_steps]), jnp.asarray(zs[:n_steps])
    period = _scan_period(log.timestamps_s)
    duration = n_steps * 2 * period  # each step spans two scans of the log
    runs = {}
    run_variants = [("native", pfs["native_2t"])]
    if args.run_jax:
        run_variants.append(("jax", pfs["jax"]))
    for label, pf in run_variants:
        state0 = init_gaussian(n_run, P[odd[0]], INIT_STD, key=jax.random.key(1))
        try:
            _, run_first = warm(lambda pf=pf, state0=state0: pf.run(state0, c, m))
        except Exception as e:  # noqa: BLE001
            runs[label] = {"error": f"{type(e).__name__}: {e}"}
            continue
        state0 = init_gaussian(n_run, P[odd[0]], INIT_STD, key=jax.random.key(2))
        holder = {}

        def run_block(pf=pf, state0=state0, holder=holder):
            timed, holder["out"] = time_calls(
                lambda: pf.run(state0, c, m), 1, warmup=0, return_output=True
            )
            return timed

        timed = policy.measure(f"run {label}", run_block)
        run_wall = timed["median_s"]
        _, infos = holder["out"]
        est = np.asarray(to_vector(infos.estimate))
        err = np.hypot(*(est[:, :2] - truth[:n_steps, :2]).T)
        runs[label] = {
            "backend": label,
            "threads": 2 if label == "native" else None,
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
                "timestamp difference of all scans (each step spans two scans); raw span of "
                f"the timestamps {float(np.ptp(log.timestamps_s)):.1f} s"
            ),
            "real_time_factor": run_wall / duration,
            "real_time_factor_note": "wall time / log duration; < 1 is faster than real time",
            "resampled_steps": int(np.asarray(infos.resampled).sum()),
            "degenerate_steps": int(np.asarray(infos.degenerate).sum()),
            "estimate_error_m_median": float(np.median(err)),
            "estimate_error_m_p95": float(np.percentile(err, 95)),
            "load": timed["load"],
        }
        print(
            f"run ({label}): {n_steps} steps x {n_run} particles in {run_wall:.2f} s "
            f"({n_steps / run_wall:.1f} scans/s, real-time factor {run_wall / duration:.2e})",
            flush=True,
        )

    goals = {str(n): per_count[str(n)]["goal"] for n in counts if "goal" in per_count[str(n)]}
    report = {
        "machine": machine_info(
            numpy_dtype="float64",
            native=machine_native,
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
            "chunk_size": sensors["jax"].chunk_size,
            "variants": [list(v) for v in VARIANTS],
            "timing": "warm-up step (compile), then median over consecutive real scans",
            "ratio_note": "native_over_X = X's time per step / native's (higher is faster)",
        },
        "particle_counts": per_count,
        "run": runs.get("native"),
        "runs": runs,
        "goal": goals,
        "load_policy": policy.summary(),
        "wall_time_s": time.perf_counter() - t_start,
    }
    write_json(args.out, report)

    def f(e, key, fmt):
        v = e.get(key)
        return "-" if v is None else format(v, fmt)

    lines = [
        f"Intel decay-rate map {spec.shape[0]}x{spec.shape[1]} cells of {RESOLUTION} m, "
        f"{az.size} beams, r_max {r_max:.1f} m, {jax.default_backend()} "
        f"({os.cpu_count()} cores), {report['machine']['dtype']}; ms per step "
        "(measurement update alone in brackets), median",
        "",
        "| particles | native 1t | native 2t | JAX | NumPy | 2t/JAX | 1t/JAX | 2t/NumPy "
        "| load (2t) | goal |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for n, r in per_count.items():
        n1, n2, jx = r.get("native_1t", {}), r.get("native_2t", {}), r.get("jax", {})

        def ms(e):
            if "ms_per_step" not in e:
                return "failed"
            return f"{e['ms_per_step']:.1f} ({e.get('measurement_only_ms', float('nan')):.1f})"

        g = r.get("goal")
        gs = (
            "-"
            if g is None
            else f"≤ {1e3 * g['target_s_per_step']:.0f}: " + ("met" if g["met"] else "NOT met")
        )
        lines.append(
            f"| {n} | {ms(n1)} | {ms(n2)} | {ms(jx)} | {r['numpy']['ms_per_step']:.1f} | "
            f"{f(n2, 'native_over_jax', '.2f')} | {f(n1, 'native_over_jax', '.2f')} | "
            f"{f(n2, 'native_over_numpy', '.1f')} | "
            f"{f(n2.get('load', {}), 'load_1min', '.2f')} | {gs} |"
        )
    for label, run in runs.items():
        if "error" in run:
            lines.append(f"Whole log ({label}): FAILED {run['error']}")
            continue
        lines += [
            "",
            f"Whole log ({label}, {run['particles']} particles): {run['scans_per_s']:.1f} "
            f"scans/s, real-time factor {run['real_time_factor']:.2e}, median error "
            f"{run['estimate_error_m_median']:.3f} m",
        ]
    print("\n".join(lines))
    print(f"\n(wall time {report['wall_time_s']:.0f} s; JSON: {args.out})")
    return report


if __name__ == "__main__":
    main()
