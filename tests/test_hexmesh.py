"""All-hex cartilage meshes on a real knee: the quality gate, fidelity, node order, outputs."""

from __future__ import annotations

import json

import numpy as np
import pytest
import pyvista as pv

from conftest import SAMPLE, real
from kneemesh_core.hexmesh import mesh_cartilage
from kneemesh_core.hexmesh.optimize import scaled_jacobian
from kneemesh_core.hexmesh.quality import hex_quality, passes_gate, to_grid
from kneemesh_core.knee import load_knee
from kneemesh_core.pipeline import JobOptions, run


@pytest.fixture(scope="module")
def sample():
    return load_knee(real(SAMPLE))


@pytest.mark.parametrize("tissue", ["medial_tibial_cartilage", "lateral_tibial_cartilage", "patellar_cartilage"])
def test_plates_and_patella_pass_gate_and_fidelity(sample, tissue):
    cm = mesh_cartilage(sample.labels, tissue)
    f = cm.facts
    assert f["gate_passed"], f
    assert f["min_scaled_jacobian"] >= 0.5 and f["collapsed"] == 0 and f["inverted"] == 0
    assert f["frac_edge_ratio_above_6"] <= 0.001
    assert abs(f["volume_error"]) <= 0.05 and f["coverage"] >= 0.97
    assert f["surface_deviation_mm"]["median"] <= 0.15 and f["surface_deviation_mm"]["p95"] <= 0.5
    assert f["n_layers"] == 4 and 0.85 <= f["element_size_mm"] <= 1.2
    # every column has exactly four layers: hexes = 4 x quads, nodes = 5 x nodes per layer
    assert len(cm.mesh.hexes) % 4 == 0 and len(cm.mesh.points) % 5 == 0
    g = cm.grid()
    assert set(g.cell_data) >= {"scaled_jacobian", "layer", "ring"}
    assert set(g.point_data) >= {"bone_side", "articular", "edge"}


def test_femoral_cartilage_meets_gate_with_fallbacks(sample):
    f = mesh_cartilage(sample.labels, "femoral_cartilage").facts
    assert f["gate_passed"] and f["min_scaled_jacobian"] >= 0.5, f
    assert f["coverage"] >= 0.97 and abs(f["volume_error"]) <= 0.05
    assert f["domain"]["kind"] == "cylinder" and abs(f["domain"]["axis"][0]) > 0.9  # condylar axis ~ left-right


def test_numpy_scaled_jacobian_matches_verdict():
    rng = np.random.default_rng(0)
    cube = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    pts = np.concatenate([cube + rng.normal(0, 0.15, cube.shape) + 3 * i for i in range(50)])
    hexes = np.arange(len(pts)).reshape(-1, 8)
    verdict = to_grid(pts, hexes).cell_quality("scaled_jacobian").cell_data["scaled_jacobian"]
    np.testing.assert_allclose(scaled_jacobian(pts, hexes), verdict, atol=1e-9)


def test_quality_catches_what_verdict_misses():
    cube = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    collapsed = np.array([[0, 1, 2, 3, 4, 5, 6, 6]])  # a wedge disguised as a hex: Verdict says 1e30
    q = hex_quality(cube, collapsed)
    assert q["collapsed"][0] and q["scaled_jacobian"][0] < 0
    flat = cube * [1, 1, 0.05]  # SJ is blind to aspect ratio; the edge ratio is not
    q = hex_quality(flat, np.arange(8)[None])
    assert q["scaled_jacobian"][0] == pytest.approx(1.0) and q["max_edge_ratio"][0] == pytest.approx(20.0)
    assert not passes_gate({"min_scaled_jacobian": 1.0, "collapsed": 0, "inverted": 0, "frac_edge_ratio_above_6": 1.0})


def test_pipeline_writes_vtu_in_physical_space(tmp_path, sample):
    report = run(real(SAMPLE), tmp_path, JobOptions(only="cartilage"), workers=2)
    e = report["tissues"]["lateral_tibial_cartilage"]
    assert e["status"] == "ok"
    for key in ("n_layers", "element_size_mm", "min_scaled_jacobian", "frac_sj_below_0_5", "max_edge_ratio",
                "collapsed", "volume_ml", "label_volume_ml", "coverage", "surface_deviation_mm", "fallbacks", "seconds"):
        assert key in e, key
    g = pv.read(tmp_path / "meshes" / "lateral_tibial_cartilage.vtu")
    assert g.celltypes.tolist() == [pv.CellType.HEXAHEDRON] * g.n_cells
    # C3D8 node order: positive Jacobians as stored
    assert g.cell_quality("scaled_jacobian").cell_data["scaled_jacobian"].min() >= 0.5
    # physical LPS mm: the mesh sits on the lateral plate (right knee: lateral faces -x)
    mtc = pv.read(tmp_path / "meshes" / "medial_tibial_cartilage.vtu")
    assert g.center[0] < mtc.center[0]
    assert json.loads((tmp_path / "report.json").read_text())["input"]["side"] == "right"
