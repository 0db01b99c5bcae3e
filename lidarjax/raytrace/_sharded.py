"""Ray statistics over several devices (issue #23): rays split over the devices, or a grid
split into row tiles over them.

- :func:`accumulate_sharded`: the rays of a batch are split over the devices of a 1-D
  mesh (padded to a multiple of the device count with rays that contribute exactly
  nothing); every device walks its rays into a full-grid ``H``/``M``/``R`` (the native
  kernel per shard when available, else the JAX walk), and **one** ``psum`` of one packed
  array adds them up. The result is replicated on every device. ``H`` and ``M`` equal
  :func:`~lidarjax.raytrace.accumulate`'s exactly; ``R`` to float rounding (the partial
  sums are added in another order). Speed: the JAX walk runs serially on one device, so
  ``k`` devices can walk up to ``k`` times as many rays per second; the native kernel
  already uses every core on one device, so more *host* devices of the same CPU cannot
  speed it up (``benchmarks/scaling.py`` measures both).
- :func:`accumulate_tiled`: a grid larger than one device's memory, as row tiles
  (``shape[0] / k`` rows per device, ``NamedSharding(mesh, P("tiles", None))``). Every
  device walks every ray over the whole grid's geometry (the same walk as the one-device
  JAX path, so the same cells and lengths) and adds only into the cells of its own tile
  (other cells go to a discarded bin). No collective at all. Rays are streamed in chunks
  of ``ray_chunk`` rays, replicated to all devices, so a device holds its tile, its
  accumulators and one chunk. Limits: every device walks every ray (no speed-up, only
  memory); the JAX walk only (a native walk on the tile's own :class:`GridSpec` clips
  rays to the tile box and does not reproduce the full walk's cells exactly: the tile
  origin ``origin + row0 * resolution`` rounds, and so do the crossings and the
  tolerance of sliver segments; measured on random rays: hundreds of differing counts).
The same split for the likelihood at poses and the DCT objective lives in the layers
that own those functions: :func:`lidarjax.sensor_models.log_likelihood_at_poses_sharded`
and :func:`lidarjax.maps.dct_objective_sharded` / :func:`lidarjax.maps.fit_dct_sharded`.

Why one collective per program: XLA's CPU runtime runs independent operations of a
program concurrently on one shared thread pool, and each device's part of a collective
holds a pool thread until every device has arrived; several independent collectives can
deadlock a small pool (see :func:`lidarjax.localization._sharding.gather_then`). So the
counts and lengths are packed into one float array (counts exactly: split into digits
whose sums over the devices stay below the float's ``2**mantissa``) and reduced by one
``psum``; the run-time check flags of the JAX walk travel in the same array.
"""

from __future__ import annotations

import math
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from .. import _checks
from ..rays import SUB, RayBatch
from . import _native
from ._grid import (
    _BLOCK_RAYS,
    GridSpec,
    GridStats,
    _accumulate,
    _accumulate_args,
    _accumulate_blocks,
)
from ._primitives import n_chunks_for

RAY_AXIS = "rays"
"""Default name of the mesh axis rays (or poses) are split over."""
TILE_AXIS = "tiles"
"""Default name of the mesh axis grid row tiles are split over."""


def device_mesh(axis_name: str = RAY_AXIS, devices=None) -> Mesh:
    """A 1-D :class:`jax.sharding.Mesh` over ``devices`` with one axis ``axis_name``.

    Args:
        axis_name: the mesh axis name (``"rays"`` for :func:`accumulate_sharded`,
            ``"tiles"`` for :func:`accumulate_tiled`; any name works with both).
        devices: the devices (default ``jax.devices()``; on a CPU one device unless
            ``XLA_FLAGS=--xla_force_host_platform_device_count=k`` was set before JAX
            started).
    """
    if not isinstance(axis_name, str) or not axis_name:
        raise ValueError(f"axis_name must be a non-empty str, got {axis_name!r}")
    devs = list(jax.devices() if devices is None else devices)
    if not devs:
        raise ValueError("devices must hold at least one device")
    return Mesh(np.asarray(devs, dtype=object), (axis_name,))


def _mesh_axis(mesh, default_axis: str) -> tuple[Mesh, str]:
    """``(mesh, its axis name)``; ``None`` is a mesh over all devices."""
    if mesh is None:
        mesh = device_mesh(default_axis)
    if not isinstance(mesh, Mesh):
        raise ValueError(f"mesh must be a jax.sharding.Mesh, got {type(mesh).__name__}")
    if len(mesh.axis_names) != 1:
        raise ValueError(
            f"mesh must be 1-D (one axis, see device_mesh), got axes {tuple(mesh.axis_names)}"
        )
    return mesh, mesh.axis_names[0]


