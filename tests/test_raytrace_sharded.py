"""Rays split over devices (``accumulate_sharded``), grids split in row tiles over devices
(``accumulate_tiled``), poses split over devices (``log_likelihood_at_poses_sharded``) and
the DCT objective's ray sums per device (``dct_objective_sharded``).

JAX fixes its devices when it starts, so the 2-device runs happen in one fresh process with
``XLA_FLAGS=--xla_force_host_platform_device_count=2`` (the 2 host devices of one CPU); the
main process (one device) checks 1-device meshes and the argument errors."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import run_on_host_devices
from jax.sharding import Mesh

from lidarjax.maps import dct_objective_sharded
from lidarjax.rays import HIT, SUB, SUP, RayBatch
from lidarjax.raytrace import (
    GridSpec,
    accumulate,
    accumulate_sharded,
    accumulate_tiled,
    device_mesh,
)
from lidarjax.sensor_models import log_likelihood_at_poses_sharded

ROOT = Path(__file__).resolve().parents[1]

# float32 lengths summed in another order: |dR| <= R_TOL * max(1 m, R) (~80 ulps)
R_TOL = 1e-5

SCRIPT = r"""
import json, re
import optimistix as optx
import numpy as np
import jax, jax.numpy as jnp, jaxlie
from jax.sharding import NamedSharding, PartitionSpec as P
import lidarjax
from lidarjax import maps
from lidarjax.rays import RayBatch, HIT, SUB, SUP, from_scan
from lidarjax.raytrace import (
    GridSpec, GridStats, accumulate, accumulate_sharded, accumulate_tiled, device_mesh,
    _native, _sharded,
)
from lidarjax.maps import dct_objective_sharded, fit_dct_sharded
from lidarjax.sensor_models import log_likelihood_at_poses, log_likelihood_at_poses_sharded
from lidarjax.sensor_models import _sharded as _sm_sharded
from lidarjax.sim import make_office, simulate_scans

lidarjax.enable_compilation_cache()
R_TOL = __R_TOL__
out = {"devices": len(jax.devices()), "native": bool(_native.available())}
N = 2001  # odd: the sharded runs pad one ray
SHAPE = (40, 30)


def random_rays(seed, spec, n=N, dim=2):
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(spec.origin), np.asarray(spec.upper)
    o = rng.uniform(lo - 1, hi + 1, (n, dim)).astype(np.float32)
    d = rng.normal(size=(n, dim))
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    r = rng.uniform(0, 6, n).astype(np.float32)
    u = rng.uniform(size=n)
    k = np.where(u < 0.2, SUP, np.where(u < 0.3, SUB, HIT)).astype(np.int32)
    return RayBatch(o, d, r, k, 0.5, 5.0)


def dyadic_rays(seed):
    # axis-aligned rays, dyadic origins and ranges, 0.25 m cells at the origin: every
    # segment length and every partial sum is exact in float32, in any order
    rng = np.random.default_rng(seed)
    o = (rng.integers(-8, 48, (N, 2)) / 4).astype(np.float32)
    axis = rng.integers(0, 2, N)
    sign = rng.choice([-1.0, 1.0], N)
    d = np.zeros((N, 2), np.float32)
    d[np.arange(N), axis] = sign
    r = (rng.integers(0, 48, N) / 8).astype(np.float32)
    k = np.where(rng.uniform(size=N) < 0.2, SUP, HIT).astype(np.int32)
    return RayBatch(o, d, r, k, 0.0, 5.0)


def compare(one, two):
    h1, m1, r1 = (np.asarray(x) for x in (one.hits, one.misses, one.lengths))
    h2, m2, r2 = (np.asarray(x) for x in (two.hits, two.misses, two.lengths))
    err = np.abs(r2 - r1) / np.maximum(1.0, np.abs(r1))
    return {
        "hits_equal": bool(np.array_equal(h1, h2)) and h2.dtype == h1.dtype,
        "misses_equal": bool(np.array_equal(m1, m2)) and m2.dtype == m1.dtype,
        "lengths_rel_err": float(err.max()),
        "lengths_bitwise": bool(np.array_equal(r1, r2)) and r2.dtype == r1.dtype,
        "n_hits": int(h1.sum()),
        "n_misses": int(m1.sum()),
    }


def layout(x):
    return {
        "spec": [a for a in x.sharding.spec],
        "n_devices": len(x.sharding.device_set),
        "shards": sorted(list(s.data.shape) for s in x.addressable_shards),
    }


