"""Tests of curvimesh.bezier: Jacobian of P2 triangles in Bezier form, validity.

The fast vectorised functions are judged by a slow, obvious, per-triangle
reference written here in plain Python with exact rational arithmetic
(`fractions.Fraction`): the P2 map is expanded into monomials, ``J`` is formed
by polynomial multiplication, and its minimum over the triangle is found by
enumerating the critical points of ``J`` restricted to each face (corners,
edges, interior). None of the module's Bezier machinery is used there.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from curvimesh import bezier

# Reference coordinates of the six nodes, Gmsh triangle6 order, written out
# independently of the module.
REF = np.array([[0, 0], [1, 0], [0, 1], [0.5, 0], [0.5, 0.5], [0, 0.5]], dtype=float)
EDGE_CORNERS = ((0, 1), (1, 2), (2, 0))

# Hand-picked P2 triangles on the reference corners (edge nodes given).
# Sufficient test fails (b_01 = -0.12) but min J = 0.12 > 0 on edge 01.
VALID_NOT_SUFFICIENT = np.vstack([REF[:3], [[0.3, 0.2], [0.9, 0.3], [0.0, 0.5]]])
# J > 0 at all six nodes, min J = -0.2 at (u, v) = (0.25, 0.75) on edge 12.
INVALID_ON_EDGE = np.vstack([REF[:3], [[1.0, -0.5], [0.3, 0.3], [0.0, 0.5]]])
# J > 0 on the whole boundary, min J = -1/16 inside.
INVALID_INSIDE = np.vstack([REF[:3], [[0.0, -0.1], [0.9, 0.9], [-0.1, 0.0]]])


# ---------------------------------------------------------------------------
# Slow, obvious reference (plain Python, exact rationals, one triangle at a time)
# ---------------------------------------------------------------------------

Poly = dict[tuple[int, int], Fraction]  # {(a, b): c} for c u^a v^b


def poly_add(*polys: Poly) -> Poly:
    out: Poly = {}
    for p in polys:
        for key, c in p.items():
            out[key] = out.get(key, Fraction(0)) + c
    return out


def poly_scale(p: Poly, s: Fraction) -> Poly:
    return {key: s * c for key, c in p.items()}


def poly_mul(p: Poly, q: Poly) -> Poly:
    out: Poly = {}
    for (a1, b1), c1 in p.items():
        for (a2, b2), c2 in q.items():
            key = (a1 + a2, b1 + b2)
            out[key] = out.get(key, Fraction(0)) + c1 * c2
    return out


def poly_diff(p: Poly, var: int) -> Poly:
    out: Poly = {}
    for (a, b), c in p.items():
        power = (a, b)[var]
        if power:
            key = (a - 1, b) if var == 0 else (a, b - 1)
            out[key] = out.get(key, Fraction(0)) + power * c
    return out


def poly_eval(p: Poly, u: Fraction, v: Fraction) -> Fraction:
    return sum((c * u**a * v**b for (a, b), c in p.items()), Fraction(0))


def reference_jacobian_poly(tri: np.ndarray) -> Poly:
    """J(u, v) of one P2 triangle (6, 2) as an exact polynomial."""
    one = Fraction(1)
    lam = [{(0, 0): one, (1, 0): -one, (0, 1): -one}, {(1, 0): one}, {(0, 1): one}]
    shapes = [poly_mul(l, poly_add(poly_scale(l, Fraction(2)), {(0, 0): -one})) for l in lam]
    shapes += [poly_scale(poly_mul(lam[i], lam[j]), Fraction(4)) for i, j in EDGE_CORNERS]
    x = poly_add(*[poly_scale(n, Fraction(float(tri[a, 0]))) for a, n in enumerate(shapes)])
    y = poly_add(*[poly_scale(n, Fraction(float(tri[a, 1]))) for a, n in enumerate(shapes)])
    xu, xv, yu, yv = poly_diff(x, 0), poly_diff(x, 1), poly_diff(y, 0), poly_diff(y, 1)
    return poly_add(poly_mul(xu, yv), poly_scale(poly_mul(xv, yu), Fraction(-1)))


def reference_min(jac: Poly) -> Fraction:
    """Exact min of a quadratic over the closed triangle by face enumeration.

    Every critical point of J restricted to a face is a point of the triangle,
    so adding maxima or saddles never spoils the minimum; the minimiser is a
    critical point of the face whose relative interior holds it (or, if that
    restriction is degenerate, J is constant along a line to a lower face).
    """
    corners = [(Fraction(0), Fraction(0)), (Fraction(1), Fraction(0)), (Fraction(0), Fraction(1))]
    values = [poly_eval(jac, *c) for c in corners]
    for i, j in EDGE_CORNERS:
        (u0, v0), (u1, v1) = corners[i], corners[j]

        def along(t: Fraction, u0=u0, v0=v0, u1=u1, v1=v1) -> Fraction:
            return poly_eval(jac, u0 + t * (u1 - u0), v0 + t * (v1 - v0))

        g0, gh, g1 = along(Fraction(0)), along(Fraction(1, 2)), along(Fraction(1))
        alpha = 2 * g0 - 4 * gh + 2 * g1  # g(t) = alpha t^2 + beta t + g0
        beta = g1 - g0 - alpha
        if alpha != 0:
            t = -beta / (2 * alpha)
            if 0 < t < 1:
                values.append(along(t))
    ju, jv = poly_diff(jac, 0), poly_diff(jac, 1)  # linear: c + cu u + cv v
    a1, a2, a3 = (ju.get(k, Fraction(0)) for k in ((0, 0), (1, 0), (0, 1)))
    b1, b2, b3 = (jv.get(k, Fraction(0)) for k in ((0, 0), (1, 0), (0, 1)))
    det = a2 * b3 - a3 * b2
    if det != 0:
        u = (a3 * b1 - a1 * b3) / det
        v = (a1 * b2 - a2 * b1) / det
        if u >= 0 and v >= 0 and u + v <= 1:
            values.append(poly_eval(jac, u, v))
    return min(values)


def bernstein_poly(coeffs: np.ndarray) -> Poly:
    """sum_k b_k B_k as an exact polynomial in (u, v), from one row of 6 coefficients."""
    one = Fraction(1)
    lam = [{(0, 0): one, (1, 0): -one, (0, 1): -one}, {(1, 0): one}, {(0, 1): one}]
    basis = [poly_mul(l, l) for l in lam]
    basis += [poly_scale(poly_mul(lam[i], lam[j]), Fraction(2)) for i, j in EDGE_CORNERS]
    return poly_add(
        *[poly_scale(bk, Fraction(float(c))) for bk, c in zip(basis, coeffs, strict=True)]
    )


def reference_check(nodes: np.ndarray) -> dict[str, list]:
    """Per-triangle loop: exact nodal J, the paper's sufficient test, exact min J."""
    out: dict[str, list] = {"nodal": [], "sufficient": [], "min": []}
    for tri in nodes:
        jac = reference_jacobian_poly(tri)
        nodal = [poly_eval(jac, Fraction(float(u)), Fraction(float(v))) for u, v in REF]
        # Paper section 4: J_i > 0 and 4 J_ij > J_i + J_j.
        sufficient = all(nodal[i] > 0 for i in range(3)) and all(
            4 * nodal[3 + k] > nodal[i] + nodal[j] for k, (i, j) in enumerate(EDGE_CORNERS)
        )
        out["nodal"].append(nodal)
        out["sufficient"].append(sufficient)
        out["min"].append(reference_min(jac))
    return out


