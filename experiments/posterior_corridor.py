"""Section 8.5.1 / Figure 8.2: localization in a simulated corridor, ML maps vs. map posteriors.

Protocol (dissertation section 8.5.1, formulas of sections 8.4.3-8.5):

- World: a corridor of ``N = n_voxels`` consecutive voxels. In each run a new hidden map is
  drawn: reflection probabilities ``mu_i ~ U(0, 1)`` (reflection model, REF) and, independently,
  decay rates ``lambda_i ~ Gamma(1, 1)`` (decay-rate model, DEC; shape/rate configurable).
- Mapping: "the robot visits every voxel n times" and "n is the number of observations per
  voxel" (Fig. 8.2 caption), so every voxel is observed exactly ``n`` times, each observation
  sampled from the single-voxel forward model: REF, Eq. (8.3): ``delta ~ Bernoulli(mu_i)``,
  giving ``H_i ~ Binomial(n, mu_i)``, ``M_i = n - H_i``; DEC, Eq. (8.4): a ray enters the voxel
  and travels ``r ~ Exp(lambda_i)``; it is reflected (``delta = 1``) if ``r < L`` (the voxel
  length ``voxel_length_m``), else it leaves the voxel after ``r_i = L`` (``delta = 0``).
  ``H_i`` sums the ``delta`` and ``R_i`` the ``min(r, L)``.
- Maps from these statistics (three methods per model):
  MLM: ``mu* = H/(H+M)`` (Eq. 8.16) with likelihood Eq. (8.23), ``lambda* = H/R`` (Eq. 8.18)
  with likelihood ``exp(-lambda* r) lambda*^delta``;
  FMP, uniform prior: ``Beta(1, 1)`` / the uninformative ``Gamma(1, 0)`` (section 8.4.3);
  FMP, conjugate prior: ``alpha, beta`` moment-matched to the empirical mean and (population)
  variance of the ML map values over the ``N`` voxels of the run (section 8.5 formulas).
  FMP likelihoods are Eq. (8.22) and the decay-rate analogue after Eq. (8.23).
- Localization: the belief is a discrete distribution over the ``N`` voxels, initialised
  uniform. In iteration ``t = 0 .. steps-1`` the robot is in voxel ``t`` (it traverses the
  corridor from start to end, one voxel per iteration), fires its sensor once (a fresh sample
  of the same single-voxel model at the true voxel) and updates the belief with Eq. (8.19)
  (MLM) or Eq. (8.20) (FMP). The motion is known and deterministic (+1 voxel): the prediction
  shifts the belief by one voxel.
- Measure: ``rho`` of one run is the belief at the true voxel after the update, averaged over
  the iterations ("the pose belief at the true pose averaged over each iteration"); the figure
  shows its mean over runs with error bars = variance over runs (Fig. 8.2 caption; ``std`` and
  ``sem`` are configurable and all are written to ``results.json``).
- Statistics: one-tailed paired-sample t-test over runs (same map and measurements for all
  methods of a model): ``d = rho_A - rho_B``, ``t = mean(d) / (std(d, ddof=1) / sqrt(runs))``,
  ``p = P(T_{runs-1} >= t)``, from ``scipy.stats.t.sf`` when scipy is importable, otherwise
  from ``0.5 I_{df/(df+t^2)}(df/2, 1/2)`` with ``jax.scipy.special.betainc`` in float64.

Choices where the text is silent or degenerate (all configurable or documented here):

1. DEC observation geometry: one voxel of length ``L = 1 m`` per observation (see above);
   with ``lambda ~ Gamma(1, 1)`` a voxel reflects half of the rays on average, like REF.
2. Corridor end (``boundary``): ``bounded`` (default) is the exact Bayes filter of a corridor
   of ``N`` voxels with a known forward motion: hypotheses pushed past the last voxel are
   eliminated, so at iteration ``t`` only voxels ``>= t`` are possible (at the last iteration
   every method is certain). ``cyclic`` treats the corridor as a ring (no boundary
   information; ``rho`` then measures map quality alone).
3. Belief collapse: MLM assigns likelihood 0 to measurements its map deems impossible
   (``mu* = 0`` or ``1``, ``lambda* = 0``), so all hypotheses can reach probability 0. Then the
   filter re-initialises (uniform over the voxels still possible, then the current update) and
   the event is counted (``resets_per_run``). FMP never collapses. This is the most favourable
   choice for MLM; with "keep the collapsed belief" its ``rho`` would be lower.
4. Degenerate conjugate prior: at ``n = 1`` every ML reflection value is 0 or 1, so the empirical
   variance equals ``E(1-E)`` and the formulas give ``alpha = beta = 0``, no Beta distribution
   (in that limit Eq. 8.22 *is* Eq. 8.23, i.e. FMP-conjugate would equal MLM). Whenever the
   moments admit no Beta (``V >= E(1-E)`` or ``V = 0``) or Gamma (``V = 0`` or ``E = 0``), the
   uniform prior is used instead (``conjugate_fallback: uniform``), and the fraction of runs
   where this happened is reported. For REF at ``n = 1`` FMP-conjugate therefore equals
   FMP-uniform.
5. Randomness: run ``i`` for observation count ``n`` uses ``fold_in(fold_in(key(seed), n), i)``,
   so results do not depend on ``chunk_size`` and fewer runs give a prefix of more runs (up
   to float32 rounding, ~1e-7, from different batch shapes).

Writes ``results.json``, ``results.md`` and ``figure_8_2.png`` into Hydra's output folder.
"""

