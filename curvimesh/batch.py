"""Adapt many metric files and judge the results: ``curvimesh batch`` as a library.

:func:`run_batch` adapts every metric file (in worker processes with
``jobs`` > 1), writes for each metric ``NAME`` (the file's stem) into the
output directory

* ``NAME.msh``: the adapted mesh;
* ``NAME.json``: the report of SPEC section 4 plus ``"swaps"`` and
  ``"seconds"`` per stage, as ``adapt --stats`` writes it;
* ``NAME.txt``: the same report as a readable table;
* ``NAME.png``: the mesh coloured by quality with the histograms
  (:func:`curvimesh.plot.plot_mesh_report`, stored with a 256-colour palette);
* ``NAME-zoom.png``: the same, zoomed on the densest part of the metric
  (:func:`zoom_window`);

then ``summary.json`` and ``summary.md``, and with ``readme`` the generated
part of ``README.md`` (:func:`write_readme`). A run that fails (a bad metric
file, a failed adaptation) never stops the others: it gets a row with its
error. Nothing is ever deleted from the directory.

A *gate* (:func:`parse_gate`) is a condition on the report that every run
must meet: ``KEY OP NUMBER`` with OP one of ``>= <= > < == !=``, or a yes/no
key alone (``valid``). KEY is a dotted path into the report
(``edge_length.max``, ``quality.min``, ``efficiency``, ``swaps``,
``seconds.total``); a short name stands for the one dotted path that ends in
it (``in_range``, ``max``, ``p99``), and a short name that several paths end
in (``min``, ``mean``, ``p01``) is refused as ambiguous.
"""

from __future__ import annotations

import concurrent.futures
import difflib
import json
import math
import multiprocessing
import operator
import os
import re
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from curvimesh import adapt as pipeline
from curvimesh.errors import CurvimeshError, InputError
from curvimesh.io import atomic_output, atomic_write_text, write_mesh
from curvimesh.mesh import Mesh
from curvimesh.metric import MetricField, load_metric
from curvimesh.quality import (
    COUNT_RTOL,
    REPORT_RTOL,
    edge_lengths,
    metric_areas_adaptive,
    quality_from,
)
from curvimesh.report import UNIT_RANGE, format_report, mesh_report

__all__ = [
    "BOOLEAN_KEYS",
    "NUMBER_KEYS",
    "BatchResult",
    "Gate",
    "RunResult",
    "parse_gate",
    "run_batch",
    "run_one",
    "summary_markdown",
    "summary_table",
    "write_readme",
    "zoom_window",
]

#: The numeric keys of a batch report (SPEC section 4, plus swaps and seconds), as dotted paths.
NUMBER_KEYS = (
    "vertices",
    "nodes",
    "triangles",
    "edges",
    "edge_length.min",
    "edge_length.max",
    "edge_length.mean",
    "edge_length.p01",
    "edge_length.p99",
    "edge_length.in_range",
    "quality.min",
    "quality.mean",
    "quality.p01",
    "invalid_triangles",
    "straight_invalid_triangles",
    "metric_area",
    "ideal_triangles",
    "efficiency",
    "swaps",
    "seconds.sample",
    "seconds.triangulate",
    "seconds.curve",
    "seconds.swap",
    "seconds.total",
)
#: The yes/no keys: a gate names them alone.
BOOLEAN_KEYS = ("valid",)

_OPERATORS: dict[str, Callable[[float, float], bool]] = {
    ">=": operator.ge,
    "<=": operator.le,
    "==": operator.eq,
    "!=": operator.ne,
    ">": operator.gt,
    "<": operator.lt,
}
_GATE = re.compile(r"^\s*([A-Za-z_][\w.]*)\s*(?:(>=|<=|==|!=|>|<)\s*(\S+))?\s*$")
#: Width of the zoomed picture, as a fraction of the box.
ZOOM_FRACTION = 0.1
#: The markers around the part of README.md that :func:`write_readme` writes.
README_BEGIN = "<!-- curvimesh batch: begin (generated; edits between these lines are lost) -->"
README_END = "<!-- curvimesh batch: end -->"


