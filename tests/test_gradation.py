"""Metric gradation on a background grid (curvimesh.gradation), against exact sizes.

Oracles: an isotropic field with one fine node is graded to min(H, h + (γ − 1) d)
with d the length of the shortest path of grid steps (the law composed along
straight steps is exactly linear); an axis-aligned anisotropic line grows each of
its two sizes by (γ − 1) times the distance; a field whose sizes do not vary is
left as it is. The B-spline of the node logarithms reproduces linear functions,
and the compiled twin gives the numpy values.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import sympy
from hypothesis import given, settings
from hypothesis import strategies as st

from curvimesh import kernels
from curvimesh.gradation import (
    GradedGrid,
    _pad_linear,
    grade,
    graded_grid,
    grid_nodes,
    grid_shape,
)
from curvimesh.interpolation import InterpolationMetric, X, Y
from curvimesh.tensors import exp_components, log_components


def isotropic(h: np.ndarray) -> np.ndarray:
    """Node metrics ``(nx, ny, 3)`` of isotropic sizes ``h`` ``(nx, ny)``."""
    return np.stack([h**-2, np.zeros_like(h), h**-2], axis=-1)


def sizes(g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The smaller and larger size of metrics ``(..., 3)``."""
    m = 0.5 * (g[..., 0] + g[..., 2])
    r = np.hypot(0.5 * (g[..., 0] - g[..., 2]), g[..., 1])
    return 1.0 / np.sqrt(m + r), 1.0 / np.sqrt(m - r)


def octile(di: np.ndarray, dj: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """Length of the shortest path of the 8 grid steps from (0, 0) to (di dx, dj dy)."""
    a, b = np.abs(di), np.abs(dj)
    diag = np.minimum(a, b)
    return diag * math.hypot(dx, dy) + (a - diag) * dx + (b - diag) * dy


@settings(max_examples=25, deadline=None)
@given(
    nx=st.integers(3, 14),
    ny=st.integers(3, 14),
    dx=st.floats(0.01, 1.0),
    dy=st.floats(0.01, 1.0),
    rate=st.floats(0.05, 3.0),
    data=st.data(),
)
def test_a_fine_node_grows_linearly_along_the_grid_paths(nx, ny, dx, dy, rate, data):
    i0 = data.draw(st.integers(0, nx - 1))
    j0 = data.draw(st.integers(0, ny - 1))
    big, small = 1e3, 1e-3
    h = np.full((nx, ny), big)
    h[i0, j0] = small
    out, sweeps = grade(isotropic(h), (dx, dy), rate)
    ii, jj = np.meshgrid(np.arange(nx) - i0, np.arange(ny) - j0, indexing="ij")
    expected = np.minimum(big, small + rate * octile(ii, jj, dx, dy))
    fine, coarse = sizes(out)
    np.testing.assert_allclose(fine, expected, rtol=1e-9)
    np.testing.assert_allclose(coarse, expected, rtol=1e-9)
    assert sweeps <= 3  # fast sweeping: straight paths are done in one sweep


def test_an_anisotropic_line_grows_both_sizes_with_the_distance():
    nx, ny, dx, dy, rate = 41, 9, 0.01, 0.03, 0.5
    across, along, far = 1e-3, 2e-2, 0.5
    g = isotropic(np.full((nx, ny), far))
    g[20] = [across**-2, 0.0, along**-2]  # the line x = 0.2, fine across (along x)
    out, _ = grade(g, (dx, dy), rate)
    dist = np.abs(np.arange(nx) - 20)[:, None] * dx * np.ones((1, ny))
    g11, g22 = out[..., 0], out[..., 2]
    np.testing.assert_allclose(out[..., 1], 0.0, atol=1e-9 * g11.max())
    np.testing.assert_allclose(g11**-0.5, np.minimum(far, across + rate * dist), rtol=1e-9)
    np.testing.assert_allclose(g22**-0.5, np.minimum(far, along + rate * dist), rtol=1e-9)


@settings(max_examples=30, deadline=None)
@given(
    h1=st.floats(1e-4, 1.0),
    ratio=st.floats(1.0, 1e4),
    angle=st.floats(0.0, math.pi),
    rate=st.floats(0.01, 5.0),
)
def test_a_field_that_does_not_vary_is_left_as_it_is(h1, ratio, angle, rate):
    c, s = math.cos(angle), math.sin(angle)
    l1, l2 = h1**-2, (h1 * ratio) ** -2
    m = np.array([l1 * c * c + l2 * s * s, (l1 - l2) * c * s, l1 * s * s + l2 * c * c])
    g = np.broadcast_to(m, (6, 5, 3)).copy()
    out, sweeps = grade(g, (0.1, 0.07), rate)
    np.testing.assert_array_equal(out, g)
    assert sweeps == 1


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), rate=st.floats(0.05, 2.0))
def test_the_graded_field_is_finer_than_the_field_and_than_its_own_spans(seed, rate):
    rng = np.random.default_rng(seed)
    nx, ny, dx, dy = 9, 7, 0.1, 0.05
    h1 = np.exp(rng.uniform(np.log(1e-3), 0.0, (nx, ny)))
    h2 = h1 * np.exp(rng.uniform(0.0, np.log(100.0), (nx, ny)))
    phi = rng.uniform(0.0, np.pi, (nx, ny))
    c, s, l1, l2 = np.cos(phi), np.sin(phi), h1**-2, h2**-2
    g = np.stack([l1 * c * c + l2 * s * s, (l1 - l2) * c * s, l1 * s * s + l2 * c * c], axis=-1)
    out, _ = grade(g, (dx, dy), rate)

    def at_least(a: np.ndarray, b: np.ndarray, tol: float) -> None:
        """a − b positive semidefinite, to tol relative to a."""
        d = a - b
        slack = tol * (a[..., 0] + a[..., 2])
        assert np.all(d[..., 0] >= -slack) and np.all(d[..., 2] >= -slack)
        m = 0.5 * (d[..., 0] + d[..., 2])
        assert np.all(m - np.hypot(0.5 * (d[..., 0] - d[..., 2]), d[..., 1]) >= -slack)

    at_least(out, g, 1e-12)
    for di, dj in ((1, 0), (0, 1), (1, 1), (1, -1)):
        p = out[max(0, -di) : nx - max(0, di), max(0, -dj) : ny - max(0, dj)]
        q = out[max(0, di) : nx + min(0, di) or None, max(0, dj) : ny + min(0, dj) or None]
        grow = rate * math.hypot(di * dx, dj * dy)
        for a, b in ((q, p), (p, q)):
            span = np.array([kernels.span_metric(*row, grow) for row in b.reshape(-1, 3)]).reshape(
                b.shape
            )
            at_least(a, span, 1e-5)  # intersect treats tensors within ~1e-5 as equal


