"""The compiled kernels against the numpy code they stand in for, and the metric cache.

Every metric with expressions is evaluated by compiled scalar code
(:mod:`curvimesh.kernels`) by default; ``MetricField(jit=False)`` keeps the
vectorised numpy expressions, the reference the kernels are judged by here.
The analytic oracles of test_geodesic.py and test_metric.py run on the
compiled path.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import numba
import numpy as np
import pytest
import sympy
from hypothesis import given, settings
from hypothesis import strategies as st

from curvimesh import geodesic as geo
from curvimesh import kernels
from curvimesh.errors import MetricError
from curvimesh.metric import (
    Component,
    MetricField,
    X,
    Y,
    load_metric,
    load_metric_text,
)
from curvimesh.tensors import intersect_components, intersect_with_derivatives, nested

METRICS = Path(__file__).resolve().parent.parent / "metrics"
EXAMPLES = ["toy", "three_toys", "concentric", "quartic", "front", "circular_layer"]


def both(fld: MetricField) -> tuple[MetricField, MetricField]:
    """The field on the compiled path and on the numpy path."""
    assert fld.kernel is not None
    return fld, dataclasses.replace(fld, jit=False)


def box_points(fld: MetricField, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xmin, ymin, xmax, ymax = fld.box
    return np.column_stack([rng.uniform(xmin, xmax, n), rng.uniform(ymin, ymax, n)])


def scale(g: np.ndarray, dg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-point magnitudes of g, and of ∂g's terms (|g| over the box's length scale)."""
    mag = np.abs(g).max(axis=(1, 2))
    return mag, np.maximum(np.abs(dg).max(axis=(1, 2, 3)), mag)


@pytest.mark.parametrize("name", EXAMPLES)
def test_compiled_metric_and_derivatives_match_numpy(name):
    fast, ref = both(load_metric(METRICS / f"{name}.yaml"))
    pts = box_points(fast, 4000, 7)
    # the singular centre of the rings and the box corners take the limits
    pts = np.vstack([pts, [[0.0, 0.0], [0.5, 0.5]], np.array(fast.box).reshape(2, 2)])
    g, dg = fast.evaluate(pts, derivatives=True)
    g0, dg0 = ref.evaluate(pts, derivatives=True)
    mag, dmag = scale(g0, dg0)
    # intersections reduce nearly proportional tensors: 1e-9 relative there
    tol = 1e-9 if name == "three_toys" else 1e-12
    assert np.all(np.abs(g - g0).max(axis=(1, 2)) <= tol * mag)
    assert np.all(np.abs(dg - dg0).max(axis=(1, 2, 3)) <= 1e3 * tol * dmag)


# --------------------------------------------------------------------------- #
# The intersection's derivatives: forward mode against the complex step        #
# --------------------------------------------------------------------------- #


def complex_step_intersect_d(a: tuple, b: tuple) -> tuple:
    """The complex-step ``kernels.intersect_d`` that forward mode replaced, kept as the
    reference: ∂ₖI = Im I(M1 + i h ∂ₖM1, M2 + i h ∂ₖM2) / h, h = 1e-30, by
    ``kernels.intersect`` on complex arguments; the value is the y step's real part."""
    h = 1e-30
    z = [
        kernels.intersect(*(a[i] + 1j * h * a[i + k] for i in range(3)),
                          *(b[i] + 1j * h * b[i + k] for i in range(3)))
        for k in (3, 6)
    ]  # fmt: skip
    return (*(v.real for v in z[1]), *(v.imag / h for v in z[0]), *(v.imag / h for v in z[1]))


def rotation(t: float) -> np.ndarray:
    return np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])


def away(s: float) -> st.SearchStrategy[float]:
    """s times or over a factor e^0.06..e^3."""
    return st.builds(
        lambda sign, e: s * math.exp(sign * e), st.sampled_from([-1.0, 1.0]), st.floats(0.06, 3.0)
    )


@st.composite
def spd_pairs(draw, smooth: bool = False) -> dict:
    """M1 = R(θ) diag(l1, l2) R(θ)ᵀ and M2 = B diag(s1, s2) Bᵀ, B = R(θ) diag(√l1, √l2) R(φ):
    the generalised eigenvalues of M2 v = s M1 v are s1 and s2, drawn apart, close
    (nearly proportional metrics), equal, or one of them within 1e-12..0.1 of 1 (where
    max(s, 1) switches); with ``smooth``, apart from each other and from 1. With
    derivatives of M1 and M2 along x and y of their size."""
    log_l1 = draw(st.floats(-2.0, 10.0))
    l1, l2 = math.exp(log_l1), math.exp(log_l1 + draw(st.floats(-5.0, 5.0)))
    if smooth:
        s1 = draw(away(1.0))
        s2 = draw(away(s1).filter(lambda s: abs(math.log(s)) > 0.06))
    else:
        near_one = st.builds(
            lambda sign, e: 1.0 + sign * 10.0**e, st.sampled_from([-1.0, 1.0]), st.floats(-12, -1)
        )
        s1 = draw(st.one_of(st.floats(-3.0, 3.0).map(math.exp), near_one, st.just(1.0)))
        near_s1 = st.builds(
            lambda sign, e: s1 * (1.0 + sign * 10.0**e),
            st.sampled_from([-1.0, 1.0]),
            st.floats(-9, -1),
        )
        s2 = draw(st.one_of(away(s1), near_one, near_s1, st.just(s1)))
    r = rotation(draw(st.floats(0.0, math.pi)))
    m1 = r @ np.diag([l1, l2]) @ r.T
    b = r @ np.diag([math.sqrt(l1), math.sqrt(l2)]) @ rotation(draw(st.floats(0.0, math.pi)))
    m2 = b @ np.diag([s1, s2]) @ b.T
    t = np.array(draw(st.lists(st.floats(-1.0, 1.0), min_size=12, max_size=12)))
    ta, tb = t[:6] * np.abs(m1).max(), t[6:] * np.abs(m2).max()
    return {
        "a": (m1[0, 0], m1[0, 1], m1[1, 1], *ta),
        "b": (m2[0, 0], m2[0, 1], m2[1, 1], *tb),
        "kappa": max(l1, l2) / min(l1, l2),
        "s": (s1, s2),
    }


def reduction_is_whole(a: tuple, b: tuple) -> bool:
    """Whether ``kernels.intersect`` returns M1 or M2 whole or max(1, s) M1 (its tests,
    in the same operations): no null vector is computed."""
    m2_over, m1_over = nested(*(tuple(np.array([v]) for v in m[:3]) for m in (a, b)))
    if m2_over[0] or m1_over[0]:
        return True
    qa = a[0] * a[2] - a[1] * a[1]
    qb = -(a[0] * b[2] + a[2] * b[0] - 2.0 * a[1] * b[1])
    qc = b[0] * b[2] - b[1] * b[1]
    return qb * qb - 4.0 * qa * qc <= 1e-10 * (qb * qb)


