"""``lidarjax.testing``: finite differences against closed forms (pytrees, matrices, Lie
groups), the gradient checker passing on correct gradients and raising on wrong or NaN
ones (float64 and float32), and the smoothness statement of the smooth scan objective
(:class:`~lidarjax.localization.refine.FieldScan` on a
:class:`~lidarjax.maps.SmoothDecayRateField`): the check passes away from the cell-centre
lattice and the one-sided derivatives jump by the predicted amount on it."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from lidarjax import maps
from lidarjax.localization.refine import FieldScan, SmoothDecayRateField
from lidarjax.raytrace import GridSpec
from lidarjax.testing import (
    GradientReport,
    check_gradients,
    default_eps,
    default_tolerances,
    finite_difference,
    manifold_finite_difference,
    manifold_jacobian,
    tree_allclose,
)

# --------------------------------------------------------------------------------------
# finite differences against closed forms (float64)


def test_finite_difference_of_a_polynomial_and_sin_in_a_pytree():
    x = {"a": jnp.asarray([0.3, -1.7, 2.5]), "b": jnp.asarray(0.8)}

    def f(t):
        a, b = t["a"], t["b"]
        return {"p": a**3 - 2.0 * a**2 + 0.5 * a * b, "s": jnp.sin(a).sum() * b**2}

    fd = finite_difference(f, x)
    a, b = np.asarray(x["a"]), float(x["b"])
    want = {
        "p": {"a": np.diag(3 * a**2 - 4 * a + 0.5 * b), "b": 0.5 * a},
        "s": {"a": np.cos(a) * b**2, "b": 2 * b * np.sin(a).sum()},
    }
    assert jax.tree.structure(fd) == jax.tree.structure(jax.jacfwd(f)(x))
    for k in ("p", "s"):
        for i in ("a", "b"):
            assert fd[k][i].shape == jax.jacfwd(f)(x)[k][i].shape
            np.testing.assert_allclose(fd[k][i], want[k][i], rtol=1e-8, atol=1e-8)


def test_finite_difference_of_a_matrix_function():
    rng = np.random.default_rng(0)
    a = jnp.asarray(rng.normal(size=(3, 3)) + 3 * np.eye(3))
    inv = np.linalg.inv(np.asarray(a))
    fd = finite_difference(jnp.linalg.inv, a)  # [3 3 3 3]: d inv_ij / d a_kl
    want = -np.einsum("ik,lj->ijkl", inv, inv)  # d(A^-1) = -A^-1 dA A^-1
    assert fd.shape == (3, 3, 3, 3)
    np.testing.assert_allclose(fd, want, rtol=1e-8, atol=1e-8)
    sq = finite_difference(lambda m: m @ m, a)  # d(A A) = dA A + A dA
    eye = np.eye(3)
    want_sq = np.einsum("ik,lj->ijkl", eye, a) + np.einsum("ik,jl->ijkl", a, eye)
    np.testing.assert_allclose(sq, want_sq, rtol=1e-8, atol=1e-8)


def test_step_sizes_and_one_sided_differences():
    assert default_eps(jnp.float64) == 1e-6 and default_eps(jnp.float32) == 1e-3
    x = jnp.asarray([1e4, 0.5])
    # relative step: at 1e4 a plain 1e-6 step would lose 4 more digits to round-off
    fd = finite_difference(lambda t: t**2, x)
    np.testing.assert_allclose(np.diag(fd), 2 * np.asarray(x), rtol=1e-9)
    for method in ("forward", "backward"):
        one = finite_difference(jnp.exp, jnp.asarray([0.3]), method=method)
        np.testing.assert_allclose(one[0, 0], np.exp(0.3), rtol=1e-5)  # O(h)
        assert abs(float(one[0, 0]) - np.exp(0.3)) > 1e-9  # ... but not O(h^2)
    kink = jnp.asarray([0.0])
    assert float(finite_difference(jnp.abs, kink, method="forward")[0, 0]) == 1.0
    assert float(finite_difference(jnp.abs, kink, method="backward")[0, 0]) == -1.0
    assert float(finite_difference(jnp.abs, kink)[0, 0]) == 0.0  # neither side


def test_bad_arguments_raise_naming_them():
    with pytest.raises(TypeError, match="f must be callable"):
        finite_difference(3.0, jnp.zeros(2))
    with pytest.raises(TypeError, match="f must be callable"):
        check_gradients("sin", jnp.zeros(2))
    with pytest.raises(TypeError, match=r"x.*int"):
        finite_difference(jnp.sin, jnp.arange(3))
    with pytest.raises(TypeError, match=r"x\['b'\].*int"):
        check_gradients(lambda t: t["a"], {"a": 1.0, "b": 2})
    with pytest.raises(TypeError, match="x must have real floating-point leaves"):
        check_gradients(jnp.sin, np.array([True]))
    with pytest.raises(ValueError, match="x must be finite"):
        finite_difference(jnp.sin, jnp.asarray([0.0, np.nan]))
    with pytest.raises(ValueError, match="method"):
        finite_difference(jnp.sin, jnp.zeros(2), method="complex-step")
    with pytest.raises(ValueError, match="eps"):
        finite_difference(jnp.sin, jnp.zeros(2), eps=0.0)
    with pytest.raises(ValueError, match="modes"):
        check_gradients(jnp.sin, jnp.zeros(2), modes=("fwd", "bwd"))
    with pytest.raises(ValueError, match="order"):
        check_gradients(jnp.sin, jnp.zeros(2), order=0)
    with pytest.raises(TypeError, match="pose must be a jaxlie group element"):
        manifold_finite_difference(jnp.sin, jnp.zeros(3))


def test_tree_allclose():
    a = {"x": jnp.asarray([1.0, 2.0]), "y": (jnp.asarray(3.0),)}
    assert tree_allclose(a, jax.tree.map(lambda t: t * (1 + 1e-11), a))
    assert not tree_allclose(a, jax.tree.map(lambda t: t * (1 + 1e-7), a))
    assert tree_allclose(a, jax.tree.map(lambda t: t * (1 + 1e-7), a), rtol=1e-6, atol=0.0)
    assert not tree_allclose(a, {"x": a["x"], "y": [a["y"][0]]})  # structure differs
    assert not tree_allclose(jnp.asarray(np.nan), jnp.asarray(np.nan))


# --------------------------------------------------------------------------------------
# Lie groups: right perturbation pose @ exp(delta), against closed forms


def _skew(p):
    return np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])


def test_manifold_derivatives_on_se2_and_se3_match_closed_forms():
    p2, p3 = np.array([0.7, -0.4]), np.array([0.3, -0.5, 0.9])
    se2 = jaxlie.SE2.from_xy_theta(1.0, -2.0, 0.6)
    r2 = np.asarray(se2.rotation().as_matrix())
    # d/d(v, omega) of (T exp(delta)).apply(p) = [R, R J p] with J the 90-degree rotation
    want2 = np.column_stack([r2, r2 @ np.array([-p2[1], p2[0]])])
    se3 = jaxlie.SE3.exp(jnp.asarray([0.1, 0.2, -0.3, 0.4, -0.5, 0.6]))
    r3 = np.asarray(se3.rotation().as_matrix())
    want3 = np.column_stack([r3, -r3 @ _skew(p3)])  # [R, -R [p]x]
    so3 = se3.rotation()
    for pose, p, want in ((se2, p2, want2), (se3, p3, want3), (so3, p3, want3[:, 3:])):

        def f(t, p=p):
            return t.apply(jnp.asarray(p))

        fd = manifold_finite_difference(f, pose)
        assert fd.shape == (p.size, pose.tangent_dim)
        np.testing.assert_allclose(fd, want, rtol=1e-8, atol=1e-8)
        np.testing.assert_allclose(manifold_jacobian(f, pose), want, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(manifold_jacobian(f, pose, mode="rev"), want, atol=1e-12)
    # translation(): d/dv = R, d/domega = 0
    fd = manifold_finite_difference(lambda t: t.translation(), se2)
    np.testing.assert_allclose(fd, np.column_stack([r2, np.zeros(2)]), atol=1e-8)
    so2 = jaxlie.SO2.from_radians(0.4)
    fd = manifold_finite_difference(lambda t: t.as_radians(), so2)
    np.testing.assert_allclose(fd, [1.0], rtol=1e-9)


def test_manifold_derivative_of_a_batched_pose():
    poses = jaxlie.SE2.from_xy_theta(jnp.asarray([0.0, 1.0]), jnp.zeros(2), jnp.asarray([0.3, 1.2]))
    fd = manifold_finite_difference(lambda t: t.translation(), poses)
    ad = manifold_jacobian(lambda t: t.translation(), poses)
    assert fd.shape == ad.shape == (2, 2, 2, 3)  # [*out, *batch, tangent]
    np.testing.assert_allclose(fd, ad, atol=1e-8)
    np.testing.assert_allclose(fd[0, :, 1], 0.0)  # poses do not interact


# --------------------------------------------------------------------------------------
# the checker


def test_check_gradients_passes_on_correct_gradients():
    x = {"a": jnp.asarray([0.3, -1.2, 0.8]), "m": jnp.asarray([[2.0, 0.3], [0.1, 1.5]])}

    def f(t):
        return {
            "u": jnp.sin(t["a"]) * t["a"][::-1],
            "v": jnp.linalg.inv(t["m"]) @ t["a"][:2],
            "w": jnp.sum(t["m"] ** 3),
        }

    rep = check_gradients(f, x, order=2)
    assert isinstance(rep, GradientReport) and not rep.manifold and rep.dtype == "float64"
    assert rep.n_inputs == 7 and rep.n_skipped == 0
    names = [c.name for c in rep.comparisons]
    assert names[:3] == ["fwd vs rev", "fwd vs fd", "rev vs fd"] and len(names) == 6
    assert rep["fwd vs rev"].max_abs_error < 1e-12
    assert rep["fwd vs fd"].max_rel_error < 1e-6
    assert rep["order 2: rev vs fd"].max_abs_error < 1e-6
    assert "gradient check passed" in str(rep)
    # one mode only, op by op; a jaxlie pose is checked in its tangent space
    rep = check_gradients(f, x, modes=("rev",), jit=False)
    assert [c.name for c in rep.comparisons] == ["rev vs fd"]
    pose = jaxlie.SE3.exp(jnp.asarray([0.1, 0.2, -0.3, 0.4, -0.5, 0.6]))
    rep = check_gradients(lambda t: t.apply(jnp.asarray([1.0, 2.0, 3.0])), pose)
    assert rep.manifold and rep.n_inputs == 6


def _scaled_sin(scale):
    @jax.custom_jvp
    def g(x):
        return jnp.sin(x)

    @g.defjvp
    def _jvp(primals, tangents):
        (x,), (t,) = primals, tangents
        return jnp.sin(x), scale * jnp.cos(x) * t

    return g


def test_check_gradients_raises_on_a_wrong_custom_jvp():
    wrong = _scaled_sin(1.1)  # derivative off by 10 %
    x = jnp.asarray([0.3, 0.5])
    check_gradients(_scaled_sin(1.0), x)
    with pytest.raises(AssertionError, match="fwd and fd disagree") as err:
        check_gradients(wrong, x)
    msg = str(err.value)
    assert "max rel error 0.1" in msg and "output index (0,), input index (0,)" in msg
    # the message names the offending leaf of a pytree
    with pytest.raises(AssertionError, match=r"output f\(x\)\['bad'\], input x\['b'\]"):
        check_gradients(lambda t: {"ok": jnp.sin(t["a"]), "bad": wrong(t["b"])}, {"a": x, "b": x})
    with pytest.raises(AssertionError, match="rev and fd disagree"):
        check_gradients(wrong, x, modes=("rev",))


def test_check_gradients_raises_on_a_nan_gradient_where_f_is_finite():
    def f(x):  # the untaken sqrt branch at x < 0 poisons reverse mode: 0 * nan
        return jnp.where(x > 0, jnp.sqrt(x), 0.0)

    x = jnp.asarray([-1.0, 2.0])
    assert np.all(np.isfinite(np.asarray(f(x))))
    assert np.isnan(np.asarray(jax.jacrev(f)(x))[0, 0])
    with pytest.raises(AssertionError, match="jacrev is not finite where f is finite"):
        check_gradients(f, x)
    check_gradients(f, x, modes=("fwd",))  # forward mode selects the zero tangent


def test_check_gradients_skips_outputs_where_f_is_not_finite():
    def f(x):  # -inf in the first entry (its derivative is finite: 0), finite elsewhere
        return jnp.where(jnp.arange(3) == 0, -jnp.inf, jnp.sin(x))

    rep = check_gradients(f, jnp.asarray([0.1, 0.2, 0.3]))
    assert rep.n_skipped == 1 and rep["fwd vs fd"].n_compared == 6


def test_float32_tolerances():
    assert default_tolerances(jnp.float32) == {"fd": (1e-2, 1e-3), "ad": (1e-5, 1e-6)}
    assert default_tolerances(jnp.float64) == {"fd": (1e-6, 1e-8), "ad": (1e-10, 1e-12)}
    rng = np.random.default_rng(1)
    x = jnp.asarray(rng.normal(size=4), jnp.float32)
    for f in (
        lambda t: jnp.sin(t) * t[::-1],
        lambda t: t**3 - 2 * t**2 + 0.5 * t,
        lambda t: jnp.linalg.inv(t.reshape(2, 2) + 3 * jnp.eye(2, dtype=t.dtype)).reshape(-1),
        lambda t: 100.0 * jnp.sum(jnp.exp(t)),
    ):
        rep = check_gradients(f, x)
        assert rep.dtype == "float32"
        assert rep["fwd vs fd"].max_rel_error < 1e-2
    with pytest.raises(AssertionError, match="rtol=0.01, atol=0.001"):
        check_gradients(_scaled_sin(1.1), x)  # a 10 % error is still caught in float32
    fd32 = finite_difference(jnp.sin, x)
    assert fd32.dtype == jnp.float32


# --------------------------------------------------------------------------------------
# where the smooth scan objective is smooth: FieldScan on a SmoothDecayRateField

ORIGIN, RES, K, FLOOR = np.array([-1.5, -1.5]), 0.25, 16, 1e-3


def _smooth_field():
    rates = np.random.default_rng(0).uniform(0.5, 2.0, (12, 12))
    spec = GridSpec(ORIGIN, RES, rates.shape)
    m = maps.DecayRateMap(spec, jnp.asarray(rates), jnp.asarray(0.3))
    return rates, SmoothDecayRateField(m, n_nodes=K)


def _points(xyt, az, ranges):
    """Midpoint nodes ``[b K 2]`` and end points ``[b 2]`` of HIT beams (all inside the
    grid box, so the integrated chord is ``[0, range]``)."""
    x, y, th = xyt
    d = np.stack([np.cos(th + az), np.sin(th + az)], -1)
    t = ranges[:, None] * (np.arange(K) + 0.5) / K
    return np.array([x, y]) + t[..., None] * d[:, None, :], np.array([x, y]) + ranges[:, None] * d


def _lattice(p):
    """Coordinates in the cell-centre lattice: integers on the lines x (or y) = origin +
    (i + 1/2) resolution, where the bilinear interpolant's gradient jumps."""
    return (p - ORIGIN) / RES - 0.5


