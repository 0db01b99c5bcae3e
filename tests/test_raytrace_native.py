"""The native (C++, XLA FFI) ray kernels against the pure-JAX path, their oracle: the same
hit/miss counts and per-ray folds on 2-D and 3-D grids, float32 and float64, every term
form, every grid model and ray kind, inside ``jit``, ``lax.scan`` and ``vmap``; backend
selection, fallback, staleness and the never-hang guarantees."""

from __future__ import annotations

import math
import re
import shutil
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from test_fast_likelihood import LIMITS, _all_kinds, _assert_same, _geometry, _maps

from lidarjax.rays import HIT, SUB, SUP, RayBatch, from_scan
from lidarjax.raytrace import CellTerm, GridSpec, _build, _native, accumulate, fold_rays
from lidarjax.sensor_models import batch_log_likelihood

HAVE_COMPILER = _build.compiler() is not None
native = pytest.mark.skipif(
    not _native.available(), reason=f"native kernels unavailable: {_native.unavailable_reason()}"
)


def test_native_is_built_where_a_compiler_exists(monkeypatch):
    """`make` builds the kernels; with a compiler present, a missing or stale library is a
    build failure, not a reason to skip the native tests silently."""
    if HAVE_COMPILER:
        assert _build.up_to_date(), "native library missing or stale: run `make`"
        assert _native.available(), _native.unavailable_reason()
        assert _native.unavailable_reason() is None
    else:
        # no compiler: nothing may pretend to be native; "auto" must fall back to JAX
        assert not _native.available()
        assert re.search("not built|stale", _native.unavailable_reason() or "")
        monkeypatch.setitem(_native._state, "warned", False)
        with pytest.warns(RuntimeWarning, match="pure-JAX"):
            assert _native.resolve("auto") == "jax"


# --------------------------------------------------------------------------------------
# accumulate
# --------------------------------------------------------------------------------------


def _random_batch(rng, spec, n, dtype=np.float64, r_min=0.3, r_max=6.0):
    lo, hi = np.asarray(spec.origin), np.asarray(spec.upper)
    o = rng.uniform(lo - 1.0, hi + 1.0, size=(n, spec.dim))
    d = rng.normal(size=(n, spec.dim))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rng.uniform(0.0, 1.3 * r_max, size=n)
    kind = np.where(r < r_min, SUB, np.where(r >= r_max, SUP, HIT))
    return RayBatch(
        origins=jnp.asarray(o, dtype),
        directions=jnp.asarray(d, dtype),
        ranges=jnp.asarray(r, dtype),
        kind=jnp.asarray(kind, jnp.int32),
        r_min=jnp.asarray(r_min, dtype),
        r_max=jnp.asarray(r_max, dtype),
    )


def _assert_stats_equal(a, b, rtol):
    np.testing.assert_array_equal(np.asarray(a.hits), np.asarray(b.hits))
    np.testing.assert_array_equal(np.asarray(a.misses), np.asarray(b.misses))
    np.testing.assert_allclose(np.asarray(a.lengths), np.asarray(b.lengths), rtol=rtol, atol=rtol)


@native
@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("sub_rays", ["ignore", "hit"])
@pytest.mark.parametrize("threads", [1, 3])
def test_accumulate_matches_jax_float64(dim, sub_rays, threads):
    rng = np.random.default_rng(dim)
    spec = (
        GridSpec([-1.0, 0.5], 0.25, (40, 30))
        if dim == 2
        else GridSpec([-1.0, 0.5, 0.0], 0.25, (20, 16, 12))
    )
    rays = _random_batch(rng, spec, 3000)
    ref = accumulate(spec, rays, sub_rays=sub_rays, backend="jax")
    got = accumulate(spec, rays, sub_rays=sub_rays, backend="native", threads=threads)
    assert int(ref.hits.sum()) > 100 and int(ref.misses.sum()) > 1000
    _assert_stats_equal(got, ref, 1e-9)


@native
@pytest.mark.parametrize("dim", [2, 3])
def test_accumulate_edge_rays_every_kind(dim):
    """Hand-picked edge cases (grid lines, corners, outside, zero length) as HIT, SUB and
    SUP rays, with finite and infinite r_max."""
    spec, o, d, r = _geometry(dim)
    for r_min, r_max in LIMITS:
        rays = _all_kinds(o, d, r, r_min, r_max)
        for sub_rays in ("ignore", "hit"):
            ref = accumulate(spec, rays, sub_rays=sub_rays, backend="jax")
            got = accumulate(spec, rays, sub_rays=sub_rays, backend="native")
            _assert_stats_equal(got, ref, 1e-9)


