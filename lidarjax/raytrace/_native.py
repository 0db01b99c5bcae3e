"""Loader and JAX bindings of the native (C++, XLA FFI) ray kernels.

The kernels in ``csrc/walk.cc`` reproduce the JAX walk of :mod:`._grid` exactly and are
registered as XLA FFI targets for the CPU platform, so they work inside ``jit``,
``lax.scan`` and ``vmap`` (``vmap`` runs them once per batch element). They are built by
``make`` (``python -m lidarjax.raytrace._build``) against the installed jaxlib's FFI headers.

Backend selection, for every driver that has a native kernel (``backend=`` argument):

- ``"jax"``: the pure-JAX path (differentiable where the driver is; runs on any device).
- ``"native"``: the C++ kernel; raises if it is unavailable (not built, stale, or the
  default JAX device is not a CPU).
- ``"auto"`` (default): native when available, else the JAX path with one warning saying
  why. The environment variable ``LIDARJAX_BACKEND`` (``auto``/``native``/``jax``) sets
  the default for ``"auto"`` calls.

A CUDA kernel of the same target names can be registered for ``platform="CUDA"`` later;
until then ``"auto"`` uses the JAX path on GPUs.
"""

from __future__ import annotations

import ctypes
import os
import warnings
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np

Backend = Literal["auto", "native", "jax"]
BACKENDS = ("auto", "native", "jax")
TERM_MODES = {0: 2, 1: 1, 2: 1, 3: 3}  # mode -> number of tables

_state: dict = {"loaded": None, "reason": None, "warned": False, "isa": None}


def _dt(dtype) -> str:
    dtype = np.dtype(dtype)
    if dtype == np.float32:
        return "f32"
    if dtype == np.float64:
        return "f64"
    raise ValueError(f"native ray kernels support float32 and float64, got {dtype}")


def _load() -> bool:
    if _state["loaded"] is not None:
        return _state["loaded"]
    from . import _build  # imported lazily: `python -m lidarjax.raytrace._build` stays clean

    ok, reason = False, None
    if not _build.LIBRARY.exists():
        reason = (
            "the native library is not built (run `make` or `python -m lidarjax.raytrace._build`)"
        )
    elif not _build.up_to_date():
        reason = (
            "the native library is stale (C++ sources or jaxlib changed since it was built; "
            "run `make` or `python -m lidarjax.raytrace._build`)"
        )
    else:
        try:
            lib = ctypes.CDLL(str(_build.LIBRARY))
            isa = os.environ.get("LIDARJAX_NATIVE_ISA", "auto")
            if isa not in ("auto", "baseline", "avx2"):
                raise ValueError(f"LIDARJAX_NATIVE_ISA must be auto, baseline or avx2, got {isa!r}")
            has_avx2 = bool(lib.lidarjax_cpu_has_avx2())
            if isa == "avx2" and not has_avx2:
                raise OSError("LIDARJAX_NATIVE_ISA=avx2 but this CPU has no AVX2")
            if isa != "baseline" and has_avx2 and "avx2" in _build.variants():
                lib = ctypes.CDLL(str(_build.LIBRARY_AVX2))
                _state["isa"] = "avx2"
            else:
                _state["isa"] = "baseline"
            for dt in ("F32", "F64"):
                for d in (2, 3):
                    jax.ffi.register_ffi_target(
                        f"lidarjax_accumulate_{dt.lower()}_{d}d",
                        jax.ffi.pycapsule(getattr(lib, f"LidarjaxAccumulate{dt}D{d}")),
                        platform="cpu",
                    )
                    for m in TERM_MODES:
                        jax.ffi.register_ffi_target(
                            f"lidarjax_fold_{dt.lower()}_{d}d_m{m}",
                            jax.ffi.pycapsule(getattr(lib, f"LidarjaxFold{dt}D{d}M{m}")),
                            platform="cpu",
                        )
                # optical depth of a bilinear field (SmoothDecayRateField) and its second
                # derivatives, field_integral.cc; the front end's map blur, blur.cc
                for target, symbol in (
                    ("chord_integral", "LidarjaxChordIntegral"),
                    ("chord_hessian", "LidarjaxChordHessian"),
                    ("blur2d", "LidarjaxBlur2D"),
                ):
                    jax.ffi.register_ffi_target(
                        f"lidarjax_{target}_{dt.lower()}",
                        jax.ffi.pycapsule(getattr(lib, f"{symbol}{dt}")),
                        platform="cpu",
                    )
                # PLE+ (lidarjax.features.optimize_polylines), csrc/polyline_plus.cc
                jax.ffi.register_ffi_target(
                    f"lidarjax_polyline_plus_{dt.lower()}",
                    jax.ffi.pycapsule(getattr(lib, f"LidarjaxPolylinePlus{dt}")),
                    platform="cpu",
                )
            ok = True
        except (OSError, AttributeError) as e:
            reason = f"the native library could not be loaded: {e}"
    _state["loaded"], _state["reason"] = ok, reason
    return ok