def _line_distance(p):
    u = _lattice(p)
    return RES * np.abs(u - np.round(u))


def test_smooth_scan_objective_passes_the_check_away_from_the_lattice():
    """At a pose where no end point and no midpoint node of any beam is within 2 mm of a
    cell-centre line (and every ray is far above ``ray_floor``), the objective is smooth:
    ``check_gradients`` passes at float64 tolerances, in the tangent space of SE(2)."""
    _, field = _smooth_field()
    az = np.array([-1.4, -1.0, -0.3, 0.4, 1.1, 1.5])
    ranges = np.array([0.8, 0.9, 1.1, 0.7, 1.0, 1.2])
    scan = FieldScan(field, az, ranges, 0.0, 3.0, rate_floor=FLOOR)
    rng = np.random.default_rng(5)
    while True:  # the first random pose with every point off the lines
        xyt = np.array([*rng.uniform(-0.3, 0.3, 2), rng.uniform(-np.pi, np.pi)])
        nodes, ends = _points(xyt, az, ranges)
        if min(_line_distance(nodes).min(), _line_distance(ends).min()) >= 2e-3:
            break
    pose = jaxlie.SE2.from_xy_theta(*xyt)
    ll = jax.jit(lambda p: scan.ray_log_likelihoods(p))(pose)
    assert np.all(np.asarray(ll) > scan.ray_floor + 1)
    rep = check_gradients(jax.jit(lambda p: scan(p)), pose)
    assert rep.manifold and rep["fwd vs fd"].max_rel_error < 1e-6


