"""Reader and writer for ROS bags (ROS 1 ``.bag`` files, ROS 2 ``sqlite3`` / ``mcap`` bags).

Built on the pure-Python :mod:`rosbags` library. A ROS 1 bag is one file ending in ``.bag``;
a ROS 2 bag is a folder holding ``metadata.yaml`` and its storage files (a single ``.db3``
or ``.mcap`` file can be read on its own as well).

Readers:

- :func:`read_bag_topics`: topic -> ``(message type, message count)``.
- :func:`read_bag_laser_scans`: ``sensor_msgs/msg/LaserScan`` -> the
  :class:`~lidarjax.datasets.CarmenLog` that :func:`~lidarjax.datasets.load_carmen` returns,
  with poses from ``tf`` and odometry from ``nav_msgs/msg/Odometry`` (or ``tf``) sampled at
  the scan stamps.
- :func:`iter_bag_point_clouds` / :func:`read_bag_point_clouds`:
  ``sensor_msgs/msg/PointCloud2`` -> :class:`BagPointCloud` (a
  :class:`~lidarjax.datasets.PointCloud` with its stamp and frame).
- :func:`read_bag_odometry`, :func:`read_bag_tf`: pose time series.

Writers (:func:`write_bag_laser_scans`, :func:`write_bag_point_clouds`) make bags that these
readers read back exactly up to the rounding the message types impose (float32 ranges and
angles, nanosecond stamps).

Every message is decoded with NumPy views of its byte buffers (no Python loop per beam or
point). A bag that cannot be read (truncated, garbage, wrong message type on the requested
topic, missing or empty topic, inconsistent scans) raises
:class:`~lidarjax.datasets.DatasetFormatError` naming the path and the topic.

Time handling: message *header stamps* (``header.stamp``) are the timestamps returned and the
times at which poses are sampled; the bag's own record times only fix the message order,
which is the order the readers return.

Sampling a pose series (``tf`` edges, odometry) at a query stamp ``t``:

1. *Exact stamps*: if messages carry exactly the stamp ``t``, the value of such a message is
   used as is. When several messages share one stamp (and several queries share it too),
   the ``k``-th query with that stamp takes the ``k``-th message with that stamp in bag order
   (the last one once they run out). This keeps logs with repeated or constant timestamps,
   which CARMEN logs have, exact.
2. Otherwise the two messages around ``t`` are interpolated: linearly in translation,
   spherically (slerp) in rotation.
3. Before the first or after the last message: NaN (no extrapolation). ``tf_static``
   transforms hold at every time (the last one sent for an edge wins).
"""

from __future__ import annotations

import math
import os
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np

from ._carmen import CarmenLog
from ._errors import DatasetFormatError
from ._pcd import PointCloud

__all__ = [
    "BagPointCloud",
    "iter_bag_point_clouds",
    "read_bag_laser_scans",
    "read_bag_odometry",
    "read_bag_point_clouds",
    "read_bag_tf",
    "read_bag_topics",
    "write_bag_laser_scans",
    "write_bag_point_clouds",
]

LASER_SCAN = "sensor_msgs/msg/LaserScan"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
_TF_TYPES = (TF_MESSAGE, "tf/msg/tfMessage")  # ROS 1 bags may carry the old tf type
_TF_TOPICS = {"/tf": False, "tf": False, "/tf_static": True, "tf_static": True}  # -> static

_BAG_FORMAT = (
    "a ROS 1 bag file ending in .bag, or a ROS 2 bag folder with metadata.yaml (or its "
    "single .db3 / .mcap file)"
)
_NS = 1_000_000_000
_T = TypeVar("_T")
_MAX_SEC = 2**31 - 1  # builtin_interfaces/Time.sec is int32 (ROS 1 time is uint32)

# PointField.datatype -> NumPy type code (sensor_msgs/msg/PointField constants).
_POINTFIELD_DTYPES: dict[int, str] = {
    1: "i1",  # INT8
    2: "u1",  # UINT8
    3: "i2",  # INT16
    4: "u2",  # UINT16
    5: "i4",  # INT32
    6: "u4",  # UINT32
    7: "f4",  # FLOAT32
    8: "f8",  # FLOAT64
}
_DTYPE_TO_POINTFIELD: dict[str, int] = {code: dt for dt, code in _POINTFIELD_DTYPES.items()}


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


# --------------------------------------------------------------------------------------------
# Containers
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class BagPointCloud:
    """One ``sensor_msgs/msg/PointCloud2`` message.

    Attributes:
        cloud: The points; one field per ``PointField`` (native byte order, dtype from the
            field's datatype), shape ``[height, width]`` or ``[height, width, count]``.
            ``viewpoint`` is the identity (``PointCloud2`` has no viewpoint).
        stamp_s: ``header.stamp`` in seconds.
        frame_id: ``header.frame_id``, the frame the points are expressed in.
    """

    cloud: PointCloud
    stamp_s: float
    frame_id: str


# --------------------------------------------------------------------------------------------
# Opening bags and reading topics
# --------------------------------------------------------------------------------------------


def _stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * _NS + int(stamp.nanosec)


def _seconds(ns: int) -> float:
    return ns / _NS  # int / int: correctly rounded


def _ns_from_seconds(t: float, what: str) -> int:
    if not (math.isfinite(t) and 0.0 <= t <= _MAX_SEC):
        raise ValueError(
            f"{what} must be finite seconds in [0, {_MAX_SEC}] for a ROS stamp, got {t!r}"
        )
    return round(Fraction(t) * _NS)  # the nearest nanosecond, exactly


def _tf_frame(name: str) -> str:
    return name[1:] if name.startswith("/") else name  # tf2 ignores a leading slash


