"""Convex-polyhedron scenes with labelled faces and their exact ray caster (NumPy).

A SynPEB-style scene (:class:`SynPEBScene`) is a list of convex polyhedra
(:class:`ConvexPolyhedron`), each given by half-spaces ``n_f . x <= d_f`` (outward unit
normals ``n_f``, offsets ``d_f`` in metres) and one ground-truth plane label per face. The
room is an *inside-out* polyhedron: rays start inside it and hit it where they leave it.
:func:`cast_rays` intersects rays with the scene exactly (the half-space slab method per
convex solid, in float64).

The caster is NumPy, not a :mod:`lidarjax.raytrace` primitive: the geometry core's slab
test (:func:`~lidarjax.raytrace.ray_box`) handles axis-aligned boxes only, and a ray
against a general convex polyhedron (any number of oblique faces, reporting the face hit)
has no primitive there yet.

NumPy only; nothing here is called inside ``jit``.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import operator
from collections.abc import Sequence

import numpy as np

__all__ = ["ConvexPolyhedron", "SynPEBScene", "cast_rays"]

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
