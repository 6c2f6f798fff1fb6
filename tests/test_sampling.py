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
from curvimesh.metric import frame_turn, layer_sag, load_metric, load_metric_text

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
    bnd = discretize_box(fld, target=opt.step, min_dist=opt.min_dist)
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
    shot = sampling.shoot(fld, start, d, opt.step, tol=opt.shoot_tol)
    child, arrival = shot.end[shot.ok], shot.velocity[shot.ok]
    gc = fld.tensor(child)
    cdirs = sampling.principal_directions(gc)
    flags = sampling.backward(gc, cdirs, arrival)
    # at most one way back from each child (none where the frame turned more than 20°)
    assert flags.sum(axis=1).max() == 1 and flags.sum() > 0.9 * len(child)
    back, row = cdirs[flags], np.nonzero(flags)[0]
    again = sampling.shoot(fld, child[row], back, opt.step, tol=opt.shoot_tol)
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


@pytest.mark.parametrize("name", ["three_toys", "quartic2"])
def test_circumcentres_kept_from_the_last_round_are_computed_ones_bit_for_bit(name, monkeypatch):
    fld = load_metric(METRICS / f"{name}.yaml")
    opt = sampling.SamplingOptions()
    pts = sampling.sample_points(
        fld, discretize_box(fld, target=opt.step, min_dist=opt.min_dist), opt
    )
    tris = fill.metric_delaunay_of(fld, pts, fld.box).triangles
    keys = fill._source_keys(tris[:, :3], len(pts))
    half = np.arange(0, len(tris), 2)  # every other triangle known, with its own keys
    by_key = np.argsort(keys[half])
    centre, radius = fill.metric_circumcentres(fld, pts, tris)
    known = (keys[half][by_key], centre[half][by_key], radius[half][by_key])
    again = fill.circumcentres_again(fld, pts, tris, keys, known)
    np.testing.assert_array_equal(again[0], centre)
    np.testing.assert_array_equal(again[1], radius)
    # and the rounds of gap filling keep the same points when every round computes them all
    kept = fill.fill_gaps(fld, pts, opt)
    monkeypatch.setattr(
        fill, "circumcentres_again", lambda f, p, t, k, known: fill.metric_circumcentres(f, p, t)
    )
    np.testing.assert_array_equal(kept, fill.fill_gaps(fld, pts, opt))


@pytest.mark.parametrize("name", ["three_toys", "quartic2", "boundary_layer"])
def test_gap_filling_without_retesting_refused_candidates_is_the_same(name, monkeypatch):
    fld = load_metric(METRICS / f"{name}.yaml")
    opt = sampling.SamplingOptions()
    bnd = discretize_box(fld, target=opt.step, min_dist=opt.min_dist)
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


@settings(max_examples=200, deadline=None)
@given(
    st.floats(0.0, math.pi),
    st.floats(-3.0, 3.0),
    st.floats(0.0, 2 * math.pi),
    st.lists(st.integers(-3, 3), min_size=1, max_size=6),
)
def test_turned_directions_are_unit_and_60_degrees_apart_in_the_metric(
    angle, log_ratio, heading, turns
):
    # g = R diag(1, r²) Rᵀ is the identity in u = diag(1, r) Rᵀ x: there the
    # directions must be the unit vectors at 60° × turns counter-clockwise from ref
    r = math.exp(log_ratio)
    rot = rotation(angle)
    g = rot @ np.diag([1.0, r * r]) @ rot.T
    ref = rot @ (np.array([1.0, 1.0 / r]) * [math.cos(heading), math.sin(heading)]) * 0.3
    dirs = sampling.turned_directions(g[None], ref[None], tuple(turns))[0]
    u = np.array([1.0, r]) * (rot.T @ dirs.T).T
    want = [heading + math.radians(60.0 * t) for t in turns]
    np.testing.assert_allclose(u, np.column_stack([np.cos(want), np.sin(want)]), atol=1e-9)


CONSTANT = """domain: {box: [[0, 0], [1, 1]]}
metric:
  eigen:
    sizes: [0.05, 0.02]
    angle: 0.5
"""


