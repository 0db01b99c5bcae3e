"""Grid maps out (and back in): ROS ``map_server`` YAML + PGM, and lidarjax ``.npz`` map files.

**ROS map_server.** A map is a YAML file next to an 8-bit grey image (here always a binary
``P5`` PGM) as ROS 1 ``map_server`` / ROS 2 ``nav2_map_server`` load it::

    image: intel.pgm          # relative to the YAML file
    mode: trinary             # trinary | scale | raw
    resolution: 0.1           # m per pixel
    origin: [-20.0, -30.0, 0.0]   # x (m), y (m), yaw (rad) of the lower-left pixel's corner
    negate: 0
    occupied_thresh: 0.65
    free_thresh: 0.196

Image row 0 is the *top* of the map (largest y), column 0 the left (smallest x). A pixel value
``p`` (0..255) stands for the occupancy ``occ = (255 - p) / 255`` (``p / 255`` with
``negate: 1``); ``trinary`` maps it to occupied (``occ > occupied_thresh``), free
(``occ < free_thresh``) or unknown; ``scale`` keeps the values in between (unknown needs an
alpha channel, which a PGM does not have); ``raw`` reads ``p`` as the occupancy in percent
(``p > 100``: unknown).

Index order. lidarjax grid arrays are indexed ``[ix, iy]`` (x first, ``GridSpec.shape =
(nx, ny)``, cell ``(ix, iy)`` covering ``origin + [ix, ix + 1) * resolution`` in x), the
image ``[row, col]`` with row 0 on top, so ``pixels = occupancy.T[::-1]`` and
``occupancy = pixels[::-1].T``. The functions here take and return lidarjax order; only
:attr:`MapServerMap.pixels` is in image order. ``GridSpec.origin`` is the ROS ``origin``
(both are the lower corner of cell ``(0, 0)``).

**.npz map files** (:func:`save_grid_map` / :func:`load_grid_map`) store any set of grid
arrays with the grid geometry, a model name, JSON metadata and a format version, loaded
with ``allow_pickle=False``.

NumPy only (PyYAML, a dependency of Hydra, parses the YAML); nothing here imports JAX: a
``GridSpec`` (or any object with ``origin``, ``resolution`` and ``shape``) is read through
``np.asarray``.

Length (~900 lines): the two map file formats share the grid-geometry arguments (plain
``origin``/``resolution`` or a duck-typed ``spec=``); every YAML key, PGM header field and
``.npz`` key is validated so that a damaged file is a ``DatasetFormatError``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ._errors import DatasetFormatError

__all__ = [
    "GRID_MAP_FORMAT_VERSION",
    "GridMapFile",
    "MapServerMap",
    "load_grid_map",
    "occupancy_from_decay_rate",
    "occupancy_from_reflection",
    "read_map_server",
    "save_grid_map",
    "write_map_server",
]

_YAML_FORMAT = (
    "map_server YAML with image, resolution, origin [x, y, yaw], occupied_thresh, "
    "free_thresh (optional negate 0/1, mode trinary|scale|raw)"
)
_PGM_FORMAT = "PGM image: 'P5' (binary) or 'P2' (ASCII), width, height, maxval 1..65535"
_MODES = ("trinary", "scale", "raw")
_PGM_SEPARATOR = re.compile(rb"\s(?:\s|#[^\n\r]*)*")  # comments run to the end of the line
_PGM_NUMBER = re.compile(rb"[0-9]+")

# map_saver's pixel values for the three trinary classes (negate: 0)
_SAVER_OCCUPIED, _SAVER_FREE, _SAVER_UNKNOWN = 0, 254, 205


# --------------------------------------------------------------------------------------
# Grid geometry: plain arguments or a duck-typed GridSpec
# --------------------------------------------------------------------------------------


def _geometry(
    spec: Any, origin: Any, resolution: Any, *, origin_name: str
) -> tuple[np.ndarray, float, tuple[int, ...] | None]:
    """``(origin [d], resolution, shape or None)`` from ``spec=`` or the plain arguments."""
    if spec is not None:
        if origin is not None or resolution is not None:
            raise ValueError(f"give either spec or {origin_name} and resolution, not both")
        try:
            origin = np.asarray(spec.origin, dtype=np.float64)
            resolution = np.asarray(spec.resolution, dtype=np.float64)
            shape = tuple(int(s) for s in spec.shape)
        except AttributeError:
            raise ValueError(
                "spec must have origin, resolution and shape attributes (a GridSpec), got "
                f"{type(spec).__name__}"
            ) from None
    else:
        if origin is None or resolution is None:
            raise ValueError(f"give {origin_name} and resolution (or spec=)")
        shape = None
    o = np.asarray(origin, dtype=np.float64)
    if o.ndim != 1 or not np.isfinite(o).all():
        raise ValueError(f"{origin_name} must be a finite [d] vector, got {o!r}")
    r = np.asarray(resolution, dtype=np.float64)
    if r.shape != () or not (np.isfinite(r) and r > 0):
        raise ValueError(f"resolution must be a positive finite scalar, got {resolution!r}")
    return o, float(r), shape


def _mask(observed_mask: Any, shape: tuple[int, ...]) -> np.ndarray:
    if observed_mask is None:
        return np.ones(shape, dtype=bool)
    m = np.asarray(observed_mask)
    if m.dtype != np.bool_ or m.shape != shape:
        raise ValueError(
            f"observed_mask must be a bool array of shape {shape}, got dtype {m.dtype} and "
            f"shape {m.shape}"
        )
    return m


# --------------------------------------------------------------------------------------
# Occupancy from lidarjax maps
# --------------------------------------------------------------------------------------


def occupancy_from_reflection(p_ref: Any, observed_mask: Any = None) -> np.ndarray:
    """Occupancy of a reflection map: the reflection probability itself.

    A reflection map holds ``mu_i = H_i / (H_i + M_i)`` (Eq. 7.22), the probability that a
    ray entering cell ``i`` is reflected inside it, which is what ``map_server`` reads as
    occupancy. With the default thresholds a cell is occupied for ``mu_i > 0.65``, free for
    ``mu_i < 0.196`` and unknown in between (trinary mode).

    Args:
        p_ref: ``[*shape]`` reflection probabilities in ``[0, 1]``, e.g.
            ``np.asarray(reflection_map(stats).probs)``.
        observed_mask: bool ``[*shape]``, cells some ray entered, e.g.
            ``np.asarray(stats.hits + stats.misses) > 0``; ``None``: all cells.

    Returns:
        float64 ``[*shape]`` occupancy in ``[0, 1]``, NaN (unknown) where not observed.

    Raises:
        ValueError: an observed value is NaN or outside ``[0, 1]``, or the mask does not
            match (message names the argument).
    """
    p = np.array(p_ref, dtype=np.float64)
    seen = _mask(observed_mask, p.shape)
    bad = seen & ~((p >= 0) & (p <= 1))
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"p_ref must lie in [0, 1] where observed, got {p[idx]} at {idx}")
    p[~seen] = np.nan
    return p


def occupancy_from_decay_rate(
    rates_per_m: Any,
    resolution: float | None = None,
    observed_mask: Any = None,
    *,
    spec: Any = None,
) -> np.ndarray:
    """Occupancy of a decay-rate map: the probability that a ray crossing a cell stops in it.

    A ray travelling the distance ``d`` through a cell of decay rate ``lambda`` is reflected
    with probability ``1 - exp(-lambda d)`` (Eq. 7.3); taking ``d`` as the cell's edge
    (a ray crossing the whole cell parallel to an axis) gives
    ``occ_i = 1 - exp(-lambda_i * resolution)``. With the default thresholds a cell is
    occupied for ``lambda_i > -ln(0.35) / resolution`` (10.5 /m at 0.1 m) and free for
    ``lambda_i < -ln(0.804) / resolution`` (2.18 /m at 0.1 m).

    Args:
        rates_per_m: ``[*shape]`` decay rates ``lambda_i >= 0`` (1/m), e.g.
            ``np.asarray(decay_rate_map(stats).rates)``.
        resolution: cell edge (m); or give ``spec=``.
        observed_mask: bool ``[*shape]``, cells some ray traversed, e.g.
            ``np.asarray(stats.lengths) > 0``; ``None``: all cells.
        spec: a ``GridSpec`` (or any object with ``resolution``) instead of ``resolution``.

    Returns:
        float64 ``[*shape]`` occupancy in ``[0, 1]``, NaN (unknown) where not observed.

    Raises:
        ValueError: an observed rate is negative or NaN, ``resolution`` is not positive, or
            the mask does not match (message names the argument).
    """
    if spec is not None:
        if resolution is not None:
            raise ValueError("give either spec or resolution, not both")
        try:
            resolution = np.asarray(spec.resolution, dtype=np.float64)
        except AttributeError:
            raise ValueError(
                f"spec must have a resolution attribute, got {type(spec).__name__}"
            ) from None
    if resolution is None:
        raise ValueError("give resolution (or spec=)")
    res = np.asarray(resolution, dtype=np.float64)
    if res.shape != () or not (np.isfinite(res) and res > 0):
        raise ValueError(f"resolution must be a positive finite scalar, got {resolution!r}")
    lam = np.array(rates_per_m, dtype=np.float64)
    seen = _mask(observed_mask, lam.shape)
    bad = seen & ~(lam >= 0)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"rates_per_m must be >= 0 where observed, got {lam[idx]} at {idx}")
    with np.errstate(invalid="ignore"):
        occ = -np.expm1(-lam * float(res))  # inf rate -> 1
    occ[~seen] = np.nan
    return occ


# --------------------------------------------------------------------------------------
# map_server: write
# --------------------------------------------------------------------------------------


def _trinary_pixels(occupied_thresh: float, free_thresh: float, negate: bool) -> tuple[int, ...]:
    """Pixel values ``(occupied, free, unknown)`` that ``map_server`` classifies correctly."""

    def occ(p: int) -> float:
        return p / 255.0 if negate else (255 - p) / 255.0

    def pick(preferred: int, ok) -> int:
        if ok(occ(preferred)):
            return preferred
        hits = [p for p in range(256) if ok(occ(p))]
        if not hits:
            raise ValueError(
                f"no 8-bit pixel value falls in this class for occupied_thresh "
                f"{occupied_thresh} and free_thresh {free_thresh}"
            )
        mid = 0.5 * (occupied_thresh + free_thresh)
        return min(hits, key=lambda p: abs(occ(p) - mid))

    flip = (lambda p: 255 - p) if negate else (lambda p: p)
    return (
        pick(flip(_SAVER_OCCUPIED), lambda o: o > occupied_thresh),
        pick(flip(_SAVER_FREE), lambda o: o < free_thresh),
        pick(flip(_SAVER_UNKNOWN), lambda o: free_thresh <= o <= occupied_thresh),
    )


def write_map_server(
    path_yaml: str | os.PathLike[str],
    occupancy: Any,
    *,
    origin_xy: Any = None,
    resolution: float | None = None,
    spec: Any = None,
    occupied_thresh: float = 0.65,
    free_thresh: float = 0.196,
    negate: bool = False,
    mode: Literal["trinary", "scale", "raw"] = "trinary",
) -> Path:
    """Write a 2-D occupancy grid as a ROS ``map_server`` map (YAML + binary PGM).

    The image is written next to the YAML file with the same stem and suffix ``.pgm``
    (``maps/intel.yaml`` -> ``maps/intel.pgm``), 8-bit, row 0 = largest y.

    Pixel values (``negate=False``; with ``negate=True`` every value ``p`` becomes
    ``255 - p``):

    - ``"trinary"``: occupied (``occ > occupied_thresh``) -> 0, free
      (``occ < free_thresh``) -> 254, unknown (NaN or in between) -> 205, as ROS's
      ``map_saver`` writes them (another value if the thresholds would misclassify these).
    - ``"scale"``: ``p = round(255 * (1 - occ))``, so :func:`read_map_server` returns ``occ``
      to within ``0.5 / 255``; a PGM cannot mark unknown cells in this mode (map_server
      needs an alpha channel), so NaN is rejected.
    - ``"raw"``: ``p = round(100 * occ)`` (occupancy in percent, read back to within
      ``0.005``), unknown -> 255.

    Args:
        path_yaml: Output YAML file (overwritten, as is the PGM next to it).
        occupancy: ``[nx ny]`` occupancy probabilities in ``[0, 1]``, NaN = unknown,
            indexed ``[ix, iy]`` like every lidarjax grid array (not image order), e.g.
            from :func:`occupancy_from_decay_rate` or :func:`occupancy_from_reflection`.
        origin_xy: ``[2]`` world coordinates (m) of the lower corner of cell ``(0, 0)``
            (``GridSpec.origin``).
        resolution: Cell edge (m).
        spec: Instead of ``origin_xy`` and ``resolution``: a 2-D ``GridSpec`` (or any object
            with ``origin``, ``resolution``, ``shape``); its shape must be
            ``occupancy.shape``.
        occupied_thresh: ``occupied_thresh`` of the YAML file, in ``(free_thresh, 1)``.
        free_thresh: ``free_thresh`` of the YAML file, in ``(0, occupied_thresh)``.
        negate: Write ``negate: 1`` (white = occupied) and invert the pixels accordingly.
        mode: ``"trinary"`` (default), ``"scale"`` or ``"raw"``.

    Returns:
        The YAML path.

    Raises:
        ValueError: a bad argument (the message names it): occupancy not 2-D, a value
            outside ``[0, 1]`` or infinite, NaN in ``"scale"`` mode, geometry or thresholds
            invalid, ``path_yaml`` ending in ``.pgm``.
    """
    path_yaml = Path(path_yaml)
    if path_yaml.suffix.lower() == ".pgm":
        raise ValueError(f"path_yaml must be the YAML file, not the image: {path_yaml}")
    if mode not in _MODES:
        raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
    occ = np.asarray(occupancy, dtype=np.float64)
    if occ.ndim != 2 or occ.size == 0:
        raise ValueError(f"occupancy must be a non-empty [nx ny] array, got shape {occ.shape}")
    origin, res, shape = _geometry(spec, origin_xy, resolution, origin_name="origin_xy")
    if origin.shape != (2,):
        raise ValueError(f"origin_xy must have shape (2,), got {origin.shape}")
    if shape is not None and shape != occ.shape:
        raise ValueError(f"spec.shape {shape} does not match occupancy.shape {occ.shape}")
    known = ~np.isnan(occ)
    bad = known & ~((occ >= 0) & (occ <= 1))
    if bad.any():
        ix, iy = (int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"occupancy must lie in [0, 1] or be NaN, got {occ[ix, iy]} at {ix, iy}")
    for name, v in (("occupied_thresh", occupied_thresh), ("free_thresh", free_thresh)):
        if not (isinstance(v, int | float) and not isinstance(v, bool) and 0 < v < 1):
            raise ValueError(f"{name} must be a number in (0, 1), got {v!r}")
    if not free_thresh < occupied_thresh:
        raise ValueError(
            f"free_thresh ({free_thresh}) must be below occupied_thresh ({occupied_thresh})"
        )
    if not isinstance(negate, bool | np.bool_):
        raise ValueError(f"negate must be a bool, got {negate!r}")
    negate = bool(negate)

    if mode == "trinary":
        p_occ, p_free, p_unknown = _trinary_pixels(occupied_thresh, free_thresh, negate)
        pix = np.full(occ.shape, p_unknown, dtype=np.uint8)
        pix[known & (occ > occupied_thresh)] = p_occ
        pix[known & (occ < free_thresh)] = p_free
    elif mode == "scale":
        if not known.all():
            ix, iy = (int(i) for i in np.argwhere(~known)[0])
            raise ValueError(
                f"occupancy is NaN at {ix, iy}: mode='scale' cannot mark unknown cells in a "
                "PGM (map_server reads unknown from an alpha channel); use mode='trinary' or "
                "fill them first, e.g. np.nan_to_num(occupancy, nan=0.5)"
            )
        shade = np.rint(255.0 * (occ if negate else 1.0 - occ))
        pix = shade.astype(np.uint8)
    else:  # raw
        pct = np.rint(100.0 * np.where(known, occ, 0.0)).astype(np.int64)
        pct = np.where(known, pct, 255)
        pix = (255 - pct if negate else pct).astype(np.uint8)
    image = np.ascontiguousarray(pix.T[::-1])  # [rows cols], row 0 = largest y

    image_path = path_yaml.with_name(path_yaml.stem + ".pgm")
    rows, cols = image.shape
    header = f"P5\n# CREATOR: lidarjax {res!r} m/pix\n{cols} {rows}\n255\n".encode("ascii")
    image_path.write_bytes(header + image.tobytes())
    text = (
        f"image: {json.dumps(image_path.name)}\n"
        f"mode: {mode}\n"
        f"resolution: {res!r}\n"
        f"origin: [{float(origin[0])!r}, {float(origin[1])!r}, 0.0]\n"
        f"negate: {int(negate)}\n"
        f"occupied_thresh: {float(occupied_thresh)!r}\n"
        f"free_thresh: {float(free_thresh)!r}\n"
    )
    path_yaml.write_text(text, encoding="utf-8")
    return path_yaml


# --------------------------------------------------------------------------------------
# map_server: read
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class MapServerMap:
    """A ROS ``map_server`` map as :func:`read_map_server` reads it.

    Attributes:
        occupancy: float64 ``[nx ny]`` indexed ``[ix, iy]`` (lidarjax order): ``"trinary"``:
            1 (occupied), 0 (free) or NaN (unknown); ``"scale"``: the pixel occupancy
            ``(255 - p) / 255`` (``p / 255`` negated; no unknown cells); ``"raw"``:
            ``p / 100``, NaN for ``p > 100``.
        origin_xy: float64 ``[2]`` lower corner (m) of cell ``(0, 0)``, the YAML origin's x, y
            (``GridSpec.origin``).
        origin_yaw: yaw (rad) of the YAML origin; map_server ignores it (nav2 warns), and so
            do the arrays here.
        resolution: cell edge (m).
        pixels: the image ``[rows cols]`` as stored (row 0 = largest y), uint8 (or uint16
            for a PGM with ``maxval > 255``).
        maxval: the PGM's maximum grey value (255 for 8-bit images).
        mode: ``"trinary"``, ``"scale"`` or ``"raw"``.
        negate: the YAML ``negate`` flag.
        occupied_thresh: the YAML ``occupied_thresh``.
        free_thresh: the YAML ``free_thresh``.
        path: the YAML file.
        image_path: the image file.
    """

    occupancy: np.ndarray
    origin_xy: np.ndarray
    origin_yaw: float
    resolution: float
    pixels: np.ndarray
    maxval: int
    mode: str
    negate: bool
    occupied_thresh: float
    free_thresh: float
    path: Path
    image_path: Path

    @property
    def shape(self) -> tuple[int, int]:
        """``(nx, ny)``, the ``GridSpec.shape`` of the map."""
        return self.occupancy.shape  # type: ignore[return-value]

    def to_occupancy_grid(self) -> np.ndarray:
        """The ``nav_msgs/OccupancyGrid`` values ``nav2_map_server`` publishes for this map.

        ``-1`` unknown, ``0..100`` occupancy in percent: trinary -> 100 / 0 / -1; scale ->
        100 above ``occupied_thresh``, 0 below ``free_thresh``, else
        ``rint(100 (occ - free) / (occupied - free))``; raw -> ``p`` (``-1`` for ``p > 100``).

        Returns:
            int8 ``[nx ny]`` in lidarjax order; ``.T.ravel()`` is the message's ``data``
            (row-major from the lower-left cell).
        """
        shade = self.pixels[::-1].T.astype(np.float64) / self.maxval
        occ = shade if self.negate else 1.0 - shade
        out = np.full(occ.shape, -1, dtype=np.int8)
        if self.mode == "raw":
            v = np.rint(255.0 * (1.0 - occ))
            ok = v <= 100
            out[ok] = v[ok].astype(np.int8)
            return out
        hi, lo = occ > self.occupied_thresh, occ < self.free_thresh
        out[hi] = 100
        out[lo] = 0
        if self.mode == "scale":
            mid = ~(hi | lo)
            frac = (occ[mid] - self.free_thresh) / (self.occupied_thresh - self.free_thresh)
            out[mid] = np.rint(100.0 * frac).astype(np.int8)
        return out


def _pgm_header(data: bytes, path: Path) -> tuple[bytes, list[int], int]:
    """``(magic, [width, height, maxval], raster offset)`` of a PGM, comments skipped."""
    if len(data) < 2 or data[:2] not in (b"P5", b"P2"):
        raise DatasetFormatError(
            path, f"not a PGM image (starts with {data[:2]!r})", expected=_PGM_FORMAT
        )
    pos, values = 2, []
    while len(values) < 3:
        m = _PGM_SEPARATOR.match(data, pos)  # whitespace first: b"P5#c" is not a PGM
        if m is None:
            raise DatasetFormatError(
                path, "header fields must be separated by whitespace", expected=_PGM_FORMAT
            )
        pos = m.end()
        n = _PGM_NUMBER.match(data, pos)
        if n is None:
            raise DatasetFormatError(path, "truncated or malformed header", expected=_PGM_FORMAT)
        values.append(int(n.group()))
        pos = n.end()
    if pos >= len(data) or data[pos : pos + 1] not in (b" ", b"\t", b"\n", b"\r", b"\v", b"\f"):
        raise DatasetFormatError(
            path, "header must end with one whitespace character", expected=_PGM_FORMAT
        )
    return data[:2], values, pos + 1


def _read_pgm(path: Path) -> tuple[np.ndarray, int]:
    """The image ``[rows cols]`` of a P5 or P2 PGM and its maxval."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise DatasetFormatError(path, f"cannot read the image ({exc})") from None
    magic, (width, height, maxval), start = _pgm_header(data, path)
    if width <= 0 or height <= 0 or not 0 < maxval < 65536:
        raise DatasetFormatError(
            path, f"bad size {width}x{height} or maxval {maxval}", expected=_PGM_FORMAT
        )
    n = width * height
    if magic == b"P5":
        dtype = np.dtype(np.uint8) if maxval < 256 else np.dtype(">u2")
        raster = data[start:]
        if len(raster) != n * dtype.itemsize:
            raise DatasetFormatError(
                path,
                f"raster holds {len(raster)} bytes, a {width}x{height} image needs "
                f"{n * dtype.itemsize}",
                expected=_PGM_FORMAT,
            )
        img = np.frombuffer(raster, dtype=dtype).reshape(height, width)
    else:
        tokens = data[start:].split()
        if len(tokens) != n or not all(t.isdigit() for t in tokens):
            raise DatasetFormatError(
                path,
                f"ASCII raster must hold {n} unsigned integers, found {len(tokens)} tokens",
                expected=_PGM_FORMAT,
            )
        img = np.array([int(t) for t in tokens], dtype=np.int64).reshape(height, width)
    if int(img.max()) > maxval:
        raise DatasetFormatError(
            path, f"pixel value {int(img.max())} exceeds maxval {maxval}", expected=_PGM_FORMAT
        )
    return img.astype(np.uint8 if maxval < 256 else np.uint16), maxval


