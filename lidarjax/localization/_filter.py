"""A functional particle filter over SE(2) / SE(3) poses (Thrun et al., Probabilistic
Robotics ch. 4 and 8; dissertation section 12.4.3).

Everything is a pure function of a :class:`ParticleState` (particles, normalised
log-weights, PRNG key). One :meth:`ParticleFilter.step` is: motion update (sample from the
motion model), measurement update (add the measurement log-likelihood of every particle),
pose estimate, and resampling when the effective sample size ``n_eff = 1 / sum w_i^2``
falls below ``resample_fraction * n``. :meth:`ParticleFilter.run` is one ``lax.scan`` over
a sequence of controls and measurements, so a whole log compiles once and runs without
host round-trips; ``jax.vmap`` over independent runs (keys / initial states) works. The
sequence is padded to a bucket of steps (``step_bucket``: the next power of two, at least
8), so logs of 100 and 120 steps share one compiled program.

Optional extensions, all with static shapes (off by default, so the plain filter is
unchanged):

* Augmented MCL (Thrun et al. Table 8.3): random-particle injection driven by short- and
  long-term averages of the measurement likelihood (``alpha_slow`` / ``alpha_fast`` and
  an ``injector`` such as :func:`global_injector`), for recovery from kidnapping.
* KLD-sampling (Fox 2003): an adaptive number ``n_active`` of live particles chosen at
  each resampling from the number of occupied histogram bins (``kld=True``); see
  :func:`kld_particle_count` and :func:`count_occupied_bins`.
* A proposal hook: a motion model with a ``propose`` method samples the new particles
  with the measurement in view and returns importance corrections (see
  :meth:`ParticleFilter.step`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .. import _checks
from ..rays import is_concrete
from . import _sharding
from ._particles import ParticleState, estimate
from ._poses import Pose, dof, take, to_vector
from ._resampling import (
    RESAMPLERS,
    _bin_keys,
    _check_open_unit,
    _check_particle_count,
    _inverse_cdf,
    _kld_sequential_count,
    effective_sample_size,
    normalize_log_weights,
)

# --------------------------------------------------------------------------------------
# The filter
# --------------------------------------------------------------------------------------


class StepInfo(eqx.Module):
    """Per-step output of :meth:`ParticleFilter.step` (stacked ``[T]`` by ``run``).

    Attributes:
        estimate: pose estimate after the measurement update (before resampling).
        n_eff: effective sample size after the measurement update.
        resampled: whether the particles were resampled.
        degenerate: every particle had likelihood 0 (or NaN); the weights were reset to
            uniform instead of becoming NaN.
        injected: int32, number of resampled particles replaced by injector samples
            (augmented MCL; 0 otherwise).
        n_active: int32, number of live particles after the step (KLD-sampling; ``n``
            otherwise).
        bad_control: the control had a NaN or infinite entry (only possible under
            ``jit`` / ``lax.scan``; concrete controls raise ``ValueError``). The step then
            left the particles and weights as they were (no motion, no measurement
            update, no resampling); ``estimate`` and ``n_eff`` describe those kept
            particles.
        infinite_likelihood: some live particle had log-likelihood ``+inf`` (and none
            NaN): the ``k`` particles at ``+inf`` share the weight equally, the others
            get weight 0, so ``n_eff = k`` (see :func:`normalize_log_weights`).
    """

    estimate: Pose
    n_eff: Float[Array, ""]
    resampled: Bool[Array, ""]
    degenerate: Bool[Array, ""]
    injected: Int[Array, ""]
    n_active: Int[Array, ""]
    bad_control: Bool[Array, ""] = eqx.field(default_factory=lambda: jnp.zeros((), bool))
    infinite_likelihood: Bool[Array, ""] = eqx.field(default_factory=lambda: jnp.zeros((), bool))


def _control_leaves(control) -> list:
    """The floating-point leaves of a control pytree (integer leaves are always finite)."""
    return [x for x in jax.tree.leaves(control) if jnp.issubdtype(jnp.result_type(x), jnp.inexact)]


def _check_controls_concrete(control, name: str, per_step: bool) -> None:
    """``ValueError`` naming ``name`` if every leaf of ``control`` is concrete and one has a
    NaN or infinite entry (no-op for traced controls: no host sync inside ``scan``)."""
    leaves = _control_leaves(control)
    if not leaves or not all(is_concrete(x) for x in leaves):
        return
    for x in leaves:
        a = np.asarray(x)
        bad = ~np.isfinite(a)
        if np.any(bad):
            first = tuple(int(i) for i in np.argwhere(bad)[0])
            where = f" (step {first[0]})" if per_step and first else ""
            raise ValueError(
                f"{name} must be finite (NaN or infinite odometry?); found {a[first]!r} at "
                f"index {first}{where}"
            )


def _bad_control(control) -> Bool[Array, ""]:
    """Traced test: does any floating-point leaf of ``control`` hold a NaN or inf?"""
    bad = jnp.zeros((), bool)
    for x in _control_leaves(control):
        bad = bad | jnp.any(~jnp.isfinite(x))
    return bad


def _log_interp(log_old, log_new, rate):
    """``log((1 - rate) exp(log_old) + rate exp(log_new))`` for ``rate`` in [0, 1]
    without leaving log space (``rate = 1`` gives ``log_new``, ``0`` gives ``log_old``)."""
    a = jnp.where(rate < 1, jnp.log1p(-jnp.minimum(rate, 1.0)) + log_old, -jnp.inf)
    b = jnp.where(rate > 0, jnp.log(jnp.maximum(rate, 0.0)) + log_new, -jnp.inf)
    return jnp.logaddexp(a, b)


def _average_rate(alpha: float, t, dtype):
    """Rate of the ``t``-th (1-based) update of a bias-corrected exponential average:
    ``alpha / (1 - (1 - alpha)^t)`` (``1`` at ``t = 1``, tending to ``alpha``; ``1/t``,
    the running mean, for ``alpha = 0``)."""
    t = jnp.asarray(t, dtype)
    if alpha == 0:
        return 1.0 / t
    if alpha == 1:
        return jnp.ones_like(t)
    return alpha / -jnp.expm1(t * math.log1p(-alpha))


def _where_tree(mask, a, b):
    """Per-particle ``where(mask, a, b)`` over the leaves of two ``[n]`` pose batches."""

    def sel(x, y):
        return jnp.where(mask.reshape(mask.shape + (1,) * (y.ndim - 1)), x.astype(y.dtype), y)

    return jax.tree.map(sel, a, b)


def _as_tuple(b):
    """A hashable tuple of floats for a static field (left as is if not convertible; the
    filter's check then reports it)."""
    try:
        return tuple(float(x) for x in np.asarray(b, np.float64).reshape(-1))
    except (TypeError, ValueError):
        return b


MIN_STEP_BUCKET = 8
"""The smallest number of steps :meth:`ParticleFilter.run` compiles for."""


def step_bucket(n_steps: int) -> int:
    """The number of steps :meth:`ParticleFilter.run` pads a sequence of ``n_steps`` to:
    the next power of two, at least ``MIN_STEP_BUCKET`` (8): 1-8 -> 8, 100 and 120 -> 128,
    129 -> 256. A new bucket compiles a new program. Fewer than half of the scanned steps
    are padding, and those skip the measurement model, the costly part of a step."""
    n_steps = int(n_steps)
    if n_steps < 0:
        raise ValueError(f"n_steps must be >= 0, got {n_steps}")
    return max(MIN_STEP_BUCKET, 1 << max(n_steps - 1, 0).bit_length())


def _steps_of(name: str, tree, n_steps: int | None) -> int:
    """The common leading axis ``[T]`` of the leaves of ``tree`` (``ValueError`` naming
    ``name`` if a leaf has none or another length than ``n_steps``)."""
    for x in jax.tree.leaves(tree):
        shape = jnp.shape(x)
        if len(shape) == 0:
            raise ValueError(f"{name} must have a leading [T] axis (steps), got a scalar leaf")
        if n_steps is None:
            n_steps = int(shape[0])
        elif shape[0] != n_steps:
            raise ValueError(
                f"{name} must have a leading axis of {n_steps} steps (that of controls), "
                f"got a leaf of shape {tuple(shape)}"
            )
    if n_steps is None:
        raise ValueError(f"{name} must hold at least one array with a leading [T] axis")
    return n_steps


def _pad_steps(tree, n_pad: int):
    """Append ``n_pad`` steps of zeros (``False``) to every leaf's leading axis. NumPy and
    list leaves are padded in NumPy (no compilation, no device round trip); JAX arrays and
    tracers with ``jnp`` (a small program per new length, or part of the caller's trace)."""

    def pad(x):
        if isinstance(x, jax.Array):  # includes tracers
            return jnp.concatenate([x, jnp.zeros((n_pad, *x.shape[1:]), x.dtype)])
        a = np.asarray(x)
        return np.concatenate([a, np.zeros((n_pad, *a.shape[1:]), a.dtype)])

    return jax.tree.map(pad, tree)


def _select_tree(pred, a, b):
    """``a`` where the scalar ``pred`` holds, else ``b`` (leaf by leaf, exact)."""
    return jax.tree.map(lambda x, y: jax.lax.select(pred, x, y), a, b)


class ParticleFilter(eqx.Module):
    """Particle filter with pluggable, pure motion and measurement models.

    Attributes:
        motion: ``motion(particles [n], control, *, key) -> particles [n]``, e.g.
            :class:`OdometryMotionModel`. If it also has a method
            ``propose(particles, control, z, *, key) -> (particles [n], log_correction [n])``
            that is used on measurement-update steps (see :meth:`step`).
        measurement: ``measurement(particles [n], z) -> [n]`` log-likelihoods (``-inf``
            allowed), e.g. :class:`~lidarjax.localization.ScanModel`. Use an
            ``equinox.Module`` so its arrays (the map) are traced, not baked in.
        resample_fraction: resample when ``n_eff < resample_fraction * n``.
        resampler: ``"systematic"`` (low variance, default), ``"stratified"`` or
            ``"multinomial"``.
        best_fraction: fraction of highest-weight particles averaged for the estimate.
        alpha_slow, alpha_fast: augmented MCL (Thrun et al. Table 8.3) decay rates of the
            long- and short-term averages of the measurement likelihood; ``0`` and ``0``
            (default) turn it off, otherwise ``0 <= alpha_slow < alpha_fast <= 1``.
        injector: ``injector(key, n) -> [n] poses`` of the particles' group, the source
            of random particles for augmented MCL (e.g. :func:`global_injector`).
        kld: KLD-sampling (Fox 2003): adapt the number of live particles at each
            resampling.
        kld_epsilon, kld_delta: KL bound (nats) and failure probability, both in (0, 1).
        kld_bin_size: bin edge lengths per pose-vector component (m, rad): 3 for SE(2),
            6 for SE(3).
        n_min: lower bound on the number of live particles with KLD-sampling.

    Augmented MCL. On every measurement update the weighted mean likelihood
    ``w_avg = sum_i w_i p(z | x_i)`` (``w`` the previous normalised weights) updates the
    averages ``w_slow += a_slow (w_avg - w_slow)`` and ``w_fast += a_fast (w_avg -
    w_fast)``, kept in log space (``logaddexp``) because scan log-likelihoods of hundreds
    of nats underflow in linear space. The averages are bias-corrected exponential means
    (Thrun's recursion started at 0 and divided by ``1 - (1 - a)^t`` after ``t``
    updates), so both equal ``w_avg`` after the first update and the first step cannot
    inject spuriously. The injection probability is ``p = max(0, 1 - w_fast / w_slow)``.
    An update step resamples when ``n_eff`` is low *or* ``p > 0`` (Thrun resamples every
    step; the ``n_eff`` test alone would rarely fire after a kidnapping, when all
    likelihoods are uniformly small), and every resampled live particle is then
    replaced, with probability ``p``, by an injector sample (``n`` candidates are drawn
    and selected with a Bernoulli mask, so shapes stay static).

    KLD-sampling. The state's ``n`` slots are the maximum; ``state.n_active`` leading
    ones are live, the others have log-weight ``-inf`` and are ignored by the estimate,
    ``n_eff``, the resampling threshold (``resample_fraction * n_active``) and the
    resampler. At a resampling, ``n`` iid candidates are drawn from the weights, and
    Fox's rule picks the smallest ``m`` with ``m >= kld_particle_count(k_m)`` and
    ``m >= n_min`` (``k_m`` the bins occupied by the first ``m`` candidates; ``n`` if
    none); then exactly ``n_active = m`` ancestors are drawn afresh with the chosen
    resampler (unbiased: ``m w_i`` offspring in expectation). The bins are those of the
    posterior particles (after motion and measurement). With static shapes the motion and
    measurement models still run on all ``n`` slots, so ``n_active`` reports how many
    particles the posterior needs; it does not save compute in JAX.
    """

    motion: Callable
    measurement: Callable
    resample_fraction: float = eqx.field(static=True, default=0.5)
    resampler: str = eqx.field(static=True, default="systematic")
    best_fraction: float = eqx.field(static=True, default=0.1)
    alpha_slow: float = eqx.field(static=True, default=0.0)
    alpha_fast: float = eqx.field(static=True, default=0.0)
    injector: Callable | None = None
    kld: bool = eqx.field(static=True, default=False)
    kld_epsilon: float = eqx.field(static=True, default=0.05)
    kld_delta: float = eqx.field(static=True, default=0.01)
    kld_bin_size: tuple = eqx.field(
        static=True, default=(0.5, 0.5, math.radians(10)), converter=lambda b: _as_tuple(b)
    )
    n_min: int = eqx.field(static=True, default=10)

    def __check_init__(self):
        if self.resampler not in RESAMPLERS:
            raise ValueError(
                f"resampler must be one of {sorted(RESAMPLERS)}, got {self.resampler!r}"
            )
        if not 0 <= self.resample_fraction <= 1:
            raise ValueError(
                f"resample_fraction must lie in [0, 1], got {self.resample_fraction!r}"
            )
        if not 0 < self.best_fraction <= 1:
            raise ValueError(f"best_fraction must lie in (0, 1], got {self.best_fraction!r}")
        for name in ("alpha_slow", "alpha_fast"):
            a = getattr(self, name)
            if isinstance(a, bool) or not isinstance(a, (int, float)) or not 0 <= a <= 1:
                raise ValueError(f"{name} must be a number in [0, 1], got {a!r}")
        if self.augmented:
            if not self.alpha_slow < self.alpha_fast:
                raise ValueError(
                    f"alpha_slow must be < alpha_fast for augmented MCL, got "
                    f"alpha_slow={self.alpha_slow!r}, alpha_fast={self.alpha_fast!r}"
                )
            if self.injector is None or not callable(self.injector):
                raise ValueError(
                    "injector must be a callable (key, n) -> poses when "
                    "alpha_slow / alpha_fast are set"
                )
        if not isinstance(self.kld, bool):
            raise ValueError(f"kld must be a bool, got {self.kld!r}")
        _check_open_unit("kld_epsilon", self.kld_epsilon)
        _check_open_unit("kld_delta", self.kld_delta)
        if isinstance(self.n_min, bool) or not isinstance(self.n_min, (int, np.integer)):
            raise ValueError(f"n_min must be a positive int, got {self.n_min!r}")
        if self.n_min <= 0:
            raise ValueError(f"n_min must be a positive int, got {self.n_min!r}")
        try:
            bs = np.asarray(self.kld_bin_size, np.float64)
        except (TypeError, ValueError):
            bs = None
        if (
            bs is None
            or bs.ndim != 1
            or bs.size not in (3, 6)
            or not np.all(np.isfinite(bs) & (bs > 0))
        ):
            raise ValueError(
                "kld_bin_size must be 3 (SE2) or 6 (SE3) positive finite bin sizes, got "
                f"{self.kld_bin_size!r}"
            )
        group = getattr(self.motion, "group", None)
        if group in (jaxlie.SE2, jaxlie.SE3) and self.kld and bs.size != dof(group):
            raise ValueError(
                f"kld_bin_size must have {dof(group)} entries for {group.__name__}, got "
                f"{self.kld_bin_size!r}"
            )

    @property
    def augmented(self) -> bool:
        """Whether augmented MCL (random-particle injection) is on."""
        return self.alpha_slow != 0 or self.alpha_fast != 0

    def _predict(self, state: ParticleState, control, z, update, key):
        """Motion update and log-likelihood (plus importance correction) per particle."""
        dtype = state.log_weights.dtype
        if not hasattr(self.motion, "propose"):
            particles = self.motion(state.particles, control, key=key)
            ll = _checks.cond(
                update,
                lambda: jnp.asarray(self.measurement(particles, z), dtype),
                lambda: jnp.zeros_like(state.log_weights),
            )
            return particles, ll

        def proposed():
            p, log_corr = self.motion.propose(state.particles, control, z, key=key)
            ll = jnp.asarray(self.measurement(p, z), dtype) + jnp.asarray(log_corr, dtype)
            return jax.tree.map(lambda x, y: x.astype(y.dtype), p, state.particles), ll

        def prior():
            p = self.motion(state.particles, control, key=key)
            p = jax.tree.map(lambda x, y: x.astype(y.dtype), p, state.particles)
            return p, jnp.zeros_like(state.log_weights)

        return _checks.cond(update, proposed, prior)

    def step(
        self, state: ParticleState, control, z, update: bool | Bool[Array, ""] = True
    ) -> tuple[ParticleState, StepInfo]:
        """One filter step: motion update with ``control``, measurement update with ``z``
        (skipped where ``update`` is False), estimate, conditional resampling (with
        random-particle injection and an adaptive particle count when configured; see
        the class docstring).

        Proposal hook: if ``self.motion`` has ``propose(particles, control, z, *, key)
        -> (new_particles [n], log_correction [n])``, update steps take the new particles
        from it and add ``log_correction = log p(x_new | x_prev, u) - log q(x_new | x_prev,
        u, z)`` (nats; prior minus proposal density of each new particle) to the
        measurement log-likelihood before normalising. The weights then stay
        ``w_prev * p(z | x) p(x | x_prev, u) / q(x | ...)``, so the filter remains a valid
        importance sampler of the same posterior for any proposal ``q`` whose support
        covers the prior's. Steps without an update use the plain ``motion(...)``.

        Bad input: a concrete ``control`` with a NaN or infinite entry raises
        ``ValueError``; a traced one (under ``jit`` / in :meth:`run`'s ``scan``) makes the
        step keep the previous particles and weights (no motion, measurement update or
        resampling) and sets ``StepInfo.bad_control``. Measurement log-likelihoods that are
        NaN or all ``-inf`` reset the weights to uniform (``StepInfo.degenerate``);
        ``+inf`` ones share the weight among those particles
        (``StepInfo.infinite_likelihood``). A state with no particles raises
        ``ValueError``.

        Sharding: on a state placed by :func:`~lidarjax.localization.shard_state` the
        measurement update runs per shard and the returned state is sharded the same way;
        the results equal the one-device results bitwise (see
        :func:`~lidarjax.localization.shard_state`). Such a step is compiled (one program
        per mesh and shapes); under your own ``jit`` the mesh is not visible, and XLA's
        default partitioning applies (correct, but not guaranteed bitwise).
        """
        mesh = _sharding.state_mesh(state)
        if mesh is None:
            return self._step(state, control, z, update, None)
        _check_particle_count(state.log_weights, "state")
        _check_controls_concrete(control, "control", per_step=False)
        return self._step_sharded(state, control, z, update, mesh)

    @_checks.checked_jit
    def _step_sharded(self, state: ParticleState, control, z, update, mesh):
        """:meth:`step` on a sharded state, compiled (``mesh`` static)."""
        return self._step(state, control, z, update, mesh)

    def _step(self, state: ParticleState, control, z, update, mesh):
        """:meth:`step`; ``mesh`` (static) is the particles' mesh or None."""
        _check_particle_count(state.log_weights, "state")
        _check_controls_concrete(control, "control", per_step=False)
        if mesh is not None:
            return self._step_on_mesh(state, control, z, update, mesh)
        key, k_motion, k_resample, bad_control, safe_control, update = self._step_keys(
            state, control, update
        )
        particles, ll = self._predict(state, safe_control, z, update, k_motion)
        n = state.log_weights.shape[-1]
        particles = _where_tree(jnp.broadcast_to(bad_control, (n,)), state.particles, particles)
        return self._update(state, particles, ll, bad_control, update, key, k_resample)

    @staticmethod
    def _step_keys(state: ParticleState, control, update):
        """The keys of a step and its control check: ``(key, k_motion, k_resample,
        bad_control, safe_control, update)``."""
        key, k_motion, k_resample = jax.random.split(state.key, 3)
        # A NaN/inf control (traced): no motion, no measurement update, no resampling;
        # the motion model sees zeros so that nothing downstream is computed from NaN.
        bad_control = _bad_control(control)
        safe_control = jax.tree.map(
            lambda x: (
                jnp.where(bad_control, jnp.zeros_like(x), x)
                if jnp.issubdtype(jnp.result_type(x), jnp.inexact)
                else x
            ),
            control,
        )
        update = jnp.asarray(update) & ~bad_control
        return key, k_motion, k_resample, bad_control, safe_control, update

    def _step_on_mesh(self, state: ParticleState, control, z, update, mesh):
        """:meth:`step` on particles split over ``mesh`` (see :mod:`._sharding`): one
        all-gather per step, then the bookkeeping on the whole arrays on every device,
        exactly as on one device; the new particles and weights are split again.

        With a per-particle measurement (:class:`ScanModel`) and no proposal hook, the
        motion update is partitioned by XLA (elementwise; JAX's partitionable threefry
        draws each shard's numbers of the one-device filter) and the measurement runs on
        each device's own particles before the gather. Otherwise the state is gathered
        first and the whole one-device step runs on every device."""
        rest = (state.key, state.n_active, state.log_w_slow, state.log_w_fast, state.n_updates)

        def rebuild(particles, log_weights, rest):
            key, n_active, log_w_slow, log_w_fast, n_updates = rest
            return ParticleState(
                particles,
                log_weights,
                key,
                n_active=n_active,
                log_w_slow=log_w_slow,
                log_w_fast=log_w_fast,
                n_updates=n_updates,
            )

        def unbuild(new_state, info):
            split = (new_state.particles, new_state.log_weights)
            kept = (
                new_state.key,
                new_state.n_active,
                new_state.log_w_slow,
                new_state.log_w_fast,
                new_state.n_updates,
            )
            return split, (kept, info)

        if _sharding.per_particle(self.measurement) and not hasattr(self.motion, "propose"):
            key, k_motion, k_resample, bad_control, safe_control, update = self._step_keys(
                state, control, update
            )
            moved = _sharding.split(self.motion(state.particles, safe_control, key=k_motion), mesh)
            filt = self
            if self.measurement.threads is None:  # the cores shared by the shards
                threads = _sharding.threads_per_shard(mesh)
                filt = eqx.tree_at(
                    lambda f: f.measurement, self, self.measurement._with_threads(threads)
                )
            dtype = state.log_weights.dtype

            def local(split, rep):
                moved, old, log_weights = split
                filt, z, update, bad_control = rep[:4]
                ll = _checks.cond(
                    update,
                    lambda: jnp.asarray(filt.measurement(moved, z), dtype),
                    lambda: jnp.zeros_like(log_weights),
                )
                m = log_weights.shape[0]
                kept = _where_tree(jnp.broadcast_to(bad_control, (m,)), old, moved)
                return kept, log_weights, ll

            def full(split, rep):
                particles, log_weights, ll = split
                filt, _, update, bad_control, rest, key, k_resample = rep
                whole = rebuild(particles, log_weights, rest)
                return unbuild(
                    *filt._update(whole, particles, ll, bad_control, update, key, k_resample)
                )

            (particles, log_weights), (kept, info) = _sharding.gather_then(
                local,
                full,
                mesh,
                (moved, state.particles, state.log_weights),
                (filt, z, update, bad_control, rest, key, k_resample),
            )
        else:

            def full(split, rep):
                particles, log_weights = split
                filt, rest, control, z, update = rep
                whole = rebuild(particles, log_weights, rest)
                return unbuild(*filt._step(whole, control, z, update, None))

            (particles, log_weights), (kept, info) = _sharding.gather_then(
                lambda split, rep: split,
                full,
                mesh,
                (state.particles, state.log_weights),
                (self, rest, control, z, update),
            )
        return _sharding.split_state(rebuild(particles, log_weights, kept), mesh), info

    def _update(self, state: ParticleState, particles, ll, bad_control, update, key, k_resample):
        """The weights, estimate and resampling of :meth:`step` after the motion update
        (``particles``) and the measurement log-likelihoods ``ll``."""
        n = _check_particle_count(state.log_weights, "state")
        if self.kld or self.augmented:
            k_resample, k_cand, k_inject = jax.random.split(k_resample, 3)
        dtype = state.log_weights.dtype

        n_active = jnp.asarray(state.n_active, jnp.int32)
        slots = jnp.arange(n)
        raw = state.log_weights + ll
        if self.kld:
            active = slots < n_active
            raw = jnp.where(active, raw, -jnp.inf)
        nan = jnp.any(jnp.isnan(raw))
        degenerate = ~jnp.any(raw > -jnp.inf) | nan
        infinite = jnp.any(raw == jnp.inf) & ~nan
        log_weights = normalize_log_weights(raw)
        if self.kld:  # the uniform fallback of normalize_log_weights: live slots only
            uniform = jnp.where(active, -jnp.log(n_active.astype(dtype)), -jnp.inf)
            log_weights = jnp.where(degenerate, uniform, log_weights)
        log_weights = jnp.where(bad_control, state.log_weights, log_weights)

        # augmented MCL: bias-corrected exponential averages of w_avg in log space
        log_w_slow, log_w_fast = state.log_w_slow, state.log_w_fast
        n_updates = state.n_updates
        p_inject = jnp.zeros((), dtype)
        if self.augmented:
            log_w_avg = jax.nn.logsumexp(raw)  # log sum_i w_i p(z | x_i) (w normalised)
            fold = update & ~jnp.isnan(log_w_avg) & (log_w_avg < jnp.inf)
            t = n_updates + 1
            new_slow = _log_interp(log_w_slow, log_w_avg, _average_rate(self.alpha_slow, t, dtype))
            new_fast = _log_interp(log_w_fast, log_w_avg, _average_rate(self.alpha_fast, t, dtype))
            log_w_slow = jnp.where(fold, new_slow, log_w_slow).astype(dtype)
            log_w_fast = jnp.where(fold, new_fast, log_w_fast).astype(dtype)
            n_updates = jnp.where(fold, t, n_updates).astype(jnp.int32)
            diff = log_w_fast - log_w_slow  # NaN when both are -inf: no information
            p_inject = jnp.where(
                jnp.isnan(diff), 0.0, jnp.clip(-jnp.expm1(jnp.minimum(diff, 0.0)), 0.0, 1.0)
            ).astype(dtype)

        mid = ParticleState(particles, log_weights, key, n_active=n_active)
        est = estimate(mid, self.best_fraction)
        n_eff = effective_sample_size(log_weights)
        if self.kld:
            resample = update & (n_eff < self.resample_fraction * n_active.astype(dtype))
        else:
            resample = update & (n_eff < self.resample_fraction * n)
        if self.augmented:
            resample = resample | (update & (p_inject > 0))

        resample_fn = RESAMPLERS[self.resampler]
        if self.kld:
            u = jax.random.uniform(k_cand, (n,), dtype=dtype)
            cand = _inverse_cdf(log_weights, u)  # n iid draws, in draw order
            v = to_vector(particles)
            if v.shape[-1] != len(self.kld_bin_size):
                raise ValueError(
                    f"kld_bin_size must have {v.shape[-1]} entries for these particles, "
                    f"got {len(self.kld_bin_size)}"
                )
            bins = _bin_keys(v, self.kld_bin_size)[cand]
            m = _kld_sequential_count(bins, self.kld_epsilon, self.kld_delta, self.n_min)
            idx = resample_fn(log_weights, key=k_resample, n_active=m)
            n_next = jnp.where(resample, m, n_active).astype(jnp.int32)
        else:
            idx = resample_fn(log_weights, key=k_resample)
            n_next = jnp.where(resample, n, n_active).astype(jnp.int32)
        idx = jnp.where(resample, idx, slots)
        particles = take(particles, idx)
        live = slots < n_next

        injected = jnp.zeros((), jnp.int32)
        if self.augmented:
            k_draw, k_coin = jax.random.split(k_inject)
            fresh = self.injector(k_draw, n)
            if type(fresh) is not type(particles) or (
                fresh.parameters().shape != particles.parameters().shape
            ):
                raise ValueError(
                    f"injector must return [{n}] {type(particles).__name__} poses, got "
                    f"{type(fresh).__name__} {getattr(fresh.parameters(), 'shape', None)}"
                )
            coin = jax.random.uniform(k_coin, (n,), dtype=dtype) < p_inject
            swap = resample & live & coin
            particles = _where_tree(swap, fresh, particles)
            injected = jnp.sum(swap).astype(jnp.int32)

        if self.kld:
            reset = jnp.where(live, -jnp.log(n_next.astype(dtype)), -jnp.inf)
        else:
            reset = -math.log(n)
        log_weights = jnp.where(resample, reset, log_weights)
        info = StepInfo(
            est,
            n_eff,
            resample,
            degenerate & update,
            injected,
            n_next,
            bad_control=bad_control,
            infinite_likelihood=infinite & update,
        )
        new_state = ParticleState(
            particles,
            log_weights,
            key,
            n_active=n_next,
            log_w_slow=log_w_slow,
            log_w_fast=log_w_fast,
            n_updates=n_updates,
        )
        return new_state, info

    def run(
        self, state: ParticleState, controls, measurements, updates=None
    ) -> tuple[ParticleState, StepInfo]:
        """Filter a whole sequence with one ``lax.scan`` (jit-compiled once per bucket).

        Shape buckets: the ``T`` steps are padded to ``step_bucket(T)`` steps (the next
        power of two, at least 8: 100 and 120 steps both run as 128) and the number of
        real steps is a traced value, so sequences of every length in a bucket share one
        compiled program (and one entry of the persistent compilation cache). A padded
        step gets a zero control and measurement and no measurement update (the
        measurement model is not evaluated; the motion model and the bookkeeping run);
        its new state is discarded, so the state after step ``T`` is carried to the end
        unchanged, and its ``StepInfo`` is sliced off. The results are those of the
        unpadded scan for the same key and inputs (the same operations on the same
        values). Trimming the outputs and padding JAX-array inputs compile tiny programs
        per new ``T`` (NumPy inputs are padded in NumPy).

        The particle count is not bucketed: a new ``n`` compiles a new program, because
        padded particles would not reproduce the unpadded filter for the same key. The
        motion model, a proposal and the injector are user callables that draw noise for
        the padded shape; the first ``n`` draws match the unpadded ones only for
        particle-major draws under JAX's partitionable threefry (the default since JAX
        0.5, but a config switch). The plain filter's ``n`` enters as exact constants (the
        threshold ``resample_fraction * n``, the reset ``-log n``, the estimate's
        ``ceil(best_fraction * n)`` particles) that would become a traced count computed
        in the weights' dtype: ``ceil(0.3 * 100)`` is 31 in float32, 30 in Python. And
        KLD-sampling already uses the slots as its maximum particle count.

        Sharding: a state placed by :func:`~lidarjax.localization.shard_state` compiles a
        program for its mesh that measures each shard on its own device and returns a state
        sharded the same way, with bitwise the one-device results.

        Args:
            state: initial state (at least one particle).
            controls: pytree with leading axis ``[T]`` (e.g. ``[T k]`` relative odometry).
                Concrete controls must be finite (checked once, before the scan); traced
                ones with a NaN/inf step are flagged per step (``StepInfo.bad_control``).
            measurements: pytree with leading axis ``[T]`` (e.g. ``[T b]`` ranges).
            updates: optional ``[T]`` bool, measurement update on/off per step.

        Returns:
            The final state and the stacked ``[T]`` :class:`StepInfo`.

        Raises:
            ValueError: ``state`` has no particles, a concrete control is NaN/inf (the
                message names ``controls`` and the step), or ``controls``,
                ``measurements`` and ``updates`` do not share a leading ``[T]`` axis.
        """
        _check_particle_count(state.log_weights, "state")
        _check_controls_concrete(controls, "controls", per_step=True)
        n_steps = _steps_of("controls", controls, None)
        _steps_of("measurements", measurements, n_steps)
        if updates is None:
            updates = np.ones(n_steps, bool)
        elif not isinstance(updates, jax.Array):
            updates = np.asarray(updates)
        _steps_of("updates", updates, n_steps)
        n_pad = step_bucket(n_steps) - n_steps
        padded = _pad_steps((controls, measurements, updates), n_pad)
        mesh = _sharding.state_mesh(state)
        final, infos = self._run_padded(state, *padded, np.int32(n_steps), mesh)
        return final, jax.tree.map(lambda x: x[:n_steps], infos)

    @_checks.checked_jit
    def _run_padded(self, state: ParticleState, controls, measurements, updates, n_live, mesh=None):
        """The scan of :meth:`run` over the padded steps; steps ``>= n_live`` (traced) run
        without measurement update and leave the state as it was. ``mesh`` (static): the
        particles' mesh of a sharded state, or None."""
        n_total = jax.tree.leaves(updates)[0].shape[0]
        live = jnp.arange(n_total) < n_live

        def body(s, xs):
            c, z, u, keep = xs
            new, info = self._step(s, c, z, u & keep, mesh)
            return _select_tree(keep, new, s), info

        return _checks.scan(body, state, (controls, measurements, updates, live))

    @_checks.checked_jit
    def _run(self, state: ParticleState, controls, measurements, updates=None):
        """The unpadded scan (one program per ``T``): the reference :meth:`run` matches."""
        n_steps = jax.tree.leaves(controls)[0].shape[0]
        if updates is None:
            updates = jnp.ones(n_steps, bool)

        def body(s, xs):
            c, z, u = xs
            return self.step(s, c, z, u)

        return _checks.scan(body, state, (controls, measurements, updates))
