"""Ray batches: the one input type of every sensor model, map fit and ray tracer.

A lidar measurement is a ray that starts at the sensor (``origins``), travels along a unit
``directions`` vector and either is reflected at ``ranges`` (a *HIT*), or is reported as
out of range: *SUB* (reflected below ``r_min``) or *SUP* (no return up to ``r_max``), as in
Eq. (7.14) of the dissertation.

The leading axes of a :class:`RayBatch` are free (``[*batch]``); kernels are written for one
ray and batched with ``vmap``; :meth:`RayBatch.flatten` gives the ``[n]`` layout that
:func:`lidarjax.raytrace.accumulate` and the sensor models consume.

Validation: every builder here (and :class:`RayBatch` itself) rejects NaN or infinite poses,
azimuths, directions and points, NaN or negative ranges, and bad limits (``r_min`` negative
or not finite, ``r_max <= r_min`` for the builders, ``r_max < r_min`` for a
:class:`RayBatch` built directly). Concrete values raise ``ValueError`` at once, naming the
argument; values traced under ``jit``/``vmap``/``grad`` are checked at run time with
``eqx.error_if`` (``EquinoxRuntimeError`` under ``eqx.filter_jit``, ``JaxRuntimeError``
under ``jax.jit``), whose message names the argument too. A NaN range reading is always an
error, never a kind: :func:`classify` would otherwise call it a HIT (``NaN < r_min`` and
``NaN >= r_max`` are both false). Give no-returns as ``+inf`` (see
:func:`from_spinning_scan`) or drop them.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._checks import check

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


def reject_where(x, bad: Callable, message: str, deps: tuple = ()):
    """``x`` checked against the elementwise predicate ``bad(xp, x)`` (``xp`` is ``np`` or
    ``jnp``; ``deps`` are other arrays ``bad`` reads): if ``x`` and ``deps`` are concrete,
    a bad entry raises ``ValueError(message ...)`` at once and ``x`` is returned unchanged;
    otherwise ``x`` is returned as an array carrying ``eqx.error_if`` (use it)."""
    if is_concrete(x) and all(is_concrete(v) for v in deps):
        arr = np.asarray(x)
        if arr.size and not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_):
            raise ValueError(f"{message}; got non-numeric dtype {arr.dtype}")
        mask = np.broadcast_to(np.asarray(bad(np, arr)), arr.shape)
        if np.any(mask):
            first = tuple(int(i) for i in np.argwhere(mask)[0])
            raise ValueError(
                f"{message}; found {arr[first]!r} at index {first} ({int(mask.sum())} bad values)"
            )
        return x
    x = jnp.asarray(x)
    return check(x, bad(jnp, x), message)


def check_finite_nonnegative(x: ArrayLike, name: str) -> Array:
    """Return ``x`` as an array, raising if any entry is NaN, infinite or negative.

    Concrete inputs raise ``ValueError`` immediately; traced inputs are checked at run time
    with ``eqx.error_if`` (the returned array carries the check, so use it).

    Args:
        x: values to check, any shape.
        name: the argument's name, quoted in the error message.
    """
    x = reject_where(
        x, lambda xp, a: ~xp.isfinite(a) | (a < 0), f"{name} must be finite and non-negative"
    )
    return jnp.asarray(x)


def check_finite(x: ArrayLike, name: str) -> Array:
    """Return ``x`` as an array, raising if any entry is NaN or infinite (``ValueError`` when
    concrete, ``eqx.error_if`` when traced; use the returned array).

    Args:
        x: values to check, any shape.
        name: the argument's name, quoted in the error message.
    """
    return jnp.asarray(reject_where(x, lambda xp, a: ~xp.isfinite(a), f"{name} must be finite"))


ROTATION_NORM_TOL = 1e-3  # |norm - 1| allowed for a pose's unit complex / quaternion


def check_pose(T, name: str = "T_world_sensor"):
    """Return the ``jaxlie`` group element ``T`` with its parameters checked to be finite
    (a NaN or infinite heading, rotation or translation) and its rotation to be normalised
    (unit complex or quaternion of norm 1 within :data:`ROTATION_NORM_TOL`; an unnormalised
    one would scale every ray direction): ``ValueError`` when concrete, ``eqx.error_if``
    when traced; use the returned pose.

    Args:
        T: a ``jaxlie`` group element (``SE2``, ``SE3``, ...), any batch axes.
        name: the argument's name, quoted in the error message.
    """
    message = f"{name} must be finite (NaN or infinite pose parameters)"
    T = jax.tree.map(lambda p: reject_where(p, lambda xp, a: ~xp.isfinite(a), message), T)
    if not hasattr(T, "rotation"):  # SO2 / SO3 themselves: nothing more to check here
        return T
    n_rot = T.rotation().parameters().shape[-1]  # 2 (unit complex) or 4 (quaternion)

    def unnormalised(xp, params):
        norm = xp.sqrt(xp.sum(params[..., :n_rot] ** 2, axis=-1, keepdims=True))
        return xp.broadcast_to(xp.abs(norm - 1) > ROTATION_NORM_TOL, params.shape)

    unit = "complex number" if n_rot == 2 else "quaternion"
    message = (
        f"{name} has an unnormalised rotation: its unit {unit} must have norm 1 "
        f"(+- {ROTATION_NORM_TOL}); normalise it (e.g. jaxlie's .normalize()) or build it with "
        "from_xy_theta / from_rotation_and_translation"
    )
    return jax.tree.map(lambda p: reject_where(p, unnormalised, message), T)


def _check_ranges(ranges, kind, name: str):
    """Ranges not NaN, not negative, and ``+inf`` only for SUP rays."""

    def bad(xp, r):
        k = xp.asarray(kind)
        return xp.isnan(r) | (r < 0) | (xp.isinf(r) & (k != SUP))

    message = f"{name} must be >= 0 and not NaN (+inf only for SUP rays, kind={SUP})"
    return reject_where(ranges, bad, message, deps=(kind,))


def _check_shapes(o, d, r, k, r_min, r_max) -> None:
    if jnp.ndim(o) < 1 or jnp.shape(o)[-1] not in (2, 3):
        raise ValueError(f"origins must have shape [*batch, 2 or 3], got {jnp.shape(o)}")
    if jnp.shape(d) != jnp.shape(o):
        raise ValueError(
            f"directions must have the shape of origins {jnp.shape(o)}, got {jnp.shape(d)}"
        )
    if jnp.shape(r) != jnp.shape(o)[:-1]:
        raise ValueError(f"ranges must have shape {jnp.shape(o)[:-1]}, got {jnp.shape(r)}")
    if jnp.shape(k) != jnp.shape(r):
        raise ValueError(f"kind must have shape {jnp.shape(r)}, got {jnp.shape(k)}")
    if jnp.shape(r_min) != () or jnp.shape(r_max) != ():
        raise ValueError("r_min and r_max must be scalars")


class RayBatch(eqx.Module):
    """A batch of lidar rays with their measurement kind.

    Construction validates the values (``ValueError`` naming the field when they are
    concrete, ``eqx.error_if`` when traced under ``jit``): ``origins`` and ``directions``
    finite; ``ranges`` not NaN, not negative, ``+inf`` only for SUP rays; ``kind`` one of
    HIT/SUB/SUP; ``r_min`` finite and ``>= 0``; ``r_max >= r_min`` (``inf`` allowed); no
    direction is the zero vector (it would count a miss and no hit). Concrete fields
    are stored as given, traced ones as the checked arrays.

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

    def __init__(self, origins, directions, ranges, kind, r_min, r_max):
        origins, directions, ranges, kind = (
            x if hasattr(x, "shape") else jnp.asarray(x)
            for x in (origins, directions, ranges, kind)
        )
        _check_shapes(origins, directions, ranges, kind, r_min, r_max)
        self.origins = reject_where(
            origins, lambda xp, a: ~xp.isfinite(a), "origins must be finite (NaN or inf pose?)"
        )
        self.directions = reject_where(
            reject_where(
                directions,
                lambda xp, a: ~xp.isfinite(a),
                "directions must be finite (NaN or inf heading/azimuth?)",
            ),
            lambda xp, a: xp.all(a == 0, axis=-1, keepdims=True),
            "directions must be non-zero (a zero direction has no ray to walk)",
        )
        self.kind = reject_where(
            kind,
            lambda xp, a: (a != HIT) & (a != SUB) & (a != SUP),
            f"kind must be HIT ({HIT}), SUB ({SUB}) or SUP ({SUP})",
        )
        self.ranges = _check_ranges(ranges, kind, "ranges")
        self.r_min, self.r_max = _check_limit_values(r_min, r_max, strict=False)

    @classmethod
    def _trusted(cls, origins, directions, ranges, kind, r_min, r_max) -> RayBatch:
        """A batch from fields already validated (by a builder or an existing batch): shapes
        are checked, values are not checked again. Same mechanism as pytree unflattening."""
        _check_shapes(origins, directions, ranges, kind, r_min, r_max)
        return jax.tree.unflatten(
            _raybatch_treedef(), [origins, directions, ranges, kind, r_min, r_max]
        )

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
        return RayBatch._trusted(
            origins=self.origins.reshape(-1, d),
            directions=self.directions.reshape(-1, d),
            ranges=self.ranges.reshape(-1),
            kind=self.kind.reshape(-1),
            r_min=self.r_min,
            r_max=self.r_max,
        )

    def mapping_lengths(self) -> Float[Array, "*batch"]:
        """Length (m) the ray is known to have travelled, the evidence a map is built from:
        the range for HIT and SUB rays, ``r_max`` for SUP rays. Mapping
        (:func:`~lidarjax.raytrace.accumulate`) and :meth:`endpoints` use it."""
        return jnp.where(self.kind == SUP, self.r_max, self.ranges)

    def model_lengths(self) -> Float[Array, "*batch"]:
        """Length (m) a forward sensor model evaluates the ray to: the range for HIT rays,
        ``r_min`` for SUB rays (``P(r < r_min)``) and ``r_max`` for SUP rays
        (``P(r >= r_max)``), Eq. (7.16). The grid models walk their rays this far."""
        return jnp.where(
            self.kind == HIT, self.ranges, jnp.where(self.kind == SUB, self.r_min, self.r_max)
        )

    def trace_lengths(self) -> Float[Array, "*batch"]:
        """The :meth:`mapping_lengths` (the name before the two lengths were told apart)."""
        return self.mapping_lengths()

    def endpoints(self) -> Float[Array, "*batch d"]:
        """``origins + mapping_lengths * directions`` (m); for SUP rays the point at r_max
        (``inf`` components when ``r_max`` is infinite)."""
        return self.origins + self.mapping_lengths()[..., None] * self.directions

    def counts(self) -> dict[str, int]:
        """Number of HIT, SUB and SUP rays (host-side convenience)."""
        k = np.asarray(self.kind)
        return {name: int((k == code).sum()) for code, name in KIND_NAMES.items()}


