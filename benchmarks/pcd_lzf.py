"""LZF in PCD ``binary_compressed``: the compiled codec (python-lzf) against the pure-Python one.

Data: one SynPEB-style organized scan (:func:`lidarjax.sim.synpeb_scan`, ``"test"`` split,
index 0, 500 x 500 by default) as PCL stores it: fields ``x y z intensity`` (float32, the
label in ``intensity``, NaN where there is no return), laid out field-major exactly as
:func:`lidarjax.datasets.write_pcd` hands them to the LZF encoder (4 MB for 500 x 500).

Measured, for each codec (``python-lzf``: liblzf through the ``lzf`` module; ``pure-python``:
the fallback codec of :mod:`lidarjax.datasets._pcd`), both timed in the same run:

1. encode: seconds per call and MB/s of uncompressed data, compressed size and ratio;
2. decode of the codec's own stream: seconds per call and MB/s of uncompressed data;
3. the whole file: :func:`~lidarjax.datasets.write_pcd` and :func:`~lidarjax.datasets.read_pcd`
   of a ``binary_compressed`` file with the codec selected through ``LIDARJAX_LZF``.

``speedup`` = pure-Python median time / python-lzf median time. Both decoders are checked to
return the input from either encoder's stream. Every timed block records the 1-minute load
average right before it and is rerun after waiting for the load to drop when it was above
0.5 (:mod:`benchmarks._harness`).

Run with ``python benchmarks/pcd_lzf.py [--quick] [--repeats N] [--shape H W] [--out PATH]``.
Results go to ``benchmarks/results/pcd_lzf.json`` (write quick runs elsewhere with ``--out``)
and a Markdown table is printed.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from _harness import (
    RESULTS,
    LoadPolicy,
    add_policy_args,
    machine_info,
    policy_from_args,
    ratio,
    write_json,
)

from lidarjax.datasets import read_pcd, write_pcd
from lidarjax.datasets._pcd import LZF_ENV, _lzf_decode, _lzf_encode
from lidarjax.sim import synpeb_scan

DEFAULT_OUT = RESULTS / "pcd_lzf.json"
BACKENDS = ("python-lzf", "pure-python")

_POLICY = LoadPolicy()


def scan_fields(shape: tuple[int, int]) -> dict[str, np.ndarray]:
    """``x y z intensity`` float32 fields of a SynPEB-style scan (SynPEB's PCD layout)."""
    scan = synpeb_scan("test", 0, shape=shape)
    pts = scan.points.astype(np.float32)
    return {
        "x": pts[..., 0],
        "y": pts[..., 1],
        "z": pts[..., 2],
        "intensity": scan.labels.astype(np.float32),
    }


def field_major(fields: dict[str, np.ndarray]) -> bytes:
    """The bytes ``write_pcd`` compresses: each field's little-endian values in turn."""
    return b"".join(a.astype(a.dtype.newbyteorder("<")).tobytes() for a in fields.values())


def bench_codecs(plain: bytes, repeats: int) -> dict:
    mb = len(plain) / 1e6
    out: dict = {"uncompressed_bytes": len(plain)}
    streams = {}
    for backend in BACKENDS:
        enc, stream = _POLICY.time_calls(
            f"encode {backend}",
            lambda b=backend: _lzf_encode(plain, b),
            repeats,
            return_output=True,
        )
        streams[backend] = stream
        dec = _POLICY.time_calls(
            f"decode {backend}", lambda b=backend: _lzf_decode(stream, len(plain), b), repeats
        )
        out[backend] = {
            "encode": enc,
            "decode": dec,
            "encode_mb_per_s": mb / enc["median_s"],
            "decode_mb_per_s": mb / dec["median_s"],
            "compressed_bytes": len(stream),
            "compression_ratio": len(plain) / len(stream),
        }
    # Cross-check: every decoder returns the input from every encoder's stream.
    out["cross_decode_ok"] = all(
        _lzf_decode(streams[enc], len(plain), dec) == plain for enc in BACKENDS for dec in BACKENDS
    )
    fast, slow = out["python-lzf"], out["pure-python"]
    out["speedup_encode"] = ratio(slow["encode"]["median_s"], fast["encode"]["median_s"])
    out["speedup_decode"] = ratio(slow["decode"]["median_s"], fast["decode"]["median_s"])
    return out


def bench_files(fields: dict[str, np.ndarray], repeats: int) -> dict:
    out: dict = {}
    old = os.environ.get(LZF_ENV)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "scan.pcd"
        try:
            for backend in BACKENDS:
                os.environ[LZF_ENV] = backend
                write = _POLICY.time_calls(
                    f"write_pcd {backend}",
                    lambda: write_pcd(path, fields, data="binary_compressed"),
                    repeats,
                )
                read = _POLICY.time_calls(f"read_pcd {backend}", lambda: read_pcd(path), repeats)
                out[backend] = {
                    "write_pcd": write,
                    "read_pcd": read,
                    "file_bytes": path.stat().st_size,
                }
        finally:
            if old is None:
                os.environ.pop(LZF_ENV, None)
            else:
                os.environ[LZF_ENV] = old
    fast, slow = out["python-lzf"], out["pure-python"]
    out["speedup_write"] = ratio(slow["write_pcd"]["median_s"], fast["write_pcd"]["median_s"])
    out["speedup_read"] = ratio(slow["read_pcd"]["median_s"], fast["read_pcd"]["median_s"])
    return out


def main() -> None:
    global _POLICY
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="2 timed calls per block")
    ap.add_argument("--repeats", type=int, default=None, help="timed calls per block")
    ap.add_argument("--shape", type=int, nargs=2, default=(500, 500), metavar=("H", "W"))
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    add_policy_args(ap)
    args = ap.parse_args()
    _POLICY = policy_from_args(args)
    repeats = args.repeats or (2 if args.quick else 5)
    t_start = time.perf_counter()
    shape = (int(args.shape[0]), int(args.shape[1]))
    fields = scan_fields(shape)
    plain = field_major(fields)
    res = {
        "machine": machine_info(),
        "quick": args.quick,
        "repeats": repeats,
        "scan": {"split": "test", "index": 0, "shape": list(shape), "fields": list(fields)},
        "codecs": bench_codecs(plain, repeats),
        "files": bench_files(fields, repeats),
    }
    res["load_policy"] = _POLICY.summary()
    res["load_average_end"] = list(os.getloadavg())
    res["wall_time_s"] = time.perf_counter() - t_start
    write_json(args.out, res)

    c, f = res["codecs"], res["files"]
    rows = [
        "| codec | encode MB/s | decode MB/s | ratio | write_pcd s | read_pcd s |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for b in BACKENDS:
        rows.append(
            f"| {b} | {c[b]['encode_mb_per_s']:.1f} | {c[b]['decode_mb_per_s']:.1f} | "
            f"{c[b]['compression_ratio']:.2f} | {f[b]['write_pcd']['median_s']:.3f} | "
            f"{f[b]['read_pcd']['median_s']:.3f} |"
        )
    print(f"\nSynPEB-style scan {shape[0]} x {shape[1]}, {len(plain) / 1e6:.1f} MB uncompressed")
    print("\n".join(rows))
    print(
        f"python-lzf speedup: encode x{c['speedup_encode']:.0f}, decode "
        f"x{c['speedup_decode']:.0f}, write_pcd x{f['speedup_write']:.0f}, read_pcd "
        f"x{f['speedup_read']:.0f}; cross-decode ok: {c['cross_decode_ok']}"
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
