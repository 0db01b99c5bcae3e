"""``lidarjax slam``: decay-rate SLAM (:func:`lidarjax.slam.run_slam`) on a laser log's
scans and raw odometry. Writes the trajectories (TUM), the loop closures, the map of the
estimate (``map.npz`` as ``lidarjax map`` writes it, so ``lidarjax localize`` reads it),
a figure and, where the log has ground truth, the errors against it."""

from __future__ import annotations

import json
import math

import numpy as np

from ._inputs import CliInputError, load_log_scans, out_dir
from ._localize import _stamps
from ._map import R_MIN_M, _positive, build_stats, model_from_stats, scan_ranges, write_map_files

__all__ = ["BACK_ENDS", "CHAINS", "DRIFT", "MATCHING", "cmd_slam"]

MATCHING = ("decay-rate", "endpoint")
"""``--model``: the scan-matching model (:data:`lidarjax.slam.MATCHING_MODELS`, spelled
with a hyphen as ``lidarjax map`` spells its models)."""
CHAINS = (*MATCHING, "icp", "gicp")
"""``--extra-chains``' models (:data:`lidarjax.slam.CHAIN_MODELS`): a matching model's
front end; ``icp``, point-to-line ICP in JAX (:func:`lidarjax.slam.point_icp_front_end`);
or ``gicp``, small_gicp's scan-to-submap registration
(:func:`lidarjax.slam.icp_front_end`; needs ``pip install 'lidarjax[slam]'``)."""
BACK_ENDS = ("none", "joint", "alternating")
"""``--back-end``: :class:`lidarjax.slam.SlamConfig`'s ``back_end`` (default none)."""
DRIFT = {
    "sigma_trans_rel": 0.05,
    "sigma_rot_per_m": math.radians(1.0),
    "heading_bias_per_m": math.radians(0.3),
    "sigma_rot_per_rad": 0.02,
}
"""``--drift``: :func:`lidarjax.sim.wheel_odometry`'s settings, those of
``configs/slam.yaml`` (5 % of each step's length, 1 deg per m of heading noise, 0.3 deg
per m of heading bias, 2 % of each turn)."""
SAME_POSES_M = 1e-6
"""Odometry within this of the ground truth at every scan (m, rad) equals it."""
MAX_WINDOW_CELLS = 4000**2
"""Largest map window of the front end (cells; 880 x 880 at the defaults)."""
ODOMETRY_SIGMAS = (
    "odometry_sigma_rel",
    "odometry_sigma_xy_m",
    "odometry_sigma_yaw_per_m",
    "odometry_sigma_yaw_rel",
    "odometry_sigma_yaw_rad",
)
"""The :class:`lidarjax.slam.FrontEndConfig` fields ``--odometry-noise`` scales."""


def _extra_chains(value: str) -> tuple[str, ...] | None:
    """``--extra-chains``: None for 'auto' (SlamConfig's default: the other model and icp), ()
    for 'none', else the comma-separated models (as SlamConfig spells them)."""
    v = value.strip()
    if v == "auto":
        return None
    if v == "none":
        return ()
    models = tuple(m.strip() for m in v.split(","))
    for m in models:
        if m not in CHAINS:
            raise CliInputError(
                "--extra-chains",
                f"must be 'auto', 'none' or a comma-separated list of {', '.join(CHAINS)}; "
                f"got {value!r}",
            )
    if len(set(models)) != len(models):
        raise CliInputError("--extra-chains", f"must not repeat a model, got {value!r}")
    return tuple(m.replace("-", "_") for m in models)


def _range_cap(value: float | None, usable: float, ranges: np.ndarray) -> float:
    """``--range-cap``: readings at or beyond it are no-returns to the front end. At most
    the log's usable range: a reading beyond that is already a no-return, and a cap above
    it would read the sensor's no-return value as a wall. Default: the smallest of 20, 30
    and 40 m that keeps 98 % of ``ranges``' returns (:func:`lidarjax.slam.auto_range_cap`)."""
    if value is None:
        from .. import slam

        return slam.auto_range_cap(ranges, usable)
    cap = _positive(value, "--range-cap")
    if cap <= R_MIN_M:
        raise CliInputError("--range-cap", f"must exceed {R_MIN_M} m, got {cap}")
    if cap > usable:
        raise CliInputError(
            "--range-cap",
            f"must be at most LOG's usable range, {usable:.3f} m (readings at or beyond it "
            f"are no-returns), got {cap}",
        )
    return cap


