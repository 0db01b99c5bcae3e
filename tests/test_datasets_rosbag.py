"""Tests of the ROS bag reader and writer (``lidarjax.datasets._rosbag``).

Every bag is written here: by the module's writers (round trips of a real CARMEN log) and
directly with :mod:`rosbags` (hand-made messages: no-returns, interpolation, tf chains,
PointCloud2 layouts packed byte by byte with :mod:`struct`, bad bags).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import struct
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from lidarjax.datasets import (
    BagPointCloud,
    CarmenLog,
    DatasetFormatError,
    PointCloud,
    fetch,
    iter_bag_point_clouds,
    load_carmen,
    read_bag_laser_scans,
    read_bag_odometry,
    read_bag_point_clouds,
    read_bag_tf,
    read_bag_topics,
    write_bag_laser_scans,
    write_bag_point_clouds,
)

KINDS = ("ros1", "sqlite3", "mcap")
NS = 1_000_000_000


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _bag_path(tmp: Path, name: str, kind: str) -> Path:
    return tmp / (f"{name}.bag" if kind == "ros1" else f"{name}_{kind}")


def _write_kw(kind: str) -> dict:
    return dict(version=1) if kind == "ros1" else dict(version=2, storage=kind)


# --------------------------------------------------------------------------- hand-made bags


class RawBag:
    """A bag written directly with rosbags (independent of the module's writers)."""

    def __init__(self, path: Path, kind: str) -> None:
        self.ros1 = kind == "ros1"
        if self.ros1:
            self.ts = get_typestore(Stores.ROS1_NOETIC)
            self.ts.register(
                get_types_from_msg(
                    "geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"
                )
            )
            self.writer = Writer1(path)
        else:
            self.ts = get_typestore(Stores.ROS2_HUMBLE)
            plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer2(path, version=9, storage_plugin=plugin)
        self.T = self.ts.types
        self.conns: dict[str, object] = {}
        self.time = 0

    def __enter__(self):
        self.writer.open()
        return self

    def __exit__(self, *exc):
        self.writer.close()

    def header(self, stamp_s: float, frame: str):
        ns = round(Fraction(stamp_s) * NS)  # exact: the nearest nanosecond
        stamp = self.T["builtin_interfaces/msg/Time"](sec=ns // NS, nanosec=ns % NS)
        if self.ros1:
            return self.T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
        return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def connect(self, topic: str, msgtype: str):
        self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.ts)

    def write(self, topic: str, msg) -> None:
        conn = self.conns[topic]
        ser = self.ts.serialize_ros1 if self.ros1 else self.ts.serialize_cdr
        self.time += 1000
        self.writer.write(conn, self.time, ser(msg, conn.msgtype))

    def scan(self, stamp_s, ranges, *, frame="laser", angle_min=-1.0, inc=0.5, rmin=0.1, rmax=30):
        return self.T["sensor_msgs/msg/LaserScan"](
            header=self.header(stamp_s, frame),
            angle_min=angle_min,
            angle_max=angle_min + inc * (len(ranges) - 1),
            angle_increment=inc,
            time_increment=0.0,
            scan_time=0.0,
            range_min=rmin,
            range_max=rmax,
            ranges=np.asarray(ranges, dtype=np.float32),
            intensities=np.zeros(0, dtype=np.float32),
        )

    def transform_stamped(self, stamp_s, parent, child, xyz, yaw):
        T = self.T
        return T["geometry_msgs/msg/TransformStamped"](
            header=self.header(stamp_s, parent),
            child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2]),
                rotation=T["geometry_msgs/msg/Quaternion"](
                    x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
                ),
            ),
        )

    def tf(self, transforms):
        return self.T["tf2_msgs/msg/TFMessage"](transforms=transforms)

    def odometry(self, stamp_s, parent, child, xy, yaw):
        T = self.T
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=xy[0], y=xy[1], z=0.0),
            orientation=T["geometry_msgs/msg/Quaternion"](
                x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
            ),
        )
        v = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        return T["nav_msgs/msg/Odometry"](
            header=self.header(stamp_s, parent),
            child_frame_id=child,
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=v, angular=v),
                covariance=np.zeros(36),
            ),
        )


# --------------------------------------------------------------------------- CARMEN round trip


