"""SynPEB-style synthetic plane-extraction benchmark (dissertation chapter 11).

SynPEB is a synthetic benchmark for plane extraction from organized 3-D laser scans: a
closed room of about 6 m x 7 m x 3 m holds polyhedral objects (boxes, wedges, prisms,
frustums, steps, slanted panels) in random poses, and a sensor at the origin, looking along
``+x``, records an organized scan of 500 x 500 rays. Every ray hits a plane with a known
label, so a segmentation can be scored against the ground truth (e.g. with the Hoover
metrics, which also need to know which planes share an edge).

This module builds such scenes from a seed (:func:`make_synpeb_scene`), casts rays against
them exactly (:func:`cast_rays`), simulates noisy organized scans
(:func:`simulate_synpeb_scan`), provides fixed train / test splits (:func:`synpeb_split`,
:func:`synpeb_scan`) and reads / writes SynPEB PCD files (:func:`write_synpeb_pcd`,
:func:`load_synpeb_pcd`).

Geometry. A scene is a list of convex polyhedra, each given by half-spaces
``n_f . x <= d_f`` (outward unit normals ``n_f``, offsets ``d_f`` in metres) and one
ground-truth plane label per face. The room is an *inside-out* polyhedron: rays start inside
it and hit it where they leave it. All coordinates are in the sensor frame (metres): the
sensor sits at the origin, ``x`` forward, ``y`` left, ``z`` up (up to the small random tilt of
the room, see :func:`make_synpeb_scene`).

Scan model. Ray ``(i, j)`` has the nominal azimuth ``azimuth_rad[j]`` (``atan2(y, x)``,
increasing with the column) and elevation ``elevation_rad[i]`` (decreasing with the row).
Both angles are perturbed independently by ``N(0, angular_sigma^2)``, the perturbed ray is
intersected exactly with the scene, and ``N(0, radial_sigma^2)`` is added to the exact range.
As in the published SynPEB files, the point is reported along the *nominal* ray direction at
the noisy range (the sensor does not know its angular error).

NumPy only; nothing here is called inside ``jit``. Deterministic given the seeds.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import operator
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ._errors import DatasetFormatError
from ._pcd import PointCloud, read_pcd, write_pcd

__all__ = [
    "ConvexPolyhedron",
    "SynPEBScan",
    "SynPEBScene",
    "cast_rays",
    "load_synpeb_pcd",
    "make_synpeb_scene",
    "simulate_synpeb_scan",
    "synpeb_scan",
    "synpeb_split",
    "write_synpeb_pcd",
]

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

_UNIT_TOL = 1e-6  # accepted deviation of |n| from 1
_PLANE_TOL = 1e-6  # faces with the same label must agree on (n, d) to this tolerance
_VERTEX_TOL = 1e-7  # (m) a vertex lies on a face / inside a polyhedron within this slack
_DEFAULT_CHUNK = 2048  # rays per block in cast_rays: [chunk F] float64 work arrays


@functools.lru_cache(maxsize=64)
def _face_triples(f: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index arrays ``(i, j, k)`` of all face triples ``i < j < k`` of ``f`` faces."""
    idx = np.array(list(itertools.combinations(range(f), 3)), dtype=np.int64).reshape(-1, 3)
    return idx[:, 0], idx[:, 1], idx[:, 2]


