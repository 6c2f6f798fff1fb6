"""The adapt pipeline: sample | triangulate | curve | swap, as library calls.

Every stage takes and returns a :class:`~curvimesh.mesh.Mesh` (a point cloud
for ``sample``), so that the CLI can run them alone, chained through files or
pipes, or all at once in :func:`adapt`, with the same result byte for byte
(where :func:`adapt` made a further run and kept that mesh, the chain with that
run's sampling options, ``sample --no-rows``, ``--max-sag 0.5``, ``--no-hexagons``
or ``--seed``, gives it).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from curvimesh import curve as _curve
from curvimesh import swap as _swap
from curvimesh.bend import bend_nodes
from curvimesh.boundary import discretize_box
from curvimesh.charts import chart_flips
from curvimesh.cores import layer_cores
from curvimesh.errors import InputError
from curvimesh.fill import fill_gaps
from curvimesh.fit import fit_nodes
from curvimesh.insert import insert_points
from curvimesh.intrinsic import intrinsic_flips
from curvimesh.mesh import Mesh
from curvimesh.metric import UNIT_TRIANGLE_AREA, MetricField, density_integral
from curvimesh.quality import fixed_rule_lengths, fixed_rule_measures
from curvimesh.recurve import recurve
from curvimesh.remove import remove_vertices
from curvimesh.rows import layer_rows
from curvimesh.sampling import CORE_SPACING, HEX_MAX_SAG, SamplingOptions, sample_points
from curvimesh.shift import shift_vertices
from curvimesh.smooth import relocate
from curvimesh.split import split_long_edges
from curvimesh.triangulate import delaunay, metric_delaunay_of

#: Default bound on the vertex count (SPEC: ``--max-vertices``).
MAX_VERTICES = 2_000_000

Progress = Callable[[str], None]


def _quiet(_: str) -> None:
    return None


@dataclass(frozen=True)
class AdaptOptions:
    """Options of the whole pipeline."""

    seed: int = 0
    sampling: SamplingOptions = field(default_factory=SamplingOptions)
    max_vertices: int = MAX_VERTICES
    max_swap_rounds: int = 200
    hexagons: bool = True
    cores: bool = True
    fill: bool = True
    straight: bool = False
    relocate: bool = True
    charts: bool = True
    intrinsic: bool = True
    insert: bool = True
    split: bool = True
    recurve: bool = True
    length_swaps: bool = True
    shift: bool = True
    remove: bool = True
    repeat: bool = True
    bend: bool = True
    fit: bool = True
    retry: bool = True
    rows: bool = True


#: The stages beyond the paper's method, by their :class:`AdaptOptions` field, in
#: pipeline order: the first four build and triangulate the point cloud, the others
#: (:data:`SWAP_STAGES`) run in the swap stage.
STAGES = (
    "hexagons",
    "cores",
    "fill",
    "relocate",
    "charts",
    "intrinsic",
    "insert",
    "split",
    "recurve",
    "length_swaps",
    "shift",
    "remove",
    "repeat",
    "bend",
    "fit",
)

#: The stages run by the swap stage (:func:`swap`).
SWAP_STAGES = STAGES[4:]


#: A run of :func:`adapt` whose mesh keeps an edge longer than this (the longest edge
#: issue 7 allows) is made again, differently (:func:`retries`, ``options.retry``).
RETRY_ABOVE = 1.5

#: A run whose curved mesh (stage 3) has more than this share of its edges longer
#: than :data:`RETRY_ABOVE` (:func:`long_share`) has its swap stage put off when
#: another run follows (:func:`adapt`): the clean-up stages mend local defects,
#: and so many long edges say that the point cloud itself is wrong. Measured on the
#: first runs of 83 metrics at seed 0 (the 11 examples, ``bench/robustness`` and 19
#: thin layers and fronts of 100:1 to 5,000:1) and of the closest ones at seeds 0 –
#: 7: every run that ended within 1.5 had at most 8.4 % (``metrics/hard/tight_front``,
#: 80° per unit, seed 0; the examples at most 6.6 %); the tight front's other seeds
#: had 8.4 – 9.6 % and ended with edges of 1.46 – 8.3 (its later runs mend most), and
#: the thin circular and elliptic layers that fail had 12 – 37 % and ended with
#: edges of 4.2 – 34 after swap stages of 14 – 114 s.
PUT_OFF_SHARE = 0.10

#: Runs with other sampling seeds made when no run of the given seed leaves its edges
#: within :data:`RETRY_ABOVE` (:func:`adapt`), and the stride between their seeds (the
#: seeds 0 – 2 a batch may use stay apart from each other's retries). Each costs a
#: curved mesh where it is dropped (about 1 – 2 s on the thin layers of
#: ``bench/robustness``), a whole run where it is not.
SEED_RETRIES = 3
SEED_STRIDE = 1000

#: The shortest-parabola searches the vertex shifts of one swap stage may make in all,
#: per vertex of the mesh (:func:`curvimesh.shift.shift_vertices`, ``max_searches``).
#: Measured on the examples (seeds 0 – 4) and on the robustness metrics that search
#: most (seeds 0 and 3): at most 782 (front, seed 2); on a front turning 180° per unit
#: length (x = 0.5 + 0.25 cos 4πy, seed 3), 4,369, the shifts taking 135 of its 146 s
#: for 758 vertices and edges left up to 4.85.
SHIFT_SEARCHES_PER_VERTEX = 1000


def estimated_vertices(metric_area: float) -> float:
    """Vertices of an ideal unit mesh: half its triangle count, metric_area / (√3/4) / 2."""
    return metric_area / UNIT_TRIANGLE_AREA / 2.0


def check_size(fld: MetricField, max_vertices: int) -> float:
    """Fail fast when the ideal mesh would exceed ``max_vertices``; return the metric area."""
    area = density_integral(fld, cells=64, rtol=1e-2)  # a bound, not a figure
    est = estimated_vertices(area)
    if est > max_vertices:
        raise InputError(
            f"{fld.source}: the metric asks for about {est:,.0f} vertices, more than "
            f"--max-vertices {max_vertices:,}"
        )
    return area


def sample(fld: MetricField, options: AdaptOptions | None = None) -> Mesh:
    """Stage 1: boundary discretisation, Algorithm 1 and gap filling; a point cloud on the box."""
    opt = options or AdaptOptions()
    sopt = replace(opt.sampling, hexagons=opt.hexagons, cores=opt.cores)
    boundary = discretize_box(fld, target=sopt.step, min_dist=sopt.min_dist)
    rows = (
        layer_rows(fld, CORE_SPACING * sopt.step, sopt.step) if sopt.rows and sopt.cores else None
    )
    pts = sample_points(fld, boundary, sopt, seed=opt.seed, rows=rows)
    if opt.fill:
        pts = fill_gaps(fld, pts, sopt)
    return Mesh(pts, np.zeros((0, 3), dtype=np.int64), fld.box)


def triangulate(
    points: Mesh, fld: MetricField | None = None, options: AdaptOptions | None = None
) -> Mesh:
    """Stage 2: Delaunay triangulation of the nodes of a point cloud (or of any mesh).

    With a metric, the Euclidean Delaunay triangulation is then flipped to
    the Delaunay triangulation in the metric
    (:func:`curvimesh.triangulate.metric_delaunay`) and,
    unless ``options.relocate`` is off, its vertices are relocated
    (:func:`curvimesh.smooth.relocate`).
    """
    if fld is None:
        return delaunay(np.asarray(points.points), box=points.box)
    mesh = metric_delaunay_of(fld, np.asarray(points.points), points.box)
    opt = options or AdaptOptions()
    if opt.relocate:
        mesh = relocate(fld, mesh, min_dist=opt.sampling.min_dist)
    return mesh


def curve(fld: MetricField, mesh: Mesh, options: AdaptOptions | None = None) -> Mesh:
    """Stage 3: P2 edge nodes on geodesic parabolas, backtracked to validity."""
    opt = options or AdaptOptions()
    return _curve.curve(fld, mesh, straight=opt.straight)


@dataclass(frozen=True)
class SwapStage:
    """The mesh after the swap stage, and its counts of swaps, insertions, splits,
    swap rounds, re-curved edge nodes, node moves fitting an interpolation metric's
    function, vertex shifts, vertex removals, intrinsic flips, edges the chart flips
    made, repeated passes of the clean-up stages and edge nodes bent for quality."""

    mesh: Mesh
    swaps: int
    splits: int
    rounds: int
    inserted: int = 0
    recurved: int = 0
    fitted: int = 0
    bent: int = 0
    shifted: int = 0
    removed: int = 0
    flips: int = 0
    chart_edges: int = 0
    chart_triangles: int = 0
    passes: int = 0
    searched: int = 0
    defects: Defects | None = None  # the final mesh's, when the repeated passes measured them
    # the unit mesh's (before the fit trades its lengths for the error of the function)
    unit_defects: Defects | None = None

    def counts(self) -> str:
        """What the stage did, in one line."""
        return (
            f"{self.chart_triangles} triangles made in layer charts, "
            f"{self.chart_edges} edges flipped in layer charts, {self.flips} intrinsic flips, "
            f"{self.swaps} swaps in {self.rounds} rounds, {self.inserted} insertions, "
            f"{self.splits} splits, {self.recurved} re-curved nodes, {self.shifted} shifts, "
            f"{self.removed} removals, {self.passes} repeated passes, "
            f"{self.bent} bent nodes, {self.fitted} fitting moves"
        )


#: Length above which an edge left at the end of the swap stage is re-curved once
#: more, towards its shortest parabola with a free node where that is shorter
#: (:func:`curvimesh.recurve.optimal_nodes`): the top of the unit range.
FREE_FROM = 1.4

#: Most passes of (swaps, re-curving) at the end of the swap stage; a pass after the
#: first runs only when the re-curving before it moved a node.
RECURVE_PASSES = 3

#: Most repeated passes of the clean-up stages (``options.repeat``).
REPEAT_PASSES = 2


@dataclass
class _Tally:
    """The counts of the swap stage, added up over its passes."""

    swaps: int = 0
    rounds: int = 0
    splits: int = 0
    inserted: int = 0
    recurved: int = 0
    shifted: int = 0
    removed: int = 0
    searched: int = 0  # the vertex shifts' shortest-parabola searches

    def changes(self) -> int:
        """Every change made so far (a pass that adds none changed nothing)."""
        return (
            self.swaps + self.splits + self.inserted + self.recurved + self.shifted + self.removed
        )


def swap(fld: MetricField, mesh: Mesh, options: AdaptOptions | None = None) -> SwapStage:
    """Stage 4: (unless ``options.charts`` is off) the edges of thin curved layers
    flipped to the Delaunay triangulation of each layer's own coordinates, with the
    edge nodes those give (:mod:`curvimesh.charts`); (unless ``options.intrinsic`` is
    off) intrinsic Delaunay flips where the metric's frame turns fast
    (:mod:`curvimesh.intrinsic`), curvilinear edge
    swaps driven by quality (4), then the clean-up stages: (unless ``options.insert``
    is off) vertex insertions into the cavities of the long curved edges
    (:mod:`curvimesh.insert`), (unless ``options.split`` is off)
    splits of the long edges left at their nodes (:mod:`curvimesh.split`), and
    the last swaps: driven by quality and (unless ``options.length_swaps`` is off)
    edge lengths (:func:`curvimesh.swap.swap`), alternating (unless
    ``options.recurve`` is off) with edge nodes moved back towards their shortest
    parabolas (:mod:`curvimesh.recurve`) until a re-curving moves nothing, at most
    :data:`RECURVE_PASSES` times; then (unless ``options.shift`` is off) end
    vertices of the edges still longer than 1.4 and of the triangles of quality
    below 0.3 moved (:mod:`curvimesh.shift`); then (unless ``options.remove`` is
    off) vertices of the triangles still below 0.3 and of the edges still longer
    than 1.4 removed (:mod:`curvimesh.remove`). Then (unless ``options.repeat`` is
    off), while edges longer than 1.4 or triangles of quality below 0.3 are left,
    at most :data:`REPEAT_PASSES` times:
    the last swaps again, on the mesh that the shifts and removals changed, and
    the clean-up stages again (see :func:`repeat_passes`). Then (unless
    ``options.bend`` is off) the nodes of the edges of the triangles still below
    quality 0.8 bent off their parabolas where that raises the worse quality of
    their two triangles (:mod:`curvimesh.bend`). Then (unless ``options.recurve`` is off) the
    nodes of the edges still longer than :data:`FREE_FROM` re-curved once more, from
    where they are towards the shortest parabola with a free middle node
    (:func:`curvimesh.recurve.optimal_nodes`). Last,
    when the metric is an ``interpolation``
    form (and unless ``options.fit`` is off), edge nodes moved to lower the
    interpolation error of its function (:mod:`curvimesh.fit`).

    The swaps for lengths and the re-curving come last, on the mesh that the
    insertions and splits leave: run before them, they change the long edges
    that insertion works on and the positions it tries, and it then fails
    where it succeeded (the longest edge of quartic, seed 1, 1.70 → 1.99).
    """
    opt = options or AdaptOptions()
    flips = chart_edges = chart_triangles = 0
    if opt.charts and not opt.straight:
        cr = chart_flips(fld, mesh)
        mesh, chart_edges, chart_triangles = cr.mesh, cr.edges, cr.rebuilt
    if opt.intrinsic and not opt.straight:
        fl = intrinsic_flips(fld, mesh)
        mesh, flips = fl.mesh, fl.flips
    res = _swap.swap(fld, mesh, max_rounds=opt.max_swap_rounds, straight=opt.straight)
    mesh = res.mesh
    tally = _Tally(swaps=res.swaps, rounds=res.rounds)
    if opt.straight:
        return SwapStage(mesh, **vars(tally))
    mesh = _clean_up(fld, mesh, opt, tally)
    passes = 0
    found = None
    if opt.repeat:
        mesh, passes, found = repeat_passes(fld, mesh, opt, tally)
    bent = 0
    if opt.bend:
        known = None if found is None else (found.lengths, found.qualities)
        br = bend_nodes(fld, mesh, min_dist=opt.sampling.min_dist, measured=known)
        mesh, bent = br.mesh, br.bent
    freed = 0
    if opt.recurve:
        rc = recurve(fld, mesh, longer_than=FREE_FROM, free_from=FREE_FROM, from_node=True)
        mesh, freed = rc.mesh, rc.moved
        tally.recurved += freed
    if bent or freed:
        found = None  # measured before the nodes moved
    unit = found  # the unit mesh's, which the fit (a trade, by design) leaves behind
    fitted = 0
    function = fld.error_function
    if opt.fit and function is not None:
        unit = defects(fld, mesh) if unit is None else unit
        fr = fit_nodes(function, mesh)
        mesh, fitted = fr.mesh, fr.moves
    if fitted:
        found = None
    return SwapStage(
        mesh, fitted=fitted, bent=bent, flips=flips, chart_edges=chart_edges,
        chart_triangles=chart_triangles, passes=passes,
        defects=found, unit_defects=unit, **vars(tally),
    )  # fmt: skip


def _clean_up(fld: MetricField, mesh: Mesh, opt: AdaptOptions, tally: _Tally) -> Mesh:
    """Insertions, splits, the last swaps, shifts and removals (see :func:`swap`),
    each unless its option is off; counts added to ``tally``."""
    inserted = splits = 0
    if opt.insert:
        ins = insert_points(fld, mesh, min_dist=opt.sampling.min_dist)
        mesh, inserted = ins.mesh, ins.inserted
    if opt.split:
        sp = split_long_edges(fld, mesh, min_dist=opt.sampling.min_dist)
        mesh, splits = sp.mesh, sp.splits
    tally.inserted += inserted
    tally.splits += splits
    if inserted or splits or opt.length_swaps or opt.recurve:
        mesh = _last_swaps(fld, mesh, opt, tally)
    if opt.shift:
        budget = max(SHIFT_SEARCHES_PER_VERTEX * len(mesh.vertex_ids) - tally.searched, 0)
        sh = shift_vertices(fld, mesh, min_dist=opt.sampling.min_dist, max_searches=budget)
        mesh, tally.shifted = sh.mesh, tally.shifted + sh.shifted
        tally.searched += sh.searched
    if opt.remove:
        rm = remove_vertices(fld, mesh, min_dist=opt.sampling.min_dist)
        mesh, tally.removed = rm.mesh, tally.removed + rm.removed
    return mesh


@dataclass(frozen=True)
class Defects:
    """What the clean-up stages work on: the edges longer than 1.4 and the
    triangles of quality (4) below 0.3, and the mesh's extreme figures."""

    long_edges: int
    flat_triangles: int
    min_length: float
    max_length: float
    min_quality: float
    # the measures behind the figures: edge lengths and qualities by the loops' fixed rules
    lengths: np.ndarray | None = field(default=None, repr=False, compare=False)
    qualities: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def count(self) -> int:
        return self.long_edges + self.flat_triangles

    def worse_than(
        self, other: Defects, *, min_length: float = 0.7, min_quality: float = 0.3
    ) -> bool:
        """Whether these figures are worse than ``other``'s: a new edge below
        ``min_length``, a longer longest edge, a lower worst quality (unless the
        longest edge got shorter and the worst quality stays at least
        ``min_quality``), or, with the same extremes, more defects.

        >>> old = Defects(3, 0, 0.70, 1.60, 0.40)
        >>> Defects(5, 0, 0.70, 1.45, 0.40).worse_than(old)  # more, but shorter
        False
        >>> Defects(1, 0, 0.65, 1.45, 0.40).worse_than(old)  # a short edge made
        True
        >>> Defects(4, 0, 0.70, 1.60, 0.40).worse_than(old)  # same extremes, more
        True
        >>> Defects(1, 0, 0.70, 1.45, 0.35).worse_than(old)  # shorter, quality above 0.3
        False
        >>> Defects(1, 1, 0.70, 1.45, 0.25).worse_than(old)  # shorter, quality below 0.3
        True
        """
        if self.min_length < min(min_length, other.min_length):
            return True
        if self.max_length > other.max_length:
            return True
        if self.min_quality < other.min_quality:
            return not (self.max_length < other.max_length and self.min_quality >= min_quality)
        same = self.max_length == other.max_length and self.min_quality == other.min_quality
        return same and self.count > other.count