def reference_subdivision_min(jac: Poly, depth: int) -> Fraction:
    """Least Bezier coefficient over the 4**depth midpoint sub-triangles, by plain
    recursion: on a sub-triangle, J is again quadratic, so its coefficients follow
    from its values at the sub-triangle's corners and edge midpoints."""

    def recurse(corners: list[tuple[Fraction, Fraction]], level: int) -> Fraction:
        mids = [
            ((corners[i][0] + corners[j][0]) / 2, (corners[i][1] + corners[j][1]) / 2)
            for i, j in EDGE_CORNERS
        ]
        if level == 0:
            jc = [poly_eval(jac, *c) for c in corners]
            jm = [poly_eval(jac, *c) for c in mids]
            coeffs = jc + [2 * jm[k] - (jc[i] + jc[j]) / 2 for k, (i, j) in enumerate(EDGE_CORNERS)]
            return min(coeffs)
        m01, m12, m20 = mids
        children = [
            [corners[0], m01, m20],
            [m01, corners[1], m12],
            [m20, m12, corners[2]],
            [m12, m20, m01],
        ]
        return min(recurse(child, level - 1) for child in children)

    zero, one = Fraction(0), Fraction(1)
    return recurse([(zero, zero), (one, zero), (zero, one)], depth)


# ---------------------------------------------------------------------------
# Generators and independent evaluators
# ---------------------------------------------------------------------------


