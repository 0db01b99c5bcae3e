"""PLE+ (dissertation section 10.4.3): :func:`optimize_polylines`.

With the ray-to-segment association of PLE held fixed, Eq. (10.4) is a smooth
least-squares problem in the vertex coordinates; it is solved with optimistix
Levenberg–Marquardt (end vertices move along their ray, ``2(J - I)`` unknowns). Candidates
are accepted exactly, per polyline and per vertex, under the *true* first-intersection
model, so the scan likelihood never decreases and the set of explained rays is unchanged:
``f(PLE) = f(PLE+)``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float, Int

from ..rays import RayBatch
from ..raytrace import _native, cross2, ray_segment
from ._polyline import PolylineExtraction, _Scan, _scan_arrays, _scan_layout
from ._polyline_map import PolylineMap, _first_hits

# --------------------------------------------------------------------------------------
# PLE+
# --------------------------------------------------------------------------------------


class PolylineOptimization(eqx.Module):
    """Result of :func:`optimize_polylines` (leading axes ``[*scans]`` when batched).

    Attributes:
        map: the optimised :class:`PolylineMap` (same topology and slots as the input).
        sse_before_m2: ``Σ d²`` over the explained rays before optimisation (m²).
        sse_after_m2: the same for the returned :attr:`map` (never larger; it is the true
            first-intersection error of exactly the returned vertices).
        moved_fraction: the share of the map's vertices that the last round moved (0: it
            found no move that passes the check, so the search has converged).
        result: the optimistix result code of the last round's solve from the current
            vertices.
        n_steps: solver steps taken over all rounds, restarts included.
    """

    map: PolylineMap
    sse_before_m2: Float[Array, "*scans"]
    sse_after_m2: Float[Array, "*scans"]
    moved_fraction: Float[Array, "*scans"]
    result: optx.RESULTS
    n_steps: Int[Array, "*scans"]


_ANCHOR = 1e-3
PATTERN_M = (0.02, 0.1, 0.3)
"""Default lengths (m) of PLE+'s per-vertex pattern moves."""
RESTART_SIGMA = (0.02, 0.05)
"""Default spreads of PLE+'s random starts, relative to each vertex's range (cycled)."""
# trial fractions of a round's least-squares step, largest first; when none is accepted
# the round keeps its current vertices (no trial of fraction 0: re-projecting the end
# vertices onto their rays need not reproduce the current map to the last bit)
_FRACTIONS = (1.0, 0.5, 0.25, 0.125, 0.0625, 0.03125)


def _true_sse(m: PolylineMap, sc: _Scan):
    t, _ = _first_hits(m, jnp.broadcast_to(sc.origin, sc.dirs.shape), sc.dirs)
    hit = sc.refl & jnp.isfinite(t)
    d2 = jnp.where(hit, (sc.ranges - jnp.where(hit, t, 0.0)) ** 2, 0.0)
    return jnp.sum(d2), hit


def _first_segment(t: Array) -> tuple[Array, Array]:
    """The segment each ray is held on in the surrogate, from ``t`` ``[K S]`` (distance
    along ray ``k`` to segment ``s``, ``inf``: none): ``(index [K], distance [K])``.

    The first hit, where distances within a relative ``1024 eps`` of the nearest count as
    equal and the lowest index among them is taken (``0`` for a ray that hits nothing). A
    ray through a vertex meets both segments there at the same distance up to round-off
    (6e-15 relative at most on the shared logs, float64); a plain ``argmin`` would let
    that round-off pick the segment, and with it the surrogate's minimum, so the search
    would depend on the last bits of the vertices (the native kernel has the same rule).
    """
    tmin = jnp.min(t, axis=1)
    near = t <= (tmin * (1 + 1024 * jnp.finfo(t.dtype).eps))[:, None]
    return jnp.argmax(near, axis=1), tmin


def _predecessors(succ: Array) -> Array:
    """``[n]`` predecessor of each slot from the successor links ``succ`` (``-1``: none)."""
    n = succ.shape[0]
    idx = jnp.arange(n, dtype=jnp.int32)
    return jnp.full(n, -1, jnp.int32).at[jnp.where(succ >= 0, succ, n)].set(idx, mode="drop")


