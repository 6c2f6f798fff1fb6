"""Reading and writing meshes, and atomic output files.

The only module that imports :mod:`meshio`. Meshes are written as Gmsh MSH
ASCII, version 2.2 (default) or 4.1, with physical tags 1 for the surface
and 11-14 for the boundary lines on the bottom, right, top and left sides of
the domain box (15, named "other", for boundary lines on none of them); a
point cloud is one ``vertex`` cell per node, physical tag 1 of dimension 0
named "points". Node ``i`` of a
:class:`~curvimesh.mesh.Mesh` is node tag ``i + 1`` in the file, so that a
mesh reads back exactly and the same mesh always gives the same bytes. MSH 2.2
is written here (the bytes meshio writes, formatted a block at a time), MSH 4.1
by meshio.

Every output goes through :func:`atomic_output`: a temporary file beside the
target, renamed over it only once complete. ``-`` as a path means stdin or
stdout.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import io
import os
import sys
import tempfile
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import meshio
import numpy as np
from numpy.typing import NDArray

from .bezier import jacobian_bezier
from .errors import InputError, MeshReadError
from .mesh import Mesh, boundary_sides, is_conforming, signed_areas

__all__ = [
    "FORMATS",
    "atomic_output",
    "atomic_write_bytes",
    "atomic_write_text",
    "check_writable",
    "read_mesh",
    "write_mesh",
]

PathLike = str | os.PathLike

SIDE_NAMES = ("bottom", "right", "top", "left")
SURFACE_TAG = 1
SIDE_TAGS = (11, 12, 13, 14)
OTHER_BOUNDARY_TAG = 15

# A triangle is degenerate when |2 A| <= _DEGENERATE * (longest edge)^2; collinear
# corners give a few ulps of L^2 from rounding.
_DEGENERATE = 1e-13
# Corner swap 1 <-> 2 of a clockwise triangle; for P2 the edge nodes follow:
# new edges 0-2, 2-1, 1-0 are the old edges 20, 12, 01.
_FLIP = {3: [0, 2, 1], 6: [0, 2, 1, 5, 4, 3]}


def _name(path: PathLike, stream: str) -> str:
    text = os.fspath(path)
    return f"<{stream}>" if text == "-" else text


def _is_dash(path: PathLike) -> bool:
    return os.fspath(path) == "-"


# --------------------------------------------------------------------------- output


@functools.cache
def _umask() -> int:
    # /proc avoids the process-wide window of os.umask(0) on Linux.
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_output(path: PathLike, suffix: str | None = None) -> Iterator[str]:
    """Yield a temporary path to write; on success it replaces ``path``.

    The temporary file lies in the target's directory and ends in ``suffix``
    (default: the target's suffix, so that tools choosing a format by
    extension, such as ``savefig``, work). On success it is fsynced and
    renamed over ``path``; on any exception, ``KeyboardInterrupt`` included,
    it is removed and the target is left untouched. ``-`` writes the finished
    file to ``sys.stdout.buffer``. An ``OSError`` becomes :class:`InputError`
    ``"<path>: cannot write: <reason>"``.
    """
    name = _name(path, "stdout")
    target = Path(os.fspath(path))
    if suffix is None:
        suffix = "" if _is_dash(path) else target.suffix
    directory = None if _is_dash(path) else target.parent
    prefix = "curvimesh-stdout-" if directory is None else f".{target.name}."
    try:
        with tempfile.NamedTemporaryFile(
            dir=directory, prefix=prefix, suffix=suffix, delete=False
        ) as handle:
            tmp = handle.name
    except OSError as exc:
        raise InputError(f"{name}: cannot write: {exc.strerror or exc}") from exc
    try:
        yield tmp
        if directory is None:
            with open(tmp, "rb") as src:
                while chunk := src.read(1 << 20):
                    sys.stdout.buffer.write(chunk)
            sys.stdout.buffer.flush()
        else:
            mode = target.stat().st_mode & 0o7777 if target.is_file() else 0o666 & ~_umask()
            os.chmod(tmp, mode)
            fd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
            os.replace(tmp, target)
    except OSError as exc:
        raise InputError(f"{name}: cannot write: {exc.strerror or exc}") from exc
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)


def check_writable(path: PathLike) -> None:
    """Fail early, before any work, if ``path`` cannot be an output file.

    Raises :class:`InputError` ``"<path>: cannot write: <reason>"`` when the
    parent directory is missing or is not a directory, or ``path`` is a
    directory. ``-`` (stdout) is always fine. A full disk or a read-only
    directory is still only found when writing (:func:`atomic_output`).
    """
    if _is_dash(path):
        return
    target = Path(os.fspath(path))
    parent = target.parent
    if target.is_dir():
        reason = errno.EISDIR
    elif not parent.exists():
        reason = errno.ENOENT
    elif not parent.is_dir():
        reason = errno.ENOTDIR
    else:
        return
    raise InputError(f"{os.fspath(path)}: cannot write: {os.strerror(reason)}")


def atomic_write_bytes(path: PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` (``-``: stdout) atomically, see :func:`atomic_output`."""
    with atomic_output(path) as tmp, open(tmp, "wb") as handle:
        handle.write(data)


