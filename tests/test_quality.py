"""Metric areas to a tolerance (quality.metric_areas_adaptive) against exact integrals."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from curvimesh.metric import load_metric_text
from curvimesh.quality import REPORT_RTOL, metric_areas, metric_areas_adaptive

#: sqrt(det g) = 1 + K max(0, x − C): continuous, with a kink along x = C.
K, C = 4.0, 0.35
KINKED = load_metric_text(
    f"""
name: kinked
domain: {{box: [[0, 0], [1, 1]]}}
metric:
  isotropic: 1/sqrt(1 + {K}*max(0, x - {C}))
"""
)


def _clip_right(poly: np.ndarray, c: float) -> np.ndarray:
    """The part x ≥ c of a convex polygon ``(k, 2)`` (one Sutherland–Hodgman step)."""
    out = []
    for p, q in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        if p[0] >= c:
            out.append(p)
        if (p[0] - c) * (q[0] - c) < 0:
            t = (c - p[0]) / (q[0] - p[0])
            out.append(p + t * (q - p))
    return np.array(out).reshape(-1, 2)


def _moment(poly: np.ndarray) -> tuple[float, float]:
    """Area and ∫ x dA of a counter-clockwise polygon (shoelace)."""
    if len(poly) < 3:
        return 0.0, 0.0
    x, y = poly[:, 0], poly[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    return 0.5 * cross.sum(), (cross * (x + xn)).sum() / 6.0


def _exact_kinked_area(tri: np.ndarray) -> float:
    """∫_T 1 + K max(0, x − C) dA of a straight counter-clockwise triangle ``(3, 2)``."""
    area, _ = _moment(tri)
    right, x_moment = _moment(_clip_right(tri, C))
    return area + K * (x_moment - C * right)


def _straight_p2(tri: np.ndarray) -> np.ndarray:
    return np.vstack([tri, 0.5 * (tri + np.roll(tri, -1, axis=0))])


corner = st.tuples(st.floats(0.05, 0.95), st.floats(0.05, 0.95))


@settings(max_examples=40, deadline=None, derandomize=True)
@given(corner, corner, corner)
def test_areas_across_a_kink_meet_their_tolerance(a, b, c):
    # derandomized here as in CI: drawn afresh, about 0.4 % of such triangles defeat
    # the error estimate (test_a_kink_can_hide_from_the_error_estimate)
    tri = np.array([a, b, c], dtype=float)
    area, _ = _moment(tri)
    if abs(area) < 1e-3:
        return
    if area < 0:
        tri = tri[::-1].copy()
    exact = _exact_kinked_area(tri)
    got = metric_areas_adaptive(KINKED, _straight_p2(tri)[None], rtol=1e-6)[0]
    assert abs(got - exact) <= 1e-5 * exact


def test_a_fixed_rule_misses_the_kink_that_the_adaptive_areas_resolve():
    tri = np.array([[0.1, 0.2], [0.9, 0.3], [0.4, 0.9]])
    exact = _exact_kinked_area(tri)
    nodes = _straight_p2(tri)[None]
    fixed = metric_areas(KINKED, nodes, order=8, remember=False)[0]
    assert abs(fixed - exact) > 1e-4 * exact
    assert abs(metric_areas_adaptive(KINKED, nodes, rtol=1e-5)[0] - exact) <= 1e-5 * exact


def test_subdivided_pieces_add_up_to_a_curved_triangle():
    # In g = I the area is ∫ J over the reference triangle, J of degree 2: the
    # order-4 rule is exact; forced to its finest level (rtol 0), the 4⁴ pieces of
    # the subdivision must add up to the same number.
    flat = load_metric_text("name: flat\ndomain: {box: [[0, 0], [2, 2]]}\nmetric: {isotropic: 1}\n")
    nodes = np.array([[[0.1, 0.1], [1.5, 0.2], [0.4, 1.6], [0.8, 0.05], [1.1, 1.0], [0.15, 0.9]]])
    exact = metric_areas(flat, nodes, order=4, remember=False)[0]
    pieces = metric_areas_adaptive(flat, nodes, rtol=0.0, max_level=4)[0]
    assert abs(pieces - exact) <= 1e-13 * exact


def test_smooth_metric_areas_stop_at_the_first_level():
    toy = load_metric_text(
        "name: iso\ndomain: {box: [[0, 0], [1, 1]]}\nmetric: {isotropic: 0.1 + 0.2*x*y}\n"
    )
    nodes = np.array(
        [[[0.1, 0.1], [0.3, 0.12], [0.15, 0.3], [0.2, 0.1], [0.23, 0.22], [0.12, 0.2]]]
    )
    fine = metric_areas(toy, nodes, order=8, remember=False)[0]
    assert metric_areas_adaptive(toy, nodes, rtol=1e-8)[0] == fine


@pytest.mark.xfail(strict=True, reason="the estimate of orders 4 and 8 can agree across a kink")
def test_a_kink_can_hide_from_the_error_estimate():
    # found by the property test above drawn afresh (a = (0.75, 0.5), b = (0.75, 0.75),
    # c = (0.3359375, 0.5): 1.06e-5 at rtol 1e-6); the worst of 3,954 random triangles
    # at the report's tolerance is this one, 3.5e-4 off (35 times the tolerance), where
    # the two rules' errors across the kink agree and the triangle is never split.
    # Known, not yet mended: when it is, this test passes and, strict, fails the run
    tri = np.array([[0.7223, 0.3333], [0.6286, 0.6444], [0.0977, 0.9107]])
    exact = _exact_kinked_area(tri)
    got = metric_areas_adaptive(KINKED, _straight_p2(tri)[None], rtol=REPORT_RTOL)[0]
    assert abs(got - exact) <= 10 * REPORT_RTOL * exact
