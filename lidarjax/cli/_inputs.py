"""Input handling shared by the subcommands: the one error type the command line reports
as a usage error, laser logs from registry names, CARMEN files and ROS bags, scan slices,
poses and output folders."""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "AZIMUTH_LAYOUTS",
    "BAG_SUFFIXES",
    "CliInputError",
    "LoadedLog",
    "load_log",
    "load_log_scans",
    "out_dir",
    "parse_floats",
    "parse_scans",
    "require_file",
]

BAG_SUFFIXES = (".bag", ".db3", ".mcap")
"""File suffixes read as ROS bags (a folder is read as a ROS 2 bag)."""

CARMEN_SUFFIXES = (".log", ".gz", ".clf")

AZIMUTH_LAYOUTS = ("spread", "sweep")
"""Values of ``--azimuth-layout``: ``lidarjax.datasets.AZIMUTH_LAYOUTS``, spelled out here
so that building the parser does not import JAX (``lidarjax.datasets`` does)."""
DEFAULT_AZIMUTH_LAYOUT = "spread"
"""The layout of a CARMEN log read without ``--azimuth-layout``: ``load_carmen``'s default."""


class CliInputError(Exception):
    """A bad command-line input (a missing or corrupt file, a malformed value).

    The command line prints ``argument <argument>: <message>`` on one line and exits with
    status 2.

    Attributes:
        argument: the argument's name as the user typed it (``LOG``, ``--scans``, ...).
    """

    def __init__(self, argument: str, message: str):
        super().__init__(f"argument {argument}: {message}")
        self.argument = argument


def require_file(value: str, argument: str, *, folder_ok: bool = False) -> Path:
    """``value`` as an existing path, else :class:`CliInputError` naming ``argument``."""
    path = Path(value).expanduser()
    if not path.exists():
        raise CliInputError(argument, f"no such file: {value}")
    if path.is_dir() and not folder_ok:
        raise CliInputError(argument, f"{value} is a folder, expected a file")
    if not os.access(path, os.R_OK):
        raise CliInputError(argument, f"cannot read {value} (permission denied)")
    return path


def out_dir(value: str, argument: str = "-o/--out") -> Path:
    """Create the output folder ``value`` (and its parents); :class:`CliInputError` if that
    fails (e.g. a file of that name exists)."""
    path = Path(value).expanduser()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise CliInputError(argument, f"{value} exists and is not a folder") from None
    except OSError as e:
        raise CliInputError(argument, f"cannot create {value}: {e.strerror or e}") from None
    return path


def parse_scans(value: str | None, n_scans: int, argument: str = "--scans") -> np.ndarray:
    """Scan indices from ``start:stop[:step]`` (Python slice rules, negative indices count
    from the end, parts may be empty) or a single index; ``None`` means all scans.

    Returns:
        ``[k]`` int indices, ``k >= 1``.
    """
    if value is None:
        idx = np.arange(n_scans)
    else:
        parts = value.split(":")
        try:
            nums = [int(p) if p.strip() else None for p in parts]
        except ValueError:
            raise CliInputError(
                argument, f"expected start:stop[:step] or an index, got {value!r}"
            ) from None
        if len(nums) == 1:
            i = nums[0]
            if i is None or not -n_scans <= i < n_scans:
                raise CliInputError(argument, f"scan {value} is not in 0..{n_scans - 1}")
            idx = np.array([i % n_scans])
        elif len(nums) in (2, 3):
            if len(nums) == 3 and nums[2] == 0:
                raise CliInputError(argument, "the step must not be 0")
            idx = np.arange(n_scans)[slice(*nums)]
        else:
            raise CliInputError(argument, f"expected start:stop[:step] or an index, got {value!r}")
    if idx.size == 0:
        raise CliInputError(argument, f"{value!r} selects no scan of the {n_scans} in the log")
    return idx


def parse_floats(value: str, n: int, argument: str) -> np.ndarray:
    """``n`` comma-separated finite numbers (``"1.0,-2,0.5"``)."""
    try:
        out = np.array([float(v) for v in value.split(",")], float)
    except ValueError:
        out = np.zeros(0)
    if out.shape != (n,) or not np.all(np.isfinite(out)):
        raise CliInputError(argument, f"expected {n} comma-separated numbers, got {value!r}")
    return out


@dataclass(frozen=True)
class LoadedLog:
    """A laser log and where it came from.

    Attributes:
        log: the :class:`~lidarjax.datasets.CarmenLog` (scans, corrected poses, odometry).
        source: what the user named (registry name or path).
        kind: ``"registry"``, ``"carmen"`` or ``"bag"``.
        has_ground_truth: whether ``log.poses`` are ground truth (the corrected poses of a
            CARMEN log, or the ``map`` frame tf poses of a bag) rather than a stand-in.
        note: what was substituted, if anything (printed by the commands).
        azimuth_layout: the ``azimuth_layout`` a CARMEN log was read with (``"spread"`` or
            ``"sweep"``); ``None`` for a bag, whose scans carry their own angles.
    """

    log: object
    source: str
    kind: str
    has_ground_truth: bool
    note: str | None = None
    azimuth_layout: str | None = None


