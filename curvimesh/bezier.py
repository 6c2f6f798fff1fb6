"""Jacobian of P2 triangles in Bezier form, and the validity of curved triangles.

A P2 triangle has six nodes in Gmsh ``triangle6`` order, shape ``(m, 6, 2)``:
the corners 0, 1, 2, then the nodes of the edges 01, 12, 20. With the reference
coordinates ``(u, v)`` (``u, v >= 0``, ``u + v <= 1``) and the barycentrics

    l0 = 1 - u - v,   l1 = u,   l2 = v,

the map is ``x(u, v) = sum_i N_i(u, v) x_i`` with the P2 Lagrange functions

    N_i  = l_i (2 l_i - 1)      (corner i),
    N_ij = 4 l_i l_j            (edge ij).

Its Jacobian determinant ``J = det(dx/d(u, v))`` is a polynomial of degree 2,
so it is *exactly* a Bezier triangle of degree 2:

    J = sum_i b_i l_i^2 + sum_{i<j} 2 b_ij l_i l_j = l^T B l,

with the symmetric 3x3 matrix ``B`` holding ``b_i`` on the diagonal and
``b_ij`` off it. Evaluating at the corners and edge midpoints gives

    b_i  = J_i,
    b_ij = 2 J_ij - (J_i + J_j) / 2,

(Johnen, Remacle, Geuzaine 2013, "Geometrical validity of curvilinear finite
elements"). The Bernstein functions are non-negative and sum to one, so
``min_k b_k <= J`` everywhere (convex hull property): all six coefficients
positive, i.e. ``J_i > 0`` and ``4 J_ij > J_i + J_j``, is the sufficient validity
test used by Zhang, Johnen, Remacle, "Curvilinear mesh adaptation", section 4.
:func:`min_jacobian` computes the exact minimum of the quadratic in closed
form, which decides validity without subdivision.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "EDGES",
    "REFERENCE_NODES",
    "bezier_min",
    "jacobian_at_nodes",
    "jacobian_bezier",
    "min_jacobian",
    "min_jacobian_subdivision",
    "p2_jacobian",
    "p2_map",
    "p2_shape",
    "p2_shape_grad",
    "scaled_jacobian_min",
    "valid_exact",
    "valid_sufficient",
]

#: Reference coordinates ``(u, v)`` of the six nodes, shape ``(6, 2)``.
REFERENCE_NODES: NDArray[np.float64] = np.array(
    [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.5, 0.0], [0.5, 0.5], [0.0, 0.5]]
)

#: Local corners ``(i, j)`` of edge ``k``; the node of edge ``k`` is ``3 + k``.
EDGES: tuple[tuple[int, int], ...] = ((0, 1), (1, 2), (2, 0))

#: Default relative tolerance of :func:`valid_exact`.
VALID_RTOL = 1e-12

# Midpoint subdivision of the reference triangle into 4. Column k of each 3x3
# matrix holds the barycentrics (in the parent) of corner k of the child.
#
#         2
#         | \
#        20 -12          children: (0, 01, 20), (01, 1, 12),
#         | \ | \                  (20, 12, 2), (12, 20, 01)
#         0 - 01 - 1
_SUBDIVISION: NDArray[np.float64] = np.array(
    [
        [[1.0, 0.5, 0.5], [0.0, 0.5, 0.0], [0.0, 0.0, 0.5]],
        [[0.5, 0.0, 0.0], [0.5, 1.0, 0.5], [0.0, 0.0, 0.5]],
        [[0.5, 0.0, 0.0], [0.0, 0.5, 0.0], [0.5, 0.5, 1.0]],
        [[0.0, 0.5, 0.5], [0.5, 0.0, 0.5], [0.5, 0.5, 0.0]],
    ]
)


def _as_nodes(nodes: ArrayLike) -> NDArray[np.float64]:
    """Return ``nodes`` as a finite float array of shape ``(m, 6, 2)`` or raise ValueError."""
    arr = np.asarray(nodes, dtype=float)
    if arr.ndim != 3 or arr.shape[1:] != (6, 2):
        raise ValueError(f"P2 triangle nodes must have shape (m, 6, 2), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError("P2 triangle nodes must be finite")
    return arr


def _as_coeffs(coeffs: ArrayLike) -> NDArray[np.float64]:
    """Return ``coeffs`` as a float array of shape ``(m, 6)`` or raise ValueError."""
    arr = np.asarray(coeffs, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 6:
        raise ValueError(f"Bezier coefficients must have shape (m, 6), got {arr.shape}")
    return arr


def _as_uv(uv: ArrayLike) -> NDArray[np.float64]:
    """Return ``uv`` as a float array of shape ``(k, 2)`` or raise ValueError."""
    arr = np.asarray(uv, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"reference points must have shape (k, 2), got {arr.shape}")
    return arr


def _barycentrics(uv: NDArray[np.float64]) -> NDArray[np.float64]:
    """Barycentrics ``(l0, l1, l2) = (1 - u - v, u, v)``, shape ``(k, 3)``."""
    return np.column_stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]])


def p2_shape(uv: ArrayLike) -> NDArray[np.float64]:
    """P2 Lagrange shape functions at reference points.

    ``N_i = l_i (2 l_i - 1)`` for the corners and ``N_ij = 4 l_i l_j`` for the
    edges 01, 12, 20, with ``l = (1 - u - v, u, v)``.

    Parameters
    ----------
    uv : (k, 2) reference coordinates.

    Returns
    -------
    (k, 6) values, columns in node order; each row sums to one.

    >>> np.allclose(p2_shape(REFERENCE_NODES), np.eye(6))
    True
    """
    lam = _barycentrics(_as_uv(uv))
    corner = lam * (2.0 * lam - 1.0)
    edge = np.column_stack([4.0 * lam[:, i] * lam[:, j] for i, j in EDGES])
    return np.hstack([corner, edge])


def p2_shape_grad(uv: ArrayLike) -> NDArray[np.float64]:
    """Gradients of the P2 shape functions with respect to ``(u, v)``.

    With ``dl/du = (-1, 1, 0)`` and ``dl/dv = (-1, 0, 1)``, the chain rule gives
    ``dN_i = (4 l_i - 1) dl_i`` and ``dN_ij = 4 (l_i dl_j + l_j dl_i)``.

    Parameters
    ----------
    uv : (k, 2) reference coordinates.

    Returns
    -------
    (k, 6, 2) array ``G[p, a, d] = dN_a / d(u, v)_d`` at point ``p``.

    >>> p2_shape_grad([[0.0, 0.0]])[0, [0, 3, 5]]
    array([[-3., -3.],
           [ 4.,  0.],
           [ 0.,  4.]])
    >>> bool(np.abs(p2_shape_grad([[0.2, 0.3]]).sum(axis=1)).max() < 1e-15)
    True
    """
    lam = _barycentrics(_as_uv(uv))
    dlam = np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]])  # (3, 2): dl_i / d(u, v)
    corner = (4.0 * lam - 1.0)[:, :, None] * dlam[None, :, :]
    edge = np.stack(
        [4.0 * (lam[:, i, None] * dlam[j] + lam[:, j, None] * dlam[i]) for i, j in EDGES],
        axis=1,
    )
    return np.concatenate([corner, edge], axis=1)


def p2_map(nodes: ArrayLike, uv: ArrayLike) -> NDArray[np.float64]:
    """Images ``x(u, v) = sum_a N_a(u, v) x_a`` of reference points.

    Parameters
    ----------
    nodes : (m, 6, 2) P2 triangles, Gmsh order.
    uv : (k, 2) reference coordinates.

    Returns
    -------
    (m, k, 2) physical coordinates.

    >>> tri = np.array([[[0, 0], [2, 0], [0, 2], [1, 0], [1, 1], [0, 1]]])
    >>> p2_map(tri, [[0.25, 0.5]])
    array([[[0.5, 1. ]]])
    """
    x = _as_nodes(nodes)
    return p2_shape(uv) @ x


def p2_jacobian(nodes: ArrayLike, uv: ArrayLike) -> NDArray[np.float64]:
    """Jacobian determinant ``J = det(dx/d(u, v)) = x_u y_v - x_v y_u`` at reference points.

    Parameters
    ----------
    nodes : (m, 6, 2) P2 triangles, Gmsh order.
    uv : (k, 2) reference coordinates.

    Returns
    -------
    (m, k) values of ``J``; positive where the map preserves orientation.

    >>> tri = np.array([[[0, 0], [2, 0], [0, 2], [1, 0], [1, 1], [0, 1]]])
    >>> p2_jacobian(tri, [[0.2, 0.3], [1.0, 0.0]])
    array([[4., 4.]])
    """
    x = _as_nodes(nodes)
    # The gradients sum to zero over the nodes: work relative to corner 0, so
    # that round-off scales with the element size, not with |x|.
    local = x - x[:, :1]
    grad = p2_shape_grad(uv)
    xu = grad[:, :, 0] @ local  # (m, k, 2): dx/du
    xv = grad[:, :, 1] @ local  # (m, k, 2): dx/dv
    return xu[..., 0] * xv[..., 1] - xv[..., 0] * xu[..., 1]


def jacobian_at_nodes(nodes: ArrayLike) -> NDArray[np.float64]:
    """``J`` at the six nodes, shape ``(m, 6)``, columns in node order.

    >>> tri = np.array([[[0, 0], [1, 0], [0, 1], [0.5, 0], [0.5, 0.5], [0, 0.5]]])
    >>> jacobian_at_nodes(tri)
    array([[1., 1., 1., 1., 1., 1.]])
    """
    return p2_jacobian(nodes, REFERENCE_NODES)


def jacobian_bezier(nodes: ArrayLike) -> NDArray[np.float64]:
    """Bezier (Bernstein) coefficients of ``J``, shape ``(m, 6)``.

    Order: corners 0, 1, 2, then edges 01, 12, 20, so that
    ``J = sum_i b_i l_i^2 + sum_{ij} 2 b_ij l_i l_j`` exactly. From the nodal
    values (Johnen, Remacle, Geuzaine 2013):

        b_i = J_i,    b_ij = 2 J_ij - (J_i + J_j) / 2.

    A straight-sided triangle has all six equal to twice its signed area.

    >>> tri = np.array([[[0, 0], [1, 0], [0, 1], [1, -0.5], [0.3, 0.3], [0, 0.5]]])
    >>> jacobian_at_nodes(tri).round(12)
    array([[3. , 3.4, 0.2, 1.6, 0.2, 1.6]])
    >>> jacobian_bezier(tri).round(12)
    array([[ 3. ,  3.4,  0.2,  0. , -1.4,  1.6]])
    """
    jn = jacobian_at_nodes(nodes)
    b = jn.copy()
    for k, (i, j) in enumerate(EDGES):
        b[:, 3 + k] = 2.0 * jn[:, 3 + k] - 0.5 * (jn[:, i] + jn[:, j])
    return b


def valid_sufficient(nodes: ArrayLike) -> NDArray[np.bool_]:
    """Sufficient validity test: all six Bezier coefficients of ``J`` are positive.

    Equivalent to ``J_i > 0`` and ``4 J_ij > J_i + J_j`` (paper section 4). True
    implies ``J > 0`` on the closed triangle; False decides nothing.

    Returns
    -------
    (m,) booleans.

    >>> tri = np.array([[[0, 0], [1, 0], [0, 1], [0.5, 0], [0.5, 0.5], [0, 0.5]]])
    >>> valid_sufficient(tri)
    array([ True])
    """
    return np.all(jacobian_bezier(nodes) > 0.0, axis=1)


def _coeff_matrix(b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Symmetric ``(m, 3, 3)`` matrices ``B`` with ``J = l^T B l`` from ``(m, 6)`` coefficients."""
    mat = np.empty((b.shape[0], 3, 3))
    for i in range(3):
        mat[:, i, i] = b[:, i]
    for k, (i, j) in enumerate(EDGES):
        mat[:, i, j] = mat[:, j, i] = b[:, 3 + k]
    return mat


