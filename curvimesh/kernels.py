"""Compiled inner loops (numba): the metric at a point, parabola lengths, geodesic shots.

The vectorised numpy code of :mod:`curvimesh.geodesic` spends most of its
time outside arithmetic: temporaries of shape (rows, quadrature points, 2, 2),
einsums, and Python overhead on the small arrays of an iterative search's
last rows. Here the same algorithms run one row at a time in machine code,
the rows of large calls in parallel (``prange``), calling the metric as a compiled scalar
function ``g(x, y)`` (a numba ``cfunc`` built once per metric field by
:func:`compile_metric`, passed to the kernels as a first-class function, so
that each kernel is compiled once, cached on disk, and serves every metric).

Scalar metric functions:

* ``g(x, y) -> (g11, g12, g22)`` (:data:`SIG_G`);
* ``gd(x, y) -> (g11, g12, g22, ∂ₓg11, ∂ₓg12, ∂ₓg22, ∂ᵧg11, ∂ᵧg12, ∂ᵧg22)`` (:data:`SIG_GD`);

both NaN wherever the metric is not finite and positive definite.

Each kernel mirrors, step for step, the numpy function of :mod:`curvimesh.geodesic`
it stands in for (which stays the reference, and serves metrics with no scalar
form); results agree to rounding (the tests compare them). Floating-point
semantics are numpy's (``error_model="numpy"``: x/0 is ±inf or NaN, no exception),
not fast-math, so NaN marks undefined metric values as in the numpy code.

The mesh's edge table (:func:`edge_table`, :func:`edge_triangles`) is integer
work: a counting sort and linear passes, O(m + n) for m triangles on n nodes,
where :class:`curvimesh.mesh.Mesh` sorted with numpy; the arrays are the same.

This module is the only user of numba (STYLE: each third-party edge in one module).
"""

from __future__ import annotations

import hashlib
import importlib.util
import math
import os
import re
import sys
from collections.abc import Callable, Mapping
from functools import cache
from pathlib import Path

# GNU OpenMP (numba's threading layer where libgomp is found) spins while it waits
# for its threads: with another process on the other core, adapt of the 9,746-vertex
# toy took 19 s instead of 8 (one run each); waiting passively, 8 s. Set before numba
# starts it.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numba
import numpy as np
from numba import float64, njit, prange, types
from numpy.typing import NDArray

#: Signature of a scalar metric: (x, y) ↦ (g11, g12, g22).
SIG_G = types.UniTuple(float64, 3)(float64, float64)
#: Signature of a scalar metric with its first derivatives: (x, y) ↦ 9 values.
SIG_GD = types.UniTuple(float64, 9)(float64, float64)
#: Signature of a scalar function of (x, y).
SIG_F = float64(float64, float64)

_JIT = {"cache": True, "error_model": "numpy", "nogil": True}


#: Rows from which a row kernel spreads its rows over numba's threads
#: (``NUMBA_NUM_THREADS``, by default one per core). Measured on two cores: adapt of
#: the 9,746-vertex toy 3.2 s with 20,000 (only the largest calls in parallel), 2.9 s
#: with 2,000, 2.8 s with 500; two such runs at once, 3.8-3.9 s each (4.0-4.2 s each
#: on one thread).
PARALLEL_ROWS = 500

#: The same for the kernels whose rows are searches (shortest parabolas, closeness
#: tests, shots: tens to hundreds of metric evaluations a row).
SEARCH_PARALLEL_ROWS = 64

#: Rows a thread takes at a time in the adaptive measures (:func:`_row_kernel`'s
#: ``chunk``). Measured on the 19,130 triangles of the three toys at 9,644 vertices
#: (report accuracy, two threads): 0.38 s in two equal shares (the triangles across the
#: kinks, which subdivide deepest, lie together), 0.26 s by chunks of 4 to 64, 0.35 s of 1.
ADAPTIVE_CHUNK = 16


def _row_kernel(
    py: Callable | None = None,
    *,
    min_rows: int | None = None,
    rows_arg: int = 1,
    chunk: int = 0,
) -> Callable:
    """A kernel whose rows (``prange``) are independent, compiled once with
    ``parallel=True`` and run on numba's threads for calls of at least ``min_rows``
    rows (default :data:`PARALLEL_ROWS`), on the calling thread alone below (same
    results).

    One compiled variant, not a serial and a parallel one: every variant a run
    calls is loaded from numba's cache at its first call (about 5 ms each, 0.1 s of
    a run for the twins), against about 3 µs more per small call.

    The rows are those of argument ``rows_arg`` (default the second, after the metric
    function). With ``chunk``, the threads take the rows ``chunk`` at a time as they
    finish them (``numba.set_parallel_chunksize``) instead of one equal share each:
    for rows whose cost varies by orders of magnitude, as an adaptive subdivision's."""
    if py is None:
        return lambda f: _row_kernel(f, min_rows=min_rows, rows_arg=rows_arg, chunk=chunk)
    parallel = njit(parallel=True, **_JIT)(py)

    def run(*args):
        n = args[rows_arg].shape[0]
        threads = numba.get_num_threads()
        if threads == 1:
            return parallel(*args)
        if n >= (min_rows or PARALLEL_ROWS):
            if not chunk:
                return parallel(*args)
            before = numba.set_parallel_chunksize(chunk)
            try:
                return parallel(*args)
            finally:
                numba.set_parallel_chunksize(before)
        numba.set_num_threads(1)
        try:
            return parallel(*args)
        finally:
            numba.set_num_threads(threads)

    run.__doc__, run.__name__ = py.__doc__, py.__name__
    run.parallel = parallel
    return run


# --------------------------------------------------------------------------- #
# Scalar helpers for generated metric code                                     #
# --------------------------------------------------------------------------- #


@njit(**_JIT)
def sign(u):
    """sign(u): −1, 0 or 1 (NaN for NaN), as sympy's ``sign`` of a real."""
    if u > 0:
        return 1.0
    if u < 0:
        return -1.0
    if u == 0:
        return 0.0
    return u


@njit(**_JIT)
def _re(z):
    return z.real


@njit(**_JIT)
def _nested(a11, a12, a22, b11, b12, b22):
    """Which metric contains the other: 1 if M2 − M1 is positive semidefinite (M2
    whole is the intersection), −1 if negative semidefinite (M1 whole), 0 otherwise
    (decided on real parts: det(M2 − M1) ≥ 0 and the sign of its trace)."""
    d11 = _re(b11) - _re(a11)
    d12 = _re(b12) - _re(a12)
    d22 = _re(b22) - _re(a22)
    if d11 * d22 - d12 * d12 >= 0.0:
        return 1 if d11 + d22 >= 0.0 else -1
    return 0


@njit(**_JIT)
def intersect(a11, a12, a22, b11, b12, b22):
    """Metric intersection by simultaneous reduction, one point, real or complex.

    The scalar twin of :func:`curvimesh.tensors.intersect_components` (same
    formula, same branches chosen on real parts, same degenerate case). The
    compiled metrics call it on reals; :func:`intersect_d` carries the same
    formula with its derivatives; with complex arguments it gives them by the
    complex step (the tests' reference for :func:`intersect_d`).

    Nested metrics (:func:`_nested`) give the larger one, unchanged; otherwise
    s₋ < 1 < s₊ and only s₊'s term differs from M1 (see the numpy twin).
    """
    nested = _nested(a11, a12, a22, b11, b12, b22)
    if nested > 0:
        return b11, b12, b22
    if nested < 0:
        return a11, a12, a22
    qa = a11 * a22 - a12 * a12
    qb = -(a11 * b22 + a22 * b11 - 2.0 * a12 * b12)
    qc = b11 * b22 - b12 * b12
    disc = qb * qb - 4.0 * qa * qc
    inv2qa = 0.5 / qa
    if _re(disc) <= 1e-10 * (_re(qb) * _re(qb)):  # degenerate: max(1, s) M1
        s0 = -qb * inv2qa
        big = s0 if _re(s0) > 1.0 else 1.0 + 0.0 * s0
        return big * a11, big * a12, big * a22
    s = (np.sqrt(disc) - qb) * inv2qa  # s₊ (qa > 0)
    c11 = b11 - s * a11
    c12 = b12 - s * a12
    c22 = b22 - s * a22
    if abs(_re(c11)) >= abs(_re(c22)):
        v1 = -c12
        v2 = c11
    else:
        v1 = c22
        v2 = -c12
    w1 = a11 * v1 + a12 * v2
    w2 = a12 * v1 + a22 * v2
    f = (s - 1.0) / (v1 * w1 + v2 * w2)
    fw1 = f * w1
    return a11 + fw1 * w1, a12 + fw1 * w2, a22 + f * w2 * w2


# Forward-mode arithmetic for intersect_d: a quantity u travels as the triple
# (u, ∂ₓu, ∂ᵧu); each helper computes the value exactly as intersect does (same
# operations in the same order, hence the same bits) and the two derivatives by
# the chain rule of that one operation.


@njit(**_JIT)
def _dual(g, i):
    """Component i (0: 11, 1: 12, 2: 22) of a 9-tuple (g, ∂ₓg, ∂ᵧg) as (u, ∂ₓu, ∂ᵧu)."""
    return (g[i], g[i + 3], g[i + 6])


@njit(**_JIT)
def _d_add(u, v):
    """u + v: ∂(u + v) = ∂u + ∂v."""
    return (u[0] + v[0], u[1] + v[1], u[2] + v[2])


@njit(**_JIT)
def _d_sub(u, v):
    """u − v: ∂(u − v) = ∂u − ∂v."""
    return (u[0] - v[0], u[1] - v[1], u[2] - v[2])


@njit(**_JIT)
def _d_scale(c, u):
    """c u for a constant c: ∂(c u) = c ∂u."""
    return (c * u[0], c * u[1], c * u[2])


@njit(**_JIT)
def _d_mul(u, v):
    """u v: ∂(u v) = ∂u v + u ∂v."""
    return (u[0] * v[0], u[1] * v[0] + u[0] * v[1], u[2] * v[0] + u[0] * v[2])


@njit(**_JIT)
def _d_div(u, v):
    """q = u / v: ∂q = (∂u − q ∂v) / v."""
    q = u[0] / v[0]
    return (q, (u[1] - q * v[1]) / v[0], (u[2] - q * v[2]) / v[0])


@njit(**_JIT)
def _d_sqrt(u):
    """r = √u: ∂r = ∂u / (2 r)."""
    r = np.sqrt(u[0])
    return (r, u[1] / (2.0 * r), u[2] / (2.0 * r))


@njit(**_JIT)
def _d_max1(s):
    """max(s, 1) as :func:`intersect` takes it: s and ∂s if s > 1, else 1 and 0
    (the derivative of the branch chosen at the point, one-sided at s = 1; a NaN
    in s stays NaN, as 1 + 0 s)."""
    if s[0] > 1.0:
        return s
    return (1.0 + 0.0 * s[0], 0.0 * s[1], 0.0 * s[2])


@njit(**_JIT)
def intersect_d(a, b):
    """Intersection of two 9-tuples (g, ∂ₓg, ∂ᵧg) with its derivatives, forward mode.

    The intersection I(M1, M2) of :func:`intersect` is M2 or M1 itself where one
    contains the other (their derivatives then are I's), and otherwise a
    composition of arithmetic and one square root: with q(s) = det(M2 − s M1) =
    qa s² + qb s + qc, disc = qb² − 4 qa qc, the larger root s₊ = (√disc − qb) / (2 qa),
    the null vector v of C = M2 − s₊ M1 (v = (−c12, c11) or (c22, −c12)), w = M1 v,
    λ = vᵀw, and I = M1 + (s₊ − 1) / λ · w wᵀ (max(s, 1) M1 where s1 ≈ s2). Its derivative
    along x_k is the directional derivative of that composition along (∂ₖM1, ∂ₖM2):
    every quantity u is carried with (∂ₓu, ∂ᵧu) and each line's chain rule gives
    theirs (e.g. ∂√disc = ∂disc / (2√disc), ∂(u/v) = (∂u − (u/v) ∂v) / v), both
    directions in one pass over the shared values. The branches (nested metrics,
    degenerate case, null-vector row, max(s, 1)) are chosen on the values, as
    :func:`intersect` does, so the derivative is that of the branch selected at the
    point: where I is not smooth, a one-sided derivative. The values are
    :func:`intersect`'s, bit for bit; the derivatives are the complex step's of
    :func:`curvimesh.tensors.intersect_with_derivatives` to rounding (which the
    two amplify alike where s1 ≈ s2). A non-finite derivative of the metric kept
    stays in the derivatives (the complex step spread one along y into the values too).
    """
    nested = _nested(a[0], a[1], a[2], b[0], b[1], b[2])
    if nested > 0:
        return b
    if nested < 0:
        return a
    a11, a12, a22 = _dual(a, 0), _dual(a, 1), _dual(a, 2)
    b11, b12, b22 = _dual(b, 0), _dual(b, 1), _dual(b, 2)
    qa = _d_sub(_d_mul(a11, a22), _d_mul(a12, a12))
    qb = _d_scale(
        -1.0,
        _d_sub(_d_add(_d_mul(a11, b22), _d_mul(a22, b11)), _d_mul(_d_scale(2.0, a12), b12)),
    )
    qc = _d_sub(_d_mul(b11, b22), _d_mul(b12, b12))
    disc = _d_sub(_d_mul(qb, qb), _d_mul(_d_scale(4.0, qa), qc))
    inv2qa = _d_div((0.5, 0.0, 0.0), qa)
    if disc[0] <= 1e-10 * (qb[0] * qb[0]):  # degenerate: max(1, s) M1
        big = _d_max1(_d_mul(_d_scale(-1.0, qb), inv2qa))
        o11, o12, o22 = _d_mul(big, a11), _d_mul(big, a12), _d_mul(big, a22)
    else:
        s = _d_mul(_d_sub(_d_sqrt(disc), qb), inv2qa)
        c11 = _d_sub(b11, _d_mul(s, a11))
        c12 = _d_sub(b12, _d_mul(s, a12))
        c22 = _d_sub(b22, _d_mul(s, a22))
        if abs(c11[0]) >= abs(c22[0]):
            v1, v2 = _d_scale(-1.0, c12), c11
        else:
            v1, v2 = c22, _d_scale(-1.0, c12)
        w1 = _d_add(_d_mul(a11, v1), _d_mul(a12, v2))
        w2 = _d_add(_d_mul(a12, v1), _d_mul(a22, v2))
        f = _d_div(_d_sub(s, (1.0, 0.0, 0.0)), _d_add(_d_mul(v1, w1), _d_mul(v2, w2)))
        fw1 = _d_mul(f, w1)
        o11 = _d_add(a11, _d_mul(fw1, w1))
        o12 = _d_add(a12, _d_mul(fw1, w2))
        o22 = _d_add(a22, _d_mul(_d_mul(f, w2), w2))
    return (
        o11[0], o12[0], o22[0],
        o11[1], o12[1], o22[1],
        o11[2], o12[2], o22[2],
    )  # fmt: skip


@njit(**_JIT)
def finite3(g):
    return math.isfinite(g[0]) and math.isfinite(g[1]) and math.isfinite(g[2])


@njit(**_JIT)
def spd3(g):
    """Whether (g11, g12, g22) is finite and positive definite (as ``metric._spd``)."""
    return finite3(g) and g[0] > 0 and g[0] * g[2] - g[1] * g[1] > 0


@njit(**_JIT)
def finite9(d):
    for k in range(9):
        if not math.isfinite(d[k]):
            return False
    return True


#: Names the generated metric code may use besides ``math``'s functions.
HELPERS: Mapping[str, Callable] = {
    "sign": sign,
    "intersect": intersect,
    "intersect_d": intersect_d,
    "finite3": finite3,
    "spd3": spd3,
    "finite9": finite9,
}


class TypedFunction:
    """A compiled scalar function (a numba ``cfunc`` of signature ``sig``) as the kernels
    take it, its numba type found once.

    Numba types a cfunc argument afresh at every call of a kernel (a new
    ``FunctionType`` from the signature, about 40 µs: 0.16 s of the three toys'
    adaptation at 10⁴ vertices, 2,868 kernel calls). This holder carries the type
    (``_numba_type_``, which numba's ``typeof`` reads) and hands numba the
    function's address by the wrapper address protocol
    (``numba.experimental.function_type``); the kernels run the same machine code.
    Callable from Python as the cfunc is.
    """

    def __init__(self, cfunc, sig) -> None:
        self.cfunc = cfunc
        self._numba_type_ = types.FunctionType(sig)

    def __wrapper_address__(self, *_) -> int:
        return self.cfunc.address

    def __call__(self, *args):
        return self.cfunc(*args)


class CompiledMetric:
    """A metric field's scalar functions: ``g`` (:data:`SIG_G`) and ``gd`` (:data:`SIG_GD`),
    as :class:`TypedFunction`."""

    def __init__(self, g, gd) -> None:
        self.g = TypedFunction(g, SIG_G)
        self.gd = TypedFunction(gd, SIG_GD)


#: Environment variable naming the directory of compiled metrics (default: the
#: user's cache directory); ``off`` compiles in memory at every run.
CACHE_ENV = "CURVIMESH_CACHE"

#: Environment variable bounding the size of that directory, in megabytes (default
#: :data:`CACHE_MAX_MB`): the least recently used metrics are deleted past it.
CACHE_MAX_ENV = "CURVIMESH_CACHE_MAX_MB"
CACHE_MAX_MB = 512


def compile_metric(
    source: str | Callable[[], str | None], g_name: str, gd_name: str, *, key: str | None = None
) -> CompiledMetric | None:
    """Compile generated Python source into the two scalar functions of a metric.

    ``source`` defines plain functions of (x, y) over ``math``'s names and
    :data:`HELPERS`; every function it defines is jitted, so that the two
    entry points ``g_name`` and ``gd_name`` may call the others. The
    source is code generated from sympy expressions (never user text).

    The source is written, as a module named by a hash of it and of this
    module's own code, to the cache directory (:data:`CACHE_ENV`), where
    numba caches the machine code beside it: a metric compiled once loads in
    a fraction of the time after. Where that directory cannot be written,
    the source is compiled in memory.

    With ``key``, a string that determines the source, the module is named by
    a hash of the key instead, and ``source`` may be a function that makes the
    source: it is called only when the module is not in the cache. None when
    that source is None (an expression with no scalar code).
    """
    ns = _load_generated(source, {g_name: "SIG_G", gd_name: "SIG_GD"}, key=key)
    if ns is None:
        return None
    return CompiledMetric(ns[f"{g_name}_cfunc"], ns[f"{gd_name}_cfunc"])


def compile_function(source: str, name: str):
    """A scalar function (x, y) ↦ value (:data:`SIG_F`) from generated source, as
    :func:`compile_metric` compiles a metric (the same cache)."""
    return TypedFunction(_load_generated(source, {name: "SIG_F"})[f"{name}_cfunc"], SIG_F)


def _module_text(source: str, entries: Mapping[str, str]) -> str:
    """The generated module of ``source``: its functions jitted and, for each entry
    point, ``{name}_cfunc`` compiled with the named signature."""
    names = re.findall(r"^def (\w+)\(", source, flags=re.MULTILINE)
    helpers = [n for n in names if n not in entries]
    foot = f"\nfor _name in {helpers!r}:\n"
    foot += '    globals()[_name] = njit(error_model="numpy")(globals()[_name])\n'
    for name, sig in entries.items():
        foot += f'{name}_cfunc = cfunc({sig}, error_model="numpy", cache=True)({name})\n'
    return (
        "# curvimesh: code compiled by curvimesh.kernels (safe to delete)\n"
        "import math\nfrom math import *\nfrom numba import cfunc, njit\n"
        f"from curvimesh.kernels import SIG_F, SIG_G, SIG_GD, {', '.join(HELPERS)}\n\n"
        + source
        + foot
    )