class _Bag:
    """An open bag; every failure of :mod:`rosbags` becomes a ``DatasetFormatError``."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"no such bag: {str(self.path)!r}")
        self.reader: Any = None

    def error(
        self, message: str, topic: str | None = None, expected: str | None = None
    ) -> DatasetFormatError:
        where = "" if topic is None else f"topic {topic!r}: "
        return DatasetFormatError(self.path, where + message, expected=expected)

    def __enter__(self) -> _Bag:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        is_ros1 = self.path.suffix == ".bag"
        default = get_typestore(Stores.ROS1_NOETIC if is_ros1 else Stores.ROS2_HUMBLE)
        # The boundary with a third-party parser: anything it raises on a damaged file
        # (its own errors, struct/sqlite/zstd/unicode errors, ...) is a format error here.
        try:
            reader = AnyReader([self.path], default_typestore=default)
            reader.open()
        except Exception as exc:
            raise self.error(
                f"cannot open the bag ({type(exc).__name__}: {exc})", expected=_BAG_FORMAT
            ) from exc
        self.reader = reader
        try:
            self.topics = self._topics()
        except BaseException:
            self.reader.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        reader, self.reader = self.reader, None
        if reader is not None:
            try:
                reader.close()
            except Exception:
                if exc[0] is None:
                    raise

    def _topics(self) -> dict[str, tuple[str, int, list[Any]]]:
        out: dict[str, tuple[str, int, list[Any]]] = {}
        for conn in self.reader.connections:
            msgtype, count, conns = out.get(conn.topic, (conn.msgtype, 0, []))
            if msgtype != conn.msgtype:
                raise self.error(
                    f"carries two message types, {msgtype} and {conn.msgtype}", conn.topic
                )
            out[conn.topic] = (msgtype, count + int(conn.msgcount), [*conns, conn])
        return out

    def describe(self) -> str:
        if not self.topics:
            return "the bag has no topics"
        return "topics: " + ", ".join(f"{t} ({m})" for t, (m, _, _) in sorted(self.topics.items()))

    def of_type(self, msgtypes: Sequence[str]) -> list[str]:
        return sorted(t for t, (m, _, _) in self.topics.items() if m in msgtypes)

    def choose(self, topic: str | None, msgtype: str) -> str:
        """The topic to read: ``topic`` checked, or the only topic of ``msgtype``."""
        if topic is None:
            candidates = self.of_type([msgtype])
            if not candidates:
                raise self.error(f"no {msgtype} topic; {self.describe()}")
            if len(candidates) > 1:
                raise ValueError(
                    f"{self.path}: several {msgtype} topics {candidates}; choose one with topic="
                )
            topic = candidates[0]
        self.check(topic, (msgtype,))
        return topic

    def check(self, topic: str, msgtypes: Sequence[str]) -> None:
        if topic not in self.topics:
            raise self.error(f"no such topic; {self.describe()}", topic)
        msgtype, count, _ = self.topics[topic]
        if msgtype not in msgtypes:
            raise self.error(f"has message type {msgtype}, expected {' or '.join(msgtypes)}", topic)
        if count == 0:
            raise self.error("has no messages (empty topic)", topic)

    def messages(self, topic: str, extract: Callable[[int, Any], _T]) -> Iterator[_T]:
        """``extract(index, message)`` for the messages of ``topic`` in bag order.

        Raises a ``DatasetFormatError`` if a message cannot be read, if ``extract`` finds
        it without the fields and types of its message type (a bag whose embedded message
        definition differs from the standard one), or if none can be read.
        """
        msgtype, _, conns = self.topics[topic]
        n = 0
        try:
            it = self.reader.messages(connections=conns)
            while True:
                try:
                    _, _, raw = next(it)
                except StopIteration:
                    break
                msg = self.reader.deserialize(raw, msgtype)
                try:
                    value = extract(n, msg)
                except DatasetFormatError:
                    raise
                except (AttributeError, TypeError, ValueError, OverflowError) as exc:
                    raise self.error(
                        f"message {n} does not have the fields of {msgtype} "
                        f"({type(exc).__name__}: {exc})",
                        topic,
                    ) from exc
                n += 1
                yield value
        except (GeneratorExit, DatasetFormatError):
            raise
        except Exception as exc:
            raise self.error(
                f"cannot read message {n} ({type(exc).__name__}: {exc})", topic
            ) from exc
        if n == 0:
            raise self.error("has no readable messages (empty or truncated topic)", topic)


def read_bag_topics(path: str | os.PathLike[str]) -> dict[str, tuple[str, int]]:
    """The topics of a bag.

    Args:
        path: A ROS 1 ``.bag`` file, or a ROS 2 bag folder (or its ``.db3`` / ``.mcap`` file).

    Returns:
        Topic name -> ``(message type, number of messages)``, sorted by topic name. Message
        types are spelt the ROS 2 way (``sensor_msgs/msg/LaserScan``) for both ROS versions.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        DatasetFormatError: The bag cannot be opened (truncated, garbage, not a bag), or a
            topic carries two message types.
    """
    with _Bag(path) as bag:
        return {t: (m, c) for t, (m, c, _) in sorted(bag.topics.items())}


# --------------------------------------------------------------------------------------------
# Rigid transforms: translation [n 3] + unit quaternion [n 4] (w, x, y, z), vectorised
# --------------------------------------------------------------------------------------------


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def _qrotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def _compose(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]):
    (ta, qa), (tb, qb) = a, b
    return ta + _qrotate(qa, tb), _qmul(qa, qb)


def _inverse(a: tuple[np.ndarray, np.ndarray]):
    t, q = a
    qc = q * np.array([1.0, -1.0, -1.0, -1.0])
    return -_qrotate(qc, t), qc


def _yaw(q: np.ndarray) -> np.ndarray:
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def _planar(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``[n 3]`` (x [m], y [m], yaw [rad] in (-pi, pi])."""
    return np.column_stack([t[:, 0], t[:, 1], _yaw(q)])


def _quat_from_yaw(yaw: np.ndarray) -> np.ndarray:
    yaw = np.asarray(yaw, dtype=np.float64)
    zeros = np.zeros_like(yaw)
    return np.stack([np.cos(yaw / 2), zeros, zeros, np.sin(yaw / 2)], axis=-1)


def _slerp(q0: np.ndarray, q1: np.ndarray, w: np.ndarray) -> np.ndarray:
    d = np.sum(q0 * q1, axis=-1)
    q1 = np.where(d[:, None] < 0, -q1, q1)
    d = np.abs(d)
    theta = np.arccos(np.clip(d, -1.0, 1.0))
    s = np.sin(theta)
    small = s < 1e-9
    safe = np.where(small, 1.0, s)
    a = np.where(small, 1.0 - w, np.sin((1.0 - w) * theta) / safe)
    b = np.where(small, w, np.sin(w * theta) / safe)
    q = a[:, None] * q0 + b[:, None] * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _rank_among_equal(x: np.ndarray) -> np.ndarray:
    """For each entry, how many earlier entries have the same value."""
    order = np.argsort(x, kind="stable")
    xs = x[order]
    rank = np.empty(x.shape, dtype=np.int64)
    rank[order] = np.arange(x.size) - np.searchsorted(xs, xs, side="left")
    return rank


