"""Three decay-rate fields at equal parameter counts on the CARMEN logs: held-out-ray
log-likelihood of a grid map, a DCT map and a user-defined RBF field.

Per log (``experiments/custom_field.py``, :func:`patch_rays`): the 1 m-aligned 10 m x 10 m
patch holding the most HIT end points; ``n_rays`` HIT rays ending in it from the even scans
are the mapping rays, ``n_rays`` from the odd scans the held-out test rays (sampled with
``seed``). For every ``L`` in ``resolutions`` three fields with ``L * L`` parameters each
are fitted to the mapping rays over the patch:

- **grid**: the ML decay-rate grid map, ``L x L`` cells, closed form (Eq. 7.10), rate 0 in
  never-traversed cells and outside the patch;
- **dct**: :func:`lidarjax.maps.fit_dct`, ``L x L`` coefficients (L-BFGS from the DCT of the
  grid map; ``fit.rtol``, ``fit.atol``, ``fit.max_steps``);
- **rbf**: :class:`custom_field.RBFField`, ``softplus`` of an ``L x L`` lattice of Gaussians,
  fitted with the generic :func:`lidarjax.maps.fit` from :func:`custom_field.rbf_field_like`
  of the grid map (same tolerances, ``rbf.max_steps``).

Each field is scored by the mean per-ray log-likelihood of the test rays (nats/ray; HIT rays
are log densities in log(1/m)), each ray floored at ``floor_nats`` (a ray through a zero-rate
cell of the grid map ends with probability 0), together with the number of floored rays, and
by the unfloored mean over the test rays whose log-likelihood is finite under all three
models. Fit times (``time.perf_counter`` around the call, results blocked) include JIT
compilation: every (log, L) has new shapes or static fields, so each fit compiles afresh.

Summary over logs per L: mean and std of each model's held-out log-likelihood, the number
of logs where each model is best, and the mean paired differences dct - grid, rbf - grid,
rbf - dct.

Writes ``results.json`` (after every log), ``results.md``, ``fields.png`` (``p_ref = 1 -
exp(-lambda)`` of the three fields for ``figure_log`` at ``figure_resolution`` on a 0.05 m
raster) and ``fields_ll.png`` (mean held-out log-likelihood vs parameter count) into
Hydra's output folder. E.g. ``python experiments/decay_rate_fields.py logs=[intel]
resolutions=[10,20]``.
"""

from __future__ import annotations

import time
from pathlib import Path

import hydra
import jax
import matplotlib

matplotlib.use("Agg")
import jax.numpy as jnp  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from _common import completed_job, mark_complete, output_dir, write_results  # noqa: E402
from _schemas import validate  # noqa: E402
from custom_field import RBFField, held_out, patch_rays, rbf_field_like  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402
from tqdm import tqdm  # noqa: E402

from lidarjax import maps  # noqa: E402
from lidarjax.raytrace import GridSpec, accumulate  # noqa: E402

PATCH_M = 10.0  # side of the square patch (m), fixed by custom_field.patch_rays
MODELS = ("grid", "dct", "rbf")
RASTER_M = 0.05  # figure raster


def _block(out):
    jax.block_until_ready(jax.tree_util.tree_leaves(out))
    return out


def _n_parameters(field) -> int:
    return int(sum(np.size(x) for x in jax.tree_util.tree_leaves(field.parameters())))


def fit_fields(train, lower: np.ndarray, L: int, cfg: DictConfig) -> tuple[dict, dict]:
    """The three fitted fields ``{model: field}`` and per-model fit information."""
    info = {}
    t = time.perf_counter()
    spec = GridSpec(jnp.asarray(lower), PATCH_M / L, (L, L))
    grid = _block(maps.decay_rate_map(accumulate(spec, train), unknown_rate=0.0))  # Eq. 7.10
    info["grid"] = dict(fit_s=time.perf_counter() - t)

    t = time.perf_counter()
    dct, sol = maps.fit_dct(
        train,
        (L, L),
        lower=lower,
        extent=[PATCH_M, PATCH_M],
        rtol=cfg.fit.rtol,
        atol=cfg.fit.atol,
        max_steps=cfg.fit.max_steps,
    )
    _block(dct)
    info["dct"] = dict(
        fit_s=time.perf_counter() - t,
        steps=int(sol.stats["num_steps"]),
        result=str(sol.result),
    )

    rbf0: RBFField = rbf_field_like(
        grid, width=float(cfg.rbf.width), nodes_per_sigma=float(cfg.rbf.nodes_per_sigma)
    )
    t = time.perf_counter()
    rbf, sol = maps.fit(
        rbf0, train, rtol=cfg.fit.rtol, atol=cfg.fit.atol, max_steps=cfg.rbf.max_steps
    )
    _block(rbf)
    info["rbf"] = dict(
        fit_s=time.perf_counter() - t,
        steps=int(sol.stats["num_steps"]),
        result=str(sol.result),
        quadrature_nodes=int(rbf.n_nodes),
    )
    return {"grid": grid, "dct": dct, "rbf": rbf}, info


