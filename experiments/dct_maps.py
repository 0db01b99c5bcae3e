"""DCT maps on the CARMEN logs (dissertation section 9.5, Tables 9.2-9.4, Figures 9.1-9.2),
plus scan matching on DCT maps.

Per log: the 10 m x 10 m patch (1 m aligned) holding the most HIT end points of all scans;
the mapping pool is every HIT ray ending inside it (scans kept for scan matching excluded).

- Table 9.2: ``n_rays_accuracy`` (1e4) rays; a 0.05 m ground-truth decay-rate grid map
  (200 x 200, Eq. 7.10); DCT and grid maps with L x L parameters for every L in
  ``resolutions``; RMSE of ``p_ref = 1 - exp(-lambda)`` at the centres of the ground-truth
  cells observed at least once; over logs: mean, std, one-sided paired t-test p-value,
  ``Delta_mu = 1 - mu_DCT / mu_GM``.
- Table 9.3: ``n_rays_likelihood`` (500) rays; summed log-likelihood of those rays under
  the DCT map, the grid map, a GP occupancy map and a Hilbert map with the same number of
  parameters (the latter two rasterised at 0.05 m and evaluated as reflection maps, Sec.
  9.5.2). All models treat space outside the patch as empty (decay rate / reflection
  probability 0) and all HIT end points lie in the patch, so every model scores the same
  in-patch evidence; HIT readings are densities (1/m) in every model (the reflection model's
  probability divided by the chord of the reflecting cell, Sec. 7.6.2).
- Table 9.4: median mapping times over logs (500 rays; the DCT time includes its grid
  initialisation and precomputation; JIT compilation excluded by a warm-up fit).
- Scan matching: ``match.n_scans`` scans per log whose poses lie inside the patch,
  started ``match.offset_m`` away in a random direction and ``match.offset_deg`` off in
  heading, refined coarse to fine on the L = 40 DCT map (``refine_dct_scan_pose``).

Writes ``results.json`` (after every log), ``results.md``, ``dct_maps.png`` (Fig. 9.1),
``dct_baselines.png`` (Fig. 9.2) into Hydra's output folder. E.g.
``python experiments/dct_maps.py logs=[intel] resolutions=[10,20]``.
"""

from __future__ import annotations

import time
import zlib
from pathlib import Path

import hydra
import jax
import matplotlib

matplotlib.use("Agg")
import jax.numpy as jnp  # noqa: E402
import jaxlie  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from _common import completed_job, mark_complete, output_dir, scan_rays, write_results  # noqa: E402
from _schemas import validate  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402
from scipy import stats  # noqa: E402
from tqdm import tqdm  # noqa: E402

from lidarjax import maps  # noqa: E402
from lidarjax.datasets import fetch, load_carmen  # noqa: E402
from lidarjax.localization.refine import refine_dct_scan_pose  # noqa: E402
from lidarjax.maps import baselines  # noqa: E402
from lidarjax.rays import HIT, RayBatch  # noqa: E402
from lidarjax.raytrace import GridSpec, accumulate  # noqa: E402
from lidarjax.sensor_models import (  # noqa: E402
    decay_rate_log_likelihood,
    reflection_log_likelihood,
)

