"""``curvimesh batch``: many metrics, gates, parallel workers, the summary and the README part."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import pytest
import sympy
from click.testing import CliRunner
from clitools import run_cli

from curvimesh import batch
from curvimesh.cli import main
from curvimesh.errors import InputError
from curvimesh.io import read_mesh
from curvimesh.mesh import Mesh
from curvimesh.metric import Component, MetricField, X, Y

#: Two metrics that adapt in about a second: isotropic, and constant anisotropic.
ISO = "name: iso\nmetric:\n  isotropic: 0.2\n"
ANISO = "name: aniso\nmetric:\n  eigen: {sizes: [0.1, 0.3], angle: 0.5}\n"
BROKEN = "name: broken\nmetric: {isotropic: [\n"
FILES = ("{}.msh", "{}.json", "{}.txt", "{}.png", "{}-zoom.png")
PNG = b"\x89PNG\r\n\x1a\n"


run = functools.partial(run_cli, text=True)


@pytest.fixture(scope="module")
def metrics(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("batch")
    (d / "iso.yaml").write_text(ISO)
    (d / "aniso.yaml").write_text(ANISO)
    (d / "broken.yaml").write_text(BROKEN)
    return d


@pytest.fixture(scope="module")
def serial(metrics):
    """iso, broken, aniso in one process, gated on validity and the share of unit edges."""
    r = run(
        "batch", "iso.yaml", "broken.yaml", "aniso.yaml", "--out-dir", "serial",
        "--require", "valid", "--require", "in_range>=0.5",
        cwd=metrics,
    )  # fmt: skip
    return r, metrics / "serial"


def without_seconds(report: dict) -> dict:
    return {k: v for k, v in report.items() if k != "seconds"}


def test_a_broken_metric_fails_the_batch_but_not_the_others(serial):
    r, out = serial
    assert r.returncode == 1, r.stderr
    assert r.stderr.count("\n") == 1 and "broken" in r.stderr and "Traceback" not in r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert [run["name"] for run in summary["runs"]] == ["iso", "broken", "aniso"]
    assert summary["passed"] is False and summary["failed"] == ["broken"]
    iso, broken, aniso = summary["runs"]
    assert broken["ok"] is False and broken["report"] is None and broken["files"] == []
    assert "broken.yaml" in broken["error"] and "invalid YAML" in broken["error"]
    assert [g["passed"] for g in broken["gates"]] == [False, False]
    for done in (iso, aniso):
        assert done["ok"] and done["passed"] and done["error"] is None
        assert done["files"] == [f.format(done["name"]) for f in FILES]
        assert [g["key"] for g in done["gates"]] == ["valid", "edge_length.in_range"]
        assert done["gates"][1]["value"] == done["report"]["edge_length"]["in_range"]
    assert not list(out.glob("broken*"))
    # The readable summary names the failure too.
    assert "broken" in (out / "summary.md").read_text()
    assert "error" in r.stdout.splitlines()[2]


def test_each_run_writes_its_mesh_report_table_and_pictures(serial):
    _, out = serial
    summary = json.loads((out / "summary.json").read_text())
    for run_ in summary["runs"]:
        if not run_["ok"]:
            continue
        name = run_["name"]
        report = json.loads((out / f"{name}.json").read_text())
        assert report == run_["report"]
        assert report["valid"] is True and report["swaps"] >= 0
        assert set(report["seconds"]) == {"sample", "triangulate", "curve", "swap", "total"}
        mesh = read_mesh(out / f"{name}.msh")
        assert mesh.order == 2 and len(mesh.triangles) == report["triangles"]
        table = (out / f"{name}.txt").read_text()
        assert "edges in [0.7, 1.4]" in table and f"{report['triangles']}" in table
        for picture in (f"{name}.png", f"{name}-zoom.png"):
            assert (out / picture).read_bytes().startswith(PNG)


def test_the_gate_keys_are_the_keys_of_a_report(serial):
    # NUMBER_KEYS and BOOLEAN_KEYS are spelt out in batch.py: they must be
    # exactly the leaves of a real NAME.json, so that every key is gateable.
    _, out = serial
    report = json.loads((out / "iso.json").read_text())

    def leaves(d: dict, prefix: str = "") -> dict:
        out_ = {}
        for k, v in d.items():
            out_.update(leaves(v, f"{prefix}{k}.") if isinstance(v, dict) else {prefix + k: v})
        return out_

    flat = leaves(report)
    assert set(flat) == set(batch.NUMBER_KEYS) | set(batch.BOOLEAN_KEYS)
    assert {k for k, v in flat.items() if isinstance(v, bool)} == set(batch.BOOLEAN_KEYS)


def test_parallel_runs_give_the_same_results_and_leave_other_files(serial, metrics):
    _, ref = serial
    out = metrics / "parallel"
    out.mkdir()
    (out / "convergence.md").write_text("a study of someone else\n")
    (out / "README.md").write_text(
        "# Runs\n\nintro\n\n"
        f"{batch.README_BEGIN}\nstale\n{batch.README_END}\n\n## Convergence\n\nkept\n"
    )
    r = run(
        "batch", "iso.yaml", "aniso.yaml", "--out-dir", "parallel", "--jobs", "2", "--readme",
        "--require", "valid", "--require", "edge_length.max <= 3", "--require", "efficiency<2",
        cwd=metrics,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    for name in ("iso", "aniso"):
        one = json.loads((ref / f"{name}.json").read_text())
        two = json.loads((out / f"{name}.json").read_text())
        assert without_seconds(one) == without_seconds(two)
        assert (ref / f"{name}.msh").read_bytes() == (out / f"{name}.msh").read_bytes()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["passed"] is True and summary["failed"] == []
    assert summary["options"]["jobs"] == 2
    assert all(g["passed"] for run_ in summary["runs"] for g in run_["gates"])
    # Nothing else in the folder is touched; only the marked part of the README is replaced.
    assert (out / "convergence.md").read_text() == "a study of someone else\n"
    readme = (out / "README.md").read_text()
    assert readme.startswith("# Runs\n\nintro\n\n") and readme.endswith("## Convergence\n\nkept\n")
    assert "stale" not in readme
    assert "![iso: the whole mesh](iso.png)" in readme and "(aniso-zoom.png)" in readme
    assert readme.count(batch.README_BEGIN) == 1


def test_a_missed_gate_fails_the_batch(metrics):
    r = run(
        "batch", "iso.yaml", "--out-dir", "gated", "--require", "quality.min>=0.99",
        "--require", "valid", cwd=metrics,
    )  # fmt: skip
    assert r.returncode == 1, r.stderr
    assert "missed a gate: iso" in r.stderr and r.stderr.count("\n") == 1
    assert "missed quality.min>=0.99" in r.stdout
    summary = json.loads((metrics / "gated" / "summary.json").read_text())
    (iso,) = summary["runs"]
    assert iso["ok"] is True and iso["passed"] is False
    assert [g["passed"] for g in iso["gates"]] == [False, True]
    assert iso["gates"][0]["value"] == iso["report"]["quality"]["min"] < 0.99
    assert "missed" in (metrics / "gated" / "summary.md").read_text()


@pytest.mark.parametrize(
    "gate",
    [
        "in_range>>0.9",  # no such operator
        "min>=0.3",  # edge_length.min or quality.min
        "valid>=1",  # yes/no keys stand alone
        "in_range",  # numbers are compared
        "lenght.max<=2",  # unknown key
        "in_range>=abc",
        "in_range>=nan",
        "",
    ],
)
def test_a_bad_gate_is_refused_before_any_work(metrics, gate):
    result = CliRunner().invoke(
        main, ["batch", "iso.yaml", "--out-dir", str(metrics / "never"), "--require", gate]
    )
    assert result.exit_code == 2, result.output
    assert "--require" in result.stderr and result.stderr.count("\n") == 1
    assert not (metrics / "never").exists()


def test_two_metrics_of_the_same_name_are_refused(metrics):
    (metrics / "other").mkdir(exist_ok=True)
    (metrics / "other" / "iso.yaml").write_text(ISO)
    result = CliRunner().invoke(
        main, ["batch", str(metrics / "iso.yaml"), str(metrics / "other" / "iso.yaml"),
               "--out-dir", str(metrics / "never")],
    )  # fmt: skip
    assert result.exit_code == 2
    assert "same name 'iso'" in result.stderr
    assert not (metrics / "never").exists()


# --------------------------------------------------------------------------- the library


def test_short_gate_names_resolve_where_unambiguous():
    assert batch.parse_gate("in_range>=0.95").key == "edge_length.in_range"
    assert batch.parse_gate("max<=1.5").key == "edge_length.max"
    assert batch.parse_gate("p99 < 1.4").key == "edge_length.p99"
    assert batch.parse_gate("quality.min>=0.3") == batch.Gate(
        "quality.min>=0.3", "quality.min", ">=", 0.3
    )
    with pytest.raises(InputError, match=r"edge_length\.mean or quality\.mean"):
        batch.parse_gate("mean>0.9")


def test_gate_checks():
    report = {"valid": False, "edge_length": {"max": 1.5}, "efficiency": 1.1}
    assert batch.parse_gate("max<=1.5").check(report) == (True, 1.5)
    assert batch.parse_gate("max<1.5").check(report) == (False, 1.5)
    assert batch.parse_gate("efficiency!=1.1").check(report) == (False, 1.1)
    assert batch.parse_gate("valid").check(report) == (False, False)
    # A key the report lacks fails the gate.
    assert batch.parse_gate("quality.min>=0").check(report) == (False, None)


def test_zoom_window_is_centred_on_the_densest_point_inside_the_box():
    # Size 0.02 + |x - c|^2 is smallest, the density 1/size^2 largest, at c.
    box = (0.0, 0.0, 2.0, 1.0)
    size = 0.02 + (X - 1.3) ** 2 + (Y - 0.6) ** 2
    fld = MetricField((Component((size**-2, sympy.Integer(0), size**-2), ()),), box=box)
    gx, gy = np.meshgrid(np.linspace(0, 2, 41), np.linspace(0, 1, 21))
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    from scipy.spatial import Delaunay

    mesh = Mesh(pts, Delaunay(pts).simplices, box)
    x0, y0, x1, y1 = batch.zoom_window(fld, mesh)
    assert (x1 - x0, y1 - y0) == pytest.approx((0.2, 0.1))
    assert ((x0 + x1) / 2, (y0 + y1) / 2) == pytest.approx((1.3, 0.6), abs=0.04)
    # Near a corner the window moves inside the box.
    corner = 0.02 + X**2 + Y**2
    fld = MetricField((Component((corner**-2, sympy.Integer(0), corner**-2), ()),), box=box)
    assert batch.zoom_window(fld, mesh) == pytest.approx((0.0, 0.0, 0.2, 0.1))


def test_write_readme_makes_appends_and_replaces(tmp_path):
    result = batch.BatchResult((batch.RunResult("m", "m.yaml", error="m.yaml: bad | worse"),))
    batch.write_readme(tmp_path, result)
    first = (tmp_path / "README.md").read_text()
    assert first.startswith("# ") and "bad \\| worse" in first
    (tmp_path / "README.md").write_text("# Mine\n")
    batch.write_readme(tmp_path, result)
    batch.write_readme(tmp_path, result)
    again = (tmp_path / "README.md").read_text()
    assert again.startswith("# Mine\n\n" + batch.README_BEGIN)
    assert again.count(batch.README_BEGIN) == 1 and again.endswith(batch.README_END + "\n")
