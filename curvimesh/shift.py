"""Vertex shifts at long edges: an end vertex moved to shorten the longest edge of its star.

After the swaps, insertions, splits and re-curving, a few edges can stay
longer than 1.4 in the metric where no vertex fits in their cavity (every
position an insertion would try is within 0.7 of a vertex) and their nodes
are already on their shortest parabolas. Moving one of their end vertices,
with the edges of its star curved again, shortens them while the star's
other edges take up the slack.

For each edge e = (v, w) longer than ``max_length``, longest first, and each
of its ends v that is not on the box boundary, the candidate positions are

    v' = v + t R(φ) (w − v),   t in :data:`STEPS`, φ in :data:`ANGLES`

(R(φ) the rotation by φ: towards w and up to about 86° off that line). The
edges incident to v are put on their shortest parabolas from v' (paper
equation (3)), moved back towards their straight midpoints by the fractions
:data:`BACKTRACK` until every triangle of the star is valid (Jacobian
positive everywhere, decided exactly from its Bezier coefficients). A
candidate is admissible when

* the longest edge incident to v gets shorter: max L' < max L;
* no incident edge gets shorter than min(``min_dist``, its shortest before);
* the worst quality (4) of the star stays at least min(q_star, q_floor), with
  q_floor = max(``min_quality``, the worst quality of the mesh), so that the
  worst quality of the mesh never goes down;

and the admissible candidate with the shortest longest edge is taken (its
lengths checked again to 1e-5 before the move).

Each pass then visits the triangles of quality (4) below ``improve_below``
(:data:`IMPROVE_BELOW`), worst first. A swap guarded against short edges can
leave one: a vertex almost on the opposite edge, its two edges near 0.7 and
the third near 1.4; where the hexagonal lattices of the sampling
(:mod:`curvimesh.sampling`) grown from different sides meet, triangles of
quality 0.65 – 0.8 are left, which a move of one vertex mends.
Its interior vertices, the one opposite the longest edge first, are tried
along the height (x′ = x + t R(φ) 2(x − m), m the opposite edge's midpoint);
the move that raises the worst quality of the star most is taken, if every
edge of the star stays in [min(``min_dist``, its shortest), max(``max_length``,
its longest)]. Passes repeat until one moves nothing. Only the moved vertex
and the nodes of its incident edges move; the triangles stay.

Beyond the paper; the smoothing step of anisotropic remeshers (MMG's
vertex relocation, for instance) moves vertices to balance edge lengths
too, on straight edges. :func:`curvimesh.adapt.swap` runs it after the last
swaps (``--no-shift`` turns it off).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from curvimesh.bezier import valid_exact
from curvimesh.freenode import shortest_parabola
from curvimesh.mesh import Mesh, cells_at_vertices
from curvimesh.metric import MetricField
from curvimesh.quality import edge_lengths, edge_lengths_fast, metric_areas, quality_from

#: Fractions t of the long edge's chord a vertex is moved by. The small ones
#: matter where the metric varies fast: on the quartic example, moving a
#: vertex by 0.5 % of a 1.52-long edge shortens it by up to 5 % and a neighbouring
#: edge by up to 10 % (at 43° off the edge).
STEPS = (0.005, 0.01, 0.02, 0.04, 0.08, 0.12, 0.16, 0.2, 0.25)

#: Angles φ (radians) off the long edge's direction.
ANGLES = (0.0, 0.5, -0.5, 1.0, -1.0, 1.5, -1.5)

#: Quality (4) below which a triangle's vertices are tried for a better position.
#: Measured on the toy metric: 1.2 % of the triangles are below it at 10⁴ vertices
#: (the seams of the sampling's hexagonal lattices); with the pass the worst
#: quality is 0.80 from 10³ to 10⁵ vertices (0.67 – 0.74 without), for 0.5 s at 10⁵.
IMPROVE_BELOW = 0.8

#: Fractions of the optimal offset tried for the moved vertex's edges, in order.
BACKTRACK = (1.0, 0.5, 0.25, 0.0)


@dataclass(frozen=True)
class ShiftResult:
    """The mesh after the shifts, how many vertices moved and in how many passes."""

    mesh: Mesh
    shifted: int
    passes: int


@dataclass(frozen=True)
class _Star:
    """The triangles ``(s,)`` around a vertex, its incident edges ``(j,)`` and their
    other ends ``(j,)``, and for each slot of each star triangle ``(s, 6)``: −1
    for the vertex itself, k >= 0 for the node of incident edge k, −2 otherwise."""

    tris: NDArray
    edges: NDArray
    others: NDArray
    slots: NDArray


@dataclass(frozen=True)
class _Incidence:
    """The triangles and the edges at each vertex, ascending: rows ``start[v]:start[v + 1]``
    of ``tris`` and ``estart[v]:estart[v + 1]`` of ``edges`` (the triangles do not change
    while vertices move)."""

    start: NDArray
    tris: NDArray
    estart: NDArray
    edges: NDArray

    @classmethod
    def of(cls, mesh: Mesh) -> _Incidence:
        n = len(mesh.points)
        return cls(*cells_at_vertices(mesh.triangles[:, :3], n), *cells_at_vertices(mesh.edges, n))


def _star(mesh: Mesh, inc: _Incidence, v: int) -> _Star:
    tris = inc.tris[inc.start[v] : inc.start[v + 1]]
    edges = inc.edges[inc.estart[v] : inc.estart[v + 1]]
    others = np.where(mesh.edges[edges, 0] == v, mesh.edges[edges, 1], mesh.edges[edges, 0])
    slots = np.full((len(tris), 6), -2)
    slots[mesh.triangles[tris] == v] = -1
    for k, e in enumerate(edges):
        slots[:, 3:][mesh.tri_edges[tris] == e] = k
    return _Star(tris, edges, others, slots)


def shift_vertices(
    field: MetricField,
    mesh: Mesh,
    *,
    max_length: float = 1.4,
    min_dist: float = 0.7,
    min_quality: float = 0.3,
    improve_below: float = IMPROVE_BELOW,
    max_passes: int = 5,
) -> ShiftResult:
    """Move end vertices of the edges longer than ``max_length``, then vertices of
    the triangles of quality below ``improve_below`` (module docstring); a move for a
    long edge keeps the star's worst quality at least min(its own, max(``min_quality``,
    the mesh's worst)).

    ``mesh`` is a valid P2 mesh; the result has the same triangles and node
    numbering, and is valid. Deterministic.
    """
    if mesh.order != 2 or len(mesh.triangles) == 0:
        return ShiftResult(mesh, 0, 0)
    pts = np.array(mesh.points)
    edges = mesh.edges
    length = edge_lengths(field, pts, edges, mesh.edge_mid)
    quality = quality_from(metric_areas(field, pts[mesh.triangles]), length[mesh.tri_edges])
    floor = max(min_quality, float(quality.min()))
    fixed = mesh.boundary_vertices
    inc = _Incidence.of(mesh)
    shifted = passes = 0
    while passes < max_passes:
        passes += 1
        moved = 0
        for e in np.argsort(-length, kind="stable"):
            if length[e] <= max_length:
                break
            for v, w in (edges[e], edges[e][::-1]):
                if fixed[v]:
                    continue
                star = _star(mesh, inc, int(v))
                old = length[star.edges]
                q_min = min(float(quality[star.tris].min()), floor)
                rule = _Rule(
                    shortest=min(min_dist, float(old.min())),
                    longest=float(old.max()),
                    q_min=q_min,
                    by_quality=False,
                )
                cand = _candidates(field, pts[v], pts[w] - pts[v])
                got = _best_move(field, mesh, pts, length, star, int(v), cand, rule)
                if got is None:
                    continue
                pts[v], pts[mesh.edge_mid[star.edges]], length[star.edges], quality[star.tris] = got
                moved += 1
                break
        moved += _quality_pass(
            field, mesh, inc, pts, length, quality, fixed, (min_dist, max_length), improve_below
        )
        shifted += moved
        if moved == 0:
            break
    return ShiftResult(Mesh(pts, mesh.triangles, mesh.box), shifted, passes)


def _quality_pass(
    field: MetricField,
    mesh: Mesh,
    inc: _Incidence,
    pts: NDArray,
    length: NDArray,
    quality: NDArray,
    fixed: NDArray,
    bounds: tuple[float, float],
    improve_below: float,
) -> int:
    """One pass over the triangles of quality below ``improve_below``, worst first.

    Each interior vertex of such a triangle, the one opposite its longest
    edge first, is tried along its height (away from the opposite edge's
    midpoint, and turned by :data:`ANGLES`); the move that raises the worst
    quality of its star most is taken, if no edge of the star leaves
    [min(``min_dist``, its shortest), max(``max_length``, its longest)].
    ``pts``, ``length`` and ``quality`` are updated in place; returns the
    number of vertices moved.
    """
    min_dist, max_length = bounds
    moved = 0
    for t in np.argsort(quality, kind="stable"):
        if quality[t] >= improve_below:
            break
        corners = mesh.triangles[t, :3]
        # vertex k is opposite local edge (k + 1) % 3 (edges 0-1, 1-2, 2-0)
        opposite = length[mesh.tri_edges[t]][[1, 2, 0]]
        for k in np.argsort(-opposite, kind="stable"):
            v = int(corners[k])
            if fixed[v]:
                continue
            star = _star(mesh, inc, v)
            old = length[star.edges]
            rule = _Rule(
                shortest=min(min_dist, float(old.min())),
                longest=max(max_length, float(old.max())),
                q_min=float(quality[star.tris].min()),
                by_quality=True,
            )
            away = pts[v] - 0.5 * (pts[corners[(k + 1) % 3]] + pts[corners[(k + 2) % 3]])
            cand = _candidates(field, pts[v], 2.0 * away)
            got = _best_move(field, mesh, pts, length, star, v, cand, rule)
            if got is None:
                continue
            pts[v], pts[mesh.edge_mid[star.edges]], length[star.edges], quality[star.tris] = got
            moved += 1
            break
    return moved


@dataclass(frozen=True)
class _Rule:
    """What a move must do. A move for a long edge (not ``by_quality``) keeps the
    star's edges at least ``shortest`` and its longest strictly below
    ``longest`` (the longest now), and its worst quality at least ``q_min``;
    the best has the shortest longest edge. A move for quality keeps the edges
    in [shortest, longest] and raises the worst quality above ``q_min``; the
    best has the best worst quality."""

    shortest: float
    longest: float
    q_min: float
    by_quality: bool

    def lengths_ok(self, lens: NDArray) -> NDArray:
        top = lens.max(axis=-1)
        below = top <= self.longest if self.by_quality else top < self.longest
        return below & (lens.min(axis=-1) >= self.shortest)

    def quality_ok(self, q: NDArray) -> bool:
        worst = float(q.min())
        return worst > self.q_min if self.by_quality else worst >= self.q_min


def _candidates(field: MetricField, x: NDArray, chord: NDArray) -> NDArray:
    """Positions ``(k, 2)`` x + t R(φ) chord strictly inside the box."""
    moves = []
    for phi in ANGLES:
        c, s = np.cos(phi), np.sin(phi)
        turned = np.array([c * chord[0] - s * chord[1], s * chord[0] + c * chord[1]])
        moves += [x + t * turned for t in STEPS]
    cand = np.array(moves)
    xmin, ymin, xmax, ymax = field.box
    inside = (cand[:, 0] > xmin) & (cand[:, 0] < xmax) & (cand[:, 1] > ymin) & (cand[:, 1] < ymax)
    return cand[inside]


def _best_move(
    field: MetricField,
    mesh: Mesh,
    pts: NDArray,
    length: NDArray,
    star: _Star,
    v: int,
    cand: NDArray,
    rule: _Rule,
) -> tuple[NDArray, NDArray, NDArray, NDArray] | None:
    """The best admissible position of v among ``cand`` (module docstring, ``rule``):
    v's new position, its incident edges' new middle nodes ``(j, 2)`` and lengths
    ``(j,)``, and the star's qualities ``(s,)``; None if there is none.
    """
    k, j = len(cand), len(star.edges)
    if k == 0:
        return None
    others = pts[star.others]
    a = np.repeat(cand, j, axis=0)
    b = np.tile(others, (k, 1))
    # the candidates' pairs seldom come again: searched and measured without the memo
    optimal = shortest_parabola(field, a, b, exact_length=False, remember=False, guided=True)
    optimal = optimal.mid.reshape(k, j, 2)
    straight = 0.5 * (a + b).reshape(k, j, 2)
    base = pts[mesh.triangles[star.tris]]  # (s, 6, 2)
    inc = star.slots[:, 3:]  # (s, 3): incident edge k, or −2
    lens0 = length[mesh.tri_edges[star.tris]]  # (s, 3)
    todo = np.ones(k, dtype=bool)
    found: list[tuple[float, int, NDArray, NDArray]] = []  # (score, candidate, nodes, mids)
    for frac in BACKTRACK:
        rows = np.flatnonzero(todo)
        if rows.size == 0:
            break
        mid = straight[rows] + frac * (optimal[rows] - straight[rows])  # (r, j, 2)
        nodes = np.repeat(base[None], len(rows), axis=0)  # (r, s, 6, 2)
        nodes[:, star.slots == -1] = cand[rows][:, None, :]
        for kk in range(j):
            nodes[:, star.slots == kk] = mid[:, kk][:, None, :]
        ok = valid_exact(nodes.reshape(-1, 6, 2)).reshape(len(rows), -1).all(axis=1)
        todo[rows[ok]] = False
        if not ok.any():
            continue
        rows, mid, nodes = rows[ok], mid[ok], nodes[ok]
        new_len = edge_lengths_fast(
            field,
            np.repeat(cand[rows], j, axis=0),
            np.tile(others, (len(rows), 1)),
            mid.reshape(-1, 2),
            remember=False,
        ).reshape(len(rows), j)
        good = np.flatnonzero(rule.lengths_ok(new_len))
        if rule.by_quality and good.size:
            lens = np.repeat(lens0[None], good.size, axis=0)
            lens[:, inc >= 0] = new_len[good][:, inc[inc >= 0]]
            areas = metric_areas(field, nodes[good].reshape(-1, 6, 2), remember=False)
            areas = areas.reshape(good.size, -1)
            scores = -quality_from(areas.reshape(-1), lens.reshape(-1, 3)).reshape(good.size, -1)
            score = scores.max(axis=1)
        else:
            score = new_len[good].max(axis=1) if good.size else np.empty(0)
        for r, sc in zip(good, score, strict=True):
            found.append((float(sc), int(rows[r]), nodes[r], mid[r]))
    pairs = np.column_stack([np.zeros(j, dtype=int), np.arange(1, j + 1)])
    for _score, i, nodes, mids in sorted(found, key=lambda f: (f[0], f[1]))[:4]:
        local = np.vstack([cand[i][None], others, mids])
        exact = edge_lengths(field, local, pairs, np.arange(j + 1, 2 * j + 1))
        if not rule.lengths_ok(exact):
            continue
        lens = lens0.copy()
        lens[inc >= 0] = exact[inc[inc >= 0]]
        q = quality_from(metric_areas(field, nodes), lens)
        if rule.quality_ok(q):
            return cand[i], mids, exact, q
    return None
