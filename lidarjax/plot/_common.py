"""What the plot helpers share: axes creation, pose conversion, colour maps with a masked
colour, colour bars and the axis labels in metres. Host-side only; nothing here is traced.
"""

from __future__ import annotations

import jaxlie
import matplotlib.pyplot as plt
import numpy as np
from matplotlib import colormaps

X_LABEL = "x (m)"
Y_LABEL = "y (m)"
MASKED_COLOR = "0.72"  # unobserved cells and unlabelled points: a mid grey


def new_axes(ax, figsize: tuple[float, float] = (6.0, 4.8)):
    """``ax`` itself, or the single Axes of a new figure (constrained layout)."""
    if ax is not None:
        if not hasattr(ax, "figure") or not hasattr(ax, "plot"):
            raise ValueError(f"ax must be a matplotlib Axes or None, got {type(ax).__name__}")
        return ax
    _, ax = plt.subplots(figsize=figsize, layout="constrained")
    return ax


def metric_axes(ax, *, equal: bool = True) -> None:
    """x / y labels in metres and (by default) an equal aspect ratio."""
    ax.set_xlabel(X_LABEL)
    ax.set_ylabel(Y_LABEL)
    if equal:
        ax.set_aspect("equal")


def masked_cmap(cmap, bad: str = MASKED_COLOR):
    """A copy of the colour map ``cmap`` (name or object) drawing masked values in ``bad``."""
    try:
        cm = colormaps[cmap] if isinstance(cmap, str) else cmap
    except KeyError:
        raise ValueError(f"cmap must be a matplotlib colour map name, got {cmap!r}") from None
    return cm.with_extremes(bad=bad)


def colorbar(mappable, ax, label: str, **kw):
    """A colour bar beside ``ax`` with the quantity and unit as its label."""
    return ax.figure.colorbar(mappable, ax=ax, label=label, shrink=kw.pop("shrink", 0.85), **kw)


def pose_array(poses, name: str, *, allow_xy: bool = True) -> np.ndarray:
    """Host ``[T 3]`` (x, y, theta) or ``[T 2]`` (x, y) poses from an array or a batched
    ``jaxlie.SE2``; ``ValueError`` naming ``name`` otherwise."""
    if isinstance(poses, jaxlie.SE2):
        t = np.asarray(poses.translation(), float).reshape(-1, 2)
        th = np.asarray(poses.rotation().as_radians(), float).reshape(-1)
        return np.column_stack([t, th])
    if isinstance(poses, jaxlie.MatrixLieGroup):
        raise ValueError(f"{name} must be 2-D poses (jaxlie.SE2), got {type(poses).__name__}")
    try:
        p = np.asarray(poses, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(
            f"{name} must be a [T 3] array of (x, y, theta) or a batched jaxlie.SE2, "
            f"got {type(poses).__name__}"
        ) from None
    widths = (2, 3) if allow_xy else (3,)
    if p.ndim != 2 or p.shape[1] not in widths or p.shape[0] < 1:
        want = "[T 3] (x, y, theta) or [T 2] (x, y)" if allow_xy else "[T 3] (x, y, theta)"
        raise ValueError(f"{name} must have shape {want} with T >= 1, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name} must be finite")
    return p