def _odometry(args, loaded, idx) -> tuple[np.ndarray, str]:
    """The odometry SLAM starts from, and a description of it."""
    log = loaded.log
    if args.drift is not None:
        if args.drift < 0:
            raise CliInputError("--drift", f"must be a seed >= 0, got {args.drift}")
        if not loaded.has_ground_truth:
            raise CliInputError("--drift", "LOG has no ground-truth poses to simulate it from")
        from ..sim import wheel_odometry

        gt = np.asarray(log.poses, float)[idx]
        return wheel_odometry(gt, seed=int(args.drift), **DRIFT), f"simulated (seed {args.drift})"
    odo = np.asarray(log.odometry, float)[idx]
    if not np.all(np.isfinite(odo)):
        bad = int(idx[np.flatnonzero(~np.all(np.isfinite(odo), axis=1))[0]])
        raise CliInputError("LOG", f"scan {bad} has no odometry pose (SLAM needs one per scan)")
    if loaded.has_ground_truth:
        gt = np.asarray(log.poses, float)[idx]
        if np.max(np.abs(odo - gt)) < SAME_POSES_M:
            print(
                "note: LOG's odometry equals its ground-truth poses (a corrected log, as "
                "the shared CARMEN logs are), so SLAM starts from the answer; --drift SEED "
                "simulates a drifting wheel odometry from them"
            )
    return odo, "the log's"


RESIMULATE_FOOTPRINT_M = 0.2
"""``--resimulate``: no surface within this distance (m) of a pose (``footprint_m``)."""


def _check_resimulate(args, loaded) -> None:
    if args.resimulate is None:
        return
    if args.resimulate < 0:
        raise CliInputError("--resimulate", f"must be a seed >= 0, got {args.resimulate}")
    if not loaded.has_ground_truth:
        raise CliInputError("--resimulate", "LOG has no ground-truth poses to cast from")


def _resimulated(args, loaded, idx, ranges, az, cap, usable):
    """``--resimulate SEED``: LOG's scans re-simulated at its ground-truth poses
    (:func:`lidarjax.sim.resimulate_scans`, cast to the range cap; no-returns read the
    usable range, LOG's own no-return convention), and the settings for slam.json; or
    ``(ranges, None)`` without the option. The option was checked (:func:`_check_resimulate`)
    before anything was written."""
    if args.resimulate is None:
        return ranges, None
    from ..sim import resimulate_scans

    gt = np.asarray(loaded.log.poses, float)[idx]
    rs = resimulate_scans(
        ranges,
        az,
        gt,
        max_range_m=cap,
        footprint_m=RESIMULATE_FOOTPRINT_M,
        seed=int(args.resimulate),
    )
    out = np.where(rs.ranges_m >= cap, usable, rs.ranges_m)
    info = {
        "seed": int(args.resimulate),
        "cell_m": rs.cell_m,
        "footprint_m": RESIMULATE_FOOTPRINT_M,
        "n_segments": rs.n_segments,
        "share_returns": float(np.mean(out < cap)),
    }
    return out, info


def _write_loops(path, idx, res) -> None:
    """``loops.csv``: one relative-pose factor per row (kind ``loop``, ``short`` for the
    short loop search's, or ``revisit``), scan indices of LOG, with its weight in the
    final pose graph (``SlamResult.loop_weights``: near 1 kept, below
    ``slam.REJECTED_WEIGHT`` taken for an outlier)."""
    rows = ["kind,scan_from,scan_to,dx_m,dy_m,dyaw_rad,weight"]
    n_long = len(np.asarray(res.loops.edges).reshape(-1, 2)) - res.n_short_loops
    for kind, found, weights in (
        ("loop", res.loops, res.loop_weights),
        ("revisit", res.revisits, res.revisit_weights),
    ):
        edges = np.asarray(found.edges).reshape(-1, 2)
        meas = np.asarray(found.measurements).reshape(-1, 3)
        for k, ((a, b), m, w) in enumerate(zip(edges, meas, np.asarray(weights, float))):
            # the short loop search's loop closures come last (SlamResult.n_short_loops)
            name = "short" if kind == "loop" and k >= n_long else kind
            rows.append(f"{name},{idx[a]},{idx[b]},{m[0]:.6f},{m[1]:.6f},{m[2]:.6f},{w:.6g}")
    path.write_text("\n".join(rows) + "\n")