def amplification(pair: dict) -> float:
    """κ(M1) (1 + 1/gap)², gap = |s1 − s2| / max(s1, s2) (1 in the degenerate case): how
    much the rounding of the null vector's derivatives grows. Both of these are the
    derivative of one formula, rounded differently; nested metrics and the degenerate
    case, max(1, s) M1, amplify nothing."""
    if reduction_is_whole(pair["a"], pair["b"]):
        return 1.0
    s1, s2 = pair["s"]
    return pair["kappa"] * (1 + max(s1, s2) / abs(s1 - s2)) ** 2


def relative_derivative(a: tuple, b: tuple) -> float:
    """The largest derivative of M1 and M2 relative to their size."""
    return max(np.abs(m[3:]).max() / np.abs(m[:3]).max() for m in (a, b))


def derivative_magnitude(d: np.ndarray, a: tuple, b: tuple) -> float:
    """The scale of an intersection's derivatives: the largest of them, or |I| times the
    largest relative derivative of M1 and M2 (∂I ~ I ∂M / M) when they cancel."""
    return max(np.abs(d[3:]).max(), np.abs(d[:3]).max() * relative_derivative(a, b))


@settings(max_examples=600, deadline=None)
@given(spd_pairs())
def test_forward_mode_intersection_derivatives_are_the_complex_steps(pair):
    a, b = pair["a"], pair["b"]
    new = np.array(kernels.intersect_d(a, b))
    # the values are those of the real intersection, bit for bit
    assert np.array_equal(new[:3], kernels.intersect(*a[:3], *b[:3]))
    old = np.array(complex_step_intersect_d(a, b))  # its value is off by ~h² = 1e-60
    assert np.abs(new[:3] - old[:3]).max() <= 1e-15 * np.abs(old[:3]).max()
    g, dg = intersect_with_derivatives(
        tuple(np.array([v]) for v in a[:3]),
        [tuple(np.array([v]) for v in a[3 * k : 3 * k + 3]) for k in (1, 2)],
        tuple(np.array([v]) for v in b[:3]),
        [tuple(np.array([v]) for v in b[3 * k : 3 * k + 3]) for k in (1, 2)],
    )
    ref = np.array([*(v[0] for v in g), *(v[0] for d in dg for v in d)])
    # (over 8,000 drawn pairs the complex step and forward mode differed by at most
    # 1.2e-14 of this, by 2e-12 relative where s1 and s2 are 10% apart or more)
    tol = 1e-12 * amplification(pair) * derivative_magnitude(old, a, b)
    assert np.abs(new[3:] - old[3:]).max() <= tol
    assert np.abs(new[3:] - ref[3:]).max() <= tol


@st.composite
def nested_pairs(draw) -> tuple[np.ndarray, np.ndarray, bool]:
    """M1 SPD (anisotropy up to e^5) and M2 = M1 + P, P positive semidefinite (rank 1
    or 2, of any size against M1), each with random derivatives (9-tuples), and
    whether P has rank 2."""
    r = rotation(draw(st.floats(0.0, math.pi)))
    l1 = math.exp(draw(st.floats(-2.0, 8.0)))
    m1 = r @ np.diag([l1, l1 * math.exp(draw(st.floats(-5.0, 5.0)))]) @ r.T
    q = rotation(draw(st.floats(0.0, math.pi)))
    scale = l1 * math.exp(draw(st.floats(-8.0, 4.0)))
    ratio = draw(st.sampled_from([0.0, 0.3, 1.0]))
    p = q @ np.diag([scale, scale * ratio]) @ q.T
    m2 = m1 + p
    d = np.array(draw(st.lists(st.floats(-1.0, 1.0), min_size=12, max_size=12)))
    a = np.array([m1[0, 0], m1[0, 1], m1[1, 1], *(d[:6] * l1)])
    b = np.array([m2[0, 0], m2[0, 1], m2[1, 1], *(d[6:] * l1)])
    return a, b, ratio > 0.0


@settings(max_examples=300, deadline=None)
@given(nested_pairs())
def test_nested_metrics_intersect_to_the_larger_bit_for_bit(pair):
    # M2 = M1 + P contains M1: the intersection is M2 itself, its derivatives M2's;
    # where P has rank 1, M2 − M1 is singular and rounding may call the pair
    # crossing (s₋ = 1 within rounding): then M2 to rounding, amplified by the
    # conditioning |M2| / |P| of s₊ − 1 (a draw gave 2.8e-12 of 2.4, |P| 1e-4 of it)
    a, b, rank2 = pair
    m2_over, _ = nested(*(tuple(np.array([v]) for v in m[:3]) for m in (a, b)))
    assert m2_over[0] or not rank2
    for x, y in ((a, b), (b, a)):
        got = kernels.intersect(*x[:3], *y[:3])
        numpy = intersect_components(*(tuple(np.array([v]) for v in m[:3]) for m in (x, y)))
        if m2_over[0]:
            assert got == tuple(b[:3])
            assert np.array_equal(kernels.intersect_d(tuple(x), tuple(y)), b)
            assert [v[0] for v in numpy] == list(b[:3])
        else:
            size, gap = np.abs(b[:3]).max(), np.abs(b[:3] - a[:3]).max()
            tol = 1e-12 * size + 16 * np.finfo(float).eps * size * size / gap
            assert np.abs(np.array(got) - b[:3]).max() <= tol


@given(spd_pairs(smooth=True))
@settings(max_examples=300, deadline=None)
def test_intersection_is_the_eigen_reconstruction(pair):
    # independent truth: M = P⁻ᵀ diag(max(1, s)) Λ P⁻¹ from numpy's eigenvectors of
    # M1⁻¹ M2 (P's columns, Λ = Pᵀ M1 P), against the one-term closed form
    a, b = pair["a"], pair["b"]
    m1 = np.array([[a[0], a[1]], [a[1], a[2]]])
    m2 = np.array([[b[0], b[1]], [b[1], b[2]]])
    s, vec = np.linalg.eig(np.linalg.solve(m1, m2))
    inv = np.linalg.inv(vec.real)
    lam = np.diag(vec.real.T @ m1 @ vec.real)
    ref = inv.T @ np.diag(np.maximum(s.real, 1.0) * lam) @ inv
    got = np.array(kernels.intersect(*a[:3], *b[:3]))
    tol = 1e-12 * amplification(pair) * np.abs(ref).max()
    assert np.abs(got - [ref[0, 0], ref[0, 1], ref[1, 1]]).max() <= tol


@settings(max_examples=300, deadline=None)
@given(spd_pairs(smooth=True))
def test_forward_mode_intersection_derivatives_are_central_differences_where_smooth(pair):
    a, b = pair["a"], pair["b"]
    d = np.array(kernels.intersect_d(a, b))
    rel = relative_derivative(a, b)
    h = 1e-6 / rel if rel > 0 else 1.0  # M1 and M2 move by 1e-6 relative
    for k in (1, 2):
        step = [np.array(m[:3]) + h * np.array(m[3 * k : 3 * k + 3]) for m in (a, b)]
        back = [np.array(m[:3]) - h * np.array(m[3 * k : 3 * k + 3]) for m in (a, b)]
        fd = (
            np.array(kernels.intersect(*step[0], *step[1]))
            - np.array(kernels.intersect(*back[0], *back[1]))
        ) / (2 * h)
        # truncation ~h² and rounding ~1e-16 / h, both grown by the conditioning
        # (over 8,000 such differences at most 2e-10 of this)
        tol = 1e-8 * amplification(pair) * derivative_magnitude(d, a, b)
        assert np.abs(fd - d[3 * k : 3 * k + 3]).max() <= tol


