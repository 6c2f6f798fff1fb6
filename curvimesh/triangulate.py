"""Delaunay triangulation of the sampled points (paper section 4).

The points are connected "isotropically" (Euclidean Delaunay: Bowyer–Watson in
compiled code, certified, else scipy's Qhull): the swap stage later aligns the
mesh with the metric. Because the boundary vertices lie on the sides of the box
and include its corners, the convex hull is the box and the triangulation covers
the domain exactly, every boundary segment between consecutive boundary vertices
being a hull edge.
"""

from __future__ import annotations

import weakref

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import Delaunay, QhullError

from curvimesh import kernels
from curvimesh.errors import WorkError
from curvimesh.mesh import (
    Mesh,
    apply_flips,
    flip_candidates,
    independent_flips,
    is_conforming,
    signed_areas,
    sorted_find,
)


def _qhull_triangles(pts: NDArray) -> NDArray[np.int64]:
    """Triangles ``(m, 3)`` of Qhull's Delaunay triangulation of ``pts`` ``(n, 2)``,
    counter-clockwise, without the flat ones (area ≤ 1e-14 × the box's largest side²).

    Raises :class:`WorkError` if Qhull fails.
    """
    try:
        tri = Delaunay(pts, qhull_options="Qbb Qc Qz Q12")
    except QhullError as exc:
        raise WorkError(f"Delaunay triangulation failed: {str(exc).splitlines()[0]}") from None
    simplices = np.asarray(tri.simplices, dtype=np.int64)
    area = signed_areas(pts, simplices)
    flip = area < 0
    simplices[flip] = simplices[flip][:, [0, 2, 1]]
    return simplices[np.abs(area) > _FLAT * _area_scale(pts)]


#: A triangle whose area is at most this fraction of :func:`_area_scale` is flat.
_FLAT = 1e-14


def _area_scale(pts: NDArray) -> float:
    """The square of the largest side of the bounding box of ``pts`` ``(n, 2)``."""
    return float(np.ptp(pts, axis=0).max() ** 2)


def canonical_triangles(tris: NDArray) -> NDArray[np.int64]:
    """Triangles ``(m, 3)`` in canonical order: each row rotated (which keeps its
    orientation) to start at its smallest id, then the rows sorted lexicographically.

    Two lists of the same triangles give the same array.

    >>> canonical_triangles(np.array([[5, 3, 4], [2, 0, 1], [1, 3, 0]])).tolist()
    [[0, 1, 2], [0, 1, 3], [3, 4, 5]]
    """
    t = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
    first = np.argmin(t, axis=1)
    t = np.take_along_axis(t, (first[:, None] + np.arange(3)) % 3, axis=1)
    n = int(t.max(initial=0)) + 1
    if n < 2**21:  # one key (t0 n + t1) n + t2 below 2⁶³; a stable sort merges sorted runs
        order = np.argsort((t[:, 0] * n + t[:, 1]) * n + t[:, 2], kind="stable")
    else:
        order = np.lexsort((t[:, 2], t[:, 1], t[:, 0]))
    return np.ascontiguousarray(t[order])


def delaunay(points: NDArray, *, box: tuple[float, float, float, float] | None = None) -> Mesh:
    """Delaunay triangulation ``Mesh`` (P1, counter-clockwise) of points ``(n, 2)``.

    The points are inserted one at a time in compiled code
    (:func:`curvimesh.kernels.bowyer_watson`, in the order of :func:`_walk_order`)
    and the result is certified the unique Delaunay triangulation (:func:`_certified`);
    where it cannot be (co-circular points, a predicate not decided), Qhull
    triangulates the points instead. At the 36,372 points sampled for the three
    toys (s = 4.87): the insertion 29 ms and the certificate 24 ms, Qhull 180 –
    200 ms.

    The triangles come in canonical order (:func:`canonical_triangles`): the mesh
    is a function of the set of triangles, whichever way it was computed (as
    :func:`delaunay_insert` does). Flat triangles (which Qhull can make of
    collinear points) are dropped. Raises :class:`WorkError` if Qhull fails or
    leaves a point out.
    """
    pts = np.asarray(points, dtype=float)
    if len(pts) < 3:
        raise WorkError(f"cannot triangulate {len(pts)} points")
    mesh = _certified_delaunay(pts, box)
    if mesh is not None:
        return mesh
    simplices = _qhull_triangles(pts)
    used = np.zeros(len(pts), dtype=bool)
    used[simplices.ravel()] = True
    if not used.all():
        missing = np.flatnonzero(~used)
        p = pts[missing[0]]
        raise WorkError(
            f"Delaunay triangulation left {missing.size} point(s) out, "
            f"e.g. ({p[0]:.6g}, {p[1]:.6g}) (duplicate points?)"
        )
    return Mesh(pts, canonical_triangles(simplices), box)


