"""Curvilinear edge swaps driven by the quality of equation (4) (paper section 4).

An interior edge e = (a, b) shared by t₁ = (a, b, c) and t₂ = (b, a, d) is
replaced by e' = (c, d), its middle node on the shortest parabola between c
and d (moved back towards the straight midpoint if needed for validity)::

            c                      c
          / | \\                  /   \\
        /   |   \\              /  t₁'  \\
       a  t₁|t₂  b    ──►     a ------- b        t₁' = (a, d, c)
        \\   |   /              \\  t₂'  /        t₂' = (d, b, c)
          \\ | /                  \\   /
            d                      d
     (e = a-b drawn vertical)   (e' = c-d)

The swap is made when both new triangles are valid (Jacobian positive
everywhere, decided exactly from its Bezier coefficients) and it raises the
worse quality of the pair: min(q(t₁'), q(t₂')) > min(q(t₁), q(t₂)). Beyond
the paper, it is refused when the new edge would be shorter than
min(0.7, L_ab): quality (4) alone can prefer a short diagonal (a 0.65 edge in
the 1000-vertex three-toys mesh of the benchmark).

With the rule for lengths (beyond the paper), the edge lengths count too.
With q = min(q(t₁), q(t₂)) and q' = min(q(t₁'), q(t₂')), the floor
F = max(0.3, worst quality of the mesh), and β(L) = max(0, L/1.4 − 1,
0.7/L − 1) how far a length is out of [0.7, 1.4], the swap is made when

1. min(q', F) > min(q, F): a pair worse than the floor gets better; or
2. min(q', F) ≥ min(q, F) and β(L_cd) < β(L_ab): the new edge is nearer
   the range, and the pair stays above min(q, F); or
3. min(q', F) ≥ min(q, F), β(L_cd) ≤ β(L_ab) and q' > q: the quality
   rule, unless it puts the new edge farther out of the range.

Cases are taken in this order of priority. The worst quality of the mesh
never goes down (it is ≤ F and no pair falls below min(q, F)). No swap is
undone by the next: undoing a case 2 or 3 swap would need min(q, F) >
min(q', F) (case 1) or the old edge no farther out of the range than the
new one with a better pair (cases 2, 3), against what the swap required;
``max_rounds`` guards against longer cycles.

Swaps are made in rounds: every candidate is evaluated at once, the
improving ones are taken greedily by decreasing gain so that no two touch
the same triangle, and they are applied together. A candidate's outcome
depends only on its two triangles (their corners, and the nodes of their
edges, which stay while the triangles do), so a rejected one is remembered,
by the ids of its triangles, until one of them is flipped (a flip rewrites
its triangles in place), and not evaluated again meanwhile. Rounds stop
when nothing improves (or after ``max_rounds``, a guard against cycles).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from curvimesh.bezier import valid_exact
from curvimesh.curve import assemble_p2
from curvimesh.freenode import shortest_parabola
from curvimesh.geodesic import chord_lower_bound, lens_lower_bound
from curvimesh.mesh import (
    EdgeStore,
    Mesh,
    apply_flips,
    flip_candidates,
    independent_flips,
    local_edge,
    p1_edges,
    p1_of,
    sorted_member,
    sorted_union,
)
from curvimesh.metric import MetricField
from curvimesh.quality import edge_lengths_fast, metric_areas, quality_from

#: Fractions of the optimal offset tried for a new edge's node, in order.
BACKTRACK = (1.0, 0.5, 0.25, 0.125, 0.0)


@dataclass(frozen=True)
class SwapResult:
    """The swapped P2 mesh, how many swaps were made and in how many rounds."""

    mesh: Mesh
    swaps: int
    rounds: int


def _nodes(pts: NDArray, tri: NDArray, mids: NDArray) -> NDArray:
    """Nodes ``(k, 6, 2)`` from corners ``(k, 3)`` and edge nodes ``(k, 3, 2)``."""
    return np.concatenate([pts[tri], mids], axis=1)


def out_of_range(length: NDArray, length_range: tuple[float, float]) -> NDArray:
    """How far lengths ``(k,)`` are out of [lo, hi], relatively: max(0, L/hi − 1, lo/L − 1).

    >>> out_of_range(np.array([0.35, 1.0, 2.8]), (0.7, 1.4)).tolist()
    [1.0, 0.0, 1.0]
    """
    lo, hi = length_range
    with np.errstate(divide="ignore"):
        return np.maximum(0.0, np.maximum(length / hi - 1.0, lo / length - 1.0))


def length_rule_gain(
    q_old: NDArray,
    q_new: NDArray,
    l_old: NDArray,
    l_new: NDArray,
    *,
    floor: float,
    length_range: tuple[float, float] = (0.7, 1.4),
    min_gain: float = 1e-6,
) -> NDArray:
    """Priorities ``(k,)`` of swaps under the rule for lengths (module docstring).

    ``q_old``, ``q_new``: the worse quality of the pair before and after;
    ``l_old``, ``l_new``: the lengths of the old and the new edge. A swap is
    taken when its priority exceeds ``min_gain``: 20 + the gain of the pair's
    quality clipped at ``floor`` (case 1), 10 + the gain of :func:`out_of_range`
    (case 2), the gain of quality (case 3), −inf otherwise.

    >>> length_rule_gain(np.array([0.8, 0.8, 0.2]), np.array([0.5, 0.9, 0.25]),
    ...                  np.array([1.5, 1.5, 1.0]), np.array([1.0, 1.6, 1.0]), floor=0.3)
    array([10.07142857,        -inf, 20.05      ])
    """
    f_old, f_new = np.minimum(q_old, floor), np.minimum(q_new, floor)
    b_old, b_new = out_of_range(l_old, length_range), out_of_range(l_new, length_range)
    kept = f_new >= f_old
    gain = np.full(len(q_old), -np.inf)
    up = f_new - f_old > min_gain
    gain[up] = 20.0 + (f_new - f_old)[up]
    nearer = ~up & kept & (b_old - b_new > min_gain)
    gain[nearer] = 10.0 + np.minimum(b_old - b_new, 5.0)[nearer]
    rest = ~up & ~nearer & kept & (b_new <= b_old)
    gain[rest] = (q_new - q_old)[rest]
    return gain


#: Margins of :func:`quality_bound`: the quadrature's metric areas are not exactly
#: additive, the new edge's Gauss-rule length may fall below its chord bound (itself
#: sampled at probes), by far less than these.
AREA_MARGIN, LENGTH_MARGIN = 1.05, 1.1


def without_hope(
    bound: NDArray,
    q_old: NDArray,
    floor: float | None,
    in_range: NDArray | None,
    min_gain: float,
) -> NDArray[np.bool_]:
    """Candidates ``(k,)`` that no new edge can make worth swapping, given an upper
    bound ``bound`` of the new pair's worse quality (:func:`quality_bound`) and the
    old pair's ``q_old``: by the quality rule, those whose bound is at most ``q_old +
    min_gain``; by the rule for lengths (``floor`` and ``in_range``, whether the old
    edge is in the range, given), every case keeps the pair's quality clipped at the
    floor, and with the old edge in the range (no case 2) a pair that cannot gain
    quality has neither case 1 nor case 3."""
    if floor is None:
        return bound <= q_old + min_gain
    return (np.minimum(bound, floor) < np.minimum(q_old, floor)) | (
        in_range & (bound <= q_old + min_gain)
    )


def quality_bound(area: NDArray, outer: NDArray, lower: NDArray) -> NDArray:
    """An upper bound ``(k,)`` of the worse quality (4) of the two triangles a swap makes.

    The two new triangles cover the quad of the two old ones, so their metric
    areas add up to the old ones' ``area``; ``outer`` is the sum of the squared
    lengths of the quad's four sides and ``lower`` a lower bound of the new
    edge's length (:func:`curvimesh.geodesic.chord_lower_bound` or
    :func:`~curvimesh.geodesic.lens_lower_bound`). By the mediant inequality,
    min(A₁/D₁, A₂/D₂) ≤ (A₁ + A₂)/(D₁ + D₂), with Dᵢ the sums of squared
    lengths, D₁ + D₂ = outer + 2 L_cd²:

        min(q₁', q₂') ≤ 4√3 · AREA_MARGIN · area / (outer + 2 (lower / LENGTH_MARGIN)²).

    NaN bounds (a metric undefined on the way) are +inf: they decide nothing.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        low = lower / LENGTH_MARGIN
        bound = 4.0 * math.sqrt(3.0) * AREA_MARGIN * area / (outer + 2.0 * low * low)
    return np.where(np.isnan(bound), np.inf, bound)


