"""``lidarjax polylines``, ``lidarjax planes`` and ``lidarjax poles``."""

from __future__ import annotations

import json

import numpy as np

from ._inputs import CliInputError, load_log, out_dir, parse_floats, parse_scans, require_file

__all__ = ["cmd_planes", "cmd_poles", "cmd_polylines", "read_cloud"]


def _agg():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


# ---------------------------------------------------------------- point clouds
def read_cloud(value: str, argument: str, *, with_cloud: bool = False):
    """The x, y, z of a PCD or PLY file as float64 ``[H W 3]`` (``H = 1`` for an
    unorganized cloud), and the format (``"pcd"`` or ``"ply"``); with ``with_cloud`` also
    the :class:`~lidarjax.datasets.PointCloud` itself."""
    from ..datasets import DatasetFormatError, read_pcd, read_ply

    path = require_file(value, argument)
    suffix = path.suffix.lower()
    if suffix not in (".pcd", ".ply"):
        raise CliInputError(argument, f"expected a .pcd or .ply file, got {value}")
    try:
        cloud = (read_pcd if suffix == ".pcd" else read_ply)(path)
    except (DatasetFormatError, ValueError, OSError, EOFError) as e:
        raise CliInputError(argument, " ".join(str(e).split())) from None
    missing = [f for f in "xyz" if f not in cloud.fields]
    if missing:
        raise CliInputError(argument, f"{value} has no field(s) {', '.join(missing)}")
    pts = np.stack([np.asarray(cloud.fields[f], float) for f in "xyz"], axis=-1)
    pts = pts.reshape(cloud.height, cloud.width, 3)
    return (pts, suffix[1:], cloud) if with_cloud else (pts, suffix[1:])


def _organise(pts: np.ndarray, cloud, sensor: str, columns: int) -> np.ndarray:
    """``[H W 3]`` spinning-lidar scan organised by beam (the cloud's ``ring`` field, else
    the nearest nominal elevation of ``sensor``) and azimuth column."""
    from ..datasets import beam_elevations, organise_scan

    if columns < 8:
        raise CliInputError("--columns", f"must be >= 8, got {columns}")
    rings = cloud.fields.get("ring")
    try:
        res = organise_scan(
            pts.reshape(-1, 3),
            elevations_rad=beam_elevations(sensor),
            n_columns=int(columns),
            rings=None if rings is None else np.asarray(rings).reshape(-1).astype(np.int64),
        )
    except ValueError as e:
        raise CliInputError("--organise", " ".join(str(e).split())) from None
    c = res.cloud
    print(
        f"organised {pts[..., 0].size} points into {c.height} x {c.width} ({sensor} beams"
        f"{', ring field' if rings is not None else ''}): {res.n_dropped} off every beam, "
        f"{res.n_collisions} in taken cells, {res.n_invalid} invalid"
    )
    return np.stack([np.asarray(c.fields[f], float) for f in "xyz"], axis=-1)


