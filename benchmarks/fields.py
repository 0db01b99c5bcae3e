"""Generic decay-rate fields: cost of the generic forward model and fit against the
specialised paths, on the Intel log.

Data: :func:`patch_rays` of ``experiments/custom_field.py`` on the Intel Research Lab CARMEN
log (HIT rays from even scans ending in the 10 m x 10 m patch with the most end points;
``r_min`` 0, ``r_max`` = the log's usable range): ``n_fit`` rays for the fits and up to
``n_ll`` rays (capped at what the patch holds) for the throughput parts.

Fields (``L_field`` cells / coefficients / centres per axis):

- grid: the maximum-likelihood grid map (Eq. 7.10, ``unknown_rate`` 0) of the throughput
  rays, so every HIT ray ends in a cell with a positive rate;
- DCT: :func:`lidarjax.maps.fit_dct` of the fit rays (default tolerances);
- RBF: the user field ``rbf_field_like(grid)`` of ``experiments/custom_field.py``
  (softplus of a Gaussian lattice, Gauss-Legendre optical depth).

Measured:

1. Forward throughput (rays/s, ``eqx.filter_jit``-ed, warm, median of ``repeats``) of the
   generic :func:`lidarjax.maps.field_log_likelihood` against the specialised function where
   one exists (grid: :func:`lidarjax.sensor_models.decay_rate_log_likelihood`, DCT:
   :func:`lidarjax.maps.dct_log_likelihood`), their ratio and largest differences.
2. Forward + gradient: ``jax.value_and_grad`` of the summed log-likelihood w.r.t.
   ``field.parameters()`` through ``field.with_parameters(p)``, rays/s, generic and (grid,
   DCT) specialised, with the largest gradient difference.
3. Fits on the ``n_fit`` rays at ``L`` in ``fit_Ls`` (first call incl. compilation, and the
   warm second call; each call includes everything the function does, e.g. the initial
   log-likelihood check of ``maps.fit`` and the weight precomputation of ``fit_dct``):

   - DCT: generic :func:`lidarjax.maps.fit` vs :func:`lidarjax.maps.fit_dct`, both from
     ``maps.dct_grid_initial_map(train, lower, [10, 10], (L, L))`` with
     ``rtol = atol = 1e-4``: seconds, steps, final summed log-likelihood (both evaluated
     with ``dct_log_likelihood``); for every generic fit also the warm time of the
     un-jitted initial ``field_log_likelihood`` check that ``maps.fit`` runs per call;
   - RBF: ``maps.fit(rbf_field_like(grid_L), train, rtol=atol=1e-4, max_steps=300)``
     (``grid_L`` the L x L ML grid of the fit rays): seconds, steps, s/step;
   - grid: the closed-form ML map (``accumulate`` + ``decay_rate_map``) vs ``maps.fit`` from
     all rates 1 (``outside_rate`` 0 like the closed form, ``rtol = atol = 1e-4``,
     ``max_steps`` 300): seconds, steps, the largest relative error of the fitted rates
     against ``H / R`` over the cells with hits, and both log-likelihoods.

float64 (``jax_enable_x64``). The machine is a shared 2-core box: other processes may have
been running, so the timings are noisy.

Run with ``python benchmarks/fields.py [--quick] [--out PATH]``. ``--quick`` is a smoke run
(L = 10 only, 200 rays, 1 repeat) written by default to the temporary directory; the full run
writes ``benchmarks/results/fields.json``. A Markdown summary is printed.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ["JAX_ENABLE_X64"] = "1"  # float64; before jax is imported

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from _harness import experiments_on_path, machine_info, max_abs_diff, time_calls, write_json

experiments_on_path()  # the user-field example of experiments/custom_field.py
from custom_field import patch_rays, rbf_field_like  # noqa: E402

from lidarjax import maps  # noqa: E402
from lidarjax.raytrace import GridSpec, accumulate  # noqa: E402
from lidarjax.sensor_models import decay_rate_log_likelihood  # noqa: E402

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "fields.json"
QUICK_OUT = Path(tempfile.gettempdir()) / "lidarjax_fields_quick.json"
PATCH_M = 10.0
TOL = 1e-4


# ------------------------------------------------------------------ helpers


def ml_grid(rays, lower, L):
    spec = GridSpec(np.asarray(lower, float), PATCH_M / L, (L, L))
    stats = accumulate(spec, rays)
    return maps.decay_rate_map(stats, unknown_rate=0.0), stats


@eqx.filter_jit
def _generic_ll(field, rays):
    return maps.field_log_likelihood(field, rays)


@eqx.filter_jit
def _grid_ll(field, rays):
    return decay_rate_log_likelihood(field, rays)


@eqx.filter_jit
def _dct_ll(field, rays):
    return maps.dct_log_likelihood(field, rays)


def _value_and_grad(ll_fn):
    @eqx.filter_jit
    def vg(params, field, rays):
        def total(p):
            return jnp.sum(ll_fn(field.with_parameters(p), rays))

        return jax.value_and_grad(total)(params)

    return vg


# ------------------------------------------------------------------ 1 + 2: throughput


def bench_throughput(fields: dict, rays, repeats: int) -> dict:
    special = {
        "grid": ("decay_rate_log_likelihood", _grid_ll),
        "dct": ("dct_log_likelihood", _dct_ll),
    }
    n = int(rays.n)
    out = {}
    for name, field in fields.items():
        res = {"n_rays": n}
        paths = [("generic", maps.field_log_likelihood)]
        if name in special:
            paths.append(("specialised", special[name][1]))
            res["specialised_function"] = special[name][0]
        vals, grads = {}, {}
        for path, fn in paths:
            jitted = _generic_ll if path == "generic" else fn
            t, v = time_calls(lambda j=jitted: j(field, rays), repeats, return_output=True)
            first, med, warm = t["first_call_s"], t["median_s"], t["times_s"]
            vals[path] = v
            vg = _value_and_grad(fn)
            p0 = field.parameters()
            tg, (val, g) = time_calls(
                lambda vg=vg: vg(p0, field, rays), repeats, return_output=True
            )
            g_first, g_med, g_warm = tg["first_call_s"], tg["median_s"], tg["times_s"]
            grads[path] = g
            res[path] = {
                "forward_first_call_s": first,
                "forward_median_s": med,
                "forward_warm_s": warm,
                "forward_rays_per_s": n / med,
                "n_nonfinite": int((~np.isfinite(np.asarray(v))).sum()),
                "sum_log_likelihood": float(jnp.sum(v)),
                "grad_first_call_s": g_first,
                "grad_median_s": g_med,
                "grad_warm_s": g_warm,
                "grad_rays_per_s": n / g_med,
                "grad_finite": bool(
                    all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(g))
                ),
                "grad_value": float(val),
            }
            print(
                f"  {name:4s} {path:11s}: forward {n / med:10.4g} rays/s, value+grad "
                f"{n / g_med:10.4g} rays/s (first calls {first:.2f} s / {g_first:.2f} s)",
                flush=True,
            )
        if "specialised" in vals:
            res["forward_generic_over_specialised_rate"] = (
                res["generic"]["forward_rays_per_s"] / res["specialised"]["forward_rays_per_s"]
            )
            res["grad_generic_over_specialised_rate"] = (
                res["generic"]["grad_rays_per_s"] / res["specialised"]["grad_rays_per_s"]
            )
            res["forward_diff"] = max_abs_diff(vals["generic"], vals["specialised"])
            res["grad_diff"] = max_abs_diff(grads["generic"], grads["specialised"])
            print(
                f"  {name:4s} generic/specialised: forward "
                f"{res['forward_generic_over_specialised_rate']:.3f}x, grad "
                f"{res['grad_generic_over_specialised_rate']:.3f}x; max |diff| forward "
                f"{res['forward_diff']['max_abs_diff']:.2e}, grad "
                f"{res['grad_diff']['max_abs_diff']:.2e}",
                flush=True,
            )
        out[name] = res
    return out


# ------------------------------------------------------------------ 3: fits


def _result_name(result) -> str:
    if result == optx.RESULTS.successful:
        return "ok"
    if result == optx.RESULTS.nonlinear_max_steps_reached:
        return "max_steps reached"
    return str(result).split("<")[-1][:60]


def _eager_check_s(field, rays) -> float:
    """Warm time of the un-jitted ``field_log_likelihood`` that ``maps.fit`` runs on its
    initial field before optimising (the finiteness check)."""
    return time_calls(lambda: maps.field_log_likelihood(field, rays), 1)["median_s"]


def _fit_record(first, warm, sol, ll) -> dict:
    steps = int(sol.stats["num_steps"])
    return {
        "first_call_s": first,
        "warm_s": warm,
        "num_steps": steps,
        "s_per_step": warm / max(steps, 1),
        "solver_result": _result_name(sol.result),
        "log_likelihood": ll,
    }


def bench_fits(train, lower, L: int, repeats: int, max_steps_slow: int) -> dict:
    extent = [PATCH_M, PATCH_M]
    n = int(train.n)
    init = maps.dct_grid_initial_map(train, lower, extent, (L, L))
    res = {"L": L, "n_rays": n, "n_parameters": L * L}

    # DCT: generic fit vs fit_dct from the same initial map
    def gen():
        return maps.fit(init, train, rtol=TOL, atol=TOL)

    def spec():
        return maps.fit_dct(train, init=init, rtol=TOL, atol=TOL)

    for key, fn in (("dct_generic", gen), ("dct_fit_dct", spec)):
        t, (m, sol) = time_calls(fn, repeats, return_output=True)
        first, med = t["first_call_s"], t["median_s"]
        ll = float(jnp.sum(_dct_ll(m, train)))
        res[key] = _fit_record(first, med, sol, ll)
    res["dct_generic"]["eager_initial_check_s"] = _eager_check_s(init, train)
    res["dct_init_log_likelihood"] = float(jnp.sum(_dct_ll(init, train)))
    res["dct_generic_over_fit_dct_time"] = (
        res["dct_generic"]["warm_s"] / res["dct_fit_dct"]["warm_s"]
    )

    # the user's RBF field from the L x L ML grid
    grid_L, stats = ml_grid(train, lower, L)
    rbf0 = rbf_field_like(grid_L)

    def rbf():
        return maps.fit(rbf0, train, rtol=TOL, atol=TOL, max_steps=max_steps_slow)

    t, (m, sol) = time_calls(rbf, repeats, return_output=True)
    first, med = t["first_call_s"], t["median_s"]
    res["rbf"] = _fit_record(first, med, sol, float(jnp.sum(_generic_ll(m, train))))
    res["rbf"]["eager_initial_check_s"] = _eager_check_s(rbf0, train)
    res["rbf"]["quadrature_nodes"] = int(rbf0.quadrature_nodes())
    res["rbf"]["max_steps"] = max_steps_slow
    res["rbf_init_log_likelihood"] = float(jnp.sum(_generic_ll(rbf0, train)))

    # grid: closed form vs generic fit from rates 1
    tg, (cf, _) = time_calls(lambda: ml_grid(train, lower, L), max(repeats, 3), return_output=True)
    g_first, g_med = tg["first_call_s"], tg["median_s"]
    ones = maps.DecayRateMap(
        spec=cf.spec, rates=jnp.ones_like(cf.rates), outside_rate=jnp.zeros_like(cf.outside_rate)
    )

    def grid_fit():
        return maps.fit(ones, train, rtol=TOL, atol=TOL, max_steps=max_steps_slow)

    t, (gm, sol) = time_calls(grid_fit, repeats, return_output=True)
    first, med = t["first_call_s"], t["median_s"]
    hits = np.asarray(stats.hits) > 0
    ref = np.asarray(cf.rates)[hits]
    rel = np.abs(np.asarray(gm.rates)[hits] - ref) / ref
    res["grid_closed_form"] = {
        "first_call_s": g_first,
        "median_s": g_med,
        "log_likelihood": float(jnp.sum(_grid_ll(cf, train))),
    }
    res["grid_generic"] = _fit_record(first, med, sol, float(jnp.sum(_grid_ll(gm, train))))
    res["grid_generic"]["max_steps"] = max_steps_slow
    res["grid_generic"]["eager_initial_check_s"] = _eager_check_s(ones, train)
    res["grid_generic"]["n_cells_with_hits"] = int(hits.sum())
    res["grid_generic"]["max_rel_rate_error"] = float(rel.max())
    res["grid_generic"]["median_rel_rate_error"] = float(np.median(rel))
    res["grid_generic_over_closed_form_time"] = med / g_med

    d, r, g = res["dct_generic"], res["dct_fit_dct"], res["grid_generic"]
    print(
        f"fits L={L} ({n} rays): DCT generic {d['warm_s']:.3f} s ({d['num_steps']} steps, "
        f"ll {d['log_likelihood']:.2f}, first {d['first_call_s']:.2f} s) vs fit_dct "
        f"{r['warm_s']:.3f} s ({r['num_steps']} steps, ll {r['log_likelihood']:.2f}, first "
        f"{r['first_call_s']:.2f} s); RBF {res['rbf']['warm_s']:.3f} s "
        f"({res['rbf']['num_steps']} steps); grid closed form {g_med * 1e3:.2f} ms vs fit "
        f"{g['warm_s']:.3f} s ({g['num_steps']} steps, max rel err "
        f"{g['max_rel_rate_error']:.1e})",
        flush=True,
    )
    return res


# ------------------------------------------------------------------ main


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tiny sizes (smoke run)")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    quick = args.quick
    out_path = args.out or (QUICK_OUT if quick else DEFAULT_OUT)
    if jnp.result_type(float) != jnp.float64:
        raise RuntimeError("jax_enable_x64 was not applied")
    wall0 = time.perf_counter()
    if quick:
        n_fit, n_ll, L_field, fit_Ls, repeats, fit_repeats = 200, 200, 10, [10], 1, 1
    else:
        n_fit, n_ll, L_field, fit_Ls, repeats, fit_repeats = 1000, 10_000, 20, [10, 20, 40], 5, 1
    max_steps_slow = 300
    machine = machine_info()

    t = time.perf_counter()
    train, _, lower = patch_rays("intel", n_fit)
    ll_rays, _, lower_ll = patch_rays("intel", n_ll)
    load_s = time.perf_counter() - t
    assert np.allclose(lower, lower_ll)
    print(
        f"intel patch lower {np.asarray(lower).tolist()}: {train.n} fit rays, {ll_rays.n} "
        f"throughput rays (loaded in {load_s:.1f} s)",
        flush=True,
    )

    # 1 + 2: throughput
    grid, _ = ml_grid(ll_rays, lower, L_field)
    dct, dct_sol = maps.fit_dct(train, (L_field, L_field), lower=lower, extent=[PATCH_M] * 2)
    rbf = rbf_field_like(grid)
    fields = {"grid": grid, "dct": dct, "rbf": rbf}
    print(f"throughput, L={L_field}, {ll_rays.n} rays:", flush=True)
    throughput = bench_throughput(fields, ll_rays, repeats)

    # 3: fits
    fits = {str(L): bench_fits(train, lower, L, fit_repeats, max_steps_slow) for L in fit_Ls}

    machine["load_average_end"] = list(os.getloadavg())
    report = {
        "machine": machine,
        "quick": quick,
        "wall_time_s": time.perf_counter() - wall0,
        "setup": {
            "log": "intel",
            "patch_lower_m": np.asarray(lower).tolist(),
            "patch_extent_m": [PATCH_M, PATCH_M],
            "rays": "experiments/custom_field.py patch_rays: HIT rays of even scans ending in "
            "the patch, r_min 0, r_max the log's usable range",
            "n_fit_rays": int(train.n),
            "n_throughput_rays": int(ll_rays.n),
            "n_throughput_rays_requested": n_ll,
            "L_field": L_field,
            "fields": {
                "grid": "decay_rate_map(accumulate(L x L grid, throughput rays), unknown_rate=0)",
                "dct": "fit_dct(fit rays, (L, L)) with default tolerances, "
                f"{int(dct_sol.stats['num_steps'])} steps",
                "rbf": f"rbf_field_like(grid), {int(rbf.quadrature_nodes())} quadrature nodes",
            },
            "throughput_repeats": repeats,
            "fit_repeats": fit_repeats,
            "fit_tolerances": TOL,
            "slow_fit_max_steps": max_steps_slow,
            "jit": "eqx.filter_jit per function; field_log_likelihood chunk_size 4096 "
            "(default), dct_log_likelihood chunk_size 1024 (default)",
        },
        "throughput": throughput,
        "fits": fits,
    }
    write_json(out_path, report)
    print(markdown(report))
    print(f"wrote {out_path} (wall time {report['wall_time_s']:.1f} s)")
    return report


def _num(x):
    return "-" if x is None else f"{x:.3g}"


def _ratio(x):
    return "-" if x is None else f"{x:.2f}"


def markdown(rep: dict) -> str:
    m, s = rep["machine"], rep["setup"]
    lines = [
        f"Intel patch {s['patch_lower_m']} + 10 m, {m['jax_backend']} ({m['cpu_count']} "
        f"cores, {m['cpu_model']}), {m['dtype']}, noisy shared machine"
        + (" — QUICK smoke run" if rep["quick"] else ""),
        "",
        f"Throughput, L = {s['L_field']}, {s['n_throughput_rays']} rays (rays/s):",
        "",
        "| field | forward generic | forward specialised | ratio | max abs diff | "
        "value+grad generic | value+grad specialised | ratio | grad max abs diff |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in rep["throughput"].items():
        g, sp = r["generic"], r.get("specialised")
        fd, gd = r.get("forward_diff"), r.get("grad_diff")
        cells = [
            name,
            f"{g['forward_rays_per_s']:.4g}",
            f"{sp['forward_rays_per_s']:.4g}" if sp else "-",
            _ratio(r.get("forward_generic_over_specialised_rate")),
            f"{fd['max_abs_diff']:.1e}" if fd else "-",
            f"{g['grad_rays_per_s']:.4g}",
            f"{sp['grad_rays_per_s']:.4g}" if sp else "-",
            _ratio(r.get("grad_generic_over_specialised_rate")),
            f"{gd['max_abs_diff']:.1e}" if gd else "-",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        f"Fits, {s['n_fit_rays']} rays, rtol = atol = {s['fit_tolerances']:g} (warm = second "
        "call; first call incl. compilation):",
        "",
        "| L | method | warm (s) | first (s) | steps | s/step | log-lik | eager check (s) | note |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    labels = {
        "dct_generic": "DCT maps.fit",
        "dct_fit_dct": "DCT fit_dct",
        "rbf": "RBF maps.fit",
        "grid_generic": "grid maps.fit",
    }
    for L, r in rep["fits"].items():
        for key, label in labels.items():
            f = r[key]
            note = "" if f["solver_result"] == "ok" else f["solver_result"]
            if key == "grid_generic":
                note = (note + " " if note else "") + (
                    f"max rel rate err {f['max_rel_rate_error']:.1e} over "
                    f"{f['n_cells_with_hits']} cells"
                )
            lines.append(
                f"| {L} | {label} | {f['warm_s']:.3f} | {f['first_call_s']:.2f} | "
                f"{f['num_steps']} | {f['s_per_step'] * 1e3:.1f} ms | "
                f"{f['log_likelihood']:.2f} | {_num(f.get('eager_initial_check_s'))} | "
                f"{note} |"
            )
        cf = r["grid_closed_form"]
        lines.append(
            f"| {L} | grid closed form | {cf['median_s']:.4f} | {cf['first_call_s']:.2f} | - | "
            f"- | {cf['log_likelihood']:.2f} | - | Eq. 7.10 |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    main()
