"""A straightforward PPE (dissertation ch. 11, Algorithm 2) to test the fast one against.

:func:`extract_planes_reference` re-evaluates every action from scratch each step with the
weighted normal equations of its rays (no statistics carried between steps) and applies
the least one under the same tie rule as :func:`lidarjax.features.extract_planes`. Private:
the tests and ``benchmarks/planes.py`` import it from here.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from jaxtyping import ArrayLike, Float

from ._ppe_result import (
    CREATE,
    EXTEND,
    MERGE,
    PlaneSegmentation,
    PPEStop,
    _Partition,
    _segmentation,
)
from ._ppe_scan import _check_inputs, _neighbours, _qs, _tetromino_table
from ._ppe_threshold import _resolve_increment

__all__ = ["extract_planes_reference"]


def _ref_error(point_sets: list[np.ndarray]) -> np.ndarray:
    """Minimised linearised errors of ray sets from the weighted normal equations."""
    out = np.zeros(len(point_sets))
    for i, p in enumerate(point_sets):
        r2 = np.einsum("ki,ki->k", p, p)
        M = (p * r2[:, None]).T @ p
        b = p.T @ r2
        a = np.linalg.pinv(M, rcond=1e-13) @ b
        out[i] = float(np.sum(r2 * (p @ a - 1.0) ** 2))
    return out


def extract_planes_reference(
    points: Float[ArrayLike, "H W 3"],
    *,
    max_increment: float | str | None = "auto",
    max_planes: int | None = None,
    max_distance_m: float | None = None,
    min_points: int = 4,
    refit: bool = False,
    callback: Callable[[int, float, np.ndarray], None] | None = None,
) -> PlaneSegmentation:
    """A straightforward PPE for testing :func:`extract_planes` on small scans.

    Every step enumerates every possible action (all free tetrominoes, every regular plane
    with every adjacent atom, every adjacent plane pair), scores each from scratch with
    the weighted normal equations of its rays (no statistics are carried between steps),
    and applies the least one under the same tie rule. ``O(K)`` fits per step: use it on
    scans of a few hundred rays only. Arguments as in
    :func:`lidarjax.features.extract_planes`;
    ``callback(kind, cost, owner)`` is called after every step.
    """
    inc = _resolve_increment(points, max_increment, max_planes)
    pts, valid, prm = _check_inputs(points, inc, max_planes, max_distance_m, min_points)
    H, W = valid.shape
    K = H * W
    flat = np.where(valid[..., None], pts, 0.0).reshape(K, 3)
    nbr = _neighbours(pts, valid, prm.max_distance_m)
    anchors, shape_ids, cells = _tetromino_table(valid, nbr)
    tcost = _ref_error([flat[c] for c in cells])
    owner = np.full(K, -1, dtype=np.int64)
    owner[~valid.ravel()] = -2
    planes: dict[int, list[int]] = {}
    next_id = 0
    kinds: list[int] = []
    costs: list[float] = []
    stop = PPEStop.EXHAUSTED
    while True:
        n_atoms = int((owner == -1).sum())
        if prm.max_planes and len(planes) + n_atoms <= prm.max_planes:
            stop = PPEStop.MAX_PLANES
            break
        cands: list[tuple] = []
        free = (owner[cells] == -1).all(axis=1)
        for t in np.flatnonzero(free):
            c = float(tcost[t])
            cands.append((_qs(c), CREATE, int(anchors[t]), int(shape_ids[t]), c, t))
        for j, mem in planes.items():
            base = _ref_error([flat[mem]])[0]
            adj_atoms = sorted({u for k in mem for u in nbr[k] if u >= 0 and owner[u] == -1})
            errs = _ref_error([flat[mem + [u]] for u in adj_atoms])
            cj = min(mem)
            for u, e in zip(adj_atoms, errs):
                c = float(e - base)
                cands.append((_qs(c), EXTEND, cj, u, c, j))
            adj_planes = sorted(
                {int(owner[u]) for k in mem for u in nbr[k] if u >= 0 and owner[u] >= 0} - {j}
            )
            for q in adj_planes:
                if q < j:
                    continue
                mq = planes[q]
                e = _ref_error([flat[mem + mq], flat[mq]])
                cq = min(mq)
                c = float(e[0] - base - e[1])
                cands.append((_qs(c), MERGE, min(cj, cq), max(cj, cq), c, j, q))
        if not cands:
            break
        best = min(cands, key=lambda c: c[:4])
        cost, kind, true = best[0], best[1], best[4]
        if cost > prm.max_increment:
            stop = PPEStop.MAX_INCREMENT
            break
        if kind == CREATE:
            cl = cells[best[5]].tolist()
            planes[next_id] = cl
            owner[cl] = next_id
            next_id += 1
        elif kind == EXTEND:
            planes[best[5]].append(best[3])
            owner[best[3]] = best[5]
        else:
            j, q = best[5], best[6]
            planes[j] = planes[j] + planes.pop(q)
            owner[planes[j]] = j
        kinds.append(kind)
        costs.append(true)
        if callback is not None:
            callback(kind, true, owner.copy())
    members = [np.asarray(m, dtype=np.int64) for m in planes.values()]
    part = _Partition(members, kinds, costs, stop, int((owner == -1).sum()))
    return _segmentation(pts, valid, part, min_points, refit)
