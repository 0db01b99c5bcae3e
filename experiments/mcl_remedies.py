"""Why the ray-traced models' particle filters fail to converge, and what fixes it
(issue "Localization that converges"), on the CARMEN logs with the protocol of
``experiments/mcl.py`` (Table 7.2 start: offset and spread N(0, 1 m^2) / N(0, 0.1 rad^2),
300 particles, 30 beams, 10 runs x 100 steps).

1. **Diagnosis** at the corrected poses of the localized scans, per log and model: the
   fraction of beams whose log-likelihood is below the floor (-10 nats; mostly end points
   in cells with lambda = 0), and the fall of the scan log-likelihood for pose offsets of
   0.1 / 0.2 / 0.5 / 1 m (median over steps and x/y directions) and 0.05 rad. A plot shows
   the likelihood surface around one true pose for each model.
2. **Remedies, each alone** (``variants``): kernel-smoothed map statistics
   (``maps.smooth_stats``), tempering (``ScanModel(beam_exponent=...)``), a uniform
   mixture (``z_rand``), augmented MCL (random-particle injection), KLD sampling,
   gradient-guided particles (``GradientGuidedMotion``), and more particles, for the
   decay-rate model (and its full posterior), against the endpoint model.
3. **Global localization** from particles uniform over the free cells (``init_global``).

Per log and variant: runs converged (final error < 0.5 m), error once converged (mean
over the second half of the steps of the converged runs), mean error, and milliseconds per
filter step (the ``runs`` filters run batched; compile time excluded). Writes
``results.json``, ``results.md``, ``surfaces.png`` and ``errors.png``.
E.g. ``python experiments/mcl_remedies.py logs=[intel] filter.runs=2 filter.max_steps=20``.
"""

from __future__ import annotations

import os
import time
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
    fmt,
    grid_model,
    mapping_stats,
    mark_complete,
    output_dir,
    run_info,
    write_results,
)
from _schemas import INITS, VARIANT_KEYS, validate  # noqa: E402
from mcl import NAMES, error_grid, initial_states, prepare, wrap  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402
from tqdm import tqdm  # noqa: E402

from lidarjax import localization as loc  # noqa: E402
from lidarjax import maps  # noqa: E402


def _variant(v) -> dict:
    v = dict(v)
    unknown = set(v) - VARIANT_KEYS
    if unknown:
        raise ValueError(f"variant keys {sorted(unknown)} unknown; allowed {sorted(VARIANT_KEYS)}")
    if v.get("model") not in NAMES:
        raise ValueError(f"variant model must be one of {sorted(NAMES)}, got {v.get('model')!r}")
    if v.get("init") not in INITS:
        raise ValueError(
            f"variant init must be one of {sorted(map(str, INITS))}, got {v.get('init')!r}"
        )
    return v


class MapCache:
    """Grid models per (model, smoothing) for one log."""

    def __init__(self, stats, cfg, p_out):
        self.stats, self.cfg, self.p_out = stats, cfg, p_out
        self._smoothed, self._models = {0.0: stats}, {}

    def lattice(self, position_step_m: float, n_headings: int, max_hypotheses: int):
        """The global-initialisation lattice over the free cells (built once)."""
        key = ("lattice", float(position_step_m), int(n_headings), int(max_hypotheses))
        if key not in self._models:
            self._models[key] = loc.pose_lattice(
                self.stats.spec,
                np.asarray(_free_mask(self.stats)),
                position_step_m=float(position_step_m),
                n_headings=int(n_headings),
                max_hypotheses=int(max_hypotheses),
            )
        return self._models[key]

    def get(self, model: str, smoothing_m: float = 0.0):
        if model == "end" and smoothing_m:
            raise ValueError("smoothing_m applies to the ray-traced models, not the endpoint model")
        key = (model, float(smoothing_m))
        if key not in self._models:
            s = float(smoothing_m)
            if s not in self._smoothed:
                self._smoothed[s] = maps.smooth_stats(self.stats, s)
            self._models[key] = grid_model(model, self._smoothed[s], self.cfg, self.p_out)
        return self._models[key]


# --------------------------------------------------------------------------------------
# Diagnosis
# --------------------------------------------------------------------------------------


