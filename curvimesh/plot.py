"""Pictures of curved meshes and of unit circles in a metric.

* :func:`plot_mesh_report`: the curved mesh coloured by quality (paper
  figure 7, with the P2 triangles drawn as the curved triangles they are),
  beside histograms of edge lengths and qualities (paper figure 9).
* :func:`plot_circles`: geodesic unit circles against the ellipses of the
  tangent-plane approximation, with the geodesics along the principal
  directions of the metric (paper figures 1 and 2).

Matplotlib is imported inside the plotting functions, so that importing
:mod:`curvimesh` stays fast. The figures are built on a bare
:class:`matplotlib.figure.Figure` with an Agg canvas: pyplot is never
imported, no window ever opens, and the global backend of a caller (a
notebook, say) is left alone. Every picture is written through
:func:`curvimesh.io.atomic_output`, so a failed plot leaves no file; the
format follows the extension of the path (PNG when it has none).
"""

from __future__ import annotations

import math
import os
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from curvimesh.bezier import valid_exact
from curvimesh.geodesic import parabola_points, shoot
from curvimesh.io import atomic_output
from curvimesh.mesh import Mesh
from curvimesh.metric import MetricField
from curvimesh.quality import (
    COUNT_RTOL,
    EDGE_SLOTS,
    REPORT_RTOL,
    edge_lengths,
    metric_areas_adaptive,
    quality_from,
)

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = [
    "curved_edge_polylines",
    "curved_triangle_polygons",
    "plot_circles",
    "plot_mesh_report",
    "principal_geodesics",
    "tangent_ellipse",
    "touching_window",
    "unit_circle",
]

#: The range of a quasi-unit edge (paper section 1).
UNIT_RANGE = (0.7, 1.4)
#: Points sampled along each curved edge (odd, so that t = 1/2 is one of them).
EDGE_SAMPLES = 13
DPI = 150
#: Above this many triangles on the picture, edges are drawn without antialiasing.
DENSE = 2500


# --------------------------------------------------------------------------- #
# Geometry of the pictures                                                     #
# --------------------------------------------------------------------------- #


def curved_edge_polylines(
    points: ArrayLike, edges: ArrayLike, mids: ArrayLike | None, samples: int = EDGE_SAMPLES
) -> NDArray[np.float64]:
    """Points ``(E, samples, 2)`` along the parabolas of edges ``(E, 2)``.

    Edge ``e`` runs from ``points[edges[e, 0]]`` (t = 0) to
    ``points[edges[e, 1]]`` (t = 1) through ``points[mids[e]]`` (t = 1/2) on
    x(t) = (1−t)(1−2t) x₀ + t(2t−1) x₁ + 4t(1−t) x_m, at ``samples`` evenly
    spaced t. ``mids`` None, or a negative id, means a straight edge.

    >>> pts = np.array([[0.0, 0.0], [2.0, 0.0], [1.0, 1.0]])
    >>> curved_edge_polylines(pts, [[0, 1]], [2], samples=5)[0].tolist()
    [[0.0, 0.0], [0.5, 0.75], [1.0, 1.0], [1.5, 0.75], [2.0, 0.0]]
    """
    if samples < 2:
        raise ValueError(f"samples must be at least 2, got {samples}")
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    x0, x1 = pts[edges[:, 0]], pts[edges[:, 1]]
    xm = 0.5 * (x0 + x1)
    if mids is not None:
        mids = np.asarray(mids, dtype=np.int64).reshape(-1)
        curved = mids >= 0
        xm[curved] = pts[mids[curved]]
    return parabola_points(x0, x1, xm, np.linspace(0.0, 1.0, samples))[0]


def _triangle_nodes(mesh: Mesh) -> NDArray[np.float64]:
    """Nodes ``(m, 6, 2)`` of the triangles; a P1 triangle gets its edge midpoints."""
    pts = np.asarray(mesh.points)
    if mesh.order == 2:
        return pts[mesh.triangles]
    corners = pts[mesh.corners]
    edge_nodes = [0.5 * (corners[:, a] + corners[:, b]) for a, b, _ in EDGE_SLOTS]
    return np.concatenate([corners, np.stack(edge_nodes, axis=1)], axis=1)