from __future__ import annotations

import functools
import math
import time
from pathlib import Path

import hydra
import jax
import jax.numpy as jnp
import numpy as np
from _common import completed_job, output_dir, write_results
from _schemas import validate
from jax import lax
from jax.scipy.special import betainc
from matplotlib.figure import Figure
from omegaconf import DictConfig
from tqdm import tqdm

MODELS = ("reflection", "decay_rate")
METHODS = ("MLM", "FMP_uniform", "FMP_conjugate")
LABELS = {"MLM": "MLM", "FMP_uniform": "FMP, uniform prior", "FMP_conjugate": "FMP, conj. prior"}
COMPARISONS = (
    ("FMP_conjugate", "MLM"),
    ("FMP_conjugate", "FMP_uniform"),
    ("FMP_uniform", "MLM"),
)
# Paper, section 8.5.1: FMP-conjugate beats both others with p < 1e-4 for these n.
PAPER_SIGNIFICANT = {"reflection": "n <= 100", "decay_rate": "n <= 4"}


# --------------------------------------------------------------------------------------
# One run: map, mapping statistics, priors, localization
# --------------------------------------------------------------------------------------


def _beta_conjugate_prior(hits, misses):
    """Section 8.5 moment matching of ``Beta(alpha, beta)`` to ``mu* = H/(H+M)`` (Eq. 8.16).

    ``hits``, ``misses``: ``[N]`` with ``H + M = n > 0``. Returns ``(alpha, beta, valid)``;
    ``valid`` is False when no Beta distribution has the empirical moments.
    """
    mu = hits / (hits + misses)
    e = jnp.mean(mu)
    v = jnp.mean((mu - e) ** 2)
    v_safe = jnp.where(v > 0, v, 1.0)
    alpha = -e * (e * e - e + v) / v_safe
    beta = (e - v + e * v - 2 * e * e + e**3) / v_safe
    # All ML values in {0, 1} <=> V == E (1 - E) exactly (alpha = beta = 0); tested on the
    # integer counts because float rounding could make alpha, beta tiny but "positive".
    binary = jnp.all((hits == 0) | (misses == 0))
    valid = ~binary & (v > 0) & jnp.isfinite(alpha) & jnp.isfinite(beta)
    valid = valid & (alpha > 0) & (beta > 0)
    return alpha, beta, valid


def _gamma_conjugate_prior(hits, lengths):
    """Section 8.5 moment matching of ``Gamma(alpha, beta)`` to ``lambda* = H/R`` (Eq. 8.18)."""
    lam = hits / lengths
    e = jnp.mean(lam)
    v = jnp.mean((lam - e) ** 2)
    v_safe = jnp.where(v > 0, v, 1.0)
    alpha = e * e / v_safe
    beta = e / v_safe
    valid = (v > 0) & (e > 0) & jnp.isfinite(alpha) & jnp.isfinite(beta)
    return alpha, beta, valid


