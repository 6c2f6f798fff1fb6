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

(R(φ) the rotation by φ: towards w and up to about 60° off that line). The
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
lengths checked again to 1e-5 before the move). Passes over the long edges
repeat until one moves nothing. Only v and the nodes of its incident edges
move; the triangles stay.

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
from curvimesh.geodesic import shortest_parabola
from curvimesh.mesh import Mesh
from curvimesh.metric import MetricField
from curvimesh.quality import edge_lengths, edge_lengths_fast, metric_areas, quality_from

#: Fractions t of the long edge's chord a vertex is moved by.
STEPS = (0.04, 0.08, 0.12, 0.16, 0.2, 0.25)

#: Angles φ (radians) off the long edge's direction.
ANGLES = (0.0, 0.5, -0.5, 1.0, -1.0)

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


def _star(mesh: Mesh, v: int) -> _Star:
    tris = np.flatnonzero((mesh.triangles[:, :3] == v).any(axis=1))
    edges = np.flatnonzero((mesh.edges == v).any(axis=1))
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
    max_passes: int = 5,
) -> ShiftResult:
    """Move end vertices of the edges longer than ``max_length`` (module docstring).

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
    fixed = np.zeros(len(pts), dtype=bool)
    fixed[edges[mesh.boundary_edges].ravel()] = True
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
                star = _star(mesh, int(v))
                limits = (min(float(quality[star.tris].min()), floor), min_dist)
                got = _best_shift(field, mesh, pts, length, star, int(v), int(w), limits)
                if got is None:
                    continue
                pts, length[star.edges], quality[star.tris] = got
                moved += 1
                break
        shifted += moved
        if moved == 0:
            break
    return ShiftResult(Mesh(pts, mesh.triangles, mesh.box), shifted, passes)


def _candidates(field: MetricField, pts: NDArray, v: int, w: int) -> NDArray:
    """Positions ``(k, 2)`` v + t R(φ)(w − v) strictly inside the box."""
    chord = pts[w] - pts[v]
    moves = []
    for phi in ANGLES:
        c, s = np.cos(phi), np.sin(phi)
        turned = np.array([c * chord[0] - s * chord[1], s * chord[0] + c * chord[1]])
        moves += [pts[v] + t * turned for t in STEPS]
    cand = np.array(moves)
    xmin, ymin, xmax, ymax = field.box
    inside = (cand[:, 0] > xmin) & (cand[:, 0] < xmax) & (cand[:, 1] > ymin) & (cand[:, 1] < ymax)
    return cand[inside]


def _best_shift(
    field: MetricField,
    mesh: Mesh,
    pts: NDArray,
    length: NDArray,
    star: _Star,
    v: int,
    w: int,
    limits: tuple[float, float],
) -> tuple[NDArray, NDArray, NDArray] | None:
    """The best admissible position of v (module docstring): the new nodes, the
    incident edges' lengths and the star's qualities; None if there is none.

    ``limits`` is (the quality the star must keep, ``min_dist``).
    """
    q_min, min_dist = limits
    cand = _candidates(field, pts, v, w)
    k, j = len(cand), len(star.edges)
    if k == 0:
        return None
    a = np.repeat(cand, j, axis=0)
    b = np.tile(pts[star.others], (k, 1))
    optimal = shortest_parabola(field, a, b, exact_length=False).mid.reshape(k, j, 2)
    straight = 0.5 * (a + b).reshape(k, j, 2)
    old_len = length[star.edges]
    old_max, shortest = float(old_len.max()), min(min_dist, float(old_len.min()))
    base = pts[mesh.triangles[star.tris]]  # (s, 6, 2)
    inc = star.slots[:, 3:]  # (s, 3): incident edge k, or −2
    lens0 = length[mesh.tri_edges[star.tris]]  # (s, 3)
    todo = np.ones(k, dtype=bool)
    found: list[tuple[float, int, NDArray]] = []  # (longest, candidate, star nodes)
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
            np.tile(pts[star.others], (len(rows), 1)),
            mid.reshape(-1, 2),
        ).reshape(len(rows), j)
        good = (new_len.max(axis=1) < old_max) & (new_len.min(axis=1) >= shortest)
        for r in np.flatnonzero(good):
            found.append((float(new_len[r].max()), int(rows[r]), nodes[r]))
    for _longest, i, nodes in sorted(found, key=lambda f: (f[0], f[1]))[:4]:
        new = pts.copy()
        new[v] = cand[i]
        for kk in range(j):
            new[mesh.edge_mid[star.edges[kk]]] = nodes[star.slots == kk][0]
        exact = edge_lengths(field, new, mesh.edges[star.edges], mesh.edge_mid[star.edges])
        if not (exact.max() < old_max and exact.min() >= shortest):
            continue
        lens = lens0.copy()
        lens[inc >= 0] = exact[inc[inc >= 0]]
        q = quality_from(metric_areas(field, nodes), lens)
        if q.min() >= q_min:
            return new, exact, q
    return None
