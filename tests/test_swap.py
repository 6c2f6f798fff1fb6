"""Swaps (:func:`curvimesh.swap.swap`): the rule for edge lengths (``length_rule``) and
the refusal of short new edges, on quads whose lengths and qualities are known by hand
in the Euclidean metric."""

from __future__ import annotations

import math

import pytest

from curvimesh.mesh import Mesh, to_p2_straight
from curvimesh.metric import load_metric_text
from curvimesh.quality import edge_lengths, metric_areas, quality_from
from curvimesh.swap import swap

EUCLID = """
domain: {box: [[-1, -1], [2, 1]]}
metric:
  isotropic: 1
"""


#: A lone triangle of quality 0.371 (by hand: 4√3 · 0.0075 / 0.14), away from the kite.
LONE = [[1.6, 0.6], [1.9, 0.6], [1.75, 0.65]]


def _kite(xc: float, *, lone: bool = True) -> Mesh:
    """Triangles (a, b, c), (b, a, d): a = (0, 0), b = (1.45, 0), c, d = (xc, ±0.5),
    and (unless ``lone`` is off) the triangle :data:`LONE`, the worst of the mesh."""
    pts = [[0.0, 0.0], [1.45, 0.0], [xc, 0.5], [xc, -0.5], *(LONE if lone else [])]
    tris = [[0, 1, 2], [1, 0, 3], *([[4, 5, 6]] if lone else [])]
    return to_p2_straight(Mesh(pts, tris, (-1, -1, 2, 1)))


def _q(ax, ay, bx, by, cx, cy) -> float:
    """Equation (4) for a straight triangle in the Euclidean metric, by hand."""
    area = 0.5 * ((bx - ax) * (cy - ay) - (by - ay) * (cx - ax))
    l2 = (bx - ax) ** 2 + (by - ay) ** 2 + (cx - bx) ** 2 + (cy - by) ** 2
    l2 += (ax - cx) ** 2 + (ay - cy) ** 2
    return 4 * math.sqrt(3) * area / l2


def test_the_rule_for_lengths_takes_a_swap_that_the_quality_rule_refuses():
    fld = load_metric_text(EUCLID)
    mesh = _kite(0.3)
    # by hand: the diagonal a-b is 1.45 long (out of [0.7, 1.4]), c-d is 1.0 long;
    # the swap lowers the worse quality of the pair from 0.6255 to 0.6186
    q_old = min(_q(0, 0, 1.45, 0, 0.3, 0.5), _q(1.45, 0, 0, 0, 0.3, -0.5))
    q_new = min(_q(0, 0, 0.3, -0.5, 0.3, 0.5), _q(0.3, -0.5, 1.45, 0, 0.3, 0.5))
    assert q_old == pytest.approx(0.6255, abs=1e-4) and q_new == pytest.approx(0.6186, abs=1e-4)
    assert _q(*LONE[0], *LONE[1], *LONE[2]) == pytest.approx(0.371, abs=1e-3)
    assert swap(fld, mesh).swaps == 0
    res = swap(fld, mesh, length_rule=True)
    assert res.swaps == 1
    out = res.mesh
    pts = out.points
    lengths = edge_lengths(fld, pts, out.edges, out.edge_mid)
    assert lengths.max() == pytest.approx(math.hypot(1.15, 0.5), rel=1e-9)  # b-c, 1.254
    cd = [k for k, (i, j) in enumerate(out.edges.tolist()) if (i, j) == (2, 3)]  # c-d
    assert len(cd) == 1 and lengths[cd[0]] == pytest.approx(1.0, rel=1e-9)
    assert not any((i, j) == (0, 1) for i, j in out.edges.tolist())  # a-b is gone
    q = quality_from(metric_areas(fld, pts[out.triangles]), lengths[out.tri_edges])
    assert q[:2].min() == pytest.approx(q_new, rel=1e-9)


def test_the_rule_for_lengths_keeps_the_quality_floor():
    fld = load_metric_text(EUCLID)
    mesh = _kite(0.05)
    # by hand: the swap would make c-d 1.0 long but a triangle of quality 0.115 < 0.3
    assert _q(0, 0, 0.05, -0.5, 0.05, 0.5) == pytest.approx(0.115, abs=1e-3)
    assert swap(fld, mesh, length_rule=True).swaps == 0


def test_the_rule_for_lengths_never_lowers_the_worst_quality():
    fld = load_metric_text(EUCLID)
    # the floor is max(min_quality, the worst quality of the mesh), and q_new = 0.6186
    assert swap(fld, _kite(0.3), length_rule=True, min_quality=0.61).swaps == 1
    assert swap(fld, _kite(0.3), length_rule=True, min_quality=0.62).swaps == 0
    # without the lone triangle the kite's pair is the worst of the mesh, 0.6255
    assert swap(fld, _kite(0.3, lone=False), length_rule=True).swaps == 0


def test_no_swap_makes_an_edge_shorter_than_07():
    # a flat kite: a-b 1.45 long, c-d = (0.7, ±0.3) only 0.6 long. By hand the
    # quality rule prefers c-d (worse quality of the pair 0.452 → 0.936), but the
    # new edge would be shorter than 0.7 and than a-b
    fld = load_metric_text(EUCLID)
    pts = [[0.0, 0.0], [1.45, 0.0], [0.7, 0.3], [0.7, -0.3]]
    mesh = to_p2_straight(Mesh(pts, [[0, 1, 2], [1, 0, 3]], (-1, -1, 2, 1)))
    q_old = min(_q(0, 0, 1.45, 0, 0.7, 0.3), _q(1.45, 0, 0, 0, 0.7, -0.3))
    q_new = min(_q(0, 0, 0.7, -0.3, 0.7, 0.3), _q(0.7, -0.3, 1.45, 0, 0.7, 0.3))
    assert q_old == pytest.approx(0.452, abs=1e-3) and q_new == pytest.approx(0.936, abs=1e-3)
    assert swap(fld, mesh, min_length=0.0).swaps == 1
    assert swap(fld, mesh).swaps == 0
    assert swap(fld, mesh, length_rule=True).swaps == 0
    assert swap(fld, mesh, min_length=0.6 - 1e-9).swaps == 1


