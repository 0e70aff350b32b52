"""Image-based rendering with Laplacian-pyramid blending (docs/method.md 7) and orbit camera
paths."""

from svolsdf.ibr.blend import (
    IBRConfig,
    IBRResult,
    erode,
    fill_candidates,
    ibr_render,
    laplacian_blend,
    push_pull_fill,
    view_softmax_weights,
    warp_sources,
)
from svolsdf.ibr.path import (
    look_at_point,
    look_at_rotation,
    orbit_cameras,
    slerp_rotation,
    slerp_unit,
)

__all__ = [
    "IBRConfig",
    "IBRResult",
    "erode",
    "fill_candidates",
    "ibr_render",
    "laplacian_blend",
    "look_at_point",
    "look_at_rotation",
    "orbit_cameras",
    "push_pull_fill",
    "slerp_rotation",
    "slerp_unit",
    "view_softmax_weights",
    "warp_sources",
]
