"""Vertex removal at flat triangles (curvimesh.remove)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import Delaunay

from curvimesh.bezier import valid_exact
from curvimesh.mesh import Mesh, is_conforming, signed_areas, to_p2_straight
from curvimesh.metric import load_metric_text
from curvimesh.quality import edge_lengths, metric_areas, quality_from
from curvimesh.remove import MAX_VALENCE, polygon_triangulations, remove_vertices

EUCLID = "domain: {box: [[-0.5, -0.5], [6.5, 6.5]]}\nmetric: {isotropic: 1}\n"
BOX = (-0.5, -0.5, 6.5, 6.5)


def catalan(n: int) -> int:
    return math.comb(2 * n, n) // (n + 1)


@pytest.mark.parametrize("n", range(3, 10))
def test_every_triangulation_of_a_polygon_is_found_once(n):
    tris = polygon_triangulations(n)
    assert len(tris) == catalan(n - 2)
    assert len({frozenset(t) for t in tris}) == len(tris)
    ring = np.column_stack(
        [np.cos(2 * np.pi * np.arange(n) / n), np.sin(2 * np.pi * np.arange(n) / n)]
    )
    polygon = 0.5 * n * np.sin(2 * np.pi / n)
    for t in tris:
        corners = np.array(t)
        assert len(t) == n - 2
        area = signed_areas(ring, corners)
        assert (area > 0).all()  # counter-clockwise
        assert area.sum() == pytest.approx(polygon, rel=1e-12)


def lattice_with_extra_vertex(offset: float, *, on_edge: bool) -> tuple[Mesh, Mesh, np.ndarray]:
    """The unit triangle lattice, and the same with one more vertex p near the middle
    of an interior edge ab, ``offset`` of the way towards the third corner c of a
    triangle abc. With ``on_edge`` ab is dropped and p joined to a, b and the third
    corners of both its triangles (valence 4); otherwise p is joined to a, b and c
    (valence 3, the triangle abp flat). Returns both meshes and p."""
    i, j = np.meshgrid(np.arange(6), np.arange(6), indexing="ij")
    pts = np.column_stack([(i + 0.5 * j).ravel(), (np.sqrt(3) / 2 * j).ravel()]).astype(float)
    tris = Delaunay(pts).simplices
    area = signed_areas(pts, tris)
    tris[area < 0] = tris[area < 0][:, [0, 2, 1]]
    mesh = Mesh(pts, tris, BOX)
    centre = pts.mean(axis=0)
    inner = np.flatnonzero(mesh.edge_tris[:, 1] >= 0)
    mids = 0.5 * (pts[mesh.edges[inner, 0]] + pts[mesh.edges[inner, 1]])
    e = inner[np.argmin(np.hypot(*(mids - centre).T))]
    a, b = mesh.edges[e]
    cut = mesh.edge_tris[e] if on_edge else mesh.edge_tris[e][:1]
    c = next(int(u) for u in tris[cut[0]] if u not in (a, b))
    p = 0.5 * (pts[a] + pts[b]) + offset * (pts[c] - 0.5 * (pts[a] + pts[b]))
    k = len(pts)
    kept = [r for n, r in enumerate(tris.tolist()) if n not in cut]
    for t in cut:
        for u, w in ((0, 1), (1, 2), (2, 0)):
            x, y = tris[t][u], tris[t][w]
            if not on_edge or {x, y} != {a, b}:
                kept.append([x, y, k])
    new_pts = np.vstack([pts, p])
    return to_p2_straight(mesh), to_p2_straight(Mesh(new_pts, np.array(kept), BOX)), p


def corner_sets(mesh: Mesh) -> set[frozenset]:
    pts = np.asarray(mesh.points)
    return {frozenset(map(tuple, np.round(pts[t], 12))) for t in mesh.triangles[:, :3]}


@pytest.mark.parametrize(("on_edge", "min_quality"), [(False, 0.3), (True, 0.8)])
def test_a_vertex_near_an_edge_is_removed_and_the_lattice_restored(on_edge, min_quality):
    # valence 3: the triangle abp is flat (q < 0.3); valence 4: the four triangles
    # around p have q near 0.75, so they count as bad for min_quality 0.8
    fld = load_metric_text(EUCLID)
    lattice, extra, p = lattice_with_extra_vertex(0.05, on_edge=on_edge)
    q0 = quality(fld, extra)
    assert 0 < q0.min() < min_quality
    res = remove_vertices(fld, extra, min_quality=min_quality)
    assert res.removed == 1
    assert len(res.mesh.vertex_ids) == len(extra.vertex_ids) - 1
    assert len(res.mesh.triangles) == len(extra.triangles) - 2
    assert corner_sets(res.mesh) == corner_sets(lattice)
    pts = np.asarray(res.mesh.points)
    assert not np.any(np.all(np.isclose(pts, p), axis=1))
    assert is_conforming(res.mesh)
    assert valid_exact(pts[res.mesh.triangles]).all()
    # every node is used, and the edge nodes are the (Euclidean) midpoints
    assert len(pts) == len(res.mesh.vertex_ids) + len(res.mesh.edges)
    mids = 0.5 * (pts[res.mesh.edges[:, 0]] + pts[res.mesh.edges[:, 1]])
    np.testing.assert_allclose(pts[res.mesh.edge_mid], mids, atol=1e-6)
    np.testing.assert_allclose(quality(fld, res.mesh), 1.0, atol=1e-6)


def quality(fld, mesh: Mesh) -> np.ndarray:
    pts = np.asarray(mesh.points)
    lens = edge_lengths(fld, pts, mesh.edges, mesh.edge_mid)
    return quality_from(metric_areas(fld, pts[mesh.triangles]), lens[mesh.tri_edges])


def test_the_removal_is_deterministic_and_leaves_good_meshes_alone():
    fld = load_metric_text(EUCLID)
    lattice, extra, _ = lattice_with_extra_vertex(0.05, on_edge=False)
    one, two = remove_vertices(fld, extra).mesh, remove_vertices(fld, extra).mesh
    assert np.asarray(one.points).tobytes() == np.asarray(two.points).tobytes()
    assert one.triangles.tobytes() == two.triangles.tobytes()
    res = remove_vertices(fld, lattice)
    assert res.removed == 0 and res.mesh is lattice


def test_no_removal_makes_a_long_edge():
    # valence 4, but with max_length 0.9 both diagonals (ab 1 long, cd 1.73) are too long
    fld = load_metric_text(EUCLID)
    _, extra, _ = lattice_with_extra_vertex(0.05, on_edge=True)
    res = remove_vertices(fld, extra, max_length=0.9, min_quality=0.8)
    assert res.removed == 0


def test_boundary_vertices_and_high_valence_are_kept():
    fld = load_metric_text(EUCLID)
    # a fan of MAX_VALENCE + 1 thin triangles around an interior vertex, and a flat
    # triangle on the box side: nothing may be removed
    n = MAX_VALENCE + 1
    ring = np.column_stack(
        [np.cos(2 * np.pi * np.arange(n) / n), np.sin(2 * np.pi * np.arange(n) / n)]
    )
    pts = np.vstack([[3.0, 3.0], 3.0 + ring])
    tris = np.array([[0, 1 + k, 1 + (k + 1) % n] for k in range(n)])
    mesh = to_p2_straight(Mesh(pts, tris, BOX))
    res = remove_vertices(fld, mesh, min_quality=1.01)  # every triangle counts as bad
    assert res.removed == 0


def test_the_end_of_a_long_edge_is_removed_when_its_ring_has_a_unit_diagonal():
    """A 60° rhombus of unit sides (short diagonal 1, long one √3) with a vertex v
    inside, 0.32 from a sharp corner: v's edge to the far corner is 1.412, none of
    its triangles is flat (q ≥ 0.33). Removing v and joining the short diagonal
    leaves two equilateral triangles; the long diagonal (1.73) is refused. The edge
    of 0.32 to the sharp corner is shorter than 0.7: it removes v too."""
    fld = load_metric_text("domain: {box: [[0, -0.5], [1.8, 0.5]]}\nmetric: {isotropic: 1}\n")
    h = math.sqrt(3) / 2
    pts = np.array([[0.0, 0.0], [h, -0.5], [2 * h, 0.0], [h, 0.5], [0.32, 0.0]])
    star = to_p2_straight(Mesh(pts, np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]]), BOX))
    lens = edge_lengths(fld, np.asarray(star.points), star.edges, star.edge_mid)
    assert lens.max() == pytest.approx(2 * h - 0.32) and lens.max() > 1.4
    assert quality(fld, star).min() >= 0.33
    assert remove_vertices(fld, star, long_edges=False, short_edges=False).removed == 0
    # v's edge to the sharp corner, 0.32, is short: either edge alone removes it
    for long_edges, short_edges in ((True, False), (False, True)):
        res = remove_vertices(fld, star, long_edges=long_edges, short_edges=short_edges)
        assert res.removed == 1
        corners = np.asarray(res.mesh.points)[res.mesh.triangles[:, :3]]
        assert {frozenset(map(tuple, np.round(c, 12))) for c in corners} == {
            frozenset(map(tuple, np.round(pts[list(t)], 12))) for t in ((0, 1, 3), (1, 2, 3))
        }
        np.testing.assert_allclose(quality(fld, res.mesh), 1.0, atol=1e-9)
        assert valid_exact(np.asarray(res.mesh.points)[res.mesh.triangles]).all()
