"""Thin curved layers triangulated in their own coordinates (beyond the paper).

Across a thin layer that curves, the chord between two neighbours along a row of
points strays many rows off the row (a unit chord of a 2,000:1 layer about an
ellipse, radius of curvature 0.31 and long size 0.1, strays 0.004: 80 of its
short sizes at the core). The Delaunay triangulation of the points, straight-sided
even in the metric (:func:`curvimesh.triangulate.metric_delaunay`), then joins
points several columns apart, in fans, and the curving stage straightens the
edges whose parabolas would fold a triangle: chords many rows long. The
curvilinear swaps of the paper do not undo them: every swap on the way is
invalid or lowers the quality.

Each core of such a layer (:func:`curvimesh.cores.layer_cores`) gives the layer a
chart: a point p near the core has the coordinates (s, n), s the metric length
along the core of its foot f (the nearest point of a cubic spline through the
core) and n the signed metric length of the segment from f to p (positive on the
core's left). The rows of the layer are the lines n = const of the chart and its
columns, shot across the layer, the lines s = const, near enough: the chart
straightens the layer. The points of a layer are those where a unit chord along
it strays at least :data:`curvimesh.cores.CORE_MIN_SAG` short sizes
(:func:`curvimesh.metric.layer_sag`), near a core. The stage

1. triangulates each layer again in its chart (:func:`rebuilt`): the triangles at
   its points are replaced by the constrained Delaunay triangulation of the chart
   coordinates of their corners inside their boundary
   (:func:`chart_triangulation`), made from the coordinates alone, and each new
   edge gets the middle node that is the image of the edge's middle in the chart
   (:func:`from_chart`), or, where that leaves a triangle invalid, the shortest
   parabola's. The triangles are then the images of straight triangles of the
   chart, which bend as the layer does, valid where the map is smooth on their
   scale though their straight-sided twins fold. The new triangulation is kept
   only where it is valid (decided exactly, after flips of the edges of the
   triangles left invalid, :func:`_repaired`) and leaves fewer edges longer than
   1.4 than the one it replaces;
2. where it was not kept, flips the edges among the layer's points towards the
   Delaunay triangulation of their chart coordinates (:func:`lawson_flips`:
   Lawson's flips, as :func:`curvimesh.triangulate.metric_delaunay` in the plane,
   folds first), with the same middle nodes. Where a triangle is still invalid,
   its corners are taken out of the layer and the flips are made again from the
   input (:func:`flipped`). The flips start from the straight triangulation and
   stop on its folds where it folds most, across a layer sampled row by row
   (:mod:`curvimesh.rows`), whose rows are staggered;
3. moves the middle nodes of the layer's edges to their chart nodes where that
   shortens them, all together, then back on the edges of the triangles left
   invalid, until none is (:func:`renode`).

The result is valid: with no point left in a layer, the input. On
``bench/robustness/u58`` (2,000:1 about an ellipse) sampled row by row, after
the curving stage the layer's edges run up to 15 long; triangulated again in its
chart, none is over 1.4 after the later stages (the flips alone left 13.3). A P2
edge cannot follow such a layer closely where its points are far apart along it:
at the ellipse's ends a unit edge along a row strays 0.25 – 0.7 short sizes from
it at its quarter points (the middle node on the row), and the chart's triangles
there, one row thick, fold from a base of 0.8 long sizes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import Delaunay, QhullError, cKDTree

from curvimesh import kernels
from curvimesh.bezier import valid_exact
from curvimesh.cores import CORE_MIN_SAG, arc_lengths, layer_cores, points_on_core
from curvimesh.curve import assemble_p2, boundary_edge_mask
from curvimesh.freenode import shortest_parabola
from curvimesh.mesh import (
    Mesh,
    apply_flips,
    edge_nodes,
    flip_candidates,
    independent_flips,
    is_conforming,
    p1_edges,
    p1_of,
)
from curvimesh.metric import MetricField, eigen_frame, layer_sag
from curvimesh.quality import edge_lengths_fast
from curvimesh.triangulate import delaunay_flips, in_circle, insert_segments, orient

if TYPE_CHECKING:
    from scipy.interpolate import CubicSpline

#: Gauss–Legendre rule of the chart's metric lengths across the layer: 5 nodes on each
#: piece of the segment between its fractions 0, 2⁻¹⁰, 2⁻⁹, …, 1/2, 1. The size is least
#: at the core (the segment's start) and grows across it, by 1,800 over the chart of a
#: 1,000:1 ring: pieces graded towards the start keep the integrand within a factor of
#: about 2 on each (1e-8 relative on that ring; equal quarters: 2e-4).
_GL_X, _GL_W = np.polynomial.legendre.leggauss(5)
_CUTS = np.concatenate([[0.0], 2.0 ** np.arange(-10, 1)])
_T = (_CUTS[:-1, None] + np.diff(_CUTS)[:, None] * 0.5 * (_GL_X[None] + 1.0)).ravel()
_W = (np.diff(_CUTS)[:, None] * 0.5 * _GL_W[None]).ravel()
#: Most rounds of flips; most times the stage is made again without the corners
#: of invalid triangles.
MAX_ROUNDS = 200
MAX_TRIES = 8
#: Bisection steps of :func:`from_chart`: the offset to 2⁻²⁶ of its bracket, within
#: twice the offset (a thousandth of the short size at 60,000 of them).
BISECTIONS = 26


@dataclass(frozen=True)
class Chart:
    """A core as a smooth curve: the cubic spline ``curve`` c(u) through its traced
    points (periodic around a closed core; u the chord length along the polyline,
    from 0 to ``span``), and the metric length ``arc`` along it at the parameters
    ``u`` of a fine table (:data:`TABLE_STEPS` per polyline segment)."""

    curve: CubicSpline
    span: float
    closed: bool
    u: NDArray
    arc: NDArray

    @property
    def length(self) -> float:
        """The core's metric length."""
        return float(self.arc[-1])


