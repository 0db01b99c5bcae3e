"""Maximum-likelihood polyline extraction from 2-D scans: PLE (dissertation ch. 10).

- :func:`extract_polylines` (PLE, Algorithm 1): connect neighbouring endpoints, then
  greedily remove the vertex of least error ``e_j`` (Eq. 10.3) until a stopping criterion
  holds. The greedy loop is one ``lax.while_loop``; the errors live in an indexed
  priority queue (a min tournament tree over the vertex slots: ``O(1)`` find-min,
  ``O(log n)`` key update), and each step recomputes only the errors the removal touched.
  The error terms are batched ray–segment computations over the scan's rays.
- Stopping criteria are pluggable (:class:`MaxVertices`, :class:`MaxRMSE`, :class:`AIC`, or
  any :class:`AbstractStoppingCriterion`).
- The map type is :class:`~lidarjax.features.PolylineMap` (``_polyline_map.py``); PLE+
  (:func:`~lidarjax.features.optimize_polylines`) is in ``_polyline_plus.py``.

Scans are :class:`~lidarjax.rays.RayBatch` es of shape ``[*scans, K]`` whose rays share an
origin per scan and are ordered counter-clockwise (increasing azimuth), as every 2-D lidar
delivers them. Only HIT rays are reflected; SUB and SUP rays are never connected. As in the
paper's experiments the radial variance is constant, so it drops out of Eqs. (10.3)/(10.4):
errors are in m².
"""

from __future__ import annotations

import abc
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..rays import HIT, RayBatch, is_concrete
from ..raytrace import cross2
from ._polyline_map import PolylineMap

# --------------------------------------------------------------------------------------
# Stopping criteria
# --------------------------------------------------------------------------------------


class PolylineStats(eqx.Module):
    """Summary of a polyline map against its scan.

    Attributes:
        n_vertices: number of vertices ``J``.
        n_polylines: number of polylines ``I``.
        sse_m2: ``Σ_k d²(z_k, L)`` over reflected rays, with ``d_rm`` standing in for rays
            the map does not explain (the objective of Eq. 10.3), m².
        sse_explained_m2: the same sum over explained rays only, m².
        n_explained: reflected rays that intersect the map.
        n_reflected: reflected (HIT) rays.
    """

    n_vertices: Int[Array, "*batch"]
    n_polylines: Int[Array, "*batch"]
    sse_m2: Float[Array, "*batch"]
    sse_explained_m2: Float[Array, "*batch"]
    n_explained: Int[Array, "*batch"]
    n_reflected: Int[Array, "*batch"]

    @property
    def rmse_m(self) -> Float[Array, "*batch"]:
        """RMSE of the ray radii over explained rays (section 10.5), m; ``inf`` if none."""
        n = self.n_explained
        return jnp.where(n > 0, jnp.sqrt(self.sse_explained_m2 / jnp.maximum(n, 1)), jnp.inf)


class AbstractStoppingCriterion(eqx.Module):
    """Decides whether PLE may perform the next (cheapest) removal.

    Subclasses implement :meth:`allows`; PLE stops as soon as any of its criteria refuses.
    """

    @abc.abstractmethod
    def allows(self, before: PolylineStats, after: PolylineStats) -> Bool[Array, ""]:
        """Whether to go from the map summarised by ``before`` to the one by ``after``."""


class MaxVertices(AbstractStoppingCriterion):
    """Remove vertices while the map has more than ``n`` (the paper's ``J_max``)."""

    n: Int[Array, ""] = eqx.field(converter=lambda x: jnp.asarray(x, jnp.int32))

    def __check_init__(self):
        if is_concrete(self.n) and int(self.n) < 2:
            raise ValueError(f"MaxVertices.n must be >= 2, got {self.n}")

    def allows(self, before, after):
        return before.n_vertices > self.n


class MaxRMSE(AbstractStoppingCriterion):
    """Remove vertices while the RMSE of the ray radii stays at most ``rmse_m`` (m)."""

    rmse_m: Float[Array, ""] = eqx.field(converter=jnp.asarray)

    def allows(self, before, after):
        return after.rmse_m <= self.rmse_m


class AIC(AbstractStoppingCriterion):
    """Akaike information criterion with known radial noise ``sigma_m`` (m): remove while
    ``AIC = 2 * 2J + Σ d² / σ²`` does not increase (two parameters per vertex)."""

    sigma_m: Float[Array, ""] = eqx.field(default=0.03, converter=jnp.asarray)

    def allows(self, before, after):
        def aic(s):
            return 4.0 * s.n_vertices + s.sse_m2 / self.sigma_m**2

        return aic(after) <= aic(before)