def _load_generated(
    source: str | Callable[[], str | None], entries: Mapping[str, str], *, key: str | None = None
) -> dict | None:
    """The namespace of the generated module (:func:`_module_text`) of ``source``, from
    the cache directory where it can be; None if ``source`` makes None. The module is
    named by a hash of its text, or of ``key`` and the entry points when a key is
    given, and then ``source`` is called only if the module must be written."""

    @cache
    def text() -> str | None:
        src = source() if callable(source) else source
        return None if src is None else _module_text(src, entries)

    directory = _cache_directory()
    if directory is not None:
        if key is None:
            if text() is None:
                return None
            name_of = _VERSION + text()
        else:
            name_of = f"{_VERSION}:{sorted(entries.items())!r}:{key}"
        module_key = hashlib.sha256(name_of.encode()).hexdigest()[:24]
        path = directory / f"metric_{module_key}.py"
        try:
            if not path.exists():
                if text() is None:
                    return None
                directory.mkdir(parents=True, exist_ok=True)
                tmp = path.with_suffix(f".{os.getpid()}.tmp")
                tmp.write_text(text())
                os.replace(tmp, path)
                prune_cache(directory, _cache_max_bytes(), keep=module_key)
            else:
                os.utime(path)  # its use time, for prune_cache
            name = f"curvimesh_metric_{module_key}"
            spec = importlib.util.spec_from_file_location(name, path)
            module = importlib.util.module_from_spec(spec)
            sys.modules[name] = module  # numba's cache finds the module's functions by name
            spec.loader.exec_module(module)
            return vars(module)
        except Exception:  # an unwritable or broken cache: compile in memory below
            pass
    if text() is None:
        return None
    ns: dict = {}
    exec(compile(text().replace("cache=True", "cache=False"), "<curvimesh generated>", "exec"), ns)
    return ns


def _cache_directory() -> Path | None:
    env = os.environ.get(CACHE_ENV)
    if env == "off":
        return None
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "curvimesh"


def _cache_max_bytes() -> int:
    try:
        mb = float(os.environ.get(CACHE_MAX_ENV, CACHE_MAX_MB))
    except ValueError:
        mb = CACHE_MAX_MB
    return int(mb * 2**20)


def prune_cache(directory: Path, max_bytes: int, *, keep: str | None = None) -> list[str]:
    """Delete the least recently used compiled metrics of ``directory`` until its
    metrics take at most ``max_bytes``; the keys deleted, oldest first.

    A metric is the module ``metric_KEY.py`` and numba's files of it,
    ``__pycache__/metric_KEY.*``; its use time is the module's modification
    time, which :func:`compile_metric` refreshes at every load. The metric
    ``keep`` (a KEY) stays whatever its size. Files another process deletes
    meanwhile are skipped (a process that loses its metric compiles it again).
    """
    entries: dict[str, list[Path]] = {}
    for f in [*directory.glob("metric_*"), *(directory / "__pycache__").glob("metric_*")]:
        key = f.name.removeprefix("metric_").split(".", 1)[0]
        entries.setdefault(key, []).append(f)

    def stat(f: Path) -> tuple[int, float]:
        try:
            st = f.stat()
        except OSError:
            return 0, 0.0
        return st.st_size, st.st_mtime

    size = {k: sum(stat(f)[0] for f in fs) for k, fs in entries.items()}
    used = {k: stat(directory / f"metric_{k}.py")[1] for k in entries}
    total = sum(size.values())
    deleted = []
    for k in sorted(entries, key=lambda k: (used[k], k)):
        if total <= max_bytes:
            break
        if k == keep:
            continue
        for f in entries[k]:
            try:
                f.unlink()
            except OSError:
                pass
        total -= size[k]
        deleted.append(k)
    return deleted


#: What the compiled code of a metric depends on besides its source: numba's
#: version and the helpers of this module (a hash of its text).
_VERSION = f"{numba.__version__}:" + hashlib.sha256(Path(__file__).read_bytes()).hexdigest()


# --------------------------------------------------------------------------- #
# Evaluation on arrays                                                         #
# --------------------------------------------------------------------------- #


@_row_kernel
def _eval_g(fn, pts, out):
    for i in prange(pts.shape[0]):
        g = fn(pts[i, 0], pts[i, 1])
        out[i, 0, 0] = g[0]
        out[i, 0, 1] = g[1]
        out[i, 1, 0] = g[1]
        out[i, 1, 1] = g[2]


@_row_kernel
def _eval_gd(fn, pts, out, dout):
    for i in prange(pts.shape[0]):
        d = fn(pts[i, 0], pts[i, 1])
        out[i, 0, 0] = d[0]
        out[i, 0, 1] = d[1]
        out[i, 1, 0] = d[1]
        out[i, 1, 1] = d[2]
        for k in range(2):
            dout[i, 0, 0, k] = d[3 + 3 * k]
            dout[i, 0, 1, k] = d[4 + 3 * k]
            dout[i, 1, 0, k] = d[4 + 3 * k]
            dout[i, 1, 1, k] = d[5 + 3 * k]


def evaluate(cm: CompiledMetric, pts: NDArray, derivatives: bool) -> tuple[NDArray, NDArray | None]:
    """g ``(n, 2, 2)`` and, if asked, ∂g ``(n, 2, 2, 2)`` at points ``(n, 2)`` (C-contiguous)."""
    g = np.empty((len(pts), 2, 2))
    if not derivatives:
        _eval_g(cm.g, pts, g)
        return g, None
    dg = np.empty((len(pts), 2, 2, 2))
    _eval_gd(cm.gd, pts, g, dg)
    return g, dg


# --------------------------------------------------------------------------- #
# Parabolas                                                                    #
# --------------------------------------------------------------------------- #


@njit(**_JIT)
def _parabola_length(fn, ax, ay, bx, by, mx, my, t, w):
    """∫₀¹ sqrt(ẋᵀ g(x(t)) ẋ) dt of one parabola by the rule (t, w); inf if undefined."""
    acc = 0.0
    for k in range(t.shape[0]):
        tk = t[k]
        n0 = (1 - tk) * (1 - 2 * tk)
        n1 = tk * (2 * tk - 1)
        nm = 4 * tk * (1 - tk)
        d0 = 4 * tk - 3
        d1 = 4 * tk - 1
        dm = 4 - 8 * tk
        px = n0 * ax + n1 * bx + nm * mx
        py = n0 * ay + n1 * by + nm * my
        tx = d0 * ax + d1 * bx + dm * mx
        ty = d0 * ay + d1 * by + dm * my
        g = fn(px, py)
        acc += w[k] * math.sqrt(tx * tx * g[0] + 2 * tx * ty * g[1] + ty * ty * g[2])
    if not math.isfinite(acc):
        return math.inf
    return acc


@_row_kernel
def parabola_lengths(fn, x0, x1, xm, t, w, out):
    """Lengths of parabolas (rows of x0, x1, xm ``(n, 2)``) by the rule (t, w) into ``out``."""
    for i in prange(x0.shape[0]):
        out[i] = _parabola_length(
            fn, x0[i, 0], x0[i, 1], x1[i, 0], x1[i, 1], xm[i, 0], xm[i, 1], t, w
        )


@_row_kernel(chunk=ADAPTIVE_CHUNK)
def parabola_lengths_adaptive(fn, x0, x1, xm, two, ts, ws, starts, rtol, out):
    """Lengths of parabolas (rows of x0, x1, xm ``(n, 2)``) to ``rtol`` relative by
    composite Gauss rules of doubling segment counts, into ``out``: rule k is
    ``ts[starts[k]:starts[k + 1]]`` (weights ``ws``), with 2ᵏ segments. A row is done
    at rule k ≥ 1 when it is within ``rtol`` × itself of rule k − 1, is not finite,
    or k is the last rule. ``two`` ``(n,)`` holds the rows' lengths by rule 1 where it
    is not empty (computed otherwise). Row by row the arithmetic of
    :func:`curvimesh.geodesic.parabola_length`'s level-by-level loop, in one call."""
    for i in prange(x0.shape[0]):
        out[i] = _adaptive_length(
            fn, x0[i, 0], x0[i, 1], x1[i, 0], x1[i, 1], xm[i, 0], xm[i, 1],
            two[i] if two.shape[0] > 0 else math.nan, two.shape[0] > 0, ts, ws, starts, rtol,
        )  # fmt: skip


@njit(**_JIT)
def _adaptive_length(fn, ax, ay, bx, by, mx, my, two, has_two, ts, ws, starts, rtol):
    """The length of one parabola to ``rtol`` (:func:`parabola_lengths_adaptive`); ``two``
    its length by rule 1 where ``has_two``."""
    last = starts.shape[0] - 2
    prev = _parabola_length(fn, ax, ay, bx, by, mx, my, ts[: starts[1]], ws[: starts[1]])
    cur = prev
    for k in range(1, last + 1):
        if k == 1 and has_two:
            cur = two
        else:
            lo, hi = starts[k], starts[k + 1]
            cur = _parabola_length(fn, ax, ay, bx, by, mx, my, ts[lo:hi], ws[lo:hi])
        if abs(cur - prev) <= rtol * abs(cur) or not math.isfinite(cur):
            break
        prev = cur
    return cur


@njit(**_JIT)
def _offset_length(fn, ax, ay, bx, by, alpha, t, w):
    """Length of the parabola from a to b through (a + b)/2 + α (b − a)×e₃
    (:func:`curvimesh.geodesic.parabola_midnode`)."""
    mx = 0.5 * (ax + bx) + alpha * (by - ay)
    my = 0.5 * (ay + by) - alpha * (bx - ax)
    return _parabola_length(fn, ax, ay, bx, by, mx, my, t, w)


@njit(**_JIT)
def _convex_floor(a, b, c, fa, fb, fc):
    """A lower bound of a convex f on [a, c] from f at a ≤ b ≤ c with fb ≤ fa, fc:
    the secants b–c and a–b, extended to a and to c (−inf when b is an end)."""
    if not (a < b < c):
        return -math.inf
    return min(fb - (fc - fb) * (b - a) / (c - b), fb - (fa - fb) * (c - b) / (b - a))


def _coarse_rule(order: int) -> tuple[NDArray, NDArray]:
    xg, wg = np.polynomial.legendre.leggauss(order)
    return (xg + 1) / 2, wg / 2


#: The rule of the scan of :func:`_search` when it has at least :data:`COARSE_SCAN`
#: values: one 3-point Gauss–Legendre segment (the scan only picks a bracket).
COARSE_T, COARSE_W = _coarse_rule(3)
COARSE_SCAN = 7


@njit(**_JIT)
def _scan_bracket(fn, ax, ay, bx, by, grid, t, w):
    """The bracket (ia, ib, ic) of ``grid`` indices and the lengths (fa, fb, fc) there
    by the rule (t, w) that :func:`_search` refines.

    Short scans use the rule itself: ib is the first smallest scanned length (as
    np.argmin), ia and ic its neighbours, clipped to the scan (an end stays an
    end). Scans of at least :data:`COARSE_SCAN` values scan with the coarse rule
    (:data:`COARSE_T`), then take the three lengths by (t, w) and walk down the
    grid while a neighbour is shorter, so that fb ≤ fa, fc holds for the rule
    the search minimises.
    """
    scan = grid.shape[0]
    coarse = scan >= COARSE_SCAN
    ts = COARSE_T if coarse else t
    ws = COARSE_W if coarse else w
    vals = np.empty(scan)
    best = 0
    for j in range(scan):
        vals[j] = _offset_length(fn, ax, ay, bx, by, grid[j], ts, ws)
        if vals[j] < vals[best]:  # the first smallest, as np.argmin
            best = j
    ia = max(best - 1, 0)
    ic = min(best + 1, scan - 1)
    if not coarse:
        return ia, best, ic, vals[ia], vals[best], vals[ic]
    ib = best
    fb = _offset_length(fn, ax, ay, bx, by, grid[ib], t, w)
    fa = fb if ia == ib else _offset_length(fn, ax, ay, bx, by, grid[ia], t, w)
    fc = fb if ic == ib else _offset_length(fn, ax, ay, bx, by, grid[ic], t, w)
    while True:
        if fa < fb and fa <= fc:  # downhill towards −α
            ic, fc, ib, fb = ib, fb, ia, fa
            ia = max(ib - 1, 0)
            fa = fb if ia == ib else _offset_length(fn, ax, ay, bx, by, grid[ia], t, w)
        elif fc < fb:  # downhill towards +α
            ia, fa, ib, fb = ib, fb, ic, fc
            ic = min(ib + 1, scan - 1)
            fc = fb if ic == ib else _offset_length(fn, ax, ay, bx, by, grid[ic], t, w)
        else:
            return ia, ib, ic, fa, fb, fc


@njit(**_JIT)
def _search(fn, ax, ay, bx, by, grid, t, w, tol, max_iter, decide, short, long):
    """The shortest-parabola search of one row; returns (α, length, verdict).

    A scan of α over ``grid`` (:func:`_scan_bracket`), then :func:`_brent` in
    the bracket around the best scanned value.
    """
    ia, ib, ic, fa, fb, fc = _scan_bracket(fn, ax, ay, bx, by, grid, t, w)
    return _brent(
        fn, ax, ay, bx, by, grid[ia], grid[ib], grid[ic], fa, fb, fc,
        t, w, tol, max_iter, decide, short, long,
    )  # fmt: skip


#: Widest bracket (in α) whose convex floor (:func:`_convex_floor`) decides a verdict.
#: The length is convex in α near its minimum, not across a scan's whole bracket:
#: across the front example's front, two points 0.066 apart have parabolas of 1.88
#: at α = 0, 1.82 at 0.25 and 2.77 at 0.5, the floor of that bracket is 0.87, and the
#: parabola along the front (α = 0.080) is 0.699 long (a 0.6991 edge at seed 4).
#: Cost, measured: the closeness tests of the three toys' sampling at 10⁴ vertices
#: 0.33 → 0.37 s; no verdict changed on the examples at seed 0. It was 0.1: in a
#: circular layer of 2,500:1 (bench/robustness/u44_circ_layer_2500.yaml, 4e-5 across,
#: radius 0.3) the valley of two points 0.024 apart along the layer is a few thousandths
#: wide (α = 0.0099, length 0.37, above 0.7 a few thousandths away), and brackets 0.1
#: wide called such pairs far: the sampled cloud held 96 pairs under 0.7, and the mesh
#: edges from 0.25 to 14.3 (81.8 % in range, seed 0). At 0.01, seed 0: 0.7017 – 1.3906,
#: 100 % in range; the examples byte-identical; the three toys' sampling at 10⁴ vertices
#: about 0.04 s slower (medians of four alternated runs, 1.04 → 1.08 s, within the
#: noise). Seeds 1 and 2 kept edges of 15.8 and 13.5: pairs within 5e-5 of the circle
#: whose valley is narrower than the search's tolerance (:data:`REFINES`).
FLOOR_WIDTH = 0.01

#: Refinements of a search whose verdict its final bracket contradicts (:func:`_brent`),
#: and the factor by which each divides the α tolerance. In a circular layer of 2,500:1
#: (bench/robustness/u44_circ_layer_2500.yaml) the valley of two points 5e-5 off the
#: circle, 0.055 apart along it, is 0.001 wide in α: the length is 1.17 at α = 0.0180,
#: 0.599 at 0.0185 and 1.18 at 0.0190; the search to 0.002 stopped at 0.768 and called
#: the pair far, and the sampled cloud kept pairs 0.55 – 0.66 apart (seed 1).
REFINES, REFINE_FACTOR = 3, 10.0


@njit(**_JIT)
def _brent(fn, ax, ay, bx, by, a, b, c, fa, fb, fc, t, w, tol, max_iter, decide, short, long):
    """Brent's minimisation of the parabola length in α from the bracket a ≤ b ≤ c
    (fb ≤ fa, fc); returns (α, length, verdict).

    Brent's method (Brent 1973, chapter 5; Press et al. 2007, section 10.3):
    parabolic interpolation through the three best points seen, a golden-section
    step when the interpolated step is out of the bracket or not less than half
    the step before last, and no step shorter than tol / 4, until the bracket is
    at most ``tol`` wide around the best point; the length is the best value seen.

    With ``decide``, the search stops as soon as the verdict is known, the
    length being assumed convex in α on the bracket (Brent's own model): −1
    once a length below ``short`` is seen, +1 once the bracket's convex floor
    (:func:`_convex_floor`) is above ``long``, 0 once a length at most ``long``
    is seen and the floor is at least ``short``, the floor being trusted only on
    brackets at most :data:`FLOOR_WIDTH` wide. Otherwise the verdict is that of
    the final length. A verdict that the final bracket's convex floor contradicts
    (a length at least ``short`` with the floor below it, or above ``long`` with
    the floor at most it) is searched on with the tolerance divided by
    :data:`REFINE_FACTOR`, at most :data:`REFINES` times: the valley of a curved
    layer can be narrower than ``tol``.
    """
    cgold = 0.3819660112501051
    tol1 = 0.25 * tol
    x, fx = b, fb
    wp, fw = b, fb  # second best
    vp, fv = b, fb  # previous value of wp
    d = 0.0
    e = 0.0  # the step before last
    refines = 0
    it = 0
    while it < max_iter:
        it += 1
        if decide:
            if fx < short:
                return x, fx, -1
            floor = _convex_floor(a, x, c, fa, fx, fc) if c - a <= FLOOR_WIDTH else -math.inf
            if floor > long:
                return x, fx, 1
            if fx <= long and floor >= short:
                return x, fx, 0
        xm = 0.5 * (a + c)
        if abs(x - xm) <= 2.0 * tol1 - 0.5 * (c - a):
            if not decide or refines == REFINES:
                break
            floor = _convex_floor(a, x, c, fa, fx, fc)
            if not ((fx >= short and floor < short) or (fx > long and floor <= long)):
                break
            refines += 1
            tol1 /= REFINE_FACTOR
            it = 0
            e = 0.0  # a golden-section step first, on the narrower tolerance
        golden = True
        if abs(e) > tol1:
            r = (x - wp) * (fx - fv)
            q = (x - vp) * (fx - fw)
            p = (x - vp) * q - (x - wp) * r
            q = 2.0 * (q - r)
            if q > 0.0:
                p = -p
            q = abs(q)
            etemp = e
            e = d
            if (
                math.isfinite(p)
                and math.isfinite(q)
                and abs(p) < abs(0.5 * q * etemp)
                and p > q * (a - x)
                and p < q * (c - x)
            ):
                d = p / q
                u = x + d
                if u - a < 2.0 * tol1 or c - u < 2.0 * tol1:
                    d = tol1 if xm >= x else -tol1
                golden = False
        if golden:
            e = (a - x) if x >= xm else (c - x)
            d = cgold * e
        if abs(d) >= tol1:
            u = x + d
        else:
            u = x + (tol1 if d >= 0.0 else -tol1)
        fu = _offset_length(fn, ax, ay, bx, by, u, t, w)
        if not math.isfinite(fu):
            fu = math.inf
        if fu <= fx:
            if u >= x:
                a, fa = x, fx
            else:
                c, fc = x, fx
            vp, fv, wp, fw, x, fx = wp, fw, x, fx, u, fu
        else:
            if u < x:
                a, fa = u, fu
            else:
                c, fc = u, fu
            if fu <= fw or wp == x:
                vp, fv, wp, fw = wp, fw, u, fu
            elif fu <= fv or vp == x or vp == wp:
                vp, fv = u, fu
    verdict = -1 if fx < short else (1 if fx > long else 0)
    return x, fx, verdict


@njit(**_JIT)
def _scanned(fn, ax, ay, bx, by, grid, t, w, tol, max_iter):
    """(α, length) of :func:`_search` without a verdict."""
    a, f, _ = _search(fn, ax, ay, bx, by, grid, t, w, tol, max_iter, False, -math.inf, math.inf)
    return a, f


