"""Ray batches: the one input type of every sensor model, map fit and ray tracer.

A lidar measurement is a ray that starts at the sensor (``origins``), travels along a unit
``directions`` vector and either is reflected at ``ranges`` (a *HIT*), or is reported as
out of range: *SUB* (reflected below ``r_min``) or *SUP* (no return up to ``r_max``), as in
Eq. (7.14) of the dissertation.

The leading axes of a :class:`RayBatch` are free (``[*batch]``); kernels are written for one
ray and batched with ``vmap``; :meth:`RayBatch.flatten` gives the ``[n]`` layout that
:func:`lidarjax.raytrace.accumulate` and the sensor models consume.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

HIT: int = 0
"""Ray reflected at a range in ``[r_min, r_max)``."""
SUB: int = 1
"""Ray reflected below ``r_min`` (range unknown, only that it is below ``r_min``)."""
SUP: int = 2
"""No return up to ``r_max`` (the beam travelled at least ``r_max``)."""

KIND_NAMES = {HIT: "HIT", SUB: "SUB", SUP: "SUP"}


def is_concrete(x) -> bool:
    """True for a concrete value, False for a value traced under ``jit``/``vmap``/``grad``
    (whose run-time values can only be checked with ``eqx.error_if``)."""
    return not isinstance(x, jax.core.Tracer)


def _scan_batch(T_world_sensor, data_axes: tuple[int, ...], name: str) -> tuple[int, ...]:
    """Broadcast shape of the pose batch axes and a data argument's scan axes."""
    pose_batch = T_world_sensor.get_batch_axes()
    try:
        return jnp.broadcast_shapes(pose_batch, data_axes)
    except ValueError as e:
        raise ValueError(
            f"T_world_sensor batch axes {pose_batch} do not broadcast with {name} scan axes "
            f"{data_axes}"
        ) from e


def check_finite_nonnegative(x: ArrayLike, name: str) -> Array:
    """Return ``x`` as an array, raising if any entry is NaN, infinite or negative.

    Concrete inputs raise ``ValueError`` immediately; traced inputs are checked at run time
    with ``eqx.error_if`` (the returned array carries the check, so use it).

    Args:
        x: values to check, any shape.
        name: the argument's name, quoted in the error message.
    """
    if is_concrete(x):
        arr = np.asarray(x)
        if arr.size and not np.issubdtype(arr.dtype, np.number):
            raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
        bad = ~np.isfinite(arr) | (arr < 0)
        if np.any(bad):
            first = np.argwhere(bad)[0]
            raise ValueError(
                f"{name} must be finite and non-negative; found {arr[tuple(first)]!r} at "
                f"index {tuple(int(i) for i in first)} ({int(bad.sum())} bad values)"
            )
        return jnp.asarray(x)
    x = jnp.asarray(x)
    return eqx.error_if(x, ~jnp.isfinite(x) | (x < 0), f"{name} must be finite and non-negative")


