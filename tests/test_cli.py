"""The command line end to end: adapt, the stage pipeline, formats, Gmsh as a reader."""

from __future__ import annotations

import json
import math
from pathlib import Path

import meshio
import numpy as np
import pytest
from click.testing import CliRunner
from clitools import run_cli

from curvimesh.cli import main

METRIC = """
name: small
domain: {box: [[0, 0], [1.5, 1]]}
parameters: {h: 0.25}
definitions:
  s: h * (1 + 0.5*x)
metric:
  eigen:
    sizes: [s / 3, s]
    angle: 0.4 + 0.6*y
"""


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    (d / "m.yaml").write_text(METRIC)
    return d


run = run_cli


@pytest.fixture(scope="module")
def adapted(workdir):
    r = run("adapt", "--metric", "m.yaml", "-o", "a.msh", "--stats", "s.json", cwd=workdir)
    assert r.returncode == 0, r.stderr.decode()
    return workdir / "a.msh"


def test_adapt_writes_a_valid_p2_mesh_and_stats(adapted, workdir):
    m = meshio.read(adapted)
    assert {c.type for c in m.cells} == {"triangle6", "line3"}
    stats = json.loads((workdir / "s.json").read_text())
    assert stats["valid"] is True
    assert stats["triangles"] == len(m.cells_dict["triangle6"])
    assert set(stats["seconds"]) >= {"sample", "triangulate", "curve", "swap", "total"}
    assert isinstance(stats["swaps"], int)
    assert stats["edge_length"]["min"] >= 0.7 - 1e-9


def test_gmsh_reads_our_mesh_with_positive_jacobians(adapted):
    gmsh = pytest.importorskip("gmsh")
    ours = meshio.read(adapted)
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.open(str(adapted))
        tags, _, _ = gmsh.model.mesh.getNodes()
        assert len(tags) == len(ours.points)
        types, elems, _ = gmsh.model.mesh.getElements(2)
        assert list(types) == [9]  # 6-node second order triangle
        assert len(elems[0]) == len(ours.cells_dict["triangle6"])
        q = gmsh.model.mesh.getElementQualities(elems[0], "minDetJac")
        assert min(q) > 0
    finally:
        gmsh.finalize()


def test_stage_pipeline_through_pipes_is_byte_identical_to_adapt(adapted, workdir):
    s = run("sample", "--metric", "m.yaml", "-o", "-", cwd=workdir)
    assert s.returncode == 0, s.stderr.decode()
    t = run("triangulate", "-", "--metric", "m.yaml", "-o", "-", stdin=s.stdout, cwd=workdir)
    assert t.returncode == 0, t.stderr.decode()
    c = run("curve", "-", "--metric", "m.yaml", "-o", "-", stdin=t.stdout, cwd=workdir)
    assert c.returncode == 0, c.stderr.decode()
    w = run("swap", "-", "--metric", "m.yaml", "-o", "p.msh", stdin=c.stdout, cwd=workdir)
    assert w.returncode == 0, w.stderr.decode()
    assert (workdir / "p.msh").read_bytes() == adapted.read_bytes()
    # progress never goes to stdout
    assert s.stdout.startswith(b"$MeshFormat")


THIN_RING = """
name: ring
domain: {box: [[0, 0], [1, 1]]}
definitions:
  r: sqrt((x - 0.5)**2 + (y - 0.5)**2)
metric:
  eigen:
    sizes: ['min(0.0002 + 0.25*abs(r - 0.3), 0.05)', 0.05]
    angle: atan2(y - 0.5, x - 0.5)
"""


def test_sample_max_sag_is_the_bounded_lattice_of_adapts_second_run(workdir):
    # a ring of 250:1 turning 9.5° per unit (under HEX_MAX_SAG's turn bound) with a
    # sag of 5.2 short sizes at its circle: --max-sag 0.5 samples what adapt's
    # second run samples, and another cloud than the unbounded lattice (both with the
    # fronts from the box's sides alone: from the ring's core, the two are the same)
    from curvimesh import adapt as pipeline
    from curvimesh.io import read_mesh
    from curvimesh.metric import load_metric_text
    from curvimesh.sampling import HEX_MAX_SAG

    (workdir / "ring.yaml").write_text(THIN_RING)
    clouds = {}
    for flags in ((), ("--max-sag", str(HEX_MAX_SAG))):
        out = f"ring{len(flags)}.msh"
        r = run(
            "sample", "--metric", "ring.yaml", "-o", out, "-q", "--no-cores", *flags, cwd=workdir
        )
        assert r.returncode == 0, r.stderr.decode()
        clouds[len(flags)] = read_mesh(workdir / out).points
    fld = load_metric_text(THIN_RING)
    sides = pipeline.AdaptOptions(cores=False)
    _, bounded = pipeline.retries(sides)[0]
    np.testing.assert_array_equal(clouds[2], pipeline.sample(fld, bounded).points)
    np.testing.assert_array_equal(clouds[0], pipeline.sample(fld, sides).points)
    assert len(clouds[0]) != len(clouds[2])