def curved_triangle_polygons(nodes: ArrayLike, samples: int = EDGE_SAMPLES) -> NDArray[np.float64]:
    """Closed outlines ``(m, 3 (samples − 1), 2)`` of P2 triangles ``(m, 6, 2)``.

    The boundary of each curved triangle, sampled along its edges 01, 12, 20
    in turn (each edge's last point is the next one's first, so it is left
    out); counter-clockwise for a valid triangle.

    >>> tri = np.array([[[0, 0], [1, 0], [0, 1], [0.5, 0], [0.5, 0.5], [0, 0.5]]])
    >>> curved_triangle_polygons(tri, samples=2)[0].tolist()
    [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]
    """
    x = np.asarray(nodes, dtype=np.float64).reshape(-1, 6, 2)
    t = np.linspace(0.0, 1.0, samples)[:-1]
    sides = [parabola_points(x[:, a], x[:, b], x[:, s], t)[0] for a, b, s in EDGE_SLOTS]
    return np.concatenate(sides, axis=1)


def touching_window(
    nodes: ArrayLike, window: tuple[float, float, float, float]
) -> NDArray[np.bool_]:
    """Whether each P2 triangle ``(m, 6, 2)`` may touch ``window = (x0, y0, x1, y1)``, ``(m,)``.

    Tested on a box that holds the curved triangle: an edge parabola lies in
    the triangle of its end nodes and its Bezier control point 2 x_m − (x₀ + x₁)/2.
    So no triangle that touches the window is missed; a few that only come
    near it may be kept.

    >>> tri = np.array([[[0, 0], [1, 0], [0, 1], [0.5, 0], [0.5, 0.5], [0, 0.5]]])
    >>> touching_window(np.concatenate([tri, tri + 5]), (0.9, 0.9, 2, 2)).tolist()
    [True, False]
    """
    x = np.asarray(nodes, dtype=np.float64).reshape(-1, 6, 2)
    control = [2.0 * x[:, s] - 0.5 * (x[:, a] + x[:, b]) for a, b, s in EDGE_SLOTS]
    hull = np.concatenate([x[:, :3], np.stack(control, axis=1)], axis=1)
    lo, hi = hull.min(axis=1), hull.max(axis=1)
    x0, y0, x1, y1 = window
    return (hi[:, 0] >= x0) & (lo[:, 0] <= x1) & (hi[:, 1] >= y0) & (lo[:, 1] <= y1)