def test_undefined_points_are_nan_on_both_paths_and_named_on_check():
    text = """
domain: {box: [[-1, -1], [1, 1]]}
metric:
  tensor: [1 + x, 0, 1]
"""
    fast, ref = both(load_metric_text(text.replace("1 + x", "2 + x")))
    pts = np.array([[-3.0, 0.0], [0.0, 0.0], [-2.5, 0.1]])  # x < -2: g11 < 0
    g, dg = fast.evaluate(pts, derivatives=True, check=False)
    g0, dg0 = ref.evaluate(pts, derivatives=True, check=False)
    assert np.array_equal(np.isnan(g), np.isnan(g0))
    assert np.array_equal(np.isnan(dg), np.isnan(dg0))
    assert np.isnan(g[[0, 2]]).all() and np.isfinite(g[1]).all()
    with pytest.raises(MetricError, match=r"at \(-3, 0\): g = "):
        fast.evaluate(pts)


@pytest.mark.parametrize("name", ["toy", "three_toys", "front"])
def test_compiled_christoffel_accelerations_match_numpy(name):
    # ẍ = −Γ(x)(v, v) and the geodesic's bend at chord middles (geodesic_alpha)
    fast, ref = both(load_metric(METRICS / f"{name}.yaml"))
    x = box_points(fast, 2000, 21)
    v = np.random.default_rng(22).normal(size=(len(x), 2))
    acc, acc0 = geo._acceleration(fast, x, v), geo._acceleration(ref, x, v)
    assert np.isfinite(acc0).all()
    # relative 1e-9, or 1e-12 of the largest where the metric is flat (ẍ ~ 1e-15)
    scale = np.maximum(np.abs(acc0).max(axis=1, keepdims=True), 1e-3 * np.abs(acc0).max())
    assert np.all(np.abs(acc - acc0) <= 1e-9 * scale)
    b = x + 0.05 * v
    a1, a0 = geo.geodesic_alpha(fast, x, b), geo.geodesic_alpha(ref, x, b)
    assert np.all(np.abs(a1 - a0) <= 1e-9 * np.maximum(np.abs(a0), 1e-3))


@pytest.mark.parametrize("name", ["toy", "three_toys", "front"])
def test_geodesic_kernels_match_numpy(name):
    fast, ref = both(load_metric(METRICS / f"{name}.yaml"))
    a = box_points(fast, 1500, 11)
    d = np.random.default_rng(12).normal(size=(len(a), 2))
    s1, s0 = geo.shoot(fast, a, d, 1.0), geo.shoot(ref, a, d, 1.0)
    assert np.array_equal(s1.ok, s0.ok) and s1.ok.sum() > 1000
    ok = s1.ok
    span = np.abs(s0.end[ok] - a[ok]).max(axis=1)
    assert np.all(np.abs(s1.end[ok] - s0.end[ok]).max(axis=1) <= 1e-6 * span)
    b = np.where(ok[:, None], s1.end, a + 0.01)
    p1, p0 = geo.shortest_parabola(fast, a, b), geo.shortest_parabola(ref, a, b)
    # the compiled search walks from the geodesic's bend, the numpy one scans: both
    # stop within 1e-4 of the same minimum in α, where the length is flat (its error
    # quadratic in α's, ~1e-8 times the curvature)
    np.testing.assert_allclose(p1.alpha, p0.alpha, atol=1e-4)
    np.testing.assert_allclose(p1.length, p0.length, rtol=1e-6)
    np.testing.assert_allclose(
        geo.chord_lower_bound(fast, a, b), geo.chord_lower_bound(ref, a, b), rtol=1e-7
    )
    np.testing.assert_allclose(
        geo.lens_lower_bound(fast, a, b), geo.lens_lower_bound(ref, a, b), rtol=1e-7
    )
    np.testing.assert_allclose(
        geo.parabola_length_rule(fast, a, b, p0.mid),
        geo.parabola_length_rule(ref, a, b, p0.mid),
        rtol=1e-7,
    )


def test_parabola_through_undefined_region_is_infinitely_long_on_both_paths():
    fld = MetricField((Component((1 / Y, sympy.Integer(0), 1 / Y)),), box=(-1, 0.1, 1, 2))
    fast, ref = both(fld)
    a, b = np.array([[-0.5, 0.2], [0.0, 1.0]]), np.array([[0.5, 0.2], [0.3, 1.2]])
    mid = np.array([[0.0, -0.5], [0.15, 1.1]])  # the first dips below y = 0
    for f in (fast, ref):
        ln = geo.parabola_length_rule(f, a, b, mid)
        assert ln[0] == math.inf and np.isfinite(ln[1])


def test_constant_metric_shortest_parabola_on_the_compiled_path_is_the_segment():
    g = np.array([[40.0, 12.0], [12.0, 5.0]])
    fld = MetricField((Component(tuple(sympy.Float(v) for v in (40.0, 12.0, 5.0))),))
    assert fld.kernel is not None
    rng = np.random.default_rng(3)
    a, b = rng.uniform(0, 1, (200, 2)), rng.uniform(0, 1, (200, 2))
    par = geo.shortest_parabola(fld, a, b)
    d = b - a
    exact = np.sqrt(np.einsum("pi,ij,pj->p", d, g, d))
    np.testing.assert_allclose(par.length, exact, rtol=1e-9)
    np.testing.assert_allclose(par.alpha, 0.0, atol=1e-3)


def test_compiled_metric_is_cached_on_disk_and_loads_from_it(tmp_path, monkeypatch):
    monkeypatch.setenv(kernels.CACHE_ENV, str(tmp_path))
    src = MetricField((Component((1 + X**2, X * Y / 10, 2 + sympy.sin(Y))),)).scalar_source
    first = kernels.compile_metric(src, "field_g", "field_gd")
    modules = list(tmp_path.glob("metric_*.py"))
    assert len(modules) == 1 and "def field_gd(x, y):" in modules[0].read_text()
    assert any((tmp_path / "__pycache__").glob("*.nbi"))  # numba's index of machine code
    again = kernels.compile_metric(src, "field_g", "field_gd")
    pts = np.array([[0.3, -0.7], [2.0, 1.0]])
    for cm in (first, again):
        g, dg = kernels.evaluate(cm, pts, True)
        np.testing.assert_allclose(g[:, 0, 0], 1 + pts[:, 0] ** 2, rtol=1e-15)
        np.testing.assert_allclose(dg[:, 1, 1, 1], np.cos(pts[:, 1]), rtol=1e-15)