# --------------------------------------------------------------------------------------------
# Scene representation
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class ConvexPolyhedron:
    """A convex polyhedron (possibly unbounded) as an intersection of half-spaces.

    The solid is ``{x : normals @ x <= offsets}``. An *inside-out* polyhedron (the room) is
    seen from inside: a ray starting inside hits it where it leaves it.

    Attributes:
        normals: ``[F 3]`` float64 outward unit face normals (inputs are normalised; the
            offsets are scaled with them).
        offsets: ``[F]`` float64 face offsets ``d`` (m): a face is the plane ``n . x = d``.
        labels: ``[F]`` int64 ground-truth plane label of each face, ``>= 1``.
        inside_out: whether rays see the solid from inside (the room).
    """

    normals: np.ndarray
    offsets: np.ndarray
    labels: np.ndarray
    inside_out: bool = False

    def __post_init__(self) -> None:
        normals = np.array(self.normals, dtype=np.float64)
        if normals.ndim != 2 or normals.shape[1] != 3 or normals.shape[0] < 1:
            raise ValueError(f"normals must have shape [F 3] with F >= 1, got {normals.shape}")
        f = normals.shape[0]
        offsets = np.array(self.offsets, dtype=np.float64)
        if offsets.shape != (f,):
            raise ValueError(f"offsets must have shape [{f}] (one per face), got {offsets.shape}")
        if not (np.all(np.isfinite(normals)) and np.all(np.isfinite(offsets))):
            raise ValueError("normals and offsets must be finite")
        norm = np.linalg.norm(normals, axis=1)
        if np.any(norm < _UNIT_TOL):
            raise ValueError("normals must be non-zero vectors")
        labels_in = np.asarray(self.labels)
        if labels_in.shape != (f,):
            raise ValueError(f"labels must have shape [{f}] (one per face), got {labels_in.shape}")
        if labels_in.dtype.kind not in "iu" and not (
            labels_in.dtype.kind == "f"
            and np.all(np.isfinite(labels_in))
            and np.all(labels_in == np.round(labels_in))
        ):
            raise ValueError(f"labels must be integers, got dtype {labels_in.dtype}")
        labels = labels_in.astype(np.int64)
        if np.any(labels < 1):
            raise ValueError("labels must be >= 1 (label 0 means 'no return')")
        object.__setattr__(self, "normals", normals / norm[:, None])
        object.__setattr__(self, "offsets", offsets / norm)
        object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "inside_out", bool(self.inside_out))

    @classmethod
    def box(
        cls,
        lower_m: Sequence[float],
        upper_m: Sequence[float],
        labels: Sequence[int],
        *,
        inside_out: bool = False,
    ) -> ConvexPolyhedron:
        """An axis-aligned box ``lower <= x <= upper``.

        Args:
            lower_m: ``[3]`` lower corner (m).
            upper_m: ``[3]`` upper corner (m), strictly greater than ``lower_m``.
            labels: ``[6]`` labels of the faces ``-x, +x, -y, +y, -z, +z``.
            inside_out: ``True`` for a room seen from inside.

        Returns:
            The box.
        """
        lo = np.asarray(lower_m, dtype=np.float64)
        hi = np.asarray(upper_m, dtype=np.float64)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(hi > lo):
            raise ValueError(
                f"lower_m and upper_m must be [3] corners with upper > lower, got {lower_m!r}, "
                f"{upper_m!r}"
            )
        eye = np.eye(3)
        normals = np.stack([-eye[0], eye[0], -eye[1], eye[1], -eye[2], eye[2]])
        offsets = np.array([-lo[0], hi[0], -lo[1], hi[1], -lo[2], hi[2]])
        return cls(normals, offsets, np.asarray(labels), inside_out=inside_out)

    def vertices(self) -> tuple[np.ndarray, np.ndarray]:
        """Vertices of the polyhedron and which faces they lie on.

        Every triple of faces with independent normals is intersected; the points that satisfy
        all half-spaces (within ``1e-7`` m) are the vertices. ``O(F^3)``, meant for the small
        ``F`` of scene objects.

        Returns:
            ``(vertices, incidence)``: ``[V 3]`` float64 vertices (m) and ``[V F]`` bool, true
            where vertex ``v`` lies on face ``f``. ``V = 0`` for solids without vertices
            (e.g. a single half-space).
        """
        n, d = self.normals, self.offsets
        f = n.shape[0]
        if f < 3:
            return np.zeros((0, 3)), np.zeros((0, f), dtype=bool)
        i, j, k = _face_triples(f)
        mats = np.stack([n[i], n[j], n[k]], axis=1)  # [T 3 3]
        rhs = np.stack([d[i], d[j], d[k]], axis=1)  # [T 3]
        ok = np.abs(np.linalg.det(mats)) > 1e-9
        if not np.any(ok):
            return np.zeros((0, 3)), np.zeros((0, f), dtype=bool)
        pts = np.linalg.solve(mats[ok], rhs[ok][:, :, None])[:, :, 0]
        resid = pts @ n.T - d  # [T F]
        pts = pts[np.all(resid <= _VERTEX_TOL, axis=1)]
        close = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=-1) <= 1e-6
        duplicate = np.any(np.tril(close, k=-1), axis=1)  # an earlier point is the same
        verts = pts[~duplicate].reshape(-1, 3)
        incidence = np.abs(verts @ n.T - d) <= _VERTEX_TOL * 10
        return verts, incidence

    def is_bounded(self) -> bool:
        """Whether the solid is bounded (has vertices and no recession direction).

        A pointed polyhedron is unbounded iff some extreme ray ``u = +-(n_i x n_j)`` of its
        recession cone satisfies ``normals @ u <= 0``.
        """
        verts, _ = self.vertices()
        if verts.shape[0] == 0:
            return False
        n = self.normals
        i, j = np.triu_indices(n.shape[0], k=1)
        u = np.cross(n[i], n[j])
        u = u[np.linalg.norm(u, axis=1) > 1e-9]
        u = np.concatenate([u, -u])
        return not np.any(np.all(u @ n.T <= 1e-12, axis=1))