PAPER_92 = {  # l [m]: (mu_DCT, sigma_DCT, mu_GM, sigma_GM, p [%], Delta_mu [%])
    10: (0.3314, 0.0679, 0.3330, 0.0708, 39.36, 0.48),
    13: (0.3146, 0.0675, 0.3319, 0.0752, 1.01, 0.52),
    20: (0.2932, 0.0645, 0.3093, 0.0690, 0.03, 5.21),
    29: (0.2571, 0.0611, 0.2822, 0.0672, 0.05, 8.89),
    40: (0.2370, 0.0563, 0.2543, 0.0583, 0.07, 6.80),
}
PAPER_93 = {  # mean/std of lp_DCT - lp_GM, - lp_GPOM [1e4], - lp_HM [1e4]
    10: (88.5, 74.1, 4.21, 3.00, 4.30, 3.42),
    13: (150.6, 146.5, 3.89, 2.81, 4.19, 3.46),
    20: (135.7, 63.9, 3.53, 2.60, 4.06, 3.42),
    29: (196.1, 101.5, 2.97, 2.15, 4.12, 3.32),
    40: (96.8, 132.0, 2.68, 1.90, 4.12, 3.31),
}
PAPER_94 = {  # median mapping times [s]: DCT, GM, GPOM, HM
    10: (3.52, 0.0917, 1.12, 22.8),
    13: (4.69, 0.0915, 1.98, 40.6),
    20: (3.70, 0.0923, 3.25, 108.4),
    29: (18.25, 0.0926, 6.45, 328.3),
    40: (39.84, 0.0942, 14.04, 949.3),
}


def _subset(rays: RayBatch, idx: np.ndarray) -> RayBatch:
    return RayBatch(
        rays.origins[idx],
        rays.directions[idx],
        rays.ranges[idx],
        rays.kind[idx],
        rays.r_min,
        rays.r_max,
    )


def densest_patch(ends: np.ndarray, size: float) -> np.ndarray:
    """Lower corner of the 1 m-aligned ``size`` x ``size`` window with the most points."""
    lo = np.floor(ends.min(0))
    hi = np.ceil(ends.max(0)) + 1
    hist, _, _ = np.histogram2d(
        ends[:, 0], ends[:, 1], bins=[np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1)]
    )
    k = int(round(size))
    if hist.shape[0] < k or hist.shape[1] < k:
        return lo
    win = np.lib.stride_tricks.sliding_window_view(hist, (k, k)).sum(axis=(-1, -2))
    i, j = np.unravel_index(int(np.argmax(win)), win.shape)
    return lo + np.array([i, j], float)


def p_ref(lam):
    """``1 - exp(-lambda)`` (Sec. 9.5.1), ``lambda`` in 1/m."""
    return -np.expm1(-np.asarray(lam, float))


def _timed(fn):
    t = time.perf_counter()
    out = fn()
    jax.block_until_ready(jax.tree_util.tree_leaves(out))
    return out, time.perf_counter() - t


