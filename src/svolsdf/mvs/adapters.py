"""Backbones that wrap a depth + confidence network into probability volumes.

A network that predicts one depth d̂ and a confidence c in [0, 1] per pixel (PatchmatchNet and its
kind) has no probability volume. `DepthConfidenceAdapter` makes one on each stage's hypotheses
(docs/method.md 2.5) as a discretized Laplacian centred on d̂ whose scale grows as the confidence
drops:

    b = Δ · (b_min + (1 - c) (b_max - b_min))

where Δ is the stage's hypothesis spacing at that pixel, (d_last - d_first)/(D - 1), so b is
"in units of the hypothesis interval" at every stage. The hypotheses d_0 < ... < d_{D-1} split the
depth axis into bins with edges e_0 = -inf, e_k = (d_{k-1} + d_k)/2, e_D = +inf, and

    P_k = F(e_{k+1}) - F(e_k),   F = CDF of Laplace(d̂, b),

so the probabilities sum to 1 exactly, stay finite for any b (no exp underflow to 0/0), and a d̂
outside the hypothesis range puts its mass on the nearest end bin (the open outer bins). The
volume's depth and confidence are then the expectation and the 4-bin sum (docs/method.md 2.4), like
every backbone's.

The network runs once per reference view (at the scene's working size, or ``net_size``); each stage
only rebuilds the distribution on its own hypotheses, centred on the guide depth or the previous
stage's depth at stages 2-3 like the cascade.

A network that can start from a depth map (``can_start_from_depth``: PatchmatchNet) is also run a
second time when stage 2 gets a guide depth (the optimized surface's rendered depth, docs/method.md
6.1), starting from that guide instead of its own initialisation (``AdapterConfig.guide_network``).
That is this family's form of S-VolSDF's guidance: the surface replaces the network's coarse
estimate, as it replaces CasMVSNet's stage-1 depth. Stages 2 and 3 of that cascade then centre
their Laplacian on the guided prediction. Without it, a guide only moves the hypotheses, and the
distribution still sits on the network's unguided depth (its mass on the end bins where the two
disagree).
"""

from __future__ import annotations

import hashlib
import logging
import warnings
from abc import abstractmethod
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from svolsdf.errors import InputError
from svolsdf.io.progress import progress_bar
from svolsdf.io.weights import PublishedWeights, cached_weights, is_published
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
    "PATCHMATCHNET",
    "PatchmatchNetBackbone",
    "default_patchmatchnet_weights",
]

log = logging.getLogger(__name__)

PATCHMATCHNET_FILE = Path("weights") / "patchmatchnet" / "patchmatchnet_dtu_module.pt"

PATCHMATCHNET = PublishedWeights(
    "PatchmatchNet (DTU, TorchScript)", "patchmatchnet_module_000007-ce053605.pt",
    "https://raw.githubusercontent.com/FangjinhuaWang/PatchmatchNet/"
    "8dc6cb40bdb7053e856598b378425c76a9dcf5e0/checkpoints/module_000007.pt",
    "ce053605b4f22e1478dcc82e844a567e0aabe8415bb7f89c49382ef2e21dd44e", 1_123_557)
"""The authors' DTU-trained TorchScript module (MIT license), fetched into the torch cache
when no ``--weights`` is given (`svolsdf.io.weights.cached_weights`)."""


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
    """Hypotheses per stage (docs/method.md 0)."""
    width: str = "paper"
    """Finer-stage search width, "paper", "released" or "half-default"
    (`svolsdf.mvs.hypotheses.WIDTHS`)."""
    inverse_depth: bool = False
    """Stage-1 planes uniform in inverse depth (docs/method.md 2.5)."""
    max_sources: int = MAX_SOURCES
    """Source views per reference, the best by pair score (`select_sources`, docs/method.md 1.4: at
    most 4, as released); <= 0: every other loaded view."""
    b_min: float = 0.5
    """Laplacian scale at confidence 1, in hypothesis intervals."""
    b_max: float = 4.0
    """Laplacian scale at confidence 0, in hypothesis intervals."""
    net_size: tuple[int, int] | None = None
    """(W, H) at which the network runs; None: the scene's working size."""
    device: str = "cpu"
    """Torch device of the network."""
    seed: int = 0
    """A network that draws random initial samples (PatchmatchNet) draws them for view ``v``
    under the seed ``seed + v``, with the global random state left as it was: runs repeat."""
    guide_network: bool = True
    """A network that can start from a depth map (PatchmatchNet) reruns from the guide depth
    when stage 2 gets one, and stages 2-3 follow that prediction (module docstring). False: the
    network runs once per view, unguided, and the guide only centres the hypotheses. Points
    Chamfer of the pipeline with PatchmatchNet 16-19 % lower on three synthetic scenes and 12 %
    on dtu_scan65 (benchmarks/results/history/patchmatchnet_guided.md)."""


