"""The native optical-depth kernel of SmoothDecayRateField (``csrc/field_integral.cc``)
against its oracles: the pure-JAX midpoint rule (values and derivatives, float64 and
float32), a closed form on a field linear along the ray, and central finite differences;
inside ``jit``, ``vmap`` and forward mode; what it refuses to differentiate; bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lidarjax.maps import DecayRateMap, SmoothDecayRateField
from lidarjax.raytrace import GridSpec, _native

native = pytest.mark.skipif(
    not _native.available(), reason=f"native kernels unavailable: {_native.unavailable_reason()}"
)


def _field(dtype, n_nodes, *, outside=0.25, seed=0, shape=(23, 31), res=0.2):
    rng = np.random.default_rng(seed)
    rates = rng.gamma(0.5, 2.0, size=shape).astype(dtype)
    spec = GridSpec(jnp.asarray([0.3, -0.7], dtype), res, shape)
    m = DecayRateMap(spec, jnp.asarray(rates), jnp.asarray(outside, dtype))
    return SmoothDecayRateField(m, n_nodes=n_nodes)


def _rays(dtype, n=300, seed=1):
    """Rays inside, across and outside the grid box (origin (0.3, -0.7), 4.6 x 6.2 m),
    axis-parallel ones, zero and infinite lengths."""
    rng = np.random.default_rng(seed)
    o = rng.uniform(-4.0, 10.0, size=(n, 2))
    m = min(40, n)
    o[:m] = rng.uniform([0.5, -0.5], [4.7, 5.3], size=(m, 2))  # starting inside
    a = rng.uniform(0.0, 2.0 * np.pi, n)
    d = np.stack([np.cos(a), np.sin(a)], -1)
    d[:4] = [[1, 0], [0, 1], [-1, 0], [0, -1]]
    r = rng.uniform(0.0, 12.0, n)
    r[4:7] = 0.0
    r[7:10] = np.inf
    return tuple(jnp.asarray(x, dtype) for x in (o, d, r))


def _weighted_sum(field):
    """A scalar of every finite ray's depth, with distinct weights per ray."""

    def f(o, d, r):
        finite = jnp.isfinite(r)
        s = field.integral(o, d, jnp.where(finite, r, 1.0))
        return jnp.sum(jnp.where(finite, jnp.sin(jnp.arange(s.shape[0]) + 1.0) * s, 0.0))

    return f


@native
@pytest.mark.parametrize("n_nodes", [1, 7, 64, 100, 512])
def test_native_integral_matches_jax_float64(n_nodes):
    fj = _field(np.float64, n_nodes)
    fn = fj.with_backend("native")
    assert fn.backend == "native" and fj.backend == "jax"
    o, d, r = _rays(np.float64)
    a, b = fj.integral(o, d, r), jax.jit(lambda f, *x: f.integral(*x))(fn, o, d, r)
    # infinite rays leaving the box have infinite depth (outside rate > 0) on both paths
    np.testing.assert_array_equal(np.isfinite(a), np.isfinite(b))
    assert (~np.isfinite(a)).sum() >= 1 and (np.asarray(a)[np.isfinite(a)] > 0).sum() > 200
    np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12)
    ga = jax.grad(_weighted_sum(fj), (0, 1, 2))(o, d, r)
    gb = jax.jit(jax.grad(_weighted_sum(fn), (0, 1, 2)))(o, d, r)
    for x, y in zip(ga, gb):
        assert np.isfinite(y).all()
        np.testing.assert_allclose(y, x, rtol=1e-10, atol=1e-10)


@native
@pytest.mark.parametrize("n_nodes", [7, 64, 512])
def test_native_integral_matches_jax_float32(n_nodes):
    """float32: the kernel sums in double (the AVX2 path in float for at most 8 terms),
    the JAX path in float32; they agree to the JAX path's rounding."""
    fj = _field(np.float32, n_nodes)
    fn = fj.with_backend("native")
    o, d, r = _rays(np.float32)
    a, b = np.asarray(fj.integral(o, d, r)), np.asarray(fn.integral(o, d, r))
    assert b.dtype == a.dtype
    fin = np.isfinite(a)
    np.testing.assert_array_equal(fin, np.isfinite(b))
    np.testing.assert_allclose(b[fin], a[fin], rtol=2e-5, atol=2e-5)
    ga = jax.grad(_weighted_sum(fj), (0, 1))(o, d, r)
    gb = jax.grad(_weighted_sum(fn), (0, 1))(o, d, r)
    for x, y in zip(ga, gb):
        scale = float(np.abs(x).max())
        np.testing.assert_allclose(y, x, atol=2e-5 * scale)