def test_a_field_whose_module_is_cached_loads_it_without_generating_its_source(
    tmp_path, monkeypatch
):
    from curvimesh import metric as metric_module

    monkeypatch.setenv(kernels.CACHE_ENV, str(tmp_path))
    monkeypatch.setattr(metric_module, "_COMPILED", {})
    g = (1 + X**2, X * Y / 10, 2 + sympy.sin(Y))
    first = MetricField((Component(g),))
    assert first.kernel is not None
    assert "scalar_source" in first.__dict__  # made once, to write the module
    assert len(list(tmp_path.glob("metric_*.py"))) == 1

    monkeypatch.setattr(metric_module, "_COMPILED", {})  # a new process
    again = MetricField((Component(g),))
    pts = np.array([[0.3, -0.7], [2.0, 1.0]])
    gv, dg = again.evaluate(pts, derivatives=True)
    assert "scalar_source" not in again.__dict__  # found by its key, on disk
    assert len(list(tmp_path.glob("metric_*.py"))) == 1
    np.testing.assert_allclose(gv[:, 0, 1], pts[:, 0] * pts[:, 1] / 10, rtol=1e-15)
    np.testing.assert_allclose(dg[:, 1, 1, 1], np.cos(pts[:, 1]), rtol=1e-15)

    # the box is in the source (its limit offsets), so in the key; so are the expressions
    other_box = MetricField((Component(g),), box=(0.0, 0.0, 2.0, 1.0))
    other_g = MetricField((Component((1 + X**2, X * Y / 10, 2 + sympy.cos(Y))),))
    assert len({f.source_key for f in (again, other_box, other_g)}) == 3
    assert other_box.kernel is not None and other_g.kernel is not None
    assert len(list(tmp_path.glob("metric_*.py"))) == 3


def test_a_source_that_cannot_be_made_compiles_to_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv(kernels.CACHE_ENV, str(tmp_path))
    assert kernels.compile_metric(lambda: None, "field_g", "field_gd", key="none") is None
    assert not list(tmp_path.glob("metric_*.py"))


def test_the_numpy_derivatives_are_compiled_only_when_used():
    fld = load_metric(METRICS / "toy.yaml")
    (comp,) = fld.components
    assert "_fn" not in comp.__dict__  # loading and validating need g alone
    pts = np.array([[0.2, 0.3], [0.7, 0.9]])
    _, dg = fld.evaluate_numpy(pts, derivatives=True)
    _, dg_kernel = fld.evaluate(pts, derivatives=True)
    assert "_fn" in comp.__dict__
    np.testing.assert_allclose(dg, dg_kernel, rtol=1e-12, atol=1e-9)


def test_cache_off_compiles_in_memory(tmp_path, monkeypatch):
    monkeypatch.setenv(kernels.CACHE_ENV, "off")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    src = MetricField((Component((3 + X, sympy.Integer(0), 3 - Y)),)).scalar_source
    cm = kernels.compile_metric(src, "field_g", "field_gd")
    g, _ = kernels.evaluate(cm, np.array([[1.0, 2.0]]), False)
    assert g[0].tolist() == [[4.0, 0.0], [0.0, 1.0]]
    assert not any(tmp_path.iterdir())


def test_powers_of_zero_are_infinite_not_an_exception():
    # numba raises ZeroDivisionError for 0.0 ** -2; the generated code must not
    fld = MetricField(
        (Component((1 + 1 / X**2, sympy.Integer(0), 1 + X ** sympy.Rational(-3, 2))),)
    )
    g, _ = fld.evaluate(np.array([[0.0, 0.5]]), check=False)
    g0, _ = dataclasses.replace(fld, jit=False).evaluate(np.array([[0.0, 0.5]]), check=False)
    assert np.array_equal(np.isnan(g), np.isnan(g0))


@settings(max_examples=25, deadline=None)
@given(
    a=st.floats(0.5, 5.0),
    b=st.floats(-0.4, 0.4),
    k=st.floats(0.1, 6.0),
    c=st.floats(0.5, 5.0),
    fn=st.sampled_from(["sin", "cos", "tanh", "exp", "atan"]),
)
def test_random_smooth_metrics_compile_to_the_numpy_values(a, b, k, c, fn):
    f = getattr(sympy, fn)
    g11 = a + f(k * X) ** 2
    g12 = b * sympy.cos(k * Y)
    g22 = c + sympy.Abs(X - Y) / 3 + sympy.Max(X, Y) ** 2
    fast, ref = both(MetricField((Component((g11, g12, g22)),), box=(-1, -1, 1, 1)))
    pts = box_points(fast, 300, 5)
    g, dg = fast.evaluate(pts, derivatives=True, check=False)
    g0, dg0 = ref.evaluate(pts, derivatives=True, check=False)
    mag, dmag = scale(g0, dg0)
    assert np.all(np.abs(g - g0).max(axis=(1, 2)) <= 1e-13 * mag)
    assert np.all(np.abs(dg - dg0).max(axis=(1, 2, 3)) <= 1e-12 * dmag)


def _random_cloud(fld: MetricField, n: int, seed: int) -> np.ndarray:
    """The box corners, points on its sides and n random inner points."""
    xmin, ymin, xmax, ymax = fld.box
    s = np.linspace(0.0, 1.0, 12)[1:-1]
    sides = np.concatenate(
        [
            np.column_stack([xmin + s * (xmax - xmin), np.full_like(s, ymin)]),
            np.column_stack([xmin + s * (xmax - xmin), np.full_like(s, ymax)]),
            np.column_stack([np.full_like(s, xmin), ymin + s * (ymax - ymin)]),
            np.column_stack([np.full_like(s, xmax), ymin + s * (ymax - ymin)]),
        ]
    )
    corners = np.array([[xmin, ymin], [xmax, ymin], [xmax, ymax], [xmin, ymax]])
    return np.concatenate([corners, sides, box_points(fld, n, seed)])


@pytest.mark.parametrize("name", ["toy", "three_toys", "constant_aniso"])
def test_compiled_flips_give_the_numpy_triangulation(name):
    from curvimesh.mesh import is_conforming, signed_areas
    from curvimesh.triangulate import delaunay, metric_delaunay

    fast, ref = both(load_metric(METRICS / f"{name}.yaml"))
    mesh = delaunay(_random_cloud(fast, 3000, 21), box=fast.box)
    got, want = metric_delaunay(fast, mesh), metric_delaunay(ref, mesh)
    assert got.corners.tolist() == want.corners.tolist()
    assert is_conforming(got) and (signed_areas(got.points, got.corners) > 0).all()
    assert got.corners.tolist() != mesh.corners.tolist()  # the metric made it flip


def test_compiled_flips_on_one_thread_or_two_make_the_same_triangulation():
    # the measures of a round are made on numba's threads, the flips in one order
    import numba

    from curvimesh.triangulate import delaunay, metric_delaunay

    fld = load_metric(METRICS / "three_toys.yaml")
    mesh = delaunay(_random_cloud(fld, 3000, 23), box=fld.box)
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        one = metric_delaunay(fld, mesh).corners.tolist()
    finally:
        numba.set_num_threads(threads)
    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    try:
        two = metric_delaunay(fld, mesh).corners.tolist()
    finally:
        numba.set_num_threads(threads)
    assert one == two and one != mesh.corners.tolist()


