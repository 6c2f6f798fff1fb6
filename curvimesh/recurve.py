"""Re-curving: edge nodes moved back towards their shortest parabolas.

Curving (:mod:`curvimesh.curve`) and the swaps (:mod:`curvimesh.swap`) put
the node of an interior edge e = (x₀, x₁) on its shortest parabola (paper
equation (3)), x_m* = (x₀+x₁)/2 + α* (x₁−x₀)×e₃, unless a triangle of e came
out invalid: the node was then moved back towards the straight midpoint,
x_m = x_s + s (x_m* − x_s) with x_s = (x₀+x₁)/2 and s < 1 (paper section 6,
"a backtracking step is applied"), down to s = 0, a straight edge. The
backtracking is decided once, in the neighbourhood e had then; after the
swaps, insertions and splits changed that neighbourhood, the optimal node
is often valid again. A straight edge across a curved metric is longer
than its parabola (by 10 % to 100 % on the sharp fronts), so the edges left
straight are the longest of the mesh.

Here every interior edge whose node is not its optimal one is tried again
at the fractions :data:`FRACTIONS` of the optimal offset,
x_m(s) = x_s + s (x_m* − x_s), and moved to the largest fraction s for which

* both triangles of e are valid (Jacobian positive everywhere, decided
  exactly from its Bezier coefficients, Johnen et al. 2013);
* e gets shorter in the metric, L(s) < L (the length of the parabola
  through x₀, x_m(s), x₁, ∫₀¹ sqrt(ẋᵀ g(x) ẋ) dt, SPEC section 4), so no
  edge is ever made longer, but not shorter than min(``min_length``, L), so
  no edge is made short either (a straightened edge of 0.75 next to an
  inserted vertex came out 0.585 on its parabola: quartic2, seed 2);
* the worse quality (4) of the two triangles does not fall below
  min(q_old, q_floor): min(q₁', q₂') ≥ min(min(q₁, q₂), q_floor), where
  q_floor = max(``min_quality``, the worst quality of the mesh), so that the
  worst quality of the mesh never goes down.

Only e's node moves, so the other edges of its triangles keep their nodes
and lengths. The moves are made in rounds: every candidate is evaluated at
once, the accepted ones are taken greedily by decreasing length gain so
that no two touch the same triangle (two edges of one triangle were each
checked with the other's old node), and they are applied together. An edge
moved to s < 1, or refused, is tried again in the next round only when one
of its triangles changed; rounds stop when nothing moves.

Beyond the paper; :func:`curvimesh.adapt.swap` runs it after the insertions
and splits, alternating with the last swaps (``--no-recurve`` turns it off).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from curvimesh.bezier import valid_exact
from curvimesh.freenode import free_node, shortest_parabola
from curvimesh.geodesic import parabola_length
from curvimesh.mesh import Mesh, independent_flips, local_edge
from curvimesh.metric import MetricField
from curvimesh.quality import edge_lengths_fast, metric_areas, quality_from

#: Fractions s of the optimal offset tried for an edge node, largest first.
FRACTIONS = (1.0, 0.75, 0.5, 0.375, 0.25, 0.125)

#: Relative length accuracy of the shortening test (adaptive Gauss–Legendre).
LENGTH_RTOL = 1e-7


def optimal_nodes(field: MetricField, x0: NDArray, x1: NDArray, *, free_from: float) -> NDArray:
    """The node ``(n, 2)`` each edge moves towards: its shortest parabola's (paper
    equation (3), :func:`curvimesh.freenode.shortest_parabola`), or, where that is
    longer than ``free_from``, the node of the shortest parabola with the node free
    in the plane (:func:`curvimesh.freenode.free_node`) when that is shorter.

    The paper's node is on the chord's perpendicular bisector: the parabola is
    symmetric about it. Along a thin layer whose curvature changes (towards the
    inflection of the 1,000:1 cubic of bench/robustness u74, radius of curvature
    0.6, long size 0.08) the curve a row's edge should follow is not symmetric:
    two edges whose symmetric parabolas are 1.57 and 1.52 long are 1.28 and 1.24
    with free nodes. :mod:`curvimesh.freenode` frees nodes only where the metric's
    frame turns fast, and u74's turns 8° per unit length there.
    """
    par = shortest_parabola(field, x0, x1, exact_length=False)
    out = par.mid.copy()
    long = np.flatnonzero(par.length > free_from)
    if long.size:
        mid, length = free_node(field, x0[long], x1[long], par.alpha[long])
        shorter = length < par.length[long]
        out[long[shorter]] = mid[shorter]
    return out


@dataclass(frozen=True)
class RecurveResult:
    """The re-curved mesh, how many edge nodes moved and in how many rounds."""

    mesh: Mesh
    moved: int
    rounds: int


def recurve(
    field: MetricField,
    mesh: Mesh,
    *,
    min_quality: float = 0.3,
    min_length: float = 0.7,
    max_rounds: int = 20,
    area_order: int = 4,
    longer_than: float = 0.0,
    free_from: float = math.inf,
    from_node: bool = False,
) -> RecurveResult:
    """Move interior edge nodes towards their shortest parabolas (module docstring).

    ``mesh`` is a valid P2 mesh; the result has the same node numbering and
    triangles, and only edge nodes of interior edges (held by two triangles)
    move. Edges on the boundary keep their nodes. Deterministic.

    Only the edges longer than ``longer_than`` (by the two-segment rule) are
    tried; those whose shortest parabola is longer than ``free_from`` move towards
    the shortest one with a free node where that is shorter (:func:`optimal_nodes`).
    With ``from_node`` the fractions are taken of the way from the edge's current
    node to that node, x_m(s) = x_m + s (x_m* − x_m), instead of from the chord's
    middle: a node that is valid where it is can then go part of the way.
    """
    pts = np.array(mesh.points)
    tris = np.asarray(mesh.triangles)
    edges, emid, et, tri_edges = mesh.edges, mesh.edge_mid, mesh.edge_tris, mesh.tri_edges
    cand = np.flatnonzero(et[:, 1] >= 0)
    if cand.size == 0 or mesh.order != 2:
        return RecurveResult(mesh, 0, 0)
    length = edge_lengths_fast(field, pts[edges[:, 0]], pts[edges[:, 1]], pts[emid])
    cand = cand[length[cand] > longer_than]
    x0, x1 = pts[edges[cand, 0]], pts[edges[cand, 1]]
    opt = optimal_nodes(field, x0, x1, free_from=free_from)
    seg = pts[emid[cand]] if from_node else 0.5 * (x0 + x1)
    # already at the optimum (to rounding): nothing to gain
    scale = np.hypot(*(x1 - x0).T)
    away = np.hypot(*(pts[emid[cand]] - opt).T) > 1e-9 * scale
    cand, x0, x1, opt, seg = (v[away] for v in (cand, x0, x1, opt, seg))
    if cand.size == 0:
        return RecurveResult(mesh, 0, 0)
    cur_len = parabola_length(field, x0, x1, pts[emid[cand]], rtol=LENGTH_RTOL)
    t1, t2 = et[cand, 0], et[cand, 1]
    # slot of the edge's node in each triangle: 3 + local edge index
    s1, s2 = 3 + local_edge(tri_edges, t1, cand), 3 + local_edge(tri_edges, t2, cand)
    active = np.ones(len(cand), dtype=bool)  # worth a try in this round
    done = np.zeros(len(cand), dtype=bool)  # at the optimum
    moved = rounds = 0
    q = quality_from(metric_areas(field, pts[tris], order=area_order), length[tri_edges])
    while rounds < max_rounds and active.any():
        idx = np.flatnonzero(active)
        n1, n2 = pts[tris[t1[idx]]], pts[tris[t2[idx]]]  # (k, 6, 2)
        floor = np.minimum(np.minimum(q[t1[idx]], q[t2[idx]]), max(min_quality, float(q.min())))
        found = np.zeros(len(idx), dtype=bool)
        new_mid = np.zeros((len(idx), 2))
        new_len = np.zeros(len(idx))
        new_s = np.zeros(len(idx))
        for s in FRACTIONS:
            todo = np.flatnonzero(~found)
            if todo.size == 0:
                break
            k = idx[todo]
            m = seg[k] + s * (opt[k] - seg[k])
            a1, a2 = n1[todo].copy(), n2[todo].copy()
            r = np.arange(len(todo))
            a1[r, s1[k]] = m
            a2[r, s2[k]] = m
            ok = valid_exact(a1) & valid_exact(a2)
            if not ok.any():
                continue
            todo, k, m, a1, a2 = (v[ok] for v in (todo, k, m, a1, a2))
            ln = parabola_length(field, x0[k], x1[k], m, rtol=LENGTH_RTOL)
            shorter = (ln < cur_len[k]) & (ln >= np.minimum(min_length, cur_len[k]))
            l1 = length[tri_edges[t1[k]]].copy()
            l2 = length[tri_edges[t2[k]]].copy()
            fast = edge_lengths_fast(field, x0[k], x1[k], m)
            l1[np.arange(len(k)), s1[k] - 3] = fast
            l2[np.arange(len(k)), s2[k] - 3] = fast
            q_new = np.minimum(
                quality_from(metric_areas(field, a1, order=area_order), l1),
                quality_from(metric_areas(field, a2, order=area_order), l2),
            )
            take = shorter & (q_new >= floor[todo])
            found[todo[take]] = True
            new_mid[todo[take]] = m[take]
            new_len[todo[take]] = ln[take]
            new_s[todo[take]] = s
        active[idx[~found]] = False
        good = np.flatnonzero(found)
        if good.size == 0:
            break
        gain = cur_len[idx[good]] - new_len[good]
        good = good[independent_flips(t1[idx[good]], t2[idx[good]], gain, len(tris))]
        ch = idx[good]
        pts[emid[cand[ch]]] = new_mid[good]
        cur_len[ch] = new_len[good]
        length[cand[ch]] = edge_lengths_fast(field, x0[ch], x1[ch], new_mid[good])
        # the edges of changed triangles are worth another try (unless at the optimum)
        changed = np.zeros(len(tris), dtype=bool)
        changed[t1[ch]] = changed[t2[ch]] = True
        # only their qualities change (a move keeps the other edges' nodes)
        tc = np.flatnonzero(changed)
        areas = metric_areas(field, pts[tris[tc]], order=area_order)
        q[tc] = quality_from(areas, length[tri_edges[tc]])
        done[ch] = new_s[good] == FRACTIONS[0]
        active = (active | changed[t1] | changed[t2]) & ~done
        moved += len(ch)
        rounds += 1
    return RecurveResult(Mesh(pts, tris, mesh.box), moved, rounds)


__all__ = ["FRACTIONS", "RecurveResult", "optimal_nodes", "recurve"]
