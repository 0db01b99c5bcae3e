"""The SE(2) pose-graph optimiser (lidarjax.slam._pose_graph) against GTSAM, on consistent
graphs, with an outlier loop closure, in float32, and on bad input.

Every solve uses one graph layout (40 nodes, 59 edges) so the optimiser compiles once per
dtype."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from lidarjax.slam._pose_graph import PoseGraphResult, _solve, optimize_pose_graph

N = 40  # nodes
LOOP_GAP = 20  # loop edges (k - 20, k): the trajectory is a closed 20-step circle, twice
ODO_SIGMAS = np.array([0.05, 0.05, 0.02])  # m, m, rad
LOOP_SIGMAS = np.array([0.1, 0.1, 0.03])


def compose(a, b):
    """``a * b`` of ``(x, y, yaw)`` poses (NumPy, independent of jaxlie)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    yaw = a[2] + b[2]
    return np.array(
        [
            a[0] + c * b[0] - s * b[1],
            a[1] + s * b[0] + c * b[1],
            math.atan2(math.sin(yaw), math.cos(yaw)),
        ]
    )


def between(a, b):
    """``a^-1 * b`` of ``(x, y, yaw)`` poses (NumPy)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    dyaw = b[2] - a[2]
    return np.array([c * dx + s * dy, -s * dx + c * dy, math.atan2(math.sin(dyaw), math.cos(dyaw))])


def make_graph(seed: int, noise: float = 1.0):
    """Truth, edges, measurements (noise ``noise`` standard deviations), sigmas, loop mask and
    the dead-reckoning start of a 40-node circle driven twice with 20 loop closures."""
    rng = np.random.default_rng(seed)
    truth = [np.array([0.3, -0.2, 0.1])]
    for _ in range(N - 1):
        truth.append(
            compose(truth[-1], np.array([1.0, 0.0, 2 * np.pi / LOOP_GAP + rng.normal(0, 0.05)]))
        )
    truth = np.array(truth)
    edges, sigmas = [], []
    for k in range(N - 1):
        edges.append((k, k + 1))
        sigmas.append(ODO_SIGMAS)
    for k in range(LOOP_GAP, N):
        edges.append((k - LOOP_GAP, k))
        sigmas.append(LOOP_SIGMAS)
    edges, sigmas = np.array(edges), np.array(sigmas)
    meas = np.array([between(truth[i], truth[j]) for i, j in edges])
    meas = meas + noise * rng.normal(size=meas.shape) * sigmas
    loops = np.arange(len(edges)) >= N - 1
    start = [truth[0]]
    for k in range(N - 1):
        start.append(compose(start[-1], meas[k]))
    return truth, edges, meas, sigmas, loops, np.array(start)


def pose_error(a, b):
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    d[:, 2] = np.arctan2(np.sin(d[:, 2]), np.cos(d[:, 2]))
    return np.abs(d)


def check_result(res: PoseGraphResult, poses0, fixed=0):
    poses = np.asarray(res.poses)
    assert np.all(np.isfinite(poses)) and np.isfinite(res.cost) and np.isfinite(res.cost0)
    assert float(res.cost) <= float(res.cost0)
    assert np.all((poses[:, 2] >= -np.pi) & (poses[:, 2] < np.pi))
    np.testing.assert_array_equal(poses[fixed], np.asarray(poses0)[fixed])  # the gauge


def gtsam_solve(start, edges, meas, sigmas, robust=None, c=1.0, fixed=0, information=None):
    """GTSAM's Levenberg-Marquardt solution (tight prior on ``fixed``), its graph error at
    the solution and the Cauchy weights of the robust edges there (GTSAM's own kernel).
    With ``information`` (``[e, 3, 3]``) the edges get GTSAM's full Gaussian noise model
    ``noiseModel.Gaussian.Information`` instead of ``sigmas``."""
    gtsam = pytest.importorskip("gtsam")
    graph = gtsam.NonlinearFactorGraph()
    graph.add(
        gtsam.PriorFactorPose2(
            fixed, gtsam.Pose2(*start[fixed]), gtsam.noiseModel.Diagonal.Sigmas(np.full(3, 1e-9))
        )
    )
    kernel = gtsam.noiseModel.mEstimator.Cauchy.Create(c)
    factors = []
    for k, (i, j) in enumerate(edges):
        if information is None:
            model = gtsam.noiseModel.Diagonal.Sigmas(sigmas[k])
        else:
            model = gtsam.noiseModel.Gaussian.Information(information[k])
        if robust is not None and robust[k]:
            model = gtsam.noiseModel.Robust.Create(kernel, model)
        factor = gtsam.BetweenFactorPose2(int(i), int(j), gtsam.Pose2(*meas[k]), model)
        graph.add(factor)
        factors.append(factor)
    values = gtsam.Values()
    for k, p in enumerate(start):
        values.insert(k, gtsam.Pose2(*p))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-15)
    params.setAbsoluteErrorTol(1e-15)
    params.setMaxIterations(500)
    out = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    poses = np.array(
        [
            [out.atPose2(k).x(), out.atPose2(k).y(), out.atPose2(k).theta()]
            for k in range(len(start))
        ]
    )
    if information is None:
        whitened = [
            np.linalg.norm(f.unwhitenedError(out) / sigmas[k]) for k, f in enumerate(factors)
        ]
    else:
        whitened = [
            np.sqrt(f.unwhitenedError(out) @ information[k] @ f.unwhitenedError(out))
            for k, f in enumerate(factors)
        ]
    weights = np.array([kernel.weight(s) for s in whitened])
    return poses, graph.error(out), graph.error(values), weights


def test_matches_gtsam_least_squares():
    _, edges, meas, sigmas, _, start = make_graph(0)
    res = optimize_pose_graph(start, edges, meas, sigmas)
    ref, err, err0, _ = gtsam_solve(start, edges, meas, sigmas)
    check_result(res, start)
    assert pose_error(res.poses, ref).max() < 1e-6
    # the same cost as GTSAM's graph error (its prior term is ~0)
    np.testing.assert_allclose(float(res.cost0), err0, rtol=1e-9)
    np.testing.assert_allclose(float(res.cost), err, rtol=1e-9)
    assert 0 < int(res.n_iters) <= 50
    np.testing.assert_array_equal(np.asarray(res.edge_weights), 1.0)


def test_matches_gtsam_cauchy():
    """Cauchy loops, one an outlier. Both libraries use rho(s) = c^2/2 log(1 + s^2/c^2) of
    the norm s of the whitened 3-vector, weight 1 / (1 + s^2/c^2) (GTSAM's
    mEstimator.Cauchy: weight k^2 / (k^2 + s^2)); the weights are compared to GTSAM's."""
    truth, edges, meas, sigmas, loops, start = make_graph(1)
    meas[N + 5] = between(truth[edges[N + 5, 0]], truth[edges[N + 5, 1]]) + [1.0, -0.8, 0.3]
    c = 3.0
    res = optimize_pose_graph(
        start, edges, meas, sigmas, robust=loops, cauchy_scale=c, tol=1e-15, max_iters=200
    )
    ref, err, err0, weights = gtsam_solve(start, edges, meas, sigmas, robust=loops, c=c)
    check_result(res, start)
    assert pose_error(res.poses, ref).max() < 1e-6
    np.testing.assert_allclose(float(res.cost0), err0, rtol=1e-9)
    np.testing.assert_allclose(float(res.cost), err, rtol=1e-9)
    w = np.asarray(res.edge_weights)
    np.testing.assert_array_equal(w[~loops], 1.0)
    # poses agree to < 1e-6 m, i.e. < 2e-5 standard deviations: weights to ~1e-5
    np.testing.assert_allclose(w[loops], weights[loops], rtol=1e-5)
    assert w[N + 5] < 0.05
    assert np.delete(w[loops], 6).min() > 0.3  # loop N + 5 is the 7th


def random_information(seed: int, sigmas):
    """``[e, 3, 3]`` information matrices with correlated axes (random rotations of the
    ``(x, y, yaw)`` axes scaled by ``sigmas``), and their square roots ``W`` (``W^T W``)."""
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(len(sigmas), 3, 3)))
    scale = rng.uniform(0.5, 2.0, size=(len(sigmas), 3))
    w = np.einsum("ei,eij->eij", 1.0 / (sigmas * scale), q)  # W = diag(1/s) Q
    return np.einsum("eki,ekj->eij", w, w), w


