"""Polyline extraction from 2-D scans (dissertation ch. 10): Figure 10.4, Table 10.2 and
Figure 10.3 with PLE, PLE+ and the heuristic baselines VVL, IEF and SAM.

Real data: the scans of each CARMEN log in ``logs`` (a registered name or a path to a log
file), in the sensor frame, no-returns (readings at or beyond the log's usable range) as
SUP rays. Which scans: ``scan_indices[log]`` if given; else, with ``scans: paper`` (the
default), the 20 scans per log of the authors' evaluation (``paper_scans``), so each log's
PLE and PLE+ compare with the paper's per-log values; else (``scans: random``, or a log
without paper scans) ``scans_per_log`` scans drawn at random (seeded per log). Indices
and the selection are recorded. Simulation: as many full-revolution 360-ray scans of random
star-shaped polygons with 3, 4, 5, 6, 12, 36 or 180 vertices (cycled), angular noise 0.2 deg
and radial noise 0.03 m (section 10.5).

For every vertex budget ``J``:

- PLE (:func:`lidarjax.features.extract_polylines`, ``l_max`` 1 m, ``d_rm`` 0.5 m) and PLE+
  (:func:`lidarjax.features.optimize_polylines`), batched over the scans of a dataset;
- VVL on PLE's initial polylines, IEF and SAM on the reflected endpoints (max-range readings
  removed), each with the same ``J_max``.

Metrics (section 10.5, :mod:`lidarjax.metrics`): RMSE of the ray radii over rays that are
reflected and intersect the polylines (and, for a comparison on equal terms, over the rays
that every method's polylines intersect, as in the authors' evaluation), ``f`` = reflected
rays intersected / rays reflected, and for
simulated scans the area ratio ``a`` against the ground-truth polygon. Mean and standard
error over scans. Timing: seconds per scan, one scan per call (warm), at ``timing_J``.
Also PLE+ (Levenberg–Marquardt on Eq. 10.4) against the paper's Nelder–Mead on the true
objective for a few simulated scans.

Writes ``results.json``, ``results.md``, ``fig10_4a.png`` (real), ``fig10_4b.png``
(simulated) and ``fig10_3.png`` (all methods on one office scan) into Hydra's output folder.
E.g. ``python experiments/polylines.py logs=[intel] scans=random scans_per_log=5 J=[10,20]``,
or on a log of one's own (``scan_indices`` names it by its file name without suffixes):
``python experiments/polylines.py 'logs=[/data/my.log.gz]' '+scan_indices={my: [0, 10]}'``.

Length (~700 lines): one experiment with its three parts (CARMEN logs on the paper's
scans, simulated polygons, the Figure 10.3 example), its per-log table against the paper
and its figures; splitting it would scatter one Hydra entry point over several files.
"""

from __future__ import annotations

import json
import time
import zlib
from pathlib import Path

import hydra
import jax
import jax.numpy as jnp
import jaxlie
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from _common import completed_job, output_dir, write_results  # noqa: E402
from _schemas import log_name, validate  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402
from scipy.optimize import minimize  # noqa: E402
from tqdm import tqdm  # noqa: E402

from lidarjax import features as F  # noqa: E402
from lidarjax import metrics  # noqa: E402
from lidarjax.datasets import fetch, load_carmen  # noqa: E402
from lidarjax.plot import plot_polyline_scan  # noqa: E402
from lidarjax.rays import HIT, RayBatch, from_scan  # noqa: E402
from lidarjax.sim import random_polygon, simulate_polygon_scan  # noqa: E402

METHODS = ("VVL", "IEF", "SAM", "PLE", "PLE+")
COLORS = {"VVL": "tab:orange", "IEF": "tab:green", "SAM": "tab:purple", "PLE": "tab:blue",
          "PLE+": "tab:red"}  # fmt: skip
# Table 10.2 (MATLAB, one 2.5 GHz Xeon core): mean seconds per scan.
PAPER_SECONDS = {
    "real": {20: {"VVL": 0.056, "IEF": 0.27, "SAM": 28, "PLE": 1.4, "PLE+": 2.3},
             50: {"VVL": 0.050, "IEF": 1.12, "SAM": 27, "PLE": 1.3, "PLE+": 6.9}},
    "simulated": {20: {"VVL": 0.037, "IEF": 0.38, "SAM": 103, "PLE": 2.3, "PLE+": 11},
                  50: {"VVL": 0.037, "IEF": 1.59, "SAM": 102, "PLE": 2.2, "PLE+": 72}},
}  # fmt: skip


