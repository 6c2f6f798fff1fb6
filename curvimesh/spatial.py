"""A growing set of points with batched box queries: packed R-trees.

Algorithm 1 of the paper keeps accepted points in an R-tree (Guttman 1984)
to find the ones near a tentative point. Points arrive in batches (one front
of the sampling at a time); each batch is packed into a static R-tree by
Sort-Tile-Recursive (Leutenegger, Lopez & Edgington 1997): points sorted by
x into vertical slices, each slice by y, runs of :data:`CAPACITY` making the
leaves, and the same packing of the nodes' centres for every level above.
To keep queries cheap as batches accumulate, the index is a logarithmic
family of packed trees (Bentley & Saxe 1980): when a new batch is added,
trees of no larger size are merged into it and packed again, so there are
O(log n) trees and each point is packed O(log n) times. Queries run in
compiled code (:func:`curvimesh.kernels.rtree_count`, ``rtree_fill``), two
passes: count, then fill.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from curvimesh import kernels

#: Children per node (points per leaf).
CAPACITY = 16


def _str_order(centre: NDArray, capacity: int) -> NDArray:
    """Sort-Tile-Recursive order of boxes by their centres ``(k, 2)``: ceil(sqrt(k / B))
    slices by x, each sorted by y, so that runs of B make compact nodes."""
    k = len(centre)
    slices = max(1, int(np.ceil(np.sqrt(k / capacity))))
    per_slice = slices * capacity
    by_x = np.argsort(centre[:, 0], kind="stable")
    slice_of = np.empty(k, dtype=np.int64)
    slice_of[by_x] = np.arange(k) // per_slice
    return np.lexsort((centre[:, 1], slice_of))


def _run_boxes(boxes: NDArray, starts: NDArray) -> NDArray:
    """Bounding boxes ``(r, 4)`` of the runs of ``boxes`` ``(k, 4)`` beginning at ``starts``."""
    lo = [np.minimum.reduceat(boxes[:, i], starts) for i in (0, 1)]
    hi = [np.maximum.reduceat(boxes[:, i], starts) for i in (2, 3)]
    return np.column_stack([*lo, *hi])


class PackedTree:
    """One static R-tree over points ``(n, 2)`` with ids ``(n,)``, packed by STR.

    ``boxes`` ``(N, 4)`` (xmin, ymin, xmax, ymax) of the nodes, leaves first
    then each level up, the root last; ``first``/``count`` their children (node
    indices, or positions in ``ids`` for a leaf); ``leaf`` ``(N,)``.
    """

    def __init__(self, ids: NDArray, pts: NDArray, capacity: int = CAPACITY) -> None:
        order = _str_order(pts, capacity)
        self.ids = np.ascontiguousarray(ids[order], dtype=np.int64)
        p = self.xy = np.ascontiguousarray(pts[order], dtype=np.float64)
        starts = np.arange(0, len(p), capacity)
        boxes = _run_boxes(np.column_stack([p, p]), starts)
        levels = [(boxes, starts, np.diff(np.append(starts, len(p))))]
        while len(levels[-1][0]) > 1:
            child, offset = levels[-1][0], sum(len(lv[0]) for lv in levels[:-1])
            order = _str_order(0.5 * (child[:, :2] + child[:, 2:]), capacity)
            # the level below is renumbered in STR order, so each parent's children are a run
            levels[-1] = tuple(a[order] for a in levels[-1])
            child = levels[-1][0]
            starts = np.arange(0, len(child), capacity)
            boxes = _run_boxes(child, starts)
            levels.append((boxes, offset + starts, np.diff(np.append(starts, len(child)))))
        self.boxes = np.ascontiguousarray(np.concatenate([lv[0] for lv in levels]))
        self.first = np.concatenate([lv[1] for lv in levels]).astype(np.int64)
        self.count = np.concatenate([lv[2] for lv in levels]).astype(np.int64)
        self.leaf = np.zeros(len(self.boxes), dtype=np.bool_)
        self.leaf[: len(levels[0][0])] = True
        self.root = len(self.boxes) - 1


def packed_arrays(trees: list[PackedTree]) -> tuple[NDArray, ...]:
    """The trees side by side, as the compiled queries take them: node boxes, first
    children, child counts, leaf flags, ids, coordinates, roots (node indices and
    positions in ``ids`` shifted tree by tree)."""
    node_base = np.cumsum([0] + [len(t.boxes) for t in trees[:-1]])
    id_base = np.cumsum([0] + [len(t.ids) for t in trees[:-1]])
    boxes = np.concatenate([t.boxes for t in trees])
    first = np.concatenate(
        [
            np.where(t.leaf, t.first + ib, t.first + nb)
            for t, nb, ib in zip(trees, node_base, id_base, strict=True)
        ]
    )
    count = np.concatenate([t.count for t in trees])
    leaf = np.concatenate([t.leaf for t in trees])
    ids = np.concatenate([t.ids for t in trees])
    xy = np.concatenate([t.xy for t in trees])
    roots = np.array([t.root + nb for t, nb in zip(trees, node_base, strict=True)], dtype=np.int64)
    return boxes, first, count, leaf, ids, xy, roots


def _query(args: tuple[NDArray, ...] | None, mins: NDArray, maxs: NDArray):
    """Pairs (query index, point id) of the points of the packed trees ``args``
    (:func:`packed_arrays`, None for none) in each box, sorted."""
    mins = np.ascontiguousarray(mins, dtype=np.float64).reshape(-1, 2)
    maxs = np.ascontiguousarray(maxs, dtype=np.float64).reshape(-1, 2)
    if args is None or len(mins) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    counts = np.empty(len(mins), dtype=np.int64)
    kernels.rtree_count(mins, maxs, *args, counts)
    offsets = np.zeros(len(mins) + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    hits = np.empty(offsets[-1], dtype=np.int64)
    kernels.rtree_fill(mins, maxs, *args, offsets, hits)
    return np.repeat(np.arange(len(mins)), counts), hits


class PointIndex:
    """Points ``(n, 2)`` with integer ids 0..n−1 in insertion order.

    >>> idx = PointIndex()
    >>> idx.add(np.array([[0.0, 0.0], [1.0, 1.0]]))
    >>> q, ids = idx.query(np.array([[-0.5, -0.5]]), np.array([[0.5, 0.5]]))
    >>> q.tolist(), ids.tolist()
    ([0], [0])
    """

    def __init__(self) -> None:
        self._trees: list[PackedTree] = []
        self._chunks: list[NDArray] = []
        self._packed: tuple[NDArray, ...] | None = None
        self.size = 0

    def add(self, pts: NDArray) -> None:
        """Append points ``(k, 2)``; their ids continue the numbering."""
        pts = np.asarray(pts, dtype=float).reshape(-1, 2)
        if len(pts) == 0:
            return
        ids = np.arange(self.size, self.size + len(pts))
        self._chunks.append(pts)
        self.size += len(pts)
        while self._trees and len(self._trees[-1].ids) <= len(ids):
            ids = np.concatenate([self._trees.pop().ids, ids])
        ids = np.sort(ids)
        self._trees.append(PackedTree(ids, self.points[ids]))
        self._packed = None

    def packed(self) -> tuple[NDArray, ...] | None:
        """The trees as :func:`packed_arrays` (None while empty), kept until the next add."""
        if self._packed is None and self._trees:
            self._packed = packed_arrays(self._trees)
        return self._packed

    @property
    def points(self) -> NDArray:
        """All points ``(n, 2)`` in id order."""
        if len(self._chunks) > 1:
            self._chunks = [np.concatenate(self._chunks)]
        return self._chunks[0] if self._chunks else np.zeros((0, 2))

    def query(self, mins: NDArray, maxs: NDArray) -> tuple[NDArray, NDArray]:
        """Points inside each query box (boundary included): pairs ``(query index, point id)``,
        both ``(p,)``, sorted by query index, then point id.

        Boxes are ``mins``, ``maxs`` ``(q, 2)``.
        """
        return _query(self.packed(), mins, maxs)


def pairs_within_boxes(pts: NDArray, radius: NDArray) -> tuple[NDArray, NDArray]:
    """Pairs (i, j), i < j, where one point lies in the other's box of half-width ``radius``.

    Packs one R-tree over ``pts`` ``(n, 2)`` and queries the boxes [p − r, p + r]
    of every point; ``radius`` is ``(n,)`` or ``(n, 2)``. Sorted by i, then j.
    """
    n = len(pts)
    if n < 2:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    pts = np.asarray(pts, dtype=float)
    r = np.asarray(radius, dtype=float)
    r = r[:, None] if r.ndim == 1 else r
    a, b = _query(packed_arrays([PackedTree(np.arange(n), pts)]), pts - r, pts + r)
    keep = a != b
    # one int64 key per pair keeps the lexicographic order of (i, j)
    key = np.unique((np.minimum(a, b) * n + np.maximum(a, b))[keep])
    return key // n, key % n