_FLOAT32_SCRIPT = """
import jax, jax.numpy as jnp, numpy as np
assert not jax.config.jax_enable_x64
from lidarjax.rays import from_scan
from lidarjax.raytrace import GridSpec, accumulate, fold_rays, CellTerm
import jaxlie
rng = np.random.default_rng(7)
spec = GridSpec(np.zeros(2), 0.1, (120, 90))
assert spec.origin.dtype == jnp.float32
n = 800
u = lambda lo, hi, *shape: jnp.asarray(rng.uniform(lo, hi, shape), jnp.float32)
poses = jaxlie.SE2.from_xy_theta(u(1, 11, n), u(1, 8, n), u(-3, 3, n))
rays = from_scan(poses, jnp.linspace(-1.5, 1.5, 9), u(0, 7, n, 9), 0.3, 6.0)
assert rays.origins.dtype == jnp.float32
a = accumulate(spec, rays, backend="jax"); b = accumulate(spec, rays, backend="native")
assert b.lengths.dtype == jnp.float32
d_h = int(jnp.sum(a.hits != b.hits)); d_m = int(jnp.sum(a.misses != b.misses))
# float32 segment ends are ray parameters t <= L_max computed with a few roundings each,
# which XLA and C++ order differently (XLA turns some divisions into reciprocal products):
# allow 32 ulp(L_max) per segment (12 seen), i.e. per cell visits * 32 * eps * L_max
L_max = float(jnp.max(rays.flatten().mapping_lengths()))
bound = (a.hits + a.misses + 1) * 32 * jnp.finfo(jnp.float32).eps * L_max
rel = float(jnp.max(jnp.abs(a.lengths - b.lengths) / bound))
f = rays.flatten()
t = CellTerm.linear(slope=jnp.asarray(rng.uniform(0, 2, spec.shape), jnp.float32))
fa = fold_rays(spec, f.origins, f.directions, f.mapping_lengths(), t, backend="jax")
fb = fold_rays(spec, f.origins, f.directions, f.mapping_lengths(), t, backend="native")
cells = int(jnp.sum(jnp.any(fa.last_cell != fb.last_cell, axis=-1)))
# body sums term * segment over <= walk_bound cells: same per-segment allowance
body = float(jnp.max(jnp.abs(fa.body - fb.body)) / (2 * 210 * 32 * 1.2e-7 * L_max))
print(int(a.hits.sum()), int(a.misses.sum()), d_h, d_m, rel, cells, body)
"""


