"""The metric files of ``metrics/`` are what their comments say, and the mesh of
a constant anisotropic metric reaches the best corner quality its box allows.

Truth is computed here from the definitions (sizes and directions), not from
the loader: g = R diag(1/h₁², 1/h₂²) Rᵀ with R the rotation by the stated angle,
so that the size along a unit vector u is 1 / sqrt(uᵀ g u).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from targets import assert_unit_mesh_targets

from curvimesh import adapt as pipeline
from curvimesh.mesh import is_conforming
from curvimesh.metric import load_metric
from curvimesh.report import mesh_report

METRICS = Path(__file__).resolve().parents[1] / "metrics"
RNG = np.random.default_rng(7)


def size_along(g: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The metric size 1 / sqrt(uᵀ g u) along unit vectors ``u`` ``(n, 2)``."""
    return 1.0 / np.sqrt(np.einsum("ni,nij,nj->n", u, g, u))


def unit(angle: np.ndarray) -> np.ndarray:
    return np.column_stack([np.cos(angle), np.sin(angle)])


def inside(box, n: int) -> np.ndarray:
    (x0, y0, x1, y1) = box
    return np.column_stack([RNG.uniform(x0, x1, n), RNG.uniform(y0, y1, n)])


@pytest.mark.parametrize("path", sorted(METRICS.glob("*.yaml")), ids=lambda p: p.stem)
def test_every_example_metric_loads_and_is_spd_on_the_box(path):
    fld = load_metric(path)
    assert fld.name == path.stem
    pts = inside(fld.box, 4000)
    g = fld.tensor(pts)  # raises on a non-SPD or non-finite value
    assert np.all(np.linalg.eigvalsh(g) > 0)


def test_constant_aniso_is_size_001_along_30_degrees_and_02_across():
    fld = load_metric(METRICS / "constant_aniso.yaml")
    pts = inside(fld.box, 200)
    g = fld.tensor(pts)
    a = np.full(len(pts), math.pi / 6)
    assert np.allclose(size_along(g, unit(a)), 0.01, rtol=1e-12)
    assert np.allclose(size_along(g, unit(a + math.pi / 2)), 0.2, rtol=1e-12)
    assert np.allclose(g, g[0], rtol=1e-12)


@pytest.mark.parametrize(
    ("name", "along", "across", "rtol"),
    [
        ("boundary_layer", 0.1, lambda y: 0.001 + 0.1 * y, 1e-12),  # linear from the wall
        (
            "wall_layer_steep",
            0.08,
            lambda y: 0.08 - (0.08 - 0.00008) * np.exp(-y / 0.15),  # exponential
            1e-10,
        ),
    ],
)
def test_wall_layer_sizes_follow_their_law_from_the_wall(name, along, across, rtol):
    fld = load_metric(METRICS / f"{name}.yaml")
    pts = inside(fld.box, 200)
    g = fld.tensor(pts)
    assert np.allclose(size_along(g, unit(np.zeros(len(pts)))), along, rtol=1e-12)
    got = size_along(g, unit(np.full(len(pts), math.pi / 2)))
    assert np.allclose(got, across(pts[:, 1]), rtol=rtol)


def test_concentric_is_radial_002_tangential_01():
    fld = load_metric(METRICS / "concentric.yaml")
    pts = inside(fld.box, 200)
    pts = pts[np.hypot(*pts.T) > 1e-3]
    g = fld.tensor(pts)
    theta = np.arctan2(pts[:, 1], pts[:, 0])
    assert np.allclose(size_along(g, unit(theta)), 0.02, rtol=1e-12)
    assert np.allclose(size_along(g, unit(theta + math.pi / 2)), 0.1, rtol=1e-12)


def test_circular_layer_radial_size_follows_the_exponential_law():
    fld = load_metric(METRICS / "circular_layer.yaml")
    r = np.concatenate([[0.5], RNG.uniform(0.05, 1.0, 100)])
    theta = RNG.uniform(-math.pi, math.pi, len(r))
    pts = r[:, None] * unit(theta)
    g = fld.tensor(pts)
    s = np.sqrt((r - 0.5) ** 2 + 1e-6)
    hr = 0.1 - (0.1 - 0.002) * np.exp(-s / 0.05)
    assert np.allclose(size_along(g, unit(theta)), hr, rtol=1e-10)
    assert np.allclose(size_along(g, unit(theta + math.pi / 2)), 0.1, rtol=1e-10)
    # on the circle itself the smoothing of |r - r0| leaves about 0.004, as the file says
    assert 0.0039 < hr[0] < 0.0040


def test_front_is_002_across_the_sine_curve_and_01_along_it():
    fld = load_metric(METRICS / "front.yaml")
    x = RNG.uniform(0, 1, 100)
    y = 0.5 + 0.25 * np.sin(2 * math.pi * x)
    g = fld.tensor(np.column_stack([x, y]))
    normal = np.arctan2(1.0, -0.5 * math.pi * np.cos(2 * math.pi * x))  # grad phi
    assert np.allclose(size_along(g, unit(normal)), 0.002, rtol=1e-10)
    assert np.allclose(size_along(g, unit(normal + math.pi / 2)), 0.1, rtol=1e-10)


def corner_quality_bound(theta: float) -> float:
    """The best quality (4) of a triangle with an angle θ in a constant metric.

    With sides a, b about the angle: q = 4√3 A / Σ l² = √3 ab sin θ / (a² + b² − ab cos θ),
    largest at a = b: √3 sin θ / (2 − cos θ). A box corner whose sides meet at a
    metric angle θ lies in triangles whose angles there sum to θ, and the bound
    grows with θ on (0, π/3], so no mesh has a better worst triangle than this.
    """
    return math.sqrt(3) * math.sin(theta) / (2 - math.cos(theta))


