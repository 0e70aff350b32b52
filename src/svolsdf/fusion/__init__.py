"""svolsdf.fusion: depth-map filtering and fusion (`filter`), mesh extraction and operations on
meshes (`mesh_ops`), culling (`cull`), the reconstruction's mesh recipes (`meshing`) and the
mesh methods by name (`mesh_methods`)."""

from svolsdf.fusion.filter import FusedPoints, FusionFilterConfig, fuse_depth_maps
from svolsdf.fusion.mesh_ops import extract_mesh, largest_component, save_mesh, to_world

__all__ = [
    "FusedPoints",
    "FusionFilterConfig",
    "extract_mesh",
    "fuse_depth_maps",
    "largest_component",
    "save_mesh",
    "to_world",
]
