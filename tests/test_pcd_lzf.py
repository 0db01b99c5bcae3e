"""The two LZF codecs of ``lidarjax.datasets._pcd`` (python-lzf and pure Python) against each
other, the backend switch, and PCD ``binary_compressed`` round trips through both."""

from __future__ import annotations

import struct
from pathlib import Path

import lzf  # python-lzf: a dev dependency (the optional extra "lzf" for users)
import numpy as np
import pytest

from lidarjax.datasets import _pcd, fetch, lzf_backend, read_pcd, write_pcd
from lidarjax.datasets._pcd import _lzf_decode, _lzf_encode, _LZFError

BACKENDS = ("python-lzf", "pure-python")


def _inputs() -> dict[str, bytes]:
    rng = np.random.default_rng(0)
    scan = np.cumsum(rng.normal(scale=0.01, size=(3, 4000)), axis=1).astype(np.float32)
    labels = np.repeat(rng.integers(0, 9, size=80), 50).astype(np.float32)
    return {
        "empty": b"",
        "one": b"\x07",
        "two": b"ab",
        "three": b"abc",
        "zeros": bytes(10_000),
        "run": b"ab" * 700 + b"c" * 300,
        "text": b"the quick brown fox jumps over the lazy dog; " * 80,
        "long match": b"x" * 264 + b"y" + b"x" * 600,
        "far match": bytes(rng.integers(0, 256, 9000, dtype=np.uint8)) * 2,
        "scan": scan.tobytes() + labels.tobytes(),
        **{
            f"random {n}": bytes(rng.integers(0, 256, n, dtype=np.uint8))
            for n in (1, 2, 3, 31, 32, 33, 1000, 65_537)
        },
    }


INPUTS = _inputs()


