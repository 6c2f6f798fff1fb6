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
The improving edges are taken greedily by decreasing gain, no two in one
triangle (each was evaluated with its neighbours' old nodes), and moved
together, so the error never increases. Rounds stop when a round gains less
than ``rtol`` of the total, when every step is below :data:`MIN_STEP`, or
after ``max_rounds``. Edges whose triangles interpolate f to rounding
already (:data:`NOISE`) keep their nodes. Moving one node at a time, the descent can stop in a local
minimum (bends of neighbouring edges that cancel); it never raises the error.

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
from curvimesh.mesh import Mesh, independent_flips, local_edge, signed_areas

#: Scalings s of an edge's bend tried each round (1 is the current node).
SCALES = (1.25, 0.75, 0.5, 0.0)

#: First pattern step, relative to the edge's length, and the smallest one tried.
FIRST_STEP = 0.125
MIN_STEP = 1.0 / 1024.0

#: Quadrature order of the local errors (collapsed Gauss, exact to degree 10).
ERROR_ORDER = 6

#: Errors below this fraction of max |f| (pointwise, as an L2 density) are rounding:
#: their edges are not moved.
NOISE = 1e-12


@dataclass(frozen=True)
class FitResult:
    """The mesh with fitted edge nodes, how many node moves were made, in how many
    rounds, and the L2 error of the interpolant before and after (same quadrature)."""

    mesh: Mesh
    moves: int
    rounds: int
    error_before: float
    error_after: float


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
    cand = np.arange(len(edges))
    x0, x1 = pts[edges[cand, 0]], pts[edges[cand, 1]]
    straight = 0.5 * (x0 + x1)
    tangent = x1 - x0  # of length ℓ: steps are relative to the edge
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    # a boundary edge has one triangle: t2 = t1 stands in, its error counted once
    side = et[cand, 1] < 0
    t1 = et[cand, 0]
    t2 = np.where(side, t1, et[cand, 1])
    s1, s2 = 3 + local_edge(tri_edges, t1, cand), 3 + local_edge(tri_edges, t2, cand)
    # a pair whose error is at the level of rounding is left alone
    scale = float(np.abs(f(pts[np.unique(tris)])).max())
    areas = np.abs(signed_areas(pts, tris[:, :3]))
    noise = (NOISE * scale) ** 2 * (areas[t1] + np.where(side, 0.0, areas[t2]))
    step = np.where(local[t1] + np.where(side, 0.0, local[t2]) > noise, FIRST_STEP, 0.0)
    moves = rounds = 0
    while rounds < max_rounds:
        live = np.flatnonzero(step >= MIN_STEP)
        if live.size == 0:
            break
        rounds += 1
        cur_mid = pts[emid[cand[live]]]
        n1, n2 = pts[tris[t1[live]]], pts[tris[t2[live]]]
        one = side[live]
        current = local[t1[live]] + np.where(one, 0.0, local[t2[live]])
        best = current.copy()
        best_mid = cur_mid.copy()
        best_parts = np.column_stack([local[t1[live]], np.where(one, 0.0, local[t2[live]])])
        h = step[live, None]
        inner = ~one[:, None]  # boundary nodes stay on their side: tangent steps only
        tries = [
            np.where(inner, straight[live] + s * (cur_mid - straight[live]), cur_mid)
            for s in SCALES
        ]
        tries += [np.where(inner, cur_mid + h * d, cur_mid) for d in (normal[live], -normal[live])]
        tries += [cur_mid + h * d for d in (tangent[live], -tangent[live])]
        rows = np.arange(len(live))
        for mid in tries:
            a1, a2 = n1.copy(), n2.copy()
            a1[rows, s1[live]] = mid
            a2[rows, s2[live]] = mid
            ok = valid_exact(a1) & (one | valid_exact(a2))
            e1 = np.full(len(live), np.inf)
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
        gain = current - best
        improving = np.flatnonzero(gain > 0.0)
        step[live[gain <= 0.0]] *= 0.5
        if improving.size == 0:
            continue
        k = improving[
            independent_flips(t1[live[improving]], t2[live[improving]], gain[improving], len(tris))
        ]
        pts[emid[cand[live[k]]]] = best_mid[k]
        local[t1[live[k]]] = best_parts[k, 0]
        k2 = k[~one[k]]
        local[t2[live[k2]]] = best_parts[k2, 1]
        moves += len(k)
        if gain[k].sum() < rtol * local.sum():
            break
    after = float(np.sqrt(local.sum()))
    return FitResult(Mesh(pts, tris, mesh.box), moves, rounds, before, after)
