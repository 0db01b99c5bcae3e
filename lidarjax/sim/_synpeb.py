"""SynPEB-style synthetic plane-extraction benchmark (dissertation chapter 11).

SynPEB is a synthetic benchmark for plane extraction from organized 3-D laser scans: a
closed room of about 6 m x 7 m x 3 m holds polyhedral objects (boxes, wedges, prisms,
frustums, steps, slanted panels) in random poses, and a sensor at the origin, looking along
``+x``, records an organized scan of 500 x 500 rays. Every ray hits a plane with a known
label, so a segmentation can be scored against the ground truth (e.g. with the Hoover
metrics, which also need to know which planes share an edge).

This module builds such scenes from a seed (:func:`make_synpeb_scene`), simulates noisy
organized scans of them (:func:`simulate_synpeb_scan`, casting with
:func:`~lidarjax.sim.cast_rays`) and provides fixed, generated train / test splits
(:func:`synpeb_split`, :func:`synpeb_scan`). The scans are
:class:`~lidarjax.datasets.SynPEBScan` containers; SynPEB PCD files are read and written by
:func:`~lidarjax.datasets.load_synpeb_pcd` / :func:`~lidarjax.datasets.write_synpeb_pcd`.

Geometry. All coordinates are in the sensor frame (metres): the sensor sits at the origin,
``x`` forward, ``y`` left, ``z`` up (up to the small random tilt of the room, see
:func:`make_synpeb_scene`). The scene representation is described in
:class:`~lidarjax.sim.SynPEBScene`.

Scan model. Ray ``(i, j)`` has the nominal azimuth ``azimuth_rad[j]`` (``atan2(y, x)``,
increasing with the column) and elevation ``elevation_rad[i]`` (decreasing with the row).
Both angles are perturbed independently by ``N(0, angular_sigma^2)``, the perturbed ray is
intersected exactly with the scene, and ``N(0, radial_sigma^2)`` is added to the exact range.
As in the published SynPEB files, the point is reported along the *nominal* ray direction at
the noisy range (the sensor does not know its angular error).

NumPy only; nothing here is called inside ``jit``. Deterministic given the seeds.
"""

from __future__ import annotations

import operator

import numpy as np

from ..datasets import SynPEBScan
from ._synpeb_scene import ConvexPolyhedron, SynPEBScene, cast_rays

__all__ = ["make_synpeb_scene", "simulate_synpeb_scan", "synpeb_scan", "synpeb_split"]

# Published SynPEB grid: 500 x 500 rays, azimuth -35 .. +34.86 deg in 0.14 deg steps,
# elevation +30 .. -30 deg (row 0 at the top).
SYNPEB_SHAPE = (500, 500)
SYNPEB_AZIMUTH_DEG = (-35.0, 34.86)
SYNPEB_ELEVATION_DEG = (30.0, -30.0)
SYNPEB_RADIAL_SIGMA_M = 0.02
SYNPEB_ANGULAR_SIGMA_DEG = 1e-3

# Splits: number of scans and the base of their seeds (scene seed = base + index; the noise
# seed is offset by _NOISE_SEED_OFFSET so that it differs from the scene seed).
_SPLITS = {"train": (10, 1000), "test": (30, 2000)}
_NOISE_SEED_OFFSET = 100_000

# Object centres are drawn within these half-angles (rad) of the sensor's field of view.
_PLACE_HALF_AZ = float(np.deg2rad(33.0))
_PLACE_HALF_EL = float(np.deg2rad(26.0))


# --------------------------------------------------------------------------------------------
# Scene generation
# --------------------------------------------------------------------------------------------


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


# A solid under construction: (normals [F 3], offsets [F]) in some frame.
_HalfSpaces = tuple[np.ndarray, np.ndarray]


def _hs_box(sx: float, sy: float, sz: float) -> _HalfSpaces:
    """Box centred in x, y with its bottom on z = 0."""
    eye = np.eye(3)
    n = np.stack([-eye[0], eye[0], -eye[1], eye[1], -eye[2], eye[2]])
    d = np.array([sx / 2, sx / 2, sy / 2, sy / 2, 0.0, sz])
    return n, d


