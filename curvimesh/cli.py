"""The ``curvimesh`` command line (SPEC section 1): thin commands over the library.

Each command reads its inputs, makes one library call and writes its output
atomically. Errors of curvimesh's own types become one line on stderr and
the exit code of the error (2 bad input, 1 failed work); a traceback only
with ``-v``. Ctrl-C exits with 130 and SIGTERM with 143, leaving no output.
"""

from __future__ import annotations

import _thread
import functools
import json
import math
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import click
import numpy as np

from curvimesh import adapt as pipeline
from curvimesh.errors import CurvimeshError, InputError, WorkError
from curvimesh.geodesic import parabola_length, shoot, shortest_parabola
from curvimesh.interpolation import compile_function
from curvimesh.io import FORMATS, atomic_output, check_writable, read_mesh, write_mesh
from curvimesh.metric import (
    MAX_FRAME_TURN,
    TURN_MIN_ANISOTROPY,
    UNIT_TRIANGLE_AREA,
    MetricField,
    density_integral,
    load_metric,
    sharpest_turn,
)
from curvimesh.report import format_report, mesh_report
from curvimesh.sampling import HEX_MAX_SAG, SamplingOptions


class _Terminated(BaseException):
    """Raised by the SIGTERM handler so that cleanup runs as for Ctrl-C."""


#: The signals received while a command runs (SIGINT, SIGTERM), most recent last.
_RECEIVED: list[int] = []


def _on_sigterm(signum, frame):  # pragma: no cover - exercised through a subprocess
    _RECEIVED.append(signal.SIGTERM)
    raise _Terminated()


def _on_sigint(signum, frame):  # pragma: no cover - exercised through a subprocess
    _RECEIVED.append(signal.SIGINT)
    signal.default_int_handler(signum, frame)


class Context:
    """What every command shares: verbosity."""

    def __init__(self) -> None:
        self.verbose = False
        self.quiet = False

    def progress(self, msg: str) -> None:
        if not self.quiet and (self.verbose or sys.stderr.isatty()):
            click.echo(f"curvimesh: {msg}", err=True)


#: The options that name output files: checked before any work is done.
OUTPUT_OPTIONS = ("output", "stats_path", "plot_path")


def _fail(msg: str, code: int) -> None:
    one_line = " ".join(msg.splitlines())
    click.echo(f"curvimesh: error: {one_line}", err=True)
    sys.exit(code)


def _quiet_finalizers() -> None:
    """After an interrupt, let the finalizers of objects it cut short fail silently: a
    Ctrl-C while numba loads machine code leaves llvmlite objects half built, whose
    ``__del__`` then prints "Exception ignored ... Traceback" at exit."""
    sys.unraisablehook = lambda _unraisable: None


#: Seconds after which a signal lost in a finalizer is sent again.
LOST_SIGNAL_DELAY = 0.05


class _LostSignals:
    """An unraisable hook that sends SIGINT (SIGTERM) again when the exception it gets
    is the KeyboardInterrupt (our SIGTERM exception) of a signal that landed in a
    finalizer: Python ignores exceptions raised in ``__del__`` (it prints "Exception
    ignored"), so a Ctrl-C during numba's loading of machine code, where llvmlite
    objects are disposed of, was lost and the command ran on to the end. The signal
    is sent again from another thread (``_thread.interrupt_main``),
    :data:`LOST_SIGNAL_DELAY` later, so that its handler runs in the main thread once
    the hook has returned, in the command's own frames (a handler run while the hook
    runs would raise into it and be ignored again). Other unraisable exceptions go
    to ``default``; :meth:`cancel` stops the timers that have not fired."""

    def __init__(self, default: Callable) -> None:
        self.default = default
        self.timers: list[threading.Timer] = []

    def __call__(self, unraisable: Any) -> None:
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            signum = signal.SIGINT
        elif isinstance(unraisable.exc_value, _Terminated):
            signum = signal.SIGTERM
        else:
            self.default(unraisable)
            return
        timer = threading.Timer(LOST_SIGNAL_DELAY, _thread.interrupt_main, args=(signum,))
        timer.daemon = True
        timer.start()
        self.timers.append(timer)

    def cancel(self) -> None:
        for timer in self.timers:
            timer.cancel()


