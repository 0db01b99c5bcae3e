"""Bring your own decay-rate field — a notebook-style example (run it, or step through the
``# %%`` cells in an editor).

The decay-rate model needs no cells (dissertation ch. 1.3, 3): any non-negative field
``lambda(x)`` gives a forward model ``p(r) = lambda(s + r v) exp(-int_0^r lambda)`` and can be
fitted by maximum likelihood. Here a field that lidarjax does not ship — a lattice of
Gaussian radial basis functions squashed by ``softplus`` — is written in a few lines by
subclassing :class:`lidarjax.maps.AbstractQuadratureField`, fitted to a 10 m x 10 m patch of
the Intel log with :func:`lidarjax.maps.fit`, and compared in held-out-ray log-likelihood
with a grid map and a DCT map of the same parameter count.

``python experiments/custom_field.py [log] [L]`` (default ``intel 20``): writes
``outputs/custom_field/custom_field.png`` and prints the comparison. The Hydra experiment
``experiments/decay_rate_fields.py`` runs the same comparison on every shared log and all
parameter budgets (it imports :class:`RBFField` and :func:`rbf_field_like` from here).
"""

# %% 1. The field: ~25 lines -------------------------------------------------------------
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from lidarjax import enable_compilation_cache, maps


class RBFField(maps.AbstractQuadratureField):
    """``lambda(x) = softplus(sum_ij w_ij exp(-|x - c_ij|^2 / (2 sigma^2)))`` (1/m) with
    centres ``c_ij`` on an ``n x m`` lattice (cell centres) over the box; ``n m`` parameters
    ``w``, ``sigma = width * lattice spacing``. Positive for every ``w`` (softplus), so
    :func:`lidarjax.maps.fit` can optimise ``w`` without constraints."""

    weights: Float[Array, "n m"]  # the parameters (what `fit` optimises)
    lower: Float[Array, " 2"]  # the box, required by AbstractQuadratureField
    extent: Float[Array, " 2"]
    width: float = eqx.field(static=True, default=0.7)  # sigma in lattice spacings
    n_nodes: int = eqx.field(static=True, default=64)  # Gauss-Legendre nodes per ray

    def rate_in_box(self, points):
        n, m = self.weights.shape
        u = (points - self.lower) / self.extent * jnp.array([n, m]) - 0.5  # lattice coords
        gx = jnp.exp(-0.5 * ((u[..., :1] - jnp.arange(n)) / self.width) ** 2)  # [... n]
        gy = jnp.exp(-0.5 * ((u[..., 1:] - jnp.arange(m)) / self.width) ** 2)  # [... m]
        return jax.nn.softplus(jnp.sum((gx @ self.weights) * gy, axis=-1))

    def quadrature_nodes(self):
        return self.n_nodes


# %% 2. A start: the ML grid map, pushed through the inverse softplus ---------------------
def rbf_field_like(
    grid: maps.DecayRateMap, *, width: float = 0.7, nodes_per_sigma: float = 3.0
) -> RBFField:
    """An :class:`RBFField` with one centre per cell of ``grid`` (its box, its shape) whose
    weights make ``lambda`` roughly the grid's rates (clipped to [0.01, 20] 1/m); enough
    quadrature nodes for ``nodes_per_sigma`` nodes per Gaussian width along the box
    diagonal."""
    lam = jnp.clip(grid.rates, 0.01, 20.0)
    g = lam + jnp.log(-jnp.expm1(-lam))  # softplus^-1
    spacing = float(grid.spec.resolution)
    extent = jnp.asarray(grid.spec.shape, g.dtype) * spacing
    n_nodes = math.ceil(nodes_per_sigma * float(jnp.linalg.norm(extent)) / (width * spacing))
    return RBFField(
        weights=g / (2 * math.pi * width**2),  # a Gaussian lattice sums to ~2 pi width^2
        lower=grid.spec.origin,
        extent=extent,
        width=width,
        n_nodes=n_nodes,
    )