def collectives(hlo):
    return {
        op: len(re.findall(r"= [^=]*? %s(-start)?\(" % op, hlo))
        for op in ("all-gather", "all-reduce", "collective-permute", "all-to-all",
                   "reduce-scatter", "collective-broadcast")
    }


spec = GridSpec(np.array([-1.03, -2.17]), 0.1, SHAPE)
rays = random_rays(0, spec)
dy_spec = GridSpec(np.zeros(2), 0.25, SHAPE)
dy_rays = dyadic_rays(1)
backends = ["native", "jax"] if out["native"] else ["jax"]
for be in backends:
    for sub in ("ignore", "hit") if be == "native" else ("hit",):
        one = accumulate(spec, rays, backend=be, sub_rays=sub)
        two = accumulate_sharded(spec, rays, backend=be, sub_rays=sub)
        out[f"sharded_{be}_{sub}"] = {**compare(one, two), "layout": layout(two.hits)}
    one = accumulate(dy_spec, dy_rays, backend=be)
    two = accumulate_sharded(dy_spec, dy_rays, backend=be)
    out[f"dyadic_{be}"] = compare(one, two)
    args, kwargs = _sharded._sharded_inputs(spec, rays, None, 1024, "hit", be, None)
    hlo = _sharded._sharded_program.program.lower(*args, **kwargs).lowered.compile().as_text()
    out[f"collectives_sharded_{be}"] = collectives(hlo)
    out[f"padded_rays_{be}"] = int(args[1].shape[0])
    out[f"callbacks_sharded_{be}"] = hlo.count("callback")
    # more rays than float32 counts hold exactly (forced): counts travel as 2 digits
    r2, m2, h2 = _sharded._sharded_program(*args, **dict(kwargs, max_count=2**31 - 1))
    ref = accumulate(spec, rays, backend=be, sub_rays="hit")
    out[f"digits_{be}"] = bool(
        np.array_equal(np.asarray(m2), np.asarray(ref.misses))
        and np.array_equal(np.asarray(h2), np.asarray(ref.hits))
    )

# only padding rays contribute nothing (both SUB modes, both backends)
pad = RayBatch(*_sharded._pad_rays(spec, *(np.zeros((0, 2), np.float32),) * 2,
                                   np.zeros(0, np.float32), np.zeros(0, np.int32), 5),
               0.5, 5.0)
out["padding_zero"] = all(
    int(np.abs(np.asarray(s.hits)).sum() + np.abs(np.asarray(s.misses)).sum()) == 0
    and float(np.abs(np.asarray(s.lengths)).sum()) == 0.0
    for be in backends for sub in ("ignore", "hit")
    for s in [accumulate(spec, pad, backend=be, sub_rays=sub)]
)

# tiles: the untiled JAX accumulate is the reference
one = accumulate(spec, rays, backend="jax", sub_rays="hit")
whole = accumulate_tiled(spec, rays, sub_rays="hit", ray_chunk=None)
out["tiled_one_chunk"] = {**compare(one, whole), "layout": layout(whole.lengths)}
chunked = accumulate_tiled(spec, rays, sub_rays="hit", ray_chunk=700)  # 3 chunks, padded
out["tiled_chunks"] = {**compare(one, chunked), "layout": layout(chunked.misses)}
out["tiled_dyadic"] = compare(accumulate(dy_spec, dy_rays, backend="jax"),
                              accumulate_tiled(dy_spec, dy_rays, ray_chunk=700))
spec3 = GridSpec(np.array([-0.51, -0.3, 0.07]), 0.2, (8, 6, 4))
rays3 = random_rays(2, spec3, n=301, dim=3)
t3 = accumulate_tiled(spec3, rays3)
out["tiled_3d"] = {**compare(accumulate(spec3, rays3, backend="jax"), t3),
                   "layout": layout(t3.hits)}
mesh = device_mesh("tiles")
acc = tuple(jax.device_put(np.zeros(SHAPE, dt), NamedSharding(mesh, P("tiles", None)))
            for dt in (np.float32, np.int32, np.int32))
rep = NamedSharding(mesh, P())
inputs = (jax.device_put(spec, rep),
          *(jax.device_put(np.asarray(x), rep) for x in (rays.origins, rays.directions,
                                                         rays.ranges, rays.kind)),
          jax.device_put(np.asarray(rays.r_max), rep))
hlo = _sharded._tiled_program.lower(inputs, acc, mesh=mesh, sub_as_hit=True,
                                    chunk_size=1024).lowered.compile().as_text()
