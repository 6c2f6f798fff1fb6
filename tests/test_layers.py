"""The house stands: modules import only from layers below, each third-party edge in one place."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "curvimesh"

#: A module may import curvimesh modules of lower layers only (STYLE.md, "The house").
LAYERS = {
    "__init__": 0,
    "errors": 0,
    "kernels": 0,
    "tensors": 0,
    "gradation": 1,
    "expressions": 1,
    "bezier": 1,
    "spatial": 1,
    "memo": 1,
    "mesh": 2,
    "interpolation": 2,
    "metric": 3,
    "geodesic": 4,
    "io": 4,
    "quality": 5,
    "freenode": 5,
    "cores": 5,
    "boundary": 5,
    "triangulate": 5,
    "interpolation_error": 6,
    "sampling": 6,
    "rows": 6,
    "report": 7,
    "plot": 7,
    "curve": 7,
    "fill": 7,
    "smooth": 7,
    "swap": 8,
    "split": 8,
    "insert": 8,
    "recurve": 8,
    "fit": 8,
    "shift": 8,
    "remove": 8,
    "intrinsic": 8,
    "charts": 8,
    "bend": 8,
    "adapt": 9,
    "batch": 10,
    "cli": 11,
    "__main__": 12,
}

#: Each third-party dependency at the edge lives in the named modules only.
EDGES = {
    "meshio": {"io"},
    "click": {"cli"},
    "matplotlib": {"plot"},
    "yaml": {"metric", "batch"},
    "numba": {"kernels"},
}


def imports_of(path: Path) -> set[str]:
    """Top-level names of every module imported anywhere in the file ('.x' → 'curvimesh.x')."""
    tree = ast.parse(path.read_text())
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = "curvimesh" + (f".{node.module}" if node.module else "")
            else:
                base = node.module or ""
            if base == "curvimesh":
                out.update(f"curvimesh.{alias.name}" for alias in node.names)
            else:
                out.add(base)
    return out


MODULES = sorted(p.stem for p in PACKAGE.glob("*.py"))


def test_every_module_has_a_layer():
    assert set(MODULES) <= set(LAYERS), set(MODULES) - set(LAYERS)


@pytest.mark.parametrize("name", MODULES)
def test_imports_go_down(name):
    own = LAYERS[name]
    for imp in imports_of(PACKAGE / f"{name}.py"):
        if imp.startswith("curvimesh."):
            dep = imp.split(".")[1]
            assert LAYERS[dep] < own, f"{name} (layer {own}) imports {dep} (layer {LAYERS[dep]})"


@pytest.mark.parametrize("lib", sorted(EDGES))
def test_third_party_edges(lib):
    users = {
        m for m in MODULES if any(i.split(".")[0] == lib for i in imports_of(PACKAGE / f"{m}.py"))
    }
    assert users <= EDGES[lib], f"{lib} is imported by {sorted(users - EDGES[lib])}"
