"""Measurement model for 2-D range scans on grid maps: the particle weights of MCL."""

from __future__ import annotations

import copy

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ..maps import AbstractGridModel, EndpointMap, smooth_stats
from ..rays import HIT, SUB, from_scan
from ..raytrace import check_backend, check_threads
from ..sensor_models import batch_log_likelihood, likelihood_field_log_likelihood


class ScanModel(eqx.Module):
    """Log-likelihood of one 2-D scan at every particle, ``sum_b log p(z_b | X, m)``
    (Eq. 7.15), evaluated with :func:`lidarjax.sensor_models.batch_log_likelihood`.

    Call it as ``model(particles, ranges)`` with ``particles`` a ``jaxlie.SE2`` with batch
    axis ``[n]`` (world-from-sensor) and ``ranges`` the ``[b]`` raw readings (m); returns
    ``[n]``. Pure and jit-compatible; the map is a traced field.

    Attributes:
        map: any grid model (:class:`~lidarjax.maps.AbstractGridModel`: decay-rate,
            reflection, endpoint, Gamma / Beta full posterior, or your own).
        azimuths: ``[b]`` beam angles relative to the sensor heading (rad).
        r_min: minimum range (m); readings below are SUB.
        r_max: maximum usable range (m); readings at or beyond are SUP.
        ray_floor: per-ray log-likelihood floor (nats) or None. Maximum-likelihood maps give
            likelihood 0 to some rays (a hit in a never-hit cell); one such ray would
            otherwise veto a particle. The same floor for every model keeps comparisons fair.
        endpoint_normalized: for an :class:`~lidarjax.maps.EndpointMap` only: True uses the
            per-ray normalised model of section 7.6.2 (traces every ray to ``r_max``);
            False (default) the classic likelihood field of MCL,
            ``log(1 - P) + log(z_hit N(dist) + z_rand / r_max)`` for in-range readings and
            ``log P`` otherwise, about 10x cheaper.
        z_rand: weight of a uniform "random reading" component mixed into every beam's
            likelihood (Thrun et al.'s z_rand), in [0, 1): ``p' = (1 - z_rand) p + z_rand
            u`` with ``u`` the uniform reading distribution on ``[0, r_max)``: density
            ``1 / r_max`` for in-range readings, mass ``r_min / r_max`` for SUB, 0 for SUP.
            ``p'`` stays normalised. A beam that the map cannot explain (a person, a
            changed door) then costs at most ``-log(z_rand / r_max)`` instead of vetoing
            the particle. 0 (default) is the pure model.
        beam_exponent: tempering exponent ``beta`` in (0, 1] on every beam's (floored,
            mixed) log-likelihood: ``sum_b beta log p(z_b | X)``. Neighbouring beams of a
            scan are not independent given an imperfect map; ``beta < 1`` (e.g. the
            inverse of the number of beams that share one independent piece of evidence)
            keeps the filter from being over-confident. 1 (default) is the pure model.
        chunk_size: rays walked together (see ``batch_log_likelihood``).
        backend: ray-walk backend, ``"auto"``, ``"native"`` or ``"jax"`` (see
            ``batch_log_likelihood``).
        threads: native worker threads (default: all cores; on particles sharded over
            devices, :func:`~lidarjax.localization.shard_state`, the cores divided among
            this process's devices of the mesh, at least 1 per device).
    """

    map: eqx.Module
    azimuths: Float[Array, " b"]
    r_min: float = eqx.field(static=True)
    r_max: float = eqx.field(static=True)
    ray_floor: float | None = eqx.field(static=True, default=None)
    endpoint_normalized: bool = eqx.field(static=True, default=False)
    z_rand: float = eqx.field(static=True, default=0.0)
    beam_exponent: float = eqx.field(static=True, default=1.0)
    chunk_size: int = eqx.field(static=True, default=2048)
    backend: str = eqx.field(static=True, default="auto")
    threads: int | None = eqx.field(static=True, default=None)

    def __init__(
        self,
        map,
        azimuths: Float[ArrayLike, " b"],
        r_min: float,
        r_max: float,
        *,
        ray_floor: float | None = None,
        endpoint_normalized: bool = False,
        z_rand: float = 0.0,
        beam_exponent: float = 1.0,
        chunk_size: int = 2048,
        backend: str = "auto",
        threads: int | None = None,
    ):
        if not isinstance(map, AbstractGridModel):
            raise ValueError(
                "map must be a grid model (an AbstractGridModel: DecayRateMap, ReflectionMap, "
                f"EndpointMap, GammaPosteriorMap, BetaPosteriorMap or your own); got "
                f"{type(map).__name__}"
            )
        if map.spec.dim != 2:
            raise ValueError(f"map must be 2-D for 2-D scans, got a {map.spec.dim}-D grid")
        az = jnp.asarray(azimuths, dtype=map.spec.origin.dtype)
        if az.ndim != 1 or az.shape[0] == 0 or not bool(jnp.all(jnp.isfinite(az))):
            raise ValueError(f"azimuths must be a non-empty finite [b] array, got shape {az.shape}")
        r_min, r_max = float(r_min), float(r_max)
        if not (np.isfinite(r_min) and 0 <= r_min < r_max):
            raise ValueError(f"need 0 <= r_min < r_max, got r_min={r_min}, r_max={r_max}")
        if ray_floor is not None and not np.isfinite(ray_floor):
            raise ValueError(f"ray_floor must be finite or None, got {ray_floor!r}")
        if not (isinstance(z_rand, (int, float, np.floating)) and 0 <= z_rand < 1):
            raise ValueError(f"z_rand must be a number in [0, 1), got {z_rand!r}")
        if not (isinstance(beam_exponent, (int, float, np.floating)) and 0 < beam_exponent <= 1):
            raise ValueError(f"beam_exponent must be a number in (0, 1], got {beam_exponent!r}")
        if z_rand > 0 and not np.isfinite(r_max):
            raise ValueError("z_rand > 0 needs a finite r_max (the uniform component's support)")
        self.map = map
        self.azimuths = az
        self.z_rand = float(z_rand)
        self.beam_exponent = float(beam_exponent)
        self.r_min, self.r_max = r_min, r_max
        self.ray_floor = None if ray_floor is None else float(ray_floor)
        self.endpoint_normalized = bool(endpoint_normalized)
        self.chunk_size = int(chunk_size)
        check_backend(backend)
        if threads is not None:
            check_threads(threads)
        self.backend = backend
        self.threads = threads

    def _with_threads(self, threads: int | None) -> ScanModel:
        """This model with another ``threads`` (no re-validation: usable on traced
        models)."""
        if threads is not None:
            check_threads(threads)
        new = copy.copy(self)
        object.__setattr__(new, "threads", threads)
        return new

    def ray_log_likelihoods(
        self, particles: jaxlie.SE2, ranges: Float[ArrayLike, " b"]
    ) -> Float[Array, "n b"]:
        """Per-ray log-likelihoods ``[n b]`` (nats): the model's, mixed with the uniform
        component (``z_rand``), floored at ``ray_floor`` and multiplied by
        ``beam_exponent``."""
        if not isinstance(particles, jaxlie.SE2):
            raise ValueError(f"particles must be a jaxlie.SE2, got {type(particles).__name__}")
        ranges = jnp.asarray(ranges, self.azimuths.dtype)
        if ranges.shape != self.azimuths.shape:
            raise ValueError(
                f"ranges must have shape {self.azimuths.shape} (one per beam), got {ranges.shape}"
            )
        n = particles.parameters().shape[0]
        rays = from_scan(
            particles,
            self.azimuths,
            jnp.broadcast_to(ranges, (n, ranges.shape[0])),
            self.r_min,
            self.r_max,
        )
        if isinstance(self.map, EndpointMap) and not self.endpoint_normalized:
            ll = likelihood_field_log_likelihood(self.map, rays)
        else:
            ll = batch_log_likelihood(
                self.map,
                rays,
                chunk_size=self.chunk_size,
                backend=self.backend,
                threads=self.threads,
            )
        if self.z_rand > 0:
            ll = _mix_uniform(ll, rays.kind, self.z_rand, self.r_min, self.r_max)
        if self.ray_floor is not None:
            ll = jnp.maximum(ll, self.ray_floor)
        if self.beam_exponent != 1.0:
            ll = self.beam_exponent * ll
        return ll

    def __call__(self, particles: jaxlie.SE2, ranges: Float[ArrayLike, " b"]) -> Float[Array, " n"]:
        return jnp.sum(self.ray_log_likelihoods(particles, ranges), axis=-1)


