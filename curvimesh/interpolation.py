"""The metric of a function's interpolation error (SPEC section 2, ``interpolation:``).

Given a function f of (x, y), a polynomial degree k (1 or 2), an L^p norm
(1 <= p <= inf) and a target vertex count N, :class:`InterpolationMetric` is
the metric field whose unit meshes approximately minimise the L^p error of
the degree-k Lagrange interpolant of f among meshes of about N vertices.
It is built in four steps, all vectorised over points.

1. **Local shape Q(x).** The interpolation error of degree k on a small
   element is, to leading order, that of the homogeneous Taylor term of
   degree k + 1 (the interpolant reproduces every polynomial of degree k).

   * k = 1: the quadratic form uᵀ H u of the Hessian; Q = |H|, the Hessian
     with its eigenvalues replaced by their absolute values (the classical
     choice; Frey & George, "Mesh generation", ch. 10; Loseille & Alauzet,
     "Continuous mesh framework", SIAM J. Numer. Anal. 49, 2011).

   * k = 2: the cubic form π(u) = d³f(x)[u, u, u] = a u³ + 3b u²v + 3c uv² + d v³
     with a = f_xxx, b = f_xxy, c = f_xyy, d = f_yyy. Its level sets are not
     ellipses, so some metric has to be fitted to it. Here:

     - the *frame* is the eigenbasis (e₁ of the larger eigenvalue) of the
       contraction G_il = Σ_jk T_ijk T_ljk of the derivative tensor with itself,
       a rotation-covariant, smooth function of d³f; for a ridge
       f = φ(n·x) it is exactly (n, n⊥), and an x²y perturbation of a pure
       cube, which to first order only tilts the ridge, is absorbed by it;
     - in that frame π(s e₁ + t e₂) = A s³ + 3B s²t + 3C st² + D t³ and, on an
       element of sizes h₁, h₂ along e₁, e₂, the error is bounded by a constant
       times the largest of |A|h₁³, |B|h₁²h₂, |C|h₁h₂², |D|h₂³ (affine scaling
       of each monomial; the binomial 3s are left out, which makes the two
       canonical forms x³ − 3xy² and x³ + 3xy² isotropic, as their optimal
       metrics are). The sizes are the largest element area h₁h₂ with all
       four terms <= 1: with q_i = h_i⁻², a linear program in (log q₁, log q₂)
       with four constraints (plus the anisotropy cap below), solved exactly
       by enumerating its vertices (:func:`cubic_shape`).

     This is the directional analysis of Cao ("An interpolation error estimate
     in R² based on the anisotropic measures of higher derivatives", Math.
     Comp. 77, 2008) and of Mirebeau ("Optimal meshes for finite elements of
     arbitrary order", Constr. Approx. 32, 2010), who shows that the optimal
     error constant is, up to fixed factors, an invariant of the cubic (for
     k = 2 its discriminant to the power 1/4, zero for a double root, where
     the optimal elements are unboundedly stretched). Compared with the
     simpler choices: sizes from |∂³f/∂t³| along its maximising direction and
     its perpendicular fail on x³ − 3xy² (the perpendicular value is 0 while
     the form is isotropic) and jump where two maxima swap; the cube root of G
     is smooth but gives a near-ridge cubic x³ + 3εxy² the aspect ratio
     ε^(−1/3) instead of the optimal ε^(−1/2). The linear program is exact
     for ridges (x³: sizes (1/|A|)^(1/3) across, unbounded along), isotropic
     for x³ − 3xy² and x³ + 3xy² (the latter within 2 % in other orientations:
     G is isotropic there and the frame arbitrary), has the ε^(−1/2) scaling
     near ridges, and on random cubic forms its unit ball is, after scaling
     to fit inside {|π| <= 1}, within a median 4 % (worst about 85 %) of the
     area of the best inscribed ellipse, found by brute force.

   Both shapes are capped at the anisotropy HMAX/HMIN that the size clamp
   allows anyway, which keeps them finite where a direction is flat (x³
   along y); a point where every derivative vanishes gets q = 0, hence HMAX.

2. **Continuous-mesh scaling** (Loseille & Alauzet 2011; Mirebeau 2010 for
   k > 1). With n = 2, the metric minimising the L^p error of a mesh of
   complexity C = ∫ sqrt(det M) is

       M = D · det(Q)^β · Q,   β = −1 / (p(k+1) + n),
       D = C / ∫ det(Q)^α,     α = p(k+1) / (2 (p(k+1) + n)),

   (p = inf: α = 1/2, β = 0), since sqrt(det M) = D det(Q)^α. An ideal
   mesh of unit equilateral triangles has C / (√3/4) triangles and half as
   many vertices, so C = (√3/2) N.

3. **Clamp** the sizes h_i = μ_i^(−1/2) of the eigenvalues μ_i of M to
   [HMIN, HMAX], then solve (Brent) for the scalar D that gives the clamped
   metric its N ideal vertices: with inactive clamps this is the D above;
   with active ones it keeps the vertex count the user asked for. The integral
   is a tensor Gauss–Legendre rule on a fine grid of the box
   (``quadrature_cells``² cells of 4×4 points, 128² by default), computed
   once at construction: for tanh fronts of width 1/50 and 1/100 the scale D
   moves by less than 0.1 % between 96² and 512² cells.

4. **Gradation** (``gradation: γ``, 3 by default in the YAML form; ``off``, or
   ``None`` here, for the raw field). The sizes of step 3 follow the tail of
   d³f: across a tanh front they grow exponentially, from 0.3 % of the box to
   the clamp HMAX within a tenth of it, faster than a mesh can follow, and the
   meshes of the convergence study kept edges of metric length up to 4 there,
   in triangles that held 90 % of the squared error. The field used is
   M ∩ G, G the field graded so that each of its sizes grows at most by γ − 1
   times the distance (:mod:`curvimesh.gradation`, a background grid of the
   box), and the scale D is solved again (secant steps, to 0.1 %) so that
   M ∩ G keeps the N ideal vertices. Measured with bench/convergence.py's
   pipeline (L2 error of the fitted curved mesh; ungraded → γ = 2 → γ = 3):
   f1 at 32,000 vertices 7.9e-8 → 2.3e-8 → 2.3e-8, f1 at 4,000 7.7e-7 →
   8.5e-7 → 7.1e-7, f3 at 8,000 1.6e-7 → 1.2e-7 → 1.2e-7. The cost is a
   slightly coarser front (at 4,000 vertices on f1, D falls by e^0.35, sizes
   × 1.19, for γ = 2 and e^0.15 for γ = 3), hence the default γ = 3.

The metric's spatial derivatives, needed by the geodesic integrator, are
central differences of the whole construction (step ``min(HMIN/100, 1e-6 ×
box size)``: truncation error (step/scale)² and round-off about 1e-16/step,
both far below 1e-6 relative where the metric is smooth). The construction is
continuous; it has kinks where the clamp or a constraint of the linear
program switches, and may jump, by a bounded factor, at isolated points where
G is isotropic and the frame is undefined.

The metric models the error of straight-sided elements. A curved element adds
to d³(f∘x) the term 3 d²f(x', x'') of its quadratic map x(ξ), which no metric
sees: edges bent along the geodesics of this metric can raise the error where
f'' is large (``bench/convergence.py`` measures it).
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
import sympy
from numpy.typing import NDArray

from curvimesh import kernels
from curvimesh.errors import ExpressionError, InputError, MetricError
from curvimesh.expressions import (
    parse_expression,
    scalar_function,
    smooth_minmax,
    split_list_hint,
)
from curvimesh.gradation import GradedGrid, graded_grid, grid_nodes
from curvimesh.tensors import intersect_components

__all__ = [
    "DEGREES",
    "KEYS",
    "InterpolationMetric",
    "compile_function",
    "cubic_shape",
    "exponents",
    "hessian_shape",
    "parse_interpolation",
    "tensor_from_frame",
]

X, Y = sympy.symbols("x y", real=True)

#: Polynomial degrees of the interpolant that the metric supports.
DEGREES = (1, 2)

#: Keys of the ``interpolation:`` form (``function`` and ``vertices`` required).
KEYS = ("function", "degree", "norm", "vertices", "sizes", "gradation")

#: Default gradation γ of the ``interpolation:`` form (:mod:`curvimesh.gradation`).
GRADATION = 3.0

#: The constant of an ideal unit mesh: vertices = (2/√3) ∫ sqrt(det M).
_VERTICES_PER_AREA = 2.0 / math.sqrt(3.0)

#: Floor of |derivative| before logarithms: a vanishing term costs nothing.
_TINY = 1e-300


# --------------------------------------------------------------------------- #
# Pure kernels                                                                 #
# --------------------------------------------------------------------------- #


def exponents(degree: int, norm: float) -> tuple[float, float]:
    """Continuous-mesh exponents (α, β) of the L^p-optimal metric in 2D.

    α = p(k+1) / (2(p(k+1) + 2)) and β = −1/(p(k+1) + 2), and (1/2, 0) for
    p = inf (Loseille & Alauzet 2011). Always α = β + 1/2.

    >>> exponents(1, 2)
    (0.3333333333333333, -0.16666666666666666)
    >>> exponents(2, math.inf)
    (0.5, 0.0)
    """
    if math.isinf(norm):
        return 0.5, 0.0
    s = norm * (degree + 1)
    return s / (2.0 * (s + 2.0)), -1.0 / (s + 2.0)


def _frame(g11: NDArray, g12: NDArray, g22: NDArray) -> tuple[NDArray, NDArray]:
    """Unit eigenvector (cos φ, sin φ) of the larger eigenvalue of [[g11, g12], [g12, g22]].

    By the half-angle formulas from cos 2φ and sin 2φ, without trigonometric
    functions; (1, 0) where the matrix is isotropic.
    """
    half = 0.5 * (g11 - g22)
    radius = np.hypot(half, g12)
    cos2 = np.divide(half, radius, out=np.ones_like(half), where=radius > 0.0)
    cos = np.sqrt(0.5 + 0.5 * cos2)
    sin = np.copysign(np.sqrt(0.5 - 0.5 * cos2), g12)
    return cos, sin


def cubic_shape(coef: NDArray, *, max_aspect: float) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Shape metric of the cubic form a u³ + 3b u²v + 3c uv² + d v³ (see the module).

    ``coef`` is ``(4, n)``: rows a = f_xxx, b = f_xxy, c = f_xyy, d = f_yyy.
    Returns the frame e₁ = (cos φ, sin φ) as two ``(n,)`` arrays, and ``X, Y``
    ``(n,)``, the logs of the eigenvalues q₁, q₂ of Q along e₁ and
    e₂ = (−sin φ, cos φ): the solution of

        minimise X + Y  subject to  X >= (2/3) log|A|,  Y >= (2/3) log|D|,
        2X + Y >= 2 log|B|,  X + 2Y >= 2 log|C|,  |X − Y| <= 2 log max_aspect,

    with A, B, C, D the coefficients in the frame. In t = X − Y and S = X + Y
    the objective S(t) is the maximum of four affine functions of t, two
    decreasing and two increasing: its minimum over |t| <= 2 log max_aspect is
    at a crossing of a decreasing and an increasing one or at an end.
    Written as a few operations on whole arrays: it is called on a handful of
    points at a time by the geodesic integrator.

    A pure cube has its fine size 1/|A|^(1/3) across the ridge and the
    largest anisotropy along it; x³ − 3xy² is isotropic:

    >>> coef = np.array([[8.0, 1.0], [0.0, 0.0], [0.0, -1.0], [0.0, 0.0]])
    >>> cos, sin, X, Y = cubic_shape(coef, max_aspect=100.0)
    >>> np.exp(-X / 2).round(6).tolist(), np.exp((X - Y) / 2).round(6).tolist()
    ([0.5, 1.0], [100.0, 1.0])
    """
    a, b, c, d = coef
    # G = Σ_jk T_ijk T_ljk of the derivative tensor T (T_111 = a, T_112 = b, ...)
    g11 = a * a + 2.0 * b * b + c * c
    g12 = a * b + 2.0 * b * c + c * d
    g22 = b * b + 2.0 * c * c + d * d
    cos, sin = _frame(g11, g12, g22)
    m0, m1 = cos * cos * cos, cos * cos * sin  # the monomials p³, p²q, pq², q³ of e₁ = (p, q)
    m2, m3 = cos * sin * sin, sin * sin * sin
    # |A|, |D|, |B|, |C| in the frame, e₂ = (−q, p): A = π(e₁), D = π(e₂),
    # B = ∇π(e₁)·e₂ / 3, C = ∇π(e₂)·e₁ / 3, then their logs (the LP's right-hand sides)
    v = np.empty((4, len(a)))
    v[0] = a * m0 + 3.0 * (b * m1 + c * m2) + d * m3
    v[1] = d * m0 - a * m3 + 3.0 * (b * m2 - c * m1)
    v[2] = b * (m0 - 2.0 * m2) + c * (2.0 * m1 - m3) + d * m2 - a * m1
    v[3] = c * (m0 - 2.0 * m2) + b * (m3 - 2.0 * m1) + a * m2 + d * m1
    np.abs(v, out=v)
    np.maximum(v, _TINY, out=v)
    np.log(v, out=v)
    # constraints X >= va, Y >= vd, 2X + Y >= vb, X + 2Y >= vc
    va, vd, vb, vc = (2.0 / 3.0) * v[0], (2.0 / 3.0) * v[1], 2.0 * v[2], 2.0 * v[3]
    # in t = X − Y: S >= 2va − t, 2vd + t, (2/3)vb − t/3, (2/3)vc + t/3. Candidate
    # t: the four crossings of a decreasing and an increasing bound, and the ends
    cap = 2.0 * math.log(max_aspect)
    t = np.empty((6, len(a)))
    t[0] = va - vd
    t[1] = 1.5 * va - 0.5 * vc
    t[2] = 0.5 * vb - 1.5 * vd
    t[3] = vb - vc
    t[4], t[5] = -cap, cap
    np.clip(t, -cap, cap, out=t)
    s = np.maximum(2.0 * va - t, 2.0 * vd + t)
    np.maximum(s, (2.0 / 3.0) * vb - t / 3.0, out=s)
    np.maximum(s, (2.0 / 3.0) * vc + t / 3.0, out=s)
    best = (s.argmin(axis=0), np.arange(len(a)))
    s, t = s[best], t[best]
    return cos, sin, 0.5 * (s + t), 0.5 * (s - t)