def defects(
    fld: MetricField, mesh: Mesh, *, max_length: float = 1.4, min_quality: float = 0.3
) -> Defects:
    """The :class:`Defects` of a P2 ``mesh``: its edges longer than ``max_length`` in the
    metric (lengths of the curved edges) and its triangles below ``min_quality``."""
    length, q = fixed_rule_measures(fld, mesh)
    return Defects(
        int((length > max_length).sum()),
        int((q < min_quality).sum()),
        float(length.min()),
        float(length.max()),
        float(q.min()),
        length,
        q,
    )


def repeat_passes(
    fld: MetricField, mesh: Mesh, opt: AdaptOptions, tally: _Tally
) -> tuple[Mesh, int, Defects]:
    """The last swaps and the clean-up stages again, while :func:`defects` finds
    edges longer than 1.4 or triangles below quality 0.3, at most
    :data:`REPEAT_PASSES` times; the mesh, the passes kept and the mesh's defects.

    Beyond the paper. The shifts and removals change the edges and triangles
    around the defects they work on, and no swap runs after them: a swap they
    made possible is left undone (quartic2, seed 2: an edge of 2.76 whose
    swap to 1.18 became valid after a shift). A pass that changes nothing ends
    the repeats; one whose mesh is worse (:meth:`Defects.worse_than`) is
    dropped, and ends them too.
    """
    passes = 0
    found = defects(fld, mesh)
    while passes < REPEAT_PASSES and found.count > 0:
        trial = replace(tally)  # the pass counts into a copy, kept with its mesh
        new = _clean_up(fld, _last_swaps(fld, mesh, opt, trial), opt, trial)
        if trial.changes() == tally.changes():
            break
        now = defects(fld, new)
        if now.worse_than(found, min_length=opt.sampling.min_dist):
            break
        vars(tally).update(vars(trial))
        mesh, found, passes = new, now, passes + 1
    return mesh, passes, found


