"""lidarjax.plot: every helper labels its axes in metres (beams for label images), draws
a labelled colour bar where colour encodes a value, keeps the map's extent, masks
unobserved cells, rejects bad input naming the argument — and importing the package
leaves Matplotlib's backend alone."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import matplotlib

matplotlib.use("Agg")  # this module draws in-process; the library never picks a backend

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import jaxlie  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from lidarjax import localization as loc  # noqa: E402
from lidarjax import maps, plot  # noqa: E402
from lidarjax.features import PlaneSegmentation, Poles, PolylineMap, PPEStop  # noqa: E402
from lidarjax.raytrace import GridSpec, GridStats  # noqa: E402

ORIGIN = (-1.0, 2.0)
RES = 0.5
SHAPE = (8, 6)  # extent x in [-1, 3], y in [2, 5]
EXTENT = (-1.0, 3.0, 2.0, 5.0)


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def _stats(shape=SHAPE) -> GridStats:
    """Synthetic statistics: a wall along the last x column, free space before it, and
    the first row never observed."""
    hits = np.zeros(shape, np.int32)
    misses = np.zeros(shape, np.int32)
    lengths = np.zeros(shape)
    hits[-1] = 5
    misses[-1] = 1
    misses[:-1] = 4
    lengths[:-1] = 4 * RES
    lengths[-1] = 0.3
    hits[:, 0] = misses[:, 0] = 0
    lengths[:, 0] = 0.0
    spec = GridSpec(jnp.asarray(ORIGIN + (0.0,) * (len(shape) - 2)), RES, shape)
    return GridStats(spec, jnp.asarray(hits), jnp.asarray(misses), jnp.asarray(lengths))


def _models():
    s = _stats()
    return {
        "stats": s,
        "decay_rate": maps.decay_rate_map(s),
        "reflection": maps.reflection_map(s),
        "endpoint": maps.endpoint_map(s, sigma_m=0.2),
        "gamma": maps.gamma_posterior(s),
        "beta": maps.beta_posterior(s),
    }


def _has_metre_labels(ax) -> None:
    assert "(m)" in ax.get_xlabel() and "(m)" in ax.get_ylabel()


def _colorbar_label(ax) -> str:
    mappable = (ax.images or ax.collections)[0]
    assert mappable.colorbar is not None, "colour encodes a value: needs a colour bar"
    label = mappable.colorbar.ax.get_ylabel()
    assert label
    return label


@pytest.mark.parametrize("name", ["stats", "decay_rate", "reflection", "endpoint", "gamma", "beta"])
def test_plot_map_grid_models(name):
    model = _models()[name]
    ax = plot.plot_map(model)
    _has_metre_labels(ax)
    assert ax.get_xlim() == pytest.approx(EXTENT[:2])
    assert ax.get_ylim() == pytest.approx(EXTENT[2:])
    assert ax.get_aspect() == 1.0
    label = _colorbar_label(ax)
    if name in ("decay_rate", "gamma"):
        assert "(1/m)" in label
    data = ax.images[0].get_array()
    assert data.shape == (SHAPE[1], SHAPE[0])  # [y x]
    mask = np.ma.getmaskarray(data)
    if name != "endpoint":  # the likelihood field is defined everywhere
        assert mask[0].all(), "never-observed cells (y row 0) must be masked, not drawn as 0"
    assert not mask[1:].any()


def test_plot_map_quantities_and_observed():
    m = _models()
    assert plot.map_quantities(m["decay_rate"]) == ("rate", "p_ref")
    ax = plot.plot_map(m["decay_rate"], quantity="p_ref", observed=m["stats"])
    assert "p_ref" in _colorbar_label(ax)
    assert float(np.max(ax.images[0].get_array())) <= 1.0
    ax = plot.plot_map(m["endpoint"], quantity="distance")
    assert "(m)" in _colorbar_label(ax)
    # observed=False shows every cell; a mask of the grid's shape chooses them
    assert not np.ma.getmaskarray(
        plot.plot_map(m["decay_rate"], observed=False).images[0].get_array()
    ).any()
    keep = np.zeros(SHAPE, bool)
    keep[2:4] = True
    mask = np.ma.getmaskarray(plot.plot_map(m["gamma"], observed=keep).images[0].get_array())
    assert mask.sum() == keep.size - keep.sum()
    # a decay-rate map with unknown_rate=0 cannot tell unobserved from free cells
    zero = maps.decay_rate_map(m["stats"], unknown_rate=0.0)
    assert not np.ma.getmaskarray(plot.plot_map(zero).images[0].get_array()).any()


def test_plot_map_draws_into_given_axes_and_title():
    fig, ax = plt.subplots()
    out = plot.plot_map(_models()["reflection"], ax=ax, title="mine")
    assert out is ax and ax.get_title() == "mine"
    assert len(fig.axes) == 2  # the map and its colour bar


def test_plot_map_dct_and_smooth_field():
    dct = maps.DCTMap(jnp.asarray([[1.0, 0.3], [0.2, -0.1], [0.05, 0.0]]), [-1.0, 2.0], [4.0, 3.0])
    ax = plot.plot_map(dct, resolution_m=0.1)
    _has_metre_labels(ax)
    assert ax.get_xlim() == pytest.approx(EXTENT[:2])
    assert ax.get_ylim() == pytest.approx(EXTENT[2:])
    assert ax.images[0].get_array().shape == (30, 40)
    assert "(1/m)" in _colorbar_label(ax)
    assert "DCT" in ax.get_title()
    np.testing.assert_allclose(
        ax.images[0].get_array()[0, 0],
        np.asarray(dct.decay_rate(jnp.asarray([-0.95, 2.05]))),
        rtol=1e-5,
    )
    field = maps.SmoothDecayRateField(_models()["decay_rate"])
    ax = plot.plot_map(field, quantity="p_ref")
    assert ax.get_xlim() == pytest.approx(EXTENT[:2])
    assert ax.get_ylim() == pytest.approx(EXTENT[2:])
    assert "p_ref" in _colorbar_label(ax)


def test_plot_map_3d_needs_a_slice():
    stats3 = _stats((8, 6, 3))
    m = maps.decay_rate_map(stats3)
    with pytest.raises(ValueError, match="model is 3-D.*z_index"):
        plot.plot_map(m)
    ax = plot.plot_map(m, z_index=1)
    assert ax.get_xlim() == pytest.approx(EXTENT[:2])
    with pytest.raises(ValueError, match="z_index"):
        plot.plot_map(m, z_index=3)
    with pytest.raises(ValueError, match="z_index"):
        plot.plot_map(_models()["decay_rate"], z_index=0)


def test_plot_map_bad_input_names_the_argument():
    m = _models()
    with pytest.raises(ValueError, match="model must be"):
        plot.plot_map(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="quantity must be one of"):
        plot.plot_map(m["reflection"], quantity="rate")
    with pytest.raises(ValueError, match="observed must have"):
        plot.plot_map(m["decay_rate"], observed=np.ones((2, 2), bool))
    with pytest.raises(ValueError, match="observed must be a bool"):
        plot.plot_map(m["decay_rate"], observed=np.ones(SHAPE))
    with pytest.raises(ValueError, match="vmin"):
        plot.plot_map(m["decay_rate"], vmin=0.0)
    with pytest.raises(ValueError, match="ax must be"):
        plot.plot_map(m["decay_rate"], ax="left")


def test_plot_grid_stats_keeps_working():
    s = _stats()
    fig = plot.plot_grid_stats(s, segments=np.array([[[0, 2.5], [2, 2.5]]]), poses=np.zeros((2, 3)))
    map_axes = [a for a in fig.axes if a.get_label() != "<colorbar>"]
    assert len(map_axes) == 3
    for ax in map_axes:
        _has_metre_labels(ax)
        assert ax.get_xlim() == pytest.approx(EXTENT[:2])
        _colorbar_label(ax)
    with pytest.raises(ValueError, match="stats must be on a 2-D grid"):
        plot.plot_grid_stats(_stats((8, 6, 3)))


def _track(n=20):
    t = np.linspace(0, 1, n)
    return np.column_stack([-0.5 + 3 * t, 3 + 0.5 * np.sin(3 * t), np.full(n, 0.2)])


def test_plot_trajectory_array_and_se2():
    p = _track()
    ax = plot.plot_trajectory(p, label="run")
    _has_metre_labels(ax)
    assert ax.get_aspect() == 1.0
    np.testing.assert_allclose(ax.lines[0].get_xydata(), p[:, :2])
    assert ax.get_legend() is not None
    se2 = jaxlie.SE2.from_xy_theta(*jnp.asarray(p.T))
    ax2 = plot.plot_trajectory(se2)
    np.testing.assert_allclose(ax2.lines[0].get_xydata(), p[:, :2], atol=1e-6)
    with pytest.raises(ValueError, match="poses must have shape"):
        plot.plot_trajectory(np.zeros((5, 4)))
    with pytest.raises(ValueError, match="poses must be finite"):
        plot.plot_trajectory(np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match="poses must be 2-D"):
        plot.plot_trajectory(jaxlie.SE3.identity())


def test_plot_particles_weights_colour_bar_and_headings():
    p = _track(30)
    w = np.linspace(0.1, 1.0, 30)
    ax = plot.plot_particles(p, w, headings=True)
    _has_metre_labels(ax)
    assert "weight" in _colorbar_label(ax)
    colours = ax.collections[0].get_array()
    assert colours.sum() == pytest.approx(1.0)  # normalised
    assert len(ax.collections) == 2  # points and heading arrows
    state = loc.init_gaussian(50, [0.0, 3.0, 0.0], [0.3, 0.3, 0.1], key=jax.random.key(0))
    ax = plot.plot_particles(state)
    assert "weight" in _colorbar_label(ax)
    ax = plot.plot_particles(p)  # bare poses: one colour, no colour bar
    assert ax.collections[0].colorbar is None
    with pytest.raises(ValueError, match="weights must have shape"):
        plot.plot_particles(p, w[:5])
    with pytest.raises(ValueError, match="weights must be finite"):
        plot.plot_particles(p, -w)
    with pytest.raises(ValueError, match="particles must have shape"):
        plot.plot_particles(np.zeros((4, 5)))
    with pytest.raises(ValueError, match="headings needs"):
        plot.plot_particles(p[:, :2], headings=True)


def test_plot_localization_map_trajectories_and_error():
    m = _models()["decay_rate"]
    gt = _track()
    est = gt + np.array([0.1, 0.0, 0.0])
    fig = plot.plot_localization(m, est, truth=gt, particles=gt[:5])
    map_ax, err_ax = [a for a in fig.axes if a.get_label() != "<colorbar>"][:2]
    _has_metre_labels(map_ax)
    assert map_ax.get_xlim() == pytest.approx(EXTENT[:2])
    assert map_ax.get_ylim() == pytest.approx(EXTENT[2:])
    assert err_ax.get_ylabel() == "position error (m)" and err_ax.get_xlabel() == "step"
    np.testing.assert_allclose(err_ax.lines[0].get_ydata(), 0.1, rtol=1e-9)
    labels = [t.get_text() for t in map_ax.get_legend().get_texts()]
    assert labels == ["truth", "estimate"]
    # into given axes: several filters share one error panel; time stamps in seconds
    fig2, (a, b) = plt.subplots(1, 2)
    for k, colour in enumerate(("tab:blue", "tab:red")):
        out = plot.plot_localization(
            m,
            est,
            truth=gt,
            ax=a,
            error_ax=b,
            label=f"f{k}",
            color=colour,
            times=np.arange(20) * 0.5,
        )
        assert out is a
    assert len(b.lines) == 2 and b.get_xlabel() == "time (s)"
    ax = plot.plot_localization(None, est)  # no map, no truth
    _has_metre_labels(ax)
    with pytest.raises(ValueError, match="truth must have one pose per estimate"):
        plot.plot_localization(m, est, truth=gt[:5])
    with pytest.raises(ValueError, match="times must be"):
        plot.plot_localization(m, est, truth=gt, times=np.arange(3))
    with pytest.raises(ValueError, match="estimate must have shape"):
        plot.plot_localization(m, np.zeros(3))


def test_plot_polyline_scan_labels_and_maps():
    az = np.linspace(-1.0, 1.0, 21)
    r = np.full(21, 3.0)
    ends = np.column_stack([r * np.cos(az), r * np.sin(az)])
    refl = np.ones(21, bool)
    refl[5] = False
    ax = plot.plot_polyline_scan(None, np.zeros(2), ends, refl, [ends[[0, 10, 20]]], title="PLE")
    _has_metre_labels(ax)
    assert ax.get_title() == "PLE (J = 3)"
    fig, ax = plt.subplots()
    pmap = PolylineMap.from_polylines([ends[[0, 10, 20]]])
    out = plot.plot_polyline_scan(ax, np.zeros(2), ends, refl, pmap, color="tab:green", label="m")
    assert out is ax and ax.get_legend() is not None
    plot.plot_polyline_scan(ax, np.zeros(2), ends, refl, [ends[[0, 20]]], draw_scan=False)
    with pytest.raises(ValueError, match="endpoints_xy must have shape"):
        plot.plot_polyline_scan(None, np.zeros(2), ends[:, :1], refl, [])
    with pytest.raises(ValueError, match="reflected must be"):
        plot.plot_polyline_scan(None, np.zeros(2), ends, refl[:-1], [])
    with pytest.raises(ValueError, match=r"polylines\[0\] must have shape"):
        plot.plot_polyline_scan(None, np.zeros(2), ends, refl, [np.zeros(3)])


def _organized_scan(H=6, W=10):
    rows, cols = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    pts = np.stack([np.full((H, W), 4.0), cols * 0.3 - 1.5, rows * 0.2], axis=-1)
    labels = np.where(cols < 5, 0, 1)
    labels[0, 0] = -1
    pts[1, 1] = np.nan  # no return
    return pts, labels


def test_plot_planes_label_image_and_top_view():
    pts, labels = _organized_scan()
    fig = plot.plot_planes(pts, labels)
    ax_img, ax_top = fig.axes
    assert "(beam)" in ax_img.get_xlabel() and "(beam)" in ax_img.get_ylabel()
    assert ax_img.images[0].get_array().shape == (6, 10, 3)
    assert "2 planes" in ax_img.get_title()
    _has_metre_labels(ax_top)
    seg = PlaneSegmentation(
        labels=labels,
        normals=np.zeros((2, 3)),
        supports=np.zeros((2, 3)),
        sizes=np.array([29, 30]),
        errors=np.zeros(2),
        linear_errors=np.zeros(2),
        step_kinds=np.zeros(0, np.int8),
        step_costs=np.zeros(0),
        stop=PPEStop.EXHAUSTED,
        n_atoms=0,
        n_small=0,
    )
    ax = plot.plot_planes(pts, seg, view="top")
    _has_metre_labels(ax)
    ax = plot.plot_planes(pts, seg, view="image")
    assert "(beam)" in ax.get_xlabel()
    with pytest.raises(ValueError, match="labels must be"):
        plot.plot_planes(pts, labels[:3])
    with pytest.raises(ValueError, match="points must be an organized scan"):
        plot.plot_planes(pts[0], labels)
    with pytest.raises(ValueError, match="view must be one of"):
        plot.plot_planes(pts, labels, view="side")


def test_plot_segmentation_keeps_working():
    _, labels = _organized_scan()
    fig = plot.plot_segmentation({"truth": labels, "PPE": labels}, title="t")
    assert len(fig.axes) == 2 and "(beam)" in fig.axes[0].get_xlabel()
    with pytest.raises(ValueError, match="must be a 2-D integer label image"):
        plot.plot_segmentation({"bad": np.zeros(3)})


def test_plot_poles_sized_by_width():
    pm = loc.PoleMap(
        xy=np.array([[0.0, 0.0], [2.0, 1.0], [4.0, -1.0]]),
        width_m=np.array([0.1, 0.3, 0.2]),
        score=np.ones(3),
        n_detections=np.ones(3, int),
    )
    ax = plot.plot_poles(pm, poses=_track(), truth=pm.xy + 0.05, annotate=True)
    _has_metre_labels(ax)
    assert ax.get_aspect() == 1.0
    poles = ax.collections[-1]
    assert poles.colorbar is not None and poles.colorbar.ax.get_ylabel() == "pole width (m)"
    sizes = poles.get_sizes()
    assert sizes[1] > sizes[2] > sizes[0]
    ax = plot.plot_poles(Poles(pm.xy, pm.width_m, pm.score))
    assert ax.collections[-1].colorbar is not None
    ax = plot.plot_poles(pm.xy)  # bare positions: no colour bar
    assert ax.collections[-1].colorbar is None
    with pytest.raises(ValueError, match="pole_map must be"):
        plot.plot_poles(np.zeros(3))
    with pytest.raises(ValueError, match="truth must be"):
        plot.plot_poles(pm, truth="x")
    with pytest.raises(ValueError, match="poses must have shape"):
        plot.plot_poles(pm, poses=np.zeros((4, 7)))


_BACKEND_CHECK = textwrap.dedent(
    """
    import matplotlib
    {choose}
    before = matplotlib.get_backend()
    import lidarjax.plot
    import lidarjax.plot._maps, lidarjax.plot._localization, lidarjax.plot._features
    after = matplotlib.get_backend()
    print(before, after)
    assert before == after, (before, after)
    """
)


@pytest.mark.parametrize(
    "choose, env_backend, expected",
    [("", "pdf", "pdf"), ("matplotlib.use('svg')", None, "svg")],
)
def test_importing_plot_leaves_the_backend_alone(choose, env_backend, expected):
    env = {k: v for k, v in os.environ.items() if k != "MPLBACKEND"}
    if env_backend:
        env["MPLBACKEND"] = env_backend
    proc = subprocess.run(
        [sys.executable, "-c", _BACKEND_CHECK.format(choose=choose)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == [expected, expected]