def test_same_seed_same_bytes_and_other_seed_still_valid(adapted, workdir):
    r = run("adapt", "--metric", "m.yaml", "-o", "b.msh", "--seed", "0", cwd=workdir)
    assert r.returncode == 0
    assert (workdir / "b.msh").read_bytes() == adapted.read_bytes()
    r = run("adapt", "--metric", "m.yaml", "-o", "c.msh", "--seed", "7", cwd=workdir)
    assert r.returncode == 0
    rep = run("report", "c.msh", "--metric", "m.yaml", "--json", cwd=workdir)
    assert json.loads(rep.stdout)["valid"] is True


def test_msh41_output_reads_back_identically(adapted, workdir):
    r = run(
        "curve", "a.msh", "--metric", "m.yaml", "-o", "a41.msh", "--format", "gmsh41", cwd=workdir
    )
    assert r.returncode == 0, r.stderr.decode()
    assert (workdir / "a41.msh").read_text().startswith("$MeshFormat\n4.1")
    m22 = meshio.read(workdir / "a.msh")
    m41 = meshio.read(workdir / "a41.msh")
    np.testing.assert_array_equal(m22.points.shape, m41.points.shape)


def test_report_json_matches_the_spec_keys(adapted, workdir):
    r = CliRunner().invoke(
        main, ["report", str(adapted), "--metric", str(workdir / "m.yaml"), "--json"]
    )
    assert r.exit_code == 0, r.output
    rep = json.loads(r.stdout)
    assert set(rep) >= {
        "vertices",
        "nodes",
        "triangles",
        "edges",
        "edge_length",
        "quality",
        "valid",
        "invalid_triangles",
        "straight_invalid_triangles",
        "metric_area",
        "ideal_triangles",
        "efficiency",
    }
    assert set(rep["edge_length"]) == {"min", "max", "mean", "p01", "p99", "in_range"}
    assert set(rep["quality"]) == {"min", "mean", "p01"}
    assert rep["efficiency"] == pytest.approx(rep["triangles"] / rep["ideal_triangles"])


def test_geodesic_command_prints_json(workdir):
    r = CliRunner().invoke(
        main,
        [
            "geodesic",
            "--metric",
            str(workdir / "m.yaml"),
            "--from",
            "0.5",
            "0.5",
            "--to",
            "0.6",
            "0.55",
        ],
    )
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    assert out["length"] <= out["straight_length"] + 1e-12
    r = CliRunner().invoke(
        main,
        [
            "geodesic",
            "--metric",
            str(workdir / "m.yaml"),
            "--from",
            "0.5",
            "0.5",
            "--angle",
            "0.3",
            "--length",
            "2",
        ],
    )
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["length"] == 2.0


def test_check_metric_prints_the_ideal_count():
    toy = Path(__file__).resolve().parent.parent / "metrics" / "toy.yaml"
    r = CliRunner().invoke(main, ["check-metric", str(toy)])
    assert r.exit_code == 0, r.output
    assert "ideal triangles 761.8" in r.stdout


