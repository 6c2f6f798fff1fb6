"""The P2 triangle mesh as arrays, and its derived topology.

A :class:`Mesh` holds points ``(n, 2)`` and triangles ``(m, 3)`` (P1) or
``(m, 6)`` (P2). The corners of a triangle come first, counter-clockwise, then
for P2 the nodes of its edges 0-1, 1-2, 2-0 (Gmsh ``triangle6`` order)::

        2
        | \\
        5   4
        |     \\
        0 - 3 - 1

Edges are the unique corner pairs ``(i, j)`` with ``i < j``, sorted
lexicographically, so that everything derived from a mesh is deterministic.
Local edge ``k`` of a triangle joins its corners ``k`` and ``(k + 1) % 3``.
A mesh without triangles (shape ``(0, 3)``) is a point cloud.

The mesh is immutable: its arrays are read-only and the derived topology is
computed once, on first use, and cached on the object. An :class:`EdgeStore`
keeps a node and a length per edge, keyed by its sorted corners, for the
stages that change the triangles (swaps, intrinsic flips).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

from curvimesh import kernels

__all__ = [
    "EdgeStore",
    "Mesh",
    "apply_flips",
    "boundary_sides",
    "carried",
    "cells_at_vertices",
    "flip_candidates",
    "independent_flips",
    "is_conforming",
    "p1_of",
    "signed_areas",
    "sorted_find",
    "sorted_member",
    "sorted_union",
    "to_p2_straight",
]

# Local edge k of a triangle joins corners _LOCAL_EDGES[k] = (k, (k + 1) % 3).
_LOCAL_EDGES = np.array([[0, 1], [1, 2], [2, 0]])


def _frozen(x: ArrayLike, dtype: type) -> NDArray:
    """Return ``x`` as a read-only array of ``dtype``, never freezing the caller's array."""
    arr = np.asarray(x, dtype=dtype)
    if arr.flags.writeable or not arr.flags.owndata:
        arr = arr.copy()
    arr.setflags(write=False)
    return arr


