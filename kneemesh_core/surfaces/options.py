"""What a bone surface can be asked for: the options of :mod:`.tissue`, a plain frozen dataclass
(a job carries it as a dict; importing it loads no surface code)."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class SurfaceOptions:
    """Bone meshing parameters (the paper's defaults)."""

    bone_edge_mm: float = 3.0
    # The paper closes bone with a 3-voxel kernel. On manual OAI labels that fills the
    # slice-to-slice jaggedness and pushes the surface outwards: 42 real knees measured
    # 0.189 -> 0.179 mm mean and 0.527 -> 0.500 mm p95 distance to the label without it.
    # Internal cavities are filled instead; set 3 for the paper's behaviour.
    bone_closing_voxels: int = 0
    bone_smoothing_iterations: int = 10
    bone_pass_band: float = 0.1