@dataclass
class _Series:
    """A pose time series (messages in bag order); ``static``: valid at all times."""

    stamps_ns: np.ndarray  # int64 [n]
    t: np.ndarray  # [n 3]
    q: np.ndarray  # [n 4] unit, (w, x, y, z)
    static: bool = False

    def sample(self, query_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(t [m 3], q [m 4])`` at the query stamps (module docstring: exact stamps first,
        then interpolation; NaN outside the series)."""
        m = query_ns.size
        if self.static:
            return np.repeat(self.t[-1:], m, axis=0), np.repeat(self.q[-1:], m, axis=0)
        order = np.argsort(self.stamps_ns, kind="stable")
        s, ts, qs = self.stamps_ns[order], self.t[order], self.q[order]
        left = np.searchsorted(s, query_ns, side="left")
        right = np.searchsorted(s, query_ns, side="right")
        exact = right > left
        t_out = np.full((m, 3), np.nan)
        q_out = np.full((m, 4), np.nan)
        idx = (left + np.minimum(_rank_among_equal(query_ns), right - left - 1))[exact]
        t_out[exact], q_out[exact] = ts[idx], qs[idx]
        inside = ~exact & (right > 0) & (right < s.size)
        lo, hi = right[inside] - 1, right[inside]
        w = (query_ns[inside] - s[lo]).astype(np.float64) / (s[hi] - s[lo]).astype(np.float64)
        t_out[inside] = ts[lo] + w[:, None] * (ts[hi] - ts[lo])
        q_out[inside] = _slerp(qs[lo], qs[hi], w)
        return t_out, q_out


def _unit_quaternions(
    bag: _Bag, topic: str, q: np.ndarray, what: str
) -> tuple[np.ndarray, np.ndarray]:
    with np.errstate(all="ignore"):  # huge values: inf norm, rejected below
        norm = np.linalg.norm(q, axis=-1)
    bad = ~(np.isfinite(norm) & (norm > 0.5) & (norm < 2.0))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise bag.error(
            f"{what} {i} has an invalid rotation quaternion (x, y, z, w) = "
            f"{tuple(float(v) for v in q[i, [1, 2, 3, 0]])}",
            topic,
        )
    return q / norm[:, None], norm


def _check_finite(bag: _Bag, topic: str, t: np.ndarray, what: str) -> None:
    bad = ~np.isfinite(t).all(axis=-1)
    if bad.any():
        raise bag.error(f"{what} {int(np.flatnonzero(bad)[0])} has a non-finite position", topic)


# --------------------------------------------------------------------------------------------
# tf
# --------------------------------------------------------------------------------------------


def _tf_transforms(_: int, msg: Any) -> list[tuple[tuple[str, str], int, tuple[float, ...]]]:
    out = []
    for tr in msg.transforms:
        key = (_tf_frame(str(tr.header.frame_id)), _tf_frame(str(tr.child_frame_id)))
        t, r = tr.transform.translation, tr.transform.rotation
        values = (
            float(t.x),
            float(t.y),
            float(t.z),
            float(r.w),
            float(r.x),
            float(r.y),
            float(r.z),
        )
        out.append((key, _stamp_ns(tr.header.stamp), values))
    return out


class _TfTree:
    """The ``tf`` / ``tf_static`` transforms of a bag: edges ``(parent, child)`` -> series."""

    def __init__(self, edges: dict[tuple[str, str], _Series]) -> None:
        self.edges = edges
        self.adjacent: dict[str, list[str]] = {}
        for parent, child in edges:
            self.adjacent.setdefault(parent, []).append(child)
            self.adjacent.setdefault(child, []).append(parent)

    @classmethod
    def read(cls, bag: _Bag) -> _TfTree:
        raw: dict[tuple[str, str], tuple[bool, list[int], list[tuple[float, ...]]]] = {}
        for topic, static in _TF_TOPICS.items():
            if topic not in bag.topics or bag.topics[topic][0] not in _TF_TYPES:
                continue
            if bag.topics[topic][1] == 0:
                continue
            for transforms in bag.messages(topic, _tf_transforms):
                for key, stamp, values in transforms:
                    entry = raw.setdefault(key, (static, [], []))
                    entry[1].append(stamp)
                    entry[2].append(values)
        edges: dict[tuple[str, str], _Series] = {}
        for key, (static, stamps, values) in raw.items():
            v = np.array(values, dtype=np.float64).reshape(-1, 7)
            what = f"transform {key[0]} -> {key[1]}"
            topic = "/tf_static" if static else "/tf"
            _check_finite(bag, topic, v[:, :3], what)
            q, _ = _unit_quaternions(bag, topic, v[:, 3:], what)
            edges[key] = _Series(np.array(stamps, dtype=np.int64), v[:, :3], q, static)
        return cls(edges)

    def frames(self) -> list[str]:
        return sorted(self.adjacent)

    def path(self, target: str, source: str) -> list[str] | None:
        if target not in self.adjacent or source not in self.adjacent:
            return None
        previous: dict[str, str | None] = {target: None}
        queue = deque([target])
        while queue:
            frame = queue.popleft()
            if frame == source:
                out = [frame]
                while (p := previous[out[-1]]) is not None:
                    out.append(p)
                return out[::-1]
            for nxt in self.adjacent[frame]:
                if nxt not in previous:
                    previous[nxt] = frame
                    queue.append(nxt)
        return None

    def chain(self, target: str, source: str) -> list[tuple[_Series, bool]] | None:
        """The edges from ``target`` to ``source``, each with ``inverted``; None if unlinked."""
        frames = self.path(target, source)
        if frames is None:
            return None
        out = []
        for a, b in zip(frames[:-1], frames[1:], strict=True):
            if (a, b) in self.edges:
                out.append((self.edges[(a, b)], False))
            else:
                out.append((self.edges[(b, a)], True))
        return out

    def lookup(
        self, target: str, source: str, query_ns: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Pose of ``source`` in ``target`` at the query stamps (NaN where a link of the
        chain has no data); None if the frames are not linked."""
        target, source = _tf_frame(target), _tf_frame(source)
        m = query_ns.size
        pose = (np.zeros((m, 3)), np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (m, 1)))
        if target == source:
            return pose
        chain = self.chain(target, source)
        if chain is None:
            return None
        for series, inverted in chain:
            step = series.sample(query_ns)
            pose = _compose(pose, _inverse(step) if inverted else step)
        return pose


# --------------------------------------------------------------------------------------------
# Odometry and tf readers
# --------------------------------------------------------------------------------------------


