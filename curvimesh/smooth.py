"""Vertex relocation: moving vertices to even out their edge lengths in the metric.

The paper places its points once and only swaps edges; its conclusion
leaves "other mesh optimizations" to further work. This stage moves every
interior vertex of the straight mesh towards the place where its edges would
be unit: for an edge i–j of metric length L (its shortest parabola, paper
eq. (3)) the point p_j + (p_i − p_j) / L would make it unit if the metric were
constant along it, and the vertex goes, by a relaxation factor, towards the
weighted average of these points over its edges (the "spring" relocation of
Bossen & Heckbert 1996, in the metric). All vertices move at once (a Jacobi
move). Boundary vertices stay.

The parabola searches are the cost of a move, and the fixed sweeps of one
search and one move each converged more slowly the larger the mesh (the mean
quality (4) of the toy metric fell from 0.955 at 10³ vertices to 0.932 at
10⁵). So the parabolas are searched once, and the moves use lengths that are
cheap and nearly as exact:

* calibrated chords: an edge's length is c_e · ℓ_e(x), with ℓ_e the length of
  its chord in the metric at the chord's midpoint, sqrt(dᵀ g((p_i + p_j)/2) d),
  d = p_i − p_j, re-evaluated at every move, and c_e = L_e / ℓ_e fixed when
  the edge's parabola was searched (the ratio of the curved length to the
  chord's, which changes little as the edge moves: on the toy metric, 0.3 %
  at the 99th percentile after eight moves, against 14 % with g frozen at the
  old midpoint);
* blocks of ``moves`` moves on a fixed triangulation, then flips to the
  Delaunay triangulation in the metric (:func:`_flip`, which flips back a quad
  whose new diagonal is shorter than ``min_dist``); only the edges the flips
  made are searched;
* the safeguards on every move (:func:`_safe_move`): a vertex does not move
  when its move would invert a triangle (signed area ≤ 0, exact), make an
  edge shorter than ``min_dist`` or longer than 0.98 ``max_length``, and than
  it was (by the calibrated chords, and by the parabola where the chord comes
  within 10 % of ``min_dist`` or the calibration factor is off 1 by more than
  5 %); the vertices stopped stay for that move and the triangles and edges
  at them are judged again, until no move is bad;
* the parabolas judge each block as the sweeps did (:func:`_undo_bad_moves`:
  a move that inverts a triangle, makes an edge shorter than ``min_dist``, or
  longer than ``max_length``, and than it was at the block's start, is
  undone): the last block by all these rules, the others by the short rule at
  the edges below unit length and the untrusted ones;
* a stopping rule: the blocks stop when one lowers the mean of (log L)² over
  the edges, the spread of the lengths about 1, by less than the fraction
  ``tol`` of it, or after ``blocks`` blocks.

Tried and dropped: a Gauss-Seidel move by vertex colours (no faster than the
Jacobi move per move), over-relaxation (no gain, worse minimum quality), more
moves on a fixed triangulation (the spring system buckles after about ten:
the flips are part of the convergence), the metric frozen at the chord's old
midpoint (errors of 14 %), Simpson's rule along the chord (worse than the
midpoint with the calibration). On the toy metric the spread stops falling
by 2 % a block after 2 blocks at 10³ vertices, 5 to 8 at 10⁴ and about 12 at
10⁵.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from curvimesh.freenode import parabola_verdicts, shortest_parabola
from curvimesh.mesh import Mesh, apply_flips, flip_candidates, independent_flips, signed_areas
from curvimesh.metric import MetricField
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


def edge_parabola_lengths(
    field: MetricField, points: NDArray, edges: NDArray, start: NDArray | None = None
) -> tuple[NDArray, NDArray]:
    """Lengths ``(E,)`` of the shortest parabolas of edges ``(E, 2)`` (search accuracy)
    and their α ``(E,)``, searched from the guesses ``start`` ``(E,)`` of α if given."""
    par = shortest_parabola(
        field,
        points[edges[:, 0]],
        points[edges[:, 1]],
        scan=5,
        alpha_tol=2e-3,
        exact_length=False,
        remember=False,  # the vertices move at every sweep
        start=start,
    )
    return par.length, par.alpha


def carried(old_edges: NDArray, values: NDArray, edges: NDArray, n: int) -> NDArray:
    """Values ``(E,)`` of ``edges`` ``(E, 2)`` from the same edges in ``old_edges`` ``(E', 2)``
    with ``values`` ``(E',)`` (both sorted, as :attr:`Mesh.edges`, ``n`` points), NaN for
    the new ones.

    >>> old = np.array([[0, 1], [0, 2], [1, 2]])
    >>> carried(old, np.array([1.0, 2.0, 3.0]), np.array([[0, 2], [1, 3]]), 4).tolist()
    [2.0, nan]
    """
    old_keys = old_edges[:, 0] * n + old_edges[:, 1]
    keys = edges[:, 0] * n + edges[:, 1]
    pos = np.minimum(np.searchsorted(old_keys, keys), len(old_keys) - 1)
    return np.where(old_keys[pos] == keys, values[pos], np.nan)


def _undo_bad_moves(
    field: MetricField,
    old: NDArray,
    new: NDArray,
    moved: NDArray,
    edges: NDArray,
    tris: NDArray,
    min_dist: float,
    old_length: NDArray | None = None,
    max_length: float = 1.4,
) -> NDArray:
    """The positions ``new`` ``(n, 2)`` with the bad moves of vertices ``moved`` undone.

    A moved vertex goes back to ``old`` when it is a corner of a triangle of
    ``tris`` that is inverted (signed area ≤ 0) or an end of an edge of
    ``edges`` that touches a moved vertex and whose shortest parabola is
    shorter than ``min_dist`` or longer than ``max_length`` and, given the
    edges' lengths ``old_length`` at ``old``, than its old length (a move
    never makes a short or a long edge, nor a short edge shorter or a long
    one longer; without ``old_length`` every edge shorter than ``min_dist``
    is bad). This repeats until no move is
    undone (each pass undoes at least one, so it ends). Each pass re-measures
    only the triangles and edges at the vertices just undone: nothing else
    changes (an edge between two vertices that stay put is not checked).
    """
    n = len(new)
    new = new.copy()
    if moved.size == 0:
        return new
    is_moved = np.zeros(n, dtype=bool)
    is_moved[moved] = True
    bad_t = signed_areas(new, tris) <= 0
    short = np.zeros(len(edges), dtype=bool)
    touch = np.flatnonzero(is_moved[edges].any(axis=1))
    _update_bad(field, new, edges, touch, is_moved, short, min_dist, old_length, max_length)
    while moved.size:
        bad_v = np.zeros(n, dtype=bool)
        bad_v[tris[bad_t].ravel()] = True
        bad_v[edges[short].ravel()] = True
        undo = moved[bad_v[moved] & (np.abs(new[moved] - old[moved]).max(axis=1) > 0)]
        if undo.size == 0:
            break
        new[undo] = old[undo]
        undone = np.zeros(n, dtype=bool)
        undone[undo] = True
        moved = moved[~undone[moved]]  # ascending, as np.setdiff1d would give
        is_moved[undo] = False
        at = np.flatnonzero(undone[tris].any(axis=1))
        bad_t[at] = signed_areas(new, tris[at]) <= 0
        at = np.flatnonzero(undone[edges].any(axis=1))
        _update_bad(field, new, edges, at, is_moved, short, min_dist, old_length, max_length)
    return new


def _update_bad(
    field: MetricField,
    pts: NDArray,
    edges: NDArray,
    rows: NDArray,
    is_moved: NDArray,
    bad: NDArray,
    min_dist: float,
    old_length: NDArray | None,
    max_length: float,
) -> None:
    """Set ``bad[rows]``: the edge touches a moved vertex and its parabola is shorter than
    min_dist or (with ``old_length``) longer than max_length, and (with ``old_length``)
    than its old length."""
    bad[rows] = False
    rows = rows[is_moved[edges[rows]].any(axis=1)]
    if rows.size == 0:
        return
    # the parabola is searched only where the bounds leave the answer open
    longest = None
    if old_length is not None and np.isfinite(max_length):
        longest = np.maximum(max_length, old_length[rows])
    verdict = parabola_verdicts(
        field, pts[edges[rows, 0]], pts[edges[rows, 1]], short=min_dist, long=longest
    )
    bad[rows] = verdict != 0
    if old_length is not None:
        # a short edge is bad only if the move made it shorter: the few found short
        # are measured
        short = rows[verdict < 0]
        if short.size:
            length, _ = edge_parabola_lengths(field, pts, edges[short])
            bad[short] = length < old_length[short]


#: Edges whose calibrated chord falls below ``NEAR · min_dist`` are judged by their
#: parabolas (:func:`_safe_move`).
NEAR = 1.1
#: Edges whose calibration factor is off 1 by more than ``TRUST`` (the metric changes
#: much along them, and the factor as they move) are always judged by their parabolas.
TRUST = 0.05
#: The moves keep the chords below ``LONG · max_length`` (a margin for their error).
LONG = 0.98


def _chord_lengths(
    field: MetricField, x: NDArray, y: NDArray, a: NDArray, b: NDArray
) -> tuple[NDArray, NDArray, NDArray]:
    """The chords' metric lengths ℓ = sqrt(dᵀ g(m) d) at their midpoints m ``(E,)``, and
    d = p_a − p_b as ``dx``, ``dy`` ``(E,)``, for points ``x``, ``y`` ``(n,)``."""
    dx, dy = x[a] - x[b], y[a] - y[b]

    def norm(g):
        return np.sqrt(g[:, 0, 0] * dx * dx + 2 * g[:, 0, 1] * dx * dy + g[:, 1, 1] * dy * dy)

    return norm(field.tensor(np.column_stack([0.5 * (x[a] + x[b]), 0.5 * (y[a] + y[b])]))), dx, dy


def _spring_steps(
    length: NDArray, dx: NDArray, dy: NDArray, ab: NDArray, n: int, power: float
) -> tuple[NDArray, NDArray, NDArray]:
    """The spring average's pull on every point: (Σ w (t − p), Σ w) with t the targets.

    For the edge a–b (d = p_a − p_b, length L) the target of a is
    p_b + d / L, so t − p_a = −d (1 − 1/L), and b's is the opposite; the weight
    w = max(L, 1/L)^power makes the outliers weigh more. Returns the x and y
    sums and the weight sums ``(n,)``; ``ab`` is the edges' ends, a then b.
    """
    r = 1.0 / length
    w = np.maximum(length, r) ** power
    f = w * (1.0 - r)
    fx, fy = f * dx, f * dy
    wsum = np.bincount(ab, np.concatenate([w, w]), minlength=n)
    sx = np.bincount(ab, np.concatenate([-fx, fx]), minlength=n)
    sy = np.bincount(ab, np.concatenate([-fy, fy]), minlength=n)
    return sx, sy, wsum


def relocate(
    field: MetricField,
    mesh: Mesh,
    *,
    blocks: int = 20,
    moves: int = 4,
    relax: float = 0.5,
    power: float = 4.0,
    min_dist: float = 0.7,
    max_length: float = 1.4,
    tol: float = 0.02,
) -> Mesh:
    """The P1 ``mesh`` with its vertices relocated (see the module docstring): at most
    ``blocks`` blocks of ``moves`` moves of relaxation ``relax``, stopping when a
    block lowers the spread of the lengths by less than the fraction ``tol``."""
    pts = np.array(mesh.points, dtype=float)
    free = ~_on_box(pts, field.box)
    n = len(pts)
    cur = mesh
    e = cur.edges
    length, _ = edge_parabola_lengths(field, pts, e)
    ok = np.isfinite(length) & (length > 0)
    chord = _chord_lengths(field, pts[:, 0], pts[:, 1], e[:, 0], e[:, 1])[0]
    cal = np.where(ok, length, 1.0) / chord
    for block in range(blocks):
        if block:
            old_e, e = e, cur.edges
            cal = carried(old_e, cal, e, n)
            new = np.flatnonzero(np.isnan(cal))  # made by the flips: searched once
            if new.size:
                length, _ = edge_parabola_lengths(field, pts, e[new])
                ok = np.isfinite(length) & (length > 0)
                chord = _chord_lengths(field, pts[:, 0], pts[:, 1], e[new, 0], e[new, 1])[0]
                cal[new] = np.where(ok, length, 1.0) / chord
        a, b = e[:, 0], e[:, 1]
        ab = np.concatenate([a, b])
        tris = cur.corners
        x, y = pts[:, 0].copy(), pts[:, 1].copy()
        chord, dx, dy = _chord_lengths(field, x, y, a, b)
        start = cal * chord
        length = start
        for _ in range(moves):
            sx, sy, wsum = _spring_steps(length, dx, dy, ab, n, power)
            step = np.where(free & (wsum > 0), relax / np.maximum(wsum, 1e-300), 0.0)
            x, y, length, dx, dy = _safe_move(
                field, x, y, step * sx, step * sy, a, b, tris, cal, length, min_dist, max_length
            )
        # the spread of the lengths about 1: mean (log L)²
        spread0, spread = np.mean(np.log(start) ** 2), np.mean(np.log(length) ** 2)
        new_pts = np.column_stack([x, y])
        last = block == blocks - 1 or spread >= (1.0 - tol) * spread0
        moved = np.flatnonzero(np.abs(new_pts - pts).max(axis=1) > 0)
        if last:  # the parabolas judge the last block by all the rules
            new_pts = _undo_bad_moves(
                field, pts, new_pts, moved, e, tris, min_dist, start, max_length
            )
        else:  # and the others' edges below unit length by the short one
            check = (length < 1.0) | (np.abs(cal - 1.0) > TRUST)
            new_pts = _undo_bad_moves(
                field, pts, new_pts, moved, e[check], tris, min_dist, start[check], np.inf
            )
        pts = new_pts
        cur = _flip(field, Mesh(pts, tris, mesh.box), min_dist)
        if last:
            break
    return cur


def _flip(field: MetricField, mesh: Mesh, min_dist: float) -> Mesh:
    """``mesh`` flipped to the Delaunay triangulation in the metric, but for the flips
    whose new edge is shorter than ``min_dist`` (its parabola): those quads are
    flipped back (in one round of independent flips) where the old diagonal is valid
    and not shorter.

    The in-circle test judges a quad in the metric at its centroid; where the
    metric changes fast the diagonal it picks can be the shorter one by the
    parabolas, and no move lengthens it when its neighbours are crowded.
    """
    out = metric_delaunay(field, mesh)
    n = len(mesh.points)
    pts = np.asarray(out.points)
    new = np.flatnonzero(np.isnan(carried(mesh.edges, np.zeros(len(mesh.edges)), out.edges, n)))
    if new.size == 0:
        return out
    length, _ = edge_parabola_lengths(field, pts, out.edges[new])
    short, short_length = new[length < min_dist], length[length < min_dist]
    if short.size == 0:
        return out
    e, t1, t2, a, b, c, d = flip_candidates(out)
    rows = np.flatnonzero(np.isin(e, short))
    back = np.column_stack([c[rows], d[rows]])
    ok = (signed_areas(pts, np.column_stack([a[rows], d[rows], c[rows]])) > 0) & (
        signed_areas(pts, np.column_stack([d[rows], b[rows], c[rows]])) > 0
    )
    old, _ = edge_parabola_lengths(field, pts, back)
    rows = rows[ok & (old >= np.minimum(min_dist, short_length[np.searchsorted(short, e[rows])]))]
    if rows.size == 0:
        return out
    chosen = rows[independent_flips(t1[rows], t2[rows], np.zeros(len(rows)), len(out.corners))]
    return Mesh(pts, apply_flips(out.corners, chosen, t1, t2, a, b, c, d), out.box)


def _safe_move(
    field: MetricField,
    x: NDArray,
    y: NDArray,
    mx: NDArray,
    my: NDArray,
    a: NDArray,
    b: NDArray,
    tris: NDArray,
    cal: NDArray,
    length: NDArray,
    min_dist: float,
    max_length: float,
) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
    """Points ``x``, ``y`` ``(n,)`` moved by ``mx``, ``my`` ``(n,)`` where it inverts no
    triangle of ``tris`` and makes no edge a–b ``(E,)`` shorter than ``min_dist`` and
    than its ``length`` ``(E,)``; with the new lengths and d.

    Lengths are calibrated chords, ``cal`` · ℓ, but an edge that they put
    below ``NEAR · min_dist`` and shortened is judged by its parabola (the
    chords' error grows with the edges' size against the metric's changes:
    on the toy metric at 10³ vertices it reaches 5 % at the 99th percentile).
    A vertex whose move is bad stays; the triangles and edges at the vertices
    just stopped are judged again, until no move is bad. Each pass stops at
    least one vertex, and a vertex that stays makes nothing bad that was not
    (the old positions are valid, an edge between two vertices that stay keeps
    its length), so the loop ends.
    """
    n = len(x)
    moving = (mx != 0) | (my != 0)
    nx, ny = x + mx, y + my
    new_length, dx, dy = np.empty_like(length), np.empty_like(length), np.empty_like(length)

    def short(rows: NDArray) -> NDArray:
        chord, dx[rows], dy[rows] = _chord_lengths(field, nx, ny, a[rows], b[rows])
        new_length[rows] = cal[rows] * chord
        shorter = new_length[rows] < length[rows]
        bad = shorter & (new_length[rows] < min_dist)
        bad |= new_length[rows] > np.maximum(LONG * max_length, length[rows])
        near = (new_length[rows] < NEAR * min_dist) | (np.abs(cal[rows] - 1.0) > TRUST)
        near = np.flatnonzero(shorter & ~bad & near)
        if near.size:
            i, j = a[rows[near]], b[rows[near]]
            pa, pb = np.column_stack([nx[i], ny[i]]), np.column_stack([nx[j], ny[j]])
            bad[near] = parabola_verdicts(field, pa, pb, short=min_dist) < 0
        return bad

    def areas(t: NDArray) -> NDArray:
        x0, y0 = nx[t[:, 0]], ny[t[:, 0]]
        return (nx[t[:, 1]] - x0) * (ny[t[:, 2]] - y0) - (ny[t[:, 1]] - y0) * (nx[t[:, 2]] - x0)

    every = np.arange(len(a))
    bad_t = np.flatnonzero(areas(tris) <= 0)
    bad_e = np.flatnonzero(short(every))
    while True:
        stop = np.zeros(n, dtype=bool)
        stop[tris[bad_t].ravel()] = True
        stop[a[bad_e]] = True
        stop[b[bad_e]] = True
        stop &= moving
        if not stop.any():
            return nx, ny, new_length, dx, dy
        moving &= ~stop
        nx[stop], ny[stop] = x[stop], y[stop]
        rows = np.flatnonzero(stop[tris[:, 0]] | stop[tris[:, 1]] | stop[tris[:, 2]])
        bad_t = rows[areas(tris[rows]) <= 0]
        rows = np.flatnonzero(stop[a] | stop[b])
        bad_e = rows[short(rows)]
