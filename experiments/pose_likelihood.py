"""Pose-likelihood evaluation on the CARMEN logs (dissertation Tables 7.3, 8.2 and 8.3 in 2-D).

For every log: grid statistics from the even-numbered scans at their SLAM-corrected poses give
the maximum-likelihood (MLM) decay-rate, reflection and endpoint maps and the full map
posteriors (FMP, Gamma / Beta with moment-matched priors, section 8.5). A subset of the
odd-numbered scans is evaluated:

- Table 7.3a: ``D'(g||h)`` (Eq. 7.28), the negative log-likelihood of the evaluated scans at
  their true poses, for the decay-rate, reflection and endpoint models (all as densities for
  in-range readings, probabilities for out-of-range ones, section 7.6.2).
- Table 7.3b: the inverse KL divergence ``D(h||g)`` (Eq. 7.29) over ``M = 50`` positions drawn
  uniformly in a 2.5 m disc around the true pose (the text samples positions only; the
  heading is kept at the true heading), averaged over scans.
- Table 8.2: ratio of the summed log-likelihoods at the true poses, MLM / FMP, for the
  reflection (REF, probabilities as in Eqs. 8.19 / 8.22) and decay-rate (DEC) models.
- Table 8.3: ratio of the summed KL divergences ``D_KL(p_gt || p)`` (Eqs. 8.24 / 8.25),
  MLM / FMP, with ``p_gt = N(s, 0.05^2 I)`` over position and ``M = 50`` positions drawn
  from ``p_gt`` (true heading), ``p_gt`` and ``p`` normalised over the samples.

ML maps give likelihood 0 to some rays (a hit in a cell never hit while mapping, a ray through
a cell that was never missed); every per-ray log-likelihood is therefore floored at
``ll_floor`` (same floor for all models) and the floored fraction is reported.

Writes ``results.json``, ``results.md`` and ``pose_likelihood.png`` into Hydra's output folder
(``outputs/pose_likelihood`` by default). E.g. ``python experiments/pose_likelihood.py
logs=[intel] eval.max_scans=4``.
"""

from __future__ import annotations

import time
import zlib

import hydra
import jax
import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from _common import (  # noqa: E402
    completed_job,
    even_odd_scans,
    grid_model,
    mapping_stats,
    output_dir,
    save_figure,
    write_results,
)
from _schemas import validate  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402
from tqdm import tqdm  # noqa: E402

from lidarjax import maps  # noqa: E402
from lidarjax.datasets import fetch, load_carmen  # noqa: E402
from lidarjax.metrics import dirac_divergence, inverse_kl, kl_to_gaussian  # noqa: E402
from lidarjax.rays import HIT, RayBatch  # noqa: E402
from lidarjax.raytrace import GridSpec, max_cells_for  # noqa: E402
from lidarjax.sensor_models import (  # noqa: E402
    posterior_log_likelihood,
    ray_log_likelihoods_at_poses,
)

CH7 = ("dec", "ref", "end")  # Table 7.3 models
CH8 = ("mlm_ref", "fmp_ref", "mlm_dec", "fmp_dec")  # Tables 8.2 / 8.3
NAMES = {"dec": "Decay-rate", "ref": "Reflection", "end": "Endpoint"}


# --------------------------------------------------------------------------------------
# Callable models for ray_log_likelihoods_at_poses (module-level functions wrapped in a
# jax.tree_util.Partial so the maps stay traced arguments, not baked-in constants).
# --------------------------------------------------------------------------------------


def _fmp_log_likelihood(posterior_map, max_cells: int, rays: RayBatch):
    """Closed-form FMP likelihood L(z, x), Eq. (8.20), per ray."""
    return posterior_log_likelihood(posterior_map, rays, max_cells=max_cells)


def _log_chord(spec: GridSpec, rays: RayBatch):
    """Per-ray ``log`` of the chord of the reflecting cell (Eq. 7.32) for HIT rays, 0 else.

    Adding it to the reflection model's density turns a HIT back into the probability
    ``P(x(r) in v_k)`` of Eqs. (7.23) / (8.19). HIT rays ending outside the grid get
    ``log(resolution)`` (the outside medium is cells of the grid's resolution).
    """
    o, d, r = rays.origins, rays.directions, rays.ranges
    end = o + r[..., None] * d
    cell = spec.cell_of(end)
    inside = spec.contains(cell)
    res = spec.resolution
    lo = spec.origin + cell.astype(o.dtype) * res
    hi = lo + res
    moving = d != 0
    d_safe = jnp.where(moving, d, 1.0)
    ta, tb = (lo - o) / d_safe, (hi - o) / d_safe
    near = jnp.where(moving, jnp.minimum(ta, tb), -jnp.inf)
    far = jnp.where(moving, jnp.maximum(ta, tb), jnp.inf)
    entry = jnp.maximum(jnp.max(near, axis=-1), 0.0)
    chord = jnp.maximum(jnp.min(far, axis=-1) - entry, jnp.finfo(o.dtype).eps * res)
    val = jnp.where(inside, jnp.log(chord), jnp.log(res))
    return jnp.where(rays.kind == HIT, val, 0.0)