def bezier_min(coeffs: ArrayLike) -> NDArray[np.float64]:
    """Exact minimum over the closed triangle of a quadratic Bezier triangle.

    The minimum of ``J = l^T B l`` over the simplex is attained at a corner, at
    a critical point inside an edge, or at a critical point inside the
    triangle; each case has a closed form.

    * Corners: ``b_i``.
    * Edge ``ij`` with ``t`` from ``i`` to ``j``: ``J = b_ij + p (1-t)^2 + q t^2``
      with ``p = b_i - b_ij``, ``q = b_j - b_ij``. An interior minimum exists iff
      ``p, q > 0``; it is at ``t = p / (p + q)`` and equals ``b_ij + p q / (p + q)``
      (no cancellation: ``0 < p q / (p + q) <= min(p, q)``).
    * Interior: in ``(u, v)``, ``J = b_0 + 2 g.x + x^T A x`` with
      ``g = (b_01 - b_0, b_20 - b_0)``, ``A_11 = b_0 - 2 b_01 + b_1``,
      ``A_22 = b_0 - 2 b_20 + b_2``, ``A_12 = b_0 - b_01 - b_20 + b_12``. An interior
      minimum needs ``A`` positive definite (if ``A`` is indefinite or negative
      there is none; if it is singular and semidefinite, ``J`` is constant or
      linear along a line through any critical point, and the boundary attains the
      minimum). Then ``x* = -A^{-1} g``, tested for strict interiority by Cramer's
      rule without dividing (``det x*`` against ``det``), so no overflow.

    Every candidate is ``J`` evaluated at a point of the triangle, so the result
    is never below the true minimum by more than the evaluation round-off, and
    a critical point missed by round-off near an edge costs only a second-order
    error, the gradient being zero there.

    Parameters
    ----------
    coeffs : (m, 6) Bezier coefficients, corners then edges 01, 12, 20.

    Returns
    -------
    (m,) minima.

    >>> bezier_min([[1.0, 1.0, 1.0, -1.0, 1.0, 1.0], [2.0, 2.0, 2.0, 0.0, 0.0, 0.0]])
    array([0.        , 0.66666667])
    """
    b = _as_coeffs(coeffs)
    best = b[:, :3].min(axis=1)

    for k, (i, j) in enumerate(EDGES):
        bij = b[:, 3 + k]
        p = b[:, i] - bij
        q = b[:, j] - bij
        inside = (p > 0.0) & (q > 0.0)
        denom = np.where(inside, p + q, 1.0)
        best = np.where(inside, np.minimum(best, bij + p * q / denom), best)

    b0, b1, b2, b01, b12, b20 = b.T
    a11 = b0 - 2.0 * b01 + b1
    a22 = b0 - 2.0 * b20 + b2
    a12 = b0 - b01 - b20 + b12
    g1 = b01 - b0
    g2 = b20 - b0
    det = a11 * a22 - a12 * a12
    # x* = -A^{-1} g = (un, vn) / det
    un = a12 * g2 - a22 * g1
    vn = a12 * g1 - a11 * g2
    inside = (det > 0.0) & (a11 > 0.0) & (un > 0.0) & (vn > 0.0) & (un + vn < det)
    if np.any(inside):
        bi = b[inside]
        u = un[inside] / det[inside]
        v = vn[inside] / det[inside]
        lam = np.column_stack([1.0 - u - v, u, v])
        value = np.einsum("ni,nij,nj->n", lam, _coeff_matrix(bi), lam)
        best[inside] = np.minimum(best[inside], value)
    return best