def straight_triangles(rng: np.random.Generator, m: int) -> np.ndarray:
    """(m, 6, 2) random straight-sided P2 triangles (edge nodes at midpoints)."""
    corners = rng.uniform(-2.0, 2.0, size=(m, 3, 2))
    mids = [(corners[:, i] + corners[:, j]) / 2 for i, j in EDGE_CORNERS]
    return np.concatenate([corners, np.stack(mids, axis=1)], axis=1)


def curved_triangles(rng: np.random.Generator, m: int, amplitude: float = 0.6) -> np.ndarray:
    """(m, 6, 2) counter-clockwise P2 triangles whose edge nodes are moved off
    the midpoints by up to ``amplitude`` times the edge length; a mix of valid
    and invalid ones."""
    nodes = straight_triangles(rng, m)
    e1 = nodes[:, 1] - nodes[:, 0]
    e2 = nodes[:, 2] - nodes[:, 0]
    cw = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] < 0
    nodes[cw] = nodes[cw][:, [0, 2, 1, 5, 4, 3]]
    for k, (i, j) in enumerate(EDGE_CORNERS):
        length = np.linalg.norm(nodes[:, j] - nodes[:, i], axis=1)
        size = amplitude * rng.uniform(0.0, 1.0, size=m) * length
        nodes[:, 3 + k] += size[:, None] * rng.uniform(-1.0, 1.0, size=(m, 2))
    return nodes


def random_uv(rng: np.random.Generator, k: int) -> np.ndarray:
    """(k, 2) uniform random points of the reference triangle (reflection trick)."""
    uv = rng.uniform(0.0, 1.0, size=(k, 2))
    out = uv.sum(axis=1) > 1
    uv[out] = 1.0 - uv[out]
    return uv


def grid_uv(n: int) -> np.ndarray:
    """Structured grid of spacing 1/n on the closed reference triangle, with its boundary."""
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    keep = i + j <= n
    return np.column_stack([i[keep], j[keep]]) / n


def grid_min(nodes: np.ndarray, n: int) -> np.ndarray:
    """Brute-force min of J over grid_uv(n), in chunks of triangles to bound memory."""
    uv = grid_uv(n)
    return np.concatenate(
        [bezier.p2_jacobian(chunk, uv).min(axis=1) for chunk in np.array_split(nodes, 20)]
    )


def bernstein_eval(coeffs: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """sum_k b_k B_k(u, v) with B = (l0^2, l1^2, l2^2, 2 l0 l1, 2 l1 l2, 2 l2 l0); (m, k)."""
    l0, l1, l2 = 1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]
    basis = np.stack([l0**2, l1**2, l2**2, 2 * l0 * l1, 2 * l1 * l2, 2 * l2 * l0])
    return coeffs @ basis


