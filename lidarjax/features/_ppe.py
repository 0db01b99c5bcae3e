"""Probabilistic plane extraction (PPE, dissertation ch. 11, Algorithm 2): the fast greedy
clustering behind :func:`extract_planes` and :func:`extract_planes_path`.

PPE clusters an organized scan agglomeratively. Atomic planes (one per reflection) are
combined into regular planes by the cheapest of three actions: *create* a plane from 4
atoms forming one of the 17 valid tetrominoes (Figure 11.2), *extend* a regular plane by an
adjacent atom, *merge* two adjacent regular planes; each action costs its error increment
(Eqs. 11.3–11.4, ``e_crt``, ``e_ext``, ``e_mrg``). It stops at ``J_max`` planes and/or when
the cheapest increment exceeds ``e`` (``max_increment``; by default the noise-robust rule
``e = max(200 σ̂², 0.01 m²)`` of :func:`auto_max_increment`; without any criterion it
raises instead of merging the scan into one plane); the geometric outlier filter ``d``
(``max_distance_m``) forbids clustering neighbours farther apart than ``d``.

**The clustering objective.** An exact ``e_crt`` needs a nonlinear fit per candidate, and
a 500 x 500 scan has ~250 000 greedy steps with hundreds of candidates each. PPE here
scores actions with the ray-path error linearised in the plane's inverse-distance
parameters ``a = n / (n . x)`` (sensor at the origin): each ray contributes
``r_k² (a . p_k - 1)² = (r_k - r̂_k)² (r_k / r̂_k)²`` with the endpoint ``p_k``, i.e. the
ray-path error of Eq. (11.2) re-weighted by ``(r / r̂)² = 1 + O(noise / range)`` (with
20 mm noise at 2–5 m: within 1–2 %). It keeps Eq. (11.1)'s ray-path geometry (the
``1 / cos`` incidence factor that the point-to-plane distance lacks) and is quadratic in
``a``, so a plane is summarised by sufficient statistics (:mod:`._plane_stats`) that add in
``O(1)``, and every increment is an exact difference of minimised errors. The planes PPE
returns are then refitted on the exact Eq. (11.2) error with :func:`fit_planes`.

**The bookkeeping** (:class:`_Greedy`) is an indexed priority queue (heapq) with lazy
invalidation, in NumPy and Python floats; the tetromino scoring and the plane fits are
batched JAX. The heap holds three kinds of entries (:class:`_Create`, :class:`_Extend`,
:class:`_Merge`), ordered by (increment at float32 resolution, kind, ray / plane index).

The pieces: the scan checks, graph and tetrominoes in :mod:`._ppe_scan`, the threshold rule
in :mod:`._ppe_threshold`, the result in :mod:`._ppe_result`, and a slow from-scratch
implementation of the same algorithm for the tests in :mod:`._ppe_reference`.
"""

from __future__ import annotations

import dataclasses
import heapq
import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from jaxtyping import ArrayLike, Float

from ._plane_stats import _atom, _merge_py, _merged_error_py, _stats_error_cols, _stats_error_py
from ._ppe_result import (
    CREATE,
    EXTEND,
    MERGE,
    PlaneSegmentation,
    PPEStop,
    _Partition,
    _segmentation,
)
from ._ppe_scan import (
    _check_inputs,
    _neighbours,
    _Params,
    _q,
    _qs,
    _tetromino_costs,
    _tetromino_table,
)
from ._ppe_threshold import _resolve_increment, _resolve_increments

__all__ = ["extract_planes", "extract_planes_path"]


# --------------------------------------------------------------------------------------
# Public entry points
# --------------------------------------------------------------------------------------