def _component_labels(succ_p: Array, real: Array) -> Array:
    """Label each parameter slot with the smallest slot of its polyline (``[n]``).

    ``succ_p`` is the successor of each slot (``-1``: none). Polylines are paths or
    cycles, so pointer doubling in both directions reaches every slot of a polyline in
    ``ceil(log2 n)`` steps (a static, bounded loop)."""
    n = succ_p.shape[0]
    lab = jnp.where(real, jnp.arange(n, dtype=jnp.int32), n)
    fwd, bwd = succ_p, _predecessors(succ_p)
    for _ in range(max(1, int(np.ceil(np.log2(max(n, 2)))))):
        lab = jnp.minimum(lab, jnp.where(fwd >= 0, lab[jnp.clip(fwd, 0, n - 1)], n))
        lab = jnp.minimum(lab, jnp.where(bwd >= 0, lab[jnp.clip(bwd, 0, n - 1)], n))
        fwd = jnp.where(fwd >= 0, fwd[jnp.clip(fwd, 0, n - 1)], -1)
        bwd = jnp.where(bwd >= 0, bwd[jnp.clip(bwd, 0, n - 1)], -1)
    return jnp.where(real, lab, 0)


def _restart_draws(key0: Array, i_round: Array, restarts: int, n_params: int, dtype) -> Array:
    """``[restarts n_params 2]`` standard Gaussian draws of round ``i_round`` (uint32): the
    random starts of both backends (the native kernel takes them as an input)."""
    return jax.random.normal(jax.random.fold_in(key0, i_round), (restarts, n_params, 2), dtype)


@dataclasses.dataclass(frozen=True)
class _PlusSettings:
    """PLE+'s static settings (see :func:`optimize_polylines`)."""

    max_steps: int
    rounds: int
    restarts: int
    restart_sigma: tuple[float, ...]
    pattern_m: tuple[float, ...]
    seed: int