def twice_area(nodes: np.ndarray) -> np.ndarray:
    e1 = nodes[:, 1] - nodes[:, 0]
    e2 = nodes[:, 2] - nodes[:, 0]
    return e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]


def roundoff(nodes: np.ndarray) -> np.ndarray:
    """Round-off allowance for J per triangle: 1e-12 times the squared extent of
    the nodes about corner 0 (J is a product of two differences of positions);
    for a skinny triangle this is much larger than 1e-12 * max|J|."""
    extent2 = np.sum((nodes - nodes[:, :1]) ** 2, axis=2).max(axis=1)
    return 1e-12 * extent2


def scale_of(nodes: np.ndarray) -> np.ndarray:
    """Scale of J per triangle: the largest |Bezier coefficient|."""
    return np.abs(bezier.jacobian_bezier(nodes)).max(axis=1)


# ---------------------------------------------------------------------------
# Shape functions and the map
# ---------------------------------------------------------------------------


def test_straight_map_is_affine() -> None:
    rng = np.random.default_rng(1)
    nodes = straight_triangles(rng, 20)
    uv = random_uv(rng, 50)
    expected = (
        nodes[:, None, 0]
        + uv[None, :, :1] * (nodes[:, None, 1] - nodes[:, None, 0])
        + uv[None, :, 1:] * (nodes[:, None, 2] - nodes[:, None, 0])
    )
    np.testing.assert_allclose(bezier.p2_map(nodes, uv), expected, rtol=0, atol=1e-13)


def test_map_interpolates_nodes() -> None:
    rng = np.random.default_rng(2)
    nodes = curved_triangles(rng, 20)
    np.testing.assert_allclose(bezier.p2_map(nodes, REF), nodes, rtol=0, atol=1e-14)


def test_jacobian_matches_finite_differences_of_map() -> None:
    rng = np.random.default_rng(3)
    nodes = curved_triangles(rng, 30)
    uv = random_uv(rng, 40) * 0.9 + 0.03  # keep the stencil inside the triangle
    h = 1e-6
    du, dv = np.array([h, 0.0]), np.array([0.0, h])
    xu = (bezier.p2_map(nodes, uv + du) - bezier.p2_map(nodes, uv - du)) / (2 * h)
    xv = (bezier.p2_map(nodes, uv + dv) - bezier.p2_map(nodes, uv - dv)) / (2 * h)
    fd = xu[..., 0] * xv[..., 1] - xv[..., 0] * xu[..., 1]
    # The map is quadratic, so central differences are exact up to round-off ~ eps / h.
    np.testing.assert_allclose(bezier.p2_jacobian(nodes, uv), fd, rtol=0, atol=1e-8)


def test_bad_shapes_rejected() -> None:
    with pytest.raises(ValueError, match=r"\(m, 6, 2\)"):
        bezier.jacobian_bezier(np.zeros((6, 2)))
    with pytest.raises(ValueError, match=r"\(k, 2\)"):
        bezier.p2_map(np.zeros((1, 6, 2)), np.zeros(2))
    with pytest.raises(ValueError, match="finite"):
        bezier.min_jacobian(np.full((1, 6, 2), np.nan))
    with pytest.raises(ValueError, match="depth"):
        bezier.min_jacobian_subdivision(np.zeros((1, 6, 2)), depth=-1)
    with pytest.raises(ValueError, match="rtol"):
        bezier.valid_exact(np.zeros((1, 6, 2)), rtol=-1.0)


def test_empty_input() -> None:
    empty = np.zeros((0, 6, 2))
    assert bezier.jacobian_bezier(empty).shape == (0, 6)
    assert bezier.min_jacobian(empty).shape == (0,)
    assert bezier.valid_exact(empty).shape == (0,)
    assert bezier.valid_sufficient(empty).shape == (0,)
    assert bezier.min_jacobian_subdivision(empty, depth=2).shape == (0,)
    assert bezier.scaled_jacobian_min(empty).shape == (0,)