def _odometry_series(bag: _Bag, topic: str) -> tuple[_Series, str]:
    def extract(_: int, msg: Any) -> tuple[int, tuple[float, ...], str]:
        p, o = msg.pose.pose.position, msg.pose.pose.orientation
        values = (float(p.x), float(p.y), float(p.z), float(o.w), float(o.x), float(o.y))
        return _stamp_ns(msg.header.stamp), (*values, float(o.z)), str(msg.child_frame_id)

    rows = list(bag.messages(topic, extract))
    stamps = [r[0] for r in rows]
    child = _tf_frame(rows[0][2])
    v = np.array([r[1] for r in rows], dtype=np.float64)
    _check_finite(bag, topic, v[:, :3], "odometry message")
    q, _ = _unit_quaternions(bag, topic, v[:, 3:], "odometry message")
    return _Series(np.array(stamps, dtype=np.int64), v[:, :3], q), child


def read_bag_odometry(
    path: str | os.PathLike[str], topic: str | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The planar poses of the ``nav_msgs/msg/Odometry`` messages of a topic.

    Args:
        path: The bag (see :func:`read_bag_topics`).
        topic: The odometry topic; ``None`` picks the bag's only ``Odometry`` topic.

    Returns:
        ``(stamps_s, poses)`` in bag order: ``header.stamp`` in seconds, float64 ``[n]``, and
        ``poses [n 3]`` = ``(x [m], y [m], yaw [rad] in (-pi, pi])`` of ``child_frame_id`` in
        ``header.frame_id`` (``pose.pose``; the quaternion is normalised and reduced to its
        yaw, z is dropped).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: ``topic`` is None and the bag has several ``Odometry`` topics.
        DatasetFormatError: Unreadable bag; missing, empty or not-``Odometry`` topic;
            non-finite position or invalid quaternion (the message index is named).
    """
    with _Bag(path) as bag:
        topic = bag.choose(topic, ODOMETRY)
        series, _ = _odometry_series(bag, topic)
    stamps = np.array([_seconds(int(s)) for s in series.stamps_ns], dtype=np.float64)
    return stamps, _planar(series.t, series.q)


def read_bag_tf(
    path: str | os.PathLike[str],
    parent: str,
    child: str,
    *,
    stamps_s: Sequence[float] | np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The pose of frame ``child`` in frame ``parent`` from the bag's ``tf`` transforms.

    The ``tf2_msgs/msg/TFMessage`` topics ``/tf`` and ``/tf_static`` are read (also
    ``tf/tfMessage`` in ROS 1 bags). The two frames may be linked through any chain of
    transforms in the tf tree (e.g. ``map -> odom -> base_link -> laser``); every link is
    sampled at the stamps as the module docstring describes and the links are composed in
    SE(3). A leading ``/`` in frame names is ignored, as tf2 does.

    Args:
        path: The bag (see :func:`read_bag_topics`).
        parent: Target frame, e.g. ``"map"``.
        child: Source frame, e.g. ``"base_link"``.
        stamps_s: Times in seconds at which to sample; default: the stamps of all
            ``/tf`` messages of the non-static links of the chain (sorted, without
            repeats), or the last stamp of a purely static chain.

    Returns:
        ``(stamps_s [n], poses [n 7])``: float64 seconds, and ``x y z [m], qw qx qy qz``
        (unit quaternion, the ``viewpoint`` order of :class:`PointCloud`) of ``child`` in
        ``parent``. Rows where a link has no data around the stamp are NaN.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: ``parent`` and ``child`` are the same frame, or ``stamps_s`` holds a
            value that is not a finite number of seconds in ``[0, 2**31 - 1]``.
        DatasetFormatError: Unreadable bag, no tf transforms, a frame missing from the tf
            tree or the two frames not linked (the known frames are listed), or a transform
            with a non-finite translation or invalid quaternion.
    """
    if _tf_frame(parent) == _tf_frame(child):
        raise ValueError(f"parent and child are the same frame {parent!r}")
    with _Bag(path) as bag:
        tree = _TfTree.read(bag)
        if not tree.edges:
            raise bag.error(f"no tf transforms (no /tf or /tf_static topic); {bag.describe()}")
        chain = tree.chain(_tf_frame(parent), _tf_frame(child))
        if chain is None:
            raise bag.error(
                f"tf has no chain of transforms from frame {parent!r} to frame {child!r}; "
                f"frames: {tree.frames()}",
                "/tf",
            )
    if stamps_s is None:
        dynamic = [s.stamps_ns for s, _ in chain if not s.static]
        if dynamic:
            query = np.unique(np.concatenate(dynamic))
        else:
            query = np.array([max(int(s.stamps_ns[-1]) for s, _ in chain)], np.int64)
    else:
        values = np.asarray(stamps_s, dtype=np.float64).reshape(-1)
        query = np.array([_ns_from_seconds(float(v), "stamps_s") for v in values], np.int64)
    found = tree.lookup(parent, child, query)
    assert found is not None  # the chain exists
    t, q = found
    stamps = np.array([_seconds(int(s)) for s in query], dtype=np.float64)
    return stamps, np.concatenate([t, q], axis=1)


# --------------------------------------------------------------------------------------------
# LaserScan
# --------------------------------------------------------------------------------------------

_SCAN_EXPECTED = (
    "LaserScan messages with one frame_id, angle_min, angle_increment, range_max and number "
    "of beams, finite angles and 0 <= range_min <= range_max, range_max > 0"
)


def read_bag_laser_scans(
    path: str | os.PathLike[str],
    topic: str | None = None,
    *,
    usable_range_m: float | None = None,
    odom_topic: str | None = None,
    map_frame: str = "map",
    odom_frame: str = "odom",
    base_frame: str | None = None,
) -> CarmenLog:
    """Read the ``sensor_msgs/msg/LaserScan`` messages of a topic as a :class:`CarmenLog`.

    Scans come in bag order. Like :func:`load_carmen`, the log keeps raw readings with every
    no-return at the maximum: a reading that is NaN, infinite, ``<= 0``, below the scan's
    ``range_min`` or above its ``range_max`` is stored as ``max_range_m = range_max``; every
    other reading is its float32 value widened to float64. ``intensities``,
    ``time_increment``, ``scan_time`` and ``angle_max`` are not used.

    Poses and odometry are sampled at the scans' header stamps (module docstring):

    - ``poses``: the pose of ``base_frame`` in ``map_frame`` from ``/tf`` + ``/tf_static``,
      composing the chain of transforms between them (typically ``map -> odom -> base``).
    - ``odometry``: from the ``nav_msgs/msg/Odometry`` topic ``odom_topic`` (by default the
      bag's only one): its ``child_frame_id`` pose in its ``header.frame_id``, moved to
      ``base_frame`` through tf when the two differ and tf links them (as published when tf
      does not). Without an ``Odometry`` topic: the pose of ``base_frame`` in ``odom_frame``
      from tf.

    Rows that cannot be computed (no tf or odometry in the bag, frames not linked, a scan
    stamp outside the span of the messages) are NaN, never zeros.

    Args:
        path: The bag (see :func:`read_bag_topics`).
        topic: The ``LaserScan`` topic; ``None`` picks the bag's only one.
        usable_range_m: Readings at or beyond it are no-returns (metres); default
            ``max_range_m`` (a ``LaserScan`` does not record a smaller usable range, so pass
            ``log.usable_range_m`` to restore it for a log written by
            :func:`write_bag_laser_scans`).
        odom_topic: The ``Odometry`` topic; ``None``: the bag's only one, or tf.
        map_frame: tf frame of the poses.
        odom_frame: tf frame of the odometry when the bag has no ``Odometry`` topic.
        base_frame: tf frame whose pose is returned; default the scans' ``header.frame_id``
            (the laser, as in CARMEN logs).

    Returns:
        The log: ``ranges_m [n_scans n_beams]``; ``azimuths_rad [n_beams]`` =
        ``angle_min + k * angle_increment`` (computed in float64 from the float32 fields);
        ``poses``, ``odometry [n_scans 3]`` as ``(x [m], y [m], yaw [rad] in (-pi, pi])``;
        ``timestamps_s [n_scans]`` from ``header.stamp`` (nearest float64 to the
        nanosecond stamp); ``max_range_m`` = ``range_max``; ``path`` = ``path``.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: ``topic`` (``odom_topic``) is None and the bag has several ``LaserScan``
            (``Odometry``) topics; ``usable_range_m`` is not a positive number.
        DatasetFormatError: Unreadable bag; missing, empty or wrongly typed topic; a scan
            whose ``frame_id``, ``angle_min``, ``angle_increment``, ``range_max`` or number
            of beams differs from the first scan's (the scan index is named); no beams;
            non-finite angles; ``range_min``/``range_max`` not ``0 <= range_min <=
            range_max``, ``range_max > 0``; invalid odometry or tf values.
    """
    if usable_range_m is not None and not (math.isfinite(usable_range_m) and usable_range_m > 0):
        raise ValueError(f"usable_range_m must be a positive number, got {usable_range_m!r}")
    with _Bag(path) as bag:
        topic = bag.choose(topic, LASER_SCAN)
        if odom_topic is None:
            odoms = bag.of_type([ODOMETRY])
            if len(odoms) > 1:
                raise ValueError(
                    f"{bag.path}: several {ODOMETRY} topics {odoms}; choose one with odom_topic="
                )
            odom_topic = odoms[0] if odoms else None
        else:
            bag.check(odom_topic, (ODOMETRY,))
        rows = list(bag.messages(topic, _scan_fields))
        stamps = [r[0] for r in rows]
        frames = [r[1] for r in rows]
        params = [r[2] for r in rows]
        ranges = [r[3] for r in rows]
        scans = _scan_arrays(bag, topic, stamps, frames, params, ranges, usable_range_m)
        stamps_ns = np.array(stamps, dtype=np.int64)
        base = _tf_frame(base_frame if base_frame is not None else frames[0])
        tree = _TfTree.read(bag)
        n = stamps_ns.size
        poses = np.full((n, 3), np.nan)
        found = tree.lookup(map_frame, base, stamps_ns)
        if found is not None:
            poses = _planar(*found)
        odometry = np.full((n, 3), np.nan)
        if odom_topic is not None:
            series, child = _odometry_series(bag, odom_topic)
            pose = series.sample(stamps_ns)
            if child and child != base:
                link = tree.lookup(child, base, stamps_ns)
                if link is not None:
                    pose = _compose(pose, link)
            odometry = _planar(*pose)
        else:
            found = tree.lookup(odom_frame, base, stamps_ns)
            if found is not None:
                odometry = _planar(*found)
    ranges_m, azimuths, max_range, usable = scans
    return CarmenLog(
        ranges_m=_readonly(ranges_m),
        azimuths_rad=_readonly(azimuths),
        poses=_readonly(np.ascontiguousarray(poses)),
        odometry=_readonly(np.ascontiguousarray(odometry)),
        timestamps_s=_readonly(np.array([_seconds(s) for s in stamps], dtype=np.float64)),
        max_range_m=max_range,
        usable_range_m=usable,
        path=Path(path),
    )


def _scan_fields(_: int, msg: Any) -> tuple[int, str, tuple[float, ...], np.ndarray]:
    r = msg.ranges
    if not (isinstance(r, np.ndarray) and r.dtype == np.float32 and r.ndim == 1):
        raise TypeError("ranges is not a float32 sequence")
    params = (msg.angle_min, msg.angle_increment, msg.range_min, msg.range_max, r.size)
    return _stamp_ns(msg.header.stamp), str(msg.header.frame_id), tuple(map(float, params)), r


def _scan_arrays(
    bag: _Bag,
    topic: str,
    stamps: list[int],
    frames: list[str],
    params: list[tuple[float, ...]],
    ranges: list[np.ndarray],
    usable_range_m: float | None,
) -> tuple[np.ndarray, np.ndarray, float, float]:
    def fail(i: int, message: str) -> DatasetFormatError:
        return DatasetFormatError(
            bag.path, f"topic {topic!r}: scan {i}: {message}", expected=_SCAN_EXPECTED
        )

    p = np.array(params, dtype=np.float64)  # [n 5]
    angle_min, increment, range_min, range_max, n_beams = p.T
    for i in np.flatnonzero([f != frames[0] for f in frames])[:1]:
        raise fail(int(i), f"frame_id {frames[i]!r} differs from scan 0's {frames[0]!r}")
    for column, name in ((angle_min, "angle_min"), (increment, "angle_increment")):
        for i in np.flatnonzero(~np.isfinite(column))[:1]:
            raise fail(int(i), f"{name} is {column[i]!r}")
    bad = ~(np.isfinite(range_min) & np.isfinite(range_max) & (range_max > 0))
    bad |= ~((range_min >= 0) & (range_min <= range_max))
    for i in np.flatnonzero(bad)[:1]:
        raise fail(int(i), f"range_min {range_min[i]!r} and range_max {range_max[i]!r}")
    if n_beams[0] == 0:
        raise fail(0, "has no beams")
    for column, name in (
        (angle_min, "angle_min"),
        (increment, "angle_increment"),
        (range_max, "range_max"),
        (n_beams, "number of beams"),
    ):
        for i in np.flatnonzero(column != column[0])[:1]:
            raise fail(
                int(i),
                f"{name} {column[i]!r} differs from scan 0's {column[0]!r} (the beams "
                "must have the same angles in every scan)",
            )
    with np.errstate(invalid="ignore"):  # a signalling NaN warns when widened
        raw = np.stack(ranges).astype(np.float64)  # [n_scans n_beams]
    max_range = float(range_max[0])
    valid = np.isfinite(raw) & (raw > 0) & (raw >= range_min[:, None]) & (raw <= max_range)
    ranges_m = np.where(valid, raw, max_range)
    azimuths = angle_min[0] + np.arange(int(n_beams[0])) * increment[0]
    usable = max_range if usable_range_m is None else float(usable_range_m)
    return ranges_m, azimuths, max_range, usable


# --------------------------------------------------------------------------------------------
# PointCloud2
# --------------------------------------------------------------------------------------------

_CLOUD_EXPECTED = (
    "PointCloud2 with fields of datatype 1-8 and count >= 1 inside point_step, "
    "row_step >= width * point_step and len(data) == height * row_step"
)


def _decode_cloud(bag: _Bag, topic: str, index: int, msg: Any) -> BagPointCloud:
    def fail(message: str) -> DatasetFormatError:
        return DatasetFormatError(
            bag.path, f"topic {topic!r}: cloud {index}: {message}", expected=_CLOUD_EXPECTED
        )

    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    endian = ">" if msg.is_bigendian else "<"
    if not msg.fields:
        raise fail("has no fields")
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    for field in msg.fields:
        name = str(field.name)
        code = _POINTFIELD_DTYPES.get(int(field.datatype))
        count, offset = int(field.count), int(field.offset)
        if code is None:
            raise fail(f"field {name!r} has unknown datatype {int(field.datatype)}")
        if count < 1:
            raise fail(f"field {name!r} has count {count}")
        if not name or any(ch.isspace() for ch in name):
            raise fail(f"invalid field name {name!r}")
        if name in names:
            raise fail(f"duplicate field name {name!r}")
        dtype = np.dtype(endian + code)
        if offset + dtype.itemsize * count > point_step:
            raise fail(
                f"field {name!r} (offset {offset}, {count} x {dtype.itemsize} bytes) ends "
                f"beyond point_step {point_step}"
            )
        names.append(name)
        formats.append(dtype if count == 1 else (dtype, (count,)))
        offsets.append(offset)
    data = msg.data
    if not (isinstance(data, np.ndarray) and data.dtype == np.uint8 and data.ndim == 1):
        raise TypeError("data is not a uint8 sequence")
    if row_step < width * point_step:
        raise fail(f"row_step {row_step} < width {width} * point_step {point_step}")
    if data.size != height * row_step:
        raise fail(f"has {data.size} data bytes, not height {height} * row_step {row_step}")
    record = np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step}
    )
    rows = data.reshape(height, row_step)[:, : width * point_step]
    points = np.ascontiguousarray(rows).view(record).reshape(height, width)
    fields = {}
    for name in names:
        arr = points[name]
        fields[name] = np.ascontiguousarray(arr, dtype=arr.dtype.newbyteorder("="))
    cloud = PointCloud(fields=fields, width=width, height=height)
    return BagPointCloud(cloud, _seconds(_stamp_ns(msg.header.stamp)), str(msg.header.frame_id))


