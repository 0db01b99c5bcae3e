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
* its mean log-likelihood per used ray is at least :func:`loop_threshold` nats: the
  matching model's own threshold (``min_mean_log_likelihood``, by default
  :data:`MIN_MEAN_LOG_LIKELIHOOD`: the two models' log-likelihoods are on different
  scales), lowered to the log's own level less ``scene_margin`` where the log's scans fit
  even their own neighbourhoods worse (:func:`scene_log_likelihood`: a hall whose walls
  lie beyond the range cap scores lower than an office at every pose, the true one
  included; the wide search below keeps the model's threshold),
* the translation is constrained in every direction (smallest eigenvalue of the
  translation information at least ``min_information`` per ray, 1/m^2): a scan in a
  corridor slides along it, and such a "closure" is rejected,
* the correction from the estimate is at most ``max_correction_m``,
* the search's best score beats the best lattice pose farther than ``exclude_m`` from it
  by at least ``min_margin`` nats (a second, equally good place is ambiguity),
* with several start poses, at least two end within ``agree_m`` of the best match.

A candidate whose match fails these tests gets a second chance (``wide_search_xy_m``):
a coarse search over a window of metres, for an estimate that has drifted beyond the
local search, and the same match from its best pose. With ``far_radius_m`` (off by
default), a scan with no candidate within ``radius_m`` gets the nearest earlier scan
within ``far_radius_m`` (and within the drift bound) as a candidate for that wide search
alone: a long corridor lets the estimate drift along it by more than ``radius_m``, so its
revisits have no candidate otherwise.

Accepted closures become relative-pose factors ``pose_j^-1 pose_i`` for the pose graph.

:func:`find_revisits` pairs the same candidates without matching: a pair is kept when,
at the given poses, the scan's end points lie on the submap's (the front end put both
visits on the same walls), and its factor is the front end's own relative pose. The
pose graph needs these where it down-weights the front end's increments (see
:class:`~lidarjax.slam.SlamConfig`): a whole-map front end corrects its drift at a
revisit in one increment, and without a factor across the loop that correction is lost.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import types

import jax.numpy as jnp
import numpy as np

from ..maps import blur
from ._front_end import (
    FrontEndConfig,
    GridMap,
    between_np,
    compose_np,
    grid_map,
    match_scan,
    score_scan,
)
from ._search import correlative_search

__all__ = [
    "MIN_MEAN_LOG_LIKELIHOOD",
    "SCENE_MARGIN",
    "LoopConfig",
    "Loops",
    "find_loops",
    "find_revisits",
    "loop_threshold",
    "scene_log_likelihood",
]

#: Default least mean log-likelihood per used ray (nats) of an accepted loop closure, per
#: matching model (:attr:`FrontEndConfig.model`). The end-point model scores the log of the
#: hit indicator (1 in cells with a hit) blurred by half a cell, at most 0 nats per ray,
#: where the decay-rate model scores log rates of up to about 3-4 nats (rates of 20-40 per
#: m in 0.05 m cells) less the free-space term. Its threshold accepts the same share of the
#: candidates that pass every other test: on the shared logs' front ends (intel drift seed
#: 0, fhw seed 1, every fourth scan) the decay-rate threshold accepts 86 % and 87 %, the
#: end-point one 86 % and 83 % (at 0.5 nats, as the decay-rate model, it accepted none).
MIN_MEAN_LOG_LIKELIHOOD = types.MappingProxyType({"decay_rate": 0.5, "endpoint": -1.5})