def atomic_write_text(path: PathLike, text: str, encoding: str = "utf-8") -> None:
    """Write ``text`` to ``path`` (``-``: stdout) atomically, see :func:`atomic_output`."""
    atomic_write_bytes(path, text.encode(encoding))


# --------------------------------------------------------------------------- writing


@dataclass(frozen=True, eq=False)
class _Group:
    """One physical group of cells, on one Gmsh entity of its own."""

    name: str
    dim: int
    physical: int
    entity: int
    cell_type: str
    cells: NDArray[np.int64]


def _groups(mesh: Mesh) -> list[_Group]:
    """The cell blocks to write: surface then sides, or the vertices of a point cloud."""
    if len(mesh.triangles) == 0:
        vertices = np.arange(len(mesh.points), dtype=np.int64)[:, None]
        return [_Group("points", 0, 1, 1, "vertex", vertices)]
    p2 = mesh.order == 2
    groups = [
        _Group("surface", 2, SURFACE_TAG, 1, "triangle6" if p2 else "triangle", mesh.triangles)
    ]
    lines = mesh.boundary_lines
    sides = boundary_sides(mesh)
    named = [*zip(SIDE_NAMES, SIDE_TAGS, strict=True), ("other", OTHER_BOUNDARY_TAG)]
    for side, (name, physical) in zip([0, 1, 2, 3, -1], named, strict=True):
        cells = lines[sides == side]
        if len(cells):
            entity = physical - SIDE_TAGS[0] + 1
            groups.append(_Group(name, 1, physical, entity, "line3" if p2 else "line", cells))
    return groups


def _to_meshio(mesh: Mesh, groups: list[_Group]) -> meshio.Mesh:
    # Every node on the entity of the top group: meshio's MSH 4.1 writer emits
    # one node block per entity and its reader stores nodes in file order, so
    # a single block is what keeps node i at index i.
    top = groups[0]
    dim_tags = np.tile(np.array([top.dim, top.entity]), (len(mesh.points), 1))
    return meshio.Mesh(
        np.asarray(mesh.points),
        [(g.cell_type, np.asarray(g.cells)) for g in groups],
        point_data={"gmsh:dim_tags": dim_tags},
        cell_data={
            "gmsh:physical": [np.full(len(g.cells), g.physical) for g in groups],
            "gmsh:geometrical": [np.full(len(g.cells), g.entity) for g in groups],
        },
        field_data={g.name: np.array([g.physical, g.dim]) for g in groups},
    )


#: Gmsh's element type numbers of the cells :func:`_groups` makes (for :func:`_write_gmsh22`).
_GMSH_TYPES = {"vertex": 15, "line": 1, "triangle": 2, "line3": 8, "triangle6": 9}


