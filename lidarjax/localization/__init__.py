"""Particle-filter localization (dissertation sections 7.6.1, 8.5.2 and 12.4.3) and
gradient-based pose refinement."""

from ._filter import (
    RESAMPLERS,
    OdometryMotionModel,
    ParticleFilter,
    ParticleState,
    StepInfo,
    effective_sample_size,
    estimate,
    init_gaussian,
    init_global,
    init_uniform_disc,
    multinomial_resample,
    normalize_log_weights,
    stratified_resample,
    systematic_resample,
)
from ._poses import circular_mean, from_vector, relative_motion, take, to_vector, weighted_mean
from ._scan import ScanModel

__all__ = [
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
]
