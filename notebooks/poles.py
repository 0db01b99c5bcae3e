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
# # Poles: landmarks from 3-D lidar and localization against them
#
# Dissertation ch. 12: pole-like landmarks (trunks, lamp posts, sign posts) are extracted
# from a local occupancy map of a few scans, merged over a drive into a landmark map, and a
# particle filter localizes against it. This notebook drives a simulated car along the
# first 80 poses of KITTI-00 through a generated urban world.

# %%
import jaxlie
import matplotlib.pyplot as plt
import numpy as np

import lidarjax
from lidarjax import features, plot
from lidarjax import localization as loc
from lidarjax.datasets import load_urban_trajectory
from lidarjax.rays import from_spinning_scan
from lidarjax.sim import hdl32e, make_urban_world, simulate_urban_scan

lidarjax.enable_compilation_cache()

# %%
gt = load_urban_trajectory().xy_yaw[:80]  # x (m), y (m), yaw (rad)
world = make_urban_world(gt, seed=0)  # poles, facades, cars, crowns, barrels
lidar = hdl32e(n_azimuths=540)  # 32 rings, 540 azimuths (small for the notebook)
cfg = features.PoleConfig(extent_m=(20.0, 20.0, 4.0))


def local_poles(i):
    """Poles (world frame) of the local map of scans i and i+1."""
    idx = [i, i + 1]
    ranges = np.stack([simulate_urban_scan(world, gt[j], lidar, seed=j).ranges_m for j in idx])
    T = jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.from_z_radians(gt[idx, 2]),
        np.column_stack([gt[idx, :2], np.full(2, lidar.mount_height_m)]),
    )
    rays = from_spinning_scan(T, lidar.directions(), ranges, lidar.min_range_m, lidar.max_range_m)
    return features.extract_poles(rays, features.local_map_spec(gt[i, :2], cfg), cfg)


local = [local_poles(i) for i in range(0, 78, 6)]
pole_map = loc.map_poles(local, c=1, w=1)
d = np.linalg.norm(pole_map.xy[:, None] - world.pole_xy[None], axis=-1).min(1)
print(f"{len(pole_map)} landmarks mapped; distance to the nearest true pole: "
      f"median {np.median(d):.3f} m")

# %%
plot.plot_poles(pole_map, poses=gt, truth=world.pole_xy)
plt.show()

# %% [markdown]
# ## Which pose explains the poles best?
# The measurement model scores a pose by the distances of the observed poles to their
# nearest landmarks; here the map seen from the true pose against two wrong guesses.

# %%
model = loc.PoleMeasurementModel(pole_map.xy, var_m2=1.0, eps=0.1)
c, s_ = np.cos(gt[40, 2]), np.sin(gt[40, 2])
near = (pole_map.xy - gt[40, :2]) @ np.array([[c, -s_], [s_, c]])
guesses = loc.from_vector(gt[40] + np.array([[0, 0, 0], [0.5, 0, 0], [0, 1.0, 0]]))
print("log-likelihood (truth, +0.5 m x, +1 m y):",
      np.round(np.asarray(model(guesses, (near, np.ones(len(near), bool)))), 2))
