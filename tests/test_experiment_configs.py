"""Experiment configs: structured schemas (experiments/_schemas.py) checked before any work.

Every ``configs/<name>.yaml`` composes onto its dataclass schema: a wrongly typed override
fails while Hydra composes, a value out of range, an unknown log / model / method name or an
inconsistent combination fails in ``validate`` -- both naming the key and the value, before
any data is loaded. Composing with the schema changes no value of the YAML files.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
sys.path.insert(0, str(ROOT / "experiments"))

import _schemas  # noqa: E402
from _schemas import SCHEMAS, ConfigError, validate  # noqa: E402

EXPERIMENTS = sorted(SCHEMAS)


def composed(name: str, overrides: list[str] = ()):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        return compose(config_name=name, overrides=list(overrides))


def raw_yaml(name: str) -> dict:
    """The values of ``configs/<name>.yaml`` read without any schema (parent configs in
    its defaults list merged first, ``hydra`` settings dropped)."""
    d = OmegaConf.to_container(OmegaConf.load(CONFIGS / f"{name}.yaml"))
    out: dict = {}
    for entry in d.pop("defaults", []):
        if entry != "_self_" and not entry.endswith("_schema"):
            out.update(raw_yaml(entry))
    d.pop("hydra", None)
    out.update(d)
    return out


# --------------------------------------------------------------------------------------
# Defaults
# --------------------------------------------------------------------------------------


def test_every_config_has_a_schema_and_its_experiment_validates():
    assert {p.stem for p in CONFIGS.glob("*.yaml")} == set(SCHEMAS)
    for name in SCHEMAS:
        src = (ROOT / "experiments" / f"{name}.py").read_text()
        assert f'validate(cfg, "{name}")' in src, name
        assert "from _schemas import" in src, name


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_defaults_compose_onto_the_schema_and_validate(name):
    cfg = composed(name)
    assert OmegaConf.get_type(cfg) is SCHEMAS[name]
    validate(cfg, name)
    # The schema holds no values: the composed config is the YAML file, key order and
    # int / float types included (compared as JSON text).
    assert json.dumps(OmegaConf.to_container(cfg, resolve=True)) == json.dumps(raw_yaml(name))


def test_mcl_remedies_keeps_extending_mcl():
    base, ext = composed("mcl"), composed("mcl_remedies", ["filter.particles=77"])
    assert OmegaConf.get_type(ext) is _schemas.MclRemediesConfig
    for key in ("logs", "models", "grid", "endpoint", "refine"):
        assert ext[key] == base[key]
    assert ext.filter.particles == 77
    # the idiom of tests/test_mcl.py: replace the global-localization variants
    cfg = composed(
        "mcl_remedies",
        ["~global_localization.variants", "+global_localization.variants={a:{model:end}}"],
    )
    assert OmegaConf.to_container(cfg.global_localization.variants) == {"a": {"model": "end"}}
    validate(cfg, "mcl_remedies")


def _experiment(name: str):
    """experiments/<name>.py loaded by path (``benchmarks/`` has modules of the same names,
    which another test may have put first on ``sys.path``)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        f"_experiment_{name}", ROOT / "experiments" / f"{name}.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_name_lists_match_the_experiments():
    mcl, mcl_remedies, polylines = (_experiment(n) for n in ("mcl", "mcl_remedies", "polylines"))

    assert tuple(mcl.NAMES) == _schemas.MCL_MODELS
    assert tuple(polylines.METHODS) == _schemas.POLYLINE_METHODS
    assert set(mcl_remedies.LATTICE_DEFAULTS) == _schemas.LATTICE_KEYS
    from lidarjax.datasets import REGISTRY

    assert set(_schemas.carmen_logs()) == {
        n for n, e in REGISTRY.items() if e.relpath.startswith("carmen/")
    }


# --------------------------------------------------------------------------------------
# Wrong types: rejected while composing, naming key and value
# --------------------------------------------------------------------------------------

TYPE_ERRORS = [
    ("demo", "grid.resolution_m=abc", "grid.resolution_m", "abc"),
    ("demo", "scans.n_beams=3.5", "scans.n_beams", "3.5"),
    ("demo", "grid=7", "grid", "7"),
    ("mcl", "grid.resolution_m=abc", "grid.resolution_m", "abc"),
    ("mcl", "filter.particles=many", "filter.particles", "many"),
    ("mcl", "filter.init_std=[1.0,x,0.3]", "filter.init_std", "x"),
    ("mcl_remedies", "diagnose.enabled=maybe", "diagnose.enabled", "maybe"),
    ("pose_likelihood", "grid=7", "grid", "7"),
    ("posterior_corridor", "runs=2.5", "runs", "2.5"),
    ("dct_maps", "resolutions=[10,abc]", "resolutions", "abc"),
    ("decay_rate_fields", "rbf.max_steps=3.5", "rbf.max_steps", "3.5"),
    ("polylines", "J=[10.5]", "J", "10.5"),
    ("planes", "workers=two", "workers", "two"),
    ("poles", "lidar.n_azimuths=3.5", "lidar.n_azimuths", "3.5"),
    ("poles", "route=7", "route", "7"),
    ("slam", "back_end.max_steps=many", "back_end.max_steps", "many"),
    ("demo", "grid.resolutoin_m=0.1", "grid.resolutoin_m", "0.1"),  # misspelt key
]