def _write_gmsh22(path: str, mesh: Mesh) -> None:
    """Gmsh MSH 2.2 ASCII: the bytes of ``meshio.write(path, _to_meshio(...),
    file_format="gmsh22", binary=False)`` (its physical names sorted by dimension and
    tag, nodes with 16 digits after the point, every element with its physical and
    geometrical tags), with its loops over nodes and elements done a block at a time:
    a 38,050-vertex P2 mesh takes 0.57 s, 1.09 s in meshio's per-line formatting."""
    groups = _groups(mesh)
    names = sorted((g.dim, g.physical, g.name) for g in groups)
    pts = np.asarray(mesh.points, dtype=float).reshape(-1, 2)
    with open(path, "wb") as fh:
        fh.write(b"$MeshFormat\n2.2 0 8\n$EndMeshFormat\n")
        fh.write(f"$PhysicalNames\n{len(names)}\n".encode())
        fh.write("".join(f'{d} {p} "{n}"\n' for d, p, n in names).encode())
        fh.write(b"$EndPhysicalNames\n")
        fh.write(f"$Nodes\n{len(pts)}\n".encode())
        rows = zip(range(1, len(pts) + 1), pts[:, 0].tolist(), pts[:, 1].tolist(), strict=True)
        fh.write(
            "".join(f"{k} {x:.16e} {y:.16e} 0.0000000000000000e+00\n" for k, x, y in rows).encode()
        )
        fh.write(b"$EndNodes\n")
        fh.write(f"$Elements\n{sum(len(g.cells) for g in groups)}\n".encode())
        first = 1
        for g in groups:
            head = f"{_GMSH_TYPES[g.cell_type]} 2 {g.physical} {g.entity}"
            nodes = (np.asarray(g.cells, dtype=np.int64) + 1).tolist()
            ids = range(first, first + len(nodes))
            fh.write(
                "".join(
                    f"{i} {head} {' '.join(map(str, c))}\n" for i, c in zip(ids, nodes, strict=True)
                ).encode()
            )
            first += len(nodes)
        fh.write(b"$EndElements\n")


def _entities_section(mesh: Mesh, groups: list[_Group]) -> bytes:
    """The ``$Entities`` section of MSH 4.1 for ``groups``.

    meshio writes entities only for the node blocks (here the one top
    entity), so elements on the side curves would name entities Gmsh does not
    know ("Unknown entity 1 of dimension 1"). This lists every group's entity
    with its bounding box and physical tag; the surface is bounded by the curves.
    """

    def box(ids: NDArray[np.int64]) -> str:
        pts = mesh.points[np.unique(ids)]
        if len(pts) == 0:
            pts = np.zeros((1, 2))
        (x0, y0), (x1, y1) = pts.min(axis=0).tolist(), pts.max(axis=0).tolist()
        return f"{x0!r} {y0!r} 0 {x1!r} {y1!r} 0"

    counts = [sum(g.dim == d for g in groups) for d in range(4)]
    rows = [" ".join(map(str, counts))]
    curves = [g.entity for g in groups if g.dim == 1]
    for g in sorted(groups, key=lambda g: (g.dim, g.entity)):
        if g.dim == 0:
            x, y = (mesh.points.min(axis=0) if len(mesh.points) else np.zeros(2)).tolist()
            rows.append(f"{g.entity} {x!r} {y!r} 0 1 {g.physical}")
        elif g.dim == 1:
            rows.append(f"{g.entity} {box(g.cells)} 1 {g.physical} 0")
        else:
            bounding = " ".join(map(str, [len(curves), *curves]))
            rows.append(f"{g.entity} {box(g.cells)} 1 {g.physical} {bounding}")
    return ("$Entities\n" + "\n".join(rows) + "\n$EndEntities\n").encode()


