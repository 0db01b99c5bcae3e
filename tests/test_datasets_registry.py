"""Tests of the checksummed data registry (``lidarjax.datasets._registry``)."""

from __future__ import annotations

import hashlib
import os
import re
import shutil
from pathlib import Path

import pooch
import pytest

from lidarjax.datasets import _registry
from lidarjax.datasets._errors import DataChecksumError, DataNotFoundError
from lidarjax.datasets._registry import REGISTRY, DataFile, available, data_dirs, fetch

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"

CARMEN_LOGS = [
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
]


def _sha256sums() -> dict[str, str]:
    """relpath -> sha256 from the shared SHA256SUMS file (independent of the registry)."""
    sums: dict[str, str] = {}
    for line in (SHARED / "SHA256SUMS").read_text().splitlines():
        if line.strip():
            digest, rel = line.split()
            sums[rel] = digest
    return sums


def _name_of(relpath: str) -> str:
    matches = [n for n, e in REGISTRY.items() if e.relpath == relpath]
    assert len(matches) == 1, relpath
    return matches[0]


def _sha256_file(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_registry_names_and_entries():
    expected = set(CARMEN_LOGS) | {
        "aces",
        "seattle",
        "synpeb-test-100",
        "kitti-00-poses",
        "kitti-00-times",
    }
    assert set(REGISTRY) == expected
    relpaths = [e.relpath for e in REGISTRY.values()]
    assert len(set(relpaths)) == len(relpaths)
    for name, entry in REGISTRY.items():
        assert isinstance(entry, DataFile)
        assert re.fullmatch(r"[0-9a-f]{64}", entry.sha256), name
        if name == "synpeb-test-100":  # no public location known
            assert entry.url is None
        else:  # pinned to a commit, so the bytes (and the checksum) cannot change
            assert re.fullmatch(
                r"https://raw\.githubusercontent\.com/[\w.-]+/[\w.-]+/[0-9a-f]{40}/.+", entry.url
            ), (name, entry.url)
        assert entry.description
        assert not Path(entry.relpath).is_absolute()
    assert REGISTRY["intel"].relpath == "carmen/intel-corrected.log.gz"
    assert REGISTRY["synpeb-test-100"].relpath == "synpeb/test_100.pcd"
    assert REGISTRY["intel"].metadata["n_scans"] == 910
    assert REGISTRY["intel"].metadata["n_beams"] == 180
    # The two unshipped logs, with the checksums quoted in the data README.
    assert REGISTRY["aces"].sha256 == (
        "5434d44384166250608a64d3a8c32de84512f82c46cb60a2657f138592024569"
    )
    assert REGISTRY["seattle"].sha256 == (
        "5719198036b788d78a877ca04efdbfb07c2518508310f51d49c198bf1956bb4b"
    )
    assert (REGISTRY["aces"].metadata["n_scans"], REGISTRY["aces"].metadata["n_beams"]) == (
        440,
        180,
    )
    assert (REGISTRY["seattle"].metadata["n_scans"], REGISTRY["seattle"].metadata["n_beams"]) == (
        241,
        361,
    )


def test_datafile_is_frozen():
    with pytest.raises(AttributeError):
        REGISTRY["intel"].sha256 = "0" * 64  # type: ignore[misc]


def test_registry_matches_sha256sums():
    sums = _sha256sums()
    assert len(sums) == 14
    for rel, digest in sums.items():
        assert REGISTRY[_name_of(rel)].sha256 == digest


@pytest.mark.parametrize(
    "relpath", sorted(_sha256sums()) if (SHARED / "SHA256SUMS").is_file() else []
)
def test_fetch_verifies_every_shared_file(relpath, monkeypatch):
    monkeypatch.delenv("LIDARJAX_DATA", raising=False)
    path = fetch(_name_of(relpath))
    assert path.is_file()
    assert path.resolve() == (SHARED / relpath).resolve()
    # Independent hash with hashlib, not through the registry's own hashing.
    assert _sha256_file(path) == _sha256sums()[relpath]


def test_fetch_unknown_name_lists_valid_names():
    with pytest.raises(ValueError, match="valid names") as info:
        fetch("no-such-log")
    for name in ("intel", "aces", "kitti-00-poses", "synpeb-test-100"):
        assert name in str(info.value)


def test_fetch_checksum_mismatch(tmp_path, monkeypatch):
    entry = REGISTRY["orebro"]
    dst = tmp_path / entry.relpath
    dst.parent.mkdir(parents=True)
    data = bytearray((SHARED / entry.relpath).read_bytes())
    data[len(data) // 2] ^= 0xFF
    dst.write_bytes(bytes(data))
    monkeypatch.setenv("LIDARJAX_DATA", str(tmp_path))
    with pytest.raises(DataChecksumError) as info:
        fetch("orebro")
    msg = str(info.value)
    assert str(dst) in msg
    assert entry.sha256 in msg
    assert _sha256_file(dst) in msg


def test_env_folder_takes_precedence(tmp_path, monkeypatch):
    entry = REGISTRY["kitti-00-times"]
    dst = tmp_path / entry.relpath
    dst.parent.mkdir(parents=True)
    shutil.copyfile(SHARED / entry.relpath, dst)
    monkeypatch.setenv("LIDARJAX_DATA", str(tmp_path))
    assert data_dirs()[0] == tmp_path
    assert fetch("kitti-00-times") == dst


def test_modified_file_is_rehashed(tmp_path, monkeypatch):
    """The verified-hash cache must not hide a file that changed after a first fetch."""
    entry = REGISTRY["kitti-00-times"]
    dst = tmp_path / entry.relpath
    dst.parent.mkdir(parents=True)
    shutil.copyfile(SHARED / entry.relpath, dst)
    monkeypatch.setenv("LIDARJAX_DATA", str(tmp_path))
    assert fetch("kitti-00-times") == dst
    data = bytearray(dst.read_bytes())
    data[0] ^= 0x01  # same size
    dst.write_bytes(bytes(data))
    st = dst.stat()
    os.utime(dst, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    with pytest.raises(DataChecksumError):
        fetch("kitti-00-times")


def test_repeated_fetch_does_not_rehash(monkeypatch):
    monkeypatch.delenv("LIDARJAX_DATA", raising=False)
    first = fetch("freiburg-079")

    def boom(*args, **kwargs):
        raise AssertionError("file was hashed again")

    monkeypatch.setattr(pooch, "file_hash", boom)
    assert fetch("freiburg-079") == first


def test_missing_file_names_every_folder(tmp_path, monkeypatch):
    env_dir = tmp_path / "env"
    env_dir.mkdir()
    monkeypatch.setenv("LIDARJAX_DATA", str(env_dir))
    dirs = [env_dir, tmp_path / "shared", tmp_path / "cache"]
    monkeypatch.setattr(_registry, "data_dirs", lambda: list(dirs))
    with pytest.raises(DataNotFoundError) as info:
        fetch("intel")
    assert isinstance(info.value, FileNotFoundError)
    msg = str(info.value)
    assert "carmen/intel-corrected.log.gz" in msg
    for d in dirs:
        assert str(d) in msg
    assert "LIDARJAX_DATA" in msg
    assert available() == []


def test_unshipped_log_not_found(monkeypatch):
    monkeypatch.delenv("LIDARJAX_DATA", raising=False)
    with pytest.raises(DataNotFoundError) as info:
        fetch("aces")
    msg = str(info.value)
    assert "aces-corrected.log.gz" in msg
    for d in data_dirs():
        assert str(d) in msg


def test_available(monkeypatch):
    monkeypatch.delenv("LIDARJAX_DATA", raising=False)
    names = available()
    assert set(CARMEN_LOGS) <= set(names)
    assert {"synpeb-test-100", "kitti-00-poses", "kitti-00-times"} <= set(names)
    assert "aces" not in names
    assert "seattle" not in names
    assert names == sorted(names)


def test_data_dirs_order(tmp_path, monkeypatch):
    monkeypatch.setenv("LIDARJAX_DATA", str(tmp_path))
    dirs = data_dirs()
    assert dirs[0] == tmp_path
    assert dirs[-1] == Path(pooch.os_cache("lidarjax"))
    assert len(set(dirs)) == len(dirs)
    if SHARED.is_dir():
        assert SHARED.resolve() in dirs
    monkeypatch.delenv("LIDARJAX_DATA")
    assert tmp_path not in data_dirs()


def test_url_entries_download_into_cache(tmp_path, monkeypatch):
    monkeypatch.delenv("LIDARJAX_OFFLINE", raising=False)
    digest = hashlib.sha256(b"hello\n").hexdigest()
    entry = DataFile("extra/hello.txt", digest, "test file", url="https://example.invalid/hello")
    monkeypatch.setitem(REGISTRY, "hello", entry)
    cache = tmp_path / "cache"
    monkeypatch.setattr(_registry, "_cache_dir", lambda: cache)
    monkeypatch.setattr(_registry, "data_dirs", lambda: [tmp_path / "nowhere", cache])
    calls = []

    def fake_retrieve(url, known_hash, fname=None, path=None, **kwargs):
        calls.append((url, known_hash, fname, Path(path)))
        out = Path(path) / fname
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(b"hello\n")
        return str(out)

    monkeypatch.setattr(pooch, "retrieve", fake_retrieve)
    got = fetch("hello")
    assert got == cache / "extra" / "hello.txt"
    assert calls == [(entry.url, f"sha256:{digest}", "hello.txt", cache / "extra")]
    # Second fetch finds the cached copy without downloading again.
    assert fetch("hello") == got
    assert len(calls) == 1


def test_download_failure_is_data_not_found(tmp_path, monkeypatch):
    monkeypatch.delenv("LIDARJAX_OFFLINE", raising=False)
    entry = DataFile("extra/x.bin", "0" * 64, "test file", url="https://example.invalid/x")
    monkeypatch.setitem(REGISTRY, "x", entry)
    monkeypatch.setattr(_registry, "_cache_dir", lambda: tmp_path)
    monkeypatch.setattr(_registry, "data_dirs", lambda: [tmp_path])

    def failing_retrieve(*args, **kwargs):
        raise ConnectionError("network unreachable")

    monkeypatch.setattr(pooch, "retrieve", failing_retrieve)
    with pytest.raises(DataNotFoundError, match="network unreachable"):
        fetch("x")