@pytest.mark.parametrize("on_line", ["end point", "node 5"])
def test_smooth_scan_objective_has_a_kink_where_a_point_crosses_a_lattice_line(on_line):
    """One beam whose end point (or one midpoint node) lies on the cell-centre line
    ``x = origin_x + 6.5 res``, every other point 2 mm or more from every line: the right
    and left derivatives in each tangent direction differ by the closed-form jump of the
    bilinear interpolant's slope (``d/dx lambda`` right minus left of the line), times
    ``|d x_point / d delta|``, over ``lambda + rate_floor`` for the end point's
    ``log lambda`` and times ``-range / n_nodes`` for a node's term of ``-S``; autodiff
    returns one of the two one-sided derivatives and ``check_gradients`` fails there."""
    rates, field = _smooth_field()
    r, th = 1.0, 0.3
    az, ranges = np.array([0.0]), np.array([r])
    scan = FieldScan(field, az, ranges, 0.0, 3.0, rate_floor=FLOOR)
    f = jax.jit(lambda p: scan(p))
    k = K if on_line == "end point" else 5
    t_on = r if on_line == "end point" else r * (k + 0.5) / K
    x = ORIGIN[0] + 6.5 * RES - t_on * np.cos(th)  # the point's x on the line
    for y in np.linspace(-0.5, 0.5, 101):  # the first y with every other point off lines
        nodes, ends = _points((x, y, th), az, ranges)
        pts = np.concatenate([nodes[0], ends])
        dist = _line_distance(pts)
        dist[k, 0] = np.inf
        if dist.min() >= 2e-3:
            break
    assert dist.min() >= 2e-3 and _line_distance(pts[k])[0] < 1e-12
    # closed form: slopes of the bilinear interpolant right and left of the line
    u = _lattice(pts[k])
    i, j = int(round(u[0])), int(np.floor(u[1]))
    fy = u[1] - j
    col = (1 - fy) * rates[:, j] + fy * rates[:, j + 1]  # the interpolant along x on the line's y
    slope_right, slope_left = (col[i + 1] - col[i]) / RES, (col[i] - col[i - 1]) / RES
    lam = col[i]
    # x velocity of the point under delta = (v_x, v_y, omega) (body frame, right perturbation)
    dx = np.array([np.cos(th), -np.sin(th), -t_on * np.sin(th)])
    jump = (slope_right - slope_left) * np.abs(dx)
    jump = jump / (lam + FLOOR) if on_line == "end point" else -(r / K) * jump

    pose = jaxlie.SE2.from_xy_theta(x, y, th)
    right = np.asarray(manifold_finite_difference(f, pose, method="forward"))
    left = np.asarray(manifold_finite_difference(f, pose, method="backward"))
    np.testing.assert_allclose(right - left, jump, rtol=1e-4)
    assert np.all(np.abs(jump) > 0.02)
    ad = np.asarray(manifold_jacobian(f, pose))
    one_sided = np.isclose(ad, right, rtol=1e-4) | np.isclose(ad, left, rtol=1e-4)
    assert one_sided.all()
    with pytest.raises(AssertionError, match="disagree"):
        check_gradients(f, pose)
