"""CasMVSNet (METHOD.md 2): FPN features, variance cost volume, 3D U-Net, softmax, regression.

The modules' ``state_dict()`` keys and shapes are exactly those of the official alibaba
cascade-stereo DTU model (METHOD.md 2.1), so its checkpoint loads with ``strict=True``:
``feature.conv0.{0,1}.{conv.weight, bn.*}``, ``feature.conv1.{0,1,2}.*``,
``feature.conv2.{0,1,2}.*``,
``feature.out1.weight``, ``feature.inner{1,2}.{weight,bias}``, ``feature.out{2,3}.weight``,
``cost_regularization.{0,1,2}.{conv0..conv6, conv7, conv9, conv11}.{conv.weight, bn.*}`` and
``cost_regularization.{i}.prob.weight``. There is no refine net and no other parameter.

Memory. At the paper's MVS resolution (1152x1536 network input, METHOD.md 1.3 and 9.2 item 2)
the stage-1 variance volume alone is 32 x 192 x 288 x 384 floats (2.7 GB), and the 3D U-Net's
8-channel full-resolution activations are 0.7 GB each. :meth:`CasMVSNet.regularize` therefore
never builds the cost volume whole: it streams every 3D convolution of the U-Net over rows of the
volume (each row chunk reads only the input rows its 3x3x3 kernel touches, so the result equals the
unchunked network exactly, up to float summation order), and builds the cost volume only for the
rows the first convolution needs. Skip connections are added in place. Peak memory is about
two 8-channel full-size activations plus the chunk budget (``chunk_mb``).

Cameras. The stage-k feature map has stride s = 2^(3-k) in the network input. Its pixel i sits on
input pixel s*i (stride-2 convolutions with symmetric padding centre output i on input 2i), so
stage cameras divide K's first two rows by s, as the released code does (METHOD.md 1.3 step 3).
Image resizes before the network (working size -> x2 MVS size) follow our pixel-centre convention
(`Cameras.resize`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from svolsdf.errors import InputError
from svolsdf.mvs.backbone import (
    MAX_SOURCES,
    MVSBackbone,
    check_depth_ranges,
    register_backbone,
    select_sources,
    upsample_depth,
    volume_from_prob,
)
from svolsdf.mvs.hypotheses import (
    STAGE_DEPTHS,
    base_interval,
    guided_hypotheses,
    interval_ratio,
    plane_hypotheses,
)
from svolsdf.mvs.volume import ProbabilityVolume
from svolsdf.mvs.warping import homo_warp
from svolsdf.scene.cameras import Cameras
from svolsdf.scene.scene import Scene

__all__ = [
    "ConvBnReLU",
    "FeatureNet",
    "CostRegNet",
    "CasMVSNet",
    "load_casmvsnet",
    "CasMVSNetConfig",
    "CasMVSNetBackbone",
    "mvs_input_size",
    "stride_cameras",
]

log = logging.getLogger(__name__)

#: feature channels per stage (METHOD.md 2.2) and the U-Net base channels (METHOD.md 2.4)
STAGE_CHANNELS: tuple[int, int, int] = (32, 16, 8)
REG_BASE = 8


# --------------------------------------------------------------------------- modules
class ConvBnReLU(nn.Module):
    """conv (no bias) + BatchNorm (momentum 0.1) + ReLU (METHOD.md 2.2, 2.4).

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
    """The FPN feature net with base channels 8 (METHOD.md 2.2).

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
        # METHOD.md 2.2: nearest 2x upsampling of the coarser intra feature + lateral 1x1 conv.
        intra = F.interpolate(intra, scale_factor=2.0, mode="nearest") + self.inner1(c1)
        f2 = self.out2(intra)
        intra = F.interpolate(intra, scale_factor=2.0, mode="nearest") + self.inner2(c0)
        f3 = self.out3(intra)
        return [f1, f2, f3]


class CostRegNet(nn.Module):
    """The 3D U-Net cost regularization (METHOD.md 2.4): (B, C, D, H, W) -> (B, 1, D, H, W).

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
            f"(METHOD.md 2.4), got {tuple(x.shape)}"
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
    """skip += layer(x) for a transposed `ConvBnReLU`, in row chunks (METHOD.md 2.4 decoder)."""
    B, C, D, H, W = x.shape
    Ho = skip.shape[-2]
    per_row = 4.0 * B * (C * D * W + 3 * skip.shape[1] * skip.shape[2] * skip.shape[4])
    for a, b in _row_chunks(Ho, per_row, chunk_bytes, even=True):
        skip[..., a:b, :] += layer.post(_deconv_rows(x, layer.conv, a, b))