def _last_swaps(fld: MetricField, mesh: Mesh, opt: AdaptOptions, tally: _Tally) -> Mesh:
    """The last swaps, alternating with re-curving (see :func:`swap`); counts added to
    ``tally``."""
    for _ in range(RECURVE_PASSES):
        res = _swap.swap(fld, mesh, max_rounds=opt.max_swap_rounds, length_rule=opt.length_swaps)
        mesh = res.mesh
        tally.swaps, tally.rounds = tally.swaps + res.swaps, tally.rounds + res.rounds
        if not opt.recurve:
            break
        rc = recurve(fld, mesh)
        mesh, tally.recurved = rc.mesh, tally.recurved + rc.moved
        if rc.moved == 0:
            break
    return mesh


@dataclass(frozen=True)
class AdaptResult:
    """The adapted mesh, the swap count and the seconds of every stage."""

    mesh: Mesh
    swaps: int
    seconds: dict[str, float]
    metric_area: float


def adapt(
    fld: MetricField, options: AdaptOptions | None = None, *, progress: Progress = _quiet
) -> AdaptResult:
    """All stages in one process; then (unless ``options.retry`` is off), while the mesh
    keeps an edge longer than :data:`RETRY_ABOVE` and the hexagonal lattice was on, all
    stages again (:func:`retries`): with the thin curved layers sampled by the fronts
    (where the field has any, which the first run samples row by row:
    :func:`first_run`), with the lattice kept out of those layers, then without it;
    the mesh with the shortest longest edge is kept (the earlier on a
    tie). The seconds of every stage add up all runs. For an ``interpolation``
    metric the edges are judged before the fit (:mod:`curvimesh.fit`), which trades
    their unit lengths for the function's error: judged after it, an unseen tanh ring
    of 2,000 vertices was meshed twice for nothing (edges of 1.52 left by the fit, 1.398
    at most before it, in both runs).

    Beyond the paper. The lattice (:mod:`curvimesh.sampling`) is laid where the
    metric's directions turn slowly; beside a front that turns fast nearby, the
    seam between it and the points shot along the principal directions can leave
    cavities that no clean-up stage mends. Measured on ``metrics/hard/tight_front``
    (80° per unit length) at seeds 0 – 7: with the lattice, 1 of 8 meshes within
    1.4 (edges up to 8.3 in the others); without it, 6 of 8 (2.31 in the other two).
    In a thin layer that curves slowly the lattice's rows stray across the layer
    (:data:`curvimesh.sampling.HEX_MAX_SAG`), and keeping it out of such layers alone
    mends what leaving it out everywhere did at 1.16 – 1.18 times the ideal triangle
    count. Like Gmsh's ``Mesh.AlgorithmSwitchOnFailure``, another method where the
    first fails. The swap stage of a run that another follows is put off when more
    than :data:`PUT_OFF_SHARE` of its curved edges are longer than
    :data:`RETRY_ABOVE`, and made only if no run leaves its edges within it (the
    longest clean-up stages are those of such runs, which fail); the last run is
    always finished. A run whose curved mesh is an earlier run's (the sag bound
    kept the lattice out of no layer) makes no swap stage: its result would be the
    earlier's, which a tie keeps. A run that samples thin curved layers row by row
    always makes its swap stage: its curved mesh joins their rows by chords (on
    ``u45``, 40 % of its curved edges are longer than 1.5), which the swap stage's
    first step triangulates again (:func:`curvimesh.charts.rebuilt`).

    When no run of the given seed ends within :data:`RETRY_ABOVE`, the same runs are
    made with other sampling seeds (:func:`_seed_retries`), before the swap stages
    put off: one whose curved mesh has more than :data:`PUT_OFF_SHARE` of its edges
    longer than :data:`RETRY_ABOVE` is dropped (the given seed's runs remain to fall
    back on), and the first that ends within it ends them. In a thin curved layer the
    columns of points across it, and where they meet, depend on the order in which
    each front's points are taken (the seed): on the circular layer of 5,000:1 of
    ``bench/robustness`` (``u52``) seeds 0 and 3 end within 1.5 and seeds 1 and 2 do
    not, and ``metrics/hard/tight_front`` at seed 3 kept an edge of 1.78 in all three
    runs of its seed (1.441 with seed 1003).
    """
    opt = first_run(options or AdaptOptions(), fld)
    if not (opt.retry and opt.hexagons and not opt.straight):
        return _run(fld, opt, progress)[0]
    runs: list[tuple[str, AdaptOptions]] = []
    done: list[tuple[float, int, AdaptResult]] = []  # (longest edge, run, result)
    put_off: list[tuple[int, AdaptResult]] = []  # (run, its curved mesh)
    curves: list[Mesh] = []
    seconds: dict[str, float] = {}

    def longest() -> float:
        return min((d[0] for d in done), default=np.inf)

    def finish(i: int, curved: AdaptResult) -> None:
        run, found = _finish(fld, runs[i][1], curved, progress)
        seconds["swap"] += run.seconds["swap"]
        done.append((_longest(fld, run, found), i, run))

    def attempt(label: str, again: AdaptOptions, long_curved: str) -> None:
        """One run: its curved mesh, then, unless it is an earlier run's, its swap
        stage, put off (``long_curved`` "put off") or the run dropped ("drop") when too
        many of its curved edges are long (or neither: "finish")."""
        i = len(runs)
        runs.append((label, again))
        if again.sampling.rows:  # the charts stage triangulates its layers again
            long_curved = "finish"
        if i:
            left = f"an edge of {longest():.2f} is left: " if done else ""
            progress(f"{left}all stages again {label}")
        curved = _curved(fld, again, progress)
        for k, v in curved.seconds.items():
            seconds[k] = seconds.get(k, 0.0) + v
        twin = next(
            (j for j, c in enumerate(curves) if _same(c, curved.mesh, runs[j][1], again)), None
        )
        curves.append(curved.mesh)
        if twin is not None:  # the same stages on the same mesh: the same result
            progress(f"the curved mesh is that of run {twin + 1}: its swap stage is not made")
            return
        share = long_share(fld, curved.mesh)
        if long_curved != "finish" and share > PUT_OFF_SHARE:
            what = "the swap stage is put off" if long_curved == "put off" else "the run is dropped"
            progress(f"{share:.1%} of the curved edges are longer than {RETRY_ABOVE}: {what}")
            if long_curved == "put off":
                put_off.append((i, curved))
            return
        finish(i, curved)

    # the given seed's runs, the last always finished; then the other seeds', which
    # fall back on them
    own = [("", opt), *retries(opt, fld)]
    plan = [(label, again, "put off") for label, again in own[:-1]]
    plan.append((*own[-1], "finish"))
    for seeded in _seed_retries(opt):
        for label, again in [("", seeded), *retries(seeded, fld)]:
            joined = f" and {label.removeprefix('with ')}" if label else ""
            plan.append((f"with sampling seed {seeded.seed}{joined}", again, "drop"))
    for label, again, long_curved in plan:
        if not longest() > RETRY_ABOVE:
            break
        attempt(label, again, long_curved)
    if longest() > RETRY_ABOVE:  # none within 1.5: finish all
        for i, curved in put_off:
            progress(f"the swap stage put off: run {i + 1} of {len(runs)}")
            finish(i, curved)
    _, i, kept = min(done, key=lambda d: (d[0], d[1]))
    if i:
        progress(f"kept the mesh {runs[i][0]}")
    return AdaptResult(kept.mesh, kept.swaps, seconds, kept.metric_area)


