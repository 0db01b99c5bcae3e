"""Trajectories, particle sets and localization runs over a map (x, y in metres)."""

from __future__ import annotations

import jaxlie
import matplotlib.pyplot as plt
import numpy as np

from ..localization import ParticleState
from ._common import colorbar, metric_axes, new_axes, pose_array
from ._maps import plot_map

__all__ = ["plot_localization", "plot_particles", "plot_trajectory"]


def plot_trajectory(
    poses, *, ax=None, label: str | None = None, start_marker: bool = True, **style
):
    """Draw a 2-D trajectory (x, y in m) with a dot at its first pose.

    Args:
        poses: ``[T 3]`` poses (x (m), y (m), theta (rad)), ``[T 2]`` positions, or a
            ``jaxlie.SE2`` with batch axis ``[T]``.
        ax: the Axes to draw into; default a new figure.
        label: legend label (a legend is drawn when given).
        start_marker: mark the first pose with a dot.
        **style: Matplotlib line properties (``color``, ``lw``, ``ls``, ...).

    Returns:
        The matplotlib ``Axes``.

    Raises:
        ValueError: ``poses`` has the wrong type or shape, or is not finite.
    """
    p = pose_array(poses, "poses")
    ax = new_axes(ax)
    style.setdefault("lw", 1.2)
    (line,) = ax.plot(p[:, 0], p[:, 1], label=label, **style)
    if start_marker:
        ax.plot(p[0, 0], p[0, 1], "o", color=line.get_color(), ms=4, zorder=line.get_zorder())
    metric_axes(ax)
    if label is not None:
        ax.legend(loc="best", fontsize=8, framealpha=0.8)
    return ax


def _particle_weights(particles, weights, n: int) -> np.ndarray | None:
    if weights is None and isinstance(particles, ParticleState):
        lw = np.asarray(particles.log_weights, float)
        if np.any(np.isfinite(lw)):
            weights = np.exp(lw - np.max(lw[np.isfinite(lw)]))
    if weights is None:
        return None
    w = np.asarray(weights, float)
    if w.shape != (n,):
        raise ValueError(f"weights must have shape [{n}] (one per particle), got {w.shape}")
    if not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError("weights must be finite, >= 0 and not all 0")
    return w / w.sum()


def plot_particles(
    particles,
    weights=None,
    *,
    ax=None,
    headings: bool = False,
    arrow_m: float = 0.25,
    cmap="viridis",
    size: float = 6.0,
    show_colorbar: bool = True,
):
    """Draw a particle set: positions (m), coloured by normalised weight with a colour bar.

    Args:
        particles: a :class:`~lidarjax.localization.ParticleState` (its weights are used
            when ``weights`` is None), a ``jaxlie.SE2`` with batch axis ``[n]``, or ``[n 3]``
            poses (x, y in m, theta in rad) / ``[n 2]`` positions.
        weights: ``[n]`` non-negative weights (normalised here); None: the state's weights,
            or one colour for bare poses.
        ax: the Axes to draw into; default a new figure.
        headings: draw an arrow of ``arrow_m`` (m) along each particle's heading.
        arrow_m: arrow length (m).
        cmap: colour map of the weights.
        size: marker size (points²).
        show_colorbar: draw the weight colour bar (when there are weights).

    Returns:
        The matplotlib ``Axes``.

    Raises:
        ValueError: ``particles`` or ``weights`` has the wrong type or shape; ``headings``
            without headings.
    """
    src = particles.particles if isinstance(particles, ParticleState) else particles
    if isinstance(src, jaxlie.SE3):
        raise ValueError("particles must be 2-D (jaxlie.SE2), got jaxlie.SE3")
    p = pose_array(src, "particles")
    w = _particle_weights(particles, weights, p.shape[0])
    ax = new_axes(ax)
    if w is None:
        ax.scatter(p[:, 0], p[:, 1], s=size, color="tab:orange", lw=0, zorder=3)
    else:
        order = np.argsort(w)  # heavy particles on top
        sc = ax.scatter(
            p[order, 0], p[order, 1], c=w[order], s=size, cmap=cmap, lw=0, vmin=0, zorder=3
        )
        if show_colorbar:
            colorbar(sc, ax, "normalised particle weight")
    if headings:
        if p.shape[1] != 3:
            raise ValueError("headings needs particles with a heading ([n 3] or SE2)")
        u, v = arrow_m * np.cos(p[:, 2]), arrow_m * np.sin(p[:, 2])
        ax.quiver(
            p[:, 0], p[:, 1], u, v, angles="xy", scale_units="xy", scale=1.0,
            width=0.003, color="0.25", alpha=0.7, zorder=2,
        )  # fmt: skip
    metric_axes(ax)
    return ax