class RayBatch(eqx.Module):
    """A batch of lidar rays with their measurement kind.

    Attributes:
        origins: ``[*batch d]`` ray start points in the world frame (m), ``d`` = 2 or 3.
        directions: ``[*batch d]`` unit direction vectors in the world frame.
        ranges: ``[*batch]`` measured range (m). For SUB rays the raw reading (< r_min), for
            SUP rays the raw reading (>= r_max, e.g. the sensor's no-return value).
        kind: ``[*batch]`` int32, one of :data:`HIT`, :data:`SUB`, :data:`SUP`.
        r_min: ``[]`` minimum range of the sensor (m).
        r_max: ``[]`` maximum (usable) range of the sensor (m); may be ``inf``.
    """

    origins: Float[Array, "*batch d"]
    directions: Float[Array, "*batch d"]
    ranges: Float[Array, "*batch"]
    kind: Int[Array, "*batch"]
    r_min: Float[Array, ""]
    r_max: Float[Array, ""]

    def __check_init__(self):
        o, d, r, k = self.origins, self.directions, self.ranges, self.kind
        if o.ndim < 1 or o.shape[-1] not in (2, 3):
            raise ValueError(f"origins must have shape [*batch, 2 or 3], got {o.shape}")
        if d.shape != o.shape:
            raise ValueError(f"directions must have the shape of origins {o.shape}, got {d.shape}")
        if r.shape != o.shape[:-1]:
            raise ValueError(f"ranges must have shape {o.shape[:-1]}, got {r.shape}")
        if k.shape != r.shape:
            raise ValueError(f"kind must have shape {r.shape}, got {k.shape}")
        if jnp.shape(self.r_min) != () or jnp.shape(self.r_max) != ():
            raise ValueError("r_min and r_max must be scalars")

    @property
    def dim(self) -> int:
        """Spatial dimension (2 or 3)."""
        return self.origins.shape[-1]

    @property
    def shape(self) -> tuple[int, ...]:
        """Batch shape ``[*batch]``."""
        return self.ranges.shape

    @property
    def n(self) -> int:
        """Total number of rays."""
        return int(np.prod(self.shape, dtype=np.int64))

    def flatten(self) -> RayBatch:
        """The same rays with the batch axes flattened to ``[n]`` (row-major)."""
        d = self.dim
        return RayBatch(
            origins=self.origins.reshape(-1, d),
            directions=self.directions.reshape(-1, d),
            ranges=self.ranges.reshape(-1),
            kind=self.kind.reshape(-1),
            r_min=self.r_min,
            r_max=self.r_max,
        )

    def trace_lengths(self) -> Float[Array, "*batch"]:
        """Length (m) the ray is known to have travelled: the range for HIT and SUB rays,
        ``r_max`` for SUP rays."""
        return jnp.where(self.kind == SUP, self.r_max, self.ranges)

    def endpoints(self) -> Float[Array, "*batch d"]:
        """``origins + trace_lengths * directions`` (m); for SUP rays the point at r_max
        (``inf`` components when ``r_max`` is infinite)."""
        return self.origins + self.trace_lengths()[..., None] * self.directions

    def counts(self) -> dict[str, int]:
        """Number of HIT, SUB and SUP rays (host-side convenience)."""
        k = np.asarray(self.kind)
        return {name: int((k == code).sum()) for code, name in KIND_NAMES.items()}


def classify(ranges_m: Float[Array, "*batch"], r_min, r_max) -> Int[Array, "*batch"]:
    """Measurement kind per Eq. (7.14): SUB below ``r_min``, SUP at or beyond ``r_max``.

    Args:
        ranges_m: ``[*batch]`` raw range readings (m).
        r_min: minimum range (m).
        r_max: maximum usable range (m); readings ``>= r_max`` are no-returns.

    Returns:
        ``[*batch]`` int32 kinds.
    """
    ranges_m = jnp.asarray(ranges_m)
    kind = jnp.where(ranges_m < r_min, SUB, HIT)
    kind = jnp.where(ranges_m >= r_max, SUP, kind)
    return kind.astype(jnp.int32)


def _check_limits(r_min, r_max) -> tuple[Array, Array]:
    if is_concrete(r_min) and is_concrete(r_max):
        lo, hi = float(r_min), float(r_max)
        if not (np.isfinite(lo) and lo >= 0):
            raise ValueError(f"r_min must be finite and >= 0, got {lo}")
        if not (hi > lo):
            raise ValueError(f"r_max must be larger than r_min={lo}, got {hi}")
    dtype = jnp.result_type(float)
    return jnp.asarray(r_min, dtype), jnp.asarray(r_max, dtype)


