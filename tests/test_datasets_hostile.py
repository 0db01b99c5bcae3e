"""Hostile files for every dataset reader: seeded mutation fuzzing against independent parsers.

Each reader is fed mutants of a seed file (the shared real files where the format has one:
the SynPEB PCD crop, the CARMEN logs, the KITTI-00 poses and times; small files in the real
format written here otherwise: KITTI ``.bin`` scans and ``calib.txt``, NCLT ``velodyne_sync``,
``velodyne_hits`` and ground-truth CSV). A mutant is one byte flip, insertion or deletion, a
truncation, or (text formats) a duplicated line. For every mutant the reader must either

* raise :class:`DatasetFormatError` naming the file, or
* return exactly what the *reference* parser in this file reads.

A reader that accepts a mutant the reference rejects fails, as does any other exception
(``ValueError`` from NumPy, ``MemoryError``, ``IndexError``, ...). The references are written
from the format descriptions alone (module docstrings, the shared data README): plain Python
byte scanning, ``struct`` and a hand-written number scanner and LZF decoder; none of them calls
into ``lidarjax.datasets``. They define the accepted language: ASCII whitespace separates
tokens, numbers are decimal literals (``nan``/``inf`` only where the format allows them),
every byte of a binary payload is accounted for, and declared sizes match the file.

Mutation sites are drawn half uniformly over the file and half over "hot" spans (headers,
line starts and ends), and inserted bytes half from an alphabet of troublemakers (digits,
signs, ``_``, ``e``, whitespace including non-ASCII ``\\xa0``/``\\x85``, ``#``, separators).
Every test is seeded. The default run uses a few hundred mutants per reader; the sweeps marked
``slow`` use more mutants and every CARMEN log. ``LIDARJAX_FUZZ_SCALE=k`` multiplies all counts.
"""

from __future__ import annotations

import gzip
import math
import os
import struct
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import scipy.linalg

from lidarjax.datasets import (
    DatasetFormatError,
    fetch,
    load_carmen,
    load_kitti_poses,
    load_kitti_sequence,
    load_kitti_times,
    load_synpeb_pcd,
    load_urban_trajectory,
    read_kitti_velodyne,
    read_nclt_ground_truth,
    read_nclt_velodyne_hits,
    read_nclt_velodyne_sync,
    read_pcd,
    write_pcd,
)

_SCALE = max(1, int(os.environ.get("LIDARJAX_FUZZ_SCALE", "1")))


class Reject(Exception):
    """The reference parser rejects the file."""


# ==========================================================================================
# Mutations
# ==========================================================================================

_TROUBLE = b"0123456789.-+eE_ \t\r\n#,:nNaAiIfF" + bytes(
    [0x00, 0xFF, 0xA0, 0x85, 0x0B, 0x0C, 0x1C, 0x1F]
)


def _pick_byte(rng: np.random.Generator) -> int:
    if rng.random() < 0.5:
        return int(_TROUBLE[rng.integers(len(_TROUBLE))])
    return int(rng.integers(256))


def _pick_pos(
    rng: np.random.Generator, n: int, hot: Sequence[tuple[int, int]], *, end: bool
) -> int:
    """A byte position in ``[0, n)`` (``[0, n]`` with ``end``), half of them in a hot span."""
    top = n + 1 if end else n
    if hot and rng.random() < 0.5:
        lo, hi = hot[rng.integers(len(hot))]
        lo, hi = max(0, min(lo, top - 1)), max(1, min(hi, top))
        return int(rng.integers(lo, max(lo + 1, hi)))
    return int(rng.integers(top))


def mutants(
    data: bytes,
    n: int,
    *,
    seed: int,
    hot: Sequence[tuple[int, int]] = (),
    text: bool = False,
) -> Iterator[tuple[str, bytes]]:
    """``n`` seeded single mutations of ``data`` as ``(description, bytes)``."""
    rng = np.random.default_rng(seed)
    hot = list(hot)
    kinds = ["flip", "bitflip", "insert", "delete", "truncate"] + (["dup_line"] * 2 if text else [])
    for _ in range(n):
        kind = kinds[rng.integers(len(kinds))]
        if kind in ("flip", "bitflip") and data:
            pos = _pick_pos(rng, len(data), hot, end=False)
            new = _pick_byte(rng) if kind == "flip" else data[pos] ^ (1 << int(rng.integers(8)))
            yield (
                f"{kind} @{pos}: {data[pos]:#04x} -> {new:#04x}",
                (data[:pos] + bytes([new]) + data[pos + 1 :]),
            )
        elif kind == "insert":
            pos = _pick_pos(rng, len(data), hot, end=True)
            new = _pick_byte(rng)
            yield f"insert {new:#04x} @{pos}", data[:pos] + bytes([new]) + data[pos:]
        elif kind == "delete" and data:
            pos = _pick_pos(rng, len(data), hot, end=False)
            yield f"delete {data[pos]:#04x} @{pos}", data[:pos] + data[pos + 1 :]
        elif kind == "truncate":
            pos = _pick_pos(rng, len(data), hot, end=False)
            yield f"truncate to {pos} bytes", data[:pos]
        elif kind == "dup_line":
            starts = [0] + [i + 1 for i in range(len(data)) if data[i] == 0x0A]
            starts = [s for s in starts if s < len(data)]
            if hot and rng.random() < 0.5:
                pos = _pick_pos(rng, len(data), hot, end=False)
                start = max(s for s in starts if s <= pos)
            else:
                start = starts[rng.integers(len(starts))]
            stop = data.find(b"\n", start)
            stop = len(data) if stop < 0 else stop + 1
            line = data[start:stop] if data[stop - 1 : stop] == b"\n" else data[start:stop] + b"\n"
            yield f"duplicate line @{start}", data[:stop] + line + data[stop:]
        else:
            yield "unchanged (empty seed)", data


