"""``lidarjax map``: a grid map from a laser log or a ROS bag, and the ``map.npz`` files
``lidarjax localize`` reads back."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ._inputs import CliInputError, LoadedLog, load_log_scans, out_dir, require_file

__all__ = ["MODELS", "cmd_map", "load_map", "model_from_stats", "scan_ranges", "write_map_files"]

MODELS = ("decay-rate", "reflection", "endpoint")
MAX_CELLS = 100_000_000
"""Largest grid ``map`` builds (about 1.2 GB of statistics); coarser cells beyond."""
R_MIN_M = 0.1
"""Readings below this range (m) are SUB rays (no CARMEN log has readings below 0.12 m)."""


def scan_ranges(log, r_max: float) -> np.ndarray:
    """The log's ranges ``[s b]`` with non-finite readings (NaN, inf of a bag) set to
    ``r_max``, i.e. read as no-returns."""
    r = np.asarray(log.ranges_m, float)
    return np.where(np.isfinite(r), r, r_max)


def _positive(value: float, argument: str) -> float:
    if not (math.isfinite(value) and value > 0):
        raise CliInputError(argument, f"must be a positive number, got {value}")
    return float(value)


def model_from_stats(model: str, stats, *, sigma_m: float = 0.1, p_out: float = 0.05):
    """The sensor model's map from grid statistics (``model`` one of :data:`MODELS`)."""
    from .. import maps

    if model == "decay-rate":
        return maps.decay_rate_map(stats)
    if model == "reflection":
        return maps.reflection_map(stats)
    if model == "endpoint":
        return maps.endpoint_map(stats, sigma_m=float(sigma_m), p_out=float(p_out))
    raise ValueError(f"model must be one of {MODELS}, got {model!r}")


def _covering_spec(poses, az, ranges, r_max, resolution, margin, argument="--resolution"):
    from ..raytrace import GridSpec

    th = poses[:, 2:3] + az
    ends = poses[:, None, :2] + ranges[..., None] * np.stack([np.cos(th), np.sin(th)], -1)
    pts = np.concatenate([ends[(ranges >= R_MIN_M) & (ranges < r_max)], poses[:, :2]])
    lo, hi = pts.min(0) - margin, pts.max(0) + margin
    cells = np.prod(np.ceil((hi - lo) / resolution))
    if cells > MAX_CELLS:
        raise CliInputError(
            argument,
            f"{resolution} m cells over {hi[0] - lo[0]:.0f} m x {hi[1] - lo[1]:.0f} m are "
            f"{cells:.3g} cells (at most {MAX_CELLS:.0e}); choose coarser cells or fewer scans",
        )
    return GridSpec.covering(pts, resolution, margin=margin)


def build_stats(loaded: LoadedLog, idx, *, resolution, margin, r_max, chunk, progress):
    """Grid statistics of the scans ``idx`` at their poses, traced ``chunk`` scans at a
    time (a tqdm bar over scans). Returns ``(stats, spec, p_out)``."""
    import jax
    import jaxlie
    from tqdm import tqdm

    from ..rays import HIT, from_scan
    from ..raytrace import accumulate

    log = loaded.log
    poses = np.asarray(log.poses, float)[idx]
    if not np.all(np.isfinite(poses)):
        bad = int(idx[np.flatnonzero(~np.all(np.isfinite(poses), axis=1))[0]])
        raise CliInputError(
            "LOG", f"scan {bad} has no pose (a bag needs tf from the map or odom frame)"
        )
    az = np.asarray(log.azimuths_rad, float)
    ranges = scan_ranges(log, r_max)[idx]
    spec = _covering_spec(poses, az, ranges, r_max, resolution, margin)
    stats, n_hit, n_rays = None, 0, 0
    with tqdm(total=len(idx), unit="scan", desc="mapping", disable=not progress) as bar:
        for s in range(0, len(idx), chunk):
            p = poses[s : s + chunk]
            T = jaxlie.SE2.from_xy_theta(p[:, 0], p[:, 1], p[:, 2])
            rays = from_scan(T, az, ranges[s : s + chunk], R_MIN_M, r_max)
            part = jax.block_until_ready(accumulate(spec, rays))
            stats = part if stats is None else stats + part
            kind = np.asarray(rays.kind)
            n_hit += int((kind == HIT).sum())
            n_rays += kind.size
            bar.update(len(p))
    p_out = float(np.clip(1.0 - n_hit / max(n_rays, 1), 1e-3, 0.5))
    return stats, spec, p_out


def _short(v) -> float:
    """The shortest decimal that rounds to ``v`` in its own dtype (0.05, not the float64
    widening 0.05000000074505806 of a float32 0.05)."""
    v = np.asarray(v)
    return float(np.format_float_positional(v[()], unique=True, trim="-"))


def _occupancy(model_name: str, model, stats) -> np.ndarray:
    """ROS occupancy probabilities ``[nx ny]`` in [0, 1], NaN = unknown."""
    from .. import maps
    from ..datasets import occupancy_from_decay_rate, occupancy_from_reflection

    observed = np.asarray(stats.visited)
    res = float(stats.spec.resolution)
    if model_name == "decay-rate":
        return occupancy_from_decay_rate(np.asarray(model.rates), res, observed)
    probs = model.probs if model_name == "reflection" else maps.reflection_map(stats).probs
    return occupancy_from_reflection(np.asarray(probs), observed)


_MODEL_ARRAY = {"decay-rate": "rates", "reflection": "probs", "endpoint": "distances"}


