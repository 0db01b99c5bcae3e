"""The geometry core's ray primitives (lidarjax.raytrace._primitives) against independent
NumPy references: per-axis case analysis and point sampling for the slab test, the
quadratic formula for cylinders and spheres, a 2x2 linear solve for segments, the plane
equation's residual for planes, and plain slicing for the chunk helpers."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lidarjax.raytrace import (
    box_exit,
    clip_to_box,
    cross2,
    first_segment_hit,
    first_segment_hits,
    map_chunked,
    n_chunks_for,
    pad_to_chunks,
    ray_box,
    ray_cylinder,
    ray_plane,
    ray_segment,
    ray_sphere,
    slabs,
    unchunk,
)
from lidarjax.testing import finite_difference

INF = np.inf

# ---------------------------------------------------------------- independent references


def np_ray_box(lo, hi, o, d):
    """Interval of ``t`` with ``lo <= o + t d <= hi`` by per-axis case analysis;
    ``(inf, -inf)`` when a resting axis lies outside its slab."""
    t0, t1 = -INF, INF
    for k in range(len(o)):
        if d[k] == 0:
            if not lo[k] <= o[k] <= hi[k]:
                return INF, -INF
            continue
        a, b = (lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]
        t0, t1 = max(t0, min(a, b)), min(t1, max(a, b))
    return t0, t1


def np_ray_cylinder(c, r, z0, z1, o, d):
    """Quadratic formula for the mantle, case analysis for the caps; ``(inf, -inf)`` for a
    ray that misses the infinite cylinder or rests outside the z slab."""
    a = d[0] ** 2 + d[1] ** 2
    p = np.asarray(o[:2], float) - np.asarray(c, float)
    if a == 0:
        if p @ p > r * r:
            return INF, -INF
        ta, tb = -INF, INF
    else:
        b = 2 * (p @ np.asarray(d[:2], float))
        disc = b * b - 4 * a * (p @ p - r * r)
        if disc < 0:
            return INF, -INF
        ta, tb = (-b - np.sqrt(disc)) / (2 * a), (-b + np.sqrt(disc)) / (2 * a)
    if d[2] == 0:
        if not z0 <= o[2] <= z1:
            return INF, -INF
        za, zb = -INF, INF
    else:
        za, zb = sorted([(z0 - o[2]) / d[2], (z1 - o[2]) / d[2]])
    return max(ta, za), min(tb, zb)


def np_ray_sphere(c, r, o, d):
    """Roots of ``|o + t d - c|^2 = r^2`` (any direction length); ``(inf, -inf)`` if none."""
    w = np.asarray(o, float) - np.asarray(c, float)
    a, b, cc = d @ d, 2 * (w @ d), w @ w - r * r
    disc = b * b - 4 * a * cc
    if disc < 0:
        return INF, -INF
    return (-b - np.sqrt(disc)) / (2 * a), (-b + np.sqrt(disc)) / (2 * a)


def np_ray_segment(o, d, a, b, slack=1e-12):
    """Solve ``o + t d = a + u (b - a)`` as a 2x2 system; ``inf`` unless ``t > 0`` and
    ``u`` in ``[0, 1]``."""
    m = np.column_stack([d, -(np.asarray(b) - a)])
    if abs(np.linalg.det(m)) < 1e-12:
        return INF
    t, u = np.linalg.solve(m, np.asarray(a) - o)
    return t if t > 0 and -slack <= u <= 1 + slack else INF


def box_membership(lo, hi, pts, tol=1e-9):
    return np.all((pts >= np.asarray(lo) - tol) & (pts <= np.asarray(hi) + tol), axis=-1)


def _f(*xs):
    return [jnp.asarray(x, jnp.float64) for x in xs]


def _check_jacobians(f, degenerate, generic):
    """Forward and reverse Jacobians of ``f`` are finite at every degenerate input; at a
    generic one they agree with each other and with central finite differences."""
    f = jax.jit(f)
    jf, jr = jax.jit(jax.jacfwd(f)), jax.jit(jax.jacrev(f))
    for x in degenerate:
        x = jnp.asarray(x, jnp.float64)
        assert np.isfinite(np.asarray(jf(x))).all() and np.isfinite(np.asarray(jr(x))).all()
    x = jnp.asarray(generic, jnp.float64)
    np.testing.assert_allclose(jf(x), jr(x), rtol=1e-12)
    np.testing.assert_allclose(jr(x), finite_difference(f, x, eps=1e-6), rtol=1e-6, atol=1e-8)


# ---------------------------------------------------------------- slab test


LO, HI = np.array([-1.0, -2.0, 0.5]), np.array([2.0, 1.0, 3.0])

DEGENERATE_BOX_RAYS = [
    # (origin, direction, what)
    ([-3.0, 0.0, 1.0], [1.0, 0.0, 0.0], "two resting axes, inside both slabs"),
    ([-3.0, 5.0, 1.0], [1.0, 0.0, 0.0], "resting axis outside its slab: miss"),
    ([-3.0, 1.0, 1.0], [1.0, 0.0, 0.0], "along the face y = upper (closed box)"),
    ([-3.0, -2.0, 0.5], [1.0, 0.0, 0.0], "along an edge"),
    ([0.0, 0.0, 1.0], [0.0, 0.0, 0.0], "zero direction, origin inside"),
    ([9.0, 0.0, 1.0], [0.0, 0.0, 0.0], "zero direction, origin outside"),
    ([0.5, -0.5, 1.5], [0.3, -0.4, 0.5], "origin inside"),
    ([0.0, -4.0, 1.0], [1.0, 1.0, 0.0], "touches the edge at (2, -2) only"),
    ([-2.0, -3.0, -0.5], [1.0, 1.0, 1.0], "through the corner (-1, -2, 0.5)"),
    ([-3.0, 0.0, 1.0], [-1.0, 0.0, 0.0], "pointing away: box behind the origin"),
    ([-3.0, 4.0, 1.0], [1.0, 0.1, 0.0], "misses beside the box"),
]


@pytest.mark.parametrize("o, d, what", DEGENERATE_BOX_RAYS)
def test_ray_box_degenerate_cases_match_case_analysis(o, d, what):
    t0, t1 = ray_box(*_f(LO, HI, o, d))
    r0, r1 = np_ray_box(LO, HI, np.array(o), np.array(d))
    assert (float(t0) <= float(t1)) == (r0 <= r1), what
    if r0 <= r1:
        np.testing.assert_allclose([float(t0), float(t1)], [r0, r1], rtol=1e-14, atol=1e-14)
    else:
        assert not np.isnan(float(t0)) and not np.isnan(float(t1))
    assert t0.dtype == jnp.float64


def test_ray_box_corner_touch_is_a_single_point():
    t0, t1 = ray_box(*_f(LO, HI, [0.0, -4.0, 1.0], [1.0, 1.0, 0.0]))
    assert float(t0) == float(t1) == 2.0


def test_ray_box_random_rays_match_reference_and_sampling():
    rng = np.random.default_rng(0)
    o = rng.uniform(-4, 4, (300, 3))
    d = rng.standard_normal((300, 3))
    d[:40, 0] = 0.0
    d[40:80, 1:] = 0.0
    t0, t1 = (np.asarray(x) for x in ray_box(*_f(LO, HI, o, d)))
    for k in range(len(o)):
        r0, r1 = np_ray_box(LO, HI, o[k], d[k])
        assert (t0[k] <= t1[k]) == (r0 <= r1)
        if r0 <= r1:
            np.testing.assert_allclose([t0[k], t1[k]], [r0, r1], rtol=1e-12, atol=1e-12)
            if np.isfinite(t0[k]) and np.isfinite(t1[k]):
                ts = np.linspace(t0[k], t1[k], 17)
                assert box_membership(LO, HI, o[k] + ts[:, None] * d[k]).all()
                eps = 1e-6 * (1 + abs(t1[k] - t0[k]))
                out = o[k] + np.array([t0[k] - eps, t1[k] + eps])[:, None] * d[k]
                assert not box_membership(LO, HI, out, tol=0.0).any()


def test_slabs_per_axis_outputs_and_eps():
    o, d = _f([0.0, 5.0, 1.0], [1.0, 1e-13, 0.0])
    moving, d_safe, inside, near, far = slabs(*_f(LO, HI), o, d)
    np.testing.assert_array_equal(np.asarray(moving), [True, True, False])
    np.testing.assert_array_equal(np.asarray(inside), [True, False, True])
    assert float(d_safe[2]) == 1.0 and float(near[2]) == -INF and float(far[2]) == INF
    # with eps the tiny component rests: outside its slab -> (inf, -inf) on that axis
    moving, _, _, near, far = slabs(*_f(LO, HI), o, d, eps=1e-12)
    assert not bool(moving[1]) and float(near[1]) == INF and float(far[1]) == -INF
    with pytest.raises(ValueError, match="eps"):
        slabs(*_f(LO, HI), o, d, eps=-1.0)


def test_ray_box_broadcasts_boxes_and_keeps_float32():
    lo = jnp.asarray([[0.0, 0.0], [2.0, 2.0]], jnp.float32)  # two boxes
    o = jnp.zeros((3, 1, 2), jnp.float32)
    d = jnp.asarray([[[1.0, 1.0]], [[1.0, 0.0]], [[0.0, 1.0]]], jnp.float32)
    t0, t1 = ray_box(lo, lo + 1.0, o, d)
    assert t0.shape == (3, 2) and t0.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(t0[0]), [0.0, 2.0])
    np.testing.assert_array_equal(np.asarray(t1[0]), [1.0, 3.0])
    assert float(t0[1, 1]) > float(t1[1, 1])  # the x-ray misses the box at (2, 2)


def test_ray_box_coordinate_major_axis_matches_last_axis():
    rng = np.random.default_rng(7)
    lo = rng.uniform(-2, 0, (5, 3))  # five boxes
    hi = lo + rng.uniform(0.5, 2, (5, 3))
    o = rng.uniform(-3, 3, (4, 1, 3))  # four rays
    d = rng.standard_normal((4, 1, 3))
    d[0, 0, 1] = 0.0
    want = ray_box(*_f(lo, hi, o, d))
    got = ray_box(
        *_f(lo.T[:, None], hi.T[:, None], np.moveaxis(o, -1, 0), np.moveaxis(d, -1, 0)), axis=0
    )
    for g, w in zip(got, want):
        assert g.shape == (4, 5)
        np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
    got = box_exit(
        *_f(lo.T[:, None], hi.T[:, None], np.moveaxis(o, -1, 0), np.moveaxis(d, -1, 0)), axis=0
    )
    np.testing.assert_array_equal(np.asarray(got), np.asarray(box_exit(*_f(lo, hi, o, d))))
    with pytest.raises(ValueError, match="axis"):
        ray_box(*_f(lo, hi, o, d), axis=3)


def test_clip_to_box_clips_to_ray_and_zeroes_non_finite():
    cases = [
        ([-3.0, 0.0, 1.0], [1.0, 0.0, 0.0], 10.0, (2.0, 5.0)),
        ([-3.0, 0.0, 1.0], [1.0, 0.0, 0.0], 4.0, (2.0, 4.0)),
        ([0.0, 0.0, 1.0], [1.0, 0.0, 0.0], 10.0, (0.0, 2.0)),  # origin inside
        ([0.0, 0.0, 1.0], [1.0, 0.0, 0.0], INF, (0.0, 2.0)),
        ([0.0, 0.0, 1.0], [0.0, 0.0, 0.0], INF, (0.0, 0.0)),  # zero direction: not finite
    ]
    for o, d, length, want in cases:
        t_in, t_out = clip_to_box(*_f(LO, HI, o, d, length))
        assert (float(t_in), float(t_out)) == pytest.approx(want)
    t_in, t_out = clip_to_box(*_f(LO, HI, [-3.0, 0.0, 1.0], [-1.0, 0.0, 0.0], 10.0))
    assert float(t_out) < float(t_in)  # box behind the origin


def test_box_exit_ignores_resting_axes():
    # origin rounding just outside the y slab of the box it walks in: still exits at x = 2
    o, d = _f([0.0, 1.0 + 1e-15, 1.0], [1.0, 0.0, 0.0])
    assert float(box_exit(*_f(LO, HI), o, d)) == pytest.approx(2.0)
    assert float(box_exit(*_f(LO, HI), o, jnp.zeros(3))) == INF
    o, d = _f([0.0, 0.0, 1.0], [-0.6, 0.8, 0.0])
    assert float(box_exit(*_f(LO, HI), o, d)) == pytest.approx(1.25)


def test_ray_box_gradients_finite_at_degenerate_inputs_and_match_fd():
    def f(x):
        t0, t1 = ray_box(jnp.asarray(LO), jnp.asarray(HI), x[:3], x[3:])
        t0 = jnp.where(jnp.isfinite(t0), t0, 0.0)
        t1 = jnp.where(jnp.isfinite(t1), t1, 0.0)
        return jnp.stack([t0, t1])

    degenerate = [o + d for o, d, _ in DEGENERATE_BOX_RAYS]
    _check_jacobians(f, degenerate, [-3.0, 0.2, 1.1, 1.0, 0.1, 0.05])


@settings(max_examples=30)
@given(
    st.lists(st.floats(-4, 4), min_size=3, max_size=3),
    st.lists(st.sampled_from([-1.0, -0.5, 0.0, 0.25, 1.0]), min_size=3, max_size=3),
)
def test_ray_box_property(o, d):
    t0, t1 = ray_box(*_f(LO, HI, o, d))
    r0, r1 = np_ray_box(LO, HI, np.array(o), np.array(d))
    assert (float(t0) <= float(t1)) == (r0 <= r1)
    if r0 <= r1:
        np.testing.assert_allclose([float(t0), float(t1)], [r0, r1], rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------- vertical cylinders

CYL = dict(c=np.array([1.0, 2.0]), r=0.5, z0=-1.0, z1=2.0)


_ray_cylinder = jax.jit(ray_cylinder, static_argnames="eps")  # compiled once per shape


def _cyl(o, d, eps=0.0, **kw):
    p = {**CYL, **kw}
    return _ray_cylinder(*_f(p["c"], p["r"], p["z0"], p["z1"], o, d), eps=eps)


DEGENERATE_CYL_RAYS = [
    ([-4.0, 2.0, 0.0], [1.0, 0.0, 0.0], "horizontal, through the axis"),
    ([-4.0, 2.5, 0.0], [1.0, 0.0, 0.0], "tangent to the mantle"),
    ([-4.0, 3.0, 0.0], [1.0, 0.0, 0.0], "misses the mantle"),
    ([-4.0, 2.0, 5.0], [1.0, 0.0, 0.0], "horizontal above the top"),
    ([-4.0, 2.0, 2.0], [1.0, 0.0, 0.0], "horizontal in the top cap's plane"),
    ([1.2, 2.1, -5.0], [0.0, 0.0, 1.0], "vertical inside the mantle"),
    ([3.0, 2.0, -5.0], [0.0, 0.0, 1.0], "vertical outside the mantle"),
    ([1.0, 2.0, 0.0], [0.0, 0.0, 0.0], "zero direction inside"),
    ([1.1, 2.2, 0.5], [0.6, -0.8, 0.3], "origin inside"),
    ([-4.0, 2.0, -3.0], [1.0, 0.0, 0.8], "enters through the mantle, leaves at the top"),
    ([1.0, 2.0, -3.0], [0.1, 0.0, 1.0], "enters through the bottom cap"),
]


@pytest.mark.parametrize("o, d, what", DEGENERATE_CYL_RAYS)
def test_ray_cylinder_matches_quadratic_reference(o, d, what):
    t0, t1 = (float(x) for x in _cyl(o, d))
    r0, r1 = np_ray_cylinder(CYL["c"], CYL["r"], CYL["z0"], CYL["z1"], o, d)
    assert (t0 <= t1) == (r0 <= r1), what
    if r0 <= r1:
        np.testing.assert_allclose([t0, t1], [r0, r1], rtol=1e-12, atol=1e-12)


def test_ray_cylinder_tangent_is_a_touch():
    t0, t1 = _cyl([-4.0, 2.5, 0.0], [1.0, 0.0, 0.0])
    assert float(t0) == float(t1) == 5.0


def test_ray_cylinder_random_rays_and_sampling():
    rng = np.random.default_rng(1)
    o = rng.uniform(-3, 4, (300, 3))
    d = rng.standard_normal((300, 3)) * rng.uniform(0.2, 3, (300, 1))  # any length
    d[:30, :2] = 0.0
    d[30:60, 2] = 0.0
    t0, t1 = (np.asarray(x) for x in _cyl(o, d))
    for k in range(len(o)):
        r0, r1 = np_ray_cylinder(CYL["c"], CYL["r"], CYL["z0"], CYL["z1"], o[k], d[k])
        assert (t0[k] <= t1[k]) == (r0 <= r1)
        if r0 <= r1:
            np.testing.assert_allclose([t0[k], t1[k]], [r0, r1], rtol=1e-9, atol=1e-9)
            if np.isfinite(t0[k]) and np.isfinite(t1[k]):
                p = o[k] + np.linspace(t0[k], t1[k], 11)[:, None] * d[k]
                assert (np.hypot(*(p[:, :2] - CYL["c"]).T) <= CYL["r"] + 1e-9).all()
                assert ((p[:, 2] >= CYL["z0"] - 1e-9) & (p[:, 2] <= CYL["z1"] + 1e-9)).all()


def test_ray_cylinder_eps_treats_nearly_vertical_rays_as_vertical():
    o, d = [1.2, 2.1, -5.0], [1e-7, 0.0, 1.0]  # d_x^2 = 1e-14 < 1e-12
    t0, t1 = _cyl(o, d, eps=1e-12)
    assert (float(t0), float(t1)) == pytest.approx((4.0, 7.0))
    t0, t1 = _cyl([3.0, 2.0, -5.0], d, eps=1e-12)
    assert float(t0) > float(t1)


def test_ray_cylinder_broadcasts_and_keeps_float32():
    c = jnp.asarray([[0.0, 0.0], [5.0, 0.0]], jnp.float32)[None]  # [1 2 2]
    d = jnp.asarray([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], jnp.float32)[:, None]  # [2 1 3]
    o = jnp.asarray([-3.0, 0.0, 0.0], jnp.float32)
    t0, t1 = _ray_cylinder(c, jnp.float32(1.0), -1.0, 1.0, o, d)
    assert t0.shape == (2, 2)
    np.testing.assert_allclose(np.asarray(t0[0]), [2.0, 7.0])
    np.testing.assert_allclose(np.asarray(t1[0]), [4.0, 9.0])
    assert t0.dtype == jnp.float32


def test_ray_cylinder_gradients_finite_at_degenerate_inputs():
    def f(x):
        t0, t1 = ray_cylinder(x[6:8], x[8], x[9], x[10], x[:3], x[3:6])
        return jnp.stack([jnp.where(jnp.isfinite(t), t, 0.0) for t in (t0, t1)])

    p = [*CYL["c"], CYL["r"], CYL["z0"], CYL["z1"]]
    degenerate = [o + d + p for o, d, _ in DEGENERATE_CYL_RAYS]
    _check_jacobians(f, degenerate, [-4.0, 2.1, -0.3, 1.0, 0.05, 0.1, *p])


# ---------------------------------------------------------------- spheres


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


SPHERE_RAYS = [
    ([-5.0, 0.0, 0.0], [1.0, 0.0, 0.0], "through the centre"),
    ([-5.0, 1.0, 0.0], [1.0, 0.0, 0.0], "tangent"),
    ([-5.0, 2.0, 0.0], [1.0, 0.0, 0.0], "miss"),
    ([0.0, 0.0, 0.0], [0.0, 0.6, 0.8], "origin at the centre"),
    ([0.3, -0.2, 0.1], _unit([1.0, 2.0, -1.0]), "origin inside"),
    ([5.0, 0.0, 0.0], [1.0, 0.0, 0.0], "sphere behind the origin"),
]


@pytest.mark.parametrize("o, d, what", SPHERE_RAYS)
def test_ray_sphere_matches_quadratic_reference(o, d, what):
    t0, t1 = (float(x) for x in ray_sphere(*_f(np.zeros(3), 1.0, o, d)))
    r0, r1 = np_ray_sphere(np.zeros(3), 1.0, np.asarray(o), np.asarray(d, float))
    assert (t0 <= t1) == (r0 <= r1), what
    if r0 <= r1:
        np.testing.assert_allclose([t0, t1], [r0, r1], rtol=1e-12, atol=1e-12)
    else:
        assert (t0, t1) == (INF, -INF)


def test_ray_sphere_tangent_and_2d_disc():
    t0, t1 = ray_sphere(*_f(np.zeros(3), 1.0, [-5.0, 1.0, 0.0], [1.0, 0.0, 0.0]))
    assert float(t0) == float(t1) == 5.0
    t0, t1 = ray_sphere(*_f([3.0, 4.0], 1.0, [0.0, 0.0], [0.6, 0.8]))  # a disc in 2-D
    assert (float(t0), float(t1)) == pytest.approx((4.0, 6.0))


def test_ray_sphere_random_rays():
    rng = np.random.default_rng(2)
    c, r = np.array([0.5, -1.0, 2.0]), 1.5
    o = rng.uniform(-4, 4, (300, 3))
    d = rng.standard_normal((300, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t0, t1 = (np.asarray(x) for x in ray_sphere(*_f(c, r, o, d)))
    for k in range(len(o)):
        r0, r1 = np_ray_sphere(c, r, o[k], d[k])
        assert (t0[k] <= t1[k]) == (r0 <= r1)
        if r0 <= r1:
            np.testing.assert_allclose([t0[k], t1[k]], [r0, r1], rtol=1e-9, atol=1e-9)


@settings(max_examples=25)
@given(
    st.lists(st.floats(-3, 3), min_size=3, max_size=3),
    st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 0.1),
    st.floats(0.1, 2.0),
)
def test_ray_sphere_property(o, d, r):
    d = _unit(d)
    t0, t1 = (float(x) for x in ray_sphere(*_f(np.zeros(3), r, o, d)))
    r0, r1 = np_ray_sphere(np.zeros(3), r, np.asarray(o), d)
    if r0 <= r1 and r1 - r0 > 1e-6:  # away from tangency, where rounding decides
        np.testing.assert_allclose([t0, t1], [r0, r1], rtol=1e-9, atol=1e-9)
    elif r0 > r1:
        assert t0 > t1


def test_ray_sphere_gradients_finite_at_degenerate_inputs():
    def f(x):
        t0, t1 = ray_sphere(x[6:9], x[9], x[:3], x[3:6])
        return jnp.stack([jnp.where(jnp.isfinite(t), t, 0.0) for t in (t0, t1)])

    degenerate = [[*o, *d, 0.0, 0.0, 0.0, 1.0] for o, d, _ in SPHERE_RAYS]
    generic = [-5.0, 0.3, 0.2, *_unit([1.0, 0.05, -0.02]), 0.1, 0.0, 0.0, 1.0]
    _check_jacobians(f, degenerate, generic)


# ---------------------------------------------------------------- segments and planes


def test_cross2():
    a, b = np.array([[1.0, 2.0], [3.0, -1.0]]), np.array([[0.5, 4.0], [2.0, 2.0]])
    want = [1.0 * 4.0 - 2.0 * 0.5, 3.0 * 2.0 - (-1.0) * 2.0]
    np.testing.assert_array_equal(np.asarray(cross2(*_f(a, b))), want)


SEGMENT_RAYS = [
    ([0.0, 0.0], [1.0, 0.0], [2.0, -1.0], [2.0, 1.0], "through the middle"),
    ([0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [2.0, 1.0], "through the start vertex"),
    ([0.0, 0.0], [1.0, 0.0], [2.0, -1.0], [2.0, 0.0], "through the end vertex"),
    ([0.0, 0.0], [1.0, 0.0], [2.0, 0.5], [2.0, 1.0], "passes below"),
    ([0.0, 0.0], [1.0, 0.0], [-2.0, -1.0], [-2.0, 1.0], "behind the origin"),
    ([0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [3.0, 1.0], "parallel"),
    ([0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [3.0, 0.0], "collinear"),
    ([0.0, 0.0], [1.0, 0.0], [2.0, 1.0], [2.0, 1.0], "degenerate segment"),
    ([0.0, 0.0], _unit([1.0, 1.0]), [0.0, 3.0], [3.0, 0.0], "oblique"),
]


@pytest.mark.parametrize("o, d, a, b, what", SEGMENT_RAYS)
def test_ray_segment_matches_linear_solve(o, d, a, b, what):
    t = float(ray_segment(*_f(o, d, a, b)))
    ref = np_ray_segment(np.asarray(o), np.asarray(d), np.asarray(a), np.asarray(b))
    assert t == pytest.approx(ref, rel=1e-14), what


def test_ray_segment_random_and_gradients_finite():
    rng = np.random.default_rng(3)
    segment = jax.jit(ray_segment)
    for _ in range(200):
        o, a, b = rng.uniform(-3, 3, (3, 2))
        d = _unit(rng.standard_normal(2))
        t = float(segment(*_f(o, d, a, b)))
        ref = np_ray_segment(o, d, a, b)
        if np.isfinite(ref) or np.isfinite(t):
            assert t == pytest.approx(ref, rel=1e-9)

    def f(x):
        t = ray_segment(x[:2], x[2:4], x[4:6], x[6:8])
        return jnp.where(jnp.isfinite(t), t, 0.0)

    g = jax.jit(jax.grad(f))
    for o, d, a, b, _ in SEGMENT_RAYS:
        assert np.isfinite(np.asarray(g(jnp.asarray([*o, *d, *a, *b], jnp.float64)))).all()


def test_first_segment_hits_matches_per_ray_and_chunks():
    rng = np.random.default_rng(4)
    starts, ends = (jnp.asarray(rng.uniform(-5, 5, (12, 2))) for _ in range(2))
    valid = jnp.asarray(rng.random(12) < 0.8)
    o = jnp.asarray(rng.uniform(-1, 1, (37, 2)))
    d = rng.standard_normal((37, 2))
    d = jnp.asarray(d / np.linalg.norm(d, axis=1, keepdims=True))
    one = jax.jit(first_segment_hit)
    ref = [one(o[k], d[k], starts, ends, valid) for k in range(37)]
    for chunk in (None, 5, 100):
        t, i = first_segment_hits(o, d, starts, ends, valid, chunk_size=chunk)
        # (the compiled batch may round the last bit differently from one-ray calls)
        np.testing.assert_allclose(np.asarray(t), [float(r[0]) for r in ref], rtol=1e-14)
        np.testing.assert_array_equal(np.asarray(i), [int(r[1]) for r in ref])
    s_np, e_np, o_np, d_np = (np.asarray(v) for v in (starts, ends, o, d))
    t_np = [
        min([np_ray_segment(o_np[k], d_np[k], s_np[j], e_np[j]) for j in np.flatnonzero(valid)])
        for k in range(37)
    ]
    np.testing.assert_allclose(np.asarray(t), t_np, rtol=1e-9)


def test_ray_plane_residual_parallel_and_behind():
    rng = np.random.default_rng(5)
    plane = jax.jit(ray_plane)
    for _ in range(50):
        o, x = rng.uniform(-3, 3, (2, 3))
        v, n = _unit(rng.standard_normal(3)), rng.standard_normal(3)
        t = float(plane(*_f(o, v, x, n)))
        assert abs(n @ (o + t * v - x)) < 1e-9 * (1 + abs(t)) * np.linalg.norm(n)
    o, v = _f([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    assert float(ray_plane(o, v, *_f([0.0, 0.0, 1.0], [0.0, 0.0, 1.0]))) == INF
    assert float(ray_plane(o, v, *_f([-2.0, 0.0, 0.0], [3.0, 0.0, 0.0]))) == -2.0
    g = jax.grad(lambda n: ray_plane(o, v, jnp.zeros(3), n))(jnp.asarray([0.0, 0.0, 1.0]))
    assert np.isfinite(np.asarray(g)).all()


# ---------------------------------------------------------------- chunk helpers


def test_n_chunks_for():
    assert [n_chunks_for(n, 4) for n in (0, 1, 4, 5, 8, 9)] == [1, 1, 1, 2, 2, 3]
    for bad in (0, -1, 2.0, True):
        with pytest.raises(ValueError, match="chunk_size"):
            n_chunks_for(5, bad)


@pytest.mark.parametrize("xp", [np, jnp])
def test_pad_to_chunks_fill_edge_and_roundtrip(xp):
    x = xp.arange(14.0).reshape(7, 2)
    p = pad_to_chunks(x, 3)
    assert p.shape == (3, 3, 2) and isinstance(p, type(x))
    np.testing.assert_array_equal(np.asarray(p).reshape(9, 2)[7:], 0.0)
    np.testing.assert_array_equal(np.asarray(pad_to_chunks(x, 3, fill=-1.5))[2, 1:], -1.5)
    e = np.asarray(pad_to_chunks(x, 3, fill="edge")).reshape(9, 2)
    np.testing.assert_array_equal(e[7:], np.broadcast_to(np.asarray(x)[-1], (2, 2)))
    np.testing.assert_array_equal(np.asarray(unchunk(p, 7)), np.asarray(x))
    assert pad_to_chunks(x, 7).shape == (1, 7, 2)
    assert pad_to_chunks(xp.zeros((0, 2)), 4).shape == (1, 4, 2)
    b = pad_to_chunks(xp.asarray([True, True]), 3, fill=False)
    np.testing.assert_array_equal(np.asarray(b), [[True, True, False]])
    with pytest.raises(ValueError, match="edge"):
        pad_to_chunks(xp.zeros((0, 2)), 4, fill="edge")
    with pytest.raises(ValueError, match="fill"):
        pad_to_chunks(x, 4, fill="wrap")


def test_map_chunked_matches_direct_and_per_leaf_fill():
    rng = np.random.default_rng(6)
    a = jnp.asarray(rng.standard_normal((23, 3)))
    b = jnp.asarray(rng.uniform(0.5, 2, 23))

    def fn(xs):
        u, v = xs
        return {"s": jnp.sum(u, axis=-1) / v, "u": u * 2.0}

    direct = fn((a, b))
    for chunk, fill in [(1, 1.0), (4, "edge"), (4, (0.0, 1.0)), (23, 1.0), (50, "edge")]:
        out = map_chunked(fn, (a, b), chunk, fill=fill)
        np.testing.assert_allclose(np.asarray(out["s"]), np.asarray(direct["s"]), rtol=1e-15)
        np.testing.assert_array_equal(np.asarray(out["u"]), np.asarray(direct["u"]))
    # padded rows with b = 0 would be inf/NaN; "edge" keeps reverse mode NaN-free
    g = jax.grad(lambda v: jnp.sum(map_chunked(lambda x: 1.0 / x, v, 5, fill="edge")))(b)
    np.testing.assert_allclose(np.asarray(g), -1.0 / np.asarray(b) ** 2, rtol=1e-14)
    with pytest.raises(ValueError, match="no arrays"):
        map_chunked(fn, (), 4)
