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
# # Quickstart: a map, a particle filter, and files you can take elsewhere
#
# This notebook loads a real CARMEN log (Intel Research Lab, 910 scans of 180 beams),
# builds a **decay-rate map** (dissertation ch. 7, Eq. 7.10) from half of the scans at their
# corrected poses, **localizes** the other half with a particle filter started from raw
# odometry around a wrong initial pose, and **saves** the map and the trajectory.
#
# Every function here is pure and jit-compiled; the first call of each compiles (a few
# seconds), which the persistent compilation cache turns into well under a second in the
# next process.

# %%
import jax
import jaxlie
import matplotlib.pyplot as plt
import numpy as np

import lidarjax
from lidarjax import localization as loc
from lidarjax import maps, plot
from lidarjax.datasets import fetch, load_carmen
from lidarjax.rays import from_scan
from lidarjax.raytrace import GridSpec, accumulate

lidarjax.enable_compilation_cache()  # compiled programs are reused by the next process

# %% [markdown]
# ## Load a log
# `fetch` finds the file through the checksummed registry (`$LIDARJAX_DATA`, then
# `../shared/data`, then the user cache) and verifies its SHA-256.

# %%
log = load_carmen(fetch("intel"))
print(f"{log.n_scans} scans x {log.ranges_m.shape[1]} beams, "
      f"usable range {log.usable_range_m:.1f} m")

# %% [markdown]
# ## A decay-rate map from the even scans
# Each reading becomes a ray: a HIT (reflected within range), or a SUP ray (no return).
# `accumulate` traces every ray through the grid exactly and sums per cell the hits `H`,
# misses `M` and the travelled length `R`; the maximum-likelihood decay rate is
# `λ = H / R` (1/m).

# %%
even = np.arange(0, log.n_scans, 2)
T = jaxlie.SE2.from_xy_theta(*log.poses[even].T)
rays = from_scan(T, log.azimuths_rad, log.ranges_m[even], 0.1, log.usable_range_m)
spec = GridSpec.covering(np.asarray(rays.endpoints()[rays.kind == 0]), 0.1, margin=3.0)
stats = accumulate(spec, rays)
lam = maps.decay_rate_map(stats)
print(f"grid {spec.shape} cells of {spec.resolution} m, {rays.counts()}")

# %%
ax = plot.plot_map(lam, title="Intel: decay-rate map (even scans)")
plt.show()

# %% [markdown]
# ## Localize the odd scans
# A particle filter (`lax.scan` over the steps) with the raw odometry as controls and the
# decay-rate map as the measurement model, on 30 of the 180 beams, started 0.3 m and
# 0.1 rad around the first pose.

# %%
odd = np.arange(1, 121, 2)  # 60 scans (small for the notebook; the log has 455)
beams = np.arange(0, 180, 6)
motion = loc.OdometryMotionModel(
    sigma=[0.02, 0.02, 0.01], alpha=[[0.1, 0, 0], [0, 0.1, 0], [0.05, 0, 0.1]]
)
scan_model = loc.ScanModel(lam, log.azimuths_rad[beams], 0.1, log.usable_range_m,
                           ray_floor=-10.0)
pf = loc.ParticleFilter(motion, scan_model)
state = loc.init_gaussian(500, log.poses[odd[0]], [0.3, 0.3, 0.1], key=jax.random.key(0))
controls = loc.relative_motion(log.odometry[odd])
state, info = pf.run(state, controls, log.ranges_m[odd[1:]][:, beams])
track = np.asarray(loc.to_vector(info.estimate))  # [59 3] x (m), y (m), θ (rad)

err = np.linalg.norm(track[:, :2] - log.poses[odd[1:], :2], axis=1)
dth = np.angle(np.exp(1j * (track[:, 2] - log.poses[odd[1:], 2])))
print(f"position error: mean {err.mean():.3f} m, final {err[-1]:.3f} m; "
      f"heading error: mean {np.degrees(np.abs(dth)).mean():.2f} deg")

# %%
plot.plot_localization(lam, track, truth=log.poses[odd[1:]])
plt.show()

# %% [markdown]
# ## Save the map and the trajectory
# The map as NumPy arrays with its grid (origin and resolution in metres), the trajectory
# in the TUM format (`t x y z qx qy qz qw`, one pose per line) that `evo` reads.

# %%
import tempfile
from pathlib import Path

out = Path(tempfile.mkdtemp())
np.savez(out / "intel_decay_rate.npz", rates=np.asarray(lam.rates),
         origin=np.asarray(spec.origin), resolution=float(spec.resolution))
t = log.timestamps_s[odd[1:]]
q = np.stack([np.zeros_like(track[:, 2]), np.zeros_like(track[:, 2]),
              np.sin(track[:, 2] / 2), np.cos(track[:, 2] / 2)], axis=1)
tum = np.column_stack([t, track[:, 0], track[:, 1], np.zeros(len(track)), q])
np.savetxt(out / "intel_track.tum", tum, fmt="%.9f")
print(sorted(p.name for p in out.iterdir()))