@functools.cache
def _raybatch_treedef():
    z, unit = np.zeros((1, 2)), np.array([[1.0, 0.0]])
    return jax.tree.structure(RayBatch(z, unit, np.zeros(1), np.zeros(1, np.int32), 0.0, 1.0))


def _kind_of(ranges_m, r_min, r_max):
    kind = jnp.where(ranges_m < r_min, SUB, HIT)
    kind = jnp.where(ranges_m >= r_max, SUP, kind)
    return kind.astype(jnp.int32)


def classify(ranges_m: Float[Array, "*batch"], r_min, r_max) -> Int[Array, "*batch"]:
    """Measurement kind per Eq. (7.14): SUB below ``r_min``, SUP at or beyond ``r_max``.

    A NaN reading has no kind (the comparisons would silently call it a HIT), so NaN and
    negative readings are rejected, as are bad limits: ``ValueError`` when concrete,
    ``eqx.error_if`` when traced. ``+inf`` (no return) is SUP.

    Args:
        ranges_m: ``[*batch]`` raw range readings (m), ``>= 0`` or ``+inf``.
        r_min: minimum range (m), finite and ``>= 0``.
        r_max: maximum usable range (m), ``>= r_min``; readings ``>= r_max`` are no-returns.

    Returns:
        ``[*batch]`` int32 kinds.

    Raises:
        ValueError: concrete NaN/negative readings or bad limits.
    """
    ranges_m = reject_where(
        ranges_m, lambda xp, r: xp.isnan(r) | (r < 0), "ranges_m must be >= 0 and not NaN"
    )
    lo, hi = _check_limits(r_min, r_max, strict=False)
    return _kind_of(jnp.asarray(ranges_m), lo, hi)


