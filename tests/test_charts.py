"""Thin curved layers in their own coordinates: the chart against a ring's analytic
lengths, and the flips that join a staggered lattice across a ring to its neighbours
only."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray
from test_cores import ring as ring_yaml

from curvimesh import charts
from curvimesh.adapt import SWAP_STAGES, AdaptOptions, adapt, curve, sample, swap, triangulate
from curvimesh.bezier import valid_exact
from curvimesh.cores import layer_cores
from curvimesh.mesh import Mesh, flip_candidates, p1_of
from curvimesh.metric import load_metric, load_metric_text
from curvimesh.quality import edge_lengths
from curvimesh.report import mesh_report
from curvimesh.triangulate import in_circle, orient

METRICS = Path(__file__).resolve().parent.parent / "metrics"

#: A ring of radius R about C: radial size H0 + G |r − R| (to 0.1), 0.1 round it.
R, H0, G, C = 0.3, 1e-4, 0.25, np.array([0.5, 0.5])
RING = ring_yaml(R, H0, centre=(float(C[0]), float(C[1])), growth=G)


def radial_metric_length(delta: NDArray) -> NDArray:
    """∫₀^|δ| dr / (H0 + G r), signed: the metric length from the circle out to r = R + δ."""
    return np.sign(delta) * np.log1p(G * np.abs(delta) / H0) / G


def radial_offset(n: NDArray) -> NDArray:
    """The δ whose :func:`radial_metric_length` is n."""
    return np.sign(n) * np.expm1(G * np.abs(n)) * H0 / G


@pytest.fixture(scope="module")
def ring():
    fld = load_metric_text(RING)
    (line, closed), *rest = layer_cores(fld)
    assert closed and not rest
    return fld, charts.chart_of(fld, line, closed)


def test_the_chart_of_a_ring_measures_arcs_round_it_and_metric_lengths_across(ring):
    fld, chart = ring
    # round the circle, 0.1 long sizes: 2π R / 0.1
    assert chart.length == pytest.approx(2 * math.pi * R / 0.1, rel=1e-6)
    theta = np.linspace(0.1, 6.0, 9)
    delta = np.array([-8e-3, -1e-3, -2e-4, -1e-5, 0.0, 1e-5, 3e-4, 2e-3, 9e-3])
    pts = C + (R + delta)[:, None] * np.column_stack([np.cos(theta), np.sin(theta)])
    s, n, inside = charts.to_chart(fld, chart, pts)
    assert inside.all()
    # the feet lie on the radii: s grows as R θ / 0.1 (either way round)
    ds = np.mod(np.diff(s), chart.length)
    if ds[0] > chart.length / 2:  # traced clockwise
        ds = chart.length - ds
    np.testing.assert_allclose(ds, R * np.diff(theta) / 0.1, rtol=1e-6)
    # across, the metric length of the radial segment, the sign telling the sides apart;
    # the traced core lies on the circle to about 3e-8 (its line searches' precision),
    # 3e-4 of the radial size there
    side = np.sign(n[-1])
    np.testing.assert_allclose(side * n, radial_metric_length(delta), rtol=1e-6, atol=5e-4)


def test_from_chart_inverts_to_chart(ring):
    fld, chart = ring
    rng = np.random.default_rng(3)
    theta = rng.uniform(0, 2 * math.pi, 50)
    delta = radial_offset(rng.uniform(-20, 20, 50))
    pts = C + (R + delta)[:, None] * np.column_stack([np.cos(theta), np.sin(theta)])
    s, n, _ = charts.to_chart(fld, chart, pts)
    back = charts.from_chart(fld, chart, s, n)
    # to a thousandth of the least radial size
    np.testing.assert_allclose(back, pts, rtol=0, atol=1e-7)


def lattice(columns: int, rows: int, stagger: bool = False) -> NDArray:
    """Points (columns × (2 rows + 1), 2) of a polar lattice across the ring: the columns
    evenly round it, the rows a unit of metric length apart across it; then the centre
    and eight points half way to the ring, and the box's corners and sides a unit long
    size apart."""
    i = np.arange(-rows, rows + 1)
    theta = 2 * math.pi * (np.arange(columns)[:, None] + 0.25 + 0.5 * stagger * (i % 2)) / columns
    rad = R + radial_offset(i.astype(float))
    pts = C + rad[None, :, None] * np.stack([np.cos(theta), np.sin(theta)], axis=-1)
    inner = 2 * math.pi * np.arange(8) / 8
    inside = np.vstack([C, C + 0.5 * R * np.column_stack([np.cos(inner), np.sin(inner)])])
    side = np.linspace(0.0, 1.0, 11)
    box = np.unique(
        np.concatenate(
            [np.column_stack([side, 0 * side]), np.column_stack([side, 0 * side + 1]),
             np.column_stack([0 * side, side]), np.column_stack([0 * side + 1, side])]
        ),
        axis=0,
    )  # fmt: skip
    return np.concatenate([pts.reshape(-1, 2), inside, box])


def far_joined(mesh: Mesh, columns: int, rows: int) -> int:
    """The edges between points of a staggered lattice (:func:`lattice`) that are not
    neighbours: more than one row apart, or in the same row more than one column
    apart, or in adjacent rows more than half a column apart. The innermost row is
    left out: it borders the disc inside, empty down to the points half way, and
    its chords and the fans over them join it to that disc."""
    per = 2 * rows + 1
    e = p1_of(mesh).edges
    e = e[(e < columns * per).all(axis=1)]
    col, row = e // per, e % per
    keep = (row > 0).all(axis=1)
    col, row = col[keep], row[keep]
    half = 2 * col + (row - rows) % 2  # the position round the ring in half columns
    dh = np.abs(half[:, 0] - half[:, 1])
    dh = np.minimum(dh, 2 * columns - dh)
    dr = np.abs(row[:, 0] - row[:, 1])
    return int(((dr > 1) | ((dr == 1) & (dh > 1)) | ((dr == 0) & (dh > 2))).sum())


def test_the_flips_join_a_staggered_lattice_across_a_ring_to_its_neighbours_only(ring):
    """The chart straightens the ring: its rows become lines, its columns lines across
    them, and the Delaunay triangulation there joins each point of a lattice whose
    rows are staggered by half a column to its two neighbours in its row and the two
    nearest in each row beside it. The triangulation in the metric, straight-sided,
    joins points several columns apart under the chords of the rows (0.94 long
    sizes apart round a circle of radius 3 long sizes, they stray 30 radial sizes
    from the circle)."""
    fld, _ = ring
    columns, rows = 20, 3
    pts = lattice(columns, rows, stagger=True)
    cloud = Mesh(pts, np.zeros((0, 3), dtype=np.int64), fld.box)
    mesh = curve(fld, triangulate(cloud, fld, AdaptOptions(relocate=False)))
    assert far_joined(mesh, columns, rows) > 50
    res = charts.chart_flips(fld, mesh)
    assert valid_exact(res.mesh.points[res.mesh.triangles]).all()
    assert far_joined(res.mesh, columns, rows) == 0
    np.testing.assert_array_equal(res.mesh.points[res.mesh.vertex_ids], pts)


def test_no_core_leaves_the_mesh_as_it_is():
    fld = load_metric(METRICS / "toy.yaml")
    pts = np.random.default_rng(0).uniform(0, 1, (60, 2))
    mesh = curve(fld, triangulate(Mesh(pts, np.zeros((0, 3), dtype=np.int64), fld.box), fld))
    res = charts.chart_flips(fld, mesh)
    assert res.mesh is mesh and res.edges == 0


def test_the_swap_stage_runs_the_chart_flips_unless_turned_off(ring):
    fld, _ = ring
    pts = lattice(20, 3, stagger=True)
    cloud = Mesh(pts, np.zeros((0, 3), dtype=np.int64), fld.box)
    mesh = curve(fld, triangulate(cloud, fld, AdaptOptions(relocate=False)))
    later = set(SWAP_STAGES) - {"charts"}
    only = AdaptOptions(**dict.fromkeys(later, False))
    assert swap(fld, mesh, only).chart_edges == charts.chart_flips(fld, mesh).edges > 0
    assert swap(fld, mesh, replace(only, charts=False)).chart_edges == 0


def test_renode_lays_the_edges_along_a_rows_on_the_row(ring):
    """Straight-sided, an edge between neighbours of a row is a chord 14 – 24 long (it
    strays 30 radial sizes inside the circle); its chart node is the point of the row
    (the circle of radius R + δ) half way round, the edge then 0.95 long. The
    innermost row is left out, as in :func:`far_joined`: it borders the empty disc,
    whose triangles fold when its edges bend outwards."""
    fld, chart = ring
    columns, rows = 20, 3
    per = 2 * rows + 1
    pts = lattice(columns, rows)
    cloud = Mesh(pts, np.zeros((0, 3), dtype=np.int64), fld.box)
    mesh = curve(
        fld, triangulate(cloud, fld, AdaptOptions(relocate=False)), AdaptOptions(straight=True)
    )
    layer = charts.layer_points(fld, pts, [chart])
    out, moved = charts.renode(fld, layer, mesh)
    assert valid_exact(out.points[out.triangles]).all()
    e = out.edges
    col, row = e // per, e % per
    dc = np.abs(col[:, 0] - col[:, 1])
    along = (e < columns * per).all(axis=1) & (row[:, 0] == row[:, 1]) & (row[:, 0] > 0)
    along &= np.minimum(dc, columns - dc) == 1
    assert along.sum() == columns * (2 * rows) and moved >= along.sum()
    rel = out.points[out.edge_mid[along]] - C
    offset = radial_offset((row[along, 0] - rows).astype(float))
    size = H0 + G * np.abs(offset)
    np.testing.assert_allclose(
        np.hypot(rel[:, 0], rel[:, 1]), R + offset, rtol=0, atol=1e-3 * size.min()
    )
    half = 2 * math.pi * (np.minimum(col[along, 0], col[along, 1]) + 0.75) / columns
    wrap = np.abs(col[along, 0] - col[along, 1]) > 1  # the pair across angle 0
    half = np.where(wrap, 2 * math.pi * (columns - 0.25) / columns, half)
    angle = np.arctan2(rel[:, 1], rel[:, 0]) % (2 * math.pi)
    np.testing.assert_allclose(angle, half % (2 * math.pi), rtol=0, atol=1e-9)


@settings(max_examples=5, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.floats(0.15, 0.3),
    st.floats(5e-5, 5e-4),
    st.floats(0.1, 0.4),
    st.floats(0.45, 0.55),
    st.floats(0.45, 0.55),
)
def test_the_chart_flips_keep_any_thin_ring_s_curved_mesh_valid(radius, h0, growth, cx, cy):
    """Any thin ring (100:1 to 2,000:1, radius 0.15 – 0.3): on the curved mesh of the
    first three stages, the stage leaves every triangle valid (decided exactly), the
    vertices where they are, as many triangles, and the box's sides as they were."""
    fld = load_metric_text(ring_yaml(radius, h0, centre=(cx, cy), growth=growth))
    opt = AdaptOptions()
    mesh = curve(fld, triangulate(sample(fld, opt), fld, opt), opt)
    res = charts.chart_flips(fld, mesh)
    out = res.mesh
    assert valid_exact(out.points[out.triangles]).all()
    assert len(out.triangles) == len(mesh.triangles)
    np.testing.assert_array_equal(out.points[out.vertex_ids], mesh.points[mesh.vertex_ids])
    sides = lambda m: {  # noqa: E731
        tuple(np.round(m.points[m.edge_mid[e]], 15)) for e in np.flatnonzero(m.edge_tris[:, 1] < 0)
    }
    assert sides(out) == sides(mesh)