# ---------------------------------------------------------------------------
# Analytic oracle: straight-sided triangles
# ---------------------------------------------------------------------------


def test_straight_triangle_coefficients_equal_twice_area() -> None:
    rng = np.random.default_rng(4)
    nodes = straight_triangles(rng, 200)  # both orientations
    area2 = twice_area(nodes)
    assert (area2 > 0).any() and (area2 < 0).any()
    b = bezier.jacobian_bezier(nodes)
    np.testing.assert_allclose(b, np.repeat(area2[:, None], 6, axis=1), rtol=0, atol=1e-12)
    np.testing.assert_allclose(bezier.jacobian_at_nodes(nodes), b, rtol=0, atol=1e-12)
    np.testing.assert_allclose(bezier.min_jacobian(nodes), area2, rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        bezier.min_jacobian_subdivision(nodes, depth=3), area2, rtol=0, atol=1e-12
    )
    np.testing.assert_allclose(bezier.scaled_jacobian_min(nodes), 1.0, rtol=1e-10)
    np.testing.assert_array_equal(bezier.valid_sufficient(nodes), area2 > 0)
    np.testing.assert_array_equal(bezier.valid_exact(nodes), area2 > 0)


# ---------------------------------------------------------------------------
# Curved triangles: Bezier form, exact minimum, validity
# ---------------------------------------------------------------------------


def test_bezier_form_reproduces_jacobian() -> None:
    rng = np.random.default_rng(5)
    nodes = curved_triangles(rng, 300)
    uv = random_uv(rng, 500)
    b = bezier.jacobian_bezier(nodes)
    np.testing.assert_allclose(
        bernstein_eval(b, uv), bezier.p2_jacobian(nodes, uv), rtol=0, atol=1e-10
    )
    # Corner coefficients are the corner values; at the edge midpoints the
    # Bernstein sum gives back the nodal values.
    jn = bezier.jacobian_at_nodes(nodes)
    np.testing.assert_array_equal(b[:, :3], jn[:, :3])
    np.testing.assert_allclose(bernstein_eval(b, REF), jn, rtol=0, atol=1e-12)


def test_vectorised_functions_match_slow_reference() -> None:
    rng = np.random.default_rng(6)
    nodes = np.concatenate(
        [
            curved_triangles(rng, 150),
            curved_triangles(rng, 50, amplitude=1.5),
            VALID_NOT_SUFFICIENT[None],
            INVALID_ON_EDGE[None],
            INVALID_INSIDE[None],
        ]
    )
    ref = reference_check(nodes)
    nodal = np.array([[float(c) for c in row] for row in ref["nodal"]])
    exact_min = np.array([float(c) for c in ref["min"]])
    tol = roundoff(nodes)
    assert np.all(np.abs(bezier.jacobian_at_nodes(nodes) - nodal) <= tol[:, None])
    assert np.all(np.abs(bezier.min_jacobian(nodes) - exact_min) <= tol)
    clear = np.abs(bezier.jacobian_bezier(nodes)).min(axis=1) > tol  # no coefficient ~ 0
    np.testing.assert_array_equal(
        bezier.valid_sufficient(nodes)[clear], np.array(ref["sufficient"])[clear]
    )
    # valid_exact means min J > rtol * max|b| (rtol = 1e-12), up to round-off.
    threshold = 1e-12 * scale_of(nodes)
    decided = np.abs(exact_min - threshold) > tol
    np.testing.assert_array_equal(
        bezier.valid_exact(nodes)[decided], (exact_min > threshold)[decided]
    )
    assert clear.mean() > 0.95 and decided.mean() > 0.95
    # The mixture exercises every branch of the decision.
    valid = exact_min > 0
    sufficient = np.array(ref["sufficient"])
    assert valid.any() and (~valid).any() and (valid & ~sufficient).any()


