"""The contact skins of a rigid-cartilage model (kneemesh_core.fe.contact_skin): valid wedges on the surface
they replace, and a real CalculiX contact through them that meets the analytic solution."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

from kneemesh_core.fe.contact_skin import SKIN_EDGE_MM, articular_surface, skin
from kneemesh_core.fe.inp import set_lines
from kneemesh_core.fe.results import parse_dat
from kneemesh_core.fe.simulate import run_ccx
from kneemesh_core.geometry import grid_quads, hex_sheet

#: The linear contact law of the tests, N/mm^3 (the knee's are 5-10).
K = 9.0


def _cap_layer(radius_mm: float, half_mm: float = 12.0, spacing_mm: float = 1.0, sink_mm: float = 0.0):
    """A layer of 1 mm hexahedra under the lowest part of a sphere of ``radius_mm`` whose bottom touches
    z = -``sink_mm`` (a plane for an infinite radius): its articular side faces down, as a femoral condyle
    faces a plate; nodes (N, 3) and hexahedra (H, 8), C3D8 order, nodes 5-8 articular."""
    u = np.arange(-half_mm, half_mm + 1e-9, spacing_mm)
    xy = np.stack(np.meshgrid(u, u, indexing="ij"), axis=-1).reshape(-1, 2)
    z = 0.0 if np.isinf(radius_mm) else radius_mm - np.sqrt(radius_mm ** 2 - (xy ** 2).sum(1))
    upper = np.column_stack([xy, z - sink_mm])
    return hex_sheet(upper, grid_quads(len(u), len(u)), np.array([0.0, 0.0, -1.0]), 0.5)


def _plate_layer(half_mm: float = 12.0, spacing_mm: float = 1.0):
    """A flat layer of 1 mm hexahedra whose articular side is z = 0, facing up."""
    u = np.arange(-half_mm, half_mm + 1e-9, spacing_mm)
    xy = np.stack(np.meshgrid(u, u, indexing="ij"), axis=-1).reshape(-1, 2)
    return hex_sheet(np.column_stack([xy, np.zeros(len(xy))]), grid_quads(len(u), len(u)), np.array([0.0, 0.0, 1.0]), 0.5)


def _wedge_jacobians(nodes: np.ndarray, wedges: np.ndarray) -> np.ndarray:
    """The corner Jacobians (W, 6) of wedges in C3D6 order: positive for a valid wedge."""
    p = nodes[wedges]
    out = []
    for c, (a, b, up) in enumerate([(1, 2, 3), (2, 0, 4), (0, 1, 5)]):
        out.append(np.einsum("ij,ij->i", np.cross(p[:, a] - p[:, c], p[:, b] - p[:, c]), p[:, up] - p[:, c]))
    for c, (a, b, down) in enumerate([(4, 5, 0), (5, 3, 1), (3, 4, 2)]):
        out.append(np.einsum("ij,ij->i", np.cross(p[:, a] - p[:, c + 3], p[:, b] - p[:, c + 3]), p[:, c + 3] - p[:, down]))
    return np.stack(out, axis=1)


def test_a_contact_skin_is_valid_deterministic_coarse_and_on_the_surface_it_replaces():
    radius = 25.0
    nodes, hexes = _cap_layer(radius)
    points, triangles, outward = articular_surface(nodes, hexes)
    top_nodes, wedges = skin(points, triangles, outward)
    again = skin(points, triangles, outward)
    np.testing.assert_array_equal(again[0], top_nodes)  # the same knee, the same deck
    np.testing.assert_array_equal(again[1], wedges)
    assert (_wedge_jacobians(top_nodes, wedges) > 0).all()  # every wedge valid
    top = top_nodes[wedges[:, 3:]]
    normal = np.cross(top[:, 1] - top[:, 0], top[:, 2] - top[:, 0])
    assert (normal[:, 2] < 0).all()  # S2 faces the way the articular surface does (down, here)
    # on the sphere within a small share of the 0.5 mm the cartilages overlap under load, its facets fitting the
    # sphere in the mean (not cutting under it by their sagitta, 0.045 mm here)
    centre = np.array([0.0, 0.0, radius])
    on = np.unique(wedges[:, 3:])
    assert np.abs(np.linalg.norm(top_nodes[on] - centre, axis=1) - radius).max() < 0.1
    faces = np.hstack([np.full((len(wedges), 1), 3), wedges[:, 3:]]).ravel()
    cell, foot = pv.PolyData(top_nodes, faces).find_closest_cell(points, return_closest_point=True)
    inside = np.linalg.norm(points[:, :2], axis=1) < 10.0  # away from the outline
    assert abs(float(np.mean(np.einsum("ij,ij->i", points - foot, normal[cell] / np.linalg.norm(normal[cell], axis=1)[:, None])[inside]))) < 0.01
    # coarser: triangles of about SKIN_EDGE_MM instead of 1 mm quads, covering the same area
    edges = np.linalg.norm(top - np.roll(top, 1, axis=1), axis=2)
    assert np.median(edges) == pytest.approx(SKIN_EDGE_MM, rel=0.25)
    area = 0.5 * np.linalg.norm(normal, axis=1).sum()
    assert area == pytest.approx(0.5 * np.linalg.norm(np.cross(points[triangles[:, 1]] - points[triangles[:, 0]],
                                                                 points[triangles[:, 2]] - points[triangles[:, 0]]), axis=1).sum(), rel=0.02)
    assert len(wedges) < 0.3 * len(hexes)


@pytest.mark.parametrize(("radius", "depth"), [(40.0, 0.5), (20.0, 0.3)])
def test_a_rigid_sphere_pressed_into_a_plate_through_contact_skins_meets_the_analytic_force_and_area(tmp_path, radius, depth):
    """A rigid sphere of radius R pressed d into a rigid plane under the linear law p = K overclosure: contact
    where the sphere dips below the plane, area pi (2 R d - d^2), force K times the volume of the dip.  Both
    surfaces as 3 mm contact skins, the solver's real contact (the 1 mm quads of the same layers: force 3-7 %
    low)."""
    bodies = {"PLATE": _plate_layer(), "SPHERE": _cap_layer(radius, sink_mm=depth)}
    w, first, ids = ["*HEADING", "a sphere pressed into a plate through contact skins", "*NODE"], 1, {}
    cells = {}
    for name, (nodes, hexes) in bodies.items():
        top, wedges = skin(*articular_surface(nodes, hexes))
        ids[name] = np.arange(first, first + len(top))
        first += len(top)
        w += [f"{i}, {x:.6f}, {y:.6f}, {z:.6f}" for i, (x, y, z) in zip(ids[name], top)]
        cells[name] = ids[name][wedges]
    ref, rot = first, first + 1
    w += [f"{ref}, 0.0, 0.0, {radius - depth:.6f}", f"{rot}, 0.0, 0.0, {radius - depth:.6f}"]
    element = 1
    for name, conn in cells.items():
        w.append(f"*ELEMENT, TYPE=C3D6, ELSET={name}")
        w += [f"{element + k}, " + ", ".join(str(int(n)) for n in c) for k, c in enumerate(conn)]
        element += len(conn)
        w += set_lines("NSET", f"{name}_NODES", ids[name])
    w += ["*SURFACE, NAME=PLATE_TOP, TYPE=ELEMENT", "PLATE, S2", "*SURFACE, NAME=SPHERE_BOTTOM, TYPE=ELEMENT", "SPHERE, S2",
          "*MATERIAL, NAME=M", "*ELASTIC", "1000.0, 0.3", "*SOLID SECTION, ELSET=PLATE, MATERIAL=M",
          "*SOLID SECTION, ELSET=SPHERE, MATERIAL=M", f"*RIGID BODY, NSET=SPHERE_NODES, REF NODE={ref}, ROT NODE={rot}",
          "*SURFACE INTERACTION, NAME=LAW", "*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR", f"{K:.6e}",
          "*CONTACT PAIR, INTERACTION=LAW, TYPE=SURFACE TO SURFACE", "PLATE_TOP, SPHERE_BOTTOM",
          "*STEP, NLGEOM, INC=100", "*STATIC", "1.0, 1.0", "*BOUNDARY", "PLATE_NODES, 1, 3, 0.0", f"{ref}, 1, 3, 0.0",
          f"{rot}, 1, 3, 0.0", "*CONTACT PRINT, SLAVE=PLATE_TOP, MASTER=SPHERE_BOTTOM", "CF", "*END STEP"]
    (tmp_path / "sphere.inp").write_text("\n".join(w) + "\n")
    run = run_ccx(tmp_path, "sphere", timeout_s=120)
    assert run.completed, run.reason
    contact = parse_dat(tmp_path / "sphere.dat")["contact"][1.0]["PLATE_TOP"]
    r = np.linspace(0.0, np.sqrt(2 * radius * depth - depth ** 2), 20001)
    dip = depth - (radius - np.sqrt(radius ** 2 - r ** 2))
    force = K * float(np.sum(0.5 * (dip[1:] * r[1:] + dip[:-1] * r[:-1]) * np.diff(r))) * 2 * np.pi
    assert contact["area"] == pytest.approx(np.pi * (2 * radius * depth - depth ** 2), rel=0.04)
    assert -contact["normal_force"] == pytest.approx(force, rel=0.03)


def _skin_count(radius: float) -> int:
    nodes, hexes = _cap_layer(radius)
    return len(skin(*articular_surface(nodes, hexes))[1])


def test_a_skin_is_built_in_a_process_forked_from_one_that_built_one():
    """A job's pool forks its workers from a process that may have written decks already; a library whose
    threads do not survive a fork (pykdtree's OpenMP) hung the child for ever."""
    import multiprocessing

    expected = _skin_count(25.0)  # the parent builds one first: its thread pools, if any, now exist
    with multiprocessing.get_context("fork").Pool(1) as pool:
        assert pool.apply_async(_skin_count, (25.0,)).get(timeout=60) == expected