def _inverse_sqrt(g: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """g^(−1/2) ``(2, 2)`` of an SPD matrix, with its eigenvalues (ascending) and eigenvectors."""
    w, v = np.linalg.eigh(g)
    return (v / np.sqrt(w)) @ v.T, w, v


def _centre_metric(field: MetricField, centre: ArrayLike) -> tuple[NDArray, NDArray]:
    c = np.asarray(centre, dtype=np.float64).reshape(2)
    return c, field.tensor(c[None])[0]


def tangent_ellipse(field: MetricField, centre: ArrayLike, points: int = 361) -> NDArray:
    """The unit circle of the tangent plane at ``centre``, ``(points, 2)``, closed.

    The ellipse {x : (x − c)ᵀ g(c) (x − c) = 1}, as c + g(c)^(−1/2) (cos a, sin a)
    for ``points`` angles a from 0 to 2π (both included).
    """
    c, g = _centre_metric(field, centre)
    a = np.linspace(0.0, 2.0 * math.pi, points)
    return c + np.column_stack([np.cos(a), np.sin(a)]) @ _inverse_sqrt(g)[0]


def unit_circle(field: MetricField, centre: ArrayLike, directions: int = 181) -> NDArray:
    """End points ``(directions, 2)`` of the unit-length geodesics from ``centre`` (paper §2.1).

    The geodesics (ODE (2), :func:`~curvimesh.geodesic.shoot`) leave the
    centre c with the velocities g(c)^(−1/2) (cos a, sin a), a = 2πk/directions:
    directions evenly spaced in the angle that the metric at c measures, so
    that the points are evenly spread around a very anisotropic circle too
    (the same directions as the Euclidean angles when g(c) is isotropic).
    Rows of geodesics that fail are NaN.
    """
    if directions < 1:
        raise ValueError(f"directions must be positive, got {directions}")
    c, g = _centre_metric(field, centre)
    a = 2.0 * math.pi * np.arange(directions) / directions
    start = np.column_stack([np.cos(a), np.sin(a)]) @ _inverse_sqrt(g)[0]
    shot = shoot(field, np.tile(c, (directions, 1)), start, 1.0)
    return np.where(shot.ok[:, None], shot.end, np.nan)


def principal_geodesics(field: MetricField, centre: ArrayLike, pieces: int = 20) -> NDArray:
    """The unit-length geodesics along ±v₁, ±v₂ from ``centre``: ``(4, pieces + 1, 2)``.

    v₁, v₂ are the eigenvectors of g(c), for its smaller then larger
    eigenvalue; rows are +v₁, −v₁, +v₂, −v₂. Each geodesic is shot in
    ``pieces`` pieces of metric length 1/pieces, each piece starting with
    the end velocity of the one before; point k is at metric distance
    k/pieces along it. A geodesic of which a piece fails is NaN.
    """
    if pieces < 1:
        raise ValueError(f"pieces must be positive, got {pieces}")
    c, g = _centre_metric(field, centre)
    v = _inverse_sqrt(g)[2].T
    x = np.tile(c, (4, 1))
    vel = np.stack([v[0], -v[0], v[1], -v[1]])
    out = np.empty((4, pieces + 1, 2))
    out[:, 0] = c
    alive = np.ones(4, dtype=bool)
    for k in range(pieces):
        shot = shoot(field, x, vel, 1.0 / pieces)
        alive &= shot.ok
        x = np.where(alive[:, None], shot.end, x)
        vel = np.where(alive[:, None], shot.velocity, vel)
        out[:, k + 1] = x
    out[~alive] = np.nan
    return out


def _tangent_segments(field: MetricField, centre: ArrayLike) -> NDArray:
    """The unit segments of the tangent plane along ±v₁, ±v₂: ``(4, 2, 2)`` (c, c ± v/√λ)."""
    c, g = _centre_metric(field, centre)
    _, w, v = _inverse_sqrt(g)
    ends = np.stack([v[:, 0], -v[:, 0], v[:, 1], -v[:, 1]]) / np.sqrt(w[[0, 0, 1, 1]])[:, None]
    return np.stack([np.tile(c, (4, 1)), c + ends], axis=1)


def _log_density(field: MetricField, cells: int = 200) -> NDArray:
    """log sqrt(det g) ``(cells, cells)`` at the cell centres of a grid on the box (rows: y).

    Masked where the metric is undefined.
    """
    xmin, ymin, xmax, ymax = field.box
    xs = xmin + (np.arange(cells) + 0.5) * (xmax - xmin) / cells
    ys = ymin + (np.arange(cells) + 0.5) * (ymax - ymin) / cells
    gx, gy = np.meshgrid(xs, ys)
    g = field.tensor(np.column_stack([gx.ravel(), gy.ravel()]), check=False)
    det = g[:, 0, 0] * g[:, 1, 1] - g[:, 0, 1] ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        dens = 0.5 * np.log(det)
    return np.ma.masked_invalid(dens.reshape(cells, cells))


# --------------------------------------------------------------------------- #
# Figures                                                                      #
# --------------------------------------------------------------------------- #


def _new_figure(size: tuple[float, float]) -> Figure:
    """A figure on an Agg canvas, outside pyplot (no window, no global state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path: str | os.PathLike) -> None:
    """Write ``fig`` atomically, in the format the extension of ``path`` names (default PNG)."""
    fmt = os.path.splitext(os.fspath(path))[1].lstrip(".").lower() or "png"
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format=fmt, dpi=DPI)


def _check_window(window: tuple[float, float, float, float]) -> tuple[float, ...]:
    w = tuple(float(v) for v in window)
    if len(w) != 4 or not (w[0] < w[2] and w[1] < w[3]) or not all(map(math.isfinite, w)):
        raise ValueError(f"window must be finite (x0, y0, x1, y1) with x0 < x1, y0 < y1: {window}")
    return w


def _mesh_limits(mesh: Mesh) -> tuple[float, float, float, float]:
    if mesh.box is not None:
        x0, y0, x1, y1 = mesh.box
    else:
        (x0, y0), (x1, y1) = mesh.points.min(axis=0), mesh.points.max(axis=0)
    pad = 0.02 * max(x1 - x0, y1 - y0, 1e-12)
    return x0 - pad, y0 - pad, x1 + pad, y1 + pad


def plot_mesh_report(
    field: MetricField,
    mesh: Mesh,
    path: str | os.PathLike,
    *,
    window: tuple[float, float, float, float] | None = None,
    title: str | None = None,
    lengths: ArrayLike | None = None,
    qualities: ArrayLike | None = None,
) -> None:
    """Draw ``mesh`` coloured by quality, with histograms of lengths and qualities, to ``path``.

    Left: every triangle filled along its curved boundary (edges sampled at
    :data:`EDGE_SAMPLES` points on their parabolas; straight for P1) and
    coloured by quality, paper eq. (4); invalid triangles
    (:func:`~curvimesh.bezier.valid_exact`) outlined in red. ``window =
    (x0, y0, x1, y1)`` zooms there and draws only the triangles that touch it.
    Right: histograms of the metric lengths of all edges (the range
    [0.7, 1.4] shaded, with its share) and of the qualities of all triangles.

    ``lengths`` ``(E,)`` follow :attr:`Mesh.edges`, ``qualities`` ``(m,)``
    the triangles; either is computed when not given (lengths to 1e-4
    relative, :data:`curvimesh.quality.COUNT_RTOL`; areas to the report's 1e-5).
    The format follows the extension of ``path``; the file is written atomically.
    """
    if len(mesh.triangles) == 0:
        raise ValueError("the mesh has no triangles")
    if window is not None:
        window = _check_window(window)
    pts = np.asarray(mesh.points)
    nodes = _triangle_nodes(mesh)
    if lengths is None:
        mids = mesh.edge_mid if mesh.order == 2 else None
        lengths = edge_lengths(field, pts, mesh.edges, mids, rtol=COUNT_RTOL)
    lengths = np.asarray(lengths, dtype=np.float64)
    if lengths.shape != (len(mesh.edges),):
        raise ValueError(f"lengths must have shape ({len(mesh.edges)},), got {lengths.shape}")
    if qualities is None:
        qualities = quality_from(
            metric_areas_adaptive(field, nodes, rtol=REPORT_RTOL), lengths[mesh.tri_edges]
        )
    qualities = np.asarray(qualities, dtype=np.float64)
    if qualities.shape != (len(mesh.triangles),):
        raise ValueError(
            f"qualities must have shape ({len(mesh.triangles)},), got {qualities.shape}"
        )
    valid = valid_exact(nodes)

    fig = _new_figure((13.0, 8.0))
    grid = fig.add_gridspec(2, 2, width_ratios=(2.2, 1.0))
    _draw_mesh(fig, fig.add_subplot(grid[:, 0]), mesh, nodes, qualities, valid, window)
    _length_histogram(fig.add_subplot(grid[0, 1]), lengths)
    _quality_histogram(fig.add_subplot(grid[1, 1]), qualities)
    heading = (
        f"{field.name}: {len(mesh.vertex_ids)} vertices, {len(mesh.triangles)} triangles"
        f" (P{mesh.order})"
    )
    fig.suptitle(heading if title is None else f"{title}\n{heading}")
    _save(fig, path)


def _draw_mesh(fig, ax, mesh, nodes, qualities, valid, window) -> None:
    from matplotlib import colormaps
    from matplotlib.collections import LineCollection, PolyCollection
    from matplotlib.colors import Normalize

    samples = EDGE_SAMPLES if mesh.order == 2 else 2
    if window is None:
        shown = np.arange(len(nodes))
        x0, y0, x1, y1 = _mesh_limits(mesh)
    else:
        shown = np.flatnonzero(touching_window(nodes, window))
        x0, y0, x1, y1 = window
    # Line widths in points, thinner as more triangles share the picture.
    width = float(np.clip(12.0 / math.sqrt(max(len(shown), 1)), 0.1, 0.8))
    qmin, qmax = float(qualities.min()), float(qualities.max())
    # The scale runs to 1 (the ideal) from 0.5, or lower by steps of 0.1 to
    # hold the worst triangle. A colormap of few levels reads better and keeps
    # the PNG small (it compresses runs of equal colour).
    low = min(0.5, max(0.0, math.floor(10.0 * qmin) / 10.0))
    fill = PolyCollection(
        curved_triangle_polygons(nodes[shown], samples),
        array=qualities[shown],
        cmap=colormaps["viridis"].resampled(round(20 * (1.0 - low))),
        norm=Normalize(low, 1.0),
        edgecolors="none",
        antialiaseds=False,
    )
    ax.add_collection(fill)
    edge_ids = np.unique(mesh.tri_edges[shown])
    mids = mesh.edge_mid[edge_ids] if mesh.order == 2 else None
    lines = curved_edge_polylines(mesh.points, mesh.edges[edge_ids], mids, samples)
    # Antialiased hairlines of a dense mesh blur into grey and bloat the PNG
    # (about 1 MB for 10^4 triangles); plain one-pixel lines stay crisp.
    smooth = len(shown) <= DENSE
    ax.add_collection(LineCollection(lines, colors="0.1", linewidths=width, antialiaseds=smooth))
    bad = shown[~valid[shown]]
    if bad.size:
        outline = PolyCollection(
            curved_triangle_polygons(nodes[bad], samples),
            facecolors="none",
            edgecolors="red",
            linewidths=max(3.0 * width, 0.8),
        )
        ax.add_collection(outline)
    fig.colorbar(
        fill,
        ax=ax,
        shrink=0.8,
        extend={(False, False): "neither", (True, False): "min", (False, True): "max"}.get(
            (qmin < low, qmax > 1.0), "both"
        ),
        label="quality (4)",
    )
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    n_bad = int((~valid).sum())
    where = "" if window is None else f"window, {len(shown)} triangles shown; "
    ax.set_title(f"curved mesh ({where}{n_bad} invalid)")


def _length_histogram(ax, lengths: NDArray) -> None:
    lo, hi = UNIT_RANGE
    finite = lengths[np.isfinite(lengths)]
    top = max(2.0, 1.05 * float(np.percentile(finite, 99.5))) if finite.size else 2.0
    share = float(np.mean((lengths >= lo) & (lengths <= hi))) if lengths.size else 0.0
    ax.axvspan(lo, hi, color="tab:green", alpha=0.15, label=f"[{lo}, {hi}]: {100 * share:.1f} %")
    # Longer edges, infinite ones included, are counted in the last bin.
    counts, _, _ = ax.hist(
        np.minimum(lengths[~np.isnan(lengths)], top), bins=60, range=(0.0, top), color="tab:blue"
    )
    ax.set_ylim(0.0, 1.25 * max(float(counts.max(initial=0.0)), 1.0))  # room for the legend
    ax.set_xlabel("edge length in the metric")
    ax.set_ylabel("edges")
    ax.set_title(
        f"{lengths.size} edges, lengths {np.nanmin(lengths):.3g} to {np.nanmax(lengths):.3g}"
    )
    ax.legend(loc="upper right")


def _quality_histogram(ax, qualities: NDArray) -> None:
    top = max(1.0, float(qualities.max()))
    bottom = min(0.0, float(qualities.min()))
    ax.hist(qualities, bins=50, range=(bottom, top), color="tab:purple")
    ax.axvline(1.0, color="0.3", linestyle=":", linewidth=1.0)
    ax.set_xlabel("quality (4)")
    ax.set_ylabel("triangles")
    ax.set_title(f"quality min {qualities.min():.3g}, mean {qualities.mean():.3g}")


def plot_circles(
    field: MetricField, centres: ArrayLike, path: str | os.PathLike, *, directions: int = 181
) -> None:
    """Draw unit circles of ``field`` at ``centres`` ``(k, 2)`` to ``path`` (paper figures 1, 2).

    For each centre: the geodesic unit circle (:func:`unit_circle`, solid),
    the tangent-plane ellipse (:func:`tangent_ellipse`, dashed), the
    geodesics along the principal directions (:func:`principal_geodesics`)
    and their straight tangent-plane counterparts (dashed). Underneath,
    over the box of the field, log sqrt(det g). Failed geodesics are left
    out. The format follows the extension of ``path``; written atomically.
    """
    from matplotlib.lines import Line2D

    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
    xmin, ymin, xmax, ymax = field.box
    fig = _new_figure((9.5, 8.0 * (ymax - ymin) / (xmax - xmin) + 0.5))
    ax = fig.add_subplot()
    image = ax.imshow(
        _log_density(field),
        origin="lower",
        extent=(xmin, xmax, ymin, ymax),
        cmap="Greys",
        alpha=0.45,
        interpolation="bilinear",
    )
    fig.colorbar(image, ax=ax, shrink=0.7, label="log sqrt(det g)")
    for k, c in enumerate(centres):
        colour = f"C{k % 10}"
        circle = unit_circle(field, c, directions)
        circle = np.concatenate([circle, circle[:1]])  # closed; failed rows leave gaps
        ax.plot(circle[:, 0], circle[:, 1], color=colour, linewidth=1.4)
        ellipse = tangent_ellipse(field, c)
        ax.plot(ellipse[:, 0], ellipse[:, 1], color=colour, linewidth=1.0, linestyle="--")
        for curve in principal_geodesics(field, c):
            ax.plot(curve[:, 0], curve[:, 1], color=colour, linewidth=1.0)
        for seg in _tangent_segments(field, c):
            ax.plot(seg[:, 0], seg[:, 1], color=colour, linewidth=0.8, linestyle="--")
        ax.plot(*c, marker="+", color=colour, markersize=8)
    ax.legend(
        handles=[
            Line2D([], [], color="0.2", linewidth=1.4, label="geodesic unit circle, geodesics"),
            Line2D([], [], color="0.2", linestyle="--", label="tangent-plane ellipse, segments"),
        ],
        loc="upper right",
    )
    ax.set_xlim(xmin, xmax)
    ax.set_ylim(ymin, ymax)
    ax.set_aspect("equal")
    ax.set_title(f"{field.name}: unit circles at {len(centres)} centres")
    _save(fig, path)
