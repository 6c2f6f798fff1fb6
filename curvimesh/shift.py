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
(:data:`IMPROVE_BELOW`), worst first, their metric areas measured to the
report's accuracy (:func:`curvimesh.quality.qualities`, and so are the stars of the
moves it keeps), lest a kink of the metric hide a triangle below it from the loops'
fixed rule. A swap guarded against short edges can
leave one: a vertex almost on the opposite edge, its two edges near 0.7 and
the third near 1.4; where the hexagonal lattices of the sampling
(:mod:`curvimesh.sampling`) grown from different sides meet, triangles of
quality 0.65 – 0.8 are left, which a move of one vertex mends.
Its interior vertices, the one opposite its longest edge first, are tried
along the height (x′ = x + t R(φ) 2(x − m), m the opposite edge's midpoint);
the move that raises the worst quality of the star most is taken, if every
edge of the star stays in [min(``min_dist``, its shortest), max(``max_length``,
its longest)]. In a *healthy* star (no edge longer than ``max_length``, worst
quality at least :data:`HEALTHY_ABOVE`: the seams of the lattices, not the
defects the clean-up stages work on), three things make the pass cheaper
and let it reach further:

* the candidates are screened first, each incident edge keeping its present
  bend (the offset α of its middle node: a first-order model of its shortest
  parabola, exact on a constant metric), and only the :data:`SCREEN` best are
  searched (:func:`_screened`);
* the vertex is also tried back towards the opposite edge (φ = π, the apex of
  a tall triangle: :data:`QUALITY_ANGLES`);
* a vertex hemmed in by short edges, with no move of its own, is tried again
  after the other end u of each of its edges shorter than :data:`PUSH_BELOW`
  is moved away from it; the pair is kept when the worst quality around the
  two rose, else undone (:func:`_pair_move`).

A try that found no move is not made again before one of the triangles it
depends on changes (:class:`_Tries`). Passes repeat until one moves nothing,
at most ``max_passes``, and past :data:`MIN_PASSES` only while the worst
quality of the mesh rises. Only the moved vertices and the nodes of their
incident edges move; the triangles stay.

Beyond the paper; the smoothing step of anisotropic remeshers (MMG's
vertex relocation, for instance) moves vertices to balance edge lengths
too, on straight edges. :func:`curvimesh.adapt.swap` runs it after the last
swaps (``--no-shift`` turns it off).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from curvimesh import kernels
from curvimesh.bezier import REFERENCE_NODES, VALID_RTOL, p2_shape_grad, valid_exact
from curvimesh.freenode import shortest_parabola
from curvimesh.geodesic import (
    LENGTH_MAX_SEGMENTS,
    LENGTH_ORDER,
    SEARCH_ALPHA_MAX,
    SEARCH_MAX_ITER,
    SEARCH_SCAN,
    SEARCH_TOL,
    doubling_rules,
    gauss_rule,
    offset_alpha,
    parabola_midnode,
    search_grid,
)
from curvimesh.mesh import Mesh, cells_at_vertices
from curvimesh.metric import MetricField
from curvimesh.quality import (
    AREA_MAX_LEVEL,
    COUNT_RTOL,
    REMEASURE_MARGIN,
    REPORT_RTOL,
    area_rule,
    child_shape,
    edge_lengths,
    edge_lengths_fast,
    metric_areas,
    qualities,
    quality_from,
)

#: Fractions t of the long edge's chord a vertex is moved by. The small ones
#: matter where the metric varies fast: on the quartic example, moving a
#: vertex by 0.5 % of a 1.52-long edge shortens it by up to 5 % and a neighbouring
#: edge by up to 10 % (at 43° off the edge).
STEPS = (0.005, 0.01, 0.02, 0.04, 0.08, 0.12, 0.16, 0.2, 0.25)

#: Angles φ (radians) off the long edge's direction.
ANGLES = (0.0, 0.5, -0.5, 1.0, -1.0, 1.5, -1.5)

#: Angles of a quality move off its triangle's height: :data:`ANGLES`, and back towards
#: the opposite edge. Measured on the three toys at 1,617 vertices: the worst triangle
#: (edges 1.40, 1.39, 0.73, quality 0.749) is mended only by moving its apex towards
#: its short edge (0.749 → 0.801); its other corners' moves need an edge of 1.42.
QUALITY_ANGLES = (*ANGLES, np.pi)

#: Quality (4) below which a triangle's vertices are tried for a better position.
#: Measured on the toy metric: 1.2 % of the triangles are below it at 10⁴ vertices
#: (the seams of the sampling's hexagonal lattices); with the pass the worst
#: quality is 0.80 from 10³ to 10⁵ vertices (0.67 – 0.74 without), for 0.5 s at 10⁵.
IMPROVE_BELOW = 0.8

#: Fractions of the optimal offset tried for the moved vertex's edges, in order.
BACKTRACK = (1.0, 0.5, 0.25, 0.0)

#: How many candidates of a quality move, the best screened (:func:`_screened`), are
#: searched.
SCREEN = 4

#: The worst quality (4) of the healthy stars (module docstring). Elsewhere, near
#: singular points for instance (the centre of concentric circles), the edges' bends
#: change fast with the vertex, and the moves are those of the plain pass: screening
#: there too left an edge of 1.92 on a concentric field of 15:1 (bench/robustness,
#: u21, seed 0; none above 1.40 with the full search), and the moves towards the
#: opposite edge one of 1.55 (seed 2).
HEALTHY_ABOVE = 0.5

#: A hemmed-in vertex's edges shorter than this are lengthened by moving their other
#: ends (:func:`_pair_move`).
PUSH_BELOW = 0.75

#: The passes always made; past them, a pass is made only while the worst quality rises.
MIN_PASSES = 5


@dataclass(frozen=True)
class ShiftResult:
    """The mesh after the shifts, how many vertices moved and in how many passes."""

    mesh: Mesh
    shifted: int
    passes: int
    exhausted: bool = False
    searched: int = 0


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
    hit = mesh.tri_edges[tris][:, :, None] == edges  # (s, 3, j)
    slots[:, 3:] = np.where(hit.any(axis=2), hit.argmax(axis=2), -2)
    return _Star(tris, edges, others, slots)


def shift_vertices(
    field: MetricField,
    mesh: Mesh,
    *,
    max_length: float = 1.4,
    min_dist: float = 0.7,
    min_quality: float = 0.3,
    improve_below: float = IMPROVE_BELOW,
    max_passes: int = 20,
    max_searches: int | None = None,
) -> ShiftResult:
    """Move end vertices of the edges longer than ``max_length``, then vertices of
    the triangles of quality below ``improve_below`` (module docstring); a move for a
    long edge keeps the star's worst quality at least min(its own, max(``min_quality``,
    the mesh's worst)).

    With ``max_searches``, the moves stop once the candidates tried, each counted
    with its incident edges (the shortest parabolas a full search makes), reach it
    (``exhausted`` in the result, with the count ``searched``); the moves made stay.

    ``mesh`` is a valid P2 mesh; the result has the same triangles and node
    numbering, and is valid. Deterministic.
    """
    if mesh.order != 2 or len(mesh.triangles) == 0:
        return ShiftResult(mesh, 0, 0)
    pts = np.array(mesh.points)
    edges = mesh.edges
    length = edge_lengths(field, pts, edges, mesh.edge_mid)
    quality = qualities(field, pts[mesh.triangles], length[mesh.tri_edges], aim=improve_below)
    floor = max(min_quality, float(quality.min()))
    start = np.iinfo(np.int64).max if max_searches is None else max_searches
    budget = np.array([start], dtype=np.int64)
    state = _State(
        mesh, _Incidence.of(mesh), pts, length, quality, mesh.boundary_vertices, budget,
        improve_below,
    )  # fmt: skip
    tries = _Tries(len(mesh.triangles))
    shifted = passes = 0
    worst = float(quality.min())

    def long_rule(star: _Star, e: int) -> _Rule:
        old = length[star.edges]
        return _Rule(
            shortest=min(min_dist, float(old.min())),
            longest=float(old.max()),
            q_min=min(float(quality[star.tris].min()), floor),
            by_quality=False,
        )

    while passes < max_passes:
        passes += 1
        longest_first = _ascending(-length, length > max_length)
        moved = _end_moves(
            field, state, tries, longest_first, lambda e: length[e] > max_length, "edge",
            long_rule, towards=True,
        )  # fmt: skip
        moved += _short_pass(field, state, tries, (min_dist, max_length), improve_below)
        moved += _quality_pass(field, state, tries, (min_dist, max_length), improve_below)
        shifted += moved
        now = float(quality.min())
        if moved == 0 or state.exhausted or (passes >= MIN_PASSES and now <= worst):
            break
        worst = now
    searched = int(start - budget[0])
    return ShiftResult(
        Mesh(pts, mesh.triangles, mesh.box), shifted, passes, state.exhausted, searched
    )


@dataclass(frozen=True)
class _State:
    """The mesh being shifted: its triangles and incidence, and the arrays the moves
    update in place: node positions, edge lengths, triangle qualities."""

    mesh: Mesh
    inc: _Incidence
    pts: NDArray
    length: NDArray
    quality: NDArray
    fixed: NDArray
    budget: NDArray | None = None  # searches left (one entry, spent in place); None: no bound
    improve_below: float = IMPROVE_BELOW  # the quality pass's threshold (re-measuring below it)

    def star(self, v: int) -> _Star:
        return _star(self.mesh, self.inc, v)

    def ring(self, star: _Star) -> NDArray:
        """The triangles of the stars of a star's other ends (its own among them)."""
        inc = self.inc
        return np.concatenate([inc.tris[inc.start[o] : inc.start[o + 1]] for o in star.others])

    @property
    def exhausted(self) -> bool:
        """Whether the budget of searches is spent."""
        return self.budget is not None and bool(self.budget[0] <= 0)

    def healthy(self, star: _Star, max_length: float) -> bool:
        """Whether a star has no edge longer than ``max_length`` and a worst quality of
        at least :data:`HEALTHY_ABOVE`."""
        return (
            float(self.quality[star.tris].min()) >= HEALTHY_ABOVE
            and float(self.length[star.edges].max()) <= max_length
        )

    def saved(self, star: _Star, v: int) -> tuple:
        """What a move of v, the star's vertex, changes, as :meth:`write` takes it."""
        mids = self.mesh.edge_mid[star.edges]
        return (
            star, v, self.pts[v].copy(), self.pts[mids], self.length[star.edges],
            self.quality[star.tris],
        )  # fmt: skip

    def write(self, star: _Star, v: int, at: NDArray, mids: NDArray, lens: NDArray, q: NDArray):
        """v at ``at``, its incident edges' middle nodes ``mids`` and lengths ``lens``, its
        star's qualities ``q``."""
        self.pts[v], self.pts[self.mesh.edge_mid[star.edges]] = at, mids
        self.length[star.edges], self.quality[star.tris] = lens, q

    def move(self, field: MetricField, star: _Star, v: int, cand: NDArray, rule: _Rule) -> bool:
        """Move v to the best admissible of ``cand`` (:func:`_best_move`); whether it moved.
        Each candidate's incident edges count against the budget of searches; with
        none left, nothing moves."""
        if self.exhausted:
            return False
        if self.budget is not None:
            self.budget[0] -= len(cand) * len(star.edges)
        got = _best_move(field, self, star, v, cand, rule)
        if got is not None:
            self.write(star, v, *got)
        return got is not None


def _quality_pass(
    field: MetricField,
    state: _State,
    tries: _Tries,
    bounds: tuple[float, float],
    improve_below: float,
) -> int:
    """One pass over the triangles of quality below ``improve_below``, worst first
    (module docstring): for each, its interior corners, the one opposite its longest
    edge first, until one moves (:func:`_quality_move`, else :func:`_pair_move` in a
    healthy star). Returns the number of vertices moved."""
    mesh, pts, length, quality = state.mesh, state.pts, state.length, state.quality
    moved = 0
    for t in _ascending(quality, quality < improve_below):
        if quality[t] >= improve_below or state.exhausted:
            break
        corners = mesh.triangles[t, :3]
        # vertex k is opposite local edge (k + 1) % 3 (edges 0-1, 1-2, 2-0)
        opposite = length[mesh.tri_edges[t]][[1, 2, 0]]
        for k in np.argsort(-opposite, kind="stable"):
            v = int(corners[k])
            if state.fixed[v]:
                continue
            star = state.star(v)
            ring = state.ring(star)
            key = ("triangle", int(t), v)
            if tries.known_to_fail(key, ring):
                continue
            away = pts[v] - 0.5 * (pts[corners[(k + 1) % 3]] + pts[corners[(k + 2) % 3]])
            if _quality_move(field, state, star, v, away, bounds):
                tries.moved(star.tris)
            elif state.healthy(star, bounds[1]) and _pair_move(
                field, state, star, ring, v, away, bounds, improve_below
            ):
                tries.moved(ring)
            else:
                tries.failed(key)
                continue
            moved += 1
            break
    return moved


def _short_pass(
    field: MetricField,
    state: _State,
    tries: _Tries,
    bounds: tuple[float, float],
    improve_below: float,
) -> int:
    """One pass over the edges shorter than ``min_dist`` (beyond the report's accuracy),
    shortest first: an end v is moved away from the other (along v − w turned by
    :data:`ANGLES`) to the position of the best worst quality of its star with every
    edge of the star, this one too, at least min(``min_dist``, the shortest of the
    others) and at most max(``max_length``, its longest), the worst quality at least
    min(its own, ``improve_below``). Returns the number of vertices moved."""
    min_dist, max_length = bounds
    length, quality = state.length, state.quality
    limit = min_dist * (1.0 - COUNT_RTOL)

    def rule(star: _Star, e: int) -> _Rule:
        old = length[star.edges]
        others = old[star.edges != e]
        return _Rule(
            shortest=min(min_dist, float(others.min())) if others.size else min_dist,
            longest=max(max_length, float(old.max())),
            q_min=min(float(quality[star.tris].min()), improve_below) - 1e-12,
            by_quality=True,
        )

    shortest_first = _ascending(length, length < limit)
    return _end_moves(
        field, state, tries, shortest_first, lambda e: length[e] < limit, "short", rule,
        towards=False,
    )  # fmt: skip


def _end_moves(
    field: MetricField,
    state: _State,
    tries: _Tries,
    order: Iterator[int],
    still: Callable[[int], bool],
    kind: str,
    rule: Callable[[_Star, int], _Rule],
    *,
    towards: bool,
) -> int:
    """Moves of an end v of each edge e of ``order`` while ``still(e)``: v along the
    chord to its other end w (``towards``) or away from it, turned by :data:`ANGLES`,
    to the best admissible position by ``rule(v's star, e)`` (:func:`_best_move`); the
    other end is tried when v is fixed or finds nothing. A try that found nothing is
    not made again before its star changes (:class:`_Tries`, by ``kind``, e, v).
    Returns the number of vertices moved."""
    mesh, pts = state.mesh, state.pts
    moved = 0
    for e in order:
        if not still(e) or state.exhausted:
            break
        for v, w in (mesh.edges[e], mesh.edges[e][::-1]):
            if state.fixed[v]:
                continue
            star = state.star(int(v))
            key = (kind, int(e), int(v))
            if tries.known_to_fail(key, star.tris):
                continue
            chord = pts[w] - pts[v] if towards else pts[v] - pts[w]
            if not state.move(
                field, star, int(v), _candidates(field, pts[v], chord), rule(star, e)
            ):
                tries.failed(key)
                continue
            tries.moved(star.tris)
            moved += 1
            break
    return moved


def _quality_move(
    field: MetricField,
    state: _State,
    star: _Star,
    v: int,
    away: NDArray,
    bounds: tuple[float, float],
) -> bool:
    """Move v along ``away`` turned by :data:`ANGLES` to raise the worst quality of its
    star, no edge of the star leaving [min(min_dist, its shortest), max(max_length,
    its longest)]; in a healthy star (:meth:`_State.healthy`) also back towards the
    opposite edge (:data:`QUALITY_ANGLES`), the candidates screened first
    (:func:`_screened`). Whether it moved."""
    worst = float(state.quality[star.tris].min())
    rule = _Rule.for_quality(state.length[star.edges], worst, bounds)
    if not state.healthy(star, bounds[1]):
        return state.move(field, star, v, _candidates(field, state.pts[v], 2.0 * away), rule)
    cand = _candidates(field, state.pts[v], 2.0 * away, QUALITY_ANGLES)
    return state.move(field, star, v, _screened(field, state, star, v, cand, rule), rule)


def _pair_move(
    field: MetricField,
    state: _State,
    star: _Star,
    ring: NDArray,
    v: int,
    away: NDArray,
    bounds: tuple[float, float],
    improve_below: float,
) -> bool:
    """A quality move of v hemmed in by short edges. For each edge (v, u) shorter than
    :data:`PUSH_BELOW`, shortest first, u is moved away from v (along u − v, turned by
    :data:`ANGLES`) to the position that makes that edge longest while every edge of
    u's star stays in its bounds (as for a quality move) and the worst quality of u's
    star stays above min(its own, ``improve_below``); then v is moved
    (:func:`_quality_move`). Both are kept when the worst quality of v's ring (the
    stars of v's neighbours, u's among them) rose, else both are undone. Whether the
    pair moved. ``ring`` is v's ring (:meth:`_State.ring`)."""
    pts, length, quality = state.pts, state.length, state.quality
    before = float(quality[ring].min())
    for kk in np.argsort(length[star.edges], kind="stable"):
        if length[star.edges[kk]] >= PUSH_BELOW:
            break
        u = int(star.others[kk])
        if state.fixed[u]:
            continue
        su = state.star(u)
        q_min = min(float(quality[su.tris].min()), improve_below)
        push = int(np.flatnonzero(su.others == v)[0])
        rule = _Rule.for_quality(length[su.edges], q_min, bounds, push=push)
        cand = _screened(field, state, su, u, _candidates(field, pts[u], pts[u] - pts[v]), rule)
        saved_u = state.saved(su, u)
        if not state.move(field, su, u, cand, rule):
            continue
        saved_v = state.saved(star, v)
        if _quality_move(field, state, star, v, away, bounds):
            if float(quality[ring].min()) > before:
                return True
            state.write(*saved_v)
        state.write(*saved_u)
    return False


def _ascending(key: NDArray, mask: NDArray) -> Iterator[int]:
    """The indices of ``key`` by ascending value, ties by index (a stable argsort of
    ``key`` as it is now), where ``mask`` holds of a prefix of that order: the rows of
    the mask are sorted alone, and the rest only if the caller goes past the first of
    them (a pass's sort of every edge and triangle took 30 ms at 10⁵ vertices; a pass
    nearly always stops at the mask's end)."""
    key = np.array(key)  # the order is that of now, the caller's array may change
    rows = np.flatnonzero(mask)
    yield from rows[np.argsort(key[rows], kind="stable")].tolist()
    rest = np.flatnonzero(~mask)
    if rest.size == 0:
        return
    first = int(rest[np.argmin(key[rest])])  # the first of the minima: ties by index
    yield first
    order = rest[np.argsort(key[rest], kind="stable")]
    yield from order[order != first].tolist()


class _Tries:
    """The tries that found no move, and when each triangle's nodes last changed.

    A try (an end of a long edge, or a corner of a poor triangle) depends only on
    the nodes of some triangles (the moved vertex's star; its ring for a pair
    move): their positions give the candidates, the lengths, the qualities and
    the rule's bounds, and the moves are deterministic. A try that found nothing
    finds nothing again until a move changes one of those triangles, so it is
    not made again before (the meshes are the same, bit for bit).
    """

    def __init__(self, n_triangles: int) -> None:
        self.clock = 0
        self.changed = np.zeros(n_triangles, dtype=np.int64)
        self.failures: dict[tuple, int] = {}

    def known_to_fail(self, key: tuple, tris: NDArray) -> bool:
        when = self.failures.get(key)
        return when is not None and int(self.changed[tris].max()) <= when

    def failed(self, key: tuple) -> None:
        self.failures[key] = self.clock

    def moved(self, tris: NDArray) -> None:
        self.clock += 1
        self.changed[tris] = self.clock


@dataclass(frozen=True)
class _Rule:
    """What a move must do. A move for a long edge (not ``by_quality``) keeps the
    star's edges at least ``shortest`` and its longest strictly below
    ``longest`` (the longest now), and its worst quality at least ``q_min``;
    the best has the shortest longest edge. A move for quality keeps the edges
    in [shortest, longest] and raises the worst quality above ``q_min``; the
    best has the best worst quality, or with ``push`` >= 0 the longest incident
    edge ``push``."""

    shortest: float
    longest: float
    q_min: float
    by_quality: bool
    push: int = -1

    @classmethod
    def for_quality(
        cls, old: NDArray, q_min: float, bounds: tuple[float, float], push: int = -1
    ) -> _Rule:
        """The rule of a quality move of a star whose incident edges are ``old`` long:
        edges kept in [min(min_dist, shortest), max(max_length, longest)] (``bounds`` is
        (min_dist, max_length)), the worst quality raised above ``q_min``."""
        min_dist, max_length = bounds
        shortest, longest = min(min_dist, float(old.min())), max(max_length, float(old.max()))
        return cls(shortest, longest, q_min, by_quality=True, push=push)

    def lengths_ok(self, lens: NDArray) -> NDArray:
        top = lens.max(axis=-1)
        below = top <= self.longest if self.by_quality else top < self.longest
        return below & (lens.min(axis=-1) >= self.shortest)

    def quality_ok(self, q: NDArray) -> bool:
        worst = float(q.min())
        return worst > self.q_min if self.by_quality else worst >= self.q_min

    def scores(self, new_len: NDArray, worst: NDArray) -> NDArray:
        """Scores (lower is better) of quality moves from their incident edges' lengths
        ``(k, j)`` and their stars' worst qualities ``(k,)``."""
        return -new_len[:, self.push] if self.push >= 0 else -worst


def _candidates(
    field: MetricField, x: NDArray, chord: NDArray, angles: tuple[float, ...] = ANGLES
) -> NDArray:
    """Positions ``(k, 2)`` x + t R(φ) chord strictly inside the box, φ in ``angles``
    (φ-major, t in :data:`STEPS` ascending)."""
    c, s = _rotations(angles)
    turned = np.column_stack([c * chord[0] - s * chord[1], s * chord[0] + c * chord[1]])
    steps = np.array(STEPS)[:, None]
    cand = (x + steps * turned[:, None, :]).reshape(-1, 2)  # (φ, t, 2)
    return cand[field.inside(cand)]


@lru_cache(maxsize=8)
def _rotations(angles: tuple[float, ...]) -> tuple[NDArray, NDArray]:
    """cos φ and sin φ ``(a,)`` of ``angles`` (cached; do not modify).

    >>> [round(float(v), 12) for v in np.concatenate(_rotations((0.0, np.pi / 2)))]
    [1.0, 0.0, 0.0, 1.0]
    """
    return np.array([np.cos(a) for a in angles]), np.array([np.sin(a) for a in angles])


def _star_nodes(base: NDArray, slots: NDArray, x: NDArray, mids: NDArray) -> NDArray:
    """Nodes ``(r, s, 6, 2)`` of a star's triangles (nodes ``base`` ``(s, 6, 2)``, slots
    of :class:`_Star`) with its vertex at each of ``x`` ``(r, 2)`` and its incident edges'
    middle nodes at ``mids`` ``(r, j, 2)``."""
    nodes = np.repeat(base[None], len(x), axis=0)
    nodes[:, slots == -1] = x[:, None, :]
    for k in range(mids.shape[1]):
        nodes[:, slots == k] = mids[:, k][:, None, :]
    return nodes


def _screened(
    field: MetricField, state: _State, star: _Star, v: int, cand: NDArray, rule: _Rule
) -> NDArray:
    """The :data:`SCREEN` best candidates ``(k', 2)`` of a quality move, best first, when
    each incident edge keeps its bend: from x′ to its other end o, its middle node at
    (x′ + o)/2 + α (o − x′)×e₃ (:func:`curvimesh.geodesic.parabola_midnode`) with the
    edge's present offset α (:func:`~curvimesh.geodesic.offset_alpha`). A candidate
    whose star is then valid, with its edges in the rule's bounds and its worst
    quality above the rule's, is scored as :func:`_best_move` scores it; ties go to
    the first."""
    k = len(cand)
    if k == 0:
        return cand
    mesh, pts = state.mesh, state.pts
    others = pts[star.others]
    here = np.broadcast_to(pts[v], others.shape)
    alpha = offset_alpha(here, others, pts[mesh.edge_mid[star.edges]] - 0.5 * (here + others))
    measure = _screen_compiled if field.kernel is not None else _screen_numpy
    ok, new_len, worst = measure(field, state, star, cand, others, alpha, rule)
    rows = np.flatnonzero(ok & (worst > rule.q_min))
    order = np.lexsort((rows, rule.scores(new_len[rows], worst[rows])))
    return cand[rows[order[:SCREEN]]]


def _screen_numpy(
    field: MetricField,
    state: _State,
    star: _Star,
    cand: NDArray,
    others: NDArray,
    alpha: NDArray,
    rule: _Rule,
) -> tuple[NDArray, NDArray, NDArray]:
    """:func:`_screened`'s measures: whether each candidate's star is valid with its
    incident edges in the rule's bounds ``(k,)``, their lengths ``(k, j)`` and the star's
    worst quality ``(k,)`` (−inf where not valid or out of bounds)."""
    k, j = len(cand), len(others)
    mesh, pts = state.mesh, state.pts
    a, b = np.repeat(cand, j, axis=0), np.tile(others, (k, 1))
    mid = parabola_midnode(a, b, np.tile(alpha, k)).reshape(k, j, 2)
    nodes = _star_nodes(pts[mesh.triangles[star.tris]], star.slots, cand, mid)
    ok = valid_exact(nodes.reshape(-1, 6, 2)).reshape(k, -1).all(axis=1)
    new_len = edge_lengths_fast(field, a, b, mid.reshape(-1, 2), remember=False).reshape(k, j)
    ok &= rule.lengths_ok(new_len)
    worst = np.full(k, -np.inf)
    worst[ok] = _worst_qualities(field, state, star, nodes[ok], new_len[ok])
    return ok, new_len, worst


def _screen_compiled(
    field: MetricField,
    state: _State,
    star: _Star,
    cand: NDArray,
    others: NDArray,
    alpha: NDArray,
    rule: _Rule,
) -> tuple[NDArray, NDArray, NDArray]:
    """:func:`_screen_numpy`'s measures in one compiled call
    (:func:`curvimesh.kernels.screen_moves`), one candidate after the other, but only
    those the screen needs: ``worst`` is −inf where a candidate cannot be among the
    :data:`SCREEN` best (its worst quality at most the rule's, or it is beaten by
    :data:`SCREEN` candidates before it), and a row of ``new_len`` is complete where
    ``ok`` holds. :func:`_screened` picks the same candidates from either."""
    k, j = len(cand), len(others)
    cm = field.kernel
    ok = np.zeros(k, dtype=bool)
    new_len = np.empty((k, j))
    worst = np.full(k, -np.inf)
    mesh = state.mesh
    t, w = gauss_rule(2, 5)
    shape, du, dv, aw = area_rule(4)
    gu, gv = _node_gradients()
    kernels.screen_moves(
        cm.g, np.ascontiguousarray(cand, dtype=float), np.ascontiguousarray(others),
        np.ascontiguousarray(alpha), state.pts[mesh.triangles[star.tris]],
        np.ascontiguousarray(star.slots), state.length[mesh.tri_edges[star.tris]],
        t, w, shape, du, dv, aw, gu, gv, VALID_RTOL, rule.shortest, rule.longest,
        rule.q_min, rule.push, SCREEN, ok, new_len, worst,
    )  # fmt: skip
    return ok, new_len, worst


@lru_cache(maxsize=1)
def _node_gradients() -> tuple[NDArray, NDArray]:
    """The u and v derivatives ``(6, 6)`` of the shape functions at the six nodes."""
    grad = p2_shape_grad(REFERENCE_NODES)
    return np.ascontiguousarray(grad[:, :, 0]), np.ascontiguousarray(grad[:, :, 1])


def _worst_qualities(
    field: MetricField, state: _State, star: _Star, nodes: NDArray, new_len: NDArray
) -> NDArray:
    """The worst quality (4) ``(r,)`` of a star with nodes ``(r, s, 6, 2)`` and incident
    edges' lengths ``(r, j)``, its other edges keeping theirs."""
    r = len(nodes)
    if r == 0:
        return np.empty(0)
    inc = star.slots[:, 3:]  # (s, 3): incident edge k, or −2
    lens = np.repeat(state.length[state.mesh.tri_edges[star.tris]][None], r, axis=0)
    lens[:, inc >= 0] = new_len[:, inc[inc >= 0]]
    areas = metric_areas(field, nodes.reshape(-1, 6, 2), remember=False)
    return quality_from(areas, lens.reshape(-1, 3)).reshape(r, -1).min(axis=1)


def _best_move(
    field: MetricField, state: _State, star: _Star, v: int, cand: NDArray, rule: _Rule
) -> tuple[NDArray, NDArray, NDArray, NDArray] | None:
    """The best admissible position of v among ``cand`` (module docstring, ``rule``):
    v's new position, its incident edges' new middle nodes ``(j, 2)`` and lengths
    ``(j,)``, and the star's qualities ``(s,)``; None if there is none.

    Each incident edge's shortest parabola is searched from each candidate; its
    middle node is backtracked towards the straight one (:data:`BACKTRACK`) until the
    star is valid; the four best moves by the rule's score are measured exactly
    (lengths and areas to :data:`~curvimesh.quality.REPORT_RTOL`), the first that
    keeps the rule is made. With a compiled metric, in one call
    (:func:`curvimesh.kernels.best_move`; the searches too when they are fewer than
    :data:`~curvimesh.kernels.SEARCH_PARALLEL_ROWS`, else on all threads before it),
    otherwise in numpy (:func:`_best_move_numpy`): the same arithmetic.
    """
    k, j = len(cand), len(star.edges)
    if k == 0:
        return None
    pts = state.pts
    others = pts[star.others]
    cm = field.kernel
    # the candidates' pairs seldom come again: searched and measured without the memo;
    # a compiled move of few rows searches them itself (with the same search)
    search = cm is not None and k * j < kernels.SEARCH_PARALLEL_ROWS
    if search:
        optimal = np.empty((k, j, 2))
    else:
        a, b = np.repeat(cand, j, axis=0), np.tile(others, (k, 1))
        optimal = shortest_parabola(field, a, b, exact_length=False, remember=False, guided=True)
        optimal = optimal.mid.reshape(k, j, 2)
    if cm is None:
        return _best_move_numpy(field, state, star, cand, others, optimal, rule)
    mesh = state.mesh
    s = len(star.tris)
    mids, exact, q = np.empty((j, 2)), np.empty(j), np.empty(s)
    t, w = gauss_rule(2, 5)
    gu, gv = _node_gradients()
    i = kernels.best_move(
        cm.g, cm.gd, np.ascontiguousarray(cand, dtype=float), np.ascontiguousarray(others),
        search, search_grid(SEARCH_ALPHA_MAX, SEARCH_SCAN), SEARCH_TOL, SEARCH_MAX_ITER,
        np.ascontiguousarray(optimal), pts[mesh.triangles[star.tris]],
        np.ascontiguousarray(star.slots), state.length[mesh.tri_edges[star.tris]],
        _backtrack(), t, w, gu, gv, VALID_RTOL, *area_rule(4), child_shape(),
        *area_rule(8), *doubling_rules(LENGTH_ORDER, LENGTH_MAX_SEGMENTS), REPORT_RTOL,
        AREA_MAX_LEVEL, rule.shortest, rule.longest, rule.q_min, rule.by_quality, rule.push,
        state.improve_below + REMEASURE_MARGIN, mids, exact, q,
    )  # fmt: skip
    return None if i < 0 else (cand[i], mids, exact, q)


@lru_cache(maxsize=1)
def _backtrack() -> NDArray:
    """:data:`BACKTRACK` as an array (cached; do not modify)."""
    return np.array(BACKTRACK, dtype=float)


def _best_move_numpy(
    field: MetricField,
    state: _State,
    star: _Star,
    cand: NDArray,
    others: NDArray,
    optimal: NDArray,
    rule: _Rule,
) -> tuple[NDArray, NDArray, NDArray, NDArray] | None:
    """:func:`_best_move` after the searches (the shortest parabolas' middle nodes
    ``optimal`` ``(k, j, 2)``), in numpy."""
    k, j = len(cand), len(star.edges)
    mesh, pts, length = state.mesh, state.pts, state.length
    a = np.repeat(cand, j, axis=0)
    b = np.tile(others, (k, 1))
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
        nodes = _star_nodes(base, star.slots, cand[rows], mid)  # (r, s, 6, 2)
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
        if rule.by_quality:
            worst = _worst_qualities(field, state, star, nodes[good], new_len[good])
            if rule.push >= 0:  # only the moves keeping the quality push
                good, worst = good[worst > rule.q_min], worst[worst > rule.q_min]
            score = rule.scores(new_len[good], worst)
        else:
            score = new_len[good].max(axis=1)
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
        q = qualities(field, nodes, lens, aim=state.improve_below)
        if rule.quality_ok(q):
            return cand[i], mids, exact, q
    return None
