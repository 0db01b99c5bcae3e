"""Downloads through the data registry, against a local HTTP server (no other network).

The server (``http.server`` in a thread, 127.0.0.1) serves ``../shared/data`` or a corrupted
copy of one file; ``LIDARJAX_DATA_URL`` points the registry's mirror at it, the user cache
(``LIDARJAX_CACHE``) is a temporary folder, and the search folders are an empty folder and
that cache (so the shared copy next to the repository is not found first).
"""

from __future__ import annotations

import functools
import hashlib
import http.server
import re
import threading
from pathlib import Path

import pytest

from lidarjax.datasets import REGISTRY, DataChecksumError, DataNotFoundError, _registry, fetch
from lidarjax.datasets._registry import download_urls

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"

pytestmark = pytest.mark.skipif(not SHARED.is_dir(), reason="needs ../shared/data")


class _Server:
    """A threaded HTTP server on 127.0.0.1 serving ``root``; counts GET requests."""

    def __init__(self, root: Path):
        self.requests: list[str] = []
        outer = self

        class Handler(http.server.SimpleHTTPRequestHandler):
            def do_GET(self):  # noqa: N802 (http.server's name)
                outer.requests.append(self.path)
                super().do_GET()

            def log_message(self, *args):  # keep the test output clean
                pass

        handler = functools.partial(Handler, directory=str(root))
        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(5)


@pytest.fixture
def serve():
    servers = []

    def start(root: Path) -> _Server:
        servers.append(_Server(root))
        return servers[-1]

    yield start
    for s in servers:
        s.close()


@pytest.fixture
def isolated(tmp_path, monkeypatch):
    """Empty LIDARJAX_DATA folder, user cache in tmp, downloads on; returns the cache."""
    empty, cache = tmp_path / "empty", tmp_path / "cache"
    empty.mkdir()
    monkeypatch.setenv("LIDARJAX_DATA", str(empty))
    monkeypatch.setenv("LIDARJAX_CACHE", str(cache))
    monkeypatch.delenv("LIDARJAX_OFFLINE", raising=False)
    monkeypatch.delenv("LIDARJAX_DATA_URL", raising=False)
    # only the empty folder and the cache: the shared copy must not be found first
    monkeypatch.setattr(_registry, "data_dirs", lambda: [empty, _registry._cache_dir()])
    return cache


def _files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.is_file()) if folder.exists() else []


def test_cache_env_sets_the_user_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("LIDARJAX_CACHE", str(tmp_path / "c"))
    assert _registry._cache_dir() == tmp_path / "c"
    assert _registry.data_dirs()[-1] == tmp_path / "c"


def test_download_urls_mirror_first(monkeypatch):
    monkeypatch.setenv("LIDARJAX_DATA_URL", "http://mirror.example/data/")
    assert download_urls("intel") == [
        "http://mirror.example/data/carmen/intel-corrected.log.gz",
        REGISTRY["intel"].url,
    ]
    assert download_urls("synpeb-test-100") == ["http://mirror.example/data/synpeb/test_100.pcd"]
    monkeypatch.delenv("LIDARJAX_DATA_URL")
    assert download_urls("synpeb-test-100") == []


def test_public_urls_are_pinned():
    """Known public locations are raw files at a fixed commit, named like the file."""
    pinned = re.compile(r"https://raw\.githubusercontent\.com/[\w.-]+/[\w.-]+/[0-9a-f]{40}/\S+")
    for name, entry in REGISTRY.items():
        if entry.metadata.get("format") == "carmen":
            assert pinned.fullmatch(entry.url), name
            assert entry.url.endswith("/data/carmen/" + Path(entry.relpath).name), name
    for name in ("kitti-00-poses", "kitti-00-times"):
        assert pinned.fullmatch(REGISTRY[name].url), name
    assert REGISTRY["synpeb-test-100"].url is None  # no public copy is known


@pytest.mark.parametrize("name", ["orebro", "kitti-00-times"])
def test_fetch_downloads_and_verifies(name, isolated, serve, monkeypatch):
    server = serve(SHARED)
    monkeypatch.setenv("LIDARJAX_DATA_URL", server.url)
    entry = REGISTRY[name]
    path = fetch(name, progress=True)
    assert path == isolated / entry.relpath
    assert hashlib.sha256(path.read_bytes()).hexdigest() == entry.sha256
    assert path.read_bytes() == (SHARED / entry.relpath).read_bytes()
    assert server.requests == ["/" + entry.relpath]
    assert _files(isolated) == [path]  # nothing else left behind
    # the second fetch finds the verified copy in the cache, without a request
    assert fetch(name) == path
    assert len(server.requests) == 1


def test_corrupted_download_raises_and_leaves_nothing(isolated, serve, monkeypatch, tmp_path):
    entry = REGISTRY["orebro"]
    bad_root = tmp_path / "bad"
    bad = bad_root / entry.relpath
    bad.parent.mkdir(parents=True)
    data = bytearray((SHARED / entry.relpath).read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte
    bad.write_bytes(bytes(data))
    server = serve(bad_root)
    monkeypatch.setenv("LIDARJAX_DATA_URL", server.url)
    with pytest.raises(DataChecksumError, match="checksum") as info:
        fetch("orebro")
    assert server.url in str(info.value)
    assert server.requests == ["/" + entry.relpath]  # the public URL was not tried
    assert not isolated.exists()  # no file, and no folder made for the download either


def test_unreachable_mirror_is_data_not_found(isolated, serve, monkeypatch, tmp_path):
    server = serve(tmp_path / "empty")  # answers 404 for everything
    monkeypatch.setenv("LIDARJAX_DATA_URL", server.url)
    with pytest.raises(DataNotFoundError) as info:
        fetch("synpeb-test-100")  # no public URL: only the mirror is tried
    msg = str(info.value)
    assert f"{server.url}/synpeb/test_100.pcd" in msg and "LIDARJAX_DATA_URL" in msg
    assert not isolated.exists()


def test_offline_switch_stops_downloads(isolated, serve, monkeypatch):
    server = serve(SHARED)
    monkeypatch.setenv("LIDARJAX_DATA_URL", server.url)
    monkeypatch.setenv("LIDARJAX_OFFLINE", "1")
    with pytest.raises(DataNotFoundError, match="LIDARJAX_OFFLINE"):
        fetch("orebro")
    assert server.requests == []