def _certified_delaunay(
    pts: NDArray, box: tuple[float, float, float, float] | None = None
) -> Mesh | None:
    """The Delaunay triangulation of ``pts`` ``(n, 2)``, triangles in canonical order
    (:func:`canonical_triangles`), by :func:`curvimesh.kernels.bowyer_watson` (in the
    order of :func:`_walk_order`), when it is certified the unique one
    (:func:`_certified`), hence Qhull's; else None. The mesh keeps the tables the
    certificate computed (edges, neighbours)."""
    pts = np.ascontiguousarray(pts, dtype=float)
    tris, status = kernels.bowyer_watson(pts, _walk_order(pts), kernels.ENCLOSING_SCALE)
    if status != 0 or len(tris) == 0:
        return None
    mesh = Mesh(pts, canonical_triangles(tris), box)
    return mesh if _certified(mesh) else None


def _walk_order(q: NDArray) -> NDArray[np.int64]:
    """Indices ``(k,)`` that order points ``(k, 2)`` along a boustrophedon: about √k
    horizontal bands, run left to right and right to left in turn, so that each
    walk (:func:`curvimesh.kernels.delaunay_conflicts`) starts near its point."""
    if len(q) < 2:
        return np.arange(len(q))
    lo, hi = q.min(axis=0), q.max(axis=0)
    bands = int(np.ceil(np.sqrt(len(q))))
    band = np.minimum(
        ((q[:, 1] - lo[1]) / max(hi[1] - lo[1], 1e-300) * bands).astype(np.int64), bands - 1
    )
    x = np.where(band % 2 == 0, q[:, 0], -q[:, 0])
    return np.lexsort((x, band))


def strictly_delaunay(mesh: Mesh) -> NDArray[np.bool_]:
    """``(E,)`` for each edge of :attr:`Mesh.edges`: True on the boundary, and on an
    interior edge a-b of triangles (a, b, c) and (b, a, d) when d lies outside the
    circumcircle of (a, b, c) by more than the predicates' error bound
    (:func:`curvimesh.kernels.strict_delaunay_sides`).

    >>> sq = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]
    >>> strictly_delaunay(Mesh(sq, [[0, 1, 2], [0, 2, 3]])).tolist()  # co-circular
    [True, False, True, True, True]
    >>> kite = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 2.0]]
    >>> strictly_delaunay(Mesh(kite, [[0, 1, 2], [0, 2, 3]])).tolist()
    [True, True, True, True, True]
    """
    sides = np.empty((len(mesh.corners), 3), dtype=bool)
    corners = np.ascontiguousarray(mesh.corners)
    kernels.strict_delaunay_sides(mesh.points, corners, mesh.neighbours, sides)
    ok = np.ones(len(mesh.edges), dtype=bool)
    ok[mesh.tri_edges[~sides]] = False
    return ok


