"""Algorithm 1's shortcuts against the plain algorithm: the shots it spares and the gap
candidates it does not test again would all have been refused."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from curvimesh import fill, sampling
from curvimesh.boundary import discretize_box
from curvimesh.metric import load_metric

METRICS = Path(__file__).resolve().parent.parent / "metrics"


def rotation(t: float) -> np.ndarray:
    return np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])


@settings(max_examples=200, deadline=None)
@given(
    st.floats(0.0, math.pi),
    st.floats(-3.0, 3.0),
    st.floats(0.0, 2 * math.pi),
    st.floats(0.0, 60.0),
)
def test_backward_is_the_direction_within_20_degrees_of_the_way_back_in_the_metric(
    angle, log_ratio, heading, off
):
    # g = R diag(1, r²) Rᵀ: in the coordinates u = diag(1, r) Rᵀ x it is the identity;
    # the arrival velocity is drawn there at `heading`, and the way back is the
    # principal direction nearest to −arrival; it is flagged iff the metric angle
    # between them is at most 20° (angles drawn `off` degrees from a principal axis)
    r = math.exp(log_ratio)
    rot = rotation(angle)
    g = rot @ np.diag([1.0, r * r]) @ rot.T
    dirs = sampling.principal_directions(g[None])
    k = int(heading // (math.pi / 2)) % 4
    axis = [0.0, math.pi / 2, math.pi, 3 * math.pi / 2][k]
    back = axis + math.radians(off)  # the way back, in the identity coordinates
    u = -np.array([math.cos(back), math.sin(back)])  # arrival = −(way back)
    arrival = rot @ (np.array([1.0, 1.0 / r]) * u)  # x = R diag(1, 1/r) u
    flags = sampling.backward(g[None], dirs, arrival[None])[0]
    # the truth in the identity coordinates: the angle between each direction and −u
    uu = np.array([1.0, r]) * (rot.T @ dirs[0].T).T
    cos = (uu @ -u) / np.linalg.norm(uu, axis=1)
    truth = cos >= math.cos(math.radians(20.0))
    np.testing.assert_array_equal(flags, truth)
    # the other principal directions are at least 90° − 60° away: one flag iff off ≤ 20°
    # (where the principal axes are R's, the eigenvalues apart)
    if abs(off - 20.0) > 1e-6 and abs(log_ratio) > 0.05:
        assert flags.sum() == (off < 20.0)
    # a point not reached by a shot has no way back
    assert not sampling.backward(g[None], dirs, np.full((1, 2), np.nan)).any()


@pytest.mark.parametrize("name", ["toy", "three_toys", "front", "circular_layer"])
def test_sparing_the_backward_shots_changes_no_point(name, monkeypatch):
    fld = load_metric(METRICS / f"{name}.yaml")
    opt = sampling.SamplingOptions()
    bnd = discretize_box(fld, target=opt.spacing, min_dist=opt.min_dist)
    spared = sampling.sample_points(fld, bnd, opt)
    calls = []

    def none_backward(g, dirs, arrival):
        calls.append(sampling.BACK_COS)
        return np.zeros(dirs.shape[:2], dtype=bool)

    monkeypatch.setattr(sampling, "backward", none_backward)
    plain = sampling.sample_points(fld, bnd, opt)
    assert calls and np.array_equal(spared, plain)


def test_a_shot_back_along_the_geodesic_would_be_refused():
    # the candidates spared: shot from a point back along its arrival, on a metric
    # whose frame turns (the toy's ring), each lands within min_dist of the parent
    fld = load_metric(METRICS / "toy.yaml")
    opt = sampling.SamplingOptions()
    rng = np.random.default_rng(3)
    start = rng.uniform(-0.9, 0.9, (400, 2))
    g = fld.tensor(start)
    dirs = sampling.principal_directions(g)
    pick = rng.integers(0, 4, len(start))
    d = dirs[np.arange(len(start)), pick]
    shot = sampling.shoot(fld, start, d, opt.spacing, tol=opt.shoot_tol)
    child, arrival = shot.end[shot.ok], shot.velocity[shot.ok]
    gc = fld.tensor(child)
    cdirs = sampling.principal_directions(gc)
    flags = sampling.backward(gc, cdirs, arrival)
    # at most one way back from each child (none where the frame turned more than 20°)
    assert flags.sum(axis=1).max() == 1 and flags.sum() > 0.9 * len(child)
    back, row = cdirs[flags], np.nonzero(flags)[0]
    again = sampling.shoot(fld, child[row], back, opt.spacing, tol=opt.shoot_tol)
    parents = start[shot.ok][row]
    assert sampling.too_close(fld, again.end, parents, opt.min_dist).all()


@settings(max_examples=200, deadline=None)
@given(st.integers(3, 2000), st.integers(0, 3000), st.data())
def test_fill_source_keys_survive_renumbering(n, extra, data):
    ids = np.array(
        data.draw(
            st.lists(
                st.tuples(st.integers(0, n - 1), st.integers(0, n - 1), st.integers(-1, n - 1)),
                min_size=1,
                max_size=20,
            )
        ),
        dtype=np.int64,
    )
    keys = fill._source_keys(ids, n)
    assert len(np.unique(keys)) == len(np.unique(ids, axis=0))
    np.testing.assert_array_equal(
        fill._renumbered(keys, n, n + extra), fill._source_keys(ids, n + extra)
    )


@pytest.mark.parametrize("name", ["three_toys", "quartic2", "boundary_layer"])
def test_gap_filling_without_retesting_refused_candidates_is_the_same(name, monkeypatch):
    fld = load_metric(METRICS / f"{name}.yaml")
    opt = sampling.SamplingOptions()
    bnd = discretize_box(fld, target=opt.spacing, min_dist=opt.min_dist)
    pts = sampling.sample_points(fld, bnd, opt)
    remembered = fill.fill_gaps(fld, pts, opt)
    monkeypatch.setattr(fill, "_renumbered", lambda keys, n, m: keys[:0])  # forget them
    tested_again = fill.fill_gaps(fld, pts, opt)
    assert len(remembered) > len(pts)
    np.testing.assert_array_equal(remembered, tested_again)


@pytest.mark.parametrize(
    "name", ["toy", "three_toys", "front", "circular_layer", "boundary_layer", "quartic2"]
)
def test_search_regions_hold_every_point_closer_than_min_dist(name):
    # random points and their pairs closer than 0.7 by shortest parabola: the second
    # lies in the first's search region (an ellipse inside a box), which is much
    # smaller than the square of the largest size where the metric is anisotropic
    from curvimesh.geodesic import shortest_parabola
    from curvimesh.spatial import pairs_within_boxes

    fld = load_metric(METRICS / f"{name}.yaml")
    rng = np.random.default_rng(11)
    xmin, ymin, xmax, ymax = fld.box
    pts = rng.uniform([xmin, ymin], [xmax, ymax], (3000, 2))
    regions = sampling.search_regions(fld, pts, 1.4)
    square = regions.halfwidth.max(axis=1)
    i, j = pairs_within_boxes(pts, 2.0 * square)
    i, j = np.concatenate([i, j]), np.concatenate([j, i])
    length = shortest_parabola(fld, pts[i], pts[j]).length
    close = length < 0.7
    assert close.sum() > 50
    d = pts[j[close]] - pts[i[close]]
    q = regions.quad[i[close]]
    inside = q[:, 0] * d[:, 0] ** 2 + 2 * q[:, 1] * d[:, 0] * d[:, 1] + q[:, 2] * d[:, 1] ** 2
    assert (inside <= 1.0).all()
    assert (np.abs(d) <= regions.halfwidth[i[close]]).all()
    # the ellipses' areas against the squares' (π/4 of the square where isotropic)
    det = regions.quad[:, 0] * regions.quad[:, 2] - regions.quad[:, 1] ** 2
    ratio = np.median(np.pi / np.sqrt(det) / (4 * square**2))
    assert ratio <= math.pi / 4 + 1e-9


class _TensorsOnly:
    """A field's tensors and box without its compiled code: the numpy paths."""

    kernel = None

    def __init__(self, field) -> None:
        self.field = field

    def __getattr__(self, name):
        return getattr(self.field, name)


@pytest.mark.parametrize("name", ["toy", "three_toys", "front", "concentric", "circular_layer"])
def test_compiled_search_regions_are_the_numpy_ones_bit_for_bit(name):
    # the kernel repeats the numpy path's operations on the same tensors (the union
    # of the size tensors sampled about each point, clipped to the box)
    fld = load_metric(METRICS / f"{name}.yaml")
    assert fld.kernel is not None
    rng = np.random.default_rng(12)
    xmin, ymin, xmax, ymax = fld.box
    pts = rng.uniform([xmin, ymin], [xmax, ymax], (4000, 2))
    pts[:100] = rng.uniform([xmin, ymin], [xmin + 0.01, ymax], (100, 2))  # at a side
    fast = sampling.search_regions(fld, pts, 1.4)
    ref = sampling.search_regions(_TensorsOnly(fld), pts, 1.4)
    np.testing.assert_array_equal(fast.halfwidth, ref.halfwidth)
    np.testing.assert_array_equal(fast.quad, ref.quad)