# %% 3. Data: a 10 m x 10 m patch, mapping rays from even scans, test rays from odd scans --
def patch_rays(name: str, n_rays: int, *, size: float = 10.0, seed: int = 0):
    """``(train, test, lower)``: up to ``n_rays`` HIT rays each from even / odd scans that
    end in the ``size`` x ``size`` m patch with the most end points (1 m aligned)."""
    from _common import scan_rays
    from dct_maps import densest_patch

    from lidarjax.datasets import fetch, load_carmen
    from lidarjax.rays import HIT, RayBatch

    log = load_carmen(fetch(name))
    rays = scan_rays(log, None, 0.0, log.usable_range_m)
    ends = np.asarray(rays.origins + rays.ranges[..., None] * rays.directions)
    hit = np.asarray(rays.kind) == HIT
    lo = densest_patch(ends[hit], size)  # the patch of experiments/dct_maps.py
    inside = hit & np.all((ends >= lo) & (ends <= lo + size), axis=-1)
    scan = np.arange(log.n_scans)[:, None] + np.zeros(inside.shape[1], int)
    rng = np.random.default_rng(seed)
    out = []
    for parity in (0, 1):
        idx = np.flatnonzero((inside & (scan % 2 == parity)).reshape(-1))
        idx = np.sort(rng.choice(idx, min(n_rays, idx.size), replace=False))
        flat = rays.flatten()
        out.append(
            RayBatch(
                flat.origins[idx],
                flat.directions[idx],
                flat.ranges[idx],
                flat.kind[idx],
                flat.r_min,
                flat.r_max,
            )
        )
    return out[0], out[1], lo


# %% 4. Fit three fields with the same parameter count and compare on held-out rays -------
def held_out(field, rays, floor: float = -10.0):
    """``(mean per-ray log-likelihood with each ray floored at floor nats, rays floored)``."""
    ll = np.asarray(maps.field_log_likelihood(field, rays))
    return float(np.mean(np.maximum(ll, floor))), int(np.sum(ll < floor))


def main(name: str = "intel", L: int = 20, n_rays: int = 2000) -> dict:
    enable_compilation_cache()  # a second run loads the compiled programs
    from lidarjax.raytrace import GridSpec, accumulate

    jax.config.update("jax_enable_x64", True)
    train, test, lower = patch_rays(name, n_rays)
    spec = GridSpec(lower, 10.0 / L, (L, L))
    grid = maps.decay_rate_map(accumulate(spec, train), unknown_rate=0.0)  # Eq. 7.10
    t = time.perf_counter()
    dct, _ = maps.fit_dct(train, (L, L), lower=lower, extent=[10.0, 10.0], rtol=1e-4, atol=1e-4)
    t_dct = time.perf_counter() - t
    t = time.perf_counter()
    rbf, sol = maps.fit(rbf_field_like(grid), train, rtol=1e-4, atol=1e-4, max_steps=500)
    t_rbf = time.perf_counter() - t
    rows = {"grid": held_out(grid, test), "dct": held_out(dct, test), "rbf": held_out(rbf, test)}
    print(f"{name}, {L}x{L} = {L * L} parameters, {train.n} mapping / {test.n} test rays")
    for key, (ll, n_floor) in rows.items():
        print(f"  {key:4s}: held-out log-likelihood {ll:8.4f} nats/ray ({n_floor} rays floored)")
    print(f"  fit times: DCT {t_dct:.2f} s, RBF {t_rbf:.2f} s ({sol.stats['num_steps']} steps)")

    # %% 5. A picture: the three fields side by side
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lidarjax.plot import plot_map

    # p_ref = 1 - exp(-lambda * 1 m) of each field on a 0.05 m raster of the patch (the grid
    # map cell by cell), in world coordinates (m), with one labelled colour bar per panel
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.4), layout="constrained")
    for ax, (key, fld) in zip(axes, (("grid", grid), ("DCT", dct), ("RBF (user)", rbf))):
        plot_map(
            fld, ax=ax, quantity="p_ref", cmap="gray_r", resolution_m=0.05,
            title=f"{key}, {L * L} parameters",
        )  # fmt: skip
    fig.suptitle(f"{name}: decay-rate fields fitted to {train.n} rays of a 10 m x 10 m patch")
    out = Path("outputs/custom_field")
    out.mkdir(parents=True, exist_ok=True)
    fig.savefig(out / "custom_field.png", dpi=120, bbox_inches="tight")
    return rows


if __name__ == "__main__":
    args = sys.argv[1:]
    main(args[0] if args else "intel", int(args[1]) if len(args) > 1 else 20)
