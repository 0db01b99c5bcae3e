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
