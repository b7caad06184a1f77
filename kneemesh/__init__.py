"""The ``kneemesh`` application: the command line over :mod:`kneemesh_core`."""

from pathlib import Path

SAMPLE_LABELS = Path(__file__).parent / "data" / "right_knee_example.nrrd"