def _yaml_number(path: Path, doc: dict, key: str, *, lo: float, hi: float, strict: bool) -> float:
    v = doc[key]
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise DatasetFormatError(
            path, f"{key} must be a finite number, got {v!r}", expected=_YAML_FORMAT
        )
    v = float(v)
    ok = lo < v < hi if strict else lo <= v <= hi
    interval = f"({lo}, {hi})" if strict else f"[{lo}, {hi}]"
    if not ok:
        raise DatasetFormatError(
            path,
            f"{key} must lie in {interval}, got {v}",
            expected=_YAML_FORMAT,
        )
    return v


def read_map_server(path_yaml: str | os.PathLike[str]) -> MapServerMap:
    """Read a ROS ``map_server`` map (YAML + PGM image) the way map_server interprets it.

    Args:
        path_yaml: The YAML file; its ``image`` is relative to the YAML's folder unless
            absolute. The image must be a PGM (binary ``P5`` or ASCII ``P2``; convert PNG
            maps first, e.g. with ``convert map.png map.pgm``).

    Returns:
        A :class:`MapServerMap` with the occupancy in lidarjax order ``[nx ny]``. For a map
        written by :func:`write_map_server`, ``read(write(x)).occupancy`` equals ``x``:
        trinary -> the classes (1 where ``x > occupied_thresh``, 0 where
        ``x < free_thresh``, NaN otherwise); scale -> ``x`` to within ``0.5 / 255``;
        raw -> ``x`` to within ``0.005``.

    Raises:
        FileNotFoundError: the YAML file or the image does not exist.
        DatasetFormatError: the YAML is not valid YAML, lacks a key, has a bad value, or the
            image is not a valid PGM. The message names the file.
    """
    import yaml  # PyYAML, installed with hydra-core (omegaconf)

    path_yaml = Path(path_yaml)
    text = path_yaml.read_bytes()
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = None if mark is None else mark.line + 1
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise DatasetFormatError(
            path_yaml, f"not valid YAML ({problem})", line=line, expected=_YAML_FORMAT
        ) from None
    if not isinstance(doc, dict):
        raise DatasetFormatError(
            path_yaml,
            f"top level must be a mapping, got {type(doc).__name__}",
            expected=_YAML_FORMAT,
        )
    missing = [
        k
        for k in ("image", "resolution", "origin", "occupied_thresh", "free_thresh")
        if k not in doc
    ]
    if missing:
        raise DatasetFormatError(path_yaml, f"missing keys {missing}", expected=_YAML_FORMAT)
    image = doc["image"]
    if not isinstance(image, str) or not image:
        raise DatasetFormatError(
            path_yaml, f"image must be a file name, got {image!r}", expected=_YAML_FORMAT
        )
    resolution = _yaml_number(path_yaml, doc, "resolution", lo=0.0, hi=math.inf, strict=True)
    origin = doc["origin"]
    if (
        not isinstance(origin, list)
        or len(origin) != 3
        or any(isinstance(v, bool) or not isinstance(v, int | float) for v in origin)
        or not all(math.isfinite(v) for v in origin)
    ):
        raise DatasetFormatError(
            path_yaml,
            f"origin must be 3 finite numbers [x, y, yaw], got {origin!r}",
            expected=_YAML_FORMAT,
        )
    occupied = _yaml_number(path_yaml, doc, "occupied_thresh", lo=0.0, hi=1.0, strict=False)
    free = _yaml_number(path_yaml, doc, "free_thresh", lo=0.0, hi=1.0, strict=False)
    if not free < occupied:
        raise DatasetFormatError(
            path_yaml,
            f"free_thresh {free} must be below occupied_thresh {occupied}",
            expected=_YAML_FORMAT,
        )
    negate = doc.get("negate", 0)
    if negate not in (0, 1) or isinstance(negate, float):
        raise DatasetFormatError(
            path_yaml, f"negate must be 0 or 1, got {negate!r}", expected=_YAML_FORMAT
        )
    mode = doc.get("mode", "trinary")
    if mode not in _MODES:
        raise DatasetFormatError(
            path_yaml, f"mode must be one of {_MODES}, got {mode!r}", expected=_YAML_FORMAT
        )

    image_path = Path(image)
    if not image_path.is_absolute():
        image_path = path_yaml.parent / image_path
    pixels, maxval = _read_pgm(image_path)
    shade = pixels[::-1].T.astype(np.float64) / maxval  # [nx ny], lidarjax order
    occ = shade if negate else 1.0 - shade
    if mode == "trinary":
        out = np.full(occ.shape, np.nan)
        out[occ > occupied] = 1.0
        out[occ < free] = 0.0
    elif mode == "scale":
        out = occ
    else:
        value = np.rint(255.0 * (1.0 - occ))  # the pixel after negation, 0..255
        out = np.where(value <= 100, value / 100.0, np.nan)
    for a in (out, pixels):
        a.flags.writeable = False
    return MapServerMap(
        occupancy=out,
        origin_xy=np.array(origin[:2], dtype=np.float64),
        origin_yaw=float(origin[2]),
        resolution=resolution,
        pixels=pixels,
        maxval=maxval,
        mode=mode,
        negate=bool(negate),
        occupied_thresh=occupied,
        free_thresh=free,
        path=path_yaml,
        image_path=image_path,
    )


