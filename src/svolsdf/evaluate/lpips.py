"""LPIPS v0.1 (Zhang et al., CVPR 2018) with AlexNet or VGG16 features, in plain torch.

d(x, y) = sum_l mean_{h,w} w_l . (f_l(x) / |f_l(x)| - f_l(y) / |f_l(y)|)^2, where f_l are the
backbone's ReLU activations at five depths, normalized to unit length over channels, and w_l the
learned non-negative 1x1 "linear" heads. Inputs are RGB in [-1, 1], shifted and scaled by the
LPIPS ScalingLayer constants first. The paper's novel-view metric uses VGG (docs/method.md 8.3).

The weights are what the ``lpips`` package uses: its v0.1 linear heads (``lin0..4``; the same
files, shipped in ``lpips_heads/`` with their license, their SHA-256 checked on load) and
torchvision's ImageNet backbone (``features.N.weight/bias``), which torchvision fetches into the
torch cache (``torch.hub.get_dir()/checkpoints``, ``$TORCH_HOME``) on first use. So does
`backbone_file` (`svolsdf.io.weights.cached_weights`): once, with a message, its SHA-256
checked against the published one (a file that differs is not kept). The backbones below
reproduce torchvision's layer indices, so its state dicts load unchanged without torchvision.
Where, in order:

1. ``weights`` (``svolsdf evaluate --lpips-weights``): a whole LPIPS state dict (heads and
   backbone: ``{alexnet,vgg16}_lpips_v0.1.pth``, or a folder of them), or torchvision's backbone
   file alone (``vgg16-397923af.pth``, checked by SHA-256) for a machine without internet;
2. ``$SVOLSDF_LPIPS_BACKBONE``: such a backbone file;
3. ``$SVOLSDF_LPIPS_DIR`` or a ``shared/weights/lpips`` folder beside the checkout
   (`default_lpips_dir`): whole state dicts;
4. the torch cache, downloading the backbone there the first time (`BACKBONES`).
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
import torch.nn as nn
from torch import Tensor

from svolsdf.errors import InputError
from svolsdf.io.weights import PublishedWeights, cached_weights, is_published, sha256

__all__ = ["BACKBONES", "BACKBONE_ENV", "HEADS", "LPIPS", "backbone_file", "default_lpips_dir",
           "lpips_distance"]

_FILES = {"alex": "alexnet_lpips_v0.1.pth", "vgg": "vgg16_lpips_v0.1.pth"}
# Slice ends into `features` after each tapped ReLU (torchvision layer indices).
_TAPS = {"alex": (2, 5, 8, 10, 12), "vgg": (4, 9, 16, 23, 30)}
_CHANNELS = {"alex": (64, 192, 384, 256, 256), "vgg": (64, 128, 256, 512, 512)}
# LPIPS ScalingLayer: x' = (x - shift) / scale, on inputs in [-1, 1].
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)


BACKBONES = {
    "alex": PublishedWeights(
        "LPIPS-alex: torchvision's alexnet", "alexnet-owt-7be5be79.pth",
        "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth",
        "7be5be791159472b1fbf3c69796f7cb30dca7ad8466c2df70058c37116cdee02", 244_408_911),
    "vgg": PublishedWeights(
        "LPIPS-vgg: torchvision's vgg16", "vgg16-397923af.pth",
        "https://download.pytorch.org/models/vgg16-397923af.pth",
        "397923af8e79cdbb6a7127f12361acd7a2f83e06b05044ddf496e83de57a5bf0", 553_433_881),
}
"""The backbones LPIPS v0.1 uses (torchvision's ``alexnet`` and ``vgg16`` IMAGENET1K_V1)."""

HEADS = {"alex": ("alex.pth", "df73285e35b22355a2df87cdb6b70b343713b667eddbda73e1977e0c860835c0"),
         "vgg": ("vgg.pth", "a78928a0af1e5f0fcb1f3b9e8f8c3a2a5a3de244d830ad5c1feddc79b8432868")}
"""net -> (file in ``lpips_heads/``, SHA-256): the ``lpips`` package's v0.1 linear heads."""

BACKBONE_ENV = "SVOLSDF_LPIPS_BACKBONE"
"""Environment variable naming a local copy of the backbone file (no download)."""


def _heads(net: str) -> dict[str, Tensor]:
    """The lpips package's v0.1 linear heads of ``net``, checked by SHA-256."""
    name, digest = HEADS[net]
    path = Path(__file__).with_name("lpips_heads") / name
    if not path.is_file() or sha256(path) != digest:
        raise InputError(f"{path}: the LPIPS {net} heads are missing or changed (expected "
                         f"SHA-256 {digest}); reinstall svolsdf")
    return torch.load(str(path), map_location="cpu", weights_only=True)


def _check_backbone(path: Path, net: str) -> None:
    """Refuse a backbone file that is not torchvision's published one."""
    spec = BACKBONES[net]
    if not is_published(path, spec):
        raise InputError(f"{path}: not torchvision's {spec.file} (SHA-256 {sha256(path)}, the "
                         f"published one {spec.sha256}, {spec.url}); give that file")


def backbone_file(net: str, progress: bool = True) -> Path:
    """torchvision's backbone file of ``net`` in the torch cache, downloaded there the first
    time (`svolsdf.io.weights.cached_weights`: a message, the SHA-256 checked).

    Raises:
        InputError: the download failed or is not the published file.
    """
    return cached_weights(BACKBONES[net], f"pass it with --lpips-weights FILE or "
                                          f"{BACKBONE_ENV}=FILE", progress=progress)


def _alexnet_features() -> nn.Sequential:
    """torchvision ``alexnet().features`` layer for layer (indices 0..12)."""
    return nn.Sequential(
        nn.Conv2d(3, 64, 11, stride=4, padding=2), nn.ReLU(inplace=False),
        nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(),
        nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(),
        nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(),
        nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(),
        nn.MaxPool2d(3, 2),
    )


def _vgg16_features() -> nn.Sequential:
    """torchvision ``vgg16().features`` layer for layer (indices 0..30)."""
    layers: list[nn.Module] = []
    c = 3
    for v in (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M",
              512, 512, 512, "M"):
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(c, int(v), 3, padding=1), nn.ReLU()]
            c = int(v)
    return nn.Sequential(*layers)