# --------------------------------------------------------------------------- gates


@dataclass(frozen=True)
class Gate:
    """One ``--require`` condition: ``key op number``, or a yes/no ``key`` (``op`` None)."""

    text: str
    key: str
    op: str | None = None
    number: float | None = None

    def check(self, report: dict) -> tuple[bool, object]:
        """Whether ``report`` meets the gate, and the value it was judged on.

        >>> parse_gate("edge_length.max<=1.5").check({"edge_length": {"max": 1.7}})
        (False, 1.7)
        >>> parse_gate("valid").check({"valid": True})
        (True, True)
        """
        value: object = report
        for part in self.key.split("."):
            if not isinstance(value, dict) or part not in value:
                return False, None
            value = value[part]
        if self.op is None:
            return value is True, value
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            return False, value
        return bool(_OPERATORS[self.op](float(value), self.number)), value


def _resolve_key(name: str, text: str) -> str:
    known = NUMBER_KEYS + BOOLEAN_KEYS
    if name in known:
        return name
    if "." not in name:
        matches = [k for k in known if k.rsplit(".", 1)[-1] == name]
        if len(matches) == 1:
            return matches[0]
        if matches:
            raise InputError(
                f"--require {text!r}: {name!r} is ambiguous; write {' or '.join(matches)}"
            )
    close = difflib.get_close_matches(name, known, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    raise InputError(f"--require {text!r}: unknown report key {name!r}{hint}")


def parse_gate(text: str) -> Gate:
    """Parse a gate such as ``"in_range>=0.95"`` or ``"valid"``; raise :class:`InputError`.

    >>> parse_gate("in_range >= 0.95")
    Gate(text='in_range >= 0.95', key='edge_length.in_range', op='>=', number=0.95)
    >>> parse_gate("quality.min>0.3").key
    'quality.min'
    """
    m = _GATE.match(text)
    if m is None:
        raise InputError(
            f"--require {text!r}: expected KEY OP NUMBER (OP one of >= <= > < == !=) "
            "or a yes/no key alone, e.g. 'in_range>=0.95' or 'valid'"
        )
    name, op, number_text = m.groups()
    key = _resolve_key(name, text)
    if op is None:
        if key not in BOOLEAN_KEYS:
            raise InputError(f"--require {text!r}: {key} is a number; compare it, e.g. {key}>=1")
        return Gate(text, key)
    if key in BOOLEAN_KEYS:
        raise InputError(f"--require {text!r}: {key} is yes/no; write it alone")
    try:
        number = float(number_text)
    except ValueError:
        number = math.nan
    if not math.isfinite(number):
        raise InputError(f"--require {text!r}: {number_text!r} is not a finite number")
    return Gate(text, key, op, number)


# --------------------------------------------------------------------------- one run


@dataclass(frozen=True)
class RunResult:
    """The outcome of one metric file.

    ``report`` is what ``NAME.json`` holds (None when the run failed, with
    ``error`` its one-line message); ``files`` the names written into the
    output directory; ``gates`` one ``{"gate", "key", "value", "passed"}``
    per gate (filled in by :func:`run_batch`); ``wall_seconds`` the whole run,
    report and pictures included.
    """

    name: str
    metric: str
    report: dict | None = None
    error: str | None = None
    files: tuple[str, ...] = ()
    wall_seconds: float = 0.0
    gates: tuple[dict, ...] = ()

    @property
    def ok(self) -> bool:
        """The run completed (whether or not it met the gates)."""
        return self.error is None

    @property
    def passed(self) -> bool:
        """The run completed and met every gate."""
        return self.ok and all(g["passed"] for g in self.gates)

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "metric": self.metric,
            "ok": self.ok,
            "passed": self.passed,
            "error": self.error,
            "gates": list(self.gates),
            "files": list(self.files),
            "wall_seconds": round(self.wall_seconds, 3),
            "report": self.report,
        }