# --------------------------------------------------------------------------------------
# .npz grid maps
# --------------------------------------------------------------------------------------

GRID_MAP_FORMAT_VERSION = 1
_NPZ_FORMAT = (
    f"lidarjax grid map .npz (format version <= {GRID_MAP_FORMAT_VERSION}): keys "
    "__format__, __origin__, __resolution__, __shape__, __model__, __meta__ and array/<name>"
)
_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_META_KEYS = ("__format__", "__origin__", "__resolution__", "__shape__", "__model__", "__meta__")


@dataclasses.dataclass(frozen=True)
class GridMapFile:
    """A grid map loaded by :func:`load_grid_map`.

    Attributes:
        arrays: name -> array, each ``[]`` (a per-map scalar such as ``outside_rate``) or
            ``[*shape, ...]``.
        origin: float64 ``[d]`` lower grid corner (m).
        resolution: cell edge (m).
        shape: grid shape ``(nx, ny[, nz])``.
        model: the model name given to :func:`save_grid_map`.
        meta: the JSON metadata given to :func:`save_grid_map` (``{}`` if none).
        format_version: the file's format version.
        path: the file.
    """

    arrays: dict[str, np.ndarray]
    origin: np.ndarray
    resolution: float
    shape: tuple[int, ...]
    model: str
    meta: dict[str, Any]
    format_version: int
    path: Path


