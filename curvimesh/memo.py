"""Memo tables of pure functions of float rows: an edge's length, a triangle's area.

The stages after curving measure the same edges and triangles over and over:
each swap pass, re-curving round, insertion, split, shift and removal takes
the lengths and qualities of the whole mesh, which changed in a few places
since the last. The quantities are pure functions of the nodes, so they are
kept in open-addressing hash tables (:func:`curvimesh.kernels.memo_find`)
keyed by a 128-bit fingerprint of the bits of the nodes
(:func:`curvimesh.kernels.row_fingerprints`): a row found is the number the
function gave for the same nodes, unless two node sets share a fingerprint (a
chance of about 10⁻²⁵ in a 10⁶-vertex run), and a run's mesh does not depend
on what was cached. Fingerprints, not the nodes, are stored: 25 bytes a row
instead of 105 for a triangle, and memory is what the tables cost here
(touching fresh pages costs about 2.4 ms per MB on the machines measured).
A table holds at most :data:`MAX_TABLE_BYTES`; past that it is emptied and
filled again, and a call with more rows than half its slots is not kept (on a
10⁶-vertex mesh, the measures of the whole mesh).
"""

from __future__ import annotations

import weakref
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from curvimesh import kernels

#: The most bytes one table takes (keys and values); it is emptied beyond.
MAX_TABLE_BYTES = 256 * 2**20


class RowMemo:
    """Values ``(n,)`` of rows of ``width`` floats, by a 128-bit fingerprint of their bits."""

    def __init__(self, width: int, *, capacity: int = 1 << 12) -> None:
        self.width = width
        slot_bytes = 8 * 2 + 9  # a fingerprint, a value, a flag
        self.max_slots = 1 << max(10, int(np.log2(MAX_TABLE_BYTES / slot_bytes)))
        self._allocate(min(capacity, self.max_slots))

    def _allocate(self, slots: int) -> None:
        self.keys = np.zeros((slots, 2), dtype=np.uint64)
        self.values = np.zeros(slots)
        self.filled = np.zeros(slots, dtype=np.bool_)
        self.count = 0

    def __len__(self) -> int:
        return self.count

    def _fingerprints(self, rows: NDArray) -> NDArray:
        """The fingerprints ``(n, 2)`` of ``rows``."""
        rows = np.ascontiguousarray(rows, dtype=np.float64).reshape(-1, self.width)
        out = np.empty((len(rows), 2), dtype=np.uint64)
        kernels.row_fingerprints(rows.view(np.uint64), out)
        return out

    def find(self, rows: NDArray) -> tuple[NDArray, NDArray]:
        """Values ``(n,)`` of ``rows`` ``(n, width)`` (NaN where absent) and whether each is
        there ``(n,)``."""
        keys = self._fingerprints(rows)
        out = np.full(len(keys), np.nan)
        found = np.zeros(len(keys), dtype=np.bool_)
        if self.count:
            kernels.memo_find(self.keys, self.values, self.filled, keys, out, found)
        return out, found

    def add(self, rows: NDArray, values: NDArray) -> None:
        """Remember ``values`` ``(n,)`` of ``rows`` ``(n, width)``."""
        if 2 * len(rows) > self.max_slots:  # more rows than a table holds: not kept
            return
        keys = self._fingerprints(rows)
        values = np.ascontiguousarray(values, dtype=np.float64)
        need = 2 * (self.count + len(keys))
        if need > len(self.filled):
            slots = len(self.filled)
            while slots < need and slots < self.max_slots:
                slots *= 2
            if need > slots:  # full: start again
                self._allocate(slots)
            else:
                old_keys, old_values, old_filled = self.keys, self.values, self.filled
                self._allocate(slots)
                self.count = kernels.memo_insert(
                    self.keys,
                    self.values,
                    self.filled,
                    old_keys[old_filled],
                    old_values[old_filled],
                )
        self.count += kernels.memo_insert(self.keys, self.values, self.filled, keys, values)


_TABLES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def memo_table(owner: object, key: tuple, width: int) -> RowMemo:
    """The table of ``owner`` (a metric field; dropped with it) for ``key``."""
    per_owner = _TABLES.setdefault(owner, {})
    table = per_owner.get(key)
    if table is None:
        table = per_owner[key] = RowMemo(width)
    return table


def memoised(table: RowMemo, rows: NDArray, compute: Callable[[NDArray], NDArray]) -> NDArray:
    """``compute(rows)`` ``(n,)`` for rows ``(n, width)``, computing only the rows not in
    ``table`` (``compute`` is called on those, in order) and remembering them."""
    rows = np.ascontiguousarray(rows, dtype=np.float64).reshape(len(rows), table.width)
    out, found = table.find(rows)
    todo = np.flatnonzero(~found)
    if todo.size:
        # a row may repeat within one call: computed for each, remembered once
        vals = compute(rows[todo])
        out[todo] = vals
        table.add(rows[todo], vals)
    return out


__all__ = ["MAX_TABLE_BYTES", "RowMemo", "memo_table", "memoised"]