# The authors' published evaluation (their repository's matlab/output/eval.mat, ``rmse`` of
# PLE and PLE+ per scan, mean over each log's 20 scans): mean RMSE per log (mm) at
# J = 10, 20, 30, 40, 50, on the scans listed in ``paper_scans`` of configs/polylines.yaml.
PAPER_J = (10, 20, 30, 40, 50)
PAPER_PER_LOG_MM = {
    "acapulco": {"PLE": (115.42, 114.77, 101.23, 86.60, 63.62),
                 "PLE+": (86.10, 85.18, 75.96, 66.00, 48.24)},
    "belgioioso": {"PLE": (123.65, 74.98, 50.23, 32.29, 20.86),
                   "PLE+": (93.17, 53.87, 36.48, 23.67, 16.58)},
    "csail": {"PLE": (101.82, 82.02, 63.61, 50.78, 40.24),
              "PLE+": (74.51, 61.62, 49.92, 40.40, 32.00)},
    "edmonton": {"PLE": (125.91, 97.55, 71.64, 44.38, 27.10),
                 "PLE+": (90.57, 71.74, 53.41, 33.94, 20.16)},
    "fhw": {"PLE": (124.51, 101.14, 80.49, 59.09, 37.73),
            "PLE+": (87.67, 74.39, 61.07, 43.61, 28.95)},
    "freiburg-079": {"PLE": (135.51, 110.55, 86.37, 63.01, 44.28),
                     "PLE+": (100.39, 80.66, 61.29, 45.36, 32.50)},
    "freiburg-101": {"PLE": (94.79, 84.07, 72.92, 58.00, 50.47),
                     "PLE+": (74.38, 61.76, 52.50, 41.65, 37.63)},
    "freiburg-campus": {"PLE": (123.90, 118.57, 110.18, 103.65, 87.50),
                        "PLE+": (93.30, 90.17, 86.10, 80.18, 68.34)},
    "infinite-corridor": {"PLE": (93.35, 61.55, 36.97, 26.54, 21.29),
                          "PLE+": (73.14, 46.12, 28.72, 21.41, 17.56)},
    "intel": {"PLE": (96.56, 63.07, 30.32, 17.10, 9.83),
              "PLE+": (70.10, 44.25, 21.65, 12.97, 7.68)},
    "orebro": {"PLE": (120.21, 102.47, 76.36, 50.33, 31.84),
               "PLE+": (93.85, 77.85, 58.55, 38.55, 24.00)},
}  # fmt: skip


# ----------------------------------------------------------------------------- data


class Dataset:
    """Scans of one kind (one log, or the simulation) with equal ray counts."""

    def __init__(self, name, az, ranges, r_max, closed, polygons=None, indices=None):
        self.name = name
        self.az = np.asarray(az, float)
        self.ranges = np.asarray(ranges, float)  # [S K]
        self.r_max = float(r_max)
        self.closed = bool(closed)
        self.polygons = polygons
        self.indices = indices
        self.rays = from_scan(jaxlie.SE2.identity(), self.az, self.ranges, 0.0, self.r_max)
        self.reflected = np.asarray(self.rays.kind) == HIT  # [S K]
        dirs = np.stack([np.cos(self.az), np.sin(self.az)], -1)
        self.endpoints = self.ranges[..., None] * dirs  # [S K 2]

    @property
    def n(self) -> int:
        return self.ranges.shape[0]

    def scan_rays(self, i: int) -> RayBatch:
        return jax.tree.map(lambda x: x[i] if jnp.ndim(x) else x, self.rays)


def log_source(entry: str) -> tuple[str, Path]:
    """``(name, file)`` of a ``logs`` entry: a registered CARMEN log or a path to one."""
    from lidarjax.datasets import REGISTRY

    if entry in REGISTRY:
        return entry, Path(fetch(entry))
    p = Path(entry).expanduser()
    if not p.is_file():
        raise FileNotFoundError(f"logs: {entry!r} is neither a registered log nor a file")
    return log_name(entry), p