def _band(rng: np.random.Generator, length: float, half: float, inner: int):
    """Points of a band of a chart: rows n = ±half with a point every unit (the top one
    half a unit on), ``inner`` random points between; and its boundary with the band on
    the left (the bottom row forwards, the top row backwards, each closing round)."""
    k = int(length)
    bottom = np.column_stack([np.arange(k, dtype=float), np.full(k, -half)])
    top = np.column_stack([np.arange(k) + 0.5, np.full(k, half)])
    inside = np.column_stack([rng.uniform(0, length, inner), rng.uniform(-0.9, 0.9, inner) * half])
    pts = np.vstack([bottom, top, inside])
    i = np.arange(k)
    polygon = np.vstack(
        [np.column_stack([i, (i + 1) % k]), np.column_stack([k + (i + 1) % k, k + i])]
    )
    return pts, polygon


def _unwrapped(pts: NDArray, tris: NDArray, length: float) -> NDArray:
    """Chart coordinates ``(m, 3, 2)`` of triangles round a closed core, s measured from
    each first corner's."""
    xy = pts[tris]
    s0 = xy[:, :1, 0]
    xy[..., 0] = s0 + np.mod(xy[..., 0] - s0 + 0.5 * length, length) - 0.5 * length
    return xy


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(12, 40), st.floats(1.0, 4.0), st.floats(0.5, 1.5))
def test_the_chart_triangulation_of_a_band_round_a_closed_core_covers_it_once(
    seed, length, half, density
):
    """A band |n| ≤ half round a closed core of metric length L, its rows' points on its
    boundary a unit apart and random points inside (0.5 – 1.5 per unit of area, as a
    layer's): the triangles cover it once (their areas add up to 2 half L, every one
    counter-clockwise), use every point, hold every boundary edge, and no edge inside
    has the fourth corner of its quad in the circle of a triangle (constrained
    Delaunay)."""
    rng = np.random.default_rng(seed)
    pts, polygon = _band(rng, float(length), half, int(density * 2 * half * length))
    tris, failed = charts.chart_triangulation(pts[:, 0], pts[:, 1], float(length), True, polygon)
    assert len(failed) == 0
    xy = _unwrapped(pts, tris, float(length))
    area = orient(xy[:, 0], xy[:, 1], xy[:, 2])
    assert (area > 0).all()
    assert 0.5 * area.sum() == pytest.approx(2 * half * length, rel=1e-9)
    assert set(tris.ravel().tolist()) == set(range(len(pts)))
    mesh = Mesh(np.zeros((len(pts), 2)), tris)
    edges = set(map(tuple, np.sort(mesh.edges, axis=1).tolist()))
    assert set(map(tuple, np.sort(polygon, axis=1).tolist())) <= edges
    _, _, _, a, b, c, d = flip_candidates(mesh)
    quad = _unwrapped(pts, np.column_stack([a, b, c, d]), float(length))
    det = in_circle(quad[:, 0], quad[:, 1], quad[:, 2], quad[:, 3])
    scale = ((quad[:, 0] - quad[:, 3]) ** 2).sum(1)
    assert (det <= 1e-9 * scale**2).all()


