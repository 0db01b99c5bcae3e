"""Point-to-line ICP lidar odometry in JAX: the ``"icp"`` chain of :func:`run_slam`.

A scan-to-submap registration chain like the classical baseline's small_gicp front end
(:func:`~lidarjax.slam.icp_front_end`), written here so the pose graph's third chain needs
no optional dependency and runs as one compiled ``lax.scan`` (CPU or GPU):

1. Points. Each scan's readings in ``(0, range_cap_m)`` become 2-D points in the sensor
   frame; scans with more than ``max_points`` beams keep every ``ceil(B / max_points)``-th
   beam. A point's normal is the minor axis of the scatter of its valid neighbours along
   the scan (``normal_half_window`` beams either side, within ``normal_radius_m`` of it);
   it serves as a target only where that scatter is a line (at least three points, minor
   over major eigenvalue at most ``max_flatness``).
2. Registration. Scan ``k`` starts at the previous pose composed with the odometry's
   increment and is aligned to the last ``submap_scans`` scans (placed at their chain
   poses) by Gauss-Newton on the Cauchy-weighted (``cauchy_m``) point-to-line distances
   ``n . (R p + t - q)`` of every point to its nearest target within the stage's
   correspondence radius (``radii_m``, coarse to fine, ``iterations`` steps each, all
   bounded; brute-force nearest neighbours: ``max_points * submap_scans * max_points``
   distances per step). A direction the lines do not constrain (a corridor's axis)
   keeps the guess: the normal equations carry a small Levenberg damping.
3. Acceptance. The registration is kept when its last step moved less than
   ``converged_m`` / ``converged_rad``, at least ``min_inlier_fraction`` of the scan's
   points lie within ``inlier_m`` of a target point, and the correction to the guess is
   at most ``max_correction_m`` / ``max_correction_rad`` (the baseline's tests);
   otherwise the scan keeps the guess and is marked unregistered.

The chain runs in float32 whatever JAX's default, relative to its first pose, in
compiled blocks of :data:`BLOCK_SCANS` scans. The defaults' last radius (0.1 m) and
Cauchy width were set on orebro (drift seed 0). On the shared logs' drifting odometry
(stop 68, docs/results/slam.md; benchmarks/slam_icp_chain.py) its increments are a
median 2.2 / 3.4 / 2.4 / 4.7 cm off the corrected poses on intel / fhw / orebro /
edmonton with 1-2 gross errors per log (small_gicp's chain in the same run: 2.3 / 3.3
/ 2.8 / 4.6 cm, 3-9 gross errors), at 138-253 scans/s once compiled on a 2-core AMD
EPYC (small_gicp's chain 60-94 scans/s).
"""

from __future__ import annotations

import dataclasses
import math
import time
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from ._baselines import IcpFrontEndResult, _positive
from ._front_end import _check_inputs, between_np, compose_np

__all__ = ["BLOCK_SCANS", "PointIcpConfig", "point_icp_front_end", "scan_points"]


