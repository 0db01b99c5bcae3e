"""Features over their data: polylines over a 2-D scan, plane segmentations of organized
scans (label image in beams and top view in metres) and pole maps."""

from __future__ import annotations

from collections.abc import Sequence

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import to_rgb

from ..features import PlaneSegmentation, Poles
from ..localization import PoleMap
from ._common import MASKED_COLOR, colorbar, metric_axes, new_axes, pose_array
from ._localization import plot_trajectory

__all__ = ["plot_planes", "plot_poles", "plot_polyline_scan", "plot_segmentation"]


def _as_polylines(polylines, closed):
    """``(list of [m 2] arrays, closed flags)`` from vertex arrays or a polyline map /
    extraction / optimisation result (unbatched)."""
    src = getattr(polylines, "map", polylines)
    if hasattr(src, "to_polylines"):
        pls, cl = src.to_polylines()
        return [np.asarray(p, float) for p in pls], (list(cl) if closed is None else closed)
    if not isinstance(polylines, Sequence) and not isinstance(polylines, np.ndarray):
        raise ValueError(
            "polylines must be a list of [m 2] vertex arrays or a PolylineMap / "
            f"PolylineExtraction / PolylineOptimization, got {type(polylines).__name__}"
        )
    pls = [np.asarray(p, float) for p in polylines]
    for i, p in enumerate(pls):
        if p.ndim != 2 or p.shape[1] != 2:
            raise ValueError(f"polylines[{i}] must have shape [m 2], got {p.shape}")
    closed = [False] * len(pls) if closed is None else list(closed)
    if len(closed) != len(pls):
        raise ValueError(f"closed must have one flag per polyline ({len(pls)}), got {len(closed)}")
    return pls, closed


def plot_polyline_scan(
    ax,
    origin_xy: np.ndarray,
    endpoints_xy: np.ndarray,
    reflected: np.ndarray,
    polylines,
    closed: list[bool] | None = None,
    *,
    ray_stride: int = 2,
    title: str = "",
    color: str = "tab:blue",
    linestyle: str = "-",
    label: str | None = None,
    draw_scan: bool = True,
):
    """A 2-D scan with extracted polylines, like Figures 10.1 and 10.3 (x, y in m).

    Every ``ray_stride``-th reflected ray is drawn as a thin red line with its endpoint,
    no-return rays in grey, the polylines in ``color`` with their vertices.

    Args:
        ax: a matplotlib ``Axes``, or None for a new figure.
        origin_xy: ``[2]`` sensor position (m).
        endpoints_xy: ``[K 2]`` ray endpoints (m; for no-returns, the point at the reported
            range).
        reflected: ``[K]`` bool, HIT rays.
        polylines: list of ``[m 2]`` vertex arrays (m), or a
            :class:`~lidarjax.features.PolylineMap` / ``PolylineExtraction`` /
            ``PolylineOptimization`` of one scan.
        closed: per polyline, whether it is closed (default: all open, or the map's).
        ray_stride: draw every n-th ray.
        title: axes title (``J``, the number of vertices, is appended).
        color: colour of the polylines.
        linestyle: their line style.
        label: legend label of the polylines (a legend is drawn when given).
        draw_scan: draw the rays and the sensor (False: only add polylines).

    Returns:
        The matplotlib ``Axes``.

    Raises:
        ValueError: inputs of the wrong shape.
    """
    o = np.asarray(origin_xy, float)
    e = np.asarray(endpoints_xy, float)
    refl = np.asarray(reflected).astype(bool)
    if o.shape != (2,):
        raise ValueError(f"origin_xy must have shape [2], got {o.shape}")
    if e.ndim != 2 or e.shape[1] != 2:
        raise ValueError(f"endpoints_xy must have shape [K 2], got {e.shape}")
    if refl.shape != (e.shape[0],):
        raise ValueError(f"reflected must be [{e.shape[0]}] bool, got shape {refl.shape}")
    pls, closed = _as_polylines(polylines, closed)
    ax = new_axes(ax)
    if draw_scan:
        for k in range(0, len(e), max(1, int(ray_stride))):
            c = "tab:red" if refl[k] else "0.75"
            ax.plot([o[0], e[k, 0]], [o[1], e[k, 1]], color=c, lw=0.3, zorder=1)
        ax.plot(e[refl, 0], e[refl, 1], ".", color="tab:red", ms=1.5, zorder=2)
        ax.plot(*o, "ks", ms=4, zorder=4)
    for i, (pl, c) in enumerate(zip(pls, closed)):
        p = np.vstack([pl, pl[:1]]) if c else pl
        ax.plot(
            p[:, 0], p[:, 1], marker="o", ls=linestyle, color=color, lw=1.2, ms=2.5, zorder=3,
            label=label if i == 0 else None,
        )  # fmt: skip
    metric_axes(ax)
    n = sum(len(p) for p in pls)
    ax.set_title(f"{title} (J = {n})" if title else f"J = {n}", fontsize=9)
    ax.tick_params(labelsize=7)
    if label is not None:
        ax.legend(loc="best", fontsize=7, framealpha=0.8)
    return ax