@native
def test_native_integral_closed_form_on_a_linear_field():
    """Rates linear in x (``a + b * i`` in cell i): the interpolant is linear along a ray
    between the outermost cell centres, so the midpoint rule is exact:
    ``S = L (lambda(o) + b' (d_x L / 2))`` with ``b' = b / res`` per m, and its derivatives
    follow by hand."""
    res, a, b = 0.1, 0.5, 0.02
    nx, ny = 60, 40
    rates = np.broadcast_to(a + b * np.arange(nx)[:, None], (nx, ny)).astype(np.float64)
    spec = GridSpec(jnp.zeros(2, jnp.float64), res, (nx, ny))
    field = SmoothDecayRateField(
        DecayRateMap(spec, jnp.asarray(rates), jnp.asarray(0.0)), n_nodes=33, backend="native"
    )
    rng = np.random.default_rng(3)
    n = 50
    o = rng.uniform([1.0, 1.0], [2.0, 1.5], size=(n, 2))
    ang = rng.uniform(-0.6, 0.6, n)
    d = np.stack([np.cos(ang), np.sin(ang)], -1)
    L = rng.uniform(0.1, 2.5, n)  # ends inside the centres' box (x < 5.95, 0.05 < y < 3.95)
    assert np.all(o + L[:, None] * d < [5.95, 3.95]) and np.all(o + L[:, None] * d > 0.05)
    slope = b / res  # per m along x

    def lam(x):  # the field at x (m): cell i's centre is at (i + 1/2) res
        return a + slope * (x - 0.5 * res)

    want = L * (lam(o[:, 0]) + slope * d[:, 0] * L / 2)
    got = field.integral(jnp.asarray(o), jnp.asarray(d), jnp.asarray(L))
    np.testing.assert_allclose(got, want, rtol=1e-12)
    g_o, g_d, g_L = jax.grad(lambda o, d, L: jnp.sum(field.integral(o, d, L)), (0, 1, 2))(
        jnp.asarray(o), jnp.asarray(d), jnp.asarray(L)
    )
    np.testing.assert_allclose(g_o[:, 0], slope * L, rtol=1e-12)
    np.testing.assert_allclose(g_o[:, 1], 0.0, atol=1e-12)
    np.testing.assert_allclose(g_d[:, 0], slope * L**2 / 2, rtol=1e-12)
    np.testing.assert_allclose(g_d[:, 1], 0.0, atol=1e-12)
    np.testing.assert_allclose(g_L, lam(o[:, 0]) + slope * d[:, 0] * L, rtol=1e-12)


@native
def test_native_gradient_matches_finite_differences():
    """Central differences with a step (1e-7 m) far below the nodes' distance to the
    lattice lines, so no kink is crossed (see SmoothDecayRateField's docstring)."""
    field = _field(np.float64, 64, seed=4).with_backend("native")
    o, d, r = _rays(np.float64, n=40, seed=5)
    # lengths away from 0 (a negative length is invalid input: the kernel rejects the
    # negative chord it gives)
    r = jnp.where(jnp.isfinite(r), jnp.maximum(r, 0.5), 3.0)
    f = _weighted_sum(field)
    grads = jax.grad(f, (0, 1, 2))(o, d, r)
    h = 1e-7
    rng = np.random.default_rng(6)
    for arg, g in enumerate(grads):
        for _ in range(6):
            v = rng.normal(size=g.shape)
            args = [o, d, r]
            plus = list(args)
            minus = list(args)
            plus[arg] = args[arg] + h * v
            minus[arg] = args[arg] - h * v
            fd = (f(*plus) - f(*minus)) / (2 * h)
            np.testing.assert_allclose(float(jnp.sum(g * v)), float(fd), rtol=1e-5, atol=1e-6)