def line_spans(data: bytes, keep: Callable[[bytes], bool], head: int, tail: int):
    """Hot spans: the first ``head`` and last ``tail`` bytes of every line ``keep`` selects."""
    spans = []
    pos = 0
    for line in data.split(b"\n"):
        if keep(line):
            spans.append((pos, pos + min(head, len(line) + 1)))
            spans.append((max(pos, pos + len(line) - tail), pos + len(line) + 1))
        pos += len(line) + 1
    return spans


def fuzz(
    tmp_path: Path,
    name: str,
    seed_bytes: bytes,
    read: Callable[[Path], Any],
    reference: Callable[[bytes], Any],
    compare: Callable[[Any, Any], None],
    n: int,
    *,
    seed: int,
    hot: Sequence[tuple[int, int]] = (),
    text: bool = False,
    write: Callable[[Path, bytes], Path] | None = None,
) -> tuple[int, int]:
    """Runs the mutants through ``read`` and checks each outcome; returns (accepted, rejected).

    ``write(path, data)`` lets a test put a mutant into a larger layout (e.g. a KITTI
    sequence folder) and returns the path the reader's errors must name.
    """
    path = tmp_path / name

    def put(data: bytes) -> Path:
        if write is not None:
            return write(path, data)
        path.write_bytes(data)
        return path

    target = put(seed_bytes)
    # The seed itself must be read as the reference reads it.
    compare(read(target), reference(seed_bytes))
    accepted = rejected = 0
    for desc, data in mutants(seed_bytes, n * _SCALE, seed=seed, hot=hot, text=text):
        target = put(data)
        try:
            got = read(target)
        except DatasetFormatError as err:
            assert str(target) in str(err), f"{desc}: error does not name the file: {err}"
            rejected += 1
            continue
        except Exception as err:  # noqa: BLE001 - any other exception is the bug we look for
            pytest.fail(
                f"{name}, {desc}: {type(err).__name__} instead of DatasetFormatError: {err}"
            )
        try:
            want = reference(data)
        except Reject as why:
            pytest.fail(f"{name}, {desc}: the reader accepted a file the reference rejects ({why})")
        try:
            compare(got, want)
        except AssertionError as err:
            pytest.fail(f"{name}, {desc}: read differently from the reference: {err}")
        accepted += 1
    assert rejected > 0, "no mutant was rejected: the mutations do not reach the parser"
    return accepted, rejected


def assert_same_array(got: np.ndarray, want: np.ndarray, what: str) -> None:
    got, want = np.asarray(got), np.asarray(want)
    assert got.dtype == want.dtype, f"{what}: dtype {got.dtype} != {want.dtype}"
    assert got.shape == want.shape, f"{what}: shape {got.shape} != {want.shape}"
    if got.dtype.kind == "f":
        assert np.array_equal(got, want, equal_nan=True), f"{what}: values differ"
        num = ~np.isnan(want)
        assert np.array_equal(np.signbit(got[num]), np.signbit(want[num])), f"{what}: signs differ"
    else:
        assert np.array_equal(got, want), f"{what}: values differ"


# ==========================================================================================
# Reference number scanner (decimal literals; nan / inf spelled out)
# ==========================================================================================


def _digits(tok: bytes, i: int) -> int:
    while i < len(tok) and 0x30 <= tok[i] <= 0x39:
        i += 1
    return i


def is_decimal(tok: bytes) -> bool:
    """``[sign] digits [. digits] [e [sign] digits]`` with at least one mantissa digit."""
    i = 1 if tok[:1] in (b"+", b"-") else 0
    j = _digits(tok, i)
    mantissa = j - i
    if tok[j : j + 1] == b".":
        k = _digits(tok, j + 1)
        mantissa += k - j - 1
        j = k
    if mantissa == 0:
        return False
    if tok[j : j + 1] in (b"e", b"E"):
        j += 1
        if tok[j : j + 1] in (b"+", b"-"):
            j += 1
        k = _digits(tok, j)
        if k == j:
            return False
        j = k
    return j == len(tok)


def _nonfinite_word(tok: bytes) -> bytes | None:
    body = tok[1:] if tok[:1] in (b"+", b"-") else tok
    word = body.lower()
    return word if word in (b"nan", b"inf", b"infinity") else None


def ref_float(tok: bytes, *, nan: bool = False, inf: bool = False) -> float:
    """A float token; overflow of a decimal literal to infinity is rejected."""
    if is_decimal(tok):
        value = float(tok.decode("ascii"))
        if math.isinf(value):
            raise Reject(f"{tok!r} overflows")
        return value
    word = _nonfinite_word(tok)
    if word == b"nan" and nan:
        return float(tok.decode("ascii"))
    if word in (b"inf", b"infinity") and inf:
        return float(tok.decode("ascii"))
    raise Reject(f"not a number: {tok!r}")


def is_integer(tok: bytes, *, signed: bool = True) -> bool:
    i = 1 if signed and tok[:1] in (b"+", b"-") else 0
    return len(tok) > i and _digits(tok, i) == len(tok)


