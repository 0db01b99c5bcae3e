"""The machine description every benchmark writes into its JSON (shared by all scripts)."""

from __future__ import annotations

import os
import platform

import jax
import jax.numpy as jnp
import numpy as np


def machine_info(**extra) -> dict:
    """CPU, platform, library versions, dtype and load average at the start of the run.

    Args:
        **extra: further entries (e.g. library versions a benchmark depends on); they
            override the defaults of the same name.
    """
    cpu_model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu_model = next(
                (ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")),
                cpu_model,
            )
    except OSError:
        pass
    info = {
        "cpu_count": os.cpu_count(),
        "cpu_model": cpu_model,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "numpy": np.__version__,
        "jax_backend": jax.default_backend(),
        "dtype": str(jnp.result_type(float)),
        "load_average_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "noise_note": "shared 2-core machine; other processes may have been running",
    }
    info.update(extra)
    return info
