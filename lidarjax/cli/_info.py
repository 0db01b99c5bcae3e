"""``lidarjax info``, ``lidarjax datasets`` and ``lidarjax fetch``."""

from __future__ import annotations

import ctypes
import os
import platform

from ._inputs import CliInputError

__all__ = ["cmd_datasets", "cmd_fetch", "cmd_info", "native_kernels"]

# (kernel, exported symbol prefix, what uses it)
_KERNELS = (
    ("accumulate", "LidarjaxAccumulate", "raytrace.accumulate (grid statistics, maps)"),
    ("fold", "LidarjaxFold", "sensor-model likelihoods (batch_log_likelihood, ScanModel)"),
    ("polyline_plus", "LidarjaxPolylinePlus", "features.optimize_polylines (PLE+)"),
    (
        "field_integral",
        "LidarjaxChordIntegral",
        "SmoothDecayRateField optical depth (SLAM front end, alternating back end)",
    ),
    ("blur", "LidarjaxBlur2D", "the SLAM front end's map blur"),
)


def native_kernels() -> list[dict]:
    """Per native kernel: whether it is built into the library in use and whether
    ``backend="auto"`` calls use it (``LIDARJAX_BACKEND`` and availability)."""
    from ..raytrace import _build, _native

    available = _native.available()
    reason = _native.unavailable_reason()
    isa = _native.isa()
    env = os.environ.get("LIDARJAX_BACKEND", "auto")
    lib = None
    if _build.LIBRARY.exists():
        path = _build.LIBRARY_AVX2 if isa == "avx2" else _build.LIBRARY
        try:
            lib = ctypes.CDLL(str(path))
        except OSError:
            lib = None
    out = []
    for name, symbol, used_by in _KERNELS:
        built = lib is not None and any(
            hasattr(lib, f"{symbol}{dt}{suffix}")
            for dt in ("F32", "F64")
            for suffix in ("", "D2", "D2M0")
        )
        out.append(
            {
                "kernel": name,
                "built": built,
                "default": bool(available and built and env != "jax"),
                "used_by": used_by,
                "isa": isa,
                "reason": reason,
            }
        )
    return out


def cmd_info(args) -> int:
    import jax
    import jaxlib
    import numpy as np

    import lidarjax

    from .._runtime import default_compilation_cache_dir
    from ..datasets import data_dirs
    from ..datasets._registry import CACHE_ENV, MIRROR_ENV, OFFLINE_ENV, _cache_dir

    print(f"lidarjax   {lidarjax.__version__}  ({os.path.dirname(lidarjax.__file__)})")
    print(f"jax        {jax.__version__}")
    print(f"jaxlib     {jaxlib.__version__}")
    print(f"numpy      {np.__version__}")
    print(f"python     {platform.python_version()} ({platform.machine()})")
    devs = jax.devices()
    devices = ", ".join(f"{d.platform}:{d.id}" for d in devs)
    count = f"{len(devs)} device{'s' if len(devs) != 1 else ''}"
    print(f"devices    {devices} ({count}, default backend: {jax.default_backend()})")
    if jax.process_count() > 1:
        print(f"processes  {jax.process_count()} (this is process {jax.process_index()})")
    x64 = bool(jax.config.jax_enable_x64)
    print(f"x64        {x64} (default float{64 if x64 else 32})")
    print("native kernels (C++ through the XLA FFI):")
    kernels = native_kernels()
    for k in kernels:
        state = "built" if k["built"] else "not built"
        use = "used by default" if k["default"] else "not used (pure-JAX path)"
        isa = f", {k['isa']}" if k["isa"] and k["built"] else ""
        print(f"  {k['kernel']:<14} {state}{isa}; {use} - {k['used_by']}")
    if kernels[0]["reason"]:
        print(f"  why not: {kernels[0]['reason']}")
    backend = os.environ.get("LIDARJAX_BACKEND")
    if backend:
        print(f"  LIDARJAX_BACKEND={backend}")
    print("data folders searched (in order):")
    for d in data_dirs():
        print(f"  {d}{'' if d.is_dir() else '  (missing)'}")
    print(f"user cache ${CACHE_ENV:<14} {_cache_dir()}")
    mirror = os.environ.get(MIRROR_ENV)
    print(f"mirror     ${MIRROR_ENV:<14} {mirror or '(not set)'}")
    if os.environ.get(OFFLINE_ENV):
        print(f"offline    ${OFFLINE_ENV}={os.environ[OFFLINE_ENV]}")
    cache = default_compilation_cache_dir()
    print(f"compilation cache          {cache if cache is not None else 'off'}")
    return 0


def _size(n: int | None) -> str:
    if n is None:
        return "-"
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)  # pragma: no cover


def cmd_datasets(args) -> int:
    from ..datasets import REGISTRY, data_dirs
    from ..datasets._registry import download_urls

    dirs = data_dirs()
    rows = []
    for name, entry in REGISTRY.items():
        where = next((d / entry.relpath for d in dirs if (d / entry.relpath).is_file()), None)
        size = where.stat().st_size if where is not None else None
        url = "yes" if download_urls(name) else "no"
        rows.append((name, "yes" if where else "no", _size(size), url, entry.description, where))
    w = max(len(r[0]) for r in rows)
    print(f"{'name':<{w}}  local  {'size':>8}  url  description")
    for name, local, size, url, desc, _ in rows:
        print(f"{name:<{w}}  {local:<5}  {size:>8}  {url:<3}  {desc}")
    n_local = sum(r[1] == "yes" for r in rows)
    print(f"\n{n_local} of {len(rows)} files found locally; searched: " + ", ".join(map(str, dirs)))
    return 0


def cmd_fetch(args) -> int:
    from ..datasets import REGISTRY, DataChecksumError, DataNotFoundError, fetch

    if args.all and args.names:
        raise CliInputError("NAME", "give names or --all, not both")
    names = list(REGISTRY) if args.all else list(args.names)
    if not names:
        raise CliInputError("NAME", "give at least one registry name, or --all")
    for n in names:
        if n not in REGISTRY:
            valid = ", ".join(REGISTRY)
            raise CliInputError("NAME", f"unknown data file {n!r}; valid names: {valid}")
    failed = []
    for n in names:
        try:
            path = fetch(n, progress=True)
        except (DataNotFoundError, DataChecksumError) as e:
            if not args.all:
                raise CliInputError("NAME", f"{n}: " + " ".join(str(e).split())) from None
            failed.append(n)
            print(f"{n}: FAILED: {' '.join(str(e).split())}")
            continue
        print(f"{n}: {path} (sha256 verified)")
    if failed:
        print(f"{len(failed)} of {len(names)} files could not be fetched: {', '.join(failed)}")
        return 1
    return 0
