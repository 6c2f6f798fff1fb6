"""Metric fields: the forms of SPEC section 2, intersection, derivatives, metric area."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from curvimesh.errors import MetricError
from curvimesh.metric import (
    MAX_FRAME_TURN,
    UNIT_TRIANGLE_AREA,
    density_integral,
    frame_turn,
    layer_sag,
    load_metric,
    load_metric_text,
    sharpest_turn,
)
from curvimesh.tensors import intersect

METRICS = Path(__file__).resolve().parent.parent / "metrics"


def rand_spd(rng, n):
    a = rng.normal(size=(n, 2, 2))
    return a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(2)


def test_isotropic_form():
    fld = load_metric_text("metric: {isotropic: 0.5 + x}\n")
    g = fld.tensor(np.array([[0.5, 0.2]]))
    np.testing.assert_allclose(g[0], np.eye(2) / 1.0**2)
    assert fld.box == (0.0, 0.0, 1.0, 1.0)


@pytest.mark.parametrize("angle", [0.0, 0.3, 1.2, -2.0])
def test_eigen_form_puts_the_first_size_along_the_angle(angle):
    fld = load_metric_text(f"metric:\n  eigen: {{sizes: [0.1, 0.5], angle: {angle}}}\n")
    g = fld.tensor(np.array([[0.5, 0.5]]))[0]
    u = np.array([math.cos(angle), math.sin(angle)])
    w = np.array([-math.sin(angle), math.cos(angle)])
    assert u @ g @ u == pytest.approx(1 / 0.1**2)
    assert w @ g @ w == pytest.approx(1 / 0.5**2)
    assert u @ g @ w == pytest.approx(0, abs=1e-9)


def test_tensor_form_and_definitions():
    text = """
domain: {box: [[-1, -1], [1, 1]]}
parameters: {a: 2}
definitions:
  s: a + x**2
metric:
  tensor: [s, 0.5, 3]
"""
    fld = load_metric_text(text)
    g = fld.tensor(np.array([[0.5, 0.0]]))[0]
    np.testing.assert_allclose(g, [[2.25, 0.5], [0.5, 3.0]])


def test_toy_metric_is_radial_small_size_across_the_ring():
    fld = load_metric(METRICS / "toy.yaml")
    p = np.array([[0.5 * math.cos(0.7), 0.5 * math.sin(0.7)]])
    g = fld.tensor(p)[0]
    radial = np.array([math.cos(0.7), math.sin(0.7)])
    tangential = np.array([-math.sin(0.7), math.cos(0.7)])
    assert 1 / math.sqrt(radial @ g @ radial) == pytest.approx(0.01)
    assert 1 / math.sqrt(tangential @ g @ tangential) == pytest.approx(0.3)


def test_toy_metric_is_defined_at_its_centre():
    fld = load_metric(METRICS / "toy.yaml")
    g, dg = fld.evaluate(np.array([[0.0, 0.0]]), derivatives=True)
    assert np.isfinite(g).all() and np.isfinite(dg).all()


def test_toy_ideal_triangle_count_against_an_independent_quadrature():
    # sqrt(det g) = 1 / (lmin lmax) in closed form; midpoint rule on a fine grid.
    n = 4000
    h = 4.0 / n
    c = -2 + h * (np.arange(n) + 0.5)
    total = 0.0
    for row in np.array_split(c, 8):
        x, y = np.meshgrid(c, row)
        r = np.hypot(x, y)
        lmin = 0.01 + 0.3 * (1 - np.exp(-(((r - 0.5) / (1 / math.sqrt(10))) ** 2)))
        total += np.sum(1.0 / (lmin * 0.3)) * h * h
    fld = load_metric(METRICS / "toy.yaml")
    ours = density_integral(fld)
    assert ours == pytest.approx(total, rel=1e-5)
    assert ours / UNIT_TRIANGLE_AREA == pytest.approx(761.8, abs=0.1)


def test_intersection_of_a_metric_with_itself_is_itself():
    rng = np.random.default_rng(1)
    m = rand_spd(rng, 50)
    np.testing.assert_allclose(intersect(m, m).real, m, rtol=1e-10, atol=1e-12)


def test_intersection_contains_both_and_is_the_smallest_such():
    rng = np.random.default_rng(2)
    m1, m2 = rand_spd(rng, 200), rand_spd(rng, 200)
    m = intersect(m1, m2).real
    v = rng.normal(size=(200, 2))
    q = np.einsum("pi,pij,pj->p", v, m, v)
    q1 = np.einsum("pi,pij,pj->p", v, m1, v)
    q2 = np.einsum("pi,pij,pj->p", v, m2, v)
    assert (q >= np.maximum(q1, q2) * (1 - 1e-9)).all()
    # simultaneous reduction: along each common eigenvector it equals the larger one
    _w, vec = np.linalg.eig(np.linalg.solve(m1, m2))
    for k in range(2):
        e = vec[:, :, k].real
        qm = np.einsum("pi,pij,pj->p", e, m, e)
        qa = np.einsum("pi,pij,pj->p", e, m1, e)
        qb = np.einsum("pi,pij,pj->p", e, m2, e)
        np.testing.assert_allclose(qm, np.maximum(qa, qb), rtol=1e-8)


def test_nested_metrics_intersect_to_the_larger():
    m1 = np.array([[[4.0, 1.0], [1.0, 3.0]]])
    m2 = 0.5 * m1
    np.testing.assert_allclose(intersect(m1, m2).real, m1)
    np.testing.assert_allclose(intersect(m2, m1).real, m1)


def test_intersection_items_override_parameters_and_reuse_outer_definitions():
    text = """
