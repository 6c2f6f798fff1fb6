"""The 1D mesh of the box boundary: quasi-unit edges in the metric.

Each side of the box is split into n segments of equal metric length
(measured along the side, which stays straight), n = max(1, round(L / target)).
The P2 node of a boundary edge is the point of its side that halves the
edge's metric length (paper section 3 starts Algorithm 1 from this 1D mesh).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from curvimesh.metric import MetricField


@dataclass(frozen=True)
class BoundaryMesh:
    """Boundary vertices ``(nv, 2)``, counter-clockwise from (xmin, ymin), and
    for each boundary edge (vertex k → k+1, cyclic) its P2 node ``(nv, 2)`` and side 0..3
    (bottom, right, top, left)."""

    vertices: NDArray
    midnodes: NDArray
    sides: NDArray


def side_arclength(
    field: MetricField, a: NDArray, b: NDArray, *, samples: int
) -> tuple[NDArray, NDArray]:
    """Cumulative metric length along the segment a→b at ``samples + 1`` parameters.

    Returns the parameters s ``(k,)`` in [0, 1] and the lengths ``(k,)``: each
    cell [s_i, s_i+1] is integrated with 3-point Gauss–Legendre.
    """
    s = np.linspace(0.0, 1.0, samples + 1)
    xg, wg = np.polynomial.legendre.leggauss(3)
    h = 1.0 / samples
    t = (s[:-1, None] + h * (xg[None, :] + 1) / 2).ravel()
    d = b - a
    pts = a[None, :] + t[:, None] * d[None, :]
    g = field.tensor(pts)
    speed = np.sqrt(np.einsum("i,pij,j->p", d, g, d)).reshape(samples, 3)
    cell = speed @ (wg * h / 2)
    return s, np.concatenate([[0.0], np.cumsum(cell)])


def corner_edge_lengths(
    field: MetricField, *, target: float, min_dist: float, max_length: float
) -> NDArray:
    """Metric length ``(4,)`` of the two boundary edges at each corner (0..3 from (xmin, ymin)).

    At a corner whose angle is acute in the metric, two edges of length
    ``target`` end closer than ``min_dist`` to each other. With M = g(corner)
    and û, ŵ the unit (in M) directions of the two sides leaving the corner,
    the edge ends are ℓ|û − ŵ|_M apart, so the edges get the length
    ℓ = min_dist / |û − ŵ|_M, between ``target`` and ``max_length``. A corner
    that needs more than ``max_length`` keeps a short edge across it: no
    triangulation of a corner that sharp has all its edges in range.
    """
    xmin, ymin, xmax, ymax = field.box
    corners = np.array([[xmin, ymin], [xmax, ymin], [xmax, ymax], [xmin, ymax]])
    g = field.tensor(corners)
    out = np.empty(4)
    for k in range(4):
        u = corners[(k + 1) % 4] - corners[k]
        w = corners[(k - 1) % 4] - corners[k]
        u = u / np.sqrt(u @ g[k] @ u)
        w = w / np.sqrt(w @ g[k] @ w)
        gap = float(np.sqrt((u - w) @ g[k] @ (u - w)))
        # 2% margin: the metric varies over the corner's two edges
        out[k] = min(max(target, 1.02 * min_dist / gap), max_length)
    return out


def discretize_box(
    field: MetricField, *, target: float = 1.0, min_dist: float = 0.7, max_length: float = 1.5
) -> BoundaryMesh:
    """Split the four sides into quasi-unit edges of metric length ≈ ``target``.

    The edges at a corner that is acute in the metric are lengthened so that
    the first vertices of the two sides are at least ``min_dist`` apart (see
    :func:`corner_edge_lengths`); the rest of each side is split evenly.
    """
    xmin, ymin, xmax, ymax = field.box
    corners = np.array([[xmin, ymin], [xmax, ymin], [xmax, ymax], [xmin, ymax]])
    at_corner = corner_edge_lengths(field, target=target, min_dist=min_dist, max_length=max_length)
    verts, mids, sides = [], [], []
    for k in range(4):
        a, b = corners[k], corners[(k + 1) % 4]
        _, cum = side_arclength(field, a, b, samples=256)
        # enough cells for 64 per unit of metric length, for 1e-6 accuracy of positions
        samples = int(min(max(256, 64 * cum[-1]), 2_000_000))
        s, cum = side_arclength(field, a, b, samples=samples)
        total = cum[-1]
        first, last = at_corner[k], at_corner[(k + 1) % 4]
        rest = total - first - last
        if (first == target and last == target) or rest < 0.5 * target:
            n = max(1, round(total / target))
            targets = np.linspace(0.0, total, n + 1)
        else:
            n = max(1, round(rest / target))
            targets = np.concatenate([[0.0], first + np.linspace(0.0, rest, n + 1), [total]])
        t = np.interp(targets, cum, s)
        tm = np.interp(0.5 * (targets[:-1] + targets[1:]), cum, s)
        verts.append(a[None, :] + t[:-1, None] * (b - a)[None, :])
        mids.append(a[None, :] + tm[:, None] * (b - a)[None, :])
        sides.append(np.full(len(t) - 1, k))
    return BoundaryMesh(np.concatenate(verts), np.concatenate(mids), np.concatenate(sides))


def halving_points(field: MetricField, a: NDArray, b: NDArray, *, cells: int = 64) -> NDArray:
    """The point of each straight segment a→b that halves its metric length ``(n, 2)``.

    The cumulative length is integrated with 3-point Gauss–Legendre on
    ``cells`` equal cells per segment and inverted by linear interpolation.
    """
    a = np.asarray(a, dtype=float).reshape(-1, 2)
    b = np.asarray(b, dtype=float).reshape(-1, 2)
    xg, wg = np.polynomial.legendre.leggauss(3)
    h = 1.0 / cells
    t = (np.arange(cells)[:, None] * h + h * (xg[None, :] + 1) / 2).ravel()
    d = b - a
    pts = a[:, None, :] + t[None, :, None] * d[:, None, :]
    g = field.tensor(pts.reshape(-1, 2)).reshape(len(a), len(t), 2, 2)
    speed = np.sqrt(np.einsum("pi,pkij,pj->pk", d, g, d)).reshape(len(a), cells, 3)
    cum = np.concatenate([np.zeros((len(a), 1)), np.cumsum(speed @ (wg * h / 2), axis=1)], axis=1)
    half = 0.5 * cum[:, -1:]
    k = np.clip((cum < half).sum(axis=1) - 1, 0, cells - 1)
    rows = np.arange(len(a))
    c0, c1 = cum[rows, k], cum[rows, k + 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(c1 > c0, (half[:, 0] - c0) / (c1 - c0), 0.5)
    s = (k + frac) * h
    return a + s[:, None] * d