def _write_front_end(path, idx, res, chain_models) -> None:
    """``front_end.csv``: one row per scan (index in LOG) of the front end's match: rays in
    its objective, the standard deviations of the match's own information in the scan's
    frame (rays taken as independent, so over-confident: for comparing scans, e.g. a
    corridor's large along-track sd; empty for the first scan, ``inf`` where the
    information is not positive definite), whether it passed the gate, its wall time,
    and the final pose graph's weight of the increment from the scan before
    (``SlamResult.chain_weights``; below ``slam.REJECTED_WEIGHT``: the graph overruled
    it), then that of each further front end's increment (``graph_weight_MODEL``; empty
    where the increment is not in the graph: a rejected ``icp`` or ``gicp`` registration)."""
    names = ["graph_weight"] + [f"graph_weight_{m.replace('_', '-')}" for m in chain_models]
    rows = ["scan,rays_used,sd_x_m,sd_y_m,sd_yaw_rad,passed_gate,seconds," + ",".join(names)]
    cw = np.asarray(res.chain_weights, float)
    for k, i in enumerate(idx):
        info = np.asarray(res.front_end_information[k], float)
        info = 0.5 * (info + info.T)
        if k == 0:
            sd = ",,"  # the first scan starts the map: no match
        elif np.all(np.isfinite(info)) and np.linalg.eigvalsh(info)[0] > 0:
            sd = ",".join(f"{v:.6g}" for v in np.sqrt(np.diag(np.linalg.inv(info))))
        else:
            sd = "inf,inf,inf"
        # the first scan has no increment into it
        w = ",".join(
            "" if k == 0 or not np.isfinite(v) else f"{v:.6g}" for v in cw[:, max(k - 1, 0)]
        )
        rows.append(
            f"{i},{int(res.front_end_n_used[k])},{sd},{int(res.front_end_plausible[k])},"
            f"{float(res.front_end_seconds_per_scan[k]):.6f},{w}"
        )
    path.write_text("\n".join(rows) + "\n")


def _plot_loops(ax, est, res) -> None:
    """The loop closures as segments between their scans' estimated positions (m): kept
    ones in blue, those the pose graph rejected (weight below ``slam.REJECTED_WEIGHT``)
    in red."""
    from matplotlib.collections import LineCollection

    from .. import slam

    e = np.asarray(res.loops.edges).reshape(-1, 2)
    w = np.asarray(res.loop_weights, float)
    for keep, color, label in ((True, "tab:blue", "loop closure"), (False, "tab:red", None)):
        sel = e[(w >= slam.REJECTED_WEIGHT) == keep]
        if len(sel) == 0:
            continue
        label = label or "loop closure the pose graph rejected"
        segs = np.stack([est[sel[:, 0], :2], est[sel[:, 1], :2]], 1)
        ax.add_collection(LineCollection(segs, colors=color, linewidths=0.6, label=label))
    if len(e):
        ax.legend(loc="best", fontsize=8, framealpha=0.8)


def _verdicts(res, models) -> dict:
    """``slam.json``'s ``pose_graph``: its final cost and how many loop closures,
    revisits and increments of each front end (``models``: the first front end's, then
    the further ones'; ``MODEL: count``) it took for outliers (weight below
    ``slam.REJECTED_WEIGHT``)."""
    from .. import slam

    cut = slam.REJECTED_WEIGHT
    models = [m.replace("_", "-") for m in models]
    cw = np.asarray(res.chain_weights, float)
    return {
        "cost": float(res.pose_graph_cost),
        "rejected_weight": cut,
        "loops_rejected": int(np.sum(np.asarray(res.loop_weights) < cut)),
        "revisits_rejected": int(np.sum(np.asarray(res.revisit_weights) < cut)),
        "increments_rejected": {m: int(np.sum(row < cut)) for m, row in zip(models, cw)},
    }


