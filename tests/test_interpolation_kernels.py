"""The interpolation metric on the compiled path against its numpy evaluation.

:meth:`InterpolationMetric.scalar_source` prints the derivatives of f as
scalar code and hands them to the scalar twins of the shape, scaling and
clamp in :mod:`curvimesh.kernels`; ``MetricField(jit=False)`` evaluates the
same construction with numpy, the reference here.

The two paths evaluate the same expressions of the derivatives of f, but
with different implementations of the elementary functions (numpy's SIMD
``tanh``, ``exp``, ``log`` differ from the C library's in the last bit for a
good share of arguments). The twins themselves agree with the numpy code to
those last bits; the values of g agree to 1e-12 relative wherever the
derivative expressions are well conditioned. Where they are not, both paths
carry the same rounding error and differ by it: sympy writes the derivatives
of tanh(u) with 1 − tanh²(u), which loses log10(1/sech²(u)) digits away from a
tanh front, so there the tolerance is that loss (about ε/sech²(u) relative,
measured at most 0.51 ε/sech²(u) on f1). The derivatives are the same central
differences, of step h, of values that agree to that tolerance: they agree to
it times |g|/h.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import sympy

from curvimesh import geodesic as geo
from curvimesh import kernels
from curvimesh.interpolation import InterpolationMetric, X, Y, cubic_shape, hessian_shape
from curvimesh.metric import Component, MetricField, load_metric_text

#: f1 as the convergence study writes it (bench/convergence.py).
F1_TEXT = "(1 + tanh(50*((y - 0.5) - 0.3*sin(3*pi*x))))/2"
#: The two functions of the feNG benchmarks, and one whose derivatives of
#: orders 2 and 3 all vanish at (0.3, 0.6) (the Hessian along both lines through it).
FUNCTIONS = {
    "f1": (1 + sympy.tanh(50 * ((Y - sympy.Rational(1, 2)) - 0.3 * sympy.sin(3 * sympy.pi * X))))
    / 2,
    "f2": (X - sympy.Rational(1, 2)) ** 4 * (Y - sympy.Rational(1, 2)) ** 4,
    "f3": (X - 0.3) ** 3 * (Y - 0.6) ** 3,
}
#: Points where the derivatives of the functions vanish (f2: the lines x, y = 1/2).
SPECIAL = np.array(
    [[0.5, 0.5], [0.5, 0.2], [0.7, 0.5], [0.3, 0.6], [0.3, 0.1], [0.9, 0.6], [0.0, 0.0], [1.0, 1.0]]
)
EPS = np.finfo(float).eps


def field(function: sympy.Expr, **options: object) -> MetricField:
    """The interpolation metric of ``function`` alone (the study's sizes, coarse scale grid)."""
    options = {"vertices": 2000, "sizes": (1e-4, 0.5), "quadrature_cells": 32, **options}
    return MetricField((InterpolationMetric(function, **options),))


def points(n: int, seed: int) -> np.ndarray:
    """n random points of the unit square and :data:`SPECIAL`."""
    return np.vstack([np.random.default_rng(seed).random((n, 2)), SPECIAL])


def conditioning(name: str, comp: InterpolationMetric, pts: np.ndarray) -> np.ndarray:
    """How many times ε the two paths may differ at ``pts``, relative to |g| ``(n,)``.

    The product of two condition numbers, the worst over the central-difference
    stencil (the point and the points ±h along x and y):

    * of the derivatives of f: 1/sech²(u) for f1 = (1 + tanh u)/2, whose
      derivatives hold 1 − tanh²(u); 1 for the others;
    * of the frame: :func:`curvimesh.interpolation._frame` takes cos φ and sin φ
      from the half-angle formulas sqrt((1 ± cos 2φ)/2), which cancel near the
      axes: an ulp of cos 2φ moves cos φ by about ε/cos φ (sin φ likewise), hence
      1/min(|cos φ|, |sin φ|), at most 1/sqrt(ε) (a whole ulp under the root).
    """
    h = comp.step
    worst = np.ones(len(pts))
    for shift in ([0.0, 0.0], [h, 0.0], [-h, 0.0], [0.0, h], [0.0, -h]):
        q = pts + shift
        cos, sin, _, _ = comp.shape(q)
        axis = np.maximum(np.minimum(np.abs(cos), np.abs(sin)), math.sqrt(EPS))
        frame = np.where(np.isfinite(axis), 1.0 / axis, 1.0)
        if name == "f1":
            u = 50.0 * ((q[:, 1] - 0.5) - 0.3 * np.sin(3.0 * np.pi * q[:, 0]))
            frame = frame / np.maximum(1.0 - np.tanh(u) ** 2, 1e-300)
        worst = np.maximum(worst, frame)
    return worst


def assert_paths_agree(fld: MetricField, pts: np.ndarray, tol: np.ndarray, step: float) -> None:
    """g and ∂g of the compiled path against the numpy path, to ``tol`` ``(n,)`` relative
    for g and ``2 tol |g| / step`` for ∂g (central differences of values within tol)."""
    assert fld.kernel is not None
    ref = dataclasses.replace(fld, jit=False)
    g, dg = fld.evaluate(pts, derivatives=True, check=False)
    g0, dg0 = ref.evaluate(pts, derivatives=True, check=False)
    assert np.array_equal(np.isnan(g), np.isnan(g0))
    assert np.array_equal(np.isnan(dg), np.isnan(dg0))
    ok = np.isfinite(g0).all(axis=(1, 2))
    mag = np.abs(g0[ok]).max(axis=(1, 2))
    assert np.all(np.abs(g[ok] - g0[ok]).max(axis=(1, 2)) <= tol[ok] * mag)
    assert np.all(np.abs(dg[ok] - dg0[ok]).max(axis=(1, 2, 3)) <= 2.0 * tol[ok] * mag / step)
    # the fallback without ``check`` and the plain tensor: the same values
    np.testing.assert_array_equal(fld.tensor(pts[ok]), g[ok])


# --------------------------------------------------------------------------- #
# The scalar twins                                                             #
# --------------------------------------------------------------------------- #


def coefficients(rows: int, k: int, seed: int) -> np.ndarray:
    """Random derivative values ``(k, rows)`` over 20 orders of magnitude, with rows of
    zeros, of one zero, a NaN and an infinity."""
    rng = np.random.default_rng(seed)
    coef = rng.normal(size=(k, rows)) * np.exp(5.0 * rng.normal(size=(k, rows)))
    coef[:, :10] = 0.0
    coef[1, 10:20] = 0.0
    coef[0, 20:30] = np.nan
    coef[-1, 30:40] = np.inf
    return coef


def close_or_both_nan(a: np.ndarray, b: np.ndarray, rtol: float) -> None:
    assert np.array_equal(np.isnan(a), np.isnan(b))
    ok = ~np.isnan(b)
    assert np.all(np.abs(a[ok] - b[ok]) <= rtol * np.maximum(np.abs(b[ok]), 1.0))


@pytest.mark.parametrize(
    ("twin", "numpy_shape", "k"),
    [(kernels.cubic_shape, cubic_shape, 4), (kernels.hessian_shape, hessian_shape, 3)],
)
def test_scalar_shapes_are_the_numpy_shapes(twin, numpy_shape, k):
    coef = coefficients(2000, k, 5)
    with np.errstate(all="ignore"):
        ref = np.array(numpy_shape(coef, max_aspect=5000.0))
    out = np.array([twin(*coef[:, i], 5000.0) for i in range(coef.shape[1])]).T
    # the same operations; numpy's log and hypot differ from the C library's in the last bit
    close_or_both_nan(out, ref, 1e-13)
    assert np.isnan(out[:, 20:30]).any(axis=0).all()  # a NaN derivative: a NaN shape


def test_scalar_tensor_and_differences_are_the_numpy_ones():
    fld = field(FUNCTIONS["f1"])
    (comp,) = fld.components
    pts = points(300, 3)
    cos, sin, x_log, y_log = comp.shape(pts)
    hmin, hmax = comp.sizes
    consts = (comp._log_scale, comp.exponents[1], -2 * math.log(hmax), -2 * math.log(hmin))
    out = np.array(
        [
            kernels.interpolation_tensor((c, s, a, b), *consts)
            for c, s, a, b in zip(cos, sin, x_log, y_log, strict=True)
        ]
    )
    g = comp.evaluate(pts, False)[0]
    np.testing.assert_allclose(out, g[:, [0, 0, 1], [0, 1, 1]], rtol=1e-14, atol=0)
    # one-sided where a shifted value is NaN, as InterpolationMetric.evaluate
    h = 0.5
    g0, px, mx = (1.0, 2.0, 3.0), (2.0, 4.0, 7.0), (0.0, 0.0, 0.0)
    nan = (math.nan,) * 3
    assert kernels.central_differences(g0, px, mx, px, mx, h)[3:] == (2.0, 4.0, 7.0) * 2
    one_sided = kernels.central_differences(g0, px, nan, nan, mx, h)
    assert one_sided[3:] == (2.0, 4.0, 8.0, 2.0, 4.0, 6.0)  # forward along x, backward along y


# --------------------------------------------------------------------------- #
# Whole fields                                                                 #
# --------------------------------------------------------------------------- #


@pytest.mark.parametrize("norm", [1.0, 2.0, math.inf])
@pytest.mark.parametrize("degree", [1, 2])
@pytest.mark.parametrize("name", sorted(FUNCTIONS))
def test_compiled_interpolation_metric_matches_numpy(name, degree, norm):
    fld = field(FUNCTIONS[name], degree=degree, norm=norm)
    pts = points(1500, 7)
    comp = fld.components[0]
    tol = 1e-12 + 2.0 * EPS * conditioning(name, comp, pts)
    assert_paths_agree(fld, pts, tol, comp.step)


def test_in_an_intersection_with_a_symbolic_metric():
    text = f"""
metric:
  intersection:
    - interpolation: {{function: "{F1_TEXT}", vertices: 1000, sizes: [1e-4, 0.5]}}
    - eigen: {{sizes: [0.05 + 0.1*x, 0.2], angle: 0.3 + y}}
"""
    fld = load_metric_text(text)
    assert fld.kernel is not None
    assert "interpolation_tensor(cubic_shape(" in fld.scalar_source
    pts = points(1500, 9)
    # the intersection of nearly proportional tensors: 1e-9 (as in test_kernels)
    comp = fld.components[0]
    tol = 1e-9 + 2.0 * EPS * conditioning("f1", comp, pts)
    assert_paths_agree(fld, pts, tol, comp.step)


def test_undefined_derivatives_are_nan_on_both_paths_and_one_sided_near_them():
    # f''' = 15/(8 sqrt(x)): infinite at x = 0 (the limit 1e-9 away is taken there),
    # undefined for x < 0, and within h of 0 the derivative is one-sided
    fld = field(X ** sympy.Rational(5, 2) + Y**3 / 10)
    h = fld.components[0].step
    pts = np.array([[-0.5, 0.5], [-1e-9, 0.2], [0.0, 0.3], [0.3 * h, 0.4], [0.6, 0.6]])
    fast, ref = fld, dataclasses.replace(fld, jit=False)
    g, dg = fast.evaluate(pts, derivatives=True, check=False)
    g0, dg0 = ref.evaluate(pts, derivatives=True, check=False)
    assert np.isnan(g[:2]).all() and np.isnan(g0[:2]).all()
    assert np.isnan(dg[:2]).all() and np.isnan(dg0[:2]).all()
    assert np.isfinite(g[2:]).all() and np.isfinite(dg[2:]).all()
    mag = np.abs(g0[2:]).max(axis=(1, 2))
    assert np.all(np.abs(g[2:] - g0[2:]).max(axis=(1, 2)) <= 1e-12 * mag)
    assert np.all(np.abs(dg[2:] - dg0[2:]).max(axis=(1, 2, 3)) <= 2e-12 * mag / h)
    # one-sided: finite, where a central difference would reach x < 0
    assert np.isfinite(dg0[3]).all()


def test_geodesics_on_the_compiled_path_match_numpy_to_their_own_sensitivity():
    # Shots across f1's clamp kinks, through the band where its derivatives lose
    # digits, are sensitive: the numpy path itself, started 1e-14 away, ends up
    # to 2e-3 of the shot's span away. The compiled path must stay within that.
    fast = field(FUNCTIONS["f1"], vertices=1000)
    ref = dataclasses.replace(fast, jit=False)
    rng = np.random.default_rng(11)
    a = rng.random((200, 2)) * 0.8 + 0.1
    d = rng.normal(size=(len(a), 2))
    s1, s0 = geo.shoot(fast, a, d, 1.0), geo.shoot(ref, a, d, 1.0)
    moved = geo.shoot(ref, a + 1e-14, d, 1.0)
    assert np.array_equal(s1.ok, s0.ok) and s1.ok.all()
    span = np.abs(s0.end - a).max(axis=1)
    sensitivity = (np.abs(moved.end - s0.end).max(axis=1) / span).max()
    assert (np.abs(s1.end - s0.end).max(axis=1) / span).max() <= max(3.0 * sensitivity, 1e-6)
    p1, p0 = geo.shortest_parabola(fast, a, s0.end), geo.shortest_parabola(ref, a, s0.end)
    np.testing.assert_allclose(p1.length, p0.length, rtol=2e-5)


@dataclasses.dataclass(frozen=True)
class _NoScalarCode:
    """A component with the numpy interface only."""

    inner: Component
    key: str = "metric"

    def evaluate(self, pts, derivatives):
        return self.inner.evaluate(pts, derivatives)

    def sizes_at(self, pts):
        return self.inner.sizes_at(pts)


def test_a_component_without_scalar_code_keeps_the_numpy_path():
    comp = Component((1 + X**2, sympy.Integer(0), 2 + sympy.sin(Y)))
    fld = MetricField((_NoScalarCode(comp),))
    assert fld.scalar_source is None and fld.kernel is None
    pts = np.array([[0.5, 0.25]])
    g, _ = fld.evaluate(pts)
    np.testing.assert_allclose(g[0], [[1.25, 0.0], [0.0, 2 + math.sin(0.25)]], rtol=1e-15)
