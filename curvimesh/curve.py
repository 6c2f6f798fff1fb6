"""Curving a straight mesh: P2 edge nodes on geodesic parabolas, with backtracking.

Every interior edge gets its middle node on its shortest parabola (paper
equation (3); with the node free in the plane where the metric's frame turns
fast, :mod:`curvimesh.freenode`); a boundary edge keeps its node on its side, at the point that
halves its metric length (kept within :data:`SIDE_NODE_RANGE` of the edge).
Where a triangle comes out invalid (its Jacobian not positive everywhere,
decided exactly), the edge nodes of its interior edges are moved back
towards the straight midpoints, α ← α/2, until every triangle is valid
(paper section 6: "a backtracking step is applied"). A counter-clockwise
triangle whose interior edges are straight is valid, so the loop ends.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from curvimesh.bezier import valid_exact
from curvimesh.boundary import halving_points
from curvimesh.errors import WorkError
from curvimesh.freenode import shortest_parabola
from curvimesh.mesh import Mesh, boundary_sides, p1_of

#: Halvings of α before an edge is made straight.
MAX_HALVINGS = 6

#: Where a side edge's node may lie, as a fraction of the edge. With the node
#: shifted by δ (a fraction of the edge) from the midpoint of edge 01 of a
#: triangle of area A whose other edges are straight, the Jacobian is
#: 2A (1 + 4δ (1 − 2ξ − η)): positive everywhere iff |δ| < 1/4. Where the metric
#: varies fast along a side (a sharp front crossing it), the point halving the
#: metric length can lie outside the middle half, and no backtracking of the
#: other edges would make the triangle valid.
SIDE_NODE_RANGE = (0.3, 0.7)


def assemble_p2(corner_points: NDArray, mesh: Mesh, mids: NDArray) -> Mesh:
    """P2 mesh from a P1 ``mesh`` and one middle node per edge ``(E, 2)``.

    Nodes: the corners, then the edge nodes in :attr:`Mesh.edges` order.
    """
    n = len(corner_points)
    points = np.concatenate([corner_points, mids])
    tris = np.column_stack([mesh.corners, n + mesh.tri_edges])
    return Mesh(points, tris, mesh.box)


def boundary_edge_mask(mesh: Mesh) -> NDArray:
    """``(E,)`` True for edges on a side of the box (they stay straight)."""
    mask = np.zeros(len(mesh.edges), dtype=bool)
    be = mesh.boundary_edges
    mask[be[boundary_sides(mesh) >= 0]] = True
    return mask


def backtrack_to_valid(
    mesh: Mesh, corner_points: NDArray, mids: NDArray, movable: NDArray
) -> tuple[NDArray, int]:
    """Move edge nodes towards the midpoints until every triangle is valid.

    ``mids`` ``(E, 2)`` are the wished edge nodes and ``movable`` ``(E,)`` the
    edges that may be straightened. Returns the valid nodes and how many
    backtracking rounds were needed.
    """
    x0 = corner_points[mesh.edges[:, 0]]
    x1 = corner_points[mesh.edges[:, 1]]
    straight = 0.5 * (x0 + x1)
    offset = mids - straight
    scale = np.ones(len(mids))
    rounds = 0
    while True:
        cur = straight + scale[:, None] * offset
        p2 = assemble_p2(corner_points, mesh, cur)
        ok = valid_exact(p2.points[p2.triangles])
        if ok.all():
            return cur, rounds
        edges = np.unique(mesh.tri_edges[~ok])
        edges = edges[movable[edges] & (scale[edges] > 0)]
        if edges.size == 0:
            raise WorkError("no valid curved mesh: a straight triangle is inverted")
        scale[edges] = np.where(scale[edges] > 0.5**MAX_HALVINGS, scale[edges] / 2, 0.0)
        rounds += 1


def curve(field, mesh: Mesh, *, straight: bool = False) -> Mesh:
    """The P2 mesh of ``mesh``'s corners with every edge on its geodesic parabola.

    Input: a P1 (or P2, whose edge nodes are recomputed) mesh with
    counter-clockwise triangles. Output: a valid P2 mesh, corners first
    (same numbering as ``p1_of(mesh)``), then one node per edge. With
    ``straight`` every edge node is the midpoint (boundary nodes still halve
    the metric length along their side): the straight-sided mesh to compare
    curved meshes with.
    """
    p1 = p1_of(mesh) if mesh.order == 2 else mesh
    pts = np.asarray(p1.points)
    x0, x1 = pts[p1.edges[:, 0]], pts[p1.edges[:, 1]]
    on_side = boundary_edge_mask(p1)
    mids = np.empty((len(p1.edges), 2))
    if on_side.any():
        a, d = x0[on_side], x1[on_side] - x0[on_side]
        half = halving_points(field, a, a + d)
        frac = np.einsum("ij,ij->i", half - a, d) / np.einsum("ij,ij->i", d, d)
        lo, hi = SIDE_NODE_RANGE
        out = (frac < lo) | (frac > hi)
        half[out] = a[out] + np.clip(frac[out], lo, hi)[:, None] * d[out]
        mids[on_side] = half
    inner = ~on_side
    if straight:
        mids[inner] = 0.5 * (x0[inner] + x1[inner])
    elif inner.any():
        par = shortest_parabola(field, x0[inner], x1[inner], exact_length=False)
        mids[inner] = par.mid
    mids, _ = backtrack_to_valid(p1, pts, mids, inner)
    return assemble_p2(pts, p1, mids)


__all__ = ["assemble_p2", "backtrack_to_valid", "curve"]