class _Lin(nn.Module):
    """1x1 head; ``model.0`` is LPIPS's (eval-time inactive) dropout, ``model.1`` the conv."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.model = nn.Sequential(nn.Identity(), nn.Conv2d(channels, 1, 1, bias=False))

    def forward(self, x: Tensor) -> Tensor:
        return self.model(x)


def default_lpips_dir() -> Path:
    """Find ``shared/weights/lpips``: $SVOLSDF_LPIPS_DIR, then ``../shared`` and ``./shared``
    relative to the current folder, then ``shared`` beside the repository checkout.

    Raises:
        InputError listing the places searched.
    """
    candidates = []
    if os.environ.get("SVOLSDF_LPIPS_DIR"):
        candidates.append(Path(os.environ["SVOLSDF_LPIPS_DIR"]))
    cwd = Path.cwd()
    repo = Path(__file__).resolve().parents[3]
    candidates += [cwd.parent / "shared" / "weights" / "lpips",
                   cwd / "shared" / "weights" / "lpips",
                   repo.parent / "shared" / "weights" / "lpips"]
    for c in candidates:
        if c.is_dir() and any((c / f).is_file() for f in _FILES.values()):
            return c
    raise InputError("LPIPS weights not found; looked in " + ", ".join(map(str, candidates))
                     + f" for {_FILES['alex']} / {_FILES['vgg']} (set SVOLSDF_LPIPS_DIR or "
                     "pass the weights path)")


class LPIPS(nn.Module):
    """LPIPS v0.1 distance module.

    Args:
        net: ``"alex"`` or ``"vgg"`` (the paper's evaluation uses ``"vgg"``).
        weights: a ``.pth`` file, or a folder holding ``alexnet_lpips_v0.1.pth`` /
            ``vgg16_lpips_v0.1.pth``; default `default_lpips_dir`.

    Example:
        >>> m = LPIPS("alex")                      # doctest: +SKIP
        >>> d = m(x * 2 - 1, y * 2 - 1)            # (B,) for x, y (B, 3, H, W) in [0, 1]
    """

    def __init__(self, net: str = "vgg", weights: str | Path | None = None) -> None:
        super().__init__()
        if net not in _FILES:
            raise InputError(f"LPIPS net must be 'alex' or 'vgg', got {net!r}")
        self.net = net
        from svolsdf.io.paths import input_file, input_path

        if weights is None and os.environ.get(BACKBONE_ENV):
            weights = input_file(os.environ[BACKBONE_ENV], "LPIPS backbone file", BACKBONE_ENV)
        if weights is not None:
            path = input_path(weights, "LPIPS weights file or folder")
        else:
            try:
                path = default_lpips_dir()
            except InputError:  # no whole state dicts: the heads with torchvision's backbone
                path = backbone_file(net)
        if path.is_dir():
            path = path / _FILES[net]
        path = input_file(path, f"LPIPS {net} weights file")
        self.features = _alexnet_features() if net == "alex" else _vgg16_features()
        for k, c in enumerate(_CHANNELS[net]):
            self.add_module(f"lin{k}", _Lin(c))
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1), persistent=False)
        try:
            sd = torch.load(str(path), map_location="cpu", weights_only=True)
        except Exception as e:
            raise InputError(f"{path}: cannot load LPIPS weights ({e})") from None
        if isinstance(sd, dict) and "features.0.weight" in sd and "lin0.model.1.weight" not in sd:
            # torchvision's backbone alone (its classifier unused): with the lpips heads
            _check_backbone(path, net)
            sd = {**{k: v for k, v in sd.items() if k.startswith("features.")}, **_heads(net)}
        missing, unexpected = self.load_state_dict(sd, strict=False)
        if missing or unexpected:
            raise InputError(f"{path}: not an LPIPS {net} v0.1 state dict (missing {missing}, "
                             f"unexpected {unexpected})")
        self.eval().requires_grad_(False)

    def forward(self, x: Tensor, y: Tensor) -> Tensor:
        """LPIPS distance.

        Args:
            x: (B, 3, H, W) float in [-1, 1].
            y: (B, 3, H, W) float in [-1, 1].

        Returns:
            (B,) distances.
        """
        if x.ndim != 4 or x.shape[1] != 3 or x.shape != y.shape:
            raise InputError(f"LPIPS expects two (B, 3, H, W) tensors, got {tuple(x.shape)} and "
                             f"{tuple(y.shape)}")
        h = torch.cat([x, y]).to(self.shift.dtype)
        h = (h - self.shift) / self.scale
        b = x.shape[0]
        total = torch.zeros(b, dtype=h.dtype, device=h.device)
        start = 0
        for k, end in enumerate(_TAPS[self.net]):
            try:
                h = self.features[start:end](h)
            except RuntimeError as e:  # pooling an empty map
                raise InputError(f"LPIPS-{self.net}: a {tuple(x.shape[-2:])} image is too small "
                                 f"for the backbone (at layer {k}: {e})") from None
            start = end
            if h.shape[-1] == 0 or h.shape[-2] == 0:
                raise InputError(f"LPIPS-{self.net}: a {tuple(x.shape[-2:])} image is too small "
                                 f"for the backbone (layer {k} is empty)")
            f = h / (h.pow(2).sum(dim=1, keepdim=True).sqrt() + 1e-10)
            d = (f[:b] - f[b:]) ** 2
            total = total + getattr(self, f"lin{k}")(d).mean(dim=(1, 2, 3))
        return total


@torch.no_grad()
def lpips_distance(pred: Tensor, gt: Tensor, model: LPIPS, mask: Tensor | None = None) -> float:
    """LPIPS of two [0, 1] images, composited on white when a mask is given (docs/method.md 8.3).

    Args:
        pred: (3, H, W) float in [0, 1].
        gt: (3, H, W) float in [0, 1].
        model: an `LPIPS` module (load it once, reuse it).
        mask: (1, H, W) or (H, W) object mask, or None.

    Returns:
        the distance.
    """
    from svolsdf.evaluate.images import composite_white

    if pred.ndim != 3 or pred.shape[0] != 3 or pred.shape != gt.shape:
        raise InputError(f"LPIPS expects two (3, H, W) images, got {tuple(pred.shape)} and "
                         f"{tuple(gt.shape)}")
    x = composite_white(pred, mask)[None] * 2 - 1
    y = composite_white(gt, mask)[None] * 2 - 1
    dev = model.shift.device
    return float(model(x.to(dev), y.to(dev))[0])
