"""Rays of the unit frame (docs/method.md 1.2, 5.4).

Ray distance (``z`` along a unit direction) exists only inside ``render/``; everything leaving it is
z-depth (docs/architecture.md "Conventions"): z-depth = cos * ray distance, with ``cos`` the
z-component of the unit camera-frame direction.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from svolsdf.scene.cameras import Cameras

__all__ = ["RayBundle", "sphere_intersections", "rays_from_cameras"]


@dataclass
class RayBundle:
    """R rays in the unit frame.

    Attributes:
        origins: (R, 3) camera centres.
        dirs: (R, 3) unit world directions.
        cos: (R,) z-component of the unit camera-frame direction (z-depth = cos * distance).
        near: (R,) start distance.
        far: (R,) end distance.
        view: (R,) long index of the camera (into the ``Cameras`` the rays came from).
        uv: (R, 2) pixel coordinates (u = column, v = row; integer = pixel centre).
    """

    origins: Tensor
    dirs: Tensor
    cos: Tensor
    near: Tensor
    far: Tensor
    view: Tensor
    uv: Tensor

    def __post_init__(self) -> None:
        R = self.origins.shape[0]
        for name, shape in [("origins", (R, 3)), ("dirs", (R, 3)), ("cos", (R,)), ("near", (R,)),
                            ("far", (R,)), ("view", (R,)), ("uv", (R, 2))]:
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(
                    f"RayBundle.{name} must be {shape}, got {tuple(getattr(self, name).shape)}"
                )

    def __len__(self) -> int:
        return self.origins.shape[0]

    def __getitem__(self, idx) -> RayBundle:
        return RayBundle(*(getattr(self, f)[idx] for f in
                           ("origins", "dirs", "cos", "near", "far", "view", "uv")))

    def to(self, device=None) -> RayBundle:
        return RayBundle(*(getattr(self, f).to(device) for f in
                           ("origins", "dirs", "cos", "near", "far", "view", "uv")))

    @property
    def device(self) -> torch.device:
        return self.origins.device


def sphere_intersections(origins: Tensor, dirs: Tensor, radius: float) -> tuple[Tensor, Tensor]:
    """Distances where rays o + t d (|d| = 1) enter and leave the sphere |x| = radius.

    Solves t^2 + 2 t (o.d) + |o|^2 - R^2 = 0. Rays that miss get the tangent point's distance
    for both (the discriminant is clamped at 0).

    Args:
        origins, dirs: (R, 3).

    Returns:
        t_in, t_out: (R,) with t_in <= t_out (t_in < 0 when the origin is inside).
    """
    od = (origins * dirs).sum(-1)
    disc = (od**2 - (origins**2).sum(-1) + radius**2).clamp_min(0.0)
    root = disc.sqrt()
    return -od - root, -od + root


def rays_from_cameras(
    cameras: Cameras,
    view: Tensor | int,
    uv: Tensor | None = None,
    radius: float = 3.0,
    near: float = 1e-4,
    near_mode: str = "fixed",
    far_mode: str = "sphere",
) -> RayBundle:
    """Rays through pixels of unit-frame cameras (``Scene.cameras_unit``).

    Args:
        cameras: unit-frame cameras (V views).
        view: (R,) long view index per ray, or one int for all rays.
        uv: (R, 2) pixel coordinates; default every pixel centre of that one view, row-major
            (then ``view`` must be an int).
        radius: bounding-sphere radius (docs/method.md 5.2: 3).
        near: the smallest start distance (docs/method.md 0: near = 1e-4).
        near_mode: "fixed" (near, the paper) or "sphere" (max(near, sphere entry)).
        far_mode: "sphere" (the far sphere intersection, default) or "fixed" (2 * radius, as
            VolSDF on DTU, docs/method.md 5.4).

    Returns:
        RayBundle of R rays.
    """
    if near_mode not in ("fixed", "sphere") or far_mode not in ("sphere", "fixed"):
        raise ValueError(f"rays_from_cameras: bad near_mode {near_mode!r} or far_mode {far_mode!r}")
    device = cameras.device
    if uv is None:
        if not isinstance(view, int):
            raise ValueError("rays_from_cameras: give one int view when uv is None")
        uv = cameras.pixel_grid(dtype=cameras.K.dtype).reshape(-1, 2)
    if uv.ndim != 2 or uv.shape[-1] != 2:
        raise ValueError(f"rays_from_cameras: uv must be (R, 2), got {tuple(uv.shape)}")
    R = uv.shape[0]
    view_t = (torch.full((R,), view, dtype=torch.long, device=device) if isinstance(view, int)
              else view.to(device=device, dtype=torch.long))
    if view_t.shape != (R,):
        raise ValueError(
            f"rays_from_cameras: view must be (R,) = ({R},), got {tuple(view_t.shape)}"
        )
    K = cameras.K[view_t]
    w2c = cameras.w2c[view_t]
    uvh = torch.cat([uv.to(K.dtype), torch.ones_like(uv[:, :1], dtype=K.dtype)], dim=-1)
    d_cam = torch.linalg.solve(K, uvh[..., None])[..., 0]  # K^-1 (u, v, 1)
    d_cam = d_cam / d_cam.norm(dim=-1, keepdim=True)
    Rm = w2c[:, :3, :3]
    t = w2c[:, :3, 3]
    dirs = (Rm.transpose(1, 2) @ d_cam[..., None])[..., 0]
    origins = -(Rm.transpose(1, 2) @ t[..., None])[..., 0]
    t_in, t_out = sphere_intersections(origins, dirs, radius)
    near_t = torch.full((R,), near, dtype=dirs.dtype, device=device)
    if near_mode == "sphere":
        near_t = torch.maximum(near_t, t_in)
    far_t = t_out if far_mode == "sphere" else torch.full_like(near_t, 2.0 * radius)
    far_t = torch.maximum(far_t, near_t + 1e-4)
    f32 = torch.float32
    return RayBundle(origins.to(f32), dirs.to(f32), d_cam[:, 2].to(f32), near_t.to(f32),
                     far_t.to(f32), view_t, uv.to(f32))
