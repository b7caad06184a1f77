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
checks the blend (:func:`blend_cartilage`).
"""

from kneemesh_core.hexmesh.blend import BlendOptions
from kneemesh_core.hexmesh.mesher import (FALLBACKS, NARROWING, WIDENING, CartilageMesh, HexOptions, blend_cartilage,
                                          mesh_cartilage)

__all__ = ["BlendOptions", "CartilageMesh", "FALLBACKS", "HexOptions", "NARROWING", "WIDENING", "blend_cartilage",
           "mesh_cartilage"]
