"""Re-curving edge nodes towards their shortest parabolas, against independent answers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import minimize_scalar
from test_pipeline import slow_check

from curvimesh import adapt as pipeline
from curvimesh.bezier import valid_exact
from curvimesh.geodesic import bisector_normal, parabola_length, shortest_parabola
from curvimesh.mesh import Mesh, to_p2_straight
from curvimesh.metric import load_metric_text
from curvimesh.quality import edge_lengths, metric_areas, quality_from
from curvimesh.recurve import FRACTIONS, optimal_nodes, recurve
from curvimesh.triangulate import delaunay

CONSTANT = """
domain: {box: [[0, 0], [1, 1]]}
metric:
  eigen: {sizes: [0.1, 0.25], angle: 0.4}
"""

# the Poincaré half-plane g = I / y²: geodesics are circles centred on the x-axis
HALF_PLANE = """
domain: {box: [[-1, 0.5], [1, 1.5]]}
metric:
  tensor: ["1/y**2", 0, "1/y**2"]
"""

# a sharp circular front (as in test_pipeline): curving must backtrack
FRONT = """
domain: {box: [[-1, -1], [1, 1]]}
definitions:
  r: sqrt(x**2 + y**2)
metric:
  eigen:
    sizes: ["0.02 + 0.3*(1 - exp(-((r - 0.5)/0.2)**2))", 0.3]
    angle: atan2(y, x)