parameters: {h: 1.0}
definitions:
  size: h * (1 + x)
metric:
  intersection:
    - isotropic: size
    - parameters: {h: 0.5}
      isotropic: size
"""
    fld = load_metric_text(text)
    g = fld.tensor(np.array([[1.0, 0.0]]))[0]
    np.testing.assert_allclose(g, np.eye(2) / (0.5 * 2.0) ** 2)
    assert len(fld.components) == 2


@pytest.mark.parametrize("name", ["toy", "three_toys", "quartic", "quartic2"])
def test_derivatives_match_central_differences(name):
    fld = load_metric(METRICS / f"{name}.yaml")
    rng = np.random.default_rng(3)
    p = rng.uniform(-1.9, 1.9, (400, 2))
    _, dg = fld.evaluate(p, derivatives=True)
    h = 1e-6
    for k in range(2):
        e = np.zeros(2)
        e[k] = h
        fd = (fld.tensor(p + e) - fld.tensor(p - e)) / (2 * h)
        scale = np.abs(dg).max(axis=(1, 2, 3)) + np.abs(fld.tensor(p)).max(axis=(1, 2))
        err = np.abs(fd - dg[..., k]).max(axis=(1, 2)) / scale
        # the intersection has kinks: allow a few points within h of one
        assert np.mean(err < 1e-5) > 0.99


@settings(max_examples=30, deadline=None)
@given(
    st.floats(0.05, 2.0),
    st.floats(0.05, 2.0),
    st.floats(-3.2, 3.2),
    st.floats(0.05, 2.0),
    st.floats(0.05, 2.0),
    st.floats(-3.2, 3.2),
)
def test_intersection_derivative_is_exact_where_smooth(h1, h2, a1, k1, k2, a2):
    text = f"""
metric:
  intersection:
    - eigen: {{sizes: [{h1} * (1 + x), {h2}], angle: {a1} + y}}
    - eigen: {{sizes: [{k1}, {k2} * (1 + y*x)], angle: {a2}}}
