"""Placement of the urban world's objects along a route (NumPy, SciPy k-d trees).

Private helpers of :func:`~lidarjax.sim.make_urban_world` and
:func:`~lidarjax.sim.urban_session`: the resampled route with its tangents and revisit mask
(:class:`_Road`), a coarse occupancy grid that keeps objects apart (:class:`_Occupancy`),
and one ``_place_*`` function per object family (poles, facades, bushes, parked / moving
cars and pedestrians, the barrel row). Every function draws from the ``rng`` it is given,
so the world is deterministic given the seed and the order of the calls.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from ._urban_common import (
    _BARREL,
    _FACADE,
    _LAMP,
    _MOVING,
    _PARKED,
    _PEDESTRIAN,
    _SIGN,
    _TLIGHT,
    _TREE,
    wrap_angle,
)

_ROAD_STEP_M = 0.5  # spacing of the resampled road polyline
_MARGIN_M = 0.05  # extra clearance covering the polyline resampling error
_REVISIT_RADIUS_M = 10.0  # road within this distance of earlier road counts as revisited
_REVISIT_GAP_M = 40.0  # ... if it is at least this far behind along the route
_BARREL_ZONE_M = 15.0  # no other poles / bushes / parked cars this close to the barrel row


class _Road:
    """Resampled route with tangents, half-widths, revisit mask and a k-d tree."""

    def __init__(self, xy: np.ndarray, half_width: np.ndarray, new: np.ndarray) -> None:
        self.xy = xy
        self.half_width = half_width
        self.new = new
        self.tree = cKDTree(xy)
        k = max(1, int(round(2.0 / _ROAD_STEP_M)))
        idx = np.arange(len(xy))
        diff = xy[np.minimum(idx + k, len(xy) - 1)] - xy[np.maximum(idx - k, 0)]
        norm = np.linalg.norm(diff, axis=1, keepdims=True)
        self.tangent = np.where(norm > 1e-9, diff / np.maximum(norm, 1e-12), [1.0, 0.0])
        self.normal = np.column_stack([-self.tangent[:, 1], self.tangent[:, 0]])  # left
        self.heading = np.arctan2(self.tangent[:, 1], self.tangent[:, 0])
        self.barrel_a = np.full(2, np.nan)
        self.barrel_b = np.full(2, np.nan)

    def clear_circle(self, xy: np.ndarray, radius: float, clearance: float) -> bool:
        d, _ = self.tree.query(xy)
        return bool(d >= clearance + radius + _MARGIN_M)

    def clear_box(self, center, half_xy, yaw, clearance: float) -> bool:
        reach = float(np.hypot(*half_xy)) + clearance + _MARGIN_M
        idx = self.tree.query_ball_point(center, reach)
        if not idx:
            return True
        p = self.xy[idx] - center
        c, s = math.cos(yaw), math.sin(yaw)
        u = np.abs(c * p[:, 0] + s * p[:, 1]) - half_xy[0]
        v = np.abs(-s * p[:, 0] + c * p[:, 1]) - half_xy[1]
        dist = np.hypot(np.maximum(u, 0), np.maximum(v, 0))
        return bool(dist.min() >= clearance + _MARGIN_M)

    def in_barrel_zone(self, xy: np.ndarray) -> bool:
        if not np.all(np.isfinite(self.barrel_a)):
            return False
        ab = self.barrel_b - self.barrel_a
        t = np.clip(np.dot(xy - self.barrel_a, ab) / max(np.dot(ab, ab), 1e-12), 0, 1)
        return bool(np.linalg.norm(xy - self.barrel_a - t * ab) < _BARREL_ZONE_M)


def _resample_route(xy: np.ndarray) -> np.ndarray:
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-6])
    xy = xy[keep]
    if len(xy) < 2:
        raise ValueError("trajectory must move (its poses are all at one point)")
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    s = np.arange(0.0, cum[-1] + 1e-9, _ROAD_STEP_M)
    return np.column_stack([np.interp(s, cum, xy[:, 0]), np.interp(s, cum, xy[:, 1])])


def _revisit_mask(xy: np.ndarray) -> np.ndarray:
    """True where the route point is new (no earlier route point within the revisit radius)."""
    tree = cKDTree(xy)
    pairs = tree.query_pairs(_REVISIT_RADIUS_M, output_type="ndarray")
    new = np.ones(len(xy), dtype=bool)
    if len(pairs):
        gap = np.abs(pairs[:, 0] - pairs[:, 1])
        pairs = pairs[gap * _ROAD_STEP_M > _REVISIT_GAP_M]
        new[pairs.max(axis=1)] = False
    return new


def _smooth_uniform(rng, n: int, lo: float, hi: float, knot_every: int) -> np.ndarray:
    knots = rng.uniform(lo, hi, size=n // knot_every + 2)
    return np.interp(np.arange(n) / knot_every, np.arange(knots.size), knots)


class _Occupancy:
    """Boolean grid (0.5 m cells) of claimed ground footprint, to keep objects apart."""

    cell = 0.5

    def __init__(self, road_xy: np.ndarray, pad: float = 120.0) -> None:
        self.lo = road_xy.min(axis=0) - pad
        shape = np.ceil((road_xy.max(axis=0) + pad - self.lo) / self.cell).astype(int) + 1
        self.grid = np.zeros(tuple(shape), dtype=bool)

    def _cells(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ij = np.floor((pts - self.lo) / self.cell).astype(np.int64)
        ij = np.clip(ij, 0, np.array(self.grid.shape) - 1)
        return ij[:, 0], ij[:, 1]

    def free(self, pts: np.ndarray) -> bool:
        return not bool(self.grid[self._cells(pts)].any())

    def mark(self, pts: np.ndarray) -> None:
        self.grid[self._cells(pts)] = True


def _disk_points(xy, radius: float) -> np.ndarray:
    n = int(np.ceil(radius / 0.2))
    g = np.linspace(-radius, radius, 2 * n + 1)
    gx, gy = np.meshgrid(g, g)
    inside = gx**2 + gy**2 <= radius**2 + 1e-9
    return np.column_stack([gx[inside], gy[inside]]) + xy


def _rect_points(center_xy, half_xy, yaw: float, pad: float) -> np.ndarray:
    hx, hy = half_xy[0] + pad, half_xy[1] + pad
    u = np.linspace(-hx, hx, int(np.ceil(2 * hx / 0.2)) + 1)
    v = np.linspace(-hy, hy, int(np.ceil(2 * hy / 0.2)) + 1)
    gu, gv = (a.ravel() for a in np.meshgrid(u, v))
    c, s = math.cos(yaw), math.sin(yaw)
    return np.column_stack([c * gu - s * gv, s * gu + c * gv]) + center_xy


class _Builder:
    """Accumulates objects while generating a world or a session."""

    def __init__(self) -> None:
        self.poles: list[tuple] = []  # (x, y, r, h, kind, id)
        self.boxes: list[tuple] = []  # (cx, cy, cz, hx, hy, hz, yaw, kind)
        self.crowns: list[tuple] = []  # (cx, cy, cz, r, rate, pole_id)


_POLE_DIMS = {  # kind: (diameter range, height range, lateral offset beyond the road edge)
    _LAMP: ((0.15, 0.3), (6.0, 9.0), (0.3, 1.5)),
    _SIGN: ((0.06, 0.12), (2.0, 3.5), (0.2, 1.5)),
    _TLIGHT: ((0.2, 0.35), (4.0, 7.0), (0.3, 1.0)),
    _TREE: ((0.2, 0.6), (3.0, 5.0), (1.0, 3.5)),
}


def _try_pole(road, occ, b: _Builder, rng, i: int, side: int, kind: int, pid: int, clr) -> bool:
    """Try to place one pole of ``kind`` next to road point ``i`` on ``side`` (+1 left)."""
    (d_lo, d_hi), (h_lo, h_hi), (o_lo, o_hi) = _POLE_DIMS[kind]
    r = 0.5 * rng.uniform(d_lo, d_hi)
    h = rng.uniform(h_lo, h_hi)
    off = road.half_width[i] + rng.uniform(o_lo, o_hi)
    xy = road.xy[i] + side * off * road.normal[i]
    if road.in_barrel_zone(xy) or not road.clear_circle(xy, r, clr):
        return False
    foot = _disk_points(xy, r + 1.0)
    if not occ.free(foot):
        return False
    if kind == _TREE:
        crown_r = rng.uniform(1.5, 3.0)
        room = float(road.tree.query(xy)[0]) - clr - _MARGIN_M
        crown_r = min(crown_r, room)
        if crown_r < 1.0:
            return False
        b.crowns.append((*xy, h + 0.6 * crown_r, crown_r, rng.uniform(0.8, 2.5), pid))
    occ.mark(foot)
    b.poles.append((*xy, r, h, kind, pid))
    return True


def _pick_kind(rng, p_tree: float) -> int:
    rest = (1 - p_tree) / 0.7
    return int(rng.choice(4, p=[0.35 * rest, 0.25 * rest, 0.1 * rest, p_tree]))


def _place_poles(road, occ, b: _Builder, rng, clr: float, next_id: int) -> int:
    n = len(road.xy)
    for side in (-1, 1):
        i = int(rng.integers(0, 20))
        block = -1
        spacing, p_tree = 12.0, 0.3
        while i < n:
            if i * _ROAD_STEP_M // 100 != block:  # new 100 m block: new density and mix
                block = int(i * _ROAD_STEP_M // 100)
                spacing = rng.uniform(8.0, 18.0)
                p_tree = 0.7 if rng.random() < 0.3 else 0.2
            if road.new[i]:
                kind = _pick_kind(rng, p_tree)
                if _try_pole(road, occ, b, rng, i, side, kind, next_id, clr):
                    next_id += 1
            i += max(1, int(rng.uniform(0.4, 1.6) * spacing / _ROAD_STEP_M))
    return next_id


def _try_box(road, occ, b, i, side, off, along, half, kind, clr, yaw_noise=0.0) -> bool:
    xy = road.xy[i] + side * off * road.normal[i] + along * road.tangent[i]
    yaw = float(road.heading[i] + yaw_noise)
    if not road.clear_box(xy, half[:2], yaw, clr):
        return False
    foot = _rect_points(xy, half[:2], yaw, 0.3)
    if not occ.free(foot):
        return False
    occ.mark(foot)
    b.boxes.append((*xy, half[2], *half, yaw, kind))
    return True


def _place_facades(road, occ, b, rng, clr) -> None:
    n = len(road.xy)
    for side in (-1, 1):
        s = rng.uniform(0, 10)
        while s < n * _ROAD_STEP_M:
            length = rng.uniform(8.0, 30.0)
            i = min(n - 1, int((s + length / 2) / _ROAD_STEP_M))
            if road.new[i]:
                thick = rng.uniform(0.5, 1.0)
                off = road.half_width[i] + rng.uniform(8.0, 15.0) + thick / 2
                half = np.array([length / 2, thick / 2, rng.uniform(3.0, 10.0)])
                # shrink on curves until it fits the corridor
                for _ in range(3):
                    if _try_box(road, occ, b, i, side, off, 0.0, half, _FACADE, clr):
                        break
                    half[0] *= 0.6
            gap = rng.uniform(2.0, 15.0) if rng.random() < 0.7 else rng.uniform(15.0, 40.0)
            s += length + gap


def _place_bushes(road, occ, b, rng, clr) -> None:
    n = len(road.xy)
    for side in (-1, 1):
        s = rng.uniform(0, 20)
        while s < n * _ROAD_STEP_M:
            i = min(n - 1, int(s / _ROAD_STEP_M))
            r = rng.uniform(0.5, 1.2)
            xy = road.xy[i] + side * (road.half_width[i] + rng.uniform(0.5, 4.0)) * road.normal[i]
            if (
                road.new[i]
                and not road.in_barrel_zone(xy)
                and road.clear_circle(xy, r, clr)
                and occ.free(_disk_points(xy, r + 0.2))
            ):
                occ.mark(_disk_points(xy, r + 0.2))
                b.crowns.append((*xy, 0.7 * r, r, rng.uniform(2.0, 5.0), -1))
            s += rng.uniform(10.0, 50.0)


def _place_dynamic(road, occ, b, rng, clr) -> None:
    """Parked cars, pedestrians and oncoming (moving) cars."""
    n = len(road.xy)
    for side in (-1, 1):
        s = rng.uniform(0, 20)
        while s < n * _ROAD_STEP_M:  # parked cars, in short queues
            i = min(n - 1, int(s / _ROAD_STEP_M))
            queue = int(rng.integers(1, 5))
            for k in range(queue):
                half = np.array([rng.uniform(2.0, 2.5), rng.uniform(0.85, 0.95), 0.0])
                half[2] = rng.uniform(0.65, 0.85)
                j = min(n - 1, i + int(k * 6.0 / _ROAD_STEP_M))
                off = max(road.half_width[j] - rng.uniform(0.0, 1.0), clr + 1.0)
                xy = road.xy[j] + side * off * road.normal[j]
                if road.new[j] and not road.in_barrel_zone(xy):
                    _try_box(
                        road,
                        occ,
                        b,
                        j,
                        side,
                        off,
                        0.0,
                        half,
                        _PARKED,
                        clr,
                        0.03 * rng.standard_normal(),
                    )
            s += queue * 6.0 + rng.uniform(10.0, 60.0)
        s = rng.uniform(0, 50)
        while s < n * _ROAD_STEP_M:  # pedestrians on the sidewalk
            i = min(n - 1, int(s / _ROAD_STEP_M))
            half = np.array([0.25, 0.3, rng.uniform(0.8, 0.95)])
            off = road.half_width[i] + rng.uniform(0.5, 3.0)
            if road.new[i]:
                _try_box(
                    road,
                    occ,
                    b,
                    i,
                    side,
                    off,
                    0.0,
                    half,
                    _PEDESTRIAN,
                    clr,
                    rng.uniform(-np.pi, np.pi),
                )
            s += rng.uniform(20.0, 150.0)
    s = rng.uniform(0, 50)
    while s < n * _ROAD_STEP_M:  # oncoming traffic on the left lane
        i = min(n - 1, int(s / _ROAD_STEP_M))
        half = np.array([rng.uniform(2.0, 2.5), 0.9, rng.uniform(0.7, 0.9)])
        off = clr + half[1] + _MARGIN_M + rng.uniform(0.1, 0.7)
        if road.new[i]:
            _try_box(road, occ, b, i, 1, off, 0.0, half, _MOVING, clr, np.pi)
        s += rng.uniform(40.0, 200.0)


def _place_barrels(road, occ, b, rng, clr, next_id: int) -> tuple[int, np.ndarray, np.ndarray]:
    n = len(road.xy)
    n_barrels = int(rng.integers(6, 11))
    spacing = 3.0
    length = (n_barrels - 1) * spacing
    win = int(np.ceil((length + 10.0) / _ROAD_STEP_M))
    starts = np.arange(0, n - win, int(10.0 / _ROAD_STEP_M))
    good = []
    for i0 in starts:
        seg = slice(i0, i0 + win)
        dh = wrap_angle(road.heading[seg] - road.heading[i0 + win // 2])
        if road.new[seg].all() and np.abs(dh).max() < np.deg2rad(3.0):
            good.append(i0)
    if not good:
        raise ValueError("trajectory has no straight stretch for the barrel row")
    good = np.array(good)
    rng.shuffle(good)
    for i0 in good[:200]:
        ic = i0 + win // 2
        side = 1 if rng.random() < 0.5 else -1
        out = side * road.normal[ic]
        base = road.xy[ic] + (road.half_width[ic] + 0.3) * out
        t = road.tangent[ic]
        along = (np.arange(n_barrels) - (n_barrels - 1) / 2) * spacing
        xy = base + along[:, None] * t
        r = 0.5 * rng.uniform(0.5, 0.6, n_barrels)
        h = rng.uniform(1.0, 1.2, n_barrels)
        ok = all(road.clear_circle(p, rr, clr) for p, rr in zip(xy, r))
        ok = ok and all(occ.free(_disk_points(p, rr + 0.3)) for p, rr in zip(xy, r))
        # the shifted row (up to 5 m further out) must also stay free
        ok = ok and all(occ.free(_disk_points(p + 5.0 * out, rr + 0.3)) for p, rr in zip(xy, r))
        if not ok:
            continue
        for k in range(n_barrels):
            occ.mark(_disk_points(xy[k], r[k] + 0.3))
            b.poles.append((*xy[k], r[k], h[k], _BARREL, next_id))
            next_id += 1
        road.barrel_a, road.barrel_b = xy[0].copy(), xy[-1].copy()
        return next_id, np.stack([xy[0], xy[-1]]), out
    raise ValueError("could not place the barrel row")


def _arrays(b: _Builder) -> dict:
    poles = np.array(b.poles, dtype=np.float64).reshape(-1, 6)
    boxes = np.array(b.boxes, dtype=np.float64).reshape(-1, 8)
    crowns = np.array(b.crowns, dtype=np.float64).reshape(-1, 6)
    return dict(
        pole_xy=poles[:, :2],
        pole_radius_m=poles[:, 2],
        pole_height_m=poles[:, 3],
        pole_kind=poles[:, 4].astype(np.int64),
        pole_id=poles[:, 5].astype(np.int64),
        box_center=boxes[:, :3],
        box_half_size=boxes[:, 3:6],
        box_yaw=boxes[:, 6],
        box_kind=boxes[:, 7].astype(np.int64),
        crown_center=crowns[:, :3],
        crown_radius_m=crowns[:, 3],
        crown_rate_per_m=crowns[:, 4],
        crown_pole_id=crowns[:, 5].astype(np.int64),
    )