def test_bezier_min_on_arbitrary_quadratics() -> None:
    """The kernel on coefficient vectors of every kind, not only Jacobians."""
    rng = np.random.default_rng(15)
    m = 300
    general = rng.normal(size=(m, 6))  # definite, indefinite, negative Hessians
    # Linear J = a.l: b_i = a_i, b_ij = (a_i + a_j) / 2; min = min_i a_i.
    a = rng.normal(size=(m, 3))
    linear = np.column_stack([a] + [(a[:, i] + a[:, j]) / 2 for i, j in EDGE_CORNERS])
    # Singular PSD Hessian: J = (w.l)^2 + c, i.e. B = w w^T + c 1 1^T. The minimum
    # is c, on a whole segment, when w changes sign, else c + min_i w_i^2.
    w = rng.normal(size=(m, 3))
    c = rng.normal(size=m)
    rank1 = np.column_stack([w**2 + c[:, None]] + [w[:, i] * w[:, j] + c for i, j in EDGE_CORNERS])
    mixed = (w.min(axis=1) < 0) & (w.max(axis=1) > 0)
    rank1_min = np.where(mixed, c, c + (w**2).min(axis=1))

    np.testing.assert_allclose(bezier.bezier_min(linear), a.min(axis=1), rtol=0, atol=1e-14)
    tol = 1e-12 * np.abs(rank1).max(axis=1)
    assert np.all(np.abs(bezier.bezier_min(rank1) - rank1_min) <= tol)

    coeffs = np.concatenate([general, linear, rank1])
    exact = np.array([float(reference_min(bernstein_poly(row))) for row in coeffs])
    tol = 1e-12 * np.abs(coeffs).max(axis=1)
    assert np.all(np.abs(bezier.bezier_min(coeffs) - exact) <= tol)
    assert np.all(bezier.bezier_min(coeffs) <= bernstein_eval(coeffs, grid_uv(50)).min(axis=1))


def test_min_jacobian_bounds_sampled_values() -> None:
    rng = np.random.default_rng(7)
    nodes = curved_triangles(rng, 200)
    scale = scale_of(nodes)
    tol = roundoff(nodes)
    jmin = bezier.min_jacobian(nodes)

    samples = bezier.p2_jacobian(nodes, random_uv(rng, 2000))
    assert np.all(jmin <= samples.min(axis=1) + tol)

    # Grid of spacing h with the boundary: the nearest grid point to the true
    # minimiser is within h/sqrt(2) (same face), where the gradient along the
    # face vanishes, so grid min - true min <= ||A|| h^2 / 2 <= 4 h^2 max|b|
    # (the Hessian entries are sums of at most 4 coefficients).
    n = 400
    brute = grid_min(nodes, n)
    assert np.all(jmin <= brute + tol)
    assert np.all(jmin >= brute - 4.0 * scale / n**2)


def test_valid_exact_agrees_with_brute_force() -> None:
    rng = np.random.default_rng(8)
    nodes = curved_triangles(rng, 1000)
    scale = scale_of(nodes)
    n = 200
    brute = grid_min(nodes, n)
    # Skip triangles whose brute-force decision is within the grid error of 0.
    decided = np.abs(brute) > 4.0 * scale / n**2
    exact = bezier.valid_exact(nodes)
    sufficient = bezier.valid_sufficient(nodes)
    np.testing.assert_array_equal(exact[decided], (brute > 0)[decided])
    assert np.all(exact[sufficient])
    assert decided.mean() > 0.95
    assert exact.any() and (~exact).any() and (exact & ~sufficient).any()


def test_valid_sufficient_is_the_paper_condition() -> None:
    rng = np.random.default_rng(9)
    nodes = curved_triangles(rng, 500)
    jn = bezier.jacobian_at_nodes(nodes)
    paper = np.all(jn[:, :3] > 0, axis=1)
    for k, (i, j) in enumerate(EDGE_CORNERS):
        paper &= 4 * jn[:, 3 + k] > jn[:, i] + jn[:, j]
    margin = np.abs(bezier.jacobian_bezier(nodes)).min(axis=1) > roundoff(nodes)
    np.testing.assert_array_equal(bezier.valid_sufficient(nodes)[margin], paper[margin])


