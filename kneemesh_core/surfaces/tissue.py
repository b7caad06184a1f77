"""One tissue from canonical labels to its output mesh and its report entry."""

from __future__ import annotations

import dataclasses
import pyvista as pv
import SimpleITK as sitk

from kneemesh_core.surfaces.bones import bone_mesh
from kneemesh_core.surfaces.isosurface import mask_surface
from kneemesh_core.surfaces.masks import clean_mask
from kneemesh_core.surfaces.metrics import edges_mm, surface_distance, topology
from kneemesh_core.tissues import BONES, LABEL


@dataclasses.dataclass(frozen=True)
class SurfaceOptions:
    """Surface and bone meshing parameters (the paper's defaults)."""

    bone_edge_mm: float = 3.0
    # The paper closes bone with a 3-voxel kernel. On manual OAI labels that fills the
    # slice-to-slice jaggedness and pushes the surface outwards: 42 real knees measured
    # 0.189 -> 0.179 mm mean and 0.527 -> 0.500 mm p95 distance to the label without it.
    # Internal cavities are filled instead; set 3 for the paper's behaviour.
    bone_closing_voxels: int = 0
    bone_smoothing_iterations: int = 10
    bone_pass_band: float = 0.1
    cartilage_closing_voxels: int = 5
    cartilage_decimation: float = 0.8


def label_surface(labels: sitk.Image, tissue: str) -> pv.PolyData:
    """The label boundary itself: marching cubes of the raw label, no closing or smoothing."""
    cm = clean_mask(labels, LABEL[tissue], 0, tissue)
    return mask_surface(cm, smoothing_iterations=0, decimation=0)


def reconstruct(labels: sitk.Image, tissue: str, opts: SurfaceOptions) -> tuple[pv.PolyData, dict]:
    """Bone shell or cartilage surface of one tissue, with its report facts.

    Bones: closing, largest component, isosurface, ACVD shell, checked for
    closedness, manifoldness, self-intersections and distance to the label.
    Cartilage: closing, largest component, isosurface, 80% decimation;
    holes (full-thickness defects) are kept, only orientation is fixed.
    """
    is_bone = tissue in BONES
    closing = opts.bone_closing_voxels if is_bone else opts.cartilage_closing_voxels
    cm = clean_mask(labels, LABEL[tissue], closing, tissue, fill_holes=is_bone)
    facts = {"label_volume_ml": round(cm.label_ml, 4), "discarded_ml": round(cm.discarded_ml, 4),
             "components": cm.n_components}
    if is_bone:
        smooth = mask_surface(cm, decimation=0.0, smoothing_iterations=opts.bone_smoothing_iterations,
                              pass_band=opts.bone_pass_band)
        mesh = bone_mesh(smooth, opts.bone_edge_mm)
        e = edges_mm(mesh)
        facts.update(topology(mesh))
        facts["edge_mm"] = {"mean": round(float(e.mean()), 3), "min": round(float(e.min()), 3),
                            "max": round(float(e.max()), 3)}
        sd = surface_distance(mesh, label_surface(labels, tissue))
        facts["surface_distance_mm"] = {k: round(v, 4) for k, v in sd.items()}
    else:
        mesh = mask_surface(cm, decimation=opts.cartilage_decimation)
        facts["open_edges"] = int(mesh.n_open_edges)
    facts.update(n_points=int(mesh.n_points), n_cells=int(mesh.n_cells), volume_ml=round(float(abs(mesh.volume)) / 1000, 4))
    return mesh, facts