# ---------------------------------------------------------------- polylines
def cmd_polylines(args) -> int:
    import lidarjax

    lidarjax.enable_compilation_cache()
    import jaxlie

    plt = _agg()
    from .. import features, metrics
    from ..datasets import write_polylines_csv, write_polylines_svg
    from ..plot import plot_polyline_scan
    from ..rays import HIT, from_scan
    from ._map import R_MIN_M, scan_ranges

    if args.J < 2:
        raise CliInputError("--J", f"must be >= 2 (one segment), got {args.J}")
    loaded = load_log(args.log, topic=args.topic, azimuth_layout=args.azimuth_layout)
    log = loaded.log
    s = int(parse_scans(str(args.scan), log.n_scans, "--scan")[0])
    out = out_dir(args.out)
    r_max = float(log.usable_range_m)
    ranges = scan_ranges(log, r_max)[s]
    az = np.asarray(log.azimuths_rad, float)
    scan = from_scan(jaxlie.SE2.identity(), az, ranges, R_MIN_M, r_max)
    result = features.extract_polylines(scan, max_vertices=int(args.J))
    name = "PLE"
    if args.plus:
        result = features.optimize_polylines(result, scan)
        name = "PLE+"
    polylines, closed = result.map.to_polylines()
    reflected = np.asarray(scan.kind) == HIT
    expected = np.asarray(result.map.expected_ranges(scan), float)
    rmse = metrics.ray_rmse(ranges, expected, reflected)
    frac = metrics.explained_fraction(expected, reflected) if reflected.any() else float("nan")
    ends = ranges[:, None] * np.stack([np.cos(az), np.sin(az)], -1)  # sensor frame (m)
    # a closed polygon is written with its first vertex repeated at the end
    rows = [np.vstack([p, p[:1]]) if c else p for p, c in zip(polylines, closed)]
    write_polylines_csv(out / "polylines.csv", rows)
    write_polylines_svg(out / "polylines.svg", rows, scan_points=ends[reflected])
    ax = plot_polyline_scan(
        None, np.zeros(2), ends, reflected, result, title=f"{name}, {loaded.source} scan {s}"
    )
    ax.figure.savefig(out / "polylines.png", dpi=150, bbox_inches="tight")
    plt.close(ax.figure)
    n_vertices = sum(len(p) for p in polylines)
    summary = {
        "source": loaded.source,
        "azimuth_layout": loaded.azimuth_layout,  # None for a bag (its own angles)
        "scan": s,
        "method": name,
        "J": n_vertices,
        "n_polylines": len(polylines),
        "closed": [bool(c) for c in closed],
        "rmse_m": rmse,
        "explained_fraction": frac,
    }
    (out / "polylines.json").write_text(json.dumps(summary, indent=2))
    print(
        f"{name} on scan {s} of {loaded.source}: {len(polylines)} polylines, J = {n_vertices} "
        f"vertices, RMSE {rmse * 1000:.1f} mm, {frac:.1%} of the reflected rays explained"
    )
    for f in ("polylines.csv", "polylines.svg", "polylines.png", "polylines.json"):
        print(f"  {out / f}")
    return 0


