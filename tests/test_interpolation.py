"""The interpolation metric (metric form ``interpolation:``) and the interpolation error report."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import sympy
from click.testing import CliRunner
from scipy.optimize import linprog

from curvimesh.cli import main
from curvimesh.errors import InputError, MetricError
from curvimesh.interpolation import (
    InterpolationMetric,
    X,
    Y,
    compile_function,
    cubic_shape,
    exponents,
    hessian_shape,
)
from curvimesh.interpolation_error import interpolation_error, reference_lattice
from curvimesh.io import write_mesh
from curvimesh.mesh import Mesh, to_p2_straight
from curvimesh.metric import UNIT_TRIANGLE_AREA, MetricField, density_integral, load_metric_text

# --------------------------------------------------------------------------- #
# Helpers                                                                      #
# --------------------------------------------------------------------------- #


def cubic_coefficients(poly: sympy.Expr) -> np.ndarray:
    """(f_xxx, f_xxy, f_xyy, f_yyy) of a cubic polynomial, as a (4, 1) array."""
    return np.array(
        [[float(sympy.diff(poly, *([X] * (3 - j) + [Y] * j)))] for j in range(4)], dtype=float
    )


def grid_mesh(n: int, order: int, warp: float = 0.0) -> Mesh:
    """Structured mesh of the unit square, n×n cells cut along a diagonal.

    ``order`` 2 gives P2 triangles; with ``warp`` > 0 every node (edge nodes
    included) is moved by the smooth map x + warp·sin(πx)sin(πy)(1, 1), which
    keeps the square and makes the P2 triangles curved (isoparametric).
    """
    t = np.linspace(0.0, 1.0, n + 1)
    gx, gy = np.meshgrid(t, t, indexing="ij")
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    mesh = Mesh(pts, tris, (0.0, 0.0, 1.0, 1.0))
    if order == 2:
        mesh = to_p2_straight(mesh)
    if warp:
        p = np.array(mesh.points)
        bump = warp * np.sin(np.pi * p[:, 0]) * np.sin(np.pi * p[:, 1])
        mesh = Mesh(p + bump[:, None], mesh.triangles, mesh.box)
    return mesh


def fitted_rate(hs: list[float], errors: list[float]) -> float:
    return float(np.polyfit(np.log(hs), np.log(errors), 1)[0])


EXP_SUM = "exp(x) + exp(y)"


def interpolation_yaml(function: str, **options: object) -> str:
    body = {"function": function, "vertices": 2000, "sizes": "[1.0e-6, 10]", **options}
    lines = "\n".join(f"    {k}: {v}" for k, v in body.items())
    return f"metric:\n  interpolation:\n{lines}\n"


# --------------------------------------------------------------------------- #
# Shapes                                                                       #
# --------------------------------------------------------------------------- #


def test_exponents_of_the_continuous_mesh_formula():
    for k in (1, 2):
        for p in (1.0, 2.0, 3.5):
            a, b = exponents(k, p)
            assert a == pytest.approx(p * (k + 1) / (2 * (p * (k + 1) + 2)))
            assert a == pytest.approx(b + 0.5)
    assert exponents(2, math.inf) == (0.5, 0.0)


@pytest.mark.parametrize("angle", [0.0, 0.4, 1.3, 2.9])
def test_a_pure_cube_gives_its_direction_and_size_and_the_largest_anisotropy(angle):
    n = (math.cos(angle), math.sin(angle))
    k = 5.0
    coef = cubic_coefficients(k * (n[0] * X + n[1] * Y) ** 3)  # d³f = 6k (n·u)³
    cos, sin, x_log, y_log = cubic_shape(coef, max_aspect=50.0)
    assert abs(cos[0] * n[0] + sin[0] * n[1]) == pytest.approx(1.0, abs=1e-12)
    assert math.exp(x_log[0]) == pytest.approx((6 * k) ** (2 / 3), rel=1e-12)
    assert math.exp((x_log[0] - y_log[0]) / 2) == pytest.approx(50.0, rel=1e-12)


@pytest.mark.parametrize(
    ("poly", "exact"), [(X**3 - 3 * X * Y**2, True), (X**3 + 3 * X * Y**2, False)]
)
@pytest.mark.parametrize("angle", [0.0, 0.3, 1.0])
def test_the_canonical_cubics_are_isotropic_in_any_orientation(poly, exact, angle):
    # x³ − 3xy² (three real roots) and x³ + 3xy² (one real root): each is, up to a
    # linear map, every cubic of its class; their optimal metrics are isotropic.
    # G is isotropic for both, so the frame is whatever rounding makes it: the
    # first is isotropic in every frame, the second only nearly so.
    c, s = math.cos(angle), math.sin(angle)
    rotated = poly.subs({X: c * X + s * Y, Y: -s * X + c * Y}, simultaneous=True)
    _, _, x_log, y_log = cubic_shape(cubic_coefficients(sympy.expand(rotated)), max_aspect=1e3)
    aspect = math.exp(abs(x_log[0] - y_log[0]) / 2)
    assert aspect == pytest.approx(1.0, abs=1e-9 if exact or angle == 0 else 0.02)


@pytest.mark.parametrize("eps", [1e-1, 1e-2, -1e-2, 1e-3])
def test_near_a_ridge_the_aspect_ratio_scales_as_the_square_root(eps):
    # x³/6 + ε x y²/2: element error terms h1³ and |ε| h1 h2² balance at h2/h1 = |ε|^(−1/2).
    coef = cubic_coefficients(X**3 / 6 + eps * X * Y**2 / 2)
    _, _, x_log, y_log = cubic_shape(coef, max_aspect=1e6)
    assert math.exp((x_log[0] - y_log[0]) / 2) == pytest.approx(abs(eps) ** -0.5, rel=1e-9)


def test_the_linear_program_against_a_general_solver():
    rng = np.random.default_rng(7)
    coef = rng.normal(size=(4, 60)) * np.exp(rng.normal(size=(1, 60)))
    coef[:, :10] *= rng.random((4, 10)) < 0.5  # some vanishing derivatives
    max_aspect = 30.0
    cos, sin, x_log, y_log = cubic_shape(coef, max_aspect=max_aspect)
    for p in range(coef.shape[1]):
        a, b, c, d = coef[:, p]
        e1, e2 = np.array([cos[p], sin[p]]), np.array([-sin[p], cos[p]])

        def form(u, v, w, a=a, b=b, c=c, d=d):
            t = np.zeros((2, 2, 2))
            t[0, 0, 0], t[1, 1, 1] = a, d
            t[0, 0, 1] = t[0, 1, 0] = t[1, 0, 0] = b
            t[0, 1, 1] = t[1, 0, 1] = t[1, 1, 0] = c
            return np.einsum("ijk,i,j,k->", t, u, v, w)

        terms = [form(e1, e1, e1), form(e2, e2, e2), form(e1, e1, e2), form(e1, e2, e2)]
        logs = [math.log(max(abs(v), 1e-300)) for v in terms]
        cap = 2 * math.log(max_aspect)
        # minimise X + Y: X >= 2/3 log|A|, Y >= 2/3 log|D|, 2X + Y >= 2 log|B|,
        # X + 2Y >= 2 log|C|, |X − Y| <= cap  (as A_ub z <= b_ub)
        a_ub = [[-1, 0], [0, -1], [-2, -1], [-1, -2], [1, -1], [-1, 1]]
        b_ub = [-2 / 3 * logs[0], -2 / 3 * logs[1], -2 * logs[2], -2 * logs[3], cap, cap]
        res = linprog([1, 1], A_ub=a_ub, b_ub=b_ub, bounds=[(None, None)] * 2)
        assert res.status == 0
        assert x_log[p] + y_log[p] == pytest.approx(res.fun, abs=1e-7)
        assert np.all(np.array(a_ub) @ [x_log[p], y_log[p]] <= np.array(b_ub) + 1e-7)


def test_the_unit_ball_bounds_the_cubic():
    # On the unit ball of Q, |s| <= h1 and |t| <= h2, so each of the four
    # terms of π is at most 1 in magnitude times its binomial: |π| <= 8.
    rng = np.random.default_rng(3)
    coef = rng.normal(size=(4, 200))
    cos, sin, x_log, y_log = cubic_shape(coef, max_aspect=1e8)
    theta = np.linspace(0, 2 * np.pi, 721)
    h1, h2 = np.exp(-x_log / 2), np.exp(-y_log / 2)
    s = np.cos(theta)[:, None] * h1
    t = np.sin(theta)[:, None] * h2
    u = s * cos - t * sin
    v = s * sin + t * cos
    a, b, c, d = coef
    pi_u = a * u**3 + 3 * b * u**2 * v + 3 * c * u * v**2 + d * v**3
    top = np.abs(pi_u).max(axis=0)
    assert top.max() <= 8.0
    assert top.min() > 0.1  # and the ball is not needlessly small


def test_hessian_shape_is_the_absolute_hessian():
    rng = np.random.default_rng(5)
    coef = rng.normal(size=(3, 50))
    cos, sin, x_log, y_log = hessian_shape(coef, max_aspect=1e9)
    for p in range(50):
        h = np.array([[coef[0, p], coef[1, p]], [coef[1, p], coef[2, p]]])
        w, v = np.linalg.eigh(h)
        q = np.exp([x_log[p], y_log[p]])
        np.testing.assert_allclose(np.sort(q), np.sort(np.abs(w)), rtol=1e-9)
        assert abs(cos[p] * v[0, 1] + sin[p] * v[1, 1]) == pytest.approx(1.0, abs=1e-9)


# --------------------------------------------------------------------------- #
# The metric field                                                             #
# --------------------------------------------------------------------------- #


@pytest.mark.parametrize(("function", "degree"), [("x**3 + 2*x", 2), ("x**2 - 3*x", 1)])
def test_a_one_dimensional_function_gives_uniform_strips(function, degree):
    # The derivative of order k + 1 is a constant along x only: every size
    # across x is the same, the sizes along y are HMAX, and the count of an
    # ideal mesh, (2/√3) · 1 / (hx · HMAX), is the target.
    n_target = 3000.0
    text = (
        f"metric:\n  interpolation:\n    function: {function}\n    degree: {degree}\n"
        f"    vertices: {n_target}\n    sizes: [1.0e-5, 0.25]\n"
    )
    fld = load_metric_text(text)
    pts = np.random.default_rng(0).random((50, 2))
    g = fld.tensor(pts)
    hx = 2 / math.sqrt(3) / (n_target * 0.25)
    np.testing.assert_allclose(g[:, 0, 0], 1 / hx**2, rtol=1e-6)
    np.testing.assert_allclose(g[:, 1, 1], 1 / 0.25**2, rtol=1e-6)
    np.testing.assert_allclose(g[:, 0, 1], 0.0, atol=1e-9 / hx**2)
    np.testing.assert_allclose(fld.sizes(pts), np.tile([hx, 0.25], (50, 1)), rtol=1e-6)


@pytest.mark.parametrize(
    ("degree", "norm", "q_exponent"),
    [(2, 2, 2 / 3), (2, 1, 2 / 3), (2, "inf", 2 / 3), (1, 1, 1.0), (1, 3, 1.0)],
)
def test_the_continuous_mesh_formula_in_closed_form(degree, norm, q_exponent):
    # f = e^x + e^y: Q = diag(e^(c x), e^(c y)) with c = 2/3 (P2, third derivatives)
    # or 1 (P1, Hessian), so M = D det(Q)^β Q and D = (√3/2) N / ∫∫ det(Q)^α have
    # closed forms. The clamps [1e-6, 10] are inactive.
    n_target = 2000
    p = math.inf if norm == "inf" else float(norm)
    fld = field_of(sympy.exp(X) + sympy.exp(Y), degree=degree, norm=p, vertices=n_target)
    alpha, beta = exponents(degree, p)
    k = alpha * q_exponent
    integral = ((math.exp(k) - 1) / k) ** 2  # ∫∫ e^(k(x + y)) over the unit square
    scale = math.sqrt(3) / 2 * n_target / integral
    pts = np.random.default_rng(1).random((40, 2))
    x, y = pts[:, 0], pts[:, 1]
    common = scale * np.exp(beta * q_exponent * (x + y))
    g = fld.tensor(pts)
    np.testing.assert_allclose(g[:, 0, 0], common * np.exp(q_exponent * x), rtol=1e-7)
    np.testing.assert_allclose(g[:, 1, 1], common * np.exp(q_exponent * y), rtol=1e-7)
    np.testing.assert_allclose(g[:, 0, 1], 0.0, atol=1e-7 * g[:, 0, 0].max())
    # the ideal vertex count, by the metric module's own quadrature
    ideal = density_integral(fld) / UNIT_TRIANGLE_AREA / 2
    assert ideal == pytest.approx(n_target, rel=1e-3)


def test_the_target_is_met_with_active_clamps():
    text = """
