"""Pole-landmark mapping and long-term localization (dissertation ch. 12): Table 12.1 and
Table 12.2 analogues and Figures 12.1 / 12.3 on simulated urban drives along KITTI-00.

World and sensor: :func:`lidarjax.sim.make_urban_world` places street lamps, sign
posts, traffic-light poles, tree trunks (with permeable crowns), facades, cars,
pedestrians, bushes and one row of construction barrels along the real KITTI-00 trajectory
(``route.start`` .. ``route.stop``); an HDL-32E-like lidar (32 x 2170 rays, 2 cm noise) is
cast exactly against it at every ground-truth pose (10 Hz). Sessions 1 .. n-1 are the same
drive "weeks later" (:func:`lidarjax.sim.urban_session`): poles removed and added,
parked cars, pedestrians and moving cars re-sampled, and in ``sessions.barrel_session`` the
barrel row shifted sideways (the failure case of section 12.5.1). Every session has its own
drifting wheel odometry.

Table 12.1 analogue: the map is built from session 0 with ground-truth registration
(1.5 m segments, local maps of 30 x 30 x 5 m at 0.2 m, :func:`lidarjax.features.extract_poles`,
sliding window, overlap merging), then every session is localized ``localization.runs``
times with 5000 particles from a 2.5 m / +-5 deg start; local maps during localization are
registered by odometry. Errors are evaluated every 1 m along the ground truth
(:func:`lidarjax.metrics.trajectory_errors`) and averaged over the runs.

Table 12.2 analogue (Sefati et al.'s KITTI protocol): map and localize on the same 46 s of
session 0, 2000 particles, 3 m / +-5 deg, 50 runs, one row per voxel size in
``kitti_protocol.resolutions_m`` (the paper: 0.1 m). As in the authors' KITTI script, the
scans come from KITTI's sensor (an HDL-64E-like lidar with 64 rings, ``kitti_protocol.lidar``)
and the odometry is the ground-truth motion with 2 % Gaussian noise per component, which the
filter assumes without inflation (``kitti_protocol.odometry``; ``wheel`` uses the sessions'
wheel odometry and motion model instead).

Writes ``results.json``, ``results.md``, ``fig12_1_map.png``, ``fig12_3_local_map.png`` and
``errors.png`` into Hydra's output folder (``only=kitti_protocol``: the Table 12.2 part
alone, ``results.json`` and ``results.md`` only). E.g. ``python experiments/poles.py
route.stop=300 sessions.n=2 localization.runs=2 kitti_protocol.enabled=false``.
"""

from __future__ import annotations

import time
from dataclasses import replace

import hydra
import matplotlib

matplotlib.use("Agg")
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import jaxlie  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from _common import completed_job, output_dir, write_results  # noqa: E402
from _schemas import validate  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402
from tqdm import tqdm  # noqa: E402

from lidarjax.datasets import load_urban_trajectory  # noqa: E402
from lidarjax.features import PoleConfig, Poles, extract_poles, local_map_spec  # noqa: E402
from lidarjax.localization import (  # noqa: E402
    OdometryMotionModel,
    ParticleFilter,
    PoleMeasurementModel,
    init_uniform_disc,
    map_poles,
    pad_poles,
    relative_motion,
    segment_scans,
    sliding_window_filter,
    to_vector,
)
from lidarjax.metrics import trajectory_errors  # noqa: E402
from lidarjax.rays import SUB, RayBatch, from_spinning_scan  # noqa: E402
from lidarjax.sim import (  # noqa: E402
    POLE_KINDS,
    LidarSpec,
    hdl32e,
    make_urban_world,
    scan_seed,
    simulate_urban_scan,
    urban_session,
    wheel_odometry,
)

