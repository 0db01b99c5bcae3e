"""``lidarjax.pin_to_one_core``: pins a fresh process, refuses once JAX has started."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

import lidarjax

needs_affinity = pytest.mark.skipif(
    not hasattr(os, "sched_setaffinity"), reason="os.sched_setaffinity is Linux-only"
)


@needs_affinity
def test_pin_to_one_core_in_a_fresh_process():
    code = (
        "import os, lidarjax, jax.numpy as jnp\n"
        "c = lidarjax.pin_to_one_core()\n"
        "float(jnp.sum(jnp.arange(4.0)))\n"  # JAX starts after the pinning
        "print(c, sorted(os.sched_getaffinity(0)))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    core, allowed = out.stdout.split(" ", 1)
    assert allowed.strip() == f"[{int(core)}]"
    assert int(core) == min(os.sched_getaffinity(0))


@needs_affinity
def test_pin_to_one_core_refuses_after_jax_started_and_bad_cores():
    import jax.numpy as jnp

    float(jnp.sum(jnp.arange(3.0)))  # the backend exists in this test process
    before = os.sched_getaffinity(0)
    with pytest.raises(RuntimeError, match="before the first JAX computation"):
        lidarjax.pin_to_one_core()
    assert os.sched_getaffinity(0) == before  # nothing changed
    code = "import lidarjax\nlidarjax.pin_to_one_core(10**6)\n"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode != 0 and "core must be one of the allowed cores" in out.stderr