def first_run(opt: AdaptOptions, fld: MetricField) -> AdaptOptions:
    """The options of :func:`adapt`'s first run: ``opt``, with the thin curved layers
    sampled row by row (:mod:`curvimesh.rows`) where the field has any
    (:func:`curvimesh.cores.layer_cores`) and ``opt.rows`` and ``opt.cores`` are on
    (not for straight-sided meshes).

    Row by row, a layer's points lie on rows of its chart, which
    :func:`curvimesh.charts.rebuilt` triangulates in the chart; sampled by the fronts,
    its columns end every other one where the rows thin out, and the chart's
    triangulation of those points is not kept. Measured on the 25 fields of
    ``bench/robustness`` and ``metrics/`` with cores (seed 0, one run each): 14 give
    the same figures either way; the row-by-row run meets every target where the other
    leaves edges of 1.48 (``u72``), 7.3 (``u56``: 1.69 row by row) and 15.7
    (``u58``), and takes fewer triangles on six circular layers (``u45`` 1.106 →
    1.016 times the ideal count); on ``u74`` both runs leave long edges (8.7 row by
    row, 5.7 not), which the later runs mend."""
    if opt.rows and opt.cores and not opt.straight and not opt.sampling.rows and layer_cores(fld):
        return replace(opt, sampling=replace(opt.sampling, rows=True))
    return opt