@native
@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_float32_kernels_match_jax_float32():
    """float32 (x64 disabled, in a subprocess): the float32 kernels give the JAX float32
    path's counts except where an ulp decides a boundary tie, and lengths to round-off."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, JAX_ENABLE_X64="0")
    out = subprocess.run(
        [sys.executable, "-c", _FLOAT32_SCRIPT],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    hits, misses, d_h, d_m, rel, cells, body = out.stdout.split()
    assert int(hits) > 1000 and int(misses) > 10000
    # identical counts (float32 ties resolved the same way) and lengths to float32 round-off
    assert int(d_h) == 0 and int(d_m) == 0, (d_h, d_m)
    assert float(rel) <= 1.0
    assert int(cells) == 0 and float(body) <= 1.0


def run_under_isas(script: str, tmp_path, *args: str) -> dict:
    """``{isa: arrays}``: ``script`` run in a subprocess with the baseline and with the AVX2
    native library (``LIDARJAX_NATIVE_ISA``), as ``python -c script PATH *args ISA``; it
    saves its arrays to ``PATH`` (``np.savez``)."""
    import os
    import subprocess
    import sys

    res = {}
    for isa in ("baseline", "avx2"):
        path = tmp_path / f"{isa}.npz"
        env = dict(os.environ, LIDARJAX_NATIVE_ISA=isa)
        out = subprocess.run(
            [sys.executable, "-c", script, str(path), *args, isa],
            capture_output=True,
            text=True,
            env=env,
            timeout=300,
        )
        assert out.returncode == 0, out.stderr[-3000:]
        res[isa] = dict(np.load(path))
    return res


_ISA_SCRIPT = """
import sys
import jax
jax.config.update("jax_enable_x64", sys.argv[2] == "f64")
import jax.numpy as jnp, numpy as np
from lidarjax.rays import RayBatch
from lidarjax.raytrace import CellTerm, GridSpec, _native, accumulate, fold_rays
assert _native.isa() == sys.argv[3], (_native.isa(), sys.argv[3])
dt = np.float64 if sys.argv[2] == "f64" else np.float32
rng = np.random.default_rng(11)
out = {}
for dim, shape in ((2, (70, 50)), (3, (24, 18, 10))):
    spec = GridSpec(np.full(dim, -0.5), 0.2, shape)
    n = 5000
    o = jnp.asarray(rng.uniform(-1.5, 9.0, (n, dim)), dt)
    d = jnp.asarray(rng.normal(size=(n, dim)), dt)
    d = d.at[:500, 1:].set(0.0)  # axis-parallel rays
    r = jnp.asarray(rng.uniform(0.0, 12.0, n), dt)
    kind = jnp.asarray(rng.integers(0, 3, n), jnp.int32)
    unit = d / jnp.linalg.norm(d, axis=1, keepdims=True)
    rays = RayBatch(o, unit, r, kind, jnp.asarray(0.3, dt), jnp.asarray(10.0, dt))
    st = accumulate(spec, rays, backend="native", threads=2)
    out[f"{dim}_h"], out[f"{dim}_m"], out[f"{dim}_r"] = st.hits, st.misses, st.lengths
    a = jnp.asarray(rng.uniform(0.0, 2.0, shape), dt)
    b = jnp.asarray(rng.uniform(0.1, 3.0, shape), dt)
    terms = {
        "lin": CellTerm.linear(slope=a, offset=b),
        "slope": CellTerm.linear(slope=a),
        "off": CellTerm.linear(offset=b),
        "gam": CellTerm.gamma(a, b),
    }
    assert sorted(t.mode for t in terms.values()) == [0, 1, 2, 3]
    for name, t in terms.items():
        f = fold_rays(spec, o, d, r, t, backend="native", threads=2)
        for k in ("body", "last_cell", "last_len", "grid_len", "any_valid"):
            out[f"{dim}_{name}_{k}"] = getattr(f, k)