class DepthConfidenceAdapter(MVSBackbone):
    """An `MVSBackbone` from a network predicting per-pixel depth and confidence.

    Subclasses implement :meth:`predict`. Volumes are at `stage_cameras` sizes (stage 3 at the
    working size), world z-depth.
    """

    config_class = AdapterConfig
    signature_names = {"width": "width_mode", "guide_network": "guide_init"}
    can_start_from_depth: bool = False
    """True when :meth:`predict` uses ``init_depth`` (see `AdapterConfig.guide_network`)."""

    def __init__(self, config: AdapterConfig | None = None, **cfg):
        self.config = config or AdapterConfig(**cfg)
        interval_ratio(2, self.config.width)  # validates the name
        if not 0 < self.config.b_min <= self.config.b_max:
            raise InputError(
                f"Laplacian scales must satisfy 0 < b_min <= b_max, got "
                f"{self.config.b_min}, {self.config.b_max}"
            )
        self._pred: dict = {}
        self._pred_key = None
        # view id -> (the last volume made for it, the depth and confidence its Laplacian sits
        # on): a stage whose ``prev`` is that volume keeps following the same prediction
        self._made: dict[int, tuple[ProbabilityVolume, Tensor, Tensor]] = {}

    @abstractmethod
    def predict(self, images: Tensor, cameras: Cameras, depth_range: tuple[float, float],
                init_depth: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Depth and confidence of the first view.

        Args:
            images: (V, 3, H, W) in [0, 1], the reference first, then its sources.
            cameras: V cameras at (W, H), world units.
            depth_range: the reference's (near, far) z-depth.
            init_depth: optional (H, W) world z-depth to start from instead of the network's
                own initialisation; only passed when ``can_start_from_depth``.

        Returns:
            depth (H, W) world z-depth and confidence (H, W) in [0, 1].
        """

    def prediction(self, scene: Scene, vid: int, guide: Tensor | None = None
                   ) -> tuple[Tensor, Tensor]:
        """Cached :meth:`predict` of view ``vid`` at the working size: depth, confidence (H, W).

        Args:
            guide: optional (H', W') world z-depth the network starts from (resized to the
                size the network runs at); only used when ``can_start_from_depth`` and
                ``config.guide_network``, else the unguided prediction is returned.
        """
        key = (id(scene.images), tuple(scene.view_ids))
        if self._pred_key != key or scene.images is None:
            if scene.images is None:
                raise InputError(f"{scene.path}: the scene was loaded without images")
            self._pred, self._pred_key = {"images": scene.images}, key  # keep id() alive
        use_guide = guide is not None and self.can_start_from_depth and self.config.guide_network
        cache = vid
        if use_guide:
            guide = torch.as_tensor(guide, dtype=torch.float32).cpu()
            cache = (vid, hashlib.blake2b(guide.numpy().tobytes(), digest_size=16).hexdigest())
        if cache not in self._pred:
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
            init = None
            if use_guide:
                init = F.interpolate(guide[None, None], size=(H, W), mode="nearest")[0, 0]
                init = init.to(self.config.device)
            dev = torch.device(self.config.device)
            with torch.random.fork_rng(devices=[dev] if dev.type == "cuda" else []):
                torch.manual_seed(self.config.seed + int(vid))
                depth, conf = self.predict(images, cams.to(self.config.device, torch.float32),
                                           (near, far),
                                           **({"init_depth": init} if use_guide else {}))
            depth = upsample_depth(depth.float().cpu(), scene.width, scene.height)
            conf = upsample_depth(conf.float().cpu(), scene.width, scene.height)
            self._pred[cache] = (depth, conf)
        return self._pred[cache]

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
        ``guide_depth[view]`` or ``prev[view].depth`` (docs/method.md 2.5). Probabilities:
        :func:`laplacian_prob` with scale from the confidence (module docstring), on the
        network's prediction: the guided one (`AdapterConfig.guide_network`) when this stage has a
        guide, or when ``prev[view]`` is a volume this adapter made from the guided one; else
        the unguided one.
        """
        if k not in (1, 2, 3):
            raise ValueError(f"stage must be 1, 2 or 3, got {k}")
        ref_ids = list(scene.view_ids if ref_ids is None else ref_ids)
        check_depth_ranges(scene, ref_ids)
        cams = stage_cameras(scene.cameras, k)
        Wk, Hk = cams.width, cams.height
        D = self.config.ndepths[k - 1]
        out = []
        for vid in progress_bar(ref_ids, desc=f"MVS stage {k} ({self.name})"):
            i = scene.index(vid)
            near, far = (float(x) for x in scene.depth_range[i])
            made = self._made.get(vid)
            if k > 1 and guide_depth is not None and vid in guide_depth:
                depth, conf = self.prediction(scene, vid, guide=guide_depth[vid])
            elif k > 1 and prev is not None and made is not None and prev.get(vid) is made[0]:
                depth, conf = made[1], made[2]
            else:
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
                r = interval_ratio(k, self.config.width)
                depths = guided_hypotheses(centre, D, r * base_interval(near, far))
            spacing = (depths[-1] - depths[0]) / (D - 1)
            b = spacing * confidence_scale(c, self.config.b_min, self.config.b_max)
            prob = laplacian_prob(depths, mu, b)
            out.append(volume_from_prob(prob, depths, cams[i], vid, k,
                                        self.config.inverse_depth and k == 1))
            self._made[vid] = (out[-1], depth, conf)
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

    With ``init_depth`` the same submodules run in the same order as that forward, except that
    the coarsest PatchMatch stage (1/8 resolution) gets the depth to start from, so its first
    iteration samples around it (``patchmatch_num_sample`` inverse-depth offsets) instead of
    uniformly over [depth_min, depth_max] (:meth:`_forward_from`). The module's forward has no
    argument for it; nothing is re-implemented but the loop over its stages.
    """

    can_start_from_depth = True

    def __init__(self, module, config: AdapterConfig | None = None, **cfg):
        super().__init__(config, **cfg)
        self.module = module.to(self.config.device).eval()

    @classmethod
    def create(cls, weights=None, **cfg) -> PatchmatchNetBackbone:
        from svolsdf.io.paths import input_file, user_path


        path = user_path(weights) if weights is not None else default_patchmatchnet_weights()
        if path is None:  # the published module, once into the torch cache
            path = cached_weights(PATCHMATCHNET, "pass it with --weights FILE")
        path = input_file(path, "PatchmatchNet weights file")
        if weights is not None and not is_published(path, PATCHMATCHNET):
            log.info("%s is not the published PatchmatchNet module (%s); used as given", path,
                     PATCHMATCHNET.url)
        config = AdapterConfig(**cfg)
        load = getattr(getattr(torch, "jit", None), "load", None)
        if load is None:  # TorchScript is deprecated; docs/dependencies.md
            raise InputError(
                f"{path}: torch {torch.__version__} has no torch.jit.load to read the TorchScript "
                "PatchmatchNet weights; install a torch that has it (2.1-2.13 are tested) or use "
                "--backbone casmvsnet / planesweep (docs/dependencies.md)")
        try:
            with warnings.catch_warnings():
                # "torch.jit.load is deprecated": the weights exist only as TorchScript;
                # docs/dependencies.md says what replaces it
                warnings.simplefilter("ignore", DeprecationWarning)
                module = load(str(path), map_location=config.device)
        except Exception as e:  # noqa: BLE001 - any load failure is bad input
            raise InputError(f"{path}: cannot load as a TorchScript module ({e})") from None
        if not hasattr(module, "patchmatch_num_sample"):
            raise InputError(f"{path}: a TorchScript module, but not PatchmatchNet")
        return cls(module, config)

    @torch.no_grad()
    def predict(self, images: Tensor, cameras: Cameras, depth_range: tuple[float, float],
                init_depth: Tensor | None = None) -> tuple[Tensor, Tensor]:
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
        d_min = torch.tensor([near], dtype=torch.float32, device=dev)
        d_max = torch.tensor([far], dtype=torch.float32, device=dev)
        imgs = [images[v: v + 1] for v in range(V)]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # torch.meshgrid indexing notice
            if init_depth is None:
                depth, conf, _ = self.module(imgs, K, E, d_min, d_max)
            else:
                init = F.interpolate(init_depth.float()[None, None], size=(H8 // 8, W8 // 8),
                                     mode="nearest").clamp(near, far)
                depth, conf = self._forward_from(imgs, K, E, d_min, d_max, init)
        depth, conf = depth[0, 0], conf[0]
        if (W8, H8) != (W, H):
            depth, conf = upsample_depth(depth, W, H), upsample_depth(conf, W, H)
        return depth, conf

    def _forward_from(self, images: list[Tensor], K: Tensor, E: Tensor, d_min: Tensor,
                      d_max: Tensor, init: Tensor) -> tuple[Tensor, Tensor]:
        """The module's forward (eval mode), its coarsest PatchMatch stage started at ``init``.

        Args:
            images: V tensors (1, 3, H, W), H and W multiples of 8, the reference first.
            K: (1, V, 3, 3) intrinsics at (W, H); E: (1, V, 4, 4) world-to-camera.
            d_min, d_max: (1,) the reference's depth range.
            init: (1, 1, H/8, W/8) z-depth within the range, or an empty tensor: the
                forward's own random initialisation (the same result as the forward for the
                same random state).

        Returns:
            depth (1, 1, H, W) and photometric confidence (1, H, W), as the forward's.
        """
        m = self.module
        feats = [m.feature(img) for img in images]  # each {stage: (1, C, H_s, W_s)}
        depth, view_weights, score = init, torch.empty(0), torch.empty(0)
        scale = 0.125
        for stage in (3, 2, 1):  # 1/8, 1/4, 1/2 resolution
            K_s = K.clone()
            K_s[:, :, :2] *= scale
            proj = E.clone()
            proj[:, :, :3, :4] = K_s @ E[:, :, :3, :4]
            projs = proj.unbind(1)
            scale *= 2
            depths, score, view_weights = getattr(m, f"patchmatch_{stage}")(
                feats[0][stage], [f[stage] for f in feats[1:]], projs[0], list(projs[1:]),
                d_min, d_max, depth, view_weights)
            depth = depths[-1].detach()
            if stage > 1:
                depth = F.interpolate(depth, scale_factor=2.0, mode="nearest")
                view_weights = F.interpolate(view_weights, scale_factor=2.0, mode="nearest")
        depth = m.upsample_net(images[0], depth, d_min, d_max)
        # photometric confidence as the forward computes it: the last stage's score summed over
        # the 4 samples around its regressed sample index
        n = score.shape[1]
        s4 = F.avg_pool3d(F.pad(score[:, None], (0, 0, 0, 0, 1, 2)), (4, 1, 1), stride=1)[:, 0] * 4
        idx = (score * torch.arange(n, dtype=score.dtype, device=score.device).view(1, -1, 1, 1)
               ).sum(1, keepdim=True).long().clamp(0, n - 1)
        conf = F.interpolate(torch.gather(s4, 1, idx), size=depth.shape[-2:], mode="nearest")
        return depth, conf[:, 0]
