"""Tests of the CARMEN log reader (``lidarjax.datasets._carmen``)."""

from __future__ import annotations

import dataclasses
import gzip
import math
from pathlib import Path

import numpy as np
import pytest

from lidarjax.datasets._carmen import CarmenLog, load_carmen
from lidarjax.datasets._errors import DatasetFormatError
from lidarjax.datasets._registry import fetch

EXPECTED_SHAPES = {
    "acapulco": (861, 181),
    "belgioioso": (395, 361),
    "csail": (406, 361),
    "edmonton": (340, 180),
    "fhw": (488, 180),
    "freiburg-079": (4791, 360),
    "freiburg-101": (292, 360),
    "freiburg-campus": (2008, 360),
    "infinite-corridor": (1941, 180),
    "intel": (910, 180),
    "orebro": (237, 181),
}


_LOGS: dict[str, CarmenLog] = {}


def _log(name: str) -> CarmenLog:
    if name not in _LOGS:
        _LOGS[name] = load_carmen(fetch(name))
    return _LOGS[name]


# --------------------------------------------------------------------------- real data


def test_intel_shapes_and_dtypes():
    log = _log("intel")
    assert (log.n_scans, log.n_beams) == (910, 180)
    assert log.ranges_m.shape == (910, 180)
    assert log.azimuths_rad.shape == (180,)
    assert log.poses.shape == (910, 3)
    assert log.odometry.shape == (910, 3)
    assert log.timestamps_s.shape == (910,)
    assert log.no_return.shape == (910, 180)
    assert log.no_return.dtype == bool
    for a in (log.ranges_m, log.azimuths_rad, log.poses, log.odometry, log.timestamps_s):
        assert a.dtype == np.float64
        assert np.all(np.isfinite(a))
    assert log.path == fetch("intel")


def test_intel_first_scan_matches_file():
    """The first FLASER line (line 175 of the file), parsed independently of the reader."""
    with gzip.open(fetch("intel"), "rt") as f:
        lines = f.read().split("\n")
    tokens = lines[174].split()
    assert tokens[0] == "FLASER" and tokens[1] == "180"
    vals = [float(t) for t in tokens[2:-2]]
    log = _log("intel")
    np.testing.assert_array_equal(log.ranges_m[0], vals[:180])
    np.testing.assert_array_equal(log.poses[0], vals[180:183])
    np.testing.assert_array_equal(log.odometry[0], vals[183:186])
    assert log.timestamps_s[0] == vals[186]
    assert log.ranges_m[0, :3].tolist() == [1.09, 1.08, 1.08]


def test_intel_ranges():
    log = _log("intel")
    # No PARAM robot_front_laser_max in intel: 2 % below the no-return value.
    assert log.max_range_m == pytest.approx(81.83)
    assert log.usable_range_m == pytest.approx(0.98 * 81.83)
    assert log.ranges_m[log.ranges_m < log.usable_range_m].max() < 30.0
    assert log.ranges_m.min() >= 0
    n_max = int((log.ranges_m == log.max_range_m).sum())
    assert n_max > 1000  # no-returns are frequent in this log
    assert int(log.no_return.sum()) == n_max


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(EXPECTED_SHAPES))
def test_all_logs_load(name):
    log = _log(name)
    assert (log.n_scans, log.n_beams) == EXPECTED_SHAPES[name]
    assert np.all(np.isfinite(log.poses)) and np.all(np.isfinite(log.odometry))
    assert log.ranges_m.min() >= 0
    assert log.max_range_m == log.ranges_m.max()
    assert 0 < log.usable_range_m <= log.max_range_m
    assert np.all(np.diff(log.azimuths_rad) > 0)
    # Poses move: each log spans at least several metres.
    extent = log.poses[:, :2].max(axis=0) - log.poses[:, :2].min(axis=0)
    assert extent.max() > 5.0


@pytest.mark.parametrize(
    ("name", "fov_deg"),
    [
        ("belgioioso", 180.0),  # 361 beams, PARAM resolution 0.5
        ("csail", 180.0),  # 361 beams, PARAM resolution 0.5
        ("freiburg-079", 179.5),  # 360 beams, PARAM resolution 0.5
        ("intel", 180.0),  # 180 beams, no resolution PARAM
        ("orebro", 180.0),  # 181 beams, no PARAM
        ("fhw", 180.0),  # 'laser_frontlaser_resolution' is not the documented PARAM name
    ],
)
def test_azimuths(name, fov_deg):
    az = _log(name).azimuths_rad
    n = az.shape[0]
    fov = math.radians(fov_deg)
    assert az[0] == pytest.approx(-fov / 2, abs=1e-12)
    assert az[-1] == pytest.approx(fov / 2, abs=1e-12)
    np.testing.assert_allclose(np.diff(az), fov / (n - 1), rtol=0, atol=1e-12)
    np.testing.assert_allclose(az, -az[::-1], atol=1e-12)
    if n in (360, 361):
        np.testing.assert_allclose(np.diff(az), math.radians(0.5), atol=1e-12)


