"""Geometry helpers shared by several stages: the reprojection check of depth maps
(`reproject`) and object-mask dilation and resizing (`masks`).

They sit below every stage (docs/architecture.md, "Dependencies point down this table"): this
package imports only `svolsdf.scene`, and `mvs`, `field`, `render`, `ibr`, `fusion` may import it.
"""

from svolsdf.geometry.masks import dilate_mask, mask_to_depth_resolution
from svolsdf.geometry.reproject import (
    check_geometric_consistency,
    check_geometric_consistency_reference,
)

__all__ = [
    "check_geometric_consistency",
    "check_geometric_consistency_reference",
    "dilate_mask",
    "mask_to_depth_resolution",
]