def retries(opt: AdaptOptions, fld: MetricField | None = None) -> list[tuple[str, AdaptOptions]]:
    """The runs :func:`adapt` makes after ``opt``'s, in order, while an edge longer than
    :data:`RETRY_ABOVE` is left, each with what it says of itself: where ``opt``
    samples the thin curved layers of the field ``fld`` row by row
    (:func:`first_run`), with them sampled by the fronts like the rest; then with the
    hexagonal lattice kept out of thin curved layers (``max_sag``
    :data:`HEX_MAX_SAG`, unless ``opt`` bounds it already), then without the
    lattice."""
    runs = []
    if fld is not None and opt.rows and opt.sampling.rows and layer_cores(fld):
        fronts = replace(opt, sampling=replace(opt.sampling, rows=False))
        runs.append(("with the thin curved layers sampled by the fronts", fronts))
    if not opt.sampling.max_sag <= HEX_MAX_SAG:
        bounded = replace(opt, sampling=replace(opt.sampling, max_sag=HEX_MAX_SAG))
        runs.append(("with the hexagonal lattice kept out of thin curved layers", bounded))
    runs.append(("without the hexagonal lattice", replace(opt, hexagons=False)))
    return runs


def _seed_retries(opt: AdaptOptions) -> list[AdaptOptions]:
    """The options of the runs with other sampling seeds that :func:`adapt` makes when
    no run of ``opt``'s seed leaves its edges within :data:`RETRY_ABOVE`: seeds
    ``opt.seed`` + k :data:`SEED_STRIDE`, k = 1 … :data:`SEED_RETRIES`."""
    return [replace(opt, seed=opt.seed + k * SEED_STRIDE) for k in range(1, SEED_RETRIES + 1)]