@pytest.mark.parametrize(
    ("name", "usable"),
    [
        ("belgioioso", 0.98 * 81.91),  # PARAM 80.99 > 98 % of the max reading 81.91
        ("csail", 50.0),  # PARAM 50 < 81.91
        ("edmonton", 10.0),  # PARAM 10 although readings reach 51.16 m
        ("orebro", 0.98 * 32.767),  # no PARAM: 2 % below the no-return value
        ("acapulco", 0.98 * 51.25),  # saturated readings scatter over 51.05-51.25 m
    ],
)
def test_usable_range(name, usable):
    log = _log(name)
    assert log.usable_range_m == pytest.approx(usable)
    np.testing.assert_array_equal(log.no_return, log.ranges_m >= usable)


def test_usable_range_override():
    log = load_carmen(fetch("csail"), usable_range_m=30.0)
    assert log.usable_range_m == 30.0
    assert log.max_range_m == pytest.approx(81.91)
    np.testing.assert_array_equal(log.no_return, log.ranges_m >= 30.0)
    with pytest.raises(ValueError):
        load_carmen(fetch("csail"), usable_range_m=-1.0)


# --------------------------------------------------------------------------- synthetic logs

SMALL_LOG = """\
# message formats defined: PARAM SYNC ODOM FLASER
# FLASER num_readings [range_readings] x y theta odom_x odom_y odom_theta
PARAM robot_front_laser_max 8.0 nohost 0
PARAM laser_front_laser_resolution 45 nohost 0
PARAM robot_frontlaser_offset 0.0 nohost 0
ODOM 0.0 0.0 0.0 0 0 0 0.5 nohost 0.5

FLASER 5 1.0 2.5 10.0 9.0 0.25 1.0 2.0 0.1 1.1 2.1 0.2 100.5 myhost 100.6
NEFF 12.5 nohost 0
RLASER 3 1 2 3 0 0 0 0 0 0 1 nohost 1
FLASER 5 3.0 8.0 7.99 0.0 4.5 -1.5 -2.5 -3.0 -1.4 -2.4 -3.1 101.0 myhost 101.1
ODOM 1.0 0.0 0.0 0 0 0 101.2 nohost 101.2
FLASER 5 10.0 10.0 10.0 10.0 10.0 0 0 0 0 0 0 101.5 myhost 101.6
"""


def _write(tmp_path: Path, text: str, name: str = "small.log", *, compress=False) -> Path:
    path = tmp_path / name
    data = text.encode()
    path.write_bytes(gzip.compress(data) if compress else data)
    return path


def test_small_log_field_by_field(tmp_path):
    log = load_carmen(_write(tmp_path, SMALL_LOG))
    assert isinstance(log, CarmenLog)
    assert (log.n_scans, log.n_beams) == (3, 5)
    np.testing.assert_array_equal(
        log.ranges_m,
        [[1.0, 2.5, 10.0, 9.0, 0.25], [3.0, 8.0, 7.99, 0.0, 4.5], [10.0] * 5],
    )
    np.testing.assert_array_equal(log.poses, [[1.0, 2.0, 0.1], [-1.5, -2.5, -3.0], [0, 0, 0]])
    np.testing.assert_array_equal(log.odometry, [[1.1, 2.1, 0.2], [-1.4, -2.4, -3.1], [0, 0, 0]])
    np.testing.assert_array_equal(log.timestamps_s, [100.5, 101.0, 101.5])
    # 5 beams at 45 degrees: fov 180 degrees.
    np.testing.assert_allclose(
        log.azimuths_rad, np.radians([-90.0, -45.0, 0.0, 45.0, 90.0]), atol=1e-15
    )
    assert log.fov_rad == pytest.approx(math.pi)
    assert log.max_range_m == 10.0
    assert log.usable_range_m == 8.0  # PARAM robot_front_laser_max 8.0 < 10.0
    np.testing.assert_array_equal(
        log.no_return,
        [
            [False, False, True, True, False],
            [False, True, False, False, False],
            [True] * 5,
        ],
    )
    assert log.path == tmp_path / "small.log"


