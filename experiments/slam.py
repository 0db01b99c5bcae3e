"""Differentiable lidar SLAM with decay-rate fields (issue #24) on the CARMEN logs.

The logs' odometry equals their corrected poses, so a drifting wheel odometry is simulated
from the corrected poses (``lidarjax.sim.wheel_odometry``, ``odometry`` settings, seed
``seed``, or each of ``seeds``). Every variant starts from it and is scored against the
corrected poses:

- ``decay_rate_joint``: :func:`lidarjax.slam.run_slam` (decay-rate front end, loop
  closures, pose graph, joint optimisation of all poses and the field);
- ``decay_rate_alternating``: the same with the alternating back end (closed-form grid
  <-> poses, Eq. 7.10);
- ``decay_rate_pose_graph``: the same without a back end;
- ``endpoint``: the same pipeline with the endpoint (likelihood-field) model in the front
  end and the loop search, no back end (and no grazing cut of the map's free length:
  the model has no free-space term);
- ``icp_gtsam``: the classical baseline (:func:`lidarjax.slam.icp_pose_graph_slam`, GICP
  scan-to-submap registration and a GTSAM pose graph with loop closures; needs
  ``lidarjax[slam]``);
- ``odometry``: the raw odometry;
- ``reference_back_end`` (not in the default list): the alternating back end started at
  the corrected poses, with the same odometry factors. Its distance from them is how far
  the back end's objective puts its own optimum from the reference.

Per log and variant: absolute trajectory error after SE(2) alignment (RMSE, mean; m),
relative pose error per ``rpe_delta_m`` of path (translation RMSE m, rotation RMSE deg),
map quality (p_ref RMSE, Sec. 9.5.1, of the ML grid of the aligned estimate against the
grid of the corrected poses, over cells both observe; both grids trace the readings to
``back_end.range_cap_m``, the back end's map), the front end's scans per second and
real-time factor (scans/s over the log's scan rate, where the log's timestamps give one),
and wall times per stage. Two reference-free consistency scores, for every variant and for
the corrected poses themselves (row "reference (corrected poses)"): the mean and median
cross-visit end-point distance and the share of end points it covers
(:func:`lidarjax.metrics.cross_visit_distance`: each end point to the nearest one of a
scan at least ``loops.min_separation`` scans away, up to 0.3 m) and the decay-rate
log-likelihood per ray on the trajectory's own ML grid, averaged over 8 rigid motions of
the grid (:func:`lidarjax.slam.trajectory_log_likelihood`). They say how far the corrected poses
can referee: where an estimate is more consistent than the reference, ATE against the
reference no longer ranks it. The decay-rate front end runs once per log and is shared by the
three decay-rate variants (so are its loop closures and pose graph).

Several drift seeds (``seeds=[0,1,2,3,4,5]``) run every log and variant once per seed;
``results.json`` then has each seed's results under ``by_seed`` and ``seed_summary``
(per log and variant: the ATE RMSE per seed, its mean, median and worst), and
``results.md`` ends with that summary. Round-off and the drift seed move single runs by
as much as the systems differ (docs/results/slam.md), so rank systems over several seeds.

A variant that raises (an ``Exception``; a ``KeyboardInterrupt`` still stops the run) does
not stop the others: it is recorded under the log's ``failed`` (``results.json``:
``logs.<log>.failed.<variant> = {"error": "<type>: <message>", "traceback": "..."}``, in
each seed's ``logs`` where several seeds run; ``{}`` when none failed), a line on stderr
names the log, seed, variant and error, and the other variants and logs run and are
scored and written as usual. The shared decay-rate front end (with its loops and pose
graph) is one unit: if it raises, every decay-rate variant fails with its error; each
back end, ``reference_back_end``, ``endpoint``, ``icp_gtsam`` and the scoring of each
estimate are units of their own. ``results.md`` has a row per failed variant (its
error's first line, no scores); the seed summary lists ``failed`` for its seeds and
computes mean, median and worst over the seeds that succeeded (``n_succeeded``; ``None``
where none did). A failure outside the variants (loading the log, re-simulating it, its
reference grid, the reference's consistency) is recorded as ``failed.log`` and counts as
a failure of every variant of that log for that seed; one in the figures as
``failed.figures``. After everything is written, the run exits with a non-zero status
(``SystemExit``) listing the failures.

Writes ``results.json``, ``results.md``, the trajectories in TUM format
(``<log>_<variant>.tum`` and ``<log>_ground_truth.tum``; the timestamps are scan indices,
since some logs' are constant or not monotone), ``trajectories.png`` (map and
trajectories of ``figure_log`` against the ground truth) and ``errors.png`` (position
error over the scans), both of the first seed. E.g. ``python experiments/slam.py
logs=[intel] max_scans=120``.
"""

