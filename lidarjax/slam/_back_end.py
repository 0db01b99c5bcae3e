"""Back end of decay-rate SLAM: the joint maximum a posteriori estimate of all scan poses
and the map's decay-rate field, and the alternating scheme it is compared with.

The objective (to maximise) is

    J(poses, theta) = sum_k sum_b log p(z_kb | pose_k, lambda_theta)
                      - 1/2 sum_e || Log(m_e^-1 (pose_i^-1 pose_j)) / sigma_e ||^2

where ``lambda_theta`` is a continuous decay-rate field on a grid covering the whole run
(:class:`~lidarjax.maps.SmoothDecayRateField`: the bilinear interpolant of the cell rates
``theta**2``), ``log p`` the decay-rate log-likelihood of each ray (HIT, no-return; Eqs.
7.13, 7.16 on a continuous field, :func:`~lidarjax.maps.field_log_likelihood`) and the
second sum runs over relative-pose factors (odometry, front-end increments, loop closures).
Poses move on the manifold: ``pose_k = pose0_k @ exp(delta_k)`` (jaxlie).

* :func:`optimize_joint` maximises ``J`` over ``(delta, theta)`` together with L-BFGS
  (optimistix), started from the closed-form ML grid of the initial poses.
* :func:`optimize_alternating` alternates the closed-form ML grid ``theta**2 = H / R`` of
  the current poses (Eq. 7.10) with the maximisation over the poses alone.
"""

from __future__ import annotations

import dataclasses
import math
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from ..maps import DecayRateMap, SmoothDecayRateField, field_log_likelihood
from ..rays import from_scan
from ..raytrace import GridSpec, accumulate
from ._front_end import se2 as _se2
from ._front_end import xy_yaw as _xy_yaw

__all__ = [
    "BackEndConfig",
    "BackEndResult",
    "joint_objective",
    "optimize_alternating",
    "optimize_joint",
    "trajectory_log_likelihood",
]


