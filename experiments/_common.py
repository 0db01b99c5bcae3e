"""What the experiments share: the process setup (JAX's persistent compilation cache, the
host device count of ``$LIDARJAX_HOST_DEVICES``), the output folder and its files, table
formatting, and the CARMEN protocol of chapters 7 and 8 (maps from the even-numbered
scans at their corrected poses, evaluation on the odd-numbered scans) with the five grid
models built from it.

Every experiment calls :func:`setup` before its first JAX computation, directly or through
:func:`output_dir` (the first thing each Hydra entry point does after validating its
config), so a second run loads its compiled programs instead of compiling them again.

Sweeps (``python experiments/<name>.py -m ...``, any Hydra launcher): every job writes into
``outputs/sweeps/<name>/<override string>`` (the ``hydra.sweep`` keys of each config), and
:func:`completed_job`, called by the entry points right after :func:`output_dir`, skips a
job whose folder already holds the complete ``results.json`` of an earlier run of it, so a
rerun of an interrupted sweep only computes the missing jobs. A single run always computes.

Library code never imports this module; it knows Hydra configs.
"""

from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

import lidarjax
from lidarjax import maps
from lidarjax._runtime import cpu_info
from lidarjax.distributed import HOST_DEVICES_ENV, host_devices_from_env, use_host_devices
from lidarjax.rays import HIT, RayBatch, from_scan
from lidarjax.raytrace import GridSpec, GridStats, accumulate

__all__ = [
    "GRID_MODELS",
    "INCOMPLETE",
    "completed_job",
    "covering_grid",
    "even_odd_scans",
    "fmt",
    "grid_model",
    "is_complete",
    "mapping_stats",
    "mark_complete",
    "output_dir",
    "run_info",
    "save_figure",
    "scan_rays",
    "setup",
    "write_results",
]

GRID_MODELS = ("dec", "ref", "end", "fmp_dec", "fmp_ref")
"""The five grid models: decay rate, reflection, endpoint (ch. 7), and the full map
posteriors of the decay-rate (Gamma) and reflection (Beta) models (ch. 8)."""

MISSING = "–"  # a table cell without a value

INCOMPLETE = ".incomplete"
"""Marker file of a sweep job that started and has not finished (see :func:`completed_job`)."""

log = logging.getLogger(__name__)


# ---------------------------------------------------------------- process setup
def setup() -> Path | None:
    """Turn on JAX's persistent compilation cache for this process and return its folder.

    :func:`lidarjax.enable_compilation_cache` with its defaults: ``$LIDARJAX_JAX_CACHE``
    (``off`` disables it) or ``~/.cache/lidarjax/jax-compilation-cache``; ``None`` when
    disabled or not writable (with a warning). Idempotent; :func:`output_dir` calls it.

    With ``$LIDARJAX_HOST_DEVICES=N`` (``lidarjax --host-devices N experiment ...`` sets
    it), first exposes the CPU as ``N`` JAX devices
    (:func:`lidarjax.distributed.use_host_devices`; raises ``RuntimeError`` if JAX already
    started with another count).
    """
    n = host_devices_from_env()
    if n is not None:
        try:
            use_host_devices(n)
        except RuntimeError as e:
            raise RuntimeError(f"${HOST_DEVICES_ENV}={n}: {e}") from None
    return lidarjax.enable_compilation_cache()


# ---------------------------------------------------------------- output folder and files
def output_dir() -> Path:
    """Hydra's output folder of the running experiment (created if needed).

    Also calls :func:`setup` (the compilation cache), since every Hydra entry point asks
    for its folder before its first JAX computation.
    """
    setup()
    out = Path(HydraConfig.get().runtime.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    return out


def run_info() -> dict:
    """Provenance written beside every result: versions, dtype, machine and its load."""
    return {
        "lidarjax_version": lidarjax.__version__,
        "jax_version": jax.__version__,
        "dtype": str(jnp.result_type(float)),
        "cpu_count": os.cpu_count(),
        **cpu_info(),  # the SLAM front end's trajectories depend on the CPU
        "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
    }


def _plain(value):
    """NumPy / JAX scalars and arrays as JSON values (``json.dumps`` ``default``)."""
    if isinstance(value, np.generic | np.ndarray | jax.Array):
        return np.asarray(value).tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"results hold a {type(value).__name__}, which JSON cannot store")