def _plus_one(m: PolylineMap, sc: _Scan, solver, n_params: int, cfg: _PlusSettings):
    max_steps, rounds, restarts = cfg.max_steps, cfg.rounds, cfg.restarts
    restart_sigma, pattern_m, seed = cfg.restart_sigma, cfg.pattern_m, cfg.seed
    k = m.vertices.shape[0]
    act = m.active
    succ = jnp.where(act, m.successor, -1)
    is_end = act & ((succ < 0) | (_predecessors(succ) < 0))
    # compact the active slots into n_params parameter slots (static shape, padded)
    slot = jnp.nonzero(act, size=n_params, fill_value=0)[0]
    real = jnp.arange(n_params) < jnp.sum(act)
    param_of = (
        jnp.zeros(k, jnp.int32)
        .at[jnp.where(real, slot, k)]
        .set(jnp.arange(n_params, dtype=jnp.int32), mode="drop")
    )
    end_p = is_end[slot] & real
    dir_p = sc.dirs[slot]
    # the compacted segments: parameter p -> its successor's parameter (-1: none)
    succ_p = jnp.where(real & (succ[slot] >= 0), param_of[jnp.clip(succ[slot], 0, k - 1)], -1)
    seg_ok = succ_p >= 0
    # the polyline of each parameter slot: the blocks whose steps are accepted separately
    pred_p = _predecessors(succ_p)
    nxt = jnp.clip(succ_p, 0, n_params - 1)
    block = _component_labels(succ_p, real)
    origins = jnp.broadcast_to(sc.origin, sc.dirs.shape)

    def seg_t(a, b):
        """``[K S]``: distance along each ray to each segment ``a -> b`` (``inf``: none)."""
        t = jax.vmap(jax.vmap(ray_segment, in_axes=(None, None, 0, 0)), in_axes=(0, 0, None, None))(
            origins, sc.dirs, a, b
        )
        return jnp.where(seg_ok[None, :], t, jnp.inf)

    def positions(y):
        # end vertices move along the ray of their slot: vertex = origin + t * dir
        xy, t_end = y
        return jnp.where(end_p[:, None], sc.origin + t_end[:, None] * dir_p, xy)

    def residuals(y, args):
        pa, pb, use, p_start = args
        p = positions(y)
        a, b = p[pa], p[pb]
        e = b - a
        den = cross2(sc.dirs, e)
        ok = use & (jnp.abs(den) > 1e-12)
        rhat = cross2(a - sc.origin, e) / jnp.where(ok, den, 1.0)
        # a weak anchor (1e-3 per m moved: 1e-6 m² per m² in the objective) keeps the
        # directions that leave Σ d² unchanged (a vertex sliding along a straight wall)
        # determined
        anchor = _ANCHOR * jnp.where(real[:, None], p - p_start, 0.0).reshape(-1)
        return jnp.concatenate([jnp.where(ok, sc.ranges - rhat, 0.0), anchor])

    def block_hits(p):
        """``[K B]``: per ray, the distance to the nearest segment of each polyline
        (``inf``: none), for the parameter positions ``p`` ``[n_params 2]``."""
        t = seg_t(p, p[nxt])  # [K S]
        return jax.ops.segment_min(t.T, block, num_segments=n_params).T, t

    def error_of(t):
        hit = sc.refl & jnp.isfinite(t)
        return jnp.sum(jnp.where(hit, (sc.ranges - jnp.where(hit, t, 0.0)) ** 2, 0.0)), hit

    sse0, hit0 = _true_sse(m, sc)
    fracs = jnp.asarray(_FRACTIONS, m.vertices.dtype)

    def solve_from(p_start):
        """LM from ``p_start`` ``[S 2]`` (end vertices projected onto their rays), the
        rays held on the segments they hit first there; returns the start as projected
        and the solution, both ``[S 2]``, and the solver statistics."""
        _, t_seg_s = block_hits(p_start)
        s_first, t_first = _first_segment(t_seg_s)
        use = sc.refl & jnp.isfinite(t_first)
        pa, pb = s_first, jnp.clip(succ_p[s_first], 0, n_params - 1)
        y0 = (p_start, jnp.einsum("jd,jd->j", p_start - sc.origin, dir_p))
        p0 = positions(y0)
        sol = optx.least_squares(
            residuals, solver, y0, args=(pa, pb, use, p0), max_steps=max_steps, throw=False
        )
        p_sol = jnp.where(real[:, None], positions(sol.value), p0)
        return p0, p_sol, sol.stats["num_steps"], sol.result

    key0 = jax.random.PRNGKey(seed)

    def one_round(carry, i_round):
        verts, sse_cur, n_steps, _ = carry
        pc = verts[slot]  # current positions of the parameters
        mb0, t_seg = block_hits(pc)  # [K B], [K S]
        p0, p_lm, steps_lm, result = solve_from(pc)
        step = p_lm - p0
        p_tr = p0[None] + fracs[:, None, None] * step[None]  # [F S 2]
        if restarts:
            # restarts: LM from the current vertices moved at random (Gaussian, sigma
            # restart_sigma x the vertex's range; end vertices along their ray), whose
            # solutions are offered polyline by polyline like the step fractions: a way
            # out of a local minimum of Eq. (10.4), as the paper's Nelder-Mead simplex
            # (5 % of each coordinate) finds one
            z = _restart_draws(key0, i_round, restarts, n_params, pc.dtype)
            rng_c = jnp.linalg.norm(pc - sc.origin, axis=-1)
            t_c0 = jnp.einsum("jd,jd->j", pc - sc.origin, dir_p)
            # the spreads cycle over the restarts
            sig = jnp.asarray(
                [restart_sigma[i % len(restart_sigma)] for i in range(restarts)], pc.dtype
            )[:, None]  # [R 1]
            ps = pc[None] + (sig * rng_c[None])[..., None] * z
            ps = jnp.where(
                end_p[None, :, None],
                sc.origin + (t_c0[None] + sig * rng_c[None] * z[..., 0])[..., None] * dir_p[None],
                ps,
            )
            _, p_rs, steps_rs, _ = jax.vmap(solve_from)(ps)
            p_chain = jnp.concatenate([p_tr, p_rs], axis=0)  # [F+R S 2]
            n_steps = n_steps + jnp.sum(steps_rs).astype(n_steps.dtype)
        else:
            p_chain = p_tr
        mbf = jax.vmap(lambda p: block_hits(p)[0])(p_chain)  # [F+R K B]
        finite_tr = jax.vmap(
            lambda p: (
                jax.ops.segment_min(
                    jnp.where(jnp.all(jnp.isfinite(p), 1), 0, 1), block, num_segments=n_params
                )
                == 0
            )
        )(p_chain)  # [F+R B]
        # the exact error with one polyline b moved by fraction f, all others as they are:
        # per ray the nearest of (the other polylines now, polyline b moved)
        order = jnp.argsort(mb0, axis=1)
        first, second = order[:, 0], order[:, 1]  # n_params >= 8
        t1 = jnp.take_along_axis(mb0, first[:, None], 1)[:, 0]
        t2 = jnp.take_along_axis(mb0, second[:, None], 1)[:, 0]
        bidx = jnp.arange(n_params)
        others = jnp.where(first[:, None] == bidx[None, :], t2[:, None], t1[:, None])  # [K B]
        t_single = jnp.minimum(others[None], mbf)  # [F K B]
        sse_s, hit_s = jax.vmap(jax.vmap(error_of, in_axes=1, out_axes=0), in_axes=0)(t_single)
        # sse_s [F B], hit_s [F B K]
        ok_s = jnp.all(hit_s == hit0[None, None, :], axis=-1) & (sse_s <= sse_cur) & finite_tr
        has = jnp.any(ok_s, axis=0)  # [B]
        f_idx = jnp.argmin(jnp.where(ok_s, sse_s, jnp.inf), axis=0)  # best trial per polyline
        # all polylines at their own accepted fraction (unaccepted ones unchanged): exact
        # error from the per-polyline distances of each one's own choice
        stack = jnp.concatenate([mb0[None], mbf], axis=0)  # [F+1 K B]
        choice = jnp.where(has, f_idx + 1, 0)  # [B]
        t_comb = jnp.min(jnp.take_along_axis(stack, choice[None, None, :], axis=0)[0], axis=1)
        sse_c, hit_c = error_of(t_comb)
        ok_c = jnp.all(hit_c == hit0) & (sse_c <= sse_cur) & jnp.any(has)
        # per vertex: vertex v moved by fraction f, all others as they are. Only its two
        # segments change: (pred v -> v) with its end moved, (v -> succ v) with its start
        # moved; the rest is the nearest of the unchanged segments other than those two.
        # per-vertex trials: the LM step fractions, then pattern moves of fixed lengths
        # along the vertex's ray and across it (end vertices: along their ray only), which
        # let a vertex leave a local minimum of the fixed-association surrogate
        t_c = jnp.einsum("jd,jd->j", pc - sc.origin, dir_p)
        perp = jnp.stack([-dir_p[:, 1], dir_p[:, 0]], -1)
        pats = []
        for length in pattern_m:
            for sign in (1.0, -1.0):
                along = jnp.where(
                    end_p[:, None],
                    sc.origin + (t_c + sign * length)[:, None] * dir_p,
                    pc + sign * length * dir_p,
                )
                across = jnp.where(end_p[:, None], pc, pc + sign * length * perp)
                pats += [along, across]
        p_all = jnp.concatenate([p_tr, jnp.stack(pats)], axis=0) if pats else p_tr  # [T S 2]
        moves = jnp.any(p_all != pc[None], axis=-1)  # [T V]
        t_end = jax.vmap(lambda p: seg_t(pc, p[nxt]))(p_all)  # [T K S]: end of s moved
        t_start = jax.vmap(lambda p: seg_t(p, pc[nxt]))(p_all)  # [T K S]: start of s moved
        n3 = min(3, n_params)
        top = jnp.argsort(t_seg, axis=1)[:, :n3]  # [K 3] nearest unchanged segments
        t_top = jnp.take_along_axis(t_seg, top, 1)
        pidx = jnp.arange(n_params)
        drop = (top[:, None, :] == pidx[None, :, None]) | (
            (top[:, None, :] == pred_p[None, :, None]) & (pred_p[None, :, None] >= 0)
        )  # [K V 3]: the two segments of vertex v (at most 2 of the 3 nearest)
        rest = jnp.min(jnp.where(drop, jnp.inf, t_top[:, None, :]), axis=-1)  # [K V]
        t_in = jnp.where(
            (pred_p >= 0)[None, None, :],
            jnp.take(t_end, jnp.clip(pred_p, 0, n_params - 1), axis=2),
            jnp.inf,
        )  # [T K V]
        t_v = jnp.minimum(jnp.minimum(rest[None], t_in), t_start)  # [T K V]
        sse_v, hit_v = jax.vmap(jax.vmap(error_of, in_axes=1, out_axes=0), in_axes=0)(t_v)
        ok_v = (
            jnp.all(hit_v == hit0[None, None, :], axis=-1)
            & (sse_v <= sse_cur)
            & jnp.all(jnp.isfinite(p_all), axis=-1)
            & real[None, :]
            & moves
        )  # [T V]
        err_v = jnp.where(ok_v, sse_v, jnp.inf)
        has_v = jnp.any(ok_v, axis=0)
        tv_idx = jnp.argmin(err_v, axis=0)  # each vertex's best trial
        p_vc = jnp.where(has_v[:, None], p_all[tv_idx, pidx], pc)
        _, t_seg_vc = block_hits(p_vc)
        sse_vc, hit_vc = error_of(jnp.min(t_seg_vc, axis=1))
        ok_vc = jnp.all(hit_vc == hit0) & (sse_vc <= sse_cur) & jnp.any(has_v)

        # candidates, all with their exact error: every polyline at its own fraction,
        # every vertex at its own best trial, the best single polyline, the best single
        # vertex; the lowest error among those that pass wins (none: keep the vertices)
        gain = jnp.where(ok_s, sse_s, jnp.inf)
        fb, bb = jnp.unravel_index(jnp.argmin(gain), gain.shape)
        tvb, vb = jnp.unravel_index(jnp.argmin(err_v), err_v.shape)
        cand_sse = jnp.stack(
            [
                jnp.where(ok_c, sse_c, jnp.inf),
                jnp.where(ok_vc, sse_vc, jnp.inf),
                jnp.where(ok_s[fb, bb], sse_s[fb, bb], jnp.inf),
                jnp.where(ok_v[tvb, vb], sse_v[tvb, vb], jnp.inf),
            ]
        )
        cand_p = jnp.stack(
            [
                jnp.where(has[block][:, None], p_chain[f_idx[block], pidx], pc),
                p_vc,
                jnp.where((block == bb)[:, None], p_chain[fb], pc),
                jnp.where((pidx == vb)[:, None], p_all[tvb], pc),
            ]
        )
        best = jnp.argmin(cand_sse)
        accept = jnp.isfinite(cand_sse[best])
        p_new = jnp.where(accept & real[:, None], cand_p[best], pc)
        vv = verts.at[jnp.where(real, slot, k)].set(p_new, mode="drop")
        sse_new = jnp.where(accept, cand_sse[best], sse_cur)
        frac = jnp.sum(jnp.any(p_new != pc, axis=-1) & real) / jnp.maximum(jnp.sum(real), 1)
        carry = (vv, sse_new, n_steps + steps_lm, frac)
        return carry, result

    init = (m.vertices, sse0, jnp.zeros((), jnp.int32), jnp.ones((), m.vertices.dtype))
    (verts, sse, n_steps, frac), results = jax.lax.scan(
        one_round, init, jnp.arange(rounds, dtype=jnp.uint32)
    )
    out = PolylineMap(verts, m.successor, m.active)
    return out, sse0, sse, frac, jax.tree.map(lambda x: x[-1], results), n_steps