def iter_bag_point_clouds(
    path: str | os.PathLike[str], topic: str | None = None
) -> Iterator[BagPointCloud]:
    """Iterate over the ``sensor_msgs/msg/PointCloud2`` messages of a topic, in bag order.

    The bag is opened and the topic checked when this function is called; the clouds are
    decoded one message at a time (one NumPy view per message). Each ``PointField`` becomes
    a field of the cloud with the dtype of its datatype (INT8 .. FLOAT64 -> int8 .. float64),
    converted to native byte order (``is_bigendian`` is honoured); bytes between fields and
    at the end of ``point_step`` and of ``row_step`` are skipped. Organised clouds
    (``height > 1``) keep their ``[height, width]`` layout.

    Args:
        path: The bag (see :func:`read_bag_topics`).
        topic: The ``PointCloud2`` topic; ``None`` picks the bag's only one.

    Yields:
        One :class:`BagPointCloud` per message.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: ``topic`` is None and the bag has several ``PointCloud2`` topics.
        DatasetFormatError: Unreadable bag; missing, empty or wrongly typed topic (at the
            call); a message that cannot be decoded or whose layout is inconsistent (unknown
            datatype, count 0, duplicate or blank field name, a field beyond ``point_step``,
            ``row_step < width * point_step``, data size not ``height * row_step``), named
            by its index (while iterating).
    """
    bag = _Bag(path).__enter__()
    try:
        topic = bag.choose(topic, POINT_CLOUD2)
    except BaseException:
        bag.__exit__(None, None, None)
        raise

    def generate() -> Iterator[BagPointCloud]:
        with bag:
            yield from bag.messages(topic, lambda i, msg: _decode_cloud(bag, topic, i, msg))

    return generate()


