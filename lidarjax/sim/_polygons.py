"""Random star-shaped polygons and full-revolution scans of them (dissertation section 10.5).

The simulated experiments of section 10.5 draw a random polygon with 3, 4, 5, 6, 12, 36 or
180 vertices around the sensor and sample a noisy 360-ray scan from it: Gaussian noise on
the ray angles (0.2 deg), the exact intersection of each perturbed ray with the polygon,
then Gaussian noise on the ranges (0.03 m). NumPy in and out (the intersection is
:func:`~lidarjax.raytrace.ray_segment`, in float64); deterministic given the seeds.
"""

from __future__ import annotations

import operator

import jax
import numpy as np

from ..raytrace import first_segment_hit

__all__ = ["random_polygon", "simulate_polygon_scan"]

# First hits of rays [K 2] from one origin on the polygon's edges (start -> end) [n 2].
_first_hits = jax.jit(jax.vmap(lambda *a: first_segment_hit(*a)[0], in_axes=(None, 0, None, None)))


def random_polygon(
    n_vertices: int,
    *,
    seed: int,
    radius_range_m: tuple[float, float] = (1.0, 10.0),
) -> np.ndarray:
    """Draw a random simple polygon that is star-shaped around the origin (the sensor).

    The vertex angles are sorted uniform draws on ``[-pi, pi)``; they are redrawn until every
    angular gap between consecutive vertices (including the wrap-around gap) is positive and
    smaller than ``pi``, which guarantees that the origin lies strictly inside the polygon.
    The vertex radii are then drawn uniformly from ``radius_range_m``. Because the angles
    increase strictly, the polygon is simple and its vertices are counter-clockwise.

    Args:
        n_vertices: number of vertices ``n``, at least 3.
        seed: seed for ``np.random.default_rng``.
        radius_range_m: ``(low, high)`` vertex distance from the origin in metres, with
            ``0 < low <= high``.

    Returns:
        ``[n 2]`` float64 vertices (m) in counter-clockwise order.

    Raises:
        TypeError: if ``n_vertices`` is not an integer.
        ValueError: if ``n_vertices < 3`` or ``radius_range_m`` is not a valid range.
    """
    if isinstance(n_vertices, bool):
        raise TypeError(f"n_vertices must be an integer, got {n_vertices!r}")
    n = operator.index(n_vertices)
    if n < 3:
        raise ValueError(f"n_vertices must be at least 3, got {n}")
    rr = np.asarray(radius_range_m, dtype=float)
    if rr.shape != (2,) or not np.all(np.isfinite(rr)) or not 0.0 < rr[0] <= rr[1]:
        raise ValueError(
            f"radius_range_m must be (low, high) with 0 < low <= high, got {radius_range_m!r}"
        )

    rng = np.random.default_rng(seed)
    while True:
        angles = np.sort(rng.uniform(-np.pi, np.pi, n))
        gaps = np.diff(angles, append=angles[0] + 2.0 * np.pi)
        if np.all(gaps > 0.0) and np.all(gaps < np.pi):
            break
    radii = rng.uniform(rr[0], rr[1], n)
    return np.column_stack([radii * np.cos(angles), radii * np.sin(angles)])


def simulate_polygon_scan(
    polygon: np.ndarray,
    *,
    n_rays: int = 360,
    angular_sigma_rad: float = float(np.deg2rad(0.2)),
    radial_sigma_m: float = 0.03,
    seed: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Simulate a noisy full-revolution lidar scan from the origin inside a polygon.

    Ray ``k`` has the nominal azimuth ``-pi + 2 pi k / K``. Its angle is perturbed by
    ``N(0, angular_sigma_rad^2)``, the perturbed ray is intersected exactly with the polygon
    (first hit in front of the sensor) and ``N(0, radial_sigma_m^2)`` is added to the
    resulting range, which is clipped at 0. All rays are processed at once (``[K n]`` work).

    Args:
        polygon: ``[n 2]`` polygon vertices (m), ``n >= 3``, in either orientation; the
            closing edge from the last to the first vertex is implied. It must enclose the
            origin, so that every ray hits it.
        n_rays: number of rays ``K`` per revolution, at least 1.
        angular_sigma_rad: standard deviation (rad) of the ray-angle noise, ``>= 0``.
        radial_sigma_m: standard deviation (m) of the range noise, ``>= 0``.
        seed: seed for ``np.random.default_rng``; the angular noise is drawn first, then
            the radial noise.

    Returns:
        ``(azimuths, ranges)``: ``[K]`` float64 nominal ray azimuths (rad, in ``[-pi, pi)``)
        and ``[K]`` float64 noisy ranges (m, ``>= 0``).

    Raises:
        ValueError: on a malformed polygon, a bad ``n_rays`` or negative / non-finite noise
            level, or if some ray misses the polygon (the origin is not enclosed).
    """
    poly = np.asarray(polygon, dtype=float)
    if poly.ndim != 2 or poly.shape[1] != 2 or poly.shape[0] < 3:
        raise ValueError(f"polygon must have shape [n 2] with n >= 3, got {poly.shape}")
    if not np.all(np.isfinite(poly)):
        raise ValueError("polygon must have finite coordinates")
    if isinstance(n_rays, bool):
        raise TypeError(f"n_rays must be an integer, got {n_rays!r}")
    k = operator.index(n_rays)
    if k < 1:
        raise ValueError(f"n_rays must be at least 1, got {k}")
    for name, value in (
        ("angular_sigma_rad", angular_sigma_rad),
        ("radial_sigma_m", radial_sigma_m),
    ):
        if not (np.isfinite(value) and value >= 0.0):
            raise ValueError(f"{name} must be finite and non-negative, got {value!r}")

    rng = np.random.default_rng(seed)
    azimuths = -np.pi + 2.0 * np.pi * np.arange(k) / k
    phi = azimuths + rng.normal(0.0, angular_sigma_rad, k)
    range_noise = rng.normal(0.0, radial_sigma_m, k)

    dirs = np.stack([np.cos(phi), np.sin(phi)], axis=-1)  # [K 2] ray directions
    with jax.enable_x64(True):  # float64 whatever JAX's default
        true_ranges = np.asarray(_first_hits(np.zeros(2), dirs, poly, np.roll(poly, -1, axis=0)))
    if not np.all(np.isfinite(true_ranges)):
        raise ValueError("polygon must enclose the origin: some rays do not hit it")

    ranges = np.maximum(true_ranges + range_noise, 0.0)
    return azimuths, ranges
