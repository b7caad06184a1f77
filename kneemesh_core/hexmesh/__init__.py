"""All-hexahedral cartilage meshes by swept projection (Rodriguez-Vila 2017, Gibbons 2022).

The steps, one module each, in the order they run:

1. :mod:`.domain` - a projection domain per tissue: a cylinder about the
   condylar axis (femoral) or the superior-inferior axis (patellar), a plane
   (each tibial plate);
2. :mod:`.rays` - Embree rays on a fine 2-D grid give the bone-side and
   articular heights of the reconstructed cartilage surface;
3. :mod:`.footprint` - where the cartilage is: a cleaned, smoothed 2-D mask
   (holes kept) and its signed distance;
4. :mod:`.quadmesh` - a regular quad lattice inside, a pillowed ring on the
   contour: boundary-conforming, no staircase, no collapsed elements;
5. :mod:`.extrude` (with :mod:`.optimize`) - bone-side nodes along each ray,
   columns chosen to maximise the worst element, layers between;
6. :mod:`.quality` and :mod:`.fidelity` - the gate, and how well the mesh
   represents the cartilage, against the targets of :mod:`.targets`;
7. :mod:`.blend` - the edge blended into the bone and the bone side fused onto
   it; :mod:`.conform` - the bone gives way where a cartilage still dips into it.

:mod:`.mesher` runs steps 1-6 with a fallback chain (:func:`mesh_cartilage`) and
checks the blend (:func:`blend_cartilage`); :mod:`.options` holds what each can be asked for.

The names below load on first use: importing :mod:`.options` or :mod:`.targets` alone (the job's
options, the verdicts) loads no meshing code, so a runner can start its workers, which import the
mesher, while it reads the input (:mod:`kneemesh_core.job.local`).
"""

import importlib

#: name -> the module that defines it
_EXPORTS = {"BlendOptions": "options", "HexOptions": "options", "CartilageMesh": "mesher", "FALLBACKS": "mesher",
            "NARROWING": "mesher", "WIDENING": "mesher", "blend_cartilage": "mesher", "mesh_cartilage": "mesher"}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