# ---------------------------------------------------------------- planes
def cmd_planes(args) -> int:
    import lidarjax

    lidarjax.enable_compilation_cache()
    plt = _agg()
    from .. import features
    from ..datasets import write_labelled_cloud
    from ..plot import plot_planes

    if not args.max_distance > 0:
        raise CliInputError("--max-distance", f"must be > 0, got {args.max_distance}")
    if args.min_points < 4:
        raise CliInputError("--min-points", f"must be >= 4, got {args.min_points}")
    pts, fmt, cloud = read_cloud(args.cloud, "CLOUD", with_cloud=True)
    if args.shape is not None and args.organise is not None:
        raise CliInputError("--organise", "give --shape or --organise, not both")
    if args.organise is not None:
        if pts.shape[0] > 1:
            raise CliInputError("--organise", f"{args.cloud} is organized already")
        pts = _organise(pts, cloud, args.organise, args.columns)
    elif args.shape is not None:
        h, w = args.shape
        if h < 2 or w < 2 or h * w != pts.shape[0] * pts.shape[1]:
            raise CliInputError(
                "--shape", f"{h} x {w} does not hold the cloud's {pts[..., 0].size} points"
            )
        pts = pts.reshape(h, w, 3)
    if pts.shape[0] < 2 or pts.shape[1] < 2:
        raise CliInputError(
            "CLOUD",
            f"PPE needs an organized scan (rows x columns of rays); {args.cloud} is "
            f"{pts.shape[0]} x {pts.shape[1]}: give --shape H W if its points are in scan "
            "order, or --organise SENSOR for a spinning lidar's cloud",
        )
    if not np.isfinite(pts).all(axis=-1).any():
        raise CliInputError("CLOUD", f"{args.cloud} has no finite point")
    out = out_dir(args.out)
    seg = features.extract_planes(
        pts, max_distance_m=float(args.max_distance), min_points=int(args.min_points)
    )
    labels = np.asarray(seg.labels)
    cloud_path = out / f"labelled.{fmt}"
    write_labelled_cloud(cloud_path, pts, labels + 1)  # 0: no plane, plane j: j + 1
    fig = plot_planes(pts, seg)
    fig.savefig(out / "planes.png", dpi=130, bbox_inches="tight")
    plt.close(fig)
    normals = np.asarray(seg.normals, float)
    supports = np.asarray(seg.supports, float)
    planes = [
        {
            "label": j,
            "points": int(seg.sizes[j]),
            "normal": normals[j].round(6).tolist(),
            "distance_m": float(np.linalg.norm(supports[j])),
            "error_m2": float(seg.errors[j]),
        }
        for j in range(len(normals))
    ]
    valid = int(np.isfinite(pts).all(axis=-1).sum())
    on = int((labels >= 0).sum())
    summary = {
        "cloud": str(args.cloud),
        "shape": list(labels.shape),
        "valid_points": valid,
        "points_on_planes": on,
        "n_planes": len(planes),
        "stop": str(seg.stop),
        "planes": planes,
    }
    (out / "planes.json").write_text(json.dumps(summary, indent=2))
    h, w = labels.shape
    print(
        f"PPE on {args.cloud} ({h} x {w}, {valid} valid points): {len(planes)} planes of >= "
        f"{args.min_points} points cover {on} points ({on / max(valid, 1):.1%})"
    )
    for p in sorted(planes, key=lambda p: -p["points"])[:10]:
        n = ", ".join(f"{v:+.3f}" for v in p["normal"])
        print(
            f"  plane {p['label']:>3}: {p['points']:>6} points, normal ({n}), "
            f"{p['distance_m']:.2f} m away, error {p['error_m2']:.2e} m^2"
        )
    if len(planes) > 10:
        print(f"  ... and {len(planes) - 10} more (planes.json)")
    for f in (cloud_path.name, "planes.png", "planes.json"):
        print(f"  {out / f}")
    return 0


# ---------------------------------------------------------------- poles
def _poles_sim(args):
    """Rays of a simulated drive along KITTI-00 (poses ``--scans``), its local map, the
    true poles and the poses."""
    import jaxlie

    from .. import features
    from ..datasets import DataChecksumError, DataNotFoundError, load_urban_trajectory
    from ..rays import from_spinning_scan
    from ..sim import hdl32e, make_urban_world, simulate_urban_scan

    if args.azimuths < 16:
        raise CliInputError("--azimuths", f"must be >= 16, got {args.azimuths}")
    try:
        gt_all = np.asarray(load_urban_trajectory().xy_yaw, float)
    except (DataNotFoundError, DataChecksumError) as e:
        raise CliInputError("SOURCE", "sim needs the KITTI-00 poses: " + " ".join(str(e).split()))
    idx = parse_scans(args.scans, len(gt_all))
    if idx.size > 20:
        raise CliInputError("--scans", f"at most 20 poses per local map, got {idx.size}")
    lo, hi = max(0, int(idx.min()) - 60), min(len(gt_all), int(idx.max()) + 61)
    world = make_urban_world(gt_all[lo:hi], seed=int(args.seed))
    lidar = hdl32e(n_azimuths=int(args.azimuths))
    gt = gt_all[idx]
    ranges = np.stack(
        [simulate_urban_scan(world, p, lidar, seed=int(args.seed) + int(i)).ranges_m
         for i, p in zip(idx, gt)]
    )  # fmt: skip
    T = jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.from_z_radians(gt[:, 2]),
        np.column_stack([gt[:, :2], np.full(len(gt), lidar.mount_height_m)]),
    )
    rays = from_spinning_scan(T, lidar.directions(), ranges, lidar.min_range_m, lidar.max_range_m)
    cfg = features.PoleConfig()
    center = gt[len(gt) // 2, :2]
    spec = features.local_map_spec(center, cfg)
    return rays, spec, cfg, world.pole_xy, gt


def _poles_cloud(args):
    import jaxlie

    from .. import features
    from ..rays import from_points

    pts, _ = read_cloud(args.source, "SOURCE")
    pts = pts.reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) == 0:
        raise CliInputError("SOURCE", f"{args.source} has no finite point")
    sensor = parse_floats(args.sensor, 3, "--sensor")
    T = jaxlie.SE3.from_translation(sensor)
    rel = pts - sensor
    r_max = float(np.linalg.norm(rel, axis=1).max()) + 1.0
    rays = from_points(T, rel, 0.0, r_max)
    cfg = features.PoleConfig()
    spec = features.local_map_spec(sensor[:2], cfg, ground_z_m=float(args.ground_z))
    return rays, spec, cfg, None, sensor[None]


