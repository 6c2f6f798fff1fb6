"""Benchmark of ``curvimesh adapt`` against Gmsh's anisotropic mesher (BAMG), issue 4.

    python bench/run.py [--large] [--repeat N] [--out bench/results.md]

Two metric families, with every size (eps, lmax) divided by a scale s so that
the vertex count grows as s²: the toy metric of ``metrics/toy.yaml`` (s = 1
gives about 420 vertices) and the intersection of three toys of
``metrics/three_toys.yaml`` (s = 1 gives about 1,700). For each (metric, s):

* curvimesh: wall time of every stage of :func:`curvimesh.adapt.adapt` and in
  total, vertices per second, peak RSS, and the quality figures of
  :func:`curvimesh.report.mesh_report`;
* Gmsh 4.x BAMG (``Mesh.Algorithm = 7``) on the same metric given as a tensor
  background field, once with its default grading (``Mesh.SmoothRatio`` 1.8)
  and once with ``Mesh.SmoothRatio = 1``; the same figures, computed by
  ``mesh_report`` in our metric on the P1 mesh it makes.

The toy reaches Gmsh as a ``MathEvalAniso`` field whose components are written
out in closed form (g = b I + (a − b) n nᵀ, n the radial unit vector,
a = 1/lmin², b = 1/lmax²: the eigen form R diag(a, b) Rᵀ). Gmsh's ``MinAniso``
field cannot stand for the intersection of three toys: it combines its
fields by ``intersection_conserve_mostaniso``, not by simultaneous reduction.
The three toys reach Gmsh as a ``PostView`` field instead: a list-based
tensor view (``TT``) on a structured background triangulation of spacing
``BACKGROUND_SPACING``, with values from curvimesh's own ``MetricField.tensor``.

Every run is a fresh subprocess (this file with ``--worker``), which reports
its own peak RSS (``VmHWM``, see :func:`_rss_mb`) read right after meshing, before the quality
report. Each configuration runs ``--repeat`` times and medians are quoted,
except that a configuration whose first run takes longer than
``--max-repeat-seconds`` runs once (the ``runs`` column says how many). At each
size the tools take turns (curvimesh, BAMG, BAMG with ``SmoothRatio`` 1, then
again), so that a drift of the machine's speed over the minutes of a size falls
on all of them alike: BAMG's median at the three toys' 10⁵ vertices was 22.8 s
in one run of this script and 15.9 s in the next, with the tools run one after
the other.

Also measured: throughput of :func:`curvimesh.geodesic.shortest_parabola` on
10⁵ unit edges of the toy metric, and a cProfile of one mid-size adapt.
Results go to ``--out`` (markdown) and a log-log plot beside it (``.png``).
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import platform
import pstats
import resource
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
BOX = (-2.0, -2.0, 2.0, 2.0)
EPS = 0.01
H = 0.31622776601683794  # 1/sqrt(10), the width of a ring
#: Spacing of the structured background triangulation of the PostView field.
BACKGROUND_SPACING = 0.02
#: Gmsh settings compared: label -> Mesh.SmoothRatio (None: Gmsh's default, 1.8).
GMSH_SETTINGS = {"gmsh": None, "gmsh-sr1": 1.0}
GMSH_TITLES = {
    "gmsh": "Gmsh BAMG, default grading (SmoothRatio 1.8)",
    "gmsh-sr1": "Gmsh BAMG, SmoothRatio 1",
}
RESULT = "@@RESULT "


@dataclass(frozen=True)
class Ring:
    """One toy metric (paper eq. (1)): size lmin across the circle |x − c| = r0, lmax along it."""

    cx: float
    cy: float
    r0: float
    lmax: float


METRICS: dict[str, tuple[Ring, ...]] = {
    "toy": (Ring(0.0, 0.0, 0.5, 0.3),),
    "three_toys": (
        Ring(0.0, 0.0, 0.5, 0.3),
        Ring(0.8, 0.3, 0.4, 0.25),
        Ring(-0.5, 0.7, 0.6, 0.35),
    ),
}

#: Scales of the default run (about 420, 10³, 3·10³, 10⁴ vertices for the toy;
#: 420, 10³, 1,700 for the three toys) and the ones --large adds (toy: 10⁵,
#: 10⁶; three toys: 3·10³, 10⁴, 10⁵).
SCALES = {"toy": [1.0, 1.54, 2.67, 4.87], "three_toys": [0.5, 0.78, 1.0]}
LARGE_SCALES = {"toy": [15.4, 48.7], "three_toys": [1.34, 2.45, 7.76]}
#: Metrics and scales of the profiled adapts (mid-size of the default run).
PROFILES = [("toy", 1.54), ("three_toys", 0.5)]
THROUGHPUT_EDGES = 100_000


# --------------------------------------------------------------------------- #
# Metrics: YAML for curvimesh, math expressions for Gmsh                       #
# --------------------------------------------------------------------------- #


def metric_yaml(name: str, s: float) -> str:
    """The YAML text of metric ``name`` with eps and every lmax divided by ``s``."""
    rings = METRICS[name]
    head = f"""name: {name}-s{s:g}