def test_full_information_matches_gtsam():
    """Edges with full (correlated) information matrices, Cauchy loops and one outlier,
    against GTSAM's ``noiseModel.Gaussian.Information`` (the same cost: ``0.5 r^T L r``,
    robust on the loops)."""
    truth, edges, meas, sigmas, loops, start = make_graph(5)
    meas[N + 3] = between(truth[edges[N + 3, 0]], truth[edges[N + 3, 1]]) + [0.8, 0.5, -0.3]
    info, w = random_information(6, sigmas)
    c = 2.0
    res = optimize_pose_graph(
        start, edges, meas, sqrt_information=w, robust=loops, cauchy_scale=c, tol=1e-15,
        max_iters=200,
    )  # fmt: skip
    ref, err, err0, weights = gtsam_solve(
        start, edges, meas, sigmas, robust=loops, c=c, information=info
    )
    check_result(res, start)
    assert pose_error(res.poses, ref).max() < 1e-6
    np.testing.assert_allclose(float(res.cost0), err0, rtol=1e-9)
    np.testing.assert_allclose(float(res.cost), err, rtol=1e-9)
    np.testing.assert_allclose(np.asarray(res.edge_weights)[loops], weights[loops], rtol=1e-5)
    assert float(res.edge_weights[N + 3]) < 0.05
    # any square root of the same information gives the same solve (W -> R W, R orthogonal)
    rot, _ = np.linalg.qr(np.random.default_rng(7).normal(size=(len(edges), 3, 3)))
    res2 = optimize_pose_graph(
        start, edges, meas, sqrt_information=rot @ w, robust=loops, cauchy_scale=c, tol=1e-15,
        max_iters=200,
    )  # fmt: skip
    assert pose_error(res2.poses, res.poses).max() < 1e-6  # as converged as against GTSAM