def isa() -> str | None:
    """Which native library is in use: ``"avx2"`` (8 float / 4 double ray lanes per
    vector) or ``"baseline"`` (4 / 2), or None when the kernels are unavailable."""
    return _state["isa"] if _load() else None


def available() -> bool:
    """Whether the native kernels are built, current and usable on the default device."""
    return _load() and jax.default_backend() == "cpu"


def unavailable_reason() -> str | None:
    """Why :func:`available` is False (None if it is True)."""
    if not _load():
        return _state["reason"]
    if jax.default_backend() != "cpu":
        return f"the default JAX backend is {jax.default_backend()!r}; the kernels are CPU-only"
    return None


def check_backend(backend: str) -> str:
    """``backend`` validated (``ValueError`` naming it otherwise)."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    return backend


def resolve(backend: str) -> str:
    """``"native"`` or ``"jax"`` for a requested backend (see the module docstring).

    Raises:
        ValueError: unknown backend name.
        RuntimeError: ``backend="native"`` but the kernels are unavailable.
    """
    check_backend(backend)
    if backend == "auto":
        env = os.environ.get("LIDARJAX_BACKEND", "auto")
        if env not in BACKENDS:
            raise ValueError(f"LIDARJAX_BACKEND must be one of {BACKENDS}, got {env!r}")
        if env == "jax":
            return "jax"
        if env == "native":
            backend = "native"
    if backend == "jax":
        return "jax"
    if available():
        return "native"
    if backend == "native":
        raise RuntimeError(f"backend='native' requested but {unavailable_reason()}")
    if not _state["warned"]:
        _state["warned"] = True
        warnings.warn(
            f"lidarjax: using the pure-JAX ray walk because {unavailable_reason()}",
            RuntimeWarning,
            stacklevel=3,
        )
    return "jax"


def default_threads() -> int:
    """All cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def check_threads(threads: int | None) -> int:
    """``threads`` validated (``None`` means :func:`default_threads`)."""
    if threads is None:
        return default_threads()
    if isinstance(threads, bool) or not isinstance(threads, int) or threads <= 0:
        raise ValueError(f"threads must be a positive int or None, got {threads!r}")
    return threads


def accumulate(spec, origins, directions, ranges, kind, r_max, sub_as_hit: bool, threads: int):
    """Native :func:`~lidarjax.raytrace.accumulate` core: ``(R, M, H)`` of ``spec.shape``.

    The kernel reads the rays as they are (no per-ray temporaries) and validates them
    itself: a non-finite origin or direction, or a NaN/negative traced range, is an
    ``XlaRuntimeError`` naming the first bad ray.

    Args:
        spec: the grid (``GridSpec``).
        origins, directions: ``[n d]`` rays (float32 or float64, same dtype).
        ranges: ``[n]`` measured ranges (m).
        kind: ``[n]`` int32 ``HIT``/``SUB``/``SUP``.
        r_max: ``[]`` trace length of SUP rays (m; may be ``inf``).
        sub_as_hit: trace SUB rays like HIT rays (else they are ignored).
        threads: worker threads.
    """
    dtype = origins.dtype
    name = f"lidarjax_accumulate_{_dt(dtype)}_{spec.dim}d"
    out = (
        jax.ShapeDtypeStruct(spec.shape, dtype),
        jax.ShapeDtypeStruct(spec.shape, jnp.int32),
        jax.ShapeDtypeStruct(spec.shape, jnp.int32),
    )
    call = jax.ffi.ffi_call(name, out, vmap_method="sequential")
    r, h, m = call(
        spec.origin.astype(dtype),
        spec.resolution.astype(dtype),
        origins,
        directions.astype(dtype),
        ranges.astype(dtype),
        kind.astype(jnp.int32),
        jnp.asarray(r_max, dtype),
        sub_as_hit=bool(sub_as_hit),
        threads=np.int64(threads),
    )
    return r, m, h


