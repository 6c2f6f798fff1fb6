"""Cores of thin curved layers: found where they are analytically, nowhere else, and
sampled first."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from targets import assert_unit_mesh_targets

from curvimesh import cores, sampling
from curvimesh.adapt import AdaptOptions, adapt
from curvimesh.boundary import discretize_box
from curvimesh.geodesic import shortest_parabola
from curvimesh.metric import load_metric, load_metric_text

METRICS = Path(__file__).resolve().parent.parent / "metrics"


def ring(
    radius: float, h0: float, along: float = 0.1, centre=(0.5, 0.5), growth: float = 0.25
) -> str:
    """A ring of radius ``radius`` about ``centre``: radial size h0 + growth |r − radius|
    (to ``along``), ``along`` round it."""
    cx, cy = centre
    return f"""
name: ring
domain: {{box: [[0, 0], [1, 1]]}}
definitions:
  r: sqrt((x - {cx})**2 + (y - {cy})**2)
metric:
  eigen:
    sizes: ['min({h0} + {growth}*abs(r - {radius}), {along})', {along}]
    angle: atan2(y - {cy}, x - {cx})
"""


SPACING = 0.95


@pytest.mark.parametrize(("radius", "h0"), [(0.3, 4e-5), (0.15, 2e-4), (0.22, 1e-4), (0.35, 5e-4)])
def test_a_ring_s_core_is_its_circle_with_points_evenly_round_it(radius, h0):
    fld = load_metric_text(ring(radius, h0, centre=(0.48, 0.53)))
    pts = cores.layer_core_points(fld, SPACING)
    rel = pts - np.array([0.48, 0.53])
    # on the circle where the radial size is least, to the line search's precision
    np.testing.assert_allclose(np.hypot(rel[:, 0], rel[:, 1]), radius, atol=1e-8)
    # once round, evenly: by symmetry every step is the same angle and parabola (to
    # the arc lengths along the traced polyline, chords measured at their middles)
    angle = np.sort(np.arctan2(rel[:, 1], rel[:, 0]))
    steps = np.diff(np.concatenate([angle, angle[:1] + 2 * math.pi]))
    np.testing.assert_allclose(steps, 2 * math.pi / len(pts), rtol=1e-3)
    length = shortest_parabola(fld, pts, np.roll(pts, -1, axis=0)).length
    assert np.ptp(length) < 2e-3 * length.max()
    # as many as steps of a parabola of 0.95 between points of the exact circle go
    # round, the last fraction of a step counted when it is half a step or more
    centre = np.array([0.48, 0.53])

    def step_length(t: float) -> float:
        a = centre + radius * np.array([1.0, 0.0])
        b = centre + radius * np.array([math.cos(t), math.sin(t)])
        return float(shortest_parabola(fld, a[None], b[None]).length[0])

    lo, hi = 0.0, 1.5
    for _ in range(50):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if step_length(mid) < SPACING else (lo, mid)
    turns = 2 * math.pi / lo
    assert abs(turns % 1 - 0.5) > 0.05  # not a borderline case
    assert len(pts) == math.floor(turns) + (turns % 1 >= 0.5)


def test_an_ellipse_s_core_is_the_ellipse():
    text = """
name: ellipse
domain: {box: [[-1, -0.7], [1, 0.7]]}
definitions:
  q: sqrt((x/0.7)**2 + (y/0.45)**2)
metric:
  eigen:
    sizes: ['min(0.00005 + 0.1*abs(q - 1), 0.05)', 0.05]
    angle: atan2(y/0.45**2, x/0.7**2)
"""
    fld = load_metric_text(text)
    pts = cores.layer_core_points(fld, SPACING)
    q = np.hypot(pts[:, 0] / 0.7, pts[:, 1] / 0.45)
    np.testing.assert_allclose(q, 1.0, atol=1e-7)
    # round the whole ellipse (perimeter about 3.7, long size 0.05: some 75 units)
    assert 60 <= len(pts) <= 90
    turn = np.unwrap(np.sort(np.arctan2(pts[:, 1] / 0.45, pts[:, 0] / 0.7)))
    assert np.max(np.diff(np.concatenate([turn, turn[:1] + 2 * math.pi]))) < 0.2


def unit_box(metric: str) -> str:
    return f"name: m\ndomain: {{box: [[0, 0], [1, 1]]}}\nmetric: {metric}\n"


@pytest.mark.parametrize(
    "text",
    [
        # a wall's boundary layer, 1,000:1 and straight: no sag
        unit_box("{eigen: {sizes: ['0.0001 + 0.3*y', 0.1], angle: pi/2}}"),
        # constant and 1,000:1: the short size has no least across
        unit_box("{eigen: {sizes: [0.0001, 0.1], angle: 0.3}}"),
        # a ring of 40:1 at its thinnest
        ring(0.3, 0.0025),
    ],
)
def test_no_core_in_straight_constant_or_mildly_anisotropic_layers(text):
    assert cores.layer_core_points(load_metric_text(text), SPACING).shape == (0, 2)


@pytest.mark.parametrize("name", ["toy", "three_toys", "circular_layer", "boundary_layer"])
def test_the_examples_without_a_thin_curved_layer_have_no_core(name):
    assert len(cores.layer_core_points(load_metric(METRICS / f"{name}.yaml"), SPACING)) == 0


def _sampled_after_the_sides(fld):
    """The sampled points that follow the box's vertices, the core's points and the
    box's discretisation."""
    opt = sampling.SamplingOptions()
    boundary = discretize_box(fld, target=opt.step, min_dist=opt.min_dist)
    pts = sampling.sample_points(fld, boundary, opt)
    core = cores.layer_core_points(fld, sampling.CORE_SPACING * opt.step)
    return pts[len(boundary.vertices) :], core, boundary