# ==========================================================================================
# PCD (and SynPEB on top of it)
# ==========================================================================================

_PCD_KEYS = (b"VERSION", b"FIELDS", b"SIZE", b"TYPE", b"COUNT", b"WIDTH", b"HEIGHT")
_PCD_KEYS += (b"VIEWPOINT", b"POINTS", b"DATA")
# (TYPE, SIZE) -> (numpy dtype, struct code)
_PCD_TYPES = {
    (b"F", 4): (np.float32, "f"),
    (b"F", 8): (np.float64, "d"),
    (b"I", 1): (np.int8, "b"),
    (b"I", 2): (np.int16, "h"),
    (b"I", 4): (np.int32, "i"),
    (b"I", 8): (np.int64, "q"),
    (b"U", 1): (np.uint8, "B"),
    (b"U", 2): (np.uint16, "H"),
    (b"U", 4): (np.uint32, "I"),
    (b"U", 8): (np.uint64, "Q"),
}
_MAX_RECORD_BYTES = 2**31 - 1  # sum of SIZE * COUNT per point
_MAX_DIM = 2**32 - 1  # WIDTH, HEIGHT (uint32 in PCL)


def ref_lzf(src: bytes, size: int) -> bytes:
    """liblzf decoder: control < 32 is a literal run of control + 1 bytes, otherwise a
    back-reference of length (control >> 5) [+ next byte when 7] + 2, distance from the low
    five bits and the following byte, plus one."""
    out = bytearray()
    i = 0
    while i < len(src):
        ctrl = src[i]
        i += 1
        if ctrl < 32:
            if i + ctrl + 1 > len(src):
                raise Reject("LZF literal past the end")
            out += src[i : i + ctrl + 1]
            i += ctrl + 1
        else:
            length = ctrl >> 5
            if length == 7:
                if i >= len(src):
                    raise Reject("LZF stream ends in a back-reference")
                length += src[i]
                i += 1
            if i >= len(src):
                raise Reject("LZF stream ends in a back-reference")
            dist = ((ctrl & 0x1F) << 8 | src[i]) + 1
            i += 1
            if dist > len(out):
                raise Reject("LZF reference before the start")
            for _ in range(length + 2):
                out.append(out[-dist])
        if len(out) > size:
            raise Reject("LZF output too long")
    if len(out) != size:
        raise Reject("LZF output too short")
    return bytes(out)


def ref_pcd(raw: bytes) -> dict[str, Any]:
    """Independent PCD v0.7 parser.

    Returns:
        ``{"fields": {name: array}, "width": int, "height": int, "viewpoint": [7] array}``.
    """
    entries: dict[bytes, list[bytes]] = {}
    pos = 0
    while b"DATA" not in entries:
        if pos >= len(raw):
            raise Reject("header without DATA")
        nl = raw.find(b"\n", pos)
        end = len(raw) if nl < 0 else nl + 1
        line = raw[pos:end]
        pos = end
        if b"#" in line:
            line = line[: line.index(b"#")]
        toks = line.split()
        if not toks:
            continue
        key = toks[0].upper()
        if key not in _PCD_KEYS or key in entries:
            raise Reject(f"bad or repeated header key {toks[0]!r}")
        entries[key] = toks[1:]
    for key in (b"FIELDS", b"SIZE", b"TYPE", b"WIDTH", b"HEIGHT", b"POINTS"):
        if key not in entries:
            raise Reject(f"no {key!r}")
    if b"VERSION" in entries and entries[b"VERSION"] not in ([b".7"], [b"0.7"]):
        raise Reject("VERSION")
    names = entries[b"FIELDS"]
    nf = len(names)
    if nf == 0 or any(any(b < 0x21 or b > 0x7E for b in nm) for nm in names):
        raise Reject("FIELDS")
    real = [nm for nm in names if nm != b"_"]
    if len(set(real)) != len(real):
        raise Reject("duplicate field")

    def counts_of(key: bytes, default: list[int] | None) -> list[int]:
        if key not in entries and default is not None:
            return default
        vals = entries[key]
        if len(vals) != nf or not all(is_integer(v, signed=False) for v in vals):
            raise Reject(key.decode())
        out = [int(v) for v in vals]
        if min(out) < 1:
            raise Reject(key.decode())
        return out

    sizes = counts_of(b"SIZE", None)
    counts = counts_of(b"COUNT", [1] * nf)
    types = [t.upper() for t in entries[b"TYPE"]]
    if len(types) != nf or any((t, s) not in _PCD_TYPES for t, s in zip(types, sizes)):
        raise Reject("TYPE/SIZE")
    kinds = [_PCD_TYPES[(t, s)] for t, s in zip(types, sizes)]
    record = sum(s * c for s, c in zip(sizes, counts))
    if record > _MAX_RECORD_BYTES:
        raise Reject("record too large")
    dims = []
    for key in (b"WIDTH", b"HEIGHT", b"POINTS"):
        vals = entries[key]
        if len(vals) != 1 or not is_integer(vals[0], signed=False):
            raise Reject(key.decode())
        dims.append(int(vals[0]))
    width, height, n = dims
    if width > _MAX_DIM or height > _MAX_DIM or n != width * height:
        raise Reject("WIDTH/HEIGHT/POINTS")
    viewpoint = np.array([0, 0, 0, 1, 0, 0, 0], dtype=np.float64)
    if b"VIEWPOINT" in entries:
        vals = entries[b"VIEWPOINT"]
        if len(vals) != 7:
            raise Reject("VIEWPOINT")
        viewpoint = np.array([ref_float(v) for v in vals], dtype=np.float64)
    data = entries[b"DATA"]
    if len(data) != 1 or data[0].lower() not in (b"ascii", b"binary", b"binary_compressed"):
        raise Reject("DATA")
    encoding = data[0].lower()
    body = raw[pos:]

    columns: list[np.ndarray] = []
    if encoding == b"ascii":
        rows: list[list[bytes]] = []
        for line in body.split(b"\n"):
            toks = line.split()
            if not toks:
                continue
            if len(rows) == n:
                raise Reject("data after POINTS lines")
            if len(toks) != sum(counts):
                raise Reject("token count")
            rows.append(toks)
        if len(rows) != n:
            raise Reject("too few lines")
        start = 0
        for (dtype, _), c in zip(kinds, counts):
            vals: list[Any] = []
            for row in rows:
                for tok in row[start : start + c]:
                    if np.dtype(dtype).kind == "f":
                        v = ref_float(tok, nan=True, inf=True)
                        if dtype is np.float32:
                            with np.errstate(over="ignore"):
                                if math.isfinite(v) and math.isinf(np.float32(v)):
                                    raise Reject("float32 overflow")
                        vals.append(v)
                    else:
                        if not is_integer(tok):
                            raise Reject(f"not an integer {tok!r}")
                        v = int(tok)
                        info = np.iinfo(dtype)
                        if not info.min <= v <= info.max:
                            raise Reject("integer out of range")
                        vals.append(v)
            with np.errstate(over="ignore"):
                columns.append(np.array(vals, dtype=dtype).reshape(n, c))
            start += c
    elif encoding == b"binary":
        if len(body) != n * record:
            raise Reject(f"binary payload {len(body)} != {n} * {record}")
        fmt = "<" + "".join(f"{c}{code}" for (_, code), c in zip(kinds, counts))
        flat = list(struct.iter_unpack(fmt, body)) if n else []
        start = 0
        for (dtype, _), c in zip(kinds, counts):
            vals = [v for row in flat for v in row[start : start + c]]
            columns.append(np.array(vals, dtype=dtype).reshape(n, c))
            start += c
    else:
        if len(body) < 8:
            raise Reject("no size header")
        csize, usize = struct.unpack("<II", body[:8])
        if usize != n * record or len(body) != 8 + csize:
            raise Reject("compressed/uncompressed size")
        plain = ref_lzf(body[8:], usize)
        off = 0
        for (dtype, code), s, c in zip(kinds, sizes, counts):
            vals = struct.unpack(f"<{n * c}{code}", plain[off : off + n * s * c])
            columns.append(np.array(vals, dtype=dtype).reshape(n, c))
            off += n * s * c
    fields = {}
    for nm, c, col in zip(names, counts, columns):
        if nm != b"_":
            shape = (height, width, c) if c > 1 else (height, width)
            fields[nm.decode("ascii")] = col.reshape(shape)
    return {"fields": fields, "width": width, "height": height, "viewpoint": viewpoint}


