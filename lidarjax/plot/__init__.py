"""Matplotlib figures that explain (host-side only; nothing here is traced).

Importing this package never changes Matplotlib's backend: a script that must run
without a display chooses one itself (``matplotlib.use("Agg")`` at its top, or
``MPLBACKEND=Agg``). Every helper takes an optional ``ax=`` (a new figure when None) and
returns the Axes it drew into (the Figure for multi-panel figures); axes are labelled in
metres with an equal aspect, and a colour bar labelled with quantity and unit accompanies
every colour that encodes a value.

- maps (:mod:`._maps`): :func:`plot_map` (any grid model of :mod:`lidarjax.maps`, grid
  statistics, DCT maps and other decay-rate fields; unobserved cells masked),
  :func:`map_quantities`, :func:`plot_grid_stats`.
- localization (:mod:`._localization`): :func:`plot_trajectory`, :func:`plot_particles`,
  :func:`plot_localization` (map + trajectories + position error over time).
- features (:mod:`._features`): :func:`plot_polyline_scan` (polylines over a scan),
  :func:`plot_planes` (plane segmentation: label image and top view),
  :func:`plot_segmentation` (label images side by side), :func:`plot_poles`.
"""

from ._features import plot_planes as plot_planes
from ._features import plot_poles as plot_poles
from ._features import plot_polyline_scan as plot_polyline_scan
from ._features import plot_segmentation as plot_segmentation
from ._localization import plot_localization as plot_localization
from ._localization import plot_particles as plot_particles
from ._localization import plot_trajectory as plot_trajectory
from ._maps import map_quantities as map_quantities
from ._maps import plot_grid_stats as plot_grid_stats
from ._maps import plot_map as plot_map

__all__ = [
    "map_quantities",
    "plot_map",
    "plot_grid_stats",
    "plot_trajectory",
    "plot_particles",
    "plot_localization",
    "plot_polyline_scan",
    "plot_planes",
    "plot_segmentation",
    "plot_poles",
]
