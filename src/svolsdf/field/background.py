"""NeRF++ inverted-sphere background for unbounded scenes (docs/method.md 5.5).

Points outside the bounding sphere |x| = R are parameterised by their inverse radius
u = 1/r in [0, 1/R] and the unit direction where the ray meets the sphere of radius r, mapped
back onto the unit sphere (NeRF++, Zhang et al. 2020). Used with a foreground
:class:`~svolsdf.field.volsdf.VolSDFField` whose sphere clamp is off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from svolsdf.field.embedding import PositionalEncoding
from svolsdf.field.volsdf import SDFNetwork

__all__ = ["BackgroundConfig", "inverted_sphere_points", "NeRFColourNetwork",
           "NeRFPlusPlusBackground", "SphereMapBackground", "sphere_exit"]


@dataclass
class BackgroundConfig:
    """Background model constants (docs/method.md 5.5)."""

    n_samples: int = 32
    """Inverse-radius samples per ray."""
    radius: float = 3.0
    """Bounding-sphere radius R of the foreground."""
    multires: int = 10
    """Positional-encoding frequencies of the 4-d point (84 input channels)."""
    n_layers: int = 8
    """Hidden layers of the background MLP."""
    d_hidden: int = 256
    """Hidden width of the background MLP."""
    skip_in: tuple[int, ...] = (4,)
    """Skip layers of the background MLP."""
    feature_dim: int = 256
    """Feature size passed to the colour network."""
    multires_view: int = 4
    """Positional-encoding frequencies of the view direction (27 channels)."""
    colour_hidden: int = 128
    """Hidden width of the "nerf"-mode colour network (283 -> 128 -> 3)."""


def inverted_sphere_points(origins: Tensor, dirs: Tensor, u: Tensor, radius: float
                           ) -> tuple[Tensor, Tensor]:
    """NeRF++ background points and their ray distances (docs/method.md 5.5).

    p_s = o + d_s d on |x| = R; p_m = o - (o.d) d; p_s is rotated about o x p_s by
    asin(|p_m|/R) - asin(|p_m| u) (Rodrigues), normalised and concatenated with u. The ray
    distance of the point at radius 1/u is cos(asin(|p_m| u)) / u - o.d (unit d; 1e-6 guards u=0).

    Args:
        origins, dirs: (R, 3) with unit dirs and origins inside the sphere.
        u: (R, K) inverse radii in [0, 1/R].
        radius: R.

    Returns:
        points (R, K, 4), distances (R, K).
    """
    od = (origins * dirs).sum(-1, keepdim=True)  # (R, 1)
    disc = (od**2 - ((origins**2).sum(-1, keepdim=True) - radius**2)).clamp_min(0.0)
    d_s = disc.sqrt() - od
    p_s = origins + d_s * dirs  # (R, 3)
    p_m = origins - od * dirs
    pm_norm = p_m.norm(dim=-1, keepdim=True)  # (R, 1)
    axis = torch.linalg.cross(origins, p_s)
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    phi = torch.asin((pm_norm / radius).clamp(-1.0, 1.0))
    theta = torch.asin((pm_norm * u).clamp(-1.0, 1.0))  # (R, K)
    ang = (phi - theta)[..., None]  # (R, K, 1)
    ps, ax = p_s[:, None], axis[:, None]
    rot = (ps * torch.cos(ang) + torch.linalg.cross(ax.expand_as(ps), ps, dim=-1) * torch.sin(ang)
           + ax * (ax * ps).sum(-1, keepdim=True) * (1.0 - torch.cos(ang)))
    rot = rot / rot.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    pts = torch.cat([rot.expand(-1, u.shape[1], -1), u[..., None]], dim=-1)
    dist = torch.cos(theta) / (u + 1e-6) - od
    return pts, dist


class NeRFColourNetwork(nn.Module):
    """"nerf"-mode colour network: [gamma_L(dir), feature] -> 128 -> 3, sigmoid
    (docs/method.md 5.5)."""

    def __init__(self, feature_dim: int = 256, d_hidden: int = 128, multires_view: int = 4):
        super().__init__()
        self.embed = PositionalEncoding(3, multires_view)
        self.lin0 = nn.Linear(self.embed.out_dim + feature_dim, d_hidden)
        self.lin1 = nn.Linear(d_hidden, 3)

    def forward(self, view_dir: Tensor, feature: Tensor) -> Tensor:
        """view_dir (N, 3), feature (N, F) -> rgb (N, 3)."""
        h = torch.relu(self.lin0(torch.cat([self.embed(view_dir), feature], dim=-1)))
        return torch.sigmoid(self.lin1(h))


class NeRFPlusPlusBackground(nn.Module):
    """Background radiance field outside the bounding sphere (docs/method.md 5.5).

    Call as ``background(rays, training) -> (rgb (R, 3), sum_k w_k t_k (R,), sum_k w_k (R,))``;
    :func:`svolsdf.render.volume.render_rays` composites it with the foreground transmittance.
    """

    def __init__(self, config: BackgroundConfig | None = None):
        super().__init__()
        c = config or BackgroundConfig()
        self.config = c
        self.net = SDFNetwork(
            d_in=4, d_out=1, feature_dim=c.feature_dim, d_hidden=c.d_hidden, n_layers=c.n_layers,
            skip_in=tuple(c.skip_in), multires=c.multires, geometric_init=False,
            use_weight_norm=False,
        )
        self.colour_net = NeRFColourNetwork(c.feature_dim, c.colour_hidden, c.multires_view)

    def sample_u(self, n_rays: int, device, training: bool) -> Tensor:
        """(R, K) inverse radii from 1/R down to 0 (stratified in training)."""
        K = self.config.n_samples
        t = torch.linspace(0.0, 1.0, K, device=device).expand(n_rays, K)
        if training and K > 1:
            mids = 0.5 * (t[:, 1:] + t[:, :-1])
            upper = torch.cat([mids, t[:, -1:]], -1)
            lower = torch.cat([t[:, :1], mids], -1)
            t = lower + (upper - lower) * torch.rand_like(t)
        return torch.flip(t / self.config.radius, dims=[-1])

    def forward(self, rays, training: bool | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """rays: a RayBundle of R rays -> rgb (R, 3), sum_k w_k t_k (R,), sum_k w_k (R,)."""
        training = self.training if training is None else training
        R = len(rays)
        u = self.sample_u(R, rays.device, training)
        pts, dist = inverted_sphere_points(rays.origins, rays.dirs, u, self.config.radius)
        out = self.net(pts.reshape(-1, 4))
        K = u.shape[1]
        sigma = out[:, 0].abs().reshape(R, K)
        feat = out[:, 1:]
        dirs = rays.dirs[:, None].expand(R, K, 3).reshape(-1, 3)
        rgb = self.colour_net(dirs, feat).reshape(R, K, 3)
        deltas = torch.cat([u[:, :-1] - u[:, 1:], torch.full_like(u[:, :1], 1e10)], -1)
        fe = sigma * deltas
        shifted = torch.cat([torch.zeros_like(fe[:, :1]), torch.cumsum(fe, -1)[:, :-1]], -1)
        w = (1.0 - torch.exp(-fe)) * torch.exp(-shifted)
        return (w[..., None] * rgb).sum(1), (w * dist).sum(-1), w.sum(-1)


def sphere_exit(origins: Tensor, dirs: Tensor, radius: float) -> tuple[Tensor, Tensor]:
    """Where rays leave the bounding sphere |x| = R (the far intersection).

    Args:
        origins, dirs: (R, 3) unit-frame origins and unit directions.
        radius: R.

    Returns:
        points (R, 3) on the sphere (the ray's closest point to the sphere when it misses it),
        ray distances (R,) to them (>= 0).
    """
    od = (origins * dirs).sum(-1)
    disc = (od**2 - ((origins**2).sum(-1) - radius**2)).clamp_min(0.0)
    t = (disc.sqrt() - od).clamp_min(0.0)
    return origins + t[:, None] * dirs, t


class SphereMapBackground(nn.Module):
    """A colour painted on the bounding sphere: what a ray shows once the foreground is empty.

    Not in the paper (which uses NeRF++, :class:`NeRFPlusPlusBackground`); the fast field's
    cheap stand-in for it (docs/novel-views.md). The colour at the point where a ray leaves the
    sphere |x| = R is the sigmoid of the sum of ``levels`` equirectangular maps (latitude x
    longitude of that point, bilinear, coarse to fine) of three channels each: no network and no
    samples along the ray, so a ray costs one lookup per level. The maps start at 0 (grey).

    Call as ``background(rays, training) -> (rgb (R, 3), t_exit (R,), ones (R,))`` (the
    interface of `svolsdf.render.volume.render_rays`: the background sits at the exit
    distance with weight 1).

    Args:
        radius: R, the bounding sphere's radius (unit frame).
        resolutions: latitude rows of each level (longitude has twice as many columns).
    """

    def __init__(self, radius: float = 3.0, resolutions: tuple[int, ...] = (8, 32, 128)):
        super().__init__()
        if not resolutions or min(resolutions) < 2:
            raise ValueError(f"SphereMapBackground: resolutions must be >= 2, got {resolutions}")
        self.radius = float(radius)
        self.maps = nn.ParameterList(
            [nn.Parameter(torch.zeros(1, 3, r, 2 * r)) for r in resolutions])

    def grid_parameters(self) -> list[nn.Parameter]:
        """The maps: trained at the feature grids' rate (``train.lr_grid``), not a network's."""
        return list(self.maps)

    def colour_at(self, p: Tensor) -> Tensor:
        """p: (N, 3) points on the sphere -> (N, 3) rgb in [0, 1]."""
        n = p / p.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        lon = torch.atan2(n[:, 1], n[:, 0]) / math.pi  # [-1, 1]
        lat = torch.asin(n[:, 2].clamp(-1.0, 1.0)) / (math.pi / 2)  # [-1, 1]
        g = torch.stack([lon, lat], -1)[None, :, None]  # (1, N, 1, 2)
        acc = 0.0
        for m in self.maps:
            acc = acc + F.grid_sample(m, g, mode="bilinear", padding_mode="border",
                                      align_corners=True)[0, :, :, 0].T
        return torch.sigmoid(acc)

    def forward(self, rays, training: bool | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """rays: a RayBundle of R rays -> rgb (R, 3), exit distance (R,), ones (R,)."""
        p, t = sphere_exit(rays.origins, rays.dirs, self.radius)
        return self.colour_at(p), t, torch.ones_like(t)
