import torch
from tests.mvs.synth import make_cameras

from svolsdf.mvs.warping import homo_warp


def _bilinear(img, u, v, align_corners_quirk):
    """Hand bilinear sample of (C, H, W) at pixel (u, v) with zero padding."""
    C, H, W = img.shape
    if align_corners_quirk:  # CasMVSNet: u/((W-1)/2)-1 read with align_corners=False
        u = ((u / ((W - 1) / 2)) * W - 1) / 2
        v = ((v / ((H - 1) / 2)) * H - 1) / 2
    x0, y0 = int(torch.floor(u)), int(torch.floor(v))
    out = torch.zeros(C, dtype=img.dtype)
    for dy in (0, 1):
        for dx in (0, 1):
            x, y = x0 + dx, y0 + dy
            w = (1 - abs(u - x)) * (1 - abs(v - y))
            if 0 <= x < W and 0 <= y < H:
                out = out + w * img[:, y, x]
    return out


def _slow_warp(src_img, cams, ref, src, depths, quirk):
    """Per-pixel loop: unproject with the reference camera, project with the source camera."""
    D, H, W = depths.shape
    out = torch.zeros(src_img.shape[0], D, H, W, dtype=torch.float64)
    for k in range(D):
        for y in range(H):
            for x in range(W):
                uv = torch.tensor([[[float(x), float(y)]]], dtype=torch.float64)
                X = cams[ref].unproject(uv, depths[k, y, x].view(1, 1).double())
                p, z = cams[src].project(X[0])
                out[:, k, y, x] = _bilinear(src_img.double(), p[0, 0, 0], p[0, 0, 1], quirk)
    return out


def _setup():
    W, H = 12, 9
    cams = make_cameras(W, H)
    g = torch.Generator().manual_seed(0)
    src_img = torch.rand(2, H, W, generator=g, dtype=torch.float64)
    depths = 3.6 + 0.8 * torch.rand(3, H, W, generator=g, dtype=torch.float64)
    return cams, src_img, depths


def test_homo_warp_matches_slow_reference():
    cams, src_img, depths = _setup()
    P = cams.proj
    for quirk in (False, True):
        warped, valid = homo_warp(src_img[None], P[1:2], P[0:1], depths[None],
                                  align_corners_quirk=quirk)
        ref = _slow_warp(src_img, cams, 0, 1, depths, quirk)
        assert warped.shape == (1, 2, 3, 9, 12)
        assert torch.allclose(warped[0], ref, atol=1e-6), (warped[0] - ref).abs().max()
        assert valid.any() and not valid.all()


def test_quirk_differs_from_correct():
    cams, src_img, depths = _setup()
    P = cams.proj
    a, _ = homo_warp(src_img[None], P[1:2], P[0:1], depths[None])
    b, _ = homo_warp(src_img[None], P[1:2], P[0:1], depths[None], align_corners_quirk=True)
    assert (a - b).abs().max() > 1e-3


def test_valid_mask_matches_projection_bounds():
    cams, src_img, depths = _setup()
    P = cams.proj
    _, valid = homo_warp(src_img[None], P[1:2], P[0:1], depths[None])
    H, W = depths.shape[1:]
    uv = cams.pixel_grid(dtype=torch.float64).reshape(1, -1, 2)
    for k in range(depths.shape[0]):
        X = cams[0].unproject(uv, depths[k].reshape(1, -1))
        p, z = cams[1].project(X[0])
        inside = (p[0, :, 0] >= 0) & (p[0, :, 0] <= W - 1) & (p[0, :, 1] >= 0) \
            & (p[0, :, 1] <= H - 1) & (z[0] > 0)
        assert torch.equal(inside.reshape(H, W), valid[0, k])


def test_gradients_flow_to_features_and_depths():
    cams, src_img, depths = _setup()
    P = cams.proj
    feat = src_img[None].clone().requires_grad_(True)
    d = depths[None].clone().requires_grad_(True)
    warped, _ = homo_warp(feat, P[1:2], P[0:1], d)
    warped.square().sum().backward()
    assert feat.grad is not None and feat.grad.abs().sum() > 0
    assert d.grad is not None and d.grad.abs().sum() > 0
    assert torch.autograd.gradcheck(
        lambda f, dd: homo_warp(f, P[1:2], P[0:1], dd)[0],
        (feat.detach()[:, :, :4, :5].clone().requires_grad_(True),
         d.detach()[:, :1, :3, :4].clone().requires_grad_(True)),
        eps=1e-6, atol=1e-4,
    )
