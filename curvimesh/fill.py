"""Filling the gaps that frontal sampling leaves where fronts meet.

Algorithm 1 never puts two points closer than ``min_dist``, but where two
fronts meet it can leave a gap up to twice as wide: the Delaunay edges across
it come out longer than the unit range (the long edges of the paper's
section 5.1). Here the sampled points are triangulated (Delaunay in the
metric), and the middle node of the shortest parabola of every edge longer
than ``max_length`` is offered as a new point, longest edges first, after the
metric circumcentres of the triangles whose circumradius exceeds
max_length / 2 (Delaunay refinement, Chew 1989; in a Delaunay mesh whose
circumradii are all below max_length / 2 no edge is longer than max_length),
under the same rules as Algorithm 1's tentative points (inside, away from the boundary),
but never closer than ``fill_dist`` (0.75, not ``min_dist``) to any point: a gap
shorter than 1.5 is left to vertex relocation. Rounds repeat until no point is
added.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from curvimesh.freenode import bounded_lengths
from curvimesh.mesh import sorted_find, sorted_member, sorted_union
from curvimesh.metric import MetricField
from curvimesh.sampling import SamplingOptions, admissible_rows, conflict_free
from curvimesh.spatial import PointIndex
from curvimesh.triangulate import metric_delaunay_of


def metric_circumcentres(
    field: MetricField, pts: NDArray, tris: NDArray
) -> tuple[NDArray, NDArray]:
    """Circumcentres ``(m, 2)`` and circumradii ``(m,)`` in the metric at the centroids.

    With M = L Lᵀ at the centroid, the corners are mapped by x ↦ Lᵀx, where M
    is the identity; the Euclidean circumcentre there is mapped back.
    """
    p = pts[tris[:, :3]]  # (m, 3, 2)
    g = field.tensor(p.mean(axis=1))
    lt = np.swapaxes(np.linalg.cholesky(g), 1, 2)  # Lᵀ
    q = np.einsum("mij,mkj->mki", lt, p - p[:, :1])  # corners relative to corner 0, mapped
    b, c = q[:, 1], q[:, 2]
    d = 2.0 * (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0])
    nb, nc = (b**2).sum(1), (c**2).sum(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.column_stack([(c[:, 1] * nb - b[:, 1] * nc) / d, (b[:, 0] * nc - c[:, 0] * nb) / d])
    radius = np.hypot(u[:, 0], u[:, 1])
    centre = p[:, 0] + np.linalg.solve(lt, u[..., None])[..., 0]
    return centre, radius


def circumcentres_again(
    field: MetricField,
    pts: NDArray,
    tris: NDArray,
    keys: NDArray,
    known: tuple[NDArray, NDArray, NDArray] | None,
) -> tuple[NDArray, NDArray]:
    """:func:`metric_circumcentres` of triangles ``(m, 3+)`` whose corner ids in order
    have the keys ``keys`` ``(m,)`` (:func:`_source_keys`), taken from ``known``
    (ascending keys, centres, radii of an earlier call on the same points) where a
    triangle is there: each row is a function of its own corners, in order."""
    if known is None or len(known[0]) == 0:
        return metric_circumcentres(field, pts, tris)
    old, old_centre, old_radius = known
    pos, hit = sorted_find(old, keys)
    centre, radius = np.empty((len(tris), 2)), np.empty(len(tris))
    centre[hit], radius[hit] = old_centre[pos[hit]], old_radius[pos[hit]]
    miss = ~hit
    centre[miss], radius[miss] = metric_circumcentres(field, pts, tris[miss])
    return centre, radius


def _source_keys(ids: NDArray, n: int) -> NDArray:
    """One int64 key per row of ids (i, j, k) over n points (k = −1 for a pair):
    ((i (n + 1) + j) (n + 1) + k + 1), below 2⁶³ up to 2 million points."""
    b = n + 1
    return (ids[:, 0] * b + ids[:, 1]) * b + ids[:, 2] + 1


def _renumbered(keys: NDArray, n: int, m: int) -> NDArray:
    """:func:`_source_keys` over n points as they are over m ≥ n (the ids stay)."""
    b = n + 1
    ids = np.column_stack([keys // (b * b), keys // b % b, keys % b - 1])
    return _source_keys(ids, m)


def fill_gaps(
    field: MetricField,
    points: NDArray,
    options: SamplingOptions | None = None,
    *,
    max_length: float = 1.4,
    max_rounds: int = 8,
) -> NDArray:
    """Points ``(n', 2)``: ``points`` ``(n, 2)`` followed by the gap-filling ones."""
    opt = options or SamplingOptions()
    gap_opt = replace(opt, min_dist=opt.fill_dist)
    pts = np.asarray(points, dtype=float)
    index = PointIndex()
    index.add(pts)
    done_keys = np.zeros(0, dtype=np.int64)  # edges already measured and found short
    refused = np.zeros(0, dtype=np.int64)  # sources of candidates refused for good
    known = None  # the last round's triangles (ascending keys), circumcentres and radii
    for _ in range(max_rounds):
        mesh = metric_delaunay_of(field, pts, field.box)
        e = mesh.edges
        n = len(pts)
        keys = e[:, 0] * n + e[:, 1]
        fresh = ~sorted_member(done_keys, keys)
        e, keys = e[fresh], keys[fresh]
        if len(e) == 0:
            break
        # the straight segment bounds the shortest parabola from above: only the
        # edges it leaves long are searched
        length, mid = bounded_lengths(field, pts[e[:, 0]], pts[e[:, 1]], long=max_length)
        long = length > max_length
        done_keys = sorted_union(done_keys, keys[~long])
        # Delaunay refinement: a triangle whose empty circumcircle (in the metric)
        # has a radius above max_length / 2 can take its circumcentre.
        tri_keys = _source_keys(mesh.triangles[:, :3], n)
        centre, radius = circumcentres_again(field, pts, mesh.triangles, tri_keys, known)
        big = np.isfinite(radius) & (radius > 0.5 * max_length)
        if not long.any() and not big.any():
            break
        by_radius = np.argsort(-radius[big], kind="stable")
        by_length = np.argsort(-length[long], kind="stable")
        cand = np.concatenate([centre[big][by_radius], mid[long][by_length]])
        # each candidate's source, a triangle or an edge (sorted corner ids): one
        # refused against the points is refused for good (the points only grow)
        tri = np.sort(mesh.triangles[:, :3][big][by_radius], axis=1)
        edge = np.column_stack([e[long][by_length], np.full(int(long.sum()), -1)])
        source = np.concatenate([tri, edge])
        keys = _source_keys(source, n)
        fresh = ~sorted_member(refused, keys)
        cand, keys = cand[fresh], keys[fresh]
        rows, regions = admissible_rows(field, index, cand, gap_opt)
        out = np.ones(len(cand), dtype=bool)
        out[rows] = False
        refused = sorted_union(refused, keys[out])
        new = cand[rows][conflict_free(field, cand[rows], regions, gap_opt)]
        if len(new) == 0:
            break
        index.add(new)
        pts = index.points
        # node ids stay the same as points are appended: keys stay valid only if n is fixed
        done_keys = (done_keys // n) * len(pts) + done_keys % n
        refused = _renumbered(refused, n, len(pts))
        by_key = np.argsort(tri_keys)  # for the next round, over its points
        known = (_renumbered(tri_keys[by_key], n, len(pts)), centre[by_key], radius[by_key])
    return np.array(pts)
