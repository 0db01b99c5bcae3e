"""The JAX paths on whatever ``jax.devices()[0]`` is (a GPU on a GPU machine): the particle
filter step, ``accumulate`` and the DCT map fit, against the same code on the CPU.

A short script for a GPU machine (``pip install -e . "jax[cuda12]"``, then
``python benchmarks/gpu.py``). The native (C++) kernels are CPU-only, so every call here
uses ``backend="jax"``; the same script runs on a CPU-only machine, where the device is
the CPU and no reference is timed.

Setup: a simulated office (:func:`lidarjax.sim.make_office`, 20 m x 12 m) with scans along
its loop (10 m range, 1 cm noise), float32 unless ``--x64``.

Measured on the device (``jax.default_device``):

1. Filter step: :class:`~lidarjax.localization.ParticleFilter` with an
   :class:`~lidarjax.localization.OdometryMotionModel` and a
   :class:`~lidarjax.localization.ScanModel` (``backend="jax"``, 45 beams, per-ray floor
   -10 nats) on a decay-rate map (0.1 m cells), ``--particles`` particles (default
   30 000): seconds per step from the median of ``--repeats`` timed
   :meth:`~lidarjax.localization.ParticleFilter.run` calls over ``--steps`` steps,
   divided by the steps (the first call, compilation included, separately).
2. :func:`lidarjax.raytrace.accumulate` (``backend="jax"``) of ``--rays`` rays (default
   10^6: 1000 scans of 1000 beams) into a 0.05 m grid: seconds and rays/s.
3. :func:`lidarjax.maps.fit_dct` (default L-BFGS) with ``--fit-shape`` coefficients per
   axis (default 20 x 20) on ``--fit-rays`` rays (default 10^4, drawn from the rays of
   2.): seconds of the whole fit (precomputation and solve), solver steps.

Reference, same run: when the device is not a CPU, the same three on
``jax.devices("cpu")[0]`` (also ``backend="jax"``), and the speed-ups device / CPU
(``--no-reference`` skips them). The load average is recorded before each timed block
(:mod:`benchmarks._harness`; its rerun policy too).

Run with ``python benchmarks/gpu.py [--quick] [--x64] [--no-reference] [--out PATH]``;
results go to ``benchmarks/results/gpu.json`` (``--quick``: tiny sizes, a smoke test
under a minute on a CPU, written to ``gpu_quick.json``) and a Markdown table is printed.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import jax
from _harness import (
    BUDGET_S,
    RESULTS,
    add_policy_args,
    machine_info,
    policy_from_args,
    ratio,
    write_json,
)

DEFAULT_OUT = RESULTS / "gpu.json"
QUICK_OUT = RESULTS / "gpu_quick.json"

FULL = {"particles": 30_000, "steps": 16, "rays": 1_000_000, "fit_rays": 10_000, "fit_shape": 20}
QUICK = {"particles": 512, "steps": 4, "rays": 20_000, "fit_rays": 500, "fit_shape": 6}


def _device_record(device) -> dict:
    rec = {
        "platform": device.platform,
        "device_kind": getattr(device, "device_kind", None),
        "id": device.id,
    }
    try:
        stats = device.memory_stats()
    except Exception:  # not every backend reports memory
        stats = None
    if stats:
        rec["bytes_limit"] = stats.get("bytes_limit")
    return rec


def _world(n_poses: int, n_beams: int):
    """The office, ``n_poses`` poses along its loop and their ``[n_poses n_beams]`` ranges."""
    import numpy as np

    from lidarjax.sim import make_office, simulate_scans

    world = make_office(0)
    poses = world.trajectory(n_poses, jitter_m=0.2, seed=0)
    az = np.linspace(-np.pi, np.pi, n_beams, endpoint=False)
    ranges = simulate_scans(world, poses, az, max_range_m=10.0, noise_sigma_m=0.01, seed=0)
    return world, poses, az, ranges


def _rays(poses, az, ranges):
    import jaxlie

    from lidarjax.rays import from_scan

    T_ws = jaxlie.SE2.from_xy_theta(poses[:, 0], poses[:, 1], poses[:, 2])
    return from_scan(T_ws, az, ranges, 0.05, 10.0)


def measure(device, sizes: dict, policy, tag: str) -> dict:
    """Time the filter step, ``accumulate`` and ``fit_dct`` with every array on ``device``."""
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
    from lidarjax.rays import RayBatch
    from lidarjax.raytrace import GridSpec, accumulate

    out: dict = {"device": _device_record(device)}
    with jax.default_device(device):
        # ---------------------------------------------------------------- accumulate
        n_beams = 1000 if sizes["rays"] >= 1000 * 100 else 200
        n_scans = max(1, sizes["rays"] // n_beams)
        world, poses, az, ranges = _world(n_scans, n_beams)
        rays = jax.device_put(_rays(poses, az, ranges), device)
        lo, hi = np.asarray(world.bounds[0]) - 0.5, np.asarray(world.bounds[1]) + 0.5
        fine = GridSpec.from_bounds(lo, hi, 0.05)
        rec, stats = policy.time_calls(
            f"{tag} accumulate {rays.n} rays",
            lambda: accumulate(fine, rays, backend="jax"),
            sizes["repeats"],
            return_output=True,
        )
        rec.update(
            rays=rays.n,
            grid_shape=list(fine.shape),
            rays_per_s=rays.n / rec["median_s"],
            hits=int(jnp.sum(stats.hits)),
        )
        out["accumulate"] = rec

        # ---------------------------------------------------------------- DCT fit
        rng = np.random.default_rng(0)
        n_fit = min(sizes["fit_rays"], rays.n)
        pick = np.sort(rng.choice(rays.n, n_fit, replace=False))
        flat = rays.flatten()
        fit_rays = RayBatch(
            *(np.asarray(x)[pick] for x in (flat.origins, flat.directions, flat.ranges, flat.kind)),
            flat.r_min,
            flat.r_max,
        )
        shape = (sizes["fit_shape"],) * 2
        side = np.full(2, np.max(hi - lo))  # a square box over the office: square cells

        def fit():
            m, sol = maps.fit_dct(fit_rays, shape, lower=lo, extent=side)
            return m.coeffs, sol.stats["num_steps"]

        rec, (_, steps) = policy.time_calls(
            f"{tag} fit_dct {shape[0]}x{shape[1]}, {n_fit} rays",
            fit,
            sizes["fit_repeats"],
            return_output=True,
        )
        rec.update(rays=n_fit, shape=list(shape), solver_steps=int(steps))
        out["fit_dct"] = rec

        # ---------------------------------------------------------------- filter step
        coarse = GridSpec.from_bounds(lo, hi, 0.1)
        dm = maps.decay_rate_map(accumulate(coarse, rays, backend="jax"))
        _, fposes, faz, franges = _world(sizes["steps"] + 1, 180)
        beams = slice(None, None, 4)
        model = ScanModel(dm, faz[beams], 0.05, 10.0, ray_floor=-10.0, backend="jax")
        pf = ParticleFilter(OdometryMotionModel([0.03, 0.03, 0.01], inflation=2.0), model)
        controls = np.asarray(relative_motion(fposes))
        zs = franges[1:, beams]
        state = init_gaussian(
            sizes["particles"], fposes[0], [0.1, 0.1, 0.05], key=jax.random.key(0)
        )
        state = jax.device_put(state, device)
        rec = policy.time_calls(
            f"{tag} filter n={sizes['particles']}",
            lambda: pf.run(state, controls, zs),
            sizes["repeats"],
        )
        rec.update(
            particles=sizes["particles"],
            steps=len(controls),
            beams=int(zs.shape[1]),
            step_s=rec["median_s"] / len(controls),
            best_step_s=rec["best_s"] / len(controls),
        )
        out["filter_step"] = rec
    return out


def _ms(x) -> str:
    return "–" if x is None else f"{x * 1e3:.2f}"


def markdown(report: dict) -> str:
    dev, ref = report["device"], report.get("reference")
    name = f"{dev['device']['platform']} ({dev['device']['device_kind']})"
    rows = [
        ("filter step", "step_s", "ms per step"),
        ("accumulate", "median_s", "ms"),
        ("fit_dct", "median_s", "ms"),
    ]
    keys = {"filter step": "filter_step", "accumulate": "accumulate", "fit_dct": "fit_dct"}
    lines = [
        f"| what | size | {name} | CPU reference | speed-up |",
        "|---|---|---|---|---|",
    ]
    for label, field, unit in rows:
        d = dev[keys[label]]
        r = ref[keys[label]] if ref else None
        if label == "filter step":
            size = f"{d['particles']} particles, {d['beams']} beams"
        elif label == "accumulate":
            size = f"{d['rays']} rays ({d['rays_per_s'] / 1e6:.2f} M rays/s)"
        else:
            size = f"{d['shape'][0]}x{d['shape'][1]}, {d['rays']} rays, {d['solver_steps']} steps"
        t_ref = r[field] if r else None
        speed = ratio(t_ref, d[field])
        lines.append(
            f"| {label} ({unit}) | {size} | {_ms(d[field])} | {_ms(t_ref)} | "
            f"{'–' if speed is None else f'{speed:.1f}x'} |"
        )
    return "\n".join(lines)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="tiny sizes: a smoke test only")
    ap.add_argument("--x64", action="store_true", help="float64 (default float32)")
    ap.add_argument("--particles", type=int, default=None, help="filter particles")
    ap.add_argument("--steps", type=int, default=None, help="filter steps per timed run")
    ap.add_argument("--rays", type=int, default=None, help="rays of accumulate")
    ap.add_argument("--fit-rays", type=int, default=None, help="rays of the DCT fit")
    ap.add_argument("--fit-shape", type=int, default=None, help="DCT coefficients per axis")
    ap.add_argument("--repeats", type=int, default=None, help="timed calls per block")
    ap.add_argument("--no-reference", action="store_true", help="do not time the CPU reference")
    ap.add_argument("--out", type=Path, default=None)
    add_policy_args(ap)
    ap.set_defaults(wait_budget=None)  # --quick: no waiting for a quiet machine
    args = ap.parse_args(argv)
    if args.wait_budget is None:
        args.wait_budget = 0.0 if args.quick else BUDGET_S
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    sizes = dict(QUICK if args.quick else FULL)
    for key in ("particles", "steps", "rays", "fit_rays", "fit_shape"):
        if getattr(args, key) is not None:
            sizes[key] = getattr(args, key)
    sizes["repeats"] = args.repeats or (1 if args.quick else 5)
    sizes["fit_repeats"] = args.repeats or (1 if args.quick else 3)
    policy = policy_from_args(args)

    device = jax.devices()[0]
    print(f"device: {device.platform} {getattr(device, 'device_kind', '')}", flush=True)
    report: dict = {"benchmark": "gpu", "quick": args.quick, "sizes": sizes}
    report["device"] = measure(device, sizes, policy, device.platform)
    reference = None
    if device.platform != "cpu" and not args.no_reference:
        cpu = jax.devices("cpu")[0]
        print("CPU reference ...", flush=True)
        reference = measure(cpu, sizes, policy, "cpu")
    report["reference"] = reference
    if reference is not None:
        report["speedup_vs_cpu"] = {
            "filter_step": ratio(
                reference["filter_step"]["step_s"], report["device"]["filter_step"]["step_s"]
            ),
            "accumulate": ratio(
                reference["accumulate"]["median_s"], report["device"]["accumulate"]["median_s"]
            ),
            "fit_dct": ratio(
                reference["fit_dct"]["median_s"], report["device"]["fit_dct"]["median_s"]
            ),
        }
    report["note"] = (
        "every call uses backend='jax' (the native kernels are CPU-only); the reference is "
        "the same code on jax.devices('cpu')[0] in the same run, timed only when the "
        "device is not a CPU"
    )
    report["machine"] = machine_info(devices=[str(d) for d in jax.devices()])
    report["load_policy"] = policy.summary()
    report["load_average_end"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    out = args.out or (QUICK_OUT if args.quick else DEFAULT_OUT)
    write_json(out, report)
    print(markdown(report))
    print(f"wrote {out}")
    return report


if __name__ == "__main__":
    main()
