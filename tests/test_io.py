"""Tests of curvimesh.io: round trips through meshio and Gmsh, atomic output, bad input."""

from __future__ import annotations

import ast
import io
import os
import stat
import sys
import types
from pathlib import Path

import gmsh
import meshio
import numpy as np
import pytest
from scipy.spatial import Delaunay

import curvimesh.io as cio
from curvimesh.errors import InputError, MeshReadError
from curvimesh.io import (
    FORMATS,
    atomic_output,
    atomic_write_bytes,
    atomic_write_text,
    read_mesh,
    write_mesh,
)
from curvimesh.mesh import Mesh, boundary_sides, is_conforming, signed_areas, to_p2_straight

# ---------------------------------------------------------------- meshes


def p1_mesh() -> Mesh:
    """A Delaunay mesh of the unit square with nodes on every side."""
    rng = np.random.default_rng(7)
    t = np.linspace(0.0, 1.0, 5)[1:-1]
    sides = [np.column_stack([t, 0 * t]), np.column_stack([1 + 0 * t, t])]
    sides += [np.column_stack([t, 1 + 0 * t]), np.column_stack([0 * t, t])]
    corners = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]
    points = np.vstack([rng.uniform(0.1, 0.9, (40, 2)), corners, *sides])
    tris = Delaunay(points).simplices
    cw = signed_areas(points, tris) < 0
    tris[cw] = tris[cw][:, [0, 2, 1]]
    return Mesh(points, tris, box=(0.0, 0.0, 1.0, 1.0))


def curved_p2_mesh() -> Mesh:
    """A valid curved P2 mesh: a straight one under a smooth map fixing the box sides."""
    p2 = to_p2_straight(p1_mesh())
    x, y = p2.points.T
    bump = 0.02 * np.sin(np.pi * x) * np.sin(np.pi * y)
    return Mesh(np.column_stack([x + bump, y + bump]), p2.triangles, box=p2.box)


def point_cloud() -> Mesh:
    points = np.random.default_rng(11).random((25, 2))
    return Mesh(points, np.zeros((0, 3), dtype=np.int64), box=(0.0, 0.0, 1.0, 1.0))


MESHES = {"p1": p1_mesh, "p2": curved_p2_mesh, "cloud": point_cloud}


@pytest.fixture(params=sorted(MESHES))
def mesh(request) -> Mesh:
    return MESHES[request.param]()


@pytest.fixture(params=sorted(FORMATS))
def fmt(request) -> str:
    return request.param


def assert_same_mesh(a: Mesh, b: Mesh) -> None:
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.triangles, b.triangles)


# ---------------------------------------------------------------- round trips


def test_round_trip_with_our_reader(tmp_path, mesh, fmt):
    path = tmp_path / "m.msh"
    write_mesh(path, mesh, fmt=fmt)
    back = read_mesh(path)
    assert_same_mesh(back, mesh)
    # The box read back is the bounding box of the nodes.
    assert back.box == (*mesh.points.min(axis=0), *mesh.points.max(axis=0))


def test_msh22_is_the_file_meshio_writes_byte_for_byte(tmp_path, mesh):
    # our MSH 2.2 writer formats a block at a time what meshio's formats line by line
    ours, theirs = tmp_path / "ours.msh", tmp_path / "theirs.msh"
    write_mesh(ours, mesh, fmt="gmsh22")
    meshio.write(
        theirs, cio._to_meshio(mesh, cio._groups(mesh)), file_format="gmsh22", binary=False
    )
    assert ours.read_bytes() == theirs.read_bytes()
    assert b"$PhysicalNames" in ours.read_bytes()