def test_the_chart_triangulation_of_a_rectangle_keeps_to_it():
    """An open chart: the rectangle [0, 10] × [−2, 2], its sides' points a unit apart
    and 60 points inside, is covered once (area 40) by triangles on its points alone."""
    rng = np.random.default_rng(7)
    ring = [(float(x), -2.0) for x in range(10)] + [(10.0, float(y)) for y in range(-2, 2)]
    ring += [(float(x), 2.0) for x in range(10, 0, -1)]
    ring += [(0.0, float(y)) for y in range(2, -2, -1)]
    k = len(ring)
    pts = np.vstack([np.array(ring), rng.uniform([0.2, -1.8], [9.8, 1.8], (60, 2))])
    polygon = np.column_stack([np.arange(k), (np.arange(k) + 1) % k])
    tris, failed = charts.chart_triangulation(pts[:, 0], pts[:, 1], 10.0, False, polygon)
    assert len(failed) == 0
    area = orient(pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]])
    assert (area > 0).all() and 0.5 * area.sum() == pytest.approx(40.0, rel=1e-12)
    assert len(tris) == 2 * 60 + k - 2  # Euler: 2 inner + boundary − 2


def test_a_ring_sampled_row_by_row_is_triangulated_again_in_its_chart(ring):
    """The ring sampled row by row (:mod:`curvimesh.rows`): after the first three stages
    the edges among its layer's points run up to 25 long, hundreds over 1.5, the
    straight triangulation joining points of a row many columns apart under its chords.
    Triangulated again in the chart, none is over 1.5, the mesh is valid (decided
    exactly) and keeps its vertices and its number of edges."""
    fld, _ = ring
    opt = AdaptOptions(sampling=replace(AdaptOptions().sampling, rows=True))
    mesh = curve(fld, triangulate(sample(fld, opt), fld, opt), opt)
    pts = np.asarray(p1_of(mesh).points)
    layers = charts.layer_points(fld, pts, [charts.chart_of(fld, *c) for c in layer_cores(fld)])

    def layer_lengths(m: Mesh) -> NDArray:
        inside = (layers.which[p1_of(m).edges] >= 0).all(axis=1)
        e = m.edges[inside]
        return edge_lengths(fld, m.points, e, m.edge_mid[inside])

    before = layer_lengths(mesh)
    out, made = charts.rebuilt(fld, layers, mesh)
    after = layer_lengths(out)
    assert (before > 1.5).sum() > 300 and made > 500
    assert after.max() <= 1.5 and len(after) == len(before)
    assert valid_exact(out.points[out.triangles]).all()
    np.testing.assert_array_equal(out.points[out.vertex_ids], mesh.points[mesh.vertex_ids])


