"""DCT maps (ch. 9): fit times, likelihood throughput and pose gradients on the Intel log.

Data: all scans of the Intel Research Lab CARMEN log at their SLAM-corrected poses, rays with
``r_min`` 0 and ``r_max`` = the log's usable range. The 10 m x 10 m patch (corner on the 1 m
lattice) holding the most HIT end points is found with a 1 m 2-D histogram and a sliding
10 x 10 window sum; the rays are the HIT rays ending inside it. A seeded
``numpy.random.Generator`` draws 10^4 of them; the 500-ray set is the first 500 of that draw
and the 2,000 likelihood rays its first 2,000.

Measured:

1. :func:`lidarjax.maps.fit_dct` (default solver: L-BFGS, the paper's ``rtol`` 1e-3) at
   40 x 40 with 500 and 10^4 rays and at 10, 13, 20, 29 coefficients per axis with 500
   rays: compile + first call, then the median of 3 warm calls of the whole ``fit_dct``
   (precomputation of the ray weights, grid initialisation and the solve), solver steps,
   the log-likelihood of the fit, of its initial map and of the maximum-likelihood
   decay-rate grid map (Eq. 7.10, ``unknown_rate`` 0 like the DCT model outside its box)
   with the same number of cells, and the time to build that grid map. The dissertation's
   MATLAB times (i7-2600K, 500 rays) and the issue's goals are included with ratios.
2. Rays/s of :func:`lidarjax.maps.dct_log_likelihood` (``jax.jit``-ed, warm, median) for
   ``method`` = ``"paper"`` (Eq. 9.10, ``O(I^2)`` per ray; 10 and 20 coefficients per axis,
   few rays), ``"spectral"`` and ``"quadrature"`` on the fitted 500-ray maps, plus the
   largest differences between the methods on the same rays. A plain NumPy Eq. (9.10)
   (written here, vectorised over the coefficient pairs of one ray, Python loop over rays)
   is timed at 10 x 10 and compared with the JAX paper path.
3. Seconds per ``jax.value_and_grad`` (jit-ed) of the summed log-likelihood of one 180-beam
   scan w.r.t. the pose ``(x, y, theta)`` at 40 x 40 (spectral and quadrature). The scan is
   the one with the most HIT end points in the patch; HIT rays ending outside the box (whose
   likelihood under a DCT map is 0) are masked out of the sum but still evaluated.

float64 (``jax_enable_x64``) unless ``--float32``. The machine is a shared 2-core box:
other processes may have been running, so the timings are noisy.

Run with ``python benchmarks/dct.py [--quick] [--out PATH] [--float32]``. Results go to
``--out`` (default ``benchmarks/results/dct.json``; write quick runs elsewhere) and a
Markdown summary is printed.
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import sys
import time
from pathlib import Path

import jax

if "--float32" not in sys.argv:  # must happen before any array is created
    jax.config.update("jax_enable_x64", True)

import equinox as eqx
import jax.numpy as jnp
import jaxlie
import numpy as np
import optimistix as optx
from _harness import machine_info, max_abs_diff, time_calls, write_json

from lidarjax import maps
from lidarjax.datasets import fetch, load_carmen
from lidarjax.rays import HIT, RayBatch, from_scan
from lidarjax.raytrace import GridSpec, accumulate
from lidarjax.sensor_models import decay_rate_log_likelihood

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "dct.json"

PATCH_M = 10.0
SEED = 0
# Dissertation, Table 9.x: MATLAB fit times (s) with 500 rays on an i7-2600K.
PAPER_FIT_S = {10: 3.52, 13: 4.69, 20: 3.70, 29: 18.25, 40: 39.84}
GOALS_S = {"40x40_500_rays": 1.0, "40x40_10000_rays": 15.0}
# Elements of the [K I I] Eq. (9.10) tensor per vmap chunk of the paper path (memory bound).
PAPER_CHUNK_ELEMENTS = 4_000_000


# ------------------------------------------------------------------ helpers


def _take(rays: RayBatch, idx) -> RayBatch:
    idx = np.asarray(idx)
    return RayBatch(
        origins=rays.origins[idx],
        directions=rays.directions[idx],
        ranges=rays.ranges[idx],
        kind=rays.kind[idx],
        r_min=rays.r_min,
        r_max=rays.r_max,
    )


def densest_patch(ends: np.ndarray, size_m: float) -> tuple[np.ndarray, int]:
    """Lower corner (on the 1 m lattice) of the ``size_m`` square window with the most end
    points: 1 m histogram, then the window sums from a 2-D cumulative sum."""
    w = int(round(size_m))
    lo = np.floor(ends.min(axis=0))
    hi = np.ceil(ends.max(axis=0)) + 1.0
    nx, ny = int(hi[0] - lo[0]), int(hi[1] - lo[1])
    hist, _, _ = np.histogram2d(
        ends[:, 0], ends[:, 1], bins=(nx, ny), range=((lo[0], hi[0]), (lo[1], hi[1]))
    )
    c = np.zeros((nx + 1, ny + 1))
    c[1:, 1:] = hist.cumsum(0).cumsum(1)
    win = c[w:, w:] - c[:-w, w:] - c[w:, :-w] + c[:-w, :-w]  # [nx-w+1, ny-w+1]
    i, j = np.unravel_index(int(np.argmax(win)), win.shape)
    return lo + np.array([i, j], float), int(win[i, j])


# ------------------------------------------------------------------ NumPy Eq. (9.10)


class NumpyPaper:
    """Log-likelihood of HIT rays under a DCT map with Eq. (9.10) as printed: a double sum
    over all coefficient pairs ``(i, j)`` and sign combinations ``alpha`` (2^d) and ``beta``
    (2^(d-1)), ``S = 1/8 sum a_i a_j A(i, j, alpha, beta)`` with
    ``A = [sin(theta_0 + omega t)]_0^r / omega`` (``r cos(theta_0)`` for ``omega = 0``), and
    ``log p = log f(end)^2 - S``. 2-D only; written independently of ``lidarjax``."""

    def __init__(self, coeffs, lower, extent):
        self.a = np.asarray(coeffs, np.float64)
        self.lower = np.asarray(lower, np.float64)
        self.extent = np.asarray(extent, np.float64)
        L, M = self.a.shape
        self.n = np.array([(i, j) for i in range(L) for j in range(M)], float)  # [I 2]
        fr = []
        for alpha in itertools.product((1.0, -1.0), repeat=2):
            pair = self.n[:, None, :] + np.asarray(alpha) * self.n[None, :, :]  # [I I 2]
            for beta in ((1.0, 1.0), (1.0, -1.0)):
                fr.append(np.asarray(beta) * pair)
        self.freqs = np.stack(fr)  # [8 I I 2]
        self.flat = self.a.ravel()

    def depth(self, o, d, r) -> float:
        lo, hi = self.lower, self.lower + self.extent
        t0, t1 = 0.0, float(r)
        for k in range(2):
            if d[k] != 0.0:
                ta, tb = (lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]
                t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
            elif not (lo[k] <= o[k] <= hi[k]):
                return 0.0
        if t1 <= t0:
            return 0.0
        ell = t1 - t0
        st = np.pi * (o + t0 * d - lo) / self.extent
        vt = np.pi * d / self.extent
        om = self.freqs @ vt  # [8 I I]
        th = self.freqs @ st
        zero = om == 0.0
        A = np.where(
            zero,
            ell * np.cos(th),
            (np.sin(th + om * ell) - np.sin(th)) / np.where(zero, 1.0, om),
        )
        return float(np.einsum("i,kij,j->", self.flat, A, self.flat) / A.shape[0])

    def log_likelihood_hit(self, o, d, r) -> float:
        end = o + r * d
        if np.any(end < self.lower) or np.any(end > self.lower + self.extent):
            return -math.inf
        xt = np.pi * (end - self.lower) / self.extent
        f = self.flat @ (np.cos(self.n[:, 0] * xt[0]) * np.cos(self.n[:, 1] * xt[1]))
        lam = f * f
        return (math.log(lam) if lam > 0 else -math.inf) - self.depth(o, d, r)


# ------------------------------------------------------------------ benchmark parts


def bench_fit(rays, lower, L, repeats, note=""):
    extent = (PATCH_M, PATCH_M)

    def fit():
        m, sol = maps.fit_dct(rays, (L, L), lower=lower, extent=extent)
        return m, sol

    t, (m, sol) = time_calls(fit, repeats, return_output=True)
    first, med, times = t["first_call_s"], t["median_s"], t["times_s"]
    ll = float(jnp.sum(maps.dct_log_likelihood(m, rays)))
    init = maps.dct_grid_initial_map(rays, lower, extent, (L, L))
    ll_init = float(jnp.sum(maps.dct_log_likelihood(init, rays)))

    spec = GridSpec(np.asarray(lower, float), PATCH_M / L, (L, L))

    def grid():
        return maps.decay_rate_map(accumulate(spec, rays), unknown_rate=0.0)

    tg, gm = time_calls(grid, max(repeats, 5), return_output=True)
    g_first, g_med = tg["first_call_s"], tg["median_s"]
    ll_grid = float(jnp.sum(decay_rate_log_likelihood(gm, rays)))
    steps = int(sol.stats["num_steps"])
    ok = bool(sol.result == optx.RESULTS.successful)
    out = {
        "L": L,
        "n_rays": int(rays.n),
        "n_parameters": L * L,
        "first_call_s": first,
        "median_s": med,
        "warm_times_s": times,
        "num_steps": steps,
        "solver_successful": ok,
        "log_likelihood": ll,
        "log_likelihood_per_ray": ll / rays.n,
        "init_log_likelihood": ll_init,
        "grid_log_likelihood": ll_grid,
        "grid_log_likelihood_per_ray": ll_grid / rays.n,
        "dct_minus_grid_log_likelihood": ll - ll_grid,
        "grid_first_call_s": g_first,
        "grid_median_s": g_med,
        "grid_resolution_m": PATCH_M / L,
    }
    print(
        f"fit {L}x{L} {rays.n} rays{note}: first {first:.2f} s, warm {med:.3f} s, "
        f"{steps} steps{'' if ok else ' (solver not successful)'}, ll {ll:.2f} "
        f"(init {ll_init:.2f}, grid {ll_grid:.2f}, grid map {g_med * 1e3:.1f} ms)",
        flush=True,
    )
    return out, m


def _ll_fn(method, chunk_size, n_nodes):
    @eqx.filter_jit
    def f(m, rays):
        return maps.dct_log_likelihood(
            m, rays, method=method, chunk_size=chunk_size, n_nodes=n_nodes
        )

    return f


def bench_likelihood(m, rays_eval, rays_paper, methods, repeats, paper_repeats):
    n_par = m.n_parameters
    res, vals = {}, {}
    for meth in methods:
        rays = rays_paper if meth == "paper" else rays_eval
        if meth == "paper":
            chunk = max(1, PAPER_CHUNK_ELEMENTS // (8 * n_par * n_par))
            reps = paper_repeats
        else:
            chunk = 1024
            reps = repeats
        n_nodes = maps.dct_quadrature_nodes(m) if meth == "quadrature" else None
        f = _ll_fn(meth, chunk, n_nodes)
        t, out = time_calls(lambda f=f, rays=rays: f(m, rays), reps, return_output=True)
        first, med = t["first_call_s"], t["median_s"]
        vals[meth] = np.asarray(out, np.float64)
        res[meth] = {
            "n_rays": int(rays.n),
            "chunk_size": chunk,
            "n_nodes": n_nodes,
            "first_call_s": first,
            "median_s": med,
            "repeats": reps,
            "rays_per_s": rays.n / med,
            "n_nonfinite": int((~np.isfinite(vals[meth])).sum()),
        }
        print(
            f"  ll {meth:10s} L={m.shape[0]:2d}: {rays.n / med:.4g} rays/s "
            f"({rays.n} rays, first call {first:.2f} s)",
            flush=True,
        )
    n_p = rays_paper.n
    diffs = {}
    if "quadrature" in vals and "spectral" in vals:
        diffs["quadrature_vs_spectral"] = max_abs_diff(vals["quadrature"], vals["spectral"])
    if "paper" in vals:
        for other in ("spectral", "quadrature"):
            if other in vals:
                diffs[f"paper_vs_{other}"] = max_abs_diff(vals["paper"], vals[other][:n_p])
        res["spectral_over_paper_rate"] = res["spectral"]["rays_per_s"] / res["paper"]["rays_per_s"]
    res["differences"] = diffs
    for k, v in diffs.items():
        print(f"  {k}: max abs diff {v['max_abs_diff']:.2e}", flush=True)
    return res, vals


def bench_numpy(m, rays_paper, n_numpy, paper_vals):
    ref = NumpyPaper(m.coeffs, m.lower, m.extent)
    o = np.asarray(rays_paper.origins, np.float64)[:n_numpy]
    d = np.asarray(rays_paper.directions, np.float64)[:n_numpy]
    r = np.asarray(rays_paper.ranges, np.float64)[:n_numpy]
    ref.log_likelihood_hit(o[0], d[0], r[0])  # warm caches
    vals = np.empty(n_numpy)
    t0 = time.perf_counter()
    for k in range(n_numpy):
        vals[k] = ref.log_likelihood_hit(o[k], d[k], r[k])
    dt = time.perf_counter() - t0
    out = {
        "L": m.shape[0],
        "n_rays": n_numpy,
        "seconds": dt,
        "rays_per_s": n_numpy / dt,
        "vs_jax_paper": max_abs_diff(vals, paper_vals[:n_numpy]),
    }
    print(
        f"  numpy Eq. 9.10 L={m.shape[0]}: {n_numpy / dt:.4g} rays/s, max abs diff to JAX "
        f"paper {out['vs_jax_paper']['max_abs_diff']:.2e}",
        flush=True,
    )
    return out


def bench_pose_grad(m, pose, az, ranges, r_max, mask, methods, repeats):
    az_j = jnp.asarray(az, jnp.result_type(float))
    ranges_j = jnp.asarray(ranges, az_j.dtype)
    mask_j = jnp.asarray(mask)
    pose_j = jnp.asarray(pose, az_j.dtype)
    res = {}
    for meth in methods:
        n_nodes = maps.dct_quadrature_nodes(m) if meth == "quadrature" else None

        def total(p, m, meth=meth, n_nodes=n_nodes):
            T = jaxlie.SE2.from_xy_theta(p[0], p[1], p[2])
            rays = from_scan(T, az_j, ranges_j, 0.0, r_max)
            ll = maps.dct_log_likelihood(m, rays, method=meth, n_nodes=n_nodes)
            return jnp.sum(jnp.where(mask_j, ll, 0.0))

        vg = eqx.filter_jit(jax.value_and_grad(total))
        t, (v, g) = time_calls(lambda vg=vg: vg(pose_j, m), repeats, return_output=True)
        first, med = t["first_call_s"], t["median_s"]
        res[meth] = {
            "first_call_s": first,
            "median_s": med,
            "repeats": repeats,
            "value": float(v),
            "grad": [float(x) for x in np.asarray(g)],
            "grad_finite": bool(np.all(np.isfinite(np.asarray(g)))),
        }
        print(
            f"  pose value_and_grad {meth}: {med * 1e3:.2f} ms (first {first:.2f} s), "
            f"value {float(v):.3f}",
            flush=True,
        )
    if len(methods) > 1:
        a, b = (res[k] for k in methods[:2])
        res["value_diff"] = abs(a["value"] - b["value"])
        res["grad_diff"] = max_abs_diff(np.asarray(a["grad"]), np.asarray(b["grad"]))
        res["grad_max_abs_diff"] = res["grad_diff"]["max_abs_diff"]
    return res


# ------------------------------------------------------------------ main


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke run, < 2 min)")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--float32", action="store_true", help="do not enable jax_enable_x64")
    args = ap.parse_args(argv)
    quick = args.quick
    wall0 = time.perf_counter()
    dtype = jnp.result_type(float)
    if not args.float32 and dtype != jnp.float64:
        raise RuntimeError("jax_enable_x64 was not applied (set it before creating arrays)")

    if quick:
        n_small, n_large, L_big = 200, 1000, 10
        fit_Ls = []
        eval_Ls, paper_Ls = [10], [10]
        n_eval, n_paper, n_numpy = 300, 20, 10
        fit_repeats, ll_repeats, paper_repeats, grad_repeats = 1, 2, 1, 3
    else:
        n_small, n_large, L_big = 500, 10_000, 40
        fit_Ls = [10, 13, 20, 29]
        eval_Ls, paper_Ls = [10, 20, 40], [10, 20]
        n_eval, n_paper, n_numpy = 2000, 200, 200
        fit_repeats, ll_repeats, paper_repeats, grad_repeats = 3, 7, 3, 20

    machine = machine_info()
    log = load_carmen(fetch("intel"))
    r_max = float(log.usable_range_m)
    P = log.poses
    all_rays = from_scan(
        jaxlie.SE2.from_xy_theta(P[:, 0], P[:, 1], P[:, 2]),
        log.azimuths_rad,
        log.ranges_m,
        0.0,
        r_max,
    ).flatten()
    kind = np.asarray(all_rays.kind)
    ends = np.asarray(all_rays.endpoints(), np.float64)
    hit = kind == HIT
    lower, n_in_patch = densest_patch(ends[hit], PATCH_M)
    upper = lower + PATCH_M
    in_patch = hit & np.all((ends >= lower) & (ends <= upper), axis=1)
    pool = np.flatnonzero(in_patch)
    rng = np.random.default_rng(SEED)
    pick = rng.choice(pool, size=min(n_large, pool.size), replace=False)
    rays_large = _take(all_rays, pick)
    rays_small = _take(all_rays, pick[:n_small])
    rays_eval = _take(all_rays, pick[:n_eval])
    rays_paper = _take(all_rays, pick[:n_paper])
    print(
        f"patch lower {lower.tolist()} ({n_in_patch} HIT end points in the histogram window, "
        f"{pool.size} HIT rays in the closed box); {log.n_scans} scans, r_max {r_max:.2f} m, "
        f"{dtype}",
        flush=True,
    )

    # 1. fits ------------------------------------------------------------------------
    fits, fitted = {}, {}
    for L, rays in [(L_big, rays_small), (L_big, rays_large)] + [(L, rays_small) for L in fit_Ls]:
        key = f"{L}x{L}_{rays.n}"
        fits[key], m = bench_fit(rays, lower, L, fit_repeats)
        if rays is rays_small:
            fitted[L] = m
        paper = PAPER_FIT_S.get(L) if rays.n == 500 else None
        fits[key]["paper_matlab_s"] = paper
        fits[key]["speedup_vs_paper"] = paper / fits[key]["median_s"] if paper else None
        fits[key]["speedup_vs_paper_first_call"] = (
            paper / fits[key]["first_call_s"] if paper else None
        )
    goals = {}
    if not quick:
        for gk, key in (("40x40_500_rays", "40x40_500"), ("40x40_10000_rays", "40x40_10000")):
            t = fits[key]["median_s"]
            goals[gk] = {"goal_s": GOALS_S[gk], "median_s": t, "met": t <= GOALS_S[gk]}

    # 2. likelihood throughput -------------------------------------------------------
    for L in eval_Ls:
        if L not in fitted:  # e.g. --quick without a 500-ray fit at this size
            fitted[L], _ = maps.fit_dct(rays_small, (L, L), lower=lower, extent=(PATCH_M,) * 2)
    likelihood, numpy_ref = {}, None
    for L in eval_Ls:
        methods = (["paper"] if L in paper_Ls else []) + ["spectral", "quadrature"]
        likelihood[str(L)], vals = bench_likelihood(
            fitted[L], rays_eval, rays_paper, methods, ll_repeats, paper_repeats
        )
        if L == min(paper_Ls):
            numpy_ref = bench_numpy(fitted[L], rays_paper, n_numpy, vals["paper"])
            numpy_ref["spectral_over_numpy_rate"] = (
                likelihood[str(L)]["spectral"]["rays_per_s"] / numpy_ref["rays_per_s"]
            )
            numpy_ref["jax_paper_over_numpy_rate"] = (
                likelihood[str(L)]["paper"]["rays_per_s"] / numpy_ref["rays_per_s"]
            )

    # 3. pose value_and_grad ---------------------------------------------------------
    n_scans, n_beams = log.ranges_m.shape
    per_scan = in_patch.reshape(n_scans, n_beams).sum(axis=1)
    s = int(np.argmax(per_scan))
    m_big = fitted[L_big]
    scan_rays = _take(all_rays, np.arange(s * n_beams, (s + 1) * n_beams))
    mask = np.asarray(maps.rays_in_box(m_big, scan_rays))
    print(f"pose gradient: scan {s}, {int(mask.sum())} of {n_beams} rays in the box", flush=True)
    pose_grad = bench_pose_grad(
        m_big, P[s], log.azimuths_rad, log.ranges_m[s], r_max, mask,
        ["spectral", "quadrature"], grad_repeats,
    )  # fmt: skip
    pose_grad.update(
        {"L": L_big, "scan_index": s, "n_beams": int(n_beams), "n_rays_in_box": int(mask.sum())}
    )

    machine["load_average_end"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    report = {
        "machine": machine,
        "quick": quick,
        "wall_time_s": time.perf_counter() - wall0,
        "setup": {
            "log": "intel",
            "n_scans": log.n_scans,
            "r_min_m": 0.0,
            "r_max_m": r_max,
            "patch_lower_m": lower.tolist(),
            "patch_extent_m": [PATCH_M, PATCH_M],
            "patch_hits_histogram": n_in_patch,
            "patch_hit_rays": int(pool.size),
            "seed": SEED,
            "n_rays_small": int(rays_small.n),
            "n_rays_large": int(rays_large.n),
            "n_rays_likelihood": int(rays_eval.n),
            "n_rays_paper_method": int(rays_paper.n),
            "n_rays_numpy": n_numpy,
            "ray_sets_note": "nested: the small, likelihood and paper sets are prefixes of "
            "the large random draw",
            "solver": "fit_dct default: optx.LBFGS(rtol=1e-3, atol=1e-3), max_steps 1000, "
            "grid initial map (2x oversampled)",
            "fit_repeats": fit_repeats,
            "likelihood_repeats": ll_repeats,
            "paper_method_repeats": paper_repeats,
            "pose_grad_repeats": grad_repeats,
            "grid_map": "decay_rate_map(accumulate(GridSpec(lower, 10/L, (L, L)), rays), "
            "unknown_rate=0.0)",
        },
        "paper_matlab_fit_s_500_rays": {str(k): v for k, v in PAPER_FIT_S.items()},
        "paper_machine": "MATLAB, Intel i7-2600K",
        "goals": goals,
        "fits": fits,
        "likelihood": likelihood,
        "numpy_paper_reference": numpy_ref,
        "pose_value_and_grad": pose_grad,
    }
    write_json(args.out, report)
    print(markdown(report))
    print(f"wrote {args.out}")
    return report


def _f(x, fmt=".3g"):
    return "-" if x is None else format(x, fmt)


def markdown(rep: dict) -> str:
    m = rep["machine"]
    lines = [
        f"Intel patch {rep['setup']['patch_lower_m']} + 10 m, {m['jax_backend']} "
        f"({m['cpu_count']} cores, {m['cpu_model']}), {m['dtype']}, noisy shared machine",
        "",
        "| fit | rays | first call (s) | warm median (s) | steps | log-lik | grid log-lik | "
        "init log-lik | grid map (ms) | paper (s) | speed-up |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rep["fits"].values():
        lines.append(
            f"| {r['L']}x{r['L']} | {r['n_rays']} | {r['first_call_s']:.2f} | "
            f"{r['median_s']:.3f} | {r['num_steps']} | {r['log_likelihood']:.1f} | "
            f"{r['grid_log_likelihood']:.1f} | {r['init_log_likelihood']:.1f} | "
            f"{r['grid_median_s'] * 1e3:.1f} | {_f(r['paper_matlab_s'])} | "
            f"{_f(r['speedup_vs_paper'], '.1f')} |"
        )
    lines += ["", "| L | method | rays | rays/s | first call (s) |", "|---|---|---|---|---|"]
    for L, d in rep["likelihood"].items():
        for meth in ("paper", "spectral", "quadrature"):
            if meth in d:
                r = d[meth]
                lines.append(
                    f"| {L} | {meth} | {r['n_rays']} | {r['rays_per_s']:.4g} | "
                    f"{r['first_call_s']:.2f} |"
                )
    lines.append("")
    for L, d in rep["likelihood"].items():
        parts = [f"{k} {v['max_abs_diff']:.1e}" for k, v in d["differences"].items()]
        if "spectral_over_paper_rate" in d:
            parts.append(f"spectral/paper rate {d['spectral_over_paper_rate']:.0f}x")
        lines.append(f"- L={L}: " + ", ".join(parts))
    n = rep["numpy_paper_reference"]
    if n:
        lines.append(
            f"- NumPy Eq. 9.10 at L={n['L']}: {n['rays_per_s']:.4g} rays/s; spectral/numpy "
            f"{n['spectral_over_numpy_rate']:.0f}x, JAX paper/numpy "
            f"{n['jax_paper_over_numpy_rate']:.1f}x; max abs diff to JAX paper "
            f"{n['vs_jax_paper']['max_abs_diff']:.1e}"
        )
    pg = rep["pose_value_and_grad"]
    lines.append(
        f"- pose value_and_grad, L={pg['L']}, scan {pg['scan_index']} ({pg['n_beams']} beams, "
        f"{pg['n_rays_in_box']} in box): spectral {pg['spectral']['median_s'] * 1e3:.2f} ms, "
        f"quadrature {pg['quadrature']['median_s'] * 1e3:.2f} ms"
    )
    for k, g in rep["goals"].items():
        lines.append(
            f"- goal {k}: <= {g['goal_s']} s, measured {g['median_s']:.3f} s -> "
            f"{'met' if g['met'] else 'NOT met'}"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    main()
