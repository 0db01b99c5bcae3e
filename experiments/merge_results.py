"""Merge the jobs of a Hydra sweep into one table: one row per job, its overrides as
columns, then the experiment's headline numbers from its ``results.json``.

A sweep (``python experiments/<name>.py -m ...``) writes each job into
``<sweep dir>/<override string>/`` (``hydra.sweep`` in ``configs/<name>.yaml``) with the
job's overrides in ``.hydra/overrides.yaml``. This script reads every job folder below
``SWEEP_DIR`` and the sweep's ``multirun.yaml`` (the jobs the basic sweeper expands the
overrides into), and writes ``merged.md``, ``merged.json`` and ``merged.csv`` into
``SWEEP_DIR`` (or ``--out``). A job without a complete ``results.json`` -- not started,
interrupted, or failed -- is a row with status ``missing``, never dropped.

E.g. ``python experiments/merge_results.py outputs/sweeps/polylines``, or from Python::

    from merge_results import merge
    table = merge("outputs/sweeps/polylines")  # {"experiment", "columns", "rows"}
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from collections.abc import Callable
from pathlib import Path

from _common import INCOMPLETE, is_complete
from omegaconf import OmegaConf

__all__ = ["HEADLINES", "collect", "headline", "main", "merge"]


# ----------------------------------------------------------------------------- headlines
def _posterior_corridor(r: dict) -> dict:
    """Mean belief at the true voxel per n, model and method (Figure 8.2)."""
    return {
        f"rho n={row['n']} {model}/{method}": v["mean"]
        for row in r.get("rows", [])
        for model, per in row["rho"].items()
        for method, v in per.items()
    }


def _polylines(r: dict) -> dict:
    """Mean ray RMSE (mm) and explained fraction f per data kind, J and method."""
    out = {}
    for kind, per_j in r.get("accuracy", {}).items():
        for J, per_m in per_j.items():
            for m, s in per_m.items():
                mean = s["rmse_m"]["mean"]
                out[f"{kind} J={J} {m} rmse_mm"] = None if mean is None else 1e3 * mean
                out[f"{kind} J={J} {m} f"] = s["f"]["mean"]
    return out


def _mcl(r: dict) -> dict:
    """Mean position error over logs per grid model (Table 7.2)."""
    return {f"pos_err_m {m}": v for m, v in r.get("mean_over_logs_pos_err_m", {}).items()}


def _dct_maps(r: dict) -> dict:
    """Table 9.2: mean p_ref RMSE of the DCT and the grid map per resolution L."""
    out = {}
    for L, t in r.get("summary", {}).get("table92", {}).items():
        out[f"L={L} rmse_dct"] = t["mu_dct"]
        out[f"L={L} rmse_grid"] = t["mu_gm"]
    return out


HEADLINES: dict[str, Callable[[dict], dict]] = {
    "posterior_corridor": _posterior_corridor,
    "polylines": _polylines,
    "mcl": _mcl,
    "dct_maps": _dct_maps,
}
"""Per experiment (Hydra job name): ``results.json`` -> ``{column: number}``."""

_SKIP = {"config", "cpu_count", "load_average_1min", "seed"}
_MAX_GENERIC = 24


def _number(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def headline(experiment: str, results: dict) -> dict:
    """The headline numbers of one job: :data:`HEADLINES` of the experiment, else the
    numbers at the top two levels of ``results.json`` (``config`` and provenance left out,
    at most 24), plus the run time (``runtime_s`` or ``total_s``) when recorded."""
    if experiment in HEADLINES:
        out = HEADLINES[experiment](results)
    else:
        out = {}
        for k, v in results.items():
            if k in _SKIP or k in ("runtime_s", "total_s"):
                continue
            if _number(v):
                out[k] = v
            elif isinstance(v, dict):
                out.update({f"{k} {k2}": v2 for k2, v2 in v.items() if _number(v2)})
        out = dict(list(out.items())[:_MAX_GENERIC])
    for k in ("runtime_s", "total_s"):
        if _number(results.get(k)):
            out[k] = results[k]
    return out


# ----------------------------------------------------------------------------- jobs
def _key_value(override: str) -> tuple[str, str | None]:
    """``"+a.b=[1,2]"`` -> ``("a.b", "[1,2]")``; a deletion ``~a`` -> ``("a", None)``."""
    text = override.lstrip("+~")
    if "=" not in text:
        return text, None
    key, value = text.split("=", 1)
    return key, value


def _expected(sweep_dir: Path) -> list[list[str]]:
    """The override lists of the jobs the sweep's ``multirun.yaml`` asks for (basic
    sweeper only; ``[]`` when there is no such file or another sweeper ran)."""
    f = sweep_dir / "multirun.yaml"
    if not f.is_file():
        return []
    cfg = OmegaConf.load(f)
    sweeper = str(OmegaConf.select(cfg, "hydra.sweeper._target_", default=""))
    if not sweeper.endswith("BasicSweeper"):
        return []
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    task = list(OmegaConf.select(cfg, "hydra.overrides.task", default=[]) or [])
    parsed = OverridesParser.create().parse_overrides(task)
    return [job for batch in BasicSweeper.split_arguments(parsed, None) for job in batch]


def _experiment_name(job_dir: Path, sweep_dir: Path) -> str:
    for f in (job_dir / ".hydra" / "hydra.yaml", sweep_dir / "multirun.yaml"):
        if f.is_file():
            name = OmegaConf.select(OmegaConf.load(f), "hydra.job.name", default=None)
            if name:
                return str(name)
    return "?"


def _sort_key(value) -> tuple:
    """Numbers in numeric order before other values, those in text order."""
    try:
        return (0, float(value), "")
    except (TypeError, ValueError):
        return (1, 0.0, str(value))


def collect(sweep_dir: str | Path) -> dict:
    """Every job of the sweep in ``sweep_dir``: its folder, overrides, status and headline
    numbers.

    Returns:
        ``{"experiment": name, "sweep_dir": path, "columns": [...], "rows": [...]}``; each
        row has ``job`` (folder relative to ``sweep_dir``, ``None`` when never started),
        ``status`` (``done`` or ``missing``), ``note`` (why missing), one entry per
        override key and one per headline number (``None`` where a job has none).

    Raises:
        FileNotFoundError: ``sweep_dir`` is not a folder.
    """
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        raise FileNotFoundError(f"sweep_dir: no such folder {str(sweep_dir)!r}")
    found = {}
    for f in sorted(sweep_dir.rglob(".hydra/overrides.yaml")):
        job_dir = f.parent.parent
        overrides = [str(o) for o in OmegaConf.to_container(OmegaConf.load(f)) or []]
        found[tuple(sorted(overrides))] = (job_dir, overrides)
    jobs = dict(found)
    for overrides in _expected(sweep_dir):
        jobs.setdefault(tuple(sorted(overrides)), (None, overrides))
    experiment = "?"
    rows, override_cols, number_cols = [], [], []
    for job_dir, overrides in jobs.values():
        if job_dir is not None and experiment == "?":
            experiment = _experiment_name(job_dir, sweep_dir)
        row = {"job": None if job_dir is None else str(job_dir.relative_to(sweep_dir))}
        kv = dict(_key_value(o) for o in overrides)
        for k in kv:
            if k not in override_cols:
                override_cols.append(k)
        numbers = {}
        if job_dir is None:
            row["status"], row["note"] = "missing", "not started"
        elif is_complete(job_dir):
            row["status"], row["note"] = "done", ""
            numbers = headline(experiment, json.loads((job_dir / "results.json").read_text()))
        else:
            interrupted = (job_dir / INCOMPLETE).exists()
            row["status"] = "missing"
            row["note"] = "interrupted or failed" if interrupted else "no results.json"
        for k in numbers:
            if k not in number_cols:
                number_cols.append(k)
        rows.append((row, kv, numbers))
    table = []
    for row, kv, numbers in rows:
        row.update({k: kv.get(k) for k in override_cols})
        row.update({k: numbers.get(k) for k in number_cols})
        table.append(row)
    table.sort(key=lambda r: [_sort_key(r.get(k)) for k in override_cols])
    timing = [k for k in ("runtime_s", "total_s") if k in number_cols]
    number_cols = [k for k in number_cols if k not in timing] + timing  # run time last
    columns = ["job", "status", "note", *override_cols, *number_cols]
    return {
        "experiment": experiment,
        "sweep_dir": str(sweep_dir),
        "columns": columns,
        "override_columns": override_cols,
        "number_columns": number_cols,
        "rows": table,
    }


# ----------------------------------------------------------------------------- output
def _cell(v) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return "–" if not math.isfinite(v) else f"{v:.4g}"
    return str(v)


def _markdown(t: dict) -> str:
    cols = [c for c in t["columns"] if c != "job"]
    done = sum(r["status"] == "done" for r in t["rows"])
    lines = [
        f"### Sweep of {t['experiment']}: {done} of {len(t['rows'])} jobs done",
        "",
        f"Sweep folder `{t['sweep_dir']}`; overrides first, then the headline numbers.",
        "",
        "| " + " | ".join(c.replace("|", "/") for c in cols) + " |",
        "|---" * len(cols) + "|",
    ]
    for r in t["rows"]:
        lines.append("| " + " | ".join(_cell(r[c]).replace("|", "/") for c in cols) + " |")
    return "\n".join(lines) + "\n"


def merge(sweep_dir: str | Path, out: str | Path | None = None) -> dict:
    """:func:`collect` the sweep and write ``merged.md``, ``merged.json`` and ``merged.csv``
    into ``out`` (default: ``sweep_dir``). Returns the table (see :func:`collect`)."""
    t = collect(sweep_dir)
    out = Path(sweep_dir if out is None else out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "merged.json").write_text(json.dumps(t, indent=2))
    (out / "merged.md").write_text(_markdown(t))
    with open(out / "merged.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=t["columns"])
        w.writeheader()
        w.writerows({k: "" if v is None else v for k, v in r.items()} for r in t["rows"])
    return t


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("sweep_dir", help="the sweep folder (hydra.sweep.dir)")
    p.add_argument("--out", default=None, help="where to write merged.* (default: sweep_dir)")
    a = p.parse_args(argv)
    t = merge(a.sweep_dir, a.out)
    print(_markdown(t))
    missing = [r for r in t["rows"] if r["status"] != "done"]
    if missing:
        print(f"{len(missing)} job(s) missing: rerun the same sweep to compute only them.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
