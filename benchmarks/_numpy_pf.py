"""Plain NumPy reference of one particle-filter step with the decay-rate scan model.

The baseline of ``benchmarks/particle_filter.py``: the same computation as
:meth:`lidarjax.localization.ParticleFilter.step` with an
:class:`~lidarjax.localization.OdometryMotionModel` and a
:class:`~lidarjax.localization.ScanModel` on a
:class:`~lidarjax.maps.DecayRateMap`, written with NumPy only (float64):

- motion update: ``X_t = X_{t-1} transform(chi + std(chi) * N(0, I))``;
- measurement update: per ray ``log lambda_k - sum_i lambda_i d_i`` (HIT),
  ``log(1 - exp(-depth(r_min)))`` (SUB) or ``-depth(r_max)`` (SUP), floored at
  ``ray_floor`` and summed over the beams. The optical depth uses the exact per-cell lengths
  ``d_i`` of the ray through the grid (the cell walk of :mod:`benchmarks._numpy_reference`,
  here reduced per ray instead of scattered into the grid) plus the outside rate times the
  length travelled outside the grid;
- estimate: weighted mean of the best 10 % (circular mean for the heading);
- systematic resampling when ``n_eff < 0.5 n``.

The walk is vectorised over all rays of a chunk: every iteration advances every ray that
is still walking by one cell; finished rays are dropped once half of the chunk is done.
"""

from __future__ import annotations

import math

import numpy as np
from _numpy_reference import _setup  # benchmarks/ is on sys.path (see _harness)

__all__ = ["NumpyParticleFilter", "scan_log_likelihoods"]

HIT, SUB, SUP = 0, 1, 2


def _ray_depths(rates_flat, outside_rate, grid_origin, res, shape, o, d, length):
    """Optical depth and end-cell rate of each ray.

    Args:
        rates_flat: ``[nx * ny]`` decay rates (1/m), row-major.
        outside_rate: rate of the space outside the grid.
        grid_origin: ``[2]`` lower corner of the grid.
        res: cell size (m).
        shape: ``(nx, ny)``.
        o: per-axis list of ``[m]`` ray origins.
        d: per-axis list of ``[m]`` unit ray directions.
        length: ``[m]`` lengths the rays are traced to.

    Returns:
        ``(depth, lam_k)``: ``[m]`` optical depths ``sum_i lambda_i d_i`` (inside plus
        outside the grid) and the rate of the cell containing the ray's end (the outside
        rate where the end lies outside the grid).
    """
    dtype = length.dtype
    d, t0, t_end, tol, cell, active = _setup(grid_origin, res, shape, o, d, length)
    m = length.shape[0]
    depth = np.zeros(m, dtype)
    grid_len = np.zeros(m, dtype)
    last_flat = np.zeros(m, np.int64)
    any_valid = np.zeros(m, bool)

    idx = np.flatnonzero(active)  # ray index of every walking ray
    t = t0[idx]
    te = t_end[idx]
    tl = tol[idx]
    c0 = [c[idx] for c in cell]
    cx, cy = c0[0].copy(), c0[1].copy()
    t_first, t_scale, step = [], [], []
    for k in range(2):
        dk = d[k][idx]
        moving = dk != 0
        up = dk > 0
        d_safe = np.where(moving, dk, dtype.type(1))
        first = (grid_origin[k] - o[k][idx] + (c0[k] + up).astype(dtype) * res) / d_safe
        t_first.append(np.where(moving, first, dtype.type(np.inf)))
        t_scale.append(np.where(moving, res / d_safe, dtype.type(0)))
        step.append(np.where(up, 1, -1) * moving)
    acc = np.zeros(idx.shape[0], dtype)
    glen = np.zeros(idx.shape[0], dtype)
    lastc = np.zeros(idx.shape[0], np.int64)
    seen = np.zeros(idx.shape[0], bool)
    ny = shape[1]

    def store(sel):
        r = idx[sel]
        depth[r] = acc[sel]
        grid_len[r] = glen[sel]
        last_flat[r] = lastc[sel]
        any_valid[r] = seen[sel]

    alive = np.ones(idx.shape[0], bool)
    while idx.shape[0]:
        tx = t_first[0] + (cx - c0[0]).astype(dtype) * t_scale[0]
        ty = t_first[1] + (cy - c0[1]).astype(dtype) * t_scale[1]
        t_min = np.minimum(tx, ty)
        last = t_min >= te - tl
        t_stop = np.where(last, te, t_min)
        seg = np.maximum(t_stop - t, dtype.type(0))
        valid = alive & ((seg > tl) | last)
        seg = np.where(valid, seg, dtype.type(0))
        flat = cx * ny + cy
        acc += rates_flat.take(flat, mode="clip") * seg  # finished rays: seg = 0
        glen += seg
        lastc = np.where(valid, flat, lastc)
        seen |= valid
        thresh = t_min + tl
        cx = cx + step[0] * (tx <= thresh)
        cy = cy + step[1] * (ty <= thresh)
        inside = (cx >= 0) & (cx < shape[0]) & (cy >= 0) & (cy < ny)
        t = t_stop
        alive &= ~last & inside
        n_alive = int(np.count_nonzero(alive))
        if n_alive <= alive.shape[0] // 2:
            store(~alive)
            a = np.flatnonzero(alive)
            idx, t, te, tl = idx[a], t[a], te[a], tl[a]
            c0 = [c[a] for c in c0]
            cx, cy = cx[a], cy[a]
            t_first = [x[a] for x in t_first]
            t_scale = [x[a] for x in t_scale]
            step = [x[a] for x in step]
            acc, glen, lastc, seen = acc[a], glen[a], lastc[a], seen[a]
            alive = np.ones(a.shape[0], bool)

    inside_end = any_valid & (t_end >= length)
    lam_last = rates_flat[last_flat]
    out_len = np.maximum(length - grid_len, dtype.type(0))
    if outside_rate != 0:
        depth = depth + outside_rate * out_len  # out_len is finite (r_max is finite here)
    lam_k = np.where(inside_end, lam_last, dtype.type(outside_rate))
    return depth, lam_k


