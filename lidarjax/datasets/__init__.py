"""Dataset layer: file readers/writers and the checksummed data registry.

Formats: CARMEN logs, KITTI poses and times, NCLT, PCD (ascii, binary,
binary_compressed with LZF), PLY, ROS 1 / ROS 2 bags (LaserScan, PointCloud2, Odometry,
tf; through ``rosbags``), organised scans from spinning-lidar clouds, ROS ``map_server``
maps and ``.npz`` grid maps, TUM and KITTI trajectories, labelled clouds, polylines as
CSV and SVG. Every reader raises :class:`DatasetFormatError` naming the file on damaged
input. The registry (:func:`fetch`) verifies every file by SHA-256.

NumPy only; nothing here is called inside ``jit``. Readers return plain array containers.
The synthetic worlds and simulators live in :mod:`lidarjax.sim`; their old names here
(``lidarjax.datasets.simulate_synpeb_scan`` etc.) still resolve, lazily and with a
``DeprecationWarning`` naming the new place, so that importing this package never imports
:mod:`lidarjax.sim` (which imports this one).
"""

from __future__ import annotations

import importlib
import warnings

from ._carmen import AZIMUTH_LAYOUTS as AZIMUTH_LAYOUTS
from ._carmen import CarmenLog as CarmenLog
from ._carmen import load_carmen as load_carmen
from ._errors import DataChecksumError as DataChecksumError
from ._errors import DataNotFoundError as DataNotFoundError
from ._errors import DatasetFormatError as DatasetFormatError
from ._kitti import load_kitti_poses as load_kitti_poses
from ._kitti import load_kitti_times as load_kitti_times
from ._map_server import GRID_MAP_FORMAT_VERSION as GRID_MAP_FORMAT_VERSION
from ._map_server import GridMapFile as GridMapFile
from ._map_server import MapServerMap as MapServerMap
from ._map_server import load_grid_map as load_grid_map
from ._map_server import occupancy_from_decay_rate as occupancy_from_decay_rate
from ._map_server import occupancy_from_reflection as occupancy_from_reflection
from ._map_server import read_map_server as read_map_server
from ._map_server import save_grid_map as save_grid_map
from ._map_server import write_map_server as write_map_server
from ._organise import OrganisedScan as OrganisedScan
from ._organise import beam_elevations as beam_elevations
from ._organise import organise_scan as organise_scan
from ._pcd import PointCloud as PointCloud
from ._pcd import lzf_backend as lzf_backend
from ._pcd import read_pcd as read_pcd
from ._pcd import write_pcd as write_pcd
from ._ply import read_ply as read_ply
from ._ply import write_labelled_cloud as write_labelled_cloud
from ._ply import write_ply as write_ply
from ._polyline_io import read_polylines_csv as read_polylines_csv
from ._polyline_io import write_polylines_csv as write_polylines_csv
from ._polyline_io import write_polylines_svg as write_polylines_svg
from ._registry import REGISTRY as REGISTRY
from ._registry import available as available
from ._registry import data_dirs as data_dirs
from ._registry import download_urls as download_urls
from ._registry import fetch as fetch
from ._rosbag import BagPointCloud as BagPointCloud
from ._rosbag import iter_bag_point_clouds as iter_bag_point_clouds
from ._rosbag import read_bag_laser_scans as read_bag_laser_scans
from ._rosbag import read_bag_odometry as read_bag_odometry
from ._rosbag import read_bag_point_clouds as read_bag_point_clouds
from ._rosbag import read_bag_tf as read_bag_tf
from ._rosbag import read_bag_topics as read_bag_topics
from ._rosbag import write_bag_laser_scans as write_bag_laser_scans
from ._rosbag import write_bag_point_clouds as write_bag_point_clouds
from ._synpeb_io import SynPEBScan as SynPEBScan
from ._synpeb_io import load_synpeb_pcd as load_synpeb_pcd
from ._synpeb_io import write_synpeb_pcd as write_synpeb_pcd
from ._trajectory import TumTrajectory as TumTrajectory
from ._trajectory import read_tum as read_tum
from ._trajectory import write_kitti_poses as write_kitti_poses
from ._trajectory import write_tum as write_tum
from ._urban_trajectory import UrbanTrajectory as UrbanTrajectory
from ._urban_trajectory import load_urban_trajectory as load_urban_trajectory
from ._velodyne import KittiSequence as KittiSequence
from ._velodyne import NcltGroundTruth as NcltGroundTruth
from ._velodyne import NcltHitsPacket as NcltHitsPacket
from ._velodyne import iter_nclt_velodyne_hits as iter_nclt_velodyne_hits
from ._velodyne import load_kitti_sequence as load_kitti_sequence
from ._velodyne import nclt_ground_truth_se2 as nclt_ground_truth_se2
from ._velodyne import read_kitti_velodyne as read_kitti_velodyne
from ._velodyne import read_nclt_ground_truth as read_nclt_ground_truth
from ._velodyne import read_nclt_velodyne_hits as read_nclt_velodyne_hits
from ._velodyne import read_nclt_velodyne_sync as read_nclt_velodyne_sync
from ._velodyne import write_kitti_velodyne as write_kitti_velodyne
from ._velodyne import write_nclt_ground_truth as write_nclt_ground_truth
from ._velodyne import write_nclt_velodyne_hits as write_nclt_velodyne_hits
from ._velodyne import write_nclt_velodyne_sync as write_nclt_velodyne_sync

# Names that moved to lidarjax.sim, where they keep their names. Resolved on first access by
# __getattr__ below, never at import time: sim imports datasets, not the other way round.
_MOVED_TO_SIM = frozenset(
    (
        # office
        "OfficeWorld",
        "make_office",
        "simulate_scans",
        # polygons
        "random_polygon",
        "simulate_polygon_scan",
        # SynPEB-style scenes
        "ConvexPolyhedron",
        "SynPEBScene",
        "cast_rays",
        "make_synpeb_scene",
        "simulate_synpeb_scan",
        "synpeb_scan",
        "synpeb_split",
        # urban drives
        "BOX_KINDS",
        "HDL32E_ELEVATIONS_DEG",
        "POLE_KINDS",
        "LidarSpec",
        "UrbanScan",
        "UrbanWorld",
        "hdl32e",
        "make_urban_world",
        "simulate_urban_scan",
        "simulate_urban_scans",
        "urban_session",
        "wheel_odometry",
    )
)


def __getattr__(name: str):
    """Forward a name that moved to :mod:`lidarjax.sim`, with a ``DeprecationWarning``."""
    if name not in _MOVED_TO_SIM:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    warnings.warn(
        f"lidarjax.datasets.{name} has moved to lidarjax.sim.{name}; import it from "
        "lidarjax.sim (the old name will be removed)",
        DeprecationWarning,
        stacklevel=2,
    )
    return getattr(importlib.import_module("lidarjax.sim"), name)


def __dir__() -> list[str]:
    return sorted(set(globals()) | _MOVED_TO_SIM)
