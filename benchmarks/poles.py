"""Pole extraction and landmark particle filter (dissertation ch. 12) against NumPy/SciPy
references timed in the same run.

Setup: the simulated urban world along KITTI-00 (:func:`lidarjax.datasets.make_urban_world`,
seed 0) and the HDL-32E-like lidar (32 x 2170 rays).

Measured:

1. **Pole extraction per local map** (30 x 30 x 5 m, 0.2 m voxels, 2 scans = 138 880 rays,
   section 12.4.1) with :func:`lidarjax.features.extract_poles`, warm, median of repeats,
   and its stages (ray tracing, occupancy, score maps + mean shift), in the default
   float32. Reference: the same stages in NumPy/SciPy (the vectorised NumPy ray tracer of
   :mod:`benchmarks._numpy_reference`, ``scipy.special.betainc`` per voxel,
   ``scipy.ndimage`` box filters, a NumPy mean shift), checked to find the same poles.
2. **One particle-filter step** (motion, measurement with nearest-neighbour association,
   estimate, resampling) with 5000 particles and 20 online poles against the world's
   ~500-landmark map, and the measurement update alone. References: a NumPy measurement
   update vectorised with a SciPy k-d tree (``cKDTree.query`` of all particle x pole points
   at once), and the per-particle loop of the authors' design (one k-d tree query per
   particle), timed on 500 particles and scaled to 5000.
3. The simulator: seconds per simulated scan.

Run with ``python benchmarks/poles.py [--quick] [--out PATH]``. Results go to
``benchmarks/results/poles.json`` and a Markdown table is printed.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make `benchmarks` and `lidarjax` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import jaxlie  # noqa: E402
import numpy as np  # noqa: E402
import scipy.ndimage as ndi  # noqa: E402
import scipy.special  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from lidarjax.datasets import (  # noqa: E402
    hdl32e,
    load_urban_trajectory,
    make_urban_world,
    simulate_urban_scan,
)
from lidarjax.features import PoleConfig, extract_poles, local_map_spec  # noqa: E402
from lidarjax.features._poles import _poles_from_scores, fast_occupancy, pole_score_maps  # noqa: E402
from lidarjax.localization import (  # noqa: E402
    OdometryMotionModel,
    ParticleFilter,
    ParticleState,
    PoleMeasurementModel,
    from_vector,
)
from lidarjax.maps import beta_posterior, occupancy  # noqa: E402
from lidarjax.rays import HIT, RayBatch, from_spinning_scan  # noqa: E402
from lidarjax.raytrace import accumulate  # noqa: E402

try:  # run as a script or as a module
    from _machine import machine_info
    from _numpy_reference import accumulate_numpy
except ImportError:  # pragma: no cover
    from benchmarks._machine import machine_info
    from benchmarks._numpy_reference import accumulate_numpy

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "poles.json"
PAPER_EXTRACT_S = 1.33  # per local map, quad-core PC with GPU (section 12.5.1)
PAPER_MEASURE_S = 0.09  # measurement step with data association, 5000 particles


def _median_time(fn, repeats: int) -> tuple[float, object]:
    out = jax.block_until_ready(fn())  # warm-up / compile
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def local_map_rays(world, gt, idx, lidar) -> RayBatch:
    """Rays of the scans ``idx`` simulated and registered at the ground-truth poses."""
    ranges = np.stack([simulate_urban_scan(world, gt[i], lidar, seed=int(i)).ranges_m for i in idx])
    pose = gt[list(idx)]
    T = jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.from_z_radians(jnp.asarray(pose[:, 2])),
        jnp.column_stack([jnp.asarray(pose[:, :2]), jnp.full(len(idx), lidar.mount_height_m)]),
    )
    rays = from_spinning_scan(T, lidar.directions(), ranges, lidar.min_range_m, lidar.max_range_m)
    return rays.flatten()


# ----------------------------------------------------------------------------- NumPy reference


def numpy_occupancy(hits, misses, mu_o):
    h = hits.astype(float)
    n = h + misses
    obs = n > 0
    ml = h[obs] / n[obs]
    e, v = ml.mean(), ml.var()
    alpha = -e * (e * e - e + v) / v
    beta = (e - v + e * v - 2 * e * e + e**3) / v
    return scipy.special.betainc(misses + beta, h + alpha, 1.0 - mu_o)


def numpy_scores(occ, widths, f):
    """Q_a with cumulative sums and scipy.ndimage maximum filters (same boundary
    semantics as the JAX version: outside cells are empty inside, occupied in the hull)."""
    out = []
    for a in widths:
        p = a + f
        inside = np.pad(occ, ((p, p), (p, p), (0, 0)), constant_values=0.0)
        hull = np.pad(occ, ((p, p), (p, p), (0, 0)), constant_values=1.0)
        nx, ny = occ.shape[:2]
        m = (nx + a - 1, ny + a - 1)

        def box_sum(x, wx, wy):
            c = np.cumsum(np.cumsum(x, 0), 1)
            c = np.pad(c, ((1, 0), (1, 0), (0, 0)))
            return c[wx:, wy:] - c[:-wx, wy:] - c[wx:, :-wy] + c[:-wx, :-wy]

        def box_max(x, wx, wy):
            # window starting at each index: a centred scipy.ndimage filter, then cropped
            full = ndi.maximum_filter(x, size=(wx, wy, 1), mode="nearest")
            ox, oy = wx // 2, wy // 2
            return full[ox : ox + x.shape[0] - wx + 1, oy : oy + x.shape[1] - wy + 1]

        def crop(arr, x0, y0):
            return arr[x0 : x0 + m[0], y0 : y0 + m[1]]

        mean = crop(box_sum(inside, a, a), f + 1, f + 1) / (a * a)
        sx = box_max(hull, f, a + 2 * f)
        sy = box_max(hull, a, f)
        ring = np.maximum(
            np.maximum(crop(sx, 1, 1), crop(sx, a + f + 1, 1)),
            np.maximum(crop(sy, f + 1, 1), crop(sy, f + 1, a + f + 1)),
        )
        out.append((box_max(mean - ring, a, a) + 1) / 2)
    return np.stack(out)


# ----------------------------------------------------------------------------- benchmarks


def bench_extraction(world, gt, lidar, repeats: int) -> dict:
    cfg = PoleConfig()
    idx = [400, 401]
    rays = local_map_rays(world, gt, idx, lidar)
    spec = local_map_spec(gt[idx[0], :2], cfg)
    n_rays = int(rays.n)
    t_total, poles = _median_time(lambda: extract_poles(rays, spec, cfg), repeats)

    acc = jax.jit(lambda r, s: accumulate(s, r, chunk_size=cfg.chunk_size))
    t_acc, stats = _median_time(lambda: acc(rays, spec), repeats)
    occ_fast = jax.jit(lambda st: fast_occupancy(beta_posterior(st), cfg.mu_o))
    occ_plain = jax.jit(lambda st: occupancy(beta_posterior(st), cfg.mu_o))
    t_occ, occ = _median_time(lambda: occ_fast(stats), repeats)
    t_occ_plain, _ = _median_time(lambda: occ_plain(stats), repeats)
    post = jax.jit(
        lambda o: _poles_from_scores(pole_score_maps(o, cfg.widths, cfg.free_cells), cfg)
    )
    t_post, _ = _median_time(lambda: post(occ), repeats)

    # NumPy / SciPy references of the same stages
    sub = min(n_rays, 20_000)
    o = np.asarray(rays.origins, float)[:sub]
    d = np.asarray(rays.directions, float)[:sub]
    r = np.asarray(rays.ranges, float)[:sub]
    k = np.asarray(rays.kind)[:sub]
    t0 = time.perf_counter()
    accumulate_numpy(
        np.asarray(spec.origin, float),
        spec.resolution,
        spec.shape,
        o,
        d,
        r,
        k == HIT,
        np.ones(sub, bool),
    )
    t_np_acc = (time.perf_counter() - t0) * n_rays / sub
    h, m = np.asarray(stats.hits), np.asarray(stats.misses)
    t0 = time.perf_counter()
    occ_np = numpy_occupancy(h, m, cfg.mu_o)
    t_np_occ = time.perf_counter() - t0
    t0 = time.perf_counter()
    q_np = numpy_scores(occ_np, cfg.widths, cfg.free_cells)
    t_np_scores = time.perf_counter() - t0
    q_jax = np.asarray(pole_score_maps(jnp.asarray(occ_np), cfg.widths, cfg.free_cells))
    return {
        "n_rays": n_rays,
        "grid_shape": list(spec.shape),
        "n_poles": len(poles),
        "extract_s": t_total,
        "rays_per_s": n_rays / t_total,
        "stages_s": {
            "ray_tracing": t_acc,
            "occupancy_table": t_occ,
            "occupancy_per_voxel": t_occ_plain,
            "scores_and_mean_shift": t_post,
        },
        "numpy_s": {
            "ray_tracing_extrapolated": t_np_acc,
            "ray_tracing_rays_timed": sub,
            "occupancy": t_np_occ,
            "score_maps": t_np_scores,
        },
        "numpy_occupancy_max_abs_diff": float(np.max(np.abs(occ_np - np.asarray(occ, float)))),
        "numpy_scores_max_abs_diff": float(np.max(np.abs(q_np - q_jax))),
        "speedup_vs_numpy": (t_np_acc + t_np_occ + t_np_scores) / t_total,
        "speedup_vs_paper": PAPER_EXTRACT_S / t_total,
    }


def numpy_measurement(parts, poles, tree, var, eps, d_max):
    c, s = np.cos(parts[:, 2:3]), np.sin(parts[:, 2:3])
    wx = parts[:, 0:1] + c * poles[:, 0] - s * poles[:, 1]
    wy = parts[:, 1:2] + s * poles[:, 0] + c * poles[:, 1]
    d, _ = tree.query(np.stack([wx.ravel(), wy.ravel()], -1), k=1, distance_upper_bound=d_max)
    d = np.minimum(d, d_max).reshape(wx.shape)
    dens = np.exp(-0.5 * d * d / var) / np.sqrt(2 * np.pi * var)
    return np.log(dens + eps).sum(-1)


def loop_measurement(parts, poles, tree, var, eps, d_max):
    out = np.empty(len(parts))
    for i, (x, y, t) in enumerate(parts):  # one k-d tree query per particle
        c, s = math.cos(t), math.sin(t)
        w = np.column_stack(
            [x + c * poles[:, 0] - s * poles[:, 1], y + s * poles[:, 0] + c * poles[:, 1]]
        )
        d, _ = tree.query(w, k=1, distance_upper_bound=d_max)
        d = np.minimum(d, d_max)
        out[i] = np.sum(np.log(np.exp(-0.5 * d * d / var) / np.sqrt(2 * np.pi * var) + eps))
    return out


def bench_filter(world, gt, repeats: int, n_particles: int = 5000, n_poles: int = 20) -> dict:
    rng = np.random.default_rng(0)
    lm = world.pole_xy
    model = PoleMeasurementModel(lm)
    x0 = gt[400]
    parts_np = np.column_stack(
        [
            rng.normal(x0[0], 1.0, n_particles),
            rng.normal(x0[1], 1.0, n_particles),
            rng.normal(x0[2], 0.05, n_particles),
        ]
    )
    near = lm[np.argsort(np.linalg.norm(lm - x0[:2], axis=1))[:n_poles]]
    c, s = math.cos(x0[2]), math.sin(x0[2])
    poles = (near - x0[:2]) @ np.array([[c, -s], [s, c]]) + rng.normal(0, 0.05, near.shape)
    dtype = jnp.result_type(float)
    parts = from_vector(jnp.asarray(parts_np, dtype))
    z = (jnp.asarray(poles, dtype), jnp.ones(n_poles, bool))
    pf = ParticleFilter(OdometryMotionModel([0.01, 0.01, 0.002], inflation=2.0), model)
    state = ParticleState(
        parts, jnp.full(n_particles, -math.log(n_particles), dtype), jax.random.key(0)
    )
    step = eqx.filter_jit(lambda st: pf.step(st, jnp.asarray([0.8, 0.0, 0.01], dtype), z))
    t_step, _ = _median_time(lambda: step(state), repeats)
    meas = jax.jit(lambda p: model(p, z))
    t_meas, ll = _median_time(lambda: meas(parts), repeats)
    tree = cKDTree(lm)
    args = (model.var_m2.item(), model.eps.item(), model.d_max_m)
    t0 = time.perf_counter()
    ref = numpy_measurement(parts_np, poles, tree, *args)
    t_np = time.perf_counter() - t0
    n_loop = 500
    t0 = time.perf_counter()
    loop_measurement(parts_np[:n_loop], poles, tree, *args)
    t_loop = (time.perf_counter() - t0) * n_particles / n_loop
    return {
        "n_particles": n_particles,
        "n_online_poles": n_poles,
        "n_landmarks": len(lm),
        "lookup_truncated_cells": model.lookup.n_truncated,
        "step_ms": 1e3 * t_step,
        "measurement_ms": 1e3 * t_meas,
        "numpy_kdtree_measurement_ms": 1e3 * t_np,
        "per_particle_loop_measurement_ms": 1e3 * t_loop,
        "max_abs_loglik_diff_vs_numpy": float(np.max(np.abs(np.asarray(ll) - ref))),
        "speedup_measurement_vs_numpy": t_np / t_meas,
        "speedup_measurement_vs_loop": t_loop / t_meas,
        "speedup_measurement_vs_paper": PAPER_MEASURE_S / t_meas,
    }


def bench_simulator(world, gt, lidar, repeats: int) -> dict:
    t, _ = _median_time(
        lambda: simulate_urban_scan(world, gt[400], lidar, seed=1).ranges_m, repeats
    )
    return {"s_per_scan": t, "rays_per_scan": lidar.n_rays}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args()
    repeats = 3 if args.quick else 10
    traj = load_urban_trajectory()
    gt = traj.xy_yaw
    world = make_urban_world(traj, seed=0)
    lidar = hdl32e()
    res = {
        "machine": machine_info(),
        "extraction": bench_extraction(world, gt, lidar, repeats),
        "filter": bench_filter(world, gt, repeats),
        "simulator": bench_simulator(world, gt, lidar, repeats),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=2))
    e, f, s = res["extraction"], res["filter"], res["simulator"]
    st, ns = e["stages_s"], e["numpy_s"]
    np_total = ns["ray_tracing_extrapolated"] + ns["occupancy"] + ns["score_maps"]
    rows = [
        ("Stage", "lidarjax", "NumPy/SciPy reference"),
        ("---", "---", "---"),
        (
            f"pole extraction, 1 local map ({e['n_rays']} rays)",
            f"{e['extract_s']:.3f} s ({e['rays_per_s'] / 1e6:.2f} M rays/s)",
            f"{np_total:.2f} s",
        ),
        ("- ray tracing", f"{st['ray_tracing']:.3f} s", f"{ns['ray_tracing_extrapolated']:.2f} s"),
        (
            "- occupancy (table / per voxel)",
            f"{st['occupancy_table']:.3f} / {st['occupancy_per_voxel']:.3f} s",
            f"{ns['occupancy']:.3f} s",
        ),
        (
            "- score maps + mean shift",
            f"{st['scores_and_mean_shift']:.3f} s",
            f"{ns['score_maps']:.3f} s (score maps only)",
        ),
        (
            f"PF step, {f['n_particles']} particles, {f['n_online_poles']} poles",
            f"{f['step_ms']:.2f} ms",
            "-",
        ),
        (
            "- measurement update",
            f"{f['measurement_ms']:.2f} ms",
            f"{f['numpy_kdtree_measurement_ms']:.1f} ms (k-d tree, vectorised); "
            f"{f['per_particle_loop_measurement_ms']:.0f} ms (per-particle loop)",
        ),
        ("simulator, one HDL-32E scan", f"{s['s_per_scan']:.4f} s", "-"),
    ]
    for row in rows:
        print("| " + " | ".join(row) + " |")


if __name__ == "__main__":
    main()