def long_share(fld: MetricField, mesh: Mesh) -> float:
    """The share of a P2 mesh's edges longer than :data:`RETRY_ABOVE` (the optimisation
    loops' rule of two segments, :func:`curvimesh.quality.fixed_rule_lengths`, which
    the swap stage measures the same edges with first)."""
    if len(mesh.edges) == 0:
        return 0.0
    length = fixed_rule_lengths(fld, mesh)
    return float(np.count_nonzero(length > RETRY_ABOVE)) / len(length)


def _longest(fld: MetricField, run: AdaptResult, found: Defects | None) -> float:
    """The longest edge of a run's unit mesh: from the defects its swap stage measured,
    else measured now (the final mesh: without a fit, the unit mesh)."""
    return (found if found is not None else defects(fld, run.mesh)).max_length


def _run(
    fld: MetricField, opt: AdaptOptions, progress: Progress
) -> tuple[AdaptResult, Defects | None]:
    """The stages of :func:`adapt`, once; the result and the defects of its unit mesh
    (before the fit, which trades lengths for the function's error, when there is one)
    where the swap stage measured them."""
    return _finish(fld, opt, _curved(fld, opt, progress), progress)


def _curved(fld: MetricField, opt: AdaptOptions, progress: Progress) -> AdaptResult:
    """Stages 1 – 3 of a run: the curved mesh, swaps −1 and 0 ``swap`` seconds."""
    seconds: dict[str, float] = {}
    t = time.perf_counter()
    area = check_size(fld, opt.max_vertices)
    progress(f"metric area {area:.1f}: about {estimated_vertices(area):,.0f} vertices")
    cloud = sample(fld, opt)
    seconds["sample"] = time.perf_counter() - t
    progress(f"sample: {len(cloud.points)} points ({seconds['sample']:.1f} s)")
    t = time.perf_counter()
    p1 = triangulate(cloud, fld, opt)
    seconds["triangulate"] = time.perf_counter() - t
    progress(f"triangulate: {len(p1.triangles)} triangles ({seconds['triangulate']:.1f} s)")
    t = time.perf_counter()
    p2 = curve(fld, p1, opt)
    seconds["curve"] = time.perf_counter() - t
    progress(f"curve: done ({seconds['curve']:.1f} s)")
    return AdaptResult(p2, -1, {**seconds, "swap": 0.0}, area)