def _log1mexp(x):
    """``log(1 - exp(-x))`` for ``x >= 0`` (``-inf`` at 0)."""
    with np.errstate(divide="ignore"):
        small = x < math.log(2.0)
        return np.where(small, np.log(-np.expm1(-np.where(small, x, 1.0))), np.log1p(-np.exp(-x)))


def scan_log_likelihoods(
    poses,
    ranges,
    *,
    rates,
    outside_rate: float,
    grid_origin,
    resolution: float,
    azimuths,
    r_min: float,
    r_max: float,
    ray_floor: float | None,
    chunk_rays: int = 1 << 16,
    per_ray: bool = False,
):
    """Decay-rate log-likelihood of one scan at ``n`` poses.

    Args:
        poses: ``[n 3]`` sensor poses ``(x, y, theta)`` (world from sensor).
        ranges: ``[b]`` raw readings (m).
        rates: ``[nx ny]`` decay rates (1/m).
        outside_rate: rate outside the grid and of the end cell of rays ending outside.
        grid_origin: ``[2]`` lower grid corner (m).
        resolution: cell size (m).
        azimuths: ``[b]`` beam angles relative to the heading (rad).
        r_min, r_max: range limits (readings below r_min are SUB, at/above r_max SUP).
        ray_floor: per-ray floor (nats) or None.
        chunk_rays: rays walked together.
        per_ray: return the ``[n b]`` per-ray values instead of the ``[n]`` sums.

    Returns:
        ``[n]`` (or ``[n b]``) float64 log-likelihoods.
    """
    poses = np.asarray(poses, np.float64)
    ranges = np.asarray(ranges, np.float64)
    az = np.asarray(azimuths, np.float64)
    rates = np.asarray(rates, np.float64)
    n, b = poses.shape[0], az.shape[0]
    kind = np.where(ranges < r_min, SUB, np.where(ranges >= r_max, SUP, HIT))
    length_b = np.where(kind == HIT, ranges, np.where(kind == SUB, r_min, r_max))
    rates_flat = rates.reshape(-1)
    origin = np.asarray(grid_origin, np.float64)
    res = np.float64(resolution)

    ll = np.empty((n, b))
    per_chunk = max(1, chunk_rays // b)  # whole poses per chunk
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        for start in range(0, n, per_chunk):
            p = poses[start : start + per_chunk]
            m = p.shape[0]
            th = p[:, 2:3] + az[None, :]
            o = [np.repeat(p[:, 0], b), np.repeat(p[:, 1], b)]
            d = [np.cos(th).reshape(-1), np.sin(th).reshape(-1)]
            length = np.tile(length_b, m)
            depth, lam_k = _ray_depths(
                rates_flat, outside_rate, origin, res, rates.shape, o, d, length
            )
            k = np.tile(kind, m)
            hit = np.where(lam_k > 0, np.log(np.where(lam_k > 0, lam_k, 1.0)), -np.inf) - depth
            out = np.where(k == HIT, hit, np.where(k == SUB, _log1mexp(depth), -depth))
            if ray_floor is not None:
                out = np.maximum(out, ray_floor)
            ll[start : start + m] = out.reshape(m, b)
    return ll if per_ray else ll.sum(axis=1)


def _logsumexp(x):
    mx = np.max(x)
    if not np.isfinite(mx):
        return mx
    return mx + math.log(np.sum(np.exp(x - mx)))


class NumpyParticleFilter:
    """NumPy twin of ``ParticleFilter(OdometryMotionModel(...), ScanModel(DecayRateMap))``.

    Args:
        sigma, alpha, inflation: motion noise as in ``OdometryMotionModel`` (SE(2)).
        scan_kwargs: keyword arguments of :func:`scan_log_likelihoods` (map and sensor).
        resample_fraction: resample when ``n_eff < resample_fraction * n``.
        best_fraction: fraction of the heaviest particles averaged for the estimate.
    """

    def __init__(
        self,
        sigma,
        alpha,
        scan_kwargs: dict,
        *,
        inflation: float = 1.0,
        resample_fraction: float = 0.5,
        best_fraction: float = 0.1,
    ):
        self.sigma = np.asarray(sigma, np.float64)
        self.alpha = np.asarray(alpha, np.float64)
        self.inflation = float(inflation)
        self.scan_kwargs = scan_kwargs
        self.resample_fraction = resample_fraction
        self.best_fraction = best_fraction

    def motion(self, rng, particles, control):
        """Sample ``X @ transform(xi)``, ``xi ~ N(control, diag(std)^2)``."""
        control = np.asarray(control, np.float64)
        std = self.inflation * (self.sigma + self.alpha @ np.abs(control))
        xi = control + std * rng.standard_normal((particles.shape[0], 3))
        x, y, th = particles[:, 0], particles[:, 1], particles[:, 2]
        c, s = np.cos(th), np.sin(th)
        new_th = np.angle(np.exp(1j * (th + xi[:, 2])))
        return np.stack(
            [x + c * xi[:, 0] - s * xi[:, 1], y + s * xi[:, 0] + c * xi[:, 1], new_th], 1
        )

    def step(self, rng, particles, log_weights, control, ranges):
        """One filter step. Returns ``(particles, log_weights, estimate [3], n_eff,
        resampled)``."""
        n = particles.shape[0]
        particles = self.motion(rng, particles, control)
        ll = scan_log_likelihoods(particles, ranges, **self.scan_kwargs)
        raw = log_weights + ll
        lse = _logsumexp(raw)
        if np.isfinite(lse) and not np.any(np.isnan(raw)):
            log_weights = raw - lse
        else:
            log_weights = np.full(n, -math.log(n))
        w = np.exp(log_weights)

        k = max(1, math.ceil(self.best_fraction * n))
        top = np.argpartition(-log_weights, k - 1)[:k]
        wt = np.exp(log_weights[top] - log_weights[top].max())
        wt /= wt.sum()
        p = particles[top]
        est = np.array(
            [
                wt @ p[:, 0],
                wt @ p[:, 1],
                math.atan2(wt @ np.sin(p[:, 2]), wt @ np.cos(p[:, 2])),
            ]
        )

        n_eff = 1.0 / np.sum(w * w)
        resampled = bool(n_eff < self.resample_fraction * n)
        if resampled:
            cdf = np.cumsum(w)
            u = rng.uniform()
            idx = np.searchsorted(cdf, (np.arange(n) + u) / n * cdf[-1], side="right")
            particles = particles[np.clip(idx, 0, n - 1)]
            log_weights = np.full(n, -math.log(n))
        return particles, log_weights, est, n_eff, resampled
