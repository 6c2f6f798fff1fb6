"""Curvilinear edge splits: long curved edges cut at their middle node.

An edge longer than ``max_length`` is split at its P2 node, which becomes a
vertex; the two halves of the parabola are parabolas themselves (the
restrictions of x(t) to [0, ½] and [½, 1], whose middle nodes are x(¼) and
x(¾)), so the split keeps the curve exactly. The vertex is joined to the
opposite corners by new edges on their shortest parabolas (paper eq. (3)),
backtracked towards the straight midpoint for validity::

            c                        c
          /   \\                   / | \\
        /  t1   \\               / T1 | T1' \\
       a ---m--- b     ──►     a --- v --- b        v = the old node m
        \\  t2   /               \\ T2'| T2 /
          \\   /                   \\ | /
            d                        d

A split is made when every new triangle is valid (exactly), no new edge is
shorter than ``min_dist`` (so a split never makes a short edge), and the
worse quality of the new triangles is at least ``min_quality``. Splits are
made in rounds of edges that share no triangle, longest first. A boundary
edge (one triangle) splits the same way on its side.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from curvimesh.bezier import valid_exact
from curvimesh.freenode import shortest_parabola
from curvimesh.geodesic import parabola_points
from curvimesh.mesh import Mesh, independent_flips, local_edge, rotate_triangles
from curvimesh.metric import MetricField
from curvimesh.quality import (
    COUNT_RTOL,
    edge_lengths,
    edge_lengths_fast,
    metric_areas,
    quality_from,
)
from curvimesh.sampling import close_to_index, search_regions
from curvimesh.spatial import PointIndex

#: Fractions of the optimal offset tried for a new edge's node, in order.
BACKTRACK = (1.0, 0.5, 0.25, 0.0)


@dataclass(frozen=True)
class SplitResult:
    """The mesh after splitting and how many edges were split."""

    mesh: Mesh
    splits: int


def split_long_edges(
    field: MetricField,
    mesh: Mesh,
    *,
    max_length: float = 1.4,
    min_dist: float = 0.7,
    min_quality: float = 0.3,
    rounds: int = 4,
) -> SplitResult:
    """Split the edges longer than ``max_length`` where allowed (module docstring)."""
    total = 0
    for _ in range(rounds):
        mesh, n = _split_round(field, mesh, max_length, min_dist, min_quality)
        total += n
        if n == 0:
            break
    return SplitResult(mesh, total)


def _split_round(
    field: MetricField, mesh: Mesh, max_length: float, min_dist: float, min_quality: float
) -> tuple[Mesh, int]:
    pts = np.asarray(mesh.points)
    tris = np.asarray(mesh.triangles)
    edges, mids = mesh.edges, mesh.edge_mid
    length = edge_lengths(field, pts, edges, mids, rtol=COUNT_RTOL)
    cand = np.flatnonzero(length > max_length)
    if cand.size == 0:
        return mesh, 0
    et = mesh.edge_tris[cand]
    t1, t2 = et[:, 0], et[:, 1]
    has2 = t2 >= 0
    k1 = local_edge(mesh.tri_edges, t1, cand)
    r1 = rotate_triangles(tris[t1], k1)  # (a, b, c, n_ab, n_bc, n_ca)
    a, b, c = r1[:, 0], r1[:, 1], r1[:, 2]
    v = r1[:, 3]  # the edge's node becomes the vertex
    d = np.full(len(cand), -1)
    r2 = np.zeros_like(r1)
    if has2.any():
        k2 = local_edge(mesh.tri_edges, t2[has2], cand[has2])
        r2[has2] = rotate_triangles(tris[t2[has2]], k2)  # (b, a, d, n_ab, n_ad, n_db)
        d[has2] = r2[has2, 2]
    # halves of the split parabola: nodes x(1/4) (a side) and x(3/4) (b side)
    quarter, _ = parabola_points(pts[a], pts[b], pts[v], np.array([0.25, 0.75]))
    # new edges v-c and v-d
    new_nodes = []
    lengths_new = []
    ok = np.ones(len(cand), dtype=bool)
    for opp, mask in ((c, np.ones(len(cand), bool)), (d, has2)):
        node = np.zeros((len(cand), 2))
        ln = np.full(len(cand), np.inf)
        idx = np.flatnonzero(mask)
        if idx.size:
            par = shortest_parabola(field, pts[v[idx]], pts[opp[idx]], exact_length=False)
            node[idx] = par.mid
            ln[idx] = par.length
        new_nodes.append(node)
        lengths_new.append(ln)
        ok &= ~mask | (ln >= min_dist)

    # candidate triangles, as node coordinates, for a given offset scale of the new edges
    def patch(scale_c: NDArray, scale_d: NDArray):
        mc = 0.5 * (pts[v] + pts[c]) + scale_c[:, None] * (new_nodes[0] - 0.5 * (pts[v] + pts[c]))
        dd = np.where(has2, d, c)
        md = 0.5 * (pts[v] + pts[dd]) + scale_d[:, None] * (new_nodes[1] - 0.5 * (pts[v] + pts[dd]))
        q1, q2 = quarter[:, 0], quarter[:, 1]
        T1 = np.stack([pts[a], pts[v], pts[c], q1, mc, pts[r1[:, 5]]], axis=1)
        T1b = np.stack([pts[v], pts[b], pts[c], q2, pts[r1[:, 4]], mc], axis=1)
        T2 = np.stack([pts[b], pts[v], pts[dd], q2, md, pts[r2[:, 5]]], axis=1)
        T2b = np.stack([pts[v], pts[a], pts[dd], q1, pts[r2[:, 4]], md], axis=1)
        return mc, md, T1, T1b, T2, T2b

    level = np.full(len(cand), -1)
    chosen_c = np.zeros(len(cand))
    chosen_d = np.zeros(len(cand))
    for li, s in enumerate(BACKTRACK):
        todo = np.flatnonzero((level < 0) & ok)
        if todo.size == 0:
            break
        sc = np.full(len(cand), s)
        _, _, T1, T1b, T2, T2b = patch(sc, sc)
        valid = valid_exact(T1[todo]) & valid_exact(T1b[todo])
        valid &= ~has2[todo] | (valid_exact(T2[todo]) & valid_exact(T2b[todo]))
        got = todo[valid]
        level[got] = li
        chosen_c[got] = s
        chosen_d[got] = s
    good = np.flatnonzero(level >= 0)
    if good.size == 0:
        return mesh, 0
    mc, md, T1, T1b, T2, T2b = patch(chosen_c, chosen_d)
    # quality of the new triangles, and their new edges' lengths
    l_vc = edge_lengths_fast(field, pts[v], pts[c], mc)
    dd = np.where(has2, d, c)
    l_vd = edge_lengths_fast(field, pts[v], pts[dd], md)
    # the node at t = 1/2 need not halve the metric length: measure both halves
    qa_, qb_ = quarter[:, 0], quarter[:, 1]
    half_a = edge_lengths_fast(field, pts[a], pts[v], qa_)
    half_b = edge_lengths_fast(field, pts[v], pts[b], qb_)
    lens = {
        "bc": edge_lengths_fast(field, pts[b], pts[c], pts[r1[:, 4]]),
        "ca": edge_lengths_fast(field, pts[c], pts[a], pts[r1[:, 5]]),
    }
    q = [
        quality_from(metric_areas(field, T1), np.column_stack([half_a, l_vc, lens["ca"]])),
        quality_from(metric_areas(field, T1b), np.column_stack([half_b, lens["bc"], l_vc])),
    ]
    if has2.any():
        l_ad = edge_lengths_fast(field, pts[a], pts[dd], pts[r2[:, 4]])
        l_db = edge_lengths_fast(field, pts[dd], pts[b], pts[r2[:, 5]])
        q2a = quality_from(metric_areas(field, T2), np.column_stack([half_b, l_vd, l_db]))
        q2b = quality_from(metric_areas(field, T2b), np.column_stack([half_a, l_ad, l_vd]))
        q.append(np.where(has2, q2a, np.inf))
        q.append(np.where(has2, q2b, np.inf))
    qmin = np.min(q, axis=0)
    good = good[
        (qmin[good] >= min_quality)
        & (l_vc[good] >= min_dist)
        & (~has2[good] | (l_vd[good] >= min_dist))
        & (half_a[good] >= min_dist)
        & (half_b[good] >= min_dist)
    ]
    # the new vertex must be min_dist from every vertex (not only its neighbours),
    # or a later swap could join them by a short edge
    if good.size:
        corners = np.unique(tris[:, :3])
        index = PointIndex()
        index.add(pts[corners])
        vp = pts[v[good]]
        own = np.searchsorted(corners, v[good])  # the vertex's own index id
        regions = search_regions(field, vp, 2.0 * min_dist)
        good = good[~close_to_index(field, index, vp, regions, min_dist, exclude=own)]
    if good.size == 0:
        return mesh, 0
    # non-conflicting, longest first
    t2x = np.where(has2, t2, t1)
    sel = good[independent_flips(t1[good], t2x[good], length[cand][good], len(tris))]
    # assemble: new nodes appended (q1, q2, mc, md per split)
    new_pts = [pts]
    base = len(pts)
    k = len(sel)
    q1_id = base + np.arange(k)
    q2_id = base + k + np.arange(k)
    mc_id = base + 2 * k + np.arange(k)
    md_id = base + 3 * k + np.arange(k)
    new_pts += [quarter[sel, 0], quarter[sel, 1], mc[sel], md[sel]]
    out = np.array(tris)
    s1 = sel
    out[t1[s1]] = np.column_stack([a[s1], v[s1], c[s1], q1_id, mc_id, r1[s1, 5]])
    add = [np.column_stack([v[s1], b[s1], c[s1], q2_id, r1[s1, 4], mc_id])]
    two = has2[s1]
    s2 = s1[two]
    out[t2[s2]] = np.column_stack([b[s2], v[s2], d[s2], q2_id[two], md_id[two], r2[s2, 5]])
    add.append(np.column_stack([v[s2], a[s2], d[s2], q1_id[two], r2[s2, 4], md_id[two]]))
    tris_new = np.concatenate([out, *add])
    pts_new = np.concatenate(new_pts)
    # drop the unused md nodes of boundary splits by renumbering the used nodes
    used = np.zeros(len(pts_new), dtype=bool)
    used[tris_new.ravel()] = True
    renum = np.cumsum(used) - 1
    return Mesh(pts_new[used], renum[tris_new], mesh.box), int(k)
