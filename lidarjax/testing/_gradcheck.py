"""Finite differences, manifold Jacobians and a gradient checker (see ``lidarjax.testing``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

__all__ = [
    "Comparison",
    "GradientReport",
    "check_gradients",
    "default_eps",
    "default_tolerances",
    "finite_difference",
    "manifold_finite_difference",
    "manifold_jacobian",
    "tree_allclose",
]

_METHODS = ("central", "forward", "backward")
_MODES = ("fwd", "rev")

# (rtol, atol) against finite differences, (rtol, atol) between jacfwd and jacrev
_TOLERANCES = {
    "float64": ((1e-6, 1e-8), (1e-10, 1e-12)),
    "float32": ((1e-2, 1e-3), (1e-5, 1e-6)),
    "float16": ((1e-1, 1e-1), (1e-2, 1e-2)),
}


# --------------------------------------------------------------------------------------
# argument checks and small helpers


def _check_callable(f, name: str = "f") -> None:
    if not callable(f):
        raise TypeError(f"{name} must be callable, got {type(f).__name__}")


def _path_str(name: str, path) -> str:
    """``x['a'][0]`` for a leaf of argument ``name``; ``x`` for a bare array."""
    return name + jax.tree_util.keystr(tuple(path))


def _float_leaves(x, name: str) -> tuple[list, list[np.ndarray], Any]:
    """``(paths, leaves, treedef)`` of a pytree whose leaves must be finite, real floating
    arrays (or Python floats); leaves come back as NumPy arrays of JAX's canonical dtype."""
    flat, treedef = jax.tree_util.tree_flatten_with_path(x)
    paths, leaves = [], []
    for path, leaf in flat:
        where = _path_str(name, path)
        try:
            arr = jnp.asarray(leaf)
        except TypeError:
            raise TypeError(
                f"{name} must be a pytree of floating-point arrays; {where} is a "
                f"{type(leaf).__name__}"
            ) from None
        if not jnp.issubdtype(arr.dtype, jnp.floating):
            raise TypeError(
                f"{name} must have real floating-point leaves, but {where} has dtype "
                f"{arr.dtype} (differentiate with respect to floats, e.g. "
                f"jnp.asarray({name}, jnp.float64))"
            )
        arr = np.asarray(arr)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must be finite, but {where} has non-finite entries")
        paths.append(path)
        leaves.append(arr)
    return paths, leaves, treedef


def _check_eps(eps) -> float | None:
    if eps is None:
        return None
    try:
        e = float(eps)
    except (TypeError, ValueError):
        raise TypeError(f"eps must be a positive float or None, got {eps!r}") from None
    if not (np.isfinite(e) and e > 0):
        raise ValueError(f"eps must be finite and > 0, got {eps!r}")
    return e


def default_eps(dtype) -> float:
    """Base finite-difference step for a floating ``dtype``: 1e-6 for float64, 1e-3 for
    float32, ``eps_machine ** (1/3)`` for narrower types; :func:`finite_difference` scales
    it by ``max(1, |x_i|)`` per coordinate."""
    dtype = jnp.dtype(dtype)
    if dtype == jnp.float64:
        return 1e-6
    if dtype == jnp.float32:
        return 1e-3
    return float(jnp.finfo(dtype).eps) ** (1.0 / 3.0)


def _tier(dtypes) -> str:
    """``float64``, ``float32`` or ``float16``: the narrowest floating dtype involved."""
    bits = [jnp.finfo(d).bits for d in dtypes if jnp.issubdtype(d, jnp.floating)]
    low = min(bits, default=64)
    return "float64" if low >= 64 else "float32" if low >= 32 else "float16"


def default_tolerances(dtype) -> dict[str, tuple[float, float]]:
    """Default ``(rtol, atol)`` of :func:`check_gradients` for a floating ``dtype``:
    ``{"fd": ..., "ad": ...}`` (autodiff against finite differences; ``jacfwd`` against
    ``jacrev``)."""
    fd, ad = _TOLERANCES[_tier([jnp.dtype(dtype)])]
    return {"fd": fd, "ad": ad}


def tree_allclose(a, b, *, rtol: float = 1e-9, atol: float = 1e-12) -> bool:
    """True when two pytrees have the same structure and every pair of leaves satisfies
    ``np.allclose(x, y, rtol=rtol, atol=atol)`` (``|x - y| <= atol + rtol |y|``
    elementwise, broadcasting, NaN never close)."""
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    if ta != tb:
        return False
    return all(
        np.allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol) for x, y in zip(la, lb)
    )


