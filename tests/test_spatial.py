"""The packed R-trees of curvimesh.spatial against brute force."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from curvimesh import kernels
from curvimesh.spatial import CAPACITY, PackedTree, PointIndex, packed_arrays, pairs_within_boxes


def brute_query(pts, mins, maxs):
    inside = ((pts[None] >= mins[:, None]) & (pts[None] <= maxs[:, None])).all(axis=2)
    return np.nonzero(inside)


def brute_pairs(pts, r):
    r = r[:, None] if r.ndim == 1 else r
    a_in_b = (np.abs(pts[None] - pts[:, None]) <= r[:, None]).all(axis=2)  # [i, j]: j in i's box
    hit = a_in_b | a_in_b.T
    return np.nonzero(np.triu(hit, 1))


def test_batches_of_a_graded_cloud_answer_as_brute_force():
    rng = np.random.default_rng(0)
    idx = PointIndex()
    chunks = []
    for _ in range(25):  # batches of every size, merged into O(log n) trees
        p = rng.uniform(0, 1, (int(rng.integers(1, 2500)), 2)) ** 3  # dense near the origin
        chunks.append(p)
        idx.add(p)
    pts = np.concatenate(chunks)
    assert idx.size == len(pts) and np.array_equal(idx.points, pts)
    centre = rng.uniform(0, 1, (3000, 2)) ** 3
    half = rng.uniform(0, 0.03, (3000, 2))
    q, ids = idx.query(centre - half, centre + half)
    bq, bi = brute_query(pts, centre - half, centre + half)
    assert len(q) > 10_000
    assert np.array_equal(q, bq) and np.array_equal(ids, bi)


def test_a_walk_whose_stack_fills_says_so_and_a_larger_one_finds_every_point():
    rng = np.random.default_rng(3)
    pts = rng.uniform(0, 1, (5000, 2))
    args = packed_arrays([PackedTree(np.arange(len(pts)), pts)])
    lo, hi = np.array([0.2, 0.3]), np.array([0.6, 0.5])
    want = np.sort(brute_query(pts, lo[None], hi[None])[1])
    out = np.empty(len(pts), dtype=np.int64)
    # 5,000 points: 313 leaves of 16, under 20 nodes, under 2, under the root; a node of
    # 16 leaves that meets the box pushes more than two of them, and a stack of two overflows
    small = np.empty(2, dtype=np.int64)
    assert kernels._rtree_walk(*args, *lo, *hi, out, len(out), small) == -1
    found = kernels._rtree_walk(*args, *lo, *hi, out, len(out), np.empty(64, dtype=np.int64))
    assert found == len(want) > 300  # 0.4 × 0.2 × 5,000 expected
    assert np.array_equal(np.sort(out[:found]), want)
    # the entry point regrows its stack as needed and gives the same ids in the same order
    again = np.empty(len(pts), dtype=np.int64)
    assert kernels._rtree_visit(*args, *lo, *hi, again, len(again)) == found
    assert np.array_equal(again[:found], out[:found])


def test_boxes_are_closed_and_duplicates_all_found():
    idx = PointIndex()
    grid = np.array([[x, y] for x in range(10) for y in range(10)], dtype=float)
    idx.add(grid)
    idx.add(grid[:7])  # duplicates of the first seven points, ids 100..106
    q, ids = idx.query(np.array([[0.0, 0.0], [3.0, 4.0]]), np.array([[1.0, 0.0], [3.0, 4.0]]))
    # (0, 0) is ids 0 and 100, (1, 0) is id 10, (3, 4) is id 34; sorted by query, then id
    assert list(zip(q.tolist(), ids.tolist(), strict=True)) == [(0, 0), (0, 10), (0, 100), (1, 34)]


def test_empty_index_and_no_queries():
    idx = PointIndex()
    q, ids = idx.query(np.zeros((3, 2)), np.ones((3, 2)))
    assert q.size == 0 and ids.size == 0
    idx.add(np.array([[0.5, 0.5]]))
    q, ids = idx.query(np.zeros((0, 2)), np.zeros((0, 2)))
    assert q.size == 0 and ids.size == 0


@pytest.mark.parametrize("n", [1, CAPACITY - 1, CAPACITY, CAPACITY + 1, CAPACITY**2 + 3, 5000])
def test_packed_tree_nodes_bound_their_children(n):
    pts = np.random.default_rng(n).normal(size=(n, 2))
    tree = PackedTree(np.arange(n), pts)
    assert sorted(tree.ids.tolist()) == list(range(n))
    for node in range(len(tree.boxes)):
        lo, hi = tree.boxes[node, :2], tree.boxes[node, 2:]
        kids = range(tree.first[node], tree.first[node] + tree.count[node])
        assert 1 <= tree.count[node] <= CAPACITY
        if tree.leaf[node]:
            inner = pts[tree.ids[list(kids)]]
            assert (inner >= lo).all() and (inner <= hi).all()
        else:
            assert (tree.boxes[list(kids), :2] >= lo).all() and (
                tree.boxes[list(kids), 2:] <= hi
            ).all()
    # every point under the root's box, the root covering the cloud exactly
    assert np.array_equal(tree.boxes[tree.root], np.concatenate([pts.min(0), pts.max(0)]))


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(2, 400),
    seed=st.integers(0, 2**32 - 1),
    per_axis=st.booleans(),
    scale=st.floats(1e-3, 0.3),
)
def test_pairs_within_boxes_match_brute_force(n, seed, per_axis, scale):
    rng = np.random.default_rng(seed)
    pts = np.round(rng.uniform(0, 1, (n, 2)), 2)  # rounded: duplicates and boundary hits
    r = rng.uniform(0, scale, (n, 2) if per_axis else n)
    i, j = pairs_within_boxes(pts, r)
    bi, bj = brute_pairs(pts, r)
    assert np.array_equal(i, bi) and np.array_equal(j, bj)
