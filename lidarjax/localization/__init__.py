"""Particle-filter localization (dissertation sections 7.6.1, 8.5.2 and 12.4.3) and
gradient-based pose refinement, pole-landmark mapping and localization (ch. 12)."""

from ._filter import ParticleFilter, StepInfo
from ._global import PoseLattice, init_from_scan, lattice_scores, pose_lattice
from ._guided import GradientGuidedMotion, SmoothScanSurrogate, smooth_scan_surrogate
from ._landmarks import (
    PoleLookup,
    PoleMap,
    PoleMeasurementModel,
    build_pole_lookup,
    map_poles,
    merge_poles,
    overlap_clusters,
    pad_poles,
    segment_scans,
    sliding_window_filter,
)
from ._motion import OdometryMotionModel
from ._particles import (
    ParticleState,
    estimate,
    global_injector,
    init_gaussian,
    init_global,
    init_uniform_disc,
)
from ._poses import circular_mean, from_vector, relative_motion, take, to_vector, weighted_mean
from ._resampling import (
    RESAMPLERS,
    count_occupied_bins,
    effective_sample_size,
    kld_particle_count,
    multinomial_resample,
    normalize_log_weights,
    stratified_resample,
    systematic_resample,
)
from ._scan import CoarseToFineScanModel, ScanModel, coarse_to_fine_scan_model
from ._sharding import particle_mesh, shard_state
from .refine import (
    DCTScan,
    FieldScan,
    SmoothDecayRateField,
    SmoothDecayRateScan,
    refine_dct_scan_pose,
    refine_pose,
    refine_scan_pose,
    smooth_fields,
)

__all__ = [
    "DCTScan",
    "FieldScan",
    "SmoothDecayRateField",
    "SmoothDecayRateScan",
    "refine_dct_scan_pose",
    "refine_pose",
    "refine_scan_pose",
    "smooth_fields",
    "PoseLattice",
    "pose_lattice",
    "init_from_scan",
    "lattice_scores",
    "CoarseToFineScanModel",
    "coarse_to_fine_scan_model",
    "GradientGuidedMotion",
    "SmoothScanSurrogate",
    "smooth_scan_surrogate",
    "PoleMap",
    "overlap_clusters",
    "merge_poles",
    "sliding_window_filter",
    "map_poles",
    "PoleLookup",
    "build_pole_lookup",
    "PoleMeasurementModel",
    "pad_poles",
    "segment_scans",
    "RESAMPLERS",
    "OdometryMotionModel",
    "ParticleFilter",
    "ParticleState",
    "ScanModel",
    "StepInfo",
    "circular_mean",
    "effective_sample_size",
    "estimate",
    "from_vector",
    "init_gaussian",
    "init_global",
    "init_uniform_disc",
    "multinomial_resample",
    "normalize_log_weights",
    "relative_motion",
    "stratified_resample",
    "systematic_resample",
    "take",
    "to_vector",
    "weighted_mean",
    "count_occupied_bins",
    "global_injector",
    "kld_particle_count",
    "particle_mesh",
    "shard_state",
]