def test_compiled_flips_on_a_regular_grid_break_ties_as_numpy():
    # a constant metric on a lattice: every quad is co-circular in the metric up to
    # rounding, so the order of equal violations decides
    from curvimesh.triangulate import delaunay, metric_delaunay

    g = (sympy.Float(4.0), sympy.Float(1.5), sympy.Float(1.0))
    fast, ref = both(MetricField((Component(g),), box=(0.0, 0.0, 1.0, 1.0)))
    gx, gy = np.meshgrid(np.linspace(0, 1, 15), np.linspace(0, 1, 15))
    mesh = delaunay(np.column_stack([gx.ravel(), gy.ravel()]), box=fast.box)
    assert (
        metric_delaunay(fast, mesh).corners.tolist() == metric_delaunay(ref, mesh).corners.tolist()
    )


def test_compiled_flips_name_an_undefined_centroid():
    from curvimesh.triangulate import delaunay, metric_delaunay

    fld = MetricField((Component((1 + X, sympy.Integer(0), 1 + X)),), box=(-2.0, 0.0, 1.0, 1.0))
    mesh = delaunay(_random_cloud(fld, 50, 2), box=fld.box)
    with pytest.raises(MetricError, match="not finite and positive definite at"):
        metric_delaunay(fld, mesh)


@pytest.mark.parametrize("name", ["toy", "three_toys", "front"])
def test_verdicts_stopping_early_match_full_searches(name):
    fast, ref = both(load_metric(METRICS / f"{name}.yaml"))
    a = box_points(fast, 3000, 31)
    rng = np.random.default_rng(32)
    # ends at metric distances around the thresholds, in every direction
    shot = geo.shoot(fast, a, rng.normal(size=(len(a), 2)), rng.uniform(0.4, 1.8, len(a)))
    b = np.where(shot.ok[:, None], shot.end, a + 1e-3)
    long = rng.uniform(1.0, 1.5, len(a))
    got = geo.parabola_verdicts(fast, a, b, short=0.7, long=long)
    want = geo.parabola_verdicts(ref, a, b, short=0.7, long=long)
    length, _ = geo.bounded_lengths(fast, a, b, short=0.7, long=long)
    from_lengths = np.where(length < 0.7, -1, np.where(length > long, 1, 0))
    assert np.array_equal(got, want) and np.array_equal(got, from_lengths)
    assert min((got == v).sum() for v in (-1, 0, 1)) > 100  # all three verdicts occur
    one_sided = geo.parabola_verdicts(fast, a, b, short=0.7)
    assert np.array_equal(one_sided, np.where(length < 0.7, -1, 0))


def test_verdicts_find_a_short_parabola_in_a_narrow_valley_of_alpha():
    # two points 0.066 apart across the front (the pair of a 0.6991 edge sampled at
    # seed 4): the parabola is short only where it follows the front, α ≈ 0.08,
    # between the scanned values 0 and 0.25 (lengths 1.88 and 1.82): not convex in α
    # on the scan's bracket, whose secants put the floor at 0.87
    fast, ref = both(load_metric(METRICS / "front.yaml"))
    a, b = np.array([[0.71834314, 0.24216946]]), np.array([[0.78463087, 0.24148866]])
    alpha = np.linspace(-0.5, 0.5, 2001)
    x0, x1 = np.repeat(a, alpha.size, 0), np.repeat(b, alpha.size, 0)
    profile = geo.parabola_length(ref, x0, x1, geo.parabola_midnode(x0, x1, alpha))
    shortest = profile.min()
    assert 0.69 < shortest < 0.7 and 0.07 < alpha[profile.argmin()] < 0.09
    assert profile[alpha == 0.0][0] > 1.8 and profile[np.isclose(alpha, 0.25)][0] > 1.8
    for fld in (fast, ref):
        assert geo.parabola_verdicts(fld, a, b, short=0.7).tolist() == [-1]
        assert geo.parabola_verdicts(fld, b, a, short=0.7, long=np.array([1.4])).tolist() == [-1]
        assert geo.any_closer(fld, a, b, np.array([0, 1]), np.array([0]), 0.7).tolist() == [True]


@pytest.mark.parametrize("name", ["toy", "three_toys", "front"])
def test_compiled_metric_areas_match_numpy(name):
    from curvimesh.quality import metric_areas

    fast, ref = both(load_metric(METRICS / f"{name}.yaml"))
    rng = np.random.default_rng(41)
    corners = box_points(fast, 600, 42)
    step = np.array([[0.02, 0.0], [0.0, 0.02]])
    tri = np.stack([corners, corners + step[0], corners + step[1]], axis=1)
    mids = 0.5 * (tri + tri[:, [1, 2, 0]]) + rng.normal(scale=0.002, size=(600, 3, 2))
    nodes = np.concatenate([tri, mids], axis=1)
    got, want = metric_areas(fast, nodes), metric_areas(ref, nodes)
    np.testing.assert_allclose(got, want, rtol=1e-11 if name == "three_toys" else 1e-13)


def _curved_triangles(fld: MetricField, n: int, seed: int) -> np.ndarray:
    """Curved triangles ``(n, 6, 2)`` about random points of the box, of sizes 10⁻³ – 0.3."""
    rng = np.random.default_rng(seed)
    centre = box_points(fld, n, seed)[:, None, :]
    size = 10 ** rng.uniform(-3, -0.5, (n, 1, 1))
    corners = centre + size * rng.normal(size=(n, 3, 2))
    mids = 0.5 * (corners + corners[:, [1, 2, 0]]) + 0.1 * size * rng.normal(size=(n, 3, 2))
    return np.concatenate([corners, mids], axis=1)


def test_children_are_the_p2_map_of_the_quarter_points():
    from curvimesh.bezier import p2_map
    from curvimesh.quality import _CHILD_UV, _children

    nodes = _curved_triangles(load_metric(METRICS / "toy.yaml"), 200, 45)
    got = _children(nodes).reshape(200, 24, 2)
    want = p2_map(nodes, _CHILD_UV)  # numpy's matmul: the same sums, fused or not
    np.testing.assert_allclose(got, want, rtol=0, atol=4e-16 * np.abs(nodes).max())
    # a child's corners and edge midpoints are the parent's map at its quarter points:
    # the middle child's corners are the parent's edge nodes
    np.testing.assert_array_equal(got[:, 18:21], nodes[:, [3, 4, 5]])


@pytest.mark.parametrize("name", ["three_toys", "quartic"])
def test_compiled_adaptive_areas_are_the_level_by_level_loop_bit_for_bit(name):
    from curvimesh.quality import AREA_MAX_LEVEL, REPORT_RTOL, _areas_by_levels
    from curvimesh.quality import metric_areas_adaptive as adaptive

    fld = load_metric(METRICS / f"{name}.yaml")
    nodes = _curved_triangles(fld, 2 * kernels.PARALLEL_ROWS, 43)  # threads take chunks
    chunk = numba.get_parallel_chunksize()
    for rtol, level in ((REPORT_RTOL, AREA_MAX_LEVEL), (1e-9, 3), (0.0, 2)):
        got = adaptive(fld, nodes, rtol=rtol, max_level=level)
        want = _areas_by_levels(fld, nodes, rtol, level)
        assert np.array_equal(got, want, equal_nan=True)
    assert numba.get_parallel_chunksize() == chunk  # the kernel's chunks are its own
    # the loop's deeper levels were reached (the three toys' kinks, the quartic's bends)
    assert not np.array_equal(adaptive(fld, nodes, max_level=0), adaptive(fld, nodes))


