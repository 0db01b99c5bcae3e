"""Random star-shaped polygons and full-revolution scans of them (dissertation section 10.5).

The simulated experiments of section 10.5 draw a random polygon with 3, 4, 5, 6, 12, 36 or
180 vertices around the sensor and sample a noisy 360-ray scan from it: Gaussian noise on
the ray angles (0.2 deg), the exact intersection of each perturbed ray with the polygon,
then Gaussian noise on the ranges (0.03 m). NumPy only; deterministic given the seeds.
"""

from __future__ import annotations

import operator

import numpy as np

__all__ = ["random_polygon", "simulate_polygon_scan"]

# Relative slack on the edge parameter so rays through a vertex still hit one of its edges.
_EDGE_TOL = 1e-12


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

    dx, dy = np.cos(phi)[:, None], np.sin(phi)[:, None]  # [K 1] ray directions
    px, py = poly[:, 0], poly[:, 1]  # [n] edge starts
    edges = np.roll(poly, -1, axis=0) - poly
    ex, ey = edges[:, 0], edges[:, 1]  # [n] edge vectors
    # Solve t * d = p + s * e (Cramer's rule): t = (p x e) / (d x e), s = (p x d) / (d x e).
    den = dx * ey - dy * ex  # [K n]
    ok = den != 0.0
    safe = np.where(ok, den, 1.0)
    t = (px * ey - py * ex) / safe
    s = (px * dy - py * dx) / safe
    hit = ok & (s >= -_EDGE_TOL) & (s <= 1.0 + _EDGE_TOL) & (t > 0.0)
    true_ranges = np.min(np.where(hit, t, np.inf), axis=1)
    if not np.all(np.isfinite(true_ranges)):
        raise ValueError("polygon must enclose the origin: some rays do not hit it")

    ranges = np.maximum(true_ranges + range_noise, 0.0)
    return azimuths, ranges
