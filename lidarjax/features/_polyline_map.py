"""Polyline maps of 2-D scans (dissertation ch. 10): :class:`PolylineMap`, a set of
polylines in a padded, static-shape layout (one vertex slot per scan ray, successor
pointers), with :meth:`PolylineMap.expected_ranges` (the ``r̂(z, L)`` of Eq. 10.1: distance
to the first intersection of each ray with the map). Extraction (PLE) is in
``_polyline.py``, the optimization (PLE+) in ``_polyline_plus.py``.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ..rays import RayBatch
from ..raytrace import first_segment_hits

_CHUNK = 2048  # rays per lax.map chunk in expected_ranges


# --------------------------------------------------------------------------------------
# Polyline map
# --------------------------------------------------------------------------------------


class PolylineMap(eqx.Module):
    """A set of polylines (no shared vertices) in a padded static-shape layout.

    Vertex slot ``i`` is used when ``active[i]``; its polyline continues with slot
    ``successor[i]`` (``-1``: the polyline ends at ``i``). A closed polyline (polygon) has
    successors forming a cycle. The segments are ``(vertices[i], vertices[successor[i]])``
    for every active ``i`` with ``successor[i] >= 0``. Leading axes ``[*batch]`` are allowed
    (e.g. one map per scan from a batched extraction).

    Attributes:
        vertices: ``[*batch v 2]`` vertex coordinates (m).
        successor: ``[*batch v]`` index of the next vertex along the polyline, ``-1`` if none.
        active: ``[*batch v]`` mask of used vertex slots.
    """

    vertices: Float[Array, "*batch v 2"]
    successor: Int[Array, "*batch v"]
    active: Bool[Array, "*batch v"]

    def __check_init__(self):
        v = self.vertices.shape
        if len(v) < 2 or v[-1] != 2:
            raise ValueError(f"vertices must have shape [*batch, v, 2], got {v}")
        if self.successor.shape != v[:-1] or self.active.shape != v[:-1]:
            raise ValueError(
                f"successor {self.successor.shape} and active {self.active.shape} must have "
                f"shape {v[:-1]} to match vertices"
            )

    @classmethod
    def from_polylines(
        cls,
        polylines: Sequence[ArrayLike],
        closed: Sequence[bool] | None = None,
        *,
        n_slots: int | None = None,
    ) -> PolylineMap:
        """Build a map from vertex arrays.

        Args:
            polylines: list of ``[m_i 2]`` vertex arrays (m), ``m_i >= 2`` (``>= 3`` if closed).
            closed: per polyline, whether the last vertex connects back to the first
                (default: all open).
            n_slots: number of vertex slots (padding); default: the total vertex count.

        Returns:
            An unbatched :class:`PolylineMap`.

        Raises:
            ValueError: malformed polylines, non-finite vertices or too few slots.
        """
        closed = [False] * len(polylines) if closed is None else list(closed)
        if len(closed) != len(polylines):
            raise ValueError(f"closed has {len(closed)} entries for {len(polylines)} polylines")
        verts, succ = [], []
        for i, (pl, c) in enumerate(zip(polylines, closed)):
            a = np.asarray(pl, dtype=float)
            if a.ndim != 2 or a.shape[1] != 2 or a.shape[0] < (3 if c else 2):
                raise ValueError(
                    f"polylines[{i}] must have shape [m, 2] with m >= {3 if c else 2}, "
                    f"got {a.shape}"
                )
            if not np.all(np.isfinite(a)):
                raise ValueError(f"polylines[{i}] has non-finite vertices")
            base = len(verts)
            m = a.shape[0]
            verts.extend(a)
            nxt = list(range(base + 1, base + m)) + [base if c else -1]
            succ.extend(nxt)
        n = len(verts)
        n_slots = max(n, 1) if n_slots is None else int(n_slots)
        if n_slots < n:
            raise ValueError(f"n_slots={n_slots} is smaller than the vertex count {n}")
        v = np.zeros((n_slots, 2))
        s = np.full(n_slots, -1, np.int32)
        act = np.zeros(n_slots, bool)
        if n:
            v[:n] = np.asarray(verts)
            s[:n] = succ
            act[:n] = True
        return cls(jnp.asarray(v), jnp.asarray(s), jnp.asarray(act))

    def to_chains(self) -> tuple[list[np.ndarray], list[bool]]:
        """The polylines as vertex-slot index arrays (unbatched maps only).

        For a PLE map slot ``k`` is ray ``k``, so the chains index the scan's endpoints.

        Returns:
            ``(chains, closed)``: a list of ``[m]`` int arrays of slots in polyline order,
            and per polyline whether it is closed.
        """
        if self.vertices.ndim != 2:
            raise ValueError("to_chains needs an unbatched map; index the batch first")
        s = np.asarray(self.successor)
        act = np.asarray(self.active)
        pred = np.full(len(s), -1)
        linked = np.flatnonzero(act & (s >= 0))
        pred[s[linked]] = linked
        seen = np.zeros(len(s), bool)
        out, closed = [], []
        for i in np.flatnonzero(act & (pred < 0)):
            chain = [i]
            while s[chain[-1]] >= 0:
                chain.append(s[chain[-1]])
            seen[chain] = True
            out.append(np.asarray(chain))
            closed.append(False)
        for i in np.flatnonzero(act):  # what is left lies on cycles
            if seen[i]:
                continue
            chain = [i]
            while s[chain[-1]] != i:
                chain.append(s[chain[-1]])
            seen[chain] = True
            out.append(np.asarray(chain))
            closed.append(True)
        return out, closed

    def to_polylines(self) -> tuple[list[np.ndarray], list[bool]]:
        """The polylines as host arrays (unbatched maps only).

        Returns:
            ``(polylines, closed)``: a list of ``[m 2]`` vertex arrays (m) in order, and
            per polyline whether it is closed.
        """
        chains, closed = self.to_chains()
        v = np.asarray(self.vertices)
        return [v[c] for c in chains], closed

    @property
    def n_vertices(self) -> Int[Array, "*batch"]:
        """Number of vertices ``J`` (per batch element)."""
        return jnp.sum(self.active, axis=-1)

    def segments(self) -> tuple[Float[Array, "*batch v 2"], Float[Array, "*batch v 2"], Array]:
        """``(starts, ends, valid)``: one (possibly invalid) segment per vertex slot."""
        nxt = jnp.clip(self.successor, 0, None)
        ends = jnp.take_along_axis(self.vertices, nxt[..., None], axis=-2)
        return self.vertices, ends, self.active & (self.successor >= 0)

    def expected_ranges(self, rays: RayBatch) -> Float[Array, "*batch n"]:
        """``r̂(z, L)`` of Eq. (10.1): distance to the first intersection with the map.

        Args:
            rays: 2-D rays of shape ``[*batch n]`` whose leading axes match the map's
                (or any shape for an unbatched map).

        Returns:
            ``[*rays.shape]`` distances (m); ``inf`` where a ray hits no polyline.
        """
        return self.first_hits(rays)[0]

    def first_hits(self, rays: RayBatch) -> tuple[Array, Array]:
        """Like :meth:`expected_ranges`, also returning the index of the segment hit
        (its start vertex slot, ``-1`` if none)."""
        if rays.dim != 2:
            raise ValueError(f"rays must be 2-D, got dim={rays.dim}")
        bm = self.vertices.shape[:-2]
        if bm:
            if rays.shape[: len(bm)] != bm:
                raise ValueError(
                    f"rays of shape {rays.shape} do not start with the map's batch axes {bm}"
                )
            return _first_hits_batched(self, rays.origins, rays.directions)
        return _first_hits(self, rays.origins, rays.directions)


@eqx.filter_jit
def _first_hits_batched(m: PolylineMap, origins: Array, directions: Array):
    def one(mm, o, d):
        return _first_hits(mm, o, d)

    f = one
    for _ in range(m.vertices.ndim - 2):
        f = jax.vmap(f)
    return f(m, origins, directions)


def _first_hits(m: PolylineMap, origins: Array, directions: Array):
    shape = origins.shape[:-1]
    o = origins.reshape(-1, 2)
    d = directions.reshape(-1, 2)
    starts, ends, valid = m.segments()
    t, i = first_segment_hits(o, d, starts, ends, valid, chunk_size=_CHUNK)
    return t.reshape(shape), i.reshape(shape)