# --------------------------------------------------------------------------------------
# PLE
# --------------------------------------------------------------------------------------


class PolylineExtraction(eqx.Module):
    """Result of :func:`extract_polylines` (leading axes ``[*scans]`` when batched).

    Vertex slot ``k`` of :attr:`map` is the endpoint of ray ``k``.

    Attributes:
        map: the extracted :class:`PolylineMap` (``[*scans K]`` slots).
        stats: :class:`PolylineStats` of the final map.
        initial_stats: :class:`PolylineStats` of the initial map (Algorithm 1, lines 1–10).
        removal_order: ``[*scans K]`` ray indices in the order their vertices were removed,
            padded with ``-1`` (removing a two-vertex polyline removes both, consecutively).
        removal_error: ``[*scans K]`` the error ``e_j`` (m²) of each removal in that order
            (``inf`` padding).
        n_steps: number of removal steps performed.
        d_rm_m: the end-vertex placeholder distance used (m).
    """

    map: PolylineMap
    stats: PolylineStats
    initial_stats: PolylineStats
    removal_order: Int[Array, "*scans K"]
    removal_error: Float[Array, "*scans K"]
    n_steps: Int[Array, "*scans"]
    d_rm_m: Float[Array, ""]


class _State(eqx.Module):
    prev: Array
    next: Array
    alive: Array
    cur: Array  # current squared residual per ray (d_rm² if reflected and unexplained)
    explained: Array
    err: Array
    tree_val: tuple[Array, ...]
    tree_idx: tuple[Array, ...]
    order: Array
    order_err: Array
    n_removed: Array
    steps: Array
    done: Array
    stats: PolylineStats


class _Scan(eqx.Module):
    origin: Array  # [2]
    dirs: Array  # [K 2]
    ranges: Array  # [K]
    refl: Array  # [K]
    ends: Array  # [K 2]


def _fwd(a, b, k):
    """Forward index distance from ``a`` to ``b`` in a (cyclic) scan of ``k`` rays."""
    return jnp.mod(b - a, k)


def _candidate(sc: _Scan, st: _State, j, d_rm2):
    """Error of removing vertex ``j`` (Eq. 10.3) and what the removal does to the rays.

    Returns ``(e, mask, new_cur, lose)``: ``e`` (inf if not removable), the rays whose
    residual changes, their new squared residuals and whether they stop being explained.
    """
    k = sc.ranges.shape[0]
    idx = jnp.arange(k)
    jj = jnp.clip(j, 0, k - 1)
    p, n = st.prev[jj], st.next[jj]
    ps, ns = jnp.clip(p, 0, k - 1), jnp.clip(n, 0, k - 1)
    interior = (p >= 0) & (n >= 0)
    # interior vertex: rays strictly between p and n now hit the chord p-n
    fp = _fwd(ps, idx, k)
    in_int = (fp > 0) & (fp < _fwd(ps, ns, k))
    a = sc.ends[ps] - sc.origin
    e_vec = sc.ends[ns] - sc.ends[ps]
    den = cross2(sc.dirs, e_vec)
    good = den > 0
    rhat = cross2(a, e_vec) / jnp.where(good, den, 1.0)
    new_int = jnp.where(good, (sc.ranges - rhat) ** 2, jnp.inf)
    span_ok = cross2(sc.dirs[ps], sc.dirs[ns]) > 0
    not_triangle = st.next[ns] != ps
    # end vertex: the rays between it and its neighbour lose their segment
    start_end = (p < 0) & (n >= 0)
    last_end = (n < 0) & (p >= 0)
    pair = jnp.where(start_end, st.next[ns] < 0, st.prev[ps] < 0)
    fj = _fwd(jj, idx, k)
    in_start = jnp.where(pair, fj <= _fwd(jj, ns, k), fj < _fwd(jj, ns, k))
    in_last = jnp.where(pair, fp <= _fwd(ps, jj, k), (fp > 0) & (fp <= _fwd(ps, jj, k)))
    mask = jnp.where(interior, in_int, jnp.where(start_end, in_start, in_last & last_end))
    new_cur = jnp.where(interior, new_int, d_rm2)
    e = jnp.sum(jnp.where(mask, new_cur - st.cur, 0.0))
    ok = (j >= 0) & st.alive[jj] & (interior | start_end | last_end)
    ok = ok & jnp.where(interior, span_ok & not_triangle, True)
    ok = ok & ~jnp.any(mask & ~jnp.isfinite(new_cur))
    return jnp.where(ok, e, jnp.inf), mask, new_cur, ~interior