def _flat_rays(spec: GridSpec, rays: RayBatch, sub_rays: str, chunk_size: int):
    """:func:`~lidarjax.raytrace.accumulate`'s checks and flat ``[n]`` ray arrays, as host
    arrays: ``(o, d, r, kind, r_max)``."""
    o, d, r, k, r_max = _accumulate_args(spec, rays, sub_rays, chunk_size)
    return (*(np.asarray(x) for x in (o, d, r)), np.asarray(k, np.int32), np.asarray(r_max))


def _pad_rays(spec: GridSpec, o, d, r, k, n_total: int):
    """The rays padded to ``n_total`` with rays that contribute exactly nothing: SUB rays
    of range 0 starting one cell below the grid's lower corner, pointing away from it
    (ignored by default; with ``sub_rays="hit"`` a zero-length ray outside the grid,
    which visits no cell and records no hit)."""
    pad = n_total - o.shape[0]
    if pad == 0:
        return o, d, r, k
    dim = o.shape[1]
    corner = np.asarray(spec.origin, o.dtype) - np.asarray(spec.resolution, o.dtype)
    away = np.zeros(dim, o.dtype)
    away[0] = -1.0
    return (
        np.concatenate([o, np.broadcast_to(corner, (pad, dim))]),
        np.concatenate([d, np.broadcast_to(away, (pad, dim))]),
        np.concatenate([r, np.zeros(pad, r.dtype)]),
        np.concatenate([k, np.full(pad, SUB, np.int32)]),
    )


# ------------------------------------------------------------------ rays over devices


