"""Plane-segmentation metrics of dissertation chapter 11 (NumPy only).

- :func:`hoover_scores`: the region classification of Hoover et al., "An experimental
  comparison of range image segmentation algorithms", IEEE PAMI 18(7), 1996 (correct
  detection, over-segmentation, under-segmentation, missed, noise), the mean angular
  error between adjacent correctly detected planes, the fraction ``f`` of correctly
  detected ground-truth planes, and ``k`` of Eq. (11.5).
- :func:`k_value`: Eq. (11.5), the fraction of ground-truth points that lie in correctly
  detected planes.
- :func:`segmentation_rmse`: Eq. (11.6), the RMSE of the ray-path errors of the rays
  assigned to the extracted planes.

Label conventions (organized scans give label images ``[H W]``; flat ``[K]`` works too):

- ground truth: an integer ``>= min_gt_label`` (default 1: every positive label) is a
  ground-truth plane; a smaller value (``0``, negative, or a positive label below
  ``min_gt_label``) marks an unlabelled point (no return, clutter, a non-plane class) that
  is excluded from all counting. Which labels are planes depends on the benchmark:

  - scans from :func:`lidarjax.sim.simulate_synpeb_scan` / ``synpeb_scan`` (and PCD
    files written from them with ``write_synpeb_pcd``) label every face a plane, ``1..P``
    (room faces ``1..6``, objects from ``7``), ``0`` = no return: use the default ``1``;
  - the published SynPEB files (e.g. the shared crop ``synpeb/test_100.pcd``, read with
    ``load_synpeb_pcd``) number their planes from 10; the authors' evaluation
    (acschaefer/ppe, ``evalexp.m``) counts only labels ``>= 10`` as ground-truth planes
    (the crop's label 3 is a 20-ray sliver between two planes, not a plane): pass
    ``min_gt_label=10`` there.
- prediction: a non-negative integer is an extracted plane; a negative value (``-1``) marks
  a point not assigned to any plane.

Region sizes. ``M_m`` is the number of points of ground-truth region ``m``. ``P_n`` counts
the points of machine region ``n`` that fall on labelled ground-truth points (the usual
choice: nothing can be said about points whose truth is unknown); a machine region with no
such point is ignored altogether. ``count_unlabelled=True`` instead counts every point of
the machine region, which is what the dissertation authors' evaluation code does (their
``P_n`` is the size of the extracted plane's index set); there a region lying entirely on
unlabelled points is noise.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "HooverScores",
    "hoover_scores",
    "k_value",
    "segmentation_rmse",
]

# Relative slack of the threshold comparisons, so that an overlap of exactly T * size
# counts even when T * size is not representable (0.7 * 10 = 7.000000000000001).
_REL_TOL = 1e-12


@dataclass(frozen=True, eq=False)
class HooverScores:
    """Result of :func:`hoover_scores`.

    Attributes:
        threshold: the tolerance ``T`` used.
        n_gt: number of ground-truth regions (distinct labels ``>= min_gt_label``).
        n_pred: number of machine regions taking part (see the module docstring).
        n_correct: number of correct detections (one-to-one pairs).
        n_over: number of over-segmented ground-truth regions.
        n_under: number of under-segmenting machine regions.
        n_missed: number of missed ground-truth regions.
        n_noise: number of noise (spurious) machine regions.
        correct_pairs: ``[n_correct 2]`` int, ``(gt label, pred label)`` of each correct
            detection, sorted by ground-truth label.
        over_segmented: ``[n_over]`` ground-truth labels that are over-segmented.
        under_segmenting: ``[n_under]`` machine labels that under-segment.
        missed: ``[n_missed]`` ground-truth labels that are missed.
        noise: ``[n_noise]`` machine labels that are noise.
        f: ``n_correct / n_gt``, the fraction of correctly segmented planes (``nan`` if
            there is no ground-truth region).
        k: Eq. (11.5), the fraction of labelled ground-truth points that belong to a
            correctly detected ground-truth plane (``nan`` if no point is labelled).
        angle_deg: mean absolute difference (degrees) between the angle of adjacent
            ground-truth plane pairs and the angle of their matched machine planes, over
            the pairs whose members are both correctly detected; ``nan`` if there is no
            such pair or no normals were given.
        n_angle_pairs: number of pairs averaged in ``angle_deg``.
    """

    threshold: float
    n_gt: int
    n_pred: int
    n_correct: int
    n_over: int
    n_under: int
    n_missed: int
    n_noise: int
    correct_pairs: np.ndarray
    over_segmented: np.ndarray
    under_segmenting: np.ndarray
    missed: np.ndarray
    noise: np.ndarray
    f: float
    k: float
    angle_deg: float
    n_angle_pairs: int


def _int_labels(labels: Any, name: str) -> np.ndarray:
    a = np.asarray(labels)
    if a.dtype == np.bool_ or not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{name} must be an integer label array, got dtype {a.dtype}")
    return a


def _check_threshold(threshold: float) -> float:
    t = float(threshold)
    if not (0.5 < t <= 1.0):
        raise ValueError(f"threshold must satisfy 0.5 < threshold <= 1, got {threshold!r}")
    return t


def _at_least(overlap: np.ndarray, threshold: float, size: np.ndarray) -> np.ndarray:
    """``overlap >= threshold * size`` with a relative slack of ``_REL_TOL``."""
    return overlap >= threshold * size * (1.0 - _REL_TOL)


@dataclass(frozen=True)
class _Contingency:
    gt_ids: np.ndarray  # [m] ground-truth plane labels (>= min_gt_label)
    pred_ids: np.ndarray  # [n] machine labels taking part
    overlap: np.ndarray  # [m n] O_mn
    gt_size: np.ndarray  # [m] M_m
    pred_size: np.ndarray  # [n] P_n
    n_labelled: int  # K, number of labelled ground-truth points


def _check_min_gt_label(min_gt_label) -> int:
    if (
        isinstance(min_gt_label, bool)
        or not isinstance(min_gt_label, (int, np.integer))
        or min_gt_label < 1
    ):
        raise ValueError(f"min_gt_label must be an integer >= 1, got {min_gt_label!r}")
    return int(min_gt_label)


def _contingency(
    gt: np.ndarray, pred: np.ndarray, count_unlabelled: bool, min_gt_label: int = 1
) -> _Contingency:
    gt = gt.ravel()
    pred = pred.ravel()
    gt_ok = gt >= min_gt_label
    pred_ok = pred >= 0
    gt_ids, gt_idx = np.unique(gt[gt_ok], return_inverse=True)
    pred_mask = pred_ok if count_unlabelled else pred_ok & gt_ok
    pred_ids, pred_idx = np.unique(pred[pred_mask], return_inverse=True)
    n_gt, n_pred = gt_ids.size, pred_ids.size

    gt_size = np.bincount(gt_idx, minlength=n_gt)
    pred_size = np.bincount(pred_idx, minlength=n_pred)
    both = gt_ok & pred_ok
    # Indices of the points labelled in both images, within each id list.
    gi = np.searchsorted(gt_ids, gt[both])
    pj = np.searchsorted(pred_ids, pred[both])
    overlap = np.bincount(gi * n_pred + pj, minlength=n_gt * n_pred).reshape(n_gt, n_pred)
    return _Contingency(gt_ids, pred_ids, overlap, gt_size, pred_size, int(gt_idx.size))


def _angle_between_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Unsigned angle (deg, in [0, 90]) between the planes with normals ``a``, ``b`` [.. 3]."""
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    dot = np.abs(np.sum(a * b, axis=-1))
    return np.degrees(np.arctan2(cross, dot))


