"""Spinning multi-beam lidar specification (:class:`LidarSpec`) and the HDL-32E preset.

Ray ``(ring i, column j)`` of a :class:`LidarSpec` has the elevation ``elevations_rad[i]``
and the azimuth ``2 pi j / n_azimuths`` in the sensor frame (``x`` forward, ``y`` left,
``z`` up). The urban simulator (:func:`~lidarjax.sim.simulate_urban_scan`) casts these rays.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from ._urban_common import check_nonneg, wrap_angle

__all__ = ["HDL32E_ELEVATIONS_DEG", "LidarSpec", "hdl32e"]

HDL32E_ELEVATIONS_DEG = np.linspace(-30.67, 10.67, 32)
HDL32E_ELEVATIONS_DEG.flags.writeable = False


@dataclasses.dataclass(frozen=True, eq=False)
class LidarSpec:
    """A spinning multi-beam lidar.

    Ray ``(ring i, column j)`` has elevation ``elevations_rad[i]`` and azimuth
    ``2 pi j / n_azimuths`` (wrapped to ``[-pi, pi)``; ``atan2(y, x)`` in the sensor frame,
    column 0 looks forward).

    Attributes:
        elevations_rad: ``[n_rings]`` float64 ring elevations (rad), each in ``(-pi/2, pi/2)``.
        n_azimuths: Columns per turn (2170 gives ~70 000 rays for 32 rings).
        max_range_m: Returns with a measured range above this are dropped (m).
        min_range_m: Returns with a measured range below this are dropped (m).
        range_noise_m: Standard deviation of the Gaussian radial noise (m).
        mount_height_m: Sensor height above the ground (m).
    """

    elevations_rad: np.ndarray
    n_azimuths: int = 2170
    max_range_m: float = 80.0
    min_range_m: float = 1.0
    range_noise_m: float = 0.02
    mount_height_m: float = 1.73

    def __post_init__(self) -> None:
        elev = np.array(self.elevations_rad, dtype=np.float64)
        if elev.ndim != 1 or elev.size < 1:
            raise ValueError(f"elevations_rad must have shape [n_rings >= 1], got {elev.shape}")
        if not np.all(np.isfinite(elev)) or np.any(np.abs(elev) >= np.pi / 2 - 1e-6):
            raise ValueError("elevations_rad must be finite and inside (-pi/2, pi/2)")
        elev.flags.writeable = False
        object.__setattr__(self, "elevations_rad", elev)
        if isinstance(self.n_azimuths, bool) or int(self.n_azimuths) != self.n_azimuths:
            raise ValueError(f"n_azimuths must be an integer, got {self.n_azimuths!r}")
        if int(self.n_azimuths) < 1:
            raise ValueError(f"n_azimuths must be >= 1, got {self.n_azimuths}")
        object.__setattr__(self, "n_azimuths", int(self.n_azimuths))
        check_nonneg(self.min_range_m, "min_range_m")
        if not (math.isfinite(self.max_range_m) and self.max_range_m > self.min_range_m):
            raise ValueError(
                f"max_range_m must be finite and > min_range_m, got {self.max_range_m}"
            )
        check_nonneg(self.range_noise_m, "range_noise_m")
        if not (math.isfinite(self.mount_height_m) and self.mount_height_m > 0):
            raise ValueError(f"mount_height_m must be > 0, got {self.mount_height_m}")

    @property
    def n_rings(self) -> int:
        return int(self.elevations_rad.size)

    @property
    def n_rays(self) -> int:
        return self.n_rings * self.n_azimuths

    @property
    def azimuths_rad(self) -> np.ndarray:
        """``[n_azimuths]`` column azimuths (rad) in ``[-pi, pi)``."""
        return wrap_angle(2 * np.pi * np.arange(self.n_azimuths) / self.n_azimuths)

    def directions(self) -> np.ndarray:
        """``[n_rings * n_azimuths, 3]`` unit ray directions in the sensor frame.

        Ring-major: ray ``i * n_azimuths + j`` is ring ``i``, column ``j``.
        """
        return _directions(self.elevations_rad.tobytes(), self.n_azimuths)

    @staticmethod
    def hdl32e(**overrides) -> LidarSpec:
        """HDL-32E-like lidar; see :func:`hdl32e`."""
        return hdl32e(**overrides)


@functools.lru_cache(maxsize=16)
def _directions(elev_bytes: bytes, n_az: int) -> np.ndarray:
    elev = np.frombuffer(elev_bytes, dtype=np.float64)
    az = 2 * np.pi * np.arange(n_az) / n_az
    ce, se = np.cos(elev)[:, None], np.sin(elev)[:, None]
    d = np.stack(
        [ce * np.cos(az)[None], ce * np.sin(az)[None], np.broadcast_to(se, (elev.size, n_az))],
        axis=-1,
    ).reshape(-1, 3)
    d.flags.writeable = False
    return d


def hdl32e(**overrides) -> LidarSpec:
    """Velodyne HDL-32E-like lidar: 32 rings from -30.67 to +10.67 deg, 2170 azimuths.

    Args:
        **overrides: Any :class:`LidarSpec` field (e.g. ``n_azimuths=360``).

    Returns:
        The lidar specification.
    """
    kwargs = {"elevations_rad": np.deg2rad(HDL32E_ELEVATIONS_DEG)}
    kwargs.update(overrides)
    return LidarSpec(**kwargs)