"""
    fld = load_metric_text(text)
    p = np.array([[0.3, 0.6]])
    _, dg = fld.evaluate(p, derivatives=True)
    h = 1e-5
    g0 = fld.tensor(p)
    for k in range(2):
        e = np.zeros(2)
        e[k] = h
        gp, gm = fld.tensor(p + e), fld.tensor(p - e)
        fd = (gp - gm) / (2 * h)
        # one-sided differences agree when the point is not on a kink
        fwd = (gp - g0) / h
        bwd = (g0 - gm) / h
        scale = np.abs(fd).max() + 1.0
        # the intersection is computed to about 1e-13 relative (an eigenproblem), an
        # error the difference quotient divides by h: allowed for beside truncation
        rounding = 1e-12 * np.abs(g0).max() / h
        if np.abs(fwd - bwd).max() < 1e-3 * scale:
            assert np.abs(fd - dg[..., k]).max() < 1e-5 * scale + rounding


def test_non_spd_point_is_named():
    with pytest.raises(MetricError, match=r"\(0\.5, 0\.5\)|not finite and positive"):
        load_metric_text("metric: {tensor: [1, 2, 1]}\n", source="m.yaml")


def test_negative_size_is_an_error():
    with pytest.raises(MetricError, match="size is not finite and positive"):
        load_metric_text("metric: {isotropic: x - 0.5}\n", source="m.yaml")


def test_blocked_evaluation_and_spd_check_match_the_plain_ones(monkeypatch):
    """Evaluating in blocks gives the same bits; the SPD check is that of the (n, 2, 2) tensors."""
    import curvimesh.metric as metric

    fld = load_metric(METRICS / "three_toys.yaml")
    pts = np.random.default_rng(3).uniform(-2, 2, (1001, 2))
    g, dg = fld.evaluate(pts, derivatives=True)
    monkeypatch.setattr(metric, "EVAL_BLOCK", 64)
    g2, dg2 = fld.evaluate(pts, derivatives=True)
    assert np.array_equal(g, g2) and np.array_equal(dg, dg2)
    bad = rand_spd(np.random.default_rng(4), 400)
    bad[::7, 0, 0] = -bad[::7, 0, 0]
    bad[1::5, 0, 1] = np.nan
    bad[2::11, 1, 0] = np.inf
    bad[3::13, 1, 1] = 0.0
    with np.errstate(invalid="ignore"):
        det = bad[:, 0, 0] * bad[:, 1, 1] - bad[:, 0, 1] * bad[:, 1, 0]
        want = np.isfinite(bad).all(axis=(1, 2)) & (bad[:, 0, 0] > 0) & (det > 0)
    assert np.array_equal(metric._spd(bad), want)
    d4 = np.where(np.arange(8) % 3 == 0, np.nan, 1.0)[None].repeat(3, 0).reshape(3, 2, 2, 2)
    d4[1] = 1.0
    assert metric._finite_rows(d4).tolist() == [False, True, False]
    assert metric._finite_rows(np.zeros((0, 2, 2))).shape == (0,)


def test_smallest_eigenvalue_matches_lapack_to_relative_rounding_at_any_anisotropy():
    from curvimesh.metric import smallest_eigenvalue

    rng = np.random.default_rng(3)
    theta = rng.uniform(0, np.pi, 2000)
    lam = np.column_stack([10.0 ** rng.uniform(-8, 0, 2000), 10.0 ** rng.uniform(0, 8, 2000)])
    c, s = np.cos(theta), np.sin(theta)
    rot = np.stack([np.column_stack([c, -s]), np.column_stack([s, c])], axis=1)
    g = rot @ (lam[:, :, None] * np.eye(2)) @ rot.transpose(0, 2, 1)
    got = smallest_eigenvalue(g)
    # the exact λ_min is lam[:, 0] up to the rounding of building g (≈ 1e-16 λ_max)
    assert np.all(np.abs(got - lam[:, 0]) <= 1e-15 * lam[:, 1] + 1e-12 * lam[:, 0])
    assert np.allclose(got, np.linalg.eigvalsh(g)[:, 0], rtol=1e-9, atol=1e-15 * lam[:, 1].max())


RINGS = """
name: rings
domain:
  box: [[-1, -1], [1, 1]]
metric:
  eigen:
    sizes: [0.005, 0.1]
    angle: atan2(y, x)