def _signalled(signum: int) -> None:
    """Exit as for the signal ``signum``: 130 for SIGINT, 143 for SIGTERM, on its
    KeyboardInterrupt or _Terminated, or on another exception that came up in their
    place (compiled code that calls back into Python does not always pass on an
    exception raised there: numba's unboxing of a function argument, interrupted
    while it unpickles the signature, calls numba's ``_get_wrapper_address`` without
    it and raises a TypeError; seen in ``test_interrupt_leaves_nothing``, exit 1,
    "internal error")."""
    _quiet_finalizers()
    if signum == signal.SIGINT:
        _fail("interrupted", 130)
    _fail("terminated", 143)


def command(fn: Callable) -> Callable:
    """Run a command body, turning our errors into one line and an exit code."""

    @click.option("-v", "--verbose", is_flag=True, help="Progress, and tracebacks on errors.")
    @click.option("-q", "--quiet", is_flag=True, help="No progress messages.")
    @functools.wraps(fn)
    def wrapper(*args: Any, verbose: bool, quiet: bool, **kwargs: Any) -> None:
        ctx = Context()
        ctx.verbose, ctx.quiet = verbose, quiet
        _RECEIVED.clear()
        old = signal.signal(signal.SIGTERM, _on_sigterm)
        old_int = signal.getsignal(signal.SIGINT)
        if old_int is signal.default_int_handler:  # not where Ctrl-C is ignored (`cmd &`)
            signal.signal(signal.SIGINT, _on_sigint)
        old_hook = sys.unraisablehook
        sys.unraisablehook = hook = _LostSignals(old_hook)
        try:
            for name in OUTPUT_OPTIONS:
                if kwargs.get(name):
                    check_writable(kwargs[name])
            fn(ctx, *args, **kwargs)
        except CurvimeshError as exc:
            if verbose:
                traceback.print_exc()
            _fail(str(exc), exc.exit_code)
        except KeyboardInterrupt:
            _signalled(signal.SIGINT)
        except _Terminated:
            _signalled(signal.SIGTERM)
        except (MemoryError, RecursionError) as exc:
            if verbose:
                traceback.print_exc()
            _fail(f"{type(exc).__name__}: the work is too large", 1)
        except Exception as exc:  # a bug of ours: still one line, traceback with -v
            if _RECEIVED:  # the signal's exception, replaced (see _signalled)
                _signalled(_RECEIVED[-1])
            if verbose:
                traceback.print_exc()
            msg = str(exc).splitlines()[0] if str(exc) else ""
            _fail(f"internal error ({type(exc).__name__}: {msg}); run with -v for details", 1)
        finally:
            signal.signal(signal.SIGTERM, old)
            if old_int is signal.default_int_handler:
                signal.signal(signal.SIGINT, old_int)
            hook.cancel()
            if sys.unraisablehook is hook:  # not replaced by _quiet_finalizers
                sys.unraisablehook = old_hook

    return wrapper


def metric_option(required: bool = True) -> Callable:
    return click.option(
        "--metric",
        "metric_path",
        required=required,
        type=click.Path(),
        help="Metric YAML file (SPEC section 2).",
    )


def format_option(fn: Callable) -> Callable:
    return click.option(
        "--format",
        "fmt",
        type=click.Choice(sorted(FORMATS)),
        default="gmsh22",
        show_default=True,
        help="Mesh file format.",
    )(fn)


def output_option(fn: Callable) -> Callable:
    fn = format_option(fn)
    return click.option(
        "-o", "--output", required=True, type=click.Path(), help="Output mesh (- for stdout)."
    )(fn)


def input_argument(fn: Callable) -> Callable:
    return click.argument("mesh_path", metavar="MESH", type=click.Path())(fn)


def straight_option(fn: Callable) -> Callable:
    return click.option(
        "--straight", is_flag=True, help="Keep every edge straight (to compare with curved)."
    )(fn)


def rows_option(fn: Callable) -> Callable:
    return click.option(
        "--no-rows",
        "no_rows",
        is_flag=True,
        help=(
            "Sample thin curved layers by the fronts like the rest, not row by row from "
            "their cores, each row spaced by its own parabolas (the first run's way)."
        ),
    )(fn)


def retry_option(fn: Callable) -> Callable:
    return click.option(
        "--no-retry",
        "no_retry",
        is_flag=True,
        help=(
            "No further runs (thin curved layers sampled by the fronts, the hexagonal "
            "lattice kept out of them, no lattice, then these with other sampling seeds) "
            "when an edge longer than 1.5 is left."
        ),
    )(fn)


