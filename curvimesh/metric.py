"""Riemannian metric fields on a box, loaded from YAML (SPEC section 2).

A :class:`MetricField` evaluates the metric tensor g(x, y) and its first
partial derivatives at arrays of points at once. Components are compiled
once: the sympy expressions of g11, g12, g22 and their exact derivatives
(sympy differentiation) are lambdified into one vectorised numpy function
with common subexpressions eliminated (``cse=True``).

Shapes: points ``(n, 2)``; tensors ``(n, 2, 2)``; derivatives ``(n, 2, 2, 2)``
with ``dg[p, i, j, k] = ∂g_ij/∂x_k`` at point p.

The metric forms (SPEC section 2):

* ``isotropic: H``  →  g = I / H²
* ``eigen: {sizes: [H1, H2], angle: A}``  →  g = R(A) diag(1/H1², 1/H2²) R(A)ᵀ
* ``tensor: [G11, G12, G22]``
* ``interpolation: {function: F, degree: K, norm: P, vertices: N, sizes: [HMIN, HMAX]}``
  → the metric minimising the L^P error of degree-K interpolation of F for
  about N vertices, sizes clamped to [HMIN, HMAX]; not symbolic: built and
  differentiated numerically by :class:`curvimesh.interpolation.InterpolationMetric`.
* ``intersection: [ITEM, ...]`` → the metric intersection of the items,
  folded left (simultaneous reduction; see :func:`curvimesh.tensors.intersect`).
"""

from __future__ import annotations

import difflib
import hashlib
import math
import os
import re
from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import sympy
import yaml
from numpy.typing import NDArray
from sympy.printing.numpy import NumPyPrinter

from curvimesh import expressions, kernels
from curvimesh.errors import ExpressionError, MetricError
from curvimesh.expressions import (
    FUNCTIONS,
    parse_expression,
    scalar_function,
    smooth_minmax,
    split_list_hint,
)
from curvimesh.interpolation import InterpolationMetric, parse_interpolation
from curvimesh.tensors import intersect_components, intersect_with_derivatives

X, Y = sympy.symbols("x y", real=True)

#: Largest metric file accepted, in bytes. A metric file is a few hundred bytes;
#: pure-Python YAML parsing takes about 50 µs per item, so this bounds the time
#: a hostile file can cost to a few seconds.
MAX_FILE_BYTES = 65_536
#: Largest box coordinate, and inverse of the shortest box side, accepted.
MAX_BOX = 1e100
#: Most items in an ``intersection`` (each is compiled and evaluated on its own).
MAX_ITEMS = 32
#: Most expressions parsed for one file, outer definitions counted once per item.
MAX_EXPRESSIONS = 1000
#: Points per block when evaluating compiled expressions (each of their intermediate
#: arrays then takes at most 1 MB).
EVAL_BLOCK = 131_072

TOP_KEYS = ("name", "description", "domain", "parameters", "definitions", "metric")
ITEM_KEYS = ("parameters", "definitions")
FORMS = ("isotropic", "eigen", "tensor", "interpolation", "intersection")
RESERVED = frozenset({"x", "y", "pi", *FUNCTIONS})
_IDENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


# --------------------------------------------------------------------------- #
# Compiled fields                                                              #
# --------------------------------------------------------------------------- #


class _FastPrinter(NumPyPrinter):
    """numpy code with small integer powers written as products.

    numpy's ``x**6`` on floats calls the general ``pow`` (tens of ns an
    element); ``x*x*x*x*x*x`` costs a few. Exponents 2..8 (and their
    reciprocals) are expanded.
    """

    def _print_Pow(self, expr, rational=False):
        base, exp = expr.as_base_exp()
        if exp.is_Integer and 2 <= abs(int(exp)) <= 8:
            b = self.parenthesize(base, sympy.printing.precedence.PRECEDENCE["Mul"] + 1)
            prod = "*".join([b] * abs(int(exp)))
            return f"({prod})" if exp > 0 else f"(1/({prod}))"
        return super()._print_Pow(expr, rational=rational)


def _compile(exprs: Sequence[sympy.Expr]) -> Callable[[NDArray, NDArray], list[NDArray]]:
    """Lambdify expressions of (x, y) into one vectorised function (with cse)."""
    exprs = [smooth_minmax(sympy.sympify(e)) for e in exprs]
    fn = sympy.lambdify((X, Y), exprs, modules="numpy", cse=True, printer=_FastPrinter)

    def evaluate(x: NDArray, y: NDArray) -> list[NDArray]:
        with np.errstate(all="ignore"):
            vals = fn(x, y)
        return [
            v
            if isinstance(v, np.ndarray) and v.shape == x.shape and v.dtype == float
            else np.broadcast_to(np.asarray(v, dtype=float), x.shape)
            for v in vals
        ]

    return evaluate


