"""Grid maps (dissertation chs. 7-8) built from :class:`~lidarjax.raytrace.GridStats`:
maximum-likelihood decay-rate, reflection and endpoint maps, and the closed-form full map
posteriors (Beta / Gamma per cell) with their measurement likelihoods and occupancy; DCT
maps (ch. 9): continuous decay-rate maps with closed-form likelihoods and an optimistix fit;
the decay-rate field interface (``AbstractDecayRateField``: grid, DCT or a user's field,
one forward model ``field_log_likelihood`` and one optimistix ``fit``); kernel smoothing
of the statistics for robust localization (``smooth_stats``) and the continuous
(bilinear, optionally blurred) field of a grid map for pose refinement
(``SmoothDecayRateField``); the grid-model protocol (``AbstractGridModel``: per-cell term,
finish and walk, shared by every likelihood driver; ``grid_log_likelihood`` evaluates any
grid model differentiably);
GPOM and Hilbert-map baselines (``lidarjax.maps.baselines``, scikit-learn)."""

from ._dct import DCTMap as DCTMap
from ._dct import closed_form_derivatives as dct_closed_form_derivatives
from ._dct import closed_form_terms as dct_closed_form_terms
from ._dct import dct_spectrum as dct_spectrum
from ._dct import from_grid as dct_from_grid
from ._dct import log_likelihood as dct_log_likelihood
from ._dct import optical_depth as dct_optical_depth
from ._dct import quadrature_nodes as dct_quadrature_nodes
from ._dct import rays_in_box as rays_in_box
from ._dct import to_grid as dct_to_grid
from ._field import AbstractDecayRateField as AbstractDecayRateField
from ._field import AbstractQuadratureField as AbstractQuadratureField
from ._field import field_log_likelihood as field_log_likelihood
from ._field import fit as fit
from ._fit import DCTObjective as DCTObjective
from ._fit import dct_objective as dct_objective
from ._fit import fit_dct as fit_dct
from ._fit import grid_initial_map as dct_grid_initial_map
from ._grid import DecayRateMap as DecayRateMap
from ._grid import EndpointMap as EndpointMap
from ._grid import ReflectionMap as ReflectionMap
from ._grid import decay_rate_map as decay_rate_map
from ._grid import distance_transform as distance_transform
from ._grid import endpoint_map as endpoint_map
from ._grid import reflection_map as reflection_map
from ._model import AbstractGridModel as AbstractGridModel
from ._model import GridWalk as GridWalk
from ._model import walk_log_likelihood as grid_log_likelihood
from ._posterior import BetaPosteriorMap as BetaPosteriorMap
from ._posterior import GammaPosteriorMap as GammaPosteriorMap
from ._posterior import beta_moment_prior as beta_moment_prior
from ._posterior import beta_posterior as beta_posterior
from ._posterior import gamma_moment_prior as gamma_moment_prior
from ._posterior import gamma_posterior as gamma_posterior
from ._posterior import log_likelihood as posterior_log_likelihood
from ._posterior import occupancy as occupancy
from ._sharded import dct_objective_sharded as dct_objective_sharded
from ._sharded import fit_dct_sharded as fit_dct_sharded
from ._smooth_field import SmoothDecayRateField as SmoothDecayRateField
from ._smoothing import blur as blur
from ._smoothing import smooth_cells as smooth_cells
from ._smoothing import smooth_stats as smooth_stats

__all__ = [
    "dct_objective_sharded",
    "fit_dct_sharded",
    "AbstractDecayRateField",
    "AbstractQuadratureField",
    "field_log_likelihood",
    "fit",
    "DCTMap",
    "DCTObjective",
    "dct_closed_form_derivatives",
    "dct_closed_form_terms",
    "dct_from_grid",
    "dct_grid_initial_map",
    "dct_log_likelihood",
    "dct_objective",
    "dct_optical_depth",
    "dct_quadrature_nodes",
    "dct_spectrum",
    "dct_to_grid",
    "fit_dct",
    "rays_in_box",
    "AbstractGridModel",
    "GridWalk",
    "grid_log_likelihood",
    "DecayRateMap",
    "ReflectionMap",
    "EndpointMap",
    "decay_rate_map",
    "reflection_map",
    "endpoint_map",
    "distance_transform",
    "BetaPosteriorMap",
    "GammaPosteriorMap",
    "beta_posterior",
    "gamma_posterior",
    "beta_moment_prior",
    "gamma_moment_prior",
    "posterior_log_likelihood",
    "occupancy",
    "SmoothDecayRateField",
    "blur",
    "smooth_cells",
    "smooth_stats",
]