@dataclasses.dataclass(frozen=True)
class PointIcpConfig:
    """Settings of :func:`point_icp_front_end` (module docstring).

    Attributes:
        submap_scans: previous scans in the submap (>= 1).
        max_points: beams kept per scan (>= 8; larger scans are strided).
        normal_half_window: neighbours along the scan either side for a normal (>= 1).
        normal_radius_m: a neighbour counts within this distance of the point (m).
        max_flatness: a target's scatter: minor over major eigenvalue at most this.
        radii_m: correspondence radius per stage, coarse to fine (m).
        iterations: Gauss-Newton steps per stage (>= 1).
        inlier_m: a point is an inlier within this distance of a target point (m).
        min_inlier_fraction: accepted registration: inlier fraction at least this.
        max_correction_m, max_correction_rad: ... and correction to the guess at most
            these (m, rad).
        converged_m, converged_rad: ... and last step at most these (m, rad).
        min_correspondences: fewer pairs than this in a step: no step.
        cauchy_m: the pairs' Cauchy weights ``1 / (1 + (e / cauchy_m)^2)`` of the
            point-to-line distance ``e`` (m; 0: plain least squares).
    """

    submap_scans: int = 8
    max_points: int = 360
    normal_half_window: int = 2
    normal_radius_m: float = 0.5
    max_flatness: float = 0.1
    radii_m: tuple[float, ...] = (1.0, 0.3, 0.1)
    iterations: int = 15
    inlier_m: float = 0.1
    min_inlier_fraction: float = 0.3
    max_correction_m: float = 0.5
    max_correction_rad: float = math.radians(15.0)
    converged_m: float = 1e-3
    converged_rad: float = 1e-3
    min_correspondences: int = 10
    cauchy_m: float = 0.05

    def __post_init__(self):
        for name in (
            "submap_scans",
            "max_points",
            "normal_half_window",
            "iterations",
            "min_correspondences",
        ):
            v = getattr(self, name)
            low = 8 if name == "max_points" else 1
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ValueError(f"{name} must be an int >= {low}, got {v!r}")
        for name in (
            "normal_radius_m",
            "max_flatness",
            "inlier_m",
            "min_inlier_fraction",
            "max_correction_m",
            "max_correction_rad",
            "converged_m",
            "converged_rad",
        ):
            v = getattr(self, name)
            if (
                isinstance(v, bool)
                or not isinstance(v, (int, float))
                or not (math.isfinite(v) and v > 0)
            ):
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")
        v = self.cauchy_m
        if (
            isinstance(v, bool)
            or not isinstance(v, (int, float))
            or not (math.isfinite(v) and v >= 0)
        ):
            raise ValueError(f"cauchy_m must be a finite number >= 0 (0: off), got {v!r}")
        if self.min_inlier_fraction > 1:
            raise ValueError(
                f"min_inlier_fraction must be in (0, 1], got {self.min_inlier_fraction!r}"
            )
        r = self.radii_m
        if (
            not isinstance(r, tuple)
            or not r
            or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in r)
            or not all(math.isfinite(v) and v > 0 for v in r)
        ):
            raise ValueError(f"radii_m must be a non-empty tuple of positive numbers, got {r!r}")


