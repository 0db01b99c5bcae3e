"""Seeded urban worlds around a real vehicle trajectory, and their later sessions.

The world is built around a real vehicle trajectory (by default the KITTI odometry sequence
00 ground truth, :func:`~lidarjax.datasets.load_urban_trajectory`): along both sides of the
road the generator (:func:`make_urban_world`) places street lamps, sign posts,
traffic-light poles and tree trunks (vertical cylinders, with permeable tree crowns on top),
building facades, parked and moving cars and pedestrians (oriented boxes), bushes
(permeable spheres) and one row of construction barrels (short, thick cylinders) on a
straight stretch where no other pole-like landmarks stand. :func:`urban_session` derives
later mapping sessions ("weeks apart") from a world: a few poles disappear, new ones
appear, parked cars, pedestrians and moving cars are re-sampled, and in one chosen session
the whole barrel row is shifted sideways - the failure case of a pole-based localizer whose
only landmarks in a region moved.

Frames. The world frame is right-handed with ``z`` up and the ground at ``z = 0``. All
lengths are metres, all angles radians. World generation is NumPy (and SciPy k-d trees);
the object placement lives in :mod:`._urban_placement`. Everything is deterministic given
the seeds.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..datasets import UrbanTrajectory
from ._urban_common import _BARREL, _FACADE, check_nonneg, check_poses, check_seed
from ._urban_placement import (
    _ROAD_STEP_M,
    _arrays,
    _Builder,
    _disk_points,
    _Occupancy,
    _pick_kind,
    _place_barrels,
    _place_bushes,
    _place_dynamic,
    _place_facades,
    _place_poles,
    _rect_points,
    _resample_route,
    _revisit_mask,
    _Road,
    _smooth_uniform,
    _try_pole,
)

__all__ = ["UrbanWorld", "make_urban_world", "urban_session"]

_NEW_ID_STRIDE = 100_000  # pole ids added in session k are k * stride + 0, 1, ...


_WORLD_SHAPES = {
    "pole_xy": (2,),
    "pole_radius_m": (),
    "pole_height_m": (),
    "pole_kind": (),
    "pole_id": (),
    "box_center": (3,),
    "box_half_size": (3,),
    "box_yaw": (),
    "box_kind": (),
    "crown_center": (3,),
    "crown_radius_m": (),
    "crown_rate_per_m": (),
    "crown_pole_id": (),
    "road_xy": (2,),
    "road_half_width_m": (),
    "road_new": (),
}
_WORLD_GROUPS = (
    ("pole_xy", "pole_radius_m", "pole_height_m", "pole_kind", "pole_id"),
    ("box_center", "box_half_size", "box_yaw", "box_kind"),
    ("crown_center", "crown_radius_m", "crown_rate_per_m", "crown_pole_id"),
    ("road_xy", "road_half_width_m", "road_new"),
)
_INT_FIELDS = {"pole_kind", "pole_id", "box_kind", "crown_pole_id"}


@dataclasses.dataclass(frozen=True, eq=False)
class UrbanWorld:
    """A static urban scene (world frame, z up, ground at ``z = 0``). All NumPy.

    Attributes:
        pole_xy: ``[P, 2]`` axis positions of vertical cylinders (m).
        pole_radius_m: ``[P]`` radii (m).
        pole_height_m: ``[P]`` heights; a pole spans ``0 <= z <= height`` (m).
        pole_kind: ``[P]`` int index into :data:`POLE_KINDS` (barrels are poles too).
        pole_id: ``[P]`` int id, stable across sessions (new poles of session ``k`` get
            ids ``k * 100000 + i``).
        box_center: ``[B, 3]`` oriented box centres (m).
        box_half_size: ``[B, 3]`` half extents along the box axes (m).
        box_yaw: ``[B]`` rotation of the box about ``z`` (rad).
        box_kind: ``[B]`` int index into :data:`BOX_KINDS`.
        crown_center: ``[C, 3]`` permeable sphere centres (tree crowns, bushes) (m).
        crown_radius_m: ``[C]`` radii (m).
        crown_rate_per_m: ``[C]`` decay rates (1/m) of the permeable-sphere model.
        crown_pole_id: ``[C]`` id of the tree trunk carrying the crown, ``-1`` for bushes.
        road_xy: ``[R, 2]`` route polyline resampled every 0.5 m (m).
        road_half_width_m: ``[R]`` road half-width around the route (m).
        road_new: ``[R]`` bool, False where the route revisits a street already driven
            (no objects are generated from there, to avoid duplicates).
        barrel_row_xy: ``[2, 2]`` end points of the barrel row's axis (m), as generated.
        barrel_row_normal: ``[2]`` unit road normal at the barrel row pointing away from
            the road.
        session: Session index the world belongs to.
    """

    pole_xy: np.ndarray
    pole_radius_m: np.ndarray
    pole_height_m: np.ndarray
    pole_kind: np.ndarray
    pole_id: np.ndarray
    box_center: np.ndarray
    box_half_size: np.ndarray
    box_yaw: np.ndarray
    box_kind: np.ndarray
    crown_center: np.ndarray
    crown_radius_m: np.ndarray
    crown_rate_per_m: np.ndarray
    crown_pole_id: np.ndarray
    road_xy: np.ndarray
    road_half_width_m: np.ndarray
    road_new: np.ndarray
    barrel_row_xy: np.ndarray
    barrel_row_normal: np.ndarray
    session: int = 0

    def __post_init__(self) -> None:
        for group in _WORLD_GROUPS:
            n = None
            for name in group:
                if name in _INT_FIELDS:
                    dtype = np.int64
                elif name == "road_new":
                    dtype = bool
                else:
                    dtype = np.float64
                arr = np.asarray(getattr(self, name), dtype=dtype)
                tail = _WORLD_SHAPES[name]
                if arr.ndim == 1 and arr.size == 0 and tail:
                    arr = arr.reshape((0, *tail))
                if arr.ndim != 1 + len(tail) or arr.shape[1:] != tail:
                    raise ValueError(f"{name} must have shape [n, *{tail}], got {arr.shape}")
                if n is None:
                    n = arr.shape[0]
                elif arr.shape[0] != n:
                    raise ValueError(f"{name} has {arr.shape[0]} rows, expected {n}")
                if dtype is np.float64 and not np.all(np.isfinite(arr)):
                    raise ValueError(f"{name} must be finite")
                object.__setattr__(self, name, arr)
        for name, shape in (("barrel_row_xy", (2, 2)), ("barrel_row_normal", (2,))):
            arr = np.asarray(getattr(self, name), dtype=np.float64)
            if arr.shape != shape:
                raise ValueError(f"{name} must have shape {list(shape)}, got {arr.shape}")
            object.__setattr__(self, name, arr)
        if np.any(self.pole_radius_m <= 0) or np.any(self.pole_height_m <= 0):
            raise ValueError("pole_radius_m and pole_height_m must be > 0")
        if np.any(self.box_half_size <= 0):
            raise ValueError("box_half_size must be > 0")
        if np.any(self.crown_radius_m <= 0) or np.any(self.crown_rate_per_m < 0):
            raise ValueError("crown_radius_m must be > 0 and crown_rate_per_m >= 0")

    @property
    def n_poles(self) -> int:
        return int(self.pole_xy.shape[0])

    @property
    def n_boxes(self) -> int:
        return int(self.box_center.shape[0])

    @property
    def n_crowns(self) -> int:
        return int(self.crown_center.shape[0])

    def replace(self, **changes) -> UrbanWorld:
        """A copy with some fields replaced."""
        return dataclasses.replace(self, **changes)


def _road_from_world(world: UrbanWorld) -> _Road:
    road = _Road(world.road_xy, world.road_half_width_m, world.road_new)
    road.barrel_a, road.barrel_b = world.barrel_row_xy[0], world.barrel_row_xy[1]
    return road


def make_urban_world(
    trajectory: UrbanTrajectory | np.ndarray,
    *,
    seed: int = 0,
    road_half_width_m: tuple[float, float] = (4.0, 7.0),
    clearance_m: float = 2.5,
) -> UrbanWorld:
    """Generate a seeded urban scene around a trajectory.

    The route polyline is resampled every 0.5 m; the road half-width varies smoothly (knots
    every 50 m) within ``road_half_width_m``. Along both sides the generator places, per
    100 m block with its own density (one pole every 8-18 m on average per side before
    rejections) and mix (tree-lined or not): street lamps (diameter 0.15-0.3 m, 6-9 m
    tall), sign posts (0.06-0.12 m, 2-3.5 m), traffic-light poles (0.2-0.35 m, 4-7 m), tree
    trunks (0.2-0.6 m, 3-5 m, each with a permeable crown of radius 1-3 m on top), building
    facades (thin boxes 8-30 m long, 8-15 m behind the road edge, with gaps), bushes
    (permeable spheres), parked cars (~4.5 x 1.8 x 1.5 m at the road edge), pedestrians and
    oncoming cars on the left lane. One row of 6-10 construction barrels (diameter 0.5-0.6
    m, height 1.0-1.2 m, 3 m apart) stands at the road edge of a random straight stretch;
    no other poles, bushes or parked cars are within 15 m of it.

    No object comes closer than ``clearance_m`` (horizontally) to the route, objects do
    not overlap, and where the route revisits a street (within 10 m of route driven more
    than 40 m earlier) nothing new is generated, so loops see the same objects again.

    Args:
        trajectory: The route, an :class:`UrbanTrajectory` or an ``[N, 3]`` pose array.
        seed: Seed, ``>= 0``.
        road_half_width_m: ``(low, high)`` range of the road half-width (m).
        clearance_m: Minimum horizontal distance of any object to the route (m).

    Returns:
        The world (session 0).

    Raises:
        ValueError: Bad ``trajectory``, ``seed``, ``road_half_width_m`` or ``clearance_m``.
    """
    seed = check_seed(seed)
    if isinstance(trajectory, UrbanTrajectory):
        xy_yaw = trajectory.xy_yaw
    else:
        xy_yaw = check_poses(trajectory, "trajectory")
    lo, hi = (float(v) for v in road_half_width_m)
    if not (0 < lo <= hi) or not math.isfinite(hi):
        raise ValueError(f"road_half_width_m must be 0 < low <= high, got {road_half_width_m}")
    clr = check_nonneg(clearance_m, "clearance_m")
    if lo < clr:
        raise ValueError("road_half_width_m low must be >= clearance_m")

    rng = np.random.default_rng([seed, 0x5EED_0B])
    road_xy = _resample_route(xy_yaw[:, :2])
    half = _smooth_uniform(rng, len(road_xy), lo, hi, int(50.0 / _ROAD_STEP_M))
    road = _Road(road_xy, half, _revisit_mask(road_xy))
    occ = _Occupancy(road_xy)
    b = _Builder()
    next_id, row_xy, row_normal = _place_barrels(road, occ, b, rng, clr, 0)
    _place_facades(road, occ, b, rng, clr)
    _place_poles(road, occ, b, rng, clr, next_id)
    _place_bushes(road, occ, b, rng, clr)
    _place_dynamic(road, occ, b, rng, clr)
    return UrbanWorld(
        **_arrays(b),
        road_xy=road_xy,
        road_half_width_m=half,
        road_new=road.new,
        barrel_row_xy=row_xy,
        barrel_row_normal=row_normal,
        session=0,
    )


def urban_session(
    world: UrbanWorld,
    session: int,
    *,
    seed: int = 0,
    barrel_session: int | None = None,
    p_remove: float = 0.05,
    p_add: float = 0.05,
    barrel_shift_m: float = 3.0,
    clearance_m: float = 2.5,
) -> UrbanWorld:
    """Derive the scene of a later mapping session from a session-0 world.

    Facades, bushes and (in session 0) all poles stay. Parked cars, pedestrians and moving
    cars are always re-sampled (also in session 0). In sessions ``>= 1`` every non-barrel
    pole is removed independently with probability ``p_remove`` (never all; tree crowns go
    with their trunks) and about ``p_add`` times as many new poles (new ids ``session *
    100000 + i``) appear along the road. Barrels are never removed or added; in session
    ``barrel_session`` all barrels are shifted by ``barrel_shift_m`` along
    ``world.barrel_row_normal`` (positive: away from the road), keeping their positions
    along the road.

    Args:
        world: The session-0 world from :func:`make_urban_world`.
        session: Session index, ``>= 0``.
        seed: Seed, ``>= 0``; the result is deterministic in ``(seed, session)``.
        barrel_session: Session in which the barrel row is shifted, or ``None``.
        p_remove: Removal probability per pole, in ``[0, 1]``.
        p_add: Expected new poles per existing pole, in ``[0, 1]``.
        barrel_shift_m: Sideways barrel shift (m).
        clearance_m: Minimum horizontal distance of re-sampled objects to the route (m).

    Returns:
        The session's world.

    Raises:
        ValueError: A bad argument (the message names it).
    """
    if not isinstance(world, UrbanWorld):
        raise ValueError(f"world must be an UrbanWorld, got {type(world).__name__}")
    session = check_seed(session, "session")
    seed = check_seed(seed)
    if barrel_session is not None:
        barrel_session = check_seed(barrel_session, "barrel_session")
    for name, p in (("p_remove", p_remove), ("p_add", p_add)):
        if not (0.0 <= float(p) <= 1.0):
            raise ValueError(f"{name} must be in [0, 1], got {p}")
    if not math.isfinite(float(barrel_shift_m)):
        raise ValueError(f"barrel_shift_m must be finite, got {barrel_shift_m}")
    clr = check_nonneg(clearance_m, "clearance_m")

    rng = np.random.default_rng([seed, session, 0x5E55])
    road = _road_from_world(world)
    pole_xy = world.pole_xy.copy()
    is_barrel = world.pole_kind == _BARREL
    keep = np.ones(world.n_poles, dtype=bool)
    if session > 0:
        drop = (rng.random(world.n_poles) < p_remove) & ~is_barrel
        if drop.any() and drop.sum() == world.n_poles:
            drop[int(rng.integers(world.n_poles))] = False
        keep = ~drop
    if barrel_session is not None and session == barrel_session:
        pole_xy[is_barrel] += float(barrel_shift_m) * world.barrel_row_normal

    b = _Builder()
    b.poles = [
        (*pole_xy[k], world.pole_radius_m[k], world.pole_height_m[k], world.pole_kind[k],
         world.pole_id[k])
        for k in np.flatnonzero(keep)
    ]  # fmt: skip
    kept_ids = set(world.pole_id[keep].tolist())
    b.crowns = [
        (*world.crown_center[k], world.crown_radius_m[k], world.crown_rate_per_m[k], pid)
        for k, pid in enumerate(world.crown_pole_id.tolist())
        if pid < 0 or pid in kept_ids
    ]
    b.boxes = [
        (*world.box_center[k], *world.box_half_size[k], world.box_yaw[k], _FACADE)
        for k in np.flatnonzero(world.box_kind == _FACADE)
    ]
    occ = _Occupancy(world.road_xy)
    for x, y, r, *_ in b.poles:
        occ.mark(_disk_points(np.array([x, y]), r + 1.0))
    for x, y, _, r, *_ in b.crowns:
        occ.mark(_disk_points(np.array([x, y]), min(r, 1.0)))
    for cx, cy, _, hx, hy, _, yaw, _ in b.boxes:
        occ.mark(_rect_points(np.array([cx, cy]), (hx, hy), yaw, 0.3))

    if session > 0:
        n_add = int(rng.binomial(int((~is_barrel).sum()), p_add))
        candidates = np.flatnonzero(road.new)
        next_id = session * _NEW_ID_STRIDE
        for _ in range(20 * n_add):
            if next_id - session * _NEW_ID_STRIDE >= n_add:
                break
            i = int(rng.choice(candidates))
            side = 1 if rng.random() < 0.5 else -1
            if _try_pole(road, occ, b, rng, i, side, _pick_kind(rng, 0.3), next_id, clr):
                next_id += 1
    _place_dynamic(road, occ, b, rng, clr)
    return world.replace(**_arrays(b), session=session)