from __future__ import annotations

import dataclasses
import sys
import time
import traceback

import hydra
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from _common import fmt, output_dir, run_info, save_figure, write_results  # noqa: E402
from _schemas import validate  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

from lidarjax import slam  # noqa: E402
from lidarjax.datasets import fetch, load_carmen, write_tum  # noqa: E402
from lidarjax.maps import decay_rate_map  # noqa: E402
from lidarjax.metrics import (  # noqa: E402
    absolute_trajectory_error,
    cross_visit_distance,
    p_ref_rmse,
    relative_pose_error,
)
from lidarjax.rays import from_scan  # noqa: E402
from lidarjax.raytrace import GridSpec, accumulate  # noqa: E402
from lidarjax.sim import resimulate_scans, wheel_odometry  # noqa: E402


def _grid(poses, ranges, az, spec, cap):
    """ML decay-rate grid and observed-cell mask of the scans at ``poses``."""
    rays = from_scan(slam._front_end.se2(poses), az, ranges, 0.0, cap)
    st = accumulate(spec, rays)
    return np.asarray(decay_rate_map(st, unknown_rate=0.0).rates), np.asarray(st.lengths) > 0


def _consistency(poses, ranges, az, back, min_separation) -> dict:
    """Reference-free scores: cross-visit end-point distances and the decay-rate
    log-likelihood per ray on the trajectory's own ML grid."""
    c = cross_visit_distance(
        poses, ranges, az, min_separation=min_separation, max_range_m=back.range_cap_m
    )
    return {
        "cross_visit_mean_m": c.mean_m,
        "cross_visit_median_m": c.median_m,
        "cross_visit_fraction": c.fraction,
        "log_likelihood_per_ray": slam.trajectory_log_likelihood(poses, az, ranges, back),
    }


def _scores(est, gt, ranges, az, spec, gt_map, cfg, back) -> dict:
    a = absolute_trajectory_error(est, gt)
    r = relative_pose_error(est, gt, delta_m=cfg.rpe_delta_m)
    rates, seen = _grid(a.aligned, ranges, az, spec, back.range_cap_m)
    mask = seen & gt_map[1]
    return {
        "ate_rmse_m": a.rmse_m,
        "ate_mean_m": a.mean_m,
        "ate_max_m": a.max_m,
        "rpe_trans_rmse_m": r.rmse_m,
        "rpe_rot_rmse_deg": float(np.rad2deg(r.rotation_rmse_rad)),
        "p_ref_rmse": float(p_ref_rmse(rates, gt_map[0], mask)),
        "errors_m": a.errors_m,
        **_consistency(est, ranges, az, back, cfg.loops.min_separation),
    }


def _scan_rate(stamps) -> float | None:
    dt = np.diff(np.asarray(stamps, float))
    if dt.size == 0 or not np.all(dt > 0):
        return None
    return float(dt.size / (stamps[-1] - stamps[0]))


OFF_XY_M, OFF_YAW_RAD = 0.3, 0.05
"""An increment of the front end this far from the reference's (m, or rad) is a failure."""


