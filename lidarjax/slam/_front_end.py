"""Online front end of decay-rate SLAM: scan-to-map matching on a continuous decay-rate
field, started from raw odometry, with the map's grid statistics updated additively.

For scan ``k`` the predicted pose is the previous estimate composed with the odometry
increment. The map is a growing 2-D grid of hits ``H`` and travelled lengths ``R``
(Eq. 7.10's sufficient statistics, :func:`~lidarjax.raytrace.accumulate`), to which every
matched scan adds its rays; a window of the grid around the prediction is turned into the
ML decay rates ``H / R``, Gaussian-blurred (coarse to fine) and interpolated bilinearly
(:class:`~lidarjax.maps.SmoothDecayRateField`), and the scan's decay-rate log-likelihood
(:func:`~lidarjax.maps.field_log_likelihood`) is maximised over its SE(2) pose with
optimistix (:func:`~lidarjax.localization.refine.refine_pose`).

Two measures keep the matching unbiased where the map ends:

* rays whose end point falls in a cell no ray of the map has traversed (``R = 0`` in the
  cell and its 8 neighbours, judged at the predicted pose) are left out of the objective:
  their end-point term would pull them toward mapped space;
* unmapped cells have rate 0 in the window (a ray through them costs nothing), so rays
  into unexplored space are neither rewarded nor penalised.

A Gaussian prior on the increment (the odometry's) keeps degenerate scenes (a corridor)
well posed.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
import types

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Float

from ..maps import DecayRateMap, SmoothDecayRateField, blur
from ..rays import HIT, from_scan
from ..raytrace import GridSpec, accumulate
from ._search import correlative_search

__all__ = [
    "RANGE_CAPS_M",
    "auto_range_cap",
    "FrontEndConfig",
    "FrontEndResult",
    "GridMap",
    "MATCHING_MODELS",
    "MatchResult",
    "match_scan",
    "odometry_sigmas",
    "run_front_end",
    "score_scan",
]


#: the scan-matching models of :class:`FrontEndConfig` (``model``)
MATCHING_MODELS = ("decay_rate", "endpoint")


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def se2(xy_yaw) -> jaxlie.SE2:
    """``jaxlie.SE2`` of ``[..., 3]`` poses ``(x, y, yaw)``."""
    xy_yaw = jnp.asarray(xy_yaw)
    return jaxlie.SE2.from_xy_theta(xy_yaw[..., 0], xy_yaw[..., 1], xy_yaw[..., 2])


def xy_yaw(pose: jaxlie.SE2) -> Array:
    """``[..., 3]`` ``(x, y, yaw)`` of a ``jaxlie.SE2``."""
    return jnp.concatenate([pose.translation(), pose.rotation().as_radians()[..., None]], -1)


def compose_np(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a * b`` for ``[..., 3]`` NumPy poses ``(x, y, yaw)``."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack(
        [
            a[..., 0] + c * b[..., 0] - s * b[..., 1],
            a[..., 1] + s * b[..., 0] + c * b[..., 1],
            _wrap(a[..., 2] + b[..., 2]),
        ],
        -1,
    )


def between_np(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a^-1 * b`` for ``[..., 3]`` NumPy poses ``(x, y, yaw)``."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, _wrap(b[..., 2] - a[..., 2])], -1)


@dataclasses.dataclass(frozen=True)
class FrontEndConfig:
    """Settings of the front end (defaults hold on the shared CARMEN logs; none is tuned
    per log).

    Attributes:
        resolution_m: map cell size (m).
        range_cap_m: readings at or beyond this range are treated as no-returns traced to
            it (m), both in the map and in matching; far readings are the least accurate,
            but they fix the heading. 20 m keeps 98.6-99.8 % of the shared logs' returns
            (10 m: 88-98 %); front-end ATE (drift seeds 0-2 on orebro, 0-1 on fhw, 0 on
            intel) went from 2.07 / 1.33 / 0.98, 1.57 / 1.60 and 0.277 m at 10 m to
            0.89 / 0.64 / 0.44, 1.46 / 1.17 and 0.282 m at 20 m (orebro, seed 0: the
            heading error summed over scans 7-90 went from -0.29 to -0.007 rad). For a
            log whose walls lie farther, :func:`auto_range_cap` chooses 30 or 40 m (the
            command line's and the experiment's default), and :meth:`with_range_cap`
            sets the window and the nodes to match.
        blur_schedule_m: Gaussian blur widths (m) of the coarse-to-fine matching stages.
        window_m: half width of the square map window a scan is matched against (m); at
            least ``range_cap_m`` plus the largest expected motion between scans.
        n_nodes: midpoint nodes per ray of the optical depth. The node spacing is the
            ray's length over ``n_nodes``; 512 keeps it below a cell (0.78 of a 0.05 m
            cell) up to the 20 m range cap, so a ray crossing a one-cell wall never steps
            over it. With 256 at the 20 m cap (1.56 cells), the front end's ATE (drift
            seed 0) was orebro 0.891, fhw 1.464 and intel 0.282 m; with 512, 0.251,
            1.398 and 0.295 m.
        max_steps: BFGS iterations per stage.
        prior_sigma_xy_m, prior_sigma_yaw_rad: standard deviations of the Gaussian prior of
            :func:`match_scan` when none is given (m, rad).
        odometry_sigma_rel, odometry_sigma_xy_m: the front end's prior on each increment:
            translation standard deviation ``odometry_sigma_xy_m + odometry_sigma_rel * d``
            (m) for an odometry increment of length ``d`` (m).
        odometry_sigma_yaw_per_m, odometry_sigma_yaw_rel, odometry_sigma_yaw_rad: heading
            standard deviation ``odometry_sigma_yaw_rad + odometry_sigma_yaw_per_m * d +
            odometry_sigma_yaw_rel * |dyaw|`` (rad). Loose defaults (about twice the
            drift of typical wheel odometry); a user who knows the odometry sets them.
        ray_floor: per-ray log-likelihood floor (nats), for outlier readings.
        rate_floor: end-point rate floor (1/m).
        gap_cells: the optical depth of a HIT ray is integrated to ``gap_cells`` cells (plus
            twice the stage's blur) short of its end point. The interpolated rates of a
            wall rise over a cell (and the blur) before it, and a ray that pays that rise
            is pulled toward the sensor; measured on intel against maps from the corrected
            poses of the neighbouring scans (26 scans), the mean along-track error was
            -2.7 cm with no gap and -1.4 cm with 1.5 cells (median |error| 4.0 -> 3.0 cm).
        prior_hits, prior_length_m: pseudo-counts of the window's rates ``(H + a) / (R + b)``
            (both 0: the ML rates ``H / R``, never-seen cells 0; ``prior_hits > 0`` needs
            ``prior_length_m > 0``). A length alone shrinks rates seen over short lengths,
            such as the cell behind a wall's first one (results, stop 60), and lowers
            every scan's log-likelihood, which the loop test's threshold is not set for.
        mask_unmapped: leave rays ending in never-traversed cells out of the objective.
        model: ``"decay_rate"`` (the default) or ``"endpoint"``: the likelihood-field
            baseline, ``log`` of the blurred hit indicator at the end points (no free-space
            term), on the same map, matching and masks.
        search_xy_m, search_yaw_rad: half widths (m, rad) of the exhaustive end-point search
            (:func:`~lidarjax.slam.correlative_search`) around the start pose, on the map's
            cells and ``search_step_yaw_rad`` heading steps; its best pose starts the
            coarse-to-fine refinement (both 0: no search). Measured on the shared logs'
            front ends (0.05 m cells): ATE intel 0.925 -> 0.517 m, fhw 3.80 -> 0.386 m.
        search_step_yaw_rad: heading step of the search (rad).
        search_blur_m: Gaussian blur (m) of the rates whose log the search scores.
        search_exclude_m: the search's runner-up is its best pose farther than this (m).
        local_map_scans: match against the last this many scans only (0: every scan so
            far). A local map never snaps onto an earlier visit; loop closures then must.
            The front end alone drifts more (intel, drift seed 0: ATE 0.095 -> 0.495 m at
            30 scans; its heading takes up about 6 % of the odometry's heading error), so
            for a lidar odometry without loop closures set 0. Under
            :func:`~lidarjax.slam.run_slam` (whose revisits it turns off by default) the
            pose graph, over six drift seeds, mean / worst (m): at 100 scans (default since
            stop 62) intel 0.082 / 0.112 -> 0.063 / 0.080, fhw 0.124 / 0.150 -> 0.129 /
            0.143, orebro 0.276 / 0.501 -> 0.242 / 0.408 against 0 (every scan); at 30
            scans intel 0.060, but fhw 0.140 and orebro 0.371, where loop closures are
            sparse (docs/results/slam.md, stops 61-62).
        gate_sigmas: a match farther than this (Mahalanobis, under the prior) from the
            prior's mean is implausible; the other candidate is taken, or (neither
            plausible) the last stage from the prior's mean under a prior
            ``gate_stiffness`` times tighter, or the prior's mean itself. Front-end ATE on
            the shared logs (intel / fhw / orebro, with the search, before the ambiguous
            gate below): no gate 0.517 / 0.386 / 2.289 m; 7: 0.171 / 0.428 / 1.133 m;
            5: - / 1.425 / 1.122 m (a gate of 5 rejects fhw's correct snaps back onto
            the map).
        gate_stiffness: see ``gate_sigmas`` (>= 1).
        final_from_search: with the search on, the last stage is also run alone from the
            search's best pose, a third candidate beside the coarse-to-fine result and
            the last stage from ``pose0`` (the better plausible final objective wins).
            The blurred stages can carry a good start into a neighbouring basin: on the
            simulated office's revisit with ``grazing_cells=1`` one loop came out
            0.056 m and 0.018 rad off (mean log-likelihood 2.76 nats per ray), 0.035 m
            and 0.005 rad (3.82) with the third candidate. It costs one more
            refinement of the last stage per match. Off by default: in the front end
            it moved orebro's pose graph (drift seeds 0-5) from a mean of 0.276 to
            0.348 m (stop 54); the loop search turns it on
            (:class:`~lidarjax.slam.LoopConfig`).
        backend: which code computes the rays' optical depth with its derivatives (the
            match's information included) and the blurs of the map window: ``"auto"``
            (the default: the native C++ kernels on a CPU where they are built, else the
            pure-JAX path), ``"native"`` or ``"jax"`` (see
            :class:`~lidarjax.maps.SmoothDecayRateField`). Both compute the same midpoint
            rule and blur; the native kernels sum in double, so matches differ from the
            JAX path's by round-off, which the BFGS iterations amplify (measured in stop
            52: orebro's pose graph moved by up to 15 cm per run, a three-seed mean by up
            to 2.4 cm). On the shared logs the native front end runs 5.7-6.4 times
            faster (0.09-0.10 s per scan).
        dtype: floating-point type of each match (search, refinement, information):
            ``None`` (default: JAX's default, float32 unless x64 is on, as every result
            in docs/results/slam.md was measured), or ``"float32"`` / ``"float64"``
            whatever JAX's default (the match runs under ``jax.enable_x64``). The BFGS
            refinement of the unblurred stage stops earlier in float32. Measured in stop
            55 (drift seed 0 unless said): on intel re-simulated at its corrected poses
            (exact poses, a consistent world) float64 cut the front end's failed
            increments from 15 to 5 (ATE 0.172 -> 0.122 m); on the real logs it made the
            pose graph worse: orebro's six seeds 0.276 -> 0.452 m mean (5 of 6 worse),
            intel 0.081 -> 0.087 m. Where the likelihood's best pose is not the true one
            (the real data's), stopping near the start helps.
        ambiguous_margin, ambiguous_gate_sigmas: where the search's best score beats its
            runner-up (the best lattice pose farther than ``search_exclude_m``) by less
            than ``ambiguous_margin`` nats, the scene is ambiguous (a corridor seen
            end-on, repeating doors) and the gate is the smaller of
            ``ambiguous_gate_sigmas`` and ``gate_sigmas``. Measured on the shared logs'
            front ends: without it, orebro's three wrong
            matches beyond 3 sigma (0.8-2.1 m off) had margins of 0.5-10.5 nats, its
            correct one 48.6; with it, orebro's front-end ATE went 1.133 -> 0.366 m and
            fhw's 0.428 -> 0.430 m (all 16 of fhw's matches beyond 3 sigma: 31-123
            nats). Needs the search (without one the gate is ``gate_sigmas``).
        grazing_cells, grazing_max_m: where a HIT ray meets its surface at a grazing angle
            ``theta`` (the surface's direction from the neighbouring returns,
            :func:`grazing_lengths`), the stretch of the ray within ``grazing_cells``
            cells of the surface, ``grazing_cells * resolution_m / sin(theta)`` (m, at
            most ``grazing_max_m``), is left out of the map's free length (but for its
            last ``grazing_cells`` cells) and of the scan's optical depth in matching. A
            ray running alongside a wall otherwise marks the wall's cells free when the
            wall is a cell off (pose error, the wall's place in its cells), and a later
            scan's returns on that wall cost ``log(rate_floor)`` each: on orebro (drift
            seed 5, scan 5) that put a match 1.45 m short along a corridor. 0: off.
            Measured with 1 cell, the default since stop 54 (stop 53, drift seeds 0-5):
            orebro's front-end ATE (mean / median / worst) 0.731 / 0.672 / 1.276 ->
            0.350 / 0.266 / 0.659 m, its pose graph 0.393 / 0.383 / 0.610 -> 0.276 /
            0.235 / 0.498 m; fhw's pose graph 0.151 / 0.147 / 0.215 -> 0.125 / 0.125 /
            0.149 m, intel's 0.091 / 0.094 / 0.113 -> 0.081 / 0.085 / 0.111 m (see the
            SLAM results). Each map update costs two more ray traces of the scan. The
            endpoint model (no free-space term) ignores it: its map keeps every ray's
            free length.

    Compilation: the matcher is compiled once per static key (``resolution_m``,
    ``range_cap_m``, ``blur_schedule_m``, ``n_nodes``, ``max_steps``, ``model``,
    ``mask_unmapped``, the ``search_*`` settings, ``backend``, ``final_from_search``,
    ``dtype`` and the window's size), about 10 s on 2 idle cores. The gates
    (``gate_sigmas``, ``ambiguous_gate_sigmas``, ``ambiguous_margin``,
    ``gate_stiffness``), ``rate_floor``, ``ray_floor`` and ``gap_cells`` are traced
    arguments, and the other fields are not read by the compiled program: changing them
    reuses it.
    """

    resolution_m: float = 0.05
    range_cap_m: float = 20.0
    blur_schedule_m: tuple[float, ...] = (0.3, 0.1, 0.0)
    window_m: float = 22.0
    n_nodes: int = 512
    max_steps: int = 60
    prior_sigma_xy_m: float = 0.5
    prior_sigma_yaw_rad: float = 0.2
    odometry_sigma_rel: float = 0.1
    odometry_sigma_xy_m: float = 0.02
    odometry_sigma_yaw_per_m: float = 0.03
    odometry_sigma_yaw_rel: float = 0.05
    odometry_sigma_yaw_rad: float = 0.01
    ray_floor: float = -10.0
    rate_floor: float = 1e-3
    gap_cells: float = 1.5
    model: str = "decay_rate"
    prior_hits: float = 0.0
    prior_length_m: float = 0.0
    mask_unmapped: bool = True
    search_xy_m: float = 0.3
    search_yaw_rad: float = 0.1
    search_step_yaw_rad: float = 0.01
    search_blur_m: float = 0.1
    search_exclude_m: float = 0.2
    local_map_scans: int = 100
    gate_sigmas: float = 7.0
    gate_stiffness: float = 3.0
    ambiguous_margin: float = 15.0
    ambiguous_gate_sigmas: float = 3.0
    backend: str = "auto"
    grazing_cells: float = 1.0
    grazing_max_m: float = 1.0
    final_from_search: bool = False
    dtype: str | None = None

    def __post_init__(self):
        for name in (
            "resolution_m",
            "range_cap_m",
            "window_m",
            "prior_sigma_xy_m",
            "prior_sigma_yaw_rad",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")
        if self.window_m < self.range_cap_m:
            raise ValueError(
                f"window_m ({self.window_m}) must be >= range_cap_m ({self.range_cap_m})"
            )
        # a list (e.g. from a config file) would make the settings unhashable, and the
        # jitted matcher takes it in its static key: kept as a tuple
        try:
            sched = tuple(float(b) for b in self.blur_schedule_m)
        except (TypeError, ValueError):
            raise ValueError(
                f"blur_schedule_m must be a sequence of numbers, got {self.blur_schedule_m!r}"
            ) from None
        object.__setattr__(self, "blur_schedule_m", sched)
        if len(self.blur_schedule_m) == 0 or any(
            not (math.isfinite(b) and b >= 0) for b in self.blur_schedule_m
        ):
            raise ValueError(
                f"blur_schedule_m must be non-empty, finite, >= 0: {self.blur_schedule_m}"
            )
        for name in (
            "odometry_sigma_rel",
            "odometry_sigma_yaw_per_m",
            "odometry_sigma_yaw_rel",
            "gap_cells",
            "prior_hits",
            "prior_length_m",
            "grazing_cells",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
        if self.prior_hits > 0 and self.prior_length_m == 0:
            raise ValueError(
                f"prior_hits ({self.prior_hits}) needs prior_length_m > 0: the rates "
                "(H + prior_hits) / (R + prior_length_m) of never-seen cells would be infinite"
            )
        for name in ("mask_unmapped", "final_from_search"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be True or False, got {getattr(self, name)!r}")
        g = self.grazing_max_m
        if not (isinstance(g, (int, float)) and math.isfinite(g) and g > 0):
            raise ValueError(f"grazing_max_m must be a positive finite number, got {g!r}")
        if g < self.grazing_cells * self.resolution_m:
            raise ValueError(
                f"grazing_max_m ({g}) must be >= grazing_cells * resolution_m "
                f"({self.grazing_cells * self.resolution_m}): raise grazing_max_m or "
                "lower grazing_cells (0 turns the grazing cut off)"
            )
        from ..raytrace import _native

        _native.check_backend(self.backend)
        if self.dtype not in (None, "float32", "float64"):
            raise ValueError(f"dtype must be None, 'float32' or 'float64', got {self.dtype!r}")
        if self.model not in MATCHING_MODELS:
            raise ValueError(f"model must be one of {MATCHING_MODELS}, got {self.model!r}")
        for name in ("n_nodes", "max_steps"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise ValueError(f"{name} must be a positive int, got {v!r}")
        for name in (
            "search_xy_m",
            "search_yaw_rad",
            "search_blur_m",
            "ambiguous_margin",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
        for name in (
            "search_step_yaw_rad",
            "search_exclude_m",
            "gate_sigmas",
            "ambiguous_gate_sigmas",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")
        if not (math.isfinite(self.gate_stiffness) and self.gate_stiffness >= 1):
            raise ValueError(f"gate_stiffness must be finite and >= 1, got {self.gate_stiffness!r}")
        v = self.local_map_scans
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise ValueError(f"local_map_scans must be an int >= 0, got {v!r}")
        if not (math.isfinite(self.ray_floor)):
            raise ValueError(f"ray_floor must be finite, got {self.ray_floor!r}")
        if not (math.isfinite(self.rate_floor) and self.rate_floor >= 0):
            raise ValueError(f"rate_floor must be finite and >= 0, got {self.rate_floor!r}")

    def with_range_cap(self, range_cap_m: float) -> FrontEndConfig:
        """These settings with another range cap (m): the map window ``range_cap_m + 2``
        m, and 512 optical-depth nodes per 400 cells of range (a node every 0.78 cells or
        less: 512 at 20 m in 0.05 m cells, 1024 at 30 or 40 m)."""
        cap = float(range_cap_m)
        if not (math.isfinite(cap) and cap > 0):
            raise ValueError(f"range_cap_m must be a positive finite number, got {range_cap_m!r}")
        nodes = 512 * max(1, math.ceil(cap / (400.0 * self.resolution_m) - 1e-9))
        return dataclasses.replace(self, range_cap_m=cap, window_m=cap + 2.0, n_nodes=nodes)

    @property
    def window_cells(self) -> int:
        """Cells per side of the matching window."""
        return int(math.ceil(2 * self.window_m / self.resolution_m))

    def precision(self):
        """``(context, dtype)``: the context a match runs under (``jax.enable_x64`` where
        :attr:`dtype` is set, else a no-op) and its JAX dtype."""
        if self.dtype is None:
            return contextlib.nullcontext(), jnp.result_type(float)
        wide = self.dtype == "float64"
        return jax.enable_x64(wide), (jnp.float64 if wide else jnp.float32)

    @property
    def grazing_m(self) -> float:
        """Width of the grazing cut (m): ``grazing_cells * resolution_m``, 0 for the
        endpoint model (no free-space term)."""
        return 0.0 if self.model == "endpoint" else self.grazing_cells * self.resolution_m


#: Range caps (m) :func:`auto_range_cap` chooses from.
RANGE_CAPS_M = (20.0, 30.0, 40.0)


def auto_range_cap(
    ranges_m: np.ndarray,
    usable_range_m: float,
    *,
    share: float = 0.98,
    caps_m: tuple[float, ...] = RANGE_CAPS_M,
) -> float:
    """The front end's range cap for a log: the smallest of ``caps_m`` that keeps
    ``share`` of its returns (readings below ``usable_range_m``), else the largest, and at
    most ``usable_range_m`` (a reading there is a no-return already).

    Far readings are the least accurate, but in a hall they are the walls. 20 m keeps 98 %
    or more of the returns of intel, fhw, orebro, csail, belgioioso and edmonton (their
    caps stay 20 m, or the usable range), 96 % of freiburg-101's (30 m), 87 % of
    acapulco's and 70 % of freiburg-campus's (40 m). On acapulco (drift seed 0) 40 m took
    the front end's ATE from 1.64 to 0.36 m and the pose graph's from 0.258 to 0.146 m.

    Args:
        ranges_m: ``[N B]`` (or any shape) readings (m); non-finite ones are no-returns.
        usable_range_m: the sensor's usable range (m); readings at or beyond it are
            no-returns.
        share: fraction of the returns the cap keeps, in ``(0, 1]``.
        caps_m: candidate caps (m), increasing, positive.

    Returns:
        The cap (m).
    """
    r = np.asarray(ranges_m, float)
    u = float(usable_range_m)
    if not (math.isfinite(u) and u > 0):
        raise ValueError(f"usable_range_m must be a positive finite number, got {usable_range_m!r}")
    if isinstance(share, bool) or not (isinstance(share, (int, float)) and 0 < share <= 1):
        raise ValueError(f"share must be in (0, 1], got {share!r}")
    caps = np.asarray(caps_m, float)
    if caps.ndim != 1 or caps.size == 0 or not np.all(np.isfinite(caps) & (caps > 0)):
        raise ValueError(f"caps_m must be a non-empty sequence of positive numbers, got {caps_m!r}")
    if np.any(np.diff(caps) <= 0):
        raise ValueError(f"caps_m must be increasing, got {caps_m!r}")
    if np.any(np.isnan(r)) or np.any(r < 0):
        raise ValueError("ranges_m must be >= 0 and not NaN")
    returns = r[np.isfinite(r) & (r < u)]
    cap = float(caps[-1])
    if returns.size:
        for c in caps:
            if np.mean(returns < c) >= share:
                cap = float(c)
                break
    return min(cap, u)


def grazing_lengths(
    azimuths: np.ndarray,
    ranges: np.ndarray,
    range_cap_m: float,
    delta_m: float,
    max_m: float,
    max_bend_rad: float = 0.26,
) -> np.ndarray:
    """``[b]`` length (m) of the last stretch of each HIT ray (``ranges < range_cap_m``)
    that runs within ``delta_m`` of the surface it hits: ``delta_m / sin(theta)``, at most
    ``max_m`` and the range, where ``theta`` is the angle between the ray and the surface
    (0 for no-returns). ``azimuths`` (rad) and ``ranges`` (m) are ``[b]``, in beam order.

    The surface's direction at a return is that of the line through its two neighbouring
    returns, in the sensor frame (so it does not depend on the pose), where the two
    one-sided differences bend by at most ``max_bend_rad`` (a straight surface); elsewhere
    (an edge, a corner, a lone return) ``theta`` is taken as 90 degrees (``delta_m``). A
    ray hitting a wall at a grazing angle runs alongside it for a long stretch, within a
    cell or two of the wall: a few centimetres of pose error or of the wall's place in its
    cells put that stretch on the wall's cells.
    """
    az = np.asarray(azimuths, float)
    r = np.asarray(ranges, float)
    if az.ndim != 1 or r.shape != az.shape:
        raise ValueError(
            f"azimuths and ranges must be [b] arrays of one length, got {az.shape}, {r.shape}"
        )
    if not (np.all(np.isfinite(az)) and np.all(np.isfinite(r)) and np.all(r >= 0)):
        raise ValueError("azimuths must be finite and ranges finite and >= 0")
    if not (math.isfinite(delta_m) and delta_m >= 0):
        raise ValueError(f"delta_m must be finite and >= 0, got {delta_m!r}")
    if not (math.isfinite(max_m) and max_m >= delta_m and max_m > 0):
        raise ValueError(f"max_m must be finite, > 0 and >= delta_m, got {max_m!r}")
    hit = r < range_cap_m
    p = np.stack([r * np.cos(az), r * np.sin(az)], 1)
    out = np.where(hit, delta_m, 0.0)
    if r.shape[0] < 3:
        return out
    d_prev = p[1:-1] - p[:-2]
    d_next = p[2:] - p[1:-1]
    ok = hit[:-2] & hit[1:-1] & hit[2:]
    n_prev = np.linalg.norm(d_prev, axis=1)
    n_next = np.linalg.norm(d_next, axis=1)
    ok &= (n_prev > 0) & (n_next > 0)
    cos_bend = np.sum(d_prev * d_next, 1) / np.maximum(n_prev * n_next, 1e-300)
    ok &= cos_bend >= math.cos(max_bend_rad)
    t = d_prev + d_next
    nt = np.linalg.norm(t, axis=1)
    ok &= nt > 0
    u = np.stack([np.cos(az[1:-1]), np.sin(az[1:-1])], 1)
    sin_theta = np.abs(u[:, 0] * t[:, 1] - u[:, 1] * t[:, 0]) / np.maximum(nt, 1e-300)
    length = np.minimum(delta_m / np.maximum(sin_theta, delta_m / max_m), max_m)
    out[1:-1] = np.where(ok, np.maximum(length, delta_m), out[1:-1])
    return np.minimum(out, r)  # never longer than the ray


def _grazing(azimuths, ranges, cfg: FrontEndConfig) -> np.ndarray:
    """``[b]`` :func:`grazing_lengths` of one scan under ``cfg`` (zeros when off, or
    for the endpoint model)."""
    if cfg.grazing_m <= 0:
        return np.zeros(np.shape(ranges))
    return grazing_lengths(
        np.asarray(azimuths, float),
        np.asarray(ranges, float),
        cfg.range_cap_m,
        cfg.grazing_m,
        cfg.grazing_max_m,
    )


_ADD_BLOCK = 128
"""Cells: :meth:`GridMap.add_scans` traces on a square grid of a multiple of this side."""


def grid_map(cfg: FrontEndConfig) -> GridMap:
    """An empty :class:`GridMap` with the resolution, range cap and grazing settings of
    ``cfg`` (no grazing cut for the endpoint model)."""
    return GridMap(
        cfg.resolution_m, cfg.range_cap_m, grazing_m=cfg.grazing_m, grazing_max_m=cfg.grazing_max_m
    )


class GridMap:
    """A growing 2-D grid of decay-rate statistics (hits ``H``, lengths ``R`` in m), in
    NumPy float64, to which scans are added (or removed) at given poses.

    Each scan is traced on a small grid around its pose with
    :func:`~lidarjax.raytrace.accumulate` and added at its offset; the grid grows (by
    whole blocks) when a scan reaches beyond it. Cells are aligned to multiples of the
    resolution, so windows and whole maps line up exactly.

    With ``grazing_m > 0`` a HIT ray's free length leaves out the stretch before its
    return that runs within ``grazing_m`` of the surface (:func:`grazing_lengths`, at
    most ``grazing_max_m``), except its last ``grazing_m``: the return still counts, and
    its cell still gets length. A wall seen at a grazing angle then keeps its cells, where
    otherwise the rays running alongside it would mark them free.
    """

    def __init__(
        self,
        resolution_m: float,
        range_cap_m: float,
        *,
        block_m: float = 20.0,
        grazing_m: float = 0.0,
        grazing_max_m: float = 1.0,
    ):
        if not (math.isfinite(resolution_m) and resolution_m > 0):
            raise ValueError(f"resolution_m must be positive and finite, got {resolution_m!r}")
        if not (math.isfinite(range_cap_m) and range_cap_m > 0):
            raise ValueError(f"range_cap_m must be positive and finite, got {range_cap_m!r}")
        if not (math.isfinite(grazing_m) and grazing_m >= 0):
            raise ValueError(f"grazing_m must be finite and >= 0, got {grazing_m!r}")
        if not (math.isfinite(grazing_max_m) and grazing_max_m >= grazing_m):
            raise ValueError(
                f"grazing_max_m must be finite and >= grazing_m, got {grazing_max_m!r}"
            )
        self.res = float(resolution_m)
        self.cap = float(range_cap_m)
        self.grazing_m = float(grazing_m)
        self.grazing_max_m = float(grazing_max_m)
        self._block = max(1, int(round(block_m / self.res)))
        self.lo = None  # [2] int: index of cell (0, 0) on the global lattice
        self.hits = np.zeros((0, 0))
        self.lengths = np.zeros((0, 0))
        self._n_local = int(math.ceil(2 * self.cap / self.res)) + 4

    def _ensure(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Grow so that lattice cells ``lo .. hi - 1`` are inside."""
        if self.lo is None:
            self.lo = lo - self._block
            shape = hi - lo + 2 * self._block
            self.hits = np.zeros(tuple(shape))
            self.lengths = np.zeros(tuple(shape))
            return
        cur_hi = self.lo + np.asarray(self.hits.shape)
        new_lo = np.where(lo < self.lo, lo - self._block, self.lo)
        new_hi = np.where(hi > cur_hi, hi + self._block, cur_hi)
        if np.all(new_lo == self.lo) and np.all(new_hi == cur_hi):
            return
        pad = [(int(self.lo[i] - new_lo[i]), int(new_hi[i] - cur_hi[i])) for i in range(2)]
        self.hits = np.pad(self.hits, pad)
        self.lengths = np.pad(self.lengths, pad)
        self.lo = new_lo

    def add_scan(self, pose_xy_yaw, azimuths, ranges, *, sign: float = 1.0) -> None:
        """Add (``sign=1``) or remove (``sign=-1``) one scan's statistics at a pose."""
        pose_xy_yaw = np.asarray(pose_xy_yaw, dtype=float)
        lo = np.floor(pose_xy_yaw[:2] / self.res).astype(np.int64) - self._n_local // 2
        hi = lo + self._n_local
        self._ensure(lo, hi)
        spec = GridSpec(lo * self.res, self.res, (self._n_local, self._n_local))
        rays = from_scan(se2(pose_xy_yaw), azimuths, ranges, 0.0, self.cap)
        st = accumulate(spec, rays)
        # the kernel's own dtypes (counts, the rays' float), widened exactly by the adds
        hits, lengths = np.asarray(st.hits), np.asarray(st.lengths)
        if self.grazing_m > 0:
            lengths = self._grazing_free_lengths(
                spec, pose_xy_yaw[None], azimuths, np.asarray(ranges, float)[None], lengths
            )
        i, j = (lo - self.lo).astype(int)
        n = self._n_local
        cells = (slice(i, i + n), slice(j, j + n))
        if sign == 1.0:  # in place, no temporaries (the same sums as below)
            self.hits[cells] += hits
            self.lengths[cells] += lengths
        elif sign == -1.0:
            self.hits[cells] -= hits
            self.lengths[cells] -= lengths
        else:
            self.hits[cells] += sign * hits.astype(float)
            self.lengths[cells] += sign * lengths.astype(float)

    def add_scans(self, poses_xy_yaw, azimuths, ranges, *, sign: float = 1.0) -> None:
        """Add (``sign=1``) or remove (``sign=-1``) several scans at once: the sum of
        :meth:`add_scan` of each, traced in one
        batch on a grid just spanning their rays (three traces in all, instead of one to
        three per scan on a grid of twice the range cap).

        The cells are the same; the lengths are summed in the rays' float type over all
        the scans (not per scan), so they agree with :meth:`add_scan`'s to round-off, and a
        ray's end point exactly on a cell border may fall in the neighbouring cell. Scans
        spread wider than twice :meth:`add_scan`'s grid are added in halves, so memory
        stays bounded.

        Args:
            poses_xy_yaw: ``[S 3]`` the scans' poses ``(x m, y m, yaw rad)``, finite.
            azimuths: ``[B]`` beam angles (rad).
            ranges: ``[S B]`` readings (m), finite and >= 0.
            sign: 1 adds, -1 removes (the same scans at the same poses remove exactly
                what they added).
        """
        if sign not in (1.0, -1.0):
            raise ValueError(f"sign must be 1 or -1, got {sign!r}")
        poses = np.asarray(poses_xy_yaw, dtype=float)
        az = np.asarray(azimuths, dtype=float)
        rng = np.asarray(ranges, dtype=float)
        if poses.ndim != 2 or poses.shape[1] != 3 or not np.all(np.isfinite(poses)):
            raise ValueError(f"poses_xy_yaw must be a finite [S, 3] array, got {poses.shape}")
        if az.ndim != 1 or az.shape[0] == 0 or not np.all(np.isfinite(az)):
            raise ValueError(f"azimuths must be a finite [B] array, B > 0, got {az.shape}")
        if rng.shape != (poses.shape[0], az.shape[0]):
            raise ValueError(
                f"ranges must have shape [{poses.shape[0]}, {az.shape[0]}] (poses, azimuths), "
                f"got {rng.shape}"
            )
        if not (np.all(np.isfinite(rng)) and np.all(rng >= 0)):
            raise ValueError("ranges must be finite and >= 0 (give no-returns as the max reading)")
        if poses.shape[0] == 0:
            return
        # the cells every ray can touch: its origin to its (capped) end, plus a margin
        yaw = poses[:, 2:3] + az
        reach = np.minimum(rng, self.cap)
        xs = np.concatenate([poses[:, 0], (poses[:, 0:1] + reach * np.cos(yaw)).ravel()])
        ys = np.concatenate([poses[:, 1], (poses[:, 1:2] + reach * np.sin(yaw)).ravel()])
        lo = np.floor(np.array([xs.min(), ys.min()]) / self.res).astype(np.int64) - 2
        hi = np.floor(np.array([xs.max(), ys.max()]) / self.res).astype(np.int64) + 3
        # a square of a multiple of _ADD_BLOCK cells: few distinct shapes to compile
        side = _ADD_BLOCK * int(math.ceil(int((hi - lo).max()) / _ADD_BLOCK))
        if side > 2 * max(self._n_local, _ADD_BLOCK) and poses.shape[0] > 1:
            # scans far apart: in two halves, so the grid stays bounded (memory)
            h = poses.shape[0] // 2
            self.add_scans(poses[:h], az, rng[:h], sign=sign)
            self.add_scans(poses[h:], az, rng[h:], sign=sign)
            return
        lo = (lo + hi) // 2 - side // 2
        hi = lo + side
        self._ensure(lo, hi)
        shape = tuple(int(v) for v in hi - lo)
        spec = GridSpec(lo * self.res, self.res, shape)
        st = accumulate(spec, from_scan(se2(poses), az, rng, 0.0, self.cap))
        hits = np.asarray(st.hits)
        lengths = np.asarray(st.lengths, dtype=float)
        if self.grazing_m > 0:
            lengths = self._grazing_free_lengths(spec, poses, az, rng, lengths)
        i, j = (lo - self.lo).astype(int)
        cells = (slice(i, i + shape[0]), slice(j, j + shape[1]))
        if sign == 1.0:
            self.hits[cells] += hits
            self.lengths[cells] += lengths
        else:
            self.hits[cells] -= hits
            self.lengths[cells] -= lengths

    def _grazing_free_lengths(self, spec, poses_xy_yaw, azimuths, ranges, plain) -> np.ndarray:
        """``[n n]`` lengths of the scans at ``[S 3]`` poses with ``[S B]`` ranges when each
        cut HIT ray's free length is ``[0, r - skip]`` and ``[r - keep, r]`` instead of
        ``[0, r]`` (``skip`` from :func:`grazing_lengths`, ``keep = grazing_m``);
        ``plain`` (the uncut lengths) where no ray is cut."""
        rng = np.asarray(ranges, float)
        az = np.asarray(azimuths, float)
        poses = np.asarray(poses_xy_yaw, float)
        skip = np.stack(
            [grazing_lengths(az, r, self.cap, self.grazing_m, self.grazing_max_m) for r in rng]
        )
        keep = self.grazing_m
        cut = (rng < self.cap) & (skip > keep)
        if not np.any(cut):
            return plain

        def lengths(rays):
            return np.asarray(accumulate(spec, rays).lengths, dtype=float)

        # every ray in both batches, so that the shapes (and the compiled tracer) never
        # change: an uncut ray is traced whole in the first and has no tail in the second
        head = np.where(cut, rng - skip, np.minimum(rng, self.cap))
        yaw = poses[:, 2:3] + az
        start = np.where(cut, rng - keep, 0.0)[..., None] * np.stack([np.cos(yaw), np.sin(yaw)], -1)
        tail_poses = np.concatenate([poses[:, None, :2] + start, yaw[..., None]], -1)
        tail = from_scan(
            se2(tail_poses.reshape(-1, 3)), np.zeros(1), np.where(cut, keep, 0.0).reshape(-1, 1)
        )
        return lengths(from_scan(se2(poses), az, head)) + lengths(tail)

    def _overlap(self, lo: np.ndarray, n: int):
        """Slices ``(global, window)`` of the overlap of the window at ``lo`` with the grid,
        or None."""
        if self.lo is None:
            return None
        a = np.maximum(lo, self.lo)
        b = np.minimum(lo + n, self.lo + np.asarray(self.hits.shape))
        if not np.all(b > a):
            return None
        src = tuple(slice(int(a[k] - self.lo[k]), int(b[k] - self.lo[k])) for k in range(2))
        dst = tuple(slice(int(a[k] - lo[k]), int(b[k] - lo[k])) for k in range(2))
        return src, dst

    def window_lo(self, center_xy, n: int) -> np.ndarray:
        """Lattice index of the lower corner of the ``[n n]`` window around ``center_xy``."""
        return np.floor(np.asarray(center_xy, float) / self.res).astype(np.int64) - n // 2

    def window(self, center_xy, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(H, R, origin)`` of the ``[n n]`` window of cells around ``center_xy`` (zeros
        beyond the grid); ``origin`` (m) is its lower corner."""
        lo = self.window_lo(center_xy, n)
        h, r = np.zeros((n, n)), np.zeros((n, n))
        ov = self._overlap(lo, n)
        if ov is not None:
            src, dst = ov
            h[dst], r[dst] = self.hits[src], self.lengths[src]
        return h, r, lo * self.res

    def rates(self) -> tuple[np.ndarray, np.ndarray]:
        """``(rates, origin)``: ML rates ``H / R`` of the whole grid (0 where ``R = 0``)."""
        seen = self.lengths > 1e-9
        rates = np.where(seen, self.hits / np.where(seen, self.lengths, 1.0), 0.0)
        return rates, self.lo * self.res


def _dilate(mask):
    """3x3 max filter of a 2-D boolean array."""
    p = jnp.pad(mask, 1)
    n0, n1 = mask.shape
    out = mask
    for di in range(3):
        for dj in range(3):
            out = out | p[di : di + n0, dj : dj + n1]
    return out


def _blur(rates, sigma_cells: float, backend: str):
    """:func:`~lidarjax.maps.blur` of the window's rates, by the native kernel where
    ``backend`` resolves to it (the map is fixed during a match: no derivatives needed)."""
    from ..raytrace import _native

    if sigma_cells > 0 and backend != "jax" and _native.resolve(backend) == "native":
        return _native.blur2d(rates, sigma_cells)
    return blur(rates, sigma_cells)


def _scan_log_likelihoods(field, pose, az, rng, cfg: FrontEndConfig, gap=0.0):
    """``[b]`` per-ray decay-rate log-likelihoods of one scan at ``pose`` (readings at or
    beyond the range cap are no-returns to it), floored at ``cfg.ray_floor``; the optical
    depth of HIT rays is integrated to ``r - gap`` (m)."""
    rays = from_scan(pose, az, rng, 0.0, cfg.range_cap_m)
    hit = rays.kind == HIT
    ell = jnp.where(hit, jnp.maximum(rays.ranges - gap, 0.0), cfg.range_cap_m)
    if cfg.model == "endpoint":
        depth = jnp.zeros(ell.shape, ell.dtype)
    else:
        depth = field.integral(rays.origins, rays.directions, ell)
    end = rays.origins + jnp.where(hit, rays.ranges, 0.0)[:, None] * rays.directions
    lam = field.decay_rate(end)
    ll = jnp.where(hit, jnp.log(lam + cfg.rate_floor), 0.0) - depth
    return jnp.maximum(ll, cfg.ray_floor)


def _ray_weights(seen, origin, res, az, rng, pose, cfg: FrontEndConfig):
    """``[b]`` 1 for rays in the objective, 0 for HIT rays ending in unmapped cells (no
    traversed length in the end point's cell and its 8 neighbours) or off the window."""
    n = seen.shape[0]
    rays = from_scan(pose, az, rng, 0.0, cfg.range_cap_m)
    end = rays.origins + jnp.where(rays.kind == HIT, rays.ranges, 0.0)[:, None] * rays.directions
    idx = jnp.floor((end - origin) / res).astype(jnp.int32)
    inside = jnp.all((idx >= 0) & (idx < n), axis=-1)
    near = _dilate(seen)[jnp.clip(idx[:, 0], 0, n - 1), jnp.clip(idx[:, 1], 0, n - 1)]
    return jnp.where(rays.kind == HIT, inside & near, True)


#: The :class:`FrontEndConfig` numbers the jitted matcher and scorer take as traced
#: arguments: a different value reuses the compiled program (and the persistent
#: compilation cache) instead of compiling again (a sweep over the gates, a test).
_TRACED_FIELDS = (
    "rate_floor",
    "ray_floor",
    "gap_cells",
    "gate_sigmas",
    "ambiguous_gate_sigmas",
    "ambiguous_margin",
    "gate_stiffness",
)
#: The fields that shape the compiled program (sizes, loop counts, branches, kernels):
#: the jit's static key. Fields in neither tuple are not read inside the jit, so they
#: do not cause a compilation either (``local_map_scans``, the odometry's sigmas, ...).
_STATIC_FIELDS = (
    "resolution_m",
    "range_cap_m",
    "blur_schedule_m",
    "n_nodes",
    "max_steps",
    "model",
    "mask_unmapped",
    "search_xy_m",
    "search_yaw_rad",
    "search_step_yaw_rad",
    "search_blur_m",
    "search_exclude_m",
    "backend",
    "final_from_search",
)


def _jit_settings(cfg: FrontEndConfig, dt) -> tuple[tuple, dict]:
    """``(static, traced)``: the values of :data:`_STATIC_FIELDS` (a hashable tuple, the
    static key) and of :data:`_TRACED_FIELDS` as ``dt`` scalars: the jitted matcher's and
    scorer's view of ``cfg``."""
    static = tuple(getattr(cfg, f) for f in _STATIC_FIELDS)
    traced = {f: jnp.asarray(getattr(cfg, f), dt) for f in _TRACED_FIELDS}
    return static, traced


def _settings(static: tuple, traced: dict) -> types.SimpleNamespace:
    """The settings inside the jit, under :class:`FrontEndConfig`'s names: the static
    fields as Python values, the traced ones as arrays."""
    return types.SimpleNamespace(**dict(zip(_STATIC_FIELDS, static)), **traced)


def _match_impl(rates, seen, origin, az, rng, graze, pose0, pred, sigmas, static, traced):
    """Jitted core of :func:`match_scan` (settings from :func:`_jit_settings`): ``(pose
    [3], n_used, mean log-likelihood per used ray (nats), [3 3] information of the pose
    (negative Hessian of the last stage's log-likelihood in the tangent space))``."""
    from ..localization.refine import refine_pose

    cfg = _settings(static, traced)

    res = cfg.resolution_m
    n = rates.shape[0]
    spec = GridSpec(origin, res, (n, n))
    pose0 = se2(pose0)
    pred_pose = se2(pred)
    # rays whose end points fall in unmapped space are left out (judged at pose0)
    w = _ray_weights(seen, origin, res, az, rng, pose0, cfg)
    w = (w if cfg.mask_unmapped else jnp.ones_like(w)).astype(rates.dtype)
    inv_sig = 1.0 / sigmas
    zero = jnp.zeros((), rates.dtype)
    n_xy = int(round(cfg.search_xy_m / res))
    n_yaw = int(round(cfg.search_yaw_rad / cfg.search_step_yaw_rad))
    if n_xy > 0 or n_yaw > 0:
        # exhaustive end-point search on a lattice around pose0 (basin finding)
        sb = cfg.search_blur_m / res
        lam = _blur(rates, sb, cfg.backend) if sb > 0 else rates
        table = jnp.maximum(jnp.log(lam + cfg.rate_floor), cfg.ray_floor)
        hitw = w * (rng < cfg.range_cap_m)
        start, s_best, s_runner = correlative_search(
            table,
            origin,
            res,
            az,
            rng,
            hitw,
            xy_yaw(pose0),
            pred,
            inv_sig,
            n_xy=n_xy,
            n_yaw=n_yaw,
            step_yaw=cfg.search_step_yaw_rad,
            exclude_m=cfg.search_exclude_m,
        )
        start = se2(start)
    else:
        start, s_best, s_runner = pose0, zero, zero

    def whitened(p):
        """The pose's deviation from the prior's mean in prior standard deviations."""
        return jaxlie.manifold.rminus(p, pred_pose) * inv_sig

    def stage_objective(b, stiffness=1.0):
        if cfg.model == "endpoint":
            b = max(b, res / 2)  # a likelihood field needs some width
        field = SmoothDecayRateField(
            DecayRateMap(spec, _blur(rates, b / res, cfg.backend), zero),
            n_nodes=cfg.n_nodes,
            backend=cfg.backend,
        )
        gap = jnp.maximum(cfg.gap_cells * res, graze) + 2.0 * b

        def objective(p):
            ll = _scan_log_likelihoods(field, p, az, rng, cfg, gap)
            return jnp.sum(w * ll) - 0.5 * stiffness**2 * jnp.sum(whitened(p) ** 2)

        return field, objective

    stages = [stage_objective(b) for b in cfg.blur_schedule_m]
    field, final = stages[-1]
    # coarse to fine from the search's best (or pose0) ...
    pose = start
    for _, objective in stages:
        pose, _ = refine_pose(objective, pose, max_steps=cfg.max_steps)
    # ... and the last stage alone from pose0: a blurred stage, or the search's end-point
    # score (no free-space term), can lead into a wrong basin (a corridor's repeating
    # doors); the better final objective wins
    direct, _ = refine_pose(final, pose0, max_steps=cfg.max_steps)

    # the gate: gate_sigmas, or ambiguous_gate_sigmas where the search found a second,
    # nearly as good pose (margin below ambiguous_margin nats: a corridor, repeating doors)
    gate = cfg.gate_sigmas
    if n_xy > 0 or n_yaw > 0:
        tight = jnp.minimum(cfg.ambiguous_gate_sigmas, cfg.gate_sigmas)
        gate = jnp.where(s_best - s_runner < cfg.ambiguous_margin, tight, gate)

    def plausible(p):
        # within the gate (Mahalanobis) of the prior: a match farther off slid along a
        # corridor or snapped onto an aliased structure
        return jnp.sum(whitened(p) ** 2) <= gate**2

    candidates = [pose, direct]
    if (n_xy > 0 or n_yaw > 0) and cfg.final_from_search:
        # a third candidate: the last stage alone from the search's best (the blurred
        # stages can carry a good start into a neighbouring basin)
        candidates.append(refine_pose(final, start, max_steps=cfg.max_steps)[0])
    # the first of the best plausible ones (an implausible candidate scores -inf)
    scores = jnp.stack([jnp.where(plausible(c), final(c), -jnp.inf) for c in candidates])
    best = jnp.argmax(scores)
    pick = jnp.stack([c.parameters() for c in candidates])[best]
    ok = jnp.isfinite(scores[best])

    def stiff_fallback():
        # neither is plausible: the last stage from the prediction under a prior
        # ``gate_stiffness`` times tighter (the constrained directions still follow the
        # scan); if even that leaves the gate, the prediction itself
        _, stiff = stage_objective(cfg.blur_schedule_m[-1], cfg.gate_stiffness)
        q, _ = refine_pose(stiff, pred_pose, max_steps=cfg.max_steps)
        return jnp.where(plausible(q), q.parameters(), pred_pose.parameters())

    pose = jaxlie.SE2(jax.lax.cond(ok, lambda: pick, stiff_fallback))

    def data_term(delta):
        p = jaxlie.manifold.rplus(pose, delta)
        gap = jnp.maximum(cfg.gap_cells * res, graze)
        return jnp.sum(w * _scan_log_likelihoods(field, p, az, rng, cfg, gap))

    d0 = jnp.zeros(3, rates.dtype)
    n_used = jnp.sum(w)
    mean_ll = data_term(d0) / jnp.maximum(n_used, 1.0)
    info = -jax.hessian(data_term)(d0)
    return xy_yaw(pose), n_used, mean_ll, info, s_best, s_runner, ok


_match_jit = jax.jit(_match_impl, static_argnames="static")


@dataclasses.dataclass(frozen=True)
class MatchResult:
    """One scan-to-map match.

    Attributes:
        pose: ``[3]`` matched pose ``(x m, y m, yaw rad)``.
        n_used: rays in the objective.
        mean_log_likelihood: mean decay-rate log-likelihood per used ray (nats).
        information: ``[3 3]`` negative Hessian of the scan's log-likelihood at the match in
            the pose's tangent space (``(v_x m, v_y m, omega rad)``, sensor frame).
    """

    pose: np.ndarray
    n_used: int
    mean_log_likelihood: float
    information: np.ndarray
    search_score: float = 0.0
    search_runner_up: float = 0.0
    plausible: bool = True

    @property
    def min_translation_information(self) -> float:
        """Smallest eigenvalue of the translation block of :attr:`information` (1/m^2):
        small in a corridor, where the match slides along the walls."""
        return float(np.linalg.eigvalsh(self.information[:2, :2])[0])


def _window_inputs(grid: GridMap, center_xy, azimuths, ranges, cfg: FrontEndConfig, dt):
    """The jitted matcher's and scorer's map and scan inputs, as ``dt`` arrays: the
    model's rates in the window around ``center_xy`` (the hit indicator for the endpoint
    model), its traversed cells, its lower corner (m), the scan's azimuths and ranges and
    its grazing lengths (:func:`_grazing`)."""
    h, r, origin = grid.window(center_xy, cfg.window_cells)
    seen = r > 1e-9
    if cfg.model == "endpoint":
        rates = (h > 0).astype(float)
    elif cfg.prior_length_m > 0:
        rates = (h + cfg.prior_hits) / (r + cfg.prior_length_m)
    else:
        rates = np.where(seen, h / np.where(seen, r, 1.0), 0.0)
    return (
        jnp.asarray(rates, dt),
        jnp.asarray(seen),
        jnp.asarray(origin, dt),
        jnp.asarray(azimuths, dt),
        jnp.asarray(ranges, dt),
        jnp.asarray(_grazing(azimuths, ranges, cfg), dt),
    )


def _score_impl(rates, seen, origin, az, rng, graze, pose, static, traced):
    """Jitted core of :func:`score_scan` (settings from :func:`_jit_settings`): ``(mean
    log-likelihood per used ray, n_used)`` of the last matching stage's data term at
    ``pose``."""
    cfg = _settings(static, traced)
    res = cfg.resolution_m
    n = rates.shape[0]
    b = cfg.blur_schedule_m[-1]
    if cfg.model == "endpoint":
        b = max(b, res / 2)  # as the match's last stage
    field = SmoothDecayRateField(
        DecayRateMap(
            GridSpec(origin, res, (n, n)),
            _blur(rates, b / res, cfg.backend),
            jnp.zeros((), rates.dtype),
        ),
        n_nodes=cfg.n_nodes,
        backend=cfg.backend,
    )
    p = se2(pose)
    w = _ray_weights(seen, origin, res, az, rng, p, cfg)
    w = (w if cfg.mask_unmapped else jnp.ones_like(w)).astype(rates.dtype)
    gap = jnp.maximum(cfg.gap_cells * res, graze)
    n_used = jnp.sum(w)
    ll = jnp.sum(w * _scan_log_likelihoods(field, p, az, rng, cfg, gap))
    return ll / jnp.maximum(n_used, 1.0), n_used


_score_jit = jax.jit(_score_impl, static_argnames="static")


def score_scan(
    grid: GridMap,
    azimuths: Float[Array, " b"],
    ranges: Float[Array, " b"],
    pose_xy_yaw: np.ndarray,
    cfg: FrontEndConfig,
) -> tuple[float, int]:
    """One scan's fit to a map at a given pose, without matching: the mean log-likelihood
    per used ray (nats) of :func:`match_scan`'s last stage (its data term, no prior) and
    the number of used rays, with the rays ending in unmapped cells left out (judged at
    ``pose_xy_yaw``).

    Args:
        grid: the map statistics.
        azimuths: ``[b]`` beam angles (rad); ranges: ``[b]`` readings (m).
        pose_xy_yaw: ``[3]`` the scan's pose ``(x m, y m, yaw rad)``.
        cfg: settings (model, resolution, range cap, window, last blur, ...).

    Returns:
        ``(mean log-likelihood per used ray, n_used)``; ``(0.0, 0)`` when no ray is used.
    """
    pose = np.asarray(pose_xy_yaw, float)
    if pose.shape != (3,) or not np.all(np.isfinite(pose)):
        raise ValueError(f"pose_xy_yaw must be 3 finite numbers, got {pose_xy_yaw!r}")
    context, dt = cfg.precision()
    with context:
        inputs = _window_inputs(grid, pose[:2], azimuths, ranges, cfg, dt)
        mean_ll, n_used = _score_jit(*inputs, jnp.asarray(pose, dt), *_jit_settings(cfg, dt))
    return float(mean_ll), int(n_used)


def match_scan(
    grid: GridMap,
    azimuths: Float[Array, " b"],
    ranges: Float[Array, " b"],
    pose0_xy_yaw: np.ndarray,
    cfg: FrontEndConfig,
    *,
    prior_xy_yaw: np.ndarray | None = None,
    prior_sigmas: np.ndarray | None = None,
) -> MatchResult:
    """Match one scan against the map window around ``pose0_xy_yaw``: coarse-to-fine
    maximisation of its decay-rate log-likelihood plus the Gaussian prior.

    Args:
        grid: the map statistics.
        azimuths: ``[b]`` beam angles (rad); ranges: ``[b]`` readings (m).
        pose0_xy_yaw: ``[3]`` start pose ``(x m, y m, yaw rad)``.
        cfg: settings.
        prior_xy_yaw: ``[3]`` mean of the Gaussian pose prior (default: the start pose).
        prior_sigmas: ``[3]`` its standard deviations (m, m, rad) in the prior's frame
            (default: ``cfg.prior_sigma_xy_m`` twice and ``cfg.prior_sigma_yaw_rad``).

    Returns:
        :class:`MatchResult`.
    """
    pose0 = np.asarray(pose0_xy_yaw, float)
    prior = pose0 if prior_xy_yaw is None else np.asarray(prior_xy_yaw, float)
    if prior_sigmas is None:
        prior_sigmas = (cfg.prior_sigma_xy_m, cfg.prior_sigma_xy_m, cfg.prior_sigma_yaw_rad)
    sig = np.asarray(prior_sigmas, float)
    if sig.shape != (3,) or not np.all(np.isfinite(sig) & (sig > 0)):
        raise ValueError(f"prior_sigmas must be 3 positive finite numbers, got {sig}")
    context, dt = cfg.precision()
    with context:
        inputs = _window_inputs(grid, pose0[:2], azimuths, ranges, cfg, dt)
        pose, n_used, mean_ll, info, s_best, s_runner, ok = _match_jit(
            *inputs,
            jnp.asarray(pose0, dt),
            jnp.asarray(prior, dt),
            jnp.asarray(sig, dt),
            *_jit_settings(cfg, dt),
        )
    return MatchResult(
        np.asarray(pose, float),
        int(n_used),
        float(mean_ll),
        np.asarray(info, float),
        float(s_best),
        float(s_runner),
        bool(ok),
    )


@dataclasses.dataclass(frozen=True)
class FrontEndResult:
    """Output of :func:`run_front_end`.

    Attributes:
        poses: ``[N 3]`` matched poses ``(x m, y m, yaw rad)``.
        n_used: ``[N]`` rays in each scan's objective (0 for the first scan).
        seconds: wall time of the run (s), first compilation included.
        seconds_per_scan: ``[N]`` wall time per scan (s).
        grid: the final :class:`GridMap`.
        information: ``[N 3 3]`` each match's :attr:`MatchResult.information` (the
            scan's log-likelihood alone, no prior; zeros for the first scan).
        plausible: ``[N]`` bool, False where neither candidate of the match passed the
            gate and the fallback was taken (True for the first scan).
    """

    poses: np.ndarray
    n_used: np.ndarray
    seconds: float
    seconds_per_scan: np.ndarray
    grid: GridMap
    information: np.ndarray | None = None
    plausible: np.ndarray | None = None


def odometry_sigmas(increments: np.ndarray, cfg: FrontEndConfig) -> np.ndarray:
    """``[E 3]`` standard deviations (m, m, rad) of ``[E 3]`` odometry increments under the
    front end's noise model (``cfg.odometry_sigma_*``): the front end's prior on each
    increment, and the weights of the pose graph's and the back ends' odometry factors."""
    inc = np.asarray(increments, float)
    d = np.hypot(inc[:, 0], inc[:, 1])
    sxy = cfg.odometry_sigma_xy_m + cfg.odometry_sigma_rel * d
    syaw = (
        cfg.odometry_sigma_yaw_rad
        + cfg.odometry_sigma_yaw_per_m * d
        + cfg.odometry_sigma_yaw_rel * np.abs(inc[:, 2])
    )
    return np.stack([sxy, sxy, syaw], 1)


def _check_inputs(ranges_m, azimuths_rad, odometry_xy_yaw):
    rng = np.asarray(ranges_m, dtype=float)
    az = np.asarray(azimuths_rad, dtype=float)
    odo = np.asarray(odometry_xy_yaw, dtype=float)
    if rng.ndim != 2 or rng.shape[0] == 0 or rng.shape[1] == 0:
        raise ValueError(f"ranges_m must have shape [N, B] with N, B > 0, got {rng.shape}")
    if az.shape != (rng.shape[1],):
        raise ValueError(f"azimuths_rad must have shape [{rng.shape[1]}], got {az.shape}")
    if odo.shape != (rng.shape[0], 3):
        raise ValueError(f"odometry_xy_yaw must have shape [{rng.shape[0]}, 3], got {odo.shape}")
    if not np.all(np.isfinite(rng)) or np.any(rng < 0):
        raise ValueError("ranges_m must be finite and >= 0 (give no-returns as the max reading)")
    if not np.all(np.isfinite(az)):
        raise ValueError("azimuths_rad must be finite")
    if not np.all(np.isfinite(odo)):
        raise ValueError("odometry_xy_yaw must be finite")
    return rng, az, odo


def run_front_end(
    ranges_m: np.ndarray,
    azimuths_rad: np.ndarray,
    odometry_xy_yaw: np.ndarray,
    cfg: FrontEndConfig | None = None,
    *,
    initial_pose: np.ndarray | None = None,
    progress: bool = False,
) -> FrontEndResult:
    """Decay-rate lidar odometry: match every scan against the map of the scans before it
    (the last ``cfg.local_map_scans`` of them, 100 by default; 0: all of them).

    Args:
        ranges_m: ``[N B]`` readings (m); no-returns as the sensor's maximum reading (any
            value ``>= cfg.range_cap_m`` is treated as one).
        azimuths_rad: ``[B]`` beam angles (rad).
        odometry_xy_yaw: ``[N 3]`` raw odometry poses; only increments are used.
        cfg: settings (default :class:`FrontEndConfig`).
        initial_pose: ``[3]`` pose of the first scan (default: the first odometry pose).
        progress: show a tqdm progress bar.

    Returns:
        :class:`FrontEndResult`.

    Raises:
        ValueError: bad shapes or values, naming the argument.
    """
    cfg = FrontEndConfig() if cfg is None else cfg
    rng, az, odo = _check_inputs(ranges_m, azimuths_rad, odometry_xy_yaw)
    n = rng.shape[0]
    poses = np.zeros((n, 3))
    poses[0] = odo[0] if initial_pose is None else np.asarray(initial_pose, float)
    n_used = np.zeros(n, dtype=np.int64)
    info = np.zeros((n, 3, 3))
    plausible = np.ones(n, bool)
    secs = np.zeros(n)
    grid = grid_map(cfg)
    t_start = time.perf_counter()
    grid.add_scan(poses[0], az, rng[0])
    secs[0] = time.perf_counter() - t_start
    inc = between_np(odo[:-1], odo[1:])
    sigmas = odometry_sigmas(inc, cfg)  # the prior of each match
    it = range(1, n)
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(it, desc="front end", unit="scan")
    for k in it:
        t0 = time.perf_counter()
        pred = compose_np(poses[k - 1], inc[k - 1])
        m = match_scan(grid, az, rng[k], pred, cfg, prior_sigmas=sigmas[k - 1])
        poses[k], n_used[k] = m.pose, m.n_used
        info[k], plausible[k] = m.information, m.plausible
        grid.add_scan(poses[k], az, rng[k])
        old = k - cfg.local_map_scans
        if cfg.local_map_scans > 0 and old >= 0:
            grid.add_scan(poses[old], az, rng[old], sign=-1.0)
        secs[k] = time.perf_counter() - t0
    return FrontEndResult(poses, n_used, time.perf_counter() - t_start, secs, grid, info, plausible)