_FANOUT = 8  # children per node of the tournament tree


def _tree_build(err: Array, levels: int):
    """An indexed min tournament tree over ``err``: a ``_FANOUT``-ary tree of ``levels``
    levels above the (padded) leaves. Each node holds the minimum of its subtree and the
    leaf index where it sits (the lowest index on ties). Returns ``(values, indices)``,
    tuples of per-level arrays from the root (size 1) to the leaves."""
    size = _FANOUT**levels
    v = jnp.full(size, jnp.inf, err.dtype).at[: err.shape[0]].set(err)
    i = jnp.arange(size, dtype=jnp.int32)
    vals, idxs = [v], [i]
    for _ in range(levels):
        v2 = vals[-1].reshape(-1, _FANOUT)
        a = jnp.argmin(v2, axis=1)  # first minimum: the lowest leaf index wins ties
        vals.append(jnp.take_along_axis(v2, a[:, None], 1)[:, 0])
        idxs.append(jnp.take_along_axis(idxs[-1].reshape(-1, _FANOUT), a[:, None], 1)[:, 0])
    return tuple(vals[::-1]), tuple(idxs[::-1])


def _tree_update(tv, ti, err, leaves):
    """Set the given leaves to ``err[leaves]`` and repair their root paths:
    ``O(_FANOUT * log n)`` per leaf, all leaves at once."""
    k = err.shape[0]
    leaves = jnp.clip(leaves, 0, k - 1)
    tv, ti = list(tv), list(ti)
    tv[-1] = tv[-1].at[leaves].set(err[leaves])
    node = leaves
    for lvl in range(len(tv) - 2, -1, -1):
        node = node // _FANOUT
        kids = node[:, None] * _FANOUT + jnp.arange(_FANOUT)  # [t F]
        cv = tv[lvl + 1][kids]
        a = jnp.argmin(cv, axis=1)
        tv[lvl] = tv[lvl].at[node].set(jnp.take_along_axis(cv, a[:, None], 1)[:, 0])
        tv_i = jnp.take_along_axis(ti[lvl + 1][kids], a[:, None], 1)[:, 0]
        ti[lvl] = ti[lvl].at[node].set(tv_i)
    return tuple(tv), tuple(ti)


def _stats(sc: _Scan, st: _State, n_polylines: Array) -> PolylineStats:
    return PolylineStats(
        n_vertices=jnp.sum(st.alive).astype(jnp.int32),
        n_polylines=n_polylines.astype(jnp.int32),
        sse_m2=jnp.sum(jnp.where(sc.refl, st.cur, 0.0)),
        sse_explained_m2=jnp.sum(jnp.where(st.explained, st.cur, 0.0)),
        n_explained=jnp.sum(st.explained).astype(jnp.int32),
        n_reflected=jnp.sum(sc.refl).astype(jnp.int32),
    )