def from_scan(
    T_world_sensor: jaxlie.SE2,
    azimuths_rad: Float[ArrayLike, " b"],
    ranges_m: Float[ArrayLike, "*scans b"],
    r_min: float = 0.0,
    r_max: float = np.inf,
) -> RayBatch:
    """Rays of 2-D range scans taken at the given sensor poses.

    Args:
        T_world_sensor: sensor pose(s), ``jaxlie.SE2`` with batch axes ``[*scans]``
            broadcastable against ``ranges_m.shape[:-1]``.
        azimuths_rad: ``[b]`` beam angles relative to the sensor heading (rad).
        ranges_m: ``[*scans b]`` raw readings (m); must be finite and non-negative.
        r_min: minimum range (m); readings below are SUB.
        r_max: maximum usable range (m); readings at or beyond are SUP (no return).

    Returns:
        A :class:`RayBatch` of shape ``[*scans b]`` with 2-D origins and unit directions.

    Raises:
        ValueError: wrong types/shapes, NaN/negative ranges, or ``r_max <= r_min``.
    """
    if not isinstance(T_world_sensor, jaxlie.SE2):
        raise ValueError(
            f"T_world_sensor must be a jaxlie.SE2, got {type(T_world_sensor).__name__}"
        )
    az = jnp.asarray(azimuths_rad, dtype=jnp.result_type(float))
    if az.ndim != 1 or az.shape[0] == 0:
        raise ValueError(f"azimuths_rad must have shape [b] with b > 0, got {az.shape}")
    ranges = check_finite_nonnegative(ranges_m, "ranges_m").astype(az.dtype)
    if ranges.ndim < 1 or ranges.shape[-1] != az.shape[0]:
        raise ValueError(
            f"ranges_m must have shape [*scans, {az.shape[0]}] to match azimuths_rad, "
            f"got {ranges.shape}"
        )
    batch = _scan_batch(T_world_sensor, ranges.shape[:-1], "ranges_m")
    lo, hi = _check_limits(r_min, r_max)
    b = az.shape[0]
    xy = T_world_sensor.translation().astype(az.dtype)  # [*P 2]
    cs = T_world_sensor.rotation().unit_complex.astype(az.dtype)  # [*P 2] (cos, sin)
    c, s = cs[..., 0:1], cs[..., 1:2]  # [*P 1]
    ca, sa = jnp.cos(az), jnp.sin(az)  # [b]
    dirs = jnp.stack([c * ca - s * sa, s * ca + c * sa], axis=-1)  # [*P b 2]
    origins = jnp.broadcast_to(xy[..., None, :], (*batch, b, 2))
    dirs = jnp.broadcast_to(dirs, (*batch, b, 2))
    ranges = jnp.broadcast_to(ranges, (*batch, b))
    return RayBatch(
        origins=origins,
        directions=dirs,
        ranges=ranges,
        kind=classify(ranges, lo, hi),
        r_min=lo,
        r_max=hi,
    )


def from_points(
    T_world_sensor: jaxlie.SE3,
    points_xyz: Float[ArrayLike, "*scans n 3"],
    r_min: float = 0.0,
    r_max: float = np.inf,
) -> RayBatch:
    """Rays from the sensor origin to measured 3-D points given in the sensor frame.

    A point at the sensor origin (range 0) gets the direction ``+x``; with the default
    ``r_min = 0`` it is a HIT at range 0.

    Args:
        T_world_sensor: sensor pose(s), ``jaxlie.SE3`` with batch axes ``[*scans]``
            broadcastable against ``points_xyz.shape[:-2]``.
        points_xyz: ``[*scans n 3]`` measured points in the sensor frame (m); no NaNs
            (drop no-return points of organized clouds first, or give them as SUP rays by
            building a :class:`RayBatch` directly).
        r_min: minimum range (m).
        r_max: maximum usable range (m).

    Returns:
        A :class:`RayBatch` of shape ``[*scans n]``.
    """
    if not isinstance(T_world_sensor, jaxlie.SE3):
        raise ValueError(
            f"T_world_sensor must be a jaxlie.SE3, got {type(T_world_sensor).__name__}"
        )
    if is_concrete(points_xyz):
        pts_np = np.asarray(points_xyz)
        if not np.all(np.isfinite(pts_np)):
            raise ValueError(
                f"points_xyz contains {int((~np.isfinite(pts_np)).sum())} NaN/inf values"
            )
        pts = jnp.asarray(pts_np, dtype=jnp.result_type(float))
    else:
        pts = jnp.asarray(points_xyz, dtype=jnp.result_type(float))
        pts = eqx.error_if(pts, ~jnp.isfinite(pts), "points_xyz contains NaN/inf values")
    if pts.ndim < 2 or pts.shape[-1] != 3:
        raise ValueError(f"points_xyz must have shape [*scans, n, 3], got {pts.shape}")
    batch = _scan_batch(T_world_sensor, pts.shape[:-2], "points_xyz")
    lo, hi = _check_limits(r_min, r_max)
    rng = jnp.linalg.norm(pts, axis=-1)  # [*S n]
    safe = jnp.where(rng > 0, rng, 1.0)
    unit = jnp.where(
        (rng > 0)[..., None], pts / safe[..., None], jnp.array([1.0, 0.0, 0.0], pts.dtype)
    )
    return _sensor_rays(T_world_sensor, unit, rng, lo, hi, batch)


