"""The targets of a unit mesh, asserted on an adapted mesh (shared by the tests of the
examples and of the hard metrics)."""

from __future__ import annotations

from curvimesh.mesh import Mesh, is_conforming
from curvimesh.metric import MetricField
from curvimesh.report import mesh_report


def assert_unit_mesh_targets(fld: MetricField, mesh: Mesh, *, quality_floor: bool = True) -> None:
    """Valid and conforming, no edge shorter than 0.7 (lengths are accurate to 1e-5), at
    least 98 % in [0.7, 1.4], none over 1.5, quality at least 0.3 (unless
    ``quality_floor`` is off) and 0.8 on average, at most 1.15 times the ideal
    triangle count."""
    rep = mesh_report(fld, mesh)
    lengths = rep["edge_length"]
    assert rep["valid"] and is_conforming(mesh)
    assert lengths["min"] >= 0.7 * (1 - 1e-5)
    assert lengths["in_range"] >= 0.98
    assert lengths["max"] <= 1.5
    if quality_floor:
        assert rep["quality"]["min"] >= 0.3
    assert rep["quality"]["mean"] >= 0.8
    assert rep["efficiency"] <= 1.15