metric:
  interpolation:
    function: (1 + tanh(50*((y - 0.5) - 0.3*sin(3*pi*x))))/2
    degree: 2
    norm: 2
    vertices: 4000
    sizes: [1e-4, 0.5]
"""
    fld = load_metric_text(text)
    sizes = fld.sizes(fld.sample_points(101))
    assert sizes.max() == pytest.approx(0.5)  # the flat regions
    assert sizes.min() < 0.01
    ideal = density_integral(fld, cells=256) / UNIT_TRIANGLE_AREA / 2
    assert ideal == pytest.approx(4000, rel=0.02)


def five_point_derivative(fld: MetricField, pts: np.ndarray, h: float) -> np.ndarray:
    """∂g/∂x_k by the fourth-order stencil (−f(2h) + 8f(h) − 8f(−h) + f(−2h)) / 12h."""
    out = np.empty((len(pts), 2, 2, 2))
    for k in range(2):
        e = np.zeros(2)
        e[k] = h
        g = [fld.tensor(pts + j * e) for j in (2, 1, -1, -2)]
        out[..., k] = (-g[0] + 8 * g[1] - 8 * g[2] + g[3]) / (12 * h)
    return out


def field_of(function: sympy.Expr, **options: object) -> MetricField:
    """The interpolation metric alone, on a coarse normalisation grid (fast)."""
    options = {"vertices": 2000, "sizes": (1e-6, 10.0), "quadrature_cells": 32, **options}
    return MetricField((InterpolationMetric(function, **options),))


def test_derivatives_in_closed_form():
    fld = field_of(sympy.exp(X) + sympy.exp(Y))
    _, beta = exponents(2, 2.0)
    pts = np.random.default_rng(2).random((30, 2)) * 0.9 + 0.05
    g, dg = fld.evaluate(pts, derivatives=True)
    # g11 ∝ e^(β c (x+y) + c x), g22 ∝ e^(β c (x+y) + c y), c = 2/3
    c = 2 / 3
    np.testing.assert_allclose(dg[:, 0, 0, 0], g[:, 0, 0] * (beta * c + c), rtol=1e-6)
    np.testing.assert_allclose(dg[:, 0, 0, 1], g[:, 0, 0] * beta * c, rtol=1e-6)
    np.testing.assert_allclose(dg[:, 1, 1, 0], g[:, 1, 1] * beta * c, rtol=1e-6)
    np.testing.assert_allclose(dg[:, 1, 1, 1], g[:, 1, 1] * (beta * c + c), rtol=1e-6)


@pytest.mark.parametrize("degree", [1, 2])
def test_derivatives_against_a_fourth_order_stencil(degree):
    fld = field_of(sympy.sin(2 * X + Y) * sympy.exp(X * Y) + X**4, degree=degree)
    pts = np.random.default_rng(4).random((25, 2)) * 0.9 + 0.05
    _, dg = fld.evaluate(pts, derivatives=True)
    ref = five_point_derivative(fld, pts, 1e-4)
    scale = np.abs(ref).max(axis=(1, 2, 3))[:, None, None, None]
    np.testing.assert_allclose(dg, ref, atol=1e-5 * scale.max(), rtol=1e-5)
    assert np.all(np.abs(dg - ref) <= 1e-5 * scale)


def test_geodesics_shoot_through_the_field():
    from curvimesh.geodesic import shoot

    fld = field_of(sympy.exp(X) + sympy.exp(Y), vertices=200)
    shot = shoot(fld, np.array([[0.3, 0.4]]), np.array([[1.0, 0.5]]), 1.0)
    assert shot.ok[0] and np.isfinite(shot.end).all()


# --------------------------------------------------------------------------- #
# Loading                                                                      #
# --------------------------------------------------------------------------- #


def test_the_form_defaults_and_uses_parameters_and_definitions():
    text = """
