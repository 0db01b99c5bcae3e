"""2-D Monte-Carlo localization on the CARMEN logs (dissertation Table 7.2, Figure 8.3 and
gradient-based refinement), with the functional particle filter of lidarjax.localization.

For every log, maps are built from the even-numbered scans at their SLAM-corrected poses;
the filter localizes on the odd-numbered scans (a disjoint subset), driven by the raw
odometry (relative motion between consecutive localized scans) and evaluated against the
corrected poses at every step. Each model runs ``filter.runs`` identically parameterised
filters; run ``i`` starts from the same initial particles for every model (Sec. 7.6.1:
offset and particles drawn from N(0, 1 m^2) in x, y and N(0, 0.1 rad^2) in heading).

Tables written to ``results.md`` / ``results.json``:

1. mean position / heading error over time per log and model (dec, ref, end = Table 7.2),
   plus the ``campus*`` variant (10 % of the beams of every scan failed: set below r_min);
2. MLM vs FMP filters for the decay-rate (and reflection) model (Figure 8.3);
3. the decay-rate filter's estimate vs that estimate refined by gradient ascent on the
   scan likelihood (``localization.refine``), every ``refine.every`` steps (at the last
   step only when a log has fewer steps; ``refine.every=0`` turns refinement off).

The config is checked before any log is loaded (``experiments/_schemas.py``): types by
Hydra while composing, ranges and names (logs, models) by ``validate``.

Plots: error over time per log (``errors.png``) and trajectories (``trajectories.png``).
E.g. ``python experiments/mcl.py logs=[intel] filter.runs=2 filter.max_steps=20``.
"""

from __future__ import annotations

import time
import zlib
from pathlib import Path

import equinox as eqx
import hydra
import jax
import jax.numpy as jnp
import jaxlie
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from _common import (  # noqa: E402
    completed_job,
    even_odd_scans,
    fmt,
    grid_model,
    mapping_stats,
    mark_complete,
    output_dir,
    run_info,
    write_results,
)
from _schemas import validate  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402
from tqdm import tqdm  # noqa: E402

from lidarjax import localization as loc  # noqa: E402
from lidarjax.datasets import fetch, load_carmen  # noqa: E402
from lidarjax.localization.refine import refine_scan_pose, smooth_fields  # noqa: E402
from lidarjax.plot import plot_map, plot_trajectory  # noqa: E402
from lidarjax.raytrace import GridSpec  # noqa: E402

NAMES = {  # the GRID_MODELS and their table labels
    "dec": "Decay-rate",
    "ref": "Reflection",
    "end": "Endpoint",
    "fmp_dec": "Decay-rate FMP",
    "fmp_ref": "Reflection FMP",
}


def build_maps(log, cfg: DictConfig, r_min: float, r_max: float) -> tuple[dict, GridSpec]:
    """All grid models from the even-numbered scans at their corrected poses."""
    stats, spec, p_out = mapping_stats(log, cfg, r_min, r_max)
    return {m: grid_model(m, stats, cfg, p_out) for m in NAMES}, spec


def initial_states(key, start_pose: np.ndarray, cfg: DictConfig):
    """Per run: offset ~ N(0, S), particles ~ N(truth + offset, S); stacked ``[runs]``."""
    std = np.asarray(cfg.filter.init_std, np.float64)
    states = []
    for r in range(int(cfg.filter.runs)):
        k_off, k_init = jax.random.split(jax.random.fold_in(key, r))
        off = std * np.asarray(jax.random.normal(k_off, (3,)), np.float64)
        states.append(
            loc.init_gaussian(int(cfg.filter.particles), start_pose + off, std, key=k_init)
        )
    return jax.tree.map(lambda *x: jnp.stack(x), *states)


def wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


@eqx.filter_jit
def _run_all(pf, states, controls, z):
    return eqx.filter_vmap(pf.run, in_axes=(0, None, None))(states, controls, z)