@dataclasses.dataclass(frozen=True)
class BackEndConfig:
    """Settings of the back end.

    Attributes:
        resolution_m: cell size of the field (m).
        range_cap_m: readings at or beyond are no-returns traced to it (m).
        n_nodes: midpoint nodes per ray of the optical depth.
        rate_floor: end-point rate floor (1/m).
        ray_floor: per-ray log-likelihood floor (nats).
        prior_hits, prior_length_m: pseudo-counts of the initial grid ``(H + a) / (R + b)``
            (never-seen cells start at ``a / b``).
        max_steps: L-BFGS iterations (joint), or per pose step (alternating).
        rounds: alternating rounds.
        chunk_size: rays per chunk of the likelihood (memory bound).
        backend: the optical depth of :func:`optimize_alternating`'s pose steps (the field
            is fixed there) and of :func:`trajectory_log_likelihood`: ``"auto"`` (the
            native kernel on a CPU where it is built, else JAX), ``"native"`` or
            ``"jax"``. :func:`optimize_joint` differentiates in the field too and always
            uses the JAX path.
    """

    resolution_m: float = 0.05
    range_cap_m: float = 10.0
    n_nodes: int = 256
    rate_floor: float = 1e-3
    ray_floor: float = -10.0
    prior_hits: float = 0.02
    prior_length_m: float = 0.1
    max_steps: int = 100
    rounds: int = 3
    chunk_size: int = 8192
    backend: str = "auto"

    def __post_init__(self):
        from ..raytrace import _native

        _native.check_backend(self.backend)
        for name in ("resolution_m", "range_cap_m", "prior_length_m"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")
        for name in ("rate_floor", "prior_hits"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
        if not (isinstance(self.ray_floor, (int, float)) and math.isfinite(self.ray_floor)):
            raise ValueError(f"ray_floor must be finite, got {self.ray_floor!r}")
        for name in ("n_nodes", "max_steps", "rounds", "chunk_size"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise ValueError(f"{name} must be a positive int, got {v!r}")


@dataclasses.dataclass(frozen=True)
class BackEndResult:
    """Output of :func:`optimize_joint` / :func:`optimize_alternating`.

    Attributes:
        poses: ``[N 3]`` optimised poses ``(x m, y m, yaw rad)``.
        field: the decay-rate field at the optimum.
        objective: ``[steps + 1]`` values of ``J`` (nats) at the start and after each
            step (joint: the final value only is exact per step; alternating: per round).
        seconds: wall time (s).
        seconds_per_iteration: wall time per L-BFGS iteration or per round (s).
    """

    poses: np.ndarray
    field: SmoothDecayRateField
    objective: np.ndarray
    seconds: float
    seconds_per_iteration: float


def _grid_spec(poses: np.ndarray, cfg: BackEndConfig) -> GridSpec:
    """A grid covering every pose plus the range cap (cells aligned to the resolution)."""
    res = cfg.resolution_m
    lo = np.floor((poses[:, :2].min(0) - cfg.range_cap_m) / res) - 2
    hi = np.ceil((poses[:, :2].max(0) + cfg.range_cap_m) / res) + 2
    return GridSpec(lo * res, res, tuple(int(v) for v in hi - lo))


def _ml_params(spec, poses, az, ranges, cfg: BackEndConfig):
    """``sqrt((H + a) / (R + b))`` of the scans at ``poses`` (Eq. 7.10 with pseudo-counts)."""
    rays = from_scan(_se2(jnp.asarray(poses)), az, ranges, 0.0, cfg.range_cap_m)
    st = accumulate(spec, rays)
    h = jnp.asarray(st.hits, st.lengths.dtype)
    return jnp.sqrt((h + cfg.prior_hits) / (st.lengths + cfg.prior_length_m))


def _field(spec, params, n_nodes, backend="jax"):
    zero = jnp.zeros((), params.dtype)
    return SmoothDecayRateField(
        DecayRateMap(spec, params**2, zero), n_nodes=n_nodes, backend=backend
    )


def joint_objective(
    deltas: Float[Array, "n 3"],
    params: Float[Array, "nx ny"],
    poses0: Float[Array, "n 3"],
    azimuths: Float[Array, " b"],
    ranges: Float[Array, "n b"],
    edges: Array,
    measurements: Float[Array, "e 3"],
    sigmas: Float[Array, "e 3"],
    spec: GridSpec,
    cfg: BackEndConfig,
    backend: str = "jax",
) -> Float[Array, ""]:
    """``J`` of the module docstring (nats) at ``pose_k = pose0_k @ exp(delta_k)`` and the
    field with cell rates ``params**2``.

    Args:
        deltas: ``[n 3]`` tangent offsets ``(v_x m, v_y m, omega rad)`` of the poses.
        params: ``[nx ny]`` square roots of the cell rates (sqrt(1/m)) on ``spec``.
        poses0: ``[n 3]`` base poses ``(x m, y m, yaw rad)``.
        azimuths: ``[b]`` beam angles (rad); ranges: ``[n b]`` readings (m).
        edges: ``[e 2]`` int node pairs ``(i, j)``; measurements: ``[e 3]`` relative poses
            ``pose_i^-1 pose_j``; sigmas: ``[e 3]`` their standard deviations (m, m, rad).
        spec: the field's grid.
        cfg: settings.
        backend: the optical depth's backend (``"jax"``: differentiable in ``params``;
            ``"native"`` / ``"auto"``: in ``deltas`` only, to second order).
    """
    poses = jaxlie.manifold.rplus(_se2(poses0), deltas)
    rays = from_scan(poses, azimuths, ranges, 0.0, cfg.range_cap_m)
    field = _field(spec, params, cfg.n_nodes, backend)
    ll = field_log_likelihood(field, rays, chunk_size=cfg.chunk_size, rate_floor=cfg.rate_floor)
    data = jnp.sum(jnp.maximum(ll, cfg.ray_floor))
    if edges.shape[0] == 0:
        return data
    pi = jax.tree_util.tree_map(lambda x: x[edges[:, 0]], poses)
    pj = jax.tree_util.tree_map(lambda x: x[edges[:, 1]], poses)
    err = (_se2(measurements).inverse() @ (pi.inverse() @ pj)).log() / sigmas
    return data - 0.5 * jnp.sum(err**2)


def _check(poses0, azimuths, ranges, edges, measurements, sigmas, pose_name="poses0"):
    p = np.asarray(poses0, float)
    az = np.asarray(azimuths, float)
    rg = np.asarray(ranges, float)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] == 0 or not np.all(np.isfinite(p)):
        raise ValueError(f"{pose_name} must be a finite [N, 3] array, got shape {p.shape}")
    if az.ndim != 1 or not np.all(np.isfinite(az)):
        raise ValueError("azimuths must be a finite [B] array")
    if rg.shape != (p.shape[0], az.shape[0]) or not np.all(np.isfinite(rg)) or np.any(rg < 0):
        raise ValueError(
            f"ranges must be finite, >= 0, shape {(p.shape[0], az.shape[0])}; got {rg.shape}"
        )
    e = np.zeros((0, 2), np.int32) if edges is None else np.asarray(edges)
    m = np.zeros((0, 3)) if measurements is None else np.asarray(measurements, float)
    s = np.ones((0, 3)) if sigmas is None else np.asarray(sigmas, float)
    if e.ndim != 2 or e.shape[1] != 2 or not np.issubdtype(e.dtype, np.integer):
        raise ValueError(f"edges must be an int [E, 2] array, got {e.dtype} {e.shape}")
    if e.size and (e.min() < 0 or e.max() >= p.shape[0]):
        raise ValueError("edges must index poses0")
    if m.shape != (e.shape[0], 3) or not np.all(np.isfinite(m)):
        raise ValueError(f"measurements must be a finite [{e.shape[0]}, 3] array")
    if s.shape != (e.shape[0], 3) or not np.all(np.isfinite(s) & (s > 0)):
        raise ValueError(f"sigmas must be a positive finite [{e.shape[0]}, 3] array")
    return p, az, rg, e.astype(np.int32), m, s


@eqx.filter_jit
def _lbfgs(fn, x0, args, max_steps):
    solver = optx.LBFGS(rtol=1e-8, atol=1e-8)
    return optx.minimise(fn, solver, x0, args, max_steps=max_steps, throw=False)


def _setup(poses0, azimuths, ranges, edges, measurements, sigmas, cfg):
    """Checked inputs as arrays of the default float dtype, the field's grid, the gauge
    mask (the first pose is held fixed) and the objective's scale (rays)."""
    p0, az, rg, e, m, s = _check(poses0, azimuths, ranges, edges, measurements, sigmas)
    dt = jnp.result_type(float)
    arrays = tuple(jnp.asarray(x, dt) for x in (p0, az, rg)) + (
        jnp.asarray(e),
        jnp.asarray(m, dt),
        jnp.asarray(s, dt),
    )
    n = p0.shape[0]
    free = jnp.ones((n, 1), dt).at[0].set(0.0)
    return arrays, _grid_spec(p0, cfg), free, float(n * az.shape[0])


def trajectory_log_likelihood(
    poses: np.ndarray,
    azimuths: np.ndarray,
    ranges: np.ndarray,
    cfg: BackEndConfig | None = None,
    *,
    grid_shifts: int = 8,
) -> float:
    """Self-consistency of a trajectory: the data term of ``J`` (module docstring) per ray
    (nats), the scans at ``poses`` scored on the closed-form ML grid of the same scans at
    the same poses (Eq. 7.10 with the pseudo-counts, then the continuous field).

    The better the scans of all visits agree at ``poses``, the higher it is; it needs no
    reference trajectory, so it also scores a reference (e.g. a log's corrected poses) on
    the same footing as an estimate. Comparable between trajectories of the same scans and
    settings only.

    A grid is tied to its axes: the same trajectory moved rigidly by part of a cell, or
    turned, scores differently (walls along the cell edges score higher). The score is
    therefore the mean over ``grid_shifts`` rigid motions of the whole trajectory, turned
    about its centroid by ``(k + 1/2) / grid_shifts`` of a right angle and shifted by a
    sub-cell offset (a low-discrepancy sequence), ``k = 0 .. grid_shifts - 1``. Measured on
    a simulated office (135 scans, walls along the axes), over seven random rigid motions
    of the true trajectory: a spread of 0.031 nats per ray with one motion, 0.007 with 8;
    the true poses as given, on an unmoved grid, score 0.07 higher.

    Args:
        poses: ``[N 3]`` poses ``(x m, y m, yaw rad)``.
        azimuths: ``[B]`` beam angles (rad).
        ranges: ``[N B]`` readings (m).
        cfg: settings (field resolution, range cap, floors, pseudo-counts).
        grid_shifts: rigid motions averaged over.

    Returns:
        Mean log-likelihood per ray (nats), each ray floored at ``cfg.ray_floor``.
    """
    cfg = BackEndConfig() if cfg is None else cfg
    if not isinstance(cfg, BackEndConfig):
        raise ValueError(f"cfg must be a BackEndConfig, got {type(cfg).__name__}")
    if isinstance(grid_shifts, bool) or not isinstance(grid_shifts, (int, np.integer)):
        raise ValueError(f"grid_shifts must be a positive int, got {grid_shifts!r}")
    if grid_shifts <= 0:
        raise ValueError(f"grid_shifts must be a positive int, got {grid_shifts!r}")
    p, az_np, rg_np, e, m, s = _check(poses, azimuths, ranges, None, None, None, "poses")
    k = np.arange(grid_shifts)
    # no motion is the identity: a trajectory whose walls happen to lie along the axes
    # gains nothing
    phi = 0.5 * np.pi * (k + 0.5) / grid_shifts
    # R2 low-discrepancy offsets in [0, 1)^2 cells
    off = np.stack([((k + 1) * 0.7548776662466927) % 1, ((k + 1) * 0.5698402909980532) % 1], 1)
    c = p[:, :2].mean(0)
    moved = []
    for a, o in zip(phi, off * cfg.resolution_m):
        rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        moved.append(np.c_[(p[:, :2] - c) @ rot.T + c + o, p[:, 2] + a])
    # one grid covering every motion: one compiled program
    spec = _grid_spec(np.concatenate(moved), cfg)
    dt = jnp.result_type(float)
    az, rg = jnp.asarray(az_np, dt), jnp.asarray(rg_np, dt)
    e, m, s = jnp.asarray(e), jnp.asarray(m, dt), jnp.asarray(s, dt)
    total = 0.0
    for q in moved:
        qj = jnp.asarray(q, dt)
        theta = _ml_params(spec, qj, az, rg, cfg)
        d0 = jnp.zeros_like(qj)
        total += float(joint_objective(d0, theta, qj, az, rg, e, m, s, spec, cfg, cfg.backend))
    return total / (grid_shifts * rg_np.size)


def optimize_joint(
    poses0: np.ndarray,
    azimuths: np.ndarray,
    ranges: np.ndarray,
    edges: np.ndarray | None = None,
    measurements: np.ndarray | None = None,
    sigmas: np.ndarray | None = None,
    cfg: BackEndConfig | None = None,
) -> BackEndResult:
    """Joint MAP estimate of all poses and the decay-rate field (module docstring), with
    L-BFGS over the pose offsets and the field's parameters together, started at
    ``poses0`` and the ML grid of ``poses0``. The first pose is held fixed (gauge).

    Args:
        poses0: ``[N 3]`` initial poses ``(x m, y m, yaw rad)``.
        azimuths: ``[B]`` beam angles (rad).
        ranges: ``[N B]`` readings (m).
        edges, measurements, sigmas: relative-pose factors (see :func:`joint_objective`);
            None for none.
        cfg: settings.

    Returns:
        :class:`BackEndResult`.
    """
    cfg = BackEndConfig() if cfg is None else cfg
    args, spec, free, scale = _setup(poses0, azimuths, ranges, edges, measurements, sigmas, cfg)
    t0 = time.perf_counter()
    theta0 = _ml_params(spec, args[0], args[1], args[2], cfg)

    def fn(x, _):
        d, th = x
        return -joint_objective(d * free, th, *args, spec, cfg) / scale

    x0 = (jnp.zeros_like(args[0]), theta0)
    j0 = -float(fn(x0, None)) * scale
    sol = _lbfgs(fn, x0, None, cfg.max_steps)
    d, th = sol.value
    j1 = -float(fn((d, th), None)) * scale
    secs = time.perf_counter() - t0
    poses = np.asarray(_xy_yaw(jaxlie.manifold.rplus(_se2(args[0]), d * free)), float)
    steps = max(int(sol.stats["num_steps"]), 1)
    return BackEndResult(
        poses, _field(spec, th, cfg.n_nodes), np.array([j0, j1]), secs, secs / steps
    )


def optimize_alternating(
    poses0: np.ndarray,
    azimuths: np.ndarray,
    ranges: np.ndarray,
    edges: np.ndarray | None = None,
    measurements: np.ndarray | None = None,
    sigmas: np.ndarray | None = None,
    cfg: BackEndConfig | None = None,
) -> BackEndResult:
    """The alternating scheme: ``cfg.rounds`` times, the closed-form ML grid of the current
    poses (Eq. 7.10, with the pseudo-counts), then L-BFGS over all poses with that field
    fixed (same objective ``J`` as :func:`optimize_joint`). Arguments as there."""
    cfg = BackEndConfig() if cfg is None else cfg
    (p0, azj, rgj, ej, mj, sj), spec, free, scale = _setup(
        poses0, azimuths, ranges, edges, measurements, sigmas, cfg
    )

    def fn(d, th_poses):  # one function for every round: compiled once
        th, poses = th_poses
        j = joint_objective(d * free, th, poses, azj, rgj, ej, mj, sj, spec, cfg, cfg.backend)
        return -j / scale

    t0 = time.perf_counter()
    poses = p0
    d0 = jnp.zeros_like(p0)
    values = []
    th = None
    for _ in range(cfg.rounds):
        th = _ml_params(spec, poses, azj, rgj, cfg)
        if not values:
            values.append(-float(fn(d0, (th, poses))) * scale)
        sol = _lbfgs(fn, d0, (th, poses), cfg.max_steps)
        values.append(-float(fn(sol.value, (th, poses))) * scale)
        poses = _xy_yaw(jaxlie.manifold.rplus(_se2(poses), sol.value * free))
    secs = time.perf_counter() - t0
    return BackEndResult(
        np.asarray(poses, float),
        _field(spec, th, cfg.n_nodes),
        np.asarray(values),
        secs,
        secs / cfg.rounds,
    )