def max_sag_option(fn: Callable) -> Callable:
    return click.option(
        "--max-sag",
        "max_sag",
        type=click.FloatRange(min=0.0, min_open=True),
        default=None,
        help=(
            "Keep the hexagonal lattice out of thin curved layers: where a unit chord along "
            "the layer strays this many of its short sizes or more from it (adapt's second "
            f"run uses {HEX_MAX_SAG}). Default: no bound."
        ),
    )(fn)


def _options(
    *,
    seed: int = 0,
    max_vertices: int = pipeline.MAX_VERTICES,
    straight: bool = False,
    retry: bool = True,
    rows: bool = True,
    max_sag: float | None = None,
    **stages: bool,
) -> pipeline.AdaptOptions:
    """The pipeline's options; ``stages`` switches stages by their :class:`AdaptOptions` field,
    ``max_sag`` (None: no bound) is the sampling's :attr:`SamplingOptions.max_sag`."""
    sampling = SamplingOptions(max_sag=math.inf if max_sag is None else max_sag)
    return pipeline.AdaptOptions(
        seed=seed, max_vertices=max_vertices, straight=straight, retry=retry, rows=rows,
        sampling=sampling, **stages,
    )  # fmt: skip


#: The help of each stage's flag --no-FIELD (FIELD its AdaptOptions field).
STAGE_HELP = {
    "hexagons": (
        "No hexagonal lattice: every point shoots along the metric's principal directions "
        "(the paper's Algorithm 1)."
    ),
    "cores": (
        "No sampling from the cores of thin curved layers first (anisotropy 100 or more): "
        "the fronts grow from the box's sides alone."
    ),
    "fill": "No gap filling after Algorithm 1.",
    "relocate": "No vertex relocation.",
    "charts": (
        "No edges of thin curved layers flipped to the Delaunay triangulation of each "
        "layer's own coordinates (along its core, metric length across)."
    ),
    "intrinsic": (
        "No intrinsic Delaunay flips (on curved edge lengths) where the metric's directions "
        "turn 60 degrees or more per unit length."
    ),
    "insert": "No vertex insertions at long curved edges.",
    "split": "No splits of long curved edges.",
    "recurve": (
        "No re-curving of edge nodes towards their shortest parabolas (nor, at the "
        "end, of the edges left longer than 1.4 towards a free middle node)."
    ),
    "length_swaps": "No swaps for edge lengths (swaps for quality (4) only).",
    "shift": (
        "No vertex shifts at the edges left longer than 1.4 and at triangles of quality < 0.8."
    ),
    "remove": (
        "No vertex removals at the triangles left below quality 0.3 and at the edges "
        "left longer than 1.4."
    ),
    "repeat": (
        "No repeated passes of the swaps and the clean-up stages while edges longer than "
        "1.4 or triangles below quality 0.3 are left."
    ),
    "bend": (
        "No edge nodes bent off their parabolas to raise the triangles left below quality 0.8."
    ),
    "fit": "No edge nodes fitted to the function of an interpolation metric.",
}

#: The stages beyond the paper's method (:data:`curvimesh.adapt.STAGES`, in pipeline
#: order) with their flags' help.
STAGES = tuple((name, STAGE_HELP[name]) for name in pipeline.STAGES)

#: The stages run by the swap stage (``curvimesh swap``).
SWAP_STAGES = pipeline.SWAP_STAGES


def stage_flags(*names: str) -> Callable[[Callable], Callable]:
    """The --no-STAGE flags of the named stages (all of :data:`STAGES` by default),
    handed to the command as one keyword ``stages``: {AdaptOptions field: on}."""
    chosen = [(n, what) for n, what in STAGES if not names or n in names]

    def decorate(fn: Callable) -> Callable:
        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> None:
            stages = {n: not kwargs.pop(f"no_{n}") for n, _ in chosen}
            return fn(*args, stages=stages, **kwargs)

        for n, what in reversed(chosen):
            flag = "--no-" + n.replace("_", "-")
            wrapper = click.option(flag, f"no_{n}", is_flag=True, help=what)(wrapper)
        return wrapper

    return decorate


def max_vertices_option(fn: Callable) -> Callable:
    return click.option(
        "--max-vertices",
        type=click.IntRange(min=1),
        default=pipeline.MAX_VERTICES,
        show_default=True,
        help="Fail fast above this estimated vertex count.",
    )(fn)