def _apply(sc: _Scan, st: _State, j, d_rm2) -> _State:
    k = sc.ranges.shape[0]
    e, mask, new_cur, lose = _candidate(sc, st, j, d_rm2)
    p, n = st.prev[j], st.next[j]
    ps, ns = jnp.clip(p, 0, k - 1), jnp.clip(n, 0, k - 1)
    interior = (p >= 0) & (n >= 0)
    partner = jnp.where(n >= 0, ns, ps)
    pair = ~interior & jnp.where(n >= 0, st.next[ns] < 0, st.prev[ps] < 0)
    nxt = st.next
    prv = st.prev
    # unlink j
    nxt = jnp.where(p >= 0, nxt.at[ps].set(jnp.where(interior, n, -1)), nxt)
    prv = jnp.where(n >= 0, prv.at[ns].set(jnp.where(interior, p, -1)), prv)
    nxt = nxt.at[j].set(-1)
    prv = prv.at[j].set(-1)
    alive = st.alive.at[j].set(False)
    alive = jnp.where(pair, alive.at[partner].set(False), alive)
    nxt = jnp.where(pair, nxt.at[partner].set(-1), nxt)
    prv = jnp.where(pair, prv.at[partner].set(-1), prv)
    cur = jnp.where(mask, new_cur, st.cur)
    explained = jnp.where(mask & lose, False, st.explained)
    n_gone = 1 + pair.astype(jnp.int32)
    old = st.stats
    stats = PolylineStats(
        n_vertices=old.n_vertices - n_gone,
        n_polylines=old.n_polylines - pair.astype(jnp.int32),
        sse_m2=old.sse_m2 + e,
        sse_explained_m2=old.sse_explained_m2
        + jnp.sum(jnp.where(mask & explained, new_cur, 0.0))
        - jnp.sum(jnp.where(mask & st.explained, st.cur, 0.0)),
        n_explained=old.n_explained - jnp.sum(mask & lose & st.explained).astype(jnp.int32),
        n_reflected=old.n_reflected,
    )
    pos = st.n_removed
    order = st.order.at[pos].set(j)
    order_err = st.order_err.at[pos].set(e)
    order = jnp.where(pair, order.at[pos + 1].set(partner), order)
    order_err = jnp.where(pair, order_err.at[pos + 1].set(e), order_err)
    return eqx.tree_at(
        lambda s: (
            s.prev,
            s.next,
            s.alive,
            s.cur,
            s.explained,
            s.order,
            s.order_err,
            s.n_removed,
            s.stats,
        ),
        st,
        (
            prv,
            nxt,
            alive,
            cur,
            explained,
            order,
            order_err,
            pos + 1 + pair.astype(pos.dtype),
            stats,
        ),
    )


def _initial_state(sc: _Scan, closed: bool, l_max, d_rm2) -> _State:
    k = sc.ranges.shape[0]
    idx = jnp.arange(k)
    nb = (idx + 1) % k
    gap = jnp.linalg.norm(sc.ends[nb] - sc.ends, axis=-1)
    conn = sc.refl & sc.refl[nb] & (gap <= l_max) & (cross2(sc.dirs, sc.dirs[nb]) > 0)
    if not closed:
        conn = conn & (idx < k - 1)
    nxt = jnp.where(conn, nb, -1)
    pb = (idx - 1) % k
    prv = jnp.where(conn[pb], pb, -1)
    alive = (nxt >= 0) | (prv >= 0)
    starts = alive & (prv < 0)
    full_cycle = jnp.all(conn)  # a closed polygon of all rays
    n_poly = jnp.sum(starts) + full_cycle.astype(jnp.int32)
    cur = jnp.where(sc.refl & ~alive, d_rm2, 0.0).astype(sc.ranges.dtype)
    zero = jnp.zeros((), jnp.int32)
    st = _State(
        prev=prv.astype(jnp.int32),
        next=nxt.astype(jnp.int32),
        alive=alive,
        cur=cur,
        explained=alive,
        err=jnp.zeros(k, sc.ranges.dtype),
        tree_val=(),
        tree_idx=(),
        order=jnp.full(k, -1, jnp.int32),
        order_err=jnp.full(k, jnp.inf, sc.ranges.dtype),
        n_removed=zero,
        steps=zero,
        done=jnp.zeros((), bool),
        stats=None,
    )
    stats = _stats(sc, st, n_poly)
    return eqx.tree_at(lambda s: s.stats, st, stats, is_leaf=lambda x: x is None)


def _tree_levels(k: int) -> int:
    levels = 1
    while _FANOUT**levels < k:
        levels += 1
    return levels


def _removal_errors(sc: _Scan, st: _State, d_rm2) -> Array:
    k = sc.ranges.shape[0]
    return jax.vmap(lambda j: _candidate(sc, st, j, d_rm2)[0])(jnp.arange(k))


