"""Edge nodes bent for quality: the middle node of an edge of a poor triangle moved
off its parabola where that raises the worse quality (4) of the edge's two triangles.

The stages before leave each edge node on the edge's shortest parabola (paper
equation (3)), or between it and the straight midpoint where validity asked
for less (:mod:`curvimesh.recurve`): the shortest edges, not the best
triangles. The quality q = 4√3 A / (L₁² + L₂² + L₃²) of a triangle has its
metric area A in the numerator, and the node of an edge shared by triangles t
and u moves area between them: offset by δ along the chord's normal, it
sweeps area from one to the other to first order in δ, while the edge's
length, stationary at its shortest parabola, grows to second order only.
Where t is poor and u has quality to spare, a small offset raises
min(q_t, q_u). Measured on the three toys at 3,801 vertices (all sizes over
1.54): the worst triangle, where the intersection switches from one ring's
metric to another's, has edges 1.058, 1.064, 1.029 and quality 0.797 after the
vertex shifts (:mod:`curvimesh.shift`, which move vertices, not nodes); its
third edge's node moved by 2 % of the chord makes both triangles 0.906, the
edge 1.029 → 1.046 long.

Each round takes the interior edges of the triangles of quality below
``improve_below`` (:data:`BEND_BELOW`) and tries their nodes at

    x_m′ = x_m + f (x₁ − x₀)×e₃,   f in ±:data:`OFFSETS`

(x_m the node now, x₀, x₁ the edge's ends). A position is admissible when

* both triangles of the edge are valid (Jacobian positive everywhere, decided
  exactly from its Bezier coefficients: :func:`curvimesh.bezier.valid_exact`);
* the edge's length stays in [min(``min_dist``, L), max(``max_length``, L)]
  (L its length now), so no edge leaves [0.7, 1.4] that was in it;
* the worse quality of the two triangles rises: min(q_t′, q_u′) > min(q_t, q_u),
  and neither ends below min(its quality now, ``improve_below``): the quality
  moved into a poor triangle comes from a neighbour's surplus above
  ``improve_below`` only (without that floor, on the box corners of
  ``metrics/constant_aniso.yaml``, which no bending can raise much, the moves
  cascaded from neighbour to neighbour: 1 % of the triangles fell below 0.40
  instead of 0.56).

Each edge takes its best admissible position (the highest worse quality, ties
to the first offset); the edges move together, greedily by their gain, no two
of one triangle (:func:`curvimesh.mesh.independent_flips`). An edge found
with no admissible position is tried again only when one of its triangles
has changed. Rounds repeat while an edge moves, at most ``max_rounds``. The
offsets of an edge are ranked by the loops' fixed rules, and the best
:data:`SCREEN` measured again, in that order, to the report's accuracy
(:data:`curvimesh.quality.REPORT_RTOL`) until one is admissible: the worst
triangles lie where the metric has kinks, which the fixed rules misjudge (see
:data:`curvimesh.quality.REMEASURE_MARGIN`), and there the adaptive measures
cost most (every offset measured so, bending took 87 of the 112 s of the swap
stage on an interpolation metric of 2,000 vertices whose metric costs 285 ns a
point; screened, 14 s, the same 114 nodes bent). Only nodes of interior edges move
(a boundary edge's node stays on its side); the worst quality of the mesh
never goes down and no edge leaves [0.7, 1.4].

Beyond the paper, and beyond its restriction of the node to the perpendicular
bisector (issue 7 asks for the node to be optimised beyond it);
:func:`curvimesh.adapt.swap` runs it last, after the vertex shifts and
removals (``--no-bend`` turns it off).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from curvimesh.bezier import valid_exact
from curvimesh.geodesic import parabola_length
from curvimesh.mesh import Mesh, independent_flips, local_edge
from curvimesh.metric import MetricField
from curvimesh.quality import (
    REMEASURE_MARGIN,
    REPORT_RTOL,
    edge_lengths,
    edge_lengths_fast,
    fixed_rule_measures,
    metric_areas,
    metric_areas_adaptive,
    quality_from,
)

#: Quality (4) below which a triangle's edges are bent: the vertex shifts' threshold
#: (:data:`curvimesh.shift.IMPROVE_BELOW`, a layer above this module's), so that the
#: two aim at the same figure.
BEND_BELOW = 0.8

#: Offsets f of a node along its chord's normal, as fractions of the chord, tried on
#: both sides. The one that mends the three toys' triangle of 0.797 is 0.02.
OFFSETS = (0.0025, 0.005, 0.01, 0.02, 0.04, 0.08)

#: How many of an edge's offsets, the best by the loops' fixed rules first, are measured
#: to the report's accuracy, until one is admissible.
SCREEN = 4


@dataclass(frozen=True)
class BendResult:
    """The mesh with its bent nodes, how many node moves and in how many rounds."""

    mesh: Mesh
    bent: int
    rounds: int


def bend_nodes(
    field: MetricField,
    mesh: Mesh,
    *,
    improve_below: float = BEND_BELOW,
    min_dist: float = 0.7,
    max_length: float = 1.4,
    max_rounds: int = 10,
    measured: tuple[NDArray, NDArray] | None = None,
) -> BendResult:
    """Bend the nodes of the interior edges of the triangles of quality below
    ``improve_below`` where that raises the worse quality of their two triangles
    (module docstring).

    ``mesh`` is a valid P2 mesh; the result has the same triangles and node
    numbering, and only nodes of interior edges move. Deterministic.
    ``measured``: the mesh's edge lengths and qualities by the loops' fixed rules
    (:func:`~curvimesh.quality.fixed_rule_measures`), where the caller has them
    (:func:`curvimesh.adapt.defects`); measured here otherwise.
    """
    if mesh.order != 2 or len(mesh.triangles) == 0:
        return BendResult(mesh, 0, 0)
    pts = np.array(mesh.points)
    tris = np.asarray(mesh.triangles)
    emid, et, tri_edges = mesh.edge_mid, mesh.edge_tris, mesh.tri_edges
    ruler = _Ruler(field, mesh, pts, measured)
    ruler.measure(np.flatnonzero(ruler.q < improve_below + REMEASURE_MARGIN))
    length, q = ruler.length, ruler.q
    changed = np.zeros(len(tris), dtype=np.int64)  # round of each triangle's last change
    failed = np.full(len(mesh.edges), -1, dtype=np.int64)  # round of each edge's last failed try
    bent = rounds = 0
    while rounds < max_rounds:
        rounds += 1
        poor = np.flatnonzero(q < improve_below)
        if poor.size == 0:
            break
        cand = np.unique(tri_edges[poor])
        cand = cand[et[cand, 1] >= 0]  # interior edges only
        t1, t2 = et[cand, 0], et[cand, 1]
        # a try that failed in round r saw the triangles before that round's moves
        fresh = (failed[cand] < 0) | (np.maximum(changed[t1], changed[t2]) >= failed[cand])
        cand, t1, t2 = cand[fresh], t1[fresh], t2[fresh]
        if cand.size == 0:
            break
        ruler.measure(np.concatenate([t1, t2]))
        floors = np.minimum(np.column_stack([q[t1], q[t2]]), improve_below)
        best, where, new_len = _best_offsets(
            field, mesh, pts, length, cand, floors, (min_dist, max_length)
        )
        worse = np.minimum(q[t1], q[t2])
        good = np.flatnonzero(best[:, 0] > worse)
        failed[cand[best[:, 0] <= worse]] = rounds
        if good.size == 0:
            break
        good = good[independent_flips(t1[good], t2[good], best[good, 0] - worse[good], len(tris))]
        e = cand[good]
        pts[emid[e]] = where[good]
        length[e] = new_len[good]
        q[t1[good]], q[t2[good]] = best[good, 1], best[good, 2]
        changed[t1[good]] = changed[t2[good]] = rounds
        bent += len(good)
    return BendResult(Mesh(pts, tris, mesh.box), bent, rounds)


class _Ruler:
    """Edge lengths and triangle qualities (4) of a mesh whose nodes ``pts`` move: by the
    loops' fixed rules (:func:`~curvimesh.quality.fixed_rule_measures`, remembered from
    the stages before) for
    the whole mesh, and to :data:`~curvimesh.quality.REPORT_RTOL` for the triangles
    :meth:`measure` is asked for and their edges (a few: the poor triangles and their
    neighbours), so that the whole mesh is not measured to the report's accuracy."""

    def __init__(
        self, field: MetricField, mesh: Mesh, pts: NDArray, measured: tuple | None = None
    ) -> None:
        self.field, self.mesh, self.pts = field, mesh, pts
        known = fixed_rule_measures(field, mesh) if measured is None else measured
        self.length, self.q = (np.array(v, dtype=float) for v in known)
        self.exact_edge = np.zeros(len(mesh.edges), dtype=bool)
        self.exact_tri = np.zeros(len(mesh.triangles), dtype=bool)

    def measure(self, tris: NDArray) -> None:
        """Lengths of the edges of triangles ``tris`` and their qualities to the report's
        accuracy (those not measured so: a moved node's are written by its mover)."""
        mesh, pts = self.mesh, self.pts
        tris = np.unique(tris)
        tris = tris[~self.exact_tri[tris]]
        if tris.size == 0:
            return
        e = np.unique(mesh.tri_edges[tris])
        e = e[~self.exact_edge[e]]
        if e.size:
            self.length[e] = edge_lengths(self.field, pts, mesh.edges[e], mesh.edge_mid[e])
            self.exact_edge[e] = True
        area = metric_areas_adaptive(self.field, pts[mesh.triangles[tris]])
        self.q[tris] = quality_from(area, self.length[mesh.tri_edges[tris]])
        self.exact_tri[tris] = True


