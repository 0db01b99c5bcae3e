"""Dataset layer: file readers/writers, the checksummed data registry and synthetic worlds.

NumPy only; nothing here is called inside ``jit``. Readers return plain array containers.
"""

from ._carmen import CarmenLog as CarmenLog
from ._carmen import load_carmen as load_carmen
from ._errors import DataChecksumError as DataChecksumError
from ._errors import DataNotFoundError as DataNotFoundError
from ._errors import DatasetFormatError as DatasetFormatError
from ._kitti import load_kitti_poses as load_kitti_poses
from ._kitti import load_kitti_times as load_kitti_times
from ._pcd import PointCloud as PointCloud
from ._pcd import read_pcd as read_pcd
from ._pcd import write_pcd as write_pcd
from ._polygons import random_polygon as random_polygon
from ._polygons import simulate_polygon_scan as simulate_polygon_scan
from ._registry import REGISTRY as REGISTRY
from ._registry import available as available
from ._registry import data_dirs as data_dirs
from ._registry import fetch as fetch
from ._synpeb import ConvexPolyhedron as ConvexPolyhedron
from ._synpeb import SynPEBScan as SynPEBScan
from ._synpeb import SynPEBScene as SynPEBScene
from ._synpeb import cast_rays as cast_rays
from ._synpeb import load_synpeb_pcd as load_synpeb_pcd
from ._synpeb import make_synpeb_scene as make_synpeb_scene
from ._synpeb import simulate_synpeb_scan as simulate_synpeb_scan
from ._synpeb import synpeb_scan as synpeb_scan
from ._synpeb import synpeb_split as synpeb_split
from ._synpeb import write_synpeb_pcd as write_synpeb_pcd
from ._synthetic import OfficeWorld as OfficeWorld
from ._synthetic import make_office as make_office
from ._synthetic import simulate_scans as simulate_scans
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