def _lookup_normals(normals: Any, labels: np.ndarray, name: str) -> np.ndarray:
    try:
        out = np.stack([np.asarray(normals[int(lab)], dtype=float) for lab in labels])
    except (KeyError, IndexError) as err:
        raise ValueError(f"{name} has no normal for a matched label: {err}") from None
    if out.shape[1:] != (3,):
        raise ValueError(f"{name} must map each label to a normal of shape [3]")
    if not np.all(np.isfinite(out)) or np.any(np.linalg.norm(out, axis=1) == 0.0):
        raise ValueError(f"{name} must hold finite, non-zero normals")
    return out


def hoover_scores(
    gt_labels: np.ndarray,
    pred_labels: np.ndarray,
    *,
    threshold: float = 0.8,
    gt_normals: Any = None,
    pred_normals: Any = None,
    gt_adjacent: np.ndarray | Sequence[Sequence[int]] | None = None,
    count_unlabelled: bool = False,
    min_gt_label: int = 1,
) -> HooverScores:
    """Hoover et al. (1996) segmentation scores of an extracted plane segmentation.

    With ``O_mn`` the number of points in both ground-truth region ``R_m`` (size ``M_m``)
    and machine region ``R_n`` (size ``P_n``) and the tolerance ``0.5 < T <= 1``:

    - correct detection of ``R_m`` by ``R_n``: ``O_mn >= T P_n`` and ``O_mn >= T M_m``;
    - over-segmentation of ``R_m`` into ``R_n1 .. R_nx`` (``x >= 2``): every
      ``O_mni >= T P_ni`` and ``sum_i O_mni >= T M_m``;
    - under-segmentation of ``R_m1 .. R_mx`` (``x >= 2``) by ``R_n``: every
      ``O_min >= T M_mi`` and ``sum_i O_min >= T P_n``;
    - missed: a ground-truth region in none of these; noise: a machine region in none.

    Precedence: correct detections are decided first, and regions in a correct detection
    take no part in over- or under-segmentations. With ``T > 0.5`` the remaining
    classifications are then mutually exclusive (each machine region is mostly inside at
    most one ground-truth region and vice versa), so every region gets exactly one class.
    The maximal set of parts is used: for ``R_m`` these are all machine regions not in a
    correct detection with ``O_mn >= T P_n`` (adding parts only raises the sum).
    Differences to other implementations: Hoover's SegComp tool and the dissertation
    authors' code resolve a region qualifying for several classes by the largest average
    overlap fraction (so a correct detection plus a small fragment can become an
    over-segmentation), and the authors' code compares with ``>`` instead of ``>=``.
    Region sizes and ``count_unlabelled``: see the module docstring.

    Angle: for each pair in ``gt_adjacent`` whose two ground-truth planes are both
    correctly detected, the angle between the two ground-truth normals and the angle
    between the two matched machine normals are taken as unsigned plane angles,
    ``atan2(|n1 x n2|, |n1 . n2|)`` in ``[0, 90]`` degrees (plane normals have no sign);
    ``angle_deg`` is the mean absolute difference. Pairs not both correctly detected are
    skipped.

    Args:
        gt_labels: ``[H W]`` (or any shape) int ground-truth labels; ``< min_gt_label``
            unlabelled.
        pred_labels: int machine labels of the same shape; ``< 0`` unassigned.
        threshold: the tolerance ``T``, ``0.5 < T <= 1`` (the dissertation uses 0.8).
        gt_normals: indexable by a ground-truth label (an array ``[L 3]`` or a mapping),
            giving a normal ``[3]`` (any length, not zero) of that plane.
        pred_normals: indexable by a machine label, giving a normal ``[3]``.
        gt_adjacent: ``[A 2]`` int, pairs of adjacent ground-truth labels.
        count_unlabelled: count machine-region points on unlabelled ground truth in
            ``P_n`` (the authors' convention) instead of ignoring them.
        min_gt_label: the smallest ground-truth label that is a plane; smaller labels are
            unlabelled points like ``0``. Default 1 (every positive label is a plane: this
            package's SynPEB-style generator); 10 for the published SynPEB files, as in
            the authors' evaluation (module docstring).

    Returns:
        The :class:`HooverScores`.

    Raises:
        ValueError: if the label arrays are not integer or differ in shape, ``threshold``
            is outside ``(0.5, 1]``, only some of ``gt_normals``, ``pred_normals``,
            ``gt_adjacent`` are given, ``gt_adjacent`` is not ``[A 2]`` int, a needed
            normal is missing or degenerate, or ``min_gt_label`` is not an integer >= 1.
    """
    gt = _int_labels(gt_labels, "gt_labels")
    pred = _int_labels(pred_labels, "pred_labels")
    if gt.shape != pred.shape:
        raise ValueError(
            f"gt_labels and pred_labels must have equal shapes, got {gt.shape}, {pred.shape}"
        )
    t = _check_threshold(threshold)
    min_label = _check_min_gt_label(min_gt_label)
    given = [x is not None for x in (gt_normals, pred_normals, gt_adjacent)]
    if any(given) and not all(given):
        raise ValueError("gt_normals, pred_normals and gt_adjacent must be given together")
    adjacent = None
    if gt_adjacent is not None:
        adjacent = np.asarray(gt_adjacent)
        if adjacent.size == 0:
            adjacent = adjacent.reshape(0, 2).astype(int)
        if adjacent.ndim != 2 or adjacent.shape[1] != 2:
            raise ValueError(f"gt_adjacent must have shape [A 2], got {adjacent.shape}")
        if not np.issubdtype(adjacent.dtype, np.integer):
            raise ValueError(f"gt_adjacent must hold integer labels, got {adjacent.dtype}")

    c = _contingency(gt, pred, count_unlabelled, min_label)
    o = c.overlap
    # inside[m, n]: machine region n lies (to fraction T) inside ground-truth region m.
    inside = _at_least(o, t, c.pred_size[None, :])
    # covers[m, n]: machine region n covers (to fraction T) ground-truth region m.
    covers = _at_least(o, t, c.gt_size[:, None])

    correct = inside & covers & (o > 0)
    gt_correct = correct.any(axis=1)
    pred_correct = correct.any(axis=0)
    free = ~gt_correct[:, None] & ~pred_correct[None, :]

    over_parts = inside & free & (o > 0)
    over = (over_parts.sum(axis=1) >= 2) & _at_least(
        np.where(over_parts, o, 0).sum(axis=1), t, c.gt_size
    )
    under_parts = covers & free & (o > 0)
    under = (under_parts.sum(axis=0) >= 2) & _at_least(
        np.where(under_parts, o, 0).sum(axis=0), t, c.pred_size
    )
    gt_in_under = (under_parts & under[None, :]).any(axis=1)
    pred_in_over = (over_parts & over[:, None]).any(axis=0)
    missed = ~(gt_correct | over | gt_in_under)
    noise = ~(pred_correct | under | pred_in_over)

    gi, pj = np.nonzero(correct)
    pairs = np.stack([c.gt_ids[gi], c.pred_ids[pj]], axis=1).astype(np.int64)
    pairs = pairs.reshape(-1, 2)
    n_gt = int(c.gt_ids.size)
    f = float(gi.size / n_gt) if n_gt else float("nan")
    k = float(c.gt_size[gi].sum() / c.n_labelled) if c.n_labelled else float("nan")

    angle, n_angle = float("nan"), 0
    if adjacent is not None and adjacent.shape[0] > 0 and pairs.shape[0] > 0:
        match = dict(zip(pairs[:, 0].tolist(), pairs[:, 1].tolist(), strict=True))
        use = [(a, b) for a, b in adjacent.tolist() if a in match and b in match]
        if use:
            ga, gb = np.array(use).T
            pa = np.array([match[x] for x in ga])
            pb = np.array([match[x] for x in gb])
            ang_gt = _angle_between_deg(
                _lookup_normals(gt_normals, ga, "gt_normals"),
                _lookup_normals(gt_normals, gb, "gt_normals"),
            )
            ang_pred = _angle_between_deg(
                _lookup_normals(pred_normals, pa, "pred_normals"),
                _lookup_normals(pred_normals, pb, "pred_normals"),
            )
            angle, n_angle = float(np.mean(np.abs(ang_gt - ang_pred))), len(use)

    return HooverScores(
        threshold=t,
        n_gt=n_gt,
        n_pred=int(c.pred_ids.size),
        n_correct=int(gi.size),
        n_over=int(over.sum()),
        n_under=int(under.sum()),
        n_missed=int(missed.sum()),
        n_noise=int(noise.sum()),
        correct_pairs=pairs,
        over_segmented=c.gt_ids[over],
        under_segmenting=c.pred_ids[under],
        missed=c.gt_ids[missed],
        noise=c.pred_ids[noise],
        f=f,
        k=k,
        angle_deg=angle,
        n_angle_pairs=n_angle,
    )


