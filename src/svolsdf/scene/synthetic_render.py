"""Ray casting of the synthetic scenes (`svolsdf.scene.synthetic`): sphere tracing of the object's
signed distance function, a ray-plane table, Lambertian shading with an ambient term, a
directional light and soft shadows (`render_view`).

Rays are cast in the scene's local frame (millimetres, z up, table z = 0, `_World`); depths are
returned in world z-depth at pixel centres, camera axes as in `svolsdf.scene.cameras`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from svolsdf.scene.cameras import Cameras
from svolsdf.scene.synthetic_shapes import SynthObject, _hash01, _Noise, _sdf_grad

__all__ = [
    "render_view",
]


# =============================================================================== rendering
@dataclass
class _World:
    """Everything a ray needs: the object, the table and the light, in the LOCAL frame
    (millimetres, z up, table z = 0), plus the similarity local -> world."""

    obj: SynthObject
    table_half: float
    light: Tensor  # (3,) unit, towards the light, local frame
    ambient: float
    soft_shadows: bool
    table_seed: int
    rot: Tensor  # (3, 3) float64 columns = local axes in world coordinates
    origin: Tensor  # (3,) float64 world position of the local origin
    scale: float  # world units per local unit
    specular: float = 0.0  # strength of the object's white Blinn-Phong highlight
    shininess: float = 40.0  # its exponent

    def __post_init__(self) -> None:
        self.table_noise = _Noise(self.table_seed)

    def to_local(self, x: Tensor) -> Tensor:
        """(N, 3) world points -> local points."""
        return ((x - self.origin) @ self.rot) / self.scale

    def to_world(self, x: Tensor) -> Tensor:
        """(N, 3) local points -> world points."""
        return (x * self.scale) @ self.rot.T + self.origin


def _sphere_interval(o: Tensor, d: Tensor, c: Tensor, r: float) -> tuple[Tensor, Tensor]:
    """Ray-sphere entry and exit distances (inf, inf when missed). o, d: (N, 3) -> (N,), (N,)."""
    oc = o - c
    b = (oc * d).sum(-1)
    disc = b * b - ((oc * oc).sum(-1) - r * r)
    s = disc.clamp(min=0).sqrt()
    t0 = (-b - s).clamp(min=0.0)
    t1 = -b + s
    miss = (disc <= 0) | (t1 <= 0)
    inf = torch.full_like(t0, math.inf)
    return torch.where(miss, inf, t0), torch.where(miss, inf, t1)


def _sphere_trace(obj: SynthObject, o: Tensor, d: Tensor, t0: Tensor, t1: Tensor,
                  eps: float = 1e-3, min_step: float = 0.02, max_steps: int = 192) -> Tensor:
    """First t in [t0, t1] where the object SDF vanishes (inf where none).

    Sphere tracing (Hart 1996): the SDF is 1-Lipschitz so a step of the SDF value never crosses
    the surface. Steps are at least ``min_step`` so that rays grazing a surface do not crawl; a
    ray that thereby lands inside is bisected back onto the surface (error < 1e-5 world units).
    o, d: (N, 3) origins and unit directions; t0, t1: (N,). Returns (N,).
    """
    ox, oy, oz = o.T.contiguous()
    dx, dy, dz = d.T.contiguous()
    t = t0.clone()
    hit_t = torch.full_like(t0, math.inf)
    idx = torch.nonzero(torch.isfinite(t0) & (t0 < t1)).squeeze(1)
    for _ in range(max_steps):
        if idx.numel() == 0:
            break
        ti = t[idx]
        dist = obj.sdf_xyz(ox[idx] + ti * dx[idx], oy[idx] + ti * dy[idx], oz[idx] + ti * dz[idx])
        done = dist < eps
        hit_t[idx[done]] = ti[done]
        tn = ti + dist.clamp(min=min_step)
        t[idx] = tn
        idx = idx[~done & (tn < t1[idx])]
    # Overshoots by a minimum step: bisect within the last step, which started outside.
    hit = torch.nonzero(torch.isfinite(hit_t)).squeeze(1)
    th = hit_t[hit]

    def f(tt: Tensor, ii: Tensor) -> Tensor:
        return obj.sdf_xyz(ox[ii] + tt * dx[ii], oy[ii] + tt * dy[ii], oz[ii] + tt * dz[ii])

    inside = f(th, hit) < -eps
    ii, hi = hit[inside], th[inside]
    lo = hi - min_step
    for _ in range(12):
        mid = 0.5 * (lo + hi)
        neg = f(mid, ii) < 0
        hi = torch.where(neg, mid, hi)
        lo = torch.where(neg, lo, mid)
    hit_t[ii] = lo
    return hit_t


def _normals(obj: SynthObject, p: Tensor, h: float = 0.02) -> Tensor:
    """Unit outward normals. p: (N, 3) -> (N, 3)."""
    g = _sdf_grad(obj, p, h)
    return g / g.norm(dim=-1, keepdim=True).clamp(min=1e-12)


def _soft_shadow(obj: SynthObject, p: Tensor, light: Tensor, k: float = 16.0,
                 max_steps: int = 64) -> Tensor:
    """Soft shadow factor in [0, 1] (1 = lit) for points p (N, 3) lit from direction ``light``
    (the classic min(k h / t) penumbra estimate along a sphere-traced shadow ray)."""
    c, r = obj.bound()
    d = light.expand_as(p)
    t0, t1 = _sphere_interval(p, d, p.new_tensor(c), r)
    res = torch.ones_like(p[:, 0])
    idx = torch.nonzero(torch.isfinite(t0)).squeeze(1)
    t = t0.clamp(min=0.5)
    px, py, pz = p.T.contiguous()
    lx, ly, lz = (float(v) for v in light)
    for _ in range(max_steps):
        if idx.numel() == 0:
            break
        ti = t[idx]
        h = obj.sdf_xyz(px[idx] + ti * lx, py[idx] + ti * ly, pz[idx] + ti * lz)
        res[idx] = torch.minimum(res[idx], (k * h / ti).clamp(0.0, 1.0))
        t[idx] = ti + h.clamp(0.3, 20.0)
        keep = (res[idx] > 1e-3) & (t[idx] < t1[idx])
        idx = idx[keep]
    return res * res * (3.0 - 2.0 * res)


def _table_albedo(world: _World, p: Tensor) -> Tensor:
    """Wood-and-tiles solid texture of the table. p: (N, 3) -> (N, 3)."""
    coarse = world.table_noise.fbm(p, 40.0, 3)  # warp, blotch
    fine = world.table_noise.fbm(p, 3.0, 2)[2]
    grain = 0.5 + 0.5 * torch.sin(2 * math.pi * (p[:, 0] + 60.0 * coarse[0]) / 9.0)
    wood_a = p.new_tensor([0.55, 0.36, 0.20])
    wood_b = p.new_tensor([0.80, 0.62, 0.40])
    c = wood_a * (1 - grain[:, None]) + wood_b * grain[:, None]
    tile = torch.floor(p[:, :2] / 60.0).to(torch.int64)
    tint = _hash01(tile[:, 0], tile[:, 1], torch.zeros_like(tile[:, 0]), world.table_seed)
    c = c * (0.75 + 0.5 * tint[:, None]) * (0.8 + 0.4 * fine[:, None])
    blot = 0.35 * (coarse[1] > 0.62).to(p.dtype)[:, None]
    c = c * (1 - blot) + p.new_tensor([0.2, 0.3, 0.45]) * blot
    return c.clamp(0.0, 1.0)


def _cast(world: _World, o: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
    """Cast local-frame rays. o, d: (N, 3) float32 -> t (N,) (inf: background), what (N,) int8
    (0 background, 1 table, 2 object)."""
    dz = d[:, 2]
    t_tab = torch.where(dz < -1e-9, -o[:, 2] / dz.clamp(max=-1e-9), torch.full_like(dz, math.inf))
    ptab = o + t_tab.nan_to_num(posinf=0.0)[:, None] * d
    on_table = torch.isfinite(t_tab) & (ptab[:, :2].abs() <= world.table_half).all(-1)
    t_tab = torch.where(on_table, t_tab, torch.full_like(t_tab, math.inf))
    c, r = world.obj.bound()
    t0, t1 = _sphere_interval(o, d, o.new_tensor(c), r)
    t1 = torch.minimum(t1, t_tab)
    t_obj = _sphere_trace(world.obj, o, d, t0, t1)
    what = torch.zeros_like(dz, dtype=torch.int8)
    what[torch.isfinite(t_tab)] = 1
    is_obj = torch.isfinite(t_obj) & (t_obj <= t_tab)
    what[is_obj] = 2
    t = torch.where(is_obj, t_obj, t_tab)
    return t, what


def _shade(world: _World, o: Tensor, d: Tensor, t: Tensor, what: Tensor) -> Tensor:
    """Colour of cast rays (N, 3) in [0, 1]: albedo * (ambient + (1 - ambient) max(0, n.l) vis),
    plus on the object ``specular * max(0, n.h)^shininess * vis`` in white (Blinn-Phong, h the
    half vector of the light and the view direction -d) when ``world.specular`` > 0."""
    y = (d[:, 2].clamp(-1, 1) + 1) / 2  # background: a dim vertical gradient
    rgb = torch.stack([0.10 + 0.10 * y, 0.11 + 0.12 * y, 0.14 + 0.16 * y], -1)
    light = world.light.to(o.dtype)
    for kind in (1, 2):
        sel = what == kind
        if not bool(sel.any()):
            continue
        p = o[sel] + t[sel, None] * d[sel]
        if kind == 1:
            n = torch.zeros_like(p)
            n[:, 2] = 1.0
            alb = _table_albedo(world, p)
        else:
            n = _normals(world.obj, p)
            alb = world.obj.albedo(p)
        lam = (n @ light).clamp(min=0.0)
        vis = (lam > 0).to(lam.dtype)
        if world.soft_shadows:
            lit = lam > 0
            if bool(lit.any()):
                vis[lit] = _soft_shadow(world.obj, p[lit] + 0.5 * n[lit], light)
            lam = lam * vis
        c = alb * (world.ambient + (1 - world.ambient) * lam[:, None])
        if kind == 2 and world.specular > 0:
            h = torch.nn.functional.normalize(light[None] - d[sel], dim=-1)
            spec = (n * h).sum(-1).clamp(min=0.0) ** world.shininess
            c = c + world.specular * (spec * vis)[:, None]
        rgb[sel] = c
    return rgb.clamp(0.0, 1.0)


def render_view(world: _World, cam: Cameras, supersample: int = 2,
                chunk: int = 1 << 17) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render one view by exact ray casting (sphere tracing of the object SDF, ray-plane table).

    Args:
        world: the scene (object, table, light) and its local -> world similarity.
        cam: one camera (world frame) at the output size.
        supersample: anti-aliasing samples per pixel axis for the colours.
        chunk: rays per chunk.

    Returns:
        image: (H, W, 3) uint8 RGB.
        depth: (H, W) float32 world z-depth at pixel centres, 0 where no surface.
        mask: (H, W) bool, True where the pixel-centre ray first hits the object.
    """
    H, W = cam.height, cam.width
    K = cam.K[0].to(torch.float64)
    w2c = cam.w2c[0].to(torch.float64)
    Kinv = torch.linalg.inv(K)
    R = w2c[:3, :3]
    centre = -(R.T @ w2c[:3, 3])
    o_loc = world.to_local(centre[None])[0]
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64),
                          torch.arange(W, dtype=torch.float64), indexing="ij")
    uv = torch.stack([u.reshape(-1), v.reshape(-1)], -1)
    n_pix = uv.shape[0]
    offs = [0.0] if supersample == 1 else [(k + 0.5) / supersample - 0.5
                                         for k in range(supersample)]

    def local_dirs(uvs: Tensor) -> tuple[Tensor, Tensor]:
        cam_d = torch.cat([uvs, torch.ones_like(uvs[:, :1])], -1) @ Kinv.T  # z = 1
        dw = cam_d @ R  # R^T d, world frame
        dl = dw @ world.rot  # local frame (rotation only)
        norm = dl.norm(dim=-1, keepdim=True)
        # z-depth = t_world * (z-component of the unit camera-frame direction)
        return (dl / norm).to(torch.float32), (1.0 / cam_d.norm(dim=-1)).to(torch.float32)

    depth = np.zeros(n_pix, np.float32)
    mask = np.zeros(n_pix, bool)
    rgb = np.zeros((n_pix, 3), np.float64)
    o32 = o_loc.to(torch.float32)
    # One cast per chunk for the pixel-centre rays (depth, mask) and the supersamples (colour),
    # concatenated: sphere tracing costs per step, not per ray.
    shifts = [(ox, oy) for oy in offs for ox in offs] if supersample > 1 else []
    n_ray = 1 + len(shifts)
    step = max(1, chunk // n_ray)
    for s in range(0, n_pix, step):
        uvc = uv[s:s + step]
        n = uvc.shape[0]
        all_uv = torch.cat([uvc] + [uvc + uvc.new_tensor(sh) for sh in shifts])
        dl, cos = local_dirs(all_uv)
        o = o32.expand_as(dl)
        t, what = _cast(world, o, dl)
        hit = torch.isfinite(t[:n])
        z = torch.where(hit, t[:n] * cos[:n] * world.scale, torch.zeros_like(t[:n]))
        depth[s:s + n] = z.numpy()
        mask[s:s + n] = (what[:n] == 2).numpy()
        first = 0 if supersample == 1 else n
        c = _shade(world, o[first:], dl[first:], t[first:], what[first:]).to(torch.float64)
        rgb[s:s + n] = c.reshape(-1, n, 3).mean(0).numpy()
    img = np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8).reshape(H, W, 3)
    return img, depth.reshape(H, W), mask.reshape(H, W)