def test_diagonal_sqrt_information_is_sigmas():
    _, edges, meas, sigmas, loops, start = make_graph(0)
    a = optimize_pose_graph(start, edges, meas, sigmas, robust=loops, cauchy_scale=2.0)
    w = np.eye(3) / sigmas[:, :, None]
    b = optimize_pose_graph(start, edges, meas, sqrt_information=w, robust=loops, cauchy_scale=2.0)
    np.testing.assert_array_equal(np.asarray(a.poses), np.asarray(b.poses))
    assert float(a.cost) == float(b.cost) and int(a.n_iters) == int(b.n_iters)


def test_rank_deficient_edges():
    """Edges that fix only some directions (a corridor's match: across, not along) are
    allowed; where the others fix the rest, the solve is the same as with those directions
    given any other weight on a consistent graph."""
    truth, edges, meas, sigmas, _, _ = make_graph(2, noise=0.0)
    rng = np.random.default_rng(8)
    start = truth + rng.normal(size=truth.shape) * [0.3, 0.3, 0.1]
    start[0] = truth[0]
    w = np.eye(3) / sigmas[:, :, None]
    w[N:, 0, :] = 0.0  # loops 1..: no information along x
    res = optimize_pose_graph(start, edges, meas, sqrt_information=w)
    check_result(res, start)
    assert pose_error(res.poses, truth).max() < 1e-9


@pytest.mark.parametrize("fixed", [0, 27])
def test_consistent_graph_recovered_exactly(fixed):
    truth, edges, meas, sigmas, _, _ = make_graph(2, noise=0.0)
    rng = np.random.default_rng(3)
    start = truth + rng.normal(size=truth.shape) * [0.5, 0.5, 0.3]
    start[fixed] = truth[fixed]
    res = optimize_pose_graph(start, edges, meas, sigmas, fixed=fixed)
    check_result(res, start, fixed)
    assert pose_error(res.poses, truth).max() < 1e-9
    assert float(res.cost) < 1e-15 < 1.0 < float(res.cost0)


def test_outlier_loop_rejected_only_with_cauchy():
    """An outlier loop (2 m, 0.4 rad off): with Cauchy loops its weight is tiny and the poses
    are those of the graph with the loop measured correctly; least squares bends them."""
    truth, edges, meas, sigmas, loops, start = make_graph(4, noise=0.5)
    bad = N + 10  # loop (10, 30)
    clean = optimize_pose_graph(start, edges, meas, sigmas, robust=loops, cauchy_scale=2.0)
    meas[bad] = between(truth[10], truth[30]) + [2.0, 0.0, 0.4]
    robust = optimize_pose_graph(start, edges, meas, sigmas, robust=loops, cauchy_scale=2.0)
    plain = optimize_pose_graph(start, edges, meas, sigmas)
    check_result(robust, start)
    check_result(plain, start)
    w = np.asarray(robust.edge_weights)
    assert w[bad] < 0.02
    assert np.delete(w[loops], bad - (N - 1)).min() > 0.5
    np.testing.assert_array_equal(np.asarray(plain.edge_weights), 1.0)
    assert pose_error(robust.poses, clean.poses)[:, :2].max() < 0.02
    assert pose_error(plain.poses, clean.poses)[:, :2].max() > 0.2
    assert pose_error(robust.poses, truth)[:, :2].max() < 0.15
    assert pose_error(plain.poses, truth)[:, :2].max() > 0.3


def test_float32():
    _, edges, meas, sigmas, loops, start = make_graph(0)
    r64 = optimize_pose_graph(start, edges, meas, sigmas, robust=loops, cauchy_scale=2.0)
    f32 = np.float32
    r32 = optimize_pose_graph(
        start.astype(f32),
        edges,
        meas.astype(f32),
        sigmas.astype(f32),
        robust=loops,
        cauchy_scale=2.0,
    )
    assert r32.poses.dtype == jnp.float32 and r32.cost.dtype == jnp.float32
    check_result(r32, start.astype(f32))
    assert int(r32.n_iters) < 50  # it stops by itself below float64's tolerance
    assert pose_error(r32.poses, r64.poses).max() < 1e-3
    np.testing.assert_allclose(float(r32.cost), float(r64.cost), rtol=1e-4)