# --------------------------------------------------------------------------------------
# finite differences


def finite_difference(f: Callable, x, *, eps: float | None = None, method: str = "central"):
    """Finite-difference Jacobian of ``f`` at the pytree ``x``, structured like
    ``jax.jacobian(f)(x)``.

    Each input coordinate ``x_i`` is stepped by ``h_i`` (``eps`` if given, else
    :func:`default_eps` of its dtype times ``max(1, |x_i|)``); the derivative divides by
    the step actually taken in that dtype (``fl(x_i + h_i) - fl(x_i - h_i)``). ``f`` is
    called ``2 n + 1`` times (``n + 1`` for one-sided methods) with concrete arrays, one
    coordinate at a time in a Python loop: a testing tool for up to a few thousand
    coordinates; pass a jitted ``f`` for speed. ``f`` need not be traceable. Differences
    are formed in float64 (NumPy) and cast to each output leaf's dtype.

    For a ``jaxlie`` group element ``x`` this is the derivative with respect to its raw
    parameters (which leaves the manifold); use :func:`manifold_finite_difference` for
    the tangent-space one.

    Args:
        f: ``f(x) -> pytree`` of arrays (any structure and shapes).
        x: pytree of finite, real floating-point arrays (or Python floats); float64
            recommended (float32 differences are accurate to about 1e-4 relative at best).
        eps: absolute step for every coordinate, or None for the dtype default.
        method: ``"central"`` (error ``O(h^2)``), ``"forward"`` or ``"backward"``
            (one-sided, ``O(h)``: the right and left derivatives at a kink).

    Returns:
        A pytree shaped like ``f(x)`` whose leaves are pytrees shaped like ``x``: the leaf
        for output leaf ``y`` (shape ``So``) and input leaf ``x`` (shape ``Si``) has shape
        ``So + Si`` (``dy / dx``), as ``jax.jacfwd(f)(x)``; entries are NaN/inf where
        ``f`` is not finite at the evaluation points.

    Raises:
        TypeError: ``f`` is not callable, a leaf of ``x`` is not real floating-point.
        ValueError: non-finite ``x``, a bad ``eps`` or ``method``, a step that vanishes in
            the dtype, or ``f`` returning differently structured outputs.
    """
    _check_callable(f)
    if method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
    eps = _check_eps(eps)
    paths, xs, treedef = _float_leaves(x, "x")

    def call(leaves):
        return f(jax.tree_util.tree_unflatten(treedef, [jnp.asarray(v) for v in leaves]))

    def outputs(leaves, tree0=None):
        y_leaves, y_tree = jax.tree_util.tree_flatten(call(leaves))
        out = [np.asarray(v, dtype=np.float64) for v in y_leaves]
        if tree0 is not None and (
            y_tree != tree0[0] or [v.shape for v in out] != [v.shape for v in tree0[1]]
        ):
            raise ValueError(
                "f returned outputs of a different structure or shape at a perturbed x "
                f"({y_tree} vs {tree0[0]})"
            )
        return out, y_tree, y_leaves

    y0, y_tree, y0_raw = outputs(xs)
    ref = (y_tree, y0)
    out_dtypes = [
        jnp.asarray(v).dtype if jnp.issubdtype(jnp.asarray(v).dtype, jnp.floating) else None
        for v in y0_raw
    ]
    blocks: list[list] = [[None] * len(xs) for _ in y0]
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        for k, leaf in enumerate(xs):
            flat = leaf.reshape(-1)
            cols = [np.empty((flat.size,) + y.shape, np.float64) for y in y0]
            for i in range(flat.size):
                xi = flat[i]
                h = eps if eps is not None else default_eps(leaf.dtype) * max(1.0, abs(float(xi)))
                up = np.asarray(float(xi) + h, leaf.dtype)
                down = np.asarray(float(xi) - h, leaf.dtype)
                if method == "forward":
                    down = xi
                elif method == "backward":
                    up = xi
                step = float(up) - float(down)
                if step == 0.0:
                    raise ValueError(
                        f"eps={h!r} is too small for {leaf.dtype} at "
                        f"{_path_str('x', paths[k])} (value {float(xi)!r})"
                    )

                def at(v, k=k, i=i):
                    new = flat.copy()
                    new[i] = v
                    leaves = list(xs)
                    leaves[k] = new.reshape(leaf.shape)
                    return outputs(leaves, ref)[0]

                yp = y0 if method == "backward" else at(up)
                ym = y0 if method == "forward" else at(down)
                for o in range(len(y0)):
                    cols[o][i] = (yp[o] - ym[o]) / step
            for o, y in enumerate(y0):
                jac = np.moveaxis(cols[o], 0, -1).reshape(y.shape + leaf.shape)
                dtype = out_dtypes[o] if out_dtypes[o] is not None else leaf.dtype
                blocks[o][k] = jnp.asarray(jac.astype(dtype))
    return jax.tree_util.tree_unflatten(
        y_tree, [jax.tree_util.tree_unflatten(treedef, b) for b in blocks]
    )