def hessian_shape(coef: NDArray, *, max_aspect: float) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Shape metric |H| of the Hessian, as (cos φ, sin φ, X, Y) like :func:`cubic_shape`.

    ``coef`` is ``(3, n)``: rows f_xx, f_xy, f_yy. e₁ = (cos φ, sin φ) is the
    eigenvector of the larger eigenvalue of H, X and Y the logs of the absolute
    eigenvalues along it and across it, the smaller raised so that
    |X − Y| <= 2 log max_aspect.

    >>> cos, sin, X, Y = hessian_shape(np.array([[2.0], [0.0], [-8.0]]), max_aspect=100.0)
    >>> [float(cos[0]), float(sin[0])], np.exp([X[0], Y[0]]).round(12).tolist()
    ([1.0, 0.0], [2.0, 8.0])
    """
    fxx, fxy, fyy = coef
    mean = 0.5 * (fxx + fyy)
    radius = np.hypot(0.5 * (fxx - fyy), fxy)
    cos, sin = _frame(fxx, fxy, fyy)
    x_log, y_log = np.log(np.maximum(np.abs([mean + radius, mean - radius]), _TINY))
    floor = np.maximum(x_log, y_log) - 2.0 * math.log(max_aspect)
    return cos, sin, np.maximum(x_log, floor), np.maximum(y_log, floor)


def tensor_from_frame(
    cos: NDArray, sin: NDArray, l1: NDArray, l2: NDArray
) -> tuple[NDArray, NDArray, NDArray]:
    """Metric (g11, g12, g22) with eigenvalue l1 along (cos φ, sin φ) and l2 across it.

    The sizes along the two directions are l1^(−1/2) and l2^(−1/2):

    >>> g = tensor_from_frame(np.array([0.0]), np.array([1.0]), np.array([4.0]), np.array([16.0]))
    >>> [float(v[0]) + 0.0 for v in g]
    [16.0, 0.0, 4.0]
    """
    cc, ss, cs = cos * cos, sin * sin, (l1 - l2) * cos * sin
    return l1 * cc + l2 * ss, cs, l1 * ss + l2 * cc


# --------------------------------------------------------------------------- #
# Functions of (x, y)                                                          #
# --------------------------------------------------------------------------- #


def _lambdify(exprs: list[sympy.Expr]) -> Callable[[NDArray, NDArray], NDArray]:
    """Vectorised numpy function of (x, y) ``(n,)`` returning ``(len(exprs), n)``."""
    fn = sympy.lambdify((X, Y), exprs, modules="numpy", cse=True)

    def evaluate(x: NDArray, y: NDArray) -> NDArray:
        out = np.empty((len(exprs), *np.shape(x)))
        with np.errstate(all="ignore"):
            for i, value in enumerate(fn(x, y)):
                out[i] = value  # a constant derivative comes back as a scalar
        return out

    return evaluate


def _derivatives(expr: sympy.Expr, order: int) -> list[sympy.Expr]:
    """All partial derivatives of order ``order``, ∂^order f / ∂x^(order−j) ∂y^j, j = 0..order.

    Delta functions (from differentiating abs) are dropped: their support has
    measure zero. Raises ValueError if sympy cannot differentiate in closed form.
    """
    expr = smooth_minmax(expr)
    out = []
    for j in range(order + 1):
        term = sympy.diff(expr, *([X] * (order - j) + [Y] * j))
        term = term.replace(sympy.DiracDelta, lambda *_: sympy.Integer(0))
        if term.has(sympy.Derivative, sympy.Subs, sympy.re, sympy.im):
            raise ValueError("the function has no closed-form derivatives here")
        out.append(term)
    return out


def compile_function(text: str, *, source: str = "function") -> Callable[[NDArray], NDArray]:
    """Parse an expression over x, y (never evaluated as Python) into f(points ``(n, 2)``) ``(n,)``.

    Raises :class:`InputError` ``"{source}: message"`` for a rejected expression.

    >>> f = compile_function("x**2 + 3*y")
    >>> f(np.array([[1.0, 2.0], [0.5, 0.0]])).tolist()
    [7.0, 0.25]
    """
    try:
        expr = parse_expression(text, {"x": X, "y": Y})
    except ExpressionError as exc:
        raise InputError(f"{source}: {exc}") from None
    fn = _lambdify([smooth_minmax(expr)])

    def f(points: NDArray) -> NDArray:
        points = np.asarray(points, dtype=float).reshape(-1, 2)
        return fn(points[:, 0], points[:, 1])[0]

    return f


# --------------------------------------------------------------------------- #
# The metric component                                                         #
# --------------------------------------------------------------------------- #


def _box_rule(
    box: tuple[float, float, float, float], cells: int, order: int = 4
) -> tuple[NDArray, NDArray]:
    """Tensor Gauss–Legendre points ``(cells² order², 2)`` and weights over the box."""
    xmin, ymin, xmax, ymax = box
    xg, wg = np.polynomial.legendre.leggauss(order)
    t = (xg + 1.0) / 2.0
    px = (np.linspace(xmin, xmax, cells + 1)[:-1, None] + (xmax - xmin) / cells * t).ravel()
    py = (np.linspace(ymin, ymax, cells + 1)[:-1, None] + (ymax - ymin) / cells * t).ravel()
    wx = np.tile(wg / 2.0, cells) * (xmax - xmin) / cells
    wy = np.tile(wg / 2.0, cells) * (ymax - ymin) / cells
    gx, gy = np.meshgrid(px, py, indexing="ij")
    return np.column_stack([gx.ravel(), gy.ravel()]), np.outer(wx, wy).ravel()


class ScalarFunction:
    """A function f of (x, y): ``f(points)`` maps ``(n, 2)`` points to ``(n,)`` values
    (numpy), and ``scalar`` is f compiled for one point, (x, y) ↦ f
    (:data:`curvimesh.kernels.SIG_F`), for the kernels, or None."""

    def __init__(self, values: Callable[[NDArray], NDArray], scalar: object = None) -> None:
        self._values = values
        self.scalar = scalar

    def __call__(self, pts: NDArray) -> NDArray:
        return self._values(pts)


#: Compiled scalar forms of functions, by their source (:meth:`InterpolationMetric.error_function`).
_COMPILED: dict[str, object] = {}


@dataclass(frozen=True)
class InterpolationMetric:
    """The L^p interpolation-error metric of a function (see the module docstring).

    A metric component with the interface of :class:`curvimesh.metric.Component`:
    :meth:`evaluate`, :meth:`sizes_at`, :meth:`scalar_source` and :attr:`key`. Construction compiles
    the derivatives of ``function`` and fixes the scale from the box
    quadrature; it raises ValueError if the function has no closed-form
    derivatives, is not finite on the box, or if ``vertices`` is out of the
    reach of the size clamp.

    ``degree`` is k (1 or 2), ``norm`` is p (>= 1, or ``math.inf``),
    ``vertices`` the target N, ``sizes`` (HMIN, HMAX), ``box`` the domain
    (xmin, ymin, xmax, ymax), ``gradation`` γ > 1 (step 4 of the module) or None
    for the raw field (the default here; the YAML form's is :data:`GRADATION`).
    """

    function: sympy.Expr
    degree: int = 2
    norm: float = 2.0
    vertices: float = 4000.0
    sizes: tuple[float, float] = (1e-4, 0.5)
    box: tuple[float, float, float, float] = (0.0, 0.0, 1.0, 1.0)
    key: str = "metric.interpolation"
    quadrature_cells: int = 128
    gradation: float | None = None
    _derivatives: tuple[sympy.Expr, ...] = field(init=False, repr=False, compare=False)
    _fn: Callable = field(init=False, repr=False, compare=False)
    _values: Callable = field(init=False, repr=False, compare=False)
    _log_scale: float = field(init=False, repr=False, compare=False)
    _shifts: NDArray = field(init=False, repr=False, compare=False)
    _grid: GradedGrid | None = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.degree not in DEGREES:
            raise ValueError(f"degree must be 1 or 2, got {self.degree!r}")
        if not self.norm >= 1.0:
            raise ValueError(f"norm must be at least 1 (or inf), got {self.norm!r}")
        hmin, hmax = self.sizes
        if not (0.0 < hmin <= hmax < math.inf):
            raise ValueError(f"sizes must satisfy 0 < HMIN <= HMAX, got {self.sizes!r}")
        if not (math.isfinite(self.vertices) and self.vertices > 0):
            raise ValueError(f"vertices must be positive, got {self.vertices!r}")
        if self.gradation is not None and not (1.0 < self.gradation < math.inf):
            raise ValueError(f"gradation must be a number > 1, got {self.gradation!r}")
        derivatives = tuple(_derivatives(self.function, self.degree + 1))
        object.__setattr__(self, "_derivatives", derivatives)
        object.__setattr__(self, "_fn", _lambdify(list(derivatives)))
        object.__setattr__(self, "_values", _lambdify([smooth_minmax(self.function)]))
        h = self.step
        shifts = np.array([[0.0, 0.0], [h, 0.0], [-h, 0.0], [0.0, h], [0.0, -h]])
        object.__setattr__(self, "_shifts", shifts[:, None, :])
        object.__setattr__(self, "_grid", None)
        object.__setattr__(self, "_log_scale", self._solve_scale())

    # -- the construction ---------------------------------------------------- #

    @property
    def exponents(self) -> tuple[float, float]:
        """(α, β) of the continuous-mesh formula for this degree and norm."""
        return exponents(self.degree, self.norm)

    @property
    def step(self) -> float:
        """Central-difference step of the derivatives."""
        xmin, ymin, xmax, ymax = self.box
        return min(1e-2 * self.sizes[0], 1e-6 * max(xmax - xmin, ymax - ymin))

    def shape(self, pts: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Unscaled shape Q at ``(n, 2)`` points: frame e₁ (cos, sin), log eigenvalues X, Y."""
        pts = np.asarray(pts, dtype=float).reshape(-1, 2)
        values = self._fn(pts[:, 0], pts[:, 1])
        hmin, hmax = self.sizes
        shape = hessian_shape if self.degree == 1 else cubic_shape
        with np.errstate(invalid="ignore", over="ignore"):  # non-finite rows come out NaN
            return shape(values, max_aspect=hmax / hmin)

    def _log_sizes(
        self, x_log: NDArray, y_log: NDArray, log_scale: float
    ) -> tuple[NDArray, NDArray]:
        """Clamped log sizes along e₁, e₂ of M = D det(Q)^β Q with log D = ``log_scale``."""
        _, beta = self.exponents
        common = log_scale + beta * (x_log + y_log)
        lo, hi = math.log(self.sizes[0]), math.log(self.sizes[1])
        return (
            np.clip(-0.5 * (common + x_log), lo, hi),
            np.clip(-0.5 * (common + y_log), lo, hi),
        )

    def _components(
        self, cos: NDArray, sin: NDArray, x_log: NDArray, y_log: NDArray, log_scale: float
    ) -> tuple[NDArray, NDArray, NDArray]:
        """(g11, g12, g22) of M = D det(Q)^β Q, sizes clamped, for a shape (as :meth:`shape`)."""
        # log of the eigenvalues μ = h⁻², clamped to [HMAX⁻², HMIN⁻²]
        lo, hi = -2.0 * math.log(self.sizes[1]), -2.0 * math.log(self.sizes[0])
        with np.errstate(invalid="ignore"):  # inf − inf where a derivative is infinite: NaN
            common = log_scale + self.exponents[1] * (x_log + y_log)
            mu = np.exp(np.clip([common + x_log, common + y_log], lo, hi))
        return tensor_from_frame(cos, sin, mu[0], mu[1])

    def _solve_scale(self) -> float:
        """log D giving the metric ``vertices`` ideal vertices (module, step 3), and, with
        ``gradation``, the graded grid (:attr:`_grid`) of that D (see :meth:`_grade`)."""
        pts, w = _box_rule(self.box, self.quadrature_cells)
        cos = np.empty(len(pts))
        sin = np.empty(len(pts))
        x_log = np.empty(len(pts))
        y_log = np.empty(len(pts))
        for start in range(0, len(pts), 250_000):
            part = slice(start, start + 250_000)
            cos[part], sin[part], x_log[part], y_log[part] = self.shape(pts[part])
        if not (np.isfinite(x_log).all() and np.isfinite(y_log).all()):
            bad = int(np.argmax(~(np.isfinite(x_log) & np.isfinite(y_log))))
            raise ValueError(
                f"the derivatives of the function are not finite at "
                f"({pts[bad, 0]:.6g}, {pts[bad, 1]:.6g})"
            )
        _, beta = self.exponents

        def vertices(log_scale: float) -> float:
            h1, h2 = self._log_sizes(x_log, y_log, log_scale)
            return _VERTICES_PER_AREA * float(np.dot(np.exp(-h1 - h2), w))

        # Every size is HMAX below `low` and HMIN above `high`.
        lo, hi = math.log(self.sizes[0]), math.log(self.sizes[1])
        rest = beta * (x_log + y_log)
        low = float(-2.0 * hi - np.max(rest + np.maximum(x_log, y_log))) - 1.0
        high = float(-2.0 * lo - np.min(rest + np.minimum(x_log, y_log))) + 1.0
        n_low, n_high = vertices(low), vertices(high)
        target = float(self.vertices)
        if not n_low <= target <= n_high:
            raise ValueError(
                f"{target:g} vertices cannot be reached with sizes in [{self.sizes[0]:g}, "
                f"{self.sizes[1]:g}]: between {n_low:.4g} and {n_high:.4g}"
            )
        if n_low == n_high:
            return low
        from scipy.optimize import brentq  # here: scipy.optimize takes 0.1 s to import

        log_scale = brentq(
            lambda s: math.log(vertices(s)) - math.log(target), low, high, xtol=1e-12, rtol=1e-14
        )
        if self.gradation is None:
            return log_scale
        return self._grade(log_scale, pts, w, (cos, sin, x_log, y_log))

    def _grade(self, log_scale: float, pts: NDArray, w: NDArray, shape: tuple) -> float:
        """log D of the graded metric with ``vertices`` ideal vertices; sets :attr:`_grid`.

        Gradation refines the field, so the D of the ungraded one (``log_scale``) gives
        more vertices than asked. The vertex count of M ∩ G (G the grid graded from M
        of scale D) grows with log D at a slope of at most 1 (exactly 1 where no clamp
        is active), so the secant iteration on log N(D) − log N starts with slope 1 and
        stops within 0.1 % of N (or after 8 grids). ``pts``, ``w`` and ``shape`` are the
        quadrature rule and the shape Q at its points.
        """
        target = math.log(float(self.vertices))
        node_shape = self.shape(grid_nodes(self.box)[0])  # the grid's nodes: Q once
        previous = None
        slope = 1.0
        for _ in range(8):
            nodes = self._components(*node_shape, log_scale)
            grid = graded_grid(self.box, nodes, self.gradation)
            comps = self._components(*shape, log_scale)
            g11, g12, g22 = intersect_components(comps, grid.components(pts))
            count = _VERTICES_PER_AREA * float(np.dot(np.sqrt(g11 * g22 - g12 * g12), w))
            miss = math.log(count) - target
            object.__setattr__(self, "_grid", grid)
            if abs(miss) <= 1e-3:
                break
            if previous is not None and log_scale != previous[0]:
                slope = min(max((miss - previous[1]) / (log_scale - previous[0]), 0.05), 1.5)
            previous = (log_scale, miss)
            log_scale -= miss / slope
        return log_scale

    def error_function(self, *, compiled: bool = True) -> ScalarFunction:
        """f as a :class:`ScalarFunction`: :meth:`values`, and (if ``compiled`` and f
        has scalar code) its compiled scalar form, compiled once per function."""
        if not compiled:
            return ScalarFunction(self.values)
        try:
            source = scalar_function("f_values", [smooth_minmax(self.function)])
        except ValueError:
            return ScalarFunction(self.values)
        source += "\ndef f(x, y):\n    return f_values(x, y)[0]\n"
        if source not in _COMPILED:
            _COMPILED[source] = kernels.compile_function(source, "f")
        return ScalarFunction(self.values, _COMPILED[source])

    def values(self, pts: NDArray) -> NDArray:
        """The function f at ``(n, 2)`` points, ``(n,)``."""
        pts = np.asarray(pts, dtype=float).reshape(-1, 2)
        return self._values(pts[:, 0], pts[:, 1])[0]

    # -- the Component interface -------------------------------------------- #

    def _tensor(self, pts: NDArray) -> NDArray:
        comps = self._components(*self.shape(pts), self._log_scale)
        if self._grid is not None:
            with np.errstate(invalid="ignore"):
                comps = intersect_components(comps, self._grid.components(pts))
        g11, g12, g22 = comps
        return np.stack([g11, g12, g12, g22], axis=-1).reshape(-1, 2, 2)

    def evaluate(self, pts: NDArray, derivatives: bool) -> tuple[NDArray, NDArray | None]:
        """g ``(n, 2, 2)`` and, if asked, ∂g ``(n, 2, 2, 2)`` by central differences.

        ``dg[p, i, j, k] = ∂g_ij/∂x_k``. Where one of the two shifted points is
        not finite (the function undefined beyond a box side) the difference
        is one-sided.
        """
        pts = np.asarray(pts, dtype=float).reshape(-1, 2)
        n = len(pts)
        if not derivatives:
            return self._tensor(pts), None
        h = self.step
        g_all = self._tensor((pts[None, :, :] + self._shifts).reshape(-1, 2)).reshape(5, n, 2, 2)
        g = g_all[0]
        dg = np.stack([g_all[1] - g_all[2], g_all[3] - g_all[4]], axis=-1) * (0.5 / h)
        if np.isfinite(dg).all():
            return g, dg
        for k in range(2):
            plus, minus = g_all[1 + 2 * k], g_all[2 + 2 * k]
            ok_p = np.isfinite(plus).all(axis=(1, 2))[:, None, None]
            ok_m = np.isfinite(minus).all(axis=(1, 2))[:, None, None]
            central = (plus - minus) / (2.0 * h)
            forward = (plus - g) / h
            backward = (g - minus) / h
            dg[..., k] = np.where(ok_p & ok_m, central, np.where(ok_p, forward, backward))
        return g, dg

    def scalar_source(self, name: str) -> str:
        """Source of ``name_g(x, y)`` (g11, g12, g22) and ``name_gd(x, y)`` (with ∂ₓg, ∂ᵧg)
        for :func:`curvimesh.kernels.compile_metric`: :meth:`evaluate` at one point.

        ``name_f(x, y)`` returns the derivatives of order k + 1 of f, the very
        expressions that :meth:`shape` evaluates with numpy, printed as scalar code
        (:func:`curvimesh.expressions.scalar_function`); ``name_g`` passes them to
        the kernels' scalar twins of :func:`cubic_shape` (or :func:`hessian_shape`)
        and of the scaling and clamp of :meth:`_tensor`
        (:func:`curvimesh.kernels.interpolation_tensor`), with this metric's
        constants (HMAX/HMIN, log D, β, the clamp bounds) written as exact
        literals; ``name_gd`` takes the central differences of ``name_g`` with
        step :attr:`step`, one-sided where a shifted tensor is not finite
        (:func:`curvimesh.kernels.central_differences`). The shifted points are
        formed as :meth:`evaluate` forms them (point + (±h, 0.0), ...).

        The twins repeat numpy's operations in its order, so the values differ
        only by the last bits of the elementary functions (the C library's
        against numpy's own tanh, exp, log), amplified by the conditioning of
        the construction: 1e-12 relative where it is well conditioned, more
        where a derivative of f cancels (1 − tanh²(u) far from a tanh front) or
        the frame is within a small angle δ of an axis (the half-angle formulas
        lose digits there: about ε/δ); the derivatives by that over the step.
        With ``gradation``, ``name_g`` intersects that tensor with the graded grid's
        (:meth:`curvimesh.gradation.GradedGrid.scalar_source`, its node arrays
        compiled in as constants), as :meth:`_tensor` does.
        ValueError if a derivative has no scalar code.
        """
        hmin, hmax = self.sizes
        shape = "hessian_shape" if self.degree == 1 else "cubic_shape"
        args = ", ".join(f"d[{i}]" for i in range(self.degree + 2))
        constants = (
            self._log_scale,
            self.exponents[1],
            -2.0 * math.log(hmax),  # the clamp of log μ, as in _tensor
            -2.0 * math.log(hmin),
        )
        scaling = ", ".join(repr(float(c)) for c in constants)
        h = self.step
        shifted = "".join(  # the points of evaluate: point + shift, (0, 0) included
            f"        {name}_g(x + {float(sx)!r}, y + {float(sy)!r}),\n"
            for sx, sy in self._shifts[:, 0, :]
        )
        tensor = f"interpolation_tensor({shape}({args}, {float(hmax / hmin)!r}), {scaling})"
        grid = ""
        if self._grid is not None:  # M ∩ G, as _tensor
            grid = self._grid.scalar_source(f"{name}_grid")
            tensor = f"intersect(*{tensor}, *{name}_grid_g(x, y))"
        return (
            scalar_function(f"{name}_f", self._derivatives)
            + grid
            + f"""
def {name}_g(x, y):
    d = {name}_f(x, y)
    return {tensor}

def {name}_gd(x, y):
    return central_differences(
{shifted}        {h!r},
    )
"""
        )

    def sizes_at(self, pts: NDArray) -> NDArray:
        """The clamped sizes (h₁ along e₁, h₂ across) at points, ``(n, 2)``."""
        pts = np.asarray(pts, dtype=float).reshape(-1, 2)
        _, _, x_log, y_log = self.shape(pts)
        with np.errstate(invalid="ignore"):
            h1, h2 = self._log_sizes(x_log, y_log, self._log_scale)
        return np.column_stack([np.exp(h1), np.exp(h2)])


# --------------------------------------------------------------------------- #
# The YAML form                                                                #
# --------------------------------------------------------------------------- #


def _constant(text: object, names: Mapping[str, sympy.Expr], what: str) -> float:
    """A number, or an expression without x and y (YAML reads ``1e-4`` as text)."""
    if isinstance(text, bool) or not isinstance(text, str | int | float):
        raise ValueError(f"{what}must be a number, got {text!r}")
    if isinstance(text, str) and text.strip().lower() in ("inf", "+inf", "infinity"):
        return math.inf
    if isinstance(text, str):
        try:
            text = parse_expression(text, names)
        except ExpressionError as exc:
            raise ValueError(f"{what}{exc}") from None
        if text.free_symbols:
            raise ValueError(f"{what}must be a constant, got {text}")
    try:
        return float(text)
    except (OverflowError, TypeError, ValueError):
        raise ValueError(f"{what}must be a number in the double range, got {text}") from None


def parse_interpolation(
    body: object,
    names: Mapping[str, sympy.Expr],
    *,
    key: str,
    box: tuple[float, float, float, float],
    source: str,
) -> InterpolationMetric:
    """Build the ``interpolation:`` form of a metric file (SPEC section 2).

    ``body`` is the parsed YAML mapping with keys :data:`KEYS` (``function``
    and ``vertices`` required; ``degree`` 2, ``norm`` 2, ``sizes``
    [1e-4 L, W/2] and ``gradation`` :data:`GRADATION` by default, L the longest
    side of the box and W the shortest; ``gradation: off`` for none). ``names`` are
    the parameters and definitions in scope. Raises :class:`MetricError`
    ``"{source}: {key}.{subkey}: message"`` on one line.
    """

    def fail(sub: str, msg: str) -> MetricError:
        return MetricError(f"{source}: {key}{'.' + sub if sub else ''}: {msg}")

    if not isinstance(body, dict):
        raise fail("", "must be a mapping with keys " + ", ".join(KEYS))
    for k in body:
        if k not in KEYS:
            close = difflib.get_close_matches(str(k), KEYS, n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise fail(str(k), f"unknown key{hint}; allowed: {', '.join(KEYS)}")
    for required in ("function", "vertices"):
        if required not in body:
            raise fail(required, "missing")
    text = body["function"]
    if isinstance(text, bool) or not isinstance(text, str | int | float):
        raise fail("function", f"must be an expression, got {text!r}")
    try:
        function = parse_expression(text, names)
    except ExpressionError as exc:
        raise fail("function", str(exc)) from None

    degree = body.get("degree", 2)
    if isinstance(degree, bool) or degree not in DEGREES:
        raise fail("degree", f"must be 1 or 2, got {degree!r}")
    try:
        norm = _constant(body.get("norm", 2), names, "")
    except ValueError as exc:
        raise fail("norm", str(exc)) from None
    if not norm >= 1.0:
        raise fail("norm", f"must be a number >= 1 or inf, got {body.get('norm')!r}")
    try:
        vertices = _constant(body["vertices"], names, "")
    except ValueError as exc:
        raise fail("vertices", str(exc)) from None
    if not (math.isfinite(vertices) and vertices >= 1):
        raise fail("vertices", f"must be a positive number, got {body['vertices']!r}")
    # HMAX: half the shorter side (a longer size than the box's width asks for edges
    # the box cannot hold); HMIN: 1e-4 of the longer side
    length = max(box[2] - box[0], box[3] - box[1])
    width = min(box[2] - box[0], box[3] - box[1])
    raw_sizes = body.get("sizes", [1e-4 * length, 0.5 * width])
    if not isinstance(raw_sizes, list) or len(raw_sizes) != 2:
        raise fail(
            "sizes", f"must be a list [HMIN, HMAX], got {raw_sizes!r}{split_list_hint(raw_sizes)}"
        )
    try:
        hmin, hmax = (_constant(v, names, "") for v in raw_sizes)
    except ValueError as exc:
        raise fail("sizes", str(exc)) from None
    if not (0.0 < hmin <= hmax < math.inf):
        raise fail("sizes", f"must satisfy 0 < HMIN <= HMAX < inf, got [{hmin:g}, {hmax:g}]")
    raw = body.get("gradation", GRADATION)
    # YAML reads an unquoted off (or no, false) as False, and null or ~ as None
    if raw is None or raw is False or (isinstance(raw, str) and raw.strip().lower() == "off"):
        gradation = None
    else:
        try:
            gradation = _constant(raw, names, "")
        except ValueError as exc:
            raise fail("gradation", str(exc)) from None
        if not (1.0 < gradation < math.inf):
            raise fail("gradation", f"must be a number > 1 or off, got {raw!r}")
    try:
        return InterpolationMetric(
            function,
            degree=int(degree),
            norm=norm,
            vertices=vertices,
            sizes=(hmin, hmax),
            box=box,
            key=key,
            gradation=gradation,
        )
    except ValueError as exc:
        sub = "vertices" if "vertices" in str(exc) else "function"
        raise fail(sub, str(exc)) from None