@pytest.mark.parametrize(("name", "override", "key", "value"), TYPE_ERRORS)
def test_wrong_types_fail_while_composing(name, override, key, value):
    with pytest.raises(ConfigCompositionException) as info:
        composed(name, [override])
    text = f"{info.value}\n{info.value.__cause__}"
    assert f"full_key: {key}" in text, text
    assert value in text, text


# --------------------------------------------------------------------------------------
# Bad values: rejected by validate, naming key and value
# --------------------------------------------------------------------------------------

VALUE_ERRORS = [
    ("demo", ["grid.resolution_m=-0.1"], "grid.resolution_m = -0.1", "> 0"),
    ("demo", ["grid.resolution_m=nan"], "grid.resolution_m = nan", "finite"),
    ("demo", ["scans.n_poses=0"], "scans.n_poses = 0", ">= 1"),
    ("demo", ["scans.r_min_m=9.0"], "scans.r_min_m = 9.0", "max_range_m"),
    ("demo", ["+grid.resolutoin_m=0.1"], "grid.resolutoin_m = 0.1", "unknown key"),
    ("mcl", ["logs=[orebro,intell]"], "logs[1] = 'intell'", "did you mean 'intel'"),
    ("mcl", ["logs=[intel,intel]"], "logs = ['intel', 'intel']", "repeat"),
    ("mcl", ["logs=[]"], "logs = []", "at least one"),
    ("mcl", ["robustness_log=campus"], "robustness_log = 'campus'", "unknown CARMEN log"),
    ("mcl", ["models=[dec,decay]"], "models[1] = 'decay'", "choose from"),
    ("mcl", ["failure_fraction=1.5"], "failure_fraction = 1.5", "[0, 1]"),
    ("mcl", ["grid.resolution_m=0"], "grid.resolution_m = 0.0", "> 0"),
    ("mcl", ["filter.resampler=systemic"], "filter.resampler = 'systemic'", "one of"),
    ("mcl", ["filter.init_std=[1.0,1.0]"], "filter.init_std = [1.0, 1.0]", "3 entries"),
    ("mcl", ["filter.motion_sigma=[0.1,-0.1,0.0]"], "filter.motion_sigma[1] = -0.1", ">= 0"),
    ("mcl", ["filter.runs=0"], "filter.runs = 0", ">= 1"),
    ("mcl", ["endpoint.p_out=1.5"], "endpoint.p_out = 1.5", "'auto' or a number"),
    ("mcl", ["endpoint.p_out=often"], "endpoint.p_out = 'often'", "'auto' or a number"),
    ("mcl", ["refine.every=-1"], "refine.every = -1", ">= 0"),
    ("mcl_remedies", ["variants.dec.model=decay"], "variants.dec.model = 'decay'", "one of"),
    (
        "mcl_remedies",
        ["+variants.x={model:dec,smothing_m:0.1}"],
        "variants.x = {'model': 'dec', 'smothing_m': 0.1}",
        "unknown keys ['smothing_m']",
    ),
    ("mcl_remedies", ["+variants.k={model:dec,kld:{delta:2}}"], "variants.k.kld.delta = 2", "("),
    ("mcl_remedies", ["only=[dec,nope]"], "only[1] = 'nope'", "choose from"),
    ("mcl_remedies", ["diagnose.models=[end@0.1]"], "diagnose.models[0] = 'end@0.1'", "'end'"),
    ("mcl_remedies", ["diagnose.models=[dec@x]"], "diagnose.models[0] = 'dec@x'", "sigma"),
    ("mcl_remedies", ["reference_variant=nope"], "reference_variant = 'nope'", "not in"),
    ("mcl_remedies", ["global_localization.runs=-1"], "global_localization.runs = -1", ">= 0"),
    (
        "mcl_remedies",
        ["+global_localization.variants.end.init=uniform"],
        "global_localization.variants.end.init = 'uniform'",
        "one of",
    ),
    ("pose_likelihood", ["kl.estimator=exact"], "kl.estimator = 'exact'", "one of"),
    ("pose_likelihood", ["logs=[intell]"], "logs[0] = 'intell'", "unknown CARMEN log"),
    ("pose_likelihood", ["eval.beam_stride=0"], "eval.beam_stride = 0", ">= 1"),
    ("posterior_corridor", ["steps=101"], "steps = 101", "n_voxels"),
    ("posterior_corridor", ["n_values=[1,1]"], "n_values = [1, 1]", "repeat"),
    ("posterior_corridor", ["significance_level=1.0"], "significance_level = 1.0", "(0, 1)"),
    ("dct_maps", ["resolutions=[0]"], "resolutions[0] = 0", ">= 1"),
    ("dct_maps", ["figure_log=intell"], "figure_log = 'intell'", "unknown CARMEN log"),
    ("decay_rate_fields", ["rbf.width=0"], "rbf.width = 0.0", "> 0"),
    ("polylines", ["methods=[PLE,PLE++]"], "methods[1] = 'PLE++'", "choose from"),
    ("polylines", ["simulation.n_scans=-1"], "simulation.n_scans = -1", "'auto' or an int"),
    ("polylines", ["logs=[/no/such/file.log]"], "logs[0] = '/no/such/file.log'", "path of a log"),
    ("polylines", ["+scan_indices={intel: [-1]}"], "scan_indices.intel = [-1]", "distinct scan"),
    (
        "polylines",
        ["logs=[intel]", "+scan_indices={csail: [1]}"],
        "scan_indices = ['csail']",
        "not in logs",
    ),
    ("planes", ["+msac.grid.nonsense=[1]"], "msac.grid.nonsense = [1]", "not an argument"),
    ("planes", ["methods=[PPE,RANSAC]"], "methods[1] = 'RANSAC'", "choose from"),
    ("planes", ["ppe.grid.kappa=[16,-1]"], "ppe.grid.kappa[1] = -1", "> 0"),
    ("poles", ["localization.c=4"], "localization.c = 4", "<= localization.w"),
    ("poles", ["sessions.p_remove=1.5"], "sessions.p_remove = 1.5", "[0, 1]"),
    ("poles", ["extractor.extent_m=[30.0,30.0]"], "extractor.extent_m = [30.0, 30.0]", "3"),
    ("slam", ["variants=[decay_rate_joint,orb_slam]"], "variants[1] = 'orb_slam'", "choose from"),
    ("slam", ["front_end.range_cap_m=0"], "front_end.range_cap_m = 0.0", "> 0"),
    ("slam", ["loops.min_separation=5"], "loops.min_separation = 5", "> 10"),
    ("slam", ["max_scans=0"], "max_scans = 0", ">= 1"),
    ("slam", ["azimuth_layout=centred"], "azimuth_layout = 'centred'", "must be one of"),
    ("slam", ["front_end.backend=cuda"], "front_end.backend = 'cuda'", "must be one of"),
    ("slam", ["front_end.grazing_cells=-1"], "front_end.grazing_cells = -1", ">= 0"),
    ("slam", ["front_end.prior_length_m=-0.5"], "front_end.prior_length_m = -0.5", ">= 0"),
    ("slam", ["front_end.prior_hits=-1"], "front_end.prior_hits = -1", ">= 0"),
    ("slam", ["front_end.local_map_scans=-3"], "front_end.local_map_scans = -3", ">= 0"),
    (
        "slam",
        ["loops.min_mean_log_likelihood=inf"],
        "loops.min_mean_log_likelihood = inf",
        "finite",
    ),
    ("slam", ["loops.scene_margin=-1"], "loops.scene_margin = -1", ">= 0"),
    ("slam", ["loops.scene_samples=-1"], "loops.scene_samples = -1", ">= 0"),
    ("slam", ["loops.far_radius_m=-1"], "loops.far_radius_m = -1", ">= 0"),
    ("slam", ["loops.short_separation=2"], "loops.short_separation = 2", "0 (off) or >= 3"),
    (
        "slam",
        ["pose_graph.extra_chain_models=[endpoint,lidar]"],
        "pose_graph.extra_chain_models[1] = 'lidar'",
        "must be one of",
    ),
    (
        "slam",
        ["pose_graph.extra_chain_models=[endpoint,endpoint]"],
        "pose_graph.extra_chain_models = ['endpoint', 'endpoint']",
        "must not repeat",
    ),
    ("slam", ["seeds=[0,1,0]"], "seeds = [0, 1, 0]", "must not repeat"),
    ("slam", ["seeds=[]"], "seeds = []", "must not be empty"),
    ("slam", ["seeds=[0,-2]"], "seeds[1] = -2", ">= 0"),
]


