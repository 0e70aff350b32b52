"""Tests for svolsdf.ibr.path: orbit camera paths between input views."""

from __future__ import annotations

import math

import pytest
import torch
from ibr_synth import look_at_camera, stack_cameras

from svolsdf.ibr import look_at_point, orbit_cameras, slerp_rotation, slerp_unit

TARGET = (0.2, -0.1, 0.3)
# different heights and distances: consecutive views are not related by one rotation about p
EYES = [(2.0, -0.5, -2.0), (0.0, -1.0, -3.2), (-2.2, 0.3, -1.5)]


def _views(target=TARGET):
    return stack_cameras([look_at_camera(e, target=target) for e in EYES])


def _rotation_ok(R):
    eye = torch.eye(3, dtype=R.dtype).expand_as(R)
    return torch.allclose(R @ R.transpose(1, 2), eye, atol=1e-9) and bool(
        (torch.linalg.det(R) > 0.999).all()
    )


def test_look_at_point_recovers_target():
    p = look_at_point(_views())
    assert torch.allclose(p, torch.tensor(TARGET, dtype=torch.float64), atol=1e-9)


def test_look_at_point_parallel_axes_raises():
    cams = stack_cameras([look_at_camera((x, 0.0, -3.0), target=(x, 0.0, 0.0)) for x in (0, 1)])
    with pytest.raises(ValueError, match="parallel"):
        look_at_point(cams)


@pytest.mark.parametrize("closed", [False, True])
def test_orbit_starts_ends_at_views_and_looks_at_target(closed):
    cams = _views()
    path = orbit_cameras(cams, 41, closed=closed)
    assert len(path) == 41 and (path.width, path.height) == (cams.width, cams.height)
    assert torch.equal(path.w2c[0], cams.w2c[0])
    assert torch.equal(path.w2c[-1], cams.w2c[0 if closed else 2])
    assert torch.allclose(path.K, cams.K[:1].expand(41, -1, -1))
    assert _rotation_ok(path.w2c[:, :3, :3])
    # every camera sees the target at its principal point, in front of it
    uv, z = path.project(torch.tensor([TARGET], dtype=torch.float64))
    assert bool((z > 0).all())
    assert torch.allclose(uv[:, 0], path.K[:, :2, 2], atol=1e-6)
    # centres on arcs: the distance to the target stays between the views' distances
    p = torch.tensor(TARGET, dtype=torch.float64)
    r = (path.centers - p).norm(dim=-1)
    rv = (cams.centers - p).norm(dim=-1)
    assert float(r.min()) >= float(rv.min()) - 1e-9 and float(r.max()) <= float(rv.max()) + 1e-9
    # smooth: consecutive frames are close, with no jumps
    step = (path.centers[1:] - path.centers[:-1]).norm(dim=-1)
    assert float(step.max()) < 2.5 * float(step.mean())
    rel = path.w2c[1:, :3, :3] @ path.w2c[:-1, :3, :3].transpose(1, 2)
    ang = torch.arccos(((rel.diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1))
    assert float(ang.max()) < math.radians(10)


def test_orbit_passes_through_middle_view():
    cams = _views()
    # choose n so that a frame lands on the middle view: frames are evenly spaced in arc length
    path = orbit_cameras(cams, 200)
    d = (path.centers[:, None] - cams.centers[None]).norm(dim=-1)  # (n, V)
    k = int(d[:, 1].argmin())
    assert float(d[k, 1]) < 0.05
    assert 0 < k < 199


def test_orbit_keeps_view_offsets_when_views_do_not_look_at_target():
    # views aimed at slightly different points: endpoints are still exact and rotations valid
    cams = stack_cameras([
        look_at_camera(EYES[0], target=(0.3, 0.0, 0.3)),
        look_at_camera(EYES[2], target=(0.0, -0.2, 0.2)),
    ])
    path = orbit_cameras(cams, 9, target=torch.tensor(TARGET))
    assert torch.equal(path.w2c[0], cams.w2c[0]) and torch.equal(path.w2c[-1], cams.w2c[1])
    assert _rotation_ok(path.w2c[:, :3, :3])
    assert path.w2c.dtype == cams.w2c.dtype


def test_orbit_float32_and_errors():
    cams = _views().to(dtype=torch.float32)
    path = orbit_cameras(cams, 5)
    assert path.w2c.dtype == torch.float32 and path.K.dtype == torch.float32
    with pytest.raises(ValueError, match="at least 2 views"):
        orbit_cameras(cams[0], 5)
    with pytest.raises(ValueError, match="n >= 2"):
        orbit_cameras(cams, 1)


def test_slerp_helpers():
    a = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    b = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    t = torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64)
    s = slerp_unit(a, b, t)
    h = math.sqrt(0.5)
    assert torch.allclose(s, torch.tensor([[1.0, 0, 0], [h, h, 0], [0, 1.0, 0]], dtype=s.dtype))
    Ra = torch.eye(3, dtype=torch.float64)
    c, sn = math.cos(1.2), math.sin(1.2)
    Rb = torch.tensor([[c, -sn, 0], [sn, c, 0], [0, 0, 1]], dtype=torch.float64)
    R = slerp_rotation(Ra, Rb, t)
    c2, s2 = math.cos(0.6), math.sin(0.6)
    half = torch.tensor([[c2, -s2, 0], [s2, c2, 0], [0, 0, 1]], dtype=torch.float64)
    assert torch.allclose(R[0], Ra) and torch.allclose(R[2], Rb) and torch.allclose(R[1], half)