def evaluate_log(name: str, cfg: DictConfig, figs: dict, bar=None) -> dict:
    train, test, lower = patch_rays(name, int(cfg.n_rays), size=PATCH_M, seed=int(cfg.seed))
    lower = np.asarray(lower, float)
    row = dict(
        log=name,
        patch_lower=lower.tolist(),
        n_train=int(train.n),
        n_test=int(test.n),
        res={},
    )
    floor = float(cfg.floor_nats)
    for L in cfg.resolutions:
        L = int(L)
        if bar is not None:
            bar.set_postfix_str(f"{name} L={L}")
        fields, info = fit_fields(train, lower, L, cfg)
        ll = {m: np.asarray(maps.field_log_likelihood(f, test)) for m, f in fields.items()}
        common = np.all([np.isfinite(v) for v in ll.values()], axis=0)
        r = dict(n_common_finite=int(common.sum()))
        for m, f in fields.items():
            mean_floored, n_floored = held_out(f, test, floor=floor)
            r[m] = dict(
                ll=mean_floored,
                n_floored=n_floored,
                ll_unfloored_common=float(ll[m][common].mean()) if common.any() else None,
                n_parameters=_n_parameters(f),
                **info[m],
            )
        r["best"] = max(MODELS, key=lambda m: r[m]["ll"])
        row["res"][str(L)] = r
        if name == cfg.figure_log and L == int(cfg.figure_resolution):
            figs["fields"] = (fields, lower, L)
    return row


def _sd(x: np.ndarray) -> float:
    return float(x.std(ddof=1)) if x.size > 1 else 0.0


def summarize(rows: list[dict], cfg: DictConfig) -> dict:
    out = {}
    for L in cfg.resolutions:
        k = str(int(L))
        ll = {m: np.array([r["res"][k][m]["ll"] for r in rows]) for m in MODELS}
        best = [r["res"][k]["best"] for r in rows]
        out[k] = dict(
            n_parameters=int(L) ** 2,
            n_logs=len(rows),
            mean={m: float(ll[m].mean()) for m in MODELS},
            std={m: _sd(ll[m]) for m in MODELS},
            n_best={m: best.count(m) for m in MODELS},
            diff={
                "dct-grid": float((ll["dct"] - ll["grid"]).mean()),
                "rbf-grid": float((ll["rbf"] - ll["grid"]).mean()),
                "rbf-dct": float((ll["rbf"] - ll["dct"]).mean()),
            },
            mean_fit_s={m: float(np.mean([r["res"][k][m]["fit_s"] for r in rows])) for m in MODELS},
        )
    return out


