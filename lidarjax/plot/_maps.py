"""Maps as images: any grid model of :mod:`lidarjax.maps`, grid statistics, DCT maps and
any decay-rate field with a box, drawn in world coordinates (m) with a labelled colour bar
and unobserved cells masked.
"""

from __future__ import annotations

from dataclasses import dataclass

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import LogNorm, Normalize

from ..maps import (
    AbstractDecayRateField,
    BetaPosteriorMap,
    DCTMap,
    DecayRateMap,
    EndpointMap,
    GammaPosteriorMap,
    ReflectionMap,
    SmoothDecayRateField,
)
from ..raytrace import GridSpec, GridStats
from ._common import colorbar, masked_cmap, metric_axes, new_axes

__all__ = ["map_quantities", "plot_grid_stats", "plot_map"]

RATE = "decay rate λ (1/m)"
P_REF = "p_ref = 1 − exp(−λ · 1 m)"


@dataclass(frozen=True)
class _Quantity:
    label: str  # colour-bar label: quantity and unit
    log: bool  # logarithmic colour scale
    unit_range: bool  # values are probabilities: colour scale [0, 1]
    cmap: str


_QUANTITIES: dict[type, dict[str, _Quantity]] = {
    GridStats: {
        "hit_fraction": _Quantity("hit fraction H / (H + M)", False, True, "magma_r"),
        "hits": _Quantity("hits H (count)", True, False, "viridis"),
        "misses": _Quantity("misses M (count)", True, False, "viridis"),
        "lengths": _Quantity("travelled length R (m)", True, False, "viridis"),
    },
    DecayRateMap: {
        "rate": _Quantity(RATE, True, False, "magma_r"),
        "p_ref": _Quantity(P_REF, False, True, "magma_r"),
    },
    ReflectionMap: {
        "reflection_prob": _Quantity("reflection probability μ", False, True, "magma_r"),
    },
    EndpointMap: {
        "likelihood": _Quantity(
            "likelihood field z_hit · N(d; 0, σ) (1/m)", False, False, "magma_r"
        ),
        "distance": _Quantity(
            "distance d to the nearest occupied cell (m)", False, False, "viridis"
        ),
    },
    GammaPosteriorMap: {
        "mean": _Quantity("posterior mean decay rate E[λ] (1/m)", True, False, "magma_r"),
        "std": _Quantity("posterior std of the decay rate (1/m)", True, False, "viridis"),
    },
    BetaPosteriorMap: {
        "mean": _Quantity("posterior mean reflection probability E[μ]", False, True, "magma_r"),
        "std": _Quantity("posterior std of the reflection probability", False, False, "viridis"),
    },
    AbstractDecayRateField: {
        "rate": _Quantity(RATE, True, False, "magma_r"),
        "p_ref": _Quantity(P_REF, False, True, "magma_r"),
    },
}

_TITLES = {
    GridStats: "grid statistics",
    DecayRateMap: "decay-rate map",
    ReflectionMap: "reflection map",
    EndpointMap: "endpoint map (likelihood field)",
    GammaPosteriorMap: "decay-rate posterior (Gamma)",
    BetaPosteriorMap: "reflection posterior (Beta)",
    DCTMap: "DCT map",
    AbstractDecayRateField: "decay-rate field",
}


def _kind(model) -> type:
    for cls in _QUANTITIES:  # DecayRateMap before AbstractDecayRateField
        if isinstance(model, cls):
            return cls
    known = "GridStats, DecayRateMap, ReflectionMap, EndpointMap, Gamma/BetaPosteriorMap, "
    raise ValueError(
        f"model must be a grid model of lidarjax.maps ({known}DCTMap or another "
        f"AbstractDecayRateField), got {type(model).__name__}"
    )


def map_quantities(model) -> tuple[str, ...]:
    """The quantities :func:`plot_map` can draw for ``model`` (the first is the default).

    Raises:
        ValueError: ``model`` is not a map :func:`plot_map` knows.
    """
    return tuple(_QUANTITIES[_kind(model)])


@dataclass(frozen=True)
class _Image:
    values: np.ndarray  # [nx ny]
    observed: np.ndarray  # [nx ny] bool
    extent: tuple[float, float, float, float]
    quantity: _Quantity


def _slice(a, z_index: int | None) -> np.ndarray:
    a = np.asarray(a)
    return a if a.ndim == 2 else a[:, :, z_index]