@settings(max_examples=30, deadline=None)
@given(
    h=st.floats(1e-6, 1e3),
    ratio=st.floats(1.0, 1e6),
    angle=st.floats(0.0, math.pi),
)
def test_log_and_exp_of_metrics_are_inverse(h, ratio, angle):
    c, s = math.cos(angle), math.sin(angle)
    l1, l2 = h**-2, (h * ratio) ** -2
    g = np.array([[l1 * c * c + l2 * s * s], [(l1 - l2) * c * s], [l1 * s * s + l2 * c * c]])
    back = np.array(exp_components(*log_components(*g)))
    scale = l1
    np.testing.assert_allclose(back, g, atol=1e-9 * scale, rtol=0)
    # eigenvalues of log g are log l1, log l2
    lg = np.array(log_components(*g))[:, 0]
    m, r = 0.5 * (lg[0] + lg[2]), math.hypot(0.5 * (lg[0] - lg[2]), lg[1])
    assert m + r == pytest.approx(math.log(l1), abs=1e-9 * max(1.0, abs(math.log(l1))))
    # the components hold the small eigenvalue to about ε l1 only
    loose = 1e-9 * max(1.0, abs(math.log(l2))) + 10.0 * np.finfo(float).eps * l1 / l2
    assert m - r == pytest.approx(math.log(l2), abs=loose)


def test_the_grid_spline_reproduces_linear_logarithms_and_its_twin_agrees():
    nx, ny, x0, y0, dx, dy = 12, 9, -1.0, 0.5, 0.2, 0.25
    gx, gy = np.meshgrid(x0 + dx * np.arange(nx), y0 + dy * np.arange(ny), indexing="ij")
    coef = np.array([[0.3, 2.0, -1.0], [0.1, -0.5, 0.7], [1.2, 0.4, 1.5]])
    logs = np.stack([a + b * gx + c * gy for a, b, c in coef])
    grid = GradedGrid((x0, y0), (dx, dy), _pad_linear(logs))
    rng = np.random.default_rng(3)
    # inside the box and up to one cell beyond it, where the pieces extrapolate
    pts = np.column_stack(
        [rng.uniform(x0 - dx, x0 + (nx - 1 + 1) * dx, 500), rng.uniform(y0 - dy, y0 + ny * dy, 500)]
    )
    exact = exp_components(*(a + b * pts[:, 0] + c * pts[:, 1] for a, b, c in coef))
    got = grid.components(pts)
    for e, v in zip(exact, got, strict=True):
        np.testing.assert_allclose(v, e, rtol=1e-11, atol=1e-11 * np.abs(exact[0]).max())
    twin = np.array(
        [
            kernels.grid_tensor(
                x, y, *(np.ascontiguousarray(grid.logs[k]) for k in range(3)), x0, y0, dx, dy
            )
            for x, y in pts
        ]
    )
    np.testing.assert_allclose(twin, np.column_stack(got), rtol=1e-14, atol=0)


def test_grid_shapes_keep_the_node_arrays_under_a_megabyte():
    for box in ((0, 0, 1, 1), (0, 0, 10, 1), (-2, -2, 2, 2), (0, 0, 1, 7), (0, 0, 1e6, 1)):
        nx, ny = grid_shape(box)
        assert (nx + 2) * (ny + 2) * 8 <= 1_000_000
        dx, dy = (box[2] - box[0]) / (nx - 1), (box[3] - box[1]) / (ny - 1)
        if min(nx, ny) > 4:  # square cells but where a side is down to its 4 nodes
            assert dx == pytest.approx(dy, rel=0.05)


