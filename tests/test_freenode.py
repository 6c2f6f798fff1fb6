"""Shortest parabolas with a free middle node (curvimesh.freenode): they follow a front
from its tip where the paper's symmetric parabola cannot, and are the paper's
parabola, bit for bit, wherever the metric's frame turns slowly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from curvimesh import freenode, geodesic
from curvimesh.metric import load_metric, load_metric_text

METRICS = Path(__file__).resolve().parents[1] / "metrics"


def front_points(arc: np.ndarray) -> np.ndarray:
    """Points of the front x = 0.5 + 0.2 cos(3πy) of tight_front at Euclidean arc
    lengths ``arc`` from its tip (0.7, 2/3), towards larger y."""
    y = np.linspace(2 / 3, 0.9, 200_001)
    x = 0.5 + 0.2 * np.cos(3 * np.pi * y)
    s = np.concatenate([[0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    yy = np.interp(arc, s, y)
    return np.column_stack([0.5 + 0.2 * np.cos(3 * np.pi * yy), yy])


def test_a_unit_arc_from_the_tip_of_a_tight_front_has_a_unit_free_parabola():
    # along the front the metric size is 0.08, so an arc of 0.08 is one unit long;
    # from the tip it bends 81 degrees, more at the tip than at its other end
    fld = load_metric(METRICS / "hard" / "tight_front.yaml")
    a = front_points(np.array([0.0, 0.0]))
    b = front_points(np.array([0.08, 0.056]))
    paper = geodesic.shortest_parabola(fld, a, b)
    free = freenode.shortest_parabola(fld, a, b)
    assert paper.length[0] > 3.0  # symmetric about the chord's bisector: cuts the front
    assert free.length[0] == pytest.approx(1.0, abs=0.02)
    assert free.length[1] == pytest.approx(0.7, abs=0.02)
    # the reported length is the node's, and the node is off the bisector
    again = geodesic.parabola_length(fld, a, b, free.mid)
    np.testing.assert_allclose(free.length, again, rtol=1e-5)
    d = b - a
    off = np.einsum("ij,ij->i", free.mid - 0.5 * (a + b), d) / np.einsum("ij,ij->i", d, d)
    assert np.all(np.abs(off) > 0.03)


def test_where_the_frame_turns_slowly_it_is_the_papers_parabola_exactly():
    rng = np.random.default_rng(3)
    for name in ("toy", "front", "three_toys_coarse"):
        fld = load_metric(METRICS / f"{name}.yaml")
        x0, y0, x1, y1 = fld.box
        a = np.column_stack([rng.uniform(x0, x1, 300), rng.uniform(y0, y1, 300)])
        b = a + rng.normal(scale=0.05, size=a.shape)
        assert not freenode.edges_turning_fast(fld, a, b).any()
        for kw in ({}, {"exact_length": False, "scan": 5}):
            ours, paper = (
                freenode.shortest_parabola(fld, a, b, **kw),
                geodesic.shortest_parabola(fld, a, b, **kw),
            )
            assert np.array_equal(ours.mid, paper.mid) and np.array_equal(ours.length, paper.length)
        for kw in ({"short": 0.7}, {"long": 1.4}):
            ours, paper = (
                freenode.bounded_lengths(fld, a, b, **kw),
                geodesic.bounded_lengths(fld, a, b, **kw),
            )
            assert np.array_equal(ours[0], paper[0]) and np.array_equal(ours[1], paper[1])


def test_the_free_node_of_a_constant_metric_is_the_midpoint():
    fld = load_metric_text("metric: {eigen: {sizes: [0.01, 0.2], angle: 0.5}}\n")
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 1, (20, 2))
    b = a + rng.normal(scale=0.05, size=a.shape)
    par = geodesic.shortest_parabola(fld, a, b, exact_length=False)
    mid, length = freenode.free_node(fld, a, b, par.alpha)
    np.testing.assert_allclose(mid, 0.5 * (a + b), atol=1e-6 * np.hypot(*(b - a).T).max())
    np.testing.assert_allclose(length, par.length, rtol=1e-9)


def test_only_the_fast_turns_of_the_tight_front_are_fast():
    fld = load_metric(METRICS / "hard" / "tight_front.yaml")
    tip = np.array([[0.7, 2 / 3], [0.3, 1 / 3]])
    flank = np.array([[0.5, 0.5], [0.5 + 0.2 * np.cos(3 * np.pi * 0.45), 0.45]])
    far = np.array([[0.1, 0.5], [0.9, 0.1]])  # isotropic there
    assert freenode.turns_fast(fld, tip).all()
    assert not freenode.turns_fast(fld, np.concatenate([flank, far])).any()


def test_the_compiled_free_node_is_the_numpy_one_bit_for_bit():
    """kernels.free_nodes runs free_node's damped Newton one row at a time in the same
    operations: on edges about the tight front's tips (where it matters) and across it,
    the same nodes and lengths, bit for bit."""
    fld = load_metric(METRICS / "hard" / "tight_front.yaml")
    assert fld.kernel is not None
    rng = np.random.default_rng(11)
    a = front_points(rng.uniform(0.0, 0.15, 200)) + rng.normal(scale=0.002, size=(200, 2))
    b = a + rng.normal(scale=0.04, size=a.shape)
    alpha = geodesic.shortest_parabola(fld, a, b, exact_length=False).alpha
    mid, length = freenode.free_node(fld, a, b, alpha)
    ref_mid, ref_length = freenode._free_node_numpy(fld, a, b, alpha)
    assert np.array_equal(mid, ref_mid) and np.array_equal(length, ref_length)
    moved = np.hypot(*(mid - geodesic.parabola_midnode(a, b, alpha)).T)
    assert (moved > 0.1 * np.hypot(*(b - a).T)).sum() > 20  # nodes freed far off the bisector