out["collectives_tiled"] = collectives(hlo)
out["callbacks_tiled"] = hlo.count("callback")
try:
    accumulate_tiled(GridSpec(np.zeros(2), 0.1, (41, 30)), rays)
    out["odd_rows"] = None
except ValueError as e:
    out["odd_rows"] = str(e)

# likelihood at poses: poses split, no collective
world = make_office(0)
poses = world.trajectory(8, jitter_m=0.2, seed=0)
az = np.linspace(-np.pi / 2, np.pi / 2, 31)
ranges = simulate_scans(world, poses, az, max_range_m=10.0, noise_sigma_m=0.01, seed=0)
T_ws = jaxlie.SE2.from_xy_theta(poses[:, 0], poses[:, 1], poses[:, 2])
ospec = GridSpec.from_bounds(world.bounds[0] - 0.5, world.bounds[1] + 0.5, 0.2)
orays = from_scan(T_ws, az, ranges, 0.05, 10.0)
st = accumulate(ospec, orays)
# a smoothed map (every rate > 0): finite log-likelihoods at perturbed poses
dm = maps.decay_rate_map(GridStats(ospec, st.hits + 1, st.misses, st.lengths + 1.0))
test_poses = poses + np.random.default_rng(3).normal(0, 0.05, poses.shape)
kw = dict(r_min=0.05, r_max=10.0, chunk_size=4)
ll1 = np.asarray(log_likelihood_at_poses(dm, az, ranges[0], test_poses[:7], **kw))
ll2 = log_likelihood_at_poses_sharded(dm, az, ranges[0], test_poses[:7], **kw)  # 7: padded
even = log_likelihood_at_poses_sharded(dm, az, ranges[0], test_poses, **kw)  # same program
out["poses"] = {
    "max_rel_diff": float(np.max(np.abs(np.asarray(ll2) - ll1) / np.abs(ll1))),
    "max_rel_diff_even": float(np.max(np.abs(np.asarray(even)[:7] - ll1) / np.abs(ll1))),
    "n_finite": int(np.sum(np.isfinite(ll1))),
    "shape": list(ll2.shape),
    "layout": layout(even),
}
args, kwargs = _sm_sharded._poses_inputs(dm, az, ranges[0], test_poses, None, 0.05, 10.0, 4, None)
kwargs.pop("n_pad")
hlo = _sm_sharded._poses_program.lower(*args, **kwargs).lowered.compile().as_text()
out["collectives_poses"] = collectives(hlo)

# the DCT objective's ray sums, one ray group per device (every ray of the office scans
# has evidence in the box: HIT end points inside it, SUP rays start inside it)
lower = np.asarray(world.bounds[0]) - 0.5
extent = np.asarray(world.bounds[1]) - np.asarray(world.bounds[0]) + 1.0
flat = orays.flatten()
kind = np.asarray(flat.kind).copy()
rng_ = np.asarray(flat.ranges).copy()
kind[::9], rng_[::9] = SUB, 0.02  # some SUB rays (below r_min = 0.05 m)
drays = RayBatch(flat.origins, flat.directions, rng_, kind, flat.r_min, flat.r_max)
o1 = maps.dct_objective(drays, lower, extent, (6, 6), check=False)
o2 = dct_objective_sharded(drays, lower, extent, (6, 6), check=False)
coeffs = jnp.asarray(np.random.default_rng(4).normal(0, 0.3, (6, 6)), jnp.float32).at[0, 0].set(2.0)
# the fit on the office rays in float64 from the same start (non-square cells: no grid
# start): in float32 the L-BFGS path on this small problem depends on rounding (the
# bucketed and the plain objective, equal to 1e-7, end in different local optima)
with jax.enable_x64(True):
    flat64 = RayBatch(*(np.asarray(x, np.float64) for x in (flat.origins, flat.directions,
                                                           flat.ranges)),
                      np.asarray(flat.kind), float(flat.r_min), float(flat.r_max))
    start = maps.DCTMap(jnp.asarray(coeffs, jnp.float64), lower, extent)
    m1, s1 = maps.fit_dct(flat64, init=start, rtol=1e-9, atol=1e-9)
    m2, s2 = fit_dct_sharded(flat64, init=start, rtol=1e-9, atol=1e-9)
    o_flat = maps.dct_objective(flat64, lower, extent, (6, 6), check=False)
    out["dct_fit"] = {
        "max_diff": float(np.max(np.abs(np.asarray(m1.coeffs) - np.asarray(m2.coeffs)))),
        "max_coeff": float(np.max(np.abs(np.asarray(m1.coeffs)))),
        "ll": [float(o_flat(m1.coeffs)), float(o_flat(m2.coeffs))],
        "steps": [int(s1.stats["num_steps"]), int(s2.stats["num_steps"])],
        "ok": [bool(s1.result == optx.RESULTS.successful),
               bool(s2.result == optx.RESULTS.successful)],
        "dtype": str(m2.coeffs.dtype),
    }