def min_jacobian(nodes: ArrayLike) -> NDArray[np.float64]:
    """Exact minimum of ``J`` over the closed reference triangle, shape ``(m,)``.

    Closed form on the Bezier coefficients, see :func:`bezier_min`.

    Positive at all six nodes, yet ``J = -0.2`` at ``(u, v) = (0.25, 0.75)`` on edge 12:

    >>> tri = np.array([[[0, 0], [1, 0], [0, 1], [1, -0.5], [0.3, 0.3], [0, 0.5]]])
    >>> min_jacobian(tri).round(12), p2_jacobian(tri, [[0.25, 0.75]]).round(12)
    (array([-0.2]), array([[-0.2]]))
    """
    return bezier_min(jacobian_bezier(nodes))


def valid_exact(nodes: ArrayLike, *, rtol: float = VALID_RTOL) -> NDArray[np.bool_]:
    """Whether ``J > 0`` on the whole closed triangle, decided exactly.

    A triangle is valid when ``min J > rtol * max_k |b_k|``: the tolerance is
    relative to the scale of ``J``, so that a triangle with ``J = 0`` at a point
    (a degenerate corner, say) is invalid despite round-off. The cheap
    sufficient test ``min_k b_k > rtol * max_k |b_k|`` (``min J >= min_k b_k``)
    settles most triangles; :func:`bezier_min` runs only on the others.

    Parameters
    ----------
    nodes : (m, 6, 2) P2 triangles, Gmsh order.
    rtol : relative tolerance, ``>= 0``.

    Returns
    -------
    (m,) booleans.

    >>> tri = np.array([[[0, 0], [1, 0], [0, 1], [0.5, 0], [0.5, 0.5], [0, 0.5]]])
    >>> bad = tri.copy(); bad[0, 4] = [0.2, 0.2]
    >>> valid_exact(np.concatenate([tri, bad]))
    array([ True, False])
    """
    if rtol < 0.0:
        raise ValueError(f"rtol must be >= 0, got {rtol}")
    b = jacobian_bezier(nodes)
    threshold = rtol * np.abs(b).max(axis=1, initial=0.0)
    valid = b.min(axis=1, initial=np.inf) > threshold
    undecided = ~valid
    if np.any(undecided):
        valid[undecided] = bezier_min(b[undecided]) > threshold[undecided]
    return valid


