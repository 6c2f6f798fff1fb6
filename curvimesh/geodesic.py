"""Geodesics of a metric field: Christoffel symbols, shooting, geodesic parabolas.

Paper section 2 (Zhang, Johnen, Remacle, "Curvilinear mesh adaptation"):

* Christoffel symbols Γⁱ_kl = ½ gⁱᵐ (g_mk,l + g_ml,k − g_kl,m);
* the geodesic ODE (2): ẍⁱ + Γⁱ_jk ẋʲ ẋᵏ = 0, integrated here with an
  adaptive Dormand–Prince 5(4) pair (the paper used RK2) in arc-length
  parametrisation, and with fixed-step RK4 as a reference;
* the geodesic parabola between two points (equation (3)): the quadratic
  curve x(t) = (1−t)(1−2t) x₀ + t(2t−1) x₁ + 4t(1−t) x_m whose middle node
  x_m = (x₀+x₁)/2 + α (x₁−x₀)×e₃ lies on the perpendicular bisector, with α
  minimising its length in the metric.

Every function works on arrays of rows (one geodesic or one edge a row).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from curvimesh import kernels
from curvimesh.metric import MetricField

# --------------------------------------------------------------------------- #
# Christoffel symbols and the geodesic ODE                                     #
# --------------------------------------------------------------------------- #


def christoffel(g: NDArray, dg: NDArray) -> NDArray:
    """Christoffel symbols of the second kind, ``(n, 2, 2, 2)``: ``G[p, i, k, l] = Γⁱ_kl``.

    Γⁱ_kl = ½ gⁱᵐ (∂_l g_mk + ∂_k g_ml − ∂_m g_kl)  (paper section 2), from
    g ``(n,2,2)`` and ``dg[p, i, j, k] = ∂g_ij/∂x_k``.

    >>> g = np.eye(2)[None]; dg = np.zeros((1, 2, 2, 2))
    >>> float(np.abs(christoffel(g, dg)).max())
    0.0
    """
    t = dg + np.einsum("pmlk->pmkl", dg) - np.einsum("pklm->pmkl", dg)
    ginv = np.linalg.inv(g)
    return 0.5 * np.einsum("pim,pmkl->pikl", ginv, t)


def _acceleration(field: MetricField, x: NDArray, v: NDArray) -> NDArray:
    """ẍ = −Γ(x)(ẋ, ẋ) ``(n, 2)``; rows where the metric is not defined give NaN."""
    cm = field.kernel
    if cm is not None:
        out = np.empty((len(x), 2))
        kernels.accelerations(cm.gd, *_rows(x, v), out)
        return out
    g, dg = field.evaluate(x, derivatives=True, check=False)
    ok = np.isfinite(g).all(axis=(1, 2))
    gam = np.full((len(x), 2, 2, 2), np.nan)
    if ok.any():
        gam[ok] = christoffel(g[ok], dg[ok])
    return -np.einsum("pikl,pk,pl->pi", gam, v, v)


def offset_alpha(x0: NDArray, x1: NDArray, offset: NDArray) -> NDArray:
    """The α ``(n,)`` of the middle node (x₀ + x₁)/2 + ``offset`` ``(n, 2)``, projected on
    the bisector: offset·d⊥ / |d|² (d = x₁ − x₀, d⊥ = d × e₃; the inverse of
    :func:`parabola_midnode` for offsets along d⊥); NaN or inf where x₀ = x₁."""
    d = np.asarray(x1, dtype=float) - np.asarray(x0, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.einsum("pi,pi->p", offset, bisector_normal(x0, x1)) / np.einsum("pi,pi->p", d, d)


def geodesic_alpha(field: MetricField, x0: NDArray, x1: NDArray) -> NDArray:
    """A guess ``(n,)`` of the offset α of the shortest parabola from x₀ to x₁: the α whose
    parabola bends as the geodesic does at the chord's middle.

    The parabola x(t) = x₀ + t d + 4t(1−t) α d⊥ (d = x₁ − x₀, d⊥ = d × e₃) has
    ẍ = −8α d⊥; a geodesic through the middle with velocity d has
    ẍ = −Γ(d, d) + λ d (paper equation (2), any parametrisation), so
    α = Γ(d, d)·d⊥ / (8 |d|²): the middle node offset by Γ(d, d)/8
    (:func:`offset_alpha`). Exact to first order in the metric's variation;
    NaN where the metric is undefined at the middle.
    """
    x0, x1 = np.asarray(x0, dtype=float), np.asarray(x1, dtype=float)
    acc = _acceleration(field, 0.5 * (x0 + x1), x1 - x0)  # −Γ(d, d)
    return offset_alpha(x0, x1, -0.125 * acc)


def unit_velocity(field: MetricField, x: NDArray, direction: NDArray) -> NDArray:
    """Scale directions ``(n, 2)`` to unit speed in the metric at x: vᵀ g(x) v = 1."""
    g = field.tensor(x, check=False)
    speed2 = np.einsum("pi,pij,pj->p", direction, g, direction)
    with np.errstate(invalid="ignore", divide="ignore"):
        return direction / np.sqrt(speed2)[:, None]


def shoot_fixed(
    field: MetricField, x0: NDArray, v0: NDArray, length: NDArray | float, steps: int
) -> tuple[NDArray, NDArray]:
    """Integrate the geodesic ODE (2) with ``steps`` RK4 steps over t ∈ [0, length].

    ``v0`` must have unit speed in the metric (see :func:`unit_velocity`), so
    t is arc length. Returns the end points and end velocities ``(n, 2)``.
    """
    x = np.array(x0, dtype=float, copy=True)
    v = np.array(v0, dtype=float, copy=True)
    h = (np.broadcast_to(np.asarray(length, dtype=float), (len(x),)) / steps)[:, None]
    with np.errstate(invalid="ignore", over="ignore"):
        for _ in range(steps):
            a1 = _acceleration(field, x, v)
            x2, v2 = x + 0.5 * h * v, v + 0.5 * h * a1
            a2 = _acceleration(field, x2, v2)
            x3, v3 = x + 0.5 * h * v2, v + 0.5 * h * a2
            a3 = _acceleration(field, x3, v3)
            x4, v4 = x + h * v3, v + h * a3
            a4 = _acceleration(field, x4, v4)
            x = x + h / 6.0 * (v + 2 * v2 + 2 * v3 + v4)
            v = v + h / 6.0 * (a1 + 2 * a2 + 2 * a3 + a4)
    return x, v


@dataclass(frozen=True)
class Shot:
    """Shot geodesics: end points and velocities ``(n, 2)``, success flags ``(n,)``."""

    end: NDArray
    velocity: NDArray
    ok: NDArray


# Dormand & Prince (1980) RK5(4)7M tableau: 5th-order solution, 4th-order error estimate.
_DP_C = np.array([0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0])
_DP_A = [
    [],
    [1 / 5],
    [3 / 40, 9 / 40],
    [44 / 45, -56 / 15, 32 / 9],
    [19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729],
    [9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656],
    [35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84],
]
_DP_B = np.array([35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84, 0.0])
_DP_E = _DP_B - np.array(
    [5179 / 57600, 0.0, 7571 / 16695, 393 / 640, -92097 / 339200, 187 / 2100, 1 / 40]
)


def _dp_step(field: MetricField, x: NDArray, v: NDArray, h: NDArray):
    """One Dormand–Prince step of the geodesic ODE for every row; h ``(n, 1)``.

    Returns the 5th-order (x, v) and the embedded error estimates (ex, ev).
    """
    kx, kv = [], []
    for i in range(7):
        xi, vi = x, v
        for j, a in enumerate(_DP_A[i]):
            if a:
                xi = xi + h * a * kx[j]
                vi = vi + h * a * kv[j]
        kx.append(vi)
        kv.append(_acceleration(field, xi, vi))
    x5 = x + h * sum(b * k for b, k in zip(_DP_B, kx, strict=True) if b)
    v5 = v + h * sum(b * k for b, k in zip(_DP_B, kv, strict=True) if b)
    ex = h * sum(e * k for e, k in zip(_DP_E, kx, strict=True) if e)
    ev = h * sum(e * k for e, k in zip(_DP_E, kv, strict=True) if e)
    return x5, v5, ex, ev


def shoot(
    field: MetricField,
    x0: NDArray,
    direction: NDArray,
    length: NDArray | float = 1.0,
    *,
    tol: float = 1e-8,
    max_iterations: int = 2000,
) -> Shot:
    """Shoot geodesics of metric length ``length`` from ``x0`` along ``direction``.

    The geodesic ODE (2) in arc-length parametrisation (unit speed in the
    metric, so t runs to ``length``) is integrated with the embedded
    Dormand–Prince 5(4) pair, every row with its own step size: a step is
    accepted when its error estimate, in position (and velocity times the
    step), is below ``tol`` times the Euclidean scale of the shot
    (|v₀| · length); the next step is h · min(5, max(0.2, 0.9 (tol/err)^(1/5))).
    Rows where the metric is undefined on the way, or that need more than
    ``max_iterations`` steps, have ``ok = False`` and NaN ends.
    """
    x0 = np.asarray(x0, dtype=float).reshape(-1, 2)
    n = len(x0)
    total = np.broadcast_to(np.asarray(length, dtype=float), (n,)).copy()
    v0 = unit_velocity(field, x0, np.asarray(direction, dtype=float).reshape(-1, 2))
    end = np.full((n, 2), np.nan)
    vel = np.full((n, 2), np.nan)
    ok = np.zeros(n, dtype=bool)
    rows = np.flatnonzero(np.isfinite(v0).all(axis=1) & (total > 0))
    ok[total == 0] = True
    end[total == 0], vel[total == 0] = x0[total == 0], v0[total == 0]
    cm = field.kernel
    if cm is not None:
        e, w, k = end[rows], vel[rows], ok[rows]
        kernels.shoot(cm.gd, x0[rows], v0[rows], total[rows], tol, max_iterations, e, w, k)
        end[rows], vel[rows], ok[rows] = e, w, k
        return Shot(end, vel, ok)
    x, v = x0[rows], v0[rows]
    t = np.zeros(len(rows))
    L = total[rows]
    scale = np.hypot(v[:, 0], v[:, 1]) * L
    h = L / 4.0
    for _ in range(max_iterations):
        if rows.size == 0:
            break
        h = np.minimum(h, L - t)
        with np.errstate(invalid="ignore", over="ignore"):
            x5, v5, ex, ev = _dp_step(field, x, v, h[:, None])
            err = np.maximum(np.abs(ex).max(axis=1), np.abs(ev).max(axis=1) * h) / scale
        finite = np.isfinite(x5).all(axis=1) & np.isfinite(v5).all(axis=1) & np.isfinite(err)
        accept = finite & (err <= tol)
        x = np.where(accept[:, None], x5, x)
        v = np.where(accept[:, None], v5, v)
        t = np.where(accept, t + h, t)
        with np.errstate(divide="ignore", invalid="ignore"):
            factor = np.clip(0.9 * (tol / np.maximum(err, 1e-300)) ** 0.2, 0.2, 5.0)
        factor = np.where(finite, factor, 0.25)
        h = h * factor
        done = accept & (t >= L * (1 - 1e-14))
        dead = h < 1e-12 * L
        if done.any():
            idx = rows[done]
            end[idx], vel[idx], ok[idx] = x[done], v[done], True
        keep = ~done & ~dead
        rows, x, v, t, L, scale, h = (a[keep] for a in (rows, x, v, t, L, scale, h))
    return Shot(end, vel, ok)


# --------------------------------------------------------------------------- #
# Parabolas                                                                    #
# --------------------------------------------------------------------------- #


def bisector_normal(x0: NDArray, x1: NDArray) -> NDArray:
    """(x₁ − x₀) × e₃ = (Δy, −Δx), the direction of the perpendicular bisector ``(n, 2)``."""
    d = x1 - x0
    return np.column_stack([d[:, 1], -d[:, 0]])


def parabola_midnode(x0: NDArray, x1: NDArray, alpha: NDArray) -> NDArray:
    """Middle node (x₀+x₁)/2 + α (x₁−x₀)×e₃ ``(n, 2)`` (paper section 2.2)."""
    return 0.5 * (x0 + x1) + np.asarray(alpha)[:, None] * bisector_normal(x0, x1)


@lru_cache(maxsize=64)
def gauss_rule(segments: int, order: int) -> tuple[NDArray, NDArray]:
    """Composite Gauss–Legendre nodes and weights on [0, 1] (cached; do not modify)."""
    xg, wg = np.polynomial.legendre.leggauss(order)
    a = np.arange(segments) / segments
    t = (a[:, None] + (xg[None, :] + 1) / (2 * segments)).ravel()
    w = np.tile(wg / (2 * segments), segments)
    return t, w


def parabola_points(x0: NDArray, x1: NDArray, xm: NDArray, t: NDArray) -> tuple[NDArray, NDArray]:
    """Points and tangents of the parabolas at parameters t: ``(n, k, 2)`` each.

    x(t) = (1−t)(1−2t) x₀ + t(2t−1) x₁ + 4t(1−t) x_m (SPEC section 3),
    ẋ(t) = (4t−3) x₀ + (4t−1) x₁ + (4−8t) x_m.
    """
    t = np.asarray(t, dtype=float)
    n0, n1, nm = (1 - t) * (1 - 2 * t), t * (2 * t - 1), 4 * t * (1 - t)
    d0, d1, dm = 4 * t - 3, 4 * t - 1, 4 - 8 * t
    pts = (
        n0[None, :, None] * x0[:, None]
        + n1[None, :, None] * x1[:, None]
        + nm[None, :, None] * xm[:, None]
    )
    tan = (
        d0[None, :, None] * x0[:, None]
        + d1[None, :, None] * x1[:, None]
        + dm[None, :, None] * xm[:, None]
    )
    return pts, tan


def _rows(*arrays: NDArray) -> list[NDArray]:
    """C-contiguous float copies (where needed) of ``(n, 2)`` arrays, for the kernels."""
    return [np.ascontiguousarray(a, dtype=float) for a in arrays]


def parabola_length_rule(
    field: MetricField, x0: NDArray, x1: NDArray, xm: NDArray, *, segments: int = 2, order: int = 5
) -> NDArray:
    """Length ∫₀¹ sqrt(ẋᵀ g(x(t)) ẋ) dt of parabolas ``(n,)`` by a fixed composite Gauss rule.

    Rows where the metric is undefined on the curve get +inf.
    """
    t, w = gauss_rule(segments, order)
    cm = field.kernel
    if cm is not None:
        out = np.empty(len(x0))
        kernels.parabola_lengths(cm.g, *_rows(x0, x1, xm), t, w, out)
        return out
    n0, n1, nm = (1 - t) * (1 - 2 * t), t * (2 * t - 1), 4 * t * (1 - t)
    shape = np.stack([n0, n1, nm], axis=1)  # (k, 3)
    dshape = np.stack([4 * t - 3, 4 * t - 1, 4 - 8 * t], axis=1)
    nodes = np.stack([x0, x1, xm], axis=1)  # (n, 3, 2)
    pts = np.matmul(shape, nodes)  # (n, k, 2)
    tan = np.matmul(dshape, nodes)
    k = len(t)
    g = field.tensor(pts.reshape(-1, 2), check=False).reshape(len(x0), k, 2, 2)
    tx, ty = tan[..., 0], tan[..., 1]
    with np.errstate(invalid="ignore"):
        speed = np.sqrt(
            tx * tx * g[..., 0, 0] + 2 * tx * ty * g[..., 0, 1] + ty * ty * g[..., 1, 1]
        )
    out = speed @ w
    out[~np.isfinite(out)] = np.inf
    return out


#: The Gauss order of :func:`parabola_length`'s composite rules, and its most segments.
LENGTH_ORDER = 5
LENGTH_MAX_SEGMENTS = 256


def parabola_length(
    field: MetricField,
    x0: NDArray,
    x1: NDArray,
    xm: NDArray | None = None,
    *,
    rtol: float = 1e-5,
    order: int = LENGTH_ORDER,
    max_segments: int = LENGTH_MAX_SEGMENTS,
    two_segments: NDArray | None = None,
) -> NDArray:
    """Metric length of parabolas ``(n,)`` to relative accuracy ``rtol``.

    Composite Gauss–Legendre with S and 2S segments; the rows whose two
    answers differ by more than rtol are refined again (S doubled) until
    ``max_segments``. ``xm`` defaults to the midpoints (straight edges).
    ``two_segments`` ``(n,)``, when given, are the rows' lengths by the rule of
    two segments (:func:`parabola_length_rule`, same order), used instead of
    computing them again.

    With a compiled metric every row is refined in one call
    (:func:`curvimesh.kernels.parabola_lengths_adaptive`), the same arithmetic as the
    loop over levels (:func:`_lengths_by_levels`), bit for bit.
    """
    x0 = np.asarray(x0, dtype=float).reshape(-1, 2)
    x1 = np.asarray(x1, dtype=float).reshape(-1, 2)
    xm = 0.5 * (x0 + x1) if xm is None else np.asarray(xm, dtype=float).reshape(-1, 2)
    cm = field.kernel
    if cm is None or len(x0) == 0:
        return _lengths_by_levels(field, x0, x1, xm, rtol, order, max_segments, two_segments)
    two = np.zeros(0) if two_segments is None else np.ascontiguousarray(two_segments, dtype=float)
    out = np.empty(len(x0))
    kernels.parabola_lengths_adaptive(
        cm.g, *_rows(x0, x1, xm), two, *doubling_rules(order, max_segments), rtol, out
    )
    return out


@lru_cache(maxsize=8)
def doubling_rules(order: int, max_segments: int) -> tuple[NDArray, NDArray, NDArray]:
    """The composite Gauss rules (:func:`gauss_rule`) of 1, 2, 4, … segments, up to the
    first count of at least ``max_segments`` (two at least), end to end: nodes, weights
    and the offsets ``(k + 1,)`` where each rule starts (cached; do not modify)."""
    rules = [gauss_rule(1, order)]
    while len(rules) < 2 or 2 ** (len(rules) - 1) < max_segments:
        rules.append(gauss_rule(2 ** len(rules), order))
    starts = np.cumsum([0] + [len(t) for t, _ in rules]).astype(np.int64)
    return np.concatenate([t for t, _ in rules]), np.concatenate([w for _, w in rules]), starts


def _lengths_by_levels(
    field: MetricField,
    x0: NDArray,
    x1: NDArray,
    xm: NDArray,
    rtol: float,
    order: int,
    max_segments: int,
    two_segments: NDArray | None,
) -> NDArray:
    """:func:`parabola_length` level by level: every row still refined measured at the
    next rule in one call of :func:`parabola_length_rule`."""
    out = np.empty(len(x0))
    todo = np.arange(len(x0))
    s = 1
    prev = parabola_length_rule(field, x0, x1, xm, segments=s, order=order)
    while todo.size:
        s *= 2
        if s == 2 and two_segments is not None:
            cur = np.asarray(two_segments, dtype=float)[todo]
        else:
            cur = parabola_length_rule(field, x0[todo], x1[todo], xm[todo], segments=s, order=order)
        with np.errstate(invalid="ignore"):
            done = (
                (np.abs(cur - prev) <= rtol * np.abs(cur)) | ~np.isfinite(cur) | (s >= max_segments)
            )
        out[todo[done]] = cur[done]
        todo, prev = todo[~done], cur[~done]
    return out


@dataclass(frozen=True)
class Parabolas:
    """Optimal parabolas: ``alpha (n,)``, middle nodes ``mid (n, 2)``, lengths ``(n,)``."""

    alpha: NDArray
    mid: NDArray
    length: NDArray


#: :func:`shortest_parabola`'s defaults: α scanned at ``SEARCH_SCAN`` values in
#: ±``SEARCH_ALPHA_MAX``, refined to ``SEARCH_TOL`` in at most ``SEARCH_MAX_ITER`` steps.
SEARCH_ALPHA_MAX = 0.5
SEARCH_SCAN = 11
SEARCH_TOL = 1e-4
SEARCH_MAX_ITER = 60


@lru_cache(maxsize=8)
def search_grid(alpha_max: float, scan: int) -> NDArray:
    """The α the searches scan: ``scan`` values evenly in ±``alpha_max`` (cached; do not
    modify)."""
    return np.linspace(-alpha_max, alpha_max, scan)


def shortest_parabola(
    field: MetricField,
    x0: NDArray,
    x1: NDArray,
    *,
    alpha_max: float = SEARCH_ALPHA_MAX,
    scan: int = SEARCH_SCAN,
    alpha_tol: float = SEARCH_TOL,
    segments: int = 2,
    order: int = 5,
    exact_length: bool = True,
    remember: bool = True,
    guided: bool = False,
    start: NDArray | None = None,
) -> Parabolas:
    """The shortest parabola between each pair of points (paper equation (3)).

    α is found by a coarse scan of ``scan`` values in [−alpha_max, alpha_max]
    (the length need not be unimodal over the whole range; scans of at least
    :data:`curvimesh.kernels.COARSE_SCAN` values use a 3-point rule, then walk
    down the grid by the search's rule to a bracket) and Brent's method
    (parabolic interpolation safeguarded by golden-section steps; the paper
    used golden section alone) in the bracket around the best scanned value,
    down to ``alpha_tol``. The search uses a fixed composite Gauss rule; the
    returned length is recomputed to 1e-5 relative when ``exact_length``.

    With ``remember`` the searches are looked up in, and added to, the field's
    memo (:class:`_SearchMemo`); callers whose end points are new every time
    (points that move, shots) pass False. The compiled searches of the pairs
    not in the memo walk from the geodesic's bend at the chord's middle
    (:func:`geodesic_alpha`) and keep its minimum when no value of the coarse
    scan is shorter, else search as above
    (:func:`curvimesh.kernels.shortest_parabolas_guided`): still a function of
    the pair alone, so the memo stays exact. ``guided`` chooses that search
    without the memo too (the remembered searches are always guided): the same
    answers, for pairs that will not come again.

    ``start`` ``(n,)`` are guesses of α (NaN: none), for pairs whose points
    moved a little since their last search: the compiled search walks downhill
    from the guess to a bracket and refines it
    (:func:`curvimesh.kernels.shortest_parabolas_near`), about three lengths
    instead of fifteen when α barely changed, and finds the local minimum
    nearest the guess. Only without ``remember``; the numpy path scans anyway.
    """
    x0 = np.asarray(x0, dtype=float).reshape(-1, 2)
    x1 = np.asarray(x1, dtype=float).reshape(-1, 2)
    nrm = bisector_normal(x0, x1)
    mid0 = 0.5 * (x0 + x1)
    grid = search_grid(alpha_max, scan)
    if start is not None:
        if remember:
            raise ValueError("shortest_parabola: start needs remember=False")
        alpha, f_alpha = _search_alpha(
            field, x0, x1, grid, alpha_tol, segments, order, start=np.asarray(start, dtype=float)
        )
    elif guided and not remember:
        alpha, f_alpha = _guided_search(field, x0, x1, grid, alpha_tol, segments, order)
    elif not remember:
        alpha, f_alpha = _search_alpha(field, x0, x1, grid, alpha_tol, segments, order)
    else:
        memo = _memo(field, (alpha_max, scan, alpha_tol, segments, order))
        keys = _pair_keys(x0, x1)
        alpha, f_alpha, found = memo.find(keys)
        todo = np.flatnonzero(~found)
        if todo.size:
            a, f = _guided_search(field, x0[todo], x1[todo], grid, alpha_tol, segments, order)
            alpha[todo], f_alpha[todo] = a, f
            memo.add(keys[todo], a, f)
    mid = mid0 + alpha[:, None] * nrm
    if exact_length:
        ln = parabola_length(field, x0, x1, mid)
    else:
        ln = f_alpha
    return Parabolas(alpha, mid, ln)


def _guided_search(field, x0, x1, grid, alpha_tol, segments, order):
    """:func:`_search_alpha` from the geodesic's bend at each chord's middle
    (:func:`geodesic_alpha`) where the field is compiled: the search of the pairs not
    in the memo (:func:`shortest_parabola`)."""
    guess = geodesic_alpha(field, x0, x1) if field.kernel is not None else None
    return _search_alpha(field, x0, x1, grid, alpha_tol, segments, order, guess=guess)


def _search_alpha(field, x0, x1, grid, alpha_tol, segments, order, start=None, guess=None):
    """α ``(n,)`` of the shortest parabolas by :func:`shortest_parabola`'s search, and the
    fixed rule's length there ``(n,)``. Compiled, from the guesses ``start`` when given
    (:func:`curvimesh.kernels.shortest_parabolas_near`), else from the guesses ``guess``
    checked against the scan (:func:`curvimesh.kernels.shortest_parabolas_guided`)."""
    cm = field.kernel
    if cm is not None:
        alpha, f_alpha = np.empty(len(x0)), np.empty(len(x0))
        t, w = gauss_rule(segments, order)
        a, b = _rows(x0, x1)
        if start is not None:
            (s,) = _rows(start)
            kernels.shortest_parabolas_near(
                cm.g, a, b, s, grid, t, w, alpha_tol, SEARCH_MAX_ITER, alpha, f_alpha
            )
        elif guess is not None:
            (s,) = _rows(guess)
            kernels.shortest_parabolas_guided(
                cm.g, a, b, s, grid, t, w, alpha_tol, SEARCH_MAX_ITER, alpha, f_alpha
            )
        else:
            kernels.shortest_parabolas(
                cm.g, a, b, grid, t, w, alpha_tol, SEARCH_MAX_ITER, alpha, f_alpha
            )
        return alpha, f_alpha
    n = len(x0)
    nrm = bisector_normal(x0, x1)
    mid0 = 0.5 * (x0 + x1)

    def length(alpha: NDArray, rows: NDArray | slice = slice(None), rule=None) -> NDArray:
        seg, order_ = rule or (segments, order)
        xm = mid0[rows] + alpha[:, None] * nrm[rows]
        return parabola_length_rule(field, x0[rows], x1[rows], xm, segments=seg, order=order_)

    ia, ib, ic, fa, fb, fc = _scan_brackets(length, grid, n, segments, order)
    return _brent_minimise(length, grid[ia], grid[ib], grid[ic], fa, fb, fc, alpha_tol)


def _scan_brackets(length, grid: NDArray, n: int, segments: int, order: int):
    """The brackets of :func:`_search_alpha`'s numpy path, as the compiled
    :func:`curvimesh.kernels._scan_bracket` takes them: indices (ia, ib, ic) into
    ``grid`` and the lengths (fa, fb, fc) there, ``(n,)`` each, by the search's rule;
    ``length(alpha, rows, rule)`` gives lengths by a rule ``(segments, order)``."""
    scan = len(grid)
    coarse = scan >= kernels.COARSE_SCAN
    rule = (1, len(kernels.COARSE_T)) if coarse else (segments, order)
    vals = np.empty((n, scan))
    for j, a in enumerate(grid):
        vals[:, j] = length(np.full(n, a), slice(None), rule)
    ib = np.argmin(vals, axis=1)
    rows = np.arange(n)
    # bracket (a, b, c) around the best scanned value; ends of the scan stay ends
    ia, ic = np.maximum(ib - 1, 0), np.minimum(ib + 1, scan - 1)
    if not coarse:
        return ia, ib, ic, vals[rows, ia], vals[rows, ib], vals[rows, ic]

    def at(i: NDArray, rows: NDArray) -> NDArray:
        return length(grid[i], rows, (segments, order))

    fb = at(ib, rows)
    fa = np.where(ia == ib, fb, at(ia, rows))
    fc = np.where(ic == ib, fb, at(ic, rows))
    while True:  # walk down the grid while a neighbour is shorter by the search's rule
        left = fa < fb
        left &= fa <= fc
        right = ~left & (fc < fb)
        if not (left.any() or right.any()):
            return ia, ib, ic, fa, fb, fc
        r = np.flatnonzero(left)
        ic[r], fc[r], ib[r], fb[r] = ib[r], fb[r], ia[r], fa[r]
        ia[r] = np.maximum(ib[r] - 1, 0)
        fa[r] = np.where(ia[r] == ib[r], fb[r], at(ia[r], r))
        r = np.flatnonzero(right)
        ia[r], fa[r], ib[r], fb[r] = ib[r], fb[r], ic[r], fc[r]
        ic[r] = np.minimum(ib[r] + 1, scan - 1)
        fc[r] = np.where(ic[r] == ib[r], fb[r], at(ic[r], r))


def _lower_bound(sorted_keys: NDArray, keys: NDArray) -> NDArray:
    """``np.searchsorted(sorted_keys, keys)`` of 32-byte void keys, by a compiled binary
    search (:func:`curvimesh.kernels.bytes_lower_bound`; numpy compares void keys
    through a generic path, 5.5 s for 3·10⁶ keys in 4·10⁶ against 0.2 s)."""
    pos = np.empty(len(keys), dtype=np.int64)
    if len(keys):
        kernels.bytes_lower_bound(
            np.ascontiguousarray(sorted_keys).view(np.uint8).reshape(len(sorted_keys), -1),
            np.ascontiguousarray(keys).view(np.uint8).reshape(len(keys), -1),
            pos,
        )
    return pos


class _SearchMemo:
    """Finished searches of :func:`shortest_parabola` (α and the rule's length) by their
    exact end points, for one field and one set of search options.

    The search is a pure function of the end points: later stages of a run
    (re-curving, swaps, shifts, splits) ask again for the parabolas of edges
    that curving or an earlier swap round already found, and get the same
    numbers back. Entries are kept in sorted runs, a logarithmic family
    (Bentley & Saxe 1980: a new run absorbs the older runs no larger than
    itself), so that adding k entries costs O(k log n) amortised and a lookup
    one binary search per run. Past :data:`MEMO_SIZE` entries the oldest run
    is dropped.
    """

    def __init__(self) -> None:
        self.runs: list[tuple[NDArray, NDArray, NDArray]] = []  # (keys, alpha, length)

    def find(self, keys: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        """α and lengths ``(k,)`` (NaN where absent) and whether each key is there."""
        alpha, length = np.full(len(keys), np.nan), np.full(len(keys), np.nan)
        found = np.zeros(len(keys), dtype=bool)
        for run_keys, run_alpha, run_length in self.runs:
            rest = np.flatnonzero(~found)
            if rest.size == 0:
                break
            pos = np.minimum(_lower_bound(run_keys, keys[rest]), len(run_keys) - 1)
            hit = run_keys[pos] == keys[rest]
            at, pos = rest[hit], pos[hit]
            alpha[at], length[at], found[at] = run_alpha[pos], run_length[pos], True
        return alpha, length, found

    def add(self, keys: NDArray, alpha: NDArray, length: NDArray) -> None:
        """Insert entries for keys not yet present (the first of repeated keys is kept)."""
        run = (keys, alpha, length)
        while self.runs and len(self.runs[-1][0]) <= len(run[0]):
            older = self.runs.pop()
            run = tuple(np.concatenate([a, b]) for a, b in zip(older, run, strict=True))
        k = run[0]
        order = np.argsort(k, kind="stable")  # older entries first among equal keys
        first = np.ones(len(k), dtype=bool)
        first[1:] = k[order][1:] != k[order][:-1]
        self.runs.append(tuple(a[order[first]] for a in run))
        while sum(len(r[0]) for r in self.runs) > MEMO_SIZE and len(self.runs) > 1:
            self.runs.pop(0)


#: Most entries of a :class:`_SearchMemo` (48 bytes each, 400 MB at most): an adapt
#: adds about 4.4 per vertex (419,000 for the 96,003-vertex toy), so a 10⁶-vertex
#: run keeps all of its searches (with 2²² it dropped the curve stage's, and the
#: swap stage searched them again: 120 s against 97 s).
MEMO_SIZE = 1 << 23
#: The end points (x₀, y₀, x₁, y₁) of a pair as one 32-byte key.
_PAIR_KEY = np.dtype((np.void, 32))
_MEMOS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _pair_keys(x0: NDArray, x1: NDArray) -> NDArray:
    rows = np.ascontiguousarray(np.column_stack([x0, x1]), dtype=np.float64)
    return rows.view(_PAIR_KEY).ravel()


def _memo(field: MetricField, options: tuple) -> _SearchMemo:
    """The memo of ``field``'s searches with ``options`` (dropped with the field)."""
    per_field = _MEMOS.setdefault(field, {})
    return per_field.setdefault(options, _SearchMemo())


def _brent_minimise(f, a, b, c, fa, fb, fc, tol: float, max_iter: int = 60):
    """Brent's method (Brent 1973; Press et al. 2007, section 10.3) on brackets
    a ≤ b ≤ c (fb ≤ fa, fc), vectorised: the numpy twin of
    :func:`curvimesh.kernels._brent` (same steps, same stopping rule).

    ``f(x, rows)`` evaluates the objective on the given rows. Each iteration
    tries the vertex of the parabola through the three best points seen and
    falls back to a golden-section step when it leaves the bracket or is not
    less than half the step before last; no step is shorter than tol / 4, and a
    row stops once its bracket is at most ``tol`` wide around its best point.
    Returns the best point ``(n,)`` and its value.
    """
    a, c = a.astype(float).copy(), c.astype(float).copy()
    fa, fc = fa.astype(float).copy(), fc.astype(float).copy()
    x, fx = b.astype(float).copy(), fb.astype(float).copy()
    w, fw, v, fv = x.copy(), fx.copy(), x.copy(), fx.copy()
    d, e = np.zeros_like(x), np.zeros_like(x)
    cgold = 0.3819660112501051
    tol1 = 0.25 * tol
    for _ in range(max_iter):
        xm = 0.5 * (a + c)
        act = np.flatnonzero(np.abs(x - xm) > 2.0 * tol1 - 0.5 * (c - a))
        if act.size == 0:
            break
        X, W, V, FX, FW, FV = x[act], w[act], v[act], fx[act], fw[act], fv[act]
        A, C, XM, D, E = a[act], c[act], xm[act], d[act], e[act]
        with np.errstate(invalid="ignore", over="ignore"):
            r = (X - W) * (FX - FV)
            q = (X - V) * (FX - FW)
            p = (X - V) * q - (X - W) * r
            q = 2.0 * (q - r)
            p = np.where(q > 0.0, -p, p)
            q = np.abs(q)
            para = (
                (np.abs(E) > tol1)
                & np.isfinite(p)
                & np.isfinite(q)
                & (np.abs(p) < np.abs(0.5 * q * E))
                & (p > q * (A - X))
                & (p < q * (C - X))
            )
            dp = p / np.where(para, q, 1.0)
        up = XM >= X
        u = X + dp
        near_end = (u - A < 2.0 * tol1) | (C - u < 2.0 * tol1)
        dp = np.where(near_end, np.where(up, tol1, -tol1), dp)
        eg = np.where(X >= XM, A - X, C - X)
        # e: the step before last, as the compiled loop keeps it
        new_e = np.where(para, D, eg)
        new_d = np.where(para, dp, cgold * eg)
        step = np.where(np.abs(new_d) >= tol1, new_d, np.where(new_d >= 0.0, tol1, -tol1))
        u = X + step
        fu = f(u, act)
        fu = np.where(np.isfinite(fu), fu, np.inf)
        better = fu <= FX
        right = u >= X
        # bracket ends
        na = np.where(better, np.where(right, X, A), np.where(~right, u, A))
        nfa = np.where(better, np.where(right, FX, fa[act]), np.where(~right, fu, fa[act]))
        nc = np.where(better, np.where(right, C, X), np.where(right, u, C))
        nfc = np.where(better, np.where(right, fc[act], FX), np.where(right, fu, fc[act]))
        # best three
        to_w = ~better & ((fu <= FW) | (W == X))
        to_v = ~better & ~to_w & ((fu <= FV) | (V == X) | (V == W))
        nv = np.where(better, W, np.where(to_w, W, np.where(to_v, u, V)))
        nfv = np.where(better, FW, np.where(to_w, FW, np.where(to_v, fu, FV)))
        nw = np.where(better, X, np.where(to_w, u, W))
        nfw = np.where(better, FX, np.where(to_w, fu, FW))
        nx = np.where(better, u, X)
        nfx = np.where(better, fu, FX)
        a[act], fa[act], c[act], fc[act] = na, nfa, nc, nfc
        x[act], fx[act], w[act], fw[act], v[act], fv[act] = nx, nfx, nw, nfw, nv, nfv
        d[act], e[act] = new_d, new_e
    return x, fx


#: Points (t, s) ↦ a + t (b − a) + s (b − a)×e₃ where :func:`chord_lower_bound` samples
#: the metric of a pair: the ends, the chord's quarter points and middle, and the
#: middle nodes of offset ±1/4 and ±1/2 (the extreme parabolas searched).
PROBES = (
    (0.0, 0.0),
    (1.0, 0.0),
    (0.25, 0.0),
    (0.5, 0.0),
    (0.75, 0.0),
    (0.5, 0.25),
    (0.5, -0.25),
    (0.5, 0.5),
    (0.5, -0.5),
)


_PROBES = np.array(PROBES)


def _probe_metrics(field: MetricField, a: NDArray, b: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """(g11, g12, g22), each ``(len(PROBES), p)``, at the :data:`PROBES` of the pairs a, b."""
    d = b - a
    nrm = bisector_normal(a, b)
    probes = np.concatenate([a + t * d + s * nrm for t, s in PROBES])
    g = field.tensor(probes, check=False).reshape(len(PROBES), -1, 2, 2)
    return g[..., 0, 0], g[..., 0, 1], g[..., 1, 1]


def chord_lower_bound(field: MetricField, a: NDArray, b: NDArray) -> NDArray:
    """A lower bound ``(p,)`` of the metric length of the parabolas from a to b, |α| ≤ 1/2.

    With ν the unit vector along d = b − a, x′ᵀ g x′ ≥ μ (x′·ν)² for every x′
    holds with μ = 1 / (νᵀ g⁻¹ ν) (the largest such μ for an SPD g), so a curve
    from a to b is at least |d| / max h_ν long, h_ν(x) = sqrt(νᵀ g(x)⁻¹ ν) the
    support size of the metric ball along ν, the maximum taken over the curve.
    It is taken over :data:`PROBES`, points of the lens swept by the parabolas.
    In a constant metric the bound is |d| / sqrt(νᵀ g⁻¹ ν) ≤ sqrt(dᵀ g d) (the
    geodesic's length, Cauchy–Schwarz), with equality when d is along a
    principal direction.
    """
    cm = field.kernel
    if cm is not None:
        out = np.empty(len(a))
        kernels.chord_bounds(cm.g, *_rows(a, b), _PROBES, out)
        return out
    d = b - a
    chord = np.hypot(d[:, 0], d[:, 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        nu = d / chord[:, None]
    g11, g12, g22 = _probe_metrics(field, a, b)
    with np.errstate(invalid="ignore", divide="ignore"):
        # νᵀ g⁻¹ ν = (g22 νx² − 2 g12 νx νy + g11 νy²) / det g
        support = (g22 * nu[:, 0] ** 2 - 2 * g12 * nu[:, 0] * nu[:, 1] + g11 * nu[:, 1] ** 2) / (
            g11 * g22 - g12**2
        )
        return chord / np.sqrt(support.max(axis=0))


def lens_lower_bound(field: MetricField, a: NDArray, b: NDArray) -> NDArray:
    """Another lower bound ``(p,)`` of the metric length of the parabolas from a to b,
    |α| ≤ 1/2, tight where the metric varies little: sqrt(λ dᵀ g₀ d), d = b − a.

    g₀ is the metric at the chord's middle and λ the least over :data:`PROBES`
    of g's smallest eigenvalue relative to g₀ (the smaller root of det(g − λ g₀)
    = 0, the smallest eigenvalue of L⁻¹ g L⁻ᵀ with g₀ = L Lᵀ), so that g ⪰ λ g₀
    in the lens the parabolas sweep. A curve x(t) from a to b there is then at
    least sqrt(λ) times as long as in the constant metric g₀, where no curve is
    shorter than the straight one: ∫ sqrt(x′ᵀ g x′) ≥ sqrt(λ) ∫ sqrt(x′ᵀ g₀ x′)
    ≥ sqrt(λ dᵀ g₀ d). In a constant metric it is the geodesic's length (λ = 1);
    :func:`chord_lower_bound` is, only where d lies along a principal
    direction. NaN where g is undefined at a probe.
    """
    cm = field.kernel
    if cm is not None:
        out = np.empty(len(a))
        kernels.lens_bounds(cm.g, *_rows(a, b), _PROBES, out)
        return out
    d = b - a
    g0 = field.tensor(0.5 * (a + b), check=False)
    a11, a12, a22 = g0[:, 0, 0], g0[:, 0, 1], g0[:, 1, 1]
    g11, g12, g22 = _probe_metrics(field, a, b)
    with np.errstate(invalid="ignore", divide="ignore"):
        # the eigenvalues of C = M g Mᵀ, M = L⁻¹ with g₀ = L Lᵀ (Cholesky)
        l11 = np.sqrt(a11)
        l21 = a12 / l11
        l22 = np.sqrt(a22 - l21 * l21)
        m11, m21, m22 = 1 / l11, -l21 / (l11 * l22), 1 / l22
        c11 = m11 * m11 * g11
        c12 = m11 * (m21 * g11 + m22 * g12)
        c22 = m21 * m21 * g11 + 2 * m21 * m22 * g12 + m22 * m22 * g22
        rel = 0.5 * (c11 + c22) - np.hypot(0.5 * (c11 - c22), c12)
        d2 = a11 * d[:, 0] ** 2 + 2 * a12 * d[:, 0] * d[:, 1] + a22 * d[:, 1] ** 2
        det_a = a11 * a22 - a12**2
        spd = (a11 > 0) & (det_a > 0) & (d2 > 0)
        bound = np.where(spd, np.sqrt(np.maximum(rel.min(axis=0), 0.0) * d2), 0.0)
    bound[np.isnan(d2 + det_a) | (spd & np.isnan(rel).any(axis=0))] = np.nan
    return bound


#: A pair whose :func:`chord_lower_bound` is at least this times a length is taken
#: to be no shorter (10 % for the metric between the bound's probes).
LOWER_BOUND_MARGIN = 1.1


def bounded_lengths(
    field: MetricField,
    a: NDArray,
    b: NDArray,
    *,
    short: float | None = None,
    long: float | NDArray | None = None,
    straight_order: int = 5,
) -> tuple[NDArray, NDArray]:
    """Shortest-parabola lengths ``(p,)`` and middle nodes ``(p, 2)`` from a to b,
    searched only where bounds leave open whether a length is below ``short``
    or above ``long`` (a number, or one per pair).

    Elsewhere a bound on the same side of both stands, with the chord's
    midpoint: the straight segment's length (α = 0, an upper bound; its Gauss
    rule of order ``straight_order``, 5 being the search's own) or, when only
    ``short`` is asked, :func:`chord_lower_bound` where it is at least
    :data:`LOWER_BOUND_MARGIN` × short (the straight length is then not
    computed). The search is :func:`shortest_parabola` with a 5-value scan
    and α to 2e-3 (the lengths of its fixed rule).
    """
    length, mid, s = _bounds(field, a, b, short, long, straight_order)
    if s.size:
        par = _bounded_search(field, a[s], b[s])
        length[s], mid[s] = par.length, par.mid
    return length, mid


def _bounded_search(field: MetricField, a: NDArray, b: NDArray) -> Parabolas:
    """The search of :func:`bounded_lengths` (not remembered: its pairs seldom repeat)."""
    return shortest_parabola(
        field, a, b, scan=BOUNDED_SCAN, alpha_tol=BOUNDED_TOL, exact_length=False, remember=False
    )


def _verdicts(length: NDArray, short: float, long: NDArray) -> NDArray[np.int8]:
    """−1 where ``length`` is below ``short``, +1 where above ``long``, 0 elsewhere."""
    return np.where(length < short, -1, np.where(length > long, 1, 0)).astype(np.int8)


#: The search of :func:`bounded_lengths` and :func:`parabola_verdicts`: scan, α tolerance.
BOUNDED_SCAN, BOUNDED_TOL = 5, 2e-3


def parabola_verdicts(
    field: MetricField,
    a: NDArray,
    b: NDArray,
    *,
    short: float | None = None,
    long: float | NDArray | None = None,
    straight_order: int = 5,
) -> NDArray[np.int8]:
    """Whether the shortest parabola from a to b is shorter than ``short`` (−1),
    longer than ``long`` (+1, a number or one per pair) or neither (0), ``(p,)``.

    The verdicts of :func:`bounded_lengths`' lengths, with the same bounds first;
    where the field is compiled, the search stops as soon as its verdict is
    known (:func:`curvimesh.kernels.classify_parabolas`: a length below
    ``short`` seen, or the bracket's convex floor above ``long``, or a length
    at most ``long`` seen with the floor at least ``short``; the floor only
    once the bracket is at most :data:`curvimesh.kernels.FLOOR_WIDTH` wide in α).
    With ``short`` alone the compiled pairs are decided one by one
    (:func:`curvimesh.kernels.close_pairs`), both bounds before the straight
    segment, each bound stopping at the first probe that leaves it short of its
    verdict (the same verdicts wherever the bounds hold).
    """
    cm = field.kernel
    if cm is not None and short is not None and long is None:
        # pair by pair, each bound computed only as far as its verdict needs
        close = np.zeros(len(a), dtype=np.bool_)
        kernels.close_pairs(cm.g, *_rows(a, b), *_closeness_rule(short, straight_order), close)
        return np.where(close, -1, 0).astype(np.int8)
    lo = -np.inf if short is None else short
    hi = np.broadcast_to(np.inf if long is None else np.asarray(long, dtype=float), (len(a),))
    length, _, s = _bounds(field, a, b, short, long, straight_order)
    verdict = _verdicts(length, lo, hi)
    if s.size == 0:
        return verdict
    if cm is None:
        verdict[s] = _verdicts(_bounded_search(field, a[s], b[s]).length, lo, hi[s])
        return verdict
    grid = np.linspace(-0.5, 0.5, BOUNDED_SCAN)
    t, w = gauss_rule(2, 5)
    out = np.empty(s.size, dtype=np.int64)
    kernels.classify_parabolas(
        cm.g,
        *_rows(a[s], b[s]),
        grid,
        t,
        w,
        BOUNDED_TOL,
        60,
        float(lo),
        np.ascontiguousarray(hi[s]),
        out,
    )
    verdict[s] = out
    return verdict


#: Pairs decided at once by the numpy code of :func:`any_closer` and
#: :func:`curvimesh.sampling.too_close`: their temporaries (probes, quadrature points
#: and the search per pair) stay some tens of MB whatever the number of pairs
#: (millions in the gap filling of a 10⁵-vertex mesh).
PAIR_BLOCK = 32_768


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
    """Whether each point ``a[i]`` ``(k, 2)`` has a shortest parabola shorter than
    ``short`` to one of ``b[hits[offsets[i]:offsets[i + 1]]]`` (``b`` ``(n, 2)``,
    ``offsets`` ``(k + 1,)``), ``(k,)``.

    The verdicts of :func:`parabola_verdicts` (``short`` only), pair by pair;
    where the field is compiled, :func:`curvimesh.kernels.close_candidates`
    tries each point's pairs nearest first and stops at the first close one.
    """
    cm = field.kernel
    if cm is None:
        q = np.repeat(np.arange(len(a)), np.diff(offsets))
        close = np.zeros(len(a), dtype=bool)
        for start in range(0, len(q), PAIR_BLOCK):  # bounded temporaries
            rows = slice(start, start + PAIR_BLOCK)
            v = parabola_verdicts(
                field, a[q[rows]], b[hits[rows]], short=short, straight_order=straight_order
            )
            close[q[rows][v < 0]] = True
        return close
    a = _rows(a)[0]
    out = np.zeros(len(a), dtype=np.bool_)
    kernels.close_candidates(
        cm.g, a, _metric_rows(field, a), *_rows(b),
        np.ascontiguousarray(offsets, dtype=np.int64), np.ascontiguousarray(hits, dtype=np.int64),
        *_closeness_rule(short, straight_order), out,
    )  # fmt: skip
    return out


def _metric_rows(field: MetricField, a: NDArray) -> NDArray:
    """(g11, g12, g22) at points ``a`` ``(k, 2)`` as ``(k, 3)`` rows for the kernels."""
    g = field.tensor(a, check=False)
    return np.ascontiguousarray(g[:, [0, 0, 1], [0, 1, 1]])


def _closeness_rule(short: float, straight_order: int) -> tuple:
    """The trailing arguments of the compiled closeness tests
    (:func:`curvimesh.kernels._is_close`): ``short``, the chord bound's margin and
    probes, the straight segment's rule, the search's scan, rule and tolerance."""
    ts, ws = gauss_rule(2, straight_order)
    t, w = gauss_rule(2, 5)
    grid = np.linspace(-0.5, 0.5, BOUNDED_SCAN)
    return float(short), LOWER_BOUND_MARGIN, _PROBES, ts, ws, grid, t, w, BOUNDED_TOL


def inscribed_quads(mins: NDArray, maxs: NDArray) -> NDArray:
    """(Q11, Q12, Q22) ``(k, 3)`` of the ellipses inscribed in the boxes [mins, maxs]
    (half-axes the half-widths; a flat box gives an infinite Q, which holds no point)."""
    half = 0.5 * (np.asarray(maxs, dtype=float) - np.asarray(mins, dtype=float))
    with np.errstate(divide="ignore"):
        inv = 1.0 / (half * half)
    return np.column_stack([inv[:, 0], np.zeros(len(half)), inv[:, 1]])


def index_neighbours(
    index,
    mins: NDArray,
    maxs: NDArray,
    exclude: NDArray,
    quad: NDArray | None = None,
    centre: NDArray | None = None,
):
    """Offsets ``(k + 1,)`` and ids of the points of ``index`` in each box ``[mins[i],
    maxs[i]]`` and the ellipse ``quad[i]`` about ``centre[i]`` (:func:`curvimesh.kernels.
    in_region`; by default the one inscribed in the box, about its centre,
    :func:`inscribed_quads`) but ``exclude[i]``, as :func:`any_closer` takes them."""
    if quad is None:
        quad = inscribed_quads(mins, maxs)
    q, hit = index.query(mins, maxs)
    if centre is None:
        centre = 0.5 * (np.asarray(mins) + np.asarray(maxs))
    inside = np.empty(len(q), dtype=np.bool_)
    kernels.in_region(*_rows(index.points[hit], centre[q], quad[q]), inside)
    other = (hit != exclude[q]) & inside
    q, hit = q[other], hit[other]
    return np.searchsorted(q, np.arange(len(mins) + 1)), hit  # q is sorted


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
    """:func:`any_closer` of each point ``a[i]`` ``(k, 2)`` against the points of ``index``
    (a :class:`curvimesh.spatial.PointIndex`) in its box ``[mins[i], maxs[i]]`` and its
    ellipse ``quad[i]`` (about a[i], the box's centre; by default the one inscribed in
    the box), but the point ``exclude[i]`` (−1: none), ``(k,)``.

    Where the field is compiled, the box queries and the verdicts are one pass
    (:func:`curvimesh.kernels.close_in_index`): no table of pairs is built.
    """
    if quad is None:
        quad = inscribed_quads(mins, maxs)
    cm = field.kernel
    if cm is None or index.packed() is None or len(a) == 0:
        offsets, hit = index_neighbours(index, mins, maxs, exclude, quad, a)
        return any_closer(
            field, a, index.points, offsets, hit, short, straight_order=straight_order
        )
    a, mins, maxs, quad = _rows(a, mins, maxs, quad)
    out = np.zeros(len(a), dtype=np.bool_)
    kernels.close_in_index(
        cm.g, a, _metric_rows(field, a), mins, maxs, quad,
        np.ascontiguousarray(exclude, dtype=np.int64), *index.packed(), *_rows(index.points),
        *_closeness_rule(short, straight_order), out,
    )  # fmt: skip
    return out


def _bounds(field, a, b, short, long, straight_order):
    """The bound stage of :func:`bounded_lengths`: lengths (bounds) ``(p,)``, chord
    midpoints ``(p, 2)`` and the rows whose parabola must be searched."""
    n = len(a)
    mid = 0.5 * (a + b)
    length = np.empty(n)
    far = np.zeros(n, dtype=bool)
    if short is not None:
        lower = chord_lower_bound(field, a, b)
        far = lower >= LOWER_BOUND_MARGIN * short
        if long is None:
            length[far] = lower[far]
    rows = np.flatnonzero(~far) if long is None else np.arange(n)
    upper = parabola_length_rule(
        field, a[rows], b[rows], mid[rows], segments=2, order=straight_order
    )
    length[rows] = upper
    search = np.zeros(n, dtype=bool)
    if long is not None:
        search |= length > long
    if short is not None:
        open_short = rows[(upper >= short) & ~far[rows]]
        # the lens bound decides many that the chord bound leaves open (three toys,
        # 3.9·10⁴ vertices: 83 % of the pairs searched in sampling, none of them close)
        lens = lens_lower_bound(field, a[open_short], b[open_short])
        search[open_short[~(lens >= LOWER_BOUND_MARGIN * short)]] = True
    return length, mid, np.flatnonzero(search)
