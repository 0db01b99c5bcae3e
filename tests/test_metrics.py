"""Tests of the map and pose-likelihood metrics against hand-computed small examples."""

from __future__ import annotations

import jaxlie
import numpy as np
import pytest
from scipy import stats

from lidarjax.metrics import (
    dirac_divergence,
    gaussian_log_density,
    inverse_kl,
    kl_to_gaussian,
    map_rmse,
    p_ref,
    p_ref_rmse,
)


def test_p_ref_definition():
    lam = np.array([0.0, 0.5, 2.0, np.inf])
    np.testing.assert_allclose(p_ref(lam), [0.0, 1 - np.exp(-0.5), 1 - np.exp(-2.0), 1.0])
    np.testing.assert_allclose(p_ref(lam, 0.2), [0.0, 1 - np.exp(-0.1), 1 - np.exp(-0.4), 1.0])
    # Tiny rates: expm1 keeps full relative precision.
    np.testing.assert_allclose(p_ref(1e-20), 1e-20, rtol=1e-12)


def test_map_rmse_and_p_ref_rmse():
    a = np.array([[0.0, 1.0], [2.0, 3.0]])
    b = np.array([[1.0, 1.0], [2.0, 0.0]])
    np.testing.assert_allclose(map_rmse(a, b), np.sqrt((1 + 0 + 0 + 9) / 4))
    mask = np.array([[True, True], [False, False]])
    np.testing.assert_allclose(map_rmse(a, b, mask), np.sqrt(1 / 2))
    la, lb = np.array([0.0, 1.0, np.inf]), np.array([0.0, 2.0, 1.0])
    want = np.sqrt(((np.exp(-2) - np.exp(-1)) ** 2 + np.exp(-2.0)) / 3)
    np.testing.assert_allclose(p_ref_rmse(la, lb), want, rtol=1e-12)


def test_dirac_divergence_is_negative_sum():
    ll = np.array([[-1.5, -0.25], [0.5, -2.0]])
    np.testing.assert_allclose(dirac_divergence(ll), 3.25)
    assert dirac_divergence(np.array([-1.0, -np.inf])) == np.inf


POSES = np.array([[0.0, 0.0, 0.0], [0.3, -0.1, 0.2], [1.0, 0.5, -3.0], [-0.4, 0.2, 3.1]])
TRUE = np.array([0.05, 0.0, 0.1])
COV = np.diag([0.2, 0.3, 0.5]) + 0.05 * (np.ones((3, 3)) - np.eye(3))
LOGL = np.array([-10.0, -11.5, -20.0, -np.inf])


def _wrapped_diffs():
    d = POSES - TRUE
    d[:, 2] = (d[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return d


def test_gaussian_log_density_wraps_angles():
    want = stats.multivariate_normal(np.zeros(3), COV).logpdf(_wrapped_diffs())
    np.testing.assert_allclose(gaussian_log_density(POSES, TRUE, COV), want, rtol=1e-12)
    se2 = jaxlie.SE2.from_xy_theta(POSES[:, 0], POSES[:, 1], POSES[:, 2])
    true = jaxlie.SE2.from_xy_theta(*TRUE)
    np.testing.assert_allclose(gaussian_log_density(se2, true, COV), want, rtol=1e-9)


def test_inverse_kl_eq_7_29_by_hand():
    p = np.exp(LOGL - LOGL.max())
    p /= p.sum()
    g = stats.multivariate_normal(np.zeros(3), COV).pdf(_wrapped_diffs())
    nz = p > 0
    want = np.sum(p[nz] * np.log(p[nz] / g[nz]))
    np.testing.assert_allclose(inverse_kl(LOGL, POSES, TRUE, COV), want, rtol=1e-10)
    gn = g / g.sum()
    want_n = np.sum(p[nz] * np.log(p[nz] / gn[nz]))
    got_n = inverse_kl(LOGL, POSES, TRUE, COV, normalize_reference=True)
    np.testing.assert_allclose(got_n, want_n, rtol=1e-10)
    assert got_n >= 0
    # Likelihoods proportional to the Gaussian: the discrete divergence vanishes, and a
    # constant offset of the log-likelihoods changes nothing.
    logg = np.log(g)
    np.testing.assert_allclose(
        inverse_kl(logg + 7.0, POSES, TRUE, COV, normalize_reference=True), 0.0, atol=1e-12
    )


def test_kl_to_gaussian_eqs_8_24_8_25_by_hand():
    g = stats.multivariate_normal(np.zeros(3), COV).pdf(_wrapped_diffs())
    g /= g.sum()
    ll = LOGL[:3]
    p = np.exp(ll - ll.max())
    p /= p.sum()
    poses = POSES[:3]
    np.testing.assert_allclose(
        kl_to_gaussian(ll, poses, TRUE, COV), np.sum(np.log(g[:3] / g[:3].sum() / p)), rtol=1e-10
    )
    gd = g[:3] / g[:3].sum()
    np.testing.assert_allclose(
        kl_to_gaussian(ll, poses, TRUE, COV, estimator="discrete"),
        np.sum(gd * np.log(gd / p)),
        rtol=1e-10,
    )
    # A zero-likelihood sample makes the divergence infinite, not NaN.
    assert kl_to_gaussian(LOGL, POSES, TRUE, COV) == np.inf
    assert kl_to_gaussian(LOGL, POSES, TRUE, COV, estimator="discrete") == np.inf


def test_bad_inputs_raise_value_error_naming_argument():
    with pytest.raises(ValueError, match="rates"):
        p_ref([-1.0])
    with pytest.raises(ValueError, match="distance_m"):
        p_ref([1.0], 0.0)
    with pytest.raises(ValueError, match="a and b"):
        map_rmse(np.zeros(3), np.zeros(4))
    with pytest.raises(ValueError, match="mask"):
        map_rmse(np.zeros(3), np.zeros(3), np.zeros(3, bool))
    with pytest.raises(ValueError, match="mask"):
        map_rmse(np.zeros(3), np.zeros(3), np.ones(2, bool))
    with pytest.raises(ValueError, match="log_likelihoods"):
        dirac_divergence(np.zeros(0))
    with pytest.raises(ValueError, match="sample_poses"):
        inverse_kl(LOGL, POSES[:2], TRUE, COV)
    with pytest.raises(ValueError, match="log_lik_samples"):
        inverse_kl(np.array([np.nan, 0, 0, 0]), POSES, TRUE, COV)
    with pytest.raises(ValueError, match="cov"):
        inverse_kl(LOGL, POSES, TRUE, -COV)
    with pytest.raises(ValueError, match="true_pose"):
        kl_to_gaussian(LOGL, POSES, TRUE[:2], COV)
    with pytest.raises(ValueError, match="estimator"):
        kl_to_gaussian(LOGL, POSES, TRUE, COV, estimator="mc")
