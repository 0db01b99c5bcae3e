"""Experiment sweeps: Hydra multiruns with a real launcher (joblib locally, submitit on
SLURM), one folder per job named by its overrides, resuming (finished jobs are skipped)
and the merged table (experiments/merge_results.py)."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from omegaconf.errors import InterpolationResolutionError

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
sys.path.insert(0, str(ROOT / "experiments"))

import merge_results  # noqa: E402
from _common import INCOMPLETE, is_complete  # noqa: E402
from _schemas import SCHEMAS  # noqa: E402

# posterior_corridor on a 20-voxel corridor: a few seconds per job once compiled
TINY = ["runs=20", "n_values=[1]", "n_voxels=20", "steps=20"]
JOBS = {"0": "n_values=[1],n_voxels=20,runs=20,seed=0,steps=20",
        "1": "n_values=[1],n_voxels=20,runs=20,seed=1,steps=20"}  # fmt: skip
SKIP = "skipping job"


def _hydra_cfg(name: str, overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        return compose(config_name=name, overrides=overrides, return_hydra_config=True)


# --------------------------------------------------------------------------------------
# Configs: deterministic sweep folders, launcher presets
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(SCHEMAS))
def test_every_experiment_sweeps_into_a_fixed_folder_named_by_the_overrides(name):
    cfg = _hydra_cfg(name, [])
    assert cfg.hydra.sweep.dir == f"outputs/sweeps/{name}"
    subdir = OmegaConf.to_container(cfg.hydra.sweep, resolve=False)["subdir"]
    assert subdir == "${hydra.job.override_dirname}"
    assert cfg.hydra.run.dir == f"outputs/{name}" and cfg.hydra.job.chdir is False


def test_slurm_preset_composes_without_submitting(monkeypatch):
    cfg = _hydra_cfg("mcl", ["hydra/launcher=slurm", "hydra.launcher.timeout_min=240"])
    launcher = cfg.hydra.launcher
    assert launcher._target_.endswith("submitit_launcher.SlurmLauncher")
    assert launcher.timeout_min == 240 and launcher.cpus_per_task == 4
    assert launcher.mem_gb == 16 and launcher.tasks_per_node == 1
    raw = OmegaConf.to_container(launcher, resolve=False)
    assert raw["partition"] == "${oc.env:SLURM_PARTITION}"  # the placeholder
    assert raw["submitit_folder"] == "${hydra.sweep.dir}/.submitit/%j"
    monkeypatch.delenv("SLURM_PARTITION", raising=False)
    with pytest.raises(InterpolationResolutionError, match="SLURM_PARTITION"):
        launcher.partition  # unset: the launcher fails to build, before any submission
    monkeypatch.setenv("SLURM_PARTITION", "cpu")
    assert launcher.partition == "cpu"
    cfg = _hydra_cfg("mcl", ["hydra/launcher=slurm", "hydra.launcher.partition=gpu"])
    assert cfg.hydra.launcher.partition == "gpu"


def test_local_preset_is_joblib_with_two_workers():
    launcher = _hydra_cfg("polylines", ["hydra/launcher=local"]).hydra.launcher
    assert launcher._target_.endswith("joblib_launcher.JoblibLauncher")
    assert launcher.n_jobs == 2


# --------------------------------------------------------------------------------------
# Merging: one row per job, jobs without results listed as missing
# --------------------------------------------------------------------------------------


def _fake_job(sweep: Path, overrides: list[str], results: dict | None, marker=False) -> Path:
    job = sweep / ",".join(sorted(overrides))
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text(OmegaConf.to_yaml(overrides))
    (job / ".hydra" / "hydra.yaml").write_text("hydra:\n  job:\n    name: mcl\n")
    if results is not None:
        (job / "results.json").write_text(json.dumps(results))
    if marker:
        (job / INCOMPLETE).write_text("")
    return job


def test_merge_lists_every_job_and_marks_the_missing_ones(tmp_path):
    sweep = tmp_path / "sweep"
    res = {"mean_over_logs_pos_err_m": {"dec": 0.25, "end": 0.5}, "runtime_s": 3.0}
    done = _fake_job(sweep, ["seed=2", "filter.particles=100"], res)
    _fake_job(sweep, ["seed=10", "filter.particles=100"], None)
    half = _fake_job(sweep, ["seed=1", "filter.particles=300"], res, marker=True)
    assert is_complete(done) and not is_complete(half)
    t = merge_results.merge(sweep)
    assert t["experiment"] == "mcl"
    assert t["override_columns"] == ["seed", "filter.particles"]  # command-line order
    assert t["number_columns"] == ["pos_err_m dec", "pos_err_m end", "runtime_s"]
    rows = {r["seed"]: r for r in t["rows"]}
    assert [r["seed"] for r in t["rows"]] == ["1", "2", "10"]  # sorted, numbers as numbers
    assert rows["2"]["status"] == "done" and rows["2"]["pos_err_m dec"] == 0.25
    assert rows["10"] == {**rows["10"], "status": "missing", "note": "no results.json"}
    assert rows["1"]["status"] == "missing" and rows["1"]["pos_err_m end"] is None
    assert rows["1"]["note"] == "interrupted or failed"
    on_disk = json.loads((sweep / "merged.json").read_text())
    assert on_disk["rows"] == t["rows"]
    with open(sweep / "merged.csv") as fh:
        assert [r["status"] for r in csv.DictReader(fh)] == ["missing", "done", "missing"]
    md = (sweep / "merged.md").read_text()
    assert "1 of 3 jobs done" in md and md.count("| missing |") == 2


def test_merge_needs_a_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match="sweep_dir"):
        merge_results.collect(tmp_path / "nope")


# --------------------------------------------------------------------------------------
# End to end: a joblib multirun, resumed
# --------------------------------------------------------------------------------------


def _sweep(sweep: Path, launcher: list[str]) -> subprocess.CompletedProcess:
    cmd = [sys.executable, str(ROOT / "experiments" / "posterior_corridor.py"), "-m",
           *launcher, f"hydra.sweep.dir={sweep}", *TINY, "seed=0,1"]  # fmt: skip
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def _skips(job: Path) -> int:
    return (job / "posterior_corridor.log").read_text().count(SKIP)


@pytest.mark.slow  # three multiruns of two jobs: 40-80 s (imports dominate)
def test_joblib_sweep_merges_skips_finished_jobs_and_reruns_missing_ones(tmp_path):
    sweep = tmp_path / "sweep"
    joblib = ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"]
    _sweep(sweep, joblib)
    jobs = {seed: sweep / d for seed, d in JOBS.items()}
    for job in jobs.values():
        assert is_complete(job) and not (job / INCOMPLETE).exists()
        assert (job / "figure_8_2.png").stat().st_size > 0 and _skips(job) == 0
    t = merge_results.merge(sweep)
    assert t["experiment"] == "posterior_corridor"
    assert set(t["override_columns"]) == {"runs", "n_values", "n_voxels", "steps", "seed"}
    assert [(r["job"], r["status"], r["seed"], r["runs"]) for r in t["rows"]] == [
        (JOBS["0"], "done", "0", "20"),
        (JOBS["1"], "done", "1", "20"),
    ]
    for r in t["rows"]:
        stored = json.loads((sweep / r["job"] / "results.json").read_text())
        want = stored["rows"][0]["rho"]["decay_rate"]["FMP_conjugate"]["mean"]
        assert r["rho n=1 decay_rate/FMP_conjugate"] == want
    assert (sweep / "merged.md").read_text().count("| done |") == 2

    # the same sweep again (the local preset): both jobs skipped, nothing rewritten
    mtimes = {s: (j / "results.json").stat().st_mtime_ns for s, j in jobs.items()}
    _sweep(sweep, ["hydra/launcher=local"])
    for seed, job in jobs.items():
        assert _skips(job) == 1, (job / "posterior_corridor.log").read_text()
        assert (job / "results.json").stat().st_mtime_ns == mtimes[seed]

    # one job lost its results (as if interrupted): only that one runs again
    (jobs["1"] / "results.json").unlink()
    assert merge_results.collect(sweep)["rows"][1]["status"] == "missing"
    _sweep(sweep, joblib)
    assert _skips(jobs["0"]) == 2 and _skips(jobs["1"]) == 1
    assert (jobs["0"] / "results.json").stat().st_mtime_ns == mtimes["0"]
    assert is_complete(jobs["1"])
    assert [r["status"] for r in merge_results.merge(sweep)["rows"]] == ["done", "done"]
