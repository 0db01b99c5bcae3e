"""Polyline-extraction metrics of dissertation section 10.5 (NumPy only).

- :func:`ray_rmse`: RMSE between the measured ray ranges and the ranges at which the rays
  would hit the extracted polylines.
- :func:`explained_fraction`: ``f``, the number of rays intersected by the polylines over
  the number of rays reflected in the scan.
- :func:`area_ratio`: ``a = (|GT u E| - |GT n E|) / |E|``, the area of the symmetric
  difference between the ground-truth polygon and the estimated polygon ``E`` (the
  estimated vertices ordered counter-clockwise around the sensor, :func:`star_polygon`)
  relative to the area of ``E``. Computed exactly in polar coordinates.
- :func:`polygon_area`: shoelace area.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "ray_rmse",
    "explained_fraction",
    "polygon_area",
    "star_polygon",
    "area_ratio",
]

_TWO_PI = 2.0 * np.pi
# Angular intervals narrower than this (rad) are dropped from the polar integration; their
# area is below radius^2 * 1e-13, far under float64 resolution of any realistic area.
_MIN_INTERVAL_RAD = 1e-13


def _bool_mask(mask: np.ndarray, name: str) -> np.ndarray:
    m = np.asarray(mask)
    if m.dtype != np.bool_:
        raise TypeError(f"{name} must be a boolean array, got dtype {m.dtype}")
    return m


def ray_rmse(ranges: np.ndarray, expected: np.ndarray, reflected: np.ndarray) -> float:
    """Root mean squared range error between a scan and the extracted polylines.

    The error of a ray is its measured range minus the range at which it would hit the
    polylines, measured along the ray axis. Only rays that were reflected in the scan *and*
    are intersected by the polylines (finite ``expected``) take part.

    Args:
        ranges: ``[K]`` measured ranges (m); finite wherever a ray qualifies.
        expected: ``[K]`` range (m) of each ray's intersection with the polylines;
            ``inf`` (or ``nan``) for rays that miss them.
        reflected: ``[K]`` bool, whether the ray was reflected (not a max-range reading).

    Returns:
        The RMSE in metres, or ``float('inf')`` if no ray is both reflected and intersected
        (the polylines explain nothing, so the error is unbounded); never ``nan``.

    Raises:
        TypeError: if ``reflected`` is not boolean.
        ValueError: if the shapes differ or a qualifying ray has a non-finite range.
    """
    r = np.asarray(ranges, dtype=float)
    e = np.asarray(expected, dtype=float)
    m = _bool_mask(reflected, "reflected")
    if not r.shape == e.shape == m.shape:
        raise ValueError(
            f"ranges, expected and reflected must have equal shapes, got "
            f"{r.shape}, {e.shape}, {m.shape}"
        )
    use = m & np.isfinite(e)
    if not np.any(use):
        return float("inf")
    if not np.all(np.isfinite(r[use])):
        raise ValueError("ranges must be finite for reflected, intersected rays")
    return float(np.sqrt(np.mean((r[use] - e[use]) ** 2)))


def explained_fraction(expected: np.ndarray, reflected: np.ndarray) -> float:
    """Fraction ``f`` of the scan explained by the polylines.

    ``f`` is the number of reflected rays that intersect the polylines (finite
    ``expected``) divided by the number of rays reflected in the measured scan, so
    ``0 <= f <= 1``. Section 10.5 words it as "rays hypothetically intersected by the
    polylines / rays actually reflected"; counting only reflected rays in the numerator is
    how the authors' published evaluation computes it (their IEF, whose lines bridge the
    no-return gaps, has f = 1, not more).

    Args:
        expected: ``[K]`` range (m) of each ray's intersection with the polylines;
            ``inf`` (or ``nan``) for rays that miss them.
        reflected: ``[K]`` bool, whether the ray was reflected.

    Returns:
        ``f`` (dimensionless, in ``[0, 1]``).

    Raises:
        TypeError: if ``reflected`` is not boolean.
        ValueError: if the shapes differ or no ray is reflected.
    """
    e = np.asarray(expected, dtype=float)
    m = _bool_mask(reflected, "reflected")
    if e.shape != m.shape:
        raise ValueError(f"expected and reflected must have equal shapes, got {e.shape}, {m.shape}")
    n_reflected = int(np.count_nonzero(m))
    if n_reflected == 0:
        raise ValueError("explained_fraction needs at least one reflected ray")
    return int(np.count_nonzero(np.isfinite(e) & m)) / n_reflected


def _as_vertices(vertices: np.ndarray, name: str) -> np.ndarray:
    v = np.asarray(vertices, dtype=float)
    if v.ndim != 2 or v.shape[1] != 2:
        raise ValueError(f"{name} must have shape [n 2], got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must have finite coordinates")
    return v


def _as_center(center: np.ndarray | tuple[float, float]) -> np.ndarray:
    c = np.asarray(center, dtype=float)
    if c.shape != (2,) or not np.all(np.isfinite(c)):
        raise ValueError(f"center must be a finite point of shape [2], got {center!r}")
    return c


def _signed_area(v: np.ndarray) -> float:
    x, y = v[:, 0], v[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def polygon_area(vertices: np.ndarray) -> float:
    """Area of a simple polygon (shoelace formula).

    Args:
        vertices: ``[n 2]`` vertices (m) in boundary order, either orientation; the closing
            edge is implied. Fewer than 3 vertices give 0.

    Returns:
        The absolute enclosed area (m^2).
    """
    v = _as_vertices(vertices, "vertices")
    if v.shape[0] < 3:
        return 0.0
    return abs(_signed_area(v))


def star_polygon(
    vertices: np.ndarray, center: np.ndarray | tuple[float, float] = (0.0, 0.0)
) -> np.ndarray:
    """Order points counter-clockwise by polar angle about a centre.

    This is the paper's construction of the estimated polygon: the estimated polyline
    vertices are converted to polar coordinates with respect to the sensor and joined in
    counter-clockwise order. The angle is ``atan2`` in ``(-pi, pi]``; points with equal
    angles are ordered by increasing distance from the centre.

    Args:
        vertices: ``[n 2]`` points (m).
        center: ``[2]`` centre (m), e.g. the sensor position.

    Returns:
        ``[n 2]`` the same points, reordered.
    """
    v = _as_vertices(vertices, "vertices")
    c = _as_center(center)
    rel = v - c
    angle = np.arctan2(rel[:, 1], rel[:, 0])
    dist = np.hypot(rel[:, 0], rel[:, 1])
    return v[np.lexsort((dist, angle))]


def _polar_polygon(rel: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Check a centred polygon is star-shaped around 0 with 0 strictly inside, orient it.

    Args:
        rel: ``[n 2]`` vertices relative to the centre, in boundary order.
        name: argument name for error messages.

    Returns:
        ``(vertices, alpha)``: ``[n 2]`` counter-clockwise vertices and ``[n+1]`` their
        unwrapped, non-decreasing polar angles (rad) with ``alpha[n] = alpha[0] + 2 pi``.
    """
    if rel.shape[0] < 3:
        raise ValueError(f"{name} must have at least 3 vertices, got {rel.shape[0]}")
    if _signed_area(rel) < 0.0:
        rel = rel[::-1]
    if np.any(np.hypot(rel[:, 0], rel[:, 1]) == 0.0):
        raise ValueError(f"center must lie strictly inside {name}, but it is a vertex")
    ang = np.arctan2(rel[:, 1], rel[:, 0])
    steps = np.mod(np.diff(ang, append=ang[0]), _TWO_PI)
    # A tie computed as a tiny negative step wraps to ~2 pi; it is really a zero step.
    steps = np.where(steps > _TWO_PI - 1e-12, 0.0, steps)
    if np.any(steps >= np.pi) or not np.isclose(np.sum(steps), _TWO_PI, rtol=0.0, atol=1e-9):
        raise ValueError(
            f"center must lie strictly inside {name} and {name} must be star-shaped with "
            f"respect to it (every vertex visible from the centre)"
        )
    alpha = np.mod(ang[0], _TWO_PI) + np.concatenate([[0.0], np.cumsum(steps)])
    alpha[-1] = alpha[0] + _TWO_PI
    return rel, alpha