def k_value(
    gt_labels: np.ndarray,
    pred_labels: np.ndarray,
    *,
    threshold: float = 0.8,
    count_unlabelled: bool = False,
    min_gt_label: int = 1,
) -> float:
    """Fraction ``k`` of points in correctly segmented planes, Eq. (11.5).

    ``k = sum_j K_hat(l_j) / K``: the sum runs over the extracted planes ``l_j``;
    ``K_hat(l)`` is the number of points of the corresponding ground-truth plane if ``l``
    is a correct detection in the sense of :func:`hoover_scores` (tolerance ``threshold``,
    0.8 in the dissertation) and 0 otherwise; ``K`` is the number of labelled
    ground-truth points. This is the authors' ``fcorrseg`` ("fraction correctly segmented
    points"): ground-truth plane sizes weighted by correct detection, over all labelled
    ground-truth points.

    Args:
        gt_labels: int ground-truth labels; ``< min_gt_label`` unlabelled.
        pred_labels: int machine labels of the same shape; ``< 0`` unassigned.
        threshold: the tolerance ``T``, ``0.5 < T <= 1``.
        count_unlabelled: see :func:`hoover_scores`.
        min_gt_label: the smallest ground-truth plane label, see :func:`hoover_scores`.

    Returns:
        ``k`` in ``[0, 1]``, ``nan`` if no point is labelled.

    Raises:
        ValueError: as :func:`hoover_scores`.
    """
    return hoover_scores(
        gt_labels,
        pred_labels,
        threshold=threshold,
        count_unlabelled=count_unlabelled,
        min_gt_label=min_gt_label,
    ).k