"""


def test_frame_turn_of_concentric_rings_is_the_tangential_size_over_the_radius():
    """Directions radial and tangential: along the tangent (unit step 0.1 in the
    plane) they turn at 1/r per unit of plane length, radially not at all."""
    fld = load_metric_text(RINGS)
    r = np.array([0.1, 0.2, 0.5, 0.9])
    a = np.array([0.3, 2.0, -1.0, 4.0])
    g, dg = fld.evaluate(np.column_stack([r * np.cos(a), r * np.sin(a)]), derivatives=True)
    np.testing.assert_allclose(frame_turn(g, dg), 0.1 / r, rtol=1e-12)
    # anisotropy 20: below a threshold of 21 the rings are ignored
    assert not frame_turn(g, dg, min_anisotropy=21).any()


def test_frame_turn_of_spokes_is_the_fine_tangential_size_over_the_radius():
    """Sizes 0.1 radial and 0.005 tangential: the frame turns along the fine
    direction only (a step of 0.005 turns it by 0.005 / r), the other eigenvector."""
    fld = load_metric_text(RINGS.replace("[0.005, 0.1]", "[0.1, 0.005]"))
    r = np.array([0.1, 0.2, 0.5, 0.9])
    a = np.array([0.3, 2.0, -1.0, 4.0])
    g, dg = fld.evaluate(np.column_stack([r * np.cos(a), r * np.sin(a)]), derivatives=True)
    np.testing.assert_allclose(frame_turn(g, dg), 0.005 / r, rtol=1e-12)


def test_layer_sag_of_rings_is_the_sagitta_of_a_unit_chord_in_radial_sizes():
    """Rings of tangential size 0.1 and radial size 0.005: a chord of 0.1 (one unit)
    along a circle of radius r strays 0.1² / (8r) from it, 0.1² / (8r · 0.005) radial
    sizes; spokes (0.1 radial, 0.005 tangential) turn only along their fine size: no
    sag; nor has a constant field."""
    r = np.array([0.1, 0.2, 0.5, 0.9])
    a = np.array([0.3, 2.0, -1.0, 4.0])
    pts = np.column_stack([r * np.cos(a), r * np.sin(a)])
    g, dg = load_metric_text(RINGS).evaluate(pts, derivatives=True)
    np.testing.assert_allclose(layer_sag(g, dg), 0.1**2 / (8 * r * 0.005), rtol=1e-12)
    assert not layer_sag(g, dg, min_anisotropy=21).any()
    spokes = load_metric_text(RINGS.replace("[0.005, 0.1]", "[0.1, 0.005]"))
    g, dg = spokes.evaluate(pts, derivatives=True)
    np.testing.assert_allclose(layer_sag(g, dg), 0.0, atol=1e-12)
    const = load_metric_text(RINGS.replace("atan2(y, x)", "0.7"))
    assert not layer_sag(*const.evaluate(pts, derivatives=True)).any()


def test_frame_turn_is_zero_for_a_constant_metric_and_sharpest_turn_is_nearest_the_centre():
    const = load_metric_text(RINGS.replace("atan2(y, x)", "0.7"))
    g, dg = const.evaluate(const.sample_points(9), derivatives=True)
    assert not frame_turn(g, dg).any()
    turn, at, long_size = sharpest_turn(load_metric_text(RINGS), n=8)
    # the 8×8 grid of [-1, 1]² (spacing 2/7, centre not on it) comes closest
    # to the centre at (±1/7, ±1/7)
    assert math.isclose(turn, 0.1 / (math.sqrt(2) / 7), rel_tol=1e-12)
    np.testing.assert_allclose(np.abs(at), [1 / 7, 1 / 7], rtol=1e-12)
    assert math.isclose(long_size, 0.1, rel_tol=1e-12)


def test_examples_turn_slowly_enough_and_the_tight_front_does_not():
    """No example draws the warning; the tight front (metrics/hard) does, and
    with its long size cut to 0.05 no longer. The directions follow the level
    sets x = 0.5 + c + 0.2 cos(3 pi y) of phi, whose curvature at the tips is
    0.2 (3 pi)^2 for every c: at the grid row y = 1 (a tip), one unit step of
    0.08 along them turns them by 0.08 · 0.2 (3 pi)^2 = 1.42 rad, the largest turn."""
    for path in sorted(METRICS.glob("*.yaml")):
        assert sharpest_turn(load_metric(path))[0] <= MAX_FRAME_TURN, path.name
    text = (METRICS / "hard" / "tight_front.yaml").read_text()
    turn = sharpest_turn(load_metric_text(text))[0]
    assert math.isclose(turn, 0.08 * 0.2 * (3 * math.pi) ** 2, rel_tol=1e-9)
    relaxed = load_metric_text(text.replace("hmax: 0.08", "hmax: 0.05"))
    assert sharpest_turn(relaxed)[0] <= MAX_FRAME_TURN


def test_metric_area_of_a_steep_wall_layer_against_adaptive_1d_quadrature():
    """sqrt(det g) = 1 / (0.08 h(y)) depends on y alone: the area is 1.6 / 0.08 times
    ∫₀¹ dy / h(y), integrated by scipy's adaptive quadrature. The layer is resolved
    within 1e-4 of the wall, where a uniform grid of the box misses 3 %."""
    from scipy.integrate import quad

    def h(y):
        return 0.08 - (0.08 - 0.00008) * math.exp(-y / 0.15)

    exact = 1.6 / 0.08 * quad(lambda y: 1 / h(y), 0, 1, epsrel=1e-12, points=[1e-4, 1e-3])[0]
    fld = load_metric(METRICS / "wall_layer_steep.yaml")
    assert density_integral(fld) == pytest.approx(exact, rel=2e-5)
    assert density_integral(fld, rtol=1e-8) == pytest.approx(exact, rel=1e-8)


def test_a_fields_hash_is_made_once_and_is_the_dataclass_hash_of_all_its_fields():
    import dataclasses

    text = (METRICS / "three_toys.yaml").read_text()
    fld, same = load_metric_text(text), load_metric_text(text)
    fields = tuple(getattr(fld, f.name) for f in dataclasses.fields(fld))
    assert hash(fld) == hash(fields) == hash(same) and fld == same
    assert hash(dataclasses.replace(fld, jit=False)) != hash(fld)
    assert "_hash" in vars(fld)  # kept after the first call