domain:
  box: [[{BOX[0]!r}, {BOX[1]!r}], [{BOX[2]!r}, {BOX[3]!r}]]
parameters:
  eps: {EPS / s!r}
  h: {H!r}
  cx: {rings[0].cx!r}
  cy: {rings[0].cy!r}
  r0: {rings[0].r0!r}
  lmax: {rings[0].lmax / s!r}
definitions:
  r: sqrt((x - cx)**2 + (y - cy)**2)
  theta: atan2(y - cy, x - cx)
  lmin: eps + lmax*(1 - exp(-((r - r0)/h)**2))
metric:
"""
    if len(rings) == 1:
        return head + "  eigen: {sizes: [lmin, lmax], angle: theta}\n"
    items = "".join(
        f"    - parameters: {{cx: {g.cx!r}, cy: {g.cy!r}, r0: {g.r0!r}, lmax: {g.lmax / s!r}}}\n"
        "      eigen: {sizes: [lmin, lmax], angle: theta}\n"
        for g in rings
    )
    return head + "  intersection:\n" + items


def ring_expressions(ring: Ring, s: float) -> tuple[str, str, str]:
    """g11, g12, g22 of one scaled ring as text valid both for Gmsh's MathEval and Python.

    Only numbers, x, y, + - * /, sqrt, exp and parentheses (no powers, no
    unary minus before a power: the two parsers disagree on those).
    g = b I + (a − b) n nᵀ with n = (x − c)/|x − c|, a = 1/lmin², b = 1/lmax²;
    the 1e-300 makes it b I at the centre instead of 0/0.
    """
    lmax, eps = ring.lmax / s, EPS / s
    dx, dy = f"(x - {ring.cx!r})", f"(y - {ring.cy!r})"
    r2 = f"({dx}*{dx} + {dy}*{dy})"
    u = f"((sqrt({r2}) - {ring.r0!r})/{H!r})"
    lmin = f"({eps!r} + {lmax!r}*(1 - exp(0 - {u}*{u})))"
    b = f"{1.0 / lmax**2!r}"
    ab = f"(1/({lmin}*{lmin}) - {b})"
    r2s = f"({r2} + 1e-300)"
    return (
        f"{b} + {ab}*{dx}*{dx}/{r2s}",
        f"{ab}*{dx}*{dy}/{r2s}",
        f"{b} + {ab}*{dy}*{dy}/{r2s}",
    )


def _eval_expressions(exprs: tuple[str, str, str], pts: np.ndarray) -> np.ndarray:
    env = {"sqrt": np.sqrt, "exp": np.exp, "x": pts[:, 0], "y": pts[:, 1], "__builtins__": {}}
    g11, g12, g22 = (np.broadcast_to(eval(e, env), len(pts)) for e in exprs)
    return np.stack([np.stack([g11, g12], -1), np.stack([g12, g22], -1)], -2)


def check_translations(scales: dict[str, list[float]]) -> list[str]:
    """Check the metric texts against the repository's files and the Gmsh expressions.

    At s = 1 the generated YAML must give the tensor of ``metrics/NAME.yaml``;
    at every scale the Gmsh expressions (evaluated in Python; intersected by
    :func:`curvimesh.tensors.intersect` for several rings) must give the
    tensor of the generated YAML. Returns one line per check; raises on a
    mismatch.
    """
    from curvimesh.metric import load_metric, load_metric_text
    from curvimesh.tensors import intersect

    rng = np.random.default_rng(1)
    pts = rng.uniform(BOX[0], BOX[2], (2000, 2))
    lines = []
    for name, ss in scales.items():
        ref_file = ROOT / "metrics" / f"{name}.yaml"
        if ref_file.exists():
            err = _rel_err(
                load_metric(ref_file).tensor(pts),
                load_metric_text(metric_yaml(name, 1)).tensor(pts),
            )
            if err > 1e-12:
                raise SystemExit(f"generated {name} metric differs from {ref_file}: {err:.2e}")
            lines.append(f"{name}: generated YAML at s = 1 matches metrics/{name}.yaml ({err:.1e})")
        for s in ss:
            fld = load_metric_text(metric_yaml(name, s))
            parts = [_eval_expressions(ring_expressions(g, s), pts) for g in METRICS[name]]
            g = parts[0]
            for p in parts[1:]:
                g = intersect(g, p).real
            err = _rel_err(fld.tensor(pts), g)
            if err > 1e-9:
                raise SystemExit(f"Gmsh expressions of {name} at s = {s} are wrong: {err:.2e}")
        lines.append(f"{name}: Gmsh expressions match the YAML metric at every scale")
    return lines


def _rel_err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b) / np.linalg.norm(a, axis=(1, 2))[:, None, None]))


# --------------------------------------------------------------------------- #
# Workers (run in a subprocess each)                                           #
# --------------------------------------------------------------------------- #


def _cpu() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def _rss_mb() -> float:
    """The process's peak resident memory (MB): ``VmHWM`` where /proc has it, the
    high-water mark of this program's own address space, else ``ru_maxrss``. Linux
    keeps ``ru_maxrss`` across ``execve`` and starts a child at its parent's size at the
    fork, so a worker's figure was at least the size of the parent it came from (this
    script, 222 MB after it had compiled the metrics it checks)."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux


def _quality(rep: dict) -> dict:
    el, q = rep["edge_length"], rep["quality"]
    return {
        "vertices": rep["vertices"],
        "triangles": rep["triangles"],
        "edge_min": el["min"],
        "edge_max": el["max"],
        "in_range": el["in_range"],
        "q_min": q["min"],
        "q_mean": q["mean"],
        "valid": rep["valid"],
        "efficiency": rep["efficiency"],
    }


def work_adapt(spec: dict) -> dict:
    """One curvimesh adapt: seconds per stage, total, peak RSS, quality (if asked).

    With ``warm_below`` and a first adapt of at most that many seconds, the metric is
    loaded again, as a field of another source (not equal to the first: nothing of the
    first run's is found by it), and adapted a second time in the same process
    (``warm``: its total, from the metric's code to the mesh, numba's kernels loaded by
    the first: what a worker of ``curvimesh batch`` takes for its later metrics)."""
    from curvimesh.adapt import adapt
    from curvimesh.metric import load_metric_text
    from curvimesh.report import mesh_report

    text = metric_yaml(spec["metric"], spec["s"])
    fld = load_metric_text(text)
    base = _rss_mb()
    cpu, t = _cpu(), time.perf_counter()
    _ = fld.kernel  # the metric's compiled code: compiled on a metric's first run, then loaded
    jit = time.perf_counter() - t
    res = adapt(fld)
    total, cpu = time.perf_counter() - t, _cpu() - cpu
    out = {
        "seconds": {"metric code": jit, **res.seconds},
        "total": total,
        "cpu": cpu,
        "rss_mb": _rss_mb(),
        "base_mb": base,
        "vertices": len(res.mesh.vertex_ids),
        "triangles": len(res.mesh.triangles),
    }
    if spec.get("report"):
        out["quality"] = _quality(mesh_report(fld, res.mesh))
    if spec.get("warm_below") is not None and total <= spec["warm_below"]:
        # another source: a field equal to the first would find the first run's
        # searches and measures in the memo tables keyed by the field (MetricField
        # compares by value), which a batch worker's next metric does not
        again = load_metric_text(text, source="<warm run>")
        assert again != fld
        t = time.perf_counter()
        _ = again.kernel
        adapt(again)
        out["warm"] = time.perf_counter() - t
    return out


def _background_view(gmsh, fld) -> int:
    """A list-based tensor view (TT) of the metric on a structured grid; its tag."""
    xmin, ymin, xmax, ymax = BOX
    nx = round((xmax - xmin) / BACKGROUND_SPACING)
    ny = round((ymax - ymin) / BACKGROUND_SPACING)
    gx, gy = np.meshgrid(
        np.linspace(xmin, xmax, nx + 1), np.linspace(ymin, ymax, ny + 1), indexing="ij"
    )
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    ids = np.arange(len(pts)).reshape(nx + 1, ny + 1)
    a, b = ids[:-1, :-1].ravel(), ids[1:, :-1].ravel()
    c, d = ids[1:, 1:].ravel(), ids[:-1, 1:].ravel()
    tris = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    g = fld.tensor(pts)
    full = np.zeros((len(pts), 9))  # row-major 3x3, g33 = 1
    full[:, 0], full[:, 1], full[:, 3], full[:, 4], full[:, 8] = (
        g[:, 0, 0],
        g[:, 0, 1],
        g[:, 0, 1],
        g[:, 1, 1],
        1.0,
    )
    # per triangle: x1 x2 x3, y1 y2 y3, z1 z2 z3, then 9 values per node
    xyz = pts[tris]
    data = np.concatenate(
        [xyz[..., 0], xyz[..., 1], np.zeros((len(tris), 3)), full[tris].reshape(len(tris), 27)],
        axis=1,
    )
    view = gmsh.view.add("metric")
    gmsh.view.addListData(view, "TT", len(tris), data.ravel().tolist())
    return view


