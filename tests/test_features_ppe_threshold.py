"""PPE's stopping threshold (lidarjax/features/_ppe_threshold.py): the noise estimate, the
default rule e = max(200 σ̂², 0.01 m²) (issue #20) and the refusal to run without a
stopping criterion."""

import math

import numpy as np
import pytest
import scipy.stats
from test_features_plane_fit import _scene_scan

from lidarjax.features import (
    AUTO_FLOOR_M2,
    AUTO_KAPPA,
    TETROMINOES,
    PPEStop,
    auto_max_increment,
    estimate_noise,
    extract_planes,
    extract_planes_path,
    linearized_plane_error,
)
from lidarjax.features._ppe_reference import extract_planes_reference


def test_estimate_noise_recovers_radial_sigma():
    for sigma, seed in ((0.02, 0), (0.005, 1)):
        pts, _ = _scene_scan(h=40, w=50, sigma=sigma, seed=seed)
        assert abs(estimate_noise(pts) / sigma - 1.0) < 0.1


# ---------------------------------------------------------------------------------------
# Stopping criteria: no silent collapse, the default threshold rule (issue #20)
# ---------------------------------------------------------------------------------------


def test_no_stopping_criterion_raises():
    """Without e and J_max the greedy loop would merge every connected ray into one plane
    (stop PPEStop.EXHAUSTED); that must be an error naming both arguments."""
    pts, _ = _scene_scan(h=8, w=10, sigma=0.02, seed=3)
    for fn in (extract_planes, extract_planes_reference):
        with pytest.raises(ValueError, match="max_increment=None and max_planes=None"):
            fn(pts, max_increment=None)
        with pytest.raises(ValueError, match="max_increment"):
            fn(pts, max_increment="automatic")
    with pytest.raises(ValueError, match="max_increments"):
        extract_planes_path(pts, [1e-3, None])
    with pytest.raises(ValueError, match="max_increments"):
        extract_planes_path(pts, "auto")
    # an explicit "no threshold" still runs to the end, and J_max alone is a criterion
    assert extract_planes(pts, max_increment=math.inf, refit=False).stop is PPEStop.EXHAUSTED
    seg = extract_planes(pts, max_increment=None, max_planes=20, refit=False)
    assert seg.stop is PPEStop.MAX_PLANES


def _brute_force_sigma(pts):
    """sigma_hat from scratch: every 4-ray placement of the 17 tetrominoes, each fitted by
    least squares (linearized_plane_error), median / median of chi²(1)."""
    H, W = pts.shape[:2]
    errs = []
    for shape in TETROMINOES:
        for r in range(H - shape[:, 0].max()):
            for c in range(W - shape[:, 1].max()):
                errs.append(linearized_plane_error(pts[r + shape[:, 0], c + shape[:, 1]]))
    return np.sqrt(np.median(errs) / scipy.stats.chi2(1).median())


@pytest.mark.parametrize("sigma, branch", [(0.02, "kappa"), (0.0005, "floor")])
def test_auto_threshold_is_the_documented_rule(sigma, branch):
    """e = max(200 sigma_hat², 0.01 m²) with sigma_hat recomputed by brute force, and
    extract_planes(points) uses it."""
    pts, _ = _scene_scan(h=12, w=14, sigma=sigma, seed=8)
    sig = _brute_force_sigma(pts)
    expected = max(200.0 * sig**2, 0.01)
    assert (AUTO_KAPPA, AUTO_FLOOR_M2) == (200.0, 0.01)
    assert ("kappa" if 200.0 * sig**2 > 0.01 else "floor") == branch
    np.testing.assert_allclose(auto_max_increment(pts), expected, rtol=1e-9)
    auto = extract_planes(pts, refit=False)
    same = extract_planes(pts, max_increment=expected, refit=False)
    np.testing.assert_array_equal(auto.labels, same.labels)
    np.testing.assert_array_equal(auto.step_costs, same.step_costs)
    assert auto.stop is PPEStop.MAX_INCREMENT and auto.step_costs.max() <= expected
    ref = extract_planes_reference(pts)
    np.testing.assert_array_equal(ref.labels, auto.labels)
    path = extract_planes_path(pts, ["auto", 1e-4], refit=False)
    np.testing.assert_array_equal(path[0].labels, auto.labels)


def _synpeb_window(radial_sigma_m, angular_sigma_deg=1e-3, n=64):
    """A 64 x 64 window of a generated SynPEB-style scan at the full 500 x 500 angular
    resolution (0.14° x 0.12°): floor, a wall and four object faces of training scene 0."""
    from lidarjax.sim import make_synpeb_scene, simulate_synpeb_scan

    return simulate_synpeb_scan(
        make_synpeb_scene(seed=1000),
        shape=(n, n),
        radial_sigma_m=radial_sigma_m,
        angular_sigma_deg=angular_sigma_deg,
        seed=1007,
        azimuth_deg=(18.2, 18.2 + (n - 1) * 0.14),
        elevation_deg=(-15.7, -15.7 - (n - 1) * 60.0 / 499),
    )


def test_default_rule_neither_collapses_nor_over_segments():
    """Issue #20: at 0.4 mm radial noise 200 sigma_hat² (the old default) cuts planes into
    spurious pieces; the default rule gives the ground-truth planes at 0.4 mm and 20 mm."""
    from lidarjax.metrics import hoover_scores

    for radial, min_f in ((0.0004, 0.85), (0.02, 0.5)):
        scan = _synpeb_window(radial)
        seg = extract_planes(scan.points, max_distance_m=0.2, refit=False)
        h = hoover_scores(scan.labels, seg.labels)
        n_big = int((np.bincount(scan.labels.ravel())[1:] >= 50).sum())
        assert seg.stop is PPEStop.MAX_INCREMENT  # no collapse into one plane
        assert n_big >= 5 and seg.n_planes >= n_big - 1, (radial, seg.n_planes, n_big)
        assert h.n_noise <= 2 and h.n_over == 0 and h.n_under == 0, (radial, h)
        assert h.f >= min_f and h.k >= 0.9, (radial, h.f, h.k)
        if radial < 1e-3:  # the old relative rule over-segments the same scan
            old = extract_planes(
                scan.points,
                max_increment=200 * estimate_noise(scan.points) ** 2,
                max_distance_m=0.2,
                refit=False,
            )
            assert old.n_planes >= seg.n_planes + 5
            assert hoover_scores(scan.labels, old.labels).n_noise >= h.n_noise + 5