#: Steps of a chart's table of arc lengths per segment of the traced polyline.
TABLE_STEPS = 16
#: Newton steps of a foot's parameter (from the nearest point of the table).
FOOT_STEPS = 4


def chart_of(field: MetricField, line: NDArray, closed: bool) -> Chart:
    """The chart of a traced core (:func:`curvimesh.cores.trace`).

    The polyline's chords stray from a curved core (a step of a quarter long size
    about a radius of curvature R strays h_max² / (128 R): 5 short sizes of a 2,000:1
    layer about an ellipse), so the chart follows the cubic spline through points
    of the core laid evenly along the polyline, twice as many as it has
    (:func:`curvimesh.cores.place`'s projection). Along it the metric length is
    measured in the long size, |c′(u)| sqrt(λ_min(g)) (the core runs along the long
    direction), integrated by the trapezoidal rule on the table: the full
    sqrt(c′ᵀ g c′) would count the spline's tangent error ε as (h_max / h_min) ε,
    2.5e-5 of the length of a 1,000:1 ring from its tangents' 1e-5.
    """
    pts = np.asarray(line, dtype=float)
    if closed:
        pts = np.vstack([pts, pts[:1]])
    # twice as many points, evenly along it (a closed trace's last step can be 1.6
    # steps long), projected on the core
    arc = arc_lengths(field, pts)
    pts = points_on_core(field, pts, arc, np.linspace(0.0, arc[-1], 2 * len(pts) - 1))
    if closed:
        pts[-1] = pts[0]
    step = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    keep = np.concatenate([[True], step > 1e-12 * step.sum()])  # the spline's u must grow
    if closed:
        keep[-1] = True
        keep[-2] = keep[-2] and step[-1] > 1e-12 * step.sum()
    pts = pts[keep]
    u = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    # here: scipy.interpolate adds 0.08 s to every command's start, and only metrics with
    # thin curved layers come here
    from scipy.interpolate import CubicSpline

    curve = CubicSpline(u, pts, bc_type="periodic" if closed else "not-a-knot")
    table = np.linspace(0.0, u[-1], TABLE_STEPS * (len(u) - 1) + 1)
    m, r, _, _ = eigen_frame(field.tensor(curve(table), check=False))
    speed = np.linalg.norm(curve(table, 1), axis=1) * np.sqrt(np.maximum(m - r, 0.0))
    arc = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(table))])
    return Chart(curve, float(u[-1]), closed, table, arc)


def segment_lengths(field: MetricField, a: NDArray, b: NDArray) -> NDArray:
    """Metric lengths ``(k,)`` of the straight segments a → b ``(k, 2)``:
    ∫₀¹ sqrt(dᵀ g(a + t d) d) dt, d = b − a, by the graded Gauss–Legendre rule of
    :data:`_T`, :data:`_W`."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    d = b - a
    x = a[:, None, :] + _T[None, :, None] * d[:, None, :]
    g = field.tensor(x.reshape(-1, 2), check=False).reshape(len(a), len(_T), 2, 2)
    return np.sqrt(np.einsum("ki,ktij,kj->kt", d, g, d)) @ _W


def _wrap(chart: Chart, u: NDArray) -> NDArray:
    """Parameters brought into [0, span]: modulo the span around a closed core, clipped
    at an open core's ends."""
    return np.mod(u, chart.span) if chart.closed else np.clip(u, 0.0, chart.span)


