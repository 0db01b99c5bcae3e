"""The Hydra experiments run end to end on small configs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_experiment(name: str, out: Path, *overrides: str) -> dict:
    cmd = [sys.executable, str(ROOT / "experiments" / f"{name}.py"), f"hydra.run.dir={out}"]
    proc = subprocess.run(
        [*cmd, *overrides], capture_output=True, text=True, timeout=600, cwd=ROOT
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads((out / "results.json").read_text())


def test_demo_small(tmp_path):
    res = run_experiment(
        "demo", tmp_path, "scans.n_poses=30", "scans.n_beams=91", "grid.resolution_m=0.1"
    )
    assert res["n_rays"] == 30 * 91
    assert sum(res["rays_by_kind"].values()) == res["n_rays"]
    assert res["hits_total"] == res["rays_by_kind"]["HIT"]  # all endpoints inside the grid
    assert res["hits_near_true_walls_fraction"] > 0.99
    assert res["grid_shape"] == [210, 130]
    for f in ("grid_stats.png", "results.md", "results.json"):
        assert (tmp_path / f).stat().st_size > 0