def _check_grid(spec: GridSpec, z_index) -> None:
    if spec.dim == 2:
        if z_index is not None:
            raise ValueError(f"z_index must be None for a 2-D model, got {z_index!r}")
        return
    if z_index is None:
        raise ValueError(
            f"model is 3-D (grid shape {spec.shape}); pass z_index to draw one horizontal slice"
        )
    if isinstance(z_index, bool) or not isinstance(z_index, (int, np.integer)):
        raise ValueError(f"z_index must be an int, got {type(z_index).__name__}")
    if not 0 <= int(z_index) < spec.shape[2]:
        raise ValueError(f"z_index must lie in [0, {spec.shape[2]}), got {z_index}")


def _stats_observed(stats: GridStats) -> np.ndarray:
    h, m = np.asarray(stats.hits), np.asarray(stats.misses)
    return (h + m > 0) | (np.asarray(stats.lengths) > 0)


def _grid_values(model, kind: type, quantity: str) -> tuple[np.ndarray, np.ndarray | None]:
    """``(values [*shape], default observed mask or None)`` of a grid model."""
    if kind is GridStats:
        h, m = np.asarray(model.hits, float), np.asarray(model.misses, float)
        r = np.asarray(model.lengths, float)
        if quantity == "hit_fraction":
            with np.errstate(invalid="ignore", divide="ignore"):
                return np.where(h + m > 0, h / (h + m), np.nan), h + m > 0
        value = {"hits": h, "misses": m, "lengths": r}[quantity]
        return value, value > 0
    if kind is DecayRateMap:
        rates = np.asarray(model.rates, float)
        out = float(model.outside_rate)
        # decay_rate_map gives never-traversed cells outside_rate (> 0 by default)
        observed = rates != out if out > 0 else None
        return (rates if quantity == "rate" else -np.expm1(-rates)), observed
    if kind is ReflectionMap:
        probs = np.asarray(model.probs, float)
        unknown = float(model.unknown_prob)
        return probs, (probs != unknown if unknown > 0 else None)
    if kind is EndpointMap:
        if quantity == "distance":
            return np.asarray(model.distances, float), None
        return float(model.z_hit) * np.asarray(model.hit_field(), float), None
    if kind is GammaPosteriorMap:
        obs = (np.asarray(model.hits) > 0) | (np.asarray(model.lengths) > 0)
        v = model.mean() if quantity == "mean" else np.sqrt(model.variance())
        return np.asarray(v, float), obs
    # BetaPosteriorMap
    obs = np.asarray(model.hits) + np.asarray(model.misses) > 0
    v = model.mean() if quantity == "mean" else np.sqrt(model.variance())
    return np.asarray(v, float), obs


def _field_box(model, bounds) -> tuple[np.ndarray, np.ndarray]:
    """``(lower [2], upper [2])`` (m) of a field: its box, its grid, or ``bounds``."""
    if bounds is not None:
        b = np.asarray(bounds, float)
        if b.shape != (2, 2) or not np.all(np.isfinite(b)) or np.any(b[1] <= b[0]):
            raise ValueError(
                f"bounds must be ((x0, y0), (x1, y1)) with x1 > x0 and y1 > y0 (m), got {bounds!r}"
            )
        return b[0], b[1]
    if isinstance(model, SmoothDecayRateField):
        spec = model.grid.spec
        return np.asarray(spec.origin, float), np.asarray(spec.upper, float)
    lower, extent = getattr(model, "lower", None), getattr(model, "extent", None)
    if lower is None or extent is None:
        raise ValueError(
            f"model ({type(model).__name__}) has no box (lower, extent); pass bounds="
            "((x0, y0), (x1, y1)) in metres"
        )
    lo = np.asarray(lower, float)
    return lo, lo + np.asarray(extent, float)


def _field_values(model, quantity: str, resolution_m, bounds):
    if model.dim != 2:
        raise ValueError(f"model must be a 2-D field, got a {model.dim}-D {type(model).__name__}")
    lo, hi = _field_box(model, bounds)
    size = hi - lo
    if resolution_m is None:
        resolution_m = float(size.max()) / 240.0
    elif not (np.isfinite(resolution_m) and resolution_m > 0):
        raise ValueError(f"resolution_m must be finite and > 0, got {resolution_m!r}")
    n = np.maximum(np.ceil(size / resolution_m - 1e-6).astype(int), 1)
    axes = [lo[k] + (np.arange(n[k]) + 0.5) * size[k] / n[k] for k in range(2)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)  # [nx ny 2]
    rates = np.asarray(model.decay_rate(pts.reshape(-1, 2)), float).reshape(n)
    values = rates if quantity == "rate" else -np.expm1(-rates)
    return values, (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))


