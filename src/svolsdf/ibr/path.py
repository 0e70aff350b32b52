"""Smooth camera paths between input views, for novel-view videos (``--path orbit``).

The path visits the given views in order. Between consecutive views the camera centre moves on
an arc around a look-at point p: its direction from p is slerped and its distance to p is
interpolated linearly. The orientation is a look-at rotation towards p (up vector slerped
between the views' up vectors) composed with a slerped per-view offset rotation O_i = R_i L_i^T,
where L_i is the look-at rotation of view i. So the path starts and ends exactly at the given
views, and when the views look at p (O_i = I) every path camera looks at p. Frames are spaced
evenly in arc angle (plus a small share for changes of radius). Intrinsics: the first view's.

Conventions: `svolsdf.scene.cameras` (OpenCV axes: x right, y down, z forward; world-to-camera).
"""

from __future__ import annotations

import math

import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle
from torch import Tensor

from svolsdf.scene.cameras import Cameras

__all__ = ["look_at_point", "look_at_rotation", "orbit_cameras", "slerp_rotation", "slerp_unit"]


def look_at_point(cams: Cameras) -> Tensor:
    """Least-squares nearest point to all optical axes.

    p = argmin sum_i ||(I - z_i z_i^T)(p - c_i)||^2, with c_i the centres and z_i the unit
    optical axes.

    Args:
        cams: `Cameras` with V >= 2 views whose optical axes are not all parallel.

    Returns:
        (3,) float64 world point.

    Raises:
        ValueError: if the axes are (nearly) parallel, so no single point is closest.
    """
    c = cams.centers.double()
    z = cams.view_dirs.double()
    P = torch.eye(3, dtype=torch.float64) - z[:, :, None] * z[:, None, :]  # (V, 3, 3)
    A = P.sum(0)
    b = (P @ c[:, :, None]).sum(0)[:, 0]
    ev = torch.linalg.eigvalsh(A)
    if float(ev[0]) < 1e-6 * float(ev[-1]):
        raise ValueError(
            "the cameras' optical axes are (nearly) parallel, so they have no common look-at "
            "point; pass target= explicitly"
        )
    return torch.linalg.solve(A, b)