np.savez(sys.argv[1], **{k: np.asarray(v) for k, v in out.items()})
"""


@native
@pytest.mark.skipif(_native.isa() != "avx2", reason="the AVX2 library is not in use here")
@pytest.mark.parametrize("dtype", ["f32", "f64"])
@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_avx2_and_baseline_libraries_agree(tmp_path, dtype):
    """The AVX2 build (8 float / 4 double ray lanes) and the baseline build (4 / 2 lanes),
    in subprocesses: per-ray folds bit-identical, hit/miss counts identical, per-cell
    lengths equal to round-off (rays add to a cell in a lane-width dependent order)."""
    res = run_under_isas(_ISA_SCRIPT, tmp_path, dtype)
    base, wide = res["baseline"], res["avx2"]
    assert base.keys() == wide.keys() and len(base) == 2 * (3 + 4 * 5)
    rtol = 1e-12 if dtype == "f64" else 1e-5
    for k in base:
        if k.endswith("_r"):
            np.testing.assert_allclose(wide[k], base[k], rtol=rtol, atol=rtol, err_msg=k)
        else:
            np.testing.assert_array_equal(wide[k], base[k], err_msg=k)
    assert base["2_h"].sum() > 500 and base["3_m"].sum() > 1000
    assert np.isfinite(base["2_gam_body"]).all() and np.abs(base["2_lin_body"]).sum() > 100


@native
@pytest.mark.slow
def test_accumulate_intel_log_identical_counts():
    """The Intel log at 0.1 m (real data): identical H and M, R within 1e-9 relative."""
    from lidarjax.datasets import fetch, load_carmen

    log = load_carmen(fetch("intel"))
    p = log.poses
    rays = from_scan(
        jaxlie.SE2.from_xy_theta(p[:, 0], p[:, 1], p[:, 2]),
        log.azimuths_rad,
        log.ranges_m,
        0.0,
        log.usable_range_m,
    )
    spec = GridSpec.covering(np.asarray(rays.endpoints()[rays.kind == HIT]), 0.1, margin=1.0)
    ref = accumulate(spec, rays, backend="jax")
    got = accumulate(spec, rays, backend="native", threads=2)
    _assert_stats_equal(got, ref, 1e-9)
    # a wider grid (the README's): counts may differ only through sliver segments at the
    # walk's tolerance (1-ulp differences of XLA's reciprocal rewrites); bound them
    wide = GridSpec.covering(log.poses[:, :2], 0.1, margin=20.0)
    ref = accumulate(wide, rays, backend="jax")
    got = accumulate(wide, rays, backend="native", threads=2)
    np.testing.assert_array_equal(np.asarray(got.hits), np.asarray(ref.hits))
    dm = np.abs(np.asarray(got.misses) - np.asarray(ref.misses))
    assert dm.sum() <= 1e-6 * float(ref.misses.sum()), dm.sum()
    np.testing.assert_allclose(
        np.asarray(got.lengths), np.asarray(ref.lengths), rtol=1e-9, atol=1e-9
    )


# --------------------------------------------------------------------------------------
# fold_rays and the grid models
# --------------------------------------------------------------------------------------


def _terms(shape, rng):
    t = jnp.asarray(rng.uniform(0.1, 2.0, shape))
    u = jnp.asarray(rng.uniform(0.1, 2.0, shape))
    return [
        CellTerm.linear(slope=t),
        CellTerm.linear(offset=jnp.log(t)),
        CellTerm.linear(offset=-t, slope=u),
        CellTerm.gamma(t, u),
        CellTerm.gamma(t, u.at[(0,) * len(shape)].set(0.0)),  # improper cell: -inf
    ]


@native
@pytest.mark.parametrize("dim", [2, 3])
def test_fold_every_term_matches_jax(dim):
    rng = np.random.default_rng(11)
    spec, o, d, r = _geometry(dim, n_random=150)
    r = np.concatenate([r[:-5], [np.inf] * 5])  # some rays traced to the border
    args = (spec, jnp.asarray(o), jnp.asarray(d), jnp.asarray(r))
    for term in _terms(spec.shape, rng):
        ref = fold_rays(*args, term, backend="jax")
        got = fold_rays(*args, term, backend="native")
        for name in ("last_cell", "any_valid"):
            np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=name)
        for name in ("body", "last_len", "grid_len", "t_start", "t_end"):
            _assert_same(getattr(got, name), getattr(ref, name))


@native
@pytest.mark.parametrize(
    ("dim", "limits"),
    [(2, LIMITS[0]), (2, LIMITS[1]), (2, LIMITS[2]), (3, LIMITS[0]), (3, LIMITS[1])],
    ids=["2d-finite", "2d-rmin0_rmaxinf", "2d-short_rmax", "3d-finite", "3d-rmin0_rmaxinf"],
)
@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_every_grid_model_native_matches_jax(dim, limits):
    spec, o, d, r = _geometry(dim, n_random=60)
    rays = _all_kinds(o, d, r, *limits)
    for name, m in _maps(spec).items():
        ref = batch_log_likelihood(m, rays, backend="jax")
        got = batch_log_likelihood(m, rays, backend="native")
        assert np.isfinite(np.asarray(ref)).sum() > 0, name
        _assert_same(got, ref)


@native
def test_native_inside_jit_vmap_and_scan():
    spec, o, d, r = _geometry(2, n_random=50)
    m = _maps(spec)["decay"]
    rays = _all_kinds(o, d, r, 0.4, 4.0)
    ref = batch_log_likelihood(m, rays, backend="jax")

    jitted = jax.jit(lambda m, rays: batch_log_likelihood(m, rays, backend="native"))
    _assert_same(jitted(m, rays), ref)

    def rebuild(o, d, r, k):
        return RayBatch(
            origins=o, directions=d, ranges=r, kind=k, r_min=rays.r_min, r_max=rays.r_max
        )

    parts = (rays.origins, rays.directions, rays.ranges, rays.kind)
    # vmap over the leading (kind) axis of the rays and over a batch of maps
    vm = jax.vmap(lambda *a: batch_log_likelihood(m, rebuild(*a), backend="native"))(*parts)
    _assert_same(vm, ref)
    maps2 = jax.tree.map(lambda a: jnp.stack([a, 2 * a]), m)
    vmm = jax.vmap(lambda mm: batch_log_likelihood(mm, rays, backend="native"))(maps2)
    _assert_same(vmm[0], ref)
    m2 = jax.tree.map(lambda a: a[1], maps2)
    _assert_same(vmm[1], batch_log_likelihood(m2, rays, backend="jax"))

    # lax.scan over the three kinds; accumulate inside the scan body too
    def body(c, a):
        rr = rebuild(*a)
        st = accumulate(spec, rr, backend="native")
        return c + jnp.sum(st.hits, dtype=jnp.int32), batch_log_likelihood(m, rr, backend="native")

    total, out = jax.lax.scan(body, jnp.asarray(0, jnp.int32), parts)
    _assert_same(out, ref)
    ref_hits = sum(
        int(accumulate(spec, rebuild(*(x[k] for x in parts)), backend="jax").hits.sum())
        for k in range(3)
    )
    assert int(total) == ref_hits > 0


@native
@pytest.mark.slow  # > 4 s: runs in make test-slow / CI
def test_scan_model_native_in_particle_filter_step():
    """The particle filter's measurement model gives the same weights on both paths."""
    from lidarjax.localization import ScanModel
    from lidarjax.maps import decay_rate_map

    rng = np.random.default_rng(3)
    spec = GridSpec([-2.0, -2.0], 0.1, (40, 40))
    st = accumulate(spec, _random_batch(rng, spec, 2000), backend="jax")
    az = jnp.linspace(-1.5, 1.5, 30)
    parts = jaxlie.SE2.from_xy_theta(
        jnp.asarray(rng.uniform(-1, 1, 64)),
        jnp.asarray(rng.uniform(-1, 1, 64)),
        jnp.asarray(rng.uniform(-3, 3, 64)),
    )
    z = jnp.asarray(rng.uniform(0.1, 3.0, 30))
    m = decay_rate_map(st)
    ref = ScanModel(m, az, 0.2, 2.5, ray_floor=-10.0, backend="jax")(parts, z)
    model = ScanModel(m, az, 0.2, 2.5, ray_floor=-10.0, backend="native")
    got = eqx.filter_jit(model)(parts, z)
    np.testing.assert_allclose(np.asarray(got), np.asarray(ref), rtol=1e-9)