# --------------------------------------------------------------------------- the network
class CasMVSNet(nn.Module):
    """``CascadeMVSNet(refine=False, share_cr=False, cr_base_chs=[8,8,8], arch_mode="fpn")``.

    Parameter names follow cascade-stereo (METHOD.md 2.1). The hypothesis counts do not change
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
        """Per-stage features of each view, one view at a time (METHOD.md 2.2).

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

        METHOD.md 2.4; source features are warped by `homo_warp` (METHOD.md 2.3) with the
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
            align_corners_quirk: CasMVSNet's warping normalization (METHOD.md 2.3).

        Returns:
            (D, H, W) regularized cost (softmax over D gives the probability, METHOD.md 2.4).
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
        """``DepthNet`` of stage ``k`` up to the probability volume (METHOD.md 2.4).

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
    """Load the official cascade-stereo checkpoint format (METHOD.md 2.1), in eval mode.

    ``torch.load(path)['model']`` loaded with ``strict=True``; a DataParallel ``module.`` prefix is
    stripped. A bare state dict with CasMVSNet keys is accepted too.

    Raises:
        InputError: the file is missing or unreadable, or holds another architecture (the
            message names the file and lists missing and unexpected keys or wrong shapes).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: CasMVSNet weights file not found")
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
            f"(torch.load(path)['model'], METHOD.md 2.1); found {found}"
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
            f"{path}: not the cascade-stereo CasMVSNet architecture (METHOD.md 2.1): "
            + "; ".join(parts)
        )
    model = CasMVSNet()
    model.load_state_dict(sd, strict=True)
    return model.to(device).eval()


def _few(keys: list[str], n: int = 4) -> str:
    return ", ".join(keys[:n]) + (", ..." if len(keys) > n else "")


# --------------------------------------------------------------------------- the backbone
def mvs_input_size(width: int, height: int, x2_mvsres: bool = True) -> tuple[int, int]:
    """Network input (W, H): the working size, doubled with ``x2_mvsres``, rounded to 32.

    METHOD.md 1.3: 576x768 -> 1152x1536 with x2_mvsres; multiples of 32 (METHOD.md 2.4 needs
    H/4 and D divisible by 8).
    """
    s = 2 if x2_mvsres else 1
    return max(32, round(s * width / 32) * 32), max(32, round(s * height / 32) * 32)