def write_results(
    out: Path,
    *,
    results: dict | None = None,
    markdown: str | None = None,
    cfg: DictConfig | None = None,
    allow_nan: bool = True,
    partial: bool = False,
) -> None:
    """Write ``results.md``, ``config.yaml`` and ``results.json`` (each when given) to ``out``.

    ``results.json`` is written last and atomically (a temporary file renamed onto it), so
    it is never half written.

    Args:
        out: the output folder.
        results: JSON-able results (NumPy scalars and arrays are converted).
        markdown: the Markdown tables.
        cfg: the resolved experiment config, saved as ``config.yaml``.
        allow_nan: ``False`` refuses NaN / inf in ``results`` (strict JSON).
        partial: ``True`` for a snapshot of a run still going (results after every log);
            ``False`` (default) also marks a sweep job complete (:func:`mark_complete`).
    """
    if markdown is not None:
        (out / "results.md").write_text(markdown)
    if cfg is not None:
        (out / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    if results is not None:
        text = json.dumps(results, indent=2, default=_plain, allow_nan=allow_nan)
        tmp = out / ".results.json.tmp"
        tmp.write_text(text)
        os.replace(tmp, out / "results.json")
    if not partial:
        mark_complete(out)


# ---------------------------------------------------------------- sweeps: resuming jobs
def is_complete(out: Path) -> bool:
    """Whether the folder ``out`` holds the results of a finished run: a ``results.json``
    that parses, and no :data:`INCOMPLETE` marker (which :func:`completed_job` puts into a
    sweep job's folder when the job starts and :func:`mark_complete` removes at its end)."""
    out = Path(out)
    if (out / INCOMPLETE).exists():
        return False
    try:
        json.loads((out / "results.json").read_text())
    except (OSError, ValueError):
        return False
    return True


def completed_job(out: Path) -> dict | None:
    """Resume a sweep: the stored results of this job if an earlier run of it finished.

    In a Hydra multirun (``-m``): when the job's folder ``out`` is complete
    (:func:`is_complete`), logs one line saying the job is skipped and returns the stored
    ``results.json``; the entry point returns it at once, without recomputing. Otherwise
    (no ``results.json``, or an interrupted run) marks ``out`` as :data:`INCOMPLETE` and
    returns ``None``: the job runs, and its final :func:`write_results` (or
    :func:`mark_complete`) marks it complete. In a single run: ``None``, nothing written
    (a single run always recomputes).

    Usage, right after :func:`output_dir`::

        if (done := completed_job(out)) is not None:
            return done
    """
    if HydraConfig.get().mode != RunMode.MULTIRUN:
        return None
    out = Path(out)
    if is_complete(out):
        log.info(f"skipping job {out.name!r}: {out / 'results.json'} is complete "
                 "(delete it to run the job again)")  # fmt: skip
        return json.loads((out / "results.json").read_text())
    (out / INCOMPLETE).write_text(
        "this job started and has not finished (experiments/_common.py)\n"
    )
    return None


def mark_complete(out: Path) -> None:
    """Mark the sweep job in ``out`` as finished (removes the :data:`INCOMPLETE` marker;
    no-op outside sweeps). For entry points whose last :func:`write_results` is ``partial``."""
    (Path(out) / INCOMPLETE).unlink(missing_ok=True)


def save_figure(fig, path: Path, dpi: int = 120) -> None:
    """Save a Matplotlib figure (tight bounding box) and close it."""
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=dpi, bbox_inches="tight")
    plt.close(fig)


def fmt(x, digits: int = 3, scale: float = 1.0) -> str:
    """``x * scale`` with ``digits`` decimals; ``–`` for ``None`` and non-finite values."""
    if x is None or not math.isfinite(float(x)):
        return MISSING
    return f"{float(x) * scale:.{digits}f}"


