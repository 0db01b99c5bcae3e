"""Test configuration: float64 everywhere, a PRNG key fixture, hypothesis profiles, the
persistent compilation cache and a per-module release of compiled code."""

import os

import jax
import pytest
from hypothesis import HealthCheck, settings

import lidarjax

jax.config.update("jax_enable_x64", True)

# No test downloads from the internet: registry entries with a public URL would otherwise
# be fetched into the user cache on a machine with network access (the download path is
# tested against a local HTTP server, tests/test_registry_download.py).
os.environ.setdefault("LIDARJAX_OFFLINE", "1")


# JAX's persistent compilation cache: ``LIDARJAX_JAX_CACHE`` names a folder (``off``, ``0``
# or empty disable it), default ``$XDG_CACHE_HOME/lidarjax/jax-compilation-cache``
# (``~/.cache/...``). A second run of the suite then loads most executables instead of
# compiling them; an unwritable folder only warns.
lidarjax.enable_compilation_cache()

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
