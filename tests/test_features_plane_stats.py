"""Sufficient statistics of PPE's linearised clustering error
(lidarjax/features/_plane_stats.py) against least squares from scratch."""

import numpy as np
from test_features_plane_fit import _fit, _plane_rays

from lidarjax.features import linearized_plane_error
from lidarjax.features._plane_stats import (
    _merge_py,
    _points_stats,
    _stats_error,
    _stats_error_py,
)

# ---------------------------------------------------------------------------------------
# Linearised clustering error (sufficient statistics)
# ---------------------------------------------------------------------------------------


def test_stats_error_equals_lstsq_and_merges_exactly():
    rng = np.random.default_rng(3)
    for n in (4, 9, 50):
        a, b = rng.normal([3, 0, 0], 0.4, (n, 3)), rng.normal([3, 1, 0.5], 0.4, (n + 2, 3))
        Wa, ma, Ca = _points_stats(a)
        Wb, mb, Cb = _points_stats(b)
        np.testing.assert_allclose(_stats_error(Wa, ma, Ca), linearized_plane_error(a), rtol=1e-9)
        st = _merge_py(
            (float(Wa), *ma.tolist(), *Ca.tolist()), (float(Wb), *mb.tolist(), *Cb.tolist())
        )
        W, m, C = st[0], np.array(st[1:4]), np.array(st[4:])
        np.testing.assert_allclose(_stats_error_py(st), _stats_error(W, m, C), rtol=1e-12)
        Wr, mr, Cr = _points_stats(np.concatenate([a, b]))
        np.testing.assert_allclose(W, Wr, rtol=1e-13)
        np.testing.assert_allclose(m, mr, rtol=1e-12)
        np.testing.assert_allclose(C, Cr, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(
            _stats_error(W, m, C), linearized_plane_error(np.concatenate([a, b])), rtol=1e-9
        )


def test_linearized_error_tracks_the_exact_ray_path_error():
    """E_lin = Σ (r - r̂)² (r / r̂)²: within a few % of Eq. 11.2 at 20 mm noise, 2-5 m."""
    for seed in range(4):
        normal = np.array([1.0, 0.3 * seed - 0.4, -0.2])
        o, d, r = _plane_rays(60, normal, 2.0 + seed, 0.02, seed=seed)
        exact = float(_fit(o, d, r).error)
        lin = linearized_plane_error(d * r[:, None])
        assert abs(lin / exact - 1.0) < 0.03
