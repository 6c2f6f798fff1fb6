"""Thin curved layers sampled row by row, each row spaced by its own parabolas
(beyond the paper).

Along the core of a thin curved layer (:mod:`curvimesh.cores`) a quadratic edge
cannot follow the curve as closely as the layer is thin, so the points laid on the
core are nearer along it than a unit arc (:func:`curvimesh.cores.place`): on the
1,000:1 sine layer of bench/robustness ``u56`` they are 0.53 – 0.72 long sizes apart
where the parabola between them is 0.95. A few short sizes off the core the layer
is wider and a parabola follows it better: between the points shot straight across
from those core points it is 0.6 two rows out, under ``min_dist``, so the frontal
sampling (:func:`curvimesh.sampling._grow`) ends every other column there and
leaves gaps of two columns, whose edges measure 1.6 and more.

Here each row gets its own spacing. A fine polyline of the core (:func:`fine_core`)
is carried across the layer one unit at a time on each side, every point shot
along the short direction where it stands (:func:`next_row`: the lines of the
short direction, which the charts of :mod:`curvimesh.charts` take as the layer's
columns; a geodesic continued from row to row drifts along a layer whose width
grows unevenly, 15 – 50 long sizes after six rows on ``u58``). Each row is walked
on its own, successive points a parabola of ``spacing`` apart
(:func:`curvimesh.cores.walk`, as :func:`curvimesh.cores.place` walks the core),
and its points are shot from the
core again at the places found (:func:`on_row`), so that they lie on the row. A
row thins out one point at a time as the parabolas along it shorten. The rows of
a side end after the first one that has no fewer points than the row before: the
fronts grow on from there.

:func:`curvimesh.adapt.adapt` samples row by row in its first run
(:func:`curvimesh.adapt.first_run`), and the swap stage triangulates such a layer
again in its own coordinates (:func:`curvimesh.charts.rebuilt`), where its rows are
lines. Measured without retries, sampled by the fronts → row by row: ``u56`` 97.6 %
of the edges in [0.7, 1.4] and edges up to 7.29 → 99.94 % and 1.69; ``u72`` (800:1
about an ellipse) 99.83 % and 1.48 → 100 % and 1.400; ``u58`` (2,000:1 about an
ellipse) 92.8 % and 15.7 → 100 % and 1.400. Before the layer was triangulated
again, Lawson's flips from the metric Delaunay triangulation towards the layer's
own (:func:`curvimesh.charts.flipped`) stopped on its folds, which staggered rows
make worst (a ring 0.05 from a side, ``u73``, kept edges of 11.7), and the rows
were a later run. A P2 triangle one row thick is valid only so long (on a 5,000:1
ring its base on the core at most 0.7 – 0.8 long sizes, on the fourth row 1.1):
capping the walk's steps so did worse.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from curvimesh.cores import (
    arc_lengths,
    core_polyline,
    evened,
    frames,
    layer_cores,
    place,
    points_on_core,
    walk,
)
from curvimesh.geodesic import shoot
from curvimesh.metric import MetricField

#: Most rows on each side of a core.
MAX_ROWS = 400
#: Most metric length along the core between two of its points, times the step. The
#: parabola spacing lays them 0.54 apart where a sine layer turns (the parabola cannot
#: follow the inflection) but 0.84 at its crests (it follows them), where the triangles
#: one row thick on that base are invalid as images of the chart's
#: (:func:`curvimesh.charts.rebuilt`): they were flipped into an edge across the core,
#: 2.0 long, and the first run of bench/robustness u56 kept 1.69. At 0.75: 1.402, and
#: u53 1.495 → 1.411; at 0.8, 1.71. Measured on the 25 fields with cores (first run,
#: seed 0): every other field within the targets as before, the worst efficiency 1.126
#: (u07, unchanged), four 0.04 – 0.07 more (u24, u57, u60, u71), six less.
CORE_MAX_STEP = 0.75
#: Step of the fine polyline of the core the rows are shot from, times ``spacing``.
#: The walk measures parabolas between points on the chords of the fine rows, which
#: stray from the row by their sag: at 0.05 up to half a short size of a 5,000:1
#: ring of radius 0.3 (bench/robustness u45, whose mesh then kept edges of 18), at
#: 0.01 a fiftieth.
FINE_STEP = 0.01


def _runs(alive: NDArray, closed: bool) -> list[NDArray]:
    """Index runs ``(m,)`` of consecutive True entries of ``alive``; with ``closed``
    a run may wrap round the end. One run of every index when all are alive."""
    n = len(alive)
    if alive.all():
        return [np.arange(n)]
    idx = np.flatnonzero(alive)
    if len(idx) == 0:
        return []
    cuts = np.flatnonzero(np.diff(idx) > 1) + 1
    runs = np.split(idx, cuts)
    if closed and len(runs) > 1 and runs[0][0] == 0 and runs[-1][-1] == n - 1:
        runs = [np.concatenate([runs[-1], runs[0]]), *runs[1:-1]]
    return runs


@dataclass(frozen=True)
class Core:
    """A core's polyline ``poly`` ``(m, 2)`` with its metric arc lengths ``arc``
    ``(m,)`` (``total`` the last), whether it closes, and its fine points ``points``
    ``(n, 2)`` at arc lengths ``s`` ``(n,)`` with the short direction ``v`` ``(n, 2)``
    at each, turned to the left of the way along the polyline."""

    poly: NDArray
    arc: NDArray
    total: float
    closed: bool
    s: NDArray
    points: NDArray
    v: NDArray


def fine_core(field: MetricField, poly: NDArray, closed: bool, spacing: float) -> Core:
    """The core of the polyline ``poly`` (closed: its last point is its first) with
    fine points every :data:`FINE_STEP` × ``spacing`` of metric arc, projected on the
    core (:func:`curvimesh.cores.points_on_core`)."""
    arc = arc_lengths(field, poly)
    total = float(arc[-1])
    n = max(int(np.ceil(total / (FINE_STEP * spacing))), 2)
    s = np.linspace(0.0, total, n + 1)
    if closed:
        s = s[:-1]
    pts = points_on_core(field, poly, arc, s)
    _, _, v, _ = frames(field, pts)
    if closed:
        tangent = np.roll(pts, -1, axis=0) - np.roll(pts, 1, axis=0)
    else:
        tangent = np.gradient(pts, axis=0)
    side = np.sign(tangent[:, 0] * v[:, 1] - tangent[:, 1] * v[:, 0])
    return Core(poly, arc, total, closed, s, pts, v * side[:, None])


def next_row(
    field: MetricField, core: NDArray, row: NDArray, vel: NDArray, closed: bool, step: float
) -> tuple[NDArray, NDArray]:
    """The fine row ``(n, 2)`` one ``step`` further across the layer than ``row``
    (NaN where a point is dead), and the velocities that reached its points: each
    live point shot (:func:`curvimesh.geodesic.shoot`) along the short direction
    where it stands, turned the way of the velocity ``vel[i]`` that reached it; dead
    where the shot fails or leaves the box, or where the row folds (its chord to the
    next point turns against the core's ``core`` ``(n, 2)``)."""
    live = np.flatnonzero(np.isfinite(row).all(axis=1))
    new = np.full_like(row, np.nan)
    vel = vel.copy()
    if len(live):
        v_short = frames(field, row[live])[2]
        turn = np.sign(np.einsum("ij,ij->i", v_short, vel[live]))
        shot = shoot(field, row[live], v_short * turn[:, None], step)
        ok = shot.ok & field.inside(shot.end)
        new[live[ok]] = shot.end[ok]
        vel[live[ok]] = shot.velocity[ok]
    chord = np.roll(new, -1, axis=0) - new
    back = np.einsum("ij,ij->i", chord, np.roll(core, -1, axis=0) - core) <= 0.0
    if not closed:
        back[-1] = False
    back &= np.isfinite(chord).all(axis=1)
    new[back | np.roll(back, 1)] = np.nan
    return new, vel


def row_places(
    field: MetricField,
    rows: list[NDArray],
    closed: bool,
    to_ends: bool,
    spacing: float,
) -> list[tuple[NDArray, NDArray, NDArray]]:
    """Where the points of each fine row (:func:`next_row`) go, walked at once
    (:func:`curvimesh.cores.walk`) on the row's polyline: a closed row whole, evenly
    round (:func:`curvimesh.cores.evened`); every run of live points otherwise from
    its first, and where ``to_ends`` (the core crosses the box, so that the row's
    runs end near its sides) evenly to its last, both ends left out. Each point as
    the fine indices ``i``, ``j`` of the chord it falls on and its fraction ``f`` of
    the way, ``(k,)`` each."""
    polys, runs, whole, owner = [], [], [], []
    for k, row in enumerate(rows):
        alive = np.isfinite(row).all(axis=1)
        for run in _runs(alive, closed):
            if len(run) < 2:
                continue
            full = len(run) == len(row)
            if full and closed:
                run = np.append(run, run[0])
            polys.append(row[run])
            runs.append(run)
            whole.append(full)
            owner.append(k)
    if not polys:
        return [(np.zeros(0, int), np.zeros(0, int), np.zeros(0)) for _ in rows]
    arcs = [arc_lengths(field, p) for p in polys]
    totals = np.array([a[-1] for a in arcs])

    def at(r: NDArray, s: NDArray) -> NDArray:
        out = np.empty((len(r), 2))
        for q in np.unique(r):
            k = r == q
            out[k, 0] = np.interp(s[k], arcs[q], polys[q][:, 0])
            out[k, 1] = np.interp(s[k], arcs[q], polys[q][:, 1])
        return out

    walks = walk(field, at, totals, spacing)
    out: list[list[tuple[NDArray, NDArray, NDArray]]] = [[] for _ in rows]
    for q, w in enumerate(walks):
        if whole[q] and closed:
            w = evened(w, totals[q])
        elif to_ends and not closed:
            w = evened(w, totals[q])[1:]
        pos = np.interp(w, arcs[q], np.arange(len(runs[q]), dtype=float))
        lo = np.minimum(np.floor(pos).astype(int), len(runs[q]) - 2)
        out[owner[q]].append((runs[q][lo], runs[q][lo + 1], pos - lo))
    return [
        tuple(np.concatenate(parts) for parts in zip(*o, strict=True))
        if o
        else (np.zeros(0, int), np.zeros(0, int), np.zeros(0))
        for o in out
    ]


def on_row(
    field: MetricField,
    core: Core,
    rows: list[NDArray],
    place_: tuple[NDArray, NDArray, NDArray],
    step: float,
) -> NDArray:
    """The points ``(k, 2)`` of the last of the fine rows ``rows`` at the places
    ``place_`` (:func:`row_places`), exactly: the core's point at the same fraction
    of the chord (:func:`curvimesh.cores.points_on_core`), shot across one ``step``
    at a time along the short direction, as the fine rows were (a point between two
    fine ones strays from the row by the chord's sag, up to half a short size on a
    5,000:1 ring at fine steps of 0.05). A point whose shot fails is left out."""
    i, j, f = place_
    if len(i) == 0:
        return np.zeros((0, 2))
    si, sj = core.s[i], core.s[j]
    sj = np.where(sj < si, sj + core.total, sj)  # the closing chord of a ring
    s = np.mod(si + f * (sj - si), core.total) if core.closed else si + f * (sj - si)
    x = points_on_core(field, core.poly, core.arc, s)
    ok = np.isfinite(x).all(axis=1)
    near = np.where(f < 0.5, i, j)
    before = core.points
    for row in rows:
        way = row[near] - before[near]
        v = frames(field, x)[2]
        v = v * np.sign(np.einsum("ij,ij->i", v, way))[:, None]
        shot = shoot(field, x, v, step)
        ok &= shot.ok & field.inside(shot.end)
        x, before = shot.end, row
    return x[ok]


#: Per field (dropped with it), by spacing: the rows of each core.
_ROWS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def layer_rows(
    field: MetricField, spacing: float, step: float = 1.0
) -> list[tuple[NDArray, list[list[NDArray]]]]:
    """For each core of the field's thin curved layers (:func:`curvimesh.cores.layer_cores`),
    thinnest first: the points laid on it (:func:`curvimesh.cores.place`) and, per
    side (left of the core's way, right), the points of its rows outward.

    Each fine row is traced one ``step`` across from the last (:func:`next_row`),
    walked (:func:`row_places`), and its points shot from the core
    (:func:`on_row`). A side's rows end after the
    first whose walk has no fewer points than the row before it (the core's points
    the first row before): the parabolas along it have stopped lengthening, and the
    columns shot across from there keep their spacing. A side whose first row has as
    many points as the core, or more, has none (its columns need not thin out); a row
    of fewer than three points is left out and ends its side; at most
    :data:`MAX_ROWS`."""
    per_field = _ROWS.setdefault(field, {})
    key = (spacing, step)
    if key not in per_field:
        per_field[key] = [
            _core_rows(field, line, closed, spacing, step) for line, closed in layer_cores(field)
        ]
    return [(c.copy(), [[r.copy() for r in rows] for rows in sides]) for c, sides in per_field[key]]


def _core_rows(
    field: MetricField, line: NDArray, closed: bool, spacing: float, step: float
) -> tuple[NDArray, list[list[NDArray]]]:
    """The points laid on one core and its rows on each side (:func:`layer_rows`)."""
    poly, at_box = core_polyline(field, line, closed)
    to_ends = at_box[0] and at_box[1]
    core = fine_core(field, poly, closed, spacing)
    laid = place(field, line, closed, spacing, CORE_MAX_STEP * step)
    fine: dict[float, list[NDArray]] = {1.0: [], -1.0: []}
    ways = {1.0: core.v, -1.0: -core.v}
    counts = {1.0: len(laid), -1.0: len(laid)}
    sides: dict[float, list[NDArray]] = {1.0: [], -1.0: []}
    active = [1.0, -1.0]
    for _ in range(MAX_ROWS):
        if not active:
            break
        for sign in active:
            last = fine[sign][-1] if fine[sign] else core.points
            row, ways[sign] = next_row(field, core.points, last, ways[sign], closed, step)
            fine[sign].append(row)
        places = row_places(field, [fine[sign][-1] for sign in active], closed, to_ends, spacing)
        still = []
        for sign, where in zip(active, places, strict=True):
            if len(where[0]) < 3:
                continue
            sides[sign].append(on_row(field, core, fine[sign], where, step))
            if len(where[0]) < counts[sign]:
                still.append(sign)
            counts[sign] = len(where[0])
        active = still
    out = [sides[1.0], sides[-1.0]]
    for i in (0, 1):
        if len(out[i]) == 1 and len(out[i][0]) >= len(laid):
            out[i] = []
    return laid, out