def _hs_prism(poly_xy: np.ndarray, height: float) -> _HalfSpaces:
    """Right prism over a convex counter-clockwise polygon, bottom on z = 0."""
    e = np.roll(poly_xy, -1, axis=0) - poly_xy
    side = np.column_stack([e[:, 1], -e[:, 0], np.zeros(len(e))])  # outward for CCW
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    d_side = np.sum(side[:, :2] * poly_xy, axis=1)
    n = np.vstack([side, [[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]])
    d = np.concatenate([d_side, [0.0, height]])
    return n, d


def _hs_wedge(length: float, width: float, height: float, apex: float) -> _HalfSpaces:
    """Triangular prism lying on a rectangular face: triangle in the x-z plane, extruded in y.

    The triangle has the base ``[-length/2, length/2]`` on z = 0 and its apex at
    ``x = (apex - 1/2) length``, ``z = height``; ``apex`` in ``[0, 1]``.
    """
    x0, x1, xa = -length / 2, length / 2, (apex - 0.5) * length
    pts = [(x0, 0.0), (x1, 0.0), (xa, height)]
    normals, offsets = [], []
    for (ax, az), (bx, bz) in zip(pts, pts[1:] + pts[:1], strict=True):
        ex, ez = bx - ax, bz - az  # CCW in (x, z): outward normal is (ez, -ex)
        nn = np.array([ez, 0.0, -ex])
        nn /= np.linalg.norm(nn)
        normals.append(nn)
        offsets.append(nn[0] * ax + nn[2] * az)
    normals += [np.array([0.0, -1.0, 0.0]), np.array([0.0, 1.0, 0.0])]
    offsets += [width / 2, width / 2]
    return np.array(normals), np.array(offsets)


def _hs_frustum(bottom_half: float, top_half: float, height: float) -> _HalfSpaces:
    """Square frustum (truncated pyramid) with its bottom on z = 0."""
    slope = (bottom_half - top_half) / height
    normals, offsets = [], []
    for ax in (np.array([1.0, 0.0]), np.array([0.0, 1.0])):
        for sgn in (-1.0, 1.0):
            nn = np.array([sgn * ax[0], sgn * ax[1], slope])
            k = np.linalg.norm(nn)
            normals.append(nn / k)
            offsets.append(bottom_half / k)
    normals += [np.array([0.0, 0.0, -1.0]), np.array([0.0, 0.0, 1.0])]
    offsets += [0.0, height]
    return np.array(normals), np.array(offsets)


def _hs_shift(hs: _HalfSpaces, shift: np.ndarray) -> _HalfSpaces:
    n, d = hs
    return n, d + n @ shift


def _hs_transform(hs: _HalfSpaces, rot: np.ndarray, shift: np.ndarray) -> _HalfSpaces:
    """Half-spaces of ``{rot @ x + shift : x in solid}``."""
    n, d = hs
    n2 = n @ rot.T
    return n2, d + n2 @ shift


def _vertices(hs: _HalfSpaces) -> np.ndarray:
    n, d = hs
    return ConvexPolyhedron(n, d, np.ones(len(d), dtype=np.int64)).vertices()[0]


def _random_object(rng: np.random.Generator) -> tuple[str, list[_HalfSpaces]]:
    """One random object (a group of convex parts), bottom on z = 0, centred near x = y = 0."""
    kind = rng.choice(
        ["box", "wedge", "prism", "frustum", "steps", "panel"],
        p=[0.25, 0.2, 0.17, 0.13, 0.1, 0.15],
    )
    if kind == "box":
        parts = [_hs_box(*rng.uniform([0.25, 0.25, 0.2], [0.8, 0.8, 0.9]))]
    elif kind == "wedge":
        length, width, height = rng.uniform([0.35, 0.3, 0.2], [0.9, 0.8, 0.6])
        parts = [_hs_wedge(length, width, height, rng.choice([0.0, 1.0, rng.uniform()]))]
    elif kind == "prism":
        k = int(rng.choice([3, 5, 6, 8]))
        radius, height = rng.uniform([0.18, 0.2], [0.4, 0.9])
        a = rng.uniform(0, 2 * np.pi) + 2 * np.pi * np.arange(k) / k
        parts = [_hs_prism(radius * np.column_stack([np.cos(a), np.sin(a)]), height)]
    elif kind == "frustum":
        bottom, height = rng.uniform([0.2, 0.2], [0.45, 0.7])
        parts = [_hs_frustum(bottom, bottom * rng.uniform(0.35, 0.8), height)]
    elif kind == "steps":
        n_steps = int(rng.integers(2, 4))
        depth, rise, width = rng.uniform([0.2, 0.15, 0.4], [0.35, 0.3, 0.9])
        parts = []
        for s in range(n_steps):
            box = _hs_box(depth, width, rise * (s + 1))
            shift = np.array([(s + 0.5 - n_steps / 2) * depth, 0.0, 0.0])
            parts.append(_hs_shift(box, shift))
    else:  # panel: a thin board, tilted later
        parts = [_hs_box(*rng.uniform([0.5, 0.03, 0.6], [1.1, 0.06, 1.2]))]
    return str(kind), parts


def _random_pose(
    rng: np.random.Generator,
    kind: str,
    verts: np.ndarray,
    rot: np.ndarray,
    pos: np.ndarray,
    room_hi: np.ndarray,
    placed: list[tuple[np.ndarray, float]],
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Draws a pose (room frame) for an object with centred local vertices ``verts`` [V 3].

    Returns ``(orientation [3 3], centre [3], bounding radius)`` or ``None`` if the pose puts
    the object outside the room, within 0.8 m of the sensor or into another object.
    """
    if kind == "panel":
        mode = "lean"
    elif kind == "steps":
        mode = "floor"
    else:
        u = rng.uniform()
        mode = "floor" if u < 0.45 else ("lean" if u < 0.6 else "float")
    if mode == "float":
        orient = _random_rotation(rng)
    else:
        orient = _rot_z(rng.uniform(0, 2 * np.pi))
        if mode == "lean":
            tilt = rng.uniform(20.0, 60.0) if kind == "panel" else rng.uniform(10.0, 35.0)
            orient = orient @ _rot_x(np.deg2rad(tilt))
    rv = verts @ orient.T  # vertices about the centre, room orientation
    radius = float(np.max(np.linalg.norm(rv, axis=1)))
    az = rng.uniform(-_PLACE_HALF_AZ, _PLACE_HALF_AZ)
    if mode == "float":
        el = rng.uniform(-_PLACE_HALF_EL, _PLACE_HALF_EL)
        dist = rng.uniform(1.3, 4.2)
        dir_s = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        centre = pos + rot @ (dist * dir_s)
        floor_clear = 0.02
    else:
        dist = rng.uniform(1.6, 4.5)
        heading = rot @ np.array([np.cos(az), np.sin(az), 0.0])
        heading[2] = 0.0
        centre = pos + dist * heading / np.linalg.norm(heading)
        centre[2] = -rv[:, 2].min()  # lowest vertex on the floor
        floor_clear = -1e-9
    world = rv + centre
    inside = (
        np.all(world[:, 2] >= floor_clear)
        and np.all(world[:, :2] >= 0.02)
        and np.all(world <= room_hi - 0.02)
    )
    if not inside or np.linalg.norm(centre - pos) - radius < 0.8:
        return None
    if placed:
        others = np.array([c for c, _ in placed])
        reach = np.array([r for _, r in placed]) + radius + 0.03
        if np.any(np.sum((others - centre) ** 2, axis=1) < reach**2):
            return None
    return orient, centre, radius


def make_synpeb_scene(*, seed: int) -> SynPEBScene:
    """Builds a random SynPEB-style room with polyhedral objects, seen from the origin.

    The room (the inside-out first polyhedron, labels 1..6 for floor, ceiling and the four
    walls) measures about 6 m x 7 m x 3 m: the sensor is 1.2-1.5 m above the floor and
    1.5-1.8 m below the ceiling, the wall ahead is 3-5 m away and the side walls 2.7-4.5 m.
    The room is yawed by up to +-15 deg and tilted by up to +-5 deg about x and y relative to
    the sensor (the published SynPEB scans are not axis-aligned either).

    About 15 objects are placed mostly inside the field of view ahead of the sensor: boxes,
    wedges (triangular prisms lying on a rectangular face), 3/5/6/8-gonal prisms, square
    frustums, steps (2-3 boxes; coplanar faces of one staircase share a label) and thin
    slanted panels. Each object either stands on the floor rotated about the vertical, leans
    tilted on an edge (panels always do), or floats in a uniformly random orientation.
    Objects do not overlap (bounding spheres), stay 2 cm inside the room and keep 0.8 m
    clearance around the sensor. Every object face gets its own label ``7..P`` (coplanar
    faces of the boxes of one staircase share a label). A 500 x 500 scan typically sees 30-55
    labels with at least 50 points each (43 on average over the 20 seeds measured).

    Args:
        seed: seed for ``np.random.default_rng``.

    Returns:
        The scene in the sensor frame.
    """
    rng = np.random.default_rng(seed)
    # Room frame: floor z = 0, axis-aligned walls. Sensor pose (R, p) maps sensor -> room.
    floor_gap, ceil_gap = rng.uniform([1.2, 1.5], [1.5, 1.8])
    front, back = rng.uniform([3.0, 1.0], [5.0, 2.5])
    left, right = rng.uniform([2.7, 2.7], [4.5, 4.5])
    yaw = np.deg2rad(rng.uniform(-15.0, 15.0))
    pitch, roll = np.deg2rad(rng.uniform(-5.0, 5.0, 2))
    rot = _rot_z(yaw) @ _rot_y(pitch) @ _rot_x(roll)  # sensor -> room
    pos = np.array([back, right, floor_gap])  # sensor position in the room frame
    room_hi = np.array([back + front, right + left, floor_gap + ceil_gap])

    def to_sensor(hs: _HalfSpaces) -> _HalfSpaces:  # room -> sensor frame
        return _hs_transform(hs, rot.T, -rot.T @ pos)

    # Room faces: floor, ceiling, -x (back), +x (front), -y (right), +y (left) walls.
    eye = np.eye(3)
    room_n = np.stack([-eye[2], eye[2], -eye[0], eye[0], -eye[1], eye[1]])
    room_d = np.array([0.0, room_hi[2], 0.0, room_hi[0], 0.0, room_hi[1]])
    solids: list[tuple[int, _HalfSpaces, bool]] = [(0, to_sensor((room_n, room_d)), True)]

    placed: list[tuple[np.ndarray, float]] = []  # bounding spheres (room frame)
    target = int(rng.integers(15, 21))
    group = 0
    for _ in range(6 * target):  # candidate objects; each gets up to 10 random poses
        if len(placed) >= target:
            break
        kind, parts = _random_object(rng)
        verts = np.vstack([_vertices(p) for p in parts])
        centre_local = 0.5 * (verts.min(axis=0) + verts.max(axis=0))
        for _ in range(10):
            pose = _random_pose(rng, kind, verts - centre_local, rot, pos, room_hi, placed)
            if pose is not None:
                orient, centre, radius = pose
                placed.append((centre, radius))
                group += 1
                shift = centre - orient @ centre_local
                for part in parts:
                    solids.append((group, to_sensor(_hs_transform(part, orient, shift)), False))
                break

    # Labels: room faces 1..6, then object faces in order; coplanar, equally oriented faces
    # of one object group (e.g. the sides of a staircase) share a label.
    polys: list[ConvexPolyhedron] = []
    group_planes: dict[int, list[tuple[np.ndarray, float, int]]] = {}
    next_label = 1
    for grp, (n, d), inside_out in solids:
        known = group_planes.setdefault(grp, [])
        labels = []
        for nn, dd in zip(n, d, strict=True):
            match = [
                lab
                for kn, kd, lab in known
                if grp != 0 and np.max(np.abs(kn - nn)) < 1e-9 and abs(kd - dd) < 1e-9
            ]
            if match:
                labels.append(match[0])
            else:
                labels.append(next_label)
                known.append((nn, float(dd), next_label))
                next_label += 1
        polys.append(ConvexPolyhedron(n, d, np.array(labels), inside_out=inside_out))
    return SynPEBScene.from_polyhedra(polys, seed=seed)


# --------------------------------------------------------------------------------------------
# Scans
# --------------------------------------------------------------------------------------------


def _check_shape(shape: object) -> tuple[int, int]:
    try:
        if isinstance(shape, (str, bytes)) or len(shape) != 2:  # type: ignore[arg-type]
            raise TypeError
        if any(isinstance(s, bool) for s in shape):  # type: ignore[union-attr]
            raise TypeError
        h, w = (operator.index(s) for s in shape)  # type: ignore[union-attr]
    except TypeError:
        raise ValueError(
            f"shape must be a pair of positive integers (H, W), got {shape!r}"
        ) from None
    if h < 1 or w < 1:
        raise ValueError(f"shape must be a pair of positive integers (H, W), got {shape!r}")
    return h, w


def _check_angle_range(name: str, value: object, limit: float) -> tuple[float, float]:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (2,) or not np.all(np.isfinite(arr)) or np.any(np.abs(arr) > limit):
        raise ValueError(
            f"{name} must be a finite (first, last) pair within +-{limit} deg, got {value!r}"
        )
    return float(arr[0]), float(arr[1])


def simulate_synpeb_scan(
    scene: SynPEBScene,
    *,
    shape: tuple[int, int] = SYNPEB_SHAPE,
    radial_sigma_m: float = SYNPEB_RADIAL_SIGMA_M,
    angular_sigma_deg: float = SYNPEB_ANGULAR_SIGMA_DEG,
    seed: int,
    azimuth_deg: tuple[float, float] = SYNPEB_AZIMUTH_DEG,
    elevation_deg: tuple[float, float] = SYNPEB_ELEVATION_DEG,
) -> SynPEBScan:
    """Simulates a noisy organized scan of a scene from the origin.

    The nominal grid is ``azimuth = linspace(az_first, az_last, W)`` and
    ``elevation = linspace(el_first, el_last, H)`` (for the default 500 x 500 this is the
    published SynPEB grid: -35 .. 34.86 deg in 0.14 deg steps, +30 .. -30 deg). Each ray's
    azimuth and elevation are perturbed independently by ``N(0, angular_sigma_deg^2)``, the
    perturbed ray ``(cos el cos az, cos el sin az, sin el)`` is cast exactly
    (:func:`cast_rays`), ``N(0, radial_sigma_m^2)`` is added to the exact range (clipped at 0)
    and the point is placed at that range along the *nominal* direction. The label is that of
    the face the perturbed ray hits.

    Args:
        scene: the scene (sensor frame).
        shape: ``(H, W)`` rows and columns, positive.
        radial_sigma_m: range noise standard deviation (m), ``>= 0``.
        angular_sigma_deg: angular noise standard deviation (deg), ``>= 0``.
        seed: seed for ``np.random.default_rng``; azimuth noise ``[H W]`` is drawn first,
            then elevation noise ``[H W]``, then range noise ``[H W]``.
        azimuth_deg: ``(first, last)`` column azimuths (deg), within +-180.
        elevation_deg: ``(first, last)`` row elevations (deg), within +-90.

    Returns:
        The scan.

    Raises:
        ValueError: on a bad ``shape``, noise level or angle range (the argument is named).
    """
    if not isinstance(scene, SynPEBScene):
        raise ValueError(f"scene must be a SynPEBScene, got {type(scene).__name__}")
    h, w = _check_shape(shape)
    for name, value in (
        ("radial_sigma_m", radial_sigma_m),
        ("angular_sigma_deg", angular_sigma_deg),
    ):
        if not (np.isfinite(value) and value >= 0.0):
            raise ValueError(f"{name} must be finite and non-negative, got {value!r}")
    az0, az1 = _check_angle_range("azimuth_deg", azimuth_deg, 180.0)
    el0, el1 = _check_angle_range("elevation_deg", elevation_deg, 90.0)

    az_nom = np.deg2rad(np.linspace(az0, az1, w))
    el_nom = np.deg2rad(np.linspace(el0, el1, h))
    rng = np.random.default_rng(seed)
    sigma = np.deg2rad(angular_sigma_deg)
    az = az_nom[None, :] + rng.normal(0.0, sigma, (h, w))
    el = el_nom[:, None] + rng.normal(0.0, sigma, (h, w))
    range_noise = rng.normal(0.0, radial_sigma_m, (h, w))

    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)
    true_r, labels = cast_rays(scene, dirs.reshape(-1, 3))
    ranges = np.maximum(true_r.reshape(h, w) + range_noise, 0.0)  # NaN stays NaN
    labels = labels.reshape(h, w)
    nominal = np.stack(
        [
            np.cos(el_nom)[:, None] * np.cos(az_nom)[None, :],
            np.cos(el_nom)[:, None] * np.sin(az_nom)[None, :],
            np.broadcast_to(np.sin(el_nom)[:, None], (h, w)),
        ],
        axis=-1,
    )
    points = ranges[..., None] * nominal
    return SynPEBScan(
        points=points,
        ranges=ranges,
        labels=labels,
        azimuth_rad=az_nom,
        elevation_rad=el_nom,
        plane_normals=scene.plane_normals.copy(),
        plane_offsets=scene.plane_offsets.copy(),
        adjacent_labels=scene.adjacent_labels.copy(),
        seed=int(seed),
        scene_seed=scene.seed,
    )


# --------------------------------------------------------------------------------------------
# Splits
# --------------------------------------------------------------------------------------------


def _split_info(split: object) -> tuple[int, int]:
    if not isinstance(split, str) or split not in _SPLITS:
        raise ValueError(f"split must be one of {sorted(_SPLITS)}, got {split!r}")
    return _SPLITS[split]


def synpeb_scan(split: str, index: int, *, shape: tuple[int, int] = SYNPEB_SHAPE) -> SynPEBScan:
    """One scan of a fixed split, without simulating the others.

    Scan ``i`` of ``"train"`` (10 scans) uses the scene seed ``1000 + i``, of ``"test"``
    (30 scans) ``2000 + i``; the noise seed is the scene seed plus 100000.

    Args:
        split: ``"train"`` or ``"test"``.
        index: scan index, ``0 <= index < len(split)``.
        shape: ``(H, W)`` of the scan (the same field of view at another resolution).

    Returns:
        The scan (deterministic).

    Raises:
        ValueError: on an unknown ``split``, an out-of-range ``index`` or a bad ``shape``.
    """
    count, base = _split_info(split)
    if isinstance(index, bool):
        raise ValueError(f"index must be an integer in [0, {count}), got {index!r}")
    try:
        i = operator.index(index)
    except TypeError:
        raise ValueError(f"index must be an integer in [0, {count}), got {index!r}") from None
    if not 0 <= i < count:
        raise ValueError(f"index must be in [0, {count}) for split {split!r}, got {i}")
    _check_shape(shape)
    scene = make_synpeb_scene(seed=base + i)
    return simulate_synpeb_scan(scene, shape=shape, seed=base + i + _NOISE_SEED_OFFSET)


def synpeb_split(
    split: str, *, shape: tuple[int, int] = SYNPEB_SHAPE, n: int | None = None
) -> list[SynPEBScan]:
    """The scans of a fixed split: ``"train"`` (10 scans) or ``"test"`` (30 scans).

    Args:
        split: ``"train"`` or ``"test"``.
        shape: ``(H, W)`` of the scans.
        n: if given, only the first ``n`` scans (``0 <= n``; larger values give all).

    Returns:
        ``[synpeb_scan(split, i, shape=shape) for i in range(min(n, len))]``.

    Raises:
        ValueError: on an unknown ``split``, a negative ``n`` or a bad ``shape``.
    """
    count, _ = _split_info(split)
    _check_shape(shape)
    if n is not None:
        if isinstance(n, bool):
            raise ValueError(f"n must be a non-negative integer or None, got {n!r}")
        try:
            n_int = operator.index(n)
        except TypeError:
            raise ValueError(f"n must be a non-negative integer or None, got {n!r}") from None
        if n_int < 0:
            raise ValueError(f"n must be a non-negative integer or None, got {n_int}")
        count = min(count, n_int)
    return [synpeb_scan(split, i, shape=shape) for i in range(count)]