@pytest.mark.parametrize("name", ["toy", "front", "constant_aniso"])
def test_quality_bound_holds_for_every_possible_swap(name):
    """The bound that spares hopeless candidates their parabola search is above the
    worse quality of the two new triangles, with the new edge straight or on its
    shortest parabola, for every interior edge of an adapted mesh."""
    from pathlib import Path

    import numpy as np

    from curvimesh import adapt as pipeline
    from curvimesh.geodesic import chord_lower_bound, lens_lower_bound, shortest_parabola
    from curvimesh.mesh import flip_candidates, p1_edges, p1_of
    from curvimesh.metric import load_metric
    from curvimesh.quality import edge_lengths_fast
    from curvimesh.swap import quality_bound

    fld = load_metric(Path(__file__).resolve().parent.parent / "metrics" / f"{name}.yaml")
    opt = pipeline.AdaptOptions()
    p2 = pipeline.curve(fld, pipeline.triangulate(pipeline.sample(fld, opt), fld, opt), opt)
    p1 = p1_of(p2)
    pts = np.asarray(p1.points)
    edges = p1_edges(p2)
    mids = np.asarray(p2.points)[p2.edge_mid]
    node = {(int(min(i, j)), int(max(i, j))): k for k, (i, j) in enumerate(edges)}
    _, _, _, a, b, c, d = flip_candidates(p1)

    def mid_of(u, v):
        return mids[[node[(min(x, y), max(x, y))] for x, y in zip(u, v, strict=True)]]

    def length_of(u, v):
        return edge_lengths_fast(fld, pts[u], pts[v], mid_of(u, v))

    def nodes(corner, edge_mids):
        return np.concatenate([pts[np.column_stack(corner)], np.stack(edge_mids, axis=1)], axis=1)

    old1 = nodes([a, b, c], [mid_of(a, b), mid_of(b, c), mid_of(c, a)])
    old2 = nodes([b, a, d], [mid_of(b, a), mid_of(a, d), mid_of(d, b)])
    area = metric_areas(fld, old1) + metric_areas(fld, old2)
    l_ad, l_ca, l_db, l_bc = (length_of(u, v) for u, v in ((a, d), (c, a), (d, b), (b, c)))
    outer = l_ad**2 + l_ca**2 + l_db**2 + l_bc**2
    bound = quality_bound(area, outer, chord_lower_bound(fld, pts[c], pts[d]))
    lens = quality_bound(area, outer, lens_lower_bound(fld, pts[c], pts[d]))
    straight = 0.5 * (pts[c] + pts[d])
    for m_cd in (straight, shortest_parabola(fld, pts[c], pts[d], exact_length=False).mid):
        l_cd = edge_lengths_fast(fld, pts[c], pts[d], m_cd)
        q1 = quality_from(
            metric_areas(fld, nodes([a, d, c], [mid_of(a, d), m_cd, mid_of(c, a)])),
            np.column_stack([l_ad, l_cd, l_ca]),
        )
        q2 = quality_from(
            metric_areas(fld, nodes([d, b, c], [mid_of(d, b), mid_of(b, c), m_cd])),
            np.column_stack([l_db, l_bc, l_cd]),
        )
        assert np.all(np.minimum(q1, q2) <= bound)
        assert np.all(np.minimum(q1, q2) <= lens)
    # and it spares most searches: a good mesh's swaps are mostly hopeless
    q_old = np.minimum(
        quality_from(
            metric_areas(fld, old1), np.column_stack([length_of(a, b), length_of(b, c), l_ca])
        ),
        quality_from(metric_areas(fld, old2), np.column_stack([length_of(b, a), l_ad, l_db])),
    )
    assert np.mean(bound <= q_old) > 0.2


def test_the_lens_bound_spares_searches_and_changes_no_swap(monkeypatch):
    """The swaps with the lens bound are those without it, with fewer new edges searched."""
    from pathlib import Path

    import numpy as np

    from curvimesh import adapt as pipeline
    from curvimesh import swap as swap_module
    from curvimesh.metric import load_metric

    fld = load_metric(Path(__file__).resolve().parent.parent / "metrics" / "three_toys.yaml")
    opt = pipeline.AdaptOptions()
    p2 = pipeline.curve(fld, pipeline.triangulate(pipeline.sample(fld, opt), fld, opt), opt)
    searched = []
    search = swap_module.shortest_parabola

    def counted(field, a, b, **kw):
        searched.append(len(a))
        return search(field, a, b, **kw)

    monkeypatch.setattr(swap_module, "shortest_parabola", counted)
    runs = []
    for lens in (True, False):
        if not lens:
            monkeypatch.setattr(
                swap_module, "lens_lower_bound", lambda field, a, b: np.zeros(len(a))
            )
        searched.clear()
        res = swap(fld, p2, length_rule=True)
        runs.append((res, sum(searched)))
    (with_lens, n_lens), (without, n_without) = runs
    assert np.array_equal(with_lens.mesh.points, without.mesh.points)
    assert np.array_equal(with_lens.mesh.triangles, without.mesh.triangles)
    assert with_lens.swaps == without.swaps > 0
    assert n_lens < 0.9 * n_without