def seed_option(fn: Callable) -> Callable:
    return click.option(
        "--seed",
        type=click.IntRange(min=0),
        default=0,
        show_default=True,
        help="Random seed (0: each front in its natural order).",
    )(fn)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="curvimesh")
def main() -> None:
    """Curvilinear (P2) unit meshes adapted to a Riemannian metric field.

    Method: Zhang, Johnen & Remacle, "Curvilinear mesh adaptation".
    """


def _read(path: str, fld: MetricField | None = None):
    return read_mesh(path, box=fld.box if fld is not None else None)


@main.command("check-metric")
@click.argument("metric_path", metavar="METRIC", type=click.Path())
@command
def check_metric(ctx: Context, metric_path: str) -> None:
    """Parse and validate a metric file, sample it and print a summary."""
    fld = load_metric(metric_path)
    pts = fld.sample_points(129)
    fld.validate(pts)
    g = fld.tensor(pts)
    w = np.linalg.eigvalsh(g)
    sizes = 1.0 / np.sqrt(w)
    aniso = sizes.max(axis=1) / sizes.min(axis=1)
    area = density_integral(fld)
    ideal = area / UNIT_TRIANGLE_AREA
    xmin, ymin, xmax, ymax = fld.box
    lines = [
        f"metric      {fld.name} ({metric_path})",
        f"domain      [{xmin:g}, {xmax:g}] x [{ymin:g}, {ymax:g}]",
        f"items       {len(fld.components)}",
        f"size        {sizes.min():.6g} .. {sizes.max():.6g}",
        f"anisotropy  {aniso.min():.6g} .. {aniso.max():.6g}",
        f"metric area {area:.6g}",
        f"ideal triangles {ideal:.1f} (about {pipeline.estimated_vertices(area):.0f} vertices)",
    ]
    sharpest = sharpest_turn(fld)
    turn, (px, py), _ = sharpest
    where = f" at ({px:.6g}, {py:.6g})" if turn > 0 else ""
    lines.append(
        f"turning     {math.degrees(turn):.3g} deg per unit length{where}"
        f" (where anisotropy >= {TURN_MIN_ANISOTROPY:g})"
    )
    click.echo("\n".join(lines))
    _warn_turn(ctx, fld, sharpest)


def _warn_turn(ctx: Context, fld: MetricField, sharpest: tuple | None = None) -> None:
    """Warn on stderr where the metric's directions turn too fast for unit edges."""
    turn, (px, py), h = sharpest if sharpest is not None else sharpest_turn(fld)
    if turn <= MAX_FRAME_TURN or ctx.quiet:
        return
    if turn < 2 * math.pi:
        what = f"turn {math.degrees(turn):.0f} deg"
        cure = f"; a long size below {h * MAX_FRAME_TURN / turn:.3g} there (now {h:.3g})"
        cure += " would let them"
    else:  # a singular point such as the centre of concentric directions
        what, cure = "turn more than a full circle", ""
    click.echo(
        f"curvimesh: warning: {fld.source}: the metric's directions {what} within one unit "
        f"length near ({px:.3g}, {py:.3g}); unit edges can hardly follow them there "
        f"(edges over 1.4 may remain){cure}",
        err=True,
    )


@main.command()
@metric_option()
@click.option("--from", "start", nargs=2, type=float, required=True, help="Start point X Y.")
@click.option("--to", "end", nargs=2, type=float, default=None, help="End point X Y.")
@click.option("--angle", type=float, default=None, help="Shooting direction (radians).")
@click.option("--length", type=float, default=1.0, show_default=True, help="Metric length.")
@command
def geodesic(ctx: Context, metric_path, start, end, angle, length) -> None:
    """Shortest parabola between two points, or a geodesic shot from a point (JSON)."""
    if (end is None) == (angle is None):
        raise InputError("geodesic: give exactly one of --to X Y or --angle A")
    fld = load_metric(metric_path)
    x0 = np.array([start], dtype=float)
    if end is not None:
        x1 = np.array([end], dtype=float)
        if np.allclose(x0, x1):
            raise InputError("geodesic: --from and --to are the same point")
        fld.validate(np.concatenate([x0, x1]))
        par = shortest_parabola(fld, x0, x1)
        straight = parabola_length(fld, x0, x1)
        out = {
            "length": float(par.length[0]),
            "midpoint": [float(v) for v in par.mid[0]],
            "straight_length": float(straight[0]),
        }
    else:
        if not (math.isfinite(length) and length > 0):
            raise InputError("geodesic: --length must be positive")
        fld.validate(x0)
        shot = shoot(fld, x0, np.array([[math.cos(angle), math.sin(angle)]]), length)
        if not shot.ok[0]:
            raise InputError("geodesic: the geodesic leaves the region where the metric is defined")
        out = {"end": [float(v) for v in shot.end[0]], "length": float(length)}
    click.echo(json.dumps(out))