# --------------------------------------------------------------------------------------
# Per-log evaluation
# --------------------------------------------------------------------------------------


def _finite_or_none(x: float):
    return float(x) if np.isfinite(x) else None


def sample_poses(key, true_pose: np.ndarray, cfg: DictConfig) -> tuple[np.ndarray, np.ndarray]:
    """``[M 3]`` poses uniform in a disc (Eq. 7.29) and ``[M 3]`` poses from ``p_gt``
    (Eq. 8.24); both keep the true heading."""
    k_disc, k_gauss = jax.random.split(key)
    m7, m8 = cfg.inverse_kl.n_samples, cfg.kl.n_samples
    u = np.asarray(jax.random.uniform(k_disc, (m7, 2), dtype=jnp.float32), np.float64)
    rad = cfg.inverse_kl.radius_m * np.sqrt(u[:, 0])
    ang = 2 * np.pi * u[:, 1]
    disc = np.repeat(true_pose[None], m7, 0)
    disc[:, 0] += rad * np.cos(ang)
    disc[:, 1] += rad * np.sin(ang)
    g = np.asarray(jax.random.normal(k_gauss, (m8, 2), dtype=jnp.float32), np.float64)
    gauss = np.repeat(true_pose[None], m8, 0)
    gauss[:, :2] += cfg.kl.sigma_m * g
    return disc, gauss