def _label_colors(seed: int, n: int = 4096) -> np.ndarray:
    """``[n 3]`` seeded random RGB colours, one per label index (the same in every panel)."""
    return np.random.default_rng(seed).uniform(0.15, 1.0, (n, 3))


def _label_image(lab: np.ndarray, colors: np.ndarray, background) -> np.ndarray:
    img = np.empty(lab.shape + (3,))
    img[:] = to_rgb(background)
    on = lab >= 0
    img[on] = colors[lab[on] % len(colors)]
    return img


def _beam_axes(ax) -> None:
    ax.set_xlabel("column (beam)")
    ax.set_ylabel("row (beam)")


def plot_segmentation(
    images: dict[str, np.ndarray],
    *,
    title: str = "",
    seed: int = 0,
):
    """Label images side by side (ground truth, then methods), like Figure 11.1.

    Each region gets a random colour (the same label index the same colour in every
    panel); pixels with a negative label (unsegmented, no return) are black.

    Args:
        images: ``{panel title: [H W] int labels}``.
        title: figure title.
        seed: seed of the colour table.

    Returns:
        The matplotlib ``Figure``.
    """
    if not images:
        raise ValueError("images must not be empty")
    fig, axes = plt.subplots(1, len(images), figsize=(3.2 * len(images), 3.6), squeeze=False)
    colors = _label_colors(seed)
    for ax, (name, lab) in zip(axes[0], images.items()):
        lab = np.asarray(lab)
        if lab.ndim != 2 or not np.issubdtype(lab.dtype, np.integer):
            raise ValueError(
                f"images[{name!r}] must be a 2-D integer label image, got {lab.dtype} {lab.shape}"
            )
        ax.imshow(_label_image(lab, colors, "black"), interpolation="nearest")
        ax.set_title(name, fontsize=10)
        ax.set_xticks([])
        ax.set_yticks([])
        _beam_axes(ax)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


_VIEWS = ("both", "image", "top")


