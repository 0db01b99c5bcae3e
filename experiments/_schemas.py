"""Structured configs (schemas) of the Hydra experiments and their up-front validation.

Every experiment's YAML file (``configs/<name>.yaml``) starts its defaults list with
``<name>_schema``, a dataclass from this module registered in Hydra's ``ConfigStore`` by
:func:`register` (run when this module is imported; the experiments import it). Hydra
composes the YAML onto that dataclass, so

- a value of the wrong type (``grid.resolution_m=abc``, ``scans.n_beams=3.5``, ``grid=7``)
  and a misspelt key (``grid.resolutoin_m=0.1``) fail during composition, before the
  experiment's ``main`` runs, with Hydra's message naming the key and the value;
- :func:`validate` (the first call in every ``main``) then checks ranges (positive
  resolutions, counts >= 1, probabilities in [0, 1], finite numbers), names (CARMEN logs
  against ``lidarjax.datasets.REGISTRY``, models, methods, variants) and constraints between
  keys, and raises one :class:`ConfigError` (a ``ValueError``) listing every offending key
  with its value, before any log is loaded.

The dataclasses hold no values: every field is ``MISSING`` and the YAML files stay the only
source of the defaults, so composing with a schema gives exactly the values (and types) the
YAML gives. ``Any`` / ``Dict[str, Any]`` fields are used only where a value is free-form in
shape (``"auto"`` or a number; the remedy variants of ``mcl_remedies``; keyword-argument
grids of the plane baselines); :func:`validate` checks those entries in Python.

Length (~1200 lines): every experiment's structured config, one dataclass section per
experiment, next to the shared checks they compose; Hydra registers them all at once
(``register``) and ``validate`` walks any of them.
"""

from __future__ import annotations

import dataclasses
import difflib
import inspect
import math
import typing
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import MISSING, DictConfig, ListConfig, OmegaConf

__all__ = [
    "ConfigError",
    "MCL_MODELS",
    "SCHEMAS",
    "carmen_logs",
    "register",
    "validate",
]


class ConfigError(ValueError):
    """An experiment config value is out of range, unknown or inconsistent.

    ``problems`` lists ``(key, value, reason)`` triples; the message has one line per
    problem, ``key = value: reason``.
    """

    def __init__(self, experiment: str, problems: list[tuple[str, Any, str]]):
        self.experiment = experiment
        self.problems = problems
        lines = "\n".join(f"  {k} = {v!r}: {why}" for k, v, why in problems)
        super().__init__(f"invalid config for experiment {experiment!r}:\n{lines}")


# --------------------------------------------------------------------------------------
# Checks on single values. A check returns None (fine) or the reason the value is bad.
# --------------------------------------------------------------------------------------

Check = Callable[[Any], str | None]


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _numeric(test: Callable[[float], bool], what: str) -> Check:
    def check(v):
        if not _is_number(v):
            return f"must be a number {what}"
        if not math.isfinite(v):
            return f"must be finite and {what}"
        return None if test(v) else f"must be {what}"

    return check


def gt(lo: float) -> Check:
    return _numeric(lambda v: v > lo, f"> {lo}")


def ge(lo: float) -> Check:
    return _numeric(lambda v: v >= lo, f">= {lo}")


def closed(lo: float, hi: float) -> Check:
    return _numeric(lambda v: lo <= v <= hi, f"in [{lo}, {hi}]")


def half_open(lo: float, hi: float) -> Check:
    """``(lo, hi]``."""
    return _numeric(lambda v: lo < v <= hi, f"in ({lo}, {hi}]")


def open_(lo: float, hi: float) -> Check:
    return _numeric(lambda v: lo < v < hi, f"in ({lo}, {hi})")


finite = _numeric(lambda v: True, "(not nan or inf)")
positive = gt(0)
nonnegative = ge(0)
count = ge(1)
probability = closed(0, 1)


def one_of(*choices) -> Check:
    def check(v):
        return None if v in choices else f"must be one of {list(choices)}"

    return check


def length(n: int) -> Check:
    def check(v):
        return None if len(v) == n else f"must have {n} entries, got {len(v)}"

    return check


def nonempty(v) -> str | None:
    return None if len(v) > 0 else "must not be empty"


def unique(v) -> str | None:
    dup = sorted({str(x) for x in v if list(v).count(x) > 1})
    return None if not dup else f"must not repeat entries (repeated: {dup})"


def increasing(v) -> str | None:
    ok = all(a < b for a, b in zip(list(v), list(v)[1:]))
    return None if ok else "must be strictly increasing"


def _f(*checks: Check, each: Check | Iterable[Check] = ()) -> Any:
    """A ``MISSING`` dataclass field with value checks (``each``: per list entry)."""
    each = (each,) if callable(each) else tuple(each)
    return field(default=MISSING, metadata={"checks": checks, "each": each})


def _node(cls) -> Any:
    return field(default_factory=cls)


# --------------------------------------------------------------------------------------
# Names
# --------------------------------------------------------------------------------------

MCL_MODELS = ("dec", "ref", "end", "fmp_dec", "fmp_ref")
"""Grid models of ``experiments/mcl.py`` (its ``NAMES``)."""

POLYLINE_METHODS = ("VVL", "IEF", "SAM", "PLE", "PLE+")
"""Methods of ``experiments/polylines.py`` (its ``METHODS``)."""

PLANE_METHODS = ("PPE", "MSAC", "PEAC")
"""Methods of ``experiments/planes.py``."""


def carmen_logs() -> list[str]:
    """Registered CARMEN log names (``lidarjax.datasets.REGISTRY``, format ``carmen``)."""
    from lidarjax.datasets import REGISTRY

    return sorted(n for n, e in REGISTRY.items() if e.metadata.get("format") == "carmen")