@pytest.fixture(scope="module")
def intel30() -> CarmenLog:
    """The first 30 intel scans, odometry made to drift away from the corrected poses (the
    corrected log has odometry == poses), one reading of 0 (a ROS no-return)."""
    log = load_carmen(fetch("intel")).subset(slice(0, 30))
    k = np.arange(30)
    odometry = log.poses + np.column_stack([0.01 * k, -0.02 * k, 0.003 * k + 0.5])
    ranges = np.array(log.ranges_m)
    ranges[4, 7] = 0.0
    return dataclasses.replace(log, ranges_m=ranges, odometry=odometry)


@pytest.fixture(scope="module")
def intel_bags(intel30, tmp_path_factory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("intel")
    return {
        kind: write_bag_laser_scans(_bag_path(tmp, "intel", kind), intel30, **_write_kw(kind))
        for kind in KINDS
    }


def _ulp32(x: float) -> float:
    x32 = np.float32(abs(x))
    return float(np.nextafter(x32, np.float32(np.inf)) - x32)


@pytest.mark.parametrize("kind", KINDS)
def test_laser_scans_round_trip(intel30, intel_bags, kind):
    log = intel30
    back = read_bag_laser_scans(intel_bags[kind], usable_range_m=log.usable_range_m)
    assert back.path == intel_bags[kind]
    assert back.ranges_m.shape == (30, 180) and back.ranges_m.dtype == np.float64
    # max range: the float32 value of the log's
    assert back.max_range_m == float(np.float32(log.max_range_m))
    assert back.usable_range_m == log.usable_range_m
    # ranges: exactly the float32 rounding; the 0 reading is a ROS no-return -> max range
    expected = log.ranges_m.astype(np.float32).astype(np.float64)
    expected[4, 7] = back.max_range_m
    np.testing.assert_array_equal(back.ranges_m, expected)
    no_return = expected >= log.usable_range_m
    assert no_return.sum() > 400  # the intel log saturates a lot: no-returns are exercised
    np.testing.assert_array_equal(back.no_return, no_return)
    # azimuths: float32 angle_min and angle_increment, k increments
    inc = (log.azimuths_rad[-1] - log.azimuths_rad[0]) / 179
    k = np.arange(180)
    bound = 0.5 * _ulp32(log.azimuths_rad[0]) + k * 0.5 * _ulp32(inc) + 1e-15 * (1 + k)
    assert np.all(np.abs(back.azimuths_rad - log.azimuths_rad) <= bound)
    # stamps: decimal seconds with <= 9 decimals come back exactly
    np.testing.assert_array_equal(back.timestamps_s, log.timestamps_s)
    # poses (tf map -> odom -> laser) and odometry (the Odometry topic): float64 rounding
    for got, want in ((back.poses, log.poses), (back.odometry, log.odometry)):
        np.testing.assert_allclose(got[:, :2], want[:, :2], rtol=0, atol=1e-12)
        np.testing.assert_allclose(_wrap(got[:, 2] - want[:, 2]), 0, atol=1e-12)
        assert np.all((got[:, 2] > -np.pi) & (got[:, 2] <= np.pi))
    assert not back.ranges_m.flags.writeable and not back.poses.flags.writeable


def test_default_usable_range_is_range_max(intel_bags):
    back = read_bag_laser_scans(intel_bags["ros1"])
    assert back.usable_range_m == back.max_range_m
    with pytest.raises(ValueError, match="usable_range_m"):
        read_bag_laser_scans(intel_bags["ros1"], usable_range_m=-1.0)


@pytest.mark.parametrize("kind", KINDS)
def test_topics_odometry_and_tf_readers(intel30, intel_bags, kind):
    path = intel_bags[kind]
    assert read_bag_topics(path) == {
        "/odom": ("nav_msgs/msg/Odometry", 30),
        "/scan": ("sensor_msgs/msg/LaserScan", 30),
        "/tf": ("tf2_msgs/msg/TFMessage", 30),
    }
    stamps, odo = read_bag_odometry(path)
    np.testing.assert_array_equal(stamps, intel30.timestamps_s)
    np.testing.assert_allclose(odo[:, :2], intel30.odometry[:, :2], rtol=0, atol=1e-12)
    np.testing.assert_allclose(_wrap(odo[:, 2] - intel30.odometry[:, 2]), 0, atol=1e-12)
    stamps, T = read_bag_tf(path, "map", "/laser")
    assert T.shape == (30, 7)
    np.testing.assert_array_equal(stamps, np.sort(intel30.timestamps_s))
    np.testing.assert_allclose(T[:, :2], intel30.poses[:, :2], rtol=0, atol=1e-12)
    np.testing.assert_allclose(T[:, 2], 0.0, atol=0)
    np.testing.assert_allclose(np.linalg.norm(T[:, 3:], axis=1), 1.0, atol=1e-15)
    yaw = 2 * np.arctan2(T[:, 6], T[:, 3])
    np.testing.assert_allclose(_wrap(yaw - intel30.poses[:, 2]), 0, atol=1e-12)
    _, T = read_bag_tf(path, "odom", "laser", stamps_s=intel30.timestamps_s[:3])
    np.testing.assert_allclose(T[:, :2], intel30.odometry[:3, :2], rtol=0, atol=1e-12)


def test_repeated_and_backward_stamps_keep_order_and_exact_poses(tmp_path):
    """Stamps that repeat or go backwards (as in CARMEN logs): scans keep the log order and
    each scan gets its own odometry and tf pose (exact-stamp pairing, in order)."""
    log = load_carmen(fetch("intel")).subset(slice(290, 300))  # a backward step at 294
    assert np.any(np.diff(log.timestamps_s) < 0)
    stamps = np.array(log.timestamps_s)
    stamps[6:9] = stamps[5]  # a stamp shared by four scans
    odometry = log.poses + np.column_stack([np.arange(10) * 0.1, np.zeros(10), np.zeros(10)])
    log = dataclasses.replace(log, timestamps_s=stamps, odometry=odometry)
    path = write_bag_laser_scans(tmp_path / "b.bag", log)
    back = read_bag_laser_scans(path)
    np.testing.assert_array_equal(back.timestamps_s, stamps)
    np.testing.assert_array_equal(back.ranges_m, log.ranges_m.astype(np.float32))
    np.testing.assert_allclose(back.odometry[:, :2], odometry[:, :2], rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.poses[:, :2], log.poses[:, :2], rtol=0, atol=1e-12)


def test_writer_arguments(intel30, tmp_path):
    with pytest.raises(ValueError, match="version"):
        write_bag_laser_scans(tmp_path / "a.bag", intel30, version=3)
    with pytest.raises(ValueError, match="storage"):
        write_bag_laser_scans(tmp_path / "a", intel30, version=2, storage="csv")
    with pytest.raises(ValueError, match=r"\.bag"):
        write_bag_laser_scans(tmp_path / "a.db", intel30, version=1)
    with pytest.raises(ValueError, match="folder"):
        write_bag_laser_scans(tmp_path / "a.bag", intel30, version=2)
    negative = dataclasses.replace(intel30, timestamps_s=intel30.timestamps_s - 100.0)
    with pytest.raises(ValueError, match="timestamps_s"):
        write_bag_laser_scans(tmp_path / "n.bag", negative)
    uneven = dataclasses.replace(intel30, azimuths_rad=intel30.azimuths_rad**3)
    with pytest.raises(ValueError, match="evenly spaced"):
        write_bag_laser_scans(tmp_path / "u.bag", uneven)
    (tmp_path / "x.bag").write_bytes(b"")
    with pytest.raises(FileExistsError):
        write_bag_laser_scans(tmp_path / "x.bag", intel30)


def test_without_odometry_and_tf_poses_are_nan(intel30, tmp_path):
    path = write_bag_laser_scans(tmp_path / "s.bag", intel30, odom_topic=None, tf=False)
    assert set(read_bag_topics(path)) == {"/scan"}
    back = read_bag_laser_scans(path)
    assert np.isnan(back.poses).all() and np.isnan(back.odometry).all()
    # tf only: odometry falls back to tf odom -> laser
    path = write_bag_laser_scans(tmp_path / "t.bag", intel30, odom_topic=None)
    back = read_bag_laser_scans(path)
    np.testing.assert_allclose(back.odometry[:, :2], intel30.odometry[:, :2], atol=1e-12)


# --------------------------------------------------------------------------- hand-made scans


@pytest.mark.parametrize("kind", KINDS)
def test_no_returns_azimuths_and_stamps(tmp_path, kind):
    path = _bag_path(tmp_path, "n", kind)
    rows = [
        [np.nan, np.inf, -1.0, 0.0, 0.05, 5.0, 31.0, 30.0],
        [1.0, 2.0, 3.0, -np.inf, 0.1, 29.5, 1e30, 0.25],
    ]
    with RawBag(path, kind) as bag:
        bag.connect("/front", "sensor_msgs/msg/LaserScan")
        bag.write("/front", bag.scan(12.5, rows[0], angle_min=-1.25, inc=0.25))
        bag.write("/front", bag.scan(1e9 + 0.125, rows[1], angle_min=-1.25, inc=0.25))
    log = read_bag_laser_scans(path)
    f32 = lambda v: float(np.float32(v))  # noqa: E731
    np.testing.assert_array_equal(
        log.ranges_m,
        [
            [30.0, 30.0, 30.0, 30.0, 30.0, 5.0, 30.0, 30.0],
            [1.0, 2.0, 3.0, 30.0, f32(0.1), 29.5, 30.0, 0.25],
        ],
    )
    np.testing.assert_array_equal(log.azimuths_rad, -1.25 + 0.25 * np.arange(8))
    np.testing.assert_array_equal(log.timestamps_s, [12.5, 1e9 + 0.125])
    assert log.max_range_m == 30.0 and log.usable_range_m == 30.0
    assert np.isnan(log.poses).all() and np.isnan(log.odometry).all()


def test_tf_chain_interpolation_static_and_odometry_frames(tmp_path):
    """map -> odom (dynamic) -> base (dynamic) -> laser (tf_static); Odometry of base_link;
    scans between, on and outside the tf stamps."""
    path = tmp_path / "tf.bag"
    with RawBag(path, "ros1") as bag:
        bag.connect("/scan", "sensor_msgs/msg/LaserScan")
        bag.connect("/tf", "tf2_msgs/msg/TFMessage")
        bag.connect("/tf_static", "tf2_msgs/msg/TFMessage")
        bag.connect("/odom", "nav_msgs/msg/Odometry")
        bag.write(
            "/tf_static",
            bag.tf([bag.transform_stamped(0.0, "base", "laser", (0.5, 0.0, 0.2), np.pi / 2)]),
        )
        for t, x, yaw in ((10.0, 0.0, 0.0), (11.0, 2.0, 1.0)):
            bag.write(
                "/tf",
                bag.tf(
                    [
                        bag.transform_stamped(t, "/map", "odom", (1.0, 1.0, 0.0), 0.0),
                        bag.transform_stamped(t, "odom", "base", (x, 0.0, 0.0), yaw),
                    ]
                ),
            )
            bag.write("/odom", bag.odometry(t, "odom", "base", (x, 0.0), yaw))
        for t in (10.0, 10.5, 11.0, 12.0):
            bag.write("/scan", bag.scan(t, [1.0, 2.0]))
    log = read_bag_laser_scans(path)

    def laser_in(x0, y0, x, yaw):  # base at (x, 0, yaw) in odom, odom at (x0, y0) in map
        return [x0 + x + 0.5 * np.cos(yaw), y0 + 0.5 * np.sin(yaw), _wrap(yaw + np.pi / 2)]

    expected = np.array(
        [
            laser_in(1, 1, 0.0, 0.0),
            laser_in(1, 1, 1.0, 0.5),  # translation lerp, rotation slerp half-way
            laser_in(1, 1, 2.0, 1.0),
            [np.nan] * 3,  # after the last tf message: no extrapolation
        ]
    )
    np.testing.assert_allclose(log.poses, expected, rtol=0, atol=1e-12)
    # Odometry is of base_link: moved to the laser through tf (odom frame, no map shift)
    expected_odo = expected - np.array([1.0, 1.0, 0.0])
    np.testing.assert_allclose(log.odometry, expected_odo, rtol=0, atol=1e-12)
    # base frame chosen by argument: the base pose
    base = read_bag_laser_scans(path, base_frame="base")
    np.testing.assert_allclose(base.poses[1], [2.0, 1.0, 0.5], atol=1e-12)
    # a frame tf does not know: NaN poses, odometry as published
    other = read_bag_laser_scans(path, map_frame="world", base_frame="base")
    assert np.isnan(other.poses).all()
    np.testing.assert_allclose(other.odometry[1], [1.0, 0.0, 0.5], atol=1e-12)
    # read_bag_tf: the union of the dynamic stamps; explicit stamps
    stamps, T = read_bag_tf(path, "map", "laser")
    np.testing.assert_array_equal(stamps, [10.0, 11.0])
    np.testing.assert_allclose(T[:, :2], expected[[0, 2], :2], atol=1e-12)
    stamps, T = read_bag_tf(path, "base", "laser")
    np.testing.assert_array_equal(stamps, [0.0])
    np.testing.assert_allclose(T[0], [0.5, 0, 0.2, np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    _, T = read_bag_tf(path, "laser", "map", stamps_s=[9.0, 10.0])
    assert np.isnan(T[0]).all() and np.isfinite(T[1]).all()
    with pytest.raises(DatasetFormatError, match="frames"):
        read_bag_tf(path, "map", "nowhere")
    with pytest.raises(ValueError, match="same frame"):
        read_bag_tf(path, "map", "/map")


def test_ros1_tf_message_of_the_old_tf_package(tmp_path):
    """ROS 1 bags recorded with ``tf`` (not ``tf2``) carry ``tf/tfMessage`` on ``/tf``."""
    path = tmp_path / "oldtf.bag"
    with RawBag(path, "ros1") as bag:
        bag.ts.register(
            get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf/msg/tfMessage")
        )
        bag.connect("/scan", "sensor_msgs/msg/LaserScan")
        bag.connect("/tf", "tf/msg/tfMessage")
        for t in (1.0, 2.0):
            tr = bag.transform_stamped(t, "map", "laser", (t, 0.0, 0.0), 0.0)
            bag.write("/tf", bag.T["tf/msg/tfMessage"](transforms=[tr]))
            bag.write("/scan", bag.scan(t, [1.0]))
    assert read_bag_topics(path)["/tf"] == ("tf/msg/tfMessage", 2)
    log = read_bag_laser_scans(path)
    np.testing.assert_allclose(log.poses, [[1.0, 0.0, 0.0], [2.0, 0.0, 0.0]], atol=1e-15)


@pytest.mark.parametrize("kind", ("ros1", "sqlite3"))
def test_topic_selection(tmp_path, kind):
    path = _bag_path(tmp_path, "m", kind)
    with RawBag(path, kind) as bag:
        for topic in ("/front", "/rear"):
            bag.connect(topic, "sensor_msgs/msg/LaserScan")
        for topic in ("/odom", "/odom_filtered"):
            bag.connect(topic, "nav_msgs/msg/Odometry")
        bag.write("/front", bag.scan(1.0, [1.0, 2.0, 3.0]))
        bag.write("/rear", bag.scan(1.0, [4.0, 5.0]))
        bag.write("/odom", bag.odometry(1.0, "odom", "laser", (1.0, 2.0), 0.5))
        bag.write("/odom_filtered", bag.odometry(1.0, "odom", "laser", (3.0, 4.0), 0.25))
    with pytest.raises(ValueError, match=r"/front.*/rear"):
        read_bag_laser_scans(path)
    with pytest.raises(ValueError, match=r"/odom.*/odom_filtered"):
        read_bag_laser_scans(path, "/rear")
    log = read_bag_laser_scans(path, "/rear", odom_topic="/odom_filtered")
    np.testing.assert_array_equal(log.ranges_m, [[4.0, 5.0]])
    np.testing.assert_allclose(log.odometry, [[3.0, 4.0, 0.25]], atol=1e-15)
    with pytest.raises(ValueError, match="several"):
        read_bag_odometry(path)
    stamps, poses = read_bag_odometry(path, "/odom")
    np.testing.assert_allclose(poses, [[1.0, 2.0, 0.5]], atol=1e-15)


@pytest.mark.parametrize(
    ("scan2", "fragment"),
    [
        (dict(angle_min=-0.5), "scan 2: angle_min"),
        (dict(inc=0.25), "scan 2: angle_increment"),
        (dict(rmax=40.0), "scan 2: range_max"),
        (dict(ranges=[1.0, 2.0]), "scan 2: number of beams"),
        (dict(frame="other"), "scan 2: frame_id"),
        (dict(rmin=50.0), "scan 2: range_min"),
        (dict(rmax=-1.0), "scan 2: range_min"),
        (dict(angle_min=float("nan")), "scan 2: angle_min"),
    ],
)
def test_inconsistent_scans(tmp_path, scan2, fragment):
    path = tmp_path / "i.bag"
    with RawBag(path, "ros1") as bag:
        bag.connect("/scan", "sensor_msgs/msg/LaserScan")
        for i in range(4):
            kw = dict(ranges=[1.0, 2.0, 3.0])
            if i == 2:
                kw.update(scan2)
            bag.write("/scan", bag.scan(float(i), kw.pop("ranges"), **kw))
    with pytest.raises(DatasetFormatError, match=fragment) as err:
        read_bag_laser_scans(path)
    assert str(path) in str(err.value) and "'/scan'" in str(err.value)


# --------------------------------------------------------------------------- PointCloud2


def _pack_cloud(bag: RawBag, *, height, width, big, row_pad, stamp_s=3.25, frame="velo"):
    """A PointCloud2 packed value by value with struct: x y z float32, intensity uint8 at
    offset 13 (gap before it), ring uint16, t float64, rgb2 int16 x 2, 6 bytes of point
    padding, ``row_pad`` bytes at the end of each row. Returns the message and the expected
    fields."""
    rng = np.random.default_rng(height * 100 + width)
    n = height * width
    expect = {
        "x": rng.normal(size=n).astype(np.float32),
        "y": rng.normal(size=n).astype(np.float32),
        "z": rng.normal(size=n).astype(np.float32),
        "intensity": rng.integers(0, 256, n).astype(np.uint8),
        "ring": rng.integers(0, 65536, n).astype(np.uint16),
        "t": rng.normal(size=n),
        "rgb2": rng.integers(-32768, 32768, (n, 2)).astype(np.int16),
    }
    layout = [  # name, offset, datatype, count, struct code
        ("x", 0, 7, 1, "f"),
        ("y", 4, 7, 1, "f"),
        ("z", 8, 7, 1, "f"),
        ("intensity", 13, 2, 1, "B"),
        ("ring", 14, 4, 1, "H"),
        ("t", 16, 8, 1, "d"),
        ("rgb2", 24, 3, 2, "h"),
    ]
    point_step = 34
    row_step = width * point_step + row_pad
    e = ">" if big else "<"
    data = bytearray(b"\xab" * (height * row_step))
    for i in range(n):
        base = (i // width) * row_step + (i % width) * point_step
        for name, off, _, count, code in layout:
            values = expect[name][i].tolist() if count > 1 else [expect[name][i].item()]
            struct.pack_into(e + code * count, data, base + off, *values)
    T = bag.T
    msg = T["sensor_msgs/msg/PointCloud2"](
        header=bag.header(stamp_s, frame),
        height=height,
        width=width,
        fields=[
            T["sensor_msgs/msg/PointField"](name=nm, offset=off, datatype=dt, count=c)
            for nm, off, dt, c, _ in layout
        ],
        is_bigendian=big,
        point_step=point_step,
        row_step=row_step,
        data=np.frombuffer(bytes(data), dtype=np.uint8),
        is_dense=True,
    )
    shape = (height, width)
    return msg, {k: v.reshape(shape + v.shape[1:]) for k, v in expect.items()}


@pytest.mark.parametrize("kind", KINDS)
def test_point_clouds_layouts(tmp_path, kind):
    path = _bag_path(tmp_path, "pc", kind)
    cases = [
        dict(height=1, width=7, big=False, row_pad=0),
        dict(height=4, width=5, big=False, row_pad=3),
        dict(height=3, width=2, big=True, row_pad=5),
        dict(height=1, width=6, big=True, row_pad=0),
    ]
    with RawBag(path, kind) as bag:
        bag.connect("/points", "sensor_msgs/msg/PointCloud2")
        expected = []
        for i, case in enumerate(cases):
            msg, exp = _pack_cloud(bag, stamp_s=3.25 + i, **case)
            bag.write("/points", msg)
            expected.append(exp)
    clouds = read_bag_point_clouds(path)
    assert len(clouds) == len(cases)
    for i, (case, got, exp) in enumerate(zip(cases, clouds, expected, strict=True)):
        assert isinstance(got, BagPointCloud)
        assert got.stamp_s == 3.25 + i and got.frame_id == "velo"
        assert (got.cloud.height, got.cloud.width) == (case["height"], case["width"])
        assert got.cloud.is_organized == (case["height"] > 1)
        assert list(got.cloud.fields) == list(exp)
        for name, want in exp.items():
            arr = got.cloud[name]
            assert arr.dtype == want.dtype and arr.dtype.isnative, name
            np.testing.assert_array_equal(arr, want, err_msg=name)
    first = next(iter_bag_point_clouds(path, "/points"))
    np.testing.assert_array_equal(first.cloud["x"], expected[0]["x"])


@pytest.mark.parametrize("kind", KINDS)
def test_point_clouds_write_round_trip(tmp_path, kind):
    rng = np.random.default_rng(1)
    clouds = [
        BagPointCloud(
            PointCloud.from_fields(
                {
                    "x": rng.normal(size=(3, 4)).astype(np.float32),
                    "y": rng.normal(size=(3, 4)),
                    "label": rng.integers(-5, 5, (3, 4)).astype(np.int32),
                    "normal": rng.normal(size=(3, 4, 3)).astype(np.float32),
                }
            ),
            2.5,
            "lidar",
        ),
        BagPointCloud(
            PointCloud.from_fields({"x": np.array([np.nan, 1.0], np.float32)}), 2.5, "lidar2"
        ),
    ]
    path = write_bag_point_clouds(_bag_path(tmp_path, "w", kind), clouds, **_write_kw(kind))
    assert read_bag_topics(path) == {"/points": ("sensor_msgs/msg/PointCloud2", 2)}
    back = read_bag_point_clouds(path)
    for got, want in zip(back, clouds, strict=True):
        assert (got.stamp_s, got.frame_id) == (want.stamp_s, want.frame_id)
        assert list(got.cloud.fields) == list(want.cloud.fields)
        for name, arr in want.cloud.fields.items():
            assert got.cloud[name].dtype == arr.dtype
            np.testing.assert_array_equal(got.cloud[name], arr)
    bad = [BagPointCloud(PointCloud.from_fields({"x": np.zeros(2, np.int64)}), 0.0, "f")]
    with pytest.raises(ValueError, match="'x'"):
        write_bag_point_clouds(tmp_path / "bad.bag", bad)


@pytest.mark.parametrize(
    ("change", "fragment"),
    [
        (dict(datatype=9), "unknown datatype 9"),
        (dict(count=0), "count 0"),
        (dict(offset=31), "beyond point_step"),
        (dict(name="x"), "duplicate field name"),
        (dict(name="a b"), "invalid field name"),
        (dict(row_step=10), "row_step"),
        (dict(data_cut=1), "data bytes"),
    ],
)
def test_bad_point_cloud_layouts(tmp_path, change, fragment):
    path = tmp_path / "bad.bag"
    with RawBag(path, "ros1") as bag:
        bag.connect("/points", "sensor_msgs/msg/PointCloud2")
        good, _ = _pack_cloud(bag, height=1, width=3, big=False, row_pad=0)
        bag.write("/points", good)
        msg, _ = _pack_cloud(bag, height=1, width=3, big=False, row_pad=0)
        field = msg.fields[1]
        for key in ("datatype", "count", "offset", "name"):
            if key in change:
                setattr(field, key, change[key])
        if "row_step" in change:
            msg.row_step = change["row_step"]
        if "data_cut" in change:
            msg.data = msg.data[: -change["data_cut"]]
        bag.write("/points", msg)
    it = iter_bag_point_clouds(path)
    assert next(it).cloud.width == 3
    with pytest.raises(DatasetFormatError, match=fragment) as err:
        next(it)
    assert "cloud 1" in str(err.value) and "'/points'" in str(err.value)


# --------------------------------------------------------------------------- bad bags


def _storage_file(path: Path) -> Path:
    if path.is_file():
        return path
    return next(p for p in path.iterdir() if p.suffix in (".db3", ".mcap"))


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("cut", [0.0, 0.3, 0.9])
def test_truncated_bags(intel_bags, tmp_path, kind, cut):
    src = intel_bags[kind]
    dst = _bag_path(tmp_path, "cut", kind)
    if src.is_dir():
        shutil.copytree(src, dst)
    else:
        shutil.copy(src, dst)
    f = _storage_file(dst)
    raw = f.read_bytes()
    f.write_bytes(raw[: int(len(raw) * cut)])
    with pytest.raises(DatasetFormatError) as err:
        read_bag_laser_scans(dst, "/scan")
    assert str(dst) in str(err.value)


@pytest.mark.parametrize("kind", KINDS)
def test_garbage_bags(intel_bags, tmp_path, kind):
    dst = _bag_path(tmp_path, "garbage", kind)
    if kind == "ros1":
        dst.write_bytes(np.random.default_rng(0).bytes(4000))
    else:
        shutil.copytree(intel_bags[kind], dst)
        f = _storage_file(dst)
        f.write_bytes(np.random.default_rng(0).bytes(f.stat().st_size))
    for read in (read_bag_topics, read_bag_laser_scans, read_bag_point_clouds):
        with pytest.raises(DatasetFormatError, match="cannot open the bag") as err:
            read(dst)
        assert str(dst) in str(err.value)
    folder = tmp_path / "not_a_bag"
    folder.mkdir(exist_ok=True)
    with pytest.raises(DatasetFormatError):
        read_bag_topics(folder)
    with pytest.raises(FileNotFoundError):
        read_bag_topics(tmp_path / "missing.bag")


@pytest.mark.parametrize("kind", KINDS)
def test_topic_errors(intel_bags, tmp_path, kind):
    path = intel_bags[kind]
    cases = [
        (lambda: read_bag_laser_scans(path, "/odom"), "'/odom'.*nav_msgs/msg/Odometry"),
        (lambda: read_bag_laser_scans(path, "/nope"), "'/nope'.*no such topic.*/scan"),
        (lambda: read_bag_point_clouds(path), "no sensor_msgs/msg/PointCloud2 topic"),
        (lambda: read_bag_point_clouds(path, "/scan"), "'/scan'.*LaserScan"),
        (lambda: read_bag_odometry(path, "/tf"), "'/tf'"),
        (lambda: read_bag_laser_scans(path, odom_topic="/scan"), "'/scan'"),
    ]
    for call, pattern in cases:
        with pytest.raises(DatasetFormatError, match=pattern) as err:
            call()
        assert str(path) in str(err.value)
    # an empty topic (a connection without messages)
    empty = _bag_path(tmp_path, "empty", kind)
    with RawBag(empty, kind) as bag:
        bag.connect("/scan", "sensor_msgs/msg/LaserScan")
        bag.connect("/points", "sensor_msgs/msg/PointCloud2")
        bag.write("/points", _pack_cloud(bag, height=1, width=2, big=False, row_pad=0)[0])
    with pytest.raises(DatasetFormatError, match="'/scan'.*no messages") as err:
        read_bag_laser_scans(empty, "/scan")
    assert str(empty) in str(err.value)
    with pytest.raises(DatasetFormatError, match="no tf transforms"):
        read_bag_tf(empty, "map", "laser")


def _mutation_fuzz(log: CarmenLog, tmp_path: Path, kind: str, n: int, seed: int) -> dict:
    """Seeded byte mutations of a small bag: each is a DatasetFormatError naming the path or
    a log with the written layout whose ranges are valid readings or the no-return value."""
    src = write_bag_laser_scans(_bag_path(tmp_path, "src", kind), log, **_write_kw(kind))
    raw = _storage_file(src).read_bytes()
    rng = np.random.default_rng(seed)
    outcomes = {"rejected": 0, "read": 0}
    for k in range(n):
        mutant = bytearray(raw)
        for _ in range(int(rng.integers(1, 4))):
            mutant[int(rng.integers(len(mutant)))] = int(rng.integers(256))
        p = _bag_path(tmp_path, f"m{k}", kind)
        if src.is_dir():
            shutil.copytree(src, p)
            _storage_file(p).write_bytes(bytes(mutant))
        else:
            p.write_bytes(bytes(mutant))
        try:
            back = read_bag_laser_scans(p)
        except DatasetFormatError as err:
            assert str(p) in str(err)
            outcomes["rejected"] += 1
            continue
        outcomes["read"] += 1
        assert back.ranges_m.ndim == 2 and back.ranges_m.shape[1] == back.azimuths_rad.size
        assert np.all((back.ranges_m > 0) & (back.ranges_m <= back.max_range_m))
        assert np.isfinite(back.azimuths_rad).all()
    return outcomes


def test_mutated_bags_fast(intel30, tmp_path):
    outcomes = _mutation_fuzz(intel30.subset(slice(0, 5)), tmp_path, "ros1", 15, seed=7)
    assert outcomes["rejected"] > 0 and outcomes["read"] > 0


@pytest.mark.slow  # ~100 bag reads per storage: runs in make test-slow / CI
@pytest.mark.parametrize("kind", KINDS)
def test_mutated_bags(intel30, tmp_path, kind):
    outcomes = _mutation_fuzz(intel30.subset(slice(0, 10)), tmp_path, kind, 100, seed=11)
    assert outcomes["rejected"] > 0 and outcomes["read"] > 0
