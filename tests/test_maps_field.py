"""The decay-rate field interface: one forward model and one optimistix fit for grid, DCT and
user-defined fields; the grid case checked against Eqs. (7.10), (7.19), (7.21)."""

from __future__ import annotations

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import optimistix as optx
import pytest
from scipy.special import erf

from lidarjax import maps
from lidarjax.localization.refine import FieldScan, refine_pose, refine_scan_pose
from lidarjax.rays import HIT, SUB, SUP, RayBatch, from_scan
from lidarjax.raytrace import GridSpec, accumulate
from lidarjax.sensor_models import decay_rate_log_likelihood
from lidarjax.testing import finite_difference

# --------------------------------------------------------------------------------------
# user-style fields for the tests


class PlaneField(maps.AbstractQuadratureField):
    """``softplus(t0 + t1 (x - cx) + t2 (y - cy))`` on a box: 3 parameters."""

    theta: jax.Array
    lower: jax.Array
    extent: jax.Array

    def rate_in_box(self, points):
        c = self.lower + 0.5 * self.extent
        p = points - c
        return jax.nn.softplus(
            self.theta[0] + p[..., 0] * self.theta[1] + p[..., 1] * self.theta[2]
        )

    def quadrature_nodes(self):
        return 24  # smooth along rays: 24 Gauss-Legendre nodes are exact to ~1e-13


class BumpField(maps.AbstractQuadratureField):
    """``base + sum_k a_k exp(-|x - c_k|^2 / (2 s^2))`` on a box; closed-form line
    integrals (erf)."""

    amps: jax.Array
    centres: jax.Array
    base: jax.Array
    lower: jax.Array
    extent: jax.Array
    sigma: float = eqx.field(static=True, default=0.3)
    n_nodes: int = eqx.field(static=True, default=64)

    def rate_in_box(self, points):
        d2 = jnp.sum((points[..., None, :] - self.centres) ** 2, axis=-1)
        return self.base + jnp.sum(self.amps * jnp.exp(-0.5 * d2 / self.sigma**2), axis=-1)

    def quadrature_nodes(self):
        return self.n_nodes


def bump_integral_np(f: BumpField, o, d, t0, t1):
    """Closed form of ``int_t0^t1 rate(o + t d) dt`` for a BumpField (unit d)."""
    s = f.sigma
    total = float(f.base) * (t1 - t0)
    for a, c in zip(np.asarray(f.amps), np.asarray(f.centres)):
        w = o - c
        tc = -np.dot(w, d)  # closest approach
        dmin2 = np.dot(w, w) - tc**2
        g = a * np.exp(-0.5 * dmin2 / s**2) * s * np.sqrt(np.pi / 2)
        total += g * (erf((t1 - tc) / (np.sqrt(2) * s)) - erf((t0 - tc) / (np.sqrt(2) * s)))
    return total


def random_rays(rng, n, lo, hi, *, r_min=0.1, r_max=2.5, max_range=3.0, sup_range=10.0):
    o = rng.uniform(lo, hi, (n, 2))
    th = rng.uniform(0, 2 * np.pi, n)
    d = np.stack([np.cos(th), np.sin(th)], 1)
    kind = rng.choice([HIT, SUB, SUP], n, p=[0.6, 0.2, 0.2])
    r = np.where(kind == SUB, 0.05, np.where(kind == SUP, sup_range, rng.uniform(r_min, r_max, n)))
    del max_range
    return RayBatch(jnp.asarray(o), jnp.asarray(d), jnp.asarray(r), jnp.asarray(kind), r_min, r_max)


# --------------------------------------------------------------------------------------
# one forward model for every field