def save_map(path: Path, model_name: str, model, stats, meta: dict) -> None:
    """``map.npz``: the statistics ``hits``, ``misses``, ``lengths`` and the model's own
    array (``rates``, ``probs`` or ``distances``), with the grid and ``meta``."""
    from ..datasets import save_grid_map

    key = _MODEL_ARRAY[model_name]
    arrays = {
        "hits": np.asarray(stats.hits),
        "misses": np.asarray(stats.misses),
        "lengths": np.asarray(stats.lengths),
        key: np.asarray(getattr(model, key)),
    }
    if model_name == "decay-rate":
        arrays["outside_rate"] = np.asarray(model.outside_rate)
    elif model_name == "reflection":
        arrays["unknown_prob"] = np.asarray(model.unknown_prob)
    save_grid_map(
        path,
        arrays,
        spec=stats.spec,
        model=model_name.replace("-", "_"),  # the library's spelling: decay_rate
        meta=meta,
    )


def write_map_files(out: Path, model_name: str, model, stats, meta: dict) -> None:
    """``map.npz`` (:func:`save_map`) and ``map.yaml`` + ``map.pgm`` (ROS map_server) in
    ``out``."""
    from ..datasets import write_map_server

    save_map(out / "map.npz", model_name, model, stats, meta)
    write_map_server(
        out / "map.yaml",
        _occupancy(model_name, model, stats),
        origin_xy=[_short(v) for v in np.asarray(stats.spec.origin)],
        resolution=_short(stats.spec.resolution),
    )


def load_map(value: str, argument: str = "MAP"):
    """Read a ``map.npz`` written by ``lidarjax map``.

    Returns:
        ``(model_name, model, stats, meta)``: the map rebuilt from its statistics.
    """
    import jax.numpy as jnp

    from ..datasets import DatasetFormatError, load_grid_map
    from ..raytrace import GridSpec, GridStats

    path = require_file(value, argument)
    try:
        gm = load_grid_map(path)
    except (DatasetFormatError, ValueError, OSError, KeyError, EOFError) as e:
        raise CliInputError(argument, " ".join(str(e).split())) from None
    arrays, meta = gm.arrays, dict(gm.meta or {})
    model_name = str(gm.model).replace("_", "-")
    missing = [k for k in ("hits", "misses", "lengths") if k not in arrays]
    if model_name not in MODELS or missing:
        raise CliInputError(
            argument,
            f"{value} is not a map written by `lidarjax map` (model {model_name!r}, "
            f"missing arrays {missing})",
        )
    shape = tuple(np.shape(arrays["hits"]))
    if len(shape) != 2 or any(np.shape(arrays[k]) != shape for k in ("misses", "lengths")):
        raise CliInputError(argument, f"{value}: hits, misses and lengths differ in shape")
    spec = GridSpec(np.asarray(gm.origin, float), float(gm.resolution), shape)
    dtype = jnp.result_type(float)
    stats = GridStats(
        spec,
        jnp.asarray(arrays["hits"], jnp.int32),
        jnp.asarray(arrays["misses"], jnp.int32),
        jnp.asarray(arrays["lengths"], dtype),
    )
    model = model_from_stats(
        model_name, stats, sigma_m=meta.get("sigma_m", 0.1), p_out=meta.get("p_out", 0.05)
    )
    return model_name, model, stats, meta


def cmd_map(args) -> int:
    import lidarjax

    lidarjax.enable_compilation_cache()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..plot import plot_map, plot_trajectory

    resolution = _positive(args.resolution, "--resolution")
    if not (math.isfinite(args.margin) and args.margin >= 0):
        raise CliInputError("--margin", f"must be >= 0, got {args.margin}")
    if args.chunk < 1:
        raise CliInputError("--chunk", f"must be >= 1, got {args.chunk}")
    sigma = _positive(args.sigma, "--sigma")
    loaded, idx = load_log_scans(args)
    log = loaded.log
    r_max = log.usable_range_m if args.max_range is None else args.max_range
    r_max = _positive(float(r_max), "--max-range")
    if r_max <= R_MIN_M:
        raise CliInputError("--max-range", f"must exceed {R_MIN_M} m, got {r_max}")
    out = out_dir(args.out)

    stats, spec, p_out = build_stats(
        loaded,
        idx,
        resolution=resolution,
        margin=float(args.margin),
        r_max=r_max,
        chunk=int(args.chunk),
        progress=not args.no_progress,
    )
    model = model_from_stats(args.model, stats, sigma_m=sigma, p_out=p_out)
    meta = {
        "source": loaded.source,
        "source_kind": loaded.kind,
        "topic": args.topic,
        "azimuth_layout": loaded.azimuth_layout,  # None for a bag (its own angles)
        "scans": args.scans or ":",
        "n_scans_used": int(len(idx)),
        "r_min_m": R_MIN_M,
        "r_max_m": r_max,
        "sigma_m": sigma,
        "p_out": p_out,
        "lidarjax_version": lidarjax.__version__,
    }
    write_map_files(out, args.model, model, stats, meta)
    ax = plot_map(model, observed=stats, title=f"{args.model} map of {loaded.source}")
    fig = ax.figure
    fig.set_size_inches(8, 8 * spec.shape[1] / max(spec.shape[0], 1) + 0.5)
    plot_trajectory(np.asarray(log.poses)[idx], ax=ax, color="tab:orange", lw=0.6)
    fig.savefig(out / "map.png", dpi=150, bbox_inches="tight")
    plt.close(fig)
    nx, ny = spec.shape
    print(
        f"{args.model} map of {loaded.source}: {len(idx)} scans, {nx} x {ny} cells of "
        f"{resolution} m ({nx * resolution:.1f} m x {ny * resolution:.1f} m), "
        f"{int(np.asarray(stats.visited).sum())} cells observed"
    )
    for f in ("map.npz", "map.yaml", "map.pgm", "map.png"):
        print(f"  {out / f}")
    return 0
