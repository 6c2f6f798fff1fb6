"""Measures of a curved mesh in a metric: edge lengths, metric areas, quality (4).

* Edge length: the metric length of the parabola through an edge's three
  nodes, L = ∫₀¹ sqrt(ẋᵀ g(x(t)) ẋ) dt (SPEC section 4).
* Metric area of a curved triangle: ∫_t sqrt(det g) dx = ∫_ref sqrt(det g(x(ξ))) J(ξ) dξ,
  with the P2 map x(ξ) and its Jacobian J.
* Quality, paper equation (4) (as SPEC section 4 fixes its normalisation):
  q = 4√3 ∫_t sqrt(det g) dx / (L₁² + L₂² + L₃²); 1 for a unit equilateral triangle.
"""

from __future__ import annotations

import math
import time
import weakref
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from curvimesh import kernels
from curvimesh.bezier import p2_jacobian, p2_map, p2_shape, p2_shape_grad
from curvimesh.geodesic import parabola_length, parabola_length_rule
from curvimesh.memo import RowMemo, memo_table, memoised
from curvimesh.mesh import Mesh
from curvimesh.metric import MetricField

#: Relative accuracy of the figures a user reads: the report's edge lengths and metric
#: areas (:mod:`curvimesh.report`), the areas behind the qualities of ``batch``'s summary
#: and of the plot's colours, and the re-measured triangles of the quality pass
#: (:mod:`curvimesh.shift`), so that all of them show the report's worst quality.
REPORT_RTOL = 1e-5

#: Relative accuracy of edge lengths where they are counted rather than quoted to the
#: last digit: ``batch``'s summary, the plot's histogram, the long edges that insertion
#: and splitting work on.
COUNT_RTOL = 1e-4

#: A metric whose compiled evaluation of a point takes at least this many times a look-up
#: of one row in a memo table (:func:`memo_lookup_ns`), both timed on the machine that
#: runs, has its areas and edge lengths remembered (:func:`remembers`); below, looking
#: a measure up costs about what computing it does. A measure takes 10 (a length) to
#: 16 (an area) evaluations; a row looked up, computed and added costs several look-ups.
#: Measured on a 2-core machine where a look-up took 29 – 48 ns (in process, each case
#: with the tables and without, medians):
#:
#: - the toy, 25 ns a point (ratio 0.5 – 0.85): the same time either way, 9.46 s and
#:   9.51 s at 91,028 vertices (the swap stage 2.23 s and 2.57 s, the curving 0.67 s and
#:   0.59 s);
#: - the three toys, 40 – 65 ns (ratio 0.85 – 2.2): 2.36 s and 2.58 s at 9,644 vertices,
#:   6.46 s and 7.14 s at 38,050.
#:
#: The threshold lies between, where the choice costs nothing. An absolute one (45 ns,
#: set on a machine where the toy took 29 ns and the three toys 70) had the three toys
#: at 38,050 vertices, 44 ns on this one, go without the tables.
MEMO_MIN_RATIO = 0.6

_REMEMBERS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _best_ns(run, n: int, repeat: int = 3) -> float:
    """The best of ``repeat`` timings of ``run()``, in nanoseconds per each of its ``n``."""
    best = math.inf
    for _ in range(repeat):
        t = time.perf_counter()
        run()
        best = min(best, time.perf_counter() - t)
    return best / n * 1e9


@lru_cache(maxsize=1)
def memo_lookup_ns() -> float:
    """Nanoseconds a row of six floats takes to be found in a memo table
    (:class:`curvimesh.memo.RowMemo`, 4,096 rows, best of three), timed once a process."""
    rows = np.random.default_rng(0).uniform(size=(4096, 6))
    table = RowMemo(6)
    table.add(rows, rows[:, 0])
    table.find(rows[:16])
    return _best_ns(lambda: table.find(rows), len(rows))


def metric_ns(field: MetricField) -> float:
    """Nanoseconds the compiled evaluation of ``field`` takes a point (4,096 points of its
    box, best of three)."""
    xmin, ymin, xmax, ymax = field.box
    u = (np.arange(64) + 0.5) / 64
    pts = np.column_stack(
        [np.repeat(xmin + u * (xmax - xmin), 64), np.tile(ymin + u * (ymax - ymin), 64)]
    )
    field.evaluate(pts[:16], derivatives=False, check=False)
    return _best_ns(lambda: field.evaluate(pts, derivatives=False, check=False), len(pts))


def remembers(field: MetricField) -> bool:
    """Whether the measures of ``field`` are kept in memo tables (:mod:`curvimesh.memo`):
    where its evaluation is not compiled, or takes at least :data:`MEMO_MIN_RATIO` times
    a look-up (:func:`metric_ns`, :func:`memo_lookup_ns`; decided once per field). The
    tables only spare work: the numbers are the same either way."""
    known = _REMEMBERS.get(field)
    if known is None:
        known = field.kernel is None or metric_ns(field) >= MEMO_MIN_RATIO * memo_lookup_ns()
        _REMEMBERS[field] = known
    return known