@pytest.mark.parametrize("name", ["three_toys", "quartic"])
@pytest.mark.parametrize("max_segments", [1, 2, 100, 256])
def test_compiled_adaptive_lengths_are_the_level_by_level_loop_bit_for_bit(name, max_segments):
    fld = load_metric(METRICS / f"{name}.yaml")
    nodes = _curved_triangles(fld, 2 * kernels.PARALLEL_ROWS, 44)  # threads take chunks
    x0, x1, xm = nodes[:, 0], nodes[:, 1], nodes[:, 3]
    two = geo.parabola_length_rule(fld, x0, x1, xm, segments=2, order=5)
    for given_two in (None, two):
        got = geo.parabola_length(
            fld, x0, x1, xm, rtol=1e-8, max_segments=max_segments, two_segments=given_two
        )
        want = geo._lengths_by_levels(fld, x0, x1, xm, 1e-8, 5, max_segments, given_two)
        assert np.array_equal(got, want, equal_nan=True)
    if max_segments == 256:  # rows were refined past two segments
        assert not np.array_equal(geo.parabola_length(fld, x0, x1, xm, max_segments=2), got)


def test_guided_search_keeps_the_scans_minimum_when_the_guess_is_in_a_worse_basin():
    # a costly spot on the chord's middle: parabolas pass it below (α > 0), where the
    # metric is cheaper (1 + 0.3 y), or above (α < 0): two minima in α, 1.254 and 1.335
    f = "(1 + 50*exp(-(x**2 + y**2)/0.02))*(1 + 0.3*y)"
    fld = load_metric_text(
        f"domain: {{box: [[-1, -1], [1, 1]]}}\nmetric: {{tensor: [{f}, 0, {f}]}}"
    )
    a, b = np.array([[-0.5, 0.0]]), np.array([[0.5, 0.0]])
    grid = np.linspace(-0.5, 0.5, 11)

    def search(**guess):
        alpha, length = geo._search_alpha(fld, a, b, grid, 1e-4, 2, 5, **guess)
        return alpha[0], length[0]

    best = search()
    worse = search(start=np.array([-0.3]))  # the walk keeps to the basin it starts in
    assert best[0] > 0.3 and worse[0] < -0.3 and worse[1] > 1.06 * best[1]
    for guess in (-0.3, -0.45, np.nan, 0.7):  # the worse basin, none, out of the scan
        assert search(guess=np.array([guess])) == best  # the scan's own answer
    # in the best basin (the geodesic's bend, 0.019, walks down into it): walked
    for guess in (best[0] + 0.02, float(geo.geodesic_alpha(fld, a, b)[0])):
        alpha, length = search(guess=np.array([guess]))
        assert abs(alpha - best[0]) <= 1e-4 and abs(length - best[1]) <= 1e-8 * best[1]


def test_repeated_searches_are_remembered_exactly():
    fld = load_metric(METRICS / "toy.yaml")
    a = box_points(fld, 500, 51)
    b = a + np.random.default_rng(52).normal(scale=0.05, size=a.shape)
    first = geo.shortest_parabola(fld, a, b, exact_length=False)
    calls = []
    real = geo._search_alpha

    def counting(field, x0, *args, **kwargs):
        calls.append(len(x0))
        return real(field, x0, *args, **kwargs)

    try:
        geo._search_alpha = counting
        # half repeated, half new, in another order: only the new ones are searched
        mixed_a = np.concatenate([a[250:][::-1], a[:250] + 1e-3])
        mixed_b = np.concatenate([b[250:][::-1], b[:250]])
        again = geo.shortest_parabola(fld, mixed_a, mixed_b, exact_length=False)
    finally:
        geo._search_alpha = real
    assert calls == [250]
    assert np.array_equal(again.alpha[:250], first.alpha[250:][::-1])
    assert np.array_equal(again.length[:250], first.length[250:][::-1])
    fresh = geo.shortest_parabola(
        dataclasses.replace(fld, name="other"), mixed_a, mixed_b, exact_length=False
    )
    assert np.array_equal(again.alpha, fresh.alpha)  # what a search from scratch gives
    # the same search without the memo (for pairs that will not come again)
    calls.clear()
    try:
        geo._search_alpha = counting
        alone = geo.shortest_parabola(
            fld, mixed_a, mixed_b, exact_length=False, remember=False, guided=True
        )
    finally:
        geo._search_alpha = real
    assert calls == [500]
    assert np.array_equal(alone.alpha, again.alpha) and np.array_equal(alone.length, again.length)


def test_search_memo_runs_answer_as_a_dictionary(monkeypatch):
    monkeypatch.setattr(geo, "MEMO_SIZE", 3000)
    memo = geo._SearchMemo()
    rng = np.random.default_rng(61)
    truth: dict[bytes, float] = {}
    for size in rng.integers(1, 400, 40):
        pts = np.round(rng.uniform(0, 1, (size, 4)), 2)  # repeats across and within batches
        keys = geo._pair_keys(pts[:, :2], pts[:, 2:])
        alpha, _, found = memo.find(keys)
        for k, a, f in zip(keys, alpha, found, strict=True):
            assert not f or k.tobytes() in truth  # found: stored before (dropped runs forget)
            if f:
                assert a == truth[k.tobytes()]
        new = np.flatnonzero(~found)
        values = rng.uniform(size=new.size)
        memo.add(keys[new], values, values)
        for k, v in zip(keys[new], values, strict=True):
            truth.setdefault(k.tobytes(), v)  # the first of repeated keys is kept
        assert sum(len(r[0]) for r in memo.runs) <= 3000 or len(memo.runs) == 1
        sizes = [len(r[0]) for r in memo.runs]
        assert sizes == sorted(sizes, reverse=True)  # runs shrink: O(log n) of them