@dataclasses.dataclass(frozen=True, eq=False)
class SynPEBScene:
    """A SynPEB scene: convex polyhedra with labelled faces and the ground-truth plane table.

    Build it with :meth:`from_polyhedra` (hand-made scenes) or :func:`make_synpeb_scene`.

    Attributes:
        polyhedra: the convex solids; the room (inside-out) is the first one in generated
            scenes.
        plane_normals: ``[P+1 3]`` float64 unit normal of plane ``label`` (row 0, "no return",
            and unused labels are NaN). Oriented like the face normals (outward of objects;
            for the room, pointing out of the room, i.e. away from the sensor).
        plane_offsets: ``[P+1]`` float64 offsets (m): plane ``l`` is
            ``plane_normals[l] . x = plane_offsets[l]`` (row 0 is NaN).
        adjacent_labels: ``[M 2]`` int64 label pairs ``(a, b)``, ``a < b``, whose faces share
            a geometric edge: the edges of each convex polyhedron (including the room's wall /
            floor / ceiling edges) and the lines where faces of touching or intersecting
            solids meet (an object standing on the floor, the treads and risers of steps).
            Contacts may also pair a face that is completely hidden by the contact.
        seed: the seed of :func:`make_synpeb_scene`, or ``None`` for hand-made scenes.
    """

    polyhedra: tuple[ConvexPolyhedron, ...]
    plane_normals: np.ndarray
    plane_offsets: np.ndarray
    adjacent_labels: np.ndarray
    seed: int | None = None

    def __post_init__(self) -> None:
        polys = tuple(self.polyhedra)
        if not polys or not all(isinstance(p, ConvexPolyhedron) for p in polys):
            raise ValueError("polyhedra must be a non-empty sequence of ConvexPolyhedron")
        object.__setattr__(self, "polyhedra", polys)
        pn = np.asarray(self.plane_normals, dtype=np.float64)
        po = np.asarray(self.plane_offsets, dtype=np.float64)
        max_label = max(int(p.labels.max()) for p in polys)
        if pn.ndim != 2 or pn.shape[1] != 3 or pn.shape[0] < max_label + 1:
            raise ValueError(
                f"plane_normals must have shape [P+1 3] with P >= {max_label}, got {pn.shape}"
            )
        if po.shape != (pn.shape[0],):
            raise ValueError(f"plane_offsets must have shape [{pn.shape[0]}], got {po.shape}")
        adj = np.asarray(self.adjacent_labels, dtype=np.int64).reshape(-1, 2)
        object.__setattr__(self, "plane_normals", pn)
        object.__setattr__(self, "plane_offsets", po)
        object.__setattr__(self, "adjacent_labels", adj)

    @classmethod
    def from_polyhedra(
        cls, polyhedra: Sequence[ConvexPolyhedron], *, seed: int | None = None
    ) -> SynPEBScene:
        """Builds a scene, deriving the plane table and the edge adjacency from the solids.

        Args:
            polyhedra: the convex solids. Faces may share a label (coplanar pieces of one
                plane); they must then lie on the same oriented plane.
            seed: recorded in the scene.

        Two faces are adjacent if they are not parallel and their closed faces share at least
        two points that are vertices of one solid (faces of one solid) or of the intersection
        of two solids (contacts; only solids whose bounding spheres meet are tested).

        Returns:
            The scene, with ``P = max label``.

        Raises:
            ValueError: if ``polyhedra`` is empty or two faces with one label lie on different
                planes.
        """
        polys = tuple(polyhedra)
        if not polys or not all(isinstance(p, ConvexPolyhedron) for p in polys):
            raise ValueError("polyhedra must be a non-empty sequence of ConvexPolyhedron")
        p_max = max(int(p.labels.max()) for p in polys)
        normals = np.full((p_max + 1, 3), np.nan)
        offsets = np.full(p_max + 1, np.nan)
        pairs: set[tuple[int, int]] = set()
        for poly in polys:
            for n, d, lab in zip(poly.normals, poly.offsets, poly.labels, strict=True):
                if np.isnan(offsets[lab]):
                    normals[lab], offsets[lab] = n, d
                elif (
                    np.max(np.abs(normals[lab] - n)) > _PLANE_TOL
                    or abs(offsets[lab] - d) > _PLANE_TOL
                ):
                    raise ValueError(
                        f"polyhedra: faces with label {lab} lie on different planes "
                        f"(n={normals[lab]}, d={offsets[lab]} vs n={n}, d={d})"
                    )
        centres, radii = _bounding_spheres(polys)
        for a, poly_a in enumerate(polys):
            for b in range(a, len(polys)):
                poly_b = polys[b]
                gap = np.linalg.norm(centres[a] - centres[b]) - radii[a] - radii[b]
                if gap > 1e-6:  # bounding spheres apart: no contact
                    continue
                if a == b:
                    inc_a = inc_b = poly_a.vertices()[1]
                else:  # faces of two solids meet on the boundary of their intersection
                    both = ConvexPolyhedron(
                        np.concatenate([poly_a.normals, poly_b.normals]),
                        np.concatenate([poly_a.offsets, poly_b.offsets]),
                        np.ones(poly_a.labels.size + poly_b.labels.size, dtype=np.int64),
                    )
                    inc = both.vertices()[1]
                    inc_a, inc_b = inc[:, : poly_a.labels.size], inc[:, poly_a.labels.size :]
                shared = inc_a.T.astype(np.int64) @ inc_b.astype(np.int64)  # common vertices
                cos = np.abs(poly_a.normals @ poly_b.normals.T)
                fi, fj = np.nonzero((shared >= 2) & (cos < 1.0 - 1e-9))
                for la, lb in zip(poly_a.labels[fi], poly_b.labels[fj], strict=True):
                    if la != lb:
                        pairs.add((int(min(la, lb)), int(max(la, lb))))
        adj = np.array(sorted(pairs), dtype=np.int64).reshape(-1, 2)
        return cls(polys, normals, offsets, adj, seed)

    def _bounding_spheres(self) -> tuple[np.ndarray, np.ndarray]:
        """Cached :func:`_bounding_spheres` of the solids."""
        cached = self.__dict__.get("_spheres")
        if cached is None:
            cached = _bounding_spheres(self.polyhedra)
            object.__setattr__(self, "_spheres", cached)
        return cached

    @property
    def num_labels(self) -> int:
        """``P``, the largest plane label (labels run over ``1..P``)."""
        return self.plane_normals.shape[0] - 1


