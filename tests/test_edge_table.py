"""The compiled edge table (kernels.edge_table, kernels.edge_triangles) against numpy.

The reference is the numpy code the kernels replaced in :class:`curvimesh.mesh.Mesh`:
``np.unique`` of one int64 key per side, and a stable argsort of the sides by edge.
The arrays must be the same, not merely equivalent: every stage downstream
(flips, splits, removals) visits edges in this order.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial import Delaunay

from curvimesh import kernels
from curvimesh.mesh import Mesh, to_p2_straight


def reference_topology(triangles, n):
    """(edges, tri_edges, edge_tris) of the first three columns of ``triangles`` on n nodes,
    by numpy's sorts."""
    corners = np.asarray(triangles, dtype=np.int64).reshape(-1, np.shape(triangles)[-1])[:, :3]
    a = corners.ravel()  # side k of triangle t at 3 t + k: corners k, k + 1
    b = corners[:, [1, 2, 0]].ravel()
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    n = max(n, 1)
    keys, inverse = np.unique(lo * n + hi, return_inverse=True)
    edges = np.column_stack([keys // n, keys % n]).astype(np.int64).reshape(-1, 2)
    tri_edges = inverse.reshape(-1, 3).astype(np.int64)
    flat = tri_edges.ravel()
    by_edge = np.argsort(flat, kind="stable")  # sides grouped by edge, in the order t, k
    counts = np.bincount(flat, minlength=len(edges))
    first = np.cumsum(counts) - counts
    edge_tris = np.full((len(edges), 2), -1, dtype=np.int64)
    edge_tris[:, 0] = by_edge[first] // 3
    two = counts >= 2
    edge_tris[two, 1] = by_edge[first[two] + 1] // 3
    return edges, tri_edges, edge_tris


def assert_same_as_reference(mesh):
    want_all = reference_topology(mesh.triangles, len(mesh.points))
    for got, want in zip((mesh.edges, mesh.tri_edges, mesh.edge_tris), want_all, strict=True):
        assert got.dtype == np.int64
        assert got.shape == want.shape
        assert not got.flags.writeable
        np.testing.assert_array_equal(got, want)


def delaunay_triangles(n, seed):
    points = np.random.default_rng(seed).random((n, 2))
    return points, Delaunay(points).simplices.astype(np.int64)


# ---------------------------------------------------------------- random triangle arrays


@st.composite
def triangle_arrays(draw):
    """Random node ids: repeated corners, edges of one to many triangles, repeated
    triangles (turned or reversed), unused nodes, few nodes (long runs of one lower
    end) or many; three or six columns."""
    n = draw(st.integers(1, 60))
    m = draw(st.integers(0, 120))
    width = draw(st.sampled_from([3, 6]))
    tris = draw(arrays(np.int64, (m, width), elements=st.integers(0, n - 1)))
    if m and draw(st.booleans()):
        picks = draw(st.lists(st.integers(0, m - 1), min_size=1, max_size=2 * m))
        copies = tris[picks]
        copies[:, :3] = np.roll(copies[:, :3], draw(st.integers(0, 2)), axis=1)
        if draw(st.booleans()):
            copies[:, :3] = copies[:, 2::-1]
        tris = np.concatenate([tris, copies])
        tris = tris[draw(st.permutations(range(len(tris))))]
    unused = draw(st.integers(0, 5))
    return n + unused, tris


@settings(max_examples=300, deadline=None)
@given(triangle_arrays())
def test_mesh_edge_table_is_numpys_on_random_triangles(case):
    n, tris = case
    assert_same_as_reference(Mesh(np.zeros((n, 2)), tris))


@settings(max_examples=100, deadline=None)
@given(triangle_arrays())
def test_kernels_on_writable_arrays_are_numpys(case):
    n, tris = case
    edges, tri_edges, edge_tris = reference_topology(tris, n)
    got_edges, got_tri_edges = kernels.edge_table(tris, n)
    np.testing.assert_array_equal(got_edges, edges)
    np.testing.assert_array_equal(got_tri_edges, tri_edges)
    np.testing.assert_array_equal(kernels.edge_triangles(tri_edges, len(edges)), edge_tris)


def test_edge_of_many_triangles_keeps_its_two_lowest():
    # Edge (1, 4) in triangles 1, 3, 4 (twice in 4, a repeated corner), (2, 3) only in 0.
    tris = [[2, 3, 0], [4, 1, 0], [0, 0, 0], [1, 4, 2], [4, 1, 4]]
    mesh = Mesh(np.zeros((6, 2)), tris)
    assert_same_as_reference(mesh)
    e = {tuple(edge): i for i, edge in enumerate(mesh.edges.tolist())}
    assert mesh.edge_tris[e[1, 4]].tolist() == [1, 3]
    assert mesh.edge_tris[e[0, 0]].tolist() == [2, 2]
    assert mesh.edge_tris[e[2, 3]].tolist() == [0, -1]
    assert mesh.edge_tris[e[4, 4]].tolist() == [4, -1]


def test_a_node_of_high_degree_sorts_as_numpy():
    # A fan of 400 triangles around node 7, shuffled: one run of 800 sides of lower end 7
    # (node ids above 7 but for two), far beyond INSERTION_SORT_MAX.
    rng = np.random.default_rng(5)
    rim = rng.permutation(np.arange(8, 408))
    tris = np.column_stack([np.full(400, 7), rim, np.roll(rim, -1)])
    tris[[3, 10]] = [[7, 0, 1], [2, 7, 5]]
    tris = tris[rng.permutation(400)]
    runs = np.bincount(np.minimum(tris, np.roll(tris, -1, axis=1)).ravel())
    assert runs.max() > 10 * kernels.INSERTION_SORT_MAX
    assert_same_as_reference(Mesh(np.zeros((408, 2)), tris))


@settings(max_examples=100, deadline=None)
@given(
    arrays(np.int64, st.tuples(st.integers(0, 300), st.just(2)), elements=st.integers(0, 9)),
    st.data(),
)
def test_merge_sort_of_long_runs_is_a_stable_sort(rows, data):
    b0 = data.draw(st.integers(0, len(rows)))
    b1 = data.draw(st.integers(b0, len(rows)))
    want = rows.copy()
    want[b0:b1] = rows[b0:b1][np.argsort(rows[b0:b1, 0], kind="stable")]
    kernels._merge_sort_rows(rows, b0, b1)
    np.testing.assert_array_equal(rows, want)


@pytest.mark.parametrize("n", [0, 1, 4])
def test_no_triangles(n):
    mesh = Mesh(np.zeros((n, 2)), np.zeros((0, 3), dtype=np.int64))
    assert mesh.edges.shape == (0, 2) and mesh.tri_edges.shape == (0, 3)
    assert mesh.edge_tris.shape == (0, 2)
    assert_same_as_reference(mesh)
    assert_same_as_reference(Mesh(np.zeros((n, 2)), np.zeros((0, 6), dtype=np.int64)))


# ---------------------------------------------------------------- Delaunay meshes


@pytest.mark.parametrize("seed", [0, 1])
def test_delaunay_mesh_edge_table_is_numpys(seed):
    points, tris = delaunay_triangles(3000, seed)
    mesh = Mesh(points, tris)
    assert_same_as_reference(mesh)
    assert_same_as_reference(to_p2_straight(mesh))
    # Nodes numbered along x (runs of one lower end in consecutive slots), unused nodes.
    rank = np.argsort(np.argsort(points[:, 0]))
    assert_same_as_reference(Mesh(np.zeros((len(points) + 9, 2)), 9 + rank[tris]))


def test_delaunay_edge_table_counts():
    points, tris = delaunay_triangles(2000, 2)
    mesh = Mesh(points, tris)
    # Euler for a disc, and every interior edge of two triangles, boundary of one.
    assert len(points) - len(mesh.edges) + len(tris) == 1
    holders = (mesh.edge_tris >= 0).sum(axis=1)
    assert np.array_equal(np.bincount(mesh.tri_edges.ravel()), holders)
