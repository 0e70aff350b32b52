"""The `Scene`: images, masks, cameras, view ids, source-view pairs, depth ranges, normalization.

Readers (``svolsdf.scene.loaders``) return a `Scene`; nothing downstream knows the file format.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from svolsdf.errors import InputError
from svolsdf.scene.cameras import Cameras

__all__ = ["Normalization", "Scene", "SceneError"]


class SceneError(InputError):
    """Bad scene input. The message names the file and the problem."""


@dataclass
class Normalization:
    """A similarity between the world frame and the unit frame the field works in.

    x_unit = (x_world - center) / scale and x_world = scale * x_unit + center; this is the
    inverse of IDR's ``scale_mat`` = [[s, 0, 0, cx], [0, s, 0, cy], [0, 0, s, cz], [0, 0, 0, 1]]
    (docs/method.md 1.2). The region of interest lies inside the sphere of radius ``radius``.

    Attributes:
        center: (3,) float64 world coordinates of the unit frame's origin.
        scale: world units per unit.
        radius: bounding-sphere radius in the unit frame (VolSDF: 3).
    """

    center: Tensor
    scale: float
    radius: float = 3.0

    def to_unit(self, x: Tensor) -> Tensor:
        """(..., 3) world points -> (..., 3) unit-frame points."""
        c = self.center.to(device=x.device, dtype=x.dtype)
        return (x - c) / self.scale

    def to_world(self, x: Tensor) -> Tensor:
        """(..., 3) unit-frame points -> (..., 3) world points."""
        c = self.center.to(device=x.device, dtype=x.dtype)
        return x * self.scale + c

    @property
    def scale_mat(self) -> Tensor:
        """(4, 4) float64 IDR scale_mat (unit -> world)."""
        m = torch.eye(4, dtype=torch.float64)
        m[:3, :3] *= self.scale
        m[:3, 3] = self.center.to(torch.float64)
        return m


@dataclass
class Scene:
    """A set of calibrated views of one object.

    Attributes:
        images: (V, 3, H, W) float32 in [0, 1], or None when loaded without pixels (``info``).
        cameras: `Cameras` in world units at the working image size.
        view_ids: V view ids as in the source data (e.g. DTU 0..48).
        masks: (V, 1, H, W) float32 in {0, 1} (1 = object), or None.
        pairs: view id -> source view ids, best first (from pair.txt or computed); may name views
            that were not loaded.
        depth_range: (V, 2) float64 z-depth [near, far] per view, world units.
        normalization: world <-> unit frame similarity.
        path: the scene folder.
        format: the detected on-disk format ("idr", "dtu_raw", "mvsnet", "colmap", "nerf").
        units: world units ("mm" for DTU, otherwise "unknown" unless the format says).
        image_paths: V source image files.
        extras: format-specific facts (e.g. the DTU scan number, ObsMask path, gt files).
    """

    images: Tensor | None
    cameras: Cameras
    view_ids: list[int]
    masks: Tensor | None
    pairs: dict[int, list[int]]
    depth_range: Tensor
    normalization: Normalization
    path: Path = Path(".")
    format: str = "unknown"
    units: str = "unknown"
    image_paths: list[Path] = field(default_factory=list)
    extras: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.view_ids)

    @property
    def height(self) -> int:
        return self.cameras.height

    @property
    def width(self) -> int:
        return self.cameras.width

    @property
    def cameras_unit(self) -> Cameras:
        """Cameras in the unit frame (depths divided by ``normalization.scale``)."""
        return self.cameras.transformed(self.normalization.center, self.normalization.scale)

    def index(self, view_id: int) -> int:
        """Position of ``view_id`` in this scene; raises SceneError naming the known ids."""
        try:
            return self.view_ids.index(int(view_id))
        except ValueError:
            raise SceneError(
                f"{self.path}: view id {view_id} does not exist "
                f"(available: {_id_summary(self.view_ids)})"
            ) from None

    def select(self, view_ids: list[int]) -> Scene:
        """A scene with only ``view_ids``, in that order (pairs keep all ids)."""
        idx = [self.index(v) for v in view_ids]
        return replace(
            self,
            images=None if self.images is None else self.images[idx],
            masks=None if self.masks is None else self.masks[idx],
            cameras=self.cameras[idx],
            view_ids=[int(v) for v in view_ids],
            depth_range=self.depth_range[idx],
            image_paths=[self.image_paths[i] for i in idx] if self.image_paths else [],
        )

    def resize(self, width: int, height: int) -> Scene:
        """The scene at another image size (bicubic images, nearest masks)."""
        if (width, height) == (self.width, self.height):
            return self
        images = masks = None
        if self.images is not None:
            images = F.interpolate(
                self.images, size=(height, width), mode="bicubic", align_corners=False,
                antialias=height < self.height,
            ).clamp(0, 1)
        if self.masks is not None:
            masks = (
                F.interpolate(self.masks, size=(height, width), mode="bilinear",
                              align_corners=False, antialias=height < self.height)
                > 0.5
            ).float()
        return replace(self, images=images, masks=masks,
                       cameras=self.cameras.resize(width, height))

    def images_at(self, width: int, height: int, from_files: bool = True) -> Tensor:
        """The images at another size, e.g. a backbone's MVS size (`svolsdf.mvs.backbone.mvs_size`).

        Larger than the working size, and with ``from_files``, the images are read again from
        ``image_paths`` and resized from the files' size (bicubic, antialiased when shrinking, as
        docs/method.md 1.3), when the files are larger than the working size: a 1600x1200 DTU photo
        gives its own detail at 1536x1152 instead of the working 768x576 upsampled. Otherwise (or
        when the files are gone) they are resized from the working-size images: bicubic when
        enlarging (the released code's x2_mvsres, docs/method.md 9.2.2), antialiased when shrinking.

        Args:
            width, height: the size in pixels.
            from_files: allow reading the files (False: always from the working-size images).

        Returns:
            (V, 3, height, width) float32 in [0, 1]; ``images`` itself at the working size.
        """
        if self.images is None:
            raise InputError(f"{self.path}: the scene was loaded without images")
        if (width, height) == (self.width, self.height):
            return self.images
        native = self.extras.get("native_size")
        enlarge = width > self.width or height > self.height
        if (from_files and enlarge and native is not None and len(self.image_paths) == len(self)
                and native[0] > self.width and native[1] > self.height
                and all(Path(p).is_file() for p in self.image_paths)):
            from svolsdf.io.images import read_image, resize_image

            background = self.extras.get("background")
            out = torch.empty(len(self), 3, height, width, dtype=torch.float32)
            for k, p in enumerate(self.image_paths):
                img = read_image(p, background)
                if tuple(img.shape[-2:]) != (native[1], native[0]):
                    raise SceneError(f"{p} is now {img.shape[-1]}x{img.shape[-2]}, but the scene "
                                     f"was loaded from {native[0]}x{native[1]} files")
                out[k] = resize_image(img, width, height)
            return out
        return F.interpolate(self.images.float(), size=(height, width), mode="bicubic",
                             align_corners=False, antialias=not enlarge).clamp(0, 1)

    def source_views(self, ref_id: int, candidates: list[int] | None = None) -> list[int]:
        """Source views for ``ref_id`` among ``candidates`` (default: the loaded views).

        Order as MVSNet datasets do (docs/method.md 1.4): candidates in pair order first, then the
        remaining candidates in their given order.
        """
        candidates = [v for v in (candidates or self.view_ids) if v != ref_id]
        ranked = [v for v in self.pairs.get(int(ref_id), []) if v in candidates]
        return ranked + [v for v in candidates if v not in ranked]


def _id_summary(ids: list[int]) -> str:
    ids = sorted(ids)
    if len(ids) > 2 and ids == list(range(ids[0], ids[-1] + 1)):
        return f"{ids[0]}..{ids[-1]}"
    return ", ".join(str(i) for i in ids)