def stride_cameras(cameras: Cameras, stride: int) -> Cameras:
    """Cameras of a feature map with ``stride``: K[:2] / stride, size / stride (METHOD.md 1.3).

    Feature pixel i sits on input pixel stride*i (see the module docstring).
    """
    K = cameras.K.clone()
    K[:, :2] /= stride
    return Cameras(K, cameras.w2c.clone(), cameras.width // stride, cameras.height // stride)


@dataclass
class CasMVSNetConfig:
    """Options of the CasMVSNet backbone (METHOD.md 0 and 2)."""

    ndepths: tuple[int, int, int] = STAGE_DEPTHS
    """Hypotheses per stage (METHOD.md 0: 192, 32, 8). Each must be divisible by 8."""
    width_mode: str = "released"
    """Finer-stage search width: "released" (r = 0.5, 0.5, what the checkpoint was run with in
    the released S-VolSDF code) or "paper" ("half the default width"); see
    `svolsdf.mvs.hypotheses`."""
    x2_mvsres: bool = True
    """Run the network on the working-size images upsampled 2x (METHOD.md 1.3, 9.2 item 2); the
    stage-3 volume is then at twice the working size."""
    native_images: bool = False
    """With ``x2_mvsres``, read the images from their files when those are larger than the
    working size (`Scene.images_at`), instead of upsampling the working-size images as the
    released code does (METHOD.md 9.2.2)."""
    inverse_depth: bool = False
    """Stage-1 planes uniform in inverse depth (METHOD.md 2.5, 9.1)."""
    max_sources: int = MAX_SOURCES
    """Source views per reference, the best by pair score (`select_sources`, METHOD.md 1.4: at
    most 4, as released); <= 0: every other loaded view."""
    align_corners_quirk: bool = True
    """Reproduce CasMVSNet's warping normalization (METHOD.md 2.3), which the checkpoint expects."""
    chunk_mb: float | None = 512.0
    """Memory budget in MB of one row chunk of the cost volume / 3D U-Net; None: unchunked."""
    device: str = "cpu"
    """Torch device of the network."""


@register_backbone("casmvsnet")
class CasMVSNetBackbone(MVSBackbone):
    """CasMVSNet as an `MVSBackbone`: stage-by-stage probability volumes (METHOD.md 2).

    Stage k's volume lives at 1/2^(3-k) of the network input size (``mvs_input_size``; with
    ``x2_mvsres`` stage 3 is at twice the scene's working size, stage 1 at half). Its camera is
    the reference camera at that size (`stride_cameras`). Depths are world z-depths.
    """

    config_class = CasMVSNetConfig

    def __init__(self, model: CasMVSNet, config: CasMVSNetConfig | None = None, **cfg):
        self.config = config or CasMVSNetConfig(**cfg)
        if any(d % 8 or d < 8 for d in self.config.ndepths):
            raise InputError(f"CasMVSNet ndepths must be multiples of 8, got {self.config.ndepths}")
        interval_ratio(2, self.config.width_mode)  # validates the name
        self.model = model.to(self.config.device).eval()
        self._cache: tuple | None = None

    @classmethod
    def create(cls, weights=None, **cfg) -> CasMVSNetBackbone:
        if weights is None:
            raise InputError(
                "the 'casmvsnet' backbone needs --weights PATH: the official cascade-stereo DTU "
                "checkpoint (e.g. casmvsnet.ckpt); no CasMVSNet weights ship with svolsdf"
            )
        config = CasMVSNetConfig(**cfg)
        return cls(load_casmvsnet(weights, config.device), config)

    # ----------------------------------------------------------------- preparation
    def prepare(self, scene: Scene) -> tuple[list[Tensor], Cameras]:
        """Network-size features of every view and the cameras at the network input size.

        Images are resized to :func:`mvs_input_size` (`Scene.images_at`: from the files when
        they are larger, else bicubic from the working size); the features
        are cached for the scene's images tensor, so the three stages compute them once.

        Returns:
            feats: [(V, 32, H/4, W/4), (V, 16, H/2, W/2), (V, 8, H, W)].
            cameras: (V) cameras at the network input size (W, H).
        """
        if scene.images is None:
            raise InputError(f"{scene.path}: the scene was loaded without images")
        c = self._cache
        if c is not None and c[0] is scene.images and c[1] == tuple(scene.view_ids):
            return c[2], c[3]
        Wn, Hn = mvs_input_size(scene.width, scene.height, self.config.x2_mvsres)
        dev = self.config.device
        images = scene.images_at(Wn, Hn, from_files=self.config.native_images).to(
            dev, torch.float32)
        cams = scene.cameras.resize(Wn, Hn).to(dev, torch.float32)
        log.info("CasMVSNet: features of %d views at %dx%d", len(scene), Wn, Hn)
        feats = self.model.features(images)
        self._cache = (scene.images, tuple(scene.view_ids), feats, cams)
        return feats, cams

    # ----------------------------------------------------------------- stages
    @torch.no_grad()
    def stage(
        self,
        k: int,
        scene: Scene,
        ref_ids: list[int] | None = None,
        guide_depth: dict[int, Tensor] | None = None,
        prev: dict[int, ProbabilityVolume] | None = None,
    ) -> list[ProbabilityVolume]:
        """Run stage ``k`` (1..3) for ``ref_ids`` (see `MVSBackbone.stage`).

        Stage 1: ``ndepths[0]`` planes over each view's depth range. Stages 2-3: hypotheses centred
        on ``guide_depth[view]`` or else ``prev[view].depth``, bilinearly upsampled to the network
        input size and resized to the stage (METHOD.md 2.5), interval r * Δ̄ with r from
        ``width_mode``.
        """
        if k not in (1, 2, 3):
            raise ValueError(f"stage must be 1, 2 or 3, got {k}")
        ref_ids = list(scene.view_ids if ref_ids is None else ref_ids)
        check_depth_ranges(scene, ref_ids)
        feats, cams = self.prepare(scene)
        s = 2 ** (3 - k)
        scams = stride_cameras(cams, s)
        Wk, Hk = scams.width, scams.height
        D = self.config.ndepths[k - 1]
        projs = scams.proj
        out = []
        for vid in ref_ids:
            i = scene.index(vid)
            near, far = (float(x) for x in scene.depth_range[i])
            if k == 1:
                depths = plane_hypotheses(near, far, D, Hk, Wk, self.config.inverse_depth,
                                          device=projs.device)
            else:
                centre = _guide(vid, k, guide_depth, prev)
                centre = upsample_depth(centre.to(projs.device), cams.width, cams.height)
                if s > 1:  # METHOD.md 2.5 step 3 (trilinear resize; along D it is the identity)
                    centre = F.interpolate(centre[None, None], size=(Hk, Wk), mode="bilinear",
                                           align_corners=False)[0, 0]
                r = interval_ratio(k, self.config.width_mode)
                depths = guided_hypotheses(centre, D, r * base_interval(near, far))
            order = [i] + [scene.index(v) for v in
                           select_sources(scene, vid, self.config.max_sources)]
            prob = self.model.depth_stage(
                k, feats[k - 1][order], projs[order], depths, self.config.chunk_mb,
                self.config.align_corners_quirk,
            )
            out.append(volume_from_prob(prob, depths, scams[i], vid, k,
                                        self.config.inverse_depth and k == 1))
        return out


def _guide(vid, k, guide_depth, prev) -> Tensor:
    if guide_depth is not None and vid in guide_depth:
        g = torch.as_tensor(guide_depth[vid], dtype=torch.float32)
    elif prev is not None and vid in prev:
        g = prev[vid].depth.float()
    else:
        raise ValueError(f"stage {k} of view {vid} needs a guide depth or the previous volume")
    if g.ndim != 2:
        raise ValueError(f"guide depth of view {vid} must be (H, W), got {tuple(g.shape)}")
    return g
