"""Cores of thin curved layers, sampled first (beyond the paper).

A thin layer that curves (a circular boundary layer, a layer about an ellipse) is
meshed by columns of points across it, about one unit apart along it. When the
fronts of Algorithm 1 (:mod:`curvimesh.sampling`) grow from the box's sides,
they enter such a layer at several places; the columns grown from different
entries meet somewhere in it, and a column ends half way through the layer.
There the edges along the layer span two columns, and no parabola that long
follows the layer's curve: on a 500:1 layer about a circle of radius 0.15
(long size 0.1), the shortest parabola between two points of the circle one
unit apart along it is 1.57 long, and 1.10 at 0.8 units (a free middle node
gains nothing); its mesh kept edges of 1.5 – 6.3 at every seed tried.

The layer is sampled from its core instead. A row of points is laid along the
core, successive points a parabola of ``spacing`` apart, and the fronts grow
from that row (:func:`curvimesh.sampling.sample_points`) before the box's
sides are sampled: the columns start together on the core and a column ends
only where the layer has widened.

The core of a layer is where the short size h_min is least across it (along the
short direction). Its points are found by line searches from the points of a
grid of the box, kept where the anisotropy there is at least
:data:`CORE_MIN_ANISOTROPY` and a unit chord along the layer strays at least
:data:`CORE_MIN_SAG` short sizes from it (:func:`curvimesh.metric.layer_sag`:
straight layers, a wall's boundary layer, are left to the fronts); each core is
traced from its thinnest point along the long direction, every step projected
back on the core.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from curvimesh.geodesic import shortest_parabola
from curvimesh.metric import MetricField, eigen_frame, layer_sag

#: Least anisotropy h_max / h_min of a core. Measured on bench/robustness: the
#: layers whose meshes missed the targets at some seed with the fronts from the
#: sides alone are 500:1 and more; at 100:1 (u07) the core changes nothing there.
CORE_MIN_ANISOTROPY = 100.0
#: Least sag of a unit chord along the layer at a core, in short sizes.
CORE_MIN_SAG = 2.0
#: Anisotropy from which a grid point starts a line search.
START_MIN_ANISOTROPY = 10.0
#: The grid (n × n points) of the box the line searches start from.
CORE_GRID = 129
#: Samples of h_min along a line search, per round; rounds of a full search.
SEARCH_SAMPLES = 33
SEARCH_ROUNDS = 6
#: Step of a trace along a core, in long sizes h_max.
TRACE_STEP = 0.25
#: Most steps of a trace; most cores traced.
MAX_TRACE_STEPS = 5000
MAX_CORES = 8
#: The arc lengths, in units of ``spacing``, tried for the next point along a core.
_TRIAL = np.linspace(0.3, 1.2, 37)


def frames(field: MetricField, pts: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """h_min, h_max ``(n,)``, the short and the long direction ``(n, 2)`` at points.

    From the eigenpairs λ = m ± r in closed form (:func:`curvimesh.metric.eigen_frame`):
    h_min = 1/sqrt(m + r), h_max = 1/sqrt(λ_min) with λ_min = det g / (m + r) (no
    cancellation however thin the layer). NaN where the metric is undefined.
    """
    g = field.tensor(pts, check=False)
    m, r, c, s = eigen_frame(g)
    with np.errstate(invalid="ignore", divide="ignore"):
        h_min = 1.0 / np.sqrt(m + r)
        h_max = np.sqrt((m + r) / (g[:, 0, 0] * g[:, 1, 1] - g[:, 0, 1] ** 2))
    return h_min, h_max, np.column_stack([c, s]), np.column_stack([-s, c])


def least_along(
    field: MetricField, pts: NDArray, dirs: NDArray, half: NDArray, rounds: int = SEARCH_ROUNDS
) -> tuple[NDArray, NDArray]:
    """Line searches: the points ``pts + t dirs``, |t| ≤ ``half``, where h_min is least
    ``(n, 2)``, and whether that least is inside the interval ``(n,)``.

    Each round samples h_min at :data:`SEARCH_SAMPLES` evenly spaced t and
    narrows the interval to the two spacings about the least: after k rounds
    the point is within ``half`` (1/16)^k of a local least of the samples.
    """
    offsets = np.linspace(-1.0, 1.0, SEARCH_SAMPLES)
    centre = np.zeros(len(pts))
    half = np.asarray(half, dtype=float).copy()
    inside = np.ones(len(pts), dtype=bool)
    for k in range(rounds):
        t = centre[:, None] + half[:, None] * offsets[None, :]
        h = frames(field, (pts[:, None, :] + t[:, :, None] * dirs[:, None, :]).reshape(-1, 2))[0]
        j = np.argmin(np.where(np.isfinite(h), h, np.inf).reshape(t.shape), axis=1)
        if k == 0:
            inside = (j > 0) & (j < SEARCH_SAMPLES - 1)
        centre = t[np.arange(len(pts)), j]
        half = half * 2.0 / (SEARCH_SAMPLES - 1)
    return pts + centre[:, None] * dirs, inside


def core_starts(field: MetricField, n: int = CORE_GRID) -> NDArray:
    """Points on cores ``(k, 2)``, thinnest first.

    From the points of an n × n grid of the box where the anisotropy is at least
    :data:`START_MIN_ANISOTROPY` and h_min, sampled at 0, ±1, ±2 grid cells along
    the short direction, is least inside (a core passes nearby), a line search
    over ±2 cells: two rounds first, which leave out the layers whose anisotropy
    stays below half :data:`CORE_MIN_ANISOTROPY`, then all rounds. Kept: the
    points with the anisotropy and the sag of a core.
    """
    xmin, ymin, xmax, ymax = field.box
    pts = field.sample_points(n)
    h_min, h_max, v_short, _ = frames(field, pts)
    with np.errstate(invalid="ignore"):
        rows = np.flatnonzero(h_max / h_min >= START_MIN_ANISOTROPY)
    cell = max(xmax - xmin, ymax - ymin) / (n - 1)
    offsets = cell * np.arange(-2.0, 3.0)
    q = pts[rows, None, :] + offsets[None, :, None] * v_short[rows, None, :]
    h = frames(field, q.reshape(-1, 2))[0]
    h = np.where(np.isfinite(h), h, np.inf).reshape(len(rows), len(offsets))
    j = np.argmin(h, axis=1)
    rows = rows[(j > 0) & (j < len(offsets) - 1) & (h[np.arange(len(rows)), j] < h[:, 0])]
    half = np.full(len(rows), 2.0 * cell)
    p, inside = least_along(field, pts[rows], v_short[rows], half, rounds=2)
    h_min, h_max, _, _ = frames(field, p)
    with np.errstate(invalid="ignore"):
        rows = rows[inside & (h_max / h_min >= 0.5 * CORE_MIN_ANISOTROPY)]
    p, inside = least_along(field, pts[rows], v_short[rows], half[: len(rows)])
    p = p[inside & field.inside(p)]
    if len(p) == 0:
        return np.zeros((0, 2))
    g, dg = field.evaluate(p, derivatives=True, check=False)
    h_min, h_max, _, _ = frames(field, p)
    with np.errstate(invalid="ignore"):
        good = (h_max / h_min >= CORE_MIN_ANISOTROPY) & (layer_sag(g, dg) >= CORE_MIN_SAG)
    p, h_min = p[good], h_min[good]
    return p[np.argsort(h_min, kind="stable")]


def trace(field: MetricField, start: NDArray) -> tuple[NDArray, bool]:
    """The core through ``start`` as a polyline ``(m, 2)``, and whether it closes.

    Steps of :data:`TRACE_STEP` h_max along the long direction (kept pointing
    the way of the previous step), each projected back on the core by a line
    search along the short direction over as much; a way ends where the
    anisotropy falls below :data:`CORE_MIN_ANISOTROPY`, at the box, or where
    no least is found; the core closes when a step comes back within 0.6 of a
    step of the start (the first way is then all of it).
    """
    ways: list[list[NDArray]] = []
    for sign in (1.0, -1.0):
        p, ahead, way = start, None, []
        for k in range(MAX_TRACE_STEPS):
            h_min, h_max, _, v_long = frames(field, p[None])
            if not h_max[0] / h_min[0] >= CORE_MIN_ANISOTROPY:  # NaN too
                break
            step = TRACE_STEP * h_max[0]
            d = v_long[0] * (sign if ahead is None else np.sign(v_long[0] @ ahead))
            q = p + step * d
            if not field.inside(q):
                break
            v_short = frames(field, q[None])[2]
            q, inside = least_along(field, q[None], v_short, np.array([step]))
            if not (inside[0] and field.inside(q[0])):
                break
            ahead, p = (q[0] - p) / np.linalg.norm(q[0] - p), q[0]
            if k > 3 and np.linalg.norm(p - start) < 0.6 * step:
                return np.array([start, *way]), True
            way.append(p)
        ways.append(way)
    return np.array([*ways[1][::-1], start, *ways[0]]), False


def arc_lengths(field: MetricField, line: NDArray) -> NDArray:
    """Metric length from the first point to each point of a polyline (chords
    measured in the metric at their middles)."""
    d = np.diff(line, axis=0)
    g = field.tensor(0.5 * (line[1:] + line[:-1]), check=False)
    return np.concatenate([[0.0], np.cumsum(np.sqrt(np.einsum("pi,pij,pj->p", d, g, d)))])


def points_on_core(field: MetricField, line: NDArray, arc: NDArray, s: NDArray) -> NDArray:
    """The points of the core at arc lengths ``s``: on the polyline, then projected
    on the core (a chord of the polyline strays from a curved core)."""
    pts = np.column_stack([np.interp(s, arc, line[:, 0]), np.interp(s, arc, line[:, 1])])
    _, h_max, v_short, _ = frames(field, pts)
    q, inside = least_along(field, pts, v_short, TRACE_STEP * h_max)
    return np.where(inside[:, None], q, pts)


def walk(
    field: MetricField,
    at: Callable[[NDArray, NDArray], NDArray],
    totals: NDArray,
    spacing: float,
    max_step: float = np.inf,
) -> list[NDArray]:
    """Arc lengths of walks along several curves at once, each a list starting at 0:
    from the last point, the next is at the arc length where the shortest parabola
    (equation (3), :func:`curvimesh.geodesic.shortest_parabola`) from it is
    ``spacing`` long, interpolated between the first of the trial arc lengths (0.3 to
    1.2 times ``spacing``) whose parabola is that long or longer and the one before,
    and at most ``max_step`` of arc on; a walk ends where no trial within its curve's
    length ``totals[r]`` is. The searches start from the geodesic's bend at the
    chord's middle (``guided``): from the scan alone, a trial of a row 4 rows inside a
    5,700:1 ring (radius 0.219) measured 12.39 where its parabola is 0.80 long (the
    valley in the offset narrower than the scan's step), and the walk stopped there,
    a step 12 % short.

    ``at(r, s)`` gives the points ``(k, 2)`` of curves ``r`` ``(k,)`` at arc lengths
    ``s`` ``(k,)``."""
    n = len(totals)
    s = np.zeros(n)
    last = at(np.arange(n), s)
    walked: list[list[float]] = [[0.0] for _ in range(n)]
    active = np.flatnonzero(totals > 0.0)
    while len(active):
        cand = s[active, None] + spacing * _TRIAL[None, :]
        ok = cand <= totals[active, None]
        rr, jj = np.nonzero(ok)
        length = np.full(cand.shape, np.nan)
        if len(rr):
            ends = at(active[rr], cand[rr, jj])
            length[rr, jj] = shortest_parabola(
                field, last[active[rr]], ends, exact_length=False, remember=False, guided=True
            ).length
        with np.errstate(invalid="ignore"):
            hit = ok & (length >= spacing)
        has = hit.any(axis=1)
        active, cand, length, hit = active[has], cand[has], length[has], hit[has]
        if not len(active):
            break
        k = np.argmax(hit, axis=1)
        i = np.arange(len(active))
        new = cand[i, k]
        mid = k > 0
        km = k[mid]
        lo, hi = length[i[mid], km - 1], length[i[mid], km]
        t = (spacing - lo) / (hi - lo)
        new[mid] = cand[i[mid], km - 1] + t * (cand[i[mid], km] - cand[i[mid], km - 1])
        new = np.minimum(new, s[active] + max_step)
        s[active] = new
        last[active] = at(active, new)
        for r, v in zip(active, new, strict=True):
            walked[r].append(float(v))
    return [np.array(w) for w in walked]


def evened(walked: NDArray, total: float) -> NDArray:
    """The arc lengths of a walk ``walked`` (:func:`walk`, fewer than three: as they are)
    scaled so that its steps, a closing one to ``total`` as long as their mean, reach
    ``total`` (the last walked point is dropped when its gap to ``total`` is under
    half a step)."""
    w = walked
    if len(w) < 3:
        return w
    mean = w[-1] / (len(w) - 1)
    if total - w[-1] < 0.5 * mean:
        w = w[:-1]
        mean = w[-1] / (len(w) - 1)
    return w * (total / (w[-1] + mean))


def place(
    field: MetricField, line: NDArray, closed: bool, spacing: float, max_step: float = np.inf
) -> NDArray:
    """Points ``(k, 2)`` along a traced core, the shortest parabola between successive
    ones (:func:`curvimesh.geodesic.shortest_parabola`, equation (3)) ``spacing`` long,
    and at most ``max_step`` apart in metric length along the core.

    Across a thin curved layer a parabola cannot follow the core's curve as
    closely as the layer is thin: the shortest one between two points of the
    core is longer than the arc between them (a unit arc of the 1,000:1 ring of
    ``metrics/thin_ring.yaml``: 1.45), and the points are nearer along it.
    (Arc steps of 0.95 shortened only where the parabola would pass 1.2 or 1.3
    did worse on the thin rings of bench/robustness: edges of 1.44 – 1.57 left
    where these steps leave none over 1.41.)

    The points are those of a :func:`walk` from the first, each projected on the
    core (:func:`points_on_core`). Around a closed core the last gap is a fraction
    of a step: the walk is :func:`evened` to go round once. An open core that
    crosses the box (:func:`to_box`) is walked from a side, the same way: the
    walk's steps are scaled to reach the other side, and the points on the sides
    are left out (the sides have their own vertices there); with one end on the
    box, the walk starts there and leaves that end out.
    """
    line, at_box = core_polyline(field, line, closed)
    if at_box[1] and not at_box[0]:  # walk from the box
        line, at_box = line[::-1], (True, False)
    arc = arc_lengths(field, line)
    total = arc[-1]
    (walked,) = walk(
        field,
        lambda _, s: points_on_core(field, line, arc, s),
        np.array([total]),
        spacing,
        max_step,
    )
    if closed or at_box[1]:
        walked = evened(walked, total)
    return points_on_core(field, line, arc, walked[1:] if at_box[0] else walked)


def core_polyline(
    field: MetricField, line: NDArray, closed: bool
) -> tuple[NDArray, tuple[bool, bool]]:
    """The polyline a traced core is walked along, and whether each end lies on the
    box: a closed core's with its first point again at the end, an open core's
    extended to the box where it crosses it (:func:`to_box`)."""
    if closed:
        return np.vstack([line, line[:1]]), (False, False)
    return to_box(field, line)


def to_box(field: MetricField, line: NDArray) -> tuple[NDArray, tuple[bool, bool]]:
    """An open core ``(m, 2)`` extended to the box at each end that its trace stopped
    near (:func:`trace` stops where a step would leave the box), and whether each
    end now lies on the box.

    An end within 1.5 trace steps of a side along its last chord is extended to
    that side, then moved along the side to where h_min is least (the core's
    crossing: a straight extension strays from a curved core by some of its short
    sizes, and the chord to it would be measured across the layer).

    Why: the side's own vertices (:func:`curvimesh.boundary.discretize_box`) stand
    where the core crosses it, so a point laid on the core a fraction of a step
    inside is dropped as too close to them, and the layer's first column is then up
    to two steps from the side (edges of 1.4 - 1.6 from the crossing on the
    1,000:1 cubic of bench/robustness u74). :func:`place` walks from the side.
    """
    xmin, ymin, xmax, ymax = field.box
    lo, hi = np.array([xmin, ymin]), np.array([xmax, ymax])
    ends, flags = [None, None], [False, False]
    for k, (end, prev) in enumerate(((line[0], line[1]), (line[-1], line[-2]))):
        d = (end - prev) / np.linalg.norm(end - prev)
        with np.errstate(divide="ignore", invalid="ignore"):
            hits = np.concatenate([(lo - end) / d, (hi - end) / d])  # x, y, x, y faces
        hits = np.where(hits >= 0.0, hits, np.inf)
        face = int(np.argmin(hits))
        reach = 1.5 * TRACE_STEP * frames(field, end[None])[1][0]
        if not hits[face] <= reach:
            continue
        on_side = np.clip(end + hits[face] * d, lo, hi)
        along = np.array([[0.0, 1.0]]) if face % 2 == 0 else np.array([[1.0, 0.0]])
        q, inside = least_along(field, on_side[None], along, np.array([reach]))
        ends[k] = np.clip(q[0], lo, hi) if inside[0] else on_side
        flags[k] = True
    line = np.vstack([p for p in (ends[0], line, ends[1]) if p is not None])
    return line, (flags[0], flags[1])


#: The traced cores of each field (dropped with the field), and their points by
#: spacing: every run of :func:`curvimesh.adapt.adapt` samples the same field again.
_LINES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_CORES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def layer_cores(field: MetricField) -> list[tuple[NDArray, bool]]:
    """The cores of the field's thin curved layers, thinnest first: each a polyline
    ``(m, 2)`` (:func:`trace`) and whether it closes; an empty list where there are none.

    The thinnest start (:func:`core_starts`) is traced, the starts within a trace
    step of its polyline are dropped, and so on, for at most :data:`MAX_CORES`
    cores. A trace of fewer than three points is no core.
    """
    if field in _LINES:
        return list(_LINES[field])
    starts = core_starts(field)
    reach = TRACE_STEP * frames(field, starts)[1]
    out = []
    while len(starts) and len(out) < MAX_CORES:
        line, closed = trace(field, starts[0])
        if len(line) >= 3:
            out.append((line, closed))
        far = cKDTree(line).query(starts)[0] > reach
        far[0] = False
        starts, reach = starts[far], reach[far]
    _LINES[field] = tuple(out)
    return list(out)


def layer_core_points(field: MetricField, spacing: float) -> NDArray:
    """Points ``(k, 2)`` along the cores of the field's thin curved layers
    (:func:`layer_cores`, each laid by :func:`place`), thinnest core first; ``(0, 2)`` where
    there are none."""
    per_field = _CORES.setdefault(field, {})
    if spacing in per_field:
        return per_field[spacing].copy()
    out = [place(field, line, closed, spacing) for line, closed in layer_cores(field)]
    per_field[spacing] = np.concatenate(out) if out else np.zeros((0, 2))
    return per_field[spacing].copy()