def _write_gmsh41(path: str, mesh: Mesh) -> None:
    """Gmsh MSH 4.1 ASCII, with the ``$Entities`` section completed."""
    groups = _groups(mesh)
    meshio.write(path, _to_meshio(mesh, groups), file_format="gmsh", binary=False)
    data = Path(path).read_bytes()
    start = data.index(b"$Entities\n")
    end_tag = b"$EndEntities\n"
    end = data.index(end_tag, start) + len(end_tag)
    Path(path).write_bytes(data[:start] + _entities_section(mesh, groups) + data[end:])


FORMATS: dict[str, Callable[[str, Mesh], None]] = {
    "gmsh22": _write_gmsh22,
    "gmsh41": _write_gmsh41,
}
"""Mesh file formats by name: each writes a :class:`Mesh` to a file path."""


def write_mesh(path: PathLike, mesh: Mesh, *, fmt: str = "gmsh22") -> None:
    """Write ``mesh`` to ``path`` (``-``: stdout) atomically in format ``fmt`` of :data:`FORMATS`.

    P2 meshes are written as ``triangle6`` and ``line3`` cells, P1 meshes as
    ``triangle`` and ``line``, point clouds as one ``vertex`` cell per node.
    The sides are those of ``mesh.box``, else of the bounding box of the points.
    Raises :class:`InputError` for an unknown format or an unwritable path.
    """
    try:
        writer = FORMATS[fmt]
    except KeyError:
        raise InputError(f"unknown mesh format {fmt!r}; choose from {', '.join(FORMATS)}") from None
    with atomic_output(path, suffix=".msh") as tmp:
        writer(tmp, mesh)


# --------------------------------------------------------------------------- reading


def _is_msh(head: bytes) -> bool:
    return head.lstrip().startswith((b"$MeshFormat", b"$Comments"))


def _check_msh_tail(tail: bytes, name: str) -> None:
    """A complete MSH file ends with the ``$End...`` line of its last section."""
    last = tail.rstrip().rsplit(b"\n", 1)[-1].strip()
    if not (last.startswith(b"$End") and last[4:].isalpha()):
        raise MeshReadError(f"{name}: truncated Gmsh MSH file (it does not end with an $End line)")