@njit(**_JIT)
def _search_near(fn, ax, ay, bx, by, start, grid, t, w, tol, max_iter):
    """The shortest-parabola search of one row from a guess ``start`` of α; returns
    (α, length).

    Downhill from ``start`` in steps of 0.45 ``tol`` doubling at each step
    until the length rises (a bracket, Press et al. 2007, section 10.1), then
    :func:`_brent`; the scan of :func:`_search` instead when ``start`` is NaN
    or the walk leaves the scanned range [grid₀, grid₋₁]. It finds the local
    minimum nearest the guess, not necessarily the scan's.
    """
    if not math.isfinite(start) or start < grid[0] or start > grid[-1]:
        return _scanned(fn, ax, ay, bx, by, grid, t, w, tol, max_iter)
    h = 0.45 * tol
    b, fb = start, _offset_length(fn, ax, ay, bx, by, start, t, w)
    c, fc = b + h, _offset_length(fn, ax, ay, bx, by, b + h, t, w)
    if fc < fb:  # downhill towards +α
        a, fa = b, fb
        b, fb = c, fc
        step = 2.0 * h
        c = b + step
        fc = _offset_length(fn, ax, ay, bx, by, c, t, w)
        while fc < fb:
            if c > grid[-1]:
                return _scanned(fn, ax, ay, bx, by, grid, t, w, tol, max_iter)
            a, fa, b, fb = b, fb, c, fc
            step *= 2.0
            c = b + step
            fc = _offset_length(fn, ax, ay, bx, by, c, t, w)
    else:
        a, fa = b - h, _offset_length(fn, ax, ay, bx, by, b - h, t, w)
        step = h
        while fa < fb:  # downhill towards −α
            if a < grid[0]:
                return _scanned(fn, ax, ay, bx, by, grid, t, w, tol, max_iter)
            c, fc, b, fb = b, fb, a, fa
            step *= 2.0
            a = b - step
            fa = _offset_length(fn, ax, ay, bx, by, a, t, w)
    if not (math.isfinite(fa) and math.isfinite(fb) and math.isfinite(fc)):
        return _scanned(fn, ax, ay, bx, by, grid, t, w, tol, max_iter)
    a, f, _ = _brent(
        fn, ax, ay, bx, by, a, b, c, fa, fb, fc, t, w, tol, max_iter, False, -math.inf, math.inf
    )
    return a, f


@njit(**_JIT)
def _search_guided(fn, ax, ay, bx, by, guess, grid, t, w, tol, max_iter):
    """The shortest-parabola search of one row from a guess of α that may be far off;
    returns (α, length).

    :func:`_search_near` from ``guess``, kept when its α is, by the coarse rule of
    the scan (:data:`COARSE_T`), no longer than the parabola at every value of
    ``grid``; otherwise the scan's search (:func:`_scanned`), as without a guess.
    The check costs the coarse scan alone (three lengths a value), not the scan's
    refinement, and keeps the scan's guarantee: no scanned α is shorter than the
    one returned (the guess's local minimum can be a poor one where the metric
    varies fast, as across a clamped function's kinks).
    """
    if not math.isfinite(guess) or guess < grid[0] or guess > grid[-1]:
        return _scanned(fn, ax, ay, bx, by, grid, t, w, tol, max_iter)
    a, f = _search_near(fn, ax, ay, bx, by, guess, grid, t, w, tol, max_iter)
    found = _offset_length(fn, ax, ay, bx, by, a, COARSE_T, COARSE_W)
    for j in range(grid.shape[0]):
        if not (_offset_length(fn, ax, ay, bx, by, grid[j], COARSE_T, COARSE_W) >= found):
            return _scanned(fn, ax, ay, bx, by, grid, t, w, tol, max_iter)
    return a, f


@_row_kernel(min_rows=SEARCH_PARALLEL_ROWS)
def shortest_parabolas_guided(fn, x0, x1, guess, grid, t, w, tol, max_iter, alpha, length):
    """The search of :func:`curvimesh.geodesic.shortest_parabola` from guesses ``guess``
    of α that may be far off (NaN: none), one row at a time (:func:`_search_guided`)."""
    for i in prange(x0.shape[0]):
        alpha[i], length[i] = _search_guided(
            fn, x0[i, 0], x0[i, 1], x1[i, 0], x1[i, 1], guess[i], grid, t, w, tol, max_iter
        )


@_row_kernel(min_rows=SEARCH_PARALLEL_ROWS)
def shortest_parabolas(fn, x0, x1, grid, t, w, tol, max_iter, alpha, length):
    """The search of :func:`curvimesh.geodesic.shortest_parabola`, one row at a time
    (:func:`_search`): writes α and the rule's length at it."""
    for i in prange(x0.shape[0]):
        alpha[i], length[i], _ = _search(
            fn, x0[i, 0], x0[i, 1], x1[i, 0], x1[i, 1], grid, t, w, tol, max_iter, False,
            -math.inf, math.inf,
        )  # fmt: skip


@_row_kernel(min_rows=SEARCH_PARALLEL_ROWS)
def shortest_parabolas_near(fn, x0, x1, start, grid, t, w, tol, max_iter, alpha, length):
    """The search of :func:`curvimesh.geodesic.shortest_parabola` from guesses ``start``
    of α (NaN: none), one row at a time (:func:`_search_near`)."""
    for i in prange(x0.shape[0]):
        alpha[i], length[i] = _search_near(
            fn, x0[i, 0], x0[i, 1], x1[i, 0], x1[i, 1], start[i], grid, t, w, tol, max_iter
        )


@njit(**_JIT)
def _free_length(fn, ax, ay, bx, by, mx, my, nx, ny, dx, dy, a, b, t, w):
    """Length by the rule (t, w) of the parabola from a to b through the node
    (mx, my) + α (nx, ny) + β (dx, dy) (:func:`curvimesh.freenode.free_node`'s)."""
    return _parabola_length(fn, ax, ay, bx, by, mx + a * nx + b * dx, my + a * ny + b * dy, t, w)


@njit(**_JIT)
def _newton_step(ga, gb, haa, hab, hbb, max_step):
    """:func:`curvimesh.freenode.newton_step` of one row (the same operations)."""
    det = haa * hbb - hab**2
    if haa > 0.0 and det > 0.0:
        sa = -(hbb * ga - hab * gb) / det
        sb = -(haa * gb - hab * ga) / det
    else:
        scale = _nan_max(abs(haa) + abs(hbb) + 2.0 * abs(hab), 1e-300)
        sa = -ga / scale
        sb = -gb / scale
    norm = math.hypot(sa, sb)
    cap = max_step / norm if norm > max_step else 1.0
    sa, sb = sa * cap, sb * cap
    if not (math.isfinite(sa) and math.isfinite(sb)):
        return 0.0, 0.0
    return sa, sb


@_row_kernel(min_rows=SEARCH_PARALLEL_ROWS)
def free_nodes(
    fn, x0, x1, alpha, t, w, h, h2, max_step, iterations, halvings, tol, mid, length
):  # fmt: skip
    """:func:`curvimesh.freenode.free_node` one row at a time, in the same operations:
    damped Newton on (α, β) from (``alpha[i]``, 0), the gradient and Hessian by central
    differences of step ``h`` (``h2`` = h²), steps capped at ``max_step`` and halved
    at most ``halvings`` times until the length decreases, at most ``iterations``,
    stopping when a step shortens by no more than ``tol`` (relative); the node into
    ``mid`` ``(n, 2)``, the length by the rule (t, w) into ``length``."""
    for i in prange(x0.shape[0]):
        ax, ay, bx, by = x0[i, 0], x0[i, 1], x1[i, 0], x1[i, 1]
        dx, dy = bx - ax, by - ay
        nx, ny = dy, -dx
        mx, my = 0.5 * (ax + bx), 0.5 * (ay + by)
        a, b = alpha[i], 0.0
        f = _free_length(fn, ax, ay, bx, by, mx, my, nx, ny, dx, dy, a, b, t, w)
        if math.isfinite(f):
            for _ in range(iterations):
                A, B, F = a, b, f
                fpa = _free_length(fn, ax, ay, bx, by, mx, my, nx, ny, dx, dy, A + h, B, t, w)
                fma = _free_length(fn, ax, ay, bx, by, mx, my, nx, ny, dx, dy, A - h, B, t, w)
                fpb = _free_length(fn, ax, ay, bx, by, mx, my, nx, ny, dx, dy, A, B + h, t, w)
                fmb = _free_length(fn, ax, ay, bx, by, mx, my, nx, ny, dx, dy, A, B - h, t, w)
                fab = _free_length(fn, ax, ay, bx, by, mx, my, nx, ny, dx, dy, A + h, B + h, t, w)
                ga, gb = (fpa - fma) / (2.0 * h), (fpb - fmb) / (2.0 * h)
                haa, hbb = (fpa - 2.0 * F + fma) / h2, (fpb - 2.0 * F + fmb) / h2
                hab = (fab - fpa - fpb + F) / h2
                sa, sb = _newton_step(ga, gb, haa, hab, hbb, max_step)
                step = 1.0
                moved = False
                for _ in range(halvings):
                    fs = _free_length(
                        fn, ax, ay, bx, by, mx, my, nx, ny, dx, dy, A + step * sa, B + step * sb,
                        t, w,
                    )  # fmt: skip
                    if math.isfinite(fs) and fs < F:
                        a, b, f = A + step * sa, B + step * sb, fs
                        moved = True
                        break
                    step *= 0.5
                if not (moved and F - f > tol * F):
                    break
        mid[i, 0] = mx + a * nx + b * dx
        mid[i, 1] = my + a * ny + b * dy
        length[i] = f


@_row_kernel(min_rows=SEARCH_PARALLEL_ROWS)
def classify_parabolas(fn, x0, x1, grid, t, w, tol, max_iter, short, long, verdict):
    """Whether the shortest parabola of each row is below ``short`` (−1), above
    ``long[i]`` (+1) or neither (0), by :func:`_search` stopping at the verdict."""
    for i in prange(x0.shape[0]):
        _, _, verdict[i] = _search(
            fn, x0[i, 0], x0[i, 1], x1[i, 0], x1[i, 1], grid, t, w, tol, max_iter, True,
            short, long[i],
        )  # fmt: skip


@njit(**_JIT)
def _probe_sup(fn, ax, ay, dx, dy, nx, ny, tk, sk):
    """νᵀ g⁻¹ ν at the probe a + t d + s d×e₃ (ν = d / |d| = (nx, ny)), the squared
    size along ν there; NaN where g is undefined."""
    g = fn(ax + tk * dx + sk * dy, ay + tk * dy - sk * dx)
    det = g[0] * g[2] - g[1] ** 2
    return (g[2] * nx**2 - 2 * g[1] * nx * ny + g[0] * ny**2) / det


@njit(**_JIT)
def _chord_bound(fn, ax, ay, bx, by, probes):
    """|d| / max over the probes (t, s) of sqrt(νᵀ g⁻¹ ν) at a + t d + s d×e₃, d = b − a,
    ν = d / |d| (:func:`curvimesh.geodesic.chord_lower_bound`); NaN if g is undefined
    at a probe."""
    dx = bx - ax
    dy = by - ay
    chord = math.hypot(dx, dy)
    nx = dx / chord
    ny = dy / chord
    worst = -math.inf
    for k in range(probes.shape[0]):
        sup = _probe_sup(fn, ax, ay, dx, dy, nx, ny, probes[k, 0], probes[k, 1])
        if math.isnan(sup):
            return math.nan
        if sup > worst:
            worst = sup
    return chord / math.sqrt(worst)


@_row_kernel
def chord_bounds(fn, a, b, probes, out):
    """:func:`_chord_bound` row by row."""
    for i in prange(a.shape[0]):
        out[i] = _chord_bound(fn, a[i, 0], a[i, 1], b[i, 0], b[i, 1], probes)


@njit(**_JIT)
def _chord_bound_reaches(fn, ax, ay, bx, by, probes, target):
    """Whether :func:`_chord_bound` is at least ``target`` > 0 (False where it is NaN):
    |d| / sqrt(worst) ≥ target ⇔ worst ≤ (|d| / target)², so the probes stop at the
    first one above that (most pairs that are not far: the first probe)."""
    dx = bx - ax
    dy = by - ay
    chord = math.hypot(dx, dy)
    nx = dx / chord
    ny = dy / chord
    limit = (chord / target) ** 2
    for k in range(probes.shape[0]):
        sup = _probe_sup(fn, ax, ay, dx, dy, nx, ny, probes[k, 0], probes[k, 1])
        if not sup <= limit:  # above, or NaN
            return False
    return True


@njit(**_JIT)
def _relative_floor(m11, m21, m22, g11, g12, g22):
    """The smallest eigenvalue of g relative to a = L Lᵀ (the largest λ with g ⪰ λ a),
    given M = L⁻¹ (lower triangular: m11, m21, m22): the smallest eigenvalue of
    C = M g Mᵀ, (c11 + c22)/2 − hypot((c11 − c22)/2, c12), whose discriminant is a
    sum of squares (exact for g = c a, where tr² − 4 det a det g cancels); NaN where
    g is undefined."""
    c11 = m11 * m11 * g11
    c12 = m11 * (m21 * g11 + m22 * g12)
    c22 = m21 * m21 * g11 + 2.0 * m21 * m22 * g12 + m22 * m22 * g22
    return 0.5 * (c11 + c22) - math.hypot(0.5 * (c11 - c22), c12)


@njit(**_JIT)
def _lens_bound(fn, ax, ay, bx, by, probes, target):
    """:func:`curvimesh.geodesic.lens_lower_bound` of one pair, sqrt(λ dᵀ g₀ d) with g₀
    the metric at the chord's middle and λ the least over the probes of g's smallest
    eigenvalue relative to g₀ (:func:`_relative_floor`); NaN where g is undefined at a
    probe. With ``target`` > 0 the probes stop at the first one that puts the bound
    below it (the value returned is then below ``target``, not the bound)."""
    dx = bx - ax
    dy = by - ay
    g0 = fn(0.5 * (ax + bx), 0.5 * (ay + by))
    a11, a12, a22 = g0[0], g0[1], g0[2]
    d2 = a11 * dx * dx + 2.0 * a12 * dx * dy + a22 * dy * dy
    if math.isnan(d2 + a11 * a22 - a12 * a12):
        return math.nan
    if not (a11 > 0.0 and a11 * a22 - a12 * a12 > 0.0 and d2 > 0.0):
        return 0.0
    l11 = math.sqrt(a11)  # g₀ = L Lᵀ (Cholesky), M = L⁻¹
    l21 = a12 / l11
    l22 = math.sqrt(a22 - l21 * l21)
    m11, m21, m22 = 1.0 / l11, -l21 / (l11 * l22), 1.0 / l22
    floor = (target * target) / d2  # the λ below which the bound misses target
    lam = math.inf
    for k in range(probes.shape[0]):
        tk, sk = probes[k, 0], probes[k, 1]
        g = fn(ax + tk * dx + sk * dy, ay + tk * dy - sk * dx)
        r = _relative_floor(m11, m21, m22, g[0], g[1], g[2])
        if math.isnan(r):
            return math.nan
        lam = min(lam, r)
        if target > 0.0 and lam < floor:
            break
    return math.sqrt(max(lam, 0.0) * d2)


@_row_kernel
def lens_bounds(fn, a, b, probes, out):
    """:func:`_lens_bound` row by row (no target)."""
    for i in prange(a.shape[0]):
        out[i] = _lens_bound(fn, a[i, 0], a[i, 1], b[i, 0], b[i, 1], probes, 0.0)


@njit(**_JIT)
def _is_close(fn, ax, ay, bx, by, short, margin, probes, ts, ws, grid, t, w, tol, straight_first):
    """Whether the shortest parabola from a to b is below ``short``, decided as
    :func:`curvimesh.geodesic.parabola_verdicts` with only ``short``: far if the
    chord bound is at least ``margin`` × short (:func:`_chord_bound_reaches`) or
    the lens bound (:func:`_lens_bound`) is, close if the straight segment (rule
    ``ts``, ``ws``) is below it, else by the search stopping at its verdict.

    The bounds are lower bounds (from the metric at their probes, with the margin
    for the metric between them) and the segment an upper one: where the bounds
    hold, no pair is both far and close, and the order changes only the work. The
    bounds come first, each stopping at its first probe that leaves it short (for
    pairs likely far: the segment is then not needed; in the three toys' sampling
    at 3.8·10⁴ vertices, of the 150,193 pairs that the chord bound leaves open the
    lens bound calls 128,136 far, and the segment had found 2,172 close, none of
    them far by the lens bound). With ``straight_first`` the segment is measured
    first (for pairs likely close: the bounds are then not needed)."""
    if straight_first:
        upper = _parabola_length(fn, ax, ay, bx, by, 0.5 * (ax + bx), 0.5 * (ay + by), ts, ws)
        if upper < short:  # (an undefined length is inf, never NaN)
            return True
    if _chord_bound_reaches(fn, ax, ay, bx, by, probes, margin * short):
        return False
    if _lens_bound(fn, ax, ay, bx, by, probes, margin * short) >= margin * short:
        return False
    if not straight_first:
        upper = _parabola_length(fn, ax, ay, bx, by, 0.5 * (ax + bx), 0.5 * (ay + by), ts, ws)
        if upper < short:
            return True
    return _search(fn, ax, ay, bx, by, grid, t, w, tol, 60, True, short, math.inf)[2] < 0


@njit(**_JIT)
def _nearest_close(
    fn, cx, cy, g11, g12, g22, pts, nbr, short, margin, probes, ts, ws, grid, t, w, tol
):
    """Whether one of the points ``pts[nbr]`` is closer than ``short`` to (cx, cy)
    (:func:`_is_close`), trying them nearest first by the length of the chord in
    the metric (g11, g12, g22) at (cx, cy) and stopping at the first close one.
    A point whose chord is below ``short`` in that metric has its straight segment
    measured first: on the three toys' candidates, 3,876 of 3,903 such pairs are
    decided close by it (the chord bound would have cost nine metric values)."""
    key = np.empty(nbr.shape[0])
    for k in range(nbr.shape[0]):
        dx = pts[nbr[k], 0] - cx
        dy = pts[nbr[k], 1] - cy
        key[k] = g11 * dx * dx + 2.0 * g12 * dx * dy + g22 * dy * dy
    for k in np.argsort(key, kind="mergesort"):
        p = nbr[k]
        if _is_close(
            fn, cx, cy, pts[p, 0], pts[p, 1], short, margin, probes, ts, ws, grid, t, w, tol,
            key[k] < short * short,
        ):  # fmt: skip
            return True
    return False


@_row_kernel(min_rows=SEARCH_PARALLEL_ROWS)
def close_pairs(fn, a, b, short, margin, probes, ts, ws, grid, t, w, tol, out):
    """Whether the shortest parabola of each pair (rows of ``a``, ``b`` ``(n, 2)``) is
    below ``short`` (:func:`_is_close`, the chord bound first)."""
    for i in prange(a.shape[0]):
        out[i] = _is_close(
            fn, a[i, 0], a[i, 1], b[i, 0], b[i, 1], short, margin, probes, ts, ws, grid, t, w,
            tol, False,
        )  # fmt: skip


@_row_kernel(min_rows=SEARCH_PARALLEL_ROWS)
def close_candidates(
    fn, cand, g_cand, pts, offsets, hits, short, margin, probes, ts, ws, grid, t, w, tol, out
):
    """Whether each candidate ``cand[i]`` is closer than ``short`` to any of its
    neighbours ``pts[hits[offsets[i]:offsets[i+1]]]`` (shortest parabola from the
    candidate, decided by :func:`_is_close`).

    The neighbours are tried nearest first, by the length of the chord in the
    candidate's metric ``g_cand[i]`` (g11, g12, g22), and the first close one
    decides (:func:`_nearest_close`): the verdict of every pair being fixed, the
    order changes only how many are tried (a rejected candidate usually has a
    close neighbour among its nearest).
    """
    for i in prange(cand.shape[0]):
        out[i] = _nearest_close(
            fn, cand[i, 0], cand[i, 1], g_cand[i, 0], g_cand[i, 1], g_cand[i, 2], pts,
            hits[offsets[i] : offsets[i + 1]], short, margin, probes, ts, ws, grid, t, w, tol,
        )  # fmt: skip


