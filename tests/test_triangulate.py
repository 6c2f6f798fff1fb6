"""Euclidean Delaunay triangulations: canonical order, the compiled Bowyer–Watson and
local insertion against Qhull from scratch, and the certificate's predicates against
plain loops."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from curvimesh import kernels, triangulate
from curvimesh.fill import fill_gaps
from curvimesh.mesh import Mesh, apply_flips, flip_candidates, independent_flips, is_conforming
from curvimesh.metric import load_metric
from curvimesh.triangulate import (
    canonical_triangles,
    delaunay,
    delaunay_insert,
    metric_delaunay,
    metric_delaunay_of,
    strictly_delaunay,
)

METRICS = Path(__file__).resolve().parent.parent / "metrics"
BOX = (0.0, 0.0, 2.0, 1.0)


def cloud(rng: np.random.Generator, n: int, per_side: int) -> np.ndarray:
    """The corners of BOX, ``per_side`` points drawn on each side (each side its own
    draws, as the sampler spaces each side by its own metric) and n inner points."""
    x0, y0, x1, y1 = BOX
    corners = [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]
    s = rng.uniform(0.0, 1.0, (4, per_side))
    sides = [
        np.column_stack([x0 + s[0] * (x1 - x0), np.full(per_side, y0)]),
        np.column_stack([x0 + s[1] * (x1 - x0), np.full(per_side, y1)]),
        np.column_stack([np.full(per_side, x0), y0 + s[2] * (y1 - y0)]),
        np.column_stack([np.full(per_side, x1), y0 + s[3] * (y1 - y0)]),
    ]
    inner = rng.uniform((x0, y0), (x1, y1), (n, 2))
    return np.concatenate([corners, *sides, inner])


def near_boundary(rng: np.random.Generator, k: int) -> np.ndarray:
    """k inner points within 1e-7 to 1e-2 of a side of BOX."""
    x0, y0, x1, y1 = BOX
    p = rng.uniform((x0, y0), (x1, y1), (k, 2))
    gap = 10.0 ** rng.uniform(-7, -2, k)
    side = rng.integers(0, 4, k)
    p[side == 0, 1] = y0 + gap[side == 0]
    p[side == 1, 1] = y1 - gap[side == 1]
    p[side == 2, 0] = x0 + gap[side == 2]
    p[side == 3, 0] = x1 - gap[side == 3]
    return p


def slow_in_circle(p: np.ndarray, a: int, b: int, c: int, q: np.ndarray) -> float:
    """The 3 × 3 in-circle determinant of q against CCW (a, b, c), by numpy's det."""
    rows = [[*(p[i] - q), float((p[i] - q) @ (p[i] - q))] for i in (a, b, c)]
    return float(np.linalg.det(np.array(rows)))


def test_canonical_order_is_independent_of_how_the_triangles_are_listed():
    rng = np.random.default_rng(1)
    mesh = delaunay(cloud(rng, 300, 10))
    tris = np.array(mesh.triangles)
    rolled = np.array(
        [np.roll(t, -r) for t, r in zip(tris, rng.integers(0, 3, len(tris)), strict=True)]
    )
    shuffled = rolled[rng.permutation(len(tris))]
    assert not np.array_equal(shuffled, tris)
    np.testing.assert_array_equal(canonical_triangles(shuffled), tris)
    assert (tris[:, 0] < tris[:, 1:].min(axis=1)).all()
    assert (np.diff(tris[:, 0]) >= 0).all()
    assert (triangulate.signed_areas(mesh.points, tris) > 0).all()


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(0, 3000),
    per_side=st.integers(0, 40),
    k=st.integers(1, 400),
    edge=st.integers(0, 30),
    mid=st.integers(0, 10),
)
def test_insertion_is_qhull_from_scratch_bit_for_bit(seed, n, per_side, k, edge, mid):
    rng = np.random.default_rng(seed)
    old = cloud(rng, n, per_side)
    mesh = delaunay(old, box=BOX)
    # delaunay itself: the compiled insertion where it is certified, Qhull where not,
    # the same array as Qhull's
    np.testing.assert_array_equal(
        mesh.triangles, canonical_triangles(triangulate._qhull_triangles(old))
    )
    assert mesh.box == BOX
    # and midpoints of edges, as gap filling offers in a constant metric: on the edge
    # up to rounding, so that no walk can decide its side
    inner = mesh.edges[~mesh.boundary_vertices[mesh.edges].all(axis=1)]
    halves = old[inner[rng.permutation(len(inner))[:mid]]].mean(axis=1)
    new = np.concatenate([rng.uniform(BOX[:2], BOX[2:], (k, 2)), near_boundary(rng, edge), halves])
    got = delaunay_insert(mesh, new)
    want = delaunay(np.concatenate([old, new]), box=BOX)
    np.testing.assert_array_equal(
        want.triangles, canonical_triangles(triangulate._qhull_triangles(want.points))
    )
    # random doubles, sides drawn apart: no four points co-circular, no new point
    # closer to a circumcircle or another point than the error bound; certified
    assert got is not None
    np.testing.assert_array_equal(got.points, want.points)
    np.testing.assert_array_equal(got.triangles, want.triangles)
    assert got.box == want.box


