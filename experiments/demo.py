"""Headline demo (`make demo`): a seeded synthetic office, simulated scans, grid statistics.

Writes ``grid_stats.png``, ``results.json`` and ``results.md`` into Hydra's output folder
(``outputs/demo`` by default). Override anything from the command line, e.g.
``python experiments/demo.py grid.resolution_m=0.1 scans.n_poses=500``.
"""

from __future__ import annotations

import time

import hydra
import jax
import jaxlie
import numpy as np
from _common import output_dir, write_results
from _schemas import validate
from omegaconf import DictConfig

from lidarjax.plot import plot_grid_stats
from lidarjax.rays import from_scan
from lidarjax.raytrace import GridSpec, accumulate
from lidarjax.sim import make_office, simulate_scans


def point_segment_distance(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """``[n]`` distance (m) from each point ``[n 2]`` to the nearest segment ``[k 2 2]``."""
    a = segments[None, :, 0]
    e = segments[None, :, 1] - a
    w = points[:, None] - a
    t = np.clip(np.sum(w * e, -1) / np.maximum(np.sum(e * e, -1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(w - t[..., None] * e, axis=-1).min(axis=1)


@hydra.main(config_path="../configs", config_name="demo", version_base=None)
def main(cfg: DictConfig) -> dict:
    validate(cfg, "demo")
    out = output_dir()
    world = make_office(cfg.seed, width_m=cfg.world.width_m, height_m=cfg.world.height_m)
    poses = world.trajectory(cfg.scans.n_poses, jitter_m=0.3, seed=cfg.seed)
    fov = np.radians(cfg.scans.fov_deg)
    az = np.linspace(-fov / 2, fov / 2, cfg.scans.n_beams)
    t0 = time.perf_counter()
    ranges = simulate_scans(
        world,
        poses,
        az,
        max_range_m=cfg.scans.max_range_m,
        noise_sigma_m=cfg.scans.noise_sigma_m,
        seed=cfg.seed,
    )
    t_sim = time.perf_counter() - t0

    T = jaxlie.SE2.from_xy_theta(poses[:, 0], poses[:, 1], poses[:, 2])
    rays = from_scan(T, az, ranges, cfg.scans.r_min_m, cfg.scans.max_range_m)
    margin = cfg.grid.margin_m
    spec = GridSpec.from_bounds(
        world.bounds[0] - margin, world.bounds[1] + margin, cfg.grid.resolution_m
    )
    t0 = time.perf_counter()
    stats = jax.block_until_ready(accumulate(spec, rays, chunk_size=cfg.chunk_size))
    t_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    stats = jax.block_until_ready(accumulate(spec, rays, chunk_size=cfg.chunk_size))
    t_acc = time.perf_counter() - t0

    H = np.asarray(stats.hits)
    centers = np.asarray(spec.cell_centers())[H > 0]
    dist = point_segment_distance(centers, world.segments)
    near = dist <= cfg.grid.resolution_m + 3 * cfg.scans.noise_sigma_m
    counts = rays.counts()
    results = {
        "seed": cfg.seed,
        "n_scans": int(ranges.shape[0]),
        "n_beams": int(ranges.shape[1]),
        "n_rays": rays.n,
        "rays_by_kind": counts,
        "grid_shape": list(spec.shape),
        "resolution_m": cfg.grid.resolution_m,
        "hits_total": int(H.sum()),
        "misses_total": int(np.asarray(stats.misses).sum()),
        "length_total_m": float(np.asarray(stats.lengths).sum()),
        "hit_cells": int((H > 0).sum()),
        "hits_near_true_walls_fraction": float((H[H > 0] * near).sum() / H.sum()),
        "simulate_s": t_sim,
        "accumulate_first_call_s": t_first,
        "accumulate_s": t_acc,
        "accumulate_rays_per_s": rays.n / t_acc,
        "jax_backend": jax.default_backend(),
    }
    title = f"synthetic office (seed {cfg.seed}): {rays.n} rays, {cfg.grid.resolution_m} m cells"
    fig = plot_grid_stats(stats, segments=world.segments, poses=poses, title=title)
    fig.savefig(out / "grid_stats.png", dpi=110)
    write_results(out, results=results)
    near_pct = 100 * results["hits_near_true_walls_fraction"]
    rate = results["accumulate_rays_per_s"]
    rows = [
        ("rays (HIT / SUB / SUP)", f"{counts['HIT']} / {counts['SUB']} / {counts['SUP']}"),
        ("grid", f"{spec.shape[0]} x {spec.shape[1]} cells of {cfg.grid.resolution_m} m"),
        ("hits / misses", f"{results['hits_total']} / {results['misses_total']}"),
        ("hits within res + 3 sigma of a true wall", f"{near_pct:.2f} %"),
        ("accumulate (steady state)", f"{t_acc * 1e3:.1f} ms = {rate:.3g} rays/s"),
        ("accumulate (first call, incl. compile)", f"{t_first:.2f} s"),
    ]
    table = "| quantity | value |\n|---|---|\n" + "".join(f"| {a} | {b} |\n" for a, b in rows)
    write_results(out, markdown=table, cfg=cfg)
    print(table)
    print(f"wrote {out / 'grid_stats.png'}, {out / 'results.json'}, {out / 'results.md'}")
    return results


if __name__ == "__main__":
    main()
