"""SE(2) pose-graph optimisation: Levenberg-Marquardt on the manifold with a dense LU
solve and Cauchy-robust (IRLS) edges, the back end of decay-rate SLAM (issue #24).

Poses are ``(x, y, yaw)`` rows (m, m, rad). An edge ``(i, j)`` carries a measurement
``Z_ij`` of pose ``j`` in the frame of pose ``i`` and its standard deviations
``sigma_ij``; its whitened residual is

    r_ij = Log(Z_ij^-1 (T_i^-1 T_j)) / sigma_ij          (SE(2) log, element-wise divide)

or, for an edge with a full ``[3, 3]`` square-root information ``W_ij`` (``W^T W`` the
information matrix; ``W = diag(1 / sigma)`` is the case above),
``r_ij = W_ij Log(Z_ij^-1 (T_i^-1 T_j))``,

and the cost is ``sum_ij rho(|r_ij|)`` with ``rho(s) = s^2 / 2`` for ordinary edges and the
Cauchy kernel ``rho(s) = c^2 / 2 * log(1 + s^2 / c^2)`` (weight ``w(s) = rho'(s) / s =
1 / (1 + s^2 / c^2)``) on the robust ones, applied to the norm of the whole whitened
3-vector. This is GTSAM's ``noiseModel.Robust.Create(mEstimator.Cauchy.Create(c), Diagonal
.Sigmas(sigma))`` (same loss, same weight), so the cost equals GTSAM's graph error.

Each iteration linearises every edge in the tangent spaces of its two poses (``T <- T
exp(delta)``; a 3x6 Jacobian block per edge by ``jax.jacfwd``, batched with ``vmap``),
recomputes the IRLS weights, scatter-adds ``H = J^T W J`` and ``g = J^T W r`` into a dense
``[3n, 3n]`` system, removes the gauge node's rows and columns (its pose stays exactly
``poses0[fixed]``), and solves ``(H + lambda diag(H)) delta = -g`` by LU. A step is
accepted only if the robust cost decreases (then ``lambda`` shrinks), otherwise ``lambda``
grows (both bounded). The loop stops after ``max_iters`` iterations, when an accepted step
decreases the cost by less than ``tol`` relative, when a step no longer moves the poses
(a few ulp), when ``lambda`` hits its bound, or when the cost is not finite. The whole solve
is one jitted program (shapes static, no host round trips).

Dense storage costs ``(3n)^2`` floats (60 MB for ``n = 910`` poses in float64) and each
iteration one dense LU factorisation, ``O((3n)^3)``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Bool, Float, Int

__all__ = ["PoseGraphResult", "optimize_pose_graph"]

_LAMBDA_INIT = 1e-4  # initial Marquardt damping (relative to diag(H))
_LAMBDA_MIN = 1e-10
_LAMBDA_MAX = 1e10
_LAMBDA_FACTOR = 10.0  # lambda /= factor on an accepted step, *= factor on a rejected one
_STEP_ULPS = 100.0  # a step below this many ulp of the poses' scale ends the loop


class PoseGraphResult(eqx.Module):
    """The optimised pose graph.

    Attributes:
        poses: ``[n, 3]`` optimised poses ``(x m, y m, yaw rad)``, yaw wrapped to
            ``[-pi, pi)``; row ``fixed`` equals the initial pose.
        cost: ``[]`` final robust cost ``sum rho(|r|)`` (``0.5 |r|^2`` on ordinary edges,
            the Cauchy loss on robust ones; whitened, dimensionless).
        cost0: ``[]`` the same cost at the initial poses.
        n_iters: ``[]`` Levenberg-Marquardt iterations run (accepted and rejected steps).
        edge_weights: ``[e]`` IRLS weights at the final poses, ``1 / (1 + |r|^2 / c^2)`` on
            robust edges and 1 on the others: a loop closure with a small weight is one the
            graph rejects.
    """

    poses: Float[Array, "n 3"]
    cost: Float[Array, ""]
    cost0: Float[Array, ""]
    n_iters: Int[Array, ""]
    edge_weights: Float[Array, " e"]


# --- the problem --------------------------------------------------------------------------


def _se2(params) -> jaxlie.SE2:
    return jaxlie.SE2(params)


def _edge_residual(p_i, p_j, z, sqrt_info) -> Array:
    """Whitened residual ``[3]`` of one edge: ``W Log(Z^-1 (T_i^-1 T_j))``."""
    # jaxlie's log returns float64 for float32 input when x64 is on: keep the input's dtype
    tangent = (_se2(z).inverse() @ (_se2(p_i).inverse() @ _se2(p_j))).log().astype(p_i.dtype)
    return sqrt_info @ tangent


def _edge_linearise(p_i, p_j, z, sqrt_info):
    """Residual ``[3]`` and Jacobian ``[3, 6]`` w.r.t. the tangent deltas ``(d_i, d_j)`` of
    ``T_i exp(d_i)``, ``T_j exp(d_j)`` at zero.

    The Jacobian is taken through the retraction ``T (d_x, d_y, d_yaw)`` (translation then
    rotation) instead of ``T exp(d)``: the two agree to first order at ``d = 0``
    (``exp(d) = (V(d_yaw) (d_x, d_y), d_yaw)`` with ``V = I + O(d_yaw)``), so the
    Jacobian is identical, and XLA compiles the simpler chart faster. Steps are applied
    with ``exp`` (:func:`_solve`).
    """

    def f(d):
        t_i = _se2(p_i) @ jaxlie.SE2.from_xy_theta(d[0], d[1], d[2])
        t_j = _se2(p_j) @ jaxlie.SE2.from_xy_theta(d[3], d[4], d[5])
        r = _edge_residual(t_i.parameters(), t_j.parameters(), z, sqrt_info)
        return r, r

    jac, r = jax.jacfwd(f, has_aux=True)(jnp.zeros(6, p_i.dtype))
    return r, jac


def _retract(p, delta):
    """``T exp(delta)`` (SE(2) parameters ``[4]``, the dtype of ``p``)."""
    step = jaxlie.SE2.exp(delta).parameters().astype(p.dtype)  # jaxlie may promote
    return (_se2(p) @ _se2(step)).parameters()


def _robust_terms(r, robust, c):
    """Per-edge robust cost ``[e]`` and IRLS weight ``[e]`` of whitened residuals ``[e, 3]``."""
    s2 = jnp.sum(r * r, axis=-1)
    u = s2 / (c * c)
    cost = jnp.where(robust, 0.5 * c * c * jnp.log1p(u), 0.5 * s2)
    weight = jnp.where(robust, 1.0 / (1.0 + u), jnp.ones_like(s2))
    return cost, weight


def _to_xy_yaw(params) -> Array:
    pose = _se2(params)
    yaw = pose.rotation().as_radians()
    yaw = jnp.where(yaw >= jnp.pi, yaw - 2 * jnp.pi, yaw)  # atan2's +pi -> -pi
    return jnp.concatenate([pose.translation(), yaw[..., None]], axis=-1)


@eqx.filter_jit
def _solve(poses0, edges, z_xy_yaw, sqrt_info, robust, c, fixed, max_iters, tol):
    """The Levenberg-Marquardt loop. Each pass evaluates the candidate poses once
    (residuals, Jacobians, weights, cost: the only copy of the edge model in the program),
    accepts or rejects them, and solves for the next candidate from the normal equations
    of the current poses (kept in the loop state, so a rejected step costs one LU solve)."""
    dtype = poses0.dtype
    n = poses0.shape[0]
    e = edges.shape[0]
    params0 = jaxlie.SE2.from_xy_theta(poses0[:, 0], poses0[:, 1], poses0[:, 2]).parameters()
    z = jaxlie.SE2.from_xy_theta(z_xy_yaw[:, 0], z_xy_yaw[:, 1], z_xy_yaw[:, 2]).parameters()
    idx = (3 * edges[:, :, None] + jnp.arange(3)[None, None, :]).reshape(-1, 6)  # [e, 6]
    free = jnp.repeat(jnp.arange(n) != fixed, 3)  # [3n]: the gauge node's rows are fixed
    eps = jnp.finfo(dtype).eps

    def normal_equations(r, jac, w):
        jtj = jnp.einsum("e,eka,ekb->eab", w, jac, jac)  # [e, 6, 6]
        jtr = jnp.einsum("e,eka,ek->ea", w, jac, r)  # [e, 6]
        h = jnp.zeros((3 * n, 3 * n), dtype).at[idx[:, :, None], idx[:, None, :]].add(jtj)
        g = jnp.zeros(3 * n, dtype).at[idx].add(jtr)
        h = jnp.where(free[:, None] & free[None, :], h, 0.0)  # drop the gauge node
        return h, jnp.where(free, g, 0.0)

    def solve(params, h, g, lam):
        d = jnp.diagonal(h)
        d = jnp.maximum(d, 1e-9 * jnp.max(d))  # an unconstrained direction stays damped
        a = h + jnp.diag(jnp.where(free, lam * d, 1.0))  # the gauge rows: identity
        # LU, not Cholesky: on the CPU, OpenBLAS's threaded Cholesky of a [2730 2730]
        # matrix took 3.5-4.5 s on 2 cores, LU 0.7 s (measured; same answer to round-off)
        delta = -jnp.linalg.solve(a, g)
        delta = jnp.where(free, delta, 0.0).reshape(n, 3)
        new = jax.vmap(_retract)(params, delta)
        scale = 1.0 + jnp.max(jnp.abs(params[:, 2:]))
        # a failed factorisation (NaN step) is not tiny: it is rejected and lambda grows
        tiny = jnp.max(jnp.abs(delta)) <= _STEP_ULPS * eps * scale
        return new, tiny

    def cond(state):
        evals, done, cost = state[0], state[1], state[3]
        # evaluation k > 0 is iteration k; the first one is the initial cost
        return (evals <= max_iters) & ~done & ~(jnp.isnan(cost) | (cost == jnp.inf))

    def body(state):
        evals, _, params, cost, cost0, weights, h, g, lam, cand = state
        r, jac = jax.vmap(_edge_linearise)(cand[edges[:, 0]], cand[edges[:, 1]], z, sqrt_info)
        terms, w = _robust_terms(r, robust, c)
        cand_cost = jnp.sum(terms)
        first = evals == 0
        accept = first | (cand_cost < cost)  # False for NaN after the first
        rel = (cost - cand_cost) / jnp.maximum(cost, jnp.finfo(dtype).tiny)
        converged = ~first & accept & ((rel < tol) | (cand_cost <= 0))
        h_new, g_new = normal_equations(r, jac, w)
        params = jnp.where(accept, cand, params)
        cost = jnp.where(accept, cand_cost, cost)
        cost0 = jnp.where(first, cand_cost, cost0)
        weights = jnp.where(accept, w, weights)
        h = jnp.where(accept, h_new, h)
        g = jnp.where(accept, g_new, g)
        lam = jnp.where(
            first,
            lam,
            jnp.where(
                accept,
                jnp.maximum(lam / _LAMBDA_FACTOR, _LAMBDA_MIN),
                jnp.minimum(lam * _LAMBDA_FACTOR, _LAMBDA_MAX),
            ),
        )
        stuck = ~accept & (lam >= _LAMBDA_MAX)
        cand, tiny = solve(params, h, g, lam)
        done = converged | stuck | tiny | (first & (cand_cost <= 0))
        return evals + 1, done, params, cost, cost0, weights, h, g, lam, cand

    zero = jnp.zeros((), dtype)
    state = (
        jnp.asarray(0, jnp.int32),  # evaluations of candidates
        jnp.asarray(False),  # done
        params0,  # current poses
        zero,  # current cost
        zero,  # initial cost
        jnp.ones(e, dtype),  # IRLS weights at the current poses
        jnp.zeros((3 * n, 3 * n), dtype),  # normal equations at the current poses
        jnp.zeros(3 * n, dtype),
        jnp.asarray(_LAMBDA_INIT, dtype),
        params0,  # candidate
    )
    evals, _, params, cost, cost0, weights, *_ = jax.lax.while_loop(cond, body, state)
    poses = _to_xy_yaw(params)
    # the gauge node is returned as given (yaw wrapped; exact if already in [-pi, pi))
    yaw0 = poses0[:, 2] - 2 * jnp.pi * jnp.floor((poses0[:, 2] + jnp.pi) / (2 * jnp.pi))
    given = jnp.concatenate([poses0[:, :2], yaw0[:, None]], axis=1)
    poses = jnp.where((jnp.arange(n) == fixed)[:, None], given, poses)
    return PoseGraphResult(
        poses=poses,
        cost=cost,
        cost0=cost0,
        n_iters=jnp.maximum(evals - 1, 0),
        edge_weights=weights,
    )


# --- input checks -------------------------------------------------------------------------


def _traced(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def _check_values(x, bad, name: str, what: str):
    """Raise ``ValueError`` for concrete ``x`` where ``bad(x)`` holds; traced ``x`` gets an
    ``eqx.error_if`` with the same message."""
    msg = f"{name}: {what}"
    if _traced(x):
        return eqx.error_if(x, bad(x), msg)
    if np.any(bad(x)):
        raise ValueError(msg)
    return x


def _array(x, name: str, shape: tuple):
    """``x`` as a NumPy array (a JAX array if traced) of real numbers and shape ``shape``
    (``None``: any length)."""
    try:
        a = x if _traced(x) else np.asarray(x)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name}: not a numeric array ({err})") from None
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        want = "[" + ", ".join("?" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name}: expected shape {want}, got {tuple(a.shape)}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{name}: expected real numbers, got dtype {a.dtype}")
    return a


def _scalar(x, name: str, *, integer: bool):
    if isinstance(x, bool | np.bool_):
        raise ValueError(f"{name}: expected {'an integer' if integer else 'a number'}, got {x!r}")
    if _traced(x):
        if jnp.ndim(x) != 0:
            raise ValueError(f"{name}: expected a scalar, got shape {jnp.shape(x)}")
        return x
    a = np.asarray(x)
    ok = a.ndim == 0 and (
        np.issubdtype(a.dtype, np.integer)
        if integer
        else np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)
    )
    if not ok:
        raise ValueError(f"{name}: expected {'an integer' if integer else 'a number'}, got {x!r}")
    return a.item()


def optimize_pose_graph(
    poses0: Float[Array, "n 3"],
    edges: Int[Array, "e 2"],
    measurements: Float[Array, "e 3"],
    sigmas: Float[Array, "e 3"] | None = None,
    *,
    sqrt_information: Float[Array, "e 3 3"] | None = None,
    robust: Bool[Array, " e"] | None = None,
    cauchy_scale: float = 1.0,
    fixed: int = 0,
    max_iters: int = 50,
    tol: float = 1e-9,
) -> PoseGraphResult:
    """Optimise an SE(2) pose graph by Levenberg-Marquardt on the manifold.

    Minimises ``sum_e rho(|W_e Log(Z_e^-1 (T_i^-1 T_j))|)`` (``W_e = diag(1 / sigma_e)``,
    or a full square-root information) over all poses but the gauge node ``fixed`` (held
    at ``poses0[fixed]``), with ``rho(s) = s^2 / 2`` and, on the ``robust`` edges, the
    Cauchy kernel ``rho(s) = c^2 / 2 log(1 + s^2 / c^2)`` (IRLS weight
    ``1 / (1 + s^2 / c^2)``, GTSAM's ``mEstimator.Cauchy``), see the module docstring.
    Runs as one jitted program; float32 and float64 (the dtype of the inputs).

    Args:
        poses0: ``[n, 3]`` initial poses ``(x m, y m, yaw rad)``.
        edges: ``[e, 2]`` integer node indices ``(i, j)``, ``i != j``: edge ``k`` measures
            pose ``j`` in the frame of pose ``i``.
        measurements: ``[e, 3]`` relative poses ``(dx m, dy m, dyaw rad)`` of
            ``poses[i]^-1 poses[j]``.
        sigmas: ``[e, 3]`` standard deviations ``(m, m, rad)`` of the measurements, ``> 0``.
            Give either ``sigmas`` or ``sqrt_information``.
        sqrt_information: ``[e, 3, 3]`` square-root information ``W`` of each measurement
            (``W^T W`` its information matrix, in ``(m, m, rad)`` units inverted, in the
            tangent space of ``T_i^-1 T_j`` (right perturbation); e.g. the transposed
            Cholesky factor of the information). A singular ``W`` (an edge that fixes
            only some directions) is allowed; the graph as a whole must fix every pose.
        robust: ``[e]`` bool, the edges (loop closures) that get the Cauchy kernel; default
            none.
        cauchy_scale: the Cauchy scale ``c`` in whitened units (standard deviations), > 0.
        fixed: index of the node held fixed (the gauge).
        max_iters: maximum number of Levenberg-Marquardt iterations (>= 0).
        tol: stop when an accepted step decreases the cost by less than this fraction.

    Returns:
        :class:`PoseGraphResult` with the optimised ``[n, 3]`` poses, the final and initial
        costs, the iterations run and the final ``[e]`` IRLS edge weights.

    Raises:
        ValueError: naming the argument, for wrong shapes, non-finite poses or
            measurements, sigmas ``<= 0``, a non-finite ``sqrt_information``, both or
            neither of ``sigmas`` and ``sqrt_information``, edge indices out of range or
            ``i == j``, no edges, ``fixed`` out of range, ``cauchy_scale <= 0``,
            ``max_iters < 0`` or a bad ``tol``. Traced (jitted) values are checked with
            ``eqx.error_if`` instead.
    """
    poses0 = _array(poses0, "poses0", (None, 3))
    n = poses0.shape[0]
    if n == 0:
        raise ValueError("poses0: expected at least one pose, got shape (0, 3)")
    edges = _array(edges, "edges", (None, 2))
    if not np.issubdtype(edges.dtype, np.integer):
        raise ValueError(f"edges: expected integer node indices, got dtype {edges.dtype}")
    e = edges.shape[0]
    if e == 0:
        raise ValueError("edges: the graph has no edges")
    measurements = _array(measurements, "measurements", (e, 3))
    if (sigmas is None) == (sqrt_information is None):
        raise ValueError(
            "sigmas: give either sigmas or sqrt_information (one noise model per edge), "
            f"got {'both' if sigmas is not None else 'neither'}"
        )
    if sigmas is not None:
        sigmas = _array(sigmas, "sigmas", (e, 3))
        weights = sigmas
    else:
        sqrt_information = _array(sqrt_information, "sqrt_information", (e, 3, 3))
        weights = sqrt_information
    if robust is None:
        robust = np.zeros(e, bool)
    else:
        robust = robust if _traced(robust) else np.asarray(robust)
        if robust.shape != (e,) or robust.dtype != np.bool_:
            raise ValueError(
                f"robust: expected a bool array of shape ({e},), "
                f"got {robust.dtype} of shape {tuple(robust.shape)}"
            )
    # float32 or float64 (with x64 enabled), from the inputs; integers become floats
    dtype = np.result_type(poses0.dtype, measurements.dtype, weights.dtype)
    if not np.issubdtype(dtype, np.floating):
        dtype = np.dtype(float)
    dtype = jax.dtypes.canonicalize_dtype(dtype)
    cauchy_scale = _scalar(cauchy_scale, "cauchy_scale", integer=False)
    fixed = _scalar(fixed, "fixed", integer=True)
    max_iters = _scalar(max_iters, "max_iters", integer=True)
    tol = _scalar(tol, "tol", integer=False)
    if not _traced(fixed) and not 0 <= fixed < n:
        raise ValueError(f"fixed: node index {fixed} out of range for {n} poses")
    if not _traced(cauchy_scale) and not (np.isfinite(cauchy_scale) and cauchy_scale > 0):
        raise ValueError(f"cauchy_scale: expected a finite value > 0, got {cauchy_scale}")
    if not _traced(max_iters) and max_iters < 0:
        raise ValueError(f"max_iters: expected >= 0, got {max_iters}")
    if not _traced(tol) and not (np.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol: expected a finite value >= 0, got {tol}")

    def not_finite(x):
        return ~(abs(x) < np.inf)  # NumPy or JAX

    poses0 = _check_values(poses0, not_finite, "poses0", "contains NaN or inf")
    measurements = _check_values(measurements, not_finite, "measurements", "contains NaN or inf")
    if sigmas is not None:
        sigmas = _check_values(
            sigmas, lambda x: ~(x > 0) | (x == np.inf), "sigmas", "expected finite values > 0"
        )
        xp = jnp if _traced(sigmas) else np
        sqrt_info = xp.eye(3) / sigmas.astype(dtype)[:, :, None]  # diag(1 / sigma)
    else:
        sqrt_info = _check_values(
            sqrt_information, not_finite, "sqrt_information", "contains NaN or inf"
        )
    edges = _check_values(
        edges, lambda x: (x < 0) | (x >= n), "edges", f"node index out of range [0, {n})"
    )
    edges = _check_values(
        edges, lambda x: x[:, 0] == x[:, 1], "edges", "an edge connects a node to itself (i == j)"
    )
    return _solve(
        poses0.astype(dtype),
        edges.astype(jnp.int32),
        measurements.astype(dtype),
        sqrt_info.astype(dtype),
        robust,
        jnp.asarray(cauchy_scale, dtype),
        jnp.asarray(fixed, jnp.int32),
        jnp.asarray(max_iters, jnp.int32),
        jnp.asarray(tol, dtype),
    )