def _readonly(arr: NDArray) -> NDArray:
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False, repr=False)
class Mesh:
    """A P1 or P2 triangle mesh, or a point cloud.

    Attributes:
        points: ``(n, 2)`` float64 node coordinates.
        triangles: ``(m, 3)`` or ``(m, 6)`` int64 node ids: corners
            counter-clockwise, then (P2) the nodes of edges 01, 12, 20.
            ``(0, 3)`` for a point cloud.
        box: ``(xmin, ymin, xmax, ymax)`` of the domain, if known.

    The arrays are copied unless already read-only and are made read-only.

    >>> mesh = Mesh([[0, 0], [1, 0], [1, 1], [0, 1]], [[0, 1, 2], [0, 2, 3]])
    >>> mesh.order, len(mesh.edges), mesh.boundary_edges.tolist()
    (1, 5, [0, 2, 3, 4])
    >>> mesh.edges[1].tolist(), mesh.edge_tris[1].tolist()
    ([0, 2], [0, 1])
    >>> mesh.neighbours.tolist()
    [[-1, -1, 1], [0, -1, -1]]
    """

    points: NDArray[np.float64]
    triangles: NDArray[np.int64]
    box: tuple[float, float, float, float] | None = None

    def __post_init__(self) -> None:
        points = _frozen(self.points, np.float64)
        if points.ndim != 2 or points.shape[1] != 2:
            raise ValueError(f"points must have shape (n, 2), got {points.shape}")
        raw = np.asarray(self.triangles)
        if raw.size == 0:
            width = raw.shape[1] if raw.ndim == 2 and raw.shape[1] in (3, 6) else 3
            raw = np.zeros((0, width), dtype=np.int64)
        elif raw.dtype.kind not in "iu":
            raise ValueError(f"triangles must hold integers, got {raw.dtype}")
        triangles = _frozen(raw, np.int64)
        if triangles.ndim != 2 or triangles.shape[1] not in (3, 6):
            raise ValueError(f"triangles must have shape (m, 3) or (m, 6), got {triangles.shape}")
        if triangles.size and (triangles.min() < 0 or triangles.max() >= len(points)):
            raise ValueError(f"triangle node ids must lie in [0, {len(points)})")
        box = self.box
        if box is not None:
            box = tuple(float(v) for v in box)
            if len(box) != 4 or not (box[0] <= box[2] and box[1] <= box[3]):
                raise ValueError(f"box must be (xmin, ymin, xmax, ymax), got {self.box}")
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "triangles", triangles)
        object.__setattr__(self, "box", box)

    def __repr__(self) -> str:
        return (
            f"Mesh(order={self.order}, nodes={len(self.points)}, "
            f"triangles={len(self.triangles)}, box={self.box})"
        )

    @property
    def order(self) -> int:
        """Polynomial order of the triangles: 1 (and for a point cloud) or 2."""
        return 2 if self.triangles.shape[1] == 6 else 1

    @property
    def corners(self) -> NDArray[np.int64]:
        """``(m, 3)`` corner node ids of the triangles (a read-only view)."""
        return self.triangles[:, :3]

    @cached_property
    def vertex_ids(self) -> NDArray[np.int64]:
        """``(nv,)`` sorted unique node ids that are triangle corners (marked in a mask of
        the nodes: O(n + m), where np.unique sorts the 3m corners)."""
        used = np.zeros(len(self.points), dtype=bool)
        used[self.corners.ravel()] = True
        return _readonly(np.flatnonzero(used))

    @cached_property
    def _edge_table(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        # A counting sort of the sides by their lower end (compiled): the sorted
        # unique edges and the inverse that np.unique of lo * n + hi gives.
        edges, tri_edges = kernels.edge_table(self.triangles, len(self.points))
        return _readonly(edges), _readonly(tri_edges)

    @property
    def edges(self) -> NDArray[np.int64]:
        """``(E, 2)`` unique corner pairs ``(i, j)``, ``i < j``, sorted lexicographically."""
        return self._edge_table[0]

    @property
    def tri_edges(self) -> NDArray[np.int64]:
        """``(m, 3)`` index in :attr:`edges` of the edges 01, 12, 20 of each triangle."""
        return self._edge_table[1]

    @cached_property
    def edge_tris(self) -> NDArray[np.int64]:
        """``(E, 2)`` the triangles of each edge, ascending; ``-1`` in column 1 on the boundary.

        On a non-conforming edge held by more than two triangles, the first two.
        """
        return _readonly(kernels.edge_triangles(self.tri_edges, len(self.edges)))

    @cached_property
    def edge_mid(self) -> NDArray[np.int64]:
        """``(E,)`` the P2 node id of each edge; ``-1`` everywhere for a P1 mesh."""
        mid = np.full(len(self.edges), -1, dtype=np.int64)
        if self.order == 2:
            np.maximum.at(mid, self.tri_edges.ravel(), self.triangles[:, 3:].ravel())
        return _readonly(mid)

    @cached_property
    def boundary_edges(self) -> NDArray[np.int64]:
        """``(nb,)`` ascending indices in :attr:`edges` of the edges held by one triangle."""
        return _readonly(np.flatnonzero(self.edge_tris[:, 1] < 0))

    @cached_property
    def boundary_vertices(self) -> NDArray[np.bool_]:
        """``(n,)`` True for the nodes that end a boundary edge."""
        mask = np.zeros(len(self.points), dtype=bool)
        mask[self.edges[self.boundary_edges].ravel()] = True
        return _readonly(mask)

    @cached_property
    def boundary_lines(self) -> NDArray[np.int64]:
        """``(nb, 2)`` (P1) or ``(nb, 3)`` (P2) node ids of each boundary edge.

        Rows follow :attr:`boundary_edges`. Each runs as in its triangle, so
        the domain lies on its left; the P2 edge node comes last (Gmsh
        ``line3`` order).
        """
        be = self.boundary_edges
        tri = self.edge_tris[be, 0]
        local = np.argmax(self.tri_edges[tri] == be[:, None], axis=1)
        cols = [local, (local + 1) % 3] + ([local + 3] if self.order == 2 else [])
        lines = np.column_stack([self.triangles[tri, c] for c in cols]).astype(np.int64)
        return _readonly(lines.reshape(len(be), len(cols)))

    @cached_property
    def _neighbour_tables(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        nbr, side = kernels.neighbour_tables(self.tri_edges, self.edge_tris)
        return _readonly(nbr), _readonly(side)

    @property
    def neighbours(self) -> NDArray[np.int64]:
        """``(m, 3)`` the triangle across local edge 01, 12, 20 of each triangle, or ``-1``."""
        return self._neighbour_tables[0]

    @property
    def neighbour_sides(self) -> NDArray[np.int64]:
        """``(m, 3)`` the local edge of :attr:`neighbours` ``[t, k]`` that faces t, or ``-1``
        on the boundary (on a non-conforming edge, 0 where the neighbour does not face t).

        >>> Mesh([[0, 0], [1, 0], [1, 1], [0, 1]], [[0, 1, 2], [0, 2, 3]]).neighbour_sides.tolist()
        [[-1, -1, 0], [2, -1, -1]]
        """
        return self._neighbour_tables[1]


def signed_areas(points: ArrayLike, tris: ArrayLike) -> NDArray[np.float64]:
    """Signed areas ``(m,)`` of the straight triangles on the first three columns of ``tris``.

    Positive for counter-clockwise corners: A = ((x1 - x0) × (x2 - x0)) / 2.

    >>> signed_areas([[0, 0], [2, 0], [0, 1]], [[0, 1, 2], [0, 2, 1]]).tolist()
    [1.0, -1.0]
    """
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(tris, dtype=np.int64)
    if t.size == 0:
        return np.zeros(0)
    u = p[t[:, 1]] - p[t[:, 0]]
    v = p[t[:, 2]] - p[t[:, 0]]
    return 0.5 * (u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])


def rotate_triangles(tris: NDArray, k: NDArray) -> NDArray[np.int64]:
    """P2 triangles ``(s, 6)`` renumbered so that their local edge ``k`` ``(s,)`` comes first.

    Corners (c₀, c₁, c₂) become (c_k, c_k+1, c_k+2) and the edge nodes follow
    (node j sits on edge c_j → c_j+1), so the orientation is kept.

    >>> rotate_triangles(np.array([[0, 1, 2, 3, 4, 5]]), np.array([1])).tolist()
    [[1, 2, 0, 4, 5, 3]]
    """
    r = np.arange(len(tris))
    cols = [(k + i) % 3 for i in range(3)] + [3 + (k + i) % 3 for i in range(3)]
    return np.column_stack([tris[r, c] for c in cols])


def is_conforming(mesh: Mesh) -> bool:
    """Whether ``mesh`` is a conforming triangulation.

    True when every triangle has three distinct corners, every edge is held
    by at most two triangles, an edge held by two runs in opposite directions
    in them, and (P2) both triangles of an edge use the same edge node, that
    node serving no other edge and being no corner. Geometry is not looked at.
    """
    corners = mesh.corners
    if len(corners) == 0:
        return True
    if np.any((corners[:, 0] == corners[:, 1]) | (corners[:, 1] == corners[:, 2])):
        return False
    if np.any(corners[:, 2] == corners[:, 0]):
        return False
    n_edges = len(mesh.edges)
    flat = mesh.tri_edges.ravel()
    counts = np.bincount(flat, minlength=n_edges)
    if counts.max() > 2:
        return False
    # +1 where the triangle runs along its edge i -> j (i < j), -1 against it:
    # an interior edge must get one of each.
    sense = np.where(corners.ravel() < corners[:, [1, 2, 0]].ravel(), 1, -1)
    if np.any(np.bincount(flat, weights=sense, minlength=n_edges)[counts == 2] != 0):
        return False
    if mesh.order == 2:
        mids = mesh.triangles[:, 3:].ravel()
        low = np.full(n_edges, np.iinfo(np.int64).max, dtype=np.int64)
        np.minimum.at(low, flat, mids)
        if np.any(low != mesh.edge_mid):
            return False
        if len(np.unique(mesh.edge_mid)) != n_edges:
            return False
        if np.intersect1d(mesh.edge_mid, mesh.vertex_ids).size:
            return False
    return True


def to_p2_straight(mesh: Mesh) -> Mesh:
    """The straight-sided P2 mesh with the corners of ``mesh``.

    A P1 mesh gets one new node per edge, at its midpoint, numbered
    ``n + e`` for edge ``e`` of :attr:`Mesh.edges` (appended after the
    existing points). A P2 mesh keeps its numbering and has its edge nodes
    moved back to the edge midpoints.

    >>> p2 = to_p2_straight(Mesh([[0, 0], [2, 0], [0, 2]], [[0, 1, 2]]))
    >>> p2.triangles.tolist(), p2.points[3:].tolist()
    ([[0, 1, 2, 3, 5, 4]], [[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    """
    corners = mesh.corners
    if mesh.order == 2:
        points = np.array(mesh.points)
        for k, (a, b) in enumerate(_LOCAL_EDGES):
            points[mesh.triangles[:, 3 + k]] = 0.5 * (
                mesh.points[corners[:, a]] + mesh.points[corners[:, b]]
            )
        return Mesh(points, mesh.triangles, mesh.box)
    n = len(mesh.points)
    edges = mesh.edges
    mid = 0.5 * (mesh.points[edges[:, 0]] + mesh.points[edges[:, 1]])
    points = np.concatenate([mesh.points, mid.reshape(-1, 2)])
    triangles = np.column_stack([corners, n + mesh.tri_edges]).reshape(-1, 6)
    return Mesh(points, triangles, mesh.box)


def p1_of(mesh: Mesh) -> Mesh:
    """The P1 mesh on the corners of ``mesh``.

    Nodes that are no triangle corner are dropped; the others keep their
    relative order. A point cloud is returned unchanged.

    >>> p1 = p1_of(Mesh([[0, 0], [9, 9], [2, 0], [0, 2], [1, 0], [1, 1], [0, 1]],
    ...                 [[0, 2, 3, 4, 5, 6]]))
    >>> p1.triangles.tolist(), p1.points.tolist()
    ([[0, 1, 2]], [[0.0, 0.0], [2.0, 0.0], [0.0, 2.0]])
    """
    if len(mesh.triangles) == 0:
        return mesh
    return Mesh(mesh.points[mesh.vertex_ids], corner_numbers(mesh)[mesh.corners], mesh.box)


def corner_numbers(mesh: Mesh) -> NDArray[np.int64]:
    """Each node's number among the triangle corners ``(n,)``, -1 for the other nodes:
    the point it is in :func:`p1_of`.

    >>> corner_numbers(Mesh([[0, 0], [9, 9], [2, 0], [0, 2], [1, 0], [1, 1], [0, 1]],
    ...                     [[0, 2, 3, 4, 5, 6]])).tolist()
    [0, -1, 1, 2, -1, -1, -1]
    """
    out = np.full(len(mesh.points), -1, dtype=np.int64)
    out[mesh.vertex_ids] = np.arange(len(mesh.vertex_ids))
    return out


def p1_edges(mesh: Mesh) -> NDArray[np.int64]:
    """The two corners of each edge of ``mesh`` ``(ne, 2)``, numbered as the points of
    :func:`p1_of` (the edges in ``mesh.edges``' order)."""
    return corner_numbers(mesh)[mesh.edges]


def edge_nodes(mesh: Mesh) -> EdgeStore:
    """The middle nodes of ``mesh``'s edges in an :class:`EdgeStore` keyed by their
    corners numbered as in :func:`p1_of` (lengths not measured: zero)."""
    ends = p1_edges(mesh)
    store = EdgeStore(len(mesh.vertex_ids))
    store.add(store.key(ends[:, 0], ends[:, 1]), mesh.points[mesh.edge_mid], np.zeros(len(ends)))
    return store


def boundary_sides(mesh: Mesh, tol: float | None = None) -> NDArray[np.int64]:
    """The side of the domain box each boundary edge lies on.

    Returns ``(nb,)`` ints following :attr:`Mesh.boundary_edges`: 0 bottom,
    1 right, 2 top, 3 left, -1 on no side. An edge is on a side when both its
    corners are within ``tol`` of that side's line (default 1e-9 times the
    larger box extent). The box is ``mesh.box``, else the bounding box of the
    points.

    >>> mesh = Mesh([[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.5]],
    ...             [[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    >>> mesh.edges[mesh.boundary_edges].tolist(), boundary_sides(mesh).tolist()
    ([[0, 1], [0, 3], [1, 2], [2, 3]], [0, 3, 1, 2])
    """
    lines = mesh.points[mesh.edges[mesh.boundary_edges]]  # (nb, 2 ends, 2 coords)
    if len(lines) == 0:
        return np.zeros(0, dtype=np.int64)
    if mesh.box is not None:
        xmin, ymin, xmax, ymax = mesh.box
    else:
        (xmin, ymin), (xmax, ymax) = mesh.points.min(axis=0), mesh.points.max(axis=0)
    if tol is None:
        tol = 1e-9 * max(xmax - xmin, ymax - ymin, np.finfo(float).tiny)
    # (coordinate, value) of the line of each side: y = ymin, x = xmax, y = ymax, x = xmin.
    sides = [(1, ymin), (0, xmax), (1, ymax), (0, xmin)]
    result = np.full(len(lines), -1, dtype=np.int64)
    for side in reversed(range(4)):  # the first matching side wins
        axis, value = sides[side]
        on = np.all(np.abs(lines[:, :, axis] - value) <= tol, axis=1)
        result[on] = side
    return result


def local_edge(tri_edges: NDArray, tris: NDArray, edges: NDArray) -> NDArray[np.int64]:
    """Local index (0, 1, 2) of each edge ``(k,)`` in its triangle ``(k,)``: edge i of a
    triangle joins corners i and i + 1, and a P2 triangle holds its node in slot 3 + i.

    >>> mesh = Mesh([[0, 0], [1, 0], [1, 1], [0, 1]], [[0, 1, 2], [0, 2, 3]])
    >>> local_edge(mesh.tri_edges, np.array([0, 1]), np.array([1, 1])).tolist()
    [2, 0]
    """
    return np.argmax(tri_edges[tris] == np.asarray(edges)[:, None], axis=1)


def flip_candidates(mesh: Mesh) -> tuple[NDArray[np.int64], ...]:
    """The interior edges of ``mesh`` as flip candidates, with their quads.

    For every interior edge e = (a, b) held by t1 = (a, b, c) and t2 = (b, a, d)
    (corners counter-clockwise), returns ``(e, t1, t2, a, b, c, d)``, each
    ``(k,)``. Flipping e gives t1' = (a, d, c) and t2' = (d, b, c)::

              c                    c
            / | \\                / \\
           a t1|t2 b    -->     a --- b       (the quad a-d-b-c, new diagonal c-d)
            \\ | /                \\ /
              d                    d
    """
    edge_tris = mesh.edge_tris
    e = np.flatnonzero(edge_tris[:, 1] >= 0)
    t1, t2 = edge_tris[e, 0], edge_tris[e, 1]
    tri_edges, corners = mesh.tri_edges, mesh.corners
    k1, k2 = local_edge(tri_edges, t1, e), local_edge(tri_edges, t2, e)
    a = corners[t1, k1]
    b = corners[t1, (k1 + 1) % 3]
    c = corners[t1, (k1 + 2) % 3]
    d = corners[t2, (k2 + 2) % 3]
    return e, t1, t2, a, b, c, d


def independent_flips(t1: NDArray, t2: NDArray, priority: NDArray, m: int) -> NDArray[np.int64]:
    """Indices of candidates to flip together, no two touching the same triangle.

    Greedy by decreasing ``priority`` (ties broken by candidate order), over
    candidates ``(k,)`` joining triangles t1 and t2 of a mesh of m triangles.

    >>> independent_flips(np.array([0, 1, 2]), np.array([1, 2, 3]), np.array([1., 3., 2.]), 4)
    array([1])
    """
    order = np.argsort(-np.asarray(priority, dtype=float), kind="stable")
    used = np.zeros(m, dtype=bool)
    chosen = []
    for k in order.tolist():
        if not used[t1[k]] and not used[t2[k]]:
            used[t1[k]] = used[t2[k]] = True
            chosen.append(k)
    return np.array(chosen, dtype=np.int64)


def apply_flips(
    corners: NDArray, chosen: NDArray, t1: NDArray, t2: NDArray, a, b, c, d
) -> NDArray[np.int64]:
    """New corner array ``(m, 3)`` with the chosen flips made (see :func:`flip_candidates`)."""
    out = np.array(corners, dtype=np.int64)
    out[t1[chosen]] = np.column_stack([a[chosen], d[chosen], c[chosen]])
    out[t2[chosen]] = np.column_stack([d[chosen], b[chosen], c[chosen]])
    return out


def cells_at_vertices(cells: NDArray, n: int) -> tuple[NDArray, NDArray]:
    """The cells around each vertex, in compressed rows: the rows of ``cells`` ``(m, k)``
    (triangles' corners, edges' ends) holding vertex v are ``order[start[v]:start[v + 1]]``,
    ascending (n points).

    >>> start, order = cells_at_vertices(np.array([[0, 1, 2], [1, 3, 2]]), 4)
    >>> order[start[2] : start[3]].tolist()
    [0, 1]
    >>> start, order = cells_at_vertices(np.array([[0, 1], [1, 2], [2, 0]]), 3)
    >>> order[start[0] : start[1]].tolist()
    [0, 2]
    """
    cells = np.asarray(cells)
    flat = cells.ravel()
    by_vertex = np.argsort(flat, kind="stable")
    start = np.searchsorted(flat[by_vertex], np.arange(n + 1))
    return start, by_vertex // cells.shape[1]


def sorted_find(sorted_keys: NDArray, keys: NDArray) -> tuple[NDArray, NDArray[np.bool_]]:
    """Where each of ``keys`` ``(k,)`` is in the ascending array ``sorted_keys`` and
    whether it is there, by binary search: positions ``(k,)`` (clipped to the last
    one; 0 while ``sorted_keys`` is empty) and ``(k,)`` found.

    >>> pos, found = sorted_find(np.array([2, 5, 9]), np.array([9, 1, 5, 10]))
    >>> pos.tolist(), found.tolist()
    ([2, 0, 1, 2], [True, False, True, False])
    """
    if len(sorted_keys) == 0:
        return np.zeros(len(keys), dtype=np.int64), np.zeros(len(keys), dtype=bool)
    pos = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
    return pos, sorted_keys[pos] == keys


def carried(old_edges: NDArray, values: NDArray, edges: NDArray, n: int) -> NDArray:
    """Values ``(E,)`` of ``edges`` ``(E, 2)`` from the same edges in ``old_edges``
    ``(E', 2)`` (``values`` ``(E',)``; both sorted, as :attr:`Mesh.edges`, ``n`` points),
    NaN for the new ones.

    >>> carried(np.array([[0, 1], [1, 2]]), np.array([5.0, 7.0]), np.array([[0, 2], [1, 2]]), 3)
    array([nan,  7.])
    """
    old_keys = old_edges[:, 0] * n + old_edges[:, 1]
    keys = edges[:, 0] * n + edges[:, 1]
    pos, found = sorted_find(old_keys, keys)
    return np.where(found, values[pos], np.nan)


def sorted_member(sorted_keys: NDArray, keys: NDArray) -> NDArray[np.bool_]:
    """Whether each of ``keys`` ``(k,)`` is in the ascending array ``sorted_keys``, by
    binary search (:func:`sorted_find`; np.isin sorts or hashes both arrays at every
    call).

    >>> sorted_member(np.array([2, 5, 9]), np.array([9, 1, 5, 10])).tolist()
    [True, False, True, False]
    """
    return sorted_find(sorted_keys, keys)[1]


def sorted_union(sorted_keys: NDArray, keys: NDArray) -> NDArray:
    """The distinct values of the ascending array ``sorted_keys`` and of ``keys``, ascending
    (np.union1d, by a stable sort that merges the sorted run instead of hashing).

    >>> sorted_union(np.array([2, 5, 9]), np.array([7, 2, 1])).tolist()
    [1, 2, 5, 7, 9]
    """
    out = np.concatenate([sorted_keys, keys])
    out.sort(kind="stable")
    keep = np.ones(len(out), dtype=bool)
    keep[1:] = out[1:] != out[:-1]
    return out[keep]


class EdgeStore:
    """Middle nodes ``(k, 2)`` and lengths ``(k,)`` of edges, keyed by ``lo * n + hi``."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.keys = np.zeros(0, dtype=np.int64)
        self.mid = np.zeros((0, 2))
        self.length = np.zeros(0)

    def key(self, a: NDArray, b: NDArray) -> NDArray:
        """Keys of the undirected edges (a, b)."""
        return np.minimum(a, b) * self.n + np.maximum(a, b)

    def find(self, keys: NDArray) -> tuple[NDArray, NDArray]:
        """Positions of keys in the store and whether they are there (:func:`sorted_find`)."""
        return sorted_find(self.keys, keys)

    def add(self, keys: NDArray, mid: NDArray, length: NDArray) -> None:
        """Insert or overwrite entries."""
        k = np.concatenate([keys, self.keys])
        order = np.argsort(k, kind="stable")  # new entries first among equal keys
        k = k[order]
        first = np.ones(len(k), dtype=bool)
        first[1:] = k[1:] != k[:-1]
        sel = order[first]
        self.keys = k[first]
        self.mid = np.concatenate([mid, self.mid])[sel]
        self.length = np.concatenate([length, self.length])[sel]
