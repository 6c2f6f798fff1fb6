"""Edge nodes fitted to a function (curvimesh.fit) and its place in the pipeline."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from curvimesh import adapt as pipeline
from curvimesh.bezier import valid_exact
from curvimesh.cli import main
from curvimesh.fit import fit_nodes
from curvimesh.interpolation import compile_function
from curvimesh.interpolation_error import element_l2_squared, interpolation_error
from curvimesh.io import read_mesh
from curvimesh.mesh import Mesh
from curvimesh.metric import load_metric_text

_SPEC = importlib.util.spec_from_file_location(
    "convergence", Path(__file__).resolve().parents[1] / "bench" / "convergence.py"
)
convergence = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(convergence)

FRONT = "(1 + tanh(30*((y - 0.5) - 0.2*sin(2*pi*x))))/2"
FRONT_YAML = f"""
metric:
  interpolation:
    function: {FRONT}
    vertices: 300
    sizes: [1e-3, 0.5]
"""


def grid_p2(n: int) -> Mesh:
    """Straight P2 mesh of the unit square, n × n squares cut along a diagonal."""
    return convergence.uniform_mesh((n + 1) ** 2)


def bent(mesh: Mesh, amount: float, seed: int = 0) -> Mesh:
    """The mesh with every interior edge node pushed along its chord's normal."""
    pts = np.array(mesh.points)
    inner = np.flatnonzero(mesh.edge_tris[:, 1] >= 0)
    a, b = pts[mesh.edges[inner, 0]], pts[mesh.edges[inner, 1]]
    normal = np.column_stack([-(b - a)[:, 1], (b - a)[:, 0]])
    push = np.random.default_rng(seed).uniform(-amount, amount, len(inner))
    pts[mesh.edge_mid[inner]] += push[:, None] * normal
    out = Mesh(pts, mesh.triangles, mesh.box)
    assert valid_exact(out.points[out.triangles]).all()
    return out


def test_a_quadratic_is_fitted_by_straightening_the_edges():
    # the isoparametric P2 interpolant reproduces a quadratic on straight
    # triangles only (on bent ones f∘x is quartic in ξ): straight edges are the
    # global optimum, error 0. Moving one node at a time, the fit removes at
    # least 99 % of the error (it can stop in a local minimum where bends of
    # neighbouring edges cancel)
    f = compile_function("x**2 + 3*x*y - 2*y**2 + x")
    mesh = bent(grid_p2(6), 0.08)
    before = interpolation_error(f, mesh).l2
    res = fit_nodes(f, mesh)
    after = interpolation_error(f, res.mesh).l2
    assert before > 1e-4
    assert after < 0.01 * before
    assert res.error_before == pytest.approx(before, rel=1e-6)
    assert res.error_after == pytest.approx(after, rel=1e-3)
    assert interpolation_error(f, grid_p2(6)).l2 < 1e-14


def test_fitting_lowers_the_error_and_keeps_the_mesh_valid():
    f = compile_function(FRONT)
    mesh = pipeline.adapt(load_metric_text(FRONT_YAML), pipeline.AdaptOptions(fit=False)).mesh
    res = fit_nodes(f, mesh)
    out = res.mesh
    assert valid_exact(out.points[out.triangles]).all()
    np.testing.assert_array_equal(out.triangles, mesh.triangles)
    # vertices stay where they were, and boundary nodes on their sides
    fixed = mesh.vertex_ids
    np.testing.assert_array_equal(out.points[fixed], np.asarray(mesh.points)[fixed])
    assert_on_sides(out)
    before, after = interpolation_error(f, mesh).l2, interpolation_error(f, out).l2
    assert after < 0.5 * before
    # the error the stage reports is the sum of its local errors
    total = np.sqrt(element_l2_squared(f, np.asarray(out.points)[out.triangles], order=6).sum())
    assert res.error_after == pytest.approx(total, rel=1e-9)
    assert res.error_after <= res.error_before
    again = fit_nodes(f, mesh).mesh
    assert np.asarray(again.points).tobytes() == np.asarray(out.points).tobytes()


def assert_on_sides(mesh: Mesh) -> None:
    """Every boundary node lies on its edge's chord, in its middle half."""
    lines = mesh.boundary_lines
    pts = np.asarray(mesh.points)
    a, b, m = pts[lines[:, 0]], pts[lines[:, 1]], pts[lines[:, 2]]
    ab, am = b - a, m - a
    # on a box side the chord is axis-parallel and the node keeps its coordinate
    # across it exactly
    across = np.where(np.abs(ab[:, 0]) > np.abs(ab[:, 1]), am[:, 1], am[:, 0])
    assert np.all(across == 0.0)
    t = (am * ab).sum(axis=1) / (ab * ab).sum(axis=1)
    assert np.all((t > 0.25) & (t < 0.75))


def test_boundary_nodes_slide_along_their_sides_to_lower_the_error():
    # f varies along the sides y = 0 and y = 1 only through x: on the straight
    # uniform grid the interpolant along those sides improves when their nodes
    # move along them, and they may not leave them
    f = compile_function("tanh(8*(x - 0.3))")
    mesh = grid_p2(5)
    res = fit_nodes(f, mesh)
    out = res.mesh
    assert res.error_after < res.error_before
    side = mesh.edge_mid[mesh.edge_tris[:, 1] < 0]
    pts0, pts1 = np.asarray(mesh.points), np.asarray(out.points)
    moved = side[np.any(pts1[side] != pts0[side], axis=1)]
    assert len(moved) > 0
    assert_on_sides(out)
    assert valid_exact(pts1[out.triangles]).all()


def test_a_mesh_at_rounding_error_is_left_alone():
    f = compile_function("2*x - y + 0.5")  # linear: no element has an error
    mesh = grid_p2(3)
    res = fit_nodes(f, mesh)
    assert res.moves == 0
    np.testing.assert_array_equal(res.mesh.points, mesh.points)


def test_the_function_comes_from_one_interpolation_form_only():
    assert load_metric_text(FRONT_YAML).error_function is not None
    assert load_metric_text("metric: {isotropic: 0.1}\n").error_function is None
    two = """
metric:
  intersection:
    - interpolation: {function: x**3, vertices: 300}
    - interpolation: {function: y**3, vertices: 300}
"""
    assert load_metric_text(two).error_function is None
    f = load_metric_text(FRONT_YAML).error_function
    pts = np.array([[0.2, 0.3], [0.7, 0.9]])
    np.testing.assert_allclose(f(pts), compile_function(FRONT)(pts), rtol=1e-15)


def test_adapt_fits_by_default_and_no_fit_turns_it_off(tmp_path):
    path = tmp_path / "front.yaml"
    path.write_text(FRONT_YAML)
    f = compile_function(FRONT)
    errors = {}
    for flags in ((), ("--no-fit",)):
        out = tmp_path / f"m{len(flags)}.msh"
        r = CliRunner().invoke(main, ["adapt", "--metric", str(path), "-o", str(out), *flags])
        assert r.exit_code == 0, r.output
        errors[flags] = interpolation_error(f, read_mesh(out)).l2
    fld = load_metric_text(FRONT_YAML)
    want = pipeline.adapt(fld, pipeline.AdaptOptions(fit=False)).mesh
    assert errors[("--no-fit",)] == pytest.approx(interpolation_error(f, want).l2, rel=1e-9)
    assert errors[()] < 0.5 * errors[("--no-fit",)]
