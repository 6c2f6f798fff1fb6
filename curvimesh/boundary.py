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


def discretize_box(field: MetricField, *, target: float = 1.0) -> BoundaryMesh:
    """Split the four sides into quasi-unit edges of metric length ≈ ``target``."""
    xmin, ymin, xmax, ymax = field.box
    corners = np.array([[xmin, ymin], [xmax, ymin], [xmax, ymax], [xmin, ymax]])
    verts, mids, sides = [], [], []
    for k in range(4):
        a, b = corners[k], corners[(k + 1) % 4]
        _, cum = side_arclength(field, a, b, samples=256)
        # enough cells for 64 per unit of metric length, for 1e-6 accuracy of positions
        samples = int(min(max(256, 64 * cum[-1]), 2_000_000))
        s, cum = side_arclength(field, a, b, samples=samples)
        total = cum[-1]
        n = max(1, round(total / target))
        targets = np.linspace(0.0, total, n + 1)
        t = np.interp(targets, cum, s)
        tm = np.interp(0.5 * (targets[:-1] + targets[1:]), cum, s)
        verts.append(a[None, :] + t[:-1, None] * (b - a)[None, :])
        mids.append(a[None, :] + tm[:, None] * (b - a)[None, :])
        sides.append(np.full(n, k))
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
