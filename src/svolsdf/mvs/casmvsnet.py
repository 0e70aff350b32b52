"""CasMVSNet (docs/method.md 2): FPN features, variance cost volume, 3D U-Net, softmax, regression.

The modules' ``state_dict()`` keys and shapes are exactly those of the official alibaba
cascade-stereo DTU model (docs/method.md 2.1), so its checkpoint loads with ``strict=True``:
``feature.conv0.{0,1}.{conv.weight, bn.*}``, ``feature.conv1.{0,1,2}.*``,
``feature.conv2.{0,1,2}.*``,
``feature.out1.weight``, ``feature.inner{1,2}.{weight,bias}``, ``feature.out{2,3}.weight``,
``cost_regularization.{0,1,2}.{conv0..conv6, conv7, conv9, conv11}.{conv.weight, bn.*}`` and
``cost_regularization.{i}.prob.weight``. There is no refine net and no other parameter.

Memory. At the paper's MVS resolution (1152x1536 network input, docs/method.md 1.3 and 9.2 item 2)
the stage-1 variance volume alone is 32 x 192 x 288 x 384 floats (2.7 GB), and the 3D U-Net's
8-channel full-resolution activations are 0.7 GB each. :meth:`CasMVSNet.regularize` therefore
never builds the cost volume whole: it streams every 3D convolution of the U-Net over rows of the
volume (each row chunk reads only the input rows its 3x3x3 kernel touches, so the result equals the
unchunked network exactly, up to float summation order), and builds the cost volume only for the
rows the first convolution needs. Skip connections are added in place. Peak memory is about
two 8-channel full-size activations plus the chunk budget (``chunk_mb``).

Cameras. The stage-k feature map has stride s = 2^(3-k) in the network input. Its pixel i sits on
input pixel s*i (stride-2 convolutions with symmetric padding centre output i on input 2i), so
stage cameras divide K's first two rows by s, as the released code does (docs/method.md 1.3 step 3).
Image resizes before the network (working size -> x2 MVS size) follow our pixel-centre convention
(`Cameras.resize`).

The network modules and the checkpoint loader are in `svolsdf.mvs.casmvsnet_net`; this module is
the backbone around them (input sizes, stage cameras and hypotheses).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from svolsdf.errors import InputError
from svolsdf.io.progress import progress_bar
from svolsdf.mvs.backbone import (
    MAX_SOURCES,
    MVSBackbone,
    check_depth_ranges,
    register_backbone,
    select_sources,
    upsample_depth,
    volume_from_prob,
)
from svolsdf.mvs.casmvsnet_net import CasMVSNet, load_casmvsnet
from svolsdf.mvs.hypotheses import (
    STAGE_DEPTHS,
    base_interval,
    guided_hypotheses,
    interval_ratio,
    plane_hypotheses,
)
from svolsdf.mvs.volume import ProbabilityVolume
from svolsdf.scene.cameras import Cameras
from svolsdf.scene.scene import Scene

__all__ = ["CasMVSNetConfig", "CasMVSNetBackbone", "mvs_input_size", "stride_cameras"]

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- the backbone
def mvs_input_size(width: int, height: int, x2_mvsres: bool = True,
                   scale: float | None = None) -> tuple[int, int]:
    """Network input (W, H): the working size times ``scale`` (None: 2 with ``x2_mvsres``,
    else 1), rounded to 32.

    docs/method.md 1.3: 576x768 -> 1152x1536 with x2_mvsres; multiples of 32 (docs/method.md 2.4
    needs H/4 and D divisible by 8). The paper's mid resolution, 864x1152 with the network at
    1152x1536, is ``scale`` 4/3.
    """
    s = float(scale) if scale is not None else (2 if x2_mvsres else 1)
    return max(32, round(s * width / 32) * 32), max(32, round(s * height / 32) * 32)


def stride_cameras(cameras: Cameras, stride: int) -> Cameras:
    """Cameras of a feature map with ``stride``: K[:2] / stride, size / stride (docs/method.md 1.3).

    Feature pixel i sits on input pixel stride*i (see the module docstring).
    """
    K = cameras.K.clone()
    K[:, :2] /= stride
    return Cameras(K, cameras.w2c.clone(), cameras.width // stride, cameras.height // stride)


@dataclass
class CasMVSNetConfig:
    """Options of the CasMVSNet backbone (docs/method.md 0 and 2)."""

    ndepths: tuple[int, int, int] = STAGE_DEPTHS
    """Hypotheses per stage (docs/method.md 0: 192, 32, 8). Each must be divisible by 8."""
    width: str = "released"
    """Finer-stage search width: "released" (r = 0.5, 0.5, what the checkpoint was run with in
    the released S-VolSDF code), "paper" (the same, the paper's explicit numbers) or
    "half-default" (r = 1, 0.5); see `svolsdf.mvs.hypotheses`."""
    x2_mvsres: bool = True
    """Run the network on the working-size images upsampled 2x (docs/method.md 1.3, 9.2 item 2); the
    stage-3 volume is then at twice the working size."""
    scale: float | None = None
    """Network input at this many times the working size (rounded to multiples of 32),
    instead of ``x2_mvsres``'s 2 or 1 (`mvs_input_size`; ``mvs.scale`` other than 1 and 2).
    None: ``x2_mvsres`` decides."""
    native_images: bool = False
    """With ``x2_mvsres``, read the images from their files when those are larger than the
    working size (`Scene.images_at`), instead of upsampling the working-size images as the
    released code does (docs/method.md 9.2.2)."""
    inverse_depth: bool = False
    """Stage-1 planes uniform in inverse depth (docs/method.md 2.5, 9.1)."""
    max_sources: int = MAX_SOURCES
    """Source views per reference, the best by pair score (`select_sources`, docs/method.md 1.4: at
    most 4, as released); <= 0: every other loaded view."""
    align_corners_quirk: bool = True
    """Reproduce CasMVSNet's warping normalization (docs/method.md 2.3), which the checkpoint
    expects."""
    chunk_mb: float | None = 512.0
    """Memory budget in MB of one row chunk of the cost volume / 3D U-Net; None: unchunked."""
    device: str = "cpu"
    """Torch device of the network."""


@register_backbone("casmvsnet")
class CasMVSNetBackbone(MVSBackbone):
    """CasMVSNet as an `MVSBackbone`: stage-by-stage probability volumes (docs/method.md 2).

    Stage k's volume lives at 1/2^(3-k) of the network input size (``mvs_input_size``; with
    ``x2_mvsres`` stage 3 is at twice the scene's working size, stage 1 at half). Its camera is
    the reference camera at that size (`stride_cameras`). Depths are world z-depths.
    """

    config_class = CasMVSNetConfig
    signature_names = {"width": "width_mode"}

    @classmethod
    def scale_problem(cls, scale: float | None) -> str | None:
        """None: CasMVSNet runs at any ``mvs.scale`` > 0 (its input rounded to multiples of
        32, `mvs_input_size`); 1 and 2 are ``x2_mvsres``, others ``scale``."""
        return None

    @classmethod
    def options(cls, mvs) -> dict:
        """`MVSBackbone.options`, with ``scale`` for an ``mvs.scale`` other than 1 and 2 (the
        paper's mid resolution needs 4/3)."""
        kw = super().options(mvs)
        if mvs.scale is not None and float(mvs.scale) not in (1.0, 2.0):
            kw["scale"] = float(mvs.scale)
        return kw

    def __init__(self, model: CasMVSNet, config: CasMVSNetConfig | None = None, **cfg):
        self.config = config or CasMVSNetConfig(**cfg)
        if any(d % 8 or d < 8 for d in self.config.ndepths):
            raise InputError(f"CasMVSNet ndepths must be multiples of 8, got {self.config.ndepths}")
        interval_ratio(2, self.config.width)  # validates the name
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
        Wn, Hn = mvs_input_size(scene.width, scene.height, self.config.x2_mvsres,
                                self.config.scale)
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
        input size and resized to the stage (docs/method.md 2.5), interval r * Δ̄ with r from
        ``width``.
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
        for vid in progress_bar(ref_ids, desc=f"MVS stage {k} (CasMVSNet)"):
            i = scene.index(vid)
            near, far = (float(x) for x in scene.depth_range[i])
            if k == 1:
                depths = plane_hypotheses(near, far, D, Hk, Wk, self.config.inverse_depth,
                                          device=projs.device)
            else:
                centre = _guide(vid, k, guide_depth, prev)
                centre = upsample_depth(centre.to(projs.device), cams.width, cams.height)
                # docs/method.md 2.5 step 3 (trilinear resize; along D it is the identity)
                if s > 1:
                    centre = F.interpolate(centre[None, None], size=(Hk, Wk), mode="bilinear",
                                           align_corners=False)[0, 0]
                r = interval_ratio(k, self.config.width)
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