out["dct"] = {
    "n_rays": [o1.n_rays, o2.n_rays, int(kind.size)],
    "sub_equal": bool(np.array_equal(np.asarray(o1.w_sub), np.asarray(o2.w_sub))),
    "hits_equal": bool(np.array_equal(np.asarray(o1.hit_points), np.asarray(o2.hit_points))),
    "n_sub": int(o1.w_sub.shape[0]),
    "w_free_rel": float(np.max(np.abs(np.asarray(o2.w_free) - np.asarray(o1.w_free)))
                        / float(np.max(np.abs(np.asarray(o1.w_free))))),
    "value": [float(o1(coeffs)), float(o2(coeffs))],
}
print("RESULT " + json.dumps(out))
""".replace("__R_TOL__", repr(R_TOL))


@pytest.fixture(scope="module")
def two_devices() -> dict:
    return run_on_host_devices(SCRIPT, ROOT)


def _backends(r: dict) -> list[str]:
    return ["native", "jax"] if r["native"] else ["jax"]


def _counts_equal_lengths_close(c: dict) -> None:
    assert c["hits_equal"] and c["misses_equal"], c
    assert c["lengths_rel_err"] <= R_TOL, c
    assert c["n_hits"] > 0 and c["n_misses"] > 0  # the comparison is not vacuous


def test_sharded_accumulate_equals_one_device(two_devices):
    r = two_devices
    assert r["devices"] == 2
    for be in _backends(r):
        for sub in ("ignore", "hit") if be == "native" else ("hit",):
            c = r[f"sharded_{be}_{sub}"]
            _counts_equal_lengths_close(c)
            lay = c["layout"]  # replicated on both devices
            assert lay["spec"] == [] and lay["n_devices"] == 2
            assert lay["shards"] == [[40, 30], [40, 30]]


def test_sharded_accumulate_dyadic_lengths_exact(two_devices):
    for be in _backends(two_devices):
        c = two_devices[f"dyadic_{be}"]
        assert c["hits_equal"] and c["misses_equal"] and c["lengths_bitwise"], c
        assert c["n_hits"] > 0 and c["n_misses"] > 0


def test_counts_split_into_digits_stay_exact(two_devices):
    for be in _backends(two_devices):
        assert two_devices[f"digits_{be}"]


def test_count_digits_pack_unpack_exact():
    """Counts near 2**31 survive the float32 packing and a 2-device sum exactly."""
    from lidarjax.raytrace import _sharded

    bits, pieces = _sharded._count_digits(jnp.float32, 2, 2**31 - 1)
    assert pieces == 2 and 2 * (2**bits - 1) < 2**24
    assert _sharded._count_digits(jnp.float32, 2, 2**24 - 1) == (31, 1)
    big = np.array([0, 1, 2**23 - 1, 2**23, 2**30 - 7, 123456789], np.int32)
    parts = [
        _sharded._pack(
            (jnp.ones(6, jnp.float32), jnp.asarray(c), jnp.asarray(c[::-1])),
            jnp.zeros(1, bool),
            bits,
            pieces,
            jnp.float32,
        )
        for c in (big, big // 3)
    ]
    (r, m, h), flags = _sharded._unpack(parts[0] + parts[1], (6,), 1, bits, pieces)
    np.testing.assert_array_equal(np.asarray(m), big + big // 3)
    np.testing.assert_array_equal(np.asarray(h), (big + big // 3)[::-1])
    np.testing.assert_array_equal(np.asarray(r), 2.0)
    assert not bool(flags[0])


def test_odd_ray_count_is_padded_with_rays_that_contribute_nothing(two_devices):
    for be in _backends(two_devices):
        assert two_devices[f"padded_rays_{be}"] == 2002  # 2001 rays + 1 padding ray
    assert two_devices["padding_zero"]


def test_one_collective_per_program(two_devices):
    """The sharded accumulate's only collective is one all-reduce (counts, lengths and
    check flags packed in one array); tiles and poses need none. Several independent
    collectives per program can deadlock XLA's CPU runtime on a small thread pool."""
    for be in _backends(two_devices):
        counts = two_devices[f"collectives_sharded_{be}"]
        assert counts["all-reduce"] == 1 and sum(counts.values()) == 1, counts
        assert two_devices[f"callbacks_sharded_{be}"] == 0  # checks are flags, not callbacks
    for name in ("collectives_tiled", "collectives_poses"):
        assert sum(two_devices[name].values()) == 0, (name, two_devices[name])
    assert two_devices["callbacks_tiled"] == 0


