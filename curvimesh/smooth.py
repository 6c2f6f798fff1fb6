"""Vertex relocation: moving vertices to even out their edge lengths in the metric.

The paper places its points once and only swaps edges; its conclusion
leaves "other mesh optimizations" to further work. This stage moves every
interior vertex of the straight mesh towards the place where its edges would
be unit: for an edge i–j of metric length L (its shortest parabola, paper
eq. (3)) the point p_j + (p_i − p_j) / L would make it unit if the metric were
constant along it, and the vertex goes, by a relaxation factor, towards the
average of these points over its edges (the "spring" relocation of
Bossen & Heckbert 1996, in the metric). All vertices move at once (a Jacobi
sweep); a move is undone when it would invert a triangle, bring an edge
below ``min_dist``, or make an edge longer than ``max_length`` and than it
was. Between sweeps the edges are flipped back to the Delaunay triangulation
in the metric. Boundary vertices stay.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from curvimesh import kernels
from curvimesh.freenode import shortest_parabola
from curvimesh.geodesic import (
    gauss_rule,
    geodesic_alpha,
    parabola_length_rule,
    parabola_midnode,
)
from curvimesh.mesh import Mesh, carried, signed_areas
from curvimesh.metric import MetricField
from curvimesh.sampling import too_close
from curvimesh.triangulate import metric_delaunay


def _on_box(points: NDArray, box: tuple[float, float, float, float]) -> NDArray:
    xmin, ymin, xmax, ymax = box
    tol = 1e-12 * max(xmax - xmin, ymax - ymin)
    x, y = points[:, 0], points[:, 1]
    return (
        (np.abs(x - xmin) <= tol)
        | (np.abs(x - xmax) <= tol)
        | (np.abs(y - ymin) <= tol)
        | (np.abs(y - ymax) <= tol)
    )


#: The tolerance in α of the relocation's shortest-parabola searches.
ALPHA_TOL = 2e-3

#: Moved edges whose tracked length (:func:`tracked_lengths`) is below this times
#: min_dist are searched before a move is judged by them.
SEARCH_BELOW = 1.1


def edge_parabola_lengths(
    field: MetricField, points: NDArray, edges: NDArray, start: NDArray | None = None
) -> tuple[NDArray, NDArray]:
    """Lengths ``(E,)`` of the shortest parabolas of edges ``(E, 2)`` (search accuracy,
    α to :data:`ALPHA_TOL`) and their α ``(E,)``, searched from the guesses ``start``
    ``(E,)`` of α if given, else from the geodesic's bend at each chord's middle
    (:func:`geodesic_alpha`)."""
    if start is None:
        start = geodesic_alpha(field, points[edges[:, 0]], points[edges[:, 1]])
    par = shortest_parabola(
        field,
        points[edges[:, 0]],
        points[edges[:, 1]],
        scan=5,
        alpha_tol=ALPHA_TOL,
        exact_length=False,
        remember=False,  # the vertices move at every sweep
        start=start,
    )
    return par.length, par.alpha


def tracked_lengths(
    field: MetricField, points: NDArray, edges: NDArray, alpha: NDArray
) -> tuple[NDArray, NDArray]:
    """Lengths ``(E,)`` of edges ``(E, 2)`` whose ends moved a little since their shortest
    parabola's α ``alpha`` ``(E,)`` was found, and the α kept ``(E,)``: the shorter of
    the parabolas at that α and at the geodesic's bend at the chord's middle
    (:func:`geodesic_alpha`), by the search's rule (composite Gauss, 2 × 5 points).

    Not searched: each is an upper bound of the shortest parabola's length, and
    the length is stationary in α at its optimum, so a guess δ off is off by
    O(δ²). The bend alone is within 1e-3 of the optimum α at the 99th percentile
    of the three toys' edges, but can be far off where the geodesic bends hard
    (α 0.63 for 0.20, a length 1.46 times too long, on 1 edge in 10⁵); the α
    of the last sweep, at ends moved by a few hundredths, is not. Where the two
    are within the searches' tolerance (:data:`ALPHA_TOL`) they are one guess
    to the accuracy α is known with, and only the last α is measured (most
    edges: one length instead of two). With a compiled metric, in one pass
    (:func:`curvimesh.kernels.tracked_lengths`: the same bits).
    """
    cm = field.kernel
    if cm is not None:
        length, kept = np.empty(len(edges)), np.empty(len(edges))
        t, w = gauss_rule(2, 5)
        kernels.tracked_lengths(
            cm.g, cm.gd, np.ascontiguousarray(points, dtype=float),
            np.ascontiguousarray(edges, dtype=np.int64),
            np.ascontiguousarray(alpha, dtype=float), ALPHA_TOL, t, w, length, kept,
        )  # fmt: skip
        return length, kept
    a, b = points[edges[:, 0]], points[edges[:, 1]]
    bend = geodesic_alpha(field, a, b)
    bend[~np.isfinite(bend)] = 0.0
    other = np.flatnonzero(~(np.abs(bend - alpha) <= ALPHA_TOL))
    rows = np.concatenate([np.arange(len(edges)), other])
    guess = np.concatenate([alpha, bend[other]])
    ln = parabola_length_rule(field, a[rows], b[rows], parabola_midnode(a[rows], b[rows], guess))
    length, kept = ln[: len(edges)], np.array(alpha, dtype=float, copy=True)
    use_bend = ln[len(edges) :] < length[other]
    length[other[use_bend]] = ln[len(edges) :][use_bend]
    kept[other[use_bend]] = bend[other[use_bend]]
    return length, kept


def _undo_bad_moves(
    field: MetricField,
    old: NDArray,
    new: NDArray,
    moved: NDArray,
    edges: NDArray,
    tris: NDArray,
    min_dist: float,
    old_length: NDArray,
    old_alpha: NDArray,
    max_length: float = 1.4,
) -> tuple[NDArray, NDArray, NDArray]:
    """The positions ``new`` ``(n, 2)`` with the bad moves of vertices ``moved`` undone,
    and the lengths and α ``(E,)`` of ``edges`` there.

    ``old_length`` and ``old_alpha`` are the edges' lengths and α at ``old``
    (:func:`edge_parabola_lengths`). An edge touching a moved vertex is measured
    again at its new ends, from its old α (:func:`tracked_lengths`), and searched
    from there (:func:`edge_parabola_lengths`) when that is below
    :data:`SEARCH_BELOW` × ``min_dist``; a moved
    vertex goes back to ``old`` when it is a corner of a triangle of ``tris``
    that is inverted (signed area ≤ 0) or an end of such an edge that came out
    shorter than ``min_dist`` or longer than both ``max_length`` and its old length (a move
    never makes a long edge, or a long edge longer). This repeats until no
    move is undone (each pass undoes at least one, so it ends). Each pass
    re-measures only the triangles and edges at the vertices just undone: an
    edge whose ends are both back has its old length. The lengths returned
    are those the next sweep needs, so that no edge is measured twice at the
    same ends.
    """
    n = len(new)
    new = new.copy()
    length, alpha = old_length.copy(), old_alpha.copy()
    bad_e = np.zeros(len(edges), dtype=bool)
    if moved.size == 0:
        return new, length, alpha
    is_moved = np.zeros(n, dtype=bool)
    is_moved[moved] = True
    longest = np.maximum(max_length, old_length)

    def touching(rows: NDArray, mask: NDArray) -> NDArray:
        # ascending ids of the rows (of edges or triangles) with a corner in mask
        hit = mask[rows[:, 0]]
        for k in range(1, rows.shape[1]):
            hit |= mask[rows[:, k]]
        return np.flatnonzero(hit)

    def measure(rows: NDArray) -> None:
        # rows with a moved end are searched at their new ends, the others are back
        now = is_moved[edges[rows, 0]] | is_moved[edges[rows, 1]]
        back = rows[~now]
        length[back], alpha[back], bad_e[back] = old_length[back], old_alpha[back], False
        rows = rows[now]
        if rows.size == 0:
            return
        ln, al = tracked_lengths(field, new, edges[rows], old_alpha[rows])
        # a tracked length is an upper bound: near min_dist it is searched, lest a
        # stale α hide a short edge (u18, crossing fronts: 1.3 % over, a 0.691 edge)
        near = np.flatnonzero(ln < SEARCH_BELOW * min_dist)
        short = np.zeros(len(rows), dtype=bool)
        if near.size:
            ln[near], al[near] = edge_parabola_lengths(field, new, edges[rows[near]], al[near])
            # the search stops within ALPHA_TOL of the best α, and in a thin layer the
            # length's valley in α is narrower (u51, seed 2: an edge searched at 0.70008
            # is 0.69915, its best α 1.5e-4 away): the sampling's closeness test, whose
            # search goes on while its bracket's floor contradicts it, decides
            near = near[ln[near] >= min_dist]
            e = edges[rows[near]]
            short[near] = too_close(field, new[e[:, 0]], new[e[:, 1]], min_dist)
        length[rows], alpha[rows] = ln, al
        bad_e[rows] = (ln < min_dist) | short | (ln > longest[rows])

    bad_t = signed_areas(new, tris) <= 0
    measure(touching(edges, is_moved))
    while True:
        # the moved corners of the bad triangles and ends of the bad edges, ascending
        ends = np.concatenate([tris[bad_t].ravel(), edges[bad_e].ravel()])
        ends = np.unique(ends[is_moved[ends]])
        undo = ends[np.abs(new[ends] - old[ends]).max(axis=1) > 0]
        if undo.size == 0:
            break
        new[undo] = old[undo]
        undone = np.zeros(n, dtype=bool)
        undone[undo] = True
        is_moved[undo] = False
        at = touching(tris, undone)
        bad_t[at] = signed_areas(new, tris[at]) <= 0
        measure(touching(edges, undone))
    return new, length, alpha


def relocate(
    field: MetricField,
    mesh: Mesh,
    *,
    sweeps: int = 6,
    relax: float = 0.5,
    power: float = 4.0,
    min_dist: float = 0.7,
    max_length: float = 1.4,
) -> Mesh:
    """The P1 ``mesh`` after ``sweeps`` relocation sweeps (see the module docstring)."""
    pts = np.array(mesh.points, dtype=float)
    fixed = _on_box(pts, field.box)
    n = len(pts)
    cur = mesh
    e = cur.edges
    length, alpha = edge_parabola_lengths(field, pts, e)
    for sweep in range(sweeps):
        # each vertex towards the weighted mean of the points that would make its edges
        # unit (kernels.relocation_sweep); outliers weigh more: w = max(L, 1/L)^power
        ok = np.isfinite(length) & (length > 0)
        w = np.where(ok, np.maximum(length, 1.0 / np.where(ok, length, 1.0)), 1.0) ** power
        new, is_moved = np.empty_like(pts), np.empty(n, dtype=bool)
        kernels.relocation_sweep(
            pts, np.ascontiguousarray(e), np.ascontiguousarray(length), w, fixed,
            float(relax), new, is_moved,
        )  # fmt: skip
        moved = np.flatnonzero(is_moved)
        pts, length, alpha = _undo_bad_moves(
            field, pts, new, moved, e, cur.corners, min_dist, length, alpha, max_length
        )
        cur = metric_delaunay(field, Mesh(pts, cur.corners, mesh.box))
        if sweep + 1 == sweeps:
            break
        # the edges a flip made are searched from scratch; the others keep their
        # lengths at these positions (measured by the undo pass)
        old_edges, e = e, cur.edges
        length = carried(old_edges, length, e, n)
        alpha = carried(old_edges, alpha, e, n)
        fresh = np.flatnonzero(np.isnan(alpha))
        if fresh.size:
            length[fresh], alpha[fresh] = edge_parabola_lengths(field, pts, e[fresh])
    return cur