def test_insertion_in_rounds_stays_the_triangulation_from_scratch():
    rng = np.random.default_rng(7)
    pts = cloud(rng, 2000, 30)
    mesh = delaunay(pts)
    for k in (500, 40, 3, 1):
        pts = np.concatenate([pts, rng.uniform(BOX[:2], BOX[2:], (k, 2))])
        mesh = delaunay_insert(mesh, pts[len(mesh.points) :])
        assert mesh is not None
        np.testing.assert_array_equal(mesh.triangles, delaunay(pts).triangles)


def lattice(m: int) -> np.ndarray:
    gx, gy = np.meshgrid(np.linspace(BOX[0], BOX[2], 2 * m + 1), np.linspace(BOX[1], BOX[3], m + 1))
    return np.column_stack([gx.ravel(), gy.ravel()])


def test_insertion_into_a_lattice_is_not_certified():
    # every cell of the lattice is a co-circular quad: Qhull picks its diagonals
    # by round-off, which a local update cannot promise to repeat
    pts = lattice(8)
    new = np.random.default_rng(3).uniform(BOX[:2], BOX[2:], (5, 2))
    assert delaunay_insert(delaunay(pts), new) is None


def test_bowyer_watson_gives_the_delaunay_triangulation_of_a_cloud():
    rng = np.random.default_rng(11)
    pts = cloud(rng, 3000, 25)
    tris, status = kernels.bowyer_watson(pts, np.arange(len(pts)), kernels.ENCLOSING_SCALE)
    assert status == 0
    mesh = Mesh(pts, canonical_triangles(tris))
    assert triangulate._certified(mesh)  # so delaunay takes it, not Qhull's
    # every circumcircle empty of the other points (plain loops on a sample)
    for tri in mesh.corners[rng.permutation(len(tris))[:40]].tolist():
        others = np.setdiff1d(np.arange(len(pts)), tri)
        assert max(slow_in_circle(pts, *tri, pts[j]) for j in others) < 0
    # Euler's formula with 4 + 100 hull points: T = 2N − h − 2
    assert len(tris) == 2 * len(pts) - (4 + 4 * 25) - 2


def test_bowyer_watson_leaves_a_lattice_to_qhull():
    # co-circular cells: the insertion cannot pick Qhull's diagonals; not certified,
    # delaunay falls back to Qhull's
    pts = lattice(6)
    tris, status = kernels.bowyer_watson(pts, np.arange(len(pts)), kernels.ENCLOSING_SCALE)
    assert status != 0 or not triangulate._certified(Mesh(pts, canonical_triangles(tris)))
    np.testing.assert_array_equal(
        delaunay(pts).triangles, canonical_triangles(triangulate._qhull_triangles(pts))
    )


def test_insertion_refuses_points_outside_duplicated_or_on_circumcircles():
    rng = np.random.default_rng(4)
    pts = cloud(rng, 200, 5)
    mesh = delaunay(pts)
    assert delaunay_insert(mesh, np.array([[2.5, 0.5]])) is None  # outside the hull
    assert delaunay_insert(mesh, pts[50:51]) is None  # a vertex again
    # on the circumcircle of the triangle nearest the middle, beyond its edge 01: inside
    # the circumcircle of the neighbour there, so the search meets the tie
    t = int(np.argmin(np.linalg.norm(pts[mesh.corners].mean(axis=1) - [1.0, 0.5], axis=1)))
    a, b, c = pts[mesh.corners[t]]
    centre = np.linalg.solve(2 * np.array([b - a, c - a]), [b @ b - a @ a, c @ c - a @ a])
    out = 0.5 * (a + b) - centre
    on_circle = centre + np.linalg.norm(a - centre) * out / np.linalg.norm(out)
    assert delaunay_insert(mesh, on_circle[None]) is None
    assert delaunay_insert(mesh, on_circle[None] + 1e-3 * out) is not None
    assert delaunay_insert(mesh, np.zeros((0, 2))) is mesh