def _same(a: Mesh, b: Mesh, opt_a: AdaptOptions, opt_b: AdaptOptions) -> bool:
    """Whether two curved meshes have the same nodes and triangles, bit for bit, and
    their runs the same options but those of the sampling's lattice (``hexagons``,
    ``sampling.max_sag``, which the swap stage does not read): the same swap stage."""

    def stage4(o: AdaptOptions) -> AdaptOptions:
        return replace(o, hexagons=True, sampling=replace(o.sampling, max_sag=math.inf))

    return (
        stage4(opt_a) == stage4(opt_b)
        and np.array_equal(a.points, b.points)
        and np.array_equal(a.triangles, b.triangles)
    )


def _finish(
    fld: MetricField, opt: AdaptOptions, curved: AdaptResult, progress: Progress
) -> tuple[AdaptResult, Defects | None]:
    """Stage 4 of a run on its curved mesh (:func:`_curved`); the result and the
    defects as :func:`_run` gives them."""
    t = time.perf_counter()
    res = swap(fld, curved.mesh, opt)
    seconds = {**curved.seconds, "swap": time.perf_counter() - t}
    progress(f"swap: {res.counts()} ({seconds['swap']:.1f} s)")
    return AdaptResult(res.mesh, res.swaps, seconds, curved.metric_area), res.unit_defects