def _feet(chart: Chart, pts: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """For each point p ``(k, 2)``: the parameter u of its foot (the nearest point of the
    curve: (c(u) − p) · c′(u) = 0 by Newton's method from the nearest point of the
    table), whether it lies inside the curve (not at an open core's end), and the
    Euclidean distance |p − c(u)|."""
    pts = np.asarray(pts, dtype=float)
    u = chart.u[cKDTree(chart.curve(chart.u)).query(pts)[1]]
    for _ in range(FOOT_STEPS):
        r = chart.curve(u) - pts
        d1, d2 = chart.curve(u, 1), chart.curve(u, 2)
        f = np.einsum("ki,ki->k", r, d1)
        df = np.einsum("ki,ki->k", d1, d1) + np.einsum("ki,ki->k", r, d2)
        step = np.where(df > 0, f / np.where(df > 0, df, 1.0), 0.0)
        u = _wrap(chart, u - step)
    inside = chart.closed | ((u > 0.0) & (u < chart.span))
    return u, inside, np.linalg.norm(pts - chart.curve(u), axis=1)


def _left_normals(chart: Chart, u: NDArray) -> NDArray:
    """The unit normals ``(k, 2)`` on the left of the curve at parameters u."""
    d = chart.curve(u, 1)
    d = d / np.linalg.norm(d, axis=1)[:, None]
    return np.column_stack([-d[:, 1], d[:, 0]])


def to_chart(field: MetricField, chart: Chart, pts: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Chart coordinates s, n ``(k,)`` of points ``(k, 2)`` (module docstring), and
    whether each foot lies inside the curve (not at an open core's end)."""
    pts = np.asarray(pts, dtype=float)
    u, inside, _ = _feet(chart, pts)
    return (*_coordinates(field, chart, pts, u), inside)


def _coordinates(
    field: MetricField, chart: Chart, pts: NDArray, u: NDArray
) -> tuple[NDArray, NDArray]:
    """Chart coordinates s, n ``(k,)`` of points ``(k, 2)`` whose feet are at the curve's
    parameters u (:func:`_feet`)."""
    foot = chart.curve(u)
    s = np.interp(u, chart.u, chart.arc)
    side = np.where(np.einsum("ki,ki->k", pts - foot, _left_normals(chart, u)) < 0, -1.0, 1.0)
    return s, side * segment_lengths(field, foot, pts)


def from_chart(field: MetricField, chart: Chart, s: NDArray, n: NDArray) -> NDArray:
    """The points ``(k, 2)`` of chart coordinates s, n ``(k,)``: the foot at metric length
    s along the core, then the offset along the curve's left normal whose metric
    length is n (bisection: the length grows with the offset)."""
    s = np.asarray(s, dtype=float)
    n = np.asarray(n, dtype=float)
    if chart.closed:
        s = np.mod(s, chart.length)
    u = np.interp(s, chart.arc, chart.u)
    foot = chart.curve(u)
    nu = _left_normals(chart, u) * np.where(n < 0, -1.0, 1.0)[:, None]
    target = np.abs(n)
    # bracket: from the offset that the foot's metric would give, doubled until past |n|
    g = field.tensor(foot, check=False)
    hi = target / np.sqrt(np.einsum("ki,kij,kj->k", nu, g, nu))
    for _ in range(60):
        short = segment_lengths(field, foot, foot + hi[:, None] * nu) < target
        if not short.any():
            break
        hi = np.where(short, 2.0 * hi, hi)
    lo = np.zeros_like(hi)
    for _ in range(BISECTIONS):
        mid = 0.5 * (lo + hi)
        below = segment_lengths(field, foot, foot + mid[:, None] * nu) < target
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return foot + (0.5 * (lo + hi))[:, None] * nu


@dataclass(frozen=True)
class Layers:
    """The points of a mesh in the layers: the chart of each (``charts``), and per
    vertex the chart it lies in (−1: none), its coordinates s, n there and, where
    :func:`layer_points` measured it, how far a unit chord along the layer strays
    there (``sag``, in short sizes; 0 elsewhere)."""

    charts: list[Chart]
    which: NDArray
    s: NDArray
    n: NDArray
    sag: NDArray | None = None


def layer_points(
    field: MetricField, pts: NDArray, charts: list[Chart], min_sag: float = CORE_MIN_SAG
) -> Layers:
    """The points ``(k, 2)`` in the layers: those where a unit chord along the layer
    strays at least ``min_sag`` short sizes (:func:`curvimesh.metric.layer_sag`),
    within a long size of the nearest chart's curve and with their foot inside it (not
    at an open core's end)."""
    pts = np.asarray(pts, dtype=float)
    which = np.full(len(pts), -1, dtype=np.int64)
    s, n, sag = np.zeros(len(pts)), np.zeros(len(pts)), np.zeros(len(pts))
    if not charts or len(pts) == 0:
        return Layers(charts, which, s, n, sag)
    g, dg = field.evaluate(pts, derivatives=True)
    m, r, _, _ = eigen_frame(g)
    h_max = 1.0 / np.sqrt(np.maximum(m - r, 1e-300))
    sag = layer_sag(g, dg)
    cand = np.flatnonzero(sag >= min_sag)
    if cand.size == 0:
        return Layers(charts, which, s, n, sag)
    feet = [_feet(c, pts[cand]) for c in charts]  # (u, inside, distance) on each
    dist = np.stack([f[2] for f in feet])
    nearest = np.argmin(dist, axis=0)
    close = dist[nearest, np.arange(len(cand))] <= h_max[cand]
    for k, (chart, (u, inside, _)) in enumerate(zip(charts, feet, strict=True)):
        on = close & (nearest == k)
        if not on.any():
            continue
        idx = cand[on]
        s[idx], n[idx] = _coordinates(field, chart, pts[idx], u[on])
        which[idx[inside[on]]] = k
    return Layers(charts, which, s, n, sag)


def thinned(layers: Layers, min_sag: float) -> Layers:
    """``layers`` (from :func:`layer_points` with a ``min_sag`` at most this one) as
    :func:`layer_points` gives them with ``min_sag``: each point's figures are its own,
    so those of the points straying less are dropped."""
    keep = layers.sag >= min_sag
    return Layers(
        layers.charts,
        np.where(keep, layers.which, -1),
        np.where(keep, layers.s, 0.0),
        np.where(keep, layers.n, 0.0),
        layers.sag,
    )


def _quad_coordinates(layers: Layers, quads: NDArray) -> NDArray:
    """Chart coordinates ``(k, 4, 2)`` of quads ``(k, 4)`` of points of one chart each,
    s unwrapped around a closed core (measured from the first corner's)."""
    s, n = layers.s[quads], layers.n[quads]
    for k, chart in enumerate(layers.charts):
        on = layers.which[quads[:, 0]] == k
        if chart.closed and on.any():
            length = chart.length
            s0 = s[on, :1]
            s[on] = s0 + np.mod(s[on] - s0 + 0.5 * length, length) - 0.5 * length
    return np.stack([s, n], axis=-1)


def lawson_flips(
    layers: Layers, p1: Mesh, in_layer: NDArray, max_rounds: int = MAX_ROUNDS
) -> NDArray:
    """Corners ``(m, 3)`` of ``p1`` after Lawson flips towards the Delaunay triangulation
    of the chart coordinates, made where the quad's four corners are ``in_layer`` ``(n,)``
    points of one chart and it is convex in the chart: the edge a-b of the quad
    a-d-b-c is flipped to c-d when d lies inside the chart circumcircle of (a, b, c)
    (beyond 1e-10 of the squared scale, as :func:`curvimesh.triangulate.metric_delaunay`).
    Rounds of non-conflicting flips, by decreasing violation."""
    pts = np.asarray(p1.points)
    out = np.array(p1.corners, dtype=np.int64)
    inner = in_layer[out].all(axis=1)  # the flips stay among these triangles
    tris = out[inner]
    for _ in range(max_rounds):
        _, t1, t2, a, b, c, d = flip_candidates(Mesh(pts, tris))
        quads = np.column_stack([a, b, c, d])
        which = layers.which[quads]
        idx = np.flatnonzero((which == which[:, :1]).all(axis=1))
        if idx.size == 0:
            break
        xy = _quad_coordinates(layers, quads[idx])
        pa, pb, pc, pd = xy[:, 0], xy[:, 1], xy[:, 2], xy[:, 3]
        det = in_circle(pa, pb, pc, pd)
        scale = ((pa - pd) ** 2).sum(1)
        convex = (orient(pa, pd, pc) > 0) & (orient(pd, pb, pc) > 0)
        # a fold (a triangle inverted in the chart) is undone first, whatever the circles
        folded = (orient(pa, pb, pc) <= 0) | (orient(pb, pa, pd) <= 0)
        viol = convex & (folded | (det > 1e-10 * scale**2))
        cand = idx[viol]
        if cand.size == 0:
            break
        priority = np.where(folded[viol], np.inf, det[viol] / scale[viol] ** 2)
        chosen = cand[independent_flips(t1[cand], t2[cand], priority, len(tris))]
        tris = apply_flips(tris, chosen, t1, t2, a, b, c, d)
    out[inner] = tris
    return out


def _chart_nodes(field: MetricField, layers: Layers, edges: NDArray) -> NDArray:
    """Middle nodes ``(k, 2)`` of edges ``(k, 2)`` between points of one chart: the images
    of the middles of the edges in the chart (:func:`from_chart`)."""
    out = np.empty((len(edges), 2))
    for k, chart in enumerate(layers.charts):
        on = np.flatnonzero(layers.which[edges[:, 0]] == k)
        if on.size == 0:
            continue
        xy = _quad_coordinates(layers, edges[on])
        mid = xy.mean(axis=1)
        out[on] = from_chart(field, chart, mid[:, 0], mid[:, 1])
    return out


def renode(field: MetricField, layers: Layers, mesh: Mesh) -> tuple[Mesh, int]:
    """A valid P2 ``mesh`` with the middle nodes of its edges between points of one chart
    at their chart nodes (:func:`_chart_nodes`) where that shortens the edge
    (:func:`curvimesh.quality.edge_lengths_fast`); and how many moved. All move
    together; then, while a triangle is invalid, its edges take their nodes back
    (as :func:`curvimesh.curve.backtrack_to_valid`, the input's nodes the valid end).

    Why together: the middle node an edge of a layer gets from the curving stage can
    be the straight midpoint (backtracked to validity), and across a thin curved
    layer the chord strays rows from the row it joins (on u58 an edge 1.78 long with
    its chart node, as with its shortest parabola, is 23.8 with its midpoint). Its
    chart node alone leaves a triangle invalid whose other edges are chords; with
    theirs moved too, the triangle bends as the layer does."""
    pts = np.array(mesh.points)
    ends = p1_edges(mesh)
    which = layers.which[ends]
    cand = np.flatnonzero((which[:, 0] >= 0) & (which[:, 0] == which[:, 1]))
    cand = cand[mesh.edge_tris[cand, 1] >= 0]  # not the box's sides
    if cand.size == 0:
        return mesh, 0
    x0, x1 = pts[mesh.edges[cand, 0]], pts[mesh.edges[cand, 1]]
    old = pts[mesh.edge_mid[cand]]
    target = _chart_nodes(field, layers, ends[cand])
    shorter = edge_lengths_fast(field, x0, x1, target, remember=False) < edge_lengths_fast(
        field, x0, x1, old, remember=False
    )
    cand, old, target = cand[shorter], old[shorter], target[shorter]
    moved = np.ones(len(cand), dtype=bool)
    at = np.full(len(mesh.edges), -1, dtype=np.int64)
    at[cand] = np.arange(len(cand))
    touched = np.unique(mesh.edge_tris[cand].ravel())
    touched = touched[touched >= 0]
    while moved.any():
        pts[mesh.edge_mid[cand]] = np.where(moved[:, None], target, old)
        bad = touched[~valid_exact(pts[mesh.triangles[touched]])]
        back = at[mesh.tri_edges[bad].ravel()]
        back = back[back >= 0]
        back = back[moved[back]]
        if back.size == 0:
            break
        moved[back] = False
    pts[mesh.edge_mid[cand]] = np.where(moved[:, None], target, old)
    return Mesh(pts, mesh.triangles, mesh.box), int(moved.sum())


def _triangle_keys(tris: NDArray, n: int) -> NDArray:
    """One integer per triangle ``(m, 3)`` of points numbered below n, the same for any
    order of its corners (n < 2²¹: the key stays below 2⁶³)."""
    t = np.sort(np.asarray(tris, dtype=np.int64), axis=1)
    return (t[:, 0] * n + t[:, 1]) * n + t[:, 2]


def _valid_nodes(
    field: MetricField, layers: Layers, mesh: Mesh, mids: NDArray, fresh: NDArray
) -> tuple[NDArray, NDArray]:
    """Middle nodes ``(E, 2)`` for the edges of a P1 ``mesh``: ``mids`` where ``fresh`` is
    False; elsewhere the chart node (:func:`_chart_nodes`), or, on the edges of the
    triangles that it leaves invalid, the shortest parabola's
    (:func:`curvimesh.freenode.shortest_parabola`). Returns the nodes and the
    triangles still invalid (decided exactly)."""
    pts = np.asarray(mesh.points)
    edges = np.flatnonzero(fresh)
    mids = np.array(mids, dtype=float)
    mids[edges] = _chart_nodes(field, layers, mesh.edges[edges])
    touched = np.flatnonzero(fresh[mesh.tri_edges].any(axis=1))

    def invalid() -> NDArray:
        nodes = np.concatenate([pts[mesh.corners[touched]], mids[mesh.tri_edges[touched]]], axis=1)
        return touched[~valid_exact(nodes)]

    bad = invalid()
    redo = np.unique(mesh.tri_edges[bad])
    redo = redo[fresh[redo]]
    if redo.size == 0:
        return mids, bad
    a, b = pts[mesh.edges[redo, 0]], pts[mesh.edges[redo, 1]]
    mids[redo] = shortest_parabola(field, a, b, exact_length=False).mid
    return mids, invalid()


@dataclass(frozen=True)
class ChartResult:
    """The mesh after the stage, the triangles its layers were triangulated again with
    in their charts, its edges that the input did not have, the edge nodes moved to
    their chart nodes, and how many times the flips were made."""

    mesh: Mesh
    edges: int
    renoded: int
    tries: int
    rebuilt: int = 0


def chart_flips(field: MetricField, mesh: Mesh) -> ChartResult:
    """The stage of the module docstring on a valid P2 ``mesh``: each layer triangulated
    again in its chart (:func:`rebuilt`), the flips where that was not made
    (:func:`flipped`), then the chart nodes of the layers' edges (:func:`renode`).
    The result is valid and has the same vertices."""
    cores = layer_cores(field)
    if mesh.order != 2 or not cores or len(mesh.triangles) == 0:
        return ChartResult(mesh, 0, 0, 0)
    pts = np.asarray(p1_of(mesh).points)
    charts = [chart_of(field, line, closed) for line, closed in cores]
    wide = layer_points(field, pts, charts, REBUILD_MIN_SAG)  # the rebuild's points
    layers = thinned(wide, CORE_MIN_SAG)  # the flips' and the nodes'
    if (layers.which >= 0).sum() < 4:
        return ChartResult(mesh, 0, 0, 0)
    out, made = rebuilt(field, wide, mesh)
    out, edges, tries = flipped(field, layers, out)
    out, moved = renode(field, layers, out)
    return ChartResult(out, edges, moved, tries, made)


def flipped(field: MetricField, layers: Layers, mesh: Mesh) -> tuple[Mesh, int, int]:
    """A valid P2 ``mesh`` after :func:`lawson_flips` among its points in ``layers``, the
    edges of the new triangles with their chart nodes (:func:`_valid_nodes`); its
    edges that ``mesh`` did not have; and how many times the flips were made (the
    corners of the triangles left invalid taken out of the layers each time). The
    input's edge nodes stay on the edges outside the new triangles. With no flip
    left to make, or after :data:`MAX_TRIES`, ``mesh`` itself."""
    p1 = p1_of(mesh)
    pts = np.asarray(p1.points)
    in_layer = layers.which >= 0
    store = edge_nodes(mesh)  # the input's edge nodes, by their ends
    n = len(pts)
    old_tris = np.sort(_triangle_keys(p1.corners, n))
    tries = 0
    while tries < MAX_TRIES and in_layer.sum() >= 4:
        tries += 1
        tris = lawson_flips(layers, p1, in_layer)
        cur = Mesh(pts, tris, p1.box)
        new = ~np.isin(_triangle_keys(tris, n), old_tris, assume_unique=True)
        if not new.any():
            break
        pos, known = store.find(store.key(cur.edges[:, 0], cur.edges[:, 1]))
        mids = np.where(known[:, None], store.mid[pos], 0.0)
        # the edges of the new triangles take their chart nodes (not the box's sides)
        fresh = np.zeros(len(cur.edges), dtype=bool)
        fresh[cur.tri_edges[new].ravel()] = True
        fresh &= ~boundary_edge_mask(cur)
        fresh |= ~known
        mids, bad = _valid_nodes(field, layers, cur, mids, fresh)
        if bad.size == 0:
            return assemble_p2(pts, cur, mids), int((~known).sum()), tries
        in_layer = in_layer.copy()
        in_layer[tris[bad].ravel()] = False
    return mesh, 0, tries


#: Most times a layer is triangulated again in its chart (:func:`rebuilt`), with the
#: points about the triangles left invalid taken out of it each time.
REBUILD_TRIES = 8
#: The points a layer is triangulated again at (:func:`rebuilt`): where a unit chord
#: along it strays this many short sizes or more, half the layer's
#: (:data:`curvimesh.cores.CORE_MIN_SAG`). At 2 the boundary of the triangles
#: replaced ran along the rows just past it, and the triangles one row thick between
#: them, of a base of 0.9 long sizes, were invalid with every node tried: on a
#: 1,000:1 ellipse of semi-axes 0.32 and 0.22 (written to test this, not in
#: bench/robustness) the layer kept its straight triangulation and edges of 3.37;
#: at 1 it is triangulated again and meets every target (1.399, quality 0.52). At
#: 0.5 the same meshes but for a few vertices on u58 and u72.
REBUILD_MIN_SAG = 1.0


def _boundary_edges(tris: NDArray) -> NDArray:
    """The boundary of the triangles ``tris`` ``(m, 3)`` (counter-clockwise): their edges
    a → b ``(k, 2)`` held by no other of them, as they run in their triangle (the
    triangles on their left). :attr:`curvimesh.mesh.Mesh.boundary_lines` lists the
    same edges in another order, which is the order the polygon's edges are inserted
    in (:func:`chart_triangulation`): with points of exactly cocircular rows, another
    triangulation (u57: same figures, other bytes)."""
    de = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    big = int(tris.max()) + 1
    return de[~np.isin(de[:, 1] * big + de[:, 0], de[:, 0] * big + de[:, 1])]


def _fill(tris: NDArray, seed: NDArray, wall: NDArray, window: NDArray) -> NDArray:
    """``(m,)`` the triangles of ``tris`` ``(m, 3)`` reached from the ``seed`` ones through
    edges that are not ``wall`` edges ``(k, 2)`` (either way round), only ever into
    triangles of the ``window`` ``(m,)`` (:func:`curvimesh.kernels.flood_fill`, the
    sides into triangles outside the window walled too)."""
    nbr = np.ascontiguousarray(Mesh(np.zeros((int(tris.max()) + 1, 2)), tris).neighbours)
    big = int(tris.max()) + 1
    a, b = tris, np.roll(tris, -1, axis=1)  # side k: corners k → k + 1, as nbr's
    w = np.sort(wall, axis=1)
    walled = np.isin(np.minimum(a, b) * big + np.maximum(a, b), w[:, 0] * big + w[:, 1])
    walled |= (nbr >= 0) & ~window[np.maximum(nbr, 0)]
    inside = np.zeros(len(tris), dtype=np.bool_)
    kernels.flood_fill(nbr, walled, np.flatnonzero(seed & window), inside)
    return inside


def chart_triangulation(
    s: NDArray, n: NDArray, length: float, closed: bool, polygon: NDArray
) -> tuple[NDArray, NDArray]:
    """The constrained Delaunay triangulation ``(m, 3)`` (counter-clockwise) of points of
    chart coordinates s, n ``(k,)`` inside ``polygon``: directed edges ``(j, 2)`` with
    the inside on their left (one or more loops; around a closed core of the given
    metric length, the points' s taken modulo it). Delaunay's triangulation of the
    points (Qhull), each polygon edge inserted
    (:func:`curvimesh.triangulate.insert_segments`), the triangles reached from the
    polygon's left sides without crossing it kept and flipped towards Delaunay
    (:func:`curvimesh.triangulate.delaunay_flips`). Around a closed core, this is
    made on three copies of the points side by side (s − length, s, s + length),
    from the middle copy. Returns the triangles and the polygon edges that could
    not be inserted (then no triangle)."""
    k = len(s)
    if closed:
        xy = np.column_stack([np.concatenate([s - length, s, s + length]), np.tile(n, 3)])
        ds = np.mod(s[polygon[:, 1]] - s[polygon[:, 0]] + 0.5 * length, length) - 0.5 * length
        jump = np.rint((s[polygon[:, 0]] + ds - s[polygon[:, 1]]) / length).astype(np.int64)
        copies = []
        for c in range(3):
            ok = (c + jump >= 0) & (c + jump <= 2)
            ends = [c * k + polygon[ok, 0], (c + jump[ok]) * k + polygon[ok, 1]]
            copies.append(np.column_stack(ends))
        segs = np.concatenate(copies)
    else:
        xy, segs = np.column_stack([s, n]), polygon
    none = np.zeros((0, 3), dtype=np.int64)
    try:
        tris = Delaunay(xy).simplices.astype(np.int64)
    except QhullError:
        return none, polygon
    area = orient(xy[tris[:, 0]], xy[tris[:, 1]], xy[tris[:, 2]])
    tris = np.where((area < 0)[:, None], tris[:, [0, 2, 1]], tris)[area != 0]
    tris, failed = insert_segments(xy, tris, segs)
    if len(failed):
        return none, failed % k
    # the triangles on the left of the polygon's edges, and those reached from them
    de = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    big = len(xy)
    seed = np.isin(de[:, 0] * big + de[:, 1], segs[:, 0] * big + segs[:, 1])
    seed = seed.reshape(3, -1).any(axis=0)
    middle = xy[tris].mean(axis=1)[:, 0]
    # three copies: the walls end at the ends of the copies, so stay well inside them
    window = (middle >= -0.5 * length) & (middle < 1.5 * length)
    window |= not closed
    inside = tris[_fill(tris, seed, segs, window)]
    inside = delaunay_flips(xy, inside)
    if closed:
        middle = xy[inside].mean(axis=1)[:, 0]
        inside = inside[(middle >= 0.0) & (middle < length)] % k
    return inside, np.zeros((0, 2), dtype=np.int64)


def _node_choices(field: MetricField, layers: Layers, pts: NDArray, a: int, b: int) -> list:
    """Middle nodes to try on the edge a-b of a layer: its chart node, its shortest
    parabola's, its straight midpoint."""
    return [
        _chart_nodes(field, layers, np.array([[a, b]]))[0],
        shortest_parabola(field, pts[[a]], pts[[b]], exact_length=False).mid[0],
        0.5 * (pts[a] + pts[b]),
    ]


def _repaired(
    field: MetricField,
    layers: Layers,
    pts: NDArray,
    mesh: Mesh,
    mids: NDArray,
    free: NDArray,
    bad: NDArray,
) -> tuple[Mesh, NDArray, NDArray]:
    """A P1 ``mesh`` whose triangles ``bad`` are invalid as P2 with the middle nodes
    ``mids`` ``(E, 2)``, after flips of their ``free`` ``(E,)`` edges (convex in the
    chart) where both triangles after the flip are valid, the new edge with one of
    :func:`_node_choices`; rounds while one is made. Returns the mesh, its nodes and
    its triangles still invalid. Few (the layer's outer rows): a loop."""
    n = len(pts)
    tris = [tuple(t) for t in np.asarray(mesh.corners).tolist()]
    ends = np.sort(mesh.edges, axis=1)
    node = dict(zip((ends[:, 0] * n + ends[:, 1]).tolist(), mids, strict=True))
    frozen = set((ends[~free, 0] * n + ends[~free, 1]).tolist())
    watch = set(bad.tolist())

    def key(a: int, b: int) -> int:
        return min(a, b) * n + max(a, b)

    def valid(*ts: tuple[int, int, int]) -> bool:
        nodes = [
            [pts[a], pts[b], pts[c], node[key(a, b)], node[key(b, c)], node[key(c, a)]]
            for a, b, c in ts
        ]
        return bool(valid_exact(np.array(nodes)).all())

    while True:
        holders: dict[int, list[int]] = {}
        for i, t in enumerate(tris):
            for j in range(3):
                holders.setdefault(key(t[j], t[(j + 1) % 3]), []).append(i)
        bad_now = sorted(i for i in watch if not valid(tris[i]))
        changed: set[int] = set()
        for i in bad_now:
            if i in changed:
                continue
            for j in range(3):
                a, b, c = tris[i][j], tris[i][(j + 1) % 3], tris[i][(j + 2) % 3]
                pair = holders[key(a, b)]
                if key(a, b) in frozen or len(pair) != 2:
                    continue
                i2 = pair[0] if pair[1] == i else pair[1]
                if i2 in changed:
                    continue
                d = next(v for v in tris[i2] if v not in (a, b))
                if key(c, d) in node:  # joined outside the layer already
                    continue
                pa, pd, pb, pc = _quad_coordinates(layers, np.array([[a, d, b, c]]))[0]
                if orient(pa, pd, pc) <= 0 or orient(pd, pb, pc) <= 0:
                    continue
                for choice in _node_choices(field, layers, pts, c, d):
                    node[key(c, d)] = choice
                    if valid((a, d, c), (d, b, c)):
                        tris[i], tris[i2] = (a, d, c), (d, b, c)
                        changed.update((i, i2))
                        watch.update((i, i2))
                        break
                else:
                    del node[key(c, d)]
                    continue
                break
        if not changed:
            break
    out = Mesh(pts, np.array(tris, dtype=np.int64), mesh.box)
    ends = np.sort(out.edges, axis=1)
    mids = np.array([node[k] for k in (ends[:, 0] * n + ends[:, 1]).tolist()])
    still = np.array(sorted(i for i in watch if not valid(tris[i])), dtype=np.int64)
    return out, mids, still


#: Length from which an edge counts against a layer's new triangulation: the top of
#: the unit range.
LONG_EDGE = 1.4


def _long_edges(field: MetricField, mesh: Mesh, tris: NDArray) -> int:
    """How many edges of the triangles ``tris`` ``(k,)`` of the P2 ``mesh`` are longer than
    :data:`LONG_EDGE`."""
    at = np.unique(mesh.tri_edges[tris])
    pts = mesh.points
    x0, x1, xm = pts[mesh.edges[at, 0]], pts[mesh.edges[at, 1]], pts[mesh.edge_mid[at]]
    return int((edge_lengths_fast(field, x0, x1, xm, remember=False) > LONG_EDGE).sum())


def _near(corners: NDArray, points: NDArray) -> NDArray:
    """The corners of the triangles ``corners`` ``(m, 3)`` at any of ``points``."""
    return np.unique(corners[np.isin(corners, points).any(axis=1)])


def _rebuilt_layer(field: MetricField, layers: Layers, mesh: Mesh, k: int) -> tuple[Mesh, int, int]:
    """:func:`rebuilt` for the layer of chart k: the mesh, the triangles made, the tries."""
    p1 = p1_of(mesh)
    pts = np.asarray(p1.points)
    corners = np.asarray(p1.corners)
    npts = len(pts)
    chart = layers.charts[k]
    inner = (layers.which == k) & ~p1.boundary_vertices
    store = edge_nodes(mesh)
    for tries in range(1, REBUILD_TRIES + 1):
        if inner.sum() < 4:
            break
        region = inner[corners].any(axis=1)
        ring = np.unique(corners[region])
        ring = ring[~inner[ring]]
        rs, rn, foot_in = to_chart(field, chart, pts[ring])
        if not foot_in.all():  # past an open core's end
            inner[_near(corners, ring[~foot_in])] = False
            continue
        ids = np.concatenate([np.flatnonzero(inner), ring])
        local = np.full(npts, -1, dtype=np.int64)
        local[ids] = np.arange(len(ids))
        s = np.concatenate([layers.s[inner], rs])
        s = np.mod(s, chart.length) if chart.closed else s
        n = np.concatenate([layers.n[inner], rn])
        polygon = _boundary_edges(corners[region])
        tris, failed = chart_triangulation(s, n, chart.length, chart.closed, local[polygon])
        if len(failed):
            inner[_near(corners, ids[failed.ravel()])] = False
            continue
        new = ids[tris]
        if len(new) != region.sum():  # a point of the layer outside the polygon
            lost = inner.copy()
            lost[new.ravel()] = False
            if not lost.any():
                break
            inner[_near(corners, np.flatnonzero(lost))] = False
            continue
        cur = Mesh(pts, np.vstack([corners[~region], new]), p1.box)
        if not is_conforming(cur) or len(cur.boundary_edges) != len(p1.boundary_edges):
            break
        ext = Layers(
            layers.charts, layers.which.copy(), layers.s.copy(), layers.n.copy(), layers.sag
        )
        ext.which[ring], ext.s[ring], ext.n[ring] = k, rs, rn
        pos, known = store.find(store.key(cur.edges[:, 0], cur.edges[:, 1]))
        mids = np.where(known[:, None], store.mid[pos], 0.0)
        # the polygon's edges (and the box's sides) keep their nodes
        ends = np.sort(cur.edges, axis=1)
        wall = np.sort(polygon, axis=1)
        free = ~np.isin(ends[:, 0] * npts + ends[:, 1], wall[:, 0] * npts + wall[:, 1])
        free &= ~boundary_edge_mask(cur)
        fresh = np.zeros(len(cur.edges), dtype=bool)
        fresh[cur.tri_edges[len(cur.corners) - len(new) :].ravel()] = True
        fresh = (fresh & free) | ~known
        mids, bad = _valid_nodes(field, ext, cur, mids, fresh)
        if bad.size:
            cur, mids, bad = _repaired(field, ext, pts, cur, mids, fresh, bad)
        if bad.size == 0:
            out = assemble_p2(pts, cur, mids)  # the new triangles last, as in cur
            made = np.arange(len(cur.corners) - len(new), len(cur.corners))
            if _long_edges(field, out, made) < _long_edges(field, mesh, np.flatnonzero(region)):
                return out, len(new), tries
            break
        inner[_near(np.asarray(cur.corners), np.asarray(cur.corners)[bad].ravel())] = False
    return mesh, 0, tries


def rebuilt(field: MetricField, layers: Layers, mesh: Mesh) -> tuple[Mesh, int]:
    """A valid P2 ``mesh`` with each of its ``layers`` triangulated again in its chart, and
    how many triangles were made so.

    The triangles at the points of a layer (their star) are replaced by the
    constrained Delaunay triangulation, in the layer's chart, of those points and the
    other corners of the star, inside the star's boundary (:func:`chart_triangulation`;
    the boundary's edges keep their nodes). Made from the chart's coordinates alone,
    the triangulation does not start from the straight one, which folds across a layer
    that curves (:func:`lawson_flips` stops on the folds of a layer sampled row by row,
    :mod:`curvimesh.rows`). Its new edges take their chart nodes, or, where that leaves
    a triangle invalid, their shortest parabolas' (:func:`_valid_nodes`); the triangles
    still invalid (decided exactly) have their edges flipped where that makes both
    triangles valid (:func:`_repaired`). Where some are left, or the boundary cannot
    be kept, the points about them are taken out of the layer and the triangulation
    made again, at most :data:`REBUILD_TRIES` times; then the layer keeps its mesh.
    A valid new triangulation is kept only where it has fewer edges longer than
    :data:`LONG_EDGE` than the triangles it replaces: about two 500:1 rings side by
    side (``bench/robustness/u57``) sampled by the fronts, the layers' edges over 1.5
    on the curved mesh went from 3 to 243 (why, not found)."""
    made = 0
    for k in range(len(layers.charts)):
        mesh, count, _ = _rebuilt_layer(field, layers, mesh, k)
        made += count
    return mesh, made


__all__ = [
    "REBUILD_TRIES",
    "Chart",
    "ChartResult",
    "Layers",
    "chart_flips",
    "chart_of",
    "chart_triangulation",
    "flipped",
    "from_chart",
    "lawson_flips",
    "layer_points",
    "rebuilt",
    "renode",
    "segment_lengths",
    "thinned",
    "to_chart",
]
