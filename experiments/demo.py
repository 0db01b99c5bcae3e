"""Headline demo (`make demo`): what lidarjax is for, on the built-in simulated office.

1. Simulate 2-D lidar scans along a trajectory through a seeded office
   (:mod:`lidarjax.sim`) and accumulate the grid statistics of the mapping half.
2. Build the three grid maps of chapter 7: decay rate, reflection and endpoint.
3. Localize with a particle filter on each map along a held-out trajectory (the same
   loop woven with another phase, its own scans and noisy odometry) from a wrong start.
4. Fit a DCT map (ch. 9) to a subset of the same rays and compare it in p_ref with the
   grid map.
5. Extract PLE and PLE+ polylines (ch. 10) from one held-out scan.

Writes ONE figure ``demo.png`` (the three maps with the true and estimated trajectories,
the DCT map, the polylines over the scan, the position error over time of the three
filters) and ``results.md`` / ``results.json`` into Hydra's output folder
(``outputs/demo``); the table is printed too. Runs in well under a minute on two cores,
compilation included. Override anything from the command line, e.g.
``python experiments/demo.py localization.particles=1000 dct.cell_m=0.5``.
"""

from __future__ import annotations

import time

T_START = time.perf_counter()

import matplotlib  # noqa: E402

matplotlib.use("Agg")  # a script without a display; lidarjax never picks a backend

import logging  # noqa: E402

import hydra  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import jaxlie  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from _common import completed_job, output_dir, run_info, write_results  # noqa: E402
from _schemas import validate  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

import lidarjax  # noqa: E402
from lidarjax import features, maps, metrics, plot  # noqa: E402
from lidarjax import localization as loc  # noqa: E402
from lidarjax.rays import HIT, RayBatch, from_scan  # noqa: E402
from lidarjax.raytrace import GridSpec, accumulate  # noqa: E402
from lidarjax.sim import make_office, simulate_scans  # noqa: E402

MODELS = {"dec": "decay rate", "ref": "reflection", "end": "endpoint"}
COLORS = {"dec": "tab:blue", "ref": "tab:green", "end": "tab:purple"}


