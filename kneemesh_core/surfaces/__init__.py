"""Triangle surfaces of every tissue and FE-ready bone meshes, in LPS mm.

Steps, in order: :mod:`.masks` (closing, largest component), :mod:`.isosurface`
(flying-edges marching cubes, windowed-sinc smoothing, decimation, outward
normals), :mod:`.bones` (repair, ACVD uniform remeshing, closed shells) and
:mod:`.metrics` (watertightness, manifoldness, self-intersections, accuracy); :mod:`.tissue` the
recipes per tissue, :mod:`.options` what they can be asked for.

The names below load on first use, so that :mod:`.masks` or :mod:`.options` alone (reading a
knee's labels, a job's options) loads no VTK filters or remeshing.
"""

import importlib

#: name -> the module that defines it
_EXPORTS = {"bone_mesh": "bones", "mask_surface": "isosurface", "clean_mask": "masks", "CleanMask": "masks"}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