def look_at_rotation(eye: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """World-to-camera rotations looking from ``eye`` at ``target`` (OpenCV axes, y down).

    Rows: x = normalize(down x z), y = z x x, z = normalize(target - eye), down = -up.

    Args:
        eye: (N, 3) centres.
        target: (3,) or (N, 3) look-at points.
        up: (3,) or (N, 3) world up vectors (not parallel to the viewing direction).

    Returns:
        (N, 3, 3) rotations R with rows [x; y; z].
    """
    z = torch.nn.functional.normalize(target - eye, dim=-1)
    down = -up.expand_as(z)
    x = torch.linalg.cross(down, z, dim=-1)
    if bool((x.norm(dim=-1) < 1e-9).any()):
        raise ValueError("look_at_rotation: the up vector is parallel to the viewing direction")
    x = torch.nn.functional.normalize(x, dim=-1)
    y = torch.linalg.cross(z, x, dim=-1)
    return torch.stack([x, y, z], dim=-2)


def slerp_unit(a: Tensor, b: Tensor, t: Tensor) -> Tensor:
    """Spherical interpolation of unit vectors.

    s(t) = sin((1-t) w) / sin w * a + sin(t w) / sin w * b, w = angle(a, b) (lerp-normalize
    when w is tiny).

    Args:
        a, b: (3,) unit vectors, not antipodal.
        t: (N,) parameters in [0, 1].

    Returns:
        (N, 3) unit vectors.
    """
    cw = torch.clamp((a * b).sum(), -1.0, 1.0)
    w = torch.arccos(cw)
    if float(w) > math.pi - 1e-6:
        raise ValueError("slerp_unit: the vectors are antipodal, the arc between them is undefined")
    t = t[:, None]
    if float(w) < 1e-8:
        return torch.nn.functional.normalize((1 - t) * a + t * b, dim=-1)
    s = torch.sin(w)
    out = torch.sin((1 - t) * w) / s * a + torch.sin(t * w) / s * b
    return torch.nn.functional.normalize(out, dim=-1)


def slerp_rotation(Ra: Tensor, Rb: Tensor, t: Tensor) -> Tensor:
    """Geodesic interpolation of rotations: R(t) = exp(t log(Rb Ra^T)) Ra.

    Args:
        Ra, Rb: (3, 3) rotation matrices.
        t: (N,) parameters in [0, 1].

    Returns:
        (N, 3, 3) rotations; R(0) = Ra, R(1) = Rb.
    """
    rel = (Rb.double() @ Ra.double().T)[None]
    aa = rotation_matrix_to_axis_angle(rel)[0]  # (3,), angle in [0, pi]
    R = axis_angle_to_rotation_matrix(t[:, None].double() * aa[None])
    return R @ Ra.double()


def orbit_cameras(
    cams: Cameras,
    n: int,
    target: Tensor | None = None,
    closed: bool = False,
) -> Cameras:
    """A smooth camera path through the given views, for orbit videos.

    See the module docstring: centres on arcs around the look-at point ``target`` (slerped
    direction, linearly interpolated distance), orientation = look-at rotation (slerped up
    vector) composed with the slerped per-view offset rotation, intrinsics of the first view.

    Args:
        cams: `Cameras` with V >= 2 views, visited in this order.
        n: number of path cameras (>= 2); the first is ``cams[0]`` and the last is ``cams[-1]``
            (or ``cams[0]`` again when ``closed``).
        target: (3,) look-at point in world units; default `look_at_point` (the point nearest to
            all optical axes).
        closed: return to the first view at the end (a looping video).

    Returns:
        `Cameras` with n views, K (n, 3, 3) = the first view's, w2c (n, 4, 4), the input size,
        in the input dtype.
    """
    V = len(cams)
    if V < 2:
        raise ValueError(f"orbit_cameras needs at least 2 views, got {V}")
    if n < 2:
        raise ValueError(f"orbit_cameras needs n >= 2 frames, got {n}")
    dtype = cams.w2c.dtype
    c64 = cams.to(dtype=torch.float64)
    p = look_at_point(c64) if target is None else torch.as_tensor(target, dtype=torch.float64)
    p = p.to(c64.device)

    order = list(range(V)) + ([0] if closed else [])
    C = c64.centers[order]  # (S+1, 3)
    R = c64.w2c[order, :3, :3]
    rel = C - p
    r = rel.norm(dim=-1)
    if bool((r < 1e-9).any()):
        raise ValueError("a camera centre coincides with the look-at point")
    d = rel / r[:, None]
    up = -R[:, 1, :]  # the world direction of each view's -y axis
    L = look_at_rotation(C, p, up)
    O = R @ L.transpose(1, 2)  # per-view offsets, R = O L

    # Segment lengths: arc angle plus relative radius change, so frames are evenly spread.
    ang = torch.arccos(torch.clamp((d[:-1] * d[1:]).sum(-1), -1.0, 1.0))
    dr = (r[1:] - r[:-1]).abs() / r.mean()
    seg = ang + dr + 1e-9
    cum = torch.cat([torch.zeros(1, dtype=torch.float64, device=p.device), seg.cumsum(0)])
    s = torch.linspace(0.0, float(cum[-1]), n, dtype=torch.float64, device=p.device)
    idx = torch.clamp(torch.searchsorted(cum, s, right=True) - 1, 0, len(seg) - 1)
    t = ((s - cum[idx]) / seg[idx]).clamp(0, 1)

    w2c = torch.eye(4, dtype=torch.float64, device=p.device).repeat(n, 1, 1)
    for k in range(len(seg)):  # a handful of segments; frames within a segment are batched
        sel = idx == k
        if not bool(sel.any()):
            continue
        tk = t[sel]
        dk = slerp_unit(d[k], d[k + 1], tk)
        rk = (1 - tk) * r[k] + tk * r[k + 1]
        ck = p + rk[:, None] * dk
        uk = slerp_unit(
            torch.nn.functional.normalize(up[k], dim=0),
            torch.nn.functional.normalize(up[k + 1], dim=0), tk,
        )
        Rk = slerp_rotation(O[k], O[k + 1], tk) @ look_at_rotation(ck, p, uk)
        w2c[sel, :3, :3] = Rk
        w2c[sel, :3, 3] = -(Rk @ ck[:, :, None])[..., 0]
    # exact endpoints (no round-off from the interpolation)
    w2c[0] = c64.w2c[order[0]]
    w2c[-1] = c64.w2c[order[-1]]
    K = cams.K[:1].expand(n, -1, -1).clone()
    return Cameras(K, w2c.to(dtype), cams.width, cams.height)