@eqx.filter_jit
def _optimize(m: PolylineMap, sc: _Scan, solver, n_params: int, cfg: _PlusSettings):
    def f(mm, s):
        return _plus_one(mm, s, solver, n_params, cfg)

    for _ in range(sc.ranges.ndim - 1):
        f = jax.vmap(f)
    return f(m, sc)


def _results_of(codes: Array) -> optx.RESULTS:
    """``optx.RESULTS`` of the shape of ``codes`` (0: successful, else max steps reached,
    the code the JAX path's solve reports when it runs out of steps)."""
    r = jax.vmap(
        lambda c: optx.RESULTS.where(
            c == 0, optx.RESULTS.successful, optx.RESULTS.nonlinear_max_steps_reached
        )
    )(codes.reshape(-1))
    return jax.tree.map(lambda x: x.reshape(codes.shape), r)


@eqx.filter_jit
def _optimize_native(m: PolylineMap, sc: _Scan, n_params: int, cfg: _PlusSettings, fma: int = -1):
    """:func:`_optimize` by the C++ kernel ``csrc/polyline_plus.cc`` (one FFI call for the
    whole batch; the scans run one after the other on the calling thread). ``fma``: -1
    contract multiply-adds as XLA does on this CPU (FMA if it has it), 0 never, 1 always
    (for experiments: only -1 reproduces the JAX path's distances bit for bit)."""
    if not _native._load():  # registers the FFI targets
        raise RuntimeError(f"the native PLE+ kernel is unavailable: {_native.unavailable_reason()}")
    dtype = m.vertices.dtype
    batch, k = sc.ranges.shape[:-1], sc.ranges.shape[-1]
    n = math.prod(batch)
    key0 = jax.random.PRNGKey(cfg.seed)
    z = jax.vmap(lambda i: _restart_draws(key0, i, cfg.restarts, n_params, dtype))(
        jnp.arange(cfg.rounds, dtype=jnp.uint32)
    )  # [rounds R n_params 2]: the JAX path's draws
    sig = jnp.asarray(
        [cfg.restart_sigma[i % len(cfg.restart_sigma)] for i in range(cfg.restarts)], dtype
    ).reshape(cfg.restarts)
    pat = jnp.asarray(cfg.pattern_m, dtype).reshape(len(cfg.pattern_m))
    f = jax.ShapeDtypeStruct((n,), dtype)
    i32 = jax.ShapeDtypeStruct((n,), jnp.int32)
    call = jax.ffi.ffi_call(
        f"lidarjax_polyline_plus_{_native._dt(dtype)}",
        (jax.ShapeDtypeStruct((n, k, 2), dtype), f, f, f, i32, i32),
        vmap_method="sequential",
    )
    verts, sse0, sse1, frac, codes, steps = call(
        m.vertices.reshape(n, k, 2),
        m.successor.reshape(n, k).astype(jnp.int32),
        m.active.reshape(n, k),
        sc.origin.reshape(n, 2).astype(dtype),
        sc.dirs.reshape(n, k, 2).astype(dtype),
        sc.ranges.reshape(n, k).astype(dtype),
        sc.refl.reshape(n, k),
        z,
        sig,
        pat,
        max_steps=np.int64(cfg.max_steps),
        rounds=np.int64(cfg.rounds),
        n_params=np.int64(n_params),
        fma=np.int64(fma),
    )
    out = PolylineMap(verts.reshape(m.vertices.shape), m.successor, m.active)
    return (
        out,
        sse0.reshape(batch),
        sse1.reshape(batch),
        frac.reshape(batch),
        _results_of(codes.reshape(batch)),
        steps.reshape(batch),
    )


