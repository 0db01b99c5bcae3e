"""Polylines out: a CSV table (and back) and a standalone SVG drawing.

Pass plain vertex arrays. From a PLE / PLE+ result (:mod:`lidarjax.features`) of one scan::

    polylines, closed = ple.map.to_polylines()        # list of [m 2] arrays (m), flags
    polylines = [np.vstack([p, p[:1]]) if c else p   # close polygons explicitly
                 for p, c in zip(polylines, closed)]
    hits = np.asarray(scan.kind) == HIT               # lidarjax.rays.HIT
    points = np.asarray(scan.endpoints())[hits]       # [n 2] reflected endpoints (m)
    write_polylines_svg(out / "scan.svg", polylines, scan_points=points)

For a batched extraction (``rays`` of shape ``[scans K]``), index one scan first:
``jax.tree.map(lambda a: a[s], ple.map).to_polylines()``.

NumPy only.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ._errors import DatasetFormatError
from ._text import DECIMAL_RE, UNSIGNED_RE

__all__ = ["read_polylines_csv", "write_polylines_csv", "write_polylines_svg"]

_CSV_HEADER = "polyline,vertex,x_m,y_m"
_CSV_FORMAT = (
    f"header '{_CSV_HEADER}', then one row per vertex: polyline id (0, 1, ... in order), "
    "vertex index (0, 1, ... within the polyline), x and y (m); >= 2 vertices per polyline"
)


def _check_polylines(polylines: Any, name: str = "polylines") -> list[np.ndarray]:
    if isinstance(polylines, np.ndarray) or not isinstance(polylines, Sequence):
        raise ValueError(f"{name} must be a list of [k 2] arrays, got {type(polylines).__name__}")
    out = []
    for i, p in enumerate(polylines):
        a = np.asarray(p, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 2 or a.shape[0] < 2:
            raise ValueError(f"{name}[{i}] must have shape [k 2] with k >= 2, got {a.shape}")
        bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
        if bad.size:
            raise ValueError(f"{name}[{i}] vertex {int(bad[0])} is not finite: {a[bad[0]]}")
        out.append(a)
    return out


def write_polylines_csv(path: str | os.PathLike[str], polylines: Sequence[Any]) -> Path:
    """Write polylines as CSV: header ``polyline,vertex,x_m,y_m``, one row per vertex.

    Numbers are written with ``repr`` (shortest round-trip text), so
    :func:`read_polylines_csv` returns the vertices bit for bit.

    Args:
        path: Output file (overwritten).
        polylines: List of ``[k_i 2]`` vertex arrays (m), ``k_i >= 2``, finite. A closed
            polygon is written with its first vertex repeated at the end (the caller adds
            it; see the module docstring).

    Returns:
        The written path.

    Raises:
        ValueError: ``polylines`` is not a list of finite ``[k 2]`` arrays with ``k >= 2``
            (the message names the polyline and vertex).
    """
    pls = _check_polylines(polylines)
    lines = [_CSV_HEADER + "\n"]
    for i, a in enumerate(pls):
        for j, (x, y) in enumerate(a.tolist()):
            lines.append(f"{i},{j},{x!r},{y!r}\n")
    path = Path(path)
    path.write_text("".join(lines), encoding="ascii")
    return path


def read_polylines_csv(path: str | os.PathLike[str]) -> list[np.ndarray]:
    """Read polylines written by :func:`write_polylines_csv`.

    Lines may end with ``\\n`` or ``\\r\\n``; blank lines are skipped. Rows must list the
    polylines in order (ids 0, 1, ...) and each polyline's vertices in order (0, 1, ...).

    Args:
        path: The CSV file.

    Returns:
        List of float64 ``[k_i 2]`` vertex arrays (m); empty if the file has only the header.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        DatasetFormatError: wrong header, a row without 4 fields, a malformed or non-finite
            number, ids out of order, or a polyline with fewer than 2 vertices; the message
            names the line.
    """
    path = Path(path)
    raw = path.read_bytes().split(b"\n")
    rows = [(n, line.removesuffix(b"\r")) for n, line in enumerate(raw, start=1)]
    rows = [(n, line) for n, line in rows if line.strip()]
    if not rows or rows[0][1].strip() != _CSV_HEADER.encode():
        got = rows[0][1][:60] if rows else b""
        raise DatasetFormatError(
            path, f"first line must be the header, got {got!r}", line=rows[0][0] if rows else 1,
            expected=_CSV_FORMAT,
        )  # fmt: skip
    out: list[np.ndarray] = []
    current: list[tuple[float, float]] = []
    start_line = 0

    def close(lineno: int) -> None:
        if current and len(current) < 2:
            raise DatasetFormatError(
                path, f"polyline {len(out)} has a single vertex", line=lineno, expected=_CSV_FORMAT
            )
        if current:
            out.append(np.asarray(current, dtype=np.float64))

    for lineno, line in rows[1:]:
        fields = [f.strip(b" \t") for f in line.split(b",")]
        if len(fields) != 4:
            raise DatasetFormatError(
                path, f"found {len(fields)} fields, not 4", line=lineno, expected=_CSV_FORMAT
            )
        pid, vid, xs, ys = fields
        if not (UNSIGNED_RE.fullmatch(pid) and UNSIGNED_RE.fullmatch(vid)):
            raise DatasetFormatError(
                path, f"ids must be unsigned integers, got {pid!r}, {vid!r}", line=lineno,
                expected=_CSV_FORMAT,
            )  # fmt: skip
        if not (DECIMAL_RE.fullmatch(xs) and DECIMAL_RE.fullmatch(ys)):
            raise DatasetFormatError(
                path, f"x_m, y_m must be decimal numbers, got {xs!r}, {ys!r}", line=lineno,
                expected=_CSV_FORMAT,
            )  # fmt: skip
        x, y = float(xs), float(ys)
        if not (np.isfinite(x) and np.isfinite(y)):
            raise DatasetFormatError(
                path, "coordinate overflows float64", line=lineno, expected=_CSV_FORMAT
            )
        p, v = int(pid), int(vid)
        if p == len(out) and v == len(current):
            current.append((x, y))
        elif p == len(out) + 1 and v == 0 and current:
            close(start_line)
            current = [(x, y)]
        else:
            raise DatasetFormatError(
                path,
                f"row ({p}, {v}) out of order: expected ({len(out)}, {len(current)}) or "
                f"({len(out) + 1}, 0)",
                line=lineno,
                expected=_CSV_FORMAT,
            )
        if v == 0:
            start_line = lineno
    close(start_line)
    return out


def _num(v: float) -> str:
    """SVG number: 4 decimals (1e-4 px), trailing zeros dropped."""
    s = f"{v:.4f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def write_polylines_svg(
    path: str | os.PathLike[str],
    polylines: Sequence[Any],
    *,
    scan_points: Any = None,
    pixels_per_m: float = 50.0,
    stroke: str = "#1f77b4",
    stroke_width_px: float = 2.0,
    point_fill: str = "#d62728",
    point_radius_px: float = 1.5,
    margin_px: float = 20.0,
) -> Path:
    """Draw polylines (and optionally scan points) as a standalone SVG file, y up.

    A world point ``(x, y)`` (m) is drawn at SVG user coordinates
    ``(x * pixels_per_m, -y * pixels_per_m)`` (SVG's y axis points down, so the drawing
    shows y up); the ``viewBox`` covers every polyline vertex, point and the scale bar plus
    ``margin_px``, and ``width``/``height`` equal its size, so one user unit is one pixel.
    Layers: ``<g id="polylines">`` with one ``<polyline>`` each, ``<g id="scan_points">``
    with one ``<circle>`` per point, ``<g id="scale_bar">``: a 1 m bar labelled "1 m"
    below the drawing's lower-left corner.

    Args:
        path: Output file (overwritten).
        polylines: List of ``[k_i 2]`` vertex arrays (m), ``k_i >= 2``, finite (see the
            module docstring for PLE results and closed polygons).
        scan_points: Optional ``[n 2]`` finite points (m), e.g. the HIT endpoints of a scan.
        pixels_per_m: Scale, > 0.
        stroke: Polyline colour (any SVG colour).
        stroke_width_px: Polyline width (px), > 0.
        point_fill: Scan point colour.
        point_radius_px: Scan point radius (px), > 0.
        margin_px: Blank border (px), >= 0.

    Returns:
        The written path.

    Raises:
        ValueError: a bad argument (the message names it).
    """
    pls = _check_polylines(polylines)
    if scan_points is None:
        pts = np.zeros((0, 2))
    else:
        pts = np.asarray(scan_points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise ValueError(f"scan_points must have shape [n 2], got {pts.shape}")
        bad = np.flatnonzero(~np.isfinite(pts).all(axis=1))
        if bad.size:
            raise ValueError(
                f"scan_points[{int(bad[0])}] is not finite (drop no-return beams first)"
            )
    for name, v, lo_ok in (
        ("pixels_per_m", pixels_per_m, False),
        ("stroke_width_px", stroke_width_px, False),
        ("point_radius_px", point_radius_px, False),
        ("margin_px", margin_px, True),
    ):
        if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v):
            raise ValueError(f"{name} must be a finite number, got {v!r}")
        if v < 0 or (v == 0 and not lo_ok):
            raise ValueError(f"{name} must be {'>= 0' if lo_ok else '> 0'}, got {v!r}")
    for name, v in (("stroke", stroke), ("point_fill", point_fill)):
        if not isinstance(v, str) or not v:
            raise ValueError(f"{name} must be a non-empty colour string, got {v!r}")
    k = float(pixels_per_m)

    def to_svg(a: np.ndarray) -> np.ndarray:
        return np.column_stack([a[:, 0] * k, -a[:, 1] * k])

    drawn = [to_svg(a) for a in pls] + [to_svg(pts)]
    allp = np.concatenate(drawn, axis=0)
    if allp.shape[0]:
        lo, hi = allp.min(axis=0), allp.max(axis=0)
    else:
        lo, hi = np.zeros(2), np.zeros(2)
    # scale bar: 1 m long, 15 px below the drawing, label under it
    font = 12.0
    bar_y = hi[1] + point_radius_px + 15.0
    bar = (lo[0], bar_y, lo[0] + k, bar_y)
    text_y = bar_y + 4.0 + font
    lo = np.minimum(lo, [bar[0], bar_y])
    hi = np.maximum(hi, [bar[2], text_y + 3.0])
    pad = float(margin_px) + max(point_radius_px, stroke_width_px)
    x0, y0 = lo - pad
    w, h = hi - lo + 2 * pad

    svg = ET.Element(
        "svg",
        {
            "xmlns": "http://www.w3.org/2000/svg",
            "version": "1.1",
            "width": _num(w),
            "height": _num(h),
            "viewBox": f"{_num(x0)} {_num(y0)} {_num(w)} {_num(h)}",
        },
    )
    ET.SubElement(svg, "title").text = "lidarjax polylines (x right, y up, 1 m bar)"
    g = ET.SubElement(
        svg,
        "g",
        {
            "id": "polylines",
            "fill": "none",
            "stroke": stroke,
            "stroke-width": _num(stroke_width_px),
            "stroke-linejoin": "round",
            "stroke-linecap": "round",
        },
    )
    for a in drawn[:-1]:
        ET.SubElement(g, "polyline", {"points": " ".join(f"{_num(x)},{_num(y)}" for x, y in a)})
    g = ET.SubElement(svg, "g", {"id": "scan_points", "fill": point_fill, "stroke": "none"})
    r = _num(point_radius_px)
    for x, y in drawn[-1]:
        ET.SubElement(g, "circle", {"cx": _num(x), "cy": _num(y), "r": r})
    g = ET.SubElement(svg, "g", {"id": "scale_bar", "stroke": "black", "fill": "black"})
    ET.SubElement(
        g,
        "line",
        {
            "x1": _num(bar[0]),
            "y1": _num(bar[1]),
            "x2": _num(bar[2]),
            "y2": _num(bar[3]),
            "stroke-width": "2",
        },
    )
    label = ET.SubElement(
        g,
        "text",
        {
            "x": _num(0.5 * (bar[0] + bar[2])),
            "y": _num(text_y),
            "font-family": "sans-serif",
            "font-size": _num(font),
            "text-anchor": "middle",
            "stroke": "none",
        },
    )
    label.text = "1 m"
    path = Path(path)
    ET.ElementTree(svg).write(path, encoding="utf-8", xml_declaration=True)
    return path