def read_bag_point_clouds(
    path: str | os.PathLike[str], topic: str | None = None
) -> list[BagPointCloud]:
    """All ``sensor_msgs/msg/PointCloud2`` messages of a topic (see
    :func:`iter_bag_point_clouds`, which this collects into a list)."""
    return list(iter_bag_point_clouds(path, topic))


# --------------------------------------------------------------------------------------------
# Writers
# --------------------------------------------------------------------------------------------


class _Writer:
    """A new bag: ROS 1 (``version=1``, a ``.bag`` file) or ROS 2 (a folder)."""

    def __init__(self, path: str | os.PathLike[str], version: int, storage: str) -> None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.path = Path(path)
        if version not in (1, 2):
            raise ValueError(f"version must be 1 or 2, got {version!r}")
        if storage not in ("sqlite3", "mcap"):
            raise ValueError(f"storage must be 'sqlite3' or 'mcap', got {storage!r}")
        if version == 1 and self.path.suffix != ".bag":
            raise ValueError(f"path of a ROS 1 bag must end in .bag, got {str(self.path)!r}")
        if version == 2 and self.path.suffix == ".bag":
            raise ValueError(f"path of a ROS 2 bag (a folder) must not end in .bag: {self.path}")
        if self.path.exists():
            raise FileExistsError(f"{str(self.path)!r} exists already; bags are never overwritten")
        self.version = version
        if version == 1:
            from rosbags.rosbag1 import Writer

            self.typestore = get_typestore(Stores.ROS1_NOETIC)
            self.typestore.register(
                get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_MESSAGE)
            )
            self.writer: Any = Writer(self.path)
            self.serialize = self.typestore.serialize_ros1
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            self.typestore = get_typestore(Stores.ROS2_HUMBLE)
            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer(self.path, version=9, storage_plugin=plugin)
            self.serialize = self.typestore.serialize_cdr
        self.types = self.typestore.types
        self.seq = 0

    def __enter__(self) -> _Writer:
        self.writer.__enter__()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.writer.__exit__(*exc)

    def connection(self, topic: str, msgtype: str) -> Any:
        return self.writer.add_connection(topic, msgtype, typestore=self.typestore)

    def write(self, connection: Any, time_ns: int, msg: Any) -> None:
        self.writer.write(connection, time_ns, self.serialize(msg, connection.msgtype))

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        stamp = self.types["builtin_interfaces/msg/Time"](
            sec=stamp_ns // _NS, nanosec=stamp_ns % _NS
        )
        if self.version == 1:
            self.seq += 1
            return self.types["std_msgs/msg/Header"](seq=self.seq, stamp=stamp, frame_id=frame_id)
        return self.types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def transform(self, t: np.ndarray, q: np.ndarray) -> Any:
        types = self.types
        return types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2]),
            rotation=types["geometry_msgs/msg/Quaternion"](x=q[1], y=q[2], z=q[3], w=q[0]),
        )