def _check_limit_values(r_min, r_max, *, strict: bool = True):
    """``r_min`` finite and >= 0, ``r_max > r_min`` (``>=`` unless ``strict``; not NaN,
    ``inf`` allowed). Concrete values raise ``ValueError`` and are returned unchanged;
    traced ones carry ``eqx.error_if``."""
    if jnp.shape(r_min) != () or jnp.shape(r_max) != ():
        raise ValueError(
            f"r_min and r_max must be scalars, got shapes {jnp.shape(r_min)}, {jnp.shape(r_max)}"
        )
    relation = "larger than" if strict else "at least"
    lo_c, hi_c = is_concrete(r_min), is_concrete(r_max)
    if lo_c:
        lo = float(r_min)
        if not (np.isfinite(lo) and lo >= 0):
            raise ValueError(f"r_min must be finite and >= 0, got {lo}")
    else:
        r_min = check(r_min, ~(jnp.isfinite(r_min) & (r_min >= 0)), "r_min must be finite and >= 0")
    if lo_c and hi_c:
        hi = float(r_max)
        if not (hi > lo if strict else hi >= lo):
            raise ValueError(f"r_max must be {relation} r_min={lo}, got {hi}")
    else:
        ok = (r_max > r_min) if strict else (r_max >= r_min)
        r_max = check(jnp.asarray(r_max), ~ok, f"r_max must be {relation} r_min (and not NaN)")
    return r_min, r_max


