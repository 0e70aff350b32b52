"""`ProbabilityVolume`: one reference view's depth distribution at one cascade stage."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from svolsdf.scene.cameras import Cameras

__all__ = ["ProbabilityVolume"]


@dataclass
class ProbabilityVolume:
    """Per-pixel depth hypotheses and their probabilities for one reference view and stage.

    Stage 1's fronto-parallel planes and stages 2-3's per-pixel ranges share this type
    (docs/architecture.md "Interfaces").

    Attributes:
        depths: (D, H, W) hypothesis z-depths in world units, increasing along D.
        prob: (D, H, W) probabilities, summing to 1 over D.
        depth: (H, W) the backbone's depth estimate: the expectation sum_k prob_k * depths_k
            (docs/method.md 2.4), or for the plane sweep by default the expectation around the most
            likely hypothesis (`svolsdf.mvs.backbone.mode_depth`).
        confidence: (H, W) photometric confidence in [0, 1] (docs/method.md 2.4, 4-bin sum).
        cameras: the reference camera (1 view) at the volume's resolution (W, H).
        view_id: the reference view id.
        stage: cascade stage, 1-based.
        inverse_depth: True when stage-1 planes are spaced uniformly in inverse depth
            (docs/method.md 2.5); the soft-consistency lookup (docs/method.md 3, step 6) follows it.
    """

    depths: Tensor
    prob: Tensor
    depth: Tensor
    confidence: Tensor
    cameras: Cameras
    view_id: int
    stage: int = 1
    inverse_depth: bool = False

    def __post_init__(self) -> None:
        if self.depths.ndim != 3 or self.prob.shape != self.depths.shape:
            raise ValueError(
                f"ProbabilityVolume: depths {tuple(self.depths.shape)} and prob "
                f"{tuple(self.prob.shape)} must both be (D, H, W)"
            )
        D, H, W = self.depths.shape
        if self.depth.shape != (H, W) or self.confidence.shape != (H, W):
            raise ValueError(
                f"ProbabilityVolume: depth {tuple(self.depth.shape)} and confidence "
                f"{tuple(self.confidence.shape)} must be (H, W) = ({H}, {W})"
            )
        if len(self.cameras) != 1 or (self.cameras.width, self.cameras.height) != (W, H):
            raise ValueError(
                f"ProbabilityVolume: camera must be one view at {W}x{H}, got "
                f"{len(self.cameras)} view(s) at {self.cameras.width}x{self.cameras.height}"
            )

    @property
    def num_depths(self) -> int:
        return self.depths.shape[0]

    def to(self, device=None) -> ProbabilityVolume:
        return ProbabilityVolume(
            self.depths.to(device), self.prob.to(device), self.depth.to(device),
            self.confidence.to(device), self.cameras.to(device), self.view_id, self.stage,
            self.inverse_depth,
        )

    def save(self, path) -> None:
        """Write a compressed .npz (prob as float16) atomically.

        Deflate level 1 instead of `numpy.savez_compressed`'s 6: half the time for files
        within 1-4 % of the size (three views' stages 1-3 at 768x576: ~4.4 s less per run).
        `numpy.load` reads it as any .npz.
        """
        import os
        import zipfile

        import numpy as np

        arrays = {
            "depths": self.depths.float().cpu().numpy(),
            "prob": self.prob.to(torch.float16).cpu().numpy(),
            "depth": self.depth.float().cpu().numpy(),
            "confidence": self.confidence.float().cpu().numpy(),
            "K": self.cameras.K[0].double().cpu().numpy(),
            "w2c": self.cameras.w2c[0].double().cpu().numpy(),
            "size": np.array([self.cameras.width, self.cameras.height]),
            "meta": np.array([self.view_id, self.stage, int(self.inverse_depth)]),
        }
        tmp = f"{path}.tmp.npz"
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
            for name, arr in arrays.items():
                with zf.open(f"{name}.npy", "w", force_zip64=True) as f:
                    np.lib.format.write_array(f, arr, allow_pickle=False)
        os.replace(tmp, path)

    @classmethod
    def load(cls, path) -> ProbabilityVolume:
        """Read a volume written by :meth:`save`."""
        import numpy as np

        z = np.load(path)
        prob = torch.from_numpy(z["prob"].astype(np.float32))
        prob = prob / prob.sum(0, keepdim=True).clamp_min(1e-12)
        W, H = (int(v) for v in z["size"])
        cams = Cameras(
            torch.from_numpy(z["K"])[None].float(), torch.from_numpy(z["w2c"])[None].float(), W, H
        )
        view_id, stage, inv = (int(v) for v in z["meta"])
        return cls(
            torch.from_numpy(z["depths"]), prob, torch.from_numpy(z["depth"]),
            torch.from_numpy(z["confidence"]), cams, view_id, stage, bool(inv),
        )