# --------------------------------------------------------------------------- #
# Geodesic shooting                                                            #
# --------------------------------------------------------------------------- #


@njit(**_JIT)
def _acceleration(fn, x, y, vx, vy):
    """ẍ = −Γ(x)(ẋ, ẋ) at one point (paper equation (2)); NaN where g is undefined.

    With Tₘ = Σₖₗ (∂ₗg_mk + ∂ₖg_ml − ∂ₘg_kl) vₖvₗ = 2 Σₖₗ ∂ₗg_mk vₖvₗ − Σₖₗ ∂ₘg_kl vₖvₗ,
    ẍ = −½ g⁻¹ T.
    """
    d = fn(x, y)
    g11, g12, g22 = d[0], d[1], d[2]
    # ∂g/∂x and ∂g/∂y, contracted with v
    gx11, gx12, gx22 = d[3], d[4], d[5]
    gy11, gy12, gy22 = d[6], d[7], d[8]
    vgv_x = gx11 * vx * vx + 2 * gx12 * vx * vy + gx22 * vy * vy  # Σ ∂ₓg_kl vₖvₗ
    vgv_y = gy11 * vx * vx + 2 * gy12 * vx * vy + gy22 * vy * vy
    # Σₖₗ ∂ₗ g_mk vₖ vₗ = Σₖ (v·∇) g_mk vₖ
    dv11 = gx11 * vx + gy11 * vy
    dv12 = gx12 * vx + gy12 * vy
    dv22 = gx22 * vx + gy22 * vy
    t1 = 2 * (dv11 * vx + dv12 * vy) - vgv_x
    t2 = 2 * (dv12 * vx + dv22 * vy) - vgv_y
    det = g11 * g22 - g12 * g12
    ax = -0.5 * (g22 * t1 - g12 * t2) / det
    ay = -0.5 * (-g12 * t1 + g11 * t2) / det
    return ax, ay


@njit(**_JIT)
def _bend_alpha(fd, ax, ay, bx, by):
    """:func:`curvimesh.geodesic.geodesic_alpha` of one chord a–b (the same operations,
    hence the same bits): the α of the parabola that bends as the geodesic does at the
    chord's middle, −Γ(d, d)/8 projected on d × e₃ over |d|² (d = b − a; ``fd`` the
    metric with its derivatives); NaN or inf where undefined."""
    dx, dy = bx - ax, by - ay
    acc_x, acc_y = _acceleration(fd, 0.5 * (ax + bx), 0.5 * (ay + by), dx, dy)
    ox, oy = -0.125 * acc_x, -0.125 * acc_y
    return (ox * dy + oy * (-dx)) / (dx * dx + dy * dy)


@_row_kernel
def accelerations(fn, x, v, out):
    """:func:`_acceleration` row by row: ẍ = −Γ(x)(v, v) ``(n, 2)`` into ``out``
    (``fn`` the metric with its derivatives; NaN where it is undefined)."""
    for i in prange(x.shape[0]):
        out[i, 0], out[i, 1] = _acceleration(fn, x[i, 0], x[i, 1], v[i, 0], v[i, 1])


# Dormand & Prince (1980) RK5(4)7M, as geodesic._DP_*
_C2, _C3, _C4, _C5 = 1 / 5, 3 / 10, 4 / 5, 8 / 9
_A21 = 1 / 5
_A31, _A32 = 3 / 40, 9 / 40
_A41, _A42, _A43 = 44 / 45, -56 / 15, 32 / 9
_A51, _A52, _A53, _A54 = 19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729
_A61, _A62, _A63, _A64, _A65 = 9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656
_B1, _B3, _B4, _B5, _B6 = 35 / 384, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84
_E1 = 35 / 384 - 5179 / 57600
_E3 = 500 / 1113 - 7571 / 16695
_E4 = 125 / 192 - 393 / 640
_E5 = -2187 / 6784 + 92097 / 339200
_E6 = 11 / 84 - 187 / 2100
_E7 = -1 / 40


@njit(**_JIT)
def _dp_step(fn, x, y, vx, vy, h):
    """One Dormand–Prince step of the geodesic ODE; (x5, y5, vx5, vy5, error estimate)."""
    k1x, k1y = vx, vy
    a1x, a1y = _acceleration(fn, x, y, vx, vy)
    x2 = x + h * _A21 * k1x
    y2 = y + h * _A21 * k1y
    k2x = vx + h * _A21 * a1x
    k2y = vy + h * _A21 * a1y
    a2x, a2y = _acceleration(fn, x2, y2, k2x, k2y)
    x3 = x + h * (_A31 * k1x + _A32 * k2x)
    y3 = y + h * (_A31 * k1y + _A32 * k2y)
    k3x = vx + h * (_A31 * a1x + _A32 * a2x)
    k3y = vy + h * (_A31 * a1y + _A32 * a2y)
    a3x, a3y = _acceleration(fn, x3, y3, k3x, k3y)
    x4 = x + h * (_A41 * k1x + _A42 * k2x + _A43 * k3x)
    y4 = y + h * (_A41 * k1y + _A42 * k2y + _A43 * k3y)
    k4x = vx + h * (_A41 * a1x + _A42 * a2x + _A43 * a3x)
    k4y = vy + h * (_A41 * a1y + _A42 * a2y + _A43 * a3y)
    a4x, a4y = _acceleration(fn, x4, y4, k4x, k4y)
    x5 = x + h * (_A51 * k1x + _A52 * k2x + _A53 * k3x + _A54 * k4x)
    y5 = y + h * (_A51 * k1y + _A52 * k2y + _A53 * k3y + _A54 * k4y)
    k5x = vx + h * (_A51 * a1x + _A52 * a2x + _A53 * a3x + _A54 * a4x)
    k5y = vy + h * (_A51 * a1y + _A52 * a2y + _A53 * a3y + _A54 * a4y)
    a5x, a5y = _acceleration(fn, x5, y5, k5x, k5y)
    x6 = x + h * (_A61 * k1x + _A62 * k2x + _A63 * k3x + _A64 * k4x + _A65 * k5x)
    y6 = y + h * (_A61 * k1y + _A62 * k2y + _A63 * k3y + _A64 * k4y + _A65 * k5y)
    k6x = vx + h * (_A61 * a1x + _A62 * a2x + _A63 * a3x + _A64 * a4x + _A65 * a5x)
    k6y = vy + h * (_A61 * a1y + _A62 * a2y + _A63 * a3y + _A64 * a4y + _A65 * a5y)
    a6x, a6y = _acceleration(fn, x6, y6, k6x, k6y)
    # 7th stage (FSAL): at the 5th-order solution
    nx = x + h * (_B1 * k1x + _B3 * k3x + _B4 * k4x + _B5 * k5x + _B6 * k6x)
    ny = y + h * (_B1 * k1y + _B3 * k3y + _B4 * k4y + _B5 * k5y + _B6 * k6y)
    nvx = vx + h * (_B1 * a1x + _B3 * a3x + _B4 * a4x + _B5 * a5x + _B6 * a6x)
    nvy = vy + h * (_B1 * a1y + _B3 * a3y + _B4 * a4y + _B5 * a5y + _B6 * a6y)
    a7x, a7y = _acceleration(fn, nx, ny, nvx, nvy)
    ex = h * (_E1 * k1x + _E3 * k3x + _E4 * k4x + _E5 * k5x + _E6 * k6x + _E7 * nvx)
    ey = h * (_E1 * k1y + _E3 * k3y + _E4 * k4y + _E5 * k5y + _E6 * k6y + _E7 * nvy)
    evx = h * (_E1 * a1x + _E3 * a3x + _E4 * a4x + _E5 * a5x + _E6 * a6x + _E7 * a7x)
    evy = h * (_E1 * a1y + _E3 * a3y + _E4 * a4y + _E5 * a5y + _E6 * a6y + _E7 * a7y)
    err = max(max(abs(ex), abs(ey)), max(abs(evx), abs(evy)) * h)
    return nx, ny, nvx, nvy, err


@_row_kernel(min_rows=SEARCH_PARALLEL_ROWS)
def shoot(fn, x0, v0, total, tol, max_iterations, end, vel, ok):
    """:func:`curvimesh.geodesic.shoot`'s adaptive Dormand–Prince loop, one row at a time.

    ``v0`` has unit speed in the metric and finite rows; ``total`` > 0 the lengths.
    Accepted steps have an error estimate at most ``tol`` times |v₀| · length;
    the next step is h · min(5, max(0.2, 0.9 (tol/err)^(1/5))), or h/4 after
    a non-finite step. Writes ends, end velocities and success flags.
    """
    for i in prange(x0.shape[0]):
        x, y = x0[i, 0], x0[i, 1]
        vx, vy = v0[i, 0], v0[i, 1]
        L = total[i]
        scale = math.hypot(vx, vy) * L
        t = 0.0
        h = L / 4.0
        for _ in range(max_iterations):
            h = min(h, L - t)
            nx, ny, nvx, nvy, err = _dp_step(fn, x, y, vx, vy, h)
            err = err / scale
            finite = (
                math.isfinite(nx)
                and math.isfinite(ny)
                and math.isfinite(nvx)
                and math.isfinite(nvy)
                and math.isfinite(err)
            )
            accept = finite and err <= tol
            if accept:
                x, y, vx, vy = nx, ny, nvx, nvy
                t = t + h
            if finite:
                factor = min(max(0.9 * (tol / max(err, 1e-300)) ** 0.2, 0.2), 5.0)
            else:
                factor = 0.25
            h = h * factor
            if accept and t >= L * (1 - 1e-14):
                end[i, 0], end[i, 1] = x, y
                vel[i, 0], vel[i, 1] = vx, vy
                ok[i] = True
                break
            if h < 1e-12 * L:
                break


# --------------------------------------------------------------------------- #
# Vertex relocation (:mod:`curvimesh.smooth`)                                 #
# --------------------------------------------------------------------------- #


@_row_kernel(rows_arg=3)
def tracked_lengths(fn, fd, pts, edges, alpha, tol, t, w, length, kept):
    """:func:`curvimesh.smooth.tracked_lengths` row by row, in one pass (the same
    operations in the same order as its numpy, hence the same bits): for each edge
    ``edges[r]`` ``(E, 2)`` between ``pts`` ``(n, 2)``, the geodesic's bend at the chord's
    middle (:func:`curvimesh.geodesic.geodesic_alpha`, ``fd`` the metric with its
    derivatives; 0 where not finite), the length by the rule (``t``, ``w``) of the parabola
    at ``alpha[r]`` and, where the bend is not within ``tol`` of it, at the bend: the
    shorter into ``length[r]`` and its α into ``kept[r]`` (α on a tie)."""
    for r in prange(edges.shape[0]):
        i, j = edges[r, 0], edges[r, 1]
        ax, ay, bx, by = pts[i, 0], pts[i, 1], pts[j, 0], pts[j, 1]
        dx, dy = bx - ax, by - ay
        cx, cy = 0.5 * (ax + bx), 0.5 * (ay + by)
        bend = _bend_alpha(fd, ax, ay, bx, by)
        if not math.isfinite(bend):
            bend = 0.0
        a = alpha[r]
        best = _parabola_length(fn, ax, ay, bx, by, cx + a * dy, cy + a * (-dx), t, w)
        if not abs(bend - a) <= tol:
            other = _parabola_length(fn, ax, ay, bx, by, cx + bend * dy, cy + bend * (-dx), t, w)
            if other < best:
                best, a = other, bend
        length[r], kept[r] = best, a


@njit(**_JIT)
def relocation_sweep(pts, edges, length, weight, fixed, relax, new, moved):
    """One sweep of :func:`curvimesh.smooth.relocate`'s moves, as its numpy did them (the
    same operations in the same order, hence the same bits): for each edge a–b of
    ``edges`` ``(E, 2)`` of metric length L = ``length[e]``, the targets p_b + (p_a − p_b)/L
    of a and p_a + (p_b − p_a)/L of b (each end itself where L is not finite and
    positive), weighed by ``weight[e]``; each vertex v goes to
    p_v + ``relax`` (Σ w t / max(Σ w, 1e-300) − p_v), unless ``fixed[v]`` or it has no
    edge, into ``new`` ``(n, 2)``, and ``moved[v]`` says whether that move is finite and
    not zero. The sums run over the edges' first ends, then their second ends, each
    in the order of ``edges`` (numpy's ``bincount`` over the two ends concatenated)."""
    n, m = pts.shape[0], edges.shape[0]
    count = np.zeros(n, dtype=np.int64)
    wsum = np.zeros(n)
    sx = np.zeros(n)
    sy = np.zeros(n)
    for r in range(2 * m):
        e = r if r < m else r - m
        i, j = (edges[e, 0], edges[e, 1]) if r < m else (edges[e, 1], edges[e, 0])
        ln = length[e]
        if math.isfinite(ln) and ln > 0:
            tx = pts[j, 0] + (pts[i, 0] - pts[j, 0]) / ln
            ty = pts[j, 1] + (pts[i, 1] - pts[j, 1]) / ln
        else:
            tx, ty = pts[i, 0], pts[i, 1]
        w = weight[e]
        count[i] += 1
        wsum[i] += w
        sx[i] += w * tx
        sy[i] += w * ty
    for v in range(n):
        den = 1e-300 if wsum[v] < 1e-300 else wsum[v]  # np.maximum: NaN stays
        if fixed[v] or count[v] == 0:
            mx, my = 0.0, 0.0
        else:
            mx = relax * (sx[v] / den - pts[v, 0])
            my = relax * (sy[v] / den - pts[v, 1])
        new[v, 0], new[v, 1] = pts[v, 0] + mx, pts[v, 1] + my
        moved[v] = not (math.isnan(mx) or math.isnan(my)) and (abs(mx) > 0 or abs(my) > 0)


# --------------------------------------------------------------------------- #
# Interpolation error of a function on curved triangles                        #
# --------------------------------------------------------------------------- #


@_row_kernel
def element_l2_squared(fn, nodes, shape, du, dv, w, out):
    """∫_t (f − I f)² of the isoparametric P2 interpolant of f (a scalar function
    (x, y) ↦ f, :data:`SIG_F`) on P2 triangles ``nodes`` ``(m, 6, 2)``, by the rule
    (ξ_k, w_k) with the shape functions ``shape`` and their derivatives ``du``,
    ``dv`` ``(k, 6)`` at its points: Σ_k w_k (f(x(ξ_k)) − Σ_a N_a(ξ_k) f(x_a))² |J(ξ_k)|,
    J relative to corner 0 (as :func:`curvimesh.interpolation_error.element_l2_squared`)."""
    for i in prange(nodes.shape[0]):
        x0, y0 = nodes[i, 0, 0], nodes[i, 0, 1]
        values = np.empty(6)
        for a in range(6):
            values[a] = fn(nodes[i, a, 0], nodes[i, a, 1])
        acc = 0.0
        for k in range(w.shape[0]):
            px = py = interp = 0.0
            xu = yu = xv = yv = 0.0
            for a in range(6):
                x, y = nodes[i, a, 0], nodes[i, a, 1]
                px += shape[k, a] * x
                py += shape[k, a] * y
                interp += shape[k, a] * values[a]
                lx, ly = x - x0, y - y0
                xu += du[k, a] * lx
                yu += du[k, a] * ly
                xv += dv[k, a] * lx
                yv += dv[k, a] * ly
            err = fn(px, py) - interp
            acc += err * err * abs(xu * yv - xv * yu) * w[k]
        out[i] = acc


# --------------------------------------------------------------------------- #
# The edge table of a triangle mesh                                            #
# --------------------------------------------------------------------------- #

#: Sides sharing a lower end up to this many are sorted by insertion; more (a node
#: of very high degree, as the centre of a fan) by :func:`_merge_sort_rows`, so that
#: no mesh costs quadratic time.
INSERTION_SORT_MAX = 32


@njit(**_JIT)
def _merge_sort_rows(rows, b0, b1):
    """Rows b0 to b1 − 1 of ``rows`` ``(k, 2)`` sorted in place by column 0, stably
    (bottom-up merge sort, O(r log r) for r rows)."""
    size = b1 - b0
    src = np.empty((size, 2), dtype=rows.dtype)
    dst = np.empty((size, 2), dtype=rows.dtype)
    for i in range(size):
        src[i, 0], src[i, 1] = rows[b0 + i, 0], rows[b0 + i, 1]
    width = 1
    while width < size:
        for left in range(0, size, 2 * width):
            mid = min(left + width, size)
            right = min(left + 2 * width, size)
            i, j = left, mid
            for k in range(left, right):
                if j >= right or (i < mid and src[i, 0] <= src[j, 0]):
                    dst[k, 0], dst[k, 1] = src[i, 0], src[i, 1]
                    i += 1
                else:
                    dst[k, 0], dst[k, 1] = src[j, 0], src[j, 1]
                    j += 1
        src, dst = dst, src
        width *= 2
    for i in range(size):
        rows[b0 + i, 0], rows[b0 + i, 1] = src[i, 0], src[i, 1]


@njit(**_JIT)
def edge_table(triangles, n):
    """The unique edges of the triangles and the edge of each triangle side, as
    ``np.unique(lo * n + hi, return_inverse=True)`` would give them.

    ``triangles`` ``(m, ≥3)`` holds node ids in [0, n) in its first three columns
    (the corners); side k of triangle t joins corners k and (k + 1) % 3, and
    (lo, hi) are its ends sorted (lo = hi where a triangle repeats a corner).
    Returns ``edges`` ``(E, 2)``, the distinct pairs (lo, hi) in lexicographic
    order, and ``tri_edges`` ``(m, 3)``, the index in ``edges`` of side k of t.

    The 3m sides are sorted by a counting sort on lo (O(m + n)), then each run
    of one lo (a handful of sides) by insertion on hi (runs longer than
    :data:`INSERTION_SORT_MAX`: a merge sort), then numbered, a new edge wherever
    (lo, hi) changes. Both sorts are stable: sides of one edge stay in the order t, k.
    """
    m = triangles.shape[0]
    start = np.zeros(n + 1, dtype=np.int64)  # start[lo]: first slot of lo's run
    for t in range(m):
        for k in range(3):
            start[min(triangles[t, k], triangles[t, (k + 1) % 3]) + 1] += 1
    for v in range(n):
        start[v + 1] += start[v]
    fill = start[:n].copy()
    side = np.empty((3 * m, 2), dtype=np.int64)  # (hi, 3 t + k) grouped by lo
    for t in range(m):
        for k in range(3):
            a, b = triangles[t, k], triangles[t, (k + 1) % 3]
            lo = min(a, b)
            p = fill[lo]
            side[p, 0] = max(a, b)
            side[p, 1] = 3 * t + k
            fill[lo] = p + 1
    edges = np.empty((3 * m, 2), dtype=np.int64)
    flat = np.empty(3 * m, dtype=np.int64)
    n_edges = 0
    for v in range(n):
        b0, b1 = start[v], start[v + 1]
        if b1 - b0 > INSERTION_SORT_MAX:
            _merge_sort_rows(side, b0, b1)
        else:
            for i in range(b0 + 1, b1):
                hi, s = side[i, 0], side[i, 1]
                j = i - 1
                while j >= b0 and side[j, 0] > hi:
                    side[j + 1, 0], side[j + 1, 1] = side[j, 0], side[j, 1]
                    j -= 1
                side[j + 1, 0], side[j + 1, 1] = hi, s
        for i in range(b0, b1):
            if i == b0 or side[i, 0] != side[i - 1, 0]:
                edges[n_edges, 0], edges[n_edges, 1] = v, side[i, 0]
                n_edges += 1
            flat[side[i, 1]] = n_edges - 1
    return edges[:n_edges].copy(), flat.reshape(m, 3)


