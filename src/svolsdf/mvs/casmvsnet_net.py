"""The CasMVSNet network (docs/method.md 2): FPN features, variance cost volume, 3D U-Net, softmax,
and the loader of the official checkpoint.

`svolsdf.mvs.casmvsnet` wraps it as an `MVSBackbone`; its module docstring gives the checkpoint's
key layout (docs/method.md 2.1), how :meth:`CasMVSNet.regularize` streams the cost volume and the
U-Net over rows to bound memory, and the stage cameras.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from svolsdf.errors import InputError
from svolsdf.mvs.warping import homo_warp

__all__ = [
    "ConvBnReLU",
    "FeatureNet",
    "CostRegNet",
    "CasMVSNet",
    "load_casmvsnet",
    "REG_BASE",
    "STAGE_CHANNELS",
]

#: feature channels per stage (docs/method.md 2.2) and the U-Net base channels (docs/method.md 2.4)
STAGE_CHANNELS: tuple[int, int, int] = (32, 16, 8)
REG_BASE = 8


# --------------------------------------------------------------------------- modules
class ConvBnReLU(nn.Module):
    """conv (no bias) + BatchNorm (momentum 0.1) + ReLU (docs/method.md 2.2, 2.4).

    The child names ``conv`` and ``bn`` are cascade-stereo's ``Conv2d``/``Conv3d``/``Deconv3d``.
    """

    def __init__(self, conv: nn.Module, bn: nn.Module):
        super().__init__()
        self.conv = conv
        self.bn = bn

    def post(self, y: Tensor) -> Tensor:
        """BatchNorm + ReLU of a convolution output (pointwise in space)."""
        return F.relu(self.bn(y), inplace=True)

    def forward(self, x: Tensor) -> Tensor:
        return self.post(self.conv(x))


def _conv2d(cin: int, cout: int, k: int, stride: int = 1) -> ConvBnReLU:
    return ConvBnReLU(
        nn.Conv2d(cin, cout, k, stride=stride, padding=k // 2, bias=False),
        nn.BatchNorm2d(cout, momentum=0.1),
    )


def _conv3d(cin: int, cout: int, stride: int = 1) -> ConvBnReLU:
    return ConvBnReLU(
        nn.Conv3d(cin, cout, 3, stride=stride, padding=1, bias=False),
        nn.BatchNorm3d(cout, momentum=0.1),
    )


def _deconv3d(cin: int, cout: int) -> ConvBnReLU:
    return ConvBnReLU(
        nn.ConvTranspose3d(cin, cout, 3, stride=2, padding=1, output_padding=1, bias=False),
        nn.BatchNorm3d(cout, momentum=0.1),
    )


class FeatureNet(nn.Module):
    """The FPN feature net with base channels 8 (docs/method.md 2.2).

    Input RGB in [0, 1], no mean/std normalization. Output features per stage:
    (B, 32, H/4, W/4), (B, 16, H/2, W/2), (B, 8, H, W).
    """

    def __init__(self, base: int = 8):
        super().__init__()
        b = base
        self.conv0 = nn.Sequential(_conv2d(3, b, 3), _conv2d(b, b, 3))
        self.conv1 = nn.Sequential(_conv2d(b, 2 * b, 5, 2), _conv2d(2 * b, 2 * b, 3),
                                   _conv2d(2 * b, 2 * b, 3))
        self.conv2 = nn.Sequential(_conv2d(2 * b, 4 * b, 5, 2), _conv2d(4 * b, 4 * b, 3),
                                   _conv2d(4 * b, 4 * b, 3))
        self.out1 = nn.Conv2d(4 * b, 4 * b, 1, bias=False)
        self.inner1 = nn.Conv2d(2 * b, 4 * b, 1, bias=True)
        self.inner2 = nn.Conv2d(b, 4 * b, 1, bias=True)
        self.out2 = nn.Conv2d(4 * b, 2 * b, 3, padding=1, bias=False)
        self.out3 = nn.Conv2d(4 * b, b, 3, padding=1, bias=False)

    def forward(self, x: Tensor) -> list[Tensor]:
        """(B, 3, H, W) images (H, W multiples of 4) -> [stage-1, stage-2, stage-3 features]."""
        if x.ndim != 4 or x.shape[1] != 3:
            raise ValueError(f"FeatureNet expects (B, 3, H, W) images, got {tuple(x.shape)}")
        c0 = self.conv0(x)
        c1 = self.conv1(c0)
        intra = self.conv2(c1)
        f1 = self.out1(intra)
        # docs/method.md 2.2: nearest 2x upsampling of the coarser intra feature + lateral 1x1 conv.
        intra = F.interpolate(intra, scale_factor=2.0, mode="nearest") + self.inner1(c1)
        f2 = self.out2(intra)
        intra = F.interpolate(intra, scale_factor=2.0, mode="nearest") + self.inner2(c0)
        f3 = self.out3(intra)
        return [f1, f2, f3]


class CostRegNet(nn.Module):
    """The 3D U-Net cost regularization (docs/method.md 2.4): (B, C, D, H, W) -> (B, 1, D, H, W).

    D, H and W must be divisible by 8.
    """

    def __init__(self, in_channels: int, base: int = REG_BASE):
        super().__init__()
        b = base
        self.conv0 = _conv3d(in_channels, b)
        self.conv1 = _conv3d(b, 2 * b, 2)
        self.conv2 = _conv3d(2 * b, 2 * b)
        self.conv3 = _conv3d(2 * b, 4 * b, 2)
        self.conv4 = _conv3d(4 * b, 4 * b)
        self.conv5 = _conv3d(4 * b, 8 * b, 2)
        self.conv6 = _conv3d(8 * b, 8 * b)
        self.conv7 = _deconv3d(8 * b, 4 * b)
        self.conv9 = _deconv3d(4 * b, 2 * b)
        self.conv11 = _deconv3d(2 * b, b)
        self.prob = nn.Conv3d(b, 1, 3, stride=1, padding=1, bias=False)

    def body(self, c0: Tensor) -> Tensor:
        """Everything after ``conv0``: (B, 8, D, H, W) -> (B, 1, D, H, W) logits."""
        c2 = self.conv2(self.conv1(c0))
        c4 = self.conv4(self.conv3(c2))
        x = self.conv6(self.conv5(c4))
        x = c4 + self.conv7(x)
        x = c2 + self.conv9(x)
        x = c0 + self.conv11(x)
        return self.prob(x)

    def forward(self, x: Tensor) -> Tensor:
        _check_divisible(x)
        return self.body(self.conv0(x))

    def body_streamed(self, c0: Tensor, chunk_bytes: int) -> Tensor:
        """:meth:`body` computed in row chunks, equal to it up to summation order.

        Every convolution is evaluated for a few output rows at a time from the input rows its
        kernel touches (:func:`_conv_rows`, :func:`_deconv_rows`); skip connections are added in
        place, so ``c0`` is overwritten (pass a tensor you no longer need).

        Args:
            c0: (1, 8, D, H, W) output of ``conv0``.
            chunk_bytes: memory budget of one chunk's temporaries.

        Returns:
            (1, 1, D, H, W) logits.
        """
        _check_divisible(c0)
        c2 = _stream_conv(self.conv2, _stream_conv(self.conv1, c0, 2, chunk_bytes), 1, chunk_bytes)
        c4 = _stream_conv(self.conv4, _stream_conv(self.conv3, c2, 2, chunk_bytes), 1, chunk_bytes)
        x = _stream_conv(self.conv6, _stream_conv(self.conv5, c4, 2, chunk_bytes), 1, chunk_bytes)
        _stream_deconv_add(self.conv7, x, c4, chunk_bytes)
        del x
        _stream_deconv_add(self.conv9, c4, c2, chunk_bytes)
        del c4
        _stream_deconv_add(self.conv11, c2, c0, chunk_bytes)
        del c2
        return _stream_conv(self.prob, c0, 1, chunk_bytes)


def _check_divisible(x: Tensor) -> None:
    if x.ndim != 5 or any(s % 8 for s in x.shape[2:]):
        raise ValueError(
            f"CostRegNet needs a (B, C, D, H, W) volume with D, H, W divisible by 8 "
            f"(docs/method.md 2.4), got {tuple(x.shape)}"
        )


# --------------------------------------------------------------------------- row streaming
def _conv_rows(x: Tensor, conv: nn.Conv3d, stride: int, a: int, b: int) -> Tensor:
    """Output rows [a, b) of ``conv(x)`` (k3, padding 1, ``stride``) from the rows they need.

    Args:
        x: (B, C, D, H, W).

    Returns:
        (B, C', D', b - a, W') exactly the rows of the full convolution.
    """
    H = x.shape[-2]
    lo, hi = stride * a - 1, stride * (b - 1) + 2  # input rows [lo, hi) incl. zero padding
    xs = x[..., max(lo, 0): min(hi, H), :]
    if lo < 0 or hi > H:
        xs = F.pad(xs, (0, 0, max(0, -lo), max(0, hi - H)))
    return F.conv3d(xs, conv.weight, conv.bias, stride=stride, padding=(1, 0, 1))


def _deconv_rows(x: Tensor, conv: nn.ConvTranspose3d, a: int, b: int) -> Tensor:
    """Output rows [a, b) (a, b even) of ``conv(x)`` (k3, stride 2, padding 1, output pad 1).

    Output row o receives input row o/2 (o even) or (o +- 1)/2 (o odd), so rows [a, b) need input
    rows [a/2, b/2] (the last clipped at the border, where the full result has zeros too).
    """
    Hin = x.shape[-2]
    i0, i1 = a // 2, min(b // 2 + 1, Hin)
    y = F.conv_transpose3d(x[..., i0:i1, :], conv.weight, conv.bias, stride=2, padding=1,
                           output_padding=1)
    return y[..., : b - a, :]


def _row_chunks(rows: int, per_row_bytes: float, chunk_bytes: int, even: bool = False):
    n = max(1, int(chunk_bytes // max(per_row_bytes, 1.0)))
    if even:
        n = max(2, n - n % 2)
    for a in range(0, rows, n):
        yield a, min(rows, a + n)


def _stream_conv(layer: nn.Module, x: Tensor, stride: int, chunk_bytes: int) -> Tensor:
    """``layer(x)`` for a `ConvBnReLU` (3D) or a plain ``nn.Conv3d``, computed in row chunks."""
    conv = layer.conv if isinstance(layer, ConvBnReLU) else layer
    B, C, D, H, W = x.shape
    Ho = H // stride
    out = x.new_empty(B, conv.out_channels, D // stride, Ho, W // stride)
    # temporaries per output row: the input rows read (plus a layout copy) and the output row
    per_row = 8.0 * B * (C * D * W * stride + conv.out_channels * out.shape[2] * out.shape[4])
    for a, b in _row_chunks(Ho, per_row, chunk_bytes):
        y = _conv_rows(x, conv, stride, a, b)
        out[..., a:b, :] = layer.post(y) if isinstance(layer, ConvBnReLU) else y
    return out


def _stream_deconv_add(layer: ConvBnReLU, x: Tensor, skip: Tensor, chunk_bytes: int) -> None:
    """skip += layer(x) for a transposed `ConvBnReLU`, in row chunks (docs/method.md 2.4
    decoder)."""
    B, C, D, H, W = x.shape
    Ho = skip.shape[-2]
    per_row = 4.0 * B * (C * D * W + 3 * skip.shape[1] * skip.shape[2] * skip.shape[4])
    for a, b in _row_chunks(Ho, per_row, chunk_bytes, even=True):
        skip[..., a:b, :] += layer.post(_deconv_rows(x, layer.conv, a, b))


# --------------------------------------------------------------------------- the network
class CasMVSNet(nn.Module):
    """``CascadeMVSNet(refine=False, share_cr=False, cr_base_chs=[8,8,8], arch_mode="fpn")``.

    Parameter names follow cascade-stereo (docs/method.md 2.1). The hypothesis counts do not change
    any parameter shape. Use in eval mode (BatchNorm with running statistics), as released.
    """

    def __init__(self):
        super().__init__()
        self.feature = FeatureNet(8)
        self.cost_regularization = nn.ModuleList(
            [CostRegNet(c, REG_BASE) for c in STAGE_CHANNELS]
        )

    @torch.no_grad()
    def features(self, images: Tensor) -> list[Tensor]:
        """Per-stage features of each view, one view at a time (docs/method.md 2.2).

        Args:
            images: (V, 3, H, W) RGB in [0, 1], H and W multiples of 32.

        Returns:
            [(V, 32, H/4, W/4), (V, 16, H/2, W/2), (V, 8, H, W)].
        """
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"images must be (V, 3, H, W), got {tuple(images.shape)}")
        H, W = images.shape[-2:]
        if H % 32 or W % 32:
            raise ValueError(f"CasMVSNet needs H and W divisible by 32, got {W}x{H}")
        per_view = [self.feature(images[v: v + 1]) for v in range(images.shape[0])]
        return [torch.cat([f[k] for f in per_view]) for k in range(3)]

    def cost_volume_rows(
        self, feats: Tensor, projs: Tensor, depths: Tensor, a: int, b: int,
        align_corners_quirk: bool = True,
    ) -> Tensor:
        """Variance cost volume C = mean_v F_v^2 - (mean_v F_v)^2 of reference rows [a, b).

        docs/method.md 2.4; source features are warped by `homo_warp` (docs/method.md 2.3) with the
        reference camera cropped to the rows, so the result equals rows [a, b) of the full volume.

        Args:
            feats: (V, C, H, W) features, the reference first.
            projs: (V, 4, 4) projections [K E; 0 0 0 1] at the features' size.
            depths: (D, H, W) reference hypotheses.
            a, b: row range, 0 <= a < b <= H.

        Returns:
            (1, C, D, b - a, W).
        """
        V, C, H, W = feats.shape
        D = depths.shape[0]
        crop = torch.eye(4, dtype=projs.dtype, device=projs.device)
        crop[1, 2] = -a  # y' = y - a
        ref_proj = (crop @ projs[0])[None]
        dep = depths[None, :, a:b]
        ref = feats[0:1, :, None, a:b].expand(1, C, D, b - a, W)
        vsum = ref.clone()
        vsq = ref.pow(2)
        for v in range(1, V):
            warped, _ = homo_warp(feats[v: v + 1], projs[v: v + 1], ref_proj, dep,
                                  align_corners_quirk=align_corners_quirk)
            vsum += warped
            vsq += warped.pow_(2)
            del warped
        return vsq.div_(V).sub_(vsum.div_(V).pow_(2))

    @torch.no_grad()
    def regularize(
        self, k: int, feats: Tensor, projs: Tensor, depths: Tensor,
        chunk_mb: float | None = 512.0, align_corners_quirk: bool = True,
    ) -> Tensor:
        """Stage ``k``'s cost volume through its 3D U-Net: logits over the hypotheses.

        Args:
            k: stage 1, 2 or 3 (selects ``cost_regularization[k - 1]``).
            feats: (V, C_k, H, W) stage features, the reference first.
            projs: (V, 4, 4) projections at (W, H).
            depths: (D, H, W) hypotheses; D, H, W divisible by 8.
            chunk_mb: memory budget per chunk in MB; None builds the volume whole and runs the
                U-Net unchunked (the reference the chunked path is tested against).
            align_corners_quirk: CasMVSNet's warping normalization (docs/method.md 2.3).

        Returns:
            (D, H, W) regularized cost (softmax over D gives the probability, docs/method.md 2.4).
        """
        if self.training:
            raise RuntimeError("CasMVSNet runs in eval mode (BatchNorm running statistics)")
        V, C, H, W = feats.shape
        D = depths.shape[0]
        if depths.shape[1:] != (H, W) or projs.shape != (V, 4, 4):
            raise ValueError(
                f"stage {k}: features {tuple(feats.shape)}, projections {tuple(projs.shape)} "
                f"and hypotheses {tuple(depths.shape)} disagree"
            )
        reg = self.cost_regularization[k - 1]
        if chunk_mb is None:
            cost = self.cost_volume_rows(feats, projs, depths, 0, H, align_corners_quirk)
            return reg(cost)[0, 0]
        if D % 8 or H % 8 or W % 8:
            raise ValueError(f"stage {k}: D, H, W must be divisible by 8, got {(D, H, W)}")
        chunk = int(chunk_mb * 2**20)
        # conv0 streamed together with the cost volume: rows [a, b) need cost rows [a-1, b+1).
        c0 = feats.new_empty(1, reg.conv0.conv.out_channels, D, H, W)
        per_row = 4.0 * D * W * (4 * C + 12) + 8.0 * reg.conv0.conv.out_channels * D * W
        for a, b in _row_chunks(H, per_row, chunk):
            lo, hi = max(0, a - 1), min(H, b + 1)
            cost = self.cost_volume_rows(feats, projs, depths, lo, hi, align_corners_quirk)
            c0[..., a:b, :] = reg.conv0.post(_conv_rows(cost, reg.conv0.conv, 1, a - lo, b - lo))
            del cost
        return reg.body_streamed(c0, chunk)[0, 0]

    @torch.no_grad()
    def depth_stage(
        self, k: int, feats: Tensor, projs: Tensor, depths: Tensor,
        chunk_mb: float | None = 512.0, align_corners_quirk: bool = True,
    ) -> Tensor:
        """``DepthNet`` of stage ``k`` up to the probability volume (docs/method.md 2.4).

        Args: as :meth:`regularize`.

        Returns:
            (D, H, W) probabilities, softmax over D. Depth and confidence follow from
            `svolsdf.mvs.backbone.volume_from_prob`.
        """
        logits = self.regularize(k, feats, projs, depths, chunk_mb, align_corners_quirk)
        return torch.softmax(logits, dim=0)


# --------------------------------------------------------------------------- loading
def _expected_shapes() -> dict[str, tuple[int, ...]]:
    return {k: tuple(v.shape) for k, v in CasMVSNet().state_dict().items()}


def load_casmvsnet(path, device=None) -> CasMVSNet:
    """Load the official cascade-stereo checkpoint format (docs/method.md 2.1), in eval mode.

    ``torch.load(path)['model']`` loaded with ``strict=True``; a DataParallel ``module.`` prefix is
    stripped. A bare state dict with CasMVSNet keys is accepted too.

    Raises:
        InputError: the file is missing or unreadable, or holds another architecture (the
            message names the file and lists missing and unexpected keys or wrong shapes).
    """
    from svolsdf.io.paths import input_file

    path = input_file(path, "CasMVSNet weights file")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unpickling failure is bad input
        raise InputError(f"{path}: cannot read as a PyTorch checkpoint ({e})") from None
    if isinstance(ckpt, dict) and isinstance(ckpt.get("model"), dict):
        sd = ckpt["model"]
    elif isinstance(ckpt, dict) and any(str(k).endswith("feature.conv0.0.conv.weight")
                                        for k in ckpt):
        sd = ckpt
    else:
        found = list(ckpt)[:8] if isinstance(ckpt, dict) else type(ckpt).__name__
        raise InputError(
            f"{path}: expected a checkpoint dict with a 'model' state dict "
            f"(torch.load(path)['model'], docs/method.md 2.1); found {found}"
        )
    if sd and all(str(k).startswith("module.") for k in sd):
        sd = {k[len("module."):]: v for k, v in sd.items()}
    expected = _expected_shapes()
    missing = [k for k in expected if k not in sd]
    unexpected = [k for k in sd if k not in expected]
    wrong = [
        f"{k} {tuple(sd[k].shape)} (expected {expected[k]})"
        for k in expected
        if k in sd and isinstance(sd[k], Tensor) and tuple(sd[k].shape) != expected[k]
    ]
    if missing or unexpected or wrong:
        parts = []
        if missing:
            parts.append(f"{len(missing)} missing keys ({_few(missing)})")
        if unexpected:
            parts.append(f"{len(unexpected)} unexpected keys ({_few(unexpected)})")
        if wrong:
            parts.append(f"{len(wrong)} keys with wrong shapes ({_few(wrong)})")
        raise InputError(
            f"{path}: not the cascade-stereo CasMVSNet architecture (docs/method.md 2.1): "
            + "; ".join(parts)
        )
    model = CasMVSNet()
    model.load_state_dict(sd, strict=True)
    return model.to(device).eval()


def _few(keys: list[str], n: int = 4) -> str:
    return ", ".join(keys[:n]) + (", ..." if len(keys) > n else "")