@pytest.mark.parametrize("outside_rate", [0.0, 0.7])
@pytest.mark.parametrize("r_max", [2.5, np.inf])
@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_generic_model_equals_grid_decay_rate_model(outside_rate, r_max):
    rng = np.random.default_rng(0)
    rays = random_rays(rng, 300, -0.5, 4.5)
    rays = RayBatch(rays.origins, rays.directions, rays.ranges, rays.kind, 0.1, r_max)
    spec = GridSpec([0.0, 0.0], 0.25, (16, 16))
    m = maps.DecayRateMap(
        spec, jnp.asarray(rng.uniform(0.1, 3, (16, 16))), jnp.asarray(outside_rate)
    )
    a = np.asarray(maps.field_log_likelihood(m, rays, chunk_size=64))
    b = np.asarray(decay_rate_log_likelihood(m, rays))
    np.testing.assert_array_equal(np.isfinite(a), np.isfinite(b))
    fin = np.isfinite(b)
    np.testing.assert_allclose(a[fin], b[fin], rtol=1e-12, atol=1e-12)
    assert not np.any(np.isnan(a))
    if r_max == np.inf and outside_rate > 0:  # SUP rays leave the grid: impossible
        assert np.all(a[np.asarray(rays.kind) == SUP] == -np.inf)


@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_generic_model_equals_dct_model():
    rng = np.random.default_rng(1)
    rays = random_rays(rng, 300, 0.2, 3.8)
    dct = maps.DCTMap(rng.normal(size=(5, 4)) * 0.4, [0.0, 0.0], [4.0, 4.0])
    a = np.asarray(maps.field_log_likelihood(dct, rays, chunk_size=50))
    b = np.asarray(maps.dct_log_likelihood(dct, rays, method="paper"))
    fin = np.isfinite(b)
    np.testing.assert_array_equal(np.isfinite(a), fin)
    np.testing.assert_allclose(a[fin], b[fin], rtol=1e-9, atol=1e-11)
    # the DCT's interface pieces agree with its own functions
    pts = jnp.asarray(rng.uniform(-1, 5, (50, 2)))
    np.testing.assert_array_equal(
        dct.decay_rate(pts), jnp.where(dct.contains(pts), dct.amplitude(pts) ** 2, 0)
    )
    assert dct.with_parameters(dct.parameters() * 2).coeffs is not None
    np.testing.assert_allclose(dct.with_parameters(dct.parameters() * 2).coeffs, 2 * dct.coeffs)


def test_quadrature_field_matches_closed_form_integral():
    rng = np.random.default_rng(2)
    f = BumpField(
        amps=jnp.asarray([2.0, 1.0, 3.0]),
        centres=jnp.asarray([[1.0, 1.0], [2.5, 3.0], [3.0, 1.5]]),
        base=jnp.asarray(0.05),
        lower=jnp.asarray([0.0, 0.0]),
        extent=jnp.asarray([4.0, 4.0]),
        n_nodes=96,
    )
    n = 60
    o = rng.uniform(-1.0, 5.0, (n, 2))
    th = rng.uniform(0, 2 * np.pi, n)
    d = np.stack([np.cos(th), np.sin(th)], 1)
    r = rng.uniform(0.0, 6.0, n)
    r[:5] = np.inf  # integrate to the box exit
    d[5] = [1.0, 0.0]  # axis-parallel
    got = np.asarray(f.integral(jnp.asarray(o), jnp.asarray(d), jnp.asarray(r)))
    want = []
    for k in range(n):  # independent clipping in numpy
        t_lo, t_hi = 0.0, r[k]
        for ax in range(2):
            if d[k, ax] == 0:
                if not (0 <= o[k, ax] <= 4):
                    t_hi = -1.0
                continue
            ta, tb = (0 - o[k, ax]) / d[k, ax], (4 - o[k, ax]) / d[k, ax]
            t_lo, t_hi = max(t_lo, min(ta, tb)), min(t_hi, max(ta, tb))
        want.append(bump_integral_np(f, o[k], d[k], t_lo, t_hi) if t_hi > t_lo else 0.0)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    assert np.sum(np.asarray(want) == 0.0) >= 1  # some rays miss the box
    # the rate is zero outside the box, the user's function inside it
    pts = jnp.asarray([[1.0, 1.0], [-0.1, 1.0], [2.0, 4.2]])
    lam = np.asarray(f.decay_rate(pts))
    assert lam[0] == pytest.approx(float(f.rate_in_box(pts[0]))) and lam[0] > 2.0
    assert lam[1] == 0.0 and lam[2] == 0.0
    # parameters() leaves the box out
    params = f.parameters()
    assert params.lower is None and params.extent is None and params.amps is not None