def test_constant_aniso_mesh_is_unit_and_its_corner_as_good_as_the_lengths_allow():
    fld = load_metric(METRICS / "constant_aniso.yaml")
    g = fld.tensor(np.array([[0.5, 0.5]]))[0]
    ex, ey = np.array([1.0, 0.0]), np.array([0.0, 1.0])
    theta = math.acos(ex @ g @ ey / math.sqrt((ex @ g @ ex) * (ey @ g @ ey)))
    assert math.degrees(theta) == pytest.approx(6.6, abs=0.05)  # corners (0, 0) and (1, 1)
    # the best corner triangle with its three edges no shorter than 0.7: sides a = 0.7
    # and b on the box sides, b solving the law of cosines for a cut of exactly 0.7
    a = 0.7
    b = a * math.cos(theta) + math.sqrt(0.49 - (a * math.sin(theta)) ** 2)
    q_unit = math.sqrt(3) * a * b * math.sin(theta) / (a * a + b * b - a * b * math.cos(theta))
    mesh = pipeline.adapt(fld).mesh
    rep = mesh_report(fld, mesh)
    assert rep["valid"] and is_conforming(mesh)
    assert rep["edge_length"]["min"] >= 0.7 and rep["edge_length"]["max"] <= 1.5
    assert rep["edge_length"]["in_range"] >= 0.98
    assert rep["quality"]["min"] <= corner_quality_bound(theta) * (1 + 1e-4)  # a theorem
    assert rep["quality"]["min"] >= 0.95 * q_unit  # the corner is as good as unit edges allow
    assert rep["quality"]["mean"] >= 0.85
    # a constant metric has straight geodesics: every edge node is at its edge's midpoint,
    # but those the bending moved off to raise a triangle below 0.8 (curvimesh.bend)
    straight = pipeline.adapt(fld, pipeline.AdaptOptions(bend=False)).mesh
    pts = np.asarray(straight.points)
    mid = (pts[straight.edges[:, 0]] + pts[straight.edges[:, 1]]) / 2
    assert np.allclose(pts[straight.edge_mid], mid, atol=1e-9)
    bent = np.any(np.asarray(mesh.points) != pts, axis=1)
    assert np.array_equal(mesh.triangles, straight.triangles)
    assert np.isin(np.flatnonzero(bent), straight.edge_mid).all() and bent.sum() <= 0.02 * len(mid)


def sharpest_corner(fld) -> float:
    """The smallest angle (radians) of the box corners in the metric at each corner."""
    x0, y0, x1, y1 = fld.box
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    g = fld.tensor(corners)
    ex, ey = np.array([1.0, 0.0]), np.array([0.0, 1.0])
    cos = np.abs(np.einsum("i,nij,j->n", ex, g, ey)) / np.sqrt(
        np.einsum("i,nij,j->n", ex, g, ex) * np.einsum("i,nij,j->n", ey, g, ey)
    )
    return float(np.arccos(cos.max()))


@pytest.mark.parametrize("path", sorted(METRICS.glob("*.yaml")), ids=lambda p: p.stem)
def test_every_example_mesh_meets_the_unit_mesh_targets(path):
    # the targets of a unit mesh: valid, no edge shorter than 0.7 (lengths are
    # accurate to 1e-5), at least 98 % in [0.7, 1.4], none over 1.5, quality at
    # least 0.3 (or what the sharpest box corner allows: see the constant_aniso
    # test) and 0.8 on average, at most 1.15 times the ideal triangle count
    fld = load_metric(path)
    mesh = pipeline.adapt(fld).mesh
    floor = corner_quality_bound(sharpest_corner(fld)) >= 0.3
    assert_unit_mesh_targets(fld, mesh, quality_floor=floor)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_quartic2_meets_the_unit_mesh_targets_at_other_seeds(seed):
    """The hardest example at other seeds. At seed 2 the sampled cloud leaves a gap
    on the curve's 30:1 layer and, before the repeated passes, an edge of 2.76 stayed
    (its swap to 1.18 became valid only after a vertex shift)."""
    fld = load_metric(METRICS / "quartic2.yaml")
    mesh = pipeline.adapt(fld, pipeline.AdaptOptions(seed=seed)).mesh
    assert_unit_mesh_targets(fld, mesh)


def test_the_repeated_passes_leave_no_worse_a_mesh_than_one_pass():
    """Same cloud and curved mesh, the swap stage with and without the repeats: the
    repeats never raise the longest edge, lower the worst quality or add a short edge."""
    fld = load_metric(METRICS / "quartic2.yaml")
    opt = pipeline.AdaptOptions(seed=3)  # one pass leaves edges up to 2.75 long
    p2 = pipeline.curve(fld, pipeline.triangulate(pipeline.sample(fld, opt), fld, opt), opt)
    once = pipeline.swap(fld, p2, pipeline.AdaptOptions(seed=3, repeat=False))
    again = pipeline.swap(fld, p2, opt)
    assert once.passes == 0 and again.passes >= 1
    before, after = pipeline.defects(fld, once.mesh), pipeline.defects(fld, again.mesh)
    assert not after.worse_than(before)
    assert after.count < before.count
    rep = mesh_report(fld, again.mesh)
    assert rep["edge_length"]["max"] == pytest.approx(after.max_length, rel=1e-4)
    assert rep["quality"]["min"] == pytest.approx(after.min_quality, rel=1e-4)
