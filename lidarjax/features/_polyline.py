"""Maximum-likelihood polyline extraction from 2-D scans: PLE and PLE+ (dissertation ch. 10).

- :class:`PolylineMap`: a set of polylines in a padded, static-shape layout (one vertex slot
  per scan ray, successor pointers), with :meth:`PolylineMap.expected_ranges` (the
  ``r̂(z, L)`` of Eq. 10.1: distance to the first intersection of each ray with the map).
- :func:`extract_polylines` (PLE, Algorithm 1): connect neighbouring endpoints, then
  greedily remove the vertex of least error ``e_j`` (Eq. 10.3) until a stopping criterion
  holds. The greedy loop is one ``lax.while_loop``; the errors live in an indexed
  priority queue (a min tournament tree over the vertex slots: ``O(1)`` find-min,
  ``O(log n)`` key update), and each step recomputes only the errors the removal touched.
  The error terms are batched ray–segment computations over the scan's rays.
- :func:`optimize_polylines` (PLE+, section 10.4.3): with the ray-to-segment association of
  PLE held fixed, Eq. (10.4) is a smooth least-squares problem in the vertex coordinates;
  it is solved with optimistix Levenberg–Marquardt (end vertices move along their ray,
  ``2(J - I)`` unknowns). A final backtracking step guarantees that the scan likelihood
  under the *true* first-intersection model never decreases and that the set of explained
  rays is unchanged, so ``f(PLE) = f(PLE+)``.
- Stopping criteria are pluggable (:class:`MaxVertices`, :class:`MaxRMSE`, :class:`AIC`, or
  any :class:`AbstractStoppingCriterion`).

Scans are :class:`~lidarjax.rays.RayBatch` es of shape ``[*scans, K]`` whose rays share an
origin per scan and are ordered counter-clockwise (increasing azimuth), as every 2-D lidar
delivers them. Only HIT rays are reflected; SUB and SUP rays are never connected. As in the
paper's experiments the radial variance is constant, so it drops out of Eqs. (10.3)/(10.4):
errors are in m².
"""

from __future__ import annotations

import abc
import dataclasses
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ..rays import HIT, RayBatch, is_concrete
from ..raytrace import cross2, first_segment_hits, ray_segment

_CHUNK = 2048  # rays per lax.map chunk in expected_ranges


# --------------------------------------------------------------------------------------
# Polyline map
# --------------------------------------------------------------------------------------


