"""Triangle surfaces of every tissue and FE-ready bone meshes, in LPS mm.

Steps, in order: :mod:`.masks` (closing, largest component), :mod:`.isosurface`
(flying-edges marching cubes, windowed-sinc smoothing, decimation, outward
normals), :mod:`.bones` (repair, ACVD uniform remeshing, closed shells) and
:mod:`.metrics` (watertightness, manifoldness, self-intersections, accuracy).
"""

from kneemesh_core.surfaces.bones import bone_mesh
from kneemesh_core.surfaces.isosurface import mask_surface
from kneemesh_core.surfaces.masks import CleanMask, clean_mask

__all__ = ["bone_mesh", "mask_surface", "clean_mask", "CleanMask"]
