"""Intrinsic Delaunay flips where the metric's frame turns fast.

The triangulation stage connects the sampled points by straight edges
(Delaunay, then flipped to the Delaunay triangulation of the metric at each
quad's centroid), and the swaps then only make changes that keep every
curved triangle valid. Where a layer of the metric bends through more than
about 60° within one unit length (``check-metric`` warns), the straight
connection is wrong at the bend: the chord between two points one unit
apart along the layer cuts across a dozen of its levels, so the straight
metric-Delaunay triangulation joins points across the layer instead of along
it, and no sequence of swaps that stay valid one at a time leads back
(on ``metrics/hard/tight_front.yaml`` the swaps of the edges longer than 2
left at the bends were refused, most because a triangle came out invalid
even with a straight new edge, the others for quality).

Here the connection is made from the curved edge lengths alone. With ℓ the
metric length of an edge's shortest parabola (with a free middle node where
the frame turns fast, :mod:`curvimesh.freenode`), an interior edge a–b of
the triangles (a, b, c) and (b, a, d) has the angles

    γ = arccos((ℓ_ac² + ℓ_bc² − ℓ_ab²) / (2 ℓ_ac ℓ_bc))   at c,  δ likewise at d,

of the triangles with those side lengths, and is flipped to c–d when
γ + δ > π + :data:`ANGLE_TOLERANCE` (it is not locally Delaunay) and
ℓ_cd < ℓ_ab: Lawson's flips for the intrinsic Delaunay triangulation of the
lengths (Bobenko and Springborn 2007), in rounds of flips that share no
triangle, by decreasing γ + δ. In a tangle the lengths of parabolas break
the triangle inequality (an edge 6.4 long beside a path of 1.5 and 1.0
through c); such an edge counts as not Delaunay, before all others
(:func:`delaunay_excess`). No flip makes an edge shorter than min(0.7, the
edge it replaces) nor an edge that is there already; each flip shortens an
edge, so the flips end. Only quads with a corner within :data:`RINGS` edges
of a fast turn (:func:`fast_region`: a vertex, edge midpoint or triangle
centroid where :func:`curvimesh.freenode.turns_fast`) are flipped; elsewhere
the mesh is left exactly as it is. The flips ignore the embedding: a
triangle of the result may be inverted as a straight triangle and valid only
curved (paper figure 8).

The interior edges with an end in that region and the edges of the new
triangles then get their shortest parabolas (unless that makes an old edge
shorter than min(0.7, its old length)); every other edge keeps its node. A
triangle left invalid (Jacobian not positive everywhere, decided exactly)
has the nodes of its interior edges chosen among :func:`node_options` (that
parabola, the edge's old node, the paper's symmetric parabola, points
between them and the straight midpoint), the combination with the shortest
longest edge that leaves every triangle of those edges valid. Where a
triangle stays invalid, the flips are made again from the start with the
flips that made it and its neighbours forbidden (the first half of
:data:`ATTEMPTS`), then with its corners and their neighbours frozen (no flip
touches them, their edges keep their nodes: the input there, valid). After
:data:`ATTEMPTS` the input is returned unchanged. The result is always a valid
P2 mesh. On ``metrics/hard/tight_front.yaml`` 120 flips at the first attempt
take the longest edge of the curved mesh from 10.9 to 1.61 and the edges in
[0.7, 1.4] from 89.3 % to 96.5 %, the worst quality (4) to 0.61, before any
swap.

Beyond the paper; :func:`curvimesh.adapt.swap` runs it before the first
swaps (``--no-intrinsic`` turns it off).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from curvimesh import geodesic
from curvimesh.bezier import valid_exact
from curvimesh.curve import assemble_p2
from curvimesh.freenode import may_turn_fast, shortest_parabola, turns_fast
from curvimesh.mesh import (
    EdgeStore,
    Mesh,
    apply_flips,
    edge_nodes,
    flip_candidates,
    independent_flips,
    p1_of,
)
from curvimesh.metric import MetricField
from curvimesh.quality import edge_lengths_fast

#: Excess of γ + δ over π (radians) from which an edge is flipped.
ANGLE_TOLERANCE = 1e-3

#: Edges around the fast-turning vertices within which quads may be flipped.
RINGS = 2

#: Most rounds of flips, most restarts (with forbidden flips, then frozen vertices),
#: most passes of repairs.
MAX_ROUNDS = 100
ATTEMPTS = 16
REPAIR_PASSES = 4

#: Fractions of a node's offset from the straight midpoint tried by :func:`node_options`.
FRACTIONS = (0.75, 0.5, 0.25, 0.0)


@dataclass(frozen=True)
class IntrinsicResult:
    """The mesh after the flips, how many flips it has and how many restarts were needed."""

    mesh: Mesh
    flips: int
    restarts: int = 0


def intrinsic_angle(opposite: NDArray, side1: NDArray, side2: NDArray) -> NDArray:
    """The angle ``(k,)`` facing the side ``opposite`` of triangles with these side lengths
    (law of cosines; 0 or π where the sides break the triangle inequality).

    >>> np.degrees(intrinsic_angle(np.array([1.0, 2 ** 0.5]), np.ones(2), np.ones(2))).round(6)
    array([60., 90.])
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        cos = (side1**2 + side2**2 - opposite**2) / (2.0 * side1 * side2)
    return np.arccos(np.clip(np.nan_to_num(cos, nan=1.0), -1.0, 1.0))