def extract_planes(
    points: Float[ArrayLike, "H W 3"],
    *,
    max_increment: float | str | None = "auto",
    max_planes: int | None = None,
    max_distance_m: float | None = None,
    min_points: int = 4,
    refit: bool = True,
    progress: bool = False,
) -> PlaneSegmentation:
    """PPE (Algorithm 2): maximum-likelihood plane extraction from an organized scan.

    Starting from one atomic plane per reflection, repeatedly applies the action with the
    least error increment (ties: create < extend < merge, then lowest ray / plane index):

    - create a regular plane from 4 atoms forming a valid tetromino (``e_crt``, Eq. 11.4);
    - extend a regular plane by a 4-adjacent atom (``e_ext``);
    - merge two 4-adjacent regular planes (``e_mrg``).

    Errors are the linearised ray-path error (module docstring), so each increment is an
    exact ``O(1)`` difference of minimised errors. The bookkeeping is an indexed priority
    queue with lazy invalidation: a plane's actions are re-scored (vectorised) only when
    the plane changes; tetromino and extension entries whose rays were taken are skipped
    or re-scored when popped (their cost can only rise). ``O(K log K)`` overall.

    Args:
        points: ``[H, W, 3]`` organized scan in the sensor frame (sensor at the origin),
            metres; NaN points (no return) are never clustered.
        max_increment: ``e``: stop when the cheapest action's increment exceeds it (m²).
            ``"auto"`` (default): the noise-robust rule ``e = max(200 σ̂², 0.01 m²)``
            of :func:`auto_max_increment` (``σ̂`` = :func:`estimate_noise` of the scan).
            ``None``: no threshold (then ``max_planes`` is required); ``math.inf``:
            cluster until no action is left (everything connected ends in one plane).
        max_planes: ``J_max``: stop when the number of planes (regular + remaining
            atomic planes, as in Algorithm 2) is at most this. Combined with a threshold,
            the first criterion met stops.
        max_distance_m: ``d``: the geometric outlier filter; neighbouring rays whose
            endpoints are farther apart are never clustered (default: no filter; the
            SynPEB experiments use 0.2 m: without it f and k are as good there, but
            about 400 small planes of 4-29 rays per 500 x 500 scan remain as spurious
            planes; ``min_points=30`` also removes them).
        min_points: planes with fewer rays are reported as unclustered (``-1``).
        refit: refit the returned planes on the exact ray-path error (:func:`fit_planes`).
        progress: show a tqdm progress bar over the clustered rays.

    Returns:
        A :class:`PlaneSegmentation`.

    Raises:
        ValueError: If ``points`` is not an organized ``[H, W, 3]`` float scan, has no valid
            point, contains inf or partly-NaN points, a parameter is out of range, or
            ``max_increment=None`` and ``max_planes=None`` (no stopping criterion: the
            whole scan would collapse into one plane).
    """
    max_increment = _resolve_increment(points, max_increment, max_planes)
    pts, valid, prm = _check_inputs(points, max_increment, max_planes, max_distance_m, min_points)
    parts = _greedy(pts, valid, prm, [prm.max_increment], progress)
    return _segmentation(pts, valid, parts[0], min_points, refit)


def extract_planes_path(
    points: Float[ArrayLike, "H W 3"],
    max_increments: Sequence[float | str],
    *,
    max_planes: int | None = None,
    max_distance_m: float | None = None,
    min_points: int = 4,
    refit: bool = True,
    progress: bool = False,
) -> list[PlaneSegmentation]:
    """PPE at several error thresholds ``e`` from one greedy run.

    The greedy order does not depend on ``e`` (it only decides when to stop), so the
    segmentation for every ``e`` is a prefix of the run with the largest one. Used by the
    experiments' grid searches. Arguments as in :func:`extract_planes`; each entry of
    ``max_increments`` is a threshold in m² (``math.inf``: no threshold) or ``"auto"``
    (:func:`auto_max_increment`).

    Returns:
        One :class:`PlaneSegmentation` per entry of ``max_increments`` (same order).
    """
    incs = _resolve_increments(points, max_increments)
    pts, valid, prm = _check_inputs(points, max(incs), max_planes, max_distance_m, min_points)
    order = np.argsort(incs, kind="stable")
    parts = _greedy(pts, valid, prm, [incs[k] for k in order], progress)
    out: list[PlaneSegmentation | None] = [None] * len(incs)
    for k, part in zip(order, parts):
        out[k] = _segmentation(pts, valid, part, min_points, refit)
    return out  # type: ignore[return-value]


def _greedy(
    pts: np.ndarray,
    valid: np.ndarray,
    prm: _Params,
    max_increments: list[float],
    progress: bool,
) -> list[_Partition]:
    """The fast greedy loop on a checked scan; one partition per threshold in
    ``max_increments`` (ascending), taken when the loop first passes it."""
    greedy = _Greedy(pts, valid, prm, max_increments)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=greedy.n_atoms, desc="PPE", unit="ray", mininterval=0.5)
    try:
        return greedy.run(bar)
    finally:
        if bar is not None:
            bar.close()