def zoom_window(
    field_: MetricField, mesh: Mesh, fraction: float = ZOOM_FRACTION
) -> tuple[float, float, float, float]:
    """A window ``(x0, y0, x1, y1)`` on the finest part of ``mesh``.

    Centred on the triangle whose corner centroid has the highest metric
    density sqrt(det g) (the first such, so the choice is deterministic),
    ``fraction`` of the box wide and high, and moved inside the box.

    >>> import sympy
    >>> from curvimesh.metric import Component, X
    >>> fld = MetricField((Component((1 + X**2, sympy.Integer(0), 1 + X**2), ()),))
    >>> mesh = Mesh([[0, 0], [1, 0], [1, 1], [0, 1]], [[0, 1, 2], [0, 2, 3]], (0, 0, 1, 1))
    >>> [round(v, 3) for v in zoom_window(fld, mesh)]
    [0.617, 0.283, 0.717, 0.383]
    """
    xmin, ymin, xmax, ymax = (float(v) for v in (field_.box if mesh.box is None else mesh.box))
    centroids = np.asarray(mesh.points)[mesh.corners].mean(axis=1)
    g = field_.tensor(centroids, check=False)
    with np.errstate(invalid="ignore"):
        density = np.sqrt(g[:, 0, 0] * g[:, 1, 1] - g[:, 0, 1] ** 2)
    cx, cy = (float(v) for v in centroids[int(np.argmax(np.nan_to_num(density, nan=-1.0)))])
    half_w, half_h = 0.5 * fraction * (xmax - xmin), 0.5 * fraction * (ymax - ymin)
    cx = min(max(cx, xmin + half_w), xmax - half_w)
    cy = min(max(cy, ymin + half_h), ymax - half_h)
    return (cx - half_w, cy - half_h, cx + half_w, cy + half_h)


def _lengths_and_qualities(field_: MetricField, mesh: Mesh) -> tuple[NDArray, NDArray] | None:
    """Edge lengths ``(E,)`` and qualities ``(m,)`` of a P2 mesh, computed once for both plots
    (None for a P1 mesh: the plot computes them)."""
    if mesh.order != 2:
        return None
    pts = np.asarray(mesh.points)
    lengths = edge_lengths(field_, pts, mesh.edges, mesh.edge_mid, rtol=COUNT_RTOL)
    qualities = quality_from(
        metric_areas_adaptive(field_, pts[mesh.triangles], rtol=REPORT_RTOL),
        lengths[mesh.tri_edges],
    )
    return lengths, qualities


def _palette_png(path: Path) -> None:
    """Rewrite a PNG with a palette of 256 colours, atomically.

    The plots hold a few flat colours and their antialiased edges, so this
    is hard to tell from the original and about a third of its size.
    """
    from PIL import Image  # a dependency of matplotlib

    with Image.open(path) as image:
        small = image.convert("RGB").quantize(256, dither=Image.Dither.NONE)
    with atomic_output(path) as tmp:
        small.save(tmp, format="PNG", optimize=True)


def run_one(
    metric_path: str,
    out_dir: str,
    options: pipeline.AdaptOptions | None = None,
    *,
    fmt: str = "gmsh22",
) -> RunResult:
    """Adapt one metric file and write its five files into ``out_dir``; never raises
    for a failed run (a :class:`RunResult` with ``error`` set), only on interrupts."""
    from curvimesh.plot import plot_mesh_report

    name = Path(metric_path).stem
    out = Path(out_dir)
    files: list[str] = []
    t0 = time.perf_counter()
    try:
        fld = load_metric(metric_path)
        t = time.perf_counter()
        res = pipeline.adapt(fld, options)
        total = time.perf_counter() - t
        report = mesh_report(fld, res.mesh, metric_area=None)
        report["swaps"] = res.swaps
        report["seconds"] = {
            **{k: round(v, 4) for k, v in res.seconds.items()},
            "total": round(total, 4),
        }
        write_mesh(out / f"{name}.msh", res.mesh, fmt=fmt)
        files.append(f"{name}.msh")
        atomic_write_text(out / f"{name}.json", json.dumps(report, indent=2) + "\n")
        files.append(f"{name}.json")
        atomic_write_text(out / f"{name}.txt", format_report(report) + "\n")
        files.append(f"{name}.txt")
        lengths, qualities = _lengths_and_qualities(fld, res.mesh) or (None, None)
        x0, y0, x1, y1 = zoom_window(fld, res.mesh)
        zoom = f"densest part of the metric: [{x0:.3g}, {x1:.3g}] x [{y0:.3g}, {y1:.3g}]"
        for suffix, window, title in (("", None, None), ("-zoom", (x0, y0, x1, y1), zoom)):
            picture = out / f"{name}{suffix}.png"
            plot_mesh_report(
                fld,
                res.mesh,
                picture,
                window=window,
                title=title,
                lengths=lengths,
                qualities=qualities,
            )
            _palette_png(picture)
            files.append(picture.name)
    except CurvimeshError as exc:
        return _failed(name, metric_path, str(exc), files, t0)
    except (MemoryError, RecursionError) as exc:
        return _failed(name, metric_path, f"{type(exc).__name__}: the work is too large", files, t0)
    except Exception as exc:  # a bug of ours: reported on the run's row, the others go on
        msg = str(exc).splitlines()[0] if str(exc) else ""
        return _failed(
            name, metric_path, f"internal error ({type(exc).__name__}: {msg})", files, t0
        )
    return RunResult(
        name, metric_path, report, files=tuple(files), wall_seconds=time.perf_counter() - t0
    )


