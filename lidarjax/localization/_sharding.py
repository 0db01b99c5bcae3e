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
  included (the FFI fold kernel is called once per shard on that shard's rays, with
  this process's cores divided among its devices unless the model sets ``threads``);
- one all-gather per step (:func:`gather_then`): the new poses, the previous
  log-weights, the log-likelihoods and the per-shard check flags, packed bit for bit into
  one ``[n_local k]`` uint32 array;
- the bookkeeping over all particles (normaliser, ``n_eff``, estimate, resampling's
  ``cumsum`` + ``searchsorted`` and gather, KLD-sampling's sort, injection) then runs on
  every device on the full arrays, exactly as on one device; each device keeps its rows
  of the new state.

Any other measurement model (one that may mix particles, like
``CoarseToFineScanModel``'s spread) or a motion model with a proposal hook: the state is
gathered first (the same single all-gather) and the whole one-device step runs on every
device: bitwise the same results, without a speed-up.

So a sharded filter gives bitwise the one-device results for the same key: no reduction
over particles is split into per-shard partial sums.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
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

    Several processes (after ``jax.distributed.initialize``, e.g.
    :func:`lidarjax.distributed.initialize_cpu`): the default mesh spans the devices of
    every process; each process calls this with the same state (the same initialiser and
    key) and keeps the rows of its own devices. The results are global arrays: replicated
    ones (key, counters, the run's ``StepInfo``) read in any process, the particles by
    their ``addressable_shards``.

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
    return _particle_leaves_map(lambda x: _place(x, split), lambda x: _place(x, whole), state)


def _place(x, sharding: NamedSharding):
    """``x`` placed with ``sharding``. One process: ``jax.device_put``. Several processes
    (a mesh with other processes' devices, after ``jax.distributed.initialize``): every
    process holds the whole, identical ``x`` (e.g. drawn from the same key) and puts the
    rows of its own devices from a host copy; an array already global is resharded."""
    if sharding.is_fully_addressable:
        return jax.device_put(x, sharding)
    if isinstance(x, jax.Array) and not x.is_fully_addressable:
        return x if x.sharding == sharding else jax.jit(lambda a: a, out_shardings=sharding)(x)
    if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
        data = _place(jax.random.key_data(x), sharding)
        return jax.random.wrap_key_data(data, impl=jax.random.key_impl(x))
    return jax.device_put(np.asarray(x), sharding)


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


def threads_per_shard(mesh: Mesh) -> int:
    """Native worker threads per shard: this process's cores divided among its devices
    of ``mesh`` (at least 1), so that the shards' kernels do not oversubscribe the
    cores."""
    from ..raytrace._native import default_threads

    mine = sum(1 for d in mesh.devices.flat if d.process_index == jax.process_index())
    return max(1, default_threads() // max(1, mine))


def per_particle(measurement) -> bool:
    """Measurement models known to treat every particle on its own (safe to split)."""
    from ._scan import ScanModel

    return isinstance(measurement, ScanModel)


def _to_words(x) -> jax.Array:
    """``[m ...]`` array -> ``[m k]`` uint32 words holding its bits exactly."""
    m = x.shape[0]
    x = x.reshape(m, -1)
    if x.dtype == jnp.bool_:
        return x.astype(jnp.uint32)
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        raise ValueError(f"sharded particle arrays cannot be complex, got {x.dtype}")
    size = x.dtype.itemsize
    if size == 8:
        return jax.lax.bitcast_convert_type(x, jnp.uint32).reshape(m, -1)
    if size == 4:
        return jax.lax.bitcast_convert_type(x, jnp.uint32)
    narrow = {2: jnp.uint16, 1: jnp.uint8}[size]
    return jax.lax.bitcast_convert_type(x, narrow).astype(jnp.uint32)


def _from_words(w, tail: tuple[int, ...], dtype) -> jax.Array:
    """Inverse of :func:`_to_words` for an array of trailing shape ``tail``."""
    m = w.shape[0]
    dtype = jnp.dtype(dtype)
    if dtype == jnp.bool_:
        x = w != 0
    elif dtype.itemsize == 8:
        x = jax.lax.bitcast_convert_type(w.reshape(m, -1, 2), dtype)
    elif dtype.itemsize == 4:
        x = jax.lax.bitcast_convert_type(w, dtype)
    else:
        narrow = {2: jnp.uint16, 1: jnp.uint8}[dtype.itemsize]
        x = jax.lax.bitcast_convert_type(w.astype(narrow), dtype)
    return x.reshape((m, *tail))


def gather_then(local_fn, full_fn, mesh: Mesh, split_in, rep_in):
    """One sharded filter step's communication pattern, with exactly one collective.

    Under one ``jax.shard_map`` over ``mesh``: ``local_fn(split_local, rep)`` runs on
    each device's rows of ``split_in`` (arrays with a leading ``[n]`` axis, split over the
    devices) and returns arrays with the same leading (local) axis; those are packed bit
    for bit into one ``[n_local k]`` uint32 array (with the per-shard check flags) and
    gathered with a single ``all_gather``; then ``full_fn(split_full, rep)`` runs on the
    whole arrays on every device (exactly the one-device computation) and returns
    ``(split_out, rep_out)``: ``split_out`` (leading ``[n]``) comes back split over the
    devices, ``rep_out`` replicated. ``rep_in``'s array leaves are replicated inputs, its
    other leaves static. Run-time checks of both functions are re-attached at the caller's
    level (see :mod:`lidarjax._checks`).

    Why a single collective: XLA's CPU runtime runs independent operations of a program
    concurrently on one shared thread pool, and each device's part of a collective holds
    a pool thread until every device has arrived. Several independent collectives per
    step (one all-gather per gathered array, an all-reduce of the check flags) can take
    every thread of a small pool for one device while the other waits for a thread (a
    deadlock XLA aborts after 40 s, seen on a 2-core machine). One collective per step,
    each depending on the previous step's result, holds at most one thread per device.
    """
    d = mesh.devices.size
    rep_arrays, rep_static = eqx.partition(rep_in, eqx.is_array)
    box: dict = {}

    def body(split_local, rep_arrays):
        rep = eqx.combine(rep_arrays, rep_static)
        loc, f_local, m_local = _checks._collect(local_fn, split_local, rep)
        leaves, treedef = jax.tree.flatten(loc)
        n_local = leaves[0].shape[0]
        cols = [_to_words(x) for x in leaves]
        cols.append(jnp.broadcast_to(f_local.astype(jnp.uint32), (n_local, f_local.shape[0])))
        edges = np.cumsum([0] + [c.shape[1] for c in cols])
        payload = jnp.concatenate(cols, axis=1)
        whole = jax.lax.all_gather(payload, PARTICLE_AXIS, axis=0, tiled=True)
        full = [
            _from_words(whole[:, edges[i] : edges[i + 1]], x.shape[1:], x.dtype)
            for i, x in enumerate(leaves)
        ]
        f_all = whole[:, edges[-2] : edges[-1]].reshape(d, n_local, -1)[:, 0, :]
        f_all = jnp.any(f_all != 0, axis=0)
        (split_out, rep_out), f_full, m_full = _checks._collect(
            full_fn, jax.tree.unflatten(treedef, full), rep
        )
        i = jax.lax.axis_index(PARTICLE_AXIS)
        split_out = jax.tree.map(
            lambda x: jax.lax.dynamic_slice_in_dim(x, i * n_local, n_local, axis=0), split_out
        )
        rep_out_arrays, box["static"] = eqx.partition(rep_out, eqx.is_array)
        box["messages"] = m_local + m_full
        return split_out, rep_out_arrays, jnp.concatenate([f_all, f_full])

    split_out, rep_out_arrays, flags = jax.shard_map(
        body,
        mesh=mesh,
        in_specs=(P(PARTICLE_AXIS), P()),
        out_specs=(P(PARTICLE_AXIS), P(), P()),
        check_vma=False,
    )(split_in, rep_arrays)
    out = (split_out, eqx.combine(rep_out_arrays, box["static"]))
    return _checks._reattach(out, flags, box["messages"])