def evaluate_log(name: str, cfg: DictConfig, figs: dict) -> dict:
    log = load_carmen(fetch(name))
    rng = np.random.default_rng([cfg.seed, zlib.crc32(name.encode())])
    p = log.poses
    size = float(cfg.patch_m)
    ext = np.array([size, size])
    all_rays = scan_rays(log, None, cfg.r_min_m, log.usable_range_m)
    n_b = log.ranges_m.shape[1]
    flat = all_rays.flatten()
    kind = np.asarray(flat.kind)
    ends = np.asarray(flat.origins + flat.ranges[:, None] * flat.directions)
    hit = kind == HIT
    lower = densest_patch(ends[hit], size)
    in_patch = hit & np.all((ends >= lower) & (ends <= lower + ext), axis=1)
    # scans for scan matching: poses inside the patch (margin), held out of the mapping pool
    margin = float(cfg.match.margin_m)
    inside = np.flatnonzero(
        np.all((p[:, :2] > lower + margin) & (p[:, :2] < lower + ext - margin), 1)
    )
    n_match = min(int(cfg.match.n_scans), inside.size)
    match_scans = (
        np.sort(rng.choice(inside, n_match, replace=False)) if n_match else np.array([], int)
    )
    pool_mask = in_patch.copy()
    for s in match_scans:
        pool_mask[s * n_b : (s + 1) * n_b] = False
    pool = np.flatnonzero(pool_mask)
    n_acc = min(int(cfg.n_rays_accuracy), pool.size)
    acc_idx = rng.choice(pool, n_acc, replace=False)
    lik_idx = acc_idx[: min(int(cfg.n_rays_likelihood), n_acc)]
    rays_acc = _subset(flat, acc_idx)
    rays_lik = _subset(flat, lik_idx)
    row = dict(
        log=name,
        patch_lower=lower.tolist(),
        n_pool=int(pool.size),
        n_rays_accuracy=n_acc,
        n_rays_likelihood=int(lik_idx.size),
        match_scans=match_scans.tolist(),
        res={},
    )

    # ground truth: 0.05 m ML decay-rate grid from the accuracy rays
    gt_res = float(cfg.ground_truth_resolution_m)
    gt_spec = GridSpec(lower, gt_res, (int(round(size / gt_res)),) * 2)
    gt_stats = accumulate(gt_spec, rays_acc)
    observed = np.asarray(gt_stats.lengths) > 0
    gt_map = maps.decay_rate_map(gt_stats, unknown_rate=0.0)
    centres = np.asarray(gt_spec.cell_centers())[observed]
    gt_p = p_ref(np.asarray(gt_map.rates)[observed])
    row["gt_observed_cells"] = int(observed.sum())
    if name == cfg.figure_log:
        figs["gt"] = (np.asarray(gt_map.rates), gt_spec)

    box_lo, box_hi = lower, lower + ext
    pts, labels = baselines.occupancy_training_points(
        rays_lik, box_lo, box_hi, free_step_m=cfg.baselines.free_step_m, seed=cfg.seed
    )

    def fit(rays, L):
        return maps.fit_dct(
            rays,
            (L, L),
            lower=lower,
            extent=ext,
            rtol=cfg.fit.rtol,
            atol=cfg.fit.atol,
            max_steps=cfg.fit.max_steps,
        )

    dct40 = None
    for L in cfg.resolutions:
        L = int(L)
        r = {}
        # --- Table 9.2: accuracy with 1e4 rays
        dct, sol = fit(rays_acc, L)
        grid = maps.decay_rate_map(accumulate(GridSpec(lower, size / L, (L, L)), rays_acc))
        lam_dct = np.asarray(dct.decay_rate(jnp.asarray(centres)))
        cells = np.clip(np.floor((centres - lower) / (size / L)).astype(int), 0, L - 1)
        lam_gm = np.asarray(grid.rates)[cells[:, 0], cells[:, 1]]
        r["rmse_dct"] = float(np.sqrt(np.mean((p_ref(lam_dct) - gt_p) ** 2)))
        r["rmse_gm"] = float(np.sqrt(np.mean((p_ref(lam_gm) - gt_p) ** 2)))
        r["fit_steps_accuracy"] = int(sol.stats["num_steps"])
        if L == max(cfg.resolutions):
            dct40 = dct
        if name == cfg.figure_log and L == int(cfg.figure_resolution_92):
            figs["fig91"] = (dct, np.asarray(grid.rates), grid.spec)
        if not cfg.likelihood_tables:
            row["res"][str(L)] = r
            continue
        # --- Table 9.3 / 9.4: 500 rays
        fit(rays_lik, L)  # warm-up (compile)
        (dct_l, sol_l), t_dct = _timed(lambda L=L: fit(rays_lik, L))
        spec_l = GridSpec(lower, size / L, (L, L))
        accumulate(spec_l, rays_lik)  # warm-up
        grid_l, t_gm = _timed(
            lambda spec_l=spec_l: maps.decay_rate_map(
                accumulate(spec_l, rays_lik), unknown_rate=0.0
            )
        )
        lp_dct = float(jnp.sum(maps.dct_log_likelihood(dct_l, rays_lik)))
        lp_gm = float(jnp.sum(decay_rate_log_likelihood(grid_l, rays_lik)))
        budget = L * L
        t = time.perf_counter()
        gp = baselines.fit_gpom(
            pts, labels, budget, seed=cfg.seed, length_scale_m=cfg.baselines.length_scale_m
        )
        t_gp = time.perf_counter() - t
        t = time.perf_counter()
        hm = baselines.fit_hilbert(
            pts, labels, budget, seed=cfg.seed, gamma=1.0 / (2 * cfg.baselines.length_scale_m**2)
        )
        t_hm = time.perf_counter() - t
        lp = {}
        rasters = {}
        for key, model in (("gpom", gp), ("hm", hm)):
            spec_r, probs = baselines.rasterize(
                model.occupancy, box_lo, box_hi, resolution_m=cfg.baselines.raster_m
            )
            rasters[key] = probs
            rmap = baselines.occupancy_reflection_map(spec_r, probs, unknown_prob=0.0)
            lp[key] = float(jnp.sum(reflection_log_likelihood(rmap, rays_lik)))
        r.update(
            lp_dct=lp_dct,
            lp_gm=lp_gm,
            lp_gpom=lp["gpom"],
            lp_hm=lp["hm"],
            t_dct=t_dct,
            t_gm=t_gm,
            t_gpom=t_gp,
            t_hm=t_hm,
            fit_steps_likelihood=int(sol_l.stats["num_steps"]),
            fit_result_likelihood=str(sol_l.result),
        )
        if name == cfg.figure_log and L == int(cfg.figure_resolution_93):
            figs["fig92"] = (dct_l, np.asarray(grid_l.rates), rasters["gpom"], rasters["hm"])
        row["res"][str(L)] = r

    # --- scan matching on the finest DCT map
    matches = []
    ang_rng = np.random.default_rng([cfg.seed, zlib.crc32(name.encode()), 1])
    for s in match_scans:
        a = ang_rng.uniform(0, 2 * np.pi)
        dth = np.deg2rad(cfg.match.offset_deg) * ang_rng.choice([-1.0, 1.0])
        start = jaxlie.SE2.from_xy_theta(
            p[s, 0] + cfg.match.offset_m * np.cos(a),
            p[s, 1] + cfg.match.offset_m * np.sin(a),
            p[s, 2] + dth,
        )
        t = time.perf_counter()
        pose, sol = refine_dct_scan_pose(
            dct40,
            log.azimuths_rad,
            log.ranges_m[s],
            start,
            cfg.r_min_m,
            float(log.usable_range_m),
            blur_schedule_m=tuple(cfg.match.blur_schedule_m),
        )
        v = np.asarray(pose.translation())
        th = float(pose.rotation().as_radians())
        matches.append(
            dict(
                scan=int(s),
                err_m=float(np.hypot(*(v - p[s, :2]))),
                err_deg=float(np.rad2deg(abs((th - p[s, 2] + np.pi) % (2 * np.pi) - np.pi))),
                steps=int(sol.stats["num_steps"]),
                seconds=time.perf_counter() - t,
            )
        )
    row["matches"] = matches
    return row