def test_the_fronts_start_from_the_core_before_the_sides():
    fld = load_metric(METRICS / "thin_ring.yaml")
    after, core, boundary = _sampled_after_the_sides(fld)
    np.testing.assert_array_equal(after[: len(core)], core)
    without = sampling.sample_points(fld, boundary, sampling.SamplingOptions(cores=False))
    assert not np.isin(core[:, 0], without[:, 0]).any()


def test_a_thin_ring_meets_the_targets_in_one_run():
    fld = load_metric(METRICS / "thin_ring.yaml")
    res = adapt(fld, AdaptOptions(retry=False))
    assert_unit_mesh_targets(fld, res.mesh)


def test_the_columns_across_a_small_ring_start_on_the_core_at_every_seed():
    # 1,000:1 about a circle of radius 0.15 (13 core points 27.7° apart): a geodesic
    # shot across a rotationally symmetric layer stays radial, so the columns grown
    # from the core keep its points' angles, inside the circle as outside. A shot
    # along the core leaves it, as a tangent leaves a circle, and landed 12° on, a
    # quarter of a step inside: the inner columns started staggered (0.21 rad off
    # the core's angles). The fronts grown from a core keep their order, so the
    # layer's points do not depend on the seed.
    centre = np.array([0.45, 0.55])
    fld = load_metric_text(ring(0.15, 1e-4, centre=tuple(centre)))
    opt = sampling.SamplingOptions()
    boundary = discretize_box(fld, target=opt.step, min_dist=opt.min_dist)
    core = cores.layer_core_points(fld, sampling.CORE_SPACING * opt.step)
    assert len(core) == 13
    angles = np.arctan2(core[:, 1] - centre[1], core[:, 0] - centre[0])
    layers = []
    for seed in (0, 1, 2):
        rel = sampling.sample_points(fld, boundary, opt, seed=seed) - centre
        r = np.hypot(rel[:, 0], rel[:, 1])
        band = np.abs(r - 0.15) < 5e-4  # the rows within about four short sizes
        assert np.count_nonzero(r[band] < 0.15 - 1e-8) >= 3 * len(core)  # rows inside too
        a = np.arctan2(rel[band, 1], rel[band, 0])
        off = np.abs((a[:, None] - angles[None, :] + math.pi) % (2 * math.pi) - math.pi)
        assert off.min(axis=1).max() < 1e-9
        layers.append(np.sort(rel[band], axis=0))
    for other in layers[1:]:
        np.testing.assert_array_equal(other, layers[0])


# 1,000:1 about the circle of radius 1 centred at (0.5, -0.6), long size 0.1: the
# core crosses the box's left and right sides at y = -0.6 + sqrt(0.75)
ARC = """
name: arc
domain: {box: [[0, 0], [1, 1]]}
definitions:
  r: sqrt((x - 0.5)**2 + (y + 0.6)**2)
metric:
  eigen:
    sizes: ['min(0.0001 + 0.25*abs(r - 1), 0.1)', 0.1]
    angle: atan2(y + 0.6, x - 0.5)
"""
CROSSING_Y = -0.6 + math.sqrt(0.75)


def test_an_open_core_is_extended_to_where_it_crosses_the_sides():
    fld = load_metric_text(ARC)
    ((line, closed),) = cores.layer_cores(fld)
    assert not closed
    # the trace stops short of the sides (a step would leave the box)
    assert min(line[0, 0], 1 - line[0, 0], line[-1, 0], 1 - line[-1, 0]) > 1e-3
    ext, at_box = cores.to_box(fld, line)
    assert at_box == (True, True)
    np.testing.assert_array_equal(ext[1:-1], line)
    ends = sorted([tuple(ext[0]), tuple(ext[-1])])
    np.testing.assert_allclose(ends, [(0.0, CROSSING_Y), (1.0, CROSSING_Y)], atol=1e-8)
    # a ring inside the box has no end on it
    ring_line = cores.layer_cores(load_metric_text(ring(0.3, 1e-4)))[0][0]
    assert cores.to_box(load_metric_text(ring(0.3, 1e-4)), ring_line[:40])[1] == (False, False)


def test_the_points_of_a_core_across_the_box_are_evenly_spaced_from_side_to_side():
    fld = load_metric_text(ARC)
    pts = cores.layer_core_points(fld, SPACING)
    centre = np.array([0.5, -0.6])
    np.testing.assert_allclose(np.linalg.norm(pts - centre, axis=1), 1.0, atol=1e-8)
    # by symmetry every parabola step along the circle spans the same angle, so the
    # steps scaled to fit from side to side are equal, the gaps to the sides too
    side = math.atan2(CROSSING_Y + 0.6, 0.5)
    angle = np.sort(np.arctan2(pts[:, 1] + 0.6, pts[:, 0] - 0.5))
    gaps = np.diff(np.concatenate([[side], angle, [math.pi - side]]))
    np.testing.assert_allclose(gaps, gaps.mean(), rtol=1e-3)
    # each of them a parabola of about 0.95 (scaled by under half a step in all)
    length = shortest_parabola(fld, pts[:-1], pts[1:]).length
    assert np.all(np.abs(length - SPACING) < 0.5 * SPACING / len(pts))
    # and the fronts keep the first and last: a step from the sides' vertices
    after, core, _ = _sampled_after_the_sides(fld)
    np.testing.assert_array_equal(after[: len(core)], core)
