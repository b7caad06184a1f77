"""Reading and writing knee volumes in physical LPS space (mm)."""

from kneemesh_core.io.volumes import (
    Volume,
    read_volume,
    read_label_map,
    write_image,
    voxel_to_lps,
    voxel_volume_ml,
)

__all__ = ["Volume", "read_volume", "read_label_map", "write_image", "voxel_to_lps", "voxel_volume_ml"]