def diagnose(cache: MapCache, az, seq, cfg, r_min, r_max, models) -> tuple[dict, dict]:
    """Floor fraction and likelihood fall-off at the true poses; surface around one pose."""
    gt = jnp.asarray(seq["gt"])
    z = seq["z"]
    floor = float(cfg.ray_floor)
    out, surfaces = {}, {}
    offsets = [0.1, 0.2, 0.5, 1.0]
    for name in models:
        base_model, _, sigma = name.partition("@")  # "dec@0.1": smoothed statistics
        m = cache.get(base_model, float(sigma) if sigma else 0.0)
        sm = loc.ScanModel(m, az, r_min, r_max, ray_floor=None)

        def per_ray(p, zz, sm=sm):
            return sm.ray_log_likelihoods(jaxlie.SE2.from_xy_theta(p[0:1], p[1:2], p[2:3]), zz)[0]

        def total(p, zz, sm=sm):
            return jnp.sum(jnp.maximum(per_ray(p, zz, sm), floor))

        ll = np.asarray(jax.vmap(per_ray)(gt, z))
        base = np.asarray(jax.vmap(total)(gt, z))
        falls = {}
        for d in offsets:
            drops = []
            for dx, dy in ((d, 0.0), (-d, 0.0), (0.0, d), (0.0, -d)):
                shifted = gt + jnp.asarray([dx, dy, 0.0])
                drops.append(base - np.asarray(jax.vmap(total)(shifted, z)))
            falls[f"{d:g} m"] = float(np.median(np.stack(drops)))
        for dth in (0.05,):
            drops = [
                base - np.asarray(jax.vmap(total)(gt + jnp.asarray([0.0, 0.0, s * dth]), z))
                for s in (1, -1)
            ]
            falls[f"{dth:g} rad"] = float(np.median(np.stack(drops)))
        out[name] = {
            "below_floor_fraction": float((ll < floor).mean()),
            "log_lik_at_truth_per_beam": float(np.maximum(ll, floor).mean()),
            "fall_nats": falls,
        }
        # surface (x, y) around the middle step's true pose, with floor
        t = gt.shape[0] // 2
        g = np.linspace(-1.0, 1.0, 41)
        xx, yy = np.meshgrid(g, g, indexing="ij")
        pts = gt[t] + jnp.stack(
            [jnp.asarray(xx.ravel()), jnp.asarray(yy.ravel()), jnp.zeros(xx.size)], -1
        )
        surf = np.asarray(jax.vmap(lambda p, zt=z[t], f=total: f(p, zt))(pts)).reshape(xx.shape)
        surfaces[name] = surf - surf.max()
    return out, surfaces


# --------------------------------------------------------------------------------------
# Filters
# --------------------------------------------------------------------------------------


@eqx.filter_jit
def _run_all(pf, states, controls, z):
    return eqx.filter_vmap(pf.run, in_axes=(0, None, None))(states, controls, z)


def _free_mask(stats):
    """Free cells for global initialisation: visited, reflection ratio below 0.2."""
    h = np.asarray(stats.hits, np.float64)
    n = h + np.asarray(stats.misses, np.float64)
    return jnp.asarray((n > 0) & (h < 0.2 * np.maximum(n, 1)))


def make_filter(v: dict, cache: MapCache, az, cfg, r_min, r_max):
    scan_kwargs = dict(
        ray_floor=float(cfg.ray_floor),
        z_rand=float(v.get("z_rand", 0.0)),
        beam_exponent=float(v.get("beam_exponent", 1.0)),
        chunk_size=int(cfg.filter.chunk_size),
    )
    if v.get("coarse_to_fine"):
        c2f = dict(v["coarse_to_fine"])
        sig = [float(x) for x in c2f["sigmas_m"]]
        scan = loc.CoarseToFineScanModel(
            [loc.ScanModel(cache.get(v["model"], s), az, r_min, r_max, **scan_kwargs) for s in sig],
            sig,
            spread_factor=float(c2f.get("spread_factor", 1.0)),
        )
    else:
        m = cache.get(v["model"], float(v.get("smoothing_m", 0.0)))
        scan = loc.ScanModel(m, az, r_min, r_max, **scan_kwargs)
    motion = loc.OdometryMotionModel(
        sigma=list(cfg.filter.motion_sigma),
        alpha=[list(r) for r in cfg.filter.motion_alpha],
        inflation=float(cfg.filter.inflation),
    )
    if v.get("guided"):
        g = dict(v["guided"])
        field_map = cache.get("dec", float(v.get("smoothing_m", 0.0)))
        surrogate = loc.smooth_scan_surrogate(
            field_map,
            az,
            r_min,
            r_max,
            blur_m=float(g.get("blur_m", 0.1)),
            n_nodes=int(g.get("n_nodes", 64)),
            ray_floor=float(cfg.ray_floor),
        )
        motion = loc.GradientGuidedMotion(
            motion,
            surrogate,
            step_scale=float(g.get("step_scale", 1.0)),
            proposal_inflation=float(g.get("proposal_inflation", 1.0)),
            n_grad_steps=int(g.get("n_grad_steps", 1)),
            curvature=bool(g.get("curvature", True)),
        )
    extra = {}
    if float(v.get("alpha_fast", 0.0)) > 0:
        extra.update(
            alpha_slow=float(v["alpha_slow"]),
            alpha_fast=float(v["alpha_fast"]),
            injector=loc.global_injector(cache.stats.spec, _free_mask(cache.stats)),
        )
    if v.get("kld"):
        k = dict(v["kld"]) if not isinstance(v["kld"], bool) else {}
        extra.update(
            kld=True,
            kld_epsilon=float(k.get("epsilon", 0.05)),
            kld_delta=float(k.get("delta", 0.01)),
            n_min=int(k.get("n_min", 100)),
        )
    return loc.ParticleFilter(
        motion,
        scan,
        resample_fraction=float(cfg.filter.resample_fraction),
        resampler=str(cfg.filter.resampler),
        best_fraction=float(cfg.filter.best_fraction),
        **extra,
    )