# --------------------------------------------------------------------------------------
# Heap entries and plane state
# --------------------------------------------------------------------------------------
# The heap compares entries as tuples: (cost, kind, then two ray indices) decide the order;
# the remaining fields only identify the action. ``cost`` is the increment at float32
# resolution (``_q``), ``increment`` the float64 value recorded in ``step_costs``.


class _Create(NamedTuple):
    """The cheapest not yet rejected tetromino placement of one anchor ray."""

    cost: float  # e_crt of placement `first` at float32 resolution
    kind: int  # CREATE
    anchor: int  # flat index of the top-left ray of the placement's bounding box
    shape: int  # tetromino id (index into TETROMINOES)
    first: int  # index of the placement in the sorted placement table
    end: int  # one past the anchor's last placement (placements first .. end-1 are left)


class _Extend(NamedTuple):
    """The cheapest extension of one plane by one adjacent atom."""

    cost: float  # e_ext at float32 resolution
    kind: int  # EXTEND
    canon: int  # the plane's lowest ray index (tie rule)
    ray: int  # the atom to add
    plane: int  # plane id
    version: int  # the plane's version when scored (stale if it changed since)
    increment: float  # e_ext (m²)


class _Merge(NamedTuple):
    """The cheapest merge of one plane with one of its adjacent planes."""

    cost: float  # e_mrg at float32 resolution
    kind: int  # MERGE
    canon_lo: int  # the lower of the two planes' lowest ray indices (tie rule)
    canon_hi: int  # the higher one
    plane: int  # the plane that was re-scored
    partner: int  # the plane to merge it with
    version: int  # versions of both when scored (stale if either changed since)
    partner_version: int
    increment: float  # e_mrg (m²)


@dataclasses.dataclass(slots=True)
class _Plane:
    """One regular plane of the greedy loop (its id is its index in ``_Greedy.planes``).

    Attributes:
        stats: the sufficient statistics ``(W, m0, m1, m2, c00, c01, c02, c11, c12, c22)``.
        error: its minimised linearised error (m²).
        canon: its lowest ray index (the greedy tie rule).
        members: its rays (flat indices, in joining order).
        boundary: the atoms 4-adjacent to it (may hold rays taken since; pruned lazily).
        adjacent: the ids of the planes 4-adjacent to it.
        version: bumped on every change; heap entries scored before are stale.
        alive: False once merged into another plane.
    """

    stats: tuple
    error: float
    canon: int
    members: list[int]
    boundary: set[int] = dataclasses.field(default_factory=set)
    adjacent: set[int] = dataclasses.field(default_factory=set)
    version: int = 0
    alive: bool = True


class _Placements(NamedTuple):
    """The tetromino placements of a scan sorted by (anchor, cost, shape)."""

    anchors: np.ndarray  # [T] flat index of each placement's anchor ray
    shape_ids: np.ndarray  # [T] tetromino ids
    cells: np.ndarray  # [T, 4] flat ray indices
    cost: np.ndarray  # [T] e_crt (m²)
    cost_q: np.ndarray  # [T] e_crt at float32 resolution
    starts: np.ndarray  # [A] first placement of each anchor
    ends: np.ndarray  # [A] one past its last placement


def _placements(flat: np.ndarray, valid: np.ndarray, nbr: np.ndarray) -> _Placements:
    """Every tetromino placement, scored in one batched call and sorted per anchor (each
    anchor's placements are a lazy list: the heap holds the cheapest one not yet tried)."""
    anchors, shape_ids, cells = _tetromino_table(valid, nbr)
    tcost = _tetromino_costs(flat, cells)
    tq = _q(tcost)
    order = np.lexsort((shape_ids, tq, anchors))
    anchors, shape_ids, cells = anchors[order], shape_ids[order], cells[order]
    tcost, tq = tcost[order], tq[order]
    starts = (
        np.flatnonzero(np.r_[True, anchors[1:] != anchors[:-1]])
        if anchors.size
        else np.zeros(0, int)
    )
    ends = np.r_[starts[1:], anchors.size].astype(np.int64)
    return _Placements(anchors, shape_ids, cells, tcost, tq, starts, ends)


