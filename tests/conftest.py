"""Test configuration: float64 everywhere, a PRNG key fixture, hypothesis profiles, the
persistent compilation cache and a per-module release of compiled code."""

import os
from pathlib import Path

import jax
import pytest
from hypothesis import HealthCheck, settings

jax.config.update("jax_enable_x64", True)


def _compilation_cache_dir() -> Path | None:
    """Where JAX's persistent compilation cache lives for the test suite.

    ``LIDARJAX_JAX_CACHE`` names a folder, or ``off`` disables the cache; the default is
    ``$XDG_CACHE_HOME/lidarjax/jax-compilation-cache`` (``~/.cache/...``). A second run of
    the suite then loads most executables instead of compiling them. The cache key holds
    the jaxlib version, the XLA flags and the program, so a stale entry is never reused.
    """
    env = os.environ.get("LIDARJAX_JAX_CACHE", "")
    if env.lower() == "off":
        return None
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "lidarjax" / "jax-compilation-cache"


_cache = _compilation_cache_dir()
if _cache is not None:
    try:
        _cache.mkdir(parents=True, exist_ok=True)
    except OSError:  # read-only home: run without the cache
        _cache = None
if _cache is not None:
    jax.config.update("jax_compilation_cache_dir", str(_cache))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)

settings.register_profile(
    "default",
    max_examples=40,
    deadline=None,
    derandomize=True,  # CI runs the same examples every time
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile("default")


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_code():
    """Drop JAX's compiled executables after every test module.

    Each executable keeps about three memory mappings of machine code alive; a process that
    compiles the whole slow suite (~20 000 executables) reaches Linux's default limit of
    65 530 mappings (``vm.max_map_count``) and XLA aborts in the next compilation. Clearing
    the caches between modules bounds the mappings by the largest module's programs.
    """
    yield
    jax.clear_caches()


@pytest.fixture
def key():
    return jax.random.key(0)