class PolylineMap(eqx.Module):
    """A set of polylines (no shared vertices) in a padded static-shape layout.

    Vertex slot ``i`` is used when ``active[i]``; its polyline continues with slot
    ``successor[i]`` (``-1``: the polyline ends at ``i``). A closed polyline (polygon) has
    successors forming a cycle. The segments are ``(vertices[i], vertices[successor[i]])``
    for every active ``i`` with ``successor[i] >= 0``. Leading axes ``[*batch]`` are allowed
    (e.g. one map per scan from a batched extraction).

    Attributes:
        vertices: ``[*batch v 2]`` vertex coordinates (m).
        successor: ``[*batch v]`` index of the next vertex along the polyline, ``-1`` if none.
        active: ``[*batch v]`` mask of used vertex slots.
    """

    vertices: Float[Array, "*batch v 2"]
    successor: Int[Array, "*batch v"]
    active: Bool[Array, "*batch v"]

    def __check_init__(self):
        v = self.vertices.shape
        if len(v) < 2 or v[-1] != 2:
            raise ValueError(f"vertices must have shape [*batch, v, 2], got {v}")
        if self.successor.shape != v[:-1] or self.active.shape != v[:-1]:
            raise ValueError(
                f"successor {self.successor.shape} and active {self.active.shape} must have "
                f"shape {v[:-1]} to match vertices"
            )

    @classmethod
    def from_polylines(
        cls,
        polylines: Sequence[ArrayLike],
        closed: Sequence[bool] | None = None,
        *,
        n_slots: int | None = None,
    ) -> PolylineMap:
        """Build a map from vertex arrays.

        Args:
            polylines: list of ``[m_i 2]`` vertex arrays (m), ``m_i >= 2`` (``>= 3`` if closed).
            closed: per polyline, whether the last vertex connects back to the first
                (default: all open).
            n_slots: number of vertex slots (padding); default: the total vertex count.

        Returns:
            An unbatched :class:`PolylineMap`.

        Raises:
            ValueError: malformed polylines, non-finite vertices or too few slots.
        """
        closed = [False] * len(polylines) if closed is None else list(closed)
        if len(closed) != len(polylines):
            raise ValueError(f"closed has {len(closed)} entries for {len(polylines)} polylines")
        verts, succ = [], []
        for i, (pl, c) in enumerate(zip(polylines, closed)):
            a = np.asarray(pl, dtype=float)
            if a.ndim != 2 or a.shape[1] != 2 or a.shape[0] < (3 if c else 2):
                raise ValueError(
                    f"polylines[{i}] must have shape [m, 2] with m >= {3 if c else 2}, "
                    f"got {a.shape}"
                )
            if not np.all(np.isfinite(a)):
                raise ValueError(f"polylines[{i}] has non-finite vertices")
            base = len(verts)
            m = a.shape[0]
            verts.extend(a)
            nxt = list(range(base + 1, base + m)) + [base if c else -1]
            succ.extend(nxt)
        n = len(verts)
        n_slots = max(n, 1) if n_slots is None else int(n_slots)
        if n_slots < n:
            raise ValueError(f"n_slots={n_slots} is smaller than the vertex count {n}")
        v = np.zeros((n_slots, 2))
        s = np.full(n_slots, -1, np.int32)
        act = np.zeros(n_slots, bool)
        if n:
            v[:n] = np.asarray(verts)
            s[:n] = succ
            act[:n] = True
        return cls(jnp.asarray(v), jnp.asarray(s), jnp.asarray(act))

    def to_chains(self) -> tuple[list[np.ndarray], list[bool]]:
        """The polylines as vertex-slot index arrays (unbatched maps only).

        For a PLE map slot ``k`` is ray ``k``, so the chains index the scan's endpoints.

        Returns:
            ``(chains, closed)``: a list of ``[m]`` int arrays of slots in polyline order,
            and per polyline whether it is closed.
        """
        if self.vertices.ndim != 2:
            raise ValueError("to_chains needs an unbatched map; index the batch first")
        s = np.asarray(self.successor)
        act = np.asarray(self.active)
        pred = np.full(len(s), -1)
        linked = np.flatnonzero(act & (s >= 0))
        pred[s[linked]] = linked
        seen = np.zeros(len(s), bool)
        out, closed = [], []
        for i in np.flatnonzero(act & (pred < 0)):
            chain = [i]
            while s[chain[-1]] >= 0:
                chain.append(s[chain[-1]])
            seen[chain] = True
            out.append(np.asarray(chain))
            closed.append(False)
        for i in np.flatnonzero(act):  # what is left lies on cycles
            if seen[i]:
                continue
            chain = [i]
            while s[chain[-1]] != i:
                chain.append(s[chain[-1]])
            seen[chain] = True
            out.append(np.asarray(chain))
            closed.append(True)
        return out, closed

    def to_polylines(self) -> tuple[list[np.ndarray], list[bool]]:
        """The polylines as host arrays (unbatched maps only).

        Returns:
            ``(polylines, closed)``: a list of ``[m 2]`` vertex arrays (m) in order, and
            per polyline whether it is closed.
        """
        chains, closed = self.to_chains()
        v = np.asarray(self.vertices)
        return [v[c] for c in chains], closed

    @property
    def n_vertices(self) -> Int[Array, "*batch"]:
        """Number of vertices ``J`` (per batch element)."""
        return jnp.sum(self.active, axis=-1)

    def segments(self) -> tuple[Float[Array, "*batch v 2"], Float[Array, "*batch v 2"], Array]:
        """``(starts, ends, valid)``: one (possibly invalid) segment per vertex slot."""
        nxt = jnp.clip(self.successor, 0, None)
        ends = jnp.take_along_axis(self.vertices, nxt[..., None], axis=-2)
        return self.vertices, ends, self.active & (self.successor >= 0)

    def expected_ranges(self, rays: RayBatch) -> Float[Array, "*batch n"]:
        """``r̂(z, L)`` of Eq. (10.1): distance to the first intersection with the map.

        Args:
            rays: 2-D rays of shape ``[*batch n]`` whose leading axes match the map's
                (or any shape for an unbatched map).

        Returns:
            ``[*rays.shape]`` distances (m); ``inf`` where a ray hits no polyline.
        """
        return self.first_hits(rays)[0]

    def first_hits(self, rays: RayBatch) -> tuple[Array, Array]:
        """Like :meth:`expected_ranges`, also returning the index of the segment hit
        (its start vertex slot, ``-1`` if none)."""
        if rays.dim != 2:
            raise ValueError(f"rays must be 2-D, got dim={rays.dim}")
        bm = self.vertices.shape[:-2]
        if bm:
            if rays.shape[: len(bm)] != bm:
                raise ValueError(
                    f"rays of shape {rays.shape} do not start with the map's batch axes {bm}"
                )
            return _first_hits_batched(self, rays.origins, rays.directions)
        return _first_hits(self, rays.origins, rays.directions)