def test_conflicts_are_the_triangles_whose_circumcircle_holds_a_new_point():
    rng = np.random.default_rng(5)
    mesh = delaunay(cloud(rng, 400, 8))
    p, corners = mesh.points, np.ascontiguousarray(mesh.corners)
    q = rng.uniform(BOX[:2], BOX[2:], (30, 2))
    got = np.zeros(len(corners), dtype=bool)
    assert kernels.delaunay_conflicts(p, corners, mesh.neighbours, q, got) == 0
    want = [any(slow_in_circle(p, *tri, point) > 0 for point in q) for tri in corners.tolist()]
    assert got.tolist() == want
    assert 30 < got.sum() < len(corners)


def test_strict_local_delaunay_as_a_plain_loop_judges_it():
    rng = np.random.default_rng(8)
    for mesh in (delaunay(cloud(rng, 300, 6)), delaunay(lattice(4))):
        p = mesh.points
        want = []
        for i, (t1, t2) in enumerate(mesh.edge_tris.tolist()):
            if t2 < 0:
                want.append(True)
                continue
            d = (set(mesh.corners[t2].tolist()) - set(mesh.edges[i].tolist())).pop()
            det = slow_in_circle(p, *mesh.corners[t1], p[d])
            scale = np.abs(p[mesh.corners[t1]] - p[d]).max() ** 4
            want.append(det < -1e-9 * scale)  # clear of the kernel's bound either way
        got = strictly_delaunay(mesh)
        assert got.tolist() == want
    assert not got.all()  # the lattice's diagonals are co-circular


@pytest.fixture(scope="module")
def three_toys():
    return load_metric(METRICS / "three_toys.yaml")


@pytest.fixture
def insertions(monkeypatch):
    """Whether each :func:`delaunay_insert` call of the test was certified, in order."""
    seen = []

    def spy(mesh, new):
        out = delaunay_insert(mesh, new)
        seen.append(out is not None)
        return out

    monkeypatch.setattr(triangulate, "delaunay_insert", spy)
    return seen


def test_metric_delaunay_of_inserts_and_equals_a_fresh_triangulation(three_toys, insertions):
    fld, seen = three_toys, insertions
    x0, y0, x1, y1 = fld.box
    rng = np.random.default_rng(9)
    pts = np.concatenate(
        [[[x0, y0], [x1, y0], [x1, y1], [x0, y1]], rng.uniform((x0, y0), (x1, y1), (3000, 2))]
    )
    metric_delaunay_of(fld, pts[:2500], fld.box)
    for stop in (2900, 3004):
        got = metric_delaunay_of(fld, pts[:stop], fld.box)
        want = metric_delaunay(fld, delaunay(pts[:stop], box=fld.box))
        np.testing.assert_array_equal(got.triangles, want.triangles)
        np.testing.assert_array_equal(got.points, pts[:stop])
    assert seen == [True, True]
    assert metric_delaunay_of(fld, pts.copy(), fld.box) is got  # remembered


def test_metric_delaunay_of_falls_back_on_a_lattice(three_toys, insertions):
    fld, seen = three_toys, insertions
    x0, y0, x1, y1 = fld.box
    gx, gy = np.meshgrid(np.linspace(x0, x1, 21), np.linspace(y0, y1, 21))
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    more = np.concatenate([pts, np.random.default_rng(10).uniform((x0, y0), (x1, y1), (20, 2))])
    metric_delaunay_of(fld, pts, fld.box)
    got = metric_delaunay_of(fld, more, fld.box)
    assert seen == [False]
    want = metric_delaunay(fld, delaunay(more, box=fld.box))
    np.testing.assert_array_equal(got.triangles, want.triangles)


@pytest.mark.parametrize("name", ["three_toys_coarse", "constant_aniso"])
def test_gap_filling_gives_the_same_points_without_insertion(name, monkeypatch, insertions):
    from curvimesh.boundary import discretize_box
    from curvimesh.sampling import SamplingOptions, sample_points

    fld = load_metric(METRICS / f"{name}.yaml")
    opt = SamplingOptions()
    boundary = discretize_box(fld, target=opt.step, min_dist=opt.min_dist)
    pts = sample_points(fld, boundary, opt, seed=0)
    with_insertion = fill_gaps(fld, pts, opt)
    assert any(insertions)
    monkeypatch.setattr(triangulate, "delaunay_insert", lambda mesh, new: None)
    triangulate._LAST.pop(fld, None)
    np.testing.assert_array_equal(fill_gaps(fld, pts, opt), with_insertion)