LATTICE_DEFAULTS = {
    "position_step_m": 0.5,
    "n_headings": 72,
    "max_hypotheses": 4_000_000,
    "smoothing_factor": 0.6,  # the scoring map is smoothed by this times the block side
    "uniform_fraction": 0.1,
}


def init_from_start_scan(v: dict, cache: MapCache, az, seq, cfg, r_min, r_max, n, keys):
    """Global initialisation from the start scan (``loc.init_from_scan``), one state per
    key, stacked: a pose lattice over the free cells scored once by the variant's model on
    statistics smoothed by ``smoothing_factor`` x the block side (the endpoint model
    unsmoothed)."""
    lat_cfg = {**LATTICE_DEFAULTS, **dict(v.get("lattice") or {})}
    unknown = set(lat_cfg) - set(LATTICE_DEFAULTS)
    if unknown:
        raise ValueError(
            f"lattice keys {sorted(unknown)} unknown; allowed {sorted(LATTICE_DEFAULTS)}"
        )
    lattice = cache.lattice(
        lat_cfg["position_step_m"], lat_cfg["n_headings"], lat_cfg["max_hypotheses"]
    )
    sigma = 0.0 if v["model"] == "end" else float(lat_cfg["smoothing_factor"]) * lattice.step_m
    scorer = loc.ScanModel(
        cache.get(v["model"], sigma),
        az,
        r_min,
        r_max,
        ray_floor=float(cfg.ray_floor),
        chunk_size=int(cfg.filter.chunk_size),
    )
    scores = loc.lattice_scores(lattice, scorer, seq["z0"])
    states = [
        loc.init_from_scan(
            n,
            lattice,
            scorer,
            seq["z0"],
            key=k,
            uniform_fraction=float(lat_cfg["uniform_fraction"]),
            scores=scores,
        )
        for k in keys
    ]
    return jax.tree.map(lambda *x: jnp.stack(x), *states)


def run_variant(v: dict, cache: MapCache, az, seq, key, cfg, r_min, r_max, runs: int) -> dict:
    pf = make_filter(v, cache, az, cfg, r_min, r_max)
    n = int(v.get("particles", cfg.filter.particles))
    init_seconds = 0.0
    if v.get("init") == "global":
        free = _free_mask(cache.stats)
        states = [
            loc.init_global(n, cache.stats.spec, free, key=jax.random.fold_in(key, 100 + r))
            for r in range(runs)
        ]
        states = jax.tree.map(lambda *x: jnp.stack(x), *states)
    elif v.get("init") == "global_scan":
        t_init = time.perf_counter()
        keys = [jax.random.fold_in(key, 100 + r) for r in range(runs)]
        states = init_from_start_scan(v, cache, az, seq, cfg, r_min, r_max, n, keys)
        jax.block_until_ready(states)
        init_seconds = (time.perf_counter() - t_init) / runs
    else:
        fcfg = OmegaConf.merge(cfg, {"filter": {"particles": n, "runs": runs}})
        states = initial_states(key, seq["start"], fcfg)
    compiled = _run_all.lower(pf, states, seq["controls"], seq["z"]).compile()
    t0 = time.perf_counter()
    _, info = compiled(pf, states, seq["controls"], seq["z"])
    est = np.asarray(loc.to_vector(info.estimate), np.float64)  # [runs T 3]
    seconds = time.perf_counter() - t0
    gt = seq["gt"]
    pos = np.linalg.norm(est[..., :2] - gt[None, :, :2], axis=-1)
    head = np.abs(wrap(est[..., 2] - gt[None, :, 2]))
    conv = pos[:, -1] < 0.5
    half = pos.shape[1] // 2
    n_active = getattr(info, "n_active", None)
    return {
        "converged_runs": int(conv.sum()),
        "runs": int(runs),
        "pos_err_converged_m": float(pos[conv, half:].mean()) if conv.any() else None,
        "head_err_converged_deg": float(np.rad2deg(head[conv, half:].mean()))
        if conv.any()
        else None,
        "pos_err_m": float(pos.mean()),
        "ms_per_step": 1e3 * seconds / (pos.shape[1] * runs),
        "particles": n,
        "mean_active_particles": None if n_active is None else float(np.asarray(n_active).mean()),
        "init_seconds_per_run": init_seconds,
        "curve": pos.mean(0).tolist(),
    }


