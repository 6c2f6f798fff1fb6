"""Vertex relocation (curvimesh.smooth): calibrated chords, safe moves, the blocks."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from curvimesh import adapt as pipeline
from curvimesh.mesh import Mesh, signed_areas
from curvimesh.metric import load_metric_text
from curvimesh.smooth import (
    _chord_lengths,
    _on_box,
    _safe_move,
    _spring_steps,
    edge_parabola_lengths,
    relocate,
)
from curvimesh.triangulate import delaunay, metric_delaunay

#: Sizes 0.08 across, 0.2 along the direction at angle 0.5: straight geodesics.
CONSTANT = """
domain: {box: [[0, 0], [2, 1]]}
metric:
  eigen: {sizes: [0.08, 0.2], angle: 0.5}
"""
#: Unit edges are 0.1 long: the equilateral lattice of spacing 0.1 is the unit mesh.
ISOTROPIC = "domain: {box: [[0, 0], [1.2, 1.2]]}\nmetric: {isotropic: 0.1}\n"


def lattice(rows: int = 12, cols: int = 12) -> np.ndarray:
    """Points of the equilateral lattice of spacing 0.1, rows offset by half a spacing;
    the bottom row on y = 0."""
    i, j = np.meshgrid(np.arange(cols), np.arange(rows), indexing="ij")
    x = 0.1 * (i + 0.5 * (j % 2)) + 0.05
    y = 0.1 * np.sqrt(3) / 2 * j
    return np.column_stack([x.ravel(), y.ravel()])


def spread(fld, mesh: Mesh, inner: bool = False) -> float:
    """Standard deviation of log L over the edges (0 for a unit mesh); with ``inner``,
    over the edges off the boundary vertices."""
    e = mesh.edges
    if inner:
        e = e[~mesh.boundary_vertices[e].any(axis=1)]
    length, _ = edge_parabola_lengths(fld, np.asarray(mesh.points), e)
    return float(np.log(length).std())


def test_relocation_brings_a_jittered_unit_lattice_back_towards_unit_edges():
    fld = load_metric_text(ISOTROPIC)
    pts = lattice()
    fixed = _on_box(pts, fld.box)  # the bottom row
    assert 0 < fixed.sum() < len(pts)
    rng = np.random.default_rng(11)
    jittered = pts + np.where(fixed[:, None], 0.0, rng.normal(scale=0.012, size=pts.shape))
    mesh = metric_delaunay(fld, delaunay(jittered, box=fld.box))
    # the hull's edges across the notches of the lattice's sides (√3 long) stay
    before = spread(fld, mesh, inner=True)
    out = relocate(fld, mesh)
    after = spread(fld, out, inner=True)
    assert before > 0.1
    assert after < 0.6 * before
    new = np.asarray(out.points)
    assert np.array_equal(new[fixed], jittered[fixed])  # the box side stays
    assert (signed_areas(new, out.corners) > 0).all()
    assert np.array_equal(out.corners, relocate(fld, mesh).corners)


def test_relocation_evens_out_a_sampled_mesh_and_is_deterministic():
    fld = load_metric_text(CONSTANT)
    cloud = pipeline.sample(fld)
    mesh = metric_delaunay(fld, delaunay(np.asarray(cloud.points), box=fld.box))
    out = relocate(fld, mesh)
    again = relocate(fld, mesh)
    assert np.asarray(out.points).tobytes() == np.asarray(again.points).tobytes()
    assert np.asarray(out.corners).tobytes() == np.asarray(again.corners).tobytes()
    assert spread(fld, out) < 0.8 * spread(fld, mesh)
    pts = np.asarray(out.points)
    assert (signed_areas(pts, out.corners) > 0).all()
    length, _ = edge_parabola_lengths(fld, pts, out.edges)
    assert length.min() >= 0.7
    box = _on_box(np.asarray(mesh.points), fld.box)
    assert np.array_equal(pts[box], np.asarray(mesh.points)[box])


def test_one_block_is_what_a_tolerance_of_one_stops_at():
    # the blocks stop as soon as one lowers the spread by less than tol: with tol = 1
    # (no block lowers it by 100 %) the first block is the last
    fld = load_metric_text(CONSTANT)
    cloud = pipeline.sample(fld)
    mesh = metric_delaunay(fld, delaunay(np.asarray(cloud.points), box=fld.box))
    a, b = relocate(fld, mesh, tol=1.0), relocate(fld, mesh, blocks=1)
    assert np.array_equal(a.points, b.points) and np.array_equal(a.corners, b.corners)
    assert not np.array_equal(a.points, relocate(fld, mesh).points)


@settings(max_examples=25, deadline=None)
@given(
    h1=st.floats(0.02, 0.3),
    ratio=st.floats(1.0, 20.0),
    angle=st.floats(0.0, np.pi),
    seed=st.integers(0, 2**16),
)
def test_in_a_constant_metric_the_chord_is_the_parabola(h1, ratio, angle, seed):
    # straight geodesics: the shortest parabola is the chord, of length sqrt(dᵀ g d)
    # with g the same everywhere, so the calibration factors are 1
    fld = load_metric_text(
        f"domain: {{box: [[0, 0], [1, 1]]}}\n"
        f"metric: {{eigen: {{sizes: [{h1!r}, {h1 * ratio!r}], angle: {angle!r}}}}}\n"
    )
    rng = np.random.default_rng(seed)
    pts = rng.uniform(0, 1, (40, 2))
    e = np.column_stack([np.arange(20), np.arange(20, 40)])
    chord, dx, dy = _chord_lengths(fld, pts[:, 0], pts[:, 1], e[:, 0], e[:, 1])
    g = fld.tensor(pts[:1])[0]
    d = pts[e[:, 0]] - pts[e[:, 1]]
    np.testing.assert_allclose(chord, np.sqrt(np.einsum("ki,ij,kj->k", d, g, d)), rtol=1e-12)
    np.testing.assert_array_equal(np.column_stack([dx, dy]), d)
    length, _ = edge_parabola_lengths(fld, pts, e)
    np.testing.assert_allclose(length, chord, rtol=1e-6)


def test_unit_edges_pull_nothing_and_a_long_edge_pulls_its_ends_together():
    # t − p_a = −d (1 − 1/L): zero at L = 1; for L = 2 each end goes half-way to unit
    length = np.array([1.0, 1.0, 2.0])
    dx, dy = np.array([1.0, 0.0, 2.0]), np.array([0.0, 1.0, 0.0])
    ab = np.array([0, 0, 1, 1, 2, 3])  # edges 0–1, 0–2, 1–3
    sx, sy, w = _spring_steps(length, dx, dy, ab, 4, 4.0)
    assert sx[0] == 0 and sy[0] == 0 and sy[2] == 0
    # edge 1–3: d = p_1 − p_3 = (2, 0), w = 2⁴, pull on 1: −w d (1 − 1/2) = (−16, 0)
    assert sx[1] == -16.0 and sx[3] == 16.0 and w[3] == 16.0 and w[1] == 17.0


@lru_cache(maxsize=1)
def sampled_mesh() -> Mesh:
    """The metric Delaunay triangulation of the sampled points of CONSTANT."""
    fld = load_metric_text(CONSTANT)
    cloud = pipeline.sample(fld)
    return metric_delaunay(fld, delaunay(np.asarray(cloud.points), box=fld.box))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**16), scale=st.floats(0.001, 0.05))
def test_safe_moves_invert_nothing_and_make_no_edge_short_or_long(seed, scale):
    fld = load_metric_text(CONSTANT)
    mesh = sampled_mesh()
    pts = np.asarray(mesh.points)
    e = mesh.edges
    a, b = e[:, 0], e[:, 1]
    x, y = pts[:, 0].copy(), pts[:, 1].copy()
    chord, _, _ = _chord_lengths(fld, x, y, a, b)
    cal = np.ones(len(e))  # a constant metric: the chords are the lengths
    move = np.random.default_rng(seed).normal(scale=scale, size=pts.shape)
    nx, ny, length, dx, dy = _safe_move(
        fld, x.copy(), y.copy(), move[:, 0], move[:, 1], a, b, mesh.corners, cal, chord, 0.7, 1.4
    )
    new = np.column_stack([nx, ny])
    went = np.all(new == pts + move, axis=1)
    assert np.all(went | np.all(new == pts, axis=1))  # each vertex moved fully or stayed
    assert (signed_areas(new, mesh.corners) > 0).all()
    exact = _chord_lengths(fld, nx, ny, a, b)[0]
    np.testing.assert_allclose(length, exact, rtol=1e-12)
    assert np.all((exact >= 0.7) | (exact >= chord))
    assert np.all((exact <= 0.98 * 1.4) | (exact <= chord))
    np.testing.assert_array_equal(np.column_stack([dx, dy]), new[a] - new[b])
    if scale <= 0.002:
        assert went.mean() > 0.5  # moves of a few hundredths of an edge mostly pass