def plot_localization(
    map_model,
    estimate,
    truth=None,
    particles=None,
    *,
    ax=None,
    error_ax=None,
    label: str = "estimate",
    color: str = "tab:blue",
    times=None,
    weights=None,
    quantity: str | None = None,
    observed=None,
    title: str | None = None,
):
    """A localization run: the map, the estimated (and true) trajectory, optionally the
    particles, and — when the truth is given — the position error over time.

    With ``truth`` and neither ``ax`` nor ``error_ax``, a two-panel figure is made (map
    and trajectories | position error (m) vs step or time) and returned; otherwise the
    map Axes ``ax`` is returned and the error curve goes into ``error_ax`` if given (call
    again with the same Axes to compare several filters).

    Args:
        map_model: anything :func:`plot_map` draws, or None (no background).
        estimate: ``[T 3]`` estimated poses (x, y in m, theta in rad), ``[T 2]``, or a
            batched ``jaxlie.SE2``.
        truth: the true poses at the same ``T`` steps (same forms), or None.
        particles: particles to overlay (see :func:`plot_particles`), or None.
        ax: the map Axes; default a new figure.
        error_ax: the Axes of the error curve.
        label: legend label of the estimate (also of its error curve).
        color: colour of the estimate and its error curve.
        times: ``[T]`` time stamps (s) for the error axis; default the step index.
        weights: particle weights (see :func:`plot_particles`).
        quantity, observed: passed to :func:`plot_map`.
        title: the map Axes' title.

    Returns:
        The two-panel ``Figure`` (made here), else the map ``Axes``.

    Raises:
        ValueError: ``estimate`` / ``truth`` / ``times`` with bad shapes or lengths.
    """
    est = pose_array(estimate, "estimate")
    gt = None if truth is None else pose_array(truth, "truth")
    if gt is not None and gt.shape[0] != est.shape[0]:
        raise ValueError(
            f"truth must have one pose per estimate ({est.shape[0]}), got {gt.shape[0]}"
        )
    t = None
    if times is not None:
        t = np.asarray(times, float)
        if t.shape != (est.shape[0],) or not np.all(np.isfinite(t)):
            raise ValueError(f"times must be [{est.shape[0]}] finite seconds, got {t.shape}")
    fig = None
    if gt is not None and ax is None and error_ax is None:
        fig, (ax, error_ax) = plt.subplots(
            1, 2, figsize=(12.5, 4.8), width_ratios=[1.6, 1.0], layout="constrained"
        )
    ax = new_axes(ax)
    if map_model is not None:
        plot_map(map_model, ax=ax, quantity=quantity, observed=observed)
    if particles is not None:
        plot_particles(particles, weights, ax=ax)
    if gt is not None:
        plot_trajectory(gt, ax=ax, label="truth", color="k", ls="--", lw=1.0)
    plot_trajectory(est, ax=ax, label=label, color=color, lw=1.3)
    if title is not None:
        ax.set_title(title)
    if gt is not None and error_ax is not None:
        err = np.linalg.norm(est[:, :2] - gt[:, :2], axis=1)
        x = np.arange(err.size) if t is None else t
        error_ax.plot(x, err, color=color, lw=1.2, label=label)
        error_ax.set_xlabel("step" if t is None else "time (s)")
        error_ax.set_ylabel("position error (m)")
        error_ax.set_ylim(bottom=0)
        error_ax.grid(alpha=0.3)
        error_ax.legend(loc="best", fontsize=8, framealpha=0.8)
        error_ax.set_title("position error")
    return fig if fig is not None else ax
