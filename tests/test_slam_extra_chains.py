"""Further front ends as further Cauchy-robust chains of run_slam's pose graph
(SlamConfig.extra_chain_models, front_end_pose_graph's extra_chains)."""

import numpy as np
import pytest

import lidarjax.slam._pipeline as pipeline
from lidarjax.metrics import absolute_trajectory_error
from lidarjax.slam import (
    FrontEndConfig,
    FrontEndResult,
    Loops,
    SlamConfig,
    calibrate_odometry,
    front_end_pose_graph,
    odometry_sigmas,
    optimize_pose_graph,
    run_slam,
)
from lidarjax.slam._front_end import between_np, compose_np


def _chain(p0, inc):
    out = [np.asarray(p0, float)]
    for u in inc:
        out.append(compose_np(out[-1], u))
    return np.array(out)


NO_LOOPS = Loops(np.zeros((0, 2), np.int64), np.zeros((0, 3)), 0)


def _noisy_pair(seed, n=150):
    """Truth, odometry (2 cm, 1 degree per increment) and two front ends with
    independent 2 cm / 0.3 degree noise per increment; exact loops (0, n // 2),
    (n // 2, n - 1), (0, n - 1)."""
    r = np.random.default_rng(seed)
    d = r.uniform(0.3, 0.8, n - 1)
    inc = np.stack([d, r.normal(0, 0.01, n - 1), r.uniform(-0.3, 0.3, n - 1)], 1)
    truth = _chain([0.5, 1.0, 0.2], inc)

    def noisy(s):
        return _chain(truth[0], inc + r.normal(0, 1, inc.shape) * s)

    fe_noise = [0.02, 0.02, np.deg2rad(0.3)]
    odo, a, b = noisy([0.02, 0.02, np.deg2rad(1.0)]), noisy(fe_noise), noisy(fe_noise)
    e = np.array([[0, n // 2], [n // 2, n - 1], [0, n - 1]])
    return truth, odo, a, b, Loops(e, between_np(truth[e[:, 0]], truth[e[:, 1]]), 3)


def _ate(p, truth):
    return absolute_trajectory_error(np.asarray(p), truth).rmse_m


@pytest.mark.parametrize("failures", [False, True])
def test_a_second_chain_averages_the_noise_and_bridges_failures(failures):
    """Two front ends with independent errors: the fused graph is better than either
    alone by about 1 / sqrt(2) (eight scenes). With failures (10 degrees and 0.3 m, the
    first front end at increment 40, the second at 110) the loops reject each failed
    increment and the other front end's increment at that step is kept."""
    cfg = SlamConfig(back_end="none")
    alone, fused = [], []
    for seed in range(8):
        truth, odo, a, b, loops = _noisy_pair(seed)
        n = len(truth)
        if failures:
            ia, ib = between_np(a[:-1], a[1:]), between_np(b[:-1], b[1:])
            ia[40] += [0.3, 0.0, np.deg2rad(10.0)]
            ib[110] -= [0.3, 0.0, np.deg2rad(10.0)]
            a, b = _chain(a[0], ia), _chain(b[0], ib)
        for p in (a, b):
            alone.append(_ate(front_end_pose_graph(p, odo, loops, cfg).poses, truth))
        g = front_end_pose_graph(a, odo, loops, cfg, extra_chains=[b])
        fused.append(_ate(g.poses, truth))
        # edge weights: chain, loops, (no revisits), odometry, extra chain
        w = np.asarray(g.edge_weights)
        assert w.shape == (3 * (n - 1) + 3,)
        w_a, w_odo, w_b = w[: n - 1], w[n + 2 : 2 * n + 1], w[2 * n + 1 :]
        assert np.all(w_odo == 1.0)
        if failures:
            assert w_a[40] < 0.05 and w_b[110] < 0.05
            assert w_b[40] > 0.5
    assert np.mean(fused) < 0.85 * np.mean(alone)


def test_extra_chains_graph_is_the_explicit_graph():
    truth, odo, a, b, _ = _noisy_pair(4, n=60)
    c = _chain(truth[0], between_np(truth[:-1], truth[1:]))  # a third, exact front end
    e = np.array([[3, 50], [10, 55]])
    loops = Loops(e, between_np(truth[e[:, 0]], truth[e[:, 1]]), 2)
    cfg = SlamConfig(back_end="none", chain_sigma_xy_m=0.04, chain_sigma_yaw_rad=0.02)
    got = front_end_pose_graph(a, odo, loops, cfg, extra_chains=(b, c))
    # built by hand: every chain at sqrt(3) times the chain sigmas, Cauchy-robust
    n = len(truth)
    ch = np.stack([np.arange(n - 1), np.arange(1, n)], 1)
    s = np.sqrt(3.0) * np.array([0.04, 0.04, 0.02])
    inc_odo = between_np(odo[:-1], odo[1:])
    edges = np.concatenate([ch, e, ch, ch, ch])
    meas = [between_np(p[:-1], p[1:]) for p in (a, b, c)]
    z = np.concatenate([meas[0], loops.measurements, inc_odo, meas[1], meas[2]])
    sig = np.concatenate(
        [
            np.tile(s, (n - 1, 1)),
            np.tile([0.1, 0.1, 0.02], (2, 1)),
            odometry_sigmas(inc_odo, cfg.front),
            np.tile(s, (n - 1, 1)),
            np.tile(s, (n - 1, 1)),
        ]
    )
    robust = np.concatenate(
        [np.ones(n - 1 + 2, bool), np.zeros(n - 1, bool), np.ones(2 * (n - 1), bool)]
    )
    want = optimize_pose_graph(a, edges.astype(np.int32), z, sig, robust=robust, cauchy_scale=1.0)
    np.testing.assert_allclose(np.asarray(got.poses), np.asarray(want.poses), atol=1e-12)
    np.testing.assert_allclose(
        np.asarray(got.edge_weights), np.asarray(want.edge_weights), atol=1e-12
    )


def test_without_extra_chains_nothing_changes():
    truth, odo, a, _, _ = _noisy_pair(2, n=40)
    cfg = SlamConfig(back_end="none")
    p0 = front_end_pose_graph(a, odo, NO_LOOPS, cfg)
    p1 = front_end_pose_graph(a, odo, NO_LOOPS, cfg, extra_chains=[])
    np.testing.assert_array_equal(np.asarray(p0.poses), np.asarray(p1.poses))


def test_bad_extra_chains_raise():
    truth, odo, a, b, _ = _noisy_pair(0, n=20)
    cfg = SlamConfig(back_end="none")
    with pytest.raises(ValueError, match=r"extra_chains\[0\]"):
        front_end_pose_graph(a, odo, NO_LOOPS, cfg, extra_chains=[b[:-1]])
    bad = b.copy()
    bad[5, 1] = np.nan
    with pytest.raises(ValueError, match=r"extra_chains\[1\]"):
        front_end_pose_graph(a, odo, NO_LOOPS, cfg, extra_chains=[b, bad])
    with pytest.raises(ValueError, match="robust_chain"):
        front_end_pose_graph(a, odo, NO_LOOPS, SlamConfig(robust_chain=False), extra_chains=[b])
    with pytest.raises(ValueError, match="extra_chain_models"):
        SlamConfig(extra_chain_models=("lidar",))
    with pytest.raises(ValueError, match="extra_chain_models"):
        SlamConfig(extra_chain_models=["endpoint"])
    with pytest.raises(ValueError, match="must not repeat"):
        SlamConfig(extra_chain_models=("endpoint", "endpoint"))
    with pytest.raises(ValueError, match="robust_chain"):
        SlamConfig(extra_chain_models=("endpoint",), robust_chain=False)


def test_chain_models_default_to_the_other_model_and_icp():
    assert SlamConfig().chain_models == ("endpoint", "icp")
    assert SlamConfig(front=FrontEndConfig(model="endpoint")).chain_models == (
        "decay_rate",
        "icp",
    )
    assert SlamConfig(robust_chain=False).chain_models == ()
    assert SlamConfig(extra_chain_models=()).chain_models == ()
    two = ("endpoint", "decay_rate")
    assert SlamConfig(extra_chain_models=two).chain_models == two


def test_run_slam_runs_each_extra_front_end_and_fuses_its_chain(monkeypatch):
    truth, odo, a, b, _ = _noisy_pair(5, n=100)
    calls = []

    def fake_front_end(rng, azimuths, odometry, cfg, progress=False):
        calls.append(cfg.model)
        np.testing.assert_array_equal(odometry, odo)  # every front end gets the raw odometry
        p = a if cfg.model == "decay_rate" else b
        n = rng.shape[0]
        return FrontEndResult(p, np.zeros(n), 0.5, np.zeros(n), None, None, np.ones(n, bool))

    third = _noisy_pair(15, n=100)[2]  # the ICP chain: a third front end's noise
    reg = np.ones(len(truth), bool)
    reg[[30, 31]] = False

    def fake_icp(rng, azimuths, odometry, cap, icfg, progress):
        calls.append("icp")
        np.testing.assert_array_equal(odometry, odo)
        return third, reg, 0.25

    e = np.array([[2, 90], [5, 95]])
    loops = Loops(e, between_np(truth[e[:, 0]], truth[e[:, 1]]), 2)
    monkeypatch.setattr(pipeline, "run_front_end", fake_front_end)
    monkeypatch.setattr(pipeline, "point_icp_chain", fake_icp)
    monkeypatch.setattr(pipeline, "find_loops", lambda *a_, **k: loops)
    cfg = SlamConfig(back_end="none", loop_rounds=1)  # default: endpoint and ICP chains
    ranges, az = np.full((len(truth), 4), 5.0), np.linspace(-1, 1, 4)
    r = run_slam(ranges, az, odo, cfg)
    assert calls == ["decay_rate", "endpoint", "icp"]
    assert len(r.extra_front_end_poses) == 2
    np.testing.assert_array_equal(r.extra_front_end_poses[0], b)
    np.testing.assert_array_equal(r.extra_front_end_poses[1], third)
    np.testing.assert_array_equal(r.front_end_poses, a)
    assert r.seconds["front_end"] == 0.5 and r.seconds["extra_front_ends"] == 0.75
    # the calibration follows the first front end
    c = calibrate_odometry(a, odo, cfg.front, valid=np.ones(len(truth) - 1, bool))
    assert r.odometry_calibration == c
    pg = front_end_pose_graph(
        a, c.apply(odo), loops, cfg, extra_chains=[b, third], extra_chain_valid=[None, reg[1:]]
    )
    np.testing.assert_allclose(r.pose_graph_poses, np.asarray(pg.poses), atol=1e-9)
    # and without the extra model the graph is the single chain's
    calls.clear()
    r1 = run_slam(
        ranges, az, odo, SlamConfig(back_end="none", loop_rounds=1, extra_chain_models=())
    )
    assert calls == ["decay_rate"]
    assert r1.extra_front_end_poses == () and r1.seconds["extra_front_ends"] == 0.0
    pg1 = front_end_pose_graph(a, c.apply(odo), loops, cfg)
    np.testing.assert_allclose(r1.pose_graph_poses, np.asarray(pg1.poses), atol=1e-9)


def _fake_run_slam(monkeypatch, a, b, loops, cfg, odo):
    """run_slam with front ends returning ``a`` (decay rate) and ``b`` (endpoint) and a
    loop search returning ``loops``."""

    def fake_front_end(rng, azimuths, odometry, fcfg, progress=False):
        p = a if fcfg.model == "decay_rate" else b
        n = rng.shape[0]
        return FrontEndResult(p, np.zeros(n), 0.5, np.zeros(n), None, None, np.ones(n, bool))

    monkeypatch.setattr(pipeline, "run_front_end", fake_front_end)
    monkeypatch.setattr(pipeline, "find_loops", lambda *a_, **k: loops)
    ranges, az = np.full((len(a), 4), 5.0), np.linspace(-1, 1, 4)
    return run_slam(ranges, az, odo, cfg)


def test_run_slam_reports_what_the_pose_graph_rejected(monkeypatch):
    """SlamResult's loop, revisit and chain weights are the final pose graph's edge
    weights, split by factor; a wrong loop closure and a failed increment of the first
    front end fall below REJECTED_WEIGHT, the other front end's increment at that step
    and the right loops stay near 1."""
    from lidarjax.slam import REJECTED_WEIGHT

    truth, odo, a, b, _ = _noisy_pair(7, n=100)
    ia = between_np(a[:-1], a[1:])
    ia[40] += [0.3, 0.0, np.deg2rad(10.0)]  # a failed match of the first front end
    a = _chain(a[0], ia)
    e = np.array([[2, 90], [5, 95], [0, 50], [50, 99], [20, 70]])
    z = between_np(truth[e[:, 0]], truth[e[:, 1]])
    z[4, :2] += [2.0, -1.0]  # an aliased place: 2.2 m off
    loops = Loops(e, z, 5)
    cfg = SlamConfig(back_end="none", loop_rounds=1, extra_chain_models=("endpoint",))
    r = _fake_run_slam(monkeypatch, a, b, loops, cfg, odo)
    # the same graph re-solved: its weights, split as front_end_pose_graph orders them
    pg = front_end_pose_graph(a, r.odometry, loops, cfg, revisits=r.revisits, extra_chains=[b])
    w = np.asarray(pg.edge_weights)
    m = len(truth) - 1
    assert r.loop_weights.shape == (5,) and r.revisit_weights.shape == (0,)
    assert r.chain_weights.shape == (2, m)
    np.testing.assert_allclose(r.loop_weights, w[m : m + 5], atol=1e-12)
    np.testing.assert_allclose(r.chain_weights[0], w[:m], atol=1e-12)
    np.testing.assert_allclose(r.chain_weights[1], w[-m:], atol=1e-12)
    assert r.pose_graph_cost == pytest.approx(float(pg.cost), rel=1e-12)
    # the verdicts
    assert r.loop_weights[4] < REJECTED_WEIGHT and np.all(r.loop_weights[:4] > 0.5)
    assert r.chain_weights[0, 40] < REJECTED_WEIGHT and r.chain_weights[1, 40] > 0.5
    assert np.sum(r.chain_weights < REJECTED_WEIGHT) == 1
    # a plain chain (no robust kernel, no further front end) keeps every increment
    plain = SlamConfig(back_end="none", loop_rounds=1, robust_chain=False)
    r1 = _fake_run_slam(monkeypatch, a, b, loops, plain, odo)
    np.testing.assert_array_equal(r1.chain_weights, np.ones((1, m)))
    pg1 = front_end_pose_graph(a, r1.odometry, loops, plain, revisits=r1.revisits)
    np.testing.assert_allclose(r1.loop_weights, np.asarray(pg1.edge_weights)[m : m + 5])


def test_run_slam_on_one_scan_reports_no_pose_graph(monkeypatch):
    one = np.zeros((1, 3))
    r = _fake_run_slam(monkeypatch, one, one, NO_LOOPS, SlamConfig(back_end="none"), one)
    assert r.loop_weights.shape == (0,) and r.chain_weights.shape == (3, 0)  # + the ICP chain
    np.testing.assert_array_equal(r.extra_front_end_poses[1], one)
    assert r.pose_graph_cost == 0.0


def test_run_slam_short_loops_join_the_pose_graph(monkeypatch):
    """short_loop_separation: after the loop rounds, one more loop search along the pose
    graph with the short settings (the known pairs skipped, the level along the front
    end's poses); its loops are appended and the graph is solved again with them."""
    truth, odo, a, b, _ = _noisy_pair(3, n=80)
    e = np.array([[2, 70], [5, 75]])
    loops = Loops(e, between_np(truth[e[:, 0]], truth[e[:, 1]]), 2, 1.25)
    es = np.array([[10, 17], [30, 37], [50, 57]])
    short = Loops(es, between_np(truth[es[:, 0]], truth[es[:, 1]]), 9, 1.25)
    calls = []

    def fake_find_loops(rng, az, poses, lcfg, fcfg, **kw):
        calls.append((np.array(poses), lcfg, kw))
        return loops if len(calls) == 1 else short

    def fake_front_end(rng, azimuths, odometry, fcfg, progress=False):
        n = rng.shape[0]
        p = a if fcfg.model == "decay_rate" else b
        return FrontEndResult(p, np.zeros(n), 0.5, np.zeros(n), None, None, np.ones(n, bool))

    monkeypatch.setattr(pipeline, "run_front_end", fake_front_end)
    monkeypatch.setattr(pipeline, "find_loops", fake_find_loops)
    ranges, az = np.full((len(a), 4), 5.0), np.linspace(-1, 1, 4)
    cfg = SlamConfig(
        back_end="none", loop_rounds=1, short_loop_separation=7, extra_chain_models=("endpoint",)
    )
    r = run_slam(ranges, az, odo, cfg)
    assert len(calls) == 2
    poses, lcfg, kw = calls[1]
    assert (lcfg.min_separation, lcfg.submap_half, lcfg.every) == (7, 3, 1)
    assert lcfg.wide_search_xy_m == 0.0 and lcfg.far_radius_m == 0.0
    assert lcfg.radius_m == cfg.loops.radius_m  # the rest as the loop rounds'
    np.testing.assert_array_equal(kw["known"], e)
    np.testing.assert_array_equal(kw["level_poses"], a)
    assert kw["scene_level"] == 1.25
    # searched along the pose graph of the loop rounds
    first = front_end_pose_graph(a, r.odometry, loops, cfg, extra_chains=[b])
    np.testing.assert_allclose(poses, np.asarray(first.poses), atol=1e-9)
    # the short loops come last, and the final graph has all five
    assert r.n_short_loops == 3 and r.loops.n_tried == 11
    np.testing.assert_array_equal(r.loops.edges, np.concatenate([e, es]))
    final = front_end_pose_graph(a, r.odometry, r.loops, cfg, extra_chains=[b])
    np.testing.assert_allclose(r.pose_graph_poses, np.asarray(final.poses), atol=1e-9)
    assert r.loop_weights.shape == (5,) and r.seconds["short_loops"] >= 0
    assert np.abs(r.pose_graph_poses - np.asarray(first.poses)).max() > 1e-6


@pytest.mark.parametrize("bad", [-1, 1, 2, True, 7.0, "7"])
def test_short_loop_separation_must_be_zero_or_at_least_three(bad):
    with pytest.raises(ValueError, match="short_loop_separation"):
        SlamConfig(short_loop_separation=bad)
    assert SlamConfig(short_loop_separation=3).short_loop_config.submap_half == 1


def test_masked_extra_chain_graph_is_the_explicit_graph():
    """extra_chain_valid leaves an extra chain's masked increments out of the graph: the
    same graph as one built by hand without them, whatever those increments say."""
    truth, odo, a, b, loops = _noisy_pair(3, n=50)
    ib = between_np(b[:-1], b[1:])
    ok = np.ones(len(truth) - 1, bool)
    ok[[7, 20, 21]] = False
    ib[~ok] += [1.0, -0.5, 0.4]  # a rejected registration's increment: never used
    c = _chain(b[0], ib)
    cfg = SlamConfig(back_end="none")
    got = front_end_pose_graph(a, odo, loops, cfg, extra_chains=[c], extra_chain_valid=[ok])
    n = len(truth)
    ch = np.stack([np.arange(n - 1), np.arange(1, n)], 1)
    s = np.sqrt(2.0) * np.array(
        [cfg.chain_sigma_xy_m, cfg.chain_sigma_xy_m, cfg.chain_sigma_yaw_rad]
    )
    inc_odo = between_np(odo[:-1], odo[1:])
    edges = np.concatenate([ch, loops.edges, ch, ch[ok]])
    zc = between_np(c[:-1], c[1:])
    z = np.concatenate([between_np(a[:-1], a[1:]), loops.measurements, inc_odo, zc[ok]])
    sig = np.concatenate(
        [
            np.tile(s, (n - 1, 1)),
            np.tile([0.1, 0.1, 0.02], (3, 1)),
            odometry_sigmas(inc_odo, cfg.front),
            np.tile(s, (int(ok.sum()), 1)),
        ]
    )
    robust = np.concatenate([np.ones(n + 2, bool), np.zeros(n - 1, bool), np.ones(ok.sum(), bool)])
    want = optimize_pose_graph(a, edges.astype(np.int32), z, sig, robust=robust, cauchy_scale=1.0)
    np.testing.assert_allclose(np.asarray(got.poses), np.asarray(want.poses), atol=1e-12)
    assert np.asarray(got.edge_weights).shape == (3 * (n - 1) + 3 - 3,)
    # None and an all-True mask are the unmasked graph
    full = front_end_pose_graph(a, odo, loops, cfg, extra_chains=[b])
    for v in (None, [None], [np.ones(n - 1, bool)]):
        g = front_end_pose_graph(a, odo, loops, cfg, extra_chains=[b], extra_chain_valid=v)
        np.testing.assert_array_equal(np.asarray(g.poses), np.asarray(full.poses))


def test_bad_extra_chain_masks_raise():
    truth, odo, a, b, _ = _noisy_pair(0, n=20)
    cfg = SlamConfig(back_end="none")
    ok = np.ones(19, bool)
    for bad, what in (
        ([ok, ok], "one mask per extra chain"),
        ([ok[:-1]], r"extra_chain_valid\[0\]"),
        ([ok.astype(int)], r"extra_chain_valid\[0\]"),
    ):
        with pytest.raises(ValueError, match=what):
            front_end_pose_graph(a, odo, NO_LOOPS, cfg, extra_chains=[b], extra_chain_valid=bad)


def test_gicp_is_a_chain_model():
    from lidarjax.slam import CHAIN_MODELS

    assert CHAIN_MODELS == ("decay_rate", "endpoint", "icp", "gicp")
    cfg = SlamConfig(extra_chain_models=("endpoint", "gicp"))
    assert cfg.chain_models == ("endpoint", "gicp")
    with pytest.raises(ValueError, match="extra_chain_models"):
        SlamConfig(extra_chain_models=("gicp", "gicp"))


def test_run_slam_fuses_a_gicp_chain_without_its_rejected_registrations(monkeypatch):
    """extra_chain_models ("endpoint", "gicp"): the GICP chain (icp_front_end's, on the
    readings below the front end's range cap) joins the graph where its registration was
    accepted; chain_weights is NaN where it was not, and extra_chain_valid says which."""
    truth, odo, a, b, loops = _noisy_pair(6, n=80)
    n = len(truth)
    c = _noisy_pair(16, n=80)[2]  # a third front end's noise
    c = _chain(truth[0], between_np(c[:-1], c[1:]))
    reg = np.ones(n, bool)
    reg[[11, 12, 40]] = False
    ic = between_np(c[:-1], c[1:])
    ic[~reg[1:]] = between_np(odo[:-1], odo[1:])[~reg[1:]]  # the odometry's increment
    c = _chain(c[0], ic)
    got = {}

    def fake_icp(rng, az, odometry, max_range_m, range_cap_m, voxel_m, progress):
        got.update(max_range_m=max_range_m, range_cap_m=range_cap_m, voxel_m=voxel_m)
        np.testing.assert_array_equal(odometry, odo)  # the raw odometry, as every chain
        return c, reg, 0.25

    monkeypatch.setattr(pipeline, "_icp_chain", fake_icp)
    cfg = SlamConfig(back_end="none", loop_rounds=1, extra_chain_models=("endpoint", "gicp"))
    r = _fake_run_slam(monkeypatch, a, b, loops, cfg, odo)
    cap = cfg.front.range_cap_m
    assert got == {"max_range_m": cap, "range_cap_m": cap, "voxel_m": pipeline.GICP_VOXEL_M}
    assert r.seconds["extra_front_ends"] == 0.5 + 0.25
    assert len(r.extra_front_end_poses) == 2
    np.testing.assert_array_equal(r.extra_front_end_poses[1], c)
    assert [v.tolist() for v in r.extra_chain_valid] == [[True] * (n - 1), reg[1:].tolist()]
    pg = front_end_pose_graph(
        a, r.odometry, loops, cfg, extra_chains=[b, c], extra_chain_valid=[None, reg[1:]]
    )
    np.testing.assert_allclose(r.pose_graph_poses, np.asarray(pg.poses), atol=1e-9)
    w = np.asarray(pg.edge_weights)
    assert r.chain_weights.shape == (3, n - 1)
    np.testing.assert_array_equal(np.isnan(r.chain_weights[2]), ~reg[1:])
    np.testing.assert_allclose(r.chain_weights[2, reg[1:]], w[-int(reg[1:].sum()) :], atol=1e-12)
    np.testing.assert_allclose(
        r.chain_weights[1], w[-int(reg[1:].sum()) - (n - 1) : -int(reg[1:].sum())], atol=1e-12
    )
    assert not np.isnan(r.chain_weights[:2]).any()
    # three chains that agree with the truth about as well as two: the graph is good
    assert _ate(r.pose_graph_poses, truth) < 0.05


def test_run_slam_without_small_gicp_fails_before_the_front_ends(monkeypatch):
    """A 'gicp' chain without small_gicp installed: the ImportError comes first, before
    the front ends run (minutes on a real log)."""

    def missing():
        raise ImportError("needs small_gicp (pip install 'lidarjax[slam]')")

    def no_front_end(*a, **k):
        raise AssertionError("a front end ran")

    monkeypatch.setattr(pipeline, "_import_small_gicp", missing)
    monkeypatch.setattr(pipeline, "run_front_end", no_front_end)
    cfg = SlamConfig(back_end="none", extra_chain_models=("gicp",))
    ranges, az = np.full((5, 4), 5.0), np.linspace(-1, 1, 4)
    with pytest.raises(ImportError, match="small_gicp"):
        run_slam(ranges, az, np.zeros((5, 3)), cfg)
