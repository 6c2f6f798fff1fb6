"""Tests of curvimesh.plot: the pictures are written (atomically), their geometry is right."""

from __future__ import annotations

import math

import numpy as np
import pytest
import sympy

from curvimesh import plot
from curvimesh.mesh import Mesh, to_p2_straight
from curvimesh.metric import Component, MetricField, Y

PNG = b"\x89PNG\r\n\x1a\n"


def constant_field(g11=16.0, g12=0.0, g22=16.0, box=(0.0, 0.0, 1.0, 1.0)) -> MetricField:
    g = tuple(sympy.Float(v) for v in (g11, g12, g22))
    return MetricField((Component(g, ()),), box=box, name="constant")


def poincare_field() -> MetricField:
    """The Poincaré half-plane, g = I / y²."""
    return MetricField(
        (Component((1 / Y**2, sympy.Integer(0), 1 / Y**2), ()),),
        box=(-2.0, 0.5, 2.0, 4.0),
        name="poincare",
    )


def grid_mesh(cells: int = 4, seed: int = 0, shake: float = 0.02) -> Mesh:
    """A P2 mesh of the unit square, ``cells`` x ``cells`` squares cut in two, interior
    edge nodes moved by up to ``shake`` (well inside the validity limit)."""
    n = cells + 1
    gx, gy = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    tris = []
    for j in range(cells):
        for i in range(cells):
            a, b, c, d = j * n + i, j * n + i + 1, (j + 1) * n + i + 1, (j + 1) * n + i
            tris += [[a, b, c], [a, c, d]]
    p2 = to_p2_straight(Mesh(pts, tris, box=(0, 0, 1, 1)))
    moved = np.array(p2.points)
    inner = np.setdiff1d(p2.edge_mid, p2.edge_mid[p2.boundary_edges])
    rng = np.random.default_rng(seed)
    moved[inner] += rng.uniform(-shake, shake, size=(len(inner), 2))
    return Mesh(moved, p2.triangles, p2.box)


# --------------------------------------------------------------------------- geometry


