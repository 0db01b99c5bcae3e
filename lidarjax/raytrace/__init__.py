"""The geometry core: every ray kernel of lidarjax, written once (dissertation Sec. 7.4).

- :mod:`._grid`: :class:`GridSpec`, :class:`GridStats`, the exact grid walk
  (:func:`traverse`, :func:`traverse_rays`), :func:`accumulate` (H, M, R) and the folds
  (:func:`fold_traversal`, :func:`fold_rays`) the grid sensor models are built on.
- :mod:`._primitives`: ray-box (slab test), ray-cylinder, ray-sphere, ray-plane,
  ray-segment, and chunking helpers.
- :mod:`._native`: C++ kernels of the hot walks through the XLA FFI (CPU), selected with
  ``backend="auto" | "native" | "jax"``; the JAX path is the differentiable path, the
  fallback and the test oracle.
"""

from ..rays import HIT as HIT
from ..rays import SUB as SUB
from ..rays import SUP as SUP
from ._grid import CellTerm as CellTerm
from ._grid import GridSpec as GridSpec
from ._grid import GridStats as GridStats
from ._grid import RayFold as RayFold
from ._grid import Traversal as Traversal
from ._grid import accumulate as accumulate
from ._grid import expected_cell_count as expected_cell_count
from ._grid import fold_rays as fold_rays
from ._grid import fold_traversal as fold_traversal
from ._grid import gather as gather
from ._grid import max_cells_for as max_cells_for
from ._grid import traverse as traverse
from ._grid import traverse_rays as traverse_rays
from ._native import BACKENDS as BACKENDS
from ._native import check_backend as check_backend
from ._native import check_threads as check_threads
from ._primitives import box_exit as box_exit
from ._primitives import clip_to_box as clip_to_box
from ._primitives import cross2 as cross2
from ._primitives import first_segment_hit as first_segment_hit
from ._primitives import first_segment_hits as first_segment_hits
from ._primitives import map_chunked as map_chunked
from ._primitives import n_chunks_for as n_chunks_for
from ._primitives import pad_to_chunks as pad_to_chunks
from ._primitives import ray_box as ray_box
from ._primitives import ray_cylinder as ray_cylinder
from ._primitives import ray_plane as ray_plane
from ._primitives import ray_segment as ray_segment
from ._primitives import ray_sphere as ray_sphere
from ._primitives import slabs as slabs
from ._primitives import unchunk as unchunk
from ._sharded import accumulate_sharded as accumulate_sharded
from ._sharded import accumulate_tiled as accumulate_tiled
from ._sharded import device_mesh as device_mesh

__all__ = [
    "GridSpec",
    "GridStats",
    "Traversal",
    "RayFold",
    "CellTerm",
    "traverse",
    "traverse_rays",
    "max_cells_for",
    "accumulate",
    "accumulate_sharded",
    "accumulate_tiled",
    "device_mesh",
    "expected_cell_count",
    "fold_traversal",
    "fold_rays",
    "gather",
    "slabs",
    "ray_box",
    "clip_to_box",
    "box_exit",
    "ray_cylinder",
    "ray_sphere",
    "ray_plane",
    "cross2",
    "ray_segment",
    "first_segment_hit",
    "first_segment_hits",
    "n_chunks_for",
    "pad_to_chunks",
    "unchunk",
    "map_chunked",
    "BACKENDS",
    "check_backend",
    "check_threads",
    "HIT",
    "SUB",
    "SUP",
]