def test_round_trip_with_meshio(tmp_path, mesh, fmt):
    path = tmp_path / "m.msh"
    write_mesh(path, mesh, fmt=fmt)
    raw = meshio.read(path)
    np.testing.assert_array_equal(raw.points[:, :2], mesh.points)
    np.testing.assert_array_equal(raw.points[:, 2], 0.0)
    blocks = {}
    tags = {}
    for block, physical in zip(raw.cells, raw.cell_data["gmsh:physical"], strict=True):
        blocks.setdefault(block.type, []).append(block.data)
        tags.setdefault(block.type, []).append(physical)
    if len(mesh.triangles) == 0:
        assert set(blocks) == {"vertex"}
        np.testing.assert_array_equal(np.concatenate(blocks["vertex"]).ravel(), np.arange(25))
        return
    tri_type, line_type = ("triangle6", "line3") if mesh.order == 2 else ("triangle", "line")
    assert set(blocks) == {tri_type, line_type}
    np.testing.assert_array_equal(np.concatenate(blocks[tri_type]), mesh.triangles)
    np.testing.assert_array_equal(np.concatenate(tags[tri_type]), 1)
    # Boundary lines: each side's lines carry its physical tag 11..14.
    lines = np.concatenate(blocks[line_type])
    line_tags = np.concatenate(tags[line_type])
    sides = boundary_sides(mesh)
    expected = {
        tuple(line): 11 + side
        for line, side in zip(mesh.boundary_lines.tolist(), sides.tolist(), strict=True)
    }
    assert dict(zip(map(tuple, lines.tolist()), line_tags.tolist(), strict=True)) == expected
    assert {name: int(v[0]) for name, v in raw.field_data.items()} == {
        "surface": 1,
        "bottom": 11,
        "right": 12,
        "top": 13,
        "left": 14,
    }


@pytest.fixture
def gmsh_session():
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        yield gmsh
    finally:
        gmsh.finalize()


def test_gmsh_opens_what_we_write(tmp_path, mesh, fmt, gmsh_session):
    path = tmp_path / "m.msh"
    write_mesh(path, mesh, fmt=fmt)
    gmsh.open(str(path))
    tags, coords, _ = gmsh.model.mesh.getNodes()
    order = np.argsort(tags)
    np.testing.assert_array_equal(tags[order], np.arange(1, len(mesh.points) + 1))
    np.testing.assert_array_equal(coords.reshape(-1, 3)[order, :2], mesh.points)
    if len(mesh.triangles) == 0:
        types_, elements, _ = gmsh.model.mesh.getElements(0)
        assert types_.tolist() == [15] and len(elements[0]) == len(mesh.points)
        return
    types_, elements, nodes = gmsh.model.mesh.getElements(2)
    assert types_.tolist() == [9 if mesh.order == 2 else 2]
    assert len(elements[0]) == len(mesh.triangles)
    np.testing.assert_array_equal(nodes[0].reshape(len(mesh.triangles), -1) - 1, mesh.triangles)
    _, lines, _ = gmsh.model.mesh.getElements(1)
    assert len(lines[0]) == len(mesh.boundary_edges)
    groups = {gmsh.model.getPhysicalName(d, t): (d, t) for d, t in gmsh.model.getPhysicalGroups()}
    assert groups == {
        "surface": (2, 1),
        "bottom": (1, 11),
        "right": (1, 12),
        "top": (1, 13),
        "left": (1, 14),
    }
    min_det = gmsh.model.mesh.getElementQualities(elements[0], "minDetJac")
    assert np.all(min_det > 0)


def test_gmsh_sees_an_inverted_p2_triangle(tmp_path, fmt, gmsh_session):
    # The check above has teeth: pull one interior edge node across its triangle.
    mesh = curved_p2_mesh()
    e = int(np.flatnonzero(mesh.edge_tris[:, 1] >= 0)[0])
    points = np.array(mesh.points)
    a, b = mesh.edges[e]
    mid = mesh.edge_mid[e]
    normal = np.array([[0, -1], [1, 0]]) @ (points[b] - points[a])
    points[mid] += 3.0 * normal
    write_mesh(tmp_path / "bad.msh", Mesh(points, mesh.triangles), fmt=fmt)
    gmsh.open(str(tmp_path / "bad.msh"))
    _, elements, _ = gmsh.model.mesh.getElements(2)
    min_det = gmsh.model.mesh.getElementQualities(elements[0], "minDetJac")
    assert np.sum(min_det < 0) >= 1


def test_reads_files_written_by_gmsh(tmp_path, gmsh_session):
    gmsh.model.occ.addRectangle(0, 0, 0, 2, 1)
    gmsh.model.occ.synchronize()
    gmsh.option.setNumber("Mesh.MeshSizeMax", 0.3)
    gmsh.model.mesh.generate(2)
    gmsh.model.mesh.setOrder(2)
    n_tris = len(gmsh.model.mesh.getElements(2)[1][0])
    for version in (2.2, 4.1):
        for binary in (0, 1):
            gmsh.option.setNumber("Mesh.MshFileVersion", version)
            gmsh.option.setNumber("Mesh.Binary", binary)
            path = tmp_path / f"g{version}-{binary}.msh"
            gmsh.write(str(path))
            mesh = read_mesh(path)
            assert mesh.order == 2
            assert len(mesh.triangles) == n_tris
            assert is_conforming(mesh)
            assert np.all(signed_areas(mesh.points, mesh.triangles) > 0)
            assert mesh.box == pytest.approx((0.0, 0.0, 2.0, 1.0))