@njit(**_JIT)
def edge_triangles(tri_edges, n_edges):
    """``(n_edges, 2)`` the first two triangles holding each edge, ascending, given
    ``tri_edges`` ``(m, 3)`` (the edge of each side, as :func:`edge_table`); −1 in
    column 1 for an edge of one triangle (in both for an edge of none).

    Sides count in the order t, k: a triangle holding an edge with two sides
    (a repeated corner) takes both columns, and an edge of three or more
    triangles gets its two lowest."""
    out = np.full((n_edges, 2), -1, dtype=np.int64)
    for t in range(tri_edges.shape[0]):
        for k in range(3):
            e = tri_edges[t, k]
            if out[e, 0] < 0:
                out[e, 0] = t
            elif out[e, 1] < 0:
                out[e, 1] = t
    return out


@njit(**_JIT)
def neighbour_tables(tri_edges, edge_tris):
    """``(nbr, side)``, each ``(m, 3)``: ``nbr[t, k]`` the triangle across side k of t
    (the other of the edge's two triangles in ``edge_tris``, :func:`edge_triangles`),
    or −1, and ``side[t, k]`` the first local side of ``nbr[t, k]`` whose neighbour is
    t (0 where none is, −1 on the boundary).

    The same arrays as ``np.where(pair[..., 0] == t, pair[..., 1], pair[..., 0])``
    with ``pair = edge_tris[tri_edges]``, and ``np.where(nbr >= 0,
    np.argmax(nbr[nbr] == t, axis=2), -1)``, in two passes instead of gathers of
    ``(m, 3, 2)`` and ``(m, 3, 3)``.
    """
    m = tri_edges.shape[0]
    nbr = np.empty((m, 3), dtype=np.int64)
    for t in range(m):
        for k in range(3):
            e = tri_edges[t, k]
            nbr[t, k] = edge_tris[e, 1] if edge_tris[e, 0] == t else edge_tris[e, 0]
    side = np.full((m, 3), -1, dtype=np.int64)
    for t in range(m):
        for k in range(3):
            o = nbr[t, k]
            if o >= 0:
                side[t, k] = 0
                for j in range(3):
                    if nbr[o, j] == t:
                        side[t, k] = j
                        break
    return nbr, side


# --------------------------------------------------------------------------- #
# Lawson flips towards the Delaunay triangulation in the metric                #
# --------------------------------------------------------------------------- #


@njit(**_JIT)
def _area(pts, i, j, k):
    """Signed area of triangle (i, j, k), as :func:`curvimesh.mesh.signed_areas`."""
    ux = pts[j, 0] - pts[i, 0]
    uy = pts[j, 1] - pts[i, 1]
    vx = pts[k, 0] - pts[i, 0]
    vy = pts[k, 1] - pts[i, 1]
    return 0.5 * (ux * vy - uy * vx)


@njit(**_JIT)
def _in_circle(pts, a, b, c, d, g11, g12, g22):
    """(in-circle determinant, scale) of :func:`curvimesh.triangulate._in_circle_metric`:
    d against (a, b, c) after x ↦ Lᵀx, M = L Lᵀ (L as LAPACK's Cholesky), and the
    squared metric length of a − d."""
    l00 = math.sqrt(g11)
    l10 = g12 * (1.0 / l00)
    l11 = math.sqrt(g22 - l10 * l10)
    dx, dy = pts[d, 0], pts[d, 1]
    ux, uy = pts[a, 0] - dx, pts[a, 1] - dy
    a0, a1 = l00 * ux + l10 * uy, l11 * uy
    vx, vy = pts[b, 0] - dx, pts[b, 1] - dy
    b0, b1 = l00 * vx + l10 * vy, l11 * vy
    wx, wy = pts[c, 0] - dx, pts[c, 1] - dy
    c0, c1 = l00 * wx + l10 * wy, l11 * wy
    na, nb, nc = a0 * a0 + a1 * a1, b0 * b0 + b1 * b1, c0 * c0 + c1 * c1
    det = a0 * (b1 * nc - nb * c1) - a1 * (b0 * nc - nb * c0) + na * (b0 * c1 - b1 * c0)
    scale = ux * g11 * ux + ux * g12 * uy + uy * g12 * ux + uy * g22 * uy
    return det, scale


@njit(**_JIT)
def _edge_violation(fn, pts, corners, nbr_k, t, k, o):
    """(violation, centroid x, centroid y) of the interior edge k of t (triangle o across):
    for a convex quad, the relative in-circle determinant of its fourth corner in the
    metric at the quad's centroid where it is above 1e-10, else 0; NaN where the metric
    is undefined at the centroid (:func:`metric_delaunay_flips`)."""
    k2 = nbr_k[t, k]
    a = corners[t, k]
    b = corners[t, (k + 1) % 3]
    c = corners[t, (k + 2) % 3]
    d = corners[o, (k2 + 2) % 3]
    cx = 0.25 * (pts[a, 0] + pts[b, 0] + pts[c, 0] + pts[d, 0])
    cy = 0.25 * (pts[a, 1] + pts[b, 1] + pts[c, 1] + pts[d, 1])
    if not (_area(pts, a, d, c) > 0 and _area(pts, d, b, c) > 0):
        return 0.0, cx, cy
    g = fn(cx, cy)
    if not spd3(g):
        return math.nan, cx, cy
    det, scale = _in_circle(pts, a, b, c, d, g[0], g[1], g[2])
    if det > 1e-10 * scale**2:
        return det / scale**2, cx, cy
    return 0.0, cx, cy


@njit(parallel=True, **_JIT)
def metric_delaunay_flips(fn, pts, corners, nbr, nbr_k, max_rounds, bad):
    """:func:`curvimesh.triangulate.metric_delaunay`'s rounds of Lawson flips, in place.

    ``corners`` ``(m, 3)`` counter-clockwise; ``nbr[t, k]`` the triangle across
    local edge k (corners k, k+1) of t, or −1, and ``nbr_k[t, k]`` that edge's
    local index there. Each round takes every interior edge whose quad is
    convex and whose fourth corner lies inside the circumcircle of the other
    three in the metric at the quad's centroid (relative threshold 1e-10 on
    the determinant), orders them by decreasing violation (ties by the
    edge's sorted end ids, as the numpy code's edge table), flips greedily
    those touching no triangle flipped before in the round, and repeats
    until none is left or ``max_rounds``. Only edges of triangles changed in
    the last round are measured again. Returns the number of rounds, or −1
    with the undefined centroid in ``bad`` ``(2,)`` (the first in the order of the
    triangles and their edges).

    The measures of a round are made on numba's threads (each edge is written by
    the one of its triangles that owns it), then taken in that order: the same
    rounds and flips as one thread makes.
    """
    m = corners.shape[0]
    n = pts.shape[0]
    prio = np.zeros((m, 3))  # > 0: the edge violates (by that much); NaN: undefined
    dirty = np.ones(m, dtype=np.bool_)
    used = np.zeros(m, dtype=np.bool_)
    cap = 3 * m
    keys = np.empty(cap, dtype=np.int64)
    pr = np.empty(cap)
    ct = np.empty(cap, dtype=np.int64)
    ck = np.empty(cap, dtype=np.int64)
    for rounds in range(max_rounds):
        for t in prange(m):
            for k in range(3):
                o = nbr[t, k]
                # not boundary, nor the edge of the smaller triangle o
                if o > t and (dirty[t] or dirty[o]):
                    prio[t, k] = _edge_violation(fn, pts, corners, nbr_k, t, k, o)[0]
        count = 0
        for t in range(m):
            for k in range(3):
                o = nbr[t, k]
                if o < t:
                    continue
                if math.isnan(prio[t, k]):
                    _, bad[0], bad[1] = _edge_violation(fn, pts, corners, nbr_k, t, k, o)
                    return -1
                if prio[t, k] > 0.0:
                    a = corners[t, k]
                    b = corners[t, (k + 1) % 3]
                    keys[count] = min(a, b) * n + max(a, b)
                    pr[count] = -prio[t, k]
                    ct[count] = t
                    ck[count] = k
                    count += 1
        if count == 0:
            return rounds
        by_key = np.argsort(keys[:count], kind="mergesort")
        order = by_key[np.argsort(pr[:count][by_key], kind="mergesort")]
        dirty[:] = False
        used[:] = False
        for q in order:
            t1, k1 = ct[q], ck[q]
            t2, k2 = nbr[t1, k1], nbr_k[t1, k1]
            if used[t1] or used[t2]:
                continue
            used[t1] = used[t2] = True
            dirty[t1] = dirty[t2] = True
            a = corners[t1, k1]
            b = corners[t1, (k1 + 1) % 3]
            c = corners[t1, (k1 + 2) % 3]
            d = corners[t2, (k2 + 2) % 3]
            # outer edges a-d (of t2) and c-a (of t1) go to t1' = (a, d, c),
            # d-b (of t2) and b-c (of t1) to t2' = (d, b, c):
            #         c                 c
            #       / | \             / \
            #      a t1|t2 b   -->    a --- b
            #       \ | /             \ /
            #         d                 d
            o_ad, k_ad = nbr[t2, (k2 + 1) % 3], nbr_k[t2, (k2 + 1) % 3]
            o_db, k_db = nbr[t2, (k2 + 2) % 3], nbr_k[t2, (k2 + 2) % 3]
            o_bc, k_bc = nbr[t1, (k1 + 1) % 3], nbr_k[t1, (k1 + 1) % 3]
            o_ca, k_ca = nbr[t1, (k1 + 2) % 3], nbr_k[t1, (k1 + 2) % 3]
            corners[t1, 0], corners[t1, 1], corners[t1, 2] = a, d, c
            corners[t2, 0], corners[t2, 1], corners[t2, 2] = d, b, c
            nbr[t1, 0], nbr_k[t1, 0] = o_ad, k_ad
            nbr[t1, 1], nbr_k[t1, 1] = t2, 2
            nbr[t1, 2], nbr_k[t1, 2] = o_ca, k_ca
            nbr[t2, 0], nbr_k[t2, 0] = o_db, k_db
            nbr[t2, 1], nbr_k[t2, 1] = o_bc, k_bc
            nbr[t2, 2], nbr_k[t2, 2] = t1, 1
            if o_ad >= 0:
                nbr[o_ad, k_ad], nbr_k[o_ad, k_ad] = t1, 0
            if o_ca >= 0:
                nbr[o_ca, k_ca], nbr_k[o_ca, k_ca] = t1, 2
            if o_db >= 0:
                nbr[o_db, k_db], nbr_k[o_db, k_db] = t2, 0
            if o_bc >= 0:
                nbr[o_bc, k_bc], nbr_k[o_bc, k_bc] = t2, 1
    return max_rounds


# --------------------------------------------------------------------------- #
# R-tree box queries                                                           #
# --------------------------------------------------------------------------- #


#: Nodes the stack of an R-tree walk holds at first (:func:`_rtree_visit`). The walk
#: keeps at most (children − 1) × depth + 1: with :data:`curvimesh.spatial.CAPACITY`
#: children, 15 × depth + 1, enough up to a depth of 68.
RTREE_STACK = 1024


@njit(**_JIT)
def _rtree_visit(boxes, first, count, leaf, ids, xy, roots, lo_x, lo_y, hi_x, hi_y, out, n_out):
    """Ids of the points in [lo, hi] (closed) over the trees of ``roots``; writes the first
    ``n_out`` of them to ``out`` from 0 and returns their number.

    ``xy`` holds the points' coordinates in the order of ``ids`` (leaf by leaf), so
    that a leaf's points are read from consecutive memory; a leaf whose box lies
    inside the query box is taken whole. The walk (:func:`_rtree_walk`) gets a stack
    of :data:`RTREE_STACK` nodes, four times more each time it fills one."""
    size = RTREE_STACK
    while True:
        stack = np.empty(size, dtype=np.int64)
        found = _rtree_walk(
            boxes, first, count, leaf, ids, xy, roots, lo_x, lo_y, hi_x, hi_y, out, n_out, stack
        )
        if found >= 0:
            return found
        size *= 4


@njit(**_JIT)
def _overlaps(boxes, node, lo_x, lo_y, hi_x, hi_y):
    """Whether node's box meets the query box [lo, hi] (True where a bound is NaN)."""
    if boxes[node, 0] > hi_x or boxes[node, 2] < lo_x:
        return False
    return not (boxes[node, 1] > hi_y or boxes[node, 3] < lo_y)


@njit(**_JIT)
def _rtree_walk(
    boxes, first, count, leaf, ids, xy, roots, lo_x, lo_y, hi_x, hi_y, out, n_out, stack
):
    """:func:`_rtree_visit`'s depth-first walk with the stack ``stack`` (an argument, never
    replaced: an array the loop may swap for a larger one cost it five times as
    long, 2.6 µs a query against 0.5 on the three toys' fronts); −1 when the stack
    is full. A node is pushed only where its box meets the query's, children in
    order and popped last first, so the ids come in the order of a walk that tests
    each box when popped."""
    found = 0
    for r in range(roots.shape[0]):
        if not _overlaps(boxes, roots[r], lo_x, lo_y, hi_x, hi_y):
            continue
        stack[0] = roots[r]
        top = 1
        while top > 0:
            top -= 1
            node = stack[top]
            start = first[node]
            if leaf[node]:
                whole = (
                    lo_x <= boxes[node, 0]
                    and boxes[node, 2] <= hi_x
                    and lo_y <= boxes[node, 1]
                    and boxes[node, 3] <= hi_y
                )
                for k in range(start, start + count[node]):
                    if whole or (lo_x <= xy[k, 0] <= hi_x and lo_y <= xy[k, 1] <= hi_y):
                        if found < n_out:
                            out[found] = ids[k]
                        found += 1
            else:
                for k in range(start, start + count[node]):
                    if _overlaps(boxes, k, lo_x, lo_y, hi_x, hi_y):
                        if top == stack.shape[0]:
                            return -1
                        stack[top] = k
                        top += 1
    return found


@_row_kernel
def rtree_count(mins, maxs, boxes, first, count, leaf, ids, xy, roots, counts):
    """Number of indexed points in each query box ``[mins[q], maxs[q]]`` into ``counts``.

    The index is packed R-trees (:mod:`curvimesh.spatial`): node bounding boxes
    (xmin, ymin, xmax, ymax), the first child and the number of children of
    each node (nodes for inner nodes, positions in ``ids`` for leaves)."""
    dummy = np.empty(0, dtype=np.int64)
    for q in prange(mins.shape[0]):
        counts[q] = _rtree_visit(
            boxes, first, count, leaf, ids, xy, roots,
            mins[q, 0], mins[q, 1], maxs[q, 0], maxs[q, 1], dummy, 0,
        )  # fmt: skip


@_row_kernel
def rtree_fill(mins, maxs, boxes, first, count, leaf, ids, xy, roots, offsets, hits):
    """The ids of :func:`rtree_count`'s points, query after query from ``offsets``,
    each query's ids in ascending order."""
    for q in prange(mins.shape[0]):
        seg = hits[offsets[q] : offsets[q + 1]]
        n = _rtree_visit(
            boxes, first, count, leaf, ids, xy, roots,
            mins[q, 0], mins[q, 1], maxs[q, 0], maxs[q, 1], seg, offsets[q + 1] - offsets[q],
        )  # fmt: skip
        seg[:n].sort()


@njit(**_JIT)
def _largest_size(g11, g12, g22):
    """1 / sqrt(λ_min) of one tensor, λ_min as :func:`curvimesh.metric.smallest_eigenvalue`
    (the same operations); 0 where it is not finite."""
    top = 0.5 * (g11 + g22) + math.hypot(0.5 * (g11 - g22), g12)
    h = 1.0 / math.sqrt((g11 * g22 - g12 * g12) / top)
    return h if math.isfinite(h) else 0.0


@njit(**_JIT)
def _size_tensor(g11, g12, g22):
    """(s11, s12, s22) = g⁻¹ of one tensor and whether it is a size tensor (finite,
    positive definite), as :func:`curvimesh.sampling._size_tensors` and the test
    of :func:`curvimesh.sampling.search_regions`."""
    det = g11 * g22 - g12 * g12
    s11, s12, s22 = g22 / det, -g12 / det, g11 / det
    ok = (
        math.isfinite(s11) and math.isfinite(s12) and math.isfinite(s22)
        and s11 > 0.0 and s11 * s22 - s12 * s12 > 0.0
    )  # fmt: skip
    return s11, s12, s22, ok


@_row_kernel
def search_regions(fn, pts, box, samples, radius, reach, half, quad):
    """:func:`curvimesh.sampling.search_regions` row by row (the same operations in the
    same order, hence the same bits): the half-widths ``half`` ``(n, 2)`` and the
    ellipses ``quad`` ``(n, 3)`` about points ``pts`` ``(n, 2)`` from the union of
    the size tensors at each point and at ``samples`` ``(k, 2)`` × radius × its
    largest size, clipped to ``box`` (xmin, ymin, xmax, ymax)."""
    for i in prange(pts.shape[0]):
        px, py = pts[i, 0], pts[i, 1]
        g = fn(px, py)
        h = _largest_size(g[0], g[1], g[2])
        u11, u12, u22, have = _size_tensor(g[0], g[1], g[2])
        largest = 0.0
        for k in range(samples.shape[0]):
            qx = min(max(px + samples[k, 0] * (radius * h), box[0]), box[2])
            qy = min(max(py + samples[k, 1] * (radius * h), box[1]), box[3])
            gk = fn(qx, qy)
            largest = max(largest, _largest_size(gk[0], gk[1], gk[2]))
            s11, s12, s22, ok = _size_tensor(gk[0], gk[1], gk[2])
            if ok and have:  # the union of size tensors: their intersection as metrics
                u11, u12, u22 = intersect(u11, u12, u22, s11, s12, s22)
            elif ok:  # the first defined one (the numpy twin intersects it with itself,
                # which gives it back: nested, the larger whole)
                u11, u12, u22, have = s11, s12, s22, True
        hw = reach * max(largest, h)
        det = u11 * u22 - u12 * u12
        scale = det * reach * reach
        q11, q12, q22 = u22 / scale, -u12 / scale, u11 / scale
        r1, r2 = reach * math.sqrt(u11), reach * math.sqrt(u22)
        finite = (
            math.isfinite(q11) and math.isfinite(q12) and math.isfinite(q22)
            and math.isfinite(r1) and math.isfinite(r2)
        )  # fmt: skip
        if have and finite and det > 0.0:
            quad[i, 0], quad[i, 1], quad[i, 2] = q11, q12, q22
            half[i, 0], half[i, 1] = min(r1, hw), min(r2, hw)
        else:  # no defined sample: the square of the local size
            iso = 1.0 / (hw * hw)
            quad[i, 0], quad[i, 1], quad[i, 2] = iso, 0.0, iso
            half[i, 0], half[i, 1] = hw, hw


@njit(**_JIT)
def _in_region(px, py, cx, cy, q11, q12, q22):
    """Whether (px, py) lies in the ellipse (x − c)ᵀ Q (x − c) ≤ 1 (boundary included)."""
    dx = px - cx
    dy = py - cy
    return q11 * dx * dx + 2.0 * q12 * dx * dy + q22 * dy * dy <= 1.0


@_row_kernel
def in_region(p, c, quad, out):
    """:func:`_in_region` row by row: ``p[i]`` in the ellipse ``quad[i]`` about ``c[i]``."""
    for i in prange(p.shape[0]):
        out[i] = _in_region(p[i, 0], p[i, 1], c[i, 0], c[i, 1], quad[i, 0], quad[i, 1], quad[i, 2])


