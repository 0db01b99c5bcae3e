# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3 (ipykernel)
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Gradients you can trust
#
# lidarjax's models are differentiable: DCT maps and decay-rate fields are fitted by
# gradient descent, poses are refined with pose gradients. This notebook checks those
# gradients three ways, in float64:
#
# 1. against the dissertation's **closed-form derivatives** (DCT maps, Sec. 9.4.4),
# 2. against **central finite differences** (`lidarjax.testing.finite_difference`),
# 3. forward against reverse mode (`lidarjax.testing.check_gradients` does 2 and 3 at once,
#    on pytrees and on SE(2)/SE(3) poses).

# %%
import jax

jax.config.update("jax_enable_x64", True)  # gradient checks in float64

import jax.numpy as jnp
import jaxlie
import numpy as np

import lidarjax
from lidarjax import maps, testing
from lidarjax.datasets import fetch, load_carmen
from lidarjax.localization import SmoothDecayRateScan
from lidarjax.rays import RayBatch, from_scan
from lidarjax.raytrace import GridSpec, accumulate

lidarjax.enable_compilation_cache()

# %% [markdown]
# ## Rays of a real log in a 10 m × 10 m patch: hits, short readings, no-returns

# %%
log = load_carmen(fetch("intel"))
T = jaxlie.SE2.from_xy_theta(*log.poses.T)
# r_min = 0.5 m: shorter readings are SUB rays ("something closer than r_min")
rays = from_scan(T, log.azimuths_rad, log.ranges_m, 0.5, log.usable_range_m).flatten()
lower, extent = np.array([-8.0, -8.0]), np.array([10.0, 10.0])
box = maps.DCTMap(jnp.zeros((6, 6)), lower, extent)
inside = np.asarray(maps.rays_in_box(box, rays))
kind = np.asarray(rays.kind)  # 0 HIT, 1 SUB, 2 SUP
keep = np.concatenate([np.flatnonzero(inside & (kind == k))[::97][:15] for k in (0, 1, 2)])
patch = RayBatch(rays.origins[keep], rays.directions[keep], rays.ranges[keep],
                 rays.kind[keep], rays.r_min, rays.r_max)
print(patch.counts())

# %% [markdown]
# ## 1. DCT map: closed form vs `jax.grad` vs finite differences
# A 6 × 6 DCT map with random coefficients. Sec. 9.4.4 gives the per-ray gradient and
# Hessian of the log-likelihood in the coefficients (HIT: `B_i/λ − C_i`, SUB:
# `N C_i / (1 − N)`, SUP: `−C_i`).

# %%
coeffs = jnp.asarray(np.random.default_rng(0).normal(0.0, 0.3, (6, 6)))
dct = maps.DCTMap(coeffs, lower, extent)


def total_ll(c):
    return jnp.sum(maps.dct_log_likelihood(dct.with_parameters(c), patch, method="paper"))


g_closed, h_closed = maps.dct_closed_form_derivatives(dct, patch)  # [n 36], [n 36 36]
g_auto = jax.grad(total_ll)(coeffs).reshape(-1)
h_auto = jax.hessian(total_ll)(coeffs).reshape(36, 36)
g_fd = testing.finite_difference(total_ll, coeffs).reshape(-1)
print("gradient: |closed - autodiff| =", float(jnp.max(jnp.abs(g_closed.sum(0) - g_auto))))
print("gradient: |autodiff - FD|     =", float(jnp.max(jnp.abs(g_auto - g_fd))))
print("Hessian:  |closed - autodiff| =", float(jnp.max(jnp.abs(h_closed.sum(0) - h_auto))))

# %% [markdown]
# The dissertation prints the last SUB Hessian term with a `+`; differentiating its own
# gradient gives a `−`, which autodiff confirms: `sub_hessian="paper"` returns the printed
# version, and it disagrees wherever SUB rays contribute.

# %%
_, h_paper = maps.dct_closed_form_derivatives(dct, patch, sub_hessian="paper")
print("printed Hessian vs autodiff:", float(jnp.max(jnp.abs(h_paper.sum(0) - h_auto))))

# %% [markdown]
# ## 2. `check_gradients`: forward, reverse and finite differences in one call
# It raises an `AssertionError` naming the leaf and the error when anything disagrees,
# and returns the largest errors when all agree.

# %%
report = testing.check_gradients(total_ll, coeffs)
print(report)

# %% [markdown]
# ## 3. Pose gradients of a scan on a smooth decay-rate field
# On a grid map the end-point rate jumps from cell to cell, so the scan log-likelihood is
# only piecewise smooth in the pose. `SmoothDecayRateScan` blurs the grid statistics into a
# smooth field (see its docstring for where its derivative is continuous). Derivatives with
# respect to a pose are taken in its tangent space (right perturbation `T ∘ exp(δ)`).

# %%
spec = GridSpec.covering(np.asarray(rays.endpoints()[rays.kind == 0]), 0.1, margin=3.0)
field = maps.SmoothDecayRateField(maps.decay_rate_map(accumulate(spec, rays)), blur_m=0.15)
s = 300
obj = SmoothDecayRateScan(field, log.azimuths_rad, log.ranges_m[s], 0.0, log.usable_range_m)
pose = jaxlie.SE2.from_xy_theta(log.poses[s, 0] + 0.05, log.poses[s, 1] - 0.04,
                                log.poses[s, 2] + 0.01)
print("autodiff:", np.asarray(testing.manifold_jacobian(obj, pose)))
print("FD:      ", np.asarray(testing.manifold_finite_difference(obj, pose)))
