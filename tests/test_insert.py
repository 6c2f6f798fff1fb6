"""Vertex insertion into the cavities of long curved edges, against independent answers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import brentq

from curvimesh import adapt as pipeline
from curvimesh import insert
from curvimesh.bezier import valid_exact
from curvimesh.insert import insert_points, metric_fraction_params
from curvimesh.mesh import Mesh, is_conforming
from curvimesh.metric import load_metric, load_metric_text
from curvimesh.quality import COUNT_RTOL, edge_lengths
from curvimesh.triangulate import delaunay

METRICS = Path(__file__).resolve().parents[1] / "metrics"

ISO = """
domain: {box: [[0, 0], [1, 1]]}
metric:
  eigen: {sizes: [0.1, 0.1], angle: 0}
"""

ANISO = """
domain: {box: [[-1, -1], [2, 2]]}
metric:
  eigen: {sizes: [0.1, 1.0], angle: 0}
"""


def _arc_param(g: np.ndarray, x0, x1, xm, fraction: float) -> float:
    """t where the parabola through x0, xm, x1 has run ``fraction`` of its length in g (scipy)."""
    x0, x1, xm = map(np.asarray, (x0, x1, xm))

    def speed(t: float) -> float:
        d = (4 * t - 3) * x0 + (4 * t - 1) * x1 + (4 - 8 * t) * xm
        return float(np.sqrt(d @ g @ d))

    total = quad(speed, 0, 1, epsabs=1e-12)[0]
    return brentq(lambda t: quad(speed, 0, t, epsabs=1e-12)[0] - fraction * total, 0, 1)


def test_fraction_params_of_a_straight_edge_are_the_fractions():
    fld = load_metric_text(ISO)
    x0, x1 = np.array([[0.1, 0.2]]), np.array([[0.7, 0.5]])
    t = metric_fraction_params(fld, x0, x1, 0.5 * (x0 + x1), np.array([0.25, 0.5, 0.9]))
    np.testing.assert_allclose(t, [[0.25, 0.5, 0.9]], atol=1e-12)


@pytest.mark.parametrize("metric", [ISO, ANISO])
def test_fraction_params_of_curved_edges_match_quadrature(metric):
    fld = load_metric_text(metric)
    g = fld.tensor(np.array([[0.5, 0.5]]))[0]
    x0 = np.array([[0.0, 0.0], [0.2, 0.9]])
    x1 = np.array([[1.0, 0.0], [0.9, 0.1]])
    xm = np.array([[0.5, 0.35], [0.4, 0.3]])  # strongly bent parabolas
    fr = np.array([0.3, 0.5, 0.6])
    t = metric_fraction_params(fld, x0, x1, xm, fr)
    for i in range(2):
        want = [_arc_param(g, x0[i], x1[i], xm[i], f) for f in fr]
        np.testing.assert_allclose(t[i], want, atol=2e-4)


def _holed_grid(fld, *, skip: int = 1):
    """A curved (here straight, the metric is constant) P2 mesh of a 0.1 grid with holes."""
    s = np.linspace(0.0, 1.0, 11)
    x, y = np.meshgrid(s, s)
    pts = np.column_stack([x.ravel(), y.ravel()])
    holes = [(0.5, 0.5), (0.3, 0.7)][:skip]
    keep = np.ones(len(pts), dtype=bool)
    for h in holes:
        keep &= np.hypot(*(pts - h).T) > 1e-9
    # a slight shake (deterministic) so that the Delaunay triangulation is unique
    rng = np.random.default_rng(3)
    pts = pts[keep]
    inner = (pts > 0).all(axis=1) & (pts < 1).all(axis=1)
    pts[inner] += rng.uniform(-0.004, 0.004, (int(inner.sum()), 2))
    return pipeline.curve(fld, delaunay(pts, box=fld.box))


def _lengths(fld, mesh):
    return edge_lengths(fld, np.asarray(mesh.points), mesh.edges, mesh.edge_mid)


def test_insertion_fills_holes_and_keeps_a_valid_tiling():
    fld = load_metric_text(ISO)
    mesh = _holed_grid(fld, skip=2)
    before = _lengths(fld, mesh)
    assert before.max() > 1.8  # the edges across the holes
    res = insert_points(fld, mesh)
    out = res.mesh
    assert res.inserted >= 2
    assert len(out.vertex_ids) == len(mesh.vertex_ids) + res.inserted
    assert is_conforming(out)
    assert valid_exact(out.points[out.triangles]).all()
    # a tiling of the same domain: areas (straight edges here) add up to the box
    p = out.points[out.corners]
    u, v = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    area = 0.5 * (u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])
    assert (area > 0).all()
    assert np.isclose(area.sum(), 1.0, rtol=1e-12)
    after = _lengths(fld, out)
    assert after.min() >= 0.7 - 1e-9
    assert after.max() < 1.5
    # each hole got a vertex near its centre (the removed grid point, 1 from its neighbours)
    new = out.points[out.vertex_ids][len(mesh.vertex_ids) :]
    for h in [(0.5, 0.5), (0.3, 0.7)]:
        assert np.hypot(*(new - h).T).min() < 0.03


def test_insertion_is_deterministic_and_idle_without_long_edges():
    fld = load_metric_text(ISO)
    mesh = _holed_grid(fld)
    a, b = insert_points(fld, mesh).mesh, insert_points(fld, mesh).mesh
    assert np.array_equal(a.points, b.points) and np.array_equal(a.triangles, b.triangles)
    again = insert_points(fld, a, max_length=2.0)
    assert again.inserted == 0 and again.mesh is a


def test_insertion_never_comes_closer_than_min_dist():
    fld = load_metric_text(ISO)
    mesh = _holed_grid(fld)
    # with min_dist 1.1 no point of the hole is far enough from its eight neighbours
    res = insert_points(fld, mesh, min_dist=1.1)
    assert res.inserted == 0
    assert isinstance(res.mesh, Mesh)


def test_a_round_carries_the_lengths_of_the_edges_it_keeps():
    # the three toys' unit mesh before any insertion: after one round, the edges that
    # stayed bring their lengths along and the new ones are measured; bit for bit the
    # lengths of the new mesh measured afresh
    fld = load_metric(METRICS / "three_toys.yaml")
    opt = pipeline.AdaptOptions(insert=False, shift=False, remove=False, repeat=False)
    mesh = pipeline.adapt(fld, opt).mesh
    length = edge_lengths(fld, mesh.points, mesh.edges, mesh.edge_mid, rtol=COUNT_RTOL)
    out, k, carried = insert._insert_round(fld, mesh, length, 1.4, 0.7, 0.3)
    assert k > 0
    fresh = edge_lengths(fld, out.points, out.edges, out.edge_mid, rtol=COUNT_RTOL)
    assert carried.tobytes() == fresh.tobytes()
    assert len(out.edges) != len(mesh.edges)
