"""Overlaps of final meshes, measured on constructed cases with known depths and areas."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

from kneemesh_core.job.verdict import knee_verdict
from kneemesh_core.metrics.compare import articular_surface
from kneemesh_core.geometry import quad_node_areas as node_areas
from kneemesh_core.metrics.overlap import MAX_SEATABLE_OVERLAP_MM, closed_surface, knee_overlaps, overlap


def slab(x: tuple[float, float], y: tuple[float, float], z: tuple[float, float], h: float = 1.0, layers: int = 2) -> pv.UnstructuredGrid:
    """A block of hexahedra (h in-plane, ``layers`` through z), its top layer articular, laid out as a
    KneeMesh cartilage mesh (cell data ``layer``)."""
    xs, ys = np.arange(x[0], x[1] + 1e-9, h), np.arange(y[0], y[1] + 1e-9, h)
    zs = np.linspace(z[0], z[1], layers + 1)
    nx, ny = len(xs), len(ys)
    points = np.array([(a, b, c) for c in zs for b in ys for a in xs])
    idx = np.arange(len(points)).reshape(len(zs), ny, nx)
    hexes, layer = [], []
    for k in range(layers):
        for j in range(ny - 1):
            for i in range(nx - 1):
                bottom = [idx[k, j, i], idx[k, j, i + 1], idx[k, j + 1, i + 1], idx[k, j + 1, i]]
                hexes.append(bottom + [n + nx * ny for n in bottom])
                layer.append(k)
    grid = pv.UnstructuredGrid({pv.CellType.HEXAHEDRON: np.array(hexes)}, points)
    grid.cell_data["layer"] = np.array(layer)
    return grid


def test_an_overlap_of_known_depth_and_area_is_measured():
    """The top of a 10 x 10 mm slab reaches 0.4 mm into a box over x <= 4.5 mm: depth 0.4, area 45 mm^2."""
    points, quads = articular_surface(slab((0, 10), (0, 10), (-2, 0)))
    areas = node_areas(points, quads)
    assert areas.sum() == pytest.approx(100.0)
    box = closed_surface(pv.Box(bounds=(-1.0, 4.5, -1.0, 11.0, -0.4, 2.0)))
    found = overlap(points, areas, box)
    assert found["max_depth_mm"] == pytest.approx(0.4, abs=1e-6) and found["area_mm2"] == pytest.approx(45.0)
    apart = overlap(points, areas, closed_surface(pv.Box(bounds=(-1.0, 11.0, -1.0, 11.0, 0.2, 2.0))))
    assert apart == {"max_depth_mm": 0.0, "area_mm2": 0.0, "nodes": 0}


def test_an_overlap_beyond_what_seating_resolves_makes_the_knee_review(tmp_path):
    """A medial tibial plate 1.5 mm into the femoral cartilage: review with the reason; 0.3 mm: ok."""
    for depth, status in ((1.5, "review"), (0.3, "ok")):
        meshes = tmp_path / f"d{depth}"
        meshes.mkdir()
        slab((0, 20), (0, 20), (-2, 0)).save(meshes / "medial_tibial_cartilage.vtu")
        femoral = slab((-5, 25), (-5, 25), (-depth, 10.0 - depth))
        femoral.save(meshes / "femoral_cartilage.vtu")
        found = knee_overlaps(meshes)
        pair = found["pairs"]["medial_tibial_cartilage/femoral_cartilage"]
        assert pair["max_depth_mm"] == pytest.approx(depth, abs=1e-6) and pair["area_mm2"] == pytest.approx(400.0)
        assert found["status"] == status
        verdict = knee_verdict({"tissues": {}, "overlaps": found})
        assert verdict["status"] == status
        if status == "review":
            assert f"limit {MAX_SEATABLE_OVERLAP_MM} mm" in verdict["reasons"][0] and "1.50 mm" in verdict["reasons"][0]