def run_model(model, az, seq, states, cfg, r_min, r_max):
    scan_model = loc.ScanModel(
        model,
        az,
        r_min,
        r_max,
        ray_floor=float(cfg.ray_floor),
        chunk_size=int(cfg.filter.chunk_size),
    )
    motion = loc.OdometryMotionModel(
        sigma=list(cfg.filter.motion_sigma),
        alpha=[list(r) for r in cfg.filter.motion_alpha],
        inflation=float(cfg.filter.inflation),
    )
    pf = loc.ParticleFilter(
        motion,
        scan_model,
        resample_fraction=float(cfg.filter.resample_fraction),
        resampler=str(cfg.filter.resampler),
        best_fraction=float(cfg.filter.best_fraction),
    )
    t0 = time.perf_counter()
    _, info = _run_all(pf, states, seq["controls"], seq["z"])
    est = np.asarray(loc.to_vector(info.estimate), np.float64)  # [runs T 3]
    seconds = time.perf_counter() - t0
    gt = seq["gt"]
    pos = np.linalg.norm(est[..., :2] - gt[None, :, :2], axis=-1)
    head = np.abs(wrap(est[..., 2] - gt[None, :, 2]))
    return {
        "est": est,
        "pos_err": pos,
        "head_err": head,
        "seconds": seconds,
        "degenerate_steps": int(np.asarray(info.degenerate).sum()),
        "resampled_fraction": float(np.asarray(info.resampled).mean()),
    }


@eqx.filter_jit
def _refine_all(fields, az, ranges, poses, r_min, r_max, max_steps):
    def one(p):
        pose, sol = refine_scan_pose(
            fields, az, ranges, jaxlie.SE2(p), r_min, r_max, max_steps=max_steps
        )
        return pose.parameters(), sol.stats["num_steps"]

    return jax.vmap(one)(poses)


def refine_steps(every: int, n_steps: int) -> np.ndarray:
    """Steps (0-based) at which ``refine_eval`` refines: ``every - 1, 2 every - 1, ...``
    below ``n_steps``, or the last step alone when ``n_steps < every`` (e.g. the example
    ``filter.max_steps=20`` with the default ``refine.every=25``). ``[S]`` ints, ``S >= 1``.

    Raises:
        ValueError: ``every < 1`` or ``n_steps < 1``.
    """
    if every < 1 or n_steps < 1:
        raise ValueError(f"need refine.every >= 1 and n_steps >= 1, got {every}, {n_steps}")
    every = min(every, n_steps)
    return np.arange(every - 1, n_steps, every)


def refine_eval(m, log, seq, est, cfg, r_min, r_max):
    """Refine the decay-rate filter's estimates ``est`` ``[runs T 3]`` at every
    ``refine.every``-th step (steps ``every - 1, 2 every - 1, ... < T``); when the run has
    fewer steps than ``refine.every`` (``T < every``), at its last step only."""
    beams = np.arange(0, log.n_beams, int(cfg.refine.beam_stride))
    az = jnp.asarray(log.azimuths_rad[beams])
    steps = refine_steps(int(cfg.refine.every), est.shape[1])
    t0 = time.perf_counter()
    before, after, n_steps = [], [], []
    fields = smooth_fields(m, [float(b) for b in cfg.refine.blur_schedule_m])
    for t in steps:
        ranges = jnp.asarray(log.ranges_m[seq["scan_idx"][t], beams])
        poses = loc.from_vector(jnp.asarray(est[:, t])).parameters()
        out, k = _refine_all(fields, az, ranges, poses, r_min, r_max, int(cfg.refine.max_steps))
        ref = np.asarray(loc.to_vector(jaxlie.SE2(out)), np.float64)
        gt = seq["gt"][t]
        before.append(np.linalg.norm(est[:, t, :2] - gt[:2], axis=-1))
        after.append(np.linalg.norm(ref[:, :2] - gt[:2], axis=-1))
        n_steps.append(np.asarray(k))
    b, a = np.stack(before, 1), np.stack(after, 1)  # [runs S]
    return {
        "steps": steps.tolist(),
        "filter_pos_err": float(b.mean()),
        "refined_pos_err": float(a.mean()),
        "filter_pos_err_converged": float(b[b < 0.3].mean()) if (b < 0.3).any() else None,
        "refined_pos_err_converged": float(a[b < 0.3].mean()) if (b < 0.3).any() else None,
        "improved_fraction": float((a < b).mean()),
        "mean_solver_steps": float(np.mean(n_steps)),
        "seconds": time.perf_counter() - t0,
    }


