"""Metric tensors at arrays of points: intersection (simultaneous reduction), matrix
logarithm and exponential of 2 × 2 symmetric tensors.

Pure numpy on arrays of points; the compiled twins of the intersection are in
:mod:`curvimesh.kernels` (:func:`~curvimesh.kernels.intersect`,
:func:`~curvimesh.kernels.intersect_d`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "exp_components",
    "intersect",
    "intersect_components",
    "intersect_with_derivatives",
    "log_components",
    "nested",
]


def intersect(m1: NDArray, m2: NDArray) -> NDArray:
    """Metric intersection M1 ∩ M2 by simultaneous reduction, in closed form.

    With the generalised eigenpairs M2 v = s M1 v (s real, positive), and
    λ = vᵀ M1 v, the intersection keeps in each common direction the larger
    of the two lengths' inverses (Frey & George, "Mesh generation", §10.6):

        M = Σ_i max(1, s_i) / λ_i · (M1 v_i)(M1 v_i)ᵀ.

    As Σ_i (M1 v_i)(M1 v_i)ᵀ / λ_i = M1 (the v_i are M1-orthogonal), this is M2
    where both s_i ≥ 1 (M2 − M1 positive semidefinite), M1 where both are ≤ 1,
    and M1 + (s₊ − 1) / λ₊ · (M1 v₊)(M1 v₊)ᵀ where s₋ < 1 < s₊ (one null vector).

    Works on real or complex arrays of shape (n, 2, 2) (complex inputs are
    used for complex-step derivatives; branches are chosen on real parts).
    If the two metrics are nearly proportional (s1 ≈ s2 ≈ s) the result is max(1, s) M1.

    >>> a = np.array([[[1.0, 0.0], [0.0, 4.0]]]); b = np.array([[[4.0, 0.0], [0.0, 1.0]]])
    >>> intersect(a, b)[0].real.tolist()
    [[4.0, 0.0], [0.0, 4.0]]
    """
    a = (m1[:, 0, 0].copy(), m1[:, 0, 1].copy(), m1[:, 1, 1].copy())
    b = (m2[:, 0, 0].copy(), m2[:, 0, 1].copy(), m2[:, 1, 1].copy())
    c11, c12, c22 = intersect_components(a, b)
    out = np.empty(m1.shape, dtype=c11.dtype)
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = c11, c12, c12, c22
    return out


def nested(a: tuple, b: tuple) -> tuple[NDArray, NDArray]:
    """Rows where M2 contains M1 (M2 − M1 positive semidefinite) and where M1 contains
    M2 (negative semidefinite), decided on real parts by det(M2 − M1) ≥ 0 and the
    sign of its trace (as :func:`curvimesh.kernels._nested`)."""
    d11 = b[0].real - a[0].real
    d12 = b[1].real - a[1].real
    d22 = b[2].real - a[2].real
    semi = d11 * d22 - d12 * d12 >= 0.0
    up = d11 + d22 >= 0.0
    return semi & up, semi & ~up


def intersect_components(a: tuple, b: tuple) -> tuple[NDArray, NDArray, NDArray]:
    """:func:`intersect` on components: a = (a11, a12, a22), b likewise, 1D arrays."""
    a11, a12, a22 = a
    b11, b12, b22 = b
    take_b, take_a = nested(a, b)
    # det(M2 - s M1) = qa s² + qb s + qc
    qa = a11 * a22 - a12 * a12
    qb = -(a11 * b22 + a22 * b11 - 2.0 * a12 * b12)
    qc = b11 * b22 - b12 * b12
    disc = qb * qb - 4.0 * qa * qc
    # s1 ≈ s2 (M2 ≈ s M1): the eigenvectors are ill-conditioned, and rounding
    # makes disc ~1e-16 qb² of either sign; the result is max(1, s) M1 there
    degenerate = disc.real <= 1e-10 * (qb.real * qb.real)
    whole = take_a | take_b | degenerate
    inv2qa = 0.5 / qa
    s = (np.sqrt(np.where(whole, 1.0, disc)) - qb) * inv2qa  # s₊ (qa > 0)
    # null vector of C = M2 - s M1 (symmetric, singular)
    c11, c12, c22 = b11 - s * a11, b12 - s * a12, b22 - s * a22
    use_first = np.abs(c11.real) >= np.abs(c22.real)
    v1 = np.where(use_first, -c12, c22)
    v2 = np.where(use_first, c11, -c12)
    w1 = a11 * v1 + a12 * v2  # M1 v
    w2 = a12 * v1 + a22 * v2
    f = (s - 1.0) / np.where(whole, 1.0, v1 * w1 + v2 * w2)
    fw1 = f * w1
    o11, o12, o22 = a11 + fw1 * w1, a12 + fw1 * w2, a22 + f * w2 * w2
    if degenerate.any():
        s0 = -qb * inv2qa
        big = np.where(s0.real > 1.0, s0, 1.0)
        o11 = np.where(degenerate, big * a11, o11)
        o12 = np.where(degenerate, big * a12, o12)
        o22 = np.where(degenerate, big * a22, o22)
    o11 = np.where(take_b, b11, np.where(take_a, a11, o11))
    o12 = np.where(take_b, b12, np.where(take_a, a12, o12))
    o22 = np.where(take_b, b22, np.where(take_a, a22, o22))
    return o11, o12, o22


def intersect_with_derivatives(a: tuple, da: list, b: tuple, db: list) -> tuple[tuple, list]:
    """Intersection of components a, b and its derivatives, by the complex-step method.

    ``a`` = (a11, a12, a22) and ``da[k]`` its derivatives along x_k (likewise
    b, db). The intersection is not smooth where the choice of max(1, s_i)
    switches or where s1 = s2; everywhere else it is an analytic function of
    (M1, M2), so its directional derivative along (∂M1/∂x_k, ∂M2/∂x_k) is
    Im I(M1 + i h ∂M1, M2 + i h ∂M2) / h exactly (to rounding) with h = 1e-30
    (Squire & Trapp 1998). Where it is not smooth this gives the derivative
    of the branch selected at the point, a one-sided derivative, which is
    what a geodesic integrator stepping across the kink needs. The real part
    of a complex step is the value itself (h² is far below rounding).

    The reference for :func:`curvimesh.kernels.intersect_d`, which computes the
    same derivatives on the compiled path in forward mode.
    """
    h = 1e-30
    out = []
    for k in range(2):
        z = intersect_components(
            tuple(ai + 1j * h * di for ai, di in zip(a, da[k], strict=True)),
            tuple(bi + 1j * h * di for bi, di in zip(b, db[k], strict=True)),
        )
        out.append(tuple(zi.imag / h for zi in z))
    return tuple(zi.real for zi in z), out


def log_components(g11: NDArray, g12: NDArray, g22: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Matrix logarithm L of SPD tensors (g11, g12, g22), as (L11, L12, L22).

    With m = (g11 + g22)/2, d = (g11 − g22)/2, r = hypot(d, g12) the eigenvalues
    are λ± = m ± r, and log g = ½ log(λ₊λ₋) I + k (g − m I) with
    k = log(λ₊/λ₋)/(2r) = artanh(r/m)/r (1/m at r = 0; artanh below r/m = 1/2,
    the difference of the logarithms above); λ₋ is taken as
    det g / λ₊, which keeps its digits at high anisotropy.

    >>> [float(v[0]) for v in log_components(np.array([np.e]), np.array([0.0]), np.array([1.0]))]
    [1.0, 0.0, 0.0]
    """
    m = 0.5 * (g11 + g22)
    d = 0.5 * (g11 - g22)
    r = np.hypot(d, g12)
    big = m + r
    log_big = np.log(big)
    log_small = np.log((g11 * g22 - g12 * g12) / big)
    mean = 0.5 * (log_big + log_small)
    # half the log of the eigenvalue ratio: artanh(r/m) near isotropy, where the
    # difference of the logs cancels; that difference where artanh is ill-conditioned
    ratio = r / m
    half = np.where(ratio < 0.5, np.arctanh(np.minimum(ratio, 0.5)), 0.5 * (log_big - log_small))
    k = np.divide(half, r, out=1.0 / m, where=ratio > 1e-8)
    return mean + k * d, k * g12, mean - k * d


def exp_components(l11: NDArray, l12: NDArray, l22: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Matrix exponential of symmetric tensors (L11, L12, L22), SPD, as (g11, g12, g22).

    With m = (L11 + L22)/2, d = (L11 − L22)/2, r = hypot(d, L12):
    exp L = e^m (cosh r I + sinh(r)/r (L − m I)) (sinh(r)/r = 1 for r <= 1e-8).
    The inverse of :func:`log_components`; the scalar twin is
    :func:`curvimesh.kernels.exp_tensor`.

    >>> [round(float(v[0]), 12) for v in exp_components(*log_components(
    ...     np.array([5.0]), np.array([2.0]), np.array([1.0])))]
    [5.0, 2.0, 1.0]
    """
    m = 0.5 * (l11 + l22)
    d = 0.5 * (l11 - l22)
    r = np.hypot(d, l12)
    e = np.exp(m)
    c = e * np.cosh(r)
    s = e * np.divide(np.sinh(r), r, out=np.ones_like(r), where=r > 1e-8)
    return c + s * d, s * l12, c - s * d