def _mix_uniform(ll, kind, z_rand: float, r_min: float, r_max: float) -> Array:
    """``log((1 - z) p + z u)`` per ray from ``log p``; ``u`` is the uniform reading
    distribution on ``[0, r_max)`` (density ``1/r_max`` for HIT, mass ``r_min/r_max`` for
    SUB, 0 for SUP). ``-inf`` inputs stay finite where ``u > 0``; no NaN."""
    log_keep = np.log1p(-z_rand)
    log_u = jnp.where(
        kind == HIT,
        np.log(z_rand / r_max),
        jnp.where(kind == SUB, np.log(z_rand * r_min / r_max) if r_min > 0 else -jnp.inf, -jnp.inf),
    ).astype(ll.dtype)
    return jnp.logaddexp(ll + log_keep, log_u)


class CoarseToFineScanModel(eqx.Module):
    """A scan likelihood whose map resolution follows the particle cloud: the measurement
    update uses the map smoothed by the largest ``sigmas_m[l]`` not above
    ``spread_factor`` times the cloud's spread, so a filter that does not yet know where
    it is weighs with a wide basin and a localized one with the sharp map.

    Build the levels from kernel-smoothed statistics (:func:`~lidarjax.maps.smooth_stats`)
    with :func:`coarse_to_fine_scan_model`. The spread is the root-mean-square distance of
    the particle positions from their mean (m, unweighted: after resampling all weights
    are equal). Like tempering, this changes the measurement model while the filter is
    uncertain (the posterior is that of a coarser map); once the spread is below
    ``sigmas_m[1] / spread_factor`` the filter uses the finest map, ``sigmas_m[0]``.

    One level is evaluated per call (the level's map is gathered from the stacked maps,
    so under ``vmap`` each filter uses its own level without evaluating the others).

    Attributes:
        stacked: the per-level :class:`ScanModel` s stacked along a leading ``[L]`` axis.
        sigmas_m: ``[L]`` increasing smoothing widths (m), ``sigmas_m[0]`` the finest.
        spread_factor: level ``l`` is used while ``spread >= sigmas_m[l] / spread_factor``.
    """

    stacked: ScanModel
    sigmas_m: tuple[float, ...] = eqx.field(static=True)
    spread_factor: float = eqx.field(static=True)

    def __init__(self, levels, sigmas_m, spread_factor: float = 1.0):
        levels = list(levels)
        sig = tuple(float(x) for x in sigmas_m)
        if not levels or not all(isinstance(m, ScanModel) for m in levels):
            raise ValueError("levels must be a non-empty sequence of ScanModel")
        if len(sig) != len(levels):
            raise ValueError(f"sigmas_m must have one width per level ({len(levels)}), got {sig}")
        if any(not np.isfinite(x) or x < 0 for x in sig) or any(
            b <= a for a, b in zip(sig, sig[1:])
        ):
            raise ValueError(f"sigmas_m must be finite, >= 0 and increasing, got {sig}")
        if not (np.isfinite(spread_factor) and spread_factor > 0):
            raise ValueError(f"spread_factor must be finite and > 0, got {spread_factor!r}")
        statics = {
            (
                type(m.map),
                m.r_min,
                m.r_max,
                m.ray_floor,
                m.z_rand,
                m.beam_exponent,
                m.endpoint_normalized,
                m.chunk_size,
                m.backend,
                m.threads,
            )
            for m in levels
        }
        shapes = {tuple(m.map.spec.shape) for m in levels}
        if len(statics) != 1 or len(shapes) != 1:
            raise ValueError("levels must share the map type, grid and ScanModel settings")
        self.stacked = jax.tree.map(lambda *x: jnp.stack(x), *levels)
        self.sigmas_m = sig
        self.spread_factor = float(spread_factor)

    def level(self, particles: jaxlie.SE2) -> Int[Array, ""]:
        """Index of the level used for these particles (int32 scalar)."""
        t = particles.translation()
        spread = jnp.sqrt(jnp.mean(jnp.sum((t - jnp.mean(t, axis=0)) ** 2, axis=-1)))
        thresholds = jnp.asarray(self.sigmas_m[1:], t.dtype) / self.spread_factor
        return jnp.sum(spread >= thresholds).astype(jnp.int32)

    def _at(self, level) -> ScanModel:
        return jax.tree.map(lambda a: a[level], self.stacked)

    def ray_log_likelihoods(self, particles: jaxlie.SE2, ranges) -> Float[Array, "n b"]:
        """Per-ray log-likelihoods ``[n b]`` (nats) of the level chosen for ``particles``."""
        return self._at(self.level(particles)).ray_log_likelihoods(particles, ranges)

    def __call__(self, particles: jaxlie.SE2, ranges) -> Float[Array, " n"]:
        return jnp.sum(self.ray_log_likelihoods(particles, ranges), axis=-1)