def point_segment_distance(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """``[n]`` distance (m) from each point ``[n 2]`` to the nearest segment ``[k 2 2]``."""
    a = segments[None, :, 0]
    e = segments[None, :, 1] - a
    w = points[:, None] - a
    t = np.clip(np.sum(w * e, -1) / np.maximum(np.sum(e * e, -1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(w - t[..., None] * e, axis=-1).min(axis=1)


def wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def _subset(flat: RayBatch, idx: np.ndarray) -> RayBatch:
    return RayBatch(
        flat.origins[idx], flat.directions[idx], flat.ranges[idx], flat.kind[idx],
        flat.r_min, flat.r_max,
    )  # fmt: skip


def localize(model, cfg, az, z, controls, start, key) -> dict:
    """Particle filter on ``model`` from a wrong start; the estimate per step and times
    (the first run includes compilation, the second is steady state)."""
    lc = cfg.localization
    scan_model = loc.ScanModel(
        model, az, cfg.scans.r_min_m, cfg.scans.max_range_m,
        ray_floor=float(lc.ray_floor), chunk_size=int(cfg.chunk_size),
    )  # fmt: skip
    motion = loc.OdometryMotionModel(
        sigma=list(lc.motion_sigma), alpha=[list(r) for r in lc.motion_alpha]
    )
    pf = loc.ParticleFilter(motion, scan_model)
    guess = start + np.asarray(lc.init_offset, float)
    state = loc.init_gaussian(int(lc.particles), guess, list(lc.init_std), key=key)
    t0 = time.perf_counter()
    _, info = pf.run(state, controls, z)
    est = np.asarray(loc.to_vector(info.estimate), float)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(pf.run(state, controls, z))
    steady = time.perf_counter() - t0
    return {"est": est, "guess": guess, "seconds": first, "steady_seconds": steady}


def fit_dct(cfg, spec: GridSpec, rays: RayBatch, grid_map, observed, seed: int) -> dict:
    """DCT map over the grid's box (``dct.cell_m`` per coefficient) fitted to a seeded
    subset of the mapping rays; p_ref RMSE against the grid map on observed cells, and
    that of a grid map with as many cells as the DCT map has coefficients."""
    c = float(cfg.dct.cell_m)
    lower = np.asarray(spec.origin, float)
    extent = np.ceil((np.asarray(spec.upper, float) - lower) / c - 1e-9) * c
    shape = tuple(int(round(e / c)) for e in extent)
    flat = rays.flatten()
    rng = np.random.default_rng(seed)
    idx = np.sort(rng.choice(flat.n, min(int(cfg.dct.n_rays), flat.n), replace=False))
    sub = _subset(flat, idx)
    inside = np.asarray(maps.rays_in_box(maps.DCTMap(jnp.zeros(shape), lower, extent), sub))
    sub = _subset(sub, np.flatnonzero(inside))
    t0 = time.perf_counter()
    dct, sol = maps.fit_dct(
        sub, shape, lower=lower, extent=extent, max_steps=int(cfg.dct.max_steps)
    )
    dct = jax.block_until_ready(dct)
    seconds = time.perf_counter() - t0
    centres = np.asarray(spec.cell_centers())[observed]
    lam_grid = np.asarray(grid_map.rates)[observed]
    lam_dct = np.asarray(dct.decay_rate(jnp.asarray(centres)))
    coarse = maps.decay_rate_map(accumulate(GridSpec(lower, c, shape), sub))
    cells = np.clip(np.floor((centres - lower) / c).astype(int), 0, np.asarray(shape) - 1)
    lam_coarse = np.asarray(coarse.rates)[cells[:, 0], cells[:, 1]]
    return {
        "map": dct,
        "shape": list(shape),
        "n_rays": int(sub.n),
        "steps": int(sol.stats["num_steps"]),
        "result": str(sol.result),
        "seconds": seconds,
        "p_ref_rmse": float(metrics.p_ref_rmse(lam_dct, lam_grid)),
        "p_ref_rmse_coarse_grid": float(metrics.p_ref_rmse(lam_coarse, lam_grid)),
    }


def polylines(cfg, az: np.ndarray, ranges: np.ndarray) -> dict:
    """PLE and PLE+ on one scan (sensor frame): vertices, ray RMSE (m) and times."""
    rays = from_scan(jaxlie.SE2.identity(), az, ranges[None], cfg.scans.r_min_m,
                     cfg.scans.max_range_m)  # fmt: skip
    refl = np.asarray(rays.kind)[0] == HIT
    out = {}
    t0 = time.perf_counter()
    ple = features.extract_polylines(rays, max_vertices=int(cfg.polylines.max_vertices))
    out["PLE"] = {"map": ple.map, "seconds": time.perf_counter() - t0}
    t0 = time.perf_counter()
    plus = features.optimize_polylines(ple, rays)
    out["PLE+"] = {"map": plus.map, "seconds": time.perf_counter() - t0}
    for r in out.values():
        one = jax.tree.map(lambda x: x[0] if jnp.ndim(x) else x, r["map"])
        r["polylines"], r["closed"] = one.to_polylines()
        exp = np.asarray(r["map"].expected_ranges(rays))[0]
        r["rmse_m"] = float(metrics.ray_rmse(ranges, exp, refl))
        r["J"] = int(sum(len(p) for p in r["polylines"]))
    dirs = np.stack([np.cos(az), np.sin(az)], -1)
    return {"methods": out, "endpoints": ranges[:, None] * dirs, "reflected": refl}


def figure(path, cfg, world, spec, stats, models, runs, truth, dct, lines) -> None:
    fig, axes = plt.subplots(2, 3, figsize=(18, 9.6), layout="constrained")
    err_ax = axes[1, 2]
    for ax, (name, model) in zip(axes[0], models.items()):
        r = runs[name]
        plot.plot_localization(
            model, r["est"], truth=truth, ax=ax, error_ax=err_ax, label=f"{MODELS[name]} filter",
            color=COLORS[name], observed=stats,
        )  # fmt: skip
        ax.plot(*r["guess"][:2], "x", color=COLORS[name], ms=8, mew=2, label="initial guess")
        ax.legend(loc="upper left", fontsize=7, framealpha=0.85)
        ax.set_title(
            f"{MODELS[name]} map + filter: final error {r['final_pos_err_m']:.3f} m", fontsize=10
        )
    errs = np.concatenate([r["pos_err_m"] for r in runs.values()])
    err_ax.set_yscale("log")
    err_ax.set_ylim(max(errs[errs > 0].min(), 1e-4) / 1.5, errs.max() * 1.5)
    err_ax.set_title("position error of the three filters", fontsize=10)
    # the DCT map on the grid's cells (its box is the grid's): unobserved cells masked
    same = tuple(round(float(e) / float(spec.resolution)) for e in np.asarray(dct["map"].extent))
    observed = stats if same == tuple(spec.shape) else None
    plot.plot_map(
        dct["map"], ax=axes[1, 0], quantity="p_ref", resolution_m=float(spec.resolution),
        observed=observed,
    )  # fmt: skip
    axes[1, 0].set_title(
        f"DCT map, {dct['shape'][0]} × {dct['shape'][1]} coefficients: p_ref RMSE "
        f"{dct['p_ref_rmse']:.3f} vs the grid",
        fontsize=10,
    )
    ax = axes[1, 1]
    m = lines["methods"]
    plot.plot_polyline_scan(
        ax, np.zeros(2), lines["endpoints"], lines["reflected"], m["PLE"]["polylines"],
        m["PLE"]["closed"], color="tab:orange", label="PLE", ray_stride=3, linestyle="--",
    )  # fmt: skip
    plot.plot_polyline_scan(
        ax, np.zeros(2), lines["endpoints"], lines["reflected"], m["PLE+"]["polylines"],
        m["PLE+"]["closed"], color="tab:blue", label="PLE+", draw_scan=False,
    )  # fmt: skip
    ax.set_title(
        f"polylines of held-out scan {cfg.polylines.scan} (sensor frame), J = {m['PLE']['J']}: "
        f"ray RMSE PLE {1e3 * m['PLE']['rmse_m']:.1f} mm, PLE+ {1e3 * m['PLE+']['rmse_m']:.1f} mm",
        fontsize=9,
    )
    fig.suptitle(
        f"lidarjax demo: simulated office (seed {cfg.seed}), {cfg.scans.n_poses} mapping scans, "
        f"{cfg.localization.n_poses - 1} held-out scans localized with "
        f"{cfg.localization.particles} particles",
        fontsize=12,
    )
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)


def tables(cfg, runs: dict, dct: dict, lines: dict, total_s: float, load: float | None) -> str:
    n = cfg.localization.n_poses - 1
    lc = cfg.localization
    head = (
        f"## lidarjax demo — simulated office (seed {cfg.seed})\n\n"
        f"Maps from {cfg.scans.n_poses} scans ({cfg.scans.n_beams} beams, "
        f"{cfg.grid.resolution_m} m cells); particle filter ({lc.particles} particles, "
        f"{lc.n_beams} beams) on {n} held-out scans from a start "
        f"{np.hypot(*lc.init_offset[:2]):.2f} m / {np.degrees(lc.init_offset[2]):.0f}° off.\n\n"
    )
    rows = [
        "| map | final position error (m) | mean position error (m) | mean heading error (deg) "
        "| run time (s, incl. compile) | steady state (s) |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in runs.items():
        rows.append(
            f"| {MODELS[name]} | {r['final_pos_err_m']:.3f} | {r['mean_pos_err_m']:.3f} | "
            f"{r['mean_head_err_deg']:.2f} | {r['seconds']:.2f} | {r['steady_seconds']:.2f} |"
        )
    m = lines["methods"]
    extra = [
        "",
        "| also | result | time (s) |",
        "|---|---|---|",
        f"| DCT map {dct['shape'][0]} × {dct['shape'][1]} ({dct['n_rays']} rays, "
        f"{dct['steps']} L-BFGS steps) | p_ref RMSE vs the {cfg.grid.resolution_m} m grid "
        f"{dct['p_ref_rmse']:.3f} (grid of {dct['shape'][0]} × {dct['shape'][1]} cells: "
        f"{dct['p_ref_rmse_coarse_grid']:.3f}) | {dct['seconds']:.2f} |",
    ]
    for k in ("PLE", "PLE+"):
        extra.append(
            f"| {k} polylines, scan {cfg.polylines.scan} (J = {m[k]['J']}) | ray RMSE "
            f"{1e3 * m[k]['rmse_m']:.1f} mm | {m[k]['seconds']:.2f} |"
        )
    load_txt = "" if load is None else f" (1-min load average {load:.2f})"
    foot = f"\nTotal run time {total_s:.1f} s{load_txt}, JAX backend {jax.default_backend()}.\n"
    return head + "\n".join(rows + extra) + "\n" + foot


@hydra.main(config_path="../configs", config_name="demo", version_base=None)
def main(cfg: DictConfig) -> dict:
    validate(cfg, "demo")
    laps, t_lap = {}, [T_START]

    def lap(stage: str) -> None:  # wall time (s) per stage, compilation included
        now = time.perf_counter()
        laps[stage] = now - t_lap[0]
        t_lap[0] = now

    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)  # no TPU notice
    # JAX's persistent compilation cache: a second run loads its programs (about half the
    # run time is compilation); LIDARJAX_JAX_CACHE=off measures a cold start
    cache = lidarjax.enable_compilation_cache()
    out = output_dir()
    if (done := completed_job(out)) is not None:  # a sweep job that already finished
        return done
    key = jax.random.key(int(cfg.seed))
    world = make_office(cfg.seed, width_m=cfg.world.width_m, height_m=cfg.world.height_m)
    fov = np.radians(cfg.scans.fov_deg)
    full = np.isclose(fov, 2 * np.pi)
    az = np.linspace(-fov / 2, fov / 2, cfg.scans.n_beams, endpoint=not full)
    sim = dict(max_range_m=cfg.scans.max_range_m, noise_sigma_m=cfg.scans.noise_sigma_m)
    lap("imports_and_setup")

    # 1. scans: the mapping trajectory and a held-out one (another weave of the loop)
    poses = world.trajectory(cfg.scans.n_poses, jitter_m=0.3, seed=cfg.seed)
    held = world.trajectory(cfg.localization.n_poses, jitter_m=0.3, seed=cfg.seed + 1)
    ranges = simulate_scans(world, poses, az, seed=cfg.seed, **sim)
    held_ranges = simulate_scans(world, held, az, seed=cfg.seed + 1, **sim)
    lap("simulate")

    # 2. grid statistics and the three maps
    T = jaxlie.SE2.from_xy_theta(poses[:, 0], poses[:, 1], poses[:, 2])
    rays = from_scan(T, az, ranges, cfg.scans.r_min_m, cfg.scans.max_range_m)
    margin = cfg.grid.margin_m
    spec = GridSpec.from_bounds(
        world.bounds[0] - margin, world.bounds[1] + margin, cfg.grid.resolution_m
    )
    stats = jax.block_until_ready(accumulate(spec, rays, chunk_size=cfg.chunk_size))
    p_out = float(np.clip((np.asarray(rays.kind) != HIT).mean(), 1e-3, 0.5))
    ep = cfg.endpoint
    models = {
        "dec": maps.decay_rate_map(stats),
        "ref": maps.reflection_map(stats),
        "end": maps.endpoint_map(
            stats, sigma_m=ep.sigma_m, z_hit=ep.z_hit, z_rand=ep.z_rand, p_out=p_out
        ),
    }
    H = np.asarray(stats.hits)
    near = point_segment_distance(np.asarray(spec.cell_centers())[H > 0], world.segments)
    near = near <= cfg.grid.resolution_m + 3 * cfg.scans.noise_sigma_m
    lap("maps")

    # 3. particle filters on the held-out trajectory, driven by noisy odometry
    lc = cfg.localization
    rng = np.random.default_rng(cfg.seed)
    motion = np.asarray(loc.relative_motion(jnp.asarray(held)), float)
    controls = jnp.asarray(
        motion + rng.normal(0.0, 1.0, motion.shape) * np.asarray(lc.odometry_noise)
    )
    beams = np.unique(np.round(np.linspace(0, cfg.scans.n_beams - 1, lc.n_beams)).astype(int))
    z = jnp.asarray(held_ranges[1:, beams])
    truth = held[1:]
    runs = {}
    for name, model in models.items():
        r = localize(model, cfg, jnp.asarray(az[beams]), z, controls, held[0], key)
        pos = np.linalg.norm(r["est"][:, :2] - truth[:, :2], axis=1)
        head = np.degrees(np.abs(wrap(r["est"][:, 2] - truth[:, 2])))
        r.update(
            pos_err_m=pos,
            final_pos_err_m=float(pos[-1]),
            mean_pos_err_m=float(pos.mean()),
            mean_head_err_deg=float(head.mean()),
            final_head_err_deg=float(head[-1]),
        )
        runs[name] = r
    lap("localization")

    # 4. a DCT map of the same rays; 5. polylines of one held-out scan
    observed = np.asarray(stats.lengths) > 0
    dct = fit_dct(cfg, spec, rays, models["dec"], observed, cfg.seed)
    lap("dct")
    lines = polylines(cfg, az, held_ranges[int(cfg.polylines.scan)])
    lap("polylines")

    figure(out / "demo.png", cfg, world, spec, stats, models, runs, truth, dct, lines)
    lap("figure")
    total = time.perf_counter() - T_START
    info = run_info()
    md = tables(cfg, runs, dct, lines, total, info["load_average_1min"])
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
        "hits_near_true_walls_fraction": float((H[H > 0] * near).sum() / max(H.sum(), 1)),
        "localization": {
            name: {
                "final_pos_err_m": r["final_pos_err_m"],
                "mean_pos_err_m": r["mean_pos_err_m"],
                "mean_head_err_deg": r["mean_head_err_deg"],
                "final_head_err_deg": r["final_head_err_deg"],
                "seconds": r["seconds"],
                "steady_seconds": r["steady_seconds"],
                "pos_err_m_per_step": r["pos_err_m"],
            }
            for name, r in runs.items()
        },
        "n_localized_scans": int(truth.shape[0]),
        "dct": {k: v for k, v in dct.items() if k != "map"},
        "polylines": {
            k: {"J": v["J"], "rmse_m": v["rmse_m"], "seconds": v["seconds"]}
            for k, v in lines["methods"].items()
        },
        "timings_s": {**laps, "total": total},
        "compilation_cache": None if cache is None else str(cache),
        "jax_backend": jax.default_backend(),
        **info,
    }
    write_results(out, results=results, markdown=md, cfg=cfg)
    print(md)
    print(f"wrote {out / 'demo.png'}, {out / 'results.md'}, {out / 'results.json'}")
    return results


if __name__ == "__main__":
    main()