def compare_pcd(got, want) -> None:
    assert (got.width, got.height) == (want["width"], want["height"]), "width/height"
    assert list(got.fields) == list(want["fields"]), "field names"
    for nm, arr in want["fields"].items():
        assert_same_array(got[nm], arr, nm)
    assert_same_array(got.viewpoint, want["viewpoint"], "viewpoint")


def ref_synpeb(raw: bytes) -> tuple[np.ndarray, np.ndarray]:
    cloud = ref_pcd(raw)
    f = cloud["fields"]
    if any(k not in f or f[k].ndim != 2 for k in ("x", "y", "z", "intensity")):
        raise Reject("SynPEB fields")
    if cloud["height"] <= 1:
        raise Reject("not organized")
    pts = np.stack([f[k].astype(np.float64) for k in "xyz"], axis=-1)
    valid = np.isfinite(pts).all(axis=-1)
    lab = f["intensity"].astype(np.float64)
    good = np.isfinite(lab) & (lab >= 0) & (lab == np.floor(lab))
    if (valid & ~good).any():
        raise Reject("bad label")
    return pts, np.where(valid & good, lab, 0).astype(np.int64)


def compare_synpeb(got, want) -> None:
    assert_same_array(got[0], want[0], "points")
    assert_same_array(got[1], want[1], "labels")


def _synpeb_file() -> bytes:
    return fetch("synpeb-test-100").read_bytes()


def _pcd_header_span(raw: bytes) -> int:
    return raw.index(b"\nDATA") + 20


def _synpeb_crop_bytes(rows: int) -> bytes:
    """The first ``rows`` rows of the shared cloud, as real file bytes (header edited)."""
    raw = _synpeb_file()
    cut = raw.index(b"\n", raw.index(b"\nDATA") + 1) + 1
    header, body = raw[:cut], raw[cut:]
    lines = body.split(b"\n")[: rows * 100]
    header = header.replace(b"HEIGHT 100", b"HEIGHT %d" % rows)
    header = header.replace(b"POINTS 10000", b"POINTS %d" % (rows * 100))
    return header + b"\n".join(lines) + b"\n"