# Table 12.1 (NCLT, 27 sessions) and Table 12.2 (KITTI) of the dissertation.
PAPER_121 = {"delta_pos_m_mean": 0.284, "delta_pos_m_mean_wo_barrels": 0.200}
PAPER_122 = {
    "Ours (paper)": dict(
        delta_pos_m=0.096,
        rmse_pos_m=0.111,
        delta_lat_m=0.061,
        sigma_lat_m=0.075,
        delta_lon_m=0.060,
        sigma_lon_m=0.067,
        delta_ang_deg=0.133,
        sigma_ang_deg=0.188,
        rmse_ang_deg=0.214,
    ),
    "Sefati et al.": dict(rmse_pos_m=0.24, rmse_ang_deg=0.68),
}
# Velodyne HDL-64E S2 (KITTI's sensor): 32 lasers from +2.0 to -8.33 deg (1/3 deg apart)
# and 32 from -8.83 to -24.33 deg (1/2 deg apart).
HDL64E_ELEVATIONS_DEG = np.concatenate(
    [np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.33, 32)]
)
FIELDS_122 = (
    "delta_pos_m", "rmse_pos_m", "delta_lat_m", "sigma_lat_m", "delta_lon_m", "sigma_lon_m",
    "delta_ang_deg", "sigma_ang_deg", "rmse_ang_deg",
)  # fmt: skip


# ----------------------------------------------------------------------------- local maps


def make_rays(ranges, directions, poses, lidar, n_pad: int) -> RayBatch:
    """World-frame rays of ``len(ranges)`` scans taken at ``poses [m 3]`` (x, y, yaw),
    padded with ignored (SUB) rays to ``n_pad`` scans so every local map has one shape."""
    m, n = len(ranges), directions.shape[0]
    yaw = jaxlie.SO3.from_z_radians(jnp.asarray(poses[:, 2]))
    xyz = jnp.column_stack([jnp.asarray(poses[:, :2]), jnp.full(m, lidar.mount_height_m)])
    T = jaxlie.SE3.from_rotation_and_translation(yaw, xyz)
    rays = from_spinning_scan(T, directions, np.stack(ranges), lidar.min_range_m, lidar.max_range_m)
    rays = rays.flatten()
    pad = (n_pad - m) * n

    def cat(x, fill):
        return jnp.concatenate(
            [x, jnp.broadcast_to(jnp.asarray(fill, x.dtype), (pad, *x.shape[1:]))]
        )

    return RayBatch(
        cat(rays.origins, 0.0), cat(rays.directions, [1.0, 0.0, 0.0]), cat(rays.ranges, 0.0),
        cat(rays.kind, SUB), rays.r_min, rays.r_max,
    )  # fmt: skip