@main.command()
@metric_option()
@output_option
@seed_option
@max_vertices_option
@stage_flags("hexagons", "cores", "fill")
@max_sag_option
@rows_option
@command
def sample(
    ctx: Context, metric_path, output, fmt, seed, max_vertices, stages, max_sag, no_rows
) -> None:
    """Stage 1: sample points (Algorithm 1, then gap filling); writes nodes with vertex cells.

    Thin curved layers are sampled row by row from their cores, as in adapt's first
    run (--no-rows: by the fronts, as in its run after a first that leaves an edge
    longer than 1.5)."""
    fld = load_metric(metric_path)
    opt = _options(seed=seed, max_vertices=max_vertices, max_sag=max_sag, **stages)
    opt = pipeline.first_run(replace(opt, rows=not no_rows), fld)
    pipeline.check_size(fld, max_vertices)
    cloud = pipeline.sample(fld, opt)
    ctx.progress(f"sample: {len(cloud.points)} points")
    write_mesh(output, cloud, fmt=fmt)


@main.command()
@input_argument
@metric_option(required=False)
@output_option
@click.option("--no-relocate", is_flag=True, help="No vertex relocation (with --metric).")
@command
def triangulate(ctx: Context, mesh_path, metric_path, output, fmt, no_relocate) -> None:
    """Stage 2: Delaunay triangulation of the points; writes triangle (P1) cells.

    With --metric the triangulation is made Delaunay in the metric and its
    vertices are relocated to even out the edge lengths.
    """
    fld = load_metric(metric_path) if metric_path else None
    cloud = _read(mesh_path, fld)
    if len(cloud.points) < 3:
        raise InputError(f"{mesh_path}: {len(cloud.points)} node(s); at least 3 are needed")
    try:
        mesh = pipeline.triangulate(cloud, fld, _options(relocate=not no_relocate))
    except WorkError as exc:  # Qhull failed on these points (all collinear, duplicates)
        raise InputError(f"{mesh_path}: cannot triangulate the nodes: {exc}") from None
    write_mesh(output, mesh, fmt=fmt)


@main.command()
@input_argument
@metric_option()
@output_option
@straight_option
@command
def curve(ctx: Context, mesh_path, metric_path, output, fmt, straight) -> None:
    """Stage 3: P2 nodes on geodesic parabolas, backtracked to validity."""
    fld = load_metric(metric_path)
    mesh = _require_triangles(_read(mesh_path, fld), mesh_path)
    write_mesh(output, pipeline.curve(fld, mesh, _options(straight=straight)), fmt=fmt)


@main.command()
@input_argument
@metric_option()
@output_option
@straight_option
@stage_flags(*SWAP_STAGES)
@command
def swap(
    ctx: Context,
    mesh_path,
    metric_path,
    output,
    fmt,
    straight,
    stages,
) -> None:
    """Stage 4: curvilinear edge swaps driven by quality (4) and edge lengths,
    re-curving, vertex insertions and splits at the long edges, and swaps and
    re-curving again, vertex shifts at the edges left long and the flat triangles,
    vertex removals at the flat triangles left, edge nodes bent to raise the
    triangles left below quality 0.8; for an interpolation metric, edge nodes
    fitted to its function."""
    fld = load_metric(metric_path)
    mesh = _require_triangles(_read(mesh_path, fld), mesh_path)
    if mesh.order != 2:
        raise InputError(f"{mesh_path}: swap needs a P2 (triangle6) mesh; run curve first")
    res = pipeline.swap(fld, mesh, _options(straight=straight, **stages))
    ctx.progress(f"swap: {res.counts()}")
    write_mesh(output, res.mesh, fmt=fmt)


def _require_triangles(mesh, path: str):
    if len(mesh.triangles) == 0:
        raise InputError(f"{path}: the mesh has no triangles")
    return mesh