def min_jacobian_subdivision(nodes: ArrayLike, *, depth: int) -> NDArray[np.float64]:
    """Lower bound of ``min J`` by recursive subdivision of the Bezier triangle.

    The classic method of Johnen, Remacle, Geuzaine (2013): split the reference
    triangle at the edge midpoints into 4, ``depth`` times, and take the least
    Bezier coefficient of the ``4**depth`` sub-triangles. The coefficients of a
    sub-triangle with corners at barycentric points ``P_0, P_1, P_2`` are the
    blossom values ``b'_kl = P_k^T B P_l``, i.e. ``B' = P^T B P`` — what de
    Casteljau's algorithm computes. They are convex combinations of the parent's,
    so the bound never decreases with depth and never exceeds the true minimum;
    its error decreases as ``h^2``, about a factor 4 per level (the blossom
    ``b'_kl = J((P_k + P_l)/2) - (P_k - P_l)^T B (P_k - P_l) / 4`` is within
    ``||B|| |P_k - P_l|^2 / 4 <= 1.5 * 4**-depth * max|b|`` of a value of ``J``).

    Sub-triangles are carried as one flat array for all triangles, with the index
    of their owner. A sub-triangle whose least coefficient is not below the best
    known value of ``J`` (the least corner coefficient ``b'_kk = J(P_k)`` seen so
    far, an upper bound of ``min J``) is not subdivided further: its descendants
    cannot lower the result, which is therefore that of the full subdivision, at
    a cost that usually grows linearly with ``depth`` (up to ``m * 4**depth``
    when ``J`` is nearly constant).

    Parameters
    ----------
    nodes : (m, 6, 2) P2 triangles, Gmsh order.
    depth : number of levels, ``>= 0`` (0 gives ``min_k b_k``).

    Returns
    -------
    (m,) lower bounds.

    Here the minimum, ``-1/16``, is inside the triangle:

    >>> tri = np.array([[[0, 0], [1, 0], [0, 1], [0, -0.1], [0.9, 0.9], [-0.1, 0]]])
    >>> [round(float(min_jacobian_subdivision(tri, depth=d)[0]), 6) for d in range(5)]
    [-2.2, -0.68, -0.2, -0.1, -0.07]
    >>> min_jacobian(tri).round(12)
    array([-0.0625])
    """
    if depth < 0:
        raise ValueError(f"depth must be >= 0, got {depth}")
    mat = _coeff_matrix(jacobian_bezier(nodes))  # (n, 3, 3), n sub-triangles
    m = mat.shape[0]
    owner = np.arange(m)
    diagonal = np.arange(3)
    upper = mat[:, diagonal, diagonal].min(axis=1, initial=np.inf)  # (m,) min J at corners
    lower = np.full(m, np.inf)  # (m,) least coefficient of the sub-triangles set aside
    for _ in range(depth):
        mat = np.einsum("ski,nkl,slj->nsij", _SUBDIVISION, mat, _SUBDIVISION).reshape(-1, 3, 3)
        owner = np.repeat(owner, 4)
        np.minimum.at(upper, owner, mat[:, diagonal, diagonal].min(axis=1))
        least = mat.reshape(-1, 9).min(axis=1)
        keep = least < upper[owner]
        np.minimum.at(lower, owner[~keep], least[~keep])
        mat, owner = mat[keep], owner[keep]
    np.minimum.at(lower, owner, mat.reshape(-1, 9).min(axis=1, initial=np.inf))
    return lower


def scaled_jacobian_min(nodes: ArrayLike) -> NDArray[np.float64]:
    """``min J`` divided by the Jacobian of the straight triangle through the corners.

    The straight Jacobian is ``(x_1 - x_0) x (x_2 - x_0)``, twice the signed area
    of the corner triangle; the ratio is 1 for a straight-sided triangle and
    positive for a valid one when the corners are counter-clockwise. Where the
    corners are collinear the ratio is ``-inf`` (worst quality).

    Returns
    -------
    (m,) ratios.

    >>> tri = np.array([[[0, 0], [1, 0], [0, 1], [0.5, 0], [0.5, 0.5], [0, 0.5]]])
    >>> scaled_jacobian_min(tri)
    array([1.])
    """
    x = _as_nodes(nodes)
    e1 = x[:, 1] - x[:, 0]
    e2 = x[:, 2] - x[:, 0]
    straight = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    out = np.full(x.shape[0], -np.inf)
    np.divide(min_jacobian(x), straight, out=out, where=straight != 0.0)
    return out
