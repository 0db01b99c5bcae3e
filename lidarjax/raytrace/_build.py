"""Build the native ray kernels (``csrc/*.cc``) into a shared library next to this file.

Run as ``python -m lidarjax.raytrace._build`` (``make`` does it on install and whenever a
C++ source changes). It compiles with the XLA FFI headers of the *installed* jaxlib
(``jax.ffi.include_dir()``), so nothing third-party lives in the repository, and records
the source hash, the jaxlib version and the flags in ``_lidarjax_native.json``; the loader
(:mod:`lidarjax.raytrace._native`) uses the library only if both still match.

Portable by default (no ``-march=native``). On x86-64 a second library is built with
``-mavx2`` and 8 float / 4 double lanes per vector (``_lidarjax_native_avx2.so``); the
loader uses it only when the CPU reports AVX2 at run time (``LIDARJAX_NATIVE_ISA=baseline``
forces the baseline library). Both compute the same operations in the same order per ray,
so their results are identical. Set ``LIDARJAX_NATIVE_MARCH=native`` (or any ``-march``
value) to build one library tuned for the build machine instead. ``CXX`` selects the
compiler. Exit status:
0 on success, or when no compiler exists and ``--optional`` is given (the JAX path is then
used, with one warning); 1 when compilation fails.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
SOURCES = sorted((HERE / "csrc").glob("*.cc")) + sorted((HERE / "csrc").glob("*.h"))
LIBRARY = HERE / "_lidarjax_native.so"
LIBRARY_AVX2 = HERE / "_lidarjax_native_avx2.so"
INFO = HERE / "_lidarjax_native.json"
# the AVX2 variant: 32-byte vectors of ray lanes (GCC vector extensions), no FMA
AVX2_FLAGS = ["-mavx2", "-DLIDARJAX_VECTOR_BYTES=32"]
BASE_FLAGS = [
    "-O3",
    "-std=c++17",
    "-shared",
    "-fPIC",
    "-pthread",
    # no fused multiply-add: the JAX path rounds products and sums separately
    "-ffp-contract=off",
    "-fno-math-errno",
]


def source_hash() -> str:
    """SHA-256 over the C++ sources (names and contents)."""
    h = hashlib.sha256()
    for p in SOURCES:
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def jaxlib_version() -> str:
    import jaxlib

    return str(jaxlib.__version__)


def compiler() -> str | None:
    """The C++ compiler to use (``$CXX``, else ``g++``, ``c++``, ``clang++``), or None."""
    cands = [os.environ["CXX"]] if os.environ.get("CXX") else ["g++", "c++", "clang++"]
    for c in cands:
        path = shutil.which(c)
        if path:
            return path
    return None


def flags() -> list[str]:
    """Flags of the baseline library."""
    out = list(BASE_FLAGS)
    march = os.environ.get("LIDARJAX_NATIVE_MARCH")
    if march:
        out.append(f"-march={march}")
    return out


def variants() -> dict[str, tuple[Path, list[str]]]:
    """The libraries to build: name -> (path, flags). ``baseline`` always; ``avx2`` on
    x86-64 unless ``LIDARJAX_NATIVE_MARCH`` asks for one machine-tuned library."""
    out = {"baseline": (LIBRARY, flags())}
    x86 = platform.machine().lower() in ("x86_64", "amd64")
    if x86 and not os.environ.get("LIDARJAX_NATIVE_MARCH"):
        out["avx2"] = (LIBRARY_AVX2, [*flags(), *AVX2_FLAGS])
    return out


def _info() -> dict:
    return {
        "source_sha256": source_hash(),
        "jaxlib": jaxlib_version(),
        "flags": flags(),
        "variants": {k: fl for k, (_, fl) in variants().items()},
    }


def build(verbose: bool = True) -> Path:
    """Compile the libraries (atomically replacing old ones, in parallel) and write the
    info file. Returns the baseline library's path.

    Raises:
        RuntimeError: no compiler, or compilation failed (with the compiler's output).
    """
    import jax

    cxx = compiler()
    if cxx is None:
        raise RuntimeError("no C++ compiler found (install g++, or set CXX)")
    include = jax.ffi.include_dir()
    cc = [str(p) for p in SOURCES if p.suffix == ".cc"]
    with tempfile.TemporaryDirectory(dir=HERE) as tmp:
        jobs = []
        for name, (lib, fl) in variants().items():
            out = Path(tmp) / lib.name
            cmd = [cxx, *fl, "-isystem", include, *cc, "-o", str(out)]
            if verbose:
                print(f"lidarjax: building native ray kernels ({name}):", " ".join(cmd), flush=True)
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            jobs.append((cmd, out, lib, proc))
        failed = []
        for cmd, out, lib, proc in jobs:
            _, err = proc.communicate()
            if proc.returncode != 0:
                failed.append(f"native build failed ({' '.join(cmd)}):\n{err[-4000:]}")
        if failed:
            raise RuntimeError("\n".join(failed))
        for _, out, lib, _ in jobs:
            os.replace(out, lib)
    info = {**_info(), "compiler": cxx}
    INFO.write_text(json.dumps(info, indent=2) + "\n")
    return LIBRARY


def up_to_date() -> bool:
    """Whether the built libraries match the current sources, jaxlib and flags."""
    if not INFO.exists() or not all(lib.exists() for lib, _ in variants().values()):
        return False
    try:
        info = json.loads(INFO.read_text())
    except (OSError, ValueError):
        return False
    want = _info()
    return all(info.get(k) == v for k, v in want.items())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--optional", action="store_true", help="exit 0 when no compiler exists")
    ap.add_argument("--force", action="store_true", help="rebuild even if up to date")
    args = ap.parse_args(argv)
    if up_to_date() and not args.force:
        print("lidarjax: native ray kernels are up to date")
        return 0
    if compiler() is None:
        msg = (
            "lidarjax: no C++ compiler found; the native ray kernels are not built and the "
            "pure-JAX path is used (install g++ and rerun `make` for the fast path)"
        )
        print(msg, file=sys.stderr)
        return 0 if args.optional else 1
    try:
        build()
    except RuntimeError as e:
        print(f"lidarjax: {e}", file=sys.stderr)
        return 1
    print(f"lidarjax: built {LIBRARY}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