def save_grid_map(
    path: str | os.PathLike[str],
    arrays: Mapping[str, Any],
    *,
    origin: Any = None,
    resolution: float | None = None,
    model: str,
    meta: Mapping[str, Any] | None = None,
    spec: Any = None,
) -> Path:
    """Save grid arrays with their geometry as an uncompressed ``.npz`` file.

    Every array is ``[]`` or has the grid shape as its leading axes. For the lidarjax maps::

        save_grid_map(p, {"rates": np.asarray(m.rates),
                          "outside_rate": np.asarray(m.outside_rate)},
                      spec=m.spec, model="decay_rate")          # DecayRateMap
        save_grid_map(p, {"probs": ..., "unknown_prob": ...}, spec=m.spec,
                      model="reflection")                       # ReflectionMap
        save_grid_map(p, {"hits": ..., "lengths": ..., "alpha": ..., "beta": ...},
                      spec=m.spec, model="gamma_posterior")     # GammaPosteriorMap

    Args:
        path: Output file (overwritten; NumPy adds ``.npz`` if missing, the returned path
            includes it).
        arrays: Name -> array; names are identifiers (``[A-Za-z_][A-Za-z0-9_]*``) and
            not ``__dunder__``; dtypes numeric or bool (no objects).
        origin: ``[d]`` lower grid corner (m), ``d`` = 2 or 3.
        resolution: Cell edge (m).
        model: Model name, e.g. ``"decay_rate"``, ``"reflection"``, ``"beta_posterior"``.
        meta: JSON-serialisable metadata (units, the data set, the command), or ``None``.
        spec: Instead of ``origin`` and ``resolution``: a ``GridSpec`` (or any object with
            ``origin``, ``resolution``, ``shape``), which also fixes the grid shape.

    Returns:
        The written path.

    Raises:
        ValueError: a bad argument (the message names it): geometry, no grid-shaped array,
            shapes that disagree, a bad name or dtype, ``meta`` not JSON-serialisable.
    """
    o, res, shape = _geometry(spec, origin, resolution, origin_name="origin")
    d = o.shape[0]
    if d not in (2, 3):
        raise ValueError(f"origin must have 2 or 3 entries, got {d}")
    if not isinstance(model, str) or not model:
        raise ValueError(f"model must be a non-empty string, got {model!r}")
    if meta is None:
        meta = {}
    if not isinstance(meta, Mapping):
        raise ValueError(f"meta must be a dict or None, got {type(meta).__name__}")
    try:
        meta_json = json.dumps(dict(meta), allow_nan=False, sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"meta must be JSON-serialisable: {exc}") from None
    if not isinstance(arrays, Mapping) or not arrays:
        raise ValueError("arrays must be a non-empty dict of name -> array")
    out: dict[str, np.ndarray] = {}
    for name, value in arrays.items():
        if not isinstance(name, str) or not _NAME_RE.fullmatch(name) or name.startswith("__"):
            raise ValueError(f"arrays: bad name {name!r} (identifiers, not __dunder__)")
        a = np.asarray(value)
        if a.dtype.kind not in "biuf":
            raise ValueError(f"arrays[{name!r}] must be numeric or bool, got dtype {a.dtype}")
        if a.ndim:
            if shape is None:
                if a.ndim < d:
                    raise ValueError(
                        f"arrays[{name!r}] has shape {a.shape}, fewer than {d} grid axes"
                    )
                shape = tuple(a.shape[:d])
            if tuple(a.shape[:d]) != shape:
                raise ValueError(
                    f"arrays[{name!r}] has shape {a.shape}; grid arrays must start with the "
                    f"grid shape {shape}"
                )
        out["array/" + name] = a
    if shape is None:
        raise ValueError("arrays holds only scalars; give spec= or at least one grid array")
    if len(shape) != d or any(s <= 0 for s in shape):
        raise ValueError(f"grid shape {shape} does not fit origin {o.tolist()}")
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    np.savez(
        path,
        __format__=np.int64(GRID_MAP_FORMAT_VERSION),
        __origin__=o,
        __resolution__=np.float64(res),
        __shape__=np.asarray(shape, dtype=np.int64),
        __model__=np.str_(model),
        __meta__=np.str_(meta_json),
        **out,
    )
    return path