@main.command()
@metric_option()
@output_option
@seed_option
@click.option(
    "--stats",
    "stats_path",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write the report JSON with swaps and seconds per stage.",
)
@max_vertices_option
@straight_option
@stage_flags()
@retry_option
@rows_option
@max_sag_option
@command
def adapt(
    ctx: Context,
    metric_path,
    output,
    fmt,
    seed,
    stats_path,
    max_vertices,
    straight,
    stages,
    no_retry,
    no_rows,
    max_sag,
) -> None:
    """All stages: sample | triangulate | curve | swap, in one process.

    The stages beyond the paper's method (a hexagonal lattice of sampled
    points where the metric's directions turn slowly, sampling from the cores of thin
    curved layers first, gap filling, vertex relocation, flips of the edges of thin
    curved layers to the Delaunay triangulation of each layer's own coordinates,
    intrinsic flips where the metric's directions turn fast, vertex insertion,
    edge splits, re-curving, swaps for lengths, vertex shifts, vertex removals,
    repeated passes of these where defects remain, edge nodes bent for quality, and
    for an interpolation metric edge nodes fitted to its function) run by default;
    --no-hexagons, --no-cores, --no-fill, --no-relocate, --no-charts, --no-intrinsic,
    --no-insert, --no-split, --no-recurve, --no-length-swaps, --no-shift, --no-remove,
    --no-repeat, --no-bend and --no-fit turn them off, so that the paper's method alone
    is `--no-hexagons --no-cores --no-fill --no-relocate --no-charts --no-intrinsic
    --no-insert --no-split --no-recurve --no-length-swaps --no-shift --no-remove
    --no-repeat --no-bend --no-fit`. Thin curved layers are sampled row by row from
    their cores, each row spaced by its own parabolas (--no-rows: by the fronts like
    the rest). When an edge longer than 1.5 is left, all stages run again: where the
    metric has thin curved layers, with them sampled by the fronts; then with the
    hexagonal lattice kept out of thin curved layers (--max-sag 0.5); then, if one is
    still left, without the lattice; then these runs with the sampling seeds --seed +
    1000, + 2000 and + 3000 (each dropped when more than 10 % of its curved edges are
    longer than 1.5), and the mesh with the shortest longest edge is kept (--no-retry:
    not).
    """
    fld = load_metric(metric_path)
    _warn_turn(ctx, fld)
    opt = _options(
        seed=seed, max_vertices=max_vertices, straight=straight, retry=not no_retry,
        rows=not no_rows, max_sag=max_sag, **stages,
    )  # fmt: skip
    t0 = time.perf_counter()
    res = pipeline.adapt(fld, opt, progress=ctx.progress)
    total = time.perf_counter() - t0
    stats = None
    if stats_path:
        stats = mesh_report(fld, res.mesh, metric_area=None)
        stats["swaps"] = res.swaps
        stats["seconds"] = {
            **{k: round(v, 4) for k, v in res.seconds.items()},
            "total": round(total, 4),
        }
    if stats is None:
        write_mesh(output, res.mesh, fmt=fmt)
        return
    # The stats go to their temporary file first: if either write fails, neither
    # output is replaced (short of a failing rename).
    with atomic_output(stats_path) as tmp:
        Path(tmp).write_text(json.dumps(stats, indent=2) + "\n", encoding="utf-8")
        write_mesh(output, res.mesh, fmt=fmt)


@main.command()
@input_argument
@metric_option()
@click.option("--json", "as_json", is_flag=True, help="Print the SPEC section 4 JSON object.")
@click.option(
    "--plot",
    "plot_path",
    type=click.Path(dir_okay=False),
    default=None,
    help="Draw the mesh and histograms into this image.",
)
@click.option(
    "--function",
    "function_text",
    metavar="EXPR",
    default=None,
    help="Also report the L2 and Linf errors of the Lagrange interpolant of EXPR(x, y).",
)
@click.option(
    "--window",
    nargs=4,
    type=float,
    default=None,
    metavar="X0 Y0 X1 Y1",
    help="With --plot: draw only this rectangle of the mesh (zoom).",
)
@command
def report(ctx: Context, mesh_path, metric_path, as_json, plot_path, function_text, window) -> None:
    """Edge lengths, qualities and validity of a mesh in a metric."""
    if window is not None:
        _check_window(window, plot_path)
    function = compile_function(function_text, source="--function") if function_text else None
    fld = load_metric(metric_path)
    mesh = _require_triangles(_read(mesh_path, fld), mesh_path)
    rep = mesh_report(fld, mesh, function=function)
    if plot_path:
        from curvimesh.plot import plot_mesh_report

        plot_mesh_report(fld, mesh, plot_path, window=window)
    click.echo(json.dumps(rep, indent=2) if as_json else format_report(rep))


