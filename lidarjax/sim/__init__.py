"""Synthetic worlds and lidar simulators: office, polygons, SynPEB-style scenes, urban drives.

Every simulator is seeded and deterministic, takes and returns NumPy arrays (or the plain
containers of :mod:`lidarjax.datasets`), and casts its rays exactly, with the geometry
core's primitives (:mod:`lidarjax.raytrace`) where one exists:

- office (:mod:`._office`): :func:`make_office` builds a 2-D office of wall segments,
  :func:`simulate_scans` casts planar scans against them
  (:func:`~lidarjax.raytrace.first_segment_hits`).
- polygons (:mod:`._polygons`, dissertation Sec. 10.5): :func:`random_polygon` and
  :func:`simulate_polygon_scan` (:func:`~lidarjax.raytrace.first_segment_hit`).
- SynPEB-style scenes (:mod:`._synpeb_scene`, :mod:`._synpeb`, ch. 11): convex polyhedra
  with labelled faces (:class:`ConvexPolyhedron`, :class:`SynPEBScene`), their exact caster
  :func:`cast_rays` (NumPy half-space slabs; the geometry core has no ray/convex-polyhedron
  primitive), :func:`make_synpeb_scene`, :func:`simulate_synpeb_scan` and the generated
  splits :func:`synpeb_scan` / :func:`synpeb_split`. Scans are
  :class:`~lidarjax.datasets.SynPEBScan` containers; their PCD files are read and written
  by :mod:`lidarjax.datasets`.
- urban drives (ch. 12): a spinning lidar (:class:`LidarSpec`, :func:`hdl32e`), worlds
  around a real trajectory (:func:`make_urban_world`, :func:`urban_session`; the trajectory
  comes from :func:`~lidarjax.datasets.load_urban_trajectory`), scans cast in a jitted
  kernel (:func:`simulate_urban_scan`, :func:`simulate_urban_scans`, with
  :func:`~lidarjax.raytrace.ray_cylinder`, :func:`~lidarjax.raytrace.ray_box` and
  :func:`~lidarjax.raytrace.ray_sphere`) and drifting odometry (:func:`wheel_odometry`).
- re-simulated logs (:mod:`._resimulate`): :func:`resimulate_scans` builds a world from a
  log's own surfaces at given poses (segments between neighbouring end points, on a fine
  grid) and casts the log's beams again from those poses, so the poses are exact
  (:class:`ResimulatedScans`).

Layering: ``sim`` imports :mod:`lidarjax.datasets` and :mod:`lidarjax.raytrace`, never the
other way round (``lidarjax.datasets`` still forwards the old names here, lazily and with a
``DeprecationWarning``).
"""

from ._lidar import HDL32E_ELEVATIONS_DEG as HDL32E_ELEVATIONS_DEG
from ._lidar import LidarSpec as LidarSpec
from ._lidar import hdl32e as hdl32e
from ._odometry import wheel_odometry as wheel_odometry
from ._office import OfficeWorld as OfficeWorld
from ._office import make_office as make_office
from ._office import simulate_scans as simulate_scans
from ._polygons import random_polygon as random_polygon
from ._polygons import simulate_polygon_scan as simulate_polygon_scan
from ._resimulate import ResimulatedScans as ResimulatedScans
from ._resimulate import resimulate_scans as resimulate_scans
from ._synpeb import make_synpeb_scene as make_synpeb_scene
from ._synpeb import simulate_synpeb_scan as simulate_synpeb_scan
from ._synpeb import synpeb_scan as synpeb_scan
from ._synpeb import synpeb_split as synpeb_split
from ._synpeb_scene import ConvexPolyhedron as ConvexPolyhedron
from ._synpeb_scene import SynPEBScene as SynPEBScene
from ._synpeb_scene import cast_rays as cast_rays
from ._urban_cast import UrbanScan as UrbanScan
from ._urban_cast import scan_seed as scan_seed
from ._urban_cast import simulate_urban_scan as simulate_urban_scan
from ._urban_cast import simulate_urban_scans as simulate_urban_scans
from ._urban_common import BOX_KINDS as BOX_KINDS
from ._urban_common import POLE_KINDS as POLE_KINDS
from ._urban_world import UrbanWorld as UrbanWorld
from ._urban_world import make_urban_world as make_urban_world
from ._urban_world import urban_session as urban_session