def _memoised(
    field: MetricField, key: tuple, width: int, rows: NDArray, compute, remember: bool = True
) -> NDArray:
    """``compute(rows)``, through the field's memo table ``key`` where it :func:`remembers`
    (and ``remember``: False for rows that will not come again)."""
    if not (remember and remembers(field)):
        return compute(np.ascontiguousarray(rows, dtype=np.float64).reshape(len(rows), width))
    return memoised(memo_table(field, key, width), rows, compute)


#: Local corner pairs (a, b) and edge-node slot of the three edges of a triangle6.
EDGE_SLOTS = ((0, 1, 3), (1, 2, 4), (2, 0, 5))


@lru_cache(maxsize=16)
def triangle_rule(n: int) -> tuple[NDArray, NDArray]:
    """Collapsed (Duffy) Gauss rule on the reference triangle: points ``(n², 2)``, weights.

    Gauss–Jacobi in one direction folded by the map u = s, v = (1 − s) t; exact
    for polynomials of degree 2n − 2 and weights summing to 1/2 (the area).

    >>> uv, w = triangle_rule(3)
    >>> round(float(w.sum()), 15), round(float(w @ uv[:, 0]), 15)
    (0.5, 0.166666666666667)
    """
    xs, ws = np.polynomial.legendre.leggauss(n)
    s, t = (xs + 1) / 2, (xs + 1) / 2
    S, T = np.meshgrid(s, t, indexing="ij")
    W = np.outer(ws / 2, ws / 2) * (1 - S)
    uv = np.column_stack([S.ravel(), ((1 - S) * T).ravel()])
    return uv, W.ravel()


@lru_cache(maxsize=16)
def area_rule(order: int) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """The P2 shape functions, their u and v derivatives ``(k, 6)`` and the weights ``(k,)``
    at the points of :func:`triangle_rule` of ``order``, as the compiled
    :func:`curvimesh.kernels.metric_areas` takes them (cached; do not modify)."""
    uv, w = triangle_rule(order)
    grad = p2_shape_grad(uv)
    return p2_shape(uv), np.ascontiguousarray(grad[:, :, 0]), np.ascontiguousarray(grad[:, :, 1]), w


def metric_areas(
    field: MetricField, nodes: NDArray, *, order: int = 4, remember: bool = True
) -> NDArray:
    """Metric areas ∫_t sqrt(det g) dx of curved triangles ``(m,)`` from nodes ``(m, 6, 2)``.

    Uses :func:`triangle_rule` of the given order on the reference triangle;
    J(ξ) enters with its sign, so an inverted triangle has a smaller area.
    Areas are remembered by their nodes (:mod:`curvimesh.memo`) with ``remember``.
    """
    nodes = np.asarray(nodes, dtype=float).reshape(-1, 6, 2)
    return _memoised(
        field,
        ("metric_areas", order),
        12,
        nodes.reshape(-1, 12),
        lambda rows: _metric_areas(field, rows, order),
        remember,
    )


#: The nodes of a triangle6's four children under midpoint subdivision, in reference
#: coordinates ``(24, 2)``, six a child (corners, then edge midpoints 0-1, 1-2, 2-0, as
#: :class:`Mesh` orders them): points of the quarter lattice (i/4, j/4). The middle
#: child is the one of the three edge midpoints, counter-clockwise like the others.
_CHILD_UV = (
    np.array(
        [
            [(0, 0), (2, 0), (0, 2), (1, 0), (1, 1), (0, 1)],
            [(2, 0), (4, 0), (2, 2), (3, 0), (3, 1), (2, 1)],
            [(0, 2), (2, 2), (0, 4), (1, 2), (1, 3), (0, 3)],
            [(2, 0), (2, 2), (0, 2), (2, 1), (1, 2), (1, 1)],
        ]
    )
    / 4.0
).reshape(-1, 2)

#: Finest subdivision of :func:`metric_areas_adaptive` (4⁶ = 4,096 children at most).
AREA_MAX_LEVEL = 6