# ---------------------------------------------------------------------------
# Hand-constructed cases
# ---------------------------------------------------------------------------


def test_valid_but_not_sufficient() -> None:
    tri = VALID_NOT_SUFFICIENT[None]
    b = bezier.jacobian_bezier(tri)
    assert b[0, 3] < 0  # 4 J_01 < J_0 + J_1
    assert not bezier.valid_sufficient(tri)[0]
    assert bezier.valid_exact(tri)[0]
    exact = float(reference_check(tri)["min"][0])
    assert exact == pytest.approx(0.12, abs=1e-12)
    assert bezier.min_jacobian(tri)[0] == pytest.approx(exact, abs=1e-12)
    assert bezier.p2_jacobian(tri, grid_uv(200)).min() > 0


def test_valid_but_not_sufficient_cases_exist() -> None:
    rng = np.random.default_rng(10)
    found = []
    for _ in range(20):  # seeded search, in batches
        nodes = curved_triangles(rng, 500)
        hit = ~bezier.valid_sufficient(nodes) & bezier.valid_exact(nodes)
        found.extend(nodes[hit])
        if len(found) >= 20:
            break
    assert len(found) >= 20
    found_arr = np.array(found[:20])
    ref = reference_check(found_arr)
    assert not any(ref["sufficient"])
    assert all(m > 0 for m in ref["min"])


@pytest.mark.parametrize("tri", [INVALID_ON_EDGE, INVALID_INSIDE], ids=["edge", "inside"])
def test_invalid_despite_positive_nodal_jacobians(tri: np.ndarray) -> None:
    nodes = tri[None]
    assert np.all(bezier.jacobian_at_nodes(nodes) > 0)
    assert not bezier.valid_sufficient(nodes)[0]
    assert not bezier.valid_exact(nodes)[0]
    exact = float(reference_check(nodes)["min"][0])
    assert exact < 0
    assert bezier.min_jacobian(nodes)[0] == pytest.approx(exact, abs=1e-12)
    assert bezier.p2_jacobian(nodes, grid_uv(200)).min() < 0


def test_invalid_edge_case_minimum_location() -> None:
    nodes = INVALID_ON_EDGE[None]
    assert bezier.min_jacobian(nodes)[0] == pytest.approx(-0.2, abs=1e-12)
    assert bezier.p2_jacobian(nodes, [[0.25, 0.75]])[0, 0] == pytest.approx(-0.2, abs=1e-12)


def test_invalid_inside_case_positive_on_boundary() -> None:
    nodes = INVALID_INSIDE[None]
    t = np.linspace(0.0, 1.0, 1001)
    boundary = np.concatenate(
        [np.column_stack([t, 0 * t]), np.column_stack([1 - t, t]), np.column_stack([0 * t, t])]
    )
    assert bezier.p2_jacobian(nodes, boundary).min() > 0.05
    assert bezier.min_jacobian(nodes)[0] == pytest.approx(-1 / 16, abs=1e-12)


def test_degenerate_corner_is_invalid() -> None:
    # Edge node of 01 at (0.5, 0.25): J = 1 - u, zero at corner 1 and positive elsewhere.
    tri = np.vstack([REF[:3], [[0.5, 0.25], [0.5, 0.5], [0.0, 0.5]]])
    rng = np.random.default_rng(11)
    theta = rng.uniform(0, 2 * np.pi, size=50)
    scale = rng.uniform(0.01, 100.0, size=50)
    rot = np.stack([np.cos(theta), -np.sin(theta), np.sin(theta), np.cos(theta)], axis=1)
    rot = (scale[:, None] * rot).reshape(-1, 2, 2)
    shift = scale[:, None, None] * rng.uniform(-10, 10, size=(50, 1, 2))
    nodes = np.einsum("mij,aj->mai", rot, tri) + shift
    jmin = bezier.min_jacobian(nodes)
    assert np.all(np.abs(jmin) <= 1e-12 * scale_of(nodes))  # zero up to round-off
    assert not bezier.valid_exact(nodes).any()