def _failed(name: str, metric: str, msg: str, files: list[str], t0: float) -> RunResult:
    one_line = " ".join(msg.splitlines())
    return RunResult(
        name, metric, error=one_line, files=tuple(files), wall_seconds=time.perf_counter() - t0
    )


# --------------------------------------------------------------------------- many runs


@dataclass(frozen=True)
class BatchResult:
    """Every run, in the order of the metric files given, and the gates they were judged by."""

    runs: tuple[RunResult, ...]
    gates: tuple[Gate, ...] = ()
    options: dict = field(default_factory=dict)

    @property
    def passed(self) -> bool:
        return all(r.passed for r in self.runs)

    def as_dict(self) -> dict:
        return {
            "passed": self.passed,
            "failed": [r.name for r in self.runs if not r.passed],
            "gates": [g.text for g in self.gates],
            "options": self.options,
            "runs": [r.as_dict() for r in self.runs],
        }


def _judge(run: RunResult, gates: Sequence[Gate]) -> RunResult:
    verdicts = []
    for g in gates:
        passed, value = g.check(run.report) if run.report is not None else (False, None)
        verdicts.append({"gate": g.text, "key": g.key, "value": value, "passed": passed})
    return RunResult(
        run.name, run.metric, run.report, run.error, run.files, run.wall_seconds, tuple(verdicts)
    )


def _names(metric_paths: Sequence[str]) -> list[str]:
    names = [Path(p).stem for p in metric_paths]
    seen: dict[str, str] = {}
    for name, path in zip(names, metric_paths, strict=True):
        if name in seen:
            raise InputError(
                f"{path}: same name {name!r} as {seen[name]}: their outputs would collide"
            )
        seen[name] = path
    return names


def _verdict_line(run: RunResult) -> str:
    if not run.ok:
        return f"{run.name}: error: {run.error}"
    rep = run.report or {}
    missed = [g["gate"] for g in run.gates if not g["passed"]]
    state = "ok" if not missed else "missed " + ", ".join(missed)
    return (
        f"{run.name}: {state} ({rep.get('vertices')} vertices, "
        f"{'valid' if rep.get('valid') else 'INVALID'}, {run.wall_seconds:.1f} s)"
    )