@eqx.filter_jit
def _first_hits_batched(m: PolylineMap, origins: Array, directions: Array):
    def one(mm, o, d):
        return _first_hits(mm, o, d)

    f = one
    for _ in range(m.vertices.ndim - 2):
        f = jax.vmap(f)
    return f(m, origins, directions)


def _first_hits(m: PolylineMap, origins: Array, directions: Array):
    shape = origins.shape[:-1]
    o = origins.reshape(-1, 2)
    d = directions.reshape(-1, 2)
    starts, ends, valid = m.segments()
    t, i = first_segment_hits(o, d, starts, ends, valid, chunk_size=_CHUNK)
    return t.reshape(shape), i.reshape(shape)


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
        s_first = jnp.argmin(t_seg_s, axis=1)
        use = sc.refl & jnp.isfinite(jnp.min(t_seg_s, axis=1))
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
            z = jax.random.normal(
                jax.random.fold_in(key0, i_round), (restarts, n_params, 2), pc.dtype
            )
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
) -> PolylineOptimization:
    """PLE+: move the vertices to maximise the scan likelihood (Eq. 10.4, section 10.4.3).

    With each reflected ray held on the segment it hits first (the ray-to-segment
    association), its residual ``r_k - r̂_k`` measured to that segment's line makes
    Eq. (10.4) a smooth least-squares problem, solved with ``solver`` (default
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
    deterministic. Batched over ``[*scans]`` with ``vmap``.

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

    Returns:
        A :class:`PolylineOptimization`.

    Raises:
        ValueError: a bad ``extraction``, ``rays`` not in its layout, or a count or spread
            out of range (``max_steps``, ``rounds`` >= 1; ``restarts`` >= 0;
            ``restart_sigma`` and every ``pattern_m`` finite and > 0).
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
    if solver is None:
        solver = default_plus_solver()
    n_active = int(jnp.max(m.n_vertices)) if m.active.size else 0
    n_params = max(8, -(-n_active // 8) * 8)  # bucket to limit recompiles
    cfg = _PlusSettings(
        int(max_steps), int(rounds), int(restarts), restart_sigma, pattern_m, int(seed)
    )
    out, s0, s1, frac, res, steps = _optimize(m, _scan_arrays(rays), solver, n_params, cfg)
    return PolylineOptimization(out, s0, s1, frac, res, steps)
