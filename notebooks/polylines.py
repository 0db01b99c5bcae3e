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
# # Polylines from a 2-D scan: PLE and PLE+
#
# **PLE** (dissertation ch. 10) grows polylines greedily so that every added vertex explains
# the most rays; **PLE+** then moves the vertices to maximise the scan likelihood
# (Levenberg–Marquardt with exact acceptance: the result is never worse than PLE's and
# explains the same rays). Both work on a `RayBatch` in the sensor frame.

# %%
import jaxlie
import matplotlib.pyplot as plt
import numpy as np

import lidarjax
from lidarjax import features, metrics, plot
from lidarjax.datasets import fetch, load_carmen
from lidarjax.rays import from_scan

lidarjax.enable_compilation_cache()

# %%
log = load_carmen(fetch("intel"))
s = 675
scan = from_scan(jaxlie.SE2.identity(), log.azimuths_rad, log.ranges_m[s], 0.0,
                 log.usable_range_m)  # [180] rays in the sensor frame
reflected = np.asarray(scan.kind) == 0

# %% [markdown]
# ## Error against the number of vertices J

# %%
rows = []
for J in (10, 20, 30):
    ple = features.extract_polylines(scan, max_vertices=J)
    plus = features.optimize_polylines(ple, scan)
    for name, m in (("PLE", ple.map), ("PLE+", plus.map)):
        r_hat = np.asarray(m.expected_ranges(scan))  # [180] m, inf where no polyline
        rows.append((J, name, 1000 * metrics.ray_rmse(np.asarray(scan.ranges), r_hat, reflected),
                     metrics.explained_fraction(r_hat, reflected)))
print(f"{'J':>3} {'method':6} {'RMSE (mm)':>10} {'explained':>10}")
for J, name, rmse, f in rows:
    print(f"{J:3d} {name:6} {rmse:10.1f} {100 * f:9.1f}%")

# %% [markdown]
# ## The scan and its polylines (J = 20)

# %%
ple = features.extract_polylines(scan, max_vertices=20)
plus = features.optimize_polylines(ple, scan)
fig, axes = plt.subplots(1, 2, figsize=(11, 5), constrained_layout=True)
ends = np.asarray(scan.endpoints())
for ax, (name, m) in zip(axes, (("PLE", ple.map), ("PLE+", plus.map))):
    lines, closed = m.to_polylines()
    plot.plot_polyline_scan(ax, np.zeros(2), ends, reflected, lines, closed, title=name)
plt.show()