def _best_offsets(
    field: MetricField,
    mesh: Mesh,
    pts: NDArray,
    length: NDArray,
    cand: NDArray,
    floors: NDArray,
    bounds: tuple[float, float],
) -> tuple[NDArray, NDArray, NDArray]:
    """For each interior edge ``cand`` ``(k,)`` of ``mesh`` (node positions ``pts``, edge
    lengths ``length``): its best admissible offset's worse quality and the two
    triangles' qualities ``(k, 3)`` (−inf where none is admissible), the node there
    ``(k, 2)`` and the edge's length ``(k,)``. An offset is admissible where both
    triangles are valid, neither ends below its floor ``floors`` ``(k, 2)``, and the
    edge's length stays within ``bounds`` (min_dist, max_length) or its own, measured
    to the report's accuracy; the valid offsets are measured so in the order of their
    worse quality by the fixed rules, at most :data:`SCREEN` of them, until one is
    admissible (the best of those measured is taken)."""
    tris, edges, emid, tri_edges = mesh.triangles, mesh.edges, mesh.edge_mid, mesh.tri_edges
    t1, t2 = mesh.edge_tris[cand, 0], mesh.edge_tris[cand, 1]
    k, n_off = len(cand), 2 * len(OFFSETS)
    x0, x1 = pts[edges[cand, 0]], pts[edges[cand, 1]]
    chord = x1 - x0
    normal = np.column_stack([chord[:, 1], -chord[:, 0]])  # (x₁ − x₀)×e₃
    f = np.concatenate([OFFSETS, -np.asarray(OFFSETS)])
    node = (pts[emid[cand]][:, None, :] + f[None, :, None] * normal[:, None, :]).reshape(-1, 2)
    rows = np.repeat(np.arange(k), n_off)
    # slot of the edge in each triangle: 3 + its local index
    s1, s2 = local_edge(tri_edges, t1, cand)[rows], local_edge(tri_edges, t2, cand)[rows]
    n1, n2 = pts[tris[t1[rows]]], pts[tris[t2[rows]]]  # (k n_off, 6, 2)
    r = np.arange(len(rows))
    n1[r, 3 + s1], n2[r, 3 + s2] = node, node
    scores = np.full((len(rows), 3), -np.inf)
    new_len = np.full(len(rows), np.nan)
    live = np.flatnonzero(valid_exact(n1) & valid_exact(n2))
    # the loops' fixed rules rank each edge's valid offsets, best worse quality first
    fixed = np.full(len(rows), -np.inf)
    if live.size:
        ln = edge_lengths_fast(field, x0[rows[live]], x1[rows[live]], node[live], remember=False)
        q1, q2 = _pair_qualities(
            field, mesh, length, (t1, t2), (s1, s2), (n1, n2), rows, live, ln, fixed_rule=True
        )
        fixed[live] = np.minimum(q1, q2)
    rank = np.argsort(-fixed.reshape(k, n_off), axis=1, kind="stable")
    rank += n_off * np.arange(k)[:, None]  # rows of the tries
    todo = np.arange(k)
    for r in range(min(SCREEN, n_off)):
        live = rank[todo, r]
        live = live[np.isfinite(fixed[live])]
        if live.size == 0:
            break
        # measured again to the report's accuracy; the first admissible one is kept
        ln = parabola_length(field, x0[rows[live]], x1[rows[live]], node[live], rtol=REPORT_RTOL)
        old = length[cand[rows[live]]]
        inside = (ln >= np.minimum(bounds[0], old)) & (ln <= np.maximum(bounds[1], old))
        live, ln = live[inside], ln[inside]
        if live.size:
            q1, q2 = _pair_qualities(
                field, mesh, length, (t1, t2), (s1, s2), (n1, n2), rows, live, ln, fixed_rule=False
            )
            keep = (q1 >= floors[rows[live], 0]) & (q2 >= floors[rows[live], 1])
            live = live[keep]
            new_len[live] = ln[keep]
            scores[live] = np.column_stack([np.minimum(q1, q2), q1, q2])[keep]
        todo = np.setdiff1d(todo, rows[live], assume_unique=True)
    scores = scores.reshape(k, n_off, 3)
    pick = np.argmax(scores[:, :, 0], axis=1)  # the first of the best
    kk = np.arange(k)
    return (
        scores[kk, pick],
        node.reshape(k, n_off, 2)[kk, pick],
        new_len.reshape(k, n_off)[kk, pick],
    )