def summarize(rows: list[dict], cfg: DictConfig) -> dict:
    out = {"table92": {}, "table93": {}, "table94": {}}
    for L in cfg.resolutions:
        k = str(int(L))
        rd = np.array([r["res"][k]["rmse_dct"] for r in rows])
        rg = np.array([r["res"][k]["rmse_gm"] for r in rows])
        pval = float(stats.ttest_rel(rd, rg, alternative="less").pvalue) if len(rows) > 1 else None
        out["table92"][k] = dict(
            l_m=float(cfg.patch_m) / int(L),
            mu_dct=float(rd.mean()),
            sd_dct=float(rd.std(ddof=1)) if len(rd) > 1 else 0.0,
            mu_gm=float(rg.mean()),
            sd_gm=float(rg.std(ddof=1)) if len(rg) > 1 else 0.0,
            p_percent=None if pval is None or not np.isfinite(pval) else 100 * pval,
            delta_mu_percent=100 * (1 - rd.mean() / rg.mean()),
            dct_better=f"{int((rd < rg).sum())}/{len(rd)}",
        )
        if "lp_dct" not in rows[0]["res"][k]:
            continue
        t93 = {}
        for other in ("gm", "gpom", "hm"):
            d = np.array([r["res"][k]["lp_dct"] - r["res"][k][f"lp_{other}"] for r in rows])
            t93[other] = dict(
                mu=float(d.mean()),
                sd=float(d.std(ddof=1)) if len(d) > 1 else 0.0,
                dct_better=f"{int((d > 0).sum())}/{len(d)}",
            )
        out["table93"][k] = t93
        out["table94"][k] = {
            m: float(np.median([r["res"][k][f"t_{m}"] for r in rows]))
            for m in ("dct", "gm", "gpom", "hm")
        }
    m = [x for r in rows for x in r["matches"]]
    if m:
        e = np.array([x["err_m"] for x in m])
        a = np.array([x["err_deg"] for x in m])
        ok = (e < cfg.match.success_m) & (a < cfg.match.success_deg)
        out["matching"] = dict(
            n=len(m),
            converged=int(ok.sum()),
            median_err_m=float(np.median(e)),
            median_err_deg=float(np.median(a)),
            mean_s=float(np.mean([x["seconds"] for x in m])),
        )
    return out


