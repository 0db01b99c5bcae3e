"""Run-time checks as program outputs (``lidarjax._checks``, issue #25): the same errors as
``eqx.error_if`` — eagerly, under ``checked_jit``, under a user's ``jit``/``vmap``/``grad``,
inside ``scan``/``map`` bodies — and no host callback in the compiled programs, so JAX's
persistent compilation cache can keep them."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lidarjax import _checks

jax.config.update("jax_enable_x64", True)

# eqx.error_if raises EquinoxRuntimeError eagerly and under eqx.filter_jit; under a plain
# jax.jit the failed callback surfaces as a JaxRuntimeError or a ValueError (as in
# tests/test_raytrace_hostile.py)
RUNTIME = (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError, ValueError)


def _has_callback(lowered) -> bool:
    return "callback" in lowered.as_text()


def f_body(x):
    y = _checks.check(x, x < 0, "x must be >= 0")
    return jnp.sqrt(y)


def f_loops(xs):
    """A check at the top, in a scan body and in a map body."""
    xs = _checks.check(xs, jnp.isnan(xs), "xs must not be NaN")

    def body(c, x):
        x = _checks.check(x, x > 100, "scan: x must be <= 100")
        return c + x, 2 * x

    total, doubled = _checks.scan(body, jnp.zeros((), xs.dtype), xs)
    halves = _checks.map(lambda x: _checks.check(x, x == 7, "map: x must not be 7") / 2, xs)
    return total, doubled, halves


checked = _checks.checked_jit(f_body)
checked_loops = _checks.checked_jit(f_loops)


def test_eager_check_is_error_if():
    assert float(_checks.check(jnp.asarray(1.0), jnp.asarray(False), "m")) == 1.0
    with pytest.raises(eqx.EquinoxRuntimeError, match="x must be >= 0"):
        f_body(jnp.asarray(-1.0))


def test_checked_jit_returns_values_and_raises_on_the_host():
    np.testing.assert_allclose(checked(jnp.asarray([1.0, 4.0])), [1.0, 2.0])
    with pytest.raises(eqx.EquinoxRuntimeError, match="x must be >= 0"):
        checked(jnp.asarray([1.0, -4.0]))


def test_checked_programs_have_no_host_callback():
    """The point of the module: the plain eqx.error_if program has a callback, the
    checked one (check at the top level and in scan/map bodies) has none."""
    x = jnp.arange(5.0)
    assert _has_callback(jax.jit(lambda x: eqx.error_if(x, x < 0, "m")).lower(x))
    assert not _has_callback(checked.program.lower(x))
    assert not _has_callback(checked_loops.program.lower(x))


@pytest.mark.parametrize(
    ("x", "message"),
    [
        ([1.0, float("nan"), 3.0], "xs must not be NaN"),
        ([1.0, 101.0, 3.0], "scan: x must be <= 100"),
        ([1.0, 7.0, 3.0], "map: x must not be 7"),
    ],
)
def test_each_loop_check_raises_its_own_message(x, message):
    good = checked_loops(jnp.asarray([1.0, 2.0, 3.0]))
    np.testing.assert_allclose(good[0], 6.0)
    np.testing.assert_allclose(good[1], [2.0, 4.0, 6.0])
    np.testing.assert_allclose(good[2], [0.5, 1.0, 1.5])
    with pytest.raises(eqx.EquinoxRuntimeError, match=message):
        checked_loops(jnp.asarray(x))
    # eagerly (no jit at all) the loops raise the same messages
    with pytest.raises(eqx.EquinoxRuntimeError, match=message):
        f_loops(jnp.asarray(x))


def test_under_a_users_jit_the_checks_are_reattached():
    """Traced flags become eqx.error_if checks of the enclosing program: still raised."""
    outer = jax.jit(lambda x: checked_loops(x)[0] + 1)
    np.testing.assert_allclose(outer(jnp.asarray([1.0, 2.0])), 4.0)
    with pytest.raises(RUNTIME, match="scan: x must be <= 100"):
        jax.block_until_ready(outer(jnp.asarray([1.0, 200.0])))


def test_nested_checked_jit_reports_to_the_outer_program():
    """A checked program inside another: its flags become the outer one's (no callback)."""
    outer = _checks.checked_jit(lambda x: checked(x) * 2)
    assert not _has_callback(outer.program.lower(jnp.ones(3)))
    np.testing.assert_allclose(outer(jnp.asarray([4.0])), [4.0])
    with pytest.raises(eqx.EquinoxRuntimeError, match="x must be >= 0"):
        outer(jnp.asarray([-4.0]))


