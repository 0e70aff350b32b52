"""Backbones that wrap a depth + confidence network into probability volumes.

A network that predicts one depth d̂ and a confidence c in [0, 1] per pixel (PatchmatchNet and its
kind) has no probability volume. `DepthConfidenceAdapter` makes one on each stage's hypotheses
(METHOD.md 2.5) as a discretized Laplacian centred on d̂ whose scale grows as the confidence drops:

    b = Δ · (b_min + (1 - c) (b_max - b_min))

where Δ is the stage's hypothesis spacing at that pixel, (d_last - d_first)/(D - 1), so b is
"in units of the hypothesis interval" at every stage. The hypotheses d_0 < ... < d_{D-1} split the
depth axis into bins with edges e_0 = -inf, e_k = (d_{k-1} + d_k)/2, e_D = +inf, and

    P_k = F(e_{k+1}) - F(e_k),   F = CDF of Laplace(d̂, b),

so the probabilities sum to 1 exactly, stay finite for any b (no exp underflow to 0/0), and a d̂
outside the hypothesis range puts its mass on the nearest end bin (the open outer bins). The
volume's depth and confidence are then the expectation and the 4-bin sum (METHOD.md 2.4), like
every backbone's.

The network runs once per reference view (at the scene's working size, or ``net_size``); each stage
only rebuilds the distribution on its own hypotheses, centred on the guide depth or the previous
stage's depth at stages 2-3 like the cascade.
"""

from __future__ import annotations