# --------------------------------------------------------------------------------------
# Backend selection, fallback, staleness
# --------------------------------------------------------------------------------------


def test_backend_argument_is_checked():
    spec, o, d, r = _geometry(2, n_random=3)
    rays = _all_kinds(o, d, r, 0.4, 4.0)
    with pytest.raises(ValueError, match="backend"):
        accumulate(spec, rays, backend="cuda")
    with pytest.raises(ValueError, match="backend"):
        batch_log_likelihood(_maps(spec)["decay"], rays, backend="fast")
    with pytest.raises(ValueError, match="threads"):
        accumulate(spec, rays, threads=0)
    with pytest.raises(ValueError, match="CellTerm"):
        fold_rays(
            spec,
            jnp.asarray(o),
            jnp.asarray(d),
            jnp.asarray(r),
            lambda cells, lengths: lengths,
            backend="native",
        )
    with pytest.raises(ValueError, match="mode"):
        CellTerm(jnp.ones((1, 3, 3)), 7)
    with pytest.raises(ValueError, match="tables"):
        CellTerm(jnp.ones((2, 3, 3)), 1)


def test_auto_falls_back_with_one_warning(monkeypatch):
    monkeypatch.setattr(
        _native, "_state", {"loaded": False, "reason": "test: not built", "warned": False}
    )
    spec, o, d, r = _geometry(2, n_random=20)
    rays = _all_kinds(o, d, r, 0.4, 4.0)
    with pytest.warns(RuntimeWarning, match="test: not built"):
        a = accumulate(spec, rays)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        b = accumulate(spec, rays)  # warned once only
    _assert_stats_equal(a, b, 0.0)
    with pytest.raises(RuntimeError, match="test: not built"):
        accumulate(spec, rays, backend="native")
    monkeypatch.setenv("LIDARJAX_BACKEND", "jax")
    assert _native.resolve("auto") == "jax"
    monkeypatch.setenv("LIDARJAX_BACKEND", "bogus")
    with pytest.raises(ValueError, match="LIDARJAX_BACKEND"):
        _native.resolve("auto")


def test_stale_library_is_not_used(monkeypatch, tmp_path):
    """A changed C++ source makes the built library stale (the build reruns)."""
    src = tmp_path / "walk.cc"
    src.write_text("// changed\n")
    monkeypatch.setattr(_build, "SOURCES", [src])
    assert not _build.up_to_date()


@pytest.mark.skipif(not HAVE_COMPILER, reason="no C++ compiler")
def test_build_without_compiler_is_optional(monkeypatch, capsys):
    monkeypatch.setattr(_build, "compiler", lambda: None)
    monkeypatch.setattr(_build, "up_to_date", lambda: False)
    assert _build.main(["--optional"]) == 0
    assert "pure-JAX path" in capsys.readouterr().err
    assert _build.main([]) == 1