def _observed_mask(observed, shape: tuple[int, ...], z_index) -> np.ndarray:
    if isinstance(observed, GridStats):
        if tuple(observed.spec.shape) != tuple(shape):
            raise ValueError(
                f"observed: GridStats of shape {observed.spec.shape}, the map has {shape}"
            )
        return _slice(_stats_observed(observed), z_index)
    mask = np.asarray(observed)
    if mask.dtype != bool:
        raise ValueError(f"observed must be a bool mask, a GridStats or None, got {mask.dtype}")
    if mask.shape == tuple(shape):
        return _slice(mask, z_index)
    if mask.shape == tuple(shape[:2]):
        return mask
    raise ValueError(f"observed must have the map's shape {shape}, got {mask.shape}")


def _map_image(model, quantity, observed, z_index, resolution_m, bounds) -> _Image:
    kind = _kind(model)
    table = _QUANTITIES[kind]
    quantity = next(iter(table)) if quantity is None else quantity
    if quantity not in table:
        raise ValueError(
            f"quantity must be one of {list(table)} for a {type(model).__name__}, got {quantity!r}"
        )
    q = table[quantity]
    if kind is AbstractDecayRateField:
        if z_index is not None:
            raise ValueError("z_index applies to 3-D grid models only")
        values, extent = _field_values(model, quantity, resolution_m, bounds)
        shape = values.shape
        auto = None
    else:
        spec = model.spec
        _check_grid(spec, z_index)
        extent = spec.extent()
        full, auto = _grid_values(model, kind, quantity)
        shape = tuple(spec.shape)
        values = _slice(full, z_index)
        auto = None if auto is None else _slice(auto, z_index)
    if observed is None:
        mask = auto
    elif observed is False:
        mask = None
    else:
        mask = _observed_mask(observed, shape, z_index)
    if mask is None:
        mask = np.ones(values.shape, bool)
    return _Image(values, mask & np.isfinite(values), tuple(float(e) for e in extent), q)


def _norm(img: _Image, vmin, vmax):
    v = img.values[img.observed]
    if img.quantity.unit_range and not img.quantity.log:
        lo, hi = 0.0, 1.0
    elif v.size:
        lo, hi = float(v.min()), float(v.max())
    else:
        lo, hi = 0.0, 1.0
    if img.quantity.log:  # robust top: a cell a ray barely entered can have a huge rate
        pos = v[v > 0]
        hi = float(np.percentile(pos, 99.0)) if pos.size else 1.0
        lo = max(float(pos.min()), 1e-3 * hi) if pos.size else 1e-3 * hi
    lo = lo if vmin is None else float(vmin)
    hi = hi if vmax is None else float(vmax)
    if hi <= lo:  # a constant image
        hi = 10.0 * lo if img.quantity.log and lo > 0 else lo + 1.0
    if img.quantity.log:
        if lo <= 0:
            raise ValueError(f"vmin must be > 0 on the logarithmic scale, got {lo}")
        return LogNorm(vmin=lo, vmax=hi, clip=False)
    return Normalize(vmin=lo, vmax=hi)