def plot_planes(
    points,
    labels,
    *,
    ax=None,
    view: str = "both",
    max_points: int = 50_000,
    seed: int = 0,
):
    """A plane segmentation of an organized scan: the label image (row / column in beams)
    and a top view of the points (x, y in m), coloured by plane; unlabelled points grey.

    Each plane gets a seeded random colour (the same in both panels and as in
    :func:`plot_segmentation`); planes are categories, so there is no colour bar.

    Args:
        points: ``[H W 3]`` organized scan (m; NaN where there is no return).
        labels: a :class:`~lidarjax.features.PlaneSegmentation` (PPE's result) or ``[H W]``
            int plane labels, negative for points on no plane.
        ax: ``view="both"``: None (new figure) or two Axes; otherwise one Axes or None.
        view: ``"both"``, ``"image"`` (label image only) or ``"top"`` (top view only).
        max_points: at most this many points in the top view (evenly subsampled).
        seed: seed of the colour table.

    Returns:
        The ``Figure`` for ``view="both"``, else the ``Axes``.

    Raises:
        ValueError: bad shapes (naming ``points`` / ``labels``), an unknown ``view``, or
            ``ax`` not matching the view.
    """
    if view not in _VIEWS:
        raise ValueError(f"view must be one of {list(_VIEWS)}, got {view!r}")
    pts = np.asarray(points, float)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise ValueError(f"points must be an organized scan [H W 3], got {pts.shape}")
    lab = np.asarray(labels.labels if isinstance(labels, PlaneSegmentation) else labels)
    if lab.shape != pts.shape[:2] or not np.issubdtype(lab.dtype, np.integer):
        raise ValueError(
            f"labels must be [H W] = {pts.shape[:2]} integers (or a PlaneSegmentation), "
            f"got {lab.dtype} {lab.shape}"
        )
    colors = _label_colors(seed)
    n_planes = len(np.unique(lab[lab >= 0]))
    fig = None
    if view == "both":
        if ax is None:
            fig, axes = plt.subplots(1, 2, figsize=(11, 4.6), layout="constrained")
        else:
            axes = list(ax) if isinstance(ax, Sequence | np.ndarray) else [ax]
            if len(axes) != 2:
                raise ValueError("ax must be None or two Axes for view='both'")
            fig = axes[0].figure
        ax_img, ax_top = axes
    else:
        if isinstance(ax, Sequence | np.ndarray):
            raise ValueError(f"ax must be one Axes or None for view={view!r}")
        ax = new_axes(ax)
        ax_img, ax_top = (ax, None) if view == "image" else (None, ax)
    if ax_img is not None:
        H, W = lab.shape
        ax_img.imshow(
            _label_image(lab, colors, MASKED_COLOR),
            interpolation="nearest",
            aspect="equal" if W <= 4 * H else "auto",
        )
        _beam_axes(ax_img)
        ax_img.set_title(f"plane labels ({n_planes} planes; grey: none)", fontsize=10)
    if ax_top is not None:
        ok = np.all(np.isfinite(pts), axis=-1)
        p, l_ = pts[ok], lab[ok]
        step = max(1, -(-p.shape[0] // int(max_points)))
        p, l_ = p[::step], l_[::step]
        on = l_ >= 0
        ax_top.scatter(p[~on, 0], p[~on, 1], s=1, color=MASKED_COLOR, lw=0)
        ax_top.scatter(p[on, 0], p[on, 1], s=1.5, c=colors[l_[on] % len(colors)], lw=0)
        ax_top.plot(0, 0, "k^", ms=6)  # the sensor
        metric_axes(ax_top)
        ax_top.set_title("top view (sensor frame)", fontsize=10)
    if fig is not None:
        return fig
    return ax


def _pole_arrays(poles, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    if isinstance(poles, Poles | PoleMap):
        return np.asarray(poles.xy, float).reshape(-1, 2), np.asarray(poles.width_m, float)
    try:
        xy = np.asarray(poles, float)
    except (TypeError, ValueError):
        xy = None
    if xy is None or xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(
            f"{name} must be a PoleMap, Poles or [K 2] positions (m), got "
            f"{type(poles).__name__} {getattr(xy, 'shape', '')}"
        )
    return xy, None


def plot_poles(
    pole_map,
    *,
    ax=None,
    poses=None,
    truth=None,
    annotate: bool = False,
    cmap="viridis",
):
    """A pole map (x, y in m): poles sized and coloured by their width (colour bar), the
    true poles as crosses and the trajectory.

    Args:
        pole_map: a :class:`~lidarjax.localization.PoleMap`, :class:`~lidarjax.features.Poles`
            or ``[K 2]`` positions (m; then one size and colour, no colour bar).
        ax: the Axes to draw into; default a new figure.
        poses: the trajectory (``[T 3]``, ``[T 2]`` or a batched ``jaxlie.SE2``), or None.
        truth: the true pole positions (same forms as ``pole_map``), or None.
        annotate: write each pole's width (m) beside it.
        cmap: colour map of the widths.

    Returns:
        The matplotlib ``Axes``.

    Raises:
        ValueError: ``pole_map`` / ``truth`` / ``poses`` of the wrong type or shape.
    """
    xy, width = _pole_arrays(pole_map, "pole_map")
    gt = None if truth is None else _pole_arrays(truth, "truth")[0]
    traj = None if poses is None else pose_array(poses, "poses")
    ax = new_axes(ax, figsize=(7.0, 5.6))
    if traj is not None:
        plot_trajectory(traj, ax=ax, color="0.45", lw=1.0, label="trajectory")
    if gt is not None:
        ax.scatter(gt[:, 0], gt[:, 1], marker="x", s=30, color="k", lw=1.0, label="true poles")
    if width is None or width.size == 0:
        ax.scatter(xy[:, 0], xy[:, 1], s=25, color="tab:red", label="poles", zorder=3)
    else:
        w_max = max(float(width.max()), 1e-9)
        sc = ax.scatter(
            xy[:, 0], xy[:, 1], s=12 + 60 * width / w_max, c=width, cmap=cmap,
            edgecolors="k", linewidths=0.4, label="poles (size: width)", zorder=3,
        )  # fmt: skip
        colorbar(sc, ax, "pole width (m)")
        if annotate:
            for (x, y), w in zip(xy, width):
                ax.annotate(f"{w:.2f} m", (x, y), xytext=(3, 3), textcoords="offset points",
                            fontsize=6)  # fmt: skip
    metric_axes(ax)
    ax.set_title(f"pole map ({xy.shape[0]} poles)")
    ax.legend(loc="best", fontsize=8, framealpha=0.8)
    return ax