def _error_budget(base, odo, gt, scfg) -> dict:
    """What limits the decay-rate pose graph: its ATE (m) re-solved with one input taken
    from the corrected poses: the loop closures' relative poses, the front end's
    increments, or only its failed increments (off by more than ``OFF_XY_M`` or
    ``OFF_YAW_RAD``), and the median errors of the increments and loops (m). Further
    front ends' chains (``pose_graph.extra_chain_models``) stay as run. The reference's
    own errors make these lower bounds, not estimates."""
    between, compose = slam._front_end.between_np, slam._front_end.compose_np
    fe, loops, rv = base.front_end_poses, base.loops, base.revisits

    def ate(front_poses, lp=loops):
        pg = slam.front_end_pose_graph(
            front_poses,
            odo,
            lp,
            scfg,
            rv if scfg.uses_revisits else None,
            base.extra_front_end_poses,
            base.extra_chain_valid or None,  # icp and gicp chains: rejected registrations stay out
        )
        return absolute_trajectory_error(np.asarray(pg.poses), gt).rmse_m

    def rechain(inc):
        out = [fe[0]]
        for d in inc:
            out.append(compose(out[-1], d))
        return np.array(out)

    inc_ref, inc_fe = between(gt[:-1], gt[1:]), between(fe[:-1], fe[1:])
    e = between(inc_ref, inc_fe)
    off = (np.hypot(e[:, 0], e[:, 1]) > OFF_XY_M) | (np.abs(e[:, 2]) > OFF_YAW_RAD)
    edges = np.asarray(loops.edges).reshape(-1, 2)
    ref_loops = slam.Loops(edges, between(gt[edges[:, 0]], gt[edges[:, 1]]), loops.n_tried)
    le = between(ref_loops.measurements, np.asarray(loops.measurements).reshape(-1, 3))
    return {
        "pose_graph_m": ate(fe),
        "reference_loops_m": ate(fe, ref_loops) if len(edges) else None,
        "reference_increments_m": ate(rechain(inc_ref)),
        "reference_off_increments_m": ate(rechain(np.where(off[:, None], inc_ref, inc_fe))),
        "n_off_increments": int(off.sum()),
        "increment_error_median_m": float(np.median(np.hypot(e[:, 0], e[:, 1]))),
        "loop_error_median_m": float(np.median(np.hypot(le[:, 0], le[:, 1])))
        if len(edges)
        else None,
    }


def _failure(name, seed, variants, e) -> dict:
    """The record of ``variants`` failed with ``e`` (call it in the ``except`` block: it
    keeps the traceback), after one line on stderr naming them."""
    error = f"{type(e).__name__}: {e}"
    print(
        f"slam: {name}, seed {seed}: {', '.join(variants)} failed: {error.splitlines()[0]}",
        file=sys.stderr,
        flush=True,
    )
    return {"error": error, "traceback": traceback.format_exc()}


