"""Metric gradation: bounding how fast the sizes of a metric field may grow.

A metric computed point by point (the interpolation-error metric of
:mod:`curvimesh.interpolation`) can change its sizes faster than any mesh can
follow: across a tanh front its sizes grow exponentially with the distance,
from a fraction of a percent of the box to the size clamp within a tenth of
it, and the mesh is left with long edges between the fine and the coarse
side. The remedy of mesh generators is gradation (Borouchaki, Hecht & Frey,
"Mesh gradation control", IJNME 43, 1998; Alauzet, "Size gradation control of
anisotropic meshes", Finite Elem. Anal. Des. 46, 2010): refine the field so
that its sizes grow at most linearly with the distance, at a rate γ − 1, so
that two adjacent unit edges differ in length by a factor of at most about γ
(MMG's ``-hgrad`` and Gmsh's ``Mesh.SmoothRatio`` are this γ).

**The law.** The metric M_p at p, *spanned* to a point q, has the
eigenvectors of M_p and each of its sizes hᵢ (along them) grown to
hᵢ + (γ − 1)|pq|: the physical-space law of Alauzet (2010), under which every
size grows at most linearly with the distance, in every direction, while the
field turns isotropic away from a fine anisotropic feature. (His metric-space
law, M_p scaled by (1 + (γ − 1) ℓ_p(pq))⁻², grows the sizes across a layer in
proportion to those along it; composed over the steps of a grid it kept the
fine size of a curved front a third of the box away, where the field asks for
the coarsest size.) The graded field is the largest one below the given field
M and below the spans of its own values: M̃(q) = M(q) ∩ ⋂_p M̃_p→q (∩ the
intersection by simultaneous reduction).

**On a grid.** It is computed on a background grid of the box, at most
:data:`MAX_NODES` nodes of equal spacing along x and y: each node takes the
intersection with the spans of its 8 neighbours, in Gauss-Seidel sweeps in the
four raster orders until nothing changes (:func:`curvimesh.kernels.grade_metrics`;
a node is refined only, so the sweeps end). A path of grid steps is at most
8 % longer than the straight segment (8 neighbours), so sizes grow up to 8 %
slower than the law along directions between the grid's.

**Between nodes.** The graded node metrics are carried by their logarithms
(:func:`curvimesh.tensors.log_components`; a convex combination of logarithms
is the logarithm of an SPD tensor, and it interpolates sizes geometrically),
blended by the uniform cubic B-spline of the node values (C², each value a
convex combination of 16 node values, linear functions reproduced; the nodes
beyond the box are extrapolated linearly) and exponentiated
(:class:`GradedGrid`). This smooths the field over about two grid cells, which
changes it little where its sizes are larger than the spacing, the only place
where gradation acts: the field a metric uses is M(x) ∩ G(x) with G the grid's
(:meth:`curvimesh.interpolation.InterpolationMetric.evaluate`), exact where M is
finer.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from curvimesh import kernels
from curvimesh.tensors import exp_components, log_components

__all__ = [
    "MAX_NODES",
    "GradedGrid",
    "bspline_basis",
    "grade",
    "graded_grid",
    "grid_nodes",
    "grid_shape",
]

#: Most nodes of a background grid. Each of its three node arrays (padded by one
#: node on every side) stays under 1 MB, the size up to which numba compiles a
#: global array into the metric's code as a constant, so the compiled metric can be
#: cached on disk.
MAX_NODES = 65_536

#: Sweeps of the grid gradation before it stops converging, and the relative margin
#: by which a span must be finer than a node to change it
#: (:func:`curvimesh.kernels.grade_metrics`).
MAX_SWEEPS = 100
MARGIN = 1e-9


def grid_shape(
    box: tuple[float, float, float, float], max_nodes: int = MAX_NODES
) -> tuple[int, int]:
    """Nodes (nx, ny) along x and y of a grid of the box with about equal spacings.

    At least 4 nodes along each side, so a very long box gets a grid of 4 rows:

    >>> grid_shape((0.0, 0.0, 1.0, 1.0)), grid_shape((0.0, 0.0, 4.0, 1.0))
    ((256, 256), (512, 128))
    >>> grid_shape((0.0, 0.0, 1e6, 1.0)), grid_shape((0.0, 0.0, 1.0, 1e6))
    ((16384, 4), (4, 16384))
    """
    xmin, ymin, xmax, ymax = box
    aspect = (xmax - xmin) / (ymax - ymin)
    nx = max(4, min(max_nodes // 4, math.floor(math.sqrt(max_nodes * aspect))))
    ny = max(4, math.floor(max_nodes / nx))
    return nx, ny


def bspline_basis(t: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """The uniform cubic B-spline weights of the nodes i − 1, i, i + 1, i + 2 at
    offset t in cell [i, i + 1]: (1 − t)³/6, (3t³ − 6t² + 4)/6, (−3t³ + 3t² + 3t + 1)/6,
    t³/6 (they sum to 1, are positive on [0, 1], and reproduce linear functions).

    >>> [float(b) for b in bspline_basis(np.array(0.0))]  # doctest: +ELLIPSIS
    [0.1666..., 0.6666..., 0.1666..., 0.0]
    """
    s = 1.0 - t
    t2 = t * t
    t3 = t2 * t
    return (
        s * s * s / 6.0,
        (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0,
        (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0,
        t3 / 6.0,
    )


def _pad_linear(a: NDArray) -> NDArray:
    """``a`` ``(..., nx, ny)`` with one more node on every side, extrapolated linearly."""
    out = np.empty((*a.shape[:-2], a.shape[-2] + 2, a.shape[-1] + 2))
    out[..., 1:-1, 1:-1] = a
    out[..., 0, 1:-1] = 2.0 * a[..., 0, :] - a[..., 1, :]
    out[..., -1, 1:-1] = 2.0 * a[..., -1, :] - a[..., -2, :]
    out[..., :, 0] = 2.0 * out[..., :, 1] - out[..., :, 2]
    out[..., :, -1] = 2.0 * out[..., :, -2] - out[..., :, -3]
    return out


def _cell(u: NDArray, n: int) -> tuple[NDArray, NDArray]:
    """Cell index in [0, n − 2] of grid coordinates u and the offsets in them, within
    [−1, 2] (NaN where u is not finite), as :func:`curvimesh.kernels.grid_tensor`."""
    finite = np.isfinite(u)
    i = np.clip(np.floor(np.where(finite, u, 0.0)), 0.0, n - 2.0)
    t = np.where(finite, np.clip(u - i, -1.0, 2.0), np.nan)
    return i.astype(np.int64), t


@dataclass(frozen=True)
class GradedGrid:
    """A graded metric on a grid: node (i, j) at (x0 + i dx, y0 + j dy); ``logs``
    ``(3, nx + 2, ny + 2)`` the logarithms (L11, L12, L22) of the node metrics,
    padded by one node on every side (extrapolated linearly)."""

    origin: tuple[float, float]
    spacing: tuple[float, float]
    logs: NDArray

    @property
    def shape(self) -> tuple[int, int]:
        """Nodes (nx, ny) of the grid, without the padding."""
        return self.logs.shape[1] - 2, self.logs.shape[2] - 2

    @property
    def key(self) -> str:
        """A name of the content: a hash of the node arrays, origin and spacing."""
        h = hashlib.sha256(np.ascontiguousarray(self.logs).tobytes())
        h.update(repr((self.origin, self.spacing, self.logs.shape)).encode())
        return h.hexdigest()[:20]

    def components(self, pts: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        """The grid's metric (g11, g12, g22) at points ``(n, 2)``: the cubic B-spline of
        the node logarithms, exponentiated (the scalar twin is
        :func:`curvimesh.kernels.grid_tensor`, the same operations in the same order)."""
        pts = np.asarray(pts, dtype=float).reshape(-1, 2)
        (x0, y0), (dx, dy) = self.origin, self.spacing
        nx, ny = self.shape
        i, t = _cell((pts[:, 0] - x0) / dx, nx)
        j, u = _cell((pts[:, 1] - y0) / dy, ny)
        bx, by = bspline_basis(t), bspline_basis(u)
        s = np.zeros((3, len(pts)))
        for a in range(4):
            r = np.zeros((3, len(pts)))
            for b in range(4):
                r = r + by[b] * self.logs[:, i + a, j + b]
            s = s + bx[a] * r
        return exp_components(s[0], s[1], s[2])

    def scalar_source(self, name: str) -> str:
        """Module-level source binding ``{name}_l11``, ``{name}_l12``, ``{name}_l22`` to the
        node arrays (registered in :data:`curvimesh.kernels.GRIDS` under names made of
        :attr:`key`), and ``{name}_g(x, y)``, the grid's metric at a point."""
        key = self.key
        lines = []
        for k, comp in enumerate(("l11", "l12", "l22")):
            kernels.GRIDS.setdefault(f"{key}_{k}", np.ascontiguousarray(self.logs[k]))
            lines.append(f'{name}_{comp} = grid_array("{key}_{k}")\n')
        (x0, y0), (dx, dy) = self.origin, self.spacing
        args = ", ".join(repr(float(v)) for v in (x0, y0, dx, dy))
        return (
            "".join(lines)
            + f"""
def {name}_g(x, y):
    return grid_tensor(x, y, {name}_l11, {name}_l12, {name}_l22, {args})
"""
        )


