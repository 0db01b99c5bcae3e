"""Sufficient statistics of PPE's clustering error (dissertation ch. 11).

PPE scores its actions with the ray-path error linearised in the plane's inverse-distance
parameters ``a = n / (n . x)`` (sensor at the origin): each ray contributes
``r_k² (a . p_k - 1)² = (r_k - r̂_k)² (r_k / r̂_k)²`` with the endpoint ``p_k``, i.e. the
ray-path error of Eq. (11.2) re-weighted by ``(r / r̂)² = 1 + O(noise / range)``. It is
quadratic in ``a``, so a ray set is summarised by its sufficient statistics
``(W, m [3], C [6])``: total weight ``W = Σ r²``, weighted endpoint mean ``m`` and the
weighted scatter ``C = Σ w (p - m)(p - m)^T`` stored as ``(c00, c01, c02, c11, c12, c22)``.
Two clusters merge in ``O(1)`` (:func:`_merge_py`), and the minimised error has the closed
form ``min_a Σ w (a . p - 1)² = 1 / (1 / W + m^T C^-1 m) = det C / (det C / W + m^T adj(C) m)``
(:func:`_stats_error`).

The same formulas run on NumPy or JAX arrays (``xp=``) and, for the greedy loop's hot path,
on tuples of Python floats (``*_py``). :func:`linearized_plane_error` is the independent
least-squares reference the tests compare them with.
"""

from __future__ import annotations

import numpy as np
from jaxtyping import ArrayLike, Float

__all__ = ["linearized_plane_error"]


def _outer6(d):
    d0, d1, d2 = d[..., 0], d[..., 1], d[..., 2]
    return (d0 * d0, d0 * d1, d0 * d2, d1 * d1, d1 * d2, d2 * d2)


def _adj6(c00, c01, c02, c11, c12, c22):
    """Adjugate of a symmetric 3 x 3 matrix, as its 6 unique entries (floats or arrays)."""
    return (
        c11 * c22 - c12 * c12,
        c02 * c12 - c01 * c22,
        c01 * c12 - c02 * c11,
        c00 * c22 - c02 * c02,
        c01 * c02 - c00 * c12,
        c00 * c11 - c01 * c01,
    )


def _det_q(m0, m1, m2, c00, c01, c02, c11, c12, c22):
    """``(det C, m^T adj(C) m)``, the two terms of the minimised error (floats or arrays)."""
    A00, A01, A02, A11, A12, A22 = _adj6(c00, c01, c02, c11, c12, c22)
    det = c00 * A00 + c01 * A01 + c02 * A02
    q = (
        A00 * m0 * m0
        + A11 * m1 * m1
        + A22 * m2 * m2
        + 2.0 * (A01 * m0 * m1 + A02 * m0 * m2 + A12 * m1 * m2)
    )
    return det, q


def _stats_error_cols(W, m0, m1, m2, c00, c01, c02, c11, c12, c22, xp=np):
    """``min_a Σ w (a . p - 1)² = det C / (det C / W + m^T adj(C) m)`` (0 if degenerate),
    on the statistics' columns (arrays)."""
    det, q = _det_q(m0, m1, m2, c00, c01, c02, c11, c12, c22)
    det = xp.maximum(det, 0.0)
    den = det / W + q
    ok = den > 0
    return xp.where(ok, det / xp.where(ok, den, 1.0), 0.0)


def _stats_error(W, m, C, xp=np):
    """:func:`_stats_error_cols` on ``(W [...], m [..., 3], C [..., 6])``."""
    return _stats_error_cols(
        W, *(m[..., i] for i in range(3)), *(C[..., i] for i in range(6)), xp=xp
    )


def _stats_plane(W, m, C):
    """Minimiser ``a ∝ adj(C) m`` -> (support, unit normal); NumPy arrays."""
    A00, A01, A02, A11, A12, A22 = _adj6(*(C[..., i] for i in range(6)))
    A = np.stack(
        [
            np.stack([A00, A01, A02], -1),
            np.stack([A01, A11, A12], -1),
            np.stack([A02, A12, A22], -1),
        ],
        -2,
    )
    Am = np.einsum("...ij,...j->...i", A, m)
    normal = Am / np.linalg.norm(Am, axis=-1, keepdims=True)  # direction of a (scale irrelevant)
    dist = np.einsum("...i,...i->...", normal, m)
    return normal * dist[..., None], normal


def _points_stats(points, xp=np):
    """Statistics of point sets ``[..., k, 3]`` computed from scratch (centred)."""
    w = xp.sum(points * points, axis=-1)
    W = xp.sum(w, axis=-1)
    m = xp.sum(points * w[..., None], axis=-2) / W[..., None]
    d = points - m[..., None, :]
    C = xp.stack([xp.sum(w * o, axis=-1) for o in _outer6(d)], axis=-1)
    return W, m, C


def _atom(w: float, p: list[float]) -> tuple:
    return (w, p[0], p[1], p[2], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def _merge_py(a: tuple, b: tuple) -> tuple:
    """Statistics of the union of two clusters (parallel-axis / Chan update), Python floats."""
    W1, x1, y1, z1, c00, c01, c02, c11, c12, c22 = a
    W2, x2, y2, z2, d00, d01, d02, d11, d12, d22 = b
    W = W1 + W2
    dx, dy, dz = x2 - x1, y2 - y1, z2 - z1
    f = W2 / W
    g = W1 * f
    return (
        W, x1 + dx * f, y1 + dy * f, z1 + dz * f,
        c00 + d00 + g * dx * dx, c01 + d01 + g * dx * dy, c02 + d02 + g * dx * dz,
        c11 + d11 + g * dy * dy, c12 + d12 + g * dy * dz, c22 + d22 + g * dz * dz,
    )  # fmt: skip


def _stats_error_py(s: tuple) -> float:
    """:func:`_stats_error` of one cluster in plain Python floats (the greedy hot path)."""
    det, q = _det_q(*s[1:])
    det = max(det, 0.0)
    den = det / s[0] + q
    return det / den if den > 0 else 0.0


def _merged_error_py(a: tuple, b: tuple) -> float:
    """The minimised error of the union of two clusters (Python floats)."""
    return _stats_error_py(_merge_py(a, b))


def linearized_plane_error(points: Float[ArrayLike, "k 3"]) -> float:
    """The PPE clustering error of one ray set, from scratch by least squares (m²).

    ``min_a Σ_k r_k² (a . p_k - 1)²`` for endpoints ``p_k`` seen from the origin, solved
    with ``numpy.linalg.lstsq``: an independent reference for the sufficient statistics
    the fast PPE keeps.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape [k, 3], got {p.shape}")
    r = np.linalg.norm(p, axis=1)
    a, *_ = np.linalg.lstsq(p * r[:, None], r, rcond=None)
    return float(np.sum((r * (p @ a - 1.0)) ** 2))
