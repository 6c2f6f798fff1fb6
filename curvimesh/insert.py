"""Vertex insertion into the cavity of a long curved edge.

Where the sampled points leave a hole, an edge e = (a, b) comes out longer
than ``max_length`` and the triangles around it are big or thin; splitting
e at its middle node alone (:mod:`curvimesh.split`) often gives a bad or
invalid triangle. Here a new vertex p is inserted into a *cavity* around e
and the cavity is re-triangulated as a star from p, the Bowyer–Watson step
of Delaunay refinement (Chew 1989) made for a curved P2 mesh::

                c                                   c
       x₃ . . / | \\ . . x₂                x₃ ----- / | \\ ----- x₂
         .  /   |   \\  .                    \\   /   |   \\   /
          / t₁  e  t₂ \\          ──►          \\ /    p    \\ /
         a ---- | ---- b                        a  ... | ...  b   (spokes p–a, p–b, ...)
          \\     |     /                          \\     |     /
            \\   |   /                              \\   |   /
              \\ | /                                  \\ | /
                d                                      d

The cavity is t₁ = (a, b, c) and t₂ = (b, a, d), the two triangles of e,
plus any subset of the four triangles N_j across the outer edges of the
quad a–d–b–c (2⁴ = 16 cavities, fewer at the boundary). Its boundary is a
closed loop of old edges, which keep their P2 nodes; the new triangles are
(p, u, w) for every loop edge u → w, and every spoke p–u gets its shortest
parabola (paper eq. (3)), its node moved back by the same fraction for all
spokes, x_m = (p + u)/2 + s (x_m* − (p + u)/2), s ∈ :data:`BACKTRACK`, until
every new triangle is valid (exact Bezier test). The loop passes a vertex
at most once (so the cavity is a topological disk), and a star whose
triangles are all valid covers that disk exactly once: the angles at p of
positively oriented triangles add up to 2π times the winding number of the
loop around p, which is 1 for p inside a disk and 0 outside.

The positions tried for p, for each long interior edge, are its middle node
and the points of its parabola at the fractions :data:`EDGE_FRACTIONS` of its
metric length, the images under the curved (P2) maps of
t₁ and t₂ of the barycentric points :data:`INNER` (weights on a, b and the
opposite corner), and the metric circumcentres of t₁ and t₂. For every
(position, cavity) pair, all at once, the insertion is admissible when every
new triangle is valid, every spoke and the distance from p to every vertex
of the mesh is at least ``min_dist`` (no short edge, now or after a swap),
every spoke is shorter than e, and the worse quality (4) of the new
triangles is at least ``min_quality``. The admissible one with the fewest
long edges left around p (spokes, and outer edges of the quad still on the
loop, longer than ``max_length``) and then the best worse quality is taken.
Insertions are made in rounds, longest edge first, no two sharing a
triangle nor putting their new vertices closer than ``min_dist``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from curvimesh.bezier import p2_map, valid_exact
from curvimesh.fill import metric_circumcentres
from curvimesh.freenode import shortest_parabola
from curvimesh.geodesic import parabola_points
from curvimesh.mesh import Mesh, carried, local_edge, rotate_triangles
from curvimesh.metric import MetricField
from curvimesh.quality import (
    COUNT_RTOL,
    edge_lengths,
    edge_lengths_fast,
    metric_areas,
    quality_from,
)
from curvimesh.sampling import close_to_index, search_halfwidths, search_regions, too_close
from curvimesh.spatial import PointIndex, pairs_within_boxes

#: Fractions of the optimal offset tried for the spokes' nodes, in order.
BACKTRACK = (1.0, 0.5, 0.25, 0.0)

#: Fractions of the long edge's metric length, from a, at which its parabola is tried
#: for the new vertex (besides its middle node, t = 1/2).
EDGE_FRACTIONS = (0.4, 0.5, 0.6)

#: Barycentric weights (on a, on b, on the opposite corner) tried in t₁ and t₂.
INNER = ((5 / 12, 5 / 12, 1 / 6), (1 / 3, 1 / 3, 1 / 3))

#: The 12 star triangles a cavity can use, as (j, kind): kind 0 is (p, q_j, q_j+1)
#: on outer edge j; kinds 1 and 2 are (p, q_j, x_j) and (p, x_j, q_j+1) when the
#: triangle N_j across outer edge j is in the cavity. Spoke targets: q_0..q_3 are
#: 0..3 (the quad a, d, b, c), x_j is 4 + j.
_STAR = [(j, kind) for j in range(4) for kind in range(3)]
_FROM = np.array([j if k < 2 else 4 + j for j, k in _STAR])
_TO = np.array([(j + 1) % 4 if k != 1 else 4 + j for j, k in _STAR])
#: (16, 12): which star triangles cavity ``mask`` uses (bit j: N_j included).
_USES = np.array([[(k == 0) != bool(m >> j & 1) for j, k in _STAR] for m in range(16)], dtype=bool)
#: (16, 8): which spoke targets cavity ``mask`` uses.
_TARGETS = np.array([[True] * 4 + [bool(m >> j & 1) for j in range(4)] for m in range(16)])


@dataclass(frozen=True)
class InsertResult:
    """The mesh after the insertions and how many vertices were inserted."""

    mesh: Mesh
    inserted: int


def metric_fraction_params(
    field: MetricField,
    x0: NDArray,
    x1: NDArray,
    xm: NDArray,
    fractions: NDArray,
    *,
    segments: int = 32,
) -> NDArray:
    """Parameters t ``(n, f)`` where the parabolas have run the given fractions of their length.

    s(t) = ∫₀ᵗ sqrt(ẋᵀ g(x) ẋ) dτ is integrated over ``segments`` equal pieces
    of [0, 1] by a 3-point Gauss rule each; t with s(t) = f · s(1) is found in
    its piece by linear interpolation of s (the speed taken constant there).
    """
    xg, wg = np.polynomial.legendre.leggauss(3)
    edges_t = np.linspace(0.0, 1.0, segments + 1)
    h = 1.0 / segments
    t = (edges_t[:-1, None] + h * (xg[None, :] + 1) / 2).ravel()
    pts, tan = parabola_points(x0, x1, xm, t)
    n, k = pts.shape[:2]
    g = field.tensor(pts.reshape(-1, 2), check=False).reshape(n, k, 2, 2)
    speed = np.sqrt(np.einsum("nki,nkij,nkj->nk", tan, g, tan))
    piece = (speed.reshape(n, segments, 3) * (h * wg / 2)).sum(axis=2)
    cum = np.concatenate([np.zeros((n, 1)), np.cumsum(piece, axis=1)], axis=1)  # (n, S + 1)
    goal = cum[:, -1:] * np.asarray(fractions, dtype=float)[None, :]  # (n, f)
    j = np.clip((cum[:, None, :] <= goal[..., None]).sum(axis=2) - 1, 0, segments - 1)
    lo = np.take_along_axis(cum, j, axis=1)
    step = np.take_along_axis(piece, j, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(step > 0, (goal - lo) / step, 0.0)
    return edges_t[j] + h * np.clip(frac, 0.0, 1.0)


def star_positions(pts: NDArray, r1: NDArray, r2: NDArray, field: MetricField) -> NDArray:
    """Positions ``(s, P, 2)`` tried for the new vertex of each long edge.

    ``r1`` = (a, b, c, n_ab, n_bc, n_ca) and ``r2`` = (b, a, d, n_ba, n_ad, n_db)
    ``(s, 6)`` are the two triangles of the edge (node ids). Non-finite
    circumcentres (degenerate triangles) come back as NaN.
    """
    xa, xb, xm = pts[r1[:, 0]], pts[r1[:, 1]], pts[r1[:, 3]]
    t = metric_fraction_params(field, xa, xb, xm, np.array(EDGE_FRACTIONS))
    t = np.column_stack([np.full(len(t), 0.5), np.where(np.isfinite(t), t, 0.5)])
    # the parabola x(t) = (1−t)(1−2t) x_a + t(2t−1) x_b + 4t(1−t) x_m at per-row parameters
    n0, n1, nm = (1 - t) * (1 - 2 * t), t * (2 * t - 1), 4 * t * (1 - t)
    on_edge = sum(w[..., None] * x[:, None] for w, x in ((n0, xa), (n1, xb), (nm, xm)))
    lam = np.array(INNER)
    uv1 = lam[:, 1:]  # reference (u, v) = (weight of corner 1, weight of corner 2)
    uv2 = lam[:, [0, 2]]  # t₂ = (b, a, d): corner 1 is a
    inner1 = p2_map(pts[r1], uv1)
    inner2 = p2_map(pts[r2], uv2)
    cc1 = metric_circumcentres(field, pts, r1[:, :3])[0]
    cc2 = metric_circumcentres(field, pts, r2[:, :3])[0]
    return np.concatenate([on_edge, inner1, inner2, cc1[:, None], cc2[:, None]], axis=1)


def insert_points(
    field: MetricField,
    mesh: Mesh,
    *,
    max_length: float = 1.4,
    min_dist: float = 0.7,
    min_quality: float = 0.3,
    rounds: int = 4,
) -> InsertResult:
    """Insert vertices at the long interior edges where allowed (module docstring)."""
    total = 0
    length = edge_lengths(
        field, np.asarray(mesh.points), mesh.edges, mesh.edge_mid, rtol=COUNT_RTOL
    )
    for _ in range(rounds):
        mesh, n, length = _insert_round(field, mesh, length, max_length, min_dist, min_quality)
        total += n
        if n == 0:
            break
    return InsertResult(mesh, total)


def _carried_lengths(
    field: MetricField, old: Mesh, length: NDArray, mesh: Mesh, renum: NDArray
) -> NDArray:
    """:func:`~curvimesh.quality.edge_lengths` of ``mesh``'s edges (to ``COUNT_RTOL``) where
    ``mesh`` is ``old`` (edge lengths ``length``) with some triangles replaced and its
    nodes renumbered by ``renum`` (old id → new id, ascending, −1 for a node dropped).

    An edge of ``old`` is in ``mesh`` when its middle node is (a node belongs to one
    edge); its length comes along (:func:`curvimesh.mesh.carried`: ``renum`` keeps the
    edges' order), the others' are measured (the lengths are functions of the nodes'
    positions, which do not change)."""
    kept = renum[old.edge_mid] >= 0
    out = carried(renum[old.edges[kept]], length[kept], mesh.edges, len(mesh.points))
    fresh = np.isnan(out)
    out[fresh] = edge_lengths(
        field, np.asarray(mesh.points), mesh.edges[fresh], mesh.edge_mid[fresh], rtol=COUNT_RTOL
    )
    return out


def _far_from_vertices(field: MetricField, mesh: Mesh, x: NDArray, min_dist: float) -> NDArray:
    """``(k,)`` whether points ``x`` ``(k, 2)`` are min_dist from every vertex of the mesh."""
    pts = np.asarray(mesh.points)
    corners = mesh.vertex_ids
    index = PointIndex()
    index.add(pts[corners])
    return ~close_to_index(field, index, x, search_regions(field, x, 2.0 * min_dist), min_dist)


def _insert_round(
    field: MetricField,
    mesh: Mesh,
    length: NDArray,
    max_length: float,
    min_dist: float,
    min_quality: float,
) -> tuple[Mesh, int, NDArray]:
    """One round of insertions on ``mesh`` (edge lengths ``length`` to ``COUNT_RTOL``):
    the new mesh, the vertices inserted and the new mesh's edge lengths."""
    pts = np.asarray(mesh.points)
    tris = np.asarray(mesh.triangles)
    et, tri_edges = mesh.edge_tris, mesh.tri_edges
    seeds = np.flatnonzero((length > max_length) & (et[:, 1] >= 0))
    ns = len(seeds)
    if ns == 0:
        return mesh, 0, length
    t1, t2 = et[seeds, 0], et[seeds, 1]
    k1, k2 = local_edge(tri_edges, t1, seeds), local_edge(tri_edges, t2, seeds)
    r1 = rotate_triangles(tris[t1], k1)  # (a, b, c, n_ab, n_bc, n_ca)
    r2 = rotate_triangles(tris[t2], k2)  # (b, a, d, n_ba, n_ad, n_db)
    quad = np.column_stack([r1[:, 0], r2[:, 2], r1[:, 1], r1[:, 2]])  # a, d, b, c (CCW)
    # outer edges j = (q_j, q_j+1): owner triangle, local index, node
    owner = np.column_stack([t2, t2, t1, t1])
    local = np.column_stack([(k2 + 1) % 3, (k2 + 2) % 3, (k1 + 1) % 3, (k1 + 2) % 3])
    onode = np.column_stack([r2[:, 4], r2[:, 5], r1[:, 4], r1[:, 5]])
    oedge = tri_edges[owner, local]
    nb = mesh.neighbours[owner, local]  # (s, 4), −1 on the boundary
    has = nb >= 0
    nbs = np.where(has, nb, owner)
    kk = np.argmax(tri_edges[nbs] == oedge[..., None], axis=2)
    rn = rotate_triangles(tris[nbs.ravel()], kk.ravel()).reshape(
        ns, 4, 6
    )  # (w, u, x, n_wu, n_ux, n_xw)
    xv = np.where(has, rn[..., 2], quad)
    targets = np.column_stack([quad, xv])  # (s, 8) spoke ends
    # the 12 star triangles' loop edges: node and length
    e_ux = tri_edges[nbs, (kk + 1) % 3]
    e_xw = tri_edges[nbs, (kk + 2) % 3]
    bnode = np.stack([onode, rn[..., 4], rn[..., 5]], axis=2).reshape(ns, 12)
    blen = np.stack([length[oedge], length[e_ux], length[e_xw]], axis=2).reshape(ns, 12)

    pos = star_positions(pts, r1, r2, field)  # (s, P, 2)
    npos = pos.shape[1]
    pos_ok = field.inside(pos)
    pos = np.where(pos_ok[..., None], pos, pts[r1[:, 3]][:, None])  # placeholder where not ok
    flat = pos.reshape(-1, 2)
    pos_ok &= _far_from_vertices(field, mesh, flat, min_dist).reshape(ns, npos)

    # admissible cavities: neighbours exist, loop vertices distinct
    bits = (np.arange(16)[:, None] >> np.arange(4)) & 1 == 1  # (16, 4)
    cav_ok = ~(bits[None] & ~has[:, None]).any(axis=2)  # (s, 16)
    loop = np.where(bits[None], xv[:, None], -1 - np.arange(4))  # placeholders distinct
    dup = (loop[..., :, None] == loop[..., None, :]) & ~np.eye(4, dtype=bool)
    in_quad = (xv[:, :, None] == quad[:, None, :]).any(axis=2)  # (s, 4)
    dup = dup.any(axis=(2, 3)) | (bits[None] & in_quad[:, None]).any(axis=2)
    cav_ok &= ~dup
    # Only the cavities that can be admissible are measured, each as far as it needs:
    # its triangles' validity level by level up to its first valid level, then their
    # qualities and its spokes' lengths at that level (the measures are row by row,
    # so the figures of the cavities measured are those of measuring every level)
    pending = cav_ok[:, None] & pos_ok[..., None]  # (s, P, 16)
    nl = len(BACKTRACK)
    shape = (ns, npos, 12, nl)

    # spokes p – targets: optimal nodes, then the backtracked nodes per level
    live = (pending[..., None] & _TARGETS).any(axis=2).reshape(-1)  # (s P 8,) spokes used
    p_rep = np.repeat(flat, 8, axis=0)[live]
    t_pts = pts[np.repeat(targets[:, None, :], npos, axis=1).ravel()][live]
    par = shortest_parabola(field, p_rep, t_pts, exact_length=False)
    straight = 0.5 * (p_rep + t_pts)
    s_mid = np.full((ns * npos * 8, nl, 2), np.nan)
    s_mid[live] = (
        straight[:, None] + np.array(BACKTRACK)[None, :, None] * (par.mid - straight)[:, None]
    )
    s_mid = s_mid.reshape(ns, npos, 8, nl, 2)

    # the 12 star triangles at every level: (s, P, 12, L, 6, 2)
    tri_nodes = np.empty((*shape, 6, 2))
    tri_nodes[..., 0, :] = pos[:, :, None, None]
    tri_nodes[..., 1, :] = pts[targets[:, _FROM]][:, None, :, None]
    tri_nodes[..., 2, :] = pts[targets[:, _TO]][:, None, :, None]
    tri_nodes[..., 3, :] = s_mid[:, :, _FROM]
    tri_nodes[..., 4, :] = pts[bnode][:, None, :, None]
    tri_nodes[..., 5, :] = s_mid[:, :, _TO]

    # the 16 cavities: first level where all their triangles are valid
    valid = np.zeros(shape, dtype=bool)
    ok_lvl = np.zeros((ns, npos, 16, nl), dtype=bool)
    for lv in range(nl):
        need = np.nonzero((pending[..., None] & _USES).any(axis=2))  # (s, P, 12) used
        valid[(*need, lv)] = valid_exact(tri_nodes[(*need, lv)])
        ok_lvl[..., lv] = pending & (valid[:, :, None, :, lv] | ~_USES).all(axis=3)
        pending &= ~ok_lvl[..., lv]
    level = np.argmax(ok_lvl, axis=3)  # (s, P, 16)
    any_ok = ok_lvl.any(axis=3)
    # at each valid cavity's level: its spokes' lengths, its triangles' qualities
    at = (level[..., None] == np.arange(nl)) & any_ok[..., None]  # (s, P, 16, L)
    need = np.nonzero((at[..., None, :] & _TARGETS[..., None]).any(axis=2))  # (s, P, 8, L)
    s_len = np.full((ns, npos, 8, nl), np.nan)
    s_len[need] = edge_lengths_fast(
        field, pos[need[:2]], pts[targets[need[0], need[2]]], s_mid[need]
    )
    need = np.nonzero((at[..., None, :] & _USES[..., None]).any(axis=2))  # (s, P, 12, L)
    lens = np.stack(
        [
            s_len[:, :, _FROM],
            np.broadcast_to(blen[:, None, :, None], shape),
            s_len[:, :, _TO],
        ],
        axis=-1,
    )
    q = np.full(shape, np.nan)
    q[need] = quality_from(metric_areas(field, tri_nodes[need]), lens[need])
    q = np.where(valid, q, -np.inf)

    def at_level(v: NDArray) -> NDArray:
        # (s, P, k, L) → (s, P, 16, k): each cavity's row at its level
        return np.take_along_axis(v[:, :, None], level[..., None, None], axis=4)[..., 0]

    q_best = np.where(_USES, at_level(q), np.inf).min(axis=3)  # (s, P, 16)
    sp = at_level(s_len)  # (s, P, 16, 8)
    sp_min = np.where(_TARGETS, sp, np.inf).min(axis=3)
    sp_max = np.where(_TARGETS, sp, -np.inf).max(axis=3)
    n_long_sp = (_TARGETS & (sp > max_length)).sum(axis=3)
    long_left = (~bits[None] & (length[oedge] > max_length)[:, None]).sum(axis=2)  # (s, 16)
    seed_len = length[seeds]
    admissible = (
        cav_ok[:, None]
        & pos_ok[..., None]
        & any_ok
        & (q_best >= min_quality)
        & (sp_min >= min_dist)
        & (sp_max < seed_len[:, None, None])
    )
    score = np.where(admissible, q_best - 10.0 * (n_long_sp + long_left[:, None]), -np.inf)
    best = np.argmax(score.reshape(ns, -1), axis=1)
    good = np.flatnonzero(np.isfinite(score.reshape(ns, -1)[np.arange(ns), best]))
    if good.size == 0:
        return mesh, 0, length
    bp, bm = best[good] // 16, best[good] % 16
    bl = level[good, bp, bm]
    newp = pos[good, bp]

    # greedy, longest edge first: disjoint cavities, new vertices min_dist apart
    removed = np.column_stack([t1[good], t2[good], np.where(bits[bm], nb[good], -1)])
    ci, cj = pairs_within_boxes(newp, search_halfwidths(field, newp, 2.0 * min_dist))
    close = too_close(field, newp[ci], newp[cj], min_dist)
    conflicts: dict[int, list[int]] = {}
    for i, j in zip(ci[close].tolist(), cj[close].tolist(), strict=True):
        conflicts.setdefault(i, []).append(j)
        conflicts.setdefault(j, []).append(i)
    used = np.zeros(len(tris), dtype=bool)
    taken = np.zeros(len(good), dtype=bool)
    for i in np.argsort(-seed_len[good], kind="stable").tolist():
        rem = removed[i][removed[i] >= 0]
        if used[rem].any() or any(taken[j] for j in conflicts.get(i, ())):
            continue
        used[rem] = True
        taken[i] = True
    sel = np.flatnonzero(taken)
    k = len(sel)
    g, bp, bm, bl = good[sel], bp[sel], bm[sel], bl[sel]

    # assemble: new vertices, then the used spokes' nodes
    base = len(pts)
    p_id = base + np.arange(k)
    spoke_used = _TARGETS[bm]  # (k, 8)
    spoke_id = np.full((k, 8), -1)
    spoke_id[spoke_used] = base + k + np.arange(int(spoke_used.sum()))
    spoke_xy = s_mid[g, bp][np.arange(k)[:, None], np.arange(8), bl[:, None]]  # (k, 8, 2)
    new_pts = np.concatenate([pts, pos[g, bp], spoke_xy[spoke_used]])
    tri_used = _USES[bm]  # (k, 12)
    ii, tt = np.nonzero(tri_used)
    fr, to = _FROM[tt], _TO[tt]
    rows = np.column_stack(
        [
            p_id[ii],
            targets[g[ii], fr],
            targets[g[ii], to],
            spoke_id[ii, fr],
            bnode[g[ii], tt],
            spoke_id[ii, to],
        ]
    )
    gone = removed[sel][removed[sel] >= 0]
    keep = np.ones(len(tris), dtype=bool)
    keep[gone] = False
    tris_new = np.concatenate([tris[keep], rows])
    used_nodes = np.zeros(len(new_pts), dtype=bool)
    used_nodes[tris_new.ravel()] = True
    renum = np.where(used_nodes, np.cumsum(used_nodes) - 1, -1)
    out = Mesh(new_pts[used_nodes], renum[tris_new], mesh.box)
    return out, int(k), _carried_lengths(field, mesh, length, out, renum[: len(pts)])