def _mixed_cloud() -> dict[str, np.ndarray]:
    """Small organized cloud with every kind of field: ints, COUNT 3, float64, padding-free."""
    rng = np.random.default_rng(7)
    shape = (3, 4)
    return {
        "x": rng.normal(size=shape).astype(np.float32),
        "t": rng.uniform(0, 1e6, size=shape),
        "ring": rng.integers(0, 32, size=shape, dtype=np.uint16),
        "id": rng.integers(-1000, 1000, size=shape, dtype=np.int32),
        "flag": rng.integers(0, 256, size=shape, dtype=np.uint8),
        "normal": rng.normal(size=(*shape, 3)).astype(np.float32),
    }


def test_reference_pcd_reads_the_shared_file():
    """The reference agrees with the README's description of the shared crop."""
    cloud = ref_pcd(_synpeb_file())
    assert (cloud["height"], cloud["width"]) == (100, 100)
    assert list(cloud["fields"]) == ["x", "y", "z", "intensity"]
    assert np.unique(cloud["fields"]["intensity"]).size == 13
    assert ref_lzf(bytes([0x02, *b"abc", 0xC0, 0x02]), 11) == b"abcabcabcab"


@pytest.mark.slow  # > 5 s: runs in make test-slow / CI
def test_fuzz_synpeb_shared_file(tmp_path):
    """The full shared ASCII file: ``read_pcd`` and ``load_synpeb_pcd`` on the same mutants."""
    raw = _synpeb_file()
    hot = [(0, _pcd_header_span(raw)), (len(raw) - 200, len(raw))]

    def both(path):
        return read_pcd(path), load_synpeb_pcd(path)

    def ref_both(data):
        return ref_pcd(data), ref_synpeb(data)

    def compare(got, want):
        compare_pcd(got[0], want[0])
        compare_synpeb(got[1], want[1])

    fuzz(tmp_path, "test_100.pcd", raw, both, ref_both, compare, 40, seed=1, hot=hot, text=True)


def _pcd_seed(kind: str, data: str, tmp_path: Path) -> bytes:
    if kind == "synpeb-crop":
        crop = _synpeb_crop_bytes(8)
        if data == "ascii":
            return crop  # real bytes, only HEIGHT/POINTS edited
        fields = {k: ref_pcd(crop)["fields"][k] for k in ("x", "y", "z", "intensity")}
    else:
        fields = _mixed_cloud()
    return write_pcd(tmp_path / "seed.pcd", fields, data=data).read_bytes()


@pytest.mark.parametrize("kind", ["synpeb-crop", "mixed"])
@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
def test_fuzz_pcd(tmp_path, kind, data):
    raw = _pcd_seed(kind, data, tmp_path)
    hot = [(0, _pcd_header_span(raw)), (len(raw) - 40, len(raw))]
    fuzz(
        tmp_path,
        f"{kind}.pcd",
        raw,
        read_pcd,
        ref_pcd,
        compare_pcd,
        250,
        seed=11 + len(kind) + 3 * len(data),
        hot=hot,
        text=data == "ascii",
    )


@pytest.mark.slow
@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
def test_fuzz_pcd_sweep(tmp_path, data):
    raw = _pcd_seed("synpeb-crop", data, tmp_path)
    hot = [(0, _pcd_header_span(raw))]
    fuzz(
        tmp_path,
        "sweep.pcd",
        raw,
        read_pcd,
        ref_pcd,
        compare_pcd,
        800,
        seed=100 + len(data),
        hot=hot,
        text=data == "ascii",
    )


# ==========================================================================================
# CARMEN
# ==========================================================================================

_RES = b"laser_front_laser_resolution"
_MAXR = b"robot_front_laser_max"


def ref_carmen(raw: bytes) -> dict[str, Any]:
    """Independent CARMEN parser following the shared data README."""
    if raw[:2] == b"\x1f\x8b":
        try:
            raw = gzip.decompress(raw)
        except Exception as exc:  # noqa: BLE001
            raise Reject(f"gzip: {exc}") from None
    res = maxr = None
    n_beams = None
    rows = []
    for line in raw.split(b"\n"):
        if not (line.startswith(b"FLASER") or line.startswith(b"PARAM")):
            continue
        toks = line.split()
        if toks[0] == b"PARAM":
            if len(toks) >= 2 and toks[1] in (_RES, _MAXR):
                if len(toks) < 3:
                    raise Reject("PARAM without value")
                v = ref_float(toks[2])
                if not v > 0 or (toks[1] == _RES and v > 360):
                    raise Reject("PARAM value")
                if toks[1] == _RES:
                    res = v
                else:
                    maxr = v
            continue
        if toks[0] != b"FLASER":
            continue
        if len(toks) < 2 or not is_integer(toks[1], signed=False) or int(toks[1]) == 0:
            raise Reject("beam count")
        n = int(toks[1])
        if n_beams is not None and n != n_beams:
            raise Reject("beam count changes")
        n_beams = n
        if len(toks) != n + 11:
            raise Reject("token count")
        vals = [ref_float(t, nan=True, inf=True) for t in toks[2 : n + 9] + [toks[-1]]]
        if not all(math.isfinite(v) for v in vals) or min(vals[:n]) < 0:
            raise Reject("value")
        rows.append(vals)
    if not rows:
        raise Reject("no scans")
    fov_deg = 180.0 if res is None else res * (n_beams - 1)
    if not fov_deg <= 360.0:
        raise Reject("field of view")
    fov = math.radians(fov_deg)
    if n_beams > 1:
        az = [-fov / 2 + i * fov / (n_beams - 1) for i in range(n_beams)]
    else:
        az = [0.0]
    data = np.array(rows, dtype=np.float64)
    max_range = float(data[:, :n_beams].max())
    usable = max_range * (1.0 - 0.02)
    if maxr is not None:
        usable = min(usable, maxr)
    return {
        "ranges_m": data[:, :n_beams],
        "poses": data[:, n_beams : n_beams + 3],
        "odometry": data[:, n_beams + 3 : n_beams + 6],
        "timestamps_s": data[:, n_beams + 6],
        "azimuths_rad": np.array(az),
        "max_range_m": max_range,
        "usable_range_m": usable,
    }


