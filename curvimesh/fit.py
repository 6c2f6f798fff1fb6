"""Edge nodes fitted to a function: the P2 nodes that minimise its interpolation error.

For the ``interpolation`` metric (SPEC section 2) the mesh is wanted for the
error of the isoparametric P2 interpolant of a function f, not for unit
lengths alone. On a curved triangle with the quadratic map x(ξ), f is
interpolated through f∘x, whose third derivative

    d³(f∘x)[ξ] = d³f(x)[x', x', x'] + 3 d²f(x)[x', x'']      (x''' = 0)

has, beside the term the metric is built from, a term in the curvature x''
of the element weighted by d²f. Edges bent along the metric's geodesics
(paper section 2) make it large across sharp layers, where d²f is large, and
the curved unit meshes then interpolate f worse than straight-sided ones
(``bench/convergence.py`` measures 4 to 20 times worse on tanh fronts); bent
the right way, the same term cancels part of the first and the error drops
below the straight-sided one.

Here the vertices and triangles stay and every interior edge node m moves to
lower E(m) = Σ_t ∫_t (f − I_t f)² dx over the two triangles t of its edge
(:func:`curvimesh.interpolation_error.element_l2_squared`), whose sum over
the edges is twice the squared L2 error. Each round tries, for every edge,

* the bend scaled: m_s + s (m − m_s), m_s the straight midpoint, for s in
  :data:`SCALES` (s = 0 straightens the edge);
* a pattern step: m ± h ℓ n̂ and m ± h ℓ t̂, ℓ the edge's length, n̂ and t̂
  the unit normal and tangent of its chord, with a step h per edge that
  starts at :data:`FIRST_STEP` and is halved when no candidate improves;

and keeps the best candidate that lowers E and leaves both triangles valid
(Jacobian positive everywhere, decided exactly from its Bezier coefficients).
A boundary edge (one triangle, on a box side) takes the tangent steps only,
so that its node stays on the side: the curve is the same segment, but its
parametrisation, and with it the interpolant along the side, changes.
Each round sweeps the edges colour by colour (:func:`edge_colours`: no two
edges of one colour share a triangle), so that every edge of a colour is
evaluated with its neighbours' current nodes and all the improving ones move
together: a Gauss-Seidel sweep, and the error never increases. Rounds stop
when a round gains less than ``rtol`` of the total, when every step is below
:data:`MIN_STEP`, or after ``max_rounds``. Edges whose triangles interpolate f
to rounding already (:data:`NOISE`) keep their nodes, and so do those whose two
triangles hold a negligible share of the error (:data:`NEGLIGIBLE`): far from
where f varies, its interpolation error there can be 10⁻²⁰ of the total and
still above rounding, and a node that chased it could go anywhere its
triangles stay valid, the edge's metric length with it (2.26 on two peaks of
exp(−200 r²), none over 1.57 with the share kept, the error the same to
10⁻⁴). Moving one node at a
time, the descent can stop in a local minimum (bends of neighbouring edges
that cancel); it never raises the error.

The step resolution matters: near the minimum E is nearly quadratic in m,
and the share of the error a node can still remove depends on how finely the
pattern resolves that minimum relative to the edge's length, which the finer
meshes need ever finer. With steps down to ℓ/1024 only, and one
independent set of moves per round, the fitted error of a circular tanh front
(``bench/convergence.py``, f3) fell as N^-1.3 to N^-1.2 at 10^4 to 5·10^4
vertices; with the sweeps and steps down to ℓ/65536 it is 2.5 to 3 times lower
at 8,000 and 16,000 vertices, and falls as N^-1.56 between them.

One node at a time cannot leave every trap: a sliver across a sharp layer
whose geodesic edges make its interpolant far from f, while straightening
any one of them inverts a neighbour. After the sweeps, the triangles whose
error stands out have the edges around them straightened together
(:func:`unbend_outliers`), and :data:`POLISH_ROUNDS` more sweeps polish the
edges there.

Beyond the paper (which curves for the metric only); :func:`curvimesh.adapt.swap`
runs it last when the metric is an ``interpolation`` form (``--no-fit`` turns
it off). It trades the unit lengths of the curved edges, which the report
still measures, for the error the metric was built to minimise.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from curvimesh.bezier import valid_exact
from curvimesh.interpolation_error import element_l2_squared
from curvimesh.mesh import Mesh, cells_at_vertices, local_edge, signed_areas

#: Scalings s of an edge's bend tried each round (1 is the current node).
SCALES = (1.25, 0.75, 0.5, 0.0)

#: First pattern step, relative to the edge's length, and the smallest one tried.
FIRST_STEP = 0.125
MIN_STEP = 2.0**-16

#: A triangle whose error exceeds this many times the mean is an outlier
#: (:func:`unbend_outliers`), and at most this many are treated.
OUTLIER = 100.0
MAX_OUTLIERS = 2000

#: Rounds of sweeps after the outliers are unbent.
POLISH_ROUNDS = 10

#: Rings of triangles around an outlier whose edges are straightened together.
RINGS = 3

#: Quadrature order of the local errors (collapsed Gauss, exact to degree 10).
ERROR_ORDER = 6

#: Errors below this fraction of max |f| (pointwise, as an L2 density) are rounding:
#: their edges are not moved.
NOISE = 1e-12

#: An edge whose triangles' squared error is below this fraction of their count times
#: the mean triangle's keeps its node: all such edges together can remove at most
#: three times this fraction of the squared error (a node's move removes at most its
#: triangles' error, and each triangle has three edges).
NEGLIGIBLE = 1e-6


@dataclass(frozen=True)
class FitResult:
    """The mesh with fitted edge nodes, how many node moves were made, in how many
    rounds, and the L2 error of the interpolant before and after (same quadrature)."""

    mesh: Mesh
    moves: int
    rounds: int
    error_before: float
    error_after: float


def edge_colours(t1: NDArray, t2: NDArray, m: int) -> NDArray[np.int64]:
    """Colours of edges such that no two edges of one colour share a triangle.

    Greedy in edge order over the edges ``(k,)`` joining triangles t1 and t2
    (t1 = t2 for a boundary edge) of a mesh of m triangles: each edge takes the
    smallest colour none of its triangles' other edges has. A triangle has
    three edges, so an edge meets at most four others and five colours do.

    >>> edge_colours(np.array([0, 0, 0, 1]), np.array([1, 0, 0, 1]), 2).tolist()
    [0, 1, 2, 1]
    """
    used = np.zeros(m, dtype=np.int64)  # bit c set: the triangle has an edge of colour c
    out = np.empty(len(t1), dtype=np.int64)
    for k, (a, b) in enumerate(zip(t1.tolist(), t2.tolist(), strict=True)):
        taken = int(used[a] | used[b])
        c = ((taken + 1) & ~taken).bit_length() - 1  # lowest clear bit
        out[k] = c
        used[a] |= 1 << c
        used[b] |= 1 << c
    return out


def _best_nodes(
    f: Callable[[NDArray], NDArray],
    pts: NDArray,
    tris: NDArray,
    local: NDArray,
    one: NDArray,
    mid_ids: NDArray,
    straight: NDArray,
    normal: NDArray,
    tangent: NDArray,
    t1: NDArray,
    t2: NDArray,
    s1: NDArray,
    s2: NDArray,
    step: NDArray,
) -> tuple[NDArray, NDArray, NDArray]:
    """The best candidate node of each edge given (module docstring).

    Returns the best node ``(k, 2)``, its triangles' errors ``(k, 2)`` (0 for
    the missing triangle of a boundary edge) and the gain E(m) − E(best) (0
    where no candidate improves).
    """
    cur_mid = pts[mid_ids]
    n1, n2 = pts[tris[t1]], pts[tris[t2]]
    current = local[t1] + np.where(one, 0.0, local[t2])
    best = current.copy()
    best_mid = cur_mid.copy()
    best_parts = np.column_stack([local[t1], np.where(one, 0.0, local[t2])])
    rows = np.arange(len(one))
    h = step[:, None]
    inner = ~one[:, None]  # boundary nodes stay on their side: tangent steps only

    def consider(mid: NDArray) -> None:
        """E of the pairs with their nodes at ``mid`` (inf where a triangle is
        invalid) taken as the best where it is lower."""
        a1, a2 = n1.copy(), n2.copy()
        a1[rows, s1] = mid
        a2[rows, s2] = mid
        ok = valid_exact(a1) & (one | valid_exact(a2))
        e1 = np.full(len(one), np.inf)
        e2 = np.where(one, 0.0, np.inf)
        if ok.any():
            e1[ok] = element_l2_squared(f, a1[ok], order=ERROR_ORDER)
            two = ok & ~one
            e2[two] = element_l2_squared(f, a2[two], order=ERROR_ORDER)
        total = e1 + e2
        better = total < best
        best[better] = total[better]
        best_mid[better] = mid[better]
        best_parts[better] = np.column_stack([e1, e2])[better]

    for s in SCALES:
        consider(np.where(inner, straight + s * (cur_mid - straight), cur_mid))
    for d in (normal, -normal):
        consider(np.where(inner, cur_mid + h * d, cur_mid))
    for d in (tangent, -tangent):
        consider(cur_mid + h * d)
    gain = current - best
    return best_mid, best_parts, np.where(gain > 0.0, gain, 0.0)


def unbend_outliers(
    f: Callable[[NDArray], NDArray],
    mesh: Mesh,
    pts: NDArray,
    local: NDArray,
    *,
    ratio: float = OUTLIER,
    limit: int = MAX_OUTLIERS,
) -> NDArray[np.int64]:
    """Straighten the edges around the triangles whose error stands out; in place.

    A triangle whose local error (``local``, its share of E) exceeds ``ratio``
    times the mean is an outlier. One node at a time cannot always unbend it:
    across a sharp layer a sliver's edges bent along the geodesics may make
    its interpolant far from f, while straightening any one of them inverts
    a neighbour whose other edges are still bent (measured: the fitted mesh of
    ``bench/convergence.py``'s f3 at 53,000 vertices, 10 triangles with 99 %
    of the squared error, each 10⁴ times worse than its straight version). So
    for each outlier, worst first, this tries moving jointly to the chord
    midpoints the nodes of its own three edges, then those of every edge of
    the triangles at its vertices (one ring), then of the triangles at their
    vertices, up to :data:`RINGS` rings, and keeps the first set that leaves
    every triangle having one of those edges valid (exactly, from Bezier
    coefficients) with a lower sum of their errors. ``pts`` and ``local`` are
    updated; returns the edges whose nodes moved. At most ``limit`` outliers.
    """
    tris = np.asarray(mesh.triangles)
    if len(tris) == 0:
        return np.zeros(0, dtype=np.int64)
    mean = float(local.mean())
    worst = np.argsort(-local, kind="stable")[:limit]
    worst = worst[local[worst] > ratio * mean]
    if worst.size == 0:
        return np.zeros(0, dtype=np.int64)
    start, order = cells_at_vertices(tris[:, :3], len(pts))
    tri_edges, edge_tris, edges, emid = mesh.tri_edges, mesh.edge_tris, mesh.edges, mesh.edge_mid
    moved = []
    for t in worst.tolist():
        if local[t] <= ratio * mean:  # a neighbour's unbending fixed it already
            continue
        ring = np.array([t])
        for _ in range(RINGS + 1):
            group = np.unique(tri_edges[ring])
            around = np.unique(edge_tris[group])
            around = around[around >= 0]
            keep = pts[emid[group]].copy()
            pts[emid[group]] = 0.5 * (pts[edges[group, 0]] + pts[edges[group, 1]])
            nodes = pts[tris[around]]
            if valid_exact(nodes).all():
                err = element_l2_squared(f, nodes, order=ERROR_ORDER)
                if err.sum() < local[around].sum():
                    local[around] = err
                    moved.append(group)
                    break
            pts[emid[group]] = keep
            verts = np.unique(tris[ring, :3])
            ring = np.unique(np.concatenate([order[start[v] : start[v + 1]] for v in verts]))
    return np.unique(np.concatenate(moved)) if moved else np.zeros(0, dtype=np.int64)


def fit_nodes(
    f: Callable[[NDArray], NDArray],
    mesh: Mesh,
    *,
    max_rounds: int = 40,
    rtol: float = 1e-3,
) -> FitResult:
    """Move interior edge nodes to lower the interpolation error of f (module docstring).

    ``mesh`` is a valid P2 mesh and ``f`` maps points ``(n, 2)`` to values
    ``(n,)``. Returns a valid P2 mesh with the same vertices and triangles,
    its boundary nodes on their edges' chords. Deterministic.
    """
    pts = np.array(mesh.points)
    tris = np.asarray(mesh.triangles)
    if mesh.order != 2 or len(tris) == 0:
        return FitResult(mesh, 0, 0, 0.0, 0.0)
    local = element_l2_squared(f, pts[tris], order=ERROR_ORDER)
    before = float(np.sqrt(local.sum()))
    edges, emid, et, tri_edges = mesh.edges, mesh.edge_mid, mesh.edge_tris, mesh.tri_edges
    x0, x1 = pts[edges[:, 0]], pts[edges[:, 1]]
    straight = 0.5 * (x0 + x1)
    tangent = x1 - x0  # of length ℓ: steps are relative to the edge
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    # a boundary edge has one triangle: t2 = t1 stands in, its error counted once
    side = et[:, 1] < 0
    t1 = et[:, 0]
    t2 = np.where(side, t1, et[:, 1])
    ids = np.arange(len(edges))
    s1, s2 = 3 + local_edge(tri_edges, t1, ids), 3 + local_edge(tri_edges, t2, ids)
    # a pair whose error is at the level of rounding, or a negligible share of the
    # error, is left alone
    scale = float(np.abs(f(pts[np.unique(tris)])).max())
    areas = np.abs(signed_areas(pts, tris[:, :3]))
    noise = (NOISE * scale) ** 2 * (areas[t1] + np.where(side, 0.0, areas[t2]))
    share = NEGLIGIBLE * float(local.mean()) * np.where(side, 1.0, 2.0)
    pair = local[t1] + np.where(side, 0.0, local[t2])
    step = np.where(pair > np.maximum(noise, share), FIRST_STEP, 0.0)
    colours = edge_colours(t1, t2, len(tris))
    moves = rounds = 0

    def sweeps(most: int) -> None:
        nonlocal moves, rounds
        for _ in range(most):
            if not np.any(step >= MIN_STEP):
                break
            rounds += 1
            swept = 0.0
            for colour in range(int(colours.max()) + 1):
                live = np.flatnonzero((colours == colour) & (step >= MIN_STEP))
                if live.size == 0:
                    continue
                one = side[live]
                best_mid, parts, gain = _best_nodes(
                    f, pts, tris, local, one,
                    emid[live], straight[live], normal[live], tangent[live],
                    t1[live], t2[live], s1[live], s2[live], step[live],
                )  # fmt: skip
                # no two edges of a colour share a triangle: the improving ones move together
                k = np.flatnonzero(gain > 0.0)
                step[live[gain <= 0.0]] *= 0.5
                pts[emid[live[k]]] = best_mid[k]
                local[t1[live[k]]] = parts[k, 0]
                k2 = k[~one[k]]
                local[t2[live[k2]]] = parts[k2, 1]
                moves += len(k)
                swept += float(gain[k].sum())
            if swept < rtol * local.sum():
                break

    sweeps(max_rounds)
    unbent = unbend_outliers(f, mesh, pts, local)
    if unbent.size:
        # the unbent edges and their triangles' other edges descend again from there
        touched = np.unique(et[unbent])
        step[np.unique(tri_edges[touched[touched >= 0]])] = FIRST_STEP
        moves += len(unbent)
        sweeps(POLISH_ROUNDS)
    after = float(np.sqrt(local.sum()))
    return FitResult(Mesh(pts, tris, mesh.box), moves, rounds, before, after)
