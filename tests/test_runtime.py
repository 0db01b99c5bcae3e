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


def test_cpu_info_reads_model_and_widest_vector_isa(tmp_path):
    """The CPU a result was measured on (its float32 code, and so the SLAM front end's
    trajectory, depends on it): the first model name and the widest of AVX-512 / AVX2 /
    AVX / SSE4.2 among the first processor's flags; None for what is missing."""
    from lidarjax._runtime import cpu_info

    f = tmp_path / "cpuinfo"
    f.write_text(
        "processor\t: 0\nmodel name\t: Test CPU @ 2 GHz\nflags\t\t: fpu sse4_2 avx avx2\n\n"
        "processor\t: 1\nmodel name\t: Other\nflags\t\t: fpu avx512f\n"
    )
    assert cpu_info(f) == {"cpu_model": "Test CPU @ 2 GHz", "cpu_vector_isa": "avx2"}
    f.write_text("processor\t: 0\nflags\t\t: fpu avx512f avx2\n")
    assert cpu_info(f) == {"cpu_model": None, "cpu_vector_isa": "avx512"}
    f.write_text("processor\t: 0\nflags\t\t: fpu\n")
    assert cpu_info(f) == {"cpu_model": None, "cpu_vector_isa": None}
    assert cpu_info(tmp_path / "missing") == {"cpu_model": None, "cpu_vector_isa": None}
    # experiments' run_info and the benchmarks' machine_info record it
    assert set(cpu_info()) == {"cpu_model", "cpu_vector_isa"}