def work_gmsh(spec: dict) -> dict:
    """One Gmsh BAMG mesh of the metric: setup and generate seconds, peak RSS, quality."""
    import gmsh

    from curvimesh.mesh import Mesh, signed_areas
    from curvimesh.metric import load_metric_text
    from curvimesh.report import mesh_report

    name, s = spec["metric"], spec["s"]
    fld = load_metric_text(metric_yaml(name, s))
    rings = METRICS[name]
    gmsh.initialize(["gmsh", "-noenv"], readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("bench")
        xmin, ymin, xmax, ymax = BOX
        gmsh.model.occ.addRectangle(xmin, ymin, 0.0, xmax - xmin, ymax - ymin)
        gmsh.model.occ.synchronize()
        base = _rss_mb()
        cpu, t = _cpu(), time.perf_counter()
        if len(rings) == 1:
            field = gmsh.model.mesh.field.add("MathEvalAniso")
            g11, g12, g22 = ring_expressions(rings[0], s)
            for key, expr in zip(
                ("M11", "M12", "M13", "M22", "M23", "M33"),
                (g11, g12, "0", g22, "0", "1"),
                strict=True,
            ):
                gmsh.model.mesh.field.setString(field, key, expr)
            kind = "MathEvalAniso"
        else:
            view = _background_view(gmsh, fld)
            field = gmsh.model.mesh.field.add("PostView")
            gmsh.model.mesh.field.setNumber(field, "ViewTag", view)
            kind = "PostView"
        gmsh.model.mesh.field.setAsBackgroundMesh(field)
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
        gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
        gmsh.option.setNumber("Mesh.Algorithm", 7)
        if spec.get("smooth_ratio") is not None:
            gmsh.option.setNumber("Mesh.SmoothRatio", spec["smooth_ratio"])
        setup = time.perf_counter() - t
        t = time.perf_counter()
        gmsh.model.mesh.generate(2)
        generate = time.perf_counter() - t
        cpu = _cpu() - cpu
        rss = _rss_mb()
        tags, xyz, _ = gmsh.model.mesh.getNodes()
        _, _, enodes = gmsh.model.mesh.getElements(2)
        version = gmsh.__version__
    finally:
        gmsh.finalize()
    pts = np.asarray(xyz).reshape(-1, 3)[:, :2]
    index = np.full(int(np.max(tags)) + 1, -1, dtype=np.int64)
    index[np.asarray(tags, dtype=np.int64)] = np.arange(len(tags))
    tris = index[np.concatenate([np.asarray(e, dtype=np.int64) for e in enodes]).reshape(-1, 3)]
    used, tris = np.unique(tris, return_inverse=True)
    pts, tris = pts[used], tris.reshape(-1, 3)
    flip = signed_areas(pts, tris) < 0
    tris[flip] = tris[flip][:, [0, 2, 1]]
    out = {
        "seconds": {"setup": setup, "generate": generate},
        "total": setup + generate,
        "cpu": cpu,
        "rss_mb": rss,
        "base_mb": base,
        "vertices": len(pts),
        "triangles": len(tris),
        "field": kind,
        "version": version,
    }
    if spec.get("report"):
        out["quality"] = _quality(mesh_report(fld, Mesh(pts, tris, BOX)))
    return out


def work_profile(spec: dict) -> dict:
    """cProfile of one adapt: the top entries by cumulative and by own time."""
    from curvimesh.adapt import adapt
    from curvimesh.metric import load_metric_text

    fld = load_metric_text(metric_yaml(spec["metric"], spec["s"]))
    prof = cProfile.Profile()
    t = time.perf_counter()
    prof.enable()
    res = adapt(fld)
    prof.disable()
    total = time.perf_counter() - t
    tables = {}
    for key in ("cumulative", "tottime"):
        buf = io.StringIO()
        st = pstats.Stats(prof, stream=buf).strip_dirs().sort_stats(key)
        st.print_stats(spec.get("top", 15) if key == "cumulative" else 10)
        text = buf.getvalue()
        start = text.find("   ncalls")
        tables[key] = text[start:].rstrip() if start >= 0 else text.rstrip()
    st = pstats.Stats(prof)
    own = sorted(
        (
            (v[2], k[2] if k[0] == "~" else f"{Path(k[0]).name}:{k[1]}({k[2]})")
            for k, v in st.stats.items()
        ),
        reverse=True,
    )
    return {
        "total": total,
        "vertices": len(res.mesh.vertex_ids),
        "seconds": dict(res.seconds),
        "tables": tables,
        "top_own": own[:8],
        "profiled_seconds": st.total_tt,
    }


def work_throughput(spec: dict) -> dict:
    """Edges per second of shortest_parabola on random unit edges of the toy metric."""
    from curvimesh.geodesic import shoot, shortest_parabola
    from curvimesh.metric import load_metric_text

    fld = load_metric_text(metric_yaml("toy", 1.0))
    n, repeat = spec["edges"], spec["repeat"]
    rng = np.random.default_rng(0)
    x0 = rng.uniform(BOX[0] + 0.2, BOX[2] - 0.2, (n, 2))
    angle = rng.uniform(0.0, 2 * np.pi, n)
    t = time.perf_counter()
    shot = shoot(fld, x0, np.column_stack([np.cos(angle), np.sin(angle)]), 1.0)
    shoot_s = time.perf_counter() - t
    x0, x1 = x0[shot.ok], shot.end[shot.ok]
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        par = shortest_parabola(fld, x0, x1)
        times.append(time.perf_counter() - t)
    return {
        "edges": len(x0),
        "times": times,
        "shoot_seconds": shoot_s,
        "length_median": float(np.median(par.length)),
        "length_max": float(np.max(par.length)),
        "rss_mb": _rss_mb(),
    }


WORKERS = {
    "adapt": work_adapt,
    "gmsh": work_gmsh,
    "profile": work_profile,
    "throughput": work_throughput,
}


def run_worker(spec: dict) -> dict:
    """Run one worker in a fresh Python process; its result, or {"error": ...}."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(spec)]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, check=False)
    for line in reversed(proc.stdout.splitlines()):
        if line.startswith(RESULT):
            return json.loads(line[len(RESULT) :])
    tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
    return {"error": f"exit {proc.returncode}: {tail}"}


# --------------------------------------------------------------------------- #
# Driver                                                                       #
# --------------------------------------------------------------------------- #


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def measure(specs: dict[str, dict], repeat: int, max_repeat_seconds: float) -> dict[str, dict]:
    """Run each configuration of ``specs`` (by name) up to ``repeat`` times, in turns
    (one run of each, then again); medians of each one's times.

    Only the first run of each computes the quality report (runs are
    deterministic: same seed, same mesh). A configuration's repeats stop after a
    first run longer than ``max_repeat_seconds``, or at an error.
    """
    runs: dict[str, list[dict]] = {name: [] for name in specs}
    errors: dict[str, dict] = {}
    for i in range(repeat):
        for name, spec in specs.items():
            if name in errors or (i > 0 and runs[name][0]["total"] > max_repeat_seconds):
                continue
            r = run_worker({**spec, "report": i == 0})
            if "error" in r:
                errors[name] = {"error": r["error"], "runs": len(runs[name])}
            else:
                runs[name].append(r)
    return {name: errors.get(name) or _summary(runs[name]) for name in specs}


def _summary(runs: list[dict]) -> dict:
    """Medians of the times of a configuration's runs, its first run's mesh figures."""
    stages = list(runs[0]["seconds"])
    out = {
        "runs": len(runs),
        "seconds": {k: statistics.median(r["seconds"].get(k, 0.0) for r in runs) for k in stages},
        "total": statistics.median(r["total"] for r in runs),
        "totals": [r["total"] for r in runs],
        "cpu": statistics.median(r["cpu"] for r in runs),
        "rss_mb": statistics.median(r["rss_mb"] for r in runs),
        "base_mb": statistics.median(r["base_mb"] for r in runs),
        "vertices": runs[0]["vertices"],
        "triangles": runs[0]["triangles"],
        "quality": runs[0].get("quality"),
    }
    warm = [r["warm"] for r in runs if "warm" in r]
    if warm:
        out["warm"] = statistics.median(warm)
    counts = [r["vertices"] for r in runs]
    if min(counts) != max(counts):
        out["vertex_range"] = [min(counts), max(counts)]
    for key in ("field", "version"):
        if key in runs[0]:
            out[key] = runs[0][key]
    return out


def fit_exponent(n: list[float], t: list[float]) -> float | None:
    """p in t ∝ nᵖ, least squares on logs (None with fewer than two sizes)."""
    if len(n) < 2:
        return None
    return float(np.polyfit(np.log(n), np.log(t), 1)[0])


def _fmt(v: object, digits: int = 3) -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "NO"
    if isinstance(v, int):
        return f"{v:,}"
    if isinstance(v, float):
        if v == 0:
            return "0"
        if abs(v) >= 100:
            return f"{v:,.0f}"
        return f"{v:.{digits}g}"
    return str(v)


def _table(header: list[str], rows: list[list[object]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---:" for _ in header) + "|"]
    lines += ["| " + " | ".join(_fmt(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def tool_table(results: dict[float, dict]) -> str:
    """One row per scale: counts, seconds per stage, total, rate, memory, quality."""
    ok = {s: r for s, r in results.items() if "error" not in r}
    stages: list[str] = []
    for r in ok.values():
        stages += [k for k in r["seconds"] if k not in stages]
    warm = any("warm" in r for r in ok.values())
    header = ["s", "vertices", "triangles", "runs", *[f"{k} s" for k in stages], "total s"]
    header += ["warm s"] if warm else []
    header += ["CPU s", "vertices/s", "peak RSS MB (base)", "edge min", "edge max", "in range"]
    header += ["q min", "q mean", "valid", "efficiency"]
    rows = []
    for s, r in results.items():
        if "error" in r:
            rows.append([s, f"failed: {r['error']}"] + [None] * (len(header) - 2))
            continue
        q = r["quality"] or {}
        rows.append(
            [
                s,
                r["vertices"],
                r["triangles"],
                f"{r['runs']}*" if "vertex_range" in r else r["runs"],
                *[r["seconds"].get(k) for k in stages],
                r["total"],
                *([r.get("warm")] if warm else []),
                r["cpu"],
                r["vertices"] / r["total"],
                f"{r['rss_mb']:.0f} ({r['base_mb']:.0f})",
                q.get("edge_min"),
                q.get("edge_max"),
                q.get("in_range"),
                q.get("q_min"),
                q.get("q_mean"),
                q.get("valid"),
                q.get("efficiency"),
            ]
        )
    text = _table(header, rows)
    varying = [
        f"{r['vertex_range'][0]:,}–{r['vertex_range'][1]:,} at s = {s:g}"
        for s, r in results.items()
        if "vertex_range" in r
    ]
    if varying:
        text += (
            "\n\n\\* the vertex count differed between runs ("
            + "; ".join(varying)
            + "); counts and quality figures are those of the first run."
        )
    return text


def exponents(results: dict[float, dict]) -> dict[str, float | None]:
    """Fitted exponents of the total and of every stage against the vertex count."""
    ok = [r for r in results.values() if "error" not in r]
    n = [r["vertices"] for r in ok]
    out = {
        "total": fit_exponent(n, [r["total"] for r in ok]),
        "CPU": fit_exponent(n, [r["cpu"] for r in ok]),
    }
    for k in ok[0]["seconds"] if ok else []:
        t = [max(r["seconds"].get(k, 0.0), 1e-6) for r in ok]
        out[k] = fit_exponent(n, t)
    return out


def make_plot(all_results: dict, path: Path) -> None:
    """Log-log plot of total time against vertices, one panel per metric."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(all_results)
    fig, axes = plt.subplots(1, len(names), figsize=(6 * len(names), 4.5), squeeze=False)
    styles = {"curvimesh": "o-", "gmsh": "s--", "gmsh-sr1": "^:"}
    labels = {"curvimesh": "curvimesh adapt", **GMSH_TITLES}
    for ax, name in zip(axes[0], names, strict=True):
        for tool, res in all_results[name].items():
            ok = [r for r in res.values() if "error" not in r]
            if not ok:
                continue
            n = [r["vertices"] for r in ok]
            t = [r["total"] for r in ok]
            p = fit_exponent(n, t)
            lab = labels[tool] + (f" (t ∝ n^{p:.2f})" if p is not None else "")
            ax.loglog(n, t, styles[tool], label=lab)
        ax.set_title(f"metric: {name}")
        ax.set_xlabel("vertices")
        ax.set_ylabel("wall time (s), median")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def cpu_model() -> str:
    """The processor as ``/proc/cpuinfo`` names it (with its family and model numbers,
    which a virtual machine's bare name such as "AMD EPYC" leaves out), else
    ``platform.processor()``: the ratio to BAMG differs between machines of the same size
    (BAMG ran 1.3 - 1.8 times as long on some as on others, curvimesh 1.1 - 1.2)."""
    fields: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                fields.setdefault(key.strip(), value.strip())
    except OSError:
        return platform.processor() or "unknown processor"
    name = fields.get("model name") or platform.processor() or "unknown processor"
    if "cpu family" in fields and "model" in fields:
        name += f", family {fields['cpu family']} model {fields['model']}"
    return name


def write_markdown(ctx: dict, all_results: dict, throughput: dict, profiles: dict) -> str:
    out = ["# curvimesh benchmark: adapt against Gmsh BAMG", ""]
    out += [
        f"Generated by `{ctx['command']}` on {ctx['date']} in {ctx['wall']:.0f} s "
        f"({ctx['cpus']} CPUs: {ctx['cpu_model']}; load average {ctx['load_before']} before, "
        f"{ctx['load_after']} after; the machine was shared, so times are noisy).",
        f"Python {platform.python_version()}, numpy {np.__version__}, Gmsh {ctx['gmsh']}.",
        "",
        "Times are medians over `runs` fresh processes (a configuration whose first run "
        f"took over {ctx['max_repeat_seconds']:g} s ran once), the tools taking turns at "
        "each size (curvimesh, then each Gmsh setting, then again). Peak RSS is the process's "
        "own high-water mark (`VmHWM`) right after meshing (in brackets: before meshing, "
        "after imports and "
        "metric loading). Quality figures are `curvimesh.report.mesh_report` in our metric, "
        "for Gmsh on its P1 mesh: edge lengths in the metric (in range: 0.7 ≤ L ≤ 1.4), "
        "quality (4), efficiency = triangles / ideal unit-triangle count. "
        "Gmsh's time is field setup plus `generate(2)`.",
        "",
        f"curvimesh ran its compiled kernels on {ctx['threads']} threads (numba); its total "
        "includes the `metric code` column: compiling the metric's scalar code on a metric's "
        "first run (about 1 s), loading it from the cache on the later ones, and numba's start "
        "(about 0.2 s, its first compiled call); the loads of its compiled kernels from their "
        "cache (about 0.2 s) fall in the stages that first call them. `warm s`: the metric "
        "loaded again and adapted a second "
        "time in the same process (where the first run took at most "
        f"{ctx['max_repeat_seconds']:g} s), numba's kernels already loaded, as for a "
        "`curvimesh batch` worker's later metrics (the median over the runs). A warm-up run "
        f"before timing took {ctx['warm_up']:.1f} s (it compiles numba's kernels, about "
        "15 s, when their cache is cold, as after a fresh install).",
        "",
        "Checks before timing: " + "; ".join(ctx["checks"]) + ".",
        "",
        f"![time against vertices]({ctx['plot']})",
        "",
    ]
    for name, tools in all_results.items():
        out += [f"## Metric `{name}` (eps and lmax divided by s)", ""]
        out += ["### curvimesh adapt", "", tool_table(tools["curvimesh"]), ""]
        for tool, title in GMSH_TITLES.items():
            field = next((r.get("field") for r in tools[tool].values() if "field" in r), "?")
            out += [f"### {title}, {field} field", "", tool_table(tools[tool]), ""]
        out += ["### Time ratio curvimesh / Gmsh", ""]
        header = ["s", "curvimesh vertices", "curvimesh s"]
        for tool in GMSH_TITLES:
            header += [f"{tool} vertices", f"{tool} s", "time ratio", "warm ratio", "CPU ratio"]
            header += ["per vertex"]
        rows = []
        for s, c in tools["curvimesh"].items():
            if "error" in c:
                continue
            row: list[object] = [s, c["vertices"], c["total"]]
            for tool in GMSH_TITLES:
                g = tools[tool].get(s, {})
                if "error" in g or not g:
                    row += [None] * 6
                    continue
                ratio = c["total"] / g["total"]
                warm = c["warm"] / g["total"] if "warm" in c else None
                cpu_ratio = c["cpu"] / g["cpu"]
                per_vertex = ratio * g["vertices"] / c["vertices"]
                row += [g["vertices"], g["total"], ratio, warm, cpu_ratio, per_vertex]
            rows.append(row)
        out += [
            _table(header, rows),
            "",
            "Time ratio: wall times (curvimesh total / Gmsh setup + generate); warm ratio: "
            "the same with curvimesh's `warm s` (a second adapt in the same process, numba's "
            "kernels loaded); CPU ratio: the time ratio's with user + system CPU seconds, less "
            "sensitive to a shared machine; per vertex: the time ratio times Gmsh's vertex "
            "count over curvimesh's.",
            "",
        ]
        out += ["### Growth exponent p of time ∝ vertices^p (np.polyfit on logs)", ""]
        for tool, res in tools.items():
            ex = exponents(res)
            parts = [f"{k} {v:.2f}" for k, v in ex.items() if v is not None]
            out.append(f"- {tool}: " + (", ".join(parts) if parts else "fewer than two sizes"))
        out.append("")
    if throughput:
        out += ["## Shortest parabola throughput", ""]
        if "error" in throughput:
            out += [f"failed: {throughput['error']}", ""]
        else:
            med = statistics.median(throughput["times"])
            shoot_rate = throughput["edges"] / throughput["shoot_seconds"]
            out += [
                f"`curvimesh.geodesic.shortest_parabola(fld, x0, x1)` (default options) on "
                f"{throughput['edges']:,} unit edges of the toy metric (x0 uniform in the box "
                "shrunk by 0.2, x1 the end of a geodesic of length 1 in a random direction): "
                f"median {med:.2f} s of {len(throughput['times'])} "
                f"({', '.join(f'{t:.2f}' for t in throughput['times'])}), "
                f"**{throughput['edges'] / med:,.0f} edges/s**. Parabola lengths: median "
                f"{throughput['length_median']:.6f}, max {throughput['length_max']:.4f} (≥ 1, "
                f"the geodesic being shortest). Shooting the geodesics took "
                f"{throughput['shoot_seconds']:.2f} s ({shoot_rate:,.0f} "
                f"geodesics/s). Peak RSS {throughput['rss_mb']:.0f} MB.",
                "",
            ]
    for (name, scale), prof in profiles.items():
        out += [f"## Profile: `{name}` at s = {scale}", ""]
        if "error" in prof:
            out += [f"failed: {prof['error']}", ""]
            continue
        stages = ", ".join(f"{k} {v:.1f} s" for k, v in prof["seconds"].items())
        total = prof["profiled_seconds"]
        own = "; ".join(
            f"`{f}` {t:.1f} s ({100 * t / total:.0f} %)" for t, f in prof["top_own"][:6]
        )
        out += [
            f"cProfile of one adapt ({prof['vertices']:,} vertices, {prof['total']:.1f} s "
            f"under the profiler: {stages}).",
            "",
            f"Largest own times: {own}.",
            "",
            "Top entries by cumulative time:",
            "",
            "```",
            prof["tables"]["cumulative"],
            "```",
            "",
            "Top entries by own time:",
            "",
            "```",
            prof["tables"]["tottime"],
            "```",
            "",
        ]
    return "\n".join(out)


def summary(all_results: dict, throughput: dict) -> str:
    """A short plain-text summary for stdout."""
    lines = []
    for name, tools in all_results.items():
        lines.append(f"{name}:")
        for tool, res in tools.items():
            for s, r in res.items():
                if "error" in r:
                    lines.append(f"  {tool:10s} s={s:<5g} failed: {r['error']}")
                    continue
                q = r["quality"] or {}
                lines.append(
                    f"  {tool:10s} s={s:<5g} {r['vertices']:>8,} vertices  {r['total']:8.2f} s "
                    f"(runs {r['runs']})  {r['rss_mb']:6.0f} MB  edges "
                    f"[{q.get('edge_min', 0):.2f}, {q.get('edge_max', 0):.2f}] "
                    f"in range {q.get('in_range', 0):.3f}  q min {q.get('q_min', 0):.3f} "
                    f"mean {q.get('q_mean', 0):.3f}  efficiency {q.get('efficiency', 0):.2f}"
                )
            p = exponents(res)["total"]
            if p is not None:
                lines.append(f"  {tool:10s} exponent {p:.2f}")
    if throughput and "error" not in throughput:
        med = statistics.median(throughput["times"])
        lines.append(f"shortest_parabola: {throughput['edges'] / med:,.0f} edges/s")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--large", action="store_true", help="add the big sizes (hours)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per configuration (median)")
    ap.add_argument(
        "--max-repeat-seconds",
        type=float,
        default=25.0,
        help="run a configuration once if its first run takes longer",
    )
    ap.add_argument("--out", type=Path, default=HERE / "results.md")
    ap.add_argument("--metrics", default=",".join(METRICS), help="comma-separated metric names")
    ap.add_argument("--scales", help="comma-separated scales s (instead of the default list)")
    ap.add_argument("--no-extras", action="store_true", help="skip the throughput and profile")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.worker:
        spec = json.loads(args.worker)
        print(RESULT + json.dumps(WORKERS[spec["kind"]](spec)), flush=True)
        return 0

    names = [m for m in args.metrics.split(",") if m]
    for m in names:
        if m not in METRICS:
            ap.error(f"unknown metric {m!r}; choose from {', '.join(METRICS)}")
    if args.scales:
        scales = {m: [float(v) for v in args.scales.split(",")] for m in names}
    else:
        scales = {m: SCALES[m] + (LARGE_SCALES[m] if args.large else []) for m in names}

    t0 = time.perf_counter()
    import numba

    log("warm-up run (toy, s = 1): compiles numba's kernels if their cache is cold")
    warm = time.perf_counter()
    run_worker({"kind": "adapt", "metric": "toy", "s": 1.0})
    warm = time.perf_counter() - warm
    ctx = {
        "warm_up": warm,
        "threads": numba.config.NUMBA_NUM_THREADS,
        "command": "python bench/run.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "cpus": os.cpu_count(),
        "cpu_model": cpu_model(),
        "load_before": " ".join(f"{v:.1f}" for v in os.getloadavg()),
        "max_repeat_seconds": args.max_repeat_seconds,
    }
    ctx["command"] = ctx["command"].strip()
    ctx["checks"] = check_translations(scales)
    for line in ctx["checks"]:
        log(line)

    all_results: dict[str, dict[str, dict[float, dict]]] = {}
    for name in names:
        tools: dict[str, dict[float, dict]] = {"curvimesh": {}, **{k: {} for k in GMSH_SETTINGS}}
        for s in scales[name]:
            base = {"metric": name, "s": s}
            specs = {"curvimesh": {**base, "kind": "adapt", "warm_below": args.max_repeat_seconds}}
            for tool, ratio in GMSH_SETTINGS.items():
                specs[tool] = {**base, "kind": "gmsh", "smooth_ratio": ratio}
            got = measure(specs, args.repeat, args.max_repeat_seconds)
            for tool, r in got.items():
                tools[tool][s] = r
                log(f"{name} s={s}: {tool} {r.get('vertices')} vertices, {r.get('total', 0):.2f} s")
        all_results[name] = tools

    throughput: dict = {}
    profiles: dict = {}
    if not args.no_extras:
        log(f"shortest_parabola throughput on {THROUGHPUT_EDGES:,} edges")
        throughput = run_worker(
            {"kind": "throughput", "edges": THROUGHPUT_EDGES, "repeat": args.repeat}
        )
        for name, scale in PROFILES:
            if name in names:
                log(f"profile of {name} at s = {scale}")
                spec = {"kind": "profile", "metric": name, "s": scale}
                profiles[name, scale] = run_worker(spec)

    ctx["gmsh"] = next(
        (r["version"] for t in all_results.values() for r in t["gmsh"].values() if "version" in r),
        "?",
    )
    ctx["wall"] = time.perf_counter() - t0
    ctx["load_after"] = " ".join(f"{v:.1f}" for v in os.getloadavg())
    args.out.parent.mkdir(parents=True, exist_ok=True)
    ctx["plot"] = args.out.with_suffix(".png").name  # beside the markdown
    args.out.write_text(write_markdown(ctx, all_results, throughput, profiles))
    make_plot(all_results, args.out.with_suffix(".png"))
    print(summary(all_results, throughput))
    log(f"wrote {args.out} and {args.out.with_suffix('.png')} in {ctx['wall']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