@pytest.mark.parametrize(("name", "overrides", "where", "why"), VALUE_ERRORS)
def test_bad_values_are_rejected_by_validate(name, overrides, where, why):
    cfg = composed(name, overrides)  # the types are fine
    with pytest.raises(ConfigError) as info:
        validate(cfg, name)
    assert isinstance(info.value, ValueError)
    line = next((ln for ln in str(info.value).splitlines() if where in ln), None)
    assert line is not None, str(info.value)
    assert why in line, line


def test_validate_reports_every_problem_at_once():
    cfg = composed("demo", ["grid.resolution_m=-1", "scans.n_beams=0", "chunk_size=0"])
    with pytest.raises(ConfigError) as info:
        validate(cfg, "demo")
    keys = [k for k, _, _ in info.value.problems]
    assert keys == ["scans.n_beams", "grid.resolution_m", "chunk_size"]


def test_validate_names_unknown_experiments():
    with pytest.raises(KeyError, match="no schema for experiment 'nope'"):
        validate(composed("demo"), "nope")


# --------------------------------------------------------------------------------------
# End to end: the scripts fail before any work
# --------------------------------------------------------------------------------------


def _run(script: str, out: Path, *overrides: str) -> tuple[subprocess.CompletedProcess, float]:
    cmd = [sys.executable, str(ROOT / "experiments" / f"{script}.py"), f"hydra.run.dir={out}"]
    t0 = time.perf_counter()
    proc = subprocess.run([*cmd, *overrides], capture_output=True, text=True, timeout=300, cwd=ROOT)
    return proc, time.perf_counter() - t0