def _one_line(what: object, limit: int = 160) -> str:
    text = " ".join(str(what).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _meshio_read(path: PathLike, file_format: str | None, name: str) -> meshio.Mesh:
    """``meshio.read`` with every failure turned into a one-line :class:`MeshReadError`.

    On a reader error ``meshio.read`` prints the message to *stdout* and calls
    ``sys.exit(1)``; both are caught here, so nothing reaches stdout (which
    may be a pipeline) and no ``SystemExit`` escapes.
    """
    out, err = io.StringIO(), io.StringIO()
    try:
        with (
            warnings.catch_warnings(),
            contextlib.redirect_stdout(out),
            contextlib.redirect_stderr(err),
        ):
            warnings.simplefilter("ignore")
            raw = meshio.read(path, file_format=file_format)
    except (Exception, SystemExit) as exc:
        printed = out.getvalue().strip().splitlines()
        detail = _one_line(exc if isinstance(exc, Exception) else "") or (
            _one_line(printed[0]) if printed else ""
        )
        if "deduce file format" in detail:
            what = f"unknown mesh format {Path(os.fspath(path)).suffix!r} (expected Gmsh .msh)"
        elif "zero-size array" in detail:  # meshio's Gmsh readers on "$Nodes 0"
            what = "empty mesh (no nodes)"
        else:
            kind = "Gmsh MSH" if file_format == "gmsh" else "mesh"
            what = f"invalid {kind} file" + (f" ({detail})" if detail else "")
        raise MeshReadError(f"{name}: {what}") from exc
    # meshio reports oddities of a file it could read on stderr: an unclosed
    # section is a truncated file, the rest is passed on.
    unclosed = [line for line in err.getvalue().splitlines() if "not closed by" in line]
    if unclosed:
        detail = _one_line(unclosed[0].removeprefix("Warning:"))
        raise MeshReadError(f"{name}: truncated or malformed file ({detail})")
    sys.stderr.write(err.getvalue())
    if file_format == "gmsh" and not any(len(block) for block in raw.cells):
        # meshio's MSH 2.2 reader takes a file cut after $EndNodes for a mesh
        # without elements; Gmsh always writes some.
        raise MeshReadError(f"{name}: no elements (truncated Gmsh MSH file?)")
    return raw


def _from_meshio(raw: meshio.Mesh, name: str, box: tuple | None) -> Mesh:
    """Check a mesh read by meshio and turn it into a counter-clockwise :class:`Mesh`."""

    def fail(what: str) -> MeshReadError:
        return MeshReadError(f"{name}: {what}")

    points = np.asarray(raw.points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] not in (2, 3):
        raise fail(f"node coordinates have shape {points.shape}")
    if not np.all(np.isfinite(points)):
        raise fail("node coordinates are not all finite")
    xy = points[:, :2]
    if points.shape[1] == 3 and len(points):
        scale = max(1.0, float(np.abs(xy).max()))
        if np.abs(points[:, 2]).max() > 1e-9 * scale:
            raise fail("not a planar mesh (some node has z != 0)")

    blocks: dict[str, list[NDArray]] = {"triangle": [], "triangle6": []}
    for block in raw.cells:
        if block.type in blocks:
            blocks[block.type].append(np.asarray(block.data, dtype=np.int64))
        elif block.dim >= 2:
            raise fail(f"unsupported cell type {block.type!r} (expected triangle or triangle6)")
    if blocks["triangle"] and blocks["triangle6"]:
        raise fail("mixes triangle and triangle6 cells")
    width = 6 if blocks["triangle6"] else 3
    parts = blocks["triangle6"] or blocks["triangle"]
    tris = np.concatenate(parts).reshape(-1, width) if parts else np.zeros((0, 3), np.int64)
    if len(tris) == 0 and len(points) == 0:
        raise fail("no nodes and no triangles")
    if tris.size and (tris.min() < 0 or tris.max() >= len(points)):
        raise fail("a triangle refers to an undefined node")

    if width == 6:
        # signed area of the curved triangle: ∫J over the reference triangle is
        # half the mean of J's six Bezier coefficients. A valid curved triangle
        # may have clockwise corners, so orientation is judged on this.
        areas = jacobian_bezier(xy[tris]).mean(axis=1) / 2.0 if len(tris) else np.zeros(0)
    else:
        areas = signed_areas(xy, tris)
    corners = xy[tris[:, :3]]
    longest = np.max(np.sum((corners - np.roll(corners, 1, axis=1)) ** 2, axis=2), axis=1)
    degenerate = np.flatnonzero(2.0 * np.abs(areas) <= _DEGENERATE * longest)
    if degenerate.size:
        raise fail(
            f"{degenerate.size} degenerate (zero-area) triangle(s), "
            f"the first is triangle {degenerate[0]} of {len(tris)}"
        )
    clockwise = areas < 0
    tris[clockwise] = tris[clockwise][:, _FLIP[width]]
    _check_folds(tris, len(xy), fail)

    if box is None and len(xy):
        (x0, y0), (x1, y1) = xy.min(axis=0), xy.max(axis=0)
        box = (float(x0), float(y0), float(x1), float(y1))
    else:
        _check_inside(xy, box, fail)
    mesh = Mesh(xy, tris, box)
    if width == 6 and not is_conforming(mesh):
        raise fail("neighbouring triangle6 cells do not share their edge nodes")
    return mesh


def _check_folds(tris: NDArray[np.int64], n: int, fail: Callable[[str], MeshReadError]) -> None:
    """Reject meshes that fold over or are not conforming, once every triangle is CCW.

    In a conforming counter-clockwise mesh an edge is held by at most two
    triangles, which run along it in opposite directions. Two that run the
    same way overlap: one of them was inverted in the file (a folded mesh).
    """
    corners = tris[:, :3]
    a, b = corners.ravel(), corners[:, [1, 2, 0]].ravel()
    directed = a * max(n, 1) + b
    keys, counts = np.unique(directed, return_counts=True)
    if np.any(counts > 1):
        key = keys[np.argmax(counts > 1)]
        t = np.flatnonzero(directed == key) // 3
        raise fail(
            f"triangles {t[0]} and {t[1]} overlap across their edge ({key // n}, {key % n}): "
            "an inverted triangle, or not a conforming mesh (triangles count from 0)"
        )
    undirected = np.minimum(a, b) * max(n, 1) + np.maximum(a, b)
    keys, counts = np.unique(undirected, return_counts=True)
    if np.any(counts > 2):
        i = np.argmax(counts > 2)
        raise fail(
            f"edge ({keys[i] // n}, {keys[i] % n}) is held by {counts[i]} triangles "
            "(not a conforming mesh)"
        )


def _check_inside(
    xy: NDArray[np.float64],
    box: tuple[float, float, float, float],
    fail: Callable[[str], MeshReadError],
) -> None:
    """Every node must lie in the box (the metric's domain), to 1e-9 of its size."""
    x0, y0, x1, y1 = box
    tol = 1e-9 * max(x1 - x0, y1 - y0)
    x, y = xy[:, 0], xy[:, 1]
    out = (x < x0 - tol) | (x > x1 + tol) | (y < y0 - tol) | (y > y1 + tol)
    if np.any(out):
        i = int(np.argmax(out))
        raise fail(
            f"node {i} at ({x[i]:.6g}, {y[i]:.6g}) is outside the domain box "
            f"[{x0:g}, {x1:g}] x [{y0:g}, {y1:g}] of the metric "
            f"({np.count_nonzero(out)} of {len(xy)} nodes outside; nodes count from 0)"
        )


def read_mesh(path: PathLike, *, box: tuple[float, float, float, float] | None = None) -> Mesh:
    """Read a triangle mesh or a point cloud; ``-`` reads stdin (MSH only).

    Gmsh MSH files of any version meshio reads (2.2, 4.0, 4.1, ASCII or
    binary) are recognised by their header; other formats by their
    extension. ``triangle`` or ``triangle6`` cells make the mesh; ``vertex``
    and line cells are ignored; without triangles all nodes make a point
    cloud. z must be 0. Clockwise triangles are flipped. ``box`` defaults to
    the bounding box of the nodes. Every failure raises :class:`MeshReadError`
    ``"<path>: <what is wrong>"``.
    """
    if _is_dash(path):
        name = "<stdin>"
        data = sys.stdin.buffer.read()
        if not data or data.isspace():
            raise MeshReadError(f"{name}: empty input")
        if not _is_msh(data[:256]):
            raise MeshReadError(f"{name}: not a Gmsh MSH file (only MSH is read from stdin)")
        _check_msh_tail(data[-256:], name)
        with tempfile.TemporaryDirectory(prefix="curvimesh-") as tmpdir:
            tmp = Path(tmpdir) / "stdin.msh"
            tmp.write_bytes(data)
            raw = _meshio_read(tmp, "gmsh", name)
        return _from_meshio(raw, name, box)

    name = os.fspath(path)
    try:
        with open(path, "rb") as handle:
            head = handle.read(256)
            handle.seek(max(0, handle.seek(0, os.SEEK_END) - 256))
            tail = handle.read()
    except OSError as exc:
        raise MeshReadError(f"{name}: cannot read: {exc.strerror or exc}") from exc
    if not head.strip():
        raise MeshReadError(f"{name}: empty file")
    if _is_msh(head):
        _check_msh_tail(tail, name)
        file_format = "gmsh"
    elif Path(name).suffix.lower() == ".msh":
        raise MeshReadError(f"{name}: not a Gmsh MSH file (no $MeshFormat header)")
    else:
        file_format = None
    return _from_meshio(_meshio_read(path, file_format, name), name, box)
