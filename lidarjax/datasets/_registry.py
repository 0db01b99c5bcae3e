"""Checksummed registry of the project's real data files.

Every data file the project reads is registered here under a short name with its SHA-256.
:func:`fetch` looks for the file in the folders returned by :func:`data_dirs` (in order),
verifies its checksum and returns its path. Files that are in no folder are downloaded into
the user cache with :mod:`pooch` (and verified) when a download location is known: the
mirror ``$LIDARJAX_DATA_URL/<relpath>`` if that variable is set, then the entry's own
``url``; otherwise :class:`~lidarjax.datasets.DataNotFoundError` explains where the file was
looked for and how to provide it.

Public locations (each checked against the registered SHA-256 by hashing the files in a
clone of the repository, pinned to a commit):

- the 13 SLAM-corrected CARMEN logs (incl. ``aces`` and ``seattle``, not in the shared
  folder): the data folder of the PLE repository (A. Schaefer, ``acschaefer/ple``);
- ``kitti-00-poses`` / ``kitti-00-times``: the KITTI-00 test data of the evo package
  (``MichaelGrupp/evo``, ``test/data/KITTI_00_gt.txt`` and ``KITTI_00_gt_times.txt``);
- ``synpeb-test-100`` (a crop made for this project): no public location, ``url=None``.

Environment variables: ``LIDARJAX_DATA`` (a folder searched first), ``LIDARJAX_DATA_URL``
(a mirror base URL: ``<base>/<relpath>``, e.g. ``file:`` or ``http:`` URLs of a copy of the
shared folder), ``LIDARJAX_CACHE`` (the user cache, default ``pooch.os_cache("lidarjax")``)
and ``LIDARJAX_OFFLINE`` (``1``: never download).

The shared data folder (``../shared/data`` from the project root) holds the eleven CARMEN
logs, a SynPEB crop and the KITTI sequence 00 trajectory; see its ``README.md``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pooch

from ._errors import DataChecksumError, DataNotFoundError

__all__ = ["DataFile", "REGISTRY", "available", "data_dirs", "download_urls", "fetch"]

ENV_VAR = "LIDARJAX_DATA"
"""Environment variable naming a folder searched before all others."""

MIRROR_ENV = "LIDARJAX_DATA_URL"
"""Environment variable holding a mirror base URL; a file is downloaded from
``<base>/<relpath>`` before the entry's own ``url`` is tried."""

CACHE_ENV = "LIDARJAX_CACHE"
"""Environment variable overriding the user cache folder (where downloads go)."""

OFFLINE_ENV = "LIDARJAX_OFFLINE"
"""Environment variable: ``1`` / ``true`` / ``yes`` / ``on`` turn downloads off."""

_PLE_URL = (  # acschaefer/ple at the commit that added its data folder (2018-07-26)
    "https://raw.githubusercontent.com/acschaefer/ple/"
    "8af88b28759f8a48b1bf33083a85f2013907c41d/data/carmen/{name}-corrected.log.gz"
)
_EVO_URL = (  # MichaelGrupp/evo's KITTI-00 test data (blobs unchanged since 2019-01-16)
    "https://raw.githubusercontent.com/MichaelGrupp/evo/"
    "6c1cbf18380c934a6699d8a5c1b6948d1f6220aa/test/data/{file}"
)


@dataclass(frozen=True)
class DataFile:
    """One registered data file.

    Attributes:
        relpath: Path relative to a data folder, POSIX style, e.g.
            ``"carmen/intel-corrected.log.gz"``.
        sha256: Expected SHA-256 of the file contents, 64 lowercase hex digits.
        description: One-line human-readable description.
        url: Download URL, or ``None`` when the file can only be provided locally.
        metadata: Extra facts about the file (e.g. ``n_scans`` and ``n_beams`` for laser
            logs, ``n_poses`` for trajectories). Informational; not checked by :func:`fetch`.
    """

    relpath: str
    sha256: str
    description: str
    url: str | None = None
    metadata: dict[str, Any] = field(default_factory=dict, compare=False, hash=False)