def plot_map(
    model,
    *,
    ax=None,
    quantity: str | None = None,
    title: str | None = None,
    cmap=None,
    observed=None,
    z_index: int | None = None,
    resolution_m: float | None = None,
    bounds=None,
    vmin: float | None = None,
    vmax: float | None = None,
    colorbar_label: str | None = None,
    show_colorbar: bool = True,
):
    """Draw a map in world coordinates (m) with a labelled colour bar.

    What is drawn per model (``quantity``; the first is the default):

    - :class:`~lidarjax.maps.DecayRateMap`: ``"rate"`` λ (1/m, logarithmic scale; zero rates
      take the lowest colour) or ``"p_ref"`` = 1 − exp(−λ · 1 m).
    - :class:`~lidarjax.maps.ReflectionMap`: ``"reflection_prob"`` μ per cell.
    - :class:`~lidarjax.maps.EndpointMap`: ``"likelihood"``, the hit term
      ``z_hit N(d; 0, σ)`` of the likelihood field (1/m), or ``"distance"`` d (m).
    - :class:`~lidarjax.maps.GammaPosteriorMap`: ``"mean"`` E[λ] (1/m, log) or ``"std"``.
    - :class:`~lidarjax.maps.BetaPosteriorMap`: ``"mean"`` E[μ] or ``"std"``.
    - :class:`~lidarjax.raytrace.GridStats`: ``"hit_fraction"`` H / (H + M), ``"hits"``,
      ``"misses"`` or ``"lengths"`` R (m).
    - a :class:`~lidarjax.maps.DCTMap` or any other 2-D
      :class:`~lidarjax.maps.AbstractDecayRateField`: ``"rate"`` or ``"p_ref"``, evaluated
      at the centres of a regular raster over its box (``lower``/``extent``, the grid of a
      :class:`~lidarjax.maps.SmoothDecayRateField`, or ``bounds``).

    Unobserved cells are masked (grey), not drawn as 0: by default the cells without data
    of statistics and posteriors, and the cells a ML map filled with its unknown value
    (``outside_rate`` / ``unknown_prob`` when that is > 0, as :func:`decay_rate_map` and
    :func:`reflection_map` do by default). Pass ``observed`` to choose them.

    Args:
        model: the map (see above); 3-D grid models need ``z_index``.
        ax: the Axes to draw into; default a new figure.
        quantity: what to draw (see above; :func:`map_quantities` lists them).
        title: Axes title; default the kind of map.
        cmap: colour map (name or object); default per quantity.
        observed: cells to show: a bool mask of the grid's shape, a
            :class:`~lidarjax.raytrace.GridStats` (cells some ray reached), ``False`` (all
            cells), or ``None`` (the model's default, above).
        z_index: the horizontal slice of a 3-D grid model.
        resolution_m: raster cell size (m) for fields (default: the longer box side / 240).
        bounds: ``((x0, y0), (x1, y1))`` (m), the raster box of a field without a box.
        vmin, vmax: colour scale limits (default: the observed values' range; [0, 1] for
            probabilities; on a log scale the 99th percentile of the positive values and
            ``max(smallest positive, 1e-3 vmax)``; values beyond take the end colours).
        colorbar_label: overrides the colour bar's label.
        show_colorbar: draw the colour bar.

    Returns:
        The matplotlib ``Axes``.

    Raises:
        ValueError: an unknown model or quantity (naming ``model`` / ``quantity``), a 3-D
            model without ``z_index``, a mask of the wrong shape, bad limits.
    """
    img = _map_image(model, quantity, observed, z_index, resolution_m, bounds)
    ax = new_axes(ax)
    q = img.quantity
    norm = _norm(img, vmin, vmax)
    values = img.values
    if q.log:  # zeros (free space) take the lowest colour instead of vanishing
        values = np.maximum(values, norm.vmin)
    data = np.ma.masked_array(values, mask=~img.observed)
    im = ax.imshow(
        data.T,
        origin="lower",
        extent=img.extent,
        cmap=masked_cmap(cmap or q.cmap),
        norm=norm,
        interpolation="nearest",
    )
    if show_colorbar:
        colorbar(im, ax, colorbar_label or q.label, extend="both" if q.log else "neither")
    ax.set_xlim(img.extent[0], img.extent[1])
    ax.set_ylim(img.extent[2], img.extent[3])
    metric_axes(ax)
    ax.set_title(_TITLES[_kind(model)] if title is None else title)
    if isinstance(model, DCTMap) and title is None:
        ax.set_title(f"DCT map ({model.shape[0]} × {model.shape[1]} coefficients)")
    return ax


def plot_grid_stats(
    stats: GridStats,
    *,
    segments: np.ndarray | None = None,
    poses: np.ndarray | None = None,
    title: str = "",
):
    """Three panels of a 2-D :class:`GridStats`: hits ``H``, travelled length ``R`` and the
    hit fraction ``H / (H + M)`` (cells without data masked), optionally with ground-truth
    wall segments ``[k 2 2]`` (m) and sensor poses ``[s 3]`` overlaid.

    Returns:
        The matplotlib ``Figure``.

    Raises:
        ValueError: ``stats`` is not a 2-D :class:`GridStats`.
    """
    if not isinstance(stats, GridStats):
        raise ValueError(f"stats must be a GridStats, got {type(stats).__name__}")
    if stats.spec.dim != 2:
        raise ValueError(f"stats must be on a 2-D grid, got {stats.spec.dim}-D")
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.8), layout="constrained")
    for ax, quantity in zip(axes, ("hits", "lengths", "hit_fraction")):
        plot_map(stats, ax=ax, quantity=quantity, cmap="viridis")
        ax.set_title(_QUANTITIES[GridStats][quantity].label)
        if segments is not None:
            for (x0, y0), (x1, y1) in np.asarray(segments, float):
                ax.plot([x0, x1], [y0, y1], color="tab:red", lw=0.6, alpha=0.7)
        if poses is not None:
            p = np.asarray(poses, float)
            ax.plot(p[:, 0], p[:, 1], color="white", lw=0.8, alpha=0.8)
    if title:
        fig.suptitle(title)
    return fig