def test_vmap_and_grad_through_a_checked_function():
    xs = jnp.asarray([[1.0, 4.0], [9.0, 16.0]])
    np.testing.assert_allclose(jax.vmap(checked)(xs), jnp.sqrt(xs))
    with pytest.raises(RUNTIME, match="x must be >= 0"):
        jax.block_until_ready(jax.vmap(checked)(-xs))
    g = jax.grad(lambda x: jnp.sum(checked(x)))(jnp.asarray([4.0]))
    np.testing.assert_allclose(g, [0.25])  # d sqrt(x) / dx = 1 / (2 sqrt x)
    with pytest.raises(RUNTIME, match="x must be >= 0"):
        jax.block_until_ready(jax.grad(lambda x: jnp.sum(checked(x)))(jnp.asarray([-4.0])))


def test_a_check_in_a_plain_loop_body_stays_a_callback_and_still_raises():
    """Not every loop is converted: a check in a plain lax.scan body is at another trace
    level, so it falls back to eqx.error_if (correct, not cacheable)."""

    def plain(xs):
        def body(c, x):
            return c + _checks.check(x, x < 0, "plain: x must be >= 0"), None

        return jax.lax.scan(body, jnp.zeros(()), xs)[0]

    prog = _checks.checked_jit(plain)
    assert _has_callback(prog.program.lower(jnp.ones(3)))
    assert float(prog(jnp.ones(3))) == 3.0
    with pytest.raises(eqx.EquinoxRuntimeError, match="plain: x must be >= 0"):
        prog(jnp.asarray([1.0, -1.0]))


def test_checked_jit_keeps_the_function_name():
    """Compiled programs are named after the function (compile counters rely on it)."""
    assert checked.__name__ == "f_body"
    assert "f_body" in checked.program.lower(jnp.ones(2)).as_text()


def _lowered_text(lowered) -> str:
    return getattr(lowered, "lowered", lowered).as_text()


def test_the_librarys_main_programs_have_no_host_callback(monkeypatch, key):
    """Accumulation, likelihoods at poses and the particle filter's scan (a decay-rate map
    of a simulated office): JAX can write all three to its persistent cache."""
    import jaxlie

    from lidarjax import maps
    from lidarjax.localization import (
        OdometryMotionModel,
        ParticleFilter,
        ScanModel,
        _filter,
        init_gaussian,
        relative_motion,
    )
    from lidarjax.rays import from_scan
    from lidarjax.raytrace import GridSpec, _grid, accumulate
    from lidarjax.sensor_models import _common, log_likelihood_at_poses
    from lidarjax.sim import make_office, simulate_scans

    world = make_office(0)
    poses = world.trajectory(9, jitter_m=0.2, seed=0)
    az = np.linspace(-np.pi / 2, np.pi / 2, 61)
    ranges = simulate_scans(world, poses, az, max_range_m=10.0, noise_sigma_m=0.01, seed=0)
    T = jaxlie.SE2.from_xy_theta(poses[:, 0], poses[:, 1], poses[:, 2])
    rays = from_scan(T, az, ranges, 0.05, 10.0)
    spec = GridSpec.from_bounds(world.bounds[0] - 0.5, world.bounds[1] + 0.5, 0.2)

    texts = {}

    def spy(module, name, getter=None):
        real = getattr(module, name)

        def wrapped(*args, **kwargs):
            texts[name] = _lowered_text(real.program.lower(*args, **kwargs))
            return real(*args, **kwargs)

        monkeypatch.setattr(module, name, wrapped)

    spy(_grid, "_accumulate")
    spy(_common, "_at_poses")
    stats = accumulate(spec, rays, backend="jax")
    dm = maps.decay_rate_map(stats)
    log_likelihood_at_poses(dm, az, ranges[4], poses[:4], r_min=0.05, r_max=10.0)

    real_run = _filter.ParticleFilter._run_padded

    def run_spy(self, *args):
        texts["_run_padded"] = _lowered_text(real_run.program.lower(self, *args))
        return real_run(self, *args)

    monkeypatch.setattr(_filter.ParticleFilter, "_run_padded", run_spy)
    pf = ParticleFilter(
        OdometryMotionModel([0.03, 0.03, 0.01]), ScanModel(dm, az, 0.05, 10.0, backend="jax")
    )
    state = init_gaussian(50, poses[0], [0.1, 0.1, 0.05], key=key)
    pf.run(state, np.asarray(relative_motion(poses)), ranges[1:])
    assert sorted(texts) == ["_accumulate", "_at_poses", "_run_padded"]
    for name, text in texts.items():
        assert "callback" not in text, name