def _use_native(backend: str, default_solver: bool, arrays: Sequence[Array]) -> bool:
    """Whether :func:`optimize_polylines` runs the C++ kernel (see its ``backend``)."""
    _native.check_backend(backend)
    if backend == "jax":
        return False
    traced = any(isinstance(x, jax.core.Tracer) for x in arrays)
    cpu = all(d.platform == "cpu" for x in arrays if hasattr(x, "devices") for d in x.devices())
    if backend == "native":
        if not default_solver:
            raise ValueError(
                "backend='native' runs PLE+'s own Levenberg–Marquardt (the default solver); "
                "pass solver=None or backend='jax' for a custom solver"
            )
        if traced:
            raise ValueError("backend='native' needs concrete inputs (not under jit/vmap/grad)")
        _native.resolve("native")  # RuntimeError when the library is unavailable
        if not cpu:
            raise RuntimeError("backend='native' requested but the inputs are not on a CPU")
        return True
    if not default_solver or traced or not cpu:
        return False
    return _native.resolve("auto") == "native"


def default_plus_solver() -> optx.LevenbergMarquardt:
    """PLE+'s default solver: Levenberg–Marquardt (``rtol`` 1e-6, ``atol`` 1e-9) whose
    damped steps solve the normal equations by Cholesky.

    On the CPU, XLA's QR (optimistix's default for LM) of a ``[K + 3J, 3J]`` system took
    about 0.4 s per step here, against under 1 ms for Cholesky of the ``3J x 3J`` normal
    equations, which are well conditioned because the damping adds ``λ I``.
    """
    return optx.LevenbergMarquardt(rtol=1e-6, atol=1e-9, linear_solver=lx.Normal(lx.Cholesky()))