def test_hexagons_sample_an_equilateral_lattice_in_a_constant_metric():
    # geodesics of a constant metric are straight: a point's children are at 0°
    # and ±60° in the metric, exactly ``step`` away, and the rows grown from a side
    # are the equilateral lattice of side 1 (six neighbours 1 away), up to the
    # seams where the lattices of two sides meet; the principal directions make
    # squares (four neighbours 0.98 away, the diagonals 1.39)
    fld = load_metric_text(CONSTANT)
    g = fld.tensor(np.zeros((1, 2)))[0]
    for hexagons, neighbours, share in ((True, 6, 0.75), (False, 4, 0.75)):
        opt = sampling.SamplingOptions(hexagons=hexagons)
        bnd = discretize_box(fld, target=opt.step, min_dist=opt.min_dist)
        pts = sampling.sample_points(fld, bnd, opt)
        d = pts[:, None, :] - pts[None, len(bnd.vertices) :, :]
        dist = np.sqrt(np.einsum("abi,ij,abj->ab", d, g, d))
        unit = (np.abs(dist - opt.step) < 0.05).sum(axis=0)
        assert unit.max() == neighbours
        assert (unit == neighbours).mean() >= share


CIRCLES = (
    "domain: {box: [[-0.5, -1], [1.5, 1]]}\n"
    "metric: {eigen: {sizes: [0.1, 0.005], angle: 'atan2(y, x - 0.5) + pi/2'}}\n"
)


def test_the_front_shoots_along_the_principal_directions_where_the_frame_turns_fast():
    # circles about (0.5, 0), tangential size 0.1 (20:1, above the anisotropy from
    # which frame_turn counts): a unit step along a circle of radius ρ turns the
    # frame by 0.1 / ρ, 14.3° at ρ = 0.4 (over HEX_MAX_TURN = 10°) and 7.2° at
    # ρ = 0.8 (also at the points one unit ahead, ρ = 0.80 ± 0.01)
    fld = load_metric_text(CIRCLES)
    front = np.array([[0.9, 0.0], [1.3, 0.0]])
    g = fld.tensor(front)
    arrival = np.array([[0.0, 0.1], [0.0, 0.1]])  # along the circles
    dirs, shots = sampling.front_directions(
        fld, front, arrival, arrival, sampling.FRONT_TURNS, hexagons=True
    )
    plain = sampling.principal_directions(g[:1])[0]
    np.testing.assert_array_equal(dirs[0], plain)
    np.testing.assert_array_equal(shots[0], ~sampling.backward(g[:1], plain[None], arrival[:1])[0])
    np.testing.assert_array_equal(shots[1], [True, True, True, False])
    hexa = sampling.turned_directions(g[1:], arrival[1:], sampling.FRONT_TURNS)[0]
    np.testing.assert_array_equal(dirs[1, :3], hexa)


def test_the_front_shoots_along_the_principal_directions_in_a_thin_layer_turning_slowly():
    # the circles above at 200:1 (radial size 0.0005): at ρ = 0.8 the frame still
    # turns 7.2° per unit, but a unit chord along the circle strays
    # 0.1² / (8 ρ 0.0005) = 3.1 radial sizes from it, over HEX_MAX_SAG; at 20:1,
    # 0.31, under it; with no bound on the sag (the default), the lattice either way
    thin = load_metric_text(CIRCLES.replace("0.005", "0.0005"))
    front = np.array([[1.3, 0.0]])
    arrival = np.array([[0.0, 0.1]])
    bound = sampling.HEX_MAX_SAG
    for fld, sag, max_sag, lattice in (
        (thin, 3.125, bound, False),
        (load_metric_text(CIRCLES), 0.3125, bound, True),
        (thin, 3.125, math.inf, True),
    ):
        g, dg = fld.evaluate(front, derivatives=True)
        assert math.isclose(float(layer_sag(g, dg)[0]), sag, rel_tol=1e-9)
        assert float(frame_turn(g, dg)[0]) < sampling.HEX_MAX_TURN
        dirs, _ = sampling.front_directions(
            fld, front, arrival, arrival, sampling.FRONT_TURNS, True, max_sag
        )
        if lattice:
            hexa = sampling.turned_directions(g, arrival, sampling.FRONT_TURNS)[0]
            np.testing.assert_array_equal(dirs[0, :3], hexa)
        else:
            np.testing.assert_array_equal(dirs[0], sampling.principal_directions(g)[0])