def _run_log(cfg, name, seed, out, front, loops, back, multi):
    """Every variant on one log from the drift seed's odometry: ``(results of the log,
    the figures' arguments)``. Writes the TUM files
    ``<log>_<variant>.tum`` (``<log>_<variant>_seed<seed>.tum`` where several seeds run).
    A variant that raises an ``Exception`` is recorded in the results' ``failed`` (module
    docstring) and the others go on."""
    o = cfg.odometry
    log = load_carmen(fetch(name), azimuth_layout=cfg.azimuth_layout)
    n = log.n_scans if cfg.max_scans is None else min(cfg.max_scans, log.n_scans)
    gt = log.poses[:n]
    ranges = np.minimum(log.ranges_m[:n], log.max_range_m)
    az = log.azimuths_rad
    usable = log.usable_range_m
    if cfg.front_end.range_cap_m is None:  # the log's own (slam.auto_range_cap)
        front = front.with_range_cap(slam.auto_range_cap(ranges, usable))
    resim = None
    if cfg.resimulate.enabled:
        # the log's own surfaces at the corrected poses, cast again from them: the
        # corrected poses become exact, so their own errors leave the scores
        r = cfg.resimulate
        rs = resimulate_scans(
            ranges,
            az,
            gt,
            max_range_m=front.range_cap_m,
            cell_m=r.cell_m,
            link_m=r.link_m,
            noise_sigma_m=r.noise_sigma_m,
            footprint_m=r.footprint_m,
            seed=seed,
        )
        cut = (ranges < front.range_cap_m) & (rs.ranges_m < ranges - 0.3)
        resim = {
            "cell_m": r.cell_m,
            "link_m": r.link_m,
            "noise_sigma_m": r.noise_sigma_m,
            "footprint_m": r.footprint_m,
            "n_segments": rs.n_segments,
            "min_range_m": float(rs.ranges_m.min()),
            "share_returns": float((rs.ranges_m < front.range_cap_m).mean()),
            "share_cut_short_0p3m": float(cut.mean()),
        }
        ranges, usable = rs.ranges_m, front.range_cap_m
    odo = wheel_odometry(
        gt,
        seed=seed,
        sigma_trans_rel=o.sigma_trans_rel,
        sigma_rot_per_m=float(np.deg2rad(o.sigma_rot_per_m_deg)),
        heading_bias_per_m=float(np.deg2rad(o.heading_bias_per_m_deg)),
        sigma_rot_per_rad=o.sigma_rot_per_rad,
    )
    res = cfg.map_resolution_m
    lo = np.floor((gt[:, :2].min(0) - back.range_cap_m) / res) - 2
    hi = np.ceil((gt[:, :2].max(0) + back.range_cap_m) / res) + 2
    spec = GridSpec(lo * res, res, tuple(int(v) for v in hi - lo))
    gt_map = _grid(gt, ranges, az, spec, back.range_cap_m)
    rate = _scan_rate(log.timestamps_s[:n])
    est: dict[str, np.ndarray] = {"odometry": odo}
    info: dict[str, dict] = {"odometry": {}}
    failed: dict[str, dict] = {}  # variant -> {"error", "traceback"}
    want = set(cfg.variants)
    edges = np.stack([np.arange(n - 1), np.arange(1, n)], 1)
    inc = slam._front_end.between_np(odo[:-1], odo[1:])
    sig = slam.odometry_sigmas(inc, front)
    dr = [
        v
        for v in ("decay_rate_joint", "decay_rate_alternating", "decay_rate_pose_graph")
        if v in want
    ]
    scfg = slam.SlamConfig(
        front=front,
        loops=loops,
        back=back,
        back_end="none",
        robust_chain=cfg.pose_graph.robust_chain,
        revisits=cfg.pose_graph.revisits,
        loop_rounds=cfg.loops.rounds,
        calibrate_odometry=cfg.pose_graph.calibrate_odometry,
        extra_chain_models=None
        if cfg.pose_graph.extra_chain_models is None
        else tuple(cfg.pose_graph.extra_chain_models),
        short_loop_separation=cfg.loops.short_separation,
    )
    if dr:
        # the front end, loops and pose graph once; each back end from the pose graph
        try:
            base = slam.run_slam(ranges, az, odo, scfg, progress=True)
            fe_rate = n / base.seconds["front_end"]
            common = {
                "front_end_scans_per_s": fe_rate,
                "front_end_rtf": None if rate is None else fe_rate / rate,
                "n_loops": int(len(base.loops.edges)),
                "n_revisits": int(len(base.revisits.edges)),
                "n_short_loops": base.n_short_loops,  # of n_loops (loops.short_separation)
                "seconds_short_loops": base.seconds["short_loops"],
                # what the final pose graph took for outliers (weight below
                # slam.REJECTED_WEIGHT): loop closures, and each front end's increments
                "loops_rejected": int(np.sum(base.loop_weights < slam.REJECTED_WEIGHT)),
                "increments_rejected": {
                    m: int(np.sum(row < slam.REJECTED_WEIGHT))
                    for m, row in zip((front.model, *scfg.chain_models), base.chain_weights)
                },
                "seconds_front_end": base.seconds["front_end"],
                "seconds_loops": base.seconds["loops"],
                "seconds_pose_graph": base.seconds["pose_graph"],
                "front_end_ate_rmse_m": absolute_trajectory_error(base.front_end_poses, gt).rmse_m,
                # the pose graph's odometry: the raw one without its systematic heading
                # errors (pose_graph.calibrate_odometry)
                "odometry_calibration": None
                if base.odometry_calibration is None
                else dataclasses.asdict(base.odometry_calibration),
                "error_budget": _error_budget(base, base.odometry, gt, scfg),
                # further front ends (pose_graph.extra_chain_models): their own ATE, and
                # the pose graph without them on the same loops, for comparison
                "extra_chain_models": list(scfg.chain_models),
                "seconds_extra_front_ends": base.seconds["extra_front_ends"],
                "extra_front_end_ate_rmse_m": [
                    absolute_trajectory_error(p, gt).rmse_m for p in base.extra_front_end_poses
                ],
                "pose_graph_one_chain_ate_rmse_m": None
                if not base.extra_front_end_poses
                else absolute_trajectory_error(
                    np.asarray(
                        slam.front_end_pose_graph(
                            base.front_end_poses,
                            base.odometry,
                            base.loops,
                            scfg,
                            base.revisits if scfg.uses_revisits else None,
                        ).poses
                    ),
                    gt,
                ).rmse_m,
            }
            # the back ends' odometry factors: the pose graph's odometry
            b_inc = slam._front_end.between_np(base.odometry[:-1], base.odometry[1:])
            b_sig = slam.odometry_sigmas(b_inc, front)
        except Exception as e:  # every decay-rate variant needs it
            failed.update(dict.fromkeys(dr, _failure(name, seed, dr, e)))
            dr = []
        for v in dr:
            t = time.perf_counter()
            try:
                if v == "decay_rate_pose_graph":
                    poses, extra = base.pose_graph_poses, {}
                else:
                    f = slam.optimize_joint if v.endswith("joint") else slam.optimize_alternating
                    b = f(base.pose_graph_poses, az, ranges, edges, b_inc, b_sig, back)
                    poses = b.poses
                    extra = {
                        "seconds_back_end": b.seconds,
                        "back_end_seconds_per_iteration": b.seconds_per_iteration,
                        "objective_nats": b.objective,
                    }
            except Exception as e:
                failed[v] = _failure(name, seed, [v], e)
                continue
            est[v] = poses
            info[v] = {**common, **extra, "seconds_variant": time.perf_counter() - t}
    if "reference_back_end" in want:
        t = time.perf_counter()
        try:
            b = slam.optimize_alternating(gt, az, ranges, edges, inc, sig, back)
            info["reference_back_end"] = {
                "seconds_back_end": b.seconds,
                "back_end_seconds_per_iteration": b.seconds_per_iteration,
                "objective_nats": b.objective,
                "seconds_variant": time.perf_counter() - t,
            }
            est["reference_back_end"] = b.poses  # last: only a complete variant is scored
        except Exception as e:
            failed["reference_back_end"] = _failure(name, seed, ["reference_back_end"], e)
    if "endpoint" in want:
        # the endpoint model has no free-space term: its map keeps every ray's free
        # length whatever grazing_cells says (slam.grid_map)
        ep_front = dataclasses.replace(front, model="endpoint")
        try:
            # a baseline: the endpoint model alone (no further chain)
            ep_cfg = dataclasses.replace(scfg, front=ep_front, extra_chain_models=())
            ep = slam.run_slam(ranges, az, odo, ep_cfg, progress=True)
            info["endpoint"] = {
                "n_loops": int(len(ep.loops.edges)),
                "n_revisits": int(len(ep.revisits.edges)),
                "front_end_scans_per_s": n / ep.seconds["front_end"],
                "seconds": sum(ep.seconds.values()),
            }
            est["endpoint"] = ep.poses
        except Exception as e:
            failed["endpoint"] = _failure(name, seed, ["endpoint"], e)
    if "icp_gtsam" in want:
        t = time.perf_counter()
        try:
            ic = slam.icp_pose_graph_slam(ranges, az, odo, max_range_m=usable)
            info["icp_gtsam"] = {"n_loops": int(len(ic.loops)), "seconds": time.perf_counter() - t}
            est["icp_gtsam"] = ic.poses
        except Exception as e:
            failed["icp_gtsam"] = _failure(name, seed, ["icp_gtsam"], e)
    per = {}
    traj = {}
    tag = f"_seed{seed}" if multi else ""
    write_tum(out / f"{name}_ground_truth.tum", np.arange(n, dtype=float), gt)
    for v, p in est.items():
        try:
            s = _scores(p, gt, ranges, az, spec, gt_map, cfg, back)
            aligned = absolute_trajectory_error(p, gt).aligned
        except Exception as e:  # the estimate is written all the same
            failed[v] = _failure(name, seed, [v], e)
        else:
            per[v] = {**{k: x for k, x in s.items() if k != "errors_m"}, **info[v]}
            traj[(name, v)] = (aligned, s["errors_m"])
        write_tum(out / f"{name}_{v}{tag}.tum", np.arange(n, dtype=float), p)
    result = {
        "n_scans": n,
        "range_cap_m": front.range_cap_m,
        "azimuth_layout": cfg.azimuth_layout,
        "resimulated": resim,
        "scan_rate_hz": rate,
        "variants": per,
        "failed": failed,
        "reference_consistency": _consistency(gt, ranges, az, back, cfg.loops.min_separation),
    }
    return result, (gt, gt_map, spec, est, traj)