def test_reads_other_formats_by_extension(tmp_path):
    mesh = p1_mesh()
    path = tmp_path / "m.vtu"
    meshio.write(path, meshio.Mesh(mesh.points, [("triangle", mesh.triangles)]))
    assert_same_mesh(read_mesh(path), mesh)


def test_explicit_box(tmp_path):
    path = tmp_path / "m.msh"
    write_mesh(path, p1_mesh())
    assert read_mesh(path, box=(-1, -1, 2, 2)).box == (-1.0, -1.0, 2.0, 2.0)


def test_deterministic_bytes(tmp_path, mesh, fmt):
    write_mesh(tmp_path / "a.msh", mesh, fmt=fmt)
    write_mesh(tmp_path / "b.msh", Mesh(np.array(mesh.points), np.array(mesh.triangles)), fmt=fmt)
    assert (tmp_path / "a.msh").read_bytes() == (tmp_path / "b.msh").read_bytes()


def test_boundary_off_the_box_sides(tmp_path, fmt, gmsh_session):
    # An L-shaped domain: the re-entrant edges are boundary lines on no side.
    points = [[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2], [1, 0], [0, 1]]
    tris = [[0, 6, 3], [0, 3, 7], [6, 1, 2], [6, 2, 3], [7, 3, 4], [7, 4, 5]]
    mesh = Mesh(points, tris)
    write_mesh(tmp_path / "l.msh", mesh, fmt=fmt)
    raw = meshio.read(tmp_path / "l.msh")
    physical = np.concatenate(raw.cell_data["gmsh:physical"][1:])
    assert sorted(physical.tolist()) == [11, 11, 12, 13, 14, 14, 15, 15]
    assert_same_mesh(read_mesh(tmp_path / "l.msh"), mesh)
    gmsh.open(str(tmp_path / "l.msh"))
    assert len(gmsh.model.mesh.getElements(1)[1][0]) == 8


# ---------------------------------------------------------------- stdin / stdout


def test_read_stdin(tmp_path, monkeypatch, fmt):
    mesh = curved_p2_mesh()
    write_mesh(tmp_path / "m.msh", mesh, fmt=fmt)
    stdin = types.SimpleNamespace(buffer=io.BytesIO((tmp_path / "m.msh").read_bytes()))
    monkeypatch.setattr(sys, "stdin", stdin)
    assert_same_mesh(read_mesh("-"), mesh)


@pytest.mark.parametrize(
    ("data", "what"), [(b"", "empty input"), (b"garbage\n", "not a Gmsh MSH file")]
)
def test_read_bad_stdin(monkeypatch, data, what):
    monkeypatch.setattr(sys, "stdin", types.SimpleNamespace(buffer=io.BytesIO(data)))
    with pytest.raises(MeshReadError, match=f"^<stdin>: {what}"):
        read_mesh("-")


def test_write_stdout(tmp_path, monkeypatch, fmt):
    mesh = p1_mesh()
    write_mesh(tmp_path / "m.msh", mesh, fmt=fmt)
    stdout = types.SimpleNamespace(buffer=io.BytesIO())
    monkeypatch.setattr(sys, "stdout", stdout)
    write_mesh("-", mesh, fmt=fmt)
    assert stdout.buffer.getvalue() == (tmp_path / "m.msh").read_bytes()


# ---------------------------------------------------------------- atomic output


def test_write_into_missing_directory(tmp_path):
    target = tmp_path / "missing" / "m.msh"
    with pytest.raises(InputError, match=r"m\.msh: cannot write: "):
        write_mesh(target, p1_mesh())
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root ignores modes")
def test_write_into_read_only_directory(tmp_path):
    directory = tmp_path / "ro"
    directory.mkdir()
    directory.chmod(0o500)
    try:
        with pytest.raises(InputError, match="cannot write: Permission denied"):
            write_mesh(directory / "m.msh", p1_mesh())
        assert list(directory.iterdir()) == []
    finally:
        directory.chmod(0o700)


def test_write_over_a_directory(tmp_path):
    (tmp_path / "d.msh").mkdir()
    with pytest.raises(InputError, match="cannot write"):
        write_mesh(tmp_path / "d.msh", p1_mesh())
    assert [p.name for p in tmp_path.iterdir()] == ["d.msh"]