# --------------------------------------------------------------------------------------
# manifolds (jaxlie)


def _check_pose(pose, name: str = "pose") -> None:
    if not isinstance(pose, jaxlie.MatrixLieGroup):
        raise TypeError(
            f"{name} must be a jaxlie group element (SO2, SO3, SE2, SE3), got {type(pose).__name__}"
        )
    dtype = jnp.asarray(pose.parameters()).dtype
    if not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(f"{name} must have floating-point parameters, got {dtype}")


def _zero_tangent(pose):
    dtype = jnp.asarray(pose.parameters()).dtype
    return jnp.zeros(pose.get_batch_axes() + (pose.tangent_dim,), dtype)


def _on_tangent(f: Callable, pose) -> Callable:
    """``delta -> f(pose @ exp(delta))`` (``jaxlie.manifold.rplus``)."""
    return lambda delta: f(jaxlie.manifold.rplus(pose, delta))


def manifold_finite_difference(
    f: Callable, pose, *, eps: float | None = None, method: str = "central"
):
    """Finite-difference derivative of ``f(pose @ exp(delta))`` with respect to the
    tangent vector ``delta`` at 0 (right perturbation, ``jaxlie.manifold.rplus``).

    The tangent is jaxlie's: SE2 ``(v_x, v_y, omega)``, SE3 ``(v [3], omega [3])``, SO2
    ``(omega,)``, SO3 ``omega [3]`` (m and rad, in the body frame of ``pose``).

    Args:
        f: ``f(pose) -> pytree`` of arrays.
        pose: a ``jaxlie`` group element (SO2, SO3, SE2, SE3); float64 recommended. A
            batched pose (batch axes ``B``) is perturbed element by element.
        eps: absolute step (default: :func:`default_eps` of the pose's dtype).
        method: as in :func:`finite_difference`.

    Returns:
        Like ``f(pose)`` with each leaf ``[*out]`` replaced by ``[*out, *B, tangent_dim]``.

    Raises:
        TypeError: ``f`` not callable or ``pose`` not a jaxlie group element.
    """
    _check_callable(f)
    _check_pose(pose)
    return finite_difference(_on_tangent(f, pose), _zero_tangent(pose), eps=eps, method=method)


def manifold_jacobian(f: Callable, pose, *, mode: str = "fwd"):
    """Autodiff counterpart of :func:`manifold_finite_difference`: ``jax.jacfwd`` (or
    ``jax.jacrev`` with ``mode="rev"``) of ``delta -> f(pose @ exp(delta))`` at
    ``delta = 0``.

    Returns:
        Like ``f(pose)`` with each leaf ``[*out]`` replaced by ``[*out, *B, tangent_dim]``.

    Raises:
        TypeError: ``f`` not callable or ``pose`` not a jaxlie group element.
        ValueError: ``mode`` not ``"fwd"`` or ``"rev"``.
    """
    _check_callable(f)
    _check_pose(pose)
    if mode not in _MODES:
        raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
    jac = jax.jacfwd if mode == "fwd" else jax.jacrev
    return jac(_on_tangent(f, pose))(_zero_tangent(pose))


# --------------------------------------------------------------------------------------
# the checker


@dataclasses.dataclass(frozen=True)
class Comparison:
    """One comparison of two Jacobians made by :func:`check_gradients`.

    Attributes:
        name: e.g. ``"fwd vs rev"``, ``"fwd vs fd"``; prefixed ``"order 2: "`` for the
            derivative of the Jacobian.
        max_abs_error: largest ``|a - b|`` over the compared entries.
        max_rel_error: largest ``|a - b| / |b|`` over entries with ``|b| > atol`` (``b``
            the reference: ``jacrev`` for fwd vs rev, finite differences otherwise).
        rtol, atol: the tolerances used (``|a - b| <= atol + rtol |b|``).
        n_compared: number of Jacobian entries compared.
    """

    name: str
    max_abs_error: float
    max_rel_error: float
    rtol: float
    atol: float
    n_compared: int