def compare_carmen(got, want) -> None:
    for key in ("ranges_m", "poses", "odometry", "timestamps_s"):
        assert_same_array(getattr(got, key), want[key], key)
    assert got.azimuths_rad.shape == want["azimuths_rad"].shape, "azimuths"
    np.testing.assert_allclose(got.azimuths_rad, want["azimuths_rad"], rtol=0, atol=1e-12)
    assert got.max_range_m == want["max_range_m"], "max_range_m"
    assert got.usable_range_m == want["usable_range_m"], "usable_range_m"


def _carmen_head(name: str, n_scans: int) -> bytes:
    """The real log up to and including its ``n_scans``-th FLASER line (decompressed)."""
    raw = gzip.decompress(fetch(name).read_bytes())
    pos = 0
    for _ in range(n_scans):
        pos = raw.index(b"\nFLASER", pos) + 1
    return raw[: raw.index(b"\n", pos) + 1]


def _carmen_fuzz(tmp_path, name: str, n: int, seed: int) -> None:
    head = _carmen_head(name, 3)
    hot = line_spans(head, lambda ln: ln.startswith(b"FLASER") or _RES in ln or _MAXR in ln, 24, 90)
    fuzz(
        tmp_path,
        f"{name}.log",
        head,
        load_carmen,
        ref_carmen,
        compare_carmen,
        n,
        seed=seed,
        hot=hot,
        text=True,
    )
    # A few mutants of the gzip stream itself (mostly caught by the CRC, some header bytes not).
    zipped = gzip.compress(head, mtime=0)
    fuzz(
        tmp_path,
        f"{name}.log.gz",
        zipped,
        load_carmen,
        ref_carmen,
        compare_carmen,
        n // 10,
        seed=seed + 1,
        hot=[(0, 12), (len(zipped) - 8, len(zipped))],
    )


@pytest.mark.parametrize("name", ["csail", "intel", "orebro"])
def test_fuzz_carmen(tmp_path, name):
    _carmen_fuzz(tmp_path, name, 400, seed=20 + len(name))


@pytest.mark.slow
@pytest.mark.parametrize(
    "name",
    [
        "acapulco",
        "belgioioso",
        "edmonton",
        "fhw",
        "freiburg-079",
        "freiburg-101",
        "freiburg-campus",
        "infinite-corridor",
    ],
)
def test_fuzz_carmen_sweep(tmp_path, name):
    _carmen_fuzz(tmp_path, name, 300, seed=40 + len(name))


# ==========================================================================================
# KITTI: poses, times, calib.txt, velodyne .bin (and the urban trajectory built on poses)
# ==========================================================================================


def _ref_rows(raw: bytes, n_cols: int) -> np.ndarray:
    rows = []
    for line in raw.split(b"\n"):
        toks = line.split()
        if not toks or toks[0].startswith(b"#"):
            continue
        if len(toks) != n_cols:
            raise Reject("column count")
        vals = [ref_float(t, nan=True, inf=True) for t in toks]
        if not all(math.isfinite(v) for v in vals):
            raise Reject("not finite")
        rows.append(vals)
    if not rows:
        raise Reject("no rows")
    return np.array(rows, dtype=np.float64)


def ref_kitti_poses(raw: bytes) -> np.ndarray:
    mats = _ref_rows(raw, 12).reshape(-1, 3, 4)
    out = np.zeros((len(mats), 4, 4))
    for k, m in enumerate(mats):
        sv = np.linalg.svd(m[:, :3], compute_uv=False)
        if np.abs(sv - 1).max() > 1e-3 or np.linalg.det(m[:, :3]) < 0:
            raise Reject("not a rotation")
        out[k, :3, :3] = scipy.linalg.polar(m[:, :3])[0]  # nearest orthogonal matrix
        out[k, :3, 3] = m[:, 3]
        out[k, 3, 3] = 1.0
    return out


def compare_poses(got, want) -> None:
    assert got.shape == want.shape, "shape"
    assert_same_array(got[:, :3, 3], want[:, :3, 3], "translations")
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def _head_lines(path: Path, n: int) -> bytes:
    return b"".join(path.read_bytes().splitlines(keepends=True)[:n])


def test_fuzz_kitti_poses_and_urban_trajectory(tmp_path):
    seed = _head_lines(fetch("kitti-00-poses"), 30)
    hot = line_spans(seed, lambda ln: True, 16, 16)
    camera_to_ground = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])

    def read(path):
        return load_kitti_poses(path, as_matrix=True), load_urban_trajectory(path)

    def ref(data):
        mats = ref_kitti_poses(data)
        pos = mats[:, :3, 3] @ camera_to_ground.T
        fwd = mats[:, :3, 2] @ camera_to_ground.T
        return mats, np.column_stack([pos[:, :2], np.arctan2(fwd[:, 1], fwd[:, 0])])

    def compare(got, want):
        compare_poses(got[0], want[0])
        np.testing.assert_allclose(got[1].xy_yaw, want[1], rtol=0, atol=1e-9)
        np.testing.assert_allclose(got[1].times_s, 0.1 * np.arange(len(want[1])), atol=1e-12)

    fuzz(tmp_path, "poses.txt", seed, read, ref, compare, 500, seed=3, hot=hot, text=True)