@pytest.mark.parametrize("error", [RuntimeError("disk on fire"), KeyboardInterrupt()])
def test_failed_write_leaves_target_untouched(tmp_path, monkeypatch, fmt, error):
    target = tmp_path / "m.msh"
    target.write_bytes(b"old contents\n")
    seen = []

    def failing_write(filename, *args, **kwargs):
        seen.append(os.fspath(filename))
        with open(filename, "wb") as handle:
            handle.write(b"$MeshFormat\n2.2 0 8\n")
        raise error

    # the format's writer fails half way (ours for MSH 2.2, meshio's for 4.1)
    monkeypatch.setitem(cio.FORMATS, fmt, failing_write)
    with pytest.raises(type(error)):
        write_mesh(target, curved_p2_mesh(), fmt=fmt)
    assert os.path.dirname(seen[0]) == str(tmp_path)  # the temp file was beside the target
    assert target.read_bytes() == b"old contents\n"
    assert [p.name for p in tmp_path.iterdir()] == ["m.msh"]


def test_os_error_midway_becomes_input_error(tmp_path, monkeypatch):
    def full_disk(filename, *args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setitem(cio.FORMATS, "gmsh22", full_disk)
    with pytest.raises(InputError, match=r"^.*m\.msh: cannot write: No space left on device$"):
        write_mesh(tmp_path / "m.msh", p1_mesh())
    assert list(tmp_path.iterdir()) == []


def test_atomic_helpers(tmp_path, monkeypatch):
    atomic_write_text(tmp_path / "a.json", '{"x": 1}\n')
    assert (tmp_path / "a.json").read_text() == '{"x": 1}\n'
    atomic_write_bytes(tmp_path / "a.json", b"{}")
    assert (tmp_path / "a.json").read_bytes() == b"{}"
    with atomic_output(tmp_path / "fig.png") as tmp:
        assert tmp.endswith(".png") and os.path.dirname(tmp) == str(tmp_path)
        with open(tmp, "wb") as handle:
            handle.write(b"png")
        assert not (tmp_path / "fig.png").exists()
    assert (tmp_path / "fig.png").read_bytes() == b"png"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "fig.png"]
    stdout = types.SimpleNamespace(buffer=io.BytesIO())
    monkeypatch.setattr(sys, "stdout", stdout)
    atomic_write_text("-", "hello\n")
    assert stdout.buffer.getvalue() == b"hello\n"


def test_file_modes(tmp_path):
    umask = os.umask(0o022)
    os.umask(umask)
    atomic_write_bytes(tmp_path / "new", b"x")
    assert stat.S_IMODE((tmp_path / "new").stat().st_mode) == 0o666 & ~umask
    (tmp_path / "old").write_bytes(b"x")
    (tmp_path / "old").chmod(0o640)
    atomic_write_bytes(tmp_path / "old", b"y")
    assert stat.S_IMODE((tmp_path / "old").stat().st_mode) == 0o640


def test_unknown_format(tmp_path):
    with pytest.raises(InputError, match="unknown mesh format 'stl'"):
        write_mesh(tmp_path / "m.msh", p1_mesh(), fmt="stl")
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------- reading bad input


def test_clockwise_triangles_are_flipped(tmp_path):
    p2 = curved_p2_mesh()
    flip = np.array(p2.triangles)
    flip[::2] = flip[::2][:, [0, 2, 1, 5, 4, 3]]
    for tris in (flip, flip[:, :3]):
        path = tmp_path / f"cw{tris.shape[1]}.msh"
        cell_type = "triangle6" if tris.shape[1] == 6 else "triangle"
        meshio.write(path, meshio.Mesh(p2.points, [(cell_type, tris)]), "gmsh22", binary=False)
        mesh = read_mesh(path)
        assert np.all(signed_areas(mesh.points, mesh.triangles) > 0)
        np.testing.assert_array_equal(mesh.triangles, p2.triangles[:, : tris.shape[1]])
        assert is_conforming(mesh)


def write_meshio(path, points, cells):
    meshio.write(path, meshio.Mesh(points, cells), file_format="gmsh22", binary=False)
    return path


SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])


