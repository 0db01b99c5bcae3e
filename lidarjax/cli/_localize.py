"""``lidarjax localize``: the particle filter of :mod:`lidarjax.localization` on a log, in
a map written by ``lidarjax map``."""

from __future__ import annotations

import json
import math

import numpy as np

from ._inputs import CliInputError, load_log, out_dir, parse_floats, parse_scans
from ._map import load_map, scan_ranges

__all__ = ["cmd_localize", "wrap_angle"]

MOTION_SIGMA = (0.02, 0.02, 0.01)
"""Motion model: constant std per step (m, m, rad)."""
MOTION_ALPHA = ((0.1, 0.0, 0.0), (0.0, 0.1, 0.0), (0.05, 0.0, 0.1))
"""Motion model: std per metre / radian moved."""
RAY_FLOOR = -10.0
"""Per-ray log-likelihood floor (nats): one bad beam cannot veto a particle."""


def wrap_angle(a):
    """Angles wrapped into ``[-pi, pi)`` (rad)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _initial_pose(value: str, loaded, first: int) -> np.ndarray:
    log = loaded.log
    if value == "gt":
        if not loaded.has_ground_truth:
            raise CliInputError("--init", "LOG has no ground-truth poses; give odom or x,y,theta")
        return np.asarray(log.poses[first], float)
    if value == "odom":
        pose = np.asarray(log.odometry[first], float)
        if not np.all(np.isfinite(pose)):
            raise CliInputError("--init", f"LOG has no odometry pose at scan {first}")
        return pose
    return parse_floats(value, 3, "--init")


def _stamps(log, idx) -> tuple[np.ndarray, str]:
    """Time stamps (s) of the scans ``idx``, or the scan indices when the log's stamps
    are not strictly increasing (some CARMEN logs have constant stamps)."""
    t = np.asarray(log.timestamps_s, float)[idx]
    if t.size and np.all(np.isfinite(t)) and np.all(np.diff(t) > 0):
        return t, "s"
    return np.asarray(idx, float), "scan"


def cmd_localize(args) -> int:
    import lidarjax

    lidarjax.enable_compilation_cache()
    import jax
    import jaxlie
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from tqdm import tqdm

    from .. import localization as loc
    from ..datasets import write_kitti_poses, write_tum

    if args.particles < 1:
        raise CliInputError("--particles", f"must be >= 1, got {args.particles}")
    if args.beams < 1:
        raise CliInputError("--beams", f"must be >= 1, got {args.beams}")
    if args.chunk < 1:
        raise CliInputError("--chunk", f"must be >= 1, got {args.chunk}")
    std = parse_floats(args.init_std, 3, "--init-std")
    if np.any(std < 0):
        raise CliInputError("--init-std", f"must be >= 0, got {args.init_std}")
    model_name, model, stats, meta = load_map(args.map)
    loaded = load_log(args.log, topic=args.topic, azimuth_layout=args.azimuth_layout)
    log = loaded.log
    if loaded.note:
        print(f"note: {loaded.note}")
    map_layout = meta.get("azimuth_layout")
    if map_layout and loaded.azimuth_layout and map_layout != loaded.azimuth_layout:
        print(
            f"note: MAP was built with the {map_layout} azimuth layout, LOG is read with the "
            f"{loaded.azimuth_layout} layout (--azimuth-layout)"
        )
    idx = parse_scans(args.scans, log.n_scans)
    if idx.size < 2:
        raise CliInputError("--scans", "select at least 2 scans (one filter step)")
    odo = np.asarray(log.odometry, float)[idx]
    if not np.all(np.isfinite(odo)):
        raise CliInputError("LOG", "the selected scans need odometry poses (finite)")
    mean = _initial_pose(args.init, loaded, int(idx[0]))
    out = out_dir(args.out)

    r_min, r_max = float(meta.get("r_min_m", 0.1)), float(meta.get("r_max_m", log.usable_range_m))
    n_beams = log.n_beams
    beams = np.unique(np.round(np.linspace(0, n_beams - 1, min(args.beams, n_beams))).astype(int))
    az = np.asarray(log.azimuths_rad, float)[beams]
    z = np.clip(scan_ranges(log, r_max)[idx[1:]][:, beams], 0.0, r_max)
    controls = np.asarray(loc.relative_motion(odo), float)
    motion = loc.OdometryMotionModel(
        sigma=list(MOTION_SIGMA), alpha=[list(a) for a in MOTION_ALPHA]
    )
    scan_model = loc.ScanModel(model, az, r_min, r_max, ray_floor=RAY_FLOOR)
    pf = loc.ParticleFilter(motion, scan_model)
    state = loc.init_gaussian(int(args.particles), mean, std, key=jax.random.key(int(args.seed)))
    n_dev = len(jax.devices())
    if n_dev > 1:  # e.g. --host-devices: the same results, the scans measured per device
        if args.particles % n_dev == 0:
            state = loc.shard_state(state)
            print(f"particles split over {n_dev} devices")
        else:
            print(f"note: {args.particles} particles not split over the {n_dev} devices "
                  f"(use a multiple of {n_dev})")  # fmt: skip

    n_steps = len(controls)
    est, degenerate = [], 0
    with tqdm(total=n_steps, unit="step", desc="localizing", disable=args.no_progress) as bar:
        for s in range(0, n_steps, args.chunk):  # each run continues from the last state
            state, info = pf.run(state, controls[s : s + args.chunk], z[s : s + args.chunk])
            est.append(np.asarray(loc.to_vector(info.estimate), float))
            degenerate += int(np.asarray(info.degenerate).sum())
            bar.update(len(est[-1]))
    est = np.concatenate(est)  # [T 3] after the scans idx[1:]

    stamps, unit = _stamps(log, idx[1:])
    T = jaxlie.SE2.from_xy_theta(est[:, 0], est[:, 1], est[:, 2])
    write_tum(out / "trajectory.tum", stamps, T)
    write_kitti_poses(out / "trajectory_kitti.txt", T)
    print(
        f"localized {n_steps} steps of {loaded.source} in the {model_name} map with "
        f"{args.particles} particles, {len(beams)} beams per scan"
        + (f" ({degenerate} degenerate steps)" if degenerate else "")
    )
    print(f"  {out / 'trajectory.tum'}\n  {out / 'trajectory_kitti.txt'}")
    if loaded.has_ground_truth:
        gt = np.asarray(log.poses, float)[idx[1:]]
        pos = np.linalg.norm(est[:, :2] - gt[:, :2], axis=1)
        head = np.abs(wrap_angle(est[:, 2] - gt[:, 2]))
        ate = float(np.sqrt(np.mean(pos**2)))
        t = stamps - stamps[0]
        fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 5), sharex=True, layout="constrained")
        a1.plot(t, pos, color="tab:blue")
        a1.set_ylabel("position error (m)")
        a1.set_title(
            f"{loaded.source}: {model_name} map, {args.particles} particles, ATE {ate:.3f} m"
        )
        a2.plot(t, np.degrees(head), color="tab:red")
        a2.set_ylabel("heading error (deg)")
        a2.set_xlabel("time since the first step (s)" if unit == "s" else "scan index")
        for a in (a1, a2):
            a.grid(alpha=0.3)
            a.set_ylim(bottom=0)
        fig.savefig(out / "errors.png", dpi=120)
        plt.close(fig)
        summary = {
            "ate_m": ate,
            "final_pos_err_m": float(pos[-1]),
            "mean_pos_err_m": float(pos.mean()),
            "mean_head_err_deg": float(np.degrees(head.mean())),
            "max_pos_err_m": float(pos.max()),
            "steps": int(n_steps),
            "degenerate_steps": degenerate,
            "time_unit": unit,
            "azimuth_layout": loaded.azimuth_layout,
            "pos_err_m": pos.tolist(),
            "head_err_deg": np.degrees(head).tolist(),
        }
        (out / "errors.json").write_text(json.dumps(summary, indent=1))
        print(
            f"ATE (RMSE of the position error, no alignment): {ate:.3f} m; final "
            f"{pos[-1]:.3f} m, mean heading error {math.degrees(head.mean()):.2f} deg"
        )
        print(f"  {out / 'errors.png'}\n  {out / 'errors.json'}")
    else:
        print("no ground truth in LOG: no errors.png, no ATE")
    return 0
