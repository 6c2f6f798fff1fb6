"""`report` on meshes made by Gmsh itself, `report --window`, `circles`."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import pytest
from clitools import run_cli

PNG = b"\x89PNG\r\n\x1a\n"
H = 0.25
#: A constant metric: straight geodesics, and metric lengths are Euclidean lengths / H.
CONSTANT = f"name: constant\nmetric:\n  isotropic: {H}\n"
TOY = """
name: ring
domain: {box: [[-1, -1], [1, 1]]}
definitions:
  r: sqrt(x**2 + y**2)
metric:
  eigen:
    sizes: [0.05 + 0.3*(1 - exp(-(r - 0.5)**2/0.02)), 0.3]
    angle: atan2(y, x)
"""


run = functools.partial(run_cli, text=True)


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("report")
    (d / "constant.yaml").write_text(CONSTANT)
    (d / "ring.yaml").write_text(TOY)
    return d


def gmsh_square(path: Path, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Mesh the unit square with Gmsh (P1 or P2), write MSH 4.1; return nodes and corners."""
    gmsh = pytest.importorskip("gmsh")
    gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("square")
        gmsh.model.occ.addRectangle(0, 0, 0, 1, 1)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.3)
        gmsh.model.mesh.generate(2)
        gmsh.model.mesh.setOrder(order)
        gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
        gmsh.write(str(path))
        tags, coords, _ = gmsh.model.mesh.getNodes()
        etype = 2 if order == 1 else 9
        _, enodes = gmsh.model.mesh.getElementsByType(etype)
    finally:
        gmsh.finalize()
    index = np.empty(int(tags.max()) + 1, dtype=np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    points = coords.reshape(-1, 3)[:, :2]
    cells = index[enodes.astype(np.int64)].reshape(-1, 3 if order == 1 else 6)
    return points, cells[:, :3]


@pytest.mark.parametrize("order", [1, 2])
def test_report_reads_gmsh_own_msh41_output(workdir, order):
    msh = workdir / f"gmsh-p{order}.msh"
    points, corners = gmsh_square(msh, order)
    r = run("report", msh.name, "--metric", "constant.yaml", "--json", cwd=workdir)
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    # Straight-sided triangles in a constant metric: every figure is known exactly.
    edges = np.unique(np.sort(corners[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    lengths = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1) / H
    assert rep["triangles"] == len(corners)
    assert rep["vertices"] == len(np.unique(corners))
    assert rep["edges"] == len(edges)
    assert rep["edge_length"]["min"] == pytest.approx(lengths.min(), rel=1e-4)
    assert rep["edge_length"]["max"] == pytest.approx(lengths.max(), rel=1e-4)
    assert rep["metric_area"] == pytest.approx(1 / H**2, rel=1e-6)
    assert rep["valid"] is True and rep["straight_invalid_triangles"] == 0
    table = run("report", msh.name, "--metric", "constant.yaml", cwd=workdir)
    assert table.returncode == 0 and f"{len(corners)}" in table.stdout


def test_report_window_zooms_the_picture(workdir):
    msh = workdir / "zoom.msh"
    gmsh_square(msh, 2)
    r = run(
        "report", msh.name, "--metric", "constant.yaml",
        "--plot", "zoom.png", "--window", "0.2", "0.2", "0.5", "0.4", cwd=workdir,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert (workdir / "zoom.png").read_bytes().startswith(PNG)


@pytest.mark.parametrize(
    "extra",
    [
        ["--plot", "bad.png", "--window", "0.5", "0", "0.2", "1"],  # x0 > x1
        ["--window", "0", "0", "1", "1"],  # no picture to zoom
        ["--plot", "bad.png", "--window", "0", "0", "1"],  # three numbers
    ],
)
def test_report_refuses_a_bad_window(workdir, extra):
    msh = workdir / "bad.msh"
    gmsh_square(msh, 1)
    r = run("report", msh.name, "--metric", "constant.yaml", *extra, cwd=workdir)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") <= 1 and "Traceback" not in r.stderr
    assert not (workdir / "bad.png").exists()


def test_circles_draws_unit_circles(workdir):
    r = run(
        "circles", "--metric", "ring.yaml", "--at", "0.5", "0", "--at", "-0.2", "0.3",
        "--plot", "circles.png", cwd=workdir,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert (workdir / "circles.png").read_bytes().startswith(PNG)


def test_circles_refuses_a_point_outside_the_box(workdir):
    r = run(
        "circles", "--metric", "ring.yaml", "--at", "0", "0", "--at", "1.5", "0",
        "--plot", "out.png", cwd=workdir,
    )  # fmt: skip
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "--at 1.5 0: outside the box" in r.stderr
    assert "ring.yaml" in r.stderr
    assert not (workdir / "out.png").exists()