def markdown(rows: list[dict], summ: dict, cfg: DictConfig, total_s: float) -> str:
    lines = [
        f"# Decay-rate fields on {len(rows)} CARMEN logs ({total_s / 60:.1f} min)",
        "",
        f"Held-out mean log-likelihood [nats/ray] of {cfg.n_rays} odd-scan HIT rays per log "
        f"(each floored at {cfg.floor_nats}), fields fitted to {cfg.n_rays} even-scan HIT rays "
        "in the densest 10 m x 10 m patch; L x L parameters for every model. Best = number "
        "of logs where the model has the highest held-out log-likelihood.",
        "",
        "| L | parameters | grid μ | grid σ | DCT μ | DCT σ | RBF μ | RBF σ | best grid/DCT/RBF "
        "| DCT−grid | RBF−grid | RBF−DCT |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for k, s in summ.items():
        mu, sd, nb, d = s["mean"], s["std"], s["n_best"], s["diff"]
        lines.append(
            f"| {k} | {s['n_parameters']} | {mu['grid']:.4f} | {sd['grid']:.4f} | "
            f"{mu['dct']:.4f} | {sd['dct']:.4f} | {mu['rbf']:.4f} | {sd['rbf']:.4f} | "
            f"{nb['grid']}/{nb['dct']}/{nb['rbf']} | {d['dct-grid']:+.4f} | "
            f"{d['rbf-grid']:+.4f} | {d['rbf-dct']:+.4f} |"
        )
    lines += [
        "",
        "Mean fit times [s] (including JIT compilation):",
        "",
        "| L | grid | DCT | RBF |",
        "|---|---|---|---|",
    ]
    for k, s in summ.items():
        t = s["mean_fit_s"]
        lines.append(f"| {k} | {t['grid']:.3f} | {t['dct']:.2f} | {t['rbf']:.2f} |")
    return "\n".join(lines) + "\n"


def plot_figures(figs: dict, summ: dict, cfg: DictConfig, out: Path) -> None:
    if "fields" in figs:
        fields, lower, L = figs["fields"]
        n = int(round(PATCH_M / RASTER_M))
        xs = lower[0] + (np.arange(n) + 0.5) * RASTER_M
        ys = lower[1] + (np.arange(n) + 0.5) * RASTER_M
        pts = jnp.asarray(np.stack(np.meshgrid(xs, ys, indexing="ij"), -1))
        fig, axs = plt.subplots(1, 3, figsize=(12, 4.2))
        for ax, (m, title) in zip(axs, (("grid", "grid"), ("dct", "DCT"), ("rbf", "RBF (user)"))):
            p = -np.expm1(-np.asarray(fields[m].decay_rate(pts), float))
            ax.imshow(
                p.T,
                origin="lower",
                extent=(lower[0], lower[0] + PATCH_M, lower[1], lower[1] + PATCH_M),
                cmap="gray_r",
                vmin=0,
                vmax=1,
                interpolation="nearest",
            )
            ax.set_title(f"{title}, {L * L} parameters (p_ref)", fontsize=9)
            ax.set_xticks([])
            ax.set_yticks([])
        fig.suptitle(f"{cfg.figure_log}: p_ref = 1 - exp(-lambda), {RASTER_M} m raster")
        fig.tight_layout()
        fig.savefig(out / "fields.png", dpi=100)
        plt.close(fig)
    if summ:
        ks = list(summ)
        n_par = [summ[k]["n_parameters"] for k in ks]
        fig, ax = plt.subplots(figsize=(5.5, 4))
        for m, label in (("grid", "grid"), ("dct", "DCT"), ("rbf", "RBF (user)")):
            mu = np.array([summ[k]["mean"][m] for k in ks])
            sd = np.array([summ[k]["std"][m] for k in ks])
            ax.errorbar(n_par, mu, yerr=sd, marker="o", capsize=3, label=label)
        ax.set_xscale("log")
        ax.set_xlabel("parameters (L x L)")
        ax.set_ylabel("held-out log-likelihood [nats/ray]")
        ax.set_title(f"mean ± std over {summ[ks[0]]['n_logs']} logs", fontsize=9)
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / "fields_ll.png", dpi=100)
        plt.close(fig)


@hydra.main(config_path="../configs", config_name="decay_rate_fields", version_base=None)
def main(cfg: DictConfig) -> dict:
    validate(cfg, "decay_rate_fields")
    jax.config.update("jax_enable_x64", bool(cfg.x64))
    out = output_dir()
    if (done := completed_job(out)) is not None:  # a sweep job that already finished
        return done
    t0 = time.perf_counter()
    rows, figs, summ, results = [], {}, {}, {}
    for name in (bar := tqdm(list(cfg.logs), desc="logs", unit="log")):
        bar.set_postfix_str(name)
        t_log = time.perf_counter()
        row = evaluate_log(name, cfg, figs, bar)
        row["log_s"] = time.perf_counter() - t_log
        rows.append(row)
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
    plot_figures(figs, summ, cfg, out)
    mark_complete(out)  # a sweep job: every log and figure written
    print(md)
    return results


if __name__ == "__main__":
    main()
