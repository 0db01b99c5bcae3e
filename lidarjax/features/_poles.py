"""Pole extraction from registered 3-D lidar rays (dissertation ch. 6, section 12.4.1).

The pipeline, every step a batched JAX computation over the voxel grid:

1. **Full-posterior reflection map** ``p(mu_j | Z) = Beta(h_j + alpha, m_j + beta)`` from
   exact ray tracing (:func:`lidarjax.raytrace.accumulate`), with ``alpha, beta``
   moment-matched to the maximum-likelihood map (section 12.4.1, Luft et al.).
2. **Occupancy** ``o_j = int_{mu_o}^1 p(mu_j | Z) dmu_j``
   (:func:`lidarjax.maps.occupancy`).
3. **Pole score maps** ``Q_a`` for every pole width ``a`` (in cells,
   :func:`pole_score_maps`; the candidate widths are physical sizes, 1 cell up to
   :attr:`PoleConfig.max_width_m`, so they cover the same poles at every resolution)::

       q_{a,j} = max_{k in inside(j,a)} ( mean_{l in inside(k,a)} o_l
                                          - max_{l in outside(k,a,f)} o_l )

   ``inside(k, a)`` is the ``a x a`` square of a horizontal slice whose lower-left cell is
   ``k``; ``outside(k, a, f)`` the ring of thickness ``f`` around it. Box sums and box
   maxima are ``lax.reduce_window`` filters. Scores are reported on the ``[0, 1]`` scale
   ``(q + 1) / 2`` (as in the authors' implementation, on which ``q_min = 0.6`` is
   defined). Cells outside the grid count as occupied in the free hull and as empty inside
   the pole, so a pole must lie with its hull inside the local map.
4. ``Q = max_a Q_a``; for every column the longest contiguous vertical run of cells with
   ``Q >= q_min`` (:func:`pole_score_image`); runs shorter than ``h_min`` are dropped; the
   2-D score map ``S`` holds the mean ``Q`` of the run.
5. **Modes of S** by mean shift with a Gaussian kernel, seeded at the local maxima of
   ``S`` (:func:`mean_shift`); width = average of ``a`` weighted by the mean raw score
   ``max(q_a, 0)`` over the run of the mode's column (on the ``[0, 1]`` scale every width
   would weigh >= 0.5 and every estimate drift towards the middle width); score = the
   same weighted mean of the run means of ``Q_a``.
6. Near-duplicate modes (closer than the free-hull length plus their mean half width) keep
   the higher score.

Conventions: grids are :class:`~lidarjax.raytrace.GridSpec` with cubic voxels, z up;
positions are metres in the grid's (world) frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import betainc
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .. import _checks
from ..maps import BetaPosteriorMap, beta_posterior
from ..rays import RayBatch
from ..raytrace import GridSpec, GridStats, accumulate, check_backend

__all__ = [
    "PoleConfig",
    "Poles",
    "pole_score_maps",
    "pole_score_image",
    "mean_shift",
    "extract_poles",
    "extract_poles_from_occupancy",
    "local_map_spec",
    "fast_occupancy",
    "matched_beta_prior",
]


class _DerivedWidths(tuple):
    """Candidate widths (cells) that :class:`PoleConfig` derived from ``max_width_m``.

    A plain tuple to every reader; the type only tells ``PoleConfig.__post_init__`` to
    derive the widths again for the new resolution when a config is copied with
    ``dataclasses.replace``."""

    __slots__ = ()


@dataclass(frozen=True)
class PoleConfig:
    """Parameters of the pole extractor (defaults: the dissertation's NCLT settings).

    Attributes:
        resolution_m: voxel edge length (m); 0.2 in section 12.5.1, 0.1 for KITTI.
        extent_m: local-map size ``(x, y, z)`` (m); 30 x 30 x 5 in section 12.5.1.
        z_min_m: height of the local map's floor above the vehicle's ground point (m).
        mu_o: reflection-rate threshold of the occupancy integral.
        max_width_m: largest candidate pole edge length (m). The candidate widths are
            ``a = 1 .. round(max_width_m / resolution_m)`` cells (at least one), i.e. the
            same physical sizes at every resolution: 0.2-1.0 m in 5 widths at 0.2 m,
            0.1-1.0 m in 10 widths at 0.1 m (the authors' KITTI setting).
        widths: explicit pole edge lengths ``a`` in cells, used at every resolution
            instead of the widths derived from ``max_width_m``. Omitted (``None``), the
            field holds the derived widths after construction (:attr:`width_cells`), and
            they are derived again whenever the resolution changes (also through
            ``dataclasses.replace`` and when a grid's resolution overrides
            ``resolution_m``).
        free_m: thickness of the free hull around a pole (m); ``f`` = ``round(free_m /
            resolution_m)`` cells, at least 1.
        q_min: minimum score (``[0, 1]`` scale) of the cells of a pole's vertical run.
        h_min_m: minimum pole height (m).
        bandwidth_m: standard deviation of the mean-shift Gaussian kernel (m).
        max_poles: static number of mean-shift seeds (the highest local maxima of S).
        mean_shift_steps: maximum mean-shift iterations.
        mean_shift_tol_m: mean shift stops when no mode moves farther (m).
        chunk_size: rays traced together (static; JAX walk only).
        backend: ray-tracing backend of :func:`lidarjax.raytrace.accumulate`
            (``"auto"``, ``"native"`` or ``"jax"``).
        threads: native tracing threads (None: all cores).
    """

    resolution_m: float = 0.2
    extent_m: tuple[float, float, float] = (30.0, 30.0, 5.0)
    z_min_m: float = 0.1
    mu_o: float = 0.2
    max_width_m: float = 1.0
    widths: tuple[int, ...] | None = None
    free_m: float = 0.5
    q_min: float = 0.6
    h_min_m: float = 1.0
    bandwidth_m: float = 0.2
    max_poles: int = 64
    mean_shift_steps: int = 50
    mean_shift_tol_m: float = 1e-3
    chunk_size: int = 8192
    backend: str = "auto"
    threads: int | None = None

    def __post_init__(self):
        check_backend(self.backend)
        if not (self.resolution_m > 0 and math.isfinite(self.resolution_m)):
            raise ValueError(f"resolution_m must be > 0, got {self.resolution_m!r}")
        if len(self.extent_m) != 3 or not all(e > 0 for e in self.extent_m):
            raise ValueError(f"extent_m must be three positive lengths, got {self.extent_m!r}")
        if not (0.0 <= self.mu_o <= 1.0):
            raise ValueError(f"mu_o must lie in [0, 1], got {self.mu_o!r}")
        mw = self.max_width_m
        if (
            isinstance(mw, bool)
            or not isinstance(mw, (int, float))
            or not (math.isfinite(mw) and mw > 0)
        ):
            raise ValueError(f"max_width_m must be finite and > 0, got {self.max_width_m!r}")
        if self.widths is None or isinstance(self.widths, _DerivedWidths):
            # derived from the physical size (again, after a change of resolution)
            n = max(1, int(round(self.max_width_m / self.resolution_m)))
            object.__setattr__(self, "widths", _DerivedWidths(range(1, n + 1)))
        else:
            w = self.widths
            if (
                isinstance(w, (str, bytes))
                or not hasattr(w, "__len__")
                or not w
                or any(
                    isinstance(a, bool)
                    or not isinstance(a, (int, float, np.integer, np.floating))
                    or not math.isfinite(a)
                    or int(a) != a
                    or a < 1
                    for a in w
                )
            ):
                raise ValueError(f"widths must be positive ints (cells) or None, got {w!r}")
            if len(set(w)) != len(w):
                raise ValueError(f"widths must be distinct, got {w!r}")
            object.__setattr__(self, "widths", tuple(int(a) for a in w))
        if not (self.free_m > 0):
            raise ValueError(f"free_m must be > 0, got {self.free_m!r}")
        if not (0.0 <= self.q_min <= 1.0):
            raise ValueError(f"q_min must lie in [0, 1], got {self.q_min!r}")
        if not (self.h_min_m > 0):
            raise ValueError(f"h_min_m must be > 0, got {self.h_min_m!r}")
        if not (self.bandwidth_m > 0):
            raise ValueError(f"bandwidth_m must be > 0, got {self.bandwidth_m!r}")
        for name in ("max_poles", "mean_shift_steps", "chunk_size"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be a positive int, got {v!r}")

    @property
    def width_cells(self) -> tuple[int, ...]:
        """Candidate pole edge lengths ``a`` in cells (``widths``, explicit or derived)."""
        return tuple(self.widths)

    @property
    def free_cells(self) -> int:
        """Hull thickness ``f`` in cells."""
        return max(1, int(round(self.free_m / self.resolution_m)))

    @property
    def min_cells(self) -> int:
        """Minimum run length in cells for ``h_min_m``."""
        return max(1, int(math.ceil(self.h_min_m / self.resolution_m - 1e-9)))

    @property
    def shape(self) -> tuple[int, int, int]:
        """Voxel counts of the local map."""
        return tuple(max(1, int(round(e / self.resolution_m))) for e in self.extent_m)


@dataclass(frozen=True)
class Poles:
    """Extracted poles (NumPy arrays, ``K`` poles).

    Attributes:
        xy: ``[K 2]`` pole centres in the grid's frame (m).
        width_m: ``[K]`` estimated edge lengths of the square footprints (m).
        score: ``[K]`` mean pole scores in ``[0, 1]``.
        z_range_m: ``[K 2]`` bottom and top of the pole's voxel run (m).
    """

    xy: np.ndarray
    width_m: np.ndarray
    score: np.ndarray
    z_range_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    def __post_init__(self):
        k = np.shape(self.xy)[0] if np.ndim(self.xy) == 2 else -1
        if np.shape(self.xy) != (k, 2) or k < 0:
            raise ValueError(f"xy must have shape [K, 2], got {np.shape(self.xy)}")
        for name in ("width_m", "score"):
            if np.shape(getattr(self, name)) != (k,):
                raise ValueError(
                    f"{name} must have shape [{k}], got {np.shape(getattr(self, name))}"
                )
        if np.shape(self.z_range_m) != (k, 2):
            object.__setattr__(self, "z_range_m", np.full((k, 2), np.nan))

    def __len__(self) -> int:
        return int(np.shape(self.xy)[0])

    @staticmethod
    def empty() -> Poles:
        return Poles(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros((0, 2)))

    def take(self, index) -> Poles:
        """The poles at ``index`` (ints or bool mask)."""
        return Poles(self.xy[index], self.width_m[index], self.score[index], self.z_range_m[index])

    def transform(self, T_xy_yaw: ArrayLike) -> Poles:
        """Poles mapped by the 2-D rigid transform ``(x, y, yaw)`` (target <- source)."""
        x, y, yaw = (float(v) for v in np.asarray(T_xy_yaw, float).reshape(3))
        c, s = math.cos(yaw), math.sin(yaw)
        xy = self.xy @ np.array([[c, s], [-s, c]]) + np.array([x, y])
        return Poles(xy, self.width_m.copy(), self.score.copy(), self.z_range_m.copy())


# --------------------------------------------------------------------------------------
# Score maps (Q_a), the score image S and mean shift
# --------------------------------------------------------------------------------------


def _box(x: Array, window: tuple[int, int], op: str) -> Array:
    """2-D box filter over the first two axes (VALID): out[i, j] = op(x[i:i+wx, j:j+wy]).

    Separable: a 1-D window along axis 0, then along axis 1 (``wx + wy`` operations per
    output instead of ``wx * wy``; the max is identical, the sum equal to round-off)."""
    if op == "sum":
        init, fn = jnp.zeros((), x.dtype), jax.lax.add
    else:
        init, fn = jnp.array(-jnp.inf, x.dtype), jax.lax.max
    ones = (1,) * (x.ndim - 2)
    for axis, size in enumerate(window):
        if size > 1:
            w = (size, 1) + ones if axis == 0 else (1, size) + ones
            x = jax.lax.reduce_window(x, init, fn, w, (1,) * x.ndim, "VALID")
    return x


def _score_map_one(occ: Array, a: int, f: int) -> Array:
    nx, ny = occ.shape[:2]
    p = a + f
    widths = [(p, p), (p, p)] + [(0, 0)] * (occ.ndim - 2)
    inside = jnp.pad(occ, widths, constant_values=0.0)
    hull = jnp.pad(occ, widths, constant_values=1.0)
    # Lower-left corners k = -(a-1) .. n-1 on each axis: padded start index k + p.
    m = (nx + a - 1, ny + a - 1)

    def crop(arr, x0, y0):
        return arr[x0 : x0 + m[0], y0 : y0 + m[1]]

    mean = crop(_box(inside, (a, a), "sum"), f + 1, f + 1) / (a * a)
    strip_x = _box(hull, (f, a + 2 * f), "max")  # left/right strips
    strip_y = _box(hull, (a, f), "max")  # bottom/top strips
    ring = jnp.maximum(
        jnp.maximum(crop(strip_x, 1, 1), crop(strip_x, a + f + 1, 1)),
        jnp.maximum(crop(strip_y, f + 1, 1), crop(strip_y, f + 1, a + f + 1)),
    )
    s = mean - ring
    return _box(s, (a, a), "max")  # max over the corners whose square contains j


def pole_score_maps(
    occ: Float[ArrayLike, "nx ny nz"], widths: tuple[int, ...], free_cells: int
) -> Float[Array, "A nx ny nz"]:
    """Pole score maps ``Q_a`` of section 12.4.1 on the ``[0, 1]`` scale ``(q + 1) / 2``.

    Args:
        occ: ``[nx ny nz]`` occupancy probabilities (any number of trailing axes).
        widths: pole edge lengths ``a`` in cells (static).
        free_cells: hull thickness ``f`` in cells (static, >= 1).

    Returns:
        ``[len(widths) nx ny nz]`` scores in ``[0, 1]``.
    """
    occ = jnp.asarray(occ)
    if occ.ndim < 2:
        raise ValueError(f"occ must have at least 2 axes, got shape {occ.shape}")
    if not isinstance(free_cells, int) or free_cells < 1:
        raise ValueError(f"free_cells must be an int >= 1, got {free_cells!r}")
    if not widths or any(not isinstance(a, int) or a < 1 for a in widths):
        raise ValueError(f"widths must be positive ints, got {widths!r}")
    occ = occ.astype(jnp.result_type(float))
    return jnp.stack([(_score_map_one(occ, a, free_cells) + 1.0) / 2.0 for a in widths])


def pole_score_image(
    q: Float[ArrayLike, "nx ny nz"], q_min: float, min_cells: int
) -> tuple[Float[Array, "nx ny"], Int[Array, "nx ny"], Int[Array, "nx ny"]]:
    """2-D score map ``S`` from the merged score map ``Q`` (section 12.4.1).

    For every column, the longest contiguous run of cells with ``Q >= q_min`` (the lowest
    one on ties); runs shorter than ``min_cells`` give ``S = 0``, others the mean ``Q`` of
    the run.

    Returns:
        ``(S [nx ny], z0 [nx ny], height [nx ny])``: score, first cell and length (cells)
        of the run (``height = 0`` where no run qualifies).
    """
    q = jnp.asarray(q)
    if q.ndim != 3:
        raise ValueError(f"q must have shape [nx, ny, nz], got {q.shape}")
    shape2 = q.shape[:2]
    zeros_i = jnp.zeros(shape2, jnp.int32)
    zeros_f = jnp.zeros(shape2, q.dtype)

    def body(carry, xs):
        cur_len, cur_start, cur_sum, best_len, best_start, best_sum = carry
        z, qz = xs
        on = qz >= q_min
        cur_start = jnp.where(on & (cur_len == 0), z, cur_start)
        cur_len = jnp.where(on, cur_len + 1, 0)
        cur_sum = jnp.where(on, cur_sum + qz, 0.0)
        better = cur_len > best_len
        best_len = jnp.where(better, cur_len, best_len)
        best_start = jnp.where(better, cur_start, best_start)
        best_sum = jnp.where(better, cur_sum, best_sum)
        return (cur_len, cur_start, cur_sum, best_len, best_start, best_sum), None

    init = (zeros_i, zeros_i, zeros_f, zeros_i, zeros_i, zeros_f)
    zs = jnp.arange(q.shape[2], dtype=jnp.int32)
    (_, _, _, h, z0, total), _ = jax.lax.scan(body, init, (zs, jnp.moveaxis(q, 2, 0)))
    ok = h >= min_cells
    s = jnp.where(ok, total / jnp.maximum(h, 1), 0.0)
    return s, jnp.where(ok, z0, 0), jnp.where(ok, h, 0)


def _local_maxima(s: Array, radius: int) -> Bool[Array, "nx ny"]:
    """Mean-shift seeds: cells with ``S > 0`` and no higher cell within ``radius`` (a
    ``(2 radius + 1)^2`` window), one per plateau: of equal maxima within a window only the
    first (lowest flat index) is kept, so a flat top of ``S`` (``Q_a`` is a box maximum,
    so every pole has one, of about ``a x a`` cells) takes one of the ``max_poles`` seeds
    instead of all of them (the authors' code seeds at the centroid of each plateau)."""
    w = (2 * radius + 1, 2 * radius + 1)
    m = _box(jnp.pad(s, radius, constant_values=-jnp.inf), w, "max")
    peak = (s > 0) & (s >= m)
    n = s.size  # flat indices are exact in float32 up to 2^24 cells
    idx = jnp.where(peak, jnp.arange(n, dtype=s.dtype).reshape(s.shape), float(n))
    first = -_box(jnp.pad(-idx, radius, constant_values=-float(n)), w, "max")
    return peak & (idx == first)


def mean_shift(
    s: Float[ArrayLike, "nx ny"],
    seeds: Float[ArrayLike, "k 2"],
    bandwidth_cells: float,
    *,
    max_steps: int = 50,
    tol_cells: float = 1e-3,
) -> Float[Array, "k 2"]:
    """Mean shift on the weighted cell centres of a 2-D score map (Gaussian kernel).

    Cell ``(i, j)`` sits at ``(i + 0.5, j + 0.5)`` with weight ``S_ij``; every seed moves
    to ``sum_c S_c K(c - x) c / sum_c S_c K(c - x)`` until no seed moves more than
    ``tol_cells`` or ``max_steps`` is reached. The kernel is truncated at 5 standard
    deviations (a relative weight of ``4e-6``). A seed with no weight in its window stays.

    Args:
        s: ``[nx ny]`` non-negative weights.
        seeds: ``[k 2]`` start points in cell units.
        bandwidth_cells: kernel standard deviation in cells.

    Returns:
        ``[k 2]`` modes in cell units.
    """
    s = jnp.asarray(s)
    seeds = jnp.asarray(seeds, s.dtype)
    if s.ndim != 2 or seeds.ndim != 2 or seeds.shape[1] != 2:
        raise ValueError(f"s must be [nx, ny] and seeds [k, 2], got {s.shape}, {seeds.shape}")
    r = max(1, int(math.ceil(5.0 * bandwidth_cells)))
    w = 2 * r + 1
    padded = jnp.pad(s, r)
    offs = jnp.arange(-r, r + 1, dtype=s.dtype)

    def shift_one(x):
        c = jnp.floor(x).astype(jnp.int32)
        win = jax.lax.dynamic_slice(padded, (c[0], c[1]), (w, w))  # cells c - r .. c + r
        cx = c[0].astype(s.dtype) + offs + 0.5
        cy = c[1].astype(s.dtype) + offs + 0.5
        kx = jnp.exp(-0.5 * ((cx - x[0]) / bandwidth_cells) ** 2)
        ky = jnp.exp(-0.5 * ((cy - x[1]) / bandwidth_cells) ** 2)
        wgt = win * kx[:, None] * ky[None, :]
        tot = jnp.sum(wgt)
        safe = jnp.where(tot > 0, tot, 1.0)
        new = jnp.stack([jnp.sum(wgt * cx[:, None]), jnp.sum(wgt * cy[None, :])]) / safe
        return jnp.where(tot > 0, new, x)

    step = jax.vmap(shift_one)
    hi = jnp.asarray(s.shape, s.dtype) - 1e-6

    def cond(carry):
        i, _, moved = carry
        return (i < max_steps) & (moved > tol_cells)

    def body(carry):
        i, x, _ = carry
        new = jnp.clip(step(x), 0.0, hi)
        return i + 1, new, jnp.max(jnp.linalg.norm(new - x, axis=-1))

    _, x, _ = jax.lax.while_loop(cond, body, (0, jnp.clip(seeds, 0.0, hi), jnp.inf))
    return x


class _RawPoles(eqx.Module):
    xy_cells: Float[Array, "k 2"]
    width_cells: Float[Array, " k"]
    score: Float[Array, " k"]
    z0: Int[Array, " k"]
    height: Int[Array, " k"]
    valid: Bool[Array, " k"]


def _poles_from_scores(q_all: Array, cfg: PoleConfig) -> _RawPoles:
    q = jnp.max(q_all, axis=0)
    s, z0, h = pole_score_image(q, cfg.q_min, cfg.min_cells)
    nx, ny = s.shape
    peaks = _local_maxima(s, cfg.free_cells)
    k = min(cfg.max_poles, nx * ny)
    vals, flat = jax.lax.top_k(jnp.where(peaks, s, -1.0).ravel(), k)
    valid = vals > 0
    seeds = jnp.stack([flat // ny, flat % ny], axis=-1).astype(s.dtype) + 0.5
    modes = mean_shift(
        s,
        seeds,
        cfg.bandwidth_m / cfg.resolution_m,
        max_steps=cfg.mean_shift_steps,
        tol_cells=cfg.mean_shift_tol_m / cfg.resolution_m,
    )
    modes = jnp.where(valid[:, None], modes, seeds)
    cell = jnp.floor(modes).astype(jnp.int32)
    # a mode whose column holds no pole run falls back to its seed
    off = h[cell[:, 0], cell[:, 1]] == 0
    modes = jnp.where(off[:, None], seeds, modes)
    cell = jnp.floor(modes).astype(jnp.int32)
    col_z0 = z0[cell[:, 0], cell[:, 1]]
    col_h = h[cell[:, 0], cell[:, 1]]
    zs = jnp.arange(q.shape[2])
    in_run = (zs[None, :] >= col_z0[:, None]) & (zs[None, :] < (col_z0 + col_h)[:, None])
    cols = q_all[:, cell[:, 0], cell[:, 1], :]  # [A k nz]
    n_run = jnp.maximum(jnp.sum(in_run, -1), 1)
    # weight of width a: run mean of the raw score q = 2 Q - 1, clipped at 0 (on the [0, 1]
    # scale every width would weigh at least ~0.5 and all widths drift to the middle)
    raw = jnp.maximum(2.0 * cols - 1.0, 0.0)
    w_a = jnp.sum(jnp.where(in_run[None], raw, 0.0), -1) / n_run  # [A k]
    mean_a = jnp.sum(jnp.where(in_run[None], cols, 0.0), -1) / n_run  # [A k]
    w_sum = jnp.maximum(jnp.sum(w_a, 0), 1e-12)
    widths = jnp.asarray(cfg.width_cells, q.dtype)
    width = jnp.sum(w_a * widths[:, None], 0) / w_sum
    score = jnp.sum(w_a * mean_a, 0) / w_sum  # run mean of the w_a-weighted score maps
    valid = valid & (col_h > 0)
    return _RawPoles(modes, width, score, col_z0, col_h, valid)


@eqx.filter_jit
def _extract_occ(occ: Array, cfg: PoleConfig) -> _RawPoles:
    q_all = pole_score_maps(occ, cfg.width_cells, cfg.free_cells)
    return _poles_from_scores(q_all, cfg)


_TABLE_H, _TABLE_M, _OUTLIER_CAP = 32, 256, 16384


def fast_occupancy(beta_map: BetaPosteriorMap, mu_o: float) -> Float[Array, "*shape"]:
    """:func:`lidarjax.maps.occupancy` for integer counts, evaluated once per distinct count.

    The regularised incomplete beta function dominates the extractor's cost when evaluated
    per voxel, but a local map has only ~10^3 distinct ``(H, M)`` pairs. This evaluates it
    on a table of ``H < 32, M < 256`` and directly on at most ``max(16 384, n / 16)``
    voxels outside the table (falling back to every voxel if there are more); results equal
    :func:`~lidarjax.maps.occupancy` exactly (same function, same arguments).
    """
    h, m = beta_map.hits, beta_map.misses
    a0, b0 = beta_map.alpha, beta_map.beta
    dtype = h.dtype
    x = jnp.asarray(1.0 - jnp.asarray(mu_o, dtype), dtype)

    def occ(hh, mm):  # same expression as lidarjax.maps.occupancy
        return jnp.clip(betainc(mm + b0, hh + a0, jnp.broadcast_to(x, hh.shape)), 0.0, 1.0)

    th = jnp.arange(_TABLE_H, dtype=dtype)[:, None]
    tm = jnp.arange(_TABLE_M, dtype=dtype)[None, :]
    table = occ(
        jnp.broadcast_to(th, (_TABLE_H, _TABLE_M)), jnp.broadcast_to(tm, (_TABLE_H, _TABLE_M))
    )
    hi = h.astype(jnp.int32)
    mi = m.astype(jnp.int32)
    in_table = (hi < _TABLE_H) & (mi < _TABLE_M)
    out = table[jnp.minimum(hi, _TABLE_H - 1), jnp.minimum(mi, _TABLE_M - 1)]
    flat_out, flat_in = out.ravel(), in_table.ravel()
    n_out = jnp.sum(~flat_in)
    cap = min(max(_OUTLIER_CAP, flat_out.shape[0] // 16), flat_out.shape[0])

    def sparse():
        (idx,) = jnp.nonzero(~flat_in, size=cap, fill_value=0)
        vals = occ(h.ravel()[idx], m.ravel()[idx])
        valid = jnp.arange(cap) < n_out
        return flat_out.at[jnp.where(valid, idx, flat_out.shape[0])].set(vals, mode="drop")

    def dense():
        return jnp.where(flat_in, flat_out, occ(h.ravel(), m.ravel()))

    return jax.lax.cond(n_out <= cap, sparse, dense).reshape(h.shape)


def matched_beta_prior(stats: GridStats) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Moment-matched Beta prior of section 12.4.1, safe for sparse local maps.

    Same formulas as :func:`lidarjax.maps.beta_moment_prior` (mean ``E`` and variance
    ``V`` of the ML reflection map over observed voxels), but where no Beta distribution has
    these moments - ``V >= E (1 - E)``, which happens when almost every voxel was seen
    once, so its ML value is 0 or 1 - ``V`` is clamped to ``0.99 E (1 - E)`` (a prior of
    total weight ``alpha + beta = 1/99``, i.e. nearly flat), and ``E`` to ``[1e-6, 1 - 1e-6]``.
    Never raises, so a local map with few rays still yields an occupancy grid.
    """
    h = stats.hits.astype(jnp.result_type(float))
    n = h + stats.misses
    obs = n > 0
    cnt = jnp.maximum(jnp.sum(obs), 1)
    mu = jnp.where(obs, h / jnp.where(obs, n, 1.0), 0.0)
    e = jnp.clip(jnp.sum(mu) / cnt, 1e-6, 1.0 - 1e-6)
    v = jnp.sum(jnp.where(obs, (mu - e) ** 2, 0.0)) / cnt
    bound = e * (1.0 - e)
    v = jnp.clip(v, 1e-12 * bound, 0.99 * bound)
    k = bound / v - 1.0
    return e * k, (1.0 - e) * k


@_checks.checked_jit
def _extract_rays(rays: RayBatch, spec: GridSpec, cfg: PoleConfig) -> tuple[_RawPoles, Array]:
    stats = accumulate(
        spec, rays, chunk_size=cfg.chunk_size, backend=cfg.backend, threads=cfg.threads
    )
    alpha, beta = matched_beta_prior(stats)
    occ = fast_occupancy(beta_posterior(stats, alpha=alpha, beta=beta), cfg.mu_o)
    q_all = pole_score_maps(occ, cfg.width_cells, cfg.free_cells)
    return _poles_from_scores(q_all, cfg), occ


def _finish(raw: _RawPoles, spec: GridSpec, cfg: PoleConfig) -> Poles:
    raw = jax.device_get(raw)
    origin = np.asarray(spec.origin, float)
    res = float(spec.resolution)
    idx = np.flatnonzero(np.asarray(raw.valid))
    xy = origin[:2] + np.asarray(raw.xy_cells, float)[idx] * res
    width = np.asarray(raw.width_cells, float)[idx] * res
    score = np.asarray(raw.score, float)[idx]
    z0 = np.asarray(raw.z0)[idx]
    zr = origin[2] + np.stack([z0, z0 + np.asarray(raw.height)[idx]], -1) * res
    order = np.argsort(-score, kind="stable")
    keep: list[int] = []
    for i in order:  # at most max_poles candidates
        if all(
            np.hypot(*(xy[i] - xy[j])) - 0.5 * (width[i] + width[j]) >= cfg.free_m for j in keep
        ):
            keep.append(int(i))
    keep_a = np.asarray(keep, int)
    return Poles(xy[keep_a], width[keep_a], score[keep_a], zr[keep_a].reshape(-1, 2))


def _check_cfg(config) -> PoleConfig:
    if config is None:
        return PoleConfig()
    if not isinstance(config, PoleConfig):
        raise ValueError(f"config must be a PoleConfig, got {type(config).__name__}")
    return config


def extract_poles_from_occupancy(
    occ: Float[ArrayLike, "nx ny nz"], spec: GridSpec, config: PoleConfig | None = None
) -> Poles:
    """Poles from a 3-D occupancy grid (steps 3-6 of the module docstring).

    Args:
        occ: ``[nx ny nz]`` occupancy probabilities in ``[0, 1]`` on ``spec``.
        spec: the 3-D grid (cubic voxels, z up).
        config: extractor parameters (``config.resolution_m`` is ignored in favour of
            ``spec.resolution``).

    Returns:
        :class:`Poles` in ``spec``'s frame, sorted by decreasing score.
    """
    cfg = _check_cfg(config)
    if not isinstance(spec, GridSpec) or spec.dim != 3:
        raise ValueError("spec must be a 3-D GridSpec")
    occ = jnp.asarray(occ, jnp.result_type(float))
    if occ.shape != spec.shape:
        raise ValueError(f"occ must have the grid's shape {spec.shape}, got {occ.shape}")
    if not bool(jnp.all((occ >= 0) & (occ <= 1))):
        raise ValueError("occ must lie in [0, 1] (NaN not allowed)")
    cfg = _with_resolution(cfg, float(spec.resolution))
    return _finish(_extract_occ(occ, cfg), spec, cfg)


def _with_resolution(cfg: PoleConfig, res: float) -> PoleConfig:
    if abs(cfg.resolution_m - res) <= 1e-9 * res:
        return cfg
    from dataclasses import replace

    return replace(cfg, resolution_m=res)


def extract_poles(
    rays: RayBatch,
    spec: GridSpec,
    config: PoleConfig | None = None,
    *,
    return_occupancy: bool = False,
) -> Poles | tuple[Poles, Array]:
    """Pole extraction of section 12.4.1 from registered 3-D rays.

    Traces every ray through ``spec`` (hits and misses per voxel), builds the
    full-posterior reflection map with moment-matched Beta prior, converts it to occupancy
    with ``config.mu_o`` and runs :func:`extract_poles_from_occupancy`'s steps. Compiles
    once per (ray count, grid shape, config).

    Args:
        rays: 3-D :class:`~lidarjax.rays.RayBatch` in the grid's frame (HIT and SUP rays
            are used, SUB rays ignored).
        spec: 3-D grid, e.g. :func:`local_map_spec`.
        config: extractor parameters.
        return_occupancy: also return the ``[nx ny nz]`` occupancy grid.

    Returns:
        :class:`Poles` (and the occupancy grid).
    """
    cfg = _check_cfg(config)
    if not isinstance(rays, RayBatch) or rays.dim != 3:
        raise ValueError("rays must be a 3-D RayBatch")
    if not isinstance(spec, GridSpec) or spec.dim != 3:
        raise ValueError("spec must be a 3-D GridSpec")
    if rays.n == 0:
        raise ValueError("rays is empty")
    cfg = _with_resolution(cfg, float(spec.resolution))
    raw, occ = _extract_rays(rays, spec, cfg)
    poles = _finish(raw, spec, cfg)
    return (poles, occ) if return_occupancy else poles


def local_map_spec(
    center_xy: ArrayLike, config: PoleConfig | None = None, *, ground_z_m: float = 0.0
) -> GridSpec:
    """Local-map grid of ``config.extent_m`` around ``center_xy``, axis-aligned with the
    world and snapped to multiples of the resolution (so all local maps share one raster,
    section 12.4.2). The floor is ``z_min_m`` above ``ground_z_m``.

    Args:
        center_xy: ``[2]`` centre in the world frame (m).
        config: extractor parameters.
        ground_z_m: ground height (m).
    """
    cfg = _check_cfg(config)
    c = np.asarray(center_xy, float)
    if c.shape != (2,) or not np.all(np.isfinite(c)):
        raise ValueError(f"center_xy must be 2 finite numbers, got {center_xy!r}")
    res = cfg.resolution_m
    nx, ny, nz = cfg.shape
    lo = np.floor((c - 0.5 * np.array([nx, ny]) * res) / res + 0.5) * res
    origin = np.array([lo[0], lo[1], ground_z_m + cfg.z_min_m])
    return GridSpec(jnp.asarray(origin, jnp.result_type(float)), res, (nx, ny, nz))
