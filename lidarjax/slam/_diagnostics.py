"""The scan matcher's own error, apart from drift: every scan matched against the map of
the scans before it at reference poses (a log's corrected poses, a simulation's truth)."""

from __future__ import annotations

import dataclasses
import operator

import numpy as np

from ._front_end import (
    FrontEndConfig,
    _check_inputs,
    between_np,
    grid_map,
    match_scan,
    odometry_sigmas,
)


@dataclasses.dataclass(frozen=True)
class ReferenceMatchErrors:
    """Output of :func:`reference_match_errors`.

    Attributes:
        indices: ``[M]`` the matched scans.
        errors: ``[M 3]`` each match's pose in its reference pose's frame: ``(forward m,
            left m, yaw rad)``; positive forward means the match lies ahead of the
            reference along the scan's heading.
        n_used: ``[M]`` rays in each match's objective.
    """

    indices: np.ndarray
    errors: np.ndarray
    n_used: np.ndarray

    @property
    def mean(self) -> np.ndarray:
        """``[3]`` mean error (m, m, rad): the matcher's bias."""
        return self.errors.mean(axis=0)

    @property
    def median_abs(self) -> np.ndarray:
        """``[3]`` median absolute error (m, m, rad)."""
        return np.median(np.abs(self.errors), axis=0)

    @property
    def standard_error(self) -> np.ndarray:
        """``[3]`` standard error of :attr:`mean` (m, m, rad)."""
        m = self.errors.shape[0]
        return self.errors.std(axis=0, ddof=1) / np.sqrt(m) if m > 1 else np.full(3, np.nan)

    def summary(self) -> dict:
        """Plain numbers (mm and millidegrees) for a results file."""
        scale = np.array([1e3, 1e3, np.rad2deg(1.0) * 1e3])
        return {
            "n_matches": int(self.errors.shape[0]),
            "mean_forward_mm": float(self.mean[0] * scale[0]),
            "mean_left_mm": float(self.mean[1] * scale[1]),
            "mean_yaw_mdeg": float(self.mean[2] * scale[2]),
            "standard_error_forward_mm": float(self.standard_error[0] * scale[0]),
            "median_abs_forward_mm": float(self.median_abs[0] * scale[0]),
            "median_abs_left_mm": float(self.median_abs[1] * scale[1]),
            "median_abs_yaw_mdeg": float(self.median_abs[2] * scale[2]),
        }


def _count(value, name: str, least: int) -> int:
    if isinstance(value, bool):
        raise TypeError(f"{name} must be an integer, got {value!r}")
    try:
        v = operator.index(value)
    except TypeError:
        raise TypeError(f"{name} must be an integer, got {value!r}") from None
    if v < least:
        raise ValueError(f"{name} must be >= {least}, got {v}")
    return v


def reference_match_errors(
    ranges_m: np.ndarray,
    azimuths_rad: np.ndarray,
    poses_xy_yaw: np.ndarray,
    cfg: FrontEndConfig | None = None,
    *,
    every: int = 1,
    local_scans: int = 0,
    progress: bool = False,
) -> ReferenceMatchErrors:
    """Match scans against the map of the scans before them placed at reference poses,
    each started at (and with the front end's prior centred on) its own reference pose:
    the matcher's error with no drift and no error in the map's poses. Its mean is the
    matcher's bias against a map at correct poses. A front end's map is built at its own
    poses, so its increments can carry less of that bias (on intel, stop 60 of the
    results: +11 mm here, under 1 mm per increment in the front end). One match per
    matched scan and one map update per scan: intel's 910 scans with ``every=3`` take
    about a minute on 2 cores.

    Args:
        ranges_m: ``[N B]`` readings (m); no-returns as the maximum reading.
        azimuths_rad: ``[B]`` beam angles (rad).
        poses_xy_yaw: ``[N 3]`` reference poses ``(x m, y m, yaw rad)``.
        cfg: the front end's settings (default :class:`FrontEndConfig`); its model,
            resolution, blurs, gaps and rate priors are the ones measured. The prior's
            standard deviations are :func:`odometry_sigmas` of the reference increment.
        every: match every ``every``-th scan (scans ``every, 2 every, ...``); every scan is
            added to the map.
        local_scans: > 0: the map holds only the last ``local_scans`` scans (as
            ``FrontEndConfig.local_map_scans``); 0: all scans before.
        progress: show a tqdm progress bar.

    Returns:
        :class:`ReferenceMatchErrors`.

    Raises:
        ValueError, TypeError: bad shapes or values, naming the argument.
    """
    cfg = FrontEndConfig() if cfg is None else cfg
    ref = np.asarray(poses_xy_yaw, dtype=float)
    n_scans = np.shape(ranges_m)[0] if np.ndim(ranges_m) == 2 else None
    if ref.ndim != 2 or ref.shape[1] != 3 or (n_scans is not None and ref.shape[0] != n_scans):
        raise ValueError(
            f"poses_xy_yaw must have shape [N, 3] with N = len(ranges_m), got {ref.shape}"
        )
    if not np.all(np.isfinite(ref)):
        raise ValueError("poses_xy_yaw must be finite")
    rng, az, ref = _check_inputs(ranges_m, azimuths_rad, ref)
    every = _count(every, "every", 1)
    local_scans = _count(local_scans, "local_scans", 0)
    n = rng.shape[0]
    if n < 2:
        raise ValueError(f"ranges_m must hold at least 2 scans, got {n}")
    inc = between_np(ref[:-1], ref[1:])
    sigmas = odometry_sigmas(inc, cfg)
    grid = grid_map(cfg)
    grid.add_scan(ref[0], az, rng[0])
    idx, err, used = [], [], []
    it = range(1, n)
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(it, desc="reference matches", unit="scan")
    for k in it:
        if k % every == 0:
            m = match_scan(grid, az, rng[k], ref[k], cfg, prior_sigmas=sigmas[k - 1])
            idx.append(k)
            err.append(between_np(ref[k][None], m.pose[None])[0])
            used.append(m.n_used)
        grid.add_scan(ref[k], az, rng[k])
        if local_scans > 0 and k - local_scans >= 0:
            old = k - local_scans
            grid.add_scan(ref[old], az, rng[old], sign=-1.0)
    if not idx:
        raise ValueError(f"every = {every} matches no scan of the {n} given")
    return ReferenceMatchErrors(
        np.asarray(idx, dtype=np.int64), np.asarray(err, float), np.asarray(used, np.int64)
    )


__all__ = ["ReferenceMatchErrors", "reference_match_errors"]
