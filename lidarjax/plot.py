"""Matplotlib figures (host-side only; nothing here is traced)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import LogNorm  # noqa: E402

from .raytrace import GridStats  # noqa: E402


def plot_grid_stats(
    stats: GridStats,
    *,
    segments: np.ndarray | None = None,
    poses: np.ndarray | None = None,
    title: str = "",
):
    """Three panels of a 2-D :class:`GridStats`: hits ``H``, travelled length ``R`` and the
    hit fraction ``H / (H + M)``, optionally with ground-truth wall segments ``[k 2 2]`` (m)
    and sensor poses ``[s 3]`` overlaid.

    Returns:
        The matplotlib ``Figure``.
    """
    if stats.spec.dim != 2:
        raise ValueError(f"plot_grid_stats needs a 2-D grid, got {stats.spec.dim}-D")
    H = np.asarray(stats.hits, dtype=float)
    M = np.asarray(stats.misses, dtype=float)
    R = np.asarray(stats.lengths, dtype=float)
    extent = stats.spec.extent()
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(H + M > 0, H / (H + M), np.nan)
    panels = [
        ("hits H (count)", np.where(H > 0, H, np.nan), LogNorm(vmin=1, vmax=max(H.max(), 2))),
        (
            "travelled length R (m)",
            np.where(R > 0, R, np.nan),
            LogNorm(vmin=1e-3, vmax=max(R.max(), 1e-2)),
        ),
        ("hit fraction H/(H+M)", frac, None),
    ]
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.8), constrained_layout=True)
    for ax, (name, img, norm) in zip(axes, panels):
        im = ax.imshow(
            img.T, origin="lower", extent=extent, cmap="viridis", norm=norm, interpolation="nearest"
        )
        fig.colorbar(im, ax=ax, shrink=0.8)
        if segments is not None:
            for (x0, y0), (x1, y1) in segments:
                ax.plot([x0, x1], [y0, y1], color="tab:red", lw=0.6, alpha=0.7)
        if poses is not None:
            ax.plot(poses[:, 0], poses[:, 1], color="white", lw=0.8, alpha=0.8)
        ax.set_title(name)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_aspect("equal")
    if title:
        fig.suptitle(title)
    return fig


def plot_polyline_scan(
    ax,
    origin_xy: np.ndarray,
    endpoints_xy: np.ndarray,
    reflected: np.ndarray,
    polylines: list[np.ndarray],
    closed: list[bool] | None = None,
    *,
    ray_stride: int = 2,
    title: str = "",
):
    """A 2-D scan with extracted polylines, like Figures 10.1 and 10.3.

    Every ``ray_stride``-th reflected ray is drawn as a thin red line with its endpoint,
    no-return rays in grey, the polylines in blue with their vertices.

    Args:
        ax: a matplotlib ``Axes``.
        origin_xy: ``[2]`` sensor position (m).
        endpoints_xy: ``[K 2]`` ray endpoints (m; for no-returns, the point at the reported
            range).
        reflected: ``[K]`` bool, HIT rays.
        polylines: list of ``[m 2]`` vertex arrays (m).
        closed: per polyline, whether it is closed (default: all open).
        ray_stride: draw every n-th ray.
        title: axes title.
    """
    o = np.asarray(origin_xy, float)
    e = np.asarray(endpoints_xy, float)
    refl = np.asarray(reflected, bool)
    for k in range(0, len(e), max(1, int(ray_stride))):
        c, lw = ("tab:red", 0.3) if refl[k] else ("0.75", 0.3)
        ax.plot([o[0], e[k, 0]], [o[1], e[k, 1]], color=c, lw=lw, zorder=1)
    ax.plot(e[refl, 0], e[refl, 1], ".", color="tab:red", ms=1.5, zorder=2)
    closed = [False] * len(polylines) if closed is None else closed
    for pl, c in zip(polylines, closed):
        p = np.asarray(pl, float)
        if c:
            p = np.vstack([p, p[:1]])
        ax.plot(p[:, 0], p[:, 1], "-o", color="tab:blue", lw=1.2, ms=2.5, zorder=3)
    ax.plot(*o, "ks", ms=4, zorder=4)
    ax.set_aspect("equal")
    n = sum(len(p) for p in polylines)
    ax.set_title(f"{title} (J = {n})" if title else f"J = {n}", fontsize=9)
    ax.tick_params(labelsize=7)
    return ax


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
    fig, axes = plt.subplots(1, len(images), figsize=(3.2 * len(images), 3.4), squeeze=False)
    colors = np.random.default_rng(seed).uniform(0.15, 1.0, (4096, 3))
    for ax, (name, lab) in zip(axes[0], images.items()):
        lab = np.asarray(lab)
        if lab.ndim != 2 or not np.issubdtype(lab.dtype, np.integer):
            raise ValueError(
                f"images[{name!r}] must be a 2-D integer label image, got {lab.dtype} {lab.shape}"
            )
        img = np.zeros(lab.shape + (3,))
        on = lab >= 0
        img[on] = colors[lab[on] % len(colors)]
        ax.imshow(img, interpolation="nearest")
        ax.set_title(name, fontsize=10)
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig
