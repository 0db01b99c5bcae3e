"""Gradient-based pose refinement ("optimization-based localization", dissertation ch. 1.3
and 3: decay-rate maps make the scan likelihood differentiable in the pose).

:func:`refine_pose` maximises any differentiable scan log-likelihood ``objective(pose)``
over an SE(2) pose with optimistix, stepping on the manifold: the unknown is a tangent
vector ``delta`` and the pose is ``pose0 @ exp(delta)`` (``jaxlie.manifold.rplus``).

There is one scan objective, :class:`FieldScan`: the decay-rate log-likelihood of a scan on
any :class:`~lidarjax.maps.AbstractDecayRateField` (a DCT map, a user's field, a grid map,
the smoothed grid map) through the one forward model
:func:`~lidarjax.maps.field_log_likelihood`.

On a grid decay-rate map the exact likelihood is only piecewise smooth (the end-point term
``log lambda_k`` jumps between cells), so its gradient carries no information about where
the end points should go. :class:`~lidarjax.maps.SmoothDecayRateField` is the *continuous*
field obtained by bilinear interpolation of the cell rates (optionally Gaussian-blurred for
a wider basin); :func:`SmoothDecayRateScan` is :class:`FieldScan` on it with an end-point
rate floor. :func:`refine_scan_pose` runs refinement coarse to fine over a sequence of
fields, e.g. :func:`smooth_fields` with blur widths 0.3, 0.15, 0.05 m (on the Intel map an
unblurred last stage has spurious local optima a few cm from the global one, a 0.05 m blur
removes them), and :func:`refine_dct_scan_pose` over a DCT map's ``smoothed`` copies.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float

from ..maps import (
    AbstractDecayRateField,
    DCTMap,
    DecayRateMap,
    SmoothDecayRateField,
    blur,
    field_log_likelihood,
)
from ..rays import check_finite_nonnegative, from_scan

__all__ = [
    "DCTScan",
    "FieldScan",
    "refine_dct_scan_pose",
    "SmoothDecayRateField",
    "SmoothDecayRateScan",
    "blur",
    "refine_pose",
    "refine_scan_pose",
    "smooth_fields",
]

# ``SmoothDecayRateField`` (now in ``lidarjax.maps``) and ``blur`` (``lidarjax.maps``'s
# smoothing) are re-exported here under their old names.


def _check_scan(azimuths, ranges, r_min, r_max, dtype) -> tuple[Array, Array]:
    """One 2-D scan's ``[b]`` azimuths and ranges as arrays of ``dtype`` (``ValueError`` for
    mismatched or empty shapes, bad ranges or limits)."""
    az = jnp.asarray(azimuths, dtype)
    rg = jnp.asarray(ranges, dtype)
    if az.ndim != 1 or rg.shape != az.shape or az.shape[0] == 0:
        raise ValueError(
            f"azimuths and ranges must both have shape [b], b > 0; got {az.shape}, {rg.shape}"
        )
    if not (0 <= float(r_min) < float(r_max)):
        raise ValueError(f"need 0 <= r_min < r_max, got {r_min}, {r_max}")
    return az, check_finite_nonnegative(rg, "ranges")


class FieldScan(eqx.Module):
    """Log-likelihood of one 2-D scan on any decay-rate field; ``obj(pose) -> []`` (nats),
    differentiable in the pose (world-from-sensor SE(2)), for :func:`refine_pose`.

    Works with every :class:`~lidarjax.maps.AbstractDecayRateField`: a
    :class:`~lidarjax.maps.DCTMap` (smooth, ch. 9: no blurring needed), a user's field, a
    :class:`~lidarjax.maps.SmoothDecayRateField` (see :func:`SmoothDecayRateScan`), or a
    :class:`~lidarjax.maps.DecayRateMap` (exact but only piecewise smooth in the pose: the
    end-point rate jumps between cells, so prefer a smooth field there). Eqs. (9.5),
    (9.11), (9.12) via :func:`~lidarjax.maps.field_log_likelihood`:
    ``log(lambda(x(r)) + rate_floor) - int_0^r lambda`` for HIT readings,
    ``log(1 - exp(-int_0^r_min lambda))`` for SUB and ``-int_0^r_max lambda`` for SUP.

    Smoothness in the pose: as smooth as the field's ``decay_rate`` at the HIT end points
    and its ``integral``, plus a kink per ray where its log-likelihood meets ``ray_floor``
    (``rate_floor`` adds none). On a :class:`~lidarjax.maps.SmoothDecayRateField` the
    objective is continuous, and C-infinity on the open set of poses where

    1. no HIT end point lies on a cell-centre line ``x = origin_x + (i + 1/2) res`` or
       ``y = origin_y + (j + 1/2) res`` (where the bilinear interpolant's slope jumps),
    2. no midpoint node of any ray lies on such a line (``n_nodes`` per ray, evenly over
       the part inside the grid box of ``[0, r]``; ``r`` the range for HIT, ``r_min`` for
       SUB, ``r_max`` for SUP),
    3. no ray starts or ends on the grid box border or passes through a box corner,
    4. no ray's log-likelihood equals ``ray_floor``.

    On these sets the gradient jumps (right minus left derivative): for (1) by the
    interpolant's slope jump across the line times ``|d x_end / d pose|`` over
    ``lambda + rate_floor``; for (2) by minus ``chord / n_nodes`` times the slope jump
    times ``|d x_node / d pose|`` (the node's share of ``-S``). Where a HIT end point
    crosses the grid box border the value itself jumps (the end-point rate switches to
    ``outside_rate``). Set (2) is dense: with 256 nodes, a 1e-4 finite-difference step in
    the pose crosses lines even on a 7-beam scan, which is why ``jax.test_util.check_grads``
    reports relative errors ~1e-3; at poses whose points keep off the lines by more than the
    step, :func:`lidarjax.testing.check_gradients` passes at float64 tolerances, and on a
    line the one-sided derivatives differ by the jump above (``tests/test_testing.py``).

    Attributes:
        field: the decay-rate field.
        azimuths: ``[b]`` beam angles (rad); ranges: ``[b]`` readings (m).
        r_min, r_max: range limits (m).
        rate_floor: added to ``lambda`` at HIT end points (1/m, default 0) so that end
            points where the field is 0 (e.g. never-hit cells) give a finite density.
        ray_floor: per-ray log-likelihood floor (nats) or None; a floor keeps beams whose end
            points leave a field's box (``lambda = 0`` there) from making the objective
            ``-inf`` at a poor start pose.
    """

    field: AbstractDecayRateField
    azimuths: Float[Array, " b"]
    ranges: Float[Array, " b"]
    r_min: float = eqx.field(static=True)
    r_max: float = eqx.field(static=True)
    rate_floor: float = eqx.field(static=True)
    ray_floor: float | None = eqx.field(static=True)

    def __init__(
        self,
        field: AbstractDecayRateField,
        azimuths: Float[ArrayLike, " b"],
        ranges: Float[ArrayLike, " b"],
        r_min: float,
        r_max: float,
        *,
        rate_floor: float = 0.0,
        ray_floor: float | None = -10.0,
    ):
        if not isinstance(field, AbstractDecayRateField) or field.dim != 2:
            raise ValueError(
                f"field must be a 2-D AbstractDecayRateField, got {type(field).__name__}"
            )
        dtype = jnp.result_type(float)
        self.azimuths, self.ranges = _check_scan(azimuths, ranges, r_min, r_max, dtype)
        self.field = field
        self.r_min, self.r_max = float(r_min), float(r_max)
        if not (np.isfinite(rate_floor) and rate_floor >= 0):
            raise ValueError(f"rate_floor must be finite and >= 0 (1/m), got {rate_floor!r}")
        self.rate_floor = float(rate_floor)
        self.ray_floor = None if ray_floor is None else float(ray_floor)

    def ray_log_likelihoods(self, pose: jaxlie.SE2) -> Float[Array, " b"]:
        """Per-beam log-likelihoods at ``pose``."""
        rays = from_scan(pose, self.azimuths, self.ranges, self.r_min, self.r_max)
        ll = field_log_likelihood(self.field, rays, rate_floor=self.rate_floor)
        if self.ray_floor is not None:
            ll = jnp.maximum(ll, self.ray_floor)
        return ll

    def __call__(self, pose: jaxlie.SE2) -> Float[Array, ""]:
        return jnp.sum(self.ray_log_likelihoods(pose))


def SmoothDecayRateScan(  # the former class's name, kept
    field: SmoothDecayRateField,
    azimuths: Float[ArrayLike, " b"],
    ranges: Float[ArrayLike, " b"],
    r_min: float,
    r_max: float,
    *,
    rate_floor: float = 1e-3,
    ray_floor: float | None = -10.0,
    n_nodes: int | None = None,
) -> FieldScan:
    """Decay-rate log-likelihood of one 2-D scan on a
    :class:`~lidarjax.maps.SmoothDecayRateField`: the :class:`FieldScan` of the field with
    an end-point rate floor (the former class of this name; same arguments, same values).

    ``log p(r) = log(lambda(x(r)) + rate_floor) - int_0^r lambda`` for HIT readings,
    ``log(1 - exp(-int_0^r_min lambda))`` for SUB and ``-int_0^r_max lambda`` for SUP
    (Eqs. 7.13, 7.16 on a continuous field); the optical depth is the field's midpoint rule
    (:meth:`~lidarjax.maps.SmoothDecayRateField.integral`).

    Args:
        field: the continuous field.
        azimuths: ``[b]`` beam angles (rad).
        ranges: ``[b]`` readings (m).
        r_min, r_max: range limits (m).
        rate_floor: added to ``lambda`` at end points (1/m) so never-hit cells give a finite
            density.
        ray_floor: per-ray log-likelihood floor (nats) or None.
        n_nodes: midpoint nodes per ray; default: the field's (256 unless built otherwise).

    Returns:
        ``obj(pose) -> []`` (nats), a :class:`FieldScan`.
    """
    if not isinstance(field, SmoothDecayRateField):
        raise ValueError(f"field must be a SmoothDecayRateField, got {type(field).__name__}")
    if n_nodes is not None and n_nodes != field.n_nodes:
        field = field.with_nodes(n_nodes)
    return FieldScan(
        field, azimuths, ranges, r_min, r_max, rate_floor=rate_floor, ray_floor=ray_floor
    )


DCTScan = FieldScan
"""The scan objective on a :class:`~lidarjax.maps.DCTMap` (kept name; same class as
:class:`FieldScan`)."""


def refine_pose(
    objective: Callable[[jaxlie.SE2], Float[Array, ""]],
    pose0: jaxlie.SE2,
    *,
    solver: optx.AbstractMinimiser | None = None,
    max_steps: int = 200,
    throw: bool = False,
    scale: float | None = None,
) -> tuple[jaxlie.SE2, optx.Solution]:
    """Maximise a differentiable scan log-likelihood over an SE(2) pose.

    Minimises ``-objective(pose) / scale`` over a tangent vector ``delta = (v_x, v_y,
    omega)`` (m, m, rad; in ``pose0``'s frame) with ``pose = pose0 @ exp(delta)``
    (``jaxlie.manifold.rplus``): the step is a retraction on SE(2), so the heading never
    wraps and the solver still sees a flat vector.

    Args:
        objective: ``objective(pose: jaxlie.SE2) -> []`` log-likelihood (e.g. a
            :class:`FieldScan`), differentiable.
        pose0: start pose (unbatched ``jaxlie.SE2``), e.g. the filter's estimate.
        solver: an optimistix minimiser; default ``optx.BFGS(rtol=1e-6, atol=1e-6)``
            (3 unknowns, so the dense quasi-Newton Hessian is cheap and robust).
        max_steps: iteration limit.
        throw: raise if the solver fails (default: report it in ``Solution.result``).
        scale: divides the objective (default: its magnitude at ``pose0``, at least 1), so
            that the tolerances are relative.

    Returns:
        ``(pose, solution)``: the refined pose and optimistix's ``Solution`` (``.value`` is
        the tangent vector ``delta``, ``.result``, ``.stats["num_steps"]``).
    """
    if not isinstance(pose0, jaxlie.SE2) or pose0.get_batch_axes() != ():
        raise ValueError("pose0 must be a single (unbatched) jaxlie.SE2")
    if solver is None:
        solver = optx.BFGS(rtol=1e-6, atol=1e-6)
    if scale is None:
        scale = jnp.maximum(jnp.abs(objective(pose0)), 1.0)

    def fn(delta, args):
        return -objective(jaxlie.manifold.rplus(pose0, delta)) / scale

    delta0 = jaxlie.manifold.zero_tangents(pose0)  # [3]
    sol = optx.minimise(fn, solver, delta0, max_steps=max_steps, throw=throw)
    return jaxlie.manifold.rplus(pose0, sol.value), sol


def smooth_fields(
    map: DecayRateMap, blur_schedule_m: Sequence[float] = (0.3, 0.15, 0.05)
) -> tuple[SmoothDecayRateField, ...]:
    """One :class:`~lidarjax.maps.SmoothDecayRateField` per blur width (m), for
    :func:`refine_scan_pose`."""
    if len(blur_schedule_m) == 0:
        raise ValueError("blur_schedule_m must not be empty")
    return tuple(SmoothDecayRateField(map, float(b)) for b in blur_schedule_m)


def refine_scan_pose(
    fields: Sequence[SmoothDecayRateField | AbstractDecayRateField],
    azimuths: Float[ArrayLike, " b"],
    ranges: Float[ArrayLike, " b"],
    pose0: jaxlie.SE2,
    r_min: float,
    r_max: float,
    *,
    max_steps: int = 200,
    **kwargs,
) -> tuple[jaxlie.SE2, optx.Solution]:
    """Coarse-to-fine :func:`refine_pose` of one scan: one optimisation per field (e.g.
    :func:`smooth_fields` of a decay-rate map, or any
    :class:`~lidarjax.maps.AbstractDecayRateField`s such as a user's fields of increasing
    detail; coarse first), each started from the last result. Each stage's objective is
    the :class:`FieldScan` of its field, built by :func:`SmoothDecayRateScan` (end-point
    rate floor 1e-3 by default) for a :class:`~lidarjax.maps.SmoothDecayRateField`;
    ``kwargs`` go to it. Jit- and vmap-compatible.

    Returns:
        The final pose and the last stage's ``Solution``.
    """
    if len(fields) == 0:
        raise ValueError("fields must not be empty")
    pose, sol = pose0, None
    for fld in fields:
        make = SmoothDecayRateScan if isinstance(fld, SmoothDecayRateField) else FieldScan
        obj = make(fld, azimuths, ranges, r_min, r_max, **kwargs)
        pose, sol = refine_pose(obj, pose, max_steps=max_steps)
    return pose, sol


@eqx.filter_jit
def refine_dct_scan_pose(
    map: DCTMap,
    azimuths: Float[ArrayLike, " b"],
    ranges: Float[ArrayLike, " b"],
    pose0: jaxlie.SE2,
    r_min: float,
    r_max: float,
    *,
    blur_schedule_m: Sequence[float] = (0.3, 0.15, 0.05, 0.0),
    max_steps: int = 100,
    ray_floor: float | None = -10.0,
) -> tuple[jaxlie.SE2, optx.Solution]:
    """Scan matching on a DCT map (ch. 9): coarse-to-fine :func:`refine_pose` of one 2-D
    scan with :class:`FieldScan` on :meth:`~lidarjax.maps.DCTMap.smoothed` copies of the map
    (Gaussian widths in m, coarse first; the last stage should be 0, the map itself).
    The stages run as one ``lax.scan`` (one compiled refinement); the whole call is
    compiled once per scan size and schedule (``eqx.filter_jit``); vmappable over scans.

    Returns:
        The final pose and the last stage's ``Solution``.
    """
    if len(blur_schedule_m) == 0:
        raise ValueError("blur_schedule_m must not be empty")
    sig = np.asarray(blur_schedule_m, dtype=float)
    if not np.all(np.isfinite(sig) & (sig >= 0)):
        raise ValueError(f"blur_schedule_m must be finite and >= 0, got {blur_schedule_m}")
    sigmas = jnp.asarray(sig, map.coeffs.dtype)

    def stage(pose_params, sigma):
        # one compiled refinement, scanned over the blur widths
        obj = FieldScan(map.smoothed(sigma), azimuths, ranges, r_min, r_max, ray_floor=ray_floor)
        pose, sol = refine_pose(obj, jaxlie.SE2(pose_params), max_steps=max_steps)
        return pose.parameters(), sol

    params, sols = jax.lax.scan(stage, pose0.parameters(), sigmas)
    return jaxlie.SE2(params), jax.tree_util.tree_map(lambda x: x[-1], sols)
