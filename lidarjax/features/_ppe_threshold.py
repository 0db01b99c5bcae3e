"""PPE's stopping threshold ``e`` (dissertation ch. 11; issue #20): the scan's noise
estimate, the default rule ``e = max(κ σ̂², e_floor)`` (``max_increment="auto"``) and the
resolution of the ``max_increment`` / ``max_increments`` arguments to numbers (m²).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from jaxtyping import ArrayLike, Float

from ._ppe_scan import _check_scan, _neighbours, _tetromino_costs, _tetromino_table

__all__ = ["estimate_noise", "auto_max_increment", "AUTO_KAPPA", "AUTO_FLOOR_M2"]

_CHI2_1_MEDIAN = 0.45493642311957283  # median of the chi-squared distribution with 1 dof


def estimate_noise(points: Float[ArrayLike, "H W 3"]) -> float:
    """Robust estimate of the radial noise ``σ`` (m) of an organized scan.

    Each tetromino's creation cost ``e_crt`` is the minimised error of a plane fitted to 4
    rays, so on a plane it is ``σ² χ²(1)`` distributed (4 rays, 3 plane parameters; the
    ray-path residual of radial noise does not depend on the incidence angle). Tetrominoes
    across edges are outliers, hence the median: ``σ = sqrt(median(e_crt) / 0.455)``.
    Lets a threshold ``e = κ σ²`` carry over between sensors of different noise.

    Raises:
        ValueError: As :func:`extract_planes` for bad ``points``, or if the scan holds no
            complete tetromino.
    """
    pts, valid = _check_scan(points)
    sigma = _noise_sigma(pts, valid)
    if math.isnan(sigma):
        raise ValueError("points: the scan holds no 4 valid neighbouring rays")
    return sigma


def _noise_sigma(pts: np.ndarray, valid: np.ndarray) -> float:
    """:func:`estimate_noise` of checked inputs; NaN if the scan holds no tetromino."""
    K = valid.size
    flat = np.where(valid[..., None], pts, 0.0).reshape(K, 3)
    nbr = _neighbours(pts, valid, math.inf)
    _, _, cells = _tetromino_table(valid, nbr)
    if cells.shape[0] == 0:
        return math.nan
    return float(np.sqrt(np.median(_tetromino_costs(flat, cells)) / _CHI2_1_MEDIAN))


AUTO_KAPPA = 200.0
"""``κ`` of the default threshold rule ``e = max(κ σ̂², e_floor)`` (:func:`auto_max_increment`)."""

AUTO_FLOOR_M2 = 0.01
"""``e_floor`` (m²) of the default threshold rule ``e = max(κ σ̂², e_floor)``."""


def auto_max_increment(points: Float[ArrayLike, "H W 3"]) -> float:
    """The default PPE stopping threshold ``e = max(κ σ̂², e_floor)`` in m² (``"auto"``).

    ``σ̂`` is :func:`estimate_noise` (from the median 4-ray plane-fit error of the scan),
    ``κ =`` :data:`AUTO_KAPPA` ``= 200`` and ``e_floor =`` :data:`AUTO_FLOOR_M2`
    ``= 0.01 m²`` (one ray 10 cm off its plane).

    - ``κ σ̂²`` follows the noise where it is radial and homoscedastic: at 20 mm it is
      0.08 m², the threshold tuned on the 20 mm training scans (``κ`` = 100-400 does
      equally well there).
    - The floor is needed because ``σ̂`` is a *median*: it describes the rays seen near
      normal incidence. Angular noise ``δ`` adds a ray-path error ``≈ r δ tan θ`` that
      grows with the range ``r`` and the incidence angle ``θ`` (1.2 cm at 5 m and 80° for
      25 mdeg), and the rays next to plane edges carry larger errors still. At low radial
      noise (``σ̂ = 0.4-1 mm``) ``200 σ̂²`` is only ``3e-5 - 2e-4 m²``: planes seen at
      grazing incidence are cut into pieces and hundreds of small spurious planes remain.
    - The value: on generated SynPEB-style training scans (500 x 500 rays; radial noise
      0.4-20 mm with 1 mdeg angular noise, and 0.4 mm with 10 and 25 mdeg) the fraction of
      correctly found planes stays within 2 points of its best at every noise level for
      floors from 0.003 to 0.03 m² (without a floor it falls to 73 % at 25 mdeg; above
      0.03 m² small planes start to be absorbed by their neighbours; on the shared real
      SynPEB crop the plateau is 0.002-0.1 m²). 0.01 m² is the middle on a log scale.
      Results on held-out test scans: README, Table 11.1 per noise level.

    A scan without 4 valid neighbouring rays creates no plane; its threshold is the floor.

    Args:
        points: ``[H, W, 3]`` organized scan, sensor at the origin (m), NaN = no return.

    Returns:
        ``e`` in m².

    Raises:
        ValueError: As :func:`extract_planes` for bad ``points``.
    """
    pts, valid = _check_scan(points)
    sigma = _noise_sigma(pts, valid)
    if math.isnan(sigma):
        return AUTO_FLOOR_M2
    return max(AUTO_KAPPA * sigma * sigma, AUTO_FLOOR_M2)


def _resolve_increment(points, max_increment, max_planes):
    """``max_increment`` as a float (``"auto"`` -> :func:`auto_max_increment`) or None;
    refuses a call without any stopping criterion."""
    if isinstance(max_increment, str) or isinstance(max_increment, bool):
        if max_increment == "auto":
            return auto_max_increment(points)
        raise ValueError(
            f"max_increment must be 'auto', a number (m²) or None, got {max_increment!r}"
        )
    if max_increment is None and max_planes is None:
        raise ValueError(
            "max_increment=None and max_planes=None: PPE needs a stopping criterion, "
            "otherwise it merges the whole scan into one plane. Pass max_increment='auto' "
            "(the default rule), a threshold e in m², and/or max_planes; "
            "max_increment=math.inf clusters until no action is left"
        )
    return max_increment


def _resolve_increments(points, max_increments: Sequence[float | str]) -> list[float]:
    """Every entry of ``max_increments`` as a threshold in m² (``"auto"`` ->
    :func:`auto_max_increment`, computed once); ``math.inf`` = no threshold.

    Raises:
        ValueError: Naming ``max_increments`` if it is a string or empty, or an entry is
            None, a bool, not a number or negative.
    """
    if isinstance(max_increments, str):
        raise ValueError(
            f"max_increments must be a sequence of thresholds (m²) or 'auto', got "
            f"{max_increments!r}"
        )
    raw = list(max_increments)
    if not raw:
        raise ValueError("max_increments must not be empty")
    auto = None
    incs = []
    for e in raw:
        if e is None:
            raise ValueError("max_increments: use math.inf, not None, for 'no threshold'")
        if isinstance(e, str) and e == "auto":
            auto = auto_max_increment(points) if auto is None else auto
            e = auto
        elif isinstance(e, str) or isinstance(e, bool):
            raise ValueError(f"max_increments entry must be 'auto' or a number (m²), got {e!r}")
        try:
            e = float(e)
        except (TypeError, ValueError):
            raise ValueError(
                f"max_increments entry must be 'auto' or a number (m²), got {e!r}"
            ) from None
        if not e >= 0:
            raise ValueError(f"max_increments entry must be >= 0 (m²), got {e}")
        incs.append(e)
    return incs
