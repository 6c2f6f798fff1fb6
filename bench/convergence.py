"""Convergence of P2 interpolation: uniform, adapted straight-sided and adapted curved meshes.

For each test function f on [0, 1]² and each target vertex count N:

* ``uniform``: the structured straight P2 mesh with about N vertices
  (n × n squares cut along a diagonal, (n + 1)² = N vertices);
* ``straight``: curvimesh's mesh for the ``interpolation`` metric of f
  (degree 2, L2 norm, N vertices) with every edge kept straight
  (``AdaptOptions(straight=True)``, the CLI's ``adapt --straight``);
* ``geodesic``: curvimesh's curved unit mesh for the same metric, its edges
  on the metric's shortest parabolas (``adapt --no-fit``);
* ``curved``: the default ``adapt``: the ``geodesic`` mesh with its edge nodes
  then fitted to f (:mod:`curvimesh.fit`), the same vertices and triangles;
* ``straightened``: the geodesic mesh with its edge nodes moved back to the
  edge midpoints: the same vertices and triangles, straight edges. Against
  ``geodesic`` it isolates the effect of the curvature itself; against
  ``straight``, that of the connectivity the curved swaps chose.

The adapted meshes share their sampling and triangulation, which do not
depend on ``straight`` (same seed), so they differ only by the curving and
swapping stages (and the fitting). Errors are those of the isoparametric P2 Lagrange
interpolant (:func:`curvimesh.interpolation_error.interpolation_error`); the
plot is error against the *actual* vertex count, and the slopes are fitted by
least squares in log-log (the optimal rate for P2 in 2D is N^(−3/2)).

Writes ``convergence.json`` (every run, saved as they finish, so that an
interrupted study keeps its results), ``convergence.png`` and
``convergence.md`` into the output directory (``sample_runs`` by default);
``--replot`` rewrites the last two from the first.

    python bench/convergence.py                 # 500 .. 2800 vertices
    python bench/convergence.py --full          # and 4000 .. 50 000 (many hours)
    python bench/convergence.py --vertices 500 1000 --functions f1
    python bench/convergence.py --keep-straight  # recompute the curved series only
    python bench/convergence.py --vertices 32000 --merge  # add a level to the saved runs
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

from curvimesh import adapt as pipeline
from curvimesh.bezier import valid_exact
from curvimesh.fit import fit_nodes
from curvimesh.interpolation import GRADATION, compile_function
from curvimesh.interpolation_error import interpolation_error
from curvimesh.mesh import Mesh, to_p2_straight
from curvimesh.metric import load_metric_text

#: The test functions: the two of the feNG benchmarks and a sharp circular front.
FUNCTIONS = {
    "f1": "(1 + tanh(50*((y - 0.5) - 0.3*sin(3*pi*x))))/2",
    "f2": "(x - 0.5)**4 * (y - 0.5)**4",
    "f3": "(1 + tanh(500/3*((x - 0.5)**2 + (y - 0.5)**2 - 0.09)))/2",
}
DESCRIPTIONS = {
    "f1": "sine-shaped tanh front, width ~1/50",
    "f2": "smooth quartic (x-1/2)^4 (y-1/2)^4",
    "f3": "circular tanh front r = 0.3, width ~1/100",
}
DEFAULT_VERTICES = (500, 700, 1000, 1400, 2000, 2800)
FULL_VERTICES = (*DEFAULT_VERTICES, 4000, 5600, 8000, 16000, 32000, 50000)
SIZES = (1e-4, 0.5)
SERIES = ("uniform", "straight", "geodesic", "curved", "straightened")

#: The series that do not depend on the curving stages, kept by ``--keep-straight``.
STRAIGHT_SERIES = ("uniform", "straight")


def metric_text(function: str, vertices: int) -> str:
    return (
        "metric:\n  interpolation:\n"
        f"    function: {function}\n    degree: 2\n    norm: 2\n"
        f"    vertices: {vertices}\n    sizes: [{SIZES[0]}, {SIZES[1]}]\n"
    )


def uniform_mesh(vertices: int) -> Mesh:
    """Straight P2 mesh of the unit square with about ``vertices`` corner vertices."""
    n = max(1, round(math.sqrt(vertices)) - 1)
    t = np.linspace(0.0, 1.0, n + 1)
    gx, gy = np.meshgrid(t, t, indexing="ij")
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    p1 = Mesh(np.column_stack([gx.ravel(), gy.ravel()]), tris, (0.0, 0.0, 1.0, 1.0))
    return to_p2_straight(p1)


def run_uniform(name: str, vertices: int) -> list[dict]:
    f = compile_function(FUNCTIONS[name])
    t0 = time.perf_counter()
    mesh = uniform_mesh(vertices)
    err = interpolation_error(f, mesh)
    return [_record(name, "uniform", vertices, mesh, err, time.perf_counter() - t0)]


def run_adapted(name: str, vertices: int, seed: int = 0, straight: bool = True) -> list[dict]:
    """Adapt to the metric of ``name`` with ``vertices``: straight (unless not
    ``straight``), geodesic, curved (fitted) and straightened."""
    f = compile_function(FUNCTIONS[name])
    t0 = time.perf_counter()
    fld = load_metric_text(metric_text(FUNCTIONS[name], vertices), source=f"{name}.yaml")
    opt = pipeline.AdaptOptions(seed=seed)
    cloud = pipeline.sample(fld, opt)
    p1 = pipeline.triangulate(cloud, fld)
    shared = time.perf_counter() - t0
    out = []
    runs = (("straight", True), ("geodesic", False)) if straight else (("geodesic", False),)
    for series, flat in runs:
        t1 = time.perf_counter()
        opt = pipeline.AdaptOptions(seed=seed, straight=flat, fit=False)
        mesh = pipeline.swap(fld, pipeline.curve(fld, p1, opt), opt).mesh
        seconds = shared + time.perf_counter() - t1
        out.append(_record(name, series, vertices, mesh, interpolation_error(f, mesh), seconds))
    t1 = time.perf_counter()
    fitted = fit_nodes(fld.error_function, mesh).mesh  # what the default adapt does last
    seconds += time.perf_counter() - t1
    out.append(_record(name, "curved", vertices, fitted, interpolation_error(f, fitted), seconds))
    flat = to_p2_straight(mesh)
    out.append(_record(name, "straightened", vertices, flat, interpolation_error(f, flat), 0.0))
    return out


def vertices_for_error(rows: list[dict], error: float, key: str = "l2") -> float:
    """Vertices a series needs for ``error``: log-log interpolation between its runs
    (NaN outside their range)."""
    n = np.log([r["vertices"] for r in rows])
    e = np.log([r[key] for r in rows])
    order = np.argsort(e)
    if not (e.min() <= math.log(error) <= e.max()):
        return math.nan
    return float(np.exp(np.interp(math.log(error), e[order], n[order])))


def _record(name: str, series: str, target: int, mesh: Mesh, err, seconds: float) -> dict:
    nodes = np.asarray(mesh.points)[mesh.triangles]
    return {
        "function": name,
        "series": series,
        "target": target,
        "vertices": len(mesh.vertex_ids),
        "triangles": len(mesh.triangles),
        "valid": bool(valid_exact(nodes).all()),
        "l2": err.l2,
        "linf": err.linf,
        "seconds": round(seconds, 2),
    }


def slope(records: list[dict], key: str) -> float:
    """Least-squares slope of log(error) against log(vertices)."""
    if len(records) < 2:
        return math.nan
    n = np.log([r["vertices"] for r in records])
    e = np.log([r[key] for r in records])
    return float(np.polyfit(n, e, 1)[0])


def series_of(results: list[dict], name: str, series: str) -> list[dict]:
    rows = [r for r in results if r["function"] == name and r["series"] == series]
    return sorted(rows, key=lambda r: r["vertices"])


def write_table(
    results: list[dict], path: Path, wall: float | None, jobs: int, note: str | None = None
) -> None:
    """The markdown table of ``results``; ``note`` (the saved JSON's, if any) under the head."""
    lines = [
        "# Convergence of P2 interpolation on uniform, adapted straight and adapted curved meshes",
        "",
        "Generated by `make convergence` (`bench/convergence.py`). Error of the isoparametric",
        "P2 Lagrange interpolant against the vertex count N; slopes fitted by least squares",
        "in log-log over all runs of a series (optimal rate for P2 in 2D: N^(-3/2), slope -1.5).",
        f"Metric: `interpolation` form, degree 2, norm 2, sizes [{SIZES[0]}, {SIZES[1]}], "
        f"gradation {GRADATION:g} (the default).",
        f"Wall time {wall / 60:.1f} min with {jobs} worker(s)."
        if wall
        else "Wall time not recorded.",
        "",
        *([note, ""] if note else []),
        "| function | series | N range | slope L2 | slope L2, finest 3 | slope Linf "
        "| L2 at largest N | Linf at largest N | all valid |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name in FUNCTIONS:
        for series in SERIES:
            rows = series_of(results, name, series)
            if not rows:
                continue
            last = rows[-1]
            lines.append(
                f"| {name} | {series} | {rows[0]['vertices']}–{last['vertices']} | "
                f"{slope(rows, 'l2'):.2f} | {slope(rows[-3:], 'l2'):.2f} | "
                f"{slope(rows, 'linf'):.2f} | {last['l2']:.3e} | "
                f"{last['linf']:.3e} | {'yes' if all(r['valid'] for r in rows) else 'NO'} |"
            )
    lines += [
        "",
        "Curved against straight-sided, L2 error ratios at each target N (< 1: the first",
        "mesh wins). *curved / straight* compares the default curved mesh (edge nodes fitted",
        "to f) with the adapted straight-sided one; *geodesic / straight*, the unit mesh",
        "curved along the metric's geodesics; *geodesic / straightened* isolates that",
        "curvature (same vertices and triangles, edge nodes moved back to the midpoints);",
        "*straightened / straight* isolates the connectivity chosen by the curved swaps.",
        "A straightened mesh may hold folded triangles (the paper's figure 8; *all valid*",
        "says so above): its error is then integrated with |J|. *vertices at equal error*",
        "is the vertex count the curved series needs for the straight mesh's L2 error",
        "(log-log interpolation between the curved runs), over the straight mesh's count.",
        "",
        "| function | target | curved / straight | geodesic / straight | "
        "geodesic / straightened | straightened / straight | vertices at equal error |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in FUNCTIONS:
        by = {s: {r["target"]: r for r in series_of(results, name, s)} for s in SERIES}
        both = set(by["curved"]) & set(by["geodesic"]) & set(by["straight"])
        for target in sorted(both & set(by["straightened"])):
            c, g, st, fl = (
                by[k][target]["l2"] for k in ("curved", "geodesic", "straight", "straightened")
            )
            need = vertices_for_error(series_of(results, name, "curved"), st)
            lines.append(
                f"| {name} | {target} | {c / st:.2f} | {g / st:.2f} | {g / fl:.2f} | "
                f"{fl / st:.2f} | {need / by['straight'][target]['vertices']:.2f} |"
            )
    lines += ["", "Functions:", ""]
    lines += [f"- {k} = `{v}` ({DESCRIPTIONS[k]})" for k, v in FUNCTIONS.items()]
    lines += ["", "Every run:", "", "| function | series | target | vertices | L2 | Linf | s |"]
    lines += ["|---|---|---|---|---|---|---|"]
    for name in FUNCTIONS:
        for series in SERIES:
            for r in series_of(results, name, series):
                lines.append(
                    f"| {name} | {series} | {r['target']} | {r['vertices']} | {r['l2']:.3e} | "
                    f"{r['linf']:.3e} | {r['seconds']} |"
                )
    path.write_text("\n".join(lines) + "\n")


def plot(results: list[dict], path: Path) -> None:
    """Error against vertices, log-log: one column per function, L2 above and Linf below."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n in FUNCTIONS if any(r["function"] == n for r in results)]
    fig, axes = plt.subplots(2, len(names), figsize=(5.0 * len(names), 8.4), squeeze=False)
    styles = {
        "uniform": ("k", "o", "-"),
        "straight": ("tab:blue", "s", "-"),
        "geodesic": ("tab:purple", "d", "--"),
        "curved": ("tab:red", "^", "-"),
        "straightened": ("tab:orange", "v", ":"),
    }
    for col, name in enumerate(names):
        for row, key in enumerate(("l2", "linf")):
            ax = axes[row, col]
            for series in SERIES:
                rows = series_of(results, name, series)
                if not rows:
                    continue
                n = np.array([r["vertices"] for r in rows])
                e = np.array([r[key] for r in rows])
                color, marker, line = styles[series]
                label = f"{series} (slope {slope(rows, key):.2f})"
                ax.loglog(n, e, line, color=color, marker=marker, ms=4, label=label)
            rows = series_of(results, name, "straight") or series_of(results, name, "uniform")
            if len(rows) > 1:
                n0, e0 = rows[0]["vertices"], rows[0][key]
                ref = np.array([n0, rows[-1]["vertices"]])
                ax.loglog(ref, e0 * (ref / n0) ** -1.5, "--", color="gray", label="N^(-3/2)")
            ax.set_title(f"{name}: {DESCRIPTIONS[name]}", fontsize=9)
            ax.set_xlabel("vertices N")
            ax.set_ylabel(f"{'L2' if key == 'l2' else 'Linf'} interpolation error")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def library_commit() -> str | None:
    """The checkout's commit (short hash), with "+changes" if curvimesh/ differs from it."""
    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True
        )
        dirty = subprocess.run(["git", "diff", "--quiet", "HEAD", "--", "curvimesh"], cwd=root)
    except OSError:
        return None
    if head.returncode != 0:
        return None
    return head.stdout.strip() + ("+changes" if dirty.returncode != 0 else "")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="Also 4000 to 50 000 vertices.")
    parser.add_argument("--vertices", type=int, nargs="+", help="Target vertex counts.")
    parser.add_argument("--functions", nargs="+", choices=sorted(FUNCTIONS), default=None)
    parser.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--out", default="sample_runs", help="Output directory.")
    parser.add_argument(
        "--replot", action="store_true", help="Only rewrite the table and plot from the JSON."
    )
    parser.add_argument(
        "--keep-straight",
        action="store_true",
        help="Keep the uniform and straight runs of OUT/convergence.json (they do not depend "
        "on the curving stages) and compute the curved series only.",
    )
    parser.add_argument(
        "--merge",
        action="store_true",
        help="Keep the runs of OUT/convergence.json at the other targets (and functions), "
        "so that a level can be added or redone alone.",
    )
    args = parser.parse_args(argv)
    vertices = args.vertices or (FULL_VERTICES if args.full else DEFAULT_VERTICES)
    names = args.functions or list(FUNCTIONS)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = out / "convergence.json"
    if args.replot:
        saved = json.loads(log.read_text())
        write_table(
            saved["runs"],
            out / "convergence.md",
            saved["wall_seconds"],
            saved["jobs"],
            saved.get("note"),
        )
        plot(saved["runs"], out / "convergence.png")
        return 0
    results: list[dict] = []
    saved_before = json.loads(log.read_text()) if log.exists() else {"runs": []}
    old = saved_before["runs"]
    # the note says which commit made which runs: kept when runs are kept (edit it by hand)
    note = saved_before.get("note") if args.merge or args.keep_straight else None
    if args.merge:
        results = [r for r in old if r["function"] not in names or r["target"] not in vertices]
    if args.keep_straight:
        results += [
            r
            for r in old
            if r["series"] in STRAIGHT_SERIES and r["function"] in names and r["target"] in vertices
        ]
    commit = library_commit()
    t0 = time.perf_counter()
    uniform = (
        [] if args.keep_straight else [(run_uniform, n, v, {}) for n in names for v in vertices]
    )
    adapted = [
        (run_adapted, n, v, {"straight": not args.keep_straight}) for n in names for v in vertices
    ]
    # largest adapted runs first, so that the two workers finish together
    tasks = uniform + sorted(adapted, key=lambda t: -t[2])
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futures = {pool.submit(fn, n, v, **kw): (fn.__name__, n, v) for fn, n, v, kw in tasks}
        for fut in as_completed(futures):
            what = futures[fut]
            try:
                records = fut.result()
            except Exception as exc:  # report and keep going: one failure is a result too
                print(f"{what}: FAILED: {type(exc).__name__}: {exc}", file=sys.stderr, flush=True)
                continue
            for r in records:
                r["commit"] = commit
                print(
                    f"{r['function']} {r['series']:8s} N={r['vertices']:6d} "
                    f"L2={r['l2']:.3e} Linf={r['linf']:.3e} ({r['seconds']} s)",
                    flush=True,
                )
            results += records
            saved = {"jobs": args.jobs, "wall_seconds": None, "note": note, "runs": results}
            log.write_text(json.dumps(saved, indent=1) + "\n")
    wall = time.perf_counter() - t0
    saved = {"jobs": args.jobs, "wall_seconds": round(wall, 1), "note": note, "runs": results}
    log.write_text(json.dumps(saved, indent=1) + "\n")
    write_table(results, out / "convergence.md", wall, args.jobs, note)
    plot(results, out / "convergence.png")
    print(f"wrote {out / 'convergence.md'} and {out / 'convergence.png'} ({wall / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
