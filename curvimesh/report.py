"""The figures a user checks on a mesh in a metric (SPEC section 4).

:func:`mesh_report` returns the JSON object of SPEC section 4: counts, edge
lengths of the curved edges (to 1e-5 relative:
:data:`curvimesh.quality.REPORT_RTOL`), quality of equation (4) (metric
areas to 1e-5 relative too: :func:`curvimesh.quality.metric_areas_adaptive`),
validity decided exactly, the straight-sided version's invalid count (paper
figure 8), metric area, ideal triangle count and efficiency; with a function,
the errors of its Lagrange interpolant on the mesh.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from curvimesh.bezier import valid_exact
from curvimesh.interpolation_error import interpolation_error
from curvimesh.mesh import Mesh, signed_areas, to_p2_straight
from curvimesh.metric import UNIT_TRIANGLE_AREA, MetricField, density_integral
from curvimesh.quality import REPORT_RTOL, edge_lengths, metric_areas_adaptive, quality_from

#: The range of a quasi-unit edge (paper section 1).
UNIT_RANGE = (0.7, 1.4)


def mesh_report(
    field: MetricField,
    mesh: Mesh,
    *,
    metric_area: float | None = None,
    function: Callable[[NDArray], NDArray] | None = None,
) -> dict:
    """The SPEC section 4 report of ``mesh`` (P1 or P2) in ``field``.

    With ``function`` (points ``(n, 2)`` to values ``(n,)``, e.g. from
    :func:`curvimesh.interpolation.compile_function`), also
    ``"interpolation_error": {"l2", "linf"}`` of its Lagrange interpolant on
    the mesh as it is (:func:`curvimesh.interpolation_error.interpolation_error`).
    """
    if len(mesh.triangles) == 0:
        raise ValueError("the mesh has no triangles")
    pts = np.asarray(mesh.points)
    edges = mesh.edges
    mids = mesh.edge_mid if mesh.order == 2 else None
    lengths = edge_lengths(field, pts, edges, mids, rtol=REPORT_RTOL)
    p2 = mesh if mesh.order == 2 else to_p2_straight(mesh)
    nodes = np.asarray(p2.points)[p2.triangles]
    area = metric_areas_adaptive(field, nodes, rtol=REPORT_RTOL)
    q = quality_from(area, lengths[mesh.tri_edges])
    valid = valid_exact(nodes)
    straight_bad = int((signed_areas(pts, mesh.corners) <= 0).sum())
    if metric_area is None:
        metric_area = density_integral(field)
    ideal = metric_area / UNIT_TRIANGLE_AREA
    lo, hi = UNIT_RANGE
    out = {
        "vertices": len(mesh.vertex_ids),
        "nodes": len(np.unique(mesh.triangles)),
        "triangles": len(mesh.triangles),
        "edges": len(edges),
        "edge_length": {
            "min": float(lengths.min()),
            "max": float(lengths.max()),
            "mean": float(lengths.mean()),
            "p01": float(np.percentile(lengths, 1)),
            "p99": float(np.percentile(lengths, 99)),
            "in_range": float(np.mean((lengths >= lo) & (lengths <= hi))),
        },
        "quality": {
            "min": float(q.min()),
            "mean": float(q.mean()),
            "p01": float(np.percentile(q, 1)),
        },
        "valid": bool(valid.all()),
        "invalid_triangles": int((~valid).sum()),
        "straight_invalid_triangles": straight_bad,
        "metric_area": float(metric_area),
        "ideal_triangles": float(ideal),
        "efficiency": float(len(mesh.triangles) / ideal) if ideal > 0 else math.inf,
    }
    if function is not None:
        out["interpolation_error"] = interpolation_error(function, mesh).as_dict()
    return out


def format_report(report: dict) -> str:
    """The report as a readable table (one figure a line)."""
    el, q = report["edge_length"], report["quality"]
    rows = [
        ("vertices", f"{report['vertices']}"),
        ("nodes", f"{report['nodes']}"),
        ("triangles", f"{report['triangles']}"),
        ("edges", f"{report['edges']}"),
        ("edge length min / mean / max", f"{el['min']:.4f} / {el['mean']:.4f} / {el['max']:.4f}"),
        ("edge length p01 / p99", f"{el['p01']:.4f} / {el['p99']:.4f}"),
        ("edges in [0.7, 1.4]", f"{100 * el['in_range']:.2f} %"),
        ("quality min / mean / p01", f"{q['min']:.4f} / {q['mean']:.4f} / {q['p01']:.4f}"),
        ("valid", "yes" if report["valid"] else "NO"),
        ("invalid triangles", f"{report['invalid_triangles']}"),
        ("straight-sided invalid triangles", f"{report['straight_invalid_triangles']}"),
        ("metric area", f"{report['metric_area']:.4f}"),
        ("ideal triangles", f"{report['ideal_triangles']:.1f}"),
        ("efficiency (triangles / ideal)", f"{report['efficiency']:.4f}"),
    ]
    if "interpolation_error" in report:
        err = report["interpolation_error"]
        rows.append(("interpolation error L2 / Linf", f"{err['l2']:.4e} / {err['linf']:.4e}"))
    for key in ("swaps",):
        if key in report:
            rows.append((key, f"{report[key]}"))
    if "seconds" in report:
        rows.append(("seconds", ", ".join(f"{k} {v:.2f}" for k, v in report["seconds"].items())))
    width = max(len(r[0]) for r in rows)
    return "\n".join(f"{k.ljust(width)}  {v}" for k, v in rows)
