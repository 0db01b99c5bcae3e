"""Evaluation measures from the dissertation: map RMSE in p_ref (section 9.5.1), the
pose-likelihood divergences of Eqs. (7.28), (7.29), (8.24)/(8.25), the polyline metrics of
section 10.5, the plane-segmentation metrics of chapter 11 (Hoover scores, k, RMSE) and
the trajectory errors of Table 12.2, and a reference-free map consistency of a
trajectory (cross-visit end-point distances)."""

from ._consistency import CrossVisitDistance as CrossVisitDistance
from ._consistency import cross_visit_distance as cross_visit_distance
from ._maps import dirac_divergence as dirac_divergence
from ._maps import gaussian_log_density as gaussian_log_density
from ._maps import inverse_kl as inverse_kl
from ._maps import kl_to_gaussian as kl_to_gaussian
from ._maps import map_rmse as map_rmse
from ._maps import p_ref as p_ref
from ._maps import p_ref_rmse as p_ref_rmse
from ._polyline import area_ratio as area_ratio
from ._polyline import explained_fraction as explained_fraction
from ._polyline import polygon_area as polygon_area
from ._polyline import ray_rmse as ray_rmse
from ._polyline import star_polygon as star_polygon
from ._segmentation import HooverScores as HooverScores
from ._segmentation import hoover_scores as hoover_scores
from ._segmentation import k_value as k_value
from ._segmentation import segmentation_rmse as segmentation_rmse
from ._trajectory import AbsoluteTrajectoryError as AbsoluteTrajectoryError
from ._trajectory import RelativePoseError as RelativePoseError
from ._trajectory import TrajectoryErrors as TrajectoryErrors
from ._trajectory import absolute_trajectory_error as absolute_trajectory_error
from ._trajectory import align_se2 as align_se2
from ._trajectory import interpolate_at_arclength as interpolate_at_arclength
from ._trajectory import relative_pose_error as relative_pose_error
from ._trajectory import trajectory_errors as trajectory_errors

__all__ = [
    "p_ref",
    "map_rmse",
    "p_ref_rmse",
    "dirac_divergence",
    "inverse_kl",
    "kl_to_gaussian",
    "gaussian_log_density",
    "ray_rmse",
    "explained_fraction",
    "polygon_area",
    "star_polygon",
    "area_ratio",
    "HooverScores",
    "hoover_scores",
    "k_value",
    "segmentation_rmse",
    "TrajectoryErrors",
    "trajectory_errors",
    "AbsoluteTrajectoryError",
    "absolute_trajectory_error",
    "relative_pose_error",
    "RelativePoseError",
    "align_se2",
    "interpolate_at_arclength",
    "CrossVisitDistance",
    "cross_visit_distance",
]
