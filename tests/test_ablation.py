"""bench/ablation.py: its shared stages give the meshes of five separate adapt runs,
and it rewrites only its own section of a README."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from curvimesh import adapt as pipeline
from curvimesh.metric import load_metric
from curvimesh.report import mesh_report

ROOT = Path(__file__).resolve().parents[1]
SPEC = importlib.util.spec_from_file_location("ablation", ROOT / "bench" / "ablation.py")
ablation = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(ablation)

SMALL = """name: small
domain:
  box: [[0, 0], [1, 1]]
metric:
  eigen:
    sizes: [0.05 + 0.1*x, 0.15]
    angle: 0.3*y
"""


def test_each_row_is_the_mesh_of_adapt_with_those_stages(tmp_path):
    path = tmp_path / "small.yaml"
    path.write_text(SMALL)
    rows = ablation.ablate(str(path))["rows"]
    assert [r["stage"] for r in rows] == list(ablation.STAGES)
    fld = load_metric(path)
    names = [name for name in pipeline.STAGES if name != "fit"]
    # row i has the first i stages on (row 0: the paper's method); the rows are built
    # stage by stage, without adapt's second run (which this metric's rows with the
    # hexagons but without the clean-up stages would start: edges over 1.5)
    for i, row in enumerate(rows):
        opt = pipeline.AdaptOptions(retry=False, **{k: j < i for j, k in enumerate(names)})
        rep = mesh_report(fld, pipeline.adapt(fld, opt).mesh)
        assert row["vertices"] == rep["vertices"]
        assert row["triangles"] == rep["triangles"]
        assert row["length_max"] == pytest.approx(rep["edge_length"]["max"], rel=1e-12)
        assert row["quality_min"] == pytest.approx(rep["quality"]["min"], rel=1e-12)


def test_the_readme_section_is_replaced_in_place_and_the_rest_kept(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text("# head\n")
    ablation.write_readme(readme, f"{ablation.BEGIN}\nfirst\n{ablation.END}\n")
    readme.write_text(readme.read_text() + "\nhand-written tail\n")
    ablation.write_readme(readme, f"{ablation.BEGIN}\nsecond\n{ablation.END}\n")
    text = readme.read_text()
    assert text.startswith("# head\n")
    assert "first" not in text and text.count("second") == 1
    assert text.endswith("hand-written tail\n")
    assert text.count(ablation.BEGIN) == 1 and text.count(ablation.END) == 1