def choose_scans(name: str, entry: str, n_scans: int, cfg) -> tuple[np.ndarray, str]:
    """Scan indices of one log and how they were chosen (``explicit``, ``paper``,
    ``random``): ``scan_indices[name]`` if given; else, with ``scans: paper``, the
    authors' 20 scans when the log has them; else ``scans_per_log`` seeded random scans."""
    explicit = cfg.get("scan_indices") or {}
    if name in explicit:
        idx = np.asarray(list(explicit[name]), int)
        if idx.size == 0 or idx.min() < 0 or idx.max() >= n_scans:
            raise ValueError(
                f"scan_indices.{name}: the log {entry!r} has {n_scans} scans "
                f"(0 … {n_scans - 1}); got {idx.tolist()}"
            )
        return idx, "explicit"
    paper = cfg.get("paper_scans") or {}
    if cfg.scans == "paper" and name in paper:
        idx = np.asarray(list(paper[name]), int)
        if idx.max() >= n_scans:
            raise ValueError(f"paper_scans[{name!r}] has index {idx.max()} >= {n_scans} scans")
        return idx, "paper"
    rng = np.random.default_rng([int(cfg.seed), zlib.crc32(name.encode())])
    idx = np.sort(rng.choice(n_scans, size=min(cfg.scans_per_log, n_scans), replace=False))
    return idx, "random"


def real_dataset(entry: str, cfg) -> Dataset:
    name, path = log_source(entry)
    log = load_carmen(path)
    idx, how = choose_scans(name, entry, log.n_scans, cfg)
    r = np.minimum(log.ranges_m[idx], log.usable_range_m)  # no-returns: SUP at r_max
    ds = Dataset(name, log.azimuths_rad, r, log.usable_range_m, False, indices=idx.tolist())
    ds.selection = how
    return ds


def sim_dataset(cfg, n_scans: int) -> Dataset:
    s = cfg.simulation
    polys, ranges, az = [], [], None
    for i in range(n_scans):
        n = int(s.polygon_sizes[i % len(s.polygon_sizes)])
        poly = random_polygon(n, seed=int(cfg.seed) * 100_003 + i,
                              radius_range_m=tuple(s.radius_range_m))  # fmt: skip
        az, r = simulate_polygon_scan(
            poly,
            n_rays=int(s.n_rays),
            angular_sigma_rad=float(np.deg2rad(s.angular_sigma_deg)),
            radial_sigma_m=float(s.radial_sigma_m),
            seed=int(cfg.seed) * 100_003 + i,
        )
        polys.append(poly)
        ranges.append(r)
    return Dataset("simulated", az, np.stack(ranges), np.inf, True, polygons=polys)


# ----------------------------------------------------------------------------- methods


def _plus_kw(cfg) -> dict:
    """``optimize_polylines`` keyword arguments from ``cfg.ple_plus``."""
    return {"rounds": int(cfg.ple_plus.rounds), "restarts": int(cfg.ple_plus.restarts)}