def fold(spec, mode: int, tables, origins, directions, lengths, threads: int):
    """Native :func:`~lidarjax.raytrace.fold_rays` core for a :class:`CellTerm`.

    Returns ``(body, last_cell, last_len, grid_len, any_valid, t_start, t_end)`` with
    leading axis ``[n]``.
    """
    dtype = origins.dtype
    if mode not in TERM_MODES:
        raise ValueError(f"unknown term mode {mode!r}")
    n = origins.shape[0]
    name = f"lidarjax_fold_{_dt(dtype)}_{spec.dim}d_m{mode}"
    f = jax.ShapeDtypeStruct((n,), dtype)
    out = (
        f,
        jax.ShapeDtypeStruct((n, spec.dim), jnp.int32),
        f,
        f,
        jax.ShapeDtypeStruct((n,), jnp.bool_),
        f,
        f,
    )
    call = jax.ffi.ffi_call(name, out, vmap_method="sequential")
    return call(
        spec.origin.astype(dtype),
        spec.resolution.astype(dtype),
        tables.astype(dtype),
        origins,
        directions.astype(dtype),
        lengths.astype(dtype),
        threads=np.int64(threads),
    )


def _chord_args(rates, origin, resolution, origins, directions, t0, chord):
    """The chord kernels' inputs in the dtype of ``rates`` (origin ``[2]``, resolution
    ``[]``)."""
    dtype = rates.dtype
    return (
        rates,
        jnp.asarray(origin, dtype).reshape(2),
        jnp.asarray(resolution, dtype).reshape(()),
        *(jnp.asarray(x, dtype) for x in (origins, directions, t0, chord)),
    )


def chord_integral(rates, origin, resolution, origins, directions, t0, chord, n_nodes: int):
    """Native core of :meth:`~lidarjax.maps.SmoothDecayRateField.integral` (the chords inside
    the grid box; ``csrc/field_integral.cc``): the midpoint rule ``F = chord / K * sum_j
    f(o + (t0 + chord s_j) d)`` over the bilinear interpolant ``f`` of ``rates``, and its
    derivatives in the rays.

    Args:
        rates: ``[nx ny]`` cell rates (1/m).
        origin: ``[2]`` grid origin (m); resolution: ``[]`` cell size (m).
        origins, directions: ``[n 2]`` ray starts (m) and unit directions.
        t0, chord: ``[n]`` chord start along the ray and chord length (m), ``>= 0``.
        n_nodes: midpoint nodes ``K`` per chord.

    Returns:
        ``(F [n], dF/dorigins [n 2], dF/ddirections [n 2], dF/dt0 [n], dF/dchord [n])`` in
        the dtype of ``rates``. Non-finite rays, negative chords, or non-finite rates on a
        ray's path are an ``XlaRuntimeError`` naming the ray.
    """
    dtype = rates.dtype
    n = origins.shape[0]
    f = jax.ShapeDtypeStruct((n,), dtype)
    f2 = jax.ShapeDtypeStruct((n, 2), dtype)
    call = jax.ffi.ffi_call(
        f"lidarjax_chord_integral_{_dt(dtype)}", (f, f2, f2, f, f), vmap_method="sequential"
    )
    return call(
        *_chord_args(rates, origin, resolution, origins, directions, t0, chord),
        n_nodes=np.int64(n_nodes),
    )


def chord_hessian(rates, origin, resolution, origins, directions, t0, chord, n_nodes: int):
    """Second derivatives of :func:`chord_integral`'s ``F`` per ray: ``[n 6 6]`` in the ray
    parameters ``(o_x, o_y, d_x, d_y, t0, chord)`` (``csrc/field_integral.cc``,
    ``ChordHessian``), in the dtype of ``rates``; arguments and errors as there."""
    dtype = rates.dtype
    n = origins.shape[0]
    call = jax.ffi.ffi_call(
        f"lidarjax_chord_hessian_{_dt(dtype)}",
        jax.ShapeDtypeStruct((n, 6, 6), dtype),
        vmap_method="sequential",
    )
    return call(
        *_chord_args(rates, origin, resolution, origins, directions, t0, chord),
        n_nodes=np.int64(n_nodes),
    )


def blur2d(values, sigma_cells: float):
    """Native :func:`~lidarjax.maps.blur` of a ``[nx ny]`` array (``csrc/blur.cc``): the
    separable Gaussian (truncated at 3 sigma) with the border cells extended, the same
    taps in the same order as the JAX path (equal to round-off). Not differentiable (the
    SLAM front end blurs a fixed map). A non-finite cell is an error naming it.

    Args:
        values: ``[nx ny]`` float32 or float64 array.
        sigma_cells: standard deviation in cells (> 0).
    """
    from ..maps._smoothing import gaussian_kernel_1d

    values = jnp.asarray(values)
    if values.ndim != 2:
        raise ValueError(f"values must be [nx ny], got shape {values.shape}")
    taps = jnp.asarray(gaussian_kernel_1d(float(sigma_cells), 3.0), values.dtype)
    call = jax.ffi.ffi_call(
        f"lidarjax_blur2d_{_dt(values.dtype)}",
        jax.ShapeDtypeStruct(values.shape, values.dtype),
        vmap_method="sequential",
    )
    return call(values, taps)