def _certified(new: Mesh, old: Mesh | None = None) -> bool:
    """Whether ``new`` is the unique Delaunay triangulation of its points (knowing that
    ``old``, if given, is a triangulation whose boundary it must keep).

    Checked: every triangle counter-clockwise beyond the error bound and not flat
    for :func:`delaunay` (area above 10 × its threshold); conforming (an edge in
    at most two triangles, in opposite directions); the same boundary edges as
    ``old`` (if given), turning left or straight at every boundary vertex (a convex
    polygon, hence the convex hull of the points); the triangles' total area
    that of the polygon (each interior edge having a triangle on either side,
    the triangles then cover it exactly once); Euler's N − E + T = 1 with all N
    points (none left out); every interior edge strictly locally Delaunay
    (:func:`strictly_delaunay`). A triangulation of the convex hull whose edges
    are all strictly locally Delaunay is the Delaunay triangulation, and the
    only one.
    """
    pts, corners = new.points, new.corners
    u = pts[corners[:, 1]] - pts[corners[:, 0]]
    v = pts[corners[:, 2]] - pts[corners[:, 0]]
    cross = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]  # twice the signed area
    perm = np.abs(u[:, 0] * v[:, 1]) + np.abs(u[:, 1] * v[:, 0])
    if not np.all(cross > kernels.PREDICATE_TOL * perm):
        return False
    if not 0.5 * cross.min() > 10 * _FLAT * _area_scale(pts):
        return False
    if not is_conforming(new):
        return False
    if old is not None and not np.array_equal(
        new.edges[new.boundary_edges], old.edges[old.boundary_edges]
    ):
        return False
    lines = new.boundary_lines  # the domain on their left
    after = np.full(len(pts), -1, dtype=np.int64)
    after[lines[:, 0]] = np.arange(len(lines))
    nxt = after[lines[:, 1]]
    if np.any(nxt < 0):
        return False
    a, b = pts[lines[:, 0]], pts[lines[:, 1]]
    s, e = b - a, b[nxt] - a[nxt]
    if np.any(s[:, 0] * e[:, 1] - s[:, 1] * e[:, 0] < 0):
        return False
    polygon = 0.5 * np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])  # shoelace
    if not abs(0.5 * cross.sum() - polygon) <= 1e-9 * abs(polygon):
        return False
    if len(pts) - len(new.edges) + len(corners) != 1:
        return False
    return bool(strictly_delaunay(new).all())