def delaunay_excess(
    l_ab: NDArray, l_ac: NDArray, l_bc: NDArray, l_ad: NDArray, l_bd: NDArray
) -> NDArray:
    """γ + δ − π ``(k,)`` for edges a–b of the triangles (a, b, c), (b, a, d) with these
    side lengths: positive where a–b is not locally Delaunay. Where a–b is longer than
    the path through c or through d (the lengths of a tangle break the triangle
    inequality), the excess is π plus the relative overshoot, so that such an edge
    is flipped first.

    >>> delaunay_excess(*(np.array([v]) for v in (1.0, 1.0, 1.0, 1.0, 1.0))).round(6)
    array([-1.047198])
    >>> float(delaunay_excess(*(np.array([v]) for v in (3.0, 1.0, 1.0, 2.0, 2.0)))[0]) > np.pi
    True
    """
    excess = intrinsic_angle(l_ab, l_ac, l_bc) + intrinsic_angle(l_ab, l_ad, l_bd) - np.pi
    with np.errstate(divide="ignore", invalid="ignore"):
        over = np.maximum(l_ab / (l_ac + l_bc), l_ab / (l_ad + l_bd)) - 1.0
    return np.where(over > 0, np.pi + over, excess)


def fast_region(field: MetricField, mesh: Mesh, rings: int = RINGS) -> NDArray:
    """Vertices ``(n,)`` within ``rings`` edges of a fast turn of the frame: of a vertex, the
    midpoint of an edge or the centroid of a triangle where the frame turns fast (the
    zone past the turn threshold can be narrower than the edges: 0.02 along a front
    whose edges are 0.06 long there)."""
    pts = np.asarray(mesh.points)
    edges, corners = mesh.edges, mesh.corners
    n_e = len(edges)
    fast = turns_fast(
        field,
        np.concatenate([pts, 0.5 * (pts[edges[:, 0]] + pts[edges[:, 1]]), pts[corners].mean(1)]),
    )
    region = fast[: len(pts)].copy()
    region[edges[fast[len(pts) : len(pts) + n_e]].ravel()] = True
    region[corners[fast[len(pts) + n_e :]].ravel()] = True
    for _ in range(rings):
        near = region.copy()
        near[edges[:, 0]] |= region[edges[:, 1]]
        near[edges[:, 1]] |= region[edges[:, 0]]
        region = near
    return region