def evaluate_log(name: str, cfg: DictConfig) -> dict:
    t_start = time.perf_counter()
    log = load_carmen(fetch(name))
    r_min, r_max = float(cfg.r_min_m), float(log.usable_range_m)
    even, odd = even_odd_scans(log.n_scans)
    map_idx = even[:: int(cfg.mapping.scan_stride)]
    n_eval = min(int(cfg.eval.max_scans), odd.size)
    eval_idx = odd[np.unique(np.round(np.linspace(0, odd.size - 1, n_eval)).astype(int))]
    beams = np.arange(0, log.n_beams, int(cfg.eval.beam_stride))
    az = np.asarray(log.azimuths_rad[beams])

    # ---- mapping: even scans at their corrected poses ----
    # Grid: all in-range endpoints of all scans (even and odd) plus a margin that covers the
    # endpoints of scans evaluated at poses up to 2.5 m away.
    stats, spec, p_out = mapping_stats(
        log,
        cfg,
        r_min,
        r_max,
        stride=int(cfg.mapping.scan_stride),
        chunk_size=int(cfg.accumulate_chunk_size),
    )
    models = {m: grid_model(m, stats, cfg, p_out) for m in ("dec", "ref", "end")}
    gamma = maps.gamma_posterior(stats)
    beta = maps.beta_posterior(stats)
    mc = max_cells_for(spec, r_max)
    models["fmp_dec"] = jax.tree_util.Partial(_fmp_log_likelihood, gamma, mc)
    models["fmp_ref"] = jax.tree_util.Partial(_fmp_log_likelihood, beta, mc)
    models["chord"] = jax.tree_util.Partial(_log_chord, spec)
    jax.block_until_ready(models["end"].distances)
    t_map = time.perf_counter() - t_start

    # ---- evaluation: odd scans at the true pose and at sampled poses ----
    floor = float(cfg.ll_floor)
    key_log = jax.random.fold_in(jax.random.PRNGKey(cfg.seed), zlib.crc32(name.encode()) >> 1)
    m7, m8 = int(cfg.inverse_kl.n_samples), int(cfg.kl.n_samples)
    cov7 = np.eye(2) * float(cfg.inverse_kl.sigma_m) ** 2
    cov8 = np.eye(2) * float(cfg.kl.sigma_m) ** 2
    # Which poses each model is evaluated at: [true | disc | gauss] slices.
    layout = {
        "dec": ("true", "disc", "gauss"),
        "ref": ("true", "disc", "gauss"),
        "end": ("true", "disc"),
        "fmp_dec": ("true", "gauss"),
        "fmp_ref": ("true", "gauss"),
        "chord": ("true", "gauss"),
    }
    sizes = {"true": 1, "disc": m7, "gauss": m8}
    ll_true = {k: 0.0 for k in (*CH7, *CH8)}
    ll_true_raw = {k: 0.0 for k in CH7}
    n_floored = {k: 0 for k in (*CH7, *CH8)}
    inv_kl = {k: [] for k in CH7}
    kl = {k: 0.0 for k in CH8}
    n_rays = 0
    t0 = time.perf_counter()
    for s in eval_idx:
        true = log.poses[s]
        disc, gauss = sample_poses(jax.random.fold_in(key_log, int(s)), true, cfg)
        groups = {"true": true[None], "disc": disc, "gauss": gauss}
        ranges = np.asarray(log.ranges_m[s, beams])
        per_ray = {}  # model -> {group: [p b]}
        for mname, groups_used in layout.items():
            poses = np.concatenate([groups[g] for g in groups_used])
            out = np.asarray(
                ray_log_likelihoods_at_poses(
                    models[mname],
                    az,
                    ranges,
                    poses,
                    r_min=r_min,
                    r_max=r_max,
                    chunk_size=int(cfg.chunk_size),
                ),
                np.float64,
            )
            parts, lo = {}, 0
            for g in groups_used:
                parts[g] = out[lo : lo + sizes[g]]
                lo += sizes[g]
            per_ray[mname] = parts
        # MLM reflection on the probability scale of Eq. (8.19) (density times chord).
        per_ray["mlm_ref"] = {g: per_ray["ref"][g] + per_ray["chord"][g] for g in ("true", "gauss")}
        per_ray["mlm_dec"] = per_ray["dec"]
        n_rays += ranges.size
        for k in (*CH7, *CH8):
            raw = per_ray[k]["true"][0]
            n_floored[k] += int((raw < floor).sum())
            ll_true[k] += float(np.maximum(raw, floor).sum())
            if k in CH7:
                ll_true_raw[k] += float(raw.sum())

        def pose_ll(k, g):
            return np.maximum(per_ray[k][g], floor).sum(-1)

        for k in CH7:
            inv_kl[k].append(float(inverse_kl(pose_ll(k, "disc"), disc[:, :2], true[:2], cov7)))
        for k in CH8:
            kl[k] += float(
                kl_to_gaussian(
                    pose_ll(k, "gauss"), gauss[:, :2], true[:2], cov8, estimator=cfg.kl.estimator
                )
            )
    t_eval = time.perf_counter() - t0

    dprime = {k: float(dirac_divergence(jnp.asarray([ll_true[k]]))) for k in CH7}
    ll_ratio = {m: ll_true[f"mlm_{m}"] / ll_true[f"fmp_{m}"] for m in ("ref", "dec")}
    kl_ratio = {m: kl[f"mlm_{m}"] / kl[f"fmp_{m}"] for m in ("ref", "dec")}
    inv_mean = {k: float(np.mean(v)) for k, v in inv_kl.items()}
    orderings = {
        "decay_best_dprime": bool(dprime["dec"] < min(dprime["ref"], dprime["end"])),
        "decay_best_inverse_kl": bool(inv_mean["dec"] < min(inv_mean["ref"], inv_mean["end"])),
        "decay_lt_reflection_dprime": bool(dprime["dec"] < dprime["ref"]),
        # FMP better <=> higher summed log-likelihood / lower summed KL. For negative LL sums
        # and positive KL sums this is exactly "ratio MLM/FMP > 1" as in Tables 8.2/8.3.
        "fmp_better_ll_ref": bool(ll_true["fmp_ref"] > ll_true["mlm_ref"]),
        "fmp_better_ll_dec": bool(ll_true["fmp_dec"] > ll_true["mlm_dec"]),
        "fmp_better_kl_ref": bool(kl["fmp_ref"] < kl["mlm_ref"]),
        "fmp_better_kl_dec": bool(kl["fmp_dec"] < kl["mlm_dec"]),
        "ll_ratio_gt1_ref": bool(ll_ratio["ref"] > 1),
        "ll_ratio_gt1_dec": bool(ll_ratio["dec"] > 1),
        "kl_ratio_gt1_ref": bool(kl_ratio["ref"] > 1),
        "kl_ratio_gt1_dec": bool(kl_ratio["dec"] > 1),
    }
    return {
        "log": name,
        "n_scans": log.n_scans,
        "n_beams": log.n_beams,
        "usable_range_m": r_max,
        "grid_shape": list(spec.shape),
        "n_map_scans": int(map_idx.size),
        "map_scan_stride": 2 * int(cfg.mapping.scan_stride),
        "eval_scan_indices": [int(i) for i in eval_idx],
        "eval_beam_stride": int(cfg.eval.beam_stride),
        "n_eval_rays": n_rays,
        "endpoint_p_out": float(p_out),
        "gamma_prior": [float(gamma.alpha), float(gamma.beta)],
        "beta_prior": [float(beta.alpha), float(beta.beta)],
        "dprime": dprime,
        "dprime_per_ray": {k: v / n_rays for k, v in dprime.items()},
        "dprime_unfloored": {k: _finite_or_none(-v) for k, v in ll_true_raw.items()},
        "inverse_kl": inv_mean,
        "ll_sum": ll_true,
        "ll_ratio": ll_ratio,
        "kl_sum": kl,
        "kl_ratio": kl_ratio,
        "floored_fraction": {k: v / n_rays for k, v in n_floored.items()},
        "orderings": orderings,
        "map_s": t_map,
        "eval_s": t_eval,
    }


