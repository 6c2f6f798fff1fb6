"""Tests of curvimesh.mesh: topology judged by a slow loop-based checker."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import Delaunay

from curvimesh.mesh import (
    Mesh,
    boundary_sides,
    is_conforming,
    p1_of,
    signed_areas,
    to_p2_straight,
)

# ---------------------------------------------------------------- slow oracles


def slow_topology(triangles):
    """Edges, tri_edges, edge_tris, neighbours, neighbour sides, boundary by plain loops
    over triangles."""
    corners = [list(map(int, t[:3])) for t in triangles]
    holders = {}
    for t, c in enumerate(corners):
        for k in range(3):
            a, b = c[k], c[(k + 1) % 3]
            holders.setdefault((min(a, b), max(a, b)), []).append(t)
    edges = sorted(holders)
    index = {e: i for i, e in enumerate(edges)}
    tri_edges = [
        [index[(min(c[k], c[(k + 1) % 3]), max(c[k], c[(k + 1) % 3]))] for k in range(3)]
        for c in corners
    ]
    edge_tris = [(holders[e] + [-1])[:2] for e in edges]
    neighbours = []
    for t in range(len(corners)):
        row = []
        for k in range(3):
            others = [s for s in edge_tris[tri_edges[t][k]] if s != t]
            row.append(others[0] if others else -1)
        neighbours.append(row)
    # the first side of the neighbour whose neighbour is t (0 if none: a non-conforming edge)
    sides = [
        [(neighbours[s].index(t) if t in neighbours[s] else 0) if s >= 0 else -1 for s in row]
        for t, row in enumerate(neighbours)
    ]
    boundary = [i for i, e in enumerate(edges) if len(holders[e]) == 1]
    return edges, tri_edges, edge_tris, neighbours, sides, boundary


def slow_is_conforming(triangles):
    """The definition of conformity, spelled out with loops."""
    directed = {}
    mid_of = {}
    for t in triangles:
        t = list(map(int, t))
        if len(set(t[:3])) < 3:
            return False
        for k in range(3):
            a, b = t[k], t[(k + 1) % 3]
            directed.setdefault((min(a, b), max(a, b)), []).append((a, b))
            if len(t) == 6:
                mid_of.setdefault((min(a, b), max(a, b)), set()).add(t[3 + k])
    for uses in directed.values():
        if len(uses) > 2:
            return False
        if len(uses) == 2 and uses[0] == uses[1]:
            return False
    if mid_of:
        if any(len(m) != 1 for m in mid_of.values()):
            return False
        mids = [next(iter(m)) for m in mid_of.values()]
        if len(set(mids)) != len(mids):
            return False
        corner_ids = {int(v) for t in triangles for v in t[:3]}
        if corner_ids & set(mids):
            return False
    return True


def assert_topology_matches(mesh):
    edges, tri_edges, edge_tris, neighbours, sides, boundary = slow_topology(mesh.triangles)
    np.testing.assert_array_equal(mesh.edges, np.array(edges, dtype=np.int64).reshape(-1, 2))
    np.testing.assert_array_equal(mesh.tri_edges, np.array(tri_edges).reshape(-1, 3))
    np.testing.assert_array_equal(mesh.edge_tris, np.array(edge_tris).reshape(-1, 2))
    np.testing.assert_array_equal(mesh.neighbours, np.array(neighbours).reshape(-1, 3))
    np.testing.assert_array_equal(mesh.neighbour_sides, np.array(sides).reshape(-1, 3))
    np.testing.assert_array_equal(mesh.boundary_edges, boundary)


# ---------------------------------------------------------------- fixtures


def grid_mesh(k: int = 2) -> Mesh:
    """A k x k grid of unit-square cells on [0, 1]^2, each split by its diagonal."""
    x = np.linspace(0.0, 1.0, k + 1)
    points = np.array([(xi, yj) for yj in x for xi in x])
    tris = []
    for j in range(k):
        for i in range(k):
            a = j * (k + 1) + i
            b, c, d = a + 1, a + k + 2, a + k + 1
            tris += [[a, b, c], [a, c, d]]
    return Mesh(points, tris, box=(0.0, 0.0, 1.0, 1.0))


def delaunay_mesh(n: int = 60, seed: int = 1) -> Mesh:
    rng = np.random.default_rng(seed)
    points = np.vstack([rng.random((n, 2)), [[0, 0], [1, 0], [1, 1], [0, 1]]])
    tris = Delaunay(points).simplices
    # Delaunay does not promise an orientation: make every triangle CCW.
    cw = signed_areas(points, tris) < 0
    tris[cw] = tris[cw][:, [0, 2, 1]]
    return Mesh(points, tris)


# ---------------------------------------------------------------- the 2 x 2 grid


def test_grid_counts_and_euler():
    mesh = grid_mesh(2)
    assert mesh.order == 1
    assert len(mesh.vertex_ids) == 9
    assert len(mesh.triangles) == 8
    assert len(mesh.edges) == 16
    assert len(mesh.boundary_edges) == 8
    # Euler characteristic of a disc: V - E + F = 1.
    assert len(mesh.vertex_ids) - len(mesh.edges) + len(mesh.triangles) == 1
    assert np.all(signed_areas(mesh.points, mesh.triangles) > 0)
    assert is_conforming(mesh)


def test_grid_edge_tables_are_consistent():
    mesh = grid_mesh(2)
    edges = mesh.edges
    assert np.all(edges[:, 0] < edges[:, 1])
    assert len(np.unique(edges, axis=0)) == len(edges)
    np.testing.assert_array_equal(np.lexsort(edges.T[::-1]), np.arange(len(edges)))
    for t, tri in enumerate(mesh.corners):
        for k in range(3):
            a, b = tri[k], tri[(k + 1) % 3]
            e = mesh.tri_edges[t, k]
            assert tuple(edges[e]) == (min(a, b), max(a, b))
            assert t in mesh.edge_tris[e]
    interior = mesh.edge_tris[:, 1] >= 0
    assert interior.sum() == 8
    assert np.all(mesh.edge_tris[interior, 0] < mesh.edge_tris[interior, 1])
    assert_topology_matches(mesh)


def test_grid_neighbours_are_symmetric():
    mesh = grid_mesh(2)
    nb = mesh.neighbours
    assert (nb == -1).sum() == 8
    for t in range(len(nb)):
        for k in range(3):
            s = nb[t, k]
            if s >= 0:
                assert t in nb[s]
                assert mesh.tri_edges[t, k] in mesh.tri_edges[s]


def test_neighbour_sides_face_back_across_the_same_edge():
    mesh = delaunay_mesh(200, seed=4)
    nb, side = mesh.neighbours, mesh.neighbour_sides
    c = mesh.corners
    t, k = np.nonzero(nb >= 0)
    o, j = nb[t, k], side[t, k]
    assert len(t) == 2 * (len(mesh.edges) - len(mesh.boundary_edges))
    # side j of o runs along side k of t, the other way
    assert (c[o, j] == c[t, (k + 1) % 3]).all() and (c[o, (j + 1) % 3] == c[t, k]).all()
    assert (nb[o, j] == t).all() and (side[o, j] == k).all()
    assert (side[nb < 0] == -1).all()


def test_grid_boundary_sides_and_lines():
    mesh = grid_mesh(2)
    sides = boundary_sides(mesh)
    assert np.bincount(sides, minlength=4).tolist() == [2, 2, 2, 2]
    lines = mesh.boundary_lines
    assert lines.shape == (8, 2)
    # Domain on the left of every boundary line: the box centre is.
    a, b = mesh.points[lines[:, 0]], mesh.points[lines[:, 1]]
    centre = np.array([0.5, 0.5])
    cross = (b - a)[:, 0] * (centre - a)[:, 1] - (b - a)[:, 1] * (centre - a)[:, 0]
    assert np.all(cross > 0)
    # A side's lines lie on its line of the box.
    side_line = [(1, 0.0), (0, 1.0), (1, 1.0), (0, 0.0)]
    for side, (axis, value) in enumerate(side_line):
        ends = mesh.points[lines[sides == side]]
        np.testing.assert_array_equal(ends[..., axis], value)


def test_boundary_sides_without_box_and_off_side_edges():
    # A triangle whose hypotenuse lies on no side of its bounding box.
    mesh = Mesh([[0, 0], [1, 0], [0, 1]], [[0, 1, 2]])
    sides = boundary_sides(mesh)
    edges = mesh.edges[mesh.boundary_edges].tolist()
    assert dict(zip(map(tuple, edges), sides.tolist(), strict=True)) == {
        (0, 1): 0,
        (0, 2): 3,
        (1, 2): -1,
    }


# ---------------------------------------------------------------- P2


def test_to_p2_straight_nodes_at_midpoints():
    mesh = grid_mesh(2)
    p2 = to_p2_straight(mesh)
    n, n_edges = len(mesh.points), len(mesh.edges)
    assert p2.order == 2
    assert p2.triangles.shape == (8, 6)
    assert len(p2.points) == n + n_edges
    np.testing.assert_array_equal(p2.points[:n], mesh.points)
    np.testing.assert_array_equal(p2.edge_mid, n + np.arange(n_edges))
    for k in range(3):
        a, b = p2.triangles[:, k], p2.triangles[:, (k + 1) % 3]
        np.testing.assert_allclose(
            p2.points[p2.triangles[:, 3 + k]], 0.5 * (p2.points[a] + p2.points[b]), rtol=0
        )
    assert is_conforming(p2)
    assert slow_is_conforming(p2.triangles)
    assert p2.box == mesh.box
    assert p2.boundary_lines.shape == (8, 3)
    np.testing.assert_array_equal(p2.boundary_lines[:, :2], mesh.boundary_lines)


def test_to_p2_straight_of_p2_straightens_in_place():
    p2 = to_p2_straight(grid_mesh(2))
    bent = np.array(p2.points)
    bent[p2.edge_mid] += 0.01
    curved = Mesh(bent, p2.triangles)
    again = to_p2_straight(curved)
    np.testing.assert_array_equal(again.triangles, p2.triangles)
    np.testing.assert_allclose(again.points, p2.points, rtol=0, atol=1e-15)


def test_p1_of_round_trip():
    mesh = grid_mesh(3)
    p1 = p1_of(to_p2_straight(mesh))
    np.testing.assert_array_equal(p1.points, mesh.points)
    np.testing.assert_array_equal(p1.triangles, mesh.triangles)
    assert p1.box == mesh.box


def test_p1_of_drops_and_renumbers_unused_nodes():
    mesh = Mesh([[9, 9], [0, 0], [1, 0], [8, 8], [0, 1]], [[1, 2, 4]])
    p1 = p1_of(mesh)
    assert p1.points.tolist() == [[0, 0], [1, 0], [0, 1]]
    assert p1.triangles.tolist() == [[0, 1, 2]]


# ---------------------------------------------------------------- conformity


def test_is_conforming_detects_broken_meshes():
    mesh = grid_mesh(2)
    tris = np.array(mesh.triangles)
    flipped = tris.copy()
    flipped[0] = flipped[0, [0, 2, 1]]
    extra = np.vstack([tris, tris[:1, [1, 0, 2]]])  # a third triangle on an edge
    repeated = tris.copy()
    repeated[3, 2] = repeated[3, 0]
    for bad in (flipped, extra, repeated):
        broken = Mesh(mesh.points, bad)
        assert not is_conforming(broken)
        assert not slow_is_conforming(broken.triangles)
    p2 = to_p2_straight(mesh)
    shared = p2.edge_tris[p2.edge_tris[:, 1] >= 0][0]
    t6 = np.array(p2.triangles)
    local = int(np.flatnonzero(p2.tri_edges[shared[0]] == p2.tri_edges[shared[1]][:, None])[0])
    t6[shared[1], 3 + local] = t6[shared[1], 3 + (local + 1) % 3]
    for bad in (t6, np.column_stack([tris, tris[:, [1, 2, 0]]])):
        broken = Mesh(p2.points, bad)
        assert not is_conforming(broken)
        assert not slow_is_conforming(broken.triangles)


# ---------------------------------------------------------------- fast vs slow


def test_fast_topology_matches_slow_on_delaunay():
    mesh = delaunay_mesh()
    assert_topology_matches(mesh)
    assert is_conforming(mesh)
    p2 = to_p2_straight(mesh)
    assert_topology_matches(p2)
    assert is_conforming(p2) and slow_is_conforming(p2.triangles)
    n_vertices, n_edges, n_tris = len(mesh.vertex_ids), len(mesh.edges), len(mesh.triangles)
    assert n_vertices - n_edges + n_tris == 1


@st.composite
def triangle_soups(draw):
    """Small random triangle soups, P1 or P2, conforming or not."""
    n = draw(st.integers(3, 7))
    m = draw(st.integers(0, 8))
    tris = []
    for _ in range(m):
        tris.append(draw(st.permutations(range(n)))[:3])
    tris = np.array(tris, dtype=np.int64).reshape(-1, 3)
    points = np.random.default_rng(0).random((n, 2))
    if draw(st.booleans()):
        mesh = to_p2_straight(Mesh(points, tris))
        if draw(st.booleans()) and m:
            t6 = np.array(mesh.triangles)
            t6[draw(st.integers(0, m - 1)), draw(st.integers(3, 5))] = draw(
                st.integers(0, len(mesh.points) - 1)
            )
            mesh = Mesh(mesh.points, t6)
        return mesh
    return Mesh(points, tris)


@settings(max_examples=200, deadline=None)
@given(triangle_soups())
def test_fast_topology_matches_slow_on_soups(mesh):
    assert_topology_matches(mesh)
    assert is_conforming(mesh) == slow_is_conforming(mesh.triangles)


# ---------------------------------------------------------------- the Mesh object


def test_mesh_is_immutable_and_caches():
    points = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    tris = np.array([[0, 1, 2]])
    mesh = Mesh(points, tris)
    assert points.flags.writeable and tris.flags.writeable  # the caller's arrays
    points[0] = 5.0
    assert mesh.points[0].tolist() == [0.0, 0.0]
    with pytest.raises(ValueError):
        mesh.points[0, 0] = 1.0
    with pytest.raises(ValueError):
        mesh.edges[0, 0] = 1
    with pytest.raises(AttributeError):
        mesh.points = points
    assert mesh.edges is mesh.edges
    assert mesh.neighbours is mesh.neighbours
    assert Mesh(mesh.points, mesh.triangles).points is mesh.points  # no needless copy


def test_point_cloud():
    mesh = Mesh(np.random.default_rng(3).random((5, 2)), np.zeros((0, 3), dtype=np.int64))
    assert mesh.order == 1
    assert mesh.triangles.shape == (0, 3)
    assert mesh.edges.shape == (0, 2)
    assert mesh.edge_tris.shape == (0, 2)
    assert mesh.neighbours.shape == (0, 3)
    assert mesh.boundary_edges.size == 0
    assert boundary_sides(mesh).size == 0
    assert is_conforming(mesh)
    assert p1_of(mesh) is mesh
    assert Mesh(mesh.points, []).triangles.shape == (0, 3)


@pytest.mark.parametrize(
    ("points", "tris"),
    [
        ([[0, 0, 0]], np.zeros((0, 3), int)),
        ([[0, 0], [1, 0], [0, 1]], [[0, 1, 3]]),
        ([[0, 0], [1, 0], [0, 1]], [[0, 1]]),
        ([[0, 0], [1, 0], [0, 1]], [[0.0, 1.0, 2.0]]),
    ],
)
def test_mesh_rejects_bad_arrays(points, tris):
    with pytest.raises(ValueError):
        Mesh(points, tris)