@native
def test_native_forward_mode_and_vmap():
    fj = _field(np.float64, 16)
    fn = fj.with_backend("native")
    o, d, r = _rays(np.float64, n=30)
    r = jnp.where(jnp.isfinite(r), r, 2.0)
    t = jnp.asarray(np.random.default_rng(0).normal(size=o.shape))
    _, ja = jax.jvp(lambda o: fj.integral(o, d, r), (o,), (t,))
    _, jb = jax.jvp(lambda o: fn.integral(o, d, r), (o,), (t,))
    np.testing.assert_allclose(jb, ja, rtol=1e-10, atol=1e-10)
    # vmap over a batch of ray sets (the kernel runs once per element)
    shift = jnp.asarray([[0.0, 0.0], [0.3, -0.2], [1.0, 0.5]])
    va = jax.vmap(lambda s: fj.integral(o + s, d, r))(shift)
    vb = jax.jit(jax.vmap(lambda s: fn.integral(o + s, d, r)))(shift)
    np.testing.assert_allclose(vb, va, rtol=1e-12, atol=1e-12)


@native
def test_native_second_derivatives_match_jax():
    """Second order (the SLAM front end's match information is a Hessian in the pose):
    the Hessian kernel against JAX's Hessian of the JAX path, over every ray parameter of
    a batch and in a sensor pose, float64."""
    import jaxlie

    from lidarjax.rays import from_scan

    fj = _field(np.float64, 64, seed=7)
    fn = fj.with_backend("native")
    o, d, r = _rays(np.float64, n=60, seed=8)
    r = jnp.where(jnp.isfinite(r), jnp.maximum(r, 0.5), 3.0)
    n = o.shape[0]
    w = jnp.sin(jnp.arange(n) + 1.0)

    def flat(field):
        def f(x):
            return jnp.sum(
                w
                * field.integral(
                    x[: 2 * n].reshape(n, 2), x[2 * n : 4 * n].reshape(n, 2), x[4 * n :]
                )
            )

        return f

    x = jnp.concatenate([o.ravel(), d.ravel(), r])
    hj = jax.hessian(flat(fj))(x)
    hn = jax.jit(jax.hessian(flat(fn)))(x)
    scale = float(jnp.abs(hj).max())
    assert scale > 10 and np.isfinite(hn).all()
    np.testing.assert_allclose(hn, hj, atol=1e-11 * scale)
    # in a sensor pose (the tangent space of SE(2)), as the front end's information
    az = jnp.linspace(-1.5, 1.5, 90)
    rr = jnp.asarray(np.random.default_rng(9).uniform(1.0, 6.0, 90))

    def in_pose(field):
        def f(delta):
            p = jaxlie.manifold.rplus(jaxlie.SE2.from_xy_theta(2.0, 1.5, 0.3), delta)
            rays = from_scan(p, az, rr, 0.0, 20.0)
            return jnp.sum(field.integral(rays.origins, rays.directions, rays.ranges))

        return f

    pj = jax.hessian(in_pose(fj))(jnp.zeros(3))
    pn = jax.hessian(in_pose(fn))(jnp.zeros(3))
    np.testing.assert_allclose(pn, pj, rtol=1e-10, atol=1e-10 * float(jnp.abs(pj).max()))


@native
def test_native_refuses_what_it_cannot_differentiate():
    """Derivatives in the rates are an error naming them, and a third derivative is an
    error too (never a silent 0)."""
    fn = _field(np.float64, 16).with_backend("native")
    o, d, r = _rays(np.float64, n=10)
    r = jnp.where(jnp.isfinite(r), r, 2.0)

    def in_rates(rates):
        g = SmoothDecayRateField(
            DecayRateMap(fn.grid.spec, rates, fn.outside_rate), backend="native"
        )
        return jnp.sum(g.integral(o, d, r))

    with pytest.raises(NotImplementedError, match="rates"):
        jax.grad(in_rates)(fn.rates)
    with pytest.raises(Exception, match="cannot be differentiated"):
        jax.jacfwd(jax.hessian(lambda o: jnp.sum(fn.integral(o, d, r))))(o)
    # the JAX field of the same grid differentiates in the rates
    g = jax.grad(lambda q: jnp.sum(fn.with_backend("jax").with_parameters(q).integral(o, d, r)))(
        fn.parameters()
    )
    assert np.isfinite(g).all() and np.abs(g).sum() > 0


