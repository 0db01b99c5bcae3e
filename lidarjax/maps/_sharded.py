"""The DCT fit's ray sums split over devices (issue #23): :func:`dct_objective_sharded`
and :func:`fit_dct_sharded`.

The costly part of the DCT fit is the precomputation of the summed weights ``w_free``
over all HIT and SUP rays (Sec. 9.4.4); the solve itself works on a spectrum. Here the
rays are cut into one contiguous group per device, each device sums its group, and the
sums are added on the first device; the solve then runs as in :func:`fit_dct`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.sharding import Mesh

from ..rays import RayBatch
from ..raytrace._sharded import RAY_AXIS, _mesh_axis
from ._dct import DCTMap
from ._fit import _fit_box, _minimise, dct_objective, grid_initial_map

__all__ = ["dct_objective_sharded", "fit_dct_sharded"]


def dct_objective_sharded(
    rays: RayBatch,
    lower,
    extent,
    shape: tuple[int, ...],
    mesh: Mesh | None = None,
    *,
    chunk_size: int = 256,
    check: bool = True,
    method: str = "spectral",
):
    """:func:`~lidarjax.maps.dct_objective` with its ray sums split over devices.

    The ``n`` rays (flattened) are cut into ``k`` contiguous groups, one per device of
    ``mesh``; ``dct_objective`` of each group runs on its device (JAX dispatches them
    asynchronously, so the devices work concurrently on the costly summed weights
    ``w_free``); then the ``k`` sums are added on the first device and the per-ray
    parts (SUB weights, HIT end points) concatenated in ray order. The result is an
    ordinary :class:`~lidarjax.maps.DCTObjective` on the first device: ``w_sub``,
    ``hit_points`` and ``n_rays`` equal the one-device objective's exactly, ``w_free``
    to float rounding (partial sums added in another order). No collective: a
    device-to-device copy of one spectrum per group.

    Args:
        rays, lower, extent, shape, chunk_size, check, method: as for
            ``dct_objective``.
        mesh: a 1-D mesh (default :func:`~lidarjax.raytrace.device_mesh`: all devices).
    """
    mesh, _ = _mesh_axis(mesh, RAY_AXIS)
    if not isinstance(rays, RayBatch):
        raise ValueError(f"rays must be a RayBatch, got {type(rays).__name__}")
    flat = rays.flatten()
    n = flat.ranges.shape[0]
    if n == 0:
        raise ValueError("rays is empty")
    devices = list(mesh.devices.flat)[:n]
    edges = np.linspace(0, n, len(devices) + 1).round().astype(int)
    host = [np.asarray(x) for x in (flat.origins, flat.directions, flat.ranges, flat.kind)]
    parts = []
    for dev, lo, hi in zip(devices, edges[:-1], edges[1:]):
        with jax.default_device(dev):
            group = RayBatch(
                *(jax.device_put(x[lo:hi], dev) for x in host),
                np.asarray(flat.r_min),
                np.asarray(flat.r_max),
            )
            parts.append(
                dct_objective(
                    group, lower, extent, shape, chunk_size=chunk_size, check=check, method=method
                )
            )
    move = functools.partial(jax.device_put, device=devices[0])
    w_free = move(parts[0].w_free)
    for part in parts[1:]:
        w_free = w_free + move(part.w_free)
    return type(parts[0])(
        lower=move(parts[0].lower),
        extent=move(parts[0].extent),
        w_free=w_free,
        w_sub=jnp.concatenate([move(q.w_sub) for q in parts]),
        hit_points=jnp.concatenate([move(q.hit_points) for q in parts]),
        n_rays=int(sum(q.n_rays for q in parts)),
    )


def fit_dct_sharded(
    rays: RayBatch,
    shape: tuple[int, ...] | None = None,
    *,
    lower=None,
    extent=None,
    init: DCTMap | None = None,
    mesh: Mesh | None = None,
    solver: optx.AbstractMinimiser | None = None,
    rtol: float = 1e-3,
    atol: float = 1e-3,
    max_steps: int = 1000,
    throw: bool = False,
    chunk_size: int = 256,
) -> tuple[DCTMap, optx.Solution]:
    """:func:`~lidarjax.maps.fit_dct` with the ray sums computed per device
    (:func:`dct_objective_sharded`); the arguments are ``fit_dct``'s plus ``mesh``
    (default: all devices). The objective equals the one-device one to float rounding
    (``w_free`` summed in another order), so the fit agrees with ``fit_dct`` to the
    solver's tolerance. Unlike ``fit_dct`` the rays are not padded to shape buckets (a
    new ray count compiles the set-up again).

    Returns:
        ``(map, solution)`` as for ``fit_dct``.
    """
    shape, lower, extent = _fit_box(init, shape, lower, extent)
    obj = dct_objective_sharded(rays, lower, extent, tuple(shape), mesh, chunk_size=chunk_size)
    if init is None:
        init = grid_initial_map(rays, lower, extent, tuple(shape))
    a0 = jax.device_put(jnp.asarray(init.coeffs, obj.w_free.dtype), obj.w_free.device)
    if solver is None:
        solver = optx.LBFGS(rtol=rtol, atol=atol)
    sol = _minimise(obj, solver, a0, max_steps, throw)
    return DCTMap(sol.value, obj.lower, obj.extent), sol
