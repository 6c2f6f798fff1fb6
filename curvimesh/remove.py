"""Vertex removal at flat triangles: a vertex taken out and its cavity re-triangulated.

A swap that refuses to make a short edge can leave a flat triangle: a vertex
almost on the opposite edge, with two edges near 0.7 and the third near 1.4.
When the vertex is hemmed in (all its edges near 0.7), no move of it raises
the quality without making an edge short (:mod:`curvimesh.shift`); the
vertex is one too many. This stage removes it: for each triangle of quality
(4) below ``min_quality``, worst first, and each of its interior corners v of
at most :data:`MAX_VALENCE` edges, the polygon of v's neighbours (its ring,
whose edges keep their nodes) is triangulated every possible way (Catalan
many: 2, 5, 14 or 42 for 4 to 7 neighbours). The new edges (diagonals of the
ring) are put on their shortest parabolas (paper eq. (3)), moved back
towards their straight midpoints by the fractions :data:`BACKTRACK` until
every new triangle is valid (exactly, from its Bezier coefficients). A
triangulation is admissible when every diagonal has metric length in
[``min_dist``, ``max_length``] and its worst quality is above the worst
quality of v's star; the admissible one with the best worst quality
replaces the star. The mesh loses one vertex and two triangles per removal.

The same removal serves the edges shorter than ``min_dist``, shortest first (two
vertices of a thin curved layer too close for the sampling's test, which a
triangulation in the layer's own coordinates joins, :mod:`curvimesh.charts`: 0.681
on ``bench/robustness/u72``), and the edges left longer than ``max_length``, longest
first: an end v of such an edge goes when its ring has an admissible
triangulation whose worst quality is at least min(worst quality of v's
star, ``min_quality``). Near the singular centre of concentric circles the
innermost vertices end up two rings apart from the next ones, joined by a
radial edge of about 2 (1.80 and 1.98 on a 12.5:1 field, two seeds); the
vertex of valence 3 at its inner end is one too many, and its ring's
triangle is in range.

Beyond the paper, whose only topological operation is the edge swap; vertex
removal by cavity re-triangulation is a classic remeshing operator (the
collapse of MMG and of Gmsh's anisotropic 2D mesher, for instance).
:func:`curvimesh.adapt.swap` runs it before the vertex shifts
(``--no-remove`` turns it off).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np
from numpy.typing import NDArray

from curvimesh.bezier import valid_exact
from curvimesh.freenode import shortest_parabola
from curvimesh.geodesic import parabola_length
from curvimesh.mesh import Mesh, rotate_triangles, signed_areas
from curvimesh.metric import MetricField
from curvimesh.quality import edge_lengths, metric_areas, quality_from

#: The most neighbours a removed vertex may have. Seven: in a thin layer about a small
#: circle (1,000:1, radius 0.15, bench/robustness u47), where the columns of points
#: across it end, one point lands under the chords of the rows beyond and is joined to
#: seven, by edges up to 2.45 (quality 0.22); its ring has a triangulation in range
#: (the mesh then 0.70 - 1.40, quality 0.62 at worst). The twelve examples do not change.
MAX_VALENCE = 7

#: How far under ``min_dist`` an edge's length must be for its ends to be removed: the
#: targets' 0.7 to three digits.
SHORT_SLACK = 1e-3

#: Fractions of the optimal offset tried for the nodes of the new edges, in order.
BACKTRACK = (1.0, 0.5, 0.25, 0.0)


@dataclass(frozen=True)
class RemoveResult:
    """The mesh after the removals and how many vertices were removed."""

    mesh: Mesh
    removed: int


@cache
def polygon_triangulations(n: int) -> tuple[tuple[tuple[int, int, int], ...], ...]:
    """Every triangulation of the convex polygon 0, 1, ..., n − 1 by diagonals.

    Triangles are counter-clockwise index triples (i < k < j); there are
    Catalan(n − 2) triangulations.

    >>> len(polygon_triangulations(4)), len(polygon_triangulations(6))
    (2, 14)
    >>> polygon_triangulations(4)
    (((0, 1, 3), (1, 2, 3)), ((0, 1, 2), (0, 2, 3)))
    """

    def sub(i: int, j: int) -> list[tuple[tuple[int, int, int], ...]]:
        if j - i < 2:
            return [()]
        return [
            (*left, (i, k, j), *right)
            for k in range(i + 1, j)
            for left in sub(i, k)
            for right in sub(k, j)
        ]

    return tuple(sub(0, n - 1))


def _ring(mesh: Mesh, v: int) -> tuple[NDArray, NDArray, NDArray] | None:
    """The star of an interior vertex v: its triangles ``(s,)``, its neighbours in
    counter-clockwise order ``(s,)`` and the node of each ring edge (ring[i],
    ring[i + 1]) ``(s,)``; None if the neighbours do not close a ring."""
    tris = np.flatnonzero((mesh.triangles[:, :3] == v).any(axis=1))
    local = np.argmax(mesh.triangles[tris, :3] == v, axis=1)
    rot = rotate_triangles(mesh.triangles[tris], local)  # (v, a, b, m_va, m_ab, m_bv)
    nxt = {int(r[1]): (int(r[2]), int(r[4])) for r in rot}
    if len(nxt) != len(tris):
        return None
    ring, nodes = [int(rot[0, 1])], []
    for _ in range(len(tris)):
        step = nxt.get(ring[-1])
        if step is None:
            return None
        ring.append(step[0])
        nodes.append(step[1])
    if ring[-1] != ring[0] or len(set(ring[:-1])) != len(tris):
        return None
    return tris, np.array(ring[:-1]), np.array(nodes)


def remove_vertices(
    field: MetricField,
    mesh: Mesh,
    *,
    min_dist: float = 0.7,
    max_length: float = 1.4,
    min_quality: float = 0.3,
    long_edges: bool = True,
    short_edges: bool = True,
) -> RemoveResult:
    """Remove vertices of the triangles of quality below ``min_quality``, (with
    ``short_edges``) of the edges shorter than ``min_dist`` (by more than
    :data:`SHORT_SLACK` of it) and (with ``long_edges``) of the edges longer than
    ``max_length`` (module docstring).

    ``mesh`` is a valid P2 mesh; the result is valid, with the removed
    vertices, their edge nodes and their triangles gone and the nodes
    renumbered in their order. Deterministic.
    """
    if mesh.order != 2 or len(mesh.triangles) == 0:
        return RemoveResult(mesh, 0)
    length = edge_lengths(field, mesh.points, mesh.edges, mesh.edge_mid)
    quality = quality_from(metric_areas(field, mesh.points[mesh.triangles]), length[mesh.tri_edges])
    fixed = mesh.boundary_vertices
    pts = [np.asarray(mesh.points)]
    n_pts = len(mesh.points)
    tris = np.array(mesh.triangles)
    alive = np.ones(len(tris), dtype=bool)
    touched = np.zeros(len(tris), dtype=bool)
    removed = 0
    # the flat triangles, worst first, then (with long_edges) the long edges, longest
    # first: (the triangle or the edge's triangles, its corners or ends, whether the new
    # worst quality must beat the star's)
    flat = np.flatnonzero(quality < min_quality)
    tasks = [
        (np.array([t]), mesh.triangles[t, :3], True)
        for t in flat[np.argsort(quality[flat], kind="stable")]
    ]
    et = mesh.edge_tris
    if short_edges:
        short = np.flatnonzero(length < min_dist * (1.0 - SHORT_SLACK))
        tasks += [
            (et[k][et[k] >= 0], mesh.edges[k], False)
            for k in short[np.argsort(length[short], kind="stable")]
        ]
    if long_edges:
        long = np.flatnonzero(length > max_length)
        tasks += [
            (et[k][et[k] >= 0], mesh.edges[k], False)
            for k in long[np.argsort(-length[long], kind="stable")]
        ]
    for at, ends, beat in tasks:
        if touched[at].any():
            continue
        for v in ends:
            if fixed[v]:
                continue
            ring = _ring(mesh, int(v))
            if ring is None or len(ring[1]) > MAX_VALENCE or touched[ring[0]].any():
                continue
            star, ring_v, ring_m = ring
            q_star = float(quality[star].min())
            got = _best_triangulation(
                field,
                mesh.points,
                ring_v,
                ring_m,
                (min_dist, max_length),
                q_star if beat else min(q_star, min_quality) - 1e-12,
            )
            if got is None:
                continue
            new_tris, new_nodes = got
            new_tris = np.where(new_tris < 0, n_pts - 1 - new_tris, new_tris)  # −1 − k → n + k
            pts.append(new_nodes)
            n_pts += len(new_nodes)
            keep = star[: len(new_tris)]
            tris[keep] = new_tris
            alive[star[len(new_tris) :]] = False
            touched[star] = True
            removed += 1
            break
    if removed == 0:
        return RemoveResult(mesh, 0)
    tris = tris[alive]
    all_pts = np.concatenate(pts)
    used = np.zeros(len(all_pts), dtype=bool)
    used[tris.ravel()] = True
    renum = np.cumsum(used) - 1
    return RemoveResult(Mesh(all_pts[used], renum[tris], mesh.box), removed)


def _triangle_nodes(
    triangulation: tuple[tuple[int, int, int], ...],
    ring: NDArray,
    ring_nodes: NDArray,
    diagonals: list[tuple[int, int]],
) -> NDArray:
    """The P2 triangles ``(n − 2, 6)`` of a triangulation of the ring: node ids, with
    the node of diagonal k written −1 − k."""
    n = len(ring)
    slot = {pq: k for k, pq in enumerate(diagonals)}

    def node(p: int, q: int) -> int:
        if (q - p) % n == 1:
            return int(ring_nodes[p])
        if (p - q) % n == 1:
            return int(ring_nodes[q])
        return -1 - slot[(min(p, q), max(p, q))]

    return np.array(
        [
            [ring[i], ring[k], ring[j], node(i, k), node(k, j), node(j, i)]
            for i, k, j in triangulation
        ]
    )


def _best_triangulation(
    field: MetricField,
    points: NDArray,
    ring: NDArray,
    ring_nodes: NDArray,
    bounds: tuple[float, float],
    q_star: float,
) -> tuple[NDArray, NDArray] | None:
    """The best admissible triangulation of the ring (module docstring).

    Returns its triangles ``(n − 2, 6)``, with the node of the k-th new edge
    written −1 − k, and those nodes' coordinates ``(n − 3, 2)``; None if
    there is none.
    """
    min_dist, max_length = bounds
    n = len(ring)
    best: tuple[float, NDArray, NDArray] | None = None
    for triangulation in polygon_triangulations(n):
        corners = np.array(triangulation)
        if (signed_areas(points, ring[corners]) <= 0).any():
            continue
        diagonals = sorted(
            {
                (min(p, q), max(p, q))
                for tri in triangulation
                for p, q in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[0], tri[2]))
                if (q - p) % n not in (1, n - 1)
            }
        )
        d = np.array(diagonals, dtype=np.int64).reshape(-1, 2)
        a, b = points[ring[d[:, 0]]], points[ring[d[:, 1]]]
        optimal = 0.5 * (a + b)
        if len(d):
            par = shortest_parabola(field, a, b, exact_length=False)
            if ((par.length < min_dist) | (par.length > max_length)).any():
                continue
            optimal = par.mid
        tri_ids = _triangle_nodes(triangulation, ring, ring_nodes, diagonals)
        new_node = tri_ids < 0
        nodes = points[np.where(new_node, 0, tri_ids)]  # (n − 2, 6, 2); new nodes set below
        for frac in BACKTRACK:
            mids = 0.5 * (a + b) + frac * (optimal - 0.5 * (a + b))
            nodes[new_node] = mids[-1 - tri_ids[new_node]]
            if not valid_exact(nodes).all():
                continue
            # edges 01, 12, 20 of each triangle through their nodes 3, 4, 5
            lens = parabola_length(
                field,
                nodes[:, [0, 1, 2]].reshape(-1, 2),
                nodes[:, [1, 2, 0]].reshape(-1, 2),
                nodes[:, 3:].reshape(-1, 2),
            ).reshape(-1, 3)
            new = lens[new_node[:, 3:]]
            if (new < min_dist).any() or (new > max_length).any():
                break
            q = float(quality_from(metric_areas(field, nodes), lens).min())
            if q > q_star and (best is None or q > best[0]):
                best = (q, tri_ids, mids)
            break
    return None if best is None else (best[1], best[2])