def local_maps(world, gt, reg, segments, lidar, pcfg, seed, n_pad, desc, keep=None):
    """Poles of every segment's local map, in the registration frame of ``reg``.

    Scans are simulated at the ground-truth poses ``gt`` and registered with ``reg``
    (ground truth for mapping, odometry for localization). Returns the poles per segment,
    the extraction seconds per local map (after the first, which compiles) and, for the
    segment index ``keep``, the occupancy grid and its spec (for the figure)."""
    directions = lidar.directions()
    out, secs, kept = [], [], None
    for k, seg in enumerate(tqdm(segments, desc=desc, leave=False)):
        ranges = [
            simulate_urban_scan(world, gt[i], lidar, seed=scan_seed(seed, int(i))).ranges_m
            for i in seg
        ]
        mid = seg[len(seg) // 2]
        spec = local_map_spec(reg[mid, :2], pcfg)
        rays = make_rays(ranges, directions, reg[seg], lidar, n_pad)
        t0 = time.perf_counter()
        if k == keep:
            poles, occ = extract_poles(rays, spec, pcfg, return_occupancy=True)
            kept = (np.asarray(occ), spec, seg)
        else:
            poles = extract_poles(rays, spec, pcfg)
        secs.append(time.perf_counter() - t0)
        out.append(poles)
    return out, np.asarray(secs[1:] if len(secs) > 1 else secs), kept


# ----------------------------------------------------------------------------- localization


def wheel_motion_model(inflation: float) -> OdometryMotionModel:
    """The filter's noise model of the simulated wheel odometry: 1 % of the distance,
    0.2 deg/m heading, small constants, standard deviations times ``inflation``."""
    alpha = jnp.asarray([[0.01, 0.0, 0.0], [0.0, 0.01, 0.0], [np.deg2rad(0.2), 0.0, 0.0]])
    return OdometryMotionModel([0.005, 0.005, np.deg2rad(0.05)], alpha, inflation=inflation)


def relative_odometry(gt: np.ndarray, rel_sigma: float, seed: int) -> np.ndarray:
    """Odometry of the authors' KITTI script: every ground-truth increment ``(dx, dy,
    dyaw)`` (robot frame) plus ``N(0, (rel_sigma * |component|)^2)`` per component, chained
    from the first ground-truth pose. Returns ``[N 3]`` poses."""
    gt = np.asarray(gt, float)
    rel = np.asarray(relative_motion(jnp.asarray(gt)), float)
    rng = np.random.default_rng([seed, 0x0DD])
    rel = rel + rel_sigma * np.abs(rel) * rng.standard_normal(rel.shape)
    out = np.empty_like(gt)
    out[0] = gt[0]
    for i, (dx, dy, dyaw) in enumerate(rel):
        x, y, yaw = out[i]
        c, s = np.cos(yaw), np.sin(yaw)
        out[i + 1] = (
            x + c * dx - s * dy,
            y + s * dx + c * dy,
            np.arctan2(np.sin(yaw + dyaw), np.cos(yaw + dyaw)),
        )
    return out


def run_filter(
    model, gt, odo, segs, poles_odo, lcfg, n_particles, radius_m, heading_deg, runs, seed,
    motion=None,
):  # fmt: skip
    """``runs`` particle filters (vmapped) over the whole drive; returns ``[runs T 3]``
    estimates for scans 1 .. N-1 and the seconds per filter step (all runs together).
    ``motion``: the odometry noise model (default: :func:`wheel_motion_model` with
    ``lcfg.inflation``)."""
    n = len(gt)
    per_step: list[Poles | None] = [None] * n
    filtered = sliding_window_filter(poles_odo, lcfg.c, lcfg.w)
    for seg, p in zip(segs, filtered, strict=True):
        e = int(seg[-1])
        x, y, yaw = odo[e]
        # odometry frame -> robot frame at the segment's last scan
        c, s = np.cos(yaw), np.sin(yaw)
        rel = (p.xy - [x, y]) @ np.array([[c, -s], [s, c]])
        per_step[e] = Poles(rel, p.width_m, p.score, p.z_range_m)
    xy, mask = pad_poles(per_step[1:], int(lcfg.max_online_poles))
    controls = relative_motion(jnp.asarray(odo))
    if motion is None:
        motion = wheel_motion_model(float(lcfg.inflation))
    pf = ParticleFilter(motion, model)
    h = np.deg2rad(heading_deg)

    keys = jax.random.split(jax.random.key(seed), runs)
    states = [
        init_uniform_disc(n_particles, gt[0, :2], radius_m, (gt[0, 2] - h, gt[0, 2] + h), key=k)
        for k in keys
    ]
    states = jax.tree.map(lambda *x: jnp.stack(x), *states)
    z = (jnp.asarray(xy), jnp.asarray(mask))
    updates = jnp.asarray(mask.any(1))

    def one(state):
        _, info = pf.run(state, controls, z, updates)
        return to_vector(info.estimate), info.degenerate

    run_all = jax.jit(jax.vmap(one))
    jax.block_until_ready(run_all(states))  # compile
    t0 = time.perf_counter()
    est, degenerate = jax.block_until_ready(run_all(states))
    secs = (time.perf_counter() - t0) / max(1, n - 1)
    return np.asarray(est), bool(np.any(degenerate)), secs, int(mask.any(1).sum())


def evaluate(est_runs, gt, diverged_m):
    rows = [trajectory_errors(e, gt[1:], spacing_m=1.0).as_dict() for e in est_runs]
    keys = [k for k in rows[0] if k != "n"]
    mean = {k: float(np.mean([r[k] for r in rows])) for k in keys}
    err = np.linalg.norm(est_runs[:, :, :2] - gt[None, 1:, :2], axis=-1)
    mean["diverged_fraction"] = float(np.mean(err > diverged_m))
    mean["n_eval_points"] = int(rows[0]["n"])
    return mean, err


def map_quality(pole_map, world, match_m=0.5, near_xy=None, near_m=15.0):
    """Precision, recall (within ``match_m``) and mean error of a landmark map; with
    ``near_xy`` (a drive's positions) also found / total per pole kind for the true poles
    within ``near_m`` of the drive (``near``)."""
    truth = world.pole_xy
    d = (
        np.linalg.norm(pole_map.xy[:, None] - truth[None], axis=-1)
        if len(pole_map)
        else np.zeros((0, len(truth)))
    )
    matched = d.min(1) < match_m if len(pole_map) else np.zeros(0, bool)
    found = d.min(0) < match_m if len(pole_map) else np.zeros(len(truth), bool)
    by_kind, near = {}, {}
    close = np.zeros(len(truth), bool)
    if near_xy is not None and len(truth):
        close = np.linalg.norm(truth[:, None] - np.asarray(near_xy)[None], axis=-1).min(1) < near_m
    for k, name in enumerate(POLE_KINDS):
        sel = world.pole_kind == k
        if sel.any():
            by_kind[name] = float(found[sel].mean())
        if near_xy is not None and (sel & close).any():
            near[name] = dict(found=int(found[sel & close].sum()), total=int((sel & close).sum()))
    out = {
        "n_landmarks": len(pole_map),
        "n_true_poles": len(truth),
        "precision": float(matched.mean()) if len(pole_map) else 0.0,
        "recall": float(found.mean()),
        "recall_by_kind": by_kind,
        "mean_error_m": float(d.min(1)[matched].mean()) if matched.any() else float("nan"),
    }
    if near_xy is not None:
        out["near"] = near
        out["near_m"] = float(near_m)
    return out


# ----------------------------------------------------------------------------- figures


def plot_map(path, pole_map, world, gt, est, title):
    fig, ax = plt.subplots(figsize=(8, 8))
    ax.plot(gt[:, 0], gt[:, 1], color="0.6", lw=3, label="ground truth")
    ax.plot(est[:, 0], est[:, 1], color="tab:red", lw=1, label="estimate")
    ax.scatter(
        world.pole_xy[:, 0], world.pole_xy[:, 1], s=10, marker="x", color="0.3", label="true poles"
    )
    ax.scatter(pole_map.xy[:, 0], pole_map.xy[:, 1], s=8, color="tab:blue", label="pole map")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def plot_local_map(path, occ, spec, poles, world, pcfg):
    from lidarjax.features import pole_score_image, pole_score_maps

    q = np.asarray(pole_score_maps(jnp.asarray(occ), pcfg.width_cells, pcfg.free_cells)).max(0)
    s, _, _ = pole_score_image(jnp.asarray(q), pcfg.q_min, pcfg.min_cells)
    o = np.asarray(spec.origin)
    res = float(spec.resolution)
    ext = [o[0], o[0] + occ.shape[0] * res, o[1], o[1] + occ.shape[1] * res]
    fig, axes = plt.subplots(1, 2, figsize=(13, 6.2))
    axes[0].imshow(occ.max(2).T, origin="lower", extent=ext, cmap="gray_r", vmin=0, vmax=1)
    axes[0].set_title("occupancy (max over height)")
    axes[1].imshow(np.asarray(s).T, origin="lower", extent=ext, cmap="viridis", vmin=0, vmax=1)
    axes[1].set_title("2-D pole score S, extracted poles (squares), true poles (o)")
    inside = (
        (world.pole_xy[:, 0] > ext[0]) & (world.pole_xy[:, 0] < ext[1])
        & (world.pole_xy[:, 1] > ext[2]) & (world.pole_xy[:, 1] < ext[3])
    )  # fmt: skip
    for ax in axes:
        for (x, y), w in zip(poles.xy, poles.width_m, strict=True):
            ax.add_patch(
                Rectangle((x - w / 2, y - w / 2), w, w, fill=False, color="tab:orange", lw=1.5)
            )
        for (x, y), r in zip(world.pole_xy[inside], world.pole_radius_m[inside], strict=True):
            ax.add_patch(plt.Circle((x, y), max(r, 0.15), fill=False, color="tab:red", lw=1))
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_errors(path, curves, arc):
    fig, ax = plt.subplots(figsize=(10, 4))
    for name, err in curves.items():
        ax.plot(arc[1:], err, lw=1, label=name)
    ax.set_yscale("log")
    ax.set_xlabel("distance driven [m]")
    ax.set_ylabel("position error [m] (mean over runs)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ----------------------------------------------------------------------------- tables


def table(res) -> str:
    lines = []
    if "sessions" in res:
        r, mp, loc = res["route"], res["map"], res["localization"]
        head = (
            "| Session | changes | f_map [%] | Δpos [m] | RMSE_pos [m] | Δang [°] | RMSE_ang [°] "
            "| max [m] | diverged [%] |"
        )
        lines += [
            "### Table 12.1 analogue: map from session 0, localize every session",
            "",
            f"Route: KITTI-00 poses {r['start']}..{r['stop']} ({r['length_m']:.0f} m, "
            f"{r['n_scans']} scans); {loc['runs']} runs x {loc['n_particles']} particles per "
            f"session; map: {mp['n_landmarks']} landmarks for {mp['n_true_poles']} true poles, "
            f"precision {100 * mp['precision']:.1f} %, recall {100 * mp['recall']:.1f} % "
            f"(within 0.5 m), mean error {mp['mean_error_m']:.3f} m.",
            "",
            head,
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for s in res["sessions"]:
            m = s["errors"]
            lines.append(
                f"| {s['session']} | {s['changes']} | {s['f_map'] * 100:.1f} | "
                f"{m['delta_pos_m']:.3f} | {m['rmse_pos_m']:.3f} | {m['delta_ang_deg']:.3f} | "
                f"{m['rmse_ang_deg']:.3f} | {m['max_pos_m']:.2f} | "
                f"{100 * m['diverged_fraction']:.1f} |"
            )
        agg = res["summary"]
        lines += [
            "",
            f"Mean Δpos over all sessions: {agg['delta_pos_m_mean']:.3f} m; without the barrel "
            f"session: {agg['delta_pos_m_mean_wo_barrels']:.3f} m (paper, NCLT: "
            f"{PAPER_121['delta_pos_m_mean']} / {PAPER_121['delta_pos_m_mean_wo_barrels']} m).",
        ]
    if "kitti_protocol" in res:
        k = res["kitti_protocol"]
        kinds = [n for n in POLE_KINDS if any(n in row["map"]["near"] for row in k["rows"])]
        lines += [
            "",
            "### Table 12.2 analogue: map and localize on the same 46 s drive",
            "",
            f"{k['n_scans']} scans ({k['length_m']:.0f} m), {k['runs']} runs x "
            f"{k['n_particles']} particles, lidar {k['lidar']}, odometry {k['odometry']}"
            + (f" ({100 * k['rel_sigma']:g} %)" if k["odometry"] == "relative" else "")
            + f", motion noise x{k['inflation']:g}. Found / total: true poles within "
            f"{k['rows'][0]['map']['near_m']:g} m of the drive with a landmark within 0.5 m.",
            "",
            "| Voxels [m] | landmarks | precision [%] | "
            + " | ".join(f"{n} found" for n in kinds)
            + " |",
            "|---:|---:|---:|" + "---:|" * len(kinds),
        ]
        for row in k["rows"]:
            mp = row["map"]
            cells = [
                f"{mp['near'][n]['found']} / {mp['near'][n]['total']}" if n in mp["near"] else "-"
                for n in kinds
            ]
            lines.append(
                f"| {row['resolution_m']:g} | {mp['n_landmarks']} | {100 * mp['precision']:.1f} | "
                + " | ".join(cells)
                + " |"
            )
        lines += [
            "",
            "| Approach | " + " | ".join(FIELDS_122) + " |",
            "|---|" + "---|" * len(FIELDS_122),
        ]
        rows = {f"lidarjax (simulated), {r['resolution_m']:g} m": r["errors"] for r in k["rows"]}
        rows.update(PAPER_122)
        for name, row in rows.items():
            cells = [f"{row[f]:.3f}" if f in row else "-" for f in FIELDS_122]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    if "timing" in res:
        t, loc = res["timing"], res["localization"]
        lines += [
            "",
            f"Timing: pole extraction {t['extract_s_per_local_map']:.3f} s per local map "
            f"({t['scans_per_local_map']:.2f} scans, {t['rays_per_s'] / 1e6:.2f} M rays/s); "
            f"particle filter {1e3 * t['filter_s_per_step_per_run']:.2f} ms per step and run "
            f"({loc['n_particles']} particles).",
        ]
    return "\n".join(lines).lstrip("\n") + "\n"


# ----------------------------------------------------------------------------- main


def changes_of(session: int, cfg) -> str:
    if session == 0:
        return "map session"
    if cfg.sessions.barrel_session is not None and session == cfg.sessions.barrel_session:
        return "poles ±, cars, barrel row shifted"
    return "poles ±, cars"


def kitti_protocol(cfg, gt, world0, pcfg, odometry) -> dict:
    """Table 12.2 analogue: map and localize on the same short drive, once per resolution
    in ``kitti_protocol.resolutions_m`` (see the module docstring)."""
    k, mcfg, lcfg = cfg.kitti_protocol, cfg.mapping, cfg.localization
    n_pad = int(mcfg.max_scans)
    a = int(k.start)
    sub = gt[a : a + int(k.n_scans)]
    if len(sub) < 2:
        raise ValueError(f"kitti_protocol.start/n_scans select only {len(sub)} poses of the route")
    lidar_kw = dict(
        n_azimuths=int(cfg.lidar.n_azimuths),
        max_range_m=float(cfg.lidar.max_range_m),
        range_noise_m=float(cfg.lidar.range_noise_m),
    )
    if k.lidar == "hdl64e":
        lidar = LidarSpec(np.deg2rad(HDL64E_ELEVATIONS_DEG), **lidar_kw)
    else:
        lidar = hdl32e(**lidar_kw)
    if k.odometry == "relative":
        odo_k = relative_odometry(sub, float(k.rel_sigma), int(cfg.seed) * 1000 + 12)
        rs = float(k.rel_sigma)
        motion = OdometryMotionModel(np.zeros(3), rs * np.eye(3), inflation=float(k.inflation))
    else:
        odo_k = odometry(0)[a : a + int(k.n_scans)]
        motion = wheel_motion_model(float(k.inflation))
    segs_k = segment_scans(sub[:, :2], float(mcfg.segment_m), max_scans=n_pad)
    segs_o = segment_scans(odo_k[:, :2], float(mcfg.segment_m), max_scans=n_pad)
    scan_seed0 = int(cfg.seed) * 1000 + a
    rows = []
    for res_m in k.resolutions_m:
        kcfg = replace(pcfg, resolution_m=float(res_m))  # widths from max_width_m follow
        loc_k, _, _ = local_maps(
            world0, sub, sub, segs_k, lidar, kcfg, scan_seed0, n_pad, f"kitti map {res_m} m"
        )
        map_k = map_poles(loc_k, c=int(mcfg.c), w=int(mcfg.w))
        loc_o, _, _ = local_maps(
            world0, sub, odo_k, segs_o, lidar, kcfg, scan_seed0, n_pad, f"kitti loc {res_m} m"
        )
        if len(map_k) == 0:
            raise RuntimeError(f"the Table 12.2 drive produced no landmarks at {res_m} m")
        model_k = PoleMeasurementModel(map_k.xy, var_m2=float(lcfg.var_m2), eps=float(lcfg.eps))
        est_k, _, _, n_updates = run_filter(
            model_k, sub, odo_k, segs_o, loc_o, lcfg, int(k.n_particles), float(k.radius_m),
            float(k.heading_deg), int(k.runs), int(cfg.seed) + 12, motion=motion,
        )  # fmt: skip
        err_k, _ = evaluate(est_k, sub, float(lcfg.diverged_m))
        quality = map_quality(map_k, world0, near_xy=sub[:, :2])
        rows.append(
            dict(
                resolution_m=float(res_m), widths_cells=list(kcfg.width_cells),
                free_cells=kcfg.free_cells, map=quality, errors=err_k, n_updates=n_updates,
                mean_online_poles=float(np.mean([len(p) for p in loc_o])),
            )
        )  # fmt: skip
        print(
            f"Table 12.2, {res_m} m: {len(map_k)} landmarks, Δpos {err_k['delta_pos_m']:.3f} m, "
            f"Δang {err_k['delta_ang_deg']:.3f} deg"
        )
    arc_k = np.sum(np.linalg.norm(np.diff(sub[:, :2], axis=0), axis=1))
    return dict(
        n_scans=len(sub), length_m=float(arc_k), runs=int(k.runs),
        n_particles=int(k.n_particles), lidar=str(k.lidar), n_rings=lidar.n_rings,
        odometry=str(k.odometry), rel_sigma=float(k.rel_sigma), inflation=float(k.inflation),
        rows=rows,
    )  # fmt: skip


@hydra.main(config_path="../configs", config_name="poles", version_base=None)
def main(cfg: DictConfig) -> None:
    validate(cfg, "poles")
    out = output_dir()
    if (done := completed_job(out)) is not None:  # a sweep job that already finished
        return done
    t_start = time.perf_counter()
    traj = load_urban_trajectory()
    stop = len(traj.xy_yaw) if cfg.route.stop is None else int(cfg.route.stop)
    gt = traj.xy_yaw[int(cfg.route.start) : stop]
    if len(gt) < 10:
        raise ValueError(f"route.start/stop select only {len(gt)} poses")
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(gt[:, :2], axis=0), axis=1))])
    lidar = hdl32e(
        n_azimuths=int(cfg.lidar.n_azimuths),
        max_range_m=float(cfg.lidar.max_range_m),
        range_noise_m=float(cfg.lidar.range_noise_m),
    )
    e = cfg.extractor
    pcfg = PoleConfig(
        resolution_m=float(e.resolution_m), extent_m=tuple(e.extent_m), mu_o=float(e.mu_o),
        q_min=float(e.q_min), h_min_m=float(e.h_min_m), free_m=float(e.free_m),
        max_width_m=float(e.max_width_m),
        widths=None if e.widths is None else tuple(int(a) for a in e.widths),
    )  # fmt: skip
    base = make_urban_world(gt, seed=int(cfg.seed))

    def odometry(session):
        o = cfg.odometry
        return wheel_odometry(
            gt, seed=int(cfg.seed) * 1000 + session,
            sigma_trans_rel=float(o.sigma_trans_rel),
            sigma_rot_per_m=np.deg2rad(float(o.sigma_rot_deg_per_m)),
            heading_bias_per_m=np.deg2rad(float(o.heading_bias_deg_per_m)),
        )  # fmt: skip

    def world_of(session):
        return urban_session(
            base, session, seed=int(cfg.seed), barrel_session=cfg.sessions.barrel_session,
            p_remove=float(cfg.sessions.p_remove), p_add=float(cfg.sessions.p_add),
            barrel_shift_m=float(cfg.sessions.barrel_shift_m),
        )  # fmt: skip

    world0 = world_of(0)
    res = dict(
        config=OmegaConf.to_container(cfg, resolve=True),
        route=dict(start=int(cfg.route.start), stop=stop, n_scans=len(gt), length_m=float(arc[-1])),
        world=dict(
            n_poles=int(base.n_poles), n_boxes=int(base.n_boxes), n_crowns=int(base.n_crowns)
        ),
        paper=dict(table_12_1=PAPER_121, table_12_2=PAPER_122),
    )
    if cfg.only != "kitti_protocol":
        res.update(table_12_1(cfg, out, gt, arc, lidar, pcfg, world0, world_of, odometry))
    if cfg.kitti_protocol.enabled and cfg.only != "table_12_1":
        res["kitti_protocol"] = kitti_protocol(cfg, gt, world0, pcfg, odometry)
    res["wall_s"] = time.perf_counter() - t_start
    write_results(out, results=res, markdown=table(res), cfg=cfg)
    print(table(res))


