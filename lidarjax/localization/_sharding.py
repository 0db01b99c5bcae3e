"""Particles sharded over devices: :func:`shard_state` places a :class:`ParticleState` with
its particles and log-weights split along the particle axis over a 1-D device mesh, and
:class:`~lidarjax.localization.ParticleFilter` keeps that layout.

What runs where inside a filter step on a sharded state (``ParticleFilter.step`` /
``run`` find the mesh from the concrete state's arrays and pass it as a static argument
of their compiled programs; a ``step`` under your own ``jit`` sees a traced state, no
mesh, and gets XLA's default partitioning, correct but not guaranteed bitwise):

- motion update: elementwise per particle, partitioned by XLA (GSPMD) over the shards
  (the noise comes from JAX's partitionable threefry, so every shard draws exactly the
  numbers the one-device filter draws for its particles);
- measurement update: a :class:`~lidarjax.localization.ScanModel` (the costly part) runs
  per shard under ``jax.shard_map``, each device on its own particles, native kernels
  included (the FFI fold kernel is called once per shard on that shard's rays); any other
  measurement model is left to GSPMD, which is correct for any function of the particles
  (a model that mixes particles, like ``CoarseToFineScanModel``'s spread, must see all
  of them, so it is not split by hand);
- the bookkeeping over all particles (normaliser, ``n_eff``, estimate, resampling's
  ``cumsum`` + ``searchsorted`` and gather, KLD-sampling's sort, injection): the
  particles and log-likelihoods are gathered (one all-gather of ``[n 4]`` poses and
  ``[n]`` log-likelihoods per step) and every device computes it on the full arrays,
  exactly as one device does; the new state is split again.

So a sharded filter gives bitwise the one-device results for the same key: no reduction
over particles is split into per-shard partial sums.
"""

from __future__ import annotations

import equinox as eqx
import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from .. import _checks
from ._particles import ParticleState

PARTICLE_AXIS = "particles"
"""Name of the mesh axis the particles are split over."""


def particle_mesh(devices=None) -> Mesh:
    """A 1-D :class:`jax.sharding.Mesh` with axis ``"particles"``.

    Args:
        devices: the devices (default: ``jax.devices()``, all devices of the default
            backend; on a CPU these are the host devices, one unless
            ``XLA_FLAGS=--xla_force_host_platform_device_count=k`` was set before JAX
            started).
    """
    devs = list(jax.devices() if devices is None else devices)
    if not devs:
        raise ValueError("devices must hold at least one device")
    return Mesh(np.asarray(devs, dtype=object), (PARTICLE_AXIS,))


def _check_mesh(mesh) -> Mesh:
    if not isinstance(mesh, Mesh):
        raise ValueError(f"mesh must be a jax.sharding.Mesh, got {type(mesh).__name__}")
    if tuple(mesh.axis_names) != (PARTICLE_AXIS,):
        raise ValueError(
            f"mesh must be 1-D with the axis name {PARTICLE_AXIS!r} (see particle_mesh), got "
            f"axes {tuple(mesh.axis_names)}"
        )
    return mesh


def _particle_leaves_map(fn_particles, fn_other, state: ParticleState) -> ParticleState:
    """``state`` with ``fn_particles`` applied to the leaves of the particles and the
    log-weights and ``fn_other`` to the other array leaves (key, counters)."""
    particles = jax.tree.map(fn_particles, state.particles)
    log_weights = fn_particles(state.log_weights)
    rest = (state.key, state.n_active, state.log_w_slow, state.log_w_fast, state.n_updates)
    rest = jax.tree.map(fn_other, rest)
    return eqx.tree_at(
        lambda s: (
            s.particles,
            s.log_weights,
            s.key,
            s.n_active,
            s.log_w_slow,
            s.log_w_fast,
            s.n_updates,
        ),
        state,
        (particles, log_weights, *rest),
    )


def shard_state(state: ParticleState, mesh: Mesh | None = None) -> ParticleState:
    """``state`` with its particles and log-weights split over the devices of ``mesh``
    along the particle axis (``NamedSharding(mesh, P("particles"))``); the key and the
    scalar fields are replicated.

    :meth:`ParticleFilter.step` and :meth:`ParticleFilter.run` keep the layout: their
    output states are sharded the same way, and their results equal the one-device
    results for the same key bitwise (see the module docstring).

    Args:
        state: an unbatched state (``[n]`` particles).
        mesh: a 1-D mesh with axis ``"particles"`` (default :func:`particle_mesh`: all
            devices).

    Returns:
        The same state, placed on the mesh.

    Raises:
        ValueError: ``n`` is not divisible by the number of devices of the mesh, the
            state is batched, or the mesh is not a 1-D ``"particles"`` mesh.
    """
    if not isinstance(state, ParticleState):
        raise ValueError(f"state must be a ParticleState, got {type(state).__name__}")
    mesh = particle_mesh() if mesh is None else _check_mesh(mesh)
    if state.log_weights.ndim != 1:
        raise ValueError(
            f"state must be unbatched ([n] log-weights) to be sharded, got log-weights of "
            f"shape {tuple(state.log_weights.shape)}"
        )
    n, d = state.n, mesh.devices.size
    if n % d:
        raise ValueError(
            f"n = {n} particles must be divisible by the number of devices ({d}) to shard "
            f"them; use a multiple of {d}"
        )
    split = NamedSharding(mesh, P(PARTICLE_AXIS))
    whole = NamedSharding(mesh, P())
    return _particle_leaves_map(
        lambda x: jax.device_put(x, split), lambda x: jax.device_put(x, whole), state
    )


