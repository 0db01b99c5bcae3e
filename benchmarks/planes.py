"""Plane extraction (dissertation ch. 11): seconds per organized scan of PPE, fast against the
straightforward reference, and the MSAC / PEAC-style baselines.

Data (float64): generated SynPEB-style scans (``synpeb_scan("train", 0, shape=...)``,
20 mm radial noise) at 100 x 100 and 500 x 500 rays, square crops of the 100 x 100 scan for
the reference, and the shared real crop ``synpeb/test_100.pcd``.

PPE parameters: ``max_increment`` 0.01 m² (25 σ² at 20 mm; the crop uses 25 σ̂² with its
own :func:`estimate_noise`), ``max_distance_m`` 0.1.

Measured (seconds per scan, median of ``--repeats`` warm calls unless noted):

- ``ppe_greedy``: :func:`extract_planes` with ``refit=False``: the clustering alone
  (tetromino scoring in JAX + the heap-driven greedy loop).
- ``ppe``: :func:`extract_planes` with the exact ray-path refit of every plane
  (:func:`fit_planes`, vmapped Gauss–Newton); compilation excluded (one warm-up call).
- ``reference``: :func:`extract_planes_reference` (every action re-scored from scratch each
  step) on 12 x 12 … 28 x 28 crops, where it is feasible. Its time grows as ``K^b``; the
  power law fitted to these sizes extrapolates it to 100 x 100 and 500 x 500 (marked
  *extrapolated*). The fast PPE is timed on the same crops and must give the same labels.
- ``msac`` / ``peac``: :func:`msac_planes` / :func:`peac_planes` with their defaults.

Speed-ups: reference / fast on the same crops (measured) and at the large sizes
(extrapolated); the paper's 1.6 h for a 500 x 500 scan on one Xeon core (MATLAB) / ours.
Also rays/s and greedy steps/s. The issue's goal: <= 60 s per 500 x 500 scan on 2 cores.

Writes ``--out`` (default ``benchmarks/results/planes.json``) and a Markdown table beside it.
``--quick``: 100 x 100 only, small crops, 1 repeat (for smoke tests).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from _harness import machine_info, time_calls, write_json  # noqa: E402

from lidarjax.datasets import fetch, load_synpeb_pcd  # noqa: E402
from lidarjax.features import (  # noqa: E402
    estimate_noise,
    extract_planes,
    msac_planes,
    peac_planes,
)
from lidarjax.features._ppe_reference import extract_planes_reference  # noqa: E402
from lidarjax.sim import synpeb_scan  # noqa: E402

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "planes.json"
PAPER_PPE_S = 1.6 * 3600  # 500 x 500, one 2.6 GHz Xeon core, MATLAB (section 11.5)
PAPER_MSAC_S = 1.1
E = 0.01
D = 0.1


def bench_scan(points: np.ndarray, e: float, repeats: int, big: bool) -> dict:
    K = int(points.shape[0] * points.shape[1])
    extract_planes(points, max_increment=e, max_distance_m=D)  # warm-up (compilation)
    greedy, seg = time_calls(
        lambda: extract_planes(points, max_increment=e, max_distance_m=D, refit=False),
        repeats,
        warmup=0,
        return_output=True,
    )
    full, seg_full = time_calls(
        lambda: extract_planes(points, max_increment=e, max_distance_m=D),
        repeats,
        warmup=0,
        return_output=True,
    )
    t_greedy, t_full = greedy["median_s"], full["median_s"]
    t_msac = time_calls(lambda: msac_planes(points), 1 if big else repeats, warmup=0)["median_s"]
    t_peac = time_calls(lambda: peac_planes(points), repeats, warmup=0)["median_s"]
    steps = int(seg.step_costs.size)
    return dict(
        shape=list(points.shape[:2]),
        rays=K,
        steps=steps,
        planes=seg_full.n_planes,
        ppe_greedy_s=t_greedy,
        ppe_s=t_full,
        refit_s=t_full - t_greedy,
        rays_per_s=K / t_full,
        steps_per_s=steps / t_greedy,
        us_per_step=1e6 * t_greedy / steps,
        msac_s=t_msac,
        peac_s=t_peac,
    )


def bench_reference(points: np.ndarray, sizes: list[int], repeats: int) -> dict:
    rows = []
    for n in sizes:
        sub = points[:n, :n]
        extract_planes(sub, max_increment=E, max_distance_m=D, refit=False)
        t_fast, fast = time_calls(
            lambda: extract_planes(sub, max_increment=E, max_distance_m=D, refit=False),
            repeats,
            warmup=0,
            return_output=True,
        )
        t_ref, ref = time_calls(
            lambda: extract_planes_reference(sub, max_increment=E, max_distance_m=D),
            1,
            warmup=0,
            return_output=True,
        )
        t_fast, t_ref = t_fast["median_s"], t_ref["median_s"]
        same = bool(np.array_equal(fast.labels, ref.labels))
        rows.append(
            dict(
                size=n,
                rays=n * n,
                fast_s=t_fast,
                reference_s=t_ref,
                speedup=t_ref / t_fast,
                same_labels=same,
            )
        )
    K = np.array([r["rays"] for r in rows], float)
    t = np.array([r["reference_s"] for r in rows])
    b, log_a = np.polyfit(np.log(K), np.log(t), 1)
    return dict(crops=rows, power_law={"a": float(np.exp(log_a)), "b": float(b)})


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    repeats = 1 if args.quick else args.repeats
    shapes = [(100, 100)] if args.quick else [(100, 100), (500, 500)]
    ref_sizes = [10, 14] if args.quick else [12, 16, 20, 24, 28]

    results: dict = {
        "machine": machine_info(),
        "settings": dict(max_increment=E, max_distance_m=D, repeats=repeats),
    }
    scans = {}
    for shape in shapes:
        scan = synpeb_scan("train", 0, shape=shape)
        scans[f"{shape[0]}x{shape[1]}"] = bench_scan(
            scan.points, E, 1 if shape[0] > 200 else repeats, shape[0] > 200
        )
    crop, _ = load_synpeb_pcd(fetch("synpeb-test-100"))
    e_crop = 25 * estimate_noise(crop) ** 2
    scans["crop_test_100"] = bench_scan(crop, e_crop, repeats, False)
    scans["crop_test_100"]["max_increment"] = e_crop
    results["scans"] = scans

    small = synpeb_scan("train", 0, shape=(100, 100)).points
    ref = bench_reference(small, ref_sizes, repeats)
    a, b = ref["power_law"]["a"], ref["power_law"]["b"]
    for name, s in scans.items():
        s["reference_extrapolated_s"] = a * s["rays"] ** b
        s["speedup_extrapolated"] = s["reference_extrapolated_s"] / s["ppe_s"]
    results["reference"] = ref
    if "500x500" in scans:
        s = scans["500x500"]
        results["paper"] = dict(
            ppe_s=PAPER_PPE_S, msac_s=PAPER_MSAC_S, ppe_ratio=PAPER_PPE_S / s["ppe_s"]
        )
        results["goal_60s_met"] = bool(s["ppe_s"] <= 60.0)
    write_json(args.out, results)
    md = markdown(results)
    args.out.with_suffix(".md").write_text(md)
    print(md)


def markdown(results: dict) -> str:
    m = results["machine"]
    st = results["settings"]
    lines = [
        f"Plane extraction, seconds per scan ({m['cpu_count']} CPU cores, "
        f"{m.get('cpu_model', '')}), e = {st['max_increment']} m², d = {st['max_distance_m']} m",
        "",
        "| scan | rays | steps | PPE greedy | PPE + exact refit | µs/step | rays/s "
        "| reference (extrapolated) | speed-up | MSAC | PEAC |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, s in results["scans"].items():
        lines.append(
            f"| {name} | {s['rays']} | {s['steps']} | {s['ppe_greedy_s']:.2f} | {s['ppe_s']:.2f} "
            f"| {s['us_per_step']:.0f} | {s['rays_per_s']:.0f} "
            f"| {s['reference_extrapolated_s']:.3g} "
            f"| {s['speedup_extrapolated']:.0f}x | {s['msac_s']:.2f} | {s['peac_s']:.2f} |"
        )
    lines += ["", "Reference vs fast on crops of the 100 x 100 scan (measured, same run):", ""]
    lines += [
        "| crop | rays | reference s | fast s | speed-up | same labels |",
        "|---|---|---|---|---|---|",
    ]
    for r in results["reference"]["crops"]:
        lines.append(
            f"| {r['size']}x{r['size']} | {r['rays']} | {r['reference_s']:.2f} | {r['fast_s']:.3f} "
            f"| {r['speedup']:.0f}x | {r['same_labels']} |"
        )
    pl = results["reference"]["power_law"]
    lines += ["", f"Reference time ≈ {pl['a']:.3g} · K^{pl['b']:.2f} s (fit over the crops)."]
    if "paper" in results:
        p = results["paper"]
        lines.append(
            f"Paper: PPE 1.6 h per 500 x 500 scan (one core, MATLAB): "
            f"{p['ppe_ratio']:.0f}x slower than ours."
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