@dataclass(frozen=True)
class Component:
    """One smooth metric g = [[g11, g12], [g12, g22]] given by sympy expressions.

    ``sizes`` are the expressions that must be finite and positive
    (the H of the isotropic and eigen forms); empty for the tensor form.
    """

    g: tuple[sympy.Expr, sympy.Expr, sympy.Expr]
    sizes: tuple[sympy.Expr, ...] = ()
    key: str = "metric"
    _gfn: Callable = field(init=False, repr=False, compare=False)
    _sizes_fn: Callable | None = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # min/max as (a + b ∓ |a − b|)/2 before differentiating: d|u| = sign(u) du
        # lambdifies plainly, where dMax (Heaviside) does not
        g = tuple(smooth_minmax(sympy.sympify(e)) for e in self.g)
        object.__setattr__(self, "g", g)
        object.__setattr__(self, "_gfn", _compile(list(self.g)))
        sizes_fn = _compile(self.sizes) if self.sizes else None
        object.__setattr__(self, "_sizes_fn", sizes_fn)

    @cached_property
    def _fn(self) -> Callable:
        """g and its exact derivatives ∂ₓg, ∂ᵧg (numpy), compiled at their first use:
        where the compiled kernel evaluates the field, they are never needed."""
        exprs = list(self.g)
        exprs += [sympy.diff(e, X) for e in self.g]
        exprs += [sympy.diff(e, Y) for e in self.g]
        return _compile(exprs)

    @property
    def source_key(self) -> str:
        """What :meth:`scalar_source` is made from: the expressions of g, exactly
        (``sympy.srepr``)."""
        return "expressions:" + ";".join(sympy.srepr(e) for e in self.g)

    def evaluate(self, pts: NDArray, derivatives: bool) -> tuple[NDArray, NDArray | None]:
        """g ``(n,2,2)`` and, if asked, ∂g ``(n,2,2,2)`` (exact, from sympy).

        Points are evaluated in blocks of :data:`EVAL_BLOCK` (the compiled
        expressions are elementwise, so the values do not depend on the blocks;
        the blocks bound the memory of their intermediate arrays).
        """
        if len(pts) <= EVAL_BLOCK:
            return self._evaluate(pts, derivatives)
        g = np.empty((len(pts), 2, 2))
        dg = np.empty((len(pts), 2, 2, 2)) if derivatives else None
        for start in range(0, len(pts), EVAL_BLOCK):
            rows = slice(start, start + EVAL_BLOCK)
            g[rows], d = self._evaluate(pts[rows], derivatives)
            if dg is not None:
                dg[rows] = d
        return g, dg

    def _evaluate(self, pts: NDArray, derivatives: bool) -> tuple[NDArray, NDArray | None]:
        x, y = pts[:, 0], pts[:, 1]
        if not derivatives:
            v = self._gfn(x, y)
            return _pack(v[0], v[1], v[2]), None
        v = self._fn(x, y)
        g = _pack(v[0], v[1], v[2])
        dg = np.stack([_pack(v[3], v[4], v[5]), _pack(v[6], v[7], v[8])], axis=-1)
        return g, dg

    def sizes_at(self, pts: NDArray) -> NDArray:
        """The size expressions at points, ``(n, k)`` (k = 0 for the tensor form)."""
        if self._sizes_fn is None:
            return np.zeros((len(pts), 0))
        return np.stack(self._sizes_fn(pts[:, 0], pts[:, 1]), axis=1)

    def scalar_source(self, name: str) -> str:
        """Source of ``name_g(x, y)`` (g11, g12, g22) and ``name_gd(x, y)`` (with ∂ₓg, ∂ᵧg)
        for :func:`curvimesh.kernels.compile_metric`; ValueError if an expression has none."""
        d = [sympy.diff(e, X) for e in self.g] + [sympy.diff(e, Y) for e in self.g]
        return scalar_function(f"{name}_g", self.g) + scalar_function(f"{name}_gd", [*self.g, *d])