@pytest.mark.parametrize("name", ["tiled_one_chunk", "tiled_chunks"])
def test_tiled_equals_untiled(two_devices, name):
    c = two_devices[name]
    _counts_equal_lengths_close(c)
    lay = c["layout"]  # each device holds half the rows
    assert lay["spec"] == ["tiles", None] and lay["n_devices"] == 2
    assert lay["shards"] == [[20, 30], [20, 30]]


def test_tiled_one_chunk_lengths_bitwise(two_devices):
    """One ray chunk: the tile walk adds in the order of the untiled JAX walk."""
    assert two_devices["tiled_one_chunk"]["lengths_bitwise"]
    c = two_devices["tiled_dyadic"]
    assert c["hits_equal"] and c["misses_equal"] and c["lengths_bitwise"], c


def test_tiled_3d(two_devices):
    c = two_devices["tiled_3d"]
    _counts_equal_lengths_close(c)
    assert c["layout"]["spec"] == ["tiles", None, None]
    assert c["layout"]["shards"] == [[4, 6, 4], [4, 6, 4]]


def test_tiled_rows_not_divisible_raises(two_devices):
    msg = two_devices["odd_rows"]
    assert msg is not None and "spec.shape[0] = 41" in msg and "(2)" in msg


def test_likelihood_at_poses_sharded(two_devices):
    """Poses split over the devices: the same walks per pose; the sum over a pose's 31
    rays may be fused differently by XLA (measured: 1 ulp), so float32 rounding."""
    p = two_devices["poses"]
    assert p["shape"] == [7] and p["n_finite"] == 7
    assert p["max_rel_diff"] <= 1e-6 and p["max_rel_diff_even"] <= 1e-6, p
    lay = p["layout"]
    assert lay["spec"] == ["rays"] and lay["shards"] == [[4], [4]]


def test_fit_dct_sharded_matches_fit_dct(two_devices):
    """The fit from the per-device ray sums: both solves succeed and reach the same
    log-likelihood (the objectives differ by float rounding of w_free only)."""
    d = two_devices["dct_fit"]
    assert d["steps"][0] > 1 and d["steps"][1] > 1  # the solves moved
    d = two_devices["dct_fit"]
    assert all(d["ok"])
    ll1, ll2 = d["ll"]
    assert d["dtype"] == "float64"
    assert abs(ll2 - ll1) <= 1e-8 * abs(ll1), d
    assert d["max_diff"] <= 1e-4 * d["max_coeff"], d


def test_dct_objective_sharded(two_devices):
    d = two_devices["dct"]
    assert d["n_rays"][0] == d["n_rays"][1] == d["n_rays"][2] > 0
    assert d["sub_equal"] and d["hits_equal"] and d["n_sub"] > 0
    assert d["w_free_rel"] <= 1e-5, d
    v1, v2 = d["value"]
    assert abs(v1 - v2) <= 1e-5 * abs(v1), d


# ---------------------------------------------------------------- main process: 1 device


def _rays(n: int = 301) -> tuple[GridSpec, RayBatch]:
    rng = np.random.default_rng(0)
    spec = GridSpec(np.array([-1.03, -2.17]), 0.1, (20, 16))
    o = rng.uniform(-1.5, 1.5, (n, 2))
    a = rng.uniform(-np.pi, np.pi, n)
    d = np.stack([np.cos(a), np.sin(a)], 1)
    k = rng.choice([HIT, SUB, SUP], n)
    return spec, RayBatch(o, d, rng.uniform(0, 3, n), k, 0.2, 2.5)


