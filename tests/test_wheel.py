"""The built wheel works outside the repository.

Builds the wheel (``pip wheel --no-deps``), installs it into a fresh virtual environment in
a temporary folder (dependencies from the package index; pip's cache makes a second run
fast), and from another temporary working folder, with ``LIDARJAX_DATA`` pointing at the
shared data, runs ``lidarjax info``, ``lidarjax map``, ``lidarjax experiment demo`` on tiny
settings and the README's quickstart. Nothing may come from the repository: ``PYTHONPATH``
is cleared and every check confirms the installed package is the one in the new
environment, and that the experiment wrote into the working folder, not site-packages.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = (ROOT / ".." / "shared" / "data").resolve()

pytestmark = [
    pytest.mark.slow,  # ~3-4 min: builds, installs (index / pip cache) and runs
    pytest.mark.skipif(not SHARED.is_dir(), reason="needs ../shared/data"),
]

DEMO_OVERRIDES = (
    "scans.n_poses=30",
    "scans.n_beams=91",
    "localization.n_poses=12",
    "localization.n_beams=15",
    "localization.particles=50",
    "dct.cell_m=2.0",
    "dct.n_rays=800",
    "dct.max_steps=30",
    "polylines.scan=3",
    "polylines.max_vertices=8",
)


def _run(cmd, *, cwd, env, timeout=900) -> subprocess.CompletedProcess:
    proc = subprocess.run(
        [str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )
    assert proc.returncode == 0, f"{cmd}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """``(venv, cwd, env)``: the wheel installed into a new venv, an empty working folder."""
    base = tmp_path_factory.mktemp("wheel")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env.update(LIDARJAX_DATA=str(SHARED), MPLBACKEND="Agg", PYTHONNOUSERSITE="1")
    dist = base / "dist"
    _run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", dist, ROOT],
        cwd=base, env=env,
    )  # fmt: skip
    (wheel,) = dist.glob("lidarjax-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    for required in (
        "lidarjax/cli/__init__.py",
        "lidarjax/_experiments/experiments/demo.py",
        "lidarjax/_experiments/experiments/_common.py",
        "lidarjax/_experiments/configs/demo.yaml",
    ):
        assert required in names, f"{required} is not in the wheel"
    for script in (ROOT / "experiments").glob("[a-z]*.py"):  # every experiment + config
        assert f"lidarjax/_experiments/experiments/{script.name}" in names, script.name
    for config in (ROOT / "configs").glob("*.yaml"):
        assert f"lidarjax/_experiments/configs/{config.name}" in names, config.name
    assert not any(n.endswith(".so") for n in names)  # a pure wheel: kernels build locally
    venv = base / "venv"
    _run([sys.executable, "-m", "venv", venv], cwd=base, env=env)
    py = venv / "bin" / "python"
    _run([py, "-m", "pip", "install", "-q", wheel], cwd=base, env=env, timeout=1800)
    cwd = base / "work"
    cwd.mkdir()
    return venv, cwd, env


def test_info_from_the_wheel(installed):
    venv, cwd, env = installed
    out = _run([venv / "bin" / "lidarjax", "info"], cwd=cwd, env=env).stdout
    site = re.search(r"^lidarjax +\S+ +\((.*)\)$", out, re.M).group(1)
    assert Path(site).resolve().is_relative_to(venv.resolve())  # not the repository
    assert str(SHARED) in out and "native kernels" in out


def test_map_from_the_wheel(installed):
    venv, cwd, env = installed
    _run([venv / "bin" / "lidarjax", "map", "carmen/intel", "--scans", "0:40", "-o", "out",
          "--no-progress"], cwd=cwd, env=env)  # fmt: skip
    for f in ("map.npz", "map.yaml", "map.pgm", "map.png"):
        assert (cwd / "out" / f).stat().st_size > 0, f


def test_experiment_demo_from_the_wheel(installed):
    venv, cwd, env = installed
    _run([venv / "bin" / "lidarjax", "experiment", "demo", *DEMO_OVERRIDES], cwd=cwd, env=env)
    res = json.loads((cwd / "outputs" / "demo" / "results.json").read_text())
    assert res["n_rays"] == 30 * 91 and set(res["localization"]) == {"dec", "ref", "end"}
    assert (cwd / "outputs" / "demo" / "demo.png").stat().st_size > 0
    site = next((venv / "lib").glob("python*/site-packages"))
    assert not list(site.rglob("outputs"))  # nothing written into the installation


def test_readme_examples_from_the_wheel(installed):
    venv, cwd, env = installed
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.S)
    script = cwd / "quickstart.py"
    checks = (
        "import lidarjax",
        f"assert lidarjax.__file__.startswith({str(venv.resolve())!r}), lidarjax.__file__",
        "assert track.shape == (19, 3) and bool(np.isfinite(np.asarray(track)).all())",
        "print('quickstart ok')",
    )
    assert len(blocks) >= 6  # the quickstart and every format example
    script.write_text("\n".join(blocks) + "\n" + "\n".join(checks) + "\n")
    out = _run([venv / "bin" / "python", script], cwd=cwd, env=env).stdout
    assert "quickstart ok" in out
