"""Polylines CSV (round trip, every bad row, mutation fuzz) and SVG (well-formed, y up,
coordinates, viewBox, scale bar)."""

from __future__ import annotations

import csv
import io
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from lidarjax.datasets import (
    DatasetFormatError,
    read_polylines_csv,
    write_polylines_csv,
    write_polylines_svg,
)
from lidarjax.features import PolylineMap

SVG = "{http://www.w3.org/2000/svg}"


def _polylines(seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = [rng.normal(0, 5, (int(k), 2)) for k in rng.integers(2, 9, 5)]
    out[0][0] = [-0.0, 1e-300]  # signed zero, subnormal-ish magnitudes survive
    out[1][1] = [123456.789012345, -7.5e-9]
    return out


# ----------------------------------------------------------------------------------------
# CSV
# ----------------------------------------------------------------------------------------


def test_csv_round_trip_is_exact(tmp_path):
    pls = _polylines()
    back = read_polylines_csv(write_polylines_csv(tmp_path / "p.csv", pls))
    assert len(back) == len(pls)
    for a, b in zip(pls, back):
        np.testing.assert_array_equal(a, b)
        assert b.dtype == np.float64
    assert np.signbit(back[0][0, 0])
    lines = (tmp_path / "p.csv").read_text().splitlines()
    assert lines[0] == "polyline,vertex,x_m,y_m"
    assert lines[1].startswith("0,0,") and len(lines) == 1 + sum(len(p) for p in pls)
    assert read_polylines_csv(write_polylines_csv(tmp_path / "e.csv", [])) == []


def test_csv_reads_crlf_and_blank_lines(tmp_path):
    (tmp_path / "p.csv").write_bytes(
        b"polyline,vertex,x_m,y_m\r\n0,0,1,2\r\n0,1,3.5,-4e-1\r\n\r\n1,0,0,0\r\n1,1,.5,5.\r\n"
    )
    back = read_polylines_csv(tmp_path / "p.csv")
    np.testing.assert_array_equal(back[0], [[1, 2], [3.5, -0.4]])
    np.testing.assert_array_equal(back[1], [[0, 0], [0.5, 5.0]])


def test_closed_polylines_from_a_polyline_map(tmp_path):
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    m = PolylineMap.from_polylines([square, square[:2] + 5], closed=[True, False])
    pls, closed = m.to_polylines()
    pls = [np.vstack([p, p[:1]]) if c else p for p, c in zip(pls, closed)]  # as documented
    back = read_polylines_csv(write_polylines_csv(tmp_path / "p.csv", pls))
    assert sorted(len(p) for p in back) == [2, 5]
    ring = next(p for p in back if len(p) == 5)
    np.testing.assert_array_equal(ring[0], ring[-1])


@pytest.mark.parametrize(
    ("polylines", "match"),
    [
        (np.zeros((2, 2)), "must be a list"),
        ([np.zeros((1, 2))], r"polylines\[0\] must have shape \[k 2\] with k >= 2"),
        ([np.zeros((2, 2)), np.zeros((3, 3))], r"polylines\[1\] must have shape"),
        ([np.zeros(4)], r"polylines\[0\] must have shape"),
        ([np.array([[0, 0], [np.inf, 1]])], r"polylines\[0\] vertex 1 is not finite"),
        ([np.array([[0, 0], [np.nan, 1]])], r"polylines\[0\] vertex 1 is not finite"),
    ],
)
def test_writers_reject_bad_polylines(tmp_path, polylines, match):
    with pytest.raises(ValueError, match=match):
        write_polylines_csv(tmp_path / "p.csv", polylines)
    with pytest.raises(ValueError, match=match):
        write_polylines_svg(tmp_path / "p.svg", polylines)


_HEADER = "polyline,vertex,x_m,y_m\n"


@pytest.mark.parametrize(
    ("body", "match", "line"),
    [
        ("0,0,1,2\n", "first line must be the header", 1),
        ("x,y\n", "first line must be the header", 1),
        ("", "first line must be the header", 1),
        (_HEADER + "0,0,1\n0,1,2,3\n", "found 3 fields, not 4", 2),
        (_HEADER + "0,0,1,2,3\n", "found 5 fields", 2),
        (_HEADER + "0,0,1,a\n0,1,2,3\n", "must be decimal numbers", 2),
        (_HEADER + "0,0,1,1_0\n0,1,2,3\n", "must be decimal numbers", 2),
        (_HEADER + "0,0,1,nan\n0,1,2,3\n", "must be decimal numbers", 2),
        (_HEADER + "0,0,1,1e999\n0,1,2,3\n", "overflows", 2),
        (_HEADER + "-1,0,1,2\n", "unsigned integers", 2),
        (_HEADER + "0,0.5,1,2\n", "unsigned integers", 2),
        (_HEADER + "1,0,1,2\n1,1,1,2\n", r"row \(1, 0\) out of order", 2),
        (_HEADER + "0,1,1,2\n", r"row \(0, 1\) out of order", 2),
        (_HEADER + "0,0,1,2\n0,2,1,2\n", r"row \(0, 2\) out of order", 3),
        (_HEADER + "0,0,1,2\n0,1,1,2\n2,0,1,2\n", r"row \(2, 0\) out of order", 4),
        (_HEADER + "0,0,1,2\n1,0,1,2\n1,1,1,2\n", "polyline 0 has a single vertex", 2),
        (_HEADER + "0,0,1,2\n0,1,1,2\n1,0,5,5\n", "polyline 1 has a single vertex", 4),
    ],
)
def test_read_csv_rejects_bad_rows(tmp_path, body, match, line):
    (tmp_path / "p.csv").write_text(body)
    with pytest.raises(DatasetFormatError, match=match) as info:
        read_polylines_csv(tmp_path / "p.csv")
    assert info.value.line == line and info.value.path == str(tmp_path / "p.csv")


def _independent_csv(text: str) -> list[np.ndarray] | None:
    """A plain csv-module parser of the same format (None: it rejects the text)."""
    try:
        rows = [r for r in csv.reader(io.StringIO(text, newline="")) if r]
    except csv.Error:
        return None
    rows = [[f.strip(" \t") for f in r] for r in rows]
    if not rows or rows[0] != ["polyline", "vertex", "x_m", "y_m"]:
        return None
    groups: dict[int, list] = {}
    for r in rows[1:]:
        if len(r) != 4 or not (r[0].isdigit() and r[1].isdigit()):
            return None
        groups.setdefault(int(r[0]), []).append((int(r[1]), float(r[2]), float(r[3])))
    if sorted(groups) != list(range(len(groups))):
        return None
    out = []
    for k in range(len(groups)):
        g = groups[k]
        if [v for v, _, _ in g] != list(range(len(g))) or len(g) < 2:
            return None
        out.append(np.array([(x, y) for _, x, y in g]))
    return out


def test_csv_mutation_fuzz(tmp_path):
    """A mutant is rejected with DatasetFormatError or read as an independent parser reads
    it."""
    good = write_polylines_csv(tmp_path / "p.csv", _polylines(1)).read_bytes()
    rng = np.random.default_rng(0)
    alphabet = b"0123456789,.-e\n\r x"
    n_read = 0
    for _ in range(400):
        data = bytearray(good)
        pos = int(rng.integers(0, len(data)))
        kind = rng.integers(3)
        if kind == 0:
            data[pos] = alphabet[int(rng.integers(len(alphabet)))]
        elif kind == 1:
            del data[pos]
        else:
            data.insert(pos, alphabet[int(rng.integers(len(alphabet)))])
        (tmp_path / "m.csv").write_bytes(bytes(data))
        try:
            ours = read_polylines_csv(tmp_path / "m.csv")
        except DatasetFormatError:
            continue
        n_read += 1
        theirs = _independent_csv(bytes(data).decode("latin-1"))
        assert theirs is not None, bytes(data)
        assert len(ours) == len(theirs)
        for a, b in zip(ours, theirs):
            np.testing.assert_array_equal(a, b)
    assert n_read > 50  # the fuzz also exercises the accepting path


# ----------------------------------------------------------------------------------------
# SVG
# ----------------------------------------------------------------------------------------


def _points(el) -> np.ndarray:
    return np.array([[float(v) for v in p.split(",")] for p in el.get("points").split()])


def test_svg_is_well_formed_y_up_and_covers_everything(tmp_path):
    pls = [np.array([[-1.0, 0.5], [2.0, 0.5], [2.0, 3.25]]), np.array([[0.0, -2.0], [0.1, -2.5]])]
    pts = np.array([[4.0, 1.0], [-3.0, -1.0]])
    k = 40.0
    root = ET.parse(write_polylines_svg(tmp_path / "p.svg", pls, scan_points=pts, pixels_per_m=k))
    svg = root.getroot()
    assert svg.tag == SVG + "svg"
    x0, y0, w, h = (float(v) for v in svg.get("viewBox").split())
    assert float(svg.get("width")) == w and float(svg.get("height")) == h

    lines = svg.findall(f"{SVG}g[@id='polylines']/{SVG}polyline")
    assert len(lines) == 2
    for el, p in zip(lines, pls):
        np.testing.assert_allclose(_points(el), np.column_stack([p[:, 0], -p[:, 1]]) * k, atol=5e-5)
    circles = svg.findall(f"{SVG}g[@id='scan_points']/{SVG}circle")
    got = np.array([[float(c.get("cx")), float(c.get("cy"))] for c in circles])
    np.testing.assert_allclose(got, np.column_stack([pts[:, 0], -pts[:, 1]]) * k, atol=5e-5)
    # y up: the point with the larger y is drawn higher (smaller SVG y)
    assert got[0, 1] < got[1, 1]

    bar = svg.find(f"{SVG}g[@id='scale_bar']/{SVG}line")
    x1, y1, x2, y2 = (float(bar.get(a)) for a in ("x1", "y1", "x2", "y2"))
    assert x2 - x1 == pytest.approx(k) and y1 == y2
    label = svg.find(f"{SVG}g[@id='scale_bar']/{SVG}text")
    assert label.text == "1 m"
    assert y1 > got[:, 1].max()  # below the drawing

    everything = np.vstack([_points(el) for el in lines] + [got, [[x1, y1], [x2, y2]]])
    assert (everything[:, 0] > x0).all() and (everything[:, 0] < x0 + w).all()
    assert (everything[:, 1] > y0).all() and (everything[:, 1] < y0 + h).all()
    assert float(label.get("y")) < y0 + h


def test_svg_without_points_and_empty(tmp_path):
    svg = ET.parse(write_polylines_svg(tmp_path / "a.svg", [np.zeros((2, 2)) + [0, 1]])).getroot()
    assert svg.findall(f"{SVG}g[@id='scan_points']/{SVG}circle") == []
    svg = ET.parse(write_polylines_svg(tmp_path / "b.svg", [])).getroot()
    assert svg.find(f"{SVG}g[@id='scale_bar']/{SVG}text").text == "1 m"
    # a user colour with XML specials is escaped, not injected
    p = write_polylines_svg(tmp_path / "c.svg", [np.eye(2)], stroke='red" onload="x')
    g = ET.parse(p).getroot().find(f"{SVG}g[@id='polylines']")
    assert g.get("stroke") == 'red" onload="x' and g.get("onload") is None


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"scan_points": np.zeros((3, 3))}, r"scan_points must have shape \[n 2\]"),
        ({"scan_points": np.zeros(3)}, r"scan_points must have shape \[n 2\]"),
        ({"scan_points": np.array([[0, 0], [np.nan, 0]])}, r"scan_points\[1\] is not finite"),
        ({"pixels_per_m": 0}, "pixels_per_m must be > 0"),
        ({"pixels_per_m": np.inf}, "pixels_per_m must be a finite number"),
        ({"pixels_per_m": True}, "pixels_per_m must be a finite number"),
        ({"stroke_width_px": -1.0}, "stroke_width_px must be > 0"),
        ({"point_radius_px": 0.0}, "point_radius_px must be > 0"),
        ({"margin_px": -1.0}, "margin_px must be >= 0"),
        ({"stroke": ""}, "stroke must be a non-empty colour"),
        ({"point_fill": None}, "point_fill must be a non-empty colour"),
    ],
)
def test_svg_rejects_bad_arguments(tmp_path, kwargs, match):
    with pytest.raises(ValueError, match=match):
        write_polylines_svg(tmp_path / "p.svg", [np.eye(2)], **kwargs)
