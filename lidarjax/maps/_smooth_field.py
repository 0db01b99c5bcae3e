"""A continuous decay-rate field from a 2-D grid map: the bilinear interpolant of the
(optionally Gaussian-blurred) cell rates (dissertation ch. 1.3 and 3: decay-rate maps make
the scan likelihood differentiable in the pose).

On a grid decay-rate map the exact scan likelihood is only piecewise smooth in the pose:
the end-point term ``log lambda_k`` jumps between cells, so its gradient says nothing about
where the end points should go. Interpolating the cell rates bilinearly between the cell
centres makes ``lambda(x)`` continuous, and a Gaussian blur of the rates widens the basin
of pose refinement. :class:`SmoothDecayRateField` is an
:class:`~lidarjax.maps.AbstractDecayRateField`, so the one forward model
(:func:`~lidarjax.maps.field_log_likelihood`) and the one scan objective
(:class:`~lidarjax.localization.refine.FieldScan`) apply to it unchanged.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._math import mul0
from ._field import AbstractDecayRateField, box_segment
from ._grid import DecayRateMap
from ._smoothing import blur

__all__ = ["SmoothDecayRateField"]


def _native_chord_impl(n_nodes, rates, origin, resolution, origins, directions, t0, chord):
    from ..raytrace import _native

    return _native.chord_integral(
        rates, origin, resolution, origins, directions, t0, chord, n_nodes
    )


def _grid_tangents_are_zero(tangents):
    from jax.custom_derivatives import SymbolicZero

    for name, t in zip(("rates", "grid origin", "resolution"), tangents[:3]):
        if not isinstance(t, SymbolicZero):
            raise NotImplementedError(
                f"SmoothDecayRateField(backend='native').integral is differentiable in the "
                f"rays only, not in the {name}: build the field with backend='jax' to "
                "differentiate in the grid"
            )


def _ray_tangents(primals, tangents):
    """``[n 6]`` tangents of the ray parameters ``(o_x, o_y, d_x, d_y, t0, chord)``
    (symbolic zeros materialised)."""
    from jax.custom_derivatives import SymbolicZero

    cols = []
    for p, t in zip(primals[3:], tangents[3:]):
        t = jnp.zeros_like(p) if isinstance(t, SymbolicZero) else t
        cols.append(t if t.ndim == 2 else t[:, None])
    return jnp.concatenate(cols, axis=1)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _native_chord(n_nodes, rates, origin, resolution, origins, directions, t0, chord):
    """``[n]`` optical depths of the chords ``[t0, t0 + chord]`` by the native kernel,
    differentiable (forward and reverse mode, to second order) in the rays, not in the
    grid."""
    return _native_chord_impl(n_nodes, rates, origin, resolution, origins, directions, t0, chord)[0]


def _stacked_gradient(g_o, g_d, g_t0, g_c):
    """``[n 6]`` gradient in ``(o_x, o_y, d_x, d_y, t0, chord)``."""
    return jnp.concatenate([g_o, g_d, g_t0[:, None], g_c[:, None]], axis=1)


def _native_chord_jvp(n_nodes, primals, tangents):
    _grid_tangents_are_zero(tangents)
    value, *grads = _native_chord_grads(n_nodes, *primals)
    return value, jnp.sum(_stacked_gradient(*grads) * _ray_tangents(primals, tangents), axis=1)


_native_chord.defjvp(_native_chord_jvp, symbolic_zeros=True)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _native_chord_grads(n_nodes, rates, origin, resolution, origins, directions, t0, chord):
    """``(F, dF/dorigins, dF/ddirections, dF/dt0, dF/dchord)`` by the native kernel; its
    own derivatives (the second derivatives of ``F``) come from the Hessian kernel."""
    return _native_chord_impl(n_nodes, rates, origin, resolution, origins, directions, t0, chord)


def _native_chord_grads_jvp(n_nodes, primals, tangents):
    from ..raytrace import _native

    _grid_tangents_are_zero(tangents)
    outs = _native_chord_impl(n_nodes, *primals)
    g = _stacked_gradient(*outs[1:])
    xdot = _ray_tangents(primals, tangents)
    hess = _native.chord_hessian(*primals, n_nodes)
    gdot = jnp.einsum("nab,nb->na", hess, xdot)
    tans = (jnp.sum(g * xdot, axis=1), gdot[:, 0:2], gdot[:, 2:4], gdot[:, 4], gdot[:, 5])
    return outs, tans


_native_chord_grads.defjvp(_native_chord_grads_jvp, symbolic_zeros=True)


def _check_nodes(n_nodes) -> int:
    if isinstance(n_nodes, bool) or not isinstance(n_nodes, (int, np.integer)) or n_nodes <= 0:
        raise ValueError(f"n_nodes must be a positive int, got {n_nodes!r}")
    return int(n_nodes)


class SmoothDecayRateField(AbstractDecayRateField):
    """Continuous decay-rate field of a 2-D grid map: the bilinear interpolant of the cell
    rates (optionally Gaussian-blurred), sampled at cell centres and clamped to the border
    cells' values between the outermost centres and the grid border; ``outside_rate`` off
    the grid.

    The optical depth (:meth:`integral`) is the midpoint rule with :attr:`n_nodes` nodes
    over the part of the ray inside the grid box, plus ``outside_rate`` times the length
    outside it. The node spacing is ``chord / n_nodes``: the default 256 nodes keep it
    below half a cell for chords up to 128 cells; longer chords are integrated more
    coarsely. The rule is exact for fields linear along the ray; otherwise its error is
    ``O(spacing^2)`` per cell crossed (the interpolant is quadratic along a ray between
    crossings of the cell-centre lattice).

    :func:`~lidarjax.maps.fit` optimises ``sqrt`` of the (blurred) cell rates, like
    :class:`~lidarjax.maps.DecayRateMap`.

    Smoothness (in the points, hence in a sensor pose). Let ``c_i = origin + (i + 1/2) res``
    be the cell-centre coordinates (``i = 0 .. n - 1`` per axis). Inside each square
    ``[c_i, c_i+1] x [c_j, c_j+1]`` of the cell-centre lattice, and in the half-cell border
    strips where it is clamped, the field is a bilinear polynomial (C-infinity). On the
    lattice lines ``x = c_i`` and ``y = c_j`` it is continuous but its gradient jumps: the
    slope across the line changes from the left to the right pair of cells (generically
    nonzero; exactly on a line, autodiff returns the slope on the side of the larger
    coordinate). On the grid box border the value jumps from the clamped border value to
    ``outside_rate``. :meth:`integral` inherits this: it is ``chord / n_nodes`` times the
    sum of the field at the midpoint nodes, so it is continuous in the rays and smooth
    except where a node lies on a lattice line (its derivative jumps by ``chord / n_nodes``
    times that node's slope jump) or where the chord's ends switch (a ray starting or
    ending on the box border, a ray through a box corner). These kink sets are dense: a
    perturbation moving the points by ``h`` (m) crosses about ``n_nodes * h / res`` of them
    per ray and axis, so finite-difference steps must stay below the nodes' distance to the
    nearest line (``jax.test_util.check_grads``'s 1e-4 typically crosses some and fails
    with relative errors ~1e-3). The scan objective's kink sets are stated in
    :class:`~lidarjax.localization.refine.FieldScan`. (A C1 field needs a smoother
    interpolant, e.g. quadratic B-splines, which changes the values: not done here.)

    Attributes:
        grid: the 2-D :class:`~lidarjax.maps.DecayRateMap` whose (blurred) cell rates are
            the field's values at the cell centres.
        n_nodes: midpoint nodes per ray of :meth:`integral` (static).
        backend: ``"jax"`` or ``"native"`` (static): which code computes :meth:`integral`'s
            chords (see ``__init__``).
    """

    grid: DecayRateMap
    n_nodes: int = eqx.field(static=True)
    backend: str = eqx.field(static=True)

    def __init__(
        self,
        map: DecayRateMap,
        blur_m: float = 0.0,
        *,
        n_nodes: int = 256,
        backend: str = "jax",
    ):
        """
        Args:
            map: a 2-D :class:`~lidarjax.maps.DecayRateMap`.
            blur_m: standard deviation (m) of the Gaussian blur of the cell rates (border
                cells extended, kernel truncated at 3 sigma); 0 uses the rates as they are.
            n_nodes: midpoint nodes per ray of :meth:`integral`.
            backend: ``"jax"`` (the default; differentiable in everything, any device),
                ``"native"`` (the C++ kernel of ``raytrace/csrc/field_integral.cc``: the same
                midpoint rule, sums in double, about 10 times faster on a CPU;
                differentiable to second order in the rays only, so for pose refinement
                and its Hessian, not for fitting the rates) or ``"auto"`` (native when
                available, see :mod:`lidarjax.raytrace`'s backends). Resolved here, once.

        Raises:
            ValueError: ``map`` is not a 2-D DecayRateMap, or a bad ``blur_m`` / ``n_nodes``
                / ``backend``.
            RuntimeError: ``backend="native"`` but the native kernels are unavailable.
        """
        from ..raytrace import _native

        if not isinstance(map, DecayRateMap) or map.spec.dim != 2:
            raise ValueError(f"map must be a 2-D DecayRateMap, got {type(map).__name__}")
        if not (np.isfinite(blur_m) and blur_m >= 0):
            raise ValueError(f"blur_m must be finite and >= 0, got {blur_m!r}")
        self.n_nodes = _check_nodes(n_nodes)
        self.backend = _native.resolve(backend) if backend != "jax" else "jax"
        if blur_m == 0:
            self.grid = map
        else:
            rates = blur(map.rates, float(blur_m) / float(map.spec.resolution))
            self.grid = DecayRateMap(map.spec, rates, map.outside_rate)

    # the attributes of the former localization-only class, read from the grid
    @property
    def rates(self) -> Float[Array, "nx ny"]:
        """``[nx ny]`` cell rates (1/m) after blurring."""
        return self.grid.rates

    @property
    def origin(self) -> Float[Array, " 2"]:
        """``[2]`` grid origin (m)."""
        return self.grid.spec.origin

    @property
    def resolution(self) -> Float[Array, ""]:
        """Cell size (m)."""
        return self.grid.spec.resolution

    @property
    def outside_rate(self) -> Float[Array, ""]:
        """Rate (1/m) outside the grid."""
        return self.grid.outside_rate

    @property
    def dim(self) -> int:
        return 2

    def with_nodes(self, n_nodes: int) -> SmoothDecayRateField:
        """The same field with ``n_nodes`` midpoint nodes per ray in :meth:`integral`."""
        return SmoothDecayRateField(self.grid, 0.0, n_nodes=n_nodes, backend=self.backend)

    def with_backend(self, backend: str) -> SmoothDecayRateField:
        """The same field with :meth:`integral` computed by ``backend``."""
        return SmoothDecayRateField(self.grid, 0.0, n_nodes=self.n_nodes, backend=backend)

    def _interpolate(self, points: Float[Array, "*b 2"]) -> Float[Array, "*b"]:
        """Bilinear interpolant of the cell rates at ``points``, border cells clamped (the
        value inside the grid; outside it the clamped extension)."""
        rates = self.grid.rates
        nx, ny = rates.shape
        u = (points - self.origin) / self.resolution - 0.5
        i0 = jnp.floor(u)
        f = u - i0
        i0 = i0.astype(jnp.int32)

        def at(di, dj):
            i = jnp.clip(i0[..., 0] + di, 0, nx - 1)
            j = jnp.clip(i0[..., 1] + dj, 0, ny - 1)
            return rates[i, j]

        fx, fy = f[..., 0], f[..., 1]
        return (
            at(0, 0) * (1 - fx) * (1 - fy)
            + at(1, 0) * fx * (1 - fy)
            + at(0, 1) * (1 - fx) * fy
            + at(1, 1) * fx * fy
        )

    def decay_rate(self, points: Float[Array, "*b 2"]) -> Float[Array, "*b"]:
        """``lambda(points)`` (1/m): the interpolant inside the closed grid box,
        ``outside_rate`` beyond it. ``points`` may have any leading axes."""
        points = jnp.asarray(points)
        nx, ny = self.grid.rates.shape
        rel = (points - self.origin) / self.resolution
        inside = jnp.all((rel >= 0) & (rel <= jnp.asarray([nx, ny], rel.dtype)), axis=-1)
        return jnp.where(inside, self._interpolate(points), self.outside_rate)

    def __call__(self, points: Float[Array, "*b 2"]) -> Float[Array, "*b"]:
        """``lambda(points)`` (1/m), same as :meth:`decay_rate`."""
        return self.decay_rate(points)

    def integral(
        self,
        origins: Float[Array, "n 2"],
        directions: Float[Array, "n 2"],
        lengths: Float[Array, " n"],
    ) -> Float[Array, " n"]:
        """Optical depth ``S = int_0^r lambda(s + t v) dt`` per ray: the midpoint rule with
        :attr:`n_nodes` nodes over the chord ``[t0, t1]`` inside the grid box (slab test
        :func:`~lidarjax.maps._field.box_segment`) plus ``outside_rate * (r - (t1 - t0))``
        (``0 * inf := 0``). Differentiable in the rays and the rates (``backend="native"``:
        in the rays, to second order).

        Args:
            origins: ``[n 2]`` ray starts (m).
            directions: ``[n 2]`` unit directions.
            lengths: ``[n]`` upper limits (m), ``>= 0``, possibly ``inf``.

        Returns:
            ``[n]`` optical depths (dimensionless).
        """
        origins, directions, lengths = (jnp.asarray(x) for x in (origins, directions, lengths))
        for name, x, ndim in (("origins", origins, 2), ("directions", directions, 2)):
            if x.ndim != ndim or x.shape[-1] != 2:
                raise ValueError(f"{name} must be [n 2], got shape {x.shape}")
        if directions.shape != origins.shape or lengths.shape != origins.shape[:1]:
            raise ValueError(
                f"origins {origins.shape}, directions {directions.shape} and lengths "
                f"{lengths.shape} must be [n 2], [n 2] and [n]"
            )
        spec = self.grid.spec
        t0, t1 = jax.vmap(lambda o, d, r: box_segment(spec.origin, spec.upper, o, d, r))(
            origins, directions, lengths
        )
        chord = t1 - t0
        dtype = jnp.result_type(origins.dtype, self.grid.rates.dtype)
        out_len = jnp.maximum(lengths - chord, 0.0)
        if self.backend == "native":
            inside = _native_chord(
                self.n_nodes,
                self.grid.rates.astype(dtype),
                spec.origin.astype(dtype),
                jnp.asarray(spec.resolution, dtype),
                origins.astype(dtype),
                directions.astype(dtype),
                t0.astype(dtype),
                chord.astype(dtype),
            )
            return inside + mul0(self.outside_rate, out_len)
        s = (jnp.arange(self.n_nodes, dtype=dtype) + 0.5) / self.n_nodes  # [K]
        t = t0[:, None] + chord[:, None] * s  # [n K]
        pts = origins[:, None, :] + t[..., None] * directions[:, None, :]  # [n K 2]
        inside = chord * jnp.mean(self._interpolate(pts), axis=-1)
        return inside + mul0(self.outside_rate, out_len)

    def parameters(self) -> Float[Array, "nx ny"]:
        """``sqrt(rates)`` (the grid map's amplitudes); ``outside_rate`` stays fixed."""
        return self.grid.parameters()

    def with_parameters(self, params: Float[Array, "nx ny"]) -> SmoothDecayRateField:
        """The field on the grid with rates ``params**2`` (not blurred again)."""
        return SmoothDecayRateField(
            self.grid.with_parameters(params), 0.0, n_nodes=self.n_nodes, backend=self.backend
        )
