"""The memo tables (curvimesh.memo) against a dict of the same rows."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from curvimesh import memo
from curvimesh.geodesic import parabola_length
from curvimesh.memo import RowMemo, memoised
from curvimesh.metric import load_metric_text
from curvimesh.quality import edge_lengths_fast, metric_areas

floats = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.tuples(floats, floats, floats), min_size=1, max_size=300),
    st.lists(st.tuples(floats, floats, floats), min_size=1, max_size=50),
)
def test_rows_added_are_found_with_their_first_value_and_others_are_not(rows, queries):
    table = RowMemo(3, capacity=16)  # small: adding grows it several times
    ref: dict[bytes, float] = {}
    arr = np.array(rows, dtype=float)
    vals = np.arange(len(arr), dtype=float)
    for lo in range(0, len(arr), 37):  # in chunks, so the table grows between them
        table.add(arr[lo : lo + 37], vals[lo : lo + 37])
        for r, v in zip(arr[lo : lo + 37], vals[lo : lo + 37], strict=True):
            ref.setdefault(r.tobytes(), v)
    assert len(table) == len(ref)
    q = np.concatenate([arr, np.array(queries, dtype=float)])
    out, found = table.find(q)
    for r, o, f in zip(q, out, found, strict=True):
        key = r.tobytes()
        assert f == (key in ref)
        if f:
            assert o == ref[key]
        else:
            assert np.isnan(o)


def test_a_full_table_starts_again(monkeypatch):
    monkeypatch.setattr(memo, "MAX_TABLE_BYTES", 2048 * (8 * 2 + 9))
    table = RowMemo(2)
    assert table.max_slots == 2048
    first = np.column_stack([np.arange(1000.0), np.zeros(1000)])
    table.add(first, np.arange(1000.0))
    assert len(table) == 1000
    second = first + np.array([0.0, 1.0])
    table.add(second, -np.arange(1000.0))  # 2,000 rows need 4,096 slots: emptied first
    assert len(table) == 1000
    assert not table.find(first)[1].any()
    out, found = table.find(second)
    assert found.all() and np.array_equal(out, -np.arange(1000.0))
    # a call with more rows than half the slots is not kept, and the table stays
    big = np.column_stack([np.arange(1100.0), np.full(1100, 7.0)])
    table.add(big, np.zeros(1100))
    assert len(table) == 1000 and not table.find(big)[1].any()
    assert table.find(second)[1].all()


def test_memoised_computes_only_the_rows_it_has_not_seen():
    table = RowMemo(2)
    calls = []

    def f(rows):
        calls.append(len(rows))
        return rows[:, 0] * 10 + rows[:, 1]

    a = np.array([[1.0, 2.0], [3.0, 4.0]])
    assert np.array_equal(memoised(table, a, f), [12.0, 34.0])
    b = np.array([[3.0, 4.0], [5.0, 6.0], [1.0, 2.0]])
    assert np.array_equal(memoised(table, b, f), [34.0, 56.0, 12.0])
    assert calls == [2, 1]


def test_remembered_areas_and_lengths_are_the_computed_ones(monkeypatch):
    import curvimesh.quality as quality

    monkeypatch.setattr(quality, "MEMO_MIN_RATIO", 0.0)  # remember, however cheap the metric
    text = """
domain: {box: [[-1, -1], [1, 1]]}
metric:
  eigen: {sizes: [0.05 + 0.2*x**2, 0.3], angle: x*y}
"""
    rng = np.random.default_rng(4)
    corners = rng.uniform(-0.8, 0.8, (200, 3, 2))
    mids = (corners + np.roll(corners, -1, axis=1)) / 2 + rng.normal(scale=0.01, size=(200, 3, 2))
    nodes = np.concatenate([corners, mids], axis=1)
    fld, fresh = load_metric_text(text), load_metric_text(text)
    assert quality.remembers(fld)
    whole = metric_areas(fld, nodes)
    # half of them again, in another order, among new ones: the same numbers
    again = np.concatenate([nodes[150:], nodes[::2]])
    assert np.array_equal(metric_areas(fld, again), metric_areas(fresh, again))
    assert np.array_equal(metric_areas(fld, nodes[::2]), whole[::2])
    assert np.array_equal(metric_areas(fld, nodes, remember=False), whole)
    x0, x1, xm = corners[:, 0], corners[:, 1], mids[:, 0]
    first = edge_lengths_fast(fld, x0, x1, xm)
    assert np.array_equal(edge_lengths_fast(fld, x0[::-1], x1[::-1], xm[::-1]), first[::-1])
    assert np.array_equal(edge_lengths_fast(fresh, x0, x1, xm, remember=False), first)
    # exact lengths take their two-segment level from those: the adaptive rule's values
    pts = np.concatenate([x0, x1, xm])
    edges, mid_ids = np.column_stack([np.arange(200), np.arange(200, 400)]), np.arange(400, 600)
    for rtol in (1e-4, 1e-6):
        exact = quality.edge_lengths(fld, pts, edges, mid_ids, rtol=rtol)
        assert np.array_equal(exact, parabola_length(fresh, x0, x1, xm, rtol=rtol))


def test_adapt_gives_the_same_mesh_without_the_tables(monkeypatch):
    """The tables only spare work: the toy's mesh is the same, bit for bit, when every
    area and length is computed afresh."""
    from pathlib import Path

    import curvimesh.quality as quality
    from curvimesh.adapt import adapt
    from curvimesh.metric import load_metric

    path = Path(__file__).resolve().parents[1] / "metrics" / "toy.yaml"
    monkeypatch.setattr(quality, "MEMO_MIN_RATIO", 0.0)  # remember, whatever the machine
    fld = load_metric(path)
    assert quality.remembers(fld)
    with_tables = adapt(fld).mesh
    monkeypatch.setattr(quality, "memoised", lambda table, rows, compute: compute(rows))
    without = adapt(load_metric(path)).mesh
    assert np.array_equal(with_tables.points, without.points)
    assert np.array_equal(with_tables.triangles, without.triangles)


def test_only_metrics_slow_to_evaluate_are_remembered(monkeypatch):
    import dataclasses

    import curvimesh.quality as quality

    text = "domain: {box: [[0, 0], [1, 1]]}\nmetric: {eigen: {sizes: [0.1, 0.2], angle: x}}\n"
    monkeypatch.setattr(quality, "MEMO_MIN_RATIO", float("inf"))
    fld = load_metric_text(text)
    assert not quality.remembers(fld)
    assert quality.remembers(dataclasses.replace(fld, jit=False))  # numpy: microseconds
    monkeypatch.setattr(quality, "MEMO_MIN_RATIO", 0.0)
    assert not quality.remembers(fld)  # decided once per field (equal fields share it)
    assert not quality.remembers(load_metric_text(text))
    assert quality.remembers(load_metric_text(text.replace("0.2", "0.3")))


def test_the_look_up_is_timed_once_and_the_metric_per_field():
    import curvimesh.quality as quality

    first = quality.memo_lookup_ns()
    assert 0.0 < first < 1e5 and quality.memo_lookup_ns() == first  # once a process
    text = "domain: {box: [[0, 0], [1, 1]]}\nmetric: {eigen: {sizes: [0.1, 0.2], angle: x}}\n"
    assert 0.0 < quality.metric_ns(load_metric_text(text)) < 1e5