def run_batch(
    metric_paths: Iterable[str | os.PathLike],
    out_dir: str | os.PathLike,
    *,
    options: pipeline.AdaptOptions | None = None,
    gates: Sequence[Gate] = (),
    jobs: int = 1,
    fmt: str = "gmsh22",
    readme: bool = False,
    progress: Callable[[str], None] = lambda _: None,
) -> BatchResult:
    """Adapt every metric file into ``out_dir`` and judge the runs by ``gates``.

    Runs in this process when ``jobs`` is 1, else in ``jobs`` worker
    processes (spawned, so that nothing of this process's state leaks into
    them); the result is the same either way, timings aside. Raises
    :class:`InputError` before any work for two files of the same stem or an
    output directory that cannot be made; a failing run only marks its row.
    Writes ``summary.json``, ``summary.md`` and, with ``readme``, the
    generated part of ``README.md`` (:func:`write_readme`).
    """
    paths = [os.fspath(p) for p in metric_paths]
    if not paths:
        raise InputError("batch: no metric files given")
    if jobs < 1:
        raise InputError(f"batch: jobs must be at least 1, got {jobs}")
    _names(paths)
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(
            f"{out}: cannot make the output directory: {exc.strerror or exc}"
        ) from None
    opt = options or pipeline.AdaptOptions()
    runs: list[RunResult | None] = [None] * len(paths)

    def done(i: int, run: RunResult) -> None:
        runs[i] = _judge(run, gates)
        progress(f"[{sum(r is not None for r in runs)}/{len(paths)}] {_verdict_line(runs[i])}")

    if jobs == 1 or len(paths) == 1:
        for i, p in enumerate(paths):
            done(i, run_one(p, os.fspath(out), opt, fmt=fmt))
    else:
        context = multiprocessing.get_context("spawn")
        with concurrent.futures.ProcessPoolExecutor(
            max_workers=min(jobs, len(paths)), mp_context=context
        ) as pool:
            futures = {
                pool.submit(run_one, p, os.fspath(out), opt, fmt=fmt): i
                for i, p in enumerate(paths)
            }
            try:
                for fut in concurrent.futures.as_completed(futures):
                    i = futures[fut]
                    try:
                        run = fut.result()
                    except concurrent.futures.process.BrokenProcessPool:
                        run = RunResult(Path(paths[i]).stem, paths[i], error="worker process died")
                    done(i, run)
            except BaseException:
                pool.shutdown(wait=False, cancel_futures=True)
                raise
    result = BatchResult(
        tuple(r for r in runs if r is not None),
        tuple(gates),
        {
            "seed": opt.seed,
            **{name: getattr(opt, name) for name in pipeline.STAGES},
            "retry": opt.retry,
            "rows": opt.rows,
            **({"max_sag": opt.sampling.max_sag} if math.isfinite(opt.sampling.max_sag) else {}),
            "straight": opt.straight,
            "format": fmt,
            "jobs": jobs,
        },
    )
    atomic_write_text(out / "summary.json", json.dumps(result.as_dict(), indent=2) + "\n")
    atomic_write_text(out / "summary.md", summary_markdown(result))
    if readme:
        write_readme(out, result)
    return result


# --------------------------------------------------------------------------- tables


def _cells(run: RunResult) -> list[str]:
    """The table row of a run: see :data:`_COLUMNS`."""
    if run.report is None:
        return [run.name, "error", *["–"] * (len(_COLUMNS) - 2)]
    r, el, q = run.report, run.report["edge_length"], run.report["quality"]
    missed = [g["gate"] for g in run.gates if not g["passed"]]
    return [
        run.name,
        "ok" if not missed else "missed " + ", ".join(missed),
        f"{r['vertices']}",
        f"{r['triangles']}",
        f"{r['swaps']}",
        f"{el['min']:.3f}",
        f"{el['max']:.3f}",
        f"{100 * el['in_range']:.1f} %",
        f"{q['min']:.3f}",
        f"{q['mean']:.3f}",
        "yes" if r["valid"] else "NO",
        f"{r['straight_invalid_triangles']}",
        f"{r['efficiency']:.3f}",
        f"{r['seconds']['total']:.1f}",
    ]


_COLUMNS = (
    "metric",
    "status",
    "vertices",
    "triangles",
    "swaps",
    "length min",
    "length max",
    f"in [{UNIT_RANGE[0]}, {UNIT_RANGE[1]}]",
    "quality min",
    "quality mean",
    "valid",
    "straight-invalid",
    "efficiency",
    "seconds",
)


def summary_table(result: BatchResult) -> str:
    """The runs as a plain-text table (what ``curvimesh batch`` prints), errors below it."""
    rows = [list(_COLUMNS), *[_cells(r) for r in result.runs]]
    widths = [max(len(row[c]) for row in rows) for c in range(len(_COLUMNS))]
    lines = [
        "  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip()
        for row in rows
    ]
    lines += [f"{r.name}: error: {r.error}" for r in result.runs if not r.ok]
    return "\n".join(lines)