def _registry_name(value: str) -> str | None:
    from ..datasets import REGISTRY

    if value in REGISTRY:
        return value
    for name, entry in REGISTRY.items():  # "carmen/intel" or the relative path itself
        stem = entry.relpath.removesuffix("-corrected.log.gz")
        if value in (entry.relpath, stem):
            return name
    return None


def _format_error(argument: str, exc: Exception) -> CliInputError:
    msg = " ".join(str(exc).split())  # one line
    return CliInputError(argument, msg)


def load_log(
    value: str,
    *,
    topic: str | None = None,
    azimuth_layout: str | None = None,
    argument: str = "LOG",
) -> LoadedLog:
    """Load a laser log: a registry name (``intel``, ``carmen/intel``), a CARMEN
    ``.log``/``.log.gz`` file, or a ROS bag (``.bag``, ``.db3``, ``.mcap`` or a ROS 2 bag
    folder; ``topic`` selects the LaserScan topic).

    ``azimuth_layout`` is :func:`~lidarjax.datasets.load_carmen`'s (``"spread"`` or
    ``"sweep"``; ``None``: its default, ``"spread"``). A bag's scans carry their own angles,
    so giving it for a bag is an error naming ``--azimuth-layout``, like ``topic`` for a
    CARMEN log.
    """
    from ..datasets import (
        DataChecksumError,
        DataNotFoundError,
        DatasetFormatError,
        fetch,
        load_carmen,
    )

    if azimuth_layout is not None and azimuth_layout not in AZIMUTH_LAYOUTS:
        choices = ", ".join(AZIMUTH_LAYOUTS)
        raise CliInputError("--azimuth-layout", f"expected {choices}, got {azimuth_layout!r}")
    # None: load_carmen's own default, passed on explicitly and recorded as used
    layout = DEFAULT_AZIMUTH_LAYOUT if azimuth_layout is None else azimuth_layout
    name = _registry_name(value)
    path = Path(value).expanduser()
    if name is not None and not path.exists():
        from ..datasets import REGISTRY

        if REGISTRY[name].metadata.get("format") != "carmen":
            raise CliInputError(argument, f"{value!r} is a registered file but not a laser log")
        try:
            log = load_carmen(fetch(name), azimuth_layout=layout)
        except (DataNotFoundError, DataChecksumError, DatasetFormatError) as e:
            raise _format_error(argument, e) from None
        return LoadedLog(log, value, "registry", True, azimuth_layout=layout)
    if not path.exists():
        raise CliInputError(
            argument,
            f"{value!r} is neither a file nor a registered log (see `lidarjax datasets`)",
        )
    require_file(value, argument, folder_ok=True)
    is_bag = path.is_dir() or path.suffix.lower() in BAG_SUFFIXES
    if topic is not None and not is_bag:
        raise CliInputError("--topic", "only ROS bags have topics; LOG is a CARMEN log")
    if azimuth_layout is not None and is_bag:
        raise CliInputError(
            "--azimuth-layout",
            "only CARMEN logs have an azimuth layout; LOG is a ROS bag, whose scans carry "
            "their own angle_min and angle_increment",
        )
    if is_bag:
        try:
            from ..datasets import read_bag_laser_scans
        except ImportError:  # pragma: no cover - the bag reader is part of the package
            raise CliInputError(argument, "this lidarjax has no ROS bag reader") from None
        try:
            log = read_bag_laser_scans(path, topic=topic)
        except DatasetFormatError as e:
            named = topic is not None and f"topic {topic!r}" in str(e)
            raise _format_error("--topic" if named else argument, e) from None
        except ValueError as e:  # several LaserScan / Odometry topics
            raise _format_error("--topic" if "topic" in str(e) else argument, e) from None
        except (OSError, KeyError) as e:
            raise _format_error(argument, e) from None
        poses, odo = np.asarray(log.poses), np.asarray(log.odometry)
        if np.all(np.isfinite(poses)):
            return LoadedLog(log, value, "bag", True)
        if np.isnan(poses).all() and np.all(np.isfinite(odo)):  # no map frame: odometry
            log = dataclasses.replace(log, poses=odo)
            note = "the bag has no map -> laser tf; using its odometry poses (no ground truth)"
            return LoadedLog(log, value, "bag", False, note)
        return LoadedLog(log, value, "bag", False, "some scans have no map -> laser tf pose")
    try:
        log = load_carmen(path, azimuth_layout=layout)
    except (DatasetFormatError, OSError, EOFError, ValueError) as e:
        raise _format_error(argument, e) from None
    return LoadedLog(log, value, "carmen", True, azimuth_layout=layout)


def load_log_scans(args) -> tuple[LoadedLog, np.ndarray]:
    """:func:`load_log` of a command's ``LOG``, ``--topic`` and ``--azimuth-layout``, its
    note printed, and the scan indices of its ``--scans``."""
    loaded = load_log(args.log, topic=args.topic, azimuth_layout=args.azimuth_layout)
    if loaded.note:
        print(f"note: {loaded.note}")
    return loaded, parse_scans(args.scans, loaded.log.n_scans)