def _unpack(g: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    return (
        np.ascontiguousarray(g[..., 0, 0]),
        np.ascontiguousarray(g[..., 0, 1]),
        np.ascontiguousarray(g[..., 1, 1]),
    )


def _pack(g11: NDArray, g12: NDArray, g22: NDArray) -> NDArray:
    g = np.empty((*g11.shape, 2, 2))
    g[..., 0, 0] = g11
    g[..., 0, 1] = g12
    g[..., 1, 0] = g12
    g[..., 1, 1] = g22
    return g


#: Compiled scalar metrics by their source or its key (:attr:`MetricField.kernel`).
_COMPILED: dict[str, kernels.CompiledMetric | None] = {}

#: What :attr:`MetricField.scalar_source` depends on besides the expressions and
#: the box: the code that generates it (this module and :mod:`curvimesh.expressions`,
#: hashed) and sympy's version (its cse and printers).
_SOURCE_VERSION = hashlib.sha256(
    Path(__file__).read_bytes()
    + Path(expressions.__file__).read_bytes()
    + sympy.__version__.encode()
).hexdigest()


@dataclass(frozen=True)
class MetricField:
    """A metric field on a box: one component, or the intersection of several.

    ``box`` is (xmin, ymin, xmax, ymax). ``source`` names the file it came
    from (for messages).
    """

    components: tuple[Component, ...]
    box: tuple[float, float, float, float] = (0.0, 0.0, 1.0, 1.0)
    name: str = "metric"
    source: str = "<metric>"
    #: Evaluate through compiled scalar code (:attr:`kernel`) where the metric has one.
    jit: bool = True

    def __hash__(self) -> int:
        """The dataclass's hash (of all the fields), made once: the memo tables and the
        caches keyed by the field hash it about 1,500 times a run, 6 µs each."""
        return self._hash

    @cached_property
    def _hash(self) -> int:
        return hash((self.components, self.box, self.name, self.source, self.jit))

    def evaluate(
        self, pts: NDArray, *, derivatives: bool = False, check: bool = True
    ) -> tuple[NDArray, NDArray | None]:
        """The metric ``(n,2,2)`` and optionally its derivatives ``(n,2,2,2)`` at ``pts``.

        With ``check`` (the default) a non-finite or non-SPD value raises
        :class:`MetricError` naming the first bad point; without it, bad rows
        are returned as NaN for the caller to handle.

        Derivatives that come out non-finite at an isolated singular point of
        the expressions (e.g. d/dx sqrt(x²+y²) at the origin) while g itself
        is finite are replaced by central differences of g there.

        Computed by the compiled :attr:`kernel` when there is one (the same
        expressions, limits and checks, one point at a time), by numpy otherwise.
        """
        pts = np.ascontiguousarray(pts, dtype=float).reshape(-1, 2)
        cm = self.kernel
        if cm is None:
            return self.evaluate_numpy(pts, derivatives=derivatives, check=check)
        g, dg = kernels.evaluate(cm, pts, derivatives)
        if check:
            bad = ~_finite_rows(g)
            if bad.any():  # the numpy path names the point and its value
                i = int(np.argmax(bad))
                self.evaluate_numpy(pts[i : i + 1], derivatives=False, check=True)
        return g, dg

    @cached_property
    def scalar_source(self) -> str | None:
        """Python source of ``field_g`` and ``field_gd``, the metric at one point
        (signatures :data:`curvimesh.kernels.SIG_G` and ``SIG_GD``), generated from
        the components' expressions: the intersection folded left (its derivatives
        in forward mode, :func:`curvimesh.kernels.intersect_d`; the numpy path's by
        complex step), a non-finite value replaced by the value 1e-9 box sizes away,
        NaN where g is not SPD, non-finite derivatives by central differences, as
        :meth:`evaluate_numpy` does. Each component gives its own functions by
        its ``scalar_source`` method (:meth:`Component.scalar_source`,
        :meth:`~curvimesh.interpolation.InterpolationMetric.scalar_source`); None when a
        component has no such method or an expression has no scalar code."""
        if not all(callable(getattr(c, "scalar_source", None)) for c in self.components):
            return None
        try:
            parts = [c.scalar_source(f"c{k}") for k, c in enumerate(self.components)]
        except ValueError:
            return None
        xmin, ymin, xmax, ymax = self.box
        span = max(xmax - xmin, ymax - ymin)
        sx, sy = (1e-9 * span * np.array([0.6, 0.8])).tolist()
        h = 1e-6 * span
        fold_g = "".join(f"    a = intersect(*a, *c{k}_g(x, y))\n" for k in range(1, len(parts)))
        fold_d = "".join(f"    a = intersect_d(a, c{k}_gd(x, y))\n" for k in range(1, len(parts)))
        nan = "math.nan"
        top = f"""
def raw_g(x, y):
    a = c0_g(x, y)
{fold_g}    return a

def raw_gd(x, y):
    a = c0_gd(x, y)
{fold_d}    return a

def limit_g(x, y):
    a = raw_g(x, y)
    if not finite3(a):
        a = raw_g(x + {sx!r}, y + {sy!r})
    return a

def field_g(x, y):
    a = limit_g(x, y)
    if not spd3(a):
        return ({nan}, {nan}, {nan})
    return a

def field_gd(x, y):
    d = raw_gd(x, y)
    if not finite3((d[0], d[1], d[2])):
        d = raw_gd(x + {sx!r}, y + {sy!r})
    if not spd3((d[0], d[1], d[2])):
        return ({", ".join([nan] * 9)})
    if not finite9(d):
        px = limit_g(x + {h!r}, y)
        mx = limit_g(x - {h!r}, y)
        py = limit_g(x, y + {h!r})
        my = limit_g(x, y - {h!r})
        s = {2 * h!r}
        d = (d[0], d[1], d[2],
             (px[0] - mx[0]) / s, (px[1] - mx[1]) / s, (px[2] - mx[2]) / s,
             (py[0] - my[0]) / s, (py[1] - my[1]) / s, (py[2] - my[2]) / s)
    return d
"""
        return "import math\n" + "".join(parts) + top

    @cached_property
    def source_key(self) -> str | None:
        """A key that determines :attr:`scalar_source` (the code that generates it,
        the box, every component's ``source_key``), cheap to make where the source is
        not; None when a component has no ``source_key``."""
        keys = [getattr(c, "source_key", None) for c in self.components]
        if not all(isinstance(k, str) for k in keys):
            return None
        return f"{_SOURCE_VERSION}:{self.box!r}:" + "|".join(keys)

    @property
    def kernel(self) -> kernels.CompiledMetric | None:
        """The compiled scalar metric (:func:`curvimesh.kernels.compile_metric` of
        :attr:`scalar_source`), compiled on first use and shared by equal sources;
        None when ``jit`` is off or there is no scalar source.

        Where the field has a :attr:`source_key`, the metric is found by it, in
        memory and in the cache directory, and the source (sympy's derivatives and
        code printing, about 0.1 s for three components) is generated only when
        neither holds it."""
        if not self.jit:
            return None
        key = cache_key = self.source_key
        if key is None:  # the source is its own key
            key = self.scalar_source
            if key is None:
                return None
        if key not in _COMPILED:
            source = lambda: self.scalar_source  # noqa: E731
            _COMPILED[key] = kernels.compile_metric(source, "field_g", "field_gd", key=cache_key)
        return _COMPILED[key]

    def evaluate_numpy(
        self, pts: NDArray, *, derivatives: bool = False, check: bool = True
    ) -> tuple[NDArray, NDArray | None]:
        """:meth:`evaluate` by the vectorised numpy expressions (the reference)."""
        pts = np.ascontiguousarray(pts, dtype=float).reshape(-1, 2)
        g, dg = self._raw(pts, derivatives)
        bad = ~_spd(g)
        if bad.any():
            if check:
                p = pts[np.argmax(bad)]
                raise MetricError(
                    f"{self.source}: metric is not finite and positive definite at "
                    f"({p[0]:.6g}, {p[1]:.6g}): g = {_fmt(g[np.argmax(bad)])}"
                )
            g[bad] = np.nan
        if derivatives:
            assert dg is not None
            nf = ~_finite_rows(dg) & ~bad
            if nf.any():
                dg[nf] = self._central_difference(pts[nf])
            if bad.any():
                dg[bad] = np.nan
        return g, dg

    def tensor(self, pts: NDArray, *, check: bool = True) -> NDArray:
        """The metric ``(n, 2, 2)`` at points ``(n, 2)``."""
        return self.evaluate(pts, check=check)[0]

    def _raw(self, pts: NDArray, derivatives: bool) -> tuple[NDArray, NDArray | None]:
        g, dg = self._raw_once(pts, derivatives)
        bad = ~_finite_rows(g)
        if bad.any():
            # An isolated 0/0 of the expressions (sympy writes cos(atan2(y, x)) as
            # x/sqrt(x² + y²), undefined at the origin): take the value at a point
            # 1e-9 box sizes away, the limit along that direction.
            xmin, ymin, xmax, ymax = self.box
            shift = 1e-9 * max(xmax - xmin, ymax - ymin) * np.array([0.6, 0.8])
            g2, dg2 = self._raw_once(pts[bad] + shift, derivatives)
            g[bad] = g2
            if derivatives:
                dg[bad] = dg2
        return g, dg

    def _raw_once(self, pts: NDArray, derivatives: bool) -> tuple[NDArray, NDArray | None]:
        g, dg = self.components[0].evaluate(pts, derivatives)
        if len(self.components) == 1:
            return g, dg
        # fold the intersection on contiguous component arrays (g11, g12, g22)
        a = _unpack(g)
        da = [_unpack(dg[..., k]) for k in range(2)] if derivatives else []
        with np.errstate(all="ignore"):
            for comp in self.components[1:]:
                g2, dg2 = comp.evaluate(pts, derivatives)
                b = _unpack(g2)
                if derivatives:
                    db = [_unpack(dg2[..., k]) for k in range(2)]
                    a, da = intersect_with_derivatives(a, da, b, db)
                else:
                    a = intersect_components(a, b)
        g = _pack(*a)
        if not derivatives:
            return g, None
        return g, np.stack([_pack(*da[0]), _pack(*da[1])], axis=-1)

    def _central_difference(self, pts: NDArray) -> NDArray:
        xmin, ymin, xmax, ymax = self.box
        h = 1e-6 * max(xmax - xmin, ymax - ymin)
        dg = np.empty((len(pts), 2, 2, 2))
        for k in range(2):
            e = np.zeros(2)
            e[k] = h
            gp, _ = self._raw(pts + e, False)
            gm, _ = self._raw(pts - e, False)
            dg[..., k] = (gp - gm) / (2 * h)
        return dg

    @cached_property
    def largest_turn(self) -> float:
        """The largest :func:`frame_turn` on a 129 × 129 grid of the box (radians), once."""
        return sharpest_turn(self)[0]

    def sizes(self, pts: NDArray) -> NDArray:
        """The user's size expressions (H, H1, H2 of every item) at points, ``(n, k)``."""
        return np.concatenate([c.sizes_at(pts) for c in self.components], axis=1)

    @property
    def error_function(self) -> Callable[[NDArray], NDArray] | None:
        """The function f of the field's ``interpolation`` form (points ``(n, 2)`` → ``(n,)``,
        a :class:`curvimesh.interpolation.ScalarFunction`, compiled unless ``jit`` is off),
        when it has exactly one (alone or in an intersection); None otherwise."""
        forms = [c for c in self.components if isinstance(c, InterpolationMetric)]
        return forms[0].error_function(compiled=self.jit) if len(forms) == 1 else None

    def validate(self, pts: NDArray) -> None:
        """Raise :class:`MetricError` if a size is not finite and positive, or g is not SPD."""
        pts = np.asarray(pts, dtype=float).reshape(-1, 2)
        for comp in self.components:
            s = comp.sizes_at(pts)
            if s.size:
                with np.errstate(invalid="ignore"):
                    bad = ~(np.isfinite(s) & (s > 0)).all(axis=1)
                if bad.any():
                    i = int(np.argmax(bad))
                    raise MetricError(
                        f"{self.source}: {comp.key}: size is not finite and positive at "
                        f"({pts[i, 0]:.6g}, {pts[i, 1]:.6g}): sizes = "
                        f"{', '.join(f'{v:.6g}' for v in s[i])}"
                    )
        self.evaluate_numpy(pts, derivatives=False, check=True)

    def inside(self, pts: NDArray) -> NDArray:
        """Whether points ``(..., 2)`` lie strictly inside the box (not where NaN)."""
        xmin, ymin, xmax, ymax = self.box
        x, y = pts[..., 0], pts[..., 1]
        with np.errstate(invalid="ignore"):
            return (x > xmin) & (x < xmax) & (y > ymin) & (y < ymax)

    def sample_points(self, n: int = 65) -> NDArray:
        """A regular n×n grid over the box, boundary included, ``(n*n, 2)``."""
        xmin, ymin, xmax, ymax = self.box
        gx, gy = np.meshgrid(np.linspace(xmin, xmax, n), np.linspace(ymin, ymax, n))
        return np.column_stack([gx.ravel(), gy.ravel()])


#: Rows of 4 or 8 booleans read as one unsigned integer: all True is 0x01 in every byte.
_ALL_TRUE = {4: (np.uint32, 0x01010101), 8: (np.uint64, 0x0101010101010101)}


def smallest_eigenvalue(g: NDArray) -> NDArray:
    """λ_min ``(n,)`` of symmetric 2×2 matrices ``(n, 2, 2)``, in closed form.

    λ_max = (a + c)/2 + sqrt(((a − c)/2)² + b²) and λ_min = det / λ_max (the
    product of the eigenvalues), which keeps its relative accuracy however
    anisotropic g is, where (a + c)/2 − sqrt(…) would cancel. Several times
    faster than :func:`numpy.linalg.eigvalsh` on many small matrices.

    >>> float(smallest_eigenvalue(np.array([[[4.0, 0.0], [0.0, 1e-12]]]))[0])
    1e-12
    """
    a, b, c = g[:, 0, 0], g[:, 0, 1], g[:, 1, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        top = 0.5 * (a + c) + np.hypot(0.5 * (a - c), b)
        return (a * c - b * b) / top


#: Anisotropy below which :func:`frame_turn` ignores the principal directions:
#: a nearly round unit ball has no direction for edges to follow.
TURN_MIN_ANISOTROPY = 10.0


def frame_turn(g: NDArray, dg: NDArray, *, min_anisotropy: float = TURN_MIN_ANISOTROPY) -> NDArray:
    """How far the principal directions turn over one unit of metric length ``(n,)``, radians.

    With a = g₁₁ − g₂₂ and b = 2 g₁₂, the eigenvectors of g make the angle
    φ = ½ atan2(b, a) with the axes, so ∇φ = (a ∇b − b ∇a) / (2 (a² + b²)).
    A unit step along eigenvector eᵢ is hᵢ eᵢ in the plane (hᵢ = λᵢ^(-1/2)),
    over which the frame turns by |∇φ · eᵢ| hᵢ; the larger of the two is
    returned. Where it passes about one radian the directions change within
    one unit edge: a front curving more tightly than its own long size, which
    no unit edge can follow (the paper's method assumes a metric that varies
    slowly on the scale of its unit ball). Zero where the anisotropy
    h_max / h_min is below ``min_anisotropy`` or g is isotropic.

    ``g`` is ``(n, 2, 2)`` and ``dg[p, i, j, k] = ∂g_ij/∂x_k`` ``(n, 2, 2, 2)``.
    """
    across, along, anisotropy = _frame_rates(g, dg)
    out = np.where(anisotropy >= min_anisotropy, np.maximum(across, along), 0.0)
    return np.where(np.isfinite(out), out, 0.0)


def eigen_frame(g: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """The eigenpairs of symmetric 2×2 matrices ``(n, 2, 2)`` in closed form: m, r, c, s
    ``(n,)`` with the eigenvalues λ = m ± r, m = tr g / 2, r = ½ sqrt(a² + b²)
    (a = g₁₁ − g₂₂, b = 2 g₁₂), and (c, s) = (cos φ, sin φ), φ = ½ atan2(b, a), the unit
    eigenvector of the larger one ((−s, c) that of the smaller).

    >>> [float(v[0]) for v in eigen_frame(np.array([[[4.0, 0.0], [0.0, 1.0]]]))]
    [2.5, 1.5, 1.0, 0.0]
    """
    a = g[:, 0, 0] - g[:, 1, 1]
    b = 2.0 * g[:, 0, 1]
    m = 0.5 * (g[:, 0, 0] + g[:, 1, 1])
    r = 0.5 * np.hypot(a, b)
    phi = 0.5 * np.arctan2(b, a)
    return m, r, np.cos(phi), np.sin(phi)


def _frame_rates(g: NDArray, dg: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """The turns of :func:`frame_turn` per unit step across the layer (along the
    short size) and along it (the long size), and the anisotropy h_max / h_min."""
    a = g[:, 0, 0] - g[:, 1, 1]
    b = 2.0 * g[:, 0, 1]
    da = dg[:, 0, 0, :] - dg[:, 1, 1, :]
    db = 2.0 * dg[:, 0, 1, :]
    m, r, c, s = eigen_frame(g)  # (c, s) along the short size, (−s, c) the long
    with np.errstate(invalid="ignore", divide="ignore"):
        grad = (a[:, None] * db - b[:, None] * da) / (2.0 * (a * a + b * b))[:, None]
        across = np.abs(grad[:, 0] * c + grad[:, 1] * s) / np.sqrt(m + r)
        along = np.abs(grad[:, 1] * c - grad[:, 0] * s) / np.sqrt(m - r)
        return across, along, np.sqrt((m + r) / (m - r))


def layer_sag(g: NDArray, dg: NDArray, *, min_anisotropy: float = TURN_MIN_ANISOTROPY) -> NDArray:
    """How many short sizes the chord of one unit along the long size lies off the
    layer's curve ``(n,)``: (h_max / h_min) τ / 8, τ the turn of the frame over that
    unit (:func:`frame_turn`).

    A curve of radius R turning by τ over the long size h_max = R τ strays
    h_max² / (8R) = h_max τ / 8 from its chord (the sagitta), which is that
    many short sizes h_min: a circular layer of 2,500:1 about a circle of
    radius 0.3 (long size 0.1, τ = 1/3) strays 104 of its short sizes at the
    circle, a wall layer none. It can be large where the frame turns slowly
    (the second run of :func:`curvimesh.adapt.adapt` lays no hexagonal lattice
    where it passes :data:`curvimesh.sampling.HEX_MAX_SAG`). Zero where the anisotropy is below
    ``min_anisotropy``.
    """
    _, along, anisotropy = _frame_rates(g, dg)
    out = np.where(anisotropy >= min_anisotropy, anisotropy * along / 8.0, 0.0)
    return np.where(np.isfinite(out), out, 0.0)


#: Turn (radians) of the principal directions within one unit length above
#: which :func:`sharpest_turn` callers warn, and from which edges get free middle
#: nodes (:mod:`curvimesh.freenode`). Measured, not derived: every metric of
#: metrics/ turns at most 57° and meshes to the targets with the paper's
#: symmetric parabolas; a cosine front with long size 0.08 and radius of
#: curvature 0.056 turns 81° and left edges up to 5.6 long with them
#: (sample_runs/README, "Where it still fails").
MAX_FRAME_TURN = math.radians(60.0)


def sharpest_turn(field_: MetricField, n: int = 129) -> tuple[float, NDArray, float]:
    """The largest :func:`frame_turn` on an n×n grid of the box.

    Returns (turn in radians, the grid point, the long size h_max there).
    """
    pts = field_.sample_points(n)
    g, dg = field_.evaluate(pts, derivatives=True)
    turn = frame_turn(g, dg)
    i = int(np.argmax(turn))
    return float(turn[i]), pts[i], float(1.0 / np.sqrt(smallest_eigenvalue(g[i : i + 1])[0]))


def _finite_rows(arr: NDArray) -> NDArray:
    """Whether all entries of each row of ``arr`` ``(n, 2, 2)`` or ``(n, 2, 2, 2)`` are finite.

    Same as ``np.isfinite(arr).all(axis=(1, ...))``; numpy reduces such short
    rows slowly, so each row of 4 or 8 booleans is compared as one integer.
    """
    ok = np.ascontiguousarray(np.isfinite(arr)).reshape(len(arr), math.prod(arr.shape[1:]))
    if ok.shape[1] not in _ALL_TRUE:
        return ok.all(axis=1)
    kind, all_true = _ALL_TRUE[ok.shape[1]]
    return ok.view(kind)[:, 0] == all_true


def _spd(g: NDArray) -> NDArray:
    """Whether each tensor of ``g`` ``(n, 2, 2)`` is finite and positive definite ``(n,)``.

    All four entries finite, g₁₁ > 0 and det g > 0 (which, with g₁₁ > 0, implies g₂₂ > 0).
    """
    with np.errstate(invalid="ignore"):
        det = g[:, 0, 0] * g[:, 1, 1] - g[:, 0, 1] * g[:, 1, 0]
        return _finite_rows(g) & (g[:, 0, 0] > 0) & (det > 0)


def _fmt(g: NDArray) -> str:
    return f"[{g[0, 0]:.6g}, {g[0, 1]:.6g}, {g[1, 1]:.6g}]"


# --------------------------------------------------------------------------- #
# Integrals over the box                                                       #
# --------------------------------------------------------------------------- #


def density_integral(
    field_: MetricField,
    *,
    cells: int = 128,
    order: int = 4,
    rtol: float = 1e-5,
    max_levels: int = 24,
    max_cells: int | None = None,
) -> float:
    """Metric area ∫_Ω sqrt(det g) dx over the box (SPEC section 4).

    Tensor-product Gauss–Legendre with ``order`` points per direction on a
    ``cells`` × ``cells`` grid of the box, refined where it is not accurate:
    each cell is integrated whole and as its four quarters, and a cell whose
    two values differ by more than ``rtol`` × (the total) × (its share of the
    box's area) is replaced by its quarters, until the differences add up to
    less than ``rtol`` × (the total), at most ``max_levels`` times
    (adaptive quadrature on a quadtree), and at most ``max_cells`` quarters in
    all (4 × ``cells``², the worst cells first): a field that is not smooth
    to ``rtol`` anywhere (the central differences of an ``interpolation``
    metric) costs at most 5 times the uniform grid. A smooth field is not
    refined. A wall layer whose size grows from 8e-5 within a few thousandths
    of the wall has a metric area of 508.99; the uniform 128 × 128 grid gave
    493.3, 3 % short.
    """
    xmin, ymin, xmax, ymax = field_.box
    xg, wg = np.polynomial.legendre.leggauss(order)
    t, w = (xg + 1) / 2, wg / 2

    def integrals(x0: NDArray, y0: NDArray, dx: NDArray, dy: NDArray) -> NDArray:
        # (k,) Gauss integrals over the cells [x0, x0 + dx] × [y0, y0 + dy]
        px = (x0[:, None, None] + dx[:, None, None] * t[None, :, None]).repeat(order, axis=2)
        py = (y0[:, None, None] + dy[:, None, None] * t[None, None, :]).repeat(order, axis=1)
        pts = np.column_stack([px.ravel(), py.ravel()])
        dens = np.empty(len(pts))
        for chunk in range(0, len(pts), 200_000):
            g = field_.tensor(pts[chunk : chunk + 200_000])
            dens[chunk : chunk + 200_000] = np.sqrt(g[:, 0, 0] * g[:, 1, 1] - g[:, 0, 1] ** 2)
        return (dens.reshape(-1, order, order) @ w @ w) * dx * dy

    ex, ey = np.linspace(xmin, xmax, cells + 1), np.linspace(ymin, ymax, cells + 1)
    gx, gy = np.meshgrid(ex[:-1], ey[:-1], indexing="ij")
    x0, y0 = gx.ravel(), gy.ravel()
    dx, dy = np.full(len(x0), ex[1] - ex[0]), np.full(len(x0), ey[1] - ey[0])
    whole = integrals(x0, y0, dx, dy)
    box_area = (xmax - xmin) * (ymax - ymin)
    total, scale = 0.0, None
    budget = 4 * cells * cells if max_cells is None else max_cells
    for _ in range(max_levels):
        # the four quarters of every cell, quarter q at (q // 2, q % 2) halves
        hx, hy = dx / 2, dy / 2
        qx = (x0[:, None] + hx[:, None] * np.array([0, 0, 1, 1])).ravel()
        qy = (y0[:, None] + hy[:, None] * np.array([0, 1, 0, 1])).ravel()
        qdx, qdy = np.repeat(hx, 4), np.repeat(hy, 4)
        quarters = integrals(qx, qy, qdx, qdy).reshape(-1, 4)
        finer = quarters.sum(axis=1)
        if scale is None:
            scale = abs(float(finer.sum()))
        err = np.abs(finer - whole)
        if err.sum() <= rtol * scale:  # accurate enough as a whole
            return total + float(finer.sum())
        bad = err > rtol * scale * (dx * dy / box_area)
        if 4 * int(bad.sum()) > budget:  # the worst cells the budget allows, in order
            worst = np.argsort(-np.where(bad, err, -1.0), kind="stable")[: budget // 4]
            bad = np.zeros(len(bad), dtype=bool)
            bad[worst] = True
        budget -= 4 * int(bad.sum())
        total += float(finer[~bad].sum())
        if not bad.any():
            return total
        keep = np.repeat(bad, 4)
        x0, y0, dx, dy, whole = qx[keep], qy[keep], qdx[keep], qdy[keep], quarters[bad].ravel()
    return total + float(whole.sum())


#: Area of the unit equilateral triangle, √3/4.
UNIT_TRIANGLE_AREA = math.sqrt(3.0) / 4.0


# --------------------------------------------------------------------------- #
# Loading YAML                                                                 #
# --------------------------------------------------------------------------- #


class _NoAliasLoader(yaml.SafeLoader):
    """A safe loader that refuses YAML aliases (no 'billion laughs') and duplicate keys.

    Floats are read as in YAML 1.2 (``1e-3`` is a number, not a string), and an
    integer too long for Python to convert is a YAML error, not a ValueError.
    """

    def compose_node(self, parent, index):  # type: ignore[override]
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.constructor.ConstructorError(
                None, None, "aliases are not allowed", event.start_mark
            )
        return super().compose_node(parent, index)

    def construct_mapping(self, node, deep=False):  # type: ignore[override]
        seen: set = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if isinstance(key, str) and key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {_short(key)}", key_node.start_mark
                )
            if isinstance(key, Hashable):  # an unhashable key is reported by SafeLoader
                seen.add(key)
        return super().construct_mapping(node, deep=deep)

    def construct_yaml_int(self, node):  # type: ignore[override]
        try:
            return super().construct_yaml_int(node)
        except ValueError:  # more digits than int() converts (sys.get_int_max_str_digits)
            raise yaml.constructor.ConstructorError(
                None, None, "integer too long", node.start_mark
            ) from None


_NoAliasLoader.add_constructor("tag:yaml.org,2002:int", _NoAliasLoader.construct_yaml_int)
# YAML 1.2 floats without a dot (1e-3, 2E+5); YAML 1.1, and so SafeLoader, reads them as strings.
_NoAliasLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def _short(value: object, limit: int = 60) -> str:
    """``repr(value)`` on one line of at most ``limit`` characters, for messages."""
    try:
        text = repr(value)
    except ValueError:  # an int of more digits than repr converts
        return f"<an integer of {value.bit_length()} bits>"  # type: ignore[union-attr]
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _as_float(value: object) -> float | None:
    """The value as a finite float, or None (bools, strings, inf, nan, huge ints)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        out = float(value)
    except OverflowError:
        return None
    return out if math.isfinite(out) else None


def _suggest(word: str, choices: Sequence[str]) -> str:
    close = difflib.get_close_matches(word, list(choices), n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


class _Loader:
    """Turns a parsed YAML document into a :class:`MetricField`, naming keys in errors."""

    def fail(self, key: str, msg: str) -> MetricError:
        return MetricError(f"{self.source}: {key}: {msg}")

    def __init__(self, source: str) -> None:
        self.source = source
        self.expressions = 0
        self.domain = (0.0, 0.0, 1.0, 1.0)  # the box, for forms that integrate over it

    def check_keys(self, mapping: Mapping, allowed: Sequence[str], key: str) -> None:
        for k in mapping:
            if not isinstance(k, str) or k not in allowed:
                raise self.fail(
                    _join(key, k),
                    f"unknown key{_suggest(str(k), allowed)}; allowed: {', '.join(allowed)}",
                )

    def load(self, doc: object) -> MetricField:
        if not isinstance(doc, dict):
            raise MetricError(f"{self.source}: expected a mapping at the top level")
        self.check_keys(doc, TOP_KEYS, "")
        name = doc.get("name", os.path.splitext(os.path.basename(self.source))[0])
        if not isinstance(name, str | int | float):
            raise self.fail("name", "must be a string")
        box = self.box(doc.get("domain"))
        self.domain = box
        params = self.parameters(doc.get("parameters"), "parameters", {})
        defs = self.definitions_raw(doc.get("definitions"), "definitions")
        if "metric" not in doc:
            raise self.fail("metric", "missing (one of: " + ", ".join(FORMS) + ")")
        comps = self.form(doc["metric"], "metric", params, defs)
        return MetricField(tuple(comps), box=box, name=str(name), source=self.source)

    def box(self, domain: object) -> tuple[float, float, float, float]:
        if domain is None:
            return (0.0, 0.0, 1.0, 1.0)
        if not isinstance(domain, dict):
            raise self.fail("domain", "must be a mapping with key 'box'")
        self.check_keys(domain, ("box",), "domain")
        b = domain.get("box")
        ok = (
            isinstance(b, list)
            and len(b) == 2
            and all(isinstance(p, list) and len(p) == 2 for p in b)
            and all(_is_number(v) for p in b for v in p)
        )
        if not ok:
            raise self.fail("domain.box", f"must be [[xmin, ymin], [xmax, ymax]], got {_short(b)}")
        vals = [_as_float(v) for p in b for v in p]
        if any(v is None for v in vals):
            raise self.fail("domain.box", f"coordinates must be finite numbers, got {_short(b)}")
        x0, y0, x1, y1 = (float(v) for v in vals)  # type: ignore[arg-type]
        if not (x0 < x1 and y0 < y1):
            raise self.fail("domain.box", f"min must be below max in x and in y, got {_short(b)}")
        # Areas and relative tolerances (1e-9 of the box) must stay meaningful.
        reach = max(abs(x0), abs(y0), abs(x1), abs(y1))
        if reach > MAX_BOX or min(x1 - x0, y1 - y0) < max(1.0 / MAX_BOX, 1e-6 * reach):
            raise self.fail(
                "domain.box",
                f"coordinates must lie within ±{MAX_BOX:g} and each side be longer than "
                f"{1.0 / MAX_BOX:g} and than 1e-6 of the largest coordinate, got {_short(b)}",
            )
        return (x0, y0, x1, y1)

    def name_ok(self, name: object, key: str) -> str:
        if not isinstance(name, str) or not _IDENT.match(name):
            raise self.fail(key, f"{_short(name)} is not a valid name")
        if name in RESERVED:
            raise self.fail(key, f"'{name}' is reserved (x, y, pi and function names)")
        return name

    def parameters(self, raw: object, key: str, base: Mapping[str, sympy.Expr]) -> dict:
        out = dict(base)
        if raw is None:
            return out
        if not isinstance(raw, dict):
            raise self.fail(key, "must be a mapping of names to numbers")
        for k, v in raw.items():
            k = self.name_ok(k, _join(key, k))
            if _as_float(v) is None:
                raise self.fail(f"{key}.{k}", f"must be a finite number, got {_short(v)}")
            out[k] = sympy.Integer(v) if isinstance(v, int) else sympy.Float(v)
        return out

    def definitions_raw(self, raw: object, key: str) -> list[tuple[str, object, str]]:
        if raw is None:
            return []
        if not isinstance(raw, dict):
            raise self.fail(key, "must be a mapping of names to expressions")
        return [(self.name_ok(k, _join(key, k)), v, f"{key}.{k}") for k, v in raw.items()]

    def scope(self, params: Mapping, defs: list[tuple[str, object, str]]) -> dict:
        names: dict[str, sympy.Expr] = {"x": X, "y": Y, **params}
        for name, text, key in defs:
            names[name] = self.expr(text, names, key)
        return names

    def expr(self, text: object, names: Mapping[str, sympy.Expr], key: str) -> sympy.Expr:
        if isinstance(text, bool) or not isinstance(text, str | int | float):
            raise self.fail(key, f"must be an expression or a number, got {_short(text)}")
        if isinstance(text, int) and _as_float(text) is None:
            raise self.fail(key, f"{_short(text)} is not finite")
        self.expressions += 1
        if self.expressions > MAX_EXPRESSIONS:
            raise self.fail(key, f"too many expressions (more than {MAX_EXPRESSIONS} to parse)")
        try:
            return parse_expression(text, names)
        except ExpressionError as exc:
            raise self.fail(key, str(exc)) from None

    def size(self, text: object, names: Mapping[str, sympy.Expr], key: str) -> sympy.Expr:
        """A size H: an expression that, if constant, must be finite and positive.

        (A zero constant would make 1/H² sympy's complex infinity; sizes that
        vary are checked where the metric is evaluated.)
        """
        h = self.expr(text, names, key)
        if h.is_number and not (h.is_finite and h.is_extended_real and h > 0):
            raise self.fail(key, f"size must be positive, got {_short(text)} = {h}")
        return h

    def form(self, raw: object, key: str, params: dict, defs: list) -> list[Component]:
        if not isinstance(raw, dict) or len(raw) == 0:
            raise self.fail(key, "must hold exactly one of: " + ", ".join(FORMS))
        for k in raw:
            if k not in FORMS and k not in ITEM_KEYS:
                allowed = FORMS if key == "metric" else (*FORMS, *ITEM_KEYS)
                raise self.fail(_join(key, k), f"unknown metric form{_suggest(str(k), allowed)}")
        forms = [k for k in raw if k in FORMS]
        if len(forms) != 1:
            found = ", ".join(forms) if forms else "none"
            raise self.fail(key, f"must hold exactly one of {', '.join(FORMS)} (found {found})")
        if key == "metric" and any(k in ITEM_KEYS for k in raw):
            bad = next(k for k in raw if k in ITEM_KEYS)
            raise self.fail(f"{key}.{bad}", "put parameters and definitions at the top level")
        form = forms[0]
        body = raw[form]
        fkey = f"{key}.{form}"
        if form == "intersection":
            if not isinstance(body, list) or len(body) == 0:
                raise self.fail(fkey, "must be a non-empty list of metric items")
            if len(body) > MAX_ITEMS:
                raise self.fail(fkey, f"too many items ({len(body)}; at most {MAX_ITEMS})")
            comps: list[Component] = []
            for i, item in enumerate(body):
                ikey = f"{fkey}[{i}]"
                if not isinstance(item, dict):
                    raise self.fail(ikey, "must be a mapping")
                p = self.parameters(item.get("parameters"), f"{ikey}.parameters", params)
                d = defs + self.definitions_raw(item.get("definitions"), f"{ikey}.definitions")
                comps += self.form(item, ikey, p, d)
            return comps
        names = self.scope(params, defs)
        if form == "isotropic":
            h = self.size(body, names, fkey)
            return [Component((1 / h**2, sympy.Integer(0), 1 / h**2), (h,), fkey)]
        if form == "eigen":
            if not isinstance(body, dict):
                raise self.fail(fkey, "must be a mapping with keys sizes and angle")
            self.check_keys(body, ("sizes", "angle"), fkey)
            sizes = body.get("sizes")
            if not isinstance(sizes, list) or len(sizes) != 2:
                raise self.fail(
                    f"{fkey}.sizes",
                    f"must be a list [H1, H2], got {_short(sizes)}{split_list_hint(sizes)}",
                )
            if "angle" not in body:
                raise self.fail(f"{fkey}.angle", "missing")
            h1 = self.size(sizes[0], names, f"{fkey}.sizes[0]")
            h2 = self.size(sizes[1], names, f"{fkey}.sizes[1]")
            a = self.expr(body["angle"], names, f"{fkey}.angle")
            c, s = sympy.cos(a), sympy.sin(a)
            l1, l2 = 1 / h1**2, 1 / h2**2
            g11 = l1 * c**2 + l2 * s**2
            g12 = (l1 - l2) * c * s
            g22 = l1 * s**2 + l2 * c**2
            return [Component((g11, g12, g22), (h1, h2), fkey)]
        if form == "interpolation":
            return [parse_interpolation(body, names, key=fkey, box=self.domain, source=self.source)]
        # tensor
        if not isinstance(body, list) or len(body) != 3:
            raise self.fail(
                fkey, f"must be a list [G11, G12, G22], got {_short(body)}{split_list_hint(body)}"
            )
        g = tuple(self.expr(v, names, f"{fkey}[{i}]") for i, v in enumerate(body))
        return [Component(g, (), fkey)]  # type: ignore[arg-type]


def _is_number(v: object) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _join(key: str, sub: object) -> str:
    """``key.sub`` for messages; a key that is not a plain name is shown by its short repr."""
    part = sub if isinstance(sub, str) and _IDENT.match(sub) else _short(sub)
    return f"{key}.{part}" if key else str(part)


def _check_items(field_: MetricField, pts: NDArray) -> None:
    """Each item of an intersection must be SPD on its own: the intersection of an
    SPD metric with an indefinite one can come out SPD and hide the error."""
    if len(field_.components) < 2:
        return
    for comp in field_.components:
        alone = MetricField((comp,), box=field_.box, source=field_.source)
        g, _ = alone._raw(pts, False)  # with the limit at isolated 0/0 points
        bad = ~_spd(g)
        if bad.any():
            i = int(np.argmax(bad))
            raise MetricError(
                f"{field_.source}: {comp.key}: metric is not finite and positive definite at "
                f"({pts[i, 0]:.6g}, {pts[i, 1]:.6g}): g = {_fmt(g[i])}"
            )


def load_metric_text(text: str, *, source: str = "<metric>") -> MetricField:
    """Parse a metric from YAML text. Raises :class:`MetricError` with a one-line message."""
    if len(text) > MAX_FILE_BYTES:
        raise MetricError(
            f"{source}: file too large ({len(text):,} characters; limit {MAX_FILE_BYTES:,})"
        )
    try:
        doc = yaml.load(text, Loader=_NoAliasLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise MetricError(f"{source}: invalid YAML{where}: {problem}") from None
    except RecursionError:
        raise MetricError(f"{source}: invalid YAML: nested too deeply") from None
    field_ = _Loader(source).load(doc)
    pts = field_.sample_points(33)
    # Overflow only makes values non-finite, which is what is checked (and reported).
    with np.errstate(over="ignore", invalid="ignore"):
        field_.validate(pts)
        _check_items(field_, pts)
    return field_


def load_metric(path: str | os.PathLike) -> MetricField:
    """Load and validate a metric file (SPEC section 2)."""
    source = os.fspath(path)
    try:
        with open(source, "rb") as f:
            data = f.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise MetricError(f"{source}: cannot read: {exc.strerror or exc}") from None
    if len(data) > MAX_FILE_BYTES:  # in bytes, before decoding: no truncated text gets through
        raise MetricError(f"{source}: file too large (more than {MAX_FILE_BYTES:,} bytes)")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise MetricError(f"{source}: not a UTF-8 text file") from None
    return load_metric_text(text, source=source)