def test_fuzz_kitti_times(tmp_path):
    seed = _head_lines(fetch("kitti-00-times"), 60)

    def compare(got, want):
        assert_same_array(got, want, "times")

    fuzz(
        tmp_path,
        "times.txt",
        seed,
        load_kitti_times,
        lambda d: _ref_rows(d, 1)[:, 0],
        compare,
        500,
        seed=4,
        text=True,
    )


_CALIB = b"".join(
    [
        b"P0: 7.188560e+02 0.000000e+00 6.071928e+02 0.000000e+00 0.000000e+00 7.188560e+02 "
        b"1.852157e+02 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00\n",
        b"P1: 7.188560e+02 0.000000e+00 6.071928e+02 -3.861448e+02 0.000000e+00 7.188560e+02 "
        b"1.852157e+02 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00\n",
        b"Tr: 4.276802e-04 -9.999672e-01 -8.084491e-03 -1.198459e-02 -7.210626e-03 "
        b"8.081198e-03 -9.999413e-01 -5.403984e-02 9.999738e-01 4.859485e-04 -7.206933e-03 "
        b"-2.921968e-01\n",
    ]
)


def ref_calib(raw: bytes) -> np.ndarray | None:
    for line in raw.split(b"\n"):
        key, sep, rest = line.partition(b":")
        if not sep or key.strip() != b"Tr":
            continue
        toks = rest.split()
        if len(toks) != 12:
            raise Reject("Tr values")
        vals = [ref_float(t, nan=True, inf=True) for t in toks]
        if not all(math.isfinite(v) for v in vals):
            raise Reject("Tr not finite")
        mat = np.eye(4)
        mat[:3] = np.array(vals).reshape(3, 4)
        return mat
    return None


def test_fuzz_kitti_calib(tmp_path):
    root = tmp_path / "kitti"
    seq = root / "sequences" / "00"
    (seq / "velodyne").mkdir(parents=True)
    (root / "poses").mkdir()
    for k in range(3):
        (seq / "velodyne" / f"{k:06d}.bin").write_bytes(struct.pack("<4f", k, 0, 0, 0))
    (root / "poses" / "00.txt").write_bytes(_head_lines(fetch("kitti-00-poses"), 3))

    def write(path, data):
        (seq / "calib.txt").write_bytes(data)
        return seq / "calib.txt"

    def read(path):
        s = load_kitti_sequence(root, "00")
        return s.T_cam_velo, s.has_calibration

    def ref(data):
        mat = ref_calib(data)
        return (np.eye(4), False) if mat is None else (mat, True)

    def compare(got, want):
        assert got[1] == want[1], "has_calibration"
        assert_same_array(got[0], want[0], "T_cam_velo")

    hot = line_spans(_CALIB, lambda ln: ln.startswith(b"Tr"), 8, 20)
    fuzz(
        tmp_path, "calib", _CALIB, read, ref, compare, 500, seed=5, hot=hot, text=True, write=write
    )


def _kitti_scan_bytes() -> bytes:
    """A small scan in the KITTI layout: a ring of returns with a few zero-range points."""
    rng = np.random.default_rng(8)
    az = np.linspace(-np.pi, np.pi, 64, endpoint=False)
    r = rng.uniform(2, 40, size=64)
    pts = [(r[i] * np.cos(a), r[i] * np.sin(a), -1.73, rng.uniform(0, 1)) for i, a in enumerate(az)]
    pts[5] = (0.0, 0.0, 0.0, 0.0)
    return b"".join(struct.pack("<4f", *p) for p in pts)


def ref_kitti_bin(raw: bytes) -> np.ndarray:
    if len(raw) % 16:
        raise Reject("size")
    pts = np.array(list(struct.iter_unpack("<4f", raw)), dtype=np.float32).reshape(-1, 4)
    if not np.isfinite(pts).all():
        raise Reject("not finite")
    return pts


def test_fuzz_kitti_velodyne(tmp_path):
    fuzz(
        tmp_path,
        "000000.bin",
        _kitti_scan_bytes(),
        read_kitti_velodyne,
        ref_kitti_bin,
        lambda g, w: assert_same_array(g, w, "points"),
        500,
        seed=6,
    )


# ==========================================================================================
# NCLT: velodyne_sync, velodyne_hits, ground truth
# ==========================================================================================


def _hits(n: int, seed: int) -> bytes:
    rng = np.random.default_rng(seed)
    return b"".join(
        struct.pack(
            "<HHHBB",
            *(int(v) for v in rng.integers(18000, 24000, size=3)),
            int(rng.integers(256)),
            int(rng.integers(32)),
        )
        for _ in range(n)
    )