def test_chunking_does_not_change_values_or_gradients():
    rng = np.random.default_rng(3)
    rays = random_rays(rng, 53, 0.2, 3.8)
    f = PlaneField(theta=jnp.asarray([0.1, 0.3, -0.2]), lower=jnp.zeros(2), extent=jnp.full(2, 4.0))

    @functools.partial(jax.jit, static_argnums=1)
    def total(theta, chunk):
        return jnp.sum(
            maps.field_log_likelihood(
                eqx.tree_at(lambda g: g.theta, f, theta), rays, chunk_size=chunk
            )
        )

    a, ga = jax.value_and_grad(total)(f.theta, 7)
    b, gb = jax.value_and_grad(total)(f.theta, 4096)
    np.testing.assert_allclose(a, b, rtol=1e-12)
    np.testing.assert_allclose(ga, gb, rtol=1e-10, atol=1e-12)
    empty = RayBatch(
        rays.origins[:0], rays.directions[:0], rays.ranges[:0], rays.kind[:0], 0.1, 2.5
    )
    assert maps.field_log_likelihood(f, empty).shape == (0,)


def test_user_field_gradients_four_ways():
    rng = np.random.default_rng(4)
    rays = random_rays(rng, 40, 0.2, 3.8)
    f = PlaneField(theta=jnp.asarray([0.1, 0.3, -0.2]), lower=jnp.zeros(2), extent=jnp.full(2, 4.0))

    @jax.jit
    def per_ray(theta):
        return maps.field_log_likelihood(eqx.tree_at(lambda g: g.theta, f, theta), rays)

    ll = np.asarray(per_ray(f.theta))
    fin = np.isfinite(ll)
    assert 10 <= fin.sum() < fin.size  # HITs outside the box are impossible (-inf) ...
    jf = np.asarray(jax.jacfwd(per_ray)(f.theta))
    jr = np.asarray(jax.jacrev(per_ray)(f.theta))
    assert np.all(np.isfinite(jr))  # ... with finite gradients, never NaN
    np.testing.assert_allclose(jf, jr, rtol=1e-10, atol=1e-12)
    fd = finite_difference(per_ray, f.theta)
    np.testing.assert_allclose(jr[fin], fd[fin], rtol=1e-6, atol=1e-7)


# --------------------------------------------------------------------------------------
# the grid case against the paper's closed forms


def _hit_sup_rays(rng, n):
    rays = random_rays(rng, n, 0.3, 2.7, r_min=0.0, r_max=2.0)
    kind = np.where(np.asarray(rays.kind) == SUB, HIT, np.asarray(rays.kind))  # no SUB: Eq. 7.17
    r = np.where(kind == HIT, rng.uniform(0.05, 1.9, n), 10.0)
    return RayBatch(rays.origins, rays.directions, jnp.asarray(r), jnp.asarray(kind), 0.0, 2.0)