# (short name, sha256, n_scans, n_beams, place)
_CARMEN_LOGS: tuple[tuple[str, str, int, int, str], ...] = (
    (
        "acapulco",
        "fbd19a018534dee751606a9520fd6be25c86f3d7f1f7d849b1834d047b330116",
        861,
        181,
        "Acapulco Convention Center",
    ),
    (
        "aces",
        "5434d44384166250608a64d3a8c32de84512f82c46cb60a2657f138592024569",
        440,
        180,
        "ACES building, University of Texas at Austin",
    ),
    (
        "belgioioso",
        "a130e3e6d9e5ec5e6a7f94cbb5cb6bca2df2626c7ed6bebb7b7a282253b10f6e",
        395,
        361,
        "Belgioioso castle",
    ),
    (
        "csail",
        "a98de24fc319651f231f9a8625b78bf1972312b86f7b00d2ddc979c4ac92ae2d",
        406,
        361,
        "MIT CSAIL building",
    ),
    (
        "edmonton",
        "96599a91e0cc9cb2570dbb92f92bbdf1e3a405b16aa99f6d3ce1a703011befdb",
        340,
        180,
        "Edmonton convention centre",
    ),
    (
        "fhw",
        "4233abbfbc15baaddc730aceb3482dc660b25c9d5757005fff97a3fe083595b8",
        488,
        180,
        "FH Wedel",
    ),
    (
        "freiburg-079",
        "0631d30baf4b9d1d209af47da9096e876e1b4cb3d5a2d68ef9c39c5a2360a466",
        4791,
        360,
        "University of Freiburg, building 079",
    ),
    (
        "freiburg-101",
        "7792de88bcb050f8edba92914aea75e8ec2fb73b483c01903bd2753aa655e982",
        292,
        360,
        "University of Freiburg, building 101",
    ),
    (
        "freiburg-campus",
        "534fae978c3a28fd9994c9b3327a36a2752df8339e232b9b70f96f67f76341b0",
        2008,
        360,
        "University of Freiburg campus (outdoor)",
    ),
    (
        "infinite-corridor",
        "6a63c51eb97aa4e720fe207e91f926c283f77b4c534903983f9c5a6cbed6ebc4",
        1941,
        180,
        "MIT Infinite Corridor",
    ),
    (
        "intel",
        "71bef16e9926506cf7417995ef35ace09dbd5de067fd042a3aab85188b5480dc",
        910,
        180,
        "Intel Research Lab, Seattle",
    ),
    (
        "orebro",
        "39a189c64489b84996669bc484d6bd6864f8733029a280a0e549a0adaae08a82",
        237,
        181,
        "Örebro University",
    ),
    (
        "seattle",
        "5719198036b788d78a877ca04efdbfb07c2518508310f51d49c198bf1956bb4b",
        241,
        361,
        "University of Washington, Seattle",
    ),
)

_SHIPPED_CARMEN = frozenset(
    {
        "acapulco",
        "belgioioso",
        "csail",
        "edmonton",
        "fhw",
        "freiburg-079",
        "freiburg-101",
        "freiburg-campus",
        "infinite-corridor",
        "intel",
        "orebro",
    }
)