def segmentation_rmse(
    ranges: np.ndarray,
    rhat: np.ndarray,
    pred_labels: np.ndarray,
    *,
    max_plane_rmse_m: float | None = None,
) -> float:
    """RMSE of the ray-path errors of the extracted planes, Eq. (11.6).

    Eq. (11.6) is printed as ``RMSE = sqrt(E(Z, L) / J(L))`` with ``E`` the sum of squared
    ray-path errors ``(r_k - rhat_k)^2`` over the rays assigned to the extracted planes and
    ``J`` the number of planes; read literally that is not an RMSE. The authors'
    evaluation code (acschaefer/ppe, ``matlab/experiments/evalexp.m``) pools the errors of
    all rays assigned to any extracted plane and takes ``sqrt(mean(err^2))``, i.e. the
    denominator is the number of assigned rays. This function implements that reading:

        ``RMSE = sqrt( sum_j sum_{k in Q_j} (r_k - rhat_k)^2 / sum_j |Q_j| )``

    where ``Q_j`` are the rays assigned to plane ``j`` and ``rhat_k`` is the range at which
    ray ``k`` hits plane ``j`` (ray-path error along the beam, not point-to-plane
    distance). All extracted planes take part, correctly detected or not. The authors
    additionally drop planes holding a single point before evaluation and, as an outlier
    guard, any plane whose own RMSE is 10 m or more (``max_plane_rmse_m=10`` reproduces
    the guard).

    Args:
        ranges: ``[...]`` measured ranges (m), e.g. a ``[H W]`` range image; finite on
            assigned rays.
        rhat: ranges (m) at which each ray hits its assigned plane, same shape; finite on
            assigned rays (any value elsewhere).
        pred_labels: int plane labels, same shape; ``< 0`` marks unassigned rays.
        max_plane_rmse_m: if given, planes whose own RMSE is ``>=`` this value (m) are left
            out.

    Returns:
        The RMSE in metres; ``nan`` if no ray is assigned (after the outlier guard).

    Raises:
        ValueError: if the shapes differ, ``pred_labels`` is not integer, an assigned ray
            has a non-finite ``ranges`` or ``rhat``, or ``max_plane_rmse_m`` is not
            positive.
    """
    r = np.asarray(ranges, dtype=float)
    e = np.asarray(rhat, dtype=float)
    lab = _int_labels(pred_labels, "pred_labels")
    if not r.shape == e.shape == lab.shape:
        raise ValueError(
            f"ranges, rhat and pred_labels must have equal shapes, got "
            f"{r.shape}, {e.shape}, {lab.shape}"
        )
    if max_plane_rmse_m is not None and not float(max_plane_rmse_m) > 0.0:
        raise ValueError(f"max_plane_rmse_m must be positive, got {max_plane_rmse_m!r}")
    use = lab >= 0
    if not np.all(np.isfinite(r[use])):
        raise ValueError("ranges must be finite on rays assigned to a plane")
    if not np.all(np.isfinite(e[use])):
        raise ValueError("rhat must be finite on rays assigned to a plane")
    sq = (r[use] - e[use]) ** 2
    ids, idx = np.unique(lab[use], return_inverse=True)
    sse = np.bincount(idx, weights=sq, minlength=ids.size)
    count = np.bincount(idx, minlength=ids.size)
    if max_plane_rmse_m is not None:
        keep = np.sqrt(sse / np.maximum(count, 1)) < float(max_plane_rmse_m)
        sse, count = sse[keep], count[keep]
    n = int(count.sum())
    if n == 0:
        return float("nan")
    return float(np.sqrt(sse.sum() / n))