@_row_kernel(min_rows=SEARCH_PARALLEL_ROWS)
def close_in_index(
    fn, cand, g_cand, mins, maxs, quad, exclude, boxes, first, count, leaf, ids, xy, roots,
    pts, short, margin, probes, ts, ws, grid, t, w, tol, out,
):  # fmt: skip
    """:func:`close_candidates` with each candidate's neighbours found on the fly: the
    indexed points (:func:`rtree_fill`'s arguments) in its box ``[mins[i], maxs[i]]``
    and its ellipse ``quad[i]`` about it (:func:`in_region`), but the point
    ``exclude[i]`` (−1: none), in ascending id order as there. One pass over the
    trees per candidate, and no table of pairs."""
    for i in prange(cand.shape[0]):
        x0, y0, x1, y1 = mins[i, 0], mins[i, 1], maxs[i, 0], maxs[i, 1]
        buf = np.empty(64, dtype=np.int64)
        m = _rtree_visit(boxes, first, count, leaf, ids, xy, roots, x0, y0, x1, y1, buf, 64)
        if m > 64:
            buf = np.empty(m, dtype=np.int64)
            _rtree_visit(boxes, first, count, leaf, ids, xy, roots, x0, y0, x1, y1, buf, m)
        nbr = buf[:m]
        nbr.sort()
        kept = 0
        for k in range(m):
            p = nbr[k]
            if p != exclude[i] and _in_region(
                pts[p, 0], pts[p, 1], cand[i, 0], cand[i, 1], quad[i, 0], quad[i, 1], quad[i, 2]
            ):
                nbr[kept] = p
                kept += 1
        out[i] = _nearest_close(
            fn, cand[i, 0], cand[i, 1], g_cand[i, 0], g_cand[i, 1], g_cand[i, 2], pts,
            nbr[:kept], short, margin, probes, ts, ws, grid, t, w, tol,
        )  # fmt: skip


@_row_kernel
def bytes_lower_bound(keys, queries, pos):
    """For each row of ``queries`` ``(k, b)`` (uint8), the first row of ``keys`` ``(n, b)``
    (uint8, sorted byte-wise as memcmp sorts, which is numpy's order of void keys) not
    below it, into ``pos`` ``(k,)``: ``np.searchsorted`` of void keys, binary search."""
    n, width = keys.shape
    for q in prange(queries.shape[0]):
        lo, hi = 0, n
        while lo < hi:
            mid = (lo + hi) // 2
            below = False  # keys[mid] < queries[q]
            for c in range(width):
                if keys[mid, c] != queries[q, c]:
                    below = keys[mid, c] < queries[q, c]
                    break
            if below:
                lo = mid + 1
            else:
                hi = mid
        pos[q] = lo


# --------------------------------------------------------------------------- #
# Memo tables: values of float rows, by the rows' bits                          #
# --------------------------------------------------------------------------- #

_H0 = np.uint64(0x9E3779B97F4A7C15)
_HM = np.uint64(0xFF51AFD7ED558CCD)
_S33 = np.uint64(33)


@njit(**_JIT)
def _slot(words, i, mask):
    """The first slot of row ``i`` of ``words`` ``(n, w)`` (uint64) in a table of
    ``mask + 1`` slots: the row's words folded by the multiply–xorshift step of
    MurmurHash3's finaliser (Appleby 2011)."""
    h = _H0
    for k in range(words.shape[1]):
        h = (h ^ words[i, k]) * _HM
        h = h ^ (h >> _S33)
    return h & mask


_G0 = np.uint64(0x6A09E667F3BCC909)
_GM = np.uint64(0xC4CEB9FE1A85EC53)
_S29 = np.uint64(29)


@njit(**_JIT)
def _fmix(h):
    """MurmurHash3's 64-bit finaliser (Appleby 2011)."""
    h ^= h >> _S33
    h *= _HM
    h ^= h >> _S33
    h *= _GM
    h ^= h >> _S33
    return h


@njit(**_JIT)
def row_fingerprints(words, out):
    """Two 64-bit hashes ``out`` ``(n, 2)`` of each row of ``words`` ``(n, w)`` (uint64, the
    bits of float rows): the words folded by two multiply–xorshift chains of different
    constants, each finished by :func:`_fmix`. Distinct rows share both with a chance
    of about 2⁻¹²⁸ per pair."""
    for i in range(words.shape[0]):
        h = _H0
        g = _G0
        for k in range(words.shape[1]):
            w = words[i, k]
            h = (h ^ w) * _HM
            h = h ^ (h >> _S33)
            g = (g ^ w) * _GM
            g = g ^ (g >> _S29)
        out[i, 0] = _fmix(h)
        out[i, 1] = _fmix(g ^ np.uint64(words.shape[1]))


@njit(**_JIT)
def _probe(keys, filled, words, i):
    """The slot holding row ``i`` of ``words``, or the empty slot where it would go
    (linear probing; the table is never full)."""
    mask = np.uint64(keys.shape[0] - 1)
    j = _slot(words, i, mask)
    while filled[j]:
        same = True
        for k in range(words.shape[1]):
            if keys[j, k] != words[i, k]:
                same = False
                break
        if same:
            return j
        j = (j + np.uint64(1)) & mask
    return j


@_row_kernel(rows_arg=3)
def memo_find(keys, values, filled, words, out, found):
    """For each row of ``words`` ``(n, w)`` (uint64), its value in the table (``keys``
    ``(cap, w)``, ``values`` ``(cap,)``, ``filled`` ``(cap,)``, cap a power of two) into
    ``out`` and whether it is there into ``found`` (lookups only read the table)."""
    for i in prange(words.shape[0]):
        j = _probe(keys, filled, words, i)
        found[i] = filled[j]
        if filled[j]:
            out[i] = values[j]


@njit(**_JIT)
def memo_insert(keys, values, filled, words, vals):
    """Put rows ``words`` ``(n, w)`` with values ``vals`` ``(n,)`` into the table
    (a row already there keeps its first value); the number of rows added. The
    caller keeps the table at most half full."""
    added = 0
    for i in range(words.shape[0]):
        j = _probe(keys, filled, words, i)
        if not filled[j]:
            filled[j] = True
            for k in range(words.shape[1]):
                keys[j, k] = words[i, k]
            values[j] = vals[i]
            added += 1
    return added


# --------------------------------------------------------------------------- #
# Metric areas of curved triangles                                             #
# --------------------------------------------------------------------------- #


@_row_kernel
def metric_areas(fn, nodes, shape, du, dv, w, out):
    """∫_t sqrt(det g) dx of P2 triangles ``nodes`` ``(m, 6, 2)`` by the rule (ξ_k, w_k),
    given the shape functions ``shape`` and their derivatives ``du``, ``dv`` ``(k, 6)``
    at its points: Σ_k w_k sqrt(det g(x(ξ_k))) J(ξ_k), J taken relative to corner 0
    (as :func:`curvimesh.quality.metric_areas`); NaN where g is undefined."""
    for i in prange(nodes.shape[0]):
        out[i] = _metric_area(fn, nodes[i], shape, du, dv, w)


@njit(**_JIT)
def _metric_area(fn, nodes, shape, du, dv, w):
    """∫_t sqrt(det g) dx of one P2 triangle ``nodes`` ``(6, 2)`` (see :func:`metric_areas`)."""
    x0, y0 = nodes[0, 0], nodes[0, 1]
    acc = 0.0
    for k in range(w.shape[0]):
        px = py = 0.0
        xu = yu = xv = yv = 0.0
        for a in range(6):
            x, y = nodes[a, 0], nodes[a, 1]
            px += shape[k, a] * x
            py += shape[k, a] * y
            lx, ly = x - x0, y - y0
            xu += du[k, a] * lx
            yu += du[k, a] * ly
            xv += dv[k, a] * lx
            yv += dv[k, a] * ly
        g = fn(px, py)
        dens = math.sqrt(g[0] * g[2] - g[1] * g[1])
        acc += dens * (xu * yv - xv * yu) * w[k]
    return acc