def _edge_lines(
    rel: np.ndarray, alpha: np.ndarray, theta: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Start point and direction of the polygon edge seen at each angle.

    Args:
        rel: ``[n 2]`` counter-clockwise centred vertices.
        alpha: ``[n+1]`` their unwrapped angles from :func:`_polar_polygon`.
        theta: ``[m]`` query angles (rad) in ``[0, 2 pi)``, away from vertex angles.

    Returns:
        ``(p, e)``: ``[m 2]`` edge start points and ``[m 2]`` edge vectors.
    """
    n = rel.shape[0]
    shifted = alpha[0] + np.mod(theta - alpha[0], _TWO_PI)
    idx = np.clip(np.searchsorted(alpha, shifted, side="right") - 1, 0, n - 1)
    p = rel[idx]
    e = rel[(idx + 1) % n] - p
    return p, e


def _radius(p: np.ndarray, e: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Distance from the centre along direction ``theta`` to the line ``p + s e`` (m)."""
    ux, uy = np.cos(theta), np.sin(theta)
    return (p[:, 0] * e[:, 1] - p[:, 1] * e[:, 0]) / (ux * e[:, 1] - uy * e[:, 0])


def _triangle(r0: np.ndarray, r1: np.ndarray, dtheta: np.ndarray) -> np.ndarray:
    """Area of the triangle (centre, r0 at angle 0, r1 at angle dtheta) (m^2)."""
    return 0.5 * r0 * r1 * np.sin(dtheta)


def area_ratio(
    gt_polygon: np.ndarray,
    estimated_vertices: np.ndarray,
    center: np.ndarray | tuple[float, float] = (0.0, 0.0),
) -> float:
    """Relative area error ``a`` between a ground-truth and an estimated polygon.

    ``a = (|GT u E| - |GT n E|) / |E|`` with ``E = star_polygon(estimated_vertices, center)``.
    Both polygons are star-shaped with respect to ``center``, so with ``rho_P(theta)`` the
    boundary distance of polygon ``P`` in direction ``theta``,
    ``|GT n E| = 1/2 int min(rho_GT, rho_E)^2 dtheta`` and the union uses ``max``. The
    angle is split at all vertex angles of both polygons; inside each interval both
    boundaries are straight lines, which cross at most once, so splitting there as well
    leaves pieces on which one boundary is inside the other and whose areas are exact
    triangles.

    Args:
        gt_polygon: ``[n 2]`` ground-truth polygon vertices (m) in boundary order (either
            orientation); star-shaped with respect to ``center``.
        estimated_vertices: ``[m 2]`` estimated vertices (m), any order, ``m >= 3``.
        center: ``[2]`` sensor position (m).

    Returns:
        ``a`` (dimensionless, ``>= 0``; 0 iff the polygons coincide).

    Raises:
        ValueError: if ``estimated_vertices`` has fewer than 3 points, or ``center`` is not
            strictly inside either polygon, or ``gt_polygon`` is not star-shaped with
            respect to ``center``.
    """
    gt = _as_vertices(gt_polygon, "gt_polygon")
    est = _as_vertices(estimated_vertices, "estimated_vertices")
    c = _as_center(center)
    if est.shape[0] < 3:
        raise ValueError(f"estimated_vertices must have at least 3 points, got {est.shape[0]}")
    gt_rel, gt_alpha = _polar_polygon(gt - c, "gt_polygon")
    e_rel, e_alpha = _polar_polygon(star_polygon(est, c) - c, "the estimated polygon")

    cuts = np.concatenate(
        [[0.0, _TWO_PI], np.mod(gt_alpha[:-1], _TWO_PI), np.mod(e_alpha[:-1], _TWO_PI)]
    )
    cuts = np.unique(cuts)
    lo, hi = cuts[:-1], cuts[1:]
    keep = hi - lo > _MIN_INTERVAL_RAD
    lo, hi = lo[keep], hi[keep]
    mid = 0.5 * (lo + hi)

    p1, e1 = _edge_lines(gt_rel, gt_alpha, mid)
    p2, e2 = _edge_lines(e_rel, e_alpha, mid)
    r1_lo, r1_hi = _radius(p1, e1, lo), _radius(p1, e1, hi)
    r2_lo, r2_hi = _radius(p2, e2, lo), _radius(p2, e2, hi)
    d_lo, d_hi = r1_lo - r2_lo, r1_hi - r2_hi

    # Crossing of the two boundary lines where the radius difference changes sign.
    cross = d_lo * d_hi < 0.0
    den = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    safe = np.where(cross, den, 1.0)
    q = p2 - p1
    s = (q[:, 0] * e2[:, 1] - q[:, 1] * e2[:, 0]) / safe
    x = p1 + s[:, None] * e1
    theta_x = lo + np.mod(np.arctan2(x[:, 1], x[:, 0]) - lo, _TWO_PI)
    theta_c = np.where(cross, np.clip(theta_x, lo, hi), hi)
    r1_c, r2_c = _radius(p1, e1, theta_c), _radius(p2, e2, theta_c)

    # Piece [lo, theta_c]: the inner boundary is the one that is smaller at its interior.
    first_gt_inner = np.where(d_lo != 0.0, d_lo < 0.0, d_hi < 0.0)
    t1 = _triangle(r1_lo, r1_c, theta_c - lo)
    t2 = _triangle(r2_lo, r2_c, theta_c - lo)
    inter = np.where(first_gt_inner, t1, t2)
    union = np.where(first_gt_inner, t2, t1)
    # Piece [theta_c, hi] (empty unless the lines cross): the roles swap.
    t1 = _triangle(r1_c, r1_hi, hi - theta_c)
    t2 = _triangle(r2_c, r2_hi, hi - theta_c)
    inter = inter + np.where(first_gt_inner, t2, t1)
    union = union + np.where(first_gt_inner, t1, t2)

    inter_area = float(np.sum(inter))
    union_area = float(np.sum(union))
    est_area = polygon_area(e_rel)
    return max(union_area - inter_area, 0.0) / est_area