def optimize_polylines(
    extraction: PolylineExtraction | PolylineMap,
    rays: RayBatch,
    *,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 10,
    rounds: int = 5,
    restarts: int = 0,
    restart_sigma: float | Sequence[float] = RESTART_SIGMA,
    pattern_m: Sequence[float] = PATTERN_M,
    seed: int = 0,
    backend: str = "auto",
) -> PolylineOptimization:
    """PLE+: move the vertices to maximise the scan likelihood (Eq. 10.4, section 10.4.3).

    With each reflected ray held on the segment it hits first (the ray-to-segment
    association; a ray through a vertex, which meets both of its segments at the same
    distance up to round-off, is held on the one of the lower vertex slot), its residual
    ``r_k - r̂_k`` measured to that segment's line makes Eq. (10.4) a smooth
    least-squares problem, solved with ``solver`` (default
    :func:`default_plus_solver`: Levenberg–Marquardt). Interior vertices move freely; the
    first and last vertex of an open polyline move along the axis of their own ray
    (``2(J - I)`` unknowns for ``I`` open polylines). A weak anchor term
    (``1e-6 |Δv|²``) keeps directions that do not change ``Σ d²`` determined.

    The search runs for ``rounds`` rounds. Each round re-associates the rays with the
    current map and solves from the current vertices and, with ``restarts`` > 0, from
    random starts
    (each vertex moved by a Gaussian of ``restart_sigma`` times its range, 2 % and 5 % in
    turn; end vertices along their ray), as the paper's Nelder–Mead simplex (5 % of each
    coordinate) escapes
    the local minima that a descent from PLE's vertices stops in. The candidate moves are
    then checked with the true first-intersection model, each exactly:

    - per polyline: the fractions ``(1, 1/2, ..., 1/32)`` of the step from the current
      vertices, and the restart solutions, with all other polylines as they are;
    - per vertex: the same step fractions and pattern moves of ``pattern_m`` metres along
      and across its ray (end vertices: along it), with all other vertices as they are;
    - every polyline (every vertex) at its own best move, checked again as a whole, since
      polylines interact through occlusion.

    A move qualifies if it keeps exactly the explained rays of the input explained and
    does not raise ``Σ d²``; the qualifying candidate of least error is taken, and if
    none qualifies the round keeps its vertices. So the returned map is the input or one
    that passed this check: the likelihood never decreases, ``f`` is unchanged and
    ``sse_after_m2`` is the true error of the returned vertices (the fixed association
    alone lets a line run past a corner, which lowers the surrogate but raises the true
    error). The random starts come from ``seed`` and the round: results are
    deterministic. Batched over ``[*scans]``.

    Backends: ``"jax"`` is the pure-JAX search (optimistix ``solver``, ``vmap`` over the
    scans), the oracle. ``"native"`` is the same search as one C++ kernel through the XLA
    FFI (``lidarjax/raytrace/csrc/polyline_plus.cc``) that runs the scans one after the
    other on the calling thread: the same association, candidates, exact checks (distances
    bit for bit those of the JAX path) and random starts (drawn by JAX), with its own
    Levenberg–Marquardt written after optimistix's (same damping schedule, trust-region
    update and termination; Cholesky of the damped normal equations). Per solve step the
    two agree to round-off; converged solves agree to the resolution of the termination
    test (errors within 1e-4 relative); with the defaults the errors agree to 1e-8 on the
    shared logs. ``moved_fraction`` may count vertices moved by round-off differently. The
    kernel exists because the JAX path hands every loop iteration between XLA's pool
    threads, which other busy processes turn into waits: one 180-ray intel scan at J = 50
    (defaults) took 0.16 s idle and 1.2 s median, 3.3 s max, with two busy loops on 2
    cores (5.8 s median on a busier day), against 14 ms idle and 34 ms (max 60 ms) loaded
    for the kernel (``benchmarks/ple_plus_contention.py``); ``rounds=10, restarts=4``:
    1.0 s against 57 ms idle. ``"auto"`` (default) runs the kernel when the native
    library is built, the inputs live on a CPU, ``solver`` is the default (``None`` or
    equal to :func:`default_plus_solver`) and the inputs are concrete (not traced); else
    the JAX path (``LIDARJAX_BACKEND`` overrides as for the ray kernels).

    Args:
        extraction: a :class:`PolylineExtraction` (or its map) of these rays, in the PLE
            layout (vertex slot ``k`` = endpoint of ray ``k``).
        rays: the ``[*scans K]`` rays the map was extracted from.
        solver: an optimistix least-squares solver.
        max_steps: solver step budget per solve.
        rounds: association / solve / check rounds.
        restarts: random starts solved per round. The default 0 is the descent from the
            current vertices alone: 0.11 s per 180-ray scan at J = 50 on one core, and
            the least exposed to XLA thread contention. ``rounds=10, restarts=4`` (what
            ``experiments/polylines.py`` uses) reaches the paper's Nelder–Mead optima,
            at about 6x the time.
        restart_sigma: spread of the random starts, relative to each vertex's range; a
            sequence is cycled over the restarts (default 2 % and 5 %).
        pattern_m: lengths (m) of the per-vertex pattern moves (empty: none).
        seed: seed of the random starts.
        backend: ``"auto"``, ``"native"`` or ``"jax"`` (see above).

    Returns:
        A :class:`PolylineOptimization`.

    Raises:
        ValueError: a bad ``extraction``, ``rays`` not in its layout, or a count or spread
            out of range (``max_steps``, ``rounds`` >= 1; ``restarts`` >= 0;
            ``restart_sigma`` and every ``pattern_m`` finite and > 0); an unknown
            ``backend``, or ``backend="native"`` with a custom ``solver``.
        RuntimeError: ``backend="native"`` but the native library is unavailable or the
            inputs are not on a CPU.
    """
    m = extraction.map if isinstance(extraction, PolylineExtraction) else extraction
    if not isinstance(m, PolylineMap):
        raise ValueError(
            f"extraction must be a PolylineExtraction or PolylineMap, got {type(m).__name__}"
        )
    _scan_layout(rays)
    if m.vertices.shape[:-1] != rays.shape:
        raise ValueError(
            f"the map has vertex slots {m.vertices.shape[:-1]} but rays have shape "
            f"{rays.shape}; PLE+ needs the PLE layout (one slot per ray)"
        )
    if int(max_steps) < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    if int(rounds) < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    if int(restarts) < 0:
        raise ValueError(f"restarts must be >= 0, got {restarts}")
    restart_sigma = tuple(
        float(x) for x in (restart_sigma if np.ndim(restart_sigma) else [restart_sigma])
    )
    if not restart_sigma or not all(np.isfinite(x) and x > 0 for x in restart_sigma):
        raise ValueError(
            f"restart_sigma must be finite and > 0 (one or several), got {restart_sigma}"
        )
    pattern_m = tuple(float(x) for x in pattern_m)
    if not all(np.isfinite(x) and x > 0 for x in pattern_m):
        raise ValueError(f"pattern_m must hold finite lengths > 0 (m), got {pattern_m}")
    _native.check_backend(backend)
    default_solver = solver is None or eqx.tree_equal(solver, default_plus_solver()) is True
    native = _use_native(
        backend, default_solver, jax.tree.leaves((m, rays.origins, rays.directions, rays.ranges))
    )
    if solver is None:
        solver = default_plus_solver()
    n_active = int(jnp.max(m.n_vertices)) if m.active.size else 0
    n_params = max(8, -(-n_active // 8) * 8)  # bucket to limit recompiles
    cfg = _PlusSettings(
        int(max_steps), int(rounds), int(restarts), restart_sigma, pattern_m, int(seed)
    )
    if native:
        out, s0, s1, frac, res, steps = _optimize_native(m, _scan_arrays(rays), n_params, cfg)
    else:
        out, s0, s1, frac, res, steps = _optimize(m, _scan_arrays(rays), solver, n_params, cfg)
    return PolylineOptimization(out, s0, s1, frac, res, steps)