"""


def _p1_grid(fld, n: int, *, shake: float = 0.0) -> Mesh:
    """P1 Delaunay mesh of an n × n grid of the box (interior points shaken, seeded)."""
    x0, y0, x1, y1 = fld.box
    X, Y = np.meshgrid(np.linspace(x0, x1, n), np.linspace(y0, y1, n))
    pts = np.column_stack([X.ravel(), Y.ravel()])
    inner = (pts[:, 0] > x0) & (pts[:, 0] < x1) & (pts[:, 1] > y0) & (pts[:, 1] < y1)
    h = (x1 - x0) / (n - 1)
    pts[inner] += np.random.default_rng(7).uniform(-shake * h, shake * h, (int(inner.sum()), 2))
    return delaunay(pts, box=fld.box)


def _grid(fld, n: int, *, shake: float = 0.0) -> Mesh:
    """Straight P2 mesh of :func:`_p1_grid`."""
    return to_p2_straight(_p1_grid(fld, n, shake=shake))


def _interior(mesh: Mesh) -> np.ndarray:
    return np.flatnonzero(mesh.edge_tris[:, 1] >= 0)


def _lengths(fld, mesh: Mesh) -> np.ndarray:
    return edge_lengths(fld, np.asarray(mesh.points), mesh.edges, mesh.edge_mid, rtol=1e-9)


def _bend(mesh: Mesh, alpha: float) -> Mesh:
    """Every interior edge node moved off the midpoint by α (x₁ − x₀)×e₃, alternating sides."""
    pts = np.array(mesh.points)
    e = _interior(mesh)
    x0, x1 = pts[mesh.edges[e, 0]], pts[mesh.edges[e, 1]]
    sign = np.where(np.arange(len(e)) % 2 == 0, 1.0, -1.0)
    pts[mesh.edge_mid[e]] = 0.5 * (x0 + x1) + (alpha * sign)[:, None] * bisector_normal(x0, x1)
    return Mesh(pts, mesh.triangles, mesh.box)


def test_bent_edges_of_a_constant_metric_come_back_straight_at_the_exact_length():
    fld = load_metric_text(CONSTANT)
    g = fld.tensor(np.array([[0.5, 0.5]]))[0]
    bent = _bend(_grid(fld, 6, shake=0.15), 0.08)
    assert valid_exact(bent.points[bent.triangles]).all()
    res = recurve(fld, bent)
    out = res.mesh
    e = _interior(out)
    assert res.moved == len(e)
    pts = out.points
    x0, x1, xm = pts[out.edges[e, 0]], pts[out.edges[e, 1]], pts[out.edge_mid[e]]
    # the geodesics of a constant metric are straight: the shortest parabola is the segment
    h = np.hypot(*(x1 - x0).T)
    assert np.hypot(*(xm - 0.5 * (x0 + x1)).T).max() < 2e-4 * h.max()
    # and its length is sqrt(Δᵀ g Δ)
    d = x1 - x0
    exact = np.sqrt(np.einsum("ei,ij,ej->e", d, g, d))
    np.testing.assert_allclose(_lengths(fld, out)[e], exact, rtol=1e-7)
    slow_check(out)


def _shortest_alpha(g, x0: np.ndarray, x1: np.ndarray) -> float:
    """α of the shortest parabola through x0, x1 (scipy quad and a bounded Brent search)."""
    n = np.array([x1[1] - x0[1], x0[0] - x1[0]])
    s = 0.5 * (x0 + x1)

    def length(alpha: float) -> float:
        xm = s + alpha * n

        def speed(t: float) -> float:
            p = (1 - t) * (1 - 2 * t) * x0 + t * (2 * t - 1) * x1 + 4 * t * (1 - t) * xm
            v = (4 * t - 3) * x0 + (4 * t - 1) * x1 + (4 - 8 * t) * xm
            return float(np.sqrt(v @ g(p) @ v))

        return quad(speed, 0, 1, epsabs=1e-13, epsrel=1e-12)[0]

    return minimize_scalar(length, bounds=(-0.5, 0.5), options={"xatol": 1e-9}).x


def test_straight_edges_of_the_half_plane_go_to_their_shortest_parabolas():
    fld = load_metric_text(HALF_PLANE)
    straight = _grid(fld, 6, shake=0.1)
    # edges of 0.3 to 0.8: no length floor, so that every edge may reach its optimum
    res = recurve(fld, straight, min_length=0.0)
    out = res.mesh
    slow_check(out)
    e = _interior(out)
    pts = out.points
    x0, x1, xm = pts[out.edges[e, 0]], pts[out.edges[e, 1]], pts[out.edge_mid[e]]
    moved = np.hypot(*(xm - 0.5 * (x0 + x1)).T) > 0
    at_optimum = 0
    for i in np.flatnonzero(moved):
        alpha = _shortest_alpha(lambda p: np.eye(2) / p[1] ** 2, x0[i], x1[i])
        offset = alpha * bisector_normal(x0[i : i + 1], x1[i : i + 1])[0]
        # the node is at one of the fractions of the optimal offset; the search stops
        # at α within 1e-4, so the node is within 1e-4 |Δ| of that point
        s = FRACTIONS[
            np.argmin([np.hypot(*(xm[i] - 0.5 * (x0[i] + x1[i]) - f * offset)) for f in FRACTIONS])
        ]
        want = 0.5 * (x0[i] + x1[i]) + s * offset
        assert np.hypot(*(xm[i] - want)) < 1.5e-4 * np.hypot(*(x1[i] - x0[i]))
        at_optimum += s == 1.0
    # a coarse, valid grid: nearly every edge can go all the way
    assert at_optimum >= 0.85 * len(e)
    # the parabola is longer than the geodesic (a circle), shorter than the segment
    before, after = _lengths(fld, straight)[e], _lengths(fld, out)[e]
    dy2 = ((x1 - x0) ** 2).sum(axis=1)
    geodesic = np.arccosh(1 + dy2 / (2 * x0[:, 1] * x1[:, 1]))
    assert (after >= geodesic * (1 - 1e-9)).all()
    assert (after[moved] < before[moved]).all()
    np.testing.assert_allclose(after, geodesic, rtol=2e-3)


@pytest.fixture(scope="module")
def front_case():
    """A curved mesh of a sharp front (curving backtracks three edges), and the same
    with its nodes forced back to straight."""
    fld = load_metric_text(FRONT)
    curved = pipeline.curve(fld, _p1_grid(fld, 9, shake=0.2))
    straight = to_p2_straight(curved)
    return fld, curved, straight, recurve(fld, straight)


def test_recurving_never_makes_an_edge_longer_nor_a_triangle_invalid(front_case):
    fld, _, straight, res = front_case
    slow_check(res.mesh)
    before, after = _lengths(fld, straight), _lengths(fld, res.mesh)
    assert (after <= before * (1 + 1e-9)).all()
    assert after.sum() < before.sum() * (1 - 1e-3)
    # the corners and the box-side nodes stay where they were
    fixed = np.ones(len(straight.points), dtype=bool)
    fixed[straight.edge_mid[_interior(straight)]] = False
    np.testing.assert_array_equal(res.mesh.points[fixed], straight.points[fixed])
    np.testing.assert_array_equal(res.mesh.triangles, straight.triangles)


def test_recurving_a_curved_mesh_keeps_its_optimal_nodes_and_shortens_the_others(front_case):
    fld, curved, _, _ = front_case
    res = recurve(fld, curved)
    slow_check(res.mesh)
    e = _interior(curved)
    x0, x1 = curved.points[curved.edges[e, 0]], curved.points[curved.edges[e, 1]]
    opt = shortest_parabola(fld, x0, x1, exact_length=False).mid
    before, after = curved.points[curved.edge_mid[e]], res.mesh.points[res.mesh.edge_mid[e]]
    h = np.hypot(*(x1 - x0).T)
    optimal = np.hypot(*(before - opt).T) < 1e-9 * h
    assert 0 < (~optimal).sum() < len(e)  # curving backtracked some edges
    np.testing.assert_array_equal(after[optimal], before[optimal])
    la, lb = _lengths(fld, res.mesh)[e], _lengths(fld, curved)[e]
    assert (la <= lb * (1 + 1e-9)).all()
    assert (la[~optimal] < lb[~optimal] * (1 - 1e-6)).any()


def test_recurving_never_makes_an_edge_shorter_than_the_length_floor(front_case):
    """With the floor at the median straight length, every edge ends at least
    min(floor, its length before); without it (floor 0), some of those edges end below."""
    fld, _, straight, _ = front_case
    before = _lengths(fld, straight)
    floor = float(np.median(before))
    free = _lengths(fld, recurve(fld, straight, min_length=0.0).mesh)
    assert (free < np.minimum(floor, before) * (1 - 1e-6)).any()
    res = recurve(fld, straight, min_length=floor)
    slow_check(res.mesh)
    after = _lengths(fld, res.mesh)
    assert res.moved > 0
    assert (after >= np.minimum(floor, before) * (1 - 1e-6)).all()
    assert (after <= before * (1 + 1e-9)).all()


def _quality(fld, mesh: Mesh) -> np.ndarray:
    lengths = edge_lengths(fld, np.asarray(mesh.points), mesh.edges, mesh.edge_mid)
    return quality_from(metric_areas(fld, mesh.points[mesh.triangles]), lengths[mesh.tri_edges])


def test_every_edge_left_short_of_its_optimum_is_blocked(front_case):
    """The fixed point, checked edge by edge in a plain loop: moving any node that is not
    at its optimum to a larger fraction would make a triangle invalid, the edge no
    shorter, the edge shorter than min(0.7, its length), or the pair's worse quality
    below min(its own, max(0.3, the mesh's worst))."""
    fld, _, _, res = front_case
    out = res.mesh
    assert recurve(fld, out).moved == 0

    pts = np.asarray(out.points)
    e = _interior(out)
    x0, x1 = pts[out.edges[e, 0]], pts[out.edges[e, 1]]
    opt = shortest_parabola(fld, x0, x1, exact_length=False).mid
    q = _quality(fld, out)
    length = _lengths(fld, out)
    blocked = 0
    for i, k in enumerate(e.tolist()):
        node = out.edge_mid[k]
        if np.hypot(*(pts[node] - opt[i])) < 1e-12:
            continue
        blocked += 1
        t1, t2 = out.edge_tris[k]
        floor = min(q[t1], q[t2], max(0.3, q.min()))
        for s in FRACTIONS:
            trial = pts.copy()
            trial[node] = 0.5 * (x0[i] + x1[i]) + s * (opt[i] - 0.5 * (x0[i] + x1[i]))
            m = Mesh(trial, out.triangles, out.box)
            tri = trial[out.triangles[[t1, t2]]]
            if not valid_exact(tri).all():
                continue
            new_length = _lengths(fld, m)[k]
            if new_length >= length[k] * (1 - 1e-6):
                continue
            if new_length < min(0.7, length[k]) * (1 + 1e-6):
                continue
            assert min(_quality(fld, m)[[t1, t2]]) < floor + 1e-3
    assert blocked > 0


def test_recurving_is_deterministic_and_leaves_its_input_alone(front_case):
    fld, _, straight, res = front_case
    copy = np.array(straight.points)
    again = recurve(fld, straight)
    np.testing.assert_array_equal(again.mesh.points, res.mesh.points)
    assert again.moved == res.moved and again.rounds == res.rounds
    np.testing.assert_array_equal(straight.points, copy)


# 1,000:1 about the cubic y = 0.5 + 2.4 (x - 0.5)^3 (bench/robustness u74): on the
# cubic the long size 0.08 lies along it, so the metric length of an arc of the
# cubic is its Euclidean length over 0.08
CUBIC = """
domain: {box: [[0, 0], [1, 1]]}
definitions:
  d: (y - 0.5 - 2.4*(x - 0.5)**3)/sqrt(1 + (7.2*(x - 0.5)**2)**2)
metric:
  eigen:
    sizes: ['min(0.00008 + 0.2*abs(d), 0.08)', 0.08]
    angle: atan2(1, -7.2*(x - 0.5)**2)
"""


def test_a_free_node_follows_a_thin_layer_that_no_symmetric_parabola_follows():
    fld = load_metric_text(CUBIC)
    # two arcs about 1.08 long, mirror images of each other through the inflection
    xa = np.array([0.30, 0.615])
    xb = xa + 0.085

    def cubic(x):
        return np.column_stack([x, 0.5 + 2.4 * (x - 0.5) ** 3])

    a, b = cubic(xa), cubic(xb)
    arc = np.array(
        [
            quad(lambda x: np.sqrt(1 + (7.2 * (x - 0.5) ** 2) ** 2), u, v)[0]
            for u, v in zip(xa, xb, strict=True)
        ]
    )
    arc /= 0.08
    symmetric = shortest_parabola(fld, a, b).length
    assert (symmetric > 2.5 * arc).all()
    # below free_from the paper's node; above it, the free one, within 5 % of the arc
    np.testing.assert_array_equal(
        optimal_nodes(fld, a, b, free_from=np.inf), shortest_parabola(fld, a, b).mid
    )
    free = parabola_length(fld, a, b, optimal_nodes(fld, a, b, free_from=1.4))
    assert (free < 1.05 * arc).all()
    np.testing.assert_allclose(free[0], free[1], rtol=1e-3)  # the mirror images


def test_recurving_the_long_edges_from_their_nodes_moves_only_them(front_case):
    fld, _, straight, _ = front_case
    before = _lengths(fld, straight)
    floor = float(np.quantile(before[_interior(straight)], 0.75))
    out = recurve(fld, straight, longer_than=floor, free_from=floor, from_node=True)
    slow_check(out.mesh)
    after = _lengths(fld, out.mesh)
    assert out.moved > 0
    assert (after <= before * (1 + 1e-9)).all()
    # the edges not longer than the floor keep their nodes (the two-segment rule
    # decides: those within 1e-3 of the floor are left out of the check)
    keep = before < floor * (1 - 1e-3)
    nodes = straight.edge_mid[keep]
    np.testing.assert_array_equal(out.mesh.points[nodes], straight.points[nodes])
    moved = np.flatnonzero(
        np.hypot(*(out.mesh.points[straight.edge_mid] - straight.points[straight.edge_mid]).T) > 0
    )
    assert (before[moved] > floor * (1 - 1e-3)).all()
