"""What a cartilage mesh and its blend can be asked for: the options of :mod:`.mesher` and
:mod:`.blend`, plain frozen dataclasses (a job carries them as dicts; importing them loads no
meshing code)."""

from __future__ import annotations

import dataclasses

from kneemesh_core.hexmesh.targets import MIN_SCALED_JACOBIAN


@dataclasses.dataclass(frozen=True)
class HexOptions:
    """Cartilage meshing parameters (the paper's: ~1 mm in-plane, 4 layers)."""

    element_size: float = 1.0
    layers: int = 4
    # The paper closes cartilage with a 5-voxel kernel; on manual OAI segmentations that adds
    # ~7% volume. The footprint already fills sub-millimetre cracks, so closing is a fallback here.
    closing_voxels: int = 0
    min_component_ml: float = 0.005
    ray_step_fraction: float = 0.25  # ray grid spacing as a fraction of the element size
    inset: float = 0.5  # lattice cells sit this many elements inside the contour
    min_thickness: float = 0.2
    edge_fraction: float = 0.2  # the contour runs where thickness is this fraction of the median
    max_slope_deg: float = 65.0  # or where the rim rolls over steeper than this
    fold_slope_deg: float = 80.0  # the footprint is cut where the rays jump this steeply (folds)
    pass_band: float = 0.02  # windowed-sinc smoothing of the cartilage surface (smaller: smoother)
    probe_inset: float = 0.0  # contour nodes read heights this many elements inside (folded rims)
    fallbacks: bool = True  # try the FALLBACKS when the first attempt misses the gate or a fidelity target


@dataclasses.dataclass(frozen=True)
class BlendOptions:
    """Edge blending and bone fusion parameters (:mod:`.blend`)."""

    angle_deg: float = 45.0
    bone_share: float = 0.8
    rings: int = 3
    edge_height: float = 0.3
    edge_floor: float = MIN_SCALED_JACOBIAN  # the outermost ring's floor while blending
    fuse_max_mm: float = 1.5
    max_backoffs: int = 10
    backoffs_per_column: int = 5