@native
def test_native_with_parameters_and_nodes_keep_the_backend():
    fn = _field(np.float64, 16).with_backend("native")
    assert fn.with_nodes(32).backend == "native" and fn.with_nodes(32).n_nodes == 32
    assert fn.with_parameters(fn.parameters()).backend == "native"
    assert fn.with_backend("jax").backend == "jax"


@native
@pytest.mark.parametrize("bad", ["origins", "directions", "t0", "chord", "negative"])
@pytest.mark.parametrize("kernel", ["integral", "hessian"])
def test_native_kernel_rejects_bad_rays(bad, kernel):
    rates = jnp.ones((10, 12))
    o = np.array([[0.2, 0.3], [0.4, 0.5]])
    d = np.array([[1.0, 0.0], [0.6, 0.8]])
    t0 = np.array([0.0, 0.1])
    c = np.array([0.5, 0.4])
    if bad == "origins":
        o[1, 0] = np.nan
    elif bad == "directions":
        d[0, 1] = np.inf
    elif bad == "t0":
        t0[1] = np.nan
    elif bad == "chord":
        c[0] = np.inf
    else:
        c[1] = -0.1
    match = "negative t0 or chord at ray 1" if bad == "negative" else f"non-finite {bad}"
    with pytest.raises(Exception, match=match):
        fn = _native.chord_integral if kernel == "integral" else _native.chord_hessian
        jax.block_until_ready(fn(rates, [0.0, 0.0], 0.1, o, d, t0, c, 8))


@native
@pytest.mark.parametrize("jit", [False, True])
def test_native_nan_rate_on_a_path_is_an_error_off_it_no_effect(jit):
    """A NaN rate a ray's nodes read is an error naming the ray; one no ray reads changes
    nothing (as on the JAX path, where it stays out of every sum)."""
    # (a DecayRateMap rejects NaN rates itself: the kernel is called directly here)
    rates = np.ones((10, 12))
    rates[8, 10] = np.nan  # far corner
    o = jnp.asarray([[0.1, 0.1], [0.1, 0.15]])
    d = jnp.asarray([[1.0, 0.0], [1.0, 0.0]])
    t0 = jnp.zeros(2)
    c = jnp.asarray([0.3, 0.3])

    def call(rates):
        return _native.chord_integral(rates, jnp.zeros(2), 0.1, o, d, t0, c, 16)[0]

    call = jax.jit(call) if jit else call
    np.testing.assert_allclose(call(jnp.asarray(rates)), 0.3, rtol=1e-12)
    rates[1, 1] = np.nan  # on both rays' patches
    with pytest.raises(Exception, match="non-finite rates on the path of ray 0"):
        jax.block_until_ready(call(jnp.asarray(rates)))


@pytest.mark.parametrize("backend", ["jax", "native"])
def test_integral_rejects_batched_rays(backend):
    """A scan batch ``[scans beams 2]`` is not a ray list: an error naming the argument on
    both paths (the kernel would otherwise see a shape it cannot read)."""
    if backend == "native" and not _native.available():
        # without the kernels, asking for them is an error saying why (no silent fallback)
        with pytest.raises(RuntimeError, match="backend='native'"):
            _field(np.float64, 4).with_backend(backend)
        return
    f = _field(np.float64, 4).with_backend(backend)
    o, d, r = _rays(np.float64, n=6)
    with pytest.raises(ValueError, match="origins must be"):
        f.integral(o.reshape(2, 3, 2), d, r)
    with pytest.raises(ValueError, match="lengths"):
        f.integral(o, d, r[:5])


def test_field_backend_argument_is_checked(monkeypatch):
    m = _field(np.float64, 4).grid
    with pytest.raises(ValueError, match="backend"):
        SmoothDecayRateField(m, backend="cuda")
    monkeypatch.setattr(
        _native, "_state", {"loaded": False, "reason": "test: not built", "warned": True}
    )
    with pytest.raises(RuntimeError, match="test: not built"):
        SmoothDecayRateField(m, backend="native")
    # "auto" falls back to the JAX path
    assert SmoothDecayRateField(m, backend="auto").backend == "jax"