def _md_escape(text: str) -> str:
    return text.replace("|", "\\|")


def _markdown_table(result: BatchResult) -> list[str]:
    lines = [
        "| " + " | ".join(_COLUMNS) + " |",
        "|" + "|".join(["---"] * 2 + ["--:"] * (len(_COLUMNS) - 2)) + "|",
    ]
    lines += ["| " + " | ".join(_md_escape(c) for c in _cells(r)) + " |" for r in result.runs]
    return lines


def _markdown_errors(result: BatchResult) -> list[str]:
    failed = [r for r in result.runs if not r.ok]
    if not failed:
        return []
    return ["", "Errors:", ""] + [f"- **{r.name}**: {_md_escape(r.error or '')}" for r in failed]


def summary_markdown(result: BatchResult) -> str:
    """``summary.md``: the table of runs, the gates, the errors."""
    gates = ", ".join(f"`{g.text}`" for g in result.gates) or "none"
    verdict = (
        "every run passed" if result.passed else f"failed: {', '.join(result.as_dict()['failed'])}"
    )
    lines = [
        "# curvimesh batch summary",
        "",
        f"Options: {_options_text(result.options)}. Gates: {gates}. Verdict: {verdict}.",
        "",
        *_markdown_table(result),
        *_markdown_errors(result),
    ]
    return "\n".join(lines) + "\n"


def _options_text(opts: dict) -> str:
    off = [f"--no-{k.replace('_', '-')}" for k in pipeline.STAGES if not opts.get(k, True)]
    if not opts.get("retry", True):
        off.append("--no-retry")
    if not opts.get("rows", True):
        off.append("--no-rows")
    if opts.get("straight"):
        off.append("--straight")
    if "max_sag" in opts:
        off.append(f"--max-sag {opts['max_sag']:g}")
    return f"seed {opts.get('seed', 0)}, " + (" ".join(off) if off else "every stage on")


def _readme_section(result: BatchResult) -> str:
    lines = [
        README_BEGIN,
        "",
        "Edge lengths are metric lengths of the curved (parabolic) edges; quality is the",
        "paper's equation (4), 1 for a unit equilateral triangle; *straight-invalid* counts the",
        "triangles that would be inverted with straight edges (paper figure 8); efficiency is",
        "triangles / (metric area / (√3/4)); seconds are the adaptation alone.",
        f"Options: {_options_text(result.options)}.",
        "",
        *_markdown_table(result),
        *_markdown_errors(result),
    ]
    for run in result.runs:
        if not run.ok:
            continue
        lines += ["", f"### {run.name}", ""]
        lines += [
            f"`{run.metric}`: [report]({run.name}.txt), [JSON]({run.name}.json)"
            + (f", [mesh]({run.name}.msh)" if f"{run.name}.msh" in run.files else ""),
            "",
        ]
        lines += [f"![{run.name}: the whole mesh]({run.name}.png)", ""]
        lines += [f"![{run.name}: zoom on the densest part of the metric]({run.name}-zoom.png)"]
    lines += ["", README_END]
    return "\n".join(lines)


def write_readme(out_dir: str | os.PathLike, result: BatchResult) -> None:
    """Write the generated part of ``out_dir/README.md``: the table and the pictures inline.

    Only the text between :data:`README_BEGIN` and :data:`README_END` is
    replaced; what lies around it (a title, sections written by others) is
    kept. A README without the markers gets the section appended; a missing
    one is made with a title.
    """
    path = Path(out_dir) / "README.md"
    section = _readme_section(result)
    try:
        old = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        old = "# curvimesh sample runs\n\n"
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from None
    start, end = old.find(README_BEGIN), old.find(README_END)
    if start >= 0 and end > start:
        text = old[:start] + section + old[end + len(README_END) :]
    else:
        text = old.rstrip("\n") + "\n\n" + section + "\n"
    atomic_write_text(path, text)
