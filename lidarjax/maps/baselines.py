"""Continuous occupancy-map baselines for the DCT-map comparison (dissertation Sec. 9.5.2).

Two classical continuous occupancy maps, fitted with scikit-learn on the host (NumPy):

- :class:`GPOccupancyMap` (:func:`fit_gpom`): Gaussian-process occupancy map in the style of
  O'Callaghan & Ramos (2012): GP regression on targets ``+1`` (occupied) / ``-1`` (free) with
  a Matern kernel, squashed to probabilities with the probit link
  ``p = Phi(mu / sqrt(1 + sigma^2))``.
- :class:`HilbertMap` (:func:`fit_hilbert`): Hilbert map (Ramos & Ott 2015): logistic
  regression on Nystroem features of an RBF kernel.

Both are trained on labelled points sampled from lidar rays by
:func:`occupancy_training_points` and have a parameter budget (GP: the number of training
points kept, Hilbert: the number of Nystroem components), so they can be compared with DCT
maps of the same number of coefficients. As in Sec. 9.5.2, their continuous occupancy fields
are rasterised (:func:`rasterize`, 0.05 m cells by default) and used as the per-cell
reflection probabilities of a :class:`~lidarjax.maps.ReflectionMap`
(:func:`occupancy_reflection_map`), whose ray likelihoods are those of
:func:`lidarjax.sensor_models.reflection_log_likelihood` (occupancy cumulated along the ray).
"""

from __future__ import annotations

import numbers
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from scipy.special import ndtr
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import Matern
from sklearn.kernel_approximation import Nystroem
from sklearn.linear_model import LogisticRegression

from ..rays import HIT, SUP, RayBatch
from ..raytrace import GridSpec, ray_box
from ._grid import ReflectionMap

__all__ = [
    "GPOccupancyMap",
    "HilbertMap",
    "fit_gpom",
    "fit_hilbert",
    "occupancy_reflection_map",
    "occupancy_training_points",
    "rasterize",
]

HIT_MARGIN_M: float = 0.1
"""Free-space samples of a HIT ray stop this far (m) before its end point."""
PROB_CLIP: float = 1e-6
"""Occupancy probabilities are clipped to ``[PROB_CLIP, 1 - PROB_CLIP]``."""
_CHUNK_ELEMENTS = 4_000_000  # bound on (query points x parameters) per prediction chunk
_RASTER_CHUNK = 65_536  # cell centres per occupancy call in :func:`rasterize`


# --------------------------------------------------------------------------------------
# input checks


def _check_seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise ValueError(f"seed must be a non-negative int, got {seed!r}")
    return int(seed)