def test_the_look_ahead_sees_the_frame_turn_fast_one_step_inwards():
    # from ρ = 0.8 (7.2° per unit length), a step of 0.3 towards the centre ends at
    # ρ = 0.5 (11.5°), steps away from it at ρ = 0.85 and 1.05 (6.7°, 5.5°); outside
    # the box the turn counts as zero
    fld = load_metric_text(CIRCLES)
    start = np.array([[1.3, 0.0]])
    inwards = np.array([[[-0.3, 0.0], [0.05, 0.0]]])
    outwards = np.array([[[0.05, 0.0], [0.25, 0.0]]])
    assert not sampling.turns_slowly_ahead(fld, start, inwards)[0]
    assert sampling.turns_slowly_ahead(fld, start, outwards)[0]
    assert sampling.turns_slowly_ahead(fld, np.array([[1.45, 0.0]]), outwards)[0]


CIRCULAR_2500 = """
domain: {box: [[0, 0], [1, 1]]}
definitions:
  r: sqrt((x - 0.5)**2 + (y - 0.5)**2)
metric:
  eigen:
    sizes: ['min(0.00004 + 0.25*abs(r - 0.3), 0.1)', 0.1]
    angle: atan2(y - 0.5, x - 0.5)
"""


def test_closeness_in_a_thin_curved_layer_agrees_with_the_full_search():
    """In a circular layer of 2,500:1 (4e-5 across at radius 0.3, growing 0.25 a unit of
    distance) the length of the parabola between two points 2e-4 or 4e-4 outside the
    circle and 0.024 - 0.05 apart along it has a valley a few thousandths wide in α,
    where the parabola follows the layer; the closeness verdict, which stops its search
    early, must agree with the search run to its end. With brackets 0.1 wide trusted
    for a verdict it called all 72 pairs far (the sampled cloud held pairs 0.25 apart)."""
    from curvimesh.geodesic import shortest_parabola

    fld = load_metric_text(CIRCULAR_2500)
    angles = np.linspace(0.1, 6.2, 12)
    for offset in (2e-4, 4e-4):
        for chord in (0.024, 0.035, 0.05):
            r, turn = 0.3 + offset, chord / 0.3
            a = 0.5 + r * np.column_stack([np.cos(angles), np.sin(angles)])
            b = 0.5 + r * np.column_stack([np.cos(angles + turn), np.sin(angles + turn)])
            full = shortest_parabola(fld, a, b).length
            assert (full < 0.7).all()
            assert sampling.too_close(fld, a, b, 0.7).all()
    far = 0.5 + 0.3 * np.column_stack([np.cos(angles + 0.5), np.sin(angles + 0.5)])
    assert (shortest_parabola(fld, a, far).length > 0.7).all()
    assert not sampling.too_close(fld, a, far, 0.7).any()


def test_closeness_in_a_valley_narrower_than_the_tolerance_agrees_with_a_dense_scan():
    """Two points within 5e-5 of the circle of the same layer (inside, outside, or
    one of each), 0.045 - 0.065 apart along it: the parabola's length dips under
    0.7 in a valley about 0.001 wide in α (1.17, 0.60, 1.18 at α = 0.0180, 0.0185,
    0.0190 for a pair of seed 1's cloud), narrower than the search's tolerance of
    0.002. Stopped there, the search called 36 of these 90 pairs far (the cloud of
    seed 1 kept pairs 0.55 - 0.66 apart). The verdict must be that of the same
    rule's length minimised over a grid of α 5e-6 apart."""
    from curvimesh.geodesic import parabola_length_rule, parabola_midnode

    fld = load_metric_text(CIRCULAR_2500)
    angles = np.linspace(0.3, 6.0, 6)
    alphas = np.linspace(-0.05, 0.05, 20_001)
    a_all, b_all = [], []
    for off_a, off_b in ((2e-5, 5e-6), (-3e-5, -3e-5), (-2e-5, -4e-6), (1e-5, 3e-5), (5e-5, 5e-5)):
        for chord in (0.045, 0.055, 0.065):
            turn = angles + chord / 0.3
            a_all.append(0.5 + (0.3 + off_a) * np.column_stack([np.cos(angles), np.sin(angles)]))
            b_all.append(0.5 + (0.3 + off_b) * np.column_stack([np.cos(turn), np.sin(turn)]))
    a, b = np.concatenate(a_all), np.concatenate(b_all)
    scanned = np.empty(len(a))
    for i in range(len(a)):
        x0, x1 = np.repeat(a[i : i + 1], len(alphas), 0), np.repeat(b[i : i + 1], len(alphas), 0)
        scanned[i] = parabola_length_rule(fld, x0, x1, parabola_midnode(x0, x1, alphas)).min()
    close = scanned < 0.7
    assert 20 <= close.sum() <= len(a) - 20  # both verdicts are tested
    assert (sampling.too_close(fld, a, b, 0.7) == close).all()