def test_small_log_gzip_detected_by_magic(tmp_path):
    plain = load_carmen(_write(tmp_path, SMALL_LOG))
    # Gzip content under a name without '.gz', and plain text under a '.gz' name.
    zipped = load_carmen(_write(tmp_path, SMALL_LOG, "zipped.log", compress=True))
    misnamed = load_carmen(_write(tmp_path, SMALL_LOG, "plain.log.gz"))
    for other in (zipped, misnamed):
        for field in ("ranges_m", "azimuths_rad", "poses", "odometry", "timestamps_s"):
            np.testing.assert_array_equal(getattr(other, field), getattr(plain, field))
        assert other.usable_range_m == plain.usable_range_m


def test_defaults_without_params(tmp_path):
    text = "\n".join(line for line in SMALL_LOG.splitlines() if not line.startswith("PARAM"))
    log = load_carmen(_write(tmp_path, text))
    np.testing.assert_allclose(log.azimuths_rad, np.linspace(-np.pi / 2, np.pi / 2, 5))
    assert log.max_range_m == 10.0
    assert log.usable_range_m == pytest.approx(9.8)
    np.testing.assert_array_equal(log.no_return, log.ranges_m >= 9.8)


def test_param_larger_than_max_reading_is_ignored(tmp_path):
    text = SMALL_LOG.replace("robot_front_laser_max 8.0", "robot_front_laser_max 50")
    log = load_carmen(_write(tmp_path, text))
    assert log.max_range_m == 10.0
    assert log.usable_range_m == pytest.approx(9.8)


def test_subset(tmp_path):
    log = load_carmen(_write(tmp_path, SMALL_LOG))
    sub = log.subset([2, 0])
    assert (sub.n_scans, sub.n_beams) == (2, 5)
    np.testing.assert_array_equal(sub.ranges_m, log.ranges_m[[2, 0]])
    np.testing.assert_array_equal(sub.poses, log.poses[[2, 0]])
    np.testing.assert_array_equal(sub.odometry, log.odometry[[2, 0]])
    np.testing.assert_array_equal(sub.timestamps_s, [101.5, 100.5])
    np.testing.assert_array_equal(sub.azimuths_rad, log.azimuths_rad)
    assert (sub.max_range_m, sub.usable_range_m, sub.path) == (
        log.max_range_m,
        log.usable_range_m,
        log.path,
    )
    assert log.subset(slice(1, None)).n_scans == 2
    assert log.subset(np.array([True, False, True])).n_scans == 2
    one = log.subset(1)
    assert one.ranges_m.shape == (1, 5)
    np.testing.assert_array_equal(one.poses, log.poses[1:2])
    assert log.n_scans == 3  # original untouched


def test_log_is_immutable(tmp_path):
    log = load_carmen(_write(tmp_path, SMALL_LOG))
    with pytest.raises(dataclasses.FrozenInstanceError):
        log.usable_range_m = 1.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        log.ranges_m[0, 0] = 5.0


GOOD = "FLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 1.0 host 1.0"


@pytest.mark.parametrize(
    ("bad_line", "fragment"),
    [
        ("FLASER 3 1.0 2.0 0 0 0 0 0 0 1.0 host 1.0", "tokens"),  # one range missing
        ("FLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 1.0 host 1.0 extra", "tokens"),
        ("FLASER 3 1.0 abc 3.0 0 0 0 0 0 0 1.0 host 1.0", "abc"),
        ("FLASER 4 1.0 2.0 3.0 4.0 0 0 0 0 0 0 1.0 host 1.0", "beams"),  # n changes
        ("FLASER 3 1.0 nan 3.0 0 0 0 0 0 0 1.0 host 1.0", "r_2"),
        ("FLASER 3 1.0 2.0 -3.0 0 0 0 0 0 0 1.0 host 1.0", "r_3"),
        ("FLASER 3 1.0 2.0 inf 0 0 0 0 0 0 1.0 host 1.0", "r_3"),
        ("FLASER 3 1.0 2.0 3.0 0 0 nan 0 0 0 1.0 host 1.0", "not finite"),
        ("FLASER three 1.0 2.0 3.0 0 0 0 0 0 0 1.0 host 1.0", "integer"),
        ("FLASER", "beam count"),
    ],
)
def test_corrupt_flaser_line(tmp_path, bad_line, fragment):
    text = "\n".join(["# header", GOOD, "ODOM 0 0 0 0 0 0 1 host 1", GOOD, bad_line, GOOD])
    path = _write(tmp_path, text)
    with pytest.raises(DatasetFormatError) as info:
        load_carmen(path)
    err = info.value
    assert err.line == 5
    assert f"{path}:5:" in str(err)
    assert fragment in str(err)
    assert "FLASER n r_1" in str(err)  # the expected format is quoted


