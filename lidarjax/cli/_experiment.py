"""``lidarjax experiment``: run a packaged Hydra experiment in a new Python process.

Where the experiments are: an installed wheel carries ``experiments/`` and ``configs/``
as ``lidarjax/_experiments/experiments`` and ``lidarjax/_experiments/configs`` (so each
script's ``@hydra.main(config_path="../configs")`` resolves beside it); a source checkout
(editable install) uses the repository's top-level folders. The script runs as
``python <script> <overrides>`` from the current folder, so its ``from _common import``
finds the shared module beside it and Hydra writes into ``./outputs/<name>``.
"""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

from ._inputs import CliInputError

__all__ = ["cmd_experiment", "experiment_dirs", "experiments"]


def experiment_dirs() -> tuple[Path, Path] | None:
    """``(experiments, configs)`` folders: the packaged copy, else the source checkout's."""
    pkg = Path(__file__).resolve().parents[1]  # .../lidarjax
    for root in (pkg / "_experiments", pkg.parent):
        exp, cfg = root / "experiments", root / "configs"
        if (exp / "_common.py").is_file() and cfg.is_dir():
            return exp, cfg
    return None


def _summary(path: Path) -> str:
    """The first line of a script's docstring."""
    try:
        doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
    except (OSError, SyntaxError, UnicodeDecodeError):
        return ""
    para = " ".join(doc.strip().split("\n\n")[0].split())
    first = re.split(r"\.\s+(?=[A-Z])", para)[0].rstrip(".")
    return first if len(first) <= 110 else first[:107] + "..."


def experiments() -> dict[str, Path]:
    """Runnable experiments by name (``experiments/<name>.py``, no leading underscore)."""
    dirs = experiment_dirs()
    if dirs is None:
        return {}
    return {p.stem: p for p in sorted(dirs[0].glob("*.py")) if not p.stem.startswith("_")}


def cmd_experiment(args) -> int:
    found = experiments()
    if not found:
        raise CliInputError(
            "NAME", "no packaged experiments found (neither lidarjax/_experiments nor a checkout)"
        )
    if args.list or not args.name:
        if not args.list:
            raise CliInputError("NAME", "give an experiment name (`lidarjax experiment --list`)")
        w = max(map(len, found))
        for name, path in found.items():
            print(f"{name:<{w}}  {_summary(path)}")
        print(f"\n({experiment_dirs()[0]})")
        return 0
    if args.name not in found:
        raise CliInputError(
            "NAME", f"unknown experiment {args.name!r}; choose from {', '.join(found)}"
        )
    env = dict(os.environ)
    env.setdefault("MPLBACKEND", "Agg")
    cmd = [sys.executable, str(found[args.name]), *args.overrides]
    return subprocess.run(cmd, env=env, check=False).returncode