@native
@pytest.mark.skipif(_native.isa() != "avx2", reason="the AVX2 library is not in use here")
@pytest.mark.slow  # two subprocesses compile: runs in make test-slow / CI
def test_native_integral_avx2_and_baseline_agree(tmp_path):
    """The AVX2 float32 path (8 nodes per step, float lane sums flushed every 64 nodes) and
    the baseline's scalar double sums agree to float32 rounding; float64 is scalar in both
    builds and identical."""
    from test_raytrace_native import run_under_isas

    script = """
import sys, jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp, numpy as np
from lidarjax.raytrace import _native
assert _native.isa() == sys.argv[2]
rng = np.random.default_rng(2)
out = {}
for dt in (np.float32, np.float64):
    rates = jnp.asarray(rng.gamma(0.5, 2.0, (300, 280)), dt)
    n = 400
    o = rng.uniform(-2.0, 16.0, (n, 2)); a = rng.uniform(0, 2 * np.pi, n)
    d = np.stack([np.cos(a), np.sin(a)], -1); t0 = rng.uniform(0, 1, n); c = rng.uniform(0, 9, n)
    for k in (5, 512):
        r = _native.chord_integral(rates, [-0.5, -0.3], 0.05, o, d, t0, c, k)
        for i, x in enumerate(r):
            out[f"{np.dtype(dt).name}_{k}_{i}"] = np.asarray(x)
np.savez(sys.argv[1], **out)
"""
    res = run_under_isas(script, tmp_path)
    base, wide = res["baseline"], res["avx2"]
    assert base.keys() == wide.keys() and len(base) == 2 * 2 * 5
    for k in base:
        if k.startswith("float64"):
            np.testing.assert_array_equal(wide[k], base[k], err_msg=k)
        else:
            scale = np.abs(base[k]).max()
            assert scale > 0, k
            np.testing.assert_allclose(wide[k], base[k], atol=2e-6 * scale, err_msg=k)


# --------------------------------------------------------------------------------------
# the native blur of the SLAM front end's window
# --------------------------------------------------------------------------------------


@native
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("sigma", [0.4, 2.0, 6.0])
def test_native_blur_matches_jax(dtype, sigma):
    from lidarjax.maps import blur

    x = jnp.asarray(np.random.default_rng(0).gamma(0.5, 2.0, (57, 43)), dtype)
    a, b = blur(x, sigma), jax.jit(lambda x: _native.blur2d(x, sigma))(x)
    assert b.dtype == a.dtype and b.shape == a.shape
    tol = 1e-14 if dtype == np.float64 else 1e-6
    np.testing.assert_allclose(b, a, rtol=tol, atol=tol * float(jnp.abs(a).max()))
    # an independent reference: the blur of a unit impulse far from the border is the
    # outer product of the 1-D taps, and a constant stays constant (border extended)
    from lidarjax.maps._smoothing import gaussian_kernel_1d

    k = gaussian_kernel_1d(sigma, 3.0)
    h = (k.size - 1) // 2
    imp = np.zeros((2 * h + 9, 2 * h + 11))
    imp[h + 4, h + 5] = 1.0
    got = np.asarray(_native.blur2d(jnp.asarray(imp, dtype), sigma))
    np.testing.assert_allclose(got[4 : 4 + 2 * h + 1, 5 : 5 + 2 * h + 1], np.outer(k, k), atol=tol)
    const = np.asarray(_native.blur2d(jnp.full((9, 7), 0.7, dtype), sigma))
    np.testing.assert_allclose(const, 0.7, rtol=10 * tol)


@native
def test_native_blur_rejects_bad_input():
    with pytest.raises(Exception, match="non-finite values at cell 5"):
        jax.block_until_ready(
            _native.blur2d(jnp.asarray(np.r_[np.ones(5), np.nan, np.ones(6)].reshape(3, 4)), 1.0)
        )
    with pytest.raises(ValueError, match="values"):
        _native.blur2d(jnp.ones((2, 3, 4)), 1.0)
    with pytest.raises(ValueError, match="sigma_cells"):
        _native.blur2d(jnp.ones((3, 4)), 0.0)