def metric_areas_adaptive(
    field: MetricField,
    nodes: NDArray,
    *,
    rtol: float = REPORT_RTOL,
    max_level: int = AREA_MAX_LEVEL,
) -> NDArray:
    """Metric areas of curved triangles ``(m, 6, 2)`` to ``rtol`` relative (estimated),
    by adaptive midpoint subdivision.

    Each piece is integrated by :func:`triangle_rule` of orders 4 and 8; their
    difference estimates the error of the first. A triangle is done when the
    estimates of its pieces add up to at most ``rtol`` × its area; otherwise its
    pieces whose estimate exceeds their share (``rtol`` × area × their share of
    the reference triangle) are split in four and measured again, down to
    ``max_level``. A P2 map restricted to a piece is again a P2 map, so a piece is
    a triangle6 whose nodes are the parent's map at the quarter points.

    Where g is smooth the two rules agree on the whole triangle; where it has a
    kink (an intersection's switch from one metric to the other, SPEC section 2),
    a fixed rule converges slowly: on the three toys, a triangle crossing one
    measured 0.806, 0.799, 0.798 in quality (4) with the orders 4, 8 and 16.

    The estimate is not a bound: across a kink the two rules' errors can agree, and
    the triangle is then taken unsplit. On 1 + 4 max(0, x − 0.35) over 3,954 random
    triangles (tests/test_quality.py), 8 missed 10 × ``rtol`` at ``rtol`` 1e-5, the
    worst by 3.5e-4 relative.

    With a compiled metric, the whole subdivision of every triangle is one call
    (:func:`curvimesh.kernels.metric_areas_adaptive`), the same arithmetic in the
    same order as the loop over levels (:func:`_areas_by_levels`), bit for bit.
    """
    nodes = np.ascontiguousarray(nodes, dtype=float).reshape(-1, 6, 2)
    cm = field.kernel
    if cm is None or len(nodes) == 0:
        return _areas_by_levels(field, nodes, rtol, max_level)
    out = np.empty(len(nodes))
    kernels.metric_areas_adaptive(
        cm.g, nodes, child_shape(), *area_rule(4), *area_rule(8), rtol, max_level, out
    )
    return out


@lru_cache(maxsize=1)
def child_shape() -> NDArray:
    """The P2 shape functions ``(24, 6)`` at the nodes of the four children
    (:data:`_CHILD_UV`): :func:`curvimesh.bezier.p2_map`'s matrix for them."""
    return np.ascontiguousarray(p2_shape(_CHILD_UV))


def _children(nodes: NDArray) -> NDArray:
    """The nodes ``(4m, 6, 2)`` of the four children of each triangle6 ``(m, 6, 2)``, in
    order (:func:`curvimesh.kernels.child_nodes`: ``p2_map(nodes, _CHILD_UV)``)."""
    out = np.empty((len(nodes), 4, 6, 2))
    kernels.child_nodes(child_shape(), np.ascontiguousarray(nodes, dtype=float), out)
    return out.reshape(-1, 6, 2)


def _areas_by_levels(field: MetricField, nodes: NDArray, rtol: float, max_level: int) -> NDArray:
    """:func:`metric_areas_adaptive` level by level, every piece of a level measured
    in one call of :func:`metric_areas`."""
    m = len(nodes)
    total = np.zeros(m)
    if m == 0:
        return total
    coarse = metric_areas(field, nodes, order=4, remember=False)
    fine = metric_areas(field, nodes, order=8, remember=False)
    budget = rtol * np.abs(fine)
    owner = np.arange(m)
    share = np.ones(m)  # each piece's share of its triangle's reference area
    err = np.abs(fine - coarse)
    for level in range(max_level + 1):
        spent = np.bincount(owner, err, minlength=m)
        done = (spent <= budget)[owner] | ~np.isfinite(err) | (level == max_level)
        keep = done | (err <= budget[owner] * share)
        np.add.at(total, owner[keep], fine[keep])
        budget = budget - np.bincount(owner[keep & ~done], err[keep & ~done], minlength=m)
        split = ~keep
        if not split.any():
            break
        nodes = _children(nodes[split])
        owner = np.repeat(owner[split], 4)
        share = np.repeat(share[split] / 4.0, 4)
        coarse = metric_areas(field, nodes, order=4, remember=False)
        fine = metric_areas(field, nodes, order=8, remember=False)
        err = np.abs(fine - coarse)
    return total


def _metric_areas(field: MetricField, rows: NDArray, order: int) -> NDArray:
    """:func:`metric_areas` of nodes ``(m, 12)``, computed."""
    nodes = rows.reshape(-1, 6, 2)
    uv, w = triangle_rule(order)
    cm = field.kernel
    if cm is not None:
        out = np.empty(len(nodes))
        kernels.metric_areas(cm.g, np.ascontiguousarray(nodes, dtype=float), *area_rule(order), out)
        return out
    pts = p2_map(nodes, uv)  # (m, k, 2)
    jac = p2_jacobian(nodes, uv)  # (m, k)
    g = field.tensor(pts.reshape(-1, 2), check=False).reshape(*pts.shape[:2], 2, 2)
    with np.errstate(invalid="ignore"):
        dens = np.sqrt(g[..., 0, 0] * g[..., 1, 1] - g[..., 0, 1] ** 2)
    return (dens * jac) @ w