# --------------------------------------------------------------------------------------
# Output
# --------------------------------------------------------------------------------------


def write_tables(results: dict, cfg) -> str:
    lines = []
    diag_models = list(cfg.diagnose.models)
    if any("diagnosis" in r for r in results.values()):
        lines += [
            "### Diagnosis at the true poses: beams below the floor [%] / fall of the scan "
            "log-likelihood for a 0.1 m, 0.5 m, 0.05 rad offset [nats, median]",
            "",
            "| log | " + " | ".join(_label(m) for m in diag_models) + " |",
            "|---|" + "---|" * len(diag_models),
        ]
        for name, r in results.items():
            if "diagnosis" not in r:
                continue
            cells = []
            for m in diag_models:
                d = r["diagnosis"][m]
                f = d["fall_nats"]
                cells.append(
                    f"{100 * d['below_floor_fraction']:.1f} / {f['0.1 m']:.0f}, "
                    f"{f['0.5 m']:.0f}, {f['0.05 rad']:.0f}"
                )
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        lines.append("")
    variants = [v for v in cfg.variants if any(v in r["variants"] for r in results.values())]
    lines += [
        "### Remedies: runs converged / error once converged [m] (per log); totals",
        "",
        "| variant | " + " | ".join(results) + " | converged | logs ≤ endpoint | ms/step |",
        "|---|" + "---|" * (len(results) + 3),
    ]
    for vn in variants:
        cells, conv, total, ms, better = [], 0, 0, [], 0
        for r in results.values():
            x = r["variants"].get(vn)
            if x is None:
                cells.append("")
                continue
            cells.append(f"{x['converged_runs']}/{x['runs']}: {fmt(x['pos_err_converged_m'])}")
            conv += x["converged_runs"]
            total += x["runs"]
            ms.append(x["ms_per_step"])
            e = r["variants"].get(cfg.reference_variant)
            if (
                e is not None
                and x["pos_err_converged_m"] is not None
                and e["pos_err_converged_m"] is not None
                and x["pos_err_converged_m"] <= e["pos_err_converged_m"]
            ):
                better += 1
        pct = 100 * conv / max(total, 1)
        lines.append(
            f"| {vn} | " + " | ".join(cells) + f" | {conv}/{total} ({pct:.0f} %) | {better} | "
            f"{np.mean(ms):.1f} |"
        )
    glob = [r.get("global") for r in results.values() if r.get("global")]
    if glob:
        lines += [
            "",
            "### Global localization: runs converged / error once converged [m] "
            "(ms per step, init s)",
            "",
        ]
        gv = list(glob[0])
        lines.append("| log | " + " | ".join(gv) + " |")
        lines.append("|---|" + "---|" * len(gv))
        for name, r in results.items():
            if not r.get("global"):
                continue
            cells = [
                f"{x['converged_runs']}/{x['runs']}: {fmt(x['pos_err_converged_m'])} "
                f"({x['ms_per_step']:.0f} ms"
                + (
                    f", init {x['init_seconds_per_run']:.0f} s)"
                    if x.get("init_seconds_per_run")
                    else ")"
                )
                for x in r["global"].values()
            ]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        tot = {vn: [0, 0] for vn in gv}
        for r in results.values():
            for vn, x in (r.get("global") or {}).items():
                tot[vn][0] += x["converged_runs"]
                tot[vn][1] += x["runs"]
        lines.append(
            "| all | "
            + " | ".join(f"{c}/{t} ({100 * c / max(t, 1):.0f} %)" for c, t in tot.values())
            + " |"
        )
    return "\n".join(lines) + "\n"


def _label(name: str) -> str:
    base, _, sigma = name.partition("@")
    return NAMES[base] + (f", smoothed {sigma} m" if sigma else "")


