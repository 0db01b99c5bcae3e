"""Feature extraction from lidar scans: polylines (PLE / PLE+, dissertation ch. 10)."""

from ._polyline import AIC as AIC
from ._polyline import AbstractStoppingCriterion as AbstractStoppingCriterion
from ._polyline import MaxRMSE as MaxRMSE
from ._polyline import MaxVertices as MaxVertices
from ._polyline import PolylineExtraction as PolylineExtraction
from ._polyline import PolylineMap as PolylineMap
from ._polyline import PolylineOptimization as PolylineOptimization
from ._polyline import PolylineStats as PolylineStats
from ._polyline import extract_polylines as extract_polylines
from ._polyline import is_full_revolution as is_full_revolution
from ._polyline import optimize_polylines as optimize_polylines

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
    "PolylineOptimization",
    "is_full_revolution",
]