@dataclasses.dataclass(frozen=True)
class GradientReport:
    """What :func:`check_gradients` compared (returned when every check passed).

    Attributes:
        comparisons: one :class:`Comparison` per pair of Jacobians (and per order).
        n_inputs: number of input coordinates (tangent coordinates in manifold mode).
        n_skipped: output entries where ``f`` is not finite (their derivatives are not
            compared), summed over orders.
        manifold: True when ``x`` was a jaxlie group element (derivatives in the tangent
            space, right perturbation).
        dtype: the tolerance tier used (``"float64"``, ``"float32"`` or ``"float16"``).
    """

    comparisons: tuple[Comparison, ...]
    n_inputs: int
    n_skipped: int
    manifold: bool
    dtype: str

    def __getitem__(self, name: str) -> Comparison:
        for c in self.comparisons:
            if c.name == name:
                return c
        raise KeyError(f"no comparison {name!r}; have {[c.name for c in self.comparisons]}")

    def __str__(self) -> str:
        lines = [
            f"gradient check passed ({self.n_inputs} inputs, {self.dtype} tolerances"
            + (", tangent space" if self.manifold else "")
            + (f", {self.n_skipped} non-finite outputs skipped" if self.n_skipped else "")
            + ")"
        ]
        for c in self.comparisons:
            lines.append(
                f"  {c.name}: max abs error {c.max_abs_error:.3g}, max rel error "
                f"{c.max_rel_error:.3g} (rtol={c.rtol:g}, atol={c.atol:g}, "
                f"{c.n_compared} entries)"
            )
        return "\n".join(lines)


def _split_index(flat_index: int, shape: tuple, n_out_axes: int) -> tuple[tuple, tuple]:
    idx = tuple(int(i) for i in np.unravel_index(flat_index, shape)) if shape else ()
    return idx[:n_out_axes], idx[n_out_axes:]


