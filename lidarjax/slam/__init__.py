"""Differentiable lidar SLAM with decay-rate fields (issue #24): an online scan-to-map
front end, loop closures, a pose graph, the joint optimisation of all poses and the map,
and a classical baseline (GICP registration with a GTSAM pose graph)."""

from ._back_end import BackEndConfig as BackEndConfig
from ._back_end import BackEndResult as BackEndResult
from ._back_end import joint_objective as joint_objective
from ._back_end import optimize_alternating as optimize_alternating
from ._back_end import optimize_joint as optimize_joint
from ._back_end import trajectory_log_likelihood as trajectory_log_likelihood
from ._baselines import IcpFrontEndResult as IcpFrontEndResult
from ._baselines import IcpSlamResult as IcpSlamResult
from ._baselines import icp_front_end as icp_front_end
from ._baselines import icp_pose_graph_slam as icp_pose_graph_slam
from ._calibration import OdometryCalibration as OdometryCalibration
from ._calibration import calibrate_odometry as calibrate_odometry
from ._diagnostics import ReferenceMatchErrors as ReferenceMatchErrors
from ._diagnostics import reference_match_errors as reference_match_errors
from ._front_end import MATCHING_MODELS as MATCHING_MODELS
from ._front_end import RANGE_CAPS_M as RANGE_CAPS_M
from ._front_end import FrontEndConfig as FrontEndConfig
from ._front_end import FrontEndResult as FrontEndResult
from ._front_end import GridMap as GridMap
from ._front_end import MatchResult as MatchResult
from ._front_end import auto_range_cap as auto_range_cap
from ._front_end import grazing_lengths as grazing_lengths
from ._front_end import grid_map as grid_map
from ._front_end import match_scan as match_scan
from ._front_end import odometry_sigmas as odometry_sigmas
from ._front_end import run_front_end as run_front_end
from ._front_end import score_scan as score_scan
from ._loops import MIN_MEAN_LOG_LIKELIHOOD as MIN_MEAN_LOG_LIKELIHOOD
from ._loops import SCENE_MARGIN as SCENE_MARGIN
from ._loops import LoopConfig as LoopConfig
from ._loops import Loops as Loops
from ._loops import find_loops as find_loops
from ._loops import find_revisits as find_revisits
from ._loops import loop_threshold as loop_threshold
from ._loops import scene_log_likelihood as scene_log_likelihood
from ._pipeline import CHAIN_MODELS as CHAIN_MODELS
from ._pipeline import REJECTED_WEIGHT as REJECTED_WEIGHT
from ._pipeline import SlamConfig as SlamConfig
from ._pipeline import SlamResult as SlamResult
from ._pipeline import front_end_pose_graph as front_end_pose_graph
from ._pipeline import run_slam as run_slam
from ._pose_graph import PoseGraphResult as PoseGraphResult
from ._pose_graph import optimize_pose_graph as optimize_pose_graph
from ._search import correlative_search as correlative_search