def delaunay_insert(mesh: Mesh, new: NDArray) -> Mesh | None:
    """The Delaunay triangulation (as :func:`delaunay`) of the points of ``mesh``
    followed by ``new`` ``(k, 2)``, updated locally, or None when it cannot be
    certified (then call :func:`delaunay`).

    ``mesh`` is the Delaunay triangulation of its points P (as :func:`delaunay`
    makes it). The conflict set C, the triangles whose circumcircle strictly
    holds a point of Q = ``new``, comes from walks and searches through neighbours
    (:func:`curvimesh.kernels.delaunay_conflicts`); S is Q and the corners of
    C. S is triangulated (:func:`_certified_delaunay`, else Qhull), and the
    triangles of DT(S) inside the region R that C covers replace C. Why: the
    triangles outside C keep empty circumcircles, so they stay in DT(P ∪ Q); R
    is bounded by their edges (and hull edges), which are edges of DT(S) too
    (empty circumcircles, corners in S); DT(P ∪ Q) tiles R with triangles whose
    corners are in S (a point of P in R is a corner of C) and whose
    circumcircles are empty of all points, hence of S: they are the triangles
    of DT(S) in R (points in general position).
    These are found without geometry: from the triangle of DT(S) on the inner
    side of each boundary edge of R, through the edges of DT(S) that do not
    bound R (:func:`curvimesh.kernels.flood_fill`).

    The result is certified (:func:`_certified`) to be a triangulation of the
    same convex region, using every point, whose every interior edge is
    strictly locally Delaunay: the unique Delaunay triangulation, which
    :func:`delaunay` computes too, in the same canonical order. Returns None
    when a walk or an in-circle test is not decided beyond the error bound
    (a new point outside the triangulation, on a circumcircle, or on a point),
    when R's boundary is not in DT(S), or when the check fails (co-circular
    points, where Qhull's choice among Delaunay triangulations cannot be
    foreseen).
    """
    q = np.asarray(new, dtype=float).reshape(-1, 2)
    if len(q) == 0:
        return mesh
    pts_old = np.asarray(mesh.points)
    corners = np.ascontiguousarray(mesh.corners)
    nbr = np.ascontiguousarray(mesh.neighbours)
    n = len(pts_old)
    conflict = np.zeros(len(corners), dtype=bool)
    qs = np.ascontiguousarray(q[_walk_order(q)])
    if kernels.delaunay_conflicts(pts_old, corners, nbr, qs, conflict) < 0:
        return None
    # an edge not strictly Delaunay (co-circular points) between two triangles that
    # stay would fail the certificate: give up before triangulating
    sides = np.empty((len(corners), 3), dtype=bool)
    if kernels.strict_delaunay_sides(pts_old, corners, nbr, sides):
        if (~sides & (nbr >= 0) & ~conflict[:, None] & ~conflict[nbr]).any():
            return None
    ids = np.concatenate([np.unique(corners[conflict]), n + np.arange(len(q))])
    pts = np.concatenate([pts_old, q])
    s_pts = pts[ids]
    s_mesh = _certified_delaunay(s_pts)
    if s_mesh is None:
        try:
            s_mesh = Mesh(s_pts, _qhull_triangles(s_pts))
        except WorkError:
            return None
    local = s_mesh.triangles
    # R's boundary: the sides of C's triangles towards a triangle outside C or none,
    # directed with R on their left, in S's numbering
    t, k = np.nonzero(~conflict[nbr] | (nbr < 0))
    inner = conflict[t]
    t, k = t[inner], k[inner]
    ns = len(ids)
    u = np.searchsorted(ids, corners[t, k])
    v = np.searchsorted(ids, corners[t, (k + 1) % 3])
    # the sides of DT(S) by their directed end pairs
    key = (local * ns + np.roll(local, -1, axis=1)).ravel()  # side k: corners k → k + 1
    order = np.argsort(key)
    sorted_key = key[order]

    def side_of(a: NDArray, b: NDArray) -> NDArray:
        """Flat index (3 t + k) of the side a → b of DT(S), or −1."""
        pos, found = sorted_find(sorted_key, a * ns + b)
        return np.where(found, order[pos], -1)

    seed, twin = side_of(u, v), side_of(v, u)
    if (seed < 0).any():
        return None
    wall = np.zeros(3 * len(local), dtype=bool)
    wall[seed] = True
    wall[twin[twin >= 0]] = True
    inside = np.zeros(len(local), dtype=bool)
    s_nbr = np.ascontiguousarray(s_mesh.neighbours)
    kernels.flood_fill(s_nbr, wall.reshape(-1, 3), seed // 3, inside)
    if inside[twin[twin >= 0] // 3].any():  # R's boundary does not close it
        return None
    tris = np.concatenate([corners[~conflict], ids[local[inside]]])
    out = Mesh(pts, canonical_triangles(tris), mesh.box)
    return out if _certified(out, mesh) else None


def in_circle(a: NDArray, b: NDArray, c: NDArray, d: NDArray) -> NDArray:
    """In-circle determinant ``(k,)`` of d against counter-clockwise (a, b, c), each
    ``(k, 2)``: positive when d lies inside their circumcircle (the classical
    Delaunay predicate of Lawson's flips, in floating point).

    >>> in_circle(*np.array([[[0.0, 0.0]], [[1.0, 0.0]], [[0.0, 1.0]], [[0.5, 0.5]]])).tolist()
    [0.5]
    """
    a, b, c = a - d, b - d, c - d
    na, nb, nc = (a**2).sum(1), (b**2).sum(1), (c**2).sum(1)
    return (
        a[:, 0] * (b[:, 1] * nc - nb * c[:, 1])
        - a[:, 1] * (b[:, 0] * nc - nb * c[:, 0])
        + na * (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0])
    )


def delaunay_flips(xy: NDArray, tris: NDArray, *, max_rounds: int = 200) -> NDArray[np.int64]:
    """Lawson's flips of the interior edges of a planar triangulation ``tris`` ``(m, 3)``
    (counter-clockwise) of points ``xy`` ``(n, 2)`` towards Delaunay: the edge a-b of
    the convex quad a-d-b-c goes to c-d when d lies inside the circle of (a, b, c)
    (:func:`in_circle`, beyond 1e-10 of the squared scale). Its boundary edges are
    never flipped, so a triangulation of a polygon becomes its constrained Delaunay
    triangulation (Lee and Lin 1986). Rounds of non-conflicting flips."""
    xy = np.asarray(xy, dtype=float)
    tris = np.array(tris, dtype=np.int64)
    for _ in range(max_rounds):
        _, t1, t2, a, b, c, d = flip_candidates(Mesh(xy, tris))
        pa, pb, pc, pd = xy[a], xy[b], xy[c], xy[d]
        det = in_circle(pa, pb, pc, pd)
        scale = ((pa - pd) ** 2).sum(1)
        convex = (orient(pa, pd, pc) > 0) & (orient(pd, pb, pc) > 0)
        cand = np.flatnonzero(convex & (det > 1e-10 * scale**2))
        if cand.size == 0:
            break
        priority = det[cand] / scale[cand] ** 2
        chosen = cand[independent_flips(t1[cand], t2[cand], priority, len(tris))]
        tris = apply_flips(tris, chosen, t1, t2, a, b, c, d)
    return tris


def orient(p: NDArray, q: NDArray, r: NDArray) -> NDArray:
    """Twice the signed area of the triangles (p, q, r), each ``(..., 2)``: positive when
    counter-clockwise."""
    return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (
        r[..., 0] - p[..., 0]
    )


def _crosses(xy: NDArray, a: int, b: int, p: NDArray, q: NDArray) -> NDArray:
    """``(k,)`` whether the edges p-q (corner indices ``(k,)``) cross the open segment a-b
    at a point inside both."""
    pa, pb, pp, pq = xy[a], xy[b], xy[p], xy[q]
    apart = orient(pa, pb, pp) * orient(pa, pb, pq) < 0
    return apart & (orient(pp, pq, pa) * orient(pp, pq, pb) < 0)


def _sloan(xy: NDArray, tris: list[list[int]], a: int, b: int) -> list[list[int]] | None:
    """The triangles ``tris`` (counter-clockwise) that the segment a-b crosses, flipped
    until it is an edge of theirs: each crossed edge in turn, flipped where its quad is
    strictly convex, taken again later while it or the new diagonal still crosses
    (Sloan 1993, which ends). None after too many turns."""
    holders: dict[tuple[int, int], int] = {}
    for i, t in enumerate(tris):
        for j in range(3):
            holders[t[j], t[(j + 1) % 3]] = i
    queue = []
    for t in tris:
        for j in range(3):
            p, q = t[j], t[(j + 1) % 3]
            if p < q and (q, p) in holders and _crosses(xy, a, b, np.array([p]), np.array([q]))[0]:
                queue.append((p, q))
    turns = 0
    while queue:
        turns += 1
        if turns > 50 * (len(tris) + 1) ** 2:
            return None
        p, q = queue.pop(0)
        i1, i2 = holders[p, q], holders[q, p]
        r = next(v for v in tris[i1] if v not in (p, q))
        s_ = next(v for v in tris[i2] if v not in (p, q))
        if orient(xy[p], xy[s_], xy[r]) <= 0 or orient(xy[s_], xy[q], xy[r]) <= 0:
            queue.append((p, q))
            continue
        for t in (tris[i1], tris[i2]):
            for j in range(3):
                del holders[t[j], t[(j + 1) % 3]]
        tris[i1], tris[i2] = [p, s_, r], [s_, q, r]
        for i in (i1, i2):
            t = tris[i]
            for j in range(3):
                holders[t[j], t[(j + 1) % 3]] = i
        if {r, s_} != {a, b} and _crosses(xy, a, b, np.array([r]), np.array([s_]))[0]:
            queue.append((r, s_))
    return tris


def insert_segments(
    xy: NDArray, tris: NDArray, segments: NDArray
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """A planar triangulation ``tris`` ``(m, 3)`` of points ``xy`` (counter-clockwise)
    with each segment a → b of ``segments`` ``(k, 2)`` made one of its edges, in turn,
    by flips of the triangles it crosses (:func:`_sloan`). Returns the triangles and
    the segments that could not be inserted ``(j, 2)``: those through a point, and
    those crossing a segment inserted before (which they would take out). Flips made
    later (:func:`delaunay_flips`) keep only the segments on the boundary."""
    xy = np.asarray(xy, dtype=float)
    tris = np.array(tris, dtype=np.int64)
    segments = np.asarray(segments, dtype=np.int64).reshape(-1, 2)
    n = len(xy)
    ends = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    keys = segments.min(axis=1) * n + segments.max(axis=1)
    present = np.isin(keys, ends.min(axis=1) * n + ends.max(axis=1))
    done = keys[present]  # the segments that are edges, which the others must not cross
    txy = xy[tris]
    lo_t, hi_t = txy.min(axis=1), txy.max(axis=1)
    failed = []
    for i in np.flatnonzero(~present).tolist():
        a, b = segments[i].tolist()
        pa, pb = xy[a], xy[b]
        near = (hi_t >= np.minimum(pa, pb)).all(axis=1) & (lo_t <= np.maximum(pa, pb)).all(axis=1)
        near = np.flatnonzero(near)
        t = tris[near]
        if ((t == a).any(axis=1) & (t == b).any(axis=1)).any():
            done = np.append(done, keys[i])
            continue
        p, q = t.ravel(), np.roll(t, -1, axis=1).ravel()
        cross = _crosses(xy, a, b, p, q).reshape(-1, 3)
        walls = np.isin(np.minimum(p, q) * n + np.maximum(p, q), done).reshape(-1, 3)
        d = pb - pa
        v = np.unique(t)
        v = v[(v != a) & (v != b)]
        along = (xy[v] - pa) @ d / (d @ d)
        on = (np.abs(orient(pa, pb, xy[v])) <= 1e-12 * (d @ d)) & (along > 0) & (along < 1)
        crossed = cross.any(axis=1)
        if on.any() or (cross & walls).any() or not crossed.any():
            failed.append((a, b))
            continue
        flipped = _sloan(xy, t[crossed].tolist(), a, b)
        if flipped is None:
            failed.append((a, b))
            continue
        at = near[crossed]
        tris[at] = np.array(flipped, dtype=np.int64)
        lo_t[at], hi_t[at] = xy[tris[at]].min(axis=1), xy[tris[at]].max(axis=1)
        done = np.append(done, keys[i])
    return tris, np.array(failed, dtype=np.int64).reshape(-1, 2)


def _in_circle_metric(pa, pb, pc, pd, m: NDArray) -> NDArray:
    """:func:`in_circle` of d against CCW (a, b, c) after the map x ↦ Lᵀx, M = L Lᵀ:
    positive when d lies inside the circumcircle of (a, b, c) in the metric M
    ``(k, 2, 2)`` (the predicate applied in the space where M is the identity; the
    map keeps orientation).
    """
    chol = np.linalg.cholesky(m)  # M = L Lᵀ

    def tr(p):
        return np.einsum("kji,kj->ki", chol, p - pd)  # Lᵀ (p − d)

    a, b, c = tr(pa), tr(pb), tr(pc)
    return in_circle(a, b, c, np.zeros_like(a))


def metric_delaunay(field, mesh: Mesh, *, max_rounds: int = 200) -> Mesh:
    """Lawson flips of straight edges towards the Delaunay triangulation in the metric.

    An interior edge a-b of the convex quad a-d-b-c is flipped to c-d when d
    lies inside the circumcircle of (a, b, c) measured in the metric at the
    quad's centroid (the same metric judges both diagonals, so an edge is never
    flipped back in the next round unless a neighbour changed). Flips are made
    in rounds of non-conflicting candidates, by decreasing violation, until
    none is left or ``max_rounds``. With a constant metric this is the
    anisotropic Delaunay triangulation (Borouchaki, George et al. 1997).
    """
    pts = np.asarray(mesh.points)
    cm = field.kernel
    if cm is not None and len(mesh.triangles):
        return _metric_delaunay_compiled(field, cm, mesh, max_rounds)
    corners = np.array(mesh.corners)
    for _ in range(max_rounds):
        cur = Mesh(pts, corners, mesh.box)
        _, t1, t2, a, b, c, d = flip_candidates(cur)
        if len(a) == 0:
            break
        convex = (signed_areas(pts, np.column_stack([a, d, c])) > 0) & (
            signed_areas(pts, np.column_stack([d, b, c])) > 0
        )
        idx = np.flatnonzero(convex)
        centroid = 0.25 * (pts[a[idx]] + pts[b[idx]] + pts[c[idx]] + pts[d[idx]])
        g = field.tensor(centroid)
        det = _in_circle_metric(pts[a[idx]], pts[b[idx]], pts[c[idx]], pts[d[idx]], g)
        # relative threshold: ignore co-circular quads (round-off)
        scale = np.einsum("ki,kij,kj->k", pts[a[idx]] - pts[d[idx]], g, pts[a[idx]] - pts[d[idx]])
        viol = det > 1e-10 * scale**2
        cand = idx[viol]
        if cand.size == 0:
            break
        chosen = cand[
            independent_flips(t1[cand], t2[cand], det[viol] / scale[viol] ** 2, len(corners))
        ]
        corners = apply_flips(corners, chosen, t1, t2, a, b, c, d)
    return Mesh(pts, corners, mesh.box)


def _metric_delaunay_compiled(field, cm, mesh: Mesh, max_rounds: int) -> Mesh:
    """:func:`metric_delaunay` by :func:`curvimesh.kernels.metric_delaunay_flips` (the
    same rounds, flips and order; only the edges of changed triangles measured again)."""
    pts = np.ascontiguousarray(mesh.points, dtype=float)
    corners = np.array(mesh.corners, dtype=np.int64)
    nbr = np.array(mesh.neighbours, dtype=np.int64)
    nbr_k = np.array(mesh.neighbour_sides, dtype=np.int64)
    bad = np.zeros(2)
    if kernels.metric_delaunay_flips(cm.g, pts, corners, nbr, nbr_k, max_rounds, bad) < 0:
        field.tensor(bad[None])  # raises MetricError naming the point
    return Mesh(pts, corners, mesh.box)


#: The last :func:`metric_delaunay_of` call of each field: (points, box, Euclidean
#: Delaunay mesh, result).
_LAST: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def metric_delaunay_of(
    field, points: NDArray, box: tuple[float, float, float, float] | None = None
) -> Mesh:
    """``metric_delaunay(field, delaunay(points, box=box))``, remembered for the last
    point set of each field.

    Gap filling (:func:`curvimesh.fill.fill_gaps`) ends on the triangulation of
    its final points, which the triangulation stage asks for again: the second
    call returns the same mesh without a second triangulation and Lawson flips.
    Between its rounds the points only grow (new ones appended): when the last
    call's points are the first rows of ``points`` (same box), the Euclidean
    Delaunay triangulation is updated by :func:`delaunay_insert` instead of
    triangulating every point, falling back to :func:`delaunay` when the update
    cannot be certified. Both give the same array (the unique Delaunay
    triangulation in canonical order), so the result stays a pure function of
    the points.
    """
    pts = np.asarray(points, dtype=float)
    last = _LAST.get(field)
    euclid = None
    if last is not None and last[1] == box:
        old = last[0]
        if old.shape == pts.shape and np.array_equal(old, pts):
            return last[3]
        if len(old) < len(pts) and np.array_equal(old, pts[: len(old)]):
            euclid = delaunay_insert(last[2], pts[len(old) :])
    if euclid is None:
        euclid = delaunay(pts, box=box)
    mesh = metric_delaunay(field, euclid)
    _LAST[field] = (pts.copy(), box, euclid, mesh)
    return mesh