def _pair_qualities(
    field: MetricField,
    mesh: Mesh,
    length: NDArray,
    tri: tuple[NDArray, NDArray],
    slot: tuple[NDArray, NDArray],
    nodes: tuple[NDArray, NDArray],
    rows: NDArray,
    live: NDArray,
    ln: NDArray,
    *,
    fixed_rule: bool,
) -> tuple[NDArray, NDArray]:
    """The qualities ``(r,)`` of the two triangles of the tries ``live`` of
    :func:`_best_offsets` (their edge ``ln`` long, their other edges ``length``): the
    metric areas by the loops' fixed rule, or (not ``fixed_rule``) to the report's accuracy."""
    lens = []
    j = np.arange(len(live))
    for t, s in zip(tri, slot, strict=True):
        lt = length[mesh.tri_edges[t[rows[live]]]]
        lt[j, s[live]] = ln
        lens.append(lt)
    both = np.concatenate([nodes[0][live], nodes[1][live]])
    if fixed_rule:
        area = metric_areas(field, both, remember=False)
    else:
        area = metric_areas_adaptive(field, both, rtol=REPORT_RTOL)
    return quality_from(area[: len(live)], lens[0]), quality_from(area[len(live) :], lens[1])


__all__ = ["BEND_BELOW", "OFFSETS", "BendResult", "bend_nodes"]