# ---------------------------------------------------------------- the CARMEN protocol
def even_odd_scans(n_scans: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the even-numbered (mapping) and odd-numbered (evaluation) scans."""
    return np.arange(0, n_scans, 2), np.arange(1, n_scans, 2)


def scan_rays(log, idx: np.ndarray | None, r_min: float, r_max: float) -> RayBatch:
    """Rays ``[s b]`` of the scans ``idx`` (all when ``None``) of a CARMEN log at their
    corrected poses; ranges outside ``[r_min, r_max]`` (m) are classified SUB / SUP."""
    idx = np.arange(log.n_scans) if idx is None else np.asarray(idx)
    p = log.poses[idx]
    return from_scan(
        jaxlie.SE2.from_xy_theta(p[:, 0], p[:, 1], p[:, 2]),
        log.azimuths_rad,
        log.ranges_m[idx],
        r_min,
        r_max,
    )


def covering_grid(log, r_max: float, resolution_m: float, margin_m: float) -> GridSpec:
    """A grid covering every in-range end point of every scan (even and odd) and every pose,
    plus ``margin_m`` (m) on each side."""
    th = log.poses[:, 2:3] + log.azimuths_rad
    ends = log.poses[:, None, :2] + log.ranges_m[..., None] * np.stack([np.cos(th), np.sin(th)], -1)
    pts = np.concatenate([ends[log.ranges_m < r_max], log.poses[:, :2]])
    return GridSpec.covering(pts, float(resolution_m), margin=float(margin_m))


def mapping_stats(
    log,
    cfg: DictConfig,
    r_min: float,
    r_max: float,
    *,
    stride: int = 1,
    chunk_size: int | None = None,
) -> tuple[GridStats, GridSpec, float]:
    """Grid statistics of every ``stride``-th even-numbered scan at its corrected pose.

    Args:
        log: a CARMEN log (``lidarjax.datasets.load_carmen``).
        cfg: the experiment config; reads ``grid.resolution_m``, ``grid.margin_m`` and
            ``endpoint.p_out`` (a probability or ``auto``).
        r_min, r_max: the sensor's range limits (m).
        stride: use every ``stride``-th even scan.
        chunk_size: rays per chunk of :func:`lidarjax.raytrace.accumulate` (``None``: its
            default).

    Returns:
        ``(stats, spec, p_out)``: the statistics, their grid, and the endpoint model's
        out-of-range probability (``auto``: the share of non-HIT mapping rays, clipped to
        ``[1e-3, 0.5]``).
    """
    even, _ = even_odd_scans(log.n_scans)
    rays = scan_rays(log, even[:: int(stride)], r_min, r_max)
    spec = covering_grid(log, r_max, cfg.grid.resolution_m, cfg.grid.margin_m)
    kw = {} if chunk_size is None else {"chunk_size": int(chunk_size)}
    stats = jax.block_until_ready(accumulate(spec, rays, **kw))
    p_out = cfg.endpoint.p_out
    if p_out == "auto":
        p_out = float(np.clip((np.asarray(rays.kind) != HIT).mean(), 1e-3, 0.5))
    return stats, spec, float(p_out)


def grid_model(name: str, stats: GridStats, cfg: DictConfig, p_out: float):
    """One of the :data:`GRID_MODELS` from grid statistics (``cfg.endpoint`` holds the
    endpoint model's ``sigma_m``, ``z_hit`` and ``z_rand``)."""
    if name == "dec":
        return maps.decay_rate_map(stats)
    if name == "ref":
        return maps.reflection_map(stats)
    if name == "end":
        return maps.endpoint_map(
            stats,
            sigma_m=float(cfg.endpoint.sigma_m),
            z_hit=float(cfg.endpoint.z_hit),
            z_rand=float(cfg.endpoint.z_rand),
            p_out=float(p_out),
        )
    if name == "fmp_dec":
        return maps.gamma_posterior(stats)
    if name == "fmp_ref":
        return maps.beta_posterior(stats)
    raise ValueError(f"unknown grid model {name!r}; choose from {list(GRID_MODELS)}")
