"""A growing set of points with batched box queries (the only user of ``rtree``).

Algorithm 1 of the paper keeps accepted points in an R-tree (Beckmann et
al. 1990) to find the ones near a tentative point. Points arrive in batches
(one front of the sampling at a time); each batch is bulk-loaded. To keep
queries cheap as batches accumulate, the index is a logarithmic family of
bulk-loaded R-trees (Bentley & Saxe 1980): when a new batch is added, trees
of no larger size are merged into it and rebuilt, so there are O(log n)
trees and each point is re-inserted O(log n) times.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from rtree import index as rtree_index


def _bulk(ids: NDArray, pts: NDArray) -> rtree_index.Index:
    prop = rtree_index.Property()
    prop.dimension = 2
    ids = np.ascontiguousarray(ids, dtype=np.int64)
    pts = np.ascontiguousarray(pts, dtype=np.float64)
    return rtree_index.Index((ids, pts, pts), properties=prop)


class PointIndex:
    """Points ``(n, 2)`` with integer ids 0..n−1 in insertion order.

    >>> idx = PointIndex()
    >>> idx.add(np.array([[0.0, 0.0], [1.0, 1.0]]))
    >>> q, ids = idx.query(np.array([[-0.5, -0.5]]), np.array([[0.5, 0.5]]))
    >>> q.tolist(), ids.tolist()
    ([0], [0])
    """

    def __init__(self) -> None:
        self._trees: list[tuple[int, NDArray, rtree_index.Index]] = []
        self._chunks: list[NDArray] = []
        self.size = 0

    def add(self, pts: NDArray) -> None:
        """Append points ``(k, 2)``; their ids continue the numbering."""
        pts = np.asarray(pts, dtype=float).reshape(-1, 2)
        if len(pts) == 0:
            return
        ids = np.arange(self.size, self.size + len(pts))
        self._chunks.append(pts)
        self.size += len(pts)
        while self._trees and len(self._trees[-1][1]) <= len(ids):
            _, old_ids, _ = self._trees.pop()
            ids = np.concatenate([old_ids, ids])
        self._trees.append((len(ids), ids, _bulk(ids, self.points[ids])))

    @property
    def points(self) -> NDArray:
        """All points ``(n, 2)`` in id order."""
        if len(self._chunks) > 1:
            self._chunks = [np.concatenate(self._chunks)]
        return self._chunks[0] if self._chunks else np.zeros((0, 2))

    def query(self, mins: NDArray, maxs: NDArray) -> tuple[NDArray, NDArray]:
        """Points inside each query box: pairs ``(query index, point id)``, both ``(p,)``.

        Boxes are ``mins``, ``maxs`` ``(q, 2)``. Pairs come sorted by query
        index, then point id (deterministic).
        """
        mins = np.ascontiguousarray(mins, dtype=np.float64).reshape(-1, 2)
        maxs = np.ascontiguousarray(maxs, dtype=np.float64).reshape(-1, 2)
        qs, hits = [], []
        for _, _, tree in self._trees:
            ids, counts = tree.intersection_v(mins, maxs)
            qs.append(np.repeat(np.arange(len(mins)), counts.astype(np.int64)))
            hits.append(np.asarray(ids, dtype=np.int64))
        if not qs:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        q = np.concatenate(qs)
        h = np.concatenate(hits)
        order = np.lexsort((h, q))
        return q[order], h[order]


def pairs_within_boxes(pts: NDArray, radius: NDArray) -> tuple[NDArray, NDArray]:
    """Pairs (i, j), i < j, where one point lies in the other's box of half-width ``radius``.

    Builds one bulk-loaded R-tree over ``pts`` ``(n, 2)`` and queries the
    boxes [p − r, p + r] of every point; ``radius`` is ``(n,)`` or ``(n, 2)``.
    """
    n = len(pts)
    if n < 2:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    tree = _bulk(np.arange(n), pts)
    r = np.asarray(radius, dtype=float)
    r = r[:, None] if r.ndim == 1 else r
    ids, counts = tree.intersection_v(np.ascontiguousarray(pts - r), np.ascontiguousarray(pts + r))
    a = np.repeat(np.arange(n), counts.astype(np.int64))
    b = np.asarray(ids, dtype=np.int64)
    keep = a != b
    pair = np.unique(np.column_stack([np.minimum(a, b), np.maximum(a, b)])[keep], axis=0)
    return pair[:, 0], pair[:, 1]