def _ple_one(sc: _Scan, closed: bool, l_max, d_rm, criteria) -> tuple:
    k = sc.ranges.shape[0]
    levels = _tree_levels(k)
    d_rm2 = jnp.asarray(d_rm, sc.ranges.dtype) ** 2
    st = _initial_state(sc, closed, l_max, d_rm2)
    err = _removal_errors(sc, st, d_rm2)
    tv, ti = _tree_build(err, levels)
    st = eqx.tree_at(lambda s: (s.err, s.tree_val, s.tree_idx), st, (err, tv, ti))
    init_stats = st.stats

    def cond(s: _State):
        return ~s.done & (s.steps < k)

    def commit(s: _State, after: _State, j) -> _State:
        # recompute only the errors the removal changed (Algorithm 1, line 20): the two
        # neighbours of an interior vertex (and the third vertex of a closed polygon that
        # shrinks to a triangle), or the new end vertex and its neighbour; the removed
        # vertices get inf.
        p, n = s.prev[j], s.next[j]
        ps, ns = jnp.clip(p, 0, k - 1), jnp.clip(n, 0, k - 1)
        interior = (p >= 0) & (n >= 0)
        start_end = (p < 0) & (n >= 0)
        pair = ~interior & jnp.where(n >= 0, s.next[ns] < 0, s.prev[ps] < 0)
        partner = jnp.where(n >= 0, n, p)
        first = jnp.where(interior | ~start_end, p, n)
        second = jnp.where(interior, n, jnp.where(start_end, s.next[ns], s.prev[ps]))
        third = jnp.where(interior, after.prev[ps], -1)
        redo = jnp.where(pair, -1, jnp.stack([first, second, third]))
        vals = jax.vmap(lambda t: _candidate(sc, after, t, d_rm2)[0])(redo)
        touched = jnp.concatenate([jnp.stack([j, jnp.where(pair, partner, -1)]), redo])
        vals = jnp.concatenate([jnp.full(2, jnp.inf, vals.dtype), vals])
        # invalid entries scatter out of bounds (dropped), so they cannot race a real one
        err = after.err.at[jnp.where(touched >= 0, touched, k)].set(vals, mode="drop")
        tv, ti = _tree_update(after.tree_val, after.tree_idx, err, touched)
        return eqx.tree_at(
            lambda q: (q.err, q.tree_val, q.tree_idx, q.steps),
            after,
            (err, tv, ti, s.steps + 1),
        )

    def stop(s: _State, after: _State, j) -> _State:
        return eqx.tree_at(lambda q: (q.steps, q.done), s, (s.steps + 1, jnp.ones((), bool)))

    def body(s: _State) -> _State:
        j = s.tree_idx[0][0]
        e = s.tree_val[0][0]
        after = _apply(sc, s, j, d_rm2)
        allowed = jnp.isfinite(e)
        for c in criteria:
            allowed = allowed & c.allows(s.stats, after.stats)
        return jax.lax.cond(allowed, commit, stop, s, after, j)

    st = jax.lax.while_loop(cond, body, st)
    m = PolylineMap(sc.ends, jnp.where(st.alive, st.next, -1), st.alive)
    return m, st.stats, init_stats, st.order, st.order_err, st.steps


def _check_positive(x, name: str, allow_zero: bool = False):
    if is_concrete(x):
        v = float(x)
        if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
            kind = "non-negative" if allow_zero else "positive"
            raise ValueError(f"{name} must be a finite {kind} number, got {v}")


def _scan_layout(rays: RayBatch, name: str = "rays") -> None:
    """Check (when concrete) that rays share an origin per scan and turn counter-clockwise."""
    if not isinstance(rays, RayBatch):
        raise ValueError(f"{name} must be a RayBatch, got {type(rays).__name__}")
    if rays.dim != 2:
        raise ValueError(f"{name} must be 2-D rays, got dim={rays.dim}")
    if len(rays.shape) < 1 or rays.shape[-1] < 2:
        raise ValueError(f"{name} must have shape [*scans, K] with K >= 2 rays, got {rays.shape}")
    if not (is_concrete(rays.origins) and is_concrete(rays.directions)):
        return
    o = np.asarray(rays.origins)
    if not np.allclose(o, o[..., :1, :], rtol=0, atol=1e-9 * (1 + np.abs(o).max())):
        raise ValueError(f"{name}: all rays of a scan must share one origin")
    d = np.asarray(rays.directions)
    cr = d[..., :-1, 0] * d[..., 1:, 1] - d[..., :-1, 1] * d[..., 1:, 0]
    if np.any(cr <= 0):
        raise ValueError(
            f"{name}: rays must be ordered counter-clockwise (increasing azimuth, consecutive "
            f"rays less than 180 deg apart); {int(np.sum(cr <= 0))} consecutive pairs are not"
        )
    r = np.asarray(rays.ranges)
    hit = np.asarray(rays.kind) == HIT
    if np.any(hit & ~np.isfinite(r)):
        raise ValueError(f"{name}: HIT rays must have finite ranges")