def grade(g: NDArray, spacing: tuple[float, float], growth: float) -> tuple[NDArray, int]:
    """The node metrics ``g`` ``(nx, ny, 3)`` (g11, g12, g22) graded with rate
    ``growth`` = γ − 1 (see the module), and the sweeps it took.

    An isotropic field of size H with one node of size h is graded to
    min(H, h + (γ − 1) d), d the length of the shortest path of grid steps:

    >>> g = np.full((5, 1, 3), [1.0, 0.0, 1.0]); g[0] = [100.0, 0.0, 100.0]
    >>> out, _ = grade(g, (0.1, 0.1), 1.0)
    >>> (1 / np.sqrt(out[:, 0, 0])).round(12).tolist()
    [0.1, 0.2, 0.3, 0.4, 0.5]
    """
    out = np.array(g, dtype=float, order="C")
    sweeps = kernels.grade_metrics(
        out, float(spacing[0]), float(spacing[1]), float(growth), MAX_SWEEPS, MARGIN
    )
    return out, int(sweeps)


def grid_nodes(
    box: tuple[float, float, float, float], max_nodes: int = MAX_NODES
) -> tuple[NDArray, tuple[float, float]]:
    """The nodes ``(nx ny, 2)`` of the box's grid (:func:`grid_shape`), node (i, j) in
    row i ny + j, and the spacing (dx, dy)."""
    nx, ny = grid_shape(box, max_nodes)
    dx, dy = _spacing(box, nx, ny)
    gx, gy = np.meshgrid(box[0] + dx * np.arange(nx), box[1] + dy * np.arange(ny), indexing="ij")
    return np.column_stack([gx.ravel(), gy.ravel()]), (dx, dy)


def _spacing(box: tuple[float, float, float, float], nx: int, ny: int) -> tuple[float, float]:
    """(dx, dy) of a grid of nx × ny nodes spanning the box."""
    return (box[2] - box[0]) / (nx - 1), (box[3] - box[1]) / (ny - 1)


def graded_grid(
    box: tuple[float, float, float, float],
    nodes: tuple[NDArray, NDArray, NDArray],
    gradation: float,
    *,
    max_nodes: int = MAX_NODES,
) -> GradedGrid:
    """The metric (g11, g12, g22) ``nodes``, each ``(nx ny,)`` at :func:`grid_nodes`,
    graded with γ = ``gradation`` > 1."""
    nx, ny = grid_shape(box, max_nodes)
    spacing = _spacing(box, nx, ny)
    g = np.stack(nodes, axis=-1).reshape(nx, ny, 3)
    graded, _ = grade(g, spacing, gradation - 1.0)
    logs = np.stack(log_components(graded[..., 0], graded[..., 1], graded[..., 2]))
    return GradedGrid((box[0], box[1]), spacing, _pad_linear(logs))