def prepare(name: str, cfg: DictConfig, failures: bool = False):
    """Load a log and the filter's input: odd-numbered scans (the first ``max_steps + 1``),
    ``n_beams`` evenly spaced beams, relative odometry, corrected poses for evaluation.
    Returns ``(log, r_min, r_max, azimuths, seq, key)``."""
    log = load_carmen(fetch(name))
    r_min, r_max = float(cfg.r_min_m), float(log.usable_range_m)
    odd = even_odd_scans(log.n_scans)[1][: int(cfg.filter.max_steps) + 1]
    beams = np.unique(np.round(np.linspace(0, log.n_beams - 1, int(cfg.filter.n_beams))))
    beams = beams.astype(int)
    az = jnp.asarray(log.azimuths_rad[beams])
    z = np.array(log.ranges_m[odd[1:]][:, beams])
    key = jax.random.fold_in(jax.random.PRNGKey(int(cfg.seed)), zlib.crc32(name.encode()) >> 1)
    if failures:  # campus*: sensor failures report (below) the minimum range -> SUB
        u = np.asarray(jax.random.uniform(jax.random.fold_in(key, 7), z.shape), np.float64)
        z[u < float(cfg.failure_fraction)] = 0.0
    seq = {
        "controls": loc.relative_motion(jnp.asarray(log.odometry[odd])),
        "z": jnp.asarray(z),
        "gt": log.poses[odd[1:]],
        "scan_idx": odd[1:],
        "start": log.poses[odd[0]],
        "z0": jnp.asarray(log.ranges_m[odd[0]][beams]),  # the start scan (global init)
    }
    return log, r_min, r_max, az, seq, key