def _log_problem(name) -> str | None:
    """Why ``name`` cannot be loaded as a CARMEN log, or None."""
    from lidarjax.datasets import REGISTRY, available

    logs = carmen_logs()
    if not isinstance(name, str) or name not in logs:
        close = difflib.get_close_matches(str(name), logs, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        return f"unknown CARMEN log{hint}; registered logs: {', '.join(logs)}"
    if name not in available() and REGISTRY[name].url is None:
        return (
            "registered, but its file is in no data folder (lidarjax.datasets.data_dirs(); "
            "set LIDARJAX_DATA) and it has no download URL"
        )
    return None


def _check_logs_and_figure_log(problems, cfg) -> None:
    """``cfg.logs`` and ``cfg.figure_log`` name registered logs."""
    _check_logs(problems, "logs", cfg.logs)
    why = _log_problem(cfg.figure_log)
    if why:
        problems.append(("figure_log", cfg.figure_log, why))


def _check_logs(problems, key: str, names, *, allow_empty: bool = False) -> None:
    names = list(names)
    if not names and not allow_empty:
        problems.append((key, names, "must name at least one log"))
    if unique(names):
        problems.append((key, names, unique(names)))
    for i, n in enumerate(names):
        why = _log_problem(n)
        if why:
            problems.append((f"{key}[{i}]", n, why))


def log_name(entry: str) -> str:
    """The name of a ``logs`` entry: a registered log's name, or a log file's name without
    its ``.gz`` / ``.log`` / ``.clf`` / ``.txt`` suffixes (``/data/my.log.gz`` -> ``my``)."""
    if not Path(str(entry)).expanduser().is_file():
        return str(entry)
    name = Path(str(entry)).name
    for suffix in (".gz", ".log", ".clf", ".txt"):
        name = name.removesuffix(suffix)
    return name


def _check_log_sources(problems, key: str, entries, *, allow_empty: bool = False) -> None:
    """Like :func:`_check_logs`, but an entry may also be the path of an existing file."""
    names = [e for e in entries if not Path(str(e)).expanduser().is_file()]
    if not list(entries) and not allow_empty:
        problems.append((key, list(entries), "must name at least one log"))
    if unique(list(entries)):
        problems.append((key, list(entries), unique(list(entries))))
    for i, e in enumerate(entries):
        if e in names:
            why = _log_problem(e)
            if why:
                problems.append((f"{key}[{i}]", e, why + " (or give the path of a log file)"))


def _check_names(problems, key: str, names, known, *, allow_empty: bool = False) -> None:
    names = list(names)
    if not names and not allow_empty:
        problems.append((key, names, "must not be empty"))
    if unique(names):
        problems.append((key, names, unique(names)))
    for i, n in enumerate(names):
        if n not in known:
            close = difflib.get_close_matches(str(n), [str(k) for k in known], n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            problems.append((f"{key}[{i}]", n, f"unknown{hint}; choose from {list(known)}"))


def _auto_or(problems, key: str, value, check: Check, what: str) -> None:
    """``value`` is ``"auto"`` or passes ``check``."""
    if value == "auto":
        return
    why = check(value)
    if why:
        problems.append((key, value, f"must be 'auto' or a number {what}"))


# --------------------------------------------------------------------------------------
# Shared nodes
# --------------------------------------------------------------------------------------


@dataclass
class Grid:
    resolution_m: float = _f(positive)
    margin_m: float = _f(nonnegative)


@dataclass
class Endpoint:
    sigma_m: float = _f(positive)
    z_hit: float = _f(probability)
    z_rand: float = _f(probability)
    p_out: Any = MISSING  # "auto" or a probability


@dataclass
class Fit:
    rtol: float = _f(nonnegative)
    atol: float = _f(nonnegative)
    max_steps: int = _f(count)


# --------------------------------------------------------------------------------------
# demo
# --------------------------------------------------------------------------------------


@dataclass
class DemoWorld:
    width_m: float = _f(positive)
    height_m: float = _f(positive)


@dataclass
class DemoScans:
    n_poses: int = _f(count)
    n_beams: int = _f(count)
    fov_deg: float = _f(half_open(0, 360))
    max_range_m: float = _f(positive)
    r_min_m: float = _f(nonnegative)
    noise_sigma_m: float = _f(nonnegative)


@dataclass
class DemoEndpoint:
    sigma_m: float = _f(positive)
    z_hit: float = _f(probability)
    z_rand: float = _f(probability)


@dataclass
class DemoLocalization:
    n_poses: int = _f(ge(2))  # poses of the held-out trajectory (n_poses - 1 filter steps)
    n_beams: int = _f(count)  # beams per scan in the filter (evenly spaced)
    particles: int = _f(count)
    init_offset: list[float] = _f(length(3), each=finite)  # m, m, rad: the wrong start
    init_std: list[float] = _f(length(3), each=nonnegative)  # m, m, rad
    odometry_noise: list[float] = _f(length(3), each=nonnegative)  # m, m, rad per step
    motion_sigma: list[float] = _f(length(3), each=nonnegative)  # m, m, rad per step
    motion_alpha: list[list[float]] = _f(length(3), each=nonnegative)  # [3 3]
    ray_floor: float = _f(finite)  # nats


@dataclass
class DemoDct:
    cell_m: float = _f(positive)  # box edge per coefficient (m)
    n_rays: int = _f(count)
    max_steps: int = _f(count)


@dataclass
class DemoPolylines:
    scan: int = _f(nonnegative)  # index into the held-out scans
    max_vertices: int = _f(ge(2))


@dataclass
class DemoConfig:
    """``configs/demo.yaml``."""

    seed: int = _f(nonnegative)
    world: DemoWorld = _node(DemoWorld)
    scans: DemoScans = _node(DemoScans)
    grid: Grid = _node(Grid)
    endpoint: DemoEndpoint = _node(DemoEndpoint)
    localization: DemoLocalization = _node(DemoLocalization)
    dct: DemoDct = _node(DemoDct)
    polylines: DemoPolylines = _node(DemoPolylines)
    chunk_size: int = _f(count)

    @staticmethod
    def check(cfg, problems) -> None:
        if cfg.scans.r_min_m >= cfg.scans.max_range_m:
            problems.append(("scans.r_min_m", cfg.scans.r_min_m, "must be < scans.max_range_m"))
        if cfg.scans.n_poses == 1:  # 0 is out of range already
            problems.append(("scans.n_poses", 1, "must be >= 2 (a trajectory)"))
        n_beams, loc = cfg.scans.n_beams, cfg.localization
        if n_beams >= 1 and loc.n_beams > n_beams:
            why = f"must be <= scans.n_beams ({n_beams})"
            problems.append(("localization.n_beams", loc.n_beams, why))
        if loc.n_poses >= 2 and cfg.polylines.scan >= loc.n_poses:
            why = f"must be < localization.n_poses ({loc.n_poses})"
            problems.append(("polylines.scan", cfg.polylines.scan, why))


# --------------------------------------------------------------------------------------
# mcl and mcl_remedies
# --------------------------------------------------------------------------------------


@dataclass
class MclFilter:
    particles: int = _f(count)
    runs: int = _f(count)
    max_steps: int = _f(count)  # odd-numbered scans localized per log
    n_beams: int = _f(count)
    init_std: list[float] = _f(length(3), each=nonnegative)  # m, m, rad
    motion_sigma: list[float] = _f(length(3), each=nonnegative)  # m, m, rad per step
    motion_alpha: list[list[float]] = _f(length(3), each=nonnegative)  # [3 3]
    inflation: float = _f(positive)
    resample_fraction: float = _f(probability)
    resampler: str = MISSING
    best_fraction: float = _f(half_open(0, 1))
    chunk_size: int = _f(count)


@dataclass
class MclRefine:
    every: int = _f(nonnegative)  # 0: no refinement
    beam_stride: int = _f(count)
    blur_schedule_m: list[float] = _f(nonempty, each=nonnegative)
    max_steps: int = _f(count)


@dataclass
class MclConfig:
    """``configs/mcl.yaml``."""

    seed: int = _f(nonnegative)
    logs: list[str] = MISSING
    models: list[str] = MISSING
    robustness_log: str | None = MISSING  # null: no campus* run
    failure_fraction: float = _f(probability)
    grid: Grid = _node(Grid)
    r_min_m: float = _f(nonnegative)
    ray_floor: float = _f(finite)  # nats
    endpoint: Endpoint = _node(Endpoint)
    filter: MclFilter = _node(MclFilter)
    refine: MclRefine = _node(MclRefine)

    @staticmethod
    def check(cfg, problems) -> None:
        from lidarjax.localization import RESAMPLERS

        _check_logs(problems, "logs", cfg.logs)
        if cfg.robustness_log is not None:
            why = _log_problem(cfg.robustness_log)
            if why:
                problems.append(("robustness_log", cfg.robustness_log, why))
        _check_names(problems, "models", cfg.models, MCL_MODELS)
        _check_endpoint(problems, cfg)
        alpha = OmegaConf.to_container(cfg.filter.motion_alpha)
        if any(len(row) != 3 for row in alpha):
            problems.append(("filter.motion_alpha", alpha, "must be a 3 x 3 matrix"))
        if cfg.filter.resampler not in RESAMPLERS:
            problems.append(
                ("filter.resampler", cfg.filter.resampler, f"must be one of {sorted(RESAMPLERS)}")
            )


def _check_endpoint(problems, cfg) -> None:
    _auto_or(problems, "endpoint.p_out", cfg.endpoint.p_out, probability, "in [0, 1]")
    if cfg.endpoint.z_hit + cfg.endpoint.z_rand <= 0:
        problems.append(
            ("endpoint.z_hit", cfg.endpoint.z_hit, "z_hit + z_rand must be > 0 (endpoint.z_rand)")
        )


VARIANT_KEYS = frozenset(
    {
        "model",
        "smoothing_m",
        "z_rand",
        "beam_exponent",
        "particles",
        "alpha_slow",
        "alpha_fast",
        "kld",
        "guided",
        "init",
        "coarse_to_fine",
        "runs",
        "lattice",
    }
)
"""Keys a remedy variant of ``mcl_remedies`` may set."""

INITS = (None, "gaussian", "global", "global_scan")
"""Initialisations of a variant (``None``: the Gaussian start of ``mcl``)."""

LATTICE_KEYS = frozenset(
    {"position_step_m", "n_headings", "max_hypotheses", "smoothing_factor", "uniform_fraction"}
)
"""Keys of a variant's ``lattice`` (``experiments/mcl_remedies.py`` ``LATTICE_DEFAULTS``)."""

_VARIANT_SUBKEYS = {
    "kld": {"epsilon": open_(0, 1), "delta": open_(0, 1), "n_min": None},
    "guided": {
        "blur_m": nonnegative,
        "n_nodes": None,
        "step_scale": nonnegative,
        "proposal_inflation": ge(1),
        "n_grad_steps": None,
        "curvature": None,
    },
    "coarse_to_fine": {"sigmas_m": None, "spread_factor": positive},
    "lattice": {
        "position_step_m": positive,
        "n_headings": None,
        "max_hypotheses": None,
        "smoothing_factor": nonnegative,
        "uniform_fraction": probability,
    },
}
_VARIANT_INTS = {"particles", "runs", "n_min", "n_nodes", "n_grad_steps", "n_headings"}
_VARIANT_INTS |= {"max_hypotheses"}
_VARIANT_NUMBERS = {
    "smoothing_m": nonnegative,
    "z_rand": _numeric(lambda v: 0 <= v < 1, "in [0, 1)"),
    "beam_exponent": half_open(0, 1),
    "alpha_slow": probability,
    "alpha_fast": probability,
}


def _int_problem(v) -> str | None:
    ok = isinstance(v, int) and not isinstance(v, bool) and v >= 1
    return None if ok else "must be an int >= 1"


def check_variant(key: str, v, problems: list) -> None:
    """Append the problems of one remedy variant ``v`` (a mapping) found under ``key``."""
    if isinstance(v, (DictConfig, ListConfig)):
        v = OmegaConf.to_container(v, resolve=True)
    if not isinstance(v, dict):
        problems.append((key, v, "must be a mapping such as {model: dec, particles: 3000}"))
        return
    unknown = sorted(set(v) - VARIANT_KEYS)
    if unknown:
        problems.append((key, v, f"unknown keys {unknown}; allowed {sorted(VARIANT_KEYS)}"))
    model = v.get("model")
    if model not in MCL_MODELS:
        problems.append((f"{key}.model", model, f"must be one of {list(MCL_MODELS)}"))
    if v.get("init") not in INITS:
        problems.append((f"{key}.init", v.get("init"), f"must be one of {list(INITS)}"))
    for k in ("particles", "runs"):
        if k in v and _int_problem(v[k]):
            problems.append((f"{key}.{k}", v[k], _int_problem(v[k])))
    for k, check in _VARIANT_NUMBERS.items():
        if k in v and check(v[k]):
            problems.append((f"{key}.{k}", v[k], check(v[k])))
    if model == "end" and _is_number(v.get("smoothing_m")) and v["smoothing_m"] > 0:
        problems.append(
            (f"{key}.smoothing_m", v["smoothing_m"], "applies to the ray-traced models, not 'end'")
        )
    if _is_number(v.get("alpha_fast")) and v["alpha_fast"] > 0:
        slow = v.get("alpha_slow")
        if not _is_number(slow) or not slow < v["alpha_fast"]:
            problems.append(
                (f"{key}.alpha_slow", slow, "augmented MCL needs a number < alpha_fast")
            )
    for sub, allowed in _VARIANT_SUBKEYS.items():
        if sub not in v or v[sub] is None:
            continue
        s = v[sub]
        if s is False or (sub == "kld" and s is True):  # off (kld: true = defaults)
            continue
        if not isinstance(s, dict):
            problems.append((f"{key}.{sub}", s, "must be a mapping"))
            continue
        bad = sorted(set(s) - set(allowed))
        if bad:
            problems.append((f"{key}.{sub}", s, f"unknown keys {bad}; allowed {sorted(allowed)}"))
        for k, x in s.items():
            check = allowed.get(k)
            why = check(x) if check else (_int_problem(x) if k in _VARIANT_INTS else None)
            if k == "curvature" and not isinstance(x, bool):
                why = "must be true or false"
            if why:
                problems.append((f"{key}.{sub}.{k}", x, why))
    c2f = v.get("coarse_to_fine")
    if isinstance(c2f, dict):
        sig = c2f.get("sigmas_m")
        if (
            not isinstance(sig, list)
            or not sig
            or any(nonnegative(x) for x in sig)
            or increasing(sig)
        ):
            problems.append(
                (f"{key}.coarse_to_fine.sigmas_m", sig, "must be increasing widths >= 0 (m)")
            )
        elif model == "end" and max(sig) > 0:
            problems.append(
                (f"{key}.coarse_to_fine.sigmas_m", sig, "smoothing does not apply to 'end'")
            )


@dataclass
class Diagnose:
    enabled: bool = MISSING
    models: list[str] = MISSING  # model or model@sigma_m


@dataclass
class MclRemediesConfig(MclConfig):
    """``configs/mcl_remedies.yaml`` (extends ``configs/mcl.yaml``)."""

    diagnose: Diagnose = _node(Diagnose)
    reference_variant: str = MISSING
    only: list[str] | None = MISSING
    variants: dict[str, Any] = MISSING
    # {runs: int >= 0, variants: {name: variant} | null}, checked in ``check``. A mapping,
    # not a dataclass, so that ``~global_localization.variants`` followed by
    # ``+global_localization.variants={...}`` replaces the variants (a dataclass field
    # cannot be deleted, and assigning a mapping merges into the old one).
    global_localization: dict[str, Any] = MISSING

    @staticmethod
    def check(cfg, problems) -> None:
        MclConfig.check(cfg, problems)
        for i, name in enumerate(cfg.diagnose.models):
            base, at, sigma = str(name).partition("@")
            why = None
            if base not in MCL_MODELS:
                why = f"model must be one of {list(MCL_MODELS)} (optionally model@sigma_m)"
            elif at:
                try:
                    s = float(sigma)
                except ValueError:
                    s = None
                if s is None or not math.isfinite(s) or s < 0:
                    why = "sigma after '@' must be a number >= 0 (m)"
                elif base == "end" and s > 0:
                    why = "smoothing applies to the ray-traced models, not 'end'"
            if why:
                problems.append((f"diagnose.models[{i}]", name, why))
        if not cfg.variants:
            problems.append(("variants", cfg.variants, "must name at least one variant"))
        for name, v in (cfg.variants or {}).items():
            check_variant(f"variants.{name}", v, problems)
        glob = cfg.global_localization
        bad = sorted(set(glob) - {"runs", "variants"})
        if bad:
            problems.append(("global_localization", _plain(glob), f"unknown keys {bad}"))
        runs = glob.get("runs", "???")
        if not isinstance(runs, int) or isinstance(runs, bool) or runs < 0:
            problems.append(("global_localization.runs", runs, "must be an int >= 0"))
        gvars = glob.get("variants")
        if gvars is not None and not isinstance(gvars, DictConfig):
            problems.append(("global_localization.variants", _plain(gvars), "must be a mapping"))
            gvars = None
        for name, v in (gvars or {}).items():
            if isinstance(v, DictConfig):
                v = OmegaConf.to_container(v, resolve=True)
            if isinstance(v, dict):
                v = {"init": "global", **v}
            check_variant(f"global_localization.variants.{name}", v, problems)
        names = list(cfg.variants or {})
        if cfg.reference_variant not in names:
            problems.append(("reference_variant", cfg.reference_variant, f"not in {names}"))
        if cfg.only is not None:
            _check_names(problems, "only", cfg.only, names)


# --------------------------------------------------------------------------------------
# pose_likelihood
# --------------------------------------------------------------------------------------


@dataclass
class PoseLikelihoodMapping:
    scan_stride: int = _f(count)


@dataclass
class PoseLikelihoodEval:
    max_scans: int = _f(count)
    beam_stride: int = _f(count)


@dataclass
class InverseKL:
    n_samples: int = _f(count)
    radius_m: float = _f(positive)
    sigma_m: float = _f(positive)


@dataclass
class KL:
    n_samples: int = _f(count)
    sigma_m: float = _f(positive)
    estimator: str = _f(one_of("paper", "discrete"))


@dataclass
class PoseLikelihoodConfig:
    """``configs/pose_likelihood.yaml``."""

    seed: int = _f(nonnegative)
    logs: list[str] = MISSING
    grid: Grid = _node(Grid)
    mapping: PoseLikelihoodMapping = _node(PoseLikelihoodMapping)
    eval: PoseLikelihoodEval = _node(PoseLikelihoodEval)
    r_min_m: float = _f(nonnegative)
    ll_floor: float = _f(finite)
    endpoint: Endpoint = _node(Endpoint)
    inverse_kl: InverseKL = _node(InverseKL)
    kl: KL = _node(KL)
    chunk_size: int = _f(count)
    accumulate_chunk_size: int = _f(count)

    @staticmethod
    def check(cfg, problems) -> None:
        _check_logs(problems, "logs", cfg.logs)
        _check_endpoint(problems, cfg)


# --------------------------------------------------------------------------------------
# posterior_corridor
# --------------------------------------------------------------------------------------


@dataclass
class DecayRatePrior:
    shape: float = _f(positive)
    rate: float = _f(positive)


@dataclass
class PosteriorCorridorConfig:
    """``configs/posterior_corridor.yaml``."""

    seed: int = _f(nonnegative)
    n_voxels: int = _f(ge(2))
    n_values: list[int] = _f(nonempty, unique, each=count)
    runs: int = _f(ge(2))
    steps: int = _f(count)
    chunk_size: int = _f(count)
    voxel_length_m: float = _f(positive)
    decay_rate_map: DecayRatePrior = _node(DecayRatePrior)
    boundary: str = _f(one_of("bounded", "cyclic"))
    conjugate_fallback: str = _f(one_of("uniform"))
    error_bar: str = _f(one_of("variance", "std", "sem"))
    significance_level: float = _f(open_(0, 1))
    p_value_backend: str = _f(one_of("auto", "scipy", "jax"))

    @staticmethod
    def check(cfg, problems) -> None:
        if cfg.boundary == "bounded" and cfg.steps > cfg.n_voxels:
            problems.append(("steps", cfg.steps, "must be <= n_voxels for a bounded corridor"))


# --------------------------------------------------------------------------------------
# dct_maps and decay_rate_fields
# --------------------------------------------------------------------------------------


@dataclass
class DctBaselines:
    free_step_m: float = _f(positive)
    length_scale_m: float = _f(positive)
    raster_m: float = _f(positive)


@dataclass
class DctMatch:
    n_scans: int = _f(nonnegative)
    margin_m: float = _f(nonnegative)
    offset_m: float = _f(nonnegative)
    offset_deg: float = _f(nonnegative)
    blur_schedule_m: list[float] = _f(nonempty, each=nonnegative)
    success_m: float = _f(positive)
    success_deg: float = _f(positive)


@dataclass
class DctMapsConfig:
    """``configs/dct_maps.yaml``."""

    seed: int = _f(nonnegative)
    x64: bool = MISSING
    logs: list[str] = MISSING
    patch_m: float = _f(positive)
    resolutions: list[int] = _f(nonempty, unique, each=count)
    n_rays_accuracy: int = _f(count)
    n_rays_likelihood: int = _f(count)
    likelihood_tables: bool = MISSING
    ground_truth_resolution_m: float = _f(positive)
    r_min_m: float = _f(nonnegative)
    fit: Fit = _node(Fit)
    baselines: DctBaselines = _node(DctBaselines)
    match: DctMatch = _node(DctMatch)
    figure_log: str = MISSING
    figure_resolution_92: int = _f(count)
    figure_resolution_93: int = _f(count)

    @staticmethod
    def check(cfg, problems) -> None:
        _check_logs_and_figure_log(problems, cfg)


@dataclass
class RbfFit:
    width: float = _f(positive)  # lattice spacings
    nodes_per_sigma: float = _f(positive)
    max_steps: int = _f(count)


@dataclass
class DecayRateFieldsConfig:
    """``configs/decay_rate_fields.yaml``."""

    seed: int = _f(nonnegative)
    x64: bool = MISSING
    logs: list[str] = MISSING
    resolutions: list[int] = _f(nonempty, unique, each=count)
    n_rays: int = _f(count)
    floor_nats: float = _f(finite)
    fit: Fit = _node(Fit)
    rbf: RbfFit = _node(RbfFit)
    figure_log: str = MISSING
    figure_resolution: int = _f(count)

    @staticmethod
    def check(cfg, problems) -> None:
        _check_logs_and_figure_log(problems, cfg)


# --------------------------------------------------------------------------------------
# polylines
# --------------------------------------------------------------------------------------


@dataclass
class PolylineSimulation:
    n_scans: Any = MISSING  # "auto" or an int >= 0
    polygon_sizes: list[int] = _f(nonempty, each=ge(3))
    n_rays: int = _f(count)
    angular_sigma_deg: float = _f(nonnegative)
    radial_sigma_m: float = _f(nonnegative)
    radius_range_m: list[float] = _f(length(2), each=positive)


@dataclass
class NelderMead:
    n_scans: int = _f(nonnegative)
    J: int = _f(count)
    max_evaluations: int = _f(count)


@dataclass
class PolylineExample:
    log: str = MISSING
    scan: Any = MISSING  # "auto" or a scan index
    J: int = _f(count)


@dataclass
class PlePlus:
    rounds: int = _f(count)
    restarts: int = _f(nonnegative)


@dataclass
class PolylinesConfig:
    """``configs/polylines.yaml``."""

    seed: int = _f(nonnegative)
    x64: bool = MISSING
    logs: list[str] = MISSING  # may be empty: simulated scans only; names or file paths
    scans: str = _f(one_of("paper", "random"))
    scans_per_log: int = _f(count)
    scan_indices: dict[str, Any] = MISSING  # log name (file name for a path) -> indices
    J: list[int] = _f(nonempty, unique, each=count)
    l_max_m: float = _f(positive)
    d_rm_m: float = _f(nonnegative)
    methods: list[str] = MISSING
    ple_plus: PlePlus = _node(PlePlus)
    simulation: PolylineSimulation = _node(PolylineSimulation)
    timing_J: list[int] = _f(unique, each=count)
    timing_scans: int = _f(count)
    nelder_mead: NelderMead = _node(NelderMead)
    example: PolylineExample = _node(PolylineExample)
    paper_scans: dict[str, Any] = MISSING  # log name -> the authors' scan indices

    @staticmethod
    def check(cfg, problems) -> None:
        _check_log_sources(problems, "logs", cfg.logs, allow_empty=True)
        for key in ("scan_indices", "paper_scans"):
            for name, idx in (cfg.get(key) or {}).items():
                ok = isinstance(idx, (list, ListConfig)) and all(
                    isinstance(i, int) and not isinstance(i, bool) for i in idx
                )
                if not ok or not list(idx) or any(i < 0 for i in idx) or unique(list(idx)):
                    problems.append(
                        (
                            f"{key}.{name}",
                            list(idx),
                            "must be a non-empty list of distinct scan indices >= 0",
                        )
                    )
        unused = set(cfg.get("scan_indices") or {}) - {log_name(e) for e in cfg.logs}
        if unused:
            problems.append(("scan_indices", sorted(unused), "names logs that are not in logs"))
        _check_names(problems, "methods", cfg.methods, POLYLINE_METHODS)
        n = cfg.simulation.n_scans
        if n != "auto" and (not isinstance(n, int) or isinstance(n, bool) or n < 0):
            problems.append(("simulation.n_scans", n, "must be 'auto' or an int >= 0"))
        lo, hi = cfg.simulation.radius_range_m
        if lo > hi:
            problems.append(("simulation.radius_range_m", [lo, hi], "must be [min, max]"))
        s = cfg.example.scan
        if s != "auto" and (not isinstance(s, int) or isinstance(s, bool) or s < 0):
            problems.append(("example.scan", s, "must be 'auto' or a scan index >= 0"))
        if cfg.logs:
            why = _log_problem(cfg.example.log)
            if why:
                problems.append(("example.log", cfg.example.log, why))


# --------------------------------------------------------------------------------------
# planes
# --------------------------------------------------------------------------------------


@dataclass
class PpeGrid:
    max_distance_m: list[float] = _f(nonempty, each=positive)  # extract_planes' d (m)
    kappa: list[Any] = _f(nonempty, each=positive)  # numbers (ints kept as ints)
    min_points: list[int] = _f(nonempty, each=count)


@dataclass
class PpeDefault:
    max_distance_m: float = _f(positive)  # extract_planes' d (m)
    min_points: int = _f(ge(4))


@dataclass
class Ppe:
    grid: PpeGrid = _node(PpeGrid)
    default: PpeDefault = _node(PpeDefault)  # the "PPE (default rule)" row: max_increment="auto"


PLANE_PARTS = ("table", "noise")
"""Parts of ``experiments/planes.py`` (``parts``)."""

PLANE_SPLIT_SIZES = {"train": 10, "test": 30}
"""Scans in the generated SynPEB-style splits (``lidarjax.sim.synpeb_split``)."""


@dataclass
class NoiseTable:
    split: str = _f(one_of(*PLANE_SPLIT_SIZES))
    n_scans: int = _f(count)
    shape: list[int] = _f(length(2), each=count)
    noise_levels_mm: list[float] = _f(each=nonnegative)  # radial sigma (mm)
    angular_sigma_mdeg: float = _f(nonnegative)
    extra_conditions: list[Any] = MISSING  # [radial mm, angular mdeg] pairs, checked below
    ppe_rows: list[Any] = MISSING  # {name, max_distance_m, min_points, max_increment | kappa}
    baselines: bool = MISSING


def _check_noise_table(problems, nt) -> None:
    """Cross-key checks of ``noise_table`` (pairs, PPE rows, scan counts)."""
    key = "noise_table"
    limit = PLANE_SPLIT_SIZES.get(nt.split)
    if limit is not None and nt.n_scans > limit:
        problems.append(
            (f"{key}.n_scans", nt.n_scans, f"the {nt.split!r} split has only {limit} scans")
        )
    extra = _plain(nt.extra_conditions)
    for i, pair in enumerate(extra):
        if not isinstance(pair, list) or len(pair) != 2 or any(ge(0)(x) for x in pair):
            problems.append(
                (f"{key}.extra_conditions[{i}]", pair, "must be [radial mm, angular mdeg] >= 0")
            )
    if not list(nt.noise_levels_mm) and not extra:
        problems.append(
            (f"{key}.noise_levels_mm", [], "needs a level (or noise_table.extra_conditions)")
        )
    rows = _plain(nt.ppe_rows)
    names = []
    shape = "{name, max_distance_m, min_points, max_increment | kappa}"
    for i, row in enumerate(rows):
        k = f"{key}.ppe_rows[{i}]"
        if not isinstance(row, dict):
            problems.append((k, row, f"must be a mapping {shape}"))
            continue
        names.append(row.get("name"))
        want = {"name", "max_distance_m", "min_points"}
        either = {"max_increment", "kappa"}
        thr = [t for t in ("max_increment", "kappa") if t in row]
        if not want <= set(row) or len(thr) != 1 or set(row) - want - either:
            problems.append((k, row, f"needs exactly the keys {shape}"))
            continue
        if not isinstance(row["name"], str) or not row["name"]:
            problems.append((f"{k}.name", row["name"], "must be a non-empty string"))
        for sub, check in (("max_distance_m", positive), ("min_points", ge(4))):
            why = check(row[sub])
            if why:
                problems.append((f"{k}.{sub}", row[sub], why))
        if "kappa" in row and positive(row["kappa"]):
            problems.append((f"{k}.kappa", row["kappa"], positive(row["kappa"])))
        inc = row.get("max_increment")
        if "max_increment" in row and inc != "auto" and nonnegative(inc):
            problems.append((f"{k}.max_increment", inc, "must be 'auto' or a number >= 0 (m²)"))
    if unique(names):
        problems.append((f"{key}.ppe_rows", names, "names " + unique(names)))


@dataclass
class Baseline:
    grid: dict[str, Any] = MISSING  # keyword -> list of values (msac_planes / peac_planes)
    fixed: dict[str, Any] = MISSING  # keyword -> value


@dataclass
class PlanesConfig:
    """``configs/planes.yaml``."""

    x64: bool = MISSING
    workers: int = _f(count)
    parts: list[str] = MISSING
    extra_scans: list[str] = MISSING  # PCD files or registered names; checked before any work
    synpeb_min_plane_label: int = _f(count)
    shape: list[int] = _f(length(2), each=count)
    n_train: int = _f(nonnegative)
    n_test: int = _f(count)
    methods: list[str] = MISSING
    tuned: dict[str, Any] | None = MISSING
    ppe: Ppe = _node(Ppe)
    noise_table: NoiseTable = _node(NoiseTable)
    msac: Baseline = _node(Baseline)
    peac: Baseline = _node(Baseline)

    @staticmethod
    def check(cfg, problems) -> None:
        from pathlib import Path

        from lidarjax.features import msac_planes, peac_planes

        _check_names(problems, "parts", cfg.parts, PLANE_PARTS)
        from lidarjax.datasets import REGISTRY

        for i, path in enumerate(cfg.extra_scans):
            if path not in REGISTRY and not Path(str(path)).expanduser().is_file():
                problems.append(
                    (f"extra_scans[{i}]", path, "no such file or registered scan (SynPEB PCD)")
                )
        _check_noise_table(problems, cfg.noise_table)
        _check_names(problems, "methods", cfg.methods, PLANE_METHODS)
        for name, fn in (("msac", msac_planes), ("peac", peac_planes)):
            kw = [p for p in inspect.signature(fn).parameters if p != "points"]
            node = cfg[name]
            grid = OmegaConf.to_container(node.grid, resolve=True)
            fixed = OmegaConf.to_container(node.fixed, resolve=True)
            for part, d in (("grid", grid), ("fixed", fixed)):
                for k in d:
                    if k not in kw:
                        problems.append(
                            (f"{name}.{part}.{k}", d[k], f"not an argument of {fn.__name__}: {kw}")
                        )
            for k, vals in grid.items():
                if not isinstance(vals, list) or not vals:
                    problems.append((f"{name}.grid.{k}", vals, "must be a non-empty list"))
            for k in sorted(set(grid) & set(fixed)):
                problems.append(
                    (f"{name}.fixed.{k}", fixed[k], f"also in {name}.grid (it would overwrite it)")
                )
        tuned = OmegaConf.to_container(cfg.tuned, resolve=True) if cfg.tuned else {}
        allowed = {  # PPE: extract_planes' keywords (kappa: max_increment = kappa sigma_hat²)
            "PPE": {"max_distance_m", "kappa", "min_points"},
            "PPE_abs": {"max_distance_m", "max_increment", "min_points"},
            "MSAC": None,
            "PEAC": None,
        }
        for m, p in tuned.items():
            if m not in allowed:
                problems.append((f"tuned.{m}", p, f"unknown method; choose from {list(allowed)}"))
            elif not isinstance(p, dict):
                problems.append((f"tuned.{m}", p, "must be a mapping of parameters"))
            elif allowed[m] is not None and set(p) != allowed[m]:
                problems.append((f"tuned.{m}", p, f"needs exactly the keys {sorted(allowed[m])}"))
        if "table" in cfg.parts and cfg.n_train < 1 and any(m not in tuned for m in cfg.methods):
            problems.append(("n_train", cfg.n_train, "the grid search needs >= 1 training scan"))


# --------------------------------------------------------------------------------------
# poles
# --------------------------------------------------------------------------------------


@dataclass
class PoleRoute:
    start: int = _f(nonnegative)
    stop: int | None = _f(positive)  # null: the whole route


@dataclass
class PoleLidar:
    n_azimuths: int = _f(count)
    max_range_m: float = _f(positive)
    range_noise_m: float = _f(nonnegative)


@dataclass
class PoleSessions:
    n: int = _f(count)
    barrel_session: int | None = _f(nonnegative)  # null: never
    barrel_shift_m: float = _f(finite)
    p_remove: float = _f(probability)
    p_add: float = _f(probability)


@dataclass
class PoleOdometry:
    sigma_trans_rel: float = _f(nonnegative)
    sigma_rot_deg_per_m: float = _f(nonnegative)
    heading_bias_deg_per_m: float = _f(finite)


@dataclass
class PoleExtractor:
    resolution_m: float = _f(positive)
    extent_m: list[float] = _f(length(3), each=positive)
    mu_o: float = _f(probability)
    q_min: float = _f(probability)
    h_min_m: float = _f(positive)
    free_m: float = _f(positive)
    max_width_m: float = _f(positive)  # candidate widths: 1 cell .. max_width_m
    widths: list[int] | None = _f(nonempty, unique, each=count)  # null: from max_width_m


@dataclass
class PoleMapping:
    segment_m: float = _f(positive)
    max_scans: int = _f(count)
    c: int = _f(count)
    w: int = _f(count)


@dataclass
class PoleLocalization:
    n_particles: int = _f(count)
    runs: int = _f(count)
    radius_m: float = _f(nonnegative)
    heading_deg: float = _f(nonnegative)
    inflation: float = _f(positive)
    var_m2: float = _f(positive)
    eps: float = _f(positive)
    max_online_poles: int = _f(count)
    c: int = _f(count)
    w: int = _f(count)
    diverged_m: float = _f(positive)


@dataclass
class KittiProtocol:
    enabled: bool = MISSING
    start: int = _f(nonnegative)
    n_scans: int = _f(ge(2))
    resolutions_m: list[float] = _f(nonempty, unique, each=positive)
    lidar: str = _f(one_of("hdl64e", "hdl32e"))
    odometry: str = _f(one_of("relative", "wheel"))
    rel_sigma: float = _f(nonnegative)
    inflation: float = _f(positive)
    n_particles: int = _f(count)
    runs: int = _f(count)
    radius_m: float = _f(nonnegative)
    heading_deg: float = _f(nonnegative)


@dataclass
class PolesConfig:
    """``configs/poles.yaml``."""

    seed: int = _f(nonnegative)
    route: PoleRoute = _node(PoleRoute)
    lidar: PoleLidar = _node(PoleLidar)
    sessions: PoleSessions = _node(PoleSessions)
    odometry: PoleOdometry = _node(PoleOdometry)
    extractor: PoleExtractor = _node(PoleExtractor)
    mapping: PoleMapping = _node(PoleMapping)
    localization: PoleLocalization = _node(PoleLocalization)
    kitti_protocol: KittiProtocol = _node(KittiProtocol)
    figure_session: int = _f(nonnegative)
    only: str | None = _f(one_of("table_12_1", "kitti_protocol"))  # null: both parts

    @staticmethod
    def check(cfg, problems) -> None:
        if cfg.only == "kitti_protocol" and not cfg.kitti_protocol.enabled:
            problems.append(("only", cfg.only, "needs kitti_protocol.enabled = true"))
        r = cfg.route
        if r.stop is not None and r.stop - r.start < 10:
            problems.append(("route.stop", r.stop, f"must be >= route.start + 10 ({r.start + 10})"))
        for key in ("mapping", "localization"):
            if cfg[key].c > cfg[key].w:
                problems.append((f"{key}.c", cfg[key].c, f"must be <= {key}.w ({cfg[key].w})"))


# --------------------------------------------------------------------------------------
# slam
# --------------------------------------------------------------------------------------

SLAM_VARIANTS = (
    "decay_rate_joint",
    "decay_rate_alternating",
    "decay_rate_pose_graph",
    "endpoint",
    "icp_gtsam",
    "odometry",
    "reference_back_end",
)


@dataclass
class SlamOdometry:
    sigma_trans_rel: float = _f(nonnegative)
    sigma_rot_per_m_deg: float = _f(nonnegative)
    heading_bias_per_m_deg: float = _f(finite)
    sigma_rot_per_rad: float = _f(nonnegative)


@dataclass
class SlamFrontEnd:
    resolution_m: float = _f(positive)
    range_cap_m: float | None = _f(positive)  # null: each log's own (slam.auto_range_cap)
    blur_schedule_m: list[float] = _f(nonempty, each=nonnegative)
    backend: str = _f(one_of("auto", "native", "jax"))
    grazing_cells: float = _f(nonnegative)
    prior_hits: float = _f(nonnegative)
    prior_length_m: float = _f(nonnegative)
    local_map_scans: int = _f(nonnegative)
    dtype: str | None = _f(one_of("float32", "float64"))  # null: JAX's default


@dataclass
class SlamLoops:
    radius_m: float = _f(positive)
    min_separation: int = _f(count)
    every: int = _f(count)
    wide_search_xy_m: float = _f(nonnegative)
    far_radius_m: float = _f(nonnegative)  # 0: no far candidates
    rounds: int = _f(count)
    # 0: off; else the short loop search's separation (slam.SlamConfig.short_loop_separation)
    short_separation: int = _f(_numeric(lambda v: v == 0 or v >= 3, "0 (off) or >= 3"))
    min_mean_log_likelihood: float | None = _f(finite)  # null: the model's default
    scene_margin: float | None = _f(nonnegative)  # null: the model's default
    scene_samples: int = _f(nonnegative)  # 0: the threshold is never lowered


@dataclass
class SlamPoseGraph:
    robust_chain: bool = _f()
    revisits: bool | None = _f()  # null: only with front_end.local_map_scans 0
    calibrate_odometry: bool = _f()
    # null: the other matching model's front end as a further chain; []: one chain
    extra_chain_models: list[str] | None = _f(
        unique, each=one_of("decay_rate", "endpoint", "icp", "gicp")
    )


@dataclass
class SlamBackEnd:
    range_cap_m: float = _f(positive)
    max_steps: int = _f(count)
    rounds: int = _f(count)


@dataclass
class SlamResimulate:
    enabled: bool = _f()
    cell_m: float = _f(positive)
    link_m: float = _f(positive)
    noise_sigma_m: float = _f(nonnegative)
    footprint_m: float = _f(nonnegative)


@dataclass
class SlamExperimentConfig:
    """``configs/slam.yaml``."""

    seed: int = _f(nonnegative)
    seeds: list[int] | None = _f(nonempty, unique, each=nonnegative)  # null: [seed]
    logs: list[str] = MISSING
    max_scans: int | None = _f(count)
    azimuth_layout: str = _f(one_of("spread", "sweep"))
    odometry: SlamOdometry = _node(SlamOdometry)
    front_end: SlamFrontEnd = _node(SlamFrontEnd)
    loops: SlamLoops = _node(SlamLoops)
    pose_graph: SlamPoseGraph = _node(SlamPoseGraph)
    back_end: SlamBackEnd = _node(SlamBackEnd)
    resimulate: SlamResimulate = _node(SlamResimulate)
    variants: list[str] = _f(nonempty, unique)
    rpe_delta_m: float = _f(positive)
    map_resolution_m: float = _f(positive)
    figure_log: str = MISSING

    @staticmethod
    def check(cfg, problems) -> None:
        _check_logs_and_figure_log(problems, cfg)
        _check_names(problems, "variants", list(cfg.variants), SLAM_VARIANTS)
        if cfg.loops.min_separation <= 10:
            problems.append(
                (
                    "loops.min_separation",
                    cfg.loops.min_separation,
                    "must be > 10 (2 * the submap half width)",
                )
            )


# --------------------------------------------------------------------------------------
# Registry and validation
# --------------------------------------------------------------------------------------

SCHEMAS: dict[str, type] = {
    "demo": DemoConfig,
    "mcl": MclConfig,
    "mcl_remedies": MclRemediesConfig,
    "pose_likelihood": PoseLikelihoodConfig,
    "posterior_corridor": PosteriorCorridorConfig,
    "dct_maps": DctMapsConfig,
    "decay_rate_fields": DecayRateFieldsConfig,
    "polylines": PolylinesConfig,
    "planes": PlanesConfig,
    "poles": PolesConfig,
    "slam": SlamExperimentConfig,
}
"""Experiment (config) name -> schema dataclass, stored as ``<name>_schema``."""


def register() -> None:
    """Store every schema in Hydra's ``ConfigStore`` as ``<name>_schema``."""
    from hydra.core.config_store import ConfigStore

    cs = ConfigStore.instance()
    for name, node in SCHEMAS.items():
        cs.store(name=f"{name}_schema", node=node)


def _plain(value):
    if isinstance(value, (DictConfig, ListConfig)):
        return OmegaConf.to_container(value, resolve=True)
    return value


def _leaves(value, key: str):
    """``(key[i]..., leaf)`` for the non-list entries of a (nested) list."""
    if isinstance(value, list):
        for i, x in enumerate(value):
            yield from _leaves(x, f"{key}[{i}]")
    else:
        yield key, value


def _walk(cls, node, prefix: str, problems: list) -> None:
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    for k in node.keys():
        if k not in names:
            problems.append((prefix + str(k), _plain(node[k]), f"unknown key; expected {names}"))
    for f in dataclasses.fields(cls):
        key = prefix + f.name
        if f.name not in node or OmegaConf.is_missing(node, f.name):
            problems.append((key, "???", "has no value"))
            continue
        value = node[f.name]
        if dataclasses.is_dataclass(hints[f.name]):
            _walk(hints[f.name], value, key + ".", problems)
            continue
        value = _plain(value)
        if value is None:
            continue
        for check in f.metadata.get("checks", ()):
            why = check(value)
            if why:
                problems.append((key, value, why))
        for check in f.metadata.get("each", ()):
            for k, leaf in _leaves(value, key):
                why = check(leaf)
                if why:
                    problems.append((k, leaf, why))


def validate(cfg: DictConfig, name: str) -> None:
    """Check an experiment's composed config before any work.

    Args:
        cfg: The config Hydra composed from ``configs/<name>.yaml`` (types are already
            enforced by the schema during composition).
        name: The experiment (config) name, a key of :data:`SCHEMAS`.

    Raises:
        ConfigError: (a ``ValueError``) listing every key whose value is missing, out of
            range (e.g. ``grid.resolution_m = -0.1: must be > 0``), unknown (a log name that
            is not a registered CARMEN log, a model or method name, a misspelt key added with
            ``+``) or inconsistent with another key.
        KeyError: ``name`` is not an experiment with a schema.
    """
    if name not in SCHEMAS:
        raise KeyError(f"no schema for experiment {name!r}; known: {sorted(SCHEMAS)}")
    cls = SCHEMAS[name]
    problems: list[tuple[str, Any, str]] = []
    _walk(cls, cfg, "", problems)
    if not any(v == "???" for _, v, _ in problems):  # cross-key checks need every value
        cls.check(cfg, problems)
    if problems:
        raise ConfigError(name, problems)


register()
