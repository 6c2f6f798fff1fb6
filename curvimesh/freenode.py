"""Shortest parabolas with a free middle node, where the metric's frame turns fast.

The geodesic parabola of the paper (equation (3), :func:`curvimesh.geodesic.shortest_parabola`)
has its middle node on the perpendicular bisector of the chord,

    x_m = (x₀ + x₁)/2 + α (x₁ − x₀)×e₃,

a one-parameter family of parabolas symmetric about that bisector. Where the
principal directions of the metric turn slowly over one unit length this is
enough. Where they turn fast (a front bending more tightly than its own long
size) the curve an edge should follow bends more at one end than at the
other, for instance an edge starting at the tip of a bent front: no
symmetric parabola follows it, and the shortest one cuts across the front.
On ``metrics/hard/tight_front.yaml`` (81° per unit length) a unit arc of the
front starting at its tip has a shortest symmetric parabola 3.5 long; with
the node free in the plane,

    x_m = (x₀ + x₁)/2 + α (x₁ − x₀)×e₃ + β (x₁ − x₀),

the shortest parabola is 1.004 long (1.43 against 1.00 with a long size of
0.05, 51° per unit length). The lengths mislead everything built on them:
the sampling shortens its shots along the front to a third and refuses them
(too close to their own parent), swaps, insertions and splits see unit edges
along the front as several units long.

Here (α, β) are refined from the bisector optimum (β = 0) by damped Newton
steps on the length (the composite Gauss rule of the bisector search, 2 × 5
points, a smooth function of (α, β)), with the gradient and Hessian from
central differences, a step limited to :data:`MAX_STEP` chords and halved
until the length decreases. Rows keep the bisector optimum unless the free
node shortens them by more than :data:`MIN_GAIN` (relative). With a compiled
metric the iterations run row by row in machine code
(:func:`curvimesh.kernels.free_nodes`, the same operations and bits) instead of
a dozen small calls per iteration: the three toys at 424 vertices took 1.9 s and
take 1.5 s, the tight front at seed 1 30 s and 21 s, meshes byte-identical.

Only where the frame turns fast: a field whose frame turns less than half
:data:`FREE_NODE_TURN` everywhere on a grid of its box (:func:`may_turn_fast`)
is left to :mod:`curvimesh.geodesic` at once; otherwise :func:`turns_fast` marks the points where
:func:`curvimesh.metric.frame_turn` (the rotation of the principal directions
over one unit step) is at least :data:`FREE_NODE_TURN`, the turn above which
``check-metric`` warns that unit edges can hardly follow the metric; an edge is
refined when one of its ends or its chord's midpoint is such a point.
Elsewhere every function of this module returns exactly what
:mod:`curvimesh.geodesic` returns, so that metrics which turn less are
meshed as before, bit for bit.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from curvimesh import geodesic, kernels
from curvimesh.geodesic import (
    Parabolas,
    bisector_normal,
    gauss_rule,
    parabola_length,
    parabola_length_rule,
)
from curvimesh.metric import MAX_FRAME_TURN, MetricField, frame_turn, smallest_eigenvalue

#: Turn of the principal directions over one unit length (radians) from which edges
#: get a free middle node: the threshold of ``check-metric``'s warning.
FREE_NODE_TURN = MAX_FRAME_TURN

#: Central-difference step on (α, β), in chords.
FD_STEP = 1e-5

#: Longest Newton step on (α, β), in chords.
MAX_STEP = 0.25

#: Most Newton iterations, and most halvings of a step.
ITERATIONS = 20
HALVINGS = 8

#: Relative shortening by a Newton step under which a row stops.
TOLERANCE = 1e-7

#: Relative shortening under which a row keeps its bisector node.
MIN_GAIN = 1e-6


def may_turn_fast(field: MetricField) -> bool:
    """Whether the frame turns by at least half :data:`FREE_NODE_TURN` somewhere on the
    129 × 129 grid of :attr:`curvimesh.metric.MetricField.largest_turn` (computed once
    per field): elsewhere the per-edge test (a margin of two against a turn that the
    grid misses) is not run at all."""
    return field.largest_turn >= 0.5 * FREE_NODE_TURN


def turns_fast(field: MetricField, pts: NDArray) -> NDArray:
    """Whether the metric's frame turns by at least :data:`FREE_NODE_TURN` per unit
    length at each point ``(n,)`` (:func:`curvimesh.metric.frame_turn`)."""
    pts = np.asarray(pts, dtype=float).reshape(-1, 2)
    if len(pts) == 0:
        return np.zeros(0, dtype=bool)
    g, dg = field.evaluate(pts, derivatives=True, check=False)
    return frame_turn(g, dg) >= FREE_NODE_TURN


def edges_turning_fast(field: MetricField, x0: NDArray, x1: NDArray) -> NDArray:
    """Whether the frame turns fast at either end of each chord or at its midpoint ``(n,)``."""
    n = len(x0)
    fast = turns_fast(field, np.concatenate([x0, x1, 0.5 * (x0 + x1)]))
    return fast[:n] | fast[n : 2 * n] | fast[2 * n :]


def free_node(
    field: MetricField, x0: NDArray, x1: NDArray, alpha: NDArray
) -> tuple[NDArray, NDArray]:
    """The middle node ``(n, 2)`` and length ``(n,)`` of the shortest parabola from x₀ to x₁
    with a free node, by damped Newton on (α, β) from (``alpha``, 0) (module docstring).

    The length is that of the search rule (2 × 5-point Gauss); a row never ends
    longer than it starts.
    """
    cm = field.kernel
    if cm is not None:
        x0, x1 = (np.ascontiguousarray(v, dtype=float) for v in (x0, x1))
        mid, out = np.empty((len(x0), 2)), np.empty(len(x0))
        t, w = gauss_rule(2, 5)
        kernels.free_nodes(
            cm.g, x0, x1, np.ascontiguousarray(alpha, dtype=float), t, w, FD_STEP, FD_STEP**2,
            MAX_STEP, ITERATIONS, HALVINGS, TOLERANCE, mid, out,
        )  # fmt: skip
        return mid, out
    return _free_node_numpy(field, x0, x1, alpha)


def _free_node_numpy(
    field: MetricField, x0: NDArray, x1: NDArray, alpha: NDArray
) -> tuple[NDArray, NDArray]:
    """:func:`free_node` by vectorised numpy over the rows (the metrics with no compiled
    form; the reference of :func:`curvimesh.kernels.free_nodes`)."""
    nrm = bisector_normal(x0, x1)
    d = x1 - x0
    mid0 = 0.5 * (x0 + x1)

    def length(a: NDArray, b: NDArray, rows: NDArray) -> NDArray:
        xm = mid0[rows] + a[:, None] * nrm[rows] + b[:, None] * d[rows]
        return parabola_length_rule(field, x0[rows], x1[rows], xm, segments=2, order=5)

    a = np.asarray(alpha, dtype=float).copy()
    b = np.zeros(len(a))
    rows = np.arange(len(a))
    f = length(a, b, rows)
    act = rows[np.isfinite(f)]
    h = FD_STEP
    for _ in range(ITERATIONS):
        if act.size == 0:
            break
        A, B, F = a[act], b[act], f[act]
        fpa, fma = length(A + h, B, act), length(A - h, B, act)
        fpb, fmb = length(A, B + h, act), length(A, B - h, act)
        fab = length(A + h, B + h, act)
        ga, gb = (fpa - fma) / (2 * h), (fpb - fmb) / (2 * h)
        haa, hbb = (fpa - 2 * F + fma) / h**2, (fpb - 2 * F + fmb) / h**2
        hab = (fab - fpa - fpb + F) / h**2
        sa, sb = newton_step(ga, gb, haa, hab, hbb)
        t = np.ones(len(act))
        moved = np.zeros(len(act), dtype=bool)
        todo = np.arange(len(act))
        for _ in range(HALVINGS):
            if todo.size == 0:
                break
            fn = length(A[todo] + t[todo] * sa[todo], B[todo] + t[todo] * sb[todo], act[todo])
            ok = np.isfinite(fn) & (fn < F[todo])
            take = todo[ok]
            a[act[take]] = A[take] + t[take] * sa[take]
            b[act[take]] = B[take] + t[take] * sb[take]
            f[act[take]] = fn[ok]
            moved[take] = True
            todo = todo[~ok]
            t[todo] *= 0.5
        gain = F - f[act]
        act = act[moved & (gain > TOLERANCE * F)]
    return mid0 + a[:, None] * nrm + b[:, None] * d, f


def newton_step(
    ga: NDArray, gb: NDArray, haa: NDArray, hab: NDArray, hbb: NDArray
) -> tuple[NDArray, NDArray]:
    """The step (δα, δβ) = −H⁻¹ ∇L where the Hessian H is positive definite, else −∇L / |H|,
    shortened to at most :data:`MAX_STEP`.

    >>> grad_hess = (np.array([x]) for x in (2.0, 0.0, 4.0, 0.0, 1.0))
    >>> [float(v[0]) + 0.0 for v in newton_step(*grad_hess)]
    [-0.25, 0.0]
    """
    det = haa * hbb - hab**2
    pd = (haa > 0) & (det > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        sa = np.where(pd, -(hbb * ga - hab * gb) / det, 0.0)
        sb = np.where(pd, -(haa * gb - hab * ga) / det, 0.0)
        scale = np.maximum(np.abs(haa) + np.abs(hbb) + 2 * np.abs(hab), 1e-300)
    sa = np.where(pd, sa, -ga / scale)
    sb = np.where(pd, sb, -gb / scale)
    norm = np.hypot(sa, sb)
    with np.errstate(divide="ignore", invalid="ignore"):
        cap = np.where(norm > MAX_STEP, MAX_STEP / norm, 1.0)
    sa, sb = sa * cap, sb * cap
    bad = ~(np.isfinite(sa) & np.isfinite(sb))
    return np.where(bad, 0.0, sa), np.where(bad, 0.0, sb)


def shortest_parabola(field: MetricField, x0: NDArray, x1: NDArray, **kwargs) -> Parabolas:
    """:func:`curvimesh.geodesic.shortest_parabola` (same arguments), with the middle
    node freed (:func:`free_node`) on the edges where the frame turns fast.

    A freed row's ``alpha`` stays the bisector optimum's; its ``mid`` and
    ``length`` are the free node's (the length to 1e-5 relative with
    ``exact_length``, as the bisector search's).
    """
    par = geodesic.shortest_parabola(field, x0, x1, **kwargs)
    x0 = np.asarray(x0, dtype=float).reshape(-1, 2)
    x1 = np.asarray(x1, dtype=float).reshape(-1, 2)
    if len(x0) == 0 or not may_turn_fast(field):
        return par
    rows = np.flatnonzero(edges_turning_fast(field, x0, x1) & np.isfinite(par.length))
    if rows.size == 0:
        return par
    mid, length = free_node(field, x0[rows], x1[rows], par.alpha[rows])
    if kwargs.get("exact_length", True):
        length = parabola_length(field, x0[rows], x1[rows], mid)
    better = length < par.length[rows] * (1.0 - MIN_GAIN)
    rows, mid, length = rows[better], mid[better], length[better]
    out_mid, out_len = par.mid.copy(), par.length.copy()
    out_mid[rows], out_len[rows] = mid, length
    return Parabolas(par.alpha, out_mid, out_len)


#: A pair whose :func:`round_lower_bound` is this many times ``short`` is not measured again.
LOWER_MARGIN = 1.5

#: Most a symmetric parabola is taken to overestimate a free one between points
#: closer than ``short``: a pair whose symmetric parabola is LOWER_MARGIN × OVERESTIMATE
#: × short long is not measured again. A 0.7 arc of the front of
#: ``metrics/hard/tight_front.yaml`` from its tip: 1.54 against 0.70 (2.2 times, 81° per
#: unit length); 2.54 against 0.70 with a long size of 0.1 (3.6 times, 101°).
OVERESTIMATE = 3.0


def round_lower_bound(field: MetricField, a: NDArray, b: NDArray) -> NDArray:
    """|b − a| sqrt(λ_min), λ_min the smallest eigenvalue of g at a, b and their midpoint
    ``(p,)``: the length of any curve from a to b if the largest size 1/sqrt(λ_min) of the
    metric were no larger along it than at those three points."""
    n = len(a)
    lam = smallest_eigenvalue(field.tensor(np.concatenate([a, b, 0.5 * (a + b)]), check=False))
    lam = np.min(lam.reshape(3, n), axis=0)
    with np.errstate(invalid="ignore"):
        return np.hypot(*(b - a).T) * np.sqrt(lam)


def bounded_lengths(
    field: MetricField, a: NDArray, b: NDArray, **kwargs
) -> tuple[NDArray, NDArray]:
    """:func:`curvimesh.geodesic.bounded_lengths` (same arguments), with the rows where
    the frame turns fast measured by their free-node parabolas (:func:`shortest_parabola`)
    when that is shorter."""
    length, mid = geodesic.bounded_lengths(field, a, b, **kwargs)
    if len(a) == 0 or not may_turn_fast(field):
        return length, mid
    rows = np.arange(len(a))
    short, long = kwargs.get("short"), kwargs.get("long")
    if short is not None and long is None:
        # only the rows not known to be close, and not too far to be
        maybe = (length >= short) & (length < LOWER_MARGIN * OVERESTIMATE * short)
        rows = rows[maybe]
        rows = rows[round_lower_bound(field, a[rows], b[rows]) < LOWER_MARGIN * short]
    rows = rows[edges_turning_fast(field, a[rows], b[rows])]
    if rows.size == 0:
        return length, mid
    par = shortest_parabola(field, a[rows], b[rows], scan=5, alpha_tol=2e-3, exact_length=False)
    shorter = par.length < length[rows]
    length, mid = length.copy(), mid.copy()
    length[rows[shorter]], mid[rows[shorter]] = par.length[shorter], par.mid[shorter]
    return length, mid


def parabola_verdicts(
    field: MetricField,
    a: NDArray,
    b: NDArray,
    *,
    short: float | None = None,
    long: float | NDArray | None = None,
    straight_order: int = 5,
) -> NDArray[np.int8]:
    """:func:`curvimesh.geodesic.parabola_verdicts` (same arguments), the pairs not
    found shorter than ``short`` and turning fast decided again by their lengths from
    :func:`bounded_lengths` (a free node only shortens a parabola)."""
    verdict = geodesic.parabola_verdicts(
        field, a, b, short=short, long=long, straight_order=straight_order
    )
    if len(a) == 0 or not may_turn_fast(field):
        return verdict
    rows = np.flatnonzero(verdict >= 0)
    rows = rows[edges_turning_fast(field, a[rows], b[rows])]
    if rows.size == 0:
        return verdict
    lo = -np.inf if short is None else short
    hi = np.broadcast_to(np.inf if long is None else np.asarray(long, dtype=float), (len(a),))
    length, _ = bounded_lengths(
        field, a[rows], b[rows], short=short, long=None if long is None else hi[rows],
        straight_order=straight_order,
    )  # fmt: skip
    verdict[rows] = np.where(length < lo, -1, np.where(length > hi[rows], 1, 0))
    return verdict


def any_closer(
    field: MetricField,
    a: NDArray,
    b: NDArray,
    offsets: NDArray,
    hits: NDArray,
    short: float,
    *,
    straight_order: int = 5,
) -> NDArray[np.bool_]:
    """:func:`curvimesh.geodesic.any_closer` (same arguments), the pairs of the points
    found far that turn fast decided again by :func:`parabola_verdicts`."""
    close = geodesic.any_closer(field, a, b, offsets, hits, short, straight_order=straight_order)
    if len(a) == 0 or not may_turn_fast(field):
        return close
    q = np.repeat(np.arange(len(a)), np.diff(offsets))
    keep = ~close[q]
    q, h = q[keep], np.asarray(hits)[keep]
    fast = edges_turning_fast(field, a[q], b[h])
    q, h = q[fast], h[fast]
    if q.size:
        verdict = parabola_verdicts(field, a[q], b[h], short=short, straight_order=straight_order)
        close[q[verdict < 0]] = True
    return close


def any_closer_in_index(
    field: MetricField,
    a: NDArray,
    mins: NDArray,
    maxs: NDArray,
    index,
    exclude: NDArray,
    short: float,
    *,
    straight_order: int = 5,
    quad: NDArray | None = None,
) -> NDArray[np.bool_]:
    """:func:`curvimesh.geodesic.any_closer_in_index` (same arguments); where the frame
    may turn fast, the pairs are listed and decided by :func:`any_closer`."""
    if not may_turn_fast(field):
        return geodesic.any_closer_in_index(
            field, a, mins, maxs, index, exclude, short, straight_order=straight_order, quad=quad
        )
    offsets, hit = geodesic.index_neighbours(index, mins, maxs, exclude, quad, a)
    return any_closer(field, a, index.points, offsets, hit, short, straight_order=straight_order)


__all__ = [
    "FREE_NODE_TURN",
    "any_closer",
    "any_closer_in_index",
    "bounded_lengths",
    "edges_turning_fast",
    "free_node",
    "may_turn_fast",
    "newton_step",
    "parabola_verdicts",
    "shortest_parabola",
    "turns_fast",
]