def _build_registry() -> dict[str, DataFile]:
    reg: dict[str, DataFile] = {}
    for name, sha, n_scans, n_beams, place in _CARMEN_LOGS:
        reg[name] = DataFile(
            relpath=f"carmen/{name}-corrected.log.gz",
            sha256=sha,
            description=f"SLAM-corrected CARMEN laser log: {place} (Radish)",
            url=_PLE_URL.format(name=name),
            metadata={
                "format": "carmen",
                "n_scans": n_scans,
                "n_beams": n_beams,
                "shipped": name in _SHIPPED_CARMEN,
            },
        )
    reg["synpeb-test-100"] = DataFile(
        relpath="synpeb/test_100.pcd",
        sha256="e820fe82c03c46746c65d02b165f007dfecf3b5b697bf98207e11a9ef4689cfc",
        description="Organized 100 x 100 crop of a SynPEB scan, ASCII PCD, intensity = plane label",
        metadata={"format": "pcd", "width": 100, "height": 100, "n_labels": 13, "shipped": True},
    )
    reg["kitti-00-poses"] = DataFile(
        relpath="trajectories/kitti_00_poses.txt",
        sha256="90791a4113df979b149fa9e1104e960ea59f525a8318a202dbb6aec1a3d88793",
        description="KITTI odometry sequence 00 ground-truth poses (3x4 [R|t] per line)",
        url=_EVO_URL.format(file="KITTI_00_gt.txt"),
        metadata={"format": "kitti-poses", "n_poses": 4541, "shipped": True},
    )
    reg["kitti-00-times"] = DataFile(
        relpath="trajectories/kitti_00_times.txt",
        sha256="99a2899466cdc28dd292b4856d214a8b0aab035b91b02bb6afcb4ff363e7d421",
        description="KITTI odometry sequence 00 timestamps in seconds",
        url=_EVO_URL.format(file="KITTI_00_gt_times.txt"),
        metadata={"format": "kitti-times", "n_poses": 4541, "shipped": True},
    )
    return dict(sorted(reg.items()))


REGISTRY: dict[str, DataFile] = _build_registry()
"""All registered data files by short name."""

# (resolved path, mtime_ns, size) -> sha256 hex digest, so repeated fetches skip rehashing.
_HASH_CACHE: dict[tuple[str, int, int], str] = {}


def _cache_dir() -> Path:
    """The user cache: ``$LIDARJAX_CACHE`` if set and non-empty, else
    ``pooch.os_cache("lidarjax")`` (``$XDG_CACHE_HOME/lidarjax``, default
    ``~/.cache/lidarjax`` on Linux)."""
    env = os.environ.get(CACHE_ENV, "")
    if env:
        return Path(env).expanduser()
    return Path(pooch.os_cache("lidarjax"))


def _offline() -> bool:
    return os.environ.get(OFFLINE_ENV, "").strip().lower() in ("1", "true", "yes", "on")


def data_dirs() -> list[Path]:
    """Folders searched for data files, in search order.

    1. ``$LIDARJAX_DATA`` if the variable is set and non-empty (whether or not it exists).
    2. ``<repo>/../shared/data`` where ``<repo>`` is the folder containing the ``lidarjax``
       package, if it exists.
    3. ``<cwd>/../shared/data`` if it exists and differs from 2.
    4. The user cache ``$LIDARJAX_CACHE``, default ``pooch.os_cache("lidarjax")`` (also
       where downloads go).

    Returns:
        Distinct folders, in the order :func:`fetch` tries them.
    """
    import lidarjax

    dirs: list[Path] = []
    env = os.environ.get(ENV_VAR, "")
    if env:
        dirs.append(Path(env).expanduser())
    repo = Path(lidarjax.__file__).resolve().parents[1]
    for cand in (repo / ".." / "shared" / "data", Path.cwd() / ".." / "shared" / "data"):
        if cand.is_dir():
            dirs.append(cand.resolve())
    dirs.append(_cache_dir())
    unique: list[Path] = []
    for d in dirs:
        if d not in unique:
            unique.append(d)
    return unique


def _lookup(name: str) -> DataFile:
    try:
        return REGISTRY[name]
    except KeyError:
        valid = ", ".join(sorted(REGISTRY))
        raise ValueError(f"unknown data file {name!r}; valid names: {valid}") from None


def _sha256(path: Path) -> str:
    st = path.stat()
    key = (str(path.resolve()), st.st_mtime_ns, st.st_size)
    digest = _HASH_CACHE.get(key)
    if digest is None:
        digest = pooch.file_hash(str(path), alg="sha256")
        _HASH_CACHE[key] = digest
    return digest


def _verify(path: Path, entry: DataFile) -> None:
    actual = _sha256(path)
    if actual.lower() != entry.sha256.lower():
        raise DataChecksumError(
            f"checksum mismatch for {path} (registered as {entry.relpath}): "
            f"expected sha256 {entry.sha256}, got {actual}. The file is corrupt or a "
            "different version; replace it with the original."
        )