# --------------------------------------------------------------------------------------
# The greedy loop
# --------------------------------------------------------------------------------------


_PROGRESS_RAYS = 4096  # progress bar update granularity (clustered rays)


class _Greedy:
    """PPE's greedy state: the rays, the regular planes and the priority queue.

    Rays are atoms (``owner == -1``), on a plane (``owner = plane id``) or invalid
    (``owner == -2``). Each plane keeps at most one live extension and one live merge entry
    in the heap (older ones are stale by ``version``), each anchor ray one creation entry.
    """

    def __init__(self, pts: np.ndarray, valid: np.ndarray, prm: _Params, max_increments):
        K = valid.size
        flat = np.where(valid[..., None], pts, 0.0).reshape(K, 3)
        nbr = _neighbours(pts, valid, prm.max_distance_m)
        self.max_planes = prm.max_planes
        self.tet = _placements(flat, valid, nbr)
        s = self.tet.starts
        self.heap: list[tuple] = [
            _Create(*entry)
            for entry in zip(
                self.tet.cost_q[s].tolist(),
                [CREATE] * s.size,
                self.tet.anchors[s].tolist(),
                self.tet.shape_ids[s].tolist(),
                s.tolist(),
                self.tet.ends.tolist(),
            )
        ]
        heapq.heapify(self.heap)

        self.owner = np.full(K, -1, dtype=np.int64)  # plane id, -1 = atom, -2 = invalid
        self.owner[~valid.ravel()] = -2
        self.free = bytearray(valid.ravel().astype(np.uint8).tobytes())  # 1 = atom
        self.nbr = nbr.tolist()
        # per-ray statistics: weights r² (atoms' W), endpoint columns, atoms as tuples
        self.aw = np.einsum("ki,ki->k", flat, flat)
        self.ax, self.ay, self.az = flat[:, 0].copy(), flat[:, 1].copy(), flat[:, 2].copy()
        self.atoms = [_atom(w, p) for w, p in zip(self.aw.tolist(), flat.tolist())]
        self.planes: list[_Plane] = []

        self.n_planes = 0  # regular planes alive
        self.n_atoms = int(valid.sum())
        self.kinds: list[int] = []
        self.costs: list[float] = []
        self.thresholds = list(max_increments)  # ascending; those not yet passed
        self.partitions: list[_Partition] = []

    # -- the loop ----------------------------------------------------------------------

    def run(self, bar=None) -> list[_Partition]:
        """Apply the cheapest valid action until a criterion stops the loop; returns one
        partition per threshold."""
        stop = PPEStop.EXHAUSTED
        reported = self.n_atoms
        heap, thresholds, is_current = self.heap, self.thresholds, self._is_current
        while heap and thresholds:
            if self.max_planes and self.n_planes + self.n_atoms <= self.max_planes:
                stop = PPEStop.MAX_PLANES
                break
            entry = heapq.heappop(heap)
            if not is_current(entry):
                continue
            if entry.cost > thresholds[0] and self._pass_thresholds(entry.cost):
                break
            if entry.kind == CREATE:
                increment = self._create(entry)
            elif entry.kind == EXTEND:
                increment = self._extend(entry)
            else:
                increment = self._merge(entry)
            self.kinds.append(entry.kind)
            self.costs.append(increment)
            if bar is not None and reported - self.n_atoms >= _PROGRESS_RAYS:
                bar.update(reported - self.n_atoms)
                reported = self.n_atoms
        if bar is not None:
            bar.update(reported - self.n_atoms)
        final = _Partition(self._live_members(), self.kinds, self.costs, stop, self.n_atoms)
        self.partitions.extend(final for _ in self.thresholds)
        return self.partitions

    def _pass_thresholds(self, cost: float) -> bool:
        """Record the partition for every remaining threshold below ``cost``; True if none
        is left (the loop ends)."""
        while self.thresholds and cost > self.thresholds[0]:
            self.thresholds.pop(0)
            self.partitions.append(
                _Partition(
                    self._live_members(),
                    list(self.kinds),
                    list(self.costs),
                    PPEStop.MAX_INCREMENT,
                    self.n_atoms,
                )
            )
        return not self.thresholds

    def _live_members(self) -> list[np.ndarray]:
        return [np.asarray(p.members, dtype=np.int64) for p in self.planes if p.alive]

    # -- validity of popped entries ----------------------------------------------------

    def _is_current(self, entry) -> bool:
        """Whether a popped entry still describes a possible action with its cost. A stale
        entry is dropped, or re-scored and pushed again (costs only rise, so the pop order
        stays exact)."""
        if entry.kind == CREATE:
            if self._placement_free(entry.first):
                return True
            self._push_next_placement(entry)
            return False
        plane = self.planes[entry.plane]
        if not plane.alive or entry.version != plane.version:
            return False
        if entry.kind == EXTEND:
            if not self.free[entry.ray]:
                self._push_extension(entry.plane)  # the best atom was taken: re-score
                return False
            return True
        partner = self.planes[entry.partner]
        if not partner.alive or entry.partner_version != partner.version:
            self._push_merge(entry.plane)  # the partner changed: re-score the merges
            return False
        return True

    def _placement_free(self, t: int) -> bool:
        """Whether all 4 rays of tetromino placement ``t`` are still atoms."""
        c0, c1, c2, c3 = self.tet.cells[t].tolist()
        free = self.free
        return bool(free[c0] and free[c1] and free[c2] and free[c3])

    def _push_next_placement(self, entry: _Create) -> None:
        """Push the anchor's next placement whose rays are all atoms (if any)."""
        tet, free = self.tet, self.free
        for t in range(entry.first + 1, entry.end):
            c0, c1, c2, c3 = tet.cells[t].tolist()  # _placement_free(t), inlined (hot)
            if free[c0] and free[c1] and free[c2] and free[c3]:
                heapq.heappush(
                    self.heap,
                    _Create(
                        float(tet.cost_q[t]),
                        CREATE,
                        int(tet.anchors[t]),
                        int(tet.shape_ids[t]),
                        t,
                        entry.end,
                    ),
                )
                return

    # -- actions -----------------------------------------------------------------------

    def _create(self, entry: _Create) -> float:
        """Create a plane from the 4 atoms of placement ``entry.first``; returns ``e_crt``."""
        t = entry.first
        cl = self.tet.cells[t].tolist()
        c0, c1, c2, c3 = cl
        j = len(self.planes)
        self.owner[cl] = j
        atoms = self.atoms
        st = atoms[c0]
        for u in (c1, c2, c3):
            st = _merge_py(st, atoms[u])
        self.planes.append(_Plane(stats=st, error=_stats_error_py(st), canon=min(cl), members=cl))
        for u in cl:
            self.free[u] = 0
        for u in cl:
            self._link(j, u)
        self.n_planes += 1
        self.n_atoms -= 4
        self._push_extension(j)
        self._push_merge(j)
        return float(self.tet.cost[t])

    def _extend(self, entry: _Extend) -> float:
        """Add atom ``entry.ray`` to plane ``entry.plane``; returns ``e_ext``."""
        k, j = entry.ray, entry.plane
        plane = self.planes[j]
        self.owner[k] = j
        self.free[k] = 0
        plane.members.append(k)
        st = _merge_py(plane.stats, self.atoms[k])
        plane.stats = st
        plane.error = _stats_error_py(st)
        if k < plane.canon:
            plane.canon = k
        plane.version += 1
        plane.boundary.discard(k)
        self._link(j, k)
        self.n_atoms -= 1
        self._push_extension(j)
        self._push_merge(j)
        return entry.increment

    def _merge(self, entry: _Merge) -> float:
        """Merge planes ``entry.plane`` and ``entry.partner`` (the larger survives);
        returns ``e_mrg``."""
        j, i = entry.plane, entry.partner
        if len(self.planes[i].members) > len(self.planes[j].members):
            i, j = j, i  # j survives (the larger)
        keep, gone = self.planes[j], self.planes[i]
        st = _merge_py(keep.stats, gone.stats)
        keep.stats = st
        keep.error = _stats_error_py(st)
        self.owner[gone.members] = j
        keep.members.extend(gone.members)
        gone.members = []
        keep.canon = min(keep.canon, gone.canon)
        keep.boundary |= gone.boundary
        gone.boundary = set()
        for q in gone.adjacent:
            other = self.planes[q].adjacent
            other.discard(i)
            if q != j:
                other.add(j)
                keep.adjacent.add(q)
        keep.adjacent.discard(i)
        gone.adjacent = set()
        gone.alive = False
        keep.version += 1
        self.n_planes -= 1
        self._push_extension(j)
        self._push_merge(j)
        return entry.increment

    def _link(self, j: int, k: int) -> None:
        """Ray ``k`` joined plane ``j``: grow j's boundary and adjacency from k's
        neighbours."""
        plane = self.planes[j]
        free, owner = self.free, self.owner
        for u in self.nbr[k]:
            if u < 0:
                continue
            if free[u]:
                plane.boundary.add(u)
            else:
                o = int(owner[u])
                if o >= 0 and o != j and o not in plane.adjacent:
                    plane.adjacent.add(o)
                    self.planes[o].adjacent.add(j)

    # -- scoring -----------------------------------------------------------------------

    def _push_extension(self, j: int) -> None:
        """Push plane ``j``'s best extension (all adjacent atoms re-scored, vectorised
        beyond 8 atoms)."""
        plane = self.planes[j]
        b = plane.boundary
        if not b:
            return
        B = np.fromiter(b, dtype=np.int64, count=len(b))
        keep = self.owner[B] == -1
        if not keep.all():
            b.difference_update(B[~keep].tolist())
            B = B[keep]
            if B.size == 0:
                return
        if B.size <= 8:
            best, k, inc = self._best_extension_py(plane, B.tolist())
        else:
            best, k, inc = self._best_extension_np(plane, B)
        heapq.heappush(self.heap, _Extend(best, EXTEND, plane.canon, k, j, plane.version, inc))

    def _best_extension_py(self, plane: _Plane, atoms: list[int]) -> tuple[float, int, float]:
        """``(cost at float32 resolution, atom, e_ext)`` of the cheapest extension by one
        of a few ``atoms`` (ties: the lowest ray index), in Python floats."""
        best, k, true = math.inf, -1, math.inf
        stats, error, atom = plane.stats, plane.error, self.atoms
        for u in atoms:
            inc = _merged_error_py(stats, atom[u]) - error
            qi = _qs(inc)
            if qi < best or (qi == best and u < k):
                best, k, true = qi, u, inc
        return best, k, true

    def _best_extension_np(self, plane: _Plane, B: np.ndarray) -> tuple[float, int, float]:
        """:meth:`_best_extension_py` vectorised over the atoms ``B [n]`` (NumPy)."""
        W1, x1, y1, z1, c00, c01, c02, c11, c12, c22 = plane.stats
        w = self.aw[B]
        Wn = W1 + w
        f = w / Wn
        g = W1 * f
        dx, dy, dz = self.ax[B] - x1, self.ay[B] - y1, self.az[B] - z1
        e = _stats_error_cols(
            Wn,
            x1 + dx * f,
            y1 + dy * f,
            z1 + dz * f,
            c00 + g * dx * dx,
            c01 + g * dx * dy,
            c02 + g * dx * dz,
            c11 + g * dy * dy,
            c12 + g * dy * dz,
            c22 + g * dz * dz,
        )
        inc = e - plane.error
        qi = _q(inc)
        best = float(qi.min())
        tie = np.flatnonzero(qi == best)
        i = tie[np.argmin(B[tie])]
        return best, int(B[i]), float(inc[i])

    def _push_merge(self, j: int) -> None:
        """Push plane ``j``'s best merge over all adjacent planes."""
        plane = self.planes[j]
        if not plane.adjacent:
            return
        sj, ej, cj = plane.stats, plane.error, plane.canon
        planes = self.planes
        best = None
        for q in plane.adjacent:
            other = planes[q]
            c = _merged_error_py(sj, other.stats) - ej - other.error
            cq = other.canon
            qc = _qs(c)
            key = (qc, MERGE, cj, cq) if cj < cq else (qc, MERGE, cq, cj)
            if best is None or key < best[0]:
                best = (key, q, c)
        key, q, c = best
        entry = _Merge(*key, j, q, plane.version, self.planes[q].version, c)
        heapq.heappush(self.heap, entry)
