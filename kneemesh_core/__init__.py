"""KneeMesh science library: knee label maps and MRI in, FE-ready knee models out.

The sub-packages follow the pipeline: ``io`` (volumes in physical LPS space),
``tissues`` and ``knee`` (the knee's tissues, label conventions and canonical
labels), ``side`` (left/right and medial/lateral), ``segmentation`` (the ONNX
network for DESS images), ``surfaces`` (triangle surfaces and bone meshes),
``hexmesh`` (all-hexahedral cartilage, blended into the bone), ``phantom``
(synthetic knees), ``geometry`` (small vector helpers), and ``job`` (the one
definition of the job that the CLI and the workers share).  No web or queue code
lives here.
"""

from kneemesh_core.errors import KneeMeshError

__version__ = "0.1.0"
__all__ = ["KneeMeshError", "__version__"]