# --------------------------------------------------------------------------------------
# Reporting
# --------------------------------------------------------------------------------------


def _yn(b: bool) -> str:
    return "yes" if b else "**no**"


def markdown(rows: list[dict], cfg: DictConfig, total_s: float) -> str:
    o = []
    o.append("# Pose likelihood on the CARMEN logs (Tables 7.3, 8.2, 8.3 in 2-D)\n")
    o.append(
        f"Maps from the even-numbered scans (every {2 * cfg.mapping.scan_stride}th scan), "
        f"{cfg.grid.resolution_m} m cells, r_max = the log's usable range. Evaluated: up to "
        f"{cfg.eval.max_scans} odd-numbered scans per log (evenly spaced), every "
        f"{cfg.eval.beam_stride}. beam. Per-ray log-likelihoods floored at {cfg.ll_floor} nats "
        f"for all models. Inverse KL: M = {cfg.inverse_kl.n_samples} positions uniform in a "
        f"{cfg.inverse_kl.radius_m} m disc (true heading), Sigma = "
        f"({cfg.inverse_kl.sigma_m} m)^2 I over position. KL (Eq. 8.24): M = "
        f"{cfg.kl.n_samples} positions from p_gt = N(s, ({cfg.kl.sigma_m} m)^2 I), "
        f"estimator '{cfg.kl.estimator}'. FMP priors moment-matched (section 8.5). REF in "
        f"Tables 8.2/8.3 on the probability scale of Eqs. (8.19)/(8.22). Total runtime "
        f"{total_s:.0f} s, seed {cfg.seed}.\n"
    )
    o.append("## Table 7.3a: D'(g||h) (Eq. 7.28), sum over evaluated rays (per ray in brackets)\n")
    o.append("| log | rays | Decay-rate | Reflection | Endpoint |\n|---|---|---|---|---|")
    for r in rows:
        d, pr = r["dprime"], r["dprime_per_ray"]
        cells = " | ".join(f"{d[k]:.4g} ({pr[k]:.3f})" for k in CH7)
        o.append(f"| {r['log']} | {r['n_eval_rays']} | {cells} |")
    o.append("\n## Table 7.3b: inverse KL D(h||g) (Eq. 7.29), mean over scans\n")
    o.append("| log | Decay-rate | Reflection | Endpoint |\n|---|---|---|---|")
    for r in rows:
        o.append(f"| {r['log']} | " + " | ".join(f"{r['inverse_kl'][k]:.3f}" for k in CH7) + " |")
    o.append("\n## Table 8.2: log-likelihood ratio MLM / FMP at the true poses\n")
    o.append(
        "| log | REF | DEC | sum LL REF (MLM / FMP) | sum LL DEC (MLM / FMP) |\n"
        "|---|---|---|---|---|"
    )
    for r in rows:
        s = r["ll_sum"]
        o.append(
            f"| {r['log']} | {r['ll_ratio']['ref']:.3f} | {r['ll_ratio']['dec']:.3f} | "
            f"{s['mlm_ref']:.4g} / {s['fmp_ref']:.4g} | {s['mlm_dec']:.4g} / {s['fmp_dec']:.4g} |"
        )
    o.append("\n## Table 8.3: KL-divergence ratio MLM / FMP (Eqs. 8.24, 8.25)\n")
    o.append(
        "| log | REF | DEC | sum KL REF (MLM / FMP) | sum KL DEC (MLM / FMP) |\n"
        "|---|---|---|---|---|"
    )
    for r in rows:
        s = r["kl_sum"]
        o.append(
            f"| {r['log']} | {r['kl_ratio']['ref']:.3f} | {r['kl_ratio']['dec']:.3f} | "
            f"{s['mlm_ref']:.4g} / {s['fmp_ref']:.4g} | {s['mlm_dec']:.4g} / {s['fmp_dec']:.4g} |"
        )
    o.append("\n## Do the paper's orderings hold?\n")
    o.append(
        "Paper: decay-rate has the lowest D' and inverse KL (Table 7.3); FMP beats MLM, i.e. "
        "ratios > 1 (Tables 8.2, 8.3). 'FMP better' compares the sums directly (equal to "
        "ratio > 1 when the LL sums are negative and the KL sums positive).\n"
    )
    o.append(
        "| log | dec best D' | dec best inv. KL | FMP better LL REF | FMP better LL DEC | "
        "FMP better KL REF | FMP better KL DEC |\n|---|---|---|---|---|---|---|"
    )
    keys = (
        "decay_best_dprime",
        "decay_best_inverse_kl",
        "fmp_better_ll_ref",
        "fmp_better_ll_dec",
        "fmp_better_kl_ref",
        "fmp_better_kl_dec",
    )
    for r in rows:
        o.append(f"| {r['log']} | " + " | ".join(_yn(r["orderings"][k]) for k in keys) + " |")
    counts = {k: sum(r["orderings"][k] for r in rows) for k in keys}
    o.append("| **holds in** | " + " | ".join(f"{counts[k]}/{len(rows)}" for k in keys) + " |")
    o.append("\n## Rays floored at the true pose (fraction with log-likelihood < floor)\n")
    ks = (*CH7, "mlm_ref", "fmp_ref", "fmp_dec")
    o.append("| log | " + " | ".join(ks) + " |\n|---|" + "---|" * len(ks))
    for r in rows:
        o.append(
            f"| {r['log']} | " + " | ".join(f"{r['floored_fraction'][k]:.3f}" for k in ks) + " |"
        )
    return "\n".join(o) + "\n"


