"""Frontal point sampling along the metric's principal directions (paper Algorithm 1).

Starting from the boundary vertices, every point of the current front shoots
four geodesics along ±v₁, ±v₂, the eigenvectors of g at the point (paper
section 3), or, by default where the metric's frame turns slowly, three along
a hexagonal lattice (below). A tentative end point is kept when it lies in the box, far enough
from the boundary, and not too close to any kept point, closeness being
measured by the length of the shortest parabola (equation (3)) and the
candidates found through an R-tree. The kept points form the next front.

Two departures from the paper's pseudo-code, both in its spirit:

* a tentative point is checked against every point kept so far, including the
  ones still waiting in the queue, so that two queued points are never closer
  than ``min_dist`` (Algorithm 1 as printed checks only the popped ones);
* fronts are processed as batches (all candidates of a front shot at once),
  and conflicts between candidates of one front are resolved greedily in
  their deterministic order (parent order, then direction +v₁, −v₁, +v₂, −v₂).

A point does not shoot back along the geodesic that reached it (within 20° in
the metric, :func:`backward`): that candidate would land next to its parent
and be refused; a quarter of the shots are spared.

The paper's fix of section 5.1 is applied: the shooting length is shortened so
that the parabola between a point and its child comes out of length
``spacing`` (a unit geodesic's end can be farther than 1 along a parabola).
Where the metric's frame turns fast, the parabolas measured, here and in the
closeness test, have a free middle node (:mod:`curvimesh.freenode`): the
symmetric parabola of a unit step along a tightly bent front is several
units long, and the shot would be cut to a third and refused.

Hexagons (beyond the paper; ``SamplingOptions.hexagons``). Where the metric
is nearly constant over an edge, points shot along both principal directions
make a grid of squares in the metric, which Delaunay cuts into right
triangles of quality (4) √3/2 ≈ 0.866 — the more of the mesh the finer the
metric, so that the mean quality fell from 0.955 at 10³ vertices to 0.922 at
10⁶ (toy). A point reached by a geodesic with velocity a instead shoots at
0° and ±60° from a, the angles measured in g (:func:`turned_directions`), and
a boundary vertex at 60° and 120° from its side: in a constant metric these
are the nodes of the lattice of equilateral triangles of side ``spacing``
that grows from the boundary, each new row half a step along. The shots at
±120° would land on the parent's other children and are not made. Where the
principal directions turn by :data:`HEX_MAX_TURN` or more per unit length
(:func:`curvimesh.metric.frame_turn`: curved fronts, circles about a
singular centre), or, with ``SamplingOptions.max_sag`` (:data:`HEX_MAX_SAG` in
the second run of :func:`curvimesh.adapt.adapt`), where a unit chord along the
long size strays that many short sizes or more from the layer
(:func:`curvimesh.metric.layer_sag`: thin layers that curve slowly), at the
point or one unit ahead of it along a shot, a lattice carried along geodesics
shears against the layers of the metric, and the points there shoot along the
principal directions as above (the turn and the sag are counted where the
anisotropy is 10 or more; below it, a turning frame shapes nothing and the
hexagons are used); a point of either kind may be the parent of the other.

Cores (beyond the paper; ``SamplingOptions.cores``). Where the field has thin
curved layers (anisotropy 100 or more, :mod:`curvimesh.cores`), the fronts
first grow from a row of points laid along each layer's core, and only then
from the boundary: the layer's columns all start on its core.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from curvimesh import kernels
from curvimesh.boundary import BoundaryMesh
from curvimesh.cores import layer_core_points
from curvimesh.freenode import any_closer_in_index, parabola_verdicts, shortest_parabola
from curvimesh.geodesic import (
    PAIR_BLOCK,
    offset_alpha,
    parabola_length_rule,
    shoot,
    unit_velocity,
)
from curvimesh.metric import MetricField, frame_turn, layer_sag, smallest_eigenvalue
from curvimesh.spatial import PointIndex, pairs_within_boxes
from curvimesh.tensors import intersect_components


@dataclass(frozen=True)
class SamplingOptions:
    """Parameters of Algorithm 1.

    ``spacing``: target metric length of the parabola between a point and its
    child; ``min_dist``: no two points closer (shortest parabola) than this;
    ``fill_dist``: the same for the points that fill gaps
    (:func:`curvimesh.fill.fill_gaps`); ``boundary_dist``: no interior point
    closer than this to a side (metric length of the perpendicular segment);
    ``search``: Euclidean search radius as a multiple of ``min_dist`` times
    the largest local size; ``max_points`` bounds the run.

    ``hexagons`` (default) shoots along a hexagonal lattice where the frame
    turns slowly (module docstring), else along the principal directions
    only (the paper's Algorithm 1); ``max_sag`` (default: no bound) keeps the
    lattice out of thin curved layers, where a unit chord along the layer strays
    that many short sizes or more from it (:data:`HEX_MAX_SAG`); ``cores`` (default)
    grows the fronts from the cores of thin curved layers first
    (:func:`sample_points`), and with ``rows`` (not the default) from their rows,
    each spaced by its own parabolas (:mod:`curvimesh.rows`; the caller lays them,
    :func:`curvimesh.adapt.sample`). ``spacing`` (None: :attr:`step`'s
    default) is 1 with hexagons, whose edges are all ``spacing`` long where
    the metric is constant, and 0.98 without: points shot along both
    principal directions make, where the metric varies slowly, a grid of
    squares of side ``spacing`` (unit squares in the metric), whose
    diagonals, √2 × spacing, must be in the unit range [0.7, 1.4]; with a
    spacing of 1 they are 1.414, just too long, and gap filling would put a
    point in every square (on a wall boundary layer, 1.35 times the ideal
    triangle count instead of 0.95).
    A gap point must be ``fill_dist`` = 0.75 from the others, so that only
    gaps of 1.5 or more (the longest edge we accept) are filled: a point in
    a gap between 1.4 and 1.5 would make edges of 0.7 to 0.75 where moving
    the vertices (:mod:`curvimesh.smooth`) does better.
    """

    spacing: float | None = None
    hexagons: bool = True
    max_sag: float = math.inf
    min_dist: float = 0.7
    fill_dist: float = 0.75
    boundary_dist: float = 0.6
    search: float = 2.0
    length_fix: bool = True
    shoot_tol: float = 1e-6
    max_points: int = 2_000_000
    cores: bool = True
    rows: bool = False

    @property
    def step(self) -> float:
        """The metric length between a point and its child: ``spacing``, or 1 with
        hexagons and 0.98 without (class docstring)."""
        if self.spacing is not None:
            return self.spacing
        return 1.0 if self.hexagons else 0.98


#: Turn of the principal directions per unit length (radians, 10°) from which the
#: front shoots along them instead of along hexagons, at the point or one unit ahead
#: of it (module docstring). Measured on the 27 metrics of bench/robustness at
#: three seeds, with the shift stage's quality pass at 0.3: hexagons everywhere
#: left edges of 1.6 – 3.5 beside the singular centres of concentric fields and
#: along tightly curved fronts (70 of 81 meshes met the targets; the paper's
#: directions everywhere: 75); hexagons where the turn is below 20° at the point:
#: 77. With the pass at 0.8: the paper's directions 75 again (u21 and u23 keep
#: edges of 1.52 – 1.54), 20° at the point 78, but edges of 4.6 left at the
#: tips of metrics/hard/tight_front.yaml (81° per unit length there), and of
#: 1.5 – 1.8 with a threshold of 5 – 15° at the point alone; below 10° at the
#: point and one unit ahead: 78, and the tight front within 0.7 – 1.4 (20° with
#: the look ahead: 3.07).
HEX_MAX_TURN = math.radians(10.0)

#: Short sizes a unit chord along a curved layer may stray from it
#: (:func:`curvimesh.metric.layer_sag`) where a hexagonal lattice is laid in the
#: second run of :func:`curvimesh.adapt.adapt` (``SamplingOptions.max_sag``; module
#: docstring), made when the first leaves an edge longer than 1.5. A thin layer can
#: curve slowly per unit length and still bend away from a row of its lattice by
#: many of its short sizes: a circular layer of 3,000:1 about a circle of radius 0.4
#: (0.05 along it) turns 7° per unit and strays 45 short sizes; with the lattice laid
#: there, the first run left an edge of 15.1, and a second without the lattice
#: anywhere took 84 s more and made 1.18 times the ideal triangle count. Measured
#: with the bound in every run, on 6 circular layers of 500:1 – 5,000:1 turning
#: 5 – 9.5° per unit, a sine wall of 1,000:1 and the 9 metrics of
#: bench/robustness and metrics/hard that have a sag of 0.5 or more where the
#: frame turns slowly, at seeds 0 – 2: without this bound 38 of 48 meshes met the
#: targets (14 minutes; the misses: efficiency 1.16 – 1.18 after the second run, or
#: edges of 4.7 – 10.4); with 1, 46 (5 minutes); with 0.5, 45 (4 minutes; one an
#: edge of 0.699 left by relocation, since mended: :mod:`curvimesh.smooth` asks
#: :func:`too_close`).
#: The other misses: a layer of 5,000:1 at seeds 1 and 2, edges of 9.3 – 10.6. With
#: 0.25 the tight front (metrics/hard) needed its second run at seed 0. Not a
#: bound of the first run: a wall layer of 1,000:1 along the parabola
#: y = 0.3 + (x − 0.5)² / 2 (radius of curvature 1 at least, 0.05 along it, a sag of
#: 5.7 at most) is meshed with the lattice everywhere at 0.705 – 1.399 and 0.98 times
#: the ideal count (seed 0), with the bound at 0.5 at 0.700 – 1.427 and 1.15 – 1.16
#: times it (seeds 0 – 2; at seed 0, 1.13 with 1, 1.09 with 2, 1.00 with 4). As the
#: second run's bound, the robustness metrics give 146 of 159 meshes within every
#: target (u50 and u51, such circular layers, at every seed).
HEX_MAX_SAG = 0.5

#: The unit tangent of each side of the box (bottom, right, top, left), counter-clockwise.
_SIDE_TANGENTS = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])

#: The hexagonal lattice's shots, in multiples of 60° from the reference: from a
#: boundary vertex (reference: its side, the domain on the left), from a point
#: reached by a shot (reference: its arrival velocity).
BOUNDARY_TURNS = (1, 2)
FRONT_TURNS = (-1, 0, 1)


def turned_directions(g: NDArray, ref: NDArray, turns: tuple[int, ...]) -> NDArray:
    """Directions ``(n, k, 2)`` at the angles 60° × ``turns`` from ``ref`` ``(n, 2)``,
    angles measured in the metric ``g`` ``(n, 2, 2)`` (counter-clockwise), unit in it.

    With u = ref / |ref|_g and w = J g u / |J g u|_g (J the rotation by 90°),
    uᵀ g w = (g u) · J (g u) = 0 and det(u, w) = uᵀ g u > 0: (u, w) is a
    positively oriented orthonormal frame of g, and the direction at angle θ
    is cos θ u + sin θ w.
    """
    u = ref / np.sqrt(np.einsum("ni,nij,nj->n", ref, g, ref))[:, None]
    gu = np.einsum("nij,nj->ni", g, u)
    w = np.stack([-gu[:, 1], gu[:, 0]], axis=1)
    w /= np.sqrt(np.einsum("ni,nij,nj->n", w, g, w))[:, None]
    theta = np.radians(60.0 * np.asarray(turns, dtype=float))
    cos, sin = np.cos(theta)[None, :, None], np.sin(theta)[None, :, None]
    return cos * u[:, None, :] + sin * w[:, None, :]


def principal_directions(g: NDArray) -> NDArray:
    """Unit eigenvectors ``(n, 4, 2)``: +v₁, −v₁, +v₂, −v₂ of the tensors ``g`` ``(n, 2, 2)``."""
    _, vec = np.linalg.eigh(g)
    v1, v2 = vec[:, :, 0], vec[:, :, 1]
    return np.stack([v1, -v1, v2, -v2], axis=1)


#: A direction within 20° (in the metric) of the way back along the geodesic that
#: reached a point is not shot (:func:`backward`).
BACK_COS = math.cos(math.radians(20.0))


def backward(g: NDArray, dirs: NDArray, arrival: NDArray) -> NDArray:
    """Which directions ``dirs`` ``(n, 4, 2)`` at points of metric ``g`` ``(n, 2, 2)`` point
    back along the geodesic that reached each point (velocity ``arrival`` ``(n, 2)``;
    NaN for none): those whose angle to −arrival, measured in the metric, is at most
    20° (cosine ≥ :data:`BACK_COS`), ``(n, 4)``.

    A geodesic shot from p at an angle θ to −arrival leaves the one it retraces
    (which leads back to the point p was shot from, ``spacing`` away) by an angle θ:
    where the metric is flat at the scale of an edge it ends 2 sin(θ/2) × spacing
    ≤ 0.34 from that point, well within ``min_dist``, so that the candidate
    would be rejected; it is not shot at all. (Three toys at 10⁴ vertices:
    9,156 of 37,760 candidates point back so, and no such candidate is kept.)
    """
    gd = np.einsum("nij,nkj->nki", g, dirs)  # g d for each direction
    dgd = np.einsum("nki,nki->nk", dirs, gd)
    vgv = np.einsum("ni,nij,nj->n", arrival, g, arrival)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = -np.einsum("nki,ni->nk", gd, arrival) / np.sqrt(dgd * vgv[:, None])
    return np.nan_to_num(cos, nan=-1.0) >= BACK_COS


#: Where :func:`search_regions` samples the metric besides the centre: the corners and
#: the side midpoints of the box of the local largest size (in half-widths).
_BOX_SAMPLES = np.array(
    [[1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [1, -1], [-1, 1], [-1, -1]], dtype=float
)

#: Allowance of :func:`search_regions` for the sizes' growth beyond those sampled: the
#: region reaches 0.7 × radius times the sampled sizes in each direction.
SAMPLED_GROWTH = 0.7


@dataclass(frozen=True)
class SearchRegions:
    """Where each point's close neighbours may lie: the ellipses (x − c)ᵀ Q (x − c) ≤ 1
    about the points c, ``quad`` ``(n, 3)`` = (Q11, Q12, Q22), inside the boxes of
    half-widths ``halfwidth`` ``(n, 2)``."""

    halfwidth: NDArray
    quad: NDArray

    def __getitem__(self, rows) -> SearchRegions:
        return SearchRegions(self.halfwidth[rows], self.quad[rows])


def search_halfwidths(field: MetricField, pts: NDArray, radius: float) -> NDArray:
    """Half-widths ``(n, 2)`` of the boxes of :func:`search_regions`."""
    return search_regions(field, pts, radius).halfwidth


def _size_tensors(g: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """g⁻¹ of tensors ``(..., 2, 2)`` as components (s11, s12, s22): the squared sizes."""
    with np.errstate(invalid="ignore", divide="ignore"):
        det = g[..., 0, 0] * g[..., 1, 1] - g[..., 0, 1] ** 2
        return g[..., 1, 1] / det, -g[..., 0, 1] / det, g[..., 0, 0] / det


def search_regions(field: MetricField, pts: NDArray, radius: float) -> SearchRegions:
    """Regions holding the points within metric distance radius / 2 of each point, with
    room for the sizes to grow (:class:`SearchRegions`).

    A curve of metric length D from c stays, where the metric's size tensor g⁻¹ is
    at most γ² U (every size at most γ times U's in its direction), within
    (x − c)ᵀ U⁻¹ (x − c) ≤ (γ D)². U is the union of the size tensors sampled at
    the centre, corners and side midpoints of the box of half-width radius × h (h
    the local largest size), clipped to the domain: their intersection as sizes
    (:func:`curvimesh.tensors.intersect_components`), the smallest tensor of the
    simultaneous reduction above each (Frey & George, §10.6, on g⁻¹). With
    γ D = SAMPLED_GROWTH × radius (for radius = 2 × min_dist and D = min_dist: a
    growth of 1.4 beyond the sizes sampled) that ellipse is the region, inside
    the square box of the largest size sampled (the bound of the isotropic
    argument, a point at distance D lying within D × H, H the largest size on
    the way). Where the metric is anisotropic and turns slowly the ellipse
    holds a fraction of the square's points (three toys at 3.9·10⁴ vertices:
    27,009 against 75,166); where it turns within the box the union widens it
    (across curved anisotropic layers the local metric ball alone misses
    neighbours).
    """
    pts = np.asarray(pts, dtype=float).reshape(-1, 2)
    n = len(pts)
    reach = SAMPLED_GROWTH * radius
    cm = field.kernel
    if cm is not None:  # the same operations, compiled
        half, quad = np.empty((n, 2)), np.empty((n, 3))
        box = np.array(field.box, dtype=float)
        kernels.search_regions(
            cm.g, np.ascontiguousarray(pts), box, _BOX_SAMPLES, float(radius), reach, half, quad
        )
        return SearchRegions(half, quad)
    g0 = field.tensor(pts, check=False)
    with np.errstate(invalid="ignore", divide="ignore"):
        h = 1.0 / np.sqrt(smallest_eigenvalue(g0))
    h[~np.isfinite(h)] = 0.0
    xmin, ymin, xmax, ymax = field.box
    probe = pts[:, None, :] + _BOX_SAMPLES[None] * (radius * h)[:, None, None]
    probe[..., 0] = np.clip(probe[..., 0], xmin, xmax)
    probe[..., 1] = np.clip(probe[..., 1], ymin, ymax)
    g = np.concatenate(
        [g0[:, None], field.tensor(probe.reshape(-1, 2), check=False).reshape(n, -1, 2, 2)],
        axis=1,
    )  # (n, 9, 2, 2): the centre, then the box samples
    with np.errstate(invalid="ignore", divide="ignore"):
        size = 1.0 / np.sqrt(smallest_eigenvalue(g[:, 1:].reshape(-1, 2, 2)).reshape(n, -1))
    size[~np.isfinite(size)] = 0.0
    hw = reach * np.maximum(size.max(axis=1), h)
    s11, s12, s22 = _size_tensors(g)
    ok = np.isfinite(s11) & np.isfinite(s12) & np.isfinite(s22) & (s11 > 0)
    ok &= s11 * s22 - s12 * s12 > 0
    # the union of the defined samples (an undefined one repeats the first defined)
    first = np.argmax(ok, axis=1)
    rows = np.arange(n)
    u = [c[rows, first] for c in (s11, s12, s22)]
    with np.errstate(all="ignore"):
        for k in range(1, g.shape[1]):
            union = intersect_components(tuple(u), (s11[:, k], s12[:, k], s22[:, k]))
            u = [np.where(ok[:, k], a, b) for a, b in zip(union, u, strict=True)]
        u11, u12, u22 = u
        det = u11 * u22 - u12 * u12
        quad = np.column_stack([u22, -u12, u11]) / (det * reach * reach)[:, None]
        box = np.minimum(reach * np.sqrt(np.column_stack([u11, u22])), hw[:, None])
    # no defined sample: the square of the local size (h = 0: the point alone)
    bad = ~(np.isfinite(quad).all(axis=1) & np.isfinite(box).all(axis=1) & (det > 0))
    if bad.any():
        with np.errstate(divide="ignore"):
            iso = 1.0 / (hw[bad] * hw[bad])
        quad[bad] = np.column_stack([iso, np.zeros(int(bad.sum())), iso])
        box[bad] = hw[bad, None]
    return SearchRegions(box, quad)


def too_close(field: MetricField, a: NDArray, b: NDArray, min_dist: float) -> NDArray:
    """Whether the shortest parabola between rows of a and b is shorter than min_dist ``(p,)``.

    Pairs are tested in blocks of :data:`PAIR_BLOCK` (see :func:`_too_close_block`).
    """
    close = np.zeros(len(a), dtype=bool)
    for start in range(0, len(a), PAIR_BLOCK):
        rows = slice(start, start + PAIR_BLOCK)
        close[rows] = _too_close_block(field, a[rows], b[rows], min_dist)
    return close


def _too_close_block(field: MetricField, a: NDArray, b: NDArray, min_dist: float) -> NDArray:
    """:func:`too_close` on one block of pairs.

    A pair is far without more work when :func:`chord_lower_bound` is at least
    1.1 min_dist (:func:`parabola_verdicts`). The bound is tight
    where the pair lies along a principal direction, as the pairs of
    Algorithm 1 do: against |d| times the largest size 1/sqrt(λ_min(g)) it
    spares 26 to 75 % of the parabola searches on eight example and test
    metrics, and on the 870,000 pairs they searched no pruned pair's shortest
    parabola was shorter than its bound.

    The straight segment's length bounds the shortest parabola's from above,
    so a pair whose straight length is below min_dist is close without more
    work; the parabola is searched for all the others, until the verdict is
    known (on the 377,494 pairs searched in sampling the 9,746-vertex toy, the
    same verdicts as searching to the end, in two thirds of the time). No cheaper filter on
    lengths is safe: across a curved anisotropic layer the length, as a
    function of the bisector offset α, has a valley a few hundredths wide
    where it drops from 3 to 0.6 (the chord crosses the layer, the parabola
    follows it).
    """
    if len(a) == 0:
        return np.zeros(0, dtype=bool)
    return parabola_verdicts(field, a, b, short=min_dist, straight_order=4) < 0


def close_to_index(
    field: MetricField,
    index: PointIndex,
    x: NDArray,
    regions: SearchRegions,
    min_dist: float,
    *,
    exclude: NDArray | None = None,
) -> NDArray:
    """Whether each point ``x[i]`` ``(k, 2)`` is closer than ``min_dist`` (shortest
    parabola, as :func:`too_close`) to a point of ``index`` in its search region
    (:func:`search_regions`), ignoring the index point ``exclude[i]`` (``(k,)``, −1 for
    none), ``(k,)``: nearest neighbours first (:func:`curvimesh.geodesic.any_closer`).
    """
    if exclude is None:
        exclude = np.full(len(x), -1, dtype=np.int64)
    hw = regions.halfwidth
    return any_closer_in_index(
        field, x, x - hw, x + hw, index, exclude, min_dist, straight_order=4, quad=regions.quad
    )


def _boundary_distance(field: MetricField, pts: NDArray, reach: NDArray | None = None) -> NDArray:
    """Metric length of the perpendicular segment from each point to the nearest side ``(n,)``.

    With ``reach`` ``(n,)``, a side farther than ``reach[i]`` (Euclidean) is not measured
    (its length counts as inf): the caller knows it is far enough.
    """
    xmin, ymin, xmax, ymax = field.box
    x, y = pts[:, 0], pts[:, 1]
    sides = [
        (np.column_stack([x, np.full(len(pts), ymin)]), y - ymin),
        (np.column_stack([np.full(len(pts), xmax), y]), xmax - x),
        (np.column_stack([x, np.full(len(pts), ymax)]), ymax - y),
        (np.column_stack([np.full(len(pts), xmin), y]), x - xmin),
    ]
    out = np.full(len(pts), np.inf)
    for feet, gap in sides:
        rows = np.arange(len(pts)) if reach is None else np.flatnonzero(gap < reach)
        if rows.size:
            a, f = pts[rows], feet[rows]
            d = parabola_length_rule(field, a, f, 0.5 * (a + f), segments=2, order=4)
            out[rows] = np.minimum(out[rows], d)
    return out


def _greedy_independent(n: int, i: NDArray, j: NDArray) -> NDArray:
    """Keep candidates in order 0..n−1, dropping any that conflicts with a kept one.

    Conflicts are pairs (i, j) with i < j. Returns a boolean mask ``(n,)``.
    """
    keep = np.ones(n, dtype=bool)
    if len(i) == 0:
        return keep
    order = np.argsort(i, kind="stable")
    i, j = i[order], j[order]
    start = np.searchsorted(i, np.arange(n + 1))
    for k in np.unique(i):  # rounds over conflicting candidates only
        if keep[k]:
            keep[j[start[k] : start[k + 1]]] = False
    return keep


def shortened_ends(
    field: MetricField, starts: NDArray, dirs: NDArray, shot, ok: NDArray, spacing: float
) -> NDArray:
    """The paper's fix of section 5.1: end points whose parabola from the start is ``spacing``.

    A geodesic of length ℓ = spacing ends where the shortest parabola from
    its start is p ≥ ℓ long (the geodesic is the shortest curve). The point
    at arc length ℓ² / p is taken instead (one secant step towards a
    parabola of length ℓ), by cubic Hermite interpolation of the shot's
    positions and unit-speed velocities at t = 0 and t = ℓ — no second shot.
    """
    x1, v1 = shot.end[ok], shot.velocity[ok]
    v0 = unit_velocity(field, starts, dirs) * spacing  # d/ds with s in [0, 1]
    v1 = v1 * spacing
    # the search starts from the α of the geodesic's own middle: the Hermite
    # cubic's at s = 1/2 is (x₀ + x₁)/2 + (v₀ − v₁)/8
    guess = offset_alpha(starts, x1, 0.125 * (v0 - v1))
    guess[~np.isfinite(guess)] = 0.0
    par = shortest_parabola(
        field,
        starts,
        x1,
        scan=5,
        alpha_tol=2e-3,
        exact_length=False,
        remember=False,
        start=guess,
    )
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.clip(spacing / par.length, 0.0, 1.0)  # fraction of the geodesic kept
    s[~np.isfinite(s)] = 1.0
    h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
    h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
    return h00[:, None] * starts + h10[:, None] * v0 + h01[:, None] * x1 + h11[:, None] * v1


def accept_candidates(
    field: MetricField, index: PointIndex, cand: NDArray, opt: SamplingOptions
) -> NDArray:
    """The tentative points ``(k, 2)`` that may join the points of ``index``, in order.

    A candidate is kept if it lies strictly inside the box, at least
    ``boundary_dist`` from every side, at least ``min_dist`` (shortest
    parabola) from every point of the index, and from every earlier kept
    candidate. The kept ones are returned; the index is not changed.
    """
    cand = np.asarray(cand, dtype=float).reshape(-1, 2)
    return cand[accepted_rows(field, index, cand, opt)]


def accepted_rows(
    field: MetricField, index: PointIndex, cand: NDArray, opt: SamplingOptions
) -> NDArray:
    """The rows ``(k,)`` of the candidates ``cand`` ``(m, 2)`` that
    :func:`accept_candidates` keeps, ascending."""
    rows, regions = admissible_rows(field, index, cand, opt)
    return rows[conflict_free(field, cand[rows], regions, opt)]


def admissible_rows(
    field: MetricField, index: PointIndex, cand: NDArray, opt: SamplingOptions
) -> tuple[NDArray, SearchRegions]:
    """The rows ``(k,)`` of the candidates ``cand`` ``(m, 2)`` inside the box, at least
    ``boundary_dist`` from its sides and ``min_dist`` from the points of ``index``,
    ascending, and their search regions (:func:`search_regions`). A candidate refused here
    stays refused as points are added to the index."""
    rows = np.flatnonzero(field.inside(cand))
    if len(rows) == 0:
        return rows, SearchRegions(np.zeros((0, 2)), np.zeros((0, 3)))
    cand = cand[rows]
    regions = search_regions(field, cand, opt.search * opt.min_dist)
    # the region allows the sizes to grow by g = half-width / (min_dist × sampled size):
    # a side farther than boundary_dist × g × size = half-width × boundary_dist /
    # min_dist is at least boundary_dist away (as a point outside it is min_dist away)
    reach = regions.halfwidth.max(axis=1) * (opt.boundary_dist / opt.min_dist)
    near = _boundary_distance(field, cand, reach) >= opt.boundary_dist
    rows, cand, regions = rows[near], cand[near], regions[near]
    if len(cand) == 0:
        return rows, regions
    bad = close_to_index(field, index, cand, regions, opt.min_dist)
    return rows[~bad], regions[~bad]


def conflict_free(
    field: MetricField, cand: NDArray, regions: SearchRegions, opt: SamplingOptions
) -> NDArray:
    """Rows ``(k,)`` of the candidates ``cand`` ``(m, 2)`` (search regions ``regions``)
    kept greedily in order, none closer than ``min_dist`` to an earlier kept one (the
    pairs in each other's boxes are tested)."""
    i, j = pairs_within_boxes(cand, regions.halfwidth)
    close = too_close(field, cand[i], cand[j], opt.min_dist)
    return _greedy_independent(len(cand), i[close], j[close])


def sample_points(
    field: MetricField,
    boundary: BoundaryMesh,
    options: SamplingOptions | None = None,
    *,
    seed: int = 0,
    rows: list[tuple[NDArray, list[list[NDArray]]]] | None = None,
) -> NDArray:
    """Algorithm 1: the boundary vertices followed by the sampled interior points ``(n, 2)``.

    With ``seed`` 0 every front is processed in its natural order; another
    seed shuffles each front (``np.random.default_rng(seed)``), which changes
    how conflicts between candidates are resolved, but those grown from a core,
    which keep their order (:func:`_grow`).

    With ``options.cores`` (the default), the fronts first grow from points laid
    along the cores of the field's thin curved layers
    (:func:`curvimesh.cores.layer_core_points`, :data:`CORE_SPACING`), the first
    of them shooting across the layers (:func:`_grow`), until none is kept; then
    from the boundary vertices. Where the field has no such layer, nothing changes.
    Given ``rows`` (:func:`curvimesh.rows.layer_rows`: each core's points and its rows
    on each side), each core's points are followed by its rows, row k of both sides
    before row k + 1, each kept where :func:`accepted_rows` keeps it; the fronts then
    grow from the last row kept on each side (the core where a side has none).
    """
    opt = options or SamplingOptions()
    rng = np.random.default_rng(seed) if seed else None
    index = PointIndex()
    index.add(boundary.vertices)
    if len(boundary.seeds):
        index.add(boundary.seeds)  # fixed with the boundary; the fronts keep away from them
    if opt.cores and rows is not None:
        fronts = []
        for core, sides in rows:
            core = core[accepted_rows(field, index, core, opt)]
            index.add(core)
            outer = [core, core]
            for k in range(max(len(side_rows) for side_rows in sides)):
                for side, side_rows in enumerate(sides):
                    if k < len(side_rows) and len(side_rows[k]):
                        row = side_rows[k][accepted_rows(field, index, side_rows[k], opt)]
                        if len(row):
                            index.add(row)
                            outer[side] = row
            fronts.extend(outer if outer[0] is not outer[1] else outer[:1])
        if fronts:
            _grow(field, index, np.concatenate(fronts), None, (), opt, None)
    elif opt.cores:
        core = layer_core_points(field, CORE_SPACING * opt.step)
        if len(core):
            core = core[accepted_rows(field, index, core, opt)]
            index.add(core)
            # in the core's order, not shuffled: where the rows shrink (inside a ring)
            # the columns that must end then end evenly (see _grow)
            _grow(field, index, core, None, (), opt, None)
    _grow(field, index, boundary.vertices, _SIDE_TANGENTS[boundary.sides], BOUNDARY_TURNS, opt, rng)
    return index.points.copy()


#: Spacing of the points laid along a thin curved layer's core
#: (:func:`curvimesh.cores.layer_core_points`), times the step: the columns grown from
#: them along the principal directions, a step apart across the layer, make squares
#: whose diagonals, sqrt(0.95² + 1) = 1.38, are within the unit range (with 1, 1.41:
#: 7 % of the edges of a 1,000:1 ring over 1.4 at seed 1).
CORE_SPACING = 0.95


def _grow(
    field: MetricField,
    index: PointIndex,
    front: NDArray,
    ref: NDArray | None,
    turns: tuple[int, ...],
    opt: SamplingOptions,
    rng: np.random.Generator | None,
) -> None:
    """Algorithm 1's fronts from ``front`` (points of ``index``) until no candidate is
    kept, each front's kept points added to ``index``. The first front shoots at 60° ×
    ``turns`` from ``ref`` where the hexagonal lattice fits; the later ones from the
    velocities that reached their points. Each front is shuffled by ``rng`` (None:
    kept in order).

    With ``ref`` None (the row laid along a layer's core, :func:`sample_points`), the
    first front shoots along ±v₂ alone, across the layer: the row's own points are its
    neighbours along it, and a geodesic shot along a curved core leaves it (as a
    tangent leaves a circle) to land between two of them, off the core. Where that
    point is kept, the columns on its side start staggered by half a column, under
    the chords of the rows beyond, and the triangulation joins the two sides by edges
    across the core (on a 1,000:1 layer about a circle of radius 0.15, 13 points
    27.7° apart: the shot lands 0.65 short sizes inside, 12° on, and edges up to 6.9
    were left). Such fronts are grown in order (``rng`` None): inside a circular layer
    the rows shrink with the radius, and where two columns come closer than
    ``min_dist`` (10 short sizes inside on that layer) the greedy conflict resolution
    in the core's order ends every other column, while a shuffled order leaves gaps
    of three columns, as many as chance makes, in which a shot along the row lands
    under the chords of the rows beyond (edges of 10 – 16)."""
    arrival = np.full(front.shape, np.nan)  # the velocity each point was reached with
    hexagons = opt.hexagons and ref is not None
    while len(front) and index.size < opt.max_points:
        dirs, shots = front_directions(field, front, arrival, ref, turns, hexagons, opt.max_sag)
        if ref is None:  # slots 0, 1 hold ±v₁ (eigh sorts λ ascending): the long direction
            shots[:, :2] = False
        dirs = dirs.reshape(-1, 2)[shots.ravel()]
        starts = np.repeat(front, 4, axis=0)[shots.ravel()]
        shot = shoot(field, starts, dirs, opt.step, tol=opt.shoot_tol)
        ok = shot.ok
        ends = shot.end[ok]
        if opt.length_fix and ok.any():
            ends = shortened_ends(field, starts[ok], dirs[ok], shot, ok, opt.step)
        kept = accepted_rows(field, index, ends, opt)
        if len(kept) == 0:
            break
        front, arrival = ends[kept], shot.velocity[ok][kept]
        if rng is not None:
            order = rng.permutation(len(front))
            front, arrival = front[order], arrival[order]
        index.add(front)
        ref, turns, hexagons = arrival, FRONT_TURNS, opt.hexagons


def front_directions(
    field: MetricField,
    front: NDArray,
    arrival: NDArray,
    ref: NDArray | None,
    turns: tuple[int, ...],
    hexagons: bool,
    max_sag: float = math.inf,
) -> tuple[NDArray, NDArray]:
    """The directions ``(n, 4, 2)`` the points ``front`` ``(n, 2)`` shoot along and which
    of them are shot ``(n, 4)``: ±v₁, ±v₂ but the way back (:func:`backward`; ``arrival``
    the velocities that reached the points, NaN for none), or with ``hexagons``, where
    a lattice fits (:func:`lattice_fits`, sag below ``max_sag``) at the point and one
    unit ahead, the first
    ``len(turns)`` slots at 60° × ``turns`` from ``ref`` (:func:`turned_directions`)."""
    if hexagons:
        g, dg = field.evaluate(front, derivatives=True)
    else:
        g = field.tensor(front)
    dirs = principal_directions(g)
    shots = ~backward(g, dirs, arrival)
    if hexagons:
        hexa = lattice_fits(g, dg, max_sag)
        if hexa.any():
            rows = np.flatnonzero(hexa)
            hd = turned_directions(g[rows], ref[rows], turns)
            slow = turns_slowly_ahead(field, front[rows], hd, max_sag)
            hexa[rows[~slow]] = False
            dirs[hexa, : len(turns)] = hd[slow]
            shots[hexa] = np.arange(4) < len(turns)
    return dirs, shots


def turns_slowly_ahead(
    field: MetricField, starts: NDArray, dirs: NDArray, max_sag: float = math.inf
) -> NDArray:
    """Whether a lattice fits (:func:`lattice_fits`, sag below ``max_sag``) at all the
    points ``starts + dirs`` ``(n, k, 2)`` one unit ahead of ``starts`` ``(n, 2)`` along
    all k directions ``dirs`` (unit in the metric at the start, so a unit step where the
    metric is constant; outside the box or where the metric is undefined the turn and
    the sag are taken as zero), ``(n,)``."""
    ahead = (starts[:, None, :] + dirs).reshape(-1, 2)
    g, dg = field.evaluate(ahead, derivatives=True, check=False)
    return lattice_fits(g, dg, max_sag).reshape(dirs.shape[:2]).all(axis=1)


def lattice_fits(g: NDArray, dg: NDArray, max_sag: float = math.inf) -> NDArray:
    """Where a hexagonal lattice may be laid ``(n,)``: the frame turns by less than
    :data:`HEX_MAX_TURN` per unit length (:func:`curvimesh.metric.frame_turn`) and a
    unit chord along the long size strays less than ``max_sag`` short sizes from the
    layer (:func:`curvimesh.metric.layer_sag`; no bound by default). ``g``
    ``(n, 2, 2)``, ``dg`` ``(n, 2, 2, 2)``."""
    fits = frame_turn(g, dg) < HEX_MAX_TURN
    if math.isfinite(max_sag):
        fits &= layer_sag(g, dg) < max_sag
    return fits
