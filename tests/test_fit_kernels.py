"""The compiled interpolation error of a metric's function against the numpy one."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from curvimesh.interpolation import ScalarFunction
from curvimesh.interpolation_error import element_l2_squared
from curvimesh.metric import load_metric_text

FRONT = "(1 + tanh(50*((y - 0.5) - 0.3*sin(3*pi*x))))/2"


def metric(function: str):
    text = f"metric:\n  interpolation:\n    function: {function}\n    vertices: 400\n"
    return load_metric_text(text)


def p2_triangles(n: int, seed: int, size: float = 0.05) -> np.ndarray:
    rng = np.random.default_rng(seed)
    corner = rng.uniform(0.05, 0.9, (n, 2))
    step = np.array([[size, 0.0], [0.0, size]])
    tri = np.stack([corner, corner + step[0], corner + step[1]], axis=1)
    bend = rng.normal(scale=0.1 * size, size=(n, 3, 2))
    return np.concatenate([tri, 0.5 * (tri + tri[:, [1, 2, 0]]) + bend], axis=1)


@pytest.mark.parametrize("function", [FRONT, "(x - 0.5)**4 * (y - 0.5)**4", "x**2*y - 3*x*y**2"])
def test_compiled_element_errors_match_numpy(function):
    fld = metric(function)
    fast = fld.error_function
    ref = dataclasses.replace(fld, jit=False).error_function
    assert isinstance(fast, ScalarFunction) and fast.scalar is not None and ref.scalar is None
    nodes = p2_triangles(500, 3)
    got, want = element_l2_squared(fast, nodes), element_l2_squared(ref, nodes)
    assert want.max() > 0
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12 * want.max())
    np.testing.assert_array_equal(fast(nodes[:, 0]), ref(nodes[:, 0]))


def test_a_quadratic_is_interpolated_exactly_on_straight_triangles():
    fld = metric("x**2 + 3*x*y - y**2")
    tri = p2_triangles(200, 5)
    tri[:, 3:] = 0.5 * (tri[:, :3] + tri[:, [1, 2, 0]])  # straight sides
    assert element_l2_squared(fld.error_function, tri).max() < 1e-28