def test_grid_gradient_is_eq_7_19_and_hessian_is_eq_7_21():
    rng = np.random.default_rng(11)
    rays = _hit_sup_rays(rng, 200)
    spec = GridSpec([0.0, 0.0], 0.5, (6, 6))
    stats = accumulate(spec, rays)
    h, r = np.asarray(stats.hits, float), np.asarray(stats.lengths)
    rates = jnp.asarray(rng.uniform(0.2, 2.0, (6, 6)))
    m0 = maps.DecayRateMap(spec, rates, jnp.asarray(0.3))  # outside rate: fixed

    @jax.jit
    def f(lam):
        return jnp.sum(maps.field_log_likelihood(eqx.tree_at(lambda m: m.rates, m0, lam), rays))

    g = np.asarray(jax.grad(f)(rates))
    np.testing.assert_allclose(g, h / np.asarray(rates) - r, rtol=1e-10, atol=1e-10)  # Eq. 7.19
    hess = np.asarray(jax.jit(jax.hessian(f))(rates)).reshape(36, 36)
    want = np.diag((-h / np.asarray(rates) ** 2).reshape(-1))  # Eq. 7.21, zero off-diagonal
    np.testing.assert_allclose(hess, want, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(g, finite_difference(f, rates, eps=1e-6), rtol=1e-6, atol=1e-6)
    assert (
        h.sum() > 50 and (h == 0).sum() >= 1 and (r > 0).all()
    )  # both kinds of cells are exercised


@pytest.mark.slow
def test_fit_grid_converges_to_eq_7_10_on_a_real_log():
    """Sec. 7.5.1 numerically: ``fit`` of a grid field reaches ``lambda_i = H_i / R_i``."""
    from lidarjax.datasets import fetch, load_carmen

    log = load_carmen(fetch("intel"))
    idx = np.arange(0, 40, 8)
    p = log.poses[idx]
    rays = from_scan(
        jaxlie.SE2.from_xy_theta(p[:, 0], p[:, 1], p[:, 2]),
        log.azimuths_rad,
        log.ranges_m[idx],
        0.0,
        log.usable_range_m,
    ).flatten()
    ends = np.asarray(rays.endpoints()[rays.kind == HIT])
    spec = GridSpec.covering(ends, 1.0, margin=0.5)
    stats = accumulate(spec, rays)
    h, r = np.asarray(stats.hits, float), np.asarray(stats.lengths)
    init = maps.DecayRateMap(spec, jnp.ones(spec.shape), jnp.asarray(0.0))
    fitted, sol = maps.fit(init, rays, rtol=1e-12, atol=1e-12, max_steps=3000)
    lam = np.asarray(fitted.rates)
    ml = np.asarray(maps.decay_rate_map(stats).rates)
    seen = h > 0
    assert seen.sum() > 40
    np.testing.assert_allclose(lam[seen], ml[seen], rtol=1e-4)
    # cells traversed but never hit go to 0; never-traversed cells keep their start value
    empty = (h == 0) & (r > 0)
    assert np.max(lam[empty] * r[empty]) < 1e-3
    np.testing.assert_array_equal(lam[r == 0], 1.0)
    ll_fit = float(jnp.sum(maps.field_log_likelihood(fitted, rays)))
    ml_map = maps.DecayRateMap(spec, jnp.where(r > 0, ml, 1.0), jnp.asarray(0.0))
    ll_ml = float(jnp.sum(decay_rate_log_likelihood(ml_map, rays)))
    assert ll_fit == pytest.approx(ll_ml, abs=1e-3)
    assert int(sol.stats["num_steps"]) > 1


# --------------------------------------------------------------------------------------
# fit recovers a known field from simulated rays


def simulate(field, rng, n, *, r_min=0.2, r_max=3.0):
    """Rays drawn from the decay-rate model of ``field`` by inverting ``S(r) = -log u``."""
    lo = np.asarray(field.lower) + 0.2
    hi = lo + np.asarray(field.extent) - 0.4
    o = jnp.asarray(rng.uniform(lo, hi, (n, 2)))
    th = rng.uniform(0, 2 * np.pi, n)
    d = jnp.asarray(np.stack([np.cos(th), np.sin(th)], 1))
    tau = -np.log(rng.uniform(size=n))
    integral = jax.jit(lambda o_, d_, r_: field.integral(o_, d_, r_))
    depth_max = np.asarray(integral(o, d, jnp.full(n, r_max)))
    a, b = np.zeros(n), np.full(n, r_max)
    for _ in range(60):  # bisection on the monotone optical depth
        mid = 0.5 * (a + b)
        below = np.asarray(integral(o, d, jnp.asarray(mid))) < tau
        a, b = np.where(below, mid, a), np.where(below, b, mid)
    r = 0.5 * (a + b)
    sup = tau >= depth_max
    kind = np.where(sup, SUP, np.where(r < r_min, SUB, HIT))
    r = np.where(sup, 2 * r_max, r)
    return RayBatch(o, d, jnp.asarray(r), jnp.asarray(kind), r_min, r_max)


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_fit_recovers_a_field_from_simulated_rays():
    truth = PlaneField(
        theta=jnp.asarray([0.2, 0.5, -0.3]), lower=jnp.zeros(2), extent=jnp.full(2, 4.0)
    )
    rays = simulate(truth, np.random.default_rng(6), 1000)
    counts = np.bincount(np.asarray(rays.kind), minlength=3)
    assert counts.min() > 100  # HIT, SUB and SUP all present
    start = PlaneField(theta=jnp.zeros(3), lower=jnp.zeros(2), extent=jnp.full(2, 4.0))
    fitted, sol = maps.fit(start, rays, rtol=1e-8, atol=1e-8)
    assert sol.result == optx.RESULTS.successful

    @jax.jit
    def nll(theta):
        return -jnp.sum(
            maps.field_log_likelihood(eqx.tree_at(lambda g: g.theta, start, theta), rays)
        )

    grad = np.asarray(jax.grad(nll)(fitted.theta))
    assert np.max(np.abs(grad)) < 1e-3  # a stationary point of the total log-likelihood
    cov = np.linalg.inv(np.asarray(jax.hessian(nll)(fitted.theta)))
    z = (np.asarray(fitted.theta) - np.asarray(truth.theta)) / np.sqrt(np.diag(cov))
    assert np.all(np.abs(z) < 4), z  # within 4 standard errors of the truth
    assert fitted.lower is start.lower  # the box is not a parameter


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_generic_fit_of_a_dct_map_matches_fit_dct():
    truth = BumpField(
        amps=jnp.asarray([3.0, 2.0]),
        centres=jnp.asarray([[1.2, 1.5], [2.8, 2.6]]),
        base=jnp.asarray(0.1),
        lower=jnp.zeros(2),
        extent=jnp.full(2, 4.0),
    )
    rays = simulate(truth, np.random.default_rng(7), 300)
    keep = np.asarray(
        maps.rays_in_box(maps.DCTMap(jnp.zeros((1, 1)), [0.0, 0.0], [4.0, 4.0]), rays)
    )
    rays = RayBatch(
        *(x[keep] for x in (rays.origins, rays.directions, rays.ranges, rays.kind)),
        rays.r_min,
        rays.r_max,
    )
    init = maps.dct_grid_initial_map(rays, [0.0, 0.0], [4.0, 4.0], (4, 4))
    special, _ = maps.fit_dct(rays, init=init, solver=optx.BFGS(rtol=1e-10, atol=1e-10))
    generic, _ = maps.fit(init, rays, solver=optx.BFGS(rtol=1e-10, atol=1e-10))
    assert isinstance(generic, maps.DCTMap)
    ll_s = float(jnp.sum(maps.dct_log_likelihood(special, rays)))
    ll_g = float(jnp.sum(maps.field_log_likelihood(generic, rays)))
    assert ll_g == pytest.approx(ll_s, abs=1e-4)
    ll0 = float(jnp.sum(maps.field_log_likelihood(init, rays)))
    assert ll_g > ll0 + 1.0


# --------------------------------------------------------------------------------------
# pose gradients through any field


def _scan_world():
    truth = BumpField(
        amps=jnp.asarray([6.0, 5.0, 6.0, 4.0, 5.0]),
        centres=jnp.asarray([[0.8, 0.8], [3.2, 1.0], [2.0, 3.3], [0.7, 2.8], [3.3, 3.0]]),
        base=jnp.asarray(0.02),
        lower=jnp.zeros(2),
        extent=jnp.full(2, 4.0),
        sigma=0.25,
        n_nodes=64,
    )
    pose = jaxlie.SE2.from_xy_theta(2.0, 1.9, 0.3)
    az = jnp.linspace(-np.pi, np.pi, 180, endpoint=False)
    probe = from_scan(pose, az, jnp.ones(180), 0.0, 5.0)
    rng = np.random.default_rng(8)
    tau = -np.log(rng.uniform(size=180))
    integral = jax.jit(lambda o_, d_, r_: truth.integral(o_, d_, r_))
    a, b = np.zeros(180), np.full(180, 5.0)
    for _ in range(60):
        mid = 0.5 * (a + b)
        below = np.asarray(integral(probe.origins, probe.directions, jnp.asarray(mid))) < tau
        a, b = np.where(below, mid, a), np.where(below, b, mid)
    depth_max = np.asarray(integral(probe.origins, probe.directions, jnp.full(180, 5.0)))
    ranges = np.where(tau >= depth_max, 5.0, 0.5 * (a + b))
    return truth, pose, az, jnp.asarray(ranges)


@pytest.mark.parametrize("which", ["user", "dct", "grid"])
@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_pose_gradients_through_any_field(which):
    truth, pose, az, ranges = _scan_world()
    if which == "user":
        field = truth
    elif which == "dct":
        field = maps.DCTMap(
            np.random.default_rng(9).normal(size=(6, 6)) * 0.3
            + 0.5 * (np.arange(36).reshape(6, 6) == 0),
            [0.0, 0.0],
            [4.0, 4.0],
        )
    else:
        spec = GridSpec([0.0, 0.0], 0.2, (20, 20))
        centres = spec.cell_centers()
        field = maps.DecayRateMap(spec, truth.decay_rate(centres), jnp.asarray(0.0))
    obj = FieldScan(field, az, ranges, 0.0, 5.0)
    v0 = jnp.asarray([2.03, 1.88, 0.31])

    @jax.jit
    def f(v):
        return obj(jaxlie.SE2.from_xy_theta(v[0], v[1], v[2]))

    g = np.asarray(jax.grad(f)(v0))
    assert np.all(np.isfinite(g))
    np.testing.assert_allclose(g, np.asarray(jax.jacfwd(f)(v0)), rtol=1e-9, atol=1e-9)
    fd = finite_difference(f, v0, eps=1e-6)
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-5)


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_refine_pose_on_a_user_field():
    """Coarse-to-fine refinement on a user's field (a blurred copy first) reaches the
    maximum-likelihood pose that refinement from the true pose finds."""
    truth, pose, az, ranges = _scan_world()
    wide = dataclasses.replace(truth, sigma=0.5)  # a blurred copy for the coarse stage
    start = jaxlie.SE2.from_xy_theta(2.15, 1.78, 0.3 + np.deg2rad(4.0))
    est, _ = refine_scan_pose([wide, truth], az, ranges, start, 0.0, 5.0)
    obj = FieldScan(truth, az, ranges, 0.0, 5.0)
    ml, _ = refine_pose(obj, pose)
    assert np.hypot(*np.asarray(est.translation() - ml.translation())) < 1e-3
    assert abs(float((est.inverse() @ ml).rotation().as_radians())) < 1e-3
    err = np.asarray(est.translation() - pose.translation())
    assert np.hypot(*err) < 0.1  # the ML pose of 180 random readings is near the truth
    assert float(obj(est)) > float(obj(start)) + 10.0