def scan_points(
    ranges_m: np.ndarray, azimuths_rad: np.ndarray, range_cap_m: float, cfg: PointIcpConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every scan's points and normals in the sensor frame (module docstring, 1.).

    Args:
        ranges_m: ``[N, B]`` readings (m).
        azimuths_rad: ``[B]`` beam angles (rad).
        range_cap_m: readings at or beyond this carry no point (m).
        cfg: settings.

    Returns:
        ``(xy [N, P, 2] m, valid [N, P], normals [N, P, 2], target [N, P])``: ``P <=
        max_points`` kept beams; ``valid`` marks points, ``target`` the points with a
        line-like neighbourhood (their unit ``normals``; zeros elsewhere).
    """
    r = np.asarray(ranges_m, np.float64)
    az = np.asarray(azimuths_rad, np.float64)
    valid = np.isfinite(r) & (r > 0) & (r < range_cap_m)
    rr = np.where(valid, r, 0.0)
    xy = np.stack([rr * np.cos(az), rr * np.sin(az)], -1)  # [N B 2]
    h = cfg.normal_half_window
    n, b = r.shape
    pad_xy = np.pad(xy, ((0, 0), (h, h), (0, 0)))
    pad_ok = np.pad(valid, ((0, 0), (h, h)))
    nb_xy = np.stack([pad_xy[:, o : o + b] for o in range(2 * h + 1)], 2)  # [N B W 2]
    nb_ok = np.stack([pad_ok[:, o : o + b] for o in range(2 * h + 1)], 2)
    near = np.sum((nb_xy - xy[:, :, None]) ** 2, -1) <= cfg.normal_radius_m**2
    w = (nb_ok & near & valid[:, :, None]).astype(np.float64)
    cnt = w.sum(-1)
    mean = (w[..., None] * nb_xy).sum(2) / np.maximum(cnt, 1)[..., None]
    d = nb_xy - mean[:, :, None]
    sxx = (w * d[..., 0] ** 2).sum(-1)
    syy = (w * d[..., 1] ** 2).sum(-1)
    sxy = (w * d[..., 0] * d[..., 1]).sum(-1)
    half_tr = 0.5 * (sxx + syy)
    rad = np.sqrt(0.25 * (sxx - syy) ** 2 + sxy**2)
    lo, hi = half_tr - rad, half_tr + rad
    major = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # the line's direction
    normals = np.stack([-np.sin(major), np.cos(major)], -1)
    target = valid & (cnt >= 3) & (hi > 0) & (lo <= cfg.max_flatness * hi)
    normals = np.where(target[..., None], normals, 0.0)
    stride = max(1, math.ceil(b / cfg.max_points))
    s = slice(None, None, stride)
    return xy[:, s], valid[:, s], normals[:, s], target[:, s]


def _rot(yaw):
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    return jnp.stack([jnp.stack([c, -s]), jnp.stack([s, c])])


# The chain's own float32 compose and between, unwrapped yaw: jaxlie's (se2 / xy_yaw of
# _front_end) round differently, and the chain carries that round-off from scan to scan
# (on fhw, drift seed 0, the median heading error of its increments moves 0.268 -> 0.283
# degrees and two more registrations are rejected)
def _compose(a, b):
    c, s = jnp.cos(a[2]), jnp.sin(a[2])
    return jnp.stack([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2]])


def _between(a, b):
    c, s = jnp.cos(a[2]), jnp.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    dt = jnp.arctan2(jnp.sin(b[2] - a[2]), jnp.cos(b[2] - a[2]))
    return jnp.stack([c * dx + s * dy, -s * dx + c * dy, dt])


def _nearest(p, tgt, tgt_ok):
    """Index and squared distance of each point's nearest target: ``[P]``, ``[P]``.

    The index rides in the low bits of the float32 distance's bit pattern (non-negative
    floats order as their bits do), so one integer ``min`` finds both: XLA's CPU
    ``argmin`` is several times slower. The distance's last ``log2(T)`` mantissa bits
    are lost to the index (a relative 2^-(23 - log2 T) on the squared distance), so a
    near-tie may pick the other point; the returned distance is the exact one.
    """
    t = tgt.shape[0]
    bits = max(1, (t - 1).bit_length())
    far = jnp.asarray(1e6, tgt.dtype)  # masked targets: far away (d2 ~ 1e12, finite)
    tx = jnp.where(tgt_ok, tgt[:, 0], far)
    ty = jnp.where(tgt_ok, tgt[:, 1], far)
    # [T, P], reduced over the leading axis: XLA's CPU code vectorises this layout best
    d2 = ((tx[:, None] - p[None, :, 0]) ** 2 + (ty[:, None] - p[None, :, 1]) ** 2).astype(
        jnp.float32
    )
    key = jax.lax.bitcast_convert_type(d2, jnp.int32)
    low = (1 << bits) - 1
    key = (key & ~low) | jnp.arange(t, dtype=jnp.int32)[:, None]
    j = jnp.min(key, 0) & low
    d = jnp.sum((p - tgt[j]) ** 2, -1)
    return j, jnp.where(tgt_ok[j], d, jnp.inf)


def register(pose0, src, src_ok, tgt, tgt_n, tgt_ok, cfg: PointIcpConfig):
    """Point-to-line Gauss-Newton from ``pose0`` (module docstring, 2.).

    Args:
        pose0: ``[3]`` start ``(x, y, yaw)`` (m, rad) of the scan in the target's frame.
        src: ``[P, 2]`` the scan's points (sensor frame, m); ``src_ok`` ``[P]`` bool.
        tgt: ``[T, 2]`` target points (m); ``tgt_n`` ``[T, 2]`` their unit normals;
            ``tgt_ok`` ``[T]`` bool.
        cfg: settings.

    Returns:
        ``(pose [3], last_step [3] absolute, inlier_fraction)``.
    """
    src, tgt, tgt_n = (jnp.asarray(a) for a in (src, tgt, tgt_n))
    src_ok, tgt_ok = jnp.asarray(src_ok, bool), jnp.asarray(tgt_ok, bool)
    dt = src.dtype
    pose0 = jnp.asarray(pose0, dt)

    def step(pose, radius):
        rot = _rot(pose[2])
        q = src @ rot.T  # rotated, sensor-centred
        p = q + pose[:2]
        j, d2 = _nearest(p, tgt, tgt_ok)
        use = src_ok & (d2 <= radius**2)
        nrm = tgt_n[j]
        e = jnp.sum(nrm * (p - tgt[j]), -1)
        jac = jnp.stack([nrm[:, 0], nrm[:, 1], nrm[:, 1] * q[:, 0] - nrm[:, 0] * q[:, 1]], -1)
        w = use.astype(dt)
        if cfg.cauchy_m > 0:
            w = w / (1 + (e / cfg.cauchy_m) ** 2)
        h = (jac * w[:, None]).T @ jac
        g = (jac * (w * e)[:, None]).sum(0)
        damp = 1e-6 * jnp.trace(h) + 1e-9
        delta = -jnp.linalg.solve(h + damp * jnp.eye(3, dtype=dt), g)
        enough = jnp.sum(use) >= cfg.min_correspondences
        delta = jnp.where(enough & jnp.all(jnp.isfinite(delta)), delta, 0.0)
        return pose + delta, jnp.abs(delta)

    pose, last = pose0, jnp.zeros(3, dt)
    for radius in cfg.radii_m:

        def body(_, c, radius=radius):
            return step(c[0], radius)

        pose, last = jax.lax.fori_loop(0, cfg.iterations, body, (pose, last))
    p = src @ _rot(pose[2]).T + pose[:2]
    _, d2 = _nearest(p, tgt, tgt_ok)
    inl = jnp.sum(src_ok & (d2 <= cfg.inlier_m**2)) / jnp.maximum(jnp.sum(src_ok), 1)
    return pose, last, inl


BLOCK_SCANS = 128
"""Scans per compiled block of the chain: every log compiles the same program (per
``max_points``), and a progress bar advances per block."""


def _place(pose, xy, nrm):
    rot = _rot(pose[2])
    return xy @ rot.T + pose[:2], nrm @ rot.T


@partial(jax.jit, static_argnames=("cfg",))
def _block_jit(carry, xy, ok, nrm, tgt_ok, inc, ks, cfg: PointIcpConfig):
    """``BLOCK_SCANS`` steps of the chain (module docstring, 2.-3.): scans ``ks`` with
    their points, masks and odometry increments from the previous scan; ``carry`` is
    ``(previous pose, submap points, normals, target masks)`` with one row per slot."""

    def body(c, x):
        prev, bxy, bn, bok = c
        sxy, sok, snrm, stgt, u, k = x
        guess = _compose(prev, u)
        pose, last, inl = register(
            guess, sxy, sok, bxy.reshape(-1, 2), bn.reshape(-1, 2), bok.reshape(-1), cfg
        )
        corr = _between(guess, pose)
        good = (
            jnp.all(jnp.isfinite(pose))
            & (last[0] <= cfg.converged_m)
            & (last[1] <= cfg.converged_m)
            & (last[2] <= cfg.converged_rad)
            & (inl >= cfg.min_inlier_fraction)
            & (jnp.hypot(corr[0], corr[1]) <= cfg.max_correction_m)
            & (jnp.abs(corr[2]) <= cfg.max_correction_rad)
            & (jnp.sum(sok) >= cfg.min_correspondences)
        )
        pose = jnp.where(good, pose, guess)
        wxy, wn = _place(pose, sxy, snrm)
        slot = k % cfg.submap_scans
        c = (pose, bxy.at[slot].set(wxy), bn.at[slot].set(wn), bok.at[slot].set(stgt))
        return c, (pose, good)

    return jax.lax.scan(body, carry, (xy, ok, nrm, tgt_ok, inc, ks))


def point_icp_chain(
    ranges: np.ndarray,
    az: np.ndarray,
    odo: np.ndarray,
    range_cap_m: float,
    cfg: PointIcpConfig,
    progress: bool = False,
) -> tuple[np.ndarray, np.ndarray, float]:
    """:func:`point_icp_front_end` on checked inputs: ``(poses [N 3], registered [N],
    seconds)``."""
    t0 = time.perf_counter()
    n = ranges.shape[0]
    chain = np.empty((n, 3))
    chain[0] = odo[0]
    registered = np.ones(n, bool)
    if n > 1:
        xy, ok, nrm, tgt = scan_points(ranges, az, range_cap_m, cfg)
        p = xy.shape[1]
        # the odometry's increments in float64; the chain runs in float32 relative to
        # its first pose (micrometres within a few hundred metres of it)
        inc = np.zeros((n, 3))
        inc[1:] = between_np(odo[:-1], odo[1:])
        f32 = np.float32
        s = cfg.submap_scans
        bxy = np.zeros((s, p, 2), f32)
        bn = np.zeros((s, p, 2), f32)
        bok = np.zeros((s, p), bool)
        bxy[0], bn[0], bok[0] = xy[0], nrm[0], tgt[0]
        carry = (np.zeros(3, f32), bxy, bn, bok)
        m = -(-(n - 1) // BLOCK_SCANS) * BLOCK_SCANS  # steps, padded to whole blocks
        ks = np.arange(1, m + 1)
        live = ks < n
        kk = np.where(live, ks, 0)  # padded steps: scan 0 again, masked out

        def pad(a):
            keep = live.reshape((-1,) + (1,) * (a.ndim - 1))
            return np.where(keep, a[kk], np.zeros((), a.dtype))  # keeps a's dtype

        args = (
            pad(xy).astype(f32),
            pad(ok),
            pad(nrm).astype(f32),
            pad(tgt),
            pad(inc).astype(f32),
            ks.astype(np.int32),
        )
        blocks = range(0, m, BLOCK_SCANS)
        if progress:
            from tqdm.auto import tqdm

            blocks = tqdm(blocks, desc="icp chain", unit="block", total=m // BLOCK_SCANS)
        poses, good = [], []
        for b in blocks:
            sl = slice(b, b + BLOCK_SCANS)
            carry, (pb, gb) = _block_jit(carry, *(a[sl] for a in args), cfg)
            poses.append(pb)
            good.append(gb)
        rel = np.concatenate([np.asarray(x, np.float64) for x in poses])[: n - 1]
        chain[1:] = compose_np(odo[0], rel)
        registered[1:] = np.concatenate([np.asarray(x, bool) for x in good])[: n - 1]
    chain[:, 2] = np.arctan2(np.sin(chain[:, 2]), np.cos(chain[:, 2]))
    return chain, registered, time.perf_counter() - t0


def point_icp_front_end(
    ranges_m: np.ndarray,
    azimuths_rad: np.ndarray,
    odometry_xy_yaw: np.ndarray,
    *,
    range_cap_m: float = 20.0,
    cfg: PointIcpConfig | None = None,
    progress: bool = False,
) -> IcpFrontEndResult:
    """Point-to-line ICP lidar odometry (module docstring): each scan registered against
    the previous ``cfg.submap_scans`` scans from the odometry's guess, as one compiled
    ``lax.scan``. :func:`~lidarjax.slam.run_slam` runs it as a further chain of the pose
    graph (``SlamConfig.extra_chain_models`` ``"icp"``); unlike ``"gicp"``
    (:func:`~lidarjax.slam.icp_front_end`) it needs no optional package.

    Args:
        ranges_m: ``[N, B]`` readings (m), all positive; readings at or beyond
            ``range_cap_m`` (no-returns included) carry no point.
        azimuths_rad: ``[B]`` beam angles (rad).
        odometry_xy_yaw: ``[N, 3]`` raw odometry poses; its increments are the guesses and
            row 0 anchors the chain.
        range_cap_m: readings at or beyond this carry no point (m).
        cfg: settings (:class:`PointIcpConfig`; default its defaults).
        progress: tqdm progress bar (per block of ``BLOCK_SCANS`` scans).

    Returns:
        :class:`~lidarjax.slam.IcpFrontEndResult`: the chain ``[N, 3]`` ``(x [m],
        y [m], yaw [rad])`` (row 0 the odometry's, yaw wrapped to ``(-pi, pi]``), the
        ``[N]`` registered flags (``False``: the scan took the odometry's increment) and
        the wall time (s, compilation included).

    Raises:
        ValueError: bad shapes or values (the message names the argument).
    """
    rng, az, odo = _check_inputs(ranges_m, azimuths_rad, odometry_xy_yaw)
    cap = _positive(range_cap_m, "range_cap_m")
    cfg = PointIcpConfig() if cfg is None else cfg
    if not isinstance(cfg, PointIcpConfig):
        raise ValueError(f"cfg must be a PointIcpConfig or None, got {type(cfg).__name__}")
    return IcpFrontEndResult(*point_icp_chain(rng, az, odo, cap, cfg, progress))