@njit(fastmath={"contract"}, **_JIT)
def _child_nodes(child, nodes, out):
    """The nodes ``out`` ``(4, 6, 2)`` of the four children of the triangle6 ``nodes``
    ``(6, 2)`` under midpoint subdivision: Σₐ child[k, a] xₐ with ``child`` ``(24, 6)``
    the P2 shape functions at the children's nodes
    (:data:`curvimesh.quality._CHILD_UV`), summed over a = 0 … 5 in order, each
    product added in one fused multiply-add where the machine has it (as numpy's
    matmul adds them through OpenBLAS on such machines: the children of
    :func:`curvimesh.bezier.p2_map`, bit for bit)."""
    for k in range(child.shape[0]):
        for d in range(2):
            acc = 0.0
            for a in range(6):
                acc += child[k, a] * nodes[a, d]
            out[k // 6, k % 6, d] = acc


@_row_kernel
def child_nodes(child, nodes, out):
    """:func:`_child_nodes` of each triangle6 of ``nodes`` ``(m, 6, 2)``, into ``out``
    ``(m, 4, 6, 2)``: the one computation of the children that both ways of
    :func:`curvimesh.quality.metric_areas_adaptive` use."""
    for i in prange(nodes.shape[0]):
        _child_nodes(child, nodes[i], out[i])


@njit(**_JIT)
def _adaptive_area(fn, tri, child, s4, du4, dv4, w4, s8, du8, dv8, w8, rtol, max_level):
    """The metric area of one curved triangle ``tri`` ``(6, 2)`` by adaptive midpoint
    subdivision (:func:`curvimesh.quality.metric_areas_adaptive`): each piece measured
    by the rules of orders 4 and 8 (``s4 … w4``, ``s8 … w8``: :func:`_metric_area`'s
    arguments), their difference its error; the pieces of a level in the order that
    function's arrays hold them, so that every sum is made in the same order. A
    triangle taken whole (most) allocates nothing."""
    fine0 = _metric_area(fn, tri, s8, du8, dv8, w8)
    err0 = abs(fine0 - _metric_area(fn, tri, s4, du4, dv4, w4))
    budget = rtol * abs(fine0)
    total = 0.0
    if err0 <= budget or max_level == 0 or not math.isfinite(err0):
        return total + fine0
    # level 1: the four children of the whole triangle (its budget unspent)
    pieces = np.empty((4, 6, 2))
    _child_nodes(child, tri, pieces)
    share = np.full(4, 0.25)
    for level in range(1, max_level + 1):
        p = pieces.shape[0]
        fine = np.empty(p)
        err = np.empty(p)
        spent = 0.0
        for k in range(p):
            coarse = _metric_area(fn, pieces[k], s4, du4, dv4, w4)
            fine[k] = _metric_area(fn, pieces[k], s8, du8, dv8, w8)
            err[k] = abs(fine[k] - coarse)
            spent += err[k]
        whole = spent <= budget or level == max_level
        keep = np.empty(p, dtype=np.bool_)
        paid = 0.0
        split = 0
        for k in range(p):
            done = whole or not math.isfinite(err[k])
            keep[k] = done or err[k] <= budget * share[k]
            if keep[k]:
                total += fine[k]
                if not done:
                    paid += err[k]
            else:
                split += 1
        budget = budget - paid
        if split == 0:
            break
        nxt = np.empty((4 * split, 6, 2))
        nshare = np.empty(4 * split)
        j = 0
        for k in range(p):
            if not keep[k]:
                _child_nodes(child, pieces[k], nxt[4 * j : 4 * j + 4])
                for c in range(4):
                    nshare[4 * j + c] = share[k] / 4.0
                j += 1
        pieces, share = nxt, nshare
    return total


@_row_kernel(chunk=ADAPTIVE_CHUNK)
def metric_areas_adaptive(
    fn, nodes, child, s4, du4, dv4, w4, s8, du8, dv8, w8, rtol, max_level, out
):  # fmt: skip
    """Metric areas of curved triangles ``nodes`` ``(m, 6, 2)`` to ``rtol`` (estimated) by
    adaptive subdivision down to ``max_level`` (:func:`_adaptive_area`), into ``out``:
    row by row the arithmetic of :func:`curvimesh.quality.metric_areas_adaptive`'s
    level-by-level loop, in one call."""
    for i in prange(nodes.shape[0]):
        out[i] = _adaptive_area(
            fn, nodes[i], child, s4, du4, dv4, w4, s8, du8, dv8, w8, rtol, max_level
        )


#: Corner pairs of the edges 01, 12, 20 of a triangle6 (``bezier.EDGES``).
_EDGE_I = (0, 1, 2)
_EDGE_J = (1, 2, 0)


@njit(**_JIT)
def _bezier_min(b):
    """Exact minimum over the triangle of the quadratic Bezier triangle ``b`` ``(6,)``
    (corners, then edges 01, 12, 20): the scalar twin of :func:`curvimesh.bezier.bezier_min`."""
    best = min(b[0], b[1], b[2])
    for k in range(3):
        bij = b[3 + k]
        p = b[_EDGE_I[k]] - bij
        q = b[_EDGE_J[k]] - bij
        if p > 0.0 and q > 0.0:
            best = min(best, bij + p * q / (p + q))
    b0, b1, b2, b01, b12, b20 = b[0], b[1], b[2], b[3], b[4], b[5]
    a11 = b0 - 2.0 * b01 + b1
    a22 = b0 - 2.0 * b20 + b2
    a12 = b0 - b01 - b20 + b12
    g1 = b01 - b0
    g2 = b20 - b0
    det = a11 * a22 - a12 * a12
    un = a12 * g2 - a22 * g1
    vn = a12 * g1 - a11 * g2
    if det > 0.0 and a11 > 0.0 and un > 0.0 and vn > 0.0 and un + vn < det:
        u = un / det
        v = vn / det
        l0, l1, l2 = 1.0 - u - v, u, v
        value = (
            b0 * l0 * l0 + b1 * l1 * l1 + b2 * l2 * l2
            + 2.0 * (b01 * l0 * l1 + b12 * l1 * l2 + b20 * l2 * l0)
        )  # fmt: skip
        best = min(best, value)
    return best


@njit(**_JIT)
def _valid_p2(nodes, gu, gv, rtol, b):
    """Whether J > 0 on the closed P2 triangle ``nodes`` ``(6, 2)``, decided exactly as
    :func:`curvimesh.bezier.valid_exact` decides it: J at the six nodes from the shape
    gradients there (``gu``, ``gv`` ``(6, 6)``), its Bezier coefficients into ``b`` ``(6,)``
    (b_i = J_i, b_ij = 2 J_ij − (J_i + J_j)/2), valid when their minimum, else the
    exact minimum (:func:`_bezier_min`), exceeds ``rtol`` × max |b|."""
    x0, y0 = nodes[0, 0], nodes[0, 1]
    for k in range(6):
        xu = yu = xv = yv = 0.0
        for a in range(6):
            lx, ly = nodes[a, 0] - x0, nodes[a, 1] - y0
            xu += gu[k, a] * lx
            yu += gu[k, a] * ly
            xv += gv[k, a] * lx
            yv += gv[k, a] * ly
        b[k] = xu * yv - xv * yu
    for k in range(3):
        b[3 + k] = 2.0 * b[3 + k] - 0.5 * (b[_EDGE_I[k]] + b[_EDGE_J[k]])
    top = 0.0
    low = math.inf
    for k in range(6):
        top = max(top, abs(b[k]))
        low = min(low, b[k])
    threshold = rtol * top
    if low > threshold:
        return True
    return _bezier_min(b) > threshold


@njit(**_JIT)
def _star_triangle(nodes, base, slots, r, ax, ay, mid):
    """Nodes ``(6, 2)`` of a star's triangle r into ``nodes``: its nodes ``base[r]`` but
    the star's vertex (slot −1) at (ax, ay) and incident edge e's node (slot e) at
    ``mid[e]``."""
    for a in range(6):
        slot = slots[r, a]
        if slot == -1:
            nodes[a, 0], nodes[a, 1] = ax, ay
        elif slot >= 0:
            nodes[a, 0], nodes[a, 1] = mid[slot, 0], mid[slot, 1]
        else:
            nodes[a, 0], nodes[a, 1] = base[r, a, 0], base[r, a, 1]


@njit(**_JIT)
def screen_moves(
    fn, cand, others, alpha, base, slots, lens0, t, w, shape, du, dv, aw, gu, gv,
    rtol, shortest, longest, q_min, push, keep, ok, new_len, worst,
):  # fmt: skip
    """The moves of a star's vertex to each of ``cand`` ``(k, 2)``, each incident edge
    (other ends ``others`` ``(j, 2)``) keeping its offset ``alpha`` ``(j,)``: the middle
    node (x′ + o)/2 + α (o − x′)×e₃, the length by the rule (``t``, ``w``). ``ok`` ``(k,)``:
    whether every incident edge is in [``shortest``, ``longest``] and every triangle of
    the star (nodes ``base`` ``(s, 6, 2)`` with ``slots`` ``(s, 6)``: −1 the vertex, e >= 0
    the node of incident edge e) is valid (:func:`_valid_p2`); for those, the lengths
    into ``new_len`` ``(k, j)`` (the other rows are left partly written) and ``worst``
    ``(k,)``, the least quality (4) of the star (areas by the rule ``shape``, ``du``,
    ``dv``, ``aw``; the other edges of triangle r keep their lengths ``lens0[r]``, a slot
    3 + e of an incident edge takes its new one) — or −inf where the candidate cannot
    be among the ``keep`` (>= 1) best of the screen of :func:`curvimesh.shift._screened`:
    those of worst quality above ``q_min``, scored by it (``push`` < 0) or by the length
    of incident edge ``push``, higher first, ties to the lower index.

    The candidates are taken in order, and the measures a candidate does not need are
    not made (what the screen picks is that of the full measure):

    * the lengths stop at the first edge out of bounds, the edge that stopped the
      candidate before tried first (a vertex moved further along a ray fails on
      the same edge);
    * the qualities stop once one is at most ``q_min``, or at most the ``keep``-th
      best score of the candidates before (which a later candidate must beat, ties
      going to the first), the triangle that was worst for the candidate before
      measured first; with ``push``, a candidate whose edge is not longer than the
      ``keep``-th longest before is not measured."""
    k, j, s = cand.shape[0], others.shape[0], base.shape[0]
    nodes = np.empty((6, 2))
    mid = np.empty((j, 2))
    b = np.empty(6)
    top = np.full(max(keep, 1), -math.inf)  # the best scores so far, descending
    found = 0
    first_e = first_r = 0
    for c in range(k):
        ax, ay = cand[c, 0], cand[c, 1]
        worst[c] = -math.inf
        for e in range(j):
            bx, by = others[e, 0], others[e, 1]
            mid[e, 0] = 0.5 * (ax + bx) + alpha[e] * (by - ay)
            mid[e, 1] = 0.5 * (ay + by) + alpha[e] * (-(bx - ax))
        good = True
        for i in range(j):
            e = (first_e + i) % j
            bx, by = others[e, 0], others[e, 1]
            length = _parabola_length(fn, ax, ay, bx, by, mid[e, 0], mid[e, 1], t, w)
            new_len[c, e] = length
            if not (length <= longest and length >= shortest):
                good = False
                first_e = e
                break
        for r in range(s):
            if not good:
                break
            _star_triangle(nodes, base, slots, r, ax, ay, mid)
            good = _valid_p2(nodes, gu, gv, rtol, b)
        ok[c] = good
        if not good:
            continue
        bound = top[keep - 1] if found >= keep else -math.inf
        if push >= 0 and new_len[c, push] <= bound:
            continue
        floor = q_min if push >= 0 else max(q_min, bound)
        least = math.inf
        low_r = first_r
        for i in range(s):
            r = (first_r + i) % s
            _star_triangle(nodes, base, slots, r, ax, ay, mid)
            area = _metric_area(fn, nodes, shape, du, dv, aw)
            q = _star_quality(area, slots, lens0, new_len[c], r)
            if q < least:
                least, low_r = q, r
            if least <= floor:
                break
        first_r = low_r
        if least <= floor:
            continue
        worst[c] = least
        score = new_len[c, push] if push >= 0 else least
        # insert into the descending top (a tie stays behind the earlier candidate)
        i = min(found, keep - 1)
        if found < keep or score > top[i]:
            while i > 0 and top[i - 1] < score:
                top[i] = top[i - 1]
                i -= 1
            top[i] = score
            found += 1


@njit(**_JIT)
def _star_quality(area, slots, lens0, r_lens, r):
    """Quality (4) of a star's triangle r (:func:`screen_moves`' ``slots``) of metric area
    ``area``, its incident edges ``r_lens`` ``(j,)`` long, its other edges as ``lens0[r]``:
    4√3 A / ΣL², 0 where not finite (:func:`curvimesh.quality.quality_from`)."""
    total = 0.0
    for m in range(3):
        slot = slots[r, 3 + m]
        length = r_lens[slot] if slot >= 0 else lens0[r, m]
        total += length**2
    q = 4.0 * math.sqrt(3.0) * area / total
    return q if math.isfinite(q) else 0.0


@njit(**_JIT)
def _star_qualities(fn, base, slots, lens0, r_lens, ax, ay, mid, shape, du, dv, aw, nodes, q):
    """Qualities (4) ``q`` ``(s,)`` of a star's triangles (:func:`_star_triangle`,
    :func:`_star_quality`), areas by the rule ``shape``, ``du``, ``dv``, ``aw``."""
    for r in range(base.shape[0]):
        _star_triangle(nodes, base, slots, r, ax, ay, mid)
        q[r] = _star_quality(_metric_area(fn, nodes, shape, du, dv, aw), slots, lens0, r_lens, r)


@njit(**_JIT)
def _backtracked(ax, ay, others, optimal, frac, mid):
    """Middle nodes ``mid`` ``(j, 2)`` of the edges from (ax, ay) to ``others`` ``(j, 2)``,
    ``frac`` of the way from the straight ones to ``optimal`` ``(j, 2)``."""
    for e in range(others.shape[0]):
        sx = 0.5 * (ax + others[e, 0])
        sy = 0.5 * (ay + others[e, 1])
        mid[e, 0] = sx + frac * (optimal[e, 0] - sx)
        mid[e, 1] = sy + frac * (optimal[e, 1] - sy)


@njit(**_JIT)
def _lengths_ok(lens, shortest, longest, by_quality):
    """:meth:`curvimesh.shift._Rule.lengths_ok` of one row of lengths ``(j,)``."""
    for e in range(lens.shape[0]):
        below = lens[e] <= longest if by_quality else lens[e] < longest
        if not (below and lens[e] >= shortest):
            return False
    return True


@njit(**_JIT)
def best_move(
    fn, fd, cand, others, search, grid, tol, max_iter, optimal, base, slots, lens0,
    backtrack, t, w, gu, gv, valid_rtol, s4, du4, dv4, w4, child, s8, du8, dv8, w8, ts, ws,
    starts, rtol, max_level, shortest, longest, q_min, by_quality, push, remeasure_below,
    out_mid, out_len, out_q,
):  # fmt: skip
    """:func:`curvimesh.shift._best_move`: the best admissible move of a star's vertex to
    one of ``cand`` ``(k, 2)``, each incident edge (other ends ``others`` ``(j, 2)``)
    through a middle node between the straight one and its shortest parabola's
    ``optimal`` ``(k, j, 2)``; the candidate's index (its middle nodes into ``out_mid``
    ``(j, 2)``, its exact lengths into ``out_len`` ``(j,)`` and its star's qualities into
    ``out_q`` ``(s,)``), or −1.

    With ``search``, the shortest parabolas are searched here first, into ``optimal``:
    each from the geodesic's bend at the chord's middle (:func:`_acceleration` of the
    metric with its derivatives ``fd``, as :func:`curvimesh.geodesic.geodesic_alpha`),
    kept where no value of the coarse scan of ``grid`` is shorter
    (:func:`_search_guided`, tolerance ``tol``, ``max_iter`` steps, rule ``t``, ``w``):
    :func:`curvimesh.geodesic.shortest_parabola`'s guided search, row by row on this
    thread (the caller searches the moves of many rows on all threads).

    Star as :func:`screen_moves` takes it (``base``, ``slots``, ``lens0``). For each
    fraction of ``backtrack`` in turn, the candidates not yet valid are tried with
    their nodes at it: valid (:func:`_valid_p2`), lengths by the rule (``t``, ``w``) in
    the rule's bounds (``shortest``, ``longest``, ``by_quality``: :func:`_lengths_ok`),
    scored by the longest length (a long-edge move) or, for a quality move, by the
    worst quality of the star (areas by ``s4`` … ``w4``) or the length of incident edge
    ``push`` (then only above ``q_min``), lower first. The four best, ties to the
    lower index, are measured exactly in turn: lengths to ``rtol``
    (:func:`_adaptive_length`, rules ``ts``, ``ws``, ``starts``) in the bounds, and the
    qualities of the star, by the rule of order 4 and, below ``remeasure_below``, to
    ``rtol`` (:func:`_adaptive_area`); the first whose worst quality is above ``q_min``
    (at least, for a long-edge move) is the move. The same arithmetic in the same order
    as the numpy code, which :mod:`curvimesh.shift` keeps for metrics without compiled
    code."""
    k, j, s = cand.shape[0], others.shape[0], base.shape[0]
    nodes = np.empty((6, 2))
    b = np.empty(6)
    mid = np.empty((j, 2))
    lens = np.empty(j)
    q = np.empty(s)
    todo = np.ones(k, dtype=np.bool_)
    level = np.full(k, -1, dtype=np.int64)
    score = np.empty(k)
    for c in range(k if search else 0):
        ax, ay = cand[c, 0], cand[c, 1]
        for e in range(j):
            bx, by = others[e, 0], others[e, 1]
            dx, dy = bx - ax, by - ay
            guess = _bend_alpha(fd, ax, ay, bx, by)
            alpha = _search_guided(fn, ax, ay, bx, by, guess, grid, t, w, tol, max_iter)[0]
            optimal[c, e, 0] = 0.5 * (ax + bx) + alpha * dy
            optimal[c, e, 1] = 0.5 * (ay + by) + alpha * (-dx)
    for lv in range(backtrack.shape[0]):
        frac = backtrack[lv]
        for c in range(k):
            if not todo[c]:
                continue
            ax, ay = cand[c, 0], cand[c, 1]
            _backtracked(ax, ay, others, optimal[c], frac, mid)
            valid = True
            for r in range(s):
                _star_triangle(nodes, base, slots, r, ax, ay, mid)
                if not _valid_p2(nodes, gu, gv, valid_rtol, b):
                    valid = False
                    break
            if not valid:
                continue
            todo[c] = False
            for e in range(j):
                lens[e] = _parabola_length(
                    fn, ax, ay, others[e, 0], others[e, 1], mid[e, 0], mid[e, 1], t, w
                )
            if not _lengths_ok(lens, shortest, longest, by_quality):
                continue
            if by_quality:
                _star_qualities(
                    fn, base, slots, lens0, lens, ax, ay, mid, s4, du4, dv4, w4, nodes, q
                )
                worst = q[0]
                for r in range(1, s):
                    worst = min(worst, q[r])
                if push >= 0 and not worst > q_min:
                    continue
                score[c] = -lens[push] if push >= 0 else -worst
            else:
                top = lens[0]
                for e in range(1, j):
                    top = max(top, lens[e])
                score[c] = top
            level[c] = lv
    found = np.flatnonzero(level >= 0)  # ascending index: the sort's ties
    order = found[np.argsort(score[found], kind="mergesort")]
    for c in order[:4]:
        ax, ay = cand[c, 0], cand[c, 1]
        _backtracked(ax, ay, others, optimal[c], backtrack[level[c]], mid)
        for e in range(j):
            lens[e] = _adaptive_length(
                fn, ax, ay, others[e, 0], others[e, 1], mid[e, 0], mid[e, 1], math.nan, False,
                ts, ws, starts, rtol,
            )  # fmt: skip
        if not _lengths_ok(lens, shortest, longest, by_quality):
            continue
        _star_qualities(fn, base, slots, lens0, lens, ax, ay, mid, s4, du4, dv4, w4, nodes, q)
        for r in range(s):
            if q[r] < remeasure_below:
                _star_triangle(nodes, base, slots, r, ax, ay, mid)
                area = _adaptive_area(
                    fn, nodes, child, s4, du4, dv4, w4, s8, du8, dv8, w8, rtol, max_level
                )
                q[r] = _star_quality(area, slots, lens0, lens, r)
        worst = q[0]
        for r in range(1, s):
            worst = min(worst, q[r])
        if worst > q_min if by_quality else worst >= q_min:
            out_mid[:, :] = mid
            out_len[:] = lens
            out_q[:] = q
            return c
    return -1


# --------------------------------------------------------------------------- #
# The interpolation metric at one point (helpers for generated metric code)    #
# --------------------------------------------------------------------------- #
#
# Scalar twins of the construction of :mod:`curvimesh.interpolation` (shape,
# continuous-mesh scaling, clamp, central differences), called by the code of
# :meth:`curvimesh.interpolation.InterpolationMetric.scalar_source` with the
# metric's constants as literals. Each does the numpy function's floating-point
# operations in the same order, so that the two differ only by the last bits of
# the elementary functions (the C library's log, exp, hypot against numpy's own)
# and of the derivatives of f (the same expressions, printed for numpy and for
# math); NaN propagates as there: np.maximum and np.clip keep a NaN, np.argmin
# picks the first NaN.

#: Floor of |derivative| before logarithms (``interpolation._TINY``).
_TINY = 1e-300


@njit(**_JIT)
def _nan_max(a, b):
    """np.maximum of two floats: NaN if either is NaN."""
    if math.isnan(a) or math.isnan(b):
        return math.nan
    return a if a >= b else b


@njit(**_JIT)
def _clip(v, lo, hi):
    """np.clip of one float: NaN stays NaN."""
    if v < lo:
        return lo
    if v > hi:
        return hi
    return v


@njit(**_JIT)
def _log_floor(v):
    """log(max(|v|, 1e-300)), NaN for NaN (as the numpy code)."""
    return math.log(_nan_max(abs(v), _TINY))


@njit(**_JIT)
def shape_frame(g11, g12, g22):
    """Unit eigenvector (cos φ, sin φ) of the larger eigenvalue of [[g11, g12], [g12, g22]].

    :func:`curvimesh.interpolation._frame` at one point: cos 2φ = (g11 − g22)/2 / r,
    r = hypot((g11 − g22)/2, g12), then the half-angle formulas; (1, 0) where r is
    not positive (isotropic, or NaN).
    """
    half = 0.5 * (g11 - g22)
    radius = math.hypot(half, g12)
    cos2 = half / radius if radius > 0.0 else 1.0
    cos = math.sqrt(0.5 + 0.5 * cos2)
    sin = math.copysign(math.sqrt(0.5 - 0.5 * cos2), g12)
    return cos, sin


@njit(**_JIT)
def cubic_shape(a, b, c, d, max_aspect):
    """:func:`curvimesh.interpolation.cubic_shape` at one point: (cos φ, sin φ, X, Y).

    The frame of G = Σ_jk T_ijk T_ljk of the cubic a u³ + 3b u²v + 3c uv² + d v³,
    its coefficients |A|, |D|, |B|, |C| in the frame, and the minimum of
    S = X + Y over t = X − Y in [−2 log max_aspect, 2 log max_aspect] among
    the four crossings of the LP's bounds and the two ends (the first smallest,
    as np.argmin).
    """
    g11 = a * a + 2.0 * b * b + c * c
    g12 = a * b + 2.0 * b * c + c * d
    g22 = b * b + 2.0 * c * c + d * d
    cos, sin = shape_frame(g11, g12, g22)
    m0, m1 = cos * cos * cos, cos * cos * sin
    m2, m3 = cos * sin * sin, sin * sin * sin
    v0 = _log_floor(a * m0 + 3.0 * (b * m1 + c * m2) + d * m3)
    v1 = _log_floor(d * m0 - a * m3 + 3.0 * (b * m2 - c * m1))
    v2 = _log_floor(b * (m0 - 2.0 * m2) + c * (2.0 * m1 - m3) + d * m2 - a * m1)
    v3 = _log_floor(c * (m0 - 2.0 * m2) + b * (m3 - 2.0 * m1) + a * m2 + d * m1)
    va, vd, vb, vc = (2.0 / 3.0) * v0, (2.0 / 3.0) * v1, 2.0 * v2, 2.0 * v3
    cap = 2.0 * math.log(max_aspect)
    best_s = math.inf
    best_t = math.nan
    for j in range(6):
        if j == 0:
            t = va - vd
        elif j == 1:
            t = 1.5 * va - 0.5 * vc
        elif j == 2:
            t = 0.5 * vb - 1.5 * vd
        elif j == 3:
            t = vb - vc
        elif j == 4:
            t = -cap
        else:
            t = cap
        t = _clip(t, -cap, cap)
        s = _nan_max(2.0 * va - t, 2.0 * vd + t)
        s = _nan_max(s, (2.0 / 3.0) * vb - t / 3.0)
        s = _nan_max(s, (2.0 / 3.0) * vc + t / 3.0)
        if math.isnan(s):  # np.argmin: the first NaN
            best_s, best_t = s, t
            break
        if j == 0 or s < best_s:
            best_s, best_t = s, t
    return cos, sin, 0.5 * (best_s + best_t), 0.5 * (best_s - best_t)


@njit(**_JIT)
def hessian_shape(fxx, fxy, fyy, max_aspect):
    """:func:`curvimesh.interpolation.hessian_shape` at one point: (cos φ, sin φ, X, Y).

    The eigenvector of the larger eigenvalue of H, the logs of the absolute
    eigenvalues (mean ± radius), the smaller raised to the larger − 2 log max_aspect.
    """
    mean = 0.5 * (fxx + fyy)
    radius = math.hypot(0.5 * (fxx - fyy), fxy)
    cos, sin = shape_frame(fxx, fxy, fyy)
    x_log = _log_floor(mean + radius)
    y_log = _log_floor(mean - radius)
    floor = _nan_max(x_log, y_log) - 2.0 * math.log(max_aspect)
    return cos, sin, _nan_max(x_log, floor), _nan_max(y_log, floor)


@njit(**_JIT)
def tensor_from_frame(cos, sin, l1, l2):
    """:func:`curvimesh.interpolation.tensor_from_frame` at one point: (g11, g12, g22)
    with eigenvalue l1 along (cos φ, sin φ) and l2 across it."""
    cc, ss, cs = cos * cos, sin * sin, (l1 - l2) * cos * sin
    return l1 * cc + l2 * ss, cs, l1 * ss + l2 * cc


@njit(**_JIT)
def interpolation_tensor(shape, log_scale, beta, lo, hi):
    """The metric (g11, g12, g22) of a shape (cos φ, sin φ, X, Y), as
    ``InterpolationMetric._tensor``: log μᵢ = log D + β (X + Y) + (X or Y), clamped
    to [lo, hi] = [−2 log HMAX, −2 log HMIN], eigenvalues μᵢ along e₁ and e₂."""
    cos, sin, x_log, y_log = shape
    common = log_scale + beta * (x_log + y_log)
    mu1 = math.exp(_clip(common + x_log, lo, hi))
    mu2 = math.exp(_clip(common + y_log, lo, hi))
    return tensor_from_frame(cos, sin, mu1, mu2)


@njit(**_JIT)
def central_differences(g, px, mx, py, my, h):
    """(g, ∂ₓg, ∂ᵧg) as a 9-tuple from g at (x, y) and at (x ± h, y), (x, y ± h).

    As ``InterpolationMetric.evaluate(derivatives=True)``: (g(+h) − g(−h)) · (0.5/h);
    where that is not finite, per direction: (g(+h) − g(−h)) / 2h where both
    shifted values are finite, (g(+h) − g)/h where only g(+h) is, else (g − g(−h))/h.
    """
    s = 0.5 / h
    d = (
        g[0], g[1], g[2],
        (px[0] - mx[0]) * s, (px[1] - mx[1]) * s, (px[2] - mx[2]) * s,
        (py[0] - my[0]) * s, (py[1] - my[1]) * s, (py[2] - my[2]) * s,
    )  # fmt: skip
    if finite9(d):
        return d
    dx = _one_sided(g, px, mx, h)
    dy = _one_sided(g, py, my, h)
    return (g[0], g[1], g[2], dx[0], dx[1], dx[2], dy[0], dy[1], dy[2])


@njit(**_JIT)
def _one_sided(g, p, m, h):
    """One direction of :func:`central_differences` where the central one is not finite."""
    if finite3(p) and finite3(m):
        w = 2.0 * h
        return (p[0] - m[0]) / w, (p[1] - m[1]) / w, (p[2] - m[2]) / w
    if finite3(p):
        return (p[0] - g[0]) / h, (p[1] - g[1]) / h, (p[2] - g[2]) / h
    return (g[0] - m[0]) / h, (g[1] - m[1]) / h, (g[2] - m[2]) / h


# --------------------------------------------------------------------------- #
# Graded background grids (:mod:`curvimesh.gradation`)                          #
# --------------------------------------------------------------------------- #


@njit(**_JIT)
def span_metric(g11, g12, g22, grow):
    """The SPD tensor (g11, g12, g22) with its sizes hᵢ = λᵢ^(−1/2) grown to hᵢ + grow,
    its eigenvectors kept (the span of :mod:`curvimesh.gradation`).

    λ₁ = m + r (m, r the mean and half-difference radius of the eigenvalues) along
    (cos φ, sin φ) of :func:`shape_frame`, λ₂ = det / λ₁ across it.
    """
    m = 0.5 * (g11 + g22)
    r = math.hypot(0.5 * (g11 - g22), g12)
    l1 = m + r
    l2 = (g11 * g22 - g12 * g12) / l1
    cos, sin = shape_frame(g11, g12, g22)
    h1 = 1.0 / math.sqrt(l1) + grow
    h2 = 1.0 / math.sqrt(l2) + grow
    return tensor_from_frame(cos, sin, 1.0 / (h1 * h1), 1.0 / (h2 * h2))


@njit(**_JIT)
def grade_metrics(g, dx, dy, rate, max_sweeps, margin):
    """Grade the metrics ``g`` ``(nx, ny, 3)`` of a grid's nodes in place; the sweeps done.

    Node (i, j) sits at (x0 + i dx, y0 + j dy). Each node q takes the intersection
    (:func:`intersect`) of its metric with the span of each of its 8 neighbours p:
    M_p with the same eigenvectors and each of its sizes hᵢ grown to hᵢ + rate |pq|
    (:func:`span_metric`). Gauss-Seidel sweeps in the four raster orders (fast
    sweeping), until a sweep changes no node, or ``max_sweeps``. A span changes a
    node only where it is finer by more than the relative ``margin``: where
    (1 + margin) M_q − span is not positive semidefinite (without a margin, the
    rounding of the spans and intersections of a converged grid would keep
    changing it in the last bits).
    """
    nx, ny = g.shape[0], g.shape[1]
    grow_x, grow_y, grow_xy = rate * dx, rate * dy, rate * math.hypot(dx, dy)
    scale = 1.0 + margin
    for sweep in range(max_sweeps):
        changed = False
        for order in range(4):
            for ii in range(nx):
                i = ii if order % 2 == 0 else nx - 1 - ii
                for jj in range(ny):
                    j = jj if order < 2 else ny - 1 - jj
                    a11, a12, a22 = g[i, j, 0], g[i, j, 1], g[i, j, 2]
                    for di in range(-1, 2):
                        for dj in range(-1, 2):
                            p, q = i + di, j + dj
                            if (di == 0 and dj == 0) or p < 0 or p >= nx or q < 0 or q >= ny:
                                continue
                            grow = (
                                grow_xy if di != 0 and dj != 0 else (grow_x if di != 0 else grow_y)
                            )
                            b11, b12, b22 = span_metric(g[p, q, 0], g[p, q, 1], g[p, q, 2], grow)
                            d11, d12, d22 = scale * a11 - b11, scale * a12 - b12, scale * a22 - b22
                            if d11 >= 0.0 and d22 >= 0.0 and d11 * d22 - d12 * d12 >= 0.0:
                                continue
                            a11, a12, a22 = intersect(a11, a12, a22, b11, b12, b22)
                    if a11 != g[i, j, 0] or a12 != g[i, j, 1] or a22 != g[i, j, 2]:
                        g[i, j, 0], g[i, j, 1], g[i, j, 2] = a11, a12, a22
                        changed = True
        if not changed:
            return sweep + 1
    return max_sweeps


@njit(**_JIT)
def exp_tensor(l11, l12, l22):
    """:func:`curvimesh.tensors.exp_components` at one point: exp of (L11, L12, L22)."""
    m = 0.5 * (l11 + l22)
    d = 0.5 * (l11 - l22)
    r = math.hypot(d, l12)
    e = math.exp(m)
    c = e * math.cosh(r)
    s = e * (math.sinh(r) / r if r > 1e-8 else 1.0)
    return c + s * d, s * l12, c - s * d


@njit(**_JIT)
def bspline_basis(t):
    """The four uniform cubic B-spline weights at t (:func:`curvimesh.gradation.bspline_basis`)."""
    s = 1.0 - t
    t2 = t * t
    t3 = t2 * t
    return (
        s * s * s / 6.0,
        (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0,
        (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0,
        t3 / 6.0,
    )


@njit(**_JIT)
def _cell(u, n):
    """Cell index in [0, n − 2] of grid coordinate u and the offset in it, within [−1, 2]."""
    if not math.isfinite(u):
        return 0, math.nan
    i = min(max(math.floor(u), 0.0), n - 2.0)
    t = min(max(u - i, -1.0), 2.0)
    return int(i), t


@njit(**_JIT)
def grid_tensor(x, y, l11, l12, l22, x0, y0, dx, dy):
    """:meth:`curvimesh.gradation.GradedGrid.components` at one point: the cubic B-spline
    of the padded node logarithms ``l11, l12, l22`` ``(nx + 2, ny + 2)``, exponentiated."""
    nx, ny = l11.shape[0] - 2, l11.shape[1] - 2
    i, t = _cell((x - x0) / dx, nx)
    j, u = _cell((y - y0) / dy, ny)
    bx = bspline_basis(t)
    by = bspline_basis(u)
    s11 = s12 = s22 = 0.0
    for a in range(4):
        r11 = r12 = r22 = 0.0
        for b in range(4):
            r11 += by[b] * l11[i + a, j + b]
            r12 += by[b] * l12[i + a, j + b]
            r22 += by[b] * l22[i + a, j + b]
        s11 += bx[a] * r11
        s12 += bx[a] * r12
        s22 += bx[a] * r22
    return exp_tensor(s11, s12, s22)


#: Node arrays of graded grids by key, for generated metric code (:func:`grid_array`).
GRIDS: dict[str, NDArray] = {}


def grid_array(key: str) -> NDArray:
    """The array registered as ``GRIDS[key]`` (generated code binds it to a global, which
    numba then compiles in as a constant: a key names its content, a hash of its bytes)."""
    return GRIDS[key]


#: :data:`HELPERS` with the interpolation metric's (appended here, beside their section).
HELPERS = {
    **HELPERS,
    "cubic_shape": cubic_shape,
    "hessian_shape": hessian_shape,
    "interpolation_tensor": interpolation_tensor,
    "central_differences": central_differences,
    "grid_tensor": grid_tensor,
    "grid_array": grid_array,
}


# --------------------------------------------------------------------------- #
# Walks and conflict sets in a Euclidean Delaunay triangulation                #
# --------------------------------------------------------------------------- #

#: Relative error bound of the predicates below: a determinant within this
#: fraction of its permanent (the sum of the absolute values of its terms) has
#: no trusted sign (the floating-point error is below 1e-14 of the permanent).
PREDICATE_TOL = 1e-10


@njit(**_JIT)
def _orient(pts, a, b, qx, qy):
    """(d, permanent) of the orientation of q against the directed line a → b:
    d = (b − a) × (q − a), positive when q lies on its left."""
    ux = pts[b, 0] - pts[a, 0]
    uy = pts[b, 1] - pts[a, 1]
    vx = qx - pts[a, 0]
    vy = qy - pts[a, 1]
    return ux * vy - uy * vx, abs(ux * vy) + abs(uy * vx)


@njit(**_JIT)
def in_circle_point(pts, a, b, c, qx, qy):
    """(d, permanent) of the in-circle determinant of q against counter-clockwise (a, b, c).

    With a, b, c taken relative to q, d = |a|² (b × c) + |b|² (c × a) + |c|² (a × b)
    (the lifting-map determinant), positive when q lies strictly inside the
    circumcircle.

    >>> p = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    >>> in_circle_point(p, 0, 1, 2, 0.5, 0.5)[0] > 0, in_circle_point(p, 0, 1, 2, 2.0, 2.0)[0] < 0
    (True, True)
    """
    ax, ay = pts[a, 0] - qx, pts[a, 1] - qy
    bx, by = pts[b, 0] - qx, pts[b, 1] - qy
    cx, cy = pts[c, 0] - qx, pts[c, 1] - qy
    na, nb, nc = ax * ax + ay * ay, bx * bx + by * by, cx * cx + cy * cy
    d = na * (bx * cy - by * cx) + nb * (cx * ay - cy * ax) + nc * (ax * by - ay * bx)
    perm = (
        na * (abs(bx * cy) + abs(by * cx))
        + nb * (abs(cx * ay) + abs(cy * ax))
        + nc * (abs(ax * by) + abs(ay * bx))
    )
    return d, perm


@njit(**_JIT)
def _walk(pts, corners, nbr, qx, qy, t):
    """Visibility walk from triangle t towards q: crosses local edge k while q lies
    decisively on its right (orientation below −:data:`PREDICATE_TOL` × permanent).
    Returns the triangle where no edge sends q on, or −1 when the walk leaves the
    triangulation or takes more steps than there are triangles (which a walk in a
    Delaunay triangulation never does)."""
    for _ in range(corners.shape[0] + 1):
        nxt = -1
        for k in range(3):
            d, perm = _orient(pts, corners[t, k], corners[t, (k + 1) % 3], qx, qy)
            if d < -PREDICATE_TOL * perm:
                nxt = nbr[t, k]
                if nxt < 0:
                    return -1
                break
        if nxt < 0:
            return t
        t = nxt
    return -1


@njit(**_JIT)
def _cavity(pts, corners, nbr, s, qx, qy, i, seen, stack, cavity, undecided_fails):
    """The triangles reached from ``s`` through neighbours whose circumcircle strictly
    holds q (in-circle determinant above :data:`PREDICATE_TOL` × its permanent), ``s``
    first, written into ``cavity``; returns their number. A search over neighbours (a
    stack) marking the triangles it visits with ``seen[t] = i``. A determinant within the
    bound of 0 leaves its triangle out, or with ``undecided_fails`` ends the search
    with −1."""
    seen[s] = i
    stack[0] = s
    top = 1
    nc = 0
    while top > 0:
        top -= 1
        t = stack[top]
        cavity[nc] = t
        nc += 1
        for k in range(3):
            o = nbr[t, k]
            if o < 0 or seen[o] == i:
                continue
            seen[o] = i
            d, perm = in_circle_point(pts, corners[o, 0], corners[o, 1], corners[o, 2], qx, qy)
            if abs(d) <= PREDICATE_TOL * perm:
                if undecided_fails:
                    return -1
            elif d > 0:
                stack[top] = o
                top += 1
    return nc


@njit(**_JIT)
def delaunay_conflicts(pts, corners, nbr, q, conflict):
    """Marks in ``conflict`` ``(m,)`` the triangles whose circumcircle strictly holds
    some point of ``q`` ``(k, 2)`` (the cavities of Bowyer and Watson), in a
    Delaunay triangulation ``corners`` ``(m, 3)`` of ``pts`` with neighbours ``nbr``.

    For each q: a visibility walk (from where the last one ended) to a triangle
    that holds q up to the tolerance, then a search (:func:`_cavity`) through the
    neighbours whose circumcircle holds q (a cavity is edge-connected: it is
    star-shaped from q). Returns 0, or −1 when a walk leaves the triangulation or
    an in-circle determinant is within :data:`PREDICATE_TOL` × its permanent of 0
    (q on a circumcircle, or q a vertex: the conflict set is then not certain).

    >>> p = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.2]])
    >>> tri, nbr = np.array([[0, 1, 2], [0, 2, 3]]), np.array([[-1, -1, 1], [0, -1, -1]])
    >>> c = np.zeros(2, dtype=np.bool_)
    >>> delaunay_conflicts(p, tri, nbr, np.array([[0.9, 0.05]]), c), c.tolist()
    (0, [True, False])
    """
    m = corners.shape[0]
    stamp = np.full(m, -1, dtype=np.int64)
    stack = np.empty(m, dtype=np.int64)
    cavity = np.empty(m, dtype=np.int64)
    t = 0
    for i in range(q.shape[0]):
        qx, qy = q[i, 0], q[i, 1]
        s = _walk(pts, corners, nbr, qx, qy, t)
        if s < 0:
            return -1
        t = s
        d, perm = in_circle_point(pts, corners[s, 0], corners[s, 1], corners[s, 2], qx, qy)
        if not d > PREDICATE_TOL * perm:
            return -1
        nc = _cavity(pts, corners, nbr, s, qx, qy, i, stamp, stack, cavity, True)
        if nc < 0:
            return -1
        for c in range(nc):
            conflict[cavity[c]] = True
    return 0


@njit(**_JIT)
def strict_delaunay_sides(pts, corners, nbr, ok):
    """``ok[t, k]`` ``(m, 3)``: whether the triangle across local edge k of t has its
    far corner d strictly outside the circumcircle of t (in-circle determinant
    below −:data:`PREDICATE_TOL` × its permanent); True on the boundary. Each
    interior edge is measured once, from its lower triangle, and the verdict
    written on both sides. Returns the number of interior edges not strictly
    locally Delaunay.

    >>> p = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    >>> tri, nbr = np.array([[0, 1, 2], [0, 2, 3]]), np.array([[-1, -1, 1], [0, -1, -1]])
    >>> ok = np.empty((2, 3), dtype=np.bool_)
    >>> strict_delaunay_sides(p, tri, nbr, ok), ok.tolist()  # co-circular
    (1, [[True, True, False], [False, True, True]])
    """
    bad = 0
    ok[:] = True
    for t in range(corners.shape[0]):
        for k in range(3):
            o = nbr[t, k]
            if o < t:
                continue
            a, b, c = corners[t, k], corners[t, (k + 1) % 3], corners[t, (k + 2) % 3]
            d = -1
            k2 = 0
            for j in range(3):
                if corners[o, j] != a and corners[o, j] != b:
                    d = corners[o, j]
                if nbr[o, j] == t:
                    k2 = j
            det, perm = in_circle_point(pts, a, b, c, pts[d, 0], pts[d, 1])
            if not det < -PREDICATE_TOL * perm:
                ok[t, k] = False
                ok[o, k2] = False
                bad += 1
    return bad


@njit(**_JIT)
def flood_fill(nbr, wall, seeds, inside):
    """Marks in ``inside`` ``(m,)`` the triangles reached from ``seeds`` ``(s,)`` through
    the sides (t, k) that are not walls (``wall`` ``(m, 3)``), ``nbr[t, k]`` being
    the triangle across local edge k of t, or −1. Returns the number marked.

    >>> nbr = np.array([[1, -1, -1], [0, 2, -1], [1, -1, -1]])
    >>> wall = np.zeros((3, 3), dtype=np.bool_)
    >>> wall[1, 1] = wall[2, 0] = True
    >>> inside = np.zeros(3, dtype=np.bool_)
    >>> flood_fill(nbr, wall, np.array([0]), inside), inside.tolist()
    (2, [True, True, False])
    """
    stack = np.empty(nbr.shape[0], dtype=np.int64)
    top = 0
    count = 0
    for s in seeds:
        if inside[s]:
            continue
        inside[s] = True
        count += 1
        stack[0] = s
        top = 1
        while top > 0:
            top -= 1
            t = stack[top]
            for k in range(3):
                o = nbr[t, k]
                if wall[t, k] or o < 0 or inside[o]:
                    continue
                inside[o] = True
                count += 1
                stack[top] = o
                top += 1
    return count


#: Distance of the three corners of :func:`bowyer_watson`'s enclosing triangle from the
#: points' bounding box centre, in units of its largest side D. Nearer, a flat triangle
#: of the points along their hull (a point close to a side of the box) has the corner
#: in its circumcircle and is missing; farther, the in-circle determinants of the
#: triangles with a corner lose the digits that decide them. On 300 clouds of up to
#: 3,000 points, with points drawn on the box's sides and up to 30 within 10⁻⁷ –
#: 10⁻² of them, the result was certified for 54 at 10³ D, 158 at 10⁴, 263 at 10⁵,
#: 254 at 10⁶ and 4 at 10⁸ (undecided predicates), and equal to Qhull's wherever it was.
ENCLOSING_SCALE = 1.0e5


@njit(**_JIT)
def bowyer_watson(xy, order, scale):
    """Triangles ``(m, 3)`` (counter-clockwise, ids into ``xy`` ``(n, 2)``) of the Delaunay
    triangulation of the points, inserted one at a time in the order ``order``
    (Bowyer 1981, Watson 1981), and a status: 0, or negative when a predicate could
    not be decided (then the triangles are empty).

    The points go into a triangle enclosing them, its corners ``scale`` (as
    :data:`ENCLOSING_SCALE`) times the bounding box's largest side from its centre;
    each is located by a visibility walk from the last triangle made (:func:`_walk`),
    its cavity found by a search over neighbours of the triangles whose
    circumcircle strictly holds it (:func:`_cavity`, as :func:`delaunay_conflicts`),
    and the cavity replaced by the fan of triangles joining the point to the
    cavity's boundary.
    The triangles with a corner of the enclosing triangle are dropped at the end.
    A triangle whose in-circle determinant is within :data:`PREDICATE_TOL` × its
    permanent of 0 (the point on its circumcircle, up to round-off) stays out of the
    cavity. The status is −1 when a walk fails, −2 when the point is not decisively
    inside the circumcircle of the triangle the walk found (two points at one place,
    or a point on the hull between two others much closer than the hull is wide,
    where the circle through them and a corner of the enclosing triangle holds it
    by a relative margin of about their distance over the corner's: 2.8·10⁻⁵ apart
    in a box of side 2), −3 when a triangle of a fan is not counter-clockwise beyond
    the same bound and −4 when the fan does not close (a cavity that round-off made
    other than a star about the point). Where points are co-circular the
    triangulation is one of several, which the certificate rejects. The
    enclosing corners are far but not at infinity: a triangle
    whose circumcircle reaches one of them can be missing near the convex hull,
    so the result is a triangulation to check
    (:func:`curvimesh.triangulate.delaunay` certifies it)."""
    n = xy.shape[0]
    pts = np.empty((n + 3, 2))
    pts[:n] = xy
    xmin, ymin = np.inf, np.inf
    xmax, ymax = -np.inf, -np.inf
    for i in range(n):
        xmin, xmax = min(xmin, xy[i, 0]), max(xmax, xy[i, 0])
        ymin, ymax = min(ymin, xy[i, 1]), max(ymax, xy[i, 1])
    size = max(xmax - xmin, ymax - ymin)
    if not size > 0.0:
        size = 1.0
    r = scale * size
    cx, cy = 0.5 * (xmin + xmax), 0.5 * (ymin + ymax)
    for j in range(3):  # at 90°, 210° and 330°: counter-clockwise
        angle = 0.5 * math.pi + j * (2.0 * math.pi / 3.0)
        pts[n + j, 0] = cx + r * math.cos(angle)
        pts[n + j, 1] = cy + r * math.sin(angle)
    cap = 2 * (n + 3)
    corners = np.zeros((cap, 3), dtype=np.int64)
    nbr = np.full((cap, 3), -1, dtype=np.int64)
    alive = np.zeros(cap, dtype=np.bool_)
    corners[0, 0], corners[0, 1], corners[0, 2] = n, n + 1, n + 2
    alive[0] = True
    used = 1  # slots 0 .. used − 1 have been taken
    seen = np.full(cap, -1, dtype=np.int64)  # the point whose search visited a triangle
    inside = np.full(cap, -1, dtype=np.int64)  # the point whose cavity holds a triangle
    stack = np.empty(cap, dtype=np.int64)
    cavity = np.empty(cap, dtype=np.int64)
    start_at = np.full(n + 3, -1, dtype=np.int64)  # fan triangle (a, b, q) by a
    end_at = np.full(n + 3, -1, dtype=np.int64)  # fan triangle (a, b, q) by b
    fan_a = np.empty(cap, dtype=np.int64)  # the fan's sides a → b, the triangle o
    fan_b = np.empty(cap, dtype=np.int64)  # outside each (−1: none) and the side
    fan_o = np.empty(cap, dtype=np.int64)  # k of o that faces the cavity
    fan_k = np.empty(cap, dtype=np.int64)
    fail = np.zeros((0, 3), dtype=np.int64)
    t = 0
    for i in order:
        qx, qy = pts[i, 0], pts[i, 1]
        s = _walk(pts, corners, nbr, qx, qy, t)
        if s < 0:
            return fail, -1
        d, perm = in_circle_point(pts, corners[s, 0], corners[s, 1], corners[s, 2], qx, qy)
        if not d > PREDICATE_TOL * perm:
            return fail, -2
        nc = _cavity(pts, corners, nbr, s, qx, qy, i, seen, stack, cavity, False)
        for c in range(nc):
            inside[cavity[c]] = i
        # the fan: one triangle (a, b, q) on each side a → b of the cavity's boundary,
        # in the cavity's slots and two new ones (a disc of nc triangles has nc + 2 sides)
        n_new = 0
        for c in range(nc):
            s = cavity[c]
            for k in range(3):
                o = nbr[s, k]
                if o >= 0 and inside[o] == i:
                    continue
                a, b = corners[s, k], corners[s, (k + 1) % 3]
                d, perm = _orient(pts, a, b, qx, qy)
                if not d > PREDICATE_TOL * perm or n_new == cap:
                    return fail, -3
                fan_a[n_new], fan_b[n_new], fan_o[n_new], fan_k[n_new] = a, b, o, -1
                if o >= 0:
                    for j in range(3):
                        if nbr[o, j] == s:
                            fan_k[n_new] = j
                n_new += 1
        if n_new != nc + 2:  # a cavity that is not a disc
            return fail, -4
        for c in range(nc):
            alive[cavity[c]] = False
        for f in range(n_new):
            if f < nc:
                u = cavity[f]
            else:
                u = used
                used += 1
            alive[u] = True
            a, b = fan_a[f], fan_b[f]
            corners[u, 0], corners[u, 1], corners[u, 2] = a, b, i
            nbr[u, 0] = fan_o[f]
            if fan_o[f] >= 0:
                nbr[fan_o[f], fan_k[f]] = u
            start_at[a] = u
            end_at[b] = u
            stack[f] = u
        for f in range(n_new):
            u = stack[f]
            nbr[u, 1] = start_at[corners[u, 1]]  # (b, q) meets the fan triangle from b
            nbr[u, 2] = end_at[corners[u, 0]]  # (q, a) meets the one that ends at a
        for f in range(n_new):
            start_at[fan_a[f]] = -1
            end_at[fan_b[f]] = -1
        t = stack[n_new - 1]
    m = 0
    for u in range(used):
        if alive[u] and corners[u, 0] < n and corners[u, 1] < n and corners[u, 2] < n:
            m += 1
    out = np.empty((m, 3), dtype=np.int64)
    m = 0
    for u in range(used):
        if alive[u] and corners[u, 0] < n and corners[u, 1] < n and corners[u, 2] < n:
            out[m, 0], out[m, 1], out[m, 2] = corners[u, 0], corners[u, 1], corners[u, 2]
            m += 1
    return out, 0