def plot_surfaces(surfaces: dict, out: Path) -> None:
    logs = list(surfaces)
    if not logs:
        return
    models = list(surfaces[logs[0]])
    fig, axes = plt.subplots(
        len(logs),
        len(models),
        figsize=(2.6 * len(models) + 1.2, 2.6 * len(logs)),
        squeeze=False,
        sharex=True,
        sharey=True,
        layout="constrained",
    )
    for i, name in enumerate(logs):
        for j, m in enumerate(models):
            ax = axes[i, j]
            im = ax.imshow(
                np.maximum(surfaces[name][m].T, -200.0),
                origin="lower",
                extent=(-1, 1, -1, 1),
                cmap="viridis",
                vmin=-200,
                vmax=0,
            )
            ax.set_title(f"{name}: {_label(m)}", fontsize=7)
            if i == len(logs) - 1:
                ax.set_xlabel("x offset [m]")
            if j == 0:
                ax.set_ylabel("y offset [m]")
    fig.colorbar(im, ax=axes, shrink=0.6, label="scan log-likelihood − max [nats]")
    fig.savefig(out / "surfaces.png", dpi=110)
    plt.close(fig)


def plot_errors(results: dict, out: Path) -> None:
    error_grid(
        {name: {vn: x["curve"] for vn, x in r["variants"].items()} for name, r in results.items()},
        out / "errors.png",
        "mean position error [m]",
        legend_size=5,
    )


def write_outputs(out: Path, cfg, results, surfaces, runtime_s) -> None:
    summary = {
        "config": OmegaConf.to_container(cfg, resolve=True),
        "logs": results,
        "runtime_s": runtime_s,
        **run_info(),
    }
    write_results(out, results=summary, markdown=write_tables(results, cfg), partial=True)
    plot_surfaces(surfaces, out)
    plot_errors(results, out)


@hydra.main(config_path="../configs", config_name="mcl_remedies", version_base=None)
def main(cfg: DictConfig) -> None:
    validate(cfg, "mcl_remedies")
    out = output_dir()
    if (done := completed_job(out)) is not None:  # a sweep job that already finished
        return done
    variants = {k: _variant(v) for k, v in cfg.variants.items()}
    if cfg.only is not None:
        missing = set(cfg.only) - set(variants)
        if missing:
            raise ValueError(f"only: unknown variants {sorted(missing)}")
        variants = {k: v for k, v in variants.items() if k in set(cfg.only)}
    glob = {k: _variant(v) for k, v in (cfg.global_localization.variants or {}).items()}
    if cfg.reference_variant not in cfg.variants:
        raise ValueError(f"reference_variant {cfg.reference_variant!r} is not a variant")
    t0 = time.perf_counter()
    results, surfaces = {}, {}
    for name in tqdm(list(cfg.logs), desc="logs"):
        t_log = time.perf_counter()
        log, r_min, r_max, az, seq, key = prepare(name, cfg)
        stats, spec, p_out = mapping_stats(log, cfg, r_min, r_max)
        cache = MapCache(stats, cfg, p_out)
        res = {"load_average": os.getloadavg()[0], "grid_shape": list(spec.shape)}
        if cfg.diagnose.enabled:
            res["diagnosis"], surfaces[name] = diagnose(
                cache, az, seq, cfg, r_min, r_max, list(cfg.diagnose.models)
            )
        res["variants"] = {}
        for vn, v in tqdm(variants.items(), desc=name, leave=False):
            res["variants"][vn] = run_variant(
                v, cache, az, seq, key, cfg, r_min, r_max, int(v.get("runs", cfg.filter.runs))
            )
        if glob and cfg.global_localization.runs > 0:
            res["global"] = {
                vn: run_variant(
                    {"init": "global", **v},
                    cache,
                    az,
                    seq,
                    jax.random.fold_in(key, 11),
                    cfg,
                    r_min,
                    r_max,
                    int(cfg.global_localization.runs),
                )
                for vn, v in glob.items()
            }
        res["seconds"] = time.perf_counter() - t_log
        results[name] = res
        tqdm.write(
            f"{name}: "
            + ", ".join(
                f"{vn} {x['converged_runs']}/{x['runs']}" for vn, x in res["variants"].items()
            )
            + f" ({res['seconds']:.0f} s)"
        )
        write_outputs(out, cfg, results, surfaces, time.perf_counter() - t0)
    mark_complete(out)  # a sweep job: results.json holds every log
    print(write_tables(results, cfg))


if __name__ == "__main__":
    main()
