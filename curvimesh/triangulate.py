"""Delaunay triangulation of the sampled points (paper section 4).

The points are connected "isotropically" (Euclidean Delaunay, scipy's Qhull):
the swap stage later aligns the mesh with the metric. Because the boundary
vertices lie on the sides of the box and include its corners, the convex hull
is the box and the triangulation covers the domain exactly, every boundary
segment between consecutive boundary vertices being a hull edge.
"""

from __future__ import annotations

import weakref

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import Delaunay, QhullError

from curvimesh import kernels
from curvimesh.errors import WorkError
from curvimesh.mesh import Mesh, apply_flips, flip_candidates, independent_flips, signed_areas


def delaunay(points: NDArray, *, box: tuple[float, float, float, float] | None = None) -> Mesh:
    """Delaunay triangulation ``Mesh`` (P1, counter-clockwise) of points ``(n, 2)``.

    Raises :class:`WorkError` if Qhull fails, leaves a point out, or makes a
    flat triangle.
    """
    pts = np.asarray(points, dtype=float)
    if len(pts) < 3:
        raise WorkError(f"cannot triangulate {len(pts)} points")
    try:
        tri = Delaunay(pts, qhull_options="Qbb Qc Qz Q12")
    except QhullError as exc:
        raise WorkError(f"Delaunay triangulation failed: {str(exc).splitlines()[0]}") from None
    simplices = np.asarray(tri.simplices, dtype=np.int64)
    area = signed_areas(pts, simplices)
    flip = area < 0
    simplices[flip] = simplices[flip][:, [0, 2, 1]]
    scale = np.ptp(pts, axis=0).max() ** 2
    flat = np.abs(area) <= 1e-14 * scale
    if flat.any():
        simplices = simplices[~flat]
    used = np.zeros(len(pts), dtype=bool)
    used[simplices.ravel()] = True
    if not used.all():
        missing = np.flatnonzero(~used)
        p = pts[missing[0]]
        raise WorkError(
            f"Delaunay triangulation left {missing.size} point(s) out, "
            f"e.g. ({p[0]:.6g}, {p[1]:.6g}) (duplicate points?)"
        )
    return Mesh(pts, simplices, box)


def _in_circle_metric(pa, pb, pc, pd, m: NDArray) -> NDArray:
    """In-circle determinant of d against CCW (a, b, c) after the map x ↦ Lᵀx, M = L Lᵀ.

    Positive when d lies inside the circumcircle of (a, b, c) in the metric M
    ``(k, 2, 2)`` (the classical Delaunay predicate of Lawson's flips, applied
    in the space where M is the identity; the map keeps orientation).
    """
    chol = np.linalg.cholesky(m)  # M = L Lᵀ

    def tr(p):
        return np.einsum("kji,kj->ki", chol, p - pd)  # Lᵀ (p − d)

    a, b, c = tr(pa), tr(pb), tr(pc)
    na, nb, nc = (a**2).sum(1), (b**2).sum(1), (c**2).sum(1)
    return (
        a[:, 0] * (b[:, 1] * nc - nb * c[:, 1])
        - a[:, 1] * (b[:, 0] * nc - nb * c[:, 0])
        + na * (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0])
    )


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
    t = np.repeat(np.arange(len(corners)), 3).reshape(-1, 3)
    nbr_k = np.where(nbr >= 0, np.argmax(mesh.neighbours[nbr] == t[..., None], axis=2), -1)
    bad = np.zeros(2)
    if kernels.metric_delaunay_flips(cm.g, pts, corners, nbr, nbr_k, max_rounds, bad) < 0:
        field.tensor(bad[None])  # raises MetricError naming the point
    return Mesh(pts, corners, mesh.box)


#: The last :func:`metric_delaunay_of` result of each field: (points, box, mesh).
_LAST: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def metric_delaunay_of(
    field, points: NDArray, box: tuple[float, float, float, float] | None = None
) -> Mesh:
    """``metric_delaunay(field, delaunay(points, box=box))``, remembered for the last
    point set of each field.

    Gap filling (:func:`curvimesh.fill.fill_gaps`) ends on the triangulation of
    its final points, which the triangulation stage asks for again: the second
    call returns the same mesh (both are pure functions of the points) without
    a second Qhull run and Lawson flips.
    """
    pts = np.asarray(points, dtype=float)
    last = _LAST.get(field)
    if (
        last is not None
        and last[1] == box
        and last[0].shape == pts.shape
        and np.array_equal(last[0], pts)
    ):
        return last[2]
    mesh = metric_delaunay(field, delaunay(pts, box=box))
    _LAST[field] = (pts.copy(), box, mesh)
    return mesh