def _check_limits(r_min, r_max, *, strict: bool = True) -> tuple[Array, Array]:
    """:func:`_check_limit_values`, returned as arrays of the default float dtype."""
    r_min, r_max = _check_limit_values(r_min, r_max, strict=strict)
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
            broadcastable against ``ranges_m.shape[:-1]``; finite.
        azimuths_rad: ``[b]`` beam angles relative to the sensor heading (rad); finite.
        ranges_m: ``[*scans b]`` raw readings (m); must be finite and non-negative (a NaN
            reading is an error, never a HIT; give no-returns as a reading ``>= r_max``).
        r_min: minimum range (m), finite and ``>= 0``; readings below are SUB.
        r_max: maximum usable range (m), ``> r_min``; readings at or beyond are SUP (no
            return).

    Returns:
        A :class:`RayBatch` of shape ``[*scans b]`` with 2-D origins and unit directions.

    Raises:
        ValueError: wrong types/shapes; with concrete values also a NaN/inf pose or
            azimuth, NaN/inf/negative ranges, ``r_min < 0`` or ``r_max <= r_min``. Traced
            values are checked with ``eqx.error_if`` (the message names the argument).
    """
    if not isinstance(T_world_sensor, jaxlie.SE2):
        raise ValueError(
            f"T_world_sensor must be a jaxlie.SE2, got {type(T_world_sensor).__name__}"
        )
    az = jnp.asarray(azimuths_rad, dtype=jnp.result_type(float))
    if az.ndim != 1 or az.shape[0] == 0:
        raise ValueError(f"azimuths_rad must have shape [b] with b > 0, got {az.shape}")
    ranges = jnp.asarray(ranges_m)
    if ranges.ndim < 1 or ranges.shape[-1] != az.shape[0]:
        raise ValueError(
            f"ranges_m must have shape [*scans, {az.shape[0]}] to match azimuths_rad, "
            f"got {ranges.shape}"
        )
    batch = _scan_batch(T_world_sensor, ranges.shape[:-1], "ranges_m")
    az = check_finite(az, "azimuths_rad")
    ranges = check_finite_nonnegative(ranges, "ranges_m").astype(az.dtype)
    T_world_sensor = check_pose(T_world_sensor, "T_world_sensor")
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
    return RayBatch._trusted(
        origins=origins,
        directions=dirs,
        ranges=ranges,
        kind=_kind_of(ranges, lo, hi),
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
            broadcastable against ``points_xyz.shape[:-2]``; finite.
        points_xyz: ``[*scans n 3]`` measured points in the sensor frame (m); no NaNs
            (drop no-return points of organized clouds first, or give them as SUP rays by
            building a :class:`RayBatch` directly).
        r_min: minimum range (m), finite and ``>= 0``.
        r_max: maximum usable range (m), ``> r_min``.

    Returns:
        A :class:`RayBatch` of shape ``[*scans n]``.

    Raises:
        ValueError: wrong types/shapes; with concrete values also a NaN/inf pose or
            point, or bad limits (traced values: ``eqx.error_if``).
    """
    if not isinstance(T_world_sensor, jaxlie.SE3):
        raise ValueError(
            f"T_world_sensor must be a jaxlie.SE3, got {type(T_world_sensor).__name__}"
        )
    pts = jnp.asarray(points_xyz, dtype=jnp.result_type(float))
    if pts.ndim < 2 or pts.shape[-1] != 3:
        raise ValueError(f"points_xyz must have shape [*scans, n, 3], got {pts.shape}")
    batch = _scan_batch(T_world_sensor, pts.shape[:-2], "points_xyz")
    pts = jnp.asarray(
        reject_where(pts, lambda xp, a: ~xp.isfinite(a), "points_xyz contains NaN/inf values")
    )
    T_world_sensor = check_pose(T_world_sensor, "T_world_sensor")
    lo, hi = _check_limits(r_min, r_max)
    rng = jnp.linalg.norm(pts, axis=-1)  # [*S n]
    safe = jnp.where(rng > 0, rng, 1.0)
    unit = jnp.where(
        (rng > 0)[..., None], pts / safe[..., None], jnp.array([1.0, 0.0, 0.0], pts.dtype)
    )
    return _sensor_rays(T_world_sensor, unit, rng, lo, hi, batch)