def bad_files(tmp_path):
    good = tmp_path / "good.msh"
    write_mesh(good, curved_p2_mesh())
    data = good.read_bytes()
    yield "truncated", data[: len(data) // 2], "truncated"
    yield "cut-after-nodes", data[: data.index(b"$Elements")], "no elements"
    yield "cut-in-end-tag", data[:-3], "truncated"
    yield "garbage", b"\x00\x93garbage\nmore garbage\n", "not a Gmsh MSH file"
    bad_nodes = b"$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\nabc\n$EndNodes\n"
    yield "garbage-msh", bad_nodes, "invalid Gmsh MSH file"
    yield "empty", b"", "empty file"
    yield "blank", b"\n\n  \n", "empty file"
    files = {
        "quad": ([("quad", [[0, 1, 2, 3]])], SQUARE, "unsupported cell type 'quad'"),
        "mixed": (
            [("triangle", [[0, 1, 2]]), ("triangle6", [[0, 2, 3, 4, 5, 6]])],
            np.vstack([SQUARE, [[0.5, 0.5], [0.5, 1.0], [0.0, 0.5]]]),
            "mixes triangle and triangle6",
        ),
        "tetra": ([("tetra", [[0, 1, 2, 3]])], SQUARE, "unsupported cell type 'tetra'"),
        "degenerate": (
            [("triangle", [[0, 1, 2], [0, 1, 3]])],
            np.array([[0.0, 0.0], [1.0, 0.0], [0.5, 1.0], [0.5, 0.0]]),
            "1 degenerate",
        ),
        "3d": ([("triangle", [[0, 1, 2]])], np.column_stack([SQUARE, [0, 0, 1, 0]]), "z != 0"),
        "nan": ([("triangle", [[0, 1, 2]])], np.where(SQUARE == 1, np.nan, SQUARE), "finite"),
    }
    for label, (cells, points, what) in files.items():
        path = write_meshio(tmp_path / f"{label}.msh", points, cells)
        yield label, path.read_bytes(), what


def test_bad_files_give_one_line_errors(tmp_path, capsys):
    for label, data, what in list(bad_files(tmp_path)):
        path = tmp_path / f"bad-{label}.msh"
        path.write_bytes(data)
        with pytest.raises(MeshReadError) as info:
            read_mesh(path)
        message = str(info.value)
        assert message.startswith(f"{path}: "), label
        assert what in message, (label, message)
        assert "\n" not in message, label
    out, _ = capsys.readouterr()
    assert out == ""  # meshio prints its errors to stdout: none may leak


def test_missing_and_unknown_files(tmp_path):
    with pytest.raises(MeshReadError, match=r"nope\.msh: cannot read: No such file"):
        read_mesh(tmp_path / "nope.msh")
    with pytest.raises(MeshReadError, match=r"files0: cannot read: Is a directory$"):
        read_mesh(tmp_path)
    (tmp_path / "m.xyz").write_text("1 2 3\n")
    with pytest.raises(MeshReadError, match=r"m\.xyz: unknown mesh format '\.xyz'"):
        read_mesh(tmp_path / "m.xyz")
    (tmp_path / "m.vtu").write_text("not xml")
    with pytest.raises(MeshReadError, match=r"m\.vtu: invalid mesh file"):
        read_mesh(tmp_path / "m.vtu")


def test_reader_ignores_lines_and_vertices(tmp_path):
    path = write_meshio(
        tmp_path / "m.msh",
        SQUARE,
        [("vertex", [[0], [1]]), ("line", [[0, 1]]), ("triangle", [[0, 1, 2], [0, 2, 3]])],
    )
    mesh = read_mesh(path)
    assert mesh.triangles.tolist() == [[0, 1, 2], [0, 2, 3]]


def imported_modules(module) -> set[str]:
    tree = ast.parse(Path(module.__file__).read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            names.add("." + module if node.level else module.split(".")[0])
    return names


def test_module_layering():
    # mesh needs numpy and, of curvimesh, the compiled kernels only (its edge table);
    # io is the one user of meshio.
    import curvimesh.mesh as cmesh

    assert imported_modules(cmesh) == {
        "__future__",
        "dataclasses",
        "functools",
        "numpy",
        "curvimesh",
    }
    tree = ast.parse(Path(cmesh.__file__).read_text())
    own = [
        ast.unparse(node)
        for node in ast.walk(tree)
        if isinstance(node, ast.Import | ast.ImportFrom) and "curvimesh" in ast.unparse(node)
    ]
    assert own == ["from curvimesh import kernels"]
    assert imported_modules(cio) & {"meshio", ".errors", ".mesh"} == {
        "meshio",
        ".errors",
        ".mesh",
    }
    assert not {m for m in imported_modules(cio) if m.startswith(".")} - {
        ".bezier",
        ".errors",
        ".mesh",
    }
