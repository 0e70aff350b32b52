"""svolsdf.fusion: depth-map filtering and fusion (`filter`), mesh extraction (`mesh`)."""

from svolsdf.fusion.filter import (
    FusedPoints,
    FusionConfig,
    check_geometric_consistency,
    fuse_depth_maps,
)
from svolsdf.fusion.mesh import extract_mesh, largest_component, save_mesh, to_world

__all__ = [
    "FusedPoints",
    "FusionConfig",
    "check_geometric_consistency",
    "extract_mesh",
    "fuse_depth_maps",
    "largest_component",
    "save_mesh",
    "to_world",
]