# --------------------------------------------------------------------------- #
# The graded interpolation metric                                              #
# --------------------------------------------------------------------------- #

F1 = (1 + sympy.tanh(50 * ((Y - sympy.Rational(1, 2)) - 0.3 * sympy.sin(3 * sympy.pi * X)))) / 2


@pytest.fixture(scope="module")
def graded_f1() -> tuple[InterpolationMetric, InterpolationMetric]:
    options = {"vertices": 3000, "sizes": (1e-4, 0.5)}
    return (
        InterpolationMetric(F1, gradation=2.0, **options),
        InterpolationMetric(F1, **options),
    )


def test_the_graded_metric_keeps_the_vertex_target(graded_f1):
    comp, _ = graded_f1
    # an independent count: a finer midpoint rule than the construction's quadrature
    n = 1024
    t = (np.arange(n) + 0.5) / n
    gx, gy = np.meshgrid(t, t, indexing="ij")
    g = comp.evaluate(np.column_stack([gx.ravel(), gy.ravel()]), derivatives=False)[0]
    count = 2.0 / math.sqrt(3.0) * np.sqrt(np.linalg.det(g)).mean()
    assert count == pytest.approx(3000, rel=0.01)


def test_the_graded_metric_is_the_ungraded_one_refined_where_sizes_grow_fast(graded_f1):
    comp, plain = graded_f1
    # the same scale: the graded metric is M ∩ G, finer than M at every point
    same = InterpolationMetric(F1, vertices=3000, sizes=(1e-4, 0.5))
    object.__setattr__(same, "_log_scale", comp._log_scale)
    pts = np.random.default_rng(0).random((4000, 2))
    g, m = comp.evaluate(pts, False)[0], same.evaluate(pts, False)[0]
    d = g - m
    eig = np.linalg.eigvalsh(d)
    assert np.all(eig[:, 0] >= -1e-9 * np.abs(g).max(axis=(1, 2)))
    # across the front at x = 0: the ungraded sizes jump from 0.05 to the clamp 0.5
    # within 0.1; the graded ones grow by at most (γ − 1) = 1 times the distance
    # (up to the grid: 8 % along directions between the grid's, and the spline)
    y = np.linspace(0.0, 0.45, 451)
    line = np.column_stack([np.zeros_like(y), y])
    h_graded = 1.0 / np.sqrt(np.linalg.eigvalsh(comp.evaluate(line, False)[0])[:, 0])
    h_plain = 1.0 / np.sqrt(np.linalg.eigvalsh(plain.evaluate(line, False)[0])[:, 0])
    slope = np.abs(np.diff(h_graded)) / np.diff(y)
    assert slope.max() <= 1.15
    assert (np.abs(np.diff(h_plain)) / np.diff(y)).max() > 5.0


def test_the_graded_metric_compiles_to_the_same_values(graded_f1):
    import dataclasses

    from curvimesh.metric import MetricField

    comp, _ = graded_f1
    fld = MetricField((comp,))
    assert fld.kernel is not None
    ref = dataclasses.replace(fld, jit=False)
    pts = np.random.default_rng(1).random((3000, 2))
    g, dg = fld.evaluate(pts, derivatives=True)
    g0, dg0 = ref.evaluate(pts, derivatives=True)
    mag = np.abs(g0).max(axis=(1, 2))
    # the ungraded metric's own agreement on f1 (1 − tanh² cancels away from the
    # front) bounds this one: where M dominates, the values are M's
    assert np.all(np.abs(g - g0).max(axis=(1, 2)) <= 1e-6 * mag)
    assert np.all(np.abs(dg - dg0).max(axis=(1, 2, 3)) <= 1e-6 * mag / comp.step)


def test_graded_grids_of_a_metric_on_the_grid_nodes():
    # graded_grid grades the metric at the nodes of the box's grid (grid_nodes)
    box = (0.0, 0.0, 2.0, 1.0)
    nodes, _ = grid_nodes(box, 2048)
    h = np.where(nodes[:, 0] < 1.0, 0.01, 0.5)  # a jump at x = 1
    grid = graded_grid(box, (h**-2, 0.0 * h, h**-2), 1.5, max_nodes=2048)
    nx, ny = grid.shape
    assert (nx, ny) == grid_shape(box, 2048)
    dx = grid.spacing[0]
    last = math.floor(1.0 / dx) * dx  # the last fine node
    x = np.linspace(1.2, 1.8, 7)
    g11 = grid.components(np.column_stack([x, np.full_like(x, 0.5)]))[0]
    # sizes 0.01 + 0.5 (x − last) past the jump (the spline of a linear size: 1 %)
    np.testing.assert_allclose(g11**-0.5, 0.01 + 0.5 * (x - last), rtol=0.01)