def test_one_device_mesh_equals_accumulate():
    spec, rays = _rays()
    mesh = device_mesh()
    one = accumulate(spec, rays, backend="jax")
    for stats in (
        accumulate_sharded(spec, rays, mesh, backend="jax"),
        accumulate_tiled(spec, rays, device_mesh("tiles"), ray_chunk=100),
    ):
        np.testing.assert_array_equal(np.asarray(stats.hits), np.asarray(one.hits))
        np.testing.assert_array_equal(np.asarray(stats.misses), np.asarray(one.misses))
        np.testing.assert_allclose(
            np.asarray(stats.lengths), np.asarray(one.lengths), rtol=R_TOL, atol=R_TOL
        )
        assert int(np.asarray(stats.misses).sum()) > 0


def test_bad_arguments_raise_naming_them():
    spec, rays = _rays(11)
    for fn in (accumulate_sharded, accumulate_tiled):
        with pytest.raises(ValueError, match="mesh must be a jax.sharding.Mesh"):
            fn(spec, rays, object())
        flat = Mesh(np.asarray(jax.devices()[:1], dtype=object).reshape(1, 1), ("a", "b"))
        with pytest.raises(ValueError, match="mesh must be 1-D"):
            fn(spec, rays, flat)
        with pytest.raises(ValueError, match="rays must be a RayBatch"):
            fn(spec, rays.origins)
        with pytest.raises(ValueError, match="spec must be a GridSpec"):
            fn(None, rays)
        with pytest.raises(ValueError, match="sub_rays"):
            fn(spec, rays, sub_rays="miss")
    with pytest.raises(ValueError, match="ray_chunk"):
        accumulate_tiled(spec, rays, ray_chunk=0)
    with pytest.raises(ValueError, match="backend"):
        accumulate_sharded(spec, rays, backend="gpu")
    with pytest.raises(ValueError, match="axis_name"):
        device_mesh("")


def test_nan_ray_raises_through_the_sharded_walk():
    """The JAX walk's run-time checks travel in the packed sum / the replicated flags."""
    spec, rays = _rays(11)
    bad = RayBatch._trusted(
        origins=jnp.asarray(rays.origins).at[3, 0].set(jnp.nan),
        directions=rays.directions,
        ranges=rays.ranges,
        kind=jnp.full(11, HIT),
        r_min=rays.r_min,
        r_max=rays.r_max,
    )
    with pytest.raises(Exception, match="origins must be finite"):
        accumulate_sharded(spec, bad, backend="jax")
    with pytest.raises(Exception, match="origins must be finite"):
        accumulate_tiled(spec, bad)


def test_one_device_mesh_poses_and_dct():
    """The pose-split likelihood and the per-device DCT objective on a 1-device mesh."""
    from lidarjax import maps
    from lidarjax.sensor_models import log_likelihood_at_poses

    def model(rays):  # a callable model: fn(rays) -> [*batch]
        return -0.5 * jnp.sum(rays.endpoints() ** 2, axis=-1)

    az = np.linspace(-1.0, 1.0, 5)
    rng = np.array([1.0, 2.0, 1.5, 3.0, 2.5])
    poses = np.array([[0.0, 0.0, 0.0], [0.5, -0.2, 0.3], [1.0, 1.0, -0.5]])
    ll = log_likelihood_at_poses_sharded(model, az, rng, poses, device_mesh(), r_max=5.0)
    ref = log_likelihood_at_poses(model, az, rng, poses, r_max=5.0)
    np.testing.assert_allclose(np.asarray(ll), np.asarray(ref), rtol=1e-6)
    with pytest.raises(ValueError, match="mesh must be a jax.sharding.Mesh"):
        log_likelihood_at_poses_sharded(model, az, rng, poses, mesh="cpu")
    with pytest.raises(ValueError, match="model must be"):
        log_likelihood_at_poses_sharded(3, az, rng, poses)

    _, rays = _rays(40)
    flat = rays.flatten()
    kind = np.where(np.asarray(flat.kind) == SUB, SUB, HIT)
    rays = RayBatch(flat.origins, flat.directions, flat.ranges, kind, 0.2, 2.5)
    lower, extent = np.array([-5.0, -5.0]), np.array([10.0, 10.0])
    o1 = maps.dct_objective(rays, lower, extent, (3, 3), check=False)
    o2 = dct_objective_sharded(rays, lower, extent, (3, 3), device_mesh(), check=False)
    assert o2.n_rays == o1.n_rays == 40
    np.testing.assert_array_equal(np.asarray(o2.w_free), np.asarray(o1.w_free))
    np.testing.assert_array_equal(np.asarray(o2.hit_points), np.asarray(o1.hit_points))
    with pytest.raises(ValueError, match="rays must be a RayBatch"):
        dct_objective_sharded(None, lower, extent, (3, 3))