def _errors(poses: dict, ates: dict, gt: np.ndarray, delta_m: float) -> dict:
    """ATE (``ates``: each trajectory's :func:`~lidarjax.metrics.absolute_trajectory_error`)
    and RPE per ``delta_m`` of path of each of ``poses`` against ``gt``."""
    from ..metrics import relative_pose_error

    out = {}
    for name, p in poses.items():
        a = ates[name]
        entry = {"ate_rmse_m": a.rmse_m, "ate_mean_m": a.mean_m, "ate_max_m": a.max_m}
        if len(gt) > 1 and np.sum(np.hypot(*np.diff(gt[:, :2], axis=0).T)) >= delta_m:
            r = relative_pose_error(p, gt, delta_m=delta_m)
            entry["rpe_trans_rmse_m"] = r.rmse_m
            entry["rpe_rot_rmse_deg"] = math.degrees(r.rotation_rmse_rad)
        out[name] = entry
    return out


def cmd_slam(args) -> int:
    import lidarjax

    lidarjax.enable_compilation_cache()
    import matplotlib

    matplotlib.use("Agg")
    import dataclasses

    import jaxlie
    import matplotlib.pyplot as plt

    from .. import slam
    from ..datasets import write_tum
    from ..metrics import absolute_trajectory_error
    from ..plot import plot_map, plot_trajectory

    if args.loop_rounds < 1:
        raise CliInputError("--loop-rounds", f"must be >= 1, got {args.loop_rounds}")
    resolution = _positive(args.resolution, "--resolution")
    noise = _positive(args.odometry_noise, "--odometry-noise")
    grazing = float(args.grazing_cells)
    if not (math.isfinite(grazing) and grazing >= 0):
        raise CliInputError("--grazing-cells", f"must be a number >= 0, got {grazing}")
    local = args.local_map_scans
    if local < 0:
        raise CliInputError("--local-map-scans", f"must be >= 0, got {local}")
    rpe_delta = _positive(args.rpe_delta, "--rpe-delta")
    extra_chains = _extra_chains(args.extra_chains)
    short = args.short_loops
    if not (short == 0 or short >= 3):
        raise CliInputError("--short-loops", f"must be 0 (off) or >= 3, got {short}")
    loaded, idx = load_log_scans(args)
    log = loaded.log
    if idx.size < 2:
        raise CliInputError("--scans", "select at least 2 scans")
    _check_resimulate(args, loaded)
    usable = float(log.usable_range_m)
    # non-finite readings (a bag's inf) and readings at or beyond the usable range are
    # no-returns: clipped to the usable range, at or beyond the cap
    ranges = np.minimum(scan_ranges(log, usable)[idx], usable)
    cap = _range_cap(args.range_cap, usable, ranges)
    side = 2.0 * (cap + 2.0) / resolution  # the front end's map window, in cells
    if side**2 > MAX_WINDOW_CELLS:
        raise CliInputError(
            "--resolution",
            f"{resolution} m cells make the front end's {2 * (cap + 2):.0f} m map window "
            f"{side:.0f} cells wide (at most {MAX_WINDOW_CELLS**0.5:.0f}); choose coarser "
            "cells or a smaller --range-cap",
        )
    odo, odo_source = _odometry(args, loaded, idx)
    out = out_dir(args.out)
    az = np.asarray(log.azimuths_rad, float)
    ranges, resim = _resimulated(args, loaded, idx, ranges, az, cap, usable)
    if resim is not None:  # the map below is built from the same scans
        all_ranges = np.array(log.ranges_m, float)
        all_ranges[idx] = ranges
        loaded = dataclasses.replace(loaded, log=dataclasses.replace(log, ranges_m=all_ranges))
        log = loaded.log
    base = slam.FrontEndConfig()
    front = slam.FrontEndConfig(
        model=args.model.replace("-", "_"),
        resolution_m=resolution,
        grazing_cells=grazing,
        grazing_max_m=max(base.grazing_max_m, grazing * resolution),
        local_map_scans=local,
        **{k: noise * getattr(base, k) for k in ODOMETRY_SIGMAS},
    ).with_range_cap(cap)
    cfg = slam.SlamConfig(
        front=front,
        back=slam.BackEndConfig(resolution_m=resolution, range_cap_m=min(10.0, cap)),
        back_end=args.back_end,
        loop_rounds=int(args.loop_rounds),
        calibrate_odometry=not args.no_odometry_calibration,
        extra_chain_models=extra_chains,
        short_loop_separation=int(short),
        # revisits=None: only with local == 0 (a local map's front end never matched two
        # visits to each other: its relative pose between them is no measurement)
    )
    res = slam.run_slam(ranges, az, odo, cfg, progress=not args.no_progress)
    est = np.asarray(res.poses, float)

    stamps, unit = _stamps(log, idx)
    files = []
    extra_tum = {
        f"front_end_{m.replace('_', '-')}.tum": p
        for m, p in zip(cfg.chain_models, res.extra_front_end_poses)
    }
    for name, p in (
        ("trajectory.tum", est),
        ("front_end.tum", res.front_end_poses),
        *extra_tum.items(),
        ("odometry.tum", odo),
    ):
        p = np.asarray(p, float)
        write_tum(out / name, stamps, jaxlie.SE2.from_xy_theta(p[:, 0], p[:, 1], p[:, 2]))
        files.append(name)
    _write_loops(out / "loops.csv", idx, res)
    _write_front_end(out / "front_end.csv", idx, res, cfg.chain_models)
    files += ["loops.csv", "front_end.csv"]

    # the map of the estimate, as `lidarjax map` builds one at a log's poses
    poses_all = np.full((log.n_scans, 3), np.nan)
    poses_all[idx] = est
    mapped = dataclasses.replace(loaded, log=dataclasses.replace(log, poses=poses_all))
    stats, _, p_out = build_stats(
        mapped,
        idx,
        resolution=resolution,
        margin=1.0,
        r_max=usable,
        chunk=64,
        progress=not args.no_progress,
    )
    model = model_from_stats("decay-rate", stats, p_out=p_out)
    n_fe = len(idx)
    seconds = {k: float(v) for k, v in res.seconds.items()}
    meta = {
        "source": loaded.source,
        "source_kind": loaded.kind,
        "topic": args.topic,
        "azimuth_layout": loaded.azimuth_layout,
        "scans": args.scans or ":",
        "n_scans_used": int(n_fe),
        "r_min_m": R_MIN_M,
        "r_max_m": usable,
        "sigma_m": 0.1,
        "p_out": p_out,
        "poses": "lidarjax slam",
        "lidarjax_version": lidarjax.__version__,
    }
    write_map_files(out, "decay-rate", model, stats, meta)
    files += ["map.npz", "map.yaml", "map.pgm"]

    summary = {
        "source": loaded.source,
        "scans": args.scans or ":",
        "n_scans": int(n_fe),
        "model": args.model,
        "back_end": args.back_end,
        "loop_rounds": int(args.loop_rounds),
        "odometry_noise": noise,
        "grazing_cells": grazing,
        "local_map_scans": local,
        "range_cap_m": cap,
        "resolution_m": resolution,
        "azimuth_layout": loaded.azimuth_layout,
        "odometry": odo_source,
        "resimulated": resim,
        "n_loops": int(len(res.loops.edges)),
        "n_revisits": int(len(res.revisits.edges)),
        # of n_loops, those of the short loop search (--short-loops)
        "short_loop_separation": int(short),
        "n_short_loops": int(res.n_short_loops),
        # further front ends, each a further robust chain of the pose graph
        "extra_chain_models": [m.replace("_", "-") for m in cfg.chain_models],
        # the odometry's systematic heading errors, removed before the pose graph
        "odometry_calibration": None
        if res.odometry_calibration is None
        else dataclasses.asdict(res.odometry_calibration),
        # scans whose match failed the gate: placed near the odometry's prediction
        "front_end_gate_fallbacks": int(np.sum(~np.asarray(res.front_end_plausible[1:]))),
        # what the final pose graph overruled: factors whose weight fell below
        # slam.REJECTED_WEIGHT (whitened residual over 3 Cauchy scales)
        "pose_graph": _verdicts(res, (cfg.front.model, *cfg.chain_models)),
        "seconds": seconds,
        "front_end_scans_per_s": n_fe / max(seconds.get("front_end", 0.0), 1e-9),
        "time_unit": unit,
    }

    fig, ax = plt.subplots(figsize=(8, 8), layout="constrained")
    plot_map(model, observed=stats, ax=ax, title=f"lidarjax slam: {loaded.source}")
    plot_trajectory(odo, ax=ax, color="tab:gray", lw=0.6, ls="--", label="odometry")
    gt = None
    if loaded.has_ground_truth:
        gt = np.asarray(log.poses, float)[idx]
        trajectories = {"odometry": odo, "front_end": res.front_end_poses, "estimate": est}
        ates = {k: absolute_trajectory_error(p, gt) for k, p in trajectories.items()}
        a = ates["estimate"]
        # the ground truth in the estimate's frame (the inverse of the alignment)
        c, s = math.cos(a.rotation_rad), math.sin(a.rotation_rad)
        rot = np.array([[c, s], [-s, c]])
        plot_trajectory(
            (gt[:, :2] - a.translation_m) @ rot.T,
            ax=ax,
            color="tab:green",
            lw=0.8,
            label="ground truth (aligned)",
        )
    plot_trajectory(est, ax=ax, color="tab:orange", lw=0.9, label="SLAM estimate")
    _plot_loops(ax, est, res)
    fig.savefig(out / "slam.png", dpi=150)
    plt.close(fig)
    files.append("slam.png")

    pgv = summary["pose_graph"]
    overruled = ", ".join(f"{m} {c}" for m, c in pgv["increments_rejected"].items())
    print(
        f"SLAM ({args.model} matching, back end {args.back_end}) on {n_fe} scans of "
        f"{loaded.source}: {summary['n_loops']} loop closures ({pgv['loops_rejected']} "
        f"rejected by the pose graph), {summary['n_revisits']} revisits; front end "
        f"{summary['front_end_scans_per_s']:.2f} scans/s, "
        f"{summary['front_end_gate_fallbacks']} matches failed its gate; increments the "
        f"pose graph overruled: {overruled}"
    )
    if gt is not None:
        errs = _errors(trajectories, ates, gt, rpe_delta)
        summary["errors"] = errs
        summary["rpe_delta_m"] = rpe_delta
        fig, axs = plt.subplots(figsize=(8, 3.5), layout="constrained")
        x = stamps - stamps[0] if unit == "s" else stamps
        for k, color in (("front_end", "tab:blue"), ("estimate", "tab:orange")):
            axs.plot(x, ates[k].errors_m, color=color, lw=0.8, label=k.replace("_", " "))
        axs.set_xlabel("time since the first scan (s)" if unit == "s" else "scan index")
        axs.set_ylabel("position error after SE(2) alignment (m)")
        axs.set_title(f"{loaded.source}: ATE {errs['estimate']['ate_rmse_m']:.3f} m")
        axs.set_ylim(bottom=0)
        axs.grid(alpha=0.3)
        axs.legend()
        fig.savefig(out / "errors.png", dpi=120)
        plt.close(fig)
        files.append("errors.png")
        print(
            "ATE (RMSE after SE(2) alignment): odometry "
            f"{errs['odometry']['ate_rmse_m']:.3f} m, front end "
            f"{errs['front_end']['ate_rmse_m']:.3f} m, estimate "
            f"{errs['estimate']['ate_rmse_m']:.3f} m"
        )
    else:
        print("no ground truth in LOG: no errors.png, no ATE")
    (out / "slam.json").write_text(json.dumps(summary, indent=1))
    files.append("slam.json")
    for f in files:
        print(f"  {out / f}")
    return 0