def test_build_flags_are_portable():
    assert not any("march" in f for f in _build.BASE_FLAGS)
    assert "-ffp-contract=off" in _build.BASE_FLAGS
    assert shutil.which("true")  # the test itself must be able to fail on a bad flag list


# --------------------------------------------------------------------------------------
# Never hang
# --------------------------------------------------------------------------------------


@native
@pytest.mark.parametrize("bad", ["nan_dir", "inf_origin", "nan_length"])
@pytest.mark.parametrize("jit", [False, True])
def test_native_rejects_non_finite_rays(bad, jit):
    spec = GridSpec([0.0, 0.0], 0.1, (50, 60))
    o = np.array([[1.0, 1.0], [1.0, 2.0]])
    d = np.array([[1.0, 0.0], [0.6, 0.8]])
    r = np.array([3.0, 3.0])
    if bad == "nan_dir":
        d[1, 0] = np.nan
    elif bad == "inf_origin":
        o[0, 1] = np.inf
    else:
        r[1] = np.nan

    def run(o, d, r):
        rays = RayBatch(
            origins=o,
            directions=d,
            ranges=r,
            kind=jnp.asarray([HIT, HIT], jnp.int32),
            r_min=jnp.asarray(0.0),
            r_max=jnp.asarray(10.0),
        )
        return accumulate(spec, rays, backend="native").hits

    fn = jax.jit(run) if jit else run
    with pytest.raises(Exception, match="finite|NaN"):
        jax.block_until_ready(fn(jnp.asarray(o), jnp.asarray(d), jnp.asarray(r)))
    term = CellTerm.linear(slope=jnp.ones(spec.shape))
    fold = lambda o, d, r: fold_rays(spec, o, d, r, term, backend="native").body  # noqa: E731
    fn = jax.jit(fold) if jit else fold
    with pytest.raises(Exception, match="finite|NaN"):
        jax.block_until_ready(fn(jnp.asarray(o), jnp.asarray(d), jnp.asarray(r)))


@native
def test_kernel_validates_rays_itself():
    """Called directly (no JAX-side checks), the kernels reject a NaN direction with an
    error naming the first bad ray instead of walking it (a walk of finite rays always
    ends within walk_bound steps; the kernels enforce that bound too)."""
    spec = GridSpec([0.0, 0.0], 0.1, (50, 60))
    o = jnp.asarray([[1.0, 1.0], [2.0, 2.0]])
    d = jnp.asarray([[1.0, 0.0], [math.nan, 0.5]])
    r = jnp.asarray([3.0, 3.0])
    kind = jnp.asarray([HIT, HIT], jnp.int32)
    with pytest.raises(Exception, match=r"directions must be finite.*first bad ray: 1"):
        jax.block_until_ready(_native.accumulate(spec, o, d, r, kind, 10.0, False, 1)[0])
    tab = jnp.ones((1, *spec.shape))
    with pytest.raises(Exception, match=r"directions must be finite.*first bad ray: 1"):
        jax.block_until_ready(_native.fold(spec, 1, tab, o, d, r, 1)[0])
    with pytest.raises(Exception, match=r"lengths must be >= 0.*first bad ray: 0"):
        jax.block_until_ready(_native.fold(spec, 1, tab, o, o, -r, 1)[0])


@native
def test_tiny_direction_component_float32():
    """A direction component of 1e-37 with 100 m cells in float32 ends (it used to spin)."""
    spec = GridSpec(jnp.zeros(2, jnp.float32), 100.0, (5, 6))
    rays = RayBatch(
        origins=jnp.asarray([[1.0, 1.0]], jnp.float32),
        directions=jnp.asarray([[1.0, 1e-37]], jnp.float32),
        ranges=jnp.asarray([300.0], jnp.float32),
        kind=jnp.asarray([HIT], jnp.int32),
        r_min=jnp.asarray(0.0, jnp.float32),
        r_max=jnp.asarray(1000.0, jnp.float32),
    )
    for backend in ("native", "jax"):
        st = accumulate(spec, rays, backend=backend)
        assert int(st.hits[3, 0]) == 1 and int(st.misses[:3, 0].sum()) == 3
        np.testing.assert_allclose(float(st.lengths.sum()), 300.0, rtol=1e-6)