def _bounding_spheres(polys: Sequence[ConvexPolyhedron]) -> tuple[np.ndarray, np.ndarray]:
    """``[S 3]`` centres and ``[S]`` radii (m) enclosing the solids; the radius is ``inf`` for
    inside-out or unbounded solids."""
    centres = np.zeros((len(polys), 3))
    radii = np.full(len(polys), np.inf)
    for k, poly in enumerate(polys):
        if poly.inside_out or not poly.is_bounded():
            continue
        verts, _ = poly.vertices()
        c = 0.5 * (verts.min(axis=0) + verts.max(axis=0))
        centres[k] = c
        radii[k] = np.max(np.linalg.norm(verts - c, axis=1)) * (1 + 1e-9) + 1e-9
    return centres, radii


# --------------------------------------------------------------------------------------------
# Ray casting
# --------------------------------------------------------------------------------------------


def cast_rays(
    scene: SynPEBScene,
    directions: np.ndarray,
    *,
    origin_m: Sequence[float] = (0.0, 0.0, 0.0),
    chunk_size: int = _DEFAULT_CHUNK,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact first intersections of rays with the scene (slab method per convex solid).

    For a ray ``o + t v`` (``|v| = 1``) and a face ``n . x <= d`` let
    ``t_f = (d - n . o) / (n . v)``. An ordinary solid is entered at
    ``t_in = max_{n.v<0} t_f`` and left at ``t_out = min_{n.v>0} t_f``; it is hit at ``t_in``
    if ``0 < t_in <= t_out`` (a face parallel to the ray with ``n . o > d`` rules the solid
    out). An inside-out solid (the room) containing the origin is hit at ``t_out``. The
    nearest hit over all solids wins; its label is that of the face attaining ``t_in``
    (``t_out`` for inside-out solids). Rays are processed in blocks; solids whose bounding
    sphere no ray of a block meets are skipped, so the work is at most ``[chunk_size F]`` per
    block (consecutive rows of an organized scan make compact blocks).

    Args:
        scene: the scene.
        directions: ``[N 3]`` ray directions (need not be unit; they are normalised).
        origin_m: ``[3]`` common ray origin (m), the sensor position; default the origin.
        chunk_size: rays processed per block, ``>= 1`` (bounds memory).

    Returns:
        ``(ranges, labels)``: ``[N]`` float64 distances (m) from the origin to the hit
        (NaN where nothing is hit) and ``[N]`` int64 plane labels (0 where nothing is hit).

    Raises:
        ValueError: on a malformed ``directions`` / ``origin_m`` or a bad ``chunk_size``.
    """
    if not isinstance(scene, SynPEBScene):
        raise ValueError(f"scene must be a SynPEBScene, got {type(scene).__name__}")
    v = np.asarray(directions, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"directions must have shape [N 3], got {v.shape}")
    norm = np.linalg.norm(v, axis=1)
    if not np.all(np.isfinite(norm)) or np.any(norm == 0.0):
        raise ValueError("directions must be finite and non-zero")
    v = v / norm[:, None]
    o = np.asarray(origin_m, dtype=np.float64)
    if o.shape != (3,) or not np.all(np.isfinite(o)):
        raise ValueError(f"origin_m must be a finite [3] point, got {origin_m!r}")
    if isinstance(chunk_size, bool):
        raise ValueError(f"chunk_size must be a positive integer, got {chunk_size!r}")
    chunk = operator.index(chunk_size)
    if chunk < 1:
        raise ValueError(f"chunk_size must be a positive integer, got {chunk}")

    polys = scene.polyhedra
    normals = np.concatenate([p.normals for p in polys])  # [F 3]
    gap = np.concatenate([p.offsets for p in polys]) - normals @ o  # [F] d - n.o
    labels = np.concatenate([p.labels for p in polys])
    sizes = np.array([p.normals.shape[0] for p in polys])
    owner = np.repeat(np.arange(len(polys)), sizes)  # [F] solid of each face
    io_solid = np.array([p.inside_out for p in polys])
    # An inside-out solid can only be hit from inside; an origin outside it never sees it.
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    io_usable = io_solid & np.logical_and.reduceat(gap >= 0.0, starts)
    # Bounding spheres of the bounded ordinary solids, to skip solids no ray of a block meets.
    centres, radii = scene._bounding_spheres()
    w = centres - o  # [S 3]
    w2 = np.sum(w * w, axis=1)
    always = ~np.isfinite(radii) | (w2 <= radii**2)  # unbounded, inside-out or around o

    n_rays = v.shape[0]
    ranges = np.full(n_rays, np.nan)
    out_labels = np.zeros(n_rays, dtype=np.int64)
    for lo in range(0, n_rays, chunk):
        vc = v[lo : lo + chunk]
        with np.errstate(invalid="ignore"):
            tc = vc @ np.where(always[:, None], 0.0, w).T  # [n S] closest-approach parameter
            near = (tc > 0.0) & (w2 - tc * tc <= radii**2)
        use = always | np.any(near, axis=0)
        faces = use[owner]
        r_blk, f_blk = _cast_block(
            vc,
            normals[faces],
            gap[faces],
            sizes[use],
            io_solid[use],
            io_usable[use],
        )
        hit = f_blk >= 0
        ranges[lo : lo + chunk] = np.where(hit, r_blk, np.nan)
        if np.any(hit):
            out_labels[lo : lo + chunk] = np.where(hit, labels[faces][np.maximum(f_blk, 0)], 0)
    return ranges, out_labels


def _cast_block(
    v: np.ndarray,
    normals: np.ndarray,
    gap: np.ndarray,
    sizes: np.ndarray,
    io_solid: np.ndarray,
    io_usable: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Slab-method first hits of unit rays ``v`` [n 3] against solids with contiguous faces.

    ``gap = d - n . o`` [F]; ``sizes`` [S] faces per solid. Returns ``[n]`` ranges and the hit
    face index into the given faces (``-1`` where nothing is hit).
    """
    n_rays = v.shape[0]
    if sizes.size == 0:
        return np.full(n_rays, np.inf), np.full(n_rays, -1)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    owner = np.repeat(np.arange(sizes.size), sizes)
    nv = v @ normals.T  # [n F]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = gap / nv
    t_enter = np.where(nv < 0.0, t, -np.inf)
    t_exit = np.where(nv > 0.0, t, np.inf)
    parallel_outside = (nv == 0.0) & (gap < 0.0)  # the origin is outside this face's slab
    if np.any(parallel_outside):
        t_enter[parallel_outside] = np.inf
        t_exit[parallel_outside] = -np.inf
    s_in = np.maximum.reduceat(t_enter, starts, axis=1)  # [n S]
    s_out = np.minimum.reduceat(t_exit, starts, axis=1)
    hit_obj = (~io_solid) & (s_in <= s_out) & (s_in > 0.0) & np.isfinite(s_in)
    hit_io = io_usable & (s_out > 0.0) & np.isfinite(s_out)
    t_solid = np.where(hit_obj, s_in, np.where(hit_io, s_out, np.inf))
    best = np.argmin(t_solid, axis=1)  # [n]
    t_best = np.take_along_axis(t_solid, best[:, None], axis=1)[:, 0]
    # The hit face attains t_in (ordinary solid) or t_out (inside-out) within the best solid.
    key = np.where(io_solid[owner], -t_exit, t_enter)
    key = np.where(owner[None, :] == best[:, None], key, -np.inf)
    face = np.argmax(key, axis=1)
    return t_best, np.where(np.isfinite(t_best), face, -1)


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


@dataclasses.dataclass(frozen=True, eq=False)
class SynPEBScan:
    """A simulated organized SynPEB scan with ground-truth plane labels.

    Attributes:
        points: ``[H W 3]`` float64 points (m) in the sensor frame: noisy range times the
            nominal ray direction; NaN where there is no return.
        ranges: ``[H W]`` float64 noisy ranges (m), NaN where there is no return.
        labels: ``[H W]`` int64 ground-truth plane label of each point (0 = no return).
        azimuth_rad: ``[W]`` float64 nominal azimuth of each column (``atan2(y, x)``).
        elevation_rad: ``[H]`` float64 nominal elevation of each row (row 0 at the top).
        plane_normals: ``[P+1 3]`` float64 plane normals indexed by label (row 0 NaN).
        plane_offsets: ``[P+1]`` float64 plane offsets (m) indexed by label (row 0 NaN).
        adjacent_labels: ``[M 2]`` int64 label pairs sharing an edge (see
            :class:`SynPEBScene`).
        seed: the noise seed.
        scene_seed: the scene's seed (``None`` for hand-made scenes).
    """

    points: np.ndarray
    ranges: np.ndarray
    labels: np.ndarray
    azimuth_rad: np.ndarray
    elevation_rad: np.ndarray
    plane_normals: np.ndarray
    plane_offsets: np.ndarray
    adjacent_labels: np.ndarray
    seed: int
    scene_seed: int | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``, rows and columns of the scan."""
        return (int(self.labels.shape[0]), int(self.labels.shape[1]))


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


# --------------------------------------------------------------------------------------------
# PCD I/O
# --------------------------------------------------------------------------------------------

_SYNPEB_PCD_EXPECTED = (
    "an organized PCD (HEIGHT > 1) with fields x y z intensity, intensity holding the "
    "integer plane label (0 = no return)"
)


def write_synpeb_pcd(
    path: str | os.PathLike[str], scan: SynPEBScan, *, data: str = "binary_compressed"
) -> Path:
    """Writes a scan as a SynPEB PCD file: organized, fields ``x y z intensity`` (float32).

    The label is stored as a float32 in ``intensity``; points without return are NaN.

    Args:
        path: output file (overwritten).
        scan: the scan.
        data: PCD encoding, ``"ascii"``, ``"binary"`` or ``"binary_compressed"``.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ValueError: if ``scan`` is not a :class:`SynPEBScan` or ``data`` is unknown.
    """
    if not isinstance(scan, SynPEBScan):
        raise ValueError(f"scan must be a SynPEBScan, got {type(scan).__name__}")
    pts = np.asarray(scan.points, dtype=np.float32)
    fields = {
        "x": pts[..., 0],
        "y": pts[..., 1],
        "z": pts[..., 2],
        "intensity": np.asarray(scan.labels).astype(np.float32),
    }
    return write_pcd(path, PointCloud.from_fields(fields), data=data)


def load_synpeb_pcd(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Reads a SynPEB PCD file (organized; ``intensity`` holds the plane label).

    Args:
        path: the file, e.g. the shared ``synpeb/test_100.pcd`` crop.

    Returns:
        ``(points, labels)``: ``[H W 3]`` float64 points (m) and ``[H W]`` int64 labels;
        points with a NaN coordinate get label 0.

    Raises:
        DatasetFormatError: if the file is not an organized cloud with fields
            ``x y z intensity`` or a label is not a non-negative integer (a ``ValueError``).
    """
    cloud = read_pcd(path)
    missing = [k for k in ("x", "y", "z", "intensity") if k not in cloud]
    if missing:
        raise DatasetFormatError(
            path,
            f"missing field(s) {missing}; has {list(cloud.fields)}",
            expected=_SYNPEB_PCD_EXPECTED,
        )
    if not cloud.is_organized:
        raise DatasetFormatError(
            path,
            f"cloud is not organized (HEIGHT {cloud.height}, WIDTH {cloud.width})",
            expected=_SYNPEB_PCD_EXPECTED,
        )
    if any(cloud[k].ndim != 2 for k in ("x", "y", "z", "intensity")):
        raise DatasetFormatError(
            path, "fields x y z intensity must have COUNT 1", expected=_SYNPEB_PCD_EXPECTED
        )
    points = cloud.points_xyz
    valid = np.all(np.isfinite(points), axis=-1)
    raw = cloud["intensity"].astype(np.float64)
    good = np.isfinite(raw) & (raw >= 0) & (raw == np.round(raw))
    bad = valid & ~good
    if np.any(bad):
        row, col = np.argwhere(bad)[0]
        raise DatasetFormatError(
            path,
            f"intensity {raw[row, col]!r} at row {row}, column {col} is not a plane label",
            expected=_SYNPEB_PCD_EXPECTED,
        )
    labels = np.where(valid, np.where(good, raw, 0.0), 0.0).astype(np.int64)
    return points, labels