@pytest.mark.parametrize("name", sorted(INPUTS))
def test_codecs_decode_each_other(name: str) -> None:
    data = INPUTS[name]
    packed = {b: _lzf_encode(data, b) for b in BACKENDS}
    for enc in BACKENDS:
        for dec in BACKENDS:
            assert _lzf_decode(packed[enc], len(data), dec) == data, (enc, dec)
    if name.startswith("random") and len(data) > 3:
        # Incompressible: PCD has no stored mode, the stream is literal runs (32 bytes + one
        # control byte each), slightly longer than the input, as PCL writes it too.
        # (Accidental 3-byte matches may save a few bytes.)
        for enc in BACKENDS:
            assert len(data) < len(packed[enc]) <= len(data) + -(-len(data) // 32), enc
    if name in ("zeros", "run", "text"):
        for enc in BACKENDS:
            assert len(packed[enc]) < len(data) // 2, enc
    if name == "scan":
        for enc in BACKENDS:
            assert len(packed[enc]) < len(data), enc


def test_python_lzf_refusal_falls_back_to_a_valid_stream(monkeypatch) -> None:
    """Should liblzf refuse (it returns None past its output bound) the stream is still valid."""

    class Refusing:
        @staticmethod
        def compress(data, max_len):
            return None

        decompress = staticmethod(lzf.decompress)

    monkeypatch.setattr(_pcd, "_lzf_ext", Refusing)
    data = INPUTS["random 1000"]
    packed = _lzf_encode(data, "python-lzf")
    assert _lzf_decode(packed, len(data), "pure-python") == data


def _mutants(stream: bytes, rng: np.random.Generator, n: int):
    for _ in range(n):
        s = bytearray(stream)
        kind = int(rng.integers(4))
        at = int(rng.integers(0, max(len(s), 1)))
        if kind == 0 and s:
            s[at] = int(rng.integers(256))
        elif kind == 1:
            s.insert(at, int(rng.integers(256)))
        elif kind == 2 and s:
            del s[at]
        else:
            s = s[:at]
        yield bytes(s)


def _decode_or_reject(stream: bytes, size: int, backend: str) -> bytes | None:
    try:
        return _lzf_decode(stream, size, backend)
    except _LZFError:
        return None


@pytest.mark.parametrize("name", ["text", "scan", "random 1000", "run"])
def test_codecs_accept_and_reject_the_same_streams(name: str) -> None:
    """Mutated and random streams: both decoders reject, or both return the same bytes."""
    data = INPUTS[name]
    rng = np.random.default_rng(len(name))
    stream = _lzf_encode(data, "pure-python")
    cases = list(_mutants(stream, rng, 150))
    cases += [
        bytes(rng.integers(0, 256, int(rng.integers(0, 40)), dtype=np.uint8)) for _ in range(50)
    ]
    n_both_ok = 0
    for case in cases:
        for size in (len(data), len(data) - 1, len(data) + 1, 0):
            size = max(size, 0)
            a = _decode_or_reject(case, size, "python-lzf")
            b = _decode_or_reject(case, size, "pure-python")
            assert a == b, (case[:16], size)
            n_both_ok += a is not None
    assert n_both_ok > 0


def test_hand_built_streams_both_codecs() -> None:
    cases = [
        (bytes([0x02, *b"abc", 0xC0, 0x02]), 11, b"abcabcabcab"),  # overlapping reference
        (bytes([0x00, 0x41, 0xE0, 0x01, 0x00]), 11, b"A" * 11),  # length byte after 0xE0
    ]
    for stream, size, want in cases:
        for backend in BACKENDS:
            assert _lzf_decode(stream, size, backend) == want
    bad = [
        (bytes([0x20, 0x05]), 3),  # reference before the start of the output
        (bytes([0x05, 1, 2]), 6),  # literal run past the end of the input
        (bytes([0x00, 0x41, 0xE0]), 10),  # stream ends inside a back-reference
        (bytes([0x00, 0x41, 0x20]), 4),  # stream ends before the offset byte
        (b"", 1),  # nothing for 1 byte
        (b"\x00a", 0),  # a byte for nothing
        (bytes([0x02, *b"abc", 0xC0, 0x02]), 10),  # decodes to too much
        (bytes([0x02, *b"abc", 0xC0, 0x02]), 12),  # decodes to too little
    ]
    for stream, size in bad:
        for backend in BACKENDS:
            with pytest.raises(_LZFError):
                _lzf_decode(stream, size, backend)
    for backend in BACKENDS:
        assert _lzf_decode(b"", 0, backend) == b""
    with pytest.raises(ValueError, match="backend"):
        _lzf_decode(b"", 0, "zlib")
    with pytest.raises(ValueError, match="backend"):
        _lzf_encode(b"a", "zlib")


# ------------------------------------------------------------------------------ the switch


def test_lzf_backend_switch(monkeypatch) -> None:
    monkeypatch.delenv(_pcd.LZF_ENV, raising=False)
    assert lzf_backend() == "python-lzf"
    for value, want in [("auto", "python-lzf"), ("pure-python", "pure-python")]:
        monkeypatch.setenv("LIDARJAX_LZF", value)
        assert lzf_backend() == want
    monkeypatch.setenv("LIDARJAX_LZF", " Python-LZF ")
    assert lzf_backend() == "python-lzf"
    monkeypatch.setenv("LIDARJAX_LZF", "fast")
    with pytest.raises(ValueError, match="LIDARJAX_LZF.*'fast'"):
        lzf_backend()
    monkeypatch.setattr(_pcd, "_lzf_ext", None)  # as if python-lzf were not installed
    monkeypatch.setenv("LIDARJAX_LZF", "python-lzf")
    with pytest.raises(ImportError, match="python-lzf"):
        lzf_backend()
    monkeypatch.setenv("LIDARJAX_LZF", "auto")
    assert lzf_backend() == "pure-python"


def test_read_and_write_follow_the_switch(monkeypatch, tmp_path: Path) -> None:
    """With ``pure-python`` forced, python-lzf is never called; by default it is."""
    calls: list[str] = []

    class Spy:
        @staticmethod
        def compress(data, max_len):
            calls.append("compress")
            return lzf.compress(data, max_len)

        @staticmethod
        def decompress(data, size):
            calls.append("decompress")
            return lzf.decompress(data, size)

    monkeypatch.setattr(_pcd, "_lzf_ext", Spy)
    fields = {"x": np.arange(100, dtype=np.float32)}
    monkeypatch.setenv("LIDARJAX_LZF", "pure-python")
    read_pcd(write_pcd(tmp_path / "a.pcd", fields))
    assert calls == []
    monkeypatch.setenv("LIDARJAX_LZF", "auto")
    read_pcd(write_pcd(tmp_path / "b.pcd", fields))
    assert calls == ["compress", "decompress"]


# ------------------------------------------------------------------------------ PCD files


@pytest.mark.parametrize("writer", BACKENDS)
@pytest.mark.parametrize("reader", BACKENDS)
def test_synpeb_file_round_trip_across_codecs(
    monkeypatch, tmp_path: Path, writer: str, reader: str
) -> None:
    """The shared ASCII SynPEB crop, written binary_compressed by one codec, read by the other."""
    original = read_pcd(fetch("synpeb-test-100"))
    monkeypatch.setenv("LIDARJAX_LZF", writer)
    path = write_pcd(tmp_path / "c.pcd", original, data="binary_compressed")
    raw = path.read_bytes()
    body = raw[raw.index(b"DATA binary_compressed\n") + 23 :]
    csize, usize = struct.unpack("<II", body[:8])
    assert usize == 100 * 100 * 4 * 4 and csize == len(body) - 8 and csize < usize
    monkeypatch.setenv("LIDARJAX_LZF", reader)
    back = read_pcd(path)
    assert (back.height, back.width) == (100, 100)
    assert list(back.fields) == list(original.fields) == ["x", "y", "z", "intensity"]
    for name in original.fields:
        assert back[name].dtype == original[name].dtype
        np.testing.assert_array_equal(back[name], original[name])  # NaN == NaN
    np.testing.assert_array_equal(back.viewpoint, original.viewpoint)


@pytest.mark.parametrize("writer", BACKENDS)
def test_incompressible_and_empty_clouds(monkeypatch, tmp_path: Path, writer: str) -> None:
    rng = np.random.default_rng(5)
    noise = {"b": rng.integers(0, 256, size=(7, 300), dtype=np.uint8)}
    empty = {"x": np.zeros((0, 5), np.float32)}
    for fields in (noise, empty):
        monkeypatch.setenv("LIDARJAX_LZF", writer)
        path = write_pcd(tmp_path / "n.pcd", fields, data="binary_compressed")
        for reader in BACKENDS:
            monkeypatch.setenv("LIDARJAX_LZF", reader)
            back = read_pcd(path)
            for name, want in fields.items():
                np.testing.assert_array_equal(back[name], want)
