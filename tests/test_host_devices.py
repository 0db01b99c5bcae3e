"""CPU cores as JAX devices, set from the command line (``lidarjax --host-devices N``,
``$LIDARJAX_HOST_DEVICES``) and the experiments (``$LIDARJAX_HOST_DEVICES`` in
``experiments/_common.setup``) before JAX starts; never by importing lidarjax.

JAX fixes its devices when its backends start, so the positive cases run in fresh
processes; this process (JAX started, its own device count) checks the errors."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import jax
import pytest

import lidarjax.distributed as dist
from lidarjax.cli import main

ROOT = Path(__file__).resolve().parents[1]
FLAG = "--xla_force_host_platform_device_count"


def _clean_env(**extra) -> dict:
    """This environment without a host device count (one CPU device), plus ``extra``."""
    env = dict(os.environ)
    env["XLA_FLAGS"] = re.sub(rf"{FLAG}=\S*", "", env.get("XLA_FLAGS", "")).strip()
    env.pop(dist.HOST_DEVICES_ENV, None)
    env["JAX_PLATFORMS"] = "cpu"
    env.update(extra)
    return env


def _run(cmd, env, timeout=180) -> subprocess.CompletedProcess:
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def _lidarjax() -> list[str]:
    """The ``lidarjax`` console script of this interpreter's environment."""
    script = Path(sys.executable).parent / "lidarjax"
    return [str(script)] if script.is_file() else [sys.executable, "-m", "lidarjax.cli"]


def _devices_line(out: str) -> str:
    return next(ln for ln in out.splitlines() if ln.startswith("devices "))


def test_cli_host_devices_option():
    out = _run([*_lidarjax(), "--host-devices", "2", "info"], _clean_env()).stdout
    assert _devices_line(out) == "devices    cpu:0, cpu:1 (2 devices, default backend: cpu)"


def test_cli_host_devices_env():
    out = _run([*_lidarjax(), "info"], _clean_env(LIDARJAX_HOST_DEVICES="3")).stdout
    assert "(3 devices, default backend: cpu)" in _devices_line(out)


def test_cli_without_option_has_one_device():
    out = _run([*_lidarjax(), "info"], _clean_env()).stdout
    assert _devices_line(out) == "devices    cpu:0 (1 device, default backend: cpu)"


CHILD = r"""
import json, os, subprocess, sys
from lidarjax.cli import main

code = main(["--host-devices", "2", "datasets"])  # a subcommand that does not start JAX
env = {k: os.environ.get(k) for k in ("XLA_FLAGS", "LIDARJAX_HOST_DEVICES")}
# what `lidarjax experiment` does: a new Python process with this environment, whose
# experiment calls experiments/_common.setup() before its first JAX computation
grandchild = (
    "import sys; sys.path.insert(0, 'experiments'); import _common, jax; "
    "_common.setup(); print(len(jax.devices()))"
)
n = subprocess.run([sys.executable, "-c", grandchild], capture_output=True, text=True,
                   check=True, timeout=120).stdout.split()[-1]
import jax

print("RESULT " + json.dumps({"code": code, "env": env, "devices": len(jax.devices()),
                              "experiment_devices": int(n)}))
"""


def test_cli_option_reaches_experiments():
    """``lidarjax --host-devices 2 experiment ...``: the experiment's process inherits
    ``XLA_FLAGS`` and ``$LIDARJAX_HOST_DEVICES`` and has the same 2 devices."""
    env = _clean_env(XLA_FLAGS=f"--xla_cpu_multi_thread_eigen=true {FLAG}=5")
    out = _run([sys.executable, "-c", CHILD], env).stdout
    r = json.loads(next(ln for ln in out.splitlines() if ln.startswith("RESULT "))[7:])
    assert r["code"] == 0
    assert r["env"] == {
        "XLA_FLAGS": f"--xla_cpu_multi_thread_eigen=true {FLAG}=2",  # replaced, others kept
        "LIDARJAX_HOST_DEVICES": "2",
    }
    assert r["devices"] == 2 and r["experiment_devices"] == 2


SHARED = ROOT / ".." / "shared" / "data"


@pytest.mark.slow  # two CLI runs on a shared log (~35 s)
@pytest.mark.skipif(not SHARED.is_dir(), reason="needs ../shared/data")  # as tests/test_cli.py
def test_cli_localize_splits_particles_over_host_devices(tmp_path):
    """``lidarjax --host-devices 2 localize``: the particles are split over the 2 devices
    and the trajectory is the one-device trajectory, bit for bit."""
    assert main(["map", "intel", "-o", str(tmp_path / "map"), "--scans", "0:40:2",
                 "--no-progress"]) == 0  # fmt: skip
    common = [str(tmp_path / "map" / "map.npz"), "intel", "--scans", "0:10", "--no-progress"]
    runs = {}
    for name, opts in (("one", []), ("two", ["--host-devices", "2"])):
        argv = [*_lidarjax(), *opts, "localize", *common, "-o", str(tmp_path / name)]
        runs[name] = _run([*argv, "--particles", "64", "--chunk", "4"], _clean_env()).stdout
    assert "particles split over 2 devices" in runs["two"]
    assert "devices" not in runs["one"]  # one device: no note
    one = (tmp_path / "one" / "trajectory.tum").read_text()
    assert one.count("\n") == 9 and one == (tmp_path / "two" / "trajectory.tum").read_text()
    odd = [*_lidarjax(), "--host-devices", "2", "localize", *common, "-o", str(tmp_path / "odd")]
    assert "not split over the 2 devices" in _run([*odd, "--particles", "63"], _clean_env()).stdout