@pytest.mark.parametrize("name", ["toy", "front"])
def test_any_closer_nearest_first_gives_the_pairwise_verdicts(name):
    fast, ref = both(load_metric(METRICS / f"{name}.yaml"))
    pts = box_points(fast, 700, 71)
    cand = box_points(fast, 1500, 72)
    rng = np.random.default_rng(73)
    counts = rng.integers(0, 40, len(cand))
    offsets = np.concatenate([[0], np.cumsum(counts)])
    # neighbours: mostly the nearest points (as the R-tree gives), some far ones
    d = np.hypot(*(cand[:, None, :] - pts[None, :, :]).transpose(2, 0, 1))
    near = np.argsort(d, axis=1)
    hits = np.concatenate(
        [
            np.concatenate([near[i, :c][::-1], rng.integers(0, len(pts), c // 4)])[:c]
            for i, c in enumerate(counts)
        ]
    )
    got = geo.any_closer(fast, cand, pts, offsets, hits, 0.7, straight_order=4)
    want = geo.any_closer(ref, cand, pts, offsets, hits, 0.7, straight_order=4)
    q = np.repeat(np.arange(len(cand)), counts)
    pairwise = geo.parabola_verdicts(fast, cand[q], pts[hits], short=0.7, straight_order=4) < 0
    from_pairs = np.zeros(len(cand), dtype=bool)
    from_pairs[q[pairwise]] = True
    assert np.array_equal(got, want) and np.array_equal(got, from_pairs)
    assert 50 < got.sum() < len(cand) - 50  # both answers occur
    assert not got[counts == 0].any()


@pytest.mark.parametrize("name", ["toy", "front"])
def test_closeness_in_an_index_is_the_pairwise_verdict_over_its_ellipses(name):
    from curvimesh.spatial import PointIndex

    fast, ref = both(load_metric(METRICS / f"{name}.yaml"))
    index = PointIndex()
    for seed in (81, 82, 83):  # three batches: several packed trees
        index.add(box_points(fast, 600, seed))
    pts = index.points
    cand = box_points(fast, 1200, 84)
    rng = np.random.default_rng(85)
    # boxes from tiny to wide (hundreds of points: past the kernel's first buffer)
    xmin, ymin, xmax, ymax = fast.box
    half = rng.uniform(0.001, 0.15, (len(cand), 2)) * [xmax - xmin, ymax - ymin]
    exclude = np.where(rng.random(len(cand)) < 0.3, rng.integers(0, len(pts), len(cand)), -1)
    # candidates on points of the index, excluding them: only the others decide
    exclude[:50] = rng.choice(len(pts), 50, replace=False)
    cand[:50] = pts[exclude[:50]]
    mins, maxs = cand - half, cand + half
    got = geo.any_closer_in_index(fast, cand, mins, maxs, index, exclude, 0.7, straight_order=4)
    want = geo.any_closer_in_index(ref, cand, mins, maxs, index, exclude, 0.7, straight_order=4)
    # the truth: every point in the ellipse inscribed in the box but the excluded
    # one, pair by pair
    inside = (((pts[None] - cand[:, None]) / half[:, None]) ** 2).sum(axis=2) <= 1.0
    in_box = np.all((pts[None] >= mins[:, None]) & (pts[None] <= maxs[:, None]), axis=2)
    assert (in_box & ~inside).sum() > 0.1 * in_box.sum()  # the corners are left out
    inside[np.arange(len(cand)), exclude] &= exclude < 0
    q, h = np.nonzero(inside)
    pairwise = geo.parabola_verdicts(fast, cand[q], pts[h], short=0.7, straight_order=4) < 0
    truth = np.zeros(len(cand), dtype=bool)
    truth[q[pairwise]] = True
    assert inside.sum(axis=1).max() > 64
    assert np.array_equal(got, truth) and np.array_equal(want, truth)
    assert 50 < got.sum() < len(cand) - 50
    assert not truth[:50].all()  # the exclusions matter


def test_a_row_kernel_gives_the_same_results_on_one_thread_and_puts_the_threads_back():
    import numba

    fld = load_metric(METRICS / "toy.yaml")
    a = box_points(fld, 3000, 81)
    b = a + np.random.default_rng(82).normal(scale=0.05, size=a.shape)
    t, w = geo.gauss_rule(2, 5)
    grid = np.linspace(-0.5, 0.5, 5)
    out = [np.empty(len(a)) for _ in range(4)]
    threads = numba.get_num_threads()
    kernels.shortest_parabolas(fld.kernel.g, a, b, grid, t, w, 2e-3, 60, out[0], out[1])
    for k in range(0, len(a), 50):  # calls below the kernel's parallel rows
        rows = slice(k, k + 50)
        kernels.shortest_parabolas(
            fld.kernel.g, a[rows], b[rows], grid, t, w, 2e-3, 60, out[2][rows], out[3][rows]
        )
        assert numba.get_num_threads() == threads
    assert np.array_equal(out[0], out[2]) and np.array_equal(out[1], out[3])
    with pytest.raises(TypeError):  # a call that fails puts the threads back too
        kernels.shortest_parabolas(fld.kernel.g, a[:5], b[:5], grid, t, w, 2e-3, 60, None)
    assert numba.get_num_threads() == threads


TOL = 2e-3  # the relocation's search tolerance


def test_search_from_a_guess_finds_the_scans_minimum_nearby():
    fld = load_metric(METRICS / "toy.yaml")
    a = box_points(fld, 3000, 61)
    b = a + np.random.default_rng(62).normal(scale=0.03, size=a.shape)
    kw = dict(scan=5, alpha_tol=TOL, exact_length=False, remember=False)
    ref = geo.shortest_parabola(fld, a, b, **kw)
    guess = ref.alpha + np.random.default_rng(63).uniform(-0.05, 0.05, len(a))
    got = geo.shortest_parabola(fld, a, b, start=guess, **kw)
    assert np.all(np.isfinite(got.length))
    near = np.abs(got.alpha - ref.alpha) <= 2 * TOL
    # the odd pair across a curved layer has another local minimum within 0.05
    assert near.mean() >= 0.99
    rel = (got.length - ref.length) / ref.length
    assert np.all(np.abs(rel[near]) <= 3e-5)
    # no guess (NaN), or one outside the scanned range: the scan itself
    none = geo.shortest_parabola(fld, a, b, start=np.full(len(a), np.nan), **kw)
    outside = geo.shortest_parabola(fld, a, b, start=np.full(len(a), 0.7), **kw)
    assert np.array_equal(none.alpha, ref.alpha) and np.array_equal(none.length, ref.length)
    assert np.array_equal(outside.alpha, ref.alpha)


def test_search_from_any_guess_in_a_constant_metric_ends_on_the_segment():
    fld = load_metric_text("domain: {box: [[0, 0], [1, 1]]}\nmetric: {tensor: [400, 120, 100]}\n")
    rng = np.random.default_rng(71)
    a = rng.uniform(0.2, 0.8, (500, 2))
    b = a + rng.normal(scale=0.05, size=a.shape)
    guess = rng.uniform(-0.45, 0.45, len(a))
    got = geo.shortest_parabola(
        fld, a, b, scan=5, alpha_tol=TOL, exact_length=False, remember=False, start=guess
    )
    d = b - a
    exact = np.sqrt(400 * d[:, 0] ** 2 + 240 * d[:, 0] * d[:, 1] + 100 * d[:, 1] ** 2)
    assert np.all(np.abs(got.alpha) <= TOL)
    # a parabola offset by α|b − a| is longer by the factor 1 + (8/3)α² (to first order)
    assert np.all(np.abs(got.length / exact - 1) <= 3 * TOL**2)


def test_a_guess_is_refused_with_the_memo():
    fld = load_metric(METRICS / "toy.yaml")
    with pytest.raises(ValueError, match="remember"):
        geo.shortest_parabola(fld, [[0.1, 0.1]], [[0.2, 0.2]], start=np.zeros(1))


def test_void_key_binary_search_is_numpys_searchsorted():
    rng = np.random.default_rng(91)
    pts = rng.normal(size=(5000, 4))
    pts[1::2, :3] = pts[::2, :3]  # keys sharing 24 of their 32 bytes
    keys = np.ascontiguousarray(np.vstack([pts, pts[:300]])).view(geo._PAIR_KEY).ravel()
    keys.sort()  # with repeated keys
    queries = np.vstack([pts[rng.integers(0, len(pts), 2000)], rng.normal(size=(2000, 4))])
    queries[:10] = [[-1e300] * 4] * 5 + [[1e300] * 4] * 5  # before the first, after the last
    q = np.ascontiguousarray(queries).view(geo._PAIR_KEY).ravel()
    assert np.array_equal(geo._lower_bound(keys, q), np.searchsorted(keys, q))
    assert geo._lower_bound(keys, q[:0]).shape == (0,)


def test_the_cache_loses_its_least_recently_used_metrics_past_its_size(tmp_path):
    """Six fake metrics of 1,000 bytes in module and numba files, used at times 1..6;
    a cap of 3,500 bytes keeps the three used last, and the one asked to be kept."""
    (tmp_path / "__pycache__").mkdir()
    for t in range(1, 7):
        key = f"{t:024x}"
        py = tmp_path / f"metric_{key}.py"
        py.write_bytes(b"#" * 400)
        (tmp_path / "__pycache__" / f"metric_{key}.field_g-5.py311.nbi").write_bytes(b"i" * 100)
        (tmp_path / "__pycache__" / f"metric_{key}.field_g-5.py311.1.nbc").write_bytes(b"c" * 500)
        os.utime(py, (t, t))
    (tmp_path / "other.txt").write_bytes(b"x" * 10_000)  # not a metric: never counted
    keep = f"{1:024x}"
    deleted = kernels.prune_cache(tmp_path, 3_500, keep=keep)
    assert deleted == [f"{t:024x}" for t in (2, 3, 4)]
    left = sorted(p.name[7:31] for p in tmp_path.glob("metric_*.py"))
    assert left == [f"{t:024x}" for t in (1, 5, 6)]
    assert len(list((tmp_path / "__pycache__").iterdir())) == 6
    assert (tmp_path / "other.txt").exists()
    assert kernels.prune_cache(tmp_path, 2_500) == [keep]  # the oldest, no longer kept


def test_loading_a_cached_metric_marks_it_as_used(tmp_path, monkeypatch):
    monkeypatch.setenv(kernels.CACHE_ENV, str(tmp_path))
    src = MetricField((Component((2 + X**2, sympy.Integer(0), 2 + Y**2)),)).scalar_source
    kernels.compile_metric(src, "field_g", "field_gd")
    (module,) = tmp_path.glob("metric_*.py")
    os.utime(module, (1, 1))
    kernels.compile_metric(src, "field_g", "field_gd")
    assert module.stat().st_mtime > 1e9


def test_the_kernels_take_the_metric_typed_once():
    import numba

    fld = load_metric(METRICS / "toy.yaml")
    cm = fld.kernel
    assert isinstance(cm.g, kernels.TypedFunction) and isinstance(cm.gd, kernels.TypedFunction)
    # numba reads the type kept, the one it would build from the cfunc
    assert numba.typeof(cm.g) == numba.typeof(cm.g.cfunc)
    assert numba.typeof(cm.gd) == numba.typeof(cm.gd.cfunc)
    pts = box_points(fld, 300, 91)
    held, raw = np.empty((300, 2, 2)), np.empty((300, 2, 2))
    kernels._eval_g(cm.g, pts, held)
    kernels._eval_g(cm.g.cfunc, pts, raw)
    assert np.array_equal(held, raw)
    np.testing.assert_allclose(held, fld.tensor(pts), rtol=1e-12)
    assert cm.g(0.1, 0.2) == cm.g.cfunc(0.1, 0.2)


@pytest.mark.parametrize("name", ["three_toys", "front"])
def test_tracked_lengths_are_the_bend_and_rule_lengths_bit_for_bit(name):
    # kernels.tracked_lengths against its definition (smooth.tracked_lengths' numpy):
    # the bend by geodesic_alpha, the parabolas' lengths by parabola_length_rule, the
    # shorter kept (the last α on a tie), both on the compiled metric
    from curvimesh import smooth

    fld = load_metric(METRICS / f"{name}.yaml")
    rng = np.random.default_rng(31)
    a = box_points(fld, 3000, 32)
    b = a + 0.05 * rng.normal(size=a.shape)
    pts = np.concatenate([a, b])
    edges = np.column_stack([np.arange(3000), np.arange(3000, 6000)])
    alpha = geo.geodesic_alpha(fld, a, b) + rng.choice([0.0, 1e-4, 0.05], 3000)
    alpha[::7] = np.nan
    length, kept = smooth.tracked_lengths(fld, pts, edges, alpha)
    bend = geo.geodesic_alpha(fld, a, b)
    bend[~np.isfinite(bend)] = 0.0
    at_alpha = geo.parabola_length_rule(fld, a, b, geo.parabola_midnode(a, b, alpha))
    at_bend = geo.parabola_length_rule(fld, a, b, geo.parabola_midnode(a, b, bend))
    other = ~(np.abs(bend - alpha) <= smooth.ALPHA_TOL)
    use = other & (at_bend < at_alpha)
    assert 100 < other.sum() < 3000 and use.sum() > 100
    assert np.array_equal(length, np.where(use, at_bend, at_alpha))
    assert np.array_equal(kept, np.where(use, bend, alpha), equal_nan=True)


def test_relocation_sweep_is_the_weighted_mean_of_the_unit_points_bit_for_bit():
    # kernels.relocation_sweep against the bincounts it stands for: each vertex towards
    # the mean of p_j + (p_i − p_j) / L over its edges (p_i where L is not finite and
    # positive) weighed by w, unless fixed or without edges
    rng = np.random.default_rng(41)
    n, m = 400, 1500
    pts = rng.uniform(-1.0, 1.0, (n, 2))
    edges = rng.integers(0, n - 20, (m, 2))  # the last 20 vertices have no edge
    edges = edges[edges[:, 0] != edges[:, 1]]
    length = rng.uniform(0.3, 3.0, len(edges))
    length[::11], length[1::13], length[2::17] = np.inf, np.nan, 0.0
    weight = rng.uniform(0.5, 4.0, len(edges))
    fixed = rng.random(n) < 0.1
    new, moved = np.empty_like(pts), np.empty(n, dtype=bool)
    kernels.relocation_sweep(pts, edges, length, weight, fixed, 0.5, new, moved)
    i = np.concatenate([edges[:, 0], edges[:, 1]])
    j = np.concatenate([edges[:, 1], edges[:, 0]])
    ln, w = np.concatenate([length, length]), np.concatenate([weight, weight])
    ok = np.isfinite(ln) & (ln > 0)
    target = pts[j] + (pts[i] - pts[j]) / np.where(ok, ln, 1.0)[:, None]
    target[~ok] = pts[i[~ok]]
    count = np.bincount(i, minlength=n)
    wsum = np.bincount(i, w, minlength=n)
    sums = np.column_stack([np.bincount(i, w * target[:, k], minlength=n) for k in range(2)])
    avg = sums / np.maximum(wsum, 1e-300)[:, None]
    move = np.where(fixed[:, None] | (count[:, None] == 0), 0.0, 0.5 * (avg - pts))
    assert np.array_equal(new, pts + move)
    assert np.array_equal(moved, np.abs(move).max(axis=1) > 0)
    assert 300 < moved.sum() < n - 20 and not moved[fixed].any() and not moved[-20:].any()