def _check_once(fn, x, aux, eps, fd_tol, ad_tol, modes, prefix, manifold, jit):
    """Compare the Jacobians of ``fn(x, aux)`` in ``x``; returns ``(comparisons,
    n_skipped)``. ``aux`` (the pose in manifold mode) is an argument rather than a
    closure so that the compiled programs do not depend on its value."""
    maybe_jit = jax.jit if jit else (lambda g: g)
    call = maybe_jit(fn)
    y = call(x, aux)
    y_flat, _ = jax.tree_util.tree_flatten_with_path(y)
    x_flat, _ = jax.tree_util.tree_flatten_with_path(x)
    n_in = len(x_flat)
    masks = [np.isfinite(np.asarray(v, np.float64)) for _, v in y_flat]
    jacs = {
        m: jax.tree_util.tree_leaves(
            maybe_jit((jax.jacfwd if m == "fwd" else jax.jacrev)(fn))(x, aux)
        )
        for m in modes
    }
    jacs["fd"] = jax.tree_util.tree_leaves(finite_difference(lambda t: call(t, aux), x, eps=eps))
    xname = "delta" if manifold else "x"

    def blocks(name):
        for o, (opath, yv) in enumerate(y_flat):
            out_shape = np.shape(yv)
            for i, (ipath, _) in enumerate(x_flat):
                arr = np.asarray(jacs[name][o * n_in + i], np.float64)
                mask = np.broadcast_to(
                    masks[o].reshape(out_shape + (1,) * (arr.ndim - len(out_shape))), arr.shape
                )
                where = f"output {_path_str('f(x)', opath)}, input {_path_str(xname, ipath)}"
                yield arr, mask, out_shape, where, yv

    for m in modes:  # derivatives must be finite wherever f is
        for arr, mask, out_shape, where, yv in blocks(m):
            bad = mask & ~np.isfinite(arr)
            if bad.any():
                k = int(np.flatnonzero(bad)[0])
                oi, ii = _split_index(k, arr.shape, len(out_shape))
                value = np.asarray(yv)[oi]
                raise AssertionError(
                    f"{prefix}jac{m} is not finite where f is finite: {where}, output index "
                    f"{oi}, input index {ii}: derivative {float(arr.reshape(-1)[k])!r}, f = "
                    f"{float(value)!r} ({int(bad.sum())} such entries)"
                )

    pairs = [("fwd", "rev", ad_tol)] if len(modes) == 2 else []
    pairs += [(m, "fd", fd_tol) for m in modes]
    comparisons = []
    for a_name, b_name, (rtol, atol) in pairs:
        name = f"{prefix}{a_name} vs {b_name}"
        max_abs, max_rel, n_cmp, failures = 0.0, 0.0, 0, []
        for (a, mask, out_shape, where, _), (b, *_) in zip(blocks(a_name), blocks(b_name)):
            with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
                diff = np.abs(a - b)
                diff = np.where(np.isnan(diff), np.inf, diff)
                allowed = atol + rtol * np.abs(b)
                rel = np.where(np.abs(b) > atol, diff / np.abs(b), 0.0)
                ratio = np.where(diff > allowed, diff / np.maximum(allowed, 1e-300), 0.0)
            diff, rel, ratio = (np.where(mask, v, 0.0) for v in (diff, rel, ratio))
            n_cmp += int(mask.sum())
            if diff.size:
                max_abs = max(max_abs, float(diff.max()))
                max_rel = max(max_rel, float(np.where(np.isnan(rel), np.inf, rel).max()))
            if ratio.size and ratio.max() > 0:
                k = int(np.argmax(ratio))
                oi, ii = _split_index(k, a.shape, len(out_shape))
                va, vb = float(a.reshape(-1)[k]), float(b.reshape(-1)[k])
                failures.append(
                    (
                        float(ratio.reshape(-1)[k]),
                        f"{where}: {int((ratio > 0).sum())} of {int(mask.sum())} entries out "
                        f"of tolerance, max abs error {float(diff.max()):.3g}, max rel error "
                        f"{float(rel.max()):.3g}; worst at output index {oi}, input index "
                        f"{ii}: {a_name} = {va!r}, {b_name} = {vb!r}",
                    )
                )
        if failures:
            failures.sort(key=lambda t: -t[0])
            lines = [f"{prefix}{a_name} and {b_name} disagree (rtol={rtol:g}, atol={atol:g}):"]
            lines += ["  " + msg for _, msg in failures[:5]]
            if len(failures) > 5:
                lines.append(f"  ... and {len(failures) - 5} more leaf pairs")
            if b_name == "fd":
                lines.append(
                    "  (finite differences are wrong too if f has a kink or jump within eps "
                    "of x, or if f is large: round-off ~ 1e-16 |f| / eps in float64)"
                )
            raise AssertionError("\n".join(lines))
        comparisons.append(Comparison(name, max_abs, max_rel, rtol, atol, n_cmp))
    return comparisons, int(sum((~m).sum() for m in masks))