def _count_digits(dtype, n_devices: int, max_count: int) -> tuple[int, int]:
    """``(bits, pieces)``: counts (``0 <= c <= max_count < 2**31``) split into ``pieces``
    digits of ``bits`` bits whose sums over ``n_devices`` devices are exact in ``dtype``."""
    mant = jnp.finfo(dtype).nmant + 1  # integers up to 2**mant are exact
    if max_count < 2**mant:  # a count summed over all devices is <= max_count: exact
        return 31, 1
    bits = min(31, mant - max(1, math.ceil(math.log2(n_devices))))
    return bits, -(-31 // bits)


def _pack(arrays, flags, bits: int, pieces: int, dtype):
    """One flat float array of ``R`` and the count digits of ``M`` and ``H`` (+ flags)."""
    r, m, h = arrays
    cols = [r.reshape(-1).astype(dtype)]
    mask = (1 << bits) - 1 if pieces > 1 else -1
    for c in (m, h):
        c = c.reshape(-1)
        for p in range(pieces):
            digit = (c >> (p * bits)) & mask if pieces > 1 else c
            cols.append(digit.astype(dtype))
    cols.append(flags.astype(dtype))
    return jnp.concatenate(cols)


def _unpack(total, shape, n_flags: int, bits: int, pieces: int):
    """Inverse of :func:`_pack` on the summed array: ``(R, M, H), flags``."""
    n = math.prod(shape)
    r = total[:n].reshape(shape)
    counts = []
    at = n
    for _ in range(2):
        c = jnp.zeros(n, jnp.int32)
        for p in range(pieces):
            digit = jnp.round(total[at : at + n]).astype(jnp.int32)
            c = c + (digit << (p * bits)) if pieces > 1 else digit
            at += n
        counts.append(c.reshape(shape))
    flags = total[at : at + n_flags] > 0
    return (r, counts[0], counts[1]), flags


@_checks.checked_jit
def _sharded_program(
    spec, o, d, r, k, r_max, *, mesh, native, sub_as_hit, threads, chunk_size, max_count
):
    """One compiled program: per-shard walk under ``shard_map``, one ``psum``."""
    axis = mesh.axis_names[0]
    n_dev = mesh.devices.size
    dtype = o.dtype
    bits, pieces = _count_digits(dtype, n_dev, max_count)
    box: dict = {}

    def local(spec, o, d, r, k, r_max):
        if native:
            return _native.accumulate(spec, o, d, r, k, r_max, sub_as_hit, threads)
        n_local = o.shape[0]
        return _accumulate(
            spec,
            o,
            d,
            r,
            k,
            r_max,
            chunk_size=min(chunk_size, n_local),
            block=max(_BLOCK_RAYS, chunk_size),
            sub_as_hit=sub_as_hit,
        )

    def body(spec, o, d, r, k, r_max):
        arrays, flags, messages = _checks._collect(local, spec, o, d, r, k, r_max)
        box["messages"] = messages
        payload = _pack(arrays, flags, bits, pieces, dtype)
        total = jax.lax.psum(payload, axis)  # the program's only collective
        return _unpack(total, spec.shape, flags.shape[0], bits, pieces)

    (lengths, misses, hits), flags = jax.shard_map(
        body,
        mesh=mesh,
        in_specs=(P(), P(axis), P(axis), P(axis), P(axis), P()),
        out_specs=P(),
        check_vma=False,
    )(spec, o, d, r, k, r_max)
    out = _checks._reattach((lengths, misses, hits), flags, box["messages"])
    return out


def _sharded_inputs(spec, rays, mesh, chunk_size, sub_rays, backend, threads):
    """Checked, padded and placed ``(args, kwargs)`` of :func:`_sharded_program`."""
    mesh, axis = _mesh_axis(mesh, RAY_AXIS)
    o, d, r, k, r_max = _flat_rays(spec, rays, sub_rays, chunk_size)
    _native.check_backend(backend)
    n_dev = mesh.devices.size
    if threads is None:
        threads = max(1, _native.default_threads() // n_dev)
    threads = _native.check_threads(threads)
    native = _native.resolve(backend) == "native"
    n_total = n_chunks_for(o.shape[0], n_dev) * n_dev
    o, d, r, k = _pad_rays(spec, o, d, r, k, n_total)
    split = NamedSharding(mesh, P(axis))
    whole = NamedSharding(mesh, P())
    args = (
        jax.device_put(spec, whole),
        *(jax.device_put(x, split) for x in (o, d, r, k)),
        jax.device_put(r_max, whole),
    )
    kwargs = dict(
        mesh=mesh,
        native=native,
        sub_as_hit=sub_rays == "hit",
        threads=threads,
        chunk_size=chunk_size,
        max_count=n_total,
    )
    return args, kwargs


def accumulate_sharded(
    spec: GridSpec,
    rays: RayBatch,
    mesh: Mesh | None = None,
    *,
    chunk_size: int = 1024,
    sub_rays: Literal["ignore", "hit"] = "ignore",
    backend: str = "auto",
    threads: int | None = None,
) -> GridStats:
    """:func:`~lidarjax.raytrace.accumulate` with the rays split over the devices of a
    1-D mesh (see the module docstring).

    The ``n`` rays are padded to a multiple of the device count ``k`` with rays that
    contribute nothing and split into ``k`` equal shards; each device accumulates its
    shard into a full grid; one ``psum`` adds the ``k`` grids. Memory per device: its
    ``n / k`` rays, the full grid's ``H``/``M``/``R`` and the packed sum (3 grids, 5
    when float32 counts need two digits: more than ``2**24`` rays).

    Args:
        spec: the grid; its dimension must match the rays'.
        rays: any batch shape (host or device arrays).
        mesh: a 1-D mesh (any axis name; default :func:`device_mesh`: all devices).
        chunk_size: rays walked together by the JAX path (static).
        sub_rays: ``"ignore"`` or ``"hit"``.
        backend: ``"auto"``, ``"native"`` or ``"jax"`` (as for ``accumulate``; the native
            kernel runs once per shard).
        threads: native worker threads per shard (default: the cores divided by the
            number of devices, at least 1).

    Returns:
        :class:`GridStats` of ``spec.shape``, replicated on the mesh's devices
        (``NamedSharding(mesh, P())``). ``hits`` and ``misses`` equal the one-device
        counts of the same backend exactly; ``lengths`` to float rounding.

    Raises:
        ValueError: a bad ``spec``, ``rays``, ``mesh``, ``sub_rays``, ``chunk_size``,
            ``backend`` or ``threads``, or no rays.
    """
    args, kwargs = _sharded_inputs(spec, rays, mesh, chunk_size, sub_rays, backend, threads)
    lengths, misses, hits = _sharded_program(*args, **kwargs)
    return GridStats(spec=spec, hits=hits, misses=misses, lengths=lengths)


# ------------------------------------------------------------------ grids over devices


@eqx.filter_jit(donate="all-except-first")
def _tiled_program(inputs, acc, *, mesh, sub_as_hit, chunk_size):
    """Add one replicated chunk of rays (``inputs = (spec, o, d, r, kind, r_max)``) into
    the row-tiled ``acc = (R, M, H)`` (donated); no collective. Returns the new ``acc``,
    the check flags and their messages (read on the host)."""
    spec = inputs[0]
    axis = mesh.axis_names[0]
    rows = spec.shape[0] // mesh.devices.size
    box: dict = {}

    def body(acc, inputs):
        spec, o, d, r, k, r_max = inputs
        row0 = jax.lax.axis_index(axis) * rows

        def local():
            return _accumulate_blocks(
                spec,
                o,
                d,
                r,
                k,
                r_max,
                chunk_size=min(chunk_size, o.shape[0]),
                block=max(_BLOCK_RAYS, chunk_size),
                sub_as_hit=sub_as_hit,
                tile=(row0, rows),
            )

        (rr, m, h), flags, box["messages"] = _checks._collect(local)
        # every device walks the same rays over the same grid: its flags are the same
        # on every device, so device 0's (out_specs P()) are everyone's
        return (acc[0] + rr, acc[1] + m, acc[2] + h), flags

    tiled = P(axis, *([None] * (spec.dim - 1)))
    acc, flags = jax.shard_map(
        body,
        mesh=mesh,
        in_specs=((tiled, tiled, tiled), P()),
        out_specs=((tiled, tiled, tiled), P()),
        check_vma=False,
    )(acc, inputs)
    return acc, flags, box["messages"]


def accumulate_tiled(
    spec: GridSpec,
    rays: RayBatch,
    mesh: Mesh | None = None,
    *,
    ray_chunk: int | None = 1 << 20,
    chunk_size: int = 1024,
    sub_rays: Literal["ignore", "hit"] = "ignore",
) -> GridStats:
    """:func:`~lidarjax.raytrace.accumulate` into a grid split in row tiles over the
    devices of a 1-D mesh, for grids larger than one device's memory (module docstring).

    Device ``i`` of ``k`` holds rows ``[i * nx / k, (i + 1) * nx / k)`` (first grid axis)
    of ``H``, ``M`` and ``R``. The rays are sent to every device in chunks of
    ``ray_chunk`` (the last chunk padded with rays that contribute nothing); every device
    walks every ray of a chunk with the JAX walk over the whole grid and adds only into
    its own rows. Memory per device: its tile (``H``, ``M``, ``R``: ``12 nx ny / k``
    bytes in float32), the walk's temporaries (a few more arrays of the tile's size: the
    complex + int accumulators of a block of rays and their running sums) and one chunk
    of rays. Time: the same as one device walking all rays (no speed-up).
    No collective: each compiled program (one per chunk shape) only reads its inputs.

    Args:
        spec: the grid; ``spec.shape[0]`` must be divisible by the number of devices.
        rays: any batch shape (host or device arrays).
        mesh: a 1-D mesh (any axis name; default :func:`device_mesh` with axis
            ``"tiles"``: all devices).
        ray_chunk: rays sent to the devices at a time (``None``: all at once).
        chunk_size: rays walked together (static).
        sub_rays: ``"ignore"`` or ``"hit"``.

    Returns:
        :class:`GridStats` of ``spec.shape`` whose arrays are split by rows,
        ``NamedSharding(mesh, P(axis, None[, None]))``. ``hits`` and ``misses`` equal
        ``accumulate(spec, rays, backend="jax")`` exactly, ``lengths`` to float rounding
        (bitwise with one ray chunk).

    Raises:
        ValueError: ``spec.shape[0]`` not divisible by the device count, a bad ``mesh``,
            ``ray_chunk``, ``spec``, ``rays``, ``sub_rays`` or ``chunk_size``, or no rays.
    """
    mesh, axis = _mesh_axis(mesh, TILE_AXIS)
    o, d, r, k, r_max = _flat_rays(spec, rays, sub_rays, chunk_size)
    n_dev = mesh.devices.size
    if spec.shape[0] % n_dev:
        raise ValueError(
            f"spec.shape[0] = {spec.shape[0]} rows must be divisible by the number of "
            f"devices ({n_dev}) to split the grid into row tiles; grow the grid to a "
            f"multiple of {n_dev} rows"
        )
    n = o.shape[0]
    if ray_chunk is None:
        ray_chunk = n
    if isinstance(ray_chunk, bool) or not isinstance(ray_chunk, int) or ray_chunk <= 0:
        raise ValueError(f"ray_chunk must be a positive int or None, got {ray_chunk!r}")
    ray_chunk = min(ray_chunk, n)
    n_chunks = n_chunks_for(n, ray_chunk)
    o, d, r, k = _pad_rays(spec, o, d, r, k, n_chunks * ray_chunk)
    tiled = NamedSharding(mesh, P(axis, *([None] * (spec.dim - 1))))
    whole = NamedSharding(mesh, P())
    acc = tuple(
        jax.device_put(np.zeros(spec.shape, dt), tiled) for dt in (o.dtype, np.int32, np.int32)
    )
    spec_rep = jax.device_put(spec, whole)
    r_max = jax.device_put(r_max, whole)
    for c in range(n_chunks):
        sl = slice(c * ray_chunk, (c + 1) * ray_chunk)
        chunk = (jax.device_put(x[sl], whole) for x in (o, d, r, k))
        acc, flags, messages = _tiled_program(
            (spec_rep, *chunk, r_max),
            acc,
            mesh=mesh,
            sub_as_hit=sub_rays == "hit",
            chunk_size=chunk_size,
        )
        acc = _checks._reattach(acc, flags, messages)  # concrete flags: read on the host
    lengths, misses, hits = acc
    return GridStats(spec=spec, hits=hits, misses=misses, lengths=lengths)


__all__ = [
    "RAY_AXIS",
    "TILE_AXIS",
    "device_mesh",
    "accumulate_sharded",
    "accumulate_tiled",
]