def test_curved_edge_polylines_lie_on_the_parabola():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(30, 2))
    edges = np.arange(20).reshape(10, 2)
    mids = np.arange(20, 30)
    samples = 9
    lines = plot.curved_edge_polylines(pts, edges, mids, samples)
    assert lines.shape == (10, samples, 2)
    x0, x1, xm = pts[edges[:, 0]], pts[edges[:, 1]], pts[mids]
    # t = 0, 1/2, 1 hit the three nodes exactly.
    assert np.array_equal(lines[:, 0], x0)
    assert np.array_equal(lines[:, samples // 2], xm)
    assert np.array_equal(lines[:, -1], x1)
    for k, t in enumerate(np.linspace(0, 1, samples)):
        expected = (1 - t) * (1 - 2 * t) * x0 + t * (2 * t - 1) * x1 + 4 * t * (1 - t) * xm
        np.testing.assert_allclose(lines[:, k], expected, rtol=0, atol=1e-14)


def test_curved_edge_polylines_straight_without_mids():
    pts = np.array([[0.0, 0.0], [3.0, 1.0], [9.0, 9.0]])
    straight = np.linspace(pts[0], pts[1], 7)
    for mids in (None, [-1]):
        lines = plot.curved_edge_polylines(pts, [[0, 1]], mids, 7)
        np.testing.assert_allclose(lines[0], straight, rtol=0, atol=1e-14)


def test_triangle_polygons_follow_the_edges():
    mesh = grid_mesh()
    nodes = np.asarray(mesh.points)[mesh.triangles]
    s = 5
    polys = plot.curved_triangle_polygons(nodes, s)
    assert polys.shape == (len(nodes), 3 * (s - 1), 2)
    # The polygon of triangle t starts at corner 0 and passes corners 1, 2 and
    # the edge nodes at the middles of its three sides.
    for k, node in enumerate([0, 1, 2]):
        np.testing.assert_array_equal(polys[:, k * (s - 1)], nodes[:, node])
    for k, node in enumerate([3, 4, 5]):
        np.testing.assert_allclose(polys[:, k * (s - 1) + (s - 1) // 2], nodes[:, node], atol=1e-15)


def test_touching_window_against_a_slow_check():
    mesh = grid_mesh(cells=8, shake=0.01)
    nodes = np.asarray(mesh.points)[mesh.triangles]
    window = (0.3, 0.55, 0.62, 0.7)
    got = plot.touching_window(nodes, window)
    dense = plot.curved_triangle_polygons(nodes, 101)
    x0, y0, x1, y1 = window
    for t in range(len(nodes)):
        inside = (
            (dense[t, :, 0] >= x0) & (dense[t, :, 0] <= x1)
            & (dense[t, :, 1] >= y0) & (dense[t, :, 1] <= y1)
        )  # fmt: skip
        if inside.any():  # a boundary point in the window: never missed
            assert got[t]
        lo, hi = dense[t].min(axis=0), dense[t].max(axis=0)
        if hi[0] < x0 - 0.05 or lo[0] > x1 + 0.05 or hi[1] < y0 - 0.05 or lo[1] > y1 + 0.05:
            assert not got[t]  # far away: left out


def test_unit_circle_of_a_constant_metric_is_the_ellipse():
    field = constant_field(30.0, 12.0, 9.0, box=(-1, -1, 1, 1))
    g = field.tensor(np.zeros((1, 2)))[0]
    c = np.array([0.1, -0.2])
    pts = plot.unit_circle(field, c, 37)
    assert pts.shape == (37, 2)
    d = pts - c
    np.testing.assert_allclose(np.einsum("pi,ij,pj->p", d, g, d), 1.0, rtol=0, atol=1e-8)
    ell = plot.tangent_ellipse(field, c, 50) - c
    np.testing.assert_allclose(np.einsum("pi,ij,pj->p", ell, g, ell), 1.0, rtol=0, atol=1e-12)


def test_unit_circle_in_the_poincare_half_plane():
    # The hyperbolic circle of radius 1 about (0, 1) is the Euclidean circle
    # of centre (0, cosh 1) and radius sinh 1.
    pts = plot.unit_circle(poincare_field(), [0.0, 1.0], 61)
    assert np.isfinite(pts).all()
    r = np.hypot(pts[:, 0], pts[:, 1] - math.cosh(1.0))
    np.testing.assert_allclose(r, math.sinh(1.0), rtol=0, atol=1e-6)


def test_principal_geodesics():
    field = constant_field(100.0, 0.0, 4.0, box=(-1, -1, 1, 1))
    c = np.array([0.2, 0.3])
    curves = plot.principal_geodesics(field, c, pieces=4)
    assert curves.shape == (4, 5, 2)
    # Straight lines: +-v1 along y (eigenvalue 4), +-v2 along x (eigenvalue 100).
    ends = np.abs(curves[:, -1] - c)
    np.testing.assert_allclose(ends, [[0, 0.5], [0, 0.5], [0.1, 0], [0.1, 0]], atol=1e-12)
    np.testing.assert_allclose(np.abs(curves[2, :, 0] - c[0]), np.linspace(0, 0.1, 5), atol=1e-12)
    # In the half-plane, the geodesics through (0, 1) along x are arcs of the
    # unit circle about the origin, ending at y = 1 / cosh 1 (∫ dφ / sin φ = 1 from
    # φ = π/2); along y they stay on x = 0, ending at y = e^{±1}.
    curves = plot.principal_geodesics(poincare_field(), [0.0, 1.0])
    for row in curves:
        if abs(row[-1, 0]) > 1e-9:
            np.testing.assert_allclose(np.hypot(*row.T), 1.0, atol=1e-8)
        else:
            np.testing.assert_allclose(row[:, 0], 0.0, atol=1e-12)
    np.testing.assert_allclose(
        sorted(curves[:, -1, 1]),
        sorted([math.exp(-1), math.exp(1), 1 / math.cosh(1), 1 / math.cosh(1)]),
    )


# --------------------------------------------------------------------------- pictures


def test_plot_mesh_report_writes_a_png(tmp_path):
    out = tmp_path / "mesh.png"
    plot.plot_mesh_report(constant_field(), grid_mesh(), out, title="grid")
    data = out.read_bytes()
    assert data.startswith(PNG) and len(data) > 1000
    assert [p.name for p in tmp_path.iterdir()] == ["mesh.png"]


def test_plot_mesh_report_window_and_p1(tmp_path):
    mesh = grid_mesh()
    out = tmp_path / "zoom.png"
    plot.plot_mesh_report(constant_field(), mesh, out, window=(0.2, 0.2, 0.6, 0.5))
    assert out.read_bytes().startswith(PNG)
    empty = tmp_path / "empty.png"  # a window with no triangle in it still draws
    plot.plot_mesh_report(constant_field(), mesh, empty, window=(5, 5, 6, 6))
    assert empty.read_bytes().startswith(PNG)
    with pytest.raises(ValueError, match="window"):
        plot.plot_mesh_report(constant_field(), mesh, tmp_path / "bad.png", window=(1, 0, 0, 1))
    p1 = Mesh(mesh.points[mesh.vertex_ids], np.searchsorted(mesh.vertex_ids, mesh.corners))
    plot.plot_mesh_report(constant_field(), p1, tmp_path / "p1.png")
    assert (tmp_path / "p1.png").read_bytes().startswith(PNG)
    assert not (tmp_path / "bad.png").exists()


def test_plot_mesh_report_format_and_given_measures(tmp_path):
    mesh = grid_mesh()
    lengths = np.linspace(0.5, 1.6, len(mesh.edges))
    qualities = np.linspace(0.2, 1.1, len(mesh.triangles))
    out = tmp_path / "mesh.pdf"
    plot.plot_mesh_report(constant_field(), mesh, out, lengths=lengths, qualities=qualities)
    assert out.read_bytes().startswith(b"%PDF")
    with pytest.raises(ValueError, match="lengths"):
        plot.plot_mesh_report(constant_field(), mesh, tmp_path / "x.png", lengths=lengths[1:])
    with pytest.raises(ValueError, match="qualities"):
        plot.plot_mesh_report(constant_field(), mesh, tmp_path / "x.png", qualities=[1.0])
    assert not (tmp_path / "x.png").exists()


def test_failed_plot_leaves_no_file(tmp_path, monkeypatch):
    from matplotlib.figure import Figure

    def broken_savefig(self, fname, **kwargs):
        with open(fname, "wb") as handle:
            handle.write(PNG)  # half a file, then a failure
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(Figure, "savefig", broken_savefig)
    out = tmp_path / "mesh.png"
    with pytest.raises(RuntimeError, match="disk on fire"):
        plot.plot_mesh_report(constant_field(), grid_mesh(), out)
    with pytest.raises(RuntimeError, match="disk on fire"):
        plot.plot_circles(constant_field(), [[0.5, 0.5]], tmp_path / "circles.png")
    assert list(tmp_path.iterdir()) == []
    old = tmp_path / "old.png"
    old.write_bytes(b"previous")
    with pytest.raises(RuntimeError):
        plot.plot_mesh_report(constant_field(), grid_mesh(), old)
    assert old.read_bytes() == b"previous"
    assert [p.name for p in tmp_path.iterdir()] == ["old.png"]


def test_plot_circles_writes_a_png(tmp_path):
    out = tmp_path / "circles.png"
    plot.plot_circles(
        constant_field(box=(0, 0, 1, 1)), [[0.5, 0.5], [0.2, 0.7]], out, directions=31
    )
    data = out.read_bytes()
    assert data.startswith(PNG) and len(data) > 1000
    half = tmp_path / "poincare.png"
    plot.plot_circles(poincare_field(), [[0.0, 1.0], [1.0, 2.5]], half, directions=31)
    assert half.read_bytes().startswith(PNG)


def test_plotting_never_imports_pyplot(tmp_path):
    import subprocess
    import sys

    code = (
        "import sys, sympy\n"
        "from curvimesh import plot\n"
        "from curvimesh.metric import Component, MetricField\n"
        "assert 'matplotlib' not in sys.modules\n"
        "one, zero = sympy.Integer(1), sympy.Integer(0)\n"
        "f = MetricField((Component((one, zero, one)),))\n"
        "plot.plot_circles(f, [[0.5, 0.5]], sys.argv[1], directions=9)\n"
        "assert 'matplotlib.pyplot' not in sys.modules\n"
    )
    out = tmp_path / "c.png"
    subprocess.run([sys.executable, "-c", code, str(out)], check=True)
    assert out.read_bytes().startswith(PNG)
