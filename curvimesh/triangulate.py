"""Delaunay triangulation of the sampled points (paper section 4).

The points are connected "isotropically" (Euclidean Delaunay, scipy's Qhull):
the swap stage later aligns the mesh with the metric. Because the boundary
vertices lie on the sides of the box and include its corners, the convex hull
is the box and the triangulation covers the domain exactly, every boundary
segment between consecutive boundary vertices being a hull edge.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import Delaunay, QhullError

from curvimesh.errors import WorkError
from curvimesh.mesh import Mesh, signed_areas


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