def _fmt(x, f="{:.4f}"):
    return "—" if x is None else f.format(x)


def markdown(rows, summ, cfg, total_s) -> str:
    lines = [f"# DCT maps on {len(rows)} CARMEN logs ({total_s / 60:.1f} min)", ""]
    lines += [
        f"## Table 9.2 — RMSE in p_ref vs the 0.05 m ground truth ({cfg.n_rays_accuracy} rays)",
        "",
        "| l [m] | DCT μ | DCT σ | GM μ | GM σ | p [%] | Δμ [%] | DCT better | paper Δμ [%] |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for k, t in summ["table92"].items():
        pp = PAPER_92.get(int(k))
        lines.append(
            f"| {t['l_m']:.2f} | {t['mu_dct']:.4f} | {t['sd_dct']:.4f} | {t['mu_gm']:.4f} | "
            f"{t['sd_gm']:.4f} | {_fmt(t['p_percent'], '{:.2f}')} | {t['delta_mu_percent']:.2f} | "
            f"{t['dct_better']} | {pp[5] if pp else '—'} |"
        )
    lines += [
        "",
        f"## Table 9.3 — log-likelihood differences ({cfg.n_rays_likelihood} rays)",
        "",
        "| l [m] | DCT−GM μ | σ | better | DCT−GPOM μ | σ | better | DCT−HM μ | σ | better "
        "| paper DCT−GM μ | paper DCT−GPOM μ | paper DCT−HM μ |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for k, t in summ["table93"].items():
        pp = PAPER_93.get(int(k))
        cells = []
        for o in ("gm", "gpom", "hm"):
            cells += [f"{t[o]['mu']:.1f}", f"{t[o]['sd']:.1f}", t[o]["dct_better"]]
        paper = [f"{pp[0]}", f"{pp[2]}e4", f"{pp[4]}e4"] if pp else ["—"] * 3
        lines.append(f"| {float(cfg.patch_m) / int(k):.2f} | " + " | ".join(cells + paper) + " |")
    lines += [
        "",
        "## Table 9.4 — median mapping times [s] (500 rays)",
        "",
        "| l [m] | DCT | GM | GPOM | HM | paper DCT | paper GM | paper GPOM | paper HM |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for k, t in summ["table94"].items():
        pp = PAPER_94.get(int(k), ("—",) * 4)
        lines.append(
            f"| {float(cfg.patch_m) / int(k):.2f} | {t['dct']:.3f} | {t['gm']:.4f} | "
            f"{t['gpom']:.2f} | {t['hm']:.2f} | " + " | ".join(str(x) for x in pp) + " |"
        )
    if "matching" in summ:
        m = summ["matching"]
        lines += [
            "",
            "## Scan matching on the finest DCT map",
            "",
            f"{m['converged']}/{m['n']} scans converged (< {cfg.match.success_m} m and "
            f"< {cfg.match.success_deg}°) from {cfg.match.offset_m} m / "
            f"{cfg.match.offset_deg}° offsets; median error {m['median_err_m']:.3f} m, "
            f"{m['median_err_deg']:.2f}°; {m['mean_s']:.1f} s per scan.",
        ]
    return "\n".join(lines) + "\n"


def _show(ax, img, lower, size, title, vmax=1.0):
    ax.imshow(
        np.asarray(img).T,
        origin="lower",
        extent=(lower[0], lower[0] + size, lower[1], lower[1] + size),
        vmin=0,
        vmax=vmax,
        cmap="viridis",
        interpolation="nearest",
    )
    ax.set_title(title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])


def plot_figures(figs, cfg, out: Path):
    if "gt" not in figs:
        return
    size = float(cfg.patch_m)
    gt_rates, gt_spec = figs["gt"]
    lower = np.asarray(gt_spec.origin)
    n = int(round(size / float(cfg.ground_truth_resolution_m)))
    if "fig91" in figs:
        dct, grid_rates, _ = figs["fig91"]
        fig, axs = plt.subplots(1, 3, figsize=(11, 3.8))
        _show(
            axs[0],
            p_ref(np.asarray(maps.dct_to_grid(dct, (n, n)).rates)),
            lower,
            size,
            f"DCT map {dct.shape[0]}×{dct.shape[1]} (p_ref)",
        )
        _show(axs[1], p_ref(grid_rates), lower, size, f"grid map {grid_rates.shape[0]}² (p_ref)")
        _show(axs[2], p_ref(gt_rates), lower, size, "ground truth 0.05 m (p_ref)")
        fig.suptitle(f"{cfg.figure_log}: Figure 9.1 analogue")
        fig.tight_layout()
        fig.savefig(out / "dct_maps.png", dpi=100)
        plt.close(fig)
    if "fig92" in figs:
        dct, grid_rates, gp, hm = figs["fig92"]
        fig, axs = plt.subplots(1, 5, figsize=(17, 3.8))
        _show(
            axs[0],
            p_ref(np.asarray(maps.dct_to_grid(dct, (n, n)).rates)),
            lower,
            size,
            f"DCT {dct.shape[0]}² (p_ref)",
        )
        _show(axs[1], p_ref(grid_rates), lower, size, "grid (p_ref)")
        _show(axs[2], gp, lower, size, "GPOM (occupancy)")
        _show(axs[3], hm, lower, size, "Hilbert map (occupancy)")
        _show(axs[4], p_ref(gt_rates), lower, size, "ground truth (p_ref)")
        fig.suptitle(f"{cfg.figure_log}: Figure 9.2 analogue, {dct.n_parameters} parameters")
        fig.tight_layout()
        fig.savefig(out / "dct_baselines.png", dpi=100)
        plt.close(fig)


@hydra.main(config_path="../configs", config_name="dct_maps", version_base=None)
def main(cfg: DictConfig) -> dict:
    validate(cfg, "dct_maps")
    jax.config.update("jax_enable_x64", bool(cfg.x64))
    out = output_dir()
    if (done := completed_job(out)) is not None:  # a sweep job that already finished
        return done
    t0 = time.perf_counter()
    rows, figs = [], {}
    summ = {}
    for name in (bar := tqdm(list(cfg.logs), desc="logs", unit="log")):
        bar.set_postfix_str(name)
        rows.append(evaluate_log(name, cfg, figs))
        summ = summarize(rows, cfg)
        results = {
            "config": OmegaConf.to_container(cfg, resolve=True),
            "rows": rows,
            "summary": summ,
            "total_s": time.perf_counter() - t0,
        }
        write_results(out, results=results, partial=True)
    total = time.perf_counter() - t0
    md = markdown(rows, summ, cfg, total)
    write_results(out, markdown=md, cfg=cfg, partial=True)
    plot_figures(figs, cfg, out)
    mark_complete(out)  # a sweep job: every log and figure written
    print(md)
    return results


if __name__ == "__main__":
    main()
