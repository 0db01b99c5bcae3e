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
# # DCT maps and a decay-rate field of your own
#
# A **DCT map** (dissertation ch. 9) is a continuous decay-rate map: the square of a sum of
# cosines, `λ(x) = (Σ a_i φ_i(x))²`, fitted to rays by maximum likelihood (L-BFGS, optimistix)
# and differentiable everywhere, so scans can be matched to it by gradient descent.
# lidarjax's field interface lets any function of position be a decay-rate map: this
# notebook fits a DCT map and a field written in ten lines, and compares them with a grid.

# %%
import jax
import jax.numpy as jnp
import jaxlie
import matplotlib.pyplot as plt
import numpy as np

import lidarjax
from lidarjax import maps, plot
from lidarjax.datasets import fetch, load_carmen
from lidarjax.localization import FieldScan, refine_dct_scan_pose, refine_pose
from lidarjax.rays import RayBatch, from_scan
from lidarjax.raytrace import GridSpec, accumulate

lidarjax.enable_compilation_cache()

# %% [markdown]
# ## Rays in a 10 m × 10 m patch of the Intel lab

# %%
log = load_carmen(fetch("intel"))
T = jaxlie.SE2.from_xy_theta(*log.poses.T)
flat = from_scan(T, log.azimuths_rad, log.ranges_m, 0.0, log.usable_range_m).flatten()
lower, extent = np.array([-8.0, -8.0]), np.array([10.0, 10.0])
box = maps.DCTMap(jnp.zeros((24, 24)), lower, extent)
keep = np.flatnonzero(np.asarray(maps.rays_in_box(box, flat) & (flat.kind == 0)))[::20]
patch = RayBatch(flat.origins[keep], flat.directions[keep], flat.ranges[keep],
                 flat.kind[keep], flat.r_min, flat.r_max)
print(f"{patch.shape[0]} rays in the patch")

# %% [markdown]
# ## Fit a 24 × 24 DCT map

# %%
dct, sol = maps.fit_dct(patch, (24, 24), lower=lower, extent=extent)
ll_dct = maps.dct_log_likelihood(dct, patch)  # [n] nats per ray, closed form (Eqs. 9.9-9.12)
print(f"{sol.stats['num_steps']} L-BFGS steps, mean log-likelihood {float(ll_dct.mean()):.3f}")

# %% [markdown]
# ## A field of your own: Gaussian bumps on a 6 × 6 lattice
# Subclass `maps.AbstractQuadratureField`, say what `λ(x)` is inside the box, and every
# tool works on it: the forward model, `maps.fit`, pose refinement.


# %%
class Bumps(maps.AbstractQuadratureField):
    w: jax.Array  # [6 6] weights: what maps.fit optimises
    lower: jax.Array  # the box (m); lambda = 0 outside
    extent: jax.Array

    def rate_in_box(self, x):  # lambda(x) in 1/m, >= 0 for every w
        u = (x - self.lower) / self.extent * 6 - 0.5
        g = jnp.exp(-0.5 * ((u[..., None] - jnp.arange(6)) / 0.7) ** 2)
        return jax.nn.softplus(jnp.einsum("...i,ij,...j->...", g[..., 0, :], self.w,
                                          g[..., 1, :]))


bumps0 = Bumps(w=jnp.zeros((6, 6)), lower=jnp.asarray(lower), extent=jnp.asarray(extent))
bumps, sol_b = maps.fit(bumps0, patch, max_steps=200)
grid = maps.decay_rate_map(accumulate(GridSpec(lower, 10 / 6, (6, 6)), patch),
                           unknown_rate=0.0)
for name, field in [("6 x 6 grid", grid), ("24 x 24 DCT", dct), ("6 x 6 bumps", bumps)]:
    ll = float(maps.field_log_likelihood(field, patch).mean())
    print(f"{name:12s} mean log-likelihood {ll:8.3f} nats")

# %%
fig, axes = plt.subplots(1, 2, figsize=(10, 4.2), constrained_layout=True)
plot.plot_map(dct, ax=axes[0], title="DCT map (24 x 24)")
plot.plot_map(bumps, ax=axes[1], title="user-defined field (6 x 6 bumps)")
plt.show()

# %% [markdown]
# ## Scan matching on the DCT map
# A scan taken inside the patch, started 0.42 m and 3° off, matched by gradient ascent of
# its log-likelihood (coarse to fine).

# %%
s = 675
start = jaxlie.SE2.from_xy_theta(log.poses[s, 0] + 0.3, log.poses[s, 1] - 0.3,
                                 log.poses[s, 2] + 0.05)
matched, _ = refine_dct_scan_pose(dct, log.azimuths_rad, log.ranges_m[s], start, 0.0,
                                  log.usable_range_m)
pose_b, _ = refine_pose(FieldScan(bumps, log.azimuths_rad, log.ranges_m[s], 0.0,
                                  log.usable_range_m), start)
for name, p in [("start", start), ("DCT", matched), ("bumps", pose_b)]:
    e = np.linalg.norm(np.asarray(p.translation()) - log.poses[s, :2])
    print(f"{name:6s} position error {e:.3f} m")