class _Lengths:
    """Shortest-parabola lengths and nodes of edges, each computed once (an EdgeStore)."""

    def __init__(self, field: MetricField, pts: NDArray) -> None:
        self.field, self.pts = field, pts
        self.store = EdgeStore(len(pts))

    def get(self, a: NDArray, b: NDArray) -> tuple[NDArray, NDArray]:
        keys = self.store.key(a, b)
        _, found = self.store.find(keys)
        need = np.unique(keys[~found])
        if need.size:
            n = self.store.n
            par = shortest_parabola(
                self.field, self.pts[need // n], self.pts[need % n], exact_length=False
            )
            self.store.add(need, par.mid, par.length)
        pos, _ = self.store.find(keys)
        return self.store.length[pos], self.store.mid[pos]


def _quad_keys(a: NDArray, b: NDArray, c: NDArray, d: NDArray) -> list[tuple[int, ...]]:
    """A key per flip: the old edge and the new one, each sorted."""
    return list(
        zip(
            np.minimum(a, b).tolist(),
            np.maximum(a, b).tolist(),
            np.minimum(c, d).tolist(),
            np.maximum(c, d).tolist(),
            strict=True,
        )
    )


def lawson_flips(
    mesh: Mesh,
    lengths: _Lengths,
    region: NDArray,
    forbidden: set,
    frozen: NDArray,
    min_length: float = 0.7,
) -> tuple[NDArray, list, int]:
    """Corners ``(m, 3)`` after the intrinsic Delaunay flips (module docstring) of the
    quads with a corner in ``region`` and none ``frozen``, but the ``forbidden`` ones
    (keys of :func:`_quad_keys`), and none that makes an edge shorter than
    min(``min_length``, the edge it replaces); the flip that made each triangle (None
    for an old one) and the number of flips."""
    pts = np.asarray(mesh.points)
    corners = np.array(mesh.corners)
    origin: list = [None] * len(corners)
    flips = 0
    for _ in range(MAX_ROUNDS):
        cur = Mesh(pts, corners, mesh.box)
        _, t1, t2, a, b, c, d = flip_candidates(cur)
        near = (region[a] | region[b] | region[c] | region[d]) & ~(
            frozen[a] | frozen[b] | frozen[c] | frozen[d]
        )
        t1, t2, a, b, c, d = (v[near] for v in (t1, t2, a, b, c, d))
        (l_ab, _), (l_ac, _), (l_bc, _) = (lengths.get(u, v) for u, v in ((a, b), (a, c), (b, c)))
        (l_ad, _), (l_bd, _) = lengths.get(a, d), lengths.get(b, d)
        excess = delaunay_excess(l_ab, l_ac, l_bc, l_ad, l_bd)
        cand = np.flatnonzero(excess > ANGLE_TOLERANCE)
        if forbidden and cand.size:
            keys = _quad_keys(a[cand], b[cand], c[cand], d[cand])
            cand = cand[[k not in forbidden for k in keys]]
        if cand.size == 0:
            break
        l_cd, _ = lengths.get(c[cand], d[cand])
        # never an edge that is there already (two triangles on three vertices)
        n = len(pts)
        there = np.isin(
            np.minimum(c[cand], d[cand]) * n + np.maximum(c[cand], d[cand]),
            cur.edges[:, 0] * n + cur.edges[:, 1],
        )
        shorter = (l_cd < l_ab[cand]) & (l_cd >= np.minimum(min_length, l_ab[cand]))
        cand = cand[shorter & ~there & (c[cand] != d[cand])]
        if cand.size == 0:
            break
        chosen = cand[independent_flips(t1[cand], t2[cand], excess[cand], len(corners))]
        corners = apply_flips(corners, chosen, t1, t2, a, b, c, d)
        for t, key in zip(
            np.concatenate([t1[chosen], t2[chosen]]).tolist(),
            2 * _quad_keys(a[chosen], b[chosen], c[chosen], d[chosen]),
            strict=True,
        ):
            origin[t] = key
        flips += len(chosen)
    return corners, origin, flips


def node_options(ideal: NDArray, old: NDArray, paper: NDArray, straight: NDArray) -> NDArray:
    """Candidate nodes ``(k, 2)`` for one edge: its ideal node, its old one (when finite),
    the paper's symmetric parabola's, the point halfway between the first and the third,
    and each of the first and third moved back towards the straight midpoint by the
    fractions :data:`FRACTIONS`."""
    opts = [ideal]
    if np.isfinite(old).all():
        opts.append(old)
    opts += [paper, 0.5 * (ideal + paper)]
    opts += [straight + s * (ideal - straight) for s in FRACTIONS]
    opts += [straight + s * (paper - straight) for s in FRACTIONS[:-1]]
    return np.array(opts)


def _repair(
    field: MetricField, mesh: Mesh, mids: NDArray, old: NDArray, ideal, interior: NDArray
) -> NDArray:
    """Nodes ``(E, 2)`` with the interior edges of each invalid triangle set to the
    combination of :func:`node_options` with the shortest longest edge that leaves every
    triangle of those edges valid (none found: unchanged). ``ideal(k)`` gives the ideal
    nodes of edges ``k``."""
    pts = np.asarray(mesh.points)
    corners, tri_edges, edge_tris, edges = mesh.corners, mesh.tri_edges, mesh.edge_tris, mesh.edges
    mids = mids.copy()
    valid = valid_exact(np.concatenate([pts[corners], mids[tri_edges]], axis=1))
    bad = np.flatnonzero(~valid)
    if bad.size == 0:
        return mids
    todo = np.unique(tri_edges[bad].ravel())
    todo = todo[interior[todo]]
    best_node = np.full((len(edges), 2), np.nan)
    paper = np.full((len(edges), 2), np.nan)
    best_node[todo] = ideal(todo)
    paper[todo] = geodesic.shortest_parabola(
        field, pts[edges[todo, 0]], pts[edges[todo, 1]], exact_length=False
    ).mid
    for t in bad:
        own = tri_edges[t]
        if valid_exact(np.concatenate([pts[corners[t]], mids[own]])[None])[0]:
            continue
        mine = own[interior[own]]
        if mine.size == 0:
            continue
        x0, x1 = pts[edges[mine, 0]], pts[edges[mine, 1]]
        opts = [
            node_options(best_node[k], old[k], paper[k], 0.5 * (x0[i] + x1[i]))
            for i, k in enumerate(mine)
        ]
        lens = [
            edge_lengths_fast(
                field, np.repeat(x0[i : i + 1], len(o), 0), np.repeat(x1[i : i + 1], len(o), 0), o
            )
            for i, o in enumerate(opts)
        ]
        combos = np.array(list(itertools.product(*(range(len(o)) for o in opts))))
        longest = np.max([lens[i][combos[:, i]] for i in range(len(mine))], axis=0)
        combos = combos[np.argsort(longest, kind="stable")]
        touched = np.unique(edge_tris[mine].ravel())
        touched = touched[touched >= 0]
        trial = np.repeat(mids[tri_edges[touched]][None], len(combos), axis=0)  # (c, s, 3, 2)
        for i, k in enumerate(mine):
            slot = tri_edges[touched] == k  # (s, 3)
            trial[:, slot] = opts[i][combos[:, i]][:, None]
        nodes = np.concatenate(
            [np.repeat(pts[corners[touched]][None], len(combos), axis=0), trial], axis=2
        )
        ok = valid_exact(nodes.reshape(-1, 6, 2)).reshape(len(combos), -1).all(axis=1)
        if ok.any():
            best = combos[np.argmax(ok)]
            for i, k in enumerate(mine):
                mids[k] = opts[i][best[i]]
    return mids


def intrinsic_flips(field: MetricField, mesh: Mesh, *, min_length: float = 0.7) -> IntrinsicResult:
    """Intrinsic Delaunay flips where the frame turns fast (module docstring).

    ``mesh`` is a valid P2 mesh; the result is a valid P2 mesh on the same
    vertices, numbered as :func:`curvimesh.curve.assemble_p2` numbers, or
    ``mesh`` itself when no flip is made. Deterministic.
    """
    if mesh.order != 2 or len(mesh.triangles) == 0 or not may_turn_fast(field):
        return IntrinsicResult(mesh, 0)  # (the fast turns' grid screen, as in freenode)
    p1 = p1_of(mesh)
    region = fast_region(field, p1)
    if not region.any():
        return IntrinsicResult(mesh, 0)
    pts = np.asarray(p1.points)
    given = edge_nodes(mesh)  # the input's nodes
    lengths = _Lengths(field, pts)
    forbidden: set = set()
    frozen = np.zeros(len(pts), dtype=bool)
    for attempt in range(ATTEMPTS):
        corners, origin, flips = lawson_flips(p1, lengths, region, forbidden, frozen, min_length)
        if flips == 0:
            break
        out = Mesh(pts, corners, p1.box)
        edges, tri_edges, edge_tris = out.edges, out.tri_edges, out.edge_tris
        pos, existed = given.find(given.key(edges[:, 0], edges[:, 1]))
        old = np.where(existed[:, None], given.mid[pos], np.nan)
        new_tri = np.array([o is not None for o in origin])
        interior = edge_tris[:, 1] >= 0
        renewed = region[edges[:, 0]] | region[edges[:, 1]]
        renewed[tri_edges[new_tri].ravel()] = True
        renewed &= interior & ~((frozen[edges[:, 0]] | frozen[edges[:, 1]]) & existed)
        mids = old.copy()
        r = np.flatnonzero(renewed)
        l_new, mids[r] = lengths.get(edges[r, 0], edges[r, 1])
        # an old edge is not made shorter than min(min_length, its old length)
        check = existed[r] & (l_new < min_length)
        r, l_new = r[check], l_new[check]
        if r.size:
            l_old = edge_lengths_fast(field, pts[edges[r, 0]], pts[edges[r, 1]], old[r])
            keep = r[l_new < np.minimum(min_length, l_old)]
            mids[keep] = old[keep]

        def ideal(k: NDArray, edges: NDArray = edges) -> NDArray:
            return lengths.get(edges[k, 0], edges[k, 1])[1]

        bad = ~valid_exact(np.concatenate([pts[corners], mids[tri_edges]], axis=1))
        for _ in range(REPAIR_PASSES):
            if not bad.any():
                break
            mids = _repair(field, out, mids, old, ideal, interior)
            before, bad = bad, ~valid_exact(np.concatenate([pts[corners], mids[tri_edges]], axis=1))
            if bad.sum() >= before.sum():
                break
        if not bad.any():
            return IntrinsicResult(assemble_p2(pts, out, mids), flips, attempt)
        # first forbid the flips that made the invalid triangles or their neighbours;
        # when that is not enough, freeze the invalid triangles' corners and their ring
        near = np.unique(edge_tris[tri_edges[bad]].ravel())
        more = {origin[t] for t in near[near >= 0].tolist() if origin[t] is not None}
        if attempt < ATTEMPTS // 2 and not more <= forbidden:
            forbidden |= more
            continue
        ring = np.zeros(len(pts), dtype=bool)
        ring[corners[bad].ravel()] = True
        ring[edges[ring[edges[:, 0]], 1]] = True
        ring[edges[ring[edges[:, 1]], 0]] = True
        frozen |= ring
    return IntrinsicResult(mesh, 0, ATTEMPTS)


__all__ = [
    "ANGLE_TOLERANCE",
    "IntrinsicResult",
    "delaunay_excess",
    "fast_region",
    "intrinsic_angle",
    "intrinsic_flips",
    "lawson_flips",
    "node_options",
]
