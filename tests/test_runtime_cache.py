"""``lidarjax.enable_compilation_cache``: the folder rules, a second process loading what
the first one compiled (seen through JAX's cache events and the folder, never through
timing), and an unwritable folder."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import pytest

import lidarjax
from lidarjax._runtime import default_compilation_cache_dir

CONFIG = (
    "jax_compilation_cache_dir",
    "jax_persistent_cache_min_compile_time_secs",
    "jax_persistent_cache_min_entry_size_bytes",
)

# A fresh process: turn the cache on, count JAX's cache events while one jitted function
# compiles (or loads), print the counts, the folder in use and the folder's entries.
CHILD = r"""
import json, os, sys
import jax
import jax.numpy as jnp
import lidarjax

events = {"hits": 0, "misses": 0}

def listener(event, **kw):
    if event == "/jax/compilation_cache/cache_hits":
        events["hits"] += 1
    elif event == "/jax/compilation_cache/cache_misses":
        events["misses"] += 1

folder = lidarjax.enable_compilation_cache()
jax.monitoring.register_event_listener(listener)

@jax.jit
def f(x):
    return jnp.cumsum(jnp.sin(x) * jnp.cos(x[::-1])) / (1.0 + x * x)

f(jnp.linspace(0.0, 1.0, 37)).block_until_ready()
jax.monitoring.unregister_event_listener(listener)
entries = sorted(os.listdir(folder)) if folder is not None else None
print(json.dumps({"folder": None if folder is None else str(folder), "entries": entries, **events}))
"""


def _child(env: dict) -> dict:
    full = {**os.environ, **env}
    out = subprocess.run(
        [sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=300, env=full
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def _config() -> tuple:
    return tuple(getattr(jax.config, name) for name in CONFIG)


@pytest.mark.parametrize("value", ["off", "OFF", "0", ""])
def test_env_off_gives_none_and_changes_nothing(monkeypatch, value):
    monkeypatch.setenv("LIDARJAX_JAX_CACHE", value)
    before = _config()
    assert default_compilation_cache_dir() is None
    assert lidarjax.enable_compilation_cache() is None
    assert _config() == before


def test_default_folder_follows_env_and_xdg(monkeypatch, tmp_path):
    monkeypatch.delenv("LIDARJAX_JAX_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_compilation_cache_dir() == tmp_path / "xdg/lidarjax/jax-compilation-cache"
    monkeypatch.delenv("XDG_CACHE_HOME")
    expected = Path.home() / ".cache/lidarjax/jax-compilation-cache"
    assert default_compilation_cache_dir() == expected
    monkeypatch.setenv("LIDARJAX_JAX_CACHE", str(tmp_path / "mine"))
    assert default_compilation_cache_dir() == tmp_path / "mine"


def test_a_second_process_loads_what_the_first_compiled(tmp_path):
    folder = tmp_path / "cache"
    env = {"LIDARJAX_JAX_CACHE": str(folder)}
    first = _child(env)
    assert first["folder"] == str(folder.resolve())
    assert first["misses"] >= 1 and first["hits"] == 0
    assert len(first["entries"]) >= 1  # written by the first process
    second = _child(env)
    # everything the second process compiled came from the folder; nothing new written
    assert second["hits"] >= 1 and second["misses"] == 0
    assert second["entries"] == first["entries"]
    # with the cache off, nothing is read or written
    off = _child({"LIDARJAX_JAX_CACHE": "off"})
    assert off["folder"] is None and off["hits"] == 0 and off["misses"] == 0


def test_unwritable_folder_warns_and_changes_nothing(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    before = _config()
    with pytest.warns(RuntimeWarning, match="compilation cache disabled"):
        assert lidarjax.enable_compilation_cache(blocker / "cache") is None
    assert _config() == before


def test_idempotent_switchable_and_bad_threshold(tmp_path):
    import jax.numpy as jnp

    from lidarjax._runtime import _reopen_cache_if_open

    saved = _config()
    try:
        a = lidarjax.enable_compilation_cache(tmp_path / "a")
        assert a == (tmp_path / "a").resolve()
        before = _config()
        assert lidarjax.enable_compilation_cache(tmp_path / "a") == a  # idempotent
        assert _config() == before
        jax.jit(lambda x: jnp.tanh(x) * 3.25 - x)(jnp.arange(29.0)).block_until_ready()
        n_a = len(os.listdir(a))
        assert n_a >= 1
        # after JAX opened the cache in a, another folder takes over from the next compile
        b = lidarjax.enable_compilation_cache(tmp_path / "b", min_compile_time_s=0.0)
        jax.jit(lambda x: jnp.tanh(x) * 4.75 + x)(jnp.arange(31.0)).block_until_ready()
        assert len(os.listdir(b)) >= 1 and len(os.listdir(a)) == n_a
        after_b = _config()
        for bad in (-1.0, "fast", True, float("nan")):
            with pytest.raises(ValueError, match="min_compile_time_s"):
                lidarjax.enable_compilation_cache(tmp_path / "c", min_compile_time_s=bad)
        assert _config() == after_b and not (tmp_path / "c").exists()
    finally:  # the rest of the suite keeps the cache conftest chose
        for name, value in zip(CONFIG, saved, strict=True):
            jax.config.update(name, value)
        _reopen_cache_if_open()


def test_import_does_not_enable_the_cache(tmp_path):
    code = "import jax, lidarjax\nprint(jax.config.jax_compilation_cache_dir)\n"
    env = {**os.environ, "LIDARJAX_JAX_CACHE": str(tmp_path / "never")}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "None"
    assert not (tmp_path / "never").exists()