def test_max_iters_zero_and_nan_ends_loop():
    _, edges, meas, sigmas, _, start = make_graph(0)
    res = optimize_pose_graph(start, edges, meas, sigmas, max_iters=0)
    assert int(res.n_iters) == 0 and float(res.cost) == float(res.cost0) > 0
    np.testing.assert_allclose(np.asarray(res.poses), start, atol=1e-12)
    # a NaN measurement (past the checks, straight into the compiled loop) ends it at once
    meas[3, 1] = np.nan
    out = _solve(
        jnp.asarray(start),
        jnp.asarray(edges, jnp.int32),
        jnp.asarray(meas),
        jnp.eye(3) / jnp.asarray(sigmas)[:, :, None],
        jnp.zeros(len(edges), bool),
        jnp.asarray(1.0, jnp.float64),
        jnp.asarray(0, jnp.int32),
        jnp.asarray(50, jnp.int32),
        jnp.asarray(1e-9, jnp.float64),
    )
    assert int(out.n_iters) == 0 and np.isnan(float(out.cost))


def _bad(kind):
    _, edges, meas, sigmas, _, start = make_graph(0)
    kwargs = {}
    if kind == "poses0_shape":
        start = start[:, :2]
    elif kind == "poses0_nan":
        start[5, 2] = np.nan
    elif kind == "poses0_empty":
        start = np.zeros((0, 3))
    elif kind == "edges_shape":
        edges = edges[:, :1]
    elif kind == "edges_float":
        edges = edges.astype(float)
    elif kind == "edges_range":
        edges[4, 1] = N
    elif kind == "edges_negative":
        edges[4, 0] = -1
    elif kind == "edges_self":
        edges[7] = (3, 3)
    elif kind == "edges_empty":
        edges, meas, sigmas = edges[:0], meas[:0], sigmas[:0]
    elif kind == "measurements_shape":
        meas = meas[:-1]
    elif kind == "measurements_inf":
        meas[0, 0] = np.inf
    elif kind == "sigmas_zero":
        sigmas[2, 2] = 0.0
    elif kind == "sigmas_negative":
        sigmas[2, 0] = -0.1
    elif kind == "sigmas_nan":
        sigmas[2, 1] = np.nan
    elif kind == "sigmas_and_sqrt":
        kwargs["sqrt_information"] = np.eye(3) / sigmas[:, :, None]
    elif kind == "sigmas_none":
        sigmas = None
    elif kind == "sqrt_information_shape":
        sigmas = None
        kwargs["sqrt_information"] = np.zeros((len(edges), 3))
    elif kind == "sqrt_information_nan":
        w = np.eye(3) / sigmas[:, :, None]
        w[3, 0, 1] = np.nan
        sigmas = None
        kwargs["sqrt_information"] = w
    elif kind == "robust_shape":
        kwargs["robust"] = np.ones(len(edges) - 1, bool)
    elif kind == "robust_dtype":
        kwargs["robust"] = np.ones(len(edges))
    elif kind == "cauchy_scale":
        kwargs["cauchy_scale"] = 0.0
    elif kind == "fixed_range":
        kwargs["fixed"] = N
    elif kind == "fixed_negative":
        kwargs["fixed"] = -1
    elif kind == "fixed_float":
        kwargs["fixed"] = 1.5
    elif kind == "max_iters":
        kwargs["max_iters"] = -1
    elif kind == "tol":
        kwargs["tol"] = float("nan")
    return (start, edges, meas, sigmas), kwargs


@pytest.mark.parametrize(
    "kind",
    [
        "poses0_shape", "poses0_nan", "poses0_empty", "edges_shape", "edges_float", "edges_range",
        "edges_negative", "edges_self", "edges_empty", "measurements_shape", "measurements_inf",
        "sigmas_zero", "sigmas_negative", "sigmas_nan", "sigmas_and_sqrt", "sigmas_none",
        "sqrt_information_shape", "sqrt_information_nan", "robust_shape", "robust_dtype",
        "cauchy_scale", "fixed_range", "fixed_negative", "fixed_float", "max_iters", "tol",
    ],
)  # fmt: skip
def test_bad_input(kind):
    args, kwargs = _bad(kind)
    name = kind.split("_")[0] if not kind.startswith("cauchy") else "cauchy_scale"
    name = "max_iters" if kind == "max_iters" else name
    name = "sqrt_information" if kind.startswith("sqrt_information") else name
    with pytest.raises(ValueError, match=f"^{name}:"):
        optimize_pose_graph(*args, **kwargs)