def _index(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


def baselines(ds: Dataset, i: int, J: int, chains, closed) -> dict:
    """VVL / IEF / SAM results ``(polylines, closed)`` for scan ``i``."""
    pts = ds.endpoints[i]
    refl_pts = pts[ds.reflected[i]]
    out = {}
    if chains:
        n_closed = sum(closed)
        out["VVL"] = F.visvalingam(pts, chains, closed, max(J, 3 * n_closed))
    else:
        out["VVL"] = ([], [])
    if len(refl_pts) >= 2:
        out["IEF"] = F.iterative_endpoint_fit(refl_pts, ds.closed, J)
        out["SAM"] = F.split_and_merge(refl_pts, ds.closed, J)
    else:
        out["IEF"] = out["SAM"] = ([], [])
    return out


def run_all(ds: Dataset, J: int, cfg) -> dict:
    """Every method on every scan of ``ds`` at budget ``J``: polylines and metrics."""
    k = ds.ranges.shape[1]
    init = F.extract_polylines(
        ds.rays, max_vertices=k, l_max_m=cfg.l_max_m, d_rm_m=cfg.d_rm_m, closed=ds.closed
    )
    ple = F.extract_polylines(
        ds.rays, max_vertices=J, l_max_m=cfg.l_max_m, d_rm_m=cfg.d_rm_m, closed=ds.closed
    )
    plus = F.optimize_polylines(ple, ds.rays, **_plus_kw(cfg))
    expected = {
        "PLE": np.asarray(ple.map.expected_ranges(ds.rays)),
        "PLE+": np.asarray(plus.map.expected_ranges(ds.rays)),
    }
    results = {m: [] for m in cfg.methods}
    for i in range(ds.n):
        chains, closed = _index(init.map, i).to_chains()
        base = baselines(ds, i, J, chains, closed)
        got = {}
        for m in cfg.methods:
            if m in ("PLE", "PLE+"):
                mp = _index(ple.map if m == "PLE" else plus.map, i)
                pls, cl = mp.to_polylines()
                exp = expected[m][i]
            else:
                pls, cl = base[m]
                exp = np.asarray(
                    F.PolylineMap.from_polylines(pls, cl).expected_ranges(ds.scan_rays(i))
                )
            got[m] = (pls, cl, exp)
        # rays every method explains: the RMSE on them compares the methods on equal terms
        common = ds.reflected[i] & np.all([np.isfinite(g[2]) for g in got.values()], axis=0)
        for m, (pls, cl, exp) in got.items():
            s = score(ds, i, pls, cl, exp)
            s["rmse_common_m"] = metrics.ray_rmse(ds.ranges[i], exp, common)
            results[m].append(s)
    return results


def score(ds: Dataset, i: int, pls, cl, expected) -> dict:
    refl = ds.reflected[i]
    out = {
        "J": int(sum(len(p) for p in pls)),
        "rmse_m": metrics.ray_rmse(ds.ranges[i], expected, refl),
        "f": metrics.explained_fraction(expected, refl),
        "polylines": [np.asarray(p).tolist() for p in pls],
        "closed": list(map(bool, cl)),
    }
    if ds.polygons is not None:
        verts = np.concatenate(pls) if pls else np.zeros((0, 2))
        try:
            out["a"] = metrics.area_ratio(ds.polygons[i], verts)
        except ValueError:
            out["a"] = None  # fewer than 3 vertices, or the sensor outside the estimate
    return out


def summarize(per_scan: list[dict], key: str) -> dict:
    vals = np.array([s[key] for s in per_scan if s.get(key) is not None], float)
    finite = vals[np.isfinite(vals)]
    n = len(finite)
    return {
        "mean": float(finite.mean()) if n else None,
        "se": float(finite.std(ddof=1) / np.sqrt(n)) if n > 1 else None,
        "n": n,
        "n_undefined": len(per_scan) - n,
    }


# ----------------------------------------------------------------------------- timing


def _timed(fn, *args):
    t = time.perf_counter()
    out = fn(*args)
    jax.block_until_ready(out)
    return time.perf_counter() - t, out


def time_methods(ds: Dataset, J: int, n_scans: int, cfg) -> dict:
    """Median/mean seconds per scan, one scan per call, after a warm-up call per shape."""
    k = ds.ranges.shape[1]

    def ple(r):
        return F.extract_polylines(
            r, max_vertices=J, l_max_m=cfg.l_max_m, d_rm_m=cfg.d_rm_m, closed=ds.closed
        )

    def init(r):
        return F.extract_polylines(
            r, max_vertices=k, l_max_m=cfg.l_max_m, d_rm_m=cfg.d_rm_m, closed=ds.closed
        )

    def ple_plus(r):
        return F.optimize_polylines(ple(r), r, **_plus_kw(cfg))

    times = {m: [] for m in METHODS}
    scans = list(range(min(n_scans, ds.n)))
    r0 = ds.scan_rays(scans[0])
    _timed(ple, r0), _timed(ple_plus, r0), _timed(init, r0)  # compile
    for i in scans:
        r = ds.scan_rays(i)
        times["PLE"].append(_timed(ple, r)[0])
        times["PLE+"].append(_timed(ple_plus, r)[0])
        _, init_res = _timed(init, r)
        chains, closed = init_res.map.to_chains()
        pts = ds.endpoints[i]
        refl_pts = pts[ds.reflected[i]]
        if chains:
            n_closed = sum(closed)
            t, _ = _timed(F.visvalingam, pts, chains, closed, max(J, 3 * n_closed))
            times["VVL"].append(t)  # without the initial polylines (shared with PLE)
        if len(refl_pts) >= 2:
            times["IEF"].append(_timed(F.iterative_endpoint_fit, refl_pts, ds.closed, J)[0])
            times["SAM"].append(_timed(F.split_and_merge, refl_pts, ds.closed, J)[0])
    return {
        m: {"mean_s": float(np.mean(v)), "median_s": float(np.median(v)), "n": len(v)}
        for m, v in times.items()
        if v
    }


# ----------------------------------------------------------------------------- Nelder-Mead


def _np_first_hit(dirs, segs):
    if len(segs) == 0:
        return np.full(len(dirs), np.inf)
    a = segs[:, 0][None]
    e = (segs[:, 1] - segs[:, 0])[None]
    d = dirs[:, None]
    den = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (a[..., 0] * e[..., 1] - a[..., 1] * e[..., 0]) / den
        u = (a[..., 0] * d[..., 1] - a[..., 1] * d[..., 0]) / den
    ok = (np.abs(den) > 1e-14) & (t > 0) & (u >= -1e-12) & (u <= 1 + 1e-12)
    return np.where(ok, t, np.inf).min(axis=1)


def nelder_mead_vs_lm(ds: Dataset, cfg) -> list[dict]:
    """PLE+ (LM) against scipy's Nelder–Mead on the true Eq. (10.4) objective, same
    parametrisation (interior vertices free, end vertices along their ray)."""
    nm = cfg.nelder_mead
    out = []
    dirs = np.stack([np.cos(ds.az), np.sin(ds.az)], -1)
    d_rm2 = float(cfg.d_rm_m) ** 2
    for i in range(min(int(nm.n_scans), ds.n)):
        rays = ds.scan_rays(i)
        ple = F.extract_polylines(rays, max_vertices=int(nm.J), l_max_m=cfg.l_max_m,
                                  d_rm_m=cfg.d_rm_m, closed=ds.closed)  # fmt: skip
        kw = _plus_kw(cfg)
        t_lm, plus = _timed(lambda: F.optimize_polylines(ple, rays, **kw))
        t_lm, plus = _timed(lambda: F.optimize_polylines(ple, rays, **kw))  # warm
        chains, closed = ple.map.to_chains()
        v0 = np.asarray(ple.map.vertices)
        refl = ds.reflected[i]
        r = ds.ranges[i]

        layout = []  # (slot, is_end)
        for ch, c in zip(chains, closed):
            for pos, s in enumerate(ch):
                layout.append((int(s), (not c) and pos in (0, len(ch) - 1)))

        def unpack(x, layout=layout, v0=v0):
            v = v0.copy()
            j = 0
            for s, end in layout:
                if end:
                    v[s] = x[j] * dirs[s]
                    j += 1
                else:
                    v[s] = x[j : j + 2]
                    j += 2
            return v

        x0 = np.concatenate(
            [[np.linalg.norm(v0[s])] if end else v0[s] for s, end in layout]
        ).astype(float)

        def segs_of(v, chains=chains, closed=closed):
            s = []
            for ch, c in zip(chains, closed):
                idx = list(ch) + ([ch[0]] if c else [])
                s += [(v[a], v[b]) for a, b in zip(idx[:-1], idx[1:])]
            return np.array(s)

        def objective(x, refl=refl, r=r):
            t = _np_first_hit(dirs, segs_of(unpack(x)))
            hit = refl & np.isfinite(t)
            return float(np.sum(np.where(hit, (r - np.where(hit, t, 0)) ** 2, 0)[refl])
                         + d_rm2 * np.sum(refl & ~hit))  # fmt: skip

        t0 = time.perf_counter()
        res = minimize(objective, x0, method="Nelder-Mead",
                       options={"maxfev": int(nm.max_evaluations), "xatol": 1e-7,
                                "fatol": 1e-12, "adaptive": True})  # fmt: skip
        t_nm = time.perf_counter() - t0
        n_params = len(x0)
        out.append(
            {
                "scan": i,
                "n_params": n_params,
                "objective_ple": objective(x0),
                "objective_lm": float(
                    objective(
                        np.concatenate(
                            [
                                [np.linalg.norm(np.asarray(plus.map.vertices)[s])]
                                if end
                                else np.asarray(plus.map.vertices)[s]
                                for s, end in layout
                            ]
                        )
                    )  # fmt: skip
                ),
                "objective_nm": float(res.fun),
                "seconds_lm": t_lm,
                "seconds_nm": t_nm,
                "nm_evaluations": int(res.nfev),
            }
        )
    return out


# ----------------------------------------------------------------------------- output


def _fmt(s: dict | None, scale=1.0, digits=1) -> str:
    if not s or s["mean"] is None:
        return "–"
    se = f" ± {s['se'] * scale:.{digits}f}" if s["se"] is not None else ""
    return f"{s['mean'] * scale:.{digits}f}{se}"


def per_log_vs_paper(summary: dict) -> dict:
    """PLE and PLE+ per log against the paper's per-log means (``PAPER_PER_LOG_MM``), with
    the ratio ours / paper where the log was evaluated on the paper's scans."""
    out = {}
    for name, per_j in summary["per_log"].items():
        paper = PAPER_PER_LOG_MM.get(name)
        same = summary["scan_selection"].get(name) == "paper"
        rows = {}
        for J, row in per_j.items():
            r = {}
            for m in ("PLE", "PLE+"):
                if m not in row or row[m]["rmse_m"]["mean"] is None:
                    continue
                ours = row[m]["rmse_m"]["mean"] * 1e3
                ref = paper[m][PAPER_J.index(int(J))] if paper and int(J) in PAPER_J else None
                r[m] = {
                    "ours_mm": ours,
                    "paper_mm": ref,
                    "ratio": ours / ref if (ref and same) else None,
                    "f": row[m]["f"]["mean"],
                }
            rows[J] = r
        out[name] = {"same_scans_as_paper": same, "J": rows}
    return out


def per_log_table(cmp: dict) -> list[str]:
    lines = ["### Per log: PLE and PLE+ against the paper (RMSE, mm)", ""]
    lines += ["Ratios only where the log was evaluated on the paper's 20 scans "
              "(`scans: paper`); `f` is the same for PLE and PLE+ by construction.",
              ""]  # fmt: skip
    lines += ["| log | J | PLE | paper PLE | PLE+ | paper PLE+ | PLE+ / paper | f |",
              "|---|---:|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    fmt = lambda v, d=1: "–" if v is None else f"{v:.{d}f}"  # noqa: E731
    for name, c in cmp.items():
        for J, r in c["J"].items():
            a, b = r.get("PLE", {}), r.get("PLE+", {})
            lines.append(
                f"| {name} | {J} | {fmt(a.get('ours_mm'))} | {fmt(a.get('paper_mm'))} | "
                f"{fmt(b.get('ours_mm'))} | {fmt(b.get('paper_mm'))} | "
                f"{fmt(b.get('ratio'), 3)} | {fmt(b.get('f') or a.get('f'), 3)} |"
            )
    ratios = [r["PLE+"]["ratio"] for c in cmp.values() for r in c["J"].values()
              if r.get("PLE+", {}).get("ratio") is not None]  # fmt: skip
    if ratios:
        logs_ok = sum(
            all(r["PLE+"]["ratio"] <= 1.0 for r in c["J"].values() if "PLE+" in r)
            for c in cmp.values() if c["same_scans_as_paper"]
        )  # fmt: skip
        n_same = sum(c["same_scans_as_paper"] for c in cmp.values())
        lines += ["", f"PLE+ / paper: {min(ratios):.3f} … {max(ratios):.3f}; logs at or below "
                      f"the paper at every J: {logs_ok} of {n_same}."]  # fmt: skip
    lines.append("")
    return lines


def tables(summary: dict) -> str:
    lines = []
    for kind, title in (("real", "Real scans (Figure 10.4a)"),
                        ("simulated", "Simulated scans (Figure 10.4b)")):  # fmt: skip
        if kind not in summary["accuracy"]:
            continue
        acc = summary["accuracy"][kind]
        methods = list(next(iter(acc.values())).keys())
        lines += [f"### {title}", "", "RMSE of the ray radii (mm, mean ± standard error):", ""]
        lines += ["| J | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
        for J, row in acc.items():
            lines.append(f"| {J} | " + " | ".join(_fmt(row[m]["rmse_m"], 1e3) for m in methods)
                         + " |")  # fmt: skip
        lines += ["", "RMSE on the rays every method explains (mm, mean ± standard error):", ""]
        lines += ["| J | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
        for J, row in acc.items():
            cells = [_fmt(row[m]["rmse_common_m"], 1e3) for m in methods]
            lines.append(f"| {J} | " + " | ".join(cells) + " |")
        lines += ["", "f = reflected rays intersected / reflected rays (mean ± s.e.):", ""]
        lines += ["| J | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
        for J, row in acc.items():
            lines.append(f"| {J} | " + " | ".join(_fmt(row[m]["f"], 1, 3) for m in methods)
                         + " |")  # fmt: skip
        if kind == "simulated":
            lines += ["", "a = area ratio against the ground-truth polygon:", ""]
            lines += ["| J | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
            for J, row in acc.items():
                lines.append(f"| {J} | " + " | ".join(_fmt(row[m]["a"], 1, 3) for m in methods)
                             + " |")  # fmt: skip
        lines.append("")
    if summary.get("per_log_vs_paper"):
        lines += per_log_table(summary["per_log_vs_paper"])
    if summary.get("timing"):
        lines += ["### Mean seconds per scan (Table 10.2; paper: MATLAB, one Xeon core)", ""]
        lines += ["| data | J | " + " | ".join(METHODS) + " |", "|---" * (len(METHODS) + 2) + "|"]
        for kind, per_j in summary["timing"].items():
            for J, row in per_j.items():
                paper = PAPER_SECONDS.get(kind, {}).get(int(J), {})
                cells = []
                for m in METHODS:
                    ours = f"{row[m]['mean_s']:.4f}" if m in row else "–"
                    cells.append(f"{ours} ({paper[m]})" if m in paper else ours)
                lines.append(f"| {kind} | {J} | " + " | ".join(cells) + " |")
        lines.append("")
    if summary.get("nelder_mead"):
        lines += ["### PLE+: Levenberg–Marquardt vs Nelder–Mead (Eq. 10.4 objective, m²)", ""]
        lines += ["| scan | params | PLE | LM | NM | LM s | NM s | NM evals |",
                  "|---|---|---|---|---|---|---|---|"]  # fmt: skip
        for r in summary["nelder_mead"]:
            lines.append(
                f"| {r['scan']} | {r['n_params']} | {r['objective_ple']:.5f} | "
                f"{r['objective_lm']:.5f} | {r['objective_nm']:.5f} | {r['seconds_lm']:.3f} | "
                f"{r['seconds_nm']:.2f} | {r['nm_evaluations']} |"
            )
        lines.append("")
    return "\n".join(lines)


def plot_accuracy(acc: dict, out: Path, kind: str, noise_m: float | None) -> None:
    """Figure 10.4: accuracy vs J per method; the legend sits outside the panels."""
    keys = ["rmse_m", "rmse_common_m", "f"] + (["a"] if kind == "simulated" else [])
    fig, axes = plt.subplots(
        1, len(keys), figsize=(4.2 * len(keys) + 1.0, 3.6), layout="constrained", squeeze=False
    )
    axes = axes[0]
    Js = [int(j) for j in acc]
    methods = list(next(iter(acc.values())).keys())
    for ax, key in zip(axes, keys):
        for m in methods:
            mean = [acc[str(j)][m][key]["mean"] for j in Js]
            se = [acc[str(j)][m][key]["se"] or 0.0 for j in Js]
            scale = 1e3 if key.startswith("rmse") else 1.0
            y = np.array([np.nan if v is None else v * scale for v in mean])
            ax.errorbar(Js, y, yerr=np.array(se) * scale, label=m, color=COLORS.get(m),
                        marker="o", ms=3, capsize=2)  # fmt: skip
        if key.startswith("rmse") and noise_m:
            ax.axhline(noise_m * 1e3, color="0.4", ls="--", lw=1)
        ax.set_xlabel("J (vertices)")
        labels = {
            "rmse_m": "RMSE (mm)",
            "rmse_common_m": "RMSE on common rays (mm)",
            "f": "explained fraction f",
            "a": "area ratio a",
        }
        ax.set_ylabel(labels.get(key, key))
        if key.startswith("rmse"):
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
    handles, names = axes[0].get_legend_handles_labels()
    fig.legend(handles, names, loc="outside right center", fontsize=8, title="method")
    fig.suptitle(f"Polyline extraction accuracy, {kind} scans (mean ± s.e.)", fontsize=10)
    fig.savefig(out, dpi=130)
    plt.close(fig)


def plot_example(ds: Dataset, i: int, J: int, cfg, out: Path) -> dict:
    """Figure 10.3: all methods on one scan."""
    res = run_all(Dataset(ds.name, ds.az, ds.ranges[i : i + 1], ds.r_max, ds.closed), J, cfg)
    methods = list(res)
    pts = np.vstack([ds.endpoints[i][ds.reflected[i]], np.zeros((1, 2))])
    lo, hi = pts.min(0) - 0.5, pts.max(0) + 0.5
    height = float(np.clip(3.6 * (hi[1] - lo[1]) / (hi[0] - lo[0]), 1.5, 5.0)) + 1.3
    fig, axes = plt.subplots(
        1, len(methods), figsize=(3.6 * len(methods), height), layout="constrained", squeeze=False
    )
    for ax, m in zip(axes[0], methods):
        s = res[m][0]
        plot_polyline_scan(
            ax, np.zeros(2), ds.endpoints[i], ds.reflected[i],
            [np.asarray(p) for p in s["polylines"]], s["closed"],
            title=f"{m}: RMSE {s['rmse_m'] * 1e3:.1f} mm, f {s['f']:.2f}",
        )  # fmt: skip
    for ax in axes[0]:  # same frame for all methods (SAM's vertices can fly off)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    fig.suptitle(
        f"Figure 10.3: {ds.name} scan {ds.indices[i] if ds.indices is not None else i}, "
        f"J_max = {J}, sensor frame (red: reflected rays, grey: no return)",
        fontsize=10,
    )
    fig.savefig(out, dpi=130)
    plt.close(fig)
    return {m: {k: res[m][0][k] for k in ("J", "rmse_m", "f")} for m in methods}


# ----------------------------------------------------------------------------- main


@hydra.main(config_path="../configs", config_name="polylines", version_base=None)
def main(cfg: DictConfig) -> None:
    validate(cfg, "polylines")
    jax.config.update("jax_enable_x64", bool(cfg.x64))
    out = output_dir()
    if (done := completed_job(out)) is not None:  # a sweep job that already finished
        return done
    out.mkdir(parents=True, exist_ok=True)
    unknown = set(cfg.methods) - set(METHODS)
    if unknown:
        raise ValueError(f"methods: unknown {sorted(unknown)}; choose from {list(METHODS)}")
    t0 = time.perf_counter()
    real = [real_dataset(n, cfg) for n in tqdm(cfg.logs, desc="loading logs")]
    n_sim = cfg.simulation.n_scans
    n_sim = sum(d.n for d in real) if n_sim == "auto" else int(n_sim)
    sim = sim_dataset(cfg, n_sim) if n_sim > 0 else None
    summary: dict = {
        "config": OmegaConf.to_container(cfg, resolve=True),
        "scan_indices": {d.name: d.indices for d in real},
        "scan_selection": {d.name: d.selection for d in real},
        "n_scans": {"real": sum(d.n for d in real), "simulated": n_sim},
        "accuracy": {},
        "jax_version": jax.__version__,
        "dtype": str(jnp.result_type(float)),
    }
    per_scan: dict = {}
    groups = [("real", real)] + ([("simulated", [sim])] if sim is not None else [])
    for kind, dsets in groups:
        acc = {}
        for J in tqdm(list(cfg.J), desc=f"{kind}: J"):
            merged = {m: [] for m in cfg.methods}
            for ds in dsets:
                res = run_all(ds, int(J), cfg)
                for m in cfg.methods:
                    merged[m] += res[m]
                if kind == "real":
                    summary.setdefault("per_log", {}).setdefault(ds.name, {})[str(J)] = {
                        m: {k: summarize(res[m], k) for k in ("rmse_m", "f")} for m in cfg.methods
                    }
            per_scan.setdefault(kind, {})[str(J)] = {
                m: [{k: v for k, v in s.items() if k not in ("polylines", "closed")}
                    for s in merged[m]] for m in cfg.methods
            }  # fmt: skip
            acc[str(J)] = {
                m: {k: summarize(merged[m], k) for k in ("rmse_m", "rmse_common_m", "f", "a", "J")}
                for m in cfg.methods
            }
        summary["accuracy"][kind] = acc
        noise = float(cfg.simulation.radial_sigma_m) if kind == "simulated" else None
        plot_accuracy(acc, out / ("fig10_4a.png" if kind == "real" else "fig10_4b.png"), kind,
                      noise)  # fmt: skip
    summary["timing"] = {}
    for kind, dsets in groups:
        summary["timing"][kind] = {}
        for J in cfg.timing_J:
            per = [time_methods(ds, int(J), max(1, int(cfg.timing_scans) // len(dsets)), cfg)
                   for ds in dsets]  # fmt: skip
            summary["timing"][kind][str(J)] = {
                m: {"mean_s": float(np.mean([p[m]["mean_s"] for p in per if m in p])),
                    "median_s": float(np.median([p[m]["median_s"] for p in per if m in p]))}
                for m in METHODS if any(m in p for p in per)
            }  # fmt: skip
    if sim is not None and int(cfg.nelder_mead.n_scans) > 0:
        summary["nelder_mead"] = nelder_mead_vs_lm(sim, cfg)
    ex = next((d for d in real if d.name == cfg.example.log), real[0] if real else None)
    if ex is not None:
        i = (
            int(np.argmax(ex.reflected.sum(1)))
            if cfg.example.scan == "auto"
            else int(list(ex.indices).index(int(cfg.example.scan)))
        )
        summary["example"] = {
            "log": ex.name,
            "scan": ex.indices[i],
            "J": int(cfg.example.J),
            "methods": plot_example(ex, i, int(cfg.example.J), cfg, out / "fig10_3.png"),
        }
    if "per_log" in summary:
        summary["per_log_vs_paper"] = per_log_vs_paper(summary)
    summary["runtime_s"] = time.perf_counter() - t0
    md = tables(summary)
    (out / "per_scan.json").write_text(json.dumps(per_scan))
    write_results(out, results=summary, markdown=md, cfg=cfg)
    print(md)


if __name__ == "__main__":
    main()