#: Default :attr:`LoopConfig.scene_margin` per matching model (nats per used ray; None:
#: the threshold is not lowered). The decay-rate model's 0.5 nats was set on intel and fhw,
#: and fhw's level (:func:`scene_log_likelihood`, drift seed 0's front end) is 1.06 nats:
#: a margin of 0.5 keeps it. The end-point model's threshold already accepts 55-57 loop
#: closures on acapulco (the decay-rate model's 13-25), and its levels were not studied.
SCENE_MARGIN = types.MappingProxyType({"decay_rate": 0.5, "endpoint": None})


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
        min_mean_log_likelihood: nats per used ray (None: the matching model's default,
            :data:`MIN_MEAN_LOG_LIKELIHOOD`).
        scene_margin: the loop test's threshold is lowered to the log's own level
            (:func:`scene_log_likelihood` along the searched estimate) less this (nats
            per ray) where that is lower; see :func:`loop_threshold` (None: the matching
            model's default, :data:`SCENE_MARGIN`).
        scene_samples: scans the level is the median over (spread evenly along the
            log); 0: the threshold is never lowered.
        min_information: 1/m^2 per used ray.
        max_correction_m: largest accepted correction of the estimate (m).
        every: try every ``every``-th scan (1: all).
        agree_m: with several starts, at least two must end within this distance (m) of
            the best match (a basin only one start finds is rejected).
        search_xy_m, search_yaw_rad: half widths of the exhaustive search around each
            start (m, rad; 0 and 0: none).
        exclude_m: the search's runner-up is its best pose farther than this (m).
        min_margin: least margin (nats) of the search's best score over the runner-up.
        wide_search_xy_m, wide_search_yaw_rad: where the match is rejected, a second
            chance for a drifted estimate: a coarse end-point search of this half width
            (m, rad) around the estimate (:func:`_wide_search`: rates max-pooled to
            ``wide_cell_m`` cells, ``wide_step_yaw_rad`` heading steps, no prior), and
            the match again from its best pose. Tried only where the drift bound
            (``wide_drift_per_m``) exceeds the local search. Accepted with the same tests
            (all but ``max_correction_m``; the model's mean log-likelihood threshold,
            never the scene's lower one: on acapulco, drift seed 1, such a match 4.7 m
            off at -0.54 nats per ray passed the scene's -0.70, where the true relative
            pose scored 2.69 but left 41 % of the rays in unmapped space), if the
            coarse search's best beats its best pose
            farther than ``wide_exclude_m`` by ``min_margin`` too, and if the correction
            is within the drift bound (0: off). Orebro's front end (drift seed 0) put its first
            revisit (scans 90-100 against 7-9) 3.7-4.1 m and 0.28-0.31 rad off, and
            its return to the start 4.6-7.0 m off, beyond the local search.
        far_radius_m: a scan with no candidate within ``radius_m`` gets the nearest
            earlier scan (``j <= i - min_separation``) within this distance (m) whose
            drift bound (``wide_drift_per_m``) covers its distance as a candidate for the
            wide search alone, over +-``far_radius_m`` (0, the default: none; off with the
            wide search, ``wide_search_xy_m=0``). Along a corridor the estimate drifts by
            more than ``radius_m``, and its revisits get no candidate otherwise: on
            infinite-corridor (drift seed 0) the last 190 scans' revisits were 6.0-7.9 m
            off along the corridors, and at 10 m the wide search put four of six such
            pairs within 7 cm (the two wrong ones failed ``min_margin``). But a whole run
            there with 10 m gave 3.186 m against 3.188 m (282 loops against 271): the
            robust pose graph takes the new loops' 6 m corrections for outliers, and 34
            of its loops are more than 1 m off (aliased places along the corridors).
            Elsewhere it changed nothing (intel, orebro, acapulco: 4-6, 12 and 25-26 far
            candidates per run, none accepted) or within the seeds' spread (fhw), and it
            cost time (acapulco +10 %), so it is off.
        wide_cell_m, wide_step_yaw_rad, wide_exclude_m: see ``wide_search_xy_m``.
        wide_drift_per_m: the drift bound: a wide-search correction may be at most this
            times the distance travelled between the two scans along the estimate (m/m).
            An aliased place (repeating rooms) lies at a fixed distance, the true one
            within the estimate's drift. The loops the wide search added on the shared
            logs' front ends (drift seeds 0-2 on orebro, 0-1 on fhw) corrected 1.0-5.6 %
            of the distance travelled (orebro: 4.1 m after 74 m); on a simulated office,
            an aliased room 2.1 m away after 27 m (7.7 %) passed every other test.
            Missing a loop is the safe failure, so the bound is tight.
        retry_xy_m, retry_yaw_rad: with ``previous_poses`` (a later round of
            :func:`find_loops`), a candidate pair ``(j, i)`` is matched again only if its
            estimated relative pose has moved by more than this (m or rad) since, or if
            scan ``i``'s candidates there were all more than ``submap_half`` scans from
            ``j`` (the same start on nearly the same submap gives the same match; the
            nearest candidate may switch between neighbouring scans of one visit).
        final_from_search: the matches run the last stage also alone from the search's
            best pose (:class:`~lidarjax.slam.FrontEndConfig`'s ``final_from_search``),
            whatever the front end's setting.
        submap_cache: submaps kept for reuse within one :func:`find_loops` call (the
            most recently used; 0: every candidate's submap is built afresh). A submap
            depends only on its centre scan ``j`` and the searched poses, and
            neighbouring scans often share their candidate: on intel's front ends
            (drift seeds 0-1) 48 % of the candidates' submaps were one of the last two
            built. A reused submap is the same arrays, so the loops are identical; each
            costs about 40 MB at a 20 m range cap and 0.05 m cells (90 MB at 40 m).
    """

    radius_m: float = 4.0
    min_separation: int = 30
    max_candidates: int = 1
    submap_half: int = 5
    start_offsets_m: float = 0.0
    start_offsets_rad: float = 0.0
    min_used_fraction: float = 0.6
    min_mean_log_likelihood: float | None = None
    scene_margin: float | None = None
    scene_samples: int = 40
    min_information: float = 20.0
    max_correction_m: float = 3.0
    every: int = 2
    agree_m: float = 0.05
    search_xy_m: float = 1.0
    search_yaw_rad: float = 0.2
    exclude_m: float = 0.3
    min_margin: float = 15.0
    wide_search_xy_m: float = 6.0
    wide_search_yaw_rad: float = 0.5
    far_radius_m: float = 0.0
    wide_cell_m: float = 0.2
    wide_step_yaw_rad: float = 0.02
    wide_exclude_m: float = 1.0
    wide_drift_per_m: float = 0.06
    retry_xy_m: float = 0.1
    retry_yaw_rad: float = 0.02
    final_from_search: bool = True
    submap_cache: int = 2

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
        if not isinstance(self.final_from_search, bool):
            raise ValueError(
                f"final_from_search must be True or False, got {self.final_from_search!r}"
            )
        for name in (
            "start_offsets_m",
            "start_offsets_rad",
            "min_information",
            "search_xy_m",
            "search_yaw_rad",
            "exclude_m",
            "min_margin",
            "wide_search_xy_m",
            "wide_search_yaw_rad",
            "far_radius_m",
            "retry_xy_m",
            "retry_yaw_rad",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
        for name in ("wide_cell_m", "wide_step_yaw_rad", "wide_exclude_m", "wide_drift_per_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be positive and finite, got {v!r}")
        if 0 < self.far_radius_m <= self.radius_m:
            raise ValueError(
                f"far_radius_m must be 0 or exceed radius_m ({self.radius_m}), "
                f"got {self.far_radius_m!r}"
            )
        if not (0 <= self.min_used_fraction <= 1):
            raise ValueError(f"min_used_fraction must be in [0, 1], got {self.min_used_fraction}")
        v = self.min_mean_log_likelihood
        if v is not None and (
            isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)
        ):
            raise ValueError(f"min_mean_log_likelihood must be a finite number or None, got {v!r}")
        v = self.scene_margin
        if v is not None and (
            isinstance(v, bool)
            or not isinstance(v, (int, float))
            or not (math.isfinite(v) and v >= 0)
        ):
            raise ValueError(f"scene_margin must be a finite number >= 0 or None, got {v!r}")
        for name in ("scene_samples", "submap_cache"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"{name} must be an int >= 0, got {v!r}")


@dataclasses.dataclass(frozen=True)
class Loops:
    """Accepted loop closures.

    Attributes:
        edges: ``[L 2]`` int pairs ``(j, i)``, ``j < i``.
        measurements: ``[L 3]`` relative poses ``pose_j^-1 pose_i`` ``(x m, y m, yaw rad)``.
        n_tried: candidate pairs matched.
        scene_level: the log's level (:func:`scene_log_likelihood`, nats per used ray;
            NaN where no sample had enough used rays) along the search's
            ``level_poses``, if the search computed it or was given it; None otherwise.
            A later search along the same ``level_poses`` takes it back
            (:func:`find_loops`'s ``scene_level``) instead of computing it again.
    """

    edges: np.ndarray
    measurements: np.ndarray
    n_tried: int
    scene_level: float | None = None


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


def _path(poses: np.ndarray) -> np.ndarray:
    """``[N]`` distance travelled along ``poses`` up to each scan (m)."""
    return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))])


def _far_candidates(poses: np.ndarray, path: np.ndarray, i: int, cfg: LoopConfig) -> list[int]:
    """Scan ``i``'s far candidate (a list of at most one) when it has none within
    ``radius_m``: the nearest earlier scan ``j <= i - min_separation`` within
    ``far_radius_m`` whose drift bound, ``wide_drift_per_m`` times the path ``path``
    (m) travelled from ``j`` to ``i``, is at least its distance."""
    if cfg.far_radius_m <= 0 or cfg.wide_search_xy_m <= 0 or i < cfg.min_separation:
        return []
    d = np.hypot(*(poses[: i - cfg.min_separation + 1, :2] - poses[i, :2]).T)
    bound = cfg.wide_drift_per_m * (path[i] - path[: i - cfg.min_separation + 1])
    ok = (d <= cfg.far_radius_m) & (d <= bound)
    return [int(np.argmin(np.where(ok, d, np.inf)))] if ok.any() else []


def _wide_search(
    grid: GridMap,
    az: np.ndarray,
    rng: np.ndarray,
    guess: np.ndarray,
    fcfg: FrontEndConfig,
    cfg: LoopConfig,
    half_xy_m: float | None = None,
) -> tuple[np.ndarray, float]:
    """Coarse correlative search of scan ``rng`` over ``+-cfg.wide_search_xy_m`` and
    ``+-cfg.wide_search_yaw_rad`` around ``guess`` on the submap ``grid``: its end-point
    score (log of the rates blurred by ``fcfg.search_blur_m``, max-pooled to
    ``cfg.wide_cell_m`` cells, so a coarse cell scores the best fine cell in it) on a
    lattice of ``wide_cell_m`` and ``wide_step_yaw_rad`` steps, no prior. Every HIT ray
    counts (which rays end in mapped space depends on the pose being searched).

    ``half_xy_m`` (None: ``cfg.wide_search_xy_m``) overrides the window's half width.

    Returns:
        ``(best pose [3], margin)``: the margin (nats) of the best score over the best
        lattice pose farther than ``cfg.wide_exclude_m`` from it.
    """
    res = fcfg.resolution_m
    f = max(1, int(round(cfg.wide_cell_m / res)))
    cell = f * res
    half = cfg.wide_search_xy_m if half_xy_m is None else half_xy_m
    n_xy = int(round(half / cell))
    n_yaw = int(round(cfg.wide_search_yaw_rad / cfg.wide_step_yaw_rad))
    # the window: every end point of every searched pose (to the range cap) inside
    n = fcfg.window_cells + 2 * (n_xy + 1) * f
    n = f * int(math.ceil(n / f))
    h, r, origin = grid.window(guess[:2], n)
    seen = r > 1e-9
    rates = np.where(seen, h / np.where(seen, r, 1.0), 0.0)
    context, dt = fcfg.precision()
    with context:
        lam = jnp.asarray(rates, dt)
        sb = fcfg.search_blur_m / res
        if sb > 0:
            lam = blur(lam, sb)
        pooled = lam.reshape(n // f, f, n // f, f).max(axis=(1, 3))
        table = jnp.maximum(jnp.log(pooled + fcfg.rate_floor), fcfg.ray_floor)
        best, s_best, s_runner = correlative_search(
            table,
            jnp.asarray(origin, dt),
            cell,
            jnp.asarray(az, dt),
            jnp.asarray(rng, dt),
            jnp.asarray(rng < fcfg.range_cap_m, dt),
            jnp.asarray(guess, dt),
            jnp.asarray(guess, dt),
            jnp.zeros(3, dt),
            n_xy=n_xy,
            n_yaw=n_yaw,
            step_yaw=cfg.wide_step_yaw_rad,
            exclude_m=cfg.wide_exclude_m,
        )
    return np.asarray(best, float), float(s_best - s_runner)


def _min_mean_log_likelihood(cfg: LoopConfig, fcfg: FrontEndConfig) -> float:
    """The loop test's least mean log-likelihood per used ray (nats) for the matching
    model: ``cfg``'s if given, else the model's default."""
    if cfg.min_mean_log_likelihood is not None:
        return float(cfg.min_mean_log_likelihood)
    return MIN_MEAN_LOG_LIKELIHOOD[fcfg.model]


def scene_log_likelihood(
    ranges_m: np.ndarray,
    azimuths_rad: np.ndarray,
    poses: np.ndarray,
    cfg: LoopConfig | None = None,
    front_cfg: FrontEndConfig | None = None,
) -> float:
    """How well the log's scans fit their own neighbourhoods: the median, over
    ``cfg.scene_samples`` scans ``k`` spread evenly along the log, of the mean
    log-likelihood per used ray (:func:`~lidarjax.slam.score_scan`, the matching model's
    last stage) of scan ``k`` at its pose against the submap of its neighbours ``k -
    submap_half .. k + submap_half`` (``k`` left out), the submap a loop match is scored
    against. Nothing is matched.

    The level is the scene's: under the decay-rate model at the 20 m range cap, the
    front ends of intel, fhw and orebro (drift seeds 0-5) score 2.65-2.85, 1.03-1.18 and
    1.63-1.75 nats per ray; acapulco, a hall whose walls lie mostly beyond the cap,
    -0.20 to -0.25.

    Args:
        ranges_m: ``[N B]`` readings (m).
        azimuths_rad: ``[B]`` beam angles (rad).
        poses: ``[N 3]`` the estimate ``(x m, y m, yaw rad)`` (e.g. the front end's).
        cfg: ``submap_half``, ``scene_samples`` and ``min_used_fraction`` (a sample with
            fewer used rays is left out); front_cfg: the matching settings.

    Returns:
        The level (nats per used ray); NaN when no sample has enough used rays (or the
        log is shorter than a submap).
    """
    cfg = LoopConfig() if cfg is None else cfg
    fcfg = FrontEndConfig() if front_cfg is None else front_cfg
    rng = np.asarray(ranges_m, float)
    az = np.asarray(azimuths_rad, float)
    poses = np.asarray(poses, float)
    _check_scans(rng, az, poses)
    if np.any(np.isnan(rng)) or np.any(rng < 0):
        raise ValueError("ranges_m must be >= 0 and not NaN")
    n, h = rng.shape[0], cfg.submap_half
    if n < 2 * h + 1 or h == 0:
        return math.nan
    centres = np.unique(np.round(np.linspace(h, n - 1 - h, cfg.scene_samples)).astype(int))
    levels = []
    for k in centres:
        grid = grid_map(fcfg)
        others = np.array([q for q in range(k - h, k + h + 1) if q != k])
        local = between_np(np.broadcast_to(poses[k], (others.size, 3)), poses[others])
        grid.add_scans(local, az, rng[others])
        mean_ll, n_used = score_scan(grid, az, rng[k], np.zeros(3), fcfg)
        if n_used >= cfg.min_used_fraction * az.shape[0]:
            levels.append(mean_ll)
    return float(np.median(levels)) if levels else math.nan


def loop_threshold(
    ranges_m: np.ndarray,
    azimuths_rad: np.ndarray,
    poses: np.ndarray,
    cfg: LoopConfig | None = None,
    front_cfg: FrontEndConfig | None = None,
) -> float:
    """The loop test's least mean log-likelihood per used ray (nats) along an estimate:
    the matching model's threshold (``cfg.min_mean_log_likelihood``, by default
    :data:`MIN_MEAN_LOG_LIKELIHOOD`), or the log's own level
    (:func:`scene_log_likelihood`) less the scene margin (``cfg.scene_margin``, by
    default :data:`SCENE_MARGIN`) where that is lower. With ``cfg.scene_samples = 0``
    or no margin, the model's threshold.

    Measured with the decay-rate model on the shared logs' front ends (drift seed 0, 20 m
    range cap): of the loop matches that pass every other test, those 0.3 m or more off
    the corrected poses' relative pose (2 of 284 on intel, 1 of 90 on fhw, 0 of 18 on
    orebro, 2 of 72 on acapulco) score -5.5 to -4.8 nats per ray but for two 0.30-0.31 m
    off at 2.1; the rest score down to -2.9. On acapulco, a hall whose walls lie mostly
    beyond the cap (level -0.25 nats), the model's 0.5 nats accepted 13 of its 72
    candidates; at the scene's threshold (-0.75 nats), 50. On intel, fhw and orebro
    (drift seeds 0-5) the levels are 1.0-2.9 nats and the threshold stays 0.5.

    Args:
        ranges_m, azimuths_rad, poses, cfg, front_cfg: as :func:`find_loops`.

    Returns:
        The threshold (nats per used ray).
    """
    t = _Threshold(ranges_m, azimuths_rad, poses, cfg, front_cfg)
    return t.lowered()


class _Threshold:
    """:func:`loop_threshold`, with the log's level computed only when a match scores
    below the model's own threshold (the only case the level can change the test's
    outcome), and then once."""

    def __init__(self, ranges_m, azimuths_rad, poses, cfg, front_cfg, level=None):
        self.cfg = LoopConfig() if cfg is None else cfg
        self.fcfg = FrontEndConfig() if front_cfg is None else front_cfg
        self.scans = (ranges_m, azimuths_rad, poses)
        self.base = _min_mean_log_likelihood(self.cfg, self.fcfg)
        m = self.cfg.scene_margin
        self.margin = SCENE_MARGIN[self.fcfg.model] if m is None else m
        self.level: float | None = level  # the log's level, once computed (or given)
        self._lowered: float | None = None

    def lowered(self) -> float:
        """The threshold (nats per used ray), the level computed if need be."""
        if self._lowered is None:
            self._lowered = self.base
            if self.margin is not None and self.cfg.scene_samples > 0:
                if self.level is None:
                    self.level = scene_log_likelihood(*self.scans, self.cfg, self.fcfg)
                if math.isfinite(self.level):
                    self._lowered = min(self.base, self.level - self.margin)
        return self._lowered

    def passes(self, mean_log_likelihood: float) -> bool:
        """Whether a match's mean log-likelihood per used ray passes."""
        return mean_log_likelihood >= self.base or mean_log_likelihood >= self.lowered()