def test_mcl_with_an_unknown_log_fails_before_the_first_log(tmp_path):
    # Before the schemas, orebro ran to the end (minutes) and wrote results.json, then
    # fetch('intell') failed.
    proc, seconds = _run("mcl", tmp_path, "logs=[orebro,intell]")
    assert proc.returncode != 0
    assert "logs[1] = 'intell'" in proc.stderr and "did you mean 'intel'" in proc.stderr
    assert not (tmp_path / "results.json").exists()
    assert seconds < 60, seconds  # the imports alone take 4-17 s on a loaded machine


def test_demo_with_a_wrongly_typed_value_fails_naming_it(tmp_path):
    proc, seconds = _run("demo", tmp_path, "grid.resolution_m=abc")
    assert proc.returncode != 0
    assert "full_key: grid.resolution_m" in proc.stderr and "'abc'" in proc.stderr
    assert not (tmp_path / "results.json").exists()
    assert seconds < 60, seconds  # the imports alone take 4-17 s on a loaded machine


# --------------------------------------------------------------------------------------
# mcl.py's docstring example (refine.every = 25 > filter.max_steps = 20)
# --------------------------------------------------------------------------------------


def _docstring_example() -> list[str]:
    import mcl

    m = re.search(r"``python experiments/mcl\.py ([^`]*)``", mcl.__doc__)
    assert m is not None
    return m.group(1).split()


def test_refine_steps():
    import mcl

    for every in range(1, 30):
        for n in range(1, 30):
            got = mcl.refine_steps(every, n).tolist()
            want = [t for t in range(n) if (t + 1) % every == 0] if every <= n else [n - 1]
            assert got == want, (every, n)
    with pytest.raises(ValueError):
        mcl.refine_steps(0, 5)


def test_mcl_docstring_example_composes_and_refines_its_last_step():
    overrides = _docstring_example()
    assert overrides == ["logs=[intel]", "filter.runs=2", "filter.max_steps=20"]
    cfg = composed("mcl", overrides)
    validate(cfg, "mcl")
    import mcl

    assert cfg.refine.every > cfg.filter.max_steps  # the case that crashed
    assert mcl.refine_steps(cfg.refine.every, cfg.filter.max_steps).tolist() == [19]


@pytest.mark.slow
def test_mcl_docstring_example_runs(tmp_path):
    # The example, restricted to the decay-rate model (the one refined) to keep it short:
    # it crashed with "need at least one array to stack".
    proc, _ = _run("mcl", tmp_path, *_docstring_example(), "models=[dec]")
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads((tmp_path / "results.json").read_text())
    r = res["logs"]["intel"]
    assert r["n_steps"] == 20 and r["refine"]["steps"] == [19]
    assert np.isfinite(r["refine"]["refined_pos_err"])
    assert "gradient refinement" in (tmp_path / "results.md").read_text()


def test_planes_extra_scans_take_registered_names_and_paths(tmp_path):
    """``extra_scans`` entries may be registered SynPEB scans or files; others are named."""
    f = tmp_path / "scan.pcd"
    f.write_text("x")
    validate(composed("planes", [f"extra_scans=[synpeb-test-100,{f}]"]), "planes")
    with pytest.raises(ConfigError, match=r"extra_scans\[0\] = 'synpeb-nope'"):
        validate(composed("planes", ["extra_scans=[synpeb-nope]"]), "planes")