def swap(
    field: MetricField,
    mesh: Mesh,
    *,
    max_rounds: int = 200,
    min_gain: float = 1e-6,
    area_order: int = 4,
    straight: bool = False,
    length_rule: bool = False,
    min_quality: float = 0.3,
    length_range: tuple[float, float] = (0.7, 1.4),
    min_length: float = 0.7,
) -> SwapResult:
    """Curvilinear edge swaps until no swap improves (see the module docstring).

    ``mesh`` is a valid P2 mesh; its edge nodes are kept for the edges that
    stay. Returns a valid P2 mesh on the same corners. With ``straight`` the
    new edges are straight (the classical swap of a straight-sided mesh).
    With ``length_rule``, swaps are decided by :func:`length_rule_gain`, with
    ``length_range`` and the floor max(``min_quality``, worst quality of the mesh).
    No swap makes an edge shorter than min(``min_length``, the edge it replaces).
    """
    p1 = p1_of(mesh)
    pts = np.asarray(p1.points)
    n = len(pts)
    store = EdgeStore(n)
    if mesh.order == 2:
        # edge nodes of the input: edge k of p1 has the node of the same edge in mesh
        e = p1_edges(mesh)
        mids = mesh.points[mesh.edge_mid]
    else:
        e = p1.edges
        mids = 0.5 * (pts[e[:, 0]] + pts[e[:, 1]])
    store.add(
        store.key(e[:, 0], e[:, 1]),
        mids,
        edge_lengths_fast(field, pts[e[:, 0]], pts[e[:, 1]], mids),
    )
    tris = np.array(p1.corners)
    optimal = EdgeStore(n)  # optimal nodes of candidate new edges
    m = len(tris)
    rejected = np.zeros(0, dtype=np.int64)  # t1 * m + t2 of rejected candidates, ascending
    swaps = rounds = 0
    q = area = flipped = None
    while rounds < max_rounds:
        cur = Mesh(pts, tris, p1.box)
        edges, tri_edges = cur.edges, cur.tri_edges
        pos, found = store.find(store.key(edges[:, 0], edges[:, 1]))
        assert found.all()
        emid, elen = store.mid[pos], store.length[pos]
        # qualities: all at the first round, then only of the triangles just flipped
        # (a triangle's quality depends on its own nodes and edge lengths alone)
        redo = np.arange(len(tris)) if q is None else flipped
        if q is None:
            q, area = np.empty(len(tris)), np.empty(len(tris))
        area[redo] = metric_areas(
            field, _nodes(pts, tris[redo], emid[tri_edges[redo]]), order=area_order
        )
        q[redo] = quality_from(area[redo], elen[tri_edges[redo]])
        e_ab, t1, t2, a, b, c, d = flip_candidates(cur)
        qk = t1 * m + t2
        fresh = ~sorted_member(rejected, qk)
        e_ab, a, b, c, d, t1, t2, qk = (v[fresh] for v in (e_ab, a, b, c, d, t1, t2, qk))
        if len(a) == 0:
            break
        # the quad's outer edges (rows of edges): t1 = (a, b, c) holds b-c and c-a after
        # a-b, t2 = (b, a, d) holds a-d and d-b after b-a
        k1, k2 = local_edge(tri_edges, t1, e_ab), local_edge(tri_edges, t2, e_ab)
        o_bc, o_ca = tri_edges[t1, (k1 + 1) % 3], tri_edges[t1, (k1 + 2) % 3]
        o_ad, o_db = tri_edges[t2, (k2 + 1) % 3], tri_edges[t2, (k2 + 2) % 3]
        # candidates no new edge could make worth it, before searching their parabolas
        outer = sum(elen[o] ** 2 for o in (o_ad, o_ca, o_db, o_bc))
        q_old = np.minimum(q[t1], q[t2])
        floor = in_range = None
        if length_rule:
            floor = max(min_quality, float(q.min()))
            in_range = out_of_range(elen[e_ab], length_range) <= min_gain
        quad_area = area[t1] + area[t2]
        lower = chord_lower_bound(field, pts[c], pts[d])
        bound = quality_bound(quad_area, outer, lower)
        hopeless = without_hope(bound, q_old, floor, in_range, min_gain)
        # the lens bound of the new edge, where the chord bound leaves hope
        k = np.flatnonzero(~hopeless)
        bound = quality_bound(quad_area[k], outer[k], lens_lower_bound(field, pts[c[k]], pts[d[k]]))
        hopeless[k] = without_hope(
            bound, q_old[k], floor, None if in_range is None else in_range[k], min_gain
        )
        rejected = sorted_union(rejected, qk[hopeless])
        e_ab, a, b, c, d, t1, t2, qk, o_ad, o_ca, o_db, o_bc = (
            v[~hopeless] for v in (e_ab, a, b, c, d, t1, t2, qk, o_ad, o_ca, o_db, o_bc)
        )
        if len(a) == 0:
            break
        # the new edge's optimal node (computed once per pair, kept in the store)
        ncd = store.key(c, d)
        _, found = optimal.find(ncd)
        need = np.unique(ncd[~found])
        if need.size and straight:
            ilo, ihi = need // n, need % n
            optimal.add(need, 0.5 * (pts[ilo] + pts[ihi]), np.zeros(len(need)))
        elif need.size:
            ilo, ihi = need // n, need % n
            par = shortest_parabola(field, pts[ilo], pts[ihi], exact_length=False)
            optimal.add(need, par.mid, par.length)
        opt_mid = optimal.mid[optimal.find(ncd)[0]]
        seg_mid = 0.5 * (pts[c] + pts[d])
        # outer edges' nodes: t1' = (a, d, c) edges ad, dc, ca; t2' = (d, b, c) edges db, bc, cd
        m_ad, m_ca, m_db, m_bc = (emid[o] for o in (o_ad, o_ca, o_db, o_bc))
        level = np.full(len(a), -1)
        new_mid = seg_mid.copy()
        for li, s in enumerate(BACKTRACK):
            todo = level < 0
            if not todo.any():
                break
            m_cd = seg_mid[todo] + s * (opt_mid[todo] - seg_mid[todo])
            n1 = _nodes(
                pts,
                np.column_stack([a, d, c])[todo],
                np.stack([m_ad[todo], m_cd, m_ca[todo]], axis=1),
            )
            n2 = _nodes(
                pts,
                np.column_stack([d, b, c])[todo],
                np.stack([m_db[todo], m_bc[todo], m_cd], axis=1),
            )
            ok = valid_exact(n1) & valid_exact(n2)
            idx = np.flatnonzero(todo)[ok]
            level[idx] = li
            new_mid[idx] = m_cd[ok]
        valid = level >= 0
        gain = np.full(len(a), -np.inf)
        if valid.any():
            v = np.flatnonzero(valid)
            l_cd = edge_lengths_fast(field, pts[c[v]], pts[d[v]], new_mid[v])
            l_ad, l_ca, l_db, l_bc = (elen[o[v]] for o in (o_ad, o_ca, o_db, o_bc))
            n1 = _nodes(
                pts, np.column_stack([a, d, c])[v], np.stack([m_ad[v], new_mid[v], m_ca[v]], axis=1)
            )
            n2 = _nodes(
                pts, np.column_stack([d, b, c])[v], np.stack([m_db[v], m_bc[v], new_mid[v]], axis=1)
            )
            q1 = quality_from(
                metric_areas(field, n1, order=area_order), np.column_stack([l_ad, l_cd, l_ca])
            )
            q2 = quality_from(
                metric_areas(field, n2, order=area_order), np.column_stack([l_db, l_bc, l_cd])
            )
            q_new, q_old = np.minimum(q1, q2), np.minimum(q[t1[v]], q[t2[v]])
            gain[v] = q_new - q_old
            l_ab = elen[e_ab[v]]
            if length_rule:
                gain[v] = length_rule_gain(
                    q_old,
                    q_new,
                    l_ab,
                    l_cd,
                    floor=max(min_quality, float(q.min())),
                    length_range=length_range,
                    min_gain=min_gain,
                )
            # never a new edge shorter than min(min_length, the edge it replaces)
            gain[v[l_cd < np.minimum(min_length, l_ab)]] = -np.inf
            new_len = np.zeros(len(a))
            new_len[v] = l_cd
        good = np.flatnonzero(gain > min_gain)
        rejected = sorted_union(rejected, qk[gain <= min_gain])
        if good.size == 0:
            break
        # greedy non-conflicting selection by decreasing gain (ties: candidate order)
        ch = good[independent_flips(t1[good], t2[good], gain[good], m)]
        tris = apply_flips(tris, ch, t1, t2, a, b, c, d)
        flipped = np.concatenate([t1[ch], t2[ch]])
        changed = np.zeros(m, dtype=bool)
        changed[flipped] = True
        rejected = rejected[~(changed[rejected // m] | changed[rejected % m])]
        store.add(store.key(c[ch], d[ch]), new_mid[ch], new_len[ch])
        swaps += len(ch)
        rounds += 1
    final = Mesh(pts, tris, p1.box)
    pos, _ = store.find(store.key(final.edges[:, 0], final.edges[:, 1]))
    return SwapResult(assemble_p2(pts, final, store.mid[pos]), swaps, rounds)