def _sensor_rays(T_world_sensor: jaxlie.SE3, unit, rng, lo, hi, batch) -> RayBatch:
    """Rays from sensor-frame unit directions ``[*S n 3]`` and ranges ``[*S n]`` (all
    already validated)."""
    n = rng.shape[-1]
    R = T_world_sensor.rotation().as_matrix().astype(rng.dtype)  # [*P 3 3]
    dirs = jnp.einsum("...ij,...nj->...ni", R, unit)
    t = T_world_sensor.translation().astype(rng.dtype)
    origins = jnp.broadcast_to(t[..., None, :], (*batch, n, 3))
    dirs = jnp.broadcast_to(dirs, (*batch, n, 3))
    rng = jnp.broadcast_to(rng, (*batch, n))
    return RayBatch._trusted(
        origins=origins,
        directions=dirs,
        ranges=rng,
        kind=_kind_of(rng, lo, hi),
        r_min=lo,
        r_max=hi,
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
        T_world_sensor: sensor pose(s), ``jaxlie.SE3`` with batch axes ``[*scans]``; finite.
        directions: ``[n 3]`` beam directions in the sensor frame (normalised here);
            finite and non-zero.
        ranges_m: ``[*scans n]`` measured ranges (m); ``+inf`` = no return; NaN and
            negative values are rejected (a NaN is never read as a no-return or a HIT).
        r_min: minimum range (m), finite and ``>= 0``; shorter readings are SUB rays.
        r_max: maximum usable range (m), ``> r_min``; finite when any range is ``+inf``.

    Returns:
        A :class:`RayBatch` of shape ``[*scans n]``.

    Raises:
        ValueError: wrong types/shapes; with concrete values also a NaN/inf pose,
            non-finite or zero directions, NaN/negative ranges, ``+inf`` ranges with an
            infinite ``r_max``, or bad limits (traced values: ``eqx.error_if``).
    """
    if not isinstance(T_world_sensor, jaxlie.SE3):
        raise ValueError(
            f"T_world_sensor must be a jaxlie.SE3, got {type(T_world_sensor).__name__}"
        )
    d = jnp.asarray(directions, dtype=jnp.result_type(float))
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"directions must have shape [n, 3], got {d.shape}")
    r = jnp.asarray(ranges_m, dtype=d.dtype)
    if r.shape[-1:] != (d.shape[0],):
        raise ValueError(f"ranges_m must have shape [*scans, {d.shape[0]}], got {r.shape}")
    batch = _scan_batch(T_world_sensor, r.shape[:-1], "ranges_m")
    d = jnp.asarray(
        reject_where(d, lambda xp, a: ~xp.isfinite(a), "directions must be finite and non-zero")
    )
    norm = reject_where(
        jnp.linalg.norm(d, axis=-1),
        lambda xp, a: ~(a > 0),
        "directions must be finite and non-zero",
    )
    d = d / norm[:, None]
    T_world_sensor = check_pose(T_world_sensor, "T_world_sensor")
    lo, hi = _check_limits(r_min, r_max)
    r = jnp.asarray(
        reject_where(
            r,
            lambda xp, a: xp.isnan(a) | (a < 0),
            "ranges_m must be >= 0 or +inf (no return); found NaN/negative",
        )
    )
    if is_concrete(r) and is_concrete(hi):
        if bool(jnp.any(jnp.isinf(r))) and not np.isfinite(float(hi)):
            raise ValueError("ranges_m has no-return (+inf) beams: give a finite r_max")
    else:
        r = check(
            r,
            jnp.isinf(r) & ~jnp.isfinite(hi),
            "ranges_m has no-return (+inf) beams: give a finite r_max",
        )
    r = jnp.where(jnp.isinf(r), hi.astype(d.dtype), r)
    return _sensor_rays(T_world_sensor, d, r, lo, hi, batch)