#: Triangles of quality (4) below the figure a loop aims at plus this, measured with the
#: loops' fixed rule, are measured again to :data:`REPORT_RTOL` (:func:`qualities`):
#: where the metric has a kink, the fixed rule can be off by 0.01 in quality (the three
#: toys at 997 vertices: 0.020 at most, 0.0085 at 9,644), and the loop must see the
#: triangles the report will find below its aim.
REMEASURE_MARGIN = 0.05


def fixed_rule_lengths(field: MetricField, mesh: Mesh) -> NDArray:
    """Edge lengths ``(E,)`` of a P2 ``mesh`` by the loops' rule of two segments
    (:func:`edge_lengths_fast`, remembered)."""
    pts = np.asarray(mesh.points)
    e = mesh.edges
    return edge_lengths_fast(field, pts[e[:, 0]], pts[e[:, 1]], pts[mesh.edge_mid])


def fixed_rule_measures(field: MetricField, mesh: Mesh) -> tuple[NDArray, NDArray]:
    """Edge lengths ``(E,)`` and qualities (4) ``(m,)`` of a P2 ``mesh`` by the loops' fixed
    rules (:func:`fixed_rule_lengths`, :func:`metric_areas`): what the clean-up stages
    judge a whole mesh by (:func:`curvimesh.adapt.defects`, :mod:`curvimesh.bend`)."""
    length = fixed_rule_lengths(field, mesh)
    area = metric_areas(field, np.asarray(mesh.points)[np.asarray(mesh.triangles)])
    return length, quality_from(area, length[mesh.tri_edges])


def qualities(field: MetricField, nodes: NDArray, lens: NDArray, *, aim: float) -> NDArray:
    """Qualities (4) ``(m,)`` of curved triangles ``(m, 6, 2)`` with edge lengths ``(m, 3)``:
    by the fixed rule of order 4 (:func:`metric_areas`), and those below ``aim`` +
    :data:`REMEASURE_MARGIN` again with their areas to :data:`REPORT_RTOL`
    (:func:`metric_areas_adaptive`), as the report will see them."""
    q = quality_from(metric_areas(field, nodes), lens)
    near = np.flatnonzero(q < aim + REMEASURE_MARGIN)
    if near.size:
        q[near] = quality_from(metric_areas_adaptive(field, nodes[near]), lens[near])
    return q


def edge_lengths(
    field: MetricField,
    points: NDArray,
    edges: NDArray,
    mids: NDArray | None,
    *,
    rtol: float = REPORT_RTOL,
) -> NDArray:
    """Metric lengths ``(E,)`` of edges ``(E, 2)`` through middle nodes ``mids`` ``(E,)``.

    ``mids`` are node indices (or None: straight edges), and lengths are
    accurate to ``rtol`` relative (adaptive composite Gauss–Legendre). Its
    rule of two segments is :func:`edge_lengths_fast`'s, taken from there
    (remembered by the optimisation loops for most edges).
    """
    x0, x1 = points[edges[:, 0]], points[edges[:, 1]]
    xm = 0.5 * (x0 + x1) if mids is None else points[mids]

    def compute(r: NDArray) -> NDArray:
        a, b, m = r[:, 0:2], r[:, 2:4], r[:, 4:6]
        two = edge_lengths_fast(field, a, b, m)
        return parabola_length(field, a, b, m, rtol=rtol, two_segments=two)

    return _memoised(field, ("edge_lengths", rtol), 6, np.column_stack([x0, x1, xm]), compute)


def edge_lengths_fast(
    field: MetricField, x0: NDArray, x1: NDArray, xm: NDArray, *, remember: bool = True
) -> NDArray:
    """Edge lengths ``(E,)`` with a fixed 2×5-point Gauss rule (for the optimisation loops),
    remembered by their nodes (:mod:`curvimesh.memo`) with ``remember``."""
    return _memoised(
        field,
        ("edge_lengths_fast",),
        6,
        np.column_stack([x0, x1, xm]),
        lambda r: parabola_length_rule(field, r[:, 0:2], r[:, 2:4], r[:, 4:6], segments=2, order=5),
        remember,
    )


def quality_from(area: NDArray, lengths: NDArray) -> NDArray:
    """Equation (4): q = 4√3 A / (L₁² + L₂² + L₃²), for areas ``(m,)`` and lengths ``(m, 3)``.

    >>> round(float(quality_from(np.array([math.sqrt(3) / 4]), np.ones((1, 3)))[0]), 12)
    1.0
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        q = 4.0 * math.sqrt(3.0) * area / (lengths**2).sum(axis=1)
    return np.where(np.isfinite(q), q, 0.0)


def triangle_nodes(points: NDArray, triangles: NDArray) -> NDArray:
    """Node coordinates ``(m, 6, 2)`` of P2 triangles ``(m, 6)``."""
    return points[triangles]