@pytest.mark.parametrize(
    "flags",
    [
        ("--no-hexagons",),
        ("--no-insert",),
        ("--no-recurve",),
        ("--no-length-swaps",),
        ("--no-shift",),
        ("--no-remove",),
        ("--no-repeat",),
        ("--no-bend",),
        (
            "--no-hexagons",
            "--no-fill",
            "--no-relocate",
            "--no-insert",
            "--no-split",
            "--no-recurve",
            "--no-length-swaps",
            "--no-shift",
            "--no-remove",
            "--no-repeat",
        ),
    ],
)
def test_stage_flags_give_the_library_mesh_with_those_stages_off(workdir, flags):
    from curvimesh import adapt as pipeline
    from curvimesh.io import read_mesh
    from curvimesh.metric import load_metric

    out = workdir / f"flags{''.join(flags)}.msh"
    r = CliRunner().invoke(
        main, ["adapt", "--metric", str(workdir / "m.yaml"), "-o", str(out), *flags]
    )
    assert r.exit_code == 0, r.output
    off = {f.removeprefix("--no-").replace("-", "_") for f in flags}
    opt = pipeline.AdaptOptions(**{k: k not in off for k in pipeline.STAGES})
    want = pipeline.adapt(load_metric(workdir / "m.yaml"), opt).mesh
    got = read_mesh(out)
    np.testing.assert_allclose(got.points, want.points, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(got.triangles, want.triangles)


def test_check_metric_prints_size_and_anisotropy_ranges():
    """Toy metric (SPEC): sizes lmin = 0.01 + 0.3 (1 - exp(-((r - 0.5)/h)²)) across
    and 0.3 along. The grid of [-2, 2]² (spacing 1/32) has points on the ring r = 0.5,
    where lmin = 0.01 (anisotropy 30), and far corners where lmin → 0.31; lmin passes
    0.3 on a ring between, where the metric is isotropic (anisotropy 1)."""
    toy = Path(__file__).resolve().parent.parent / "metrics" / "toy.yaml"
    r = CliRunner().invoke(main, ["check-metric", str(toy)])
    assert r.exit_code == 0, r.output
    lines = dict(line.split(None, 1) for line in r.stdout.splitlines())
    lo, hi = (float(v) for v in lines["anisotropy"].split(".."))
    assert 1 <= lo < 1.001 and math.isclose(hi, 30, rel_tol=1e-5)
    lo, hi = (float(v) for v in lines["size"].split(".."))
    assert math.isclose(lo, 0.01, rel_tol=1e-5) and math.isclose(hi, 0.31, rel_tol=1e-4)
    assert lines["turning"].endswith("(where anisotropy >= 10)")
    assert "warning" not in r.stderr


def test_directions_turning_within_a_unit_length_are_warned_of(tmp_path):
    """Rings around the origin, sizes 0.04 across and 0.8 along: at radius r the
    directions turn 0.8 / r radians per unit length, 4 rad (229 degrees) at the
    box's nearest point (0.2, 0); a long size of 0.8 · (pi/3) / 4 = 0.209 would
    bring that to the 60 degrees unit edges can follow. Around a centre inside
    the box they turn without bound."""
    metric = tmp_path / "rings.yaml"
    rings = "metric: {eigen: {sizes: [0.04, 0.8], angle: 'atan2(y, x)'}}\n"
    metric.write_text("domain: {box: [[0.2, -0.5], [1, 0.5]]}\n" + rings)
    r = CliRunner().invoke(main, ["check-metric", str(metric)])
    assert r.exit_code == 0, r.output
    assert r.stderr == (
        f"curvimesh: warning: {metric}: the metric's directions turn 229 deg within one unit "
        "length near (0.2, 0); unit edges can hardly follow them there (edges over 1.4 may "
        "remain); "
        "a long size below 0.209 there (now 0.8) would let them\n"
    )
    assert "turning     229 deg per unit length at (0.2, 0)" in r.stdout
    r = CliRunner().invoke(main, ["check-metric", "-q", str(metric)])
    assert r.exit_code == 0 and r.stderr == ""
    metric.write_text("domain: {box: [[-1, -1], [1, 1]]}\n" + rings)
    out = tmp_path / "out.msh"
    r = CliRunner().invoke(main, ["adapt", "--metric", str(metric), "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert "directions turn more than a full circle within one unit length near (0, 0)" in (
        r.stderr
    )


@pytest.mark.parametrize(("flags", "retry"), [((), True), (("--no-retry",), False)])
def test_the_retry_flag_reaches_the_pipeline(workdir, monkeypatch, flags, retry):
    from curvimesh import adapt as pipeline

    seen = []
    real = pipeline.adapt

    def recording(fld, opt, **kwargs):
        seen.append(opt)
        return real(fld, opt, **kwargs)

    monkeypatch.setattr(pipeline, "adapt", recording)
    out = workdir / f"retry{len(flags)}.msh"
    r = CliRunner().invoke(
        main, ["adapt", "--metric", str(workdir / "m.yaml"), "-o", str(out), *flags]
    )
    assert r.exit_code == 0, r.output
    assert [opt.retry for opt in seen] == [retry]
    assert all(opt.hexagons for opt in seen)