def check_gradients(
    f: Callable,
    x,
    *,
    rtol: float | None = None,
    atol: float | None = None,
    ad_rtol: float | None = None,
    ad_atol: float | None = None,
    modes: Sequence[str] = ("fwd", "rev"),
    order: int = 1,
    eps: float | None = None,
    jit: bool = True,
) -> GradientReport:
    """Check the derivatives of ``f`` at ``x``: ``jax.jacfwd`` and ``jax.jacrev`` agree to
    near machine precision, each matches central finite differences
    (:func:`finite_difference`), and every derivative is finite wherever ``f`` is.

    Entries where ``f(x)`` is not finite are not compared (finite differences mean
    nothing there); their derivatives may be anything except that the finite rows are
    checked. With ``order=2`` the same checks run again on the Jacobian function
    (``jax.jacrev(f)``, or ``jax.jacfwd`` when ``modes == ("fwd",)``), i.e. on the
    Hessian; and so on for higher orders.

    When ``x`` is a ``jaxlie`` group element the derivatives are taken in its tangent
    space: ``f`` is checked as ``delta -> f(x @ exp(delta))`` at ``delta = 0``
    (:func:`manifold_jacobian`, :func:`manifold_finite_difference`).

    Default tolerances (``|a - b| <= atol + rtol |b|``, ``b`` the finite differences or
    ``jacrev``) by the narrowest floating dtype of ``x`` and ``f(x)``:

    ===========  ====================  ==========================
    dtype        vs finite diff.       jacfwd vs jacrev
    ===========  ====================  ==========================
    float64      rtol 1e-6, atol 1e-8  rtol 1e-10, atol 1e-12
    float32      rtol 1e-2, atol 1e-3  rtol 1e-5, atol 1e-6
    16-bit       rtol 1e-1, atol 1e-1  rtol 1e-2, atol 1e-2
    ===========  ====================  ==========================

    float32 central differences with a 1e-3 step are accurate to about
    ``1e-7 |f| / 1e-3 ~ 1e-4 |f|`` (round-off) plus ``1e-6 |f'''|`` (truncation), hence the
    loose float32 tolerances: check in float64 where you can. For a large ``f`` raise
    ``atol`` (the float64 round-off is about ``1e-10 |f|``).

    Args:
        f: ``f(x) -> pytree`` of arrays, traceable by JAX (it is also called ``2 n + 1``
            times by the finite differences, ``n`` = input coordinates).
        x: pytree of finite, real floating-point arrays, or a jaxlie group element (SO2,
            SO3, SE2, SE3; batched allowed).
        rtol, atol: tolerances against finite differences (default: table above).
        ad_rtol, ad_atol: tolerances between ``jacfwd`` and ``jacrev``.
        modes: which autodiff modes to check, a non-empty subset of ``("fwd", "rev")``.
        order: how many derivatives to check (1: the Jacobian; 2: also the Hessian, ...).
        eps: finite-difference step (default: :func:`default_eps` scaled by
            ``max(1, |x_i|)``).
        jit: evaluate ``f`` and its Jacobians under ``jax.jit`` (one compilation each,
            then fast finite differences); False runs them op by op (no compilation, for
            debugging).

    Returns:
        A :class:`GradientReport` with the largest errors of every comparison.

    Raises:
        AssertionError: a derivative is not finite where ``f`` is, or two Jacobians
            disagree; the message names the comparison, the output and input leaves, the
            largest absolute and relative errors and the worst entry (its indices and both
            values).
        TypeError: ``f`` not callable, ``x`` with non-floating leaves.
        ValueError: bad ``modes``, ``order``, tolerances or ``eps``; non-finite ``x``.
    """
    _check_callable(f)
    if isinstance(modes, str) or not isinstance(modes, Sequence):
        raise ValueError(f"modes must be a sequence of 'fwd'/'rev', got {modes!r}")
    modes = tuple(modes)
    if not modes or any(m not in _MODES for m in modes) or len(set(modes)) != len(modes):
        raise ValueError(f"modes must be a non-empty subset of {_MODES}, got {modes!r}")
    modes = tuple(m for m in _MODES if m in modes)
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)) or order < 1:
        raise ValueError(f"order must be a positive int, got {order!r}")
    for name, v in (("rtol", rtol), ("atol", atol), ("ad_rtol", ad_rtol), ("ad_atol", ad_atol)):
        if v is not None and not (np.isfinite(v) and v >= 0):
            raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
    eps = _check_eps(eps)

    manifold = isinstance(x, jaxlie.MatrixLieGroup)
    if manifold:
        _check_pose(x, "x")
        fn, x0, aux = (lambda d, pose: f(jaxlie.manifold.rplus(pose, d))), _zero_tangent(x), x
    else:
        _, leaves, treedef = _float_leaves(x, "x")
        fn, aux = (lambda t, _: f(t)), None
        x0 = jax.tree_util.tree_unflatten(treedef, [jnp.asarray(v) for v in leaves])

    dtypes = [jnp.asarray(v).dtype for v in jax.tree_util.tree_leaves(x0)]
    probe = jax.eval_shape(fn, x0, aux) if jit else fn(x0, aux)  # the output dtypes
    dtypes += [
        jnp.asarray(v).dtype if not hasattr(v, "dtype") else v.dtype
        for v in jax.tree_util.tree_leaves(probe)
    ]
    tier = _tier(dtypes)
    (fd_r, fd_a), (ad_r, ad_a) = _TOLERANCES[tier]
    fd_tol = (fd_r if rtol is None else float(rtol), fd_a if atol is None else float(atol))
    ad_tol = (
        ad_r if ad_rtol is None else float(ad_rtol),
        ad_a if ad_atol is None else float(ad_atol),
    )

    comparisons, skipped = [], 0
    deriv = jax.jacrev if "rev" in modes else jax.jacfwd
    for k in range(1, int(order) + 1):
        prefix = "" if k == 1 else f"order {k}: "
        c, s = _check_once(fn, x0, aux, eps, fd_tol, ad_tol, modes, prefix, manifold, bool(jit))
        comparisons += c
        skipped += s
        fn = deriv(fn)
    n_inputs = sum(int(np.size(v)) for v in jax.tree_util.tree_leaves(x0))
    return GradientReport(tuple(comparisons), n_inputs, skipped, manifold, tier)