def evaluate_log(name: str, cfg: DictConfig, failures: bool = False) -> dict:
    t_start = time.perf_counter()
    log, r_min, r_max, az, seq, key = prepare(name, cfg, failures)
    models, spec = build_maps(log, cfg, r_min, r_max)
    states = initial_states(key, seq["start"], cfg)
    t_map = time.perf_counter() - t_start
    out = {
        "n_steps": int(len(seq["scan_idx"])),
        "n_beams": int(az.shape[0]),
        "grid_shape": list(spec.shape),
    }
    out["map_seconds"] = t_map
    per_model, curves = {}, {}
    for mname in cfg.models:
        r = run_model(models[mname], az, seq, states, cfg, r_min, r_max)
        per_run_pos = r["pos_err"].mean(axis=1)
        conv = r["pos_err"][:, -1] < 0.5
        per_model[mname] = {
            "per_run_pos_err_m": per_run_pos.tolist(),
            "pos_err_converged_runs_m": float(per_run_pos[conv].mean()) if conv.any() else None,
            "pos_err_m": float(r["pos_err"].mean()),
            "pos_err_std_over_runs_m": float(per_run_pos.std(ddof=1))
            if per_run_pos.size > 1
            else 0.0,
            "head_err_deg": float(np.rad2deg(r["head_err"].mean())),
            "pos_err_second_half_m": float(r["pos_err"][:, r["pos_err"].shape[1] // 2 :].mean()),
            "final_pos_err_m": float(r["pos_err"][:, -1].mean()),
            "converged_runs": int((r["pos_err"][:, -1] < 0.5).sum()),
            "seconds": r["seconds"],
            "steps_per_s": float(r["pos_err"].shape[1] / r["seconds"]),
            "degenerate_steps": r["degenerate_steps"],
            "resampled_fraction": r["resampled_fraction"],
        }
        curves[mname] = {"pos": r["pos_err"].mean(0), "est": r["est"][0]}
        if mname == "dec" and int(cfg.refine.every) > 0 and not failures:
            out["refine"] = refine_eval(models["dec"], log, seq, r["est"], cfg, r_min, r_max)
    out["models"] = per_model
    out["seconds"] = time.perf_counter() - t_start
    return out, curves, {"truth": seq["gt"], "map": models["dec"]}  # the figure's background


def write_tables(results: dict, models: list[str]) -> str:
    ch7 = [m for m in ("dec", "ref", "end") if m in models]
    lines = [
        "### Table 7.2 in 2-D: mean position error over time and runs [m] (heading [deg]); "
        "runs converged (final error < 0.5 m): their mean error [m]",
        "",
    ]
    lines.append("| log | " + " | ".join(NAMES[m] for m in ch7) + " | best |")
    lines.append("|---|" + "---|" * (len(ch7) + 1))

    def cell(v):
        n = len(v["per_run_pos_err_m"])
        return (
            f"{v['pos_err_m']:.3f} ({v['head_err_deg']:.1f}); {v['converged_runs']}/{n}: "
            f"{fmt(v['pos_err_converged_runs_m'])}"
        )

    for name, r in results.items():
        cells = [cell(r["models"][m]) for m in ch7]
        best = min(ch7, key=lambda m: r["models"][m]["pos_err_m"])
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {NAMES[best]} |")
    fmp = [
        (a, b) for a, b in (("dec", "fmp_dec"), ("ref", "fmp_ref")) if a in models and b in models
    ]
    if fmp:
        lines += ["", "### Figure 8.3 in 2-D: MLM vs FMP filters, mean position error [m]", ""]
        head = " | ".join(f"{NAMES[a]} MLM | {NAMES[a]} FMP" for a, _ in fmp)
        lines.append(f"| log | {head} |")
        lines.append("|---|" + "---|" * (2 * len(fmp)))
        for name, r in results.items():
            cells = " | ".join(f"{cell(r['models'][a])} | {cell(r['models'][b])}" for a, b in fmp)
            lines.append(f"| {name} | {cells} |")
    if any("refine" in r for r in results.values()):
        lines += [
            "",
            "### Decay-rate filter vs filter + gradient refinement (every k-th step) [m]",
            "",
            "| log | filter | refined | filter (err < 0.3 m) | refined (same steps) | improved |",
            "|---|---|---|---|---|---|",
        ]
        for name, r in results.items():
            if "refine" not in r:
                continue
            f = r["refine"]
            lines.append(
                f"| {name} | {f['filter_pos_err']:.3f} | {f['refined_pos_err']:.3f} | "
                f"{fmt(f['filter_pos_err_converged'])} | {fmt(f['refined_pos_err_converged'])} "
                f"| {100 * f['improved_fraction']:.0f} % |"
            )
    return "\n".join(lines) + "\n"


def error_grid(series: dict, path: Path, ylabel: str, legend_size: int = 7) -> None:
    """One log-scale panel per log (``series[log][label] = [T]`` errors), saved to path."""
    names = list(series)
    cols = min(4, len(names))
    rows = -(-len(names) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3 * rows), squeeze=False)
    for ax, name in zip(axes.flat, names):
        for label, curve in series[name].items():
            ax.plot(curve, label=label, lw=1)
        ax.set_yscale("log")
        ax.set_title(name)
        ax.set_xlabel("step")
        ax.set_ylabel(ylabel)
    for ax in list(axes.flat)[len(names) :]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=legend_size)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot(curves: dict, gts: dict, out: Path) -> None:
    """``errors.png`` and ``trajectories.png``: per log, the corrected and the estimated
    trajectories (run 0 of each model) over the log's decay-rate map, zoomed to the
    trajectories (x, y in m; colour bar: decay rate; unobserved cells grey)."""
    names = list(curves)
    cols = min(4, len(names))
    rows = -(-len(names) // cols)
    error_grid(
        {name: {NAMES[m]: c["pos"] for m, c in curves[name].items()} for name in names},
        out / "errors.png",
        "position error [m]",
        legend_size=7,
    )
    fig, axes = plt.subplots(
        rows, cols, figsize=(5.2 * cols, 4.6 * rows), squeeze=False, layout="constrained"
    )
    for ax, name in zip(axes.flat, names):
        gt = gts[name]["truth"]
        plot_map(gts[name]["map"], ax=ax, title=name)
        plot_trajectory(gt, ax=ax, color="k", lw=2, label="corrected poses")
        tracks = [gt[:, :2]]
        for m, c in curves[name].items():
            plot_trajectory(c["est"], ax=ax, lw=1, label=f"{NAMES[m]} (run 0)")
            tracks.append(c["est"][:, :2])
        pts = np.concatenate(tracks)
        lo, hi = pts.min(0), pts.max(0)
        pad = 0.15 * max(hi - lo) + 2.0  # the trajectories and some of the map around them
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        ax.legend(loc="best", fontsize=6, framealpha=0.8)
    for ax in list(axes.flat)[len(names) :]:
        ax.axis("off")
    fig.savefig(out / "trajectories.png", dpi=120)
    plt.close(fig)


@hydra.main(config_path="../configs", config_name="mcl", version_base=None)
def main(cfg: DictConfig) -> None:
    validate(cfg, "mcl")
    out = output_dir()
    if (done := completed_job(out)) is not None:  # a sweep job that already finished
        return done
    models = list(cfg.models)
    unknown = set(models) - set(NAMES)
    if unknown:
        raise ValueError(f"models: unknown {sorted(unknown)}; choose from {sorted(NAMES)}")
    t0 = time.perf_counter()
    results, curves, gts = {}, {}, {}
    jobs = []
    for n in cfg.logs:
        jobs.append((n, False))
        if n == cfg.robustness_log:
            jobs.append((n, True))
    for name, failures in tqdm(jobs, desc="logs"):
        label = f"{name}*" if failures else name
        res, c, gt = evaluate_log(name, cfg, failures)
        results[label], curves[label], gts[label] = res, c, gt
        tqdm.write(
            f"{label}: "
            + ", ".join(f"{m} {v['pos_err_m']:.3f} m" for m, v in res["models"].items())
            + f" ({res['seconds']:.0f} s)"
        )
        write_outputs(out, cfg, models, results, curves, gts, time.perf_counter() - t0)
    mark_complete(out)  # a sweep job: results.json holds every log
    print(write_tables(results, models))


def write_outputs(out: Path, cfg, models, results, curves, gts, runtime_s: float) -> None:
    """results.json / results.md / figures for the logs done so far."""
    summary = {
        "config": OmegaConf.to_container(cfg, resolve=True),
        "logs": results,
        "runtime_s": runtime_s,
        **run_info(),
    }
    ch7 = [m for m in ("dec", "ref", "end") if m in models]
    summary["mean_over_logs_pos_err_m"] = {
        m: float(np.mean([r["models"][m]["pos_err_m"] for r in results.values()])) for m in models
    }
    if ch7:
        summary["best_model_count"] = {
            m: int(
                sum(
                    min(ch7, key=lambda k: r["models"][k]["pos_err_m"]) == m
                    for r in results.values()
                )
            )
            for m in ch7
        }
    write_results(out, results=summary, markdown=write_tables(results, models), partial=True)
    plot(curves, gts, out)


if __name__ == "__main__":
    main()