def plot(rows: list[dict]):
    fig, axes = plt.subplots(4, 1, figsize=(max(8, 1.1 * len(rows) + 3), 12), sharex=True)
    x = np.arange(len(rows))
    w = 0.27
    for i, k in enumerate(CH7):
        axes[0].bar(x + (i - 1) * w, [r["dprime_per_ray"][k] for r in rows], w, label=NAMES[k])
        axes[1].bar(x + (i - 1) * w, [r["inverse_kl"][k] for r in rows], w, label=NAMES[k])
    axes[0].set_ylabel("D' per ray (nats)")
    axes[0].set_title("Table 7.3a: D'(g||h) / number of rays (lower is better)")
    axes[1].set_ylabel("inverse KL (nats)")
    axes[1].set_title("Table 7.3b: inverse KL D(h||g), mean over scans (lower is better)")
    for ax, key, title in (
        (axes[2], "ll_ratio", "Table 8.2: log-likelihood ratio MLM / FMP (> 1: FMP better)"),
        (axes[3], "kl_ratio", "Table 8.3: KL ratio MLM / FMP (> 1: FMP better)"),
    ):
        for i, m in enumerate(("ref", "dec")):
            ax.bar(x + (i - 0.5) * w, [r[key][m] for r in rows], w, label=m.upper())
        ax.axhline(1.0, color="k", lw=0.8)
        ax.set_title(title)
        ax.set_ylabel("ratio")
    for ax in axes:
        ax.legend(fontsize=8)
    axes[-1].set_xticks(x, [r["log"] for r in rows], rotation=30, ha="right")
    fig.tight_layout()
    return fig


@hydra.main(config_path="../configs", config_name="pose_likelihood", version_base=None)
def main(cfg: DictConfig) -> dict:
    validate(cfg, "pose_likelihood")
    out = output_dir()
    if (done := completed_job(out)) is not None:  # a sweep job that already finished
        return done
    t0 = time.perf_counter()
    rows = []
    for name in (bar := tqdm(list(cfg.logs), desc="logs", unit="log")):
        bar.set_postfix_str(name)
        rows.append(evaluate_log(name, cfg))
    total = time.perf_counter() - t0
    results = {
        "config": OmegaConf.to_container(cfg, resolve=True),
        "rows": rows,
        "total_s": total,
        "jax_backend": jax.default_backend(),
        "summary": {
            k: f"{sum(r['orderings'][k] for r in rows)}/{len(rows)}" for k in rows[0]["orderings"]
        },
    }
    md = markdown(rows, cfg, total)
    save_figure(plot(rows), out / "pose_likelihood.png", dpi=100)
    write_results(out, results=results, markdown=md, cfg=cfg, allow_nan=False)
    print(md)
    print(f"wrote {out / 'results.json'}, {out / 'results.md'}, {out / 'pose_likelihood.png'}")
    return results


if __name__ == "__main__":
    main()
