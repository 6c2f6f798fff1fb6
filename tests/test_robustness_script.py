"""bench/robustness.py: its verdicts, and a run of the command line it drives."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SPEC = importlib.util.spec_from_file_location("robustness", ROOT / "bench" / "robustness.py")
robustness = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(robustness)


def report(**over) -> dict:
    rep = {
        "valid": True,
        "vertices": 100,
        "edge_length": {"min": 0.71, "max": 1.39, "in_range": 1.0},
        "quality": {"min": 0.5, "mean": 0.9},
        "efficiency": 1.0,
    }
    for key, value in over.items():
        group, _, name = key.partition("__")
        if name:
            rep[group] = {**rep[group], name: value}
        else:
            rep[group] = value
    return rep


def test_each_target_is_missed_alone_and_a_sharp_corner_excuses_only_the_quality():
    assert robustness.misses(report(), 1.0) == []
    assert robustness.misses(report(valid=False), 1.0) == ["invalid"]
    assert robustness.misses(report(edge_length__min=0.69), 1.0) == ["edge 0.690 < 0.7"]
    assert robustness.misses(report(edge_length__min=0.69995), 1.0) == []  # 1e-4 accuracy
    assert robustness.misses(report(edge_length__max=1.52), 1.0) == ["edge 1.52 > 1.5"]
    assert robustness.misses(report(edge_length__in_range=0.975), 1.0) == ["97.5 % in range"]
    assert robustness.misses(report(quality__min=0.2), 1.0) == ["quality 0.200 < 0.3"]
    assert robustness.misses(report(quality__min=0.2), 0.21) == []
    assert robustness.misses(report(quality__mean=0.79, quality__min=0.2), 0.21) == [
        "mean quality 0.790 < 0.8"
    ]
    assert robustness.misses(report(efficiency=1.2), 1.0) == ["efficiency 1.200 > 1.15"]


def test_corner_bound_of_a_constant_field_is_the_bound_at_its_sharpest_corner(tmp_path):
    # sizes 0.01 along 30°, 0.2 across: the corners (0, 0) and (1, 1) are 6.6° wide
    path = tmp_path / "c.yaml"
    path.write_text("metric:\n  eigen: {sizes: [0.01, 0.2], angle: 0.5235987755982988}\n")
    g11 = math.cos(math.pi / 6) ** 2 / 1e-4 + math.sin(math.pi / 6) ** 2 / 0.04
    g22 = math.sin(math.pi / 6) ** 2 / 1e-4 + math.cos(math.pi / 6) ** 2 / 0.04
    g12 = math.cos(math.pi / 6) * math.sin(math.pi / 6) * (1 / 1e-4 - 1 / 0.04)
    theta = math.acos(abs(g12) / math.sqrt(g11 * g22))
    assert math.isclose(math.degrees(theta), 6.6, abs_tol=0.05)
    want = robustness.angle_bound(theta)
    assert math.isclose(robustness.corner_bound(str(path)), want, rel_tol=1e-9)
    # below the bound without lengths (equal sides, a cross edge of 0.12)
    assert want < math.sqrt(3) * math.sin(theta) / (2 - math.cos(theta)) < 0.2


def test_a_run_writes_the_page_with_every_mesh_counted(tmp_path):
    metric = ROOT / "bench" / "robustness" / "u14_iso_variable.yaml"
    args = [str(metric), "--seeds", "0", "--jobs", "1", "--out", str(tmp_path)]
    assert robustness.main([*args, "--work", str(tmp_path / "work")]) == 0
    page = (tmp_path / "robustness.md").read_text()
    assert "**1 of 1 meshes meet every target.**" in page
    assert (tmp_path / "work" / "seed0" / "u14_iso_variable.msh").exists()


def test_the_corner_bound_keeps_the_edges_within_the_targets():
    # 60°: the unit equilateral triangle; 90°: two triangles of 45°, better than one
    # right isosceles triangle (0.866); 12°: with the cross edge at least 0.7 no
    # triangle reaches 0.3, where equal sides alone would give 0.35 (cross edge 0.21)
    assert abs(robustness.angle_bound(math.pi / 3) - 1.0) < 1e-3
    assert robustness.angle_bound(math.pi / 2) > 0.94
    theta = math.radians(12.0)
    free = math.sqrt(3.0) * math.sin(theta) / (2.0 - math.cos(theta))
    assert free > 0.34 and 2 * math.sin(theta / 2) < 0.7
    assert 0.2 < robustness.angle_bound(theta) < 0.3
    # a = 1.4, b = 0.7 is one admissible triangle: the bound is at least its quality
    c2 = 1.4**2 + 0.7**2 - 2 * 1.4 * 0.7 * math.cos(theta)
    q = 2 * math.sqrt(3) * 1.4 * 0.7 * math.sin(theta) / (1.4**2 + 0.7**2 + c2)
    assert c2 >= 0.49 and robustness.angle_bound(theta) >= q - 1e-12