# --------------------------------------------------------------------------------------
# bad input


def test_bad_input_raises():
    rng = np.random.default_rng(10)
    rays = random_rays(rng, 20, 0.2, 3.8)
    f = PlaneField(theta=jnp.zeros(3), lower=jnp.zeros(2), extent=jnp.full(2, 4.0))
    with pytest.raises(ValueError, match="field0 must be an AbstractDecayRateField"):
        maps.fit("not a field", rays)
    with pytest.raises(ValueError, match="rays must be a RayBatch"):
        maps.field_log_likelihood(f, "rays")
    rays3 = RayBatch(
        jnp.zeros((2, 3)), jnp.asarray([[1.0, 0, 0]] * 2), jnp.ones(2), jnp.zeros(2, int), 0.0, 5.0
    )
    with pytest.raises(ValueError, match="rays are 3-D but the field is 2-D"):
        maps.field_log_likelihood(f, rays3)
    empty = RayBatch(
        rays.origins[:0], rays.directions[:0], rays.ranges[:0], rays.kind[:0], 0.1, 2.5
    )
    with pytest.raises(ValueError, match="rays is empty"):
        maps.fit(f, empty)
    with pytest.raises(ValueError, match="chunk_size"):
        maps.field_log_likelihood(f, rays, chunk_size=0)
    with pytest.raises(ValueError, match="max_steps"):
        maps.fit(f, rays, max_steps=0)
    # a HIT where the field is 0 (outside the box): the fit cannot start
    bad = RayBatch(
        jnp.asarray([[1.0, 1.0]]),
        jnp.asarray([[1.0, 0.0]]),
        jnp.asarray([5.0]),
        jnp.asarray([HIT]),
        0.0,
        10.0,
    )
    with pytest.raises(ValueError, match="non-finite log-likelihood for 1 of 1 rays"):
        maps.fit(f, bad)
    with pytest.raises(ValueError, match="2-D AbstractDecayRateField"):
        FieldScan("map", jnp.zeros(3), jnp.ones(3), 0.0, 5.0)

    class BadNodes(PlaneField):
        def quadrature_nodes(self):
            return 0

    g = BadNodes(theta=jnp.zeros(3), lower=jnp.zeros(2), extent=jnp.full(2, 4.0))
    with pytest.raises(ValueError, match="quadrature_nodes"):
        maps.field_log_likelihood(g, rays)