def _one_run(key, *, n, n_voxels, steps, length_m, shape, rate, cyclic):
    """One run of section 8.5.1 for both models. Returns per-run results (see ``_summary``)."""
    N = n_voxels
    k_mu, k_lam, k_map_ref, k_map_dec, k_loc_ref, k_loc_dec = jax.random.split(key, 6)
    dtype = jnp.result_type(float)
    tiny = jnp.finfo(dtype).tiny

    # Hidden maps.
    mu = jax.random.uniform(k_mu, (N,), dtype)
    lam = jnp.maximum(jax.random.gamma(k_lam, shape, (N,), dtype) / rate, tiny)

    # Mapping: every voxel observed n times (n is traced: one compilation serves all n).
    def observe(k, stats):
        h_ref, h_dec, r_dec = stats
        delta = jax.random.uniform(jax.random.fold_in(k_map_ref, k), (N,), dtype) < mu
        r = jax.random.exponential(jax.random.fold_in(k_map_dec, k), (N,), dtype) / lam
        return h_ref + delta, h_dec + (r < length_m), r_dec + jnp.minimum(r, length_m)

    zeros = jnp.zeros((N,), dtype)
    hits_ref, hits_dec, lengths_dec = lax.fori_loop(0, n, observe, (zeros, zeros, zeros))
    n = jnp.asarray(n, dtype)
    misses_ref = n - hits_ref
    lengths_dec = jnp.maximum(lengths_dec, tiny)  # R = 0 needs n rays of length exactly 0

    # Localization measurements at the true voxels.
    pos = jnp.arange(steps) % N
    delta_ref = jax.random.uniform(k_loc_ref, (steps,), dtype) < mu[pos]
    r_loc = jax.random.exponential(k_loc_dec, (steps,), dtype) / lam[pos]
    delta_dec = r_loc < length_m
    r_loc = jnp.minimum(r_loc, length_m)

    # Priors: uniform and moment-matched (falls back to uniform where degenerate).
    a_c, b_c, ok_ref = _beta_conjugate_prior(hits_ref, misses_ref)
    a_c = jnp.where(ok_ref, a_c, 1.0)
    b_c = jnp.where(ok_ref, b_c, 1.0)
    g_a, g_b, ok_dec = _gamma_conjugate_prior(hits_dec, lengths_dec)
    g_a = jnp.where(ok_dec, g_a, 1.0)
    g_b = jnp.where(ok_dec, g_b, 0.0)

    # REF, Eq. (8.22) with alpha = beta = 0 is Eq. (8.23) (MLM): per-voxel log l(delta).
    ref_alpha = jnp.stack([jnp.zeros_like(a_c), jnp.ones_like(a_c), a_c])[:, None]
    ref_beta = jnp.stack([jnp.zeros_like(b_c), jnp.ones_like(b_c), b_c])[:, None]
    a = hits_ref + ref_alpha  # [3 N]
    b = misses_ref + ref_beta
    ref_log1 = jnp.log(a) - jnp.log(a + b)  # log 0 = -inf for MLM: impossible measurement
    ref_log0 = jnp.log(b) - jnp.log(a + b)

    # DEC: MLM rate and FMP Gamma posteriors Gamma(H + alpha, R + beta), Eq. (8.17).
    lam_ml = hits_dec / lengths_dec
    log_lam_ml = jnp.log(lam_ml)
    dec_a = hits_dec + jnp.stack([jnp.ones_like(g_a), g_a])[:, None]  # [2 N]
    dec_b = lengths_dec + jnp.stack([jnp.zeros_like(g_b), g_b])[:, None]
    log_dec_a, log_dec_b = jnp.log(dec_a), jnp.log(dec_b)

    def log_likelihoods(d_ref, d_dec, r):
        """``[6 N]`` log-likelihood of this step's measurements at every voxel."""
        ll_ref = jnp.where(d_ref, ref_log1, ref_log0)
        ll_mlm = jnp.where(d_dec, log_lam_ml, 0.0) - lam_ml * r  # exp(-lam r) lam^delta
        log_br = jnp.log(dec_b + r)
        ll_fmp = dec_a * (log_dec_b - log_br) + jnp.where(d_dec, log_dec_a - log_br, 0.0)
        return jnp.concatenate([ll_ref, ll_mlm[None], ll_fmp])

    voxels = jnp.arange(N)
    n_filters = 2 * len(METHODS)
    log_uniform = jnp.full((n_filters, N), -math.log(N), dtype)

    def step(log_bel, inp):
        t, p, d_ref, d_dec, r = inp
        if cyclic:
            pred = jnp.roll(log_bel, 1, axis=-1)
            support = jnp.ones((N,), bool)
        else:  # the mass pushed beyond the last voxel is impossible
            pred = jnp.concatenate([jnp.full((n_filters, 1), -jnp.inf, dtype), log_bel[:, :-1]], -1)
            support = voxels >= t
        pred = jnp.where(t == 0, log_uniform, pred)
        ll = log_likelihoods(d_ref, d_dec, r)
        post = pred + ll
        lse = jax.nn.logsumexp(post, axis=-1, keepdims=True)
        collapsed = ~jnp.isfinite(lse)
        # Re-initialisation after a collapse: uniform over the possible voxels, then update.
        fresh = jnp.where(support, ll, -jnp.inf)
        lse_f = jax.nn.logsumexp(fresh, axis=-1, keepdims=True)
        n_support = jnp.sum(support).astype(dtype)
        fresh = jnp.where(
            jnp.isfinite(lse_f), fresh - lse_f, jnp.where(support, -jnp.log(n_support), -jnp.inf)
        )
        post = jnp.where(collapsed, fresh, post - lse)
        return post, (jnp.exp(post[:, p]), collapsed[:, 0])

    inputs = (jnp.arange(steps), pos, delta_ref, delta_dec, r_loc)
    _, (bel_true, collapsed) = lax.scan(step, log_uniform, inputs)
    shape_out = (len(MODELS), len(METHODS))
    return {
        "rho": jnp.mean(bel_true, axis=0).reshape(shape_out),
        "resets": jnp.sum(collapsed, axis=0).reshape(shape_out),
        "fallback": jnp.stack([~ok_ref, ~ok_dec]),
        "alpha": jnp.stack([a_c, g_a]),
        "beta": jnp.stack([b_c, g_b]),
        "hit_fraction": jnp.stack([jnp.mean(hits_ref), jnp.mean(hits_dec)]) / n,
    }


