"""KneeMesh science library: knee label maps and MRI in, FE-ready knee models out.

The sub-packages follow the pipeline: ``io`` (volumes in physical LPS space),
``tissues`` (the knee's tissues and label conventions), ``side`` (left/right and
medial/lateral), ``phantom`` (synthetic knees), ``surfaces`` (triangle surfaces
and bone meshes), ``pipeline`` (the one definition of the job that the CLI and
the workers share).  No web or queue code lives here.
"""

from kneemesh_core.errors import KneeMeshError

__version__ = "0.1.0"
__all__ = ["KneeMeshError", "__version__"]