IMPORTS = r"""
import json, os, sys
before = os.environ.get("XLA_FLAGS")
import lidarjax, lidarjax.distributed, lidarjax.cli, lidarjax.cli._main
import lidarjax.datasets, lidarjax.rays, lidarjax.raytrace, lidarjax.maps
import lidarjax.sensor_models, lidarjax.features, lidarjax.localization, lidarjax.sim
import lidarjax.metrics, lidarjax.testing
from jax._src import xla_bridge
import jax

print("RESULT " + json.dumps({
    "before": before,
    "after": os.environ.get("XLA_FLAGS"),
    "started": xla_bridge.backends_are_initialized(),
    "num_cpu_devices": jax.config.jax_num_cpu_devices,
    "devices": len(jax.devices()),
}))
"""


def test_importing_lidarjax_never_sets_devices():
    """Not even with ``$LIDARJAX_HOST_DEVICES`` set: only the command line and the
    experiments' setup act on it."""
    env = _clean_env(XLA_FLAGS="--xla_cpu_multi_thread_eigen=true", LIDARJAX_HOST_DEVICES="2")
    out = _run([sys.executable, "-c", IMPORTS], env).stdout
    r = json.loads(next(ln for ln in out.splitlines() if ln.startswith("RESULT "))[7:])
    assert r["before"] == r["after"] == "--xla_cpu_multi_thread_eigen=true"
    assert r["started"] is False  # importing started no JAX backend
    assert r["num_cpu_devices"] == -1
    assert r["devices"] == 1


# ---------------------------------------------------------------- errors, in this process
@pytest.fixture
def started(monkeypatch) -> int:
    """This process's CPU device count (JAX started); XLA_FLAGS and the variable restored."""
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
    monkeypatch.setenv(dist.HOST_DEVICES_ENV, "")  # recorded, so the CLI's value is undone
    monkeypatch.delenv(dist.HOST_DEVICES_ENV)
    return len(jax.local_devices(backend="cpu"))


def test_cli_host_devices_after_jax_started(started, capsys):
    assert main(["--host-devices", str(started + 1), "info"]) == 2
    err = capsys.readouterr().err
    assert "argument --host-devices:" in err and "JAX already started" in err
    assert f"{FLAG}={started + 1}" not in os.environ["XLA_FLAGS"]  # nothing changed
    assert main(["--host-devices", str(started), "info"]) == 0  # the count it has: fine
    names = ", ".join(f"cpu:{d.id}" for d in jax.devices())
    assert f"devices    {names} ({started} device" in capsys.readouterr().out


@pytest.mark.parametrize("value", ["0", "-1"])
def test_cli_host_devices_not_positive(started, value, capsys):
    assert main(["--host-devices", value, "info"]) == 2
    assert "argument --host-devices: must be >= 1" in capsys.readouterr().err


@pytest.mark.parametrize("value", ["two", "0", "1.5"])
def test_cli_host_devices_env_invalid(started, monkeypatch, value, capsys):
    monkeypatch.setenv(dist.HOST_DEVICES_ENV, value)
    assert main(["info"]) == 2
    err = capsys.readouterr().err
    assert f"argument ${dist.HOST_DEVICES_ENV}: must be a positive integer" in err


def test_use_host_devices(started):
    os.environ["XLA_FLAGS"] = f"{FLAG}=7 --xla_cpu_multi_thread_eigen=true"
    dist.use_host_devices(started)  # JAX started with this count: no error
    assert os.environ["XLA_FLAGS"] == f"--xla_cpu_multi_thread_eigen=true {FLAG}={started}"
    with pytest.raises(RuntimeError, match=f"cannot expose {started + 1} host devices"):
        dist.use_host_devices(started + 1)
    for bad in (0, -2, 1.5, True, "x"):
        with pytest.raises(ValueError, match="n must be a positive integer"):
            dist.use_host_devices(bad)


def test_experiment_setup_after_jax_started(started, monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "experiments"))
    import _common

    monkeypatch.setenv(dist.HOST_DEVICES_ENV, str(started + 1))
    with pytest.raises(RuntimeError, match=rf"\$LIDARJAX_HOST_DEVICES={started + 1}: cannot"):
        _common.setup()


def test_initialize_cpu_rejects_bad_arguments():
    """Checked before JAX is touched (this process keeps its single-process JAX)."""
    with pytest.raises(ValueError, match="collectives"):
        dist.initialize_cpu("127.0.0.1:1", 2, 0, collectives="nccl")
    with pytest.raises(ValueError, match="timeout_s"):
        dist.initialize_cpu("127.0.0.1:1", 2, 0, timeout_s=0)