def cmd_poles(args) -> int:
    import lidarjax

    lidarjax.enable_compilation_cache()
    plt = _agg()
    from .. import features
    from ..plot import plot_poles

    is_sim = args.source == "sim"
    if is_sim:
        rays, spec, cfg, truth_all, poses = _poles_sim(args)
    else:
        rays, spec, cfg, truth_all, poses = _poles_cloud(args)
    out = out_dir(args.out)
    poles = features.extract_poles(rays, spec, cfg)
    lo = np.asarray(spec.origin, float)[:2]
    hi = lo + np.asarray(spec.shape[:2]) * float(spec.resolution)
    summary = {
        "source": "simulated urban drive along KITTI-00" if is_sim else str(args.source),
        "local_map_origin_m": np.asarray(spec.origin).tolist(),
        "local_map_extent_m": (np.asarray(spec.shape) * float(spec.resolution)).tolist(),
        "n_poles": len(poles),
    }
    truth = None
    if truth_all is not None:
        inside = np.all((truth_all >= lo) & (truth_all < hi), axis=1)
        truth = truth_all[inside]
        if len(poles) and len(truth):
            d = np.linalg.norm(poles.xy[:, None] - truth[None], axis=-1)
            matched = int((d.min(axis=1) < 0.5).sum())
            found = int((d.min(axis=0) < 0.5).sum())
        else:
            matched = found = 0
        summary.update(
            scans=args.scans,
            seed=args.seed,
            true_poles_in_map=len(truth),
            extracted_within_0_5m_of_a_true_pole=matched,
            true_poles_found_within_0_5m=found,
        )
    with open(out / "poles.csv", "w") as f:
        f.write("x_m,y_m,width_m,score,z_bottom_m,z_top_m\n")
        for (x, y), w, s, (z0, z1) in zip(poles.xy, poles.width_m, poles.score, poles.z_range_m):
            f.write(f"{x:.4f},{y:.4f},{w:.3f},{s:.4f},{z0:.3f},{z1:.3f}\n")
    ax = plot_poles(poles, poses=poses if len(poses) > 1 else None, truth=truth)
    if len(poses) == 1:
        ax.plot(*poses[0, :2], "k^", ms=7, label="sensor")
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    known = "" if truth is None else f" ({len(truth)} true poles: x)"
    ax.set_title(f"{len(poles)} poles{known}")
    ax.figure.savefig(out / "poles.png", dpi=130, bbox_inches="tight")
    plt.close(ax.figure)
    summary["poles"] = [
        {"x_m": float(x), "y_m": float(y), "width_m": float(w), "score": float(s)}
        for (x, y), w, s in zip(poles.xy, poles.width_m, poles.score)
    ]
    (out / "poles.json").write_text(json.dumps(summary, indent=2))
    print(f"{len(poles)} poles in the local map around {summary['source']}")
    if truth is not None:
        print(
            f"  {summary['true_poles_found_within_0_5m']} of the {len(truth)} true poles in the "
            f"local map found within 0.5 m; {summary['extracted_within_0_5m_of_a_true_pole']} "
            f"of the {len(poles)} extracted poles are within 0.5 m of a true pole"
        )
    for f in ("poles.csv", "poles.png", "poles.json"):
        print(f"  {out / f}")
    return 0