def _good(m, az: np.ndarray, cfg: LoopConfig, ll_ok) -> bool:
    """A match's own acceptance tests: the used fraction of the rays, the translation
    information per used ray, the gate and (last, as it may compute the log's level) the
    mean log-likelihood per used ray (``ll_ok(mean_log_likelihood)``, e.g.
    :meth:`_Threshold.passes`)."""
    used = m.n_used / az.shape[0]
    info = m.min_translation_information / max(m.n_used, 1)
    return bool(
        used >= cfg.min_used_fraction
        and info >= cfg.min_information
        and m.plausible
        and ll_ok(m.mean_log_likelihood)
    )


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
    known: np.ndarray | None = None,
    previous_poses: np.ndarray | None = None,
    level_poses: np.ndarray | None = None,
    scene_level: float | None = None,
    progress: bool = False,
) -> Loops:
    """Search loop closures along an estimated trajectory (module docstring).

    Args:
        ranges_m: ``[N B]`` readings (m).
        azimuths_rad: ``[B]`` beam angles (rad).
        poses: ``[N 3]`` estimated poses (e.g. the front end's, or a pose graph's).
        cfg: loop settings; front_cfg: matching settings (map, blur stages).
        known: ``[K 2]`` pairs ``(j, i)`` already closed (an earlier round's loops): a
            candidate pair among them is not matched again (nor counted in ``n_tried``).
        previous_poses: ``[N 3]`` the poses an earlier round searched along (None: none):
            a candidate pair of a visit searched there too is skipped unless its relative
            pose has moved by more than ``cfg.retry_xy_m`` or ``cfg.retry_yaw_rad``.
        level_poses: ``[N 3]`` the estimate the log's level (:func:`loop_threshold`) is
            computed along (None: ``poses``). :func:`~lidarjax.slam.run_slam` passes the
            front end's in every round: a pose graph spreads its corrections over the
            scans, which fit their neighbours less well (on fhw's front ends, drift seeds
            0-3, the level was 1.03-1.18 nats along the front end and 0.85-0.98 along the
            pose graph).
        scene_level: the log's level along ``level_poses`` if already known (an earlier
            search's :attr:`Loops.scene_level` along the same poses; NaN allowed): it is
            not computed again (None: computed if a match needs it).
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
        final_from_search=cfg.final_from_search,
    )
    rng = np.asarray(ranges_m, float)
    az = np.asarray(azimuths_rad, float)
    poses = np.asarray(poses, float)
    _check_scans(rng, az, poses)
    n = rng.shape[0]
    if known is None:
        known = np.zeros((0, 2), np.int64)
    known = np.asarray(known)
    if known.ndim != 2 or known.shape[1] != 2 or not np.issubdtype(known.dtype, np.integer):
        raise ValueError(f"known must be a [K, 2] integer array of pairs, got {known.shape}")
    skip = {(int(j), int(i)) for j, i in known}
    if previous_poses is not None:
        previous_poses = np.asarray(previous_poses, float)
        if previous_poses.shape != poses.shape or not np.all(np.isfinite(previous_poses)):
            raise ValueError(
                f"previous_poses must be a finite [{n}, 3] array, got {previous_poses.shape}"
            )
    if level_poses is None:
        level_poses = poses
    level_poses = np.asarray(level_poses, float)
    if level_poses.shape != poses.shape or not np.all(np.isfinite(level_poses)):
        raise ValueError(f"level_poses must be a finite [{n}, 3] array, got {level_poses.shape}")
    if scene_level is not None and (
        isinstance(scene_level, bool)
        or not isinstance(scene_level, (int, float, np.floating))
        or math.isinf(scene_level)
    ):
        raise ValueError(f"scene_level must be a finite number, NaN or None, got {scene_level!r}")
    threshold = _Threshold(rng, az, level_poses, cfg, fcfg, scene_level)
    starts = _starts(cfg)
    searched = cfg.search_xy_m > 0 or cfg.search_yaw_rad > 0
    # distance travelled along the estimate (m), which bounds its drift
    path = _path(poses)
    previous_path = None if previous_poses is None else _path(previous_poses)

    def drift(j: int, i: int) -> float:
        return cfg.wide_drift_per_m * float(path[i] - path[j])

    edges, meas = [], []
    n_tried = 0
    cache: collections.OrderedDict[int, GridMap] = collections.OrderedDict()

    def submap(j: int) -> GridMap:
        # scans j - submap_half .. j + submap_half in the frame of scan j; matching only
        # reads it, so a cached one is reused as it is
        if j in cache:
            cache.move_to_end(j)
            return cache[j]
        lo, hi = max(0, j - cfg.submap_half), min(n, j + cfg.submap_half + 1)
        local = between_np(np.broadcast_to(poses[j], (hi - lo, 3)), poses[lo:hi])
        grid = grid_map(fcfg)
        grid.add_scans(local, az, rng[lo:hi])
        if cfg.submap_cache > 0:
            cache[j] = grid
            if len(cache) > cfg.submap_cache:
                cache.popitem(last=False)
        return grid

    def wide(grid, i: int, j: int, guess: np.ndarray, half_xy_m: float) -> None:
        # a coarse search of the wide window, then the same match from its best
        start, wide_margin = _wide_search(grid, az, rng[i], guess, fcfg, cfg, half_xy_m)
        m = match_scan(grid, az, rng[i], start, fcfg, prior_xy_yaw=start)
        if (
            wide_margin >= cfg.min_margin
            and m.search_score - m.search_runner_up >= cfg.min_margin
            and np.hypot(*(m.pose[:2] - guess[:2])) <= drift(j, i)
            # the model's own threshold: a search over metres finds aliased
            # places, which the scene's lower threshold would let through
            and _good(m, az, cfg, lambda ll: ll >= threshold.base)
        ):
            edges.append((j, i))
            meas.append(m.pose)

    it = range(cfg.min_separation, n, cfg.every)
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(it, desc="loop closures", unit="scan")
    for i in it:
        near = _candidates(poses, i, cfg)
        # no candidate within radius_m: a far one, for the wide search alone
        far = [] if near else _far_candidates(poses, path, i, cfg)
        before = ()
        if previous_poses is not None:
            before = _candidates(previous_poses, i, cfg) or _far_candidates(
                previous_poses, previous_path, i, cfg
            )
        for j in near + far:
            if (j, i) in skip:
                continue
            if any(abs(j - b) <= cfg.submap_half for b in before):
                moved = between_np(
                    between_np(previous_poses[j], previous_poses[i]), between_np(poses[j], poses[i])
                )
                if np.hypot(*moved[:2]) <= cfg.retry_xy_m and abs(moved[2]) <= cfg.retry_yaw_rad:
                    continue
            n_tried += 1
            grid = submap(j)
            guess = between_np(poses[j], poses[i])
            if far:
                wide(grid, i, j, guess, cfg.far_radius_m)
                continue
            matches = [
                match_scan(
                    grid, az, rng[i], compose_np(guess, s), fcfg, prior_xy_yaw=compose_np(guess, s)
                )
                for s in starts
            ]
            best = max(matches, key=lambda m: m.mean_log_likelihood * m.n_used)
            # the optimum must attract more than one start (a lone basin is a guess)
            agree = sum(np.hypot(*(m.pose[:2] - best.pose[:2])) <= cfg.agree_m for m in matches)
            corr = np.hypot(*(best.pose[:2] - guess[:2]))
            margin = best.search_score - best.search_runner_up
            if (
                corr <= cfg.max_correction_m
                and (agree >= 2 or len(matches) == 1)
                and (not searched or margin >= cfg.min_margin)
                and _good(best, az, cfg, threshold.passes)
            ):
                edges.append((j, i))
                meas.append(best.pose)
            elif cfg.wide_search_xy_m > 0 and drift(j, i) > cfg.search_xy_m:
                # the estimate may have drifted beyond the local search
                wide(grid, i, j, guess, cfg.wide_search_xy_m)
    e = np.asarray(edges, np.int64).reshape(-1, 2)
    level = None if threshold.level is None else float(threshold.level)
    return Loops(e, np.asarray(meas, float).reshape(-1, 3), n_tried, level)
