"""Loop closures for decay-rate SLAM: scans matched against the map of an earlier visit.

For scan ``i``, the candidates are earlier scans ``j <= i - min_separation`` whose
estimated positions lie within ``radius_m``; the nearest ``max_candidates`` (at least
``min_separation`` apart in index) are tried. Scan ``i`` is matched (coarse to fine,
:func:`~lidarjax.slam.match_scan`) against the decay-rate map of scans
``j - submap_half .. j + submap_half`` from a grid of start poses around the estimated
relative pose; the match starts with an exhaustive end-point search of
``search_xy_m`` x ``search_yaw_rad`` around the estimate
(:func:`~lidarjax.slam.correlative_search`), so a drifted estimate still finds the
right basin. The best match is accepted when

* at least ``min_used_fraction`` of the rays lie in the mapped part of the submap,
* its mean log-likelihood per used ray is at least ``min_mean_log_likelihood`` nats,
* the translation is constrained in every direction (smallest eigenvalue of the
  translation information at least ``min_information`` per ray, 1/m^2): a scan in a
  corridor slides along it, and such a "closure" is rejected,
* the correction from the estimate is at most ``max_correction_m``,
* the search's best score beats the best lattice pose farther than ``exclude_m`` from it
  by at least ``min_margin`` nats (a second, equally good place is ambiguity),
* with several start poses, at least two end within ``agree_m`` of the best match.

Accepted closures become relative-pose factors ``pose_j^-1 pose_i`` for the pose graph.

:func:`find_revisits` pairs the same candidates without matching: a pair is kept when,
at the given poses, the scan's end points lie on the submap's (the front end put both
visits on the same walls), and its factor is the front end's own relative pose. The
pose graph needs these where it down-weights the front end's increments (see
:class:`~lidarjax.slam.SlamConfig`): a whole-map front end corrects its drift at a
revisit in one increment, and without a factor across the loop that correction is lost.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ._front_end import FrontEndConfig, GridMap, between_np, compose_np, match_scan

__all__ = ["LoopConfig", "Loops", "find_loops", "find_revisits"]


@dataclasses.dataclass(frozen=True)
class LoopConfig:
    """Settings of the loop search (see the module docstring).

    Attributes:
        radius_m: candidate radius around the estimate (m).
        min_separation: index distance between a scan and its candidates.
        max_candidates: candidates tried per scan.
        submap_half: the submap holds scans ``j - submap_half .. j + submap_half``.
        start_offsets_m: the start poses are the estimate and (if > 0) the estimate shifted
            by this along +-x and +-y (m).
        start_offsets_rad: ... and turned by +- this (rad).
        min_used_fraction: see module docstring.
        min_mean_log_likelihood: nats per used ray.
        min_information: 1/m^2 per used ray.
        max_correction_m: largest accepted correction of the estimate (m).
        every: try every ``every``-th scan (1: all).
        agree_m: with several starts, at least two must end within this distance (m) of
            the best match (a basin only one start finds is rejected).
        search_xy_m, search_yaw_rad: half widths of the exhaustive search around each
            start (m, rad; 0 and 0: none).
        exclude_m: the search's runner-up is its best pose farther than this (m).
        min_margin: least margin (nats) of the search's best score over the runner-up.
    """

    radius_m: float = 4.0
    min_separation: int = 30
    max_candidates: int = 1
    submap_half: int = 5
    start_offsets_m: float = 0.0
    start_offsets_rad: float = 0.0
    min_used_fraction: float = 0.6
    min_mean_log_likelihood: float = 0.5
    min_information: float = 20.0
    max_correction_m: float = 3.0
    every: int = 2
    agree_m: float = 0.05
    search_xy_m: float = 1.0
    search_yaw_rad: float = 0.2
    exclude_m: float = 0.3
    min_margin: float = 15.0

    def __post_init__(self):
        for name in ("radius_m", "max_correction_m", "agree_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be positive and finite, got {v!r}")
        for name in ("min_separation", "max_candidates", "every"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise ValueError(f"{name} must be a positive int, got {v!r}")
        if (
            isinstance(self.submap_half, bool)
            or not isinstance(self.submap_half, int)
            or (self.submap_half < 0)
        ):
            raise ValueError(f"submap_half must be an int >= 0, got {self.submap_half!r}")
        if self.min_separation <= 2 * self.submap_half:
            raise ValueError("min_separation must exceed 2 * submap_half")
        for name in (
            "start_offsets_m",
            "start_offsets_rad",
            "min_information",
            "search_xy_m",
            "search_yaw_rad",
            "exclude_m",
            "min_margin",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
        if not (0 <= self.min_used_fraction <= 1):
            raise ValueError(f"min_used_fraction must be in [0, 1], got {self.min_used_fraction}")


@dataclasses.dataclass(frozen=True)
class Loops:
    """Accepted loop closures.

    Attributes:
        edges: ``[L 2]`` int pairs ``(j, i)``, ``j < i``.
        measurements: ``[L 3]`` relative poses ``pose_j^-1 pose_i`` ``(x m, y m, yaw rad)``.
        n_tried: candidate pairs matched.
    """

    edges: np.ndarray
    measurements: np.ndarray
    n_tried: int


def _starts(cfg: LoopConfig) -> np.ndarray:
    """The estimate, the estimate shifted by ``start_offsets_m`` along +-x and +-y, and
    turned by ``+-start_offsets_rad``."""
    o, a = cfg.start_offsets_m, cfg.start_offsets_rad
    s = [(0.0, 0.0, 0.0)]
    if o > 0:
        s += [(o, 0.0, 0.0), (-o, 0.0, 0.0), (0.0, o, 0.0), (0.0, -o, 0.0)]
    if a > 0:
        s += [(0.0, 0.0, a), (0.0, 0.0, -a)]
    return np.array(s)


def _candidates(poses: np.ndarray, i: int, cfg: LoopConfig) -> list[int]:
    """Scan ``i``'s loop candidates: the nearest ``cfg.max_candidates`` earlier scans
    ``j <= i - min_separation`` within ``radius_m``, pairwise ``min_separation`` apart."""
    d = np.hypot(*(poses[: i - cfg.min_separation + 1, :2] - poses[i, :2]).T)
    chosen: list[int] = []
    for j in np.argsort(d):
        if d[j] > cfg.radius_m or len(chosen) == cfg.max_candidates:
            break
        if all(abs(j - c) >= cfg.min_separation for c in chosen):
            chosen.append(int(j))
    return chosen


def _check_scans(rng: np.ndarray, az: np.ndarray, poses: np.ndarray) -> None:
    if rng.ndim != 2:
        raise ValueError(f"ranges_m must be an [N, B] array, got shape {rng.shape}")
    n = rng.shape[0]
    if poses.shape != (n, 3) or not np.all(np.isfinite(poses)):
        raise ValueError(f"poses must be a finite [{n}, 3] array, got {poses.shape}")
    if az.shape != (rng.shape[1],) or not np.all(np.isfinite(az)):
        raise ValueError(f"azimuths_rad must be a finite [{rng.shape[1]}] array, got {az.shape}")


def find_revisits(
    ranges_m: np.ndarray,
    azimuths_rad: np.ndarray,
    poses: np.ndarray,
    cfg: LoopConfig | None = None,
    *,
    range_cap_m: float = 10.0,
    cell_m: float = 0.1,
    min_overlap: float = 0.5,
) -> Loops:
    """Pairs of scans an estimate puts on the same walls (module docstring).

    The candidates are :func:`find_loops`'s (``cfg.radius_m``, ``min_separation``,
    ``max_candidates``, ``every``). A pair ``(j, i)`` is kept when at least
    ``min_overlap`` of scan ``i``'s end points (readings below ``range_cap_m``, placed
    at ``poses[i]``) fall in a cell of side ``cell_m``, or one of its 8 neighbours, that
    holds an end point of scans ``j - submap_half .. j + submap_half`` (at their poses).
    Nothing is matched: the measurement is ``poses[j]^-1 poses[i]`` itself.

    Args:
        ranges_m: ``[N B]`` readings (m).
        azimuths_rad: ``[B]`` beam angles (rad).
        poses: ``[N 3]`` the estimate ``(x m, y m, yaw rad)`` (e.g. the front end's).
        cfg: candidate settings (:class:`LoopConfig`).
        range_cap_m: readings at or beyond are no-returns (m).
        cell_m: cell side of the overlap test (m).
        min_overlap: least fraction of scan ``i``'s end points on the submap's.

    Returns:
        :class:`Loops` (``n_tried``: candidate pairs tested).
    """
    cfg = LoopConfig() if cfg is None else cfg
    for name, v in (("range_cap_m", range_cap_m), ("cell_m", cell_m)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be a positive finite number, got {v!r}")
    if isinstance(min_overlap, bool) or not (
        isinstance(min_overlap, (int, float)) and 0 < min_overlap <= 1
    ):
        raise ValueError(f"min_overlap must be in (0, 1], got {min_overlap!r}")
    rng = np.asarray(ranges_m, float)
    az = np.asarray(azimuths_rad, float)
    poses = np.asarray(poses, float)
    _check_scans(rng, az, poses)
    if np.any(np.isnan(rng)) or np.any(rng < 0):
        raise ValueError("ranges_m must be >= 0 and not NaN")
    n = rng.shape[0]
    hit = rng < range_cap_m
    ang = poses[:, 2:3] + az
    ex = poses[:, 0:1] + np.where(hit, rng, 0.0) * np.cos(ang)
    ey = poses[:, 1:2] + np.where(hit, rng, 0.0) * np.sin(ang)
    # end points in cells, as int64 keys ix * 2**22 + iy (1 <= ix, iy < 2**21)
    ix = np.floor((ex - ex.min()) / cell_m).astype(np.int64) + 1
    iy = np.floor((ey - ey.min()) / cell_m).astype(np.int64) + 1
    if max(ix.max(), iy.max()) >= 2**21 - 1:
        raise ValueError(
            f"the end points span more than {(2**21 - 2) * cell_m:.0f} m; split the log or "
            "raise cell_m"
        )
    key = ix * 2**22 + iy
    around = np.array([dx * 2**22 + dy for dx in (-1, 0, 1) for dy in (-1, 0, 1)], np.int64)
    edges = []
    n_tried = 0
    for i in range(cfg.min_separation, n, cfg.every):
        if not hit[i].any():
            continue
        for j in _candidates(poses, i, cfg):
            n_tried += 1
            lo, hi = max(0, j - cfg.submap_half), min(n, j + cfg.submap_half + 1)
            cells = np.unique((key[lo:hi][hit[lo:hi]][:, None] + around).ravel())
            if np.isin(key[i][hit[i]], cells).mean() >= min_overlap:
                edges.append((j, i))
    e = np.asarray(edges, np.int64).reshape(-1, 2)
    return Loops(e, between_np(poses[e[:, 0]], poses[e[:, 1]]).reshape(-1, 3), n_tried)


def find_loops(
    ranges_m: np.ndarray,
    azimuths_rad: np.ndarray,
    poses: np.ndarray,
    cfg: LoopConfig | None = None,
    front_cfg: FrontEndConfig | None = None,
    *,
    progress: bool = False,
) -> Loops:
    """Search loop closures along an estimated trajectory (module docstring).

    Args:
        ranges_m: ``[N B]`` readings (m).
        azimuths_rad: ``[B]`` beam angles (rad).
        poses: ``[N 3]`` estimated poses (e.g. the front end's).
        cfg: loop settings; front_cfg: matching settings (map, blur stages).
        progress: tqdm progress bar.

    Returns:
        :class:`Loops`.
    """
    cfg = LoopConfig() if cfg is None else cfg
    fcfg = FrontEndConfig() if front_cfg is None else front_cfg
    fcfg = dataclasses.replace(
        fcfg,
        search_xy_m=cfg.search_xy_m,
        search_yaw_rad=cfg.search_yaw_rad,
        search_exclude_m=cfg.exclude_m,
    )
    rng = np.asarray(ranges_m, float)
    az = np.asarray(azimuths_rad, float)
    poses = np.asarray(poses, float)
    _check_scans(rng, az, poses)
    n = rng.shape[0]
    starts = _starts(cfg)
    searched = cfg.search_xy_m > 0 or cfg.search_yaw_rad > 0
    edges, meas = [], []
    n_tried = 0
    it = range(cfg.min_separation, n, cfg.every)
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(it, desc="loop closures", unit="scan")
    for i in it:
        for j in _candidates(poses, i, cfg):
            n_tried += 1
            lo, hi = max(0, j - cfg.submap_half), min(n, j + cfg.submap_half + 1)
            # the submap in the frame of scan j
            local = between_np(np.broadcast_to(poses[j], (hi - lo, 3)), poses[lo:hi])
            grid = GridMap(fcfg.resolution_m, fcfg.range_cap_m)
            for k in range(hi - lo):
                grid.add_scan(local[k], az, rng[lo + k])
            guess = between_np(poses[j], poses[i])
            matches = [
                match_scan(
                    grid, az, rng[i], compose_np(guess, s), fcfg, prior_xy_yaw=compose_np(guess, s)
                )
                for s in starts
            ]
            best = max(matches, key=lambda m: m.mean_log_likelihood * m.n_used)
            # the optimum must attract more than one start (a lone basin is a guess)
            agree = sum(np.hypot(*(m.pose[:2] - best.pose[:2])) <= cfg.agree_m for m in matches)
            used = best.n_used / az.shape[0]
            info = best.min_translation_information / max(best.n_used, 1)
            corr = np.hypot(*(best.pose[:2] - guess[:2]))
            margin = best.search_score - best.search_runner_up
            if (
                used >= cfg.min_used_fraction
                and best.mean_log_likelihood >= cfg.min_mean_log_likelihood
                and info >= cfg.min_information
                and corr <= cfg.max_correction_m
                and (agree >= 2 or len(matches) == 1)
                and (not searched or margin >= cfg.min_margin)
                and best.plausible
            ):
                edges.append((j, i))
                meas.append(best.pose)
    e = np.asarray(edges, np.int64).reshape(-1, 2)
    return Loops(e, np.asarray(meas, float).reshape(-1, 3), n_tried)