def test_corrupt_line_in_gzip(tmp_path):
    text = "\n".join([GOOD, GOOD, "FLASER 3 1.0 2.0 0 0 0 0 0 0 1.0 host 1.0"])
    path = _write(tmp_path, text, "bad.log.gz", compress=True)
    with pytest.raises(DatasetFormatError, match=r"bad\.log\.gz:3:"):
        load_carmen(path)


def test_bad_param_value(tmp_path):
    text = "PARAM laser_front_laser_resolution fast nohost 0\n" + GOOD
    with pytest.raises(DatasetFormatError, match=":1:"):
        load_carmen(_write(tmp_path, text))


def test_truncated_gzip(tmp_path):
    blob = gzip.compress((GOOD + "\n").encode() * 200)
    path = tmp_path / "trunc.log.gz"
    path.write_bytes(blob[: len(blob) // 2])
    with pytest.raises(DatasetFormatError, match="gzip") as info:
        load_carmen(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize(
    "text",
    ["", "# just a comment\nPARAM robot_front_laser_max 8 nohost 0\nODOM 0 0 0 0 0 0 1 h 1\n"],
)
def test_empty_log(tmp_path, text):
    with pytest.raises(DatasetFormatError, match="no FLASER"):
        load_carmen(_write(tmp_path, text))
    with pytest.raises(DatasetFormatError, match="no FLASER"):
        load_carmen(_write(tmp_path, text, "empty.log.gz", compress=True))


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_carmen(tmp_path / "nope.log.gz")


# --------------------------------------------------------------------------- strict numbers


@pytest.mark.parametrize(
    ("bad_line", "fragment"),
    [
        ("FLASER 3 1.0 1_5 3.0 0 0 0 0 0 0 1.0 host 1.0", "1_5"),
        ("FLASER 3 1.0 2.0 3.0 0 0 0_1 0 0 0 1.0 host 1.0", "0_1"),
        ("FLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 1.0 host 1_0", "1_0"),
        ("FLASER 0_3 1.0 2.0 3.0 0 0 0 0 0 0 1.0 host 1.0", "integer"),
        ("FLASER +3 1.0 2.0 3.0 0 0 0 0 0 0 1.0 host 1.0", "integer"),
        ("FLASER 3 1.0 2.0\xa03.0 0 0 0 0 0 0 1.0 host 1.0", "tokens"),  # NBSP is no separator
        ("FLASER 3 1.0 2.0 3.0\x1c 0 0 0 0 0 0 1.0 host 1.0", "non-numeric"),
        ("FLASER 3 1.0 2.0 0x3 0 0 0 0 0 0 1.0 host 1.0", "0x3"),
    ],
)
def test_strict_numbers_in_flaser(tmp_path, bad_line, fragment):
    text = "\n".join([GOOD, bad_line, GOOD])
    path = tmp_path / "strict.log"
    path.write_bytes(text.encode("latin-1"))
    with pytest.raises(DatasetFormatError) as info:
        load_carmen(path)
    assert info.value.line == 2
    assert f"{path}:2:" in str(info.value)
    assert fragment in str(info.value)


@pytest.mark.parametrize(
    "param",
    [
        "PARAM laser_front_laser_resolution 0_5 nohost 0",
        "PARAM laser_front_laser_resolution 1e308 nohost 0",  # infinite field of view
        "PARAM laser_front_laser_resolution 400 nohost 0",
        "PARAM laser_front_laser_resolution 2 nohost 0",  # 2 deg * 360 gaps = 720 deg
        "PARAM laser_front_laser_resolution inf nohost 0",
        "PARAM robot_front_laser_max 5_0 nohost 0",
    ],
)
def test_bad_resolution_or_range_param(tmp_path, param):
    scan = "FLASER 361 " + " ".join(["1.0"] * 361) + " 0 0 0 0 0 0 1.0 host 1.0"
    text = "\n".join(["# log", scan, param, scan])
    path = _write(tmp_path, text)
    with pytest.raises(DatasetFormatError) as info:
        load_carmen(path)
    assert info.value.line == 3
    assert f"{path}:3:" in str(info.value)


def test_full_circle_resolution_is_accepted(tmp_path):
    scan = "FLASER 361 " + " ".join(["1.0"] * 361) + " 0 0 0 0 0 0 1.0 host 1.0"
    text = "\n".join(["PARAM laser_front_laser_resolution 1.0 nohost 0", scan])
    log = load_carmen(_write(tmp_path, text))
    assert np.all(np.isfinite(log.azimuths_rad))
    assert log.fov_rad == pytest.approx(2 * math.pi)


# --------------------------------------------------------------------------- azimuth layouts


def _scan_line(n: int) -> str:
    return f"FLASER {n} " + " ".join(["1.0"] * n) + " 0 0 0 0 0 0 1.0 host 1.0"


@pytest.mark.parametrize(
    ("n", "param", "spread_deg", "sweep_deg"),
    [
        (5, None, [-90, -45, 0, 45, 90], [-90, -45, 0, 45, 90]),  # odd: the layouts agree
        (4, None, [-90, -30, 30, 90], [-90, -45, 0, 45]),  # even: a 5-beam sweep minus one
        (5, 30.0, [-60, -30, 0, 30, 60], [-60, -30, 0, 30, 60]),
        (4, 30.0, [-45, -15, 15, 45], [-60, -30, 0, 30]),
        (2, None, [-90, 90], [-90, 0]),
        (1, None, [0], [0]),
        (1, 30.0, [0], [0]),
    ],
)
def test_azimuth_layouts(tmp_path, n, param, spread_deg, sweep_deg):
    lines = [] if param is None else [f"PARAM laser_front_laser_resolution {param} nohost 0"]
    path = _write(tmp_path, "\n".join([*lines, _scan_line(n), _scan_line(n)]))
    for layout, want in (("spread", spread_deg), ("sweep", sweep_deg)):
        az = load_carmen(path, azimuth_layout=layout).azimuths_rad
        np.testing.assert_allclose(az, np.radians(want), rtol=0, atol=1e-12, err_msg=layout)
    # The default is the shared data README's layout.
    np.testing.assert_allclose(
        load_carmen(path).azimuths_rad, np.radians(spread_deg), rtol=0, atol=1e-12
    )


def test_sweep_layout_field_of_view_check(tmp_path):
    # 4 beams at 100 deg: spread over 3 gaps = 300 deg is fine; a sweep has 4 gaps = 400 deg.
    text = "\n".join(["# log", "PARAM laser_front_laser_resolution 100 nohost 0", _scan_line(4)])
    path = _write(tmp_path, text)
    assert load_carmen(path).fov_rad == pytest.approx(math.radians(300))
    with pytest.raises(DatasetFormatError, match="400 deg") as info:
        load_carmen(path, azimuth_layout="sweep")
    assert info.value.line == 2


@pytest.mark.parametrize("layout", ["Sweep", "", None, 1, "centred"])
def test_bad_azimuth_layout(tmp_path, layout):
    path = _write(tmp_path, SMALL_LOG)
    with pytest.raises(ValueError, match="azimuth_layout"):
        load_carmen(path, azimuth_layout=layout)


@pytest.mark.parametrize(
    ("name", "first_deg", "last_deg"),
    [
        ("intel", -90.0, 89.0),  # 180 beams, no resolution PARAM
        ("fhw", -90.0, 89.0),  # 180 beams
        ("freiburg-101", -90.0, 89.5),  # 360 beams, PARAM resolution 0.5
        ("orebro", -90.0, 90.0),  # 181 beams: as spread
    ],
)
def test_sweep_azimuths_of_shared_logs(name, first_deg, last_deg):
    az = load_carmen(fetch(name), azimuth_layout="sweep").azimuths_rad
    assert az[0] == pytest.approx(math.radians(first_deg), abs=1e-12)
    assert az[-1] == pytest.approx(math.radians(last_deg), abs=1e-12)
    step = math.radians(last_deg - first_deg) / (az.shape[0] - 1)
    np.testing.assert_allclose(np.diff(az), step, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ["intel", "fhw", "edmonton"])
def test_sweep_layout_is_the_self_consistent_one(name):
    """On the corrected poses, end points of different visits (scans >= 30 apart) lie
    closer together with the sweep layout than with the README's spread layout, and
    rotating the sweep by a quarter step either way moves them apart again (first 300
    scans; the whole logs agree, see ``load_carmen``)."""
    from lidarjax.metrics import cross_visit_distance

    log = load_carmen(fetch(name))
    k = 300
    poses, ranges = log.poses[:k], log.ranges_m[:k]

    def median(az):
        return cross_visit_distance(poses, ranges, az, max_range_m=10.0).median_m

    spread = median(log.azimuths_rad)
    sweep_az = load_carmen(fetch(name), azimuth_layout="sweep").azimuths_rad
    sweep = median(sweep_az)
    quarter = 0.25 * (sweep_az[1] - sweep_az[0])
    assert sweep < spread
    assert sweep < median(sweep_az + quarter)
    assert sweep < median(sweep_az - quarter)