def _record_times(stamps_ns: Sequence[int]) -> list[int]:
    """Strictly increasing bag record times, equal to the stamps where those increase: the
    readers return messages in record-time order, so this keeps the caller's order."""
    out: list[int] = []
    for s in stamps_ns:
        out.append(s if not out or s > out[-1] else out[-1] + 1)
    return out


def write_bag_laser_scans(
    path: str | os.PathLike[str],
    log: CarmenLog,
    *,
    topic: str = "/scan",
    frame_id: str = "laser",
    odom_topic: str | None = "/odom",
    map_frame: str = "map",
    odom_frame: str = "odom",
    tf: bool = True,
    version: Literal[1, 2] = 1,
    storage: Literal["sqlite3", "mcap"] = "sqlite3",
) -> Path:
    """Write a :class:`CarmenLog` as a bag of ``LaserScan`` (+ ``Odometry``, + ``tf``).

    Per scan ``i`` (header stamp ``timestamps_s[i]``, rounded to the nanosecond):

    - ``topic``: ``sensor_msgs/msg/LaserScan`` in ``frame_id`` with ``ranges`` =
      ``float32(ranges_m[i])``, ``angle_min`` / ``angle_max`` = the first / last azimuth,
      ``angle_increment`` = their difference over ``n_beams - 1`` (float32 each),
      ``range_min`` 0 and ``range_max`` = ``float32(max_range_m)``.
    - ``odom_topic`` (unless None): ``nav_msgs/msg/Odometry`` with ``odometry[i]`` as the
      pose of ``frame_id`` in ``odom_frame``.
    - ``/tf`` (if ``tf``): ``odom_frame -> frame_id`` = ``odometry[i]`` and
      ``map_frame -> odom_frame`` = ``poses[i] * odometry[i]^-1``, so that tf composes
      ``map_frame -> frame_id`` = ``poses[i]``.

    A row of ``odometry`` (``poses`` and ``odometry``) with a non-finite value is left out
    of the odometry topic (of tf). The bag's record times equal the stamps where these
    increase and are bumped by 1 ns otherwise, so scans read back in the log's order even
    when its timestamps repeat or go backwards.

    :func:`read_bag_laser_scans` reads the bag back with ``ranges_m`` =
    ``float64(float32(log.ranges_m))`` exactly (readings of 0 come back as no-returns at
    ``max_range_m``), ``max_range_m`` = ``float32(log.max_range_m)``, azimuth ``k`` within
    half a float32 ulp of ``angle_min`` plus ``k`` half float32 ulps of
    ``angle_increment`` (about 2e-7 rad for 180 beams), timestamps within 0.5 ns (exact
    for stamps with at most 9 decimals), poses and odometry to float64 rounding. Pass
    ``usable_range_m=log.usable_range_m`` to get the usable range back.

    Args:
        path: New ``.bag`` file (``version=1``) or new ROS 2 bag folder (``version=2``).
        log: The scans (evenly spaced azimuths, as :func:`load_carmen` makes them;
            timestamps in ``[0, 2**31 - 1]`` s).
        topic: Scan topic.
        frame_id: Laser frame (``header.frame_id`` of the scans).
        odom_topic: Odometry topic, or None for none.
        map_frame: tf frame of ``log.poses``.
        odom_frame: tf frame of ``log.odometry``.
        tf: Whether to write ``/tf``.
        version: ROS version of the bag, 1 or 2.
        storage: ROS 2 storage plugin, ``"sqlite3"`` or ``"mcap"`` (ignored for ROS 1).

    Returns:
        ``path``.

    Raises:
        ValueError: Bad ``version``/``storage``; ``path`` suffix not matching the version;
            a timestamp outside ``[0, 2**31 - 1]`` s; azimuths not evenly spaced (to 1e-9
            relative).
        FileExistsError: ``path`` exists.
    """
    ranges = np.asarray(log.ranges_m, dtype=np.float64)
    n_scans, n_beams = ranges.shape
    stamps = [_ns_from_seconds(float(t), "log.timestamps_s") for t in log.timestamps_s]
    times = _record_times(stamps)
    az = np.asarray(log.azimuths_rad, dtype=np.float64)
    increment = (az[-1] - az[0]) / (n_beams - 1) if n_beams > 1 else 0.0
    gap = np.abs(az - (az[0] + np.arange(n_beams) * increment))
    if not (np.isfinite(az).all() and gap.max() <= 1e-9 * max(1.0, float(np.abs(az).max()))):
        raise ValueError(
            "log.azimuths_rad must be finite and evenly spaced (a LaserScan stores "
            "angle_min + k * angle_increment)"
        )
    poses = np.asarray(log.poses, dtype=np.float64)
    odometry = np.asarray(log.odometry, dtype=np.float64)
    odom_ok = np.isfinite(odometry).all(axis=1)
    tf_ok = odom_ok & np.isfinite(poses).all(axis=1)
    # map -> odom = poses * odometry^-1 (planar)
    dyaw = poses[:, 2] - odometry[:, 2]
    c, s = np.cos(dyaw), np.sin(dyaw)
    map_odom_t = np.column_stack(
        [
            poses[:, 0] - (c * odometry[:, 0] - s * odometry[:, 1]),
            poses[:, 1] - (s * odometry[:, 0] + c * odometry[:, 1]),
            np.zeros(n_scans),
        ]
    )
    map_odom_q = _quat_from_yaw(dyaw)
    odom_t = np.column_stack([odometry[:, :2], np.zeros(n_scans)])
    odom_q = _quat_from_yaw(odometry[:, 2])
    ranges32 = ranges.astype(np.float32)
    empty32 = np.zeros(0, dtype=np.float32)
    covariance = np.zeros(36, dtype=np.float64)

    with _Writer(path, version, storage) as w:
        T = w.types
        scan_conn = w.connection(topic, LASER_SCAN)
        odom_conn = w.connection(odom_topic, ODOMETRY) if odom_topic is not None else None
        tf_conn = w.connection("/tf", TF_MESSAGE) if tf else None
        zero_twist = T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](
                linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            ),
            covariance=covariance,
        )
        for i in range(n_scans):
            scan = T[LASER_SCAN](
                header=w.header(stamps[i], frame_id),
                angle_min=float(np.float32(az[0])),
                angle_max=float(np.float32(az[-1])),
                angle_increment=float(np.float32(increment)),
                time_increment=0.0,
                scan_time=0.0,
                range_min=0.0,
                range_max=float(np.float32(log.max_range_m)),
                ranges=ranges32[i],
                intensities=empty32,
            )
            w.write(scan_conn, times[i], scan)
            if odom_conn is not None and odom_ok[i]:
                pose = T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=odom_t[i, 0], y=odom_t[i, 1], z=0.0),
                    orientation=T["geometry_msgs/msg/Quaternion"](
                        x=0.0, y=0.0, z=odom_q[i, 3], w=odom_q[i, 0]
                    ),
                )
                odom = T[ODOMETRY](
                    header=w.header(stamps[i], odom_frame),
                    child_frame_id=frame_id,
                    pose=T["geometry_msgs/msg/PoseWithCovariance"](
                        pose=pose, covariance=covariance
                    ),
                    twist=zero_twist,
                )
                w.write(odom_conn, times[i], odom)
            if tf_conn is not None and tf_ok[i]:
                transforms = [
                    T["geometry_msgs/msg/TransformStamped"](
                        header=w.header(stamps[i], map_frame),
                        child_frame_id=odom_frame,
                        transform=w.transform(map_odom_t[i], map_odom_q[i]),
                    ),
                    T["geometry_msgs/msg/TransformStamped"](
                        header=w.header(stamps[i], odom_frame),
                        child_frame_id=frame_id,
                        transform=w.transform(odom_t[i], odom_q[i]),
                    ),
                ]
                w.write(tf_conn, times[i], T[TF_MESSAGE](transforms=transforms))
    return Path(path)