def _ccw(xy: np.ndarray, tris: np.ndarray) -> np.ndarray:
    area = triangulate.orient(xy[tris[:, 0]], xy[tris[:, 1]], xy[tris[:, 2]])
    return np.where((area < 0)[:, None], tris[:, [0, 2, 1]], tris)


def _edge_set(tris: np.ndarray) -> set[tuple[int, int]]:
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    return set(map(tuple, np.sort(e, axis=1).tolist()))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(20, 200), st.integers(4, 12))
def test_inserted_segments_become_edges_of_a_triangulation_of_the_same_hull(seed, n, k):
    """A polygon of k random points round the middle (a star about it: the i-th at an
    angle in 2π [i, i + 0.8) / k, so no gap reaches π and no two sides cross), n random
    points: each of its sides becomes an edge, the triangles stay counter-clockwise and
    conforming, and there are as many as before (2 n − h − 2 for n points, h on the
    hull: Euler), covering the same area."""
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(seed)
    angle = 2 * np.pi * (np.arange(k) + rng.uniform(0, 0.8, k)) / k
    radius = rng.uniform(0.2, 0.45, k)
    star = 0.5 + radius[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    xy = np.vstack([star, rng.uniform(0, 1, (n, 2))])
    tris = _ccw(xy, Delaunay(xy).simplices.astype(np.int64))
    sides = np.column_stack([np.arange(k), (np.arange(k) + 1) % k])
    out, failed = triangulate.insert_segments(xy, tris, sides)
    assert len(failed) == 0
    assert len(out) == len(tris)
    area = triangulate.orient(xy[out[:, 0]], xy[out[:, 1]], xy[out[:, 2]])
    assert (area > 0).all()
    ref = triangulate.orient(xy[tris[:, 0]], xy[tris[:, 1]], xy[tris[:, 2]])
    assert area.sum() == pytest.approx(ref.sum(), rel=1e-12)
    assert is_conforming(Mesh(xy, out))
    assert set(map(tuple, np.sort(sides, axis=1).tolist())) <= _edge_set(out)


def test_a_segment_through_a_point_or_across_another_is_refused():
    """(0, 0) – (1, 0) passes through (0.5, 0); of the two diagonals of the unit square
    (two points inside, off both), the second is refused, the first inserted."""
    xy = np.array([[0, 0], [1, 0], [0.5, 0], [0.5, 0.5], [0.5, -0.5], [0.2, 0.3], [0.8, -0.3]])
    tris = _ccw(xy, np.array([[0, 2, 3], [2, 1, 3], [0, 4, 2], [2, 4, 1], [0, 3, 5], [1, 4, 6]]))
    _, failed = triangulate.insert_segments(xy, tris, np.array([[0, 1]]))
    assert failed.tolist() == [[0, 1]]
    xy = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0.6, 0.3], [0.3, 0.75]], dtype=float)
    from scipy.spatial import Delaunay

    tris = _ccw(xy, Delaunay(xy).simplices.astype(np.int64))
    out, failed = triangulate.insert_segments(xy, tris, np.array([[0, 2], [1, 3]]))
    assert failed.tolist() == [[1, 3]]
    assert (0, 2) in _edge_set(out)


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(10, 150))
def test_lawsons_flips_reach_qhulls_delaunay_triangulation(seed, n):
    """From any triangulation of random points (Delaunay's with a third of its convex
    quads' diagonals swapped) the flips reach Delaunay's (unique: random points)."""
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 1, (n, 2))
    ref = _ccw(xy, Delaunay(xy).simplices.astype(np.int64))
    _, t1, t2, a, b, c, d = flip_candidates(Mesh(xy, ref))
    convex = (triangulate.orient(xy[a], xy[d], xy[c]) > 0) & (
        triangulate.orient(xy[d], xy[b], xy[c]) > 0
    )
    cand = np.flatnonzero(convex & (rng.uniform(size=len(a)) < 0.33))
    chosen = cand[independent_flips(t1[cand], t2[cand], np.zeros(len(cand)), len(ref))]
    start = apply_flips(ref, chosen, t1, t2, a, b, c, d)
    out = triangulate.delaunay_flips(xy, start)
    assert _edge_set(out) == _edge_set(ref)