def load_grid_map(path: str | os.PathLike[str]) -> GridMapFile:
    """Load a file written by :func:`save_grid_map` (``allow_pickle=False``).

    Rebuild a lidarjax map from it, e.g. ``DecayRateMap(spec=GridSpec(f.origin,
    f.resolution, f.shape), rates=jnp.asarray(f.arrays["rates"]),
    outside_rate=jnp.asarray(f.arrays["outside_rate"]))``.

    Args:
        path: The ``.npz`` file.

    Returns:
        A :class:`GridMapFile`.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        DatasetFormatError: not an ``.npz`` archive, a key missing, a value of the wrong
            type or shape (arrays not matching the grid shape), pickled objects, or a newer
            format version than this lidarjax reads. The message names the file.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(path)
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise DatasetFormatError(
                path, "a single .npy array, not an .npz archive", expected=_NPZ_FORMAT
            )
        with z:
            keys = list(z.keys())
            missing = [k for k in _META_KEYS if k not in keys]
            if missing:
                raise DatasetFormatError(path, f"missing keys {missing}", expected=_NPZ_FORMAT)
            raw = {k: z[k] for k in keys}
    except DatasetFormatError:
        raise
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise DatasetFormatError(
            path, f"not a readable .npz archive ({exc})", expected=_NPZ_FORMAT
        ) from None

    def scalar(key: str, kind: str) -> Any:
        v = raw[key]
        if v.shape != () or v.dtype.kind not in kind:
            raise DatasetFormatError(
                path,
                f"{key} must be a scalar of kind {kind!r}, got {v.dtype} {v.shape}",
                expected=_NPZ_FORMAT,
            )
        return v.item()

    version = scalar("__format__", "iu")
    if version > GRID_MAP_FORMAT_VERSION:
        raise DatasetFormatError(
            path,
            f"format version {version} is newer than this lidarjax reads "
            f"({GRID_MAP_FORMAT_VERSION}); update lidarjax",
            expected=_NPZ_FORMAT,
        )
    if version < 1:
        raise DatasetFormatError(path, f"bad format version {version}", expected=_NPZ_FORMAT)
    origin = raw["__origin__"]
    if (
        origin.dtype.kind != "f"
        or origin.shape not in ((2,), (3,))
        or not np.isfinite(origin).all()
    ):
        raise DatasetFormatError(
            path, f"__origin__ must be 2 or 3 finite floats, got {origin!r}", expected=_NPZ_FORMAT
        )
    resolution = float(scalar("__resolution__", "f"))
    if not (math.isfinite(resolution) and resolution > 0):
        raise DatasetFormatError(
            path, f"__resolution__ must be positive, got {resolution}", expected=_NPZ_FORMAT
        )
    shape_arr = raw["__shape__"]
    if (
        shape_arr.dtype.kind not in "iu"
        or shape_arr.shape != origin.shape
        or (shape_arr <= 0).any()
    ):
        raise DatasetFormatError(
            path,
            f"__shape__ must be {origin.shape[0]} positive ints, got {shape_arr!r}",
            expected=_NPZ_FORMAT,
        )
    shape = tuple(int(s) for s in shape_arr)
    model = scalar("__model__", "U")
    try:
        meta = json.loads(scalar("__meta__", "U"))
    except json.JSONDecodeError as exc:
        raise DatasetFormatError(
            path, f"__meta__ is not JSON ({exc})", expected=_NPZ_FORMAT
        ) from None
    if not isinstance(meta, dict):
        raise DatasetFormatError(path, "__meta__ must be a JSON object", expected=_NPZ_FORMAT)
    arrays: dict[str, np.ndarray] = {}
    for key, a in raw.items():
        if key in _META_KEYS:
            continue
        name = key.removeprefix("array/")
        if name == key or not _NAME_RE.fullmatch(name) or name.startswith("__"):
            raise DatasetFormatError(path, f"unexpected key {key!r}", expected=_NPZ_FORMAT)
        if a.dtype.kind not in "biuf":
            raise DatasetFormatError(
                path, f"array {name!r} has dtype {a.dtype}", expected=_NPZ_FORMAT
            )
        if a.ndim and tuple(a.shape[: len(shape)]) != shape:
            raise DatasetFormatError(
                path,
                f"array {name!r} has shape {a.shape}, not the grid shape {shape}",
                expected=_NPZ_FORMAT,
            )
        arrays[name] = a
    if not arrays:
        raise DatasetFormatError(path, "the file holds no arrays", expected=_NPZ_FORMAT)
    return GridMapFile(
        arrays=arrays,
        origin=origin.astype(np.float64),
        resolution=resolution,
        shape=shape,
        model=model,
        meta=meta,
        format_version=int(version),
        path=path,
    )