def write_bag_point_clouds(
    path: str | os.PathLike[str],
    clouds: Sequence[BagPointCloud],
    *,
    topic: str = "/points",
    version: Literal[1, 2] = 1,
    storage: Literal["sqlite3", "mcap"] = "sqlite3",
) -> Path:
    """Write point clouds as ``sensor_msgs/msg/PointCloud2`` messages.

    Each cloud's fields are packed in their order, little-endian, without padding
    (``point_step`` = the sum of the field sizes, ``row_step = width * point_step``);
    ``height`` and ``width`` are kept (organised clouds stay organised); ``is_dense`` is
    whether every floating-point value is finite. The header carries the cloud's
    ``stamp_s`` (rounded to the nanosecond) and ``frame_id``. ``PointCloud.viewpoint`` is
    not stored (``PointCloud2`` has no such field). :func:`read_bag_point_clouds` returns
    the same fields, values and dtypes.

    Args:
        path: New ``.bag`` file (``version=1``) or new ROS 2 bag folder (``version=2``).
        clouds: The clouds, written in this order (record times as in
            :func:`write_bag_laser_scans`).
        topic: The topic.
        version: ROS version of the bag, 1 or 2.
        storage: ROS 2 storage plugin, ``"sqlite3"`` or ``"mcap"`` (ignored for ROS 1).

    Returns:
        ``path``.

    Raises:
        ValueError: Bad ``version``/``storage``/path suffix, a stamp outside
            ``[0, 2**31 - 1]`` s, or a field of dtype int64/uint64 (``PointField`` has no
            64-bit integer type; the field is named).
        FileExistsError: ``path`` exists.
    """
    stamps = [_ns_from_seconds(float(c.stamp_s), "stamp_s") for c in clouds]
    times = _record_times(stamps)
    packed: list[tuple[list[tuple[str, int, int, int]], int, np.ndarray, bool]] = []
    for c in clouds:
        cloud = c.cloud
        layout: list[tuple[str, int, int, int]] = []
        formats, offsets, names = [], [], []
        offset = 0
        dense = True
        for name, arr in cloud.fields.items():
            code = arr.dtype.newbyteorder("<").str[1:]
            datatype = _DTYPE_TO_POINTFIELD.get(code)
            if datatype is None:
                raise ValueError(
                    f"field {name!r} has dtype {arr.dtype}, which PointField cannot store; "
                    "use float32/64 or (u)int8/16/32"
                )
            count = 1 if arr.ndim == 2 else int(arr.shape[2])
            layout.append((name, offset, datatype, count))
            names.append(name)
            formats.append("<" + code if count == 1 else ("<" + code, (count,)))
            offsets.append(offset)
            offset += arr.dtype.itemsize * count
            if arr.dtype.kind == "f":
                dense = dense and bool(np.isfinite(arr).all())
        record = np.dtype({"names": names, "formats": formats, "offsets": offsets})
        points = np.zeros((cloud.height, cloud.width), dtype=record)
        for name, arr in cloud.fields.items():
            points[name] = arr
        packed.append((layout, offset, points.reshape(-1).view(np.uint8), dense))

    with _Writer(path, version, storage) as w:
        T = w.types
        conn = w.connection(topic, POINT_CLOUD2)
        for i, (c, (layout, point_step, data, dense)) in enumerate(
            zip(clouds, packed, strict=True)
        ):
            fields = [
                T["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=k)
                for n, o, d, k in layout
            ]
            msg = T[POINT_CLOUD2](
                header=w.header(stamps[i], c.frame_id),
                height=c.cloud.height,
                width=c.cloud.width,
                fields=fields,
                is_bigendian=False,
                point_step=point_step,
                row_step=point_step * c.cloud.width,
                data=data,
                is_dense=dense,
            )
            w.write(conn, times[i], msg)
    return Path(path)