import logging
import warnings
from abc import abstractmethod
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from svolsdf.errors import InputError
from svolsdf.mvs.backbone import (
    MAX_SOURCES,
    MVSBackbone,
    check_depth_ranges,
    register_backbone,
    select_sources,
    stage_cameras,
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
from svolsdf.scene.cameras import Cameras
from svolsdf.scene.scene import Scene

__all__ = [
    "laplacian_prob",
    "confidence_scale",
    "AdapterConfig",
    "DepthConfidenceAdapter",
    "PatchmatchNetBackbone",
    "default_patchmatchnet_weights",
]

log = logging.getLogger(__name__)

PATCHMATCHNET_FILE = Path("weights") / "patchmatchnet" / "patchmatchnet_dtu_module.pt"


# --------------------------------------------------------------------------- the distribution
def confidence_scale(confidence: Tensor, b_min: float, b_max: float) -> Tensor:
    """b / Δ = b_min + (1 - c) (b_max - b_min), with c clamped to [0, 1] (module docstring).

    Args:
        confidence: (...) confidence.

    Returns:
        (...) Laplacian scale in units of the hypothesis interval.
    """
    c = confidence.clamp(0.0, 1.0)
    return b_min + (1.0 - c) * (b_max - b_min)


def laplacian_prob(depths: Tensor, mu: Tensor, b: Tensor) -> Tensor:
    """A Laplace(mu, b) distribution discretized on per-pixel hypotheses (module docstring).

    P_k = F(e_{k+1}) - F(e_k) with bin edges halfway between hypotheses and open outer bins.
    Written as G(x) = F(x) - [x >= mu] (the signed tail, +-exp(-|x - mu|/b)/2) plus the step, so
    that far-away bins are differences of small numbers rather than of numbers near 1.

    Args:
        depths: (D, H, W) increasing hypotheses.
        mu: (H, W) predicted depth.
        b: (H, W) scale in depth units, > 0.

    Returns:
        (D, H, W) probabilities summing to 1 over D.
    """
    if depths.ndim != 3 or mu.shape != depths.shape[1:] or b.shape != mu.shape:
        raise ValueError(
            f"laplacian_prob: depths (D, H, W), mu and b (H, W); got {tuple(depths.shape)}, "
            f"{tuple(mu.shape)}, {tuple(b.shape)}"
        )
    dt = torch.float64 if depths.dtype == torch.float64 else torch.float32
    d = depths.to(dt)
    mu = mu.to(dt)[None]
    b = b.to(dt).clamp_min(torch.finfo(dt).tiny)[None]
    mid = 0.5 * (d[1:] + d[:-1])  # (D-1, H, W) inner edges
    z = (mid - mu) / b
    above = z >= 0
    g = torch.where(above, -0.5 * torch.exp(-z.clamp_min(0)), 0.5 * torch.exp(z.clamp_max(0)))
    step = above.to(dt)
    # outer edges: G(-inf) = 0 with step 0; G(+inf) = 0 with step 1
    zeros = torch.zeros_like(mu)
    g = torch.cat([zeros, g, zeros])
    step = torch.cat([zeros, step, torch.ones_like(mu)])
    F_edges = g + step
    p = (F_edges[1:] - F_edges[:-1]).clamp_min(0)
    p = p / p.sum(0, keepdim=True)
    return p.to(depths.dtype)


# --------------------------------------------------------------------------- the adapter
@dataclass
class AdapterConfig:
    """Options of a depth + confidence adapter."""

    ndepths: tuple[int, int, int] = STAGE_DEPTHS
    """Hypotheses per stage (METHOD.md 0)."""
    width_mode: str = "paper"
    """Finer-stage search width, "paper" or "released" (`svolsdf.mvs.hypotheses`)."""
    inverse_depth: bool = False
    """Stage-1 planes uniform in inverse depth (METHOD.md 2.5)."""
    max_sources: int = MAX_SOURCES
    """Source views per reference, the best by pair score (`select_sources`, METHOD.md 1.4: at
    most 4, as released); <= 0: every other loaded view."""
    b_min: float = 0.5
    """Laplacian scale at confidence 1, in hypothesis intervals."""
    b_max: float = 4.0
    """Laplacian scale at confidence 0, in hypothesis intervals."""
    net_size: tuple[int, int] | None = None
    """(W, H) at which the network runs; None: the scene's working size."""
    device: str = "cpu"
    """Torch device of the network."""


class DepthConfidenceAdapter(MVSBackbone):
    """An `MVSBackbone` from a network predicting per-pixel depth and confidence.

    Subclasses implement :meth:`predict`. Volumes are at `stage_cameras` sizes (stage 3 at the
    working size), world z-depth.
    """

    config_class = AdapterConfig

    def __init__(self, config: AdapterConfig | None = None, **cfg):
        self.config = config or AdapterConfig(**cfg)
        interval_ratio(2, self.config.width_mode)  # validates the name
        if not 0 < self.config.b_min <= self.config.b_max:
            raise InputError(
                f"Laplacian scales must satisfy 0 < b_min <= b_max, got "
                f"{self.config.b_min}, {self.config.b_max}"
            )
        self._pred: dict = {}
        self._pred_key = None

    @abstractmethod
    def predict(self, images: Tensor, cameras: Cameras, depth_range: tuple[float, float]
                ) -> tuple[Tensor, Tensor]:
        """Depth and confidence of the first view.

        Args:
            images: (V, 3, H, W) in [0, 1], the reference first, then its sources.
            cameras: V cameras at (W, H), world units.
            depth_range: the reference's (near, far) z-depth.

        Returns:
            depth (H, W) world z-depth and confidence (H, W) in [0, 1].
        """

    def prediction(self, scene: Scene, vid: int) -> tuple[Tensor, Tensor]:
        """Cached :meth:`predict` of view ``vid`` at the working size: depth, confidence (H, W)."""
        key = (id(scene.images), tuple(scene.view_ids))
        if self._pred_key != key or scene.images is None:
            if scene.images is None:
                raise InputError(f"{scene.path}: the scene was loaded without images")
            self._pred, self._pred_key = {"images": scene.images}, key  # keep id() alive
        if vid not in self._pred:
            i = scene.index(vid)
            order = [i] + [scene.index(v) for v in
                           select_sources(scene, vid, self.config.max_sources)]
            images = scene.images[order].to(self.config.device, torch.float32)
            cams = scene.cameras[order]
            W, H = self.config.net_size or (scene.width, scene.height)
            if (W, H) != (scene.width, scene.height):
                images = F.interpolate(images, size=(H, W), mode="bicubic", align_corners=False,
                                       antialias=H < scene.height).clamp_(0, 1)
                cams = cams.resize(W, H)
            near, far = (float(x) for x in scene.depth_range[i])
            depth, conf = self.predict(images, cams.to(self.config.device, torch.float32),
                                       (near, far))
            depth = upsample_depth(depth.float().cpu(), scene.width, scene.height)
            conf = upsample_depth(conf.float().cpu(), scene.width, scene.height)
            self._pred[vid] = (depth, conf)
        return self._pred[vid]

    @torch.no_grad()
    def stage(
        self,
        k: int,
        scene: Scene,
        ref_ids: list[int] | None = None,
        guide_depth: dict[int, Tensor] | None = None,
        prev: dict[int, ProbabilityVolume] | None = None,
    ) -> list[ProbabilityVolume]:
        """Stage ``k``'s volumes (see `MVSBackbone.stage`) around the network's depth.

        Hypotheses: stage 1 planes over the depth range; stages 2-3 centred on
        ``guide_depth[view]`` or ``prev[view].depth`` (METHOD.md 2.5). Probabilities:
        :func:`laplacian_prob` with scale from the confidence (module docstring).
        """
        if k not in (1, 2, 3):
            raise ValueError(f"stage must be 1, 2 or 3, got {k}")
        ref_ids = list(scene.view_ids if ref_ids is None else ref_ids)
        check_depth_ranges(scene, ref_ids)
        cams = stage_cameras(scene.cameras, k)
        Wk, Hk = cams.width, cams.height
        D = self.config.ndepths[k - 1]
        out = []
        for vid in ref_ids:
            i = scene.index(vid)
            near, far = (float(x) for x in scene.depth_range[i])
            depth, conf = self.prediction(scene, vid)
            mu = _resize(depth, Wk, Hk)
            c = _resize(conf, Wk, Hk)
            if k == 1:
                depths = plane_hypotheses(near, far, D, Hk, Wk, self.config.inverse_depth)
            else:
                if guide_depth is not None and vid in guide_depth:
                    centre = torch.as_tensor(guide_depth[vid], dtype=torch.float32)
                elif prev is not None and vid in prev:
                    centre = prev[vid].depth.float()
                else:
                    raise ValueError(
                        f"stage {k} of view {vid} needs a guide depth or the previous volume"
                    )
                centre = _resize(centre.cpu(), Wk, Hk)
                r = interval_ratio(k, self.config.width_mode)
                depths = guided_hypotheses(centre, D, r * base_interval(near, far))
            spacing = (depths[-1] - depths[0]) / (D - 1)
            b = spacing * confidence_scale(c, self.config.b_min, self.config.b_max)
            prob = laplacian_prob(depths, mu, b)
            out.append(volume_from_prob(prob, depths, cams[i], vid, k,
                                        self.config.inverse_depth and k == 1))
        return out


def _resize(x: Tensor, W: int, H: int) -> Tensor:
    """(h, w) -> (H, W) bilinear, align_corners=False (antialiased when shrinking)."""
    if x.shape == (H, W):
        return x
    return F.interpolate(x[None, None].float(), size=(H, W), mode="bilinear",
                         align_corners=False, antialias=H < x.shape[0])[0, 0]


# --------------------------------------------------------------------------- PatchmatchNet
def default_patchmatchnet_weights() -> Path | None:
    """``../shared/weights/patchmatchnet/patchmatchnet_dtu_module.pt`` beside the repository or
    the working directory, if it exists."""
    repo = Path(__file__).resolve().parents[3]
    for root in (repo.parent / "shared", Path.cwd().parent / "shared", Path.cwd() / "shared"):
        p = root / PATCHMATCHNET_FILE
        if p.is_file():
            return p
    return None


@register_backbone("patchmatchnet")
class PatchmatchNetBackbone(DepthConfidenceAdapter):
    """PatchmatchNet (TorchScript, DTU-trained) through the Laplacian adapter.

    The module's ``forward(images: list[(1, 3, H, W)] in [0, 1], intrinsics (1, V, 3, 3),
    extrinsics (1, V, 4, 4) world-to-camera, depth_min (1,), depth_max (1,))`` returns the depth
    (1, 1, H, W), the photometric confidence (1, H, W) and per-stage depths. It resizes inputs to
    multiples of 8 itself; we do that beforehand with our camera convention.
    """

    def __init__(self, module, config: AdapterConfig | None = None, **cfg):
        super().__init__(config, **cfg)
        self.module = module.to(self.config.device).eval()

    @classmethod
    def create(cls, weights=None, **cfg) -> PatchmatchNetBackbone:
        path = Path(weights) if weights is not None else default_patchmatchnet_weights()
        if path is None:
            raise InputError(
                "the 'patchmatchnet' backbone needs --weights PATH (a TorchScript PatchmatchNet, "
                f"e.g. ../shared/{PATCHMATCHNET_FILE.as_posix()}), and none was found there"
            )
        if not path.is_file():
            raise InputError(f"{path}: PatchmatchNet weights file not found")
        config = AdapterConfig(**cfg)
        try:
            module = torch.jit.load(str(path), map_location=config.device)
        except Exception as e:  # noqa: BLE001 - any load failure is bad input
            raise InputError(f"{path}: cannot load as a TorchScript module ({e})") from None
        if not hasattr(module, "patchmatch_num_sample"):
            raise InputError(f"{path}: a TorchScript module, but not PatchmatchNet")
        return cls(module, config)

    @torch.no_grad()
    def predict(self, images: Tensor, cameras: Cameras, depth_range: tuple[float, float]
                ) -> tuple[Tensor, Tensor]:
        V, _, H, W = images.shape
        W8, H8 = max(8, round(W / 8) * 8), max(8, round(H / 8) * 8)
        if (W8, H8) != (W, H):
            images = F.interpolate(images, size=(H8, W8), mode="bicubic",
                                   align_corners=False).clamp_(0, 1)
            cameras = cameras.resize(W8, H8)
        dev = images.device
        K = cameras.K.float().clone()[None]  # the module scales its intrinsics in place
        E = cameras.w2c.float()[None]
        near, far = depth_range
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # torch.meshgrid indexing notice
            depth, conf, _ = self.module(
                [images[v: v + 1] for v in range(V)], K, E,
                torch.tensor([near], dtype=torch.float32, device=dev),
                torch.tensor([far], dtype=torch.float32, device=dev),
            )
        depth, conf = depth[0, 0], conf[0]
        if (W8, H8) != (W, H):
            depth, conf = upsample_depth(depth, W, H), upsample_depth(conf, W, H)
        return depth, conf