def _check_window(window: tuple[float, ...], plot_path: str | None) -> None:
    x0, y0, x1, y1 = window
    if plot_path is None:
        raise InputError("report: --window zooms the picture; give --plot FIG too")
    if not (all(map(math.isfinite, window)) and x0 < x1 and y0 < y1):
        raise InputError(f"report: --window {x0:g} {y0:g} {x1:g} {y1:g}: need X0 < X1 and Y0 < Y1")


@main.command()
@metric_option()
@click.option(
    "--at",
    "centres",
    nargs=2,
    type=float,
    multiple=True,
    required=True,
    metavar="X Y",
    help="A centre (repeat for more).",
)
@click.option(
    "--plot",
    "plot_path",
    required=True,
    type=click.Path(dir_okay=False),
    help="The image to draw.",
)
@command
def circles(ctx: Context, metric_path, centres, plot_path) -> None:
    """Unit geodesic circles at points, with the tangent-plane ellipses (paper figs. 1, 2)."""
    from curvimesh.plot import plot_circles

    fld = load_metric(metric_path)
    xmin, ymin, xmax, ymax = fld.box
    for x, y in centres:
        if not (xmin <= x <= xmax and ymin <= y <= ymax):
            raise InputError(
                f"--at {x:g} {y:g}: outside the box [{xmin:g}, {xmax:g}] x [{ymin:g}, {ymax:g}] "
                f"of {metric_path}"
            )
    pts = np.array(centres, dtype=float)
    fld.validate(pts)
    plot_circles(fld, pts, plot_path)


@main.command()
@click.argument("metric_paths", metavar="METRIC...", nargs=-1, required=True, type=click.Path())
@click.option(
    "--out-dir",
    required=True,
    type=click.Path(file_okay=False),
    help="Directory for NAME.msh/.json/.txt/.png/-zoom.png and summary.md/.json.",
)
@click.option(
    "--jobs",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="Worker processes (1: in this process).",
)
@click.option(
    "--require",
    "requires",
    multiple=True,
    metavar="GATE",
    help="A condition every run must meet: KEY OP NUMBER (in_range>=0.95, "
    "edge_length.max<=1.5, quality.min>=0.3) or a yes/no key (valid). Repeatable.",
)
@click.option(
    "--readme",
    is_flag=True,
    help="Also write the table and the pictures into the generated part of DIR/README.md.",
)
@format_option
@seed_option
@straight_option
@stage_flags()
@retry_option
@rows_option
@max_sag_option
@command
def batch(
    ctx: Context,
    metric_paths,
    out_dir,
    jobs,
    requires,
    readme,
    fmt,
    seed,
    straight,
    stages,
    no_retry,
    no_rows,
    max_sag,
) -> None:
    """Adapt every metric file, write its mesh, report and pictures, and a summary.

    Exits 1 when a run fails or misses a --require gate. KEY is a dotted
    path into the report (edge_length.min, quality.mean, efficiency, swaps,
    seconds.total); a short name stands for the one path ending in it
    (in_range, max, p99); min, mean and p01 are ambiguous and need the path.
    """
    from curvimesh.batch import parse_gate, run_batch, summary_table

    gates = [parse_gate(text) for text in requires]
    opt = _options(
        seed=seed, straight=straight, retry=not no_retry, rows=not no_rows, max_sag=max_sag,
        **stages,
    )  # fmt: skip
    result = run_batch(
        metric_paths,
        out_dir,
        options=opt,
        gates=gates,
        jobs=jobs,
        fmt=fmt,
        readme=readme,
        progress=ctx.progress,
    )
    click.echo(summary_table(result))
    failed = result.as_dict()["failed"]
    if failed:
        raise WorkError(
            f"{len(failed)} of {len(result.runs)} run(s) failed or missed a gate: "
            f"{', '.join(failed)} (see {Path(out_dir) / 'summary.md'})"
        )
