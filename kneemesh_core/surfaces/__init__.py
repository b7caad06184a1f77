"""Triangle surfaces of every tissue and FE-ready bone meshes, in LPS mm.

Steps, in order: :mod:`.masks` (closing, largest component), :mod:`.isosurface`
(flying-edges marching cubes, windowed-sinc smoothing, decimation, outward
normals), :mod:`.bones` (repair, ACVD uniform remeshing, closed shells) and
:mod:`.metrics` (watertightness, manifoldness, self-intersections, accuracy); :mod:`.tissue` the
recipes per tissue, :mod:`.options` what they can be asked for.

The names below load on first use, so that :mod:`.masks` or :mod:`.options` alone (reading a
knee's labels, a job's options) loads no VTK filters or remeshing.
"""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(__name__, submod_attrs={
    "bones": ["bone_mesh"], "isosurface": ["mask_surface"], "masks": ["CleanMask", "clean_mask"]})