def is_full_revolution(rays: RayBatch) -> bool:
    """Whether a scan wraps around (the step from the last ray to the first is no larger
    than 1.5 times the median angular step), so PLE connects its last and first endpoint.

    Args:
        rays: ``[*scans K]`` 2-D rays (the first scan decides).
    """
    d = np.asarray(rays.directions).reshape(-1, rays.shape[-1], 2)[0]
    ang = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    steps = np.diff(ang)
    wrap = 2 * np.pi - (ang[-1] - ang[0])
    return bool(0 < wrap <= 1.5 * np.median(steps))


def _criteria_list(max_vertices, criteria) -> tuple[AbstractStoppingCriterion, ...]:
    cs = list(criteria)
    if max_vertices is not None:
        if isinstance(max_vertices, bool) or int(max_vertices) != max_vertices:
            raise ValueError(f"max_vertices must be an integer, got {max_vertices!r}")
        cs.append(MaxVertices(int(max_vertices)))
    for c in cs:
        if not isinstance(c, AbstractStoppingCriterion):
            raise ValueError(
                f"criteria must be AbstractStoppingCriterion instances, got {type(c).__name__}"
            )
    if not cs:
        raise ValueError("give max_vertices and/or criteria: PLE needs a stopping criterion")
    return tuple(cs)


def _scan_arrays(rays: RayBatch) -> _Scan:
    o = rays.origins[..., 0, :]
    refl = rays.kind == HIT
    r = jnp.where(refl, rays.ranges, 0.0)
    ends = rays.origins + r[..., None] * rays.directions
    return _Scan(o, rays.directions, r, refl, ends)


@eqx.filter_jit
def _extract(rays: RayBatch, closed: bool, l_max, d_rm, criteria):
    sc = _scan_arrays(rays)
    f = lambda s: _ple_one(s, closed, l_max, d_rm, criteria)  # noqa: E731
    for _ in range(sc.ranges.ndim - 1):
        f = jax.vmap(f)
    return f(sc)


def extract_polylines(
    rays: RayBatch,
    *,
    max_vertices: int | None = None,
    criteria: Sequence[AbstractStoppingCriterion] = (),
    l_max_m: float = 1.0,
    d_rm_m: float = 0.5,
    closed: bool | None = None,
) -> PolylineExtraction:
    """PLE: maximum-likelihood polyline extraction from 2-D scans (Algorithm 1).

    Connects neighbouring endpoints of reflected rays that are at most ``l_max_m`` apart
    (lines 1–10), then repeatedly removes the vertex whose removal lowers the scan
    likelihood the least, i.e. has the smallest error ``e_j`` of Eq. (10.3)
    (``Σ d²(z_k, L \\ v_j) - d²(z_k, L)`` over the rays of its segments; ``d_rm`` stands in
    for the residual of rays that lose their segment when an end vertex goes; a polyline
    of two vertices disappears as a whole). Ties go to the lower ray index. A removal that
    would turn a chord through at least 180° of the scan or a triangle into a degenerate
    polygon is not allowed. Removal stops as soon as a criterion refuses (or nothing is
    removable).

    Args:
        rays: ``[*scans K]`` 2-D rays of one scan per leading index, sharing an origin per
            scan and ordered counter-clockwise. Only HIT rays are reflected.
        max_vertices: ``J_max``: stop at this many vertices (shorthand for
            ``MaxVertices(J_max)``).
        criteria: further stopping criteria (:class:`MaxRMSE`, :class:`AIC`, ...).
        l_max_m: longest connection between neighbouring endpoints (m).
        d_rm_m: placeholder residual for rays whose segment is removed (m).
        closed: whether the last and first ray are neighbours (a full-revolution scan);
            default: detected with :func:`is_full_revolution`.

    Returns:
        A :class:`PolylineExtraction` with leading axes ``[*scans]``.

    Raises:
        ValueError: wrong ray layout, no stopping criterion, or bad parameters.
    """
    _scan_layout(rays)
    cs = _criteria_list(max_vertices, criteria)
    _check_positive(l_max_m, "l_max_m")
    _check_positive(d_rm_m, "d_rm_m", allow_zero=True)
    if closed is None:
        closed = is_full_revolution(rays)
    dtype = rays.ranges.dtype
    d_rm = np.asarray(d_rm_m, dtype)
    m, stats, init, order, order_err, steps = _extract(
        rays, bool(closed), np.asarray(l_max_m, dtype), d_rm, cs
    )
    return PolylineExtraction(
        map=m,
        stats=stats,
        initial_stats=init,
        removal_order=order,
        removal_error=order_err,
        n_steps=steps,
        d_rm_m=jnp.asarray(d_rm),
    )
