"""lidarjax: probabilistic, differentiable lidar mapping and localization in JAX.

Layers (each imports only from the ones before it)::

    datasets (NumPy I/O) -> rays + raytrace (JAX kernels) -> maps / sensor_models / features
    -> localization
    sim (synthetic worlds, casting with raytrace's primitives) feeds the same types as datasets

See ``README.md`` and ``../shared/DESIGN.md``.
"""

__version__ = "0.1.0"

from ._runtime import enable_compilation_cache as enable_compilation_cache  # noqa: E402
from ._runtime import pin_to_one_core as pin_to_one_core  # noqa: E402

__all__ = ["__version__", "enable_compilation_cache", "pin_to_one_core"]
