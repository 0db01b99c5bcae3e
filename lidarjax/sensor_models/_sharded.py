"""Likelihood of a scan at many poses with the poses split over devices (issue #23).

A pose's sum over its rays never crosses devices when the poses are split, so every
device evaluates its share of the poses (padded with copies of the last pose) on its
own copy of the map, and the program has no collective at all (see
:mod:`lidarjax.raytrace._sharded` for why lidarjax keeps collectives to one per program).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from .. import _checks
from ..maps import AbstractGridModel
from ..raytrace import max_cells_for, n_chunks_for
from ..raytrace._sharded import RAY_AXIS, _mesh_axis
from ._common import _pose_params, log_likelihood_at_poses

__all__ = ["log_likelihood_at_poses_sharded"]


def _poses_inputs(model, azimuths_rad, ranges_m, poses, mesh, r_min, r_max, chunk_size, max_cells):
    """Checked, padded and placed ``(args, kwargs)`` of :func:`_poses_program` (and
    ``n_pad`` in ``kwargs``: the padding poses at the end)."""
    mesh, axis = _mesh_axis(mesh, RAY_AXIS)
    if not (isinstance(model, AbstractGridModel) or callable(model)):
        raise ValueError(
            f"model must be a grid model (an AbstractGridModel) or a callable, got "
            f"{type(model).__name__}"
        )
    params = np.asarray(_pose_params(poses))
    if isinstance(model, AbstractGridModel) and max_cells is None:
        max_cells = max_cells_for(model.spec, model.walk_bound_m(r_min, r_max))
    p = params.shape[0]
    if p == 0:
        raise ValueError("poses is empty")
    n_dev = mesh.devices.size
    n_pad = n_chunks_for(p, n_dev) * n_dev - p
    if n_pad:  # padding poses: copies of the last one
        params = np.concatenate([params, np.repeat(params[-1:], n_pad, axis=0)])
    whole = NamedSharding(mesh, P())
    rep, static = eqx.partition(model, eqx.is_array)
    args = (
        jax.device_put(rep, whole),
        jax.device_put(jnp.asarray(azimuths_rad), whole),
        jax.device_put(jnp.asarray(ranges_m), whole),
        jax.device_put(params, NamedSharding(mesh, P(axis))),
    )
    kwargs = dict(
        static=static,
        mesh=mesh,
        r_min=r_min,
        r_max=r_max,
        chunk_size=chunk_size,
        max_cells=max_cells,
        n_pad=n_pad,
    )
    return args, kwargs


def log_likelihood_at_poses_sharded(
    model,
    azimuths_rad,
    ranges_m,
    poses,
    mesh: Mesh | None = None,
    *,
    r_min: float = 0.0,
    r_max: float = np.inf,
    chunk_size: int = 64,
    max_cells: int | None = None,
) -> jax.Array:
    """:func:`~lidarjax.sensor_models.log_likelihood_at_poses` (Eq. 7.15) with the poses
    split over the devices of a 1-D mesh.

    Design: a pose's sum over its rays never crosses devices when the poses are split,
    so every device evaluates its ``p / k`` poses (padded with copies of the last pose)
    on its own copy of the map and the program has no collective at all. The values
    equal the one-device values to float rounding (the same walks; XLA may fuse the sum
    over a pose's rays differently in the sharded program: 1 ulp measured); the
    run-time checks of every shard are read on the host after the call.

    Args:
        model, azimuths_rad, ranges_m, r_min, r_max, chunk_size, max_cells: as for
            ``log_likelihood_at_poses`` (``chunk_size`` poses per ``vmap`` chunk on each
            device).
        poses: ``[p 3]`` ``(x, y, theta)`` (m, m, rad) or a ``jaxlie.SE2`` with batch
            axes ``[p]``.
        mesh: a 1-D mesh (default :func:`~lidarjax.raytrace.device_mesh`: all devices).

    Returns:
        ``[p]`` log-likelihoods, split over the mesh (``NamedSharding(mesh, P(axis))``
        when ``p`` is a multiple of the device count).
    """
    args, kwargs = _poses_inputs(
        model, azimuths_rad, ranges_m, poses, mesh, r_min, r_max, chunk_size, max_cells
    )
    n_pad = kwargs.pop("n_pad")
    ll, flags, messages = _poses_program(*args, **kwargs)
    ll = _checks._reattach(ll, flags, messages)  # concrete flags: read on the host
    return ll[: ll.shape[0] - n_pad] if n_pad else ll


@eqx.filter_jit
def _poses_program(rep, az, rng, params, *, static, mesh, r_min, r_max, chunk_size, max_cells):
    """Per-shard ``log_likelihood_at_poses``; returns the per-shard check flags
    (``[k n_checks]``, split) instead of reducing them (which would be a collective)."""
    axis = mesh.axis_names[0]
    box: dict = {}

    def local(rep, az, rng, params):
        model = eqx.combine(rep, static)
        return log_likelihood_at_poses(
            model,
            az,
            rng,
            jaxlie.SE2(params),
            r_min=r_min,
            r_max=r_max,
            chunk_size=chunk_size,
            max_cells=max_cells,
        )

    def body(rep, az, rng, params):
        ll, flags, box["messages"] = _checks._collect(local, rep, az, rng, params)
        return ll, flags[None]

    ll, flags = jax.shard_map(
        body,
        mesh=mesh,
        in_specs=(P(), P(), P(), P(axis)),
        out_specs=(P(axis), P(axis)),
        check_vma=False,
    )(rep, az, rng, params)
    return ll, flags, box["messages"]