def _check_positive(value, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a real number, got {value!r}")
    v = float(value)
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be finite and > 0, got {v}")
    return v


def _check_box(lower, upper) -> tuple[np.ndarray, np.ndarray]:
    lo = np.asarray(lower, dtype=np.float64)
    hi = np.asarray(upper, dtype=np.float64)
    if lo.shape != (2,):
        raise ValueError(f"lower must have shape (2,), got {lo.shape}")
    if hi.shape != (2,):
        raise ValueError(f"upper must have shape (2,), got {hi.shape}")
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError(f"lower and upper must be finite, got {lo}, {hi}")
    if np.any(hi <= lo):
        raise ValueError(f"lower {lo} must be < upper {hi} on every axis")
    return lo, hi


def _check_points(points, name: str = "points") -> np.ndarray:
    p = np.asarray(points)
    if p.size and not np.issubdtype(p.dtype, np.number):
        raise ValueError(f"{name} must be numeric, got dtype {p.dtype}")
    p = p.astype(np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"{name} must have shape [n, 2], got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name} must be finite ({int((~np.isfinite(p)).sum())} bad values)")
    return p


def _check_training(points, labels, budget) -> tuple[np.ndarray, np.ndarray, int]:
    p = _check_points(points)
    if p.shape[0] == 0:
        raise ValueError("points must contain at least one point")
    lab = np.asarray(labels)
    if lab.shape != (p.shape[0],):
        raise ValueError(f"labels must have shape ({p.shape[0]},) to match points, got {lab.shape}")
    if not (np.issubdtype(lab.dtype, np.number) or lab.dtype == np.bool_):
        raise ValueError(f"labels must be numeric, got dtype {lab.dtype}")
    if not np.all((lab == 0) | (lab == 1)):
        bad = np.unique(lab[(lab != 0) & (lab != 1)])
        raise ValueError(f"labels must be 0 (free) or 1 (occupied), found {bad[:5]}")
    if isinstance(budget, bool) or not isinstance(budget, numbers.Integral) or budget < 1:
        raise ValueError(f"budget must be an int >= 1, got {budget!r}")
    return p, lab.astype(np.int64), int(budget)


def _chunks(m: int, n_params: int):
    size = max(256, _CHUNK_ELEMENTS // max(n_params, 1))
    for start in range(0, m, size):
        yield slice(start, min(start + size, m))


# --------------------------------------------------------------------------------------
# training data


def _box_interval(
    origins: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameters ``[t_in, t_out]`` (m) of the closed box ``[lo, hi]``
    (:func:`~lidarjax.raytrace.ray_box`, in float64 whatever JAX's default); empty
    (``t_in > t_out``) for rays that miss it. ``[n 2]`` inputs, ``[n]`` outputs."""
    with jax.enable_x64(True):
        t_in, t_out = ray_box(lo, hi, np.asarray(origins, np.float64), dirs)
        return np.asarray(t_in), np.asarray(t_out)


def occupancy_training_points(
    rays: RayBatch,
    lower,
    upper,
    *,
    free_step_m: float = 0.25,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Labelled occupied/free sample points of 2-D lidar rays inside a box.

    - Occupied (label 1): the end points of HIT rays that lie inside the box.
    - Free (label 0): points along each ray's known free path, from the sensor to
      ``HIT_MARGIN_M`` = 0.1 m before the end point of a HIT ray, or to ``r_max`` for a SUP
      ray; SUB rays give nothing. Only the part inside the box is sampled, every
      ``free_step_m`` metres starting at a uniformly random offset in ``[0, free_step_m)``
      (one offset per ray) from where the free path enters the box.

    Args:
        rays: 2-D rays of any batch shape (flattened row-major).
        lower: ``[2]`` lower corner of the box (m).
        upper: ``[2]`` upper corner of the box (m), ``> lower``.
        free_step_m: spacing (m) of the free samples along a ray, ``> 0``.
        seed: seed of the random per-ray offsets.

    Returns:
        ``(points, labels)``: ``[n 2]`` float64 sample points (m), all inside the closed box,
        occupied points first (in ray order), then free points (grouped by ray, ordered along
        it); ``[n]`` int64 labels in ``{0, 1}``.

    Raises:
        ValueError: rays not a 2-D RayBatch, bad box, ``free_step_m <= 0`` or bad seed.
    """
    if not isinstance(rays, RayBatch):
        raise ValueError(f"rays must be a RayBatch, got {type(rays).__name__}")
    if rays.dim != 2:
        raise ValueError(f"rays must be 2-D, got dim {rays.dim}")
    lo, hi = _check_box(lower, upper)
    step = _check_positive(free_step_m, "free_step_m")
    rng = np.random.default_rng(_check_seed(seed))

    flat = rays.flatten()
    o = np.asarray(flat.origins, dtype=np.float64)
    d = np.asarray(flat.directions, dtype=np.float64)
    r = np.asarray(flat.ranges, dtype=np.float64)
    kind = np.asarray(flat.kind)
    r_max = float(flat.r_max)

    # occupied: in-box HIT end points
    is_hit = kind == HIT
    ends = o[is_hit] + r[is_hit, None] * d[is_hit]
    occ = ends[np.all((ends >= lo) & (ends <= hi), axis=1)]

    # free: [0, free_len] along the ray, clipped to the box
    free_len = np.where(is_hit, r - HIT_MARGIN_M, np.where(kind == SUP, r_max, -np.inf))
    t_in, t_out = _box_interval(o, d, lo, hi)
    t0 = np.maximum(t_in, 0.0)
    t1 = np.minimum(t_out, free_len)
    offset = rng.uniform(0.0, step, size=r.shape[0])  # drawn for every ray: stable stream
    start = t0 + offset
    span = t1 - start
    # samples start + k * step for k >= 0 with start + k * step <= t1
    count = np.where(np.isfinite(span) & (span >= 0), np.floor(span / step) + 1, 0)
    count = count.astype(np.int64)
    ray_idx = np.repeat(np.arange(r.shape[0]), count)
    first = np.cumsum(count) - count
    k = np.arange(ray_idx.shape[0]) - first[ray_idx]
    t = start[ray_idx] + k * step
    free = o[ray_idx] + t[:, None] * d[ray_idx]
    # guard against round-off at the box faces
    free = free[np.all((free >= lo) & (free <= hi), axis=1)]

    points = np.concatenate([occ, free], axis=0)
    labels = np.concatenate([np.ones(occ.shape[0], np.int64), np.zeros(free.shape[0], np.int64)])
    return points, labels


# --------------------------------------------------------------------------------------
# Gaussian-process occupancy map


class GPOccupancyMap:
    """Gaussian-process occupancy map (O'Callaghan & Ramos 2012 style).

    Attributes:
        model: the fitted ``sklearn`` ``GaussianProcessRegressor`` (targets ``+1`` occupied,
            ``-1`` free; zero prior mean, so far from the data ``p -> 0.5``).
        points: ``[k 2]`` training points used (m), ``k = n_parameters``.
        labels: ``[k]`` their labels in ``{0, 1}``.
        n_parameters: number of training points used (the GP's parameter vector, the
            weights ``K^-1 y``, has this length).
    """

    def __init__(self, model: GaussianProcessRegressor, points: np.ndarray, labels: np.ndarray):
        self.model = model
        self.points = points
        self.labels = labels
        self.n_parameters = int(points.shape[0])

    def latent(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Predictive mean and standard deviation (without observation noise) of the latent
        GP at ``[m 2]`` points (m); two ``[m]`` arrays."""
        q = _check_points(points)
        mu = np.empty(q.shape[0])
        sd = np.empty(q.shape[0])
        for sl in _chunks(q.shape[0], self.n_parameters):
            mu[sl], sd[sl] = self.model.predict(q[sl], return_std=True)
        return mu, sd

    def occupancy(self, points) -> np.ndarray:
        """Occupancy probabilities ``Phi(mu / sqrt(1 + sigma^2))`` at ``[m 2]`` points (m),
        clipped to ``[1e-6, 1 - 1e-6]``; ``[m]`` float64."""
        mu, sd = self.latent(points)
        p = ndtr(mu / np.sqrt(1.0 + sd**2))
        return np.clip(p, PROB_CLIP, 1.0 - PROB_CLIP)


def _stratified_subsample(labels: np.ndarray, budget: int, rng: np.random.Generator):
    """Sorted indices of ``min(budget, n)`` samples keeping the class ratio (each present
    class keeps at least one sample when ``budget >= 2``)."""
    n = labels.shape[0]
    if n <= budget:
        return np.arange(n)
    idx1 = np.flatnonzero(labels == 1)
    idx0 = np.flatnonzero(labels == 0)
    n1, n0 = idx1.shape[0], idx0.shape[0]
    k1 = int(round(budget * n1 / n))
    if budget >= 2 and n1 > 0 and n0 > 0:
        k1 = min(max(k1, 1), budget - 1)
    k1 = min(max(k1, budget - n0), n1)  # feasible: k1 <= n1 and budget - k1 <= n0
    pick1 = rng.choice(idx1, size=k1, replace=False)
    pick0 = rng.choice(idx0, size=budget - k1, replace=False)
    return np.sort(np.concatenate([pick1, pick0]))


def fit_gpom(
    points,
    labels,
    budget: int,
    *,
    seed: int = 0,
    length_scale_m: float = 0.5,
    nu: float = 1.5,
    noise: float = 0.1,
    optimize: bool = False,
) -> GPOccupancyMap:
    """Fit a Gaussian-process occupancy map to labelled points.

    The training set is randomly downsampled (stratified by label) to exactly ``budget``
    points (all points if there are fewer). The GP has zero prior mean, a unit-variance
    ``Matern(length_scale_m, nu)`` kernel and i.i.d. Gaussian observation noise of standard
    deviation ``noise`` on the targets ``+1`` (occupied) / ``-1`` (free).

    Defaults: ``length_scale_m = 0.5`` m (a few free-sample spacings, wide enough to bridge
    the gaps a limited budget leaves, narrow enough to keep walls in a room), ``nu = 1.5``
    (once-differentiable fields, as in O'Callaghan & Ramos), ``noise = 0.1`` (targets are
    nearly noise-free labels; a small value keeps the kernel matrix well conditioned).

    Args:
        points: ``[n 2]`` training points (m), e.g. from :func:`occupancy_training_points`.
        labels: ``[n]`` labels, 1 occupied, 0 free.
        budget: number of training points kept (the map's parameter count), ``>= 1``.
        seed: seed of the subsampling (and of the optimiser's restarts).
        length_scale_m: Matern length scale (m), ``> 0``; initial value if ``optimize``.
        nu: Matern smoothness (e.g. 0.5, 1.5, 2.5, inf), ``> 0``.
        noise: standard deviation of the target noise, ``> 0`` (``alpha = noise**2``).
        optimize: maximise the marginal likelihood over the length scale (L-BFGS-B).

    Returns:
        The fitted :class:`GPOccupancyMap`.

    Raises:
        ValueError: empty/non-finite points, labels not in ``{0, 1}`` or of the wrong shape,
            ``budget < 1``, non-positive hyperparameters, or bad seed.
    """
    p, lab, budget = _check_training(points, labels, budget)
    seed = _check_seed(seed)
    ell = _check_positive(length_scale_m, "length_scale_m")
    if isinstance(nu, bool) or not isinstance(nu, numbers.Real) or not float(nu) > 0:
        raise ValueError(f"nu must be > 0, got {nu!r}")
    sigma_n = _check_positive(noise, "noise")
    rng = np.random.default_rng(seed)
    keep = _stratified_subsample(lab, budget, rng)
    p, lab = p[keep], lab[keep]
    kernel = Matern(
        length_scale=ell,
        length_scale_bounds=(1e-2, 1e2) if optimize else "fixed",
        nu=float(nu),
    )
    gp = GaussianProcessRegressor(
        kernel=kernel,
        alpha=sigma_n**2,
        optimizer="fmin_l_bfgs_b" if optimize else None,
        normalize_y=False,
        random_state=seed,
    )
    gp.fit(p, 2.0 * lab - 1.0)
    return GPOccupancyMap(gp, p, lab)


# --------------------------------------------------------------------------------------
# Hilbert map


class HilbertMap:
    """Hilbert map (Ramos & Ott 2015): logistic regression on Nystroem RBF features.

    Attributes:
        features: the fitted ``sklearn`` ``Nystroem`` feature map.
        classifier: the fitted ``sklearn`` ``LogisticRegression``.
        n_parameters: number of Nystroem components (feature weights; the intercept is not
            counted).
    """

    def __init__(self, features: Nystroem, classifier: LogisticRegression):
        self.features = features
        self.classifier = classifier
        self.n_parameters = int(features.components_.shape[0])
        self._col = int(np.flatnonzero(classifier.classes_ == 1)[0])

    def occupancy(self, points) -> np.ndarray:
        """Occupancy probabilities ``P(occupied)`` at ``[m 2]`` points (m), clipped to
        ``[1e-6, 1 - 1e-6]``; ``[m]`` float64."""
        q = _check_points(points)
        out = np.empty(q.shape[0])
        for sl in _chunks(q.shape[0], self.n_parameters):
            phi = self.features.transform(q[sl])
            out[sl] = self.classifier.predict_proba(phi)[:, self._col]
        return np.clip(out, PROB_CLIP, 1.0 - PROB_CLIP)


def fit_hilbert(
    points,
    labels,
    budget: int,
    *,
    seed: int = 0,
    gamma: float | None = None,
    C: float = 1.0,
) -> HilbertMap:
    """Fit a Hilbert map to labelled points.

    Features: Nystroem approximation of the RBF kernel ``exp(-gamma |x - x'|^2)`` with
    ``budget`` components (landmarks drawn at random from the training points; all points
    if there are fewer). Classifier: L2-regularised logistic regression (inverse strength
    ``C``) on all training points.

    The default ``gamma = 1 / (2 * 0.5^2) = 2`` 1/m^2 is the RBF of length scale 0.5 m, the
    same length scale as the default GP of :func:`fit_gpom`, so both baselines smooth alike.

    Args:
        points: ``[n 2]`` training points (m).
        labels: ``[n]`` labels, 1 occupied, 0 free; both classes must be present.
        budget: number of Nystroem components (the map's parameter count), ``>= 1``.
        seed: seed of the landmark selection.
        gamma: RBF coefficient (1/m^2), ``> 0``; default 2.
        C: inverse L2 regularisation strength, ``> 0``.

    Returns:
        The fitted :class:`HilbertMap`.

    Raises:
        ValueError: as :func:`fit_gpom`, a single-class label set, or ``gamma``/``C <= 0``.
    """
    p, lab, budget = _check_training(points, labels, budget)
    seed = _check_seed(seed)
    g = 1.0 / (2.0 * 0.5**2) if gamma is None else _check_positive(gamma, "gamma")
    c = _check_positive(C, "C")
    if np.unique(lab).shape[0] < 2:
        raise ValueError("labels must contain both classes (0 free and 1 occupied)")
    features = Nystroem(
        kernel="rbf", gamma=g, n_components=min(budget, p.shape[0]), random_state=seed
    )
    phi = features.fit_transform(p)
    clf = LogisticRegression(C=c, max_iter=1000)
    clf.fit(phi, lab)
    return HilbertMap(features, clf)


# --------------------------------------------------------------------------------------
# rasterisation


def rasterize(
    occupancy_fn: Callable[[np.ndarray], np.ndarray],
    lower,
    upper,
    *,
    resolution_m: float = 0.05,
) -> tuple[GridSpec, np.ndarray]:
    """Evaluate a continuous occupancy field at the cell centres of a grid over a box.

    The grid is ``GridSpec.from_bounds(lower, upper, resolution_m)``: lower corner ``lower``,
    and the smallest number of cells per axis that covers ``upper`` (so its upper corner may
    exceed ``upper`` by less than one cell). The field is evaluated in chunks of at most
    65536 points.

    Args:
        occupancy_fn: maps ``[m 2]`` points (m) to ``[m]`` probabilities in ``[0, 1]``, e.g.
            ``GPOccupancyMap.occupancy`` or ``HilbertMap.occupancy``.
        lower: ``[2]`` lower corner (m).
        upper: ``[2]`` upper corner (m), ``> lower``.
        resolution_m: cell edge length (m), ``> 0``.

    Returns:
        ``(spec, probs)``: the grid and the ``[nx ny]`` float64 occupancies, ``probs[i, j]``
        at the centre of cell ``(i, j)``.

    Raises:
        ValueError: ``occupancy_fn`` not callable, bad box or resolution, or an occupancy
            output of the wrong shape or outside ``[0, 1]``.
    """
    if not callable(occupancy_fn):
        raise ValueError(f"occupancy_fn must be callable, got {type(occupancy_fn).__name__}")
    lo, hi = _check_box(lower, upper)
    res = _check_positive(resolution_m, "resolution_m")
    spec = GridSpec.from_bounds(lo, hi, res)
    centers = np.asarray(spec.cell_centers(), dtype=np.float64).reshape(-1, 2)
    out = np.empty(centers.shape[0])
    for start in range(0, centers.shape[0], _RASTER_CHUNK):
        sl = slice(start, min(start + _RASTER_CHUNK, centers.shape[0]))
        vals = np.asarray(occupancy_fn(centers[sl]), dtype=np.float64)
        if vals.shape != (sl.stop - sl.start,):
            raise ValueError(
                f"occupancy_fn must map [m, 2] points to [m] values, got shape {vals.shape} "
                f"for m = {sl.stop - sl.start}"
            )
        if not np.all((vals >= 0) & (vals <= 1)):
            raise ValueError("occupancy_fn must return probabilities in [0, 1]")
        out[sl] = vals
    return spec, out.reshape(spec.shape)


def occupancy_reflection_map(
    spec: GridSpec, probs, *, unknown_prob: float | None = None
) -> ReflectionMap:
    """Reflection map whose per-cell reflection probabilities are rasterised occupancies.

    Sec. 9.5.2 rasterises the continuous GP / Hilbert occupancy fields and cumulates the
    occupancy probabilities along the rays; that is exactly the reflection model, so
    :func:`lidarjax.sensor_models.reflection_log_likelihood` on the returned map gives the
    baselines' ray likelihoods.

    Outside the grid, the reflection model treats space as a homogeneous medium of cells of
    the grid's resolution with reflection probability ``unknown_prob`` (rays that start or
    travel outside the grid are attenuated by it, HITs outside get its density). Rays
    should therefore stay inside the rasterised box; for the parts that do not, the default
    ``unknown_prob`` is the mean rasterised occupancy, the reflection probability of the map
    collapsed to a homogeneous medium (like the global hit ratio that
    :func:`lidarjax.maps.reflection_map` uses). ``0`` would make HITs outside the grid
    impossible (``-inf``), ``1`` would make any ray that leaves the grid impossible.

    Args:
        spec: the grid of ``probs`` (e.g. from :func:`rasterize`), 2-D.
        probs: ``[nx ny]`` occupancy probabilities in ``[0, 1]``.
        unknown_prob: reflection probability outside the grid, in ``[0, 1]``; default the
            mean of ``probs``.

    Returns:
        A :class:`~lidarjax.maps.ReflectionMap` (float64 if x64 is enabled).

    Raises:
        ValueError: ``spec`` not a GridSpec, ``probs`` of the wrong shape, non-finite or
            outside ``[0, 1]``, or a bad ``unknown_prob``.
    """
    if not isinstance(spec, GridSpec):
        raise ValueError(f"spec must be a GridSpec, got {type(spec).__name__}")
    q = np.asarray(probs, dtype=np.float64)
    if q.shape != spec.shape:
        raise ValueError(f"probs must have the grid shape {spec.shape}, got {q.shape}")
    if not np.all(np.isfinite(q) & (q >= 0) & (q <= 1)):
        raise ValueError("probs must be finite probabilities in [0, 1]")
    if unknown_prob is None:
        u = float(q.mean())
    else:
        if isinstance(unknown_prob, bool) or not isinstance(unknown_prob, numbers.Real):
            raise ValueError(f"unknown_prob must be a real number, got {unknown_prob!r}")
        u = float(unknown_prob)
        if not (0.0 <= u <= 1.0):
            raise ValueError(f"unknown_prob must be in [0, 1], got {u}")
    dtype = spec.origin.dtype
    return ReflectionMap(spec=spec, probs=jnp.asarray(q, dtype), unknown_prob=jnp.asarray(u, dtype))