def state_mesh(state: ParticleState) -> Mesh | None:
    """The mesh of a state placed by :func:`shard_state` (concrete arrays whose
    log-weights are split over a ``"particles"`` axis of more than one device), else
    None (traced, unsharded, or another layout: then XLA's default partitioning applies)."""
    lw = state.log_weights
    if isinstance(lw, jax.core.Tracer) or not isinstance(lw, jax.Array):
        return None
    sh = getattr(lw, "sharding", None)
    if not isinstance(sh, NamedSharding) or tuple(sh.mesh.axis_names) != (PARTICLE_AXIS,):
        return None
    if sh.mesh.devices.size < 2 or tuple(sh.spec)[:1] != (PARTICLE_AXIS,):
        return None
    return sh.mesh


def split(tree, mesh: Mesh | None):
    """Constrain every array leaf (leading axis ``[n]``) to be split over ``mesh``."""
    if mesh is None:
        return tree
    s = NamedSharding(mesh, P(PARTICLE_AXIS))
    return jax.tree.map(lambda x: jax.lax.with_sharding_constraint(x, s), tree)


def split_state(state: ParticleState, mesh: Mesh | None) -> ParticleState:
    """:func:`shard_state`'s layout as sharding constraints (inside a traced step)."""
    if mesh is None:
        return state
    a = NamedSharding(mesh, P(PARTICLE_AXIS))
    b = NamedSharding(mesh, P())
    return _particle_leaves_map(
        lambda x: jax.lax.with_sharding_constraint(x, a),
        lambda x: jax.lax.with_sharding_constraint(x, b),
        state,
    )


def _per_particle(measurement) -> bool:
    """Measurement models known to treat every particle on its own (safe to split)."""
    from ._scan import ScanModel

    return isinstance(measurement, ScanModel)


def measure(measurement, particles, z, mesh: Mesh | None):
    """``measurement(particles, z)``; with a ``mesh`` and a per-particle model
    (:class:`ScanModel`), evaluated per shard under ``jax.shard_map`` (each device on its
    own particles; native kernels run per shard). Run-time checks inside the model are
    returned per shard and re-attached at the caller's level (see :mod:`lidarjax._checks`).
    """
    if mesh is None or not _per_particle(measurement):
        return measurement(particles, z)
    arrays, static = eqx.partition(measurement, eqx.is_array)
    box: dict = {}

    def body(arrays, particles, z):
        model = eqx.combine(arrays, static)
        out, flags, messages = _checks._collect(model, particles, z)
        box["messages"] = messages
        return out, flags[None]

    out, flags = jax.shard_map(
        body,
        mesh=mesh,
        in_specs=(P(), P(PARTICLE_AXIS), P()),
        out_specs=(P(PARTICLE_AXIS), P(PARTICLE_AXIS)),
        check_vma=False,
    )(arrays, particles, z)
    return _checks._reattach(out, flags, box.get("messages", ()))


def replicated(fn, mesh: Mesh, *args):
    """``fn(*args)`` computed on the whole (gathered) arrays by every device of ``mesh``
    under ``jax.shard_map`` with replicated inputs and outputs: exactly the one-device
    computation (XLA cannot split its reductions into per-shard partial sums). Non-array
    leaves of ``args`` are static; run-time checks are re-attached at the caller's level."""
    arrays, static = eqx.partition(args, eqx.is_array)
    box: dict = {}

    def body(arrays):
        out, flags, messages = _checks._collect(fn, *eqx.combine(arrays, static))
        box["messages"] = messages
        out_arrays, out_static = eqx.partition(out, eqx.is_array)
        box["static"] = out_static
        return out_arrays, flags

    out_arrays, flags = jax.shard_map(
        body, mesh=mesh, in_specs=P(), out_specs=P(), check_vma=False
    )(arrays)
    out = eqx.combine(out_arrays, box["static"])
    return _checks._reattach(out, flags, box.get("messages", ()))