@hydra.main(config_path="../configs", config_name="slam", version_base="1.3")
def main(cfg: DictConfig) -> None:
    validate(cfg, "slam")
    out = output_dir()
    front = slam.FrontEndConfig(
        resolution_m=cfg.front_end.resolution_m,
        blur_schedule_m=tuple(cfg.front_end.blur_schedule_m),
        backend=cfg.front_end.backend,
        grazing_cells=cfg.front_end.grazing_cells,
        prior_hits=cfg.front_end.prior_hits,
        prior_length_m=cfg.front_end.prior_length_m,
        local_map_scans=cfg.front_end.local_map_scans,
        dtype=cfg.front_end.dtype,
    )
    if cfg.front_end.range_cap_m is not None:  # else each log's own (_run_log)
        front = front.with_range_cap(cfg.front_end.range_cap_m)
    loops = slam.LoopConfig(
        radius_m=cfg.loops.radius_m,
        min_separation=cfg.loops.min_separation,
        every=cfg.loops.every,
        wide_search_xy_m=cfg.loops.wide_search_xy_m,
        far_radius_m=cfg.loops.far_radius_m,
        min_mean_log_likelihood=cfg.loops.min_mean_log_likelihood,
        scene_margin=cfg.loops.scene_margin,
        scene_samples=cfg.loops.scene_samples,
    )
    back = slam.BackEndConfig(
        resolution_m=cfg.front_end.resolution_m,
        range_cap_m=cfg.back_end.range_cap_m,
        max_steps=cfg.back_end.max_steps,
        rounds=cfg.back_end.rounds,
        backend=cfg.front_end.backend,
    )
    seeds = [cfg.seed] if cfg.seeds is None else [int(x) for x in cfg.seeds]
    multi = len(seeds) > 1
    results: dict = {"run_info": run_info(), "seeds": seeds, "logs": {}}
    rows = []
    ate: dict = {}  # (log, variant) -> ATE RMSE per seed (None: failed)
    failures = []  # one line per failed variant run

    def failed_row(name, seed, what, f):
        rows.append((name, seed, what, f))
        failures.append(f"{name}, seed {seed}: {what}: {f['error'].splitlines()[0]}")

    for seed in seeds:
        logs = results["logs"] if not multi else {}
        if multi:
            results.setdefault("by_seed", {})[str(seed)] = {"logs": logs}
        for name in cfg.logs:
            try:
                per, figure = _run_log(cfg, name, seed, out, front, loops, back, multi)
            except Exception as e:  # outside the variants: loading the log, its grids, ...
                f = _failure(name, seed, ["the whole log"], e)
                logs[name] = {"failed": {"log": f}}
                failed_row(name, seed, "the whole log", f)
                for v in dict.fromkeys(["odometry", *cfg.variants]):  # every variant failed
                    ate.setdefault((name, v), []).append(None)
                write_results(out, results=results, partial=True)
                continue
            logs[name] = per
            for v, r in per["variants"].items():
                rows.append((name, seed, v, r))
                ate.setdefault((name, v), []).append(r["ate_rmse_m"])
            for v, f in per["failed"].items():
                failed_row(name, seed, v, f)
                ate.setdefault((name, v), []).append(None)
            rows.append((name, seed, "reference (corrected poses)", per["reference_consistency"]))
            write_results(out, results=results, partial=True)
            if name == cfg.figure_log and seed == seeds[0]:
                try:
                    _figures(out, name, *figure)
                except Exception as e:
                    f = per["failed"]["figures"] = _failure(name, seed, ["figures"], e)
                    failed_row(name, seed, "figures", f)
                    write_results(out, results=results, partial=True)
    if multi:
        results["seed_summary"] = {
            name: {v: _seed_summary(a) for (n2, v), a in ate.items() if n2 == name}
            for name in cfg.logs
        }
    md = [
        "| log | seed | variant | ATE RMSE (m) | ATE mean (m) "
        f"| RPE/{cfg.rpe_delta_m:g} m (m, deg) | p_ref RMSE | loops (revisits) "
        "| front end scans/s (RTF) "
        "| cross-visit mean / median (mm, share) | LL per ray (nats) |",
        "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, seed, v, r in rows:
        if "error" in r:  # failed: no scores
            error = r["error"].splitlines()[0].replace("|", "\\|")
            md.append(f"| {name} | {seed} | {v} | failed: {error} |{' – |' * 7}")
            continue
        rtf = r.get("front_end_rtf")
        rv = f" ({r['n_revisits']})" if "n_revisits" in r else ""
        fe = r.get("front_end_scans_per_s")
        cons = (
            f"{fmt(r['cross_visit_mean_m'], 1, 1e3)} / {fmt(r['cross_visit_median_m'], 1, 1e3)} "
            f"({fmt(r['cross_visit_fraction'], 0, 100)} %) | "
            f"{fmt(r['log_likelihood_per_ray'])} |"
        )
        if "ate_rmse_m" not in r:  # the reference: consistency only
            md.append(f"| {name} | {seed} | {v} | – | – | – | – | – | – | {cons}")
            continue
        md.append(
            f"| {name} | {seed} | {v} | {fmt(r['ate_rmse_m'])} | {fmt(r['ate_mean_m'])} | "
            f"{fmt(r['rpe_trans_rmse_m'])}, {fmt(r['rpe_rot_rmse_deg'], 2)} | "
            f"{fmt(r['p_ref_rmse'])} | {r.get('n_loops', '–')}{rv} | "
            f"{fmt(fe, 2) if fe else '–'}{f' ({rtf:.1f})' if rtf else ''} | {cons}"
        )
    budget = [
        (n, sd, r["error_budget"])
        for n, sd, v, r in rows
        if v == "decay_rate_pose_graph" and "error_budget" in r
    ]
    if budget:
        md += [
            "",
            "What limits the decay-rate pose graph: its ATE RMSE (m) re-solved with the "
            "corrected poses' loop relative poses, increments, or only the increments the "
            f"front end got wrong (off by > {OFF_XY_M:g} m or {OFF_YAW_RAD:g} rad); median "
            "errors of the front end's increments and of the loops (cm):",
            "",
            "| log | seed | pose graph | reference loops | reference increments "
            "| reference where off (n) | median error increment / loop |",
            "|---|---:|---:|---:|---:|---:|---:|",
        ]
        for n, sd, b in budget:
            md.append(
                f"| {n} | {sd} | {fmt(b['pose_graph_m'])} | {fmt(b['reference_loops_m'])} | "
                f"{fmt(b['reference_increments_m'])} | "
                f"{fmt(b['reference_off_increments_m'])} ({b['n_off_increments']}) | "
                f"{fmt(b['increment_error_median_m'], 1, 100)} / "
                f"{fmt(b['loop_error_median_m'], 1, 100)} |"
            )
    if multi:
        md += [
            "",
            f"ATE RMSE (m) over the drift seeds {seeds}:",
            "",
            "| log | variant | per seed | mean | median | worst |",
            "|---|---|---|---:|---:|---:|",
        ]
        for name, per_v in results["seed_summary"].items():
            for v, a in per_v.items():
                each = " / ".join("failed" if x is None else fmt(x) for x in a["ate_rmse_m"])
                if a["n_succeeded"] < len(seeds):
                    each += f" ({a['n_succeeded']} of {len(seeds)} seeds succeeded)"
                md.append(
                    f"| {name} | {v} | {each} | {fmt(a['mean_m'])} | {fmt(a['median_m'])} "
                    f"| {fmt(a['worst_m'])} |"
                )
    write_results(
        out,
        results=results,
        markdown="\n".join(md) + "\n",
        cfg=OmegaConf.create(OmegaConf.to_container(cfg, resolve=True)),
    )
    print("\n".join(md))
    if failures:
        raise SystemExit(
            f"slam: {len(failures)} variant run(s) failed (results.json: each log's "
            '"failed"):\n' + "\n".join(failures)
        )


def _seed_summary(a) -> dict:
    """ATE RMSE per seed (``None`` where the variant failed), and its mean, median and
    worst over the seeds that succeeded (``None`` if none did)."""
    ok = [x for x in a if x is not None]
    return {
        "ate_rmse_m": a,
        "n_succeeded": len(ok),
        "mean_m": float(np.mean(ok)) if ok else None,
        "median_m": float(np.median(ok)) if ok else None,
        "worst_m": float(np.max(ok)) if ok else None,
    }


def _figures(out, name, gt, gt_map, spec, est, traj) -> None:
    fig, ax = plt.subplots(figsize=(8, 8))
    rates = gt_map[0]
    extent = [
        float(spec.origin[0]),
        float(spec.origin[0] + spec.shape[0] * spec.resolution),
        float(spec.origin[1]),
        float(spec.origin[1] + spec.shape[1] * spec.resolution),
    ]
    ax.imshow(1 - np.exp(-rates.T), origin="lower", extent=extent, cmap="Greys", vmin=0, vmax=1)
    ax.plot(gt[:, 0], gt[:, 1], "k-", lw=1.5, label="corrected poses (ground truth)")
    drawn = [v for v in est if (name, v) in traj]  # a failed variant has none
    for v in drawn:
        a, _ = traj[(name, v)]
        ax.plot(a[:, 0], a[:, 1], lw=1, label=f"{v} (aligned)")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal")
    ax.set_title(f"{name}: map of the corrected poses (p_ref), trajectories")
    ax.legend(loc="best", fontsize=7)
    save_figure(fig, out / "trajectories.png")
    fig, ax = plt.subplots(figsize=(8, 4))
    for v in drawn:
        _, e = traj[(name, v)]
        ax.plot(e, lw=1, label=v)
    ax.set_yscale("log")
    ax.set_xlabel("scan index")
    ax.set_ylabel("position error after SE(2) alignment (m)")
    ax.set_title(f"{name}: error over time")
    ax.legend(fontsize=7)
    save_figure(fig, out / "errors.png")


if __name__ == "__main__":
    main()
