"""Several processes and host devices: thin helpers over ``jax.distributed`` and JAX's CPU
device count, for the command line, the experiments and your own scripts.

- :func:`use_host_devices` exposes a CPU's cores as ``n`` JAX devices (what
  ``XLA_FLAGS=--xla_force_host_platform_device_count=n`` does), so that
  :func:`~lidarjax.localization.shard_state` can split particles over them. It must run
  before JAX starts its backends (before the first JAX computation). The ``lidarjax``
  command line calls it for ``--host-devices N`` / ``$LIDARJAX_HOST_DEVICES``, the
  experiments (``experiments/_common.py``) for ``$LIDARJAX_HOST_DEVICES``.
- :func:`initialize_cpu` joins a multi-process JAX run on the CPU backend
  (``jax.distributed.initialize`` with CPU collectives): afterwards ``jax.devices()`` holds
  the devices of every process, and a mesh over them (``particle_mesh()``) spans the
  processes. Every process runs the same program (same inputs, same calls in the same
  order); each computes on its own devices and the collectives cross the processes.

Importing lidarjax (this module included) never changes ``XLA_FLAGS`` or any JAX setting;
only calling these functions does.
"""

from __future__ import annotations

import os
import re

__all__ = [
    "HOST_DEVICES_ENV",
    "host_devices_from_env",
    "initialize_cpu",
    "use_host_devices",
]

HOST_DEVICES_ENV = "LIDARJAX_HOST_DEVICES"
"""Environment variable read by the command line and the experiments: the number of CPU
host devices (see :func:`use_host_devices`)."""

_FLAG = "--xla_force_host_platform_device_count"


def _count(n, name: str) -> int:
    if isinstance(n, bool) or not isinstance(n, int | str):
        raise ValueError(f"{name} must be a positive integer, got {n!r}")
    try:
        value = int(n)
    except ValueError:
        raise ValueError(f"{name} must be a positive integer, got {n!r}") from None
    if value < 1:
        raise ValueError(f"{name} must be a positive integer, got {n!r}")
    return value


def host_devices_from_env() -> int | None:
    """The device count in ``$LIDARJAX_HOST_DEVICES``, or None when it is unset or empty.

    Raises:
        ValueError: the variable is set to something other than a positive integer.
    """
    value = os.environ.get(HOST_DEVICES_ENV, "").strip()
    return None if not value else _count(value, f"${HOST_DEVICES_ENV}")


def use_host_devices(n: int) -> None:
    """Expose the CPU as ``n`` JAX devices (``jax.devices("cpu")`` then has ``n``).

    Sets JAX's ``jax_num_cpu_devices`` and puts
    ``--xla_force_host_platform_device_count=n`` into ``XLA_FLAGS`` of this process's
    environment (replacing an earlier count), so Python processes started from this one
    (e.g. ``lidarjax experiment``) get the same devices. Calling it again with the same
    ``n`` is a no-op. GPUs and other accelerators are unaffected: on a GPU machine
    ``jax.devices()`` still lists the GPUs.

    Args:
        n: number of CPU devices (>= 1). The devices share the machine's cores; more
            devices than cores gains nothing.

    Raises:
        ValueError: ``n`` is not a positive integer.
        RuntimeError: JAX's backends already started with another CPU device count
            (a JAX computation ran before this call); call it first thing, or set
            ``XLA_FLAGS`` before starting Python.
    """
    n = _count(n, "n")
    import jax

    try:
        jax.config.update("jax_num_cpu_devices", n)
    except RuntimeError:
        have = len(jax.local_devices(backend="cpu"))
        if have != n:
            raise RuntimeError(
                f"cannot expose {n} host devices: JAX already started with {have} CPU "
                "device(s) in this process; set the host device count before the first "
                "JAX computation"
            ) from None
    flags = re.sub(rf"\s*{_FLAG}=\S*", "", os.environ.get("XLA_FLAGS", "")).strip()
    os.environ["XLA_FLAGS"] = f"{flags} {_FLAG}={n}".strip()


def initialize_cpu(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    *,
    local_devices: int | None = None,
    collectives: str = "gloo",
    timeout_s: int = 300,
) -> None:
    """Join a multi-process JAX run on the CPU backend (``jax.distributed.initialize``).

    Call it in every process, first thing, before any JAX computation. Process 0 runs
    the coordinator at ``coordinator_address``; the others connect to it. On SLURM (and
    Open MPI) all three arguments may be omitted: JAX detects them from the job's
    environment (``SLURM_NTASKS``, ``SLURM_PROCID``, the first node of
    ``SLURM_STEP_NODELIST``, a port derived from ``SLURM_JOB_ID``).

    Args:
        coordinator_address: ``host:port`` of process 0, reachable from every process
            (``127.0.0.1:port`` for processes on one machine).
        num_processes: number of processes.
        process_id: this process's number, ``0 <= process_id < num_processes``.
        local_devices: CPU devices of this process (:func:`use_host_devices`; default:
            JAX's default or ``XLA_FLAGS``, one device).
        collectives: JAX's CPU collectives between processes, ``"gloo"`` (TCP, built
            into jaxlib) or ``"mpi"`` (needs an MPI library).
        timeout_s: seconds to wait for every process to join.

    Raises:
        ValueError: an argument is out of range.
        RuntimeError: JAX's backends already started, or the processes did not connect
            within ``timeout_s``.
    """
    if collectives not in ("gloo", "mpi"):
        raise ValueError(f"collectives must be 'gloo' or 'mpi', got {collectives!r}")
    timeout_s = _count(timeout_s, "timeout_s")
    if local_devices is not None:
        use_host_devices(local_devices)
    import jax

    jax.config.update("jax_platforms", "cpu")
    jax.config.update("jax_cpu_collectives_implementation", collectives)
    jax.distributed.initialize(
        coordinator_address=coordinator_address,
        num_processes=num_processes,
        process_id=process_id,
        initialization_timeout=timeout_s,
    )
