"""On-disk scene formats. Each module offers ``detect(path) -> bool`` and
``read(path, lighting) -> SceneSource`` (cameras and file lists, no pixels); `svolsdf.scene.loaders`
turns a `SceneSource` into a `Scene`."""

from svolsdf.scene.formats import colmap, dtu_raw, idr, mvsnet, nerf
from svolsdf.scene.formats._common import SceneSource

__all__ = ["FORMATS", "SceneSource", "colmap", "dtu_raw", "idr", "mvsnet", "nerf"]

# Detection order: the most specific layouts first.
FORMATS = {"idr": idr, "dtu_raw": dtu_raw, "mvsnet": mvsnet, "colmap": colmap, "nerf": nerf}
