"""Feature extraction from lidar scans: polylines (PLE / PLE+, dissertation ch. 10) with the
heuristic baselines of section 10.5 (Visvalingam, iterative endpoint fit, split-and-merge),
planes (PPE, ch. 11) with the MSAC and PEAC-style baselines, and poles (ch. 12)."""

from ._plane_baselines import msac_planes as msac_planes
from ._plane_baselines import peac_planes as peac_planes
from ._plane_fit import PlaneFit as PlaneFit
from ._plane_fit import default_plane_solver as default_plane_solver
from ._plane_fit import fit_planes as fit_planes
from ._plane_fit import plane_error as plane_error
from ._plane_fit import plane_ranges as plane_ranges
from ._plane_fit import refit_segmentation as refit_segmentation
from ._plane_stats import linearized_plane_error as linearized_plane_error
from ._poles import PoleConfig as PoleConfig
from ._poles import Poles as Poles
from ._poles import extract_poles as extract_poles
from ._poles import extract_poles_from_occupancy as extract_poles_from_occupancy
from ._poles import fast_occupancy as fast_occupancy
from ._poles import local_map_spec as local_map_spec
from ._poles import matched_beta_prior as matched_beta_prior
from ._poles import mean_shift as mean_shift
from ._poles import pole_score_image as pole_score_image
from ._poles import pole_score_maps as pole_score_maps
from ._polyline import AIC as AIC
from ._polyline import AbstractStoppingCriterion as AbstractStoppingCriterion
from ._polyline import MaxRMSE as MaxRMSE
from ._polyline import MaxVertices as MaxVertices
from ._polyline import PolylineExtraction as PolylineExtraction
from ._polyline import PolylineStats as PolylineStats
from ._polyline import extract_polylines as extract_polylines
from ._polyline import is_full_revolution as is_full_revolution
from ._polyline_baselines import iterative_endpoint_fit as iterative_endpoint_fit
from ._polyline_baselines import point_segment_distance as point_segment_distance
from ._polyline_baselines import split_and_merge as split_and_merge
from ._polyline_baselines import visvalingam as visvalingam
from ._polyline_map import PolylineMap as PolylineMap
from ._polyline_plus import PolylineOptimization as PolylineOptimization
from ._polyline_plus import default_plus_solver as default_plus_solver
from ._polyline_plus import optimize_polylines as optimize_polylines
from ._ppe import extract_planes as extract_planes
from ._ppe import extract_planes_path as extract_planes_path
from ._ppe_result import PlaneSegmentation as PlaneSegmentation
from ._ppe_result import PPEStop as PPEStop
from ._ppe_scan import TETROMINOES as TETROMINOES
from ._ppe_threshold import AUTO_FLOOR_M2 as AUTO_FLOOR_M2
from ._ppe_threshold import AUTO_KAPPA as AUTO_KAPPA
from ._ppe_threshold import auto_max_increment as auto_max_increment
from ._ppe_threshold import estimate_noise as estimate_noise

__all__ = [
    "PolylineMap",
    "PolylineStats",
    "PolylineExtraction",
    "AbstractStoppingCriterion",
    "MaxVertices",
    "MaxRMSE",
    "AIC",
    "extract_polylines",
    "optimize_polylines",
    "default_plus_solver",
    "PolylineOptimization",
    "is_full_revolution",
    "visvalingam",
    "iterative_endpoint_fit",
    "split_and_merge",
    "point_segment_distance",
    "plane_ranges",
    "plane_error",
    "PlaneFit",
    "fit_planes",
    "default_plane_solver",
    "linearized_plane_error",
    "TETROMINOES",
    "PlaneSegmentation",
    "PPEStop",
    "extract_planes",
    "extract_planes_path",
    "estimate_noise",
    "auto_max_increment",
    "AUTO_KAPPA",
    "AUTO_FLOOR_M2",
    "refit_segmentation",
    "msac_planes",
    "peac_planes",
    "PoleConfig",
    "Poles",
    "pole_score_maps",
    "pole_score_image",
    "mean_shift",
    "extract_poles",
    "extract_poles_from_occupancy",
    "local_map_spec",
    "fast_occupancy",
    "matched_beta_prior",
]
