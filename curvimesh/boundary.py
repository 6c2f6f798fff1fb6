"""The 1D mesh of the box boundary: quasi-unit edges in the metric.

Each side of the box is split into n segments of equal metric length
(measured along the side, which stays straight), n = max(1, round(L / target)).
The P2 node of a boundary edge is the point of its side that halves the
edge's metric length (paper section 3 starts Algorithm 1 from this 1D mesh).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from curvimesh.geodesic import shortest_parabola
from curvimesh.metric import MetricField


@dataclass(frozen=True)
class BoundaryMesh:
    """Boundary vertices ``(nv, 2)``, counter-clockwise from (xmin, ymin), and
    for each boundary edge (vertex k → k+1, cyclic) its P2 node ``(nv, 2)`` and side 0..3
    (bottom, right, top, left); ``seeds`` ``(ns, 2)``, interior points placed with the
    boundary (the column of a cone point, :func:`cone_design`), before sampling."""

    vertices: NDArray
    midnodes: NDArray
    sides: NDArray
    seeds: NDArray = field(default_factory=lambda: np.zeros((0, 2)))


def corner_edge_lengths(
    field: MetricField, *, target: float, min_dist: float, max_length: float
) -> NDArray:
    """Metric length ``(4,)`` of the two boundary edges at each corner (0..3 from (xmin, ymin)).

    At a corner whose angle is acute in the metric, two edges of length
    ``target`` end closer than ``min_dist`` to each other. With M = g(corner)
    and û, ŵ the unit (in M) directions of the two sides leaving the corner,
    the edge ends are ℓ|û − ŵ|_M apart, so the edges get the length
    ℓ = min_dist / |û − ŵ|_M, at least ``target`` and (infinite when the
    cap applies) at most ``max_length``; a corner that needs more gets the
    staggered vertices of :func:`wedge_distances` instead.
    """
    g, _ = _corner_frames(field)
    out = np.empty(4)
    for k, (u, w) in enumerate(_corner_sides(field)):
        u = u / np.sqrt(u @ g[k] @ u)
        w = w / np.sqrt(w @ g[k] @ w)
        gap = float(np.sqrt((u - w) @ g[k] @ (u - w)))
        # 2% margin: the metric varies over the corner's two edges
        out[k] = min(max(target, 1.02 * min_dist / gap), max_length)
    return out


def _corner_frames(field: MetricField) -> tuple[NDArray, NDArray]:
    """The metric ``(4, 2, 2)`` at the box corners and the corners ``(4, 2)``."""
    xmin, ymin, xmax, ymax = field.box
    corners = np.array([[xmin, ymin], [xmax, ymin], [xmax, ymax], [xmin, ymax]])
    return field.tensor(corners), corners


def _corner_sides(field: MetricField) -> list[tuple[NDArray, NDArray]]:
    """For each corner k, the two sides leaving it: towards corner k+1, towards corner k−1."""
    _, c = _corner_frames(field)
    return [(c[(k + 1) % 4] - c[k], c[(k - 1) % 4] - c[k]) for k in range(4)]


def corner_angles(field: MetricField) -> NDArray:
    """The angle ``(4,)`` between the two sides at each box corner, in the metric there.

    cos θ = uᵀMw / (|u|_M |w|_M) for the side directions u, w and M = g(corner).
    """
    g, _ = _corner_frames(field)
    out = np.empty(4)
    for k, (u, w) in enumerate(_corner_sides(field)):
        cos = (u @ g[k] @ w) / np.sqrt((u @ g[k] @ u) * (w @ g[k] @ w))
        out[k] = float(np.arccos(np.clip(cos, -1.0, 1.0)))
    return out


def wedge_distances(
    theta: float,
    *,
    target: float = 1.0,
    min_dist: float = 0.7,
    max_length: float = 1.5,
    margin: float = 0.005,
    tries: int = 64,
) -> tuple[NDArray, NDArray] | None:
    """Staggered boundary vertices near a corner of angle θ: metric distances from it.

    Returns the distances along the first side and along the second, or None
    when no staggering meets the bounds. In the corner's metric the two sides
    are rays at the angle θ; a vertex at distance s on one and one at t on
    the other are c(s, t) = sqrt(s² + t² − 2st cos θ) apart (law of cosines),
    so near a sharp corner two vertices facing each other would make a short
    edge. The vertices alternate between the sides instead,
    0 = t₀ < t₁ < t₂ < … (odd ones on the first side, even ones on the
    second), each one as close to the target spacing as the bounds allow:
    t_{k+1} = max(t_{k−1} + target, the smallest t with c(t_k, t) ≥ ℓ_min),
    with ℓ_min = min_dist (1 + margin). Then each triangle of the zigzag
    (t_{k−1}, t_k, t_{k+1}) has two cross edges of at least ℓ_min and a side
    edge t_{k+1} − t_{k−1}, which must not exceed max_length / (1 + margin).
    Solving c(s, t) = ℓ for t gives t = s cos θ + sqrt(ℓ² − s² sin² θ) while
    s sin θ < ℓ (beyond, the other side is ℓ away and any t will do). The
    first distance t₁ is the one of ``tries`` values from target down to ℓ_min
    whose longest side edge is shortest (the first such); the staggering ends once the
    sides are ℓ_min apart at both last vertices (s sin θ ≥ ℓ_min), where a
    regular spacing cannot make a short cross edge. A feasible t₁ exists for
    every θ > 0 when max_length ≥ 2 min_dist (with t₁ = min_dist, t₂ ≈ 2 min_dist
    for small θ), which is why a corner needs no edge shorter than min_dist.
    """
    lo = min_dist * (1.0 + margin)
    hi = max_length / (1.0 + margin)
    sin, cos = math.sin(theta), math.cos(theta)
    if sin <= 0.0:
        return None

    def t_cross(s: float) -> float:
        if s * sin >= lo:
            return s
        return s * cos + math.sqrt(lo * lo - (s * sin) ** 2)

    def next_distance(seq: list[float]) -> float | None:
        if seq[-1] * sin >= lo and seq[-2] * sin >= lo:
            return None
        return max(seq[-2] + target, t_cross(seq[-1]))

    best = _best_staggering(np.linspace(max(target, lo), lo, tries), hi, next_distance)
    if best is None:
        return None
    return np.array(best[1::2]), np.array(best[2::2])


def _best_staggering(firsts: NDArray, hi: float, next_distance) -> list[float] | None:
    """The staggering 0 = t₀ < t₁ < … whose longest side edge t_{k+1} − t_{k−1} (or t₁)
    is shortest, over the first distances ``firsts`` (the first such), or None.

    ``next_distance(seq)`` gives the distance that follows ``seq`` (inf when there is
    none), or None once the staggering may end; a staggering with a side edge longer
    than ``hi`` is dropped.
    """
    best, best_edge = None, math.inf
    for t1 in firsts:
        seq, edge = [0.0, float(t1)], float(t1)
        while edge <= hi:
            t = next_distance(seq)
            if t is None:
                break
            edge = max(edge, t - seq[-2])
            seq.append(t)
        if edge <= hi and edge < best_edge:
            best, best_edge = seq, edge
    return best


#: Margins tried in turn for a corner's staggering, until its cross edges pass in the metric.
WEDGE_MARGINS = (0.005, 0.02, 0.05, 0.1, 0.2)


def refined_arclength(
    field: MetricField,
    a: NDArray,
    b: NDArray,
    *,
    per_unit: int = 64,
    start: int = 256,
    max_cells: int = 2_000_000,
    max_rounds: int = 12,
) -> tuple[NDArray, NDArray]:
    """Cumulative metric length along the segment a→b on cells of at most 1/``per_unit``
    of metric length each: parameters s ``(k,)`` in [0, 1] and lengths ``(k,)``.

    Starts from ``start`` equal cells, integrates each with 3-point
    Gauss–Legendre, and splits every cell longer than 1/``per_unit`` into
    ⌈``per_unit`` × length⌉ equal ones, until none is (at most ``max_rounds``
    times, ``max_cells`` cells). Equal cells are not enough where the metric
    varies fast along the side: a wall layer of size 8e-5 growing to 0.08
    within 0.3 puts 3 units of length into the first of 1,600 equal cells of
    its side, and linear interpolation inside that cell placed boundary
    vertices 0.58 and 1.59 apart.

    >>> from curvimesh.metric import load_metric_text
    >>> fld = load_metric_text("metric: {isotropic: '0.01 + x'}")
    >>> s, cum = refined_arclength(fld, np.array([0.0, 0.0]), np.array([1.0, 0.0]))
    >>> bool(abs(cum[-1] - np.log(101.0)) < 1e-9), bool(np.diff(cum).max() <= 1 / 64)
    (True, True)
    """
    xg, wg = np.polynomial.legendre.leggauss(3)
    d = b - a

    def cell_lengths(s: NDArray) -> NDArray:
        h = np.diff(s)
        t = (s[:-1, None] + h[:, None] * (xg[None, :] + 1) / 2).ravel()
        g = field.tensor(a[None, :] + t[:, None] * d[None, :])
        speed = np.sqrt(np.einsum("i,pij,j->p", d, g, d)).reshape(len(h), 3)
        return (speed @ wg) * h / 2

    s = np.linspace(0.0, 1.0, start + 1)
    cell = cell_lengths(s)
    for _ in range(max_rounds):
        parts = np.maximum(1, np.ceil(cell * per_unit)).astype(np.int64)
        if (parts == 1).all() or parts.sum() > max_cells:
            break
        # cell i becomes parts[i] equal cells: s_i + (j / parts[i]) h_i, j = 0..parts[i]−1
        h = np.diff(s)
        first = np.repeat(np.cumsum(parts) - parts, parts)
        j = np.arange(parts.sum()) - first
        cell_of = np.repeat(np.arange(len(h)), parts)
        s = np.append(s[:-1][cell_of] + h[cell_of] * j / parts[cell_of], 1.0)
        cell = cell_lengths(s)
    return s, np.concatenate([[0.0], np.cumsum(cell)])


def _side_tables(field: MetricField) -> list[tuple[NDArray, NDArray]]:
    """For each side k (corner k → corner k+1): parameters and cumulative metric lengths,
    on cells of at most 1/64 of metric length (:func:`refined_arclength`)."""
    _, corners = _corner_frames(field)
    return [refined_arclength(field, corners[k], corners[(k + 1) % 4]) for k in range(4)]


def _at_distance(field: MetricField, tables, side: int, dist: NDArray, backwards: bool) -> NDArray:
    """Points ``(n, 2)`` of side ``side`` at metric distances from its first (or last) corner."""
    _, corners = _corner_frames(field)
    s, cum = tables[side]
    a, b = corners[side], corners[(side + 1) % 4]
    t = np.interp(cum[-1] - dist if backwards else dist, cum, s)
    return a[None, :] + t[:, None] * (b - a)[None, :]


def _wedges(
    field: MetricField, tables, target: float, min_dist: float, max_length: float
) -> list[tuple[NDArray, NDArray] | None]:
    """Staggered distances at each corner whose symmetric edges would exceed 1.4 × target.

    :func:`wedge_distances` works in the metric of the corner; the cross edges
    are then measured in the field (shortest parabolas, as the edges will be
    curved). Where the field makes some shorter than ``min_dist`` (it varies
    over the few units the staggering spans), the staggering is designed again
    for a narrower angle θ' = θ · r (r < 1 the shortfall of the shortest cross
    edge, over the design's ℓ_min): cross edges grow about linearly with the
    angle near a sharp corner, and the side edges are placed exactly in the
    field, so only the cross edges move. The margin is widened
    (:data:`WEDGE_MARGINS`) when that does not converge.
    """
    need = corner_edge_lengths(field, target=target, min_dist=min_dist, max_length=np.inf)
    theta = corner_angles(field)
    out: list[tuple[NDArray, NDArray] | None] = [None] * 4
    for k in np.flatnonzero(need > 1.4 * target):
        out[k] = _wedge(field, tables, int(k), float(theta[k]), target, min_dist, max_length)
    return out


#: Designs tried per margin, narrowing the angle after each one with short cross edges.
WEDGE_REDESIGNS = 8


def _wedge(
    field: MetricField,
    tables,
    k: int,
    theta: float,
    target: float,
    min_dist: float,
    max_length: float,
) -> tuple[NDArray, NDArray] | None:
    """The staggering at corner ``k`` whose cross edges pass in the field (see :func:`_wedges`).

    A design that would not fit in half of the shorter side ends the redesigns: each
    narrowing of the angle lengthens the staggering (it spans about ℓ_min / sin θ),
    and at a corner of 0.6° in a spiral layer's metric the designs grew from 478 to
    161,851 vertices in five rounds.
    """
    reach = _wedge_reach(tables, k)
    for margin in WEDGE_MARGINS:
        angle = theta
        for _ in range(WEDGE_REDESIGNS):
            w = wedge_distances(
                angle, target=target, min_dist=min_dist, max_length=max_length, margin=margin
            )
            if w is None:
                break
            if max(w[0][-1], w[1][-1]) > reach:
                return _field_wedge(field, tables, k, target, min_dist, max_length)
            shortest = float(_cross_lengths(field, tables, k, w).min())
            if shortest >= min_dist:
                return w
            angle *= 0.98 * shortest / (min_dist * (1.0 + margin))
    return _field_wedge(field, tables, k, target, min_dist, max_length)


def _wedge_reach(tables, k: int) -> float:
    """Half the metric length of the shorter side at corner ``k``: the farthest a
    staggering of that corner may reach along either side."""
    return 0.5 * min(tables[k][1][-1], tables[(k - 1) % 4][1][-1])


def _cross_lengths(
    field: MetricField, tables, k: int, w: tuple[NDArray, NDArray], *, remember: bool = True
) -> NDArray:
    """Shortest-parabola lengths of the cross edges of the staggering ``w`` at corner ``k``
    (distances along its first side and along its second): between consecutive vertices
    of the merged order a1, b1, a2, b2, …, which lie on opposite sides."""
    first = _at_distance(field, tables, k, w[0], backwards=False)
    second = _at_distance(field, tables, (k - 1) % 4, w[1], backwards=True)
    merged = np.empty((len(first) + len(second), 2))
    merged[0::2], merged[1::2] = first, second
    return shortest_parabola(field, merged[:-1], merged[1:], remember=remember).length


#: Spacing (metric length along a side) of the candidate vertices of :func:`_field_wedge`.
FIELD_WEDGE_STEP = 0.02


def _field_wedge(
    field: MetricField,
    tables,
    k: int,
    target: float,
    min_dist: float,
    max_length: float,
    *,
    margin: float = 0.005,
    tries: int = 16,
) -> tuple[NDArray, NDArray] | None:
    """The staggering of :func:`wedge_distances` with its cross edges measured in the field.

    The corner's metric can misjudge every design: where the field turns or
    shrinks over the few units the staggering spans, narrowing the design's
    angle leaves its first cross edge about ℓ_min long in the corner's metric
    and short in the field (0.61 at a corner of 22°, seen in a hypothesis
    run). The same greedy rule is run here with c(s, t) the shortest-parabola
    length in the field between the vertex at metric distance s from the
    corner on one side and the one at t on the other: t_{k+1} is the larger of
    t_{k−1} + target and the smallest candidate beyond which every candidate
    of the other side is at least ℓ_min from t_k. Candidates are
    :data:`FIELD_WEDGE_STEP` apart; the staggering ends once both last
    vertices are ℓ_min from every candidate of the other side from ``max_length``
    before the previous vertex up to the reach of the next edge. The candidates
    are measured by the search's rule, the chosen staggering's cross edges to
    1e-5. The first distance is chosen among ``tries`` values as in
    :func:`wedge_distances`. None when no staggering fits in half of the shorter
    side or within ``max_length``, or when a cross edge of the chosen one is short.
    """
    lo = min_dist * (1.0 + margin)
    hi = max_length / (1.0 + margin)
    sides = (k, (k - 1) % 4)  # odd entries of the sequence on the first, even on the second
    reach = _wedge_reach(tables, k)

    def point(side: int, dist: NDArray) -> NDArray:
        return _at_distance(field, tables, sides[side], dist, backwards=side == 1)

    def crosses(side: int, s: float, grid: NDArray) -> NDArray:
        """Lengths from the vertex at s on ``side`` to the candidates on the other side."""
        a = np.repeat(point(side, np.array([s])), len(grid), axis=0)
        b = point(1 - side, grid)
        return shortest_parabola(field, a, b, exact_length=False, remember=False).length

    far: list[bool] = []  # of each vertex of the staggering being made, the corner's False

    def next_distance(seq: list[float]) -> float | None:
        if len(seq) == 2:
            far[:] = [False]
        side = (len(seq) - 2) % 2  # of the last vertex: 0 = first side
        first = max(0.0, FIELD_WEDGE_STEP * math.floor((seq[-2] - hi) / FIELD_WEDGE_STEP))
        grid = np.arange(first, seq[-2] + hi + FIELD_WEDGE_STEP, FIELD_WEDGE_STEP)
        if grid[-1] > reach:
            return math.inf
        c = crosses(side, seq[-1], grid)
        far.append(bool(c.min() >= lo))
        if far[-1] and far[-2]:
            return None
        after = np.flatnonzero((c < lo) | (grid <= seq[-2]))[-1] + 1  # grid[0] is in
        return max(seq[-2] + target, float(grid[after]) if after < len(grid) else math.inf)

    best = _best_staggering(np.linspace(max(target, lo), lo, tries), hi, next_distance)
    if best is None:
        return None
    w = np.array(best[1::2]), np.array(best[2::2])
    if _cross_lengths(field, tables, k, w, remember=False).min() < min_dist:
        return None
    return w


#: Lengthenings tried at a corner whose cross edge the field makes short.
CORNER_RETRIES = 8


def _checked_corner(
    field: MetricField, tables, k: int, length: float, bounds: tuple[float, float, float]
) -> tuple[float, tuple[NDArray, NDArray] | None]:
    """The corner edge length at corner ``k``, its cross edge measured in the field.

    :func:`corner_edge_lengths` works in the metric of the corner; over the
    corner's two edges the field can shorten the cross edge between their far
    ends below ``min_dist`` (0.678 at a corner of 36°, seen in a hypothesis
    run). The edges are then lengthened by the shortfall (and 2 %), up to
    ``max_length``; a corner that needs more gets the staggering of
    :func:`_wedge` (None if that fails too). Returns the length and the
    staggering (None when plain edges do).
    """
    target, min_dist, max_length = bounds
    for _ in range(CORNER_RETRIES):
        first = _at_distance(field, tables, k, np.array([length]), backwards=False)
        second = _at_distance(field, tables, (k - 1) % 4, np.array([length]), backwards=True)
        cross = float(shortest_parabola(field, first, second).length[0])
        if cross >= min_dist:
            return length, None
        length *= 1.02 * min_dist / cross
        if length > max_length:
            break
    angle = float(corner_angles(field)[k])
    wedge = _wedge(field, tables, k, angle, target, min_dist, max_length)
    return min(length, max_length), wedge


def discretize_box(
    field: MetricField, *, target: float = 1.0, min_dist: float = 0.7, max_length: float = 1.5
) -> BoundaryMesh:
    """Split the four sides into quasi-unit edges of metric length ≈ ``target``.

    The edges at a corner that is acute in the metric are lengthened so that
    the first vertices of the two sides are at least ``min_dist`` apart (see
    :func:`corner_edge_lengths`); where that would take edges longer than
    1.4 × target, the vertices near the corner are staggered between its two
    sides instead (:func:`wedge_distances`). At a cone point of a side
    (:func:`side_cones`) the vertices and a column of interior seeds follow
    :func:`cone_design`. The rest of each side is split evenly.
    """
    _, corners = _corner_frames(field)
    at_corner = corner_edge_lengths(field, target=target, min_dist=min_dist, max_length=max_length)
    tables = _side_tables(field)
    wedges = _wedges(field, tables, target, min_dist, max_length)
    for k in range(4):
        if wedges[k] is None:
            at_corner[k], wedges[k] = _checked_corner(
                field, tables, k, float(at_corner[k]), (target, min_dist, max_length)
            )
    verts, mids, sides, seeds = [], [], [], []
    for k in range(4):
        a, b = corners[k], corners[(k + 1) % 4]
        s, cum = tables[k]
        total = cum[-1]
        ends = (at_corner[k], at_corner[(k + 1) % 4], wedges[k], wedges[(k + 1) % 4])
        cones = [
            (pos, cone_design(angle, min_dist=min_dist))
            for pos, angle in side_cones(field, tables, k, target=target)
        ]
        targets, kept = _cone_targets(total, target, ends, [(p, d[0]) for p, d in cones])
        seeds += [_cone_seeds(field, tables, k, cones[i][0], cones[i][1][1]) for i in kept]
        t = np.interp(targets, cum, s)
        tm = np.interp(0.5 * (targets[:-1] + targets[1:]), cum, s)
        verts.append(a[None, :] + t[:-1, None] * (b - a)[None, :])
        mids.append(a[None, :] + tm[:, None] * (b - a)[None, :])
        sides.append(np.full(len(t) - 1, k))
    return BoundaryMesh(
        np.concatenate(verts),
        np.concatenate(mids),
        np.concatenate(sides),
        np.concatenate(seeds) if seeds else np.zeros((0, 2)),
    )


#: A side point whose two side points one unit away on either side are closer than
#: this across the domain (shortest parabola) is tried as a cone point: the metric's
#: angle there below 2 asin(1/2) = 60°.
CONE_CROSS = 1.0

#: Spacing of the scan for cone points along a side (metric length).
CONE_SCAN = 0.5


def _cross(field: MetricField, tables, k: int, pos: NDArray, rho: float) -> NDArray:
    """Shortest-parabola lengths ``(n,)`` between the points of side ``k`` at metric
    distances pos − rho and pos + rho from its first corner."""
    left = _at_distance(field, tables, k, pos - rho, backwards=False)
    right = _at_distance(field, tables, k, pos + rho, backwards=False)
    return shortest_parabola(field, left, right, exact_length=False, remember=False).length


def side_cones(
    field: MetricField, tables, k: int, *, target: float = 1.0
) -> list[tuple[float, float]]:
    """Cone points of side ``k``: (metric distance from its first corner, angle).

    Where the metric is singular at a point P of a side (concentric circles
    centred on it, say: polar sizes h_r across and h_t along the circles), the
    domain about P is a cone in the metric, of angle θ = π h_r / h_t at the
    side's point: side points at distance ρ on either side of P are 2ρ sin(θ/2)
    apart across the domain, not 2ρ. A vertex at P has both its side edges
    straight along the side, at 180° in the plane: no P2 triangle there is valid
    with P as its only corner on that side, and any split of θ into two
    triangles makes both thin. The sides are scanned (:data:`CONE_SCAN`, two
    units ``target`` from the corners) for points whose side points at ±1 are
    closer than :data:`CONE_CROSS` across the domain, the closest point of each
    run refined to 1/50 of a unit; it is a cone point when the ratio of that
    distance to 2ρ is the same at ρ = 1/4 (within 20 %): a metric that is
    only strongly curved near the side (a singular point inside the domain, a
    front) straightens out at smaller ρ. The angle is :func:`_cone_angle`'s.
    """
    total = float(tables[k][1][-1])
    rho = target
    pos = np.arange(rho + target, total - rho - target, CONE_SCAN * target)
    if len(pos) == 0:
        return []
    cross = _cross(field, tables, k, pos, rho)
    low = np.flatnonzero(cross < CONE_CROSS * rho)
    out: list[tuple[float, float]] = []
    for run in np.split(low, np.flatnonzero(np.diff(low) > 1) + 1):
        if run.size == 0:
            continue
        c = pos[run[np.argmin(cross[run])]]
        fine = np.linspace(c - CONE_SCAN * target, c + CONE_SCAN * target, 51)
        fine = fine[(fine > rho) & (fine < total - rho)]
        fc = _cross(field, tables, k, fine, rho)
        best = int(np.argmin(fc))
        p, ratio = float(fine[best]), float(fc[best]) / (2 * rho)
        small = float(_cross(field, tables, k, np.array([p]), 0.25 * rho)[0]) / (0.5 * rho)
        if np.isfinite(ratio) and abs(small - ratio) <= 0.2 * ratio:
            out.append((p, _cone_angle(field, tables, k, p, rho)))
    return out


def _inward(
    field: MetricField, tables, k: int, pos: float
) -> tuple[NDArray, NDArray, NDArray, float]:
    """The point of side ``k`` at metric distance ``pos`` from its first corner, the
    side's unit tangent and inward normal there, and the box's depth along it."""
    p = _at_distance(field, tables, k, np.array([pos]), backwards=False)[0]
    _, corners = _corner_frames(field)
    a, b = corners[k], corners[(k + 1) % 4]
    t = (b - a) / np.hypot(*(b - a))
    xmin, ymin, xmax, ymax = field.box
    depth = (ymax - ymin) if k % 2 == 0 else (xmax - xmin)
    return p, t, np.array([-t[1], t[0]]), depth  # counter-clockwise: the box on the left


def _cone_angle(field: MetricField, tables, k: int, pos: float, radius: float) -> float:
    """The angle of the cone point at ``pos`` of side ``k``: the metric length of the
    half circle about it that reaches metric distance ``radius`` along the inward
    normal, over ``radius`` (circumference over radius, exact for concentric
    circles centred there: π h_r / h_t; the shortest parabolas across the cone
    bend too little to measure it)."""
    p, t, n, depth = _inward(field, tables, k, pos)
    s, cum = refined_arclength(field, p, p + depth * n)
    r = float(np.interp(radius, cum, s)) * depth
    phi = np.linspace(0.0, math.pi, 513)
    arc = p[None, :] + r * (np.cos(phi)[:, None] * t[None, :] + np.sin(phi)[:, None] * n[None, :])
    d = np.diff(arc, axis=0)
    g = field.tensor(0.5 * (arc[1:] + arc[:-1]))
    return float(np.sqrt(np.einsum("pi,pij,pj->p", d, g, d)).sum()) / radius


def cone_design(angle: float, *, min_dist: float = 0.7) -> tuple[NDArray, NDArray]:
    """Side vertices and seeds about a cone point of angle θ: their metric distances
    from it, (side distances, on both sides, ascending; seed distances on its
    bisector).

    No vertex at the cone point: the side edge across it is 2 min_dist long
    (its vertices at ±min_dist), then edges of 2 min_dist on both sides, and
    seeds on the bisector at 2 min_dist, 4 min_dist, … while the cone is narrower
    than 2 min_dist there (2ρ sin(θ/2) < 2 min_dist). In the cone, unfolded
    flat, a seed X at ρ = 2 min_dist is min_dist from the side vertices at
    min_dist (law of cosines, for θ ≤ 60°) and farther from those at 3 min_dist;
    the triangles across the cone point and beside it have edges of 2 min_dist
    and about min_dist (θ = 18°: 1.4, 0.74, 0.74, quality 0.35).
    """
    step = 2.0 * min_dist
    width = min_dist / max(math.sin(0.5 * angle), 1e-12)  # where the cone is `step` wide
    count = max(1, int(width // step))
    seeds = step * np.arange(1, count + 1)
    sides = min_dist + step * np.arange(count + 1)
    return sides, seeds


def _cone_targets(
    total: float, target: float, ends: tuple, cones: list[tuple[float, NDArray]]
) -> tuple[NDArray, list[int]]:
    """Metric distances ``(n + 1,)`` of a side's vertices from its first corner (both
    ends in, as :func:`_side_targets`) with the vertices ``pos ± design`` of each cone
    point ``(pos, design)`` (ascending ``pos``), and which cones are kept: one whose
    vertices come within two units of a corner or of the cone before is left out.
    The stretches between are split as :func:`_side_targets` splits a side."""
    first, last, wedge_a, wedge_b = ends
    blocks: list[NDArray] = []
    kept: list[int] = []
    edge = 0.0  # where the last block ends (0: the first corner)
    for i, (pos, design) in enumerate(cones):
        reach = float(design[-1])
        if pos - reach - edge < 2.0 * target or total - (pos + reach) < 2.0 * target:
            continue
        blocks.append(np.concatenate([pos - design[::-1], pos + design]))
        kept.append(i)
        edge = pos + reach
    if not blocks:
        return _side_targets(total, target, first, last, wedge_a, wedge_b), kept
    parts = [_side_targets(blocks[0][0], target, first, target, wedge_a, None)[:-1]]
    for before, after in itertools.pairwise(blocks):
        gap = after[0] - before[-1]
        parts += [before, before[-1] + _plain_targets(gap, target, target, target)[1:-1]]
    end = blocks[-1][-1]
    tail = end + _side_targets(total - end, target, target, last, None, wedge_b)
    return np.concatenate([*parts, blocks[-1], tail[1:]]), kept


def _cone_seeds(field: MetricField, tables, k: int, pos: float, dist: NDArray) -> NDArray:
    """Seeds ``(n, 2)`` at metric distances ``dist`` from the cone point at ``pos`` of
    side ``k``, on the perpendicular to the side into the box (its straight length)."""
    p, _, n, depth = _inward(field, tables, k, pos)
    s, cum = refined_arclength(field, p, p + depth * n)
    h = np.interp(dist, cum, s)
    return p[None, :] + h[:, None] * (depth * n)[None, :]


def _side_targets(
    total: float,
    target: float,
    first: float,
    last: float,
    wedge_a: tuple[NDArray, NDArray] | None,
    wedge_b: tuple[NDArray, NDArray] | None,
) -> NDArray:
    """Metric distances ``(n + 1,)`` from the side's first corner of its vertices, both ends in.

    A side leaves its first corner as that corner's first side and reaches
    its second corner as that corner's second side (both counter-clockwise).
    """
    if wedge_a is None and wedge_b is None:
        return _plain_targets(total, target, first, last)
    head = wedge_a[0] if wedge_a is not None else np.array([first])
    tail = total - wedge_b[1][::-1] if wedge_b is not None else np.array([total - last])
    lo, hi = head[-1], tail[0]
    if hi - lo < 0.7 * target:  # the two corners' vertices meet: no room for staggering
        return _plain_targets(total, target, first, last)
    n = max(1, round((hi - lo) / target))
    return np.concatenate([[0.0], head, np.linspace(lo, hi, n + 1)[1:-1], tail, [total]])


def _plain_targets(total: float, target: float, first: float, last: float) -> NDArray:
    """The side split evenly, after edges of length ``first`` and ``last`` at its ends."""
    rest = total - first - last
    if (first == target and last == target) or rest < 0.5 * target:
        n = max(1, round(total / target))
        return np.linspace(0.0, total, n + 1)
    n = max(1, round(rest / target))
    return np.concatenate([[0.0], first + np.linspace(0.0, rest, n + 1), [total]])


def halving_points(field: MetricField, a: NDArray, b: NDArray, *, cells: int = 64) -> NDArray:
    """The point of each straight segment a→b that halves its metric length ``(n, 2)``.

    The cumulative length is integrated with 3-point Gauss–Legendre on
    ``cells`` equal cells per segment and inverted by linear interpolation.
    """
    a = np.asarray(a, dtype=float).reshape(-1, 2)
    b = np.asarray(b, dtype=float).reshape(-1, 2)
    xg, wg = np.polynomial.legendre.leggauss(3)
    h = 1.0 / cells
    t = (np.arange(cells)[:, None] * h + h * (xg[None, :] + 1) / 2).ravel()
    d = b - a
    pts = a[:, None, :] + t[None, :, None] * d[:, None, :]
    g = field.tensor(pts.reshape(-1, 2)).reshape(len(a), len(t), 2, 2)
    speed = np.sqrt(np.einsum("pi,pkij,pj->pk", d, g, d)).reshape(len(a), cells, 3)
    cum = np.concatenate([np.zeros((len(a), 1)), np.cumsum(speed @ (wg * h / 2), axis=1)], axis=1)
    half = 0.5 * cum[:, -1:]
    k = np.clip((cum < half).sum(axis=1) - 1, 0, cells - 1)
    rows = np.arange(len(a))
    c0, c1 = cum[rows, k], cum[rows, k + 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(c1 > c0, (half[:, 0] - c0) / (c1 - c0), 0.5)
    s = (k + frac) * h
    return a + s[:, None] * d