def test_layers_thinned_to_a_larger_sag_are_those_measured_with_it(ring):
    """The chart stage measures the layer's points once, at the rebuild's sag, and thins
    them to the flips' (:func:`charts.thinned`): the same points, charts and
    coordinates as measuring at the flips' sag directly."""
    fld, chart = ring
    opt = AdaptOptions(sampling=replace(AdaptOptions().sampling, rows=True))
    pts = np.asarray(sample(fld, opt).points)
    wide = charts.layer_points(fld, pts, [chart], charts.REBUILD_MIN_SAG)
    direct = charts.layer_points(fld, pts, [chart])
    thin = charts.thinned(wide, charts.CORE_MIN_SAG)
    assert (wide.which >= 0).sum() > (direct.which >= 0).sum() > 100
    for a, b in ((thin.which, direct.which), (thin.s, direct.s), (thin.n, direct.n)):
        np.testing.assert_array_equal(a, b)


#: 1,000:1 about the ellipse of semi-axes 0.32 and 0.22 (radius of curvature 0.15 at
#: its ends, where the layer reaches 0.08 inside): written to test the triangulation
#: in the chart, not in bench/robustness.
ELLIPSE = """
name: ellipse_1000
domain: {box: [[0, 0], [1, 1]]}
definitions:
  q: sqrt(((x - 0.5)/0.32)**2 + ((y - 0.5)/0.22)**2)
metric:
  eigen:
    sizes: ['min(0.0001 + 0.2*abs(q - 1), 0.08)', 0.08]
    angle: atan2((y - 0.5)/0.22**2, (x - 0.5)/0.32**2)
"""


def test_a_thin_ellipse_meets_every_target_in_adapt_s_first_run():
    """Issue 7's targets on a 1,000:1 ellipse, without further runs: valid (decided
    exactly), every edge in [0.7, 1.5], 98 % of them in [0.7, 1.4], quality at least
    0.3 (mean 0.8), at most 1.15 times the ideal triangle count."""
    fld = load_metric_text(ELLIPSE)
    res = adapt(fld, AdaptOptions(retry=False))
    rep = mesh_report(fld, res.mesh, metric_area=res.metric_area)
    assert rep["valid"]
    assert 0.7 * (1 - 1e-5) <= rep["edge_length"]["min"] and rep["edge_length"]["max"] <= 1.5
    assert rep["edge_length"]["in_range"] >= 0.98
    assert rep["quality"]["min"] >= 0.3 and rep["quality"]["mean"] >= 0.8
    assert rep["efficiency"] <= 1.15