def table_12_1(cfg, out, gt, arc, lidar, pcfg, world0, world_of, odometry) -> dict:
    """Table 12.1 analogue and the figures: map from session 0 (ground-truth registration),
    localize every session; returns the ``results.json`` entries of this part."""
    mcfg, lcfg = cfg.mapping, cfg.localization
    n_pad = int(mcfg.max_scans)
    # ---- mapping (session 0, ground-truth registration)
    segs_map = segment_scans(gt[:, :2], float(mcfg.segment_m), max_scans=n_pad)
    # the figure's local map: the first one with the most scans
    keep = int(np.argmax([len(s) for s in segs_map])) if segs_map else None
    local, secs, kept = local_maps(
        world0, gt, gt, segs_map, lidar, pcfg, int(cfg.seed) * 1000, n_pad, "map", keep
    )
    pole_map = map_poles(local, c=int(mcfg.c), w=int(mcfg.w))
    if len(pole_map) == 0:
        raise RuntimeError("the mapping session produced no landmarks")
    quality = map_quality(pole_map, world0)
    extract_secs = [secs]
    scans_per_map = float(np.mean([len(s) for s in segs_map]))
    if kept is not None:
        occ, spec, _ = kept
        plot_local_map(out / "fig12_3_local_map.png", occ, spec, local[keep], world0, pcfg)

    model = PoleMeasurementModel(pole_map.xy, var_m2=float(lcfg.var_m2), eps=float(lcfg.eps))
    sessions, curves, filter_secs = [], {}, []
    fig_est = None
    for s in range(int(cfg.sessions.n)):
        world = world_of(s)
        odo = odometry(s)
        segs = segment_scans(odo[:, :2], float(mcfg.segment_m), max_scans=n_pad)
        poles_odo, secs, _ = local_maps(
            world, gt, odo, segs, lidar, pcfg, int(cfg.seed) * 1000 + s, n_pad, f"session {s}"
        )
        extract_secs.append(secs)
        est, degenerate, step_s, n_updates = run_filter(
            model, gt, odo, segs, poles_odo, lcfg, int(lcfg.n_particles), float(lcfg.radius_m),
            float(lcfg.heading_deg), int(lcfg.runs), int(cfg.seed) * 7919 + s,
        )  # fmt: skip
        filter_secs.append(step_s / int(lcfg.runs))
        errors, err = evaluate(est, gt, float(lcfg.diverged_m))
        curves[f"session {s} ({changes_of(s, cfg)})"] = err.mean(0)
        if s == int(cfg.figure_session) or fig_est is None:
            fig_est = (s, est[0])
        sessions.append(
            dict(
                session=s, changes=changes_of(s, cfg), f_map=1.0 if s == 0 else 0.0,
                errors=errors, degenerate=degenerate, n_local_maps=len(segs),
                n_updates=n_updates, mean_online_poles=float(np.mean([len(p) for p in poles_odo])),
            )
        )  # fmt: skip
        print(f"session {s}: Δpos {errors['delta_pos_m']:.3f} m, max {errors['max_pos_m']:.2f} m")

    barrel = cfg.sessions.barrel_session
    dpos = [x["errors"]["delta_pos_m"] for x in sessions]
    wo = [x["errors"]["delta_pos_m"] for x in sessions if x["session"] != barrel]
    all_secs = np.concatenate(extract_secs)
    s_fig, est_fig = fig_est
    plot_map(out / "fig12_1_map.png", pole_map, world_of(s_fig), gt, est_fig,
             f"pole map (session 0) and run 1 of session {s_fig}")  # fmt: skip
    plot_errors(out / "errors.png", curves, arc)
    return dict(
        map=quality,
        localization=dict(runs=int(lcfg.runs), n_particles=int(lcfg.n_particles)),
        sessions=sessions,
        summary=dict(
            delta_pos_m_mean=float(np.mean(dpos)), delta_pos_m_mean_wo_barrels=float(np.mean(wo))
        ),
        timing=dict(
            extract_s_per_local_map=float(np.mean(all_secs)),
            extract_s_median=float(np.median(all_secs)),
            scans_per_local_map=scans_per_map,
            rays_per_s=float(scans_per_map * lidar.n_rays / np.mean(all_secs)),
            filter_s_per_step_per_run=float(np.mean(filter_secs)),
        ),
    )


if __name__ == "__main__":
    main()