def _sensor_rays(T_world_sensor: jaxlie.SE3, unit, rng, lo, hi, batch) -> RayBatch:
    """Rays from sensor-frame unit directions ``[*S n 3]`` and ranges ``[*S n]``."""
    n = rng.shape[-1]
    R = T_world_sensor.rotation().as_matrix().astype(rng.dtype)  # [*P 3 3]
    dirs = jnp.einsum("...ij,...nj->...ni", R, unit)
    t = T_world_sensor.translation().astype(rng.dtype)
    origins = jnp.broadcast_to(t[..., None, :], (*batch, n, 3))
    dirs = jnp.broadcast_to(dirs, (*batch, n, 3))
    rng = jnp.broadcast_to(rng, (*batch, n))
    return RayBatch(
        origins=origins, directions=dirs, ranges=rng, kind=classify(rng, lo, hi), r_min=lo, r_max=hi
    )


def from_spinning_scan(
    T_world_sensor: jaxlie.SE3,
    directions: Float[ArrayLike, "n 3"],
    ranges_m: Float[ArrayLike, "*scans n"],
    r_min: float = 0.0,
    r_max: float = np.inf,
) -> RayBatch:
    """Rays of a scanner with fixed beam directions (e.g. a spinning multi-beam lidar).

    Unlike :func:`from_points`, no-return beams are kept: a range of ``+inf`` (no echo)
    becomes a SUP ray (free space up to ``r_max``, stored with range ``r_max``).

    Args:
        T_world_sensor: sensor pose(s), ``jaxlie.SE3`` with batch axes ``[*scans]``.
        directions: ``[n 3]`` beam directions in the sensor frame (normalised here).
        ranges_m: ``[*scans n]`` measured ranges (m); ``+inf`` = no return; NaN and
            negative values are rejected.
        r_min: minimum range (m); shorter readings are SUB rays.
        r_max: maximum usable range (m), finite when any range is ``+inf``.

    Returns:
        A :class:`RayBatch` of shape ``[*scans n]``.
    """
    if not isinstance(T_world_sensor, jaxlie.SE3):
        raise ValueError(
            f"T_world_sensor must be a jaxlie.SE3, got {type(T_world_sensor).__name__}"
        )
    d = jnp.asarray(directions, dtype=jnp.result_type(float))
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"directions must have shape [n, 3], got {d.shape}")
    norm = jnp.linalg.norm(d, axis=-1)
    if is_concrete(norm) and not bool(jnp.all(jnp.isfinite(norm) & (norm > 0))):
        raise ValueError("directions must be finite and non-zero")
    d = d / norm[:, None]
    lo, hi = _check_limits(r_min, r_max)
    if is_concrete(ranges_m):
        r_np = np.asarray(ranges_m, dtype=float)
        if np.any(np.isnan(r_np)) or np.any(r_np < 0):
            raise ValueError("ranges_m must be >= 0 or +inf (no return); found NaN/negative")
        if np.any(np.isinf(r_np)) and not np.isfinite(float(hi)):
            raise ValueError("ranges_m has no-return (+inf) beams: give a finite r_max")
    r = jnp.asarray(ranges_m, dtype=d.dtype)
    if r.shape[-1:] != (d.shape[0],):
        raise ValueError(f"ranges_m must have shape [*scans, {d.shape[0]}], got {r.shape}")
    batch = _scan_batch(T_world_sensor, r.shape[:-1], "ranges_m")
    r = jnp.where(jnp.isinf(r), hi.astype(d.dtype), r)
    return _sensor_rays(T_world_sensor, d, r, lo, hi, batch)