# ---------------------------------------------------------------------------
# Subdivision
# ---------------------------------------------------------------------------


def test_subdivision_matches_slow_recursion() -> None:
    rng = np.random.default_rng(12)
    nodes = np.concatenate([curved_triangles(rng, 12), INVALID_INSIDE[None]])
    tol = roundoff(nodes)
    for depth in range(4):
        slow = np.array(
            [float(reference_subdivision_min(reference_jacobian_poly(t), depth)) for t in nodes]
        )
        fast = bezier.min_jacobian_subdivision(nodes, depth=depth)
        assert np.all(np.abs(fast - slow) <= tol)


def test_subdivision_lower_bound_converges_quadratically() -> None:
    rng = np.random.default_rng(13)
    nodes = curved_triangles(rng, 300)
    exact = bezier.min_jacobian(nodes)
    scale = scale_of(nodes)
    tol = roundoff(nodes)
    depths = np.arange(11)
    bounds = np.stack([bezier.min_jacobian_subdivision(nodes, depth=d) for d in depths])
    # A lower bound, nondecreasing with depth (children's coefficients are
    # convex combinations of the parent's), equal to min_k b_k at depth 0.
    assert np.all(bounds <= exact + tol)
    assert np.all(np.diff(bounds, axis=0) >= -tol)
    np.testing.assert_array_equal(bounds[0], bezier.jacobian_bezier(nodes).min(axis=1))
    # Error bound from the blossom: 1.5 * 4^-depth * max|b| (see the docstring).
    err = (exact - bounds) / scale
    assert np.all(err <= 1.5 * 0.25 ** depths[:, None] + tol / scale)
    # And the order is exactly 2 (error ratio about 4 per level), not better:
    # fit log2(error) against depth on triangles whose error does not vanish
    # early (a minimiser at a dyadic point is found exactly).
    alive = np.all(err[2:] > 1e-12, axis=0)
    assert alive.sum() >= 50
    envelope = err[2:, alive].max(axis=1)
    assert np.polyfit(depths[2:], np.log2(envelope), 1)[0] == pytest.approx(-2.0, abs=0.1)
    slopes = np.polyfit(depths[2:], np.log2(err[2:, alive]), 1)[0]
    assert np.median(slopes) == pytest.approx(-2.0, abs=0.1)


# ---------------------------------------------------------------------------
# Scaled Jacobian
# ---------------------------------------------------------------------------


def test_scaled_jacobian_min() -> None:
    rng = np.random.default_rng(14)
    nodes = curved_triangles(rng, 100)
    scaled = bezier.scaled_jacobian_min(nodes)
    np.testing.assert_allclose(scaled, bezier.min_jacobian(nodes) / twice_area(nodes), rtol=1e-12)
    # Invariant under similarities with positive determinant; min J scales by s^2.
    s, c = 3.0 * np.sin(0.7), 3.0 * np.cos(0.7)
    moved = nodes @ np.array([[c, s], [-s, c]]) + np.array([5.0, -2.0])
    np.testing.assert_allclose(bezier.scaled_jacobian_min(moved), scaled, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(
        bezier.min_jacobian(moved), 9.0 * bezier.min_jacobian(nodes), rtol=1e-9, atol=1e-12
    )
    # Collinear corners: the straight Jacobian vanishes, the measure is -inf.
    flat = np.array([[[0, 0], [2, 0], [1, 0], [1, -0.5], [1.5, 0.5], [0.5, 0.5]]], dtype=float)
    assert bezier.scaled_jacobian_min(flat)[0] == -np.inf