def _ref_hits(raw: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    vals = list(struct.iter_unpack("<HHHBB", raw))
    pts = np.array(
        [[v[0] * 0.005 - 100.0, v[1] * 0.005 - 100.0, v[2] * 0.005 - 100.0] for v in vals],
        dtype=np.float64,
    ).reshape(-1, 3)
    inten = np.array([v[3] for v in vals], dtype=np.uint8)
    lid = np.array([v[4] for v in vals], dtype=np.uint8)
    return pts, inten, lid


def ref_nclt_sync(raw: bytes):
    if len(raw) % 8:
        raise Reject("size")
    return _ref_hits(raw)


def compare_hits(got, want) -> None:
    for name, g, w in zip(("points", "intensity", "laser_id"), got, want):
        assert_same_array(g, w, name)


def test_fuzz_nclt_sync(tmp_path):
    fuzz(
        tmp_path,
        "1326030975726043.bin",
        _hits(40, 9),
        read_nclt_velodyne_sync,
        ref_nclt_sync,
        compare_hits,
        500,
        seed=7,
    )


def _packet(utime: int, n: int, seed: int) -> bytes:
    return struct.pack("<4HIQ4x", 44444, 44444, 44444, 44444, n, utime) + _hits(n, seed)


def ref_nclt_hits(raw: bytes) -> list[tuple[int, tuple]]:
    out = []
    pos = 0
    while pos < len(raw):
        if len(raw) - pos < 8 or raw[pos : pos + 8] != b"\x9c\xad" * 4:
            raise Reject("magic")
        if len(raw) - pos < 24:
            raise Reject("short header")
        n, utime = struct.unpack_from("<IQ", raw, pos + 8)
        if utime > 2**63 - 1:
            raise Reject("utime")
        if len(raw) - pos - 24 < 8 * n:
            raise Reject("short packet")
        out.append((utime, _ref_hits(raw[pos + 24 : pos + 24 + 8 * n])))
        pos += 24 + 8 * n
    return out


def compare_packets(got, want) -> None:
    assert len(got) == len(want), f"{len(got)} packets, reference {len(want)}"
    for g, (utime, hits) in zip(got, want):
        assert int(g.utime) == utime, "utime"
        compare_hits((g.points, g.intensity, g.laser_id), hits)


def test_fuzz_nclt_hits(tmp_path):
    raw = _packet(1326030975726043, 6, 1) + _packet(1326030975727043, 0, 2)
    raw += _packet(1326030975728043, 9, 3)
    hot = [(0, 24), (72, 96), (96, 120)]
    fuzz(
        tmp_path,
        "velodyne_hits.bin",
        raw,
        read_nclt_velodyne_hits,
        ref_nclt_hits,
        compare_packets,
        600,
        seed=8,
        hot=hot,
    )


_GT = b"".join(
    [
        b"utime,x,y,z,roll,pitch,yaw\n",
        b"1326030975726043,nan,nan,nan,nan,nan,nan\n",
        b"1326030975826043,-0.0252,0.0118,0.0092,-0.0281,0.0096,-0.0162\n",
        b"1326030975926043,-0.0411,0.0237,0.0088,-0.0279,0.0094,-0.0161\n",
        b"1326030976026043,-0.0563,0.0348,0.0085,-0.0275,0.0091,-0.0158\n",
        b"1326030976126043,-0.0716,0.0461,0.0081,-0.0271,0.0089,-0.0157\n",
        b"1326030976226043,-0.0871,0.0569,0.0079,-0.0268,0.0088,-0.0156\n",
    ]
)


def ref_nclt_gt(raw: bytes):
    utimes, rows = [], []
    header_skipped = False
    for line in raw.split(b"\n"):
        text = line.strip()
        if not text or text.startswith(b"#"):
            continue
        toks = [t.strip() for t in text.split(b",")]
        if len(toks) != 7:
            raise Reject("field count")
        numeric = [is_decimal(t) or _nonfinite_word(t) is not None for t in toks]
        if not rows and not header_skipped and not any(numeric):
            header_skipped = True
            continue
        tok = toks[0]
        if is_integer(tok):
            utime = int(tok)
        elif is_decimal(tok):
            v = float(tok.decode("ascii"))
            if not (math.isfinite(v) and v == math.floor(v) and abs(v) <= 2**53):
                raise Reject("utime not an integer")
            utime = int(v)
        else:
            raise Reject("utime")
        if not -(2**63) <= utime <= 2**63 - 1:
            raise Reject("utime range")
        utimes.append(utime)
        rows.append([ref_float(t, nan=True) for t in toks[1:]])
    if not rows:
        raise Reject("no rows")
    xyz = np.array(rows, dtype=np.float64)
    return np.array(utimes, dtype=np.int64), xyz, ~np.isnan(xyz).any(axis=1)


def compare_gt(got, want) -> None:
    for name, g, w in zip(("utime", "xyz_rpy", "valid"), got, want):
        assert_same_array(g, w, name)


def test_fuzz_nclt_ground_truth(tmp_path):
    hot = line_spans(_GT, lambda ln: True, 20, 10)
    fuzz(
        tmp_path,
        "groundtruth.csv",
        _GT,
        read_nclt_ground_truth,
        ref_nclt_gt,
        compare_gt,
        500,
        seed=9,
        hot=hot,
        text=True,
    )


@pytest.mark.slow
def test_fuzz_binary_sweep(tmp_path):
    """More mutants of the small binary formats."""
    fuzz(
        tmp_path,
        "s.bin",
        _kitti_scan_bytes(),
        read_kitti_velodyne,
        ref_kitti_bin,
        lambda g, w: assert_same_array(g, w, "points"),
        1500,
        seed=60,
    )
    raw = _packet(1326030975726043, 6, 1) + _packet(1326030975727043, 0, 2)
    fuzz(
        tmp_path,
        "h.bin",
        raw,
        read_nclt_velodyne_hits,
        ref_nclt_hits,
        compare_packets,
        1500,
        seed=61,
        hot=[(0, 24), (72, 96)],
    )