def download_urls(name: str) -> list[str]:
    """Where :func:`fetch` downloads a registered file from, in the order it tries them.

    Args:
        name: Short registry name.

    Returns:
        ``$LIDARJAX_DATA_URL/<relpath>`` when that variable is set (a trailing ``/`` of
        the base is ignored), then the entry's own ``url`` when known; empty when neither.

    Raises:
        ValueError: ``name`` is not registered.
    """
    entry = _lookup(name)
    urls = []
    base = os.environ.get(MIRROR_ENV, "").strip()
    if base:
        urls.append(f"{base.rstrip('/')}/{entry.relpath}")
    if entry.url is not None and entry.url not in urls:
        urls.append(entry.url)
    return urls


def fetch(name: str, *, progress: bool = False) -> Path:
    """Locate (or download) a registered data file and verify its SHA-256.

    Args:
        name: Short registry name, e.g. ``"intel"`` or ``"kitti-00-poses"``.
        progress: Show a progress bar (tqdm) while downloading.

    Returns:
        Path of the verified file.

    Raises:
        ValueError: ``name`` is not registered (the message lists the valid names).
        DataChecksumError: The first copy found, or a downloaded copy, has the wrong
            checksum (a wrong download is deleted).
        DataNotFoundError: The file is in no search folder and cannot be downloaded (no
            URL known, downloads turned off by ``$LIDARJAX_OFFLINE``, or every download
            failed).
    """
    entry = _lookup(name)
    dirs = data_dirs()
    for d in dirs:
        path = d / entry.relpath
        if path.is_file():
            _verify(path, entry)
            return path
    tried = "\n".join(f"  - {d}" for d in dirs)
    urls = download_urls(name)
    if urls and not _offline():
        return _download(name, entry, urls, tried, progress)
    why = (
        f"Downloads are turned off ({OFFLINE_ENV} is set)."
        if urls
        else f"No download URL is known (set {MIRROR_ENV} to a mirror of the data folder)."
    )
    raise DataNotFoundError(
        f"data file {name!r} ({entry.relpath}) not found; looked in:\n{tried}\n{why} "
        f"Put the file at <folder>/{entry.relpath} and point the {ENV_VAR} environment "
        f"variable at <folder> (sha256 {entry.sha256})."
    )


def _download(name: str, entry: DataFile, urls: list[str], tried: str, progress: bool) -> Path:
    """Download ``entry`` from the first of ``urls`` that answers, into the user cache.

    A copy with the wrong checksum is an error at once (pooch deletes it), not a reason to
    try the next URL: a mirror that serves wrong data must be noticed.
    """
    target = _cache_dir() / entry.relpath
    # folders pooch creates for the download, deepest first: removed again if it fails
    created = [p for p in (target.parent, *target.parent.parents) if not p.exists()]
    failures = []
    for url in urls:
        try:
            got = pooch.retrieve(
                url,
                known_hash=f"sha256:{entry.sha256}",
                fname=target.name,
                path=target.parent,
                progressbar=progress,
            )
        except ValueError as exc:  # pooch raises ValueError on a hash mismatch
            _remove_empty(created)
            raise DataChecksumError(
                f"downloaded {url} for {name!r} but its checksum is wrong (the download "
                f"was deleted): {exc}"
            ) from exc
        except Exception as exc:  # network, HTTP or filesystem errors: try the next URL
            failures.append(f"  - {url}: {exc}")
            continue
        return Path(got)
    _remove_empty(created)
    failed = "\n".join(failures)
    raise DataNotFoundError(
        f"data file {name!r} ({entry.relpath}) not found; looked in:\n{tried}\n"
        f"and downloading failed:\n{failed}\nProvide it via {ENV_VAR} (a folder) or "
        f"{MIRROR_ENV} (a mirror base URL)."
    )


def _remove_empty(folders: list[Path]) -> None:
    """Remove the folders (deepest first) that are still empty."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:  # not empty (another download), or already gone
            pass


def available() -> list[str]:
    """Registered names whose file exists in some search folder (no checksum check).

    Returns:
        Sorted short names.
    """
    dirs = data_dirs()
    return sorted(
        name for name, entry in REGISTRY.items() if any((d / entry.relpath).is_file() for d in dirs)
    )