domain: {box: [[0, 0], [2, 1]]}
parameters: {k: 3}
definitions:
  s: k*x
metric:
  interpolation: {function: exp(s) + y**3, vertices: 1.5e3}
"""
    fld = load_metric_text(text)
    (comp,) = fld.components
    assert isinstance(comp, InterpolationMetric)
    assert (comp.degree, comp.norm, comp.vertices) == (2, 2.0, 1500.0)
    assert comp.sizes == pytest.approx((2e-4, 0.5))  # 1e-4 of the long side, half the short
    assert comp.box == (0.0, 0.0, 2.0, 1.0)
    assert comp.key == "metric.interpolation"
    assert comp.gradation == 3.0


@pytest.mark.parametrize(
    ("text", "value"), [("off", None), ("'off'", None), ("null", None), ("1.5", 1.5)]
)
def test_gradation_is_a_number_or_off(text, value):
    fld = load_metric_text(interpolation_yaml(EXP_SUM, gradation=text))
    assert fld.components[0].gradation == value


def test_the_form_in_an_intersection():
    text = f"""
metric:
  intersection:
    - interpolation: {{function: {EXP_SUM}, vertices: 300}}
    - isotropic: 0.2
"""
    fld = load_metric_text(text)
    g, dg = fld.evaluate(np.array([[0.5, 0.5]]), derivatives=True)
    assert np.isfinite(g).all() and np.isfinite(dg).all()
    assert np.linalg.eigvalsh(g[0]).min() >= 1 / 0.2**2 * (1 - 1e-9)


@pytest.mark.parametrize(
    ("body", "key", "words"),
    [
        ("{degree: 2, vertices: 100}", "metric.interpolation.function", "missing"),
        ("{function: x**3}", "metric.interpolation.vertices", "missing"),
        ("{function: x**3, vertices: 100, degree: 3}", ".degree", "1 or 2"),
        ("{function: x**3, vertices: 100, degree: true}", ".degree", "1 or 2"),
        ("{function: x**3, vertices: 100, norm: 0.5}", ".norm", ">= 1"),
        ("{function: x**3, vertices: 100, norm: two}", ".norm", "two"),
        ("{function: x**3, vertices: -4}", ".vertices", "positive"),
        ("{function: x**3, vertices: 100, sizes: [0.5, 0.1]}", ".sizes", "HMIN <= HMAX"),
        ("{function: x**3, vertices: 100, sizes: [0.1]}", ".sizes", "[HMIN, HMAX]"),
        ("{function: x**3, vertices: 100, size: [0.1, 1]}", ".size", "did you mean 'sizes'"),
        ("{function: x.real, vertices: 100}", ".function", "attribute"),
        ("{function: z**3, vertices: 100}", ".function", "z"),
        ("{function: x**3, vertices: 1e9, sizes: [0.01, 0.5]}", ".vertices", "cannot be reached"),
        ("{function: x**3, vertices: 100, gradation: 1}", ".gradation", "> 1 or off"),
        ("{function: x**3, vertices: 100, gradation: steep}", ".gradation", "steep"),
        ("{function: x**3, vertices: 100, gradation: true}", ".gradation", "number"),
        ("{function: x**3, vertices: 100, gradation: .inf}", ".gradation", "> 1 or off"),
        ("[x**3, 100]", "metric.interpolation", "mapping"),
    ],
)
def test_the_loader_rejects_bad_forms_in_one_line(body, key, words):
    with pytest.raises(MetricError) as info:
        load_metric_text(f"metric:\n  interpolation: {body}\n", source="m.yaml")
    msg = str(info.value)
    assert "\n" not in msg
    assert msg.startswith("m.yaml: ")
    assert key in msg and words in msg


@pytest.mark.parametrize("text", ["inf", ".inf"])
def test_infinity_norm_is_accepted_as_inf(text):
    fld = load_metric_text(interpolation_yaml(EXP_SUM, norm=text))
    assert fld.components[0].norm == math.inf


# --------------------------------------------------------------------------- #
# Interpolation error                                                          #
# --------------------------------------------------------------------------- #


def test_the_reference_lattice():
    pts = reference_lattice(16)
    assert len(pts) == 17 * 18 // 2
    assert pts.min() == 0.0 and (pts.sum(axis=1) <= 1 + 1e-15).all()


@pytest.mark.parametrize("order", [1, 2])
def test_polynomials_of_the_degree_are_interpolated_to_rounding(order):
    f = (
        (lambda p: 3 * p[:, 0] - 2 * p[:, 1] + 1)
        if order == 1
        else (lambda p: p[:, 0] ** 2 - 3 * p[:, 0] * p[:, 1] + 0.5 * p[:, 1] ** 2 + p[:, 1])
    )
    err = interpolation_error(f, grid_mesh(7, order))
    assert err.l2 < 1e-14 and err.linf < 1e-14


def test_the_error_of_a_cubic_on_one_triangle_against_exact_integration():
    # e = u³ − I(u³) on the reference P2 triangle: the exact ∫ e² by sympy.
    u, v = sympy.symbols("u v")
    nodes = [(0, 0), (1, 0), (0, 1), (sympy.Rational(1, 2), 0)]
    nodes += [(sympy.Rational(1, 2), sympy.Rational(1, 2)), (0, sympy.Rational(1, 2))]
    l0, l1, l2 = 1 - u - v, u, v
    shapes = [l0 * (2 * l0 - 1), l1 * (2 * l1 - 1), l2 * (2 * l2 - 1), 4 * l0 * l1]
    shapes += [4 * l1 * l2, 4 * l2 * l0]
    interp = sum(a**3 * n for (a, _), n in zip(nodes, shapes, strict=True))
    e = sympy.expand(u**3 - interp)
    exact = sympy.integrate(sympy.integrate(e**2, (v, 0, 1 - u)), (u, 0, 1))
    e_fn = sympy.lambdify((u, v), e)
    t = np.linspace(0, 1, 801)
    uu, vv = np.meshgrid(t, t)
    inside = uu + vv <= 1
    true_max = np.abs(e_fn(uu[inside], vv[inside])).max()

    tri = Mesh([[0, 0], [1, 0], [0, 1], [0.5, 0], [0.5, 0.5], [0, 0.5]], [[0, 1, 2, 3, 4, 5]])
    err = interpolation_error(lambda p: p[:, 0] ** 3, tri)
    assert err.l2**2 == pytest.approx(float(exact), rel=1e-12)
    assert true_max * (1 - 1e-2) <= err.linf <= true_max * (1 + 1e-12)


SMOOTH = "sin(3*x) * cos(2*y) + exp(x*y)"


@pytest.mark.parametrize(("order", "warp", "rate"), [(2, 0.0, 3.0), (2, 0.08, 3.0), (1, 0.0, 2.0)])
def test_the_error_converges_at_the_order_of_the_interpolant(order, warp, rate):
    f = compile_function(SMOOTH)
    ns = [4, 8, 16, 32]
    errs = [interpolation_error(f, grid_mesh(n, order, warp)) for n in ns]
    hs = [1 / n for n in ns]
    assert fitted_rate(hs, [e.l2 for e in errs]) == pytest.approx(rate, abs=0.1)
    assert fitted_rate(hs, [e.linf for e in errs]) == pytest.approx(rate, abs=0.25)


def test_the_quadrature_is_converged():
    f = compile_function(SMOOTH)
    mesh = grid_mesh(6, 2, 0.08)
    assert interpolation_error(f, mesh).l2 == pytest.approx(
        interpolation_error(f, mesh, order=14).l2, rel=1e-10
    )


def test_a_function_undefined_on_the_mesh_is_an_input_error():
    f = compile_function("log(x - 0.5)")
    with pytest.raises(InputError, match="not finite at"):
        interpolation_error(f, grid_mesh(4, 2))


# --------------------------------------------------------------------------- #
# The report command                                                           #
# --------------------------------------------------------------------------- #


@pytest.fixture
def mesh_and_metric(tmp_path):
    mesh_path = tmp_path / "grid.msh"
    write_mesh(mesh_path, grid_mesh(6, 2))
    metric_path = tmp_path / "iso.yaml"
    metric_path.write_text("metric: {isotropic: 0.2}\n")
    return str(mesh_path), str(metric_path)


def test_report_function_gives_the_error_of_a_quadratic_at_rounding(mesh_and_metric):
    mesh_path, metric_path = mesh_and_metric
    args = ["report", mesh_path, "--metric", metric_path, "--json"]
    res = CliRunner().invoke(main, [*args, "--function", "x**2 - 3*x*y + y**2/2 + 1"])
    assert res.exit_code == 0, res.output
    err = json.loads(res.output)["interpolation_error"]
    assert err["l2"] < 1e-14 and err["linf"] < 1e-14
    res = CliRunner().invoke(main, [*args, "--function", "sin(5*x)"])
    err = json.loads(res.output)["interpolation_error"]
    assert 1e-6 < err["l2"] < err["linf"] < 1e-1
    table = CliRunner().invoke(main, [*args[:-1], "--function", "sin(5*x)"])
    assert "interpolation error" in table.output


def test_report_rejects_a_bad_function_in_one_line(mesh_and_metric):
    mesh_path, metric_path = mesh_and_metric
    res = CliRunner().invoke(
        main, ["report", mesh_path, "--metric", metric_path, "--function", "__import__('os')"]
    )
    assert res.exit_code == 2
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and "--function" in lines[0]