def coarse_to_fine_scan_model(
    stats,
    model_fn,
    sigmas_m,
    azimuths,
    r_min: float,
    r_max: float,
    *,
    spread_factor: float = 1.0,
    **scan_kwargs,
) -> CoarseToFineScanModel:
    """A :class:`CoarseToFineScanModel` from grid statistics: level ``l`` is
    ``ScanModel(model_fn(smooth_stats(stats, sigmas_m[l])), azimuths, r_min, r_max,
    **scan_kwargs)``.

    Args:
        stats: the map's :class:`~lidarjax.raytrace.GridStats`.
        model_fn: ``stats -> map``, e.g. :func:`~lidarjax.maps.decay_rate_map` or
            :func:`~lidarjax.maps.gamma_posterior`.
        sigmas_m: increasing smoothing widths (m), e.g. ``(0.0, 0.1, 0.2)``.
        azimuths, r_min, r_max, scan_kwargs: as for :class:`ScanModel`.
        spread_factor: see :class:`CoarseToFineScanModel`.
    """
    levels = [
        ScanModel(model_fn(smooth_stats(stats, s)), azimuths, r_min, r_max, **scan_kwargs)
        for s in sigmas_m
    ]
    return CoarseToFineScanModel(levels, sigmas_m, spread_factor)
