"""Pinhole cameras in the OpenCV convention.

Conventions (docs/architecture.md, "Conventions"; written once here and kept everywhere):

- Axes: x right, y down, z forward (OpenCV). Extrinsics are world-to-camera 4x4 matrices.
- Pixel centres sit at integer coordinates: pixel (u, v) = (column, row) covers
  [u - 0.5, u + 0.5] x [v - 0.5, v + 0.5]. DTU and MVSNet calibrations assume this; so does
  docs/method.md 1.2 ("pixels are integer coordinates (u, v) with no +0.5").
- Resizing an image by s (per axis) scales the focal lengths (and skew) by s and maps the
  principal point as c' = s (c + 0.5) - 0.5, so that the image borders stay where they are.
- Depth is z-depth in the camera frame (world units unless said otherwise).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["Cameras", "decompose_projection"]


def decompose_projection(P: Tensor) -> tuple[Tensor, Tensor]:
    """Split a projection matrix P = K [R | t] into K and the world-to-camera matrix.

    Same result as OpenCV's ``decomposeProjectionMatrix`` followed by docs/method.md 1.2's
    normalization (K[2,2] = 1, skew kept), computed with an RQ decomposition.

    Args:
        P: (3, 4) or (4, 4) projection matrix (only the top 3 rows are used), float64 preferred.

    Returns:
        K: (3, 3) upper-triangular intrinsics with positive focal lengths and K[2,2] = 1.
        w2c: (4, 4) world-to-camera matrix [R | t; 0 0 0 1] with det(R) = +1.

    Raises:
        ValueError: if P is not finite or its left 3x3 block is singular.
    """
    P = torch.as_tensor(P, dtype=torch.float64)[:3, :4]
    if not torch.isfinite(P).all():
        raise ValueError("projection matrix has non-finite entries")
    # P is defined up to scale: divided by its largest entry, a P of any magnitude (1e300 P is
    # the camera P) is decomposed without overflow
    scale = float(P[:, :3].abs().max())
    if scale == 0.0:
        raise ValueError("projection matrix is singular (its left 3x3 block is zero)")
    P = P / scale
    if not torch.isfinite(P).all():
        raise ValueError("projection matrix's translation is beyond float64 range relative to "
                         "its left 3x3 block")
    M = P[:, :3]
    if abs(float(torch.linalg.det(M))) < 1e-12:
        raise ValueError("projection matrix is singular (its left 3x3 block has rank < 3)")
    # RQ decomposition of M via QR of the flipped transpose.
    flip = torch.flip(torch.eye(3, dtype=M.dtype), dims=[0])
    q, r = torch.linalg.qr((flip @ M).T)
    K = flip @ r.T @ flip
    R = flip @ q.T
    # Make the diagonal of K positive.
    sign = torch.diag(torch.sign(torch.diagonal(K)))
    K = K @ sign
    R = sign @ R
    t = torch.linalg.solve(K, P[:, 3])
    if torch.linalg.det(R) < 0:  # P was given up to a negative scale
        R = -R
        t = -t
    K = K / K[2, 2]
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = t
    return K, w2c


@dataclass
class Cameras:
    """A batch of V pinhole cameras sharing one image size.

    Attributes:
        K: (V, 3, 3) intrinsics (skew allowed), pixel units at ``width`` x ``height``.
        w2c: (V, 4, 4) world-to-camera extrinsics, OpenCV axes.
        width: image width in pixels.
        height: image height in pixels.
    """

    K: Tensor
    w2c: Tensor
    width: int
    height: int

    def __post_init__(self) -> None:
        if self.K.ndim != 3 or self.K.shape[-2:] != (3, 3):
            raise ValueError(f"Cameras.K must be (V, 3, 3), got {tuple(self.K.shape)}")
        if self.w2c.ndim != 3 or self.w2c.shape[-2:] != (4, 4):
            raise ValueError(f"Cameras.w2c must be (V, 4, 4), got {tuple(self.w2c.shape)}")
        if self.K.shape[0] != self.w2c.shape[0]:
            raise ValueError(
                f"Cameras has {self.K.shape[0]} intrinsics but {self.w2c.shape[0]} extrinsics"
            )
        self.width = int(self.width)
        self.height = int(self.height)

    # ------------------------------------------------------------------ basics
    def __len__(self) -> int:
        return self.K.shape[0]

    def __getitem__(self, idx) -> Cameras:
        if isinstance(idx, int):
            idx = [idx]
        return Cameras(self.K[idx], self.w2c[idx], self.width, self.height)

    def to(self, device=None, dtype=None) -> Cameras:
        return Cameras(
            self.K.to(device=device, dtype=dtype),
            self.w2c.to(device=device, dtype=dtype),
            self.width,
            self.height,
        )

    @property
    def device(self) -> torch.device:
        return self.K.device

    @property
    def c2w(self) -> Tensor:
        """(V, 4, 4) camera-to-world matrices."""
        return torch.linalg.inv(self.w2c)

    @property
    def centers(self) -> Tensor:
        """(V, 3) camera centres in world coordinates."""
        R = self.w2c[:, :3, :3]
        t = self.w2c[:, :3, 3:]
        return -(R.transpose(1, 2) @ t)[..., 0]

    @property
    def view_dirs(self) -> Tensor:
        """(V, 3) unit optical axes (camera +z) in world coordinates."""
        return self.w2c[:, 2, :3] / self.w2c[:, 2, :3].norm(dim=-1, keepdim=True)

    @property
    def proj(self) -> Tensor:
        """(V, 4, 4) full projection [K @ w2c[:3]; 0 0 0 1] (MVSNet-style homogeneous matrix)."""
        P = torch.zeros_like(self.w2c)
        P[:, :3, :4] = self.K @ self.w2c[:, :3, :4]
        P[:, 3, 3] = 1
        return P

    # ------------------------------------------------------------------ geometry
    def world_to_camera(self, points: Tensor) -> Tensor:
        """Transform world points into each camera's frame.

        Args:
            points: (N, 3) shared by all views, or (V, N, 3) per view.

        Returns:
            (V, N, 3) camera-frame coordinates.
        """
        if points.ndim == 2:
            points = points.unsqueeze(0).expand(len(self), -1, -1)
        R = self.w2c[:, :3, :3]
        t = self.w2c[:, :3, 3]
        return points @ R.transpose(1, 2) + t[:, None]

    def project(self, points: Tensor, eps: float = 1e-8) -> tuple[Tensor, Tensor]:
        """Project world points to pixels.

        Args:
            points: (N, 3) shared by all views, or (V, N, 3) per view.
            eps: smallest |z| used in the division (points behind the camera keep their sign).

        Returns:
            uv: (V, N, 2) pixel coordinates (u = column, v = row; integer = pixel centre).
            depth: (V, N) z-depth in the camera frame (negative behind the camera).
        """
        pc = self.world_to_camera(points)
        z = pc[..., 2]
        zs = torch.where(z.abs() < eps, torch.full_like(z, eps), z)
        pix = pc @ self.K.transpose(1, 2)
        uv = pix[..., :2] / zs[..., None]
        return uv, z

    def unproject(self, uv: Tensor, depth: Tensor) -> Tensor:
        """Lift pixels with z-depth to world points; the inverse of :meth:`project`.

        Args:
            uv: (V, N, 2) pixel coordinates.
            depth: (V, N) z-depths.

        Returns:
            (V, N, 3) world points.
        """
        ones = torch.ones_like(uv[..., :1])
        pix = torch.cat([uv, ones], dim=-1)  # (V, N, 3)
        cam = pix @ torch.linalg.inv(self.K).transpose(1, 2) * depth[..., None]
        R = self.w2c[:, :3, :3]
        t = self.w2c[:, :3, 3]
        return (cam - t[:, None]) @ R  # R^T (x - t), written row-wise

    def pixel_grid(self, device=None, dtype=torch.float32) -> Tensor:
        """(H, W, 2) integer pixel-centre coordinates (u, v)."""
        device = device or self.device
        v, u = torch.meshgrid(
            torch.arange(self.height, device=device, dtype=dtype),
            torch.arange(self.width, device=device, dtype=dtype),
            indexing="ij",
        )
        return torch.stack([u, v], dim=-1)

    def rays(self, uv: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """World-frame rays through pixels.

        Args:
            uv: (V, N, 2) pixel coordinates; default every pixel centre, N = H*W in row-major order.

        Returns:
            origins: (V, N, 3) camera centres.
            dirs: (V, N, 3) unit directions in world coordinates.
            cos: (V, N) z-component of the unit camera-frame direction (ray distance * cos =
                z-depth; docs/method.md 5.4 "cos theta_pix").
        """
        if uv is None:
            uv = self.pixel_grid(dtype=self.K.dtype).reshape(1, -1, 2).expand(len(self), -1, -1)
        ones = torch.ones_like(uv[..., :1])
        d_cam = torch.cat([uv, ones], dim=-1) @ torch.linalg.inv(self.K).transpose(1, 2)
        d_cam = d_cam / d_cam.norm(dim=-1, keepdim=True)
        R = self.w2c[:, :3, :3]
        dirs = d_cam @ R  # R^T d
        origins = self.centers[:, None].expand_as(dirs)
        return origins, dirs, d_cam[..., 2]

    # ------------------------------------------------------------------ image ops
    def resize(self, width: int, height: int) -> Cameras:
        """Cameras for the image resized to ``width`` x ``height``.

        Focal lengths and skew scale by s; the principal point maps as c' = s (c + 0.5) - 0.5
        (integer pixel centres; see the module docstring).
        """
        sx = width / self.width
        sy = height / self.height
        K = self.K.clone()
        K[:, 0, 0] *= sx
        K[:, 0, 1] *= sx
        K[:, 0, 2] = sx * (K[:, 0, 2] + 0.5) - 0.5
        K[:, 1, 1] *= sy
        K[:, 1, 2] = sy * (K[:, 1, 2] + 0.5) - 0.5
        return Cameras(K, self.w2c.clone(), width, height)

    def crop(self, x0: int, y0: int, width: int, height: int) -> Cameras:
        """Cameras for the crop [x0, x0 + width) x [y0, y0 + height) of each image."""
        K = self.K.clone()
        K[:, 0, 2] -= x0
        K[:, 1, 2] -= y0
        return Cameras(K, self.w2c.clone(), width, height)

    def transformed(self, center: Tensor, scale: float) -> Cameras:
        """Cameras expressed in a frame where x_new = (x_world - center) / scale.

        The rotation is unchanged; depths divide by ``scale``.
        """
        center = torch.as_tensor(center, dtype=self.w2c.dtype, device=self.w2c.device)
        w2c = self.w2c.clone()
        R = w2c[:, :3, :3]
        w2c[:, :3, 3] = (R @ center + w2c[:, :3, 3]) / scale
        return Cameras(self.K.clone(), w2c, self.width, self.height)
