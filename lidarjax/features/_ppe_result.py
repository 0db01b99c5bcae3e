"""The result of PPE (dissertation ch. 11): the step kinds, the stop reasons
(:class:`PPEStop`) and :class:`PlaneSegmentation`, built from the greedy loop's final
partition of the rays by :func:`_segmentation` (plane parameters from the clustering
statistics, optionally refitted on the exact ray-path error).
"""

from __future__ import annotations

import dataclasses
import enum
import math
from typing import NamedTuple

import numpy as np

from ._plane_fit import _refit
from ._plane_stats import _points_stats, _stats_error, _stats_plane

__all__ = ["PPEStop", "PlaneSegmentation"]

# Step kinds of the greedy loop (the values of PlaneSegmentation.step_kinds; also the
# second key of the greedy order: on equal increments create < extend < merge).
CREATE, EXTEND, MERGE = 0, 1, 2


class PPEStop(enum.Enum):
    """Why the greedy loop of :func:`extract_planes` stopped (:attr:`PlaneSegmentation.stop`).

    Attributes:
        MAX_PLANES: the number of planes (regular + remaining atoms) reached ``max_planes``.
        MAX_INCREMENT: the cheapest action's increment exceeded ``max_increment``.
        EXHAUSTED: no action was left (every connected region is one plane).
    """

    MAX_PLANES = "max_planes"
    MAX_INCREMENT = "max_increment"
    EXHAUSTED = "exhausted"


@dataclasses.dataclass(frozen=True)
class PlaneSegmentation:
    """Result of :func:`extract_planes` (``J`` planes, ``S`` greedy steps).

    Attributes:
        labels: ``[H, W]`` plane index per ray, ``-1`` where the ray is on no regular plane
            (unclustered atoms, planes below ``min_points``, no-return rays). Planes are
            numbered by their first ray in row-major order.
        normals: ``[J, 3]`` unit normals (pointing away from the sensor).
        supports: ``[J, 3]`` the point of each plane closest to the sensor (m).
        sizes: ``[J]`` rays per plane.
        errors: ``[J]`` exact ray-path error ``E`` (Eq. 11.2) of each plane after the exact
            refit, m² (the linearised error if ``refit=False``).
        linear_errors: ``[J]`` the clustering (linearised) error of each plane, m².
        step_kinds: ``[S]`` 0 = create, 1 = extend, 2 = merge.
        step_costs: ``[S]`` the error increment of every step (m²), in order.
        stop: why the loop stopped, a :class:`PPEStop`.
        n_atoms: unclustered valid rays left when the loop stopped.
        n_small: planes dropped because they had fewer than ``min_points`` rays.
    """

    labels: np.ndarray
    normals: np.ndarray
    supports: np.ndarray
    sizes: np.ndarray
    errors: np.ndarray
    linear_errors: np.ndarray
    step_kinds: np.ndarray
    step_costs: np.ndarray
    stop: PPEStop
    n_atoms: int
    n_small: int

    @property
    def n_planes(self) -> int:
        """Number of planes ``J`` returned (regular planes with at least ``min_points`` rays)."""
        return int(self.sizes.shape[0])

    @property
    def rmse(self) -> float:
        """``sqrt(Σ_j E_j / Σ_j |Q_j|)``: RMS ray-path error over the rays on planes (m)."""
        n = int(self.sizes.sum())
        return float(np.sqrt(self.errors.sum() / n)) if n else math.nan


class _Partition(NamedTuple):
    """The greedy loop's state at a stop: what :func:`_segmentation` turns into a result.

    Attributes:
        members: the flat ray indices of every regular plane (any order).
        kinds: the step kinds so far (``CREATE``, ``EXTEND``, ``MERGE``).
        costs: the error increment of every step so far (m²).
        stop: why the loop stopped.
        n_atoms: unclustered valid rays.
    """

    members: list[np.ndarray]
    kinds: list[int]
    costs: list[float]
    stop: PPEStop
    n_atoms: int


def _segmentation(
    pts: np.ndarray, valid: np.ndarray, part: _Partition, min_points: int, refit: bool
) -> PlaneSegmentation:
    """The :class:`PlaneSegmentation` of a partition of the scan ``pts [H, W, 3]``:
    planes with at least ``min_points`` rays, numbered by their first ray, with their
    clustering planes and errors (and the exact refit if ``refit``)."""
    H, W = valid.shape
    members = [np.sort(m) for m in part.members]
    big = [m for m in members if m.size >= min_points]
    n_small = len(members) - len(big)
    big.sort(key=lambda m: int(m[0]))
    labels = np.full(H * W, -1, dtype=np.int64)
    for j, m in enumerate(big):
        labels[m] = j
    flat = pts.reshape(-1, 3)
    J = len(big)
    sizes = np.array([m.size for m in big], dtype=np.int64)
    if J:
        stats = [_points_stats(flat[m]) for m in big]
        Ws = np.array([s[0] for s in stats])
        ms = np.stack([s[1] for s in stats])
        Cs = np.stack([s[2] for s in stats])
        lin = _stats_error(Ws, ms, Cs)
        supports, normals = _stats_plane(Ws, ms, Cs)
        errors = lin.copy()
        if refit:
            supports, normals, errors = _refit(flat, big)
    else:
        lin = errors = np.zeros(0)
        supports = normals = np.zeros((0, 3))
    return PlaneSegmentation(
        labels=labels.reshape(H, W),
        normals=normals,
        supports=supports,
        sizes=sizes,
        errors=errors,
        linear_errors=lin,
        step_kinds=np.asarray(part.kinds, dtype=np.int8),
        step_costs=np.asarray(part.costs, dtype=np.float64),
        stop=part.stop,
        n_atoms=int(part.n_atoms),
        n_small=n_small,
    )