@functools.partial(
    jax.jit,
    static_argnames=("runs", "chunk", "n_voxels", "steps", "length_m", "shape", "rate", "cyclic"),
)
def simulate(key, n, *, runs, chunk, **static):
    """All runs for one ``n`` (traced int): ``vmap`` over a chunk of runs, ``lax.map`` over
    chunks. Run ``i`` uses the key ``fold_in(key, i)``."""
    n_chunks = -(-runs // chunk)
    ids = jnp.arange(n_chunks * chunk).reshape(n_chunks, chunk)
    one = functools.partial(_one_run, n=n, **static)
    out = lax.map(lambda c: jax.vmap(lambda i: one(jax.random.fold_in(key, i)))(c), ids)
    return jax.tree.map(lambda x: x.reshape(n_chunks * chunk, *x.shape[2:])[:runs], out)


# --------------------------------------------------------------------------------------
# Statistics
# --------------------------------------------------------------------------------------


def _t_sf_jax(t: np.ndarray, df: float) -> np.ndarray:
    """One-tailed ``P(T_df >= t)`` via the regularised incomplete beta function (float64)."""
    with jax.enable_x64(True):
        t64 = jnp.asarray(t, jnp.float64)
        x = df / (df + t64 * t64)
        tail = 0.5 * betainc(jnp.float64(df / 2), jnp.float64(0.5), x)
        p = jnp.where(t64 > 0, tail, 1.0 - tail)
        return np.asarray(p, np.float64)


def t_sf(t: np.ndarray, df: float, backend: str) -> tuple[np.ndarray, str]:
    """Survival function of Student's t; returns ``(p, backend used)``."""
    t = np.asarray(t, np.float64)
    if backend in ("auto", "scipy"):
        try:
            from scipy.stats import t as student_t
        except ImportError:
            if backend == "scipy":
                raise
        else:
            return np.asarray(student_t.sf(t, df), np.float64), "scipy.stats.t.sf"
    return _t_sf_jax(t, df), "jax.scipy.special.betainc"


def paired_t(a: np.ndarray, b: np.ndarray) -> float:
    """Paired-sample t statistic of ``a - b`` (H1: mean(a - b) > 0)."""
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    mean, sd = d.mean(), d.std(ddof=1)
    if sd == 0:
        return math.copysign(math.inf, mean) if mean != 0 else math.nan
    return float(mean / (sd / math.sqrt(d.size)))


def _num(x) -> float | None:
    """JSON-safe float: NaN and +-inf become None."""
    x = float(x)
    return x if math.isfinite(x) else None


def _fmt_p(p) -> str:
    if p is None:
        return "n/a (identical)"
    return f"{p:.1e}" if p >= 1e-300 else "<1e-300"


# --------------------------------------------------------------------------------------
# Entry point
# --------------------------------------------------------------------------------------


def _validate(cfg: DictConfig) -> None:
    """Types, ranges and choices of the config (``experiments/_schemas.py``); raises a
    ``ValueError`` naming every bad key and value."""
    validate(cfg, "posterior_corridor")


def _plot(results: dict, error_bar: str, path: Path) -> None:
    fig = Figure(figsize=(10, 4.2))
    ns = np.array([row["n"] for row in results["rows"]], float)
    offsets = {"MLM": 0.94, "FMP_uniform": 1.0, "FMP_conjugate": 1.06}
    titles = {"reflection": "(a) Reflection model", "decay_rate": "(b) Decay-rate model"}
    for k, model in enumerate(MODELS):
        ax = fig.add_subplot(1, 2, k + 1)
        for method in METHODS:
            stats = [row["rho"][model][method] for row in results["rows"]]
            mean = np.array([s["mean"] for s in stats])
            err = np.array([s[error_bar] for s in stats])
            ax.errorbar(
                ns * offsets[method],
                mean,
                yerr=err,
                marker="o",
                ms=4,
                capsize=3,
                label=LABELS[method],
            )
        ax.set_xscale("log")
        ax.set_xlabel("n (observations per voxel while mapping)")
        ax.set_ylabel(r"$\rho$")
        ax.set_title(titles[model])
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="lower right")
    fig.suptitle(
        f"Localization accuracy in a simulated corridor ({results['runs']} runs per n, "
        f"{results['boundary']}); error bars: {error_bar} over runs"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def _markdown(results: dict) -> str:
    lines = [
        f"# Section 8.5.1 corridor simulation ({results['runs']} runs per n, "
        f"N = {results['n_voxels']}, {results['steps']} steps, {results['boundary']} corridor)",
        "",
        "rho = mean over runs of the belief at the true voxel averaged over the iterations, "
        "± standard deviation over runs (variance in results.json). p: one-tailed paired "
        f"t-test ({results['p_value_backend']}). Runtime {results['runtime_s']:.1f} s.",
    ]
    for model in MODELS:
        lines += [
            "",
            f"## {model}",
            "",
            "| n | MLM | FMP uniform | FMP conjugate | p(conj > MLM) | p(conj > unif) "
            "| MLM resets/run | conj. fallback |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for row in results["rows"]:
            r = row["rho"][model]
            p = row["p_value"][model]
            cells = [f"{r[m]['mean']:.4f} ± {r[m]['std']:.4f}" for m in METHODS]
            lines.append(
                f"| {row['n']} | "
                + " | ".join(cells)
                + f" | {_fmt_p(p['FMP_conjugate>MLM'])} | {_fmt_p(p['FMP_conjugate>FMP_uniform'])}"
                + f" | {row['resets_per_run'][model]['MLM']:.2f}"
                + f" | {100 * row['conjugate_prior'][model]['fallback_fraction']:.0f} % |"
            )
        claim = results["claims"][model]
        lines += [
            "",
            f"FMP-conjugate beats both others with p < {results['significance_level']:g} for "
            f"n in {claim['n_significant_vs_both']} (paper: {claim['paper']}).",
        ]
    return "\n".join(lines) + "\n"


@hydra.main(config_path="../configs", config_name="posterior_corridor", version_base=None)
def main(cfg: DictConfig) -> dict:
    _validate(cfg)
    out = output_dir()
    if (done := completed_job(out)) is not None:  # a sweep job that already finished
        return done
    t_start = time.perf_counter()
    root = jax.random.key(int(cfg.seed))
    runs = int(cfg.runs)
    static = dict(
        n_voxels=int(cfg.n_voxels),
        steps=int(cfg.steps),
        length_m=float(cfg.voxel_length_m),
        shape=float(cfg.decay_rate_map.shape),
        rate=float(cfg.decay_rate_map.rate),
        cyclic=cfg.boundary == "cyclic",
    )
    chunk = min(int(cfg.chunk_size), runs)
    rows, backend, times = [], None, []
    for n in tqdm(list(cfg.n_values), desc="n values", unit="n"):
        t0 = time.perf_counter()
        key = jax.random.fold_in(root, int(n))
        res = simulate(key, jnp.int32(n), runs=runs, chunk=chunk, **static)
        res = jax.tree.map(np.asarray, jax.block_until_ready(res))
        times.append(time.perf_counter() - t0)
        rho = res["rho"].astype(np.float64)  # [runs 2 3]
        row = {
            "n": int(n),
            "rho": {},
            "t_statistic": {},
            "p_value": {},
            "resets_per_run": {},
            "conjugate_prior": {},
            "hit_fraction": {},
        }
        for i, model in enumerate(MODELS):
            row["rho"][model] = {
                m: {
                    "mean": float(rho[:, i, j].mean()),
                    "variance": float(rho[:, i, j].var(ddof=1)),
                    "std": float(rho[:, i, j].std(ddof=1)),
                    "sem": float(rho[:, i, j].std(ddof=1) / math.sqrt(runs)),
                }
                for j, m in enumerate(METHODS)
            }
            ts = np.array(
                [
                    paired_t(rho[:, i, METHODS.index(a)], rho[:, i, METHODS.index(b)])
                    for a, b in COMPARISONS
                ]
            )
            ps, backend = t_sf(ts, runs - 1, str(cfg.p_value_backend))
            names = [f"{a}>{b}" for a, b in COMPARISONS]
            row["t_statistic"][model] = {k: _num(t) for k, t in zip(names, ts)}
            row["p_value"][model] = {k: _num(p) for k, p in zip(names, ps)}
            row["resets_per_run"][model] = {
                m: float(res["resets"][:, i, j].mean()) for j, m in enumerate(METHODS)
            }
            row["conjugate_prior"][model] = {
                "fallback_fraction": float(res["fallback"][:, i].mean()),
                "alpha_median": float(np.median(res["alpha"][:, i])),
                "beta_median": float(np.median(res["beta"][:, i])),
            }
            row["hit_fraction"][model] = float(res["hit_fraction"][:, i].mean())
        rows.append(row)
    runtime = time.perf_counter() - t_start

    level = float(cfg.significance_level)
    claims = {}
    for model in MODELS:
        sig = [
            row["n"]
            for row in rows
            if all(
                (p := row["p_value"][model][k]) is not None and p < level
                for k in ("FMP_conjugate>MLM", "FMP_conjugate>FMP_uniform")
            )
        ]
        claims[model] = {"n_significant_vs_both": sig, "paper": PAPER_SIGNIFICANT[model]}

    results = {
        "experiment": "posterior_corridor (dissertation section 8.5.1, Figure 8.2)",
        "seed": int(cfg.seed),
        "n_voxels": static["n_voxels"],
        "steps": static["steps"],
        "runs": runs,
        "n_values": [int(n) for n in cfg.n_values],
        "voxel_length_m": static["length_m"],
        "decay_rate_map": {"shape": static["shape"], "rate": static["rate"]},
        "boundary": str(cfg.boundary),
        "conjugate_fallback": str(cfg.conjugate_fallback),
        "error_bar": str(cfg.error_bar),
        "significance_level": level,
        "models": list(MODELS),
        "methods": list(METHODS),
        "comparisons": [f"{a}>{b}" for a, b in COMPARISONS],
        "p_value_backend": backend,
        "rows": rows,
        "claims": claims,
        "runtime_s": runtime,
        "runtime_per_n_s": dict(zip([str(int(n)) for n in cfg.n_values], times)),
        "jax_backend": jax.default_backend(),
        "dtype": str(jnp.result_type(float)),
    }
    _plot(results, str(cfg.error_bar), out / "figure_8_2.png")
    md = _markdown(results)
    write_results(out, results=results, markdown=md, cfg=cfg, allow_nan=False)
    print(md)
    print(f"wrote {out / 'figure_8_2.png'}, {out / 'results.json'}, {out / 'results.md'}")
    return results


if __name__ == "__main__":
    main()
